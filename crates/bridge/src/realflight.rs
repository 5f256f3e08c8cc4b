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

use serde::Serialize;

use crate::AcId;
use crate::paparazzi::convert::{real_sonar, twin_command};
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
/// reads about 0.23 m standing on the floor: its shortest range).
pub const AIRBORNE_ABOVE_GROUND_M: f32 = 0.1;
/// Tilted beyond this the copter has flipped: its flight is over, rad (45°).
pub const FLIPPED_RAD: f32 = std::f32::consts::FRAC_PI_4;
/// Airborne spells closer than this are one flight, s.
pub const FLIGHT_GAP_S: f64 = 2.0;
/// Shorter flights (hops, a copter lifted by hand) are left out, s.
pub const MIN_FLIGHT_S: f64 = 5.0;

/// The IR's reading on the ground: the 5th percentile of the log's readings, m.
pub fn ground_ir_m(series: &Series) -> Option<f32> {
    let mut v: Vec<f32> = series.sensors.iter().filter_map(|s| s.ir_m).filter(|z| z.is_finite()).collect();
    v.sort_by(f32::total_cmp);
    v.get(v.len() / 20).copied()
}

/// The flights of a series: motors on (the last `ROTORCRAFT_STATUS` said so), upright, IR
/// height more than [`AIRBORNE_ABOVE_GROUND_M`] above its reading on the ground
/// ([`ground_ir_m`]); spells closer than [`FLIGHT_GAP_S`] joined, those shorter than
/// [`MIN_FLIGHT_S`] dropped.
pub fn flights(series: &Series) -> Vec<Flight> {
    let Some(ground) = ground_ir_m(series) else { return Vec::new() };
    let airborne = ground + AIRBORNE_ABOVE_GROUND_M;
    let mut spells: Vec<Flight> = Vec::new();
    let mut open: Option<Flight> = None;
    // A flip ends a flight whatever the IR reads (upside down it sees the ceiling).
    let upright = |s: &Sample| s.rpy_rad.is_none_or(|r| r[0].abs() < FLIPPED_RAD && r[1].abs() < FLIPPED_RAD);
    // With motors off it is carried, not flying (a log without the status says nothing).
    let motors_on = |t: f64| {
        let n = series.motors.partition_point(|(tm, _)| *tm <= t);
        series.motors.is_empty() || n.checked_sub(1).is_some_and(|i| series.motors[i].1)
    };
    for s in &series.sensors {
        let Some(z) = s.ir_m else { continue };
        match (&mut open, z > airborne && upright(s) && motors_on(s.t_s)) {
            (Some(f), true) => f.end_s = s.t_s,
            (None, true) => open = Some(Flight { start_s: s.t_s, end_s: s.t_s }),
            (Some(_), false) => spells.extend(open.take()),
            (None, false) => {}
        }
    }
    spells.extend(open);
    let mut out: Vec<Flight> = Vec::new();
    for f in spells {
        match out.last_mut() {
            Some(last) if f.start_s - last.end_s < FLIGHT_GAP_S => last.end_s = f.end_s,
            _ => out.push(f),
        }
    }
    out.retain(|f| f.duration_s() >= MIN_FLIGHT_S);
    out
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

/// The roll and pitch the AHRS read standing on the floor before `flight` (medians over the
/// 3 s before take-off, up to 0.3 s before it), rad.
pub fn ground_level(series: &Series, flight: &Flight) -> Option<[f32; 2]> {
    let on_floor = |s: &&Sample| s.t_s >= flight.start_s - 3.0 && s.t_s <= flight.start_s - 0.3;
    let rpy: Vec<[f32; 3]> = series.attitude.iter().filter(on_floor).filter_map(|s| s.rpy_rad).collect();
    Some([median(rpy.iter().map(|r| r[0]).collect())?, median(rpy.iter().map(|r| r[1]).collect())?])
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
    /// Samples it was taken from.
    pub samples: usize,
}

/// The start of `flight` from its first airborne second of sonar readings (medians), square to
/// the walls: front towards +x when front + back is nearer the long side, towards +y
/// otherwise.
pub fn start_pose(series: &Series, flight: &Flight, arena: &ArenaEstimate) -> Option<StartPose> {
    let window = |s: &&Sample| s.t_s >= flight.start_s && s.t_s <= flight.start_s + 1.5;
    let picks: Vec<[f32; 4]> = series
        .sensors
        .iter()
        .filter(window)
        .filter_map(|s| s.sonar_m)
        .filter(|r| r.iter().all(|v| v.is_finite() && *v < REAL_SONAR_MAX_M))
        .collect();
    let med = |k: usize| median(picks.iter().map(|r| r[k]).collect());
    let [f, r, b, l] = [med(0)?, med(1)?, med(2)?, med(3)?];
    let [m1, m2] = arena.sum_modes_m;
    let (long, short) = (m1.max(m2), m1.min(m2));
    let along_x = ((f + b) - long).abs() <= ((f + b) - short).abs();
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
        samples: picks.len(),
    })
}

fn median(mut v: Vec<f32>) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f32::total_cmp);
    Some(v[v.len() / 2])
}
