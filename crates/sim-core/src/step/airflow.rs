//! The airflow between copters for the step: the surface below each, the wakes it feels.

use super::*;

/// Air for this control step: the surface below each copter (ground effect) and the
/// downwash force and torque each copter feels from the wakes of the others, from the motion
/// and rotor thrusts at the start of the step (see [`crate::airflow`]).
///
/// Wakes are indexed in a grid by their origin and reach, so each copter only visits the
/// wakes that can touch it: the cost grows with the copters, not with their pairs. Twins make
/// wakes (their real copters blow on the virtual ones) but feel none (their motion is their
/// real copter's). Crashed copters neither make nor feel any.
pub(super) fn airflow(world: &World, state: &mut State, parallel: bool, roles: Roles<'_>) -> u32 {
    let spec = &world.airflow.spec;
    let downwash = spec.downwash && world.copters.len() >= 2;
    let (violations, any) = if downwash { gather_wakes(world, state, parallel, roles) } else { (0, false) };
    // The wakes' grid on one thread, the ground below each copter on the others.
    let crate::state::Scratch { lanes, wake_grid, wake_reach, present, .. } = &mut state.scratch;
    beside(
        parallel,
        || {
            if any {
                wake_grid.set_cover(arena_rect(world));
                match roles.0 {
                    Some(_) => wake_grid.build_some(wake_reach, present, GRID_CELL_M),
                    None => wake_grid.build(wake_reach, GRID_CELL_M),
                }
            }
        },
        || {
            for_each_lane(parallel, &mut state.copters, lanes, |i, _, lane| {
                if !roles.present(i) {
                    return;
                }
                lane.downwash_force_n = Vec3::ZERO;
                lane.downwash_torque_n_m = Vec3::ZERO;
                // The ground below is read by the substeps alone: not of a far ghost, which
                // this shard never steps.
                if !roles.near(i) {
                    return;
                }
                let real_layer = world.copters[i].kind.is_real_layer();
                let af = &world.airframes[world.copters[i].airframe];
                lane.ground_m = match spec.ground_effect && may_be_over_a_box(world, lane.pos_m, af.reach_bound_m) {
                    true => {
                        af.rotor_pos_in_body_m.map(|arm| ground_below(world, lane.pos_m + lane.rot * arm, real_layer))
                    }
                    false => [0.0; 4],
                };
            })
        },
    );
    if any {
        feel_wakes(world, state, parallel, roles);
    }
    violations
}

/// Every copter's wake and its reach (a box around its origin, for the grid) into the scratch.
/// Returns the wakes reaching beyond a shard's halo, and whether any copter makes one.
pub(super) fn gather_wakes(world: &World, state: &mut State, parallel: bool, roles: Roles<'_>) -> (u32, bool) {
    let spec = &world.airflow.spec;
    let scratch = &mut state.scratch;
    let (lanes, copters) = (&scratch.lanes, &state.copters);
    let width_per_m = world.airflow.width_per_m;
    // Each wake with its reach, a sphere around its origin for the wakes' grid. An active
    // wake is one with a length (its origin above the floor, pointing down).
    let with_reach = |w: Wake| {
        let reach = if w.length_m > 0.0 { w.reach_m(width_per_m) } else { 0.0 };
        (w, OrientedBox { center: w.origin, rotation: Quat::IDENTITY, half: Vec3::new(reach, 0.0, 0.0) })
    };
    let (wakes, wake_reach) = (&mut scratch.wakes, &mut scratch.wake_reach);
    let fills = (Wake::default(), OrientedBox::default());
    // In a shard, an absent copter's entries keep what they held: the wakes' grid holds the
    // present ones only, and nothing else reads them.
    fill_present2(parallel, wakes, wake_reach, lanes.len(), fills, roles, |i| {
        let (lane, c) = (&lanes[i], &copters[i]);
        let af = &world.airframes[world.copters[i].airframe];
        let thrust: Real = c.rotor_thrust_n.iter().sum();
        let dir = lane.rot * Vec3::NEG_Z;
        let origin = lane.pos_m + lane.rot * Vec3::new(0.0, 0.0, af.rotor_pos_in_body_m[0].z);
        let active = c.crash.is_none() && thrust > 0.1 * af.hover_thrust_per_rotor_n && dir.z < -0.2 && origin.z > 0.0;
        if !active {
            // Reaches nothing, from where it would start (`wake_reach` is centred there).
            return with_reach(Wake { origin, ..Wake::default() });
        }
        let rho_a = af.spec.air_density_kg_m3 * af.disc_area_m2;
        let hubs = af.rotor_pos_in_body_m.map(|arm| lane.pos_m + lane.rot * arm);
        with_reach(Wake {
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
        })
    });
    let wake_limit = crate::partition::sense_reach_m(world);
    let (mut violations, mut any) = (0, false);
    let mut wake_of = |i: usize| {
        any |= scratch.wakes[i].length_m > 0.0;
        // A shard's neighbours see its copters only within the halo.
        if roles.0.is_some() && roles.owned(i) && scratch.wake_reach[i].half.x > wake_limit {
            violations += 1;
        }
    };
    match roles.0 {
        Some(_) => scratch.present.iter().for_each(|&i| wake_of(i as usize)),
        None => (0..scratch.wakes.len()).for_each(wake_of),
    }
    (violations, any)
}

/// The downwash force and torque each flying virtual copter feels from the wakes near it (the
/// wake grid built), at the rotor speeds and thrusts of the step's start.
pub(super) fn feel_wakes(world: &World, state: &mut State, parallel: bool, roles: Roles<'_>) {
    let spec = &world.airflow.spec;
    let width_per_m = world.airflow.width_per_m;
    let scratch = &mut state.scratch;
    let (wakes, grid) = (&scratch.wakes, &scratch.wake_grid);
    let turbulence = spec.wake_turbulence;
    // Each gust is keyed by the step, the copter, the wake and the rotor, not drawn from the
    // copter's stream: a shard can feel a ghost's wakes before (or without) sensing it.
    let (seed, tick) = (world.params.seed, state.tick);
    for_each_lane(parallel, &mut state.copters, &mut scratch.lanes, |i, c, lane| {
        if !roles.near(i) || c.crash.is_some() || world.copters[i].kind == CopterKind::Real {
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
                    let gust = crate::rng::keyed_triangular(seed, [tick, i as u64, j as u64, r as u64]);
                    let v = v * (1.0 + turbulence * gust).max(0.0);
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
pub(super) const MIN_WAKE_SPEED_M_S: Real = 0.05;

/// Whether a point within `reach_m` of `p` may have a box's top under it (see
/// [`ground_below`]): some box's top above the floor lies up to 1 m below it, its footprint
/// within `reach_m` horizontally.
#[inline]
pub(super) fn may_be_over_a_box(world: &World, p: Vec3, reach_m: Real) -> bool {
    world.boxes.iter().any(|b| {
        let top = b.top_m();
        top > 0.0 && top <= p.z + reach_m && p.z - reach_m - top <= 1.0 && b.footprint_may_be_within(p, reach_m)
    })
}

/// Height of the surface below a point: the floor, or the top of a box under it. Real-layer
/// copters skip boxes that exist only in the simulation (a real copter flies over nothing
/// there).
pub(super) fn ground_below(world: &World, p: Vec3, real_layer: bool) -> Real {
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
