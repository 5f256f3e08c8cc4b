//! A log that cannot be written, as on a full disk: a file-size limit (`prlimit --fsize`, the
//! kernel's SIGXFSZ and `EFBIG`) cuts the log mid-run. The run stops cleanly or goes on
//! without logging, as `--on-log-error` says; the exit code and the message say what
//! happened; and the file holds a log that `twinswarm log recover` makes complete.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn fresh_dir(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("twinswarm-{test}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The embedded lab for 60 s, logging to `log` under a 400 kB file-size limit.
fn run_limited(log: &Path, on_error: &str) -> (Output, serde_json::Value) {
    let out = Command::new("prlimit")
        .arg("--fsize=400000")
        .arg("--")
        .arg(env!("CARGO_BIN_EXE_twinswarm"))
        .args(["run", "--no-bus", "--duration", "60", "--json", "--on-log-error", on_error, "--log"])
        .arg(log)
        .output()
        .expect("prlimit (util-linux) runs twinswarm");
    let json = serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!("summary JSON ({e}): {}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
    });
    (out, json)
}

fn twinswarm(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twinswarm")).args(args).output().expect("run twinswarm")
}

#[test]
fn a_full_disk_stops_the_run_cleanly_and_leaves_a_recoverable_log() {
    let dir = fresh_dir("full-disk-stop");
    let log = dir.join("run.mcap");
    let (out, json) = run_limited(&log, "stop");
    let stderr = String::from_utf8_lossy(&out.stderr);
    // Not killed by SIGXFSZ (exit 153): a runtime failure, said in words.
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("logging failed at control step"), "{stderr}");
    assert!(stderr.contains("the run stopped at control step"), "{stderr}");
    assert!(stderr.contains("File too large"), "{stderr}");
    assert!(stderr.contains("twinswarm log recover"), "{stderr}");
    let steps = json["control_steps"].as_u64().unwrap();
    assert!((20..1200).contains(&steps), "stopped early, at step {steps}");
    assert!(json["log_error"].as_str().unwrap().contains("File too large"));

    let fixed = dir.join("fixed.mcap");
    let rec = twinswarm(&["log", "recover", log.to_str().unwrap(), fixed.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&rec.stdout);
    assert!(rec.status.success(), "{text}{}", String::from_utf8_lossy(&rec.stderr));
    assert!(text.contains("the input was truncated"), "{text}");
    // What is rescued: every copter's state on every step from the first to within two
    // seconds of the stop (the chunk being written when the disk filled, 1 s of log, and the
    // one being filled are lost), and nothing after the stop.
    let file = bridge::log::LogFile::open(&fixed).expect("the recovered log opens");
    let states = file.messages::<bridge::log::proto::CopterState>("/copters/state").expect("states");
    let copters = 2; // the embedded lab
    let ticks: std::collections::BTreeSet<u64> = states.iter().map(|(_, s)| s.tick).collect();
    let (first, last) = (*ticks.first().expect("states rescued"), *ticks.last().unwrap());
    assert_eq!(first, 1, "from the first step");
    assert_eq!(ticks.len() as u64, last, "no step missing up to the last rescued");
    assert_eq!(states.len() as u64, copters * last, "every copter on every step");
    let (stop_s, rescued_s) = (steps as f64 * 0.05, last as f64 * 0.05);
    assert!(rescued_s <= stop_s && rescued_s >= stop_s - 2.0, "{rescued_s} s rescued of a run stopped at {stop_s} s");
    let info = twinswarm(&["log", "info", fixed.to_str().unwrap()]);
    let info = String::from_utf8_lossy(&info.stdout);
    assert!(info.contains(&format!(" to {rescued_s:.2} s simulated")), "{info}");
    eprintln!("full disk: stopped at {stop_s:.2} s, {rescued_s:.2} s of state rescued ({} messages)", states.len());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_full_disk_with_continue_flies_the_whole_run_without_a_log_and_says_so() {
    let dir = fresh_dir("full-disk-continue");
    let log = dir.join("run.mcap");
    let (out, json) = run_limited(&log, "continue");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("the run went on without a log from control step"), "{stderr}");
    assert_eq!(json["control_steps"].as_u64(), Some(1200), "the whole minute was flown");
    assert!(std::fs::metadata(&log).unwrap().len() <= 400_000);
    let _ = std::fs::remove_dir_all(&dir);
}
