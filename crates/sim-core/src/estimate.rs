//! Estimators between the sensors and the controllers, as on the FINken's autopilot. The
//! controllers read only these estimates; ground truth is for logging and scoring.
//!
//! - **Height** above whatever is below (floor, table, another copter), from the downward IR
//!   sensor: an α–β filter predicted with the accelerometer and corrected with the IR
//!   distance times the cosine of the tilt, once per control step. Out of range, the side
//!   the reading fell off tells what is known: below the minimum range the height is at most
//!   that, beyond the maximum (1.5 m) at least that; either way the estimate dead-reckons on the
//!   accelerometer with its vertical speed leaking to zero (the FINken has no other height
//!   sensor in its loop). Height setpoints are held within the IR's range for that reason.
//! - **Attitude and rates** from the AHRS (Paparazzi's complementary filter on the Aspirin IMU):
//!   the truth through a first-order lag (the IMU's low-pass filter and the filter's own
//!   delay), plus a slowly wandering roll and pitch bias (Gauss–Markov), the drifting yaw bias
//!   of [`crate::sensors`], a per-copter residual gyro bias and white noise.
//! - **Thrust gain**, Paparazzi's adaptive hover throttle (`GUIDANCE_V_ADAPT_THROTTLE`): the
//!   ratio of the thrust the accelerometer feels to the thrust commanded, low-passed. The
//!   height loop divides its command by it, which absorbs battery sag and rotor tolerances.
//!
//! Twins (kind `real`) and `[sensors.estimator] ideal = true` use the truth: a twin flies on its
//! real copter's telemetry, which is already an estimate.

use serde::{Deserialize, Serialize};

use crate::error::{FieldPath, PathSeg, SceneError};
use crate::finken_height::FinkenHeightState;
use crate::math::{Real, wrap_angle_rad};
use crate::rng::Rng32;
use crate::sensors::ir::IrSpec;

/// `[sensors.estimator]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EstimatorSpec {
    /// Controllers read ground truth instead of estimates (a comparison aid: no real copter
    /// can).
    pub ideal: bool,
    /// α of the height filter: the share of an IR innovation taken into the height.
    pub height_alpha: Real,
    /// β of the height filter: the share taken into the vertical speed (per control step).
    pub height_beta: Real,
    /// Beyond the IR's range the vertical speed estimate decays with this time constant, s.
    pub fallback_leak_s: Real,
    /// AHRS lag, s.
    pub ahrs_lag_s: Real,
    /// Standard deviation of the wandering roll and pitch bias, deg.
    pub attitude_bias_deg: Real,
    /// Correlation time of that bias, s.
    pub attitude_bias_time_s: Real,
    /// Standard deviation of each copter's residual gyro bias, deg/s.
    pub gyro_bias_deg_s: Real,
    /// Time constant of the adaptive thrust gain, s; 0 turns it off.
    pub thrust_adapt_time_s: Real,
}

impl Default for EstimatorSpec {
    fn default() -> Self {
        Self {
            ideal: false,
            height_alpha: 0.4,
            height_beta: 0.1,
            fallback_leak_s: 1.0,
            ahrs_lag_s: 0.005,
            attitude_bias_deg: 0.15,
            attitude_bias_time_s: 20.0,
            gyro_bias_deg_s: 0.2,
            thrust_adapt_time_s: 1.0,
        }
    }
}

impl EstimatorSpec {
    pub(crate) fn validate(&self, path: &FieldPath) -> Result<(), SceneError> {
        let err = |field: &str, message: String| {
            let mut p = path.clone();
            p.0.push(PathSeg::Key(field.into()));
            SceneError::Invalid { origin: String::new(), location: None, path: p, message }
        };
        for (field, v) in [("height_alpha", self.height_alpha), ("height_beta", self.height_beta)] {
            if !(v > 0.0 && v <= 1.0) {
                return Err(err(field, format!("must be in (0, 1], got {v}")));
            }
        }
        for (field, v) in
            [("fallback_leak_s", self.fallback_leak_s), ("attitude_bias_time_s", self.attitude_bias_time_s)]
        {
            if !v.is_finite() || v <= 0.0 {
                return Err(err(field, format!("must be positive and finite, got {v}")));
            }
        }
        for (field, v) in [
            ("ahrs_lag_s", self.ahrs_lag_s),
            ("attitude_bias_deg", self.attitude_bias_deg),
            ("gyro_bias_deg_s", self.gyro_bias_deg_s),
            ("thrust_adapt_time_s", self.thrust_adapt_time_s),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(err(field, format!("must be finite and not negative, got {v}")));
            }
        }
        Ok(())
    }
}

/// One copter's estimator state.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    /// Height above the surface below, m.
    pub height_m: Real,
    /// Vertical speed, m/s.
    pub vz_m_s: Real,
    /// Whether the last IR reading was in range.
    pub ir_in_range: bool,
    /// AHRS roll, pitch, yaw (yaw with its bias), rad: what the attitude loop reads.
    pub attitude_rad: [Real; 3],
    /// Body rates, rad/s: what the attitude loop reads.
    pub rate_rad_s: [Real; 3],
    /// The lagged attitude before noise, rad.
    pub attitude_lag_rad: [Real; 3],
    /// The lagged rates before noise, rad/s.
    pub rate_lag_rad_s: [Real; 3],
    /// Current roll and pitch bias, rad.
    pub attitude_bias_rad: [Real; 2],
    /// This copter's residual gyro bias, rad/s.
    pub gyro_bias_rad_s: [Real; 3],
    /// The IMU's mounting error left by an uncalibrated copter (roll, pitch), rad.
    #[serde(default)]
    pub mount_offset_rad: [Real; 2],
    /// Measured over commanded thrust, low-passed (1 = as calibrated).
    pub thrust_gain: Real,
    /// Sum of the collective commanded in this control step's physics steps, N.
    pub collective_sum_n: Real,
    /// Physics steps in that sum.
    pub collective_steps: u32,
    /// Height loop integral, N.
    pub height_integral_n: Real,
    /// How long a landing's descent has stalled (ground detection), s.
    #[serde(default)]
    pub landing_stalled_s: Real,
    /// The last IR reading as the firmware holds it (`finken_sensor_model.pos.z`): clamped
    /// to the conversion table's range, m.
    #[serde(default)]
    pub ir_reading_m: Real,
    /// The lab firmware's height loop, for airframes that fly it.
    #[serde(default)]
    pub finken_height: FinkenHeightState,
}

impl Estimate {
    /// A copter at its start height, heading `yaw_rad`, with its gyro bias drawn from `rng`.
    pub fn new(spec: &EstimatorSpec, start_height_m: Real, yaw_rad: Real, rng: &mut Rng32) -> Self {
        let sigma = spec.gyro_bias_deg_s.to_radians();
        let gyro_bias_rad_s = [sigma * rng.normal(), sigma * rng.normal(), sigma * rng.normal()];
        Self {
            height_m: start_height_m,
            vz_m_s: 0.0,
            ir_in_range: false,
            attitude_rad: [0.0, 0.0, yaw_rad],
            rate_rad_s: [0.0; 3],
            attitude_lag_rad: [0.0, 0.0, yaw_rad],
            rate_lag_rad_s: [0.0; 3],
            attitude_bias_rad: [0.0; 2],
            gyro_bias_rad_s,
            mount_offset_rad: [0.0; 2],
            thrust_gain: 1.0,
            collective_sum_n: 0.0,
            collective_steps: 0,
            height_integral_n: 0.0,
            landing_stalled_s: 0.0,
            ir_reading_m: start_height_m,
            finken_height: FinkenHeightState::default(),
        }
    }

    /// One AHRS update (every physics step): the true attitude and body rates through the
    /// lag (blend factor `alpha`), plus biases and noise of standard deviation `att_sigma` and
    /// `rate_sigma` (rad, rad/s).
    #[inline]
    #[allow(clippy::too_many_arguments)]
    pub fn ahrs(
        &mut self,
        rpy_rad: [Real; 3],
        yaw_bias_rad: Real,
        rate_rad_s: [Real; 3],
        alpha: Real,
        att_sigma: Real,
        rate_sigma: Real,
        rng: Option<&mut Rng32>,
    ) {
        let (b, m) = (self.attitude_bias_rad, self.mount_offset_rad);
        let target = [rpy_rad[0] + b[0] + m[0], rpy_rad[1] + b[1] + m[1], rpy_rad[2] + yaw_bias_rad];
        for k in 0..3 {
            let lag = &mut self.attitude_lag_rad[k];
            *lag = wrap_angle_rad(*lag + alpha * wrap_angle_rad(target[k] - *lag));
            let r = &mut self.rate_lag_rad_s[k];
            *r += alpha * (rate_rad_s[k] + self.gyro_bias_rad_s[k] - *r);
        }
        match rng {
            Some(rng) => {
                for k in 0..3 {
                    self.attitude_rad[k] = wrap_angle_rad(self.attitude_lag_rad[k] + att_sigma * rng.triangular());
                    self.rate_rad_s[k] = self.rate_lag_rad_s[k] + rate_sigma * rng.triangular();
                }
            }
            None => {
                self.attitude_rad = self.attitude_lag_rad;
                self.rate_rad_s = self.rate_lag_rad_s;
            }
        }
    }

    /// The truth, for twins and `ideal` estimation.
    #[inline]
    pub fn ideal(&mut self, rpy_rad: [Real; 3], yaw_bias_rad: Real, rate_rad_s: [Real; 3]) {
        self.attitude_rad = [rpy_rad[0], rpy_rad[1], wrap_angle_rad(rpy_rad[2] + yaw_bias_rad)];
        self.rate_rad_s = rate_rad_s;
        self.attitude_lag_rad = self.attitude_rad;
        self.rate_lag_rad_s = rate_rad_s;
    }

    /// One step of the roll and pitch bias's Gauss–Markov process over `dt`.
    pub fn wander_bias(&mut self, spec: &EstimatorSpec, dt: Real, rng: &mut Rng32) {
        let tau = spec.attitude_bias_time_s;
        let sigma = spec.attitude_bias_deg.to_radians();
        let decay = (-dt / tau).exp();
        let drive = sigma * (1.0 - decay * decay).sqrt();
        for b in &mut self.attitude_bias_rad {
            *b = *b * decay + drive * rng.normal();
        }
    }

    /// One height update (every control step): predicted over `dt` with the measured
    /// vertical acceleration `az_m_s2` (world frame, gravity removed), then corrected with
    /// the raw IR distance `ir_raw_m` (noise included, before range checks).
    pub fn update_height(&mut self, spec: &EstimatorSpec, ir: &IrSpec, ir_raw_m: Real, az_m_s2: Real, dt: Real) {
        self.height_m += self.vz_m_s * dt + 0.5 * az_m_s2 * dt * dt;
        self.vz_m_s += az_m_s2 * dt;
        // As the FINken firmware reads it (`finken_ir_adc.c`, `finken_model_sensors.c`): the
        // reading clamped to the conversion table's range, the slant range as the height (no
        // tilt correction), the far end taken as a measurement; no rejection of a jump (a
        // copter passing below reads as the floor coming up).
        self.ir_in_range = ir_raw_m.is_finite() && (ir.min_range_m..=ir.max_range_m).contains(&ir_raw_m);
        let reading = if ir_raw_m.is_finite() { ir_raw_m.min(ir.max_range_m) } else { ir.max_range_m };
        self.ir_reading_m = reading.max(ir.min_range_m);
        if reading >= ir.min_range_m {
            let innovation = reading - self.height_m;
            self.height_m += spec.height_alpha * innovation;
            self.vz_m_s += spec.height_beta / dt * innovation;
        } else {
            // Nearer than the table reaches (on the floor, taking off): the estimate stays at
            // or below its near end, its speed leaking away.
            self.vz_m_s *= 1.0 - (dt / spec.fallback_leak_s).min(1.0);
            if self.height_m > ir.min_range_m {
                self.height_m = ir.min_range_m;
                self.vz_m_s = self.vz_m_s.min(0.0);
            }
        }
        if self.height_m < 0.0 {
            self.height_m = 0.0;
            self.vz_m_s = self.vz_m_s.max(0.0);
        }
    }

    /// The truth, for twins and `ideal` estimation.
    pub fn ideal_height(&mut self, height_m: Real, vz_m_s: Real) {
        self.height_m = height_m;
        self.ir_reading_m = height_m;
        self.vz_m_s = vz_m_s;
        self.ir_in_range = true;
    }

    /// One update of the adaptive thrust gain from this control step's mean commanded
    /// collective and the specific force the accelerometer measured along body z (`m a_z`
    /// with `mass_kg`). Only while flying level enough with real thrust; clamped to [0.5, 2].
    pub fn adapt_thrust(&mut self, spec: &EstimatorSpec, mass_kg: Real, hover_n: Real, accel_z_m_s2: Real, dt: Real) {
        let steps = std::mem::take(&mut self.collective_steps);
        let sum = std::mem::take(&mut self.collective_sum_n);
        if spec.thrust_adapt_time_s <= 0.0 || steps == 0 {
            return;
        }
        let commanded = sum / steps as Real;
        if commanded < 0.25 * hover_n {
            return;
        }
        let measured = mass_kg * accel_z_m_s2 / commanded;
        if !measured.is_finite() {
            return;
        }
        let a = (dt / spec.thrust_adapt_time_s).min(1.0);
        self.thrust_gain = (self.thrust_gain + a * (measured - self.thrust_gain)).clamp(0.5, 2.0);
    }
}
