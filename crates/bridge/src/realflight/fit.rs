//! System identification of the horizontal flight model from real flights: how well the
//! recorded attitude, fed open loop through `a = σ·g·(tan θ(t − τ) + b) − k·v` per axis, predicts
//! where the copter's own sonars put it 1, 2 and 4 s later, from the state a twin kept in step
//! with the copter would have at the start (its own data up to then, nothing after), against
//! Twinswarm's FINken defaults, constant velocity and staying put. Pure functions over a
//! [`Series`]: no I/O, no printing.
//!
//! **Frames and signs.** Everything is in the body frame the sonars look along, FLU as the
//! simulator's (front +x, left +y), the copter flying square to the walls:
//! `x = (back − front) / 2` and `y = (right − left) / 2` ([`crate::realflight::start_pose`]'s
//! convention: moving left, the right sonar's reading grows). The attitude is the series'
//! `rpy_rad`, in the simulator's frame ([`crate::paparazzi::convert::twin_command`]: roll as
//! Paparazzi's `phi`, right side down positive; pitch the negated `theta`, nose down positive).
//! Axis x is driven by the pitch, y by the roll, each with a sign σ ([`Mapping`]): Twinswarm's
//! own model (`step.rs`, `velocity_tilt`) has `a_x = +g·tan(pitch)` and `a_y = −g·tan(roll)`
//! ([`Mapping::TWINSWARM`]). The fit does not assume it: it fits both signs per axis and keeps
//! the one that predicts better ([`Params::sign_evidence`]).
//!
//! **The level.** The current model is driven as `twinswarm validate` drives its twin: with the
//! roll and pitch the AHRS read standing on the floor before take-off taken off
//! ([`crate::realflight::ground_level`]), no trim. The identified model takes the attitude as
//! the AHRS gives it and learns its trim b (the attitude it flies level at) on line: on the
//! 16 Dec 2015 flights, the trim left after the floor level is taken off follows that level one
//! for one (the floor reading is how the copter stood, not an offset of its AHRS), so taking it
//! off only adds its spread to the trim's ([`FitOptions::level_from_floor`] does, for comparison).
//!
//! **The track** ([`sonar_track`]), the predictions' targets: per axis, a reading needs both
//! opposite sonars echoing within `[sonar_min_m, sonar_max_m)`; where [`FitOptions::sum_gate_m`]
//! is set, their sum must also be within it of the arena's side, the most frequent sum over all
//! the flights given of the same series ([`crate::realflight::derive_arena`]; a sonar on an
//! object or another copter reads short, and the "position" jumps and stays there, which no
//! median gate removes); a reading more than `gate_m` from the median of its neighbours within
//! `±gate_window_s` is an outlier. What is left is resampled to a fixed grid (`grid_dt_s`) by
//! linear interpolation between readings less than `max_gap_s` apart; NaN marks a gap.
//!
//! **The synced state at t0** (every `start_every_s` from `first_start_s` after take-off;
//! `synced.rs`): the same readings, gated as a twin can at the time (against the median of the
//! readings in the `gate_window_s` before each, [`Track::causal_m`]), and the model's trajectory
//! fitted to those of the last `state_window_s` by least squares: position and velocity at the
//! window's start free, the delay, damping, signs and the trim as at t0 given, the attitude
//! recorded over the window driving it. Its end is the state at t0. Every model starts from it:
//! the attitude-driven ones integrate the recorded attitude on (known up to t0 − τ, and recorded
//! after: the prediction is open loop in position, not in attitude), constant velocity holds its
//! velocity, stay put its position. The error is the horizontal distance to the track at
//! `t0 + H`. Alternatives ([`StateEstimate`]): the fit over a window centred on t0 (peeks half
//! of it ahead), and the line through the track's last `velocity_window_s` that `twinswarm fit`
//! used before, its state at the window's centre (the velocity a quarter second old).
//!
//! **The on-line trim b**, per axis, as an acceleration `β = σ·g·b`: each window of
//! `trim_window_s` of the readings, ending every `trim_every_s`, is fitted with its own position
//! and velocity; what β explains of the rest, summed over all the windows of the flight that
//! end by t0, is a least-squares estimate of one trim for the flight so far. Its prior is the
//! mean trim over the whole of each of the other flights (the ones the delay and damping are
//! fitted on), weighing as much as `trim_prior_s` of windows.
//!
//! **Identification**: a grid search over the delay τ (`delays_s`) and the damping k
//! (`dampings_per_s`) minimising the mean horizontal error over all horizons' predictions
//! (both signs per axis first: each axis keeps the sign whose best mean error along it is
//! lower). Leave one flight out: each flight is scored with τ, k, signs and the trim's prior
//! fitted on the others, the others' errors in the search taken with that prior too (with one
//! flight only, in sample, and the report says so). The state and the trim depend on τ and k,
//! and the predictions are affine in the trim, so each grid cell's predictions are made once and
//! each fold's prior applied to them.
//!
//! **The height loop** ([`height_stats`]): the IR from take-off + `settle_after_take_off_s` to
//! landing − `settle_before_landing_s`: mean, sd, range, and its noise (sd of the IR less its
//! centred `ir_noise_window_s` moving average).

mod synced;

use serde::Serialize;

use self::synced::{
    AffineState, AxisData, Responses, TrimTrack, Windows, causal_gate, free_response, lerp, trim_track,
};
use crate::realflight::{Flight, REAL_SONAR_MAX_M, Series, derive_arena, ground_level};

/// Gravity, m/s², as the simulator has it.
fn gravity_m_s2() -> f64 {
    f64::from(sim_core::math::GRAVITY_M_S2)
}

/// The two signs a mapping may have, in the order the sums keep them.
const SIGNS: [f64; 2] = [1.0, -1.0];

/// A synced state needs this many readings in its window, per axis.
const MIN_STATE_READINGS: usize = 5;

/// A trim window needs this many readings.
const MIN_TRIM_READINGS: usize = 10;
/// A grid of values `from, from + step, …` up to `to` (inclusive).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Range {
    /// First value.
    pub from: f64,
    /// Last value (inclusive, where the steps reach it).
    pub to: f64,
    /// Step.
    pub step: f64,
}

impl Range {
    /// Its values.
    pub fn values(&self) -> Vec<f64> {
        let n = ((self.to - self.from) / self.step + 1e-9).floor().max(0.0) as usize;
        (0..=n).map(|i| self.from + i as f64 * self.step).collect()
    }

    fn is_valid(&self) -> bool {
        self.from.is_finite() && self.to.is_finite() && self.step > 0.0 && self.to >= self.from
    }
}

/// Which way the attitude drives the position: `a_x = pitch_to_x · g·tan(pitch + b_x) − k·v_x`,
/// `a_y = roll_to_y · g·tan(roll + b_y) − k·v_y`; each sign +1 or −1.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct Mapping {
    /// Sign of the pitch's push along x (front).
    pub pitch_to_x: i8,
    /// Sign of the roll's push along y (left).
    pub roll_to_y: i8,
}

impl Mapping {
    /// Twinswarm's own: nose down (positive pitch) pushes forward, right side down (positive
    /// roll) pushes right, towards −y.
    pub const TWINSWARM: Mapping = Mapping { pitch_to_x: 1, roll_to_y: -1 };

    /// The sign of `axis` (0: x ← pitch, 1: y ← roll).
    pub fn sign(&self, axis: usize) -> f64 {
        f64::from(if axis == 0 { self.pitch_to_x } else { self.roll_to_y })
    }

    fn from_signs(s: [usize; 2]) -> Mapping {
        let sign = |i: usize| if i == 0 { 1 } else { -1 };
        Mapping { pitch_to_x: sign(s[0]), roll_to_y: sign(s[1]) }
    }

    fn sign_index(&self, axis: usize) -> usize {
        usize::from(self.sign(axis) < 0.0)
    }
}

impl std::fmt::Display for Mapping {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let s = |v: i8| if v < 0 { "−" } else { "+" };
        write!(f, "a_x = {}g·tan(pitch), a_y = {}g·tan(roll)", s(self.pitch_to_x), s(self.roll_to_y))
    }
}

/// Where the state a prediction starts from comes from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum StateEstimate {
    /// The model fitted to the readings of the last `state_window_s` up to t0, gated as they
    /// came: what a twin synced to the copter knows then (causal).
    #[default]
    Synced,
    /// The same fit over a window centred on t0: it peeks half the window into the future.
    Centred,
    /// A least-squares line through the track's last `velocity_window_s` (causal), the state at
    /// the window's centre: the estimate `twinswarm fit` used before the synced one.
    Line,
}

impl std::fmt::Display for StateEstimate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            StateEstimate::Synced => "synced",
            StateEstimate::Centred => "centred",
            StateEstimate::Line => "line",
        })
    }
}

/// Everything the identification may be told; [`FitOptions::default`] is what `twinswarm fit`
/// runs.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FitOptions {
    /// The track's grid, s (20 Hz).
    pub grid_dt_s: f64,
    /// Sonar readings below this are dropped, m (the sonar's shortest range).
    pub sonar_min_m: f64,
    /// Sonar readings at or above this are no echo, m (the firmware gates at 3 m).
    pub sonar_max_m: f64,
    /// Where set, a reading whose two opposite sonars sum to more than this away from the
    /// arena's side (their most frequent sum) is dropped, m.
    pub sum_gate_m: Option<f64>,
    /// A reading further than this from the median of its neighbours is an outlier, m.
    pub gate_m: f64,
    /// The neighbours of a reading: within this either side (the synced state: before it), s.
    pub gate_window_s: f64,
    /// Readings further apart than this leave a gap between them, s (the attitude too).
    pub max_gap_s: f64,
    /// The delays τ tried, s.
    pub delays_s: Range,
    /// The dampings k tried, 1/s.
    pub dampings_per_s: Range,
    /// The prediction horizons, s.
    pub horizons_s: Vec<f64>,
    /// A prediction starts this often, s.
    pub start_every_s: f64,
    /// The first start, after take-off, s.
    pub first_start_s: f64,
    /// Where each prediction's state comes from.
    pub state: StateEstimate,
    /// The synced state's window, s.
    pub state_window_s: f64,
    /// The line state's window (and the track a start needs before it), s.
    pub velocity_window_s: f64,
    /// The trim's windows, s.
    pub trim_window_s: f64,
    /// A trim window ends this often, s.
    pub trim_every_s: f64,
    /// The trim's prior (the other flights' mean trim) weighs as much as this much of a
    /// flight's windows, s.
    pub trim_prior_s: f64,
    /// Take the floor level off the identified model's attitude too (the current model's always
    /// is).
    pub level_from_floor: bool,
    /// The sign mapping, fixed; `None`: fitted.
    pub mapping: Option<Mapping>,
    /// The "current model"'s damping: Twinswarm's FINken default (the airframe's
    /// `linear_damping`), 1/s.
    pub current_damping_per_s: f64,
    /// The height loop's settled span begins this long after take-off, s.
    pub settle_after_take_off_s: f64,
    /// And ends this long before landing, s.
    pub settle_before_landing_s: f64,
    /// The IR noise is taken against a centred moving average this wide, s.
    pub ir_noise_window_s: f64,
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            grid_dt_s: 0.05,
            sonar_min_m: f64::from(sim_core::sensors::SonarSpec::default().min_range_m),
            sonar_max_m: f64::from(REAL_SONAR_MAX_M),
            sum_gate_m: Some(0.3),
            gate_m: 0.3,
            gate_window_s: 0.5,
            max_gap_s: 0.3,
            delays_s: Range { from: 0.0, to: 0.6, step: 0.02 },
            dampings_per_s: Range { from: 0.0, to: 0.6, step: 0.02 },
            horizons_s: vec![1.0, 2.0, 4.0],
            start_every_s: 0.5,
            first_start_s: 1.0,
            state: StateEstimate::Synced,
            state_window_s: 1.0,
            velocity_window_s: 0.5,
            trim_window_s: 3.0,
            trim_every_s: 0.1,
            trim_prior_s: 1.0,
            level_from_floor: false,
            mapping: None,
            current_damping_per_s: f64::from(sim_core::AirframeSpec::default().linear_damping),
            settle_after_take_off_s: 5.0,
            settle_before_landing_s: 1.0,
            ir_noise_window_s: 1.0,
        }
    }
}

impl FitOptions {
    fn check(&self) -> Result<(), FitError> {
        let bad = |what: &str| Err(FitError::BadOptions(what.to_owned()));
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(self.grid_dt_s) {
            return bad("grid_dt_s must be a positive number of seconds");
        }
        if !self.delays_s.is_valid() || self.delays_s.from < 0.0 {
            return bad("delays_s must be a non-negative range with a positive step");
        }
        if !self.dampings_per_s.is_valid() || self.dampings_per_s.from <= -1.0 / self.grid_dt_s {
            return bad("dampings_per_s must be a range with a positive step");
        }
        if self.horizons_s.is_empty() || !self.horizons_s.iter().all(|h| positive(*h)) {
            return bad("horizons_s must be positive numbers of seconds");
        }
        let windows = [
            self.start_every_s,
            self.velocity_window_s,
            self.state_window_s,
            self.trim_window_s,
            self.trim_every_s,
            self.max_gap_s,
            self.ir_noise_window_s,
        ];
        if !windows.into_iter().all(positive) {
            return bad(
                "start_every_s, velocity_window_s, state_window_s, trim_window_s, trim_every_s, max_gap_s and ir_noise_window_s must be positive",
            );
        }
        if !(self.first_start_s >= self.velocity_window_s && self.trim_prior_s >= 0.0) {
            return bad("first_start_s must be at least velocity_window_s, and trim_prior_s non-negative");
        }
        Ok(())
    }
}

/// One flight to identify from: a series and the span of it the copter was airborne.
#[derive(Clone, Debug)]
pub struct FlightInput<'a> {
    /// How reports name it (`15_12_16__13_55_00.data flight 3`).
    pub label: String,
    /// The log's series.
    pub series: &'a Series,
    /// The flight ([`crate::realflight::flights`]).
    pub flight: Flight,
}

/// Why the identification could not run.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    /// Nothing was given.
    #[error("no flights to identify from")]
    NoFlights,
    /// No flight had a track to predict along.
    #[error("no flight has a sonar track to predict along: {}", list(.skipped))]
    NothingToScore {
        /// Each flight and what it lacks.
        skipped: Vec<Skipped>,
    },
    /// The options contradict themselves.
    #[error("fit options: {0}")]
    BadOptions(String),
}

fn list(skipped: &[Skipped]) -> String {
    skipped.iter().map(|s| format!("{}: {}", s.label, s.reason)).collect::<Vec<_>>().join("; ")
}

/// A flight left out, and why.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Skipped {
    /// The flight.
    pub label: String,
    /// What it lacks.
    pub reason: String,
}

/// What became of one axis's sonar readings.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct AxisTrack {
    /// Readings in the flight with both opposite sonars present.
    pub readings: usize,
    /// Of those, dropped for a sonar out of `[sonar_min_m, sonar_max_m)`.
    pub out_of_range: usize,
    /// Dropped for a sum of the two sonars off the arena's side ([`FitOptions::sum_gate_m`]).
    pub off_side: usize,
    /// Dropped as outliers against their neighbours' median.
    pub outliers: usize,
    /// Dropped as outliers against the median of the readings before them (the synced state's
    /// gate).
    pub causal_outliers: usize,
    /// Kept.
    pub kept: usize,
    /// Grid points in a gap.
    pub gap_points: usize,
    /// The sum of the two sonars the side gate held them to (the arena's side less the mount
    /// offsets: the most frequent sum over the series' flights), m.
    pub side_m: Option<f64>,
}

/// A flight's sonar track on a fixed grid.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Track {
    /// Log time of the grid's first point (take-off), s.
    pub start_s: f64,
    /// The grid's step, s.
    pub dt_s: f64,
    /// Position (x, y) per grid point, m; NaN in a gap.
    #[serde(skip)]
    pub pos_m: [Vec<f64>; 2],
    /// The readings as a twin has them, per axis: (log time s, position m), within the flight,
    /// gated against the readings before each only.
    #[serde(skip)]
    pub causal_m: [Vec<(f64, f64)>; 2],
    /// What became of the readings, per axis.
    pub axes: [AxisTrack; 2],
}

impl Track {
    /// Its grid points.
    pub fn len(&self) -> usize {
        self.pos_m[0].len()
    }

    /// Whether it has none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The position `flight`'s sonars give, gated and resampled (see the module docs). `sides_m`:
/// the arena's front + back and left + right sums (e.g. [`derive_arena`]'s `sum_modes_m`);
/// `None`: the most frequent ones of this flight.
pub fn sonar_track(series: &Series, flight: &Flight, sides_m: Option<[f64; 2]>, opts: &FitOptions) -> Track {
    let dt = opts.grid_dt_s;
    let n =
        if flight.end_s >= flight.start_s { ((flight.end_s - flight.start_s) / dt).floor() as usize + 1 } else { 0 };
    let mut track =
        Track { start_s: flight.start_s, dt_s: dt, pos_m: [vec![f64::NAN; n], vec![f64::NAN; n]], ..Track::default() };
    // A margin of one gap either side, so that the grid's ends interpolate.
    let (from, to) = (flight.start_s - opts.max_gap_s, flight.end_s + opts.max_gap_s);
    let mut pairs: [Vec<(f64, f64, f64)>; 2] = Default::default();
    for s in series.sensors.iter().filter(|s| s.t_s >= from && s.t_s <= to) {
        let Some([f, r, b, l]) = s.sonar_m else { continue };
        // x = (back − front) / 2, y = (right − left) / 2: (minus, plus) per axis.
        for (axis, (minus, plus)) in [(f, b), (l, r)].into_iter().enumerate() {
            let (minus, plus) = (f64::from(minus), f64::from(plus));
            track.axes[axis].readings += 1;
            let in_range = |v: f64| v.is_finite() && v >= opts.sonar_min_m && v < opts.sonar_max_m;
            if in_range(minus) && in_range(plus) {
                pairs[axis].push((s.t_s, (plus - minus) / 2.0, plus + minus));
            } else {
                track.axes[axis].out_of_range += 1;
            }
        }
    }
    for (axis, pairs) in pairs.iter_mut().enumerate() {
        pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
        let stats = &mut track.axes[axis];
        let in_flight: Vec<f64> =
            pairs.iter().filter(|p| p.0 >= flight.start_s && p.0 <= flight.end_s).map(|p| p.2).collect();
        stats.side_m = sides_m.map(|s| s[axis]).or_else(|| mode_5cm(&in_flight));
        let on_side: Vec<(f64, f64)> = match (opts.sum_gate_m, stats.side_m) {
            (Some(gate), Some(side)) => {
                pairs.iter().filter(|p| (p.2 - side).abs() <= gate).map(|p| (p.0, p.1)).collect()
            }
            _ => pairs.iter().map(|p| (p.0, p.1)).collect(),
        };
        stats.off_side = pairs.len() - on_side.len();
        let causal = causal_gate(&on_side, opts.gate_m, opts.gate_window_s);
        stats.causal_outliers = on_side.len() - causal.len();
        track.causal_m[axis] = causal.into_iter().filter(|r| r.0 >= flight.start_s && r.0 <= flight.end_s).collect();
        let kept = gate_outliers(&on_side, opts.gate_m, opts.gate_window_s);
        stats.outliers = on_side.len() - kept.len();
        stats.kept = kept.len();
        for (i, p) in track.pos_m[axis].iter_mut().enumerate() {
            *p = interp(&kept, flight.start_s + i as f64 * dt, opts.max_gap_s);
        }
        stats.gap_points = track.pos_m[axis].iter().filter(|p| p.is_nan()).count();
    }
    track
}

/// The centre of the most populated 5 cm bin (ties: the lower).
fn mode_5cm(v: &[f64]) -> Option<f64> {
    let mut bins = std::collections::BTreeMap::<i64, usize>::new();
    for x in v {
        *bins.entry((x / 0.05).floor() as i64).or_default() += 1;
    }
    let (bin, _) = bins.iter().max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0)))?;
    Some((*bin as f64 + 0.5) * 0.05)
}

/// The readings (time-ordered) within `gate_m` of the median of their neighbours within
/// `±window_s` (themselves left out); one with fewer than two neighbours is kept.
fn gate_outliers(v: &[(f64, f64)], gate_m: f64, window_s: f64) -> Vec<(f64, f64)> {
    let mut out = Vec::with_capacity(v.len());
    let mut near = Vec::new();
    let (mut lo, mut hi) = (0, 0);
    for (i, &(t, x)) in v.iter().enumerate() {
        while v[lo].0 < t - window_s {
            lo += 1;
        }
        while hi < v.len() && v[hi].0 <= t + window_s {
            hi += 1;
        }
        near.clear();
        near.extend((lo..hi).filter(|j| *j != i).map(|j| v[j].1));
        if near_median(&mut near, x, gate_m) {
            out.push((t, x));
        }
    }
    out
}

/// Whether `x` lies within `gate_m` of the median of `others` (sorted here); with fewer than
/// two others, there is nothing to gate against and it does. The gate of [`gate_outliers`] and
/// of the synced state's causal one.
fn near_median(others: &mut [f64], x: f64, gate_m: f64) -> bool {
    if others.len() < 2 {
        return true;
    }
    others.sort_by(f64::total_cmp);
    let k = others.len() / 2;
    let median = if others.len() % 2 == 1 { others[k] } else { 0.5 * (others[k - 1] + others[k]) };
    (x - median).abs() <= gate_m
}

/// `v` (time-ordered) at `t`, linear between the samples either side where they are less than
/// `max_gap_s` apart; NaN otherwise.
fn interp(v: &[(f64, f64)], t: f64, max_gap_s: f64) -> f64 {
    let j = v.partition_point(|s| s.0 <= t);
    let Some(&(ta, a)) = j.checked_sub(1).map(|i| &v[i]) else { return f64::NAN };
    if ta == t {
        return a;
    }
    let Some(&(tb, b)) = v.get(j) else { return f64::NAN };
    if tb - ta >= max_gap_s {
        return f64::NAN;
    }
    a + (b - a) * (t - ta) / (tb - ta)
}

/// The least-squares line through the non-NaN points of `pos[from..=to]` (spacing `dt`): its
/// value at index `at` and its slope; `None` with fewer than `min_points`.
fn line_fit(pos: &[f64], from: usize, to: usize, at: usize, dt: f64, min_points: usize) -> Option<(f64, f64)> {
    let (mut n, mut st, mut sp, mut stt, mut stp) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (j, p) in pos.iter().enumerate().take(to + 1).skip(from) {
        if p.is_nan() {
            continue;
        }
        let t = (j as f64 - at as f64) * dt;
        n += 1.0;
        st += t;
        sp += p;
        stt += t * t;
        stp += t * p;
    }
    let denom = n * stt - st * st;
    if n < min_points as f64 || denom <= 0.0 {
        return None;
    }
    let slope = (n * stp - st * sp) / denom;
    Some(((sp - slope * st) / n, slope))
}

/// The identified model's parameters.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Params {
    /// Attitude-to-position delay τ, s.
    pub delay_s: f64,
    /// Linear damping k, 1/s.
    pub damping_per_s: f64,
    /// The sign mapping.
    pub mapping: Mapping,
    /// The mean horizontal error it reached on the flights it was fitted on, m.
    pub mean_error_m: f64,
    /// Predictions it was fitted on.
    pub predictions: usize,
    /// Per axis (x ← pitch, y ← roll), the best mean error along it with each sign.
    pub sign_evidence: [SignEvidence; 2],
}

/// The best one axis's predictions reach with each sign.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SignEvidence {
    /// With σ = +1 (`None` where the mapping was fixed to −1): mean |error| along the axis, m,
    /// at its best (τ, k).
    pub plus: Option<AxisBest>,
    /// With σ = −1.
    pub minus: Option<AxisBest>,
}

/// An axis's best mean error and where on the grid.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AxisBest {
    /// Mean |error| along the axis, m.
    pub mean_error_m: f64,
    /// At this delay, s.
    pub delay_s: f64,
    /// And damping, 1/s.
    pub damping_per_s: f64,
}

/// A model's prediction errors at one horizon.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct HorizonScore {
    /// The horizon, s.
    pub horizon_s: f64,
    /// Predictions scored.
    pub n: usize,
    /// Median horizontal error, m.
    pub median_m: f64,
    /// 95th percentile, m.
    pub p95_m: f64,
}

/// One model's errors per horizon, over every scored flight.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ModelScore {
    /// Short name (`identified`).
    pub name: String,
    /// What it is.
    pub about: String,
    /// Per horizon.
    pub horizons: Vec<HorizonScore>,
}

/// The IR height over a flight's settled span.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct HeightStats {
    /// IR samples.
    pub samples: usize,
    /// Mean, m.
    pub mean_m: f64,
    /// Standard deviation, m.
    pub sd_m: f64,
    /// Lowest, m.
    pub min_m: f64,
    /// Highest, m.
    pub max_m: f64,
    /// Highest − lowest, m.
    pub range_m: f64,
    /// The IR's noise: sd of its difference from its centred moving average, m.
    pub noise_sd_m: f64,
}

/// One flight's part.
#[derive(Clone, Debug, Serialize)]
pub struct FlightFit {
    /// The flight.
    pub label: String,
    /// Its span.
    pub flight: Flight,
    /// Its track.
    pub track: Track,
    /// The roll and pitch its AHRS read on the floor before take-off, taken off its attitude
    /// (zero where the log has none from then), rad.
    pub level_rad: [f64; 2],
    /// Prediction starts with a known state.
    pub starts: usize,
    /// Predictions scored (starts × horizons with a target).
    pub predictions: usize,
    /// The parameters it was scored with (fitted on the other flights).
    pub params: Params,
    /// The on-line trim's range over its starts, per axis (x, y): [lowest, highest], rad.
    pub bias_rad: [[f64; 2]; 2],
    /// The trim's prior it was scored with (the other flights' mean), per axis, rad.
    pub trim_prior_rad: [f64; 2],
    /// Its height loop, where its settled span has IR readings.
    pub height: Option<HeightStats>,
}

/// The pooled count of what went in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Samples {
    /// Sonar readings in the scored flights, per axis.
    pub readings: [usize; 2],
    /// Of those, kept, per axis.
    pub kept: [usize; 2],
    /// Grid points.
    pub grid_points: usize,
    /// Grid points in a gap, per axis.
    pub gap_points: [usize; 2],
    /// Prediction starts.
    pub starts: usize,
}

/// What `twinswarm fit` reports.
#[derive(Clone, Debug, Serialize)]
pub struct FitReport {
    /// The scored flights.
    pub flights: Vec<FlightFit>,
    /// The flights left out, and why.
    pub skipped: Vec<Skipped>,
    /// Whether each flight was scored with parameters fitted on the others (false: one flight,
    /// in sample).
    pub leave_one_out: bool,
    /// The parameters fitted on all the scored flights at once (in sample: the identification's
    /// headline; the scores use the leave-one-out ones).
    pub all_flights: Params,
    /// Twinswarm's own sign mapping, which the current model uses.
    pub twinswarm_mapping: Mapping,
    /// Per model, per horizon.
    pub models: Vec<ModelScore>,
    /// The on-line trim's range over all starts, per axis: [lowest, highest], rad.
    pub bias_rad: [[f64; 2]; 2],
    /// What went in.
    pub samples: Samples,
    /// The height loop over every flight's settled span together.
    pub height: Option<HeightStats>,
    /// The options it ran with.
    pub options: FitOptions,
}

/// The models scored, in the report's order.
pub const MODELS: [(&str, &str); 5] = [
    (
        "current",
        "Twinswarm's FINken defaults: the airframe's linear damping, no delay, the floor level taken off, no trim, Twinswarm's signs",
    ),
    ("identified", "leave-one-flight-out delay, damping and signs, the trim learnt on line"),
    ("constant velocity", "the known velocity held"),
    ("stay put", "the known position held"),
    ("identified, no trim", "the identified delay, damping and signs, the floor level taken off, no trim"),
];

/// The grid everything runs on, from the options.
#[derive(Debug)]
struct Grid {
    dt: f64,
    /// Delays: the searched ones first, then 0 if it is not among them (the current model's).
    delays_s: Vec<f64>,
    searched_delays: usize,
    dampings: Vec<f64>,
    /// Grid steps of each horizon.
    horizon_steps: Vec<usize>,
    /// Half the line state's window, in grid steps.
    half: usize,
    /// The synced state's window, in grid steps.
    state_steps: usize,
    /// The trim's windows.
    trim: Windows,
    /// The longest span a response is needed over, grid steps.
    response_steps: usize,
}

impl Grid {
    fn of(opts: &FitOptions) -> Grid {
        let dt = opts.grid_dt_s;
        let steps = |s: f64| (s / dt).round().max(1.0) as usize;
        let mut delays_s = opts.delays_s.values();
        let searched_delays = delays_s.len();
        if !delays_s.iter().any(|d| d.abs() < 1e-9) {
            delays_s.push(0.0);
        }
        let half = ((opts.velocity_window_s / dt / 2.0).round() as usize).max(1);
        let horizon_steps: Vec<usize> = opts.horizons_s.iter().map(|h| steps(*h)).collect();
        let state_steps = steps(opts.state_window_s);
        let trim = Windows {
            len: steps(opts.trim_window_s),
            every: steps(opts.trim_every_s),
            min_readings: MIN_TRIM_READINGS,
        };
        let longest = horizon_steps.iter().copied().max().unwrap_or(0);
        Grid {
            dt,
            delays_s,
            searched_delays,
            dampings: opts.dampings_per_s.values(),
            response_steps: trim.len.max(state_steps.max(half) + longest) + 1,
            horizon_steps,
            half,
            state_steps,
            trim,
        }
    }

    fn delay_index(&self, delay_s: f64) -> usize {
        let d = |i: usize| (self.delays_s[i] - delay_s).abs();
        (0..self.delays_s.len()).min_by(|a, b| d(*a).total_cmp(&d(*b))).unwrap_or(0)
    }

    fn cells(&self) -> usize {
        self.searched_delays * self.dampings.len()
    }
}

/// A prediction start.
#[derive(Clone, Debug)]
struct Start {
    /// Grid index of t0.
    i: usize,
    /// Grid index of the line state's window centre.
    c: usize,
    /// The line through the track there, per axis: position and velocity at `c`.
    line: [(f64, f64); 2],
    /// The synced (or centred) state's window, grid indices.
    window: (usize, usize),
    /// Per horizon: the track at t0 + H, where it and the attitude up to it are known.
    targets: Vec<Option<[f64; 2]>>,
}

impl Start {
    /// Grid index of the state the models start from: t0, or the line's centre.
    fn state_at(&self, opts: &FitOptions) -> usize {
        if opts.state == StateEstimate::Line { self.c } else { self.i }
    }
}

/// A flight made ready: its track, readings, attitude and starts on the grid.
#[derive(Debug)]
struct Prepared {
    /// Its index among the inputs.
    input: usize,
    label: String,
    flight: Flight,
    /// The AHRS's roll and pitch on the floor, rad.
    level_rad: [f64; 2],
    track: Track,
    /// Per axis: the readings a twin has, as (fractional grid index, position m).
    readings: [Vec<(f64, f64)>; 2],
    /// Per axis (x ← pitch, y ← roll): the AHRS's angle, time-ordered (log time s, rad).
    attitude: [Vec<(f64, f64)>; 2],
    /// Per delay, per axis: tan of the identified model's angle over the step `[t_j, t_j + dt]`,
    /// taken at its middle minus the delay; NaN in an attitude gap.
    drive: Vec<[Vec<f64>; 2]>,
    /// Prefix counts of the grid steps where some delay's drive is unknown.
    unknown: Vec<usize>,
    starts: Vec<Start>,
    /// Predictions (starts × horizons with a target).
    predictions: usize,
}

impl Prepared {
    fn duration_s(&self) -> f64 {
        self.flight.end_s - self.flight.start_s
    }

    /// tan of the angle over each step, `delay_s` late, less `level` (x ← pitch, y ← roll).
    fn drive_of(&self, axis: usize, delay_s: f64, level: f64, dt: f64, max_gap_s: f64) -> Vec<f64> {
        let t = |j: usize| self.flight.start_s + (j as f64 + 0.5) * dt - delay_s;
        (0..self.track.len()).map(|j| (interp(&self.attitude[axis], t(j), max_gap_s) - level).tan()).collect()
    }
}

/// The attitude driving each axis (x ← pitch, y ← roll), time-ordered, over `[from, to]`.
fn attitude_of(series: &Series, from: f64, to: f64) -> [Vec<(f64, f64)>; 2] {
    let mut out: [Vec<(f64, f64)>; 2] = Default::default();
    for s in series.attitude.iter().filter(|s| s.t_s >= from && s.t_s <= to) {
        let Some([roll, pitch, _]) = s.rpy_rad else { continue };
        if roll.is_finite() && pitch.is_finite() {
            out[0].push((s.t_s, f64::from(pitch)));
            out[1].push((s.t_s, f64::from(roll)));
        }
    }
    for v in &mut out {
        v.sort_by(|a, b| a.0.total_cmp(&b.0));
    }
    out
}

/// Why a flight has no track to predict along, if it has none.
fn missing_sonar(track: &Track, opts: &FitOptions) -> Option<String> {
    for (axis, (name, pair)) in [("x", "front and back"), ("y", "left and right")].into_iter().enumerate() {
        if track.axes[axis].kept == 0 {
            return Some(format!(
                "no sonar readings for {name} ({pair} both echoing within {:.2}-{:.2} m{})",
                opts.sonar_min_m,
                opts.sonar_max_m,
                if track.axes[axis].readings == 0 { "; no sonar message at all" } else { "" }
            ));
        }
    }
    None
}

fn prepare(
    index: usize,
    input: &FlightInput<'_>,
    sides_m: Option<[f64; 2]>,
    opts: &FitOptions,
    grid: &Grid,
) -> Result<Prepared, String> {
    let track = sonar_track(input.series, &input.flight, sides_m, opts);
    if let Some(reason) = missing_sonar(&track, opts) {
        return Err(reason);
    }
    let f = &input.flight;
    let max_delay = grid.delays_s.iter().copied().fold(0.0, f64::max);
    let attitude = attitude_of(input.series, f.start_s - max_delay - 1.0, f.end_s + 1.0);
    if attitude[0].is_empty() {
        return Err("no attitude (AHRS_EULER_INT, ATTITUDE or FINKEN_SENSOR_MODEL) in the flight".into());
    }
    let level_rad = ground_level(input.series, f).map_or([0.0; 2], |l| l.map(f64::from));
    let (dt, n) = (grid.dt, track.len());
    let readings = track.causal_m.clone().map(|v| v.into_iter().map(|(t, x)| ((t - f.start_s) / dt, x)).collect());
    let mut p = Prepared {
        input: index,
        label: input.label.clone(),
        flight: *f,
        level_rad,
        track,
        readings,
        attitude,
        drive: Vec::new(),
        unknown: vec![0; n + 1],
        starts: Vec::new(),
        predictions: 0,
    };
    // The identified model's level: the floor's (x ← pitch, y ← roll) only where asked.
    let level = if opts.level_from_floor { [level_rad[1], level_rad[0]] } else { [0.0; 2] };
    p.drive = grid
        .delays_s
        .iter()
        .map(|&d| [0, 1].map(|axis| p.drive_of(axis, d, level[axis], dt, opts.max_gap_s)))
        .collect();
    for j in 0..n {
        let bad = p.drive.iter().any(|d| d[0][j].is_nan() || d[1][j].is_nan());
        p.unknown[j + 1] = p.unknown[j] + usize::from(bad);
    }
    p.starts = starts_of(&p, grid, opts);
    if p.starts.is_empty() {
        return Err(format!(
            "no prediction start: the sonar track never holds {:.1} s before a start with a target {:.0} s later",
            opts.velocity_window_s,
            opts.horizons_s.iter().copied().fold(f64::INFINITY, f64::min)
        ));
    }
    p.predictions = p.starts.iter().map(|s| s.targets.iter().flatten().count()).sum();
    Ok(p)
}

/// The state window of a start at `i` whose drive is known from `c` on: the last
/// `state_steps` up to t0 (or centred on it), after the last attitude gap.
fn state_window(p: &Prepared, i: usize, grid: &Grid, opts: &FitOptions) -> (usize, usize) {
    let u = &p.unknown;
    let last = p.track.len() - 1;
    let (from, to) = match opts.state {
        StateEstimate::Centred => {
            let half = grid.state_steps / 2;
            let same = u[..=last].partition_point(|&x| x <= u[i]).saturating_sub(1);
            (i.saturating_sub(half), (i + half).min(last).min(same.max(i)))
        }
        _ => (i.saturating_sub(grid.state_steps), i),
    };
    (from.max(u[..=to].partition_point(|&x| x < u[to])), to)
}

/// The readings of `axis` in the grid span `[j0, j1]`.
fn readings_in(p: &Prepared, axis: usize, (j0, j1): (usize, usize)) -> usize {
    let r = &p.readings[axis];
    let lo = r.partition_point(|x| x.0 < j0 as f64 - 1e-9);
    let hi = r.partition_point(|x| x.0 <= j1 as f64 + 1e-9);
    hi - lo
}

/// The prediction starts: where the track has a line through the `velocity_window_s` before
/// t0, the state window enough readings, and some horizon a target with the attitude known up
/// to it.
fn starts_of(p: &Prepared, grid: &Grid, opts: &FitOptions) -> Vec<Start> {
    let (dt, half, n) = (grid.dt, grid.half, p.track.len());
    let pos = &p.track.pos_m;
    let stride = ((opts.start_every_s / dt).round() as usize).max(1);
    let first = ((opts.first_start_s / dt).round() as usize).max(2 * half);
    let mut starts = Vec::new();
    for i in (first..n).step_by(stride) {
        if pos[0][i].is_nan() || pos[1][i].is_nan() {
            continue;
        }
        let c = i - half;
        let lines = [0, 1].map(|axis| line_fit(&pos[axis], c - half, c + half, c, dt, half + 1));
        let [Some(lx), Some(ly)] = lines else { continue };
        let window = state_window(p, i, grid, opts);
        let enough = (0..2).all(|axis| readings_in(p, axis, window) >= MIN_STATE_READINGS);
        if opts.state != StateEstimate::Line && !enough {
            continue;
        }
        let targets: Vec<Option<[f64; 2]>> = grid
            .horizon_steps
            .iter()
            .map(|s| {
                let end = i + s;
                let known = end < n && !pos[0][end].is_nan() && !pos[1][end].is_nan();
                (known && p.unknown[end] == p.unknown[c]).then(|| [pos[0][end], pos[1][end]])
            })
            .collect();
        if targets.iter().any(Option::is_some) {
            starts.push(Start { i, c, line: [lx, ly], window, targets });
        }
    }
    starts
}

/// One axis of one flight under one grid cell (τ, k): the attitude's response and the trim's
/// sums.
#[derive(Debug)]
struct AxisFit {
    z_pos: Vec<f64>,
    z_vel: Vec<f64>,
    z_at: Vec<f64>,
    trim: TrimTrack,
}

/// One flight under one grid cell: per axis its fit and each start's state, affine in σ and
/// the trim.
#[derive(Debug)]
struct CellFlight {
    axes: [AxisFit; 2],
    states: [Vec<Option<AffineState>>; 2],
}

impl CellFlight {
    fn of(p: &Prepared, delay: usize, k: f64, resp: &Responses, grid: &Grid, opts: &FitOptions) -> CellFlight {
        let n = p.track.len();
        let axes = [0, 1].map(|axis| {
            let (z_pos, z_vel) = free_response(&p.drive[delay][axis], k, grid.dt, gravity_m_s2());
            let z_at: Vec<f64> = p.readings[axis].iter().map(|r| lerp(&z_pos, r.0)).collect();
            let data = AxisData { readings: &p.readings[axis], z_at: &z_at, z_pos: &z_pos, z_vel: &z_vel };
            let trim = trim_track(&data, resp, &p.unknown, n, grid.trim);
            AxisFit { z_pos, z_vel, z_at, trim }
        });
        let states = [0, 1].map(|axis| {
            let data = CellFlight::data_of(&axes[axis], &p.readings[axis]);
            p.starts
                .iter()
                .map(|st| match opts.state {
                    StateEstimate::Line => Some(AffineState::of_line(st.c, st.line[axis].0, st.line[axis].1, &data)),
                    _ => AffineState::fit(&data, resp, st.window.0, st.window.1, MIN_STATE_READINGS),
                })
                .collect()
        });
        CellFlight { axes, states }
    }

    fn data_of<'a>(a: &'a AxisFit, readings: &'a [(f64, f64)]) -> AxisData<'a> {
        AxisData { readings, z_at: &a.z_at, z_pos: &a.z_pos, z_vel: &a.z_vel }
    }

    fn data<'a>(&'a self, p: &'a Prepared, axis: usize) -> AxisData<'a> {
        CellFlight::data_of(&self.axes[axis], &p.readings[axis])
    }

    /// The trim's sums (ny, nz, d) at grid index `j`.
    fn trim_at(&self, axis: usize, j: usize) -> [f64; 3] {
        let t = &self.axes[axis].trim;
        [t.ny[j], t.nz[j], t.d[j]]
    }

    /// Over the whole flight.
    fn trim_end(&self, axis: usize) -> [f64; 3] {
        self.trim_at(axis, self.axes[axis].trim.d.len() - 1)
    }
}

/// The trim's prior a fold gives: per axis and sign, the mean over its training flights of each
/// one's whole-flight trim (as an acceleration), and the weight of `trim_prior_s` of windows.
#[derive(Clone, Copy, Debug, Default)]
struct Prior {
    beta: [[f64; 2]; 2],
    weight: [f64; 2],
}

impl Prior {
    fn of(cells: &[CellFlight], prepared: &[Prepared], training: &[usize], opts: &FitOptions) -> Prior {
        let mut prior = Prior::default();
        for axis in 0..2 {
            let ends: Vec<([f64; 3], f64)> =
                training.iter().map(|&g| (cells[g].trim_end(axis), prepared[g].duration_s())).collect();
            let known: Vec<&[f64; 3]> = ends.iter().map(|e| &e.0).filter(|e| e[2] > 0.0).collect();
            for (si, sigma) in SIGNS.iter().enumerate() {
                let sum: f64 = known.iter().map(|e| (e[0] - sigma * e[1]) / e[2]).sum();
                prior.beta[axis][si] = if known.is_empty() { 0.0 } else { sum / known.len() as f64 };
            }
            let rate: f64 = ends.iter().map(|(e, dur)| if *dur > 0.0 { e[2] / dur } else { 0.0 }).sum();
            prior.weight[axis] = if ends.is_empty() { 0.0 } else { opts.trim_prior_s * rate / ends.len() as f64 };
        }
        prior
    }

    /// The trim (an acceleration, m/s²) at a start whose sums so far are `sums`, for the sign
    /// `si` of `axis`.
    fn trim(&self, axis: usize, si: usize, sums: [f64; 3]) -> f64 {
        let (w, d) = (self.weight[axis], sums[2]);
        if w + d <= 0.0 {
            return 0.0;
        }
        (sums[0] - SIGNS[si] * sums[1] + w * self.beta[axis][si]) / (d + w)
    }
}

/// The trim as an attitude offset, rad.
fn trim_rad(beta: f64, sigma: f64) -> f64 {
    (beta / (sigma * gravity_m_s2())).atan()
}

/// One axis's attitude-driven model for one rollout.
#[derive(Clone, Copy, Debug)]
struct AxisModel {
    sigma: f64,
    damping_per_s: f64,
    /// The trim, as an acceleration, m/s².
    bias_m_s2: f64,
}

/// The position after each of `steps` (ascending) grid steps of `a = σ·g·tan θ + β − k·v` from
/// `(p, v)` at grid index `from`: the velocity stepped as the simulator steps its free flight,
/// `v ← (v + a·dt) / (1 + k·dt)` (the angle taken at the step's middle), the position with the
/// step's mean velocity (the simulator's 5 ms substeps make its own position that exact).
#[allow(clippy::too_many_arguments)]
fn roll(drive: &[f64], from: usize, p: f64, v: f64, m: AxisModel, dt: f64, steps: &[usize], out: &mut [f64]) {
    let g = gravity_m_s2();
    let damp = 1.0 / (1.0 + m.damping_per_s * dt);
    let (mut p, mut v) = (p, v);
    let mut h = 0;
    let mut n = 0;
    let last = steps.last().copied().unwrap_or(0);
    while h < steps.len() && steps[h] == 0 {
        out[h] = p;
        h += 1;
    }
    for &t in drive.iter().skip(from).take(last) {
        let a = m.sigma * g * t + m.bias_m_s2;
        let v_new = (v + a * dt) * damp;
        p += 0.5 * (v + v_new) * dt;
        v = v_new;
        n += 1;
        while h < steps.len() && steps[h] == n {
            out[h] = p;
            h += 1;
        }
    }
    // Steps past the drive's end.
    for o in out.iter_mut().skip(h) {
        *o = f64::NAN;
    }
}

/// One flight's summed errors over the grid, under one fold's trim prior.
#[derive(Clone, Debug)]
struct GridSums {
    /// Per cell (delay × damping): per axis and sign, the summed |error| along the axis.
    axis: Vec<[[f64; 2]; 2]>,
    /// Per cell: per (x sign, y sign), the summed horizontal error.
    horizontal: Vec<[[f64; 2]; 2]>,
    predictions: usize,
}

/// Which signs each axis may take.
fn allowed_signs(opts: &FitOptions) -> [[bool; 2]; 2] {
    match opts.mapping {
        None => [[true; 2]; 2],
        Some(m) => [0, 1].map(|axis| [0, 1].map(|s| m.sign_index(axis) == s)),
    }
}

/// The flights a fold fits on: all but `fold`, or all of them for the fold past the last.
fn training(fold: usize, flights: usize) -> Vec<usize> {
    (0..flights).filter(|g| *g != fold).collect()
}

/// Adds flight `p`'s errors under `prior` at grid cell `cell` to `sums`.
#[allow(clippy::too_many_arguments)]
fn add_errors(
    p: &Prepared,
    cf: &CellFlight,
    prior: &Prior,
    resp: &Responses,
    allowed: &[[bool; 2]; 2],
    horizon_steps: &[usize],
    sums: &mut GridSums,
    cell: usize,
) {
    let (axis_sum, horizontal) = (&mut sums.axis[cell], &mut sums.horizontal[cell]);
    let data = [cf.data(p, 0), cf.data(p, 1)];
    for (s, st) in p.starts.iter().enumerate() {
        let states = [cf.states[0][s], cf.states[1][s]];
        let [Some(sx), Some(sy)] = states else { continue };
        let trims = [0, 1].map(|axis| [0, 1].map(|si| prior.trim(axis, si, cf.trim_at(axis, st.i))));
        for (h, target) in st.targets.iter().enumerate() {
            let Some(target) = target else { continue };
            let e_at = st.i + horizon_steps[h];
            let mut e = [[0.0; 2]; 2];
            for (axis, state) in [sx, sy].iter().enumerate() {
                let terms = state.position(e_at, &data[axis], resp);
                for si in (0..2).filter(|si| allowed[axis][*si]) {
                    e[axis][si] = terms.at(SIGNS[si], trims[axis][si]) - target[axis];
                    axis_sum[axis][si] += e[axis][si].abs();
                }
            }
            for sx in (0..2).filter(|s| allowed[0][*s]) {
                for sy in (0..2).filter(|s| allowed[1][*s]) {
                    horizontal[sx][sy] += e[0][sx].hypot(e[1][sy]);
                }
            }
        }
    }
}

/// Every flight's errors over the grid, per fold: `[fold][flight]`, the last fold all the
/// flights (no fold is fitted on a single flight's others when there is one flight only).
fn grid_sums(prepared: &[Prepared], grid: &Grid, allowed: &[[bool; 2]; 2], opts: &FitOptions) -> Vec<Vec<GridSums>> {
    let nf = prepared.len();
    let cells = grid.cells();
    let empty = |p: &Prepared| GridSums {
        axis: vec![[[0.0; 2]; 2]; cells],
        horizontal: vec![[[0.0; 2]; 2]; cells],
        predictions: p.predictions,
    };
    let mut sums: Vec<Vec<GridSums>> = (0..=nf).map(|_| prepared.iter().map(empty).collect()).collect();
    for (ki, &k) in grid.dampings.iter().enumerate() {
        let resp = Responses::of(k, grid.dt, grid.response_steps);
        for ti in 0..grid.searched_delays {
            let cell = ti * grid.dampings.len() + ki;
            let cfs: Vec<CellFlight> = prepared.iter().map(|p| CellFlight::of(p, ti, k, &resp, grid, opts)).collect();
            for (fold, fold_sums) in sums.iter_mut().enumerate() {
                if fold < nf && nf < 2 {
                    continue;
                }
                let train = training(fold, nf);
                let prior = Prior::of(&cfs, prepared, &train, opts);
                for &g in &train {
                    let s = &mut fold_sums[g];
                    add_errors(&prepared[g], &cfs[g], &prior, &resp, allowed, &grid.horizon_steps, s, cell);
                }
            }
        }
    }
    sums
}

/// The parameters the flights `sums` favour: per axis the sign whose best mean error along it is
/// lower, then the (τ, k) with the lowest mean horizontal error under those signs.
fn select(sums: &[&GridSums], grid: &Grid, allowed: &[[bool; 2]; 2]) -> Option<Params> {
    let predictions: usize = sums.iter().map(|s| s.predictions).sum();
    if predictions == 0 {
        return None;
    }
    let n = predictions as f64;
    let at = |cell: usize| (grid.delays_s[cell / grid.dampings.len()], grid.dampings[cell % grid.dampings.len()]);
    let best_cell = |err: &dyn Fn(usize) -> f64| {
        (0..grid.cells()).map(|c| (c, err(c))).min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)))
    };
    let mut signs = [0usize; 2];
    let mut evidence: [SignEvidence; 2] = [0, 1].map(|_| SignEvidence { plus: None, minus: None });
    for axis in 0..2 {
        let mut best: [Option<AxisBest>; 2] = [None, None];
        for si in (0..2).filter(|s| allowed[axis][*s]) {
            let err = |c: usize| sums.iter().map(|s| s.axis[c][axis][si]).sum::<f64>() / n;
            let (c, e) = best_cell(&err)?;
            let (delay_s, damping_per_s) = at(c);
            best[si] = Some(AxisBest { mean_error_m: e, delay_s, damping_per_s });
        }
        let score = |si: usize| best[si].map_or(f64::INFINITY, |b| b.mean_error_m);
        signs[axis] = if score(1) < score(0) { 1 } else { 0 };
        evidence[axis] = SignEvidence { plus: best[0], minus: best[1] };
    }
    let err = |c: usize| sums.iter().map(|s| s.horizontal[c][signs[0]][signs[1]]).sum::<f64>() / n;
    let (c, mean_error_m) = best_cell(&err)?;
    let (delay_s, damping_per_s) = at(c);
    Some(Params {
        delay_s,
        damping_per_s,
        mapping: Mapping::from_signs(signs),
        mean_error_m,
        predictions,
        sign_evidence: evidence,
    })
}

/// Nearest-rank quantile of sorted `v`.
fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// One flight's errors per model and horizon, and its identified model's trim range.
struct Scored {
    errors: Vec<Vec<Vec<f64>>>,
    bias_rad: [[f64; 2]; 2],
}

/// The state `(p, v)` a start's models set out from, at grid index `a`.
fn state_pv(state: &AffineState, a: usize, data: &AxisData<'_>, resp: &Responses, sigma: f64, beta: f64) -> (f64, f64) {
    (state.position(a, data, resp).at(sigma, beta), state.velocity(a, data, resp).at(sigma, beta))
}

/// Flight `p`'s predictions with `params`, its trim's prior `prior`, under the cell `cf`.
fn score_flight(
    p: &Prepared,
    cf: &CellFlight,
    prior: &Prior,
    params: &Params,
    grid: &Grid,
    opts: &FitOptions,
) -> Scored {
    let nh = grid.horizon_steps.len();
    let mut errors = vec![vec![Vec::new(); nh]; MODELS.len()];
    let mut bias_rad = [[f64::INFINITY, f64::NEG_INFINITY]; 2];
    let resp = Responses::of(params.damping_per_s, grid.dt, grid.response_steps);
    let level = [p.level_rad[1], p.level_rad[0]];
    let (dt, gap) = (grid.dt, opts.max_gap_s);
    // The floor-levelled attitude: no delay (the current model), and the identified delay.
    let levelled: [[Vec<f64>; 2]; 2] =
        [0.0, params.delay_s].map(|d| [0, 1].map(|axis| p.drive_of(axis, d, level[axis], dt, gap)));
    let mut out = vec![0.0; nh];
    for (s, st) in p.starts.iter().enumerate() {
        let [Some(sx), Some(sy)] = [cf.states[0][s], cf.states[1][s]] else { continue };
        let a = st.state_at(opts);
        let steps: Vec<usize> = grid.horizon_steps.iter().map(|h| st.i + h - a).collect();
        let last = st.targets.iter().rposition(Option::is_some).unwrap_or(0);
        // Per model, per axis, per horizon: the predicted position.
        let mut pred = vec![[vec![f64::NAN; nh], vec![f64::NAN; nh]]; MODELS.len()];
        for (axis, state) in [sx, sy].iter().enumerate() {
            let (sigma, si) = (params.mapping.sign(axis), params.mapping.sign_index(axis));
            let beta = prior.trim(axis, si, cf.trim_at(axis, st.i));
            let b = trim_rad(beta, sigma);
            bias_rad[axis] = [bias_rad[axis][0].min(b), bias_rad[axis][1].max(b)];
            let data = cf.data(p, axis);
            let (pa, va) = state_pv(state, a, &data, &resp, sigma, beta);
            for (h, e) in grid.horizon_steps.iter().enumerate().take(last + 1) {
                pred[1][axis][h] = state.position(st.i + e, &data, &resp).at(sigma, beta);
            }
            let current = AxisModel {
                sigma: Mapping::TWINSWARM.sign(axis),
                damping_per_s: opts.current_damping_per_s,
                bias_m_s2: 0.0,
            };
            let no_trim = AxisModel { sigma, damping_per_s: params.damping_per_s, bias_m_s2: 0.0 };
            for (model, drive, m) in [(0, &levelled[0][axis], current), (4, &levelled[1][axis], no_trim)] {
                roll(drive, a, pa, va, m, dt, &steps[..=last], &mut out[..=last]);
                pred[model][axis][..=last].copy_from_slice(&out[..=last]);
            }
            let p0 = pa + va * (st.i - a) as f64 * dt;
            for (h, horizon) in opts.horizons_s.iter().enumerate() {
                pred[2][axis][h] = p0 + va * horizon;
                pred[3][axis][h] = p0;
            }
        }
        for (h, target) in st.targets.iter().enumerate() {
            let Some(target) = target else { continue };
            for (model, pr) in pred.iter().enumerate() {
                errors[model][h].push((pr[0][h] - target[0]).hypot(pr[1][h] - target[1]));
            }
        }
    }
    Scored { errors, bias_rad }
}

/// Identifies the horizontal model from `inputs` and scores every model on them (see the module
/// docs).
pub fn identify(inputs: &[FlightInput<'_>], opts: &FitOptions) -> Result<FitReport, FitError> {
    opts.check()?;
    if inputs.is_empty() {
        return Err(FitError::NoFlights);
    }
    let grid = Grid::of(opts);
    let mut prepared = Vec::new();
    let mut skipped = Vec::new();
    for (index, input) in inputs.iter().enumerate() {
        // The arena's sides, from every flight given of the same series.
        let same: Vec<Flight> =
            inputs.iter().filter(|i| std::ptr::eq(i.series, input.series)).map(|i| i.flight).collect();
        let sides_m = derive_arena(input.series, &same, 0.0).map(|a| a.sum_modes_m.map(f64::from));
        match prepare(index, input, sides_m, opts, &grid) {
            Ok(p) => prepared.push(p),
            Err(reason) => skipped.push(Skipped { label: input.label.clone(), reason }),
        }
    }
    if prepared.is_empty() {
        return Err(FitError::NothingToScore { skipped });
    }
    let allowed = allowed_signs(opts);
    let sums = grid_sums(&prepared, &grid, &allowed, opts);
    let nf = prepared.len();
    let nothing = || FitError::NothingToScore { skipped: skipped.clone() };
    let all_flights = select(&sums[nf].iter().collect::<Vec<_>>(), &grid, &allowed).ok_or_else(nothing)?;
    let leave_one_out = nf >= 2;
    let nh = opts.horizons_s.len();
    let mut pooled = vec![vec![Vec::new(); nh]; MODELS.len()];
    let mut flights = Vec::new();
    let mut bias_all = [[f64::INFINITY, f64::NEG_INFINITY]; 2];
    // The height loop, per scored flight and over all of them.
    let (mut heights, mut noise) = (Vec::new(), Vec::new());
    for (f, p) in prepared.iter().enumerate() {
        let fold = if leave_one_out { f } else { nf };
        let params = if leave_one_out {
            let others: Vec<&GridSums> = training(f, nf).into_iter().map(|g| &sums[f][g]).collect();
            select(&others, &grid, &allowed).unwrap_or_else(|| all_flights.clone())
        } else {
            all_flights.clone()
        };
        let (ti, k) = (grid.delay_index(params.delay_s), params.damping_per_s);
        let resp = Responses::of(k, grid.dt, grid.response_steps);
        let cfs: Vec<CellFlight> = prepared.iter().map(|q| CellFlight::of(q, ti, k, &resp, &grid, opts)).collect();
        let prior = Prior::of(&cfs, &prepared, &training(fold, nf), opts);
        let scored = score_flight(p, &cfs[f], &prior, &params, &grid, opts);
        let input = &inputs[p.input];
        let (ir, ir_noise) = settled_ir(input.series, &input.flight, opts);
        for (model, per_h) in scored.errors.into_iter().enumerate() {
            for (h, e) in per_h.into_iter().enumerate() {
                pooled[model][h].extend(e);
            }
        }
        for (all, [lo, hi]) in bias_all.iter_mut().zip(scored.bias_rad) {
            *all = [all[0].min(lo), all[1].max(hi)];
        }
        let trim_prior_rad =
            [0, 1].map(|axis| trim_rad(prior.beta[axis][params.mapping.sign_index(axis)], params.mapping.sign(axis)));
        flights.push(FlightFit {
            label: p.label.clone(),
            flight: p.flight,
            track: p.track.clone(),
            level_rad: p.level_rad,
            starts: p.starts.len(),
            predictions: p.predictions,
            params,
            bias_rad: scored.bias_rad,
            trim_prior_rad,
            height: height_of(&ir, &ir_noise),
        });
        heights.extend(ir);
        noise.extend(ir_noise);
    }
    Ok(FitReport {
        samples: Samples::of(&flights),
        flights,
        skipped,
        leave_one_out,
        all_flights,
        twinswarm_mapping: Mapping::TWINSWARM,
        models: model_scores(pooled, opts),
        bias_rad: bias_all,
        height: height_of(&heights, &noise),
        options: opts.clone(),
    })
}

/// Each model's median and p95 per horizon from its pooled errors.
fn model_scores(pooled: Vec<Vec<Vec<f64>>>, opts: &FitOptions) -> Vec<ModelScore> {
    MODELS
        .iter()
        .zip(pooled)
        .map(|((name, about), per_h)| ModelScore {
            name: (*name).into(),
            about: (*about).into(),
            horizons: opts
                .horizons_s
                .iter()
                .zip(per_h)
                .map(|(&horizon_s, mut e)| {
                    e.sort_by(f64::total_cmp);
                    HorizonScore { horizon_s, n: e.len(), median_m: quantile(&e, 0.5), p95_m: quantile(&e, 0.95) }
                })
                .collect(),
        })
        .collect()
}

impl Samples {
    fn of(flights: &[FlightFit]) -> Samples {
        let mut samples = Samples::default();
        for f in flights {
            for axis in 0..2 {
                samples.readings[axis] += f.track.axes[axis].readings;
                samples.kept[axis] += f.track.axes[axis].kept;
                samples.gap_points[axis] += f.track.axes[axis].gap_points;
            }
            samples.grid_points += f.track.len();
            samples.starts += f.starts;
        }
        samples
    }
}
/// The IR over `flight`'s settled span (see the module docs), and each sample's difference
/// from the centred moving average.
fn settled_ir(series: &Series, flight: &Flight, opts: &FitOptions) -> (Vec<f64>, Vec<f64>) {
    let (from, to) = (flight.start_s + opts.settle_after_take_off_s, flight.end_s - opts.settle_before_landing_s);
    let z: Vec<(f64, f64)> = series
        .sensors
        .iter()
        .filter(|s| s.t_s >= from && s.t_s <= to)
        .filter_map(|s| s.ir_m.filter(|z| z.is_finite()).map(|z| (s.t_s, f64::from(z))))
        .collect();
    let w = opts.ir_noise_window_s / 2.0;
    let (mut lo, mut hi, mut sum) = (0, 0, 0.0);
    let mut diffs = Vec::with_capacity(z.len());
    for &(t, v) in &z {
        while hi < z.len() && z[hi].0 <= t + w {
            sum += z[hi].1;
            hi += 1;
        }
        while z[lo].0 < t - w {
            sum -= z[lo].1;
            lo += 1;
        }
        diffs.push(v - sum / (hi - lo) as f64);
    }
    (z.into_iter().map(|p| p.1).collect(), diffs)
}

fn height_of(values: &[f64], diffs: &[f64]) -> Option<HeightStats> {
    if values.len() < 2 {
        return None;
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let sd = |v: &[f64]| {
        let m = mean(v);
        (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
    };
    let min = values.iter().copied().fold(f64::INFINITY, f64::min);
    let max = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    Some(HeightStats {
        samples: values.len(),
        mean_m: mean(values),
        sd_m: sd(values),
        min_m: min,
        max_m: max,
        range_m: max - min,
        noise_sd_m: sd(diffs),
    })
}

/// The height loop of one flight: its IR from take-off + `settle_after_take_off_s` to landing −
/// `settle_before_landing_s`; `None` with fewer than two readings there.
pub fn height_stats(series: &Series, flight: &Flight, opts: &FitOptions) -> Option<HeightStats> {
    let (v, d) = settled_ir(series, flight, opts);
    height_of(&v, &d)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::realflight::Sample;

    /// A deterministic noise in [-1, 1].
    fn noise(k: u64) -> f64 {
        let x = k.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((x >> 33) as f64 / (1u64 << 31) as f64) * 2.0 - 1.0
    }

    /// Position, velocity and acceleration of a smooth wander, m: `sum A sin(ω t + φ)`.
    fn wander(terms: &[(f64, f64, f64)], t: f64) -> [f64; 3] {
        let mut out = [0.0; 3];
        for &(a, w, ph) in terms {
            out[0] += a * (w * t + ph).sin();
            out[1] += a * w * (w * t + ph).cos();
            out[2] -= a * w * w * (w * t + ph).sin();
        }
        out
    }

    /// The truth the synthetic flights fly.
    struct Truth {
        delay_s: f64,
        damping_per_s: f64,
        mapping: Mapping,
        /// The AHRS's trim offset per axis (x, y): the copter flies level when it reads this.
        trim_rad: [f64; 2],
    }

    /// A flight of `duration_s` whose position wanders in a 3.8 × 2.7 m arena: its sonars every
    /// 50 ms (cm, with a few mm of noise), its attitude every 20 ms being exactly what
    /// `a = σ g tan(θ(t − τ) + b) − k v` needs for that wander (so that b = −trim), its IR
    /// at 0.5 m ± 1 cm.
    fn flight_of(truth: &Truth, phase: f64, duration_s: f64, series: &mut Series) -> Flight {
        let t_start = series.sensors.last().map_or(10.0, |s| s.t_s + 20.0);
        let xs = [(0.35, 0.6, phase), (0.15, 1.3, 0.5 + phase), (0.05, 2.3, 1.0)];
        let ys = [(0.3, 0.8, 1.0 + phase), (0.1, 1.7, phase), (0.04, 2.9, 0.3)];
        let g = gravity_m_s2();
        let (half_l, half_w) = (1.9, 1.35);
        let mut k = (phase * 1000.0) as u64;
        // Standing level on the floor for 3 s before the take-off: the level is zero.
        for s in 0..30 {
            let t = t_start - 3.0 + f64::from(s) * 0.1;
            series.sensors.push(Sample { t_s: t, sonar_m: None, ir_m: Some(0.2), rpy_rad: None });
            series.attitude.push(Sample { t_s: t, sonar_m: None, ir_m: None, rpy_rad: Some([0.0; 3]) });
        }
        let steps = (duration_s / 0.01).round() as u64;
        for s in 0..=steps {
            let t = s as f64 * 0.01;
            k += 1;
            if s % 5 == 0 {
                let [x, ..] = wander(&xs, t);
                let [y, ..] = wander(&ys, t);
                let cm = |v: f64| ((v + 0.004 * noise(k * 7 + 3)) * 100.0).round() as f32 / 100.0;
                // front, right, back, left
                let sonar = [cm(half_l - x), cm(half_w + y), cm(half_l + x), cm(half_w - y)];
                let ir = (0.5 + 0.01 * noise(k * 13 + 5)) as f32;
                series.sensors.push(Sample { t_s: t_start + t, sonar_m: Some(sonar), ir_m: Some(ir), rpy_rad: None });
            }
            if s % 2 == 0 {
                // The attitude at t drives the acceleration at t + τ.
                let angle = |terms: &[(f64, f64, f64)], axis: usize| {
                    let [_, v, a] = wander(terms, t + truth.delay_s);
                    ((a + truth.damping_per_s * v) / g * truth.mapping.sign(axis)).atan() + truth.trim_rad[axis]
                };
                let (pitch, roll) = (angle(&xs, 0) as f32, angle(&ys, 1) as f32);
                series.attitude.push(Sample {
                    t_s: t_start + t,
                    sonar_m: None,
                    ir_m: None,
                    rpy_rad: Some([roll, pitch, 0.0]),
                });
            }
        }
        Flight { start_s: t_start, end_s: t_start + duration_s }
    }

    fn synthetic(truth: &Truth) -> (Series, Vec<Flight>) {
        let mut series = Series::default();
        let flights = [0.0, 1.1, 2.3].into_iter().map(|ph| flight_of(truth, ph, 40.0, &mut series)).collect();
        (series, flights)
    }

    /// A coarser grid than `twinswarm fit`'s, so that the tests run fast.
    fn coarse() -> FitOptions {
        FitOptions {
            delays_s: Range { from: 0.0, to: 0.6, step: 0.05 },
            dampings_per_s: Range { from: 0.0, to: 0.5, step: 0.05 },
            ..FitOptions::default()
        }
    }

    fn run(series: &Series, flights: &[Flight], opts: &FitOptions) -> FitReport {
        let inputs: Vec<FlightInput<'_>> = flights
            .iter()
            .enumerate()
            .map(|(i, f)| FlightInput { label: format!("flight {}", i + 1), series, flight: *f })
            .collect();
        identify(&inputs, opts).expect("identifies")
    }

    fn score<'a>(r: &'a FitReport, model: &str) -> &'a [HorizonScore] {
        &r.models.iter().find(|m| m.name == model).expect("the model").horizons
    }

    const TRUTH: Truth =
        Truth { delay_s: 0.3, damping_per_s: 0.1, mapping: Mapping::TWINSWARM, trim_rad: [0.02, -0.015] };

    #[test]
    fn the_fit_finds_the_delay_damping_signs_and_trim_a_flight_was_made_with() {
        let (series, flights) = synthetic(&TRUTH);
        let r = run(&series, &flights, &coarse());
        assert!(r.leave_one_out && r.flights.len() == 3 && r.skipped.is_empty(), "{r:?}");
        let centred = run(&series, &flights, &FitOptions { state: StateEstimate::Centred, ..coarse() });
        assert!((centred.all_flights.delay_s - 0.3).abs() < 0.06, "{:?}", centred.all_flights);
        let p = &r.all_flights;
        assert_eq!(p.mapping, Mapping::TWINSWARM, "{p:?}");
        assert!((p.delay_s - 0.3).abs() < 0.03, "{p:?}");
        assert!((p.damping_per_s - 0.1).abs() < 0.06, "{p:?}");
        for f in &r.flights {
            assert_eq!(f.params.mapping, Mapping::TWINSWARM, "{f:?}");
            assert!((f.params.delay_s - 0.3).abs() < 0.06, "{f:?}");
            // The trim the fit learns is the AHRS's offset, negated, from its prior (the other
            // flights', the same) on.
            for (axis, [lo, hi]) in f.bias_rad.into_iter().enumerate() {
                let b = -TRUTH.trim_rad[axis];
                assert!(lo >= b - 0.003 && hi <= b + 0.003, "{axis}: {f:?}");
                assert!((f.trim_prior_rad[axis] - b).abs() < 0.002, "{axis}: {f:?}");
            }
        }
        let identified = score(&r, "identified");
        let cv = score(&r, "constant velocity");
        let stay = score(&r, "stay put");
        let no_bias = score(&r, "identified, no trim");
        for h in 0..3 {
            assert!(identified[h].n > 150, "{identified:?}");
            assert!(identified[h].median_m < 0.5 * cv[h].median_m, "{h}: {identified:?} against {cv:?}");
            assert!(identified[h].median_m < 0.5 * stay[h].median_m, "{h}: {identified:?} against {stay:?}");
            assert!(identified[h].median_m < no_bias[h].median_m, "{h}: the trim counts: {no_bias:?}");
        }
        assert!(identified[0].median_m < 0.05, "{identified:?}");
        // The height loop: 0.5 m, 1 cm of uniform noise (sd 0.58 cm).
        let h = r.height.expect("IR");
        assert!((h.mean_m - 0.5).abs() < 0.002 && (h.noise_sd_m - 0.0058).abs() < 0.001, "{h:?}");
        assert!(h.range_m <= 0.0201 && h.samples > 3 * 600, "{h:?}");
    }

    /// Three flights each flown with its own trim: each learns its own from its past, setting
    /// out from the other two's mean.
    #[test]
    fn each_flight_learns_its_own_trim_from_the_others_mean_on() {
        let mut series = Series::default();
        let trims = [[0.03, -0.02], [0.0, 0.01], [0.015, 0.0]];
        let flights: Vec<Flight> = [0.0, 1.1, 2.3]
            .into_iter()
            .zip(trims)
            .map(|(ph, trim_rad)| flight_of(&Truth { trim_rad, ..TRUTH }, ph, 40.0, &mut series))
            .collect();
        let at = |v: f64| Range { from: v, to: v, step: 1.0 };
        let truth = FitOptions { delays_s: at(0.3), dampings_per_s: at(0.1), ..FitOptions::default() };
        let r = run(&series, &flights, &truth);
        for (f, trim) in r.flights.iter().zip(trims) {
            for axis in 0..2 {
                let others: f64 = trims.iter().map(|t| t[axis]).sum::<f64>() - trim[axis];
                assert!((f.trim_prior_rad[axis] + others / 2.0).abs() < 0.002, "{axis}: {f:?}");
                // From the prior (at the first start) to the flight's own trim.
                let [lo, hi] = f.bias_rad[axis];
                let (own, prior) = (-trim[axis], f.trim_prior_rad[axis]);
                assert!(lo <= own.max(prior) + 0.002 && hi >= own.min(prior) - 0.002, "{axis}: {f:?}");
                assert!(lo >= own.min(prior) - 0.004 && hi <= own.max(prior) + 0.004, "{axis}: {f:?}");
            }
        }
        let identified = score(&r, "identified");
        assert!(identified[0].median_m < 0.03 && identified[2].median_m < 0.15, "{identified:?}");
    }

    /// The synced state at a start, and the trim there, are the same whatever the copter did
    /// after it; the centred one is not.
    #[test]
    fn the_synced_state_knows_nothing_of_what_came_after_its_start() {
        let (series, flights) = synthetic(&TRUTH);
        let f = flights[0];
        let t0 = f.start_s + 20.0;
        // After t0 the copter is 0.2 m further forward: the front sonar reads less, the back more.
        let mut later = series.clone();
        for s in later.sensors.iter_mut().filter(|s| s.t_s > t0) {
            if let Some(sonar) = s.sonar_m.as_mut() {
                sonar[0] -= 0.2;
                sonar[2] += 0.2;
            }
        }
        let k = 0.1;
        let states = |series: &Series, state: StateEstimate| {
            let opts = FitOptions { state, ..coarse() };
            let grid = Grid::of(&opts);
            let input = FlightInput { label: "f".into(), series, flight: f };
            let p = prepare(0, &input, Some([3.8, 2.7]), &opts, &grid).expect("prepared");
            let resp = Responses::of(k, grid.dt, grid.response_steps);
            let cf = CellFlight::of(&p, grid.delay_index(0.3), k, &resp, &grid, &opts);
            let before: Vec<usize> = (0..p.starts.len()).filter(|s| p.starts[*s].i as f64 * grid.dt <= 20.0).collect();
            let trims: Vec<[f64; 3]> = before.iter().map(|s| cf.trim_at(0, p.starts[*s].i)).collect();
            (before.iter().map(|s| cf.states[0][*s]).collect::<Vec<_>>(), trims)
        };
        let (synced, trims) = states(&series, StateEstimate::Synced);
        assert!(synced.len() > 30 && synced.iter().all(Option::is_some), "{synced:?}");
        assert_eq!(states(&later, StateEstimate::Synced), (synced, trims));
        let (centred, _) = states(&series, StateEstimate::Centred);
        assert_ne!(states(&later, StateEstimate::Centred).0, centred);
    }

    #[test]
    fn a_flipped_roll_is_found_flipped_and_pinned_the_wrong_way_it_fails() {
        let flipped = Truth { mapping: Mapping { pitch_to_x: 1, roll_to_y: 1 }, ..TRUTH };
        let (series, flights) = synthetic(&flipped);
        let r = run(&series, &flights, &coarse());
        assert_eq!(r.all_flights.mapping, Mapping { pitch_to_x: 1, roll_to_y: 1 }, "{:?}", r.all_flights);
        let [x, y] = &r.all_flights.sign_evidence;
        let (yp, ym) = (y.plus.expect("+").mean_error_m, y.minus.expect("−").mean_error_m);
        assert!(yp * 3.0 < ym, "y: {y:?}");
        assert!(x.plus.expect("+").mean_error_m * 3.0 < x.minus.expect("−").mean_error_m, "x: {x:?}");
        let free = score(&r, "identified")[0].median_m;
        // Pinned to Twinswarm's signs, the same data predicts far worse.
        let pinned = run(&series, &flights, &FitOptions { mapping: Some(Mapping::TWINSWARM), ..coarse() });
        let wrong = score(&pinned, "identified")[0].median_m;
        assert!(wrong > 3.0 * free, "{wrong} against {free}");
        assert!(pinned.all_flights.sign_evidence[1].plus.is_none(), "{:?}", pinned.all_flights);
    }

    #[test]
    fn the_track_drops_outliers_readings_out_of_range_and_off_the_side_and_marks_gaps() {
        let mut s = Series::default();
        // x = 0.1 m, y = -0.2 m in a 3.8 × 2.7 m arena, every 50 ms from 0 to 10 s, but: a spike
        // at 2 s (x 0.5 m, the sum right), no echo on the left from 4 to 4.5 s, the back sonar on
        // an object (0.9 m) from 6 to 7 s, and nothing at all from 8 to 8.5 s.
        for k in 0..=200 {
            let t = f64::from(k) * 0.05;
            if (8.0..8.5).contains(&t) {
                continue;
            }
            let front = if k == 40 { 1.4 } else { 1.8 };
            let back = if k == 40 {
                2.4
            } else if (6.0..7.0).contains(&t) {
                0.9
            } else {
                2.0
            };
            let left = if (4.0..4.5).contains(&t) { f32::INFINITY } else { 1.55 };
            s.sensors.push(Sample { t_s: t, sonar_m: Some([front, 1.15, back, left]), ir_m: None, rpy_rad: None });
        }
        let f = Flight { start_s: 0.0, end_s: 10.0 };
        let tr = sonar_track(&s, &f, None, &FitOptions::default());
        assert_eq!(tr.len(), 201);
        let [x, y] = &tr.axes;
        assert_eq!((x.readings, x.out_of_range, x.off_side, x.outliers), (191, 0, 20, 1), "{x:?}");
        assert_eq!((x.causal_outliers, y.causal_outliers), (1, 0), "{x:?} {y:?}");
        assert_eq!((tr.causal_m[0].len(), tr.causal_m[1].len()), (191 - 20 - 1, 191 - 10));
        assert_eq!((y.readings, y.out_of_range, y.off_side, y.outliers), (191, 10, 0, 0), "{y:?}");
        assert!((x.side_m.expect("a side") - 3.8).abs() <= 0.026, "{x:?}");
        let at = |axis: usize, t: f64| tr.pos_m[axis][(t / 0.05).round() as usize];
        assert!((at(0, 1.0) - 0.1).abs() < 1e-6 && (at(1, 1.0) + 0.2).abs() < 1e-6);
        // The spike is gone, the grid interpolates over it.
        assert!((at(0, 2.0) - 0.1).abs() < 1e-6);
        // Gaps of 0.3 s or more: the left sonar's silence (0.5 s), the object (1 s), nothing (0.5 s).
        assert!(at(1, 4.25).is_nan() && at(0, 4.25).is_finite());
        assert!(at(0, 6.5).is_nan() && at(1, 6.5).is_finite());
        assert!(at(0, 8.25).is_nan() && at(1, 8.25).is_nan());
        assert_eq!((x.gap_points, y.gap_points), (20 + 10, 10 + 10), "{x:?} {y:?}");
        // Without the side gate, the object makes a step in x the median gate keeps after its
        // first half second.
        let ungated = sonar_track(&s, &f, None, &FitOptions { sum_gate_m: None, ..FitOptions::default() });
        // The side given, not the flight's own.
        let given = sonar_track(&s, &f, Some([2.9, 2.7]), &FitOptions::default());
        assert_eq!((given.axes[0].side_m, given.axes[0].off_side), (Some(2.9), 191 - 20), "{:?}", given.axes);
        assert!((ungated.pos_m[0][(6.8 / 0.05) as usize] - (0.9 - 1.8) / 2.0).abs() < 1e-6);
    }

    #[test]
    fn a_flight_without_sonars_is_skipped_by_name_and_none_at_all_is_an_error() {
        let (series, flights) = synthetic(&TRUTH);
        let mut blind = series.clone();
        let f2 = flights[1];
        for s in blind.sensors.iter_mut().filter(|s| s.t_s >= f2.start_s - 1.0 && s.t_s <= f2.end_s + 1.0) {
            s.sonar_m = None;
        }
        let r = run(&blind, &flights, &coarse());
        assert_eq!(r.skipped.len(), 1, "{:?}", r.skipped);
        assert_eq!(r.skipped[0].label, "flight 2");
        assert!(r.skipped[0].reason.contains("no sonar message"), "{:?}", r.skipped);
        assert_eq!(r.flights.len(), 2);
        let inputs = [FlightInput { label: "F.data flight 2".into(), series: &blind, flight: f2 }];
        let e = identify(&inputs, &coarse()).expect_err("nothing to score").to_string();
        assert!(e.contains("F.data flight 2") && e.contains("no sonar readings for x"), "{e}");
        assert!(matches!(identify(&[], &coarse()), Err(FitError::NoFlights)));
        let bad = FitOptions { grid_dt_s: 0.0, ..coarse() };
        assert!(matches!(identify(&inputs, &bad), Err(FitError::BadOptions(_))));
    }

    #[test]
    fn the_rollout_steps_as_the_simulator_and_the_grids_reach_their_ends() {
        // No tilt, damping 0.5: v ← v / (1 + k dt) per step.
        let m = AxisModel { sigma: 1.0, damping_per_s: 0.5, bias_m_s2: 0.0 };
        let mut out = [0.0; 2];
        roll(&[0.0; 40], 0, 1.0, 1.0, m, 0.05, &[0, 20], &mut out);
        let r: f64 = 1.0 / 1.025;
        let expected = 1.0 + 0.05 * (1..=20).map(|i| 0.5 * (r.powi(i - 1) + r.powi(i))).sum::<f64>();
        assert_eq!(out[0], 1.0);
        assert!((out[1] - expected).abs() < 1e-12, "{out:?}");
        // A constant tilt of 0.1 rad from rest, no damping, 1 s: p = g tan(0.1) t² / 2, exactly.
        let m = AxisModel { sigma: -1.0, damping_per_s: 0.0, bias_m_s2: 0.0 };
        roll(&[0.1f64.tan(); 20], 0, 0.0, 0.0, m, 0.05, &[20], &mut out[..1]);
        let a = -gravity_m_s2() * 0.1f64.tan();
        assert!((out[0] - a * 0.5).abs() < 1e-12, "{out:?}");
        assert_eq!(Range { from: 0.0, to: 0.6, step: 0.02 }.values().len(), 31);
        assert_eq!(Range { from: 0.0, to: 0.6, step: 0.01 }.values().last().copied(), Some(0.6));
        assert_eq!(FitOptions::default().current_damping_per_s, 0.3f32 as f64);
        assert_eq!(Mapping::TWINSWARM.to_string(), "a_x = +g·tan(pitch), a_y = −g·tan(roll)");
    }
}
