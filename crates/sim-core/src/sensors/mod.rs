//! Sensor models: four MB1232 sonars (exact cone geometry, Gaussian noise, centimetre
//! quantisation, cross-talk between copters), the Sharp GP2Y0A60SZLF IR height sensor and the
//! IMU/AHRS with a drifting yaw bias.
//!
//! **Sonar order** is `[front, right, back, left]` (body +x, −y, −x, +y), the order of
//! Paparazzi's `SONAR_ARRAY`. The original V-REP `sensor_dist` signal used front, left, back,
//! right; [`SONAR_NAMES`] keeps the mapping explicit.

use serde::{Deserialize, Serialize};

pub mod ir;
pub use ir::IrSpec;

use crate::control::WallAvoidSpec;
use crate::error::{FieldPath, PathSeg, SceneError};
use crate::estimate::EstimatorSpec;
use crate::geometry::{Cone, OrientedBox, Wedge, cone_box_distance, ray_box};
use crate::math::{Quat, Real, Vec3};

/// Sonar names in reading order.
pub const SONAR_NAMES: [&str; 4] = ["front", "right", "back", "left"];
/// Sonar axes in the body frame (FLU), in reading order.
pub const SONAR_AXES_IN_BODY: [Vec3; 4] = [Vec3::X, Vec3::NEG_Y, Vec3::NEG_X, Vec3::Y];

/// When copters' sonars ping, which sets what a cross-talk ping reads as.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CrosstalkPhase {
    /// Every sonar pings at the same instants: a ping from `d_AB` away reads `d_AB / 2`.
    Synchronous,
    /// Each copter's MB1232s run free on their own cycle (nominally 49 ms, each copter's
    /// oscillator a little off), from a seeded phase: the phases drift against each other,
    /// and a foreign ping reads `c Δt / 2` with `Δt` its arrival after the listener's own ping.
    #[default]
    FreeRunning,
}

/// Which sonars a sonar update reads.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SonarSchedule {
    /// The FINken firmware's (`sonar_array_i2c`): one sonar per update, round robin (front,
    /// right, back, left), so each is read every fourth update (with cross-talk `cycle_s`
    /// 0.2, crystal-close `cycle_spread` 0.00005, the defaults).
    #[default]
    RoundRobin,
    /// All four at every update (free-running sonars; with cross-talk `cycle_s` 0.049).
    Together,
}

/// `[sensors.sonar]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SonarSpec {
    /// Full opening angle of the cone, deg.
    pub opening_deg: Real,
    /// Shortest distance the sonar reports, m.
    pub min_range_m: Real,
    /// Longest distance it detects, m.
    pub max_range_m: Real,
    /// Readings are capped here, m; also the no-echo value.
    pub cap_m: Real,
    /// Standard deviation of the zero-mean Gaussian noise, m.
    pub noise_sigma_m: Real,
    /// Readings are rounded to multiples of this, m (Paparazzi's `SONAR_ARRAY` is in cm).
    pub quantum_m: Real,
    /// Distance of each sonar from the centre of the body, m.
    pub mount_offset_m: Real,
    /// A sonar update every this many control steps.
    pub period_steps: u32,
    /// Which sonars an update reads.
    pub schedule: SonarSchedule,
    /// Whether the floor and the ceiling echo when they lie inside a cone.
    pub floor_echo: bool,
}

impl Default for SonarSpec {
    fn default() -> Self {
        Self {
            opening_deg: 30.0,
            min_range_m: 0.20,
            max_range_m: 7.65,
            cap_m: 7.65,
            noise_sigma_m: 0.02,
            quantum_m: 0.01,
            mount_offset_m: 0.05,
            period_steps: 1,
            schedule: SonarSchedule::RoundRobin,
            floor_echo: true,
        }
    }
}

/// `[sensors.imu]`: the AHRS estimate and raw IMU noise.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ImuSpec {
    /// Roll and pitch estimate noise, deg.
    pub attitude_noise_deg: Real,
    /// Yaw estimate noise, deg.
    pub yaw_noise_deg: Real,
    /// Random walk of the yaw bias, deg per √s.
    pub yaw_bias_walk_deg_per_sqrt_s: Real,
    /// The yaw bias reverts to zero with this time constant, s: the AHRS pulls its heading
    /// back to the magnetometer's (a Gauss–Markov process; its spread is
    /// `walk · √(time / 2)`). 0: an unbounded random walk.
    pub yaw_bias_time_s: Real,
    /// Gyro noise, deg/s.
    pub rate_noise_deg_s: Real,
    /// Accelerometer noise, m/s².
    pub accel_noise_m_s2: Real,
}

impl Default for ImuSpec {
    fn default() -> Self {
        Self {
            attitude_noise_deg: 1.5,
            yaw_noise_deg: 2.0,
            yaw_bias_walk_deg_per_sqrt_s: 0.5,
            // Paparazzi's AHRS_MAG_OMEGA 0.04 rad/s, ζ 0.9: 1 / (ζ ω) = 27.8 s.
            yaw_bias_time_s: 27.8,
            rate_noise_deg_s: 0.5,
            accel_noise_m_s2: 0.05,
        }
    }
}

/// `[sensors.crosstalk]`: a ping of one copter's sonar heard by another copter's sonar whose
/// cone faces it, within range, arriving after the listener's own ping and before its echo.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CrosstalkSpec {
    /// Whether pings of one copter can be heard by another's sonars (every real FINken swarm
    /// has it).
    pub enabled: bool,
    /// How pings are timed.
    pub phase: CrosstalkPhase,
    /// Nominal ping cycle of each sonar, s: with the firmware's round robin one sonar per
    /// 50 ms tick, 0.2 s; free-running sonars pinging together, 0.049 s.
    pub cycle_s: Real,
    /// Standard deviation of each copter's cycle, relative (its oscillator's tolerance).
    pub cycle_spread: Real,
    /// Speed of sound, m/s.
    pub speed_of_sound_m_s: Real,
}

impl Default for CrosstalkSpec {
    fn default() -> Self {
        Self {
            enabled: true,
            phase: CrosstalkPhase::FreeRunning,
            cycle_s: 0.2,
            // The ping schedule is timed by the autopilot's crystal (tens of ppm).
            cycle_spread: 0.00005,
            speed_of_sound_m_s: 343.0,
        }
    }
}

/// `[sensors]`: all sensor models.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SensorSpec {
    /// Whether sensors are simulated at all (off: readings stay at their initial values;
    /// Wall-Avoid then sees nothing).
    #[serde(default = "yes")]
    pub enabled: bool,
    /// Whether noise is applied (off: readings are the noise-free truth, still quantised).
    #[serde(default = "yes")]
    pub noise: bool,
    /// Sonars.
    pub sonar: SonarSpec,
    /// IR height sensor.
    pub ir: IrSpec,
    /// IMU/AHRS.
    pub imu: ImuSpec,
    /// Sonar cross-talk.
    pub crosstalk: CrosstalkSpec,
    /// Estimators between these sensors and the controllers.
    pub estimator: EstimatorSpec,
    /// Wall-Avoid behaviour (it runs on these sensors).
    pub wall_avoid: WallAvoidSpec,
}

impl Default for SensorSpec {
    fn default() -> Self {
        Self {
            enabled: true,
            noise: true,
            sonar: SonarSpec::default(),
            ir: IrSpec::default(),
            imu: ImuSpec::default(),
            crosstalk: CrosstalkSpec::default(),
            estimator: EstimatorSpec::default(),
            wall_avoid: WallAvoidSpec::default(),
        }
    }
}

fn yes() -> bool {
    true
}

/// Compiled sensor parameters (radians, cosines, SI).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SensorParams {
    /// The spec compiled from.
    pub spec: SensorSpec,
    /// Sonar half-angle, rad.
    pub sonar_half_angle_rad: Real,
    /// cos of the sonar half-angle.
    pub sonar_cos_half: Real,
    /// sin of the sonar half-angle.
    pub sonar_sin_half: Real,
}

impl SensorSpec {
    pub(crate) fn compile(&self, path: &FieldPath) -> Result<SensorParams, SceneError> {
        let err = |sub: &str, field: &str, message: String| {
            let mut p = path.clone();
            p.0.push(PathSeg::Key(sub.into()));
            p.0.push(PathSeg::Key(field.into()));
            SceneError::Invalid { origin: String::new(), location: None, path: p, message }
        };
        let s = &self.sonar;
        for (field, v) in [
            ("opening_deg", s.opening_deg),
            ("min_range_m", s.min_range_m),
            ("max_range_m", s.max_range_m),
            ("cap_m", s.cap_m),
            ("quantum_m", s.quantum_m),
        ] {
            if !v.is_finite() || v <= 0.0 {
                return Err(err("sonar", field, format!("must be positive and finite, got {v}")));
            }
        }
        for (field, v) in [("noise_sigma_m", s.noise_sigma_m), ("mount_offset_m", s.mount_offset_m)] {
            if !v.is_finite() || v < 0.0 {
                return Err(err("sonar", field, format!("must be finite and not negative, got {v}")));
            }
        }
        if s.opening_deg >= 180.0 {
            return Err(err("sonar", "opening_deg", format!("must be below 180, got {}", s.opening_deg)));
        }
        if s.min_range_m >= s.max_range_m {
            return Err(err(
                "sonar",
                "min_range_m",
                format!("must be below max_range_m = {}, got {}", s.max_range_m, s.min_range_m),
            ));
        }
        if s.period_steps == 0 {
            return Err(err("sonar", "period_steps", "must be at least 1".into()));
        }
        let ir = &self.ir;
        for (field, v) in [("min_range_m", ir.min_range_m), ("max_range_m", ir.max_range_m)] {
            if !v.is_finite() || v <= 0.0 {
                return Err(err("ir", field, format!("must be positive and finite, got {v}")));
            }
        }
        if ir.min_range_m >= ir.max_range_m {
            return Err(err("ir", "min_range_m", format!("must be below max_range_m = {}", ir.max_range_m)));
        }
        for (field, v) in [("noise_sigma_m", ir.noise_sigma_m), ("noise_sigma_rel", ir.noise_sigma_rel)] {
            if !v.is_finite() || v < 0.0 {
                return Err(err("ir", field, format!("must be finite and not negative, got {v}")));
            }
        }
        let imu = &self.imu;
        for (field, v) in [
            ("attitude_noise_deg", imu.attitude_noise_deg),
            ("yaw_noise_deg", imu.yaw_noise_deg),
            ("yaw_bias_walk_deg_per_sqrt_s", imu.yaw_bias_walk_deg_per_sqrt_s),
            ("yaw_bias_time_s", imu.yaw_bias_time_s),
            ("rate_noise_deg_s", imu.rate_noise_deg_s),
            ("accel_noise_m_s2", imu.accel_noise_m_s2),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(err("imu", field, format!("must be finite and not negative, got {v}")));
            }
        }
        let ct = &self.crosstalk;
        for (field, v) in [("cycle_s", ct.cycle_s), ("speed_of_sound_m_s", ct.speed_of_sound_m_s)] {
            if !v.is_finite() || v <= 0.0 {
                return Err(err("crosstalk", field, format!("must be positive and finite, got {v}")));
            }
        }
        if !(0.0..0.5).contains(&ct.cycle_spread) {
            return Err(err("crosstalk", "cycle_spread", format!("must be in [0, 0.5), got {}", ct.cycle_spread)));
        }
        let mut est_path = path.clone();
        est_path.0.push(PathSeg::Key("estimator".into()));
        self.estimator.validate(&est_path)?;
        let w = &self.wall_avoid;
        if !(w.filter_max_m > w.filter_min_m && w.filter_max_m.is_finite()) {
            let msg = format!("must be finite and above filter_min_m = {}, got {}", w.filter_min_m, w.filter_max_m);
            return Err(err("wall_avoid", "filter_max_m", msg));
        }
        for (field, v) in [
            ("gain_deg_per_m", w.gain_deg_per_m),
            ("delay_time_s", w.delay_time_s),
            ("hold_time_s", w.hold_time_s),
            ("update_hz", w.update_hz),
            ("max_control_deg", w.max_control_deg),
        ] {
            if !v.is_finite() || v <= 0.0 {
                return Err(err("wall_avoid", field, format!("must be positive and finite, got {v}")));
            }
        }
        if !(1..=crate::control::SONAR_FILTER_MAX_LEN as u32).contains(&w.filter_len) {
            let max = crate::control::SONAR_FILTER_MAX_LEN;
            return Err(err("wall_avoid", "filter_len", format!("must be 1 to {max}, got {}", w.filter_len)));
        }
        for (field, v) in [
            ("filter_min_m", w.filter_min_m),
            ("guard_distance_m", w.guard_distance_m),
            ("safety_distance_m", w.safety_distance_m),
            ("kp_deg_per_m", w.kp_deg_per_m),
            ("kd_deg_s_per_m", w.kd_deg_s_per_m),
            ("max_tilt_deg", w.max_tilt_deg),
            ("rate_filter_s", w.rate_filter_s),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(err("wall_avoid", field, format!("must be finite and not negative, got {v}")));
            }
        }
        let half = (s.opening_deg / 2.0).to_radians();
        Ok(SensorParams {
            spec: self.clone(),
            sonar_half_angle_rad: half,
            sonar_cos_half: half.cos(),
            sonar_sin_half: half.sin(),
        })
    }
}

/// One copter's latest sensor readings.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SensorReadings {
    /// Tick of the last sonar update.
    pub sonar_tick: u64,
    /// Noise-free distance to the nearest object in each cone, capped, m (front, right, back, left).
    pub sonar_truth_m: [Real; 4],
    /// Physical reading: truth + noise (+ cross-talk), clamped, quantised, m.
    pub sonar_m: [Real; 4],
    /// Whether cross-talk shortened each reading in the last update.
    pub sonar_crosstalk: [bool; 4],
    /// What the copter's behaviour uses: `min(physical, virtual)` when a virtual reading is
    /// supplied, else the physical reading, m.
    pub sonar_fused_m: [Real; 4],
    /// IR distance along the body's −z axis, m; `None` when out of range (flagged, not faked).
    pub ir_m: Option<Real>,
    /// Noise-free IR distance, m (may be out of range).
    pub ir_truth_m: Real,
    /// The height estimate the height loop holds (from the IR), m.
    pub height_est_m: Real,
    /// Battery terminal voltage, V (what the autopilot's ADC reads).
    pub battery_v: Real,
    /// Battery state of charge, in [0, 1].
    pub battery_charge: Real,
    /// Battery current, A.
    pub battery_a: Real,
    /// AHRS attitude estimate: roll, pitch, yaw (yaw includes the drifting bias), rad: what the
    /// attitude loop read last.
    pub attitude_rad: [Real; 3],
    /// Current yaw bias, rad.
    pub yaw_bias_rad: Real,
    /// Gyro: body rates, rad/s.
    pub rate_body_rad_s: [Real; 3],
    /// Accelerometer: specific force in the body frame, m/s².
    pub accel_body_m_s2: [Real; 3],
}

/// What a sonar can see, gathered once per control step for all copters.
#[derive(Clone, Debug, Default)]
pub struct SonarScene {
    /// Inward unit normals and offsets of the arena walls (`n·x = c`).
    pub walls: Vec<(Vec3, Real)>,
    /// Static boxes.
    pub boxes: Vec<OrientedBox>,
    /// Copter bodies, by id (crashed ones included: they are still there).
    pub copters: Vec<OrientedBox>,
    /// A uniform grid over the copters, rebuilt by [`SonarScene::index_copters`].
    pub grid: CopterGrid,
}

/// A uniform 2D grid of copter ids by the cell of their centre: sonars and cross-talk visit
/// cells in rings of growing distance and stop once no closer copter can exist. Rebuilt each
/// sensing step with a counting sort into reused buffers (no allocation once warm).
#[derive(Clone, Debug, Default)]
pub struct CopterGrid {
    min: [Real; 2],
    cell_m: Real,
    nx: usize,
    ny: usize,
    starts: Vec<u32>,
    items: Vec<u32>,
    /// Each item's centre on the floor, in the order of `items`.
    floor_xy: Vec<[Real; 2]>,
    cells: Vec<u32>,
    cursor: Vec<u32>,
    max_radius_m: Real,
    built_for: usize,
    /// A rectangle (x0, y0, x1, y1) the grid always covers, whatever the items' span.
    cover: Option<[Real; 4]>,
}

impl CopterGrid {
    /// Cells per axis at most (bounds memory for sparse, huge arenas).
    const MAX_CELLS_PER_AXIS: usize = 1024;

    /// Makes every later [`CopterGrid::build`] cover the rectangle `[x0, y0, x1, y1]` (the
    /// arena) as well as its items: the grid's size then stays the same from step to step, so
    /// rebuilding it never allocates once it has been built.
    pub fn set_cover(&mut self, rect: [Real; 4]) {
        self.cover = Some(rect);
    }

    /// Indexes `boxes` by the cell of their centre; the ids are their indices.
    pub fn build(&mut self, boxes: &[OrientedBox], cell_m: Real) {
        let max_radius_m = boxes.iter().map(OrientedBox::bounding_radius).fold(0.0, Real::max);
        self.build_from(boxes.len(), |k| (k as u32, boxes[k].center), max_radius_m, cell_m);
    }

    /// Indexes only the boxes whose ids are in `ids` (ascending): each cell lists them in the
    /// order [`CopterGrid::build`] would, without the others.
    pub fn build_some(&mut self, boxes: &[OrientedBox], ids: &[u32], cell_m: Real) {
        let max_radius_m = ids.iter().map(|&i| boxes[i as usize].bounding_radius()).fold(0.0, Real::max);
        self.build_from(ids.len(), |k| (ids[k], boxes[ids[k] as usize].center), max_radius_m, cell_m);
        self.built_for = boxes.len();
    }

    /// Indexes items by their centres before their sizes are known: the ids in `ids`
    /// (ascending) or, without, `0..n`, each at `centre(id)`; cells list them as
    /// [`CopterGrid::build`] and [`CopterGrid::build_some`] would. [`CopterGrid::set_max_radius`]
    /// must follow before the grid is visited.
    pub fn build_centres(&mut self, n: usize, ids: Option<&[u32]>, centre: impl Fn(usize) -> Vec3, cell_m: Real) {
        match ids {
            Some(ids) => self.build_from(ids.len(), |k| (ids[k], centre(ids[k] as usize)), 0.0, cell_m),
            None => self.build_from(n, |k| (k as u32, centre(k)), 0.0, cell_m),
        }
        self.built_for = n;
    }

    /// The largest bounding radius of the items [`CopterGrid::build_centres`] indexed, m.
    pub fn set_max_radius(&mut self, radius_m: Real) {
        self.max_radius_m = radius_m;
    }

    /// Indexes points `(id, position)` (bounding radius 0). With `points` in ascending id
    /// order, each cell lists its ids ascending, as [`CopterGrid::build`] does.
    pub fn build_points(&mut self, points: &[(u32, Vec3)], cell_m: Real) {
        self.build_from(points.len(), |k| points[k], 0.0, cell_m);
    }

    fn build_from(&mut self, n: usize, item: impl Fn(usize) -> (u32, Vec3), max_radius_m: Real, cell_m: Real) {
        self.built_for = n;
        self.max_radius_m = max_radius_m;
        let (mut lo, mut hi) = match self.cover {
            Some([x0, y0, x1, y1]) => ([x0, y0], [x1, y1]),
            None => ([Real::MAX; 2], [Real::MIN; 2]),
        };
        for k in 0..n {
            let p = item(k).1;
            lo = [lo[0].min(p.x), lo[1].min(p.y)];
            hi = [hi[0].max(p.x), hi[1].max(p.y)];
        }
        if n == 0 && self.cover.is_none() {
            (lo, hi) = ([0.0; 2], [0.0; 2]);
        }
        let span = (hi[0] - lo[0]).max(hi[1] - lo[1]);
        self.cell_m = cell_m.max(span / Self::MAX_CELLS_PER_AXIS as Real).max(1e-3);
        self.min = lo;
        self.nx = ((hi[0] - lo[0]) / self.cell_m) as usize + 1;
        self.ny = ((hi[1] - lo[1]) / self.cell_m) as usize + 1;
        let n_cells = self.nx * self.ny;
        self.starts.clear();
        self.starts.resize(n_cells + 1, 0);
        self.cells.clear();
        for k in 0..n {
            let (ix, iy) = self.cell_of(item(k).1);
            let c = (iy as usize) * self.nx + ix as usize;
            self.cells.push(c as u32);
            self.starts[c + 1] += 1;
        }
        for c in 0..n_cells {
            self.starts[c + 1] += self.starts[c];
        }
        self.items.clear();
        self.items.resize(n, 0);
        self.floor_xy.clear();
        self.floor_xy.resize(n, [0.0; 2]);
        // Fill in item order, so each cell lists its items in that order.
        self.cursor.clear();
        self.cursor.extend_from_slice(&self.starts[..n_cells]);
        for (k, &c) in self.cells.iter().enumerate() {
            let slot = &mut self.cursor[c as usize];
            let (id, at) = item(k);
            self.items[*slot as usize] = id;
            self.floor_xy[*slot as usize] = [at.x, at.y];
            *slot += 1;
        }
    }

    #[inline]
    fn cell_of(&self, p: Vec3) -> (isize, isize) {
        // floor(), without a libm call: the truncation, one less below zero.
        let floor = |v: Real| {
            let t = v as isize;
            t.saturating_sub(isize::from((t as Real) > v))
        };
        let ix = floor((p.x - self.min[0]) / self.cell_m);
        let iy = floor((p.y - self.min[1]) / self.cell_m);
        (ix.clamp(-1, self.nx as isize), iy.clamp(-1, self.ny as isize))
    }

    /// Visits copter ids in rings of cells around `p`, nearest rings first. `visit` gets each
    /// id and returns the current search radius (m): rings that cannot hold anything closer
    /// are not visited.
    pub fn visit_near(&self, p: Vec3, radius_m: Real, visit: impl FnMut(usize) -> Real) {
        self.visit_near_over(p, radius_m, None, visit);
    }

    /// [`CopterGrid::visit_near`] of only the items that may lie over `wedge` grown by the
    /// `Real` (m) that comes with it (an item lies within the grid's bounding radius of its
    /// centre), in the same order otherwise.
    pub fn visit_near_over(
        &self,
        p: Vec3,
        radius_m: Real,
        wedge: Option<(&Wedge, Real)>,
        visit: impl FnMut(usize) -> Real,
    ) {
        if self.nx == 0 {
            return;
        }
        let cells = self.cells_over(wedge, radius_m);
        self.visit_rings(p, radius_m, cells, wedge, visit);
    }

    /// [`CopterGrid::visit_near`] of only the items whose centre may lie within the grid's
    /// bounding radius of the floor rectangle `[x0, y0, x1, y1]`, in the same order otherwise.
    pub fn visit_near_within(&self, p: Vec3, radius_m: Real, rect: [Real; 4], visit: impl FnMut(usize) -> Real) {
        if self.nx == 0 {
            return;
        }
        let cells = self.cells_in(rect, self.max_radius_m + 1e-3);
        self.visit_rings(p, radius_m, cells, None, visit);
    }

    /// The rings of [`CopterGrid::visit_near_over`] within the cells `[x0, y0, x1, y1]`.
    fn visit_rings(
        &self,
        p: Vec3,
        mut radius_m: Real,
        [x0, y0, x1, y1]: [isize; 4],
        wedge: Option<(&Wedge, Real)>,
        mut visit: impl FnMut(usize) -> Real,
    ) {
        let (cx, cy) = self.cell_of(p);
        let max_ring = self.nx.max(self.ny) as isize + 2;
        for r in 0..=max_ring {
            let ring_min = (r as Real - 1.0).max(0.0) * self.cell_m - self.max_radius_m;
            if ring_min > radius_m {
                break;
            }
            for iy in (cy - r).max(y0)..=(cy + r).min(y1) {
                // The ring's cells in this row: all of an edge row, the two ends of the others.
                let (from, to) = ((cx - r).max(x0), (cx + r).min(x1));
                let step = if iy == cy - r || iy == cy + r || r == 0 { 1 } else { 2 * r };
                let mut ix = if step == 1 { from } else { cx - r };
                while ix <= to {
                    if ix >= from {
                        self.visit_cell(ix, iy, wedge, |k| radius_m = visit(k));
                    }
                    ix += step;
                }
            }
        }
    }

    /// Visits the ids of the items that may lie over `wedge` grown by the `Real` (m) that
    /// comes with it, in the cells that may hold one within `radius_m` of `p`, row by row.
    pub fn visit_over(&self, p: Vec3, radius_m: Real, wedge: (&Wedge, Real), mut visit: impl FnMut(usize)) {
        if self.nx == 0 {
            return;
        }
        let [x0, y0, x1, y1] = self.cells_over(Some(wedge), radius_m);
        let [x0, y0, x1, y1] = {
            let r = radius_m + self.max_radius_m;
            let (lo, hi) = (self.cell_of(p - Vec3::new(r, r, 0.0)), self.cell_of(p + Vec3::new(r, r, 0.0)));
            [x0.max(lo.0), y0.max(lo.1), x1.min(hi.0), y1.min(hi.1)]
        };
        let (w, grow) = wedge;
        let reach = self.max_radius_m + grow;
        // Columns by a multiplication: a millimetre and a thousandth of a cell wider than
        // `x_range`, which covers the rounding of the multiplication and of `cell_of`'s division.
        let per_m = 1.0 / self.cell_m;
        let pad = 1e-3 + 1e-3 * self.cell_m;
        let column = |x: Real| ((x - self.min[0]) * per_m).clamp(-1.0, self.nx as Real) as isize;
        for iy in y0..=y1 {
            // The row's cells whose items may lie over the wedge.
            let row = |i: isize| self.min[1] + i as Real * self.cell_m;
            let (a, b) = w.x_range(row(iy) - 1e-3, row(iy + 1) + 1e-3, reach);
            let (a, b) = (column(a - pad), column(b + pad));
            for ix in a.max(x0)..=b.min(x1) {
                self.visit_cell(ix, iy, Some(wedge), &mut visit);
            }
        }
    }

    /// The range of cells `[x0, y0, x1, y1]` (inclusive, within the grid) that may hold an item
    /// within `radius_m` of the apex of `wedge` grown by the `Real` that comes with it (all
    /// cells without a wedge).
    fn cells_over(&self, wedge: Option<(&Wedge, Real)>, radius_m: Real) -> [isize; 4] {
        let (nx, ny) = (self.nx as isize, self.ny as isize);
        let Some((w, grow)) = wedge else { return [0, 0, nx - 1, ny - 1] };
        let m = grow + self.max_radius_m + self.cell_m;
        self.cells_in(w.bounds(radius_m + m), m)
    }

    /// The range of cells `[x0, y0, x1, y1]` (inclusive, within the grid) over the floor
    /// rectangle `[x0, y0, x1, y1]` grown by `m` on every side.
    fn cells_in(&self, [a, b, c, d]: [Real; 4], m: Real) -> [isize; 4] {
        let (nx, ny) = (self.nx as isize, self.ny as isize);
        let (lo, hi) = (self.cell_of(Vec3::new(a - m, b - m, 0.0)), self.cell_of(Vec3::new(c + m, d + m, 0.0)));
        [lo.0.max(0), lo.1.max(0), hi.0.min(nx - 1), hi.1.min(ny - 1)]
    }

    /// Visits the ids of cell `(ix, iy)` (within the grid) that may lie over `wedge`.
    #[inline]
    fn visit_cell(&self, ix: isize, iy: isize, wedge: Option<(&Wedge, Real)>, mut visit: impl FnMut(usize)) {
        let c = iy as usize * self.nx + ix as usize;
        let (start, end) = (self.starts[c] as usize, self.starts[c + 1] as usize);
        let Some((w, grow)) = wedge else {
            // No wedge: every item, without reading their floor positions.
            self.items[start..end].iter().for_each(|&id| visit(id as usize));
            return;
        };
        for (&id, &[x, y]) in self.items[start..end].iter().zip(&self.floor_xy[start..end]) {
            if w.meets_disc(x, y, self.max_radius_m + grow) {
                visit(id as usize);
            }
        }
    }
}

impl SonarScene {
    /// Indexes the copters for fast neighbour queries. Call after filling `copters`.
    pub fn index_copters(&mut self, cell_m: Real) {
        self.grid.build(&self.copters, cell_m);
    }

    /// [`SonarScene::index_copters`] for only the copters in `ids` (ascending): the others are
    /// not seen (a shard's absent copters).
    pub fn index_some_copters(&mut self, ids: &[u32], cell_m: Real) {
        self.grid.build_some(&self.copters, ids, cell_m);
    }

    /// Distance from a sonar to the nearest object in its cone, ignoring copter `self_id`.
    /// `f32::INFINITY` if nothing is inside the cone within `max_range_m`.
    pub fn cone_distance(&self, cone: &Cone, self_id: usize, max_range_m: Real) -> Real {
        let (mut best, mut hit) = self.static_cone_distance(cone, max_range_m);
        if self.grid.built_for == self.copters.len() && !self.copters.is_empty() {
            self.grid.visit_near(cone.apex, best, |id| {
                if id != self_id {
                    consider_box(cone, &self.copters[id], &mut best, &mut hit);
                }
                best
            });
        } else {
            for (id, b) in self.copters.iter().enumerate() {
                if id != self_id {
                    consider_box(cone, b, &mut best, &mut hit);
                }
            }
        }
        if hit { best } else { Real::INFINITY }
    }

    /// [`SonarScene::cone_distance`] for a copter's four sonars at once, with the same bits:
    /// one pass over the copter grid around `origin` (the copter's centre) serves all four
    /// cones. Each neighbour is tested against the cone with its apex moved back to `origin`
    /// (which contains the sonar's cone) and its bounding sphere; only the cones it can enter
    /// get the exact test. Each apex must lie on its own axis ahead of `origin` (`origin + t
    /// axis`, `t >= 0`), as [`sonar_cones`] places them.
    pub fn cone_distances(&self, cones: &[Cone; 4], origin: Vec3, self_id: usize, max_range_m: Real) -> [Real; 4] {
        self.cone_distances_of(cones, [true; 4], origin, self_id, max_range_m)
    }

    /// [`SonarScene::cone_distances`] of the `wanted` cones only (the firmware reads one sonar
    /// per tick); the others come back as `INFINITY` and cost nothing.
    pub fn cone_distances_of(
        &self,
        cones: &[Cone; 4],
        wanted: [bool; 4],
        origin: Vec3,
        self_id: usize,
        max_range_m: Real,
    ) -> [Real; 4] {
        let mut out = [Real::INFINITY; 4];
        if self.grid.built_for != self.copters.len() || self.copters.is_empty() {
            for ((o, cone), _) in out.iter_mut().zip(cones).zip(wanted).filter(|(_, w)| *w) {
                *o = self.cone_distance(cone, self_id, max_range_m);
            }
            return out;
        }
        // An unwanted cone starts with nothing left to find: no test ever lowers its `best`.
        let mut best = wanted.map(|w| if w { max_range_m } else { 0.0 });
        let mut hit = [false; 4];
        for (k, cone) in cones.iter().enumerate().filter(|(k, _)| wanted[*k]) {
            for &(n, c) in &self.walls {
                if let Some(d) = cone.distance_to_plane(n, c)
                    && d < best[k]
                {
                    best[k] = d;
                    hit[k] = true;
                }
            }
        }
        let off = cones.iter().map(|c| (c.apex - origin).length()).fold(0.0, Real::max);
        let radius = |best: &[Real; 4]| best.iter().copied().fold(0.0, Real::max) + off;
        // One cone (the firmware's one sonar per tick) looks over a twelfth of the floor.
        let only = (wanted.iter().filter(|w| **w).count() == 1).then(|| wanted.iter().position(|w| *w).unwrap_or(0));
        let one = only.map(|k| Wedge::of_cone(cones[k].apex, cones[k].axis, cones[k].sin_h));
        self.grid.visit_near_over(origin, radius(&best), one.as_ref().map(|w| (w, 1e-3)), |id| {
            if id == self_id {
                return radius(&best);
            }
            let b = &self.copters[id];
            // One cone: the tests from `origin` would only repeat `consider_box`'s own.
            if let Some(k) = only {
                consider_box(&cones[k], b, &mut best[k], &mut hit[k]);
                return radius(&best);
            }
            let r = b.bounding_radius();
            let d = b.center - origin;
            let l = d.length();
            // cos(h + β) with sin β = r / l; inside the sphere every cone is possible.
            let (sin_b, cos_b) = if l > r { (r / l, (1.0 - (r / l) * (r / l)).max(0.0).sqrt()) } else { (1.0, 0.0) };
            for k in 0..4 {
                let cone = &cones[k];
                if l - r - off >= best[k] {
                    continue;
                }
                if l > r && d.dot(cone.axis) < l * (cone.cos_h * cos_b - cone.sin_h * sin_b) - 1e-4 * l {
                    continue;
                }
                consider_box(cone, b, &mut best[k], &mut hit[k]);
            }
            radius(&best)
        });
        // Boxes after the copters: the nearest neighbour (1.5 m away in a dense grid) has
        // lowered `best` by then, and most boxes fail the sphere tests before the exact one.
        // The result is a minimum, the same in any order. One sphere test from `origin`
        // skips a box for all four cones when every apex is too far from it (`consider_box`
        // would return at its first test; the margin covers rounding in the triangle
        // inequality).
        for b in &self.boxes {
            let far = (b.center - origin).length() - b.bounding_radius() - off - 1e-4;
            if far >= best.iter().copied().fold(0.0, Real::max) {
                continue;
            }
            for k in 0..4 {
                consider_box(&cones[k], b, &mut best[k], &mut hit[k]);
            }
        }
        for k in 0..4 {
            if hit[k] {
                out[k] = best[k];
            }
        }
        out
    }

    /// The walls and boxes part of a cone distance: `(best, hit)` with `best` starting at
    /// `max_range_m`.
    fn static_cone_distance(&self, cone: &Cone, max_range_m: Real) -> (Real, bool) {
        let mut best = max_range_m;
        let mut hit = false;
        for &(n, c) in &self.walls {
            if let Some(d) = cone.distance_to_plane(n, c)
                && d < best
            {
                best = d;
                hit = true;
            }
        }
        for b in &self.boxes {
            consider_box(cone, b, &mut best, &mut hit);
        }
        (best, hit)
    }

    /// IR ray cast down the body's −z axis against the floor and the boxes (other copters
    /// below are seen too). Returns the distance, m.
    pub fn ir_distance(&self, origin: Vec3, dir: Vec3, self_id: usize) -> Real {
        let mut best = if dir.z < -1e-6 { origin.z / -dir.z } else { Real::INFINITY };
        for b in &self.boxes {
            // A hit lies at least the bounding sphere's distance away (the margin covers
            // rounding), so a box beyond `best` cannot lower it.
            if (b.center - origin).length() - b.bounding_radius() - 1e-4 < best
                && let Some(t) = ray_box(origin, dir, b)
            {
                best = best.min(t);
            }
        }
        let consider = |id: usize, b: &OrientedBox, best: &mut Real| {
            if id != self_id
                && (b.center - origin).length() - b.bounding_radius() < *best
                && let Some(t) = ray_box(origin, dir, b)
            {
                *best = best.min(t);
            }
        };
        if self.grid.built_for == self.copters.len() && !self.copters.is_empty() && best.is_finite() {
            // Only copters whose bounding sphere is within `best` of the origin can be hit:
            // the grid visits exactly those rings (the minimum does not depend on the order),
            // and of them only the cells near the ray's shadow on the floor up to `best` (a
            // hit lies on it, and a box's centre within its bounding radius of the hit).
            let end = origin + dir * best;
            let shadow = [origin.x.min(end.x), origin.y.min(end.y), origin.x.max(end.x), origin.y.max(end.y)];
            self.grid.visit_near_within(origin, best, shadow, |id| {
                consider(id, &self.copters[id], &mut best);
                best
            });
        } else {
            for (id, b) in self.copters.iter().enumerate() {
                consider(id, b, &mut best);
            }
        }
        best
    }
}

/// Lowers `best` to the cone's exact distance to the box when that is closer (and sets `hit`).
/// A cheap bounding-sphere test comes first.
#[inline]
fn consider_box(cone: &Cone, b: &OrientedBox, best: &mut Real, hit: &mut bool) {
    let to = b.center - cone.apex;
    let dist = to.length();
    let r = b.bounding_radius();
    if dist - r >= *best {
        return;
    }
    if dist > r {
        // Outside the cone widened by the sphere's angular radius β: the angle to the centre
        // exceeds h + β, i.e. cos(angle) < cos(h + β) (no trigonometric calls; a small slack
        // keeps the test conservative under rounding).
        let cos_to = to.dot(cone.axis) / dist;
        let sin_b = r / dist;
        let cos_b = (1.0 - sin_b * sin_b).max(0.0).sqrt();
        if cos_to < cone.cos_h * cos_b - cone.sin_h * sin_b - 1e-5 {
            return;
        }
    }
    if let Some(d) = cone_box_distance(cone, b)
        && d < *best
    {
        *best = d;
        *hit = true;
    }
}

/// The sonar cones of a copter at a pose.
pub fn sonar_cones(params: &SensorParams, pos: Vec3, rot: Quat) -> [Cone; 4] {
    let off = params.spec.sonar.mount_offset_m;
    SONAR_AXES_IN_BODY.map(|axis_b| {
        let axis = rot * axis_b;
        Cone { apex: pos + axis * off, axis, cos_h: params.sonar_cos_half, sin_h: params.sonar_sin_half }
    })
}

/// Turns a true distance into a reading: noise, min/cap clamping, quantisation. `INFINITY`
/// (no echo) reads the cap.
#[inline]
pub fn sonar_reading(spec: &SonarSpec, truth_m: Real, noise_m: Real) -> Real {
    if !truth_m.is_finite() || truth_m > spec.max_range_m {
        return spec.cap_m;
    }
    let v = (truth_m + noise_m).clamp(spec.min_range_m, spec.cap_m);
    if v >= spec.cap_m {
        return spec.cap_m;
    }
    quantise(v, spec.quantum_m).min(spec.cap_m)
}

/// Rounds to the nearest multiple of `quantum`.
#[inline]
pub fn quantise(v: Real, quantum: Real) -> Real {
    (v / quantum).round() * quantum
}

/// Fuses a physical sonar reading with an externally supplied virtual one: `min(physical,
/// virtual)`, the original system's rule for real copters seeing virtual objects. A
/// non-finite or non-positive virtual reading is ignored.
#[inline]
pub fn fuse_min(physical_m: [Real; 4], virtual_m: Option<[Real; 4]>) -> [Real; 4] {
    match virtual_m {
        None => physical_m,
        Some(v) => {
            let mut out = physical_m;
            for i in 0..4 {
                if v[i].is_finite() && v[i] > 0.0 {
                    out[i] = out[i].min(v[i]);
                }
            }
            out
        }
    }
}

/// Whether copter A's sonar `a` can be heard by copter B's sonar `b`: B's receiver is inside
/// A's emitting cone within range, and A's emitter is inside B's receiving cone. Returns the
/// distance between them when it can.
#[inline]
pub fn crosstalk_eligible(a: &Cone, b: &Cone, max_range_m: Real) -> Option<Real> {
    let d = b.apex - a.apex;
    let dist = d.length();
    if dist > max_range_m || dist < 1e-6 {
        return None;
    }
    let u = d / dist;
    (u.dot(a.axis) >= a.cos_h && (-u).dot(b.axis) >= b.cos_h).then_some(dist)
}

/// The distance a listener reads from a foreign ping: `c Δt / 2`, with `Δt` the delay from
/// the listener's own ping at `listen_s` to the arrival of the emitter's first ping that
/// arrives after it. The emitter pings at `phase_s + m cycle_s`; the ping travels `dist_m`.
/// Times are `f64` seconds (a run's clock would lose its milliseconds in `f32`).
#[inline]
pub fn crosstalk_reading(listen_s: f64, phase_s: f64, cycle_s: f64, dist_m: Real, speed_m_s: Real) -> Real {
    let travel = f64::from(dist_m) / f64::from(speed_m_s);
    let m = ((listen_s - travel - phase_s) / cycle_s).ceil();
    let delay = phase_s + m * cycle_s + travel - listen_s;
    (delay.max(0.0) * f64::from(speed_m_s) / 2.0) as Real
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator of numbers in [0, 1] for random layouts.
    fn xorshift(seed: u32) -> impl FnMut() -> Real {
        let mut x = seed;
        move || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x as Real / u32::MAX as Real
        }
    }

    #[test]
    fn the_copter_grid_finds_exactly_what_a_full_scan_finds() {
        let mut rnd = xorshift(99);
        let mut scene = SonarScene::default();
        for _ in 0..400 {
            scene.copters.push(OrientedBox {
                center: Vec3::new(rnd() * 30.0 - 15.0, rnd() * 20.0 - 10.0, 0.5 + rnd()),
                rotation: Quat::from_rotation_z(rnd() * 6.0),
                half: Vec3::new(0.134, 0.134, 0.03),
            });
        }
        let linear = scene.clone();
        scene.index_copters(1.0);
        let mut hits = 0;
        for id in 0..scene.copters.len() {
            let c = scene.copters[id];
            for axis in SONAR_AXES_IN_BODY {
                let cone = Cone::new(c.center + c.rotation * axis * 0.05, c.rotation * axis, 15f32.to_radians());
                let a = scene.cone_distance(&cone, id, 7.65);
                let b = linear.cone_distance(&cone, id, 7.65);
                assert_eq!(a.to_bits(), b.to_bits(), "copter {id}: grid {a} vs scan {b}");
                hits += usize::from(a.is_finite());
            }
        }
        assert!(hits > 100, "the layout must exercise hits: {hits}");
    }

    #[test]
    fn four_cones_at_once_give_the_same_bits_as_one_at_a_time() {
        let mut rnd = xorshift(7);
        let mut scene = SonarScene {
            walls: vec![(Vec3::X, 15.0), (Vec3::X, -15.0), (Vec3::Y, 10.0), (Vec3::Y, -10.0)],
            ..SonarScene::default()
        };
        scene.boxes.push(OrientedBox {
            center: Vec3::new(3.0, 2.0, 1.0),
            rotation: Quat::from_rotation_z(0.4),
            half: Vec3::new(0.5, 0.3, 1.0),
        });
        for _ in 0..600 {
            scene.copters.push(OrientedBox {
                center: Vec3::new(rnd() * 30.0 - 15.0, rnd() * 20.0 - 10.0, 0.5 + rnd()),
                rotation: Quat::from_rotation_z(rnd() * 6.0) * Quat::from_rotation_x(rnd() * 0.3 - 0.15),
                half: Vec3::new(0.134, 0.134, 0.03),
            });
        }
        scene.index_copters(1.0);
        let params = SensorSpec::default().compile(&FieldPath::default()).unwrap();
        let mut hits = 0;
        for id in 0..scene.copters.len() {
            let c = scene.copters[id];
            let cones = sonar_cones(&params, c.center, c.rotation);
            let all = scene.cone_distances(&cones, c.center, id, 7.65);
            for k in 0..4 {
                let one = scene.cone_distance(&cones[k], id, 7.65);
                assert_eq!(all[k].to_bits(), one.to_bits(), "copter {id} sonar {k}: {} vs {one}", all[k]);
                hits += usize::from(one < 7.0);
            }
        }
        assert!(hits > 500, "the layout must exercise hits: {hits}");
    }

    #[test]
    fn fusion_takes_the_minimum_and_ignores_garbage() {
        let phys = [1.0, 2.0, 3.0, 4.0];
        assert_eq!(fuse_min(phys, None), phys);
        assert_eq!(fuse_min(phys, Some([0.5, 5.0, Real::NAN, -1.0])), [0.5, 2.0, 3.0, 4.0]);
    }

    #[test]
    fn readings_are_quantised_capped_and_no_echo_reads_the_cap() {
        let s = SonarSpec::default();
        assert_eq!(sonar_reading(&s, Real::INFINITY, 0.0), s.cap_m);
        assert!((sonar_reading(&s, 1.234_56, 0.0) - 1.23).abs() < 1e-6);
        assert!((sonar_reading(&s, 0.05, 0.0) - 0.20).abs() < 1e-6);
        assert_eq!(sonar_reading(&s, 7.6, 0.5), s.cap_m);
    }

    #[test]
    fn crosstalk_needs_both_cones_to_face_each_other() {
        let h = 15f32.to_radians();
        let a = Cone::new(Vec3::ZERO, Vec3::X, h);
        let facing = Cone::new(Vec3::new(1.0, 0.0, 0.0), Vec3::NEG_X, h);
        let away = Cone::new(Vec3::new(1.0, 0.0, 0.0), Vec3::X, h);
        let side = Cone::new(Vec3::new(1.0, 0.0, 0.0), Vec3::Y, h);
        assert!(crosstalk_eligible(&a, &facing, 7.65).is_some());
        assert!(crosstalk_eligible(&a, &away, 7.65).is_none());
        assert!(crosstalk_eligible(&a, &side, 7.65).is_none());
        // Rotating the receiver: eligible only within the half-angle.
        let rot =
            |deg: Real| Cone::new(Vec3::new(1.0, 0.0, 0.0), Quat::from_rotation_z(deg.to_radians()) * Vec3::NEG_X, h);
        assert!(crosstalk_eligible(&a, &rot(10.0), 7.65).is_some());
        assert!(crosstalk_eligible(&a, &rot(20.0), 7.65).is_none());
    }
}
