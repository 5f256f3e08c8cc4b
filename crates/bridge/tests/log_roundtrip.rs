//! The logger round trip: a short run of the lab written with `Logger` and read back with the
//! `mcap` crate (channels, counts, times, attachments, metadata, every message decoded with
//! its protobuf type), the JSON logs of before, plus bad input files.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use bridge::log::{LogFile, LogMeta, LogReadError, Logger, Topic, proto, schema_data};
use foxglove::messages as fg;
use prost::Message as _;

fn temp_dir(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("twinswarm-log-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

const STEPS: u64 = 60;
const EPOCH_NS: u64 = 1_700_000_000_123_000_000;

fn write_run(path: &Path) -> sim_core::World {
    let text = sim_core::scene::DEFAULT_SCENE_TOML;
    let (_, world) = sim_core::scene::load("lab.toml", text).unwrap();
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let meta = LogMeta {
        command_line: "twinswarm run --test".into(),
        scene_origin: "lab.toml".into(),
        epoch_ns: Some(EPOCH_NS),
    };
    let mut log = Logger::create(path, &world, text, meta).unwrap();
    for _ in 0..STEPS {
        let r = sim_core::step(&world, &mut state, &inputs);
        log.log_step(&world, &state, &inputs, &r).unwrap();
    }
    log.log_bus_message("lab/ivy/201/ATTITUDE", true, "201 ATTITUDE 0.1 0.2 0.3", EPOCH_NS + 42).unwrap();
    let stats = log.finish().unwrap();
    assert_eq!(stats.last_tick, STEPS);
    world
}

#[test]
fn a_logged_run_reads_back_with_every_channel_count_and_record() {
    let dir = temp_dir("roundtrip");
    let path = dir.join("run.mcap");
    let world = write_run(&path);
    let n = world.copters.len() as u64;
    let data = std::fs::read(&path).unwrap();

    let summary = mcap::Summary::read(&data).unwrap().expect("a summary section");
    let stats = summary.stats.clone().expect("statistics");
    assert!(!summary.chunk_indexes.is_empty());
    assert!(summary.chunk_indexes.iter().all(|c| c.compression == "zstd"), "zstd chunks");
    // No message indexes (optional in MCAP): readers go by the chunk indexes.
    assert!(summary.chunk_indexes.iter().all(|c| c.message_index_offsets.is_empty()), "no message indexes");

    let mut counts: BTreeMap<String, u64> = BTreeMap::new();
    let mut last_time: BTreeMap<String, u64> = BTreeMap::new();
    let mut first_state_time = None;
    for m in mcap::MessageStream::new(&data).unwrap() {
        let m = m.unwrap();
        let topic = m.channel.topic.clone();
        let schema = m.channel.schema.as_ref().expect("every channel has a schema");
        assert_eq!(schema.encoding, "protobuf");
        assert_eq!(m.channel.message_encoding, "protobuf");
        assert_eq!(schema.data.as_ref(), schema_data(&schema.name).unwrap().as_ref(), "{topic}: its schema");
        // Every message decodes as its schema's type, and nothing is left over.
        let d = &m.data[..];
        let reencoded = match schema.name.as_str() {
            "twinswarm.CopterState" => proto::CopterState::decode(d).unwrap().encode_to_vec(),
            "twinswarm.CopterSensors" => proto::CopterSensors::decode(d).unwrap().encode_to_vec(),
            "twinswarm.CopterCommand" => proto::CopterCommand::decode(d).unwrap().encode_to_vec(),
            "twinswarm.CopterControl" => proto::CopterControl::decode(d).unwrap().encode_to_vec(),
            "twinswarm.Event" => proto::Event::decode(d).unwrap().encode_to_vec(),
            "twinswarm.BusMessage" => proto::BusMessage::decode(d).unwrap().encode_to_vec(),
            "foxglove.Log" => fg::Log::decode(d).unwrap().encode_to_vec(),
            "foxglove.FrameTransform" => fg::FrameTransform::decode(d).unwrap().encode_to_vec(),
            "foxglove.SceneUpdate" => fg::SceneUpdate::decode(d).unwrap().encode_to_vec(),
            other => panic!("{topic}: unexpected schema {other}"),
        };
        assert_eq!(reencoded, d, "{topic}: decodes and re-encodes to the same bytes");
        let prev = last_time.insert(topic.clone(), m.log_time).unwrap_or(0);
        assert!(m.log_time >= prev, "{topic}: log_time goes back");
        if topic == "/bus" {
            assert_eq!(m.publish_time, EPOCH_NS + 42, "bus: publish_time is the receive time");
        } else {
            assert_eq!(m.publish_time, m.log_time);
        }
        if topic == "/copters/state" && first_state_time.is_none() {
            first_state_time = Some(m.log_time);
            let v = proto::CopterState::decode(d).unwrap();
            assert_eq!((v.tick, v.copter.as_str(), v.pos_m.len()), (1, "finken1", 3));
        }
        *counts.entry(topic).or_insert(0) += 1;
    }
    // log_time = epoch + tick x 50 ms.
    assert_eq!(first_state_time, Some(EPOCH_NS + 50_000_000));
    assert_eq!(last_time["/copters/state"], EPOCH_NS + STEPS * 50_000_000);

    let topics: Vec<&str> = counts.keys().map(String::as_str).collect();
    let mut expected: Vec<&str> = Topic::ALL.iter().map(|t| t.name()).collect();
    expected.sort_unstable();
    assert_eq!(topics, expected);
    for t in ["/copters/state", "/copters/sensors", "/copters/command", "/copters/control", "/tf"] {
        assert_eq!(counts[t], STEPS * n, "{t}: steps x copters");
    }
    // Every 0.2 s (bridge::log::SCENE_COPTERS_PERIOD_S), ticks 4, 8, … of 1..=STEPS.
    assert_eq!(counts["/scene/copters"], STEPS / 4);
    assert_eq!(counts["/scene/arena"], 1);
    assert_eq!(counts["/bus"], 1);
    assert!(counts["/events"] >= n, "both copters took off: {counts:?}");
    assert_eq!(counts["/events"], counts["/log"]);
    assert_eq!(stats.message_count, counts.values().sum::<u64>());

    // Attachments and metadata.
    let mut names = Vec::new();
    for idx in &summary.attachment_indexes {
        let a = mcap::read::attachment(&data, idx).unwrap();
        assert_eq!(a.media_type, "application/toml");
        names.push(a.name.clone());
        if a.name == "scene.toml" {
            assert_eq!(&a.data[..], sim_core::scene::DEFAULT_SCENE_TOML.as_bytes());
        }
    }
    assert_eq!(names, ["scene.toml", "scene.effective.toml"]);
    assert_eq!(summary.metadata_indexes.len(), 1);
    let meta = mcap::read::metadata(&data, &summary.metadata_indexes[0]).unwrap();
    assert_eq!(meta.name, "twinswarm");
    let m = &meta.metadata;
    assert_eq!(m["version"], env!("CARGO_PKG_VERSION"));
    assert_eq!(m["seed"], "2016");
    assert_eq!(m["world"], "lab");
    assert_eq!(m["scene_origin"], "lab.toml");
    assert_eq!(m["command_line"], "twinswarm run --test");
    assert_eq!(m["epoch_unix_ns"], EPOCH_NS.to_string());
    let copters: serde_json::Value = serde_json::from_str(&m["copters"]).unwrap();
    assert_eq!(copters[1]["name"], "finken2");
    assert_eq!(copters[1]["ac_id"], 202);

    // The reader behind `log info` agrees.
    let info = LogFile::open(&path).unwrap().info().unwrap();
    assert_eq!(info.messages, stats.message_count);
    let state = info.channels.iter().find(|c| c.topic == "/copters/state").unwrap();
    assert_eq!(
        (state.schema.as_str(), state.encoding.as_str(), state.messages),
        ("twinswarm.CopterState", "protobuf", STEPS * n)
    );
    let (a, b) = info.time_range_ns.unwrap();
    assert_eq!(b - a, STEPS * 50_000_000);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn every_schema_is_a_descriptor_set_that_defines_it() {
    for topic in Topic::ALL {
        let name = topic.schema();
        let set = prost_types::FileDescriptorSet::decode(schema_data(name).unwrap().as_ref()).unwrap();
        let (package, message) = name.rsplit_once('.').unwrap();
        let defined = set
            .file
            .iter()
            .filter(|f| f.package() == package)
            .any(|f| f.message_type.iter().any(|m| m.name() == message));
        assert!(defined, "{name} is not in its descriptor set");
    }
}

/// A JSON log written before protobuf (`tests/fixtures/log-json-v1.mcap`: the lab, 2 s, by
/// the last JSON version) reads with the same types.
#[test]
fn json_logs_of_before_still_read() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/log-json-v1.mcap");
    let file = LogFile::open(&path).unwrap();
    assert_eq!(file.encoding("/copters/state"), Some("json"));
    let states = file.messages::<proto::CopterState>("/copters/state").unwrap();
    assert_eq!(states.len(), 80);
    let (_, last) = states.last().unwrap();
    assert_eq!(
        (last.tick, last.copter.as_str(), last.kind.as_str(), last.ac_id),
        (40, "finken2", "virtual", Some(202))
    );
    assert!(last.pos_m.len() == 3 && last.pos_m[2] > 0.5, "{last:?}");
    let sensors = file.messages::<proto::CopterSensors>("/copters/sensors").unwrap();
    assert!(sensors.iter().all(|(_, s)| s.sonar_m.len() == 4 && s.attitude_rad.len() == 3));
    let commands = file.messages::<proto::CopterCommand>("/copters/command").unwrap();
    assert_eq!(commands[0].1.mode, "wall_avoid");
    let events = file.messages::<proto::Event>("/events").unwrap();
    assert!(events.iter().all(|(_, e)| e.kind == "took_off" && e.copter.is_some()), "{events:?}");
    assert!(
        file.messages::<proto::CopterControl>("/copters/control").unwrap().iter().all(|(_, c)| c.setpoint.is_some())
    );
}

#[test]
fn bad_files_give_clear_errors_not_panics() {
    let dir = temp_dir("bad");
    let good = dir.join("good.mcap");
    write_run(&good);
    let bytes = std::fs::read(&good).unwrap();
    let write = |name: &str, content: &[u8]| {
        let p = dir.join(name);
        std::fs::write(&p, content).unwrap();
        p
    };
    let err = LogFile::open(&write("empty.mcap", b"")).unwrap_err();
    assert!(matches!(err, LogReadError::Empty { .. }), "{err}");
    let err = LogFile::open(&write("text.mcap", b"this is not a log, just some text\n")).unwrap_err();
    assert!(matches!(err, LogReadError::NotMcap { .. }), "{err}");
    assert!(err.to_string().contains("not an MCAP file"), "{err}");
    for cut in [8, 100, bytes.len() / 3, bytes.len() - 1] {
        let err = LogFile::open(&write("cut.mcap", &bytes[..cut])).unwrap_err();
        assert!(matches!(err, LogReadError::Truncated { .. }), "cut at {cut}: {err}");
        assert!(err.to_string().contains("log recover"), "{err}");
    }
    let err = LogFile::open(&dir.join("missing.mcap")).unwrap_err();
    assert!(matches!(err, LogReadError::Io { .. }), "{err}");
    // A damaged chunk (bytes flipped in the middle) is an error, not a panic.
    let mut damaged = bytes.clone();
    let mid = damaged.len() / 2;
    for b in &mut damaged[mid..mid + 64] {
        *b ^= 0x5a;
    }
    let p = write("damaged.mcap", &damaged);
    if let Ok(f) = LogFile::open(&p) {
        assert!(f.messages::<proto::CopterState>("/copters/state").is_err(), "damage went unnoticed");
    }
    // Damaged lengths: a chunk that says it unpacks to exabytes, a record longer than the
    // file. The `mcap` reader would try to allocate them and abort the process; these are
    // clear errors, and `recover` keeps what comes before the damage.
    let first_chunk = {
        let mut pos = 8;
        loop {
            let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap()) as usize;
            if bytes[pos] == 0x06 {
                break pos;
            }
            pos += 9 + len;
        }
    };
    let mut huge_chunk = bytes.clone();
    huge_chunk[first_chunk + 9 + 16..first_chunk + 9 + 24].copy_from_slice(&u64::MAX.to_le_bytes());
    let mut huge_record = bytes.clone();
    huge_record[first_chunk + 1..first_chunk + 9].copy_from_slice(&(1u64 << 62).to_le_bytes());
    for (name, damaged) in [("huge_chunk.mcap", huge_chunk), ("huge_record.mcap", huge_record)] {
        let p = write(name, &damaged);
        let err = LogFile::open(&p).unwrap_err();
        assert!(matches!(err, LogReadError::Damaged { offset, .. } if offset == first_chunk as u64), "{name}: {err}");
        assert!(err.to_string().contains("is damaged at byte"), "{err}");
        let report = bridge::log::recover(&p, &dir.join("rescued.mcap")).unwrap();
        // A record longer than the file looks like the cut record of a killed run to recover.
        let why = report.stopped_by.as_deref().unwrap_or("");
        assert!(why.contains("damaged") || why.contains("cut off"), "{name}: {report:?}");
        // What came before the chunk is kept: the scene attachments and the metadata. (The mcap
        // crate writes schemas and channels inside chunks: the first one, flushed at setup,
        // holds them; a kill -9 never reaches it, only damage like this.)
        assert!(report.attachments == 2 && report.metadata == 1, "{name}: what came before is kept: {report:?}");
        assert!(LogFile::open(&dir.join("rescued.mcap")).is_ok(), "{name}: the rescued file is complete");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
