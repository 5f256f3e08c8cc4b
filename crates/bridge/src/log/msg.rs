//! The JSON messages written with serde: events, bus traffic and the static scene. The
//! per-step messages are written by hand (`encode.rs`, `json.rs`); their serde reference
//! structs live in `reference.rs`, for the tests.
//! Field names match `crates/bridge/schemas/*.json` (and foxglove-sdk for `foxglove.*`).

use serde::Serialize;

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
