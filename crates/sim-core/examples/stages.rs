//! Where a step's time goes, stage by stage, on one thread and on two: the serial fraction of
//! a step (the time only one thread works), measured two ways.
//!
//! ```text
//! cargo run --release -p sim-core --example stages -- [N] [SECONDS] [SEED] [ROUNDS]
//! ```
//!
//! Flies the dense take-off among pillars (`scene::dense_swarm(N, 1.5, true, 10, SEED)`;
//! defaults 10,000 copters, 5 s, seed 5), ROUNDS times (default 3) with `threads = 1` and with
//! `threads = 2` in turn, timing each [`Stage`] through `step_probed` (sim-core reads no clock;
//! this example does). Per stage, over the rounds, the median of:
//!
//! - **t1, t2**: its wall time per step on one thread and on two;
//! - **Amdahl**: the part that ran on one thread, from the walls alone: s = max(0, 2 t2 − t1)
//!   (t2 = s + p / 2, t1 = s + p). It counts everything that makes two threads less than twice
//!   as fast: serial code, load imbalance, hand-offs, and two busy cores each running slower
//!   than one alone (shared caches, memory, clock);
//! - **one thread only**: the wall time during which only one of the two pool threads was on
//!   a CPU, from each thread's own CPU clock (Linux): max(0, 2 t2 − c0 − c1). Rayon's idle
//!   threads spin briefly (yielding) before they sleep, and that spin counts as CPU time here,
//!   so this figure is a lower bound of the serial time; Amdahl's is an upper one;
//! - **CPU ×**: the CPU time of both threads at two threads over the CPU time at one: the work
//!   two threads add (1.00 = none).
//!
//! On one thread the free copters' inner loops run inside `InRapierLanes` (one pass over all
//! copters); on two, beside Rapier in `RapierAndFreeLanes`: the two are read together as
//! "inner loops + Rapier". The same bits on both (checked every round). With
//! `STAGES_SUBSTEPS=1` in the environment, the physics stages are shown per substep.
#![allow(unsafe_code, reason = "clock_gettime on other threads' CPU clocks; an example, not the library")]

use std::collections::BTreeMap;
use std::time::Instant;

use sim_core::scene;
use sim_core::{Stage, StepReport, step_probed};

fn main() {
    let mut args = std::env::args().skip(1);
    let n: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(10_000);
    let seconds: f64 = args.next().and_then(|s| s.parse().ok()).unwrap_or(5.0);
    let seed: u64 = args.next().and_then(|s| s.parse().ok()).unwrap_or(5);
    let rounds: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(3).max(1);
    let worlds: Vec<_> = [1, 2]
        .map(|threads| {
            let mut spec = scene::dense_swarm(n, 1.5, true, 10, seed);
            spec.sim.threads = threads;
            scene::compile(&spec).expect("scene compiles")
        })
        .into();
    let ticks = (seconds / worlds[0].params.control_dt_s).round() as u64;
    let mut runs: [Vec<Run>; 2] = [Vec::new(), Vec::new()];
    for _ in 0..rounds {
        for (k, world) in worlds.iter().enumerate() {
            runs[k].push(fly(world, ticks));
        }
        assert_eq!(runs[0][0].digest, runs[1].last().unwrap().digest, "1 and 2 threads must give the same bits");
    }
    let rows = table(&runs, ticks as f64);
    println!(
        "dense take-off among pillars, {n} copters, {seconds} s ({ticks} steps), seed {seed}, median of {rounds} rounds"
    );
    println!(
        "{:<22} {:>9} {:>9} {:>9} {:>7} {:>10} {:>7} {:>6}",
        "stage (ms per step)", "1 thread", "2 threads", "Amdahl", "share", "one only", "share", "CPU ×"
    );
    let total = rows.iter().fold(Row::default(), |a, (_, r)| a.add(r));
    let step = "step".to_owned();
    for (name, r) in rows.iter().chain([(&step, &total)]) {
        println!(
            "{name:<22} {:>9.3} {:>9.3} {:>9.3} {:>6.1}% {:>10.3} {:>6.1}% {:>6.2}",
            r.t1,
            r.t2,
            r.amdahl(),
            100.0 * r.amdahl() / total.t1,
            r.one_only(),
            100.0 * r.one_only() / total.t1,
            r.cpu2 / r.cpu1.max(1e-9)
        );
    }
    let walls = |k: usize| median(runs[k].iter().map(|r| r.wall_s).collect());
    let f = total.amdahl() / total.t1;
    let g = total.one_only() / total.t1;
    println!(
        "speed-up on 2 threads {:.2} (wall {:.2} s / {:.2} s); serial fraction: Amdahl {:.1} % (16 threads: {:.2}), \
         one thread only {:.1} % (16 threads: {:.2}); CPU × {:.2}",
        walls(0) / walls(1),
        walls(0),
        walls(1),
        100.0 * f,
        amdahl(f, 16.0),
        100.0 * g,
        amdahl(g, 16.0),
        total.cpu2 / total.cpu1
    );
}

fn amdahl(f: f64, threads: f64) -> f64 {
    1.0 / (f + (1.0 - f) / threads)
}

/// A stage's figures, ms per step.
#[derive(Clone, Copy, Default)]
struct Row {
    t1: f64,
    t2: f64,
    cpu1: f64,
    cpu2: f64,
}

impl Row {
    fn add(self, o: &Row) -> Row {
        Row { t1: self.t1 + o.t1, t2: self.t2 + o.t2, cpu1: self.cpu1 + o.cpu1, cpu2: self.cpu2 + o.cpu2 }
    }
    fn amdahl(&self) -> f64 {
        (2.0 * self.t2 - self.t1).max(0.0)
    }
    fn one_only(&self) -> f64 {
        (2.0 * self.t2 - self.cpu2).clamp(0.0, self.t2)
    }
}

/// Per stage group, the median over the rounds of each figure, ms per step.
fn table(runs: &[Vec<Run>; 2], steps: f64) -> BTreeMap<String, Row> {
    // With STAGES_SUBSTEPS set, the physics stages are shown per substep ("RapierForces/3").
    let per_substep = std::env::var_os("STAGES_SUBSTEPS").is_some();
    let group = |&(s, sub): &(Stage, u32)| match s {
        Stage::InRapierLanes | Stage::RapierAndFreeLanes if per_substep => format!("inner loops + Rapier/{sub}"),
        Stage::InRapierLanes | Stage::RapierAndFreeLanes => "inner loops + Rapier".to_owned(),
        Stage::RapierForces | Stage::RapierResults | Stage::TiltAndTakeOff if per_substep => format!("{s:?}/{sub}"),
        s => format!("{s:?}"),
    };
    // Per group, per round: (wall, cpu) at 1 and at 2 threads.
    let mut per: BTreeMap<String, [Vec<(f64, f64)>; 2]> = BTreeMap::new();
    for (k, rs) in runs.iter().enumerate() {
        for (round, run) in rs.iter().enumerate() {
            for (stage, t) in &run.stages {
                let e = per.entry(group(stage)).or_default();
                e[k].resize(rs.len(), (0.0, 0.0));
                e[k][round].0 += t.wall_s;
                e[k][round].1 += t.cpu_s;
            }
        }
    }
    let ms = |v: &[(f64, f64)], f: fn(&(f64, f64)) -> f64| median(v.iter().map(f).collect()) / steps * 1e3;
    per.into_iter()
        .map(|(name, [a, b])| {
            let row = Row { t1: ms(&a, |x| x.0), cpu1: ms(&a, |x| x.1), t2: ms(&b, |x| x.0), cpu2: ms(&b, |x| x.1) };
            (name, row)
        })
        .collect()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => 0.0,
        n if n % 2 == 1 => v[n / 2],
        n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

#[derive(Clone, Copy, Default)]
struct Times {
    wall_s: f64,
    cpu_s: f64,
}

struct Run {
    /// Per stage and substep (0 outside the substeps).
    stages: BTreeMap<(Stage, u32), Times>,
    wall_s: f64,
    digest: Vec<u64>,
}

fn fly(world: &sim_core::World, ticks: u64) -> Run {
    let (mut state, inputs) = (world.initial_state(), world.initial_inputs());
    let mut report = StepReport::default();
    let mut stages: BTreeMap<(Stage, u32), Times> = BTreeMap::new();
    let mut substep = 0;
    let mut clocks = cpu::Clocks::default();
    let start = Instant::now();
    let (mut last, mut last_cpu) = (start, 0.0);
    for _ in 0..ticks {
        step_probed(world, &mut state, &inputs, &mut report, &mut |stage| {
            let (now, cpu) = (Instant::now(), clocks.seconds(world.params.threads));
            if stage == Stage::Begin {
                substep = 0;
            } else {
                let t = stages.entry((stage, substep)).or_default();
                substep += u32::from(stage == Stage::TiltAndTakeOff);
                t.wall_s += (now - last).as_secs_f64();
                t.cpu_s += cpu - last_cpu;
            }
            (last, last_cpu) = (now, cpu);
        });
    }
    let digest = state.copters.iter().map(|c| c.digest()).collect();
    Run { stages, wall_s: start.elapsed().as_secs_f64(), digest }
}

/// The CPU time of the threads that run a step: the calling thread on one thread, the pool's
/// threads (named `sim-core-*`) on more.
mod cpu {
    #[derive(Default)]
    pub struct Clocks {
        pool: Vec<i32>,
    }

    impl Clocks {
        /// Seconds of CPU the step's threads have used so far (0 where the OS has no such clock).
        pub fn seconds(&mut self, threads: usize) -> f64 {
            if threads <= 1 {
                return thread_cpu_s(CLOCK_THREAD_CPUTIME_ID);
            }
            if self.pool.len() != threads {
                self.pool = pool_clocks();
            }
            self.pool.iter().map(|&c| thread_cpu_s(c)).sum()
        }
    }

    const CLOCK_THREAD_CPUTIME_ID: i32 = 3;

    #[repr(C)]
    struct Timespec {
        tv_sec: i64,
        tv_nsec: i64,
    }

    #[cfg(target_os = "linux")]
    unsafe extern "C" {
        fn clock_gettime(clock: i32, out: *mut Timespec) -> i32;
    }

    #[cfg(target_os = "linux")]
    fn thread_cpu_s(clock: i32) -> f64 {
        let mut t = Timespec { tv_sec: 0, tv_nsec: 0 };
        // SAFETY: `t` is a valid, writable timespec; a bad clock id only returns an error.
        let rc = unsafe { clock_gettime(clock, &mut t) };
        if rc == 0 { t.tv_sec as f64 + 1e-9 * t.tv_nsec as f64 } else { 0.0 }
    }

    #[cfg(not(target_os = "linux"))]
    fn thread_cpu_s(_clock: i32) -> f64 {
        0.0
    }

    /// The CPU clocks of this process's threads named `sim-core-*` (Linux's per-thread clock
    /// ids: `(!tid << 3) | 6`).
    fn pool_clocks() -> Vec<i32> {
        let Ok(tasks) = std::fs::read_dir("/proc/self/task") else { return Vec::new() };
        let mut clocks: Vec<(String, i32)> = tasks
            .flatten()
            .filter_map(|t| {
                let tid: i32 = t.file_name().to_str()?.parse().ok()?;
                let comm = std::fs::read_to_string(t.path().join("comm")).ok()?;
                comm.starts_with("sim-core-").then_some((comm, (!tid << 3) | 6))
            })
            .collect();
        clocks.sort();
        clocks.into_iter().map(|(_, c)| c).collect()
    }
}
