//! A rough, ignored timing of what logging adds to a step of N = 100 copters (the criterion
//! bench `cargo bench -p twinswarm --bench log` is the measurement of record):
//!
//! `cargo test -p bridge --test log_cost -- --ignored --nocapture`

use std::time::Instant;

use bridge::log::{LogMeta, Logger};
use sim_core::{scene, step};

#[test]
#[ignore = "timing, not a check: run by hand"]
fn logging_cost_for_100_copters() {
    let world = scene::compile(&scene::grid_swarm(100, 2.0, 0.8, true)).unwrap();
    let inputs = world.initial_inputs();
    let dir = std::env::temp_dir().join(format!("twinswarm-log-cost-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let steps = 100;
    let mut results = Vec::new();
    for logging in [false, true, false, true] {
        let mut state = world.initial_state();
        for _ in 0..20 {
            step(&world, &mut state, &inputs);
        }
        let mut log = logging.then(|| Logger::create(&dir.join("cost.mcap"), &world, "", LogMeta::default()).unwrap());
        let t0 = Instant::now();
        for _ in 0..steps {
            let r = step(&world, &mut state, &inputs);
            if let Some(l) = &mut log {
                l.log_step(&world, &state, &inputs, &r).unwrap();
            }
        }
        let stepping = t0.elapsed().as_secs_f64() / steps as f64;
        let finish_start = Instant::now();
        let bytes = log.map(|l| {
            let s = l.finish().unwrap();
            std::fs::metadata(&s.path).unwrap().len()
        });
        let drain = finish_start.elapsed().as_secs_f64();
        println!(
            "logging {logging:5}: {:.3} ms per step; draining the queue and finishing took {:.1} ms; file {:?} bytes",
            stepping * 1e3,
            drain * 1e3,
            bytes
        );
        results.push(stepping);
    }
    println!("overhead: {:+.1} % (second pair)", (results[3] / results[2] - 1.0) * 100.0);
    let _ = std::fs::remove_dir_all(&dir);
}
