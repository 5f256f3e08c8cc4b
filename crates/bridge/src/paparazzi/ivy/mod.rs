//! The Ivy software bus, protocol version 3, written here: what Paparazzi's `link`, `server`,
//! GCS and `messages` agents speak.
//!
//! * [`frame`]: the wire format, sans I/O: the UDP hello, the TCP lines, a line splitter with
//!   a length cap.
//! * [`busaddr`]: `IVYBUS` / `--ivy-bus` strings (`127.255.255.255:2010`, `127:2010`, ...).
//! * [`agent`]: an agent on tokio: discovery, handshake, sender-side matching, bounded
//!   per-peer queues, counters of everything received and dropped.
//!
//! Behaviour follows ivy-c (`ivy.c`, `ivysocket.c`) and ivy-python 4.0 (`ivy/ivy.py`); where
//! they differ, the module docs say which one is followed and why. No code of either is used.

pub mod agent;
pub mod busaddr;
pub mod frame;

pub use agent::{IvyAgent, IvyCounters, IvyError, IvyOptions, PeerEvent, PeerInfo};
pub use busaddr::{BusAddr, DEFAULT_BUS};
