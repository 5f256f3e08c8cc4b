//! Two shards' links on loopback Zenoh: the end of a sharded run (a shard leaves only when each
//! neighbour has taken its last batch; a neighbour that never says so bounds the wait, which a
//! stop ends; one given another duration stops at once), and the barrier's account.

mod net;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use bridge::shard::{LEFT_GRACE, LinkError, ShardLink};
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
/// and `pause` after the last; then it `finish`es (within `finish`) or not.
struct Fly {
    ticks: u64,
    each: Duration,
    pause: Duration,
    finish: Option<Duration>,
}

impl Fly {
    fn steps(ticks: u64) -> Fly {
        Fly { ticks, each: Duration::ZERO, pause: Duration::ZERO, finish: Some(Duration::from_secs(20)) }
    }
}

/// What a test shard ends with: its state, how long `finish` took, the first error of its
/// exchanges or of `finish`, and its link.
type Flown = (State, Duration, Result<(), LinkError>, ShardLink);

/// Steps `state` through `link` as `how` says, up to its first error.
fn fly(world: &sim_core::World, mut link: ShardLink, mut state: State, how: Fly) -> Flown {
    let inputs = world.initial_inputs();
    link.wait_for_neighbours().unwrap();
    for _ in 0..how.ticks {
        std::thread::sleep(how.each);
        if let Err(e) = link.exchange(&mut state) {
            return (state, Duration::ZERO, Err(e), link);
        }
        sim_core::step(world, &mut state, &inputs);
    }
    std::thread::sleep(how.pause);
    let start = Instant::now();
    let done = how.finish.map_or(Ok(()), |t| link.finish_within(t));
    (state, start.elapsed(), done, link)
}

/// Two shards of a dense take-off of 60 copters, flown side by side as `a` and `b` say.
fn fly_two(a: Fly, b: Fly) -> (Flown, Flown) {
    let world = sim_core::compile(&sim_core::scene::dense_swarm(60, 1.5, true, 2, 3)).unwrap();
    let (la, lb) = links(Duration::from_secs(20));
    let (sa, sb) = (shard_of(&world, 0), shard_of(&world, 1));
    std::thread::scope(|s| {
        let ha = s.spawn(|| fly(&world, la, sa, a));
        let hb = s.spawn(|| fly(&world, lb, sb, b));
        (ha.join().unwrap(), hb.join().unwrap())
    })
}

#[test]
fn a_shard_leaves_only_when_its_neighbour_has_its_last_batch() {
    // Shard 1 is slow to say it is done (a loaded machine, a batch late on its way).
    let late = Duration::from_millis(2500);
    let ((sa, waited, done_a, a), (sb, _, done_b, b)) = fly_two(Fly::steps(40), Fly { pause: late, ..Fly::steps(40) });
    done_a.expect("shard 0 heard that shard 1 is done");
    done_b.expect("shard 1 heard that shard 0 is done");
    assert!(waited >= late - Duration::from_millis(500), "shard 0 left after {waited:?}, before shard 1 was done");
    assert!(a.stats().finish_s >= waited.as_secs_f64() - 1e-3, "{:?}", a.stats());
    assert_eq!((sa.tick, sb.tick), (40, 40));
    // The two shards are the one process.
    let world = sim_core::compile(&sim_core::scene::dense_swarm(60, 1.5, true, 2, 3)).unwrap();
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
}

#[test]
fn a_neighbour_that_never_says_it_is_done_bounds_the_wait_and_a_stop_or_one_that_left_ends_it() {
    let quiet = Fly { finish: None, ..Fly::steps(10) };
    let ((_, waited, done, a), (_, _, _, b)) =
        fly_two(Fly { finish: Some(Duration::from_millis(1500)), ..Fly::steps(10) }, quiet);
    match done {
        Err(LinkError::Timeout { missing, tick, .. }) => assert_eq!((missing, tick), (vec![1], 9)),
        other => panic!("shard 0 should time out waiting for shard 1's word, got {other:?}"),
    }
    assert!(waited >= Duration::from_millis(1400), "waited {waited:?}");
    // A stop (a signal, a stop request) ends the wait at once, shard 1 still silent.
    let stop = Arc::new(AtomicBool::new(false));
    let mut a = a.stop_on(stop.clone());
    let setter = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(300));
            stop.store(true, Ordering::Relaxed);
        })
    };
    let start = Instant::now();
    match a.finish_within(Duration::from_secs(20)) {
        Err(LinkError::Stopped { me: 0, tick: 9 }) => {}
        other => panic!("a stop should end shard 0's wait, got {other:?}"),
    }
    assert!(start.elapsed() < Duration::from_secs(2), "stopped after {:?}", start.elapsed());
    setter.join().unwrap();
    stop.store(false, Ordering::Relaxed);
    // Shard 1 leaves without a word: shard 0 learns it from its token, and ends after the
    // grace a word on its way gets.
    b.close().unwrap();
    let start = Instant::now();
    a.finish_within(Duration::from_secs(20)).expect("a neighbour that left is done");
    let took = start.elapsed();
    assert!(took >= LEFT_GRACE && took < LEFT_GRACE + Duration::from_secs(3), "ended after {took:?}");
    a.close().unwrap();
}

/// Shards given different durations: the one still stepping learns that its neighbour
/// ended, and stops at once with both ticks instead of waiting out the barrier timeout.
#[test]
fn a_neighbour_that_ended_earlier_stops_the_shard_with_both_ticks() {
    let short = Fly { finish: Some(Duration::from_secs(3)), ..Fly::steps(10) };
    let ((_, _, _, mut a), (_, _, done_b, b)) = fly_two(short, Fly::steps(12));
    match done_b {
        Err(LinkError::Ended { me: 1, shard: 0, at: 9, tick: 10 }) => {}
        other => panic!("shard 1 should stop: shard 0 ended at tick 9, got {other:?}"),
    }
    // Shard 0, at its end, waits for shard 1's word until shard 1, stopped, leaves.
    b.close().unwrap();
    a.finish_within(Duration::from_secs(20)).expect("a neighbour that stopped and left is done");
    a.close().unwrap();
}

/// The barrier's account tells a neighbour slow to step from a slow link: behind a shard that
/// takes 100 ms longer a step, the wait grows and the batches' transit does not.
#[test]
fn the_barrier_tells_a_slow_neighbour_from_a_slow_link() {
    let slow = Duration::from_millis(100);
    let ((_, _, done_a, a), (_, _, done_b, b)) = fly_two(Fly::steps(10), Fly { each: slow, ..Fly::steps(10) });
    done_a.and(done_b).unwrap();
    let (fast, slowed) = (a.stats().clone(), b.stats().clone());
    for (name, s) in [("shard 0", &fast), ("shard 1", &slowed)] {
        assert_eq!(s.exchanges, 10, "{name}");
        assert!(s.batches_timed >= 10 && s.batches_timed == s.batches_received, "{name}: {s:?}");
        assert!(s.transit_s > 0.0 && s.transit_max_s > 0.0, "{name}: the batches carry their put time: {s:?}");
    }
    // Shard 0 waits about 100 ms a step for shard 1 to step, not for the link.
    assert!(
        fast.wait_s - fast.transit_s > 0.5,
        "shard 0 waited {:.3} s, {:.3} s in transit",
        fast.wait_s,
        fast.transit_s
    );
    // Shard 1 finds shard 0's batch there.
    assert!(slowed.wait_s < 0.25 * fast.wait_s, "shard 1 waited {:.3} s, shard 0 {:.3} s", slowed.wait_s, fast.wait_s);
    a.close().unwrap();
    b.close().unwrap();
}
