//! MCAP logging of a run: every state, sensor reading, command and controller output, the
//! events, the scene, and Foxglove 3D views. Also the readers behind `twinswarm log info`,
//! `log recover` and `plot`.
//!
//! # Channels
//!
//! | topic | schema | encoding | rate |
//! |---|---|---|---|
//! | `/copters/state` | `twinswarm.CopterState` | json | per step, per copter |
//! | `/copters/sensors` | `twinswarm.CopterSensors` | json | per step, per copter |
//! | `/copters/command` | `twinswarm.CopterCommand` | json | per step, per copter |
//! | `/copters/control` | `twinswarm.CopterControl` | json | per step, per copter |
//! | `/events` | `twinswarm.Event` | json | when something happens |
//! | `/log` | `foxglove.Log` | json | the same events, as log lines |
//! | `/tf` | `foxglove.FrameTransform` | json | per step, per copter (`world` → copter name) |
//! | `/scene/arena` | `foxglove.SceneUpdate` | json | once: floor, walls, boxes, rotor discs and labels |
//! | `/scene/copters` | `foxglove.SceneUpdate` | json | per step: bodies and sonar cones |
//! | `/bus` | `twinswarm.BusMessage` | json | bus traffic, added on first use |
//!
//! Our own schemas are checked in under `crates/bridge/schemas/` and embedded in the binary;
//! the Foxglove ones are our own minimal copies of the foxglove-sdk JSON schemas (same titles
//! and field names), so Foxglove shows the arena and the swarm in its 3D panel.
//!
//! The scene TOML is attached (`scene.toml` as given, `scene.effective.toml` after command-line
//! overrides), and a metadata record `twinswarm` holds version, seed, command line, scene
//! origin, world name, copters and the time convention.
//!
//! # Time
//!
//! `log_time = epoch_ns + tick × control_dt_ns`, where the epoch is the wall-clock UTC time at
//! the start of the run (so files of different runs sort by time) and `tick` is the control
//! step a message describes. For simulator messages `publish_time = log_time`; for bus
//! messages `publish_time` is the wall-clock receive time. Foxglove `timestamp` fields carry
//! the `log_time`.
//!
//! # Crash safety and cost
//!
//! The stepping thread only copies each copter's numbers into a reused [`StepFrame`] and hands
//! it to a writer thread over a bounded channel. The writer thread encodes JSON into reused
//! buffers (the per-step messages by hand, `json.rs`: serde spent most of its time escaping
//! keys) and writes the file with its own chunked MCAP writer (`mcapw.rs`): a chunk's records
//! go into one buffer that is compressed by a single zstd call, then written with its message
//! indexes. Every simulated second (and at the end of setup) the writer finishes the current
//! chunk and flushes the file, so a `kill -9` loses at most about one simulated second (plus
//! the few frames queued): `twinswarm log recover` reads every complete chunk of a truncated
//! file and writes a complete one.
//! [`Logger::finish`] (or dropping the [`Logger`]) writes the summary section.

mod capture;
mod encode;
mod json;
mod mcapw;
mod msg;
mod pprz;
mod read;
mod schemas;
mod time;
mod writer;

pub use capture::{CopterSample, StepFrame};
pub use encode::{Encoder, EventKind, LogEvent, SCENE_COPTERS_PERIOD_S, Sink, Topic};
pub use read::{ChannelDef, ChannelInfo, LogFile, LogInfo, LogReadError, RecoverReport, recover};
pub use schemas::{SCHEMAS, SchemaDef, schema_for};
pub use time::{format_utc_basic, format_utc_iso, now_unix_ns, thread_cpu_ns};
pub use writer::{LogError, LogMeta, LogOptions, LogStats, Logger};
