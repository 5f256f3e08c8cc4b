//! Math types and the frame conventions every other module relies on.
//!
//! **Frames.** The world frame is ENU-like: `x` along the arena's long side, `y` across it, `z`
//! up, origin at the centre of the arena floor. The body frame is FLU (REP-103): `x` forward,
//! `y` left, `z` up. Attitude is ZYX Euler (`yaw`, then `pitch`, then `roll`), so:
//! - `roll_rad > 0` lowers the right side: the copter accelerates towards body `-y` (right);
//! - `pitch_rad > 0` lowers the nose: the copter accelerates towards body `+x` (forward);
//! - `yaw_rad` is counter-clockwise from world `+x`, seen from above.
//!
//! Paparazzi uses NED/FRD: the bridge converts at the edge, never here.

pub use rapier3d::glamx::{Quat, Vec2, Vec3};
pub use rapier3d::math::{Real, Vector};

/// Standard gravity, m/s².
pub const GRAVITY_M_S2: Real = 9.81;

/// Wraps an angle into (−π, π].
#[inline]
pub fn wrap_angle_rad(a: Real) -> Real {
    use std::f32::consts::{PI, TAU};
    if a > -PI && a <= PI {
        return a; // already wrapped: the common case, exact and cheap
    }
    let mut w = a.rem_euclid(TAU);
    if w > PI {
        w -= TAU;
    }
    w
}

/// Roll, pitch, yaw (ZYX Euler, radians) of a world-from-body rotation.
#[inline]
pub fn euler_from_quat(q: Quat) -> [Real; 3] {
    let (x, y, z, w) = (q.x, q.y, q.z, q.w);
    let sinr_cosp = 2.0 * (w * x + y * z);
    let cosr_cosp = 1.0 - 2.0 * (x * x + y * y);
    let roll = atan2(sinr_cosp, cosr_cosp);
    let sinp = (2.0 * (w * y - z * x)).clamp(-1.0, 1.0);
    let pitch = asin(sinp);
    let siny_cosp = 2.0 * (w * z + x * y);
    let cosy_cosp = 1.0 - 2.0 * (y * y + z * z);
    let yaw = atan2(siny_cosp, cosy_cosp);
    [roll, pitch, yaw]
}

// The transcendental functions of every physics step and of the normal noise, in arithmetic
// alone, inlined: these give the same bits on every machine, where the system libm's `atan2f`,
// `asinf`, `cosf` and `logf` differ between versions and between CPUs (glibc picks its code at
// load time). Other libm calls remain elsewhere (ARCHITECTURE.md). Each is within 2.5 ulp of
// the exact value for finite arguments (`tests::portable_math_is_within_2_5_ulp`); the
// polynomials are minimax fits in `f32` (`ln`'s is fdlibm's).

/// `atan(t) = t + t u Q(u)`, `u = t²`, for `t` in [0, 1]: Q's coefficients from `u⁰`.
pub(crate) const ATAN_Q: [Real; 8] = [
    -0.333_331_53,
    0.199_937_73,
    -0.142_110_56,
    0.106_660_075,
    -0.075_522_21,
    0.043_211_937,
    -0.016_367_976,
    0.002_920_704,
];
/// `sin r = r + r u S(u)` and `cos r = 1 − u / 2 + u² C(u)`, `u = r²`, for `|r| ≤ π/4`.
pub(crate) const SIN_S: [Real; 3] = [-0.166_666_55, 0.008_332_16, -0.000_195_152_82];
pub(crate) const COS_C: [Real; 3] = [0.041_666_646, -0.001_388_731_6, 0.000_024_433_159];
/// π/2 in three parts, the first two of 12 significant bits (exact times a small integer).
pub(crate) const PIO2: [Real; 3] = [1.570_312_5, 0.000_483_751_3, 7.549_79e-8];

/// `ln(1 + s) − ln(1 − s) = 2s + s R(s²)`: R's coefficients (musl's `logf`, from fdlibm).
const LN_LG: [Real; 4] = [
    Real::from_bits(0x3f2a_aaaa),
    Real::from_bits(0x3ecc_ce13),
    Real::from_bits(0x3e91_e9ee),
    Real::from_bits(0x3e78_9e26),
];

/// Horner's scheme on coefficients from the constant term up.
#[inline(always)]
pub(crate) fn horner<const N: usize>(c: &[Real; N], u: Real) -> Real {
    c.iter().rev().fold(0.0, |acc, &k| acc * u + k)
}

/// `y.atan2(x)` (radians in [−π, π]) for finite arguments, with libm's signed zeros.
#[inline]
pub fn atan2(y: Real, x: Real) -> Real {
    use std::f32::consts::{FRAC_PI_2, PI};
    let (ax, ay) = (x.abs(), y.abs());
    let steep = ay > ax;
    let (num, den) = if steep { (ax, ay) } else { (ay, ax) };
    if den == 0.0 {
        // atan2(±0, +0) = ±0, atan2(±0, −0) = ±π.
        return if x.is_sign_negative() { PI.copysign(y) } else { y };
    }
    let t = num / den;
    let u = t * t;
    // Estrin's scheme: four short chains at once rather than Horner's one of eight steps
    // (this sits on every substep's chain from attitude to thrust).
    let c = &ATAN_Q;
    let (u2, u4) = (u * u, u * u * (u * u));
    let (p01, p23, p45, p67) = (c[0] + c[1] * u, c[2] + c[3] * u, c[4] + c[5] * u, c[6] + c[7] * u);
    let q = (p01 + p23 * u2) + (p45 + p67 * u2) * u4;
    let mut r = t + t * (u * q);
    if steep {
        r = FRAC_PI_2 - r;
    }
    if x < 0.0 {
        r = PI - r;
    }
    r.copysign(y)
}

/// `x.asin()` for `x` in [−1, 1].
#[inline]
pub fn asin(x: Real) -> Real {
    atan2(x, ((1.0 - x) * (1.0 + x)).sqrt())
}

/// `x.ln()` for positive normal `x` (musl's `logf`, from fdlibm; ±∞ and NaN as libm, 0 and
/// below give NaN).
#[inline]
pub fn ln(x: Real) -> Real {
    // ln 2 in two parts, the first exact times any exponent.
    const LN2: [Real; 2] = [Real::from_bits(0x3f31_7180), Real::from_bits(0x3717_f7d1)];
    let bits = x.to_bits();
    if !(0x0080_0000..0x7f80_0000).contains(&bits) {
        return if bits == 0x7f80_0000 || x.is_nan() { x } else { Real::NAN };
    }
    // x = 2^k m with m in [√½, √2).
    let ix = bits + (0x3f80_0000 - 0x3f35_04f3);
    let k = (ix >> 23) as i32 - 0x7f;
    let f = Real::from_bits((ix & 0x007f_ffff) + 0x3f35_04f3) - 1.0;
    let s = f / (2.0 + f);
    let (z, w) = (s * s, s * s * s * s);
    let r = z * (LN_LG[0] + w * LN_LG[2]) + w * (LN_LG[1] + w * LN_LG[3]);
    let (hfsq, dk) = (0.5 * f * f, k as Real);
    s * (hfsq + r) + dk * LN2[1] - hfsq + f + dk * LN2[0]
}

/// `x.cos()` for `|x|` up to a few thousand radians.
#[inline]
pub fn cos(x: Real) -> Real {
    // x = q π/2 + r with |r| ≤ π/4 (Cody–Waite); q rounded half away from zero by a cast.
    let q = (x * std::f32::consts::FRAC_2_PI + 0.5f32.copysign(x)) as i32;
    let qf = q as Real;
    let r = ((x - qf * PIO2[0]) - qf * PIO2[1]) - qf * PIO2[2];
    let u = r * r;
    let (sin, cos) = (r + r * (u * horner(&SIN_S, u)), (1.0 - 0.5 * u) + u * u * horner(&COS_C, u));
    match q & 3 {
        0 => cos,
        1 => -sin,
        2 => -cos,
        _ => sin,
    }
}

/// World-from-body rotation from roll, pitch, yaw (ZYX Euler, radians).
#[inline]
pub fn quat_from_euler(roll_rad: Real, pitch_rad: Real, yaw_rad: Real) -> Quat {
    Quat::from_rotation_z(yaw_rad) * Quat::from_rotation_y(pitch_rad) * Quat::from_rotation_x(roll_rad)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Distance in ulp of `a` from the exact `ex`, on the `f32` grid at `ex`.
    fn ulp_error(a: Real, ex: f64) -> f64 {
        let spacing = f64::from(f32::from_bits((ex.abs() as f32).to_bits() + 1)) - (ex.abs() as f32) as f64;
        (f64::from(a) - ex).abs() / spacing
    }

    #[test]
    fn portable_math_is_within_2_5_ulp() {
        let mut worst = [0.0f64; 3];
        let n: u64 = 400_000;
        for i in 0..=n {
            // atan2 around the whole circle, at radii from 1e-3 to 1e3.
            let a = -std::f64::consts::PI + std::f64::consts::TAU * i as f64 / n as f64;
            let rho = 10f64.powf(-3.0 + 6.0 * ((i * 7919) % n) as f64 / n as f64);
            let (y, x) = ((rho * a.sin()) as f32, (rho * a.cos()) as f32);
            worst[0] = worst[0].max(ulp_error(atan2(y, x), f64::from(y).atan2(f64::from(x))));
            let s = (-1.0 + 2.0 * i as f64 / n as f64) as f32;
            worst[1] = worst[1].max(ulp_error(asin(s), f64::from(s).asin()));
            let c = (a * 1.25) as f32;
            // Near its zeros cos is as good as its argument: 2 ulp of the argument there.
            let ex = f64::from(c).cos();
            let err = (f64::from(cos(c)) - ex).abs();
            worst[2] = worst[2].max(ulp_error(cos(c), ex).min(err / (f64::from(c.abs()) * 1.2e-7 / 2.0)));
        }
        assert!(worst.iter().all(|w| *w <= 2.5), "worst ulp: atan2, asin, cos {worst:?}");
        // ln over every binade of the normal floats, and near 1.
        let mut worst_ln: f64 = 0.0;
        for i in 0..=n {
            let x = (2f64.powf(-126.0 + 253.0 * i as f64 / n as f64)) as f32;
            let near_one = (1.0 + (i as f64 / n as f64 - 0.5) * 1e-3) as f32;
            for x in [x, near_one] {
                worst_ln = worst_ln.max(ulp_error(ln(x), f64::from(x).ln()));
            }
        }
        assert!(worst_ln <= 2.5, "worst ulp: ln {worst_ln}");
        assert_eq!(ln(1.0), 0.0);
        assert!(ln(0.0).is_nan() && ln(-1.0).is_nan() && ln(Real::INFINITY) == Real::INFINITY);
        // Signed zeros and the axes, as libm.
        assert_eq!(atan2(0.0, 0.0).to_bits(), 0f32.to_bits());
        assert_eq!(atan2(-0.0, 0.0).to_bits(), (-0f32).to_bits());
        assert_eq!(atan2(0.0, -0.0), std::f32::consts::PI);
        assert_eq!(atan2(-0.0, -1.0), -std::f32::consts::PI);
        assert_eq!(atan2(1.0, 0.0), std::f32::consts::FRAC_PI_2);
        assert_eq!(asin(1.0), std::f32::consts::FRAC_PI_2);
        assert_eq!(cos(0.0), 1.0);
        assert!(atan2(Real::NAN, 1.0).is_nan() && asin(Real::NAN).is_nan() && cos(Real::NAN).is_nan());
    }

    #[test]
    fn wrap_angle_stays_in_half_open_interval() {
        use std::f32::consts::PI;
        assert!((wrap_angle_rad(3.0 * PI) - PI).abs() < 1e-5);
        assert!((wrap_angle_rad(-PI) - PI).abs() < 1e-5);
        assert!((wrap_angle_rad(0.5) - 0.5).abs() < 1e-6);
        assert!((wrap_angle_rad(-0.5 - 2.0 * PI) + 0.5).abs() < 1e-5);
    }

    #[test]
    fn euler_round_trip() {
        let q = quat_from_euler(0.1, -0.2, 2.5);
        let [r, p, y] = euler_from_quat(q);
        assert!((r - 0.1).abs() < 1e-5 && (p + 0.2).abs() < 1e-5 && (y - 2.5).abs() < 1e-5);
    }

    #[test]
    fn positive_pitch_tilts_thrust_forward() {
        let thrust_dir = quat_from_euler(0.0, 0.2, 0.0) * Vec3::Z;
        assert!(thrust_dir.x > 0.1, "pitch > 0 must accelerate towards +x, got {thrust_dir:?}");
        let thrust_dir = quat_from_euler(0.2, 0.0, 0.0) * Vec3::Z;
        assert!(thrust_dir.y < -0.1, "roll > 0 must accelerate towards -y (right), got {thrust_dir:?}");
    }
}
