//! Typed errors for invalid inputs.

use thiserror::Error;

/// Everything that can be wrong with the inputs given to this crate.
///
/// Degenerate but valid situations (all readings out of range, only two
/// sensors, a copter in a corner) are *not* errors: they produce a
/// low-confidence answer instead.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum MedusaError {
    /// The arena width or height is not a finite, strictly positive number.
    #[error("invalid arena: width {width_m} m x height {height_m} m (both must be finite and > 0)")]
    InvalidArena {
        /// Width given (m).
        width_m: f64,
        /// Height given (m).
        height_m: f64,
    },
    /// A box obstacle has a non-finite centre or yaw, or non-positive half-extents.
    #[error("invalid obstacle #{index}: {reason}")]
    InvalidObstacle {
        /// Index of the obstacle in the list given.
        index: usize,
        /// Human-readable reason.
        reason: &'static str,
    },
    /// The sensor layout has fewer than [`crate::MIN_SENSORS`] or more than
    /// [`crate::MAX_SENSORS`] sensors.
    #[error("sensor count {count} outside the supported range {min}..={max}")]
    SensorCount {
        /// Number of sensors given.
        count: usize,
        /// Minimum supported.
        min: usize,
        /// Maximum supported.
        max: usize,
    },
    /// A sensor has a non-finite angle/offset or a non-positive max range.
    #[error("invalid sensor #{index}: {reason}")]
    InvalidSensor {
        /// Index of the sensor in the layout.
        index: usize,
        /// Human-readable reason.
        reason: &'static str,
    },
    /// The number of readings does not match the number of sensors.
    #[error("got {got} readings for {expected} sensors")]
    ReadingCount {
        /// Number of sensors in the layout.
        expected: usize,
        /// Number of readings given.
        got: usize,
    },
    /// A reading is NaN or negative.
    #[error("invalid reading from sensor #{index}: {range_m} m")]
    InvalidReading {
        /// Index of the sensor.
        index: usize,
        /// The offending value (m).
        range_m: f64,
    },
    /// The yaw estimate or its sigma is not finite, or the sigma is negative.
    #[error("invalid yaw estimate: yaw {yaw_rad} rad, sigma {sigma_rad} rad")]
    InvalidYaw {
        /// Yaw given (rad).
        yaw_rad: f64,
        /// Sigma given (rad).
        sigma_rad: f64,
    },
    /// A configuration parameter is out of its valid domain.
    #[error("invalid parameter `{name}` = {value}: {reason}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// Value given.
        value: f64,
        /// Human-readable reason.
        reason: &'static str,
    },
}
