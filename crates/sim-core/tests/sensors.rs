//! Sensor models against analytic answers: sonar cone geometry (through the real sensing
//! path), sonar noise statistics, the IR height sensor, and determinism with every noise on.

use sim_core::geometry::{Cone, OrientedBox};
use sim_core::math::{Quat, Real, Vec3};
use sim_core::sensors::SonarScene;
use sim_core::{World, step};

/// Sonar half-angle of the default MB1232 model, rad.
const HALF: Real = 15.0 * std::f32::consts::PI / 180.0;
/// Default mount offset of each sonar from the body centre, m.
const MOUNT_M: Real = 0.05;

fn load(text: &str) -> World {
    match sim_core::scene::load("sensors_test.toml", text) {
        Ok((_, w)) => w,
        Err(e) => panic!("{e}"),
    }
}

/// One step from the initial state: the sensors then hold readings of the initial poses.
fn sense_once(world: &World) -> sim_core::State {
    let mut state = world.initial_state();
    step(world, &mut state, &world.initial_inputs());
    state
}

/// A copter hanging at 0.8 m (its first sensing happens before it has fallen) in an arena
/// of `arena_x × arena_y`, facing `yaw_deg`, with noise off, all four sonars read at once.
fn probe_scene(arena_x: Real, arena_y: Real, yaw_deg: Real, boxes: &str, extra_copters: &str) -> World {
    load(&format!(
        r#"
[sim]
seed = 3

[arena]
size_m = [{arena_x}, {arena_y}]
height_m = 4.0

[sensors]
noise = false

[sensors.sonar]
floor_echo = false
schedule = "together"

{boxes}

[[copter]]
name = "probe"
start = {{ pos_m = [0.0, 0.0], z_m = 0.8, yaw_deg = {yaw_deg} }}

{extra_copters}
"#
    ))
}

fn close(got: Real, want: Real, tol: Real, what: &str) {
    println!("{what}: reading {got:.5} m, analytic {want:.5} m");
    assert!((got - want).abs() <= tol, "{what}: got {got}, want {want} ± {tol}");
}

#[test]
fn sonar_sees_a_perpendicular_wall_at_its_distance() {
    // Wall at x = 1.55 m; the front sonar's apex is 0.05 m ahead of the centre: 1.5 m.
    let world = probe_scene(3.1, 20.0, 0.0, "", "");
    let state = sense_once(&world);
    let s = &state.copters[0].sensors;
    close(s.sonar_truth_m[0], 1.5, 1e-4, "perpendicular wall, front truth");
    close(s.sonar_m[0], 1.5, 1e-6, "perpendicular wall, front reading (noise off)");
    close(s.sonar_truth_m[2], 1.5, 1e-4, "perpendicular wall, back truth");
    // The side walls are 10 m away, beyond the 7.65 m range; but the side cones (axis
    // parallel to the wall x = 1.55, α = 90°) graze that wall at 1.55 / cos(90° − 15°).
    let graze = 1.55 / (std::f32::consts::FRAC_PI_2 - HALF).cos();
    close(s.sonar_truth_m[1], graze, 2e-3, "right cone grazing the wall it runs parallel to");
    close(s.sonar_truth_m[3], graze, 2e-3, "left cone grazing the wall it runs parallel to");
}

#[test]
fn sonar_reading_of_a_tilted_wall_is_the_nearest_point_inside_the_cone() {
    // Turning the copter turns the cone against the wall x = 1.55: the wall's normal makes
    // the yaw angle α with the sonar axis. Perpendicular distance from the apex: p.
    // α < h (10°): the foot of the perpendicular is inside the cone, reading p.
    // α > h (25°): the nearest point inside the cone is on its surface, p / cos(α − h).
    for (yaw_deg, inside) in [(10.0_f32, true), (25.0, false), (-25.0, false)] {
        let world = probe_scene(3.1, 20.0, yaw_deg, "", "");
        let state = sense_once(&world);
        let alpha = yaw_deg.abs().to_radians();
        let p = 1.55 - MOUNT_M * alpha.cos();
        let want = if inside { p } else { p / (alpha - HALF).cos() };
        let got = state.copters[0].sensors.sonar_truth_m[0];
        close(got, want, 2e-4, &format!("wall tilted {yaw_deg}° to the axis (inside half-angle: {inside})"));
        // The same through the scene query directly, with an exact apex at the origin.
        let mut scene = SonarScene::default();
        scene.walls.push((Vec3::NEG_X, -1.5));
        let axis = Quat::from_rotation_z(yaw_deg.to_radians()) * Vec3::X;
        let d = scene.cone_distance(&Cone::new(Vec3::ZERO, axis, HALF), usize::MAX, 7.65);
        let want = if inside { 1.5 } else { 1.5 / (alpha - HALF).cos() };
        close(d, want, 1e-4, &format!("SonarScene::cone_distance, wall tilted {yaw_deg}°"));
    }
}

#[test]
fn sonar_sees_boxes_off_axis_only_where_they_enter_the_cone() {
    // Tall boxes ahead (covering the sonar's height), in a 20 m arena (walls out of range).
    // The front apex is at (0.05, 0, 0.8); all distances below are from it.
    let tall = |name: &str, x0: Real, x1: Real, y0: Real, y1: Real| {
        format!(
            "[[box]]\nname = \"{name}\"\npos_m = [{}, {}]\nsize_m = [{}, {}, 2.0]\n",
            (x0 + x1) / 2.0,
            (y0 + y1) / 2.0,
            x1 - x0,
            y1 - y0
        )
    };
    let ax = MOUNT_M;
    // 1. Face x = 2.05 (2 m ahead), spanning y ∈ [0.3, 1.0]: the nearest point of the face
    //    is (2, 0.3) from the apex, 0.3 < 2 tan 15° = 0.536, so inside the cone.
    let world = probe_scene(20.0, 20.0, 0.0, &tall("inside", 2.0 + ax, 2.5 + ax, 0.3, 1.0), "");
    let got = sense_once(&world).copters[0].sensors.sonar_truth_m[0];
    close(got, 2.0_f32.hypot(0.3), 1e-4, "box off-axis, nearest corner inside the cone");
    // 2. y ∈ [0.6, 1.0], x ∈ [2, 2.5] ahead: the near face is outside the cone (0.6 > 0.536),
    //    the side face y = 0.6 enters it at x = 0.6 / tan 15°: reading 0.6 / sin 15°.
    let world = probe_scene(20.0, 20.0, 0.0, &tall("edge", 2.0 + ax, 2.5 + ax, 0.6, 1.0), "");
    let got = sense_once(&world).copters[0].sensors.sonar_truth_m[0];
    close(got, 0.6 / HALF.sin(), 1e-4, "box off-axis, entering the cone through its side face");
    // 3. y ∈ [1.0, 1.5]: entirely outside the cone (0.67 m radius at 2.5 m): no echo, cap.
    let world = probe_scene(20.0, 20.0, 0.0, &tall("outside", 2.0 + ax, 2.5 + ax, 1.0, 1.5), "");
    let s = sense_once(&world).copters[0].sensors;
    println!("box outside the cone: truth {} m (the cap), reading {} m", s.sonar_truth_m[0], s.sonar_m[0]);
    assert_eq!(s.sonar_truth_m[0], 7.65);
    assert_eq!(s.sonar_m[0], 7.65);
    // 4. The same cases through the scene query with a yawed box: a 45° yawed square whose
    //    corner points at the apex, on the axis: the corner is the nearest point.
    let b = OrientedBox {
        center: Vec3::new(2.0, 0.0, 0.0),
        rotation: Quat::from_rotation_z(45f32.to_radians()),
        half: Vec3::new(0.2, 0.2, 0.5),
    };
    let mut scene = SonarScene::default();
    scene.boxes.push(b);
    let d = scene.cone_distance(&Cone::new(Vec3::ZERO, Vec3::X, HALF), usize::MAX, 7.65);
    close(d, 2.0 - 0.2 * std::f32::consts::SQRT_2, 1e-4, "box yawed 45°, corner towards the sonar");
}

#[test]
fn sonar_sees_another_copter_in_its_cone() {
    // A second copter 1.5 m ahead at the same height. The sensing model represents a copter
    // by the box around its rotors: half width l/√2 + rotor radius.
    let other = r#"[[copter]]
name = "target"
start = { pos_m = [1.5, 0.0], z_m = 0.8, yaw_deg = 180.0 }"#;
    let world = probe_scene(20.0, 20.0, 0.0, "", other);
    let af = &world.airframes[world.copters[1].airframe].spec;
    let half = af.arm_length_m / std::f32::consts::SQRT_2 + af.rotor_diameter_m / 2.0;
    let state = sense_once(&world);
    close(state.copters[0].sensors.sonar_truth_m[0], 1.5 - half - MOUNT_M, 1e-4, "copter ahead");
    close(state.copters[1].sensors.sonar_truth_m[0], 1.5 - half - MOUNT_M, 1e-4, "and it sees the probe");
    // Moved 0.8 m sideways it is out of the cone (0.8 − 0.134 > 1.5 tan 15° + margin).
    let other = other.replace("[1.5, 0.0]", "[1.5, 0.8]");
    let world = probe_scene(20.0, 20.0, 0.0, "", &other);
    let state = sense_once(&world);
    println!("copter 0.8 m off the axis: front truth {} m", state.copters[0].sensors.sonar_truth_m[0]);
    assert_eq!(state.copters[0].sensors.sonar_truth_m[0], 7.65);
}

#[test]
fn sonar_noise_has_the_configured_mean_and_sigma() {
    // A copter resting on the floor (motors off: it does not move), a wall 1.5 m ahead of the
    // front sonar, noise on. 10,000 readings.
    let world = load(
        r#"
[sim]
seed = 11

[arena]
size_m = [3.1, 20.0]
height_m = 3.0

[sensors.sonar]
floor_echo = false

[[copter]]
name = "still"
start = { pos_m = [0.0, 0.0] }
"#,
    );
    let sigma = world.sensors.spec.sonar.noise_sigma_m as f64;
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let n = 10_000;
    let (mut sum, mut sum_sq) = (0.0f64, 0.0f64);
    for _ in 0..n {
        step(&world, &mut state, &inputs);
        let r = state.copters[0].sensors.sonar_m[0] as f64;
        assert!((r * 100.0 - (r * 100.0).round()).abs() < 1e-3, "not quantised to 1 cm: {r}");
        sum += r;
        sum_sq += r * r;
    }
    let truth = state.copters[0].sensors.sonar_truth_m[0] as f64;
    let mean = sum / n as f64;
    let sd = (sum_sq / n as f64 - mean * mean).sqrt();
    // Quantising to 1 cm adds a variance of (1 cm)² / 12.
    let expected_sd = (sigma * sigma + 0.01f64.powi(2) / 12.0).sqrt();
    println!(
        "sonar noise, {n} readings of a wall at {truth:.4} m: mean {mean:.4} m (bias {:+.2} mm), sd {:.2} mm \
         (σ = {:.1} mm, with quantisation {:.2} mm)",
        (mean - truth) * 1000.0,
        sd * 1000.0,
        sigma * 1000.0,
        expected_sd * 1000.0
    );
    assert!((truth - 1.5).abs() < 1e-4, "the copter moved: truth {truth}");
    assert!((mean - 1.5).abs() < 0.01, "mean {mean}");
    assert!((sd - sigma).abs() < 0.1 * sigma, "sd {sd} vs σ {sigma}");
}

#[test]
fn ir_reads_longer_when_tilted_and_flags_out_of_range() {
    // Hover at 1 m, then hold a 20° roll: the beam along −z_body meets the floor at h / cos θ.
    let world = load(
        r#"
[sim]
seed = 5

[arena]
size_m = [20.0, 20.0]
height_m = 4.0

[[copter]]
name = "tilted"
start = { pos_m = [0.0, 0.0], z_m = 1.0 }
command = { height_m = 1.0 }
"#,
    );
    let mut state = world.initial_state();
    let mut inputs = world.initial_inputs();
    for _ in 0..40 {
        step(&world, &mut state, &inputs);
    }
    let level = state.copters[0].sensors;
    let h_level = state.pose(0).pos_m.z;
    inputs.commands[0].roll_rad = 20f32.to_radians();
    for _ in 0..10 {
        step(&world, &mut state, &inputs);
    }
    // Sensing uses the pose at the start of a step: record it, then step.
    let pose = state.pose(0);
    let q = Quat::from_xyzw(pose.quat_xyzw[0], pose.quat_xyzw[1], pose.quat_xyzw[2], pose.quat_xyzw[3]);
    let cos_tilt = (q * Vec3::Z).z;
    step(&world, &mut state, &inputs);
    let s = state.copters[0].sensors;
    let want = pose.pos_m.z / cos_tilt;
    println!(
        "IR level at {h_level:.3} m: truth {:.4}, reading {:?}; tilted {:.1}° at {:.3} m: truth {:.4} m, \
         h / cos θ = {want:.4} m, reading {:?}",
        level.ir_truth_m,
        level.ir_m,
        cos_tilt.acos().to_degrees(),
        pose.pos_m.z,
        s.ir_truth_m,
        s.ir_m
    );
    assert!(cos_tilt.acos().to_degrees() > 15.0, "the copter did not tilt");
    assert!((s.ir_truth_m - want).abs() < 1e-4, "{} vs {want}", s.ir_truth_m);
    assert!(s.ir_truth_m > pose.pos_m.z + 0.04, "the tilted beam must read longer than the height");
    let sigma = world.sensors.spec.ir.noise_sigma_m + world.sensors.spec.ir.noise_sigma_rel * want;
    let ir = s.ir_m.expect("in range");
    assert!((ir - want).abs() < 5.0 * sigma, "reading {ir} vs {want} (σ {sigma})");

    // Too high: 2 m above the floor (> 1.5 m). Too low: resting on the floor (0.02 < 0.10 m).
    let world = load(
        r#"
[arena]
size_m = [20.0, 20.0]
height_m = 4.0

[[copter]]
name = "high"
start = { pos_m = [0.0, 0.0], z_m = 2.0 }

[[copter]]
name = "grounded"
start = { pos_m = [3.0, 0.0] }
"#,
    );
    let state = sense_once(&world);
    let (high, low) = (state.copters[0].sensors, state.copters[1].sensors);
    println!(
        "IR out of range: high truth {:.3} m -> {:?}; grounded truth {:.3} m -> {:?}",
        high.ir_truth_m, high.ir_m, low.ir_truth_m, low.ir_m
    );
    assert!(high.ir_truth_m > 1.5 && high.ir_m.is_none());
    assert!(low.ir_truth_m < 0.10 && low.ir_m.is_none());
}

/// Two copters in Wall-Avoid in the lab with cross-talk on: every random stream in use.
fn noisy_world(seed: u64) -> World {
    let text = include_str!("../../../assets/scenes/finken_lab.toml").replace("seed = 2016", &format!("seed = {seed}"))
        + "\n[sensors]\nnoise = true\n\n[sensors.crosstalk]\nenabled = true\n\n[airframes.noisy]\nparticle_noise = \"poisson\"\n";
    let text = text.replace("airframe = \"finken3\"", "airframe = \"noisy\"");
    load(&text)
}

fn fingerprint(world: &World, steps: usize) -> Vec<u32> {
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let mut crosstalk_events = 0;
    for _ in 0..steps {
        step(world, &mut state, &inputs);
        crosstalk_events += state.copters.iter().flat_map(|c| c.sensors.sonar_crosstalk).filter(|&x| x).count();
    }
    let mut bits = Vec::new();
    for i in 0..world.copters.len() {
        let p = state.pose(i);
        bits.extend(p.pos_m.to_array().map(f32::to_bits));
        bits.extend(p.vel_m_s.to_array().map(f32::to_bits));
        bits.extend(p.quat_xyzw.map(f32::to_bits));
        let s = &state.copters[i].sensors;
        bits.extend(s.sonar_m.map(f32::to_bits));
        bits.extend(s.sonar_truth_m.map(f32::to_bits));
        bits.extend(s.sonar_fused_m.map(f32::to_bits));
        bits.push(s.ir_m.unwrap_or(-1.0).to_bits());
        bits.extend(s.attitude_rad.map(f32::to_bits));
        bits.extend(s.rate_body_rad_s.map(f32::to_bits));
        bits.extend(s.accel_body_m_s2.map(f32::to_bits));
        bits.push(s.yaw_bias_rad.to_bits());
    }
    println!("  {steps} steps: {crosstalk_events} cross-talk readings along the way");
    bits
}

#[test]
fn determinism_holds_with_all_noise_and_crosstalk_on() {
    let a = fingerprint(&noisy_world(42), 200);
    let b = fingerprint(&noisy_world(42), 200);
    let c = fingerprint(&noisy_world(43), 200);
    println!("{} values compared bitwise", a.len());
    assert_eq!(a, b, "same seed, different bits");
    assert_ne!(a, c, "a different seed gave identical bits");
}

/// The FINken firmware takes whatever surface its IR sees below as the floor
/// (`finken_model_sensors.c`: no jump rejection): sent over another copter, a copter climbs
/// by the gap and holds its set point above the other's top. 0.8 m over 0.4 m: it settles
/// about 0.8 m above the lower one (its centre; the top is a few cm higher), not at 0.8 m.
#[test]
fn an_ir_over_another_copter_reads_it_and_the_copter_climbs_by_the_gap() {
    let world = load(
        r#"
[sim]
seed = 7
[arena]
size_m = [4.0, 3.0]
height_m = 2.5
[[copter]]
name = "low"
start = { pos_m = [0.0, 0.0] }
mode = "target"
command = { height_m = 0.4, target_m = [0.0, 0.0, 0.4] }
[[copter]]
name = "high"
start = { pos_m = [1.0, 0.0] }
mode = "target"
command = { height_m = 0.8, target_m = [0.0, 0.0, 0.8] }
"#,
    );
    let (mut state, inputs) = (world.initial_state(), world.initial_inputs());
    let (mut gaps, mut highs) = (Vec::new(), Vec::new());
    for _ in 0..(20.0 / world.params.control_dt_s) as u64 {
        step(&world, &mut state, &inputs);
        if state.tick as f64 * world.params.control_dt_s >= 15.0 {
            let (low, high) = (state.copters[0].motion.pos_m, state.copters[1].motion.pos_m);
            assert!((high.x - low.x).hypot(high.y - low.y) < 0.15, "over it: {high} {low}");
            gaps.push(high.z - low.z);
            highs.push(high.z);
        }
    }
    assert!(state.copters.iter().all(|c| c.crash.is_none()), "no crash");
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
    let (gap, high) = (mean(&gaps), mean(&highs));
    assert!((0.75..0.95).contains(&gap), "holds ~0.8 m above the lower copter: gap {gap}");
    assert!(high > 1.1, "so it is far above its own 0.8 m: {high}");
}
