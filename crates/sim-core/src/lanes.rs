//! Four copters' arithmetic side by side: the closed-form parts of a free copter's substep
//! (body rates, Euler angles, free flight, the checks after it) on four lanes at once.
//!
//! Each lane computes exactly what the scalar code computes for its copter, operation for
//! operation: `glam`'s `Vec3` component by component, its SSE2 `Quat` products in the order of
//! their shuffles, and [`crate::math`]'s functions with their branches as per-lane selects.
//! Lane-wise IEEE arithmetic rounds as scalar arithmetic does, so a copter's bits do not depend
//! on whether it ran in a batch (`tests` compare every function with its scalar original).

use std::ops::{Add, Div, Mul, Neg, Sub};

use crate::math::{self, Quat, Real, Vec3};

/// Lanes per batch.
pub(crate) const LANES: usize = 4;

/// One number per lane: a `wide::f32x4` (an SSE2 register on x86-64). Every operation is the
/// scalar one on each lane.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct F4(pub(crate) wide::f32x4);

/// One flag per lane, as all-ones or all-zeros lanes.
#[derive(Clone, Copy, Debug)]
pub(crate) struct M4(pub(crate) wide::f32x4);

impl F4 {
    #[inline(always)]
    pub(crate) fn splat(v: Real) -> Self {
        Self(wide::f32x4::splat(v))
    }

    #[inline(always)]
    pub(crate) fn from_array(a: [Real; LANES]) -> Self {
        Self(wide::f32x4::new(a))
    }

    #[inline(always)]
    pub(crate) fn to_array(self) -> [Real; LANES] {
        self.0.to_array()
    }

    #[cfg(test)]
    pub(crate) fn get(self, l: usize) -> Real {
        self.to_array()[l]
    }

    #[inline(always)]
    pub(crate) fn sqrt(self) -> Self {
        Self(self.0.sqrt())
    }

    /// The sign bit cleared.
    #[inline(always)]
    pub(crate) fn abs(self) -> Self {
        Self(self.0.abs())
    }

    #[inline(always)]
    pub(crate) fn gt(self, o: Self) -> M4 {
        M4(self.0.simd_gt(o.0))
    }

    #[inline(always)]
    pub(crate) fn lt(self, o: Self) -> M4 {
        M4(self.0.simd_lt(o.0))
    }

    #[inline(always)]
    pub(crate) fn eq_lanes(self, o: Self) -> M4 {
        M4(self.0.simd_eq(o.0))
    }

    /// `if m { a } else { b }`, lane by lane.
    #[inline(always)]
    pub(crate) fn select(m: M4, a: Self, b: Self) -> Self {
        Self(m.0.select(a.0, b.0))
    }

    /// `Real::copysign`: the magnitude of `self`, the sign of `sign`.
    #[inline(always)]
    pub(crate) fn copysign(self, sign: Self) -> Self {
        let sign_bit = wide::f32x4::splat(-0.0);
        Self((sign.0 & sign_bit) | self.0.abs())
    }

    /// `Real::max` on each lane, where the two are not zeros of opposite signs (which `max`
    /// may return either of): a NaN gives the other.
    #[inline(always)]
    pub(crate) fn max(self, o: Self) -> Self {
        F4::select(o.gt(self), o, F4::select(M4(self.0.is_nan()), o, self))
    }

    /// `Real::min` on each lane, as [`F4::max`].
    #[inline(always)]
    pub(crate) fn min(self, o: Self) -> Self {
        F4::select(o.lt(self), o, F4::select(M4(self.0.is_nan()), o, self))
    }

    /// Lanes holding a zero of either sign.
    #[inline(always)]
    pub(crate) fn is_zero(self) -> M4 {
        self.eq_lanes(F4::splat(0.0))
    }

    /// `Real::clamp` on each lane (a NaN stays NaN).
    #[inline(always)]
    pub(crate) fn clamp(self, lo: Real, hi: Real) -> Self {
        let (lo, hi) = (F4::splat(lo), F4::splat(hi));
        let x = F4::select(self.lt(lo), lo, self);
        F4::select(x.gt(hi), hi, x)
    }
}

impl M4 {
    #[inline(always)]
    pub(crate) fn get(self, l: usize) -> bool {
        self.0.to_array()[l].to_bits() != 0
    }

    #[inline(always)]
    pub(crate) fn any(self) -> bool {
        self.0.any()
    }

    #[inline(always)]
    pub(crate) fn all(self) -> bool {
        self.0.all()
    }

    /// Lanes set in either.
    #[inline(always)]
    pub(crate) fn or(self, o: M4) -> M4 {
        M4(self.0 | o.0)
    }

    /// Lanes set in both.
    #[inline(always)]
    pub(crate) fn and(self, o: M4) -> M4 {
        M4(self.0 & o.0)
    }

    #[inline(always)]
    pub(crate) fn not(self) -> M4 {
        M4(!self.0)
    }
}

macro_rules! lane_op {
    ($tr:ident, $f:ident, $op:tt) => {
        impl $tr for F4 {
            type Output = F4;
            #[inline(always)]
            fn $f(self, o: F4) -> F4 {
                F4(self.0 $op o.0)
            }
        }
        impl $tr<Real> for F4 {
            type Output = F4;
            #[inline(always)]
            fn $f(self, o: Real) -> F4 {
                F4(self.0 $op wide::f32x4::splat(o))
            }
        }
        impl $tr<F4> for Real {
            type Output = F4;
            #[inline(always)]
            fn $f(self, o: F4) -> F4 {
                F4(wide::f32x4::splat(self) $op o.0)
            }
        }
    };
}
lane_op!(Add, add, +);
lane_op!(Sub, sub, -);
lane_op!(Mul, mul, *);
lane_op!(Div, div, /);

impl Neg for F4 {
    type Output = F4;
    /// A sign flip, as scalar negation.
    #[inline(always)]
    fn neg(self) -> F4 {
        F4(-self.0)
    }
}

/// A `Vec3` per lane, with `glam`'s scalar `Vec3` arithmetic.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct V4 {
    pub(crate) x: F4,
    pub(crate) y: F4,
    pub(crate) z: F4,
}

impl V4 {
    #[inline(always)]
    pub(crate) fn new(x: F4, y: F4, z: F4) -> Self {
        Self { x, y, z }
    }

    #[inline(always)]
    pub(crate) fn splat(v: Vec3) -> Self {
        Self::new(F4::splat(v.x), F4::splat(v.y), F4::splat(v.z))
    }

    #[inline(always)]
    pub(crate) fn gather(v: [Vec3; LANES]) -> Self {
        Self::new(F4::from_array(v.map(|v| v.x)), F4::from_array(v.map(|v| v.y)), F4::from_array(v.map(|v| v.z)))
    }

    /// Every lane's vector.
    #[inline(always)]
    pub(crate) fn lanes(self) -> [Vec3; LANES] {
        let (x, y, z) = (self.x.to_array(), self.y.to_array(), self.z.to_array());
        std::array::from_fn(|l| Vec3::new(x[l], y[l], z[l]))
    }

    #[inline(always)]
    pub(crate) fn lane(self, l: usize) -> Vec3 {
        self.lanes()[l]
    }

    /// `Vec3::dot`: `(x x' + y y') + z z'`.
    #[inline(always)]
    pub(crate) fn dot(self, o: Self) -> F4 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }

    /// `Vec3::cross`.
    #[inline(always)]
    pub(crate) fn cross(self, o: Self) -> Self {
        Self::new(self.y * o.z - o.y * self.z, self.z * o.x - o.z * self.x, self.x * o.y - o.x * self.y)
    }

    #[inline(always)]
    pub(crate) fn scale(self, s: F4) -> Self {
        Self::new(self.x * s, self.y * s, self.z * s)
    }

    #[inline(always)]
    pub(crate) fn scale_by(self, s: Real) -> Self {
        Self::new(self.x * s, self.y * s, self.z * s)
    }

    /// Component by component, as `Vec3 * Vec3` and `Vec3 / Vec3`.
    #[inline(always)]
    pub(crate) fn mul_each(self, o: Vec3) -> Self {
        Self::new(self.x * o.x, self.y * o.y, self.z * o.z)
    }

    #[inline(always)]
    pub(crate) fn div_each(self, o: Vec3) -> Self {
        Self::new(self.x / o.x, self.y / o.y, self.z / o.z)
    }

    /// Each lane's vector over its own number.
    #[inline(always)]
    pub(crate) fn div_lanes(self, s: F4) -> Self {
        Self::new(self.x / s, self.y / s, self.z / s)
    }

    #[inline(always)]
    pub(crate) fn div_by(self, s: Real) -> Self {
        Self::new(self.x / s, self.y / s, self.z / s)
    }
}

impl Add for V4 {
    type Output = V4;
    #[inline(always)]
    fn add(self, o: V4) -> V4 {
        V4::new(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}

impl Sub for V4 {
    type Output = V4;
    #[inline(always)]
    fn sub(self, o: V4) -> V4 {
        V4::new(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}

/// A `Quat` per lane, with `glam`'s SSE2 `Quat` arithmetic.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct Q4 {
    pub(crate) x: F4,
    pub(crate) y: F4,
    pub(crate) z: F4,
    pub(crate) w: F4,
}

impl Q4 {
    #[inline(always)]
    pub(crate) fn gather(q: [Quat; LANES]) -> Self {
        let part = |f: fn(&Quat) -> Real| F4::from_array(std::array::from_fn(|l| f(&q[l])));
        Self { x: part(|q| q.x), y: part(|q| q.y), z: part(|q| q.z), w: part(|q| q.w) }
    }

    /// Every lane's quaternion.
    #[inline(always)]
    pub(crate) fn lanes(self) -> [Quat; LANES] {
        let (x, y, z, w) = (self.x.to_array(), self.y.to_array(), self.z.to_array(), self.w.to_array());
        std::array::from_fn(|l| Quat::from_xyzw(x[l], y[l], z[l], w[l]))
    }

    #[cfg(test)]
    pub(crate) fn lane(self, l: usize) -> Quat {
        self.lanes()[l]
    }

    /// `Quat::inverse` of a unit quaternion: its conjugate.
    #[inline(always)]
    pub(crate) fn inverse(self) -> Self {
        Self { x: -self.x, y: -self.y, z: -self.z, w: self.w }
    }

    /// `Quat * Vec3` (`mul_vec3a`): `v (w² − b·b) + b (2 v·b) + (b × v)(2 w)`, with `b` the
    /// vector part; its dot products sum `(x + y) + z` and its cross product is the
    /// SSE2 one.
    #[inline(always)]
    pub(crate) fn rotate(self, v: V4) -> V4 {
        let b = V4::new(self.x, self.y, self.z);
        let b2 = b.dot(b);
        let vb2 = v.dot(b) * 2.0;
        let w2 = self.w * 2.0;
        let s = self.w * self.w - b2;
        // The SSE2 cross product `(b.zxy v − b v.zxy).zxy`.
        let cross = V4::new(b.y * v.z - v.y * b.z, b.z * v.x - v.z * b.x, b.x * v.y - v.x * b.y);
        V4::new(
            v.x * s + b.x * vb2 + cross.x * w2,
            v.y * s + b.y * vb2 + cross.y * w2,
            v.z * s + b.z * vb2 + cross.z * w2,
        )
    }

    /// `self * rhs` for `self = (v, 0)`, a pure quaternion (`mul_quat`, after rtm's
    /// `quat_mul`: the products in its order, the negated ones negated).
    #[inline(always)]
    pub(crate) fn pure_mul(v: V4, r: Self) -> Self {
        let (ax, ay, az) = (v.x, v.y, v.z);
        let aw = F4::splat(0.0);
        Self {
            x: (aw * r.x + ax * r.w) + (ay * r.z + -(az * r.y)),
            y: (aw * r.y + -(ax * r.z)) + (ay * r.w + az * r.x),
            z: (aw * r.z + ax * r.y) + (-(ay * r.x) + az * r.w),
            w: (aw * r.w + -(ax * r.x)) + (-(ay * r.y) + -(az * r.z)),
        }
    }

    /// `(self + o).normalize()`: `Vec4` addition, then division by `sqrt((x² + z²) + (y² +
    /// w²))`, the SSE2 `dot4`'s grouping.
    #[inline(always)]
    pub(crate) fn add_normalize(self, o: Self) -> Self {
        let (x, y, z, w) = (self.x + o.x, self.y + o.y, self.z + o.z, self.w + o.w);
        let len = ((x * x + z * z) + (y * y + w * w)).sqrt();
        Self { x: x / len, y: y / len, z: z / len, w: w / len }
    }
}

/// [`math::atan2`] per lane (a lane with both arguments zero takes the scalar path).
#[inline(always)]
pub(crate) fn atan2(y: F4, x: F4) -> F4 {
    use std::f32::consts::{FRAC_PI_2, PI};
    let (ax, ay) = (x.abs(), y.abs());
    let steep = ay.gt(ax);
    let (num, den) = (F4::select(steep, ax, ay), F4::select(steep, ay, ax));
    let t = num / den;
    let u = t * t;
    let c = &math::ATAN_Q;
    let (u2, u4) = (u * u, u * u * (u * u));
    let (p01, p23, p45, p67) = (c[0] + c[1] * u, c[2] + c[3] * u, c[4] + c[5] * u, c[6] + c[7] * u);
    let q = (p01 + p23 * u2) + (p45 + p67 * u2) * u4;
    let r = t + t * (u * q);
    let r = F4::select(steep, FRAC_PI_2 - r, r);
    let r = F4::select(x.lt(F4::splat(0.0)), PI - r, r);
    let r = r.copysign(y);
    let zero = den.eq_lanes(F4::splat(0.0));
    if !zero.any() {
        return r;
    }
    let (mut out, y, x) = (r.to_array(), y.to_array(), x.to_array());
    for l in (0..LANES).filter(|&l| zero.get(l)) {
        out[l] = math::atan2(y[l], x[l]);
    }
    F4::from_array(out)
}

/// [`math::euler_from_quat`] per lane: roll, pitch, yaw.
#[inline(always)]
pub(crate) fn euler_from_quat(q: Q4) -> [F4; 3] {
    let (x, y, z, w) = (q.x, q.y, q.z, q.w);
    let sinr_cosp = 2.0 * (w * x + y * z);
    let cosr_cosp = 1.0 - 2.0 * (x * x + y * y);
    let roll = atan2(sinr_cosp, cosr_cosp);
    let sinp = (2.0 * (w * y - z * x)).clamp(-1.0, 1.0);
    // `math::asin`.
    let pitch = atan2(sinp, ((1.0 - sinp) * (1.0 + sinp)).sqrt());
    let siny_cosp = 2.0 * (w * z + x * y);
    let cosy_cosp = 1.0 - 2.0 * (y * y + z * z);
    let yaw = atan2(siny_cosp, cosy_cosp);
    [roll, pitch, yaw]
}

/// [`math::wrap_angle_rad`] per lane: a lane outside (−π, π] takes the scalar path.
#[inline(always)]
pub(crate) fn wrap_angle_rad(a: F4) -> F4 {
    use std::f32::consts::PI;
    let inside = M4(a.gt(F4::splat(-PI)).0 & !a.gt(F4::splat(PI)).0 & !a.0.is_nan());
    if inside.all() {
        return a;
    }
    F4::from_array(a.to_array().map(math::wrap_angle_rad))
}

/// [`math::cos`] per lane, for `|x|` below π/4 (the quadrant `q = 0`); a lane beyond takes
/// the scalar path.
#[inline(always)]
pub(crate) fn cos(x: F4) -> F4 {
    // `q = (x 2/π + ½ sign x) as i32` is 0 exactly when that sum lies in (−1, 1).
    let t = x * std::f32::consts::FRAC_2_PI + F4::splat(0.5).copysign(x);
    if !M4(t.abs().lt(F4::splat(1.0)).0).all() {
        return F4::from_array(x.to_array().map(math::cos));
    }
    let qf = 0.0;
    let r = ((x - qf * math::PIO2[0]) - qf * math::PIO2[1]) - qf * math::PIO2[2];
    let u = r * r;
    let c = &math::COS_C;
    (1.0 - 0.5 * u) + u * u * ((c[2] * u + c[1]) * u + c[0])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Numbers of every sign and many magnitudes, from a small generator.
    fn numbers(seed: u32) -> impl FnMut() -> Real {
        let mut x = seed;
        move || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            let u = (x >> 8) as Real / (1u32 << 24) as Real;
            let scale = [1e-3, 0.1, 1.0, 7.0][(x & 3) as usize];
            (2.0 * u - 1.0) * scale
        }
    }

    fn unit_quats(seed: u32) -> impl FnMut() -> Quat {
        let mut r = numbers(seed);
        move || Quat::from_xyzw(r(), r(), r(), r() + 0.5).normalize()
    }

    fn same(a: Real, b: Real) -> bool {
        a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
    }

    fn same3(a: Vec3, b: Vec3) -> bool {
        same(a.x, b.x) && same(a.y, b.y) && same(a.z, b.z)
    }

    #[test]
    fn quaternion_products_match_glam_bit_for_bit() {
        let (mut q, mut r) = (unit_quats(7), numbers(11));
        for _ in 0..20_000 {
            let qs: [Quat; LANES] = std::array::from_fn(|_| q());
            let vs: [Vec3; LANES] = std::array::from_fn(|_| Vec3::new(r(), r(), r()));
            let ps: [Quat; LANES] = std::array::from_fn(|l| Quat::from_xyzw(vs[l].x, vs[l].y, vs[l].z, 0.0));
            let (q4, v4) = (Q4::gather(qs), V4::gather(vs));
            let rotated = q4.rotate(v4);
            let back = q4.inverse().rotate(v4);
            let product = Q4::pure_mul(v4, q4);
            let summed = q4.add_normalize(product);
            for l in 0..LANES {
                assert!(same3(rotated.lane(l), qs[l] * vs[l]), "rotate {:?} {:?}", qs[l], vs[l]);
                assert!(same3(back.lane(l), qs[l].inverse() * vs[l]), "inverse {:?} {:?}", qs[l], vs[l]);
                let (p, s) = (ps[l] * qs[l], (qs[l] + ps[l] * qs[l]).normalize());
                for (a, b) in [(product.lane(l), p), (summed.lane(l), s)] {
                    let ok = [(a.x, b.x), (a.y, b.y), (a.z, b.z), (a.w, b.w)].iter().all(|&(a, b)| same(a, b));
                    assert!(ok, "{a:?} against glam's {b:?} for {:?} {:?}", qs[l], vs[l]);
                }
            }
        }
    }

    #[test]
    fn vector_arithmetic_matches_glam_bit_for_bit() {
        let mut r = numbers(5);
        for _ in 0..20_000 {
            let a: [Vec3; LANES] = std::array::from_fn(|_| Vec3::new(r(), r(), r()));
            let b: [Vec3; LANES] = std::array::from_fn(|_| Vec3::new(r(), r(), r()));
            let (a4, b4) = (V4::gather(a), V4::gather(b));
            let (dot, cross) = (a4.dot(b4), a4.cross(b4));
            for l in 0..LANES {
                assert!(same(dot.get(l), a[l].dot(b[l])) && same3(cross.lane(l), a[l].cross(b[l])));
                assert!(same(a4.dot(a4).sqrt().get(l), a[l].length()));
            }
        }
    }

    #[test]
    fn euler_angles_match_the_scalar_ones_bit_for_bit() {
        let mut q = unit_quats(3);
        let check = |qs: [Quat; LANES]| {
            let e = euler_from_quat(Q4::gather(qs));
            for (l, q) in qs.iter().enumerate() {
                let s = math::euler_from_quat(*q);
                assert!((0..3).all(|k| same(e[k].get(l), s[k])), "{q:?}: {s:?}");
            }
        };
        for _ in 0..50_000 {
            check(std::array::from_fn(|_| q()));
        }
        // Level, upside down, gimbal lock and the zero-argument branch of `atan2`.
        let h = std::f32::consts::FRAC_1_SQRT_2;
        check([Quat::IDENTITY, Quat::from_xyzw(1.0, 0.0, 0.0, 0.0), Quat::from_xyzw(0.0, h, 0.0, h), q()]);
        check([Quat::from_xyzw(0.0, 0.0, 1.0, 0.0), Quat::from_xyzw(0.0, -h, 0.0, h), q(), Quat::IDENTITY]);
    }

    #[test]
    fn cosine_and_wrapping_match_the_scalar_ones_bit_for_bit() {
        let mut r = numbers(13);
        let mut checked_fast = 0;
        for _ in 0..50_000 {
            let x: [Real; LANES] = std::array::from_fn(|_| r() * 1.5);
            let (c, w) = (cos(F4::from_array(x)).to_array(), wrap_angle_rad(F4::from_array(x)).to_array());
            for l in 0..LANES {
                assert!(same(c[l], math::cos(x[l])) && same(w[l], math::wrap_angle_rad(x[l])), "{}", x[l]);
            }
            checked_fast += usize::from(x.iter().all(|x| x.abs() < 0.7));
        }
        assert!(checked_fast > 1000, "{checked_fast}");
        let edges = [0.0, -0.0, std::f32::consts::PI, -std::f32::consts::PI];
        assert!(same(cos(F4::from_array(edges)).get(1), math::cos(-0.0)));
        let wrapped = wrap_angle_rad(F4::from_array(edges)).to_array();
        assert!((0..LANES).all(|l| same(wrapped[l], math::wrap_angle_rad(edges[l]))));
    }
}
