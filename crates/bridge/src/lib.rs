//! Twinswarm's bridge: everything between the simulation core and the outside world.
//!
//! Its rooms, one folder or file per concern:
//! * [`paparazzi`]: Paparazzi's formats (messages.xml, the Ivy text codec, conf.xml,
//!   telemetry, pairing), the transport-agnostic regex bus, the conversions between
//!   telemetry and twin commands, and the real Ivy wire protocol ([`paparazzi::ivy`]).
//! * [`zenoh_net`]: the Zenoh node (state, sensors, commands, clock, queryables, liveliness),
//!   Zenoh keys for Paparazzi texts, and the regex bus over Zenoh.
//! * [`ros2`]: ROS 2 over the node's Zenoh session, as rmw_zenoh lays it out.
//! * [`wire`]: the JSON messages of the bus (state, sensors, commands), which every side speaks.
//! * [`engine`]: one flight ([`engine::flight::Flight`], the engine every front end drives) and
//!   the step loop on its own thread (bounded channels in and out, real-time pacing against
//!   absolute deadlines, lockstep), what it is asked and gives out, the failsafe and
//!   checkpoints.
//! * [`mixed`]: mixed reality: real telemetry to twins (the gateway, the interpreter, the
//!   router), virtual sonar and virtual telemetry back (the outbox), over Zenoh, over Ivy, or
//!   both; keeping twins where their real copters are ([`mixed::sync`]: MEDUSA and tracking);
//!   when a real copter's telemetry arrives ([`mixed::link`]).
//! * [`realflight`]: a real flight's Paparazzi log as series in the simulator's frame, its
//!   flights, the arena its sonars describe and where each flight began; and
//!   [`realflight::fit`], system identification of the horizontal flight model from real
//!   flights' sonars and attitude, and the prediction errors it and the simpler models make.
//! * [`shard`]: a shard's link to its neighbours over Zenoh (ghosts, liveliness, barrier).
//! * [`autopilot`]: copters flown by outside autopilots (Paparazzi NPS), in lockstep over TCP,
//!   with their virtual-sonar uplink through Paparazzi's `link` counted in that lockstep.
//! * [`log`]: MCAP logs, their reader and recovery.
//! * [`live`]: the live view (a Foxglove WebSocket server).
//! * `ids.rs`: [`AcId`], at the bottom: every room that names an aircraft imports it from there.
//!
//! **Architecture invariant:** the format modules never do I/O except reading the files they
//! are asked to parse, and never panic on input. Zenoh is spoken by [`zenoh_net`] (the node and
//! the Paparazzi bus over Zenoh), [`ros2`] (its node, on the same session), [`shard`] (a shard's
//! own link: publishers, subscribers and liveliness to its neighbours) and [`mixed::gateway`]
//! (it hands a session to [`zenoh_net`]'s bus and puts the Ivy texts it bridges); nothing else
//! names `zenoh`. Only [`paparazzi::ivy`] opens Ivy sockets. Only [`engine`] steps the world
//! (tests aside), and its loop never blocks on publishing (but in lockstep, and where an
//! autopilot's uplink is counted: [`autopilot`]).

pub mod autopilot;
pub mod engine;
mod ids;
pub mod live;
pub mod log;
pub mod mixed;
pub mod paparazzi;
pub mod realflight;
pub mod ros2;
pub mod shard;
pub mod wire;
pub mod zenoh_net;

pub use ids::AcId;

/// Locks `m`, also after a panic elsewhere poisoned it. A poisoned lock still guards usable
/// data (counters, bindings, the world), and an input path never drops what arrives because an
/// earlier handler panicked; the panic itself was reported by the panic hook. Every
/// `std::sync::Mutex` in the bridge and the CLI is locked through this function.
pub fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// The CPU time this process has used so far, all its threads (user and system), s; `None`
/// where the system does not say. Beside a run's wall time it shows what the run cost: the
/// simulation's threads, the transport's, and the cores' waits left out.
#[allow(unsafe_code)]
pub fn process_cpu_s() -> Option<f64> {
    let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: `getrusage` fills the `rusage` it is given, or fails and leaves it zeroed.
    if unsafe { libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr()) } != 0 {
        return None;
    }
    // SAFETY: zeroed is a valid `rusage` (plain integers), and filled it is too.
    let usage = unsafe { usage.assume_init() };
    let seconds = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    Some(seconds(usage.ru_utime) + seconds(usage.ru_stime))
}

pub use paparazzi::bus::{BindId, Bus, BusError, Control, Delivery};
pub use paparazzi::codec::{CodecError, Message, Sender};
pub use paparazzi::conf::{Aircraft, AircraftKind, ConfXml, is_virtual_name};
pub use paparazzi::messages::{BaseType, FieldDef, FieldType, MessageDef, MessageSet};
pub use paparazzi::pairing::Pairing;
pub use paparazzi::telemetry::Telemetry;
pub use paparazzi::value::Value;
pub use paparazzi::xml::{Location, XmlError};
pub use zenoh_net::keyexpr::{key_expr_matches, key_for, key_for_text, narrow_key_expr};

#[cfg(test)]
mod tests {
    /// Work shows in the process's CPU time. (Other tests run in this process at the same
    /// time: what they spend counts too, so a sleep's cost is not checked here.)
    #[test]
    fn cpu_time_counts_work() {
        let start = super::process_cpu_s().expect("getrusage on this system");
        assert!(start > 0.0, "a running test has used some CPU: {start}");
        // Spin until 50 ms more are counted (however busy the machine), at most 20 s.
        let (wall, mut x) = (std::time::Instant::now(), 0u64);
        while super::process_cpu_s().unwrap() - start < 0.05 {
            x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
            assert!(wall.elapsed().as_secs() < 20, "20 s of spinning counted no CPU time");
        }
    }
}
