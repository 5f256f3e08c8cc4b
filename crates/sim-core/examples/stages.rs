//! Where a step's time goes, stage by stage, on one thread and on two: the serial fraction of
//! a step (the time only one thread works), measured as Amdahl's law defines it.
//!
//! ```text
//! cargo run --release -p sim-core --example stages -- [N] [SECONDS] [SEED]
//! ```
//!
//! Flies the dense take-off among pillars (`scene::dense_swarm(N, 1.5, true, 10, SEED)`;
//! defaults 10,000 copters, 5 s, seed 5) once with `threads = 1` and once with `threads = 2`,
//! timing each [`Stage`] through `step_probed` (sim-core reads no clock; this example does).
//! Per stage, with t1 and t2 its time on one and two threads, the part that ran on one thread
//! at two threads is s = max(0, 2 t2 − t1) (t2 = s + p / 2, t1 = s + p); the step's serial
//! fraction is Σ s / Σ t1, and Amdahl's law gives the speed-up on T threads as
//! 1 / (f + (1 − f) / T). On one thread the free copters' inner loops run inside
//! `InRapierLanes` (one pass over all copters); on two, beside Rapier in `RapierAndFreeLanes`:
//! the two are read together as "inner loops + Rapier". The same bits on both (checked).

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use sim_core::scene;
use sim_core::{Stage, StepReport, step_probed};

fn main() {
    let mut args = std::env::args().skip(1);
    let n: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(10_000);
    let seconds: f64 = args.next().and_then(|s| s.parse().ok()).unwrap_or(5.0);
    let seed: u64 = args.next().and_then(|s| s.parse().ok()).unwrap_or(5);
    let mut runs = Vec::new();
    for threads in [1, 2] {
        let mut spec = scene::dense_swarm(n, 1.5, true, 10, seed);
        spec.sim.threads = threads;
        let world = scene::compile(&spec).expect("scene compiles");
        let ticks = (seconds / world.params.control_dt_s).round() as u64;
        runs.push(fly(&world, ticks));
    }
    let (one, two) = (&runs[0], &runs[1]);
    assert_eq!(one.digest, two.digest, "1 and 2 threads must give the same bits");
    let group = |s: Stage| match s {
        Stage::InRapierLanes | Stage::RapierAndFreeLanes => "inner loops + Rapier".to_owned(),
        s => format!("{s:?}"),
    };
    let mut rows: BTreeMap<String, (f64, f64)> = BTreeMap::new();
    for (stage, d) in &one.stages {
        rows.entry(group(*stage)).or_default().0 += d.as_secs_f64();
    }
    for (stage, d) in &two.stages {
        rows.entry(group(*stage)).or_default().1 += d.as_secs_f64();
    }
    let steps = one.ticks as f64;
    let (t1_all, t2_all): (f64, f64) = rows.values().fold((0.0, 0.0), |a, r| (a.0 + r.0, a.1 + r.1));
    println!("dense take-off among pillars, {n} copters, {seconds} s ({} steps), seed {seed}", one.ticks);
    println!("{:<24} {:>12} {:>12} {:>14} {:>9}", "stage", "1 thread ms", "2 threads ms", "one thread ms", "share");
    let mut serial = 0.0;
    for (name, (t1, t2)) in &rows {
        let s = (2.0 * t2 - t1).max(0.0);
        serial += s;
        println!(
            "{name:<24} {:>12.3} {:>12.3} {:>14.3} {:>8.1}%",
            t1 / steps * 1e3,
            t2 / steps * 1e3,
            s / steps * 1e3,
            100.0 * s / t1_all
        );
    }
    let f = serial / t1_all;
    println!(
        "{:<24} {:>12.3} {:>12.3} {:>14.3} {:>8.1}%",
        "step",
        t1_all / steps * 1e3,
        t2_all / steps * 1e3,
        serial / steps * 1e3,
        100.0 * f
    );
    println!(
        "speed-up on 2 threads {:.2} (wall {:.1} s / {:.1} s); serial fraction {:.1} %: Amdahl gives {:.2} on 16 threads",
        t1_all / t2_all,
        one.wall.as_secs_f64(),
        two.wall.as_secs_f64(),
        100.0 * f,
        1.0 / (f + (1.0 - f) / 16.0)
    );
}

struct Run {
    ticks: u64,
    stages: BTreeMap<Stage, Duration>,
    wall: Duration,
    digest: Vec<u64>,
}

fn fly(world: &sim_core::World, ticks: u64) -> Run {
    let (mut state, inputs) = (world.initial_state(), world.initial_inputs());
    let mut report = StepReport::default();
    let mut stages: BTreeMap<Stage, Duration> = BTreeMap::new();
    let mut last = Instant::now();
    let start = last;
    for _ in 0..ticks {
        step_probed(world, &mut state, &inputs, &mut report, &mut |stage| {
            let now = Instant::now();
            if stage != Stage::Begin {
                *stages.entry(stage).or_default() += now - last;
            }
            last = now;
        });
    }
    let digest = state.copters.iter().map(|c| c.digest()).collect();
    Run { ticks, stages, wall: start.elapsed(), digest }
}
