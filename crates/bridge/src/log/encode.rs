//! Turns captured steps, events and the static scene into JSON messages (sans I/O): each
//! message goes to a sink as `(topic, log_time_ns, bytes)`.

use serde::Serialize;
use sim_core::control::FlightMode;
use sim_core::{CopterKind, Event, World};

use super::capture::StepFrame;
use super::json::{Json, quoted};
use super::msg::*;

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

    /// The schema name (see [`super::SCHEMAS`]).
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
    /// A lost link or a controller change (see `bridge::failsafe`).
    Failsafe,
    /// A step's frame was not published (the publisher was behind).
    FrameDropped,
    /// At the end of a run on a bus: what the bus received, refused and dropped.
    BusReport,
}

impl EventKind {
    /// `foxglove.Log` level.
    fn level(self) -> u8 {
        match self {
            EventKind::TookOff | EventKind::Spawned | EventKind::Paired | EventKind::BusReport => 2,
            EventKind::InputRejected
            | EventKind::StepOverrun
            | EventKind::Interrupted
            | EventKind::Failsafe
            | EventKind::FrameDropped => 3,
            EventKind::Crashed => 4,
        }
    }
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
    /// The name as a JSON string.
    name_json: String,
    /// `"copter/<name>"` as a JSON string: its `/scene/copters` entity.
    entity_id_json: String,
    /// `,"copter":<name>,"id":<id>`: in every per-copter message.
    ident: String,
    /// `,"ac_id":…,"kind":…`: in `/copters/state`.
    state_ident: String,
    kind: CopterKind,
    body_size_m: [f32; 3],
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

/// Rotation taking +z to each sonar axis (front +x, right −y, back −x, left +y).
const SONAR_Z_TO_AXIS: [Q; 4] = {
    const H: f32 = std::f32::consts::FRAC_1_SQRT_2;
    [
        Q { x: 0.0, y: H, z: 0.0, w: H },
        Q { x: H, y: 0.0, z: 0.0, w: H },
        Q { x: 0.0, y: -H, z: 0.0, w: H },
        Q { x: -H, y: 0.0, z: 0.0, w: H },
    ]
};
const SONAR_AXES: [[f32; 3]; 4] = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];

/// `/scene/copters` (bodies and sonar cones for Foxglove) is written at most this often, s:
/// the cones are for the eye; the readings themselves are on `/copters/sensors` every step.
/// At every 50 ms step it was about half the bytes of a log.
pub const SCENE_COPTERS_PERIOD_S: f64 = 0.2;

/// Encodes messages into a reused buffer. Built once per run from the [`World`].
#[derive(Debug)]
pub struct Encoder {
    epoch_ns: u64,
    dt_ns: u64,
    copters: Vec<CopterInfo>,
    sonar: SonarGeometry,
    buf: Vec<u8>,
    scene_every: u64,
    scene_text: SceneText,
}

/// A sink for encoded messages: topic, log time (ns), JSON bytes.
pub trait Sink<E>: FnMut(Topic, u64, &[u8]) -> Result<(), E> {}
impl<E, F: FnMut(Topic, u64, &[u8]) -> Result<(), E>> Sink<E> for F {}

const WORLD_FRAME: &str = "world";

impl Encoder {
    /// An encoder for a run of `world` whose tick 0 is at `epoch_ns` (Unix ns).
    pub fn new(world: &World, epoch_ns: u64) -> Self {
        let copters = world
            .copters
            .iter()
            .enumerate()
            .map(|(id, c)| {
                let af = &world.airframes[c.airframe];
                let name_json = quoted(&c.name);
                let ac_id = c.ac_id.map_or("null".to_owned(), |a| a.to_string());
                CopterInfo {
                    name: c.name.clone(),
                    ident: format!(",\"copter\":{name_json},\"id\":{id}"),
                    state_ident: format!(
                        ",\"ac_id\":{ac_id},\"kind\":{}",
                        serde_json::to_string(&c.kind).unwrap_or_default()
                    ),
                    entity_id_json: quoted(&format!("copter/{}", c.name)),
                    name_json,
                    kind: c.kind,
                    body_size_m: af.spec.body_size_m,
                }
            })
            .collect::<Vec<_>>();
        let s = &world.sensors.spec;
        Self {
            scene_text: SceneText::new(&copters),
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
        }
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

    fn emit<E, T: Serialize>(
        &mut self,
        topic: Topic,
        log_time: u64,
        msg: &T,
        sink: &mut impl Sink<E>,
    ) -> Result<(), E> {
        self.buf.clear();
        // Serialising plain structs of numbers and strings into a Vec cannot fail.
        let _ = serde_json::to_writer(&mut self.buf, msg);
        sink(topic, log_time, &self.buf)
    }

    /// Every per-step message of a captured step: state, sensors, command, control and `/tf`
    /// per copter, one `/scene/copters` update every [`Encoder::scene_every_ticks`], and the
    /// step's events. Written with [`Json`] (same text as serde's, several times faster).
    pub fn encode_step<E>(&mut self, frame: &StepFrame, sink: &mut impl Sink<E>) -> Result<(), E> {
        let tick = frame.tick;
        let lt = self.log_time(tick);
        let t_s = self.t_s(tick);
        // The part every copter message starts with: `{"tick":…,"t_s":…`.
        let mut head = Vec::with_capacity(32);
        Json(&mut head).raw("{\"tick\":").u64(tick).raw(",\"t_s\":").f64(t_s);
        for (info, c) in self.copters.iter().zip(&frame.copters) {
            let b = &mut self.buf;
            let p = &c.pose;
            let mode = c.command.mode;

            let j = &mut Json::starting(b, &head);
            j.raw(&info.ident).raw(&info.state_ident).raw(",\"mode\":\"").raw(mode.as_str()).raw("\"");
            j.raw(",\"crashed\":").bool(c.crash.is_some()).raw(",\"crash_cause\":");
            match &c.crash {
                Some(cause) => j.serde(cause),
                None => j.raw("null"),
            };
            j.raw(",\"took_off\":").bool(c.took_off_tick.is_some());
            j.raw(",\"pos_m\":").f32s(&[p.pos_m.x, p.pos_m.y, p.pos_m.z]);
            j.raw(",\"vel_m_s\":").f32s(&[p.vel_m_s.x, p.vel_m_s.y, p.vel_m_s.z]);
            j.raw(",\"rpy_rad\":").f32s(&p.rpy_rad);
            j.raw(",\"angvel_rad_s\":").f32s(&[p.angvel_rad_s.x, p.angvel_rad_s.y, p.angvel_rad_s.z]);
            j.raw(",\"quat_xyzw\":").f32s(&p.quat_xyzw);
            j.raw(",\"rotor_thrust_n\":").f32s(&c.rotor_thrust_n);
            j.raw(",\"rotor_speed_rad_s\":").f32s(&c.rotor_speed_rad_s).raw("}");
            sink(Topic::State, lt, b)?;

            let r = &c.sensors;
            let j = &mut Json::starting(b, &head);
            j.raw(&info.ident).raw(",\"sonar_tick\":").u64(r.sonar_tick);
            j.raw(",\"sonar_truth_m\":").f32s(&r.sonar_truth_m);
            j.raw(",\"sonar_m\":").f32s(&r.sonar_m);
            j.raw(",\"sonar_fused_m\":").f32s(&r.sonar_fused_m);
            j.raw(",\"sonar_crosstalk\":").bools(&r.sonar_crosstalk);
            j.raw(",\"ir_m\":").opt_f32(r.ir_m);
            j.raw(",\"ir_truth_m\":").opt_f32(r.ir_truth_m.is_finite().then_some(r.ir_truth_m));
            j.raw(",\"attitude_rad\":").f32s(&r.attitude_rad);
            j.raw(",\"yaw_bias_rad\":").f32(r.yaw_bias_rad);
            j.raw(",\"rate_body_rad_s\":").f32s(&r.rate_body_rad_s);
            j.raw(",\"accel_body_m_s2\":").f32s(&r.accel_body_m_s2);
            j.raw(",\"height_est_m\":").f32(r.height_est_m);
            j.raw(",\"battery_v\":").f32(r.battery_v);
            j.raw(",\"battery_charge\":").f32(r.battery_charge);
            j.raw(",\"battery_a\":").f32(r.battery_a).raw("}");
            sink(Topic::Sensors, lt, b)?;

            let cmd = &c.command;
            let j = &mut Json::starting(b, &head);
            j.raw(&info.ident).raw(",\"mode\":\"").raw(mode.as_str()).raw("\"");
            j.raw(",\"roll_rad\":").f32(cmd.roll_rad).raw(",\"pitch_rad\":").f32(cmd.pitch_rad);
            j.raw(",\"yaw_rad\":").f32(cmd.yaw_rad).raw(",\"throttle\":").f32(cmd.throttle);
            j.raw(",\"height_m\":").f32(cmd.height_m);
            j.raw(",\"target_m\":").opt_f32s(cmd.target_m.as_ref().map(|v| &v[..]));
            j.raw(",\"velocity_m_s\":").opt_f32s(cmd.velocity_m_s.as_ref().map(|v| &v[..]));
            j.raw(",\"virtual_sonar_m\":").opt_f32s(cmd.virtual_sonar_m.as_ref().map(|v| &v[..])).raw("}");
            sink(Topic::Command, lt, b)?;

            let (sp, wa) = (&c.setpoint, &c.wall_avoid);
            let j = &mut Json::starting(b, &head);
            j.raw(&info.ident).raw(",\"setpoint\":{\"roll_rad\":").f32(sp.roll_rad);
            j.raw(",\"pitch_rad\":").f32(sp.pitch_rad).raw(",\"yaw_rad\":").f32(sp.yaw_rad);
            j.raw(",\"height_m\":").f32(sp.height_m).raw(",\"throttle\":").f32(sp.throttle);
            let engaged = mode == FlightMode::WallAvoid && wa.out_rad != [0.0; 2];
            j.raw("},\"wall_avoid\":{\"engaged\":").bool(engaged);
            j.raw(",\"out_rad\":").f32s(&wa.out_rad).raw(",\"last_m\":").f32s(&wa.last_m);
            j.raw(",\"rate_m_s\":").f32s(&wa.rate_m_s).raw("}}");
            sink(Topic::Control, lt, b)?;

            b.clear();
            let j = &mut Json(b);
            j.raw("{\"timestamp\":").time(lt).raw(",\"parent_frame_id\":\"").raw(WORLD_FRAME);
            j.raw("\",\"child_frame_id\":").raw(&info.name_json);
            j.raw(",\"translation\":").xyz([p.pos_m.x, p.pos_m.y, p.pos_m.z]);
            j.raw(",\"rotation\":").xyzw(p.quat_xyzw).raw("}");
            sink(Topic::Tf, lt, b)?;
        }
        if tick.is_multiple_of(self.scene_every) {
            self.buf.clear();
            copter_entities(&mut Json(&mut self.buf), &self.scene_text, frame, self.sonar, lt);
            sink(Topic::SceneCopters, lt, &self.buf)?;
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

    /// An event, on `/events` and as a line on `/log`.
    pub fn encode_event<E>(&mut self, ev: &LogEvent, sink: &mut impl Sink<E>) -> Result<(), E> {
        let lt = self.log_time(ev.tick);
        let name = ev.copter.and_then(|i| self.copters.get(i)).map(|c| c.name.clone());
        let msg = EventMsg {
            tick: ev.tick,
            t_s: self.t_s(ev.tick),
            kind: ev.kind,
            copter: name.as_deref(),
            id: ev.copter,
            detail: ev.detail.as_ref(),
            message: &ev.message,
        };
        self.emit(Topic::Events, lt, &msg, sink)?;
        let log = LogMsg {
            timestamp: Time::from_ns(lt),
            level: ev.kind.level(),
            message: &ev.message,
            name: "twinswarm",
            file: "",
            line: 0,
        };
        self.emit(Topic::Log, lt, &log, sink)
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
        self.emit(Topic::Bus, lt, &BusMsg { tick, key, direction, text }, sink)
    }

    /// The static scene on `/scene/arena` at tick 0: floor, walls, outline, boxes with their
    /// names, and per copter its rotor discs, a forward arrow and its name, locked to its frame.
    pub fn encode_arena<E>(&mut self, world: &World, sink: &mut impl Sink<E>) -> Result<(), E> {
        let lt = self.log_time(0);
        let time = Time::from_ns(lt);
        let [sx, sy] = world.arena.size_m;
        let h = world.arena.height_m;
        let at = |x, y, z| Pose { position: v3(x, y, z), orientation: IDENTITY };
        let mut cubes =
            vec![Cube { pose: at(0.0, 0.0, -0.005), size: v3(sx, sy, 0.01), color: rgba(0.55, 0.55, 0.55, 1.0) }];
        let mut lines = Vec::new();
        if world.arena.walls {
            let wall = rgba(0.7, 0.8, 0.9, 0.12);
            let t = 0.02;
            cubes.push(Cube { pose: at(sx / 2.0, 0.0, h / 2.0), size: v3(t, sy, h), color: wall });
            cubes.push(Cube { pose: at(-sx / 2.0, 0.0, h / 2.0), size: v3(t, sy, h), color: wall });
            cubes.push(Cube { pose: at(0.0, sy / 2.0, h / 2.0), size: v3(sx, t, h), color: wall });
            cubes.push(Cube { pose: at(0.0, -sy / 2.0, h / 2.0), size: v3(sx, t, h), color: wall });
            let (x, y) = (sx / 2.0, sy / 2.0);
            let c = [v3(-x, -y, 0.0), v3(x, -y, 0.0), v3(x, y, 0.0), v3(-x, y, 0.0)];
            let mut pts = Vec::new();
            for i in 0..4 {
                let (a, b) = (c[i], c[(i + 1) % 4]);
                pts.extend([v3(a.x, a.y, h), v3(b.x, b.y, h), a, v3(a.x, a.y, h)]);
            }
            lines.push(Line {
                kind: 2,
                pose: at(0.0, 0.0, 0.0),
                thickness: 0.01,
                scale_invariant: false,
                points: pts,
                color: rgba(0.2, 0.3, 0.4, 1.0),
                colors: [],
                indices: [],
            });
        }
        let mut texts = Vec::new();
        for b in &world.boxes {
            let hz = b.half_extents_m;
            cubes.push(Cube {
                pose: Pose { position: v3(b.center_m.x, b.center_m.y, b.center_m.z), orientation: Q::yaw(b.yaw_rad) },
                size: v3(2.0 * hz.x, 2.0 * hz.y, 2.0 * hz.z),
                color: rgba(0.62, 0.45, 0.28, 0.9),
            });
            texts.push(Text {
                pose: at(b.center_m.x, b.center_m.y, b.center_m.z + hz.z + 0.1),
                billboard: true,
                font_size: 14.0,
                scale_invariant: true,
                color: rgba(0.1, 0.1, 0.1, 1.0),
                text: b.name.clone(),
            });
        }
        let arena = Entity {
            timestamp: time,
            frame_id: WORLD_FRAME,
            id: "arena",
            lifetime: FOREVER,
            frame_locked: false,
            metadata: &[KeyValue { key: "world".into(), value: world.name.clone() }],
            arrows: &[],
            cubes: &cubes,
            spheres: [],
            cylinders: &[],
            lines: &lines,
            triangles: [],
            texts: &texts,
            models: [],
        };
        struct Rig {
            id: String,
            cylinders: Vec<Cylinder>,
            arrows: [Arrow; 1],
            texts: [Text; 1],
            metadata: Vec<KeyValue>,
        }
        let rigs: Vec<Rig> = world
            .copters
            .iter()
            .map(|c| {
                let af = &world.airframes[c.airframe];
                let r = af.spec.rotor_diameter_m;
                let top = af.spec.body_size_m[2] / 2.0;
                let cylinders = af
                    .rotor_pos_in_body_m
                    .iter()
                    .map(|p| Cylinder {
                        pose: at(p.x, p.y, p.z + top),
                        size: v3(r, r, 0.005),
                        bottom_scale: 1.0,
                        top_scale: 1.0,
                        color: rgba(0.15, 0.15, 0.15, 0.6),
                    })
                    .collect();
                let arrow = Arrow {
                    pose: at(0.0, 0.0, top + 0.01),
                    shaft_length: 0.12,
                    shaft_diameter: 0.01,
                    head_length: 0.04,
                    head_diameter: 0.03,
                    color: rgba(0.9, 0.2, 0.1, 1.0),
                };
                let label = Text {
                    pose: at(0.0, 0.0, 0.15),
                    billboard: true,
                    font_size: 14.0,
                    scale_invariant: true,
                    color: rgba(0.0, 0.0, 0.0, 1.0),
                    text: c.name.clone(),
                };
                let metadata = vec![
                    KeyValue { key: "kind".into(), value: format!("{:?}", c.kind).to_lowercase() },
                    KeyValue { key: "ac_id".into(), value: c.ac_id.map(|a| a.to_string()).unwrap_or_default() },
                ];
                Rig { id: format!("rig/{}", c.name), cylinders, arrows: [arrow], texts: [label], metadata }
            })
            .collect();
        let mut entities = vec![arena];
        for (c, rig) in world.copters.iter().zip(&rigs) {
            entities.push(Entity {
                timestamp: time,
                frame_id: &c.name,
                id: &rig.id,
                lifetime: FOREVER,
                frame_locked: true,
                metadata: &rig.metadata,
                arrows: &rig.arrows,
                cubes: &[],
                spheres: [],
                cylinders: &rig.cylinders,
                lines: &[],
                triangles: [],
                texts: &rig.texts,
                models: [],
            });
        }
        self.emit(Topic::SceneArena, lt, &SceneUpdate { deletions: [], entities: &entities }, sink)
    }
}

/// The constant parts of the per-step `foxglove.SceneUpdate` of the copters, as JSON text:
/// written once per run, so an update formats only what changes (time, cone positions and
/// sizes).
#[derive(Clone, Debug)]
struct SceneText {
    /// Per copter, `(flying, crashed)`: everything from `frame_id` to the opening of
    /// `cylinders`, the body box coloured by kind, or red when crashed.
    bodies: Vec<(String, String)>,
    /// Per sonar, its cone's orientation (`,"orientation":…},"size":`).
    orientations: [String; 4],
    /// Per cone colour (crosstalk, no echo, closer than the safety distance, echo), the end
    /// of the cone (`,"bottom_scale":…,"color":…}`).
    colors: [String; 4],
}

impl SceneText {
    fn new(copters: &[CopterInfo]) -> Self {
        let text = |f: &dyn Fn(&mut Json<'_>)| {
            let mut b = Vec::new();
            f(&mut Json(&mut b));
            String::from_utf8(b).unwrap_or_default()
        };
        let body = |info: &CopterInfo, color: [f32; 4]| {
            text(&|j| {
                j.raw(",\"frame_id\":").raw(&info.name_json).raw(",\"id\":").raw(&info.entity_id_json);
                j.raw(",\"lifetime\":{\"sec\":0,\"nsec\":0},\"frame_locked\":true,\"metadata\":[],\"arrows\":[]");
                j.raw(",\"cubes\":[{\"pose\":{\"position\":").xyz([0.0; 3]);
                j.raw(",\"orientation\":").xyzw([0.0, 0.0, 0.0, 1.0]);
                j.raw("},\"size\":").xyz(info.body_size_m).raw(",\"color\":").rgba(color).raw("}]");
                j.raw(",\"spheres\":[],\"cylinders\":[");
            })
        };
        let bodies = copters
            .iter()
            .map(|info| {
                let flying = match info.kind {
                    CopterKind::Real => [0.1, 0.6, 0.2, 1.0],
                    CopterKind::Virtual => [0.15, 0.35, 0.8, 1.0],
                };
                (body(info, flying), body(info, [0.85, 0.1, 0.1, 1.0]))
            })
            .collect();
        let orientations = std::array::from_fn(|k| {
            let q = SONAR_Z_TO_AXIS[k];
            text(&|j| {
                j.raw(",\"orientation\":").xyzw([q.x, q.y, q.z, q.w]).raw("},\"size\":");
            })
        });
        let palette = [[1.0, 0.55, 0.0, 0.45], [0.5, 0.5, 0.5, 0.06], [0.9, 0.2, 0.2, 0.3], [0.2, 0.6, 1.0, 0.2]];
        let colors = std::array::from_fn(|k| {
            text(&|j| {
                j.raw(",\"bottom_scale\":0.0,\"top_scale\":1.0,\"color\":").rgba(palette[k]).raw("}");
            })
        });
        Self { bodies, orientations, colors }
    }
}

/// The per-step `foxglove.SceneUpdate` of the copters: per copter its body box, coloured by
/// kind and status, and its four sonar cones, each as long as its fused reading and coloured
/// by what it sees; locked to the copter's frame.
fn copter_entities(j: &mut Json<'_>, text: &SceneText, frame: &StepFrame, g: SonarGeometry, lt: u64) {
    j.raw("{\"deletions\":[],\"entities\":[");
    for (i, ((flying, crashed), c)) in text.bodies.iter().zip(&frame.copters).enumerate() {
        j.raw(if i > 0 { ",{\"timestamp\":" } else { "{\"timestamp\":" }).time(lt);
        j.raw(if c.crash.is_some() { crashed } else { flying });
        let cones = c
            .sensors
            .sonar_fused_m
            .iter()
            .zip(&c.sensors.sonar_crosstalk)
            .zip(SONAR_AXES.iter().zip(&text.orientations));
        for (k, ((&reading, &crosstalk), (a, orientation))) in cones.enumerate() {
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
            j.raw(if k > 0 { ",{\"pose\":{\"position\":" } else { "{\"pose\":{\"position\":" });
            j.xyz([a[0] * d, a[1] * d, a[2] * d]).raw(orientation);
            j.xyz([width, width, len]).raw(&text.colors[color]);
        }
        j.raw("],\"lines\":[],\"triangles\":[],\"texts\":[],\"models\":[]}");
    }
    j.raw("]}");
}

#[cfg(test)]
#[path = "reference.rs"]
mod reference;
