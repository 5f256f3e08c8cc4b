//! A physics substep of one copter: the pass over the copters ([`SubstepPass`]), its inner
//! loops (AHRS, attitude PIDs, height hold, mixer), the rotor model, and the closed-form
//! flight, floor contact and take-off of a free copter.

use super::*;

/// What a physics substep of the copters needs.
#[derive(Clone, Copy)]
pub(super) struct SubstepPass<'a> {
    pub(super) world: &'a World,
    pub(super) inner: InnerParams,
    /// Motor lag per airframe.
    pub(super) alphas: &'a [Real],
    /// Cosine of the crash tilt per airframe.
    pub(super) cos_tilt: &'a [Real],
    pub(super) roles: Roles<'a>,
    pub(super) dt: Real,
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
    ///
    /// With `ids` (ascending), only those copters are looked at: a list that holds every copter
    /// this substep steps, so that the others' lanes are not read at all.
    pub(super) fn closure(
        self,
        s: u32,
        in_rapier: Option<bool>,
        ids: Option<&'a [u32]>,
    ) -> impl Fn(usize, &mut [CopterState], &mut [Lane]) + Sync + Send + 'a {
        move |first, cs, ls| {
            let (mut batch, mut filled) = ([0; LANES], 0);
            // This chunk's part of `ids`.
            let listed = ids.map(|ids| {
                let from = |i: usize| ids.partition_point(|&id| (id as usize) < i);
                &ids[from(first)..from(first + cs.len())]
            });
            for k in 0..listed.map_or(cs.len(), <[u32]>::len) {
                let j = listed.map_or(k, |l| l[k] as usize - first);
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

    pub(super) fn alpha(&self, i: usize) -> Real {
        self.alphas[self.world.copters[i].airframe]
    }

    /// A free copter off watch runs its substeps one after the other, up to the first after
    /// which something may happen to it.
    pub(super) fn run_ahead(&self, i: usize, c: &mut CopterState, lane: &mut Lane) {
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
pub(super) fn substep_lane(
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
        // A wreck in closed form moves in its own pass (`fall_wrecks`).
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

/// What the inner loop needs of the world, computed once per step.
#[derive(Clone, Copy)]
pub(super) struct InnerParams {
    /// The AHRS lag's blend factor for one physics step.
    pub(super) ahrs_alpha: Real,
    pub(super) att_sigma: Real,
    pub(super) rate_sigma: Real,
    pub(super) noise: bool,
    pub(super) ideal: bool,
    pub(super) ground_effect: bool,
    pub(super) ground_effect_min_radii: Real,
}

impl InnerParams {
    pub(super) fn new(world: &World, dt: Real) -> Self {
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
pub(super) fn inner_loop(
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
pub(super) fn steer(
    af: &Airframe,
    p: &InnerParams,
    twin: bool,
    c: &mut CopterState,
    m: &InnerInput,
    dt: Real,
) -> (Real, Vec3) {
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
    let firmware = af.spec.finken_height.as_ref().filter(|_| control::holds_height(af, &c.setpoint));
    let collective = if let Some(fw) = firmware {
        // The lab firmware's own loop, on the IR reading it holds (the truth for twins).
        let ir = if truth { z } else { e.ir_reading_m };
        let command = e.finken_height.step(fw, c.setpoint.height_m, ir, c.battery.voltage_v, dt);
        4.0 * af.hover_thrust_per_rotor_n * command / fw.hover_command
    } else {
        if af.spec.finken_height.is_some() {
            // Landing or on throttle: the firmware loop starts afresh at the next held height.
            e.finken_height = Default::default();
        }
        let t = control::collective_thrust_n(
            af,
            &c.setpoint,
            z,
            vz,
            cos_tilt,
            &mut e.height_integral_n,
            &mut e.landing_stalled_s,
            dt,
        );
        if twin { t } else { t / e.thrust_gain }
    };
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
pub(super) fn drive(
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
pub(super) struct InnerInput {
    pub(super) rot: Quat,
    /// Its Euler angles ([`euler_from_quat`]).
    pub(super) rpy: [Real; 3],
    /// Its angular velocity in the body frame, rad/s.
    pub(super) rate_body: Vec3,
    /// Height of the centre of mass and its vertical speed, m and m/s.
    pub(super) z_m: Real,
    pub(super) vz_m_s: Real,
    /// `Lane::ground_m`.
    pub(super) ground_m: [Real; 4],
}

impl InnerInput {
    #[inline(always)]
    pub(super) fn of(lane: &Lane, rate_body: Vec3) -> Self {
        let (rot, z_m, vz_m_s, ground_m) = (lane.rot, lane.pos_m.z, lane.vel_m_s.z, lane.ground_m);
        Self { rot, rpy: euler_from_quat(rot), rate_body, z_m, vz_m_s, ground_m }
    }
}

/// Ground effect is computed only below this many rotor radii (above, it is under 0.2 %).
pub(super) const GROUND_EFFECT_RADII: Real = 12.0;

/// One physics step of a free-flying copter in closed form: gravity, thrust, torque, Rapier's
/// linear and angular damping (`v / (1 + c dt)`) and its explicit, momentum-preserving
/// gyroscopic term; semi-implicit Euler (velocities first, then pose with the new ones).
/// `rate_body` is its angular velocity in the body frame.
#[inline(always)]
pub(super) fn integrate_free(
    af: &Airframe,
    lane: &mut Lane,
    rate_body: Vec3,
    thrust_n: Real,
    torque_body_n_m: Vec3,
    dt: Real,
) {
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
pub(super) fn lifts_off(af: &Airframe, lane: &Lane, thrust_n: Real) -> bool {
    (lane.rot * Vec3::new(0.0, 0.0, thrust_n)).z + lane.downwash_force_n.z > af.mass_kg * GRAVITY_M_S2
}

/// How far the lowest point of a copter's colliders (body box, rotor discs) lies below its
/// centre of mass at attitude `rot`, m.
#[inline]
pub(super) fn lowest_point_below_centre(af: &Airframe, rot: Quat) -> Real {
    reach_along(af, rot, -Vec3::Z)
}

/// How far a copter's colliders (body box, rotor discs) reach from its centre of mass along
/// the unit direction `d`, at attitude `rot`, m: their support function.
#[inline]
pub(super) fn reach_along(af: &Airframe, rot: Quat, d: Vec3) -> Real {
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
pub(super) fn touch_floor(af: &Airframe, c: &mut CopterState, lane: &mut Lane, vel_before: Vec3, below: Real) {
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
pub(super) fn rotor_model(
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
pub(super) fn motor_alpha(af: &Airframe, dt: Real) -> Real {
    let tau = af.spec.motor_time_constant_s;
    if tau > 0.0 { 1.0 - (-dt / tau).exp() } else { 1.0 }
}
