//! Air between copters and surfaces: the downwash wake below a copter and ground effect.
//!
//! **Downwash.** The wake of a copter is a round turbulent jet along its body −z axis whose
//! momentum flux is the copter's thrust `T` (the air it pushes down carries exactly that
//! momentum). With a Gaussian profile `w(x, r) = U₀(x) exp(−r² / b(x)²)` the momentum flux is
//! `ρ π b² U₀² / 2`, so `U₀ = √(2T / (ρ π b²))`. At the rotors the wake leaves at momentum
//! theory's far-wake speed `v_final = √(2 T_rotor / (ρ A))` (2× the induced velocity, the
//! particle model's `v_final`), which fixes the initial width `b₀ = √(4A / π)` (= the rotor
//! diameter); downstream it spreads linearly, `b = b₀ + k x`, with `k` from the round jet's
//! spreading rate (`S = dr½/dx ≈ 0.094`, `k = S / √ln 2`). The centreline speed then decays as
//! `v_final b₀ / b`. A copter in the wake loses thrust on each rotor that the wake blows
//! through: a rotor in an axial inflow `w` meets its air at a smaller angle of attack, and
//! blade-element theory linearised about hover gives a loss `k_w w` (`k_w ≈ 0.08 N per m/s` for
//! the FINken's 5×3" props), applied along the wake at the rotor: force and torque.
//! Turbulence makes each rotor's `w` fluctuate with the jet's centreline intensity.
//!
//! **Ground effect.** A rotor at height `z` above a surface below it makes more thrust at the
//! same speed: Cheeseman & Bennett's image-vortex result `T / T∞ = 1 / (1 − (R / 4z)²)`,
//! bounded below `z = z_min R` where the formula stops being valid.
//!
//! Sources and constants: `docs/model.md`.

use serde::{Deserialize, Serialize};

use crate::math::Real;
use crate::scene::{FieldPath, PathSeg, SceneError};

/// `[airflow]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AirflowSpec {
    /// Whether copters' wakes push on copters below them.
    pub downwash: bool,
    /// Whether rotors near the floor or a box top make more thrust.
    pub ground_effect: bool,
    /// Round-jet spreading rate of the wake's half-width, `dr½ / dx`.
    pub wake_spread: Real,
    /// Centreline turbulence intensity of the wake, `w' / w`.
    pub wake_turbulence: Real,
    /// Thrust a rotor loses per m/s of wake blowing through it, N·s/m.
    pub wake_thrust_loss_n_s_per_m: Real,
    /// Ground effect is held constant below this height, in rotor radii.
    pub ground_effect_min_height_radii: Real,
}

impl Default for AirflowSpec {
    fn default() -> Self {
        Self {
            downwash: true,
            ground_effect: true,
            wake_spread: 0.094,
            wake_turbulence: 0.25,
            wake_thrust_loss_n_s_per_m: 0.08,
            ground_effect_min_height_radii: 0.5,
        }
    }
}

/// Compiled airflow parameters.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AirflowParams {
    /// The spec compiled from.
    pub spec: AirflowSpec,
    /// Growth of the Gaussian width `b` per metre downstream, `S / √ln 2`.
    pub width_per_m: Real,
}

impl AirflowSpec {
    pub(crate) fn compile(&self, path: &FieldPath) -> Result<AirflowParams, SceneError> {
        for (field, v, lo) in [
            ("wake_spread", self.wake_spread, 1e-3),
            ("wake_thrust_loss_n_s_per_m", self.wake_thrust_loss_n_s_per_m, 0.0),
            ("wake_turbulence", self.wake_turbulence, 0.0),
            ("ground_effect_min_height_radii", self.ground_effect_min_height_radii, 0.26),
        ] {
            if !v.is_finite() || v < lo {
                let mut p = path.clone();
                p.0.push(PathSeg::Key(field.into()));
                return Err(SceneError::Invalid {
                    origin: String::new(),
                    location: None,
                    path: p,
                    message: format!("must be finite and at least {lo}, got {v}"),
                });
            }
        }
        Ok(AirflowParams { spec: self.clone(), width_per_m: self.wake_spread / std::f32::consts::LN_2.sqrt() })
    }
}

/// Cheeseman & Bennett's ground-effect thrust ratio for a rotor of radius `radius_m` at
/// `height_m` above a surface, bounded at `min_radii` rotor radii.
#[inline]
pub fn ground_effect_ratio(radius_m: Real, height_m: Real, min_radii: Real) -> Real {
    let z = height_m.max(min_radii * radius_m);
    let q = radius_m / (4.0 * z);
    1.0 / (1.0 - q * q)
}

/// The wake of one copter, for the control step: where it starts, where it goes and how
/// strong it is.
#[derive(Clone, Copy, Debug, Default)]
pub struct Wake {
    /// Centre of the rotor plane, m.
    pub origin: crate::math::Vec3,
    /// Unit direction of the flow (the body's −z axis).
    pub dir: crate::math::Vec3,
    /// Speed leaving the rotors, `v_final`, m/s.
    pub v0_m_s: Real,
    /// Initial Gaussian width `b₀`, m.
    pub b0_m: Real,
    /// How far the wake goes (to the floor), m.
    pub length_m: Real,
}

impl Wake {
    /// The mean air speed of the wake at a point, m/s (0 outside it).
    #[inline]
    pub fn speed_at(&self, p: crate::math::Vec3, width_per_m: Real) -> Real {
        let d = p - self.origin;
        let x = d.dot(self.dir);
        if x <= 0.0 || x > self.length_m {
            return 0.0;
        }
        let b = self.b0_m + width_per_m * x;
        let r2 = (d - self.dir * x).length_squared();
        if r2 > 9.0 * b * b {
            return 0.0;
        }
        self.v0_m_s * self.b0_m / b * (-r2 / (b * b)).exp()
    }

    /// The largest horizontal distance from the origin at which the wake can be felt, m.
    pub fn reach_m(&self, width_per_m: Real) -> Real {
        3.0 * (self.b0_m + width_per_m * self.length_m) + self.length_m * self.dir.truncate().length()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::Vec3;

    #[test]
    fn ground_effect_grows_near_the_ground_and_vanishes_far_from_it() {
        let r = 0.0637;
        assert!((ground_effect_ratio(r, 10.0, 0.5) - 1.0).abs() < 1e-5);
        assert!((ground_effect_ratio(r, r, 0.5) - 1.0 / (1.0 - 1.0 / 16.0)).abs() < 1e-5);
        assert!((ground_effect_ratio(r, 0.0, 0.5) - 4.0 / 3.0).abs() < 1e-5);
    }

    #[test]
    fn the_wake_keeps_its_momentum_flux_as_it_spreads() {
        let k = 0.094 / std::f32::consts::LN_2.sqrt();
        let w = Wake { origin: Vec3::ZERO, dir: Vec3::NEG_Z, v0_m_s: 11.0, b0_m: 0.127, length_m: 3.0 };
        for x in [0.1, 0.5, 1.0, 2.0] {
            // ∫ w² 2πr dr over the Gaussian: π b² U₀² / 2 = π b₀² v₀² / 2.
            let b = 0.127 + k * x;
            let u0 = w.speed_at(Vec3::new(0.0, 0.0, -x), k);
            let flux = std::f32::consts::PI * b * b * u0 * u0 / 2.0;
            let flux0 = std::f32::consts::PI * 0.127 * 0.127 * 121.0 / 2.0;
            assert!((flux / flux0 - 1.0).abs() < 1e-3, "x = {x}: {flux} vs {flux0}");
        }
        assert_eq!(w.speed_at(Vec3::new(0.0, 0.0, 0.1), k), 0.0, "nothing above the rotors");
        assert_eq!(w.speed_at(Vec3::new(0.5, 0.0, -0.01), k), 0.0, "nothing beside them");
    }
}
