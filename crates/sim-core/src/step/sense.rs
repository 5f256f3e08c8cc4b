//! Sensing: the sonar scene, the sonars, IR and IMU, the estimators, cross-talk, and the
//! virtual readings' fusion.

use super::*;

/// Gathers what sonars can see in the current state: the arena walls, the static boxes and
/// every copter's body (crashed ones too), indexed in the copter grid. `sense` uses it; so can
/// tools that need the same geometry (e.g. extra virtual sonars).
pub fn fill_sonar_scene(world: &World, copters: &[CopterState], scene: &mut SonarScene) {
    fill_sonar_scene_of(world, copters, Roles(None), None, false, scene);
}

/// [`fill_sonar_scene`] seeing only the copters in `present` (ascending ids: those `roles`
/// has present), if given.
pub(super) fn fill_sonar_scene_of(
    world: &World,
    copters: &[CopterState],
    roles: Roles<'_>,
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
    // The grid below indexes only the present copters: nothing reads an absent one's box.
    fill_present(parallel, &mut scene.copters, copters.len(), OrientedBox::default(), roles, |i| {
        copter_box(world, copters, i)
    });
    scene.grid.set_cover(arena_rect(world));
    match present {
        Some(ids) => scene.index_some_copters(ids, grid_cell_m(world, copters.len())),
        None => scene.index_copters(grid_cell_m(world, copters.len())),
    }
}

/// The real layer's sonar scene (see [`CopterKind::Autopilot`]): the full scene without the
/// `virtual_only` boxes, indexing only the real-layer copters among those `present`.
pub(super) fn fill_real_scene(
    world: &World,
    copters: &[CopterState],
    present: Option<&[u32]>,
    ids: &mut Vec<u32>,
    scene: &mut SonarScene,
) {
    fill_sonar_scene_of(world, copters, Roles(None), None, false, scene);
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
pub(super) fn grid_cell_m(world: &World, n: usize) -> Real {
    let area_m2 = world.arena.size_m[0] * world.arena.size_m[1];
    (area_m2 / n.max(1) as Real).sqrt().clamp(GRID_CELL_M, 4.0 * GRID_CELL_M)
}

/// The arena's floor rectangle, `[x0, y0, x1, y1]`, m.
pub(super) fn arena_rect(world: &World) -> [Real; 4] {
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
pub(super) fn sense(
    world: &World,
    state: &mut State,
    inputs: &Inputs,
    sonar_due: bool,
    parallel: bool,
    roles: Roles<'_>,
    probe: &mut (dyn FnMut(Stage) + Send),
) {
    let crosstalk_due = sonar_due && world.sensors.spec.crosstalk.enabled && world.copters.len() > 1;
    let autopilots = world.copters.iter().any(|c| c.kind == CopterKind::Autopilot);
    let crate::state::Scratch { present, sonar_scene, real_scene, real_ids, pingers, lanes, .. } = &mut state.scratch;
    let (copters, present) = (&state.copters, roles.0.map(|_| &present[..]));
    // The scene's copter grid on one thread, the pingers on the others.
    beside(
        parallel,
        || {
            fill_sonar_scene_of(world, copters, roles, present, parallel, sonar_scene);
            if autopilots {
                fill_real_scene(world, copters, present, real_ids, real_scene);
            }
        },
        || {
            if sonar_due {
                gather_pingers(world, copters, lanes, pingers, parallel, roles);
            }
        },
    );
    probe(Stage::SonarScene);
    let crate::state::Scratch { sonar_scene, real_scene, pingers, ping_points, ping_grid, lanes, present, .. } =
        &mut state.scratch;
    let present = roles.0.map(|_| &present[..]);
    let (scene, real_scene, pingers) = (&*sonar_scene, &*real_scene, &*pingers);
    let p = SenseParams::new(world, state.tick, sonar_due);
    let copters = &mut state.copters;
    // Cross-talk's grid of pingers on one thread, every copter's readings on the others.
    beside(
        parallel,
        || {
            if crosstalk_due {
                fill_ping_grid(world, pingers, present, ping_points, ping_grid);
            }
        },
        || {
            for_each_lane(parallel, copters, lanes, |i, c, lane| {
                // A wreck's sensors stop (and its sonars no longer ping): its readings keep
                // their last values.
                if !roles.owned(i) || c.crash.is_some() {
                    return;
                }
                let real_layer = autopilots && world.copters[i].kind == CopterKind::Autopilot;
                let cones = pingers.get(i).map(|p| &p.cones);
                let ir = read_ranges(world, &p, if real_layer { real_scene } else { scene }, i, cones, c, lane);
                read_imu_and_estimate(world, &p, i, c, lane, ir);
            })
        },
    );
    probe(Stage::Ranges);
    if crosstalk_due {
        crosstalk(world, state, &p, parallel, roles);
    }
    probe(Stage::Crosstalk);
    fuse_and_filter(world, state, inputs, &p, parallel, roles);
}

/// What every copter's sensing shares in one control step.
pub(super) struct SenseParams {
    pub(super) tick: u64,
    pub(super) dt_control: Real,
    pub(super) sonar_due: bool,
    /// Which sonars this step reads ([`fresh_sonars`]).
    pub(super) fresh: [bool; 4],
    /// The yaw bias's decay and random walk over the step.
    pub(super) yaw_decay: Real,
    pub(super) yaw_walk: Real,
    /// The reported heading's noise per reading, rad.
    pub(super) yaw_sigma: Real,
}

impl SenseParams {
    pub(super) fn new(world: &World, tick: u64, sonar_due: bool) -> Self {
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
pub(super) fn gather_pingers(
    world: &World,
    copters: &[CopterState],
    lanes: &[Lane],
    pingers: &mut Vec<Pinger>,
    parallel: bool,
    roles: Roles<'_>,
) {
    // In a shard, an absent copter's entry keeps what it held ([`fill_ping_grid`] passes over it).
    fill_present(parallel, pingers, world.copters.len(), Pinger::default(), roles, |i| {
        let (lane, c) = (&lanes[i], &copters[i]);
        let pings = c.crash.is_none();
        Pinger {
            pos_m: lane.pos_m,
            cones: if pings { sonar_cones(&world.sensors, lane.pos_m, lane.rot) } else { Default::default() },
            phase_s: c.sonar_phase_s,
            cycle_s: c.sonar_cycle_s,
            pings,
        }
    });
}

/// The grid of the copters that ping, for [`crosstalk`]: of all, or in a shard of those
/// `present` (an absent one's pinger is stale).
pub(super) fn fill_ping_grid(
    world: &World,
    pingers: &[Pinger],
    present: Option<&[u32]>,
    ping_points: &mut Vec<(u32, Vec3)>,
    ping_grid: &mut sensors::CopterGrid,
) {
    ping_points.clear();
    let pinging = |i: u32| pingers[i as usize].pings.then(|| (i, pingers[i as usize].pos_m));
    match present {
        Some(ids) => ping_points.extend(ids.iter().filter_map(|&i| pinging(i))),
        None => ping_points.extend((0..pingers.len() as u32).filter_map(pinging)),
    }
    ping_grid.set_cover(arena_rect(world));
    // The wedges reach the sonars' full range: cells twice the usual size visit fewer rows
    // and cells per wedge (any size gives the same readings).
    ping_grid.build_points(ping_points, 2.0 * grid_cell_m(world, ping_points.len()));
}

/// A copter's fresh sonars (when due: `cones` from [`gather_pingers`]) and its IR, down the
/// body's −z axis, in `scene`. Returns the IR reading before its range check (the height
/// estimator takes it as it is).
#[inline]
pub(super) fn read_ranges(
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
pub(super) fn read_imu_and_estimate(
    world: &World,
    p: &SenseParams,
    i: usize,
    c: &mut CopterState,
    lane: &Lane,
    ir: Real,
) {
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
pub(super) fn crosstalk(world: &World, state: &mut State, p: &SenseParams, parallel: bool, roles: Roles<'_>) {
    let params = &world.sensors;
    let (ct, sonar) = (&params.spec.crosstalk, &params.spec.sonar);
    let now_s = world.time_at(p.tick);
    let stagger = if sonar.schedule == SonarSchedule::RoundRobin { 0.25 } else { 0.0 };
    // The pingers' grid is [`fill_ping_grid`]'s.
    let crate::state::Scratch { pingers, ping_grid, lanes, .. } = &mut state.scratch;
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
        // Another shard's copter pings, and this shard's hear it, but its own readings are its
        // owner's. (The role first: an absent copter's entries are not read.)
        if !roles.owned(b) || !pingers[b].pings {
            return;
        }
        let me = &pingers[b];
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
pub(super) fn crosstalk_growth(h: Real, slack: Real) -> Real {
    let c = h.cos() * slack + 1e-4;
    let least_sin = h.sin().min((h + std::f32::consts::FRAC_PI_4).sin()).min((0.5 * h).cos());
    c / least_sin.max(1e-3) + 1e-3
}

/// Each copter's readings fused with its virtual ones (`min`), and each fresh fused reading
/// into the firmware's sonar filter (a wreck's sonars are silent).
pub(super) fn fuse_and_filter(
    world: &World,
    state: &mut State,
    inputs: &Inputs,
    p: &SenseParams,
    parallel: bool,
    roles: Roles<'_>,
) {
    let wall_avoid = &world.sensors.spec.wall_avoid;
    for_each_lane(parallel, &mut state.copters, &mut state.scratch.lanes, |i, c, _| {
        // Another shard's copter is fused and filtered by its owner.
        if !roles.owned(i) {
            return;
        }
        let virt = inputs.commands.get(i).and_then(|c| c.virtual_sonar_m);
        let r = &mut c.sensors;
        r.sonar_fused_m = sensors::fuse_min(r.sonar_m, virt);
        if p.sonar_due && c.crash.is_none() {
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
pub(super) fn heard_reading(
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
pub(super) fn lower_reading(r: &mut sensors::SensorReadings, k: usize, q: Real) {
    if q < r.sonar_m[k] {
        r.sonar_m[k] = q;
        r.sonar_crosstalk[k] = true;
    }
}
