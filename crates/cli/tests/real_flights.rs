//! `twinswarm validate` and `twinswarm log import` on real FINken flights
//! (`shared/data/finken_flights`): skips loudly where the shared data is absent, fails under
//! `CI=true`.

#[path = "../../bridge/tests/common/mod.rs"]
mod common;

use std::path::Path;
use std::process::Command;

const LINKED: &str = "finken_flights/report_2015-12-16/15_12_16__13_55_00.data";
const VREP: &str = "finken_flights/report_2015-12-16/simulationPosition20151216140935.log";

fn twinswarm(args: &[&str], dir: &Path) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_twinswarm")).args(args).current_dir(dir).output().expect("run twinswarm")
}

fn json_of(out: &std::process::Output) -> serde_json::Value {
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stdout)))
}

#[test]
fn the_linked_flights_twin_stays_in_the_arena_and_consistent_beside_vreps() {
    let shared = shared_or_skip!();
    let tmp = std::env::temp_dir().join(format!("twinswarm-validate-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).expect("tmp");
    let data = shared.join(LINKED);
    let vrep = shared.join(VREP);
    let plots = tmp.join("plots");
    let args = [
        "validate",
        data.to_str().unwrap_or_default(),
        "--window",
        "826,876",
        "--vrep",
        vrep.to_str().unwrap_or_default(),
        "--plots",
        plots.to_str().unwrap_or_default(),
        "--json",
    ];
    let r = json_of(&twinswarm(&args, &tmp));
    assert_eq!(r["ac_id"], 5);
    assert_eq!(r["telemetry_mode"], "vrep");
    let flights = r["flights"].as_array().expect("flights");
    assert_eq!(flights.len(), 1, "{r}");
    let f = &flights[0];
    let synced = &f["synced"];
    // The twin as a lab uses it: in the arena, its sonars reading what the real ones read, the
    // whole flight.
    assert_eq!(synced["inside_share"], 1.0, "{synced}");
    // It strays once, for about three seconds, at the flight's hardest manoeuvre (the copter
    // brakes 0.45 m from the front wall while its back sonar reads an object the arena lacks)
    // and comes back (docs/real-flights.md).
    assert!(synced["strayed_s"].is_null() || synced["strayed_s"].as_f64().is_some_and(|t| t > 20.0), "{synced}");
    assert!(synced["consistent_share"].as_f64().is_some_and(|s| s > 0.9), "{synced}");
    assert!(synced["sonar_all_cm"]["median"].as_f64().is_some_and(|m| m < 25.0), "{synced}");
    for k in 0..2 {
        assert!(synced["attitude_rms_deg"][k].as_f64().is_some_and(|d| d < 3.0), "{synced}");
    }
    assert!(f["sources"].as_str().is_some_and(|s| s.contains("attitude ← AHRS_EULER_INT")), "{f}");
    // Without the correction the flight model alone predicts: reported, whatever it does.
    assert!(f["unsynced"]["consistent_s"].as_f64().is_some_and(|s| s > 0.0), "{f}");
    // V-REP's own twin of the flight, scored the same way.
    let v = &f["vrep"];
    assert!(v["metrics"]["sonar_all_cm"]["n"].as_u64().is_some_and(|n| n > 100), "{v}");
    assert!(v["start_s"].as_f64().is_some_and(|t| (815.0..840.0).contains(&t)), "{v}");
    // It left the arena during the flight, as the paper reports.
    assert!(v["metrics"]["inside_share"].as_f64().is_some_and(|s| s < 0.6), "{v}");
    let k = f["index"].as_u64().expect("index");
    for name in [format!("flight-{k}-attitude.png"), format!("flight-{k}-sonar.png")] {
        let png = std::fs::read(plots.join(&name)).expect(&name);
        assert!(png.starts_with(b"\x89PNG"), "{name}");
    }
    let _ = std::fs::remove_dir_all(&tmp);
}

#[test]
fn a_real_flight_imports_as_a_log_that_plot_and_log_info_read() {
    let shared = shared_or_skip!();
    let tmp = std::env::temp_dir().join(format!("twinswarm-import-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).expect("tmp");
    let data = shared.join(LINKED);
    let out = twinswarm(&["log", "import", data.to_str().unwrap_or_default(), "-o", "flight.mcap"], &tmp);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("aircraft 5") && text.contains("flight 6: log 835"), "{text}");
    let info = twinswarm(&["log", "info", "flight.mcap"], &tmp);
    let info_text = String::from_utf8_lossy(&info.stdout);
    assert!(info.status.success(), "{}", String::from_utf8_lossy(&info.stderr));
    assert!(info_text.contains("/pprz/5/FINKEN_SENSOR_MODEL"), "{info_text}");
    let plot = twinswarm(&["plot", "flight.mcap", "--attitude", "att.png", "--sonar", "sonar.png"], &tmp);
    assert!(plot.status.success(), "{}", String::from_utf8_lossy(&plot.stderr));
    assert!(std::fs::read(tmp.join("att.png")).is_ok_and(|b| b.starts_with(b"\x89PNG")));
    let _ = std::fs::remove_dir_all(&tmp);
}

/// Every shared log that has its `.log` imports, and `plot --sonar --attitude` draws each import:
/// the `default` telemetry mode's (`FINKEN_SENSOR_MODEL` at 10 Hz, `FINKEN_IR_ADC` at 1 Hz with
/// the IR only, no AHRS message) as well as the linked flight's (issue 48).
#[test]
fn every_shared_log_imports_as_a_log_whose_sonars_and_attitude_plot() {
    let shared = shared_or_skip!();
    let tmp = std::env::temp_dir().join(format!("twinswarm-import-all-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).expect("tmp");
    let logs: Vec<_> = common::files_with_extension(&shared.join("finken_flights"), "data")
        .into_iter()
        .filter(|data| data.with_extension("log").is_file())
        .collect();
    assert!(logs.len() >= 9, "the shared logs with their .log beside: {logs:?}");
    for (k, data) in logs.iter().enumerate() {
        let name = data.strip_prefix(&shared).unwrap_or(data.as_path()).display().to_string();
        let mcap = format!("import-{k}.mcap");
        let import = twinswarm(&["log", "import", data.to_str().unwrap_or_default(), "-o", mcap.as_str()], &tmp);
        assert!(import.status.success(), "{name}: log import: {}", String::from_utf8_lossy(&import.stderr));
        let (sonar, att) = (format!("sonar-{k}.png"), format!("attitude-{k}.png"));
        let plot = twinswarm(&["plot", mcap.as_str(), "--sonar", sonar.as_str(), "--attitude", att.as_str()], &tmp);
        assert!(plot.status.success(), "{name}: plot: {}", String::from_utf8_lossy(&plot.stderr));
        for png in [&sonar, &att] {
            let bytes = std::fs::read(tmp.join(png)).unwrap_or_else(|e| panic!("{name}: {png}: {e}"));
            assert!(bytes.starts_with(b"\x89PNG") && bytes.len() > 1000, "{name}: {png}: {} bytes", bytes.len());
        }
    }
    let _ = std::fs::remove_dir_all(&tmp);
}

/// Every flight of 10 s or more of every shared log: the synced twin consistent with the real
/// sonars for at least 80 % of it, or the report shows why it cannot be: the copter turned in
/// flight (its sums mix the arena's sides) and MEDUSA found no confident fix for most of its
/// estimates. Each such flight is named here, so that a newly failing one fails the test
/// (docs/real-flights.md, "Every shared flight").
#[test]
fn every_shared_flight_keeps_its_synced_twin_consistent_or_says_why_not() {
    const EXCUSED: [&str; 1] = ["FreeFlight_MC32/second"];
    let shared = shared_or_skip!();
    let tmp = std::env::temp_dir().join(format!("twinswarm-validate-all-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).expect("tmp");
    let logs: Vec<_> = common::files_with_extension(&shared.join("finken_flights"), "data")
        .into_iter()
        .filter(|data| data.with_extension("log").is_file())
        .collect();
    let (mut scored, mut excused) = (0, Vec::new());
    for data in &logs {
        let name = data.strip_prefix(&shared).unwrap_or(data.as_path()).display().to_string();
        let out = twinswarm(&["validate", data.to_str().unwrap_or_default(), "--json"], &tmp);
        if !out.status.success() {
            // Logs in which the copter never flew (turned by hand, motors off) say so.
            let err = String::from_utf8_lossy(&out.stderr);
            assert!(err.contains("no flight in the log"), "{name}: {err}");
            continue;
        }
        let r = json_of(&out);
        for f in r["flights"].as_array().expect("flights") {
            let synced = &f["synced"];
            if synced["span_s"].as_f64().is_none_or(|s| s < 10.0) {
                continue;
            }
            scored += 1;
            let share = synced["consistent_share"].as_f64().unwrap_or(0.0);
            if share >= 0.8 {
                continue;
            }
            let why = format!("{name} flight {}: consistent {:.0} % ({f})", f["index"], share * 100.0);
            assert!(EXCUSED.iter().any(|e| name.contains(e)), "{why}");
            let turned = f["turned_deg"].as_f64().unwrap_or(0.0);
            let (used, rejected) = (f["sync"]["medusa_updates"].as_u64(), f["sync"]["medusa_rejected"].as_u64());
            assert!(turned > 30.0, "{why}: it did not turn");
            assert!(used.zip(rejected).is_some_and(|(u, r)| 2 * r > u), "{why}: MEDUSA was confident");
            excused.push(name.clone());
        }
    }
    assert!(scored >= 12, "{scored} flights of 10 s or more");
    assert_eq!(excused.len(), EXCUSED.len(), "an excused flight that passes is no longer excused: {excused:?}");
    let _ = std::fs::remove_dir_all(&tmp);
}

#[test]
fn a_data_file_without_its_log_is_a_clear_error() {
    let shared = shared_or_skip!();
    let lonely = shared.join("finken_flights/robust_multicopter_flight/MC2_DistancesOnFlight/15_12_01__17_48_45.data");
    let out = twinswarm(&["validate", lonely.to_str().unwrap_or_default()], &std::env::temp_dir());
    assert_eq!(out.status.code(), Some(2), "{}", String::from_utf8_lossy(&out.stderr));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("15_12_01__17_48_45.log does not exist"), "{err}");
    // The cause, once.
    assert_eq!(err.matches("does not exist").count(), 1, "{err}");
    assert!(!err.contains("os error") && !err.contains("No such file"), "{err}");
}

/// A small FINken log of the project's own (`tests/fixtures/finken_small.*`: 8 s, aircraft 5,
/// the 2015 fork's layout), with one torn line: read, imported and validated without the
/// shared data.
#[test]
fn a_small_log_of_our_own_with_a_torn_line_imports_and_validates() {
    let fixture = |ext: &str| {
        let p = format!("{}/../../tests/fixtures/finken_small.{ext}", env!("CARGO_MANIFEST_DIR"));
        std::fs::read(&p).unwrap_or_else(|e| panic!("{p}: {e}"))
    };
    let tmp = std::env::temp_dir().join(format!("twinswarm-own-log-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).expect("tmp");
    std::fs::write(tmp.join("own.log"), fixture("log")).expect("log");
    let mut data = fixture("data");
    data.extend_from_slice(b"9.9 5 FINKEN_SENSOR_MODEL 180 13\n");
    std::fs::write(tmp.join("own.data"), &data).expect("data");
    let out = twinswarm(&["log", "import", "own.data", "-o", "own.mcap"], &tmp);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(text.contains("(1 unreadable") && text.contains("undecodable fields"), "{text}");
    let r = json_of(&twinswarm(&["validate", "own.data", "--json"], &tmp));
    assert_eq!(r["line_errors"]["by_message"]["FINKEN_SENSOR_MODEL"], 1, "{r}");
    assert_eq!(r["line_errors"]["first"][0][0], 81, "{r}");
    assert_eq!(r["flights"].as_array().map(Vec::len), Some(1), "{r}");
    // Bad arguments name what is wrong, exit 2.
    let bad = twinswarm(&["validate", "own.data", "--window", "5,3"], &tmp);
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("--window"), "{}", String::from_utf8_lossy(&bad.stderr));
    let bad = twinswarm(&["replay", "own.data", "--foxglove"], &tmp);
    assert_eq!(bad.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&bad.stderr).contains("log import"), "{}", String::from_utf8_lossy(&bad.stderr));
    let _ = std::fs::remove_dir_all(&tmp);
}

#[test]
fn a_sync_setting_that_is_no_number_is_a_clear_error() {
    // Checked before the log is read: no shared data needed.
    for (flag, v) in [("--hold-trim-s", "-1"), ("--sync-max-speed", "NaN"), ("--sync-gain", "inf")] {
        let arg = format!("{flag}={v}");
        let out = twinswarm(&["validate", "nowhere.data", arg.as_str()], &std::env::temp_dir());
        assert_eq!(out.status.code(), Some(2), "{}", String::from_utf8_lossy(&out.stderr));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(&format!("{flag} {v}: must be a number at least 0")), "{err}");
    }
}
