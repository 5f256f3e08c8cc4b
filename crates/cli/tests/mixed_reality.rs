//! Mixed reality end to end, through the binary: `twinswarm run` on the mixed lab scene and a
//! `twinswarm copter` stand-in for FINken_01 (ac_id 5), on a real Zenoh session on loopback.
//!
//! - The stand-in flies towards a box that exists **only** in the main simulation. Alone it
//!   flies into it; with its twin's virtual sonar it turns away.
//! - The twin's attitude follows the stand-in's: the RMS error is reported and bounded.
//! - The virtual copter's telemetry decodes with the project's messages.xml codec, at the
//!   plan's rates.
//! - Telemetry from FINken_03 (ac_id 7, in conf.xml, not twinned) spawns its twin; telemetry
//!   from ac_id 42 (not in conf.xml, policy `ignore`) is dropped and counted.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

fn assets() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets")
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free loopback port")
}

/// The ghost box of `assets/scenes/mixed_lab.toml`: centre x 0.6, 0.3 m deep, y in ±1.0.
const GHOST_FACE_X_M: f64 = 0.45;

struct Track {
    max_x_m: f64,
    min_ghost_distance_m: f64,
    rows: usize,
}

fn read_track(path: &Path) -> Track {
    let text = std::fs::read_to_string(path).expect("track CSV");
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap_or_else(|| panic!("no column {name}"));
    let (cx, cy) = (col("x_m"), col("y_m"));
    let mut t = Track { max_x_m: f64::NEG_INFINITY, min_ghost_distance_m: f64::INFINITY, rows: 0 };
    for line in lines {
        let v: Vec<f64> = line.split(',').map(|s| s.parse().expect("number")).collect();
        let (x, y) = (v[cx], v[cy]);
        let dx = ((x - 0.6).abs() - 0.15).max(0.0);
        let dy = (y.abs() - 1.0).max(0.0);
        t.max_x_m = t.max_x_m.max(x);
        t.min_ghost_distance_m = t.min_ghost_distance_m.min(dx.hypot(dy));
        t.rows += 1;
    }
    t
}

fn stand_in(extra: &[&str], track: &Path) -> Value {
    let scene = assets().join("scenes/mixed_lab.toml");
    let pairing = assets().join("pairing/mixed_lab.xml");
    let out = Command::new(env!("CARGO_BIN_EXE_twinswarm"))
        .arg("copter")
        .arg(&scene)
        .arg("--pairing")
        .arg(&pairing)
        // 0.4 m/s, open loop: the AHRS's wandering tilt bias (σ 0.15°) alone is worth ±0.07 m/s,
        // and 16 s must bring the control flight to the ghost box.
        .args(["--ac-id", "5", "--velocity", "0.4,0", "--duration", "16", "--json", "--track"])
        .arg(track)
        .args(extra)
        .output()
        .expect("run twinswarm copter");
    assert!(out.status.success(), "stand-in failed: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).expect("stand-in JSON")
}

/// No crash while the stand-in flew (16 s, started after the simulation). Once its telemetry
/// stops, its twin levels out and coasts on: into the ghost box, if the stand-in's last
/// attitude sent it that way, is a crash the simulation rightly records.
fn assert_no_crash_while_the_stand_in_flew(summary: &Value) {
    let crashes = summary["crashes"].as_array().cloned().unwrap_or_default();
    assert!(crashes.iter().all(|c| c["time_s"].as_f64().unwrap_or(0.0) > 16.0), "{}", summary["crashes"]);
}

#[test]
fn a_stand_in_turns_away_from_a_virtual_box_and_its_twin_follows_it() {
    let dir = std::env::temp_dir().join(format!("twinswarm-mr-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();

    // Control: the stand-in alone flies into the ghost box (it is not in its reality).
    let alone = read_track(&{
        let p = dir.join("alone.csv");
        stand_in(&["--no-bus"], &p);
        p
    });
    println!("alone: max x {:.2} m, closest to the ghost {:.2} m", alone.max_x_m, alone.min_ghost_distance_m);
    assert!(alone.max_x_m > GHOST_FACE_X_M, "the control flight should reach the ghost box");

    // The main simulation, real time, on its own port and prefix.
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let prefix = format!("twinswarm-test-{port}/mixed_lab");
    let main = Command::new(env!("CARGO_BIN_EXE_twinswarm"))
        .arg("run")
        .arg(assets().join("scenes/mixed_lab.toml"))
        .arg("--pairing")
        .arg(assets().join("pairing/mixed_lab.xml"))
        .args(["--realtime", "--duration", "20", "--twin-attitude", "measured", "--json", "--log"])
        .arg(dir.join("main.mcap"))
        .args(["--listen", &endpoint, "--prefix", &prefix])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start twinswarm run");

    // A ground-side client: watch the virtual copter's telemetry, and play two other aircraft.
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let (client, virtual_rx) = rt.block_on(async {
        let config = bridge::zenoh_net::node::client_config(std::slice::from_ref(&endpoint)).unwrap();
        let deadline = Instant::now() + Duration::from_secs(20);
        let client = loop {
            match zenoh::open(config.clone()).await {
                Ok(s) => break s,
                Err(e) if Instant::now() > deadline => panic!("cannot connect to the simulator: {e}"),
                Err(_) => tokio::time::sleep(Duration::from_millis(200)).await,
            }
        };
        let sub = client.declare_subscriber(format!("{prefix}/pprz/101/*")).await.unwrap();
        (client, sub)
    });

    // The stand-in, connected to the simulator (it flies while the simulator runs).
    let track_path = dir.join("mixed.csv");
    let stand_in_thread = {
        let (endpoint, prefix, track_path) = (endpoint.clone(), prefix.clone(), track_path.clone());
        std::thread::spawn(move || stand_in(&["--connect", &endpoint, "--prefix", &prefix], &track_path))
    };

    // 3 s of the virtual copter's telemetry; then FINken_03 and an unknown aircraft speak.
    let received: Vec<String> = rt.block_on(async {
        let mut texts = Vec::new();
        let until = tokio::time::Instant::now() + Duration::from_secs(3);
        while let Ok(Ok(sample)) = tokio::time::timeout_at(until, virtual_rx.recv_async()).await {
            texts.push(sample.payload().try_to_string().unwrap().into_owned());
        }
        for k in 0..10 {
            for text in [format!("7 ATTITUDE 0.0{k} 0.0 0.0"), format!("42 ATTITUDE 0.0{k} 0.0 0.0")] {
                let key = bridge::key_for_text(&prefix, &text).unwrap();
                client.put(key, text).await.unwrap();
            }
            tokio::time::sleep(Duration::from_millis(30)).await;
        }
        // Let the puts drain before leaving.
        tokio::time::sleep(Duration::from_millis(300)).await;
        drop(virtual_rx);
        client.close().await.expect("close the client session");
        texts
    });

    let stand_in_summary = stand_in_thread.join().expect("stand-in thread");
    let out = main.wait_with_output().expect("twinswarm run finishes");
    assert!(out.status.success(), "twinswarm run failed: {}", String::from_utf8_lossy(&out.stderr));
    let summary: Value = serde_json::from_slice(&out.stdout).expect("run JSON");

    // The virtual copter's telemetry decodes, at the plan's rates (capped at the 20 Hz
    // control rate).
    let messages = bridge::paparazzi::convert::project_messages();
    let mut counts: BTreeMap<String, usize> = BTreeMap::new();
    for text in &received {
        let msg = messages.decode(text).unwrap_or_else(|e| panic!("{text:?} does not decode: {e}"));
        assert_eq!(msg.sender.ac_id(), Some(101), "{text}");
        *counts.entry(msg.def.name.clone()).or_default() += 1;
    }
    println!("virtual copter telemetry in 3 s: {counts:?}");
    let plan = bridge::mixed::plan::TelemetryPlan::project_default();
    for (name, period) in &plan.periods {
        // INS_REF (5.1 s) may fall outside a 3 s window; the registration messages' order and
        // content are tested in the bridge (mixed.rs) and against ivy-python (test_ivy.py).
        if *period > 3.0 {
            continue;
        }
        let expected = 3.0 / period.max(0.05);
        let got = counts.get(name).copied().unwrap_or(0) as f64;
        assert!(got >= 0.7 * expected && got <= 1.3 * expected + 1.0, "{name}: {got} in 3 s, expected {expected:.0}");
    }

    // The stand-in used its twin's virtual sonar and turned away from the ghost.
    let mixed = read_track(&track_path);
    println!(
        "stand-in with its twin: max x {:.2} m, closest to the ghost {:.2} m, {} virtual sonar readings; {}",
        mixed.max_x_m, mixed.min_ghost_distance_m, stand_in_summary["virtual_sonar_received"], stand_in_summary
    );
    assert!(mixed.rows > 250, "the stand-in flew {} steps", mixed.rows);
    assert!(stand_in_summary["virtual_sonar_received"].as_u64().unwrap_or(0) > 100);
    assert!(mixed.max_x_m < GHOST_FACE_X_M, "the stand-in entered the virtual box (max x {:.2} m)", mixed.max_x_m);
    assert!(mixed.min_ghost_distance_m > 0.05);

    // The twin followed: attitude RMS, inputs, latency.
    let twin = &summary["twins"]["finken_01"];
    println!("twin finken_01: {twin}; crashes {}", summary["crashes"]);
    let rms = [twin["attitude_rms_deg"][0].as_f64().unwrap(), twin["attitude_rms_deg"][1].as_f64().unwrap()];
    assert!(twin["attitude_samples"].as_u64().unwrap() > 200, "{twin}");
    assert!(rms[0] < 3.0 && rms[1] < 3.0, "twin attitude RMS {rms:?} deg");
    assert!(twin["inputs_applied"].as_u64().unwrap() > 500, "{twin}");
    assert!(twin["input_latency_ms"]["p99"].as_f64().unwrap() < 200.0, "{twin}");
    assert_no_crash_while_the_stand_in_flew(&summary);

    // Spawn and unknown-aircraft policy.
    let telemetry = &summary["bus"]["telemetry"];
    assert_eq!(telemetry["spawned"], serde_json::json!(["finken_03"]), "{telemetry}");
    assert_eq!(telemetry["unknown_dropped"]["42"], 10, "{telemetry}");
    assert!(summary["twins"]["finken_03"]["spawned"].as_bool().unwrap_or(false), "{}", summary["twins"]);
    let _ = std::fs::remove_dir_all(&dir);
}

fn free_udp_port() -> u16 {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .and_then(|s| s.local_addr())
        .map(|a| a.port())
        .expect("a free loopback UDP port")
}

/// The same loop with no Zenoh at all: the simulator and the stand-in are two agents on one
/// real Ivy bus (loopback broadcast on a free port), as the simulator and a copter behind
/// Paparazzi's `link` would be.
#[test]
fn the_full_loop_runs_over_a_real_ivy_bus() {
    let dir = std::env::temp_dir().join(format!("twinswarm-mr-ivy-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let bus = format!("127.255.255.255:{}", free_udp_port());
    let main = Command::new(env!("CARGO_BIN_EXE_twinswarm"))
        .arg("run")
        .arg(assets().join("scenes/mixed_lab.toml"))
        .arg("--pairing")
        .arg(assets().join("pairing/mixed_lab.xml"))
        .args(["--realtime", "--duration", "19", "--twin-attitude", "measured", "--json", "--no-log"])
        .args(["--no-bus", "--ivy", &bus])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start twinswarm run");
    std::thread::sleep(Duration::from_millis(800));
    let track_path = dir.join("ivy.csv");
    let stand_in_summary = stand_in(&["--ivy", &bus], &track_path);
    let out = main.wait_with_output().expect("twinswarm run");
    assert!(out.status.success(), "twinswarm run failed: {}", String::from_utf8_lossy(&out.stderr));
    let summary: Value = serde_json::from_slice(&out.stdout).expect("run JSON");
    let mixed = read_track(&track_path);
    println!(
        "over ivy: max x {:.2} m, closest to the ghost {:.2} m, virtual sonar {}; ivy {}",
        mixed.max_x_m, mixed.min_ghost_distance_m, stand_in_summary["virtual_sonar_received"], summary["bus"]["ivy"]
    );
    assert!(stand_in_summary["virtual_sonar_received"].as_u64().unwrap_or(0) > 100, "{stand_in_summary}");
    assert!(mixed.max_x_m < GHOST_FACE_X_M, "the stand-in entered the virtual box (max x {:.2} m)", mixed.max_x_m);
    let twin = &summary["twins"]["finken_01"];
    assert!(twin["inputs_applied"].as_u64().unwrap() > 500, "{twin}");
    assert_no_crash_while_the_stand_in_flew(&summary);
    let ivy = &summary["bus"]["ivy"];
    assert!(ivy["peers_joined"].as_u64().unwrap() >= 1, "{ivy}");
    let _ = std::fs::remove_dir_all(&dir);
}
