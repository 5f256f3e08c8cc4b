//! Twinswarm's bridge core, without any network: everything the bridge
//! needs to speak Paparazzi's language, so that the Zenoh layer on top only
//! moves texts around.
//!
//! * [`messages`]: message definitions from `messages.xml` (pprzlink v1.0
//!   and the older FINken-era `conf/messages.xml`).
//! * [`codec`]: the Ivy text form `<sender> <NAME> <fields...>`, encode and
//!   decode, into typed [`value::Value`]s; JSON via serde.
//! * [`conf`]: Paparazzi `conf.xml` (aircraft list; `Virtual*` naming rule).
//! * [`telemetry`]: telemetry files (message periods per mode).
//! * [`pairing`]: our pairing file (twins, virtual copters, spawn policy).
//! * [`bus`]: an Ivy-style regex bus (`bind`, `bind_from`, `unbind`,
//!   `dispatch`), transport-agnostic.
//! * [`keyexpr`]: Zenoh keys for Ivy texts and regex → key-expression
//!   narrowing.
//! * [`xml`]: the shared XML reader and its error type with file/line/column.
//! * [`log`]: MCAP logging of runs (a writer thread), `log info`/`recover`
//!   and the readers behind `plot`.
//!
//! **Architecture invariant:** apart from [`log`], this crate does no I/O
//! except reading the files it is asked to parse (`from_file` constructors);
//! it has no async, no threads, no clocks, and never panics on input.
//! [`log`] writes files from one writer thread and reads the wall clock
//! once per run (the log epoch); its encoding ([`log::Encoder`]) is sans I/O.

pub mod bus;
pub mod node;
pub mod sim;
pub mod wire;
pub mod codec;
pub mod conf;
pub mod keyexpr;
pub mod log;
pub mod messages;
pub mod pairing;
pub mod pprz;
pub mod telemetry;
pub mod value;
pub mod xml;

/// Paparazzi aircraft id (one byte on the link, the Ivy sender of telemetry).
pub type AcId = u8;

pub use bus::{BindId, Bus, BusError, Control, Delivery};
pub use codec::{CodecError, Message, Sender};
pub use conf::{Aircraft, AircraftKind, ConfXml, is_virtual_name};
pub use keyexpr::{key_expr_matches, key_for, key_for_text, narrow_key_expr};
pub use messages::{BaseType, FieldDef, FieldType, MessageDef, MessageSet};
pub use pairing::Pairing;
pub use telemetry::Telemetry;
pub use value::Value;
pub use xml::{Location, XmlError};
