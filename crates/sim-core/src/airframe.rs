//! Airframe parameters (the scene's `airframe` tables) and the rotor model derived from them.
//!
//! The rotor model follows the project report (`report.txt`, sections 2.1 and 3.1):
//! - each rotor makes `F_i = k ω_i²` and a drag torque `τ_i = d ω_i²` (the `I_M ω̇` term is
//!   omitted, eq. 2.1);
//! - momentum theory at hover gives `F_hover = m g / 4`, `v_rotor = sqrt(F_hover / (2 ρ A))`
//!   and `v_final = 2 v_rotor` (eq. 2.12–2.14);
//! - the V-REP particle parametrisation gives the particle mass from the mass flow,
//!   `ṁ = F_hover / v_final`, `m_px = ṁ / ṅ_hover`, `ρ_px = m_px / ((π/6) s_px³)`, and the
//!   particle rate `ṅ = ρ A v_final / (2 m_px)` (eq. 2.15–2.18, 3.2–3.4).
//!
//! In flight the final air speed is tied to the rotor speed, `v_final = c ω` with
//! `c = v_final,hover / ω_hover`, so the mean thrust `ṅ m_px v_final = ρ A v_final² / 2 = k ω²`.
//! The particle count per physics step is random with mean `ṅ · dt` (see [`ParticleNoise`]).

use serde::{Deserialize, Serialize};

use crate::battery::BatterySpec;
use crate::finken_height::FinkenHeightSpec;
use crate::math::{GRAVITY_M_S2, Real, Vec3};

/// How the number of particles a rotor emits in one physics step is drawn.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ParticleNoise {
    /// `floor(λ + U)`, `U ~ U[0, 1)`: the V-REP rotor script's emission (`floor` of the rate
    /// times dt plus a carried fraction) with the fraction's phase drawn at random. Unbiased, and
    /// the least spread an integer count with mean `λ` can have. The default.
    Dither,
    /// Poisson(`λ`): independent particle arrivals. Much noisier at small `λ`.
    Poisson,
    /// No particle noise: the thrust is exactly `k ω²`.
    Off,
}

/// Gains of one attitude axis. The PID output is an angular acceleration (rad/s²), multiplied by
/// the axis inertia to give a torque.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PidGains {
    /// Proportional gain, (rad/s²) per rad of error.
    pub kp: Real,
    /// Integral gain, (rad/s²) per (rad·s).
    pub ki: Real,
    /// Derivative gain on the measured body rate, (rad/s²) per (rad/s).
    pub kd: Real,
}

/// Airframe parameters of one copter, FINken III by default. Every field may be overridden in a
/// scene; the unit is part of each name.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AirframeSpec {
    /// Body mass without motors, kg (FINken III in simulation: 0.296, report table 3.1).
    pub body_mass_kg: Real,
    /// Mass of one motor-and-rotor assembly at an arm end, kg.
    pub motor_mass_kg: Real,
    /// Distance from the centre of mass to each motor axis, m (200 mm motor diagonal).
    pub arm_length_m: Real,
    /// Size of the central body box (x, y, z), m. Used for inertia and collisions.
    pub body_size_m: [Real; 3],
    /// Rotor disc diameter, m (5" props: 0.1274).
    pub rotor_diameter_m: Real,
    /// Air density, kg/m³.
    pub air_density_kg_m3: Real,
    /// Rapier linear damping of the body (V-REP's 0.3).
    pub linear_damping: Real,
    /// Rapier angular damping of the body.
    pub angular_damping: Real,
    /// Thrust coefficient `k` of `F = k ω²`, N·s².
    pub thrust_coeff_n_s2: Real,
    /// Drag-torque coefficient `d` of `τ = d ω²`, N·m·s².
    pub drag_coeff_n_m_s2: Real,
    /// Rotor thrust saturates at this multiple of the hover thrust.
    pub max_thrust_ratio: Real,
    /// First-order time constant of the motor speed, s.
    pub motor_time_constant_s: Real,
    /// Particle diameter `s_px`, m.
    pub particle_size_m: Real,
    /// Particle rate at hover `ṅ_px`, 1/s.
    pub particle_rate_hover_hz: Real,
    /// How particle counts are drawn.
    pub particle_noise: ParticleNoise,
    /// Standard deviation of each rotor's seeded manufacturing tolerance, relative (0.02 = 2 %).
    pub rotor_tolerance_sigma: Real,
    /// Standard deviation of each copter's IMU mounting error (roll and pitch), deg.
    pub imu_mount_sigma_deg: Real,
    /// Whether the lab's procedure has trimmed the copter: the IMU calibration (the copter set
    /// level, the accelerometer's reading taken as level) cancels the mounting error, and the
    /// roll and pitch trims cancel the torque of the rotors' tolerances at hover. What is left
    /// is the AHRS's wandering bias (`[sensors.estimator]`).
    pub trimmed: bool,
    /// Roll and pitch attitude PID.
    pub roll_pitch_pid: PidGains,
    /// Yaw attitude PID.
    pub yaw_pid: PidGains,
    /// Natural frequency of the roll and pitch reference model, rad/s (0: none).
    pub attitude_ref_omega_rad_s: Real,
    /// Damping ratio of the roll and pitch reference model.
    pub attitude_ref_zeta: Real,
    /// Largest roll or pitch the attitude controller will command, deg.
    pub max_tilt_deg: Real,
    /// Height hold proportional gain, N per m of height error (eq. 3.5's `P`).
    pub height_kp_n_per_m: Real,
    /// Height hold damping, N per m/s of vertical speed (eq. 3.5's `D`).
    pub height_kd_n_s_per_m: Real,
    /// Height hold integral gain, N per (m·s) of height error.
    pub height_ki_n_per_m_s: Real,
    /// The lab firmware's own height loop (`[airframes.NAME.finken_height]`), in place of the
    /// newton PID above while a height is held; absent by default.
    pub finken_height: Option<FinkenHeightSpec>,
    /// Throttle curve parameter `a` (flatness at hover, 0 = linear, 1 = flat).
    pub throttle_curve_a: Real,
    /// Throttle curve parameter `b` (width of the flat zone around hover).
    pub throttle_curve_b: Real,
    /// Hitting the floor downward faster than this, or another copter at a relative speed
    /// above it, crashes, m/s.
    pub crash_impact_speed_m_s: Real,
    /// A tilt beyond this crashes, deg.
    pub crash_tilt_deg: Real,
    /// The flight battery.
    pub battery: BatterySpec,
}

impl Default for AirframeSpec {
    fn default() -> Self {
        Self {
            body_mass_kg: 0.296,
            motor_mass_kg: 0.025,
            arm_length_m: 0.1,
            body_size_m: [0.10, 0.10, 0.04],
            rotor_diameter_m: 0.1274,
            air_density_kg_m3: 1.2041,
            linear_damping: 0.3,
            angular_damping: 0.0,
            // A 5x3" prop (C_T ≈ 0.1): hover near 10,500 rpm for a 0.4 kg copter.
            thrust_coeff_n_s2: 7.9e-7,
            // Drag torque about 1.6 % of thrust times a metre, typical of small props.
            drag_coeff_n_m_s2: 1.3e-8,
            max_thrust_ratio: 2.0,
            motor_time_constant_s: 0.015,
            particle_size_m: 0.005,
            particle_rate_hover_hz: 430.0,
            particle_noise: ParticleNoise::Dither,
            rotor_tolerance_sigma: 0.02,
            imu_mount_sigma_deg: 0.5,
            trimmed: true,
            // The real FINken's Paparazzi gains (PHI_PGAIN 650, PHI_DGAIN 300, IGAIN 0) in SI
            // units; see docs/model.md for the conversion and why the report's are not used.
            roll_pitch_pid: PidGains { kp: 280.0, ki: 0.0, kd: 65.0 },
            yaw_pid: PidGains { kp: 40.0, ki: 4.0, kd: 12.0 },
            // REF_OMEGA_P 800 deg/s, REF_ZETA_P 0.85.
            attitude_ref_omega_rad_s: 14.0,
            attitude_ref_zeta: 0.85,
            max_tilt_deg: 30.0,
            // Report eq. 3.5 (P = D = 2 m/s of air speed per m and per m/s) in newtons; the
            // integral is GUIDANCE_V_HOVER_KI's (see docs/model.md).
            height_kp_n_per_m: 1.4,
            height_kd_n_s_per_m: 1.4,
            height_ki_n_per_m_s: 0.065,
            finken_height: None,
            throttle_curve_a: 1.0,
            throttle_curve_b: 1.0,
            crash_impact_speed_m_s: 0.6,
            crash_tilt_deg: 60.0,
            battery: BatterySpec::default(),
        }
    }
}

/// Names of the built-in airframe presets.
pub const PRESETS: &[&str] = &["finken3", "finken3_2015_12"];

/// A built-in preset by name: `finken3`, the FINken III with Twinswarm's height loop (in
/// newtons, tilt-compensated, adapting to the battery); `finken3_2015_12`, the same copter on
/// the lab firmware's own height loop of 16 Dec 2015 ([`FinkenHeightSpec`]).
pub fn preset(name: &str) -> Option<AirframeSpec> {
    match name {
        "finken3" => Some(AirframeSpec::default()),
        "finken3_2015_12" => {
            Some(AirframeSpec { finken_height: Some(FinkenHeightSpec::default()), ..Default::default() })
        }
        _ => None,
    }
}

/// Rotor positions in the body frame (FLU), X-frame: front-left, front-right, back-right,
/// back-left, at 45° to the body axes.
pub const ROTOR_NAMES: [&str; 4] = ["front_left", "front_right", "back_right", "back_left"];

/// Yaw reaction of each rotor on the body: `+1` for rotors spinning clockwise seen from above
/// (their drag pushes the body counter-clockwise, `+z`), `-1` for counter-clockwise ones.
/// Diagonal rotors spin the same way.
pub const ROTOR_YAW_SIGN: [Real; 4] = [1.0, -1.0, 1.0, -1.0];

/// Half the thickness of a rotor disc collider, m.
pub(crate) const ROTOR_DISC_HALF_THICKNESS_M: Real = 0.005;

/// The model derived from an [`AirframeSpec`]: everything the step needs, computed once.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Airframe {
    /// The parameters this was derived from.
    pub spec: AirframeSpec,
    /// Total mass, kg.
    pub mass_kg: Real,
    /// Principal moments of inertia about body x, y, z, kg·m². From the body box and four
    /// point masses at the arm ends.
    pub inertia_kg_m2: [Real; 3],
    /// Hover thrust of one rotor `m g / 4`, N.
    pub hover_thrust_per_rotor_n: Real,
    /// Rotor disc area `A = π D² / 4`, m².
    pub disc_area_m2: Real,
    /// Air speed in the rotor plane at hover, m/s.
    pub v_rotor_m_s: Real,
    /// Final air speed behind the rotor at hover, m/s.
    pub v_final_m_s: Real,
    /// Mass flow through one rotor at hover, kg/s.
    pub mass_flow_kg_s: Real,
    /// Particle mass `m_px`, kg.
    pub particle_mass_kg: Real,
    /// Particle density `ρ_px`, kg/m³.
    pub particle_density_kg_m3: Real,
    /// `ṅ / v_final = ρ A / (2 m_px)`, particles per metre of final air speed.
    pub particle_rate_per_v_final_per_m: Real,
    /// Thrust coefficient `k`, N·s².
    pub k_n_s2: Real,
    /// Drag-torque coefficient `d`, N·m·s².
    pub d_n_m_s2: Real,
    /// Rotor speed at hover `sqrt(F_hover / k)`, rad/s.
    pub omega_hover_rad_s: Real,
    /// `v_final / ω`, m per rad.
    pub v_final_per_omega_m: Real,
    /// Saturation thrust of one rotor, N.
    pub max_thrust_per_rotor_n: Real,
    /// Rotor speed at saturation, rad/s.
    pub omega_max_rad_s: Real,
    /// Rotor centres in the body frame, m.
    pub rotor_pos_in_body_m: [Vec3; 4],
    /// Height of the centre of mass above the floor when resting on it, m.
    pub rest_height_m: Real,
    /// Largest horizontal extent from the centre (for overlap checks), m.
    pub radius_m: Real,
    /// At least the farthest any collider (body box, rotor discs) reaches from the centre of
    /// mass, in any direction and at any attitude, m.
    #[serde(skip)]
    pub reach_bound_m: Real,
    /// `√(2 ρ A)`: induced power is `T^{3/2}` over it, per rotor.
    #[serde(skip)]
    pub sqrt_2_rho_a: Real,
}

/// Why an airframe is not physical.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("airframe field `{field}`: {message}")]
pub struct AirframeError {
    /// The offending field.
    pub field: &'static str,
    /// What is wrong with it.
    pub message: String,
}

impl Airframe {
    /// Derives the model, rejecting non-finite or non-physical parameters.
    pub fn derive(spec: &AirframeSpec) -> Result<Self, AirframeError> {
        spec.validate()?;
        let s = spec;
        let mass_kg = s.body_mass_kg + 4.0 * s.motor_mass_kg;
        let [bx, by, bz] = s.body_size_m;
        // Box about its centre, plus point masses at (±a, ±a, 0) with a = l / √2.
        let a2 = s.arm_length_m * s.arm_length_m / 2.0;
        let ixx = s.body_mass_kg / 12.0 * (by * by + bz * bz) + 4.0 * s.motor_mass_kg * a2;
        let iyy = s.body_mass_kg / 12.0 * (bx * bx + bz * bz) + 4.0 * s.motor_mass_kg * a2;
        let izz = s.body_mass_kg / 12.0 * (bx * bx + by * by) + 4.0 * s.motor_mass_kg * s.arm_length_m * s.arm_length_m;

        let hover = mass_kg * GRAVITY_M_S2 / 4.0;
        let disc_area = std::f32::consts::PI / 4.0 * s.rotor_diameter_m * s.rotor_diameter_m;
        let v_rotor = (hover / (2.0 * s.air_density_kg_m3 * disc_area)).sqrt();
        let v_final = 2.0 * v_rotor;
        let mass_flow = hover / v_final;
        let particle_mass = mass_flow / s.particle_rate_hover_hz;
        let particle_volume = std::f32::consts::PI / 6.0 * s.particle_size_m.powi(3);
        let particle_density = particle_mass / particle_volume;
        let rate_per_v = s.air_density_kg_m3 * disc_area / (2.0 * particle_mass);
        let omega_hover = (hover / s.thrust_coeff_n_s2).sqrt();
        let max_thrust = s.max_thrust_ratio * hover;
        let a = s.arm_length_m / std::f32::consts::SQRT_2;
        let rotor_z = bz / 2.0;
        Ok(Self {
            spec: s.clone(),
            mass_kg,
            inertia_kg_m2: [ixx, iyy, izz],
            hover_thrust_per_rotor_n: hover,
            disc_area_m2: disc_area,
            v_rotor_m_s: v_rotor,
            v_final_m_s: v_final,
            mass_flow_kg_s: mass_flow,
            particle_mass_kg: particle_mass,
            particle_density_kg_m3: particle_density,
            particle_rate_per_v_final_per_m: rate_per_v,
            k_n_s2: s.thrust_coeff_n_s2,
            d_n_m_s2: s.drag_coeff_n_m_s2,
            omega_hover_rad_s: omega_hover,
            v_final_per_omega_m: v_final / omega_hover,
            max_thrust_per_rotor_n: max_thrust,
            omega_max_rad_s: (max_thrust / s.thrust_coeff_n_s2).sqrt(),
            rotor_pos_in_body_m: [
                Vec3::new(a, a, rotor_z),
                Vec3::new(a, -a, rotor_z),
                Vec3::new(-a, -a, rotor_z),
                Vec3::new(-a, a, rotor_z),
            ],
            rest_height_m: bz / 2.0,
            radius_m: (s.arm_length_m + s.rotor_diameter_m / 2.0).max(bx.hypot(by) / 2.0),
            sqrt_2_rho_a: (2.0 * s.air_density_kg_m3 * disc_area).sqrt(),
            reach_bound_m: {
                let disc = (0.5 * s.rotor_diameter_m).hypot(ROTOR_DISC_HALF_THICKNESS_M);
                (0.5 * bx.hypot(by).hypot(bz)).max(disc + (2.0 * a * a + rotor_z * rotor_z).sqrt()) * 1.001 + 1e-4
            },
        })
    }

    /// Mean thrust of one rotor at speed `omega`, N (before its tolerance factor).
    #[inline]
    pub fn thrust_at(&self, omega_rad_s: Real) -> Real {
        self.k_n_s2 * omega_rad_s * omega_rad_s
    }

    /// Collective thrust for a throttle in [0, 1] through the logistic throttle curve, N.
    ///
    /// With `u = t − ½` and `h(u) = u − (a / (4b)) tanh(4b u)` (tanh is the centred logistic),
    /// the curve is `f(t) = ½ + h(u) / (2 h(½))`: `f(0) = 0`, `f(½) = ½` (hover), `f(1) = 1`
    /// (all rotors saturated). Its slope at hover is `(1 − a) / (2 h(½))`, so `a = 1` makes it
    /// flat there, which dampens the effect of throttle changes close to hover as in the report
    /// (section 3.1.3, eq. 3.6: a = b = 1 by default); `b` sets the width of the flat zone.
    pub fn throttle_to_thrust_n(&self, throttle: Real) -> Real {
        let a = self.spec.throttle_curve_a;
        let kb = 4.0 * self.spec.throttle_curve_b;
        let h = |u: Real| u - a / kb * (kb * u).tanh();
        let u = throttle.clamp(0.0, 1.0) - 0.5;
        let f = 0.5 + h(u) / (2.0 * h(0.5));
        4.0 * self.max_thrust_per_rotor_n * f
    }
}

impl AirframeSpec {
    fn validate(&self) -> Result<(), AirframeError> {
        let positive: [(&'static str, Real); 13] = [
            ("body_mass_kg", self.body_mass_kg),
            ("arm_length_m", self.arm_length_m),
            ("body_size_m", self.body_size_m[0].min(self.body_size_m[1]).min(self.body_size_m[2])),
            ("rotor_diameter_m", self.rotor_diameter_m),
            ("air_density_kg_m3", self.air_density_kg_m3),
            ("thrust_coeff_n_s2", self.thrust_coeff_n_s2),
            ("drag_coeff_n_m_s2", self.drag_coeff_n_m_s2),
            ("particle_size_m", self.particle_size_m),
            ("particle_rate_hover_hz", self.particle_rate_hover_hz),
            ("max_tilt_deg", self.max_tilt_deg),
            ("crash_tilt_deg", self.crash_tilt_deg),
            ("throttle_curve_b", self.throttle_curve_b),
            ("crash_impact_speed_m_s", self.crash_impact_speed_m_s),
        ];
        let non_negative: [(&'static str, Real); 15] = [
            ("imu_mount_sigma_deg", self.imu_mount_sigma_deg),
            ("attitude_ref_omega_rad_s", self.attitude_ref_omega_rad_s),
            ("attitude_ref_zeta", self.attitude_ref_zeta),
            ("height_ki_n_per_m_s", self.height_ki_n_per_m_s),
            ("motor_mass_kg", self.motor_mass_kg),
            ("linear_damping", self.linear_damping),
            ("angular_damping", self.angular_damping),
            ("motor_time_constant_s", self.motor_time_constant_s),
            ("rotor_tolerance_sigma", self.rotor_tolerance_sigma),
            ("height_kp_n_per_m", self.height_kp_n_per_m),
            ("height_kd_n_s_per_m", self.height_kd_n_s_per_m),
            ("roll_pitch_pid", self.roll_pitch_pid.kp.min(self.roll_pitch_pid.ki).min(self.roll_pitch_pid.kd)),
            ("yaw_pid", self.yaw_pid.kp.min(self.yaw_pid.ki).min(self.yaw_pid.kd)),
            ("throttle_curve_a", self.throttle_curve_a),
            ("max_thrust_ratio", self.max_thrust_ratio - 1.0),
        ];
        let all_finite = |v: Real| v.is_finite();
        for (field, v) in positive {
            if !all_finite(v) {
                return Err(AirframeError { field, message: format!("must be finite, got {v}") });
            }
            if v <= 0.0 {
                return Err(AirframeError { field, message: format!("must be positive, got {v}") });
            }
        }
        for (field, v) in non_negative {
            if !all_finite(v) {
                return Err(AirframeError { field, message: format!("must be finite, got {v}") });
            }
            if v < 0.0 {
                let message = if field == "max_thrust_ratio" {
                    format!("must be at least 1 (hover), got {}", v + 1.0)
                } else {
                    format!("must not be negative, got {v}")
                };
                return Err(AirframeError { field, message });
            }
        }
        if let Err((field, message)) = self.battery.validate() {
            return Err(AirframeError { field, message });
        }
        if let Some(Err((field, message))) = self.finken_height.as_ref().map(FinkenHeightSpec::validate) {
            return Err(AirframeError { field, message });
        }
        if self.throttle_curve_a > 1.0 {
            return Err(AirframeError {
                field: "throttle_curve_a",
                message: format!("must be at most 1, or the curve is not monotonic; got {}", self.throttle_curve_a),
            });
        }
        if self.max_tilt_deg >= 90.0 || self.crash_tilt_deg > 180.0 {
            return Err(AirframeError {
                field: "max_tilt_deg",
                message: "tilt limits must be below 90° (command) and 180° (crash)".into(),
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn throttle_curve_hits_its_anchors_and_is_flat_at_hover() {
        let af = Airframe::derive(&AirframeSpec::default()).unwrap();
        let hover_total = 4.0 * af.hover_thrust_per_rotor_n;
        assert!(af.throttle_to_thrust_n(0.0).abs() < 1e-5);
        assert!((af.throttle_to_thrust_n(0.5) - hover_total).abs() < 1e-4);
        assert!((af.throttle_to_thrust_n(1.0) - 4.0 * af.max_thrust_per_rotor_n).abs() < 1e-4);
        let slope_hover = (af.throttle_to_thrust_n(0.51) - af.throttle_to_thrust_n(0.49)) / 0.02;
        let slope_linear = 4.0 * af.max_thrust_per_rotor_n;
        assert!(slope_hover < 0.05 * slope_linear, "slope at hover {slope_hover}");
        let mut last = -1.0;
        for i in 0..=100 {
            let t = af.throttle_to_thrust_n(i as Real / 100.0);
            assert!(t >= last, "throttle curve must be monotonic");
            last = t;
        }
    }

    #[test]
    fn non_physical_airframes_are_rejected() {
        let spec = AirframeSpec { body_mass_kg: -1.0, ..Default::default() };
        assert_eq!(Airframe::derive(&spec).unwrap_err().field, "body_mass_kg");
        let spec = AirframeSpec { rotor_diameter_m: Real::NAN, ..Default::default() };
        assert_eq!(Airframe::derive(&spec).unwrap_err().field, "rotor_diameter_m");
        let spec = AirframeSpec { max_thrust_ratio: 0.9, ..Default::default() };
        assert_eq!(Airframe::derive(&spec).unwrap_err().field, "max_thrust_ratio");
    }
}
