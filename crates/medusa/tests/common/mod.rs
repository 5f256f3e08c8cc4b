//! Shared helpers for the integration tests: an independent brute-force
//! sonar simulator and a wall-avoiding copter flight.
#![allow(dead_code)]

use medusa::{
    Arena, BoxObstacle, FilterConfig, Medusa, MedusaFilter, MotionInput, SensorLayout, SensorModel, World, YawEstimate,
};
use nalgebra::Vector2;
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;

pub const ARENA_W_M: f64 = 4.0;
pub const ARENA_H_M: f64 = 3.0;
pub const MAX_RANGE_M: f64 = 3.0;
pub const SENSOR_RADIUS_M: f64 = 0.08;
pub const CONE_HALF_ANGLE_DEG: f64 = 15.0;

pub fn arena() -> Arena {
    Arena::new(ARENA_W_M, ARENA_H_M).expect("valid arena")
}

pub fn medusa(n_sensors: usize, obstacles: Vec<BoxObstacle>) -> Medusa {
    let world = World::new(arena(), obstacles).expect("valid world");
    let layout = if n_sensors == 2 {
        // Front and left: two perpendicular sonars.
        SensorLayout::new(
            [0.0f64, 90.0]
                .iter()
                .map(|deg| {
                    let a = deg.to_radians();
                    medusa::SensorSpec {
                        angle_in_body_rad: a,
                        offset_in_body_m: Vector2::new(a.cos(), a.sin()) * SENSOR_RADIUS_M,
                        max_range_m: MAX_RANGE_M,
                    }
                })
                .collect(),
        )
        .expect("layout")
    } else {
        SensorLayout::ring(n_sensors, SENSOR_RADIUS_M, MAX_RANGE_M).expect("layout")
    };
    Medusa::new(world, layout, SensorModel::default()).expect("medusa")
}

pub fn gauss(rng: &mut Pcg64) -> f64 {
    let u1: f64 = 1.0 - rng.random::<f64>();
    let u2: f64 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Brute-force centre-ray cast (independent of the crate's implementation).
fn ray_m(world: &World, o: Vector2<f64>, dir: f64) -> f64 {
    let (s, c) = dir.sin_cos();
    let a = world.arena();
    let mut best = f64::INFINITY;
    // Arena walls from inside.
    if c > 1e-12 {
        best = best.min((a.half_width_m() - o.x) / c);
    }
    if c < -1e-12 {
        best = best.min((-a.half_width_m() - o.x) / c);
    }
    if s > 1e-12 {
        best = best.min((a.half_height_m() - o.y) / s);
    }
    if s < -1e-12 {
        best = best.min((-a.half_height_m() - o.y) / s);
    }
    for b in world.obstacles() {
        let k = b.corners_in_world();
        for i in 0..4 {
            let p = k[i];
            let q = k[(i + 1) % 4];
            let e = q - p;
            let denom = c * e.y - s * e.x;
            if denom.abs() < 1e-12 {
                continue;
            }
            let ap = p - o;
            let t = (ap.x * e.y - ap.y * e.x) / denom;
            let u = (ap.x * s - ap.y * c) / denom;
            if t > 0.0 && (0.0..=1.0).contains(&u) {
                best = best.min(t);
            }
        }
    }
    best.max(0.0)
}

/// True sonar ranges by brute force: the minimum over a fan of rays
/// (edges included, so plane walls are exact).
pub fn true_ranges(world: &World, layout: &SensorLayout, pos: Vector2<f64>, yaw: f64, half_angle_rad: f64) -> Vec<f64> {
    const RAYS: usize = 24;
    let (s, c) = yaw.sin_cos();
    layout
        .sensors()
        .iter()
        .map(|spec| {
            let off = spec.offset_in_body_m;
            let o = pos + Vector2::new(c * off.x - s * off.y, s * off.x + c * off.y);
            let axis = yaw + spec.angle_in_body_rad;
            (0..=RAYS)
                .map(|k| {
                    let f = if RAYS == 0 { 0.0 } else { k as f64 / RAYS as f64 };
                    ray_m(world, o, axis - half_angle_rad + 2.0 * half_angle_rad * f)
                })
                .fold(f64::INFINITY, f64::min)
        })
        .collect()
}

/// Turn true ranges into sensor readings: add noise, report `None` at or
/// beyond the max range.
pub fn noisy_readings(ranges: &[f64], sigma_m: f64, rng: &mut Pcg64) -> Vec<Option<f64>> {
    ranges
        .iter()
        .map(|&r| {
            let z = (r + sigma_m * gauss(rng)).max(0.0);
            if r >= MAX_RANGE_M || z >= MAX_RANGE_M { None } else { Some(z) }
        })
        .collect()
}

pub fn exact_readings(ranges: &[f64]) -> Vec<Option<f64>> {
    ranges.iter().map(|&r| if r >= MAX_RANGE_M { None } else { Some(r) }).collect()
}

/// How the true yaw behaves during a flight.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum YawMode {
    /// The pilot holds the heading (the FINken's usual mode): small wobble.
    Held,
    /// The heading wanders over all angles (harder: oblique walls, corners).
    Wandering,
}

#[derive(Debug, Default, Clone)]
pub struct FlightStats {
    pub raw_err_m: Vec<f64>,
    pub refined_err_m: Vec<f64>,
    pub filt_err_m: Vec<f64>,
    pub filt_conf: Vec<f64>,
    pub bias_err_rad: Vec<f64>,
    pub filter_time_s: f64,
    pub raw_time_s: f64,
    pub updates: usize,
}

pub fn percentile(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    if s.is_empty() {
        return f64::NAN;
    }
    let idx = ((s.len() - 1) as f64 * q).round() as usize;
    s[idx]
}

/// Fly a wall-avoiding copter for `duration_s` and run raw MEDUSA and the
/// filter on its readings. The copter's true dynamics differ from the
/// filter's model (attitude lag, drag, gusts).
pub fn fly(
    n_sensors: usize,
    obstacles: Vec<BoxObstacle>,
    yaw_mode: YawMode,
    duration_s: f64,
    seed: u64,
    run_raw: bool,
) -> FlightStats {
    fly_with(n_sensors, obstacles, yaw_mode, duration_s, seed, run_raw, FilterConfig::default())
}

/// As [`fly`] with an explicit filter configuration (its seed is overridden).
pub fn fly_with(
    n_sensors: usize,
    obstacles: Vec<BoxObstacle>,
    yaw_mode: YawMode,
    duration_s: f64,
    seed: u64,
    run_raw: bool,
    config: FilterConfig,
) -> FlightStats {
    const DT_S: f64 = 0.05; // 20 Hz sonar cycle
    const G: f64 = 9.806_65;
    const BODY_RADIUS_M: f64 = 0.12;
    let m = medusa(n_sensors, obstacles.clone());
    let world = m.world().clone();
    let layout = m.layout().clone();
    let cone = CONE_HALF_ANGLE_DEG.to_radians();
    let sigma_m = 0.05;
    let yaw_noise_rad = 2f64.to_radians();
    let mut filter = MedusaFilter::new(m.clone(), FilterConfig { seed: seed ^ 0x5eed, ..config }).expect("filter");
    let mut rng = Pcg64::seed_from_u64(seed);

    // True state.
    let mut pos = Vector2::new(-1.0, 0.4);
    let mut vel = Vector2::zeros();
    let mut yaw = 0.3f64;
    let yaw_hold = yaw;
    let mut yaw_rate = 0.0f64;
    let mut att = Vector2::zeros(); // actual (pitch, roll)
    let mut bias = 3f64.to_radians() * gauss(&mut rng);
    let mut heading = rng.random::<f64>() * std::f64::consts::TAU;
    let mut gust = Vector2::zeros();

    let steps = (duration_s / DT_S).round() as usize;
    let mut stats = FlightStats::default();
    let mut cmd = MotionInput::zero();
    let mut last_readings: Vec<Option<f64>> = vec![None; layout.len()];
    for step in 0..steps {
        // --- Controller (uses the noisy readings, like the real Wall-Avoid).
        heading += 0.6 * DT_S.sqrt() * gauss(&mut rng);
        let wander = Vector2::new(heading.cos(), heading.sin()) * 0.6;
        let mut repulse = Vector2::zeros();
        let (s, c) = yaw.sin_cos();
        for (spec, r) in layout.sensors().iter().zip(&last_readings) {
            if let Some(r) = r
                && *r < 0.8
            {
                let a = yaw + spec.angle_in_body_rad;
                repulse -= Vector2::new(a.cos(), a.sin()) * (0.8 - r) * 4.0;
            }
        }
        let mut acc_w = (wander - vel) * 1.5 + repulse;
        let a_max = G * 12f64.to_radians().tan();
        if acc_w.norm() > a_max {
            acc_w *= a_max / acc_w.norm();
        }
        let acc_b = Vector2::new(c * acc_w.x + s * acc_w.y, -s * acc_w.x + c * acc_w.y);
        let pitch_cmd = (acc_b.x / G).atan();
        let roll_cmd = (-acc_b.y / G).atan();
        cmd = MotionInput::from_attitude(pitch_cmd, roll_cmd);

        // --- True dynamics.
        att += (Vector2::new(pitch_cmd, roll_cmd) - att) * (DT_S / 0.15);
        gust += -gust * (DT_S / 1.0) + Vector2::new(gauss(&mut rng), gauss(&mut rng)) * 0.4 * DT_S.sqrt();
        let a_body = Vector2::new(G * att.x.tan(), -G * att.y.tan());
        let a_world = Vector2::new(c * a_body.x - s * a_body.y, s * a_body.x + c * a_body.y) - vel * 0.4 + gust;
        vel += a_world * DT_S;
        pos += vel * DT_S;
        let lim = Vector2::new(ARENA_W_M / 2.0 - BODY_RADIUS_M, ARENA_H_M / 2.0 - BODY_RADIUS_M);
        if pos.x.abs() > lim.x {
            pos.x = pos.x.clamp(-lim.x, lim.x);
            vel.x *= -0.3;
        }
        if pos.y.abs() > lim.y {
            pos.y = pos.y.clamp(-lim.y, lim.y);
            vel.y *= -0.3;
        }
        for b in &obstacles {
            if b.contains(&pos, BODY_RADIUS_M) {
                // Bounce back out of the box.
                pos -= vel * DT_S;
                vel = -vel * 0.3;
            }
        }
        match yaw_mode {
            YawMode::Held => {
                yaw_rate += (-(yaw - yaw_hold) * 2.0 - yaw_rate * 2.0) * DT_S + 0.15 * DT_S.sqrt() * gauss(&mut rng);
            }
            YawMode::Wandering => {
                yaw_rate += -yaw_rate * 0.5 * DT_S + 0.3 * DT_S.sqrt() * gauss(&mut rng);
            }
        }
        yaw += yaw_rate * DT_S;
        bias += 0.5f64.to_radians() * DT_S.sqrt() * gauss(&mut rng);

        // --- Sensing.
        let ranges = true_ranges(&world, &layout, pos, yaw, cone);
        let readings = noisy_readings(&ranges, sigma_m, &mut rng);
        let yaw_est = YawEstimate::new(yaw + bias + yaw_noise_rad * gauss(&mut rng), yaw_noise_rad);
        last_readings = readings.clone();

        // --- Estimation.
        let t0 = std::time::Instant::now();
        let est = filter.update(DT_S, &cmd, yaw_est, &readings).expect("valid update");
        stats.filter_time_s += t0.elapsed().as_secs_f64();
        if run_raw {
            let t1 = std::time::Instant::now();
            let raw = m.locate(yaw_est, &readings).expect("valid locate");
            stats.raw_time_s += t1.elapsed().as_secs_f64();
            stats.raw_err_m.push((raw.best.pos_in_world - pos).norm());
            stats.refined_err_m.push((raw.refined.pos_in_world - pos).norm());
        }
        stats.updates += 1;
        assert!(est.pos_in_world.x.is_finite() && est.pos_in_world.y.is_finite());
        assert!((0.0..=1.0).contains(&est.confidence));
        // Skip the first 2 s (global localisation from a uniform prior).
        if step as f64 * DT_S >= 2.0 {
            stats.filt_err_m.push((est.pos_in_world - pos).norm());
            stats.filt_conf.push(est.confidence);
            stats.bias_err_rad.push(est.yaw_bias_rad - bias);
        }
    }
    let _ = cmd;
    stats
}
