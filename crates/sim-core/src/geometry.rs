//! Exact sensor geometry: the nearest point of an object inside a cone, and ray casts.
//!
//! A sonar reports the distance from its apex to the nearest point of any object inside its
//! cone (half-angle `h`). For a convex object `O` and a cone `C`, that point is either
//! 1. the nearest point of `O` to the apex, when it lies inside `C`; or else
//! 2. on the cone's surface `∂C`, and there on the boundary of `O` (moving inwards along the
//!    same surface ray would get closer while staying in `O`): in the interior of a face, on an
//!    edge, or at a vertex.
//!
//! On a face's plane, the distance along the surface ray at azimuth `φ` is `p / (u(φ)·m)`, and
//! `u(φ)·m` is a sinusoid in `φ`: its one maximum is the surface ray closest to the face's
//! normal, so a face contributes at most one candidate, in closed form. On an edge, the part
//! inside the cone is one interval of the line (a quadratic's roots), whose nearest point is an
//! end of the interval or the line's own nearest point. Taking the minimum over those finitely
//! many candidates is **exact** (up to f32 rounding): there is no ray fan and no sampling error.
//! For an infinite plane (an arena wall seen from inside the arena) the answer is
//! `p` when the plane's normal is inside the cone, else `p / cos(α − h)`.

use crate::math::{Quat, Real, Vec3};

/// A cone: apex, unit axis, and half-angle (given by its cosine and sine).
#[derive(Clone, Copy, Debug, Default)]
pub struct Cone {
    /// Apex, world frame, m.
    pub apex: Vec3,
    /// Unit axis, world frame.
    pub axis: Vec3,
    /// cos of the half-angle.
    pub cos_h: Real,
    /// sin of the half-angle.
    pub sin_h: Real,
}

impl Cone {
    /// A cone from apex, unit axis and half-angle in radians.
    pub fn new(apex: Vec3, axis: Vec3, half_angle_rad: Real) -> Self {
        let (sin_h, cos_h) = half_angle_rad.sin_cos();
        Self { apex, axis, cos_h, sin_h }
    }

    /// Whether a point lies inside the (infinite) cone.
    #[inline]
    pub fn contains(&self, p: Vec3) -> bool {
        let v = p - self.apex;
        let len = v.length();
        len <= 1e-9 || v.dot(self.axis) >= self.cos_h * len - 1e-6 * len
    }

    /// Distance along the cone to an infinite plane `{x : n·x = c}` with unit normal `n`, seen
    /// from the side the apex is on. `None` if the cone never meets the plane.
    #[inline]
    pub fn distance_to_plane(&self, n: Vec3, c: Real) -> Option<Real> {
        let s = n.dot(self.apex) - c;
        let p = s.abs();
        // m: unit direction from the apex towards the plane.
        let m = if s >= 0.0 { -n } else { n };
        let cos_a = self.axis.dot(m).clamp(-1.0, 1.0);
        if cos_a >= self.cos_h {
            return Some(p);
        }
        // Best surface ray: cos(α − h) = cos α cos h + sin α sin h.
        let sin_a = (1.0 - cos_a * cos_a).max(0.0).sqrt();
        let cos_diff = cos_a * self.cos_h + sin_a * self.sin_h;
        (cos_diff > 1e-6).then(|| p / cos_diff)
    }

    /// The surface ray closest to direction `m` (unit), and the cosine between them.
    #[inline]
    fn surface_ray_towards(&self, m: Vec3) -> Vec3 {
        let perp = m - self.axis * self.axis.dot(m);
        let len = perp.length();
        let e = if len > 1e-9 { perp / len } else { self.axis.any_orthonormal_vector() };
        self.axis * self.cos_h + e * self.sin_h
    }
}

/// An oriented box.
#[derive(Clone, Copy, Debug, Default)]
pub struct OrientedBox {
    /// Centre, world frame, m.
    pub center: Vec3,
    /// World-from-box rotation.
    pub rotation: Quat,
    /// Half extents along the box's own axes, m.
    pub half: Vec3,
}

impl OrientedBox {
    /// Radius of the bounding sphere, m.
    #[inline]
    pub fn bounding_radius(&self) -> Real {
        self.half.length()
    }
}

/// Distance from the cone's apex to the nearest point of the box inside the cone, exactly.
/// `None` if no part of the box is inside the cone.
pub fn cone_box_distance(cone: &Cone, b: &OrientedBox) -> Option<Real> {
    // Work in the box frame: apex `o`, axis `a`.
    let inv = b.rotation.inverse();
    let o = inv * (cone.apex - b.center);
    let a = inv * cone.axis;
    let local = Cone { apex: o, axis: a, cos_h: cone.cos_h, sin_h: cone.sin_h };
    let h = b.half;
    // Apex inside the box.
    if o.x.abs() <= h.x && o.y.abs() <= h.y && o.z.abs() <= h.z {
        return Some(0.0);
    }
    let mut best = Real::INFINITY;
    // 1. Nearest point of the box.
    let nearest = o.clamp(-h, h);
    if local.contains(nearest) {
        return Some((nearest - o).length());
    }
    // 2. Faces: the surface ray closest to the face normal, if it hits inside the face.
    for axis in 0..3 {
        for sign in [-1.0, 1.0] {
            let mut n = Vec3::ZERO;
            n[axis] = sign;
            let plane_c = sign * h[axis];
            let s = o[axis] * sign - h[axis];
            if s <= 0.0 {
                continue; // the apex is not on the outer side of this face
            }
            let ray = local.surface_ray_towards(-n);
            let denom = ray.dot(-n);
            if denom <= 1e-6 {
                continue;
            }
            let t = s / denom;
            let hit = o + ray * t;
            let _ = plane_c;
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            if hit[u].abs() <= h[u] + 1e-6 && hit[v].abs() <= h[v] + 1e-6 {
                best = best.min(t);
            }
        }
    }
    // 3. Edges: the part of each edge inside the cone is one interval; its nearest point is
    //    an end of the interval or the segment's unconstrained nearest point.
    for axis in 0..3 {
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        for su in [-1.0, 1.0] {
            for sv in [-1.0, 1.0] {
                let mut p0 = Vec3::ZERO;
                p0[u] = su * h[u];
                p0[v] = sv * h[v];
                p0[axis] = -h[axis];
                let mut d = Vec3::ZERO;
                d[axis] = 2.0 * h[axis];
                best = best.min(segment_in_cone_nearest(&local, p0, d));
            }
        }
    }
    // 4. Vertices (already covered by edges, kept for robustness at grazing angles).
    for i in 0..8 {
        let p = Vec3::new(
            if i & 1 == 0 { -h.x } else { h.x },
            if i & 2 == 0 { -h.y } else { h.y },
            if i & 4 == 0 { -h.z } else { h.z },
        );
        if local.contains(p) {
            best = best.min((p - o).length());
        }
    }
    best.is_finite().then_some(best)
}

/// Nearest point to the apex of the segment `p0 + s d`, `s ∈ [0, 1]`, restricted to the cone.
fn segment_in_cone_nearest(cone: &Cone, p0: Vec3, d: Vec3) -> Real {
    let w = p0 - cone.apex;
    // Points inside: (w + s d)·a >= cos_h |w + s d|, with (w + s d)·a >= 0.
    // Squared: ((w+sd)·a)² − cos²h |w+sd|² >= 0 → A s² + B s + C >= 0.
    let a = cone.axis;
    let c2 = cone.cos_h * cone.cos_h;
    let (wa, da) = (w.dot(a), d.dot(a));
    let qa = da * da - c2 * d.dot(d);
    let qb = 2.0 * (wa * da - c2 * w.dot(d));
    let qc = wa * wa - c2 * w.dot(w);
    let inside = |s: Real| {
        let p = w + d * s;
        p.dot(a) >= 0.0 && p.dot(a) >= cone.cos_h * p.length() - 1e-5
    };
    let mut candidates = [Real::NAN; 5];
    candidates[0] = 0.0;
    candidates[1] = 1.0;
    // Unconstrained nearest point of the segment to the apex.
    let dd = d.dot(d);
    if dd > 0.0 {
        candidates[2] = (-w.dot(d) / dd).clamp(0.0, 1.0);
    }
    // Where the line crosses the cone's surface.
    if qa.abs() > 1e-12 {
        let disc = qb * qb - 4.0 * qa * qc;
        if disc >= 0.0 {
            let sq = disc.sqrt();
            candidates[3] = (-qb - sq) / (2.0 * qa);
            candidates[4] = (-qb + sq) / (2.0 * qa);
        }
    } else if qb.abs() > 1e-12 {
        candidates[3] = -qc / qb;
    }
    let mut best = Real::INFINITY;
    for s in candidates {
        if s.is_nan() || !(-1e-6..=1.0 + 1e-6).contains(&s) {
            continue;
        }
        let s = s.clamp(0.0, 1.0);
        if inside(s) {
            best = best.min((w + d * s).length());
        }
    }
    best
}

/// Ray cast against an oriented box (slab method). Returns the entry distance, `0` if the
/// origin is inside, `None` on a miss.
pub fn ray_box(origin: Vec3, dir: Vec3, b: &OrientedBox) -> Option<Real> {
    let inv = b.rotation.inverse();
    let o = inv * (origin - b.center);
    let d = inv * dir;
    let (mut t0, mut t1) = (0.0_f32, Real::INFINITY);
    for i in 0..3 {
        if d[i].abs() < 1e-12 {
            if o[i].abs() > b.half[i] {
                return None;
            }
        } else {
            let inv_d = 1.0 / d[i];
            let (mut ta, mut tb) = ((-b.half[i] - o[i]) * inv_d, (b.half[i] - o[i]) * inv_d);
            if ta > tb {
                std::mem::swap(&mut ta, &mut tb);
            }
            t0 = t0.max(ta);
            t1 = t1.min(tb);
            if t0 > t1 {
                return None;
            }
        }
    }
    Some(t0)
}

/// The floor's view of a cone from above: every point of the cone lies over this wedge (its
/// shadow), so a column over the floor that misses the wedge misses the cone. For skipping grid
/// cells: a tilted sonar's 30° cone shadows a 30-odd° wedge, a twelfth of the disc around it.
///
/// A cone of half-angle `h` whose axis rises `ε` above the floor shadows the wedge of
/// half-angle `φ`, `sin φ = sin h / cos ε`, around the axis's direction on the floor (the whole
/// floor once the cone holds the vertical). `φ` is widened by a milliradian for rounding.
#[derive(Clone, Copy, Debug)]
pub struct Wedge {
    apex: [Real; 2],
    /// Unit directions of the wedge's two edges on the floor (left, right).
    edges: [[Real; 2]; 2],
    /// The whole floor.
    full: bool,
}

impl Wedge {
    /// The shadow of the cone from `apex` along the unit `axis` whose half-angle has sine `sin_h`.
    pub fn of_cone(apex: Vec3, axis: Vec3, sin_h: Real) -> Self {
        let flat = (axis.x * axis.x + axis.y * axis.y).sqrt();
        let sin_phi = sin_h / flat.max(1e-6) + 1e-3;
        let full = sin_phi >= 1.0 || !sin_phi.is_finite();
        let dir = [axis.x / flat.max(1e-6), axis.y / flat.max(1e-6)];
        let cos_phi = (1.0 - sin_phi * sin_phi).max(0.0).sqrt();
        let turn = |s: Real| [dir[0] * cos_phi - dir[1] * s, dir[0] * s + dir[1] * cos_phi];
        Self { apex: [apex.x, apex.y], edges: [turn(sin_phi), turn(-sin_phi)], full }
    }

    /// Whether the disc of radius `r` at `(x, y)` on the floor may meet the wedge: false only
    /// if it lies wholly beyond one of the wedge's edge lines (near the apex it may be true of
    /// a disc that misses the wedge).
    #[inline]
    pub fn meets_disc(&self, x: Real, y: Real, r: Real) -> bool {
        let c = [x - self.apex[0], y - self.apex[1]];
        let [left, right] = self.edges;
        // Signed distances into the wedge from its edge lines.
        let into_right = right[0] * c[1] - right[1] * c[0];
        let into_left = c[0] * left[1] - c[1] * left[0];
        self.full | ((into_right >= -r) & (into_left >= -r))
    }

    /// The range of `x` on the floor where a disc of radius `r` centred between `y0` and `y1`
    /// may meet the wedge ([`Wedge::meets_disc`]), if it is bounded.
    pub fn x_range(&self, y0: Real, y1: Real, r: Real) -> (Real, Real) {
        if self.full {
            return (Real::NEG_INFINITY, Real::INFINITY);
        }
        let (ya, yb) = (y0 - self.apex[1], y1 - self.apex[1]);
        let (mut lo, mut hi) = (Real::NEG_INFINITY, Real::INFINITY);
        // `into_right = right.x y − right.y x ≥ −r`, `into_left = left.y x − left.x y ≥ −r`:
        // each bounds x on one side, loosest over the row.
        let [left, right] = self.edges;
        for (ey, ex, sign) in [(right[1], right[0], -1.0), (left[1], left[0], 1.0)] {
            if ey.abs() < 1e-6 {
                continue;
            }
            // sign · ey · x ≥ −r + sign · ex · y, for some y in the row.
            let k = sign * ey;
            let at = |y: Real| (-r + sign * ex * y) / k;
            let (a, b) = (at(ya), at(yb));
            if k > 0.0 {
                lo = lo.max(a.min(b));
            } else {
                hi = hi.min(a.max(b));
            }
        }
        (lo + self.apex[0], hi + self.apex[0])
    }

    /// The floor rectangle `[x0, y0, x1, y1]` that holds the wedge's points within `radius`
    /// of its apex.
    pub fn bounds(&self, radius: Real) -> [Real; 4] {
        let [ax, ay] = self.apex;
        if self.full {
            return [ax - radius, ay - radius, ax + radius, ay + radius];
        }
        let mut b = [ax, ay, ax, ay];
        let mut take = |d: [Real; 2]| {
            let (x, y) = (ax + radius * d[0], ay + radius * d[1]);
            b = [b[0].min(x), b[1].min(y), b[2].max(x), b[3].max(y)];
        };
        take(self.edges[0]);
        take(self.edges[1]);
        // The arc's extremes along the axes, where they lie within the wedge.
        for d in [[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]] {
            if self.meets_disc(ax + d[0], ay + d[1], 0.0) {
                take(d);
            }
        }
        b
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cone_lies_over_its_wedge_and_its_bounds() {
        let mut rng = crate::rng::Rng32::new(11, 0);
        let (mut missed, mut total) = (0, 0);
        for _ in 0..2000 {
            let mut u = || 2.0 * rng.uniform() - 1.0;
            let tilt = Quat::from_rotation_z(3.2 * u()) * Quat::from_rotation_y(1.0 * u());
            let apex = Vec3::new(5.0 * u(), 5.0 * u(), 1.0 + u());
            let cone = Cone::new(apex, tilt * Vec3::X, 15f32.to_radians());
            let wedge = Wedge::of_cone(apex, cone.axis, cone.sin_h);
            let b = wedge.bounds(7.0);
            for _ in 0..20 {
                let q = apex + Vec3::new(7.0 * u(), 7.0 * u(), 3.0 * u());
                if cone.contains(q) && (q - apex).length() <= 7.0 {
                    assert!(wedge.meets_disc(q.x, q.y, 0.0), "{q} in the cone, not over its wedge");
                    assert!(b[0] <= q.x && q.x <= b[2] && b[1] <= q.y && q.y <= b[3], "{q} outside {b:?}");
                }
                // A disc meets the wedge when a point of it is over the cone's axis line.
                let r = 0.5 * u().abs();
                let p = q + Vec3::new(r, 0.0, 0.0);
                if cone.contains(q) {
                    assert!(wedge.meets_disc(p.x, p.y, r + 1e-4));
                }
                total += 1;
                missed += usize::from(!wedge.meets_disc(q.x, q.y, 0.1));
                if wedge.meets_disc(q.x, q.y, 0.3) {
                    let (lo, hi) = wedge.x_range(q.y - 0.2, q.y + 0.01, 0.3);
                    assert!(lo <= q.x && q.x <= hi, "{q}: x outside {lo}..{hi}");
                }
            }
        }
        assert!(missed > total / 2, "the wedge should skip most of the floor: {missed} of {total}");
    }

    const H: Real = 15.0 * std::f32::consts::PI / 180.0;

    /// Brute force: a dense fan of rays filling the cone, minimum hit distance.
    fn brute(cone: &Cone, b: &OrientedBox) -> Option<Real> {
        let e1 = cone.axis.any_orthonormal_vector();
        let e2 = cone.axis.cross(e1);
        let mut best = Real::INFINITY;
        for ri in 0..=60 {
            let th = H * ri as Real / 60.0;
            for pi in 0..360 {
                let phi = pi as Real * std::f32::consts::TAU / 360.0;
                let dir = cone.axis * th.cos() + (e1 * phi.cos() + e2 * phi.sin()) * th.sin();
                if let Some(t) = ray_box(cone.apex, dir, b) {
                    best = best.min(t);
                }
            }
        }
        best.is_finite().then_some(best)
    }

    #[test]
    fn exact_distance_matches_a_dense_fan_on_random_boxes() {
        // Deterministic pseudo-random layouts.
        let mut x: u32 = 12345;
        let mut rnd = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            (x as Real / u32::MAX as Real) * 2.0 - 1.0
        };
        let mut checked = 0;
        for _ in 0..150 {
            let cone = Cone::new(Vec3::ZERO, Vec3::X, H);
            let b = OrientedBox {
                center: Vec3::new(1.5 + rnd(), rnd() * 0.8, rnd() * 0.5),
                rotation: Quat::from_rotation_z(rnd() * 3.0) * Quat::from_rotation_x(rnd() * 0.5),
                half: Vec3::new(0.05 + rnd().abs() * 0.3, 0.05 + rnd().abs() * 0.3, 0.05 + rnd().abs() * 0.3),
            };
            let exact = cone_box_distance(&cone, &b);
            let fan = brute(&cone, &b);
            match (exact, fan) {
                (Some(e), Some(f)) => {
                    // The fan is an upper bound of the exact answer, close to it.
                    assert!(e <= f + 1e-4, "exact {e} above fan {f} for {b:?}");
                    assert!(f - e < 0.01, "exact {e} far below fan {f} for {b:?}");
                    checked += 1;
                }
                (None, None) => {}
                // A sliver the fan's rays slip past: exact sees it, the fan may not.
                (Some(_), None) => {}
                (None, Some(f)) => panic!("exact missed a box the fan hits at {f}: {b:?}"),
            }
        }
        assert!(checked > 50, "only {checked} layouts were compared");
    }

    #[test]
    fn plane_distance_inside_and_outside_the_half_angle() {
        let cone = Cone::new(Vec3::ZERO, Vec3::X, H);
        // Wall x = 1.5, perpendicular.
        assert!((cone.distance_to_plane(Vec3::X, 1.5).unwrap() - 1.5).abs() < 1e-5);
        // Wall tilted by 10° (< 15°): the perpendicular foot is inside the cone.
        let n = Vec3::new(10f32.to_radians().cos(), 10f32.to_radians().sin(), 0.0);
        let c = 1.5;
        assert!((cone.distance_to_plane(n, c).unwrap() - 1.5).abs() < 1e-5);
        // Tilted by 25°: nearest point on the cone's edge, p / cos(25° − 15°).
        let n = Vec3::new(25f32.to_radians().cos(), 25f32.to_radians().sin(), 0.0);
        let want = 1.5 / 10f32.to_radians().cos();
        assert!((cone.distance_to_plane(n, c).unwrap() - want).abs() < 1e-5);
    }
}
