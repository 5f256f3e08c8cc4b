//! `twinswarm` with no arguments is `twinswarm run` with `run`'s defaults: what
//! `cargo run --release` does on a fresh machine (the embedded lab, a log under `runs/`, the
//! bus on the default loopback endpoint).
//!
//! The defaults are checked on a free port (`run --listen`), so no test depends on the default
//! port being free. Only the no-argument run itself must take the default endpoint: when
//! another process holds that port it fails under `CI=true` (CI's machine must have it free),
//! and elsewhere skips, saying so on stderr.

use std::io::Write;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use bridge::zenoh_net::node::DEFAULT_LISTEN;

/// A fresh, empty working directory for one test.
fn fresh_dir(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("twinswarm-{test}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn twinswarm(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twinswarm")).args(args).current_dir(dir).output().expect("run twinswarm")
}

/// What a run with `run`'s defaults prints and leaves behind in `dir`.
fn assert_flew_the_embedded_lab_with_runs_defaults(out: &Output, dir: &Path) {
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "exit {:?}: {}{stdout}", out.status, String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("<embedded finken_lab.toml>"), "{stdout}");
    assert!(stdout.contains("1800 control steps") && stdout.contains("crashes: none"), "{stdout}");
    assert!(stdout.contains("bus: zenoh, prefix twinswarm/lab"), "{stdout}");
    let logs: Vec<_> = std::fs::read_dir(dir.join("runs")).expect("runs/").flatten().collect();
    assert_eq!(logs.len(), 1, "one log under runs/");
}

/// The default listen address as a socket address (`127.0.0.1:7447`).
fn default_addr() -> &'static str {
    DEFAULT_LISTEN.strip_prefix("tcp/").expect("DEFAULT_LISTEN is a TCP endpoint")
}

/// Why the default endpoint cannot be used right now, if it cannot.
fn default_port_taken() -> Option<std::io::Error> {
    TcpListener::bind(default_addr()).err()
}

/// A notice straight to stderr (`std::io::stderr()` bypasses libtest's capture, which would
/// hide an `eprintln!` of a passing test); under `CI=true` a failure instead.
fn skip_notice(test: &str, why: &str) {
    let ci = std::env::var("CI").is_ok_and(|v| v.eq_ignore_ascii_case("true") || v == "1");
    assert!(!ci, "{test}: {why}; under CI=true the default endpoint must be free");
    let _ = std::io::stderr().write_all(format!("\nSKIPPED {test}: {why}\n").as_bytes());
}

#[test]
fn run_flies_the_embedded_lab_with_its_defaults() {
    let dir = fresh_dir("defaults-run");
    let port = TcpListener::bind("127.0.0.1:0").and_then(|l| l.local_addr()).expect("a free loopback port").port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let out = twinswarm(&dir, &["run", "--listen", &endpoint]);
    assert_flew_the_embedded_lab_with_runs_defaults(&out, &dir);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn no_arguments_fly_the_embedded_lab_with_runs_defaults() {
    const TEST: &str = "no_arguments_fly_the_embedded_lab_with_runs_defaults";
    if let Some(e) = default_port_taken() {
        skip_notice(TEST, &format!("the default endpoint {DEFAULT_LISTEN} is taken ({e})"));
        return;
    }
    let dir = fresh_dir("default-run");
    let out = twinswarm(&dir, &[]);
    // Taken between the check and the run: still a skip, not a failure.
    if !out.status.success()
        && String::from_utf8_lossy(&out.stderr).contains("cannot start the Zenoh node")
        && let Some(e) = default_port_taken()
    {
        skip_notice(TEST, &format!("the default endpoint {DEFAULT_LISTEN} was taken during the run ({e})"));
        let _ = std::fs::remove_dir_all(&dir);
        return;
    }
    assert_flew_the_embedded_lab_with_runs_defaults(&out, &dir);
    let _ = std::fs::remove_dir_all(&dir);
}
