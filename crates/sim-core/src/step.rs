//! `step(&World, &mut State, &Inputs) -> StepReport`: one control step.
//!
//! A control step (default 50 ms) is, in order:
//! 1. **sense** (every `sonar.period_steps` control steps): sonar cones, cross-talk, IR, IMU,
//!    from the state at the start of the step;
//! 2. **outer loop**: each copter's flight mode turns its command and readings into a
//!    [`Setpoint`];
//! 3. **physics substeps** (default 10 × 5 ms), each: attitude PIDs, height hold, mixer, rotor
//!    model (motor lag, particle noise), forces, one Rapier step, crash detection.
//!
//! Copters are processed in id order; every random draw comes from the copter's own stream.

use serde::Serialize;

use crate::airframe::{Airframe, ParticleNoise, ROTOR_YAW_SIGN};
use crate::control::{self, Command, FlightMode, Inputs, Setpoint};
use crate::geometry::OrientedBox;
use crate::math::{GRAVITY_M_S2, Real, Vec3, euler_from_quat, wrap_angle_rad};
use crate::sensors::{
    self, SensorParams, SonarScene, crosstalk_eligible, crosstalk_reading, sonar_cones, sonar_reading,
};
use crate::state::{CopterState, CrashCause, State};
use crate::world::{ColliderTag, CopterKind, World};
use rapier3d::prelude::PhysicsWorld;

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
}

/// Cell size of the copter grid used by sonars and cross-talk, m.
pub(crate) const GRID_CELL_M: Real = 1.0;

/// Height above the rest height that counts as airborne, m.
const TAKEOFF_MARGIN_M: Real = 0.05;

/// Advances the state by one control step. Never writes `inputs`. Copters without a command
/// in `inputs` keep their initial command.
pub fn step(world: &World, state: &mut State, inputs: &Inputs) -> StepReport {
    let mut report = StepReport::default();
    let n = world.copters.len();
    let command = |i: usize| -> &Command { inputs.commands.get(i).unwrap_or(&world.copters[i].initial_command) };

    let sonar_period = world.sensors.spec.sonar.period_steps.max(1) as u64;
    if world.sensors.spec.enabled {
        sense(world, state, inputs, state.tick.is_multiple_of(sonar_period));
    }

    // Outer loop.
    let dt_control = world.params.control_dt_s as Real;
    for i in 0..n {
        let pose = state.pose(i);
        let cmd = command(i);
        let af = &world.airframes[world.copters[i].airframe];
        let c = &mut state.copters[i];
        c.setpoint = outer_loop(world, af, c, cmd, pose.pos_m, pose.vel_m_s, pose.rpy_rad[2], dt_control, state.tick);
    }

    // Physics substeps.
    let dt = world.physics_dt();
    for _ in 0..world.params.substeps {
        state.scratch.vel_before.clear();
        for i in 0..n {
            let c = &mut state.copters[i];
            let af = &world.airframes[world.copters[i].airframe];
            let body = &mut state.physics.bodies[c.body];
            state.scratch.vel_before.push(body.linvel());
            body.reset_forces(false);
            body.reset_torques(false);
            if c.crash.is_some() {
                continue;
            }
            let pos = body.translation();
            let rot = *body.rotation();
            let linvel = body.linvel();
            let rate_body = rot.inverse() * body.angvel();
            let rpy = euler_from_quat(rot);
            let rpy_est = [rpy[0], rpy[1], wrap_angle_rad(rpy[2] + c.yaw_bias_rad)];
            let cos_tilt = (rot * Vec3::Z).z;
            let collective = control::collective_thrust_n(af, &c.setpoint, pos.z, linvel.z, cos_tilt);
            let torque = control::attitude_torque(af, &mut c.pids, &c.setpoint, rpy_est, rate_body, dt);
            let wanted = control::mix(af, collective, torque);
            let yaw_torque = rotor_model(af, c, wanted, dt);
            for r in 0..4 {
                let f = rot * Vec3::new(0.0, 0.0, c.rotor_thrust_n[r]);
                let p = pos + rot * af.rotor_pos_in_body_m[r];
                body.add_force_at_point(f, p, false);
            }
            body.add_torque(rot * Vec3::new(0.0, 0.0, yaw_torque), false);
        }
        let scratch = &mut state.scratch;
        state.physics.step_with_events(&(), &scratch.collisions);
        if let Ok(mut started) = scratch.collisions.started.lock() {
            std::mem::swap(&mut *started, &mut scratch.started);
        }
        detect_crashes(world, state, &mut report);
        for i in 0..n {
            let c = &mut state.copters[i];
            if c.took_off_tick.is_none() && c.crash.is_none() {
                let z = state.physics.bodies[c.body].translation().z;
                let rest = world.airframes[world.copters[i].airframe].rest_height_m;
                if z > rest + TAKEOFF_MARGIN_M {
                    c.took_off_tick = Some(state.tick);
                    report.events.push(crate::step::Event::TookOff { copter: i });
                }
            }
        }
    }
    state.tick += 1;
    report.tick = state.tick;
    report
}

/// Motor lag, saturation, tolerance and particle noise. Writes the rotor speeds and thrusts;
/// returns the yaw drag torque about body z, N·m.
#[inline]
fn rotor_model(af: &Airframe, c: &mut CopterState, wanted_n: [Real; 4], dt: Real) -> Real {
    let tau = af.spec.motor_time_constant_s;
    let alpha = if tau > 0.0 { 1.0 - (-dt / tau).exp() } else { 1.0 };
    let mut yaw = 0.0;
    for r in 0..4 {
        let omega_cmd = (wanted_n[r].max(0.0) / af.k_n_s2).sqrt().min(af.omega_max_rad_s);
        let omega = c.rotor_speed_rad_s[r] + alpha * (omega_cmd - c.rotor_speed_rad_s[r]);
        c.rotor_speed_rad_s[r] = omega;
        let tol = c.rotor_tolerance[r];
        let mean = tol * af.thrust_at(omega);
        // Particles: rate ṅ = (ρA / 2 m_px) v_final, v_final = c ω; each carries m_px v_final.
        let lambda = af.particle_rate_per_v_final_per_m * af.v_final_per_omega_m * omega * dt;
        let thrust = match af.spec.particle_noise {
            ParticleNoise::Off => mean,
            _ if lambda <= 0.0 => 0.0,
            ParticleNoise::Dither => {
                let count = (lambda + c.rng.uniform()).floor();
                mean * count / lambda
            }
            ParticleNoise::Poisson => mean * c.rng.poisson(lambda) as Real / lambda,
        };
        c.rotor_thrust_n[r] = thrust;
        yaw += ROTOR_YAW_SIGN[r] * tol * af.d_n_m_s2 * omega * omega;
    }
    yaw
}

/// The flight mode's outer loop.
#[allow(clippy::too_many_arguments)]
fn outer_loop(
    world: &World,
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
    };
    match cmd.mode {
        FlightMode::Manual | FlightMode::MixedManual => {}
        FlightMode::Target => {
            if let Some(t) = cmd.target_m {
                let (pitch, roll) = control::target_tilt(t, pos_m, vel_m_s, true_yaw_rad);
                sp.pitch_rad = pitch;
                sp.roll_rad = roll;
                sp.height_m = t[2].max(af.rest_height_m + 0.1);
            }
        }
        FlightMode::WallAvoid => {
            let spec = &world.sensors.spec.wall_avoid;
            let fused = c.sensors.sonar_fused_m;
            // The PD runs on fresh readings only, with the sonar period as its time step;
            // between sonar updates the last output holds.
            let period = world.sensors.spec.sonar.period_steps.max(1);
            let fresh = c.sensors.sonar_tick == tick;
            let avoid = if !world.sensors.spec.enabled || c.sensors.sonar_fused_m == [0.0; 4] {
                None
            } else if fresh {
                control::wall_avoid(spec, &mut c.wall_avoid, fused, dt * period as Real)
            } else {
                (c.wall_avoid.out_rad != [0.0; 2]).then_some((c.wall_avoid.out_rad[0], c.wall_avoid.out_rad[1]))
            };
            match (avoid, cmd.velocity_m_s) {
                (Some((pitch, roll)), _) => {
                    sp.pitch_rad = pitch;
                    sp.roll_rad = roll;
                }
                (None, Some([v_fwd, v_left])) => {
                    // Open loop: the tilt whose steady state against the linear damping is v.
                    let k = af.spec.linear_damping / GRAVITY_M_S2;
                    sp.pitch_rad = (k * v_fwd).atan();
                    sp.roll_rad = -(k * v_left).atan();
                }
                (None, None) => {}
            }
        }
    }
    sp
}

/// Gathers what sonars can see in the current state: the arena walls, the static boxes and
/// every copter's body (crashed ones too), indexed in the copter grid. `sense` uses it; so can
/// tools that need the same geometry (e.g. extra virtual sonars).
pub fn fill_sonar_scene(world: &World, physics: &PhysicsWorld, copters: &[CopterState], scene: &mut SonarScene) {
    let (hx, hy) = (world.arena.size_m[0] / 2.0, world.arena.size_m[1] / 2.0);
    scene.walls.clear();
    if world.arena.walls {
        scene.walls.extend([(Vec3::X, hx), (Vec3::X, -hx), (Vec3::Y, hy), (Vec3::Y, -hy)]);
    }
    scene.boxes.clear();
    scene.boxes.extend(world.boxes.iter().map(|b| OrientedBox {
        center: b.center_m,
        rotation: crate::math::Quat::from_rotation_z(b.yaw_rad),
        half: b.half_extents_m,
    }));
    scene.copters.clear();
    scene.copters.extend((0..copters.len()).map(|i| copter_box(world, physics, copters, i)));
    scene.index_copters(GRID_CELL_M);
}

/// The box a sonar sees of copter `i`: its rotor disc square and body height.
pub fn copter_box(world: &World, physics: &PhysicsWorld, copters: &[CopterState], i: usize) -> OrientedBox {
    let body = &physics.bodies[copters[i].body];
    let af = &world.airframes[world.copters[i].airframe];
    let half_xy = af.spec.arm_length_m / std::f32::consts::SQRT_2 + af.spec.rotor_diameter_m / 2.0;
    OrientedBox {
        center: body.translation(),
        rotation: *body.rotation(),
        half: Vec3::new(half_xy, half_xy, af.spec.body_size_m[2] / 2.0 + 0.01),
    }
}

/// Samples every copter's sensors from the current state.
fn sense(world: &World, state: &mut State, inputs: &Inputs, sonar_due: bool) {
    let params: &SensorParams = &world.sensors;
    let spec = &params.spec;
    let n = world.copters.len();
    let dt_control = world.params.control_dt_s as Real;

    // What the sonars can see, gathered once.
    let scene = &mut state.scratch.sonar_scene;
    fill_sonar_scene(world, &state.physics, &state.copters, scene);

    let noise = spec.noise;
    for i in 0..n {
        let body = &state.physics.bodies[state.copters[i].body];
        let (pos, rot, vel, angvel) = (body.translation(), *body.rotation(), body.linvel(), body.angvel());
        let c = &mut state.copters[i];
        let r = &mut c.sensors;
        if sonar_due {
            let cones = sonar_cones(params, pos, rot);
            r.sonar_tick = state.tick;
            for (s, cone) in cones.iter().enumerate() {
                let truth = scene.cone_distance(cone, i, spec.sonar.max_range_m);
                let nz = if noise { spec.sonar.noise_sigma_m * c.rng.normal() } else { 0.0 };
                r.sonar_truth_m[s] = truth.min(spec.sonar.cap_m);
                r.sonar_m[s] = sonar_reading(&spec.sonar, truth, nz);
                r.sonar_crosstalk[s] = false;
            }
        }
        // IR down the body's −z axis.
        let dir = rot * Vec3::NEG_Z;
        let ir_truth = scene.ir_distance(pos, dir, i);
        r.ir_truth_m = ir_truth;
        let ir_noise = if noise {
            (spec.ir.noise_sigma_m + spec.ir.noise_sigma_rel * ir_truth.min(10.0)) * c.rng.normal()
        } else {
            0.0
        };
        let ir = ir_truth + ir_noise;
        r.ir_m = (ir_truth.is_finite() && (spec.ir.min_range_m..=spec.ir.max_range_m).contains(&ir)).then_some(ir);
        // AHRS and IMU. A twin's are ideal: it flies by its real copter's telemetry, and
        // noise or a drifting yaw of its own would only add to its error.
        let noise = noise && world.copters[i].kind != CopterKind::Real;
        let rpy = euler_from_quat(rot);
        let walk = spec.imu.yaw_bias_walk_deg_per_sqrt_s.to_radians() * dt_control.sqrt();
        if noise {
            c.yaw_bias_rad = wrap_angle_rad(c.yaw_bias_rad + walk * c.rng.normal());
        }
        let att_sigma = spec.imu.attitude_noise_deg.to_radians();
        let yaw_sigma = spec.imu.yaw_noise_deg.to_radians();
        let mut nrm = |sigma: Real| if noise { sigma * c.rng.normal() } else { 0.0 };
        r.attitude_rad = [
            rpy[0] + nrm(att_sigma),
            rpy[1] + nrm(att_sigma),
            wrap_angle_rad(rpy[2] + c.yaw_bias_rad + nrm(yaw_sigma)),
        ];
        r.yaw_bias_rad = c.yaw_bias_rad;
        let rate_sigma = spec.imu.rate_noise_deg_s.to_radians();
        let rate_b = rot.inverse() * angvel;
        r.rate_body_rad_s = [rate_b.x + nrm(rate_sigma), rate_b.y + nrm(rate_sigma), rate_b.z + nrm(rate_sigma)];
        let acc_world = if state.tick == 0 { Vec3::ZERO } else { (vel - c.prev_vel_m_s) / dt_control };
        let specific = rot.inverse() * (acc_world + Vec3::new(0.0, 0.0, GRAVITY_M_S2));
        let a_sigma = spec.imu.accel_noise_m_s2;
        r.accel_body_m_s2 = [specific.x + nrm(a_sigma), specific.y + nrm(a_sigma), specific.z + nrm(a_sigma)];
        c.prev_vel_m_s = vel;
    }

    // Cross-talk: copter A's pings heard by copter B's sonars, for B in id order, with B's
    // random stream.
    if sonar_due && spec.crosstalk.enabled && n > 1 {
        let near = &mut state.scratch.near;
        for b in 0..n {
            let body_b = &state.physics.bodies[state.copters[b].body];
            let cones_b = sonar_cones(params, body_b.translation(), *body_b.rotation());
            near.clear();
            let reach = spec.sonar.max_range_m + 1.0;
            scene.grid.visit_near(body_b.translation(), reach, |a| {
                if a != b {
                    near.push(a);
                }
                reach
            });
            near.sort_unstable();
            for &a in near.iter() {
                let body_a = &state.physics.bodies[state.copters[a].body];
                let pa = body_a.translation();
                if (pa - body_b.translation()).length() > spec.sonar.max_range_m + 1.0 {
                    continue;
                }
                let cones_a = sonar_cones(params, pa, *body_a.rotation());
                for cone_a in &cones_a {
                    for (k, cone_b) in cones_b.iter().enumerate() {
                        if let Some(d) = crosstalk_eligible(cone_a, cone_b, spec.sonar.max_range_m) {
                            let c = &mut state.copters[b];
                            if c.rng.uniform() < spec.crosstalk.probability {
                                let v = crosstalk_reading(&spec.sonar, spec.crosstalk.phase, d, &mut c.rng);
                                let q = sensors::quantise(
                                    v.clamp(spec.sonar.min_range_m, spec.sonar.cap_m),
                                    spec.sonar.quantum_m,
                                );
                                if q < c.sensors.sonar_m[k] {
                                    c.sensors.sonar_m[k] = q;
                                    c.sensors.sonar_crosstalk[k] = true;
                                }
                            }
                        }
                    }
                }
            }
        }
    }

    for i in 0..n {
        let virt = inputs.commands.get(i).and_then(|c| c.virtual_sonar_m);
        let r = &mut state.copters[i].sensors;
        r.sonar_fused_m = sensors::fuse_min(r.sonar_m, virt);
    }
}

/// Turns collision starts into crashes, and checks tilt.
fn detect_crashes(world: &World, state: &mut State, report: &mut StepReport) {
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
            let v = state.scratch.vel_before.get(i).copied().unwrap_or(Vec3::ZERO);
            let limit = af.spec.crash_impact_speed_m_s;
            let cause = match other {
                ColliderTag::Wall => Some(CrashCause::Wall),
                ColliderTag::Ceiling => Some(CrashCause::Ceiling),
                ColliderTag::Box(index) => Some(CrashCause::Box { index }),
                ColliderTag::Floor => (v.length() > limit).then_some(CrashCause::Floor { speed_m_s: v.length() }),
                ColliderTag::Copter(j) if j != i => {
                    let vj = state.scratch.vel_before.get(j).copied().unwrap_or(Vec3::ZERO);
                    let rel = (v - vj).length();
                    (rel > limit).then_some(CrashCause::Copter { other: j, speed_m_s: rel })
                }
                ColliderTag::Copter(_) => None,
            };
            if let Some(cause) = cause {
                crash(state, i, cause, report);
            }
        }
    }
    state.scratch.started = started;
    state.scratch.started.clear();
    for i in 0..world.copters.len() {
        if state.copters[i].crash.is_some() {
            continue;
        }
        let af = &world.airframes[world.copters[i].airframe];
        let rot = *state.physics.bodies[state.copters[i].body].rotation();
        let tilt = (rot * Vec3::Z).z.clamp(-1.0, 1.0).acos().to_degrees();
        if tilt > af.spec.crash_tilt_deg {
            crash(state, i, CrashCause::Tilt { tilt_deg: tilt }, report);
        }
    }
}

fn crash(state: &mut State, i: usize, cause: CrashCause, report: &mut StepReport) {
    let c = &mut state.copters[i];
    c.crash = Some(cause);
    c.rotor_speed_rad_s = [0.0; 4];
    c.rotor_thrust_n = [0.0; 4];
    report.events.push(Event::Crashed { copter: i, cause });
}
