//! Lost links, in real time: a twin whose telemetry stops holds, lands and resumes; a copter
//! claimed over Zenoh takes commands only from its controller, and falls back to its
//! failsafe when that client's session dies. Every await is under a timeout.

mod net;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bridge::engine::failsafe::{ClientLostAction, FailsafeEvent, FailsafeKind, FailsafeOptions};
use bridge::engine::{self, BusInput, Frame, LoopOptions, Request, StepObserver};
use bridge::wire::CommandMsg;
use bridge::zenoh_net::node::{self, Node};
use net::{eventually, free_port, within};
use sim_core::{Inputs, State, StepReport, World};

const SCENE: &str = r#"
name = "failsafe"
[sim]
seed = 3
duration_s = 60.0
[arena]
size_m = [4.0, 3.0]
height_m = 2.5
[[copter]]
name = "twin"
kind = "real"
ac_id = 5
start = { pos_m = [-1.0, 0.0] }
[[copter]]
name = "v1"
start = { pos_m = [1.0, 0.5] }
# Wall-Avoid: a mixed-manual copter drifts on its AHRS bias and would meet a wall before the
# test is done.
mode = "wall_avoid"
command = { height_m = 0.8 }
"#;

/// One copter after a step: z (m), summed rotor speed (rad/s), crashed.
type CopterRow = (f32, f32, bool);

/// What the loop did, as seen from inside it.
#[derive(Debug, Default)]
struct Seen {
    events: Vec<(Instant, FailsafeEvent)>,
    /// Per step: when, and each copter.
    steps: Vec<(Instant, Vec<CopterRow>)>,
    rejected: Vec<String>,
}

#[derive(Clone, Default)]
struct Recorder(Arc<Mutex<Seen>>);

impl StepObserver for Recorder {
    fn after_step(&mut self, world: &World, state: &State, _: &Inputs, _: &StepReport) {
        let row = (0..world.copters.len())
            .map(|i| {
                let c = &state.copters[i];
                (state.pose(i).pos_m.z, c.rotor_speed_rad_s.iter().sum::<f32>(), c.crash.is_some())
            })
            .collect();
        self.0.lock().unwrap().steps.push((Instant::now(), row));
    }
    fn failsafe(&mut self, _tick: u64, _world: &World, event: &FailsafeEvent) {
        self.0.lock().unwrap().events.push((Instant::now(), event.clone()));
    }
    fn input_rejected(&mut self, _tick: u64, _input: &BusInput, reason: &str) {
        self.0.lock().unwrap().rejected.push(reason.to_owned());
    }
}

fn world() -> World {
    sim_core::scene::load("failsafe.toml", SCENE).expect("scene").1
}

fn telemetry(height_m: f32) -> Request {
    let cmd = CommandMsg { height: Some(height_m), roll: Some(0.0), pitch: Some(0.0), ..Default::default() };
    Request::Twin {
        copter: "twin".into(),
        spawn: None,
        cmd: Some(cmd),
        observed_rpy: None,
        sonar_m: None,
        yaw_rad: None,
        origin: BusInput { key: "test/pprz/5/ATTITUDE".into(), text: String::new(), received_unix_ns: 0 },
    }
}

#[test]
fn a_silent_twin_holds_then_lands_and_follows_again_when_telemetry_returns() {
    let world = world();
    let rest = world.airframes[world.copters[0].airframe].rest_height_m;
    let opts = LoopOptions {
        realtime: true,
        ticks: 20 * 60,
        failsafe: FailsafeOptions { hold_after_s: 0.3, land_after_s: 1.0, descent_m_s: 0.6, ..Default::default() },
        ..LoopOptions::default()
    };
    let (tx, rx) = std::sync::mpsc::sync_channel::<Request>(256);
    let stop = Arc::new(AtomicBool::new(false));
    let recorder = Recorder::default();
    let seen = recorder.0.clone();
    let loop_stop = stop.clone();
    let looper = std::thread::spawn(move || {
        let obs = recorder;
        let (state, inputs) = (world.initial_state(), world.initial_inputs());
        engine::run_watched(world, state, inputs, rx, None, obs, &loop_stop, &opts)
    });
    // Telemetry at 50 Hz for 3 s: the twin climbs to 1 m.
    // Returns when the last one was sent.
    let send_for = |secs: f64| {
        let t0 = Instant::now();
        let mut last = t0;
        while t0.elapsed().as_secs_f64() < secs {
            tx.send(telemetry(1.0)).unwrap();
            last = Instant::now();
            std::thread::sleep(Duration::from_millis(20));
        }
        last
    };
    let silent_from = send_for(3.0);
    // Silence until it has landed (at most 8 s).
    let landed = |s: &Seen| s.events.iter().any(|(_, e)| e.kind == FailsafeKind::Landed);
    while !landed(&seen.lock().unwrap()) && silent_from.elapsed() < Duration::from_secs(8) {
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_millis(600)); // the motors spin down
    let z_landed = seen.lock().unwrap().steps.last().unwrap().1[0];
    send_for(1.5);
    stop.store(true, Ordering::Relaxed);
    let (_, state, stats, _) = looper.join().unwrap();

    let s = seen.lock().unwrap();
    let at = |kind: &str| {
        s.events
            .iter()
            .find(|(_, e)| e.copter == 0 && e.kind.name() == kind)
            .map(|(t, _)| t.duration_since(silent_from).as_secs_f64())
    };
    let (hold, land, down, back) = (at("hold"), at("land"), at("landed"), at("resumed"));
    eprintln!("failsafe timings after the last telemetry: hold {hold:?} s, land {land:?} s, landed {down:?} s");
    let hold = hold.expect("a hold event");
    let land = land.expect("a land event");
    let down = down.expect("a landed event");
    // The loop checks after each 50 ms step.
    assert!((0.3..0.5).contains(&hold), "hold after {hold} s");
    assert!((1.0..1.2).contains(&land), "land after {land} s");
    // 1 m at 0.6 m/s (the soft height loop of the report's eq. 3.5 lags a falling target by
    // about (kd / kp) v = 0.6 m), then 0.5 s on the floor before the motors stop.
    assert!((2.0..6.5).contains(&down), "landed after {down} s");
    assert!(back.expect("a resumed event") > down);
    let (z, spin, crashed) = z_landed;
    assert!(!crashed, "a failsafe landing is not a crash");
    assert!(z < rest + 0.03, "on the floor: z {z} m, resting height {rest} m");
    // Spinning down (motor lag) from about 4,000 rad/s summed at hover.
    assert!(spin < 50.0, "motors off once landed: {spin} rad/s summed");
    assert!(state.copters[0].crash.is_none());
    assert!(state.pose(0).pos_m.z > 0.3, "it climbs again after telemetry returned: z {}", state.pose(0).pos_m.z);
    assert_eq!(stats.twins["twin"].link_lost, 1);
    assert_eq!(stats.failsafe.get("resumed"), Some(&1));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_its_controller_commands_a_claimed_copter_and_losing_it_lands_the_copter() {
    let world = world();
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let prefix = format!("twinswarm-test-{port}/failsafe");
    let (req_tx, req_rx) = std::sync::mpsc::sync_channel::<Request>(256);
    let config = node::default_config(std::slice::from_ref(&endpoint), &[]).unwrap();
    let mut node = within("open node", Node::open(config, prefix.clone(), Arc::new(world.clone()), req_tx.clone()))
        .await
        .expect("node opens");
    let counters = node.counters.clone();
    let (frame_tx, mut frame_rx) = tokio::sync::mpsc::channel::<Frame>(256);
    let stop = Arc::new(AtomicBool::new(false));
    let recorder = Recorder::default();
    let seen = recorder.0.clone();
    let loop_stop = stop.clone();
    let opts = LoopOptions {
        realtime: true,
        ticks: 20 * 60,
        failsafe: FailsafeOptions { client_lost: ClientLostAction::Land, descent_m_s: 0.8, ..Default::default() },
        ..LoopOptions::default()
    };
    let looper = std::thread::spawn(move || {
        let obs = recorder;
        let (state, inputs) = (world.initial_state(), world.initial_inputs());
        engine::run_watched(world, state, inputs, req_rx, Some(frame_tx), obs, &loop_stop, &opts)
    });
    let publisher = tokio::spawn(async move {
        while let Some(frame) = frame_rx.recv().await {
            node.publish(&frame).await.expect("publish");
        }
        node
    });

    let client = |_: &str| node::client_config(std::slice::from_ref(&endpoint)).unwrap();
    let pilot = within("open pilot", zenoh::open(client("pilot"))).await.unwrap();
    let intruder = within("open intruder", zenoh::open(client("intruder"))).await.unwrap();
    let cmd_key = format!("{prefix}/copters/v1/cmd");
    // Unclaimed, anyone may command: the intruder sends it to 1.2 m.
    within("put", intruder.put(&cmd_key, r#"{"height": 1.2}"#)).await.unwrap();
    let z = |s: &Seen| s.steps.last().map_or(0.0, |r| r.1[1].0);
    eventually("v1 climbs on an unclaimed copter's command", || z(&seen.lock().unwrap()) > 1.0).await;

    // The pilot claims it.
    let token =
        within("claim", pilot.liveliness().declare_token(format!("{prefix}/alive/copters/v1/pilot"))).await.unwrap();
    eventually("the claim reaches the loop", || {
        seen.lock()
            .unwrap()
            .events
            .iter()
            .any(|(_, e)| e.kind == FailsafeKind::Controller { client: Some("pilot".into()) })
    })
    .await;
    within("put", intruder.put(&cmd_key, r#"{"height": 2.0, "client": "intruder"}"#)).await.unwrap();
    within("put", intruder.put(&cmd_key, r#"{"height": 2.0}"#)).await.unwrap();
    within("put", pilot.put(&cmd_key, r#"{"height": 0.6, "client": "pilot"}"#)).await.unwrap();
    eventually("two commands refused", || counters.commands_not_controller.load(Ordering::Relaxed) == 2).await;
    eventually("v1 descends to the pilot's 0.6 m", || (z(&seen.lock().unwrap()) - 0.6).abs() < 0.1).await;
    {
        let s = seen.lock().unwrap();
        let refusals: Vec<&String> =
            s.rejected.iter().filter(|r| r.contains("controlled by client \"pilot\"")).collect();
        assert_eq!(refusals.len(), 2, "{:?}", s.rejected);
    }

    // The pilot's process dies: its session closes, its token goes, the copter lands.
    drop(token);
    within("close pilot", pilot.close()).await.unwrap();
    eventually("client lost", || {
        seen.lock().unwrap().events.iter().any(|(_, e)| matches!(&e.kind, FailsafeKind::ClientLost { client, action: ClientLostAction::Land } if client == "pilot"))
    })
    .await;
    eventually("v1 lands", || {
        seen.lock().unwrap().events.iter().any(|(_, e)| e.copter == 1 && e.kind == FailsafeKind::Landed)
    })
    .await;
    // A new client's command ends the failsafe.
    within("put", intruder.put(&cmd_key, r#"{"height": 1.0}"#)).await.unwrap();
    eventually("resumed", || {
        seen.lock().unwrap().events.iter().any(|(_, e)| e.copter == 1 && e.kind.name() == "resumed")
    })
    .await;

    stop.store(true, Ordering::Relaxed);
    let (_, state, stats, _) = looper.join().unwrap();
    let node = within("publisher ends", publisher).await.unwrap();
    within("close node", node.close()).await.unwrap();
    within("close intruder", intruder.close()).await.unwrap();
    assert!(state.copters[1].crash.is_none(), "{:?}", state.copters[1].crash);
    assert_eq!(stats.failsafe.get("client_lost"), Some(&1));
    assert_eq!(stats.failsafe.get("landed"), Some(&1));
}
