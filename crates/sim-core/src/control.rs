//! Commands, flight modes and the FINken's controllers: mode logic (outer loop, every control
//! step), attitude PIDs, height hold and the X-frame mixer (inner loop, every physics step).

use serde::{Deserialize, Serialize};

use crate::airframe::{Airframe, PidGains, ROTOR_YAW_SIGN};
use crate::math::{Real, Vec3, wrap_angle_rad};

/// The FINken firmware's flight modes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FlightMode {
    /// Direct pitch, roll, yaw and throttle (height hold only if a height is set).
    Manual,
    /// Height and yaw held by the copter; pitch and roll from commands.
    #[default]
    MixedManual,
    /// Fully autonomous: repelled from whatever its sonars see closer than the safety distance.
    WallAvoid,
    /// Position PIDs towards a target point, from ground truth (a development aid).
    Target,
    /// The velocity command flown open loop (the tilt whose steady state against the linear
    /// damping is that velocity), height and yaw held: Wall-Avoid's velocity without its
    /// avoidance. For external swarm algorithms.
    Velocity,
    /// Four normalised rotor commands, straight to the motors: no attitude or height loop.
    Rotors,
}

impl FlightMode {
    /// The scene and wire name.
    pub fn as_str(self) -> &'static str {
        match self {
            FlightMode::Manual => "manual",
            FlightMode::MixedManual => "mixed_manual",
            FlightMode::WallAvoid => "wall_avoid",
            FlightMode::Target => "target",
            FlightMode::Velocity => "velocity",
            FlightMode::Rotors => "rotors",
        }
    }
}

/// The commands of one copter. The step reads them and never writes them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Command {
    /// Flight mode.
    pub mode: FlightMode,
    /// Roll target, rad (> 0: right side down).
    pub roll_rad: Real,
    /// Pitch target, rad (> 0: nose down, flies forward).
    pub pitch_rad: Real,
    /// Yaw target, rad, counter-clockwise from +x, as the copter's AHRS sees it.
    pub yaw_rad: Real,
    /// Throttle in [0, 1] (0.5 = hover), used when no height is held.
    pub throttle: Real,
    /// Height to hold, m; `<= 0` disables height hold.
    pub height_m: Real,
    /// Target point for [`FlightMode::Target`], m.
    pub target_m: Option<[Real; 3]>,
    /// Velocity to follow when safe in [`FlightMode::WallAvoid`], body frame (forward, left), m/s.
    pub velocity_m_s: Option<[Real; 2]>,
    /// Externally supplied virtual sonar readings (front, right, back, left), m. Fused as
    /// `min(physical, virtual)`: the original rule for real copters seeing virtual objects.
    pub virtual_sonar_m: Option<[Real; 4]>,
    /// Rotor commands for [`FlightMode::Rotors`], each in [0, 1] of the rotor's maximum thrust
    /// (front-left, front-right, back-right, back-left).
    #[serde(default)]
    pub rotors: Option<[Real; 4]>,
}

impl Default for Command {
    fn default() -> Self {
        Self {
            mode: FlightMode::MixedManual,
            roll_rad: 0.0,
            pitch_rad: 0.0,
            yaw_rad: 0.0,
            throttle: 0.0,
            height_m: 0.0,
            target_m: None,
            velocity_m_s: None,
            virtual_sonar_m: None,
            rotors: None,
        }
    }
}

/// Commands for every copter, indexed by copter id.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Inputs {
    /// One command per copter, in id order.
    pub commands: Vec<Command>,
}

/// What the outer loop asks of the inner loop for one control step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Setpoint {
    /// Roll, rad.
    pub roll_rad: Real,
    /// Pitch, rad.
    pub pitch_rad: Real,
    /// Yaw, rad, in the copter's own (biased) heading estimate.
    pub yaw_rad: Real,
    /// Height to hold, m; `<= 0`: use `throttle`.
    pub height_m: Real,
    /// Throttle in [0, 1] when no height is held.
    pub throttle: Real,
    /// [`FlightMode::Rotors`]: the rotor commands, fractions of the maximum thrust; the
    /// attitude and height loops are bypassed.
    #[serde(default)]
    pub rotors: Option<[Real; 4]>,
}

/// Integrator and memory of one PID axis, and its reference model.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PidState {
    /// Integral of the error, rad·s.
    pub integral: Real,
    /// Last error, rad.
    pub last_error: Real,
    /// The reference model's angle, rad: the setpoint shaped into a reachable trajectory.
    pub reference_rad: Real,
    /// The reference model's rate, rad/s.
    pub reference_rate_rad_s: Real,
}

impl PidState {
    /// One PID update; returns the commanded angular acceleration, rad/s².
    ///
    /// The derivative acts on the measured rate (no kick on setpoint changes). Anti-windup as
    /// in the report: the integral is reset when the error changes sign (the target was
    /// reached), and bounded so that it alone cannot ask for more than `limit`.
    #[inline]
    pub fn update(&mut self, g: &PidGains, error: Real, rate: Real, dt: Real, limit: Real) -> Real {
        if error.signum() != self.last_error.signum() {
            self.integral = 0.0;
        }
        self.last_error = error;
        self.integral += error * dt;
        if g.ki > 0.0 {
            let max_i = limit / g.ki;
            self.integral = self.integral.clamp(-max_i, max_i);
        }
        g.kp * error + g.ki * self.integral - g.kd * rate
    }

    /// Advances the reference model towards `target`: a second-order filter of natural
    /// frequency `omega` and damping `zeta` (Paparazzi's attitude reference, `REF_OMEGA_P`,
    /// `REF_ZETA_P`). With `omega <= 0` the reference is the target itself.
    #[inline]
    pub fn track(&mut self, target: Real, omega: Real, zeta: Real, dt: Real) {
        if omega <= 0.0 {
            self.reference_rad = target;
            self.reference_rate_rad_s = 0.0;
            return;
        }
        let acc = omega * omega * (target - self.reference_rad) - 2.0 * zeta * omega * self.reference_rate_rad_s;
        self.reference_rate_rad_s += acc * dt;
        self.reference_rad += self.reference_rate_rad_s * dt;
    }
}

/// X-frame mixer with saturation handling. Given the wanted collective thrust (N) and body
/// torques (N·m), returns per-rotor thrusts within `[0, max]`.
///
/// Priorities when rotors saturate: roll and pitch first (scaled down only if they alone do
/// not fit), then the collective is shifted to make room, and yaw gets what is left.
#[inline]
pub fn mix(af: &Airframe, collective_n: Real, torque_n_m: Vec3) -> [Real; 4] {
    let max = af.max_thrust_per_rotor_n;
    let a2x4 = 4.0 * af.rotor_pos_in_body_m[0].x * af.rotor_pos_in_body_m[0].x;
    let c = af.d_n_m_s2 / af.k_n_s2;
    let mut att = [0.0; 4];
    let mut yaw = [0.0; 4];
    for (i, p) in af.rotor_pos_in_body_m.iter().enumerate() {
        // τx = Σ y_i F_i, τy = −Σ x_i F_i, τz = Σ s_i c F_i.
        att[i] = (torque_n_m.x * p.y - torque_n_m.y * p.x) / a2x4;
        yaw[i] = torque_n_m.z * ROTOR_YAW_SIGN[i] / (4.0 * c);
    }
    let (lo, hi) = att.iter().fold((Real::MAX, Real::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
    if hi - lo > max {
        let s = max / (hi - lo);
        att.iter_mut().for_each(|v| *v *= s);
    }
    let (lo, hi) = att.iter().fold((Real::MAX, Real::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
    // After scaling, `max - hi >= -lo` up to rounding; never hand `clamp` an empty range.
    let (floor, ceil) = (-lo, (max - hi).max(-lo));
    let base = (collective_n / 4.0).max(floor).min(ceil);
    let mut yaw_scale: Real = 1.0;
    for i in 0..4 {
        let f = base + att[i];
        let y = yaw[i];
        if y > 0.0 && f + y > max {
            yaw_scale = yaw_scale.min((max - f) / y);
        } else if y < 0.0 && f + y < 0.0 {
            yaw_scale = yaw_scale.min(f / -y);
        }
    }
    let yaw_scale = yaw_scale.max(0.0);
    let mut out = [0.0; 4];
    for i in 0..4 {
        out[i] = (base + att[i] + yaw_scale * yaw[i]).clamp(0.0, max);
    }
    out
}

/// A height setpoint at most this far above the resting height means "land", m.
pub const LANDING_BAND_M: Real = 0.02;
/// The descent rate a landing copter holds, m/s (half the crash speed on the floor).
pub const LANDING_DESCENT_M_S: Real = 0.3;

/// A landing whose vertical speed stays below this, m/s, …
pub const LANDED_VZ_M_S: Real = 0.1;

/// … for this long, s, is on the ground: its motors stop.
pub const LANDED_AFTER_S: Real = 0.5;

/// Whether `sp` holds a height in flight (not the landing band at the floor, not rotor
/// commands): where the height loop runs.
#[inline]
pub fn holds_height(af: &Airframe, sp: &Setpoint) -> bool {
    sp.rotors.is_none() && sp.height_m > 0.0 && sp.height_m > af.rest_height_m + LANDING_BAND_M
}

/// Collective thrust for a setpoint: height hold (`hover + P e + I ∫e − D v_z`, eq. 3.5 with
/// an integral as on the real FINken's `GUIDANCE_V`, divided by the cosine of the tilt) when
/// a height is set, a 0.3 m/s descent when that height is the floor, else the throttle curve. `z_m` and `vz_m_s` are the copter's estimates;
/// `integral_n` is the loop's integral term, bounded to a quarter of the hover thrust and
/// reset while no height is held.
#[inline]
#[allow(clippy::too_many_arguments)]
pub fn collective_thrust_n(
    af: &Airframe,
    sp: &Setpoint,
    z_m: Real,
    vz_m_s: Real,
    cos_tilt: Real,
    integral_n: &mut Real,
    stalled_s: &mut Real,
    dt: Real,
) -> Real {
    if sp.height_m > 0.0 && sp.height_m <= af.rest_height_m + LANDING_BAND_M {
        // A height at the floor: land, holding a gentle descent rate rather than a height the
        // IR cannot measure there (and that ground effect would float above). A descent that
        // has stalled for a while is on the ground: the motors stop (Paparazzi's ground
        // detection, then its throttle kill).
        *stalled_s = if vz_m_s.abs() < LANDED_VZ_M_S { *stalled_s + dt } else { 0.0 };
        if *stalled_s >= LANDED_AFTER_S {
            return 0.0;
        }
        let hover = 4.0 * af.hover_thrust_per_rotor_n;
        *integral_n = 0.0;
        let t = hover + af.spec.height_kd_n_s_per_m * (-LANDING_DESCENT_M_S - vz_m_s);
        // While stalled the thrust ramps down to nothing over the detection time, as a
        // descent-rate loop's integral winds down against the floor: the copter's weight
        // comes onto its feet, and friction stops a drift. (At hover thrust it would sit on
        // its rotors' lift and skid along the floor.)
        let ramp = 1.0 - *stalled_s / LANDED_AFTER_S;
        t * ramp / cos_tilt.max(0.5)
    } else if sp.height_m > 0.0 {
        *stalled_s = 0.0;
        let hover = 4.0 * af.hover_thrust_per_rotor_n;
        let e = sp.height_m - z_m;
        let bound = 0.25 * hover;
        *integral_n = (*integral_n + af.spec.height_ki_n_per_m_s * e * dt).clamp(-bound, bound);
        let t = hover + af.spec.height_kp_n_per_m * e + *integral_n - af.spec.height_kd_n_s_per_m * vz_m_s;
        t / cos_tilt.max(0.5)
    } else {
        *integral_n = 0.0;
        *stalled_s = 0.0;
        af.throttle_to_thrust_n(sp.throttle)
    }
}

/// Attitude controller: body torques from the setpoint and the attitude estimate. Roll and
/// pitch follow the reference model's trajectory (angle and rate), as Paparazzi's
/// `stabilization_attitude_quat_int` does; yaw follows its setpoint.
#[inline]
pub fn attitude_torque(
    af: &Airframe,
    pids: &mut [PidState; 3],
    sp: &Setpoint,
    rpy_rad: [Real; 3],
    rate_body_rad_s: Vec3,
    dt: Real,
) -> Vec3 {
    let max_tilt = af.spec.max_tilt_deg.to_radians();
    let roll_target = sp.roll_rad.clamp(-max_tilt, max_tilt);
    let pitch_target = sp.pitch_rad.clamp(-max_tilt, max_tilt);
    let (omega, zeta) = (af.spec.attitude_ref_omega_rad_s, af.spec.attitude_ref_zeta);
    pids[0].track(roll_target, omega, zeta, dt);
    pids[1].track(pitch_target, omega, zeta, dt);
    let e_roll = pids[0].reference_rad - rpy_rad[0];
    let e_pitch = pids[1].reference_rad - rpy_rad[1];
    let e_yaw = wrap_angle_rad(sp.yaw_rad - rpy_rad[2]);
    let g = &af.spec.roll_pitch_pid;
    let limit_rp = 0.3 * g.kp;
    let rate_x = rate_body_rad_s.x - pids[0].reference_rate_rad_s;
    let rate_y = rate_body_rad_s.y - pids[1].reference_rate_rad_s;
    let ax = pids[0].update(g, e_roll, rate_x, dt, limit_rp);
    let ay = pids[1].update(g, e_pitch, rate_y, dt, limit_rp);
    let gy = &af.spec.yaw_pid;
    let az = pids[2].update(gy, e_yaw, rate_body_rad_s.z, dt, 0.3 * gy.kp);
    let [ix, iy, iz] = af.inertia_kg_m2;
    Vec3::new(ix * ax, iy * ay, iz * az)
}

/// Which Wall-Avoid controller a copter flies.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WallAvoidController {
    /// The FINken firmware's (`finken_wall_avoid` with `finken_sonar_filter`): per axis, the
    /// difference of opposite sonars clamped at the goal distance, through a lead-lag at 5 Hz.
    #[default]
    Firmware,
    /// A PD on each sonar's intrusion into the safety distance, every sonar update (the
    /// simulator's own controller before the firmware was ported).
    Pd,
}

/// Parameters of the Wall-Avoid behaviour.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WallAvoidSpec {
    /// Which controller.
    pub controller: WallAvoidController,
    /// Objects closer than this repel the copter, m (the firmware's `SONAR_DIFF_GOAL_DIST`).
    pub safety_distance_m: Real,
    /// Firmware: readings are clamped to `[filter_min_m, filter_max_m]` before averaging, m.
    pub filter_min_m: Real,
    /// Firmware: the upper clamp, m.
    pub filter_max_m: Real,
    /// Firmware: each sonar's moving average spans this many of its readings.
    pub filter_len: u32,
    /// Firmware: the lead-lag's gain Kp, deg per m.
    pub gain_deg_per_m: Real,
    /// Firmware: the lead time Tv, s.
    pub hold_time_s: Real,
    /// Firmware: the lag time T1, s.
    pub delay_time_s: Real,
    /// Firmware: the controller's rate, Hz (Tustin-discretised at this rate).
    pub update_hz: Real,
    /// Firmware: the lead-lag's output is capped at ± this, deg.
    pub max_control_deg: Real,
    /// Firmware: a pilot (velocity) input towards an obstacle is scaled down linearly to zero
    /// between the safety distance and this distance, m.
    pub guard_distance_m: Real,
    /// PD: tilt per metre of intrusion into the safety distance, deg/m.
    pub kp_deg_per_m: Real,
    /// PD: tilt per m/s of approach speed (from the filtered sonar rate), deg/(m/s).
    pub kd_deg_s_per_m: Real,
    /// PD: largest tilt it commands, deg.
    pub max_tilt_deg: Real,
    /// PD: time constant of the low-pass on sonar rates, s.
    pub rate_filter_s: Real,
}

/// Defaults. The firmware's are the FINken fork's (`docs/model.md` §7 cites file and commit).
/// The PD's were tuned on the lab scene (4 m × 3 m, σ = 5 cm sonar noise, linear damping 0.3,
/// open-loop tilt, all four sonars every 50 ms):
/// - `kp` 5°/m and `kd` 5°/(m/s) give the wall-approach dynamics `ẍ = g (kp e + kd ė) − 0.3 ẋ`
///   a natural frequency `√(g kp) ≈ 0.93 rad/s` and damping ratio `(g kd + 0.3) / 2ω ≈ 0.62`;
/// - the rate filter (0.15 s) keeps the derivative noise from σ = 5 cm readings at 20 Hz near
///   0.27 m/s (1.3° of tilt) while still braking within a few readings;
/// - `max_tilt` 10° (1.7 m/s² of braking) bounds what the PD can command.
impl Default for WallAvoidSpec {
    fn default() -> Self {
        Self {
            controller: WallAvoidController::Firmware,
            safety_distance_m: 1.2,
            filter_min_m: 0.2,
            filter_max_m: 3.0,
            filter_len: 3,
            gain_deg_per_m: 3.65,
            hold_time_s: 2.29,
            delay_time_s: 0.213,
            update_hz: 5.0,
            max_control_deg: 8.0,
            guard_distance_m: 0.7,
            kp_deg_per_m: 5.0,
            kd_deg_s_per_m: 5.0,
            max_tilt_deg: 10.0,
            rate_filter_s: 0.15,
        }
    }
}

/// Longest moving average the firmware's sonar filter keeps.
pub const SONAR_FILTER_MAX_LEN: usize = 8;

/// Memory of Wall-Avoid: the firmware's sonar filter and lead-lag, or the PD's last readings
/// and filtered rates.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WallAvoidState {
    /// PD: last fused sonar readings (front, right, back, left), m; 0 before the first.
    pub last_m: [Real; 4],
    /// PD: low-passed rate of each reading, m/s.
    pub rate_m_s: [Real; 4],
    /// The controller's outputs of the last update (pitch, roll), rad: the FINKEN_WALL_AVOID
    /// fields.
    pub out_rad: [Real; 2],
    /// Firmware: each sonar's last clamped readings (a ring), m.
    #[serde(default)]
    pub history_m: [[Real; SONAR_FILTER_MAX_LEN]; 4],
    /// Firmware: how many readings each ring holds.
    #[serde(default)]
    pub history_len: [u8; 4],
    /// Firmware: where each ring writes next.
    #[serde(default)]
    pub history_at: [u8; 4],
    /// Firmware: the filtered distances (front, right, back, left), m: `distance_d_*`.
    #[serde(default)]
    pub filtered_m: [Real; 4],
    /// Firmware: `distance_diff_x`, `distance_diff_y`, m.
    #[serde(default)]
    pub diff_m: [Real; 2],
    /// Firmware: the lead-lag's last input (x, y), m.
    #[serde(default)]
    pub error_k1_m: [Real; 2],
    /// Firmware: the lead-lag's last output (x, y), deg.
    #[serde(default)]
    pub out_k1_deg: [Real; 2],
}

impl WallAvoidState {
    /// The firmware's sonar filter (`finken_sonar_filter`): a new reading of sonar `k`,
    /// clamped to `[filter_min_m, filter_max_m]`, enters that sonar's moving average; the
    /// per-axis differences follow: `x = min(back, G) − min(front, G)`,
    /// `y = min(right, G) − min(left, G)` with G the goal (safety) distance.
    pub fn filter(&mut self, spec: &WallAvoidSpec, k: usize, reading_m: Real) {
        let len = (spec.filter_len as usize).clamp(1, SONAR_FILTER_MAX_LEN);
        let at = self.history_at[k] as usize % len;
        self.history_m[k][at] = reading_m.clamp(spec.filter_min_m, spec.filter_max_m);
        self.history_at[k] = ((at + 1) % len) as u8;
        self.history_len[k] = (self.history_len[k] as usize + 1).min(len) as u8;
        let n = self.history_len[k] as usize;
        self.filtered_m[k] = self.history_m[k][..n].iter().sum::<Real>() / n as Real;
        let g = spec.safety_distance_m;
        let [front, right, back, left] = self.filtered_m.map(|d| d.min(g));
        self.diff_m = [back - front, right - left];
    }

    /// Whether every sonar has been read at least once.
    pub fn filter_ready(&self) -> bool {
        self.history_len.iter().all(|&n| n > 0)
    }
}

/// The firmware's Wall-Avoid (`finken_wall_avoid`), one update at `spec.update_hz`: per axis
/// the lead-lag `Kp (1 + Tv s) / (1 + T1 s)`, Tustin-discretised, on the filtered difference
/// of opposite sonars, capped at `max_control_deg`. Returns (pitch, roll), rad, in this
/// crate's convention (pitch > 0 flies forward, roll > 0 flies right): a wall ahead makes
/// `x > 0`, the firmware's pitch up, here a negative pitch.
pub fn wall_avoid_firmware(spec: &WallAvoidSpec, st: &mut WallAvoidState) -> (Real, Real) {
    let t = 1.0 / spec.update_hz;
    let (t1, tv, kp) = (spec.delay_time_s, spec.hold_time_s, spec.gain_deg_per_m);
    let a0 = (t - 2.0 * t1) / (t + 2.0 * t1);
    let b0 = kp * (t - 2.0 * tv) / (t + 2.0 * t1);
    let b1 = kp * (t + 2.0 * tv) / (t + 2.0 * t1);
    let max = spec.max_control_deg;
    for axis in 0..2 {
        let e = st.diff_m[axis];
        let u = (-a0 * st.out_k1_deg[axis] + b1 * e + b0 * st.error_k1_m[axis]).clamp(-max, max);
        st.out_k1_deg[axis] = u;
        st.error_k1_m[axis] = e;
    }
    st.out_rad = [-st.out_k1_deg[0].to_radians(), st.out_k1_deg[1].to_radians()];
    (st.out_rad[0], st.out_rad[1])
}

/// The firmware's scaling of a pilot input towards an obstacle: 1 beyond the safety distance,
/// down to 0 at the guard distance, for the filtered distance `d` on that side.
pub fn pilot_scale(spec: &WallAvoidSpec, d: Real) -> Real {
    let span = (spec.safety_distance_m - spec.guard_distance_m).max(1e-3);
    ((d - spec.guard_distance_m) / span).clamp(0.0, 1.0)
}

/// Wall-Avoid's PD: pitch from front/back, roll from left/right, a PD on how far each sonar
/// reading intrudes into the safety distance. Uses only the copter's fused (noisy) sonar
/// readings, never ground truth. Returns (pitch, roll) in rad, or `None` when all is safe.
pub fn wall_avoid(spec: &WallAvoidSpec, st: &mut WallAvoidState, sonar_m: [Real; 4], dt: Real) -> Option<(Real, Real)> {
    let alpha = dt / (spec.rate_filter_s + dt);
    let first = st.last_m == [0.0; 4];
    for ((rate_m_s, &now), &last) in st.rate_m_s.iter_mut().zip(&sonar_m).zip(&st.last_m) {
        let rate = if first { 0.0 } else { (now - last) / dt };
        *rate_m_s += alpha * (rate - *rate_m_s);
    }
    st.last_m = sonar_m;
    let intrusion = sonar_m.map(|d| (spec.safety_distance_m - d).max(0.0));
    if intrusion.iter().all(|&e| e == 0.0) {
        st.out_rad = [0.0, 0.0];
        return None;
    }
    let kp = spec.kp_deg_per_m.to_radians();
    let kd = spec.kd_deg_s_per_m.to_radians();
    // Approach speed counts only for sonars inside the safety distance.
    let approach = |i: usize| if intrusion[i] > 0.0 { -st.rate_m_s[i] } else { 0.0 };
    let [front, right, back, left] = [0, 1, 2, 3];
    // Obstacle ahead → pitch < 0 (back off); obstacle left → roll > 0 (move right).
    let pitch = -kp * (intrusion[front] - intrusion[back]) - kd * (approach(front) - approach(back));
    let roll = kp * (intrusion[left] - intrusion[right]) + kd * (approach(left) - approach(right));
    let max = spec.max_tilt_deg.to_radians();
    st.out_rad = [pitch.clamp(-max, max), roll.clamp(-max, max)];
    Some((st.out_rad[0], st.out_rad[1]))
}

/// Target mode gains: horizontal position PD to tilt, from ground truth.
const TARGET_KP_RAD_PER_M: Real = 0.25;
const TARGET_KD_RAD_S_PER_M: Real = 0.35;
const TARGET_MAX_TILT_RAD: Real = 0.2;

/// Target mode: tilt towards a target point (world frame), rotated into the body's heading.
pub fn target_tilt(target_m: [Real; 3], pos_m: Vec3, vel_m_s: Vec3, yaw_rad: Real) -> (Real, Real) {
    let ex = target_m[0] - pos_m.x;
    let ey = target_m[1] - pos_m.y;
    let ax = TARGET_KP_RAD_PER_M * ex - TARGET_KD_RAD_S_PER_M * vel_m_s.x;
    let ay = TARGET_KP_RAD_PER_M * ey - TARGET_KD_RAD_S_PER_M * vel_m_s.y;
    let (s, c) = yaw_rad.sin_cos();
    let fwd = c * ax + s * ay;
    let left = -s * ax + c * ay;
    // Pitch > 0 flies forward; roll > 0 flies right (towards −left).
    (fwd.clamp(-TARGET_MAX_TILT_RAD, TARGET_MAX_TILT_RAD), (-left).clamp(-TARGET_MAX_TILT_RAD, TARGET_MAX_TILT_RAD))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::airframe::AirframeSpec;

    fn af() -> Airframe {
        Airframe::derive(&AirframeSpec::default()).unwrap()
    }

    fn torques(af: &Airframe, f: [Real; 4]) -> Vec3 {
        let c = af.d_n_m_s2 / af.k_n_s2;
        let mut t = Vec3::ZERO;
        for i in 0..4 {
            let p = af.rotor_pos_in_body_m[i];
            t += Vec3::new(p.y * f[i], -p.x * f[i], ROTOR_YAW_SIGN[i] * c * f[i]);
        }
        t
    }

    #[test]
    fn mixer_reproduces_torques_when_unsaturated() {
        let af = af();
        let want = Vec3::new(0.01, -0.02, 0.003);
        let f = mix(&af, 4.0 * af.hover_thrust_per_rotor_n, want);
        let got = torques(&af, f);
        assert!((got - want).length() < 1e-5, "{got:?} vs {want:?}");
        assert!((f.iter().sum::<Real>() - 4.0 * af.hover_thrust_per_rotor_n).abs() < 1e-4);
    }

    #[test]
    fn mixer_keeps_attitude_over_collective_and_yaw_when_saturated() {
        let af = af();
        let want = Vec3::new(0.05, 0.0, 0.05);
        let f = mix(&af, 8.0 * af.max_thrust_per_rotor_n, want);
        assert!(f.iter().all(|&v| (0.0..=af.max_thrust_per_rotor_n).contains(&v)));
        let got = torques(&af, f);
        assert!((got.x - want.x).abs() < 1e-5, "roll torque kept: {got:?}");
    }

    #[test]
    fn pid_integral_resets_when_error_changes_sign() {
        let g = PidGains { kp: 1.0, ki: 1.0, kd: 0.0 };
        let mut s = PidState::default();
        for _ in 0..10 {
            s.update(&g, 0.1, 0.0, 0.1, 10.0);
        }
        assert!(s.integral > 0.09);
        s.update(&g, -0.1, 0.0, 0.1, 10.0);
        assert!((s.integral + 0.01).abs() < 1e-6, "integral restarts from the new error: {}", s.integral);
    }

    #[test]
    fn wall_avoid_backs_off_from_a_wall_ahead_and_moves_right_from_a_wall_left() {
        let spec = WallAvoidSpec::default();
        let mut st = WallAvoidState::default();
        let (pitch, roll) = wall_avoid(&spec, &mut st, [0.5, 3.0, 3.0, 3.0], 0.05).unwrap();
        assert!(pitch < 0.0 && roll == 0.0);
        let mut st = WallAvoidState::default();
        let (pitch, roll) = wall_avoid(&spec, &mut st, [3.0, 3.0, 3.0, 0.5], 0.05).unwrap();
        assert!(pitch == 0.0 && roll > 0.0);
        assert!(wall_avoid(&spec, &mut WallAvoidState::default(), [3.0; 4], 0.05).is_none());
    }

    #[test]
    fn the_firmware_filter_clamps_averages_and_differences_opposite_sonars() {
        let spec = WallAvoidSpec::default();
        let mut st = WallAvoidState::default();
        for (k, d) in [(0, 0.5), (1, 7.65), (2, 0.1), (3, 2.0)] {
            st.filter(&spec, k, d);
        }
        assert!(st.filter_ready());
        assert_eq!(st.filtered_m, [0.5, 3.0, 0.2, 2.0], "clamped to 0.2–3.0");
        assert!((st.diff_m[0] - (0.2 - 0.5)).abs() < 1e-6 && (st.diff_m[1] - 0.0).abs() < 1e-6, "{:?}", st.diff_m);
        for d in [0.8, 1.1, 1.4] {
            st.filter(&spec, 0, d);
        }
        assert!((st.filtered_m[0] - (0.8 + 1.1 + 1.4) / 3.0).abs() < 1e-6, "the last three: {}", st.filtered_m[0]);
    }

    #[test]
    fn the_firmware_lead_lag_matches_its_continuous_form_and_backs_off_from_walls() {
        let spec = WallAvoidSpec::default();
        // A step of the error: the Tustin lead-lag starts at Kp (T + 2 Tv) / (T + 2 T1) and
        // settles at the DC gain Kp.
        let mut st = WallAvoidState { diff_m: [0.1, -0.1], ..WallAvoidState::default() };
        let (pitch, roll) = wall_avoid_firmware(&spec, &mut st);
        let first = 3.65 * (0.2 + 2.0 * 2.29) / (0.2 + 2.0 * 0.213) * 0.1;
        assert!((st.out_k1_deg[0] - first).abs() < 1e-4, "{} vs {first}", st.out_k1_deg[0]);
        assert!(pitch < 0.0, "a wall ahead (x > 0) backs off: {pitch}");
        assert!(roll < 0.0, "a wall right (y < 0) moves left: {roll}");
        for _ in 0..200 {
            wall_avoid_firmware(&spec, &mut st);
        }
        assert!((st.out_k1_deg[0] - 0.365).abs() < 1e-4, "DC gain Kp: {}", st.out_k1_deg[0]);
        st.diff_m = [2.0, 0.0];
        wall_avoid_firmware(&spec, &mut st);
        assert_eq!(st.out_k1_deg[0], 8.0, "capped at 8°");
        assert_eq!(pilot_scale(&spec, 1.5), 1.0);
        assert_eq!(pilot_scale(&spec, 0.5), 0.0);
        assert!((pilot_scale(&spec, 0.95) - 0.5).abs() < 1e-5);
    }
}
