//! Two shards' links on loopback Zenoh: the end of a sharded run. A shard leaves only when
//! each neighbour has taken its last batch (a batch in shared memory goes with its sender's
//! session), and a neighbour that never says so bounds the wait.

mod net;

use std::time::{Duration, Instant};

use bridge::shard::{LinkError, ShardLink};
use bridge::zenoh_net::node;
use net::free_port;
use sim_core::State;
use sim_core::shard::Partition;

/// Shard `k` of 2 of a dense take-off of 60 copters.
fn shard_of(world: &sim_core::World, k: usize) -> State {
    let mut s = world.initial_state();
    s.make_shard(Partition::new(world, 2).unwrap(), k).unwrap();
    s
}

/// Two links on one loopback port: shard 0 listens, shard 1 connects.
fn links(timeout: Duration) -> (ShardLink, ShardLink) {
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let prefix = format!("twinswarm-test-{port}/end");
    let open = |k: u16, config: zenoh::Config| ShardLink::open(config, &prefix, k, vec![1 - k], timeout).unwrap();
    let a = open(0, node::default_config(std::slice::from_ref(&endpoint), &[]).unwrap());
    let b = open(1, node::client_config(std::slice::from_ref(&endpoint)).unwrap());
    (a, b)
}

/// How a test shard flies: `ticks` steps, sleeping `each` before each exchange (a slow shard),
/// and `pause` after the last; then it `finish`es or not.
struct Fly {
    ticks: u64,
    each: Duration,
    pause: Duration,
    finish: bool,
}

/// Steps `state` through `link` as `how` says. Returns the state, how long `finish` took, and
/// its result. Returns the state, how long `finish` took, and its result.
fn fly(
    world: &sim_core::World,
    mut link: ShardLink,
    mut state: State,
    how: Fly,
) -> (State, Duration, Result<(), LinkError>, ShardLink) {
    let inputs = world.initial_inputs();
    link.wait_for_neighbours().unwrap();
    for _ in 0..how.ticks {
        std::thread::sleep(how.each);
        link.exchange(&mut state).unwrap();
        sim_core::step(world, &mut state, &inputs);
    }
    std::thread::sleep(how.pause);
    let start = Instant::now();
    let done = if how.finish { link.finish() } else { Ok(()) };
    (state, start.elapsed(), done, link)
}

#[test]
fn a_shard_leaves_only_when_its_neighbour_has_its_last_batch() {
    let world = sim_core::compile(&sim_core::scene::dense_swarm(60, 1.5, true, 2, 3)).unwrap();
    let (a, b) = links(Duration::from_secs(20));
    let (sa, sb) = (shard_of(&world, 0), shard_of(&world, 1));
    // Shard 1 is slow to say it is done (a loaded machine, a batch late on its way).
    let late = Duration::from_millis(2500);
    std::thread::scope(|s| {
        let ha = s
            .spawn(|| fly(&world, a, sa, Fly { ticks: 40, each: Duration::ZERO, pause: Duration::ZERO, finish: true }));
        let hb = s.spawn(|| fly(&world, b, sb, Fly { ticks: 40, each: Duration::ZERO, pause: late, finish: true }));
        let (sa, waited, done_a, a) = ha.join().unwrap();
        let (sb, _, done_b, b) = hb.join().unwrap();
        done_a.expect("shard 0 heard that shard 1 is done");
        done_b.expect("shard 1 heard that shard 0 is done");
        assert!(waited >= late - Duration::from_millis(500), "shard 0 left after {waited:?}, before shard 1 was done");
        assert_eq!((sa.tick, sb.tick), (40, 40));
        // The two shards are the one process.
        let mut one = world.initial_state();
        for _ in 0..40 {
            sim_core::step(&world, &mut one, &world.initial_inputs());
        }
        for (i, c) in one.copters.iter().enumerate() {
            let owner = if sa.owns(i) { &sa } else { &sb };
            assert_eq!(owner.copters[i].digest(), c.digest(), "copter {i}");
        }
        a.close().unwrap();
        b.close().unwrap();
    });
}

#[test]
fn a_neighbour_that_never_says_it_is_done_bounds_the_wait_and_one_that_left_ends_it() {
    let world = sim_core::compile(&sim_core::scene::dense_swarm(60, 1.5, true, 2, 3)).unwrap();
    let (a, b) = links(Duration::from_millis(1500));
    let (sa, sb) = (shard_of(&world, 0), shard_of(&world, 1));
    let (a, b) = std::thread::scope(|s| {
        let ha = s
            .spawn(|| fly(&world, a, sa, Fly { ticks: 10, each: Duration::ZERO, pause: Duration::ZERO, finish: true }));
        let hb = s.spawn(|| {
            fly(&world, b, sb, Fly { ticks: 10, each: Duration::ZERO, pause: Duration::ZERO, finish: false })
        });
        let (_, waited, done, a) = ha.join().unwrap();
        match done {
            Err(LinkError::Timeout { missing, tick, .. }) => assert_eq!((missing, tick), (vec![1], 9)),
            other => panic!("shard 0 should time out waiting for shard 1's word, got {other:?}"),
        }
        assert!(waited >= Duration::from_millis(1400), "waited {waited:?}");
        (a, hb.join().unwrap().3)
    });
    // Shard 1 leaves without a word: shard 0 learns it from its token and ends at once.
    let mut a = a;
    b.close().unwrap();
    let start = Instant::now();
    let mut done = a.finish();
    while matches!(done, Err(LinkError::Timeout { .. })) && start.elapsed() < Duration::from_secs(10) {
        done = a.finish();
    }
    done.expect("a neighbour that left is done");
    a.close().unwrap();
}

/// The barrier's account tells a neighbour slow to step from a slow link: behind a shard that
/// takes 30 ms longer a step, the wait grows and the batches' transit does not.
#[test]
fn the_barrier_tells_a_slow_neighbour_from_a_slow_link() {
    let world = sim_core::compile(&sim_core::scene::dense_swarm(60, 1.5, true, 2, 3)).unwrap();
    let (a, b) = links(Duration::from_secs(20));
    let (sa, sb) = (shard_of(&world, 0), shard_of(&world, 1));
    let slow = Duration::from_millis(30);
    let (a, b) = std::thread::scope(|s| {
        let ha = s
            .spawn(|| fly(&world, a, sa, Fly { ticks: 20, each: Duration::ZERO, pause: Duration::ZERO, finish: true }));
        let hb = s.spawn(|| fly(&world, b, sb, Fly { ticks: 20, each: slow, pause: Duration::ZERO, finish: true }));
        (ha.join().unwrap().3, hb.join().unwrap().3)
    });
    let (fast, slowed) = (a.stats().clone(), b.stats().clone());
    for (name, s) in [("shard 0", &fast), ("shard 1", &slowed)] {
        assert_eq!(s.exchanges, 20, "{name}");
        assert!(s.batches_received >= 20, "{name}: {s:?}");
        assert!(s.transit_s > 0.0 && s.transit_max_s > 0.0, "{name}: the batches carry their send time: {s:?}");
    }
    // Shard 0 waits about 30 ms a step for shard 1 to step, not for the link.
    assert!(fast.wait_s > 20.0 * 0.02, "shard 0 waited {:.3} s in all", fast.wait_s);
    assert!(fast.transit_s < 0.25 * fast.wait_s, "transit {:.3} s of a {:.3} s wait", fast.transit_s, fast.wait_s);
    // Shard 1 finds shard 0's batch there.
    assert!(slowed.wait_s < 0.25 * fast.wait_s, "shard 1 waited {:.3} s, shard 0 {:.3} s", slowed.wait_s, fast.wait_s);
    a.close().unwrap();
    b.close().unwrap();
}
