//! One 50 ms control step (10 physics substeps of 5 ms) of N hovering FINkens, with sensors
//! (4 sonar cones, IR, IMU, Wall-Avoid-ready readings) off and on. The arena grows with N to
//! keep the density (one copter per 2 m × 2 m cell). The budget is 50 ms: real time.
//!
//! `cargo bench -p twinswarm --bench step`

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use sim_core::{scene, step};

fn bench_step(c: &mut Criterion) {
    let mut group = c.benchmark_group("step_50ms");
    for sensors in [false, true] {
        for n in [1usize, 10, 100, 1000] {
            let spec = scene::grid_swarm(n, 2.0, 0.8, sensors);
            let world = match scene::compile(&spec) {
                Ok(w) => w,
                Err(e) => panic!("{e}"),
            };
            let mut state = world.initial_state();
            let inputs = world.initial_inputs();
            // Warm up: let every copter settle into its hover.
            for _ in 0..20 {
                step(&world, &mut state, &inputs);
            }
            if n >= 1000 {
                group.sample_size(10);
            } else {
                group.sample_size(30);
            }
            let label = if sensors { "sensors_on" } else { "sensors_off" };
            group.bench_with_input(BenchmarkId::new(label, n), &n, |b, _| {
                b.iter(|| step(&world, &mut state, &inputs));
            });
            let crashed = state.copters.iter().filter(|c| c.crash.is_some()).count();
            assert_eq!(crashed, 0, "copters crashed during the benchmark: the numbers would be wrong");
        }
    }
    group.finish();
}

criterion_group!(benches, bench_step);
criterion_main!(benches);
