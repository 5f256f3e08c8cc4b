//! Turns captured steps, events and the static scene into protobuf messages (sans I/O): each
//! message goes to a sink as `(topic, log_time_ns, bytes)`.
//!
//! The per-step messages are prost structs kept in the [`Encoder`] and refilled in place
//! (their vectors and strings keep their capacity), so encoding a warm step allocates
//! nothing; `/scene/copters` is likewise one `SceneUpdate` built once and updated.

use std::borrow::Cow;

use foxglove::Encode as _;
use foxglove::messages as fg;
use serde::Serialize;
use sim_core::control::FlightMode;
use sim_core::{CopterKind, CrashCause, Event, World};

use super::capture::{CopterSample, StepFrame};
use super::proto;

/// A channel of the log.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Topic {
    /// `/copters/state`.
    State,
    /// `/copters/sensors`.
    Sensors,
    /// `/copters/command`.
    Command,
    /// `/copters/control`.
    Control,
    /// `/events`.
    Events,
    /// `/log`.
    Log,
    /// `/tf`.
    Tf,
    /// `/scene/arena`.
    SceneArena,
    /// `/scene/copters`.
    SceneCopters,
    /// `/bus`.
    Bus,
}

impl Topic {
    /// Every topic, in channel order.
    pub const ALL: [Topic; 10] = [
        Topic::State,
        Topic::Sensors,
        Topic::Command,
        Topic::Control,
        Topic::Events,
        Topic::Log,
        Topic::Tf,
        Topic::SceneArena,
        Topic::SceneCopters,
        Topic::Bus,
    ];

    /// The MCAP topic.
    pub fn name(self) -> &'static str {
        match self {
            Topic::State => "/copters/state",
            Topic::Sensors => "/copters/sensors",
            Topic::Command => "/copters/command",
            Topic::Control => "/copters/control",
            Topic::Events => "/events",
            Topic::Log => "/log",
            Topic::Tf => "/tf",
            Topic::SceneArena => "/scene/arena",
            Topic::SceneCopters => "/scene/copters",
            Topic::Bus => "/bus",
        }
    }

    /// The schema name (see [`schema_data`]).
    pub fn schema(self) -> &'static str {
        match self {
            Topic::State => "twinswarm.CopterState",
            Topic::Sensors => "twinswarm.CopterSensors",
            Topic::Command => "twinswarm.CopterCommand",
            Topic::Control => "twinswarm.CopterControl",
            Topic::Events => "twinswarm.Event",
            Topic::Log => "foxglove.Log",
            Topic::Tf => "foxglove.FrameTransform",
            Topic::SceneArena | Topic::SceneCopters => "foxglove.SceneUpdate",
            Topic::Bus => "twinswarm.BusMessage",
        }
    }

    /// Index into [`Topic::ALL`].
    pub fn index(self) -> usize {
        self as usize
    }
}

/// What kind of event.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum EventKind {
    /// A copter left the floor for the first time.
    TookOff,
    /// A copter crashed.
    Crashed,
    /// A copter was spawned (bridge, later).
    Spawned,
    /// A real copter was paired with its twin (bridge, later).
    Paired,
    /// An input was rejected (bridge, later).
    InputRejected,
    /// A real-time step finished after its deadline.
    StepOverrun,
    /// The run was interrupted (SIGINT/SIGTERM) and the log finished cleanly.
    Interrupted,
    /// A lost link or a controller change (see `bridge::engine::failsafe`).
    Failsafe,
    /// A step's frame was not published (the publisher was behind).
    FrameDropped,
    /// At the end of a run on a bus: what the bus received, refused and dropped.
    BusReport,
    /// Lockstep: a controller did not answer a tick in time; its copter kept its last command.
    LockstepTimeout,
    /// The run went on from a checkpoint (a restart after a lost process): this log begins
    /// with the step after it.
    Resumed,
}

impl EventKind {
    /// `foxglove.Log` level.
    fn level(self) -> fg::log::Level {
        use fg::log::Level;
        match self {
            EventKind::TookOff | EventKind::Spawned | EventKind::Paired | EventKind::BusReport | EventKind::Resumed => {
                Level::Info
            }
            EventKind::InputRejected
            | EventKind::StepOverrun
            | EventKind::Interrupted
            | EventKind::Failsafe
            | EventKind::FrameDropped
            | EventKind::LockstepTimeout => Level::Warning,
            EventKind::Crashed => Level::Error,
        }
    }

    /// The name in the log (`took_off`, …), as serde writes it.
    pub fn as_str(self) -> &'static str {
        match self {
            EventKind::TookOff => "took_off",
            EventKind::Crashed => "crashed",
            EventKind::Spawned => "spawned",
            EventKind::Paired => "paired",
            EventKind::InputRejected => "input_rejected",
            EventKind::StepOverrun => "step_overrun",
            EventKind::Interrupted => "interrupted",
            EventKind::Resumed => "resumed",
            EventKind::Failsafe => "failsafe",
            EventKind::FrameDropped => "frame_dropped",
            EventKind::BusReport => "bus_report",
            EventKind::LockstepTimeout => "lockstep_timeout",
        }
    }
}

/// Every schema name the log uses and its protobuf descriptor set: the project's own
/// (`twinswarm.*`, from `twinswarm.proto`) and Foxglove's well-known ones as the `foxglove`
/// crate ships them.
pub fn schema_data(name: &str) -> Option<Cow<'static, [u8]>> {
    if let Some(own) = name.strip_prefix("twinswarm.") {
        const OWN: [&str; 8] = [
            "CopterState",
            "CopterSensors",
            "CopterCommand",
            "CopterControl",
            "Event",
            "BusMessage",
            "PprzText",
            "PprzDecoded",
        ];
        return OWN.contains(&own).then_some(Cow::Borrowed(proto::DESCRIPTOR_SET));
    }
    let schema = match name {
        "foxglove.SceneUpdate" => fg::SceneUpdate::get_schema(),
        "foxglove.FrameTransform" => fg::FrameTransform::get_schema(),
        "foxglove.Log" => fg::Log::get_schema(),
        _ => None,
    }?;
    Some(schema.data)
}

/// An event to log on `/events` and `/log`.
#[derive(Clone, Debug, PartialEq)]
pub struct LogEvent {
    /// The tick it belongs to.
    pub tick: u64,
    /// What happened.
    pub kind: EventKind,
    /// The copter concerned, by id.
    pub copter: Option<usize>,
    /// Kind-specific details (a JSON object).
    pub detail: Option<serde_json::Value>,
    /// Human-readable text.
    pub message: String,
}

impl LogEvent {
    /// The log event of a step event.
    pub fn from_step(world: &World, tick: u64, event: &Event) -> Self {
        let copter = match event {
            Event::TookOff { copter } | Event::Crashed { copter, .. } => *copter,
        };
        Self::from_step_named(world.copters.get(copter).map_or("?", |c| c.name.as_str()), tick, event)
    }

    fn from_step_named(name: &str, tick: u64, event: &Event) -> Self {
        match event {
            Event::TookOff { copter } => LogEvent {
                tick,
                kind: EventKind::TookOff,
                copter: Some(*copter),
                detail: None,
                message: format!("{name} took off"),
            },
            Event::Crashed { copter, cause } => LogEvent {
                tick,
                kind: EventKind::Crashed,
                copter: Some(*copter),
                detail: serde_json::to_value(cause).ok(),
                message: format!("{name} crashed: {cause:?}"),
            },
        }
    }
}

#[derive(Clone, Debug)]
struct CopterInfo {
    name: String,
    ac_id: Option<u32>,
    kind: CopterKind,
    body_size_m: [f32; 3],
    /// The crash cause last written and its JSON text, so a wreck's text is made once.
    crash: Option<(CrashCause, String)>,
    /// The sample last written, to find one that did not change (kept only when
    /// [`Encoder::unchanged_every`] is above 1).
    last: Option<CopterSample>,
}

/// The kind as the log names it (serde's name in the JSON logs of before).
fn kind_str(kind: CopterKind) -> &'static str {
    match kind {
        CopterKind::Real => "real",
        CopterKind::Virtual => "virtual",
        CopterKind::Autopilot => "autopilot",
    }
}

/// Sonar cone drawing constants.
#[derive(Clone, Copy, Debug)]
struct SonarGeometry {
    tan_half: f32,
    mount_offset_m: f32,
    min_m: f32,
    cap_m: f32,
    safety_m: f32,
}

const H: f64 = std::f64::consts::FRAC_1_SQRT_2;
/// Rotation taking +z to each sonar axis (front +x, right −y, back −x, left +y), x y z w.
const SONAR_Z_TO_AXIS: [[f64; 4]; 4] = [[0.0, H, 0.0, H], [H, 0.0, 0.0, H], [0.0, -H, 0.0, H], [-H, 0.0, 0.0, H]];
const SONAR_AXES: [[f32; 3]; 4] = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
/// Cone colours: crosstalk, no echo, closer than the safety distance, echo.
const CONE_COLORS: [[f64; 4]; 4] =
    [[1.0, 0.55, 0.0, 0.45], [0.5, 0.5, 0.5, 0.06], [0.9, 0.2, 0.2, 0.3], [0.2, 0.6, 1.0, 0.2]];
const CRASHED_COLOR: [f64; 4] = [0.85, 0.1, 0.1, 1.0];

/// `/scene/copters` (bodies and sonar cones for Foxglove) is written at most this often, s:
/// the cones are for the eye; the readings themselves are on `/copters/sensors` every step.
/// At every 50 ms step it was about half the bytes of a log.
pub const SCENE_COPTERS_PERIOD_S: f64 = 0.2;

/// The per-copter messages, refilled in place each step.
#[derive(Debug, Default)]
struct Reused {
    state: proto::CopterState,
    sensors: proto::CopterSensors,
    command: proto::CopterCommand,
    control: proto::CopterControl,
    tf: fg::FrameTransform,
    /// `/scene/copters`: one entity per copter (body box, four cones).
    scene: fg::SceneUpdate,
}

/// Encodes messages into a reused buffer. Built once per run from the [`World`].
#[derive(Debug)]
pub struct Encoder {
    epoch_ns: u64,
    dt_ns: u64,
    copters: Vec<CopterInfo>,
    sonar: SonarGeometry,
    buf: Vec<u8>,
    scene_every: u64,
    /// A copter whose sample is equal to the one last written for it (a wreck at rest, its
    /// sensors stopped) is written again only on ticks that are multiples of this, or on a
    /// step the caller marks full. 1: every copter on every step.
    unchanged_every: u64,
    /// Which copters the step being encoded writes.
    write: Vec<bool>,
    /// Copter samples not written because they had not changed.
    held: u64,
    msg: Reused,
}

/// A sink for encoded messages: topic, log time (ns), protobuf bytes.
pub trait Sink<E>: FnMut(Topic, u64, &[u8]) -> Result<(), E> {}
impl<E, F: FnMut(Topic, u64, &[u8]) -> Result<(), E>> Sink<E> for F {}

const WORLD_FRAME: &str = "world";

fn timestamp(ns: u64) -> fg::Timestamp {
    fg::Timestamp::new(u32::try_from(ns / 1_000_000_000).unwrap_or(u32::MAX), (ns % 1_000_000_000) as u32)
}

/// A lifetime of zero: until replaced or deleted.
fn forever() -> Option<fg::Duration> {
    Some(fg::Duration::new(0, 0))
}

fn v3(x: f32, y: f32, z: f32) -> fg::Vector3 {
    fg::Vector3 { x: x.into(), y: y.into(), z: z.into() }
}

fn rgba([r, g, b, a]: [f64; 4]) -> Option<fg::Color> {
    Some(fg::Color { r, g, b, a })
}

fn quat([x, y, z, w]: [f64; 4]) -> fg::Quaternion {
    fg::Quaternion { x, y, z, w }
}

fn at(x: f32, y: f32, z: f32) -> Option<fg::Pose> {
    Some(fg::Pose { position: Some(v3(x, y, z)), orientation: Some(quat([0.0, 0.0, 0.0, 1.0])) })
}

/// Rotation about z by `yaw_rad`.
fn yaw(yaw_rad: f32) -> fg::Quaternion {
    let (s, c) = (f64::from(yaw_rad) / 2.0).sin_cos();
    quat([0.0, 0.0, s, c])
}

/// Replaces `v`'s contents with `x`, keeping its capacity.
fn set<T: Copy>(v: &mut Vec<T>, x: &[T]) {
    v.clear();
    v.extend_from_slice(x);
}

/// Replaces `s` with `x`, keeping its capacity.
fn set_str(s: &mut String, x: &str) {
    s.clear();
    s.push_str(x);
}

impl Encoder {
    /// An encoder for a run of `world` whose tick 0 is at `epoch_ns` (Unix ns).
    pub fn new(world: &World, epoch_ns: u64) -> Self {
        let copters: Vec<CopterInfo> = world
            .copters
            .iter()
            .map(|c| CopterInfo {
                name: c.name.clone(),
                ac_id: c.ac_id.map(u32::from),
                kind: c.kind,
                body_size_m: world.airframes[c.airframe].spec.body_size_m,
                crash: None,
                last: None,
            })
            .collect();
        let s = &world.sensors.spec;
        let mut msg = Reused::default();
        msg.tf.parent_frame_id = WORLD_FRAME.to_owned();
        msg.control.setpoint = Some(proto::Setpoint::default());
        msg.control.wall_avoid = Some(proto::WallAvoid::default());
        msg.scene.entities = copters.iter().map(copter_entity).collect();
        Self {
            epoch_ns,
            dt_ns: (world.params.control_dt_s * 1e9).round() as u64,
            copters,
            sonar: SonarGeometry {
                tan_half: world.sensors.sonar_half_angle_rad.tan(),
                mount_offset_m: s.sonar.mount_offset_m,
                min_m: s.sonar.min_range_m,
                cap_m: s.sonar.cap_m,
                safety_m: s.wall_avoid.safety_distance_m,
            },
            buf: Vec::with_capacity(64 * 1024),
            scene_every: ((SCENE_COPTERS_PERIOD_S / world.params.control_dt_s).round() as u64).max(1),
            unchanged_every: 1,
            write: Vec::new(),
            held: 0,
            msg,
        }
    }

    /// Writes a copter whose sample did not change since it was last written only on ticks
    /// that are multiples of `every_ticks` (and on full steps, see [`Encoder::encode_step`]);
    /// 1 (the default) writes every copter on every step.
    pub fn set_unchanged_every(&mut self, every_ticks: u64) {
        self.unchanged_every = every_ticks.max(1);
    }

    /// Copter samples left out so far because they had not changed.
    pub fn held(&self) -> u64 {
        self.held
    }

    /// `/scene/copters` goes out on ticks that are multiples of this.
    pub fn scene_every_ticks(&self) -> u64 {
        self.scene_every
    }

    /// Log time of a tick, ns.
    pub fn log_time(&self, tick: u64) -> u64 {
        self.epoch_ns + tick * self.dt_ns
    }

    /// Control step, ns.
    pub fn control_dt_ns(&self) -> u64 {
        self.dt_ns
    }

    fn t_s(&self, tick: u64) -> f64 {
        (tick * self.dt_ns) as f64 / 1e9
    }

    fn emit<E>(
        buf: &mut Vec<u8>,
        topic: Topic,
        log_time: u64,
        msg: &impl prost::Message,
        sink: &mut impl Sink<E>,
    ) -> Result<(), E> {
        buf.clear();
        // A Vec grows as needed: encoding into it cannot fail.
        let _ = msg.encode(buf);
        sink(topic, log_time, buf)
    }

    /// Every per-step message of a captured step: state, sensors, command, control and `/tf`
    /// per copter, one `/scene/copters` update every [`Encoder::scene_every_ticks`], and the
    /// step's events.
    ///
    /// A copter whose sample equals the one last written for it is left out unless `full`
    /// or the tick is a multiple of [`Encoder::set_unchanged_every`]'s period: a reader holds
    /// a copter's last message until its next.
    pub fn encode_step<E>(&mut self, frame: &StepFrame, full: bool, sink: &mut impl Sink<E>) -> Result<(), E> {
        let tick = frame.tick;
        let lt = self.log_time(tick);
        let t_s = self.t_s(tick);
        let full = full || tick.is_multiple_of(self.unchanged_every);
        self.choose_written(frame, full);
        // Topic by topic (all states, then all sensor readings, …): a chunk's messages of one
        // topic sit together, which zstd compresses better than copter by copter.
        self.encode_states(frame, lt, t_s, sink)?;
        self.encode_sensors(frame, lt, t_s, sink)?;
        self.encode_commands(frame, lt, t_s, sink)?;
        self.encode_controls(frame, lt, t_s, sink)?;
        self.encode_tfs(frame, lt, sink)?;
        if tick.is_multiple_of(self.scene_every) {
            self.encode_scene_copters(frame, lt, sink)?;
        }
        for e in &frame.events {
            let copter = match e {
                Event::TookOff { copter } | Event::Crashed { copter, .. } => *copter,
            };
            let name = self.copters.get(copter).map_or("?", |c| c.name.as_str());
            let ev = LogEvent::from_step_named(name, tick, e);
            self.encode_event(&ev, sink)?;
        }
        Ok(())
    }

    /// Marks in `self.write` the copters of `frame` this step writes: those this shard owns,
    /// less (unless `full`) those whose sample equals the one last written, which are counted
    /// as held.
    fn choose_written(&mut self, frame: &StepFrame, full: bool) {
        self.write.resize(self.copters.len(), false);
        for ((info, c), w) in self.copters.iter_mut().zip(&frame.copters).zip(&mut self.write) {
            *w = c.owned;
            if !c.owned {
                // Another shard writes it meanwhile: the sample this one wrote last no longer
                // says what a reader holds, so it writes the copter again when it gets it back.
                info.last = None;
                continue;
            }
            if self.unchanged_every == 1 {
                continue;
            }
            match &mut info.last {
                Some(last) if last == c => {
                    if full {
                        continue;
                    }
                    *w = false;
                    self.held += 1;
                }
                Some(last) => last.clone_from(c),
                None => info.last = Some(c.clone()),
            }
        }
    }

    /// `/copters/state` of each written copter: mode, crash, pose, velocities and rotors.
    fn encode_states<E>(&mut self, frame: &StepFrame, lt: u64, t_s: f64, sink: &mut impl Sink<E>) -> Result<(), E> {
        let tick = frame.tick;
        let (m, b) = (&mut self.msg, &mut self.buf);
        for (id, ((info, c), _)) in
            self.copters.iter_mut().zip(&frame.copters).zip(&self.write).enumerate().filter(|(_, (_, w))| **w)
        {
            let p = &c.pose;
            let mode = c.command.mode.as_str();
            let id = id as u32;
            let st = &mut m.state;
            (st.tick, st.t_s, st.id, st.ac_id) = (tick, t_s, id, info.ac_id);
            set_str(&mut st.copter, &info.name);
            set_str(&mut st.kind, kind_str(info.kind));
            set_str(&mut st.mode, mode);
            st.crashed = c.crash.is_some();
            match c.crash {
                Some(cause) => {
                    if info.crash.as_ref().is_none_or(|(was, _)| *was != cause) {
                        info.crash = Some((cause, serde_json::to_string(&cause).unwrap_or_default()));
                    }
                    set_str(&mut st.crash_cause, info.crash.as_ref().map_or("", |(_, text)| text));
                }
                None => st.crash_cause.clear(),
            }
            st.took_off = c.took_off_tick.is_some();
            set(&mut st.pos_m, &[p.pos_m.x, p.pos_m.y, p.pos_m.z]);
            set(&mut st.vel_m_s, &[p.vel_m_s.x, p.vel_m_s.y, p.vel_m_s.z]);
            set(&mut st.rpy_rad, &p.rpy_rad);
            set(&mut st.angvel_rad_s, &[p.angvel_rad_s.x, p.angvel_rad_s.y, p.angvel_rad_s.z]);
            set(&mut st.quat_xyzw, &p.quat_xyzw);
            set(&mut st.rotor_thrust_n, &c.rotor_thrust_n);
            set(&mut st.rotor_speed_rad_s, &c.rotor_speed_rad_s);
            Self::emit(b, Topic::State, lt, st, sink)?;
        }
        Ok(())
    }

    /// `/copters/sensors` of each written copter: sonars, IR, IMU, estimates and battery.
    fn encode_sensors<E>(&mut self, frame: &StepFrame, lt: u64, t_s: f64, sink: &mut impl Sink<E>) -> Result<(), E> {
        let tick = frame.tick;
        let (m, b) = (&mut self.msg, &mut self.buf);
        for (id, ((info, c), _)) in
            self.copters.iter().zip(&frame.copters).zip(&self.write).enumerate().filter(|(_, (_, w))| **w)
        {
            let id = id as u32;
            let r = &c.sensors;
            let se = &mut m.sensors;
            (se.tick, se.t_s, se.id, se.sonar_tick) = (tick, t_s, id, r.sonar_tick);
            set_str(&mut se.copter, &info.name);
            set(&mut se.sonar_truth_m, &r.sonar_truth_m);
            set(&mut se.sonar_m, &r.sonar_m);
            set(&mut se.sonar_fused_m, &r.sonar_fused_m);
            set(&mut se.sonar_crosstalk, &r.sonar_crosstalk);
            se.ir_m = r.ir_m;
            se.ir_truth_m = r.ir_truth_m.is_finite().then_some(r.ir_truth_m);
            set(&mut se.attitude_rad, &r.attitude_rad);
            se.yaw_bias_rad = r.yaw_bias_rad;
            set(&mut se.rate_body_rad_s, &r.rate_body_rad_s);
            set(&mut se.accel_body_m_s2, &r.accel_body_m_s2);
            (se.height_est_m, se.battery_v, se.battery_charge, se.battery_a) =
                (r.height_est_m, r.battery_v, r.battery_charge, r.battery_a);
            Self::emit(b, Topic::Sensors, lt, se, sink)?;
        }
        Ok(())
    }

    /// `/copters/command` of each written copter: the command it flew the step with.
    fn encode_commands<E>(&mut self, frame: &StepFrame, lt: u64, t_s: f64, sink: &mut impl Sink<E>) -> Result<(), E> {
        let tick = frame.tick;
        let (m, b) = (&mut self.msg, &mut self.buf);
        for (id, ((info, c), _)) in
            self.copters.iter().zip(&frame.copters).zip(&self.write).enumerate().filter(|(_, (_, w))| **w)
        {
            let mode = c.command.mode.as_str();
            let id = id as u32;
            let cmd = &c.command;
            let co = &mut m.command;
            (co.tick, co.t_s, co.id) = (tick, t_s, id);
            set_str(&mut co.copter, &info.name);
            set_str(&mut co.mode, mode);
            (co.roll_rad, co.pitch_rad, co.yaw_rad, co.throttle, co.height_m) =
                (cmd.roll_rad, cmd.pitch_rad, cmd.yaw_rad, cmd.throttle, cmd.height_m);
            set(&mut co.target_m, cmd.target_m.as_ref().map_or(&[][..], |v| &v[..]));
            set(&mut co.velocity_m_s, cmd.velocity_m_s.as_ref().map_or(&[][..], |v| &v[..]));
            set(&mut co.virtual_sonar_m, cmd.virtual_sonar_m.as_ref().map_or(&[][..], |v| &v[..]));
            Self::emit(b, Topic::Command, lt, co, sink)?;
        }
        Ok(())
    }

    /// `/copters/control` of each written copter: its setpoint and Wall-Avoid's outputs.
    fn encode_controls<E>(&mut self, frame: &StepFrame, lt: u64, t_s: f64, sink: &mut impl Sink<E>) -> Result<(), E> {
        let tick = frame.tick;
        let (m, b) = (&mut self.msg, &mut self.buf);
        for (id, ((info, c), _)) in
            self.copters.iter().zip(&frame.copters).zip(&self.write).enumerate().filter(|(_, (_, w))| **w)
        {
            let id = id as u32;
            let (sp, wa) = (&c.setpoint, &c.wall_avoid);
            let ct = &mut m.control;
            (ct.tick, ct.t_s, ct.id) = (tick, t_s, id);
            set_str(&mut ct.copter, &info.name);
            let s = ct.setpoint.get_or_insert_default();
            (s.roll_rad, s.pitch_rad, s.yaw_rad, s.height_m, s.throttle) =
                (sp.roll_rad, sp.pitch_rad, sp.yaw_rad, sp.height_m, sp.throttle);
            let w = ct.wall_avoid.get_or_insert_default();
            w.engaged = c.command.mode == FlightMode::WallAvoid && wa.out_rad != [0.0; 2];
            set(&mut w.out_rad, &wa.out_rad);
            set(&mut w.last_m, &wa.last_m);
            set(&mut w.rate_m_s, &wa.rate_m_s);
            Self::emit(b, Topic::Control, lt, ct, sink)?;
        }
        Ok(())
    }

    /// `/tf` of each written copter: its frame in the world's.
    fn encode_tfs<E>(&mut self, frame: &StepFrame, lt: u64, sink: &mut impl Sink<E>) -> Result<(), E> {
        let (m, b) = (&mut self.msg, &mut self.buf);
        for ((info, c), _) in self.copters.iter().zip(&frame.copters).zip(&self.write).filter(|(_, w)| **w) {
            let p = &c.pose;
            let tf = &mut m.tf;
            tf.timestamp = Some(timestamp(lt));
            set_str(&mut tf.child_frame_id, &info.name);
            tf.translation = Some(v3(p.pos_m.x, p.pos_m.y, p.pos_m.z));
            let [x, y, z, w] = p.quat_xyzw.map(f64::from);
            tf.rotation = Some(quat([x, y, z, w]));
            Self::emit(b, Topic::Tf, lt, tf, sink)?;
        }
        Ok(())
    }

    /// `/scene/copters`: every copter's entities updated; a shard sends only its own.
    fn encode_scene_copters<E>(&mut self, frame: &StepFrame, lt: u64, sink: &mut impl Sink<E>) -> Result<(), E> {
        let (m, b) = (&mut self.msg, &mut self.buf);
        update_copter_entities(&mut m.scene, &self.copters, frame, self.sonar, lt);
        if frame.copters.iter().all(|c| c.owned) {
            Self::emit(b, Topic::SceneCopters, lt, &m.scene, sink)
        } else {
            // A shard updates only its own copters' entities (the others keep theirs).
            let mut own = fg::SceneUpdate::default();
            own.entities
                .extend(m.scene.entities.iter().zip(&frame.copters).filter(|(_, c)| c.owned).map(|(e, _)| e.clone()));
            Self::emit(b, Topic::SceneCopters, lt, &own, sink)
        }
    }

    /// An event, on `/events` and as a line on `/log`.
    pub fn encode_event<E>(&mut self, ev: &LogEvent, sink: &mut impl Sink<E>) -> Result<(), E> {
        let lt = self.log_time(ev.tick);
        let msg = proto::Event {
            tick: ev.tick,
            t_s: self.t_s(ev.tick),
            kind: ev.kind.as_str().to_owned(),
            copter: ev.copter.and_then(|i| self.copters.get(i)).map(|c| c.name.clone()),
            id: ev.copter.and_then(|i| u32::try_from(i).ok()),
            detail: ev.detail.as_ref().and_then(proto::json_to_struct),
            message: ev.message.clone(),
        };
        Self::emit(&mut self.buf, Topic::Events, lt, &msg, sink)?;
        let log = fg::Log {
            timestamp: Some(timestamp(lt)),
            level: ev.kind.level() as i32,
            message: ev.message.clone(),
            name: "twinswarm".to_owned(),
            file: String::new(),
            line: 0,
        };
        Self::emit(&mut self.buf, Topic::Log, lt, &log, sink)
    }

    /// A bus message (`/bus`): `log_time` is the simulated time of `tick`, `publish_time`
    /// (returned with the bytes through `sink`'s caller) is chosen by the writer.
    pub fn encode_bus<E>(
        &mut self,
        tick: u64,
        key: &str,
        direction: &str,
        text: &str,
        sink: &mut impl Sink<E>,
    ) -> Result<(), E> {
        let lt = self.log_time(tick);
        let msg =
            proto::BusMessage { tick, key: key.to_owned(), direction: direction.to_owned(), text: text.to_owned() };
        Self::emit(&mut self.buf, Topic::Bus, lt, &msg, sink)
    }

    /// The static scene on `/scene/arena` at tick 0: floor, walls, outline, boxes with their
    /// names, and per copter its rotor discs, a forward arrow and its name, locked to its frame.
    pub fn encode_arena<E>(&mut self, world: &World, sink: &mut impl Sink<E>) -> Result<(), E> {
        let lt = self.log_time(0);
        let [sx, sy] = world.arena.size_m;
        let h = world.arena.height_m;
        let cube = |pose, size, color| fg::CubePrimitive { pose, size: Some(size), color: rgba(color) };
        let mut cubes = vec![cube(at(0.0, 0.0, -0.005), v3(sx, sy, 0.01), [0.55, 0.55, 0.55, 1.0])];
        let mut lines = Vec::new();
        if world.arena.walls {
            let wall = [0.7, 0.8, 0.9, 0.12];
            let t = 0.02;
            cubes.push(cube(at(sx / 2.0, 0.0, h / 2.0), v3(t, sy, h), wall));
            cubes.push(cube(at(-sx / 2.0, 0.0, h / 2.0), v3(t, sy, h), wall));
            cubes.push(cube(at(0.0, sy / 2.0, h / 2.0), v3(sx, t, h), wall));
            cubes.push(cube(at(0.0, -sy / 2.0, h / 2.0), v3(sx, t, h), wall));
            let (x, y) = (f64::from(sx) / 2.0, f64::from(sy) / 2.0);
            let p = |x: f64, y: f64, z: f64| fg::Point3 { x, y, z };
            let c = [(-x, -y), (x, -y), (x, y), (-x, y)];
            let mut points = Vec::new();
            for i in 0..4 {
                let ((ax, ay), (bx, by)) = (c[i], c[(i + 1) % 4]);
                let h = f64::from(h);
                points.extend([p(ax, ay, h), p(bx, by, h), p(ax, ay, 0.0), p(ax, ay, h)]);
            }
            lines.push(fg::LinePrimitive {
                r#type: fg::line_primitive::Type::LineList as i32,
                pose: at(0.0, 0.0, 0.0),
                thickness: 0.01,
                scale_invariant: false,
                points,
                color: rgba([0.2, 0.3, 0.4, 1.0]),
                colors: Vec::new(),
                indices: Vec::new(),
            });
        }
        let label = |pose, text: &str, color| fg::TextPrimitive {
            pose,
            billboard: true,
            font_size: 14.0,
            scale_invariant: true,
            color: rgba(color),
            text: text.to_owned(),
        };
        let mut texts = Vec::new();
        for b in &world.boxes {
            let hz = b.half_extents_m;
            cubes.push(fg::CubePrimitive {
                pose: Some(fg::Pose {
                    position: Some(v3(b.center_m.x, b.center_m.y, b.center_m.z)),
                    orientation: Some(yaw(b.yaw_rad)),
                }),
                size: Some(v3(2.0 * hz.x, 2.0 * hz.y, 2.0 * hz.z)),
                color: rgba([0.62, 0.45, 0.28, 0.9]),
            });
            texts.push(label(at(b.center_m.x, b.center_m.y, b.center_m.z + hz.z + 0.1), &b.name, [0.1, 0.1, 0.1, 1.0]));
        }
        let ts = Some(timestamp(lt));
        let mut entities = vec![fg::SceneEntity {
            timestamp: ts,
            frame_id: WORLD_FRAME.to_owned(),
            id: "arena".to_owned(),
            lifetime: forever(),
            metadata: vec![fg::KeyValuePair { key: "world".into(), value: world.name.clone() }],
            cubes,
            lines,
            texts,
            ..Default::default()
        }];
        for c in &world.copters {
            let af = &world.airframes[c.airframe];
            let r = af.spec.rotor_diameter_m;
            let top = af.spec.body_size_m[2] / 2.0;
            let cylinders = af
                .rotor_pos_in_body_m
                .iter()
                .map(|p| fg::CylinderPrimitive {
                    pose: at(p.x, p.y, p.z + top),
                    size: Some(v3(r, r, 0.005)),
                    bottom_scale: 1.0,
                    top_scale: 1.0,
                    color: rgba([0.15, 0.15, 0.15, 0.6]),
                })
                .collect();
            let arrow = fg::ArrowPrimitive {
                pose: at(0.0, 0.0, top + 0.01),
                shaft_length: 0.12,
                shaft_diameter: 0.01,
                head_length: 0.04,
                head_diameter: 0.03,
                color: rgba([0.9, 0.2, 0.1, 1.0]),
            };
            entities.push(fg::SceneEntity {
                timestamp: ts,
                frame_id: c.name.clone(),
                id: format!("rig/{}", c.name),
                lifetime: forever(),
                frame_locked: true,
                metadata: vec![
                    fg::KeyValuePair { key: "kind".into(), value: kind_str(c.kind).into() },
                    fg::KeyValuePair { key: "ac_id".into(), value: c.ac_id.map(|a| a.to_string()).unwrap_or_default() },
                ],
                arrows: vec![arrow],
                cylinders,
                texts: vec![label(at(0.0, 0.0, 0.15), &c.name, [0.0, 0.0, 0.0, 1.0])],
                ..Default::default()
            });
        }
        Self::emit(&mut self.buf, Topic::SceneArena, lt, &fg::SceneUpdate { deletions: Vec::new(), entities }, sink)
    }
}

/// A copter's entity in `/scene/copters`, before its first update: its body box coloured by
/// kind and four sonar cones, locked to its frame.
fn copter_entity(info: &CopterInfo) -> fg::SceneEntity {
    let [x, y, z] = info.body_size_m;
    let cone = |k: usize| fg::CylinderPrimitive {
        pose: Some(fg::Pose { position: Some(v3(0.0, 0.0, 0.0)), orientation: Some(quat(SONAR_Z_TO_AXIS[k])) }),
        size: Some(v3(0.0, 0.0, 0.0)),
        bottom_scale: 0.0,
        top_scale: 1.0,
        color: rgba(CONE_COLORS[1]),
    };
    fg::SceneEntity {
        timestamp: Some(timestamp(0)),
        frame_id: info.name.clone(),
        id: format!("copter/{}", info.name),
        lifetime: forever(),
        frame_locked: true,
        cubes: vec![fg::CubePrimitive { pose: at(0.0, 0.0, 0.0), size: Some(v3(x, y, z)), color: flying_color(info) }],
        cylinders: (0..4).map(cone).collect(),
        ..Default::default()
    }
}

fn flying_color(info: &CopterInfo) -> Option<fg::Color> {
    rgba(match info.kind {
        CopterKind::Real => [0.1, 0.6, 0.2, 1.0],
        CopterKind::Virtual => [0.15, 0.35, 0.8, 1.0],
        CopterKind::Autopilot => [0.9, 0.5, 0.1, 1.0],
    })
}

/// The per-step `foxglove.SceneUpdate` of the copters: per copter its body box, coloured by
/// kind and status (red when crashed), and its four sonar cones, each as long as its fused
/// reading and coloured by what it sees. Updates the entities in place.
fn update_copter_entities(
    scene: &mut fg::SceneUpdate,
    copters: &[CopterInfo],
    frame: &StepFrame,
    g: SonarGeometry,
    lt: u64,
) {
    let ts = timestamp(lt);
    for ((e, c), info) in scene.entities.iter_mut().zip(&frame.copters).zip(copters) {
        e.timestamp = Some(ts);
        if let Some(body) = e.cubes.first_mut() {
            body.color = if c.crash.is_some() { rgba(CRASHED_COLOR) } else { flying_color(info) };
        }
        let cones = c.sensors.sonar_fused_m.iter().zip(&c.sensors.sonar_crosstalk).zip(&SONAR_AXES);
        for (cyl, ((&reading, &crosstalk), a)) in e.cylinders.iter_mut().zip(cones) {
            let echo = reading < g.cap_m;
            let len = reading.clamp(g.min_m, g.cap_m);
            let color = if crosstalk {
                0
            } else if !echo {
                1
            } else if reading < g.safety_m {
                2
            } else {
                3
            };
            let d = g.mount_offset_m + len / 2.0;
            let width = 2.0 * len * g.tan_half;
            if let Some(pose) = cyl.pose.as_mut() {
                pose.position = Some(v3(a[0] * d, a[1] * d, a[2] * d));
            }
            cyl.size = Some(v3(width, width, len));
            cyl.color = rgba(CONE_COLORS[color]);
        }
    }
}
