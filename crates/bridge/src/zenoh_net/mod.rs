//! The Zenoh side: the simulator's node (state, sensors, commands, queryables, liveliness)
//! and Paparazzi texts carried over Zenoh.
//!
//! * [`node`]: the Zenoh session: key expressions, publishers, the command subscriber,
//!   queryables and liveliness.
//! * [`keyexpr`]: Zenoh keys for Paparazzi texts and regex → key-expression narrowing.
//! * [`pprz_bus`]: the Ivy-style regex bus over Zenoh ([`pprz_bus::ZenohBus`]).
//!
//! **May use:** Zenoh, tokio, [`crate::paparazzi`] (formats and the regex bus) and
//! [`crate::wire`] and the engine's `request.rs` and `loop_io.rs` ([`crate::engine::Request`],
//! [`crate::engine::Frame`]: the payloads and the loop's channels), [`crate::AcId`] and
//! [`crate::log`]'s clock (a command's receive time).

pub mod keyexpr;
pub mod node;
pub mod pprz_bus;
