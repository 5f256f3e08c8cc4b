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
//! `v_final b₀ / b`. Closer than [`AirflowSpec::wake_merge_sizes`] motor diagonals below the
//! rotors (2.5, Bauersfeld et al.'s "jet-like after 2.5 drone diameters") the wake is still
//! four rotor jets, each a Gaussian from its hub carrying its rotor's thrust (initial width the
//! rotor radius); they blend into the round jet by adding squared speeds (Reichardt's
//! superposition of momentum), with a smoothstep weight in depth, so the momentum flux is the
//! thrust at every depth.
//!
//! A copter in the wake loses thrust on each rotor the wake blows through: a rotor in an axial
//! inflow `w` meets its air at a smaller angle of attack. Uniform-inflow blade-element momentum
//! theory with a linear lift curve and helical twist gives, at rotor speed ω, radius R,
//! `λ_c = w / (ωR)`, `C_T = K (θ − λ_c − λ_i)` with momentum's `λ_i`, in closed form
//! ([`inflow_thrust_factor`]). `K` (the effective `σa/4`) is the blade's one parameter; `θ`
//! follows from the still-air thrust. Linearised about hover it loses 0.042 N per m/s for the
//! FINken's 5×3" props; at 5 m/s it keeps 74 % of its thrust. The loss acts along the rotor's
//! axis, at the rotor: force and torque. Turbulence makes each rotor's `w` fluctuate with the
//! jet's centreline intensity.
//!
//! **Ground effect.** A rotor at height `z` above the surface below **it** (the floor, or a box
//! top under that rotor: a copter half over a table's edge has two rotors in ground effect)
//! makes more thrust at the same speed: Cheeseman & Bennett's image-vortex result
//! `T / T∞ = 1 / (1 − (R / 4z)²)`, bounded below `z = z_min R` where the formula stops being
//! valid.
//!
//! Sources and constants: `docs/model.md`.

use serde::{Deserialize, Serialize};

use crate::error::{FieldPath, PathSeg, SceneError};
use crate::math::Real;

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
    /// The blade-element model's `K` (effective solidity × lift slope / 4) of the rotors that
    /// feel a wake: how much thrust a rotor loses in an axial inflow.
    pub rotor_inflow_k: Real,
    /// Below the rotors, the wake is four rotor jets for this many motor diagonals, then one.
    pub wake_merge_sizes: Real,
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
            // Fitted to a tip-loss blade-element model of a 5x3" prop (chord 9.2 mm at 0.75 R,
            // lift slope 5.5/rad) over 0-8 m/s: docs/model.md.
            rotor_inflow_k: 0.1026,
            wake_merge_sizes: 2.5,
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
            ("rotor_inflow_k", self.rotor_inflow_k, 1e-3),
            ("wake_merge_sizes", self.wake_merge_sizes, 0.0),
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

/// The fraction of its still-air thrust a rotor makes at speed `omega_rad_s` in an axial inflow
/// `w_m_s` coming down through its disc (uniform-inflow blade-element momentum theory, linear
/// lift, helical twist; see the module docs). `k` is the blade's `K`, `ct0` the still-air
/// thrust coefficient `k_T / (ρ A R²)`. 1 at no inflow, falling to 0 at `w = θ ω R`; an
/// upward inflow (`w < 0`, the vortex-ring regime) is not modelled and counts as none.
#[inline]
pub fn inflow_thrust_factor(w_m_s: Real, omega_rad_s: Real, radius_m: Real, k: Real, ct0: Real) -> Real {
    let theta = ct0 / k + (0.5 * ct0).sqrt();
    let lc = w_m_s.max(0.0) / (omega_rad_s * radius_m).max(1.0);
    let u = theta - 0.5 * lc;
    let s = (k * k / 16.0 + 0.25 * lc * lc + 0.5 * k * u).sqrt();
    (k / ct0 * (u + 0.25 * k - s)).clamp(0.0, 1.0)
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
    /// The rotor hubs, where the four rotor jets start, m.
    pub hubs: [crate::math::Vec3; 4],
    /// Each rotor jet's initial speed (its rotor's `v_final`), m/s.
    pub hub_v0_m_s: [Real; 4],
    /// The hubs' farthest distance from the origin, m.
    pub hubs_reach_m: Real,
    /// Each rotor jet's initial width (the rotor radius), m.
    pub hub_b0_m: Real,
    /// Depth below the rotors where the four jets have become one, m (0: always one).
    pub merge_m: Real,
}

impl Wake {
    /// The mean air speed of the wake at a point, m/s (0 outside it).
    #[inline]
    pub fn speed_at(&self, p: crate::math::Vec3, width_per_m: Real) -> Real {
        self.speed_over_disc(p, width_per_m, 0.0)
    }

    /// The mean air speed of the wake over a disc of radius `disc_m` centred at `p` across the
    /// flow (a rotor's), m/s: each Gaussian `exp(−r²/b²)` averaged over the disc is close to
    /// one of width `√(b² + disc²/2)` with its amplitude scaled by `b² / (b² + disc²/2)`
    /// (within 4 % for a disc as wide as the jet).
    #[inline]
    pub fn speed_over_disc(&self, p: crate::math::Vec3, width_per_m: Real, disc_m: Real) -> Real {
        let d = p - self.origin;
        let x = d.dot(self.dir);
        if x <= 0.0 || x > self.length_m {
            return 0.0;
        }
        let spread = 0.5 * disc_m * disc_m;
        let b = self.b0_m + width_per_m * x;
        let r2 = (d - self.dir * x).length_squared();
        let b2 = b * b + spread;
        let round = match r2 > 9.0 * b2 {
            true => 0.0,
            false => self.v0_m_s * self.b0_m / b * (b * b / b2) * (-r2 / b2).exp(),
        };
        if x >= self.merge_m {
            return round;
        }
        // The near wake: the four rotor jets, blended into the round jet by momentum.
        let t = x / self.merge_m;
        let beta = t * t * (3.0 - 2.0 * t);
        let mut sum = 0.0;
        for (hub, v0) in self.hubs.iter().zip(self.hub_v0_m_s) {
            let dj = p - *hub;
            let xj = dj.dot(self.dir).max(0.0);
            let bj = self.hub_b0_m + width_per_m * xj;
            let rj2 = (dj - self.dir * xj).length_squared();
            let bj2 = bj * bj + spread;
            if rj2 < 9.0 * bj2 {
                let u = v0 * self.hub_b0_m / bj * (bj * bj / bj2);
                sum += u * u * (-2.0 * rj2 / bj2).exp();
            }
        }
        ((1.0 - beta) * sum + beta * round * round).sqrt()
    }

    /// Whether the wake is still air over every disc of radius `disc_m` centred within
    /// `near_m` of `p` ([`Wake::speed_over_disc`] gives exactly 0 there): a test of one point
    /// that spares the four rotors of a copter far from the wake the exact one.
    ///
    /// From `p`, at depth `x` along the flow and `r` across it, a centre within `near_m` lies
    /// at a depth within `x ± near_m`; it lies `r − near_m − h` or more across from the axis
    /// of the round jet and of each rotor jet (`h`: the hubs' farthest distance from the
    /// origin), and every jet is narrower there than `max(b₀, hub b₀) + width_per_m · (x +
    /// near_m + h)`. Beyond three such widths every Gaussian of [`Wake::speed_over_disc`] is
    /// cut off. A millimetre of margin covers rounding.
    #[inline]
    pub fn is_still_near(&self, p: crate::math::Vec3, near_m: Real, width_per_m: Real, disc_m: Real) -> bool {
        const MARGIN_M: Real = 1e-3;
        let d = p - self.origin;
        let x = d.dot(self.dir);
        if x + near_m + MARGIN_M <= 0.0 || x - near_m - MARGIN_M > self.length_m {
            return true;
        }
        if width_per_m < 0.0 {
            return false;
        }
        let h = self.hubs_reach_m;
        let across = (d - self.dir * x).length() - near_m - h - MARGIN_M;
        let widest = self.b0_m.max(self.hub_b0_m) + width_per_m * (x + near_m + h).max(0.0);
        across > 0.0 && across * across > 9.0 * (widest * widest + 0.5 * disc_m * disc_m)
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
    fn a_rotor_in_inflow_loses_thrust_as_blade_element_theory_says() {
        // The FINken's 5x3" at hover: 1108.7 rad/s, R 0.0637 m, C_T0 0.012684, K 0.1026.
        let f = |w: Real| inflow_thrust_factor(w, 1108.7, 0.0637, 0.1026, 0.012684);
        assert!((f(0.0) - 1.0).abs() < 1e-6);
        // The tip-loss blade-element reference (docs/model.md) at 1, 2, 5, 8 m/s.
        for (w, want) in [(1.0, 0.958), (2.0, 0.911), (5.0, 0.740), (8.0, 0.521)] {
            assert!((f(w) - want).abs() < 0.012, "w = {w}: {} vs {want}", f(w));
        }
        let slope = (1.0 - f(0.1)) / 0.1 * 0.971;
        assert!((0.035..0.05).contains(&slope), "{slope} N per m/s, not the old 0.08");
        assert!((f(-3.0) - 1.0).abs() < 1e-6, "no upward inflow modelled");
        assert_eq!(f(30.0), 0.0);
    }

    fn round_wake(v0: Real, merge_m: Real) -> Wake {
        let arm = 0.1 / std::f32::consts::SQRT_2;
        let hubs = [
            Vec3::new(arm, arm, 0.0),
            Vec3::new(arm, -arm, 0.0),
            Vec3::new(-arm, -arm, 0.0),
            Vec3::new(-arm, arm, 0.0),
        ];
        Wake {
            origin: Vec3::ZERO,
            dir: Vec3::NEG_Z,
            v0_m_s: v0,
            b0_m: 0.127,
            length_m: 3.0,
            hubs,
            hub_v0_m_s: [v0; 4],
            hubs_reach_m: 0.1,
            hub_b0_m: 0.0637,
            merge_m,
        }
    }

    #[test]
    fn the_near_wake_is_four_rotor_jets_with_the_same_momentum_flux() {
        let k = 0.094 / std::f32::consts::LN_2.sqrt();
        let w = round_wake(11.0, 0.5);
        // ∫ ρ w² dA over a plane below the rotors is the thrust at every depth.
        let flux = |x: Real| {
            let (n, half) = (200, 1.0);
            let h = 2.0 * half / n as Real;
            let mut sum = 0.0;
            for i in 0..n {
                for j in 0..n {
                    let p = Vec3::new(-half + (i as Real + 0.5) * h, -half + (j as Real + 0.5) * h, -x);
                    let v = w.speed_at(p, k);
                    sum += v * v * h * h;
                }
            }
            sum
        };
        let far = flux(1.0);
        for x in [0.05, 0.2, 0.4] {
            assert!((flux(x) / far - 1.0).abs() < 0.02, "x = {x}: {} vs {far}", flux(x));
        }
        // Below a rotor, near the rotors, faster than on the axis; beyond the merge, one jet.
        let (hub, axis) = (w.speed_at(Vec3::new(0.0707, 0.0707, -0.1), k), w.speed_at(Vec3::new(0.0, 0.0, -0.1), k));
        assert!(hub > 1.5 * axis, "{hub} vs {axis}");
        let one = round_wake(11.0, 0.0);
        assert_eq!(w.speed_at(Vec3::new(0.05, 0.0, -0.7), k), one.speed_at(Vec3::new(0.05, 0.0, -0.7), k));
    }

    #[test]
    fn a_wake_still_near_a_point_is_still_over_every_disc_around_it() {
        let k = 0.094 / std::f32::consts::LN_2.sqrt();
        let mut rng = crate::rng::Rng32::new(3, 0);
        let (mut still, mut felt, mut elsewhere) = (0, 0, 0);
        for _ in 0..4000 {
            let mut u = || 2.0 * rng.uniform() - 1.0;
            let tilt = crate::math::Quat::from_rotation_x(0.5 * u()) * crate::math::Quat::from_rotation_y(0.5 * u());
            let mut w = round_wake(11.0, if u() > 0.0 { 0.5 } else { 0.0 });
            w.origin = Vec3::new(20.0 + 3.0 * u(), -7.0 + 3.0 * u(), 1.5 + u());
            w.dir = tilt * Vec3::NEG_Z;
            w.hubs = w.hubs.map(|h| w.origin + tilt * h);
            w.length_m = w.origin.z / -w.dir.z;
            let p = w.origin + Vec3::new(u(), u(), u() - 0.5);
            let near = 0.12;
            if !w.is_still_near(p, near, k, 0.0637) {
                elsewhere += usize::from(w.speed_over_disc(p, k, 0.0637) != 0.0);
                continue;
            }
            still += 1;
            for _ in 0..16 {
                let q = p + Vec3::new(u(), u(), u()).clamp_length_max(1.0) * near;
                let v = w.speed_over_disc(q, k, 0.0637);
                felt += usize::from(v != 0.0);
            }
        }
        assert!(still > 1000 && elsewhere > 500, "the test rarely applies: {still}, {elsewhere}");
        assert_eq!(felt, 0);
    }

    #[test]
    fn the_wake_keeps_its_momentum_flux_as_it_spreads() {
        let k = 0.094 / std::f32::consts::LN_2.sqrt();
        let w = round_wake(11.0, 0.0);
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
