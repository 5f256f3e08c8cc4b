//! The scene file: a TOML [`SceneSpec`] (serde, unknown fields rejected), its span-aware parsing,
//! and its compilation into an immutable [`crate::World`] (`compile.rs`).
//!
//! Errors point at the file, the line, the column and the field:
//! `scenes/lab.toml:14:9: copter[1].start.pos_m: copter "beta" starts outside the arena ...`.
//! Parsing takes the text, never a path: reading files is the caller's business.

use std::collections::BTreeMap;
use std::fmt;
use std::ops::Range;

use serde::de::{self, MapAccess, Visitor};
use serde::{Deserialize, Deserializer, Serialize};

use crate::airflow::AirflowSpec;
use crate::airframe::AirframeSpec;
use crate::control::FlightMode;
pub use crate::error::{FieldPath, Location, PathSeg, SceneError};
use crate::math::Real;
use crate::sensors::SensorSpec;

mod chunked;
mod compile;
pub use compile::{compile, load, load_default};

/// The embedded default scene: the original lab, a 4 m × 3 m arena with two FINkens.
pub const DEFAULT_SCENE_TOML: &str = include_str!("../../../../assets/scenes/finken_lab.toml");
/// Name used in error messages for the embedded default scene.
pub const DEFAULT_SCENE_ORIGIN: &str = "<embedded finken_lab.toml>";

/// Whether a copter exists only in the simulation or twins a real one.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CopterKind {
    /// Simulated only.
    #[default]
    Virtual,
    /// The virtual twin of a real copter, driven by its telemetry.
    Real,
    /// Flown by an autopilot outside the simulation (Paparazzi's, compiled for its simulator
    /// NPS) that commands its four rotors every step; Twinswarm's physics answers. It belongs to
    /// the real layer, as a real copter does: its own sonars and IR see the arena, the ordinary
    /// boxes, twins and other such copters, while virtual copters and `virtual_only` boxes reach
    /// it only through the virtual-sonar uplink (see [`crate::mixed`]).
    Autopilot,
}

impl CopterKind {
    /// Whether the copter is in the real layer (a twin, or flown by an outside autopilot): its
    /// sensors do not see what exists only in the simulation.
    pub fn is_real_layer(self) -> bool {
        self != CopterKind::Virtual
    }
}

/// A whole scene as written in TOML.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneSpec {
    /// Name of the world; the bridge uses it in key expressions.
    #[serde(default = "default_world_name")]
    pub name: String,
    /// Simulation parameters.
    #[serde(default)]
    pub sim: SimSpec,
    /// The arena: floor, height, walls.
    pub arena: ArenaSpec,
    /// Static boxes standing in the arena.
    #[serde(default, rename = "box")]
    pub boxes: Vec<BoxSpec>,
    /// Named airframes defined by this scene (FINken III defaults, overridden per field).
    #[serde(default)]
    pub airframes: BTreeMap<String, AirframeSpec>,
    /// Sensor models, shared by all copters.
    #[serde(default)]
    pub sensors: SensorSpec,
    /// Air between copters and surfaces: downwash and ground effect.
    #[serde(default)]
    pub airflow: AirflowSpec,
    /// The copters.
    #[serde(default, rename = "copter")]
    pub copters: Vec<CopterSpec>,
}

fn default_world_name() -> String {
    "lab".into()
}

/// `[sim]`: stepping parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimSpec {
    /// Physics step, s.
    pub physics_dt_s: f64,
    /// Control step, s: a whole multiple of the physics step.
    pub control_dt_s: f64,
    /// Seed of every random draw in the run.
    pub seed: u64,
    /// Default run length, s.
    pub duration_s: f64,
    /// Worker threads for one step (sensing, control and free flight run across copters in
    /// parallel and merge in id order): `1` (the default) steps on the caller's thread only.
    /// The results are the same bits for any value; only the wall-clock time changes.
    pub threads: usize,
    /// Copters that nothing can touch within a control step fly in closed form, and free
    /// flight meets the floor in closed form (take-off, landing, floor crashes); only contact
    /// candidates and wrecks go through Rapier. `false`: every copter goes through Rapier at
    /// every substep, the reference the closed form is tested against (slow).
    pub closed_form: bool,
}

impl Default for SimSpec {
    fn default() -> Self {
        Self { physics_dt_s: 0.005, control_dt_s: 0.05, seed: 1, duration_s: 90.0, threads: 1, closed_form: true }
    }
}

/// `[arena]`: the floor rectangle, centred on the origin, and its height.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArenaSpec {
    /// Floor size along x and y, m.
    pub size_m: [Real; 2],
    /// Height of the walls and of the ceiling, m.
    pub height_m: Real,
    /// Whether the four walls and the ceiling exist (the floor always does).
    #[serde(default = "yes")]
    pub walls: bool,
    /// Thickness of walls, floor and ceiling, m.
    #[serde(default = "default_wall_thickness")]
    pub wall_thickness_m: Real,
}

fn yes() -> bool {
    true
}
fn default_wall_thickness() -> Real {
    0.1
}

/// `[[box]]`: a static box.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoxSpec {
    /// Optional name, unique when given.
    #[serde(default)]
    pub name: Option<String>,
    /// Centre of the footprint on the floor (x, y), m.
    pub pos_m: [Real; 2],
    /// Height of the box's bottom above the floor, m.
    #[serde(default)]
    pub z_m: Real,
    /// Size along its own x, y, z, m.
    pub size_m: [Real; 3],
    /// Rotation about z, degrees counter-clockwise.
    #[serde(default)]
    pub yaw_deg: Real,
    /// Whether it exists only in the simulation, not in the real lab. Virtual copters and twins
    /// collide with every box; real copters learn of `virtual_only` boxes through their twin's
    /// virtual sonar readings (see [`crate::mixed`]), and a stand-in "reality" leaves them out.
    /// A copter flown by an outside autopilot passes through them and learns of them the same
    /// way.
    #[serde(default)]
    pub virtual_only: bool,
}

/// `[[copter]]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CopterSpec {
    /// Unique name.
    pub name: String,
    /// `virtual` (simulated only), `real` (a virtual twin driven by a real copter) or
    /// `autopilot` (flown by an outside autopilot, e.g. Paparazzi NPS; needs `ac_id`).
    #[serde(default)]
    pub kind: CopterKind,
    /// Paparazzi aircraft id, if it has one.
    #[serde(default)]
    pub ac_id: Option<u8>,
    /// A preset name (`"finken3"` or a key of `[airframes]`), or an inline table of overrides.
    #[serde(default)]
    pub airframe: AirframeRef,
    /// Start pose.
    pub start: StartSpec,
    /// Initial flight mode.
    #[serde(default)]
    pub mode: FlightMode,
    /// Initial commands.
    #[serde(default)]
    pub command: CommandSpec,
}

/// A copter's airframe: a named preset or inline parameters.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(untagged)]
pub enum AirframeRef {
    /// A built-in preset or one of the scene's `[airframes]`.
    Named(String),
    /// Inline parameters; fields not given keep FINken III values.
    Inline(Box<AirframeSpec>),
}

impl Default for AirframeRef {
    fn default() -> Self {
        AirframeRef::Named("finken3".into())
    }
}

impl<'de> Deserialize<'de> for AirframeRef {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = AirframeRef;
            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a preset name or a table of airframe parameters")
            }
            fn visit_str<E: de::Error>(self, v: &str) -> Result<AirframeRef, E> {
                Ok(AirframeRef::Named(v.to_owned()))
            }
            fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<AirframeRef, A::Error> {
                let spec = AirframeSpec::deserialize(de::value::MapAccessDeserializer::new(map))?;
                Ok(AirframeRef::Inline(Box::new(spec)))
            }
        }
        d.deserialize_any(V)
    }
}

/// A copter's start pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StartSpec {
    /// Position on the floor (x, y), m.
    pub pos_m: [Real; 2],
    /// Height of the centre of mass, m. Omitted: resting on the floor.
    #[serde(default)]
    pub z_m: Option<Real>,
    /// Heading, degrees counter-clockwise from +x.
    #[serde(default)]
    pub yaw_deg: Real,
}

/// Initial commands, in user units (degrees, percent).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct CommandSpec {
    /// Roll target, deg (> 0: right side down).
    pub roll_deg: Real,
    /// Pitch target, deg (> 0: nose down, flies forward).
    pub pitch_deg: Real,
    /// Yaw target, deg counter-clockwise from +x. Omitted: the start heading.
    pub yaw_deg: Option<Real>,
    /// Throttle, percent (50 = hover), used when no height is held.
    pub throttle_pct: Option<Real>,
    /// Height to hold, m; 0 or omitted: no height hold.
    pub height_m: Real,
    /// Target point for `target` mode, m.
    pub target_m: Option<[Real; 3]>,
    /// Velocity to follow when safe in `wall_avoid` mode, body frame (forward, left), m/s.
    pub velocity_m_s: Option<[Real; 2]>,
}

impl SceneSpec {
    /// Parses a scene from TOML text. `origin` names the text in errors (usually its path).
    /// A long text whose copters come last is parsed a chunk of copters at a time, with the
    /// same result, and an error in the same place (`chunked.rs`: the parser's tree of a
    /// 100,000-copter scene took 890 MB at once).
    pub fn from_toml(origin: &str, text: &str) -> Result<Self, SceneError> {
        if text.len() >= chunked::CHUNKED_FROM_BYTES
            && let Some(starts) = chunked::copter_headers(text)
        {
            return chunked::from_toml_chunked(origin, text, &starts, chunked::COPTERS_PER_CHUNK);
        }
        parse_whole(origin, text)
    }

    /// Serialises the scene back to TOML.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# scene not serialisable: {e}"))
    }
}

/// [`SceneSpec::from_toml`] in one parse of the whole text.
fn parse_whole(origin: &str, text: &str) -> Result<SceneSpec, SceneError> {
    toml::from_str::<SceneSpec>(text).map_err(|e| chunked::syntax_error(origin, text, 0, text, 0, &e))
}

/// Converts a byte offset into a 1-based line and column (in characters).
pub fn line_col(text: &str, offset: usize) -> Location {
    let offset = offset.min(text.len());
    let before = &text[..text.floor_char_boundary(offset)];
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
    Location { line, column: before[line_start..].chars().count() + 1 }
}

/// The span of the value at `path` (of its key, for tables), or of its deepest existing
/// ancestor.
pub fn span_of(text: &str, path: &FieldPath) -> Option<Range<usize>> {
    use toml::de::DeValue;
    let doc = toml::de::DeTable::parse(text).ok()?;
    let mut span = doc.span();
    let mut cur: &DeValue<'_> = &DeValue::Table(doc.into_inner());
    for seg in &path.0 {
        let next = match (seg, cur) {
            (PathSeg::Key(k), DeValue::Table(t)) => {
                t.iter().find(|(key, _)| key.get_ref() == k).map(|(key, v)| (key.span(), v))
            }
            (PathSeg::Index(i), DeValue::Array(arr)) => arr.get(*i).map(|v| (v.span(), v)),
            _ => None,
        };
        let Some((key_span, value)) = next else { break };
        let is_container = matches!(value.get_ref(), DeValue::Table(_))
            || matches!(value.get_ref(), DeValue::Array(a) if a.iter().any(|v| matches!(v.get_ref(), DeValue::Table(_))));
        span = if is_container && matches!(seg, PathSeg::Key(_)) { key_span } else { value.span() };
        cur = value.get_ref();
    }
    Some(span)
}

/// The path of the innermost field whose key or value contains `span`.
pub fn path_at(text: &str, span: &Range<usize>) -> FieldPath {
    use toml::de::DeValue;
    type Child<'a, 'i> = (PathSeg, Option<Range<usize>>, Range<usize>, &'a DeValue<'i>);
    fn contains(s: &Range<usize>, span: &Range<usize>) -> bool {
        s.start <= span.start && span.end <= s.end.max(s.start + 1)
    }
    fn walk(v: &DeValue<'_>, span: &Range<usize>, path: &mut Vec<PathSeg>) -> bool {
        let children: Vec<Child<'_, '_>> = match v {
            DeValue::Table(t) => t
                .iter()
                .map(|(k, v)| (PathSeg::Key(k.get_ref().to_string()), Some(k.span()), v.span(), v.get_ref()))
                .collect(),
            DeValue::Array(a) => {
                a.iter().enumerate().map(|(i, v)| (PathSeg::Index(i), None, v.span(), v.get_ref())).collect()
            }
            _ => return false,
        };
        // Depth first: a descendant containing the span wins over its container.
        for (seg, _, _, child) in &children {
            path.push(seg.clone());
            if walk(child, span, path) {
                return true;
            }
            path.pop();
        }
        for (seg, key_span, value_span, child) in &children {
            let table = matches!(child, DeValue::Table(_));
            if key_span.as_ref().is_some_and(|k| contains(k, span)) || (!table && contains(value_span, span)) {
                path.push(seg.clone());
                return true;
            }
        }
        // Last resort: a whole table (e.g. a missing field reported on its header).
        for (seg, _, value_span, _) in children {
            if contains(&value_span, span) || value_span.start == span.start {
                path.push(seg);
                return true;
            }
        }
        false
    }
    let mut path = Vec::new();
    if let Ok(doc) = toml::de::DeTable::parse(text) {
        walk(&DeValue::Table(doc.into_inner()), span, &mut path);
    }
    FieldPath(path)
}

/// A benchmark swarm: `n` FINkens on a square grid `spacing_m` apart, each holding its own
/// start point at `height_m` in [`FlightMode::Target`] mode, in an arena grown with `n` to keep
/// the density. Sensors on or off.
pub fn grid_swarm(n: usize, spacing_m: Real, height_m: Real, sensors: bool) -> SceneSpec {
    let cols = (n as f64).sqrt().ceil().max(1.0) as usize;
    let rows = n.div_ceil(cols).max(1);
    let size = [cols as Real * spacing_m, rows as Real * spacing_m];
    let copters = (0..n)
        .map(|i| {
            let (cx, cy) = ((i % cols) as Real, (i / cols) as Real);
            let x = -size[0] / 2.0 + (cx + 0.5) * spacing_m;
            let y = -size[1] / 2.0 + (cy + 0.5) * spacing_m;
            CopterSpec {
                name: format!("c{i}"),
                kind: CopterKind::Virtual,
                ac_id: None,
                airframe: AirframeRef::default(),
                start: StartSpec { pos_m: [x, y], z_m: Some(height_m), yaw_deg: 0.0 },
                mode: FlightMode::Target,
                command: CommandSpec { height_m, target_m: Some([x, y, height_m]), ..CommandSpec::default() },
            }
        })
        .collect();
    SceneSpec {
        name: "swarm".into(),
        sim: SimSpec::default(),
        arena: ArenaSpec { size_m: size, height_m: 2.5, walls: true, wall_thickness_m: 0.1 },
        boxes: Vec::new(),
        airframes: BTreeMap::new(),
        sensors: SensorSpec { enabled: sensors, ..SensorSpec::default() },
        airflow: AirflowSpec::default(),
        copters,
    }
}

/// An experiment-like swarm, the scene of the real-time issue and of `pybullet`'s peer: `n`
/// FINkens on a square grid `spacing_m` apart in an arena 2 m wider on each side, flying
/// Wall-Avoid at 1 m and 0.3 m/s forward (headings spread by the golden angle), with
/// `n_boxes` pillars (0.5–2 m high, at most 0.45 m wide) placed at random grid-cell corners,
/// so never on a copter. `takeoff`: the copters start on the floor, else in the air at 1 m.
/// The pillars' placement comes from `seed`.
pub fn dense_swarm(n: usize, spacing_m: Real, takeoff: bool, n_boxes: usize, seed: u64) -> SceneSpec {
    let mut spec = cruising_swarm(n, 1);
    let cols = (n as f64).sqrt().ceil().max(1.0) as usize;
    let rows = n.div_ceil(cols).max(1);
    let margin = 2.0;
    spec.name = "dense_swarm".into();
    spec.sim.seed = seed;
    spec.sim.duration_s = 60.0;
    spec.arena.size_m = [cols as Real * spacing_m + 2.0 * margin, rows as Real * spacing_m + 2.0 * margin];
    spec.arena.height_m = 3.0;
    let x0 = -(cols as Real - 1.0) * spacing_m / 2.0;
    let y0 = -(rows as Real - 1.0) * spacing_m / 2.0;
    for (i, c) in spec.copters.iter_mut().enumerate() {
        let (cx, cy) = ((i % cols) as Real, (i / cols) as Real);
        c.start.pos_m = [x0 + cx * spacing_m, y0 + cy * spacing_m];
        c.start.z_m = if takeoff { None } else { Some(1.0) };
        c.command.height_m = 1.0;
    }
    let mut rng = crate::rng::Rng32::new(seed, u64::MAX);
    let half = (0.15 * spacing_m).min(0.225);
    spec.boxes = (0..n_boxes)
        .map(|k| {
            let i = ((rng.uniform() * (cols.max(2) - 1) as Real) as usize).min(cols.saturating_sub(2));
            let j = ((rng.uniform() * (rows.max(2) - 1) as Real) as usize).min(rows.saturating_sub(2));
            let h = 0.5 + 1.5 * rng.uniform();
            BoxSpec {
                name: Some(format!("pillar{k}")),
                pos_m: [x0 + (i as Real + 0.5) * spacing_m, y0 + (j as Real + 0.5) * spacing_m],
                z_m: 0.0,
                size_m: [2.0 * half, 2.0 * half, h],
                yaw_deg: 0.0,
                virtual_only: false,
            }
        })
        .collect();
    spec
}

/// [`dense_swarm`]'s take-off (1.5 m grid) among ten boxes of several sizes, heights and yaws
/// placed from `seed` instead of its pillars; copters that would start on or beside a box are
/// left out. The sharding checks' scene with boxes (`examples/shard_bits`, `tests/shard.rs`).
pub fn boxes_swarm(n: usize, seed: u64) -> SceneSpec {
    let mut spec = dense_swarm(n, 1.5, true, 0, seed);
    spec.name = "boxes_swarm".into();
    let [w, d] = spec.arena.size_m;
    let mut rng = crate::rng::Rng32::new(seed, 7);
    spec.boxes = (0..10)
        .map(|k| BoxSpec {
            name: Some(format!("box{k}")),
            pos_m: [(rng.uniform() - 0.5) * (w - 4.0), (rng.uniform() - 0.5) * (d - 4.0)],
            z_m: 0.0,
            size_m: [0.2 + 1.3 * rng.uniform(), 0.2 + 0.8 * rng.uniform(), 0.3 + 2.0 * rng.uniform()],
            yaw_deg: 90.0 * rng.uniform(),
            virtual_only: false,
        })
        .collect();
    let boxes = spec.boxes.clone();
    spec.copters.retain(|c| {
        boxes.iter().all(|b| {
            let r = 0.5 * b.size_m[0].hypot(b.size_m[1]) + 0.4;
            (c.start.pos_m[0] - b.pos_m[0]).hypot(c.start.pos_m[1] - b.pos_m[1]) > r
        })
    });
    spec
}

/// A flock crossing the hall: `n` copters on a 4 m grid in the air, all heading +x at
/// 0.3 m/s (Wall-Avoid at 1 m), starting 10 m left of centre in a hall 42 m wider and 22 m
/// deeper than the grid's [`dense_swarm`] arena. Over a minute the flock drifts about 18 m across
/// any split of the arena: the scene of the sharding tests.
pub fn flock_swarm(n: usize, seed: u64) -> SceneSpec {
    let mut spec = dense_swarm(n, 4.0, false, 0, seed);
    spec.name = "flock".into();
    spec.arena.size_m = [spec.arena.size_m[0] + 42.0, spec.arena.size_m[1] + 22.0];
    for c in &mut spec.copters {
        c.start.pos_m[0] -= 10.0;
        c.start.yaw_deg = 0.0;
        c.command.yaw_deg = Some(0.0);
    }
    spec
}

/// [`grid_swarm`] with sensors, every copter flying Wall-Avoid at 0.3 m/s forward, headings
/// spread by the golden angle, on `threads` threads: the swarm of the real-time benchmark and
/// of the allocation and thread tests.
pub fn cruising_swarm(n: usize, threads: usize) -> SceneSpec {
    let mut spec = grid_swarm(n, 2.0, 0.8, true);
    spec.sim.threads = threads;
    for (i, c) in spec.copters.iter_mut().enumerate() {
        c.mode = FlightMode::WallAvoid;
        c.start.yaw_deg = (i as Real * 137.508) % 360.0;
        c.command.target_m = None;
        c.command.yaw_deg = Some(c.start.yaw_deg);
        c.command.velocity_m_s = Some([0.3, 0.0]);
    }
    spec
}
