//! Real FINken flights, as Paparazzi's `server` logged them (`shared/data/finken_flights`,
//! see its SOURCES.md): read with the definitions each log carries, turned into twin inputs,
//! and the virtual-sonar uplink chosen by the messages.xml in use.
//!
//! Skips loudly where the shared data is absent; fails under `CI=true`.

mod common;

use std::sync::Arc;
use std::time::{Duration, Instant};

use bridge::mixed::{Interpreter, Quantity, TwinAttitude};
use bridge::paparazzi::convert::{Uplink, uplink_readings, uplink_text};
use bridge::paparazzi::flightlog::FlightLog;
use bridge::paparazzi::messages::MessageSet;
use bridge::realflight::{Series, derive_arena, flights, start_pose};
use bridge::sim::{BusInput, Request};

const LINKED: &str = "finken_flights/report_2015-12-16/15_12_16__13_55_00.data";

#[test]
fn every_shared_flight_log_reads_with_its_own_definitions() {
    let dir = shared_or_skip!();
    let files = common::files_with_extension(&dir.join("finken_flights"), "data");
    assert!(files.len() >= 9, "expected the SOURCES.md logs, found {files:?}");
    let mut read = 0;
    for f in &files {
        match FlightLog::open(f) {
            Ok(log) => {
                read += 1;
                assert!(!log.records.is_empty(), "{}: no message read", f.display());
                // Every line reads with the log's own definitions but one kind: the 2015
                // `link` wrote LINK_REPORT with `link_id` -1, outside the uint8 its own
                // messages.xml gives it. Those are counted and named, never guessed at.
                let others = log.errors.total() - log.errors.by_message.get("LINK_REPORT").copied().unwrap_or(0);
                assert_eq!(others, 0, "{}: {:?}", f.display(), log.errors);
                if let Some((line, why)) = log.errors.first.first() {
                    assert!(why.contains("link_id"), "{}:{line}: {why}", f.display());
                }
            }
            // One `.data` of SOURCES.md has no `.log`: a clear error naming the missing file.
            Err(e) => {
                let msg = e.to_string();
                assert!(!f.with_extension("log").exists(), "{}: {msg}", f.display());
                assert!(msg.contains(".log"), "{msg}");
            }
        }
    }
    assert!(read >= 8, "{read} logs read");
}

#[test]
fn the_linked_flight_carries_the_forks_own_finken_sensor_model() {
    let dir = shared_or_skip!();
    let log = FlightLog::open(&dir.join(LINKED)).expect("opens");
    let def = log.config.messages.by_class_and_name("telemetry", "FINKEN_SENSOR_MODEL").expect("defined");
    assert_eq!(def.fields.len(), 19);
    assert_eq!(def.fields[1].name, "distance_d_rigth");
    let ac = log.config.aircraft(5).expect("aircraft 5");
    assert_eq!(ac.name, "FINken3_01");
    assert_eq!(ac.period_s("vrep", "FINKEN_SENSOR_MODEL"), Some(0.022));
    assert_eq!(ac.period_s("vrep", "AHRS_EULER_INT"), Some(0.021));
    assert_eq!(ac.mode_sending(&["FINKEN_SENSOR_MODEL", "AHRS_EULER_INT", "ROTORCRAFT_FP"]), Some("vrep"));
    assert_eq!(log.senders().keys().copied().collect::<Vec<_>>(), vec![5]);
    // The ground segment of 2015 defined neither uplink: no virtual sonar could reach it.
    assert_eq!(Uplink::defined_by(&log.config.messages), Uplink::None);
}

#[test]
fn the_linked_flight_has_its_flights_its_arena_and_their_starts() {
    let dir = shared_or_skip!();
    let log = FlightLog::open(&dir.join(LINKED)).expect("opens");
    let series = Series::of(&log, 5);
    assert!(series.attitude.len() > 15_000 && series.sensors.len() > 15_000);
    let fl = flights(&series);
    assert!((5..=9).contains(&fl.len()), "{fl:?}");
    // The V-REP-linked flight of the report, about 826-876 s.
    assert!(fl.iter().any(|f| f.start_s < 840.0 && f.end_s > 870.0), "{fl:?}");
    let arena = derive_arena(&series, &fl, 0.05).expect("an arena");
    // The lab's 4 × 3 m, seen through the sonars' gate and mount.
    assert!((3.6..4.2).contains(&arena.size_m[0]) && (2.6..3.2).contains(&arena.size_m[1]), "{arena:?}");
    for f in &fl {
        let s = start_pose(&series, f, &arena).expect("a start");
        let [hx, hy] = arena.size_m.map(|v| v / 2.0);
        assert!(s.pos_m[0].abs() < hx && s.pos_m[1].abs() < hy, "{f:?}: {s:?}");
    }
}

#[test]
fn a_twin_follows_ahrs_euler_int_and_finken_sensor_model_when_nothing_else_speaks() {
    let dir = shared_or_skip!();
    let log = FlightLog::open(&dir.join(LINKED)).expect("opens");
    let (_, world) = sim_core::scene::load_default();
    let mut spec = sim_core::scene::load_default().0;
    spec.copters[0].kind = sim_core::CopterKind::Real;
    spec.copters[0].ac_id = Some(5);
    let world = sim_core::scene::compile(&spec).unwrap_or(world);
    let mut it = Interpreter::new(Arc::new(world), None, TwinAttitude::Setpoint);
    let messages: &MessageSet = &log.config.messages;
    let base = Instant::now();
    let (mut attitude, mut height) = (0, 0);
    for r in log.records.iter().filter(|r| r.time_s > 830.0 && r.time_s < 840.0) {
        let origin = BusInput { key: "k".into(), text: log.text(r).to_owned(), received_unix_ns: 0 };
        match it.interpret(messages, origin, base + Duration::from_secs_f64(r.time_s)) {
            Request::Twin { cmd: Some(c), .. } => {
                attitude += usize::from(c.roll.is_some());
                height += usize::from(c.height.is_some());
            }
            Request::Rejected { reason, .. } => panic!("{reason}"),
            _ => {}
        }
    }
    assert!(attitude > 300 && height > 200, "attitude {attitude}, height {height}");
    let report = it.report();
    let src = &report.sources[&5];
    // With no FINKEN_ACTUATORS_SET_POINT or ATTITUDE, the AHRS drives the attitude; the IR of
    // FINKEN_SENSOR_MODEL the height and the sonar.
    assert!(src[&Quantity::Attitude].contains_key("AHRS_EULER_INT"), "{src:?}");
    assert!(src[&Quantity::Height].contains_key("FINKEN_SENSOR_MODEL"), "{src:?}");
    assert!(src[&Quantity::Sonar].contains_key("FINKEN_SENSOR_MODEL"), "{src:?}");
    let line = &report.source_lines()[0].1;
    assert!(line.contains("attitude ← AHRS_EULER_INT"), "{line}");
}

#[test]
fn sonar_uplink_is_encoded_as_the_original_bridge_sent_it() {
    let dir = shared_or_skip!();
    let mr = MessageSet::from_file(dir.join("paparazzi_finken/mixed_reality_conf_messages.xml")).expect("parses");
    assert_eq!(Uplink::defined_by(&mr), Uplink::SonarUplink);
    // Front 1.23 m, right nothing, back 0.5 m, left 2 m; the wire order is front, left, back, right.
    let text = uplink_text(&mr, Uplink::SonarUplink, 5, [1.234, f32::INFINITY, 0.5, 2.0]).expect("encodes");
    assert_eq!(text.as_deref(), Some("dl SONAR_UPLINK 5 255 123 200 50 765"));
    let msg = mr.decode(text.as_deref().unwrap_or("")).expect("decodes");
    let (ac, back) = uplink_readings(&msg).expect("readings");
    assert_eq!(ac, 5);
    assert_eq!(back, [1.23, f32::INFINITY, 0.5, 2.0]);
    // The project's own messages.xml defines VIRTUAL_SONAR; the 2015 fork's conf/messages.xml
    // neither.
    assert_eq!(Uplink::defined_by(&bridge::paparazzi::convert::project_messages()), Uplink::VirtualSonar);
    let fork = MessageSet::from_file(dir.join("paparazzi_finken/FINken_conf_messages.xml")).expect("parses");
    assert_eq!(Uplink::defined_by(&fork), Uplink::None);
    assert_eq!(uplink_text(&fork, Uplink::None, 5, [1.0; 4]).expect("nothing"), None);
}
