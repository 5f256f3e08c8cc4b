//! What one ghost batch costs without the transport: finding the ghosts, serialising them,
//! reading them back and taking them into the neighbour's state.
//!
//! ```text
//! cargo run --release -p bridge --example ghost_codec -- [N] [STEPS] [ROUNDS]
//! ```
//!
//! Flies the dense take-off among pillars (`scene::dense_swarm(N, 1.5, true, 10, 5)`;
//! defaults 10,000 copters) as two shards in this process for STEPS steps (default 40), then
//! times, as a median over ROUNDS (default 50), shard 0's batch for shard 1: its borrowed
//! ghosts (`State::ghost_refs_for`), postcard into a reused buffer (what `ShardLink` sends,
//! framed as a batch), postcard back into owned ghosts (what Zenoh's thread does on arrival)
//! and `State::receive_ghosts` (checks every number and takes them in). `twinswarm cluster`'s
//! summary has the same parts with the transport: encode and send, wait, decode, take in.

use std::time::Instant;

use sim_core::scene;
use sim_core::shard::{Ghost, GhostState, Partition};

fn main() {
    let mut args = std::env::args().skip(1);
    let n: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(10_000);
    let steps: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(40);
    let rounds: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(50).max(1);
    let world = scene::compile(&scene::dense_swarm(n, 1.5, true, 10, 5)).expect("scene compiles");
    let inputs = world.initial_inputs();
    let partition = Partition::new(&world, 2).expect("partition");
    let mut states: Vec<_> = (0..2)
        .map(|k| {
            let mut s = world.initial_state();
            s.make_shard(partition.clone(), k).expect("shard");
            s
        })
        .collect();
    let mut reports = Vec::new();
    for _ in 0..steps {
        sim_core::shard::step_in_process(&world, &mut states, &inputs, &mut reports).expect("step");
    }
    let (sender, receiver) = states.split_at_mut(1);
    let (sender, receiver) = (&sender[0], &mut receiver[0]);
    let mut times: [Vec<f64>; 4] = Default::default();
    let (mut buffer, mut refs) = (Vec::new(), Vec::new());
    let (mut ghosts, mut whole) = (0, 0);
    for _ in 0..rounds {
        let t0 = Instant::now();
        refs.clear();
        sender.ghost_refs_for(1, &mut refs);
        let t1 = Instant::now();
        buffer.clear();
        buffer = postcard::to_extend(&(sender.tick, 0u16, &refs), buffer).expect("encode");
        let t2 = Instant::now();
        let (_, _, batch): (u64, u16, Vec<Ghost>) = postcard::from_bytes(&buffer).expect("decode");
        let t3 = Instant::now();
        (ghosts, whole) = (batch.len(), batch.iter().filter(|g| matches!(g.state, GhostState::Full(_))).count());
        receiver.receive_ghosts(batch).expect("take in");
        let t4 = Instant::now();
        for (k, (a, b)) in [(t0, t1), (t1, t2), (t2, t3), (t3, t4)].into_iter().enumerate() {
            times[k].push((b - a).as_secs_f64() * 1e3);
        }
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let [refs_ms, encode_ms, decode_ms, take_ms] = times.each_mut().map(median);
    println!(
        "{n} copters, 2 shards, after {steps} steps: a batch of {ghosts} ghosts ({whole} whole), {} B; median of \
         {rounds}, ms: find {refs_ms:.3}, encode {encode_ms:.3}, decode {decode_ms:.3}, take in {take_ms:.3}",
        buffer.len()
    );
}
