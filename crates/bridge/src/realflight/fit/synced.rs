//! The synced state: what a twin kept in step with the real copter knows at a prediction's start
//! t0, from the copter's own data up to t0 and nothing after it. Pure arithmetic over a flight's
//! readings and attitude on the fit's grid; [`super`] wires it into the identification.
//!
//! The model per axis is linear in everything a twin does not know: on the grid, from
//! `(p, v)` at index `j0`, driven by `a = σ·g·tan θ + β − k·v` (β the trim as an acceleration),
//!
//! `p(e) = P + V·Bv(e − j0) + β·Bβ(e − j0) + σ·z(e)`
//!
//! with `Bv` and `Bβ` the responses to a unit initial velocity and a unit constant acceleration
//! ([`Responses`]), `z` the response to the attitude from rest ([`free_response`]), and `P`, `V`
//! what is left of the state once `z`'s own position and velocity at `j0` are taken off. So a
//! window's least squares for `P` and `V` (with β known) is a 2 × 2 solve, and projecting a
//! window's track off `{1, Bv}` leaves what β explains ([`TrimTrack`]). Each step is the
//! simulator's free-flight step, `v ← (v + a·dt) / (1 + k·dt)` with the position advanced by the
//! step's mean velocity, as [`super`]'s rollouts step.

/// The discrete model's response to a unit initial velocity (`v_*`) and to a unit constant
/// acceleration from rest (`b_*`), per grid step, for one damping.
#[derive(Clone, Debug)]
pub(super) struct Responses {
    v_pos: Vec<f64>,
    v_vel: Vec<f64>,
    b_pos: Vec<f64>,
    b_vel: Vec<f64>,
}

impl Responses {
    /// The responses over `steps` steps of `dt` with damping `k`.
    pub(super) fn of(k: f64, dt: f64, steps: usize) -> Responses {
        let damp = 1.0 / (1.0 + k * dt);
        let run = |v0: f64, a: f64| {
            let (mut pos, mut vel) = (Vec::with_capacity(steps + 1), Vec::with_capacity(steps + 1));
            let (mut p, mut v) = (0.0, v0);
            for _ in 0..=steps {
                pos.push(p);
                vel.push(v);
                let v_new = (v + a * dt) * damp;
                p += 0.5 * (v + v_new) * dt;
                v = v_new;
            }
            (pos, vel)
        };
        let (v_pos, v_vel) = run(1.0, 0.0);
        let (b_pos, b_vel) = run(0.0, 1.0);
        Responses { v_pos, v_vel, b_pos, b_vel }
    }

    /// Position after `m` steps (fractional: linear between steps) from a unit velocity.
    fn bv(&self, m: f64) -> f64 {
        lerp(&self.v_pos, m)
    }

    /// Position after `m` steps of a unit acceleration from rest.
    fn bb(&self, m: f64) -> f64 {
        lerp(&self.b_pos, m)
    }
}

/// `v` at fractional index `m` (clamped to its ends), linear between its points.
pub(super) fn lerp(v: &[f64], m: f64) -> f64 {
    let last = v.len().saturating_sub(1);
    let m = m.clamp(0.0, last as f64);
    let a = (m.floor() as usize).min(last);
    let f = m - a as f64;
    if f <= 0.0 || a == last { v[a] } else { v[a] * (1.0 - f) + v[a + 1] * f }
}

/// The response to the attitude from rest, `a = g·tan θ − k·v` (σ = +1, no trim), at each grid
/// point: (position, velocity). `drive[j]` is tan θ over step j; a NaN there restarts it from rest
/// after the step, so that it is continuous over every span without one.
pub(super) fn free_response(drive: &[f64], k: f64, dt: f64, g: f64) -> (Vec<f64>, Vec<f64>) {
    let damp = 1.0 / (1.0 + k * dt);
    let n = drive.len();
    let (mut pos, mut vel) = (Vec::with_capacity(n), Vec::with_capacity(n));
    let (mut p, mut v) = (0.0, 0.0);
    for &t in drive {
        pos.push(p);
        vel.push(v);
        if t.is_nan() {
            (p, v) = (0.0, 0.0);
            continue;
        }
        let v_new = (v + g * t * dt) * damp;
        p += 0.5 * (v + v_new) * dt;
        v = v_new;
    }
    (pos, vel)
}

/// The readings (time-ordered `(t, x)`) within `gate_m` of the median of the readings in the
/// `window_s` before each (itself left out); one with fewer than two before it is kept. What a
/// twin can gate with at the time: [`super`]'s track uses neighbours on both sides.
pub(super) fn causal_gate(v: &[(f64, f64)], gate_m: f64, window_s: f64) -> Vec<(f64, f64)> {
    let mut out = Vec::with_capacity(v.len());
    let mut before = Vec::new();
    let mut lo = 0;
    for (i, &(t, x)) in v.iter().enumerate() {
        while v[lo].0 < t - window_s {
            lo += 1;
        }
        before.clear();
        before.extend(v[lo..i].iter().map(|r| r.1));
        if super::near_median(&mut before, x, gate_m) {
            out.push((t, x));
        }
    }
    out
}

/// One axis of a flight as the synced estimator reads it.
pub(super) struct AxisData<'a> {
    /// The causally gated readings: fractional grid position and value.
    pub readings: &'a [(f64, f64)],
    /// [`free_response`]'s position at each reading.
    pub z_at: &'a [f64],
    /// [`free_response`] on the grid.
    pub z_pos: &'a [f64],
    pub z_vel: &'a [f64],
}

/// A window's least-squares sums over its readings: the basis `{1, Bv, Bβ}` and the track `y`
/// and attitude response `z` against it.
#[derive(Clone, Copy, Debug, Default)]
struct Gram {
    n: f64,
    sv: f64,
    svv: f64,
    sb: f64,
    svb: f64,
    sbb: f64,
    /// Σy, Σy·Bv, Σy·Bβ.
    y: [f64; 3],
    /// Σz, Σz·Bv, Σz·Bβ.
    z: [f64; 3],
}

impl Gram {
    /// The sums over the readings with grid position in `[j0, j1]`.
    fn over(axis: &AxisData<'_>, resp: &Responses, j0: usize, j1: usize) -> Gram {
        let (from, to) = (j0 as f64 - 1e-9, j1 as f64 + 1e-9);
        let lo = axis.readings.partition_point(|r| r.0 < from);
        let mut g = Gram::default();
        for (r, &z) in axis.readings[lo..].iter().zip(&axis.z_at[lo..]) {
            if r.0 > to {
                break;
            }
            let m = r.0 - j0 as f64;
            let (bv, bb, y) = (resp.bv(m), resp.bb(m), r.1);
            g.n += 1.0;
            g.sv += bv;
            g.svv += bv * bv;
            g.sb += bb;
            g.svb += bv * bb;
            g.sbb += bb * bb;
            g.y = [g.y[0] + y, g.y[1] + y * bv, g.y[2] + y * bb];
            g.z = [g.z[0] + z, g.z[1] + z * bv, g.z[2] + z * bb];
        }
        g
    }

    fn det(&self) -> f64 {
        self.n * self.svv - self.sv * self.sv
    }

    /// The least-squares `(P, V)` of `w ≈ P + V·Bv` from `w`'s sums `(Σw, Σw·Bv)`.
    fn solve(&self, sw: f64, swv: f64) -> [f64; 2] {
        let det = self.det();
        [(self.svv * sw - self.sv * swv) / det, (self.n * swv - self.sv * sw) / det]
    }

    /// Whether `{1, Bv}` are independent over the readings (three of them at least, spread in
    /// time).
    fn solvable(&self, min_readings: usize) -> bool {
        self.n >= min_readings.max(3) as f64 && self.det() > 1e-12 * self.n * self.svv.max(1e-12)
    }

    /// `Bβ` with `{1, Bv}` projected off, dotted with `w` projected off the same: `w`'s sums
    /// `[Σw, Σw·Bv, Σw·Bβ]`.
    fn projected(&self, w: [f64; 3]) -> f64 {
        let [p, v] = self.solve(w[0], w[1]);
        w[2] - p * self.sb - v * self.svb
    }
}

/// The trim's least-squares sums over a flight's windows, cumulated: at grid index j, over the
/// windows that end at or before it. With σ the sign, the trim (as an acceleration) at j is
/// `(ny[j] − σ·nz[j]) / d[j]`, with a prior added by [`super`].
#[derive(Clone, Debug, Default)]
pub(super) struct TrimTrack {
    pub ny: Vec<f64>,
    pub nz: Vec<f64>,
    pub d: Vec<f64>,
}

/// Windows of the track.
#[derive(Clone, Copy, Debug)]
pub(super) struct Windows {
    /// A window's length, grid steps.
    pub len: usize,
    /// A window ends every this many steps.
    pub every: usize,
    /// Readings a window needs.
    pub min_readings: usize,
}

/// The trim's sums over `n` grid points: each window of `w.len` steps ending every `w.every`
/// steps whose drive has no gap (`unknown`: the prefix count of grid steps without one) and
/// enough readings, the track projected off the window's own position and velocity.
pub(super) fn trim_track(axis: &AxisData<'_>, resp: &Responses, unknown: &[usize], n: usize, w: Windows) -> TrimTrack {
    let mut t = TrimTrack { ny: vec![0.0; n], nz: vec![0.0; n], d: vec![0.0; n] };
    let (mut ny, mut nz, mut d) = (0.0, 0.0, 0.0);
    for j in 0..n {
        if j >= w.len && (j - w.len).is_multiple_of(w.every) && unknown[j] == unknown[j - w.len] {
            let g = Gram::over(axis, resp, j - w.len, j);
            if g.solvable(w.min_readings) {
                let bb = [g.sb, g.svb, g.sbb];
                let dj = g.projected(bb);
                if dj > 0.0 {
                    ny += g.projected(g.y);
                    nz += g.projected(g.z);
                    d += dj;
                }
            }
        }
        (t.ny[j], t.nz[j], t.d[j]) = (ny, nz, d);
    }
    t
}

/// A state affine in what the fold decides, σ and β: the model from grid index `j0`,
/// `P = y[0] − σ·z[0] − β·b[0]`, `V = y[1] − σ·z[1] − β·b[1]` (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct AffineState {
    pub j0: usize,
    pub y: [f64; 2],
    pub z: [f64; 2],
    pub b: [f64; 2],
}

/// A prediction's three parts at one grid index: it is `y − σ·z + β·b`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct Terms {
    pub y: f64,
    pub z: f64,
    pub b: f64,
}

impl Terms {
    pub(super) fn at(&self, sigma: f64, beta: f64) -> f64 {
        self.y - sigma * self.z + beta * self.b
    }
}

impl AffineState {
    /// The least-squares state over the readings in grid `[j0, j1]` (`None` with too few).
    pub(super) fn fit(
        axis: &AxisData<'_>,
        resp: &Responses,
        j0: usize,
        j1: usize,
        min_readings: usize,
    ) -> Option<Self> {
        let g = Gram::over(axis, resp, j0, j1);
        if !g.solvable(min_readings) {
            return None;
        }
        Some(AffineState { j0, y: g.solve(g.y[0], g.y[1]), z: g.solve(g.z[0], g.z[1]), b: g.solve(g.sb, g.svb) })
    }

    /// The state `(p, v)` at grid index `at` (the line's, for a line through the track there).
    pub(super) fn of_line(at: usize, p: f64, v: f64, axis: &AxisData<'_>) -> Self {
        AffineState { j0: at, y: [p, v], z: [axis.z_pos[at], axis.z_vel[at]], b: [0.0; 2] }
    }

    /// The position at grid index `e ≥ j0`.
    pub(super) fn position(&self, e: usize, axis: &AxisData<'_>, resp: &Responses) -> Terms {
        let m = (e - self.j0) as f64;
        let bv = resp.bv(m);
        Terms {
            y: self.y[0] + self.y[1] * bv,
            z: self.z[0] + self.z[1] * bv - axis.z_pos[e],
            b: resp.bb(m) - self.b[0] - self.b[1] * bv,
        }
    }

    /// The velocity at grid index `e ≥ j0`.
    pub(super) fn velocity(&self, e: usize, axis: &AxisData<'_>, resp: &Responses) -> Terms {
        let m = e - self.j0;
        let vv = resp.v_vel[m];
        Terms { y: self.y[1] * vv, z: self.z[1] * vv - axis.z_vel[e], b: resp.b_vel[m] - self.b[1] * vv }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_window_fit_recovers_the_state_and_the_trim_of_a_trajectory_the_model_flew() {
        // A trajectory of the model itself: v0 = 0.3 m/s, p0 = −0.2 m, trim 0.15 m/s², a wavy tilt,
        // k = 0.2 /s; readings every 30 ms at off-grid times.
        let (dt, k, g, sigma) = (0.05, 0.2, 9.81, -1.0);
        let n = 200;
        let drive: Vec<f64> = (0..n).map(|j| 0.03 * (j as f64 * 0.07).sin()).collect();
        let resp = Responses::of(k, dt, n);
        let (z_pos, z_vel) = free_response(&drive, k, dt, g);
        let (p0, v0, beta) = (-0.2, 0.3, 0.15);
        // The truth by stepping the model at a fine 50 ms grid with the trim.
        let truth: Vec<f64> = {
            let damp = 1.0 / (1.0 + k * dt);
            let (mut p, mut v, mut out) = (p0, v0, Vec::new());
            for &t in &drive {
                out.push(p);
                let v_new = (v + (sigma * g * t + beta) * dt) * damp;
                p += 0.5 * (v + v_new) * dt;
                v = v_new;
            }
            out
        };
        let readings: Vec<(f64, f64)> = (0..((n - 1) as f64 * dt / 0.03) as usize)
            .map(|r| r as f64 * 0.03 / dt)
            .map(|x| (x, lerp(&truth, x)))
            .collect();
        let z_at: Vec<f64> = readings.iter().map(|r| lerp(&z_pos, r.0)).collect();
        let axis = AxisData { readings: &readings, z_at: &z_at, z_pos: &z_pos, z_vel: &z_vel };
        let unknown = vec![0; n + 1];
        let w = Windows { len: 40, every: 2, min_readings: 10 };
        let trim = trim_track(&axis, &resp, &unknown, n, w);
        let j = n - 1;
        let learnt = (trim.ny[j] - sigma * trim.nz[j]) / trim.d[j];
        assert!((learnt - beta).abs() < 2e-3, "{learnt}");
        let s = AffineState::fit(&axis, &resp, 100, 120, 3).expect("a state");
        let p = s.position(120, &axis, &resp).at(sigma, beta);
        assert!((p - truth[120]).abs() < 2e-3, "{p} against {}", truth[120]);
        // The prediction 60 steps on, from the window's state: the model's own.
        let ahead = s.position(180, &axis, &resp).at(sigma, beta);
        assert!((ahead - truth[180]).abs() < 5e-3, "{ahead} against {}", truth[180]);
        let v = s.velocity(120, &axis, &resp).at(sigma, beta);
        let v_truth = (truth[121] - truth[119]) / (2.0 * dt);
        assert!((v - v_truth).abs() < 0.01, "{v} against {v_truth}");
    }

    #[test]
    fn the_causal_gate_looks_only_back() {
        let mut v: Vec<(f64, f64)> = (0..20).map(|i| (f64::from(i) * 0.05, 0.0)).collect();
        // A spike, and a step at the end that nothing after it confirms.
        v[10].1 = 0.5;
        v[18].1 = 0.4;
        v[19].1 = 0.4;
        let kept = causal_gate(&v, 0.3, 0.5);
        assert_eq!(kept.len(), 17, "{kept:?}");
        assert!(kept.iter().all(|r| r.1 == 0.0));
        // What comes later never changes what was kept before it.
        let mut later = v.clone();
        later[15].1 = 9.0;
        assert_eq!(causal_gate(&later, 0.3, 0.5)[..14], kept[..14]);
    }
}
