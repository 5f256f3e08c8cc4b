//! Crashes (collision, tilt), take-offs, and wrecks: fixed, falling and sliding in closed form.

use super::*;

/// Turns collision starts into crashes.
pub(super) fn detect_collision_crashes(world: &World, state: &mut State, report: &mut StepReport) {
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
pub(super) fn may_act(world: &World, crash_cos_tilt: &[Real], lane: &Lane) -> bool {
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
/// chunks where something may have happened: in most substeps, none. On one thread, the
/// substeps between the first and the last scan only the copters that did not run ahead to the
/// step's end ([`list_between`]).
pub(super) fn detect_tilt_and_takeoff(
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
    // Chunk `k`'s alert: one of its copters that this shard moves may act.
    let alert = |k: usize, lanes: &[Lane]| {
        let may = |(j, lane): (usize, &Lane)| roles.owned(k * ALERT_CHUNK + j) && at(lane);
        lanes.iter().enumerate().any(|jl| may(jl) && may_act(world, crash_cos_tilt, jl.1))
    };
    scratch.alerts.resize(scratch.lanes.len().div_ceil(ALERT_CHUNK), false);
    let last = world.params.substeps.saturating_sub(1);
    // With threads, every substep scans all the lanes, in parallel (see `Scratch::between`).
    if !parallel && s > 0 && s < last {
        // Between the first substep and the last, only a copter that did not run ahead to the
        // step's end can be `at` its check: the others' `batched` is the substep count.
        scratch.alerts.fill(false);
        for &i in &scratch.between {
            let i = i as usize;
            let lane = &scratch.lanes[i];
            let a = &mut scratch.alerts[i / ALERT_CHUNK];
            *a = *a || (at(lane) && may_act(world, crash_cos_tilt, lane));
        }
    } else if parallel && scratch.lanes.len() > 4 * ALERT_CHUNK {
        use rayon::prelude::*;
        let chunks = scratch.lanes.par_chunks(ALERT_CHUNK).zip(scratch.alerts.par_iter_mut());
        chunks.enumerate().for_each(|(k, (lanes, a))| *a = alert(k, lanes));
    } else {
        for (k, (lanes, a)) in scratch.lanes.chunks(ALERT_CHUNK).zip(&mut scratch.alerts).enumerate() {
            *a = alert(k, lanes);
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
            if !roles.owned(i) || !lane.flying || lane.batched > s + 1 {
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
            if !roles.owned(i) || !lane.awaiting_takeoff || lane.batched > s + 1 {
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
pub(super) const WRECK_TIME_UNTIL_SLEEP_S: Real = 0.2;

/// Inserts `i` into the sorted `ids` unless it is there. (The callers reserve room for every
/// copter: no allocation.)
pub(super) fn insert_sorted(ids: &mut Vec<u32>, i: u32) {
    if let Err(at) = ids.binary_search(&i) {
        ids.insert(at, i);
    }
}

pub(super) fn crash(world: &World, state: &mut State, i: usize, cause: CrashCause, report: &mut StepReport) {
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
pub(super) fn fix_wreck(
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
pub(super) const FALLING_WRECK: InteractionGroups = InteractionGroups::none();

/// One physics step of a wreck in closed form (`[sim] closed_form`, the default). It falls
/// with its momentum under gravity, damping and the downwash on it; walls, the ceiling and the
/// sides of boxes push it back and take its speed into them; where it first meets the floor,
/// a box top or a wreck at rest below it, it comes to rest for good: level or upside down as it
/// came, heading kept, its lowest point on that surface. Two falling wrecks pass through each
/// other. A wreck at rest is tested as its bounding disc (radius `Airframe::radius_m`) and
/// its top. Its Rapier body is fixed and follows it, so a flying copter that hits it crashes
/// as before. Wreck against wreck looks only at wrecks whose reservations meet its own: in a
/// shard they are in its contact cluster, so every shard decides the same. With threads and
/// many wrecks falling, their substeps are found in parallel first; the same bits.
pub(super) fn fall_wrecks(world: &World, state: &mut State, dt: Real, parallel: bool) {
    let crate::state::Scratch { lanes, spheres, sphere_grid, falling, wreck_moves, landed, .. } = &mut state.scratch;
    let copters = &state.copters;
    let motion = |i: usize, lanes: &[Lane], copters: &[CopterState]| {
        wreck_motion(world, WreckView { lanes, spheres, grid: sphere_grid, copters }, i, dt)
    };
    // Each wreck's substep from the substep's start, in parallel (alone, one wreck after the
    // other in the loop below).
    let ahead = parallel && falling.len() >= WRECKS_AHEAD_MIN;
    if ahead {
        wreck_moves.clear();
        wreck_moves.reserve(lanes.len());
        let (lanes, falling) = (&*lanes, &*falling);
        fill_each(true, wreck_moves, falling.len(), (Lane::default(), false), |k| {
            motion(falling[k] as usize, lanes, copters)
        });
    }
    // In id order, as one pass: a wreck near one that came to rest earlier in this substep
    // (their reservations meet) may land on it, so its substep is taken again from there.
    landed.clear();
    // Room for every copter, kept from step to step: a warm step does not allocate.
    landed.reserve(lanes.len());
    for k in 0..falling.len() {
        let i = falling[k] as usize;
        let near = |j: &u32| {
            let (a, b) = (&spheres[i], &spheres[*j as usize]);
            (b.center - a.center).length() <= a.half.x + FREE_GAP_M + b.half.x
        };
        let (lane, rests) = match ahead && !landed.iter().any(near) {
            true => wreck_moves[k],
            false => motion(i, lanes, &state.copters),
        };
        lanes[i] = lane;
        lanes[i].vel_before_m_s = lane.vel_m_s;
        if rests {
            landed.push(i as u32);
        }
        commit_wreck(&mut state.physics, &mut state.copters[i], &lane, rests);
    }
}

/// Falling wrecks from which [`fall_wrecks`] finds their substeps in parallel first (fewer
/// cost more to hand out than they take; the unit tests take the parallel path from two).
pub(super) const WRECKS_AHEAD_MIN: usize = if cfg!(test) { 2 } else { 16 };

/// What [`wreck_motion`] reads besides its own wreck.
#[derive(Clone, Copy)]
pub(super) struct WreckView<'a> {
    pub(super) lanes: &'a [Lane],
    pub(super) spheres: &'a [OrientedBox],
    pub(super) grid: &'a crate::sensors::CopterGrid,
    pub(super) copters: &'a [CopterState],
}

/// A wreck's substep ([`fall_wrecks`]): its lane after it, and whether it came to rest.
pub(super) fn wreck_motion(world: &World, view: WreckView<'_>, i: usize, dt: Real) -> (Lane, bool) {
    let af = &world.airframes[world.copters[i].airframe];
    let mut lane = view.lanes[i];
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
    let sphere = view.spheres[i];
    let r = sphere.half.x + FREE_GAP_M;
    let (spheres, lanes, copters) = (view.spheres, view.lanes, view.copters);
    view.grid.visit_near(sphere.center, r, |j| {
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
    let Some(ground) = ground else { return (lane, false) };
    let fwd = lane.rot * Vec3::X;
    let level = Quat::from_rotation_z(fwd.y.atan2(fwd.x));
    lane.rot = if (lane.rot * Vec3::Z).z < 0.0 { level * Quat::from_rotation_x(std::f32::consts::PI) } else { level };
    lane.pos_m.z = ground + lowest_point_below_centre(af, lane.rot);
    lane.vel_m_s = Vec3::ZERO;
    lane.angvel_rad_s = Vec3::ZERO;
    (lane, true)
}

/// A wreck's substep into its copter and its fixed Rapier body, which follows it; one at rest
/// becomes solid for the copters that come to it.
fn commit_wreck(physics: &mut PhysicsWorld, c: &mut CopterState, lane: &Lane, rests: bool) {
    if rests {
        c.grounded = true;
        for &collider in physics.bodies[c.body].colliders() {
            physics.colliders[collider].set_solver_groups(InteractionGroups::all());
        }
    }
    let body = &mut physics.bodies[c.body];
    body.set_translation(lane.pos_m, false);
    body.set_rotation(lane.rot, false);
}

/// A falling wreck meets a surface steeper than this (cosine of the normal's angle to the
/// vertical) as a side it slides along; flatter, it lands on it.
pub(super) const WRECK_LANDS_COS: Real = std::f32::consts::FRAC_1_SQRT_2;

/// Pushes a wreck `depth` along `n` out of a surface it penetrates, and takes away its speed
/// into it (no bounce).
pub(super) fn slide_off(lane: &mut Lane, n: Vec3, depth: Real) {
    if depth <= 0.0 {
        return;
    }
    lane.pos_m += n * depth;
    let into = lane.vel_m_s.dot(n);
    if into < 0.0 {
        lane.vel_m_s -= n * into;
    }
}
