//! Seeds made by the current code, for the targets whose inputs the project writes itself
//! (logs, ghost batches, client sessions): a format change cannot leave them stale.
//! `scripts/fuzz.sh` starts its campaigns from them and the smoke pass replays them.

use bridge::log::{LogMeta, LogOptions, Logger};
use sim_core::scene;

use crate::{MERGE_SEPARATOR, ghost_world, scratch};

/// The seeds of `target` (empty for the targets seeded from files).
pub fn seeds(target: &str) -> Vec<Vec<u8>> {
    match target {
        "log" | "plot" => vec![run_log(12, 1, 0), run_log(30, 3, 0)],
        "log_merge" => {
            let (a, b) = (run_log(10, 1, 0), run_log(10, 1, 250_000_000));
            vec![join(&[&a, &b]), join(&[&a, &a]), join(&[&a, &b, &a])]
        }
        "foxglove_client" => vec![
            concat!(
                r#"{"op":"subscribe","subscriptions":[{"id":7,"channelId":1},{"id":8,"channelId":3}]}"#,
                "\n",
                r#"{"op":"unsubscribe","subscriptionIds":[7]}"#,
                "\n",
                r#"{"op":"subscribe","subscriptions":[{"id":7,"channelId":2}]}"#,
            )
            .into(),
            concat!(r#"{"op":"advertise","channels":[]}"#, "\n", r#"{"op":"getParameters"}"#, "\n", "{}").into(),
            b"\x01\x00\x00\x00\x00\n{\"op\":\"unsubscribe\",\"subscriptionIds\":[1,2]}".to_vec(),
        ],
        "ghost_batch" => ghost_batches(),
        _ => Vec::new(),
    }
}

fn join(logs: &[&Vec<u8>]) -> Vec<u8> {
    logs.iter().map(|l| l.as_slice()).collect::<Vec<_>>().join(MERGE_SEPARATOR)
}

/// A log of the lab scene: `steps` control steps logged every `every` ticks, with a bus
/// message, its epoch `shift_ns` after a fixed one.
fn run_log(steps: u64, every: u64, shift_ns: u64) -> Vec<u8> {
    let text = scene::DEFAULT_SCENE_TOML;
    let (_, world) = scene::load("lab.toml", text).expect("the lab scene");
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let epoch = 1_700_000_000_000_000_000 + shift_ns;
    let meta = LogMeta {
        command_line: "twinswarm run --prefix fuzz/lab".into(),
        scene_origin: "lab.toml".into(),
        epoch_ns: Some(epoch),
    };
    let options = LogOptions { every_ticks: every, ..LogOptions::default() };
    let path = scratch(&format!("seed-{steps}-{every}-{shift_ns}.mcap"));
    let mut log = Logger::with_options(&path, &world, text, meta, options).expect("a seed log");
    for _ in 0..steps {
        let r = sim_core::step(&world, &mut state, &inputs);
        log.log_step(&world, &state, &inputs, &r).expect("a logged step");
    }
    log.log_bus_message("fuzz/lab/copters/finken1/cmd", true, r#"{"mode":"hover"}"#, epoch + 42).expect("bus");
    log.finish().expect("a finished seed log");
    let data = std::fs::read(&path).expect("the seed log");
    let _ = std::fs::remove_file(&path);
    data
}

/// Batches shard 1 sent shard 0 in a 2-shard flock's first steps (postcard, as on Zenoh).
fn ghost_batches() -> Vec<Vec<u8>> {
    let (world, partition) = ghost_world();
    let mut shards: Vec<_> = (0..2)
        .map(|k| {
            let mut s = world.initial_state();
            s.make_shard(partition.clone(), k).expect("a shard");
            s
        })
        .collect();
    let (inputs, mut reports) = (world.initial_inputs(), Vec::new());
    let mut out = Vec::new();
    for tick in 0..40 {
        if tick % 10 == 0 {
            let mut ghosts = Vec::new();
            shards[1].ghosts_for(0, &mut ghosts);
            let batch = bridge::shard::GhostBatch { tick, from: 1, ghosts };
            out.push(postcard::to_allocvec(&batch).expect("a batch encodes"));
        }
        sim_core::shard::step_in_process(world, &mut shards, &inputs, &mut reports).expect("a step");
    }
    out
}
