//! Twin synchronisation end to end (`twinswarm localize --sync-eval`): a stand-in's telemetry
//! (22 ms period on the measured link, 5 % loss) drives its twin through the gateway's interpreter and
//! the step loop, in simulated time.
//!
//! - 10 simulated minutes with MEDUSA correction: median error < 8 cm (measured attitude) and
//!   < 10 cm (set points), never outside the arena; without correction the twin drifts
//!   (reported).
//! - MEDUSA plus a tracking pose that drops out for two minutes mid-flight: the twin stays
//!   within bounds during the dropout.

use std::process::Command;

use serde_json::Value;

fn sync_eval(args: &[&str]) -> Value {
    let out = Command::new(env!("CARGO_BIN_EXE_twinswarm"))
        .args(["localize", "--sync-eval", "--json"])
        .args(args)
        .output()
        .expect("run twinswarm");
    assert!(out.status.success(), "exit {:?}: {}", out.status, String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).expect("JSON on stdout")
}

fn run<'a>(report: &'a Value, label: &str) -> &'a Value {
    report["runs"]
        .as_array()
        .expect("runs")
        .iter()
        .find(|r| r["variant"]["label"].as_str().is_some_and(|l| l.starts_with(label)))
        .unwrap_or_else(|| panic!("no run {label:?} in {report}"))
}

fn cm(r: &Value, what: &str, q: &str) -> f64 {
    r[what][q].as_f64().unwrap_or_else(|| panic!("{what}.{q} in {r}"))
}

#[test]
fn ten_minutes_of_lossy_telemetry_keep_the_twin_within_10_cm() {
    let report = sync_eval(&["--minutes", "10"]);
    for label in ["MEDUSA", "MEDUSA, set-point attitude"] {
        let r = run(&report, label);
        println!(
            "{label}: median {:.1} cm, p95 {:.1} cm, max {:.1} cm, outside {} steps, {} samples; {}",
            cm(r, "error_cm", "median"),
            cm(r, "error_cm", "p95"),
            cm(r, "error_cm", "max"),
            r["steps_outside_arena"],
            r["samples"],
            r["sync"]
        );
        assert!(r["samples"].as_u64().unwrap() > 11_000, "{r}");
        // 6.1 cm and 7.9 cm on the measured link with the firmware's sonar schedule and the 5/s
        // pull (docs/accuracy.md); a twin flying the set-points its real copter sends, not the
        // attitude it measured, drifts more between corrections.
        let bound = if label == "MEDUSA" { 8.0 } else { 10.0 };
        assert!(cm(r, "error_cm", "median") < bound, "{label}: {r}");
        assert_eq!(r["steps_outside_arena"], 0, "{label}: {r}");
        assert!(r["twin_crash"].is_null(), "{label}: {r}");
        let lost = r["telemetry_lost"].as_f64().unwrap() / (r["telemetry_sent"].as_f64().unwrap() + 1.0);
        assert!((0.03..0.07).contains(&lost), "5 % loss, got {lost}");
    }
    let off = run(&report, "correction off");
    println!(
        "correction off: median {:.1} cm, p95 {:.1} cm, crash {}",
        cm(off, "error_cm", "median"),
        cm(off, "error_cm", "p95"),
        off["twin_crash"]
    );
    assert!(
        cm(off, "error_cm", "median") > 5.0 * cm(run(&report, "MEDUSA"), "error_cm", "median"),
        "the twin drifts without correction"
    );
}

#[test]
fn the_twin_stays_within_bounds_while_tracking_drops_out() {
    let report = sync_eval(&["--minutes", "4", "--tracking-dropout", "60,180"]);
    let r = run(&report, "MEDUSA + tracking");
    println!("{r}");
    let during = cm(r, "error_in_dropout_cm", "max");
    assert!(r["sync"]["tracking_updates"].as_u64().unwrap() > 1000, "{r}");
    // 34 cm with the 5/s pull and the real FINken's 1.5° AHRS noise (21 cm with the 0.5° of
    // before, docs/accuracy.md): MEDUSA alone carries the twin for two minutes.
    assert!(during < 40.0, "max {during} cm during the dropout");
    assert!(cm(r, "error_cm", "median") < 10.0, "{r}");
    assert_eq!(r["steps_outside_arena"], 0, "{r}");
}
