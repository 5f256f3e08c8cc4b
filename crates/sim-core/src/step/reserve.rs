//! Which copters fly free of Rapier this step: reachable spheres, free and watched copters,
//! a shard's ownership and held clusters, watch pairs, falling wrecks, and the Rapier bodies
//! that enter or leave.

use super::*;

/// Decides which copters fly free of Rapier for this control step.
///
/// A copter flies free when the sphere it can reach within the step (its colliders' bounding
/// radius plus `|v| T + a_max T² / 2`, with `a_max` from its maximum thrust with headroom and
/// gravity) keeps [`FREE_GAP_M`] from the walls, the ceiling, the boxes and every other
/// copter's reachable sphere. Nothing but the floor can then touch it during the step, and the
/// floor is met in closed form ([`touch_floor`]), so Rapier has nothing to do for it: its body
/// is disabled and it is integrated in closed form (semi-implicit Euler, Rapier's damping and
/// gyroscopic terms). A copter whose sphere meets only other copters' flies free on watch
/// ([`watch_contacts`]). Wrecks fall and rest in closed form too ([`fall_wrecks`]), their
/// bodies fixed in Rapier where flying copters can hit them.
pub(super) fn reserve_free_flight(
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
    enable_rapier_bodies(world, state, view, parallel);
    let roles = Roles(view.as_ref().map(|v| &v.roles[..]));
    let scratch = &mut state.scratch;
    scratch.in_rapier.clear();
    // Room for every copter, so that entering Rapier during the step never grows it.
    scratch.in_rapier.reserve(scratch.lanes.len());
    let lanes = scratch.lanes.iter().enumerate();
    scratch.in_rapier.extend(lanes.filter(|(i, l)| roles.owned(*i) && !l.free).map(|(i, _)| i as u32));
    violations
}

/// Each copter's reachable sphere for the step (`Lane::reserved_m`, and per substep
/// `substep_reserved_m`), and the grid of them.
pub(super) fn reserve_spheres(world: &World, state: &mut State, parallel: bool, roles: Roles<'_>) {
    let t = world.params.control_dt_s as Real;
    let dt = world.physics_dt();
    let scratch = &mut state.scratch;
    scratch.spheres.resize(scratch.lanes.len(), OrientedBox::default());
    let (lanes, spheres) = (&mut scratch.lanes, &mut scratch.spheres);
    for_each_lane_with(parallel, &mut state.copters, lanes, spheres, |i, c, lane, sphere| {
        if !roles.present(i) {
            return;
        }
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
        let half = Vec3::new(lane.reserved_m, 0.0, 0.0);
        *sphere = OrientedBox { center: lane.pos_m, rotation: crate::math::Quat::IDENTITY, half };
    });
    // The grid is indexed already ([`index_sphere_centres`]); its reach is the largest sphere's.
    let radius = |i: usize| scratch.spheres[i].bounding_radius();
    let max_radius_m = match roles.0 {
        Some(_) => scratch.present.iter().map(|&i| radius(i as usize)).fold(0.0, Real::max),
        None => (0..scratch.spheres.len()).map(radius).fold(0.0, Real::max),
    };
    scratch.sphere_grid.set_max_radius(max_radius_m);
}

/// The grid of the copters' reachable spheres, by their centres alone: the copters' positions
/// at the step's start (the lanes' positions, which nothing moves before the substeps; so it
/// can be built beside the lanes' loading; [`reserve_spheres`] sets its reach).
pub(super) fn index_sphere_centres(
    world: &World,
    copters: &[CopterState],
    present: &[u32],
    roles: Roles<'_>,
    grid: &mut sensors::CopterGrid,
) {
    grid.set_cover(arena_rect(world));
    let ids = roles.0.map(|_| present);
    grid.build_centres(copters.len(), ids, |i| copters[i].motion.pos_m, GRID_CELL_M);
}

/// Which copters fly free (their spheres clear of the walls, the ceiling and the boxes) and,
/// of those, which on watch (their spheres meet another copter's); in a shard, which spheres
/// meet another copter's at all (`Lane::touching`, for [`take_ownership`]).
pub(super) fn sort_free_and_watched(world: &World, state: &mut State, parallel: bool, roles: Roles<'_>) {
    let scratch = &mut state.scratch;
    let spheres = &scratch.spheres;
    let grid = &scratch.sphere_grid;
    let arena = &world.arena;
    let (hx, hy) = (arena.size_m[0] / 2.0, arena.size_m[1] / 2.0);
    let closed_form = world.params.closed_form;
    // Whether copter `i`'s sphere (centre `p`, radius `r` with the gap) meets another's.
    let meets_another = |i: usize, p: Vec3, r: Real| {
        let mut meets = false;
        grid.visit_near(p, r, |j| {
            meets |= j != i && (spheres[j].center - p).length() <= r + spheres[j].half.x;
            if meets { -1.0 } else { r }
        });
        meets
    };
    // A shard's ownership joins the copters whose spheres meet: it looks only at those.
    let shard = roles.0.is_some();
    for_each_lane(parallel, &mut state.copters, &mut scratch.lanes, |i, c, lane| {
        // An absent copter's lane is not touched: nothing reads its flags.
        if !roles.present(i) {
            return;
        }
        (lane.free, lane.watch, lane.touching) = (false, false, false);
        lane.floor_impact_m_s = 0.0;
        let (p, r) = (lane.pos_m, lane.reserved_m + FREE_GAP_M);
        // A wreck in closed form falls and lies outside Rapier's dynamics (`fall_wrecks`).
        if c.crash.is_some() && closed_form {
            (lane.free, lane.touching) = (true, shard && meets_another(i, p, r));
            return;
        }
        // The floor needs no clearance: free flight meets it in closed form.
        let mut free = c.crash.is_none() && closed_form;
        if free && arena.walls {
            free = p.x.abs() + r < hx && p.y.abs() + r < hy && p.z + r < arena.height_m;
        }
        if free {
            free = world.boxes.iter().all(|b| b.is_farther_than(p, r));
        }
        // Clear of the walls and boxes but near other copters: on watch.
        let meets = (free || shard) && meets_another(i, p, r);
        (lane.free, lane.watch, lane.touching) = (free, free && meets, meets);
        // Rapier keeps a copter on the floor itself; back in free flight it lands anew.
        c.grounded &= free;
    });
}

/// Everything a copter on watch may come close to this step (once per pair; in a shard,
/// both are its own: they are in one contact cluster).
pub(super) fn gather_watch_pairs(state: &mut State, roles: Roles<'_>) {
    let scratch = &mut state.scratch;
    scratch.watch_pairs.clear();
    // A few neighbours per copter, kept from step to step.
    scratch.watch_pairs.reserve(4 * scratch.lanes.len());
    for (i, lane) in scratch.lanes.iter().enumerate().filter(|&(i, l)| roles.owned(i) && l.watch) {
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
pub(super) fn gather_falling(world: &World, state: &mut State, roles: Roles<'_>) {
    let scratch = &mut state.scratch;
    scratch.falling.clear();
    // Room for every copter, so that a crash never grows it.
    scratch.falling.reserve(scratch.lanes.len());
    if world.params.closed_form {
        // The role first: a shard's other copters' states are not read.
        let owned_falling = |(i, c): (usize, &CopterState)| roles.owned(i) && c.crash.is_some() && !c.grounded;
        scratch.falling.extend(state.copters.iter().enumerate().filter(|&ic| owned_falling(ic)).map(|(i, _)| i as u32));
    }
}

/// Each copter's Rapier body enabled for the step if it goes through Rapier, disabled if it
/// flies free or belongs to another shard; a wreck a shard has just taken over enters as its
/// owner had it. Which bodies change is found first, in parallel chunks (reading Rapier's
/// bodies only); the few that do are changed in id order.
pub(super) fn enable_rapier_bodies(world: &World, state: &mut State, view: &Option<ShardView>, parallel: bool) {
    let closed_form = world.params.closed_form;
    let (lanes, copters, bodies) = (&state.scratch.lanes, &state.copters, &state.physics.bodies);
    let roles = view.as_ref().map(|v| &v.roles[..]);
    let tick = state.tick;
    fill_each(parallel, &mut state.scratch.body_changes, copters.len(), false, |i| {
        let role = roles.map(|r| r[i]);
        // An absent copter's body was disabled while it was still read here (a copter leaves a
        // shard as a ghost, and its body is disabled then), in the state a checkpoint keeps;
        // nothing enables it since. Not looked up: most of a shard's table is absent.
        if role == Some(Role::Absent) {
            debug_assert!(
                !bodies[copters[i].body].is_enabled(),
                "absent copter {i} has an enabled body at tick {tick}"
            );
            return false;
        }
        body_changes(role, &copters[i], &lanes[i], bodies[copters[i].body].is_enabled())
    });
    for i in 0..state.copters.len() {
        if !state.scratch.body_changes[i] {
            continue;
        }
        // Borrowed mutably only when something changes: a mutable borrow marks a Rapier body
        // modified, and Rapier's next step revisits every modified body.
        let (lane, c) = (&state.scratch.lanes[i], &state.copters[i]);
        let physics = &mut state.physics;
        match view {
            // Another shard's copter is not in this shard's Rapier world.
            Some(v) if v.roles[i] != Role::Owned => physics.bodies[c.body].set_enabled(false),
            // A wreck this shard has just taken over enters as its owner had it: in closed
            // form fixed (disabled here, so the same body: the handle does not change).
            Some(_) if c.crash.is_some() && closed_form => {
                fix_wreck(world, physics, c.body, lane, i, !c.grounded);
            }
            Some(v) if c.crash.is_some() => take_over_wreck(&mut physics.bodies[c.body], lane, v.asleep[i]),
            _ if lane.free => physics.bodies[c.body].set_enabled(false),
            _ => enter_rapier(&mut physics.bodies[c.body], lane),
        }
    }
}

/// Whether [`enable_rapier_bodies`] changes copter `c`'s body (`enabled` now), with its role
/// in a shard.
fn body_changes(role: Option<Role>, c: &CopterState, lane: &Lane, enabled: bool) -> bool {
    match role {
        Some(r) if r != Role::Owned => enabled,
        Some(_) if c.crash.is_some() && !enabled => true,
        // A wreck's body is fixed (closed form) or Rapier's from its crash on.
        _ => c.crash.is_none() && lane.free == enabled,
    }
}

/// A shard's ownership for this step (see [`crate::shard`]): copters whose reservations
/// meet form contact clusters, and a cluster belongs to the home region of its lowest id,
/// unless Rapier carries one of its copters over from the last step: then it stays with the
/// shard whose Rapier world holds the lowest such copter ([`held_clusters`]).
/// Counts the violations: a cluster this shard had or takes a copter of, with a member
/// beyond the pull zone (its view of that cluster may be incomplete).
pub(super) fn take_ownership(state: &mut State, view: &mut ShardView) -> u32 {
    use crate::partition::{PULL_ZONE_M, root, union};
    let scratch = &mut state.scratch;
    let n = state.copters.len();
    let parent = &mut view.parent;
    parent.clear();
    parent.extend(0..n as u32);
    let (spheres, grid) = (&scratch.spheres, &scratch.sphere_grid);
    // A copter whose sphere meets no other is a cluster of its own.
    for &i in scratch.present.iter().filter(|&&i| scratch.lanes[i as usize].touching) {
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
    // The substeps pass over the copters this shard does not step at once (see `NOT_STEPPED`).
    let crate::state::Scratch { present, lanes, .. } = &mut state.scratch;
    for &i in present.iter() {
        if view.roles[i as usize] != Role::Owned {
            lanes[i as usize].batched = super::NOT_STEPPED;
        }
    }
    let scratch = &state.scratch;
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
/// cluster with it, while it is within [`crate::partition::HELD_ZONE_M`] of that shard's region.
/// Not covered, and not counted: a held copter farther out than that, and the second of two
/// copters held by different shards that come into one cluster, go to the cluster's owner
/// fresh (docs/sharding.md).
pub(super) fn held_clusters(state: &State, view: &mut ShardView) {
    use crate::partition::{HELD_ZONE_M, held_in_rapier, root};
    let n = state.copters.len();
    view.claim.clear();
    view.claim.resize(n, None);
    // The present copters, in id order: a cluster goes with its lowest held copter.
    for &i in &state.scratch.present {
        let i = i as usize;
        let lane = &state.scratch.lanes[i];
        // Free and off watch, it is Rapier's no longer: its own copter's body is not looked up
        // (`held_by` of this shard's copters is read only below).
        if lane.free && !lane.watch {
            continue;
        }
        if view.roles[i] == Role::Owned {
            let held = state.physics.bodies.get(state.copters[i].body).is_some_and(held_in_rapier);
            view.held_by[i] = held.then_some(view.me);
        }
        let Some(k) = view.held_by[i] else { continue };
        if view.partition.distance_to(lane.pos_m, k) > HELD_ZONE_M {
            continue;
        }
        let home = root(&mut view.parent, i as u32) as usize;
        view.claim[home].get_or_insert(k);
    }
}

/// A wreck that has just become this shard's enters its Rapier world as its owner had it
/// (`closed_form = false`; in closed form it is fixed, [`fix_wreck`]): a dynamic body, asleep
/// if it was.
pub(super) fn take_over_wreck(body: &mut RigidBody, lane: &Lane, asleep: bool) {
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
pub(super) fn enter_rapier(body: &mut RigidBody, lane: &Lane) {
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
pub(super) fn watch_contacts(state: &mut State, dt: Real) {
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
