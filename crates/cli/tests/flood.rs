//! Floods, bounded in count and time, on loopback: `twinswarm run --realtime` with 100
//! copters and two twins, logging, on Zenoh and on an Ivy bus, while this process sends at
//! once, for `FLOOD_SECONDS` (default 5; `scripts/flood.sh` runs 60):
//!
//! - `FLOOD_RATE` (default 10,000) commands per second on Zenoh, one in three malformed or out
//!   of range;
//! - `FLOOD_RATE` Paparazzi texts per second on Zenoh, and as many on Ivy: twins' telemetry,
//!   texts of an aircraft nobody paired, and undecodable ones.
//!
//! It checks that every input is accounted for (applied, rejected, ignored or dropped, in the
//! summary and in the log), that the step loop keeps its deadlines, and that memory stays
//! flat. It prints the figures; `scripts/flood.sh` collects them for docs/reliability.md.

use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use bridge::paparazzi::ivy::{BusAddr, IvyAgent, IvyOptions};
use zenoh::qos::CongestionControl;

fn env_or(name: &str, default: u64) -> u64 {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

fn free_tcp_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()).map(|a| a.port()).expect("a free port")
}

fn free_udp_port() -> u16 {
    std::net::UdpSocket::bind("127.0.0.1:0").and_then(|s| s.local_addr()).map(|a| a.port()).expect("a free port")
}

/// 100 Wall-Avoid copters on a 1.5 m grid in a 16 m arena, and two twins (ac_id 5 and 6).
fn scene(duration_s: u64) -> String {
    let mut s = format!(
        "name = \"flood\"\n[sim]\nseed = 11\nduration_s = {duration_s}.0\n[arena]\nsize_m = [16.0, 16.0]\nheight_m = 3.0\n"
    );
    for k in 0..100 {
        let (x, y) = (-7.0 + 1.5 * (k % 10) as f64, -7.0 + 1.5 * (k / 10) as f64);
        s += &format!(
            "[[copter]]\nname = \"c{k}\"\nstart = {{ pos_m = [{x}, {y}, 1.0] }}\nmode = \"wall_avoid\"\ncommand = {{ height_m = 1.0 }}\n"
        );
    }
    for (k, ac) in [(0, 5), (1, 6)] {
        s += &format!(
            "[[copter]]\nname = \"twin{ac}\"\nkind = \"real\"\nac_id = {ac}\nstart = {{ pos_m = [{}, 7.5] }}\n",
            -1.0 + 2.0 * k as f64
        );
    }
    s
}

fn rss_kb(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
        .unwrap_or(0)
}

/// The `k`-th command: two in three valid, one malformed or out of range.
fn command(k: u64) -> &'static str {
    match k % 6 {
        0 => r#"{"pitch": 0.02, "roll": -0.01}"#,
        1 => r#"{"pitch": "fast"}"#,
        2 => r#"{"height": 1.1, "yaw": 0.3}"#,
        3 => r#"{"roll": 0.05, "velocity": [0.2, 0.0]}"#,
        4 => r#"{"height": 99.0}"#,
        _ => r#"{"mode": "wall_avoid", "height": 1.0}"#,
    }
}

/// The `k`-th Paparazzi text: twins' telemetry, an aircraft nobody paired, an undecodable one.
fn text(k: u64) -> (u8, &'static str, String) {
    match k % 5 {
        0 => (5, "ATTITUDE", "5 ATTITUDE 0.01 0.2 -0.02".into()),
        1 => (6, "FINKEN_ACTUATORS_SET_POINT", "6 FINKEN_ACTUATORS_SET_POINT 1.0 -0.5 10.0 52.0".into()),
        2 => (5, "SONAR_ARRAY", "5 SONAR_ARRAY 120 80 200 300".into()),
        3 => (77, "ATTITUDE", "77 ATTITUDE 0.0 0.0 0.0".into()),
        _ => (6, "ATTITUDE", "6 ATTITUDE 0.1 nonsense".into()),
    }
}

/// `rate` items per second for `secs`, in batches every 10 ms.
struct Pacer {
    tick: tokio::time::Interval,
    per_tick: u64,
    ticks_left: u64,
    next: u64,
    /// When the first batch was due.
    started: Option<Instant>,
}

impl Pacer {
    fn new(rate: u64, secs: u64) -> Self {
        let mut tick = tokio::time::interval(Duration::from_millis(10));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Burst);
        Self { tick, per_tick: rate / 100, ticks_left: secs * 100, next: 0, started: None }
    }

    /// Items sent, and the rate they were offered at (items over the time from the first
    /// batch to the end of the last, 10 ms after it was due), per second.
    fn offered(&self) -> (u64, f64) {
        let secs = self.started.map_or(0.0, |t| t.elapsed().as_secs_f64() + 0.01);
        (self.next, if secs > 0.0 { self.next as f64 / secs } else { 0.0 })
    }

    /// The numbers of the next batch, when it is due; `None` at the end.
    async fn batch(&mut self) -> Option<std::ops::Range<u64>> {
        if self.ticks_left == 0 {
            return None;
        }
        self.ticks_left -= 1;
        self.tick.tick().await;
        self.started.get_or_insert_with(Instant::now);
        let start = self.next;
        self.next += self.per_tick;
        Some(start..self.next)
    }
}

#[test]
fn floods_of_commands_and_texts_are_all_counted_and_the_loop_keeps_time() {
    let secs = env_or("FLOOD_SECONDS", 5);
    let rate = env_or("FLOOD_RATE", 10_000);
    let dir = std::env::temp_dir().join(format!("twinswarm-flood-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let scene_path = dir.join("flood.toml");
    // Flooding starts 2 s in and ends 2 s before the run does.
    std::fs::write(&scene_path, scene(secs + 4)).unwrap();
    let log: PathBuf = dir.join("flood.mcap");
    let port = free_tcp_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let bus = format!("127.255.255.255:{}", free_udp_port());
    let prefix = format!("flood-{port}/swarm");
    let child = Command::new(env!("CARGO_BIN_EXE_twinswarm"))
        .arg("run")
        .arg(&scene_path)
        .args(["--realtime", "--json", "--listen", &endpoint, "--prefix", &prefix, "--ivy", &bus, "--log"])
        .arg(&log)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start twinswarm run");
    let pid = child.id();

    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let (sent_cmds, sent_zenoh, sent_ivy, offered, [rss_start, rss_mid, rss_end]) = rt.block_on(async {
        let config = bridge::zenoh_net::node::client_config(std::slice::from_ref(&endpoint)).unwrap();
        let session = zenoh::open(config).await.expect("zenoh client");
        let addr = BusAddr::parse(&bus).expect("bus address");
        let agent = Arc::new(IvyAgent::start(IvyOptions::new(addr, "Flooder")).await.expect("ivy agent"));
        tokio::time::sleep(Duration::from_secs(2)).await;
        let rss_start = rss_kb(pid);
        let cmd_sent = Arc::new(AtomicU64::new(0));
        let cmds = {
            let (session, prefix) = (session.clone(), prefix.clone());
            tokio::spawn(async move {
                let mut pacer = Pacer::new(rate, secs);
                while let Some(batch) = pacer.batch().await {
                    for k in batch {
                        let key = format!("{prefix}/copters/c{}/cmd", k % 100);
                        let put = session.put(key, command(k)).congestion_control(CongestionControl::Block);
                        put.await.expect("put");
                    }
                }
                pacer.offered()
            })
        };
        let texts = {
            let (session, prefix) = (session.clone(), prefix.clone());
            tokio::spawn(async move {
                let mut pacer = Pacer::new(env_or("FLOOD_ZENOH_TEXT_RATE", rate), secs);
                while let Some(batch) = pacer.batch().await {
                    for k in batch {
                        let (ac, name, t) = text(k);
                        let put = session.put(format!("{prefix}/pprz/{ac}/{name}"), t);
                        put.congestion_control(CongestionControl::Block).await.expect("put");
                    }
                }
                pacer.offered()
            })
        };
        let ivy_sent = {
            let agent = agent.clone();
            let sent = cmd_sent.clone();
            tokio::spawn(async move {
                let mut pacer = Pacer::new(env_or("FLOOD_IVY_RATE", rate), secs);
                while let Some(batch) = pacer.batch().await {
                    for k in batch {
                        // A text no peer binds is not sent at all: count what left.
                        if agent.send(&text(k).2).unwrap_or(0) > 0 {
                            sent.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                }
                pacer.offered()
            })
        };
        let started = Instant::now();
        let mid = tokio::spawn(async move {
            tokio::time::sleep(Duration::from_secs_f64(secs as f64 / 2.0)).await;
            rss_kb(pid)
        });
        let (c, z, i) = (cmds.await.unwrap(), texts.await.unwrap(), ivy_sent.await.unwrap());
        let rss_mid = mid.await.unwrap();
        eprintln!("flooded for {:.1} s", started.elapsed().as_secs_f64());
        let rss_end = rss_kb(pid);
        tokio::time::sleep(Duration::from_millis(500)).await;
        // Hellos are dropped by design (our own, echoed by the broadcast); texts must not be.
        let ivy_drops: u64 = agent.drops().iter().filter(|(why, _)| !why.starts_with("hello")).map(|(_, n)| n).sum();
        assert_eq!(ivy_drops, 0, "the flooder's own Ivy agent dropped: {:?}", agent.drops());
        agent.stop().await;
        session.close().await.unwrap();
        let offered = [c.1, z.1, i.1];
        (c.0, z.0, cmd_sent.load(Ordering::Relaxed), offered, [rss_start, rss_mid, rss_end])
    });
    let out = child.wait_with_output().expect("twinswarm run ends");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).expect("summary JSON");
    let b = &json["bus"];
    let t = &b["telemetry"];
    let n = |v: &serde_json::Value| v.as_u64().unwrap_or(0);
    let sum = |v: &serde_json::Value| v.as_object().map_or(0, |o| o.values().map(n).sum::<u64>());
    let sum_texts = |v: &serde_json::Value| {
        v.as_object().map_or(0, |o| o.iter().filter(|(k, _)| !k.starts_with("hello")).map(|(_, v)| n(v)).sum::<u64>())
    };
    let arrivals: u64 = t["arrivals"].as_array().unwrap().iter().map(|a| n(&a["count"])).sum();
    let texts_seen = arrivals + n(&t["decode_errors"]);
    let steps = n(&json["control_steps"]);
    let overruns = n(&json["realtime_overruns"]);
    let ivy = &b["ivy"];
    eprintln!(
        "flood {secs} s at {rate}/s each: commands sent {sent_cmds}, accepted {}, rejected {} (not from the \
         controller {}), dropped {}; texts sent {} (zenoh {sent_zenoh}, ivy {sent_ivy}), seen {texts_seen} \
         (decode errors {}, out of range {}, ignored {}, queue full {}); ivy drops {}; steps {steps}, \
         overruns {overruns}; offered {:.0}/{:.0}/{:.0} per s; RSS {rss_start} kB at the start, {rss_mid} kB \
         half-way, {rss_end} kB at the end",
        n(&b["commands_accepted"]),
        n(&b["commands_rejected"]),
        n(&b["commands_not_controller"]),
        n(&b["requests_dropped"]),
        sent_zenoh + sent_ivy,
        n(&t["decode_errors"]),
        n(&t["rejected"]),
        sum(&t["ignored"]),
        n(&t["queue_full"]),
        sum_texts(&ivy["dropped"]),
        offered[0],
        offered[1],
        offered[2],
    );

    // Every command is accounted for: accepted (and applied) or rejected; none lost.
    assert_eq!(n(&b["commands_accepted"]) + n(&b["commands_rejected"]), sent_cmds, "{b}");
    // Commands 1 and 4 of every 6 are bad.
    let bad = 2 * (sent_cmds / 6) + u64::from(sent_cmds % 6 > 1) + u64::from(sent_cmds % 6 > 4);
    // A good command that found the loop's queue full is rejected too, and counted dropped.
    let rejected = n(&b["commands_rejected"]);
    assert!(rejected >= bad && rejected - bad <= n(&b["requests_dropped"]), "{bad} bad commands: {b}");
    // Every text that left is accounted for: decoded (twin input, ignored) or undecodable.
    assert_eq!(texts_seen, sent_zenoh + sent_ivy, "{t}");
    assert_eq!(sum_texts(&ivy["dropped"]), 0, "{ivy}");
    // What fell off a full queue is counted, and the rest reached the loop: the accepted
    // commands applied, the others logged as rejected or ignored, every one on `/bus`, once.
    let dropped = n(&b["requests_dropped"]) + n(&t["queue_full"]);
    let incoming = n(&b["commands_accepted"]) + n(&b["commands_rejected"]) + texts_seen;
    let inputs = &json["inputs"];
    assert_eq!(n(&inputs["commands_applied"]), n(&b["commands_accepted"]), "{inputs}");
    let file = bridge::log::LogFile::open(&log).expect("log");
    let bus = file.messages::<bridge::log::proto::BusMessage>("/bus").expect("/bus");
    let on_bus = bus.iter().filter(|(_, m)| m.direction == "in").count() as u64;
    assert_eq!(on_bus, incoming - dropped, "inputs on /bus: {incoming} came, {dropped} dropped");
    // The rate offered, measured: a sender that fell behind would prove less than it says.
    for (what, r) in ["commands", "Zenoh texts", "Ivy texts"].iter().zip(offered) {
        assert!(r >= 0.9 * rate as f64, "{what} offered at {r:.0}/s, not {rate}/s");
    }
    // Every step was flown. A loop that kept every deadline was not overloaded: it dropped
    // nothing. (Deadlines missed are the machine's load: reported, not asserted.)
    assert_eq!(steps, (secs + 4) * 20, "control steps of a {}-s run", secs + 4);
    if overruns == 0 {
        assert_eq!(dropped, 0, "{dropped} inputs dropped by a loop that kept its deadlines");
    }
    let mut reported = None;
    for (_, e) in file.messages::<bridge::log::proto::Event>("/events").expect("events") {
        if e.kind == "bus_report" {
            reported = e.detail.as_ref().map(bridge::log::proto::struct_to_json);
        }
    }
    let reported = reported.expect("a bus_report event in the log");
    assert_eq!(n(&reported["requests_dropped"]), n(&b["requests_dropped"]), "{reported}");
    // Memory: flat within 32 MB (the first seconds allocate the queues and the log buffers).
    assert!(rss_end <= rss_start + 32 * 1024, "RSS grew from {rss_start} kB to {rss_end} kB");
    if std::env::var_os("FLOOD_KEEP_LOG").is_some() {
        eprintln!("log kept: {}", log.display());
    } else {
        let _ = std::fs::remove_dir_all(&dir);
    }
}
