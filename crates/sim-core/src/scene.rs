//! The scene file: a TOML [`SceneSpec`] (serde, unknown fields rejected), its span-aware parsing,
//! and its compilation into an immutable [`World`].
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
use crate::airframe::{self, Airframe, AirframeSpec};
use crate::control::{Command, FlightMode};
pub use crate::error::{FieldPath, Location, PathSeg, SceneError};
use crate::math::{Real, Vec3};
use crate::sensors::SensorSpec;
use crate::world::{Arena, CopterDef, CopterKind, SimParams, StaticBox, World};

/// The embedded default scene: the original lab, a 4 m × 3 m arena with two FINkens.
pub const DEFAULT_SCENE_TOML: &str = include_str!("../../../assets/scenes/finken_lab.toml");
/// Name used in error messages for the embedded default scene.
pub const DEFAULT_SCENE_ORIGIN: &str = "<embedded finken_lab.toml>";

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
    pub fn from_toml(origin: &str, text: &str) -> Result<Self, SceneError> {
        toml::from_str::<SceneSpec>(text).map_err(|e| {
            let span = e.span();
            let (path, location) = match &span {
                Some(span) => (path_at(text, span), Some(line_col(text, span.start))),
                None => (FieldPath::default(), None),
            };
            SceneError::Syntax { origin: origin.into(), location, path, message: e.message().trim().to_owned() }
        })
    }

    /// Serialises the scene back to TOML.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|e| format!("# scene not serialisable: {e}"))
    }
}

/// Parses and compiles a scene, locating compile errors in `text`.
pub fn load(origin: &str, text: &str) -> Result<(SceneSpec, World), SceneError> {
    let spec = SceneSpec::from_toml(origin, text)?;
    match compile(&spec) {
        Ok(world) => Ok((spec, world)),
        Err(SceneError::Invalid { path, message, .. }) => {
            let location = span_of(text, &path).map(|s| line_col(text, s.start));
            Err(SceneError::Invalid { origin: origin.into(), location, path, message })
        }
        Err(e) => Err(e),
    }
}

/// Loads the embedded default scene.
pub fn load_default() -> (SceneSpec, World) {
    match load(DEFAULT_SCENE_ORIGIN, DEFAULT_SCENE_TOML) {
        Ok(v) => v,
        // The embedded scene is checked by a test; reaching this is a build defect.
        Err(e) => panic!("the embedded default scene is invalid: {e}"),
    }
}

fn finite(path: &FieldPath, values: &[Real]) -> Result<(), SceneError> {
    if let Some(v) = values.iter().find(|v| !v.is_finite()) {
        return Err(SceneError::invalid(path.clone(), format!("must be finite, got {v}")));
    }
    Ok(())
}

fn positive(path: &FieldPath, values: &[Real]) -> Result<(), SceneError> {
    finite(path, values)?;
    if let Some(v) = values.iter().find(|v| **v <= 0.0) {
        return Err(SceneError::invalid(path.clone(), format!("must be positive, got {v}")));
    }
    Ok(())
}

/// Compiles a scene into an immutable [`World`], checking that it makes sense.
pub fn compile(spec: &SceneSpec) -> Result<World, SceneError> {
    let root = FieldPath::default();
    // [sim]
    let sim = &spec.sim;
    let p = root.clone().key("sim");
    for (name, v) in
        [("physics_dt_s", sim.physics_dt_s), ("control_dt_s", sim.control_dt_s), ("duration_s", sim.duration_s)]
    {
        if !v.is_finite() || v <= 0.0 {
            return Err(SceneError::invalid(p.clone().key(name), format!("must be positive and finite, got {v}")));
        }
    }
    let ratio = sim.control_dt_s / sim.physics_dt_s;
    let substeps = ratio.round();
    if (ratio - substeps).abs() > 1e-6 || !(1.0..=10_000.0).contains(&substeps) {
        return Err(SceneError::invalid(
            p.clone().key("control_dt_s"),
            format!(
                "must be a whole multiple (1 to 10000) of physics_dt_s = {}, got {}",
                sim.physics_dt_s, sim.control_dt_s
            ),
        ));
    }
    if !(1..=256).contains(&sim.threads) {
        return Err(SceneError::invalid(p.clone().key("threads"), format!("must be 1 to 256, got {}", sim.threads)));
    }
    let params = SimParams {
        physics_dt_s: sim.physics_dt_s,
        control_dt_s: sim.control_dt_s,
        substeps: substeps as u32,
        seed: sim.seed,
        duration_s: sim.duration_s,
        threads: sim.threads,
        closed_form: sim.closed_form,
    };

    // [arena]
    let a = &spec.arena;
    let p = root.clone().key("arena");
    positive(&p.clone().key("size_m"), &a.size_m)?;
    positive(&p.clone().key("height_m"), &[a.height_m])?;
    positive(&p.clone().key("wall_thickness_m"), &[a.wall_thickness_m])?;
    let arena = Arena { size_m: a.size_m, height_m: a.height_m, walls: a.walls, wall_thickness_m: a.wall_thickness_m };

    // [[box]]
    let mut boxes = Vec::with_capacity(spec.boxes.len());
    let mut box_names = BTreeMap::new();
    for (i, b) in spec.boxes.iter().enumerate() {
        let p = root.clone().key("box").index(i);
        finite(&p.clone().key("pos_m"), &b.pos_m)?;
        finite(&p.clone().key("z_m"), &[b.z_m])?;
        finite(&p.clone().key("yaw_deg"), &[b.yaw_deg])?;
        positive(&p.clone().key("size_m"), &b.size_m)?;
        if let Some(name) = &b.name
            && let Some(prev) = box_names.insert(name.clone(), i)
        {
            return Err(SceneError::invalid(
                p.key("name"),
                format!("box name {name:?} is already used by box[{prev}]"),
            ));
        }
        let half = Vec3::new(b.size_m[0], b.size_m[1], b.size_m[2]) / 2.0;
        boxes.push(StaticBox {
            name: b.name.clone().unwrap_or_else(|| format!("box{i}")),
            center_m: Vec3::new(b.pos_m[0], b.pos_m[1], b.z_m + half.z),
            half_extents_m: half,
            yaw_rad: b.yaw_deg.to_radians(),
            virtual_only: b.virtual_only,
        });
    }

    // [airframes]
    let mut airframes: Vec<Airframe> = Vec::new();
    let mut airframe_index: BTreeMap<String, usize> = BTreeMap::new();
    for (name, af) in &spec.airframes {
        let p = root.clone().key("airframes").key(name);
        let derived = Airframe::derive(af).map_err(|e| SceneError::invalid(p.key(e.field), e.message))?;
        airframe_index.insert(name.clone(), airframes.len());
        airframes.push(derived);
    }

    // [[copter]]
    let mut cc = CopterCompiler {
        spec_airframes: &spec.airframes,
        arena: &arena,
        boxes: &boxes,
        airframes,
        airframe_index,
        names: BTreeMap::new(),
        ac_ids: BTreeMap::new(),
    };
    let mut copters: Vec<CopterDef> = Vec::with_capacity(spec.copters.len());
    // Start points hashed in 1 m cells: a new copter can only overlap copters within its
    // radius plus the largest radius so far, a few cells around it (O(N), not O(N²)).
    const CELL_M: Real = 1.0;
    let cell_of = |p: Vec3| ((p.x / CELL_M).floor() as i64, (p.y / CELL_M).floor() as i64);
    let mut cells: std::collections::HashMap<(i64, i64), Vec<usize>> = std::collections::HashMap::new();
    let mut max_r: Real = 0.0;
    for (i, c) in spec.copters.iter().enumerate() {
        let def = cc.compile(i, c, &[])?;
        let (pos, r) = (def.start_pos_m, cc.airframes[def.airframe].radius_m);
        let k = ((r + max_r) / CELL_M).ceil() as i64;
        let (cx, cy) = cell_of(pos);
        // The lowest id it overlaps, as a scan in id order would report.
        let overlap = (-k..=k)
            .flat_map(|dx| (-k..=k).map(move |dy| (cx + dx, cy + dy)))
            .filter_map(|cell| cells.get(&cell))
            .flatten()
            .copied()
            .filter(|&o| copters[o].start_pos_m.distance(pos) < r + cc.airframes[copters[o].airframe].radius_m)
            .min();
        if let Some(o) = overlap {
            let r_other = cc.airframes[copters[o].airframe].radius_m;
            return Err(SceneError::invalid(
                FieldPath::default().key("copter").index(i).key("start").key("pos_m"),
                format!(
                    "copter {:?} overlaps copter {:?}: centres {:.3} m apart, need at least {:.3} m",
                    c.name,
                    copters[o].name,
                    copters[o].start_pos_m.distance(pos),
                    r + r_other
                ),
            ));
        }
        cells.entry((cx, cy)).or_default().push(i);
        max_r = max_r.max(r);
        copters.push(def);
    }
    let airframes = cc.airframes;
    let sensors = spec.sensors.compile(&root.clone().key("sensors"))?;
    let airflow = spec.airflow.compile(&root.clone().key("airflow"))?;
    Ok(World {
        name: spec.name.clone(),
        params,
        arena,
        boxes,
        copter_shapes: crate::world::copter_shapes(&airframes),
        airframes,
        copters,
        sensors,
        airflow,
        spec: spec.clone(),
    })
}

/// Compiles `[[copter]]` tables one by one, tracking names, ac_ids and airframes.
struct CopterCompiler<'a> {
    spec_airframes: &'a BTreeMap<String, AirframeSpec>,
    arena: &'a Arena,
    boxes: &'a [StaticBox],
    airframes: Vec<Airframe>,
    airframe_index: BTreeMap<String, usize>,
    names: BTreeMap<String, usize>,
    ac_ids: BTreeMap<u8, usize>,
}

impl CopterCompiler<'_> {
    /// Compiles copter `i`; `occupied` lists where other copters are (name, centre, radius).
    fn compile(
        &mut self,
        i: usize,
        c: &CopterSpec,
        occupied: &[(String, Vec3, Real)],
    ) -> Result<CopterDef, SceneError> {
        let p = FieldPath::default().key("copter").index(i);
        if c.name.is_empty() || !c.name.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '_' || ch == '-') {
            return Err(SceneError::invalid(
                p.key("name"),
                format!(
                    "copter name {:?} must be non-empty ASCII letters, digits, '_' or '-' (it becomes a key expression)",
                    c.name
                ),
            ));
        }
        if let Some(prev) = self.names.insert(c.name.clone(), i) {
            return Err(SceneError::invalid(
                p.key("name"),
                format!("copter name {:?} is already used by copter[{prev}]", c.name),
            ));
        }
        if let Some(ac) = c.ac_id
            && let Some(prev) = self.ac_ids.insert(ac, i)
        {
            return Err(SceneError::invalid(p.key("ac_id"), format!("ac_id {ac} is already used by copter[{prev}]")));
        }
        let af_idx = match &c.airframe {
            AirframeRef::Named(name) => match self.airframe_index.get(name) {
                Some(idx) => *idx,
                None => {
                    let Some(preset) = airframe::preset(name) else {
                        let mut known: Vec<&str> = airframe::PRESETS.to_vec();
                        known.extend(self.spec_airframes.keys().map(String::as_str));
                        return Err(SceneError::invalid(
                            p.key("airframe"),
                            format!("unknown airframe {name:?}; known: {}", known.join(", ")),
                        ));
                    };
                    let derived = Airframe::derive(&preset)
                        .map_err(|e| SceneError::invalid(p.clone().key("airframe"), e.to_string()))?;
                    self.airframe_index.insert(name.clone(), self.airframes.len());
                    self.airframes.push(derived);
                    self.airframes.len() - 1
                }
            },
            AirframeRef::Inline(af) => {
                let derived = Airframe::derive(af)
                    .map_err(|e| SceneError::invalid(p.clone().key("airframe").key(e.field), e.message))?;
                self.airframes.push(derived);
                self.airframes.len() - 1
            }
        };
        let af = &self.airframes[af_idx];
        let sp = p.clone().key("start");
        finite(&sp.clone().key("pos_m"), &c.start.pos_m)?;
        finite(&sp.clone().key("yaw_deg"), &[c.start.yaw_deg])?;
        let z = match c.start.z_m {
            Some(z) => {
                finite(&sp.clone().key("z_m"), &[z])?;
                if z < af.rest_height_m - 1e-6 {
                    return Err(SceneError::invalid(
                        sp.key("z_m"),
                        format!(
                            "copter {:?} starts below the floor: z_m = {z} < rest height {:.3} m",
                            c.name, af.rest_height_m
                        ),
                    ));
                }
                z
            }
            None => af.rest_height_m,
        };
        let pos = Vec3::new(c.start.pos_m[0], c.start.pos_m[1], z);
        let r = af.radius_m;
        let (hx, hy) = (self.arena.size_m[0] / 2.0, self.arena.size_m[1] / 2.0);
        if pos.x.abs() + r > hx || pos.y.abs() + r > hy || z + af.rest_height_m > self.arena.height_m {
            return Err(SceneError::invalid(
                sp.key("pos_m"),
                format!(
                    "copter {:?} starts outside the arena: its {:.3} m footprint at ({}, {}, {z}) must fit in x ∈ [{}, {}], y ∈ [{}, {}], z ≤ {}",
                    c.name, r, pos.x, pos.y, -hx, hx, -hy, hy, self.arena.height_m
                ),
            ));
        }
        for b in self.boxes {
            if b.distance_to_point(pos) < r {
                return Err(SceneError::invalid(
                    sp.key("pos_m"),
                    format!("copter {:?} starts inside or touching box {:?}", c.name, b.name),
                ));
            }
        }
        for (other_name, other_pos, r_other) in occupied {
            if other_pos.distance(pos) < r + r_other {
                return Err(SceneError::invalid(
                    sp.key("pos_m"),
                    format!(
                        "copter {:?} overlaps copter {:?}: centres {:.3} m apart, need at least {:.3} m",
                        c.name,
                        other_name,
                        other_pos.distance(pos),
                        r + r_other
                    ),
                ));
            }
        }
        if c.kind == CopterKind::Autopilot && c.ac_id.is_none() {
            return Err(SceneError::invalid(
                p.clone().key("ac_id"),
                format!("copter {:?} is flown by an outside autopilot, which finds it by `ac_id`: set one", c.name),
            ));
        }
        // An outside autopilot commands the rotors; until its first command they are off.
        let mode = if c.kind == CopterKind::Autopilot { FlightMode::Rotors } else { c.mode };
        let command = compile_command(&p.clone().key("command"), mode, &c.command, c.start.yaw_deg.to_radians())?;
        Ok(CopterDef {
            name: c.name.clone(),
            kind: c.kind,
            ac_id: c.ac_id,
            airframe: af_idx,
            start_pos_m: pos,
            start_yaw_rad: c.start.yaw_deg.to_radians(),
            initial_command: command,
        })
    }
}

impl World {
    /// A new world with one more copter, spawned at runtime. The new copter must fit the arena,
    /// miss the boxes and keep clear of where the other copters are *now* (`state`).
    /// Its id is the new last one. Add its body with [`State::add_copter`](crate::State::add_copter).
    pub fn with_spawned(&self, state: &crate::State, spec: &CopterSpec) -> Result<World, SceneError> {
        let mut cc = CopterCompiler {
            spec_airframes: &self.spec.airframes,
            arena: &self.arena,
            boxes: &self.boxes,
            airframes: self.airframes.clone(),
            airframe_index: BTreeMap::new(),
            names: self.copters.iter().enumerate().map(|(i, c)| (c.name.clone(), i)).collect(),
            ac_ids: self.copters.iter().enumerate().filter_map(|(i, c)| c.ac_id.map(|a| (a, i))).collect(),
        };
        for name in self.spec.airframes.keys() {
            if let Some(idx) = self
                .copters
                .iter()
                .zip(&self.spec.copters)
                .find_map(|(d, s)| matches!(&s.airframe, AirframeRef::Named(n) if n == name).then_some(d.airframe))
            {
                cc.airframe_index.insert(name.clone(), idx);
            }
        }
        let occupied: Vec<(String, Vec3, Real)> = (0..self.copters.len())
            .map(|i| {
                (self.copters[i].name.clone(), state.pose(i).pos_m, self.airframes[self.copters[i].airframe].radius_m)
            })
            .collect();
        let id = self.copters.len();
        let def = cc.compile(id, spec, &occupied)?;
        let mut world = self.clone();
        world.airframes = cc.airframes;
        world.copter_shapes = crate::world::copter_shapes(&world.airframes);
        world.copters.push(def);
        world.spec.copters.push(spec.clone());
        Ok(world)
    }
}

fn compile_command(
    p: &FieldPath,
    mode: FlightMode,
    c: &CommandSpec,
    start_yaw_rad: Real,
) -> Result<Command, SceneError> {
    finite(&p.clone().key("roll_deg"), &[c.roll_deg])?;
    finite(&p.clone().key("pitch_deg"), &[c.pitch_deg])?;
    finite(&p.clone().key("height_m"), &[c.height_m])?;
    if let Some(y) = c.yaw_deg {
        finite(&p.clone().key("yaw_deg"), &[y])?;
    }
    if let Some(t) = c.throttle_pct {
        finite(&p.clone().key("throttle_pct"), &[t])?;
        if !(0.0..=100.0).contains(&t) {
            return Err(SceneError::invalid(p.clone().key("throttle_pct"), format!("must be in [0, 100], got {t}")));
        }
    }
    if c.height_m < 0.0 {
        return Err(SceneError::invalid(
            p.clone().key("height_m"),
            format!("must not be negative, got {}", c.height_m),
        ));
    }
    if let Some(t) = c.target_m {
        finite(&p.clone().key("target_m"), &t)?;
    }
    if let Some(v) = c.velocity_m_s {
        finite(&p.clone().key("velocity_m_s"), &v)?;
    }
    if mode == FlightMode::Target && c.target_m.is_none() {
        return Err(SceneError::invalid(p.clone().key("target_m"), "mode \"target\" needs command.target_m"));
    }
    Ok(Command {
        mode,
        roll_rad: c.roll_deg.to_radians(),
        pitch_rad: c.pitch_deg.to_radians(),
        yaw_rad: c.yaw_deg.map_or(start_yaw_rad, Real::to_radians),
        throttle: c.throttle_pct.map_or(0.0, |t| t / 100.0),
        height_m: c.height_m,
        target_m: c.target_m,
        velocity_m_s: c.velocity_m_s,
        virtual_sonar_m: None,
        rotors: None,
    })
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
