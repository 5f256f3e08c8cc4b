//! `[sensors.ir]`: the IR height sensor's spec, which the height estimate
//! ([`crate::estimate`]) reads as well as the sensor model.

use serde::{Deserialize, Serialize};

use crate::math::Real;

/// `[sensors.ir]`: the downward IR distance sensor.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IrSpec {
    /// Shortest distance the firmware reports, m: nearer reads this (and the 2015-12
    /// firmware then holds its last height).
    pub min_range_m: Real,
    /// Longest distance the firmware reports, m: farther reads this, and the height loop
    /// takes it as a measurement (so a copter above it is pushed back down).
    pub max_range_m: Real,
    /// Constant part of the noise standard deviation, m.
    pub noise_sigma_m: Real,
    /// Part of the noise standard deviation proportional to the distance.
    pub noise_sigma_rel: Real,
}

impl Default for IrSpec {
    fn default() -> Self {
        // The firmware's range: `finken_ir_adc.c` maps ADC counts through a six-point table
        // onto 0.20–1.30 m and clamps outside it (both the 2015-07 and the 2015-12 firmware).
        Self { min_range_m: 0.20, max_range_m: 1.30, noise_sigma_m: 0.005, noise_sigma_rel: 0.01 }
    }
}
