//! Real-time factor of a swarm: N FINkens flying Wall-Avoid on their full model (4 sonar
//! cones with cross-talk, IR, IMU, estimators, battery, downwash), 50 ms control steps of
//! 10 × 5 ms physics substeps. Prints one JSON line per run, in the spirit of
//! `peer_pybullet.py bench`, so `scripts/bench-peers.sh` can put them side by side.
//!
//! Scenes (`--scene`):
//! - `cruise` (default): `scene::cruising_swarm`, one copter per 2 m × 2 m cell, starting in
//!   the air, each heading its own way at 0.3 m/s; 1 s of warm-up is not measured.
//! - `dense`: `scene::dense_swarm`, the experiment: a 1.5 m grid taking off from the floor,
//!   10 pillars among the copters, Wall-Avoid at 1 m; measured from the floor (tick 0), so
//!   take-off, crowding and the crashes piling up all count.
//! - `dense-air`: the same, starting in the air at 1 m.
//!
//! Each run also reports the process's resident memory after building the world and at the
//! end (`rss_mib`), and the growth per copter (`bytes_per_copter`: one run per process gives a
//! clean figure).
//!
//! ```text
//! cargo bench -p twinswarm --bench swarm_rt -- --n 100 1000 --threads 1 2 [--scene dense] [--log] [--sim-seconds S]
//! cargo bench -p twinswarm --bench swarm_rt -- --n 100 1000 --log-cost ROUNDS [--zstd-level L] [--chunk-kib K] [--log-rate HZ] [--log-unchanged S]
//! cargo bench -p twinswarm --bench swarm_rt -- --plot docs/img/scaling.png
//! ```
//!
//! `rtf_wallclock` is simulated time over elapsed time; `rtf_cpu` (one thread only) is
//! simulated time over the CPU time of the stepping thread, which a busy machine inflates
//! less (the peer script reports the same two numbers).

use std::path::{Path, PathBuf};
use std::time::Instant;

use plotters::prelude::*;
use sim_core::{World, scene, step};

/// One measured run.
#[derive(Debug)]
struct Run {
    scene: Scene,
    n: usize,
    threads: usize,
    log: bool,
    sim_s: f64,
    wall_s: f64,
    cpu_s: Option<f64>,
    crashed: usize,
    /// CPU time of the log writer thread, s (logging runs, Linux).
    writer_cpu_s: Option<f64>,
    /// Size of the log file, bytes (logging runs).
    log_bytes: u64,
    /// Copter samples the log left out as unchanged.
    held: u64,
    /// Resident memory before the world was built, after, and at the end, bytes.
    rss: [u64; 3],
}

/// Which swarm a run flies.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Scene {
    Cruise,
    Dense,
    DenseAir,
}

impl Scene {
    fn name(self) -> &'static str {
        match self {
            Scene::Cruise => "cruise",
            Scene::Dense => "dense_takeoff",
            Scene::DenseAir => "dense_air",
        }
    }
}

/// Resident memory of this process, bytes (Linux; 0 elsewhere).
fn rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("VmRSS:"))?.split_whitespace().nth(1)?.parse::<u64>().ok())
        .map_or(0, |kib| kib * 1024)
}

impl Run {
    fn us_per_copter_step(&self) -> f64 {
        let steps = self.sim_s / 0.05;
        1e6 * self.wall_s / (steps * self.n as f64)
    }

    fn json(&self) -> String {
        let steps = self.sim_s / 0.05;
        let cpu = |v: Option<f64>| v.map_or("null".to_string(), |v| format!("{v:.4}"));
        format!(
            "{{\"sim\": \"twinswarm\", \"scenario\": \"{}\", \"N\": {}, \"threads\": {}, \"log\": {}, \
             \"sim_s\": {:.2}, \"wall_clock_s\": {:.4}, \"cpu_s\": {}, \"rtf_wallclock\": {:.3}, \"rtf_cpu\": {}, \
             \"ms_per_step\": {:.4}, \"us_per_copter_step\": {:.4}, \"crashed\": {}, \"rss_mib\": [{:.1}, {:.1}], \
             \"bytes_per_copter\": {}}}",
            self.scene.name(),
            self.n,
            self.threads,
            self.log,
            self.sim_s,
            self.wall_s,
            cpu(self.cpu_s),
            self.sim_s / self.wall_s,
            cpu(self.cpu_s.map(|c| self.sim_s / c)),
            1e3 * self.wall_s / steps,
            self.us_per_copter_step(),
            self.crashed,
            self.rss[1] as f64 / (1024.0 * 1024.0),
            self.rss[2] as f64 / (1024.0 * 1024.0),
            self.rss[2].saturating_sub(self.rss[0]) / self.n.max(1) as u64,
        )
    }
}

/// CPU time of the calling thread, s (Linux).
fn thread_cpu_s() -> Option<f64> {
    bridge::log::thread_cpu_ns().map(|ns| ns as f64 * 1e-9)
}

/// The swarm of `scene` (see the module docs).
fn world(scene: Scene, n: usize, threads: usize) -> World {
    let mut spec = match scene {
        Scene::Cruise => scene::cruising_swarm(n, threads),
        Scene::Dense => scene::dense_swarm(n, 1.5, true, 10, 1),
        Scene::DenseAir => scene::dense_swarm(n, 1.5, false, 10, 1),
    };
    spec.sim.threads = threads;
    match scene::compile(&spec) {
        Ok(w) => w,
        Err(e) => panic!("{e}"),
    }
}

/// The logger's options: the defaults, or `--zstd-level L`, `--chunk-kib K`, `--log-rate HZ`
/// and `--log-unchanged S`.
fn log_options() -> bridge::log::LogOptions {
    let mut o = bridge::log::LogOptions::default();
    let args: Vec<String> = std::env::args().collect();
    let value = |flag: &str| args.iter().position(|a| a == flag).and_then(|i| args.get(i + 1)?.parse().ok());
    if let Some(l) = value("--zstd-level") {
        o.zstd_level = l;
    }
    if let Some(kib) = value("--chunk-kib") {
        o.chunk_size = kib as usize * 1024;
    }
    let unchanged = args.iter().position(|a| a == "--log-unchanged").and_then(|i| args.get(i + 1)?.parse::<f64>().ok());
    if let Some(s) = unchanged {
        o.unchanged_every_s = s;
    }
    let rate = args.iter().position(|a| a == "--log-rate").and_then(|i| args.get(i + 1)?.parse::<f64>().ok());
    if let Some(hz) = rate {
        o.every_ticks = bridge::log::LogOptions::every_ticks_for_rate(hz, 0.05).unwrap_or(1);
    }
    o
}

fn run(scene: Scene, n: usize, threads: usize, log: bool, sim_s: f64, dir: &Path) -> Run {
    let rss0 = rss_bytes();
    let world = world(scene, n, threads);
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let rss1 = rss_bytes();
    // The cruising swarm warms up (1 s: buffers grow, the thread pool starts); the experiments
    // are measured from the floor.
    if scene == Scene::Cruise {
        for _ in 0..20 {
            step(&world, &mut state, &inputs);
        }
    }
    let steps = (sim_s / world.params.control_dt_s).round().max(1.0) as usize;
    let mut logger = log.then(|| {
        let path = dir.join(format!("swarm_rt_{n}_{threads}.mcap"));
        match bridge::log::Logger::with_options(&path, &world, "", bridge::log::LogMeta::default(), log_options()) {
            Ok(l) => l,
            Err(e) => panic!("{e}"),
        }
    });
    let cpu0 = thread_cpu_s();
    let t0 = Instant::now();
    for _ in 0..steps {
        let report = step(&world, &mut state, &inputs);
        if let Some(l) = logger.as_mut()
            && let Err(e) = l.log_step(&world, &state, &inputs, &report)
        {
            panic!("{e}");
        }
    }
    let cpu_s = match (threads, cpu0, thread_cpu_s()) {
        (1, Some(a), Some(b)) => Some(b - a),
        _ => None,
    };
    // The run ends when everything is on disk: draining the writer's queue and the summary
    // section count against logging.
    let (mut writer_cpu_s, mut log_bytes, mut held) = (None, 0, 0);
    if let Some(l) = logger {
        match l.finish() {
            Ok(stats) => {
                writer_cpu_s = stats.writer_cpu_s;
                log_bytes = std::fs::metadata(&stats.path).map_or(0, |m| m.len());
                held = stats.held_samples;
                let _ = std::fs::remove_file(&stats.path);
            }
            Err(e) => panic!("{e}"),
        }
    }
    let wall_s = t0.elapsed().as_secs_f64();
    let crashed = state.copters.iter().filter(|c| c.crash.is_some()).count();
    let sim_s = steps as f64 * world.params.control_dt_s;
    let rss = [rss0, rss1, rss_bytes()];
    Run { scene, n, threads, log, sim_s, wall_s, cpu_s, crashed, writer_cpu_s, log_bytes, held, rss }
}

/// The cost of logging at `n` copters: `rounds` pairs of runs, logging off then on; the
/// overhead is the median of the pairs' ratios, the other numbers are medians over the runs.
fn log_cost(scene: Scene, n: usize, threads: usize, rounds: usize, sim_s: f64, dir: &Path) -> String {
    let (mut off, mut on) = (Vec::new(), Vec::new());
    for _ in 0..rounds {
        off.push(run(scene, n, threads, false, sim_s, dir));
        on.push(run(scene, n, threads, true, sim_s, dir));
    }
    let steps = |r: &Run| r.sim_s / 0.05;
    let median = |runs: &[Run], f: &dyn Fn(&Run) -> Option<f64>| {
        let mut v: Vec<f64> = runs.iter().filter_map(f).collect();
        v.sort_by(f64::total_cmp);
        if v.is_empty() { f64::NAN } else { v[v.len() / 2] }
    };
    let wall_off = median(&off, &|r| Some(1e3 * r.wall_s / steps(r)));
    let wall_on = median(&on, &|r| Some(1e3 * r.wall_s / steps(r)));
    let cpu_off = median(&off, &|r| r.cpu_s.map(|c| 1e3 * c / steps(r)));
    let cpu_on = median(&on, &|r| r.cpu_s.map(|c| 1e3 * c / steps(r)));
    let writer = median(&on, &|r| r.writer_cpu_s.map(|c| 1e3 * c / steps(r)));
    let bytes = median(&on, &|r| Some(r.log_bytes as f64 / steps(r)));
    let held = median(&on, &|r| Some(100.0 * r.held as f64 / (steps(r) * n as f64)));
    // The overhead of each pair (on / off of the same round), then their median: a pair runs
    // back to back, so a noisy stretch of the machine shifts both of its runs.
    let mut ratios: Vec<f64> = off.iter().zip(&on).map(|(a, b)| b.wall_s / a.wall_s).collect();
    ratios.sort_by(f64::total_cmp);
    let ratio = ratios[ratios.len() / 2];
    format!(
        "{{\"sim\": \"twinswarm\", \"scenario\": \"log_cost_{}\", \"N\": {n}, \"threads\": {threads}, \"rounds\": {rounds}, \
         \"sim_s\": {sim_s:.1}, \"ms_per_step_off\": {wall_off:.4}, \"ms_per_step_on\": {wall_on:.4}, \
         \"overhead_pct\": {:.1}, \"overhead_pct_min_max\": [{:.1}, {:.1}], \"step_thread_cpu_ms_off\": {cpu_off:.4}, \
         \"step_thread_cpu_ms_on\": {cpu_on:.4}, \"writer_cpu_ms_per_step\": {writer:.4}, \"log_kib_per_step\": {:.1}, \"held_pct\": {held:.1}}}",
        scene.name(),
        100.0 * (ratio - 1.0),
        100.0 * (ratios[0] - 1.0),
        100.0 * (ratios[ratios.len() - 1] - 1.0),
        bytes / 1024.0,
    )
}

/// Default simulated time: long enough for stable numbers, short for big swarms.
fn default_sim_s(n: usize) -> f64 {
    (2000.0 / n as f64).clamp(1.0, 20.0)
}

fn plot(out: &Path, runs: &[Run]) -> Result<(), Box<dyn std::error::Error>> {
    plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular())
        .map_err(|_| "the embedded font could not be loaded")?;
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    let root = BitMapBackend::new(out, (900, 600)).into_drawing_area();
    root.fill(&WHITE)?;
    let y_max = runs.iter().map(Run::us_per_copter_step).fold(1.0, f64::max) * 2.0;
    let y_min = runs.iter().map(Run::us_per_copter_step).fold(f64::MAX, f64::min) / 2.0;
    let mut chart = ChartBuilder::on(&root)
        .caption("Twinswarm: one 50 ms step (10 × 5 ms physics), Wall-Avoid, sensors on", ("sans-serif", 20))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(70)
        .build_cartesian_2d((0.7f64..15000.0).log_scale(), (y_min..y_max).log_scale())?;
    chart
        .configure_mesh()
        .x_desc("N copters")
        .y_desc("µs per copter-step (wall clock)")
        .label_style(("sans-serif", 14))
        .draw()?;
    // The 10× real-time budget at N = 1000: 5 ms per step = 5 µs per copter-step.
    chart
        .draw_series(LineSeries::new([(0.7, 5.0), (15000.0, 5.0)], BLACK.mix(0.4).stroke_width(1)))?
        .label("5 µs: 10× real time at N = 1000")
        .legend(|(x, y)| PathElement::new([(x, y), (x + 20, y)], BLACK.mix(0.4)));
    for (threads, color) in [(1, RGBColor(31, 119, 180)), (2, RGBColor(214, 39, 40))] {
        let pts: Vec<(f64, f64)> =
            runs.iter().filter(|r| r.threads == threads).map(|r| (r.n as f64, r.us_per_copter_step())).collect();
        chart
            .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))?
            .label(format!("{threads} thread{}", if threads > 1 { "s" } else { "" }))
            .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], color.stroke_width(2)));
        chart.draw_series(pts.iter().map(|&p| Circle::new(p, 4, color.filled())))?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .label_font(("sans-serif", 14))
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK.mix(0.3))
        .draw()?;
    root.present()?;
    Ok(())
}

fn main() {
    let mut ns = Vec::new();
    let mut threads = Vec::new();
    let mut log = false;
    let mut log_cost_rounds = None;
    let mut sim_s = None;
    let mut plot_to: Option<PathBuf> = None;
    let mut scene = Scene::Cruise;
    let mut args = std::env::args().skip(1).peekable();
    let mut list = None;
    while let Some(a) = args.next() {
        match a.as_str() {
            "--n" => list = Some(0),
            "--threads" => list = Some(1),
            "--log" => (log, list) = (true, None),
            "--log-cost" => (log_cost_rounds, list) = (args.next().and_then(|v| v.parse::<usize>().ok()), None),
            "--zstd-level" | "--log-rate" | "--chunk-kib" | "--log-unchanged" => (_, list) = (args.next(), None),
            "--sim-seconds" => (sim_s, list) = (args.next().and_then(|v| v.parse::<f64>().ok()), None),
            "--plot" => (plot_to, list) = (args.next().map(PathBuf::from), None),
            "--scene" => {
                scene = match args.next().as_deref() {
                    Some("cruise") => Scene::Cruise,
                    Some("dense") => Scene::Dense,
                    Some("dense-air") => Scene::DenseAir,
                    other => panic!("--scene takes cruise, dense or dense-air, not {other:?}"),
                };
                list = None;
            }
            // `cargo bench` passes `--bench`; other flags are not ours.
            s if s.starts_with("--") => list = None,
            s => match (list, s.parse::<usize>()) {
                (Some(0), Ok(v)) => ns.push(v),
                (Some(1), Ok(v)) => threads.push(v),
                _ => panic!("unexpected argument {s:?}"),
            },
        }
    }
    let dir = std::env::temp_dir().join(format!("twinswarm-swarm-rt-{}", std::process::id()));
    if let Err(e) = std::fs::create_dir_all(&dir) {
        panic!("cannot create {}: {e}", dir.display());
    }
    if let Some(out) = plot_to {
        let mut runs = Vec::new();
        for t in [1, 2] {
            for n in [1, 10, 100, 1000, 10_000] {
                let r = run(scene, n, t, false, sim_s.unwrap_or(default_sim_s(n) / 2.0), &dir);
                println!("{}", r.json());
                runs.push(r);
            }
        }
        if let Err(e) = plot(&out, &runs) {
            panic!("cannot draw {}: {e}", out.display());
        }
        let csv: String = std::iter::once("n,threads,us_per_copter_step\n".to_string())
            .chain(runs.iter().map(|r| format!("{},{},{:.4}\n", r.n, r.threads, r.us_per_copter_step())))
            .collect();
        let csv_path = out.with_extension("csv");
        if let Err(e) = std::fs::write(&csv_path, csv) {
            panic!("cannot write {}: {e}", csv_path.display());
        }
        eprintln!("wrote {} and {}", out.display(), csv_path.display());
    } else {
        if ns.is_empty() {
            ns = vec![100, 1000];
        }
        if threads.is_empty() {
            threads = vec![1];
        }
        for &t in &threads {
            for &n in &ns {
                // Experiments run long enough for crashes to pile up.
                let sim_s = sim_s.unwrap_or(if scene == Scene::Cruise { default_sim_s(n) } else { 60.0 });
                match log_cost_rounds {
                    Some(rounds) => println!("{}", log_cost(scene, n, t, rounds.max(1), sim_s, &dir)),
                    None => println!("{}", run(scene, n, t, log, sim_s, &dir).json()),
                }
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
