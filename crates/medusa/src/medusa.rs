//! Raw (single-frame) MEDUSA localisation.

use nalgebra::Vector2;

use crate::error::MedusaError;
use crate::geometry::{Cone, World};
use crate::sensor::{Observation, RangeLikelihood, SensorLayout, SensorModel, YawEstimate, validate_readings};

/// Candidates closer than this are merged into one mode (m).
pub const MODE_RADIUS_M: f64 = 0.15;
/// A second mode holding at least this fraction of the top mode's
/// probability makes the answer [`MedusaResult::ambiguous`].
pub const AMBIGUITY_RATIO: f64 = 0.25;
/// Spread (per-axis standard deviation, m) at which the spread factor of the
/// confidence falls to `exp(-1)` (for a circular spread), for raw MEDUSA's confidence and the
/// filter's alike.
pub const CONFIDENCE_SPREAD_M: f64 = 0.1;
/// Per-sensor geometric-mean fit at or above which the fit does not reduce
/// the confidence.
pub(crate) const FIT_GOOD: f64 = 0.3;
/// Radius around the best candidate over which the local spread of the
/// candidates is measured for the confidence (m).
const LOCAL_RADIUS_M: f64 = 0.5;
/// Hard cap on the number of scored candidates (keeps the cost bounded with
/// many obstacles; the cut is deterministic).
pub const MAX_CANDIDATES: usize = 4096;
/// Candidates outside the arena by less than this are clamped back in (m);
/// farther ones are dropped.
const OUTSIDE_TOLERANCE_M: f64 = 0.2;
/// Candidates may penetrate a box by this much before being dropped (m).
const BOX_TOLERANCE_M: f64 = 0.05;
/// Constraints whose line normals are closer to parallel than this
/// (|sin| of the angle between them) are not intersected.
const MIN_CROSSING_SIN: f64 = 0.3;
/// Assignments of a reading to a wall seen at a grazing angle (effective
/// cosine below this) are skipped.
const MIN_ASSIGNMENT_COS: f64 = 0.1;
/// A direction constrained worse than this (1-sigma, m) by the in-range
/// readings counts as unobservable.
const WEAK_DIRECTION_SIGMA_M: f64 = 0.5;
/// Spacing of fallback samples for under-determined cases (m).
const FALLBACK_SPACING_M: f64 = 0.1;
/// Bound on fallback samples per line (each way) and per grid axis.
const FALLBACK_MAX_STEPS: i64 = 100;

/// Precomputed per-sensor constants.
#[derive(Debug, Clone, Copy)]
pub(crate) struct SensorTrig {
    pub cos_a: f64,
    pub sin_a: f64,
    pub off_x: f64,
    pub off_y: f64,
    pub max_range_m: f64,
}

/// One candidate position with its score.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    /// Candidate position of the body centre in the world frame (m).
    pub pos_in_world: Vector2<f64>,
    /// ln p(readings | position, yaw) under the sensor model.
    pub log_likelihood: f64,
    /// Likelihood normalised over the whole candidate set, in [0, 1].
    pub probability: f64,
}

/// A cluster of nearby candidates (within [`MODE_RADIUS_M`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mode {
    /// Position of the best candidate of the cluster (m).
    pub pos_in_world: Vector2<f64>,
    /// Log-likelihood of that candidate.
    pub log_likelihood: f64,
    /// Summed normalised probability of the cluster's candidates, in [0, 1].
    pub probability: f64,
    /// Number of candidates in the cluster.
    pub candidate_count: usize,
}

/// Output of one raw MEDUSA localisation.
#[derive(Debug, Clone, PartialEq)]
pub struct MedusaResult {
    /// The highest-likelihood candidate (the original MEDUSA answer).
    pub best: Candidate,
    /// `best` polished by a few Gauss-Newton steps using all in-range
    /// readings (not part of the original method; usually more precise).
    pub refined: Candidate,
    /// All scored candidates, by decreasing likelihood (ties: by position).
    pub candidates: Vec<Candidate>,
    /// Clusters of candidates, by decreasing probability.
    pub modes: Vec<Mode>,
    /// True if another mode is nearly as probable as the top one, or the
    /// readings do not determine both coordinates.
    pub ambiguous: bool,
    /// True if fewer than two non-parallel wall constraints were available,
    /// so candidates were sampled along lines or over a grid.
    pub underdetermined: bool,
    /// Confidence in `best`, in [0, 1]: probability of its mode, times a
    /// factor falling with the spread of the candidates around it (a band
    /// of equally likely positions is not a fix), times a goodness-of-fit
    /// factor (per-sensor geometric-mean likelihood relative to a perfect
    /// fit, saturating at 0.3).
    pub confidence: f64,
}

/// A linear constraint `m . pos = k` from assigning a reading to a line.
#[derive(Debug, Clone, Copy)]
struct Constraint {
    mx: f64,
    my: f64,
    k: f64,
    sensor: usize,
}

/// The MEDUSA localiser: a world, a sensor layout and a sensor model.
#[derive(Debug, Clone)]
pub struct Medusa {
    world: World,
    layout: SensorLayout,
    model: SensorModel,
    lik: RangeLikelihood,
    cone: Cone,
    trig: Vec<SensorTrig>,
}

impl Medusa {
    /// A localiser for the given world, sensors and sensor model.
    ///
    /// # Errors
    /// [`MedusaError::InvalidParameter`] if the sensor model is invalid.
    pub fn new(world: World, layout: SensorLayout, model: SensorModel) -> Result<Self, MedusaError> {
        model.validate()?;
        let trig = layout
            .sensors()
            .iter()
            .map(|s| SensorTrig {
                cos_a: s.angle_in_body_rad.cos(),
                sin_a: s.angle_in_body_rad.sin(),
                off_x: s.offset_in_body_m.x,
                off_y: s.offset_in_body_m.y,
                max_range_m: s.max_range_m,
            })
            .collect();
        Ok(Self {
            lik: RangeLikelihood::new(&model),
            cone: Cone::new(model.cone_half_angle_rad),
            world,
            layout,
            model,
            trig,
        })
    }

    /// The world (arena and obstacles).
    pub fn world(&self) -> &World {
        &self.world
    }

    /// The sensor layout.
    pub fn layout(&self) -> &SensorLayout {
        &self.layout
    }

    /// The sensor model.
    pub fn model(&self) -> &SensorModel {
        &self.model
    }

    /// Noise-free true ranges (m) every sensor would see with the body at
    /// `pos_in_world` and yaw `yaw_rad`: the nearest arena wall or box point
    /// inside each sensor's cone. May exceed the max range (then the sensor
    /// would report "out of range"), or be infinite.
    pub fn predict_ranges_m(&self, pos_in_world: &Vector2<f64>, yaw_rad: f64) -> Vec<f64> {
        let (sy, cy) = yaw_rad.sin_cos();
        (0..self.trig.len()).map(|j| self.cast_sensor(j, pos_in_world.x, pos_in_world.y, cy, sy).0).collect()
    }

    /// Cast sensor `j` with the body at `(x, y)` and yaw given by `(cy, sy)`.
    /// Returns `(range_m, |d range / d yaw|)`.
    #[inline]
    pub(crate) fn cast_sensor(&self, j: usize, x: f64, y: f64, cy: f64, sy: f64) -> (f64, f64) {
        let t = &self.trig[j];
        let c = cy * t.cos_a - sy * t.sin_a;
        let s = sy * t.cos_a + cy * t.sin_a;
        let ox = x + cy * t.off_x - sy * t.off_y;
        let oy = y + sy * t.off_x + cy * t.off_y;
        self.world.cast(ox, oy, c, s, &self.cone)
    }

    /// `(ln p(readings | pose), ln fit)` for validated observations; yaw
    /// given by its cosine/sine and white-noise sigma.
    #[inline]
    pub(crate) fn score(
        &self,
        x: f64,
        y: f64,
        cy: f64,
        sy: f64,
        yaw_sigma_rad: f64,
        obs: &[Observation],
    ) -> (f64, f64) {
        let var_yaw = yaw_sigma_rad * yaw_sigma_rad;
        let mut ln_p = 0.0;
        let mut ln_fit = 0.0;
        for (j, &o) in obs.iter().enumerate() {
            let (range, dr_dyaw) = self.cast_sensor(j, x, y, cy, sy);
            let (a, b) = self.lik.eval(o, range, self.trig[j].max_range_m, dr_dyaw * dr_dyaw * var_yaw);
            ln_p += a;
            ln_fit += b;
        }
        (ln_p, ln_fit)
    }

    /// ln p(readings | position, yaw) under the sensor model.
    ///
    /// # Errors
    /// Invalid yaw or readings (see [`MedusaError`]).
    pub fn log_likelihood(
        &self,
        pos_in_world: &Vector2<f64>,
        yaw: YawEstimate,
        readings_m: &[Option<f64>],
    ) -> Result<f64, MedusaError> {
        yaw.validate()?;
        let obs = validate_readings(&self.layout, readings_m)?;
        let (sy, cy) = yaw.yaw_rad.sin_cos();
        Ok(self.score(pos_in_world.x, pos_in_world.y, cy, sy, yaw.sigma_rad, &obs).0)
    }

    /// Raw MEDUSA: generate candidates from every sensor-to-line assignment,
    /// score them all against every reading and return the best.
    ///
    /// # Errors
    /// Invalid yaw or readings (NaN, negative, wrong count).
    pub fn locate(&self, yaw: YawEstimate, readings_m: &[Option<f64>]) -> Result<MedusaResult, MedusaError> {
        yaw.validate()?;
        let obs = validate_readings(&self.layout, readings_m)?;
        Ok(self.locate_obs(yaw, &obs))
    }

    pub(crate) fn locate_obs(&self, yaw: YawEstimate, obs: &[Observation]) -> MedusaResult {
        let (sy, cy) = yaw.yaw_rad.sin_cos();
        let constraints = self.constraints(cy, sy, obs);
        let mut points = self.intersect(&constraints);
        let mut underdetermined = points.is_empty();
        if underdetermined {
            points = self.fallback_points(&constraints);
        }
        let mut candidates = self.scored(points, cy, sy, yaw.sigma_rad, obs);
        let mut best = self.first_or_centre(&candidates, cy, sy, yaw.sigma_rad, obs);
        let mut refined = self.refine(best, cy, sy, yaw.sigma_rad, obs);

        // Observability check: if the in-range readings leave a direction
        // unconstrained at the answer (e.g. two opposite sonars), the
        // candidate set from line crossings does not represent the band of
        // equally good positions. Sample the band explicitly.
        if !underdetermined && let Some(dir) = self.weak_direction(&refined.pos_in_world, cy, sy, yaw.sigma_rad, obs) {
            underdetermined = true;
            let mut extra: Vec<Vector2<f64>> = candidates.iter().map(|c| c.pos_in_world).collect();
            extra.extend(self.line_samples(&refined.pos_in_world, &dir));
            candidates = self.scored(extra, cy, sy, yaw.sigma_rad, obs);
            best = self.first_or_centre(&candidates, cy, sy, yaw.sigma_rad, obs);
            refined = self.refine(best, cy, sy, yaw.sigma_rad, obs);
        }

        let modes = cluster(&candidates);
        let top_mass = modes.first().map_or(1.0, |m| m.probability);
        let second_mass = modes.get(1).map_or(0.0, |m| m.probability);
        let ambiguous = underdetermined || second_mass >= AMBIGUITY_RATIO * top_mass;
        let best_mode_mass = modes
            .iter()
            .find(|m| (m.pos_in_world - best.pos_in_world).norm() <= MODE_RADIUS_M)
            .map_or(0.0, |m| m.probability);
        let (_, ln_fit) = self.score(refined.pos_in_world.x, refined.pos_in_world.y, cy, sy, yaw.sigma_rad, obs);
        let fit = (ln_fit / obs.len().max(1) as f64).exp();
        let spread = local_spread_factor(&candidates, &best.pos_in_world);
        let confidence = sanitize_unit(best_mode_mass * spread * (fit / FIT_GOOD).min(1.0));

        MedusaResult { best, refined, candidates, modes, ambiguous, underdetermined, confidence }
    }

    /// Dedup, cap, score, sort (by decreasing likelihood, ties by position)
    /// and normalise candidate points.
    fn scored(
        &self,
        mut points: Vec<Vector2<f64>>,
        cy: f64,
        sy: f64,
        yaw_sigma_rad: f64,
        obs: &[Observation],
    ) -> Vec<Candidate> {
        dedup_points(&mut points);
        points.truncate(MAX_CANDIDATES);
        let mut candidates: Vec<Candidate> = points
            .iter()
            .map(|p| Candidate {
                pos_in_world: *p,
                log_likelihood: self.score(p.x, p.y, cy, sy, yaw_sigma_rad, obs).0,
                probability: 0.0,
            })
            .collect();
        candidates.sort_by(|a, b| {
            b.log_likelihood
                .total_cmp(&a.log_likelihood)
                .then(a.pos_in_world.x.total_cmp(&b.pos_in_world.x))
                .then(a.pos_in_world.y.total_cmp(&b.pos_in_world.y))
        });
        let max_ll = candidates.first().map_or(0.0, |c| c.log_likelihood);
        let mut total = 0.0;
        for c in &mut candidates {
            c.probability = (c.log_likelihood - max_ll).exp();
            total += c.probability;
        }
        if total > 0.0 && total.is_finite() {
            for c in &mut candidates {
                c.probability /= total;
            }
        }
        candidates
    }

    fn first_or_centre(
        &self,
        candidates: &[Candidate],
        cy: f64,
        sy: f64,
        yaw_sigma_rad: f64,
        obs: &[Observation],
    ) -> Candidate {
        candidates.first().copied().unwrap_or_else(|| {
            // Unreachable in practice (the fallback always yields a point),
            // but never panic: answer the arena centre.
            Candidate {
                pos_in_world: Vector2::zeros(),
                log_likelihood: self.score(0.0, 0.0, cy, sy, yaw_sigma_rad, obs).0,
                probability: 1.0,
            }
        })
    }

    /// Weighted normal equations `(J^T W J, J^T W r)` of the in-range
    /// residuals at `(x, y)`, skipping readings more than 4 sigma off.
    /// Returns `None` if fewer than one reading is usable.
    fn normal_equations(
        &self,
        x: f64,
        y: f64,
        cy: f64,
        sy: f64,
        yaw_sigma_rad: f64,
        obs: &[Observation],
    ) -> Option<([f64; 3], [f64; 2])> {
        const H: f64 = 1e-5;
        let var_yaw = yaw_sigma_rad * yaw_sigma_rad;
        let sigma2 = self.model.noise_sigma_m * self.model.noise_sigma_m;
        let (mut a11, mut a12, mut a22, mut g1, mut g2) = (0.0, 0.0, 0.0, 0.0, 0.0);
        let mut used = 0;
        for (j, &o) in obs.iter().enumerate() {
            let Observation::InRange(z) = o else { continue };
            let (r0, dr) = self.cast_sensor(j, x, y, cy, sy);
            let var = sigma2 + dr * dr * var_yaw;
            let res = z - r0;
            if !r0.is_finite() || res * res > 16.0 * var {
                continue;
            }
            let jx = (self.cast_sensor(j, x + H, y, cy, sy).0 - r0) / H;
            let jy = (self.cast_sensor(j, x, y + H, cy, sy).0 - r0) / H;
            if !(jx.is_finite() && jy.is_finite()) {
                continue;
            }
            let w = 1.0 / var;
            a11 += w * jx * jx;
            a12 += w * jx * jy;
            a22 += w * jy * jy;
            g1 += w * jx * res;
            g2 += w * jy * res;
            used += 1;
        }
        (used > 0).then_some(([a11, a12, a22], [g1, g2]))
    }

    /// Unit direction along which the in-range readings give less than
    /// [`WEAK_DIRECTION_SIGMA_M`] of precision at `pos`, if any.
    fn weak_direction(
        &self,
        pos: &Vector2<f64>,
        cy: f64,
        sy: f64,
        yaw_sigma_rad: f64,
        obs: &[Observation],
    ) -> Option<Vector2<f64>> {
        let [a11, a12, a22] =
            self.normal_equations(pos.x, pos.y, cy, sy, yaw_sigma_rad, obs).map_or([0.0; 3], |(a, _)| a);
        // Smallest eigenvalue of the symmetric 2x2 information matrix.
        let half_tr = 0.5 * (a11 + a22);
        let disc = (0.25 * (a11 - a22) * (a11 - a22) + a12 * a12).sqrt();
        let lambda_min = half_tr - disc;
        if lambda_min * WEAK_DIRECTION_SIGMA_M * WEAK_DIRECTION_SIGMA_M >= 1.0 {
            return None;
        }
        // Eigenvector of lambda_min.
        let v = if a12.abs() > 1e-12 {
            Vector2::new(a12, lambda_min - a11)
        } else if a11 <= a22 {
            Vector2::new(1.0, 0.0)
        } else {
            Vector2::new(0.0, 1.0)
        };
        let n = v.norm();
        (n > 0.0 && n.is_finite()).then(|| v / n)
    }

    /// Free-space samples along a line through `origin` with direction `dir`.
    fn line_samples(&self, origin: &Vector2<f64>, dir: &Vector2<f64>) -> Vec<Vector2<f64>> {
        let arena = self.world.arena();
        let (hw, hh) = (arena.half_width_m(), arena.half_height_m());
        let reach = (hw * hw + hh * hh).sqrt() * 2.0;
        // Bounded sample count, even for a huge arena.
        let spacing = FALLBACK_SPACING_M.max(reach / FALLBACK_MAX_STEPS as f64);
        let steps = ((reach / spacing).ceil() as i64).min(FALLBACK_MAX_STEPS);
        let mut out = Vec::new();
        for k in -steps..=steps {
            let p = origin + dir * (k as f64 * spacing);
            if p.x.abs() <= hw
                && p.y.abs() <= hh
                && let Some(q) = self.accept(p)
            {
                out.push(q);
            }
        }
        out
    }

    /// Line constraints from assigning each in-range reading to each visible
    /// line (arena walls and box faces).
    fn constraints(&self, cy: f64, sy: f64, obs: &[Observation]) -> Vec<Constraint> {
        let arena = self.world.arena();
        let hw = arena.half_width_m();
        let hh = arena.half_height_m();
        let mut out = Vec::new();
        for (j, &o) in obs.iter().enumerate() {
            let Observation::InRange(z) = o else { continue };
            let t = &self.trig[j];
            let c = cy * t.cos_a - sy * t.sin_a;
            let s = sy * t.cos_a + cy * t.sin_a;
            let offx = cy * t.off_x - sy * t.off_y;
            let offy = sy * t.off_x + cy * t.off_y;
            // (m = unit normal pointing from the sensor towards the line,
            //  c = m . any point of the line)
            let mut lines: Vec<(f64, f64, f64)> =
                vec![(1.0, 0.0, hw), (-1.0, 0.0, hw), (0.0, 1.0, hh), (0.0, -1.0, hh)];
            for seg in self.world.segments() {
                lines.push((-seg.nx, -seg.ny, -(seg.nx * seg.ax + seg.ny * seg.ay)));
            }
            for (mx, my, cl) in lines {
                let cos_a = c * mx + s * my;
                let cos_eff = if cos_a >= self.cone.cos_h {
                    1.0
                } else {
                    let sin_a = (1.0 - cos_a * cos_a).max(0.0).sqrt();
                    cos_a * self.cone.cos_h + sin_a * self.cone.sin_h
                };
                if cos_eff < MIN_ASSIGNMENT_COS {
                    continue;
                }
                let p = z * cos_eff;
                // m . (pos + off) = cl - p
                out.push(Constraint { mx, my, k: cl - p - (mx * offx + my * offy), sensor: j });
            }
        }
        out
    }

    fn accept(&self, p: Vector2<f64>) -> Option<Vector2<f64>> {
        let arena = self.world.arena();
        if !(p.x.is_finite() && p.y.is_finite()) {
            return None;
        }
        if p.x.abs() > arena.half_width_m() + OUTSIDE_TOLERANCE_M
            || p.y.abs() > arena.half_height_m() + OUTSIDE_TOLERANCE_M
        {
            return None;
        }
        let q = arena.clamp(&p, 0.0);
        if self.world.obstacles().iter().any(|o| o.contains(&q, -BOX_TOLERANCE_M)) {
            return None;
        }
        Some(q)
    }

    fn intersect(&self, constraints: &[Constraint]) -> Vec<Vector2<f64>> {
        let mut out = Vec::new();
        for (i, a) in constraints.iter().enumerate() {
            for b in &constraints[i + 1..] {
                if a.sensor == b.sensor {
                    continue;
                }
                let det = a.mx * b.my - a.my * b.mx;
                if det.abs() < MIN_CROSSING_SIN {
                    continue;
                }
                let x = (a.k * b.my - a.my * b.k) / det;
                let y = (a.mx * b.k - a.k * b.mx) / det;
                if let Some(p) = self.accept(Vector2::new(x, y)) {
                    out.push(p);
                }
            }
        }
        out
    }

    /// Candidates for under-determined cases: samples along every constraint
    /// line, or a grid over free space when there is no constraint at all.
    fn fallback_points(&self, constraints: &[Constraint]) -> Vec<Vector2<f64>> {
        let arena = self.world.arena();
        let hw = arena.half_width_m();
        let hh = arena.half_height_m();
        let mut out = Vec::new();
        for c in constraints {
            let base = Vector2::new(c.mx, c.my) * c.k;
            out.extend(self.line_samples(&base, &Vector2::new(-c.my, c.mx)));
        }
        if out.is_empty() {
            let nx = ((arena.width_m() / FALLBACK_SPACING_M).floor() as i64).min(FALLBACK_MAX_STEPS);
            let ny = ((arena.height_m() / FALLBACK_SPACING_M).floor() as i64).min(FALLBACK_MAX_STEPS);
            for ix in 0..=nx {
                for iy in 0..=ny {
                    let p = Vector2::new(
                        -hw + (ix as f64 + 0.5) * arena.width_m() / (nx as f64 + 1.0),
                        -hh + (iy as f64 + 0.5) * arena.height_m() / (ny as f64 + 1.0),
                    );
                    if let Some(q) = self.accept(p) {
                        out.push(q);
                    }
                }
            }
        }
        if out.is_empty() {
            out.push(Vector2::zeros());
        }
        out
    }

    /// A few damped Gauss-Newton steps on the in-range residuals, accepted
    /// only while the full likelihood improves.
    fn refine(&self, start: Candidate, cy: f64, sy: f64, yaw_sigma_rad: f64, obs: &[Observation]) -> Candidate {
        let mut best = start;
        let mut lambda = 1e-3;
        for _ in 0..8 {
            let (x, y) = (best.pos_in_world.x, best.pos_in_world.y);
            let Some(([a11, a12, a22], [g1, g2])) = self.normal_equations(x, y, cy, sy, yaw_sigma_rad, obs) else {
                break;
            };
            let mut improved = false;
            for _ in 0..4 {
                // Levenberg-Marquardt damping; the tiny floor keeps a
                // rank-deficient system solvable (then the step is along the
                // observable direction only).
                let b11 = a11 * (1.0 + lambda) + 1e-9;
                let b22 = a22 * (1.0 + lambda) + 1e-9;
                let det = b11 * b22 - a12 * a12;
                if !(det.is_finite() && det > 0.0) {
                    break;
                }
                let dx = (b22 * g1 - a12 * g2) / det;
                let dy = (b11 * g2 - a12 * g1) / det;
                let Some(p) = self.accept(Vector2::new(x + dx, y + dy)) else {
                    lambda *= 10.0;
                    continue;
                };
                let ll = self.score(p.x, p.y, cy, sy, yaw_sigma_rad, obs).0;
                if ll >= best.log_likelihood {
                    let step = (p - best.pos_in_world).norm();
                    best = Candidate { pos_in_world: p, log_likelihood: ll, probability: best.probability };
                    lambda = (lambda * 0.1).max(1e-6);
                    improved = step > 1e-7;
                    break;
                }
                lambda *= 10.0;
            }
            if !improved {
                break;
            }
        }
        best
    }
}

/// `exp(-trace(cov) / (2 * CONFIDENCE_SPREAD_M²))` of the probability-weighted
/// candidates within [`LOCAL_RADIUS_M`] of `centre`: low when the
/// candidates form a continuum (an unobservable direction) rather than a
/// point.
fn local_spread_factor(candidates: &[Candidate], centre: &Vector2<f64>) -> f64 {
    let (mut w, mut var) = (0.0, 0.0);
    for c in candidates {
        let d2 = (c.pos_in_world - centre).norm_squared();
        if d2 <= LOCAL_RADIUS_M * LOCAL_RADIUS_M {
            w += c.probability;
            var += c.probability * d2;
        }
    }
    if w > 0.0 { (-(var / w) / (2.0 * CONFIDENCE_SPREAD_M * CONFIDENCE_SPREAD_M)).exp() } else { 0.0 }
}

/// Clamp into [0, 1], mapping NaN to 0.
pub(crate) fn sanitize_unit(v: f64) -> f64 {
    if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) }
}

/// Remove duplicates (same position to 0.1 mm), deterministically.
fn dedup_points(points: &mut Vec<Vector2<f64>>) {
    let key = |p: &Vector2<f64>| ((p.x * 1e4).round() as i64, (p.y * 1e4).round() as i64);
    points.sort_by_key(key);
    points.dedup_by_key(|p| key(p));
}

/// Greedy clustering of candidates sorted by decreasing likelihood.
fn cluster(candidates: &[Candidate]) -> Vec<Mode> {
    let mut modes: Vec<Mode> = Vec::new();
    for c in candidates {
        match modes.iter_mut().find(|m| (m.pos_in_world - c.pos_in_world).norm() <= MODE_RADIUS_M) {
            Some(m) => {
                m.probability += c.probability;
                m.candidate_count += 1;
            }
            None => modes.push(Mode {
                pos_in_world: c.pos_in_world,
                log_likelihood: c.log_likelihood,
                probability: c.probability,
                candidate_count: 1,
            }),
        }
    }
    // Stable sort: ties keep likelihood order.
    modes.sort_by(|a, b| b.probability.total_cmp(&a.probability));
    modes
}
