//! ROS 2 over Zenoh: the simulator seen by ROS 2 nodes through `rmw_zenoh` (Jazzy), with no
//! bridge process. [`cdr`] encodes and decodes CDR, [`types`] holds the message types and
//! computes their RIHS01 hashes, [`msgs`] encodes the messages, and [`node`] is the ROS node
//! on the simulator's Zenoh session (its topics, graph tokens and command subscriptions).
//!
//! **May use:** Zenoh and zenoh-ext (its own publishers, subscribers and liveliness tokens on
//! the node's session), [`crate::zenoh_net::node`] (the `CommandSink` its commands go through,
//! so that the claim rule is the node's), [`crate::wire`], the engine's `request.rs` and
//! `loop_io.rs` ([`crate::engine::Request`], [`crate::engine::Frame`]) and [`crate::log`]'s
//! clock.

pub mod cdr;
pub mod msgs;
pub mod node;
pub mod types;

pub use node::{Ros2Node, Ros2Options, Ros2Stats};
