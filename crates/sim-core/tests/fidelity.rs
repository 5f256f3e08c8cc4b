//! Where a real copter differs from a perfect one, each effect with its number, measured with
//! the effect on and off: the test fails if the effect is switched off (issue 13).
//! - height held on the IR: flying over the lab's table lifts the copter by the table;
//! - the battery: thrust at the same command falls over a 10-minute flight, and the height
//!   loop absorbs it;
//! - the lab firmware's own height loop (`finken3_2015_12`) sags below its set point and wanders
//!   as the real copter did; Twinswarm's newton loop holds it;
//! - downwash: a copter 0.5 m below another loses height and shakes; side by side at 0.5 m
//!   they barely feel each other;
//! - ground effect: the hover thrust drops near the floor and over a box top;
//! - sonars: the 7.65 m cap, floor echoes, cross-talk timed by free-running sonar cycles.

use sim_core::math::Real;
use sim_core::{State, World, step};

fn load(text: &str) -> World {
    match sim_core::scene::load("fidelity_test.toml", text) {
        Ok((_, w)) => w,
        Err(e) => panic!("{e}"),
    }
}

fn fly(world: &World, seconds: f64, mut each: impl FnMut(f64, &State)) -> State {
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    for _ in 0..(seconds / world.params.control_dt_s).round() as u64 {
        step(world, &mut state, &inputs);
        each(state.time_s(world), &state);
    }
    state
}

fn mean(v: &[Real]) -> Real {
    v.iter().sum::<Real>() / v.len() as Real
}

fn std_dev(v: &[Real]) -> Real {
    let m = mean(v);
    (v.iter().map(|x| (x - m) * (x - m)).sum::<Real>() / v.len() as Real).sqrt()
}

/// The lab with one copter in target mode holding 0.8 m on its estimate: 15 s over the floor
/// at (-1.2, 0.9), then 15 s over the table (top at 0.75 m) at (1.4, 0.9). Returns its mean
/// height over the floor and over the table (last 5 s of each) and the spread over the table.
fn table_flight(ideal: bool) -> (Real, Real, Real) {
    let lab = include_str!("../../../assets/scenes/finken_lab.toml");
    let head = &lab[..lab.find("[[copter]]").unwrap()];
    let world = load(&format!(
        "{head}\n[sensors.estimator]\nideal = {ideal}\n\n[[copter]]\nname = \"f\"\nstart = {{ pos_m = [-1.2, 0.9] }}\n\
         mode = \"target\"\ncommand = {{ target_m = [-1.2, 0.9, 0.8] }}\n"
    ));
    let mut state = world.initial_state();
    let mut inputs = world.initial_inputs();
    let (mut before, mut over) = (Vec::new(), Vec::new());
    for tick in 1..=600 {
        if tick == 300 {
            inputs.commands[0].target_m = Some([1.4, 0.9, 0.8]);
        }
        step(&world, &mut state, &inputs);
        let p = state.pose(0).pos_m;
        if (200..300).contains(&tick) {
            before.push(p.z);
        }
        if tick > 500 {
            // Target mode on the AHRS's biased attitude wanders a little: within 0.2 m of the
            // target keeps it over the 0.8 m × 0.5 m table top.
            assert!((p.x - 1.4).abs() < 0.2 && (p.y - 0.9).abs() < 0.2, "over the table at tick {tick}: {p:?}");
            over.push(p.z);
        }
    }
    assert!(state.copters[0].crash.is_none(), "{:?}", state.copters[0].crash);
    (mean(&before), mean(&over), std_dev(&over))
}

#[test]
fn a_copter_holding_height_on_its_ir_climbs_by_the_table() {
    let (before, over, sd) = table_flight(false);
    let (before_ideal, over_ideal, _) = table_flight(true);
    println!(
        "IR-held: {before:.3} m over the floor, {over:.3} m (σ {sd:.3}) over the 0.75 m table: rises {:.3} m",
        over - before
    );
    println!("ideal (true height): {before_ideal:.3} m, {over_ideal:.3} m: rises {:.3} m", over_ideal - before_ideal);
    assert!((over - before - 0.75).abs() < 0.08, "an IR-held copter rises by the table's height");
    assert!((over_ideal - before_ideal).abs() < 0.05, "a copter on true height does not");
}

/// The 16 Dec 2015 set-up (one FINken in Wall-Avoid holding 0.6 m in the 4 × 3 m arena from
/// where the real one started, its pack as charged as that day's: 11.5-11.8 V in flight),
/// 120 s, on the lab firmware's height loop or on Twinswarm's: the firmware's IR reading
/// (`finken_sensor_model.pos_z`) from 5 s after take-off, as real_flights.py takes the real
/// one's; returns its mean and standard deviation, m.
fn lab_height(firmware: bool) -> (Real, Real) {
    let height_loop = if firmware { "finken_height = {}" } else { "" };
    let world = load(&format!(
        r#"
[sim]
seed = 2015
[arena]
size_m = [4.0, 3.0]
height_m = 2.5
[airframes.under_test]
{height_loop}
battery = {{ initial_charge = 0.8 }}
[[copter]]
name = "finken"
ac_id = 5
airframe = "under_test"
start = {{ pos_m = [0.06, -0.44] }}
mode = "wall_avoid"
command = {{ height_m = 0.6 }}
"#
    ));
    let mut took_off = None;
    let mut ir = Vec::new();
    let end = fly(&world, 120.0, |t, s| {
        let c = &s.copters[0];
        if took_off.is_none() && c.took_off_tick.is_some() {
            took_off = Some(t);
        }
        if took_off.is_some_and(|t0| t >= t0 + 5.0) {
            ir.push(c.estimate.ir_reading_m);
        }
    });
    assert!(end.copters[0].crash.is_none(), "crashed (firmware loop: {firmware})");
    (mean(&ir), std_dev(&ir))
}

#[test]
fn the_lab_firmware_height_loop_sags_and_wanders_the_newton_loop_holds() {
    let (fw_mean, fw_sd) = lab_height(true);
    let (pid_mean, pid_sd) = lab_height(false);
    println!(
        "height from take-off + 5 s, set point 0.6 m: lab firmware's loop {fw_mean:.3} m, σ {:.1} cm; \
         Twinswarm's {pid_mean:.3} m, σ {:.1} cm (real, 16 Dec: 0.495 m, σ 4.4-8.5 cm per flight)",
        fw_sd * 100.0,
        pid_sd * 100.0
    );
    // The firmware's soft PIDT1 follows the battery and the tilt from below: low, wandering
    // within the real flights' spread.
    assert!(fw_mean < 0.58 && (0.044..=0.085).contains(&fw_sd), "firmware loop: {fw_mean} ± {fw_sd}");
    // The newton loop, tilt-compensated and adapting to the battery, holds its set point.
    assert!((pid_mean - 0.6).abs() < 0.01 && pid_sd < 0.02, "newton loop: {pid_mean} ± {pid_sd}");
}

/// One copter hovering 10 minutes at 0.8 m; returns (thrust factor of the same command at
/// 30 s and at the end, mean |height error| over the last minute, voltage at 30 s and end,
/// charge left).
fn battery_flight(battery: bool) -> ([Real; 2], Real, [Real; 2], Real) {
    let world = load(&format!(
        r#"
[sim]
seed = 5
[arena]
size_m = [4.0, 3.0]
height_m = 2.5
[airframes.f]
battery = {{ enabled = {battery} }}
[[copter]]
name = "f"
airframe = "f"
start = {{ pos_m = [0.0, 0.0] }}
mode = "target"
command = {{ target_m = [0.0, 0.0, 0.8] }}
"#
    ));
    let spec = &world.airframes[0].spec.battery;
    let factor = |s: &State| s.copters[0].battery.speed_scale(spec).powi(2);
    let (mut early, mut err) = ((0.0, 0.0), Vec::new());
    let end = fly(&world, 600.0, |t, s| {
        if (t - 30.0).abs() < 1e-6 {
            early = (factor(s), s.copters[0].battery.voltage_v);
        }
        if t > 540.0 {
            err.push((s.pose(0).pos_m.z - 0.8).abs());
        }
    });
    assert!(end.copters[0].crash.is_none());
    let b = &end.copters[0].battery;
    ([early.0, factor(&end)], mean(&err), [early.1, b.voltage_v], b.charge)
}

#[test]
fn the_battery_sags_over_ten_minutes_and_the_height_loop_absorbs_it() {
    let (f, err, v, charge) = battery_flight(true);
    let (f_off, err_off, _, _) = battery_flight(false);
    println!(
        "battery on: {:.2} V → {:.2} V, charge left {:.0} %; thrust at the same command ×{:.3} → ×{:.3} ({:+.1} %); \
         mean |height error| in the last minute {:.1} mm",
        v[0],
        v[1],
        charge * 100.0,
        f[0],
        f[1],
        100.0 * (f[1] / f[0] - 1.0),
        err * 1000.0
    );
    println!("battery off: thrust ×{:.3} → ×{:.3}; height error {:.1} mm", f_off[0], f_off[1], err_off * 1000.0);
    assert!(f[1] / f[0] < 0.85, "thrust at the same command falls by more than 15 % over 10 minutes");
    assert!(charge > 0.0 && charge < 0.3, "a 900 mAh pack is nearly empty after 10 minutes of hover: {charge}");
    assert!(err < 0.03, "the height loop absorbs the sag: {err}");
    assert_eq!(f_off, [1.0, 1.0], "without the battery model the thrust does not change");
}

/// Two copters in target mode, `below` holding 0.6 m, `above` 0.5 m over what its IR sees;
/// `dx` apart horizontally and `dz` apart vertically. Returns the lower one's largest height
/// loss in the first 5 s, and its height spread and tilt spread (rms) over 5–30 s.
fn pair_flight(dx: Real, dz: Real, downwash: bool) -> (Real, Real, Real) {
    let world = load(&format!(
        r#"
[sim]
seed = 8
[arena]
size_m = [6.0, 6.0]
height_m = 2.5
[airflow]
downwash = {downwash}
[[copter]]
name = "below"
start = {{ pos_m = [0.0, 0.0], z_m = 0.6 }}
mode = "target"
command = {{ target_m = [0.0, 0.0, 0.6] }}
[[copter]]
name = "above"
start = {{ pos_m = [{dx}, 0.0], z_m = {z} }}
mode = "target"
command = {{ target_m = [{dx}, 0.0, {h}] }}
"#,
        z = 0.6 + dz,
        h = if dz > 0.0 { dz } else { 0.6 },
    ));
    let (mut drop, mut z, mut tilt): (Real, Vec<Real>, Vec<Real>) = (0.0, Vec::new(), Vec::new());
    let end = fly(&world, 30.0, |t, s| {
        let p = s.pose(0);
        if t < 5.0 {
            drop = drop.max(0.6 - p.pos_m.z);
        } else {
            z.push(p.pos_m.z);
            tilt.push(p.rpy_rad[0].hypot(p.rpy_rad[1]));
        }
    });
    assert!(end.copters.iter().all(|c| c.crash.is_none()));
    let tilt_rms = (tilt.iter().map(|x| x * x).sum::<Real>() / tilt.len() as Real).sqrt();
    (drop, std_dev(&z), tilt_rms)
}

/// A pair flight with and without downwash, described in one line.
fn describe(what: &str, (drop, sd, tilt): (Real, Real, Real), (drop0, sd0, tilt0): (Real, Real, Real)) {
    println!(
        "{what}: drops {:.1} mm, height σ {:.2} mm, tilt rms {:.3}° (downwash off: {:.1} mm, {:.2} mm, {:.3}°)",
        drop * 1000.0,
        sd * 1000.0,
        tilt.to_degrees(),
        drop0 * 1000.0,
        sd0 * 1000.0,
        tilt0.to_degrees()
    );
}

#[test]
fn a_copter_below_another_loses_height_and_shakes() {
    let (on, off) = (pair_flight(0.0, 0.5, true), pair_flight(0.0, 0.5, false));
    describe("0.5 m below another", on, off);
    let ((drop, _, tilt), (drop0, _, tilt0)) = (on, off);
    assert!(drop > 0.05 && drop > 3.0 * drop0.max(0.005), "the wake pushes the lower copter down");
    assert!(tilt > 3.0 * tilt0, "and shakes it");
}

/// The thrust a copter hovering `dz` below another loses to its wake, as a share of its
/// weight: the mean downward downwash force over 10–30 s.
fn thrust_lost_below(dz: Real) -> Real {
    let world = load(&format!(
        r#"
[sim]
seed = 8
[arena]
size_m = [6.0, 6.0]
height_m = 3.0
[sensors.estimator]
ideal = true
[[copter]]
name = "below"
start = {{ pos_m = [0.0, 0.0], z_m = 0.6 }}
mode = "target"
command = {{ target_m = [0.0, 0.0, 0.6] }}
[[copter]]
name = "above"
start = {{ pos_m = [0.0, 0.0], z_m = {z} }}
mode = "target"
command = {{ target_m = [0.0, 0.0, {z}] }}
"#,
        z = 0.6 + dz,
    ));
    let weight = world.airframes[0].mass_kg * sim_core::math::GRAVITY_M_S2;
    let mut lost = Vec::new();
    fly(&world, 30.0, |t, s| {
        if t >= 10.0 {
            lost.push(-s.downwash_force_n(0).z / weight);
        }
    });
    mean(&lost)
}

/// The model against the literature (docs/model.md, the downwash table): a FINken 0.5 m below
/// another loses about 27–30 % of its weight (Neural-Swarm's Crazyflie figure scaled by size:
/// 27 %; the blade-element and jet model: 30 %), 1 m below 14–26 % (the sources disagree).
/// The upper copter holds 1.1 m and 1.6 m on ground truth (beyond its IR's range).
#[test]
fn the_thrust_lost_below_another_copter_is_the_literatures() {
    let (half, one) = (thrust_lost_below(0.5), thrust_lost_below(1.0));
    println!("thrust lost hovering below another: 0.5 m {:.1} % of the weight, 1 m {:.1} %", 100.0 * half, 100.0 * one);
    assert!((0.2..0.36).contains(&half), "{half}");
    assert!((0.1..0.3).contains(&one) && one < half, "{one}");
}

#[test]
fn side_by_side_copters_barely_feel_each_other() {
    let (on, off) = (pair_flight(0.5, 0.0, true), pair_flight(0.5, 0.0, false));
    describe("0.5 m beside another", on, off);
    let ((drop, sd, tilt), (drop0, sd0, tilt0)) = (on, off);
    assert!((drop - drop0).abs() < 0.005 && (sd - sd0).abs() < 0.002 && (tilt - tilt0).abs() < 0.1f32.to_radians());
}

/// Mean of the rotors' ω² over 10–20 s of hover at `x` beside or over the lab's table (x
/// 1.0–1.8 m, top at 0.75 m), started at `z` m and holding `target_m` (over what the IR sees,
/// or over the floor on ground truth with `ideal`); noise and battery off, so that ω² is the
/// thrust the copter needs over `k`.
fn hover_omega2_in(x: Real, z: Real, target_m: Real, ideal: bool, ground_effect: bool) -> Real {
    let world = load(&format!(
        r#"
[sim]
seed = 2
[arena]
size_m = [4.0, 3.0]
height_m = 2.5
[[box]]
name = "table"
pos_m = [1.4, 0.0]
size_m = [0.8, 0.5, 0.75]
[sensors]
noise = false
[sensors.estimator]
ideal = {ideal}
[airflow]
ground_effect = {ground_effect}
[airframes.f]
particle_noise = "off"
rotor_tolerance_sigma = 0.0
battery = {{ enabled = false }}
[[copter]]
name = "f"
airframe = "f"
start = {{ pos_m = [{x}, 0.0], z_m = {z} }}
mode = "target"
command = {{ target_m = [{x}, 0.0, {target_m}] }}
"#
    ));
    let mut w2 = Vec::new();
    fly(&world, 20.0, |t, s| {
        if t > 10.0 {
            w2.push(s.copters[0].rotor_speed_rad_s.iter().map(|w| w * w).sum::<Real>() / 4.0);
        }
    });
    mean(&w2)
}

/// Hovering `height_m` over the floor, or over the table when `over_table`, on the IR.
fn hover_omega2(height_m: Real, over_table: bool, ground_effect: bool) -> Real {
    let (x, z0) = if over_table { (1.4, 0.75) } else { (-1.0, 0.0) };
    hover_omega2_in(x, z0 + height_m, height_m, false, ground_effect)
}

#[test]
fn hover_thrust_drops_near_the_floor_and_over_a_box() {
    let high = hover_omega2(1.0, false, true);
    let low = hover_omega2(0.15, false, true);
    let table = hover_omega2(0.2, true, true);
    let low_off = hover_omega2(0.15, false, false);
    let high_off = hover_omega2(1.0, false, false);
    let pct = |a: Real, b: Real| 100.0 * (a / b - 1.0);
    println!(
        "hover ω² at 0.15 m over the floor {:+.2} %, 0.2 m over the table {:+.2} % (vs 1.0 m); ground effect off: {:+.3} %",
        pct(low, high),
        pct(table, high),
        pct(low_off, high_off)
    );
    // Cheeseman–Bennett at rotor height ≈ 0.17 m, R = 6.37 cm: 1 − (R/4z)² ≈ 0.991.
    assert!(pct(low, high) < -0.6 && pct(low, high) > -1.5);
    // At 0.2 m over the table top: ≈ 0.995.
    assert!(pct(table, high) < -0.3);
    assert!(pct(low_off, high_off).abs() < 0.05);
}

/// Hovering at `z` m over the floor at `x`, on ground truth (the same height whatever the IR
/// sees).
fn hover_omega2_at(x: Real, z: Real) -> Real {
    hover_omega2_in(x, z, z, true, true)
}

/// Ground effect under each rotor: a copter hovering over the table's edge (two rotors over
/// the table top 0.2 m below them, two over the floor 0.95 m below) gains about half of what
/// it gains wholly over the table.
#[test]
fn a_copter_half_over_a_table_edge_has_half_the_ground_effect() {
    let z = 0.95;
    let (floor, edge, table) = (hover_omega2_at(-1.0, z), hover_omega2_at(1.0, z), hover_omega2_at(1.4, z));
    let pct = |a: Real| 100.0 * (a / floor - 1.0);
    println!(
        "hover ω² at {z} m: over the table edge {:+.3} %, over the table {:+.3} % (vs over the floor)",
        pct(edge),
        pct(table)
    );
    assert!(pct(table) < -0.3, "{}", pct(table));
    let half = pct(edge) / pct(table);
    assert!((0.35..0.65).contains(&half), "half the rotors in ground effect: {half}");
}

/// A copter at `z` in a 20 m arena, facing +x, 9 m from the wall; returns its front reading
/// and truth (noise off).
fn sonar_probe(z: Real, floor_echo: bool) -> (Real, Real) {
    let world = load(&format!(
        r#"
[sim]
seed = 1
[arena]
size_m = [20.0, 20.0]
height_m = 6.0
[sensors]
noise = false
[sensors.sonar]
floor_echo = {floor_echo}
[[copter]]
name = "p"
start = {{ pos_m = [1.0, 0.0], z_m = {z} }}
"#
    ));
    let mut state = world.initial_state();
    step(&world, &mut state, &world.initial_inputs());
    let r = &state.copters[0].sensors;
    (r.sonar_m[0], r.sonar_truth_m[0])
}

#[test]
fn sonars_are_capped_at_765_cm_and_hear_the_floor_inside_their_cone() {
    let (far, far_truth) = sonar_probe(3.0, true);
    println!("wall 9 m ahead at 3 m height: reads {far} m (truth capped at {far_truth} m)");
    assert_eq!((far, far_truth), (7.65, 7.65));
    let (low, _) = sonar_probe(0.4, true);
    let (low_off, _) = sonar_probe(0.4, false);
    // The cone's lower edge (15° down) meets the floor at 0.4 / sin 15° from the sonar.
    let want = 0.4 / 15f32.to_radians().sin();
    println!("at 0.4 m the floor echoes at {low} m (cone edge {want:.3} m); without floor echoes {low_off} m");
    assert!((low - want).abs() < 0.02);
    assert_eq!(low_off, 7.65);
}

/// Two copters 1.6 m apart facing each other at 0.8 m, one minute: the fraction of the first
/// copter's front readings shortened by the other's pings, and the number of disturbed runs.
/// A minute of a facing pair with free-running sonars pinging together every 49 ms (`phase`
/// free-running or synchronous).
fn crosstalk_minute(phase: &str) -> (f64, u32, Vec<Real>) {
    crosstalk_minute_with(4, &format!("{FREE_RUNNING}phase = \"{phase}\""))
}

/// Sonars pinging together on 49 ms cycles, 2000 ppm apart.
const FREE_RUNNING: &str =
    "[sensors.sonar]\nschedule = \"together\"\n[sensors.crosstalk]\ncycle_s = 0.049\ncycle_spread = 0.002\n";

/// The firmware's schedule (the default): one sonar per 50 ms tick, each every 0.2 s, on
/// crystals 50 ppm apart.
const ROUND_ROBIN: &str =
    "[sensors.sonar]\nschedule = \"round_robin\"\n[sensors.crosstalk]\ncycle_s = 0.2\ncycle_spread = 0.00005\n";

fn crosstalk_minute_with(seed: u64, crosstalk: &str) -> (f64, u32, Vec<Real>) {
    let world = load(&format!(
        r#"
[sim]
seed = {seed}
[arena]
size_m = [8.0, 6.0]
height_m = 2.5
{crosstalk}
[[copter]]
name = "a"
start = {{ pos_m = [-0.8, 0.0], z_m = 0.8 }}
mode = "target"
command = {{ target_m = [-0.8, 0.0, 0.8] }}
[[copter]]
name = "b"
start = {{ pos_m = [0.8, 0.0], z_m = 0.8, yaw_deg = 180.0 }}
mode = "target"
command = {{ target_m = [0.8, 0.0, 0.8], yaw_deg = 180.0 }}
"#
    ));
    let (mut hits, mut n, mut runs, mut last) = (0u32, 0u32, 0u32, false);
    let mut readings = Vec::new();
    fly(&world, 60.0, |_, s| {
        let r = &s.copters[0].sensors;
        n += 1;
        if r.sonar_crosstalk[0] {
            hits += 1;
            readings.push(r.sonar_m[0]);
        }
        runs += u32::from(r.sonar_crosstalk[0] && !last);
        last = r.sonar_crosstalk[0];
    });
    (f64::from(hits) / f64::from(n), runs, readings)
}

#[test]
fn crosstalk_comes_from_free_running_sonar_cycles() {
    let (free, runs, readings) = crosstalk_minute("free_running");
    let (sync, _, sync_readings) = crosstalk_minute("synchronous");
    println!(
        "free-running: {:.1} % of front readings disturbed, in {runs} bursts; readings {:.2}–{:.2} m",
        100.0 * free,
        readings.iter().copied().fold(Real::MAX, Real::min),
        readings.iter().copied().fold(0.0, Real::max)
    );
    println!("synchronous: {:.1} % disturbed, all at d/2: {:?}", 100.0 * sync, &sync_readings[..3]);
    // Drifting phases: disturbed while the other's ping lands before this one's echo, a
    // fraction of the beat, in bursts rather than independently each cycle.
    assert!(free > 0.03 && free < 0.6, "{free}");
    assert!(runs >= 1 && f64::from(runs) < 0.25 * free * 1200.0, "bursts, not independent draws: {runs}");
    let (lo, hi) = sync_readings.iter().fold((Real::MAX, Real::MIN), |(lo, hi), &r| (lo.min(r), hi.max(r)));
    println!("synchronous readings {lo}–{hi} m");
    assert!(sync > 0.95 && lo > 0.7 && hi < 0.8, "d/2 when synchronous");
}

/// RMS of the AHRS's roll and pitch error against the truth while hovering, deg.
fn ahrs_error_rms_deg(ideal: bool) -> Real {
    let world = load(&format!(
        r#"
[sim]
seed = 6
[arena]
size_m = [4.0, 3.0]
height_m = 2.5
[sensors.estimator]
ideal = {ideal}
[[copter]]
name = "f"
start = {{ pos_m = [0.0, 0.0] }}
mode = "target"
command = {{ target_m = [0.0, 0.0, 0.8] }}
"#
    ));
    let mut sq = Vec::new();
    fly(&world, 60.0, |t, s| {
        if t > 5.0 {
            let truth = s.pose(0).rpy_rad;
            // What the attitude loop read in the last physics step (one step before the pose).
            let est = s.copters[0].estimate.attitude_rad;
            sq.push((est[0] - truth[0]).powi(2) + (est[1] - truth[1]).powi(2));
        }
    });
    (mean(&sq) / 2.0).sqrt().to_degrees()
}

#[test]
fn the_attitude_loop_reads_an_ahrs_with_noise_bias_and_lag() {
    let est = ahrs_error_rms_deg(false);
    let ideal = ahrs_error_rms_deg(true);
    println!("AHRS roll/pitch error rms while hovering: {est:.2}° (ideal estimation: {ideal:.4}°)");
    // 1.5° white noise (the real FINken's logged attitude in hover, docs/accuracy.md), a
    // 0.25° wandering bias and a 5 ms lag; the ideal reading differs from the pose only by the
    // one physics step between them.
    assert!((1.0..2.2).contains(&est), "{est}");
    assert!(ideal < 0.25 * est, "{ideal}");
}

/// The firmware's schedule (one sonar per 50 ms tick, each every 200 ms, copters' crystals
/// 50 ppm apart) instead of free-running 49 ms cycles: a facing pair is disturbed
/// only when its two schedules happen to line up (a window of about 2·d/c = 8 ms in 200 ms),
/// and then for the whole minute, since the phases hardly drift.
#[test]
fn the_firmwares_round_robin_schedule_makes_crosstalk_rarer_and_longer() {
    let (free, _, _) = crosstalk_minute("free_running");
    let minutes: Vec<f64> = (1..=100).map(|seed| crosstalk_minute_with(seed, ROUND_ROBIN).0).collect();
    let disturbed: Vec<f64> = minutes.iter().copied().filter(|&f| f > 0.0).collect();
    let mean = minutes.iter().sum::<f64>() / minutes.len() as f64;
    println!(
        "round robin, 100 seeds × 1 min: {} minutes disturbed (in those, {:.0}–{:.0} % of readings), {:.1} % of all readings; \
         free-running 49 ms: {:.1} %",
        disturbed.len(),
        100.0 * disturbed.iter().copied().fold(1.0, f64::min),
        100.0 * disturbed.iter().copied().fold(0.0, f64::max),
        100.0 * mean,
        100.0 * free
    );
    assert!((1..=20).contains(&disturbed.len()), "{} of 100 minutes disturbed", disturbed.len());
    assert!(mean < 0.5 * free, "{mean} vs {free}");
}

/// The largest horizontal distance from its start a copter hovering at 0.8 m (Mixed-Manual:
/// level attitude command, height held on the IR) strays in the 90 s after it has taken off
/// (5 s), in a 20 m × 20 m hall (no wall within sonar range to matter), m.
fn hover_drift_90_s(seed: u64, trimmed: bool, ideal: bool, extra: &str) -> Real {
    let world = load(&format!(
        r#"
[sim]
seed = {seed}
[sensors.estimator]
ideal = {ideal}
[arena]
size_m = [20.0, 20.0]
height_m = 3.0
[airframes.finken3]
trimmed = {trimmed}
{extra}
[[copter]]
name = "f"
airframe = "finken3"
start = {{ pos_m = [0.0, 0.0] }}
mode = "mixed_manual"
command = {{ height_m = 0.8 }}
"#
    ));
    let mut start = None;
    let mut worst: Real = 0.0;
    fly(&world, 95.0, |t, s| {
        let p = s.pose(0).pos_m.truncate();
        if t >= 5.0 {
            let p0 = *start.get_or_insert(p);
            worst = worst.max((p - p0).length());
        }
    });
    worst
}

/// The paper's Fig. 8: V-REP copters, flying on true attitude, "mainly moving close to the
/// initial positions" over 90 s. Trimming removes the steady tilt of the rotors' tolerances:
/// on true attitude and smooth rotors (V-REP's view of a copter without its particle noise)
/// a trimmed copter stays within 1 m where an untrimmed one drifts metres. What is left moves
/// it: the particle model's thrust noise, and with a real AHRS its wandering bias (a tilt of
/// 0.01° already drifts 0.4 m in 90 s against the 0.3/s damping); docs/accuracy.md has the
/// figures.
#[test]
fn trimming_keeps_a_hovering_copter_near_its_start() {
    let runs = |trimmed: bool, ideal: bool, extra: &str| -> Vec<Real> {
        (1..=5).map(|seed| hover_drift_90_s(seed, trimmed, ideal, extra)).collect()
    };
    let smooth = "particle_noise = \"off\"";
    let (trimmed, untrimmed) = (runs(true, true, smooth), runs(false, true, smooth));
    println!("largest drift in 90 s of hover, seeds 1–5, true attitude, smooth rotors:");
    println!("  trimmed {trimmed:.2?} m, untrimmed {untrimmed:.2?} m");
    println!("  with particle noise: trimmed {:.2?} m", runs(true, true, ""));
    println!(
        "  with the AHRS and particle noise: trimmed {:.2?} m, untrimmed {:.2?} m",
        runs(true, false, ""),
        runs(false, false, "")
    );
    assert!(trimmed.iter().all(|&d| d < 1.0), "{trimmed:?}");
    assert!(untrimmed.iter().all(|&d| d > 3.0), "{untrimmed:?}");
}
