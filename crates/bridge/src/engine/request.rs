//! What the step loop is asked ([`Request`]): commands, twins' telemetry, spawns, claims, stop,
//! each with the bus message it came from ([`BusInput`]). The gateways and the Zenoh node
//! make them; [`crate::engine::run_loop`] applies them at the start of the next control step.

use sim_core::scene::CopterSpec;

use crate::wire::CommandMsg;

/// What can be asked of the step loop.
#[derive(Debug)]
pub enum Request {
    /// A validated command for a copter, by name, from a source (e.g. a Zenoh key).
    Command {
        /// Copter name.
        copter: String,
        /// The command.
        cmd: CommandMsg,
        /// Where it came from (the bus key) and its raw text, for the log.
        origin: BusInput,
    },
    /// A text that drives nothing (an aircraft that is not ours, one of our virtual aircraft
    /// sent by someone else), for the log: every received text reaches it.
    Ignored {
        /// Where it came from and its raw text.
        origin: BusInput,
        /// Why it drives nothing.
        reason: &'static str,
    },
    /// An input the bus refused (malformed, out of range, unknown copter), for the log.
    Rejected {
        /// Where it came from and its raw text.
        origin: BusInput,
        /// Why it was refused.
        reason: String,
    },
    /// Add a virtual copter; the reply says its name or why not.
    Spawn {
        /// Its scene table.
        spec: Box<CopterSpec>,
        /// Where the answer goes.
        reply: tokio::sync::oneshot::Sender<Result<String, String>>,
    },
    /// Telemetry of a real copter for its twin (see [`crate::mixed::interpreter`]).
    Twin {
        /// The twin's name.
        copter: String,
        /// Spawn it first if it does not exist yet.
        spawn: Option<Box<CopterSpec>>,
        /// What to apply (validated).
        cmd: Option<CommandMsg>,
        /// The real copter's attitude (roll, pitch, yaw), rad, simulator frame.
        observed_rpy: Option<[f32; 3]>,
        /// The real copter's own sonar readings (front, right, back, left), m.
        sonar_m: Option<[f32; 4]>,
        /// The real copter's yaw estimate, rad, simulator frame.
        yaw_rad: Option<f32>,
        /// The telemetry text, its key and arrival time.
        origin: BusInput,
    },
    /// An external tracking pose of a twin's real copter (see [`crate::mixed::sync`]).
    Tracking {
        /// The twin's name.
        copter: String,
        /// Position (x, y), m, world frame.
        pos_m: [f32; 2],
        /// The message, its key and arrival time.
        origin: BusInput,
    },
    /// A copter's controller changed (Zenoh liveliness claims, see
    /// [`crate::zenoh_net::node`]).
    Controller {
        /// The copter's name.
        copter: String,
        /// Its controller now, if any.
        client: Option<String>,
        /// The controller that disappeared, if one did (its failsafe applies when no other
        /// client takes over).
        lost: Option<String>,
    },
    /// Finish after the current step.
    Stop,
}

/// A message as it arrived on the bus.
#[derive(Debug, Clone)]
pub struct BusInput {
    /// The key it arrived on (its source).
    pub key: String,
    /// Its payload as text (lossy UTF-8).
    pub text: String,
    /// Wall-clock receive time, ns since the Unix epoch.
    pub received_unix_ns: u64,
}
