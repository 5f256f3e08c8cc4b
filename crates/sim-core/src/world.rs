//! The immutable compiled model ([`World`]); a fresh [`crate::State`] is built from it in
//! `state.rs` ([`World::initial_state`]).

use rapier3d::prelude::{ActiveEvents, ColliderBuilder, Group, InteractionGroups, SharedShape};
use serde::Serialize;

use crate::airflow::AirflowParams;
use crate::airframe::Airframe;
use crate::control::{Command, Inputs};
use crate::math::{Quat, Real, Vec3};
pub use crate::scene::CopterKind;
use crate::scene::SceneSpec;
use crate::sensors::SensorParams;

/// Stepping parameters.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SimParams {
    /// Physics step, s.
    pub physics_dt_s: f64,
    /// Control step, s.
    pub control_dt_s: f64,
    /// Physics substeps per control step.
    pub substeps: u32,
    /// Seed of all random draws.
    pub seed: u64,
    /// Default run length, s.
    pub duration_s: f64,
    /// Worker threads for one step (`[sim] threads`); any value gives the same bits. A
    /// caller may change it between steps (e.g. from a command-line flag).
    pub threads: usize,
    /// Free flight and floor contact in closed form (`[sim] closed_form`); `false`: every
    /// copter through Rapier.
    pub closed_form: bool,
}

/// The arena: a floor rectangle centred on the origin, walls and a ceiling.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Arena {
    /// Floor size along x and y, m.
    pub size_m: [Real; 2],
    /// Wall and ceiling height, m.
    pub height_m: Real,
    /// Whether walls and ceiling exist.
    pub walls: bool,
    /// Thickness of walls, floor and ceiling, m.
    pub wall_thickness_m: Real,
}

/// A static box, yawed about z.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StaticBox {
    /// Name (given, or `box<i>`).
    pub name: String,
    /// Centre, m.
    pub center_m: Vec3,
    /// Half sizes along its own axes, m.
    pub half_extents_m: Vec3,
    /// Rotation about z, rad.
    pub yaw_rad: Real,
    /// Whether it exists only in the simulation: twins' virtual sonars see it (see
    /// [`crate::mixed`]).
    pub virtual_only: bool,
}

impl StaticBox {
    /// Euclidean distance from a point to the box (0 inside).
    pub fn distance_to_point(&self, p: Vec3) -> Real {
        let local = Quat::from_rotation_z(-self.yaw_rad) * (p - self.center_m);
        let d = local.abs() - self.half_extents_m;
        d.max(Vec3::ZERO).length()
    }

    /// Height of its top, m.
    #[inline]
    pub fn top_m(&self) -> Real {
        self.center_m.z + self.half_extents_m.z
    }

    /// Whether a point may lie within `reach_m` horizontally of the box's footprint: false only
    /// where its horizontal distance from the centre exceeds the footprint's circumradius plus
    /// `reach_m` (a yaw keeps horizontal lengths; a margin covers its rounding).
    #[inline]
    pub fn footprint_may_be_within(&self, p: Vec3, reach_m: Real) -> bool {
        let h = self.half_extents_m;
        let near = (h.x * h.x + h.y * h.y).sqrt() * (1.0 + 1e-5) + reach_m + 1e-3;
        let (dx, dy) = (p.x - self.center_m.x, p.y - self.center_m.y);
        dx * dx + dy * dy <= near * near
    }

    /// Whether a point lies farther than `r` from the box: `distance_to_point(p) > r`, with a
    /// test on the box's circumscribed sphere first (a millimetre of margin covers rounding,
    /// so it decides only where the exact test agrees).
    #[inline]
    pub fn is_farther_than(&self, p: Vec3, r: Real) -> bool {
        (p - self.center_m).length() - self.half_extents_m.length() > r + 1e-3 || self.distance_to_point(p) > r
    }
}

/// One copter of the scene, compiled.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CopterDef {
    /// Unique name.
    pub name: String,
    /// Virtual or twin of a real copter.
    pub kind: CopterKind,
    /// Paparazzi aircraft id.
    pub ac_id: Option<u8>,
    /// Index into [`World::airframes`].
    pub airframe: usize,
    /// Start position of the centre of mass, m.
    pub start_pos_m: Vec3,
    /// Start heading, rad.
    pub start_yaw_rad: Real,
    /// Commands in force at tick 0.
    pub initial_command: Command,
}

/// The immutable compiled model: arena, obstacles, airframes, copters, parameters.
///
/// **Invariant:** nothing in a `World` changes during a run; everything that does lives in
/// [`State`]. Copter ids are indices into [`World::copters`] and never change.
#[derive(Clone, Debug, Serialize)]
pub struct World {
    /// World name (key-expression segment).
    pub name: String,
    /// Stepping parameters.
    pub params: SimParams,
    /// The arena.
    pub arena: Arena,
    /// Static boxes.
    pub boxes: Vec<StaticBox>,
    /// Derived airframe models.
    pub airframes: Vec<Airframe>,
    /// Per airframe, a copter's collision shape (see [`World::copter_collider_of`]).
    #[serde(skip)]
    pub(crate) copter_shapes: Vec<SharedShape>,
    /// Copters, in id order.
    pub copters: Vec<CopterDef>,
    /// Sensor models.
    pub sensors: SensorParams,
    /// Downwash and ground effect.
    pub airflow: AirflowParams,
    /// The scene this was compiled from.
    #[serde(skip)]
    pub spec: SceneSpec,
}

/// What a static collider is, stored in its `user_data`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ColliderTag {
    /// A copter, by id.
    Copter(usize),
    /// The floor.
    Floor,
    /// One of the four walls.
    Wall,
    /// The ceiling.
    Ceiling,
    /// A static box, by index.
    Box(usize),
}

impl ColliderTag {
    const SHIFT: u32 = 64;
    /// Encodes into rapier's `user_data`.
    pub fn encode(self) -> u128 {
        let (tag, idx) = match self {
            ColliderTag::Copter(i) => (1u128, i as u128),
            ColliderTag::Floor => (2, 0),
            ColliderTag::Wall => (3, 0),
            ColliderTag::Ceiling => (4, 0),
            ColliderTag::Box(i) => (5, i as u128),
        };
        (tag << Self::SHIFT) | idx
    }
    /// Decodes rapier's `user_data`.
    pub fn decode(v: u128) -> Option<Self> {
        let idx = (v & u64::MAX as u128) as usize;
        match v >> Self::SHIFT {
            1 => Some(ColliderTag::Copter(idx)),
            2 => Some(ColliderTag::Floor),
            3 => Some(ColliderTag::Wall),
            4 => Some(ColliderTag::Ceiling),
            5 => Some(ColliderTag::Box(idx)),
            _ => None,
        }
    }
}

impl World {
    /// Physics step, s, as the physics engine's scalar.
    pub fn physics_dt(&self) -> Real {
        self.params.physics_dt_s as Real
    }

    /// Simulated time at a tick, s.
    pub fn time_at(&self, tick: u64) -> f64 {
        tick as f64 * self.params.control_dt_s
    }

    /// Number of control steps in the scene's default duration.
    pub fn default_ticks(&self) -> u64 {
        (self.params.duration_s / self.params.control_dt_s).round() as u64
    }

    /// The copter id with this name.
    pub fn copter_id(&self, name: &str) -> Option<usize> {
        self.copters.iter().position(|c| c.name == name)
    }

    /// The commands in force at tick 0.
    pub fn initial_inputs(&self) -> Inputs {
        Inputs { commands: self.copters.iter().map(|c| c.initial_command.clone()).collect() }
    }

    /// Copter `id`'s one collider, flying or wrecked: its parts (body box and rotor discs) as
    /// one compound shape, built with the world. One collider per body makes every contact pair
    /// a pair of bodies: Rapier colours a body pair's contacts in body-id order, while two
    /// collider pairs of one body pair would go in the order of their contact-graph edges, which
    /// differs between one process and a shard (docs/sharding.md, "The same bits").
    pub(crate) fn copter_collider_of(&self, id: usize) -> ColliderBuilder {
        self.copter_collider(id, self.copter_shapes[self.copters[id].airframe].clone())
    }

    /// A collider of copter `id` of `shape`: mass comes from the airframe (set on the body),
    /// not from the shapes; collision events on. A copter flown by an outside autopilot is the
    /// real copter itself: it passes through `virtual_only` boxes, which exist only in the
    /// simulation and reach it through the virtual-sonar uplink.
    fn copter_collider(&self, id: usize, shape: SharedShape) -> ColliderBuilder {
        let groups = match self.copters[id].kind {
            CopterKind::Autopilot => AUTOPILOT_COPTER,
            CopterKind::Virtual | CopterKind::Real => InteractionGroups::all(),
        };
        ColliderBuilder::new(shape)
            .density(0.0)
            .friction(0.6)
            .active_events(ActiveEvents::COLLISION_EVENTS)
            .collision_groups(groups)
            .user_data(ColliderTag::Copter(id).encode())
    }
}

/// Rapier collision groups: a `virtual_only` box meets everything but the copters flown by an
/// outside autopilot (their own group); everything else is in every group.
const AUTOPILOT_GROUP: Group = Group::GROUP_2;
pub(crate) const AUTOPILOT_COPTER: InteractionGroups = InteractionGroups::all().with_memberships(AUTOPILOT_GROUP);
pub(crate) const VIRTUAL_ONLY_BOX: InteractionGroups =
    InteractionGroups::all().with_filter(Group::ALL.difference(AUTOPILOT_GROUP));

/// A copter's collision shapes in its body frame: the body box and the four rotor discs.
fn copter_parts(af: &Airframe) -> [ColliderBuilder; 5] {
    let [bx, by, bz] = af.spec.body_size_m;
    let rotor_radius = af.spec.rotor_diameter_m / 2.0;
    let disc = |p: Vec3| {
        ColliderBuilder::cylinder(crate::airframe::ROTOR_DISC_HALF_THICKNESS_M, rotor_radius)
            .rotation(Vec3::new(std::f32::consts::FRAC_PI_2, 0.0, 0.0))
            .translation(p)
    };
    let [a, b, c, d] = af.rotor_pos_in_body_m;
    [ColliderBuilder::cuboid(bx / 2.0, by / 2.0, bz / 2.0), disc(a), disc(b), disc(c), disc(d)]
}

/// Per airframe, a copter's shape: its parts as one compound.
pub(crate) fn copter_shapes(airframes: &[Airframe]) -> Vec<SharedShape> {
    airframes.iter().map(|af| SharedShape::compound(copter_parts(af).map(|p| (p.position, p.shape)).to_vec())).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_box_is_farther_than_r_exactly_when_its_distance_is() {
        let mut rng = crate::rng::Rng32::new(5, 0);
        let b = StaticBox {
            name: "pillar".into(),
            center_m: Vec3::new(1.0, -2.0, 0.6),
            half_extents_m: Vec3::new(0.2, 0.4, 0.6),
            yaw_rad: 0.7,
            virtual_only: false,
        };
        let (mut decided_by_sphere, mut total) = (0, 0);
        for _ in 0..20_000 {
            let mut u = || 2.0 * rng.uniform() - 1.0;
            let p = b.center_m + Vec3::new(u(), u(), u()) * 3.0;
            let r = 2.0 * rng.uniform();
            assert_eq!(b.is_farther_than(p, r), b.distance_to_point(p) > r, "{p} {r}");
            total += 1;
            decided_by_sphere += usize::from((p - b.center_m).length() - b.half_extents_m.length() > r + 1e-3);
        }
        // The sphere test decides a good share of the cases (it is not vacuous).
        assert!(decided_by_sphere * 5 > total, "{decided_by_sphere} of {total}");
    }

    #[test]
    fn a_point_over_a_footprint_or_near_it_passes_the_footprint_pretest() {
        let mut rng = crate::rng::Rng32::new(6, 0);
        let b = StaticBox {
            name: "table".into(),
            center_m: Vec3::new(-3.0, 1.0, 0.3),
            half_extents_m: Vec3::new(1.2, 0.5, 0.3),
            yaw_rad: -0.4,
            virtual_only: false,
        };
        let (mut rejected, mut total) = (0, 0);
        for _ in 0..20_000 {
            let mut u = || 2.0 * rng.uniform() - 1.0;
            let p = b.center_m + Vec3::new(u() * 4.0, u() * 4.0, u());
            let reach = 0.5 * rng.uniform();
            // Exactly: the footprint grown by `reach` (its distance in the box's own frame).
            let local = Quat::from_rotation_z(-b.yaw_rad) * (p - b.center_m);
            let out = Vec3::new(local.x.abs() - b.half_extents_m.x, local.y.abs() - b.half_extents_m.y, 0.0);
            let within = out.max(Vec3::ZERO).length() <= reach;
            let pass = b.footprint_may_be_within(p, reach);
            assert!(pass || !within, "{p} {reach}");
            total += 1;
            rejected += usize::from(!pass);
        }
        // Most points far from it are turned away (it is not vacuous).
        assert!(rejected * 4 > total, "{rejected} of {total}");
    }
}
