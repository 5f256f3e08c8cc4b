//! Digests of a set of scenes that cover the model's paths, on one and two threads (or the
//! thread counts given): an optimisation that must keep the bits keeps every line of this
//! output, and every thread count gives one digest per scene.
//!
//! ```text
//! cargo run --release -p sim-core --example same_bits -- [SIM_SECONDS] [THREADS] > after.txt
//! diff before.txt after.txt
//! cargo run --release -p sim-core --example same_bits -- 20 1,2,4,8,16
//! ```
//!
//! Each line: the scene, the thread count, the number of crashed copters and an FNV-1a digest
//! over every copter's [`sim_core::CopterState::digest`] in id order.

use sim_core::scene::{self, SceneSpec};
use sim_core::sensors::{CrosstalkPhase, SonarSchedule};
use sim_core::{AirframeSpec, step};

fn scenes() -> Vec<(&'static str, SceneSpec)> {
    let dense = |n| scene::dense_swarm(n, 1.5, true, 10, 0);
    let mut together = dense(200);
    together.sensors.sonar.schedule = SonarSchedule::Together;
    together.sensors.crosstalk.cycle_s = 0.049;
    let mut sync = scene::cruising_swarm(100, 1);
    sync.sensors.crosstalk.phase = CrosstalkPhase::Synchronous;
    let mut wide = dense(200);
    wide.sensors.sonar.opening_deg = 70.0;
    let mut pillars = scene::dense_swarm(150, 1.5, false, 40, 3);
    pillars.sensors.noise = false;
    // Pairs one above the other: downwash and the IR on a copter below.
    let mut stacked = scene::cruising_swarm(100, 1);
    for k in (1..stacked.copters.len()).step_by(2) {
        let below = stacked.copters[k - 1].clone();
        let c = &mut stacked.copters[k];
        c.start.pos_m = [below.start.pos_m[0] + 0.3, below.start.pos_m[1]];
        (c.start.yaw_deg, c.command.yaw_deg) = (below.start.yaw_deg, below.command.yaw_deg);
        c.start.z_m = Some(1.6);
        c.command.height_m = 1.6;
    }
    let mut ideal = dense(100);
    ideal.sensors.estimator.ideal = true;
    let mut poisson = dense(100);
    let af = AirframeSpec { particle_noise: sim_core::airframe::ParticleNoise::Poisson, ..Default::default() };
    poisson.airframes.insert("poisson".into(), af);
    for c in poisson.copters.iter_mut().step_by(3) {
        c.airframe = scene::AirframeRef::Named("poisson".into());
    }
    vec![
        ("dense", dense(300)),
        ("cruise", scene::cruising_swarm(150, 1)),
        ("together", together),
        ("synchronous", sync),
        ("wide-sonar", wide),
        ("pillars-no-noise", pillars),
        ("stacked", stacked),
        ("ideal", ideal),
        ("poisson-mix", poisson),
    ]
}

fn main() {
    let seconds: f64 = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(20.0);
    let threads: Vec<usize> = match std::env::args().nth(2) {
        Some(list) => list.split(',').map(|t| t.trim().parse().expect("THREADS: counts such as 1,2,4")).collect(),
        None => vec![1, 2],
    };
    let mut unlike = Vec::new();
    for (name, mut spec) in scenes() {
        let mut first = None;
        for &threads in &threads {
            spec.sim.threads = threads;
            let world = scene::compile(&spec).expect("scene compiles");
            let mut state = world.initial_state();
            let inputs = world.initial_inputs();
            let ticks = (seconds / world.params.control_dt_s).round() as u64;
            for _ in 0..ticks {
                step(&world, &mut state, &inputs);
            }
            let mut h: u64 = 0xcbf2_9ce4_8422_2325;
            for b in state.copters.iter().flat_map(|c| c.digest().to_le_bytes()) {
                h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
            }
            let crashed = state.copters.iter().filter(|c| c.crash.is_some()).count();
            println!("{name:<18} threads {threads}  crashed {crashed:>4}  {h:016x}");
            if *first.get_or_insert(h) != h {
                unlike.push(format!("{name} on {threads} threads"));
            }
        }
    }
    if !unlike.is_empty() {
        eprintln!("same_bits: other digests than on {} thread(s): {}", threads[0], unlike.join(", "));
        std::process::exit(1);
    }
}
