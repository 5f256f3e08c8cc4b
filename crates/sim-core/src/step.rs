//! `step(&World, &mut State, &Inputs) -> StepReport`: one control step.
//!
//! A control step (default 50 ms) is, in order:
//! 1. **sense** (sonars every `sonar.period_steps` control steps): sonar cones with floor and
//!    ceiling, cross-talk, IR, IMU, from the state at the start of the step; then the
//!    estimators (IR height, AHRS biases, thrust gain, see [`crate::estimate`]);
//! 2. **outer loop**: each copter's flight mode turns its command and readings into a
//!    [`Setpoint`];
//! 3. **airflow**: the surface below each copter and the downwash each one feels from the
//!    others' wakes (see [`crate::airflow`]);
//! 4. **physics substeps** (default 10 × 5 ms), each: AHRS, attitude PIDs, height hold, mixer,
//!    rotor model (battery voltage, ground effect, motor lag, particle noise), battery; then
//!    free copters move in closed form (floor contact included) and the others through one
//!    Rapier step, if any needs it; crash detection.
//!
//! Only copters that may touch something go through Rapier (see [`reserve_free_flight`]);
//! `[sim] closed_form = false` sends every copter through it, the reference for the closed
//! form's crash decisions.
//!
//! Copters are processed in id order; every random draw comes from the copter's own stream.

use serde::Serialize;

use crate::airflow::{Wake, ground_effect_ratio, inflow_thrust_factor};
use crate::airframe::{Airframe, ParticleNoise, ROTOR_DISC_HALF_THICKNESS_M, ROTOR_YAW_SIGN};
use crate::control::{self, Command, FlightMode, Inputs, Setpoint, WallAvoidController};
use crate::geometry::{Cone, OrientedBox, Wedge};
use crate::lanes::LANES;
use crate::math::{self, GRAVITY_M_S2, Quat, Real, Vec3, euler_from_quat, wrap_angle_rad};
use crate::scene::CopterKind;
use crate::sensors::{
    self, SonarScene, SonarSchedule, crosstalk_eligible, crosstalk_reading, sonar_cones, sonar_reading,
};
use crate::shard::{Role, ShardView};
use crate::state::{CopterState, CrashCause, Lane, Motion, Pinger, State};
use crate::world::{ColliderTag, World};
use batch::run_ahead_batch;
use rapier3d::prelude::{
    InteractionGroups, PhysicsWorld, RigidBody, RigidBodyActivation, RigidBodyBuilder, RigidBodyHandle, RigidBodyType,
};

mod batch;

/// Something that happened during a step.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum Event {
    /// A copter left the floor for the first time.
    TookOff {
        /// Copter id.
        copter: usize,
    },
    /// A copter crashed; its motors are off from now on.
    Crashed {
        /// Copter id.
        copter: usize,
        /// Why.
        cause: CrashCause,
    },
}

/// What a step reports.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct StepReport {
    /// The tick reached by this step.
    pub tick: u64,
    /// Events, in the order they happened (copter id order within a substep).
    pub events: Vec<Event>,
    /// Physics substeps in which Rapier stepped (some copter near something, or a wreck
    /// moving); the others were closed form only.
    pub rapier_substeps: u32,
    /// In a shard ([`crate::shard`]): copters whose contact cluster reached beyond the pull
    /// zone, or whose wake beyond the halo, this step. Not 0: this shard may no longer give
    /// the one-process run's bits, and the caller should stop.
    pub shard_violations: u32,
}

/// The stages of a step, in the order [`step_probed`] reports their ends. Some run on every
/// thread (per copter), some on one (Rapier, the passes over pairs and lists); a profiler
/// times them from outside (sim-core reads no clock): `examples/stages.rs`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    /// The step begins (nothing done yet).
    Begin,
    /// Every copter's motion into its lane.
    Lanes,
    /// Sensing: sonars, IR, IMU, estimates, cross-talk.
    Sense,
    /// The flight modes' setpoints.
    OuterLoops,
    /// Downwash and wakes between copters.
    Airflow,
    /// Each copter's reachable sphere, and which fly free or on watch.
    Reserve,
    /// Ownership (in a shard), watch pairs, falling wrecks, Rapier bodies entering or leaving.
    RapierSetup,
    /// A substep: the inner loops of the copters in Rapier (all copters on one thread).
    InRapierLanes,
    /// A substep: falling wrecks and the forces onto Rapier's bodies.
    RapierForces,
    /// A substep: Rapier's step, beside the free copters' inner loops on the other threads.
    RapierAndFreeLanes,
    /// A substep: Rapier's results into the lanes, collision crashes.
    RapierResults,
    /// A substep: tilt crashes and take-offs.
    TiltAndTakeOff,
    /// The lanes back into the copters' motion.
    Store,
}

/// [`step_into`], calling `probe` at the end of each [`Stage`] (physics stages once per
/// substep): the same bits as [`step_into`].
pub fn step_probed(
    world: &World,
    state: &mut State,
    inputs: &Inputs,
    report: &mut StepReport,
    probe: &mut (dyn FnMut(Stage) + Send),
) {
    step_with(world, state, inputs, report, probe);
}

/// Which copters a step reads and which it moves: all of them, or a shard's.
#[derive(Clone, Copy)]
struct Roles<'a>(Option<&'a [Role]>);

impl Roles<'_> {
    /// Read by this step (owned or a ghost).
    #[inline]
    fn present(self, i: usize) -> bool {
        self.0.is_none_or(|r| r[i] != Role::Absent)
    }

    /// Moved by this step.
    #[inline]
    fn owned(self, i: usize) -> bool {
        self.0.is_none_or(|r| r[i] == Role::Owned)
    }

    /// Sensed and controlled by this step: owned, or a ghost it may take over (not a far one).
    #[inline]
    fn near(self, i: usize) -> bool {
        self.0.is_none_or(|r| matches!(r[i], Role::Owned | Role::Ghost))
    }
}

/// Cell size of the copter grid used by sonars and cross-talk, m.
pub(crate) const GRID_CELL_M: Real = 1.0;

/// Height above the rest height that counts as airborne, m.
const TAKEOFF_MARGIN_M: Real = 0.05;

/// Extra clearance a free copter's reservation keeps from everything else, m.
const FREE_GAP_M: Real = 0.05;

/// Headroom on the thrust-limited acceleration when bounding a free copter's motion (covers
/// rotor tolerance and particle noise; a copter that still leaves its reservation is handed
/// back to Rapier at once).
const FREE_ACCEL_HEADROOM: Real = 2.0;

/// Advances the state by one control step. Never writes `inputs`. Copters without a command
/// in `inputs` keep their initial command.
///
/// With `world.params.threads > 1`, per-copter work (sensing, control, free flight) runs on a
/// thread pool owned by the state; everything is merged in id order, so the result is the
/// same bits for any thread count.
pub fn step(world: &World, state: &mut State, inputs: &Inputs) -> StepReport {
    let mut report = StepReport::default();
    step_into(world, state, inputs, &mut report);
    report
}

/// [`step`] into a report the caller keeps: its event list is cleared and refilled, so a
/// loop that reuses one report does not allocate for events once it has seen its busiest step.
pub fn step_into(world: &World, state: &mut State, inputs: &Inputs, report: &mut StepReport) {
    step_with(world, state, inputs, report, &mut |_| {});
}

fn step_with(
    world: &World,
    state: &mut State,
    inputs: &Inputs,
    report: &mut StepReport,
    probe: &mut (dyn FnMut(Stage) + Send),
) {
    probe(Stage::Begin);
    report.events.clear();
    // Room for a take-off or a crash of every copter at once, kept from step to step.
    report.events.reserve(2 * world.copters.len());
    report.rapier_substeps = 0;
    report.shard_violations = 0;
    let threads = world.params.threads.max(1);
    if threads == 1 {
        return step_on(world, state, inputs, false, report, probe);
    }
    let pool = match state.scratch.pool.take() {
        Some(pool) if pool.current_num_threads() == threads => Some(pool),
        _ => rayon::ThreadPoolBuilder::new().num_threads(threads).thread_name(|i| format!("sim-core-{i}")).build().ok(),
    };
    match pool {
        Some(pool) => {
            pool.install(|| step_on(world, state, inputs, true, report, probe));
            state.scratch.pool = Some(pool);
        }
        // No threads to be had: the same step, on this thread.
        None => step_on(world, state, inputs, false, report, probe),
    }
}

/// Runs `f` for every copter with its lane, in parallel chunks or in order. `f` must only
/// touch its own copter and lane: then the result does not depend on the chunking.
fn for_each_lane<F>(parallel: bool, copters: &mut [CopterState], lanes: &mut [Lane], f: F)
where
    F: Fn(usize, &mut CopterState, &mut Lane) + Sync + Send,
{
    for_each_chunk(parallel, copters, lanes, |first, cs, ls| {
        for (j, (c, l)) in cs.iter_mut().zip(ls.iter_mut()).enumerate() {
            f(first + j, c, l);
        }
    });
}

/// Runs `f` on chunks of copters with their lanes (and the first one's id), in parallel or
/// all in one. `f` must only touch the copters and lanes it is given.
fn for_each_chunk<F>(parallel: bool, copters: &mut [CopterState], lanes: &mut [Lane], f: F)
where
    F: Fn(usize, &mut [CopterState], &mut [Lane]) + Sync + Send,
{
    if parallel && copters.len() > 64 {
        use rayon::prelude::*;
        let chunk = lane_chunk(copters.len());
        let chunks = copters.par_chunks_mut(chunk).zip(lanes.par_chunks_mut(chunk));
        chunks.enumerate().for_each(|(k, (cs, ls))| f(k * chunk, cs, ls));
    } else {
        f(0, copters, lanes);
    }
}

/// Copters per parallel chunk of `n`: about 32 chunks, at least 32 copters each.
fn lane_chunk(n: usize) -> usize {
    (n / 32).max(32)
}

/// Fills `out` with `f(i)` for every `i` in `0..n`, in parallel chunks or in order (the same
/// values either way); `fill` only stands in until then.
fn fill_each<T>(parallel: bool, out: &mut Vec<T>, n: usize, fill: T, f: impl Fn(usize) -> T + Sync + Send)
where
    T: Copy + Send + Sync,
{
    out.clear();
    out.resize(n, fill);
    if parallel && n > 64 {
        use rayon::prelude::*;
        let chunk = lane_chunk(n);
        out.par_chunks_mut(chunk).enumerate().for_each(|(k, out)| {
            for (j, x) in out.iter_mut().enumerate() {
                *x = f(k * chunk + j);
            }
        });
    } else {
        for (i, x) in out.iter_mut().enumerate() {
            *x = f(i);
        }
    }
}

fn step_on(
    world: &World,
    state: &mut State,
    inputs: &Inputs,
    parallel: bool,
    report: &mut StepReport,
    probe: &mut (dyn FnMut(Stage) + Send),
) {
    let mut view = state.shard.take();
    step_copters(world, state, inputs, parallel, &mut view, report, probe);
    state.shard = view;
}

/// One control step of the copters, stage by stage: each copter's motion into its lane;
/// sensing ([`sense`]); the outer loops; the airflow between copters ([`airflow`]); which
/// copters fly free of Rapier ([`reserve_free_flight`]); the physics substeps
/// ([`physics_substep`]); the lanes back into the copters' motion.
fn step_copters(
    world: &World,
    state: &mut State,
    inputs: &Inputs,
    parallel: bool,
    view: &mut Option<ShardView>,
    report: &mut StepReport,
    probe: &mut (dyn FnMut(Stage) + Send),
) {
    let present = &mut state.scratch.present;
    present.clear();
    if let Some(v) = view {
        present.extend(v.roles.iter().enumerate().filter(|(_, r)| **r != Role::Absent).map(|(i, _)| i as u32));
    }
    // Before the ownership of this step is decided: what this shard owned at its start.
    let roles = Roles(view.as_ref().map(|v| &v.roles[..]));
    load_lanes(world, state, parallel);
    probe(Stage::Lanes);
    let sonar_period = world.sensors.spec.sonar.period_steps.max(1) as u64;
    if world.sensors.spec.enabled {
        sense(world, state, inputs, state.tick.is_multiple_of(sonar_period), parallel, roles);
    }
    probe(Stage::Sense);
    outer_loops(world, state, inputs, parallel, roles);
    probe(Stage::OuterLoops);
    report.shard_violations += airflow(world, state, parallel, roles);
    probe(Stage::Airflow);
    report.shard_violations += reserve_free_flight(world, state, parallel, view, probe);
    probe(Stage::RapierSetup);
    // From here on: what this shard owns for this step.
    let roles = Roles(view.as_ref().map(|v| &v.roles[..]));

    let dt = world.physics_dt();
    let scratch = &mut state.scratch;
    scratch.crash_cos_tilt.clear();
    scratch.crash_cos_tilt.extend(world.airframes.iter().map(|af| af.spec.crash_tilt_deg.to_radians().cos()));
    scratch.motor_alpha.clear();
    scratch.motor_alpha.extend(world.airframes.iter().map(|af| motor_alpha(af, dt)));
    let inner = InnerParams::new(world, dt);
    for s in 0..world.params.substeps {
        physics_substep(world, state, inner, roles, parallel, s, report, probe);
    }

    // The step's motion is the copters' (free copters' Rapier bodies stay where they were).
    for_each_lane(parallel, &mut state.copters, &mut state.scratch.lanes, |i, c, lane| {
        if roles.owned(i) {
            c.motion =
                Motion { pos_m: lane.pos_m, rot: lane.rot, vel_m_s: lane.vel_m_s, angvel_rad_s: lane.angvel_rad_s };
        }
    });
    state.tick += 1;
    report.tick = state.tick;
    probe(Stage::Store);
}

/// Every copter's motion at the start of the step, into its lane.
fn load_lanes(world: &World, state: &mut State, parallel: bool) {
    let lanes = &mut state.scratch.lanes;
    lanes.resize(world.copters.len(), Lane::default());
    for_each_lane(parallel, &mut state.copters, lanes, |i, c, lane| {
        let m = &c.motion;
        (lane.pos_m, lane.rot, lane.vel_m_s, lane.angvel_rad_s) = (m.pos_m, m.rot, m.vel_m_s, m.angvel_rad_s);
        lane.airframe = world.copters[i].airframe as u32;
        lane.flying = c.crash.is_none();
        lane.awaiting_takeoff = lane.flying && c.took_off_tick.is_none();
        lane.batched = 0;
    });
}

/// Each copter's flight mode: its setpoint for the step's inner loops.
fn outer_loops(world: &World, state: &mut State, inputs: &Inputs, parallel: bool, roles: Roles<'_>) {
    let command = |i: usize| -> &Command { inputs.commands.get(i).unwrap_or(&world.copters[i].initial_command) };
    let dt_control = world.params.control_dt_s as Real;
    let tick = state.tick;
    for_each_lane(parallel, &mut state.copters, &mut state.scratch.lanes, |i, c, lane| {
        if !roles.near(i) {
            return;
        }
        let af = &world.airframes[world.copters[i].airframe];
        let yaw = euler_from_quat(lane.rot)[2];
        c.setpoint = outer_loop(world, i, af, c, command(i), lane.pos_m, lane.vel_m_s, yaw, dt_control, tick);
    });
}

/// Physics substep `s` of every copter: inner loops and rotors; free copters move in closed
/// form, falling wrecks fall, the others go through Rapier; then crashes, tilts and take-offs.
///
/// With threads, the copters in Rapier go first (their forces go into Rapier's step), and
/// Rapier then steps on one thread while the free copters' inner loops run on the others: a
/// free copter's substep touches nothing of Rapier's, and nothing of it is read before
/// Rapier's step is done. On one thread, one pass in id order: the same bits.
#[allow(clippy::too_many_arguments, reason = "the substep's inputs, and the probe of step_probed")]
fn physics_substep(
    world: &World,
    state: &mut State,
    inner: InnerParams,
    roles: Roles<'_>,
    parallel: bool,
    s: u32,
    report: &mut StepReport,
    probe: &mut (dyn FnMut(Stage) + Send),
) {
    let dt = world.physics_dt();
    watch_contacts(state, dt);
    let scratch = &mut state.scratch;
    let parallel_rapier = parallel && !scratch.in_rapier.is_empty();
    let pass = SubstepPass { world, inner, alphas: &scratch.motor_alpha, cos_tilt: &scratch.crash_cos_tilt, roles, dt };
    let first = pass.closure(s, parallel_rapier.then_some(true));
    for_each_chunk(parallel, &mut state.copters, &mut scratch.lanes, first);
    probe(Stage::InRapierLanes);
    for k in 0..state.scratch.falling.len() {
        let i = state.scratch.falling[k] as usize;
        fall_wreck(world, state, i, dt);
        let lane = &mut state.scratch.lanes[i];
        lane.vel_before_m_s = lane.vel_m_s;
    }
    let (copters, falling) = (&state.copters, &mut state.scratch.falling);
    falling.retain(|&i| !copters[i as usize].grounded);
    // The others go through Rapier, in id order.
    let any_near = rapier_forces(state);
    probe(Stage::RapierForces);
    let scratch = &mut state.scratch;
    let rapier = |physics: &mut PhysicsWorld| {
        if any_near {
            physics.step_with_events(&(), &scratch.collisions);
        }
    };
    if parallel_rapier {
        let pass =
            SubstepPass { world, inner, alphas: &scratch.motor_alpha, cos_tilt: &scratch.crash_cos_tilt, roles, dt };
        let free_lanes = pass.closure(s, Some(false));
        let (physics, copters, lanes) = (&mut state.physics, &mut state.copters, &mut scratch.lanes);
        rayon::join(|| rapier(physics), || for_each_chunk(true, copters, lanes, free_lanes));
    } else {
        rapier(&mut state.physics);
    }
    probe(Stage::RapierAndFreeLanes);
    if any_near {
        report.rapier_substeps += 1;
        rapier_results(state);
        detect_collision_crashes(world, state, report);
    }
    probe(Stage::RapierResults);
    detect_tilt_and_takeoff(world, state, report, roles, parallel, s);
    probe(Stage::TiltAndTakeOff);
}

/// The forces and torques of the awake copters in Rapier onto their bodies; whether any is.
fn rapier_forces(state: &mut State) -> bool {
    let scratch = &state.scratch;
    let mut any_near = false;
    for &i in &scratch.in_rapier {
        let (lane, c) = (&scratch.lanes[i as usize], &state.copters[i as usize]);
        if lane.free {
            continue;
        }
        // A crashed copter at rest sleeps until something hits it. (Looked at first: a
        // mutable borrow marks a Rapier body modified, and Rapier then revisits it.)
        let body = &state.physics.bodies[c.body];
        if body.is_sleeping() || body.is_fixed() {
            continue;
        }
        let body = &mut state.physics.bodies[c.body];
        any_near = true;
        body.reset_forces(false);
        body.reset_torques(false);
        if c.crash.is_none() {
            body.add_force(lane.force_n, false);
            body.add_torque(lane.torque_n_m, false);
        }
    }
    any_near
}

/// After Rapier's step: its collision events, and its bodies' motion into their lanes.
fn rapier_results(state: &mut State) {
    let scratch = &mut state.scratch;
    // Poisoned only if Rapier's event collector panicked; its events are still good,
    // and losing them would lose crash detection.
    let mut started = scratch.collisions.started.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    std::mem::swap(&mut *started, &mut scratch.started);
    drop(started);
    for &i in &scratch.in_rapier {
        let (lane, c) = (&mut scratch.lanes[i as usize], &state.copters[i as usize]);
        if !lane.free {
            let body = &state.physics.bodies[c.body];
            lane.pos_m = body.translation();
            lane.rot = *body.rotation();
            lane.vel_m_s = body.linvel();
            lane.angvel_rad_s = body.angvel();
        }
    }
}

/// What a physics substep of the copters needs.
#[derive(Clone, Copy)]
struct SubstepPass<'a> {
    world: &'a World,
    inner: InnerParams,
    /// Motor lag per airframe.
    alphas: &'a [Real],
    /// Cosine of the crash tilt per airframe.
    cos_tilt: &'a [Real],
    roles: Roles<'a>,
    dt: Real,
}

impl<'a> SubstepPass<'a> {
    /// Substep `s` of every copter (`in_rapier: None`), of those in Rapier (`Some(true)`) or
    /// of those flying free (`Some(false)`), as a closure for [`for_each_lane`].
    ///
    /// A free copter off watch meets nothing but the floor in this control step: at substep
    /// 0 it runs its substeps one after the other while its state is in cache, up to the
    /// first after which something may happen to it ([`may_act`]: a crash, a take-off,
    /// leaving its reservation), and the later substeps take it on from there
    /// (`Lane::batched`). The same arithmetic, in another order: the same bits.
    ///
    /// Those that run ahead and have left the floor go four at a time ([`run_ahead_batch`]):
    /// their substeps on [`lanes`], the same bits.
    fn closure(
        self,
        s: u32,
        in_rapier: Option<bool>,
    ) -> impl Fn(usize, &mut [CopterState], &mut [Lane]) + Sync + Send + 'a {
        move |first, cs, ls| {
            let (mut batch, mut filled) = ([0; LANES], 0);
            for j in 0..cs.len() {
                let (i, c, lane) = (first + j, &mut cs[j], &mut ls[j]);
                if s < lane.batched || in_rapier.is_some_and(|r| r == lane.free) {
                    continue;
                }
                let ahead = s == 0 && lane.free && !lane.watch && c.crash.is_none() && self.roles.owned(i);
                if !ahead {
                    substep_lane(self.world, &self.inner, self.alpha(i), self.roles, i, c, lane, self.dt);
                    continue;
                }
                // A batch is of one airframe, in the air.
                let other_airframe = filled > 0 && ls[batch[0]].airframe != ls[j].airframe;
                if cs[j].grounded || other_airframe {
                    self.run_ahead(i, &mut cs[j], &mut ls[j]);
                    continue;
                }
                batch[filled] = j;
                filled += 1;
                if filled == LANES {
                    let (Ok(bc), Ok(bl)) = (cs.get_disjoint_mut(batch), ls.get_disjoint_mut(batch)) else {
                        unreachable!("a batch holds distinct copters")
                    };
                    run_ahead_batch(&self, batch.map(|j| first + j), bc, bl);
                    filled = 0;
                }
            }
            for &j in &batch[..filled] {
                self.run_ahead(first + j, &mut cs[j], &mut ls[j]);
            }
        }
    }

    fn alpha(&self, i: usize) -> Real {
        self.alphas[self.world.copters[i].airframe]
    }

    /// A free copter off watch runs its substeps one after the other, up to the first after
    /// which something may happen to it.
    fn run_ahead(&self, i: usize, c: &mut CopterState, lane: &mut Lane) {
        while lane.batched < self.world.params.substeps {
            substep_lane(self.world, &self.inner, self.alpha(i), self.roles, i, c, lane, self.dt);
            lane.batched += 1;
            if may_act(self.world, self.cos_tilt, lane) {
                break;
            }
        }
    }
}

/// One copter's physics substep: its inner loop and rotors (a wreck's motors are off), and,
/// flying free, its motion in closed form; in Rapier, the force and torque for Rapier's step.
/// Records its velocity before any contact of the substep (`vel_before_m_s`).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn substep_lane(
    world: &World,
    inner: &InnerParams,
    alpha: Real,
    roles: Roles<'_>,
    i: usize,
    c: &mut CopterState,
    lane: &mut Lane,
    dt: Real,
) {
    'motion: {
        // A wreck in closed form moves in the serial pass (`fall_wreck`).
        if !roles.owned(i) || (c.crash.is_some() && lane.free) {
            break 'motion;
        }
        let af = &world.airframes[world.copters[i].airframe];
        let twin = world.copters[i].kind == CopterKind::Real;
        // The body rates, read by the gyros and the closed-form step alike.
        let rate_body = lane.rot.inverse() * lane.angvel_rad_s;
        let (thrust_n, torque_body_n_m) = match c.crash {
            Some(_) => (0.0, Vec3::ZERO),
            None => inner_loop(af, inner, twin, c, &InnerInput::of(lane, rate_body), dt, alpha),
        };
        if lane.free {
            let vel_before = lane.vel_m_s;
            if c.grounded && !lifts_off(af, lane, thrust_n) {
                break 'motion;
            }
            c.grounded = false;
            integrate_free(af, lane, rate_body, thrust_n, torque_body_n_m, dt);
            // Higher than any collider reaches, it cannot touch the floor.
            if lane.pos_m.z > af.reach_bound_m {
                break 'motion;
            }
            let below = lowest_point_below_centre(af, lane.rot);
            if lane.pos_m.z - below < 0.0 {
                touch_floor(af, c, lane, vel_before, below);
            }
        } else {
            lane.force_n = lane.rot * Vec3::new(0.0, 0.0, thrust_n) + lane.downwash_force_n;
            lane.torque_n_m = lane.rot * torque_body_n_m + lane.downwash_torque_n_m;
        }
    }
    lane.vel_before_m_s = lane.vel_m_s;
}

/// Decides which copters fly free of Rapier for this control step.
///
/// A copter flies free when the sphere it can reach within the step (its colliders' bounding
/// radius plus `|v| T + a_max T² / 2`, with `a_max` from its maximum thrust with headroom and
/// gravity) keeps [`FREE_GAP_M`] from the walls, the ceiling, the boxes and every other
/// copter's reachable sphere. Nothing but the floor can then touch it during the step, and the
/// floor is met in closed form ([`touch_floor`]), so Rapier has nothing to do for it: its body
/// is disabled and it is integrated in closed form (semi-implicit Euler, Rapier's damping and
/// gyroscopic terms). A copter whose sphere meets only other copters' flies free on watch
/// ([`watch_contacts`]). Wrecks fall and rest in closed form too ([`fall_wreck`]), their
/// bodies fixed in Rapier where flying copters can hit them.
fn reserve_free_flight(
    world: &World,
    state: &mut State,
    parallel: bool,
    view: &mut Option<ShardView>,
    probe: &mut (dyn FnMut(Stage) + Send),
) -> u32 {
    let roles = Roles(view.as_ref().map(|v| &v.roles[..]));
    reserve_spheres(world, state, parallel, roles);
    sort_free_and_watched(world, state, parallel, roles);
    probe(Stage::Reserve);
    // A shard decides which copters it steps now: the reservations are known.
    let violations = view.as_mut().map_or(0, |v| take_ownership(state, v));
    let roles = Roles(view.as_ref().map(|v| &v.roles[..]));
    gather_watch_pairs(state, roles);
    gather_falling(world, state, roles);
    enable_rapier_bodies(world, state, view);
    let roles = Roles(view.as_ref().map(|v| &v.roles[..]));
    let scratch = &mut state.scratch;
    scratch.in_rapier.clear();
    // Room for every copter, so that entering Rapier during the step never grows it.
    scratch.in_rapier.reserve(scratch.lanes.len());
    let lanes = scratch.lanes.iter().enumerate();
    scratch.in_rapier.extend(lanes.filter(|(i, l)| !l.free && roles.owned(*i)).map(|(i, _)| i as u32));
    violations
}

/// Each copter's reachable sphere for the step (`Lane::reserved_m`, and per substep
/// `substep_reserved_m`), and the grid of them.
fn reserve_spheres(world: &World, state: &mut State, parallel: bool, roles: Roles<'_>) {
    let t = world.params.control_dt_s as Real;
    let dt = world.physics_dt();
    let scratch = &mut state.scratch;
    for_each_lane(parallel, &mut state.copters, &mut scratch.lanes, |i, c, lane| {
        let af = &world.airframes[world.copters[i].airframe];
        let tol = c.rotor_tolerance.iter().copied().fold(1.0, Real::max);
        // A wreck's motors are off: only gravity and contacts move it.
        let a_max = if c.crash.is_some() {
            GRAVITY_M_S2
        } else {
            FREE_ACCEL_HEADROOM * 4.0 * af.max_thrust_per_rotor_n * tol / af.mass_kg
                + GRAVITY_M_S2
                + lane.downwash_force_n.length() / af.mass_kg
        };
        lane.anchor_m = lane.pos_m;
        lane.reach_m = lane.vel_m_s.length() * t + 0.5 * a_max * t * t;
        let radius = af.radius_m.hypot(af.spec.body_size_m[2] / 2.0) + 0.01;
        lane.reserved_m = radius + lane.reach_m;
        lane.substep_reserved_m = radius + 0.5 * a_max * dt * dt;
    });
    let lanes = &scratch.lanes;
    fill_each(parallel, &mut scratch.spheres, lanes.len(), OrientedBox::default(), |i| OrientedBox {
        center: lanes[i].pos_m,
        rotation: crate::math::Quat::IDENTITY,
        half: Vec3::new(lanes[i].reserved_m, 0.0, 0.0),
    });
    scratch.sphere_grid.set_cover(arena_rect(world));
    match roles.0 {
        Some(_) => scratch.sphere_grid.build_some(&scratch.spheres, &scratch.present, GRID_CELL_M),
        None => scratch.sphere_grid.build(&scratch.spheres, GRID_CELL_M),
    }
}

/// Which copters fly free (their spheres clear of the walls, the ceiling and the boxes) and,
/// of those, which on watch (their spheres meet another copter's).
fn sort_free_and_watched(world: &World, state: &mut State, parallel: bool, roles: Roles<'_>) {
    let scratch = &mut state.scratch;
    let spheres = &scratch.spheres;
    let grid = &scratch.sphere_grid;
    let arena = &world.arena;
    let (hx, hy) = (arena.size_m[0] / 2.0, arena.size_m[1] / 2.0);
    let closed_form = world.params.closed_form;
    for_each_lane(parallel, &mut state.copters, &mut scratch.lanes, |i, c, lane| {
        if !roles.present(i) {
            (lane.free, lane.watch) = (false, false);
            return;
        }
        lane.floor_impact_m_s = 0.0;
        // A wreck in closed form falls and lies outside Rapier's dynamics (`fall_wreck`).
        if c.crash.is_some() && closed_form {
            (lane.free, lane.watch) = (true, false);
            return;
        }
        let (p, r) = (lane.pos_m, lane.reserved_m + FREE_GAP_M);
        // The floor needs no clearance: free flight meets it in closed form.
        let mut free = c.crash.is_none() && closed_form;
        if free && arena.walls {
            free = p.x.abs() + r < hx && p.y.abs() + r < hy && p.z + r < arena.height_m;
        }
        if free {
            free = world.boxes.iter().all(|b| b.is_farther_than(p, r));
        }
        // Clear of the walls and boxes but near other copters: on watch.
        let mut watch = false;
        if free {
            grid.visit_near(p, r, |j| {
                if j != i && (spheres[j].center - p).length() <= r + spheres[j].half.x {
                    watch = true;
                }
                if watch { -1.0 } else { r }
            });
        }
        lane.free = free;
        lane.watch = watch;
        // Rapier keeps a copter on the floor itself; back in free flight it lands anew.
        c.grounded &= free;
    });
}

/// Everything a copter on watch may come close to this step (once per pair; in a shard,
/// both are its own: they are in one contact cluster).
fn gather_watch_pairs(state: &mut State, roles: Roles<'_>) {
    let scratch = &mut state.scratch;
    scratch.watch_pairs.clear();
    // A few neighbours per copter, kept from step to step.
    scratch.watch_pairs.reserve(4 * scratch.lanes.len());
    for (i, lane) in scratch.lanes.iter().enumerate().filter(|&(i, l)| l.watch && roles.owned(i)) {
        let (p, r) = (lane.pos_m, lane.reserved_m + FREE_GAP_M);
        let (spheres, lanes, pairs) = (&scratch.spheres, &scratch.lanes, &mut scratch.watch_pairs);
        scratch.sphere_grid.visit_near(p, r, |j| {
            if j != i && !(lanes[j].watch && j < i) && (spheres[j].center - p).length() <= r + spheres[j].half.x {
                pairs.push((i as u32, j as u32));
            }
            r
        });
    }
}

/// The wrecks this shard moves in closed form, in id order.
fn gather_falling(world: &World, state: &mut State, roles: Roles<'_>) {
    let scratch = &mut state.scratch;
    scratch.falling.clear();
    // Room for every copter, so that a crash never grows it.
    scratch.falling.reserve(scratch.lanes.len());
    if world.params.closed_form {
        let owned_falling = |(i, c): (usize, &CopterState)| c.crash.is_some() && !c.grounded && roles.owned(i);
        scratch.falling.extend(state.copters.iter().enumerate().filter(|&ic| owned_falling(ic)).map(|(i, _)| i as u32));
    }
}

/// Each copter's Rapier body enabled for the step if it goes through Rapier, disabled if it
/// flies free or belongs to another shard; a wreck a shard has just taken over enters as its
/// owner had it.
fn enable_rapier_bodies(world: &World, state: &mut State, view: &Option<ShardView>) {
    let closed_form = world.params.closed_form;
    for (i, (lane, c)) in state.scratch.lanes.iter().zip(&state.copters).enumerate() {
        // Borrowed mutably only when something changes: a mutable borrow marks a Rapier body
        // modified, and Rapier's next step revisits every modified body.
        let body = &state.physics.bodies[c.body];
        if let Some(v) = view {
            // Another shard's copter is not in this shard's Rapier world.
            if v.roles[i] != Role::Owned {
                if body.is_enabled() {
                    state.physics.bodies[c.body].set_enabled(false);
                }
                continue;
            }
            // A wreck this shard has just taken over enters as its owner had it.
            if c.crash.is_some() && !body.is_enabled() {
                if closed_form {
                    // Disabled here, so the same body (the handle does not change).
                    fix_wreck(world, &mut state.physics, c.body, lane, i, !c.grounded);
                } else {
                    take_over_wreck(&mut state.physics.bodies[c.body], lane, v.asleep[i]);
                }
                continue;
            }
        }
        // A wreck's body is fixed (closed form) or Rapier's from its crash on.
        if c.crash.is_some() || lane.free != body.is_enabled() {
            continue;
        }
        let body = &mut state.physics.bodies[c.body];
        if lane.free {
            body.set_enabled(false);
        } else {
            enter_rapier(body, lane);
        }
    }
}

/// A shard's ownership for this step (see [`crate::shard`]): copters whose reservations
/// meet form contact clusters, and a cluster belongs to the home region of its lowest id,
/// unless Rapier carries one of its copters over from the last step: then it stays with the
/// shard whose Rapier world holds the lowest such copter ([`held_clusters`]).
/// Counts the violations: a cluster this shard had or takes a copter of, with a member
/// beyond the pull zone (its view of that cluster may be incomplete).
fn take_ownership(state: &mut State, view: &mut ShardView) -> u32 {
    use crate::shard::{PULL_ZONE_M, root, union};
    let scratch = &mut state.scratch;
    let n = state.copters.len();
    let parent = &mut view.parent;
    parent.clear();
    parent.extend(0..n as u32);
    let (spheres, grid) = (&scratch.spheres, &scratch.sphere_grid);
    for &i in &scratch.present {
        let sphere = &spheres[i as usize];
        let (p, r) = (sphere.center, sphere.half.x + FREE_GAP_M);
        grid.visit_near(p, r, |j| {
            if j > i as usize && (spheres[j].center - p).length() <= r + spheres[j].half.x {
                union(parent, i, j as u32);
            }
            r
        });
    }
    held_clusters(state, view);
    let scratch = &state.scratch;
    let (me, part) = (view.me, &view.partition);
    let (parent, related) = (&mut view.parent, &mut view.related);
    related.clear();
    related.resize(n, false);
    for &i in &scratch.present {
        let home = root(parent, i);
        let owner = view.claim[home as usize].unwrap_or_else(|| part.region_of(scratch.lanes[home as usize].pos_m));
        let was = view.roles[i as usize];
        let now = match (owner == me, was) {
            (true, _) => Role::Owned,
            (false, Role::Far) => Role::Far,
            (false, _) => Role::Ghost,
        };
        if was == Role::Owned || now == Role::Owned {
            related[home as usize] = true;
        }
        view.roles[i as usize] = now;
    }
    let mut violations = 0;
    for &i in &scratch.present {
        let home = root(parent, i);
        if related[home as usize] && part.distance_to(scratch.lanes[i as usize].pos_m, me) > PULL_ZONE_M {
            violations += 1;
        }
    }
    violations
}

/// Which clusters stay where Rapier holds them (`ShardView::claim`, per cluster root). A
/// copter that Rapier moved in the last step and that is not free now keeps its Rapier body,
/// with the contact memory (speculative contacts, warm starts, the island) that one process
/// keeps; another shard would take it over fresh. So it stays with the shard that holds it
/// (this one's own copters from its Rapier world, ghosts as their owners sent them), and its
/// cluster with it, while it is within [`crate::shard::HELD_ZONE_M`] of that shard's region.
/// Not covered, and not counted: a held copter farther out than that, and the second of two
/// copters held by different shards that come into one cluster, go to the cluster's owner
/// fresh (docs/sharding.md).
fn held_clusters(state: &State, view: &mut ShardView) {
    use crate::shard::{HELD_ZONE_M, held_in_rapier, root};
    let n = state.copters.len();
    view.claim.clear();
    view.claim.resize(n, None);
    // The present copters, in id order: a cluster goes with its lowest held copter.
    for &i in &state.scratch.present {
        let i = i as usize;
        if view.roles[i] == Role::Owned {
            let held = state.physics.bodies.get(state.copters[i].body).is_some_and(held_in_rapier);
            view.held_by[i] = held.then_some(view.me);
        }
        let lane = &state.scratch.lanes[i];
        let Some(k) = view.held_by[i] else { continue };
        if (lane.free && !lane.watch) || view.partition.distance_to(lane.pos_m, k) > HELD_ZONE_M {
            continue;
        }
        let home = root(&mut view.parent, i as u32) as usize;
        view.claim[home].get_or_insert(k);
    }
}

/// A wreck that has just become this shard's enters its Rapier world as its owner had it
/// (`closed_form = false`; in closed form it is fixed, [`fix_wreck`]): a dynamic body, asleep
/// if it was.
fn take_over_wreck(body: &mut RigidBody, lane: &Lane, asleep: bool) {
    body.set_enabled(true);
    body.set_translation(lane.pos_m, false);
    body.set_rotation(lane.rot, false);
    body.set_linvel(lane.vel_m_s, false);
    body.set_angvel(lane.angvel_rad_s, false);
    let activation = body.activation_mut();
    *activation = RigidBodyActivation::active();
    activation.time_until_sleep = WRECK_TIME_UNTIL_SLEEP_S;
    body.set_body_type(RigidBodyType::Dynamic, false);
    if asleep {
        body.sleep();
    }
}

/// A copter enters Rapier: its body takes the lane's pose and velocities, enabled and awake.
fn enter_rapier(body: &mut RigidBody, lane: &Lane) {
    body.set_enabled(true);
    body.wake_up(true);
    body.set_translation(lane.pos_m, false);
    body.set_rotation(lane.rot, false);
    body.set_linvel(lane.vel_m_s, false);
    body.set_angvel(lane.angvel_rad_s, false);
}

/// Hands copters on watch to Rapier when they may touch something within this substep: two
/// copters whose spheres (bounding radius plus `|v| dt + a_max dt² / 2` and [`FREE_GAP_M`])
/// meet both go to Rapier (a copter already in Rapier, a wreck for one, is there), for the rest
/// of the control step. Copters on watch never meet anything else: their reservations overlap
/// only each other's.
fn watch_contacts(state: &mut State, dt: Real) {
    let scratch = &mut state.scratch;
    for &(i, j) in &scratch.watch_pairs {
        let (i, j) = (i as usize, j as usize);
        let (a, b) = (&scratch.lanes[i], &scratch.lanes[j]);
        if !(a.watch || b.watch) {
            continue;
        }
        let reach = |l: &Lane| l.substep_reserved_m + l.vel_m_s.length() * dt;
        if (a.pos_m - b.pos_m).length() > reach(a) + reach(b) + FREE_GAP_M {
            continue;
        }
        for k in [i, j] {
            let lane = &mut scratch.lanes[k];
            if !lane.watch {
                continue;
            }
            let c = &mut state.copters[k];
            enter_rapier(&mut state.physics.bodies[c.body], lane);
            (lane.free, lane.watch, c.grounded) = (false, false, false);
            insert_sorted(&mut scratch.in_rapier, k as u32);
        }
    }
}

/// Air for this control step: the surface below each copter (ground effect) and the
/// downwash force and torque each copter feels from the wakes of the others, from the motion
/// and rotor thrusts at the start of the step (see [`crate::airflow`]).
///
/// Wakes are indexed in a grid by their origin and reach, so each copter only visits the
/// wakes that can touch it: the cost grows with the copters, not with their pairs. Twins make
/// wakes (their real copters blow on the virtual ones) but feel none (their motion is their
/// real copter's). Crashed copters neither make nor feel any.
fn airflow(world: &World, state: &mut State, parallel: bool, roles: Roles<'_>) -> u32 {
    let spec = &world.airflow.spec;
    for_each_lane(parallel, &mut state.copters, &mut state.scratch.lanes, |i, _, lane| {
        if !roles.present(i) {
            return;
        }
        let real_layer = world.copters[i].kind.is_real_layer();
        let af = &world.airframes[world.copters[i].airframe];
        lane.ground_m = match spec.ground_effect && may_be_over_a_box(world, lane.pos_m, af.reach_bound_m) {
            true => af.rotor_pos_in_body_m.map(|arm| ground_below(world, lane.pos_m + lane.rot * arm, real_layer)),
            false => [0.0; 4],
        };
        lane.downwash_force_n = Vec3::ZERO;
        lane.downwash_torque_n_m = Vec3::ZERO;
    });
    if !spec.downwash || world.copters.len() < 2 {
        return 0;
    }
    let (violations, any) = gather_wakes(world, state, parallel, roles);
    if any {
        let scratch = &mut state.scratch;
        scratch.wake_grid.set_cover(arena_rect(world));
        match roles.0 {
            Some(_) => scratch.wake_grid.build_some(&scratch.wake_reach, &scratch.present, GRID_CELL_M),
            None => scratch.wake_grid.build(&scratch.wake_reach, GRID_CELL_M),
        }
        feel_wakes(world, state, parallel, roles);
    }
    violations
}

/// Every copter's wake and its reach (a box around its origin, for the grid) into the scratch.
/// Returns the wakes reaching beyond a shard's halo, and whether any copter makes one.
fn gather_wakes(world: &World, state: &mut State, parallel: bool, roles: Roles<'_>) -> (u32, bool) {
    let spec = &world.airflow.spec;
    let scratch = &mut state.scratch;
    let (lanes, copters) = (&scratch.lanes, &state.copters);
    fill_each(parallel, &mut scratch.wakes, lanes.len(), Wake::default(), |i| {
        let (lane, c) = (&lanes[i], &copters[i]);
        let af = &world.airframes[world.copters[i].airframe];
        let thrust: Real = c.rotor_thrust_n.iter().sum();
        let dir = lane.rot * Vec3::NEG_Z;
        let origin = lane.pos_m + lane.rot * Vec3::new(0.0, 0.0, af.rotor_pos_in_body_m[0].z);
        let active = c.crash.is_none()
            && thrust > 0.1 * af.hover_thrust_per_rotor_n
            && dir.z < -0.2
            && origin.z > 0.0
            && roles.present(i);
        if !active {
            // Reaches nothing, from where it would start (`wake_reach` is centred there).
            return Wake { origin, ..Wake::default() };
        }
        let rho_a = af.spec.air_density_kg_m3 * af.disc_area_m2;
        let hubs = af.rotor_pos_in_body_m.map(|arm| lane.pos_m + lane.rot * arm);
        Wake {
            origin,
            dir,
            v0_m_s: (0.5 * thrust / rho_a).sqrt(),
            b0_m: af.spec.rotor_diameter_m,
            length_m: origin.z / -dir.z,
            hubs,
            hub_v0_m_s: c.rotor_thrust_n.map(|t| (2.0 * t.max(0.0) / rho_a).sqrt()),
            hubs_reach_m: hubs.iter().map(|h| (*h - origin).length()).fold(0.0, Real::max),
            hub_b0_m: 0.5 * af.spec.rotor_diameter_m,
            merge_m: spec.wake_merge_sizes * 2.0 * af.spec.arm_length_m,
        }
    });
    let wakes = &scratch.wakes;
    let width_per_m = world.airflow.width_per_m;
    // An active wake is one with a length (its origin above the floor, pointing down).
    let reach = |w: &Wake| if w.length_m > 0.0 { w.reach_m(width_per_m) } else { 0.0 };
    fill_each(parallel, &mut scratch.wake_reach, wakes.len(), OrientedBox::default(), |i| OrientedBox {
        center: wakes[i].origin,
        rotation: Quat::IDENTITY,
        half: Vec3::new(reach(&wakes[i]), 0.0, 0.0),
    });
    let wake_limit = crate::shard::sense_reach_m(world);
    let (mut violations, mut any) = (0, false);
    for (i, w) in scratch.wakes.iter().enumerate() {
        any |= w.length_m > 0.0;
        // A shard's neighbours see its copters only within the halo.
        if roles.0.is_some() && roles.owned(i) && scratch.wake_reach[i].half.x > wake_limit {
            violations += 1;
        }
    }
    (violations, any)
}

/// The downwash force and torque each flying virtual copter feels from the wakes near it (the
/// wake grid built), at the rotor speeds and thrusts of the step's start.
fn feel_wakes(world: &World, state: &mut State, parallel: bool, roles: Roles<'_>) {
    let spec = &world.airflow.spec;
    let width_per_m = world.airflow.width_per_m;
    let scratch = &mut state.scratch;
    let (wakes, grid) = (&scratch.wakes, &scratch.wake_grid);
    let turbulence = spec.wake_turbulence;
    for_each_lane(parallel, &mut state.copters, &mut scratch.lanes, |i, c, lane| {
        if c.crash.is_some() || world.copters[i].kind == CopterKind::Real || !roles.near(i) {
            return;
        }
        let af = &world.airframes[world.copters[i].airframe];
        let (k, rotor_r) = (spec.rotor_inflow_k, 0.5 * af.spec.rotor_diameter_m);
        let ct0 = af.spec.thrust_coeff_n_s2 / (af.spec.air_density_kg_m3 * af.disc_area_m2 * rotor_r * rotor_r);
        let axis = lane.rot * Vec3::Z;
        let (mut force, mut torque) = (Vec3::ZERO, Vec3::ZERO);
        let radius = af.radius_m;
        let arms = af.rotor_pos_in_body_m.map(|arm| lane.rot * arm);
        let arms_reach = arms.iter().map(|a| a.length()).fold(0.0, Real::max);
        grid.visit_near(lane.pos_m, radius, |j| {
            let w = &wakes[j];
            if j == i || w.length_m <= 0.0 || w.is_still_near(lane.pos_m, arms_reach, width_per_m, rotor_r) {
                return radius;
            }
            for (r, &arm) in arms.iter().enumerate() {
                let v = w.speed_over_disc(lane.pos_m + arm, width_per_m, rotor_r);
                if v > MIN_WAKE_SPEED_M_S {
                    // The inflow through this rotor's disc, and the thrust it costs along the
                    // rotor's axis (at the rotor speed and thrust of the step's start).
                    let v = v * (1.0 + turbulence * c.rng.triangular()).max(0.0);
                    let inflow = v * -w.dir.dot(axis);
                    let omega = c.rotor_speed_rad_s[r];
                    let kept = inflow_thrust_factor(inflow, omega, rotor_r, k, ct0);
                    let f = axis * -((1.0 - kept) * c.rotor_thrust_n[r].max(0.0));
                    force += f;
                    torque += arm.cross(f);
                }
            }
            radius
        });
        lane.downwash_force_n = force;
        lane.downwash_torque_n_m = torque;
    });
}

/// Wake speeds below this are not applied, m/s (their force is under 4 mN per rotor).
const MIN_WAKE_SPEED_M_S: Real = 0.05;

/// Whether a point within `reach_m` of `p` may have a box's top under it (see
/// [`ground_below`]): some box's top above the floor lies up to 1 m below it, its footprint
/// within `reach_m` horizontally.
#[inline]
fn may_be_over_a_box(world: &World, p: Vec3, reach_m: Real) -> bool {
    world.boxes.iter().any(|b| {
        let top = b.top_m();
        top > 0.0 && top <= p.z + reach_m && p.z - reach_m - top <= 1.0 && b.footprint_may_be_within(p, reach_m)
    })
}

/// Height of the surface below a point: the floor, or the top of a box under it. Real-layer
/// copters skip boxes that exist only in the simulation (a real copter flies over nothing
/// there).
fn ground_below(world: &World, p: Vec3, real_layer: bool) -> Real {
    let mut ground = 0.0;
    for b in &world.boxes {
        let top = b.top_m();
        if top <= ground
            || top > p.z
            || p.z - top > 1.0
            || (real_layer && b.virtual_only)
            || !b.footprint_may_be_within(p, 0.0)
        {
            continue;
        }
        let local = Quat::from_rotation_z(-b.yaw_rad) * (p - b.center_m);
        if local.x.abs() <= b.half_extents_m.x && local.y.abs() <= b.half_extents_m.y {
            ground = top;
        }
    }
    ground
}

/// What the inner loop needs of the world, computed once per step.
#[derive(Clone, Copy)]
struct InnerParams {
    /// The AHRS lag's blend factor for one physics step.
    ahrs_alpha: Real,
    att_sigma: Real,
    rate_sigma: Real,
    noise: bool,
    ideal: bool,
    ground_effect: bool,
    ground_effect_min_radii: Real,
}

impl InnerParams {
    fn new(world: &World, dt: Real) -> Self {
        let spec = &world.sensors.spec;
        let lag = spec.estimator.ahrs_lag_s;
        Self {
            ahrs_alpha: if lag > 0.0 { 1.0 - (-dt / lag).exp() } else { 1.0 },
            att_sigma: spec.imu.attitude_noise_deg.to_radians(),
            rate_sigma: spec.imu.rate_noise_deg_s.to_radians(),
            noise: spec.noise && spec.enabled,
            ideal: spec.estimator.ideal || !spec.enabled,
            ground_effect: world.airflow.spec.ground_effect,
            ground_effect_min_radii: world.airflow.spec.ground_effect_min_height_radii,
        }
    }
}

/// AHRS, height hold, attitude PIDs, mixer, rotor model and battery of a flying copter.
/// Returns the total thrust along body z, N, and the torque in the body frame, N·m.
///
/// The controllers read the copter's estimates (twins and `ideal` estimation: the truth).
#[inline]
fn inner_loop(
    af: &Airframe,
    p: &InnerParams,
    twin: bool,
    c: &mut CopterState,
    m: &InnerInput,
    dt: Real,
    alpha: Real,
) -> (Real, Vec3) {
    let (collective, torque) = steer(af, p, twin, c, m, dt);
    drive(af, p, twin, c, m, collective, torque, dt, alpha)
}

/// The inner loop's first half: AHRS, height hold and attitude PIDs. Returns the collective
/// thrust and the torque they command, N and N·m in the body frame.
#[inline]
fn steer(af: &Airframe, p: &InnerParams, twin: bool, c: &mut CopterState, m: &InnerInput, dt: Real) -> (Real, Vec3) {
    let InnerInput { rot, rpy, rate_body, z_m, vz_m_s, .. } = *m;
    let rate = [rate_body.x, rate_body.y, rate_body.z];
    let truth = twin || p.ideal;
    let (z, vz, cos_tilt) = if truth {
        c.estimate.ideal(rpy, c.yaw_bias_rad, rate);
        (z_m, vz_m_s, (rot * Vec3::Z).z)
    } else {
        let rng = if p.noise { Some(&mut c.rng) } else { None };
        c.estimate.ahrs(rpy, c.yaw_bias_rad, rate, p.ahrs_alpha, p.att_sigma, p.rate_sigma, rng);
        let e = &c.estimate;
        (e.height_m, e.vz_m_s, math::cos(e.attitude_rad[0]) * math::cos(e.attitude_rad[1]))
    };
    let e = &mut c.estimate;
    let mut collective = control::collective_thrust_n(
        af,
        &c.setpoint,
        z,
        vz,
        cos_tilt,
        &mut e.height_integral_n,
        &mut e.landing_stalled_s,
        dt,
    );
    if !twin {
        collective /= e.thrust_gain;
    }
    e.collective_sum_n += collective;
    e.collective_steps += 1;
    // The trim cancels the rotors' tolerances in thrust actually made; in commands, like the
    // collective, that is the trim over the thrust gain (a full pack makes more per command).
    let torque = control::attitude_torque(af, &mut c.pids, &c.setpoint, e.attitude_rad, Vec3::from(e.rate_rad_s), dt)
        + Vec3::new(c.trim_torque_n_m[0], c.trim_torque_n_m[1], 0.0) / e.thrust_gain;
    (collective, torque)
}

/// The inner loop's second half: mixer, ground effect, rotor model and battery, from the
/// commanded collective and torque. Returns the total thrust along body z, N, and the torque
/// in the body frame, N·m.
#[allow(clippy::too_many_arguments)]
#[inline]
fn drive(
    af: &Airframe,
    p: &InnerParams,
    twin: bool,
    c: &mut CopterState,
    m: &InnerInput,
    collective: Real,
    torque: Vec3,
    dt: Real,
    alpha: Real,
) -> (Real, Vec3) {
    let InnerInput { rot, z_m, ground_m, .. } = *m;
    let wanted = match c.setpoint.rotors {
        Some(u) => u.map(|u| u * af.max_thrust_per_rotor_n),
        None => control::mix(af, collective, torque),
    };
    // Each rotor over the surface below it.
    let mut ground = [1.0; 4];
    let radius = 0.5 * af.spec.rotor_diameter_m;
    // No rotor lies lower than the reach bound below the centre (a millimetre covers rounding).
    let lowest = z_m - af.reach_bound_m - ground_m.iter().copied().fold(0.0, Real::max);
    if p.ground_effect && lowest < GROUND_EFFECT_RADII * radius + 1e-3 {
        for ((g, arm), below) in ground.iter_mut().zip(&af.rotor_pos_in_body_m).zip(ground_m) {
            let height = z_m + (rot * *arm).z - below;
            // Less what it is at the cut-off, so that a rotor crossing it sees no step.
            if height < GROUND_EFFECT_RADII * radius {
                let at_cut_off = ground_effect_ratio(radius, GROUND_EFFECT_RADII * radius, p.ground_effect_min_radii);
                *g = 1.0 + ground_effect_ratio(radius, height, p.ground_effect_min_radii) - at_cut_off;
            }
        }
    }
    let spec = &af.spec.battery;
    let scale = if twin { 1.0 } else { c.battery.speed_scale(spec) };
    let yaw_torque = rotor_model(af, c, wanted, dt, alpha, ground, scale);
    let mut thrust = 0.0;
    let mut torque_body = Vec3::new(0.0, 0.0, yaw_torque);
    let mut induced_power = 0.0;
    for r in 0..4 {
        let f = c.rotor_thrust_n[r];
        thrust += f;
        induced_power += f * f.max(0.0).sqrt();
        torque_body += af.rotor_pos_in_body_m[r].cross(Vec3::new(0.0, 0.0, f));
    }
    if !twin {
        let power = induced_power / af.sqrt_2_rho_a / spec.efficiency;
        c.battery.draw(spec, power, dt);
    }
    (thrust, torque_body)
}

/// What the inner loop reads of a copter's motion at the start of a substep.
#[derive(Clone, Copy)]
struct InnerInput {
    rot: Quat,
    /// Its Euler angles ([`euler_from_quat`]).
    rpy: [Real; 3],
    /// Its angular velocity in the body frame, rad/s.
    rate_body: Vec3,
    /// Height of the centre of mass and its vertical speed, m and m/s.
    z_m: Real,
    vz_m_s: Real,
    /// `Lane::ground_m`.
    ground_m: [Real; 4],
}

impl InnerInput {
    #[inline(always)]
    fn of(lane: &Lane, rate_body: Vec3) -> Self {
        let (rot, z_m, vz_m_s, ground_m) = (lane.rot, lane.pos_m.z, lane.vel_m_s.z, lane.ground_m);
        Self { rot, rpy: euler_from_quat(rot), rate_body, z_m, vz_m_s, ground_m }
    }
}

/// Ground effect is computed only below this many rotor radii (above, it is under 0.2 %).
const GROUND_EFFECT_RADII: Real = 12.0;

/// One physics step of a free-flying copter in closed form: gravity, thrust, torque, Rapier's
/// linear and angular damping (`v / (1 + c dt)`) and its explicit, momentum-preserving
/// gyroscopic term; semi-implicit Euler (velocities first, then pose with the new ones).
/// `rate_body` is its angular velocity in the body frame.
#[inline(always)]
fn integrate_free(af: &Airframe, lane: &mut Lane, rate_body: Vec3, thrust_n: Real, torque_body_n_m: Vec3, dt: Real) {
    let rot = lane.rot;
    let acc = rot * Vec3::new(0.0, 0.0, thrust_n / af.mass_kg) + lane.downwash_force_n / af.mass_kg
        - Vec3::new(0.0, 0.0, GRAVITY_M_S2);
    let vel = (lane.vel_m_s + acc * dt) * (1.0 / (1.0 + dt * af.spec.linear_damping));
    let inertia = Vec3::from(af.inertia_kg_m2);
    let torque_body_n_m = torque_body_n_m + rot.inverse() * lane.downwash_torque_n_m;
    let mut w_b = rate_body + torque_body_n_m / inertia * dt;
    let l = inertia * w_b;
    let l_gyro = l - w_b.cross(l) * dt;
    let n2 = l_gyro.length_squared();
    if n2 > 0.0 {
        w_b = l_gyro * (l.length_squared() / n2).sqrt() / inertia;
    }
    let w = rot * (w_b * (1.0 / (1.0 + dt * af.spec.angular_damping)));
    lane.vel_m_s = vel;
    lane.angvel_rad_s = w;
    lane.pos_m += vel * dt;
    // q̇ = ½ ω q, one explicit step, renormalised (|ω| dt is a few milliradians).
    let half_w = w * (0.5 * dt);
    let dq = Quat::from_xyzw(half_w.x, half_w.y, half_w.z, 0.0) * rot;
    lane.rot = (rot + dq).normalize();
}

/// Whether a copter resting on the floor leaves it this substep: its thrust and the downwash
/// on it lift more than its weight.
#[inline]
fn lifts_off(af: &Airframe, lane: &Lane, thrust_n: Real) -> bool {
    (lane.rot * Vec3::new(0.0, 0.0, thrust_n)).z + lane.downwash_force_n.z > af.mass_kg * GRAVITY_M_S2
}

/// How far the lowest point of a copter's colliders (body box, rotor discs) lies below its
/// centre of mass at attitude `rot`, m.
#[inline]
fn lowest_point_below_centre(af: &Airframe, rot: Quat) -> Real {
    reach_along(af, rot, -Vec3::Z)
}

/// How far a copter's colliders (body box, rotor discs) reach from its centre of mass along
/// the unit direction `d`, at attitude `rot`, m: their support function.
#[inline]
fn reach_along(af: &Airframe, rot: Quat, d: Vec3) -> Real {
    let [bx, by, bz] = af.spec.body_size_m;
    // How far each body axis points along d.
    let (ex, ey, ez) = ((rot * Vec3::X).dot(d), (rot * Vec3::Y).dot(d), (rot * Vec3::Z).dot(d));
    let body = 0.5 * (bx * ex.abs() + by * ey.abs() + bz * ez.abs());
    // A disc of radius r with axis body z reaches r·sin(angle to d) along d (plus its half
    // thickness along the axis).
    let reach =
        0.5 * af.spec.rotor_diameter_m * (1.0 - ez * ez).max(0.0).sqrt() + ROTOR_DISC_HALF_THICKNESS_M * ez.abs();
    af.rotor_pos_in_body_m.iter().fold(body, |far, arm| far.max(reach + (rot * *arm).dot(d)))
}

/// A free copter's colliders reached the floor during this substep. Slower than the crash
/// impact speed (the rule of Rapier's floor contacts: the downward speed before the
/// substep), it lands: level at its rest
/// height, heading kept, at rest, held there until its thrust lifts it. Faster, it is lifted
/// back onto the floor's surface and marked for the crash that the serial pass records (the
/// wreck then falls in Rapier).
fn touch_floor(af: &Airframe, c: &mut CopterState, lane: &mut Lane, vel_before: Vec3, below: Real) {
    let speed = -vel_before.z;
    if speed > af.spec.crash_impact_speed_m_s {
        lane.pos_m.z = below;
        lane.floor_impact_m_s = speed;
        return;
    }
    let fwd = lane.rot * Vec3::X;
    lane.rot = Quat::from_rotation_z(fwd.y.atan2(fwd.x));
    lane.pos_m.z = af.rest_height_m;
    lane.vel_m_s = Vec3::ZERO;
    lane.angvel_rad_s = Vec3::ZERO;
    c.grounded = true;
}

/// Motor lag, saturation, battery voltage, ground effect, tolerance and particle noise.
/// Writes the rotor speeds and thrusts; returns the yaw drag torque about body z, N·m.
///
/// The ESC's command is the speed the wanted thrust needs at the calibration voltage (at most
/// full duty); the rotor turns `speed_scale` times that. `ground[r]` multiplies rotor `r`'s
/// thrust.
#[inline]
fn rotor_model(
    af: &Airframe,
    c: &mut CopterState,
    wanted_n: [Real; 4],
    dt: Real,
    alpha: Real,
    ground: [Real; 4],
    speed_scale: Real,
) -> Real {
    let mut yaw = 0.0;
    for r in 0..4 {
        let omega_cmd = (wanted_n[r].max(0.0) / af.k_n_s2).sqrt().min(af.omega_max_rad_s) * speed_scale;
        let omega = c.rotor_speed_rad_s[r] + alpha * (omega_cmd - c.rotor_speed_rad_s[r]);
        c.rotor_speed_rad_s[r] = omega;
        let tol = c.rotor_tolerance[r];
        let mean = tol * af.thrust_at(omega) * ground[r];
        // Particles: rate ṅ = (ρA / 2 m_px) v_final, v_final = c ω; each carries m_px v_final.
        let lambda = af.particle_rate_per_v_final_per_m * af.v_final_per_omega_m * omega * dt;
        let thrust = match af.spec.particle_noise {
            ParticleNoise::Off => mean,
            _ if lambda <= 0.0 => 0.0,
            ParticleNoise::Dither => {
                // floor() of a non-negative number, as a truncating cast (no libm call).
                let count = (lambda + c.rng.uniform()) as u32 as Real;
                mean * count / lambda
            }
            ParticleNoise::Poisson => mean * c.rng.poisson(lambda) as Real / lambda,
        };
        c.rotor_thrust_n[r] = thrust;
        yaw += ROTOR_YAW_SIGN[r] * tol * af.d_n_m_s2 * omega * omega;
    }
    yaw
}

/// The motor lag's blend factor for one physics step, `1 − exp(−dt / τ)`.
fn motor_alpha(af: &Airframe, dt: Real) -> Real {
    let tau = af.spec.motor_time_constant_s;
    if tau > 0.0 { 1.0 - (-dt / tau).exp() } else { 1.0 }
}

/// The flight mode's outer loop.
#[allow(clippy::too_many_arguments)]
fn outer_loop(
    world: &World,
    id: usize,
    af: &Airframe,
    c: &mut CopterState,
    cmd: &Command,
    pos_m: Vec3,
    vel_m_s: Vec3,
    true_yaw_rad: Real,
    dt: Real,
    tick: u64,
) -> Setpoint {
    let mut sp = Setpoint {
        roll_rad: cmd.roll_rad,
        pitch_rad: cmd.pitch_rad,
        yaw_rad: cmd.yaw_rad,
        height_m: cmd.height_m,
        throttle: cmd.throttle,
        rotors: None,
    };
    match cmd.mode {
        FlightMode::Manual | FlightMode::MixedManual => {}
        FlightMode::Velocity => {
            if let Some(v) = cmd.velocity_m_s {
                (sp.pitch_rad, sp.roll_rad) = velocity_tilt(af, v);
            }
        }
        FlightMode::Rotors => sp.rotors = Some(cmd.rotors.unwrap_or([0.0; 4]).map(|u| u.clamp(0.0, 1.0))),
        FlightMode::Target => {
            if let Some(t) = cmd.target_m {
                let (pitch, roll) = control::target_tilt(t, pos_m, vel_m_s, true_yaw_rad);
                sp.pitch_rad = pitch;
                sp.roll_rad = roll;
                sp.height_m = t[2].max(af.rest_height_m + 0.1);
            }
        }
        FlightMode::WallAvoid => {
            let pilot = match cmd.velocity_m_s {
                Some(v) => velocity_tilt(af, v),
                None => (sp.pitch_rad, sp.roll_rad),
            };
            (sp.pitch_rad, sp.roll_rad) = match world.sensors.spec.wall_avoid.controller {
                WallAvoidController::Firmware => wall_avoid_firmware(world, c, pilot, dt, tick),
                WallAvoidController::Pd => wall_avoid_pd(world, af, c, cmd, pilot, dt, tick),
            };
        }
    }
    // A copter holding height on its IR cannot hold one beyond the IR's range: the setpoint
    // stays 0.1 m inside it (twins and ideal estimation hold any height).
    let est = &world.sensors.spec;
    if sp.height_m > 0.0 && world.copters[id].kind != CopterKind::Real && !est.estimator.ideal && est.enabled {
        sp.height_m = sp.height_m.min(est.ir.max_range_m - 0.1);
    }
    sp
}

/// Wall-Avoid as the FINken firmware flies it: the lead-lag at its own rate on the filtered
/// sonar differences, plus the pilot's (pitch, roll), each scaled down towards an obstacle
/// on its side. Returns (pitch, roll), rad.
fn wall_avoid_firmware(world: &World, c: &mut CopterState, pilot: (Real, Real), dt: Real, tick: u64) -> (Real, Real) {
    let spec = &world.sensors.spec.wall_avoid;
    let every = ((1.0 / (spec.update_hz * dt)).round() as u64).max(1);
    let st = &mut c.wall_avoid;
    if world.sensors.spec.enabled && st.filter_ready() && tick.is_multiple_of(every) {
        control::wall_avoid_firmware(spec, st);
    }
    let [front, right, back, left] = st.filtered_m;
    let ready = st.filter_ready();
    let scale = |input: Real, ahead: Real, behind: Real| match () {
        _ if !ready => input,
        _ if input > 0.0 => input * control::pilot_scale(spec, ahead),
        _ => input * control::pilot_scale(spec, behind),
    };
    // Pitch > 0 flies forward (towards the front sonar), roll > 0 flies right.
    (st.out_rad[0] + scale(pilot.0, front, back), st.out_rad[1] + scale(pilot.1, right, left))
}

/// Wall-Avoid's PD (`controller = "pd"`), on every full round of sonar readings: the velocity
/// command, open loop, is obeyed as long as it keeps a safe distance (paper, III): a component
/// towards a sonar that sees something inside the safety distance is dropped, the rest flies,
/// and avoidance adds its push. Returns (pitch, roll), rad.
#[allow(clippy::too_many_arguments)]
fn wall_avoid_pd(
    world: &World,
    af: &Airframe,
    c: &mut CopterState,
    cmd: &Command,
    pilot: (Real, Real),
    dt: Real,
    tick: u64,
) -> (Real, Real) {
    let spec = &world.sensors.spec.wall_avoid;
    let sonar = &world.sensors.spec.sonar;
    let fused = c.sensors.sonar_fused_m;
    let period = sonar.period_steps.max(1) as u64;
    let (round, last_of_round) = match sonar.schedule {
        SonarSchedule::Together => (period, true),
        SonarSchedule::RoundRobin => (4 * period, tick / period % 4 == 3),
    };
    // The PD runs on a fresh round of readings, with the round as its time step; between
    // rounds the last output holds.
    let fresh = c.sensors.sonar_tick == tick && last_of_round;
    let avoid = if !world.sensors.spec.enabled || fused == [0.0; 4] {
        None
    } else if fresh {
        control::wall_avoid(spec, &mut c.wall_avoid, fused, dt * round as Real)
    } else {
        (c.wall_avoid.out_rad != [0.0; 2]).then_some((c.wall_avoid.out_rad[0], c.wall_avoid.out_rad[1]))
    };
    let (pitch, roll) = match cmd.velocity_m_s {
        Some([mut v_fwd, mut v_left]) => {
            if avoid.is_some() {
                let inside = |k: usize| fused[k] < spec.safety_distance_m;
                let [front, right, back, left] = [0, 1, 2, 3];
                if (v_fwd > 0.0 && inside(front)) || (v_fwd < 0.0 && inside(back)) {
                    v_fwd = 0.0;
                }
                if (v_left > 0.0 && inside(left)) || (v_left < 0.0 && inside(right)) {
                    v_left = 0.0;
                }
            }
            velocity_tilt(af, [v_fwd, v_left])
        }
        None => pilot,
    };
    match (avoid, cmd.velocity_m_s) {
        (Some((p, r)), Some(_)) => {
            let max = spec.max_tilt_deg.to_radians();
            ((pitch + p).clamp(-max, max), (roll + r).clamp(-max, max))
        }
        (Some(avoid), None) => avoid,
        (None, _) => (pitch, roll),
    }
}

/// The velocity command, open loop: the (pitch, roll) whose steady state against the linear
/// damping is `v` (forward, left), m/s. The FINken measures no velocity of its own.
fn velocity_tilt(af: &Airframe, [v_fwd, v_left]: [Real; 2]) -> (Real, Real) {
    let k = af.spec.linear_damping / GRAVITY_M_S2;
    ((k * v_fwd).atan(), -(k * v_left).atan())
}

/// Gathers what sonars can see in the current state: the arena walls, the static boxes and
/// every copter's body (crashed ones too), indexed in the copter grid. `sense` uses it; so can
/// tools that need the same geometry (e.g. extra virtual sonars).
pub fn fill_sonar_scene(world: &World, copters: &[CopterState], scene: &mut SonarScene) {
    fill_sonar_scene_of(world, copters, None, false, scene);
}

/// [`fill_sonar_scene`] seeing only the copters in `present` (ascending ids), if given.
fn fill_sonar_scene_of(
    world: &World,
    copters: &[CopterState],
    present: Option<&[u32]>,
    parallel: bool,
    scene: &mut SonarScene,
) {
    let (hx, hy) = (world.arena.size_m[0] / 2.0, world.arena.size_m[1] / 2.0);
    scene.walls.clear();
    if world.arena.walls {
        scene.walls.extend([(Vec3::X, hx), (Vec3::X, -hx), (Vec3::Y, hy), (Vec3::Y, -hy)]);
    }
    if world.sensors.spec.sonar.floor_echo {
        scene.walls.push((Vec3::Z, 0.0));
        if world.arena.walls {
            scene.walls.push((Vec3::Z, world.arena.height_m));
        }
    }
    scene.boxes.clear();
    scene.boxes.extend(world.boxes.iter().map(|b| OrientedBox {
        center: b.center_m,
        rotation: crate::math::Quat::from_rotation_z(b.yaw_rad),
        half: b.half_extents_m,
    }));
    fill_each(parallel, &mut scene.copters, copters.len(), OrientedBox::default(), |i| copter_box(world, copters, i));
    scene.grid.set_cover(arena_rect(world));
    match present {
        Some(ids) => scene.index_some_copters(ids, grid_cell_m(world, copters.len())),
        None => scene.index_copters(grid_cell_m(world, copters.len())),
    }
}

/// The real layer's sonar scene (see [`CopterKind::Autopilot`]): the full scene without the
/// `virtual_only` boxes, indexing only the real-layer copters among those `present`.
fn fill_real_scene(
    world: &World,
    copters: &[CopterState],
    present: Option<&[u32]>,
    ids: &mut Vec<u32>,
    scene: &mut SonarScene,
) {
    fill_sonar_scene_of(world, copters, None, false, scene);
    scene.boxes.clear();
    scene.boxes.extend(world.boxes.iter().filter(|b| !b.virtual_only).map(|b| OrientedBox {
        center: b.center_m,
        rotation: crate::math::Quat::from_rotation_z(b.yaw_rad),
        half: b.half_extents_m,
    }));
    ids.clear();
    let real = |i: u32| world.copters[i as usize].kind.is_real_layer();
    match present {
        Some(p) => ids.extend(p.iter().copied().filter(|&i| real(i))),
        None => ids.extend((0..copters.len() as u32).filter(|&i| real(i))),
    }
    scene.index_some_copters(ids, grid_cell_m(world, copters.len()));
}

/// A copter grid's cell size for `n` items: about one item per cell, so sparse swarms visit
/// fewer empty cells (any cell size gives the same readings).
fn grid_cell_m(world: &World, n: usize) -> Real {
    let area_m2 = world.arena.size_m[0] * world.arena.size_m[1];
    (area_m2 / n.max(1) as Real).sqrt().clamp(GRID_CELL_M, 4.0 * GRID_CELL_M)
}

/// The arena's floor rectangle, `[x0, y0, x1, y1]`, m.
fn arena_rect(world: &World) -> [Real; 4] {
    let (hx, hy) = (world.arena.size_m[0] / 2.0, world.arena.size_m[1] / 2.0);
    [-hx, -hy, hx, hy]
}

/// The box a sonar sees of copter `i`: its rotor disc square and body height.
pub fn copter_box(world: &World, copters: &[CopterState], i: usize) -> OrientedBox {
    let m = &copters[i].motion;
    let af = &world.airframes[world.copters[i].airframe];
    let half_xy = af.spec.arm_length_m / std::f32::consts::SQRT_2 + af.spec.rotor_diameter_m / 2.0;
    OrientedBox {
        center: m.pos_m,
        rotation: m.rot,
        half: Vec3::new(half_xy, half_xy, af.spec.body_size_m[2] / 2.0 + 0.01),
    }
}

/// The sensing stage, once per control step, from the lanes (each copter's motion at the start
/// of the step): what the sonars can see, gathered once; each
/// copter's sonars and IR ([`read_ranges`]), IMU and estimators ([`read_imu_and_estimate`]);
/// the sonars' cross-talk ([`crosstalk`]); the fused readings into the firmware's sonar
/// filter ([`fuse_and_filter`]).
fn sense(world: &World, state: &mut State, inputs: &Inputs, sonar_due: bool, parallel: bool, roles: Roles<'_>) {
    let scratch = &mut state.scratch;
    let present = roles.0.map(|_| &scratch.present[..]);
    fill_sonar_scene_of(world, &state.copters, present, parallel, &mut scratch.sonar_scene);
    let autopilots = world.copters.iter().any(|c| c.kind == CopterKind::Autopilot);
    if autopilots {
        fill_real_scene(world, &state.copters, present, &mut scratch.real_ids, &mut scratch.real_scene);
    }
    if sonar_due {
        gather_pingers(world, state, parallel, roles);
    }
    let scratch = &mut state.scratch;
    let (scene, real_scene, pingers) = (&scratch.sonar_scene, &scratch.real_scene, &scratch.pingers);
    let p = SenseParams::new(world, state.tick, sonar_due);
    for_each_lane(parallel, &mut state.copters, &mut scratch.lanes, |i, c, lane| {
        // A wreck's sensors stop (and its sonars no longer ping): its readings keep their
        // last values.
        if c.crash.is_some() || !roles.near(i) {
            return;
        }
        let real_layer = autopilots && world.copters[i].kind == CopterKind::Autopilot;
        let cones = pingers.get(i).map(|p| &p.cones);
        let ir = read_ranges(world, &p, if real_layer { real_scene } else { scene }, i, cones, c, lane);
        read_imu_and_estimate(world, &p, i, c, lane, ir);
    });
    if sonar_due && world.sensors.spec.crosstalk.enabled && world.copters.len() > 1 {
        crosstalk(world, state, &p, parallel);
    }
    fuse_and_filter(world, state, inputs, &p, parallel, roles);
}

/// What every copter's sensing shares in one control step.
struct SenseParams {
    tick: u64,
    dt_control: Real,
    sonar_due: bool,
    /// Which sonars this step reads ([`fresh_sonars`]).
    fresh: [bool; 4],
    /// The yaw bias's decay and random walk over the step.
    yaw_decay: Real,
    yaw_walk: Real,
    /// The reported heading's noise per reading, rad.
    yaw_sigma: Real,
}

impl SenseParams {
    fn new(world: &World, tick: u64, sonar_due: bool) -> Self {
        let spec = &world.sensors.spec;
        let dt_control = world.params.control_dt_s as Real;
        let yaw_tau = spec.imu.yaw_bias_time_s;
        Self {
            tick,
            dt_control,
            sonar_due,
            fresh: fresh_sonars(spec, tick, sonar_due),
            yaw_decay: if yaw_tau > 0.0 { (-dt_control / yaw_tau).exp() } else { 1.0 },
            yaw_walk: spec.imu.yaw_bias_walk_deg_per_sqrt_s.to_radians() * dt_control.sqrt(),
            yaw_sigma: spec.imu.yaw_noise_deg.to_radians(),
        }
    }
}

/// Every copter's sonar cones and ping timing, for a sonar update ([`read_ranges`] and
/// [`crosstalk`]); a wreck's or an absent copter's sonars are silent.
fn gather_pingers(world: &World, state: &mut State, parallel: bool, roles: Roles<'_>) {
    let (copters, lanes) = (&state.copters, &state.scratch.lanes);
    fill_each(parallel, &mut state.scratch.pingers, world.copters.len(), Pinger::default(), |i| {
        let (lane, c) = (&lanes[i], &copters[i]);
        let pings = c.crash.is_none() && roles.present(i);
        Pinger {
            pos_m: lane.pos_m,
            cones: if pings { sonar_cones(&world.sensors, lane.pos_m, lane.rot) } else { Default::default() },
            phase_s: c.sonar_phase_s,
            cycle_s: c.sonar_cycle_s,
            pings,
        }
    });
}

/// A copter's fresh sonars (when due: `cones` from [`gather_pingers`]) and its IR, down the
/// body's −z axis, in `scene`. Returns the IR reading before its range check (the height
/// estimator takes it as it is).
#[inline]
fn read_ranges(
    world: &World,
    p: &SenseParams,
    scene: &SonarScene,
    i: usize,
    cones: Option<&[Cone; 4]>,
    c: &mut CopterState,
    lane: &Lane,
) -> Real {
    let params = &world.sensors;
    let spec = &params.spec;
    let (pos, rot) = (lane.pos_m, lane.rot);
    let r = &mut c.sensors;
    if p.sonar_due
        && let Some(cones) = cones
    {
        r.sonar_tick = p.tick;
        let truths = scene.cone_distances_of(cones, p.fresh, pos, i, spec.sonar.max_range_m);
        for (s, &truth) in truths.iter().enumerate().filter(|(s, _)| p.fresh[*s]) {
            let nz = if spec.noise { spec.sonar.noise_sigma_m * c.rng.normal() } else { 0.0 };
            r.sonar_truth_m[s] = truth.min(spec.sonar.cap_m);
            r.sonar_m[s] = sonar_reading(&spec.sonar, truth, nz);
            r.sonar_crosstalk[s] = false;
        }
    }
    let ir_truth = scene.ir_distance(pos, rot * Vec3::NEG_Z, i);
    r.ir_truth_m = ir_truth;
    let ir_noise = if spec.noise {
        (spec.ir.noise_sigma_m + spec.ir.noise_sigma_rel * ir_truth.min(10.0)) * c.rng.normal()
    } else {
        0.0
    };
    let ir = ir_truth + ir_noise;
    r.ir_m = (ir_truth.is_finite() && (spec.ir.min_range_m..=spec.ir.max_range_m).contains(&ir)).then_some(ir);
    ir
}

/// A copter's IMU, its estimators (height from the IR reading `ir`, the AHRS's slow biases,
/// the thrust gain) and the readings telemetry sends. A twin's IMU is ideal: it flies by its
/// real copter's telemetry, and noise or a drifting yaw of its own would only add to its error.
#[inline]
fn read_imu_and_estimate(world: &World, p: &SenseParams, i: usize, c: &mut CopterState, lane: &Lane, ir: Real) {
    let spec = &world.sensors.spec;
    let (pos, rot, vel, angvel) = (lane.pos_m, lane.rot, lane.vel_m_s, lane.angvel_rad_s);
    let twin = world.copters[i].kind == CopterKind::Real;
    let noise = spec.noise && !twin;
    if noise {
        c.yaw_bias_rad = wrap_angle_rad(c.yaw_bias_rad * p.yaw_decay + p.yaw_walk * c.rng.normal());
    }
    let acc_world = if p.tick == 0 { Vec3::ZERO } else { (vel - c.prev_vel_m_s) / p.dt_control };
    let specific = rot.inverse() * (acc_world + Vec3::new(0.0, 0.0, GRAVITY_M_S2));
    let mut nrm = |sigma: Real| if noise { sigma * c.rng.normal() } else { 0.0 };
    let a_sigma = spec.imu.accel_noise_m_s2;
    let accel = Vec3::new(specific.x + nrm(a_sigma), specific.y + nrm(a_sigma), specific.z + nrm(a_sigma));
    c.sensors.accel_body_m_s2 = accel.into();
    c.prev_vel_m_s = vel;
    let est = &mut c.estimate;
    let ideal = spec.estimator.ideal;
    if twin || ideal {
        let rpy = euler_from_quat(rot);
        let rate_b = rot.inverse() * angvel;
        est.ideal(rpy, c.yaw_bias_rad, rate_b.into());
        est.ideal_height(pos.z, vel.z);
    } else {
        let az = (rot * accel).z - GRAVITY_M_S2;
        est.update_height(&spec.estimator, &spec.ir, ir, az, p.dt_control);
        if noise {
            est.wander_bias(&spec.estimator, p.dt_control, &mut c.rng);
        }
    }
    // The thrust gain (ideal estimation adapts too: it is a parameter, not a state).
    let af = &world.airframes[world.copters[i].airframe];
    let cos_tilt = math::cos(est.attitude_rad[0]) * math::cos(est.attitude_rad[1]);
    let flying = c.crash.is_none() && c.took_off_tick.is_some() && est.height_m > 0.1 && cos_tilt > 0.8;
    if flying && !twin {
        est.adapt_thrust(&spec.estimator, af.mass_kg, 4.0 * af.hover_thrust_per_rotor_n, accel.z, p.dt_control);
    } else {
        est.collective_sum_n = 0.0;
        est.collective_steps = 0;
    }
    // The AHRS output the attitude loop last read (telemetry sends these), with the
    // reported heading's own noise (`yaw_noise_deg`, per reading, as the telemetry's yaw).
    let r = &mut c.sensors;
    r.attitude_rad = est.attitude_rad;
    if noise && !ideal {
        r.attitude_rad[2] = wrap_angle_rad(r.attitude_rad[2] + p.yaw_sigma * c.rng.normal());
    }
    r.yaw_bias_rad = c.yaw_bias_rad;
    r.rate_body_rad_s = est.rate_rad_s;
    r.height_est_m = est.height_m;
    r.battery_v = c.battery.voltage_v;
    r.battery_charge = c.battery.charge;
    r.battery_a = c.battery.current_a;
}

/// Cross-talk: copter A's pings heard by copter B's fresh sonars. Each copter's sonars ping
/// on its own cycle; B's reading is shortened when a ping of A arrives after B's own ping and
/// before its echo. Each listener looks for emitters only in the grid cells under its fresh
/// sonar's cone (a [`Wedge`]), and writes only its own readings: a reading is a minimum, the
/// same in any order and on any thread.
fn crosstalk(world: &World, state: &mut State, p: &SenseParams, parallel: bool) {
    let params = &world.sensors;
    let (ct, sonar) = (&params.spec.crosstalk, &params.spec.sonar);
    let now_s = world.time_at(p.tick);
    let stagger = if sonar.schedule == SonarSchedule::RoundRobin { 0.25 } else { 0.0 };
    let crate::state::Scratch { pingers, ping_points, ping_grid, lanes, .. } = &mut state.scratch;
    ping_points.clear();
    ping_points.extend(pingers.iter().enumerate().filter(|(_, p)| p.pings).map(|(i, p)| (i as u32, p.pos_m)));
    ping_grid.set_cover(arena_rect(world));
    // The wedges reach the sonars' full range: cells twice the usual size visit fewer rows
    // and cells per wedge (any size gives the same readings).
    ping_grid.build_points(ping_points, 2.0 * grid_cell_m(world, ping_points.len()));
    let (pingers, grid) = (&*pingers, &*ping_grid);
    // Emitter sonar j can reach listener sonar k only if each apex lies in the other's
    // cone. With apexes `mount_offset_m` from the centres, that needs
    // `(p_b − p_a)·axis_j ≥ cos_h (|p_b − p_a| − 2 offset)` and the same for k: a necessary
    // condition on the centres that skips most of the exact tests. It holds only near the
    // listener's cone from its centre ([`crosstalk_growth`]): the wedge's growth.
    let slack = 2.0 * sonar.mount_offset_m;
    let cos_h = params.sonar_cos_half;
    let sin_h = params.sonar_sin_half;
    let reach = sonar.max_range_m + slack;
    let grow = crosstalk_growth(params.sonar_half_angle_rad, slack);
    // What listener `b`'s sonar `k` reads of each of emitter `a`'s pings it hears. The tests
    // are those of a visit of the pair from its lower id: the same bits whichever listens.
    let listen = |b: usize, k: usize, a: usize, readings: &mut sensors::SensorReadings| {
        let (lo, hi) = if b < a { (b, a) } else { (a, b) };
        let d_c = pingers[lo].pos_m - pingers[hi].pos_m;
        let dist_c = d_c.length();
        if dist_c > reach {
            return;
        }
        let need = cos_h * (dist_c - slack) - 1e-4;
        let sees =
            |i: usize, cone: &Cone| if i == lo { -d_c.dot(cone.axis) >= need } else { d_c.dot(cone.axis) >= need };
        let (listener, emitter) = (&pingers[b], &pingers[a]);
        let ear = &listener.cones[k];
        if !sees(b, ear) {
            return;
        }
        for (j, mouth) in emitter.cones.iter().enumerate().filter(|(_, mouth)| sees(a, mouth)) {
            let (cone_hi, cone_lo) = if a == hi { (mouth, ear) } else { (ear, mouth) };
            let Some(d) = crosstalk_eligible(cone_hi, cone_lo, sonar.max_range_m) else { continue };
            if let Some(q) = heard_reading(listener, k, emitter, j, d, now_s, stagger, sonar, ct.speed_of_sound_m_s) {
                lower_reading(readings, k, q);
            }
        }
    };
    let fresh = p.fresh;
    for_each_lane(parallel, &mut state.copters, lanes, |b, c, _| {
        let me = &pingers[b];
        if !me.pings {
            return;
        }
        for k in (0..4).filter(|&k| fresh[k]) {
            let wedge = Wedge::of_cone(me.pos_m, me.cones[k].axis, sin_h);
            grid.visit_over(me.pos_m, reach, (&wedge, grow), |a| {
                if a != b {
                    listen(b, k, a, &mut c.sensors);
                }
            });
        }
    });
}

/// How far from the cone of half-angle `h` (apex at the origin, axis `u`) a point `v` with
/// `v·u ≥ cos h (|v| − slack) − 1e-4` can lie, at most, m: cross-talk's pre-test on the centres.
///
/// With `c = cos h · slack + 1e-4`, a point at angle `θ > h` from the axis passes when `|v| (cos h
/// − cos θ) ≤ c`; its distance to the cone is `|v| sin(θ − h)` (or `|v|` beyond `h + 90°`), and
/// `sin(θ − h) / (cos h − cos θ) = cos((θ − h)/2) / sin((θ + h)/2) ≤ 1 / sin((θ + h)/2)`, whose
/// half-sum lies in `[h, min(h + 45°, 90° + h/2)]`. A millimetre of margin covers rounding.
fn crosstalk_growth(h: Real, slack: Real) -> Real {
    let c = h.cos() * slack + 1e-4;
    let least_sin = h.sin().min((h + std::f32::consts::FRAC_PI_4).sin()).min((0.5 * h).cos());
    c / least_sin.max(1e-3) + 1e-3
}

/// Each copter's readings fused with its virtual ones (`min`), and each fresh fused reading
/// into the firmware's sonar filter (a wreck's sonars are silent).
fn fuse_and_filter(
    world: &World,
    state: &mut State,
    inputs: &Inputs,
    p: &SenseParams,
    parallel: bool,
    roles: Roles<'_>,
) {
    let wall_avoid = &world.sensors.spec.wall_avoid;
    for_each_lane(parallel, &mut state.copters, &mut state.scratch.lanes, |i, c, _| {
        let virt = inputs.commands.get(i).and_then(|c| c.virtual_sonar_m);
        let r = &mut c.sensors;
        r.sonar_fused_m = sensors::fuse_min(r.sonar_m, virt);
        if p.sonar_due && c.crash.is_none() && roles.near(i) {
            for k in (0..4).filter(|&k| p.fresh[k]) {
                c.wall_avoid.filter(wall_avoid, k, r.sonar_fused_m[k]);
            }
        }
    });
}

/// Which sonars a sonar update at `tick` reads: all four, or the firmware's one in turn.
pub fn fresh_sonars(spec: &sensors::SensorSpec, tick: u64, sonar_due: bool) -> [bool; 4] {
    match spec.sonar.schedule {
        _ if !sonar_due => [false; 4],
        SonarSchedule::Together => [true; 4],
        SonarSchedule::RoundRobin => {
            let k = (tick / spec.sonar.period_steps.max(1) as u64 % 4) as usize;
            std::array::from_fn(|s| s == k)
        }
    }
}

/// What listener sonar `k` reads of emitter sonar `j`'s ping, `d` apart, if it arrives within
/// range: after the listener's own last ping before `now_s` and before its echo (each copter's
/// sonars ping on its own cycle, staggered by a quarter cycle each in round robin).
#[allow(clippy::too_many_arguments)]
#[inline]
fn heard_reading(
    listener: &Pinger,
    k: usize,
    emitter: &Pinger,
    j: usize,
    d: Real,
    now_s: f64,
    stagger: f64,
    sonar: &sensors::SonarSpec,
    speed_of_sound_m_s: Real,
) -> Option<Real> {
    let phase = listener.phase_s + stagger * k as f64 * listener.cycle_s;
    let listen_s = phase + ((now_s - phase) / listener.cycle_s).floor() * listener.cycle_s;
    let emitted_s = emitter.phase_s + stagger * j as f64 * emitter.cycle_s;
    let v = crosstalk_reading(listen_s, emitted_s, emitter.cycle_s, d, speed_of_sound_m_s);
    (v <= sonar.max_range_m).then(|| sensors::quantise(v.clamp(sonar.min_range_m, sonar.cap_m), sonar.quantum_m))
}

/// A cross-talk reading replaces sonar `k`'s when it is shorter.
#[inline]
fn lower_reading(r: &mut sensors::SensorReadings, k: usize, q: Real) {
    if q < r.sonar_m[k] {
        r.sonar_m[k] = q;
        r.sonar_crosstalk[k] = true;
    }
}

/// Turns collision starts into crashes.
fn detect_collision_crashes(world: &World, state: &mut State, report: &mut StepReport) {
    let started = std::mem::take(&mut state.scratch.started);
    for &(h1, h2) in &started {
        let t1 = state.physics.colliders.get(h1).and_then(|c| ColliderTag::decode(c.user_data));
        let t2 = state.physics.colliders.get(h2).and_then(|c| ColliderTag::decode(c.user_data));
        let (Some(t1), Some(t2)) = (t1, t2) else { continue };
        for (me, other) in [(t1, t2), (t2, t1)] {
            let ColliderTag::Copter(i) = me else { continue };
            if state.copters[i].crash.is_some() {
                continue;
            }
            let af = &world.airframes[world.copters[i].airframe];
            let v = state.scratch.lanes.get(i).map_or(Vec3::ZERO, |l| l.vel_before_m_s);
            let limit = af.spec.crash_impact_speed_m_s;
            let cause = match other {
                ColliderTag::Wall => Some(CrashCause::Wall),
                ColliderTag::Ceiling => Some(CrashCause::Ceiling),
                ColliderTag::Box(index) => Some(CrashCause::Box { index }),
                // The floor: its normal speed (a copter drifting sideways as it lands is not an
                // impact).
                ColliderTag::Floor => (-v.z > limit).then_some(CrashCause::Floor { speed_m_s: -v.z }),
                ColliderTag::Copter(j) if j != i => {
                    let vj = state.scratch.lanes.get(j).map_or(Vec3::ZERO, |l| l.vel_before_m_s);
                    let rel = (v - vj).length();
                    (rel > limit).then_some(CrashCause::Copter { other: j, speed_m_s: rel })
                }
                ColliderTag::Copter(_) => None,
            };
            if let Some(cause) = cause {
                crash(world, state, i, cause, report);
            }
        }
    }
    state.scratch.started = started;
    state.scratch.started.clear();
}

/// Whether something may happen to a copter after the substep it has just run: a tilt or floor
/// crash, a take-off, or (flying free) leaving its reservation. The serial checks of
/// [`detect_tilt_and_takeoff`] decide.
#[inline]
fn may_act(world: &World, crash_cos_tilt: &[Real], lane: &Lane) -> bool {
    lane.flying
        && ((lane.rot * Vec3::Z).z.clamp(-1.0, 1.0) < crash_cos_tilt[lane.airframe as usize]
            || (lane.free && (lane.floor_impact_m_s > 0.0 || (lane.pos_m - lane.anchor_m).length() > lane.reach_m))
            || (lane.awaiting_takeoff
                && lane.pos_m.z > world.airframes[lane.airframe as usize].rest_height_m + TAKEOFF_MARGIN_M))
}

/// Lanes per chunk of the substep's alert scan.
pub(crate) const ALERT_CHUNK: usize = 256;

/// Checks tilt crashes and take-offs, in id order, and hands a free copter that left its
/// reservation back to Rapier. A scan (in parallel chunks, with threads) first finds the
/// chunks where something may have happened: in most substeps, none.
fn detect_tilt_and_takeoff(
    world: &World,
    state: &mut State,
    report: &mut StepReport,
    roles: Roles<'_>,
    parallel: bool,
    s: u32,
) {
    let scratch = &mut state.scratch;
    let crash_cos_tilt = &scratch.crash_cos_tilt;
    // A copter that ran ahead is checked at the substep it stopped after.
    let at = |lane: &Lane| lane.batched <= s + 1;
    let may_act = |lane: &Lane| at(lane) && may_act(world, crash_cos_tilt, lane);
    scratch.alerts.resize(scratch.lanes.len().div_ceil(ALERT_CHUNK), false);
    if parallel && scratch.lanes.len() > 4 * ALERT_CHUNK {
        use rayon::prelude::*;
        let chunks = scratch.lanes.par_chunks(ALERT_CHUNK).zip(scratch.alerts.par_iter_mut());
        chunks.for_each(|(lanes, alert)| *alert = lanes.iter().any(may_act));
    } else {
        for (lanes, alert) in scratch.lanes.chunks(ALERT_CHUNK).zip(&mut scratch.alerts) {
            *alert = lanes.iter().any(may_act);
        }
    }
    let n = world.copters.len();
    let chunk = |k: usize| k * ALERT_CHUNK..((k + 1) * ALERT_CHUNK).min(n);
    // Only the lanes are read until something happens: they are compact, the copters are not.
    for k in 0..state.scratch.alerts.len() {
        if !state.scratch.alerts[k] {
            continue;
        }
        for i in chunk(k) {
            let lane = &state.scratch.lanes[i];
            if !lane.flying || !roles.owned(i) || lane.batched > s + 1 {
                continue;
            }
            let cos_tilt = (lane.rot * Vec3::Z).z.clamp(-1.0, 1.0);
            if cos_tilt < state.scratch.crash_cos_tilt[lane.airframe as usize] {
                let tilt_deg = cos_tilt.acos().to_degrees();
                crash(world, state, i, CrashCause::Tilt { tilt_deg }, report);
                continue;
            }
            if lane.free && lane.floor_impact_m_s > 0.0 {
                let speed_m_s = lane.floor_impact_m_s;
                crash(world, state, i, CrashCause::Floor { speed_m_s }, report);
                continue;
            }
            if lane.free && (lane.pos_m - lane.anchor_m).length() > lane.reach_m {
                let lane = &mut state.scratch.lanes[i];
                enter_rapier(&mut state.physics.bodies[state.copters[i].body], lane);
                (lane.free, lane.watch) = (false, false);
                state.copters[i].grounded = false;
                insert_sorted(&mut state.scratch.in_rapier, i as u32);
            }
        }
    }
    for k in 0..state.scratch.alerts.len() {
        if !state.scratch.alerts[k] {
            continue;
        }
        for i in chunk(k) {
            let lane = &mut state.scratch.lanes[i];
            if !lane.awaiting_takeoff || !roles.owned(i) || lane.batched > s + 1 {
                continue;
            }
            let rest = world.airframes[lane.airframe as usize].rest_height_m;
            if lane.pos_m.z > rest + TAKEOFF_MARGIN_M {
                lane.awaiting_takeoff = false;
                state.copters[i].took_off_tick = Some(state.tick);
                report.events.push(crate::step::Event::TookOff { copter: i });
            }
        }
    }
}

/// How long a wreck lies still (Rapier's thresholds: 0.05 m/s, 0.5 rad/s) before it sleeps, s.
const WRECK_TIME_UNTIL_SLEEP_S: Real = 0.2;

/// Inserts `i` into the sorted `ids` unless it is there. (The callers reserve room for every
/// copter: no allocation.)
fn insert_sorted(ids: &mut Vec<u32>, i: u32) {
    if let Err(at) = ids.binary_search(&i) {
        ids.insert(at, i);
    }
}

fn crash(world: &World, state: &mut State, i: usize, cause: CrashCause, report: &mut StepReport) {
    let c = &mut state.copters[i];
    if let (true, Some(lane)) = (state.physics.bodies.contains(c.body), state.scratch.lanes.get_mut(i)) {
        if world.params.closed_form {
            // It falls in closed form from the next substep on; its body, fixed, follows it.
            c.body = fix_wreck(world, &mut state.physics, c.body, lane, i, true);
            (lane.free, lane.watch, c.grounded) = (true, false, false);
            insert_sorted(&mut state.scratch.falling, i as u32);
        } else {
            // Rapier may put it to sleep once it lies still; a sleeping wreck costs nothing
            // until something hits it.
            let activation = state.physics.bodies[c.body].activation_mut();
            *activation = RigidBodyActivation::active();
            activation.time_until_sleep = WRECK_TIME_UNTIL_SLEEP_S;
        }
    }
    if let Some(lane) = state.scratch.lanes.get_mut(i) {
        (lane.flying, lane.awaiting_takeoff) = (false, false);
    }
    c.crash = Some(cause);
    c.rotor_speed_rad_s = [0.0; 4];
    c.rotor_thrust_n = [0.0; 4];
    report.events.push(Event::Crashed { copter: i, cause });
}

/// Copter `id`'s body becomes a fixed body at its lane's pose, enabled (a wreck in closed
/// form); returns its handle. Rapier 0.36 keeps a body that turns fixed in its awake island,
/// and recomputes its colliders' AABBs at every step for the rest of the run; so a body
/// Rapier has in hand (enabled) makes way for a new fixed body. (Body handles therefore
/// differ between shards; each keeps its own.) A disabled body is in no island and simply
/// turns fixed. Either way the wreck has one collider, its parts as one compound; `falling`,
/// it pushes nothing ([`FALLING_WRECK`]).
fn fix_wreck(
    world: &World,
    physics: &mut PhysicsWorld,
    old: RigidBodyHandle,
    lane: &Lane,
    id: usize,
    falling: bool,
) -> RigidBodyHandle {
    let handle = if physics.bodies[old].is_enabled() {
        physics.insert_body(RigidBodyBuilder::fixed().user_data(id as u128))
    } else {
        old
    };
    let body = &mut physics.bodies[handle];
    body.set_body_type(RigidBodyType::Fixed, false);
    body.set_enabled(true);
    body.set_translation(lane.pos_m, false);
    body.set_rotation(lane.rot, false);
    // Its collider moves to the fixed body, with the wreck's solver groups.
    while let Some(&collider) = physics.bodies[old].colliders().first() {
        physics.remove_collider(collider);
    }
    if handle != old {
        physics.remove_body(old);
    }
    let solver = if falling { FALLING_WRECK } else { InteractionGroups::all() };
    physics.insert_collider(world.copter_collider_of(id).solver_groups(solver), Some(handle));
    handle
}

/// A falling wreck's solver groups: none. Its fixed body has no velocity in Rapier, so a contact
/// with a flying copter would be a static body jumping into it at every substep (a kick of
/// several rad/s in one substep); and when a wreck that crashed against a copter gets its new
/// body, all the pairs of the copter's parts with it begin to touch in one step, and Rapier
/// solves those in the order its broad phase found them, which follows the whole world's
/// history (a shard's differs from one process's). So it only reports its touches: a flying
/// copter faster than the crash speed crashes into it, a slower one passes through, as falling
/// wrecks pass through each other. At rest it is solid again.
const FALLING_WRECK: InteractionGroups = InteractionGroups::none();

/// One physics step of a wreck in closed form (`[sim] closed_form`, the default). It falls
/// with its momentum under gravity, damping and the downwash on it; walls, the ceiling and the
/// sides of boxes push it back and take its speed into them; where it first meets the floor,
/// a box top or a wreck at rest below it, it comes to rest for good: level or upside down as it
/// came, heading kept, its lowest point on that surface. Two falling wrecks pass through each
/// other. A wreck at rest is tested as its bounding disc (radius `Airframe::radius_m`) and
/// its top. Its Rapier body is fixed and follows it, so a flying copter that hits it crashes
/// as before. Wreck against wreck looks only at wrecks whose reservations meet its own: in a
/// shard they are in its contact cluster, so every shard decides the same.
fn fall_wreck(world: &World, state: &mut State, i: usize, dt: Real) {
    let af = &world.airframes[world.copters[i].airframe];
    let scratch = &mut state.scratch;
    let mut lane = scratch.lanes[i];
    let rate_body = lane.rot.inverse() * lane.angvel_rad_s;
    integrate_free(af, &mut lane, rate_body, 0.0, Vec3::ZERO, dt);
    // Planes `x · n = -h` with inward normal `n`: the walls and the ceiling.
    let arena = &world.arena;
    let (hx, hy, hz) = (arena.size_m[0] / 2.0, arena.size_m[1] / 2.0, arena.height_m);
    if arena.walls {
        for (n, h) in [(Vec3::X, hx), (-Vec3::X, hx), (Vec3::Y, hy), (-Vec3::Y, hy), (-Vec3::Z, hz)] {
            let depth = reach_along(af, lane.rot, -n) - (lane.pos_m.dot(n) + h);
            slide_off(&mut lane, n, depth);
        }
    }
    let mut ground: Option<Real> = None;
    let mut land_on = |top: Real| ground = Some(ground.map_or(top, |g: Real| g.max(top)));
    for b in &world.boxes {
        let yaw = Quat::from_rotation_z(b.yaw_rad);
        let local = yaw.inverse() * (lane.pos_m - b.center_m);
        let h = b.half_extents_m;
        let outside = local - local.clamp(-h, h);
        let (n, dist) = if outside == Vec3::ZERO {
            // Its centre inside the box: out through the nearest face.
            let gap = h - local.abs();
            let axis = if gap.x <= gap.y && gap.x <= gap.z {
                Vec3::X
            } else if gap.y <= gap.z {
                Vec3::Y
            } else {
                Vec3::Z
            };
            (yaw * (axis * local.signum()), -gap.min_element())
        } else {
            let dist = outside.length();
            (yaw * (outside / dist), dist)
        };
        let depth = reach_along(af, lane.rot, -n) - dist;
        if depth > 0.0 {
            if n.z > WRECK_LANDS_COS {
                land_on(b.center_m.z + h.z);
            } else {
                slide_off(&mut lane, n, depth);
            }
        }
    }
    let lowest = lane.pos_m.z - lowest_point_below_centre(af, lane.rot);
    if lowest <= 0.0 {
        land_on(0.0);
    }
    let sphere = scratch.spheres[i];
    let r = sphere.half.x + FREE_GAP_M;
    let (spheres, lanes, copters) = (&scratch.spheres, &scratch.lanes, &state.copters);
    scratch.sphere_grid.visit_near(sphere.center, r, |j| {
        let other = &copters[j];
        if j == i || other.crash.is_none() || !other.grounded {
            return r;
        }
        if (spheres[j].center - sphere.center).length() > r + spheres[j].half.x {
            return r;
        }
        let (lj, afj) = (&lanes[j], &world.airframes[world.copters[j].airframe]);
        let top = lj.pos_m.z + reach_along(afj, lj.rot, Vec3::Z);
        let apart = (lane.pos_m - lj.pos_m).truncate().length();
        if lane.pos_m.z > lj.pos_m.z && apart < af.radius_m + afj.radius_m && lowest < top {
            land_on(top);
        }
        r
    });
    if let Some(ground) = ground {
        let fwd = lane.rot * Vec3::X;
        let level = Quat::from_rotation_z(fwd.y.atan2(fwd.x));
        lane.rot =
            if (lane.rot * Vec3::Z).z < 0.0 { level * Quat::from_rotation_x(std::f32::consts::PI) } else { level };
        lane.pos_m.z = ground + lowest_point_below_centre(af, lane.rot);
        lane.vel_m_s = Vec3::ZERO;
        lane.angvel_rad_s = Vec3::ZERO;
        state.copters[i].grounded = true;
        // At rest for good: solid for the copters that come to it.
        let physics = &mut state.physics;
        for &collider in physics.bodies[state.copters[i].body].colliders() {
            physics.colliders[collider].set_solver_groups(InteractionGroups::all());
        }
    }
    scratch.lanes[i] = lane;
    let body = &mut state.physics.bodies[state.copters[i].body];
    body.set_translation(lane.pos_m, false);
    body.set_rotation(lane.rot, false);
}

/// A falling wreck meets a surface steeper than this (cosine of the normal's angle to the
/// vertical) as a side it slides along; flatter, it lands on it.
const WRECK_LANDS_COS: Real = std::f32::consts::FRAC_1_SQRT_2;

/// Pushes a wreck `depth` along `n` out of a surface it penetrates, and takes away its speed
/// into it (no bounce).
fn slide_off(lane: &mut Lane, n: Vec3, depth: Real) {
    if depth <= 0.0 {
        return;
    }
    lane.pos_m += n * depth;
    let into = lane.vel_m_s.dot(n);
    if into < 0.0 {
        lane.vel_m_s -= n * into;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::airframe::AirframeSpec;

    #[test]
    fn crosstalks_pretest_passes_only_near_the_listeners_cone() {
        let mut rng = crate::rng::Rng32::new(9, 0);
        for opening_deg in [10.0_f32, 30.0, 90.0, 150.0, 179.0] {
            let h = (0.5 * opening_deg).to_radians();
            let slack = 0.1;
            let grow = crosstalk_growth(h, slack);
            let (mut passed, mut farthest) = (0, 0.0_f32);
            for _ in 0..20_000 {
                let mut u = || 2.0 * rng.uniform() - 1.0;
                let v = Vec3::new(u(), u(), u()) * 3.0 * rng.uniform();
                if v.x < h.cos() * (v.length() - slack) - 1e-4 {
                    continue;
                }
                passed += 1;
                let theta = (v.x / v.length().max(1e-9)).clamp(-1.0, 1.0).acos();
                let to_cone = match theta - h {
                    off if off <= 0.0 => 0.0,
                    off if off <= std::f32::consts::FRAC_PI_2 => v.length() * off.sin(),
                    _ => v.length(),
                };
                farthest = farthest.max(to_cone);
            }
            assert!(passed > 100, "{opening_deg}°: {passed}");
            assert!(farthest <= grow, "{opening_deg}°: {farthest} m from the cone, growth {grow} m");
        }
    }

    #[test]
    fn no_collider_reaches_past_the_airframes_reach_bound() {
        let mut rng = crate::rng::Rng32::new(5, 0);
        let boxy = AirframeSpec { body_size_m: [0.3, 0.2, 0.15], ..Default::default() };
        for spec in [AirframeSpec::default(), boxy] {
            let af = Airframe::derive(&spec).unwrap();
            let mut farthest: Real = 0.0;
            for _ in 0..20_000 {
                let mut u = || 2.0 * rng.uniform() - 1.0;
                let rot = crate::math::quat_from_euler(3.2 * u(), 1.6 * u(), 3.2 * u());
                let d = Vec3::new(u(), u(), u()).normalize_or(Vec3::Z);
                farthest = farthest.max(reach_along(&af, rot, d));
            }
            assert!(farthest <= af.reach_bound_m, "{farthest} > {}", af.reach_bound_m);
            assert!(farthest > 0.97 * af.reach_bound_m, "a loose bound: {farthest} of {}", af.reach_bound_m);
        }
    }
}
