//! `twinswarm` with no arguments is `twinswarm run` with `run`'s defaults: what
//! `cargo run --release` does on a fresh machine (the embedded lab, a log under `runs/`, the
//! bus on the default loopback endpoint).

use std::process::Command;

#[test]
fn no_arguments_fly_the_embedded_lab_with_runs_defaults() {
    let dir = std::env::temp_dir().join(format!("twinswarm-default-run-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_twinswarm")).current_dir(&dir).output().expect("run twinswarm");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "exit {:?}: {}{stdout}", out.status, String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("<embedded finken_lab.toml>"), "{stdout}");
    assert!(stdout.contains("1800 control steps") && stdout.contains("crashes: none"), "{stdout}");
    assert!(stdout.contains("bus: zenoh, prefix twinswarm/lab"), "{stdout}");
    let logs: Vec<_> = std::fs::read_dir(dir.join("runs")).expect("runs/").flatten().collect();
    assert_eq!(logs.len(), 1, "one log under runs/");
    let _ = std::fs::remove_dir_all(&dir);
}
