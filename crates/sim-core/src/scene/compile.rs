//! A scene's compilation into an immutable [`World`], checking that it makes sense, and its
//! loading from TOML text with the errors located in the text.

use std::collections::BTreeMap;

use super::{
    AirframeRef, CommandSpec, CopterKind, CopterSpec, DEFAULT_SCENE_ORIGIN, DEFAULT_SCENE_TOML, SceneSpec, line_col,
    span_of,
};
use crate::airframe::{self, Airframe, AirframeSpec};
use crate::control::{Command, FlightMode};
use crate::error::{FieldPath, SceneError};
use crate::math::{Real, Vec3};
use crate::world::{Arena, CopterDef, SimParams, StaticBox, World};

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
