//! `twinswarm validate FLIGHT.data`: a real flight's Paparazzi log against Twinswarm, offline,
//! deterministic, at full speed.
//!
//! Per flight of the log (the copter airborne, [`bridge::realflight::flights`]):
//! 1. the arena comes from the log's sonars ([`bridge::realflight::derive_arena`]) or
//!    `--scene`, and the twin starts where the first airborne second of sonar readings puts
//!    it, square to the walls;
//! 2. the twin is driven by the log's own telemetry, each message at its recorded time, through
//!    the gateway's [`Interpreter`] and the step loop a live run uses, with the sync
//!    correction on (MEDUSA on the real sonars, as a lab runs it) and off (the flight model
//!    predicting from the telemetry alone);
//! 3. its trace is held against what the real copter measured ([`Scorer::score`]): attitude,
//!    the distances its sonars would read against the real sonars, height against the IR, time
//!    in the arena (its position against the arena's walls), the first time it strays. A twin's
//!    crash ends its scoring, and is reported with its time and cause: the errors are of the
//!    twin before it, and the time after it counts as neither inside the arena nor consistent.
//!
//! With `--vrep`, V-REP's own output for its twin of the flight is scored the same way.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::sync::mpsc::SyncSender;
use std::time::{Duration, Instant};

use anyhow::Context;
use bridge::engine::{BusInput, LoopOptions, Request, StepObserver};
use bridge::mixed::interpreter::{Interpreter, TwinAttitude};
use bridge::paparazzi::flightlog::{FlightLog, LineErrors};
use bridge::paparazzi::messages::MessageSet;
use bridge::realflight::{ArenaEstimate, Flight, REAL_SONAR_MAX_M, Series, StartPose, UnitWarning};
use serde::Serialize;
use sim_core::math::{Quat, Vec3, quat_from_euler};
use sim_core::sensors::{SonarScene, sonar_cones};
use sim_core::{Inputs, State, StepReport, World};

use crate::BadInput;

mod vrep;

/// Simulated time before take-off: the twin sits on the floor and hears the telemetry, s.
const LEAD_S: f64 = 2.0;
/// Metrics start this long after take-off (the climb), s.
const SETTLE_S: f64 = 1.0;
/// The window of the stray test's running mean, s.
const STRAY_WINDOW_S: f64 = 1.0;

/// `twinswarm validate` arguments.
#[derive(Debug, clap::Args)]
pub struct ValidateArgs {
    /// A Paparazzi server log: NAME.data with NAME.log beside it.
    pub file: PathBuf,
    /// The aircraft (default: the one that sent the most).
    #[arg(long, value_name = "AC_ID")]
    pub ac_id: Option<u8>,
    /// Only these flights, numbered from 1 in log order (repeatable).
    #[arg(long, value_name = "K")]
    pub flight: Vec<usize>,
    /// Only flights overlapping this log-time window, `T0,T1` in s.
    #[arg(long, value_name = "T0,T1")]
    pub window: Option<String>,
    /// The arena (and its boxes) from a scene file instead of the one the sonars describe.
    #[arg(long, value_name = "SCENE.toml")]
    pub scene: Option<PathBuf>,
    /// V-REP's position output for its twin of this log (`simulationPosition….log`; the
    /// orientation file of the same stamp is read beside it), scored beside Twinswarm's.
    #[arg(long, value_name = "FILE")]
    pub vrep: Option<PathBuf>,
    /// Log time of V-REP's time 0, s (default: found by matching V-REP's attitude to the
    /// AHRS).
    #[arg(long, value_name = "S")]
    pub vrep_start: Option<f64>,
    /// A twin has strayed when the running 1 s mean of its sonar disagreement (the median of the
    /// four directions, so that one sonar on an object the arena lacks does not count) exceeds
    /// this, m.
    #[arg(long, value_name = "M", default_value_t = 0.5)]
    pub stray_m: f64,
    /// The sync correction's gain: the fraction of the error corrected per second.
    #[arg(long, value_name = "PER_S", default_value_t = bridge::mixed::sync::SyncOptions::default().gain_per_s)]
    pub sync_gain: f64,
    /// The sync correction's largest speed, m/s.
    #[arg(long, value_name = "M_S", default_value_t = bridge::mixed::sync::SyncOptions::default().max_speed_m_s)]
    pub sync_max_speed: f64,
    /// The time constant of the sync's hold trim (the running mean of the attitude targets
    /// taken off them), s; 0 turns it off.
    #[arg(long, value_name = "S", default_value_t = bridge::mixed::sync::SyncOptions::default().hold_trim_time_constant_s)]
    pub hold_trim_s: f64,
    /// Which telemetry sets the twin's attitude targets (`measured`: the AHRS, what the copter
    /// did; `setpoint`: what it asked for, where the log has it).
    #[arg(long, value_name = "SOURCE", default_value = "measured", value_parser = crate::parse_twin_attitude)]
    pub twin_attitude: TwinAttitude,
    /// Write the pitch and roll overlays and the sonar comparison of each flight here (PNG).
    #[arg(long, value_name = "DIR")]
    pub plots: Option<PathBuf>,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Percentiles of a disagreement, cm.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct Spread {
    /// Samples.
    pub n: usize,
    /// Median.
    pub median: f64,
    /// 95th percentile.
    pub p95: f64,
}

impl Spread {
    fn of(v: &[f64]) -> Spread {
        let mut s: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
        s.sort_by(f64::total_cmp);
        let q = |p: f64| if s.is_empty() { f64::NAN } else { s[((s.len() - 1) as f64 * p).round() as usize] };
        Spread { n: s.len(), median: q(0.5), p95: q(0.95) }
    }
}

/// A twin's crash: its scoring ends there.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TwinCrash {
    /// Log time of the first step that found it crashed, s.
    pub t_s: f64,
    /// The same, s after take-off.
    pub after_take_off_s: f64,
    /// The cause, as the simulator gives it (`Wall`, `Floor { speed_m_s: 2.1 }`, …).
    pub cause: String,
}

/// How a twin (ours or V-REP's) held against the real copter over one flight: over the span
/// `[take-off + 1 s, landing]`, and of the errors only those of the twin before any crash.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Metrics {
    /// Sonar disagreement |twin − real| per direction (front, right, back, left), cm.
    pub sonar_cm: [Spread; 4],
    /// Over all four directions, cm.
    pub sonar_all_cm: Spread,
    /// Attitude RMS against the AHRS (roll, pitch), deg.
    pub attitude_rms_deg: [f64; 2],
    /// Height against the IR: mean (twin − IR) and RMS, cm.
    pub height_bias_cm: f64,
    /// RMS, cm.
    pub height_rms_cm: f64,
    /// Share of the span the twin flew with its centre inside the arena's walls: of every
    /// step of the span, those before any crash with its position inside (the steps after a
    /// crash are not inside: a twin that hit a wall did not stay in the arena).
    pub inside_share: f64,
    /// First time its position was outside the arena, s after take-off.
    pub first_outside_s: Option<f64>,
    /// First time the running 1 s mean of the sonar disagreement (the median of the four
    /// directions) exceeded `--stray-m`, s after take-off.
    pub strayed_s: Option<f64>,
    /// How long it stayed consistent: until it strayed or crashed, or the whole span, s.
    pub consistent_s: f64,
    /// The share of the span's sonar samples (after its first second) with the running
    /// disagreement within `--stray-m` (a twin that strays and comes back counts again once it
    /// is back; the samples after a crash never count).
    pub consistent_share: f64,
    /// The span scored: from the first step of the span to the last before any crash, s.
    pub scored_s: f64,
    /// The whole span, s: what the shares are of.
    pub span_s: f64,
    /// Its crash, if it crashed.
    pub crash: Option<TwinCrash>,
}

/// One flight's result.
#[derive(Clone, Debug, Serialize)]
pub struct FlightReport {
    /// Number in log order, from 1.
    pub index: usize,
    /// The flight.
    pub flight: Flight,
    /// Where the twin started.
    pub start: StartPose,
    /// Which messages drove the twin (`quantity ← messages`).
    pub sources: String,
    /// How far the copter turned in the flight (its yaw, 5th to 95th percentile), deg.
    pub turned_deg: f32,
    /// What the sync correction did for the synced twin.
    pub sync: Option<bridge::mixed::sync::SyncStats>,
    /// The twin with the sync correction (MEDUSA on the real sonars).
    pub synced: Metrics,
    /// The twin predicting from the telemetry alone.
    pub unsynced: Metrics,
    /// V-REP's twin over the span its output covers, if given and overlapping.
    pub vrep: Option<vrep::VrepScore>,
    /// The series the plots draw.
    #[serde(skip)]
    pub curves: Curves,
}

/// A labelled series of (t, roll, pitch), deg.
pub type AttitudeCurve = (String, Vec<(f64, f32, f32)>);
/// A labelled series of (t, [front, right, back, left]), m.
pub type SonarCurve = (String, Vec<(f64, [f32; 4])>);

/// Time series for the plots: the real copter's, then each twin's.
#[derive(Clone, Debug, Default)]
pub struct Curves {
    /// Attitude: the real copter's AHRS first.
    pub attitude: Vec<AttitudeCurve>,
    /// Sonars: the real copter's first.
    pub sonar: Vec<SonarCurve>,
}

/// The whole report.
#[derive(Clone, Debug, Serialize)]
pub struct ValidateReport {
    /// The `.data` file.
    pub log: String,
    /// The aircraft.
    pub ac_id: u8,
    /// Its name in the log.
    pub aircraft: String,
    /// The telemetry mode that explains what it sent.
    pub telemetry_mode: Option<String>,
    /// Lines of the `.data`, and those that could not be read.
    pub lines: u64,
    /// Unreadable lines.
    pub line_errors: LineErrors,
    /// Quantities whose values disagree with the unit they are read in
    /// ([`bridge::realflight::ir_unit_check`]); also printed to stderr.
    pub unit_warnings: Vec<UnitWarning>,
    /// The arena.
    pub arena: ArenaEstimate,
    /// Where the arena came from.
    pub arena_from: String,
    /// Per flight.
    pub flights: Vec<FlightReport>,
    /// Wall time, s.
    pub wall_s: f64,
}

/// Runs `twinswarm validate`.
pub fn run(args: ValidateArgs) -> anyhow::Result<()> {
    let started = Instant::now();
    for (flag, v) in [
        ("--stray-m", args.stray_m),
        ("--sync-gain", args.sync_gain),
        ("--sync-max-speed", args.sync_max_speed),
        ("--hold-trim-s", args.hold_trim_s),
    ] {
        if !(v.is_finite() && v >= 0.0) {
            return Err(BadInput(anyhow::anyhow!("{flag} {v}: must be a number at least 0")).into());
        }
    }
    let log = FlightLog::open(&args.file).map_err(|e| BadInput(e.into()))?;
    let ac_id = twinswarm::logcmd::aircraft_of(&log, args.ac_id, &args.file)?;
    // A unit the values contradict is said before anything is read from them (and even where
    // no flight is found); the values are never rescaled to agree.
    let unit_warnings: Vec<UnitWarning> = bridge::realflight::ir_unit_check(&log, ac_id).into_iter().collect();
    for w in &unit_warnings {
        eprintln!("warning: {}: {w}", args.file.display());
    }
    let series = Arc::new(Series::of(&log, ac_id));
    let all = bridge::realflight::flights(&series);
    anyhow::ensure!(!all.is_empty(), BadInput(anyhow::anyhow!("aircraft {ac_id}: no flight in the log")));
    let window = args.window.as_deref().map(parse_window).transpose()?;
    let chosen: Vec<(usize, Flight)> = all
        .iter()
        .enumerate()
        .map(|(i, f)| (i + 1, *f))
        .filter(|(k, _)| args.flight.is_empty() || args.flight.contains(k))
        .filter(|(_, f)| window.is_none_or(|[a, b]| f.end_s >= a && f.start_s <= b))
        .collect();
    anyhow::ensure!(!chosen.is_empty(), BadInput(anyhow::anyhow!("no flight of aircraft {ac_id} matches")));
    let base = base_world(&args, &series, &all)?;
    let vrep = match &args.vrep {
        Some(p) => Some(vrep::VrepTwin::open(p, &series, args.vrep_start)?),
        None => None,
    };
    let messages = Arc::new(log.config.messages.clone());
    let texts: Vec<(f64, String)> = log.from_aircraft(ac_id).map(|r| (r.time_s, log.text(r).to_owned())).collect();
    let mut flights = Vec::new();
    for (index, flight) in chosen {
        let report = validate_flight(&args, &base, &series, &messages, &texts, index, flight, ac_id, vrep.as_ref())?;
        flights.push(report);
    }
    let aircraft = log.config.aircraft(ac_id);
    let seen: Vec<&str> = texts
        .iter()
        .filter_map(|(_, t)| t.split(' ').nth(1))
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    let report = ValidateReport {
        log: args.file.display().to_string(),
        ac_id,
        aircraft: aircraft.map(|a| a.name.clone()).unwrap_or_default(),
        telemetry_mode: aircraft.and_then(|a| a.mode_sending(&seen)).map(str::to_owned),
        lines: log.lines,
        line_errors: log.errors.clone(),
        unit_warnings,
        arena: base.arena.clone(),
        arena_from: base.arena_from.clone(),
        flights,
        wall_s: started.elapsed().as_secs_f64(),
    };
    if let Some(dir) = &args.plots {
        for f in &report.flights {
            plots::draw(dir, f)?;
        }
    }
    if args.json {
        outln!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        outln!("{}", report.to_text(args.stray_m));
    }
    Ok(())
}

fn parse_window(s: &str) -> anyhow::Result<[f64; 2]> {
    let bad = || BadInput(anyhow::anyhow!("--window: expected T0,T1 in seconds with T0 < T1, got `{s}`"));
    let (a, b) = s.split_once(',').ok_or_else(bad)?;
    let (a, b): (f64, f64) = (a.trim().parse().map_err(|_| bad())?, b.trim().parse().map_err(|_| bad())?);
    if a.is_finite() && b.is_finite() && a < b { Ok([a, b]) } else { Err(bad().into()) }
}

/// The arena, as a scene without copters, and where it came from.
struct Base {
    spec: sim_core::SceneSpec,
    arena: ArenaEstimate,
    arena_from: String,
}

fn base_world(args: &ValidateArgs, series: &Series, flights: &[Flight]) -> anyhow::Result<Base> {
    let offset = sim_core::sensors::SonarSpec::default().mount_offset_m;
    let derived = bridge::realflight::derive_arena(series, flights, offset)
        .ok_or_else(|| BadInput(anyhow::anyhow!("the log's sonars never read all four walls in flight")))?;
    let (mut spec, arena, from) = match &args.scene {
        Some(path) => {
            let (_, spec, _) = crate::load_scene(Some(path))?;
            let mut arena = derived.clone();
            arena.size_m = spec.arena.size_m;
            (spec, arena, format!("scene {}", path.display()))
        }
        None => {
            let toml = format!(
                "name = \"lab-from-log\"\n[arena]\nsize_m = [{:.2}, {:.2}]\nheight_m = 2.5\n",
                derived.size_m[0], derived.size_m[1]
            );
            let spec = sim_core::SceneSpec::from_toml("<derived arena>", &toml)?;
            let how = format!(
                "the log's sonars: front+back and left+right most often read {:.2} m and {:.2} m \
                 ({} airborne samples, {:.0} % within 10 cm of those), plus 2 × {:.2} m mount offset",
                derived.sum_modes_m[0],
                derived.sum_modes_m[1],
                derived.samples,
                derived.share_square * 100.0,
                offset
            );
            (spec, derived, how)
        }
    };
    // The real sonars see walls, not the floor, and the log's readings are gated at 3 m.
    spec.sensors.sonar.floor_echo = false;
    spec.copters.clear();
    Ok(Base { spec, arena, arena_from: from })
}

/// A twin's pose at one log time (ours every control step, V-REP's every 50 ms).
#[derive(Clone, Copy, Debug)]
pub struct TracePoint {
    /// Log time, s.
    pub t_s: f64,
    /// Position, m, arena frame.
    pub pos_m: Vec3,
    /// Attitude (roll, pitch, yaw), rad, simulator frame.
    pub rpy_rad: [f32; 3],
}

#[allow(clippy::too_many_arguments)]
fn validate_flight(
    args: &ValidateArgs,
    base: &Base,
    series: &Arc<Series>,
    messages: &Arc<MessageSet>,
    texts: &[(f64, String)],
    index: usize,
    flight: Flight,
    ac_id: u8,
    vrep: Option<&vrep::VrepTwin>,
) -> anyhow::Result<FlightReport> {
    let start = bridge::realflight::start_pose(series, &flight, &base.arena).ok_or_else(|| {
        BadInput(anyhow::anyhow!("flight {index}: no sonar reading of all four walls in its first 1.5 s"))
    })?;
    let world = twin_world(base, &start, ac_id, flight.duration_s() + LEAD_S)?;
    let t0 = flight.start_s - LEAD_S;
    let mut runs = Vec::new();
    let synced = bridge::mixed::sync::SyncOptions {
        tracking: false,
        gain_per_s: args.sync_gain,
        max_speed_m_s: args.sync_max_speed,
        hold_trim_time_constant_s: args.hold_trim_s,
        ..Default::default()
    };
    for sync in [Some(synced), None] {
        runs.push(fly_twin(&world, series, messages, texts, t0, &start, ac_id, args.twin_attitude, sync)?);
    }
    let scorer = Scorer::new(&world, series, flight, start.level_rad, args.stray_m);
    let crash_of = |r: &Flown| {
        r.crash.as_ref().map(|(t_s, cause)| TwinCrash {
            t_s: *t_s,
            after_take_off_s: t_s - flight.start_s,
            cause: cause.clone(),
        })
    };
    let [synced, unsynced] = [&runs[0], &runs[1]].map(|r| scorer.score(&r.trace, crash_of(r).as_ref()));
    let vrep_trace = vrep.map(|v| v.trace_in(&flight)).filter(|t| !t.is_empty());
    let vrep = vrep.and_then(|v| v.score(&scorer));
    let mut traces =
        vec![("Twinswarm twin, sync on", &runs[0].trace[..]), ("Twinswarm twin, sync off", &runs[1].trace[..])];
    if let Some(t) = &vrep_trace {
        traces.push(("V-REP twin", &t[..]));
    }
    // The plots' series cost a sonar cone per sample and trace: only when plots are asked for.
    let curves = if args.plots.is_some() { scorer.curves(&traces) } else { Curves::default() };
    Ok(FlightReport {
        index,
        flight,
        start,
        sources: runs[0].sources.clone(),
        turned_deg: bridge::realflight::yaw_span_deg(series, &flight),
        sync: runs[0].sync.clone(),
        synced,
        unsynced,
        vrep,
        curves,
    })
}

/// The arena with the twin at the flight's start, on the floor.
fn twin_world(base: &Base, start: &StartPose, ac_id: u8, duration_s: f64) -> anyhow::Result<World> {
    let mut spec = base.spec.clone();
    spec.sim.duration_s = duration_s;
    let pose = bridge::paparazzi::pairing::Pose {
        x_m: f64::from(start.pos_m[0]),
        y_m: f64::from(start.pos_m[1]),
        z_m: 0.0,
        yaw_rad: f64::from(start.yaw_rad),
    };
    spec.copters.push(bridge::mixed::router::paired_copter("twin", sim_core::CopterKind::Real, ac_id, &pose));
    sim_core::scene::compile(&spec).context("the twin's world")
}

/// What one flown twin left.
struct Flown {
    trace: Vec<TracePoint>,
    sources: String,
    /// When (log time, s) and why it crashed.
    crash: Option<(f64, String)>,
    /// What the sync correction did (with it on).
    sync: Option<bridge::mixed::sync::SyncStats>,
}

/// Plays the log's texts into the step loop at their recorded times and records the twin.
struct Player {
    texts: Vec<(f64, String)>,
    next: usize,
    t0: f64,
    messages: Arc<MessageSet>,
    interpreter: Interpreter,
    requests: SyncSender<Request>,
    base: Instant,
    trace: Vec<TracePoint>,
    /// The log time of the first step that found the twin crashed, and the cause.
    crash: Option<(f64, String)>,
    queue_full: u64,
}

impl StepObserver for Player {
    fn after_step(&mut self, world: &World, state: &State, _inputs: &Inputs, _report: &StepReport) {
        let t = self.t0 + state.time_s(world);
        let p = state.pose(0);
        self.trace.push(TracePoint { t_s: t, pos_m: p.pos_m, rpy_rad: p.rpy_rad });
        if self.crash.is_none()
            && let Some(cause) = state.copters[0].crash
        {
            self.crash = Some((t, format!("{cause:?}")));
        }
        while let Some((tr, text)) = self.texts.get(self.next).filter(|(tr, _)| *tr <= t) {
            let since = (tr - self.t0).max(0.0);
            let origin = BusInput {
                key: format!("validate/pprz/{}", text.split(' ').take(2).collect::<Vec<_>>().join("/")),
                text: text.clone(),
                received_unix_ns: (since * 1e9) as u64,
            };
            let r = self.interpreter.interpret(&self.messages, origin, self.base + Duration::from_secs_f64(since));
            if self.requests.try_send(r).is_err() {
                self.queue_full += 1;
            }
            self.next += 1;
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn fly_twin(
    world: &World,
    _series: &Series,
    messages: &Arc<MessageSet>,
    texts: &[(f64, String)],
    t0: f64,
    start: &StartPose,
    ac_id: u8,
    attitude: TwinAttitude,
    sync: Option<bridge::mixed::sync::SyncOptions>,
) -> anyhow::Result<Flown> {
    let (tx, rx) = std::sync::mpsc::sync_channel::<Request>(8192);
    let end = t0 + world.params.duration_s;
    let mut interpreter = Interpreter::new(Arc::new(world.clone()), None, attitude);
    interpreter.set_heading_offset(ac_id, start.heading_offset_rad);
    interpreter.set_level(ac_id, start.level_rad);
    let first = texts.partition_point(|(t, _)| *t < t0);
    let player = Player {
        texts: texts[first..].iter().take_while(|(t, _)| *t <= end).cloned().collect(),
        next: 0,
        t0,
        messages: messages.clone(),
        interpreter,
        requests: tx,
        base: Instant::now(),
        trace: Vec::new(),
        crash: None,
        queue_full: 0,
    };
    let opts = LoopOptions { realtime: false, ticks: world.default_ticks(), sync, ..Default::default() };
    let stop = AtomicBool::new(false);
    let (world2, state, stats, player) = bridge::engine::run_watched(
        world.clone(),
        world.initial_state(),
        world.initial_inputs(),
        rx,
        None,
        player,
        &stop,
        &opts,
    );
    anyhow::ensure!(player.queue_full == 0, "{} telemetry inputs did not fit the loop's queue", player.queue_full);
    let report = player.interpreter.report();
    let sources = report.source_lines().into_iter().map(|(_, l)| l).collect::<Vec<_>>().join("; ");
    // Every step is observed; the final state is asked only should a crash have escaped that.
    let end_s = player.trace.last().map_or(t0, |p| p.t_s);
    let crash = player.crash.clone().or_else(|| state.copters[0].crash.map(|c| (end_s, format!("{c:?}"))));
    let _ = world2;
    let sync = stats.sync.into_iter().next().map(|(_, s)| s);
    Ok(Flown { trace: player.trace, sources, crash, sync })
}

/// Holds a twin's trace against the real copter's measurements over one flight.
pub struct Scorer<'a> {
    world: &'a World,
    sonar: SonarScene,
    series: &'a Series,
    flight: Flight,
    /// The AHRS's roll and pitch standing level, rad: taken off the real attitude.
    level: [f32; 2],
    stray_m: f64,
}

impl<'a> Scorer<'a> {
    fn new(world: &'a World, series: &'a Series, flight: Flight, level: [f32; 2], stray_m: f64) -> Self {
        let mut sonar = SonarScene::default();
        sim_core::step::fill_sonar_scene(world, &[], &mut sonar);
        Scorer { world, sonar, series, flight, level, stray_m }
    }

    /// The real copter's roll and pitch at `t_s`, level taken off, rad.
    fn real_attitude(&self, t_s: f64) -> Option<[f32; 2]> {
        let r = self.series.attitude_at(t_s)?.rpy_rad?;
        Some([r[0] - self.level[0], r[1] - self.level[1]])
    }

    /// What the twin's sonars would read at a pose (noise-free, gated as the real ones), m.
    fn twin_sonar(&self, p: &TracePoint) -> [f32; 4] {
        let rot: Quat = quat_from_euler(p.rpy_rad[0], p.rpy_rad[1], p.rpy_rad[2]);
        let range = self.world.sensors.spec.sonar.max_range_m;
        sonar_cones(&self.world.sensors, p.pos_m, rot)
            .map(|cone| self.sonar.cone_distance(&cone, usize::MAX, range).min(REAL_SONAR_MAX_M))
    }

    /// Scores a trace over its span, `[take-off + SETTLE_S, landing]` (and only where the
    /// trace is). A `crash` ends the scoring: the errors (sonar, attitude, height) and the stray
    /// test are of the steps before it; the shares (inside, consistent) are of the whole span,
    /// the time from the crash on in neither.
    pub fn score(&self, trace: &[TracePoint], crash: Option<&TwinCrash>) -> Metrics {
        let (from, to) = (self.flight.start_s + SETTLE_S, self.flight.end_s);
        let span: Vec<&TracePoint> = trace.iter().filter(|p| p.t_s >= from && p.t_s <= to).collect();
        let (Some(first), Some(last)) = (span.first(), span.last()) else {
            return Metrics { crash: crash.cloned(), ..Metrics::default() };
        };
        // Flying: the steps before the crash (the step that found it shows the twin on what it
        // hit, and every one after it a wreck).
        let crashed_s = crash.map_or(f64::INFINITY, |c| c.t_s);
        let flying: Vec<&TracePoint> = span.iter().copied().take_while(|p| p.t_s < crashed_s).collect();
        let mut m = Metrics {
            scored_s: flying.last().map_or(0.0, |p| p.t_s - first.t_s),
            span_s: last.t_s - first.t_s,
            crash: crash.cloned(),
            ..Metrics::default()
        };
        let [hx, hy] = self.world.arena.size_m.map(|v| v / 2.0);
        let (mut att, mut h, mut inside) = ([Vec::new(), Vec::new()], Vec::new(), 0usize);
        for p in &flying {
            // A position that is no number is nowhere, so not inside.
            if p.pos_m.x.abs() <= hx && p.pos_m.y.abs() <= hy {
                inside += 1;
            } else if m.first_outside_s.is_none() {
                m.first_outside_s = Some(p.t_s - self.flight.start_s);
            }
            if let Some(r) = self.real_attitude(p.t_s) {
                for k in 0..2 {
                    att[k].push(f64::from(p.rpy_rad[k] - r[k]).to_degrees());
                }
            }
            if let Some(z) = self.series.sensors_at(p.t_s).and_then(|s| s.ir_m) {
                h.push(f64::from(p.pos_m.z - z) * 100.0);
            }
        }
        m.inside_share = inside as f64 / span.len() as f64;
        m.attitude_rms_deg = att.map(|v| rms(&v));
        m.height_bias_cm = if h.is_empty() { f64::NAN } else { h.iter().sum::<f64>() / h.len() as f64 };
        m.height_rms_cm = rms(&h);
        self.score_sonar(trace, first.t_s, last.t_s, crashed_s, &mut m);
        m
    }

    /// The sonar metrics over the real sonar samples in `[from, to]`: those from `crashed_s` on
    /// are judged (after the first [`STRAY_WINDOW_S`]) and never consistent.
    fn score_sonar(&self, trace: &[TracePoint], from: f64, to: f64, crashed_s: f64, m: &mut Metrics) {
        let mut per = [Vec::new(), Vec::new(), Vec::new(), Vec::new()];
        let mut all = Vec::new();
        let mut window: std::collections::VecDeque<(f64, f64)> = Default::default();
        let mut sum = 0.0;
        let (mut judged, mut within) = (0usize, 0usize);
        for s in self.series.sensors.iter().filter(|s| s.t_s >= from && s.t_s <= to) {
            if s.t_s >= crashed_s {
                judged += usize::from(s.sonar_m.is_some() && s.t_s - from >= STRAY_WINDOW_S);
                continue;
            }
            let (Some(real), Some(p)) = (s.sonar_m, latest_point(trace, s.t_s)) else { continue };
            let twin = self.twin_sonar(p);
            let mut step = Vec::with_capacity(4);
            for k in 0..4 {
                let r = real[k].min(REAL_SONAR_MAX_M);
                let d = f64::from((twin[k] - r).abs()) * 100.0;
                per[k].push(d);
                step.push(d);
            }
            // The middle two of the four: one sonar on an object the arena lacks (a person, a
            // chair) is not the twin straying.
            let mut sorted = step.clone();
            sorted.sort_by(f64::total_cmp);
            let mean = (sorted[1] + sorted[2]) / 2.0;
            all.extend(step);
            window.push_back((s.t_s, mean));
            sum += mean;
            while window.front().is_some_and(|(t, _)| s.t_s - t > STRAY_WINDOW_S) {
                sum -= window.pop_front().map_or(0.0, |(_, v)| v);
            }
            let running = sum / window.len() as f64;
            if s.t_s - from >= STRAY_WINDOW_S {
                judged += 1;
                within += usize::from(running <= self.stray_m * 100.0);
                if m.strayed_s.is_none() && running > self.stray_m * 100.0 {
                    m.strayed_s = Some(s.t_s - self.flight.start_s);
                }
            }
        }
        m.sonar_cm = [0, 1, 2, 3].map(|k| Spread::of(&per[k]));
        m.sonar_all_cm = Spread::of(&all);
        // Consistent until it strayed or crashed, whichever came first (log time).
        let strayed = m.strayed_s.map(|s| s + self.flight.start_s);
        let ended = strayed.into_iter().chain((crashed_s < to).then_some(crashed_s)).reduce(f64::min);
        m.consistent_s = ended.map_or(m.span_s, |t| (t - from).max(0.0));
        m.consistent_share = within as f64 / judged.max(1) as f64;
    }
}

impl Scorer<'_> {
    /// The plots' series over the flight: the real copter's, then each trace's.
    fn curves(&self, traces: &[(&str, &[TracePoint])]) -> Curves {
        let f = self.flight;
        let within = |t: f64| t >= f.start_s - 1.0 && t <= f.end_s + 1.0;
        let deg = |r: f32| r.to_degrees();
        let mut c = Curves::default();
        let real_att = self.series.attitude.iter().filter(|s| within(s.t_s));
        c.attitude.push((
            "real copter (AHRS, level taken off)".into(),
            real_att.filter_map(|s| self.real_attitude(s.t_s).map(|r| (s.t_s, deg(r[0]), deg(r[1])))).collect(),
        ));
        let sensed: Vec<_> = self.series.sensors.iter().filter(|s| within(s.t_s) && s.sonar_m.is_some()).collect();
        c.sonar.push((
            "real copter".into(),
            sensed.iter().filter_map(|s| s.sonar_m.map(|r| (s.t_s, r.map(|v| v.min(REAL_SONAR_MAX_M))))).collect(),
        ));
        for (label, trace) in traces {
            let att = trace.iter().filter(|p| within(p.t_s)).map(|p| (p.t_s, deg(p.rpy_rad[0]), deg(p.rpy_rad[1])));
            c.attitude.push(((*label).into(), att.collect()));
            let sonar = sensed.iter().filter_map(|s| latest_point(trace, s.t_s).map(|p| (s.t_s, self.twin_sonar(p))));
            c.sonar.push(((*label).into(), sonar.collect()));
        }
        c
    }
}

fn latest_point(trace: &[TracePoint], t_s: f64) -> Option<&TracePoint> {
    let n = trace.partition_point(|p| p.t_s <= t_s);
    n.checked_sub(1).map(|i| &trace[i])
}

fn rms(v: &[f64]) -> f64 {
    if v.is_empty() { f64::NAN } else { (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt() }
}

impl ValidateReport {
    /// The terminal report: one block per flight, Twinswarm's twin synced and unsynced and
    /// V-REP's beside them.
    pub fn to_text(&self, stray_m: f64) -> String {
        let mut s = format!(
            "twinswarm validate: {} (aircraft {} {}, telemetry mode {})\n",
            self.log,
            self.ac_id,
            self.aircraft,
            self.telemetry_mode.as_deref().unwrap_or("?")
        );
        s += &format!(
            "  {} lines, {} unreadable{}\n",
            self.lines,
            self.line_errors.total(),
            if self.line_errors.by_cause.is_empty() {
                String::new()
            } else {
                format!(" {:?}", self.line_errors.by_cause)
            }
        );
        s +=
            &format!("  arena {:.2} × {:.2} m, from {}\n", self.arena.size_m[0], self.arena.size_m[1], self.arena_from);
        for f in &self.flights {
            s += &f.to_text(stray_m);
        }
        s += &format!(
            "  (sonar: |twin − real| in cm, median/p95 front right back left | all; attitude: RMS against the AHRS; \
             inside: share of the flight flown inside the arena; strayed: running {STRAY_WINDOW_S:.0} s mean of the \
             median sonar disagreement above {:.0} cm; a twin's crash ends its scoring; {:.2} s wall)\n",
            stray_m * 100.0,
            self.wall_s
        );
        s
    }
}

impl FlightReport {
    fn to_text(&self, _stray_m: f64) -> String {
        let f = &self.flight;
        let mut s = format!(
            "  flight {}: log {:.1}-{:.1} s ({:.1} s), start ({:.2}, {:.2}) m, yaw {:.0}°\n    driven by: {}\n",
            self.index,
            f.start_s,
            f.end_s,
            f.duration_s(),
            self.start.pos_m[0],
            self.start.pos_m[1],
            self.start.yaw_rad.to_degrees(),
            self.sources
        );
        s += "    twin                      sonar F      R      B      L    | all       roll  pitch   height   inside  strayed@  consistent\n";
        let mut rows = vec![("twinswarm, sync on", &self.synced), ("twinswarm, sync off", &self.unsynced)];
        if let Some(v) = &self.vrep {
            rows.push(("v-rep (its own output)", &v.metrics));
        }
        for (label, m) in rows {
            // A twin that crashed before its scoring began has nothing to show: "-", not NaN.
            let d = |x: &Spread| {
                if x.median.is_finite() { format!("{:.0}/{:.0}", x.median, x.p95) } else { "-".into() }
            };
            let deg = |v: f64| if v.is_finite() { format!("{v:.1}°") } else { "-".into() };
            let cm = |v: f64| if v.is_finite() { format!("{v:.1} cm") } else { "- cm".into() };
            s += &format!(
                "    {:<24} {:>7} {:>6} {:>6} {:>6} | {:>8} {:>6} {:>6} {:>8} {:>6.0} % {:>8} {:>6.1} s ({:.0} %)\n",
                label,
                d(&m.sonar_cm[0]),
                d(&m.sonar_cm[1]),
                d(&m.sonar_cm[2]),
                d(&m.sonar_cm[3]),
                d(&m.sonar_all_cm),
                deg(m.attitude_rms_deg[0]),
                deg(m.attitude_rms_deg[1]),
                cm(m.height_rms_cm),
                m.inside_share * 100.0,
                m.strayed_s.map_or("-".into(), |t| format!("{t:.1} s")),
                m.consistent_s,
                m.consistent_share * 100.0
            );
        }
        if let Some(y) = &self.sync {
            s += &format!(
                "    sync: {} MEDUSA estimates, {} not used (confidence under {}); trim {:.1}° pitch, {:.1}° roll\n",
                y.medusa_updates,
                y.medusa_rejected,
                bridge::mixed::sync::SyncOptions::default().min_confidence,
                y.trim_deg[0],
                y.trim_deg[1]
            );
        }
        if self.turned_deg > bridge::realflight::TURNED_DEG {
            s += &format!(
                "    the copter turned {:.0}° in this flight: its front + back and left + right sums mix the \
                 arena's sides, so an arena derived from them or its start may be wrong (give the room with --scene)\n",
                self.turned_deg
            );
        }
        if let Some(v) = &self.vrep {
            s += &format!(
                "    (v-rep: log {:.1}-{:.1} s; t_log = {:.2} s + {:.4} × its time, {})\n",
                v.from_s, v.to_s, v.start_s, v.rate, v.start_from
            );
        }
        for (label, m) in [("sync on", &self.synced), ("sync off", &self.unsynced)] {
            if let Some(c) = &m.crash {
                let when = match c.after_take_off_s {
                    a if a < 0.0 => format!("{:.1} s before take-off", -a),
                    a => format!("{a:.1} s after take-off"),
                };
                s += &format!(
                    "    twin ({label}) crashed: {} at log {:.1} s ({when}); scored to then ({:.1} of {:.1} s), the \
                     rest neither inside nor consistent\n",
                    c.cause, c.t_s, m.scored_s, m.span_s
                );
            }
        }
        s
    }
}

mod plots;

#[cfg(test)]
mod tests {
    //! Every metric `validate` reports, shown passing on a twin that flies as the real copter
    //! did and failing on a case made to fail it.

    use super::*;
    use bridge::realflight::Sample;

    /// The flight scored: its span is 11-30 s.
    const FLIGHT: Flight = Flight { start_s: 10.0, end_s: 30.0 };

    /// A 4 × 3 m arena with a twin in it, as `validate` builds it.
    fn world() -> World {
        let toml = "name = \"test-arena\"\n[arena]\nsize_m = [4.0, 3.0]\nheight_m = 2.5\n";
        let mut spec = sim_core::SceneSpec::from_toml("<test arena>", toml).expect("a scene");
        spec.sensors.sonar.floor_echo = false;
        spec.copters.clear();
        let arena = ArenaEstimate { size_m: [4.0, 3.0], sum_modes_m: [3.8, 2.8], samples: 0, share_square: 1.0 };
        let base = Base { spec, arena, arena_from: "test".into() };
        let start =
            StartPose { pos_m: [0.0, 0.0], yaw_rad: 0.0, heading_offset_rad: 0.0, level_rad: [0.0; 2], samples: 0 };
        twin_world(&base, &start, 5, 40.0).expect("the twin's world")
    }

    /// A hover that wanders about the middle of the arena at 0.6 m, rocking a little.
    fn hover(t_s: f64) -> TracePoint {
        let t = t_s as f32;
        TracePoint {
            t_s,
            pos_m: Vec3::new(0.5 * (t / 3.0).sin(), 0.3 * (t / 4.0).cos(), 0.6),
            rpy_rad: [0.05 * t.sin(), 0.03 * t.cos(), 0.0],
        }
    }

    /// The real copter's measurements every 0.1 s from 0 to 40 s along `real`: its sonars as a
    /// twin there would read them, its IR its height, its AHRS its attitude.
    fn measured_along(world: &World, real: impl Fn(f64) -> TracePoint) -> Series {
        let nothing = Series::default();
        let probe = Scorer::new(world, &nothing, FLIGHT, [0.0; 2], 0.5);
        let mut s = Series::default();
        for k in 0..=400 {
            let p = real(f64::from(k) / 10.0);
            let rpy_rad = Some(p.rpy_rad);
            s.sensors.push(Sample { t_s: p.t_s, sonar_m: Some(probe.twin_sonar(&p)), ir_m: Some(p.pos_m.z), rpy_rad });
            s.attitude.push(Sample { t_s: p.t_s, sonar_m: None, ir_m: None, rpy_rad });
        }
        s
    }

    /// A twin's trace along `twin`, every control step (0.05 s) from 0 to 40 s.
    fn trace_along(twin: impl Fn(f64) -> TracePoint) -> Vec<TracePoint> {
        (0..=800).map(|k| twin(f64::from(k) / 20.0)).collect()
    }

    fn score(real: impl Fn(f64) -> TracePoint, twin: impl Fn(f64) -> TracePoint, crash: Option<&TwinCrash>) -> Metrics {
        let world = world();
        let series = measured_along(&world, real);
        Scorer::new(&world, &series, FLIGHT, [0.0; 2], 0.5).score(&trace_along(twin), crash)
    }

    fn near(a: f64, b: f64, tol: f64) -> bool {
        (a - b).abs() <= tol
    }

    #[test]
    fn a_twin_that_flies_as_the_real_copter_passes_every_metric() {
        let m = score(hover, hover, None);
        assert!(near(m.span_s, 19.0, 1e-9) && near(m.scored_s, 19.0, 1e-9), "{m:?}");
        assert_eq!((m.inside_share, m.first_outside_s), (1.0, None), "{m:?}");
        assert!(m.sonar_all_cm.n > 700 && m.sonar_all_cm.p95 < 0.5, "{m:?}");
        assert!(m.sonar_cm.iter().all(|s| s.n > 180 && s.p95 < 0.5), "{m:?}");
        // The AHRS every 0.1 s, the twin every 0.05 s: a step's worth of rocking apart.
        assert!(m.attitude_rms_deg.iter().all(|d| *d < 0.5), "{m:?}");
        assert!(m.height_rms_cm < 0.5 && m.height_bias_cm.abs() < 0.5, "{m:?}");
        assert_eq!((m.strayed_s, m.consistent_share), (None, 1.0), "{m:?}");
        assert!(near(m.consistent_s, 19.0, 1e-9), "{m:?}");
        assert_eq!(m.crash, None);
    }

    #[test]
    fn a_twin_that_leaves_the_arena_is_not_inside_for_that_time() {
        // From 20 s to 25 s the twin is 0.5 m beyond the +x wall (a scene without walls, or a
        // trace from elsewhere: V-REP's).
        let beyond = |t: f64| {
            let mut p = hover(t);
            if (20.0..25.0).contains(&t) {
                p.pos_m.x = 2.5;
            }
            p
        };
        let m = score(hover, beyond, None);
        assert!(near(m.inside_share, 281.0 / 381.0, 1e-9), "{m:?}");
        assert_eq!(m.first_outside_s, Some(10.0), "{m:?}");
        // A twin whose position is no number is not inside either.
        let lost = |t: f64| TracePoint { pos_m: Vec3::new(f32::NAN, 0.0, 0.6), ..hover(t) };
        let m = score(hover, lost, None);
        assert_eq!((m.inside_share, m.first_outside_s), (0.0, Some(1.0)), "{m:?}");
    }

    #[test]
    fn a_twin_whose_sonars_disagree_strays_and_is_not_consistent() {
        // The twin 0.8 m towards −x of where the real copter is: its front and back sonars
        // read 1.6 m off, its left and right the same.
        let shifted =
            |dx: f32| move |t: f64| TracePoint { pos_m: hover(t).pos_m + Vec3::new(dx, 0.0, 0.0), ..hover(t) };
        let m = score(shifted(0.8), shifted(-0.8), None);
        assert_eq!(m.inside_share, 1.0, "it never left the arena: {m:?}");
        assert!(m.sonar_cm[0].median > 100.0 && m.sonar_cm[2].median > 100.0, "{m:?}");
        assert!(m.sonar_cm[1].p95 < 20.0 && m.sonar_cm[3].p95 < 20.0, "{m:?}");
        // It strays as soon as it is judged (after the span's first second) and never returns.
        assert_eq!(m.strayed_s, Some(2.0), "{m:?}");
        assert!(near(m.consistent_s, 1.0, 1e-9) && m.consistent_share == 0.0, "{m:?}");
    }

    #[test]
    fn a_twin_at_the_wrong_height_fails_the_height_rms() {
        let high = |t: f64| TracePoint { pos_m: hover(t).pos_m + Vec3::new(0.0, 0.0, 0.3), ..hover(t) };
        let m = score(hover, high, None);
        assert!(near(m.height_rms_cm, 30.0, 0.01) && near(m.height_bias_cm, 30.0, 0.01), "{m:?}");
        assert!(m.attitude_rms_deg.iter().all(|d| *d < 0.5), "only the height: {m:?}");
    }

    #[test]
    fn a_twin_at_the_wrong_attitude_fails_the_attitude_rms() {
        let rolled = |t: f64| {
            let p = hover(t);
            TracePoint { rpy_rad: [p.rpy_rad[0] + 10f32.to_radians(), p.rpy_rad[1], p.rpy_rad[2]], ..p }
        };
        let m = score(hover, rolled, None);
        assert!(near(m.attitude_rms_deg[0], 10.0, 0.2), "roll: {m:?}");
        assert!(m.attitude_rms_deg[1] < 0.5, "pitch: {m:?}");
        assert!(m.height_rms_cm < 0.5, "{m:?}");
    }

    #[test]
    fn a_crash_ends_the_scoring_and_the_time_after_it_is_neither_inside_nor_consistent() {
        // The twin hits the +x wall at 20 s and lies there, a wreck on the floor on its side,
        // while the real copter flies on.
        let wrecked = |t: f64| {
            if t < 20.0 {
                hover(t)
            } else {
                TracePoint { t_s: t, pos_m: Vec3::new(1.9, 0.0, 0.05), rpy_rad: [1.4, 0.2, 0.0] }
            }
        };
        // Scored on as before, the wreck is "inside" the whole flight, and its errors are the
        // wreck's.
        let blind = score(hover, wrecked, None);
        assert_eq!(blind.inside_share, 1.0, "{blind:?}");
        assert!(blind.height_rms_cm > 30.0 && blind.attitude_rms_deg[0] > 50.0, "{blind:?}");
        let crash = TwinCrash { t_s: 20.0, after_take_off_s: 10.0, cause: "Wall".into() };
        let m = score(hover, wrecked, Some(&crash));
        assert_eq!(m.crash.as_ref(), Some(&crash));
        assert!(near(m.scored_s, 8.95, 1e-9) && near(m.span_s, 19.0, 1e-9), "{m:?}");
        // 180 steps flown (11.00-19.95 s) of the span's 381.
        assert!(near(m.inside_share, 180.0 / 381.0, 1e-9), "{m:?}");
        assert_eq!(m.first_outside_s, None, "it never left: it crashed");
        // The errors are the flying twin's.
        assert!(m.height_rms_cm < 0.5 && m.attitude_rms_deg.iter().all(|d| *d < 0.5), "{m:?}");
        assert!(m.sonar_all_cm.n > 0 && m.sonar_all_cm.p95 < 0.5, "{m:?}");
        // Judged from 12 s: 80 sonar samples before the crash, 101 from it to 30 s.
        assert!(near(m.consistent_share, 80.0 / 181.0, 1e-9), "{m:?}");
        assert!(near(m.consistent_s, 9.0, 1e-9) && m.strayed_s.is_none(), "{m:?}");
        // Crashed before the span: nothing scored, nothing passed.
        let early = TwinCrash { t_s: 10.5, after_take_off_s: 0.5, cause: "Floor { speed_m_s: 2.0 }".into() };
        let m = score(hover, hover, Some(&early));
        assert_eq!((m.inside_share, m.consistent_share, m.consistent_s, m.scored_s), (0.0, 0.0, 0.0, 0.0), "{m:?}");
        assert!(m.height_rms_cm.is_nan() && m.attitude_rms_deg[0].is_nan() && m.sonar_all_cm.n == 0, "{m:?}");
    }

    #[test]
    fn the_report_names_a_crash_with_its_time_and_cause() {
        let crash = TwinCrash { t_s: 20.0, after_take_off_s: 10.0, cause: "Wall".into() };
        let synced = score(hover, hover, Some(&crash));
        let start =
            StartPose { pos_m: [0.0; 2], yaw_rad: 0.0, heading_offset_rad: 0.0, level_rad: [0.0; 2], samples: 9 };
        let report = FlightReport {
            index: 2,
            flight: FLIGHT,
            start,
            sources: "attitude ← FINKEN_SENSOR_MODEL".into(),
            turned_deg: 10.0,
            sync: Some(bridge::mixed::sync::SyncStats {
                medusa_updates: 36,
                medusa_rejected: 30,
                trim_deg: [1.5, -0.5],
                ..Default::default()
            }),
            unsynced: score(hover, hover, None),
            synced,
            vrep: None,
            curves: Curves::default(),
        };
        let text = report.to_text(0.5);
        assert!(text.contains("twin (sync on) crashed: Wall at log 20.0 s (10.0 s after take-off)"), "{text}");
        assert!(!text.contains("sync off) crashed"), "{text}");
        assert!(text.contains("sync: 36 MEDUSA estimates, 30 not used"), "{text}");
        assert!(text.contains("trim 1.5° pitch, -0.5° roll"), "{text}");
        assert!(!text.contains("turned"), "a copter that turned 10° kept its heading: {text}");
        let turned = FlightReport { turned_deg: 110.0, ..report.clone() };
        assert!(turned.to_text(0.5).contains("the copter turned 110° in this flight"), "{}", turned.to_text(0.5));
        let json = serde_json::to_value(&report).expect("json");
        assert_eq!(json["synced"]["crash"]["cause"], "Wall", "{json}");
        assert_eq!(json["synced"]["crash"]["t_s"], 20.0, "{json}");
        assert!(json["unsynced"]["crash"].is_null(), "{json}");
    }
}
