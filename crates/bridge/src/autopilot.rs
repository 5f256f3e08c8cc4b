//! Copters flown by outside autopilots: Paparazzi's rotorcraft autopilot compiled for its
//! simulator NPS, with this project's flight-model backend (`paparazzi/sw/nps_fdm_twinswarm.c`),
//! one process per aircraft, in lockstep with the world over a Unix-domain socket (both on one
//! machine) or TCP ([`transport`]).
//!
//! Each NPS step (1 ms at the airframe's `PERIODIC_FREQUENCY` 500) is one control step of the
//! world: the scene's `control_dt_s` must equal the autopilot's step, so that every autopilot
//! step sees the physics' answer to its own motor commands, with nothing held or extrapolated.
//! Per step, [`Autopilots::commands`] reads every aircraft's motor commands (blocking: the world
//! waits for the slowest autopilot) and [`Autopilots::answer`] sends every aircraft its copter's
//! state after the step. Nothing waits on the wall clock.
//!
//! # Protocol v2 (little-endian, fixed records, no padding; NPS connects and speaks first)
//!
//! | record | direction | layout | size |
//! |---|---|---|---|
//! | hello | NPS → world, once | `"TWFD"`, u32 version (2; 1 is still taken), u32 ac_id, f64 dt (s) | 20 |
//! | step | NPS → world, every step | u32 `0x54575331`, u64 step, u8 launch, u8 n = 4, f64 commands\[4\] | 46 |
//! | state | world → NPS, answer to a step | u32 `0x54575332`, u64 step, f64 t (s), pos\[3\], vel\[3\], accel\[3\] (NED), quat ned→body (w, x, y, z), body rates\[3\] (FRD), specific force\[3\] (FRD), agl, sonar\[4\] (front, right, back, left), ir (m; NaN: nothing in range), u8 crashed, u32 uplinks (v2 only) | 225 (v1: 221) |
//! | refused | world → NPS, in place of a state, then the world closes | u32 `0x54575330`, u16 n, n bytes of UTF-8: why | 6 + n |
//!
//! v2 added `uplinks`, the uplink in the lockstep (below); a v1 client (an aircraft built
//! before) is still flown, with v1's state records, and its uplink is not counted.
//!
//! # The uplink in the lockstep
//!
//! The run's outbox sends each autopilot aircraft the virtual-sonar uplink (`SONAR_UPLINK`, or
//! `VIRTUAL_SONAR`) as it sends a real FINken, over Ivy to Paparazzi's real `link`, which
//! forwards it over UDP to the aircraft's datalink whenever it gets it. To make such a run
//! reproducible, the world counts, per aircraft, the uplink messages it has handed to its Ivy
//! agent, and tells the aircraft that count in each state record (`uplinks`: sent before this
//! state). NPS (`nps_fdm_twinswarm.c`) holds the datalink's frames in its own queue and gives
//! its autopilot's datalink parsing the counted ones only up to that count, waiting (bounded)
//! for any still on the way: each uplink reaches the autopilot at the step the world named.
//!
//! `link` forwards an uplink only to an aircraft it has heard from (its telemetry gives link
//! the aircraft's address). So the counted uplink to an aircraft starts with the first uplink at
//! or after [`UPLINK_START_S`] of simulated time: the world sends none before, and waits at that
//! step (at most [`LINK_HEARD_TIMEOUT`]) until `link` has relayed a telemetry message of the
//! aircraft on the bus, and checks that a peer takes the uplink message at all. A real FINken
//! too gets no uplink before `link` has heard it. Without either (no `link` on the bus, or one
//! whose messages.xml lacks the message) the aircraft's uplink is sent as before, not counted
//! (`uplinks` `0xFFFFFFFF`: NPS takes its datalink as it comes), and its stats say why. The count is only
//! kept where the run sends the uplink on a real Ivy bus ([`Autopilots::count_uplinks`]); a
//! run on Zenoh alone does not count it either. The world must be the only sender of that
//! message to the aircraft; a message lost on the way ends the aircraft's NPS with an error.
//!
//! The world refuses an aircraft it cannot fly (no copter of the scene has its `ac_id`, or one
//! already flown; another step rate; a bad hello) and drops one that stalled past the step
//! timeout or broke the protocol; either way it says why in a `refused` record and shuts the
//! connection, so NPS exits non-zero with the reason instead of waiting on a silent socket
//! (also an NPS stopped with SIGSTOP and continued after the world dropped it).
//!
//! Commands are Paparazzi's motor-mixing outputs over `MAX_PPRZ` in the airframe's motor order
//! (0 front right, 1 back right, 2 back left, 3 front left); −1 means stopped. They become the
//! copter's [`FlightMode::Rotors`] commands, fractions of each rotor's maximum thrust (Paparazzi
//! assumes thrust roughly linear in its command, hover at 0.5, which the FINken's thrust ratio
//! 2 gives). Frames: the world's x is north, so NED = (x, −y, −z) and body FRD = FLU with y and
//! z negated.

use std::collections::{BTreeMap, BTreeSet};
use std::io::{Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::Serialize;
use sim_core::math::{GRAVITY_M_S2, Vec3};
use sim_core::{CopterKind, FlightMode, Inputs, State, World};

use crate::ids::AcId;
use crate::paparazzi::ivy::IvyAgent;

pub mod transport;
pub use transport::{BadListen, Listen};
use transport::{Listener, SocketFile, Stream};

/// Where the world listens by default (`nps_fdm_twinswarm.c`'s default `TWINSWARM_FDM`).
pub const DEFAULT_LISTEN: &str = "127.0.0.1:7460";
/// The protocol version this side speaks (it also takes version 1 clients).
pub const VERSION: u32 = 2;
const HELLO_LEN: usize = 20;
const STEP_LEN: usize = 46;
const STATE_LEN: usize = 225;
const STATE_LEN_V1: usize = 221;
/// A state record's `uplinks` when the world does not count the aircraft's uplink.
pub const UPLINKS_NOT_COUNTED: u32 = u32::MAX;
/// The counted uplink to an aircraft starts with its first uplink at or after this simulated
/// time, s: by then its telemetry (4 Hz and faster) has reached `link`.
pub const UPLINK_START_S: f64 = 0.5;
/// How long the world waits, there, for `link` to relay a telemetry message of the aircraft.
pub const LINK_HEARD_TIMEOUT: Duration = Duration::from_secs(10);
/// Paparazzi's `link` on the Ivy bus (its application name).
pub const LINK_IVY_NAME: &str = "Link";
const STEP_MAGIC: u32 = 0x5457_5331;
const STATE_MAGIC: u32 = 0x5457_5332;
const REFUSED_MAGIC: u32 = 0x5457_5330;
/// A refusal's reason is cut to this many bytes (at a character boundary).
const REFUSED_MAX: usize = 1000;

/// A record that is not what the protocol says.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ProtocolError {
    /// The hello does not start with `TWFD`.
    #[error("not a Twinswarm flight-model client (hello starts with {0:02x?}, not \"TWFD\")")]
    NotHello([u8; 4]),
    /// Another protocol version.
    #[error("protocol version {0}, this Twinswarm speaks {VERSION} (and 1)")]
    Version(u32),
    /// An aircraft id that does not fit Paparazzi's `uint8`.
    #[error("ac_id {0} is not a Paparazzi aircraft id (0-255)")]
    AcId(u32),
    /// A step of no possible length.
    #[error("step length {0} s is not a positive finite number")]
    Dt(f64),
    /// A step record with the wrong magic.
    #[error("step record magic {0:#010x}, expected {STEP_MAGIC:#010x}")]
    StepMagic(u32),
    /// Not four motors.
    #[error("{0} motor commands, the FINken has 4")]
    Motors(u8),
    /// A step out of order.
    #[error("step {got}, expected {expected}")]
    StepNumber {
        /// Received.
        got: u64,
        /// The world's tick.
        expected: u64,
    },
    /// A command that is not a number.
    #[error("motor {motor} command is {value}, not a finite number")]
    Command {
        /// Motor index (Paparazzi's order).
        motor: usize,
        /// The value.
        value: f64,
    },
}

/// A client's hello.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hello {
    /// The aircraft id compiled into the autopilot.
    pub ac_id: u8,
    /// The autopilot's step, s.
    pub dt_s: f64,
    /// The protocol version it speaks (1 or 2).
    pub version: u32,
}

/// Decodes a hello record.
pub fn decode_hello(b: &[u8; HELLO_LEN]) -> Result<Hello, ProtocolError> {
    let magic: [u8; 4] = b[0..4].try_into().expect("4 bytes");
    if &magic != b"TWFD" {
        return Err(ProtocolError::NotHello(magic));
    }
    let version = u32_at(b, 4);
    if !(1..=VERSION).contains(&version) {
        return Err(ProtocolError::Version(version));
    }
    let ac_id = u32_at(b, 8);
    let ac_id = u8::try_from(ac_id).map_err(|_| ProtocolError::AcId(ac_id))?;
    let dt_s = f64_at(b, 12);
    if !(dt_s.is_finite() && dt_s > 0.0) {
        return Err(ProtocolError::Dt(dt_s));
    }
    Ok(Hello { ac_id, dt_s, version })
}

/// One step's motor commands.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepRecord {
    /// The autopilot's step number (0 from its initialisation).
    pub step: u64,
    /// Commands in Paparazzi's motor order, −1 (stopped) to 1.
    pub commands: [f64; 4],
}

/// Decodes a step record.
pub fn decode_step(b: &[u8; STEP_LEN]) -> Result<StepRecord, ProtocolError> {
    let magic = u32_at(b, 0);
    if magic != STEP_MAGIC {
        return Err(ProtocolError::StepMagic(magic));
    }
    if b[13] != 4 {
        return Err(ProtocolError::Motors(b[13]));
    }
    let commands: [f64; 4] = std::array::from_fn(|k| f64_at(b, 14 + 8 * k));
    if let Some((motor, &value)) = commands.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(ProtocolError::Command { motor, value });
    }
    Ok(StepRecord { step: u64::from_le_bytes(b[4..12].try_into().expect("8 bytes")), commands })
}

/// Paparazzi's motor commands as the copter's rotor commands: motor 0 front right, 1 back
/// right, 2 back left, 3 front left → Twinswarm's front left, front right, back right, back
/// left; stopped (−1) and anything below 0 is 0.
pub fn rotor_commands(commands: [f64; 4]) -> [f32; 4] {
    [commands[3], commands[0], commands[1], commands[2]].map(|c| c.clamp(0.0, 1.0) as f32)
}

/// The state one autopilot is told after a step, in its frames (NED, FRD).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FdmState {
    /// The step answered.
    pub step: u64,
    /// World time after the step, s.
    pub t_s: f64,
    /// Position, m, NED from the arena centre on the floor.
    pub pos_ned: [f64; 3],
    /// Velocity, m/s, NED.
    pub vel_ned: [f64; 3],
    /// Acceleration, m/s², NED, without gravity.
    pub accel_ned: [f64; 3],
    /// Paparazzi's `ltp_to_body` quaternion, (w, x, y, z).
    pub quat_ned_to_body: [f64; 4],
    /// Body rates (p, q, r), rad/s, FRD.
    pub rates_frd: [f64; 3],
    /// Specific force, m/s², FRD: (0, 0, −9.81) at rest.
    pub specific_force_frd: [f64; 3],
    /// Height above what is below, m.
    pub agl_m: f64,
    /// Physical sonar readings (front, right, back, left), m; NaN: no echo.
    pub sonar_m: [f64; 4],
    /// IR height, m; NaN: nothing in range.
    pub ir_m: f64,
    /// Whether the copter crashed.
    pub crashed: bool,
    /// The uplink messages the world sent the aircraft through `link` before this state
    /// ([`UPLINKS_NOT_COUNTED`]: not counted). Not part of a v1 record.
    pub uplinks: u32,
}

/// Encodes a state record (v2; a v1 record is its first 221 bytes).
pub fn encode_state(s: &FdmState) -> [u8; STATE_LEN] {
    let mut b = [0u8; STATE_LEN];
    b[0..4].copy_from_slice(&STATE_MAGIC.to_le_bytes());
    b[4..12].copy_from_slice(&s.step.to_le_bytes());
    let floats = std::iter::once(s.t_s)
        .chain(s.pos_ned)
        .chain(s.vel_ned)
        .chain(s.accel_ned)
        .chain(s.quat_ned_to_body)
        .chain(s.rates_frd)
        .chain(s.specific_force_frd)
        .chain([s.agl_m])
        .chain(s.sonar_m)
        .chain([s.ir_m]);
    for (k, v) in floats.enumerate() {
        b[12 + 8 * k..20 + 8 * k].copy_from_slice(&v.to_le_bytes());
    }
    b[STATE_LEN_V1 - 1] = u8::from(s.crashed);
    b[STATE_LEN_V1..STATE_LEN].copy_from_slice(&s.uplinks.to_le_bytes());
    b
}

/// Copter `id`'s state after a step, as its autopilot is told it. `prev_vel` is its velocity
/// before the step (world frame), `dt` the step.
pub fn fdm_state(world: &World, state: &State, id: usize, prev_vel: Vec3, dt: f64) -> FdmState {
    let c = &state.copters[id];
    let m = &c.motion;
    let ned = |v: Vec3| [f64::from(v.x), -f64::from(v.y), -f64::from(v.z)];
    let accel = (m.vel_m_s - prev_vel) / dt as f32;
    let specific = m.rot.inverse() * (accel + Vec3::new(0.0, 0.0, GRAVITY_M_S2));
    let rates = m.rot.inverse() * m.angvel_rad_s;
    let r = &c.sensors;
    let cap = world.sensors.spec.sonar.cap_m;
    let sonar = r.sonar_m.map(|s| if s >= cap { f64::NAN } else { f64::from(s) });
    let q = m.rot;
    FdmState {
        step: state.tick.saturating_sub(1),
        t_s: state.time_s(world),
        pos_ned: ned(m.pos_m),
        vel_ned: ned(m.vel_m_s),
        accel_ned: ned(accel),
        quat_ned_to_body: [f64::from(q.w), f64::from(q.x), -f64::from(q.y), -f64::from(q.z)],
        rates_frd: ned(rates),
        specific_force_frd: ned(specific),
        agl_m: f64::from(if r.ir_truth_m.is_finite() { r.ir_truth_m } else { m.pos_m.z }),
        sonar_m: sonar,
        ir_m: r.ir_m.map_or(f64::NAN, f64::from),
        crashed: c.crash.is_some(),
        uplinks: UPLINKS_NOT_COUNTED,
    }
}

/// How the world meets its autopilots.
#[derive(Debug, Clone)]
pub struct AutopilotOptions {
    /// Where to listen for them: TCP or a Unix-domain socket ([`transport`]).
    pub listen: Listen,
    /// How long to wait for every autopilot's hello before the first step.
    pub connect_timeout: Duration,
    /// How long one step waits for an autopilot before it counts as gone.
    pub step_timeout: Duration,
}

impl Default for AutopilotOptions {
    fn default() -> Self {
        Self {
            listen: DEFAULT_LISTEN.parse().expect("valid address"),
            connect_timeout: Duration::from_secs(60),
            step_timeout: Duration::from_secs(10),
        }
    }
}

/// Why the autopilots could not be met.
#[derive(Debug, thiserror::Error)]
pub enum AutopilotError {
    /// The listening socket (the reason is the error's source).
    #[error("cannot listen for autopilots on {addr}")]
    Listen {
        /// The address (`HOST:PORT` or `unix:PATH`).
        addr: String,
        /// Why.
        source: std::io::Error,
    },
    /// Not every autopilot came.
    #[error("no autopilot connected for {missing} within {waited_s:.0} s (listening on {addr})")]
    Missing {
        /// The aircraft still missing, as `ac_id (copter)`.
        missing: String,
        /// Waited, s.
        waited_s: f64,
        /// Where (`HOST:PORT` or `unix:PATH`).
        addr: String,
    },
    /// An autopilot steps at another rate than the world.
    #[error(
        "aircraft {ac_id} steps every {autopilot_ms} ms, but the scene's control_dt_s is {world_ms} ms: \
         set [sim] control_dt_s (and physics_dt_s) to the autopilot's step, or build the aircraft with \
         PERIODIC_FREQUENCY = 1 / (2 × control_dt_s)"
    )]
    Rate {
        /// The aircraft.
        ac_id: u8,
        /// Its step, ms.
        autopilot_ms: f64,
        /// The world's control step, ms.
        world_ms: f64,
    },
}

/// What one autopilot did over the run.
#[derive(Debug, Clone, Default, Serialize)]
pub struct AutopilotStats {
    /// Its aircraft id.
    pub ac_id: u8,
    /// The copter it flew.
    pub copter: String,
    /// Where it connected from.
    pub peer: String,
    /// Steps exchanged.
    pub steps: u64,
    /// Wall time spent waiting for its commands, s.
    pub wait_s: f64,
    /// The tick at which it left, and why, if it did before the end.
    pub left: Option<(u64, String)>,
    /// The protocol version it spoke.
    pub protocol: u32,
    /// Its uplink in the lockstep: `"counted"` (from [`UPLINK_START_S`] on), `"not counted"`
    /// (none through `link`, or a v1 client), or why it stopped being counted.
    pub uplink: String,
    /// Uplink messages the world sent it through `link`, counted in the lockstep.
    pub uplinks_counted: u64,
}

/// An autopilot the world turned away at its hello.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Refusal {
    /// Where it connected from.
    pub peer: String,
    /// The aircraft its hello named, if it sent one.
    pub ac_id: Option<u8>,
    /// Why.
    pub why: String,
}

struct Conn {
    copter: usize,
    stream: Stream,
    prev_vel: Vec3,
    gone: bool,
    stats: AutopilotStats,
    counting: Counting,
}

/// Where an aircraft's uplink stands (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Counting {
    /// Not counted.
    Off,
    /// Counted, none sent yet: before [`UPLINK_START_S`].
    Before,
    /// Counted: this many sent.
    Sent(u32),
}

impl Counting {
    fn field(self) -> u32 {
        match self {
            Counting::Off => UPLINKS_NOT_COUNTED,
            Counting::Before => 0,
            Counting::Sent(n) => n,
        }
    }
}

/// Which aircraft Paparazzi's `link` has relayed telemetry of, as seen on the Ivy bus.
struct LinkWatch {
    ivy: Option<Arc<IvyAgent>>,
    heard: Arc<Mutex<BTreeSet<u8>>>,
    /// The binding per aircraft, until it is heard.
    binds: BTreeMap<u8, u32>,
}

/// The world's side of its autopilots (see the module docs).
pub struct Autopilots {
    conns: Vec<Conn>,
    /// The autopilots turned away, while waiting for all of them and after (by `late`).
    refused: Arc<Mutex<Vec<Refusal>>>,
    /// Refuses the autopilots that come once every copter has its own; held for its `Drop`.
    _late: Option<LateDoor>,
    /// The Unix socket's file (and the folder made for it), removed when dropped; after the
    /// door, so that no one connects in between.
    _socket: Option<SocketFile>,
    listening_on: String,
    dt_s: f64,
    /// The step waiting time of all autopilots together, s.
    wait_s: f64,
    /// Where the uplink goes through `link` ([`Autopilots::count_uplinks`]).
    link: Option<LinkWatch>,
}

impl std::fmt::Debug for Autopilots {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Autopilots").field("count", &self.conns.len()).finish_non_exhaustive()
    }
}

impl Autopilots {
    /// Listens on `opts.listen` and waits for one autopilot per copter of kind
    /// [`CopterKind::Autopilot`], bound by the `ac_id` of its hello. A hello for no such copter
    /// (or one already flown) is refused and the wait goes on; a rate other than the world's is
    /// an error.
    pub fn accept(world: &World, opts: &AutopilotOptions) -> Result<Self, AutopilotError> {
        Self::accept_with(world, opts, |_| {})
    }

    /// [`Autopilots::accept`], telling `bound` where it listens (`HOST:PORT` or `unix:PATH`:
    /// with [`Listen::Unix`]`(None)` the fresh socket's path) before it waits.
    pub fn accept_with(
        world: &World,
        opts: &AutopilotOptions,
        bound: impl FnOnce(&str),
    ) -> Result<Self, AutopilotError> {
        let listen_err = |source| AutopilotError::Listen { addr: opts.listen.to_string(), source };
        let (listener, file) = Listener::bind(&opts.listen).map_err(listen_err)?;
        bound(&listener.local().map_err(listen_err)?);
        let mut aps = Self::accept_on(listener, world, opts)?;
        aps._socket = file;
        Ok(aps)
    }

    /// Where `twinswarm run` tells its autopilots to connect (`TWINSWARM_FDM`), once bound:
    /// `HOST:PORT` or `unix:PATH`.
    pub fn listening_on(&self) -> &str {
        &self.listening_on
    }

    /// [`Autopilots::accept`] on a listener already bound (TCP or Unix).
    pub fn accept_on(
        listener: impl Into<Listener>,
        world: &World,
        opts: &AutopilotOptions,
    ) -> Result<Self, AutopilotError> {
        let listener = listener.into();
        let addr =
            listener.local().map_err(|source| AutopilotError::Listen { addr: opts.listen.to_string(), source })?;
        let listen_err = |source| AutopilotError::Listen { addr: addr.clone(), source };
        listener.set_nonblocking(true).map_err(listen_err)?;
        let mut wanted: Vec<(u8, usize)> = world
            .copters
            .iter()
            .enumerate()
            .filter(|(_, c)| c.kind == CopterKind::Autopilot)
            .filter_map(|(i, c)| Some((c.ac_id?, i)))
            .collect();
        let dt_s = world.params.control_dt_s;
        let start = Instant::now();
        let (mut conns, mut refused) = (Vec::new(), Vec::new());
        let mut refuse = |stream: &Stream, peer: &str, ac_id: Option<u8>, why: String| {
            tracing::warn!("autopilot from {peer} refused: {why}");
            send_refusal(stream, &why);
            refused.push(Refusal { peer: peer.to_owned(), ac_id, why });
        };
        while !wanted.is_empty() {
            if start.elapsed() > opts.connect_timeout {
                let missing = wanted
                    .iter()
                    .map(|&(ac, i)| format!("aircraft {ac} ({})", world.copters[i].name))
                    .collect::<Vec<_>>()
                    .join(", ");
                let waited_s = start.elapsed().as_secs_f64();
                return Err(AutopilotError::Missing { missing, waited_s, addr: addr.clone() });
            }
            let (stream, peer) = match listener.accept() {
                Ok(s) => s,
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    std::thread::sleep(Duration::from_millis(5));
                    continue;
                }
                Err(e) => return Err(listen_err(e)),
            };
            let hello = match read_hello(&stream, opts.step_timeout) {
                Ok(h) => h,
                Err(why) => {
                    refuse(&stream, &peer, None, why);
                    continue;
                }
            };
            if (hello.dt_s - dt_s).abs() > 1e-9 {
                let e =
                    AutopilotError::Rate { ac_id: hello.ac_id, autopilot_ms: hello.dt_s * 1e3, world_ms: dt_s * 1e3 };
                send_refusal(&stream, &e.to_string());
                return Err(e);
            }
            let Some(k) = wanted.iter().position(|&(ac, _)| ac == hello.ac_id) else {
                let why = format!("aircraft {} flies no copter of this scene (or one already flown)", hello.ac_id);
                refuse(&stream, &peer, Some(hello.ac_id), why);
                continue;
            };
            let (ac_id, copter) = wanted.swap_remove(k);
            let _ = stream.set_nodelay();
            let _ = stream.set_read_timeout(Some(opts.step_timeout));
            tracing::info!("autopilot of aircraft {ac_id} connected from {peer}: flies {}", world.copters[copter].name);
            let stats = AutopilotStats {
                ac_id,
                copter: world.copters[copter].name.clone(),
                peer,
                protocol: hello.version,
                uplink: "not counted".to_owned(),
                ..Default::default()
            };
            let counting = Counting::Off;
            conns.push(Conn { copter, stream, prev_vel: Vec3::ZERO, gone: false, stats, counting });
        }
        conns.sort_by_key(|c| c.copter);
        let refused = Arc::new(Mutex::new(refused));
        let flown = conns.iter().map(|c: &Conn| c.stats.ac_id).collect();
        let late = LateDoor::open(listener, flown, Arc::clone(&refused), opts.step_timeout);
        Ok(Self { conns, refused, _late: Some(late), _socket: None, listening_on: addr, dt_s, wait_s: 0.0, link: None })
    }

    /// How many autopilots there are.
    pub fn len(&self) -> usize {
        self.conns.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.conns.is_empty()
    }

    /// Reads every autopilot's commands for the step from `state.tick` and sets its copter's
    /// rotors. An autopilot that closed, stalled past the step timeout or broke the protocol is
    /// gone: its copter's motors stop, and the run goes on.
    pub fn commands(&mut self, world: &World, state: &State, inputs: &mut Inputs) {
        let tick = state.tick;
        let t0 = Instant::now();
        for conn in self.conns.iter_mut().filter(|c| !c.gone) {
            conn.prev_vel = state.copters[conn.copter].motion.vel_m_s;
            let waited = Instant::now();
            let got = read_step(&conn.stream, tick);
            conn.stats.wait_s += waited.elapsed().as_secs_f64();
            let cmd = &mut inputs.commands[conn.copter];
            cmd.mode = FlightMode::Rotors;
            match got {
                Ok(rec) => cmd.rotors = Some(rotor_commands(rec.commands)),
                Err(why) => {
                    cmd.rotors = Some([0.0; 4]);
                    tracing::warn!(
                        "autopilot of aircraft {} ({}) gone at tick {tick}: {why}; its motors stop",
                        conn.stats.ac_id,
                        world.copters[conn.copter].name
                    );
                    send_refusal(&conn.stream, &format!("dropped at step {tick}: {why}"));
                    conn.stats.left = Some((tick, why));
                    conn.gone = true;
                }
            }
        }
        self.wait_s += t0.elapsed().as_secs_f64();
    }

    /// Sends every autopilot its copter's state after the step.
    pub fn answer(&mut self, world: &World, state: &State) {
        for conn in self.conns.iter_mut().filter(|c| !c.gone) {
            let mut s = fdm_state(world, state, conn.copter, conn.prev_vel, self.dt_s);
            s.uplinks = conn.counting.field();
            let b = encode_state(&s);
            let b = if conn.stats.protocol == 1 { &b[..STATE_LEN_V1] } else { &b[..] };
            match (&conn.stream).write_all(b) {
                Ok(()) => conn.stats.steps += 1,
                Err(e) => {
                    let _ = conn.stream.shutdown();
                    conn.stats.left = Some((state.tick, format!("cannot send its state: {e}")));
                    conn.gone = true;
                }
            }
        }
    }

    /// Counts the uplink of each aircraft for which `sends_uplink` holds in the lockstep (see
    /// the module docs): the run sends it on the Ivy bus of `ivy`, where Paparazzi's `link`
    /// forwards it. Binds, per such aircraft, its telemetry as `link` relays it, until heard.
    /// A v1 client's uplink stays uncounted.
    pub fn count_uplinks(
        &mut self,
        ivy: &Arc<IvyAgent>,
        sends_uplink: impl Fn(AcId) -> bool,
    ) -> Result<(), crate::paparazzi::ivy::IvyError> {
        let heard = Arc::new(Mutex::new(BTreeSet::new()));
        let mut binds = BTreeMap::new();
        for ac in self.start_counting(sends_uplink) {
            let h = Arc::clone(&heard);
            let id = ivy.bind(&format!("^{ac} "), move |_, _| {
                crate::lock(&h).insert(ac);
            })?;
            binds.insert(ac, id);
        }
        if !binds.is_empty() {
            // Before the first step: `link` must have the bindings before it relays the
            // aircraft's first telemetry, or the world, waiting at the first counted uplink
            // with the aircraft held in the lockstep, would hear none (a loaded machine).
            if !ivy.sync_with(LINK_IVY_NAME, LINK_HEARD_TIMEOUT) {
                tracing::warn!(
                    "no {LINK_IVY_NAME} on the Ivy bus answered within {} s: the uplink may go uncounted",
                    LINK_HEARD_TIMEOUT.as_secs()
                );
            }
            self.link = Some(LinkWatch { ivy: Some(Arc::clone(ivy)), heard, binds });
        }
        Ok(())
    }

    /// Counts the uplink of the v2 clients among the aircraft for which `sends_uplink` holds;
    /// returns their ids.
    fn start_counting(&mut self, sends_uplink: impl Fn(AcId) -> bool) -> Vec<u8> {
        let mut counted = Vec::new();
        for conn in self.conns.iter_mut().filter(|c| sends_uplink(c.stats.ac_id)) {
            let ac = conn.stats.ac_id;
            if conn.stats.protocol < 2 {
                conn.stats.uplink = "not counted: its NPS speaks protocol v1 (rebuild the aircraft)".to_owned();
                tracing::warn!("aircraft {ac}: its uplink is not in the lockstep: {}", conn.stats.uplink);
                continue;
            }
            conn.counting = Counting::Before;
            conn.stats.uplink = "counted".to_owned();
            counted.push(ac);
        }
        counted
    }

    /// Whether an aircraft's uplink is counted (then the run must not lose a frame).
    pub fn counts_uplinks(&self) -> bool {
        self.conns.iter().any(|c| c.counting != Counting::Off)
    }

    /// Whether the run sends the uplink `text` the outbox made for aircraft `ac_id` after the
    /// step to `t_s`, and counts it (an aircraft no autopilot flies: sent, not counted). A
    /// counted uplink before [`UPLINK_START_S`] is not sent; at the first one after, the world
    /// waits until `link` has relayed the aircraft's telemetry (at most [`LINK_HEARD_TIMEOUT`])
    /// and checks that a peer on the bus takes the text; without either, the aircraft's uplink
    /// is sent uncounted from then on.
    pub fn uplink(&mut self, ac_id: AcId, text: &str, t_s: f64) -> bool {
        let Some(conn) = self.conns.iter_mut().find(|c| c.stats.ac_id == ac_id) else { return true };
        match conn.counting {
            Counting::Off => true,
            Counting::Before if t_s + 1e-9 < UPLINK_START_S => false,
            Counting::Before => {
                let watch = self.link.as_mut().expect("a counted uplink has its link watch");
                let heard = conn.gone || watch.wait_heard(ac_id, LINK_HEARD_TIMEOUT);
                if let (Some(id), Some(ivy)) = (watch.binds.remove(&ac_id), &watch.ivy) {
                    ivy.unbind(id);
                }
                let name = text.split(' ').nth(1).unwrap_or("?");
                let why = match &watch.ivy {
                    _ if !heard => Some(format!(
                        "link relayed no telemetry of the aircraft within {} s",
                        LINK_HEARD_TIMEOUT.as_secs()
                    )),
                    Some(ivy) if ivy.takers(text) == 0 => {
                        Some(format!("no peer on the Ivy bus takes {name} (is it in link's messages.xml?)"))
                    }
                    _ => None,
                };
                match why {
                    None => {
                        conn.counting = Counting::Sent(1);
                        conn.stats.uplinks_counted = 1;
                    }
                    Some(why) => {
                        conn.counting = Counting::Off;
                        conn.stats.uplink = format!("not counted from {t_s:.3} s: {why}");
                        tracing::warn!("aircraft {ac_id}: its uplink is not in the lockstep: {}", conn.stats.uplink);
                    }
                }
                true
            }
            Counting::Sent(n) => {
                conn.counting = Counting::Sent(n.saturating_add(1).min(UPLINKS_NOT_COUNTED - 1));
                conn.stats.uplinks_counted += 1;
                true
            }
        }
    }

    /// What each autopilot did, in copter order.
    pub fn stats(&self) -> Vec<AutopilotStats> {
        self.conns.iter().map(|c| c.stats.clone()).collect()
    }

    /// The autopilots turned away at their hello, in the order they came.
    pub fn refused(&self) -> Vec<Refusal> {
        crate::lock(&self.refused).clone()
    }

    /// The wall time all steps waited for the autopilots, s.
    pub fn wait_s(&self) -> f64 {
        self.wait_s
    }
}

impl LinkWatch {
    /// Whether `link` has relayed a telemetry message of `ac_id`, waiting up to `timeout`.
    fn wait_heard(&self, ac_id: u8, timeout: Duration) -> bool {
        let start = Instant::now();
        loop {
            if crate::lock(&self.heard).contains(&ac_id) {
                return true;
            }
            if start.elapsed() > timeout {
                return false;
            }
            std::thread::sleep(Duration::from_millis(1));
        }
    }
}

/// The listener after every copter has its autopilot: a thread that tells each newcomer why
/// it will not fly (instead of leaving it in the backlog or refusing its connection, which
/// NPS would retry for its whole connect timeout). Closed when the [`Autopilots`] are dropped.
struct LateDoor {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl LateDoor {
    fn open(listener: Listener, flown: Vec<u8>, refused: Arc<Mutex<Vec<Refusal>>>, timeout: Duration) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let flag = Arc::clone(&stop);
        let thread = std::thread::Builder::new().name("autopilot-door".into()).spawn(move || {
            while !flag.load(Ordering::Relaxed) {
                let Ok((stream, peer)) = listener.accept() else {
                    std::thread::sleep(Duration::from_millis(20));
                    continue;
                };
                let hello = read_hello(&stream, timeout.min(Duration::from_secs(2)));
                let ac_id = hello.as_ref().ok().map(|h| h.ac_id);
                let why = match ac_id {
                    Some(ac) if flown.contains(&ac) => {
                        format!("aircraft {ac} came after the run started: its copter already has its autopilot")
                    }
                    Some(ac) => format!("aircraft {ac} flies no copter of this scene"),
                    None => format!("came after the run started ({})", hello.err().unwrap_or_default()),
                };
                tracing::warn!("autopilot from {peer} refused: {why}");
                send_refusal(&stream, &why);
                crate::lock(&refused).push(Refusal { peer: peer.to_string(), ac_id, why });
            }
        });
        Self { stop, thread: thread.ok() }
    }
}

impl Drop for LateDoor {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A `refused` record: the reason, cut to [`REFUSED_MAX`] bytes at a character boundary.
pub fn encode_refusal(why: &str) -> Vec<u8> {
    let mut end = why.len().min(REFUSED_MAX);
    while !why.is_char_boundary(end) {
        end -= 1;
    }
    let mut b = Vec::with_capacity(6 + end);
    b.extend_from_slice(&REFUSED_MAGIC.to_le_bytes());
    b.extend_from_slice(&(end as u16).to_le_bytes());
    b.extend_from_slice(&why.as_bytes()[..end]);
    b
}

/// Tells an autopilot why the world will not fly it (best effort: it may be gone) and shuts
/// the connection, so that it reads the end of the stream after the reason.
fn send_refusal(mut stream: &Stream, why: &str) {
    let _ = stream.set_write_timeout(Some(Duration::from_secs(1)));
    let _ = stream.write_all(&encode_refusal(why));
    let _ = stream.shutdown();
}

fn read_hello(mut stream: &Stream, timeout: Duration) -> Result<Hello, String> {
    stream.set_nonblocking(false).map_err(|e| e.to_string())?;
    stream.set_read_timeout(Some(timeout)).map_err(|e| e.to_string())?;
    let mut b = [0u8; HELLO_LEN];
    stream.read_exact(&mut b).map_err(|e| format!("no hello: {e}"))?;
    decode_hello(&b).map_err(|e| e.to_string())
}

fn read_step(mut stream: &Stream, tick: u64) -> Result<StepRecord, String> {
    let mut b = [0u8; STEP_LEN];
    stream.read_exact(&mut b).map_err(|e| match e.kind() {
        std::io::ErrorKind::UnexpectedEof => "it closed the connection".to_owned(),
        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut => {
            "no commands within the step timeout".to_owned()
        }
        _ => e.to_string(),
    })?;
    let rec = decode_step(&b).map_err(|e| e.to_string())?;
    if rec.step != tick {
        return Err(ProtocolError::StepNumber { got: rec.step, expected: tick }.to_string());
    }
    Ok(rec)
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}

fn f64_at(b: &[u8], at: usize) -> f64 {
    f64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::{TcpListener, TcpStream};

    fn hello(ac: u32, dt: f64) -> [u8; HELLO_LEN] {
        hello_v(ac, dt, VERSION)
    }

    fn hello_v(ac: u32, dt: f64, version: u32) -> [u8; HELLO_LEN] {
        let mut b = [0u8; HELLO_LEN];
        b[0..4].copy_from_slice(b"TWFD");
        b[4..8].copy_from_slice(&version.to_le_bytes());
        b[8..12].copy_from_slice(&ac.to_le_bytes());
        b[12..20].copy_from_slice(&dt.to_le_bytes());
        b
    }

    fn step(k: u64, cmds: [f64; 4]) -> [u8; STEP_LEN] {
        let mut b = [0u8; STEP_LEN];
        b[0..4].copy_from_slice(&STEP_MAGIC.to_le_bytes());
        b[4..12].copy_from_slice(&k.to_le_bytes());
        b[12] = 1;
        b[13] = 4;
        for (i, c) in cmds.iter().enumerate() {
            b[14 + 8 * i..22 + 8 * i].copy_from_slice(&c.to_le_bytes());
        }
        b
    }

    #[test]
    fn records_decode_and_bad_ones_are_named() {
        assert_eq!(decode_hello(&hello(7, 0.001)), Ok(Hello { ac_id: 7, dt_s: 0.001, version: 2 }));
        assert_eq!(decode_hello(&hello_v(7, 0.001, 1)), Ok(Hello { ac_id: 7, dt_s: 0.001, version: 1 }));
        assert_eq!(decode_hello(&hello_v(7, 0.001, 3)), Err(ProtocolError::Version(3)));
        assert_eq!(decode_hello(&hello_v(7, 0.001, 0)), Err(ProtocolError::Version(0)));
        assert_eq!(decode_hello(&hello(300, 0.001)), Err(ProtocolError::AcId(300)));
        assert!(matches!(decode_hello(&hello(7, f64::NAN)), Err(ProtocolError::Dt(_))));
        let mut b = hello(7, 0.001);
        b[0] = b'X';
        assert!(decode_hello(&b).unwrap_err().to_string().contains("TWFD"));
        let rec = decode_step(&step(3, [0.5, -1.0, 0.25, 1.0])).unwrap();
        assert_eq!(rec, StepRecord { step: 3, commands: [0.5, -1.0, 0.25, 1.0] });
        assert!(matches!(
            decode_step(&step(3, [0.5, f64::INFINITY, 0.0, 0.0])),
            Err(ProtocolError::Command { motor: 1, .. })
        ));
        let mut b = step(3, [0.0; 4]);
        b[13] = 6;
        assert_eq!(decode_step(&b), Err(ProtocolError::Motors(6)));
    }

    #[test]
    fn motors_map_to_rotors_and_stopped_is_zero() {
        // Paparazzi: FR, BR, BL, FL; Twinswarm: FL, FR, BR, BL.
        assert_eq!(rotor_commands([0.1, 0.2, 0.3, 0.4]), [0.4, 0.1, 0.2, 0.3]);
        assert_eq!(rotor_commands([-1.0, 2.0, 0.5, -0.5]), [0.0, 0.0, 1.0, 0.5]);
    }

    /// A 1 ms world in the 4 × 3 m arena with these `[[copter]]` tables.
    fn world_of(copters: &str) -> (World, State) {
        let scene = format!(
            "name = \"ap\"\n[sim]\nphysics_dt_s = 0.001\ncontrol_dt_s = 0.001\n\
             [arena]\nsize_m = [4.0, 3.0]\nheight_m = 2.5\n{copters}"
        );
        let spec = sim_core::SceneSpec::from_toml("ap.toml", &scene).unwrap();
        let world = sim_core::compile(&spec).unwrap();
        let state = world.initial_state();
        (world, state)
    }

    fn world() -> (World, State) {
        world_of(
            r#"[[copter]]
name = "nps"
kind = "autopilot"
ac_id = 7
start = { pos_m = [0.5, -0.25, 0.0], yaw_deg = 30.0 }
"#,
        )
    }

    #[test]
    fn the_state_is_told_in_ned_and_frd() {
        let (world, mut state) = world();
        let inputs = world.initial_inputs();
        sim_core::step(&world, &mut state, &inputs);
        let s = fdm_state(&world, &state, 0, Vec3::ZERO, 0.001);
        assert_eq!(s.step, 0);
        assert!((s.pos_ned[0] - 0.5).abs() < 1e-6 && (s.pos_ned[1] - 0.25).abs() < 1e-6, "{:?}", s.pos_ned);
        assert!(s.pos_ned[2] < 0.0, "the centre is above the floor: z down is negative, {:?}", s.pos_ned);
        // At rest on the floor: the accelerometer reads −g along body z (FRD), heading −30°.
        assert!((s.specific_force_frd[2] + 9.81).abs() < 0.05, "{:?}", s.specific_force_frd);
        let [w, _, _, z] = s.quat_ned_to_body;
        let psi = 2.0 * z.atan2(w);
        assert!((psi + 30f64.to_radians()).abs() < 1e-5, "NED heading {psi}");
        let b = encode_state(&s);
        assert_eq!(u32_at(&b, 0), STATE_MAGIC);
        assert_eq!(f64_at(&b, 20), s.pos_ned[0]);
        assert_eq!(f64_at(&b, 212).to_bits(), s.ir_m.to_bits());
        assert_eq!(u32_at(&b, 221), UPLINKS_NOT_COUNTED, "no uplink counted outside a run");
        // The arena's walls are in range of every sonar.
        assert!(s.sonar_m.iter().all(|v| v.is_finite()), "{:?}", s.sonar_m);
    }

    #[test]
    fn a_bad_rate_and_a_stranger_are_refused_and_a_stall_stops_the_motors() {
        let (world, state) = world();
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let opts = AutopilotOptions {
            listen: Listen::Tcp(addr),
            connect_timeout: Duration::from_secs(10),
            step_timeout: Duration::from_millis(300),
        };
        let client = std::thread::spawn(move || {
            let mut stranger = TcpStream::connect(addr).unwrap();
            stranger.write_all(&hello(9, 0.001)).unwrap();
            let mut c = TcpStream::connect(addr).unwrap();
            c.write_all(&hello(7, 0.001)).unwrap();
            c.write_all(&step(0, [0.6; 4])).unwrap();
            let mut b = [0u8; STATE_LEN];
            c.read_exact(&mut b).unwrap();
            // Stalls past the step timeout: the world drops it, says why and closes.
            std::thread::sleep(Duration::from_millis(800));
            (u64::from_le_bytes(b[4..12].try_into().unwrap()), read_refusal(&mut stranger), read_refusal(&mut c))
        });
        let mut aps = Autopilots::accept_on(listener, &world, &opts).unwrap();
        // One that comes once every copter has its autopilot is told so, not left waiting.
        let mut late = TcpStream::connect(addr).unwrap();
        late.write_all(&hello(7, 0.001)).unwrap();
        let late_told = read_refusal(&mut late);
        assert!(late_told.contains("aircraft 7 came after the run started: its copter already has"), "{late_told}");
        let mut inputs = world.initial_inputs();
        let mut state = state;
        aps.commands(&world, &state, &mut inputs);
        assert_eq!(inputs.commands[0].rotors, Some([0.6; 4]));
        sim_core::step(&world, &mut state, &inputs);
        aps.answer(&world, &state);
        aps.commands(&world, &state, &mut inputs);
        assert_eq!(inputs.commands[0].rotors, Some([0.0; 4]), "a stalled autopilot's motors stop");
        let stats = aps.stats();
        assert_eq!(stats[0].steps, 1);
        assert!(stats[0].left.as_ref().unwrap().1.contains("timeout"), "{:?}", stats[0].left);
        let (answered, stranger_told, staller_told) = client.join().unwrap();
        assert_eq!(answered, 0);
        assert!(stranger_told.contains("aircraft 9 flies no copter of this scene"), "{stranger_told}");
        assert!(staller_told.contains("dropped at step 1: no commands within the step timeout"), "{staller_told}");
        let refused = aps.refused();
        assert_eq!(refused.iter().map(|r| r.ac_id).collect::<Vec<_>>(), [Some(9), Some(7)], "{refused:?}");

        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let client = std::thread::spawn(move || {
            let mut c = TcpStream::connect(addr).unwrap();
            c.write_all(&hello(7, 0.002)).unwrap();
            read_refusal(&mut c)
        });
        let err = Autopilots::accept_on(listener, &world, &opts).unwrap_err().to_string();
        assert!(err.contains("aircraft 7 steps every 2 ms") && err.contains("control_dt_s is 1 ms"), "{err}");
        assert_eq!(client.join().unwrap(), err, "the autopilot is told what the world says");
    }

    /// What an autopilot reads from a world that turned it away: the `refused` record's reason,
    /// then the end of the stream.
    fn read_refusal(c: &mut TcpStream) -> String {
        let mut head = [0u8; 6];
        c.read_exact(&mut head).unwrap();
        assert_eq!(u32_at(&head, 0), REFUSED_MAGIC);
        let mut why = vec![0u8; usize::from(u16::from_le_bytes([head[4], head[5]]))];
        c.read_exact(&mut why).unwrap();
        assert_eq!(c.read(&mut [0u8; 1]).unwrap(), 0, "the world closes after the reason");
        String::from_utf8(why).unwrap()
    }

    /// A client's next state record: its `uplinks` field (v2) or none (v1, 221 bytes).
    fn state_uplinks(c: &mut TcpStream, version: u32, step: u64) -> Option<u32> {
        let mut b = [0u8; STATE_LEN];
        let n = if version == 1 { STATE_LEN_V1 } else { STATE_LEN };
        c.read_exact(&mut b[..n]).unwrap();
        assert_eq!(u32_at(&b, 0), STATE_MAGIC);
        assert_eq!(u64::from_le_bytes(b[4..12].try_into().unwrap()), step);
        (version != 1).then(|| u32_at(&b, STATE_LEN_V1))
    }

    #[test]
    fn the_uplink_is_counted_from_its_start_and_a_v1_client_is_flown_uncounted() {
        let (world, mut state) = world_of(
            r#"[[copter]]
name = "new"
kind = "autopilot"
ac_id = 7
start = { pos_m = [0.5, 0.0, 0.0] }
[[copter]]
name = "old"
kind = "autopilot"
ac_id = 8
start = { pos_m = [-0.5, 0.0, 0.0] }
"#,
        );
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap();
        let opts = AutopilotOptions {
            listen: Listen::Tcp(addr),
            connect_timeout: Duration::from_secs(10),
            ..Default::default()
        };
        let (tx, rx) = std::sync::mpsc::channel::<()>();
        let client = std::thread::spawn(move || {
            let mut new = TcpStream::connect(addr).unwrap();
            new.write_all(&hello(7, 0.001)).unwrap();
            let mut old = TcpStream::connect(addr).unwrap();
            old.write_all(&hello_v(8, 0.001, 1)).unwrap();
            let mut seen = Vec::new();
            for k in 0..4 {
                rx.recv().unwrap();
                new.write_all(&step(k, [0.0; 4])).unwrap();
                old.write_all(&step(k, [0.0; 4])).unwrap();
                seen.push((state_uplinks(&mut new, 2, k), state_uplinks(&mut old, 1, k)));
            }
            seen
        });
        let mut aps = Autopilots::accept_on(listener, &world, &opts).unwrap();
        // As count_uplinks does, without an Ivy bus: link has heard aircraft 7 already.
        assert_eq!(aps.start_counting(|_| true), [7]);
        let heard = Arc::new(Mutex::new(BTreeSet::from([7u8])));
        aps.link = Some(LinkWatch { ivy: None, heard, binds: BTreeMap::new() });
        assert!(aps.counts_uplinks());
        let mut inputs = world.initial_inputs();
        let mut sent = Vec::new();
        for t in [0.1, UPLINK_START_S, 0.6, 0.7] {
            tx.send(()).unwrap();
            aps.commands(&world, &state, &mut inputs);
            sim_core::step(&world, &mut state, &inputs);
            aps.answer(&world, &state);
            // The outbox's uplinks after this step: one each.
            let text = "dl SONAR_UPLINK 7 255 100 765 765 765";
            sent.push((aps.uplink(7, text, t), aps.uplink(8, text, t), aps.uplink(99, text, t)));
        }
        let seen = client.join().unwrap();
        // Before its start the counted uplink is not sent; from then on each is counted and the
        // next state names it. The v1 client's is sent, uncounted, and its records are v1's; an
        // aircraft no autopilot flies (a twin) is none of the world's business here.
        assert_eq!(sent, [(false, true, true), (true, true, true), (true, true, true), (true, true, true)]);
        assert_eq!(seen.iter().map(|s| s.0).collect::<Vec<_>>(), [Some(0), Some(0), Some(1), Some(2)]);
        assert!(seen.iter().all(|s| s.1.is_none()), "{seen:?}");
        let stats = aps.stats();
        assert_eq!((stats[0].uplink.as_str(), stats[0].uplinks_counted, stats[0].protocol), ("counted", 3, 2));
        assert!(stats[1].uplink.contains("protocol v1") && stats[1].uplinks_counted == 0, "{:?}", stats[1]);
    }

    #[test]
    fn an_autopilot_flies_over_a_unix_socket_which_goes_with_the_run() {
        let (world, mut state) = world();
        let dir = std::env::temp_dir().join(format!("tw-ap-test.{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("fdm.sock");
        let opts = AutopilotOptions {
            listen: format!("unix:{}", path.display()).parse().unwrap(),
            connect_timeout: Duration::from_secs(10),
            ..Default::default()
        };
        let at = path.clone();
        let client = std::thread::spawn(move || {
            let mut c = loop {
                match std::os::unix::net::UnixStream::connect(&at) {
                    Ok(c) => break c,
                    Err(_) => std::thread::sleep(Duration::from_millis(5)),
                }
            };
            c.write_all(&hello(7, 0.001)).unwrap();
            let mut got = Vec::new();
            for k in 0..3 {
                c.write_all(&step(k, [0.6; 4])).unwrap();
                let mut b = [0u8; STATE_LEN];
                c.read_exact(&mut b).unwrap();
                got.push((u32_at(&b, 0), u64::from_le_bytes(b[4..12].try_into().unwrap())));
            }
            // The world's end closes the connection.
            (got, c.read(&mut [0u8; 1]).unwrap())
        });
        let mut told = String::new();
        let mut aps = Autopilots::accept_with(&world, &opts, |a| told = a.to_owned()).unwrap();
        assert_eq!(told, format!("unix:{}", path.display()));
        assert_eq!(aps.listening_on(), told);
        let mut inputs = world.initial_inputs();
        for _ in 0..3 {
            aps.commands(&world, &state, &mut inputs);
            assert_eq!(inputs.commands[0].rotors, Some([0.6; 4]));
            sim_core::step(&world, &mut state, &inputs);
            aps.answer(&world, &state);
        }
        assert_eq!(aps.stats()[0].steps, 3);
        assert!(aps.stats()[0].peer.starts_with("unix:"), "{:?}", aps.stats()[0].peer);
        drop(aps);
        let (got, end) = client.join().unwrap();
        assert_eq!(got, [(STATE_MAGIC, 0), (STATE_MAGIC, 1), (STATE_MAGIC, 2)]);
        assert_eq!(end, 0);
        assert!(!path.exists(), "the socket file goes with the run");
        std::fs::remove_dir(&dir).unwrap();
        // Bad input is named, with where.
        let err = Autopilots::accept(
            &world,
            &AutopilotOptions {
                listen: Listen::Unix(Some(dir.join("no such folder").join("fdm.sock"))),
                ..Default::default()
            },
        )
        .unwrap_err();
        let why = std::error::Error::source(&err).map(|e| e.to_string()).unwrap_or_default();
        let err = err.to_string();
        assert!(err.starts_with("cannot listen for autopilots on unix:") && err.contains("no such folder"), "{err}");
        assert!(why.contains("No such file or directory"), "{why}");
    }

    #[test]
    fn a_long_reason_is_cut_at_a_character_boundary() {
        let why = "é".repeat(REFUSED_MAX);
        let b = encode_refusal(&why);
        let n = usize::from(u16::from_le_bytes([b[4], b[5]]));
        assert!(n <= REFUSED_MAX && n % 2 == 0 && b.len() == 6 + n, "{n}");
        assert!(std::str::from_utf8(&b[6..]).is_ok());
    }
}
