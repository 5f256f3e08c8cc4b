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
use crate::partition::{Role, ShardView};
use crate::scene::CopterKind;
use crate::sensors::{
    self, SonarScene, SonarSchedule, crosstalk_eligible, crosstalk_reading, sonar_cones, sonar_reading,
};
use crate::state::{CopterState, CrashCause, Lane, Motion, Pinger, State};
use crate::world::{ColliderTag, World};
use batch::run_ahead_batch;
use rapier3d::prelude::{
    InteractionGroups, PhysicsWorld, RigidBody, RigidBodyActivation, RigidBodyBuilder, RigidBodyHandle, RigidBodyType,
};

mod airflow;
mod batch;
mod crash;
mod outer;
mod reserve;
mod sense;
mod substep;

use airflow::*;
use crash::*;
use outer::*;
use reserve::*;
use sense::*;
use substep::*;

pub use sense::{copter_box, fill_sonar_scene, fresh_sonars};

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
    /// Downwash and wakes between copters.
    Airflow,
    /// Each copter's reachable sphere, and which fly free or on watch.
    Reserve,
    /// Ownership (in a shard), watch pairs, falling wrecks, Rapier bodies entering or leaving.
    RapierSetup,
    /// Sensing, what the sonars can see: the sonar scene, its copter grid, the pingers.
    SonarScene,
    /// Sensing: each copter's sonars, IR, IMU and estimators.
    Ranges,
    /// Sensing: the sonars' cross-talk.
    Crosstalk,
    /// Sensing: the fused readings into the firmware's sonar filter (the end of sensing).
    Sense,
    /// The flight modes' setpoints.
    OuterLoops,
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

    /// Feels the wakes before this step's ownership is decided (its reachable sphere decides
    /// it): owned, or a ghost it may take over (not a far one).
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

/// [`for_each_lane`] with a third per-copter slice, `extra` (as long as the copters).
fn for_each_lane_with<T, F>(parallel: bool, copters: &mut [CopterState], lanes: &mut [Lane], extra: &mut [T], f: F)
where
    T: Send,
    F: Fn(usize, &mut CopterState, &mut Lane, &mut T) + Sync + Send,
{
    let run = |first: usize, cs: &mut [CopterState], ls: &mut [Lane], xs: &mut [T]| {
        for (j, ((c, l), x)) in cs.iter_mut().zip(ls.iter_mut()).zip(xs.iter_mut()).enumerate() {
            f(first + j, c, l, x);
        }
    };
    if parallel && copters.len() > 64 {
        use rayon::prelude::*;
        let chunk = lane_chunk(copters.len());
        let chunks = copters.par_chunks_mut(chunk).zip(lanes.par_chunks_mut(chunk)).zip(extra.par_chunks_mut(chunk));
        chunks.enumerate().with_max_len(PIECE).for_each(|(k, ((cs, ls), xs))| run(k * chunk, cs, ls, xs));
    } else {
        run(0, copters, lanes, extra);
    }
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
        chunks.enumerate().with_max_len(PIECE).for_each(|(k, (cs, ls))| f(k * chunk, cs, ls));
    } else {
        f(0, copters, lanes);
    }
}

/// Chunks per rayon job at most: one.
const PIECE: usize = 1;

/// Copters per parallel chunk of `n`: about 128 chunks, at least 32 copters each. Every chunk
/// is its own job (`with_max_len(PIECE)`): left to itself, rayon splits a pass only into as
/// many pieces as it takes to feed the idle threads at its start, and the last piece of a
/// crowded pass, run by one thread, is what the others wait for (the copters' cost differs
/// several times with the crowd).
fn lane_chunk(n: usize) -> usize {
    (n / 128).max(32)
}

/// [`fill_each`] for the copters `roles` has present (all, outside a shard); in a shard an
/// absent copter's entry keeps whatever it held, unwritten: nothing reads it, and a shard's
/// tables are the whole swarm's, mostly absent.
fn fill_present<T>(
    parallel: bool,
    out: &mut Vec<T>,
    n: usize,
    fill: T,
    roles: Roles<'_>,
    f: impl Fn(usize) -> T + Sync + Send,
) where
    T: Copy + Send + Sync,
{
    if roles.0.is_none() {
        return fill_each(parallel, out, n, fill, f);
    }
    out.resize(n, fill);
    fill_where(parallel, out, |i| roles.present(i), f);
}

/// [`fill_present`] into two outputs at once: `(a[i], b[i]) = f(i)`.
fn fill_present2<A, B>(
    parallel: bool,
    a: &mut Vec<A>,
    b: &mut Vec<B>,
    n: usize,
    fill: (A, B),
    roles: Roles<'_>,
    f: impl Fn(usize) -> (A, B) + Sync + Send,
) where
    A: Copy + Send + Sync,
    B: Copy + Send + Sync,
{
    a.resize(n, fill.0);
    b.resize(n, fill.1);
    let run = |first: usize, a: &mut [A], b: &mut [B]| {
        for (j, (x, y)) in a.iter_mut().zip(b.iter_mut()).enumerate() {
            if roles.present(first + j) {
                (*x, *y) = f(first + j);
            }
        }
    };
    if parallel && n > 64 {
        use rayon::prelude::*;
        let chunk = lane_chunk(n);
        let chunks = a.par_chunks_mut(chunk).zip(b.par_chunks_mut(chunk));
        chunks.enumerate().with_max_len(PIECE).for_each(|(k, (a, b))| run(k * chunk, a, b));
    } else {
        run(0, a, b);
    }
}

/// Runs `a` on this thread beside `b`, which may use every thread (a serial task, such as a
/// grid's build, beside an independent pass over the copters); without threads, `a` then `b`.
/// The two must not depend on each other: then the bits are the same either way.
fn beside(parallel: bool, a: impl FnOnce() + Send, b: impl FnOnce() + Send) {
    if parallel {
        rayon::join(a, b);
    } else {
        a();
        b();
    }
}

/// Fills `out` with `f(i)` for every `i` in `0..n`, in parallel chunks or in order (the same
/// values either way); `fill` only stands in until then, for entries `out` did not have (the
/// others are written once, not filled first).
fn fill_each<T>(parallel: bool, out: &mut Vec<T>, n: usize, fill: T, f: impl Fn(usize) -> T + Sync + Send)
where
    T: Copy + Send + Sync,
{
    out.resize(n, fill);
    fill_where(parallel, out, |_| true, f);
}

/// `out[i] = f(i)` where `keep(i)`, in parallel chunks or in order (the same values either way).
fn fill_where<T>(parallel: bool, out: &mut [T], keep: impl Fn(usize) -> bool + Sync, f: impl Fn(usize) -> T + Sync)
where
    T: Send,
{
    let run = |first: usize, out: &mut [T]| {
        for (j, x) in out.iter_mut().enumerate() {
            if keep(first + j) {
                *x = f(first + j);
            }
        }
    };
    if parallel && out.len() > 64 {
        use rayon::prelude::*;
        let chunk = lane_chunk(out.len());
        out.par_chunks_mut(chunk).enumerate().with_max_len(PIECE).for_each(|(k, out)| run(k * chunk, out));
    } else {
        run(0, out);
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

/// One control step of the copters, stage by stage: each copter's motion into its lane; the
/// airflow between copters ([`airflow`]); which copters fly free of Rapier
/// ([`reserve_free_flight`]), and in a shard which copters it steps; sensing ([`sense`]) and
/// the outer loops of those it steps; the physics substeps ([`physics_substep`]); the lanes
/// back into the copters' motion.
///
/// The airflow and the reservations read only the motion, rotor thrusts and crashes of the
/// step's start (and the wakes' keyed gusts, not the copters' streams), nothing sensing or the
/// outer loops write: so a shard decides what it owns first, and senses and controls only
/// that, not the ghosts it may have taken over.
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
    // The reachable spheres' grid by their centres on one thread, the lanes on the others.
    let crate::state::Scratch { lanes, sphere_grid, present, .. } = &mut state.scratch;
    lanes.resize(world.copters.len(), Lane::default());
    let copters = &state.copters;
    beside(
        parallel,
        || reserve::index_sphere_centres(world, copters, present, roles, sphere_grid),
        || load_lanes(world, copters, lanes, parallel, roles),
    );
    probe(Stage::Lanes);
    report.shard_violations += airflow(world, state, parallel, roles);
    probe(Stage::Airflow);
    report.shard_violations += reserve_free_flight(world, state, parallel, view, probe);
    probe(Stage::RapierSetup);
    // From here on: what this shard owns for this step.
    let roles = Roles(view.as_ref().map(|v| &v.roles[..]));
    let sonar_period = world.sensors.spec.sonar.period_steps.max(1) as u64;
    if world.sensors.spec.enabled {
        sense(world, state, inputs, state.tick.is_multiple_of(sonar_period), parallel, roles, probe);
    }
    probe(Stage::Sense);
    outer_loops(world, &mut state.copters, &state.scratch.lanes, state.tick, inputs, parallel, roles);
    probe(Stage::OuterLoops);

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

/// `Lane::batched` of a copter a shard does not step (another shard's, seen or absent): the
/// substeps' passes skip it at their first test, without reading more of its lane or calling
/// into the substep. Set when the step's roles are known: by [`load_lanes`] for absent copters,
/// by the ownership pass for the ghosts this shard does not take over. Nothing reads a lane
/// this shard does not step during the substeps (its Rapier body is disabled, so no contact
/// reads its `vel_before_m_s`).
pub(super) const NOT_STEPPED: u32 = u32::MAX;

/// Every copter's motion at the start of the step, into its lane (in a shard, of the copters
/// it reads: an absent one's lane is read by nothing, and only marked [`NOT_STEPPED`] for
/// the substeps' parallel passes).
fn load_lanes(world: &World, copters: &[CopterState], lanes: &mut [Lane], parallel: bool, roles: Roles<'_>) {
    let load = |first: usize, ls: &mut [Lane]| {
        for (j, lane) in ls.iter_mut().enumerate() {
            let i = first + j;
            if !roles.present(i) {
                // Read only by the substeps' parallel passes: on one thread they visit the
                // present copters alone, and the lane is not touched.
                if parallel {
                    lane.batched = NOT_STEPPED;
                }
                continue;
            }
            let (c, m) = (&copters[i], &copters[i].motion);
            (lane.pos_m, lane.rot, lane.vel_m_s, lane.angvel_rad_s) = (m.pos_m, m.rot, m.vel_m_s, m.angvel_rad_s);
            lane.airframe = world.copters[i].airframe as u32;
            lane.flying = c.crash.is_none();
            lane.awaiting_takeoff = lane.flying && c.took_off_tick.is_none();
            lane.batched = 0;
        }
    };
    if parallel && lanes.len() > 64 {
        use rayon::prelude::*;
        let chunk = lane_chunk(lanes.len());
        lanes.par_chunks_mut(chunk).enumerate().with_max_len(PIECE).for_each(|(k, ls)| load(k * chunk, ls));
    } else {
        load(0, lanes);
    }
}

/// Each copter's flight mode: its setpoint for the step's inner loops (reading the lanes
/// only, in parallel chunks or in order).
fn outer_loops(
    world: &World,
    copters: &mut [CopterState],
    lanes: &[Lane],
    tick: u64,
    inputs: &Inputs,
    parallel: bool,
    roles: Roles<'_>,
) {
    let command = |i: usize| -> &Command { inputs.commands.get(i).unwrap_or(&world.copters[i].initial_command) };
    let dt_control = world.params.control_dt_s as Real;
    let run = |first: usize, cs: &mut [CopterState], ls: &[Lane]| {
        for (j, (c, lane)) in cs.iter_mut().zip(ls).enumerate() {
            let i = first + j;
            if !roles.owned(i) {
                continue;
            }
            let af = &world.airframes[world.copters[i].airframe];
            let yaw = euler_from_quat(lane.rot)[2];
            c.setpoint = outer_loop(world, i, af, c, command(i), lane.pos_m, lane.vel_m_s, yaw, dt_control, tick);
        }
    };
    if parallel && copters.len() > 64 {
        use rayon::prelude::*;
        let chunk = lane_chunk(copters.len());
        let chunks = copters.par_chunks_mut(chunk).zip(lanes.par_chunks(chunk));
        chunks.enumerate().with_max_len(PIECE).for_each(|(k, (cs, ls))| run(k * chunk, cs, ls));
    } else {
        run(0, copters, lanes);
    }
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
    // On one thread, the copters this substep may step: a shard's present ones in the first
    // (the others' lanes are not read), those that did not run ahead to the step's end in the
    // later ones (listed after the first).
    let ids = match (parallel, s, roles.0) {
        (true, ..) => None,
        (false, 0, Some(_)) => Some(&scratch.present[..]),
        (false, 0, None) => None,
        (false, ..) => Some(&scratch.between[..]),
    };
    let first = pass.closure(s, parallel_rapier.then_some(true), ids);
    for_each_chunk(parallel, &mut state.copters, &mut scratch.lanes, first);
    if !parallel && s == 0 {
        list_between(world, &mut state.scratch, roles);
    }
    probe(Stage::InRapierLanes);
    fall_wrecks(world, state, dt, parallel);
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
        let free_lanes = pass.closure(s, Some(false), None);
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

/// `Scratch::between`, after the first substep's pass on one thread: the owned copters that
/// did not run ahead to the step's end. A copter runs ahead in the first substep alone, so the
/// others' `Lane::batched` is the substep count from here on: the later substeps neither step
/// nor check them before the last.
fn list_between(world: &World, scratch: &mut crate::state::Scratch, roles: Roles<'_>) {
    let last = world.params.substeps.saturating_sub(1);
    let between = |&i: &u32| roles.owned(i as usize) && scratch.lanes[i as usize].batched <= last;
    scratch.between.clear();
    match roles.0 {
        Some(_) => scratch.between.extend(scratch.present.iter().copied().filter(between)),
        None => scratch.between.extend((0..scratch.lanes.len() as u32).filter(between)),
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::airframe::AirframeSpec;

    /// Falling wrecks found in parallel and then taken in id order (`fall_wrecks`, from two
    /// falling here) give the one-thread bits, a wreck landing on one that came to rest in the
    /// same substep included.
    #[test]
    fn wrecks_falling_together_give_the_one_thread_bits() {
        let worlds = [1, 2].map(|threads| {
            let mut spec = crate::scene::dense_swarm(150, 1.5, true, 10, 3);
            spec.sim.threads = threads;
            crate::scene::compile(&spec).unwrap()
        });
        let inputs = worlds[0].initial_inputs();
        let mut states = worlds.each_ref().map(World::initial_state);
        let mut most_falling = 0;
        for _ in 0..300 {
            for (w, s) in worlds.iter().zip(&mut states) {
                step(w, s, &inputs);
            }
            most_falling = most_falling.max(states[1].scratch.falling.len());
            let digests = states.each_ref().map(|s| s.copters.iter().map(|c| c.digest()).collect::<Vec<_>>());
            assert_eq!(digests[0], digests[1], "tick {}", states[0].tick);
        }
        assert!(most_falling >= crash::WRECKS_AHEAD_MIN, "{most_falling} wrecks falling at most");
    }

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
