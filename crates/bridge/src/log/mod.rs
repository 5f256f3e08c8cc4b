//! MCAP logging of a run: every state, sensor reading, command and controller output, the
//! events, the scene, and Foxglove 3D views. Also the readers behind `twinswarm log info`,
//! `log recover` and `plot`.
//!
//! # Channels
//!
//! Every message is protobuf: Foxglove's well-known schemas as the `foxglove` crate ships
//! them, and the project's own from `crates/bridge/proto/twinswarm.proto` ([`proto`]).
//!
//! | topic | schema | rate |
//! |---|---|---|
//! | `/copters/state` | `twinswarm.CopterState` | per logged step, per copter |
//! | `/copters/sensors` | `twinswarm.CopterSensors` | per logged step, per copter |
//! | `/copters/command` | `twinswarm.CopterCommand` | per logged step, per copter |
//! | `/copters/control` | `twinswarm.CopterControl` | per logged step, per copter |
//! | `/events` | `twinswarm.Event` | when something happens |
//! | `/log` | `foxglove.Log` | the same events, as log lines |
//! | `/tf` | `foxglove.FrameTransform` | per logged step, per copter (`world` → copter name) |
//! | `/scene/arena` | `foxglove.SceneUpdate` | once: floor, walls, boxes, rotor discs and labels |
//! | `/scene/copters` | `foxglove.SceneUpdate` | every 0.2 s: bodies and sonar cones |
//! | `/bus` | `twinswarm.BusMessage` | bus traffic, added on first use |
//! | `/pprz/<sender>/<NAME>[/decoded]` | `twinswarm.PprzText`, `twinswarm.PprzDecoded` | Paparazzi traffic |
//!
//! A logged step is every control step, or every [`LogOptions::every_ticks`] (`--log-rate`).
//! The readers ([`LogFile`], [`proto::LogRecord`]) also read the JSON logs written before
//! protobuf (`json` message encoding, same field names).
//!
//! The scene TOML is attached (`scene.toml` as given, `scene.effective.toml` after command-line
//! overrides), and a metadata record `twinswarm` holds version, seed, command line, scene
//! origin, world name, copters and the time convention.
//!
//! `twinswarm log import` writes a real flight's Paparazzi log in the same form ([`import_flight`]):
//! its messages on `/pprz/…` at their recorded times, its sonars, IR and attitude on
//! `/copters/sensors` and `/copters/state`.
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
//! it to a writer thread over a bounded channel. The writer thread encodes protobuf from
//! prost messages it refills in place, and writes the file with the `mcap` crate's writer:
//! zstd chunks at one fixed level and every CRC, without message indexes (optional in MCAP:
//! readers use the chunk indexes and read whole chunks; at 16 bytes a message they were a
//! fifth of a swarm's file). (The project's own chunk
//! writer was 1.4× cheaper, not the 2× that would have justified keeping it:
//! docs/performance.md.) Every simulated second (and at the end of setup) the writer finishes the current
//! chunk and flushes the file, so a `kill -9` loses at most about one simulated second (plus
//! the few frames queued): `twinswarm log recover` reads every complete chunk of a truncated
//! file and writes a complete one.
//! [`Logger::finish`] (or dropping the [`Logger`]) writes the summary section.
//!
//! **May use:** `mcap`, `prost`, `foxglove`, `sim-core`, [`crate::paparazzi`] (the Paparazzi
//! channels, the import's log), [`crate::zenoh_net::keyexpr`] (what a key's sender chunk may
//! hold), [`crate::realflight`] (the import's series, flights and arena), [`crate::live`] (the
//! writer thread feeds the live view) and [`crate::AcId`]. Never the engine: its recorder uses
//! this room.

mod capture;
mod encode;
mod import;
mod mcap_out;
mod pprz;
pub mod proto;
mod read;
mod time;
mod writer;

pub use capture::{CopterSample, StepFrame};
pub use encode::{Encoder, EventKind, LogEvent, SCENE_COPTERS_PERIOD_S, Sink, Topic, schema_data};
pub use import::{ImportStats, import_flight};
pub use read::{ChannelDef, ChannelInfo, LogFile, LogInfo, LogReadError, MergeReport, RecoverReport, merge, recover};
pub use time::{format_utc_basic, format_utc_iso, now_unix_ns, thread_cpu_ns};
pub use writer::{LogError, LogMeta, LogOptions, LogStats, Logger};
