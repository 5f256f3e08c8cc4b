//! One process against 2, 3 and 4 shards stepped in this process (`shard::step_in_process`,
//! the ghosts traded as the Zenoh transport trades them): every copter must keep the
//! one-process bits. Prints, per scene and shard count, how many copters differ at the end
//! and the first tick at which any did.
//!
//! ```text
//! cargo run --release -p sim-core --example shard_bits -- [SIM_SECONDS] [N] [SEED]
//! ```
//!
//! The scenes (defaults: 20 s, 2,000 copters, seed 5): the dense take-off among pillars and
//! a take-off among boxes of several sizes and yaws.

use sim_core::scene::{self, SceneSpec};
use sim_core::shard::Partition;
use sim_core::{State, step};

fn scenes(n: usize, seed: u64) -> Vec<(&'static str, SceneSpec)> {
    vec![("dense-pillars", scene::dense_swarm(n, 1.5, true, 10, seed)), ("boxes", scene::boxes_swarm(n, seed + 2))]
}

fn main() {
    let mut args = std::env::args().skip(1);
    let seconds: f64 = args.next().and_then(|s| s.parse().ok()).unwrap_or(20.0);
    let n: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(2000);
    let seed: u64 = args.next().and_then(|s| s.parse().ok()).unwrap_or(5);
    for (name, spec) in scenes(n, seed) {
        let world = scene::compile(&spec).expect("scene compiles");
        let ticks = (seconds / world.params.control_dt_s).round() as u64;
        for shards in [2, 3, 4] {
            let d = compare(&world, shards, ticks);
            println!(
                "{name:<13} n {n:>5} shards {shards}  crashed {:>4}  differ {:>4}  violations {}  first divergence {}",
                d.crashed,
                d.differ.len(),
                d.violations,
                d.first.map_or("none".into(), |(t, ids)| format!("tick {t}: {ids:?}")),
            );
        }
    }
}

struct Divergence {
    crashed: usize,
    differ: Vec<usize>,
    violations: u32,
    /// The first tick at which some copter differed, and the first few of them.
    first: Option<(u64, Vec<usize>)>,
}

/// One process and `shards` shards stepped side by side for `ticks`.
fn compare(world: &sim_core::World, shards: usize, ticks: u64) -> Divergence {
    let inputs = world.initial_inputs();
    let mut one = world.initial_state();
    let partition = Partition::new(world, shards).expect("partition");
    let mut states: Vec<State> = (0..shards)
        .map(|k| {
            let mut s = world.initial_state();
            s.make_shard(partition.clone(), k).expect("shard");
            s
        })
        .collect();
    let (mut reports, mut violations, mut first) = (Vec::new(), 0u32, None);
    let differing = |one: &State, states: &[State]| -> Vec<usize> {
        (0..one.copters.len())
            .filter(|&i| {
                states.iter().find(|s| s.owns(i)).map(|s| s.copters[i].digest()) != Some(one.copters[i].digest())
            })
            .collect()
    };
    for _ in 0..ticks {
        step(world, &mut one, &inputs);
        sim_core::shard::step_in_process(world, &mut states, &inputs, &mut reports).expect("ghosts");
        violations += reports.iter().map(|r| r.shard_violations).sum::<u32>();
        if first.is_none() {
            let d = differing(&one, &states);
            if !d.is_empty() {
                first = Some((one.tick, d.into_iter().take(6).collect()));
            }
        }
    }
    let crashed = one.copters.iter().filter(|c| c.crash.is_some()).count();
    Divergence { crashed, differ: differing(&one, &states), violations, first }
}
