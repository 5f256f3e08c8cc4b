//! `[sensors.ir]`: the IR height sensor's spec, which the height estimate
//! ([`crate::estimate`]) reads as well as the sensor model.

use serde::{Deserialize, Serialize};

use crate::math::Real;

/// `[sensors.ir]`: the downward IR distance sensor.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IrSpec {
    /// Shortest valid distance, m.
    pub min_range_m: Real,
    /// Longest valid distance, m.
    pub max_range_m: Real,
    /// Constant part of the noise standard deviation, m.
    pub noise_sigma_m: Real,
    /// Part of the noise standard deviation proportional to the distance.
    pub noise_sigma_rel: Real,
}

impl Default for IrSpec {
    fn default() -> Self {
        Self { min_range_m: 0.10, max_range_m: 1.50, noise_sigma_m: 0.005, noise_sigma_rel: 0.01 }
    }
}
