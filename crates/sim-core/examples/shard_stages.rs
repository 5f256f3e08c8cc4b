//! Where a shard's step goes, stage by stage, against one process: what sharding adds.
//!
//! ```text
//! cargo run --release -p sim-core --example shard_stages -- [N] [SECONDS] [SEED] [SHARDS]
//! ```
//!
//! Flies the dense take-off among pillars (`scene::dense_swarm(N, 1.5, true, 10, SEED)`;
//! defaults 10,000 copters, 5 s, seed 5, 2 shards) on one thread in one process, and as
//! SHARDS shards stepped one after the other in this process (`shard::step_in_process`, the
//! ghosts traded in memory), timing each [`Stage`] of each shard through `step_probed`
//! (sim-core reads no clock; this example does), and the trade of ghosts. Per stage, ms per
//! step: one process; each shard; the shards' sum over one process (the work sharding adds,
//! 1.00 = none); the slowest shard over one process (the speed-up's inverse on SHARDS cores,
//! the transport apart). Every copter keeps the one-process bits (checked at the end).

use std::collections::BTreeMap;
use std::time::Instant;

use sim_core::scene;
use sim_core::shard::{Ghost, Partition, Role};
use sim_core::{Stage, State, StepReport, World, step_probed};

fn main() {
    let mut args = std::env::args().skip(1);
    let n: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(10_000);
    let seconds: f64 = args.next().and_then(|s| s.parse().ok()).unwrap_or(5.0);
    let seed: u64 = args.next().and_then(|s| s.parse().ok()).unwrap_or(5);
    let shards: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(2).max(1);
    let spec = scene::dense_swarm(n, 1.5, true, 10, seed);
    let world = scene::compile(&spec).expect("scene compiles");
    let ticks = (seconds / world.params.control_dt_s).round() as u64;
    let inputs = world.initial_inputs();

    let mut one = world.initial_state();
    let mut one_times = Times::default();
    for _ in 0..ticks {
        one_times.step(&world, &mut one, &inputs);
    }

    let partition = Partition::new(&world, shards).expect("partition");
    let mut states: Vec<State> = (0..shards)
        .map(|k| {
            let mut s = world.initial_state();
            s.make_shard(partition.clone(), k).expect("shard");
            s
        })
        .collect();
    let mut times: Vec<Times> = (0..shards).map(|_| Times::default()).collect();
    // Per step, the slowest shard's step less the mean shard's: what the barrier waits for.
    let mut imbalance_s = 0.0;
    // Per shard, its copters of each role summed over the steps (after each step's ownership).
    let mut roles = vec![[0usize; 3]; shards];
    for _ in 0..ticks {
        let trade = Instant::now();
        trade_ghosts(&mut states);
        let per_shard = trade.elapsed().as_secs_f64() / shards as f64;
        let mut walls = Vec::with_capacity(shards);
        for (s, t) in states.iter_mut().zip(&mut times) {
            *t.stages.entry("ghosts traded".to_owned()).or_default() += per_shard;
            let start = Instant::now();
            t.step(&world, s, &inputs);
            walls.push(start.elapsed().as_secs_f64());
        }
        imbalance_s += walls.iter().copied().fold(0.0, f64::max) - walls.iter().sum::<f64>() / shards as f64;
        for (s, counts) in states.iter().zip(&mut roles) {
            for r in &s.shard().expect("a shard").roles {
                match r {
                    Role::Owned => counts[0] += 1,
                    Role::Ghost => counts[1] += 1,
                    Role::Far => counts[2] += 1,
                    Role::Absent => {}
                }
            }
        }
    }
    let differ = (0..one.copters.len())
        .filter(|&i| states.iter().find(|s| s.owns(i)).map(|s| s.copters[i].digest()) != Some(one.copters[i].digest()))
        .count();

    println!("dense take-off among pillars, {n} copters, {seconds} s ({ticks} steps), seed {seed}, {shards} shards");
    print!("{:<22} {:>9}", "stage (ms per step)", "1 process");
    for k in 0..shards {
        print!(" {:>9}", format!("shard {k}"));
    }
    println!(" {:>7} {:>8}", "sum / 1", "max / 1");
    let steps = ticks as f64;
    let mut names: Vec<&String> = one_times.stages.keys().chain(times[0].stages.keys()).collect();
    names.sort_by_key(|name| order(name));
    names.dedup();
    let total = |t: &Times| t.stages.values().sum::<f64>();
    let rows = names.iter().map(|&name| {
        let get = |t: &Times| t.stages.get(name).copied().unwrap_or(0.0);
        (name.clone(), get(&one_times), times.iter().map(get).collect::<Vec<_>>())
    });
    let step_row = ("step".to_owned(), total(&one_times), times.iter().map(total).collect());
    for (name, one_s, shard_s) in rows.chain([step_row]) {
        print!("{name:<22} {:>9.3}", one_s / steps * 1e3);
        for s in &shard_s {
            print!(" {:>9.3}", s / steps * 1e3);
        }
        let (sum, max) = (shard_s.iter().sum::<f64>(), shard_s.iter().copied().fold(0.0, f64::max));
        if one_s > 0.0 {
            println!(" {:>7.2} {:>8.2}", sum / one_s, max / one_s);
        } else {
            // Work only shards do (the trade of ghosts): no ratio.
            println!(" {:>7} {:>8}", "-", "-");
        }
    }
    println!("imbalance (slowest shard's step less the mean, per step): {:.3} ms", imbalance_s / steps * 1e3);
    for (k, [owned, ghost, far]) in roles.iter().enumerate() {
        let per_step = |c: usize| c as f64 / steps;
        println!(
            "shard {k}: per step {:.0} owned, {:.0} ghosts (whole), {:.0} far ghosts",
            per_step(*owned),
            per_step(*ghost),
            per_step(*far)
        );
    }
    println!("copters unlike one process: {differ}");
}

/// Each shard's ghosts for its neighbours, received (what `shard::step_in_process` does
/// before it steps).
fn trade_ghosts(states: &mut [State]) {
    let mut inbox: Vec<Vec<Ghost>> = vec![Vec::new(); states.len()];
    for s in states.iter() {
        let view = s.shard().expect("a shard");
        for t in view.partition.neighbours(view.me) {
            s.ghosts_for(t, &mut inbox[usize::from(t)]);
        }
    }
    for (s, ghosts) in states.iter_mut().zip(inbox) {
        s.receive_ghosts(ghosts).expect("ghosts");
    }
}

/// The stages in step order (the physics ones summed over the substeps), then the rest.
fn order(name: &str) -> usize {
    let stages = [
        Stage::Lanes,
        Stage::Airflow,
        Stage::Reserve,
        Stage::RapierSetup,
        Stage::SonarScene,
        Stage::Ranges,
        Stage::Crosstalk,
        Stage::Sense,
        Stage::OuterLoops,
        Stage::InRapierLanes,
        Stage::RapierForces,
        Stage::RapierAndFreeLanes,
        Stage::RapierResults,
        Stage::TiltAndTakeOff,
        Stage::Store,
    ];
    stages.iter().position(|s| format!("{s:?}") == name).unwrap_or(0)
}

#[derive(Default)]
struct Times {
    /// Seconds, per stage.
    stages: BTreeMap<String, f64>,
    report: StepReport,
}

impl Times {
    fn step(&mut self, world: &World, state: &mut State, inputs: &sim_core::Inputs) {
        let mut last = Instant::now();
        let stages = &mut self.stages;
        step_probed(world, state, inputs, &mut self.report, &mut |stage| {
            let now = Instant::now();
            if stage != Stage::Begin {
                *stages.entry(format!("{stage:?}")).or_default() += (now - last).as_secs_f64();
            }
            last = now;
        });
    }
}
