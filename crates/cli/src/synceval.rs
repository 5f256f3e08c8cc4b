//! `twinswarm localize --sync-eval`: how well a twin stays where its real copter is, end to
//! end, in simulated time.
//!
//! The pieces are those of a live mixed-reality run, stepped in lockstep instead of against the
//! wall clock:
//! - the **reality**: the stand-in's world (the lab arena, one FINken in Wall-Avoid at 0.8 m
//!   flying the localization evaluation's cruise legs, σ = 5 cm sonar noise, 2° AHRS yaw noise
//!   plus the yaw-bias random walk, its own seed);
//! - its **telemetry**: every message of the telemetry plan (22 ms for
//!   `FINKEN_ACTUATORS_SET_POINT` and `ATTITUDE`, 50 ms for `SONAR_ARRAY`, …), timed by the
//!   paper's measured link ([`bridge::mixed::link`]) or a uniform jitter, lost with a probability,
//!   encoded to Ivy text and decoded again;
//! - the **simulation**: `bridge::engine::run_loop` with the twin, fed by the gateway's
//!   [`Interpreter`] through the loop's request queue, with [`TwinSync`](bridge::mixed::sync::TwinSync)
//!   on or off, and optionally a tracking pose that lags and drops out.
//!
//! After every control step the twin's position is compared with the real copter's at the same
//! simulated time.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::sync::mpsc::SyncSender;
use std::time::{Duration, Instant};

use anyhow::Context;
use bridge::engine::{BusInput, LoopOptions, Request, StepObserver};
use bridge::mixed::interpreter::{Interpreter, TwinAttitude};
use bridge::mixed::link::{LinkClock, LinkTiming};
use bridge::mixed::plan::TelemetryPlan;
use bridge::mixed::sync::{SyncOptions, SyncStats};
use bridge::paparazzi::convert::{TelemetrySource, telemetry_text};
use bridge::paparazzi::messages::MessageSet;
use bridge::wire::{sensors_msg, state_msg};
use serde::Serialize;
use sim_core::rng::Rng32;
use sim_core::scene;
use sim_core::{CopterKind, FlightMode, Inputs, State, StepReport, World};

use crate::BadInput;
use crate::localize::{Cruise, LocalizeArgs, SETTLE_S, WorldChoice, eval_scene};

/// `twinswarm localize --sync-eval`: every variant over the same flight, reported.
pub fn run(args: &LocalizeArgs) -> anyhow::Result<()> {
    crate::localize::check(args)?;
    let bad = |m: String| anyhow::Error::new(BadInput(anyhow::anyhow!(m)));
    if !(0.0..=1.0).contains(&args.loss) || args.jitter_ms.is_some_and(|j| !j.is_finite() || j < 0.0) {
        return Err(bad("--loss must be in [0, 1] and --jitter-ms >= 0".into()));
    }
    let choice = if args.world == WorldChoice::Both { WorldChoice::Empty } else { args.world };
    if !args.link_load.is_finite() || !(0.0..=10.0).contains(&args.link_load) {
        return Err(bad(format!("--link-load must be in [0, 10], got {}", args.link_load)));
    }
    let timing = match args.jitter_ms {
        Some(_) => bridge::mixed::link::LinkTiming::from_args(args.jitter_ms, u32::from(args.copters)),
        None => bridge::mixed::link::LinkTiming::measured_with_load(u32::from(args.copters), args.link_load),
    };
    let link = Link { timing, loss: args.loss };
    let medusa_only = SyncOptions { tracking: false, ..SyncOptions::default() };
    let variant = |label: &str, sync: Option<SyncOptions>, attitude| Variant {
        label: label.into(),
        sync,
        tracking: false,
        tracking_dropout_s: None,
        attitude,
    };
    let mut variants = vec![
        variant("correction off", None, TwinAttitude::Measured),
        variant("MEDUSA", Some(medusa_only.clone()), TwinAttitude::Measured),
        variant("MEDUSA, set-point attitude", Some(medusa_only), TwinAttitude::Setpoint),
    ];
    if let Some(d) = &args.tracking_dropout {
        let v: Vec<f64> = d
            .split(',')
            .map(|x| x.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| bad(format!("--tracking-dropout: expected START,END in seconds, got {d:?}")))?;
        let [a, b] = v[..] else { return Err(bad(format!("--tracking-dropout: expected START,END, got {d:?}"))) };
        if !(a.is_finite() && b.is_finite() && 0.0 <= a && a < b) {
            return Err(bad(format!("--tracking-dropout: expected 0 <= START < END, got {d:?}")));
        }
        variants.push(Variant {
            label: format!("MEDUSA + tracking, off {a}-{b} s"),
            sync: Some(SyncOptions::default()),
            tracking: true,
            tracking_dropout_s: Some([a, b]),
            attitude: TwinAttitude::Measured,
        });
    }
    let runs = variants
        .into_iter()
        .map(|v| run_variant(choice, args.minutes, args.seed, link, v))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let seed = eval_scene(choice, args.minutes, args.seed, 1)?.sim.seed;
    let report = SyncEvalReport { minutes: args.minutes, seed, link, runs };
    if args.json {
        outln!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        out!("{}", report.to_text());
    }
    Ok(())
}

/// A twin this far from its real copter has drifted, m.
pub const DRIFT_M: f64 = 0.3;

/// The aircraft id of the evaluated real copter.
const AC_ID: u8 = 5;

/// One configuration to evaluate.
#[derive(Clone, Debug, Serialize)]
pub struct Variant {
    /// Its label.
    pub label: String,
    /// Synchronisation (`None`: off, command prediction only).
    pub sync: Option<SyncOptions>,
    /// Publish a tracking pose every control step.
    pub tracking: bool,
    /// The tracking source is silent between these simulated times, s.
    pub tracking_dropout_s: Option<[f64; 2]>,
    /// Which telemetry sets the twin's attitude targets.
    pub attitude: TwinAttitude,
}

/// Telemetry conditions.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Link {
    /// When messages arrive: the measured link, or every slot with a uniform delay.
    pub timing: LinkTiming,
    /// Probability that a message is lost, on top of the timing.
    pub loss: f64,
}

/// Error statistics, cm.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ErrorCm {
    /// Median.
    pub median: f64,
    /// 95th percentile.
    pub p95: f64,
    /// Maximum.
    pub max: f64,
}

/// The result of one variant.
#[derive(Clone, Debug, Serialize)]
pub struct SyncRun {
    /// The variant.
    pub variant: Variant,
    /// Twin-versus-truth horizontal error from 5 s after take-off on.
    pub error_cm: ErrorCm,
    /// The same during the tracking dropout (if any).
    pub error_in_dropout_cm: Option<ErrorCm>,
    /// Error at the end, cm.
    pub final_error_cm: f64,
    /// When the twin first strayed [`DRIFT_M`] from its real copter, s after take-off: the
    /// onset of the drift the paper saw at about 30 s without correction.
    pub drift_onset_s: Option<f64>,
    /// Steps in which the twin's centre was outside the arena.
    pub steps_outside_arena: u64,
    /// Steps compared.
    pub samples: usize,
    /// Whether (and when) the twin crashed.
    pub twin_crash: Option<String>,
    /// Whether the real copter crashed.
    pub real_crash: Option<String>,
    /// Telemetry messages sent and lost.
    pub telemetry_sent: u64,
    /// Lost.
    pub telemetry_lost: u64,
    /// What synchronisation did.
    pub sync: Option<SyncStats>,
    /// Wall time of the run, s.
    pub wall_s: f64,
}

/// The whole evaluation.
#[derive(Clone, Debug, Serialize)]
pub struct SyncEvalReport {
    /// Simulated minutes per run.
    pub minutes: f64,
    /// Seed of the reality.
    pub seed: u64,
    /// Telemetry conditions.
    pub link: Link,
    /// One run per variant.
    pub runs: Vec<SyncRun>,
}

impl SyncEvalReport {
    /// A table.
    pub fn to_text(&self) -> String {
        let mut s = format!(
            "twin synchronisation, {:.1} simulated minutes, reality seed {}, telemetry link {:?}, loss {:.0} %\n",
            self.minutes,
            self.seed,
            self.link.timing,
            self.link.loss * 100.0
        );
        s += "  variant                              median    p95     max   final  outside  drift@  crash\n";
        for r in &self.runs {
            s += &format!(
                "  {:<34} {:>6.1} {:>6.1} {:>7.1} {:>7.1} {:>8} {:>7}  {}\n",
                r.variant.label,
                r.error_cm.median,
                r.error_cm.p95,
                r.error_cm.max,
                r.final_error_cm,
                r.steps_outside_arena,
                r.drift_onset_s.map_or("-".to_string(), |s| format!("{s:.1} s")),
                r.twin_crash.as_deref().unwrap_or("-")
            );
            if let Some(d) = &r.error_in_dropout_cm {
                s += &format!(
                    "  {:<34} {:>6.1} {:>6.1} {:>7.1}   (during the tracking dropout)\n",
                    "", d.median, d.p95, d.max
                );
            }
        }
        s += "  (errors in cm, twin versus real copter, horizontal; drift@: first 30 cm apart, after take-off)\n";
        s
    }
}

/// Steps the reality and plays its telemetry into the loop, after each simulation step.
struct Harness {
    world: World,
    state: State,
    inputs: Inputs,
    cruise: Cruise,
    plan: TelemetryPlan,
    /// When each message of the plan arrives next, s.
    next_due_s: Vec<f64>,
    /// Each message's link timing.
    clocks: Vec<LinkClock>,
    messages: Arc<MessageSet>,
    interpreter: Interpreter,
    requests: SyncSender<Request>,
    rng: Rng32,
    link: Link,
    base: Instant,
    prefix: String,
    variant: Variant,
    /// The real copter's recent positions, for the lagging tracking pose.
    history: std::collections::VecDeque<(f64, [f32; 2])>,
    errors: Vec<f64>,
    dropout_errors: Vec<f64>,
    /// See [`SyncRun::drift_onset_s`].
    drift_onset_s: Option<f64>,
    outside: u64,
    sent: u64,
    lost: u64,
    /// Inputs the loop's queue could not take (it holds 4096 and is drained every step).
    queue_full: u64,
    last_error: f64,
}

impl StepObserver for Harness {
    fn after_step(&mut self, world: &World, state: &State, _inputs: &Inputs, _report: &StepReport) {
        let dt = self.world.params.control_dt_s;
        // The reality steps in lockstep with the simulation.
        self.cruise.steer(&mut self.inputs.commands[0], self.state.tick, dt, false);
        sim_core::step(&self.world, &mut self.state, &self.inputs);
        let t = self.state.time_s(&self.world);
        let real = self.state.pose(0).pos_m;
        self.history.push_back((t, [real.x, real.y]));
        while self.history.front().is_some_and(|(ht, _)| t - ht > 3.0) {
            self.history.pop_front();
        }

        // Compare (the twin is copter 0 of the simulation).
        let twin = state.pose(0).pos_m;
        let err = f64::from(((twin.x - real.x).powi(2) + (twin.y - real.y).powi(2)).sqrt());
        self.last_error = err;
        let settled =
            self.state.copters[0].took_off_tick.is_some_and(|k| (self.state.tick as f64 - k as f64) * dt >= SETTLE_S);
        if let Some(k) = self.state.copters[0].took_off_tick
            && err > DRIFT_M
            && self.drift_onset_s.is_none()
        {
            self.drift_onset_s = Some((self.state.tick - k) as f64 * dt);
        }
        if settled {
            self.errors.push(err);
            if self.in_dropout(t) {
                self.dropout_errors.push(err);
            }
            let [hx, hy] = world.arena.size_m.map(|v| v / 2.0);
            if twin.x.abs() > hx || twin.y.abs() > hy {
                self.outside += 1;
            }
        }

        // Telemetry due in this step, from the reality's state after it.
        let st = state_msg(&self.world, &self.state, &self.inputs, 0);
        let se = sensors_msg(&self.world, &self.state, 0);
        let src = TelemetrySource { state: &st, sensors: &se, setpoint: self.state.copters[0].setpoint };
        for k in 0..self.plan.periods.len() {
            let name = &self.plan.periods[k].0;
            while self.next_due_s[k] <= t + 1e-9 {
                let sent_at = self.next_due_s[k];
                self.next_due_s[k] = self.clocks[k].next_s();
                if f64::from(self.rng.uniform()) < self.link.loss {
                    self.lost += 1;
                    continue;
                }
                let Some(Ok(text)) = telemetry_text(&self.messages, AC_ID, name, &src) else { continue };
                self.sent += 1;
                let origin = BusInput {
                    key: format!("{}/pprz/{AC_ID}/{name}", self.prefix),
                    text,
                    received_unix_ns: (sent_at * 1e9) as u64,
                };
                let received = self.base + Duration::from_secs_f64(sent_at);
                let r = self.interpreter.interpret(&self.messages, origin, received);
                if self.requests.try_send(r).is_err() {
                    self.queue_full += 1;
                }
            }
        }
        // The tracking pose, `lag` old.
        if self.variant.tracking && !self.in_dropout(t) {
            let lag = self.variant.sync.as_ref().map_or(0.2, |s| s.tracking_lag_s);
            if let Some((_, p)) = self.history.iter().rev().find(|(ht, _)| *ht <= t - lag + 1e-9) {
                let origin = BusInput {
                    key: format!("{}/copters/twin/tracking", self.prefix),
                    text: format!("{{\"pos_m\":[{},{}]}}", p[0], p[1]),
                    received_unix_ns: (t * 1e9) as u64,
                };
                if self.requests.try_send(Request::Tracking { copter: "twin".into(), pos_m: *p, origin }).is_err() {
                    self.queue_full += 1;
                }
            }
        }
    }
}

impl Harness {
    fn in_dropout(&self, t: f64) -> bool {
        self.variant.tracking_dropout_s.is_some_and(|[a, b]| t >= a && t < b)
    }
}

fn error_cm(v: &[f64]) -> ErrorCm {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let q = |p: f64| crate::localize::percentile(&s, p) * 100.0;
    ErrorCm { median: q(0.5), p95: q(0.95), max: q(1.0) }
}

/// Runs one variant.
pub fn run_variant(
    choice: WorldChoice,
    minutes: f64,
    seed: Option<u64>,
    link: Link,
    variant: Variant,
) -> anyhow::Result<SyncRun> {
    let started = Instant::now();
    // The reality: one Wall-Avoid FINken with the localization evaluation's noise.
    let mut reality_spec = eval_scene(choice, minutes, seed, 1)?;
    reality_spec.sim.seed = reality_spec.sim.seed.wrapping_add(1000 + u64::from(AC_ID));
    reality_spec.copters[0].ac_id = Some(AC_ID);
    let reality = scene::compile(&reality_spec).context("compiling the reality")?;
    // The simulation: the same arena with the twin at the real copter's start.
    let mut sim_spec = eval_scene(choice, minutes, seed, 1)?;
    let c = &mut sim_spec.copters[0];
    c.name = "twin".into();
    c.kind = CopterKind::Real;
    c.ac_id = Some(AC_ID);
    c.mode = FlightMode::Manual;
    c.command = Default::default();
    let world = scene::compile(&sim_spec).context("compiling the simulation")?;

    let (tx, rx) = std::sync::mpsc::sync_channel::<Request>(4096);
    let plan = TelemetryPlan::project_default();
    let messages = Arc::new(bridge::paparazzi::convert::project_messages());
    let mut clocks: Vec<LinkClock> = (0..plan.periods.len())
        .map(|k| {
            LinkClock::new(plan.periods[k].1, link.timing, Rng32::new(reality.params.seed, 0x7e1f_0000 + k as u64))
        })
        .collect();
    let next_due_s = clocks.iter_mut().map(LinkClock::next_s).collect();
    let harness = Harness {
        state: reality.initial_state(),
        inputs: reality.initial_inputs(),
        cruise: Cruise::new(reality.params.seed, 0, reality.copters[0].initial_command.yaw_rad),
        next_due_s,
        clocks,
        plan,
        messages,
        interpreter: Interpreter::new(Arc::new(world.clone()), None, variant.attitude),
        requests: tx,
        rng: Rng32::new(reality.params.seed, 0x7e1e_0000),
        link,
        base: Instant::now(),
        prefix: "twinswarm/sync-eval".into(),
        variant: variant.clone(),
        history: Default::default(),
        errors: Vec::new(),
        dropout_errors: Vec::new(),
        drift_onset_s: None,
        outside: 0,
        sent: 0,
        lost: 0,
        queue_full: 0,
        last_error: 0.0,
        world: reality,
    };
    let opts =
        LoopOptions { realtime: false, ticks: world.default_ticks(), sync: variant.sync.clone(), ..Default::default() };
    let stop = AtomicBool::new(false);
    let (state, inputs) = (world.initial_state(), world.initial_inputs());
    let (world, state, stats, harness) =
        bridge::engine::run_watched(world, state, inputs, rx, None, harness, &stop, &opts);
    anyhow::ensure!(
        harness.queue_full == 0,
        "{} inputs did not fit the loop's queue: the evaluation would be biased",
        harness.queue_full
    );
    Ok(SyncRun {
        error_cm: error_cm(&harness.errors),
        error_in_dropout_cm: variant.tracking_dropout_s.map(|_| error_cm(&harness.dropout_errors)),
        final_error_cm: harness.last_error * 100.0,
        drift_onset_s: harness.drift_onset_s,
        steps_outside_arena: harness.outside,
        samples: harness.errors.len(),
        twin_crash: state.copters[0].crash.map(|c| format!("{c:?}")),
        real_crash: harness.state.copters[0].crash.map(|c| format!("{c:?}")),
        telemetry_sent: harness.sent,
        telemetry_lost: harness.lost,
        sync: stats.sync.get(&world.copters[0].name).cloned(),
        wall_s: started.elapsed().as_secs_f64(),
        variant,
    })
}
