//! What a real flight's Paparazzi log says about the copter, in the simulator's frame: its
//! sonar, IR and attitude series, its flights (motor-on, airborne segments), the arena it flew
//! in and where in it each flight began.
//!
//! A FINken has no positioning: the log holds only what the copter measured. Its four sonars
//! at 90° still pin the arena down. Flying level and square to the walls, front + back and
//! left + right are the arena's two sides less the sonars' mount offsets; the sums a flight
//! shows most often (5 cm bins) are those sides, the rest being the copter yawed or an obstacle
//! in a cone. At a flight's start the same readings place the copter: `x = (back − front) / 2`
//! and `y = (right − left) / 2` with its front towards +x (or the same turned by 90° when its
//! front faces the shorter side).
//!
//! **Units.** A value is in its message definition's `unit` where that gives one; `alt_unit` is
//! only how Paparazzi displays it. `FINKEN_IR_ADC.ir_distance` has no `unit` (and an `alt_unit`
//! of cm) and is metres, as its firmware sends it
//! ([`crate::paparazzi::convert::IR_DISTANCE_UNIT`]). That is checked against each log: the
//! same log carries the same height as `FINKEN_SENSOR_MODEL.pos_z`, and [`ir_unit_check`]
//! names any disagreement ([`UnitWarning`]). No factor is ever applied to make them agree.
//!
//! This file holds the series, the flights, the arena and the start poses; [`fit`] identifies
//! the horizontal flight model from the same series (`twinswarm fit`).
//!
//! **May use:** [`crate::paparazzi`] (the log read by `flightlog`, the telemetry conversions of
//! `convert`), [`crate::AcId`], `sim-core`'s constants and angle arithmetic, serde. Pure
//! functions over a log already read: no I/O, no printing. Used by [`crate::log`]'s `import`
//! and the CLI's `validate`, `fit` and `log import`.

pub mod fit;

use serde::Serialize;

use crate::ids::AcId;
use crate::paparazzi::convert::{IR_DISTANCE_UNIT, real_sonar, twin_command, value_unit};
use crate::paparazzi::flightlog::FlightLog;

/// One sample of the copter's own measurements.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Sample {
    /// Log time, s.
    pub t_s: f64,
    /// Sonars (front, right, back, left), m; `INFINITY` for no echo.
    pub sonar_m: Option<[f32; 4]>,
    /// IR height, m.
    pub ir_m: Option<f32>,
    /// Attitude (roll, pitch, yaw), rad, simulator frame.
    pub rpy_rad: Option<[f32; 3]>,
}

/// The copter's measurements in log order: `FINKEN_SENSOR_MODEL` (sonars, IR, attitude where
/// the lab's definition has it), `FINKEN_IR_ADC`, `SONAR_ARRAY`, and `AHRS_EULER_INT` or
/// `ATTITUDE` (attitude).
#[derive(Clone, Debug, Default)]
pub struct Series {
    /// Samples carrying sonar or IR readings.
    pub sensors: Vec<Sample>,
    /// Samples carrying the AHRS attitude.
    pub attitude: Vec<Sample>,
    /// `ROTORCRAFT_STATUS.ap_motors_on` (log time, on), where the log has it (every 2.1 s in
    /// the FINken's telemetry modes).
    pub motors: Vec<(f64, bool)>,
}

impl Series {
    /// The series of aircraft `ac_id`.
    pub fn of(log: &FlightLog, ac_id: AcId) -> Series {
        let mut s = Series::default();
        for r in log.from_aircraft(ac_id) {
            s.push(log, r);
        }
        if s.attitude.is_empty() {
            // A telemetry mode without an AHRS message: the attitude FINKEN_SENSOR_MODEL carries.
            s.attitude = s.sensors.iter().filter(|x| x.rpy_rad.is_some()).copied().collect();
        }
        s
    }

    /// The samples of one record (empty if it carries nothing this module reads).
    pub fn of_record(log: &FlightLog, r: &crate::paparazzi::flightlog::Record) -> Series {
        let mut s = Series::default();
        s.push(log, r);
        s
    }

    fn push(&mut self, log: &FlightLog, r: &crate::paparazzi::flightlog::Record) {
        let msg = log.message(r);
        let cmd = twin_command(&msg);
        let rpy = cmd.as_ref().and_then(|c| Some([c.roll?, c.pitch?, c.yaw.unwrap_or(0.0)]));
        let sample =
            Sample { t_s: r.time_s, sonar_m: real_sonar(&msg), ir_m: cmd.and_then(|c| c.height), rpy_rad: rpy };
        match msg.def.name.as_str() {
            "FINKEN_SENSOR_MODEL" | "FINKEN_IR_ADC" | "SONAR_ARRAY" => self.sensors.push(sample),
            "AHRS_EULER_INT" | "ATTITUDE" => self.attitude.push(sample),
            "ROTORCRAFT_STATUS" => {
                if let Some(on) = msg.get("ap_motors_on").and_then(crate::Value::as_f64) {
                    self.motors.push((r.time_s, on > 0.0));
                }
            }
            _ => {}
        }
    }

    /// The latest sensor sample at or before `t_s` (binary search).
    pub fn sensors_at(&self, t_s: f64) -> Option<&Sample> {
        latest(&self.sensors, t_s)
    }

    /// The latest attitude sample at or before `t_s`.
    pub fn attitude_at(&self, t_s: f64) -> Option<&Sample> {
        latest(&self.attitude, t_s)
    }
}

fn latest(v: &[Sample], t_s: f64) -> Option<&Sample> {
    let n = v.partition_point(|s| s.t_s <= t_s);
    n.checked_sub(1).map(|i| &v[i])
}

/// One flight: the copter airborne.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Flight {
    /// Log time of take-off, s.
    pub start_s: f64,
    /// Log time of landing, s.
    pub end_s: f64,
}

impl Flight {
    /// Its duration, s.
    pub fn duration_s(&self) -> f64 {
        self.end_s - self.start_s
    }
}

/// The copter is airborne this far above the IR's reading on the ground, m (a FINken's Sharp IR
/// reads 0.20-0.24 m standing on the floor: the firmware clamps it at 0.20 m, its shortest
/// range).
pub const AIRBORNE_ABOVE_GROUND_M: f32 = 0.1;
/// Tilted beyond this the copter has flipped: its flight is over, rad (45°).
pub const FLIPPED_RAD: f32 = std::f32::consts::FRAC_PI_4;
/// A take-off: the IR this long above [`AIRBORNE_ABOVE_GROUND_M`] without a break, s. Shorter
/// spells before it are hops (a copter bouncing on its legs as it spins up), not the flight's
/// start.
pub const TAKE_OFF_HOLD_S: f64 = 3.0;
/// After a take-off, airborne spells closer than this are one flight (a hover near the
/// threshold dips below it), s.
pub const FLIGHT_GAP_S: f64 = 2.0;
/// Shorter flights (a copter lifted by hand) are left out, s.
pub const MIN_FLIGHT_S: f64 = 5.0;

/// The IR's reading on the ground: the 5th percentile of the log's readings, m (about 0.2 m;
/// the firmware clamps the IR at 0.20 m).
pub fn ground_ir_m(series: &Series) -> Option<f32> {
    let mut v: Vec<f32> = series.sensors.iter().filter_map(|s| s.ir_m).filter(|z| z.is_finite()).collect();
    v.sort_by(f32::total_cmp);
    v.get(v.len() / 20).copied()
}

/// Whether the motors ran at `t_s` by the log's `ROTORCRAFT_STATUS` (every 2.1 s or less
/// often): on while the latest status says on, and from a status that says off to the next
/// that says on (they started somewhere in between, and a copter that took off then had them
/// on). A log without the status says nothing: on.
pub fn motors_on_at(series: &Series, t_s: f64) -> bool {
    let m = &series.motors;
    let n = m.partition_point(|(t, _)| *t <= t_s);
    m.is_empty() || n.checked_sub(1).is_some_and(|i| m[i].1) || m.get(n).is_some_and(|s| s.1)
}

/// The flights of a series. The copter is airborne while its motors run ([`motors_on_at`]), it
/// is upright and its IR height is more than [`AIRBORNE_ABOVE_GROUND_M`] above its reading on
/// the ground ([`ground_ir_m`]). A flight starts at a take-off, the first sample of an airborne
/// spell that lasts [`TAKE_OFF_HOLD_S`] (hops before it are not flights), takes in the spells
/// that follow less than [`FLIGHT_GAP_S`] apart, and ends where they end (the landing) or where
/// the copter flips (a flip is never bridged). Flights shorter than [`MIN_FLIGHT_S`] are
/// dropped.
pub fn flights(series: &Series) -> Vec<Flight> {
    let Some(ground) = ground_ir_m(series) else { return Vec::new() };
    let airborne = ground + AIRBORNE_ABOVE_GROUND_M;
    // Airborne spells, each with whether a flip ended it.
    let mut spells: Vec<(Flight, bool)> = Vec::new();
    let mut open: Option<Flight> = None;
    // A flip ends a flight whatever the IR reads (upside down it sees the ceiling).
    let upright = |s: &Sample| s.rpy_rad.is_none_or(|r| r[0].abs() < FLIPPED_RAD && r[1].abs() < FLIPPED_RAD);
    for s in &series.sensors {
        let Some(z) = s.ir_m else { continue };
        let up = upright(s);
        // With motors off it is carried, not flying.
        match (&mut open, z > airborne && up && motors_on_at(series, s.t_s)) {
            (Some(f), true) => f.end_s = s.t_s,
            (None, true) => open = Some(Flight { start_s: s.t_s, end_s: s.t_s }),
            (Some(_), false) => spells.extend(open.take().map(|f| (f, !up))),
            (None, false) => {}
        }
    }
    spells.extend(open.map(|f| (f, false)));
    let mut out: Vec<Flight> = Vec::new();
    // The flight under way, and whether a flip ended its last spell.
    let mut current: Option<(Flight, bool)> = None;
    for (f, flipped) in spells {
        let joins =
            current.as_ref().is_some_and(|(c, ended_flipped)| !*ended_flipped && f.start_s - c.end_s < FLIGHT_GAP_S);
        if joins {
            if let Some((c, ended_flipped)) = current.as_mut() {
                c.end_s = f.end_s;
                *ended_flipped = flipped;
            }
        } else {
            out.extend(current.take().map(|(c, _)| c));
            if f.duration_s() >= TAKE_OFF_HOLD_S {
                current = Some((f, flipped));
            }
        }
    }
    out.extend(current.map(|(c, _)| c));
    out.retain(|f| f.duration_s() >= MIN_FLIGHT_S);
    out
}

/// Two values of one quantity a log carries, compared: the median ratio of one to the other at
/// nearby times.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct UnitComparison {
    /// The message of the value checked (`FINKEN_IR_ADC`).
    pub message: String,
    /// Its field (`ir_distance`).
    pub field: String,
    /// What its definition says of its unit (`no unit, alt_unit cm`).
    pub defined: String,
    /// The unit Twinswarm reads it in (`m`).
    pub read_as: String,
    /// The independent value it is held against, with its unit
    /// (`FINKEN_SENSOR_MODEL.pos_z (m)`).
    pub reference: String,
    /// Pairs compared: each sample with the reference sample nearest in time, within
    /// [`UNIT_PAIR_WITHIN_S`].
    pub pairs: usize,
    /// The median of (value as read) / (reference).
    pub median_ratio: f64,
}

/// A sample is compared with the reference sample nearest in time within this, s.
pub const UNIT_PAIR_WITHIN_S: f64 = 0.2;
/// Fewer pairs than this say nothing.
pub const UNIT_MIN_PAIRS: usize = 5;
/// Values read in the right unit agree with their reference within this factor (median ratio
/// in `[1/k, k]`).
pub const UNIT_AGREEMENT_FACTOR: f64 = 1.5;

impl UnitComparison {
    /// Whether the values, read as [`Self::read_as`], agree with the reference.
    pub fn agrees(&self) -> bool {
        let k = UNIT_AGREEMENT_FACTOR;
        (1.0 / k..=k).contains(&self.median_ratio)
    }

    /// The length unit the values would fit, if they do not fit the one they are read in: the
    /// one of `m`, `dm`, `cm`, `mm` whose scale puts the median ratio nearest 1 (within
    /// [`UNIT_AGREEMENT_FACTOR`]).
    pub fn fitting_unit(&self) -> Option<&'static str> {
        let read = crate::paparazzi::convert::metres_per(&self.read_as)?;
        ["m", "dm", "cm", "mm"]
            .into_iter()
            .filter_map(|u| Some((u, crate::paparazzi::convert::metres_per(u)? / read * self.median_ratio)))
            .filter(|(_, r)| (1.0 / UNIT_AGREEMENT_FACTOR..=UNIT_AGREEMENT_FACTOR).contains(r))
            .min_by(|a, b| a.1.ln().abs().total_cmp(&b.1.ln().abs()))
            .map(|(u, _)| u)
    }
}

/// A quantity whose values do not show the unit they are read in: they disagree with an
/// independent value of the same quantity in the same log. Printed by `twinswarm validate` and
/// `twinswarm log import`; nothing is rescaled to hide it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct UnitWarning {
    /// The comparison that disagreed.
    pub comparison: UnitComparison,
    /// The unit the values would fit, where one does.
    pub values_fit: Option<String>,
}

impl std::fmt::Display for UnitWarning {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let c = &self.comparison;
        write!(
            f,
            "unit: {}.{}: its definition says {}, and it is read in {}; but its values are {:.3} × {} \
             (median of {} samples against the nearest within {:.1} s)",
            c.message, c.field, c.defined, c.read_as, c.median_ratio, c.reference, c.pairs, UNIT_PAIR_WITHIN_S
        )?;
        if let Some(u) = &self.values_fit {
            write!(f, ": the values are in {u}, not {}; heights from it are wrong", c.read_as)?;
        } else {
            write!(f, ": they fit no length unit; heights from it are wrong")?;
        }
        write!(f, " (give the field `unit=\"…\"` in the messages.xml the log was read with)")
    }
}

/// What a field's definition says of its unit, for reports: `unit m`, `no unit, alt_unit cm`.
fn unit_said(field: Option<&crate::paparazzi::messages::FieldDef>) -> String {
    let Some(field) = field else { return "nothing (no such field)".to_owned() };
    let unit = field.unit.as_deref().map(str::trim).filter(|u| !u.is_empty());
    let mut s = match unit {
        Some(u) => format!("unit {u}"),
        None => "no unit".to_owned(),
    };
    if let Some(a) = field.alt_unit.as_deref() {
        s += &format!(", alt_unit {a}");
    }
    if let Some(c) = field.alt_unit_coef {
        s += &format!(", alt_unit_coef {c}");
    }
    s
}

/// `FINKEN_IR_ADC.ir_distance` as read (m) against `FINKEN_SENSOR_MODEL.pos_z` (m: the firmware
/// sets it from the same IR) for aircraft `ac_id`: each IR sample with the `pos_z` sample
/// nearest in time within [`UNIT_PAIR_WITHIN_S`]. `None` where the log has fewer than
/// [`UNIT_MIN_PAIRS`] such pairs (no `FINKEN_IR_ADC`, as in the `vrep` telemetry mode).
pub fn ir_unit_comparison(log: &FlightLog, ac_id: AcId) -> Option<UnitComparison> {
    let mut ir: Vec<(f64, f64)> = Vec::new();
    let mut pos_z: Vec<(f64, f64)> = Vec::new();
    let mut def = None;
    for r in log.from_aircraft(ac_id) {
        let msg = log.message(r);
        match msg.def.name.as_str() {
            "FINKEN_IR_ADC" => {
                def = Some(msg.def);
                if let Some(z) = twin_command(&msg).and_then(|c| c.height) {
                    ir.push((r.time_s, f64::from(z)));
                }
            }
            "FINKEN_SENSOR_MODEL" => {
                let z = msg.get("pos_z").and_then(crate::Value::as_f64);
                if let Some(z) = z.filter(|z| z.is_finite() && *z > 0.0) {
                    pos_z.push((r.time_s, z));
                }
            }
            _ => {}
        }
    }
    let def = def?;
    let (pairs, median_ratio) = median_ratio_nearest(&ir, &pos_z, UNIT_PAIR_WITHIN_S)?;
    if pairs < UNIT_MIN_PAIRS {
        return None;
    }
    let field = def.field("ir_distance");
    Some(UnitComparison {
        message: def.name.clone(),
        field: "ir_distance".to_owned(),
        defined: unit_said(field),
        read_as: value_unit(field, IR_DISTANCE_UNIT).to_owned(),
        reference: "FINKEN_SENSOR_MODEL.pos_z (m)".to_owned(),
        pairs,
        median_ratio,
    })
}

/// The warning, if `FINKEN_IR_ADC.ir_distance` as read disagrees with `FINKEN_SENSOR_MODEL.pos_z`
/// in this log ([`ir_unit_comparison`]): a median ratio near 1 says the values are metres as
/// read, near 100 that they are centimetres.
pub fn ir_unit_check(log: &FlightLog, ac_id: AcId) -> Option<UnitWarning> {
    let c = ir_unit_comparison(log, ac_id)?;
    if c.agrees() {
        return None;
    }
    let values_fit = c.fitting_unit().map(str::to_owned);
    Some(UnitWarning { comparison: c, values_fit })
}

/// The number of `values` (time, value) with a `reference` sample within `within_s` (the
/// nearest), and the median of value / reference over them; `None` if none pair. `reference`
/// in time order; non-positive references are skipped.
pub fn median_ratio_nearest(values: &[(f64, f64)], reference: &[(f64, f64)], within_s: f64) -> Option<(usize, f64)> {
    let mut ratios = Vec::new();
    for &(t, v) in values {
        let n = reference.partition_point(|(tr, _)| *tr < t);
        let nearest = [n.checked_sub(1), Some(n)]
            .into_iter()
            .flatten()
            .filter_map(|i| reference.get(i))
            .filter(|(tr, _)| (tr - t).abs() <= within_s)
            .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()));
        if let Some(&(_, r)) = nearest.filter(|(_, r)| *r > 0.0) {
            let q = v / r;
            if q.is_finite() {
                ratios.push(q);
            }
        }
    }
    if ratios.is_empty() {
        return None;
    }
    ratios.sort_by(f64::total_cmp);
    Some((ratios.len(), ratios[ratios.len() / 2]))
}

/// The arena a log's sonars describe.
#[derive(Clone, Debug, Serialize)]
pub struct ArenaEstimate {
    /// Sides (longer, shorter), m: the most frequent opposite-sonar sums plus two mount offsets.
    pub size_m: [f32; 2],
    /// The most frequent front + back and left + right sums, m.
    pub sum_modes_m: [f32; 2],
    /// Airborne samples with all four sonars echoing that went into it.
    pub samples: usize,
    /// The share of those samples within 10 cm of either mode.
    pub share_square: f64,
}

/// Sonar readings at or beyond this are taken as no echo (the firmware gates at 3 m), m.
pub const REAL_SONAR_MAX_M: f32 = 2.99;

/// Derives the arena from the airborne samples of `flights` (see the module docs).
pub fn derive_arena(series: &Series, flights: &[Flight], mount_offset_m: f32) -> Option<ArenaEstimate> {
    let airborne = |t: f64| flights.iter().any(|f| t >= f.start_s && t <= f.end_s);
    let mut fb = Vec::new();
    let mut lr = Vec::new();
    for s in series.sensors.iter().filter(|s| airborne(s.t_s)) {
        let Some([f, r, b, l]) = s.sonar_m else { continue };
        if [f, r, b, l].iter().all(|v| v.is_finite() && *v < REAL_SONAR_MAX_M) {
            fb.push(f + b);
            lr.push(r + l);
        }
    }
    let (m1, m2) = (mode_m(&fb)?, mode_m(&lr)?);
    let near = |v: &f32| (v - m1).abs() <= 0.1 || (v - m2).abs() <= 0.1;
    let square = fb.iter().filter(|v| near(v)).count() + lr.iter().filter(|v| near(v)).count();
    let (a, b) = (m1 + 2.0 * mount_offset_m, m2 + 2.0 * mount_offset_m);
    Some(ArenaEstimate {
        size_m: [a.max(b), a.min(b)],
        sum_modes_m: [m1, m2],
        samples: fb.len(),
        share_square: square as f64 / (2 * fb.len()).max(1) as f64,
    })
}

/// The centre of the most populated 5 cm bin.
fn mode_m(v: &[f32]) -> Option<f32> {
    let mut bins = std::collections::BTreeMap::<i32, usize>::new();
    for x in v {
        *bins.entry((x / 0.05).floor() as i32).or_default() += 1;
    }
    let (bin, _) = bins.iter().max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0)))?;
    Some((*bin as f32 + 0.5) * 0.05)
}

/// The copter stands on the floor while its IR reads within this of its reading on the ground
/// ([`ground_ir_m`]), m: below [`AIRBORNE_ABOVE_GROUND_M`], so that a hover low in ground
/// effect before the take-off is not taken for standing.
pub const ON_FLOOR_WITHIN_M: f32 = 0.04;
/// The floor's level is sought this far back before a take-off, s.
pub const LEVEL_LOOKBACK_S: f64 = 30.0;
/// The level is the median over this much of the last standing before the take-off, s.
pub const LEVEL_WINDOW_S: f64 = 3.0;

/// The roll and pitch the AHRS read standing on the floor before `flight`, rad: the medians over
/// the last [`LEVEL_WINDOW_S`] of attitude samples whose latest IR reading (at most 0.5 s
/// older) says the copter stood on the floor ([`ON_FLOOR_WITHIN_M`]), within
/// [`LEVEL_LOOKBACK_S`] before the take-off and up to 0.3 s before it. None where it never
/// stood there then: a copter that hovered low for half a minute before its take-off shows no
/// level, and the attitude it flew at is not one.
pub fn ground_level(series: &Series, flight: &Flight) -> Option<[f32; 2]> {
    let ground = ground_ir_m(series)?;
    let (from, to) = (flight.start_s - LEVEL_LOOKBACK_S, flight.start_s - 0.3);
    let ir: Vec<(f64, f32)> = series
        .sensors
        .iter()
        .filter(|s| s.t_s >= from - 0.5 && s.t_s <= to)
        .filter_map(|s| Some((s.t_s, s.ir_m?)))
        .collect();
    let standing = |t: f64| {
        let n = ir.partition_point(|(ti, _)| *ti <= t);
        n.checked_sub(1).is_some_and(|i| t - ir[i].0 <= 0.5 && ir[i].1 <= ground + ON_FLOOR_WITHIN_M)
    };
    let on_floor: Vec<(f64, [f32; 3])> = series
        .attitude
        .iter()
        .filter(|s| s.t_s >= from && s.t_s <= to && standing(s.t_s))
        .filter_map(|s| Some((s.t_s, s.rpy_rad?)))
        .collect();
    let last = on_floor.last()?.0;
    let rpy: Vec<[f32; 3]> = on_floor.iter().filter(|(t, _)| *t >= last - LEVEL_WINDOW_S).map(|(_, r)| *r).collect();
    Some([median(rpy.iter().map(|r| r[0]).collect())?, median(rpy.iter().map(|r| r[1]).collect())?])
}

/// A copter whose yaw spans more than this in a flight turned: its front + back and
/// left + right sums mix the arena's two sides, deg.
pub const TURNED_DEG: f32 = 30.0;

/// How far the copter turned in `flight`: the span of its AHRS yaw about the flight's circular
/// mean, 5th to 95th percentile, deg (0 without attitude).
pub fn yaw_span_deg(series: &Series, flight: &Flight) -> f32 {
    let yaws: Vec<f32> = series
        .attitude
        .iter()
        .filter(|s| s.t_s >= flight.start_s && s.t_s <= flight.end_s)
        .filter_map(|s| s.rpy_rad.map(|r| r[2]))
        .filter(|y| y.is_finite())
        .collect();
    let (sin, cos) = yaws.iter().fold((0.0f32, 0.0f32), |(s, c), y| (s + y.sin(), c + y.cos()));
    let mean = sin.atan2(cos);
    let mut d: Vec<f32> = yaws.iter().map(|y| sim_core::math::wrap_angle_rad(y - mean)).collect();
    d.sort_by(f32::total_cmp);
    match (d.get(d.len() / 20), d.get(d.len() * 19 / 20)) {
        (Some(lo), Some(hi)) => (hi - lo).to_degrees(),
        _ => 0.0,
    }
}

/// Where a flight began, in an arena `[long, short]` centred on the origin with its long side
/// along x.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct StartPose {
    /// Position, m.
    pub pos_m: [f32; 2],
    /// Heading in the arena, rad (0: front towards +x).
    pub yaw_rad: f32,
    /// The heading in the arena minus the heading the copter reports, rad.
    pub heading_offset_rad: f32,
    /// The roll and pitch its AHRS read standing on the floor before take-off, rad (zero when
    /// the log has no attitude from then).
    pub level_rad: [f32; 2],
    /// Samples its position was taken from.
    pub samples: usize,
}

/// A sonar sample sees only walls, square to them, when front + back and left + right are the
/// arena's sides (sum modes) within this, m.
pub const SQUARE_WITHIN_M: f32 = 0.15;

/// The start of `flight` from its first 1.5 airborne seconds of sonar readings, square to the
/// walls. Its heading: front towards +x when front + back and left + right (their upper
/// quartiles) fit the long and the short side better than the other way round (both sums weigh,
/// so that one sonar on an obstacle does not turn the copter), towards +y otherwise. Its position: the medians of the
/// samples that see only walls (both sums within [`SQUARE_WITHIN_M`] of those sides; an
/// obstacle or another copter only shortens a reading), or of all samples where fewer than
/// three do.
pub fn start_pose(series: &Series, flight: &Flight, arena: &ArenaEstimate) -> Option<StartPose> {
    let window = |s: &&Sample| s.t_s >= flight.start_s && s.t_s <= flight.start_s + 1.5;
    let picks: Vec<[f32; 4]> = series
        .sensors
        .iter()
        .filter(window)
        .filter_map(|s| s.sonar_m)
        .filter(|r| r.iter().all(|v| v.is_finite() && *v < REAL_SONAR_MAX_M))
        .collect();
    let [m1, m2] = arena.sum_modes_m;
    let (long, short) = (m1.max(m2), m1.min(m2));
    // The upper quartile: an obstacle, another copter or cross-talk only shortens a reading.
    let fb = quantile(picks.iter().map(|r| r[0] + r[2]).collect(), 0.75)?;
    let lr = quantile(picks.iter().map(|r| r[1] + r[3]).collect(), 0.75)?;
    let along_x = (fb - long).abs() + (lr - short).abs() <= (fb - short).abs() + (lr - long).abs();
    let (side_fb, side_lr) = if along_x { (long, short) } else { (short, long) };
    let square = |r: &&[f32; 4]| {
        (r[0] + r[2] - side_fb).abs() <= SQUARE_WITHIN_M && (r[1] + r[3] - side_lr).abs() <= SQUARE_WITHIN_M
    };
    let clean: Vec<[f32; 4]> = picks.iter().filter(square).copied().collect();
    let used = if clean.len() >= 3 { &clean } else { &picks };
    let med = |k: usize| median(used.iter().map(|r| r[k]).collect());
    let [f, r, b, l] = [med(0)?, med(1)?, med(2)?, med(3)?];
    let (pos_m, yaw_rad) = if along_x {
        ([(b - f) / 2.0, (r - l) / 2.0], 0.0)
    } else {
        // Front towards +y: its right towards +x.
        ([(l - r) / 2.0, (b - f) / 2.0], std::f32::consts::FRAC_PI_2)
    };
    let own = series.attitude_at(flight.start_s).or_else(|| series.attitude.first()).and_then(|s| s.rpy_rad)?;
    Some(StartPose {
        pos_m,
        yaw_rad,
        heading_offset_rad: sim_core::math::wrap_angle_rad(yaw_rad - own[2]),
        level_rad: ground_level(series, flight).unwrap_or([0.0, 0.0]),
        samples: used.len(),
    })
}

/// The `q` quantile of `v` (the nearest rank).
fn quantile(mut v: Vec<f32>, q: f32) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f32::total_cmp);
    Some(v[((v.len() - 1) as f32 * q).round() as usize])
}

fn median(mut v: Vec<f32>) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f32::total_cmp);
    Some(v[v.len() / 2])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::paparazzi::flightlog::LogConfig;

    /// The IR of a FINken standing on the floor, as the real logs have it: 0.200-0.212 m (the
    /// firmware clamps at 0.20 m), a few mm of jitter.
    fn floor_m(t_s: f64) -> f32 {
        0.2 + 0.004 * ((t_s * 10.0).round() as i64 % 4) as f32
    }

    /// A log's series as the `default` telemetry mode sends it: `FINKEN_SENSOR_MODEL` every 0.1 s
    /// (IR height and roll from `at(t)`), `FINKEN_IR_ADC` every 1 s between (IR only) and
    /// `ROTORCRAFT_STATUS` every 2.1 s (motors from `on(t)`), 0 to `end_s`.
    fn series(end_s: f64, at: impl Fn(f64) -> (f32, f32), on: impl Fn(f64) -> bool) -> Series {
        let mut s = Series::default();
        for k in 0..=(end_s * 10.0).round() as u32 {
            let t = f64::from(k) / 10.0;
            let (z, roll) = at(t);
            s.sensors.push(Sample { t_s: t, sonar_m: None, ir_m: Some(z), rpy_rad: Some([roll, 0.0, 0.0]) });
            if k % 10 == 5 {
                let t = t + 0.04;
                s.sensors.push(Sample { t_s: t, sonar_m: None, ir_m: Some(at(t).0), rpy_rad: None });
            }
        }
        let mut t = 0.3;
        while t <= end_s {
            s.motors.push((t, on(t)));
            t += 2.1;
        }
        s
    }

    /// The first sample above the ground + 0.1 m that stays there 3 s, worked out here from the
    /// samples alone.
    fn ir_take_off(s: &Series, ground: f32) -> Option<f64> {
        let up = |x: &Sample| x.ir_m.is_some_and(|z| z > ground + 0.1);
        s.sensors.iter().enumerate().find_map(|(i, a)| {
            let held = s.sensors[i..].iter().take_while(|b| b.t_s <= a.t_s + 3.0).all(up);
            (up(a) && held).then_some(a.t_s)
        })
    }

    #[test]
    fn a_flight_starts_at_the_ir_take_off_not_at_motors_on_nor_at_the_hops_before_it() {
        // Motors on from 2 s; two hops of 0.5 s (16 s, 17.5 s), each under a second apart from
        // the next, then the take-off at 19 s (a 0.5 s climb to 0.5 m), a hover to 40 s, a
        // landing, motors off at 42 s.
        let at = |t: f64| {
            let z = match t {
                t if (16.0..16.5).contains(&t) || (17.5..18.0).contains(&t) => 0.33,
                t if (19.0..19.5).contains(&t) => 0.2 + 0.6 * (t - 19.0) as f32,
                t if (19.5..40.0).contains(&t) => 0.5 + 0.02 * (t * 3.0).sin() as f32,
                t if (40.0..40.5).contains(&t) => 0.5 - 0.6 * (t - 40.0) as f32,
                t => floor_m(t),
            };
            (z, 0.02)
        };
        let s = series(50.0, at, |t| (2.0..42.0).contains(&t));
        let ground = ground_ir_m(&s).expect("a ground reading");
        assert!((ground - 0.2).abs() < 0.015, "the IR on the floor is about 0.2 m: {ground}");
        let take_off = ir_take_off(&s, ground).expect("a take-off");
        assert!((19.0..19.5).contains(&take_off), "{take_off}");
        let fl = flights(&s);
        assert_eq!(fl.len(), 1, "{fl:?}");
        let f = fl[0];
        assert!((f.start_s - take_off).abs() <= 1.0, "starts at the take-off ({take_off} s): {f:?}");
        assert!(f.start_s > 18.5, "not at motors-on (2 s) nor at the hops (16 s): {f:?}");
        assert!((39.5..41.0).contains(&f.end_s), "ends at the landing: {f:?}");
    }

    #[test]
    fn the_level_is_the_attitude_standing_on_the_floor_not_a_low_hover_before_the_take_off() {
        // Standing tilted 0.02 rad until 10 s; from 10 s a hover low in ground effect (0.27 m,
        // under the take-off's 0.3 m) at roll −0.09; the take-off at 19 s.
        let at = |t: f64| match t {
            t if t < 10.0 => (floor_m(t), 0.02),
            t if t < 19.0 => (0.27, -0.09),
            _ => (0.6, 0.0),
        };
        let with_attitude = |mut s: Series| {
            s.attitude = s.sensors.iter().filter(|x| x.rpy_rad.is_some()).cloned().collect();
            s
        };
        let s = with_attitude(series(40.0, at, |_| true));
        let fl = flights(&s);
        assert_eq!(fl.len(), 1, "{fl:?}");
        let level = ground_level(&s, &fl[0]).expect("a level");
        assert!((level[0] - 0.02).abs() < 1e-6, "the standing roll, not the hover's: {level:?}");
        // Hovering low for longer than the look-back: no level at all rather than a wrong one.
        let at = |t: f64| match t {
            t if t < 5.0 => (floor_m(t), 0.02),
            t if t < 5.0 + LEVEL_LOOKBACK_S + 1.0 => (0.27, -0.09),
            _ => (0.6, 0.0),
        };
        let s = with_attitude(series(60.0, at, |_| true));
        let fl = flights(&s);
        assert_eq!(fl.len(), 1, "{fl:?}");
        assert_eq!(ground_level(&s, &fl[0]), None);
    }

    #[test]
    fn no_flight_while_the_ir_stays_at_floor_level_nor_while_carried_with_motors_off() {
        // Motors on the whole minute, the copter on the floor (the IR within its floor jitter).
        let s = series(60.0, |t| (floor_m(t), 0.01), |_| true);
        assert_eq!(flights(&s), Vec::new());
        // Motors off, the copter carried about at 0.8 m for 20 s (as MC1_DISTANCES was turned by
        // hand): carried, not flown.
        let carried = |t: f64| (if (10.0..30.0).contains(&t) { 0.8 } else { floor_m(t) }, 0.05);
        let s = series(60.0, carried, |_| false);
        assert_eq!(flights(&s), Vec::new());
    }

    #[test]
    fn a_flip_ends_a_flight() {
        // Take-off at 5 s, hover at 0.5 m; at 25 s it flips (roll 3 rad, the IR reading the
        // ceiling, clamped at 1.3 m) for 0.5 s, reads upright and airborne again for a second
        // (tumbling), then lies on its back, motors on until 30 s.
        let at = |t: f64| match t {
            t if t < 5.0 => (floor_m(t), 0.0),
            t if t < 25.0 => (0.5, 0.05),
            t if t < 25.5 => (1.3, 3.0),
            t if t < 26.5 => (0.45, 0.1),
            _ => (1.3, 3.1),
        };
        let s = series(40.0, at, |t| t < 30.0);
        let fl = flights(&s);
        assert_eq!(fl.len(), 1, "{fl:?}");
        assert!((fl[0].start_s - 5.0).abs() <= 1.0, "{fl:?}");
        assert!((24.5..25.0).contains(&fl[0].end_s), "the flip at 25 s ends it, and is not bridged: {fl:?}");
    }

    #[test]
    fn the_start_heading_weighs_both_sums_and_the_position_the_samples_that_see_only_walls() {
        // A 4 × 2.8 m room (sums 3.9 and 2.7 with the mount offsets), the copter at
        // (-0.5, -0.2) facing +x: front 2.45, back 1.45, right 1.15, left 1.55. Its front
        // sonar meets something 0.8 m ahead in 6 of 10 samples.
        let arena = ArenaEstimate { size_m: [4.0, 2.8], sum_modes_m: [3.9, 2.7], samples: 100, share_square: 0.8 };
        let mut s = Series::default();
        for k in 0..10 {
            let t = 10.0 + 0.1 * f64::from(k);
            let front = if k % 5 < 3 { 0.8 } else { 2.45 };
            s.sensors.push(Sample { t_s: t, sonar_m: Some([front, 1.15, 1.45, 1.55]), ir_m: Some(0.5), rpy_rad: None });
            s.attitude.push(Sample { t_s: t, sonar_m: None, ir_m: None, rpy_rad: Some([0.0, 0.0, 0.3]) });
        }
        let f = Flight { start_s: 10.0, end_s: 30.0 };
        let p = start_pose(&s, &f, &arena).expect("a start");
        // The median front + back (2.25) is nearer the short side than the long one: the old
        // rule turned the copter by 90°. Its upper quartile (3.9) and left + right (2.7) say it
        // faces the long side.
        assert_eq!(p.yaw_rad, 0.0, "{p:?}");
        assert!((p.pos_m[0] + 0.5).abs() < 1e-5 && (p.pos_m[1] + 0.2).abs() < 1e-5, "{p:?}");
        assert_eq!(p.samples, 4, "the four samples that see only walls");
    }

    /// A `.log` with the fork's `FINKEN_IR_ADC` (`ir_distance` with `unit_attr`, if any) and a
    /// `FINKEN_SENSOR_MODEL` reduced to `pos_z`; a `.data` of 30 s, `pos_z` every 0.1 s
    /// (metres: floor, then 0.5 m) and `ir_distance` every 1 s, `ir_scale` × the height.
    fn ir_log(unit_attr: &str, ir_scale: f64) -> FlightLog {
        let log = format!(
            r#"<?xml version="1.0"?>
<configuration time_of_day="1448458956.0" data_file="t.data">
  <protocol>
    <msg_class NAME="telemetry">
      <message NAME="FINKEN_IR_ADC" ID="252">
        <field TYPE="float" NAME="ir_distance" {unit_attr} ALT_UNIT="cm"/>
        <field TYPE="uint16" NAME="ir_measurement"/>
      </message>
      <message NAME="FINKEN_SENSOR_MODEL" ID="217">
        <field TYPE="float" NAME="pos_z" ALT_UNIT="m"/>
      </message>
    </msg_class>
  </protocol>
</configuration>
"#
        );
        let config = LogConfig::parse(&log, "t.log").expect("a valid .log");
        let z = |t: f64| if t < 10.0 { 0.2 } else { 0.5 + 0.03 * (t * 2.0).sin() };
        let mut data = String::new();
        for k in 0..300 {
            let t = f64::from(k) / 10.0;
            data += &format!("{t:.3} 6 FINKEN_SENSOR_MODEL {:.6}\n", z(t));
            if k % 10 == 3 {
                let t = t + 0.05;
                data += &format!("{t:.3} 6 FINKEN_IR_ADC {:.6} 512\n", z(t) * ir_scale);
            }
        }
        FlightLog::from_parts(config, data.as_bytes(), "t.data")
    }

    #[test]
    fn the_ir_unit_check_finds_metres_where_the_values_are_metres() {
        // The fork's own definition: no `unit`, `alt_unit="cm"`, and the values metres.
        let log = ir_log("", 1.0);
        let c = ir_unit_comparison(&log, 6).expect("pairs to compare");
        assert_eq!(c.pairs, 30);
        assert!((c.median_ratio - 1.0).abs() < 0.05, "{c:?}");
        assert_eq!(c.read_as, "m");
        assert_eq!(c.defined, "no unit, alt_unit cm");
        assert!(c.agrees());
        assert_eq!(ir_unit_check(&log, 6), None);
        // What the flights read is metres too: the IR samples sit among pos_z's.
        let s = Series::of(&log, 6);
        let ir: Vec<f32> = s.sensors.iter().filter_map(|x| x.ir_m).collect();
        assert!(ir.iter().all(|z| (0.15..0.6).contains(z)), "{ir:?}");
        // A definition that says `unit="cm"` of centimetres is read right: no warning either.
        let log = ir_log(r#"UNIT="cm""#, 100.0);
        let c = ir_unit_comparison(&log, 6).expect("pairs to compare");
        assert!((c.median_ratio - 1.0).abs() < 0.05 && c.read_as == "cm", "{c:?}");
        assert_eq!(ir_unit_check(&log, 6), None);
    }

    #[test]
    fn centimetres_under_a_definition_without_unit_are_a_named_warning_never_a_silent_factor() {
        let log = ir_log("", 100.0);
        let w = ir_unit_check(&log, 6).expect("a warning");
        assert!((w.comparison.median_ratio - 100.0).abs() < 5.0, "{w:?}");
        assert_eq!(w.values_fit.as_deref(), Some("cm"));
        let text = w.to_string();
        for part in
            ["FINKEN_IR_ADC.ir_distance", "no unit, alt_unit cm", "read in m", "FINKEN_SENSOR_MODEL.pos_z", "in cm"]
        {
            assert!(text.contains(part), "{part:?} missing from: {text}");
        }
        // The values are read as the definition says (metres), not rescaled to agree.
        let s = Series::of(&log, 6);
        assert!(s.sensors.iter().filter_map(|x| x.ir_m).any(|z| z > 40.0));
    }

    #[test]
    fn median_ratio_pairs_each_value_with_the_nearest_reference_within_the_window() {
        let reference = [(0.0, 1.0), (1.0, 2.0), (2.0, 4.0)];
        // 0.9 s → 1.0 (2.0); 1.95 s → 2.0 (4.0); 5 s has none within 0.2 s.
        let values = [(0.9, 4.0), (1.95, 8.0), (5.0, 1.0)];
        assert_eq!(median_ratio_nearest(&values, &reference, 0.2), Some((2, 2.0)));
        assert_eq!(median_ratio_nearest(&values[2..], &reference, 0.2), None);
    }
}
