//! `twinswarm fit` on the real FINken flights of 16 Dec 2015 (`shared/data/finken_flights`):
//! from the state a twin synced to the copter has at each start (its own data up to then), the
//! identified model predicts within issue 48's bound (median 0.11 m at 1 s, 0.22 m at 2 s,
//! leave-one-flight-out) and better than the current model, constant velocity and staying put,
//! with a delay and a damping inside their grids; and the metric can fail: the state the fit
//! took before (a line through the last half second) misses the bound, and the same log with its
//! roll flipped or its attitude shifted in time predicts worse. Skips loudly where the shared
//! data is absent, fails under `CI=true`.

#[path = "../../bridge/tests/common/mod.rs"]
mod common;

use std::path::Path;
use std::process::Command;

use bridge::paparazzi::flightlog::FlightLog;
use bridge::realflight::Series;
use bridge::realflight::fit::{FitOptions, FitReport, FlightInput, Mapping};

const LINKED: &str = "finken_flights/report_2015-12-16/15_12_16__13_55_00.data";

fn twinswarm(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_twinswarm"))
        .args(args)
        .current_dir(std::env::temp_dir())
        .output()
        .expect("run twinswarm")
}

/// A model's (median, p95) at horizon index `h` (0: 1 s).
fn at(r: &serde_json::Value, model: &str, h: usize) -> (f64, f64) {
    let m = r["models"].as_array().and_then(|ms| ms.iter().find(|m| m["name"] == model)).expect(model);
    let s = &m["horizons"][h];
    (s["median_m"].as_f64().expect("median"), s["p95_m"].as_f64().expect("p95"))
}

/// Issue 48's bound on the identified model's median error, m, at 1 and 2 s.
const BOUND_M: [f64; 2] = [0.11, 0.22];

fn fit_json(data: &Path, extra: &[&str]) -> serde_json::Value {
    let mut args = vec!["fit", data.to_str().unwrap_or_default(), "--json"];
    args.extend_from_slice(extra);
    let out = twinswarm(&args);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).expect("JSON")
}

#[test]
fn the_16_dec_flights_identify_a_model_that_predicts_within_the_bound_from_a_synced_state() {
    let shared = shared_or_skip!();
    let data = shared.join(LINKED);
    let r = fit_json(&data, &[]);
    assert_eq!(r["flights"].as_array().map(Vec::len), Some(6), "{}", r["skipped"]);
    assert_eq!((&r["leave_one_out"], &r["models"][0]["horizons"][0]["horizon_s"]), (&true.into(), &1.0.into()));
    // Issue 48: at most 0.11 m at 1 s and 0.22 m at 2 s (median), the baselines beside it.
    for (h, bound) in BOUND_M.iter().enumerate() {
        let (identified, n) = (at(&r, "identified", h), r["models"][1]["horizons"][h]["n"].as_u64());
        assert!(identified.0 <= *bound && n > Some(90), "{h}: {identified:?} over {n:?}: {}", r["models"]);
    }
    assert_eq!(r["options"]["state"], "synced");
    let (identified, cv, stay) = (at(&r, "identified", 0), at(&r, "constant velocity", 0), at(&r, "stay put", 0));
    assert!(identified.0 < cv.0 && identified.0 < stay.0, "1 s medians: {identified:?} {cv:?} {stay:?}");
    assert!(identified.1 < cv.1 && identified.1 < stay.1, "1 s p95: {identified:?} {cv:?} {stay:?}");
    // Better than Twinswarm's current model, from the same state, at every horizon; and than
    // itself on the floor-levelled attitude without the trim it learns.
    for h in 0..3 {
        assert!(at(&r, "identified", h).0 < at(&r, "current", h).0, "{h}: {}", r["models"]);
        assert!(at(&r, "identified", h).0 < at(&r, "identified, no trim", h).0, "{h}: {}", r["models"]);
    }
    // The attitude acts on the position after a delay, and the damping is found inside its grid
    // (0-0.6 /s), on all flights and on each fold.
    let param = |p: &serde_json::Value, key: &str| p[key].as_f64().expect(key);
    let folds: Vec<&serde_json::Value> = r["flights"].as_array().into_iter().flatten().map(|f| &f["params"]).collect();
    for p in folds.iter().copied().chain([&r["all_flights"]]) {
        assert!((0.2..=0.5).contains(&param(p, "delay_s")), "{p}");
        assert!((0.1..=0.4).contains(&param(p, "damping_per_s")), "{p}");
    }
    // With the state from a window centred on each start (peeking half a second ahead), every
    // model knows the velocity better, and the identified one still leads.
    let c = fit_json(&data, &["--centred-state"]);
    assert_eq!(c["options"]["state"], "centred");
    assert!(
        at(&c, "constant velocity", 0).0 < cv.0 && at(&c, "current", 0).0 < at(&r, "current", 0).0,
        "{}",
        c["models"]
    );
    assert!(at(&c, "identified", 0).0 < at(&r, "identified", 0).0, "{}", c["models"]);
    assert!(at(&c, "identified", 0).0 < at(&c, "constant velocity", 0).0, "{}", c["models"]);
}

/// The bound is one the estimates the fit had before fail: the line through the track's last
/// half second (its state a quarter second old), and the attitude levelled by the floor.
#[test]
fn the_bound_fails_from_the_line_state_or_the_floor_levelled_attitude() {
    let shared = shared_or_skip!();
    let data = shared.join(LINKED);
    let misses = |r: &serde_json::Value| (0..2).any(|h| at(r, "identified", h).0 > BOUND_M[h]);
    let line = fit_json(&data, &["--state", "line"]);
    assert_eq!(line["options"]["state"], "line");
    assert!(misses(&line), "the line state: {}", line["models"]);
    let levelled = fit_json(&data, &["--level-from-floor"]);
    assert!(misses(&levelled), "levelled by the floor: {}", levelled["models"]);
}

/// The series of the linked log's aircraft, and its flights as `twinswarm fit` takes them.
fn linked(shared: &Path) -> (Series, Vec<bridge::realflight::Flight>) {
    let log = FlightLog::open(&shared.join(LINKED)).expect("the linked log opens");
    let series = Series::of(&log, 5);
    let flights = bridge::realflight::flights(&series);
    assert_eq!(flights.len(), 6, "{flights:?}");
    (series, flights)
}

fn fit(series: &Series, flights: &[bridge::realflight::Flight], opts: &FitOptions) -> FitReport {
    let inputs: Vec<FlightInput<'_>> = flights
        .iter()
        .enumerate()
        .map(|(k, f)| FlightInput { label: format!("flight {}", k + 1), series, flight: *f })
        .collect();
    bridge::realflight::fit::identify(&inputs, opts).expect("identifies")
}

fn median_1s(r: &FitReport, model: &str) -> f64 {
    r.models.iter().find(|m| m.name == model).expect(model).horizons[0].median_m
}

#[test]
fn the_identified_models_error_rises_on_a_flipped_roll_or_a_shifted_attitude() {
    let shared = shared_or_skip!();
    let (series, flights) = linked(&shared);
    let opts = FitOptions::default();
    let real = fit(&series, &flights, &opts);
    let (good, mapping) = (median_1s(&real, "identified"), real.all_flights.mapping);
    assert_eq!(mapping, Mapping::TWINSWARM, "the data's signs are Twinswarm's: {:?}", real.all_flights);
    // The roll's sign flipped, the signs held to what the real data showed: worse, worse than
    // staying put.
    let mut flipped = series.clone();
    for s in flipped.attitude.iter_mut().chain(flipped.sensors.iter_mut()) {
        if let Some(r) = s.rpy_rad.as_mut() {
            r[0] = -r[0];
        }
    }
    let pinned = fit(&flipped, &flights, &FitOptions { mapping: Some(mapping), ..opts.clone() });
    let wrong = median_1s(&pinned, "identified");
    assert!(wrong > 1.3 * good, "flipped roll: {wrong} m against {good} m");
    assert!(wrong > median_1s(&pinned, "stay put"), "flipped roll: {wrong} m");
    // Left to fit the signs, it finds the roll's flipped, and predicts as before.
    let free = fit(&flipped, &flights, &opts);
    assert_eq!(
        free.all_flights.mapping,
        Mapping { roll_to_y: -mapping.roll_to_y, ..mapping },
        "{:?}",
        free.all_flights
    );
    assert!((median_1s(&free, "identified") - good).abs() < 0.01, "{}", median_1s(&free, "identified"));
    // The attitude recorded 0.8 s late: no delay in the grid (0-0.6 s) undoes it.
    let mut late = series.clone();
    for s in &mut late.attitude {
        s.t_s += 0.8;
    }
    let shifted = median_1s(&fit(&late, &flights, &opts), "identified");
    assert!(shifted > 1.3 * good, "attitude 0.8 s late: {shifted} m against {good} m");
}

#[test]
fn a_missing_log_or_an_aircraft_without_flights_is_an_error_that_names_the_file() {
    let out = twinswarm(&["fit", "/nonexistent/nowhere.data"]);
    assert_eq!(out.status.code(), Some(2), "{}", String::from_utf8_lossy(&out.stderr));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("nowhere.log does not exist") || err.contains("nowhere.data does not exist"), "{err}");
    let shared = shared_or_skip!();
    let data = shared.join(LINKED);
    let out = twinswarm(&["fit", data.to_str().unwrap_or_default(), "--ac-id", "99"]);
    assert_eq!(out.status.code(), Some(2), "{}", String::from_utf8_lossy(&out.stderr));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("15_12_16__13_55_00.data: aircraft 99: no flight"), "{err}");
}
