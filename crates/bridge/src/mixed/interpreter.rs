//! Where a twin's telemetry becomes a command: the [`Interpreter`] turns each telemetry text
//! into a loop request ([`Request::Twin`], or why it drives nothing): decoding, routing by
//! aircraft ([`Router`]), primary and fallback sources, the aircraft's heading offset and level,
//! validation. The gateway runs one under a mutex; an evaluation (`validate`, the sync
//! evaluation) runs one directly, in simulated time. It counts what arrived, what it dropped
//! and which message drove which quantity ([`GatewayReport`]).
//!
//! How a twin follows its real copter ([`crate::paparazzi::convert::twin_command`]):
//! `FINKEN_ACTUATORS_SET_POINT` gives attitude targets and throttle, `FINKEN_IR_ADC` or
//! `FINKEN_SENSOR_MODEL.pos_z` the height to hold. `ATTITUDE` and `ROTORCRAFT_FP` are
//! fallbacks, used only while the primary source of the same quantity has been silent for
//! [`FALLBACK_AFTER_S`]; `ATTITUDE` is also the real attitude the twin's tracking error is
//! measured against. [`TwinAttitude::Measured`] swaps the roles of the set point and
//! `ATTITUDE` for the attitude targets.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

use sim_core::World;
use sim_core::scene::CopterSpec;

use crate::engine::request::{BusInput, Request};
use crate::ids::AcId;
use crate::mixed::router::{Decision, Router};
use crate::mixed::stats::{Sample, Summary};
use crate::paparazzi::convert::twin_command;
use crate::paparazzi::messages::MessageSet;
use crate::paparazzi::pairing::ResolvedPairing;
use crate::wire::CommandMsg;

/// A fallback source drives a twin only after the primary source has been silent this long.
pub const FALLBACK_AFTER_S: f64 = 0.5;

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
/// fallback sources, validation. The [`Gateway`](crate::mixed::gateway::Gateway) runs one
/// under a mutex; an evaluation can run one directly, in simulated time.
#[derive(Debug)]
pub struct Interpreter {
    router: Router,
    pub(super) stats: GatewayStats,
    /// When each aircraft last sent each bound message.
    last_heard: BTreeMap<(AcId, &'static str), Instant>,
    /// Per aircraft: its heading in the arena minus its own heading, rad.
    heading_offset: BTreeMap<AcId, f32>,
    /// Per aircraft: the roll and pitch its AHRS reads level (standing on the floor), rad.
    level: BTreeMap<AcId, [f32; 2]>,
    /// Twin spawns the loop's queue could not take, sent again with the aircraft's next text.
    pub(super) pending_spawn: BTreeMap<AcId, Box<CopterSpec>>,
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
