//! Mixed reality: real copters' telemetry drives their twins, twins' virtual sonar goes back,
//! virtual copters publish telemetry as if they were aircraft, and twins are kept where their
//! real copters are.
//!
//! Two halves, one per thread:
//!
//! - The loop side, inside the step loop (it needs the state): [`outbox`] makes the Paparazzi
//!   texts to send after each step on the **simulated** clock (each twin's virtual-sonar uplink,
//!   each virtual copter's telemetry at the periods of its [`plan::TelemetryPlan`]), and
//!   [`sync`] keeps each twin where its real copter is (MEDUSA on its real sonars, tracking).
//! - The tokio side: the [`gateway`] binds the FINken telemetry on Zenoh, on a real Ivy bus or
//!   both, and hands each text to the [`interpreter`], where a twin's telemetry becomes a
//!   command ([`crate::engine::Request::Twin`]); the interpreter routes it by aircraft id
//!   through the [`router`] (which also applies the pairing to a scene) and counts arrivals
//!   in [`stats`]' constant-memory samples.
//!
//! Beside them, [`link`] models when a real copter's telemetry arrives (the stand-in and the
//! sync evaluation draw from it).
//!
//! **May use:** `sim-core`, `medusa` (in [`sync`]), [`crate::AcId`], [`crate::paparazzi`]
//! (formats, the telemetry ⇄ command conversions, the Ivy agent), [`crate::wire`], the
//! engine's `request.rs` (the requests the interpreter makes), [`crate::zenoh_net`]'s
//! Paparazzi bus and keys (the gateway only; with [`crate::log`]'s clock and tokio, the gateway
//! is the only file here that does I/O). Never the engine's loop or flight: the engine uses
//! this room ([`outbox`], [`sync`], [`stats`]), not the other way round.

pub mod gateway;
pub mod interpreter;
pub mod link;
pub mod outbox;
pub mod plan;
pub mod router;
pub mod stats;
pub mod sync;
