//! Twinswarm's bridge: everything between the simulation core and the outside world.
//!
//! Sans-I/O formats (pure functions over text):
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
//! * [`pprz`]: real telemetry → twin commands, `VIRTUAL_SONAR`, virtual
//!   copters' telemetry, with the NED/FLU frame conversions.
//! * [`wire`]: the JSON messages of the bus (state, sensors, commands).
//! * [`xml`]: the shared XML reader and its error type with file/line/column.
//!
//! Runtime:
//! * [`sim`]: the step loop on its own thread, bounded channels in and out,
//!   real-time pacing against absolute deadlines.
//! * [`node`]: the Zenoh session: key expressions, publishers, the command
//!   subscriber, queryables and liveliness.
//!
//! **Architecture invariant:** the format modules never do I/O except reading
//! the files they are asked to parse, and never panic on input. Only [`node`]
//! knows Zenoh; only [`sim`] runs the step loop, and it never blocks on
//! publishing.

pub mod bus;
pub mod codec;
pub mod conf;
pub mod ivy;
pub mod keyexpr;
pub mod log;
pub mod messages;
pub mod mixed;
pub mod node;
pub mod pairing;
pub mod pprz;
pub mod sim;
pub mod sync;
pub mod telemetry;
pub mod value;
pub mod wire;
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
