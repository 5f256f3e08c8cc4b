//! Temporal Bayes filter (particle filter) around the MEDUSA sensor model.

use nalgebra::{Matrix2, Vector2};

use crate::error::MedusaError;
use crate::medusa::{CONFIDENCE_SPREAD_M, FIT_GOOD, Medusa, MedusaResult, sanitize_unit};
use crate::rng::Pcg32;
use crate::sensor::{Observation, YawEstimate, validate_readings};

/// Standard gravity (m/s²) used to turn attitude into acceleration.
pub const GRAVITY_MPS2: f64 = 9.806_65;
/// Kernel standard deviation of the mean-shift used to pick the dominant
/// mode of the particle cloud (m).
const MODE_KERNEL_M: f64 = 0.15;
/// Number of heaviest particles tried as mean-shift starting points.
const MODE_SEEDS: usize = 12;
/// Smoothing factor of the fast fit average (per correction).
const FIT_ALPHA_FAST: f64 = 0.3;
/// Smoothing factor of the slow fit average (per correction).
const FIT_ALPHA_SLOW: f64 = 0.02;
/// Fit below which the filter considers itself lost and re-seeds from raw
/// MEDUSA at the full injection rate.
const FIT_LOST: f64 = 0.08;
/// Bias estimates larger than this trigger a second, bias-corrected MEDUSA
/// run for re-localisation (rad).
const BIAS_SPLIT_THRESHOLD_RAD: f64 = 0.01;
/// Spread of the yaw bias given to re-localisation particles (rad).
const INJECTED_BIAS_SIGMA_RAD: f64 = 0.01;
/// Re-localisation particles start with their weight reduced by this many
/// log units: they must explain the next readings clearly better than the
/// tracked cloud to take over, so a single misleading frame cannot make the
/// estimate jump, while a persistently better hypothesis wins within a few
/// cycles.
const INJECTED_LOG_WEIGHT_PENALTY: f64 = 3.0;
/// Log-weight penalty for particles inside a box obstacle.
const INSIDE_BOX_PENALTY: f64 = 30.0;

/// Tuning of [`MedusaFilter`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FilterConfig {
    /// Number of particles (>= 16). Default 300. Cost is linear in it.
    pub num_particles: usize,
    /// Seed of the filter's internal PRNG: the filter is a deterministic
    /// function of the seed and its inputs.
    pub seed: u64,
    /// Speed cap of the motion model (m/s). Default 1.5.
    pub max_speed_mps: f64,
    /// Linear drag of the motion model (1/s): `dv/dt = a_cmd - drag * v`.
    /// Default 0.3.
    pub drag_per_s: f64,
    /// Velocity random walk modelling unmodelled forces and attitude-tracking
    /// errors (m/s per sqrt(s)). Default 0.5.
    pub velocity_noise_mps_per_sqrt_s: f64,
    /// Position random walk keeping the particle set diverse (m per sqrt(s)).
    /// Default 0.02.
    pub position_noise_m_per_sqrt_s: f64,
    /// Random walk of the estimated yaw bias (rad per sqrt(s)). Default 1°.
    pub yaw_bias_noise_rad_per_sqrt_s: f64,
    /// Prior standard deviation of the yaw bias (rad). Default 5°.
    pub initial_yaw_bias_sigma_rad: f64,
    /// Bound on the estimated yaw bias magnitude (rad). Default 30°.
    pub max_yaw_bias_rad: f64,
    /// Particles are kept this far from the arena walls (m): the copter's
    /// radius, or 0. Default 0.
    pub wall_margin_m: f64,
    /// Largest fraction of particles replaced per correction by samples
    /// drawn from raw MEDUSA when the readings stop fitting (sensor
    /// resetting / augmented MCL). Default 0.2; 0 disables re-localisation.
    pub max_injection_fraction: f64,
    /// Fraction of particles replaced by raw-MEDUSA samples at every
    /// correction, even when the readings fit. This keeps alternative
    /// hypotheses alive when the cloud has settled on a wrong mode that fits
    /// the readings almost as well (e.g. a wrong yaw bias making a grazing
    /// wall echo look right). Default 0.02; capped by
    /// `max_injection_fraction`.
    pub background_injection_fraction: f64,
    /// Resample when the effective sample size falls below this fraction
    /// of the particle count. Default 0.5.
    pub resample_threshold: f64,
}

impl Default for FilterConfig {
    fn default() -> Self {
        Self {
            num_particles: 300,
            seed: 0x4d45_4455_5341,
            max_speed_mps: 1.5,
            drag_per_s: 0.3,
            velocity_noise_mps_per_sqrt_s: 0.5,
            position_noise_m_per_sqrt_s: 0.02,
            yaw_bias_noise_rad_per_sqrt_s: 1f64.to_radians(),
            initial_yaw_bias_sigma_rad: 5f64.to_radians(),
            max_yaw_bias_rad: 30f64.to_radians(),
            wall_margin_m: 0.0,
            max_injection_fraction: 0.2,
            background_injection_fraction: 0.02,
            resample_threshold: 0.5,
        }
    }
}

impl FilterConfig {
    fn validate(&self) -> Result<(), MedusaError> {
        let check = |name: &'static str, value: f64, ok: bool, reason: &'static str| {
            if ok && value.is_finite() { Ok(()) } else { Err(MedusaError::InvalidParameter { name, value, reason }) }
        };
        let n = self.num_particles as f64;
        check("num_particles", n, self.num_particles >= 16, "must be >= 16")?;
        check("max_speed_mps", self.max_speed_mps, self.max_speed_mps > 0.0, "must be > 0")?;
        let nonneg: [(&'static str, f64); 7] = [
            ("drag_per_s", self.drag_per_s),
            ("velocity_noise_mps_per_sqrt_s", self.velocity_noise_mps_per_sqrt_s),
            ("position_noise_m_per_sqrt_s", self.position_noise_m_per_sqrt_s),
            ("yaw_bias_noise_rad_per_sqrt_s", self.yaw_bias_noise_rad_per_sqrt_s),
            ("initial_yaw_bias_sigma_rad", self.initial_yaw_bias_sigma_rad),
            ("max_yaw_bias_rad", self.max_yaw_bias_rad),
            ("wall_margin_m", self.wall_margin_m),
        ];
        for (name, v) in nonneg {
            check(name, v, v >= 0.0, "must be >= 0")?;
        }
        check(
            "max_injection_fraction",
            self.max_injection_fraction,
            (0.0..=1.0).contains(&self.max_injection_fraction),
            "must be in [0, 1]",
        )?;
        check(
            "background_injection_fraction",
            self.background_injection_fraction,
            (0.0..=1.0).contains(&self.background_injection_fraction),
            "must be in [0, 1]",
        )?;
        check(
            "resample_threshold",
            self.resample_threshold,
            (0.0..=1.0).contains(&self.resample_threshold),
            "must be in [0, 1]",
        )
    }
}

/// Control input of the motion model: the commanded horizontal
/// acceleration in the body frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionInput {
    /// Commanded acceleration in the body frame (m/s²), body `x` forward,
    /// `y` left.
    pub accel_in_body_mps2: Vector2<f64>,
}

impl MotionInput {
    /// From a commanded attitude, as `g * tan(angle)` per axis.
    ///
    /// Convention (right-handed rotations in the FLU body frame, z up):
    /// positive `pitch_rad` (about body `+y`) tilts the nose down and
    /// accelerates forward (`+x` body); positive `roll_rad` (about body `+x`)
    /// raises the left side and accelerates towards body `-y` (to the
    /// right). Negate the angles if the autopilot uses another convention.
    pub fn from_attitude(pitch_rad: f64, roll_rad: f64) -> Self {
        Self { accel_in_body_mps2: Vector2::new(GRAVITY_MPS2 * pitch_rad.tan(), -GRAVITY_MPS2 * roll_rad.tan()) }
    }

    /// No commanded acceleration (hover).
    pub fn zero() -> Self {
        Self { accel_in_body_mps2: Vector2::zeros() }
    }
}

/// One particle (a weighted state hypothesis).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Particle {
    /// Position of the body centre (m).
    pub pos_in_world: Vector2<f64>,
    /// Velocity (m/s).
    pub vel_in_world_mps: Vector2<f64>,
    /// Yaw bias: `yaw_estimate - true_yaw` (rad).
    pub yaw_bias_rad: f64,
    /// Normalised weight.
    pub weight: f64,
}

/// The filter's output.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FilterEstimate {
    /// Estimated position of the body centre (m): the dominant mode of the
    /// particle cloud.
    pub pos_in_world: Vector2<f64>,
    /// Covariance of the position (m²) around `pos_in_world`, over all
    /// particles (so multi-modality shows up as a large covariance).
    pub covariance_m2: Matrix2<f64>,
    /// Confidence in [0, 1]: a spread factor
    /// `exp(-trace(cov) / (2 * CONFIDENCE_SPREAD_M²))` times a fit factor
    /// (recent per-sensor geometric-mean likelihood relative to a perfect
    /// fit, saturating at 0.3).
    pub confidence: f64,
    /// Estimated velocity (m/s).
    pub vel_in_world_mps: Vector2<f64>,
    /// Estimated yaw bias `yaw_estimate - true_yaw` (rad).
    pub yaw_bias_rad: f64,
    /// Standard deviation of the yaw bias (rad).
    pub yaw_bias_sigma_rad: f64,
    /// Recent goodness of fit of the readings, in [0, 1] (smoothed).
    pub measurement_fit: f64,
    /// Effective sample size of the last correction, as a fraction in (0, 1].
    pub effective_sample_fraction: f64,
}

#[derive(Debug, Clone, Copy)]
struct P {
    x: f64,
    y: f64,
    vx: f64,
    vy: f64,
    b: f64,
    w: f64,
}

/// MEDUSA particle filter: tracks position, velocity and yaw bias.
///
/// Use [`MedusaFilter::update`] once per sonar cycle, or
/// [`MedusaFilter::predict`] at the control rate and
/// [`MedusaFilter::correct`] when readings arrive.
#[derive(Debug, Clone)]
pub struct MedusaFilter {
    medusa: Medusa,
    config: FilterConfig,
    particles: Vec<P>,
    scratch: Vec<P>,
    log_w: Vec<f64>,
    rng: Pcg32,
    fit_fast: f64,
    fit_slow: f64,
    ess_fraction: f64,
    estimate: FilterEstimate,
}

impl MedusaFilter {
    /// A filter with particles spread uniformly over free space.
    ///
    /// # Errors
    /// [`MedusaError::InvalidParameter`] for an invalid configuration.
    pub fn new(medusa: Medusa, config: FilterConfig) -> Result<Self, MedusaError> {
        config.validate()?;
        let n = config.num_particles;
        let mut filter = Self {
            medusa,
            config,
            particles: Vec::with_capacity(n),
            scratch: Vec::with_capacity(n),
            log_w: vec![0.0; n],
            rng: Pcg32::new(config.seed),
            fit_fast: FIT_GOOD,
            fit_slow: FIT_GOOD,
            ess_fraction: 1.0,
            estimate: FilterEstimate {
                pos_in_world: Vector2::zeros(),
                covariance_m2: Matrix2::identity(),
                confidence: 0.0,
                vel_in_world_mps: Vector2::zeros(),
                yaw_bias_rad: 0.0,
                yaw_bias_sigma_rad: config.initial_yaw_bias_sigma_rad,
                measurement_fit: 0.0,
                effective_sample_fraction: 1.0,
            },
        };
        filter.reset_uniform();
        Ok(filter)
    }

    /// The localiser (world, sensors, sensor model).
    pub fn medusa(&self) -> &Medusa {
        &self.medusa
    }

    /// The configuration.
    pub fn config(&self) -> &FilterConfig {
        &self.config
    }

    /// The last estimate.
    pub fn estimate(&self) -> FilterEstimate {
        self.estimate
    }

    /// A copy of the particle set (for visualisation and debugging).
    pub fn particles(&self) -> Vec<Particle> {
        self.particles
            .iter()
            .map(|p| Particle {
                pos_in_world: Vector2::new(p.x, p.y),
                vel_in_world_mps: Vector2::new(p.vx, p.vy),
                yaw_bias_rad: p.b,
                weight: p.w,
            })
            .collect()
    }

    /// Forget everything: particles uniform over free space, zero velocity,
    /// yaw bias from its prior.
    pub fn reset_uniform(&mut self) {
        let n = self.config.num_particles;
        let arena = *self.medusa.world().arena();
        let (hw, hh) = (arena.half_width_m(), arena.half_height_m());
        self.particles.clear();
        for _ in 0..n {
            let mut pos = Vector2::zeros();
            for _ in 0..64 {
                let cand = Vector2::new((2.0 * self.rng.uniform() - 1.0) * hw, (2.0 * self.rng.uniform() - 1.0) * hh);
                pos = arena.clamp(&cand, self.config.wall_margin_m);
                if self.medusa.world().is_free(&pos, 0.0) {
                    break;
                }
            }
            let b = self.sample_bias_prior();
            self.particles.push(P { x: pos.x, y: pos.y, vx: 0.0, vy: 0.0, b, w: 1.0 / n as f64 });
        }
        self.after_reset();
    }

    /// Reset around a known position with an isotropic spread `sigma_m`.
    ///
    /// # Errors
    /// [`MedusaError::InvalidParameter`] for a non-finite position or a
    /// negative / non-finite sigma.
    pub fn reset_at(&mut self, pos_in_world: Vector2<f64>, sigma_m: f64) -> Result<(), MedusaError> {
        if !(pos_in_world.x.is_finite() && pos_in_world.y.is_finite()) {
            return Err(MedusaError::InvalidParameter {
                name: "pos_in_world",
                value: if pos_in_world.x.is_finite() { pos_in_world.y } else { pos_in_world.x },
                reason: "must be finite",
            });
        }
        if !(sigma_m.is_finite() && sigma_m >= 0.0) {
            return Err(MedusaError::InvalidParameter {
                name: "sigma_m",
                value: sigma_m,
                reason: "must be finite and >= 0",
            });
        }
        let n = self.config.num_particles;
        let arena = *self.medusa.world().arena();
        self.particles.clear();
        for _ in 0..n {
            let cand = Vector2::new(
                pos_in_world.x + sigma_m * self.rng.normal(),
                pos_in_world.y + sigma_m * self.rng.normal(),
            );
            let pos = arena.clamp(&cand, self.config.wall_margin_m);
            let b = self.sample_bias_prior();
            self.particles.push(P { x: pos.x, y: pos.y, vx: 0.0, vy: 0.0, b, w: 1.0 / n as f64 });
        }
        self.after_reset();
        Ok(())
    }

    fn sample_bias_prior(&mut self) -> f64 {
        let m = self.config.max_yaw_bias_rad;
        (self.config.initial_yaw_bias_sigma_rad * self.rng.normal()).clamp(-m, m)
    }

    fn after_reset(&mut self) {
        self.fit_fast = FIT_GOOD;
        self.fit_slow = FIT_GOOD;
        self.ess_fraction = 1.0;
        self.estimate = self.compute_estimate();
    }

    /// Predict then correct: one full filter cycle.
    ///
    /// `dt_s` is the time since the previous update, `input` the commanded
    /// acceleration over that interval, `yaw` the current yaw estimate and
    /// `readings_m` one entry per sensor (`None` or `>= max range` = no echo).
    ///
    /// # Errors
    /// Invalid `dt_s`, input, yaw or readings (see [`MedusaError`]); the
    /// filter state is unchanged on error.
    pub fn update(
        &mut self,
        dt_s: f64,
        input: &MotionInput,
        yaw: YawEstimate,
        readings_m: &[Option<f64>],
    ) -> Result<FilterEstimate, MedusaError> {
        // Validate everything first so that an error leaves the state intact.
        yaw.validate()?;
        let obs = validate_readings(self.medusa.layout(), readings_m)?;
        self.predict(dt_s, input, yaw)?;
        Ok(self.correct_obs(yaw, &obs))
    }

    /// Motion update only.
    ///
    /// # Errors
    /// [`MedusaError::InvalidParameter`] for a negative or non-finite `dt_s`
    /// or a non-finite input; [`MedusaError::InvalidYaw`] for a bad yaw.
    pub fn predict(&mut self, dt_s: f64, input: &MotionInput, yaw: YawEstimate) -> Result<(), MedusaError> {
        yaw.validate()?;
        if !(dt_s.is_finite() && dt_s >= 0.0) {
            return Err(MedusaError::InvalidParameter { name: "dt_s", value: dt_s, reason: "must be finite and >= 0" });
        }
        let a = input.accel_in_body_mps2;
        if !(a.x.is_finite() && a.y.is_finite()) {
            return Err(MedusaError::InvalidParameter {
                name: "accel_in_body_mps2",
                value: if a.x.is_finite() { a.y } else { a.x },
                reason: "must be finite",
            });
        }
        if dt_s == 0.0 {
            return Ok(());
        }
        let cfg = self.config;
        let sq = dt_s.sqrt();
        let qv = cfg.velocity_noise_mps_per_sqrt_s * sq;
        let qp = cfg.position_noise_m_per_sqrt_s * sq;
        let qb = cfg.yaw_bias_noise_rad_per_sqrt_s * sq;
        let arena = *self.medusa.world().arena();
        let margin = cfg.wall_margin_m.min(0.25 * arena.width_m().min(arena.height_m()));
        let hx = arena.half_width_m() - margin;
        let hy = arena.half_height_m() - margin;
        // Exact integration of the linear drag over dt.
        let decay = (-cfg.drag_per_s * dt_s).exp();
        let gain = if cfg.drag_per_s > 1e-9 { (1.0 - decay) / cfg.drag_per_s } else { dt_s };
        for i in 0..self.particles.len() {
            let (n1, n2, n3, n4, n5) =
                (self.rng.normal(), self.rng.normal(), self.rng.normal(), self.rng.normal(), self.rng.normal());
            let p = &mut self.particles[i];
            let (s, c) = (yaw.yaw_rad - p.b).sin_cos();
            let ax = c * a.x - s * a.y;
            let ay = s * a.x + c * a.y;
            let vx0 = p.vx;
            let vy0 = p.vy;
            let mut vx = vx0 * decay + ax * gain + qv * n1;
            let mut vy = vy0 * decay + ay * gain + qv * n2;
            let speed = (vx * vx + vy * vy).sqrt();
            if speed > cfg.max_speed_mps {
                let k = cfg.max_speed_mps / speed;
                vx *= k;
                vy *= k;
            }
            let mut x = p.x + 0.5 * (vx0 + vx) * dt_s + qp * n3;
            let mut y = p.y + 0.5 * (vy0 + vy) * dt_s + qp * n4;
            if x.abs() > hx {
                x = x.clamp(-hx, hx);
                vx = 0.0;
            }
            if y.abs() > hy {
                y = y.clamp(-hy, hy);
                vy = 0.0;
            }
            p.x = x;
            p.y = y;
            p.vx = vx;
            p.vy = vy;
            p.b = (p.b + qb * n5).clamp(-cfg.max_yaw_bias_rad, cfg.max_yaw_bias_rad);
        }
        Ok(())
    }

    /// Measurement update only.
    ///
    /// # Errors
    /// Invalid yaw or readings (see [`MedusaError`]).
    pub fn correct(&mut self, yaw: YawEstimate, readings_m: &[Option<f64>]) -> Result<FilterEstimate, MedusaError> {
        yaw.validate()?;
        let obs = validate_readings(self.medusa.layout(), readings_m)?;
        Ok(self.correct_obs(yaw, &obs))
    }

    fn correct_obs(&mut self, yaw: YawEstimate, obs: &[Observation]) -> FilterEstimate {
        let n = self.particles.len();
        let has_boxes = !self.medusa.world().obstacles().is_empty();
        let mut max_lw = f64::NEG_INFINITY;
        let mut max_fit = f64::NEG_INFINITY;
        let mut fit_terms = std::mem::take(&mut self.log_w);
        fit_terms.resize(n, 0.0);
        for (i, p) in self.particles.iter_mut().enumerate() {
            let (sy, cy) = (yaw.yaw_rad - p.b).sin_cos();
            let (mut ll, ln_fit) = self.medusa.score(p.x, p.y, cy, sy, yaw.sigma_rad, obs);
            if has_boxes && self.medusa.world().obstacles().iter().any(|o| o.contains(&Vector2::new(p.x, p.y), 0.0)) {
                ll -= INSIDE_BOX_PENALTY;
            }
            let ln_w = p.w.max(1e-300).ln();
            fit_terms[i] = ln_w + ln_fit;
            max_fit = max_fit.max(fit_terms[i]);
            // Store the new log-weight in the weight slot temporarily.
            p.w = ln_w + ll;
            max_lw = max_lw.max(p.w);
        }
        // Predictive fit: ln sum_i w_i * fit_i, per sensor.
        let mut fit_sum = 0.0;
        for f in &fit_terms {
            fit_sum += (f - max_fit).exp();
        }
        let ln_pred_fit = max_fit + fit_sum.ln();
        self.log_w = fit_terms;
        let fit = sanitize_unit((ln_pred_fit / obs.len().max(1) as f64).exp());

        let mut total = 0.0;
        for p in &mut self.particles {
            p.w = (p.w - max_lw).exp();
            total += p.w;
        }
        if !(total.is_finite() && total > 0.0) {
            for p in &mut self.particles {
                p.w = 1.0 / n as f64;
            }
        } else {
            for p in &mut self.particles {
                p.w /= total;
            }
        }
        let sum_w2: f64 = self.particles.iter().map(|p| p.w * p.w).sum();
        self.ess_fraction = sanitize_unit(1.0 / (sum_w2 * n as f64));

        self.fit_fast += FIT_ALPHA_FAST * (fit - self.fit_fast);
        self.fit_slow += FIT_ALPHA_SLOW * (fit - self.fit_slow);
        self.estimate = self.compute_estimate();

        let inject = self.injection_count();
        if inject > 0 || self.ess_fraction < self.config.resample_threshold {
            self.resample();
        }
        if inject > 0 {
            // Half of the new particles come from MEDUSA run with the yaw as
            // given (zero bias), half with the yaw corrected by the current
            // bias estimate, so that neither a wrong bias estimate nor a real
            // AHRS bias blocks re-localisation.
            let b_est = self.estimate.yaw_bias_rad;
            let unbiased = self.medusa.locate_obs(yaw, obs);
            if b_est.abs() > BIAS_SPLIT_THRESHOLD_RAD {
                let debiased = self.medusa.locate_obs(YawEstimate::new(yaw.yaw_rad - b_est, yaw.sigma_rad), obs);
                let half = inject / 2;
                self.inject(&unbiased, inject - half, 0.0);
                self.inject(&debiased, half, b_est);
            } else {
                self.inject(&unbiased, inject, 0.0);
            }
            let total: f64 = self.particles.iter().map(|p| p.w).sum();
            if total > 0.0 && total.is_finite() {
                for p in &mut self.particles {
                    p.w /= total;
                }
            }
        }
        self.estimate
    }

    /// How many particles to replace with raw-MEDUSA samples.
    fn injection_count(&self) -> usize {
        let max_frac = self.config.max_injection_fraction;
        if max_frac <= 0.0 {
            return 0;
        }
        // Augmented MCL: the short-term fit dropped well below the long-term one.
        let ratio = if self.fit_slow > 1e-12 { self.fit_fast / self.fit_slow } else { 1.0 };
        let relative = ((0.5 - ratio) / 0.5).clamp(0.0, 1.0);
        // Absolute: the readings do not fit at all.
        let absolute = ((FIT_LOST - self.fit_fast) / FIT_LOST).clamp(0.0, 1.0);
        let frac = (max_frac * relative.max(absolute)).max(self.config.background_injection_fraction).min(max_frac);
        (frac * self.particles.len() as f64).round() as usize
    }

    /// Systematic resampling (one uniform draw).
    fn resample(&mut self) {
        let n = self.particles.len();
        let step = 1.0 / n as f64;
        let mut u = self.rng.uniform() * step;
        let mut cum = 0.0;
        let mut idx = 0;
        self.scratch.clear();
        for _ in 0..n {
            while idx + 1 < n && cum + self.particles[idx].w < u {
                cum += self.particles[idx].w;
                idx += 1;
            }
            let mut p = self.particles[idx];
            p.w = step;
            self.scratch.push(p);
            u += step;
        }
        std::mem::swap(&mut self.particles, &mut self.scratch);
    }

    /// Replace `count` random particles by samples around raw-MEDUSA
    /// candidates (drawn by candidate probability), with a yaw bias near
    /// `bias_rad` (the bias MEDUSA was run with).
    fn inject(&mut self, result: &MedusaResult, count: usize, bias_rad: f64) {
        let n = self.particles.len();
        let cands = &result.candidates;
        if cands.is_empty() || count == 0 {
            return;
        }
        let max_b = self.config.max_yaw_bias_rad;
        let injected_w = (-INJECTED_LOG_WEIGHT_PENALTY).exp() / n as f64;
        let sigma = self.medusa.model().noise_sigma_m;
        let arena = *self.medusa.world().arena();
        let vel = self.estimate.vel_in_world_mps;
        let step = 1.0 / count as f64;
        let mut u = self.rng.uniform() * step;
        let mut cum = 0.0;
        let mut idx = 0;
        for _ in 0..count {
            while idx + 1 < cands.len() && cum + cands[idx].probability < u {
                cum += cands[idx].probability;
                idx += 1;
            }
            u += step;
            let centre = if idx == 0 { result.refined.pos_in_world } else { cands[idx].pos_in_world };
            let target = ((self.rng.uniform() * n as f64) as usize).min(n - 1);
            let pos = arena.clamp(
                &Vector2::new(centre.x + sigma * self.rng.normal(), centre.y + sigma * self.rng.normal()),
                self.config.wall_margin_m,
            );
            let bias_noise = self.rng.normal();
            let p = &mut self.particles[target];
            p.x = pos.x;
            p.y = pos.y;
            p.vx = vel.x;
            p.vy = vel.y;
            p.b = (bias_rad + INJECTED_BIAS_SIGMA_RAD * bias_noise).clamp(-max_b, max_b);
            p.w = injected_w;
        }
    }

    fn compute_estimate(&self) -> FilterEstimate {
        let ps = &self.particles;
        let inv2k = 1.0 / (2.0 * MODE_KERNEL_M * MODE_KERNEL_M);
        let density = |x: f64, y: f64| -> f64 {
            ps.iter().map(|p| p.w * (-((p.x - x).powi(2) + (p.y - y).powi(2)) * inv2k).exp()).sum()
        };
        // Start the mean shift at the densest of the heaviest particles (a
        // single heavy particle, e.g. a fresh re-localisation sample, must
        // not pull the estimate away from the bulk of the probability).
        let mut order: Vec<usize> = (0..ps.len()).collect();
        order.sort_by(|&a, &b| ps[b].w.total_cmp(&ps[a].w).then(a.cmp(&b)));
        let mut start = (0.0, 0.0);
        let mut best_density = f64::NEG_INFINITY;
        for &i in order.iter().take(MODE_SEEDS) {
            let d = density(ps[i].x, ps[i].y);
            if d > best_density {
                best_density = d;
                start = (ps[i].x, ps[i].y);
            }
        }
        let (mut mx, mut my) = start;
        for _ in 0..4 {
            let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
            for p in ps {
                let d2 = (p.x - mx).powi(2) + (p.y - my).powi(2);
                let k = p.w * (-d2 * inv2k).exp();
                sw += k;
                sx += k * p.x;
                sy += k * p.y;
            }
            if sw > 0.0 && sw.is_finite() {
                mx = sx / sw;
                my = sy / sw;
            }
        }
        let (mut cxx, mut cxy, mut cyy) = (0.0, 0.0, 0.0);
        let (mut vx, mut vy, mut bm, mut b2, mut wsum) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for p in ps {
            let (dx, dy) = (p.x - mx, p.y - my);
            cxx += p.w * dx * dx;
            cxy += p.w * dx * dy;
            cyy += p.w * dy * dy;
            vx += p.w * p.vx;
            vy += p.w * p.vy;
            bm += p.w * p.b;
            b2 += p.w * p.b * p.b;
            wsum += p.w;
        }
        if wsum > 0.0 && wsum.is_finite() {
            cxx /= wsum;
            cxy /= wsum;
            cyy /= wsum;
            vx /= wsum;
            vy /= wsum;
            bm /= wsum;
            b2 /= wsum;
        }
        let spread = (-(cxx + cyy) / (2.0 * CONFIDENCE_SPREAD_M * CONFIDENCE_SPREAD_M)).exp();
        let fit_factor = (self.fit_fast / FIT_GOOD).min(1.0);
        let finite_or = |v: f64, d: f64| if v.is_finite() { v } else { d };
        FilterEstimate {
            pos_in_world: Vector2::new(finite_or(mx, 0.0), finite_or(my, 0.0)),
            covariance_m2: Matrix2::new(
                finite_or(cxx, 1.0),
                finite_or(cxy, 0.0),
                finite_or(cxy, 0.0),
                finite_or(cyy, 1.0),
            ),
            confidence: sanitize_unit(spread * fit_factor),
            vel_in_world_mps: Vector2::new(finite_or(vx, 0.0), finite_or(vy, 0.0)),
            yaw_bias_rad: finite_or(bm, 0.0),
            yaw_bias_sigma_rad: finite_or((b2 - bm * bm).max(0.0).sqrt(), 0.0),
            measurement_fit: sanitize_unit(self.fit_fast),
            effective_sample_fraction: self.ess_fraction,
        }
    }
}
