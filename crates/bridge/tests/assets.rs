//! Every file under `assets/` is loaded here (messages.xml is also covered
//! by tests/codec.rs): the conf.xml fixture and the pairing example, plus
//! malformed pairing files.

mod common;

use bridge::paparazzi::conf::AircraftKind;
use bridge::paparazzi::pairing::{AircraftRef, Route, UnknownAircraftPolicy, UnknownAircraftStats};
use bridge::{ConfXml, Pairing, XmlError};

use common::asset;

#[test]
fn conf_fixture_parses_with_virtual_rule() {
    let conf = ConfXml::from_file(asset("paparazzi/conf.xml")).unwrap_or_else(|e| panic!("{e}"));
    let names: Vec<(&str, u8, AircraftKind)> =
        conf.aircraft.iter().map(|a| (a.name.as_str(), a.ac_id, a.kind())).collect();
    assert_eq!(
        names,
        [
            ("FINken_01", 5, AircraftKind::Real),
            ("FINken_02", 6, AircraftKind::Real),
            ("FINken_03", 7, AircraftKind::Real),
            ("Virtual_01", 101, AircraftKind::Virtual),
            ("Virtual_02", 102, AircraftKind::Virtual),
        ]
    );
    assert_eq!(conf.real().count(), 3);
    assert_eq!(conf.virtual_aircraft().count(), 2);
    assert_eq!(conf.aircraft[0].source_line, 8);
}

#[test]
fn pairing_example_parses_and_resolves() {
    let path = asset("pairing/finken_lab.xml");
    let p = Pairing::from_file(&path).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(p.twins.len(), 2);
    assert_eq!(p.twins[0].aircraft, AircraftRef::Name("FINken_01".into()));
    assert_eq!(p.twins[1].aircraft, AircraftRef::AcId(6));
    assert!((p.twins[1].pose.yaw_rad - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    assert_eq!(p.virtual_copters.len(), 2);
    assert_eq!(p.unknown_policy, UnknownAircraftPolicy::Spawn);
    let spawn = p.spawn.expect("spawn point");
    assert_eq!(spawn.spacing_m, 0.5);
    let second = spawn.pose_for(1);
    assert!((second.x_m - 0.0).abs() < 1e-12 && (second.y_m - 0.8).abs() < 1e-12, "{second:?}");

    let conf_path = p.conf_path_from(&path);
    let conf = ConfXml::from_file(&conf_path).unwrap_or_else(|e| panic!("{e}"));
    let r = p.resolve(&conf).unwrap_or_else(|e| panic!("{e}"));
    let ids: Vec<u8> = r.by_ac_id.keys().copied().collect();
    assert_eq!(ids, [5, 6, 101, 102]);
    assert_eq!(r.by_ac_id[&6].copter, "finken_02");
    assert_eq!(r.by_ac_id[&6].aircraft_name.as_deref(), Some("FINken_02"));
    assert_eq!(r.by_ac_id[&101].kind, AircraftKind::Virtual);
    // Virtual_02 has no pose: it starts at the spawn point.
    assert_eq!(r.by_ac_id[&102].pose, spawn.pose);
    assert!(matches!(r.route(5), Route::Assigned(a) if a.copter == "finken_01"));
    assert!(
        matches!(r.route(7), Route::Spawn { aircraft: Some("FINken_03"), .. }),
        "FINken_03 is in conf.xml but not twinned"
    );
    assert!(matches!(r.route(99), Route::Spawn { aircraft: None, .. }), "not in conf.xml, policy spawn");
}

#[test]
fn ignore_is_the_default_policy_and_is_counted() {
    let text = r#"<pairing version="1"><conf path="c.xml"/><twin ac_id="5" copter="a" x_m="0" y_m="0" z_m="0" yaw_deg="0"/></pairing>"#;
    let p = Pairing::parse(text, "p.xml").unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(p.unknown_policy, UnknownAircraftPolicy::Ignore);
    let conf =
        ConfXml::parse(r#"<conf><aircraft name="A" ac_id="5"/></conf>"#, "c.xml").unwrap_or_else(|e| panic!("{e}"));
    let r = p.resolve(&conf).unwrap_or_else(|e| panic!("{e}"));
    let mut stats = UnknownAircraftStats::default();
    for id in [9, 9, 12] {
        if r.route(id) == Route::Ignore {
            stats.record(id);
        }
    }
    assert_eq!(stats.total(), 3);
    assert_eq!(stats.dropped_by_ac_id.get(&9), Some(&2));
}

fn pairing_err(text: &str) -> XmlError {
    match Pairing::parse(text, "bad.xml") {
        Ok(p) => panic!("parsed: {p:?}"),
        Err(e) => e,
    }
}

#[test]
fn malformed_pairing_files_give_errors_with_lines() {
    let head = "<pairing version=\"1\">\n<conf path=\"c.xml\"/>\n";
    // 1. twin naming both an aircraft and an ac_id (line 3)
    let e = pairing_err(&format!(
        "{head}<twin aircraft=\"A\" ac_id=\"5\" copter=\"a\" x_m=\"0\" y_m=\"0\" z_m=\"0\" yaw_deg=\"0\"/>\n</pairing>"
    ));
    assert!(matches!(e, XmlError::Invalid { .. }), "{e}");
    assert_eq!(e.line(), Some(3), "{e}");
    // 2. a pose value that is not a number, on its own line (line 5)
    let e = pairing_err(&format!(
        "{head}<twin ac_id=\"5\" copter=\"a\"\n  x_m=\"0\" y_m=\"0\"\n  z_m=\"high\" yaw_deg=\"0\"/>\n</pairing>"
    ));
    assert!(matches!(e, XmlError::BadAttribute { ref attribute, .. } if attribute == "z_m"), "{e}");
    assert_eq!(e.line(), Some(5), "{e}");
    assert!(e.to_string().starts_with("bad.xml:5:"), "{e}");
    // 3. unknown policy (line 4)
    let e = pairing_err(&format!("{head}\n<unknown_aircraft policy=\"explode\"/>\n</pairing>"));
    assert!(matches!(e, XmlError::BadAttribute { .. }), "{e}");
    assert_eq!(e.line(), Some(4), "{e}");
    // 4. duplicate copter name (line 4, first at 3)
    let e = pairing_err(&format!(
        "{head}<twin ac_id=\"5\" copter=\"a\" x_m=\"0\" y_m=\"0\" z_m=\"0\" yaw_deg=\"0\"/>\n<virtual name=\"a\" ac_id=\"101\" x_m=\"0\" y_m=\"0\" z_m=\"0\" yaw_deg=\"0\"/>\n</pairing>"
    ));
    assert!(matches!(e, XmlError::Duplicate { first_line: 3, .. }), "{e}");
    assert_eq!(e.line(), Some(4));
    // 5. unknown attribute (strict format), e.g. a misspelled unit (line 3)
    let e = pairing_err(&format!(
        "{head}<twin ac_id=\"5\" copter=\"a\" x=\"0\" y_m=\"0\" z_m=\"0\" yaw_deg=\"0\"/>\n</pairing>"
    ));
    assert!(matches!(e, XmlError::UnknownAttribute { .. }), "{e}");
    assert_eq!(e.line(), Some(3));
    // 6. unknown element (line 3)
    let e = pairing_err(&format!("{head}<copter name=\"x\"/>\n</pairing>"));
    assert!(matches!(e, XmlError::UnexpectedElement { .. }), "{e}");
    assert_eq!(e.line(), Some(3));
    // 7. missing <conf> (line 1), and spawn policy without spawn point
    let e = pairing_err("<pairing version=\"1\">\n</pairing>");
    assert_eq!(e.line(), Some(1));
    let e = pairing_err(&format!("{head}<unknown_aircraft policy=\"spawn\"/>\n</pairing>"));
    assert!(e.to_string().contains("spawn"), "{e}");
    // 8. not well-formed XML: unclosed element (reported with a line)
    let e = pairing_err(&format!("{head}<twin ac_id=\"5\" copter=\"a\"\n</pairing>"));
    assert!(matches!(e, XmlError::Syntax { .. }), "{e}");
    assert!(e.line().is_some());
    // 9. ac_id out of range
    let e = pairing_err(&format!(
        "{head}<virtual name=\"v\" ac_id=\"300\" x_m=\"0\" y_m=\"0\" z_m=\"0\" yaw_deg=\"0\"/>\n</pairing>"
    ));
    assert!(matches!(e, XmlError::BadAttribute { .. }), "{e}");
    assert_eq!(e.line(), Some(3));
}

#[test]
fn resolve_errors_point_at_the_pairing_line() {
    let conf = ConfXml::from_file(asset("paparazzi/conf.xml")).unwrap_or_else(|e| panic!("{e}"));
    let head = "<pairing version=\"1\">\n<conf path=\"c.xml\"/>\n";
    let p = Pairing::parse(
        &format!(
            "{head}\n<twin aircraft=\"Nope\" copter=\"a\" x_m=\"0\" y_m=\"0\" z_m=\"0\" yaw_deg=\"0\"/>\n</pairing>"
        ),
        "p.xml",
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let e = p.resolve(&conf).expect_err("unknown aircraft");
    assert_eq!(e.line(), Some(4), "{e}");
    let p = Pairing::parse(
        &format!(
            "{head}<twin aircraft=\"Virtual_01\" copter=\"a\" x_m=\"0\" y_m=\"0\" z_m=\"0\" yaw_deg=\"0\"/>\n</pairing>"
        ),
        "p.xml",
    )
    .unwrap_or_else(|e| panic!("{e}"));
    assert!(p.resolve(&conf).expect_err("virtual twinned").to_string().contains("virtual"));
    let p = Pairing::parse(
        &format!("{head}<virtual name=\"V\" ac_id=\"5\" x_m=\"0\" y_m=\"0\" z_m=\"0\" yaw_deg=\"0\"/>\n</pairing>"),
        "p.xml",
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let e = p.resolve(&conf).expect_err("virtual on a real id");
    assert_eq!(e.line(), Some(3), "{e}");
}

#[test]
fn a_twin_flown_by_its_autopilot_becomes_an_autopilot_copter() {
    let text = r#"<pairing version="1"><conf path="c.xml"/>
<twin aircraft="FINken_NPS" copter="nps" flown_by="autopilot" x_m="0.5" y_m="0" z_m="0" yaw_deg="0"/>
<twin ac_id="5" copter="real" x_m="-0.5" y_m="0" z_m="0" yaw_deg="0"/></pairing>"#;
    let p = Pairing::parse(text, "p.xml").unwrap_or_else(|e| panic!("{e}"));
    let conf = ConfXml::parse(
        r#"<conf><aircraft name="FINken_NPS" ac_id="7"/><aircraft name="A" ac_id="5"/></conf>"#,
        "c.xml",
    )
    .unwrap_or_else(|e| panic!("{e}"));
    let r = p.resolve(&conf).unwrap_or_else(|e| panic!("{e}"));
    let scene = "name = \"s\"\n[arena]\nsize_m = [4.0, 3.0]\nheight_m = 2.5\n";
    let mut spec = sim_core::SceneSpec::from_toml("s.toml", scene).unwrap();
    bridge::mixed::router::apply_pairing(&mut spec, &r).unwrap();
    let kinds: Vec<_> = spec.copters.iter().map(|c| (c.name.as_str(), c.kind, c.ac_id)).collect();
    assert!(kinds.contains(&("nps", sim_core::CopterKind::Autopilot, Some(7))), "{kinds:?}");
    assert!(kinds.contains(&("real", sim_core::CopterKind::Real, Some(5))), "{kinds:?}");
    let world = sim_core::compile(&spec).unwrap();
    let nps = world.copter_id("nps").unwrap();
    assert_eq!(world.copters[nps].initial_command.mode, sim_core::FlightMode::Rotors);
    // Its telemetry reaches the ground station, not the copter.
    let mut router = bridge::mixed::router::Router::new(&world, Some(r));
    assert_eq!(router.route(7), bridge::mixed::router::Decision::Autopilot);

    let e = pairing_err(
        r#"<pairing version="1"><conf path="c.xml"/>
<twin ac_id="5" copter="a" flown_by="nps" x_m="0" y_m="0" z_m="0" yaw_deg="0"/></pairing>"#,
    );
    assert!(e.to_string().contains("flown_by must be `telemetry` or `autopilot`, not `nps`"), "{e}");
    assert_eq!(e.line(), Some(2), "{e}");
}
