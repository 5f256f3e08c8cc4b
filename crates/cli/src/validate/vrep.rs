//! V-REP's own output for its twin of a real flight (the original system, 2015), read so that
//! `twinswarm validate` scores it as it scores Twinswarm's twin.
//!
//! Two files per run, one row per 50 ms simulation step, the step's time in ms first:
//! `simulationPosition<stamp>.log` (`ms x y z`, m, V-REP's world frame; an `_orig` copy has
//! `ms:` and decimal commas) and `simulationOrientation<stamp>.log` (`ms: alpha beta gamma`,
//! decimal commas). See [`FRAME`] for how they map into the arena.

use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::Serialize;
use sim_core::math::Vec3;

use super::{Metrics, Scorer, TracePoint};
use crate::BadInput;
use bridge::realflight::{Flight, Series};

/// How V-REP's frame maps into the arena frame of `twinswarm validate` (origin at the arena's
/// centre, +x towards the wall the copter's front sonar faced at take-off, +y to its left, yaw
/// counter-clockwise from +x).
///
/// From the 2015 lab scene and its output (docs/real-flights.md): the walls were at
/// x ∈ [−4, 0], y ∈ [0, 3] (the authors' own plot script); the twin started at (−1.775, 2.025),
/// which the real copter's first sonar readings put at (0.08, −0.40) in the arena frame with
/// `x = vx + 2`, `y = 1.5 − vy`. Orientation columns (deg): the twin's own motion shows
/// `a_x = −g tan(c2)` and `a_y = −g tan(c1)` along V-REP's axes, so its physical roll is `−c1`
/// and pitch `−c2` in the arena frame, and its yaw `−c3`. Measured so, its roll follows the real
/// copter's and its pitch is the real copter's inverted.
pub const FRAME: VrepFrame = VrepFrame { origin_m: [-2.0, 1.5], flip_y: true };

/// See [`FRAME`].
#[derive(Clone, Copy, Debug, Serialize)]
pub struct VrepFrame {
    /// The arena's centre in V-REP's frame, m.
    pub origin_m: [f64; 2],
    /// V-REP's y axis points the other way (the scene is a mirror image of the lab).
    pub flip_y: bool,
}

/// V-REP's twin of one run, on the log's clock.
#[derive(Debug)]
pub struct VrepTwin {
    /// Its poses in the arena frame, log time.
    trace: Vec<TracePoint>,
    /// Log time of V-REP's time 0, s.
    pub start_s: f64,
    /// Log seconds per V-REP second (its simulation clock was not the wall clock's).
    pub rate: f64,
    /// How that was found.
    pub start_from: String,
}

/// V-REP's twin scored over the part of a flight its output covers.
#[derive(Clone, Debug, Serialize)]
pub struct VrepScore {
    /// The metrics.
    pub metrics: Metrics,
    /// Log time span scored, s.
    pub from_s: f64,
    /// End.
    pub to_s: f64,
    /// Log time of V-REP's time 0, s.
    pub start_s: f64,
    /// Log seconds per V-REP second.
    pub rate: f64,
    /// How it was found.
    pub start_from: String,
}

impl VrepTwin {
    /// Reads the position file and the orientation file of the same stamp beside it, and
    /// places them on the log's clock (`start_s`, or by matching attitude to the AHRS).
    pub fn open(position: &Path, series: &Series, start_s: Option<f64>) -> anyhow::Result<VrepTwin> {
        let orientation = orientation_path(position)?;
        let pos = read_rows(position)?;
        let att = read_rows(&orientation)?;
        anyhow::ensure!(!pos.is_empty(), BadInput(anyhow::anyhow!("{}: no rows", position.display())));
        let rows: Vec<(f64, [f64; 3], [f64; 3])> = pos
            .iter()
            .filter_map(|(ms, p)| att.iter().find(|(m2, _)| (m2 - ms).abs() < 1.0).map(|(_, a)| (*ms / 1000.0, *p, *a)))
            .collect();
        let local: Vec<TracePoint> = rows.iter().map(|(t, p, a)| to_arena(*t, p, a)).collect();
        let (start_s, rate, start_from) = match start_s {
            Some(s) => (s, 1.0, "given".to_owned()),
            None => {
                let (s, rate) = match_clock(&local, series).ok_or_else(|| {
                    BadInput(anyhow::anyhow!("cannot place V-REP's output on the log's clock: the log has no attitude"))
                })?;
                (s, rate, "its roll matched to the AHRS's".to_owned())
            }
        };
        let trace = local.into_iter().map(|p| TracePoint { t_s: start_s + rate * p.t_s, ..p }).collect();
        Ok(VrepTwin { trace, start_s, rate, start_from })
    }

    /// Its poses within a flight.
    pub fn trace_in(&self, f: &Flight) -> Vec<TracePoint> {
        self.trace.iter().copied().filter(|p| p.t_s >= f.start_s && p.t_s <= f.end_s).collect()
    }

    /// Scores it with a flight's scorer, if it overlaps the flight.
    pub fn score(&self, scorer: &Scorer<'_>) -> Option<VrepScore> {
        let trace = self.trace_in(&scorer.flight);
        let (first, last) = (trace.first()?, trace.last()?);
        Some(VrepScore {
            // Its output says nothing of crashes: scored to the end of what it covers.
            metrics: scorer.score(&trace, None),
            from_s: first.t_s,
            to_s: last.t_s,
            start_s: self.start_s,
            rate: self.rate,
            start_from: self.start_from.clone(),
        })
    }
}

fn orientation_path(position: &Path) -> anyhow::Result<PathBuf> {
    let name = position.file_name().and_then(|n| n.to_str()).unwrap_or("");
    let stamp = name
        .strip_prefix("simulationPosition")
        .map(|rest| rest.trim_end_matches(".log").trim_end_matches("_orig"))
        .ok_or_else(|| BadInput(anyhow::anyhow!("{}: expected simulationPosition<stamp>.log", position.display())))?;
    Ok(position.with_file_name(format!("simulationOrientation{stamp}.log")))
}

/// Rows `ms[:] a b c` with decimal points or commas.
fn read_rows(path: &Path) -> anyhow::Result<Vec<(f64, [f64; 3])>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut rows = Vec::new();
    for (i, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let bad = || BadInput(anyhow::anyhow!("{}:{}: expected `ms: a b c`, got `{line}`", path.display(), i + 1));
        let nums: Vec<f64> = line
            .split_whitespace()
            .map(|w| w.trim_end_matches(':').replace(',', ".").parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| bad())?;
        match nums[..] {
            [ms, a, b, c] if nums.iter().all(|v| v.is_finite()) => rows.push((ms, [a, b, c])),
            _ => return Err(bad().into()),
        }
    }
    Ok(rows)
}

fn to_arena(t_s: f64, p: &[f64; 3], a: &[f64; 3]) -> TracePoint {
    let f = FRAME;
    let sign = if f.flip_y { -1.0 } else { 1.0 };
    let pos_m = Vec3::new((p[0] - f.origin_m[0]) as f32, (sign * (p[1] - f.origin_m[1])) as f32, p[2] as f32);
    let rad = |v: f64| (v as f32).to_radians();
    let yaw = sim_core::math::wrap_angle_rad(-rad(a[2]));
    TracePoint { t_s, pos_m, rpy_rad: [-rad(a[0]), -rad(a[1]), yaw] }
}

/// V-REP's clock on the log's: `t_log = start + rate · t_vrep`, the start (50 ms grid, then
/// 10 ms) and rate (0.95-1.05) that best match V-REP's roll and heading changes to the AHRS's.
/// Roll and heading, because V-REP's twin followed them with the right sign (its pitch was
/// inverted); the heading turns by tens of degrees in a flight, which pins the start down.
fn match_clock(local: &[TracePoint], series: &Series) -> Option<(f64, f64)> {
    let (first, last) = (series.attitude.first()?.t_s, series.attitude.last()?.t_s);
    let span = local.last()?.t_s;
    let wrap = sim_core::math::wrap_angle_rad;
    let p0 = local.first()?;
    let cost = |start: f64, rate: f64| -> Option<f64> {
        let r0 = series.attitude_at(start).and_then(|s| s.rpy_rad)?;
        let (mut sum, mut n) = (0.0, 0u32);
        for p in local.iter().step_by(2) {
            let r = series.attitude_at(start + rate * p.t_s).and_then(|s| s.rpy_rad)?;
            let turn = wrap(wrap(p.rpy_rad[2] - p0.rpy_rad[2]) - wrap(r[2] - r0[2]));
            sum += f64::from(p.rpy_rad[0] - r[0]).powi(2) + f64::from(turn).powi(2);
            n += 1;
        }
        (n > 0).then(|| sum / f64::from(n))
    };
    let better = |best: &mut Option<(f64, f64, f64)>, s: f64, r: f64| {
        if let Some(c) = cost(s, r)
            && best.is_none_or(|(_, _, b)| c < b)
        {
            *best = Some((s, r, c));
        }
    };
    let mut best = None;
    let mut s = first;
    while s + span <= last {
        better(&mut best, s, 1.0);
        s += 0.05;
    }
    let (s0, _, _) = best?;
    for k in -100..=100 {
        for j in -50..=50 {
            better(&mut best, s0 + f64::from(k) * 0.01, 1.0 + f64::from(j) * 0.001);
        }
    }
    best.map(|(s, r, _)| (s, r))
}
