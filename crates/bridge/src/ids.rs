//! Identifiers every room names, at the bottom of the crate: the Paparazzi formats, the Zenoh
//! bus, mixed reality, real flights and the log import all import them from here, so that none
//! of them points up at the crate root. The crate re-exports them (`bridge::AcId`).
//!
//! **May use:** nothing.

/// Paparazzi aircraft id (one byte on the link, the Ivy sender of telemetry).
pub type AcId = u8;
