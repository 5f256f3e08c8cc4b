//! ROS 2 over Zenoh: the simulator seen by ROS 2 nodes through `rmw_zenoh` (Jazzy), with no
//! bridge process. [`cdr`] encodes and decodes CDR, [`types`] holds the message types and
//! computes their RIHS01 hashes, [`msgs`] encodes the messages, and [`node`] is the ROS node
//! on the simulator's Zenoh session (its topics, graph tokens and command subscriptions).

pub mod cdr;
pub mod msgs;
pub mod node;
pub mod types;

pub use node::{Ros2Node, Ros2Options, Ros2Stats};
