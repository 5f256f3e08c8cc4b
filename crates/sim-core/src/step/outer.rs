//! The outer loop: each copter's flight mode turns its command and readings into a setpoint
//! (Wall-Avoid as the firmware flies it, or the PD variant).

use super::*;

/// The flight mode's outer loop.
#[allow(clippy::too_many_arguments)]
pub(super) fn outer_loop(
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
pub(super) fn wall_avoid_firmware(
    world: &World,
    c: &mut CopterState,
    pilot: (Real, Real),
    dt: Real,
    tick: u64,
) -> (Real, Real) {
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
pub(super) fn wall_avoid_pd(
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
pub(super) fn velocity_tilt(af: &Airframe, [v_fwd, v_left]: [Real; 2]) -> (Real, Real) {
    let k = af.spec.linear_damping / GRAVITY_M_S2;
    ((k * v_fwd).atan(), -(k * v_left).atan())
}
