//! The Paparazzi side: its file formats, its text messages, and the Ivy bus they travel on.
//!
//! Sans-I/O formats (pure functions over text; they never panic on input):
//! * [`messages`]: message definitions from `messages.xml` (pprzlink v1.0 and the older
//!   FINken-era `conf/messages.xml`).
//! * [`codec`]: the Ivy text form `<sender> <NAME> <fields...>`, encode and decode, into typed
//!   [`value::Value`]s; JSON via serde.
//! * [`conf`]: Paparazzi `conf.xml` (aircraft list; `Virtual*` naming rule).
//! * [`telemetry`]: telemetry files (message periods per mode).
//! * [`flightlog`]: Paparazzi `server` logs (`.log` + `.data`), read with the definitions they
//!   carry.
//! * [`pairing`]: our pairing file (twins, virtual copters, spawn policy).
//! * [`xml`]: the shared XML reader and its error type with file/line/column.
//! * [`bus`]: an Ivy-style regex bus (`bind`, `bind_from`, `unbind`, `dispatch`),
//!   transport-agnostic; [`narrow`] tells from a regex which senders and names it can match.
//! * [`convert`]: real telemetry → twin commands, `VIRTUAL_SONAR`, virtual copters' telemetry,
//!   with the NED/FLU frame conversions.
//!
//! The transport:
//! * [`ivy`]: the Ivy wire protocol (version 3) on UDP and TCP, an agent that joins a real
//!   Paparazzi Ivy bus beside `link`, `server` and the GCS.
//!
//! **May use:** `sim-core` (for the conversions), `regex`, `quick-xml`, std and tokio (only
//! in [`ivy`]), and the crate's bottom: [`crate::AcId`] (`ids.rs`), [`crate::wire`] (the
//! commands and states [`convert`] turns telemetry into and out of) and [`crate::lock`]. Never
//! Zenoh: the Zenoh side ([`crate::zenoh_net`]) uses this room, not the
//! other way round.

pub mod bus;
pub mod codec;
pub mod conf;
pub mod convert;
pub mod flightlog;
pub mod ivy;
pub mod messages;
pub mod narrow;
pub mod pairing;
pub mod telemetry;
pub mod value;
pub mod xml;
