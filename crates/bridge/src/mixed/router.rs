//! Which copter an aircraft is: the pairing's copters added to a scene before it is compiled
//! ([`apply_pairing`], [`paired_copter`]), and the [`Router`] that sends each telemetry text by
//! its `ac_id` to a twin (scene copters first, then the pairing's spawn rules: a twin spawned
//! on an aircraft's first text) or drops it ([`Decision`]).

use std::collections::BTreeMap;

use sim_core::scene::{CommandSpec, CopterSpec, StartSpec};
use sim_core::{CopterKind, FlightMode, SceneSpec, World};

use crate::ids::AcId;
use crate::paparazzi::conf::AircraftKind;
use crate::paparazzi::pairing::{ResolvedPairing, Route, UnknownAircraftStats};

/// Adds the pairing's copters to a scene before it is compiled: each twin and virtual copter
/// that the scene does not have is appended at its pairing pose (twins in `manual` mode on
/// the floor, waiting for telemetry; virtual copters in `wall_avoid` at 0.8 m). A scene copter
/// the pairing names gets the pairing's kind and `ac_id`; an `ac_id` used by another scene
/// copter is an error.
pub fn apply_pairing(spec: &mut SceneSpec, pairing: &ResolvedPairing) -> Result<(), String> {
    for a in pairing.by_ac_id.values() {
        let kind = match a.kind {
            AircraftKind::Real if a.autopilot => CopterKind::Autopilot,
            AircraftKind::Real => CopterKind::Real,
            AircraftKind::Virtual => CopterKind::Virtual,
        };
        if let Some(other) = spec.copters.iter().find(|c| c.ac_id == Some(a.ac_id) && c.name != a.copter) {
            return Err(format!(
                "the pairing gives ac_id {} to `{}`, but scene copter `{}` already has it",
                a.ac_id, a.copter, other.name
            ));
        }
        match spec.copters.iter_mut().find(|c| c.name == a.copter) {
            Some(c) => {
                c.kind = kind;
                c.ac_id = Some(a.ac_id);
            }
            None => spec.copters.push(paired_copter(&a.copter, kind, a.ac_id, &a.pose)),
        }
    }
    Ok(())
}

/// The scene table of a copter the bridge adds (pairing, or automatic spawn).
pub fn paired_copter(name: &str, kind: CopterKind, ac_id: AcId, pose: &crate::paparazzi::pairing::Pose) -> CopterSpec {
    let (mode, command) = match kind {
        CopterKind::Real => (FlightMode::Manual, CommandSpec::default()),
        CopterKind::Autopilot => (FlightMode::Rotors, CommandSpec::default()),
        CopterKind::Virtual => (FlightMode::WallAvoid, CommandSpec { height_m: 0.8, ..CommandSpec::default() }),
    };
    CopterSpec {
        name: name.to_owned(),
        kind,
        ac_id: Some(ac_id),
        airframe: Default::default(),
        start: StartSpec {
            pos_m: [pose.x_m as f32, pose.y_m as f32],
            z_m: (pose.z_m > 0.0).then_some(pose.z_m as f32),
            yaw_deg: pose.yaw_rad.to_degrees() as f32,
        },
        mode,
        command,
    }
}

/// What the gateway does with a telemetry message from an aircraft.
#[derive(Clone, Debug, PartialEq)]
pub enum Decision {
    /// Drive this twin.
    Twin(String),
    /// Spawn this twin first, then drive it.
    SpawnTwin(Box<CopterSpec>),
    /// Drop: one of our own virtual aircraft (someone else is sending as it).
    OwnVirtual,
    /// Drop: the telemetry of an aircraft whose autopilot flies one of our copters (its motion
    /// is the simulation's; the telemetry is for the ground station).
    Autopilot,
    /// Drop: not ours and not to be spawned.
    Unknown,
}

/// Routes aircraft ids to copters: the world's copters with an `ac_id`, then the pairing's
/// rules for the rest (see [`crate::paparazzi::pairing`]). Spawn decisions are remembered, so an aircraft
/// spawns once.
#[derive(Clone, Debug)]
pub struct Router {
    by_ac_id: BTreeMap<AcId, (String, CopterKind)>,
    pairing: Option<ResolvedPairing>,
    spawned: u32,
    /// Dropped messages of unknown aircraft.
    pub unknown: UnknownAircraftStats,
    /// Dropped messages claiming to come from one of our virtual aircraft.
    pub own_virtual_dropped: u64,
}

impl Router {
    /// A router for `world`'s copters and the optional pairing.
    pub fn new(world: &World, pairing: Option<ResolvedPairing>) -> Self {
        let by_ac_id = world.copters.iter().filter_map(|c| Some((c.ac_id?, (c.name.clone(), c.kind)))).collect();
        Self { by_ac_id, pairing, spawned: 0, unknown: UnknownAircraftStats::default(), own_virtual_dropped: 0 }
    }

    /// What to do with a message from `ac_id`.
    pub fn route(&mut self, ac_id: AcId) -> Decision {
        match self.by_ac_id.get(&ac_id) {
            Some((name, CopterKind::Real)) => return Decision::Twin(name.clone()),
            Some((_, CopterKind::Virtual)) => {
                self.own_virtual_dropped += 1;
                return Decision::OwnVirtual;
            }
            Some((_, CopterKind::Autopilot)) => return Decision::Autopilot,
            None => {}
        }
        let route = self.pairing.as_ref().map_or(Route::Ignore, |p| p.route(ac_id));
        let spawn = match route {
            Route::Spawn { point, aircraft } => {
                let name = aircraft.map_or_else(|| format!("ac_{ac_id}"), sanitise);
                Some((name, point.pose_for(self.spawned)))
            }
            // Assigned ids are in the world (the pairing was applied to the scene).
            Route::Assigned(_) | Route::Ignore => None,
        };
        match spawn {
            Some((name, pose)) => {
                self.spawned += 1;
                self.by_ac_id.insert(ac_id, (name.clone(), CopterKind::Real));
                Decision::SpawnTwin(Box::new(paired_copter(&name, CopterKind::Real, ac_id, &pose)))
            }
            None => {
                self.unknown.record(ac_id);
                Decision::Unknown
            }
        }
    }
}

/// A copter name from an aircraft name: lower case, characters outside `[a-z0-9_-]` as `_`.
fn sanitise(name: &str) -> String {
    name.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' { c.to_ascii_lowercase() } else { '_' }).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::paparazzi::conf::ConfXml;
    use crate::paparazzi::pairing::Pairing;

    #[test]
    fn known_aircraft_spawn_once_unknown_ones_follow_the_policy() {
        let (_, world) = sim_core::scene::load_default();
        let conf = ConfXml::parse(
            r#"<conf><aircraft name="FINken_01" ac_id="5"/><aircraft name="FINken 03" ac_id="7"/>
               <aircraft name="Virtual_09" ac_id="9"/></conf>"#,
            "c.xml",
        )
        .unwrap();
        let text = r#"<pairing version="1"><conf path="c.xml"/>
            <twin ac_id="5" copter="finken1" x_m="0" y_m="0" z_m="0" yaw_deg="0"/>
            <spawn x_m="0" y_m="0.5" z_m="0" yaw_deg="0" spacing_m="0.5"/></pairing>"#;
        let pairing = Pairing::parse(text, "p.xml").unwrap().resolve(&conf).unwrap();
        let mut r = Router::new(&world, Some(pairing));
        // The scene's virtual copters (201, 202) are ours.
        assert_eq!(r.route(201), Decision::OwnVirtual);
        // 7 is a real aircraft of conf.xml: spawned once, at the spawn point, then driven.
        let Decision::SpawnTwin(spec) = r.route(7) else { panic!("7 should spawn") };
        assert_eq!(spec.name, "finken_03");
        assert_eq!(spec.kind, CopterKind::Real);
        assert_eq!(spec.start.pos_m, [0.0, 0.5]);
        assert_eq!(r.route(7), Decision::Twin("finken_03".into()));
        // 9 is virtual by name but not ours; 42 is not in conf.xml and the policy is ignore.
        assert_eq!(r.route(9), Decision::Unknown);
        assert_eq!(r.route(42), Decision::Unknown);
        assert_eq!(r.route(42), Decision::Unknown);
        assert_eq!(r.unknown.dropped_by_ac_id.get(&42), Some(&2));
    }
}
