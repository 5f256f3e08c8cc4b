//! Sharded runs that survive a lost process: `cluster --checkpoint-every` restarts every
//! shard from the last checkpoint they all have when one is SIGKILLed, and ends with the
//! uninterrupted run's bits and a merged log with every copter's state once per step; `run
//! --resume` refuses checkpoints of another run, naming the file.

use std::collections::BTreeMap;
use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use bridge::log::proto::{CopterState, LogRecord};

fn twinswarm(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_twinswarm")).args(args).output().expect("run twinswarm");
    (out.status.success(), String::from_utf8_lossy(&out.stdout).into(), String::from_utf8_lossy(&out.stderr).into())
}

fn json(text: &str) -> serde_json::Value {
    serde_json::from_str(text.trim()).unwrap_or_else(|e| panic!("{e}: {text}"))
}

fn tmp(tag: &str) -> PathBuf {
    let p = std::env::temp_dir().join(format!("twinswarm-ckpt-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&p);
    p
}

/// The flock of tests/shard.rs: 144 copters crossing the borders, with crashes.
fn flock_scene(tag: &str) -> PathBuf {
    let (ok, toml, err) = twinswarm(&["scene", "flock", "--n", "144", "--seed", "3"]);
    assert!(ok, "{err}");
    let mut spec: sim_core::SceneSpec = toml::from_str(&toml).expect("the generated scene parses");
    spec.sensors.sonar.schedule = sim_core::sensors::SonarSchedule::Together;
    (spec.sensors.crosstalk.cycle_s, spec.sensors.crosstalk.cycle_spread) = (0.049, 0.002);
    let path = tmp(&format!("{tag}.toml"));
    std::fs::write(&path, toml::to_string(&spec).unwrap()).unwrap();
    path
}

fn digests(summary: &serde_json::Value) -> Vec<(u64, String)> {
    let mut v: Vec<(u64, String)> = summary["copters"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| (c["id"].as_u64().unwrap(), c["digest"].as_str().unwrap().to_owned()))
        .collect();
    v.sort();
    v
}

/// Merges every log of `dir` and returns its `/copters/state` messages by (copter, tick),
/// failing on any (copter, tick) written twice.
fn merged_states(dir: &Path) -> BTreeMap<(u32, u64), Vec<u8>> {
    let mut inputs: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "mcap"))
        .collect();
    inputs.sort();
    let out = dir.with_extension("merged.mcap");
    bridge::log::merge(&inputs, &out).unwrap_or_else(|e| panic!("merge {inputs:?}: {e}"));
    let file = bridge::log::LogFile::open(&out).unwrap();
    let mut states = BTreeMap::new();
    file.for_each_message(&["/copters/state"], |_, _, data| {
        let s = CopterState::decode_as("protobuf", data).unwrap();
        let again = states.insert((s.id, s.tick), data.to_vec());
        assert!(again.is_none(), "copter {} at tick {} is in the merged log twice", s.id, s.tick);
        Ok(())
    })
    .unwrap();
    let _ = std::fs::remove_file(out);
    states
}

/// The pid the cluster printed for `shard` in its first segment.
fn pid_of(line: &str, shard: &str) -> Option<u32> {
    let rest = line.strip_prefix(&format!("cluster: shard {shard} started, pid "))?;
    rest.split_whitespace().next()?.parse().ok()
}

#[test]
fn a_cluster_survives_a_killed_shard_with_the_uninterrupted_bits_and_one_log() {
    let scene = flock_scene("kill");
    let scene = scene.to_str().unwrap();
    let base = tmp("kill");
    let (straight_logs, restarted_logs) = (base.join("straight"), base.join("restarted"));
    let cluster = ["cluster", scene, "--shards", "3", "--no-bus", "--duration", "60", "--json", "--log-dir"];

    // Uninterrupted.
    let t0 = Instant::now();
    let (ok, out, err) = twinswarm(&[&cluster[..], &[straight_logs.to_str().unwrap()]].concat());
    assert!(ok, "{err}");
    let straight = json(&out);
    eprintln!("uninterrupted cluster: {:.1} s", t0.elapsed().as_secs_f64());

    // With checkpoints every 5 s, shard 1 killed once it has one.
    let t0 = Instant::now();
    let ckpt_dir = base.join("checkpoints");
    let mut child = Command::new(env!("CARGO_BIN_EXE_twinswarm"))
        .args(cluster)
        .arg(&restarted_logs)
        .args(["--checkpoint-every", "5", "--checkpoint-dir"])
        .arg(&ckpt_dir)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = child.stderr.take().unwrap();
    let (pid_tx, pid_rx) = std::sync::mpsc::channel();
    let err_reader = std::thread::spawn(move || {
        let mut all = String::new();
        for line in std::io::BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(pid) = pid_of(&line, "1/3") {
                let _ = pid_tx.send(pid);
            }
            all.push_str(&line);
            all.push('\n');
        }
        all
    });
    let victim = pid_rx.recv_timeout(Duration::from_secs(30)).expect("the cluster printed shard 1's pid");
    let deadline = Instant::now() + Duration::from_secs(30);
    while bridge::engine::checkpoint::list(&ckpt_dir, "shard-1-of-3").unwrap().is_empty() {
        assert!(Instant::now() < deadline, "no checkpoint of shard 1 within 30 s");
        std::thread::sleep(Duration::from_millis(5));
    }
    let killed = Command::new("kill").args(["-KILL", &victim.to_string()]).status().unwrap();
    assert!(killed.success(), "kill -KILL {victim}");
    let out = child.wait_with_output().unwrap();
    let err = err_reader.join().unwrap();
    assert!(out.status.success(), "{err}");
    let restarted = json(&String::from_utf8_lossy(&out.stdout));
    eprintln!("cluster with a restart: {:.1} s", t0.elapsed().as_secs_f64());

    // It restarted once, by itself, from a checkpoint.
    let restarts = restarted["restarts"].as_array().unwrap();
    assert_eq!(restarts.len(), 1, "one restart (was the run over before the kill?): {err}");
    assert_eq!(restarts[0]["shard"], 1);
    let from_tick = restarts[0]["from_tick"].as_u64().unwrap();
    assert!(from_tick >= 100 && from_tick.is_multiple_of(100), "from a checkpoint tick: {from_tick}");
    assert!(err.contains("shard 1/3 died"), "{err}");
    // The last segment's speed and work are of what it flew, from the checkpoint on.
    let flown_from = 60.0 - from_tick as f64 * 0.05;
    for s in restarted["per_shard"].as_array().unwrap() {
        assert!((s["flown_s"].as_f64().unwrap() - flown_from).abs() < 1e-6, "{s}");
        let (rtf, wall) = (s["real_time_factor"].as_f64().unwrap(), s["wall_time_s"].as_f64().unwrap());
        assert!((rtf * wall - flown_from).abs() < 1e-3, "shard speed {rtf} over {wall} s: not of {flown_from} s flown");
    }

    // The bits of the uninterrupted run, every copter.
    assert_eq!(digests(&straight).len(), 144);
    assert_eq!(digests(&restarted), digests(&straight), "every copter's digest as uninterrupted");
    assert_eq!(restarted["digest"], straight["digest"]);

    // The merged logs: each (copter, tick) once; every state of the uninterrupted log, with
    // its bytes. A restored shard writes every copter at its first step, also those the
    // uninterrupted log held (unchanged since their last message): the only extra states.
    let (a, b) = (merged_states(&straight_logs), merged_states(&restarted_logs));
    for (key, bytes) in &a {
        assert_eq!(b.get(key), Some(bytes), "copter {} at tick {}: the uninterrupted state", key.0, key.1);
    }
    for key in b.keys().filter(|k| !a.contains_key(k)) {
        assert_eq!(key.1, from_tick + 1, "copter {} at tick {}: not in the uninterrupted log", key.0, key.1);
    }
    let ticks: std::collections::BTreeSet<u64> = b.keys().map(|k| k.1).collect();
    assert_eq!(ticks.len(), 1200, "every step of the minute");
    let _ = std::fs::remove_dir_all(base);
    let _ = std::fs::remove_file(scene);
}

#[test]
fn resume_refuses_a_checkpoint_of_another_run_naming_the_file() {
    let scene = flock_scene("refuse");
    let scene = scene.to_str().unwrap();
    let dir = tmp("refuse");
    let dir_s = dir.to_str().unwrap();
    let run = ["run", scene, "--no-bus", "--no-log", "--json"];
    let (ok, out, err) =
        twinswarm(&[&run[..], &["--duration", "4", "--checkpoint-every", "2", "--checkpoint-dir", dir_s]].concat());
    assert!(ok, "{err}");
    let whole = json(&out);
    let ckpt = dir.join("run-tick-000000000040.ckpt");
    assert_eq!(whole["checkpoints"]["written"], 2);
    let ckpt_s = ckpt.to_str().unwrap();

    // The same run, resumed from 2 s: the same bits at 4 s.
    let (ok, out, err) = twinswarm(
        &[&run[..], &["--duration", "4", "--resume", dir.join("run-tick-000000000040.ckpt").to_str().unwrap()]]
            .concat(),
    );
    assert!(ok, "{err}");
    let resumed = json(&out);
    assert_eq!(digests(&resumed), digests(&whole));
    // Its speed is of the 2 s it flew, not of the 4 s its state reached.
    let (flown, wall, rtf) = (
        resumed["flown_s"].as_f64().unwrap(),
        resumed["wall_time_s"].as_f64().unwrap(),
        resumed["real_time_factor"].as_f64().unwrap(),
    );
    assert!((flown - 2.0).abs() < 1e-9 && resumed["sim_time_s"] == 4.0, "{resumed}");
    assert!((rtf * wall - flown).abs() < 1e-6, "real time factor {rtf} over {wall} s wall is not the 2 s flown");
    let cpu_per_sim_s = resumed["cpu_per_sim_s"].as_f64().unwrap();
    assert!((cpu_per_sim_s * flown - resumed["cpu_s"].as_f64().unwrap()).abs() < 1e-6, "{resumed}");

    let damaged = dir.join("damaged.ckpt");
    let mut bytes = std::fs::read(&ckpt).unwrap();
    let at = bytes.len() - 100;
    bytes[at] ^= 1;
    std::fs::write(&damaged, bytes).unwrap();
    let damaged_s = damaged.to_str().unwrap();
    for (extra, file, what) in [
        (vec!["--seed", "99"], ckpt_s, "it is of seed"),
        (vec!["--shard", "0/2", "--connect", "tcp/127.0.0.1:9"], ckpt_s, "this run is shard 0/2"),
        (vec![], damaged_s, "is damaged"),
        (vec![], scene, "is damaged: not a twinswarm checkpoint"),
    ] {
        let (ok, _, err) = twinswarm(&[&run[..], &extra[..], &["--resume", file]].concat());
        assert!(!ok, "{extra:?} {file}");
        assert!(err.contains(file) && err.contains(what), "{extra:?}: {err}");
        assert!(!err.contains("panicked"), "{err}");
    }
    let (ok, _, err) = twinswarm(&[&run[..], &["--checkpoint-every", "1"]].concat());
    assert!(!ok && err.contains("--checkpoint-dir"), "{err}");
    let _ = std::fs::remove_dir_all(dir);
    let _ = std::fs::remove_file(scene);
}
