//! Bus latency in real-time mode on loopback (a bench binary, not criterion: each sample is a
//! real-time round trip).
//!
//! 1. From a client's `…/copters/<name>/cmd` put to the first `…/state` that reflects it
//!    (the command toggles the flight mode; the state carries it). The loop applies inputs at
//!    its next 50 ms control step, so the floor is about half a step.
//! 2. From a telemetry message's arrival (`FINKEN_ACTUATORS_SET_POINT` from aircraft 5 at a
//!    22 ms period) to the control step that applied it to the twin.
//!
//! `cargo bench -p bridge --bench latency`

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use bridge::engine::{self, Frame, LoopOptions, Request};
use bridge::mixed::gateway::Gateway;
use bridge::mixed::interpreter::TwinAttitude;
use bridge::mixed::outbox::OutboxOptions;
use bridge::mixed::plan::TelemetryPlan;
use bridge::mixed::router::paired_copter;
use bridge::mixed::stats::Summary;
use bridge::paparazzi::pairing::Pose;
use bridge::wire::StateMsg;
use bridge::zenoh_net::node::{self, Node};
use sim_core::CopterKind;

const COMMANDS: usize = 200;
const TELEMETRY_S: f64 = 10.0;

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free loopback port")
}

fn main() {
    // `cargo bench` passes `--bench`; `cargo test --benches` runs it with no argument: skip then.
    if !std::env::args().any(|a| a == "--bench") {
        println!("latency: run with `cargo bench -p bridge --bench latency`");
        return;
    }
    let (mut spec, _) = sim_core::scene::load_default();
    let pose = Pose { x_m: 0.0, y_m: 0.8, z_m: 0.0, yaw_rad: 0.0 };
    spec.copters.push(paired_copter("twin", CopterKind::Real, 5, &pose));
    spec.sim.duration_s = 1e4;
    let world = sim_core::compile(&spec).expect("scene");
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let prefix = format!("latency-{port}/lab");
    let (req_tx, req_rx) = std::sync::mpsc::sync_channel::<Request>(1024);
    let messages = Arc::new(bridge::paparazzi::convert::project_messages());
    let world_arc = Arc::new(world.clone());
    let (mut node, gateway) = rt.block_on(async {
        let config = node::default_config(std::slice::from_ref(&endpoint), &[]).unwrap();
        let node = Node::open(config, prefix.clone(), world_arc.clone(), req_tx.clone()).await.unwrap();
        let links =
            bridge::mixed::gateway::PprzLinks { zenoh: Some((node.session().clone(), prefix.clone())), ivy: None };
        let gateway =
            Gateway::start(links, world_arc.clone(), None, messages.clone(), req_tx.clone(), TwinAttitude::Setpoint)
                .await
                .unwrap();
        (node, gateway)
    });
    let (frame_tx, mut frame_rx) = tokio::sync::mpsc::channel::<Frame>(256);
    let stop = Arc::new(AtomicBool::new(false));
    let stop_loop = stop.clone();
    let opts = LoopOptions {
        realtime: true,
        ticks: u64::MAX,
        outbox: Some(OutboxOptions {
            prefix: prefix.clone(),
            messages: messages.clone(),
            plan: TelemetryPlan::project_default(),
            virtual_sonar_period_s: 0.0,
            uplinks: Default::default(),
        }),
        sync: Some(bridge::mixed::sync::SyncOptions::default()),
        ..LoopOptions::default()
    };
    let loop_thread = std::thread::spawn(move || {
        let (state, inputs) = (world.initial_state(), world.initial_inputs());
        engine::run_watched(world, state, inputs, req_rx, Some(frame_tx), (), &stop_loop, &opts)
    });
    let publisher = rt.spawn(async move {
        while let Some(frame) = frame_rx.recv().await {
            let _ = node.publish(&frame).await;
        }
        node
    });

    // 1. cmd → state.
    let cmd_ms: Vec<f32> = rt.block_on(async {
        let client = zenoh::open(node::client_config(std::slice::from_ref(&endpoint)).unwrap()).await.unwrap();
        let states = client.declare_subscriber(format!("{prefix}/copters/finken1/state")).await.unwrap();
        tokio::time::sleep(Duration::from_secs(2)).await;
        let mut out = Vec::with_capacity(COMMANDS);
        for k in 0..COMMANDS {
            let mode = if k % 2 == 0 { "manual" } else { "mixed_manual" };
            // Drain what is already queued, then put and wait for the mode to show.
            while states.try_recv().ok().flatten().is_some() {}
            let sent = Instant::now();
            client.put(format!("{prefix}/copters/finken1/cmd"), format!("{{\"mode\":\"{mode}\"}}")).await.unwrap();
            loop {
                let sample = tokio::time::timeout(Duration::from_secs(5), states.recv_async())
                    .await
                    .expect("a state within 5 s")
                    .unwrap();
                let s: StateMsg = serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
                if s.mode == mode {
                    out.push(sent.elapsed().as_secs_f32() * 1e3);
                    break;
                }
            }
            // Desynchronise from the step grid.
            tokio::time::sleep(Duration::from_millis(7 + (k as u64 * 13) % 40)).await;
        }
        client.close().await.unwrap();
        out
    });

    // 2. telemetry → twin input.
    rt.block_on(async {
        let client = zenoh::open(node::client_config(std::slice::from_ref(&endpoint)).unwrap()).await.unwrap();
        tokio::time::sleep(Duration::from_millis(500)).await;
        let start = tokio::time::Instant::now();
        let mut k: u32 = 0;
        while start.elapsed().as_secs_f64() < TELEMETRY_S {
            k += 1;
            tokio::time::sleep_until(start + Duration::from_millis(22) * k).await;
            let text = format!("5 FINKEN_ACTUATORS_SET_POINT 0.5 -0.5 0 {}", 40 + k % 20);
            client.put(format!("{prefix}/pprz/5/FINKEN_ACTUATORS_SET_POINT"), text).await.unwrap();
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
        client.close().await.unwrap();
    });

    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let (_, _, stats, _) = loop_thread.join().unwrap();
    let node = rt.block_on(publisher).unwrap();
    let report = gateway.report();
    drop(gateway);
    rt.block_on(node.close()).unwrap();

    let c = Summary::of(&cmd_ms);
    let twin = &stats.twins["twin"];
    let t = twin.input_latency_ms;
    let arrivals = report.arrivals.iter().find(|a| a.message == "FINKEN_ACTUATORS_SET_POINT").expect("arrivals");
    println!("latency (real time, 50 ms control step, loopback), {} overruns in {} steps", stats.overruns, stats.steps);
    println!("| path | samples | p50 (ms) | p99 (ms) | max (ms) |");
    println!("|---|---|---|---|---|");
    println!(
        "| client `cmd` put → first `state` reflecting it | {} | {:.1} | {:.1} | {:.1} |",
        c.n, c.p50, c.p99, c.max
    );
    println!("| telemetry arrival → twin input applied | {} | {:.1} | {:.1} | {:.1} |", t.n, t.p50, t.p99, t.max);
    println!(
        "telemetry inter-arrival at the gateway: mean {:.1} ms, p99 {:.1} ms ({} messages, 22 ms period)",
        arrivals.gap_ms.mean, arrivals.gap_ms.p99, arrivals.count
    );
}
