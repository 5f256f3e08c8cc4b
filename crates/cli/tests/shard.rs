//! Sharding across processes, on loopback: `twinswarm cluster` (a Zenoh router and N shard
//! processes) gives the one-process bits for every copter over a minute, and a shard that dies stops its neighbour with a
//! clear error instead of a hang.

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn twinswarm(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_twinswarm")).args(args).output().expect("run twinswarm");
    (out.status.success(), String::from_utf8_lossy(&out.stdout).into(), String::from_utf8_lossy(&out.stderr).into())
}

/// `twinswarm scene flock --n 144 --seed 3`, with free-running sonars: with the firmware's
/// round robin no two of its copters meet, and the test is about crashes across borders too.
fn flock_scene(tag: &str) -> PathBuf {
    let (ok, toml, err) = twinswarm(&["scene", "flock", "--n", "144", "--seed", "3"]);
    assert!(ok, "{err}");
    let mut spec: sim_core::SceneSpec = toml::from_str(&toml).expect("the generated scene parses");
    spec.sensors.sonar.schedule = sim_core::sensors::SonarSchedule::Together;
    (spec.sensors.crosstalk.cycle_s, spec.sensors.crosstalk.cycle_spread) = (0.049, 0.002);
    scene_file(tag, &spec)
}

/// A scene file made from a generated scene.
fn scene_file(tag: &str, spec: &sim_core::SceneSpec) -> PathBuf {
    let path = std::env::temp_dir().join(format!("twinswarm-shard-{tag}-{}.toml", std::process::id()));
    std::fs::write(&path, toml::to_string(spec).unwrap()).unwrap();
    path
}

/// Every copter's `(id, digest)` in a run's or a cluster's JSON summary, in id order.
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

/// Bytes free in `/dev/shm`, where Zenoh keeps its shared memory (none: no such file system).
fn shared_memory_room() -> Option<u64> {
    let out = Command::new("df").args(["--output=avail", "-B1", "/dev/shm"]).output().ok()?;
    String::from_utf8_lossy(&out.stdout).lines().nth(1)?.trim().parse().ok()
}

#[test]
fn a_minute_over_processes_is_the_same_minute_in_one_process() {
    // 60 s of the flock: copters cross the borders, and crashes happen on the way.
    let scene = flock_scene("bits");
    let scene = scene.to_str().unwrap();
    let (ok, out, err) = twinswarm(&["run", scene, "--no-bus", "--no-log", "--duration", "60", "--json"]);
    assert!(ok, "{err}");
    let one = json(&out);
    let copters = digests(&one);
    assert_eq!(copters.len(), 144);
    let cpu = one["cpu_s"].as_f64().expect("the run's CPU time");
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get()) as f64;
    let wall = one["wall_time_s"].as_f64().unwrap();
    assert!(cpu > 0.0 && cpu <= wall * cores + 0.5, "CPU {cpu} s against {wall} s wall on {cores} cores");
    let crashed = one["copters"].as_array().unwrap().iter().filter(|c| c["crashed"] == true).count();
    assert!(crashed > 0, "the flock has crashes to agree on");
    // Shards on two threads each too: a shard's step merges its threads' work in id order.
    for (shards, threads) in [("2", "1"), ("3", "1"), ("4", "1"), ("2", "2")] {
        let (ok, out, err) =
            twinswarm(&["cluster", scene, "--shards", shards, "--threads", threads, "--duration", "60", "--json"]);
        assert!(ok, "{shards} shards: {err}");
        let c = json(&out);
        assert_eq!(digests(&c), copters, "{shards} shards: every copter, once, with the one-process bits");
        let per_shard = c["per_shard"].as_array().unwrap();
        let taken: u64 = per_shard.iter().map(|s| s["shard"]["taken_over"].as_u64().unwrap()).sum();
        assert!(taken > 0, "{shards} shards: copters migrated");
        let mut cpu = c["launcher_cpu_s"].as_f64().expect("the launcher's CPU time");
        let mut in_shm = 0;
        for s in per_shard {
            let link = &s["shard"]["link"];
            assert_eq!(link["exchanges"].as_u64(), Some(1200), "{shards} shards: one barrier per step: {s}");
            assert!(link["bytes_sent"].as_u64().unwrap() > 0);
            let (received, shm) =
                (link["batches_received"].as_u64().unwrap(), link["batches_in_shm"].as_u64().unwrap());
            assert!(received >= 1200 && shm <= received, "{link}");
            in_shm += shm;
            let shard_cpu = s["cpu_s"].as_f64().expect("each shard's CPU time");
            assert!(shard_cpu > 0.0 && shard_cpu <= s["wall_time_s"].as_f64().unwrap() * cores + 0.5, "{s}");
            cpu += shard_cpu;
        }
        let per_sim_s = c["cpu_per_sim_s"].as_f64().expect("CPU per simulated second");
        assert!((per_sim_s - cpu / 60.0).abs() < 1e-9, "{shards} shards: {per_sim_s} against {cpu} s over 60 s");
        // Shards on one machine hand their batches over in shared memory, not through the
        // sockets (all but those sent before Zenoh's pool was set up, and any under 3 kB).
        match shared_memory_room() {
            Some(free) if free >= 128 << 20 => {
                assert!(in_shm > 0, "{shards} shards: no batch came in shared memory ({free} B free in /dev/shm)")
            }
            free => eprintln!("{shards} shards: {in_shm} batches in shared memory; /dev/shm has {free:?} B free"),
        }
    }
    let _ = std::fs::remove_file(scene);
}

#[test]
fn a_crowded_take_off_over_processes_is_the_one_process_take_off() {
    // 400 copters taking off from a 1.5 m grid among 12 pillars: most crash within the minute,
    // wrecks fall across borders and onto each other.
    let path = scene_file("dense", &sim_core::scene::dense_swarm(400, 1.5, true, 12, 3));
    let scene = path.to_str().unwrap();
    let (ok, out, err) = twinswarm(&["run", scene, "--no-bus", "--no-log", "--duration", "60", "--json"]);
    assert!(ok, "{err}");
    let one = json(&out);
    let crashed = one["copters"].as_array().unwrap().iter().filter(|c| c["crashed"] == true).count();
    assert!(crashed > 100, "{crashed} crashed");
    for shards in ["2", "4"] {
        let (ok, out, err) =
            twinswarm(&["cluster", scene, "--shards", shards, "--no-bus", "--duration", "60", "--json"]);
        assert!(ok, "{shards} shards: {err}");
        assert_eq!(digests(&json(&out)), digests(&one), "{shards} shards: the one-process bits");
    }
    let _ = std::fs::remove_file(path);
}

#[test]
fn a_crash_across_a_border_over_processes_is_the_one_process_crash() {
    // Two copters meeting head-on over the border between two strips: the lower id's shard
    // takes the other over and steps the pair.
    let mut spec = sim_core::scene::dense_swarm(2, 3.0, false, 0, 1);
    spec.arena.size_m = [12.0, 6.0];
    for (c, x) in spec.copters.iter_mut().zip([-1.5_f32, 1.5]) {
        c.mode = sim_core::FlightMode::Target;
        c.start.pos_m = [x, 0.0];
        c.command.target_m = Some([-3.0 * x, 0.0, 1.0]);
    }
    let path = scene_file("headon", &spec);
    let scene = path.to_str().unwrap();
    let (ok, out, err) = twinswarm(&["run", scene, "--no-bus", "--no-log", "--duration", "10", "--json"]);
    assert!(ok, "{err}");
    let one = json(&out);
    assert!(one["copters"].as_array().unwrap().iter().all(|c| c["crashed"] == true), "both crash: {one}");
    let (ok, out, err) = twinswarm(&["cluster", scene, "--shards", "2", "--no-bus", "--duration", "10", "--json"]);
    assert!(ok, "{err}");
    let c = json(&out);
    assert_eq!(digests(&c), digests(&one));
    // Shard 0 took copter 1 over for the crash (its wreck may go home once the two lie apart).
    assert!(c["per_shard"][0]["shard"]["taken_over"].as_u64() >= Some(1), "shard 0 took copter 1 over: {c}");
    let _ = std::fs::remove_file(path);
}

fn json(text: &str) -> serde_json::Value {
    serde_json::from_str(text.trim()).unwrap_or_else(|e| panic!("{e}: {text}"))
}

/// Two shards of the flock stepping in real time for up to 10 minutes, peer to peer (shard 0
/// listens, shard 1 connects), with a 60 s barrier timeout: `(shard 0, shard 1)`, once shard 1
/// has stepped with its neighbour for a second.
fn two_shards_stepping(scene: &std::path::Path, tag: &str) -> (std::process::Child, std::process::Child) {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let prefix = format!("twinswarm/test-{tag}-{port}");
    let spawn = |k: &str, net: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_twinswarm"))
            .args(["run", scene.to_str().unwrap(), "--shard", k, "--duration", "600", "--realtime"])
            .args(["--prefix", &prefix, "--barrier-timeout", "60"])
            .args(net)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    let first = spawn("0/2", &["--listen", &endpoint]);
    std::thread::sleep(Duration::from_millis(500));
    let mut second = spawn("1/2", &["--connect", &endpoint]);
    let mut lines = std::io::BufRead::lines(std::io::BufReader::new(second.stderr.take().unwrap()));
    let up = lines.find_map(|l| l.ok().filter(|l| l.contains("neighbour(s) up")));
    assert!(up.is_some(), "shard 1 never started stepping");
    std::thread::sleep(Duration::from_secs(1));
    (first, second)
}

fn signal(child: &std::process::Child, sig: &str) {
    assert!(Command::new("kill").args([sig, &child.id().to_string()]).status().unwrap().success());
}

#[test]
fn a_shard_that_dies_stops_its_neighbour_with_a_reason() {
    let scene = flock_scene("die");
    let (survivor, mut victim) = two_shards_stepping(&scene, "die");
    victim.kill().unwrap();
    victim.wait().unwrap();
    let killed_at = Instant::now();
    let out = survivor.wait_with_output().unwrap();
    let took = killed_at.elapsed();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("shard 1 left the cluster"), "{err}");
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(summary.contains("stopped by its shard link"), "the summary says why it stopped: {summary}");
    // Liveliness, not the 60 s barrier timeout.
    assert!(took < Duration::from_secs(20), "noticed after {took:?}");
    let _ = std::fs::remove_file(scene);
}

#[test]
fn a_signal_stops_a_shard_whose_neighbour_froze_at_once() {
    // Shard 1 frozen (SIGSTOP): its token stays, so shard 0 waits at its barrier. Ctrl-C ends
    // that wait at once, not after the 60 s barrier timeout, and the run ends as interrupted.
    let scene = flock_scene("freeze");
    let (waiting, mut frozen) = two_shards_stepping(&scene, "freeze");
    signal(&frozen, "-STOP");
    std::thread::sleep(Duration::from_millis(500));
    let signalled_at = Instant::now();
    signal(&waiting, "-INT");
    let out = waiting.wait_with_output().unwrap();
    let took = signalled_at.elapsed();
    signal(&frozen, "-CONT");
    frozen.kill().unwrap();
    frozen.wait().unwrap();
    let summary = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(summary.contains("interrupted by a signal"), "{summary}");
    assert!(took < Duration::from_secs(5), "stopped {took:?} after the signal");
    let _ = std::fs::remove_file(scene);
}

#[test]
fn shards_told_to_hold_wait_out_a_router_restart_and_keep_the_bits() {
    // Two shards, clients of a router that is killed while they step and started again on the
    // same port 3 s later: with `--on-shard-lost hold` they hold at the barrier, Zenoh
    // reconnects them, lost batches are sent again, and the minute ends with every copter's
    // one-process bits.
    let scene = flock_scene("hold");
    let scene = scene.to_str().unwrap();
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let router = || {
        Command::new(env!("CARGO_BIN_EXE_twinswarm"))
            .args(["router", "--listen", &endpoint])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap()
    };
    let mut first = router();
    std::thread::sleep(Duration::from_millis(500));
    let prefix = format!("twinswarm/test-hold-{port}");
    let shards: Vec<_> = ["0/2", "1/2"]
        .iter()
        .map(|k| {
            Command::new(env!("CARGO_BIN_EXE_twinswarm"))
                .args(["run", scene, "--shard", k, "--connect", &endpoint, "--prefix", &prefix])
                .args(["--no-bus", "--no-log", "--realtime", "--duration", "15", "--json"])
                .args(["--on-shard-lost", "hold", "--barrier-timeout", "60"])
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    std::thread::sleep(Duration::from_secs(5));
    first.kill().unwrap();
    first.wait().unwrap();
    std::thread::sleep(Duration::from_secs(3));
    let mut second = router();
    let started = Instant::now();
    let mut copters = Vec::new();
    let outs: Vec<_> = shards.into_iter().map(|s| s.wait_with_output().unwrap()).collect();
    let errs: Vec<String> = outs.iter().map(|o| String::from_utf8_lossy(&o.stderr).into_owned()).collect();
    for (out, err) in outs.iter().zip(&errs) {
        assert!(out.status.success(), "{errs:#?}");
        assert!(err.contains("holding until back"), "{err}");
        let s = json(&String::from_utf8_lossy(&out.stdout));
        assert!(s["shard"]["link"]["holds"].as_u64() >= Some(1), "{s}");
        assert_eq!(s["shard"]["link"]["exchanges"].as_u64(), Some(300), "every step's barrier, once");
        copters.extend(digests(&s));
    }
    assert!(started.elapsed() < Duration::from_secs(60), "the run went on after the restart");
    second.kill().unwrap();
    second.wait().unwrap();
    copters.sort();
    let (ok, out, err) = twinswarm(&["run", scene, "--no-bus", "--no-log", "--duration", "15", "--json"]);
    assert!(ok, "{err}");
    assert_eq!(copters, digests(&json(&out)), "the one-process bits");
    let _ = std::fs::remove_file(scene);
}

#[test]
fn bad_shard_arguments_are_refused() {
    for (args, what) in [
        (vec!["run", "--shard", "2/2"], "K must be in 0..N"),
        (vec!["run", "--shard", "x"], "is not K/N"),
        (vec!["run", "--shard", "0/2", "--duration", "1"], "needs --connect"),
        (vec!["run", "--shard", "0/2", "--ivy"], "--ivy is not available for a shard"),
        (vec!["run", "--shard", "0/2", "--no-bus", "--barrier-timeout", "0"], "--barrier-timeout must be"),
        (vec!["cluster", "--shards", "0"], "--shards must be 1 to 64"),
        (vec!["run", "--shard", "0/2", "--on-shard-lost", "wait"], "--on-shard-lost"),
    ] {
        let (ok, _, err) = twinswarm(&args);
        assert!(!ok, "{args:?}");
        assert!(err.contains(what), "{args:?}: {err}");
    }
}
