//! `twinswarm scene` writes the benchmarks' experiment as a scene file a user can run, and a
//! run of a large swarm prints aggregates, not a row per copter.

use std::path::PathBuf;
use std::process::Command;

fn twinswarm(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_twinswarm")).args(args).output().expect("run twinswarm");
    (out.status.success(), String::from_utf8_lossy(&out.stdout).into(), String::from_utf8_lossy(&out.stderr).into())
}

fn scratch_file(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("twinswarm-{name}-{}.toml", std::process::id()))
}

#[test]
fn a_generated_dense_swarm_runs_and_its_summary_scales() {
    let (ok, toml, err) = twinswarm(&["scene", "dense", "--n", "60", "--seed", "4"]);
    assert!(ok, "{err}");
    let (spec, world) = sim_core::scene::load("generated", &toml).expect("the generated scene loads");
    assert_eq!(world.copters.len(), 60);
    assert_eq!(spec.boxes.len(), 10, "ten pillars");
    assert_eq!(world.params.seed, 4);
    assert!(world.copters.iter().all(|c| c.start_pos_m.z < 0.05), "dense starts on the floor");

    let path = scratch_file("dense60");
    std::fs::write(&path, &toml).unwrap();
    let (ok, out, err) =
        twinswarm(&["run", path.to_str().unwrap(), "--no-bus", "--no-log", "--duration", "20", "--threads", "2"]);
    let _ = std::fs::remove_file(&path);
    assert!(ok, "{err}");
    assert!(out.contains("60 copters"), "{out}");
    assert!(out.contains("copters: 60 flew"), "aggregates: {out}");
    assert!(out.contains("crashes: ") && out.contains("worst |dz|"), "{out}");
    assert!(out.lines().count() < 20, "no row per copter: {out}");
    // The worst few are named (crashes, height errors), not all 60.
    let named = (0..60).filter(|k| out.contains(&format!("c{k} "))).count();
    assert!(named <= 15, "{named} copters named: {out}");
}

#[test]
fn bad_scene_arguments_are_refused_with_a_reason() {
    let (ok, _, err) = twinswarm(&["scene", "dense", "--n", "0"]);
    assert!(!ok && err.contains("--n"), "{err}");
    let (ok, _, err) = twinswarm(&["scene", "dense", "--n", "4", "--spacing=0"]);
    assert!(!ok && err.contains("--spacing"), "{err}");
}
