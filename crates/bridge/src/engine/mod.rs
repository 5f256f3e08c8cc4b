//! The engine: the step loop and the one flight every front end drives.
//!
//! * [`flight`]: [`flight::Flight`], one run (world, state, inputs, what happens between two
//!   steps, counters, the [`flight::Recorder`]): the CLI's `run`, the Python package and
//!   lockstep all step it.
//! * `run.rs`: the step loop on its own thread ([`run_loop`], [`run_watched`]): bounded
//!   channels in and out, real-time pacing against absolute deadlines or lockstep; it never
//!   blocks on publishing.
//! * `request.rs`: what the loop is asked ([`Request`], each with its [`BusInput`]).
//! * `loop_io.rs`: what it runs with and gives out ([`LoopOptions`], [`Frame`], [`LoopStats`],
//!   [`TwinStats`], [`StepObserver`]).
//! * [`failsafe`]: lost links (a silent twin, a vanished controller), on the loop thread.
//! * [`checkpoint`]: a run saved between two steps, bit for bit, and restored.
//!
//! `Request`, `BusInput` and the loop's options, frames and counters are re-exported here
//! (`bridge::engine::Request`); inside the crate, files name the file that holds them
//! (`crate::engine::request::Request`), so that `scripts/check-imports.py` sees the real edges.
//!
//! **May use:** `sim-core`, [`crate::wire`] (the bus's JSON), [`crate::log`] (the recorder),
//! the loop-thread half of [`crate::mixed`] (the outbox, twin sync, statistics),
//! [`crate::shard`] (a shard's link), [`crate::autopilot`], tokio's channels (no runtime).
//! Never Zenoh or Ivy: what the bus brings arrives as [`Request`]s, what goes out leaves as
//! [`Frame`]s. Used by the bus sides ([`crate::zenoh_net`], [`crate::ros2`], [`crate::mixed`]'s
//! gateway) only through `request.rs` and `loop_io.rs`.

pub mod checkpoint;
pub mod failsafe;
pub mod flight;
pub(crate) mod loop_io;
pub(crate) mod request;
mod run;

pub use loop_io::{Frame, LockstepOptions, LockstepStats, LoopOptions, LoopStats, StepObserver, TwinStats};
pub use request::{BusInput, Request};
pub use run::{Finished, run_loop, run_watched};
