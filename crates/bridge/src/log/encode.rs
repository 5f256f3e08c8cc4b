//! Turns captured steps, events and the static scene into JSON messages (sans I/O): each
//! message goes to a sink as `(topic, log_time_ns, bytes)`.

use serde::{Serialize, Serializer, ser::SerializeSeq};
use sim_core::control::FlightMode;
use sim_core::{CopterKind, Event, World};

use super::capture::{CopterSample, StepFrame};
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
}

impl EventKind {
    /// `foxglove.Log` level.
    fn level(self) -> u8 {
        match self {
            EventKind::TookOff | EventKind::Spawned | EventKind::Paired => 2,
            EventKind::InputRejected | EventKind::StepOverrun | EventKind::Interrupted => 3,
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
    entity_id: String,
    ac_id: Option<u8>,
    kind: CopterKind,
    body_size_m: V3,
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
            .map(|c| {
                let af = &world.airframes[c.airframe];
                let [bx, by, bz] = af.spec.body_size_m;
                CopterInfo {
                    name: c.name.clone(),
                    entity_id: format!("copter/{}", c.name),
                    ac_id: c.ac_id,
                    kind: c.kind,
                    body_size_m: v3(bx, by, bz),
                }
            })
            .collect();
        let s = &world.sensors.spec;
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
    /// per copter, one `/scene/copters` update, and the step's events.
    pub fn encode_step<E>(&mut self, frame: &StepFrame, sink: &mut impl Sink<E>) -> Result<(), E> {
        let tick = frame.tick;
        let lt = self.log_time(tick);
        let t_s = self.t_s(tick);
        let copters = std::mem::take(&mut self.copters);
        let result = (|| {
            for (id, (info, c)) in copters.iter().zip(&frame.copters).enumerate() {
                let name = info.name.as_str();
                let mode = c.command.mode;
                self.emit(Topic::State, lt, &state_msg(tick, t_s, id, info, c), sink)?;
                let r = &c.sensors;
                let sensors = SensorsMsg {
                    tick,
                    t_s,
                    copter: name,
                    id,
                    sonar_tick: r.sonar_tick,
                    sonar_truth_m: r.sonar_truth_m,
                    sonar_m: r.sonar_m,
                    sonar_fused_m: r.sonar_fused_m,
                    sonar_crosstalk: r.sonar_crosstalk,
                    ir_m: r.ir_m,
                    ir_truth_m: r.ir_truth_m.is_finite().then_some(r.ir_truth_m),
                    attitude_rad: r.attitude_rad,
                    yaw_bias_rad: r.yaw_bias_rad,
                    rate_body_rad_s: r.rate_body_rad_s,
                    accel_body_m_s2: r.accel_body_m_s2,
                };
                self.emit(Topic::Sensors, lt, &sensors, sink)?;
                let cmd = &c.command;
                let command = CommandMsg {
                    tick,
                    t_s,
                    copter: name,
                    id,
                    mode,
                    roll_rad: cmd.roll_rad,
                    pitch_rad: cmd.pitch_rad,
                    yaw_rad: cmd.yaw_rad,
                    throttle: cmd.throttle,
                    height_m: cmd.height_m,
                    target_m: cmd.target_m,
                    velocity_m_s: cmd.velocity_m_s,
                    virtual_sonar_m: cmd.virtual_sonar_m,
                };
                self.emit(Topic::Command, lt, &command, sink)?;
                let wa = &c.wall_avoid;
                let control = ControlMsg {
                    tick,
                    t_s,
                    copter: name,
                    id,
                    setpoint: &c.setpoint,
                    wall_avoid: WallAvoidMsg {
                        engaged: mode == FlightMode::WallAvoid && wa.out_rad != [0.0; 2],
                        out_rad: wa.out_rad,
                        last_m: wa.last_m,
                        rate_m_s: wa.rate_m_s,
                    },
                };
                self.emit(Topic::Control, lt, &control, sink)?;
                let p = &c.pose;
                let tf = FrameTransform {
                    timestamp: Time::from_ns(lt),
                    parent_frame_id: WORLD_FRAME,
                    child_frame_id: name,
                    translation: v3(p.pos_m.x, p.pos_m.y, p.pos_m.z),
                    rotation: Q { x: p.quat_xyzw[0], y: p.quat_xyzw[1], z: p.quat_xyzw[2], w: p.quat_xyzw[3] },
                };
                self.emit(Topic::Tf, lt, &tf, sink)?;
            }
            if tick.is_multiple_of(self.scene_every) {
                let update = SceneUpdate {
                    deletions: [],
                    entities: CopterEntities { copters: &copters, frame, sonar: self.sonar, time: Time::from_ns(lt) },
                };
                self.emit(Topic::SceneCopters, lt, &update, sink)?;
            }
            Ok(())
        })();
        self.copters = copters;
        result?;
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

fn state_msg<'a>(tick: u64, t_s: f64, id: usize, info: &'a CopterInfo, c: &'a CopterSample) -> StateMsg<'a> {
    let p = &c.pose;
    StateMsg {
        tick,
        t_s,
        copter: &info.name,
        id,
        ac_id: info.ac_id,
        kind: info.kind,
        mode: c.command.mode,
        crashed: c.crash.is_some(),
        crash_cause: c.crash.as_ref(),
        took_off: c.took_off_tick.is_some(),
        pos_m: p.pos_m.into(),
        vel_m_s: p.vel_m_s.into(),
        rpy_rad: p.rpy_rad,
        angvel_rad_s: p.angvel_rad_s.into(),
        quat_xyzw: p.quat_xyzw,
        rotor_thrust_n: c.rotor_thrust_n,
        rotor_speed_rad_s: c.rotor_speed_rad_s,
    }
}

/// The per-step copter entities, serialised on the fly (no allocation): body box coloured by
/// kind and status, and the four sonar cones, each as long as its fused reading.
struct CopterEntities<'a> {
    copters: &'a [CopterInfo],
    frame: &'a StepFrame,
    sonar: SonarGeometry,
    time: Time,
}

impl Serialize for CopterEntities<'_> {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut seq = s.serialize_seq(Some(self.copters.len()))?;
        for (info, c) in self.copters.iter().zip(&self.frame.copters) {
            let body_color = match (c.crash.is_some(), info.kind) {
                (true, _) => rgba(0.85, 0.1, 0.1, 1.0),
                (false, CopterKind::Real) => rgba(0.1, 0.6, 0.2, 1.0),
                (false, CopterKind::Virtual) => rgba(0.15, 0.35, 0.8, 1.0),
            };
            let cube = [Cube {
                pose: Pose { position: V3::default(), orientation: IDENTITY },
                size: info.body_size_m,
                color: body_color,
            }];
            let g = self.sonar;
            let cones: [Cylinder; 4] = std::array::from_fn(|k| {
                let reading = c.sensors.sonar_fused_m[k];
                let echo = reading < g.cap_m;
                let len = reading.clamp(g.min_m, g.cap_m);
                let color = if c.sensors.sonar_crosstalk[k] {
                    rgba(1.0, 0.55, 0.0, 0.45)
                } else if !echo {
                    rgba(0.5, 0.5, 0.5, 0.06)
                } else if reading < g.safety_m {
                    rgba(0.9, 0.2, 0.2, 0.3)
                } else {
                    rgba(0.2, 0.6, 1.0, 0.2)
                };
                let a = SONAR_AXES[k];
                let d = g.mount_offset_m + len / 2.0;
                let width = 2.0 * len * g.tan_half;
                Cylinder {
                    pose: Pose { position: v3(a[0] * d, a[1] * d, a[2] * d), orientation: SONAR_Z_TO_AXIS[k] },
                    size: v3(width, width, len),
                    bottom_scale: 0.0,
                    top_scale: 1.0,
                    color,
                }
            });
            seq.serialize_element(&Entity {
                timestamp: self.time,
                frame_id: &info.name,
                id: &info.entity_id,
                lifetime: FOREVER,
                frame_locked: true,
                metadata: &[],
                arrows: &[],
                cubes: &cube,
                spheres: [],
                cylinders: &cones,
                lines: &[],
                triangles: [],
                texts: &[],
                models: [],
            })?;
        }
        seq.end()
    }
}
