//! Sharding: one swarm stepped by several [`State`]s, each owning the copters of its region
//! of the arena and seeing its neighbours' copters near its borders as **ghosts**. Pure: the
//! transport (Zenoh, in `bridge`) only carries [`Ghost`]s between shards, once per control
//! step, and that exchange is the lockstep barrier.
//!
//! A shard's `State` holds every copter of the scene (ids are indices everywhere), each in one
//! of three [`Role`]s:
//! - **owned**: stepped here;
//! - **ghost**: a neighbour's copter within [`Partition::halo_m`] of this region, its whole
//!   state as its owner had it at the start of the step. Sonars, cross-talk, downwash and the
//!   free-flight reservations read ghosts exactly as they read owned copters;
//! - **absent**: far away; nothing here reads it, its Rapier body is disabled.
//!
//! **Ownership** is decided afresh at every step, by every shard from the same data, in
//! [`crate::step`] once the reservations are known:
//! 1. a copter's *home* is the region holding its centre at the start of the step;
//! 2. copters whose reservation spheres meet (the only ones that can touch each other within
//!    the step) form contact clusters; a cluster belongs to the home of its lowest id, unless
//!    Rapier carries one of its copters over from the last step ([`Ghost::held_by`]: near a
//!    box or a wall, or on watch beside another copter, and within [`HELD_ZONE_M`] of its
//!    holder's region): then to the shard whose Rapier world holds the lowest such copter,
//!    since Rapier's contact memory does not travel with a ghost. So
//!    two copters that may collide across a border are stepped by one shard, the lower id's,
//!    and a copter migrates simply by being owned by another shard at the next step (its
//!    whole state, random stream, controllers, estimator and battery included, is already
//!    there as a ghost).
//!
//! That gives the same bits as one process as long as every shard sees every copter its own
//! depend on. The halo is wide enough for sonars, cross-talk and wakes plus [`PULL_ZONE_M`];
//! a contact cluster of a shard that reaches farther than the pull zone from its region, or
//! a wake longer than the halo allows, is counted in [`crate::StepReport::shard_violations`]
//! (the caller stops: the run would no longer be the one-process run).
//!
//! **Where the bits could differ:** Rapier keeps per-contact memory (warm-start impulses) and
//! an island order set by its whole world's history, which do not travel. With
//! `[sim] closed_form` (the default) only flying copters near something are in Rapier's hands,
//! and a touch is mostly a crash, after which the wreck is closed form (`step::fall_wrecks`);
//! so every copter keeps the one-process bits in `tests/shard.rs` (60 s, 2–4 shards, a crowded
//! take-off where most copters crash). Rapier colours new contacts in body-id order, which
//! every shard shares, but two collider pairs of one body pair in contact-graph order, which it
//! does not: so every body has one collider (`World::copter_collider_of`, one fixed body per
//! wall and box). What is left to Rapier's history: the sequential overflow of a pair touching
//! in several places, when one copter has two such pairs in a step; with `closed_form = false`
//! wrecks settle in Rapier and can part (docs/sharding.md).

use serde::{Deserialize, Serialize};

use crate::math::Real;
use crate::partition::held_in_rapier;
pub use crate::partition::{
    FAR_BEYOND_M, HELD_ZONE_M, PULL_ZONE_M, Partition, Role, ShardError, ShardId, ShardSnapshot, ShardView, halo_m,
};
use crate::state::{CopterState, CrashCause, Motion, State};
use crate::world::World;

/// One copter as its owner sends it to a neighbour, at the start of a step.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Ghost {
    /// Copter id.
    pub id: u32,
    /// Whether Rapier had it asleep (a wreck at rest).
    pub asleep: bool,
    /// The sender, if its Rapier world moved this copter in the last step (a flying copter
    /// near a box, a wall or another copter; a wreck with `closed_form = false`): Rapier's
    /// contact memory does not travel, so while Rapier keeps it the copter stays with that
    /// shard (see [`crate::step`]'s ownership).
    pub held_by: Option<ShardId>,
    /// Its whole state (near the receiver's region) or what others read of it (farther).
    pub state: GhostState,
}

/// What a [`Ghost`] carries.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub enum GhostState {
    /// Everything: the receiver may take it over ([`Role::Ghost`]).
    Full(Box<CopterState>),
    /// What other copters' sensing, wakes and reservations read ([`Role::Far`]).
    Seen(Seen),
}

/// A [`Ghost`] as its owner sends it, borrowing the copter's state: it serialises to the
/// same bytes as the [`Ghost`] it is read back as ([`State::ghost_refs_for`]).
#[derive(Clone, Debug, Serialize)]
#[serde(rename = "Ghost")]
pub struct GhostRef<'a> {
    /// Copter id.
    pub id: u32,
    /// See [`Ghost::asleep`].
    pub asleep: bool,
    /// See [`Ghost::held_by`].
    pub held_by: Option<ShardId>,
    /// What it carries.
    pub state: GhostStateRef<'a>,
}

/// What a [`GhostRef`] carries: [`GhostState`], the whole state borrowed.
#[derive(Clone, Debug, Serialize)]
#[serde(rename = "GhostState")]
pub enum GhostStateRef<'a> {
    /// Everything (see [`GhostState::Full`]).
    Full(&'a CopterState),
    /// What others read of it (see [`GhostState::Seen`]).
    Seen(Seen),
}

impl GhostRef<'_> {
    /// The ghost it stands for.
    pub fn to_ghost(&self) -> Ghost {
        let state = match &self.state {
            GhostStateRef::Full(c) => GhostState::Full(Box::new((*c).clone())),
            GhostStateRef::Seen(s) => GhostState::Seen(s.clone()),
        };
        Ghost { id: self.id, asleep: self.asleep, held_by: self.held_by, state }
    }
}

/// What other copters read of a far ghost.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Seen {
    /// Pose and velocities.
    pub motion: Motion,
    /// Rotor thrusts of its last physics step, N (its wake).
    pub rotor_thrust_n: [Real; 4],
    /// Whether it is a wreck (no wake, no pings), and why.
    #[serde(with = "crate::state::crash_snapshot")]
    pub crash: Option<CrashCause>,
    /// Its sonars' ping timing (cross-talk), s.
    pub sonar_phase_s: f64,
    /// Its sonars' cycle, s.
    pub sonar_cycle_s: f64,
}

impl State {
    /// Makes this state one shard of a sharded run: it owns the copters whose start lies in
    /// its region; every other copter is a ghost for the first step (all shards know the
    /// initial state), absent after it unless a neighbour sends it.
    pub fn make_shard(&mut self, partition: Partition, me: usize) -> Result<(), ShardError> {
        let shards = partition.shards();
        if me >= shards {
            return Err(ShardError::Id { shard: me, shards });
        }
        let me = me as ShardId;
        let roles = self
            .copters
            .iter()
            .map(|c| if partition.region_of(c.motion.pos_m) == me { Role::Owned } else { Role::Ghost })
            .collect();
        let n = self.copters.len();
        // Every shard knows the initial state: a copter whose body Rapier has enabled is held by
        // its region's shard, as that shard finds from its own Rapier world at the first step.
        let held_by = self
            .copters
            .iter()
            .map(|c| {
                let held = self.physics.bodies.get(c.body).is_some_and(held_in_rapier);
                held.then(|| partition.region_of(c.motion.pos_m))
            })
            .collect();
        self.shard = Some(ShardView::new(me, partition, roles, vec![false; n], held_by));
        self.disable_others_bodies();
        Ok(())
    }

    /// Disables the Rapier body of every copter this shard does not own: they are not in its
    /// Rapier world. A step keeps it so (a copter leaves a shard as a ghost, whose body the
    /// step disables), so the step need not look at an absent copter's body at all.
    fn disable_others_bodies(&mut self) {
        let Some(view) = &self.shard else { return };
        for (c, role) in self.copters.iter().zip(&view.roles) {
            if *role != Role::Owned
                && let Some(body) = self.physics.bodies.get_mut(c.body)
                && body.is_enabled()
            {
                body.set_enabled(false);
            }
        }
    }

    /// The shard view as a snapshot keeps it (`None` outside a sharded run).
    pub fn shard_snapshot(&self) -> Option<ShardSnapshot> {
        let v = self.shard.as_ref()?;
        let shards = v.partition.shards() as u16;
        Some(ShardSnapshot { me: v.me, shards, roles: v.roles.clone(), asleep: v.asleep.clone() })
    }

    /// Makes a restored state the shard it was: `partition` must be the split it was made
    /// with (same scene, same count), and the snapshot of this state's copters.
    pub fn restore_shard(&mut self, partition: Partition, snap: ShardSnapshot) -> Result<(), ShardError> {
        let shards = partition.shards();
        if usize::from(snap.shards) != shards || usize::from(snap.me) >= shards {
            return Err(ShardError::Id { shard: usize::from(snap.me), shards });
        }
        let n = self.copters.len();
        if snap.roles.len() != n || snap.asleep.len() != n {
            return Err(ShardError::Unknown { copter: snap.roles.len().max(snap.asleep.len()), copters: n });
        }
        let ShardSnapshot { me, roles, asleep, .. } = snap;
        self.shard = Some(ShardView::new(me, partition, roles, asleep, vec![None; n]));
        self.disable_others_bodies();
        Ok(())
    }

    /// Whether this state steps copter `id` (always, outside a sharded run).
    pub fn owns(&self, id: usize) -> bool {
        self.shard.as_ref().is_none_or(|s| s.roles.get(id) == Some(&Role::Owned))
    }

    /// Appends to `out` the ghosts this shard owes shard `to` for the next step: its owned
    /// copters within the halo of `to`'s region, whole within [`FAR_BEYOND_M`] of it, what
    /// others read of them beyond.
    pub fn ghosts_for(&self, to: ShardId, out: &mut Vec<Ghost>) {
        let mut refs = Vec::new();
        self.ghost_refs_for(to, &mut refs);
        out.extend(refs.iter().map(GhostRef::to_ghost));
    }

    /// [`State::ghosts_for`], borrowing each copter's state instead of copying it (what a
    /// transport serialises).
    pub fn ghost_refs_for<'a>(&'a self, to: ShardId, out: &mut Vec<GhostRef<'a>>) {
        let Some(view) = &self.shard else { return };
        for (i, c) in self.copters.iter().enumerate() {
            if view.roles[i] != Role::Owned {
                continue;
            }
            let d = view.partition.distance_to(c.motion.pos_m, to);
            if d > view.partition.halo_m() {
                continue;
            }
            let body = self.physics.bodies.get(c.body);
            // With `closed_form = false`: a sleeping wreck is a sleeping one to its next owner.
            let asleep = body.is_some_and(|b| b.is_sleeping() || b.is_fixed());
            let held_by = body.is_some_and(held_in_rapier).then_some(view.me);
            let state = if d <= FAR_BEYOND_M {
                GhostStateRef::Full(c)
            } else {
                GhostStateRef::Seen(Seen {
                    motion: c.motion,
                    rotor_thrust_n: c.rotor_thrust_n,
                    crash: c.crash,
                    sonar_phase_s: c.sonar_phase_s,
                    sonar_cycle_s: c.sonar_cycle_s,
                })
            };
            out.push(GhostRef { id: i as u32, asleep, held_by, state });
        }
    }

    /// Takes in every neighbour's ghosts for the next step (all of them at once): they become
    /// ghosts here, and every other copter this shard does not own becomes absent.
    pub fn receive_ghosts(&mut self, ghosts: impl IntoIterator<Item = Ghost>) -> Result<(), ShardError> {
        let tick = self.tick;
        let n = self.copters.len();
        let Some(view) = &mut self.shard else { return Ok(()) };
        for (role, held_by) in view.roles.iter_mut().zip(&mut view.held_by) {
            if matches!(*role, Role::Ghost | Role::Far) {
                (*role, *held_by) = (Role::Absent, None);
            }
        }
        for g in ghosts {
            let id = g.id as usize;
            if id >= n {
                return Err(ShardError::Unknown { copter: id, copters: n });
            }
            if let Some(what) = ghost_defect(&g) {
                return Err(ShardError::BadGhost { copter: id, tick, what });
            }
            if view.roles[id] == Role::Owned {
                return Err(ShardError::Duplicate { copter: id, tick });
            }
            // Its holder is its sender, a neighbour: never this shard, never one that is not.
            if let Some(k) = g.held_by.filter(|&k| k == view.me || usize::from(k) >= view.partition.shards()) {
                let what = format!("it says shard {k} holds it, which no neighbour of shard {} is", view.me);
                return Err(ShardError::BadGhost { copter: id, tick, what });
            }
            (view.asleep[id], view.held_by[id]) = (g.asleep, g.held_by);
            let c = &mut self.copters[id];
            match g.state {
                GhostState::Full(state) => {
                    view.roles[id] = Role::Ghost;
                    // Rapier handles are this shard's own (a wreck may have a new body here).
                    let (body, collider) = (c.body, c.collider);
                    *c = *state;
                    (c.body, c.collider) = (body, collider);
                }
                GhostState::Seen(seen) => {
                    // The rest of its slot is stale and nothing reads it (see `Role::Far`).
                    view.roles[id] = Role::Far;
                    (c.motion, c.rotor_thrust_n, c.crash) = (seen.motion, seen.rotor_thrust_n, seen.crash);
                    (c.sonar_phase_s, c.sonar_cycle_s) = (seen.sonar_phase_s, seen.sonar_cycle_s);
                }
            }
        }
        Ok(())
    }

    /// This shard's id and split, if it is one.
    pub fn shard(&self) -> Option<&ShardView> {
        self.shard.as_ref()
    }
}

/// Farther from the origin than this, m, no copter of any arena is.
const MAX_GHOST_DISTANCE_M: Real = 1.0e4;
/// Faster than this, m/s, no copter flies.
const MAX_GHOST_SPEED_M_S: Real = 1.0e3;
/// Faster than this, rad/s, no copter spins.
const MAX_GHOST_SPIN_RAD_S: Real = 1.0e4;

/// What is wrong with a ghost's state, if anything: every number must be finite, the pose
/// within reach, the rotation a unit quaternion, the speeds a copter's (the physics' contact
/// search fails on anything else).
fn ghost_defect(g: &Ghost) -> Option<String> {
    let (motion, thrust) = match &g.state {
        GhostState::Full(c) => {
            if let Some(path) = crate::finite::first_non_finite(c.as_ref()) {
                return Some(format!("{path} is not finite"));
            }
            (&c.motion, c.rotor_thrust_n)
        }
        GhostState::Seen(s) => {
            if let Some(path) = crate::finite::first_non_finite(s) {
                return Some(format!("{path} is not finite"));
            }
            (&s.motion, s.rotor_thrust_n)
        }
    };
    let norm = motion.rot.length();
    if motion.pos_m.length() > MAX_GHOST_DISTANCE_M {
        Some(format!("position {:?} is over {MAX_GHOST_DISTANCE_M} m away", motion.pos_m))
    } else if (norm - 1.0).abs() > 1e-3 {
        Some(format!("rotation {:?} is not a unit quaternion (norm {norm})", motion.rot))
    } else if motion.vel_m_s.length() > MAX_GHOST_SPEED_M_S {
        Some(format!("velocity {:?} is over {MAX_GHOST_SPEED_M_S} m/s", motion.vel_m_s))
    } else if motion.angvel_rad_s.length() > MAX_GHOST_SPIN_RAD_S {
        Some(format!("angular velocity {:?} is over {MAX_GHOST_SPIN_RAD_S} rad/s", motion.angvel_rad_s))
    } else if thrust.iter().any(|t| !(0.0..=1.0e3).contains(t)) {
        Some(format!("rotor thrusts {thrust:?} are outside 0 to 1000 N"))
    } else {
        None
    }
}

/// Steps every shard of a sharded run by one control step in this process, trading ghosts in
/// memory: what the shards' processes do over Zenoh (tests and benches compare the two). Each
/// state must be shard `k` of the same partition, at the same tick.
pub fn step_in_process(
    world: &World,
    shards: &mut [State],
    inputs: &crate::Inputs,
    reports: &mut Vec<crate::StepReport>,
) -> Result<(), ShardError> {
    let mut inbox: Vec<Vec<Ghost>> = vec![Vec::new(); shards.len()];
    for s in shards.iter() {
        let Some(view) = &s.shard else { continue };
        for t in view.partition.neighbours(view.me) {
            if let Some(out) = inbox.get_mut(usize::from(t)) {
                s.ghosts_for(t, out);
            }
        }
    }
    for (s, ghosts) in shards.iter_mut().zip(inbox) {
        s.receive_ghosts(ghosts)?;
    }
    reports.resize_with(shards.len(), Default::default);
    for (s, report) in shards.iter_mut().zip(reports.iter_mut()) {
        crate::step_into(world, s, inputs, report);
    }
    Ok(())
}
