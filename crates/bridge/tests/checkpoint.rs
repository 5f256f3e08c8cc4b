//! Checkpoints restored in this process: the same bytes as the uninterrupted run, one process
//! and sharded; bad checkpoints refused with an error that names the file.

use std::path::PathBuf;

use bridge::engine::LoopOptions;
use bridge::engine::checkpoint::{self, CheckpointError, CheckpointOptions, Checkpointer, RunKey};
use bridge::engine::flight::{Flight, Recorder};
use sim_core::shard::{Partition, step_in_process};
use sim_core::{State, World};

fn tmp_dir(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("twinswarm-ckpt-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// The flock of `twinswarm scene flock`: copters cruising across the arena.
fn flock(n: usize) -> World {
    sim_core::compile(&sim_core::scene::flock_swarm(n, 3)).unwrap()
}

fn bytes(state: &State) -> Vec<u8> {
    postcard::to_allocvec(state).unwrap()
}

fn options(world: &World, dir: &std::path::Path, every_ticks: u64, shard: Option<(usize, usize)>) -> CheckpointOptions {
    CheckpointOptions { dir: dir.to_owned(), every_ticks, key: RunKey::of(world, shard), log_epoch_ns: None }
}

#[test]
fn a_flight_resumed_from_its_checkpoint_has_the_uninterrupted_bytes() {
    let world = flock(36);
    let dir = tmp_dir("flight");
    let opts = LoopOptions { checkpoint: Some(options(&world, &dir, 10, None)), ..Default::default() };
    let (state, inputs) = (world.initial_state(), world.initial_inputs());
    let mut straight = Flight::new(world.clone(), state, inputs, &opts, Recorder::default(), ());
    for _ in 0..40 {
        straight.step().unwrap();
    }
    // The newest two are kept.
    let kept: Vec<u64> = checkpoint::list(&dir, "run").unwrap().into_iter().map(|(t, _)| t).collect();
    assert_eq!(kept, [30, 40]);
    assert_eq!(straight.stats().checkpoints_written, 4);

    let ckpt = checkpoint::load(&dir.join("run-tick-000000000030.ckpt"), &RunKey::of(&world, None)).unwrap();
    assert_eq!(ckpt.tick, 30);
    let mut resumed =
        Flight::new(world.clone(), ckpt.state, ckpt.inputs, &LoopOptions::default(), Recorder::default(), ());
    for _ in 0..10 {
        resumed.step().unwrap();
    }
    assert_eq!(resumed.state().tick, 40);
    assert_eq!(bytes(resumed.state()), bytes(straight.state()), "the bytes of the uninterrupted run");
    assert_eq!(resumed.inputs().commands.len(), world.copters.len());
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn shards_resumed_from_their_checkpoints_have_the_uninterrupted_bytes() {
    // 10 s each side: copters cross the borders, as ghosts and as owners.
    let changed_roles = resume_shards("shards", &flock(64), 3, 200);
    assert!(changed_roles, "copters changed roles after the checkpoint");
}

/// Among boxes, copters that Rapier holds from step to step cross borders around the
/// checkpoint (`sim_core::shard`'s held copters): the resumed shards step on from the Rapier
/// worlds they saved (which say who holds what), with the uninterrupted bytes, and those are
/// the bits of one process.
#[test]
fn shards_among_boxes_resumed_from_their_checkpoints_keep_the_one_process_bits() {
    let world = sim_core::compile(&sim_core::scene::boxes_swarm(600, 3)).unwrap();
    let changed_roles = resume_shards("boxes", &world, 2, 150);
    assert!(changed_roles, "copters changed roles after the checkpoint");
}

/// Steps `world` as `n` shards for `half` ticks, checkpoints them, steps `half` more; resumes
/// from the checkpoints and steps `half`: the resumed shards must have the uninterrupted bytes
/// and roles, and every copter the bits of one process. Returns whether roles changed after
/// the checkpoint.
fn resume_shards(tag: &str, world: &World, n: usize, half: u64) -> bool {
    let dir = tmp_dir(tag);
    let make = || -> Vec<State> {
        (0..n)
            .map(|k| {
                let mut s = world.initial_state();
                s.make_shard(Partition::new(world, n).unwrap(), k).unwrap();
                s
            })
            .collect()
    };
    let inputs = world.initial_inputs();
    let mut reports = Vec::new();
    let mut straight = make();
    let mut step = |states: &mut Vec<State>| {
        step_in_process(world, states, &inputs, &mut reports).unwrap();
        assert!(reports.iter().all(|r| r.shard_violations == 0), "{tag}: no shard violations");
    };
    for _ in 0..half {
        step(&mut straight);
    }
    for (k, s) in straight.iter().enumerate() {
        Checkpointer::new(options(world, &dir, half, Some((k, n)))).write(s, &inputs, &[]).unwrap();
    }
    let roles_then: Vec<_> = straight.iter().map(|s| s.shard_snapshot().unwrap().roles).collect();
    for _ in 0..half {
        step(&mut straight);
    }
    let mut resumed: Vec<State> = (0..n)
        .map(|k| {
            let key = RunKey::of(world, Some((k, n)));
            let path = dir.join(format!("shard-{k}-of-{n}-tick-{half:012}.ckpt"));
            let c = checkpoint::load(&path, &key).unwrap();
            let mut state = c.state;
            state.restore_shard(Partition::new(world, n).unwrap(), c.shard.unwrap()).unwrap();
            state
        })
        .collect();
    for _ in 0..half {
        step(&mut resumed);
    }
    for (k, (a, b)) in straight.iter().zip(&resumed).enumerate() {
        assert_eq!(bytes(a), bytes(b), "{tag}, shard {k}: the bytes of the uninterrupted run");
        assert_eq!(a.shard_snapshot(), b.shard_snapshot(), "{tag}, shard {k}: the same roles");
    }
    let mut one = world.initial_state();
    for _ in 0..2 * half {
        sim_core::step(world, &mut one, &inputs);
    }
    let differ: Vec<usize> = (0..one.copters.len())
        .filter(|&i| {
            let owner = resumed.iter().find(|s| s.owns(i)).unwrap();
            owner.copters[i].digest() != one.copters[i].digest()
        })
        .collect();
    assert!(differ.is_empty(), "{tag}: copters {differ:?} differ from one process");
    let _ = std::fs::remove_dir_all(dir);
    straight.iter().zip(&roles_then).any(|(s, then)| s.shard_snapshot().unwrap().roles != *then)
}

#[test]
fn bad_checkpoints_are_refused_with_the_file_named() {
    let world = flock(9);
    let dir = tmp_dir("bad");
    let key = RunKey::of(&world, Some((1, 2)));
    let mut state = world.initial_state();
    state.make_shard(Partition::new(&world, 2).unwrap(), 1).unwrap();
    let good =
        Checkpointer::new(options(&world, &dir, 1, Some((1, 2)))).write(&state, &world.initial_inputs(), &[]).unwrap();
    assert!(checkpoint::load(&good, &key).is_ok());
    let data = std::fs::read(&good).unwrap();
    let write = |name: &str, bytes: &[u8]| {
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    };
    let mut flipped = data.clone();
    let mid = flipped.len() / 2;
    flipped[mid] ^= 0x40;
    let other_seed = {
        let mut spec = world.spec.clone();
        spec.sim.seed += 1;
        RunKey::of(&sim_core::compile(&spec).unwrap(), Some((1, 2)))
    };
    let cases: Vec<(PathBuf, RunKey, &str)> = vec![
        (write("flipped.ckpt", &flipped), key.clone(), "do not match its CRC"),
        (write("short.ckpt", &data[..data.len() - 7]), key.clone(), "truncated"),
        (write("garbage.ckpt", b"not a checkpoint at all"), key.clone(), "not a twinswarm checkpoint"),
        (write("empty.ckpt", b""), key.clone(), "not a twinswarm checkpoint"),
        (good.clone(), other_seed, "seed"),
        (good.clone(), RunKey::of(&world, Some((0, 2))), "it is of shard 1/2, this run is shard 0/2"),
        (good.clone(), RunKey::of(&world, None), "this run is one process"),
        (good.clone(), RunKey::of(&flock(10), Some((1, 2))), "another scene"),
        (dir.join("missing.ckpt"), key.clone(), "No such file"),
    ];
    for (path, key, what) in cases {
        let e = checkpoint::load(&path, &key).expect_err(what);
        let text = e.to_string();
        assert!(text.contains(&path.display().to_string()), "{text}");
        assert!(text.contains(what), "{what}: {text}");
        if what == "seed" {
            assert!(matches!(e, CheckpointError::Mismatch { .. }), "{e:?}");
        }
    }
    let _ = std::fs::remove_dir_all(dir);
}
