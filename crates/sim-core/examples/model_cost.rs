//! What the model costs: real-time factor of `scene::cruising_swarm` (Wall-Avoid, 0.3 m/s,
//! sensors on, one thread), with parts of the model switched off, on the CPU time of this
//! thread. Only sim-core, so that it also builds at older commits (copy this file there).
//!
//! ```text
//! cargo run --release -p sim-core --example model_cost -- N SIM_SECONDS [dense] [takeoff] [spacing=S] [threads=T] [ideal] [no-airflow] [no-battery] [no-crosstalk] [no-floor-echo]
//! ```
//!
//! `takeoff`: the copters start on the floor (1.5 m grid) instead of in the air (2 m grid).
//! `spacing=S`: an S m grid instead.
//! `threads=T`: step on T threads (then `rtf_wall`, the wall clock's, is the figure to read).
//! `dense`: `scene::dense_swarm` (1.5 m grid, 10 pillars, Wall-Avoid at 1 m; with `takeoff`
//! from the floor).

use sim_core::{scene, step};

/// CPU time of this thread, s (Linux schedstat; the wall clock elsewhere).
fn cpu_s() -> f64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|t| t.split_whitespace().next()?.parse::<f64>().ok())
        .map(|ns| ns * 1e-9)
        .unwrap_or_else(|| std::time::UNIX_EPOCH.elapsed().map_or(0.0, |d| d.as_secs_f64()))
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let n: usize = args.first().and_then(|s| s.parse().ok()).unwrap_or(100);
    let seconds: f64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(20.0);
    let has = |flag: &str| args.iter().any(|a| a == flag);
    let mut spec = scene::cruising_swarm(n, 1);
    let spacing: Option<f32> = args.iter().find_map(|a| a.strip_prefix("spacing=")?.parse().ok());
    if let Some(spacing) = spacing {
        let grid = scene::grid_swarm(n, spacing, 0.8, true);
        spec.arena = grid.arena;
        for (c, g) in spec.copters.iter_mut().zip(grid.copters) {
            c.start.pos_m = g.start.pos_m;
        }
    }
    if has("dense") {
        spec = scene::dense_swarm(n, spacing.unwrap_or(1.5), has("takeoff"), 10, 0);
    } else if has("takeoff") {
        let grid = scene::grid_swarm(n, spacing.unwrap_or(1.5), 0.8, true);
        spec.arena = grid.arena;
        for (c, g) in spec.copters.iter_mut().zip(grid.copters) {
            c.start.pos_m = g.start.pos_m;
            c.start.z_m = None;
        }
    }
    // FLAGS BEGIN (delete this block to build at commits before the model's switches)
    spec.sensors.estimator.ideal = has("ideal");
    spec.sensors.crosstalk.enabled = !has("no-crosstalk");
    spec.sensors.sonar.floor_echo = !has("no-floor-echo");
    spec.airflow.downwash = !has("no-airflow");
    spec.airflow.ground_effect = !has("no-airflow");
    if has("no-battery") {
        let mut af = sim_core::AirframeSpec::default();
        af.battery.enabled = false;
        spec.airframes.insert("nobat".into(), af);
        for c in &mut spec.copters {
            c.airframe = scene::AirframeRef::Named("nobat".into());
        }
    }
    // FLAGS END
    spec.sim.threads = args.iter().find_map(|a| a.strip_prefix("threads=")?.parse().ok()).unwrap_or(1);
    let world = scene::compile(&spec).expect("scene compiles");
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let ticks = (seconds / world.params.control_dt_s).round() as u64;
    let (t0, wall) = (cpu_s(), std::time::Instant::now());
    for _ in 0..ticks {
        step(&world, &mut state, &inputs);
    }
    let (cpu, wall) = (cpu_s() - t0, wall.elapsed().as_secs_f64());
    let crashed = state.copters.iter().filter(|c| c.crash.is_some()).count();
    let mut causes = std::collections::BTreeMap::<&str, usize>::new();
    for c in state.copters.iter().filter_map(|c| c.crash) {
        let name = match c {
            sim_core::CrashCause::Wall => "wall",
            sim_core::CrashCause::Ceiling => "ceiling",
            sim_core::CrashCause::Box { .. } => "box",
            sim_core::CrashCause::Floor { .. } => "floor",
            sim_core::CrashCause::Copter { .. } => "copter",
            sim_core::CrashCause::Tilt { .. } => "tilt",
        };
        *causes.entry(name).or_default() += 1;
    }
    eprintln!("crash causes: {causes:?}");
    // FNV-1a over every copter's final motion bits: equal digests, equal trajectories.
    let mut digest: u64 = 0xcbf2_9ce4_8422_2325;
    for c in &state.copters {
        let m = &c.motion;
        let v = [m.pos_m.to_array(), m.vel_m_s.to_array(), m.angvel_rad_s.to_array()];
        for x in v.iter().flatten().chain(&m.rot.to_array()) {
            digest = (digest ^ u64::from(x.to_bits())).wrapping_mul(0x100_0000_01b3);
        }
    }
    println!(
        "{{\"N\": {n}, \"sim_s\": {seconds}, \"cpu_s\": {cpu:.3}, \"rtf_cpu\": {:.2}, \"rtf_wall\": {:.2}, \"crashed\": {crashed}, \"digest\": \"{digest:016x}\", \"flags\": {:?}}}",
        seconds / cpu,
        seconds / wall,
        args.iter().skip(2).collect::<Vec<_>>()
    );
}
