//! The simulator's Zenoh node against a real client session on loopback. Every await is under
//! a timeout, so a hang fails fast.

mod net;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use bridge::engine::{self, Frame, LoopOptions, Request};
use bridge::wire::{CopterListEntry, StateMsg};
use bridge::zenoh_net::node::{self, Node};
use net::{eventually, free_port, within};
use zenoh::Wait;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn commands_queryables_spawn_liveliness_and_bad_payloads() {
    let (_, world) = sim_core::scene::load_default();
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let prefix = format!("twinswarm-test-{port}/lab");
    let (req_tx, req_rx) = std::sync::mpsc::sync_channel::<Request>(256);
    let config = node::default_config(std::slice::from_ref(&endpoint), &[]).unwrap();
    let mut node = within("open node", Node::open(config, prefix.clone(), Arc::new(world.clone()), req_tx.clone()))
        .await
        .expect("node opens");

    // The step loop, real time, on its own thread.
    let (frame_tx, mut frame_rx) = tokio::sync::mpsc::channel::<Frame>(256);
    let stop = Arc::new(AtomicBool::new(false));
    let stop2 = stop.clone();
    let loop_thread = std::thread::spawn(move || {
        let state = world.initial_state();
        let inputs = world.initial_inputs();
        let opts = LoopOptions { realtime: true, ticks: 20 * 120, ..LoopOptions::default() };
        engine::run_watched(world, state, inputs, req_rx, Some(frame_tx), (), &stop2, &opts)
    });
    let publisher = tokio::spawn(async move {
        while let Some(frame) = frame_rx.recv().await {
            node.publish(&frame).await.expect("publish");
        }
        node
    });

    // A real client session, connecting over loopback.
    let client = within("open client", zenoh::open(node::client_config(&[endpoint]).unwrap())).await.unwrap();
    let states: Arc<std::sync::Mutex<Vec<StateMsg>>> = Arc::default();
    let states2 = states.clone();
    let _sub = within(
        "subscribe",
        client.declare_subscriber(format!("{prefix}/copters/*/state")).callback(move |s| {
            if let Ok(m) = serde_json::from_slice::<StateMsg>(&s.payload().to_bytes()) {
                states2.lock().unwrap().push(m);
            }
        }),
    )
    .await
    .unwrap();
    let latest = |name: &str| states.lock().unwrap().iter().rev().find(|m| m.name == name).cloned();
    eventually("first state of finken1", || latest("finken1").is_some()).await;

    // Liveliness: the simulator's token, and ours tracked by the simulator.
    let token =
        within("token", client.liveliness().declare_token(format!("{prefix}/alive/copters/tester"))).await.unwrap();
    let replies = within("liveliness get", client.liveliness().get(format!("{prefix}/alive/sim"))).await.unwrap();
    let sim_alive = within("liveliness reply", replies.recv_async()).await.is_ok();
    assert!(sim_alive, "the simulator declares a liveliness token");

    // A malformed payload is ignored and counted; the stream goes on.
    let bad_key = format!("{prefix}/copters/finken1/cmd");
    for payload in ["not json", r#"{"pitch": "fast"}"#, r#"{"throttle": 7}"#, r#"{"bogus": 1}"#] {
        within("put bad", client.put(&bad_key, payload)).await.unwrap();
    }
    within("put to unknown copter", client.put(format!("{prefix}/copters/nobody/cmd"), "{}")).await.unwrap();

    // Command → state: fly finken1 to a target at 1.2 m.
    let cmd = r#"{"mode":"target","target":[-0.8,0.0,1.2],"height":1.2}"#;
    within("put cmd", client.put(&bad_key, cmd)).await.unwrap();
    eventually("finken1 climbs above 1.1 m", || {
        latest("finken1").is_some_and(|m| m.pos_m[2] > 1.1 && m.mode == "target")
    })
    .await;
    let n_before = states.lock().unwrap().len();
    eventually("the stream continues", || states.lock().unwrap().len() > n_before + 4).await;

    // Queryables.
    let scene = within("get scene", client.get(format!("{prefix}/scene"))).await.unwrap();
    let reply = within("scene reply", scene.recv_async()).await.unwrap();
    let scene_json: serde_json::Value = serde_json::from_slice(&reply.result().unwrap().payload().to_bytes()).unwrap();
    assert_eq!(scene_json["name"], "lab");
    assert_eq!(scene_json["arena"]["size_m"], serde_json::json!([4.0, 3.0]));

    let spawn = r#"{"name":"newbie","start":{"pos_m":[0.0,0.6]},"mode":"mixed_manual","command":{"height_m":0.5}}"#;
    let replies = within("spawn", client.get(format!("{prefix}/spawn")).payload(spawn)).await.unwrap();
    let reply = within("spawn reply", replies.recv_async()).await.unwrap();
    let ok = reply.result().map(|s| String::from_utf8_lossy(&s.payload().to_bytes()).into_owned());
    assert_eq!(ok.as_deref(), Ok(r#"{"spawned":"newbie"}"#));
    eventually("the spawned copter publishes", || latest("newbie").is_some()).await;

    let bad_spawn = r#"{"name":"newbie","start":{"pos_m":[1.0,1.0]}}"#;
    let replies = within("spawn dup", client.get(format!("{prefix}/spawn")).payload(bad_spawn)).await.unwrap();
    let reply = within("spawn dup reply", replies.recv_async()).await.unwrap();
    let err =
        reply.result().err().map(|e| String::from_utf8_lossy(&e.payload().to_bytes()).into_owned()).unwrap_or_default();
    assert!(err.contains("already used"), "duplicate spawn refused with a reason: {err}");

    let list = within("get copters", client.get(format!("{prefix}/copters"))).await.unwrap();
    let reply = within("copters reply", list.recv_async()).await.unwrap();
    let copters: Vec<CopterListEntry> = serde_json::from_slice(&reply.result().unwrap().payload().to_bytes()).unwrap();
    assert_eq!(copters.iter().map(|c| c.name.as_str()).collect::<Vec<_>>(), ["finken1", "finken2", "newbie"]);

    // Shut down: stop the loop, collect the node, check its counters, close sessions.
    token.undeclare().wait().unwrap();
    stop.store(true, Ordering::Relaxed);
    let (_, _, stats, _) = loop_thread.join().unwrap();
    let node = within("publisher ends", publisher).await.unwrap();
    assert!(stats.commands_applied >= 1);
    assert_eq!(stats.spawned, 1);
    assert_eq!(node.counters.commands_rejected.load(Ordering::Relaxed), 5, "4 malformed + 1 unknown copter");
    assert!(node.counters.clients_seen.load(Ordering::Relaxed) >= 1, "our liveliness token was seen");
    within("close node", node.close()).await.unwrap();
    within("close client", client.close()).await.unwrap();
    drop(req_tx);
}
