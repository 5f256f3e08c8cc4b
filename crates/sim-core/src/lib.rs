//! `sim-core`: the deterministic FINken swarm simulation.
//!
//! In the spirit of MuJoCo's model/data split:
//! - a [`SceneSpec`] (TOML, unknown fields rejected) is compiled by [`compile`] into an
//!   immutable [`World`] (airframes, arena, obstacles, parameters);
//! - a [`State`] holds everything that changes (Rapier sets, controller integrators, rotor
//!   state, random streams, tick);
//! - [`Inputs`] hold the commands per copter and are never written by the step;
//! - [`step`] advances one control step and returns a [`StepReport`] with events such as
//!   crashes.
//!
//! **Architecture invariant:** this crate does no I/O, reads no clock and knows nothing of
//! tokio, Zenoh, XML or MCAP. Time is `tick × control_dt`. The same scene, seed and inputs
//! give bitwise-identical states.
//!
//! ```
//! let (_spec, world) = sim_core::scene::load_default();
//! let mut state = world.initial_state();
//! let inputs = world.initial_inputs();
//! for _ in 0..20 {
//!     sim_core::step(&world, &mut state, &inputs);
//! }
//! assert_eq!(state.tick, 20);
//! ```

pub mod airflow;
pub mod airframe;
pub mod battery;
pub mod control;
pub mod error;
pub mod estimate;
pub mod finite;
pub mod finken_height;
pub mod geometry;
mod lanes;
pub mod math;
pub mod mixed;
mod partition;
pub mod rng;
pub mod scene;
pub mod sensors;
pub mod shard;
pub mod state;
pub mod step;
pub mod world;

pub use airframe::{Airframe, AirframeSpec};
pub use control::{Command, FlightMode, Inputs, Setpoint};
pub use scene::{SceneError, SceneSpec, compile};
pub use sensors::SensorReadings;
pub use state::{CopterPose, CopterState, CrashCause, State};
pub use step::{Event, Stage, StepReport, fresh_sonars, step, step_into, step_probed};
pub use world::{CopterKind, World};
