//! Arena, static box obstacles and cone-aware range casting.
//!
//! Frame: the world frame has its origin at the centre of the arena floor,
//! `x` along the long side, `y` to the left, `z` up; yaw is about `+z`,
//! counter-clockwise from `+x`. The arena occupies
//! `[-W/2, W/2] x [-H/2, H/2]`.

use nalgebra::Vector2;

use crate::error::MedusaError;

/// Below this cosine a wall is treated as not visible from inside a cone
/// (the whole cone points away from or parallel to it).
const MIN_VISIBLE_COS: f64 = 1e-9;

/// The rectangular flight arena, centred at the world origin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Arena {
    width_m: f64,
    height_m: f64,
}

impl Arena {
    /// An arena of `width_m` along world `x` and `height_m` along world `y`,
    /// centred at the origin: `[-W/2, W/2] x [-H/2, H/2]`.
    ///
    /// # Errors
    /// [`MedusaError::InvalidArena`] if a side is not finite and strictly positive.
    pub fn new(width_m: f64, height_m: f64) -> Result<Self, MedusaError> {
        if !(width_m.is_finite() && height_m.is_finite() && width_m > 0.0 && height_m > 0.0) {
            return Err(MedusaError::InvalidArena { width_m, height_m });
        }
        Ok(Self { width_m, height_m })
    }

    /// Side length along world `x` (m).
    pub fn width_m(&self) -> f64 {
        self.width_m
    }

    /// Side length along world `y` (m).
    pub fn height_m(&self) -> f64 {
        self.height_m
    }

    /// Half of the width (m): the east wall is at `x = +half_width_m`.
    pub fn half_width_m(&self) -> f64 {
        0.5 * self.width_m
    }

    /// Half of the height (m): the north wall is at `y = +half_height_m`.
    pub fn half_height_m(&self) -> f64 {
        0.5 * self.height_m
    }

    /// Whether a point lies inside the arena (boundary included).
    pub fn contains(&self, pos_in_world: &Vector2<f64>) -> bool {
        pos_in_world.x.abs() <= self.half_width_m() && pos_in_world.y.abs() <= self.half_height_m()
    }

    /// The point clamped into the arena shrunk by `margin_m` on every side
    /// (the margin is reduced if the arena is too small for it).
    pub fn clamp(&self, pos_in_world: &Vector2<f64>, margin_m: f64) -> Vector2<f64> {
        let mx = margin_m.clamp(0.0, 0.5 * self.half_width_m());
        let my = margin_m.clamp(0.0, 0.5 * self.half_height_m());
        let hx = self.half_width_m() - mx;
        let hy = self.half_height_m() - my;
        Vector2::new(pos_in_world.x.clamp(-hx, hx), pos_in_world.y.clamp(-hy, hy))
    }
}

/// A static rectangular obstacle (a box seen from above), possibly yawed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoxObstacle {
    /// Centre of the rectangle in the world frame (m).
    pub centre_in_world: Vector2<f64>,
    /// Half side lengths along the box's own `x` and `y` axes (m), both > 0.
    pub half_extents_m: Vector2<f64>,
    /// Rotation of the box's `x` axis from world `+x`, counter-clockwise (rad).
    pub yaw_rad: f64,
}

impl BoxObstacle {
    /// A box with the given centre, half-extents and yaw.
    pub fn new(centre_in_world: Vector2<f64>, half_extents_m: Vector2<f64>, yaw_rad: f64) -> Self {
        Self { centre_in_world, half_extents_m, yaw_rad }
    }

    /// An axis-aligned box.
    pub fn axis_aligned(centre_in_world: Vector2<f64>, half_extents_m: Vector2<f64>) -> Self {
        Self::new(centre_in_world, half_extents_m, 0.0)
    }

    fn validate(&self, index: usize) -> Result<(), MedusaError> {
        let finite = self.centre_in_world.iter().all(|v| v.is_finite())
            && self.half_extents_m.iter().all(|v| v.is_finite())
            && self.yaw_rad.is_finite();
        if !finite {
            return Err(MedusaError::InvalidObstacle { index, reason: "non-finite centre, half-extents or yaw" });
        }
        if self.half_extents_m.x <= 0.0 || self.half_extents_m.y <= 0.0 {
            return Err(MedusaError::InvalidObstacle { index, reason: "half-extents must be > 0" });
        }
        Ok(())
    }

    /// Whether the point is inside the box grown by `margin_m` (a negative
    /// margin shrinks it).
    pub fn contains(&self, pos_in_world: &Vector2<f64>, margin_m: f64) -> bool {
        let (s, c) = self.yaw_rad.sin_cos();
        let d = pos_in_world - self.centre_in_world;
        let local_x = c * d.x + s * d.y;
        let local_y = -s * d.x + c * d.y;
        local_x.abs() <= self.half_extents_m.x + margin_m && local_y.abs() <= self.half_extents_m.y + margin_m
    }

    /// The four corners in the world frame, counter-clockwise.
    pub fn corners_in_world(&self) -> [Vector2<f64>; 4] {
        let (s, c) = self.yaw_rad.sin_cos();
        let ax = Vector2::new(c, s) * self.half_extents_m.x;
        let ay = Vector2::new(-s, c) * self.half_extents_m.y;
        let o = self.centre_in_world;
        [o + ax + ay, o - ax + ay, o - ax - ay, o + ax - ay]
    }
}

/// A straight edge of an obstacle, with its outward unit normal.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Segment {
    pub ax: f64,
    pub ay: f64,
    pub bx: f64,
    pub by: f64,
    /// Outward unit normal (pointing away from the obstacle).
    pub nx: f64,
    pub ny: f64,
}

/// Precomputed trigonometry of a sonar cone.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Cone {
    pub half_angle_rad: f64,
    pub cos_h: f64,
    pub sin_h: f64,
}

impl Cone {
    pub fn new(half_angle_rad: f64) -> Self {
        let (sin_h, cos_h) = half_angle_rad.sin_cos();
        Self { half_angle_rad, cos_h, sin_h }
    }
}

/// The static environment: the arena walls plus box obstacles.
#[derive(Debug, Clone)]
pub struct World {
    arena: Arena,
    obstacles: Vec<BoxObstacle>,
    segments: Vec<Segment>,
}

impl World {
    /// A world made of the arena and the given boxes.
    ///
    /// # Errors
    /// [`MedusaError::InvalidObstacle`] for a box with non-finite data or
    /// non-positive half-extents.
    pub fn new(arena: Arena, obstacles: Vec<BoxObstacle>) -> Result<Self, MedusaError> {
        let mut segments = Vec::with_capacity(obstacles.len() * 4);
        for (index, obstacle) in obstacles.iter().enumerate() {
            obstacle.validate(index)?;
            let corners = obstacle.corners_in_world();
            for k in 0..4 {
                let a = corners[k];
                let b = corners[(k + 1) % 4];
                let e = b - a;
                let len = e.norm();
                // Corners are counter-clockwise, so the outward normal is the
                // edge direction rotated clockwise.
                segments.push(Segment { ax: a.x, ay: a.y, bx: b.x, by: b.y, nx: e.y / len, ny: -e.x / len });
            }
        }
        Ok(Self { arena, obstacles, segments })
    }

    /// A world with no obstacles.
    pub fn empty(arena: Arena) -> Self {
        Self { arena, obstacles: Vec::new(), segments: Vec::new() }
    }

    /// The arena.
    pub fn arena(&self) -> &Arena {
        &self.arena
    }

    /// The box obstacles.
    pub fn obstacles(&self) -> &[BoxObstacle] {
        &self.obstacles
    }

    pub(crate) fn segments(&self) -> &[Segment] {
        &self.segments
    }

    /// Whether a point is in free space: inside the arena and not inside any
    /// box grown by `margin_m`.
    pub fn is_free(&self, pos_in_world: &Vector2<f64>, margin_m: f64) -> bool {
        self.arena.contains(pos_in_world) && !self.obstacles.iter().any(|o| o.contains(pos_in_world, margin_m))
    }

    /// Distance (m) from `origin_in_world` to the nearest arena wall or box
    /// point inside a cone of half-angle `cone_half_angle_rad` around the
    /// direction `direction_rad` (world frame). A half-angle of 0 gives the
    /// centre-ray distance. Returns `f64::INFINITY` if nothing is visible.
    ///
    /// This is the sonar model used everywhere in the crate: sonars report the
    /// nearest echo inside their cone, not the centre-ray distance.
    pub fn cone_range_m(&self, origin_in_world: &Vector2<f64>, direction_rad: f64, cone_half_angle_rad: f64) -> f64 {
        let (s, c) = direction_rad.sin_cos();
        let cone = Cone::new(cone_half_angle_rad.clamp(0.0, 1.5));
        self.cast(origin_in_world.x, origin_in_world.y, c, s, &cone).0
    }

    /// Cone cast with plain floats. `(c, s)` is the unit axis direction.
    /// Returns `(range_m, |d range / d yaw|)` where the derivative is taken
    /// for a rotation of the cone about its apex (m/rad).
    #[inline]
    pub(crate) fn cast(&self, ox: f64, oy: f64, c: f64, s: f64, cone: &Cone) -> (f64, f64) {
        let hw = self.arena.half_width_m();
        let hh = self.arena.half_height_m();
        // Convex room seen from inside: the nearest point of the boundary in
        // the cone is the minimum over the four wall planes of
        // p / cos(max(0, |a| - h)).
        let walls =
            [((hw - ox).max(0.0), c), ((hw + ox).max(0.0), -c), ((hh - oy).max(0.0), s), ((hh + oy).max(0.0), -s)];
        let mut best = (f64::INFINITY, 0.0);
        for (p, cos_a) in walls {
            let hit = plane_in_cone(p, cos_a, cone);
            if hit.0 < best.0 {
                best = hit;
            }
        }
        for seg in &self.segments {
            let hit = segment_in_cone(ox, oy, c, s, seg, cone);
            if hit.0 < best.0 {
                best = hit;
            }
        }
        best
    }
}

/// Nearest point in a cone on a plane at perpendicular distance `p_m` whose
/// normal (pointing away from the apex) makes an angle `a` with the cone axis,
/// given `cos_a`. Returns `(range, |d range / d a|)`.
#[inline]
fn plane_in_cone(p_m: f64, cos_a: f64, cone: &Cone) -> (f64, f64) {
    if cos_a >= cone.cos_h {
        return (p_m, 0.0);
    }
    let sin_a = (1.0 - cos_a * cos_a).max(0.0).sqrt();
    let cos_eff = cos_a * cone.cos_h + sin_a * cone.sin_h;
    if cos_eff <= MIN_VISIBLE_COS {
        return (f64::INFINITY, 0.0);
    }
    let sin_eff = sin_a * cone.cos_h - cos_a * cone.sin_h;
    let range = p_m / cos_eff;
    (range, range * sin_eff.abs() / cos_eff)
}

/// Nearest point of a segment inside a (2-D) cone.
///
/// The intersection of a segment with a convex cone (half-angle < 90°) is a
/// single interval and the distance along a segment is convex, so the minimum
/// is either the foot of the perpendicular (if inside the cone), a segment
/// endpoint inside the cone, or the crossing of a cone boundary ray.
#[inline]
fn segment_in_cone(ox: f64, oy: f64, c: f64, s: f64, seg: &Segment, cone: &Cone) -> (f64, f64) {
    let mut best = (f64::INFINITY, 0.0);
    let inside = |vx: f64, vy: f64| -> bool {
        let along = vx * c + vy * s;
        let norm = (vx * vx + vy * vy).sqrt();
        along > 0.0 && along >= norm * cone.cos_h - 1e-12
    };
    let (ax, ay) = (seg.ax - ox, seg.ay - oy);
    let (bx, by) = (seg.bx - ox, seg.by - oy);
    // Only the face seen from the outside can be the nearest echo.
    if ax * seg.nx + ay * seg.ny >= 0.0 {
        return best;
    }
    if cone.half_angle_rad > 0.0 {
        for (vx, vy) in [(ax, ay), (bx, by)] {
            if inside(vx, vy) {
                let d = (vx * vx + vy * vy).sqrt();
                if d < best.0 {
                    best = (d, 0.0);
                }
            }
        }
        // Foot of the perpendicular from the apex.
        let (ex, ey) = (bx - ax, by - ay);
        let len2 = ex * ex + ey * ey;
        if len2 > 0.0 {
            let t = -(ax * ex + ay * ey) / len2;
            if (0.0..=1.0).contains(&t) {
                let (fx, fy) = (ax + t * ex, ay + t * ey);
                if inside(fx, fy) {
                    let d = (fx * fx + fy * fy).sqrt();
                    if d < best.0 {
                        best = (d, 0.0);
                    }
                }
            }
        }
        for sign in [1.0, -1.0] {
            let rc = c * cone.cos_h - sign * s * cone.sin_h;
            let rs = s * cone.cos_h + sign * c * cone.sin_h;
            let hit = ray_segment(ax, ay, bx, by, rc, rs, seg);
            if hit.0 < best.0 {
                best = hit;
            }
        }
    } else {
        let hit = ray_segment(ax, ay, bx, by, c, s, seg);
        if hit.0 < best.0 {
            best = hit;
        }
    }
    best
}

/// Ray from the origin along unit `(rc, rs)` against the segment `a..b`
/// (coordinates relative to the ray origin). Returns `(t, |dt/dangle|)`.
#[inline]
fn ray_segment(ax: f64, ay: f64, bx: f64, by: f64, rc: f64, rs: f64, seg: &Segment) -> (f64, f64) {
    let (ex, ey) = (bx - ax, by - ay);
    let denom = rc * ey - rs * ex;
    if denom.abs() < 1e-12 {
        return (f64::INFINITY, 0.0);
    }
    // Solve t * r = a + u * e.
    let t = (ax * ey - ay * ex) / denom;
    let u = (ax * rs - ay * rc) / denom;
    if t <= 0.0 || !(0.0..=1.0).contains(&u) {
        return (f64::INFINITY, 0.0);
    }
    let cos_i = (rc * seg.nx + rs * seg.ny).abs();
    let sin_i = (rc * seg.ny - rs * seg.nx).abs();
    if cos_i <= MIN_VISIBLE_COS {
        return (f64::INFINITY, 0.0);
    }
    (t, t * sin_i / cos_i)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn world() -> World {
        World::empty(Arena::new(4.0, 3.0).expect("valid arena"))
    }

    #[test]
    fn centre_ray_hits_walls() {
        let w = world();
        let o = Vector2::new(0.5, 0.25);
        assert!((w.cone_range_m(&o, 0.0, 0.0) - 1.5).abs() < 1e-12);
        assert!((w.cone_range_m(&o, std::f64::consts::PI, 0.0) - 2.5).abs() < 1e-12);
        assert!((w.cone_range_m(&o, std::f64::consts::FRAC_PI_2, 0.0) - 1.25).abs() < 1e-12);
        let d = w.cone_range_m(&o, 0.3, 0.0);
        assert!((d - 1.5 / 0.3f64.cos()).abs() < 1e-12);
    }

    #[test]
    fn cone_shortens_oblique_reading() {
        let w = world();
        let o = Vector2::new(0.0, 0.0);
        let h = 15f64.to_radians();
        // Within the half-angle: perpendicular distance.
        assert!((w.cone_range_m(&o, 0.2, h) - 2.0).abs() < 1e-12);
        // Beyond: p / cos(a - h).
        let a = 0.5f64;
        let expect = (2.0 / (a - h).cos()).min(1.5 / (std::f64::consts::FRAC_PI_2 - a - h).cos());
        assert!((w.cone_range_m(&o, a, h) - expect).abs() < 1e-12);
    }

    #[test]
    fn box_is_seen_and_cone_matches_brute_force() {
        let arena = Arena::new(4.0, 3.0).expect("valid arena");
        let b = BoxObstacle::new(Vector2::new(1.0, 0.3), Vector2::new(0.2, 0.3), 0.4);
        let w = World::new(arena, vec![b]).expect("valid world");
        let h = 15f64.to_radians();
        let o = Vector2::new(-0.5, -0.2);
        for k in 0..72 {
            let dir = k as f64 * 5f64.to_radians();
            let exact = w.cone_range_m(&o, dir, h);
            let mut brute = f64::INFINITY;
            for j in 0..=400 {
                let off = -h + 2.0 * h * j as f64 / 400.0;
                brute = brute.min(w.cone_range_m(&o, dir + off, 0.0));
            }
            assert!(exact <= brute + 1e-9, "dir {dir}: {exact} > {brute}");
            assert!(brute - exact < 2e-3, "dir {dir}: {exact} vs {brute}");
        }
    }

    #[test]
    fn bad_arena_is_an_error() {
        assert!(Arena::new(0.0, 3.0).is_err());
        assert!(Arena::new(-1.0, 3.0).is_err());
        assert!(Arena::new(f64::NAN, 3.0).is_err());
        assert!(Arena::new(4.0, f64::INFINITY).is_err());
    }
}
