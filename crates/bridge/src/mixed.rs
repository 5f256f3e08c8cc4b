//! Mixed reality: real copters' telemetry drives their twins, twins' virtual sonar goes back,
//! and virtual copters publish telemetry as if they were aircraft.
//!
//! Two halves, one per thread:
//!
//! - [`Outbox`] runs inside the step loop (it needs the state): after each step it produces
//!   the Paparazzi texts to send, on the **simulated** clock: `VIRTUAL_SONAR` for every twin
//!   (at the sonar rate, or a configured period), and each virtual copter's telemetry at the
//!   periods of its [`TelemetryPlan`]. Periods shorter than the control step give one message
//!   per control step (the values change only that often).
//! - [`Gateway`] lives on the tokio side: it binds the FINken telemetry on the Ivy-style bus
//!   ([`crate::zenoh_net::pprz_bus::ZenohBus`]), routes each message by aircraft id ([`Router`]), and sends the
//!   loop [`Request::Twin`]s (commands, observed attitude, automatic spawns). It records
//!   inter-arrival times per aircraft and message.
//!
//! How a twin follows its real copter ([`crate::paparazzi::convert::twin_command`]):
//! `FINKEN_ACTUATORS_SET_POINT` gives attitude targets and throttle, `FINKEN_IR_ADC` or
//! `FINKEN_SENSOR_MODEL.pos_z` the height to hold. `ATTITUDE` and `ROTORCRAFT_FP` are
//! fallbacks, used only while the primary source of the same quantity has been silent for
//! [`FALLBACK_AFTER_S`]; `ATTITUDE` is also the real attitude the twin's tracking error is
//! measured against. [`TwinAttitude::Measured`] swaps the roles of the set point and
//! `ATTITUDE` for the attitude targets.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use sim_core::mixed::VirtualSonar;
use sim_core::scene::{CommandSpec, CopterSpec, StartSpec};
use sim_core::{CopterKind, FlightMode, SceneSpec, State, World};

use crate::AcId;
use crate::engine::request::{BusInput, Request};
use crate::paparazzi::conf::AircraftKind;
use crate::paparazzi::convert::{TelemetrySource, Uplink, telemetry_text, twin_command, uplink_text};
use crate::paparazzi::ivy::IvyAgent;
use crate::paparazzi::messages::MessageSet;
use crate::paparazzi::pairing::{ResolvedPairing, Route, UnknownAircraftStats};
use crate::paparazzi::telemetry::Telemetry;
use crate::wire::{CommandMsg, sensors_msg, state_msg};
use crate::zenoh_net::pprz_bus::{ZenohBus, ZenohBusError};

/// The project's telemetry plan (`assets/paparazzi/telemetry.xml`).
pub const TELEMETRY_XML: &str = include_str!("../../../assets/paparazzi/telemetry.xml");

/// A fallback source drives a twin only after the primary source has been silent this long.
pub const FALLBACK_AFTER_S: f64 = 0.5;

/// Which messages a copter sends, and how often: one mode of a telemetry file.
#[derive(Clone, Debug, PartialEq)]
pub struct TelemetryPlan {
    /// `<process>/<mode>` it came from.
    pub label: String,
    /// Message names and periods, s, in file order.
    pub periods: Vec<(String, f64)>,
}

impl TelemetryPlan {
    /// Mode `mode` (default: the first) of process `process` (default: the first).
    pub fn from_telemetry(t: &Telemetry, process: Option<&str>, mode: Option<&str>) -> Result<Self, String> {
        let p = match process {
            Some(name) => t.process(name).ok_or_else(|| format!("{}: no process `{name}`", t.source))?,
            None => t.processes.first().ok_or_else(|| format!("{}: no process", t.source))?,
        };
        let m = match mode {
            Some(name) => {
                p.mode(name).ok_or_else(|| format!("{}: process `{}` has no mode `{name}`", t.source, p.name))?
            }
            None => p.modes.first().ok_or_else(|| format!("{}: process `{}` has no mode", t.source, p.name))?,
        };
        Ok(Self {
            label: format!("{}/{}", p.name, m.name),
            periods: m.messages.iter().map(|msg| (msg.name.clone(), msg.period_s)).collect(),
        })
    }

    /// The embedded plan ([`TELEMETRY_XML`], first mode: `Main/mixed`).
    pub fn project_default() -> Self {
        let parsed = Telemetry::parse(TELEMETRY_XML, "assets/paparazzi/telemetry.xml")
            .map(|t| Self::from_telemetry(&t, None, None))
            .map_err(|e| e.to_string());
        match parsed {
            Ok(Ok(plan)) => plan,
            // Checked by a test; reaching this is a build defect.
            Ok(Err(e)) | Err(e) => panic!("the embedded telemetry.xml is invalid: {e}"),
        }
    }

    /// The period of `name`, if the plan sends it.
    pub fn period_s(&self, name: &str) -> Option<f64> {
        self.periods.iter().find(|(n, _)| n == name).map(|(_, p)| *p)
    }
}

/// Adds the pairing's copters to a scene before it is compiled: each twin and virtual copter
/// that the scene does not have is appended at its pairing pose (twins in `manual` mode on
/// the floor, waiting for telemetry; virtual copters in `wall_avoid` at 0.8 m). A scene copter
/// the pairing names gets the pairing's kind and `ac_id`; an `ac_id` used by another scene
/// copter is an error.
pub fn apply_pairing(spec: &mut SceneSpec, pairing: &ResolvedPairing) -> Result<(), String> {
    for a in pairing.by_ac_id.values() {
        let kind = match a.kind {
            AircraftKind::Real if a.autopilot => CopterKind::Autopilot,
            AircraftKind::Real => CopterKind::Real,
            AircraftKind::Virtual => CopterKind::Virtual,
        };
        if let Some(other) = spec.copters.iter().find(|c| c.ac_id == Some(a.ac_id) && c.name != a.copter) {
            return Err(format!(
                "the pairing gives ac_id {} to `{}`, but scene copter `{}` already has it",
                a.ac_id, a.copter, other.name
            ));
        }
        match spec.copters.iter_mut().find(|c| c.name == a.copter) {
            Some(c) => {
                c.kind = kind;
                c.ac_id = Some(a.ac_id);
            }
            None => spec.copters.push(paired_copter(&a.copter, kind, a.ac_id, &a.pose)),
        }
    }
    Ok(())
}

/// The scene table of a copter the bridge adds (pairing, or automatic spawn).
pub fn paired_copter(name: &str, kind: CopterKind, ac_id: AcId, pose: &crate::paparazzi::pairing::Pose) -> CopterSpec {
    let (mode, command) = match kind {
        CopterKind::Real => (FlightMode::Manual, CommandSpec::default()),
        CopterKind::Autopilot => (FlightMode::Rotors, CommandSpec::default()),
        CopterKind::Virtual => (FlightMode::WallAvoid, CommandSpec { height_m: 0.8, ..CommandSpec::default() }),
    };
    CopterSpec {
        name: name.to_owned(),
        kind,
        ac_id: Some(ac_id),
        airframe: Default::default(),
        start: StartSpec {
            pos_m: [pose.x_m as f32, pose.y_m as f32],
            z_m: (pose.z_m > 0.0).then_some(pose.z_m as f32),
            yaw_deg: pose.yaw_rad.to_degrees() as f32,
        },
        mode,
        command,
    }
}

/// How the loop side sends Paparazzi messages.
#[derive(Clone, Debug)]
pub struct OutboxOptions {
    /// Key-expression prefix.
    pub prefix: String,
    /// Message definitions (the project's `messages.xml`).
    pub messages: Arc<MessageSet>,
    /// What virtual copters send.
    pub plan: TelemetryPlan,
    /// Period of the virtual-sonar uplink per twin, s; 0: at every sonar update.
    pub virtual_sonar_period_s: f64,
    /// Per aircraft, the uplink its firmware understands, where it is not the one `messages`
    /// defines ([`Uplink::defined_by`]).
    pub uplinks: BTreeMap<AcId, Uplink>,
}

impl OutboxOptions {
    /// The uplink aircraft `ac_id`'s twin sends: its own setting, else the one `messages`
    /// defines. An uplink `messages` does not define is never sent (it could not be encoded,
    /// and Paparazzi's `link` would drop it).
    pub fn uplink_for(&self, ac_id: AcId) -> Uplink {
        let defined = |u: Uplink| u.message().is_some_and(|m| self.messages.by_class_and_name("datalink", m).is_some());
        match self.uplinks.get(&ac_id) {
            Some(&u) if u == Uplink::None || defined(u) => u,
            Some(_) => Uplink::None,
            None => Uplink::defined_by(&self.messages),
        }
    }

    /// One line per twin (or copter flown by an outside autopilot) of `world` for the start of
    /// a run: the uplink it gets, or that it gets none and why.
    pub fn uplink_lines(&self, world: &World) -> Vec<String> {
        world
            .copters
            .iter()
            .filter(|c| c.kind.is_real_layer())
            .filter_map(|c| {
                let ac = c.ac_id?;
                Some(match (self.uplink_for(ac), self.uplinks.get(&ac)) {
                    (Uplink::None, Some(Uplink::None)) => {
                        format!("{} (aircraft {ac}): no virtual-sonar uplink (set so)", c.name)
                    }
                    (Uplink::None, Some(u)) => format!(
                        "{} (aircraft {ac}): no virtual-sonar uplink: {} is not a datalink message of {}",
                        c.name,
                        u.message().unwrap_or("-"),
                        self.messages.source
                    ),
                    (Uplink::None, None) => format!(
                        "{} (aircraft {ac}): no virtual-sonar uplink: {} defines neither SONAR_UPLINK nor VIRTUAL_SONAR",
                        c.name, self.messages.source
                    ),
                    (u, _) => format!(
                        "{} (aircraft {ac}): virtual sonar as {} from `{}`",
                        c.name,
                        u.message().unwrap_or("-"),
                        u.sender()
                    ),
                })
            })
            .collect()
    }
}

/// A Paparazzi text to publish.
#[derive(Clone, Debug, PartialEq)]
pub struct PprzOut {
    /// Its key (`<prefix>/pprz/<sender>/<NAME>`).
    pub key: String,
    /// The Ivy text.
    pub text: String,
}

/// The loop side of mixed reality (see the module docs).
#[derive(Debug)]
pub struct Outbox {
    opts: OutboxOptions,
    /// Per copter: next due time of each plan message (virtual copters) or of
    /// `VIRTUAL_SONAR` (twins), s.
    due: Vec<Vec<f64>>,
    virtual_sonar: VirtualSonar,
    /// Messages whose encoding failed, by name (reported once each).
    failed: BTreeMap<String, u64>,
    /// Plan messages the simulator cannot produce (reported once each).
    unsupported: Vec<String>,
}

impl Outbox {
    /// An outbox for `world`.
    pub fn new(opts: OutboxOptions) -> Self {
        let unsupported: Vec<String> = opts
            .plan
            .periods
            .iter()
            .filter(|(n, _)| !crate::paparazzi::convert::TELEMETRY_MESSAGES.contains(&n.as_str()))
            .map(|(n, _)| n.clone())
            .collect();
        if !unsupported.is_empty() {
            tracing::warn!(
                "telemetry plan {}: virtual copters cannot send {} (not modelled)",
                opts.plan.label,
                unsupported.join(", ")
            );
        }
        Self { opts, due: Vec::new(), virtual_sonar: VirtualSonar::default(), failed: BTreeMap::new(), unsupported }
    }

    /// Encoding failures by message name.
    pub fn failures(&self) -> &BTreeMap<String, u64> {
        &self.failed
    }

    /// Appends what is due after the step that led to `state` to `out`. `sonar_updated`:
    /// whether this step sampled the sonars.
    pub fn after_step(
        &mut self,
        world: &World,
        state: &State,
        inputs: &sim_core::Inputs,
        sonar_updated: bool,
        out: &mut Vec<PprzOut>,
    ) {
        let t = state.time_s(world);
        let n = world.copters.len();
        while self.due.len() < n {
            let i = self.due.len();
            let slots = match world.copters[i].kind {
                CopterKind::Real | CopterKind::Autopilot => 1,
                CopterKind::Virtual => self.opts.plan.periods.len(),
            };
            self.due.push(vec![t; slots]);
        }
        let dt = world.params.control_dt_s;
        // Fires at most once per step, and keeps the schedule on its grid.
        let fire = |due: &mut f64, period: f64| -> bool {
            if t + 1e-9 < *due {
                return false;
            }
            let period = period.max(1e-6);
            while *due <= t + 1e-9 {
                *due += period;
            }
            true
        };
        let mut prepared = false;
        for i in 0..n {
            let def = &world.copters[i];
            let Some(ac_id) = def.ac_id else { continue };
            match def.kind {
                // A real copter and one flown by an outside autopilot get the virtual sonar;
                // the latter's telemetry is its autopilot's own.
                CopterKind::Real | CopterKind::Autopilot => {
                    if !sonar_updated {
                        continue;
                    }
                    let period = self.opts.virtual_sonar_period_s.max(dt * 0.5);
                    if !fire(&mut self.due[i][0], period) {
                        continue;
                    }
                    if !prepared {
                        self.virtual_sonar.prepare(world, state);
                        prepared = true;
                    }
                    let uplink = self.opts.uplink_for(ac_id);
                    let Some(name) = uplink.message() else { continue };
                    let readings = self.virtual_sonar.readings(world, state, i);
                    match uplink_text(&self.opts.messages, uplink, ac_id, readings) {
                        Ok(Some(text)) => out.push(PprzOut { key: self.key(uplink.sender(), name), text }),
                        Ok(None) => {}
                        Err(e) => self.fail(name, &e.to_string()),
                    }
                }
                CopterKind::Virtual => {
                    let mut src = None;
                    for k in 0..self.opts.plan.periods.len() {
                        let (name, period) = &self.opts.plan.periods[k];
                        if self.unsupported.contains(name) || !fire(&mut self.due[i][k], *period) {
                            continue;
                        }
                        let (st, se) = src
                            .get_or_insert_with(|| (state_msg(world, state, inputs, i), sensors_msg(world, state, i)));
                        let source = TelemetrySource { state: st, sensors: se, setpoint: state.copters[i].setpoint };
                        match telemetry_text(&self.opts.messages, ac_id, name, &source) {
                            Some(Ok(text)) => out.push(PprzOut { key: self.key(&ac_id.to_string(), name), text }),
                            Some(Err(e)) => {
                                let name = name.clone();
                                self.fail(&name, &e.to_string());
                            }
                            None => {}
                        }
                    }
                }
            }
        }
    }

    fn key(&self, sender: &str, name: &str) -> String {
        format!("{}/pprz/{sender}/{name}", self.opts.prefix)
    }

    fn fail(&mut self, name: &str, why: &str) {
        let n = self.failed.entry(name.to_owned()).or_insert(0);
        if *n == 0 {
            tracing::warn!("cannot encode {name}: {why}");
        }
        *n += 1;
    }
}

/// What the gateway does with a telemetry message from an aircraft.
#[derive(Clone, Debug, PartialEq)]
pub enum Decision {
    /// Drive this twin.
    Twin(String),
    /// Spawn this twin first, then drive it.
    SpawnTwin(Box<CopterSpec>),
    /// Drop: one of our own virtual aircraft (someone else is sending as it).
    OwnVirtual,
    /// Drop: the telemetry of an aircraft whose autopilot flies one of our copters (its motion
    /// is the simulation's; the telemetry is for the ground station).
    Autopilot,
    /// Drop: not ours and not to be spawned.
    Unknown,
}

/// Routes aircraft ids to copters: the world's copters with an `ac_id`, then the pairing's
/// rules for the rest (see [`crate::paparazzi::pairing`]). Spawn decisions are remembered, so an aircraft
/// spawns once.
#[derive(Clone, Debug)]
pub struct Router {
    by_ac_id: BTreeMap<AcId, (String, CopterKind)>,
    pairing: Option<ResolvedPairing>,
    spawned: u32,
    /// Dropped messages of unknown aircraft.
    pub unknown: UnknownAircraftStats,
    /// Dropped messages claiming to come from one of our virtual aircraft.
    pub own_virtual_dropped: u64,
}

impl Router {
    /// A router for `world`'s copters and the optional pairing.
    pub fn new(world: &World, pairing: Option<ResolvedPairing>) -> Self {
        let by_ac_id = world.copters.iter().filter_map(|c| Some((c.ac_id?, (c.name.clone(), c.kind)))).collect();
        Self { by_ac_id, pairing, spawned: 0, unknown: UnknownAircraftStats::default(), own_virtual_dropped: 0 }
    }

    /// What to do with a message from `ac_id`.
    pub fn route(&mut self, ac_id: AcId) -> Decision {
        match self.by_ac_id.get(&ac_id) {
            Some((name, CopterKind::Real)) => return Decision::Twin(name.clone()),
            Some((_, CopterKind::Virtual)) => {
                self.own_virtual_dropped += 1;
                return Decision::OwnVirtual;
            }
            Some((_, CopterKind::Autopilot)) => return Decision::Autopilot,
            None => {}
        }
        let route = self.pairing.as_ref().map_or(Route::Ignore, |p| p.route(ac_id));
        let spawn = match route {
            Route::Spawn { point, aircraft } => {
                let name = aircraft.map_or_else(|| format!("ac_{ac_id}"), sanitise);
                Some((name, point.pose_for(self.spawned)))
            }
            // Assigned ids are in the world (the pairing was applied to the scene).
            Route::Assigned(_) | Route::Ignore => None,
        };
        match spawn {
            Some((name, pose)) => {
                self.spawned += 1;
                self.by_ac_id.insert(ac_id, (name.clone(), CopterKind::Real));
                Decision::SpawnTwin(Box::new(paired_copter(&name, CopterKind::Real, ac_id, &pose)))
            }
            None => {
                self.unknown.record(ac_id);
                Decision::Unknown
            }
        }
    }
}

/// A copter name from an aircraft name: lower case, characters outside `[a-z0-9_-]` as `_`.
fn sanitise(name: &str) -> String {
    name.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' { c.to_ascii_lowercase() } else { '_' }).collect()
}

/// Inter-arrival times of one message kind from one aircraft.
#[derive(Clone, Debug, Default)]
pub struct Arrivals {
    last: Option<Instant>,
    /// Inter-arrival times, ms.
    pub gaps_ms: Sample,
    /// Messages received.
    pub count: u64,
}

impl Arrivals {
    fn record(&mut self, now: Instant) {
        if let Some(last) = self.last {
            self.gaps_ms.push((now - last).as_secs_f32() * 1e3);
        }
        self.last = Some(now);
        self.count += 1;
    }
}

/// A stream of values in constant memory: the exact count, mean and maximum, and a uniform
/// random sample of [`Sample::CAPACITY`] values for the percentiles (reservoir sampling,
/// Vitter's algorithm R, on a fixed-seed generator: the same stream gives the same sample).
/// Statistics of a flood or of a day-long run cost the same few kilobytes.
#[derive(Clone, Debug, Default)]
pub struct Sample {
    values: Vec<f32>,
    seen: u64,
    sum: f64,
    max: f32,
    rng: u64,
}

impl Sample {
    /// Values kept for the percentiles.
    pub const CAPACITY: usize = 4096;

    /// Adds a value (non-finite ones are ignored).
    pub fn push(&mut self, v: f32) {
        if !v.is_finite() {
            return;
        }
        if self.seen == 0 {
            self.values.reserve_exact(Self::CAPACITY);
            self.max = v;
        }
        self.seen += 1;
        self.sum += f64::from(v);
        self.max = self.max.max(v);
        if self.values.len() < Self::CAPACITY {
            self.values.push(v);
        } else {
            // xorshift64*: a cheap, fixed-seed stream.
            self.rng = if self.rng == 0 { 0x9E37_79B9_7F4A_7C15 } else { self.rng };
            self.rng ^= self.rng >> 12;
            self.rng ^= self.rng << 25;
            self.rng ^= self.rng >> 27;
            let j = self.rng.wrapping_mul(0x2545_F491_4F6C_DD1D) % self.seen;
            if let Some(slot) = self.values.get_mut(j as usize) {
                *slot = v;
            }
        }
    }

    /// Count, exact mean and maximum; median and 99th percentile of the sample.
    pub fn summary(&self) -> Summary {
        if self.seen == 0 {
            return Summary::default();
        }
        let mut s = Summary::of(&self.values);
        (s.n, s.mean, s.max) = (self.seen as usize, self.sum / self.seen as f64, f64::from(self.max));
        s
    }
}

/// What the gateway saw.
#[derive(Debug, Default)]
pub struct GatewayStats {
    /// Arrivals by (aircraft id, message name).
    pub arrivals: BTreeMap<(AcId, String), Arrivals>,
    /// Texts that did not decode.
    pub decode_errors: u64,
    /// Commands derived from telemetry that were out of range.
    pub rejected: u64,
    /// Requests the loop's queue could not take.
    pub queue_full: u64,
    /// Twins spawned on first telemetry.
    pub spawned: Vec<String>,
    /// Texts logged but not used, by reason (an aircraft that is not ours, one of our virtual
    /// aircraft sent by someone else, a sender that is not an aircraft).
    pub ignored: BTreeMap<&'static str, u64>,
    /// Per aircraft: which messages drove which quantity of its twin, and how often.
    pub sources: BTreeMap<AcId, BTreeMap<Quantity, BTreeMap<String, u64>>>,
}

/// Turns telemetry texts into loop requests: decoding, routing by aircraft, primary and
/// fallback sources, validation. The [`Gateway`] runs one under a mutex; an evaluation can run
/// one directly, in simulated time.
#[derive(Debug)]
pub struct Interpreter {
    router: Router,
    stats: GatewayStats,
    /// When each aircraft last sent each bound message.
    last_heard: BTreeMap<(AcId, &'static str), Instant>,
    /// Per aircraft: its heading in the arena minus its own heading, rad.
    heading_offset: BTreeMap<AcId, f32>,
    /// Per aircraft: the roll and pitch its AHRS reads level (standing on the floor), rad.
    level: BTreeMap<AcId, [f32; 2]>,
    /// Twin spawns the loop's queue could not take, sent again with the aircraft's next text.
    pending_spawn: BTreeMap<AcId, Box<CopterSpec>>,
    world: Arc<World>,
    attitude: TwinAttitude,
}

/// Which telemetry sets a twin's attitude targets.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TwinAttitude {
    /// `FINKEN_ACTUATORS_SET_POINT`: what the real copter's outer loop asks for (the original
    /// system's choice). A real copter's own attitude-control error is not reproduced.
    #[default]
    Setpoint,
    /// `ATTITUDE`: what the real copter's AHRS measures. Reproduces its actual tilt, and so
    /// its drift, at the cost of its AHRS noise. `FINKEN_ACTUATORS_SET_POINT` still gives the
    /// throttle, and its attitude is the fallback.
    Measured,
}

/// Why the gateway could not bind.
#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    /// On Zenoh.
    #[error(transparent)]
    Zenoh(#[from] ZenohBusError),
    /// On Ivy.
    #[error(transparent)]
    Ivy(#[from] crate::paparazzi::ivy::IvyError),
}

/// The telemetry the gateway binds, with the regex it binds it with.
pub const BOUND_TELEMETRY: [&str; 7] = [
    "FINKEN_ACTUATORS_SET_POINT",
    "FINKEN_IR_ADC",
    "FINKEN_SENSOR_MODEL",
    "ATTITUDE",
    "AHRS_EULER_INT",
    "ROTORCRAFT_FP",
    "SONAR_ARRAY",
];

/// What a twin takes from its real copter's telemetry, each from one source at a time.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Quantity {
    /// Roll, pitch and yaw targets.
    Attitude,
    /// The height to hold.
    Height,
    /// The throttle (used only while no height is held).
    Throttle,
    /// The real copter's own sonar readings (for synchronisation).
    Sonar,
}

impl Quantity {
    const ALL: [Quantity; 3] = [Quantity::Attitude, Quantity::Height, Quantity::Throttle];

    /// Its name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Quantity::Attitude => "attitude",
            Quantity::Height => "height",
            Quantity::Throttle => "throttle",
            Quantity::Sonar => "sonar",
        }
    }

    /// The messages that can give this quantity, best first: a message drives it only while
    /// every better one has been silent for [`FALLBACK_AFTER_S`]. A twin so follows whichever
    /// subset its aircraft's telemetry mode sends.
    pub fn ranking(self, attitude: TwinAttitude) -> &'static [&'static str] {
        match (self, attitude) {
            (Quantity::Attitude, TwinAttitude::Setpoint) => {
                &["FINKEN_ACTUATORS_SET_POINT", "ATTITUDE", "AHRS_EULER_INT", "FINKEN_SENSOR_MODEL", "ROTORCRAFT_FP"]
            }
            (Quantity::Attitude, TwinAttitude::Measured) => {
                &["ATTITUDE", "AHRS_EULER_INT", "FINKEN_SENSOR_MODEL", "FINKEN_ACTUATORS_SET_POINT", "ROTORCRAFT_FP"]
            }
            (Quantity::Height, _) => &["FINKEN_IR_ADC", "FINKEN_SENSOR_MODEL", "ROTORCRAFT_FP"],
            (Quantity::Throttle, _) => &["FINKEN_ACTUATORS_SET_POINT", "ROTORCRAFT_FP"],
            (Quantity::Sonar, _) => &["SONAR_ARRAY", "FINKEN_SENSOR_MODEL"],
        }
    }

    fn carried_by(self, c: &CommandMsg) -> bool {
        match self {
            Quantity::Attitude => c.roll.is_some() || c.pitch.is_some() || c.yaw.is_some(),
            Quantity::Height => c.height.is_some(),
            Quantity::Throttle => c.throttle.is_some(),
            Quantity::Sonar => false,
        }
    }

    fn clear(self, c: &mut CommandMsg) {
        match self {
            Quantity::Attitude => (c.roll, c.pitch, c.yaw) = (None, None, None),
            Quantity::Height => c.height = None,
            Quantity::Throttle => c.throttle = None,
            Quantity::Sonar => {}
        }
    }
}

/// Where Paparazzi texts travel: Zenoh (`<prefix>/pprz/<sender>/<NAME>`), a real Ivy bus, or
/// both, in which case the gateway also bridges every text between them.
#[derive(Clone, Debug, Default)]
pub struct PprzLinks {
    /// A Zenoh session and the key prefix.
    pub zenoh: Option<(zenoh::Session, String)>,
    /// An agent on a real Ivy bus.
    pub ivy: Option<Arc<IvyAgent>>,
}

/// Texts bridged between Zenoh and Ivy.
#[derive(Debug, Default)]
pub struct BridgeCounters {
    /// Texts from Ivy peers published on Zenoh.
    pub ivy_to_zenoh: AtomicU64,
    /// Texts from Zenoh sent to Ivy peers.
    pub zenoh_to_ivy: AtomicU64,
    /// Texts not bridged, by reason.
    pub dropped_queue_full: AtomicU64,
    /// Texts Ivy cannot carry (newline or separator).
    pub dropped_unsendable: AtomicU64,
    /// Ivy texts Zenoh refused to publish (the session closing).
    pub dropped_put_failed: AtomicU64,
}

/// The tokio side of mixed reality (see the module docs).
pub struct Gateway {
    zenoh: Option<ZenohBus>,
    ivy: Option<Arc<IvyAgent>>,
    shared: Arc<Mutex<Interpreter>>,
    bridged: Arc<BridgeCounters>,
    _forwarder: Option<tokio::task::JoinHandle<()>>,
}

impl std::fmt::Debug for Gateway {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Gateway").field("zenoh", &self.zenoh).field("ivy", &self.ivy).finish_non_exhaustive()
    }
}

/// A handler that interprets telemetry texts into loop requests.
fn telemetry_handler(
    shared: &Arc<Mutex<Interpreter>>,
    messages: &Arc<MessageSet>,
    requests: &SyncSender<Request>,
) -> impl FnMut(&crate::paparazzi::bus::Delivery<'_>, &mut crate::paparazzi::bus::Control) + Send + 'static {
    let (shared, messages, requests) = (shared.clone(), messages.clone(), requests.clone());
    move |d, _| {
        let received = Instant::now();
        let origin =
            BusInput { key: d.key.to_owned(), text: d.text.to_owned(), received_unix_ns: crate::log::now_unix_ns() };
        let mut sh = crate::lock(&shared);
        let request = sh.interpret(&messages, origin, received);
        if let Err(TrySendError::Full(r) | TrySendError::Disconnected(r)) = requests.try_send(request) {
            sh.stats.queue_full += 1;
            // A lost spawn would leave the aircraft routed to a twin that never exists: the
            // next text of the aircraft carries it again.
            if let Request::Twin { spawn: Some(spec), .. } = r {
                sh.pending_spawn.insert(spec.ac_id.unwrap_or(0), spec);
            }
            if sh.stats.queue_full.is_power_of_two() {
                tracing::warn!("{} telemetry texts dropped so far: the step loop's queue is full", sh.stats.queue_full);
            }
        }
    }
}

/// What the gateway binds to bridge every text: a sender and a name.
const ANY_TEXT: &str = r"^\S+ \S+";

impl Gateway {
    /// Binds the FINken telemetry on every link; requests go to the loop. With both links,
    /// every text is also bridged between them. No text loops: Zenoh subscribers take remote
    /// samples only and Ivy peers never receive their own texts, so a bridged text is never
    /// bridged back.
    pub async fn start(
        links: PprzLinks,
        world: Arc<World>,
        pairing: Option<ResolvedPairing>,
        messages: Arc<MessageSet>,
        requests: SyncSender<Request>,
        attitude: TwinAttitude,
    ) -> Result<Self, GatewayError> {
        let shared = Arc::new(Mutex::new(Interpreter::new(world, pairing, attitude)));
        let bridged = Arc::new(BridgeCounters::default());
        let zenoh = links.zenoh.map(|(session, prefix)| ZenohBus::new(session, prefix));
        for name in BOUND_TELEMETRY {
            let pattern = format!(r"^(\d+) {name} ");
            if let Some(z) = &zenoh {
                z.bind(&pattern, telemetry_handler(&shared, &messages, &requests)).await?;
            }
            if let Some(ivy) = &links.ivy {
                ivy.bind(&pattern, telemetry_handler(&shared, &messages, &requests))?;
            }
        }
        let mut forwarder = None;
        if let (Some(z), Some(ivy)) = (&zenoh, &links.ivy) {
            // Zenoh → Ivy: straight from the subscriber callback (sending never waits).
            let (ivy2, c) = (ivy.clone(), bridged.clone());
            z.bind(ANY_TEXT, move |d, _| match ivy2.send(d.text) {
                Ok(_) => {
                    c.zenoh_to_ivy.fetch_add(1, Ordering::Relaxed);
                }
                Err(_) => {
                    c.dropped_unsendable.fetch_add(1, Ordering::Relaxed);
                }
            })
            .await?;
            // Ivy → Zenoh: through a bounded queue to a publishing task.
            let (tx, mut rx) = tokio::sync::mpsc::channel::<String>(4096);
            let c = bridged.clone();
            ivy.bind(ANY_TEXT, move |d, _| {
                if tx.try_send(d.text.to_owned()).is_err() {
                    c.dropped_queue_full.fetch_add(1, Ordering::Relaxed);
                }
            })?;
            let (session, prefix, c) = (z.session().clone(), z.prefix().to_owned(), bridged.clone());
            forwarder = Some(tokio::spawn(async move {
                while let Some(text) = rx.recv().await {
                    let Ok(key) = crate::zenoh_net::keyexpr::key_for_text(&prefix, &text) else {
                        c.dropped_unsendable.fetch_add(1, Ordering::Relaxed);
                        continue;
                    };
                    match session.put(key, text).await {
                        Ok(()) => c.ivy_to_zenoh.fetch_add(1, Ordering::Relaxed),
                        Err(e) => {
                            tracing::debug!("bridging a text to Zenoh failed: {e}");
                            c.dropped_put_failed.fetch_add(1, Ordering::Relaxed)
                        }
                    };
                }
            }));
        }
        Ok(Self { zenoh, ivy: links.ivy, shared, bridged, _forwarder: forwarder })
    }

    /// Sends the loop's Paparazzi texts on Ivy (Zenoh gets them from the node).
    pub fn send_ivy(&self, out: &[PprzOut]) {
        if let Some(ivy) = &self.ivy {
            for o in out {
                // The agent counts what it cannot send (its drops); the outbox's texts hold
                // no newline or separator.
                let _ = ivy.send(&o.text);
            }
        }
    }

    /// Texts bridged between Zenoh and Ivy.
    pub fn bridged(&self) -> &BridgeCounters {
        &self.bridged
    }

    /// Tells the gateway about the world after a spawn (for command validation).
    pub fn set_world(&self, world: &Arc<World>) {
        crate::lock(&self.shared).set_world(world);
    }

    /// A copy of the statistics so far, and of the router's counters.
    pub fn report(&self) -> GatewayReport {
        crate::lock(&self.shared).report()
    }

    /// The Zenoh bus the gateway uses, if any (for counters).
    pub fn zenoh_bus(&self) -> Option<&ZenohBus> {
        self.zenoh.as_ref()
    }
}

impl Interpreter {
    /// An interpreter for `world`'s copters and the optional pairing.
    pub fn new(world: Arc<World>, pairing: Option<ResolvedPairing>, attitude: TwinAttitude) -> Self {
        Self {
            router: Router::new(&world, pairing),
            stats: GatewayStats::default(),
            last_heard: BTreeMap::new(),
            heading_offset: BTreeMap::new(),
            level: BTreeMap::new(),
            pending_spawn: BTreeMap::new(),
            world,
            attitude,
        }
    }

    /// Aircraft `ac_id`'s heading in the arena minus the heading it reports, rad: added to
    /// every yaw its telemetry gives (a real copter's magnetometer north need not be the
    /// arena's +x).
    pub fn set_heading_offset(&mut self, ac_id: AcId, offset_rad: f32) {
        self.heading_offset.insert(ac_id, offset_rad);
    }

    /// The roll and pitch aircraft `ac_id`'s AHRS reads when it stands level, rad: taken off
    /// every measured attitude it sends. A FINken's body frame sits a few degrees off its
    /// IMU's (the 2015 copter read 5° nose up on the floor); followed as it comes, that offset
    /// flies the twin into a wall within seconds.
    pub fn set_level(&mut self, ac_id: AcId, roll_pitch_rad: [f32; 2]) {
        self.level.insert(ac_id, roll_pitch_rad);
    }

    /// The world after a spawn (for command validation).
    pub fn set_world(&mut self, world: &Arc<World>) {
        if !Arc::ptr_eq(&self.world, world) {
            self.world = world.clone();
        }
    }

    /// A copy of the statistics so far, and of the router's counters.
    pub fn report(&self) -> GatewayReport {
        let sh = self;
        let arrivals = sh
            .stats
            .arrivals
            .iter()
            .map(|((ac, name), a)| ArrivalReport {
                ac_id: *ac,
                message: name.clone(),
                count: a.count,
                gap_ms: a.gaps_ms.summary(),
            })
            .collect();
        GatewayReport {
            arrivals,
            decode_errors: sh.stats.decode_errors,
            rejected: sh.stats.rejected,
            queue_full: sh.stats.queue_full,
            ignored: sh.stats.ignored.iter().map(|(k, v)| ((*k).to_owned(), *v)).collect(),
            spawned: sh.stats.spawned.clone(),
            unknown_dropped: sh.router.unknown.dropped_by_ac_id.clone(),
            own_virtual_dropped: sh.router.own_virtual_dropped,
            sources: sh.stats.sources.clone(),
        }
    }

    /// The request for one telemetry text that arrived at `received`: a twin input, a
    /// rejection (undecodable, out of range), or a text that drives nothing (logged and
    /// counted all the same: every received text reaches the loop and the log).
    pub fn interpret(&mut self, messages: &MessageSet, origin: BusInput, received: Instant) -> Request {
        let sh = self;
        let msg = match messages.decode(&origin.text) {
            Ok(m) => m,
            Err(e) => {
                sh.stats.decode_errors += 1;
                let reason = format!("undecodable telemetry: {e}");
                return Request::Rejected { origin, reason };
            }
        };
        sh.interpret_message(&msg, origin, received)
    }

    /// Whether message `name` from `ac_id` may not give quantity `q` now: it is no source of
    /// it, or a better source spoke within [`FALLBACK_AFTER_S`] of `heard`.
    fn outranked(&self, ac_id: AcId, name: &str, q: Quantity, heard: Instant) -> bool {
        let ranking = q.ranking(self.attitude);
        let Some(rank) = ranking.iter().position(|n| *n == name) else { return true };
        ranking[..rank]
            .iter()
            .any(|n| self.last_heard.get(&(ac_id, *n)).is_some_and(|t| (heard - *t).as_secs_f64() <= FALLBACK_AFTER_S))
    }

    fn ignore(&mut self, origin: BusInput, reason: &'static str) -> Request {
        *self.stats.ignored.entry(reason).or_default() += 1;
        Request::Ignored { origin, reason }
    }

    fn interpret_message(
        &mut self,
        msg: &crate::paparazzi::codec::Message<'_>,
        origin: BusInput,
        received: Instant,
    ) -> Request {
        let sh = self;
        let Some(ac_id) = msg.sender.ac_id() else { return sh.ignore(origin, "not sent by an aircraft") };
        let name = msg.def.name.clone();
        sh.stats.arrivals.entry((ac_id, name.clone())).or_default().record(received);
        let (copter, spawn) = match sh.router.route(ac_id) {
            Decision::Twin(c) => (c, sh.pending_spawn.remove(&ac_id)),
            Decision::SpawnTwin(spec) => {
                sh.stats.spawned.push(spec.name.clone());
                tracing::info!("aircraft {ac_id}: spawning its twin `{}`", spec.name);
                (spec.name.clone(), Some(spec))
            }
            Decision::OwnVirtual => return sh.ignore(origin, "sent as one of our virtual aircraft"),
            Decision::Autopilot => return sh.ignore(origin, "its autopilot flies it in the simulation"),
            Decision::Unknown => return sh.ignore(origin, "aircraft not paired"),
        };
        let heard = received;
        let full = twin_command(msg);
        let mut cmd = full.clone();
        let mut drove = Vec::new();
        if let Some(c) = cmd.as_mut() {
            for q in Quantity::ALL {
                if !q.carried_by(c) {
                    continue;
                }
                if sh.outranked(ac_id, &name, q, heard) {
                    q.clear(c);
                } else {
                    drove.push(q);
                }
            }
        }
        let mut sonar = crate::paparazzi::convert::real_sonar(msg);
        if sonar.is_some() {
            if sh.outranked(ac_id, &name, Quantity::Sonar, heard) { sonar = None } else { drove.push(Quantity::Sonar) }
        }
        if let Some(k) = BOUND_TELEMETRY.iter().find(|n| **n == name) {
            sh.last_heard.insert((ac_id, k), heard);
        }
        let offset = sh.heading_offset.get(&ac_id).copied().unwrap_or(0.0);
        let turn = |y: f32| sim_core::math::wrap_angle_rad(y + offset);
        let measured = matches!(name.as_str(), "ATTITUDE" | "AHRS_EULER_INT" | "FINKEN_SENSOR_MODEL" | "ROTORCRAFT_FP");
        let [level_roll, level_pitch] = sh.level.get(&ac_id).copied().filter(|_| measured).unwrap_or([0.0, 0.0]);
        let observed = full
            .filter(|_| measured && name != "ROTORCRAFT_FP")
            .and_then(|c| Some([c.roll? - level_roll, c.pitch? - level_pitch, c.yaw.map_or(0.0, turn)]));
        let yaw = crate::paparazzi::convert::real_yaw(msg).map(turn);
        if let Some(c) = cmd.as_mut() {
            c.yaw = c.yaw.map(turn);
            c.roll = c.roll.map(|r| r - level_roll);
            c.pitch = c.pitch.map(|p| p - level_pitch);
        }
        for q in drove {
            *sh.stats.sources.entry(ac_id).or_default().entry(q).or_default().entry(name.clone()).or_default() += 1;
        }
        let cmd = cmd.filter(|c| *c != CommandMsg::default());
        if let Some(c) = &cmd
            && let Err(e) = c.validate(&sh.world)
        {
            sh.stats.rejected += 1;
            return Request::Rejected { origin, reason: format!("telemetry gives {e}") };
        }
        // Sent even when it changes nothing (a fallback while the primary speaks): the loop logs
        // every message it receives.
        Request::Twin { copter, spawn, cmd, observed_rpy: observed, sonar_m: sonar, yaw_rad: yaw, origin }
    }
}

/// Order statistics of a sample.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct Summary {
    /// Number of values.
    pub n: usize,
    /// Mean.
    pub mean: f64,
    /// Median.
    pub p50: f64,
    /// 99th percentile.
    pub p99: f64,
    /// Maximum.
    pub max: f64,
}

impl Summary {
    /// Summarises `values` (NaNs ignored).
    pub fn of(values: &[f32]) -> Self {
        let mut v: Vec<f64> = values.iter().map(|&x| f64::from(x)).filter(|x| x.is_finite()).collect();
        if v.is_empty() {
            return Self::default();
        }
        v.sort_by(f64::total_cmp);
        let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        Self {
            n: v.len(),
            mean: v.iter().sum::<f64>() / v.len() as f64,
            p50: q(0.5),
            p99: q(0.99),
            max: v[v.len() - 1],
        }
    }
}

/// Arrivals of one message kind from one aircraft.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ArrivalReport {
    /// Aircraft.
    pub ac_id: AcId,
    /// Message name.
    pub message: String,
    /// Messages received.
    pub count: u64,
    /// Inter-arrival times, ms.
    pub gap_ms: Summary,
}

/// What the gateway reports at the end of a run.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct GatewayReport {
    /// Arrivals per aircraft and message.
    pub arrivals: Vec<ArrivalReport>,
    /// Texts that did not decode.
    pub decode_errors: u64,
    /// Commands derived from telemetry that were out of range.
    pub rejected: u64,
    /// Requests the loop's queue could not take.
    pub queue_full: u64,
    /// Twins spawned on first telemetry.
    pub spawned: Vec<String>,
    /// Dropped messages of unknown aircraft, by id.
    pub unknown_dropped: BTreeMap<AcId, u64>,
    /// Dropped messages claiming to come from one of our virtual aircraft.
    pub own_virtual_dropped: u64,
    /// Texts logged but not used, by reason.
    pub ignored: BTreeMap<String, u64>,
    /// Per aircraft: which messages drove which quantity of its twin, and how often.
    pub sources: BTreeMap<AcId, BTreeMap<Quantity, BTreeMap<String, u64>>>,
}

impl GatewayReport {
    /// One line per aircraft: `attitude ← AHRS_EULER_INT, height ← FINKEN_SENSOR_MODEL, …`
    /// (each quantity's sources, most used first).
    pub fn source_lines(&self) -> Vec<(AcId, String)> {
        self.sources
            .iter()
            .map(|(ac, by_q)| {
                let parts: Vec<String> = by_q
                    .iter()
                    .map(|(q, msgs)| {
                        let mut m: Vec<(&String, &u64)> = msgs.iter().collect();
                        m.sort_by(|a, b| b.1.cmp(a.1).then(a.0.cmp(b.0)));
                        let names: Vec<&str> = m.iter().map(|(n, _)| n.as_str()).collect();
                        format!("{} ← {}", q.name(), names.join(", "))
                    })
                    .collect();
                (*ac, parts.join("; "))
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sample_keeps_exact_count_mean_max_and_fair_percentiles_in_constant_memory() {
        let mut s = Sample::default();
        for k in 0..1_000_000u32 {
            s.push((k % 1000) as f32);
        }
        s.push(f32::NAN);
        let sum = s.summary();
        assert_eq!(sum.n, 1_000_000);
        assert!((sum.mean - 499.5).abs() < 1e-6, "{}", sum.mean);
        assert_eq!(sum.max, 999.0);
        // A uniform sample of 4,096: the median within a few percent of 500.
        assert!((sum.p50 - 500.0).abs() < 30.0, "{}", sum.p50);
        assert!(sum.p99 > 960.0, "{}", sum.p99);
        assert!(s.values.capacity() <= Sample::CAPACITY);
        assert_eq!(Sample::default().summary(), Summary::default());
    }
    use crate::paparazzi::conf::ConfXml;
    use crate::paparazzi::pairing::Pairing;

    #[test]
    fn the_embedded_plan_parses_and_sends_what_drives_a_twin_every_22_ms() {
        let plan = TelemetryPlan::project_default();
        assert_eq!(plan.label, "Main/mixed");
        assert_eq!(plan.period_s("FINKEN_ACTUATORS_SET_POINT"), Some(0.022));
        for (name, _) in &plan.periods {
            assert!(
                crate::paparazzi::convert::TELEMETRY_MESSAGES.contains(&name.as_str()),
                "{name} cannot be produced"
            );
        }
    }

    #[test]
    fn a_virtual_copter_registers_with_the_server_before_it_reports_positions() {
        // Paparazzi's server registers an aircraft on ALIVE and converts ROTORCRAFT_FP into a
        // position only once INS_REF has given the origin: both must precede the first
        // ROTORCRAFT_FP.
        let (_, world) = sim_core::scene::load_default();
        let mut state = world.initial_state();
        let inputs = world.initial_inputs();
        let messages = Arc::new(crate::paparazzi::convert::project_messages());
        let mut outbox = Outbox::new(OutboxOptions {
            prefix: "t".into(),
            messages: messages.clone(),
            plan: TelemetryPlan::project_default(),
            virtual_sonar_period_s: 0.0,
            uplinks: Default::default(),
        });
        let mut out = Vec::new();
        for _ in 0..3 {
            sim_core::step(&world, &mut state, &inputs);
            outbox.after_step(&world, &state, &inputs, true, &mut out);
        }
        let ac = world.copters[0].ac_id.unwrap();
        let names: Vec<&str> = out
            .iter()
            .filter(|o| o.text.starts_with(&format!("{ac} ")))
            .map(|o| o.text.split(' ').nth(1).unwrap())
            .collect();
        let pos = |n: &str| names.iter().position(|x| *x == n).unwrap_or_else(|| panic!("no {n} in {names:?}"));
        assert!(pos("ALIVE") < pos("ROTORCRAFT_FP") && pos("INS_REF") < pos("ROTORCRAFT_FP"), "{names:?}");
        let alive = out.iter().find(|o| o.text.starts_with(&format!("{ac} ALIVE"))).unwrap();
        assert_eq!(alive.text, format!("{ac} ALIVE 0,0,0,0,0,0,0,0,0,0,0,0,0,0,0,0"));
        for o in &out {
            messages.decode(&o.text).unwrap_or_else(|e| panic!("{}: {e}", o.text));
        }
        assert!(outbox.failures().is_empty(), "{:?}", outbox.failures());
    }

    #[test]
    fn known_aircraft_spawn_once_unknown_ones_follow_the_policy() {
        let (_, world) = sim_core::scene::load_default();
        let conf = ConfXml::parse(
            r#"<conf><aircraft name="FINken_01" ac_id="5"/><aircraft name="FINken 03" ac_id="7"/>
               <aircraft name="Virtual_09" ac_id="9"/></conf>"#,
            "c.xml",
        )
        .unwrap();
        let text = r#"<pairing version="1"><conf path="c.xml"/>
            <twin ac_id="5" copter="finken1" x_m="0" y_m="0" z_m="0" yaw_deg="0"/>
            <spawn x_m="0" y_m="0.5" z_m="0" yaw_deg="0" spacing_m="0.5"/></pairing>"#;
        let pairing = Pairing::parse(text, "p.xml").unwrap().resolve(&conf).unwrap();
        let mut r = Router::new(&world, Some(pairing));
        // The scene's virtual copters (201, 202) are ours.
        assert_eq!(r.route(201), Decision::OwnVirtual);
        // 7 is a real aircraft of conf.xml: spawned once, at the spawn point, then driven.
        let Decision::SpawnTwin(spec) = r.route(7) else { panic!("7 should spawn") };
        assert_eq!(spec.name, "finken_03");
        assert_eq!(spec.kind, CopterKind::Real);
        assert_eq!(spec.start.pos_m, [0.0, 0.5]);
        assert_eq!(r.route(7), Decision::Twin("finken_03".into()));
        // 9 is virtual by name but not ours; 42 is not in conf.xml and the policy is ignore.
        assert_eq!(r.route(9), Decision::Unknown);
        assert_eq!(r.route(42), Decision::Unknown);
        assert_eq!(r.route(42), Decision::Unknown);
        assert_eq!(r.unknown.dropped_by_ac_id.get(&42), Some(&2));
    }
}
