//! The JSON messages, as borrowed serde structs serialised straight into a reused buffer.
//! Field names match `crates/bridge/schemas/*.json` (and foxglove-sdk for `foxglove.*`).

use serde::Serialize;
use sim_core::control::FlightMode;
use sim_core::{CopterKind, CrashCause};

/// `twinswarm.CopterState`.
#[derive(Debug, Serialize)]
pub(crate) struct StateMsg<'a> {
    pub tick: u64,
    pub t_s: f64,
    pub copter: &'a str,
    pub id: usize,
    pub ac_id: Option<u8>,
    pub kind: CopterKind,
    pub mode: FlightMode,
    pub crashed: bool,
    pub crash_cause: Option<&'a CrashCause>,
    pub took_off: bool,
    pub pos_m: [f32; 3],
    pub vel_m_s: [f32; 3],
    pub rpy_rad: [f32; 3],
    pub angvel_rad_s: [f32; 3],
    pub quat_xyzw: [f32; 4],
    pub rotor_thrust_n: [f32; 4],
    pub rotor_speed_rad_s: [f32; 4],
}

/// `twinswarm.CopterSensors`.
#[derive(Debug, Serialize)]
pub(crate) struct SensorsMsg<'a> {
    pub tick: u64,
    pub t_s: f64,
    pub copter: &'a str,
    pub id: usize,
    pub sonar_tick: u64,
    pub sonar_truth_m: [f32; 4],
    pub sonar_m: [f32; 4],
    pub sonar_fused_m: [f32; 4],
    pub sonar_crosstalk: [bool; 4],
    pub ir_m: Option<f32>,
    pub ir_truth_m: Option<f32>,
    pub attitude_rad: [f32; 3],
    pub yaw_bias_rad: f32,
    pub rate_body_rad_s: [f32; 3],
    pub accel_body_m_s2: [f32; 3],
}

/// `twinswarm.CopterCommand`.
#[derive(Debug, Serialize)]
pub(crate) struct CommandMsg<'a> {
    pub tick: u64,
    pub t_s: f64,
    pub copter: &'a str,
    pub id: usize,
    pub mode: FlightMode,
    pub roll_rad: f32,
    pub pitch_rad: f32,
    pub yaw_rad: f32,
    pub throttle: f32,
    pub height_m: f32,
    pub target_m: Option<[f32; 3]>,
    pub velocity_m_s: Option<[f32; 2]>,
    pub virtual_sonar_m: Option<[f32; 4]>,
}

/// `twinswarm.CopterControl`.
#[derive(Debug, Serialize)]
pub(crate) struct ControlMsg<'a> {
    pub tick: u64,
    pub t_s: f64,
    pub copter: &'a str,
    pub id: usize,
    pub setpoint: &'a sim_core::Setpoint,
    pub wall_avoid: WallAvoidMsg,
}

#[derive(Debug, Serialize)]
pub(crate) struct WallAvoidMsg {
    pub engaged: bool,
    pub out_rad: [f32; 2],
    pub last_m: [f32; 4],
    pub rate_m_s: [f32; 4],
}

/// `twinswarm.Event`.
#[derive(Debug, Serialize)]
pub(crate) struct EventMsg<'a> {
    pub tick: u64,
    pub t_s: f64,
    pub kind: super::EventKind,
    pub copter: Option<&'a str>,
    pub id: Option<usize>,
    pub detail: Option<&'a serde_json::Value>,
    pub message: &'a str,
}

/// `twinswarm.BusMessage`.
#[derive(Debug, Serialize)]
pub(crate) struct BusMsg<'a> {
    pub tick: u64,
    pub key: &'a str,
    pub direction: &'a str,
    pub text: &'a str,
}

// ---- foxglove.* ----

/// `{sec, nsec}`.
#[derive(Clone, Copy, Debug, Serialize)]
pub(crate) struct Time {
    pub sec: u64,
    pub nsec: u32,
}

impl Time {
    pub fn from_ns(ns: u64) -> Self {
        Self { sec: ns / 1_000_000_000, nsec: (ns % 1_000_000_000) as u32 }
    }
}

#[derive(Clone, Copy, Debug, Serialize)]
pub(crate) struct Duration {
    pub sec: i32,
    pub nsec: u32,
}

pub(crate) const FOREVER: Duration = Duration { sec: 0, nsec: 0 };

#[derive(Clone, Copy, Debug, Default, Serialize)]
pub(crate) struct V3 {
    pub x: f32,
    pub y: f32,
    pub z: f32,
}

pub(crate) const fn v3(x: f32, y: f32, z: f32) -> V3 {
    V3 { x, y, z }
}

#[derive(Clone, Copy, Debug, Serialize)]
pub(crate) struct Q {
    pub x: f32,
    pub y: f32,
    pub z: f32,
    pub w: f32,
}

pub(crate) const IDENTITY: Q = Q { x: 0.0, y: 0.0, z: 0.0, w: 1.0 };

impl Q {
    /// Rotation about z by `yaw_rad`.
    pub fn yaw(yaw_rad: f32) -> Self {
        let (s, c) = (yaw_rad / 2.0).sin_cos();
        Q { x: 0.0, y: 0.0, z: s, w: c }
    }
}

#[derive(Clone, Copy, Debug, Serialize)]
pub(crate) struct Pose {
    pub position: V3,
    pub orientation: Q,
}

#[derive(Clone, Copy, Debug, Serialize)]
pub(crate) struct Color {
    pub r: f32,
    pub g: f32,
    pub b: f32,
    pub a: f32,
}

pub(crate) const fn rgba(r: f32, g: f32, b: f32, a: f32) -> Color {
    Color { r, g, b, a }
}

#[derive(Clone, Copy, Debug, Serialize)]
pub(crate) struct Cube {
    pub pose: Pose,
    pub size: V3,
    pub color: Color,
}

#[derive(Clone, Copy, Debug, Serialize)]
pub(crate) struct Cylinder {
    pub pose: Pose,
    pub size: V3,
    pub bottom_scale: f32,
    pub top_scale: f32,
    pub color: Color,
}

#[derive(Clone, Copy, Debug, Serialize)]
pub(crate) struct Arrow {
    pub pose: Pose,
    pub shaft_length: f32,
    pub shaft_diameter: f32,
    pub head_length: f32,
    pub head_diameter: f32,
    pub color: Color,
}

#[derive(Clone, Debug, Serialize)]
pub(crate) struct Line {
    /// 0 LINE_STRIP, 1 LINE_LOOP, 2 LINE_LIST.
    #[serde(rename = "type")]
    pub kind: u8,
    pub pose: Pose,
    pub thickness: f32,
    pub scale_invariant: bool,
    pub points: Vec<V3>,
    pub color: Color,
    pub colors: [Color; 0],
    pub indices: [u32; 0],
}

#[derive(Clone, Debug, Serialize)]
pub(crate) struct Text {
    pub pose: Pose,
    pub billboard: bool,
    pub font_size: f32,
    pub scale_invariant: bool,
    pub color: Color,
    pub text: String,
}

#[derive(Clone, Debug, Serialize)]
pub(crate) struct KeyValue {
    pub key: String,
    pub value: String,
}

/// `foxglove.SceneEntity`; every array is required by the schema, so the unused ones are
/// empty.
#[derive(Clone, Debug, Serialize)]
pub(crate) struct Entity<'a> {
    pub timestamp: Time,
    pub frame_id: &'a str,
    pub id: &'a str,
    pub lifetime: Duration,
    pub frame_locked: bool,
    pub metadata: &'a [KeyValue],
    pub arrows: &'a [Arrow],
    pub cubes: &'a [Cube],
    pub spheres: [u8; 0],
    pub cylinders: &'a [Cylinder],
    pub lines: &'a [Line],
    pub triangles: [u8; 0],
    pub texts: &'a [Text],
    pub models: [u8; 0],
}

/// `foxglove.SceneUpdate` with entities of any serialisable sequence.
#[derive(Debug, Serialize)]
pub(crate) struct SceneUpdate<E: Serialize> {
    pub deletions: [u8; 0],
    pub entities: E,
}

/// `foxglove.FrameTransform`.
#[derive(Debug, Serialize)]
pub(crate) struct FrameTransform<'a> {
    pub timestamp: Time,
    pub parent_frame_id: &'a str,
    pub child_frame_id: &'a str,
    pub translation: V3,
    pub rotation: Q,
}

/// `foxglove.Log`.
#[derive(Debug, Serialize)]
pub(crate) struct LogMsg<'a> {
    pub timestamp: Time,
    pub level: u8,
    pub message: &'a str,
    pub name: &'a str,
    pub file: &'a str,
    pub line: u32,
}
