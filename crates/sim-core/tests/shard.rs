//! Sharding in one process: the same swarm stepped by 2, 3 and 4 shard `State`s that trade
//! ghosts every step gives the same bits for every copter as one `State` (see
//! `sim_core::shard`). The Zenoh transport between processes is tested in `cli/tests/shard.rs`.

use sim_core::scene::{self, SceneSpec};
use sim_core::shard::{Partition, Role};
use sim_core::{CopterState, State, World, step};

/// What must be the same: motion, crash, readings and the random stream's next draw.
fn bits(c: &CopterState) -> Vec<u32> {
    let m = &c.motion;
    let mut v: Vec<u32> =
        [m.pos_m, m.vel_m_s, m.angvel_rad_s].iter().flat_map(|v| v.to_array()).map(f32::to_bits).collect();
    v.extend(m.rot.to_array().map(f32::to_bits));
    v.extend(c.sensors.sonar_m.map(f32::to_bits));
    v.extend(c.rotor_speed_rad_s.map(f32::to_bits));
    v.push(c.battery.charge.to_bits());
    v.push(u32::from(c.crash.is_some()));
    let mut rng = c.rng.clone();
    v.push(rng.uniform().to_bits());
    v
}

/// A 20 × 20 dense take-off swarm: 1.5 m grid, pillars, crashes piling up.
fn swarm() -> SceneSpec {
    scene::dense_swarm(400, 1.5, true, 12, 3)
}

/// The flock of [`scene::flock_swarm`]: 12 × 12 copters 4 m apart drifting 18 m along x.
/// (With free-running sonars: with the firmware's round robin no two of its copters meet, and
/// the test is about crashes across borders too.)
fn flock() -> SceneSpec {
    let mut spec = scene::flock_swarm(144, 3);
    spec.sensors.sonar.schedule = sim_core::sensors::SonarSchedule::Together;
    (spec.sensors.crosstalk.cycle_s, spec.sensors.crosstalk.cycle_spread) = (0.049, 0.002);
    spec
}

struct Sharded {
    states: Vec<State>,
    /// Ownership changes seen (a copter stepped by another shard than at the step before).
    migrations: usize,
    /// Most copters any shard had absent at once.
    max_absent: usize,
    /// The one-process run, stepped alongside.
    one: State,
    /// The first tick at which some copter's bits differed, and those copters.
    first_divergence: Option<(u64, Vec<usize>)>,
}

impl Sharded {
    fn owner(&self, i: usize) -> &State {
        self.states.iter().find(|s| s.owns(i)).unwrap()
    }

    /// Copters whose bits differ from the one-process run now.
    fn differing(&self) -> Vec<usize> {
        (0..self.one.copters.len()).filter(|&i| bits(&self.owner(i).copters[i]) != bits(&self.one.copters[i])).collect()
    }

    /// Every crash, in id order, with its cause's exact bits.
    fn crashes(states: &[&State], n: usize) -> Vec<(usize, String)> {
        (0..n)
            .filter_map(|i| {
                let s = states.iter().find(|s| s.owns(i)).unwrap();
                s.copters[i].crash.map(|c| (i, format!("{c:?}")))
            })
            .collect()
    }
}

/// Steps `world` for `ticks` as one process and as `shards` shards trading ghosts, side by side.
fn run_sharded(world: &World, shards: usize, ticks: u64) -> Sharded {
    let partition = Partition::new(world, shards).unwrap();
    let states: Vec<State> = (0..shards)
        .map(|k| {
            let mut s = world.initial_state();
            s.make_shard(partition.clone(), k).unwrap();
            s
        })
        .collect();
    let inputs = world.initial_inputs();
    let owners = |states: &[State]| -> Vec<usize> {
        (0..world.copters.len())
            .map(|i| {
                let owners: Vec<usize> = (0..states.len()).filter(|&k| states[k].owns(i)).collect();
                assert_eq!(owners.len(), 1, "copter {i} owned by {owners:?}");
                owners[0]
            })
            .collect()
    };
    let mut run = Sharded { states, migrations: 0, max_absent: 0, one: world.initial_state(), first_divergence: None };
    let mut before = owners(&run.states);
    let mut reports = Vec::new();
    for _ in 0..ticks {
        sim_core::shard::step_in_process(world, &mut run.states, &inputs, &mut reports).unwrap();
        for (s, report) in run.states.iter().zip(&reports) {
            let absent = s.shard().unwrap().roles.iter().filter(|r| **r == Role::Absent).count();
            run.max_absent = run.max_absent.max(absent);
            assert_eq!(report.shard_violations, 0, "tick {}", report.tick);
        }
        step(world, &mut run.one, &inputs);
        let now = owners(&run.states);
        run.migrations += before.iter().zip(&now).filter(|(a, b)| a != b).count();
        before = now;
        if run.first_divergence.is_none() {
            let differ = run.differing();
            if !differ.is_empty() {
                run.first_divergence = Some((run.one.tick, differ));
            }
        }
    }
    run
}

#[test]
fn copters_crossing_borders_keep_the_one_process_bits() {
    let world = scene::compile(&flock()).unwrap();
    for shards in [2, 3, 4] {
        let run = run_sharded(&world, shards, 1200);
        assert!(run.migrations > 20, "{shards} shards: copters crossed borders ({})", run.migrations);
        assert!(run.max_absent > 0, "{shards} shards: some copters were out of every halo");
        let n = world.copters.len();
        let crashes = Sharded::crashes(&[&run.one], n);
        assert!(!crashes.is_empty());
        let refs: Vec<&State> = run.states.iter().collect();
        assert_eq!(Sharded::crashes(&refs, n), crashes, "{shards} shards: the same crashes, to the bit");
        eprintln!(
            "flock, {shards} shards: {} migrations, {} crashes; first divergence {:?}",
            run.migrations,
            crashes.len(),
            run.first_divergence
        );
        assert_eq!(run.first_divergence, None, "{shards} shards: every copter keeps every bit for 60 s");
    }
}

#[test]
fn a_crash_across_a_border_is_the_one_process_crash() {
    // Two copters meet head-on over the border between two strips.
    let mut spec = scene::dense_swarm(2, 3.0, false, 0, 1);
    spec.arena.size_m = [12.0, 6.0];
    for (c, x) in spec.copters.iter_mut().zip([-1.5, 1.5]) {
        c.mode = sim_core::FlightMode::Target;
        c.start.pos_m = [x, 0.0];
        c.command.target_m = Some([-3.0 * x, 0.0, 1.0]);
    }
    let world = scene::compile(&spec).unwrap();
    let run = run_sharded(&world, 2, 200);
    let crashes: Vec<_> = run.one.copters.iter().map(|c| c.crash).collect();
    assert!(crashes.iter().all(|c| matches!(c, Some(sim_core::CrashCause::Copter { .. }))), "{crashes:?}");
    assert!(run.migrations > 0, "one of them was taken over by the other's shard");
    assert_eq!(run.first_divergence, None);
}

#[test]
fn a_crowded_take_off_with_crashes_keeps_the_one_process_bits() {
    let world = scene::compile(&swarm()).unwrap();
    for shards in [2, 4] {
        let run = run_sharded(&world, shards, 1200);
        let crashed = run.one.copters.iter().filter(|c| c.crash.is_some()).count();
        assert!(crashed > 50);
        // Wrecks lying on wrecks (one wreck's height above the floor; the pillars are 0.5 m
        // and taller).
        let piled = run.one.copters.iter().filter(|c| c.crash.is_some() && (0.04..0.3).contains(&c.motion.pos_m.z));
        let piled = piled.count();
        assert!(piled > 0, "some wrecks came to rest on others");
        eprintln!(
            "dense take-off, {shards} shards: {} migrations, {crashed} crashes, {piled} on other wrecks; first divergence {:?}",
            run.migrations, run.first_divergence
        );
        assert_eq!(run.first_divergence, None, "{shards} shards: every copter keeps every bit for 60 s");
    }
}

/// Copters that Rapier carries from one step to the next (near a box, or touching another)
/// stay with the shard whose Rapier world holds them, even as they cross a border: another
/// shard would take them over without Rapier's contact memory. Before that rule, this scene
/// parted from one process at tick 145 on 2 and 4 shards (203 copters differing by 10 s).
#[test]
fn copters_held_by_rapier_among_boxes_keep_the_one_process_bits_across_borders() {
    let world = scene::compile(&scene::boxes_swarm(600, 3)).unwrap();
    for shards in [2, 3, 4] {
        let run = run_sharded(&world, shards, 200);
        let crashed = run.one.copters.iter().filter(|c| c.crash.is_some()).count();
        assert!(crashed > 20, "{shards} shards: a crowded take-off among boxes ({crashed} crashes)");
        assert!(run.migrations > 0, "{shards} shards: copters crossed borders");
        assert_eq!(run.first_divergence, None, "{shards} shards: every copter keeps every bit for 10 s");
    }
}

/// Rapier colours a step's new contacts in the order of their bodies' ids, which every shard
/// shares, but two collider pairs of one body pair in the order of their contact-graph edges,
/// which only one process's history sets. So every body has one collider, flying, wrecked or
/// static (walls, floor, pillars and boxes each on a fixed body of its own). Before that, the
/// dense take-off of 2,000 among pillars parted from one process on 2 shards after 9 s
/// (`examples/shard_bits 60 2000`: 388 copters by 60 s).
#[test]
fn every_rapier_body_has_one_collider_so_contacts_are_coloured_as_in_one_process() {
    let world = scene::compile(&scene::dense_swarm(200, 1.5, true, 12, 3)).unwrap();
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let check = |state: &State, when: &str| {
        let bodies = &state.physics.bodies;
        assert!(bodies.len() > world.copters.len() + world.boxes.len(), "{when}: a body per copter, box and wall");
        for (handle, body) in bodies.iter() {
            assert_eq!(body.colliders().len(), 1, "{when}: body {handle:?} ({:?})", body.body_type());
        }
    };
    check(&state, "at the start");
    for _ in 0..(10.0 / world.params.control_dt_s) as u64 {
        step(&world, &mut state, &inputs);
    }
    let crashed = state.copters.iter().filter(|c| c.crash.is_some()).count();
    assert!(crashed > 5, "wrecks among the bodies ({crashed})");
    check(&state, "after 10 s");
}
