//! The cost of MCAP logging: one 50 ms control step of N hovering FINkens with sensors on,
//! logging off versus on (every state, sensor reading, command, controller output, transform
//! and 3D view, to a file in a temporary directory), N = 100, 1000 and 10 000, on 1 and 2
//! threads. The step thread only copies numbers; the logger's writer thread encodes and
//! compresses, and the step waits for it only when it falls behind (see the README's logging
//! table, made with `swarm_rt --log-cost`).
//!
//! `cargo bench -p twinswarm --bench log`

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use sim_core::{scene, step};

fn bench_log(c: &mut Criterion) {
    let mut group = c.benchmark_group("log_step_50ms");
    let dir = std::env::temp_dir().join(format!("twinswarm-bench-log-{}", std::process::id()));
    if let Err(e) = std::fs::create_dir_all(&dir) {
        panic!("cannot create {}: {e}", dir.display());
    }
    for threads in [1usize, 2] {
        for n in [100usize, 1000, 10_000] {
            let mut spec = scene::grid_swarm(n, 2.0, 0.8, true);
            spec.sim.threads = threads;
            let world = match scene::compile(&spec) {
                Ok(w) => w,
                Err(e) => panic!("{e}"),
            };
            group.sample_size(if n >= 1000 { 10 } else { 30 });
            let inputs = world.initial_inputs();
            for logging in [false, true] {
                let mut state = world.initial_state();
                for _ in 0..20 {
                    step(&world, &mut state, &inputs);
                }
                let label = format!("{}_{threads}t", if logging { "log_on" } else { "log_off" });
                if logging {
                    let path = dir.join("bench.mcap");
                    let meta = bridge::log::LogMeta::default();
                    let mut log = match bridge::log::Logger::create(&path, &world, "", meta) {
                        Ok(l) => l,
                        Err(e) => panic!("{e}"),
                    };
                    group.bench_with_input(BenchmarkId::new(label, n), &n, |b, _| {
                        b.iter(|| {
                            let r = step(&world, &mut state, &inputs);
                            if let Err(e) = log.log_step(&world, &state, &inputs, &r) {
                                panic!("{e}");
                            }
                        })
                    });
                    if let Err(e) = log.finish() {
                        panic!("{e}");
                    }
                } else {
                    group.bench_with_input(BenchmarkId::new(label, n), &n, |b, _| {
                        b.iter(|| step(&world, &mut state, &inputs))
                    });
                }
                let crashed = state.copters.iter().filter(|c| c.crash.is_some()).count();
                assert_eq!(crashed, 0, "copters crashed during the benchmark: the numbers would be wrong");
            }
        }
    }
    group.finish();
    let _ = std::fs::remove_dir_all(&dir);
}

criterion_group!(benches, bench_log);
criterion_main!(benches);
