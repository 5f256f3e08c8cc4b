//! Interoperability tests against the real Paparazzi / pprzlink files in
//! `shared/data`: the repository's `../shared/data`, or the directory named by
//! `TWINSWARM_SHARED_DATA`.
//!
//! When that directory is absent, each test skips loudly (a `SKIPPED` line on stderr, shown
//! even when output is captured, and a line in the file named by `TWINSWARM_SKIP_LOG`, which
//! `scripts/test.sh` counts), and under `CI=true` it fails instead, naming the path. To see
//! both: `TWINSWARM_SHARED_DATA=/nonexistent cargo test -p bridge --test shared_data`, with
//! and without `CI=true`.

mod common;

use std::collections::BTreeMap;

use bridge::paparazzi::codec::{Sender, encode};
use bridge::paparazzi::messages::{DefinitionFormat, MessageSet};
use bridge::paparazzi::telemetry::Telemetry;
use bridge::{ConfXml, XmlError};

use common::{Gen, same_bits, xml_files};

/// Every `.xml` whose root is `<protocol>` (i.e. holds message definitions).
fn message_files(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    xml_files(dir).into_iter().filter(|p| std::fs::read_to_string(p).is_ok_and(|t| t.contains("<protocol>"))).collect()
}

#[test]
fn every_shared_messages_file_parses() {
    let dir = shared_or_skip!();
    let files = message_files(&dir);
    let names: Vec<String> =
        files.iter().filter_map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned())).collect();
    // The four messages.xml of SOURCES.md.
    for expected in
        ["FINken_conf_messages.xml", "messages_v1.0.xml", "master_messages_v1.0.xml", "swarmlab_messages_v1.0.xml"]
    {
        assert!(names.iter().any(|n| n == expected), "{expected} not found in {names:?}");
    }
    for f in &files {
        let set = MessageSet::from_file(f).unwrap_or_else(|e| panic!("{e}"));
        assert!(set.len() > 100, "{}: only {} messages", f.display(), set.len());
        // The FINken fork's conf/messages.xml and its mixed-reality branch's predate pprzlink.
        let legacy = ["paparazzi_finken/FINken_conf_messages.xml", "paparazzi_finken/mixed_reality_conf_messages.xml"];
        let expected_format =
            if legacy.iter().any(|l| f.ends_with(l)) { DefinitionFormat::Legacy } else { DefinitionFormat::PprzlinkV1 };
        assert_eq!(set.format, expected_format, "{}", f.display());
    }
}

#[test]
fn every_message_of_every_file_round_trips() {
    let dir = shared_or_skip!();
    let mut total = 0;
    let mut types_seen = BTreeMap::new();
    for f in message_files(&dir) {
        let set = MessageSet::from_file(&f).unwrap_or_else(|e| panic!("{e}"));
        for (i, def) in set.iter().enumerate() {
            for f_def in &def.fields {
                *types_seen.entry(f_def.ty.to_string()).or_insert(0) += 1;
            }
            for seed in 0..4u64 {
                let mut g = Gen::new(seed * 7919 + i as u64);
                let values = g.values(def);
                let sender = match def.class_name.as_str() {
                    "telemetry" => Sender::Aircraft(g.below(256) as u8),
                    "datalink" => Sender::Agent("ground_dl".into()),
                    other => Sender::Agent(other.into()),
                };
                let text = encode(&sender, def, &values)
                    .unwrap_or_else(|e| panic!("{}: encode {}: {e}", f.display(), def.name));
                let back = set.decode(&text).unwrap_or_else(|e| panic!("{}: decode `{text}`: {e}", f.display()));
                assert_eq!(back.def.name, def.name);
                assert_eq!(back.def.class_name, def.class_name);
                assert_eq!(back.sender, sender);
                assert_eq!(back.values.len(), values.len());
                for ((a, b), fd) in values.iter().zip(&back.values).zip(&def.fields) {
                    assert!(same_bits(a, b), "{} {}.{}: {a:?} != {b:?} via `{text}`", f.display(), def.name, fd.name);
                }
                assert_eq!(back.to_ivy().as_deref(), Ok(text.as_str()), "re-encoding is identical");
                total += 1;
            }
        }
    }
    // Every kind of type present in the files was exercised.
    for t in [
        "uint8",
        "int8",
        "uint16",
        "int16",
        "uint32",
        "int32",
        "float",
        "double",
        "string",
        "char[]",
        "uint8[]",
        "float[]",
        "float[3]",
        "char[5]",
        "uint16[3]",
    ] {
        assert!(types_seen.contains_key(t), "type {t} not exercised: {types_seen:?}");
    }
    assert!(total > 4 * 1000, "only {total} round trips");
}

#[test]
fn misspelled_field_survives_verbatim() {
    let dir = shared_or_skip!();
    let set =
        MessageSet::from_file(dir.join("paparazzi_finken/FINken_conf_messages.xml")).unwrap_or_else(|e| panic!("{e}"));
    let def = set.by_name("FINKEN_SENSOR_MODEL").expect("FINKEN_SENSOR_MODEL");
    assert_eq!(def.id, 217);
    assert_eq!(def.fields[1].name, "distance_d_rigth");
    let mut g = Gen::new(1);
    let text = encode(&Sender::Aircraft(5), def, &g.values(def)).expect("encodes");
    let msg = set.decode(&text).expect("decodes");
    assert!(msg.get("distance_d_rigth").is_some());
    assert!(msg.get("distance_d_right").is_none());
    let json = serde_json::to_string(&msg).expect("json");
    assert!(json.contains("\"distance_d_rigth\":"), "{json}");
}

#[test]
fn layouts_come_from_the_file_not_from_code() {
    let dir = shared_or_skip!();
    let finken =
        MessageSet::from_file(dir.join("paparazzi_finken/FINken_conf_messages.xml")).unwrap_or_else(|e| panic!("{e}"));
    let upstream = MessageSet::from_file(dir.join("pprzlink/messages_v1.0.xml")).unwrap_or_else(|e| panic!("{e}"));
    // FINken-era classes have no ids; upstream telemetry is class 1.
    assert_eq!(finken.class("telemetry").and_then(|c| c.id), None);
    assert_eq!(upstream.class("telemetry").and_then(|c| c.id), Some(1));
    // SONAR_ARRAY exists only in the FINken-era file.
    assert!(finken.by_name("SONAR_ARRAY").is_some());
    assert!(upstream.by_name("SONAR_ARRAY").is_none());
    // Same ROTORCRAFT_FP fields, but carrot_psi's display coefficient differs.
    let a = finken.by_name("ROTORCRAFT_FP").expect("finken FP");
    let b = upstream.by_name("ROTORCRAFT_FP").expect("upstream FP");
    let names = |d: &bridge::MessageDef| d.fields.iter().map(|f| f.name.clone()).collect::<Vec<_>>();
    assert_eq!(names(a), names(b));
    assert_eq!(a.field("carrot_psi").and_then(|f| f.alt_unit_coef), Some(0.0000546));
    assert_eq!(b.field("carrot_psi").and_then(|f| f.alt_unit_coef), Some(0.0139882));
    // Typed attributes are read: values, format, unit, description, link.
    let upstream_types: Vec<String> = upstream.iter().flat_map(|d| d.fields.iter().map(|f| f.ty.to_string())).collect();
    assert!(upstream_types.iter().any(|t| t == "char[5]"));
    let setting = upstream.by_class_and_name("datalink", "SETTING").expect("SETTING");
    assert_eq!(setting.link, Some(bridge::paparazzi::messages::LinkMode::Forwarded));
    let gps = upstream.by_name("GPS").expect("GPS");
    assert_eq!(gps.field("utm_east").and_then(|f| f.unit.as_deref()), Some("cm"));
    assert!(upstream.iter().any(|d| d.fields.iter().any(|f| !f.values.is_empty())));
    assert!(upstream.iter().any(|d| d.fields.iter().any(|f| f.format.is_some())));
    assert!(upstream.iter().any(|d| d.description.is_some()));
}

#[test]
fn shared_conf_files_have_the_right_aircraft_counts() {
    let dir = shared_or_skip!();
    // Expected counts were obtained independently with
    //   grep -c "<aircraft" <file>
    // after checking (grep -n "<!--") that none of these files contains a
    // comment, so no commented-out aircraft is counted.
    let expected = [
        ("paparazzi_finken/FINken_conf.xml", 11),
        ("paparazzi_finken/FINken_conf_example.xml", 26),
        ("paparazzi_finken/FINken_conf_tests.xml", 41),
        ("paparazzi_finken/droneSwarm_conf.xml", 15),
    ];
    for (rel, count) in expected {
        let conf = ConfXml::from_file(dir.join(rel)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(conf.aircraft.len(), count, "{rel}");
        // No aircraft in these files follows the `Virtual` naming rule.
        assert_eq!(conf.virtual_aircraft().count(), 0, "{rel}");
    }
    let conf = ConfXml::from_file(dir.join("paparazzi_finken/FINken_conf.xml")).unwrap_or_else(|e| panic!("{e}"));
    let first = &conf.aircraft[0];
    assert_eq!((first.name.as_str(), first.ac_id), ("FINken3_01", 5));
    assert_eq!(first.airframe.as_deref(), Some("airframes/ovgu/fink3_max_bgr.xml"));
    assert_eq!(first.telemetry.as_deref(), Some("telemetry/ovgu/free_flight.xml"));
    assert_eq!(first.settings.len(), 6);
    assert_eq!(first.settings_modules, ["modules/ws2801.xml", "modules/logger_sd_spi_direct.xml"]);
    assert_eq!(first.gui_color.as_deref(), Some("#fe32ffff0000"));
    assert_eq!(conf.by_ac_id(50).map(|a| a.name.as_str()), Some("FINken3_Demo"));
    assert!(conf.by_name("Quad_Lia_ovgu_04").is_some_and(|a| a.settings_modules.is_empty()));
}

#[test]
fn free_flight_telemetry_periods() {
    let dir = shared_or_skip!();
    let t = Telemetry::from_file(dir.join("paparazzi_finken/FINken_telemetry_ovgu_free_flight.xml"))
        .unwrap_or_else(|e| panic!("{e}"));
    let main = t.process("Main").expect("Main");
    let names: Vec<&str> = main.modes.iter().map(|m| m.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "default",
            "extended",
            "empty",
            "finken_data",
            "ppm",
            "raw_sensors",
            "scaled_sensors",
            "ahrs",
            "attitude_setpoint_viz",
            "attitude_loop"
        ]
    );
    let default = main.mode("default").expect("default");
    assert_eq!(default.key_press.as_deref(), Some("d"));
    assert_eq!(default.period_s("FINKEN_SENSOR_MODEL"), Some(0.1));
    assert_eq!(default.period_s("FINKEN_ACTUATORS_SET_POINT"), Some(0.1));
    assert_eq!(default.period_s("ROTORCRAFT_FP"), Some(1.0));
    assert_eq!(default.period_s("SONAR_ARRAY"), None);
    let extended = main.mode("extended").expect("extended");
    assert_eq!(extended.period_s("SONAR_ARRAY"), Some(1.0));
    assert_eq!(extended.period_s("FINKEN_SENSOR_MODEL"), Some(2.0));
    assert_eq!(extended.period_s("INS_REF"), None, "commented out in the file");
    assert_eq!(main.mode("empty").map(|m| m.messages.len()), Some(0));
    assert_eq!(main.mode("ppm").and_then(|m| m.period_s("ROTORCRAFT_CMD")), Some(0.05));
    // message -> period per mode
    let by_msg = main.periods_by_message();
    let sonar: Vec<(&str, f64)> = by_msg["SONAR_ARRAY"].iter().map(|(k, v)| (*k, *v)).collect();
    assert_eq!(sonar, [("extended", 1.0)]);
    let fsm: Vec<(&str, f64)> = by_msg["FINKEN_SENSOR_MODEL"].iter().map(|(k, v)| (*k, *v)).collect();
    assert_eq!(fsm, [("default", 0.1), ("extended", 2.0), ("finken_data", 0.3)]);
    let logger = t.process("Logger").expect("Logger");
    assert_eq!(logger.mode("default").and_then(|m| m.period_s("FINKEN_SENSOR_MODEL")), Some(0.03));
}

#[test]
fn every_shared_telemetry_file_parses() {
    let dir = shared_or_skip!();
    let files: Vec<_> = xml_files(&dir)
        .into_iter()
        .filter(|p| std::fs::read_to_string(p).is_ok_and(|t| t.contains("<telemetry>")))
        .collect();
    // The four of paparazzi_finken/ and the telemetry files the real flights flew with
    // (finken_flights/airframe_*).
    assert_eq!(files.len(), 6, "{files:?}");
    for f in files {
        let t = Telemetry::from_file(&f).unwrap_or_else(|e| panic!("{e}"));
        assert!(t.process("Main").is_some(), "{}", f.display());
    }
}

#[test]
fn shared_files_of_other_kinds_are_rejected_with_a_location() {
    let dir = shared_or_skip!();
    // A conf.xml is not a messages.xml: wrong root, reported at line 1.
    let e = MessageSet::from_file(dir.join("paparazzi_finken/FINken_conf.xml")).expect_err("not messages");
    assert!(matches!(e, XmlError::WrongRoot { .. }), "{e}");
    assert_eq!(e.line(), Some(1));
}
