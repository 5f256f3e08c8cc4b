//! The pairing file: which Paparazzi aircraft is twinned with which scene
//! copter, which copters are purely virtual, and what to do with aircraft
//! nobody mentioned. It replaces the XML configuration of the original
//! copter-management component (paper, section VI-A.1).
//!
//! # Format (Twinswarm's own; strict: unknown elements and attributes are errors)
//!
//! ```xml
//! <pairing version="1">
//!   <!-- Paparazzi conf.xml, relative to this file's directory -->
//!   <conf path="../paparazzi/conf.xml"/>
//!   <!-- a real aircraft, by name or by ac_id, and its twin in the scene -->
//!   <twin aircraft="FINken_01" copter="finken_01" x_m="1.0" y_m="1.0" z_m="0" yaw_deg="0"/>
//!   <twin ac_id="6" copter="finken_02" x_m="3.0" y_m="1.0" z_m="0" yaw_deg="90"/>
//!   <!-- an aircraft whose autopilot (Paparazzi NPS) flies its copter in the simulation -->
//!   <twin aircraft="FINken_NPS" copter="finken_nps" flown_by="autopilot" x_m="0" y_m="0" z_m="0" yaw_deg="0"/>
//!   <!-- a copter that exists only in the simulation; seen by the GCS as ac_id 101 -->
//!   <virtual name="Virtual_01" ac_id="101" x_m="2.0" y_m="2.0" z_m="0" yaw_deg="180"/>
//!   <!-- where unknown real aircraft appear when policy="spawn" -->
//!   <spawn x_m="0.5" y_m="0.5" z_m="0" yaw_deg="0" spacing_m="0.5"/>
//!   <unknown_aircraft policy="ignore"/>
//! </pairing>
//! ```
//!
//! * `<conf path>` (required, once): the Paparazzi `conf.xml`.
//! * `<twin>`: exactly one of `aircraft` (name in conf.xml) or `ac_id`;
//!   `copter` is the scene copter's name; the pose is required. `flown_by`: `telemetry`
//!   (default: a real copter's telemetry drives the twin) or `autopilot` (the aircraft is
//!   Paparazzi's autopilot in NPS with Twinswarm's flight model: it flies the copter of kind
//!   `autopilot` itself, and its telemetry drives nothing; see `crate::autopilot`).
//! * `<virtual>`: `name` (also the scene copter's name) and `ac_id` (the
//!   Ivy sender it uses towards the ground station); the pose is optional
//!   and defaults to the spawn point.
//! * `<spawn>` (optional, once; required by `policy="spawn"` and by virtual
//!   copters without a pose): the spawn pose. The k-th automatically spawned
//!   copter (k = 0, 1, ...) is placed `k × spacing_m` (default 0.5 m) along
//!   the spawn pose's +y axis.
//! * `<unknown_aircraft policy>` (optional): what to do with telemetry from
//!   an `ac_id` that is **not in conf.xml**: `ignore` (default; the runtime
//!   counts such messages, see [`UnknownAircraftStats`]) or `spawn` (create a
//!   twin named `ac_<id>` at the spawn point).
//!
//! **Automatic spawn.** A *real* aircraft of conf.xml that no `<twin>` names
//! gets its twin at the spawn point (named after the aircraft, lower case) on
//! its first telemetry message, whatever the policy; without a `<spawn>`
//! point its messages are dropped and counted. An aircraft whose name marks
//! it virtual (`Virtual…`) but which is not one of our `<virtual>` copters is
//! someone else's simulation: its messages are dropped and counted.
//!
//! Poses are in the scene's world frame: metres, right-handed, z up; yaw in
//! degrees in the file (user-facing), counter-clockwise about +z from +x,
//! stored in radians.
//!
//! Parsing checks the file on its own ([`Pairing::parse`]); cross-checks
//! against the conf.xml are done by [`Pairing::resolve`]. Both report errors
//! with the pairing file's line numbers.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::ids::AcId;
use crate::paparazzi::conf::{AircraftKind, ConfXml};
use crate::paparazzi::xml::{Doc, Element, Location, XmlError};

/// A pose in the scene's world frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Pose {
    /// x, metres.
    pub x_m: f64,
    /// y, metres.
    pub y_m: f64,
    /// z (up), metres.
    pub z_m: f64,
    /// Yaw about +z, radians, counter-clockwise from +x.
    pub yaw_rad: f64,
}

/// How a twin names its aircraft.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum AircraftRef {
    /// By `name` in conf.xml.
    Name(String),
    /// By `ac_id`.
    AcId(AcId),
}

/// One `<twin>`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Twin {
    /// The real aircraft.
    pub aircraft: AircraftRef,
    /// Scene copter name.
    pub copter: String,
    /// Spawn pose of the twin.
    pub pose: Pose,
    /// Flown by the aircraft's own autopilot in the simulation (`flown_by="autopilot"`).
    pub autopilot: bool,
    /// Line in the pairing file.
    pub source_line: u32,
}

/// One `<virtual>` copter.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct VirtualCopter {
    /// Name (aircraft name towards the GCS and scene copter name).
    pub name: String,
    /// Ivy sender id.
    pub ac_id: AcId,
    /// Spawn pose, if given (otherwise the spawn point).
    pub pose: Option<Pose>,
    /// Line in the pairing file.
    pub source_line: u32,
}

/// The `<spawn>` point.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SpawnPoint {
    /// Pose of the first spawned copter.
    pub pose: Pose,
    /// Offset between successive spawns along the pose's +y axis, metres.
    pub spacing_m: f64,
}

impl SpawnPoint {
    /// Pose of the `k`-th automatically spawned copter.
    pub fn pose_for(&self, k: u32) -> Pose {
        let d = self.spacing_m * f64::from(k);
        let (s, c) = self.pose.yaw_rad.sin_cos();
        Pose { x_m: self.pose.x_m - s * d, y_m: self.pose.y_m + c * d, ..self.pose }
    }
}

/// What to do with an `ac_id` that is neither twinned nor virtual.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum UnknownAircraftPolicy {
    /// Drop its messages (and count them).
    #[default]
    Ignore,
    /// Spawn a twin at the spawn point.
    Spawn,
}

/// A parsed pairing file.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Pairing {
    /// File label given at parse time.
    pub source: String,
    /// `<conf path>` as written.
    pub conf_path: String,
    /// Twins in file order.
    pub twins: Vec<Twin>,
    /// Virtual copters in file order.
    pub virtual_copters: Vec<VirtualCopter>,
    /// Spawn point, if any.
    pub spawn: Option<SpawnPoint>,
    /// Policy for unknown aircraft.
    pub unknown_policy: UnknownAircraftPolicy,
}

/// One aircraft id's role after [`Pairing::resolve`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Assignment {
    /// Aircraft id.
    pub ac_id: AcId,
    /// Real (twinned) or virtual.
    pub kind: AircraftKind,
    /// Aircraft name (from conf.xml, or the virtual copter's name).
    pub aircraft_name: Option<String>,
    /// Scene copter name.
    pub copter: String,
    /// Spawn pose.
    pub pose: Pose,
    /// A real aircraft's autopilot flies the copter (`flown_by="autopilot"`).
    pub autopilot: bool,
}

/// What the bridge does with messages from one aircraft id.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub enum Route<'a> {
    /// Twinned or virtual.
    Assigned(&'a Assignment),
    /// Dropped (and counted).
    Ignore,
    /// Not twinned yet: spawn a twin (the runtime chooses the spawn index).
    Spawn {
        /// Where.
        point: SpawnPoint,
        /// The aircraft's name in conf.xml; `None` for an `ac_id` not in conf.xml.
        aircraft: Option<&'a str>,
    },
}

/// The pairing checked against a conf.xml: roles by aircraft id.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ResolvedPairing {
    /// Roles, sorted by aircraft id.
    pub by_ac_id: BTreeMap<AcId, Assignment>,
    /// Policy for unknown aircraft.
    pub unknown_policy: UnknownAircraftPolicy,
    /// Spawn point, if any.
    pub spawn: Option<SpawnPoint>,
    /// Aircraft of conf.xml that are not assigned, by id: name and kind by name.
    pub unassigned: BTreeMap<AcId, (String, AircraftKind)>,
}

impl ResolvedPairing {
    /// The route for messages from `ac_id` (see the module docs).
    pub fn route(&self, ac_id: AcId) -> Route<'_> {
        if let Some(a) = self.by_ac_id.get(&ac_id) {
            return Route::Assigned(a);
        }
        match (self.unassigned.get(&ac_id), self.spawn) {
            (Some((_, AircraftKind::Virtual)), _) | (Some(_), None) => Route::Ignore,
            (Some((name, AircraftKind::Real)), Some(point)) => Route::Spawn { point, aircraft: Some(name) },
            (None, Some(point)) if self.unknown_policy == UnknownAircraftPolicy::Spawn => {
                Route::Spawn { point, aircraft: None }
            }
            (None, _) => Route::Ignore,
        }
    }
}

/// Counts of messages dropped per unknown aircraft id (for the `ignore`
/// policy), in id order.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct UnknownAircraftStats {
    /// Dropped messages per aircraft id.
    pub dropped_by_ac_id: BTreeMap<AcId, u64>,
}

impl UnknownAircraftStats {
    /// Records one dropped message from `ac_id`.
    pub fn record(&mut self, ac_id: AcId) {
        *self.dropped_by_ac_id.entry(ac_id).or_insert(0) += 1;
    }

    /// Total dropped messages.
    pub fn total(&self) -> u64 {
        self.dropped_by_ac_id.values().sum()
    }
}

const POSE_ATTRS: [&str; 4] = ["x_m", "y_m", "z_m", "yaw_deg"];

fn parse_pose(doc: &Doc, el: &Element, required: bool) -> Result<Option<Pose>, XmlError> {
    let present = POSE_ATTRS.iter().filter(|k| doc.attr(el, k).is_some()).count();
    if present == 0 && !required {
        return Ok(None);
    }
    let mut v = [0.0_f64; 4];
    for (slot, key) in v.iter_mut().zip(POSE_ATTRS) {
        let a = doc.req_attr(el, key)?;
        *slot = doc.parse_f64_attr(el, a)?;
    }
    Ok(Some(Pose { x_m: v[0], y_m: v[1], z_m: v[2], yaw_rad: v[3].to_radians() }))
}

fn non_empty_name(doc: &Doc, el: &Element, key: &str) -> Result<String, XmlError> {
    let a = doc.req_attr(el, key)?;
    let v = a.value.trim();
    if v.is_empty() || v.contains(['/', '*', '$', '?', '#']) || v.chars().any(char::is_whitespace) {
        return Err(doc.bad_attr(el, a, "expected a non-empty name without whitespace or any of / * $ ? #"));
    }
    Ok(v.to_owned())
}

/// Fails if an element that may appear once already has (`first`: the line it first did).
fn once(doc: &Doc, what: &str, first: Option<u32>, el: &Element) -> Result<(), XmlError> {
    match first {
        Some(line) => Err(doc.invalid(el.offset, format!("<{what}> may appear only once (first at line {line})"))),
        None => Ok(()),
    }
}

/// What a pairing file's elements have given so far, each with the line it came from, and the
/// names and ids they have taken.
#[derive(Default)]
struct PairingParts {
    conf_path: Option<(String, u32)>,
    twins: Vec<Twin>,
    virtual_copters: Vec<VirtualCopter>,
    spawn: Option<(SpawnPoint, u32)>,
    policy: Option<(UnknownAircraftPolicy, u32)>,
    /// copter name -> first line, across twins and virtual copters
    copters: BTreeMap<String, u32>,
    ac_ids: BTreeMap<AcId, u32>,
    aircraft_names: BTreeMap<String, u32>,
}

impl PairingParts {
    /// `<conf path="..."/>`, once.
    fn conf(&mut self, doc: &Doc, el: &Element, line: u32) -> Result<(), XmlError> {
        once(doc, "conf", self.conf_path.as_ref().map(|c| c.1), el)?;
        doc.only_attrs(el, &["path"])?;
        let p = doc.req_attr(el, "path")?;
        if p.value.trim().is_empty() {
            return Err(doc.bad_attr(el, p, "path is empty"));
        }
        self.conf_path = Some((p.value.trim().to_owned(), line));
        Ok(())
    }

    /// `<twin>`: a real aircraft (by name or id), its copter's name, pose and who flies it.
    fn twin(&mut self, doc: &Doc, el: &Element, line: u32) -> Result<(), XmlError> {
        doc.only_attrs(el, &["aircraft", "ac_id", "copter", "x_m", "y_m", "z_m", "yaw_deg", "flown_by"])?;
        let autopilot = match doc.attr(el, "flown_by").map(|a| a.value.as_str()) {
            None | Some("telemetry") => false,
            Some("autopilot") => true,
            Some(other) => {
                return Err(
                    doc.invalid(el.offset, format!("flown_by must be `telemetry` or `autopilot`, not `{other}`"))
                );
            }
        };
        let aircraft = self.twinned_aircraft(doc, el, line)?;
        let copter = non_empty_name(doc, el, "copter")?;
        if let Some(first) = self.copters.insert(copter.clone(), line) {
            return Err(XmlError::Duplicate {
                at: doc.loc(el.offset),
                what: "copter name",
                name: copter,
                first_line: first,
            });
        }
        let pose = parse_pose(doc, el, true)?.ok_or_else(|| doc.invalid(el.offset, "<twin> needs a pose"))?;
        self.twins.push(Twin { aircraft, copter, pose, autopilot, source_line: line });
        Ok(())
    }

    /// A `<twin>`'s aircraft: exactly one of `aircraft` (a name) or `ac_id`, neither taken yet.
    fn twinned_aircraft(&mut self, doc: &Doc, el: &Element, line: u32) -> Result<AircraftRef, XmlError> {
        match (doc.attr(el, "aircraft"), doc.attr(el, "ac_id")) {
            (Some(_), Some(_)) | (None, None) => {
                Err(doc.invalid(el.offset, "<twin> needs exactly one of `aircraft` (name) or `ac_id`"))
            }
            (Some(_), None) => {
                let n = non_empty_name(doc, el, "aircraft")?;
                if let Some(first) = self.aircraft_names.insert(n.clone(), line) {
                    return Err(XmlError::Duplicate {
                        at: doc.loc(el.offset),
                        what: "twinned aircraft",
                        name: n,
                        first_line: first,
                    });
                }
                Ok(AircraftRef::Name(n))
            }
            (None, Some(a)) => {
                let id: AcId = doc.parse_attr(el, a, "an aircraft id 0..255")?;
                if let Some(first) = self.ac_ids.insert(id, line) {
                    return Err(XmlError::Duplicate {
                        at: doc.loc(a.offset),
                        what: "ac_id",
                        name: id.to_string(),
                        first_line: first,
                    });
                }
                Ok(AircraftRef::AcId(id))
            }
        }
    }

    /// `<virtual>`: a purely virtual copter's name, aircraft id and (optional) pose.
    fn virtual_copter(&mut self, doc: &Doc, el: &Element, line: u32) -> Result<(), XmlError> {
        doc.only_attrs(el, &["name", "ac_id", "x_m", "y_m", "z_m", "yaw_deg"])?;
        let name = non_empty_name(doc, el, "name")?;
        let a = doc.req_attr(el, "ac_id")?;
        let ac_id: AcId = doc.parse_attr(el, a, "an aircraft id 0..255")?;
        if let Some(first) = self.ac_ids.insert(ac_id, line) {
            return Err(XmlError::Duplicate {
                at: doc.loc(a.offset),
                what: "ac_id",
                name: ac_id.to_string(),
                first_line: first,
            });
        }
        if let Some(first) = self.copters.insert(name.clone(), line) {
            return Err(XmlError::Duplicate { at: doc.loc(el.offset), what: "copter name", name, first_line: first });
        }
        let pose = parse_pose(doc, el, false)?;
        self.virtual_copters.push(VirtualCopter { name, ac_id, pose, source_line: line });
        Ok(())
    }

    /// `<spawn>`, once: where spawned copters appear, and how far apart (default 0.5 m).
    fn spawn(&mut self, doc: &Doc, el: &Element, line: u32) -> Result<(), XmlError> {
        once(doc, "spawn", self.spawn.as_ref().map(|s| s.1), el)?;
        doc.only_attrs(el, &["x_m", "y_m", "z_m", "yaw_deg", "spacing_m"])?;
        let pose = parse_pose(doc, el, true)?.ok_or_else(|| doc.invalid(el.offset, "<spawn> needs a pose"))?;
        let spacing_m = match doc.attr(el, "spacing_m") {
            Some(a) => {
                let v = doc.parse_f64_attr(el, a)?;
                if v < 0.0 {
                    return Err(doc.bad_attr(el, a, "spacing must not be negative"));
                }
                v
            }
            None => 0.5,
        };
        self.spawn = Some((SpawnPoint { pose, spacing_m }, line));
        Ok(())
    }

    /// `<unknown_aircraft policy="ignore|spawn"/>`, once.
    fn unknown_aircraft(&mut self, doc: &Doc, el: &Element, line: u32) -> Result<(), XmlError> {
        once(doc, "unknown_aircraft", self.policy.as_ref().map(|p| p.1), el)?;
        doc.only_attrs(el, &["policy"])?;
        let a = doc.req_attr(el, "policy")?;
        let p = match a.value.trim() {
            "ignore" => UnknownAircraftPolicy::Ignore,
            "spawn" => UnknownAircraftPolicy::Spawn,
            _ => return Err(doc.bad_attr(el, a, "expected `ignore` or `spawn`")),
        };
        self.policy = Some((p, line));
        Ok(())
    }

    /// The pairing, once every element is read: a `<conf>` is required, and a spawn policy or
    /// a virtual copter without a pose needs a `<spawn>` point.
    fn finish(self, doc: &Doc, root: &Element, source: &str) -> Result<Pairing, XmlError> {
        let Some((conf_path, _)) = self.conf_path else {
            return Err(doc.invalid(root.offset, "<pairing> needs a <conf path=\"...\"/> element"));
        };
        let unknown_policy = self.policy.map(|p| p.0).unwrap_or_default();
        let spawn = self.spawn.map(|s| s.0);
        if unknown_policy == UnknownAircraftPolicy::Spawn && spawn.is_none() {
            return Err(doc.invalid(root.offset, "policy=\"spawn\" needs a <spawn> point"));
        }
        let virtual_copters = self.virtual_copters;
        if spawn.is_none()
            && let Some(v) = virtual_copters.iter().find(|v| v.pose.is_none())
        {
            return Err(XmlError::Invalid {
                at: Box::new(Location { file: source.to_owned(), line: v.source_line, column: 1 }),
                message: format!("virtual copter `{}` has no pose and there is no <spawn> point", v.name),
            });
        }
        Ok(Pairing { source: source.to_owned(), conf_path, twins: self.twins, virtual_copters, spawn, unknown_policy })
    }
}

impl Pairing {
    /// Reads and parses a pairing file.
    pub fn from_file(path: impl AsRef<Path>) -> Result<Pairing, XmlError> {
        let path = path.as_ref();
        let text = crate::paparazzi::xml::read_file(path)?;
        Pairing::parse(&text, &path.display().to_string())
    }

    /// Parses a pairing file's text; `source` labels error locations.
    pub fn parse(text: &str, source: &str) -> Result<Pairing, XmlError> {
        let doc = Doc::parse(text, source)?;
        let root = doc.expect_root("pairing")?;
        doc.only_attrs(root, &["version"])?;
        let version = doc.req_attr(root, "version")?;
        if version.value.trim() != "1" {
            return Err(doc.bad_attr(root, version, "only version 1 is supported"));
        }
        let mut parts = PairingParts::default();
        for el in &root.children {
            let line = doc.line(el.offset);
            match el.name.as_str() {
                "conf" => parts.conf(&doc, el, line)?,
                "twin" => parts.twin(&doc, el, line)?,
                "virtual" => parts.virtual_copter(&doc, el, line)?,
                "spawn" => parts.spawn(&doc, el, line)?,
                "unknown_aircraft" => parts.unknown_aircraft(&doc, el, line)?,
                _ => return Err(doc.unexpected(root, el)),
            }
        }
        parts.finish(&doc, root, source)
    }

    /// The conf.xml path, resolved against the pairing file's directory.
    pub fn conf_path_from(&self, pairing_file: &Path) -> PathBuf {
        let p = Path::new(&self.conf_path);
        if p.is_absolute() { p.to_path_buf() } else { pairing_file.parent().unwrap_or(Path::new(".")).join(p) }
    }

    fn err_at(&self, line: u32, message: String) -> XmlError {
        XmlError::Invalid { at: Box::new(Location { file: self.source.clone(), line, column: 1 }), message }
    }

    /// Checks the pairing against `conf` and assigns every twinned and
    /// virtual aircraft id its role.
    ///
    /// Errors (with the pairing file's line): a twin names an aircraft that
    /// is not in conf.xml, or one whose name marks it virtual; a virtual
    /// copter's `ac_id` belongs to a real aircraft of conf.xml; two entries
    /// end up with the same `ac_id`.
    pub fn resolve(&self, conf: &ConfXml) -> Result<ResolvedPairing, XmlError> {
        let mut by_ac_id: BTreeMap<AcId, Assignment> = BTreeMap::new();
        for t in &self.twins {
            let aircraft = match &t.aircraft {
                AircraftRef::Name(n) => conf.by_name(n),
                AircraftRef::AcId(id) => conf.by_ac_id(*id),
            };
            let Some(aircraft) = aircraft else {
                let what = match &t.aircraft {
                    AircraftRef::Name(n) => format!("aircraft `{n}`"),
                    AircraftRef::AcId(id) => format!("ac_id {id}"),
                };
                return Err(self.err_at(t.source_line, format!("{what} is not in {}", conf.source)));
            };
            if aircraft.kind() == AircraftKind::Virtual {
                return Err(self.err_at(
                    t.source_line,
                    format!(
                        "aircraft `{}` is virtual by name (starts with `Virtual`) and cannot be twinned",
                        aircraft.name
                    ),
                ));
            }
            let prev = by_ac_id.insert(
                aircraft.ac_id,
                Assignment {
                    ac_id: aircraft.ac_id,
                    kind: AircraftKind::Real,
                    aircraft_name: Some(aircraft.name.clone()),
                    copter: t.copter.clone(),
                    pose: t.pose,
                    autopilot: t.autopilot,
                },
            );
            if prev.is_some() {
                return Err(self.err_at(t.source_line, format!("ac_id {} is twinned twice", aircraft.ac_id)));
            }
        }
        for v in &self.virtual_copters {
            if let Some(real) = conf.by_ac_id(v.ac_id)
                && real.kind() == AircraftKind::Real
            {
                return Err(self.err_at(
                    v.source_line,
                    format!(
                        "virtual copter `{}` uses ac_id {}, which belongs to real aircraft `{}`",
                        v.name, v.ac_id, real.name
                    ),
                ));
            }
            // The spawn point exists when a pose is missing (checked by `parse`).
            let pose =
                v.pose.or(self.spawn.map(|s| s.pose)).unwrap_or(Pose { x_m: 0.0, y_m: 0.0, z_m: 0.0, yaw_rad: 0.0 });
            if by_ac_id.contains_key(&v.ac_id) {
                return Err(self.err_at(v.source_line, format!("ac_id {} is used twice", v.ac_id)));
            }
            by_ac_id.insert(
                v.ac_id,
                Assignment {
                    ac_id: v.ac_id,
                    kind: AircraftKind::Virtual,
                    aircraft_name: Some(v.name.clone()),
                    copter: v.name.clone(),
                    pose,
                    autopilot: false,
                },
            );
        }
        let unassigned = conf
            .aircraft
            .iter()
            .filter(|a| !by_ac_id.contains_key(&a.ac_id))
            .map(|a| (a.ac_id, (a.name.clone(), a.kind())))
            .collect();
        Ok(ResolvedPairing { by_ac_id, unknown_policy: self.unknown_policy, spawn: self.spawn, unassigned })
    }
}
