//! Determinism: same scene and seed give the same bits; a snapshot restored and stepped on
//! gives the same bytes as the uninterrupted run.

use sim_core::scene;
use sim_core::{Inputs, State, World, step};

fn pose_bits(state: &State) -> Vec<u32> {
    (0..state.copters.len())
        .flat_map(|i| {
            let p = state.pose(i);
            let mut v: Vec<u32> = [p.pos_m.x, p.pos_m.y, p.pos_m.z, p.vel_m_s.x, p.vel_m_s.y, p.vel_m_s.z]
                .iter()
                .map(|f| f.to_bits())
                .collect();
            v.extend(p.quat_xyzw.iter().map(|f| f.to_bits()));
            v.extend(state.copters[i].sensors.sonar_m.iter().map(|f| f.to_bits()));
            v
        })
        .collect()
}

fn lab(seed: u64) -> World {
    let (mut spec, _) = scene::load_default();
    spec.sim.seed = seed;
    scene::compile(&spec).unwrap()
}

fn run(world: &World, inputs: &Inputs, ticks: u64) -> State {
    let mut state = world.initial_state();
    for _ in 0..ticks {
        step(world, &mut state, inputs);
    }
    state
}

#[test]
fn same_seed_gives_bitwise_identical_poses() {
    let world = lab(11);
    let inputs = world.initial_inputs();
    let a = run(&world, &inputs, 300);
    let b = run(&world, &inputs, 300);
    assert_eq!(pose_bits(&a), pose_bits(&b));
    // It did fly: both copters are up.
    assert!((0..2).all(|i| a.pose(i).pos_m.z > 0.5));
}

#[test]
fn a_different_seed_gives_different_noise() {
    let inputs = lab(11).initial_inputs();
    let a = run(&lab(11), &inputs, 100);
    let b = run(&lab(12), &inputs, 100);
    assert_ne!(pose_bits(&a), pose_bits(&b));
}

/// Steps `before` control steps, snapshots the state (postcard), restores it, then steps the
/// original and the restored state `after` more: the same events, poses and bytes. `check`
/// looks at the state at the snapshot.
fn snapshot_continues_bit_for_bit(world: &World, before: usize, after: usize, check: impl Fn(&State)) {
    let inputs = world.initial_inputs();
    let mut straight = world.initial_state();
    for _ in 0..before {
        step(world, &mut straight, &inputs);
    }
    check(&straight);
    let bytes = postcard::to_allocvec(&straight).unwrap();
    let mut restored: State = postcard::from_bytes(&bytes).unwrap();
    assert_eq!(postcard::to_allocvec(&restored).unwrap(), bytes, "restore is exact");
    for _ in 0..after {
        let a = step(world, &mut straight, &inputs);
        let b = step(world, &mut restored, &inputs);
        assert_eq!(a, b, "the same events");
    }
    assert_eq!(pose_bits(&straight), pose_bits(&restored));
    assert_eq!(
        postcard::to_allocvec(&straight).unwrap(),
        postcard::to_allocvec(&restored).unwrap(),
        "the whole state, byte for byte"
    );
}

#[test]
fn snapshot_round_trip_continues_bit_for_bit() {
    snapshot_continues_bit_for_bit(&lab(5), 150, 150, |_| {});
}

#[test]
fn inputs_are_never_written_by_the_step() {
    let world = lab(3);
    let inputs = world.initial_inputs();
    let before = inputs.clone();
    run(&world, &inputs, 50);
    assert_eq!(inputs, before);
}

/// 300 copters in Wall-Avoid, each heading its own way at 0.3 m/s: copters move between free
/// flight and Rapier, meet, and some crash.
fn swarm(threads: usize) -> World {
    let mut spec = scene::cruising_swarm(300, threads);
    spec.sensors.crosstalk.enabled = true;
    scene::compile(&spec).unwrap()
}

#[test]
fn one_and_two_threads_give_the_same_bits() {
    for (one, two) in [(swarm(1), swarm(2)), (lab_threads(1), lab_threads(2))] {
        let inputs = one.initial_inputs();
        let (mut a, mut b) = (one.initial_state(), two.initial_state());
        let mut events = 0;
        for _ in 0..200 {
            let ra = step(&one, &mut a, &inputs);
            let rb = step(&two, &mut b, &inputs);
            assert_eq!(ra, rb, "the same events in the same order");
            events += ra.events.len();
        }
        assert_eq!(pose_bits(&a), pose_bits(&b));
        assert_eq!(
            postcard::to_allocvec(&a).unwrap(),
            postcard::to_allocvec(&b).unwrap(),
            "the whole state, byte for byte ({events} events)"
        );
    }
}

fn lab_threads(threads: usize) -> World {
    let (mut spec, _) = scene::load_default();
    spec.sim.threads = threads;
    scene::compile(&spec).unwrap()
}

/// The experiment: 150 copters taking off from a 1.5 m grid among pillars, crowding and
/// crashing (grounded copters, copters on watch, wrecks falling, asleep and fixed).
fn dense(threads: usize) -> World {
    let mut spec = scene::dense_swarm(150, 1.5, true, 10, 3);
    spec.sim.threads = threads;
    scene::compile(&spec).unwrap()
}

#[test]
fn the_dense_take_off_gives_the_same_bits_on_one_two_and_three_threads() {
    let worlds = [dense(1), dense(2), dense(3)];
    let inputs = worlds[0].initial_inputs();
    let mut states: Vec<State> = worlds.iter().map(World::initial_state).collect();
    let (mut crashes, mut rapier) = (0, 0);
    for _ in 0..300 {
        let reports: Vec<_> = worlds.iter().zip(&mut states).map(|(w, s)| step(w, s, &inputs)).collect();
        assert_eq!(reports[0], reports[1], "1 and 2 threads: the same events in the same order");
        assert_eq!(reports[0], reports[2], "1 and 3 threads: the same events in the same order");
        crashes += reports[0].events.iter().filter(|e| matches!(e, sim_core::Event::Crashed { .. })).count();
        rapier += usize::from(reports[0].rapier_substeps > 0);
    }
    assert!(crashes > 5 && rapier > 0, "{crashes} crashes, {rapier} steps with Rapier");
    let bytes: Vec<Vec<u8>> = states.iter().map(|s| postcard::to_allocvec(s).unwrap()).collect();
    assert_eq!(bytes[0], bytes[1], "1 and 2 threads: the whole state, byte for byte ({crashes} crashes)");
    assert_eq!(bytes[0], bytes[2], "1 and 3 threads: the whole state, byte for byte");
}

#[test]
fn a_dense_snapshot_with_wrecks_continues_bit_for_bit() {
    snapshot_continues_bit_for_bit(&dense(1), 200, 100, |state| {
        assert!(state.copters.iter().any(|c| c.crash.is_some()), "some copters crashed by now");
    });
}
