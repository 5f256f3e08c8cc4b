//! Batches of four copters run ahead side by side ([`run_ahead_batch`]): a free copter's
//! substep on [`lanes`], each lane rounding as the scalar code does.
//!
//! The lane functions here are twins of scalar ones (`steer`, `drive`, `control::mix`,
//! `rotor_model`, `BatteryState::draw`, `integrate_free`, `may_act`): a change to one must be
//! made to its twin, and `tests::a_batch_runs_ahead_as_its_copters_do_alone` fails until it is.

use super::*;
use crate::airframe::PidGains;
use crate::lanes::{self, F4, M4, Q4, V4};

/// Four free copters off watch and off the floor, of one airframe, run ahead side by side:
/// each substep's body rates, Euler angles, inner loops ([`inner_loops`]) and closed-form
/// flight on four lanes, until one of them may act ([`may_act`]) or may touch the floor (it
/// then meets it as [`substep_lane`] does), or all have run the step's substeps. The copters
/// stopped early go on in the lockstep substeps: the same arithmetic, the same bits.
pub(super) fn run_ahead_batch(
    pass: &SubstepPass<'_>,
    ids: [usize; LANES],
    mut cs: [&mut CopterState; LANES],
    ls: [&mut Lane; LANES],
) {
    let (world, dt) = (pass.world, pass.dt);
    let af = &world.airframes[ls[0].airframe as usize];
    let twin = ids.map(|i| world.copters[i].kind == CopterKind::Real);
    let alpha = pass.alpha(ids[0]);
    let mut f = FreeLanes::gather(&ls);
    let mut steering = SteerLanes::gather(af, &pass.inner, twin, &cs);
    let ground_m = ls.each_ref().map(|l| l.ground_m);
    let ground = GroundLanes::of(&ground_m);
    let bounds = ActBounds::of(af, pass.cos_tilt, &ls);
    let mut n = 0;
    let mut ls = ls;
    let floor_near = loop {
        let rate_body = f.rot.inverse().rotate(f.angvel);
        let rpy = lanes::euler_from_quat(f.rot);
        // Each copter's inputs, for the inner loops lanes do not compute.
        let inputs = || {
            let [roll, pitch, yaw] = rpy.map(F4::to_array);
            let (rots, rates) = (f.rot.lanes(), rate_body.lanes());
            let (z, vz) = (f.pos.z.to_array(), f.vel.z.to_array());
            std::array::from_fn(|l| InnerInput {
                rot: rots[l],
                rpy: [roll[l], pitch[l], yaw[l]],
                rate_body: rates[l],
                z_m: z[l],
                vz_m_s: vz[l],
                ground_m: ground_m[l],
            })
        };
        let at = Attitude { rot: f.rot, rpy, rate_body, z: f.pos.z };
        let (thrust, torque) = inner_loops(pass, af, twin, &mut steering, &mut cs, inputs, &at, &ground, alpha);
        let vel_before = f.vel;
        f.integrate(af, rate_body, thrust, torque, dt);
        n += 1;
        // Higher than any collider reaches, it cannot touch the floor.
        let floor_near = f.pos.z.gt(F4::splat(af.reach_bound_m)).not();
        if floor_near.any() {
            break Some((floor_near, vel_before));
        }
        if n == world.params.substeps || f.may_act(&bounds) {
            break None;
        }
    };
    f.scatter(&mut ls, n);
    if let Some(steering) = &steering {
        steering.scatter(&mut cs, n);
    }
    if let Some((near, vel_before)) = floor_near {
        for l in (0..LANES).filter(|&l| near.get(l)) {
            let (c, lane) = (&mut *cs[l], &mut *ls[l]);
            let below = lowest_point_below_centre(af, lane.rot);
            if lane.pos_m.z - below < 0.0 {
                touch_floor(af, c, lane, vel_before.lane(l), below);
            }
            lane.vel_before_m_s = lane.vel_m_s;
        }
    }
}

/// What the inner loops read of a batch's motion in a substep, one copter per lane.
struct Attitude {
    rot: Q4,
    /// Euler angles ([`lanes::euler_from_quat`]).
    rpy: [F4; 3],
    /// Angular velocity in the body frame, rad/s.
    rate_body: V4,
    /// Height of the centre of mass, m.
    z: F4,
}

/// The ground under a batch's rotors (`Lane::ground_m`), which stays for the batch.
struct GroundLanes {
    /// Under rotor `r`, one copter per lane, m.
    below: [F4; 4],
    /// The highest of the four (at least 0), m.
    highest: F4,
}

impl GroundLanes {
    fn of(ground_m: &[[Real; 4]; LANES]) -> Self {
        Self {
            below: std::array::from_fn(|r| F4::from_array(ground_m.map(|g| g[r]))),
            highest: F4::from_array(ground_m.map(|g| g.iter().copied().fold(0.0, Real::max))),
        }
    }
}

/// The inner loops of a batch's four copters: on lanes where they can be, else one by one
/// (on `inputs`).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn inner_loops(
    pass: &SubstepPass<'_>,
    af: &Airframe,
    twin: [bool; LANES],
    steering: &mut Option<SteerLanes>,
    cs: &mut [&mut CopterState; LANES],
    inputs: impl Fn() -> [InnerInput; LANES],
    at: &Attitude,
    ground: &GroundLanes,
    alpha: Real,
) -> (F4, V4) {
    let (p, dt) = (&pass.inner, pass.dt);
    let lanes = |each: [(Real, Vec3); LANES]| (F4::from_array(each.map(|e| e.0)), V4::gather(each.map(|e| e.1)));
    let Some(steering) = steering else {
        let inputs = inputs();
        return lanes(std::array::from_fn(|l| inner_loop(af, p, twin[l], cs[l], &inputs[l], dt, alpha)));
    };
    let noise = p.noise.then(|| imu_draws(cs));
    let (collective, torque) = steering.step(af, p, at.rpy, at.rate_body, noise, dt);
    if let Some(done) = drive_lanes(af, p, cs, at, ground, collective, torque, dt, alpha) {
        return done;
    }
    let inputs = inputs();
    let (collective, torque) = (collective.to_array(), torque.lanes());
    lanes(std::array::from_fn(|l| drive(af, p, twin[l], cs[l], &inputs[l], collective[l], torque[l], dt, alpha)))
}

/// The motion of a batch of free copters, one per lane.
struct FreeLanes {
    pos: V4,
    rot: Q4,
    vel: V4,
    angvel: V4,
    downwash_force: V4,
    downwash_torque: V4,
}

impl FreeLanes {
    fn gather(ls: &[&mut Lane; LANES]) -> Self {
        Self {
            pos: V4::gather(std::array::from_fn(|l| ls[l].pos_m)),
            rot: Q4::gather(std::array::from_fn(|l| ls[l].rot)),
            vel: V4::gather(std::array::from_fn(|l| ls[l].vel_m_s)),
            angvel: V4::gather(std::array::from_fn(|l| ls[l].angvel_rad_s)),
            downwash_force: V4::gather(std::array::from_fn(|l| ls[l].downwash_force_n)),
            downwash_torque: V4::gather(std::array::from_fn(|l| ls[l].downwash_torque_n_m)),
        }
    }

    /// Back into the lanes, after `n` substeps run ahead.
    fn scatter(&self, ls: &mut [&mut Lane; LANES], n: u32) {
        let (pos, rot, vel, angvel) = (self.pos.lanes(), self.rot.lanes(), self.vel.lanes(), self.angvel.lanes());
        for (l, lane) in ls.iter_mut().enumerate() {
            lane.pos_m = pos[l];
            lane.rot = rot[l];
            lane.vel_m_s = vel[l];
            lane.angvel_rad_s = angvel[l];
            lane.vel_before_m_s = lane.vel_m_s;
            lane.batched = n;
        }
    }

    /// [`integrate_free`] on every lane.
    #[inline(always)]
    fn integrate(&mut self, af: &Airframe, rate_body: V4, thrust_n: F4, torque_body_n_m: V4, dt: Real) {
        let rot = self.rot;
        let zero = F4::splat(0.0);
        let acc = rot.rotate(V4::new(zero, zero, thrust_n / af.mass_kg)) + self.downwash_force.div_by(af.mass_kg)
            - V4::splat(Vec3::new(0.0, 0.0, GRAVITY_M_S2));
        let vel = (self.vel + acc.scale_by(dt)).scale_by(1.0 / (1.0 + dt * af.spec.linear_damping));
        let inertia = Vec3::from(af.inertia_kg_m2);
        let torque_body_n_m = torque_body_n_m + rot.inverse().rotate(self.downwash_torque);
        let w_b = rate_body + torque_body_n_m.div_each(inertia).scale_by(dt);
        let l = w_b.mul_each(inertia);
        let l_gyro = l - w_b.cross(l).scale_by(dt);
        let n2 = l_gyro.dot(l_gyro);
        let conserved = l_gyro.scale((l.dot(l) / n2).sqrt()).div_each(inertia);
        let spins = n2.gt(zero);
        let w_b = V4::new(
            F4::select(spins, conserved.x, w_b.x),
            F4::select(spins, conserved.y, w_b.y),
            F4::select(spins, conserved.z, w_b.z),
        );
        let w = rot.rotate(w_b.scale_by(1.0 / (1.0 + dt * af.spec.angular_damping)));
        self.vel = vel;
        self.angvel = w;
        self.pos = self.pos + vel.scale_by(dt);
        let half_w = w.scale_by(0.5 * dt);
        self.rot = rot.add_normalize(Q4::pure_mul(half_w, rot));
    }

    /// Whether [`may_act`] holds for any lane.
    #[inline(always)]
    fn may_act(&self, b: &ActBounds) -> bool {
        let zero = F4::splat(0.0);
        let up = self.rot.rotate(V4::new(zero, zero, F4::splat(1.0))).z.clamp(-1.0, 1.0);
        let offset = self.pos - b.anchor;
        let moved = offset.dot(offset).sqrt();
        b.now || up.lt(b.least_up).or(moved.gt(b.most_moved)).or(self.pos.z.gt(b.highest)).any()
    }
}

/// [`may_act`]'s bounds for a batch's copters, one per lane: what it reads of a lane other
/// than its motion stays for the batch. A bound a lane cannot cross is infinite (comparisons
/// with a NaN are false, as in the scalar test).
struct ActBounds {
    /// Some lane may act at once (flying free after a floor impact).
    now: bool,
    /// The least `z` of the body's up axis (flying: the crash tilt's cosine).
    least_up: F4,
    /// The farthest the copter may move from its anchor (flying free: its reach), m.
    most_moved: F4,
    anchor: V4,
    /// The height of a take-off (flying, awaiting one), m.
    highest: F4,
}

impl ActBounds {
    fn of(af: &Airframe, crash_cos_tilt: &[Real], ls: &[&mut Lane; LANES]) -> Self {
        let each = |f: &dyn Fn(&Lane) -> Real| F4::from_array(std::array::from_fn(|l| f(ls[l])));
        let takeoff_m = af.rest_height_m + TAKEOFF_MARGIN_M;
        Self {
            now: ls.iter().any(|l| l.flying && l.free && l.floor_impact_m_s > 0.0),
            least_up: each(&|l| if l.flying { crash_cos_tilt[l.airframe as usize] } else { Real::NEG_INFINITY }),
            most_moved: each(&|l| if l.flying && l.free { l.reach_m } else { Real::INFINITY }),
            anchor: V4::gather(std::array::from_fn(|l| ls[l].anchor_m)),
            highest: each(&|l| if l.flying && l.awaiting_takeoff { takeoff_m } else { Real::INFINITY }),
        }
    }
}

/// The attitude and height loops of a batch ([`steer`]), one copter per lane, with the state
/// they keep, held in lanes for the batch. For copters with an estimator (not twins, not
/// `ideal`) holding a height on the newton PIDs: [`SteerLanes::gather`] says whether all four do.
struct SteerLanes {
    attitude_bias: [F4; 2],
    mount_offset: [F4; 2],
    yaw_bias: F4,
    gyro_bias: [F4; 3],
    attitude_lag: [F4; 3],
    rate_lag: [F4; 3],
    attitude: [F4; 3],
    rate: [F4; 3],
    height: F4,
    vz: F4,
    height_integral: F4,
    thrust_gain: F4,
    collective_sum: F4,
    /// The PIDs' integral, last error, reference angle and rate: roll, pitch, yaw.
    integral: [F4; 3],
    last_error: [F4; 3],
    reference: [F4; 3],
    reference_rate: [F4; 3],
    /// Roll and pitch targets (clamped to the maximum tilt), yaw and height setpoints.
    roll_target: F4,
    pitch_target: F4,
    yaw_setpoint: F4,
    height_setpoint: F4,
    trim: [F4; 2],
}

impl SteerLanes {
    /// The batch's state, when every copter's inner loop takes the path lanes compute.
    fn gather(af: &Airframe, p: &InnerParams, twin: [bool; LANES], cs: &[&mut CopterState; LANES]) -> Option<Self> {
        let spec = &af.spec;
        let lanes_fit = spec.finken_height.is_none() && spec.attitude_ref_omega_rad_s > 0.0;
        if !lanes_fit || p.ideal || twin.contains(&true) || !cs.iter().all(|c| control::holds_height(af, &c.setpoint)) {
            return None;
        }
        let lanes = |f: fn(&CopterState) -> Real| per_copter(cs, f);
        let axes = |f: fn(&CopterState, usize) -> Real| std::array::from_fn(|k| per_copter(cs, |c| f(c, k)));
        let max_tilt = spec.max_tilt_deg.to_radians();
        Some(Self {
            attitude_bias: [lanes(|c| c.estimate.attitude_bias_rad[0]), lanes(|c| c.estimate.attitude_bias_rad[1])],
            mount_offset: [lanes(|c| c.estimate.mount_offset_rad[0]), lanes(|c| c.estimate.mount_offset_rad[1])],
            yaw_bias: lanes(|c| c.yaw_bias_rad),
            gyro_bias: axes(|c, k| c.estimate.gyro_bias_rad_s[k]),
            attitude_lag: axes(|c, k| c.estimate.attitude_lag_rad[k]),
            rate_lag: axes(|c, k| c.estimate.rate_lag_rad_s[k]),
            attitude: axes(|c, k| c.estimate.attitude_rad[k]),
            rate: axes(|c, k| c.estimate.rate_rad_s[k]),
            height: lanes(|c| c.estimate.height_m),
            vz: lanes(|c| c.estimate.vz_m_s),
            height_integral: lanes(|c| c.estimate.height_integral_n),
            thrust_gain: lanes(|c| c.estimate.thrust_gain),
            collective_sum: lanes(|c| c.estimate.collective_sum_n),
            integral: axes(|c, k| c.pids[k].integral),
            last_error: axes(|c, k| c.pids[k].last_error),
            reference: axes(|c, k| c.pids[k].reference_rad),
            reference_rate: axes(|c, k| c.pids[k].reference_rate_rad_s),
            roll_target: per_copter(cs, |c| c.setpoint.roll_rad.clamp(-max_tilt, max_tilt)),
            pitch_target: per_copter(cs, |c| c.setpoint.pitch_rad.clamp(-max_tilt, max_tilt)),
            yaw_setpoint: lanes(|c| c.setpoint.yaw_rad),
            height_setpoint: lanes(|c| c.setpoint.height_m),
            trim: [lanes(|c| c.trim_torque_n_m[0]), lanes(|c| c.trim_torque_n_m[1])],
        })
    }

    /// Back into the copters, after `n` substeps.
    fn scatter(&self, cs: &mut [&mut CopterState; LANES], n: u32) {
        let arrays = |v: &[F4; 3]| v.map(F4::to_array);
        let (att_lag, rate_lag, att, rate) =
            (arrays(&self.attitude_lag), arrays(&self.rate_lag), arrays(&self.attitude), arrays(&self.rate));
        let (integral, last, reference, reference_rate) =
            (arrays(&self.integral), arrays(&self.last_error), arrays(&self.reference), arrays(&self.reference_rate));
        let (height_integral, collective_sum) = (self.height_integral.to_array(), self.collective_sum.to_array());
        for (l, c) in cs.iter_mut().enumerate() {
            let e = &mut c.estimate;
            for k in 0..3 {
                e.attitude_lag_rad[k] = att_lag[k][l];
                e.rate_lag_rad_s[k] = rate_lag[k][l];
                e.attitude_rad[k] = att[k][l];
                e.rate_rad_s[k] = rate[k][l];
                let pid = &mut c.pids[k];
                (pid.integral, pid.last_error) = (integral[k][l], last[k][l]);
                (pid.reference_rad, pid.reference_rate_rad_s) = (reference[k][l], reference_rate[k][l]);
            }
            e.height_integral_n = height_integral[l];
            e.landing_stalled_s = 0.0;
            e.collective_sum_n = collective_sum[l];
            e.collective_steps += n;
        }
    }

    /// One substep of [`steer`] on every lane; `noise` holds each lane's two draws per axis
    /// (attitude, rate) when the IMU is noisy. Returns the collective and the torque.
    #[inline(always)]
    fn step(
        &mut self,
        af: &Airframe,
        p: &InnerParams,
        rpy: [F4; 3],
        rate_body: V4,
        noise: Option<[[F4; 2]; 3]>,
        dt: Real,
    ) -> (F4, V4) {
        let wrap = lanes::wrap_angle_rad;
        // `Estimate::ahrs`.
        let target = [
            rpy[0] + self.attitude_bias[0] + self.mount_offset[0],
            rpy[1] + self.attitude_bias[1] + self.mount_offset[1],
            rpy[2] + self.yaw_bias,
        ];
        let rate = [rate_body.x, rate_body.y, rate_body.z];
        let alpha = p.ahrs_alpha;
        for k in 0..3 {
            self.attitude_lag[k] = wrap(self.attitude_lag[k] + alpha * wrap(target[k] - self.attitude_lag[k]));
            self.rate_lag[k] = self.rate_lag[k] + alpha * (rate[k] + self.gyro_bias[k] - self.rate_lag[k]);
        }
        match noise {
            Some(draws) => {
                for (k, [att, rate]) in draws.into_iter().enumerate() {
                    self.attitude[k] = wrap(self.attitude_lag[k] + p.att_sigma * att);
                    self.rate[k] = self.rate_lag[k] + p.rate_sigma * rate;
                }
            }
            None => (self.attitude, self.rate) = (self.attitude_lag, self.rate_lag),
        }
        let cos_tilt = lanes::cos(self.attitude[0]) * lanes::cos(self.attitude[1]);
        // `control::collective_thrust_n`, holding a height.
        let spec = &af.spec;
        let hover = 4.0 * af.hover_thrust_per_rotor_n;
        let e = self.height_setpoint - self.height;
        let bound = 0.25 * hover;
        self.height_integral = (self.height_integral + spec.height_ki_n_per_m_s * e * dt).clamp(-bound, bound);
        let t = hover + spec.height_kp_n_per_m * e + self.height_integral - spec.height_kd_n_s_per_m * self.vz;
        let half = F4::splat(0.5);
        let collective = t / F4::select(cos_tilt.gt(half), cos_tilt, half) / self.thrust_gain;
        self.collective_sum = self.collective_sum + collective;
        // `control::attitude_torque`.
        let (omega, zeta) = (spec.attitude_ref_omega_rad_s, spec.attitude_ref_zeta);
        for (k, target) in [(0, self.roll_target), (1, self.pitch_target)] {
            let acc = omega * omega * (target - self.reference[k]) - 2.0 * zeta * omega * self.reference_rate[k];
            self.reference_rate[k] = self.reference_rate[k] + acc * dt;
            self.reference[k] = self.reference[k] + self.reference_rate[k] * dt;
        }
        let errors = [
            self.reference[0] - self.attitude[0],
            self.reference[1] - self.attitude[1],
            wrap(self.yaw_setpoint - self.attitude[2]),
        ];
        let rates = [self.rate[0] - self.reference_rate[0], self.rate[1] - self.reference_rate[1], self.rate[2]];
        let (g, gy) = (&spec.roll_pitch_pid, &spec.yaw_pid);
        let gains = [(g, 0.3 * g.kp), (g, 0.3 * g.kp), (gy, 0.3 * gy.kp)];
        let accel: [F4; 3] = std::array::from_fn(|k| self.pid(k, gains[k].0, errors[k], rates[k], dt, gains[k].1));
        let [ix, iy, iz] = af.inertia_kg_m2;
        let torque = V4::new(accel[0] * ix, accel[1] * iy, accel[2] * iz)
            + V4::new(self.trim[0], self.trim[1], F4::splat(0.0)).div_lanes(self.thrust_gain);
        (collective, torque)
    }

    /// `PidState::update` on axis `k`.
    #[inline(always)]
    fn pid(&mut self, k: usize, g: &PidGains, error: F4, rate: F4, dt: Real, limit: Real) -> F4 {
        // `signum` differs: the signs differ, or either is NaN.
        let sign_flip =
            (error.0 ^ self.last_error[k].0).is_sign_negative() | error.0.is_nan() | self.last_error[k].0.is_nan();
        let integral = F4::select(M4(sign_flip), F4::splat(0.0), self.integral[k]);
        self.last_error[k] = error;
        let mut integral = integral + error * dt;
        if g.ki > 0.0 {
            let max_i = limit / g.ki;
            integral = integral.clamp(-max_i, max_i);
        }
        self.integral[k] = integral;
        g.kp * error + g.ki * integral - g.kd * rate
    }
}

/// [`drive`] on four copters with particle noise off or dithered, as [`SteerLanes`] steers
/// them: `None`, before anything changes, where a lane would meet the one case lanes cannot
/// reproduce exactly (`min` or `max` between zeros of opposite signs: an exact zero among the
/// mixer's terms or the rotor commands), or with Poisson particles or no floor on the ground
/// effect's height. Returns each copter's
/// thrust and torque in the body frame.
#[allow(clippy::too_many_arguments)]
fn drive_lanes(
    af: &Airframe,
    p: &InnerParams,
    cs: &mut [&mut CopterState; LANES],
    at: &Attitude,
    ground: &GroundLanes,
    collective: F4,
    torque: V4,
    dt: Real,
    alpha: Real,
) -> Option<(F4, V4)> {
    // Ground effect's `max` meets a zero only with a zero floor on its height.
    let min_height = p.ground_effect_min_radii * 0.5 * af.spec.rotor_diameter_m;
    if af.spec.particle_noise == ParticleNoise::Poisson || min_height.is_nan() || min_height <= 0.0 {
        return None;
    }
    let wanted = mix_lanes(af, collective, torque)?;
    let ground = ground_effect_lanes(af, p, at, ground);
    Some(rotors_and_battery(af, cs, wanted, ground, dt, alpha))
}

/// The ground effect's factor on each rotor's thrust of four copters, as [`drive`] finds it.
#[inline(always)]
fn ground_effect_lanes(af: &Airframe, p: &InnerParams, at: &Attitude, ground: &GroundLanes) -> [F4; 4] {
    let one = F4::splat(1.0);
    let radius = 0.5 * af.spec.rotor_diameter_m;
    let lowest = at.z - F4::splat(af.reach_bound_m) - ground.highest;
    let near = lowest.lt(F4::splat(GROUND_EFFECT_RADII * radius + 1e-3));
    if !p.ground_effect || !near.any() {
        return [one; 4];
    }
    let cut_off = GROUND_EFFECT_RADII * radius;
    let at_cut_off = ground_effect_ratio(radius, cut_off, p.ground_effect_min_radii);
    let min_z = F4::splat(p.ground_effect_min_radii * radius);
    std::array::from_fn(|r| {
        let height = at.z + at.rot.rotate(V4::splat(af.rotor_pos_in_body_m[r])).z - ground.below[r];
        // `airflow::ground_effect_ratio`.
        let q = radius / (4.0 * height.max(min_z));
        let g = 1.0 + 1.0 / (1.0 - q * q) - at_cut_off;
        F4::select(near.and(height.lt(F4::splat(cut_off))), g, one)
    })
}

/// `control::mix` on four lanes; `None` where a term is an exact zero (see [`drive_lanes`]).
#[inline(always)]
fn mix_lanes(af: &Airframe, collective: F4, torque: V4) -> Option<[F4; 4]> {
    let max = F4::splat(af.max_thrust_per_rotor_n);
    let a2x4 = 4.0 * af.rotor_pos_in_body_m[0].x * af.rotor_pos_in_body_m[0].x;
    let c = af.d_n_m_s2 / af.k_n_s2;
    let mut att: [F4; 4] = std::array::from_fn(|i| {
        let p = af.rotor_pos_in_body_m[i];
        (torque.x * p.y - torque.y * p.x) / a2x4
    });
    let yaw: [F4; 4] = std::array::from_fn(|i| torque.z * ROTOR_YAW_SIGN[i] / (4.0 * c));
    let span = |att: &[F4; 4]| {
        let start = (F4::splat(Real::MAX), F4::splat(Real::MIN));
        att.iter().fold(start, |(lo, hi), &v| (lo.min(v), hi.max(v)))
    };
    let zero_in = |att: &[F4; 4]| att.iter().fold(M4(collective.is_zero().0), |z, a| z.or(a.is_zero()));
    let mut zero = zero_in(&att);
    let (lo, hi) = span(&att);
    let scaled = (hi - lo).gt(max);
    let s = max / (hi - lo);
    att = att.map(|a| F4::select(scaled, a * s, a));
    zero = zero.or(zero_in(&att));
    let (lo, hi) = span(&att);
    let (floor, ceil) = (-lo, (max - hi).max(-lo));
    let base = (collective / 4.0).max(floor).min(ceil);
    let mut yaw_scale = F4::splat(1.0);
    for i in 0..4 {
        let (f, y) = (base + att[i], yaw[i]);
        let over = y.gt(F4::splat(0.0)).and((f + y).gt(max));
        let under = y.lt(F4::splat(0.0)).and((f + y).lt(F4::splat(0.0)));
        let (to_max, to_zero) = ((max - f) / y, f / -y);
        zero = zero.or(over.and(to_max.is_zero())).or(under.and(to_zero.is_zero()));
        yaw_scale = F4::select(over, yaw_scale.min(to_max), F4::select(under, yaw_scale.min(to_zero), yaw_scale));
    }
    let yaw_scale = yaw_scale.max(F4::splat(0.0));
    let out: [F4; 4] =
        std::array::from_fn(|i| (base + att[i] + yaw_scale * yaw[i]).clamp(0.0, af.max_thrust_per_rotor_n));
    zero = out.iter().fold(zero, |z, o| z.or(o.is_zero()));
    (!zero.any()).then_some(out)
}

/// `rotor_model`, the thrust and torque sums and the battery's draw of [`drive`], on four
/// lanes, for rotor commands `wanted` (none of them zero).
#[inline(always)]
fn rotors_and_battery(
    af: &Airframe,
    cs: &mut [&mut CopterState; LANES],
    wanted: [F4; 4],
    ground: [F4; 4],
    dt: Real,
    alpha: Real,
) -> (F4, V4) {
    let spec = &af.spec.battery;
    let scale = per_copter(cs, |c| c.battery.speed_scale(spec));
    let zero = F4::splat(0.0);
    let mut omega = [zero; 4];
    let mut lambda = [zero; 4];
    let mut mean = [zero; 4];
    let mut yaw = zero;
    for r in 0..4 {
        let omega_cmd = (wanted[r].max(zero) / af.k_n_s2).sqrt().min(F4::splat(af.omega_max_rad_s)) * scale;
        let speed = per_copter(cs, |c| c.rotor_speed_rad_s[r]);
        omega[r] = speed + alpha * (omega_cmd - speed);
        let tol = per_copter(cs, |c| c.rotor_tolerance[r]);
        mean[r] = tol * (af.k_n_s2 * omega[r] * omega[r]) * ground[r];
        lambda[r] = af.particle_rate_per_v_final_per_m * af.v_final_per_omega_m * omega[r] * dt;
        yaw = yaw + ROTOR_YAW_SIGN[r] * tol * af.d_n_m_s2 * omega[r] * omega[r];
    }
    // Each copter's draws, rotor by rotor, as `rotor_model` makes them.
    let (omega_l, lambda_l, mean_l) = (omega.map(F4::to_array), lambda.map(F4::to_array), mean.map(F4::to_array));
    let mut thrust_l = [[0.0; LANES]; 4];
    for (l, c) in cs.iter_mut().enumerate() {
        for r in 0..4 {
            let (lambda, mean) = (lambda_l[r][l], mean_l[r][l]);
            thrust_l[r][l] = match af.spec.particle_noise {
                ParticleNoise::Off => mean,
                _ if lambda <= 0.0 => 0.0,
                _ => mean * ((lambda + c.rng.uniform()) as u32 as Real) / lambda,
            };
            c.rotor_speed_rad_s[r] = omega_l[r][l];
            c.rotor_thrust_n[r] = thrust_l[r][l];
        }
    }
    let thrust = thrust_l.map(F4::from_array);
    let (mut total, mut induced) = (zero, zero);
    let mut torque_body = V4::new(zero, zero, yaw);
    for (f, arm) in thrust.into_iter().zip(af.rotor_pos_in_body_m) {
        total = total + f;
        induced = induced + f * f.max(zero).sqrt();
        torque_body = torque_body + V4::splat(arm).cross(V4::new(zero, zero, f));
    }
    battery_draw(spec, cs, induced / af.sqrt_2_rho_a / spec.efficiency, dt);
    (total, torque_body)
}

/// `BatteryState::draw` on four lanes.
#[inline(always)]
fn battery_draw(spec: &crate::battery::BatterySpec, cs: &mut [&mut CopterState; LANES], power_w: F4, dt: Real) {
    let charge = per_copter(cs, |c| c.battery.charge);
    let e = per_copter(cs, |c| spec.open_circuit_v(c.battery.charge));
    let zero = F4::splat(0.0);
    let power = power_w.max(zero);
    let disc = e * e - 4.0 * power * spec.internal_resistance_ohm;
    let v = F4::select(disc.gt(zero), 0.5 * (e + disc.sqrt()), 0.5 * e);
    let i = F4::select(v.gt(zero), power / v, zero);
    let charge = (charge - i * dt / (spec.capacity_mah * 3.6)).max(zero);
    let (v, i, charge) = (v.to_array(), i.to_array(), charge.to_array());
    for (l, c) in cs.iter_mut().enumerate() {
        (c.battery.voltage_v, c.battery.current_a, c.battery.charge) = (v[l], i[l], charge[l]);
    }
}

/// One number of each of a batch's copters, as lanes.
#[inline(always)]
fn per_copter(cs: &[&mut CopterState; LANES], f: impl Fn(&CopterState) -> Real) -> F4 {
    F4::from_array(std::array::from_fn(|l| f(cs[l])))
}

/// Each copter's IMU noise for one substep, drawn as `Estimate::ahrs` draws it: per axis, the
/// attitude's draw, then the rate's.
fn imu_draws(cs: &mut [&mut CopterState; LANES]) -> [[F4; 2]; 3] {
    let mut draws = [[[0.0; LANES]; 2]; 3];
    for (l, c) in cs.iter_mut().enumerate() {
        for axis in &mut draws {
            axis[0][l] = c.rng.triangular();
            axis[1][l] = c.rng.triangular();
        }
    }
    draws.map(|axis| axis.map(F4::from_array))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene;

    /// A batch leaves its four copters and their lanes exactly as running each of them ahead
    /// alone does: through the take-off (near the floor), the climb and the hover, with noise.
    #[test]
    fn a_batch_runs_ahead_as_its_copters_do_alone() {
        let world = scene::compile(&scene::dense_swarm(16, 1.5, true, 0, 3)).expect("scene compiles");
        let (mut state, inputs) = (world.initial_state(), world.initial_inputs());
        let dt = world.physics_dt();
        let (mut compared, mut near_floor, mut held) = (0, 0, 0);
        for _ in 0..80 {
            step(&world, &mut state, &inputs);
            let scratch = &state.scratch;
            let pass = SubstepPass {
                world: &world,
                inner: InnerParams::new(&world, dt),
                alphas: &scratch.motor_alpha,
                cos_tilt: &scratch.crash_cos_tilt,
                roles: Roles(None),
                dt,
            };
            let flying: Vec<usize> =
                (0..16).filter(|&i| state.copters[i].crash.is_none() && !state.copters[i].grounded).collect();
            for ids in flying.chunks_exact(LANES) {
                let ids: [usize; LANES] = ids.try_into().unwrap();
                let lane = |i: usize| Lane { free: true, watch: false, batched: 0, reach_m: 1e3, ..scratch.lanes[i] };
                let (mut cs, mut ls) = (ids.map(|i| state.copters[i].clone()), ids.map(lane));
                let (mut alone_cs, mut alone_ls) = (cs.clone(), ls);
                near_floor += ls.iter().filter(|l| l.pos_m.z <= world.airframes[0].reach_bound_m + 0.05).count();
                held += cs.iter().filter(|c| c.setpoint.height_m > world.airframes[0].rest_height_m + 0.1).count();
                run_ahead_batch(&pass, ids, cs.each_mut(), ls.each_mut());
                for l in 0..LANES {
                    while alone_ls[l].batched < ls[l].batched {
                        let (c, lane) = (&mut alone_cs[l], &mut alone_ls[l]);
                        substep_lane(&world, &pass.inner, pass.alpha(ids[l]), pass.roles, ids[l], c, lane, dt);
                        lane.batched += 1;
                    }
                    assert_eq!(format!("{:?}", cs[l]), format!("{:?}", alone_cs[l]), "copter {}", ids[l]);
                    assert_eq!(format!("{:?}", ls[l]), format!("{:?}", alone_ls[l]), "lane {}", ids[l]);
                    compared += 1;
                }
            }
        }
        assert!(compared > 500 && near_floor > 10 && held > 500, "{compared} {near_floor} {held}");
    }
}
