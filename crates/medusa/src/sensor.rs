//! Sensor layout, noise model, yaw estimate and the per-sensor likelihood.

use nalgebra::Vector2;

use crate::error::MedusaError;

/// Fewest sensors supported in a layout.
pub const MIN_SENSORS: usize = 2;
/// Most sensors supported in a layout.
pub const MAX_SENSORS: usize = 8;

/// One horizontal proximity sensor (sonar) mounted on the copter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorSpec {
    /// Direction of the sensor axis in the body frame, counter-clockwise
    /// from body `+x` (forward) (rad).
    pub angle_in_body_rad: f64,
    /// Position of the sensor in the body frame (m), body `x` forward, `y` left.
    pub offset_in_body_m: Vector2<f64>,
    /// Readings at or beyond this range mean "no echo" (m), > 0.
    pub max_range_m: f64,
}

/// The set of sensors on the copter (2 to 8).
#[derive(Debug, Clone, PartialEq)]
pub struct SensorLayout {
    sensors: Vec<SensorSpec>,
}

impl SensorLayout {
    /// A layout from explicit sensor specifications.
    ///
    /// # Errors
    /// [`MedusaError::SensorCount`] for fewer than [`MIN_SENSORS`] or more than
    /// [`MAX_SENSORS`] sensors; [`MedusaError::InvalidSensor`] for non-finite
    /// data or a non-positive max range.
    pub fn new(sensors: Vec<SensorSpec>) -> Result<Self, MedusaError> {
        if !(MIN_SENSORS..=MAX_SENSORS).contains(&sensors.len()) {
            return Err(MedusaError::SensorCount { count: sensors.len(), min: MIN_SENSORS, max: MAX_SENSORS });
        }
        for (index, s) in sensors.iter().enumerate() {
            if !(s.angle_in_body_rad.is_finite()
                && s.offset_in_body_m.x.is_finite()
                && s.offset_in_body_m.y.is_finite())
            {
                return Err(MedusaError::InvalidSensor { index, reason: "non-finite angle or offset" });
            }
            if !(s.max_range_m.is_finite() && s.max_range_m > 0.0) {
                return Err(MedusaError::InvalidSensor { index, reason: "max range must be finite and > 0" });
            }
        }
        Ok(Self { sensors })
    }

    /// `count` sensors evenly spaced in angle starting at body `+x`, each
    /// mounted `radius_m` from the body centre along its own axis (the FINken
    /// has 4 at 90°).
    ///
    /// # Errors
    /// As [`SensorLayout::new`].
    pub fn ring(count: usize, radius_m: f64, max_range_m: f64) -> Result<Self, MedusaError> {
        let sensors = (0..count)
            .map(|k| {
                let angle = k as f64 * std::f64::consts::TAU / count.max(1) as f64;
                SensorSpec {
                    angle_in_body_rad: angle,
                    offset_in_body_m: Vector2::new(angle.cos(), angle.sin()) * radius_m,
                    max_range_m,
                }
            })
            .collect();
        Self::new(sensors)
    }

    /// The sensors.
    pub fn sensors(&self) -> &[SensorSpec] {
        &self.sensors
    }

    /// Number of sensors.
    pub fn len(&self) -> usize {
        self.sensors.len()
    }

    /// Always false (a layout has at least [`MIN_SENSORS`] sensors).
    pub fn is_empty(&self) -> bool {
        self.sensors.is_empty()
    }
}

/// Noise and geometry parameters of the range sensors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorModel {
    /// Standard deviation of the range noise (m). Default 0.05.
    pub noise_sigma_m: f64,
    /// Half-angle of the sonar cone (rad); 0 = centre ray only.
    /// Default 15° (the FINken sonars have a 30° cone).
    pub cone_half_angle_rad: f64,
    /// Probability that a reading is garbage (cross-talk, missed echo):
    /// mixed in as a uniform in-range density or a spurious out-of-range.
    /// Keeps single bad readings from being fatal. Default 0.02.
    pub outlier_probability: f64,
}

impl Default for SensorModel {
    fn default() -> Self {
        Self { noise_sigma_m: 0.05, cone_half_angle_rad: 15f64.to_radians(), outlier_probability: 0.02 }
    }
}

impl SensorModel {
    pub(crate) fn validate(&self) -> Result<(), MedusaError> {
        if !(self.noise_sigma_m.is_finite() && self.noise_sigma_m > 0.0) {
            return Err(MedusaError::InvalidParameter {
                name: "noise_sigma_m",
                value: self.noise_sigma_m,
                reason: "must be finite and > 0",
            });
        }
        if !(self.cone_half_angle_rad.is_finite() && (0.0..=80f64.to_radians()).contains(&self.cone_half_angle_rad)) {
            return Err(MedusaError::InvalidParameter {
                name: "cone_half_angle_rad",
                value: self.cone_half_angle_rad,
                reason: "must be in [0, 80°]",
            });
        }
        if !(self.outlier_probability.is_finite() && (1e-9..0.5).contains(&self.outlier_probability)) {
            return Err(MedusaError::InvalidParameter {
                name: "outlier_probability",
                value: self.outlier_probability,
                reason: "must be in [1e-9, 0.5)",
            });
        }
        Ok(())
    }
}

/// A yaw estimate (e.g. from the AHRS) and its white-noise uncertainty.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct YawEstimate {
    /// Yaw of the body about world `+z`, counter-clockwise from world `+x` (rad).
    pub yaw_rad: f64,
    /// Standard deviation of its noise (rad), >= 0. A slowly varying bias is
    /// estimated by [`crate::MedusaFilter`]; raw MEDUSA only inflates the
    /// range noise by it.
    pub sigma_rad: f64,
}

impl YawEstimate {
    /// A yaw estimate with the given noise sigma.
    pub fn new(yaw_rad: f64, sigma_rad: f64) -> Self {
        Self { yaw_rad, sigma_rad }
    }

    pub(crate) fn validate(&self) -> Result<(), MedusaError> {
        if !(self.yaw_rad.is_finite() && self.sigma_rad.is_finite() && self.sigma_rad >= 0.0) {
            return Err(MedusaError::InvalidYaw { yaw_rad: self.yaw_rad, sigma_rad: self.sigma_rad });
        }
        Ok(())
    }
}

/// A validated reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Observation {
    /// An echo at this range (m), below the max range.
    InRange(f64),
    /// No echo within the max range.
    OutOfRange,
}

/// Validate raw readings: `None`, `+inf` or `>= max_range` mean out of range;
/// NaN or negative values are errors.
pub(crate) fn validate_readings(
    layout: &SensorLayout,
    readings_m: &[Option<f64>],
) -> Result<Vec<Observation>, MedusaError> {
    if readings_m.len() != layout.len() {
        return Err(MedusaError::ReadingCount { expected: layout.len(), got: readings_m.len() });
    }
    readings_m
        .iter()
        .zip(layout.sensors())
        .enumerate()
        .map(|(index, (reading, spec))| match *reading {
            None => Ok(Observation::OutOfRange),
            Some(r) if r.is_nan() || r < 0.0 => Err(MedusaError::InvalidReading { index, range_m: r }),
            Some(r) if r >= spec.max_range_m => Ok(Observation::OutOfRange),
            Some(r) => Ok(Observation::InRange(r)),
        })
        .collect()
}

/// Per-sensor likelihood evaluator with precomputed constants.
#[derive(Debug, Clone, Copy)]
pub(crate) struct RangeLikelihood {
    sigma2_m2: f64,
    outlier: f64,
    inlier: f64,
}

const INV_SQRT_2PI: f64 = 0.398_942_280_401_432_7;

impl RangeLikelihood {
    pub fn new(model: &SensorModel) -> Self {
        let sigma = model.noise_sigma_m;
        let eps = model.outlier_probability;
        Self { sigma2_m2: sigma * sigma, outlier: eps, inlier: 1.0 - eps }
    }

    /// Evaluate one observation given the predicted true range.
    ///
    /// The reading is modelled as the true range plus Gaussian noise,
    /// censored at `max_range_m` (an out-of-range reading is the event
    /// "true range + noise >= max range"), mixed with an outlier process.
    /// `extra_var_m2` adds variance (yaw uncertainty mapped through the
    /// range's sensitivity to yaw).
    ///
    /// Returns `(ln p, ln fit)` where `ln fit = ln p - ln p_best <= 0` is the
    /// log-likelihood relative to the best achievable one for this sensor
    /// (zero residual), used for confidence and re-localisation decisions.
    #[inline]
    pub fn eval(&self, obs: Observation, predicted_m: f64, max_range_m: f64, extra_var_m2: f64) -> (f64, f64) {
        let var = self.sigma2_m2 + extra_var_m2;
        let sigma = var.sqrt();
        match obs {
            Observation::InRange(z) => {
                let peak = INV_SQRT_2PI / sigma;
                let g = if predicted_m.is_finite() {
                    let r = (z - predicted_m) / sigma;
                    peak * (-0.5 * r * r).exp()
                } else {
                    0.0
                };
                let floor = self.outlier / max_range_m;
                let ln_p = (self.inlier * g + floor).ln();
                (ln_p, ln_p - (self.inlier * peak + floor).ln())
            }
            Observation::OutOfRange => {
                let p_beyond =
                    if predicted_m.is_finite() { normal_cdf((predicted_m - max_range_m) / sigma) } else { 1.0 };
                let ln_p = (self.inlier * p_beyond + self.outlier).ln();
                (ln_p, ln_p)
            }
        }
    }
}

/// Standard normal CDF, accurate to ~1e-7 relative everywhere (Numerical
/// Recipes' Chebyshev erfc).
pub(crate) fn normal_cdf(x: f64) -> f64 {
    0.5 * erfc(-x * std::f64::consts::FRAC_1_SQRT_2)
}

fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98 + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let ans = t * poly.exp();
    if x >= 0.0 { ans } else { 2.0 - ans }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cdf_sane() {
        assert!((normal_cdf(0.0) - 0.5).abs() < 1e-7);
        assert!((normal_cdf(1.0) - 0.841_344_746).abs() < 1e-6);
        assert!((normal_cdf(-1.0) - 0.158_655_254).abs() < 1e-6);
        assert!(normal_cdf(-40.0) >= 0.0);
        assert!(normal_cdf(40.0) <= 1.0 + 1e-12);
    }

    #[test]
    fn readings_validation() {
        let layout = SensorLayout::ring(4, 0.08, 3.0).expect("layout");
        assert!(validate_readings(&layout, &[None, None, None]).is_err());
        assert!(validate_readings(&layout, &[Some(f64::NAN), None, None, None]).is_err());
        assert!(validate_readings(&layout, &[Some(-0.1), None, None, None]).is_err());
        let ok = validate_readings(&layout, &[Some(1.0), Some(3.0), Some(f64::INFINITY), None]).expect("valid");
        assert_eq!(ok[0], Observation::InRange(1.0));
        assert_eq!(ok[1], Observation::OutOfRange);
        assert_eq!(ok[2], Observation::OutOfRange);
        assert!(SensorLayout::new(vec![]).is_err());
        assert!(SensorLayout::ring(9, 0.08, 3.0).is_err());
        assert!(SensorLayout::ring(4, 0.08, 0.0).is_err());
    }
}
