//! Keeping a twin where its real copter is: the original paper's hybrid approach.
//!
//! - **Command prediction.** The twin's physics is driven by the real copter's telemetry
//!   ([`crate::mixed::interpreter`]): it flies what the real one flies, and drifts as open-loop
//!   prediction does.
//! - **MEDUSA correction.** The real copter's own sonar readings (`SONAR_ARRAY`, or
//!   `FINKEN_SENSOR_MODEL` as fallback) and yaw (`ATTITUDE`, `FINKEN_SENSOR_MODEL.pos_yaw`) feed
//!   a MEDUSA particle filter per twin ([`medusa::MedusaFilter`]) over the **real** arena: the
//!   walls and the boxes that are not `virtual_only`, since the real sonars cannot see virtual
//!   ones. Its motion model is driven by the twin's attitude command.
//! - **Tracking correction.** An external pose on `…/copters/<name>/tracking` (e.g. a camera
//!   system), which arrives [`SyncOptions::tracking_lag_s`] late.
//!
//! **Latency compensation.** Each twin keeps its own recent trajectory. A measurement that
//! describes the real copter `lag` seconds ago is compared with where the twin was `lag`
//! seconds ago; the difference is the twin's error, still valid now (both moved alike since).
//!
//! **Fusion and smooth corrections.** The latest error of each source that is switched on and
//! fresh ([`SyncOptions::source_timeout_s`]) is weighted by its inverse variance (MEDUSA: the
//! filter's covariance, floored; tracking: [`SyncOptions::tracking_sigma_m`]). Each control
//! step moves the twin by [`SyncOptions::gain_per_s`] × dt of that error, at most
//! [`SyncOptions::max_speed_m_s`] × dt: no teleports. What was applied is subtracted from
//! every source's error, so a correction is never applied twice. MEDUSA estimates with a
//! confidence below [`SyncOptions::min_confidence`] (e.g. ambiguous ones) are not used.

use std::collections::{BTreeMap, VecDeque};

use medusa::{
    Arena, BoxObstacle, FilterConfig, Medusa, MedusaError, MedusaFilter, MotionInput, SensorLayout, SensorModel,
    SensorSpec, YawEstimate,
};
use nalgebra::Vector2;
use sim_core::{CopterKind, Inputs, State, World};

/// Body-frame directions of the FINken's four sonars, rad (sim-core order: front, right, back,
/// left).
pub const SONAR_ANGLES_RAD: [f64; 4] =
    [0.0, -std::f64::consts::FRAC_PI_2, std::f64::consts::PI, std::f64::consts::FRAC_PI_2];

/// Boxes whose top is lower than this are left out of MEDUSA's map: at flight height the sonar
/// cones pass over them.
pub const MIN_BOX_TOP_M: f32 = 0.7;

/// How twins are kept where their real copters are.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SyncOptions {
    /// Correct with MEDUSA on the real copter's sonars.
    pub medusa: bool,
    /// Correct with the tracking pose.
    pub tracking: bool,
    /// Age of sonar telemetry when it arrives (sampling, scheduling, transport), s.
    pub medusa_latency_s: f64,
    /// Lag of the tracking pose, s.
    pub tracking_lag_s: f64,
    /// Standard deviation of the tracking pose, m.
    pub tracking_sigma_m: f64,
    /// Floor of MEDUSA's standard deviation, m.
    pub medusa_sigma_floor_m: f64,
    /// How far a real copter's sonar readings stray from the arena as modelled, m: MEDUSA's
    /// sensor noise. Not the simulated sonars' noise: a real lab's readings also carry its
    /// people, chairs and foil walls (the 2015 logs: jumps of 20 cm and more on up to 5 % of
    /// them), which a tighter model would trust.
    pub medusa_sonar_sigma_m: f64,
    /// The share of a real copter's sonar readings MEDUSA takes for outliers: 5 %, the upper
    /// end of the 2015 logs' jumps (docs/real-flights.md §6; `twinswarm validate` on the
    /// 16 Dec flight: 83-100 % of each flight consistent at MEDUSA's own 2 %, 95-100 % at 5 %).
    pub medusa_outlier_probability: f64,
    /// Fraction of the error corrected per second.
    pub gain_per_s: f64,
    /// Largest correction speed, m/s.
    pub max_speed_m_s: f64,
    /// MEDUSA estimates less confident than this are not used.
    pub min_confidence: f64,
    /// A source silent for longer than this stops contributing, s.
    pub source_timeout_s: f64,
    /// Yaw noise assumed for the real copter's AHRS, rad.
    pub yaw_sigma_rad: f64,
    /// Fraction of the tilt implied by a velocity difference (MEDUSA's estimate of the real
    /// copter's velocity against the twin's) learnt per MEDUSA update as attitude trim: the
    /// real copter's own attitude-control error (e.g. unequal rotors), which its set points do
    /// not show. 0 turns it off.
    pub trim_gain_rad_per_m_s: f64,
    /// Largest attitude trim, rad.
    pub max_trim_rad: f64,
    /// The time constant of the hold trim, s (0 turns it off). The trim is the attitude at
    /// which the real copter holds still, less its level on the floor: over a window,
    /// mean(a)/g + k·mean(v)/g − mean(attitude target), per axis, with the acceleration and
    /// velocity from MEDUSA's confident estimates (where there are none, the copter is taken to
    /// have held its speed: a copter that stays in its arena accelerates little on average).
    /// An unknown trim of 3° (a copter standing askew, unequal rotors) flies a twin 1.5 m off
    /// in 2 s.
    pub hold_trim_time_constant_s: f64,
    /// The hold trim starts at zero worth this much flight, s: the level taken on the floor
    /// holds until the flight says otherwise.
    pub hold_trim_prior_s: f64,
}

impl Default for SyncOptions {
    fn default() -> Self {
        Self {
            medusa: true,
            tracking: true,
            medusa_latency_s: 0.03,
            tracking_lag_s: 0.2,
            tracking_sigma_m: 0.01,
            medusa_sigma_floor_m: 0.03,
            medusa_sonar_sigma_m: 0.05,
            medusa_outlier_probability: 0.05,
            // A 0.2 s time constant: about four MEDUSA estimates (docs/mixed-reality.md).
            gain_per_s: 5.0,
            // Faster than a twin with half a degree of trim error drifts after 3 s; chosen on
            // the shared real flights (docs/real-flights.md: 0.3 m/s lost four of them).
            max_speed_m_s: 0.8,
            min_confidence: 0.3,
            source_timeout_s: 1.0,
            yaw_sigma_rad: 2f64.to_radians(),
            trim_gain_rad_per_m_s: 0.02,
            max_trim_rad: 6f64.to_radians(),
            hold_trim_time_constant_s: 10.0,
            hold_trim_prior_s: 2.0,
        }
    }
}

impl SyncOptions {
    /// No correction at all: the twin is command prediction only.
    pub fn off() -> Self {
        Self { medusa: false, tracking: false, hold_trim_time_constant_s: 0.0, ..Self::default() }
    }
}

/// What synchronisation did for one twin.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct SyncStats {
    /// MEDUSA filter corrections (sonar telemetry messages used).
    pub medusa_updates: u64,
    /// MEDUSA estimates not used (low confidence).
    pub medusa_rejected: u64,
    /// Tracking poses used.
    pub tracking_updates: u64,
    /// Steps in which the twin was moved.
    pub corrected_steps: u64,
    /// Total distance the twin was moved by corrections, m.
    pub corrected_m: f64,
    /// Last MEDUSA confidence.
    pub last_confidence: f64,
    /// Learnt pitch and roll trim at the end, deg.
    pub trim_deg: [f64; 2],
    /// MEDUSA predictions and corrections that failed (bad input); the first is logged.
    pub medusa_errors: u64,
    /// Sonar telemetry replaced by newer readings before a step could use it.
    pub sonar_superseded: u64,
    /// Why MEDUSA is off for this twin although synchronisation asks for it: its filter could
    /// not be built.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub medusa_off: Option<String>,
}

#[derive(Clone, Copy, Debug)]
struct Offset {
    at_s: f64,
    xy: Vector2<f64>,
    var_m2: f64,
}

struct TwinTracker {
    filter: Option<MedusaFilter>,
    /// The twin's recent positions: (time, x, y).
    history: VecDeque<(f64, Vector2<f64>)>,
    /// The real copter's yaw estimate (simulator frame), rad, and when it came.
    yaw: Option<(f64, f64)>,
    /// Sonar readings waiting for the next step (m; `None`: out of range).
    pending_sonar: Option<[Option<f64>; 4]>,
    /// Latest error per source: [MEDUSA, tracking].
    offsets: [Option<Offset>; 2],
    /// The yaw target from the real copter's telemetry (its AHRS frame), rad.
    yaw_command: Option<f32>,
    /// MEDUSA's estimate of the real copter's AHRS yaw bias, rad.
    yaw_bias: Option<f64>,
    /// Pitch and roll targets from the real copter's telemetry, rad.
    attitude_command: Option<[f32; 2]>,
    /// Learnt pitch and roll trim, rad.
    trim: [f64; 2],
    /// The hold trim's running sums.
    hold: HoldTrim,
    stats: SyncStats,
}

/// The hold trim's exponentially weighted sums ([`SyncOptions::hold_trim_time_constant_s`]),
/// per body axis (forward, left).
#[derive(Clone, Debug)]
struct HoldTrim {
    /// The twin's linear damping, 1/s.
    damping_per_s: f64,
    /// Weight, s (the prior included).
    weight_s: f64,
    /// Σ dt · (pitch, roll) target, rad·s.
    target: [f64; 2],
    /// Σ Δv between confident MEDUSA estimates (at most a second apart), m/s.
    dv: [f64; 2],
    /// Σ dt · the latest confident velocity, m.
    v: [f64; 2],
    /// The latest confident MEDUSA velocity (forward, left) and when it came, s.
    last: Option<(f64, [f64; 2])>,
}

impl HoldTrim {
    fn new(opts: &SyncOptions, damping_per_s: f64) -> Self {
        HoldTrim {
            damping_per_s,
            weight_s: opts.hold_trim_prior_s,
            target: [0.0; 2],
            dv: [0.0; 2],
            v: [0.0; 2],
            last: None,
        }
    }

    /// (pitch, roll) trim, rad: pitch > 0 flies forward, roll > 0 flies right.
    fn trim(&self) -> [f64; 2] {
        if self.weight_s <= 0.0 {
            return [0.0; 2];
        }
        let g = f64::from(sim_core::math::GRAVITY_M_S2);
        let acc = |k: usize| (self.dv[k] + self.damping_per_s * self.v[k]) / g;
        [(acc(0) - self.target[0]) / self.weight_s, (-acc(1) - self.target[1]) / self.weight_s]
    }

    /// One control step while the twin flies its `target` (pitch, roll).
    fn step(&mut self, tau_s: f64, dt: f64, t: f64, target: [f32; 2]) {
        let decay = (-dt / tau_s).exp();
        self.weight_s = decay * self.weight_s + dt;
        let v = self.last.filter(|(at, _)| t - at <= 1.0).map_or([0.0; 2], |(_, v)| v);
        for k in 0..2 {
            self.target[k] = decay * self.target[k] + dt * f64::from(target[k]);
            self.dv[k] *= decay;
            self.v[k] = decay * self.v[k] + dt * v[k];
        }
    }

    /// A confident MEDUSA velocity (forward, left), m/s, at `t`.
    fn velocity(&mut self, t: f64, v: [f64; 2]) {
        if let Some((_, before)) = self.last.filter(|(at, _)| t - at <= 1.0) {
            for k in 0..2 {
                self.dv[k] += v[k] - before[k];
            }
        }
        self.last = Some((t, v));
    }
}

impl TwinTracker {
    /// The trim added to the twin's pitch and roll targets: the one learnt from the velocity
    /// difference plus the hold trim, each axis within `max_rad`, rad.
    fn total_trim(&self, max_rad: f64) -> [f64; 2] {
        let hold = self.hold.trim();
        [0, 1].map(|k| (self.trim[k] + hold[k]).clamp(-max_rad, max_rad))
    }
}

/// Synchronisation of every twin of a run. Runs on the loop thread.
pub struct TwinSync {
    opts: SyncOptions,
    medusa: Medusa,
    twins: BTreeMap<usize, TwinTracker>,
}

impl std::fmt::Debug for TwinSync {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TwinSync").field("opts", &self.opts).field("twins", &self.twins.len()).finish()
    }
}

/// MEDUSA over `world`'s real geometry: the arena and the boxes that are not `virtual_only`
/// and reach [`MIN_BOX_TOP_M`]; the FINken's four sonars with the scene's noise, cone and cap.
pub fn medusa_for(world: &World, angles_rad: &[f64]) -> Result<Medusa, MedusaError> {
    medusa_with_sigma(world, angles_rad, f64::from(world.sensors.spec.sonar.noise_sigma_m))
}

/// [`medusa_for`] with the sonars' noise `sigma_m` in MEDUSA's sensor model.
pub fn medusa_with_sigma(world: &World, angles_rad: &[f64], sigma_m: f64) -> Result<Medusa, MedusaError> {
    medusa_with_model(world, angles_rad, sigma_m, SensorModel::default().outlier_probability)
}

/// [`medusa_with_sigma`] with the share `outliers` of readings MEDUSA takes for outliers.
pub fn medusa_with_model(
    world: &World,
    angles_rad: &[f64],
    sigma_m: f64,
    outliers: f64,
) -> Result<Medusa, MedusaError> {
    let sonar = &world.sensors.spec.sonar;
    let sensors = angles_rad
        .iter()
        .map(|&a| SensorSpec {
            angle_in_body_rad: a,
            offset_in_body_m: Vector2::new(a.cos(), a.sin()) * f64::from(sonar.mount_offset_m),
            max_range_m: f64::from(sonar.cap_m),
        })
        .collect();
    let layout = SensorLayout::new(sensors)?;
    let (w, h) = (f64::from(world.arena.size_m[0]), f64::from(world.arena.size_m[1]));
    let mworld = medusa::World::new(Arena::new(w, h)?, real_boxes(world))?;
    let model = SensorModel {
        noise_sigma_m: sigma_m.max(0.01),
        cone_half_angle_rad: f64::from(world.sensors.sonar_half_angle_rad),
        outlier_probability: outliers,
    };
    Medusa::new(mworld, layout, model)
}

/// The boxes a real copter's sonars can see: not `virtual_only`, top at least
/// [`MIN_BOX_TOP_M`].
pub fn real_boxes(world: &World) -> Vec<BoxObstacle> {
    world
        .boxes
        .iter()
        .filter(|b| is_real_box(b))
        .map(|b| {
            BoxObstacle::new(
                Vector2::new(f64::from(b.center_m.x), f64::from(b.center_m.y)),
                Vector2::new(f64::from(b.half_extents_m.x), f64::from(b.half_extents_m.y)),
                f64::from(b.yaw_rad),
            )
        })
        .collect()
}

/// Whether a real copter's sonars see box `b`: not `virtual_only`, top at least
/// [`MIN_BOX_TOP_M`].
pub fn is_real_box(b: &sim_core::world::StaticBox) -> bool {
    !b.virtual_only && b.top_m() >= MIN_BOX_TOP_M
}

/// The MEDUSA filter configuration for copter `id` of `world`: the motion model's drag is the
/// airframe's linear damping (`g tan(tilt) = damping · v` at steady state).
pub fn filter_config(world: &World, id: usize) -> FilterConfig {
    let af = &world.airframes[world.copters[id].airframe];
    FilterConfig {
        seed: world.params.seed ^ (0x4d45_4455_5341 + id as u64),
        drag_per_s: f64::from(af.spec.linear_damping),
        ..FilterConfig::default()
    }
}

fn xy(p: sim_core::math::Vec3) -> Vector2<f64> {
    Vector2::new(f64::from(p.x), f64::from(p.y))
}

impl TwinSync {
    /// Synchronisation for the twins of `world` (more are added as they spawn).
    pub fn new(world: &World, opts: SyncOptions) -> Result<Self, MedusaError> {
        let medusa =
            medusa_with_model(world, &SONAR_ANGLES_RAD, opts.medusa_sonar_sigma_m, opts.medusa_outlier_probability)?;
        Ok(Self { opts, medusa, twins: BTreeMap::new() })
    }

    /// The options.
    pub fn options(&self) -> &SyncOptions {
        &self.opts
    }

    fn tracker(&mut self, world: &World, state: &State, id: usize) -> &mut TwinTracker {
        let (medusa, opts) = (&self.medusa, &self.opts);
        self.twins.entry(id).or_insert_with(|| {
            let mut stats = SyncStats::default();
            let filter = match opts.medusa {
                false => None,
                true => {
                    // Start where the twin is: a twin starts at its real copter's pose.
                    let built = MedusaFilter::new(medusa.clone(), filter_config(world, id))
                        .and_then(|mut f| f.reset_at(xy(state.pose(id).pos_m), 0.1).map(|()| f));
                    match built {
                        Ok(f) => Some(f),
                        Err(e) => {
                            tracing::warn!("twin {}: MEDUSA is off for it: {e}", world.copters[id].name);
                            stats.medusa_off = Some(e.to_string());
                            None
                        }
                    }
                }
            };
            TwinTracker {
                filter,
                history: VecDeque::new(),
                yaw: None,
                pending_sonar: None,
                offsets: [None, None],
                yaw_command: None,
                yaw_bias: None,
                attitude_command: None,
                trim: [0.0; 2],
                hold: HoldTrim::new(opts, f64::from(world.airframes[world.copters[id].airframe].spec.linear_damping)),
                stats,
            }
        })
    }

    /// The real copter's yaw estimate (simulator frame), rad, at time `t_s`.
    pub fn on_yaw(&mut self, world: &World, state: &State, id: usize, t_s: f64, yaw_rad: f32) {
        if yaw_rad.is_finite() {
            self.tracker(world, state, id).yaw = Some((t_s, f64::from(yaw_rad)));
        }
    }

    /// The attitude targets the telemetry gave the twin: pitch, roll and yaw (the real
    /// copter's AHRS frame), rad, each if given.
    pub fn on_command(
        &mut self,
        world: &World,
        state: &State,
        id: usize,
        pitch_rad: Option<f32>,
        roll_rad: Option<f32>,
        yaw_rad: Option<f32>,
    ) {
        let tr = self.tracker(world, state, id);
        if let Some(y) = yaw_rad.filter(|y| y.is_finite()) {
            tr.yaw_command = Some(y);
        }
        if let (Some(p), Some(r)) = (pitch_rad, roll_rad)
            && p.is_finite()
            && r.is_finite()
        {
            tr.attitude_command = Some([p, r]);
        }
    }

    /// Before a step: a twin's AHRS is ideal, its real copter's is biased, so the twin's yaw
    /// target is the real copter's minus MEDUSA's estimate of that bias. Without it the twin
    /// would fly the real copter's attitude in a heading rotated by the bias, and drift.
    ///
    /// The learnt attitude trim is added to the twin's pitch and roll targets.
    pub fn adjust_commands(&self, inputs: &mut Inputs) {
        for (&id, tr) in &self.twins {
            let Some(cmd) = inputs.commands.get_mut(id) else { continue };
            if let (Some(yaw), Some(bias)) = (tr.yaw_command, tr.yaw_bias) {
                cmd.yaw_rad = sim_core::math::wrap_angle_rad(yaw - bias as f32);
            }
            if let Some([p, r]) = tr.attitude_command {
                let trim = tr.total_trim(self.opts.max_trim_rad);
                cmd.pitch_rad = p + trim[0] as f32;
                cmd.roll_rad = r + trim[1] as f32;
            }
        }
    }

    /// The twin's telemetry stopped and the loop levelled it out: forget the last attitude
    /// targets, so that [`TwinSync::adjust_commands`] does not fly them (with the trim) again
    /// at every step until telemetry resumes. The yaw target and the estimates stay.
    pub fn on_link_lost(&mut self, id: usize) {
        if let Some(tr) = self.twins.get_mut(&id) {
            tr.attitude_command = None;
        }
    }

    /// The real copter's sonar readings (front, right, back, left), m; readings at or beyond
    /// the cap are out of range. Used at the next step.
    pub fn on_sonar(&mut self, world: &World, state: &State, id: usize, readings_m: [f32; 4]) {
        if !self.opts.medusa {
            return;
        }
        let cap = f64::from(world.sensors.spec.sonar.cap_m);
        let r = readings_m.map(|v| {
            let v = f64::from(v);
            (v.is_finite() && v > 0.0 && v < cap - 1e-3).then_some(v)
        });
        let tr = self.tracker(world, state, id);
        if tr.pending_sonar.replace(r).is_some() {
            // Two readings between steps (jitter): the newer wins, counted.
            tr.stats.sonar_superseded += 1;
        }
    }

    /// An external tracking pose (x, y), m, received at `t_s`; it shows the real copter
    /// [`SyncOptions::tracking_lag_s`] earlier.
    pub fn on_tracking(&mut self, world: &World, state: &State, id: usize, t_s: f64, pos_m: [f32; 2]) {
        if !self.opts.tracking || !pos_m.iter().all(|v| v.is_finite()) {
            return;
        }
        let lag = self.opts.tracking_lag_s;
        // What the twin and its real copter did differently during the lag is not in the pose:
        // about 0.1 m/s of relative velocity, so the lag adds to the uncertainty.
        let var = self.opts.tracking_sigma_m.powi(2) + (lag * 0.1).powi(2);
        let tr = self.tracker(world, state, id);
        if let Some(then) = past_position(&tr.history, t_s - lag) {
            let measured = Vector2::new(f64::from(pos_m[0]), f64::from(pos_m[1]));
            tr.offsets[1] = Some(Offset { at_s: t_s, xy: measured - then, var_m2: var });
            tr.stats.tracking_updates += 1;
        }
    }

    /// After each control step: records the twins' positions, runs the MEDUSA filters, and
    /// moves each twin by its bounded correction.
    pub fn after_step(&mut self, world: &World, state: &mut State, inputs: &Inputs) {
        let t = state.time_s(world);
        let dt = world.params.control_dt_s;
        for id in 0..world.copters.len() {
            if world.copters[id].kind == CopterKind::Real && state.copters[id].crash.is_none() {
                self.tracker(world, state, id);
            }
        }
        let opts = self.opts.clone();
        for (&id, tr) in &mut self.twins {
            let drag = f64::from(world.airframes[world.copters[id].airframe].spec.linear_damping);
            if state.copters[id].crash.is_some() {
                continue;
            }
            let c = &state.copters[id];
            let hold = opts.hold_trim_time_constant_s > 0.0 && c.took_off_tick.is_some() && !c.grounded;
            if let (true, Some(target)) = (hold, tr.attitude_command) {
                tr.hold.step(opts.hold_trim_time_constant_s, dt, t, target);
            }
            let now_xy = xy(state.pose(id).pos_m);
            tr.history.push_back((t, now_xy));
            while tr.history.front().is_some_and(|(ht, _)| t - ht > 3.0) {
                tr.history.pop_front();
            }
            // MEDUSA: predict with the twin's attitude command, correct with pending readings.
            if let (Some(f), Some((_, yaw))) = (tr.filter.as_mut(), tr.yaw) {
                let cmd = &inputs.commands[id];
                let input = MotionInput::from_attitude(f64::from(cmd.pitch_rad), f64::from(cmd.roll_rad));
                let yaw_est = YawEstimate::new(yaw, opts.yaw_sigma_rad);
                if let Err(e) = f.predict(dt, &input, yaw_est) {
                    medusa_error(&mut tr.stats, &world.copters[id].name, &e);
                }
                let corrected = tr.pending_sonar.take().map(|readings| f.correct(yaw_est, &readings));
                if let Some(Err(e)) = &corrected {
                    medusa_error(&mut tr.stats, &world.copters[id].name, e);
                }
                if let Some(Ok(est)) = corrected {
                    tr.stats.medusa_updates += 1;
                    tr.stats.last_confidence = est.confidence;
                    let then = past_position(&tr.history, t - opts.medusa_latency_s);
                    let var = (est.covariance_m2[(0, 0)] + est.covariance_m2[(1, 1)]) / 2.0;
                    if est.confidence >= opts.min_confidence && est.yaw_bias_sigma_rad < 5f64.to_radians() {
                        tr.yaw_bias = Some(est.yaw_bias_rad);
                    }
                    // Trim: a steady velocity difference is a tilt difference (at steady state
                    // g·tan(tilt) = damping·v), in the twin's body frame (forward, left);
                    // pitch > 0 flies forward, roll > 0 flies right.
                    let yaw = f64::from(state.pose(id).rpy_rad[2]);
                    let (sy, cy) = yaw.sin_cos();
                    if hold && est.confidence >= opts.min_confidence {
                        let v = est.vel_in_world_mps;
                        tr.hold.velocity(t, [cy * v.x + sy * v.y, -sy * v.x + cy * v.y]);
                    }
                    if est.confidence >= opts.min_confidence && opts.trim_gain_rad_per_m_s > 0.0 {
                        let dv = est.vel_in_world_mps - xy(state.pose(id).vel_m_s);
                        let (fwd, left) = (cy * dv.x + sy * dv.y, -sy * dv.x + cy * dv.y);
                        let k = opts.trim_gain_rad_per_m_s * drag / sim_core::math::GRAVITY_M_S2 as f64;
                        let m = opts.max_trim_rad;
                        tr.trim[0] = (tr.trim[0] + k * fwd).clamp(-m, m);
                        tr.trim[1] = (tr.trim[1] - k * left).clamp(-m, m);
                    }
                    if est.confidence >= opts.min_confidence
                        && est.pos_in_world.iter().all(|v| v.is_finite())
                        && let Some(then) = then
                    {
                        tr.offsets[0] = Some(Offset {
                            at_s: t,
                            xy: est.pos_in_world - then,
                            var_m2: var.max(opts.medusa_sigma_floor_m.powi(2)),
                        });
                    } else {
                        tr.stats.medusa_rejected += 1;
                    }
                }
            }
            // Fuse the fresh errors, move a bounded step towards them.
            let mut sum = Vector2::zeros();
            let mut weight = 0.0;
            for o in tr.offsets.iter().flatten() {
                if t - o.at_s <= opts.source_timeout_s {
                    sum += o.xy / o.var_m2;
                    weight += 1.0 / o.var_m2;
                }
            }
            if weight <= 0.0 {
                continue;
            }
            let error = sum / weight;
            let mut step = error * (opts.gain_per_s * dt).min(1.0);
            let max = opts.max_speed_m_s * dt;
            if step.norm() > max {
                step *= max / step.norm();
            }
            if step.norm() < 1e-6 {
                continue;
            }
            state.shift_copter(id, [step.x as f32, step.y as f32]);
            // The filter's belief is about the real copter and is not moved; the errors are.
            for o in tr.offsets.iter_mut().flatten() {
                o.xy -= step;
            }
            for h in &mut tr.history {
                h.1 += step;
            }
            tr.stats.corrected_steps += 1;
            tr.stats.corrected_m += step.norm();
        }
    }

    /// Statistics per twin id.
    pub fn stats(&self) -> BTreeMap<usize, SyncStats> {
        self.twins
            .iter()
            .map(|(id, t)| {
                let trim_deg = t.total_trim(self.opts.max_trim_rad).map(f64::to_degrees);
                (*id, SyncStats { trim_deg, ..t.stats.clone() })
            })
            .collect()
    }
}

/// Where the twin was at `t_s`, interpolated from its history (`None` if too old or empty).
/// Counts a MEDUSA error of a twin, logging the first.
fn medusa_error(stats: &mut SyncStats, name: &str, e: &impl std::fmt::Display) {
    stats.medusa_errors += 1;
    if stats.medusa_errors == 1 {
        tracing::warn!("twin {name}: a MEDUSA update failed ({e}); further failures are only counted");
    }
}

fn past_position(history: &VecDeque<(f64, Vector2<f64>)>, t_s: f64) -> Option<Vector2<f64>> {
    let (first, last) = (history.front()?, history.back()?);
    if t_s >= last.0 {
        return Some(last.1);
    }
    if t_s < first.0 {
        return None;
    }
    let k = history.partition_point(|(ht, _)| *ht <= t_s);
    let (a, b) = (history[k - 1], history[k]);
    let f = if b.0 > a.0 { (t_s - a.0) / (b.0 - a.0) } else { 0.0 };
    Some(a.1 + (b.1 - a.1) * f)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn past_positions_interpolate_and_refuse_what_is_too_old() {
        let h: VecDeque<(f64, Vector2<f64>)> =
            [(1.0, Vector2::new(0.0, 0.0)), (1.05, Vector2::new(0.1, 0.0)), (1.1, Vector2::new(0.2, 0.2))].into();
        let mid = past_position(&h, 1.025).unwrap();
        assert!((mid - Vector2::new(0.05, 0.0)).norm() < 1e-12, "{mid}");
        assert_eq!(past_position(&h, 2.0), Some(Vector2::new(0.2, 0.2)), "newer than the last: the last");
        assert_eq!(past_position(&h, 0.9), None, "older than the history");
        assert_eq!(past_position(&VecDeque::new(), 1.0), None);
    }

    /// The default lab with one copter, a twin (kind `real`) flown in Manual mode.
    fn one_twin() -> World {
        let (mut spec, _) = sim_core::scene::load_default();
        spec.copters.truncate(1);
        spec.copters[0].kind = CopterKind::Real;
        spec.copters[0].mode = sim_core::FlightMode::Manual;
        sim_core::compile(&spec).unwrap()
    }

    #[test]
    fn a_twin_whose_link_is_lost_stops_flying_its_last_attitude_targets() {
        let world = one_twin();
        let state = world.initial_state();
        let mut inputs = world.initial_inputs();
        let mut sync = TwinSync::new(&world, SyncOptions::default()).unwrap();
        sync.on_command(&world, &state, 0, Some(0.1), Some(-0.05), Some(0.3));
        sync.adjust_commands(&mut inputs);
        assert_eq!((inputs.commands[0].pitch_rad, inputs.commands[0].roll_rad), (0.1, -0.05));
        // The loop levels the silent twin out; the sync must not tilt it again.
        sync.on_link_lost(0);
        (inputs.commands[0].pitch_rad, inputs.commands[0].roll_rad) = (0.0, 0.0);
        for _ in 0..3 {
            sync.adjust_commands(&mut inputs);
        }
        assert_eq!((inputs.commands[0].pitch_rad, inputs.commands[0].roll_rad), (0.0, 0.0));
        // Telemetry back: its targets fly again.
        sync.on_command(&world, &state, 0, Some(-0.02), Some(0.04), None);
        sync.adjust_commands(&mut inputs);
        assert_eq!((inputs.commands[0].pitch_rad, inputs.commands[0].roll_rad), (-0.02, 0.04));
    }

    #[test]
    fn the_hold_trim_learns_the_attitude_at_which_the_real_copter_holds_still() {
        let world = one_twin();
        let opts = SyncOptions { medusa: false, tracking: false, ..SyncOptions::default() };
        let steps_of = |s: f64| (s / world.params.control_dt_s).round() as usize;
        // The real copter holds still pitched 3° and rolled −2° from its level on the floor
        // (unequal rotors): its telemetry says so throughout.
        let (p, r) = (3f32.to_radians(), -2f32.to_radians());
        let fly = |opts: SyncOptions, airborne_s: f64| {
            let (mut state, mut inputs) = (world.initial_state(), world.initial_inputs());
            let (state, inputs) = (&mut state, &mut inputs);
            let mut sync = TwinSync::new(&world, opts).unwrap();
            sync.on_command(&world, state, 0, Some(p), Some(r), None);
            // On the floor nothing is learnt.
            for _ in 0..steps_of(2.0) {
                state.tick += 1;
                sync.after_step(&world, state, inputs);
            }
            state.copters[0].took_off_tick = Some(state.tick);
            state.copters[0].grounded = false;
            for _ in 0..steps_of(airborne_s) {
                state.tick += 1;
                sync.after_step(&world, state, inputs);
            }
            sync.adjust_commands(inputs);
            [inputs.commands[0].pitch_rad, inputs.commands[0].roll_rad]
        };
        assert_eq!(fly(opts.clone(), 0.0), [p, r], "nothing learnt yet");
        // Three time constants in the air: the twin flies within 0.1° of level.
        let [tp, tr] = fly(opts.clone(), 30.0);
        assert!(
            tp.to_degrees().abs() < 0.1 && tr.to_degrees().abs() < 0.1,
            "{}° {}°",
            tp.to_degrees(),
            tr.to_degrees()
        );
        // Turned off, the targets fly as they came.
        let off = SyncOptions { hold_trim_time_constant_s: 0.0, ..opts };
        assert_eq!(fly(off, 30.0), [p, r]);
    }

    #[test]
    fn the_hold_trim_takes_off_what_the_copters_own_acceleration_explains() {
        // Pitched just enough to accelerate at 0.3 m/s² for 20 s, MEDUSA's velocity saying so
        // every 0.1 s: no trim. Without the velocities the whole pitch is taken for trim.
        let g = f64::from(sim_core::math::GRAVITY_M_S2);
        let (a, dt) = (0.3, 0.01);
        let pitch = (a / g) as f32;
        let opts = SyncOptions::default();
        let (mut seen, mut blind) = (HoldTrim::new(&opts, 0.0), HoldTrim::new(&opts, 0.0));
        for i in 0..2000 {
            let t = f64::from(i) * dt;
            seen.step(opts.hold_trim_time_constant_s, dt, t, [pitch, 0.0]);
            blind.step(opts.hold_trim_time_constant_s, dt, t, [pitch, 0.0]);
            if i % 10 == 0 {
                seen.velocity(t, [a * t, 0.0]);
            }
        }
        assert!(seen.trim()[0].to_degrees().abs() < 0.1, "{}°", seen.trim()[0].to_degrees());
        let expect = -f64::from(pitch);
        assert!((blind.trim()[0] - expect).abs() < 0.1 * expect.abs(), "{} against {expect}", blind.trim()[0]);
    }

    #[test]
    fn a_tracking_pose_moves_a_twin_smoothly_and_no_further_than_the_error() {
        let world = one_twin();
        let mut state = world.initial_state();
        let inputs = world.initial_inputs();
        let opts = SyncOptions { medusa: false, tracking_lag_s: 0.0, ..SyncOptions::default() };
        let mut sync = TwinSync::new(&world, opts.clone()).unwrap();
        let start = state.pose(0).pos_m;
        sim_core::step(&world, &mut state, &inputs);
        sync.after_step(&world, &mut state, &inputs);
        // The real copter stays 0.5 m further along +x than where the twin started; a tracker
        // reports it every step.
        let real = [start.x + 0.5, start.y];
        let max_step = opts.max_speed_m_s * world.params.control_dt_s;
        let mut last = state.pose(0).pos_m.x;
        for _ in 0..100 {
            let t = state.time_s(&world);
            sync.on_tracking(&world, &state, 0, t, real);
            sim_core::step(&world, &mut state, &inputs);
            sync.after_step(&world, &mut state, &inputs);
            // The step moves it by its own velocity and by the correction (a shift).
            let pose = state.pose(0);
            let (x, own) = (pose.pos_m.x, pose.vel_m_s.x * world.params.control_dt_s as f32);
            assert!(x - last - own <= max_step as f32 + 1e-3, "a correction step of {} m", x - last - own);
            last = x;
        }
        // It hovers on its own while being pulled to the pose: uncommanded, the particle model's
        // thrust noise drifts it at up to 0.2 m/s here, which the pull holds to a few cm.
        let p = state.pose(0).pos_m;
        let error = ((p.x - real[0]).powi(2) + (p.y - real[1]).powi(2)).sqrt();
        assert!(error < 0.08, "{error} m from the tracked pose after 5 s (0.5 m at the start)");
        assert_eq!(sync.stats()[&0].tracking_updates, 100);
    }
}
