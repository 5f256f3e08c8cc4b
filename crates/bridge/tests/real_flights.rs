//! Real FINken flights, as Paparazzi's `server` logged them (`shared/data/finken_flights`,
//! see its SOURCES.md): read with the definitions each log carries, turned into twin inputs,
//! their flights found where the IR says the copter took off (its `ir_distance` read in
//! metres, checked against `pos_z`), and the virtual-sonar uplink chosen by the messages.xml
//! in use.
//!
//! Skips loudly where the shared data is absent; fails under `CI=true`.

mod common;

use std::sync::Arc;
use std::time::{Duration, Instant};

use bridge::engine::{BusInput, Request};
use bridge::mixed::interpreter::{Interpreter, Quantity, TwinAttitude};
use bridge::paparazzi::convert::{Uplink, uplink_readings, uplink_text};
use bridge::paparazzi::flightlog::FlightLog;
use bridge::paparazzi::messages::MessageSet;
use bridge::realflight::{Series, derive_arena, flights, ground_ir_m, ir_unit_check, ir_unit_comparison, start_pose};

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

/// The aircraft that sent the most.
fn main_aircraft(log: &FlightLog) -> u8 {
    log.busiest_sender().expect("an aircraft sent something")
}

/// A log's IR heights (log time, value) in time order, straight from the decoded fields as the
/// log carries them: `FINKEN_SENSOR_MODEL.pos_z` and `FINKEN_IR_ADC.ir_distance`, no unit
/// applied and no `Series` in between.
fn raw_ir(log: &FlightLog, ac_id: u8) -> Vec<(f64, f64)> {
    let mut v: Vec<(f64, f64)> = log
        .from_aircraft(ac_id)
        .filter_map(|r| {
            let msg = log.message(r);
            let field = match msg.def.name.as_str() {
                "FINKEN_SENSOR_MODEL" => "pos_z",
                "FINKEN_IR_ADC" => "ir_distance",
                _ => return None,
            };
            let z = msg.get(field).and_then(bridge::Value::as_f64)?;
            (z.is_finite() && z > 0.0).then_some((r.time_s, z))
        })
        .collect();
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    v
}

/// `ROTORCRAFT_STATUS.ap_motors_on` (log time, on), straight from the decoded fields.
fn raw_motors(log: &FlightLog, ac_id: u8) -> Vec<(f64, bool)> {
    log.from_aircraft(ac_id)
        .filter(|r| log.def(r).name == "ROTORCRAFT_STATUS")
        .filter_map(|r| Some((r.time_s, log.message(r).get("ap_motors_on").and_then(bridge::Value::as_f64)? > 0.0)))
        .collect()
}

/// Take-offs by the IR alone: the first sample of each run above the floor reading (the 5th
/// percentile of all readings) + 0.1 m that stays above it 3 s or more.
fn ir_take_offs(ir: &[(f64, f64)]) -> Vec<f64> {
    let mut sorted: Vec<f64> = ir.iter().map(|s| s.1).collect();
    sorted.sort_by(f64::total_cmp);
    let Some(&ground) = sorted.get(sorted.len() / 20) else { return Vec::new() };
    let up = |z: f64| z > ground + 0.1;
    let mut out = Vec::new();
    let mut i = 0;
    while i < ir.len() {
        let run = ir[i..].iter().take_while(|s| up(s.1)).count();
        if run == 0 {
            i += 1;
            continue;
        }
        let (start, end) = (ir[i].0, ir[i + run - 1].0);
        if end - start >= 3.0 {
            out.push(start);
        }
        i += run;
    }
    out
}

/// Every shared log that has its `.log`: `FINKEN_IR_ADC.ir_distance` (no `unit`, `alt_unit`
/// cm in the lab's definitions) reads in metres, as `FINKEN_SENSOR_MODEL.pos_z` does; every
/// flight starts within 1 s of an IR take-off worked out here from the raw values (not when the
/// motors started, tens of seconds earlier in the `robust_multicopter_flight` logs), the first
/// at the first take-off with the motors on; and the two logs of a copter turned by hand on the
/// floor (`MC1_DISTANCES`, `MC2_DISTANCES`) have no flight.
#[test]
fn every_flight_starts_at_its_ir_take_off_and_the_ir_reads_in_metres() {
    let dir = shared_or_skip!();
    let mut checked = 0;
    for data in common::files_with_extension(&dir.join("finken_flights"), "data") {
        // The one `.data` without its `.log` is tested above (a clear error).
        if !data.with_extension("log").exists() {
            continue;
        }
        let name = data.display().to_string();
        let log = FlightLog::open(&data).unwrap_or_else(|e| panic!("{name}: {e}"));
        let ac_id = main_aircraft(&log);

        // The unit, checked against the independent value the same log carries.
        assert_eq!(ir_unit_check(&log, ac_id), None, "{name}");
        if log.from_aircraft(ac_id).any(|r| log.def(r).name == "FINKEN_IR_ADC") {
            let c = ir_unit_comparison(&log, ac_id).unwrap_or_else(|| panic!("{name}: no IR to hold against pos_z"));
            assert_eq!(c.read_as, "m", "{name}: {c:?}");
            assert!(c.pairs >= 20 && (0.9..1.1).contains(&c.median_ratio), "{name}: {c:?}");
        }

        let series = Series::of(&log, ac_id);
        let ground = ground_ir_m(&series).unwrap_or_else(|| panic!("{name}: no IR"));
        assert!((0.19..0.26).contains(&ground), "{name}: the IR on the floor reads {ground} m");
        let fl = flights(&series);
        let take_offs = ir_take_offs(&raw_ir(&log, ac_id));
        checked += 1;
        if name.contains("MC1_DISTANCES") || name.contains("MC2_DISTANCES") {
            assert!(take_offs.is_empty(), "{name}: never left the floor, yet the IR rose at {take_offs:?}");
            assert!(fl.is_empty(), "{name}: {fl:?}");
            continue;
        }
        assert!(!fl.is_empty(), "{name}: no flight (IR take-offs at {take_offs:?})");
        for f in &fl {
            let off = |t: &f64| (t - f.start_s).abs();
            let nearest = take_offs.iter().min_by(|a, b| off(a).total_cmp(&off(b)));
            assert!(
                nearest.is_some_and(|t| off(t) <= 1.0),
                "{name}: {f:?} does not start at an IR take-off (nearest {nearest:?}; all {take_offs:?})"
            );
        }
        // The first flight: the first take-off since the last status that said the motors were
        // off before they first ran.
        let motors = raw_motors(&log, ac_id);
        let first_on = motors.iter().find(|m| m.1).map(|m| m.0).unwrap_or_else(|| panic!("{name}: motors never on"));
        let off_before = motors.iter().rev().find(|m| !m.1 && m.0 < first_on).map_or(f64::NEG_INFINITY, |m| m.0);
        let first = take_offs.iter().copied().find(|t| *t >= off_before);
        assert!(
            first.is_some_and(|t| (fl[0].start_s - t).abs() <= 1.0),
            "{name}: first flight {:?}, first take-off with the motors on {first:?} (on at {first_on} s)",
            fl[0]
        );
    }
    assert!(checked >= 9, "{checked} logs with their .log checked");
}
