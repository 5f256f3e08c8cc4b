//! `twinswarm localize --eval`: MEDUSA localization measured on a simulated Wall-Avoid flight.
//!
//! The embedded lab scene is flown with one copter (or both) in Wall-Avoid at 0.8 m, with
//! σ = 5 cm sonar noise, 2° AHRS yaw noise and the default yaw-bias random walk. Every control
//! step each evaluated copter's **own** readings feed raw MEDUSA and the MEDUSA particle
//! filter: its sonar readings (the cap means no echo), its AHRS yaw (σ = 2°; the filter
//! estimates the bias) and its commanded attitude (the setpoint) as the motion input. The
//! estimates are compared with the ground-truth position at the instant the sonars were
//! sampled.
//!
//! Sensor sets:
//! - **2**: front + right, the first two channels of Paparazzi's `SONAR_ARRAY`. Any two
//!   *perpendicular* sonars fix both axes in a rectangle (two opposite ones leave one axis
//!   free); front + left is the mirror image and performs the same.
//! - **4**: the FINken's four physical sonars.
//! - **8**: the four physical sonars plus four diagonal ones synthesised here with sim-core's
//!   exact cone geometry ([`SonarScene::cone_distance`]), noise from a seeded stream of their
//!   own, and sim-core's quantisation and cap ([`sonar_reading`]).
//!
//! The flight: Wall-Avoid only pushes away from walls, so a hovering copter would sit still.
//! Like a pilot flying Wall-Avoid, the harness commands a cruise velocity (0.3 m/s, body frame)
//! whose direction changes every 3–8 s (seeded); Wall-Avoid overrides it near obstacles.
//! Statistics start 5 s after take-off (the filter starts from a uniform particle cloud at
//! tick 0).

use std::time::Instant;

use anyhow::Context;
use medusa::{FilterEstimate, Medusa, MedusaFilter, MotionInput, YawEstimate};
use nalgebra::Vector2;
use serde::Serialize;
use sim_core::control::FlightMode;
use sim_core::geometry::Cone;
use sim_core::math::{Real, Vec3, wrap_angle_rad};
use sim_core::rng::Rng32;
use sim_core::scene::{self, SceneSpec};
use sim_core::sensors::{SonarScene, sonar_reading};
use sim_core::{CopterState, State, World, step};

use crate::BadInput;

/// Flight height of the evaluation, m.
pub const FLIGHT_HEIGHT_M: Real = 0.8;
/// Cruise speed commanded between wall encounters, m/s.
pub const CRUISE_SPEED_M_S: Real = 0.3;
/// Largest turn rate of the heading command between legs, deg/s.
pub const TURN_RATE_DEG_S: Real = 30.0;
/// Statistics start this long after take-off, s.
pub const SETTLE_S: f64 = 5.0;
/// Sonar noise of the evaluation, m.
pub const SONAR_SIGMA_M: Real = 0.05;
/// AHRS yaw noise of the evaluation, deg.
pub const YAW_NOISE_DEG: Real = 2.0;
/// Body-frame directions of the 8 sonar slots (deg, CCW from forward): the 4 physical ones in
/// sim-core order (front, right, back, left), then 4 synthetic diagonals.
pub const SLOT_ANGLES_DEG: [f64; 8] = [0.0, -90.0, 180.0, 90.0, 45.0, -45.0, -135.0, 135.0];
/// Slot names, in slot order.
pub const SLOT_NAMES: [&str; 8] =
    ["front", "right", "back", "left", "front-left", "front-right", "back-right", "back-left"];
/// The evaluated sensor sets, as slot indices.
pub const SENSOR_SETS: [&[usize]; 3] = [&[0, 1], &[0, 1, 2, 3], &[0, 1, 2, 3, 4, 5, 6, 7]];

/// Which world to fly in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum WorldChoice {
    /// The 4 m × 3 m lab arena without its boxes (the setup).
    Empty,
    /// The lab with its table, crate and pillar.
    Lab,
    /// Both, one after the other.
    Both,
}

/// `twinswarm localize`.
#[derive(Debug, clap::Args)]
pub struct LocalizeArgs {
    /// Evaluate MEDUSA (raw and filtered) against ground truth on a simulated Wall-Avoid flight.
    #[arg(long)]
    pub eval: bool,
    /// Length of the flight, minutes.
    #[arg(long, value_name = "M", default_value_t = 9.0)]
    pub minutes: f64,
    /// Seed of the simulation and the harness (default: the lab scene's seed).
    #[arg(long, value_name = "N")]
    pub seed: Option<u64>,
    /// World: the empty 4 m × 3 m arena, the lab with its boxes, or both.
    #[arg(long, value_enum, default_value_t = WorldChoice::Empty)]
    pub world: WorldChoice,
    /// Copters flying (1 or 2, from the lab scene); each is evaluated.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=2))]
    pub copters: u8,
    /// Keep the start heading for the whole flight instead of a new random heading every leg.
    #[arg(long)]
    pub hold_yaw: bool,
    /// Evaluate twin synchronisation end to end: a real-copter stand-in's telemetry drives
    /// a twin, with correction off, with MEDUSA, and (with `--tracking-dropout`) with MEDUSA
    /// and a tracking pose that drops out.
    #[arg(long, conflicts_with = "eval")]
    pub sync_eval: bool,
    /// `--sync-eval`: a uniform telemetry link instead of the measured one (`bridge::mixed::link`):
    /// every message on time, up to this late, ms.
    #[arg(long, value_name = "MS")]
    pub jitter_ms: Option<f64>,
    /// `--sync-eval`: the measured link saturated, the telemetry asking LOAD times what the
    /// modem carries (1.27: the 16 Dec 2015 flight's); at most 1 is the paper's link.
    #[arg(long, value_name = "LOAD", default_value_t = 1.0)]
    pub link_load: f64,
    /// `--sync-eval`: probability that a telemetry message is lost.
    #[arg(long, value_name = "P", default_value_t = 0.05)]
    pub loss: f64,
    /// `--sync-eval`: also fly with a tracking pose (0.2 s lag) that is silent from START to
    /// END simulated seconds.
    #[arg(long, value_name = "START,END")]
    pub tracking_dropout: Option<String>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// Error statistics of one estimator, cm.
#[derive(Clone, Debug, Serialize)]
pub struct ErrorStats {
    /// Median position error, cm.
    pub median_cm: f64,
    /// 95th percentile, cm.
    pub p95_cm: f64,
    /// Largest error, cm.
    pub max_cm: f64,
}

/// One sensor set on one copter.
#[derive(Clone, Debug, Serialize)]
pub struct SensorSetReport {
    /// Number of sonars.
    pub sensors: usize,
    /// Their names.
    pub slots: Vec<&'static str>,
    /// Raw MEDUSA (the best candidate).
    pub raw: ErrorStats,
    /// Raw MEDUSA refined by Gauss-Newton on all readings.
    pub refined: ErrorStats,
    /// The particle filter.
    pub filtered: ErrorStats,
    /// Median filter confidence.
    pub confidence_median: f64,
    /// 5th percentile of the filter confidence.
    pub confidence_p05: f64,
    /// Median confidence when the filter error is above 15 cm (NaN-free: 0 if never).
    pub confidence_median_when_err_above_15cm: f64,
    /// Share of samples with a filter error above 15 cm.
    pub share_filtered_above_15cm: f64,
    /// Non-finite estimates or confidences seen (should be 0).
    pub non_finite: u64,
    /// Mean wall-clock cost of one filter update (predict + correct), µs.
    pub filter_us_per_update: f64,
    /// Mean wall-clock cost of one raw MEDUSA `locate`, µs.
    pub raw_us_per_locate: f64,
    /// Final yaw-bias estimate minus the true bias, deg.
    pub final_yaw_bias_error_deg: f64,
}

/// One evaluated copter.
#[derive(Clone, Debug, Serialize)]
pub struct CopterReport {
    /// Copter name.
    pub name: String,
    /// Samples in the statistics (one per control step after settling).
    pub samples: u64,
    /// Crash, if any (statistics stop there).
    pub crash: Option<String>,
    /// Distance flown horizontally, m.
    pub distance_m: f64,
    /// Ground-truth x range visited, m.
    pub x_range_m: [f64; 2],
    /// Ground-truth y range visited, m.
    pub y_range_m: [f64; 2],
    /// Largest |true yaw bias| during the flight, deg.
    pub max_abs_yaw_bias_deg: f64,
    /// Per sensor set: 2, 4, 8.
    pub sets: Vec<SensorSetReport>,
}

/// One flight.
#[derive(Clone, Debug, Serialize)]
pub struct FlightReport {
    /// `empty` or `lab`.
    pub world: WorldChoice,
    /// Boxes in the simulated world.
    pub boxes_simulated: Vec<String>,
    /// Boxes given to MEDUSA.
    pub boxes_known_to_medusa: Vec<String>,
    /// Simulated minutes.
    pub minutes: f64,
    /// Seed.
    pub seed: u64,
    /// Whether the heading was held (else a new random heading every leg).
    pub hold_yaw: bool,
    /// Wall-clock time of the whole flight and evaluation, s.
    pub wall_s: f64,
    /// Evaluated copters.
    pub copters: Vec<CopterReport>,
}

/// The whole evaluation.
#[derive(Clone, Debug, Serialize)]
pub struct EvalReport {
    /// Sonar noise, m.
    pub sonar_sigma_m: f64,
    /// Yaw noise, deg.
    pub yaw_noise_deg: f64,
    /// Yaw-bias random walk, deg/√s.
    pub yaw_bias_walk_deg_per_sqrt_s: f64,
    /// Flight height, m.
    pub height_m: f64,
    /// Seconds after take-off when statistics start.
    pub settle_s: f64,
    /// Build profile of this binary (timings depend on it).
    pub profile: &'static str,
    /// Flights.
    pub flights: Vec<FlightReport>,
    /// Target: 4 sensors, filtered, median < 5 cm and p95 < 15 cm, on every evaluated copter.
    pub target_4_sensors_met: bool,
}

/// The arguments both evaluations check.
pub fn check(args: &LocalizeArgs) -> anyhow::Result<()> {
    if !args.eval && !args.sync_eval {
        return Err(BadInput(anyhow::anyhow!(
            "localize: give `--eval` (MEDUSA accuracy) or `--sync-eval` (twin synchronisation)"
        ))
        .into());
    }
    if !(args.minutes.is_finite() && args.minutes > 0.0 && args.minutes <= 24.0 * 60.0) {
        return Err(BadInput(anyhow::anyhow!("--minutes must be in (0, 1440], got {}", args.minutes)).into());
    }
    Ok(())
}

/// Runs `localize --eval` (`--sync-eval` is [`crate::synceval::run`]).
pub fn run(args: LocalizeArgs) -> anyhow::Result<()> {
    check(&args)?;
    let worlds: &[WorldChoice] = match args.world {
        WorldChoice::Both => &[WorldChoice::Empty, WorldChoice::Lab],
        WorldChoice::Empty => &[WorldChoice::Empty],
        WorldChoice::Lab => &[WorldChoice::Lab],
    };
    let mut flights = Vec::new();
    for &w in worlds {
        flights.push(evaluate(w, args.minutes, args.seed, usize::from(args.copters), args.hold_yaw)?);
    }
    let walk = eval_scene(WorldChoice::Empty, args.minutes, args.seed, 1)?.sensors.imu.yaw_bias_walk_deg_per_sqrt_s;
    let report = EvalReport::new(flights, f64::from(walk));
    if args.json {
        outln!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        out!("{}", report.to_text());
    }
    Ok(())
}

impl EvalReport {
    fn new(flights: Vec<FlightReport>, yaw_bias_walk_deg_per_sqrt_s: f64) -> Self {
        let target = flights.iter().flat_map(|f| &f.copters).all(|c| {
            c.sets.iter().filter(|s| s.sensors == 4).all(|s| s.filtered.median_cm < 5.0 && s.filtered.p95_cm < 15.0)
        });
        Self {
            sonar_sigma_m: f64::from(SONAR_SIGMA_M),
            yaw_noise_deg: f64::from(YAW_NOISE_DEG),
            yaw_bias_walk_deg_per_sqrt_s,
            height_m: f64::from(FLIGHT_HEIGHT_M),
            settle_s: SETTLE_S,
            profile: if cfg!(debug_assertions) { "debug" } else { "release" },
            flights,
            target_4_sensors_met: target,
        }
    }

    /// The table.
    pub fn to_text(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let _ = writeln!(
            s,
            "twinswarm localize --eval: Wall-Avoid at {:.1} m, sonar σ {:.0} cm, yaw noise {:.0}° + bias walk {}°/√s; \
             statistics from {:.0} s after take-off; {} build",
            self.height_m,
            self.sonar_sigma_m * 100.0,
            self.yaw_noise_deg,
            self.yaw_bias_walk_deg_per_sqrt_s,
            self.settle_s,
            self.profile
        );
        for f in &self.flights {
            let _ = writeln!(
                s,
                "\nworld {:?}: {:.1} min simulated, seed {}, heading {}, {:.1} s wall; boxes simulated [{}], known to MEDUSA [{}]",
                f.world,
                f.minutes,
                f.seed,
                if f.hold_yaw { "held" } else { "random per leg" },
                f.wall_s,
                f.boxes_simulated.join(", "),
                f.boxes_known_to_medusa.join(", ")
            );
            for c in &f.copters {
                let _ = writeln!(
                    s,
                    "  {}: {} samples, flew {:.0} m over x [{:.2}, {:.2}] y [{:.2}, {:.2}], max |yaw bias| {:.1}°{}",
                    c.name,
                    c.samples,
                    c.distance_m,
                    c.x_range_m[0],
                    c.x_range_m[1],
                    c.y_range_m[0],
                    c.y_range_m[1],
                    c.max_abs_yaw_bias_deg,
                    c.crash.as_ref().map(|x| format!(", CRASHED: {x}")).unwrap_or_default()
                );
                let _ = writeln!(
                    s,
                    "    sonars | raw MEDUSA cm | refined cm    | filtered cm         | confidence       | filt > 15 cm | µs/update"
                );
                let _ = writeln!(
                    s,
                    "           |   med    p95  |   med    p95  |  med   p95    max  | med   p05  >15cm | share        | filter   raw"
                );
                for r in &c.sets {
                    let _ = writeln!(
                        s,
                        "    {:>6} | {:>5.1} {:>6.1}  | {:>5.1} {:>6.1}  | {:>4.1} {:>5.1} {:>6.1}  | {:.2}  {:.2}  {:.2} | {:>5.1} %      | {:>6.0} {:>5.0}",
                        r.sensors,
                        r.raw.median_cm,
                        r.raw.p95_cm,
                        r.refined.median_cm,
                        r.refined.p95_cm,
                        r.filtered.median_cm,
                        r.filtered.p95_cm,
                        r.filtered.max_cm,
                        r.confidence_median,
                        r.confidence_p05,
                        r.confidence_median_when_err_above_15cm,
                        r.share_filtered_above_15cm * 100.0,
                        r.filter_us_per_update,
                        r.raw_us_per_locate,
                    );
                }
            }
        }
        let _ = writeln!(
            s,
            "\ntarget (4 sonars, filtered: median < 5 cm, p95 < 15 cm): {}",
            if self.target_4_sensors_met { "met" } else { "NOT met" }
        );
        s
    }
}

/// The scene of one evaluation flight.
pub fn eval_scene(world: WorldChoice, minutes: f64, seed: Option<u64>, copters: usize) -> anyhow::Result<SceneSpec> {
    let (mut spec, _) = scene::load_default();
    if let Some(seed) = seed {
        spec.sim.seed = seed;
    }
    spec.sim.duration_s = minutes * 60.0;
    if world != WorldChoice::Lab {
        spec.boxes.clear();
    }
    spec.copters.truncate(copters.max(1));
    for c in &mut spec.copters {
        c.mode = FlightMode::WallAvoid;
        c.command.height_m = FLIGHT_HEIGHT_M;
    }
    spec.sensors.enabled = true;
    spec.sensors.noise = true;
    spec.sensors.sonar.noise_sigma_m = SONAR_SIGMA_M;
    spec.sensors.imu.yaw_noise_deg = YAW_NOISE_DEG;
    Ok(spec)
}

/// Raw MEDUSA + filter for one sensor set of one copter, and their statistics.
struct Tracker {
    slots: &'static [usize],
    filter: MedusaFilter,
    raw_err: Vec<f64>,
    refined_err: Vec<f64>,
    filt_err: Vec<f64>,
    conf: Vec<f64>,
    non_finite: u64,
    filter_s: f64,
    raw_s: f64,
    updates: u64,
    last: Option<FilterEstimate>,
    readings: Vec<Option<f64>>,
}

/// Per-copter harness state.
struct CopterEval {
    id: usize,
    trackers: Vec<Tracker>,
    prev_input: MotionInput,
    samples: u64,
    distance_m: f64,
    last_pos: Option<Vector2<f64>>,
    x_range: [f64; 2],
    y_range: [f64; 2],
    max_bias: f64,
    diag_rng: Rng32,
    cruise: Cruise,
    stopped: bool,
}

/// The evaluation's pilot: Wall-Avoid only pushes away from walls, so it commands a cruise
/// velocity whose direction (and heading) changes every 3–8 s (seeded); the heading command
/// turns towards its target at a bounded rate.
#[derive(Clone, Debug)]
pub struct Cruise {
    rng: Rng32,
    next_leg_tick: u64,
    heading_target_rad: Real,
}

impl Cruise {
    /// The pilot of copter `id`, starting at heading `yaw_rad`.
    pub fn new(seed: u64, id: usize, yaw_rad: Real) -> Self {
        Self { rng: Rng32::new(seed ^ 0xc401_5e00, 2000 + id as u64), next_leg_tick: 0, heading_target_rad: yaw_rad }
    }

    /// Updates `cmd` before the step at `tick`.
    pub fn steer(&mut self, cmd: &mut sim_core::Command, tick: u64, dt: f64, hold_yaw: bool) {
        if tick >= self.next_leg_tick {
            let a = self.rng.uniform() * std::f32::consts::TAU;
            cmd.velocity_m_s = Some([CRUISE_SPEED_M_S * a.cos(), CRUISE_SPEED_M_S * a.sin()]);
            if !hold_yaw {
                self.heading_target_rad = wrap_angle_rad(self.rng.uniform() * std::f32::consts::TAU);
            }
            let leg_s = 3.0 + 5.0 * f64::from(self.rng.uniform());
            self.next_leg_tick = tick + (leg_s / dt).round().max(1.0) as u64;
        }
        if !hold_yaw {
            let max_turn = TURN_RATE_DEG_S.to_radians() * dt as Real;
            let turn = wrap_angle_rad(self.heading_target_rad - cmd.yaw_rad).clamp(-max_turn, max_turn);
            cmd.yaw_rad = wrap_angle_rad(cmd.yaw_rad + turn);
        }
    }
}

/// MEDUSA for one sensor set (slot indices into [`SLOT_ANGLES_DEG`]), over the lab's real
/// geometry ([`bridge::mixed::sync::medusa_for`]).
fn medusa_for(world: &World, slots: &[usize]) -> anyhow::Result<Medusa> {
    let angles: Vec<f64> = slots.iter().map(|&k| SLOT_ANGLES_DEG[k].to_radians()).collect();
    Ok(bridge::mixed::sync::medusa_for(world, &angles)?)
}

/// The sonar scene exactly as sim-core's `sense` builds it, from the current state.
fn sonar_scene(world: &World, state: &State, scene: &mut SonarScene) {
    sim_core::step::fill_sonar_scene(world, &state.copters, scene);
}

/// Readings of the four synthetic diagonal sonars (slots 4..8) at the current state.
fn diagonal_readings(world: &World, state: &State, scene: &SonarScene, id: usize, rng: &mut Rng32) -> [Real; 4] {
    let spec = &world.sensors.spec.sonar;
    let m = &state.copters[id].motion;
    let (pos, rot) = (m.pos_m, m.rot);
    std::array::from_fn(|k| {
        let a = SLOT_ANGLES_DEG[4 + k].to_radians() as Real;
        let axis = rot * Vec3::new(a.cos(), a.sin(), 0.0);
        let cone = Cone::new(pos + axis * spec.mount_offset_m, axis, world.sensors.sonar_half_angle_rad);
        let truth = scene.cone_distance(&cone, id, spec.max_range_m);
        let noise = if world.sensors.spec.noise { spec.noise_sigma_m * rng.normal() } else { 0.0 };
        sonar_reading(spec, truth, noise)
    })
}

pub(crate) fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let idx = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[idx.min(sorted.len() - 1)]
}

fn stats(v: &[f64]) -> ErrorStats {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    ErrorStats {
        median_cm: percentile(&s, 0.5) * 100.0,
        p95_cm: percentile(&s, 0.95) * 100.0,
        max_cm: percentile(&s, 1.0) * 100.0,
    }
}

/// Flies one evaluation flight and measures every evaluated copter.
pub fn evaluate(
    choice: WorldChoice,
    minutes: f64,
    seed: Option<u64>,
    copters: usize,
    hold_yaw: bool,
) -> anyhow::Result<FlightReport> {
    let spec = eval_scene(choice, minutes, seed, copters)?;
    let world = scene::compile(&spec).context("compiling the evaluation scene")?;
    let started = Instant::now();
    // The boxes MEDUSA knows: those whose top reaches the sonars (see `bridge::mixed::sync::real_boxes`).
    let known: Vec<usize> =
        (0..world.boxes.len()).filter(|&b| bridge::mixed::sync::is_real_box(&world.boxes[b])).collect();

    let seed = world.params.seed;
    let mut evals = Vec::new();
    for id in 0..world.copters.len() {
        evals.push(CopterEval::new(&world, id, seed)?);
    }

    let state = fly(&world, &mut evals, hold_yaw)?;

    let copter_reports = evals.iter().map(|e| e.report(&world, &state)).collect();

    Ok(FlightReport {
        world: choice,
        boxes_simulated: world.boxes.iter().map(|b| b.name.clone()).collect(),
        boxes_known_to_medusa: known.iter().map(|&b| world.boxes[b].name.clone()).collect(),
        minutes,
        seed,
        hold_yaw,
        wall_s: started.elapsed().as_secs_f64(),
        copters: copter_reports,
    })
}

/// Flies the evaluation scene to its end, each copter steered by its cruise pilot and measured
/// after every control step; returns the final state.
fn fly(world: &World, evals: &mut [CopterEval], hold_yaw: bool) -> anyhow::Result<State> {
    let ticks = world.default_ticks();
    let dt = world.params.control_dt_s;
    let mut state = world.initial_state();
    let mut inputs = world.initial_inputs();
    let mut scene_buf = SonarScene::default();
    let cap = f64::from(world.sensors.spec.sonar.cap_m);
    for _ in 0..ticks {
        for e in evals.iter_mut() {
            e.cruise.steer(&mut inputs.commands[e.id], state.tick, dt, hold_yaw);
        }
        // Ground truth and the synthetic diagonals at the instant sim-core senses.
        sonar_scene(world, &state, &mut scene_buf);
        let truth: Vec<Vector2<f64>> = (0..world.copters.len())
            .map(|i| {
                let p = state.pose(i).pos_m;
                Vector2::new(f64::from(p.x), f64::from(p.y))
            })
            .collect();
        let diagonals: Vec<[Real; 4]> =
            evals.iter_mut().map(|e| diagonal_readings(world, &state, &scene_buf, e.id, &mut e.diag_rng)).collect();
        let took_off = |state: &State, i: usize| state.copters[i].took_off_tick;
        let sense_tick = state.tick;
        let report = step(world, &mut state, &inputs);
        let _ = report;

        for (e, diag) in evals.iter_mut().zip(&diagonals) {
            let c = &state.copters[e.id];
            if e.stopped {
                continue;
            }
            if c.crash.is_some() {
                e.stopped = true;
                continue;
            }
            let settled = took_off(&state, e.id).is_some_and(|t| (sense_tick as f64 - t as f64) * dt >= SETTLE_S);
            e.measure(c, diag, truth[e.id], settled, cap, dt)?;
        }
    }
    Ok(state)
}

impl CopterEval {
    /// The harness state of copter `id`: a tracker per sensor set, its seeded diagonals and pilot.
    fn new(world: &World, id: usize, seed: u64) -> anyhow::Result<Self> {
        let mut trackers = Vec::new();
        for slots in SENSOR_SETS {
            trackers.push(Tracker::new(world, id, slots)?);
        }
        Ok(CopterEval {
            id,
            trackers,
            prev_input: MotionInput::zero(),
            samples: 0,
            distance_m: 0.0,
            last_pos: None,
            x_range: [f64::INFINITY, f64::NEG_INFINITY],
            y_range: [f64::INFINITY, f64::NEG_INFINITY],
            max_bias: 0.0,
            diag_rng: Rng32::new(seed ^ 0x5eed_d1a6, 1000 + id as u64),
            cruise: Cruise::new(seed, id, world.copters[id].initial_command.yaw_rad),
            stopped: false,
        })
    }

    /// One control step of the copter `c` (after the step; `t` its true position when sensed):
    /// its flight counted once `settled`, its readings fed to every tracker.
    fn measure(
        &mut self,
        c: &CopterState,
        diag: &[Real; 4],
        t: Vector2<f64>,
        settled: bool,
        cap: f64,
        dt: f64,
    ) -> anyhow::Result<()> {
        let r = &c.sensors;
        let all: [Real; 8] =
            [r.sonar_m[0], r.sonar_m[1], r.sonar_m[2], r.sonar_m[3], diag[0], diag[1], diag[2], diag[3]];
        let yaw = YawEstimate::new(f64::from(r.attitude_rad[2]), f64::from(YAW_NOISE_DEG).to_radians());
        let input = self.prev_input;
        if settled {
            self.samples += 1;
            if let Some(lp) = self.last_pos {
                self.distance_m += (t - lp).norm();
            }
            self.last_pos = Some(t);
            self.x_range = [self.x_range[0].min(t.x), self.x_range[1].max(t.x)];
            self.y_range = [self.y_range[0].min(t.y), self.y_range[1].max(t.y)];
            self.max_bias = self.max_bias.max(f64::from(r.yaw_bias_rad).abs());
        }
        for tr in &mut self.trackers {
            tr.update(&all, cap, dt, &input, yaw, settled.then_some(t))?;
        }
        let sp = &c.setpoint;
        self.prev_input = MotionInput::from_attitude(f64::from(sp.pitch_rad), f64::from(sp.roll_rad));
        Ok(())
    }

    /// The copter's report, from the measurements and the final `state`.
    fn report(&self, world: &World, state: &State) -> CopterReport {
        let c = &state.copters[self.id];
        let true_bias = f64::from(c.yaw_bias_rad);
        CopterReport {
            name: world.copters[self.id].name.clone(),
            samples: self.samples,
            crash: c.crash.map(|x| format!("{x:?}")),
            distance_m: self.distance_m,
            x_range_m: self.x_range,
            y_range_m: self.y_range,
            max_abs_yaw_bias_deg: self.max_bias.to_degrees(),
            sets: self.trackers.iter().map(|tr| tr.report(true_bias)).collect(),
        }
    }
}

impl Tracker {
    /// MEDUSA and its filter for the sensor set `slots` of copter `id`, no measurements yet.
    fn new(world: &World, id: usize, slots: &'static [usize]) -> anyhow::Result<Self> {
        let medusa = medusa_for(world, slots)?;
        let filter = MedusaFilter::new(medusa, bridge::mixed::sync::filter_config(world, id))?;
        Ok(Tracker {
            slots,
            filter,
            raw_err: Vec::new(),
            refined_err: Vec::new(),
            filt_err: Vec::new(),
            conf: Vec::new(),
            non_finite: 0,
            filter_s: 0.0,
            raw_s: 0.0,
            updates: 0,
            last: None,
            readings: vec![None; slots.len()],
        })
    }

    /// Feeds the set's readings (of `all` eight, those under `cap`) to the filter and to raw
    /// MEDUSA, timing both; with `truth` (once the copter has settled), records their errors.
    fn update(
        &mut self,
        all: &[Real; 8],
        cap: f64,
        dt: f64,
        input: &MotionInput,
        yaw: YawEstimate,
        truth: Option<Vector2<f64>>,
    ) -> anyhow::Result<()> {
        for (slot, &k) in self.readings.iter_mut().zip(self.slots) {
            let v = f64::from(all[k]);
            *slot = (v < cap).then_some(v);
        }
        let t0 = Instant::now();
        let est = self.filter.update(dt, input, yaw, &self.readings)?;
        let t1 = Instant::now();
        let raw = self.filter.medusa().locate(yaw, &self.readings)?;
        let t2 = Instant::now();
        self.filter_s += (t1 - t0).as_secs_f64();
        self.raw_s += (t2 - t1).as_secs_f64();
        self.updates += 1;
        self.last = Some(est);
        if let Some(t) = truth {
            let fe = (est.pos_in_world - t).norm();
            if !(fe.is_finite() && est.confidence.is_finite()) {
                self.non_finite += 1;
            }
            self.filt_err.push(fe);
            self.conf.push(est.confidence);
            self.raw_err.push((raw.best.pos_in_world - t).norm());
            self.refined_err.push((raw.refined.pos_in_world - t).norm());
        }
        Ok(())
    }

    /// The sensor set's statistics; `true_bias` is the copter's true yaw bias at the end (rad).
    fn report(&self, true_bias: f64) -> SensorSetReport {
        let mut conf = self.conf.clone();
        conf.sort_by(f64::total_cmp);
        let mut bad_conf: Vec<f64> =
            self.filt_err.iter().zip(&self.conf).filter(|(e, _)| **e > 0.15).map(|(_, c)| *c).collect();
        bad_conf.sort_by(f64::total_cmp);
        let n = self.filt_err.len().max(1) as f64;
        SensorSetReport {
            sensors: self.slots.len(),
            slots: self.slots.iter().map(|&k| SLOT_NAMES[k]).collect(),
            raw: stats(&self.raw_err),
            refined: stats(&self.refined_err),
            filtered: stats(&self.filt_err),
            confidence_median: percentile(&conf, 0.5),
            confidence_p05: percentile(&conf, 0.05),
            confidence_median_when_err_above_15cm: if bad_conf.is_empty() { 0.0 } else { percentile(&bad_conf, 0.5) },
            share_filtered_above_15cm: self.filt_err.iter().filter(|&&e| e > 0.15).count() as f64 / n,
            non_finite: self.non_finite,
            filter_us_per_update: self.filter_s / self.updates.max(1) as f64 * 1e6,
            raw_us_per_locate: self.raw_s / self.updates.max(1) as f64 * 1e6,
            final_yaw_bias_error_deg: self.last.map_or(f64::NAN, |est| (est.yaw_bias_rad - true_bias).to_degrees()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// sim-core's attitude convention and medusa's `MotionInput::from_attitude` agree: a
    /// commanded pitch or roll accelerates the simulated copter along the body-frame direction
    /// medusa assumes.
    #[test]
    fn commanded_attitude_moves_the_copter_where_medusa_expects() {
        for (pitch_deg, roll_deg) in [(5.0f64, 0.0f64), (-5.0, 0.0), (0.0, 5.0), (0.0, -5.0)] {
            let (mut spec, _) = scene::load_default();
            spec.boxes.clear();
            spec.copters.truncate(1);
            spec.copters[0].mode = FlightMode::MixedManual;
            spec.copters[0].command.height_m = FLIGHT_HEIGHT_M;
            spec.copters[0].start.yaw_deg = 30.0;
            spec.copters[0].command.yaw_deg = Some(30.0);
            let world = scene::compile(&spec).unwrap();
            let mut state = world.initial_state();
            let mut inputs = world.initial_inputs();
            for _ in 0..60 {
                step(&world, &mut state, &inputs);
            }
            let v0 = state.pose(0).vel_m_s;
            inputs.commands[0].pitch_rad = (pitch_deg as Real).to_radians();
            inputs.commands[0].roll_rad = (roll_deg as Real).to_radians();
            for _ in 0..10 {
                step(&world, &mut state, &inputs);
            }
            let pose = state.pose(0);
            let dv = pose.vel_m_s - v0;
            let (s, c) = (pose.rpy_rad[2] as f64).sin_cos();
            let dv_body = Vector2::new(c * dv.x as f64 + s * dv.y as f64, -s * dv.x as f64 + c * dv.y as f64);
            let a = MotionInput::from_attitude(pitch_deg.to_radians(), roll_deg.to_radians()).accel_in_body_mps2;
            let cos = dv_body.dot(&a) / (dv_body.norm() * a.norm());
            assert!(cos > 0.9, "pitch {pitch_deg}° roll {roll_deg}°: body Δv {dv_body:?} vs medusa accel {a:?}");
        }
    }
}
