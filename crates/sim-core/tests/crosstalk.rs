//! Sonar cross-talk between copters (paper, section VII-D): two copters in Wall-Avoid facing
//! each other rarely crash when their sonars do not hear each other, and are disturbed, and
//! crash into the walls (not into each other), when they do. Cross-talk needs both cones to
//! face each other: it depends on orientation.

use sim_core::math::Real;
use sim_core::{Event, World, step};

const LAB: &str = include_str!("../../../assets/scenes/finken_lab.toml");

fn load(text: &str) -> World {
    match sim_core::scene::load("crosstalk_test.toml", text) {
        Ok((_, w)) => w,
        Err(e) => panic!("{e}"),
    }
}

/// Which sonar schedule a flight uses.
#[derive(Clone, Copy, Debug)]
enum Schedule {
    /// The default: the FINken firmware's, one sonar per 50 ms tick, each pinging every 0.2 s
    /// on the autopilot's crystal (copters 50 ppm apart).
    Firmware,
    /// All four sonars together on free-running 49 ms cycles, 2000 ppm apart.
    FreeRunning,
}

/// The lab, both copters in Wall-Avoid facing each other (the second turned to 180°), under
/// `seed`, cross-talk on or off, with the sonar `schedule`.
fn lab(seed: u64, crosstalk: bool, schedule: Schedule) -> World {
    let facing = LAB.replace("yaw_deg = 225.0", "yaw_deg = 180.0");
    assert_ne!(facing, LAB);
    let (sonar, cycle) = match schedule {
        Schedule::Firmware => ("", ""),
        Schedule::FreeRunning => {
            ("[sensors.sonar]\nschedule = \"together\"\n", "cycle_s = 0.049\ncycle_spread = 0.002\n")
        }
    };
    load(&format!(
        "{}\n{sonar}[sensors.crosstalk]\nenabled = {crosstalk}\n{cycle}",
        facing.replace("seed = 2016", &format!("seed = {seed}"))
    ))
}

/// What one flight gives.
#[derive(Debug, Default)]
struct Flight {
    /// Copters that crashed (0, 1 or 2).
    crashed: u32,
    /// Of those, copters that crashed into the other copter.
    into_copter: u32,
    /// First crash: time, copter, cause.
    first: Option<(f64, usize, String)>,
    /// Sonar readings of flying copters, and those more than 0.5 m below the truth.
    readings: u64,
    short: u64,
}

fn fly(world: &World, minutes: f64) -> Flight {
    let mut state = world.initial_state();
    let inputs = world.initial_inputs();
    let mut f = Flight::default();
    for _ in 0..(minutes * 60.0 / world.params.control_dt_s).round() as u64 {
        let r = step(world, &mut state, &inputs);
        for e in &r.events {
            if let Event::Crashed { copter, cause } = e {
                f.crashed += 1;
                f.into_copter += u32::from(matches!(cause, sim_core::CrashCause::Copter { .. }));
                f.first.get_or_insert((state.time_s(world), *copter, format!("{cause:?}")));
            }
        }
        for c in state.copters.iter().filter(|c| c.crash.is_none()) {
            for k in 0..4 {
                f.readings += 1;
                if c.sensors.sonar_m[k] < c.sensors.sonar_truth_m[k] - 0.5 {
                    f.short += 1;
                }
            }
        }
    }
    f
}

/// Upper tail of the standard normal, `P(Z > z)` (Abramowitz & Stegun 7.1.26 for erfc,
/// absolute error below 1.5e-7, then exact asymptotics far out).
fn normal_upper_tail(z: f64) -> f64 {
    if z < 0.0 {
        return 1.0 - normal_upper_tail(-z);
    }
    let x = z / std::f64::consts::SQRT_2;
    if x > 5.0 {
        // erfc(x) ≈ e^{-x²} / (x √π) (1 − 1/(2x²)).
        return 0.5 * (-x * x).exp() / (x * std::f64::consts::PI.sqrt()) * (1.0 - 0.5 / (x * x));
    }
    let t = 1.0 / (1.0 + 0.327_591_1 * x);
    let poly =
        t * (0.254_829_592 + t * (-0.284_496_736 + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    0.5 * poly * (-x * x).exp()
}

/// One-sided two-proportion z-test (pooled): `P(Z ≥ z)` for H1 `p_on > p_off`.
fn two_proportion_z(k_off: u64, n_off: u64, k_on: u64, n_on: u64) -> (f64, f64) {
    let (p1, p2) = (k_off as f64 / n_off as f64, k_on as f64 / n_on as f64);
    let p = (k_off + k_on) as f64 / (n_off + n_on) as f64;
    let se = (p * (1.0 - p) * (1.0 / n_off as f64 + 1.0 / n_on as f64)).sqrt();
    let z = (p2 - p1) / se;
    (z, normal_upper_tail(z))
}

fn ln_choose(n: u64, k: u64) -> f64 {
    let lf = |m: u64| (1..=m).map(|i| (i as f64).ln()).sum::<f64>();
    lf(n) - lf(k) - lf(n - k)
}

/// One-sided Fisher exact test on a 2×2 table: `a` of `n1` flights crashed with cross-talk on,
/// `b` of `n2` with it off. P(at least `a` crashes among the `n1` on-flights | margins).
fn fisher_one_sided(a: u64, n1: u64, b: u64, n2: u64) -> f64 {
    let k = a + b;
    let n = n1 + n2;
    (a..=k.min(n1))
        .filter(|&x| k - x <= n2)
        .map(|x| (ln_choose(n1, x) + ln_choose(n2, k - x) - ln_choose(n, k)).exp())
        .sum()
}

/// Without cross-talk, estimated-state control (AHRS bias, soft height and attitude loops)
/// still lets the two copters meet now and then (slower than 0.8 m/s): measured 12 of 80
/// copter-flights on seeds 1–40 with the firmware's IR path (14 of 80 before it, 2026-11-28;
/// the change seeds 1–40 in the loop above), 6 of the 22 here. The bound: at most 8 of the 22
/// (a rate of 15 % gives more than 8 once in about 60 draws of 11 pairs), and no readings half
/// a metre short.
#[test]
fn two_copters_without_crosstalk_rarely_crash_in_five_minutes() {
    let seeds: Vec<u64> = (1..=10).chain([2016]).collect();
    // With the firmware's schedule each sonar is read every 0.2 s and averaged over three
    // readings: two copters closing on each other are seen late, and meet (reported, not
    // bounded; docs/accuracy.md).
    for (schedule, bound) in [(Schedule::FreeRunning, 8), (Schedule::Firmware, 22)] {
        let mut crashed = 0;
        for &seed in &seeds {
            let f = fly(&lab(seed, false, schedule), 5.0);
            println!(
                "{schedule:?} seed {seed:4}: crashed {} {:?}, short readings {}/{}",
                f.crashed, f.first, f.short, f.readings
            );
            crashed += f.crashed;
            assert_eq!(f.short, 0, "seed {seed}: readings 0.5 m short without cross-talk");
        }
        println!("{schedule:?}: {crashed} of {} copters crashed", 2 * seeds.len());
        assert!(crashed <= bound, "{schedule:?}: {crashed} of {} copters crashed", 2 * seeds.len());
    }
}

/// The paper's finding (VII-D): with cross-talk, copters crash into the walls, not into each
/// other. With free-running sonars it holds; with the firmware's schedule on crystal-close
/// clocks the pings of two copters rarely line up, cross-talk is rare, and what crashes there
/// is comes from the copters meeting (reported, not asserted).
#[test]
fn with_crosstalk_copters_crash_into_walls_not_into_each_other() {
    for schedule in [Schedule::FreeRunning, Schedule::Firmware] {
        let (mut crashed, mut into_copter) = (0, 0);
        for seed in 1..=12 {
            let f = fly(&lab(seed, true, schedule), 5.0);
            crashed += f.crashed;
            into_copter += f.into_copter;
        }
        println!(
            "{schedule:?}, with cross-talk: {crashed} of 24 copters crashed, {into_copter} of them into the other copter"
        );
        if let Schedule::FreeRunning = schedule {
            assert!(crashed >= 6, "cross-talk makes copters crash: {crashed}");
            assert!(into_copter * 2 < crashed, "mostly into walls: {into_copter} of {crashed} into the other copter");
        }
    }
}

#[test]
fn crosstalk_disturbs_readings_and_crashes_copters_significantly_more() {
    let minutes = 5.0;
    let seeds: Vec<u64> = (1..=10).collect();
    println!("two copters in Wall-Avoid in the lab, {minutes} min per flight; readings > 0.5 m below the truth");
    println!("  seed | off: short/readings  crashed | on: short/readings  crashed (first)");
    let (mut off_short, mut off_n, mut on_short, mut on_n) = (0u64, 0u64, 0u64, 0u64);
    let (mut off_crash, mut on_crash) = (0u64, 0u64);
    for &seed in &seeds {
        let off = fly(&lab(seed, false, Schedule::FreeRunning), minutes);
        let on = fly(&lab(seed, true, Schedule::FreeRunning), minutes);
        println!(
            "  {seed:4} | {:6}/{:6} {:5.2} %  {} | {:6}/{:6} {:5.2} %  {} {:?}",
            off.short,
            off.readings,
            100.0 * off.short as f64 / off.readings as f64,
            off.crashed,
            on.short,
            on.readings,
            100.0 * on.short as f64 / on.readings as f64,
            on.crashed,
            on.first
        );
        off_short += off.short;
        off_n += off.readings;
        on_short += on.short;
        on_n += on.readings;
        off_crash += u64::from(off.crashed > 0);
        on_crash += u64::from(on.crashed > 0);
    }
    let (z, p_rate) = two_proportion_z(off_short, off_n, on_short, on_n);
    let p_crash = fisher_one_sided(on_crash, seeds.len() as u64, off_crash, seeds.len() as u64);
    println!("            | cross-talk off          | cross-talk on");
    println!(
        "  short rate | {:8.4} % ({off_short}/{off_n}) | {:8.4} % ({on_short}/{on_n})   z = {z:.1}, one-sided p = {}",
        100.0 * off_short as f64 / off_n as f64,
        100.0 * on_short as f64 / on_n as f64,
        if p_rate > 0.0 { format!("{p_rate:.2e}") } else { "< 1e-300".into() }
    );
    println!(
        "  flights with a crash | {off_crash}/{} | {on_crash}/{}   Fisher exact one-sided p = {p_crash:.4}",
        seeds.len(),
        seeds.len()
    );
    assert!(p_rate < 1e-6, "short-reading rate not significantly higher: p = {p_rate}");
    assert!(p_crash < 0.05, "crashes not significantly more frequent: {off_crash} vs {on_crash}, p = {p_crash}");
}

#[test]
fn crosstalk_happens_only_when_the_cones_face_each_other() {
    // The paper's fourth experiment: one copter hovers, a second one stands on the floor and is
    // turned about z in 10° steps. The hovering copter is low (0.7 m) and 3 m away, so that
    // the grounded copter's sonars are within its cone (elevation ≈ 13°) and the floor's echo
    // (at 0.7 / sin 15° = 2.7 m) comes after the other's ping (d / 2 = 1.5 m, synchronous
    // sonars); it holds its place (target mode) so that only the grounded copter's yaw changes
    // between runs.
    let mut windows = Vec::new();
    let mut table = String::new();
    for step_i in 0..36 {
        let yaw_deg = 10.0 * step_i as Real;
        let world = load(&format!(
            r#"
[sim]
seed = 9

[arena]
size_m = [6.0, 4.0]
height_m = 2.5

[sensors.sonar]
schedule = "together"

[sensors.crosstalk]
enabled = true
phase = "synchronous"
cycle_s = 0.049

[[copter]]
name = "hovering"
start = {{ pos_m = [-1.5, 0.0], z_m = 0.7, yaw_deg = 0.0 }}
mode = "target"
command = {{ target_m = [-1.5, 0.0, 0.7] }}

[[copter]]
name = "grounded"
start = {{ pos_m = [1.5, 0.0], yaw_deg = {yaw_deg} }}
"#
        ));
        let mut state = world.initial_state();
        let inputs = world.initial_inputs();
        let mut events = [0u32; 4];
        let mut pings = 0u32;
        let mut drift: Real = 0.0;
        for _ in 0..100 {
            step(&world, &mut state, &inputs);
            pings += 1;
            drift = drift.max((state.pose(0).pos_m.truncate() - sim_core::math::Vec2::new(-1.5, 0.0)).length());
            for (k, hit) in state.copters[0].sensors.sonar_crosstalk.iter().enumerate() {
                events[k] += u32::from(*hit);
            }
        }
        assert!(state.copters.iter().all(|c| c.crash.is_none()));
        let total: u32 = events.iter().sum();
        table.push_str(&format!(
            "  yaw {yaw_deg:5.1}°: {total:3} of {pings} pings disturbed {events:?} (hover drift ≤ {:.0} mm)\n",
            drift * 1000.0
        ));
        if total > 0 {
            windows.push(yaw_deg);
        }
        // The grounded copter's sonar axes point at the hovering one (bearing 180°) when its
        // yaw is a multiple of 90°; the cone half-angle is 15° (less the elevation).
        let off_axis = (yaw_deg % 90.0).min(90.0 - yaw_deg % 90.0);
        if off_axis == 0.0 {
            assert!(total > 20, "yaw {yaw_deg}: facing, but only {total} disturbed readings");
        }
        if off_axis >= 25.0 {
            assert_eq!(total, 0, "yaw {yaw_deg}: cones not facing, yet {total} disturbed readings");
        }
        // Only the hovering copter's front sonar faces the grounded one.
        assert_eq!(events[1] + events[2] + events[3], 0, "{events:?}");
    }
    print!("{table}");
    println!("disturbed readings at grounded-copter yaws (deg): {windows:?}");
}
