//! One 50 ms control step (10 physics substeps of 5 ms) of N hovering FINkens, with sensors
//! (4 sonar cones, IR, IMU, Wall-Avoid-ready readings) off and on, on 1 and 2 threads. The
//! arena grows with N to keep the density (one copter per 2 m × 2 m cell). The budget is
//! 50 ms: real time; 5 ms: ten times real time.
//!
//! `cargo bench -p twinswarm --bench step`

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use sim_core::{scene, step};

fn bench_step(c: &mut Criterion) {
    let mut group = c.benchmark_group("step_50ms");
    for threads in [1usize, 2] {
        for sensors in [false, true] {
            for n in [1usize, 10, 100, 1000, 10_000] {
                if threads > 1 && n < 100 {
                    continue; // nothing to share out
                }
                let mut spec = scene::grid_swarm(n, 2.0, 0.8, sensors);
                spec.sim.threads = threads;
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
                group.sample_size(if n >= 1000 { 10 } else { 30 });
                let label = format!("{}_{threads}t", if sensors { "sensors_on" } else { "sensors_off" });
                group.bench_with_input(BenchmarkId::new(label, n), &n, |b, _| {
                    b.iter(|| step(&world, &mut state, &inputs));
                });
                let crashed = state.copters.iter().filter(|c| c.crash.is_some()).count();
                assert_eq!(crashed, 0, "copters crashed during the benchmark: the numbers would be wrong");
            }
        }
    }
    group.finish();
}

/// One sonar reading (exact cone distance to walls, boxes and copters): the default lab (2
/// copters, 3 boxes), and a 1000-copter swarm through the copter grid.
fn bench_sonar_reading(c: &mut Criterion) {
    use sim_core::geometry::{Cone, OrientedBox};
    use sim_core::math::{Quat, Vec3};
    use sim_core::sensors::{SONAR_AXES_IN_BODY, SonarScene};
    let mut group = c.benchmark_group("sonar_reading");
    for (label, spec) in [("lab", scene::load_default().0), ("swarm_1000", scene::grid_swarm(1000, 2.0, 0.8, true))] {
        let world = match scene::compile(&spec) {
            Ok(w) => w,
            Err(e) => panic!("{e}"),
        };
        let state = world.initial_state();
        let (hx, hy) = (world.arena.size_m[0] / 2.0, world.arena.size_m[1] / 2.0);
        let mut sonar = SonarScene {
            walls: vec![(Vec3::X, hx), (Vec3::X, -hx), (Vec3::Y, hy), (Vec3::Y, -hy)],
            ..SonarScene::default()
        };
        sonar.boxes = world
            .boxes
            .iter()
            .map(|b| OrientedBox {
                center: b.center_m,
                rotation: Quat::from_rotation_z(b.yaw_rad),
                half: b.half_extents_m,
            })
            .collect();
        sonar.copters = (0..world.copters.len())
            .map(|i| OrientedBox {
                center: state.pose(i).pos_m,
                rotation: Quat::IDENTITY,
                half: Vec3::new(0.134, 0.134, 0.03),
            })
            .collect();
        sonar.index_copters(1.0);
        let cones: Vec<(usize, Cone)> = (0..world.copters.len().min(64))
            .flat_map(|i| {
                let p = state.pose(i).pos_m;
                SONAR_AXES_IN_BODY.map(|a| (i, Cone::new(p + a * 0.05, a, 15f32.to_radians())))
            })
            .collect();
        group.throughput(criterion::Throughput::Elements(cones.len() as u64));
        group.bench_function(label, |b| {
            b.iter(|| cones.iter().map(|(i, cone)| sonar.cone_distance(cone, *i, 7.65)).sum::<f32>())
        });
    }
    group.finish();
}

criterion_group!(benches, bench_step, bench_sonar_reading);
criterion_main!(benches);
