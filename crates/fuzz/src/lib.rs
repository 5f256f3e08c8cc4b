//! Fuzz targets: every path by which bytes from outside reach Twinswarm.
//!
//! Each target is a function from bytes to nothing that must not panic, abort or allocate
//! without bound, whatever the bytes. The same functions run three ways:
//! - `cargo test -p twinswarm-fuzz` replays every file under `corpus/<target>/` (seeds and
//!   everything a long run kept) and `regressions/<target>/` (each crash found, minimised):
//!   CI's smoke pass;
//! - `scripts/fuzz.sh` builds `src/bin/afl.rs` with AFL++'s instrumentation and runs
//!   `afl-fuzz` on each target for a given number of executions;
//! - a crash file found by AFL++ replays with `cargo run -p twinswarm-fuzz --features afl
//!   --bin twinswarm-afl -- TARGET < FILE` or by copying it into `regressions/`.
//!
//! Errors are the expected outcome for most inputs: a target only insists that bad input
//! gives an error value, never a panic.

use std::path::PathBuf;
use std::sync::OnceLock;

use bridge::paparazzi::ivy::frame::{Frame, Hello, Line, LineSplitter};
use bridge::{Bus, ConfXml, MessageSet, Pairing, Telemetry};
use sim_core::World;
use sim_core::scene::{self, CopterSpec};

mod seeds;
pub use seeds::seeds;

/// A fuzz target: its name (the corpus folder) and its function.
pub type Target = (&'static str, fn(&[u8]));

/// Every target, by name.
pub const TARGETS: &[Target] = &[
    ("scene", scene),
    ("messages_xml", messages_xml),
    ("conf_xml", conf_xml),
    ("pairing_xml", pairing_xml),
    ("telemetry_xml", telemetry_xml),
    ("ivy_text", ivy_text),
    ("ivy_wire", ivy_wire),
    ("zenoh_json", zenoh_json),
    ("mcap", mcap),
    ("plot", plot),
    ("log", log),
    ("log_merge", log_merge),
    ("foxglove_client", foxglove_client),
    ("ghost_batch", ghost_batch),
    ("pprz_log", pprz_log),
];

/// The target called `name`.
pub fn target(name: &str) -> Option<fn(&[u8])> {
    TARGETS.iter().find(|(n, _)| *n == name).map(|(_, f)| *f)
}

fn text(data: &[u8]) -> Option<&str> {
    std::str::from_utf8(data).ok()
}

/// Copters above this many are compiled but not stepped: a scene may legitimately ask for
/// thousands, and stepping them is the benchmarks' business, not the parser's.
const MAX_STEPPED_COPTERS: usize = 16;

/// A scene TOML: parsed, checked, compiled; if it has few copters, two control steps flown
/// (the core must not panic on any scene that compiled).
pub fn scene(data: &[u8]) {
    let Some(text) = text(data) else { return };
    let Ok((_, world)) = scene::load("fuzz.toml", text) else { return };
    if world.copters.len() <= MAX_STEPPED_COPTERS {
        let mut state = world.initial_state();
        let inputs = world.initial_inputs();
        for _ in 0..2 {
            sim_core::step(&world, &mut state, &inputs);
        }
    }
}

/// A messages.xml; then, for every message it defines, a text of zeros decoded with it.
pub fn messages_xml(data: &[u8]) {
    let Some(text) = text(data) else { return };
    let Ok(set) = MessageSet::parse(text, "fuzz/messages.xml") else { return };
    for def in set.iter() {
        let zeros = vec!["0"; def.fields.len().min(256)].join(" ");
        let _ = set.decode(&format!("1 {} {zeros}", def.name));
    }
}

/// Separates a Paparazzi log's `.log` from its `.data` in a `pprz_log` input.
pub const PPRZ_LOG_SEPARATOR: &[u8] = b"\n%%DATA%%\n";

/// A Paparazzi server log: the `.log` text, [`PPRZ_LOG_SEPARATOR`], the `.data` bytes; read,
/// then every aircraft's series, flights, arena and flight starts derived.
pub fn pprz_log(data: &[u8]) {
    use bridge::paparazzi::flightlog::{FlightLog, LogConfig};
    use bridge::realflight::{Series, derive_arena, flights, start_pose};
    let (log, rest) = match data.windows(PPRZ_LOG_SEPARATOR.len()).position(|w| w == PPRZ_LOG_SEPARATOR) {
        Some(i) => (&data[..i], &data[i + PPRZ_LOG_SEPARATOR.len()..]),
        None => (data, &[][..]),
    };
    let Some(text) = text(log) else { return };
    let Ok(config) = LogConfig::parse(text, "fuzz/flight.log") else { return };
    let log = FlightLog::from_parts(config, rest, "fuzz/flight.data");
    for r in &log.records {
        let _ = log.text(r);
        let _ = log.message(r);
    }
    for ac in log.senders().into_keys() {
        let series = Series::of(&log, ac);
        let fl = flights(&series);
        if let Some(arena) = derive_arena(&series, &fl, 0.05) {
            for f in &fl {
                let _ = start_pose(&series, f, &arena);
            }
        }
    }
}

/// A conf.xml.
pub fn conf_xml(data: &[u8]) {
    if let Some(text) = text(data) {
        let _ = ConfXml::parse(text, "fuzz/conf.xml");
    }
}

/// A pairing file.
pub fn pairing_xml(data: &[u8]) {
    if let Some(text) = text(data) {
        let _ = Pairing::parse(text, "fuzz/pairing.xml");
    }
}

/// A telemetry.xml, then the telemetry plan of its first process and mode.
pub fn telemetry_xml(data: &[u8]) {
    let Some(text) = text(data) else { return };
    if let Ok(t) = Telemetry::parse(text, "fuzz/telemetry.xml") {
        let _ = bridge::mixed::plan::TelemetryPlan::from_telemetry(&t, None, None);
    }
}

fn project_messages() -> &'static MessageSet {
    static SET: OnceLock<MessageSet> = OnceLock::new();
    SET.get_or_init(bridge::paparazzi::convert::project_messages)
}

/// Ivy texts as they arrive on the bus: the first line is a regex a peer binds (as an Ivy
/// `AddRegexp` would), the rest are texts decoded with the project's messages.xml, turned
/// into what the twins use, and dispatched on a bus with that binding and the gateway's.
pub fn ivy_text(data: &[u8]) {
    let Some(text) = text(data) else { return };
    let mut lines = text.split('\n');
    let mut bus = Bus::new();
    let _ = bus.bind(lines.next().unwrap_or(""), |_, _| {});
    let _ = bus.bind(r"^(\S+) (ATTITUDE|ROTORCRAFT_FP|SONAR_ARRAY|ROTORCRAFT_STATUS) (.*)$", |_, _| {});
    let set = project_messages();
    for line in lines {
        if let Ok(msg) = set.decode(line) {
            let _ = bridge::paparazzi::convert::twin_command(&msg);
            let _ = bridge::paparazzi::convert::real_sonar(&msg);
            let _ = bridge::paparazzi::convert::real_yaw(&msg);
            let _ = bridge::paparazzi::convert::virtual_sonar_readings(&msg);
        }
        bus.dispatch("fuzz", line);
    }
}

/// The Ivy wire protocol: the first line as a UDP hello, then the whole input as a TCP
/// stream, split into lines, each parsed; a parsed frame must encode back to a line that
/// parses to the same frame.
pub fn ivy_wire(data: &[u8]) {
    let first = data.split(|&b| b == b'\n').next().unwrap_or(data);
    if let Ok(hello) = Hello::parse(first) {
        assert_eq!(Hello::parse(&hello.encode()).as_ref(), Ok(&hello), "hello round trip");
    }
    let mut splitter = LineSplitter::default();
    // In two reads, as TCP may cut it anywhere.
    let cut = data.len() / 2;
    for part in [&data[..cut], &data[cut..]] {
        splitter.push(part, |line| {
            if let Line::Complete(bytes) = line
                && let Ok(frame) = Frame::parse(bytes)
            {
                // A received `Msg` group may hold `\x02`; such a group cannot be sent on
                // (`encode_msg` refuses it), so only sendable frames must round-trip.
                let sendable = match &frame {
                    Frame::Msg { id, args } => {
                        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
                        bridge::paparazzi::ivy::frame::encode_msg(*id, &refs, &mut Vec::new()).is_ok()
                    }
                    _ => true,
                };
                if sendable {
                    let mut out = Vec::new();
                    frame.encode(&mut out);
                    let again = out.strip_suffix(b"\n").unwrap_or(&out);
                    assert_eq!(Frame::parse(again).as_ref(), Ok(&frame), "frame round trip of {bytes:?}");
                }
            }
        });
    }
}

fn lab() -> &'static World {
    static LAB: OnceLock<World> = OnceLock::new();
    LAB.get_or_init(|| scene::load_default().1)
}

/// A JSON payload from Zenoh; the first byte says which key it came on: `cmd` (0), `tracking`
/// (1) or `spawn` (2, a copter table added to the lab).
pub fn zenoh_json(data: &[u8]) {
    let Some((&which, payload)) = data.split_first() else { return };
    let world = lab();
    match which % 3 {
        0 => {
            if let Ok(cmd) = bridge::wire::CommandMsg::parse(payload, world) {
                let mut c = world.copters[0].initial_command.clone();
                cmd.apply(&mut c);
            }
        }
        1 => {
            let _ = bridge::wire::TrackingMsg::parse(payload);
        }
        _ => {
            let Ok(spec) = serde_json::from_slice::<CopterSpec>(payload) else { return };
            let mut state = world.initial_state();
            if let Ok(w) = world.with_spawned(&state, &spec) {
                state.add_copters(&w);
                let inputs = w.initial_inputs();
                sim_core::step(&w, &mut state, &inputs);
            }
        }
    }
}

/// A scratch file for the file-reading targets, one per process and target.
fn scratch(tag: &str) -> PathBuf {
    let dir = if std::path::Path::new("/dev/shm").is_dir() { PathBuf::from("/dev/shm") } else { std::env::temp_dir() };
    dir.join(format!("twinswarm-fuzz-{}-{tag}", std::process::id()))
}

/// An MCAP log: opened, summarised, every message and attachment read, then `log recover` on
/// it and the recovered file opened again.
pub fn mcap(data: &[u8]) {
    let (path, fixed) = (scratch("in.mcap"), scratch("fixed.mcap"));
    if std::fs::write(&path, data).is_err() {
        return;
    }
    if let Ok(file) = bridge::log::LogFile::open(&path)
        && let Ok(info) = file.info()
    {
        let topics: Vec<&str> = info.channels.iter().map(|c| c.topic.as_str()).collect();
        let _ = file.for_each_message(&topics, |_, _, _| Ok(()));
        let _ = file.messages::<bridge::log::proto::CopterState>("/copters/state");
        for (name, _, _) in &info.attachments {
            let _ = file.attachment(name);
        }
    }
    if bridge::log::recover(&path, &fixed).is_ok()
        && let Ok(file) = bridge::log::LogFile::open(&fixed)
    {
        let _ = file.info();
    }
    let _ = std::fs::remove_file(&path);
    let _ = std::fs::remove_file(&fixed);
}

/// `twinswarm plot` on a log: every plot drawn into memory.
pub fn plot(data: &[u8]) {
    let path = scratch("plot.mcap");
    if std::fs::write(&path, data).is_err() {
        return;
    }
    let _ = twinswarm::plot::draw_all_in_memory(&path);
    let _ = std::fs::remove_file(&path);
}

/// Messages a replay of one fuzzed log may produce before it is cut short (an error).
const MAX_REPLAYED: usize = 100_000;

/// A log as the CLI's log commands meet it: `log info`, `log recover`, `log merge` of the
/// file with its recovered copy, and `replay` (into memory, at full speed).
pub fn log(data: &[u8]) {
    let (path, fixed, merged) = (scratch("log.mcap"), scratch("log-fixed.mcap"), scratch("log-merged.mcap"));
    if std::fs::write(&path, data).is_err() {
        return;
    }
    let _ = twinswarm::logcmd::summarise(&path);
    if bridge::log::recover(&path, &fixed).is_ok() {
        let _ = twinswarm::logcmd::summarise(&fixed);
        if bridge::log::merge(&[path.clone(), fixed.clone()], &merged).is_ok() {
            let _ = twinswarm::logcmd::summarise(&merged);
        }
    }
    let _ = twinswarm::replay::replay_in_memory(&path, MAX_REPLAYED);
    for p in [&path, &fixed, &merged] {
        let _ = std::fs::remove_file(p);
    }
}

/// Where [`log_merge`] cuts its input into logs.
pub const MERGE_SEPARATOR: &[u8] = b"--merge--";

/// `log merge` of two to four logs (the input cut at [`MERGE_SEPARATOR`]). When it succeeds,
/// the merged log must open, and hold as many messages as the merge says it wrote.
pub fn log_merge(data: &[u8]) {
    let mut parts: Vec<&[u8]> = Vec::new();
    let mut rest = data;
    while parts.len() < 3
        && let Some(k) = rest.windows(MERGE_SEPARATOR.len()).position(|w| w == MERGE_SEPARATOR)
    {
        parts.push(&rest[..k]);
        rest = &rest[k + MERGE_SEPARATOR.len()..];
    }
    parts.push(rest);
    if parts.len() < 2 {
        return;
    }
    let paths: Vec<PathBuf> = (0..parts.len()).map(|k| scratch(&format!("merge-{k}.mcap"))).collect();
    let out = scratch("merge-out.mcap");
    if paths.iter().zip(&parts).all(|(p, d)| std::fs::write(p, d).is_ok())
        && let Ok(report) = bridge::log::merge(&paths, &out)
    {
        let file = bridge::log::LogFile::open(&out).expect("a merged log opens");
        let info = file.info().expect("a merged log has a summary");
        let written: u64 = report.messages.values().sum();
        assert_eq!(info.messages, written, "messages in the merged log, as the merge counted them");
    }
    for p in paths.iter().chain([&out]) {
        let _ = std::fs::remove_file(p);
    }
}

/// A Foxglove WebSocket client's messages, one per line (a line that is not UTF-8 is a binary
/// message), handled by the live view's server.
pub fn foxglove_client(data: &[u8]) {
    let frames = data.split(|&b| b == b'\n').map(|line| std::str::from_utf8(line).map_err(|_| line));
    bridge::live::fuzzing::client_session(frames);
}

/// The 2-shard world of [`ghost_batch`] and its seeds: 16 copters 0.6 m apart across the
/// split, and a pillar.
pub(crate) fn ghost_world() -> &'static (World, sim_core::shard::Partition) {
    static WORLD: OnceLock<(World, sim_core::shard::Partition)> = OnceLock::new();
    WORLD.get_or_init(|| {
        let mut spec = scene::dense_swarm(16, 0.6, false, 1, 3);
        spec.sensors.sonar.schedule = sim_core::sensors::SonarSchedule::Together;
        let world = scene::compile(&spec).expect("the flock compiles");
        let partition = sim_core::shard::Partition::new(&world, 2).expect("two shards");
        (world, partition)
    })
}

/// A shard's ghost batch as it arrives from Zenoh (postcard), taken in by shard 0 of a
/// 2-shard flock, which then steps.
pub fn ghost_batch(data: &[u8]) {
    let Ok(batch) = postcard::from_bytes::<bridge::shard::GhostBatch>(data) else { return };
    let (world, partition) = ghost_world();
    let mut state = world.initial_state();
    state.make_shard(partition.clone(), 0).expect("shard 0 of 2");
    if state.receive_ghosts(batch.ghosts).is_ok() {
        sim_core::step(world, &mut state, &world.initial_inputs());
    }
}
