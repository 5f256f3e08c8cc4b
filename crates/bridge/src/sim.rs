//! The step loop on its own thread, fed and drained through bounded channels.
//!
//! - Requests (commands, spawns, stop) arrive on a bounded channel and are applied at the
//!   start of the next control step.
//! - After each step a [`Frame`] goes out on a bounded channel with `try_send`: publishing never
//!   blocks the step loop; frames that do not fit are dropped and counted.
//! - Real-time mode paces control steps against absolute wall-clock deadlines (`start + k·dt`),
//!   so there is no drift; a step that ends after its deadline counts as an overrun.
//! - Lockstep mode ([`LockstepOptions`], `docs/lockstep.md`) holds each step until every
//!   claimed copter's controller has answered the last state, or a timeout has passed; its
//!   frames are never dropped.
//!
//! The loop only paces and routes: the [`Flight`] it drives does the rest.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use sim_core::scene::CopterSpec;
use sim_core::{CopterKind, Inputs, State, StepReport, World};

use crate::failsafe::{FailsafeEvent, FailsafeOptions};
use crate::flight::{Flight, Halt, Recorder};
use crate::mixed::{OutboxOptions, PprzOut, Sample, Summary};
use crate::sync::{SyncOptions, SyncStats};
use crate::wire::{CommandMsg, SensorsMsg, StateMsg};

/// What can be asked of the step loop.
#[derive(Debug)]
pub enum Request {
    /// A validated command for a copter, by name, from a source (e.g. a Zenoh key).
    Command {
        /// Copter name.
        copter: String,
        /// The command.
        cmd: CommandMsg,
        /// Where it came from (the bus key) and its raw text, for the log.
        origin: BusInput,
    },
    /// A text that drives nothing (an aircraft that is not ours, one of our virtual aircraft
    /// sent by someone else), for the log: every received text reaches it.
    Ignored {
        /// Where it came from and its raw text.
        origin: BusInput,
        /// Why it drives nothing.
        reason: &'static str,
    },
    /// An input the bus refused (malformed, out of range, unknown copter), for the log.
    Rejected {
        /// Where it came from and its raw text.
        origin: BusInput,
        /// Why it was refused.
        reason: String,
    },
    /// Add a virtual copter; the reply says its name or why not.
    Spawn {
        /// Its scene table.
        spec: Box<CopterSpec>,
        /// Where the answer goes.
        reply: tokio::sync::oneshot::Sender<Result<String, String>>,
    },
    /// Telemetry of a real copter for its twin (see [`crate::mixed`]).
    Twin {
        /// The twin's name.
        copter: String,
        /// Spawn it first if it does not exist yet.
        spawn: Option<Box<CopterSpec>>,
        /// What to apply (validated).
        cmd: Option<CommandMsg>,
        /// The real copter's attitude (roll, pitch, yaw), rad, simulator frame.
        observed_rpy: Option<[f32; 3]>,
        /// The real copter's own sonar readings (front, right, back, left), m.
        sonar_m: Option<[f32; 4]>,
        /// The real copter's yaw estimate, rad, simulator frame.
        yaw_rad: Option<f32>,
        /// The telemetry text, its key and arrival time.
        origin: BusInput,
    },
    /// An external tracking pose of a twin's real copter (see [`crate::sync`]).
    Tracking {
        /// The twin's name.
        copter: String,
        /// Position (x, y), m, world frame.
        pos_m: [f32; 2],
        /// The message, its key and arrival time.
        origin: BusInput,
    },
    /// A copter's controller changed (Zenoh liveliness claims, see
    /// [`crate::zenoh_net::node`]).
    Controller {
        /// The copter's name.
        copter: String,
        /// Its controller now, if any.
        client: Option<String>,
        /// The controller that disappeared, if one did (its failsafe applies when no other
        /// client takes over).
        lost: Option<String>,
    },
    /// Finish after the current step.
    Stop,
}

/// A message as it arrived on the bus.
#[derive(Debug, Clone)]
pub struct BusInput {
    /// The key it arrived on (its source).
    pub key: String,
    /// Its payload as text (lossy UTF-8).
    pub text: String,
    /// Wall-clock receive time, ns since the Unix epoch.
    pub received_unix_ns: u64,
}

/// What one control step produced, for publishing.
#[derive(Clone, Debug)]
pub struct Frame {
    /// The world after the step (it changes only on spawn).
    pub world: Arc<World>,
    /// Tick after the step.
    pub tick: u64,
    /// Simulated time, s.
    pub time_s: f64,
    /// Per-copter state (a shard: of its own copters only).
    pub states: Vec<StateMsg>,
    /// Per-copter sensors, when the sonars updated this step.
    pub sensors: Vec<SensorsMsg>,
    /// The copter id of each entry of `states` (and of `sensors`, when it has any).
    pub ids: Vec<u32>,
    /// Events of the step.
    pub report: StepReport,
    /// Paparazzi texts to publish (virtual sonar, virtual copters' telemetry).
    pub pprz_out: Vec<PprzOut>,
    /// Wall-clock instant the step finished.
    pub stepped_at: Instant,
}

/// How the loop runs.
#[derive(Clone, Debug, Default)]
pub struct LoopOptions {
    /// Pace against the wall clock.
    pub realtime: bool,
    /// Stop after this many control steps.
    pub ticks: u64,
    /// Mixed reality: send virtual sonar and virtual telemetry (see [`crate::mixed`]).
    pub outbox: Option<OutboxOptions>,
    /// Keep twins where their real copters are (see [`crate::sync`]).
    pub sync: Option<SyncOptions>,
    /// Lost links: twins' telemetry, virtual copters' controllers (see [`crate::failsafe`]).
    pub failsafe: FailsafeOptions,
    /// A shard's link to its neighbours (see [`crate::shard`]): the state must be a shard's;
    /// every step first trades ghosts through it.
    pub shard: Option<Arc<std::sync::Mutex<crate::shard::ShardLink>>>,
    /// Hold each step for the claimed copters' controllers (needs a frame channel).
    pub lockstep: Option<LockstepOptions>,
    /// Write a checkpoint every so many steps (see [`crate::checkpoint`]).
    pub checkpoint: Option<crate::checkpoint::CheckpointOptions>,
    /// Outside autopilots flying copters of kind `autopilot` (see [`crate::autopilot`]): every
    /// step first takes their motor commands and answers them after.
    pub autopilots: Option<Arc<std::sync::Mutex<crate::autopilot::Autopilots>>>,
}

/// `run --lockstep`: see `docs/lockstep.md`.
#[derive(Clone, Debug)]
pub struct LockstepOptions {
    /// How long a step waits for the controllers' answers before it goes on without them.
    pub timeout: Duration,
    /// Copters that must be claimed before the first step.
    pub wait_claims: Vec<String>,
}

/// What the lockstep did.
#[derive(Debug, Default, Clone, serde::Serialize)]
pub struct LockstepStats {
    /// Steps that waited for at least one controller.
    pub steps_held: u64,
    /// Answers that arrived in time.
    pub answers: u64,
    /// Timeouts by controller (client name): its copter kept its last command.
    pub timeouts: BTreeMap<String, u64>,
    /// Answers for a tick already stepped past (after a timeout), refused.
    pub late: u64,
    /// Commands to a claimed copter without a tick, or with one that is not the current
    /// tick's, refused.
    pub refused: u64,
    /// Wall-clock time spent waiting for answers, s.
    pub wait_s: f64,
}

/// How well a twin follows its real copter.
#[derive(Debug, Default, Clone, serde::Serialize)]
pub struct TwinStats {
    /// Telemetry-derived inputs applied.
    pub inputs_applied: u64,
    /// From a telemetry message's arrival to the step that applied it, ms.
    pub input_latency_ms: Summary,
    /// RMS of (twin − real) roll and pitch, deg, over steps with a real attitude at most
    /// 0.2 s old (until the twin crashes, if it does).
    pub attitude_rms_deg: [f64; 2],
    /// Steps that went into `attitude_rms_deg`.
    pub attitude_samples: u64,
    /// Whether it was spawned on its first telemetry.
    pub spawned: bool,
    #[serde(skip)]
    latencies_ms: Sample,
    #[serde(skip)]
    sq_sum: [f64; 2],
    /// Times its telemetry stopped for longer than [`FailsafeOptions::hold_after_s`].
    pub link_lost: u64,
    #[serde(skip)]
    observed: Option<([f32; 3], Instant)>,
}

impl TwinStats {
    /// A telemetry input received at `received_unix_ns` was applied now.
    pub(crate) fn applied(&mut self, received_unix_ns: u64) {
        self.inputs_applied += 1;
        let now = crate::log::now_unix_ns();
        self.latencies_ms.push(now.saturating_sub(received_unix_ns) as f32 / 1e6);
    }

    /// The real copter's attitude (roll, pitch, yaw), rad, as just received.
    pub(crate) fn observe(&mut self, rpy: [f32; 3]) {
        self.observed = Some((rpy, Instant::now()));
    }

    /// Accumulates the twin's attitude error against its real copter's, if that is at most
    /// 0.2 s old.
    pub(crate) fn track(&mut self, twin_rpy: [f32; 3]) {
        let Some((rpy, at)) = self.observed else { return };
        if at.elapsed().as_secs_f64() > 0.2 {
            return;
        }
        for k in 0..2 {
            let e = f64::from(sim_core::math::wrap_angle_rad(twin_rpy[k] - rpy[k]));
            self.sq_sum[k] += e * e;
        }
        self.attitude_samples += 1;
    }

    /// Fills the summaries at the end of the run.
    pub(crate) fn finish(&mut self) {
        self.input_latency_ms = self.latencies_ms.summary();
        let n = self.attitude_samples.max(1) as f64;
        self.attitude_rms_deg = self.sq_sum.map(|s| (s / n).sqrt().to_degrees());
    }
}

/// What the loop reports when it ends.
#[derive(Debug, Default, Clone)]
pub struct LoopStats {
    /// Steps run.
    pub steps: u64,
    /// Real-time steps that finished after their deadline.
    pub overruns: u64,
    /// Frames dropped because the publisher was behind.
    pub frames_dropped: u64,
    /// Commands applied.
    pub commands_applied: u64,
    /// Commands for unknown copters.
    pub commands_unknown_copter: u64,
    /// Inputs refused before they reached the loop (malformed, out of range, not from the
    /// copter's controller), logged as rejected.
    pub inputs_rejected: u64,
    /// Texts logged that drive nothing (see [`Request::Ignored`]).
    pub inputs_ignored: u64,
    /// Requests still queued when the loop ended, logged as rejected.
    pub inputs_after_end: u64,
    /// Paparazzi texts made but not sent, because their frame was dropped.
    pub pprz_dropped: u64,
    /// Copters spawned.
    pub spawned: u64,
    /// Spawn requests the world refused (a bad copter table).
    pub spawns_failed: u64,
    /// Whether it stopped early (stop request or signal).
    pub stopped_early: bool,
    /// Twins by name.
    pub twins: BTreeMap<String, TwinStats>,
    /// Paparazzi texts produced.
    pub pprz_sent: u64,
    /// Position synchronisation per twin name.
    pub sync: BTreeMap<String, SyncStats>,
    /// Failsafe transitions by kind (`hold`, `land`, `landed`, `resumed`, `client_lost`,
    /// `controller`).
    pub failsafe: BTreeMap<&'static str, u64>,
    /// A shard: why it stopped before the end (a neighbour gone or silent, a broken
    /// invariant), if it did.
    pub shard_error: Option<String>,
    /// A shard: copters it took over from another shard during the run.
    pub shard_taken_over: u64,
    /// Checkpoints written, and the last one.
    pub checkpoints_written: u64,
    /// The last checkpoint written.
    pub last_checkpoint: Option<std::path::PathBuf>,
    /// Why a checkpoint could not be written (the run stopped there), if one could not.
    pub checkpoint_error: Option<String>,
    /// Lockstep: answers, timeouts, refusals.
    pub lockstep: Option<LockstepStats>,
    /// Outside autopilots, in copter order.
    pub autopilots: Vec<crate::autopilot::AutopilotStats>,
    /// Wall time the steps waited for the outside autopilots, s.
    pub autopilot_wait_s: f64,
}

/// Observes every step from inside the loop (e.g. a logger). Runs on the loop's thread: keep
/// it cheap.
pub trait StepObserver: Send {
    /// Called after each step.
    fn after_step(&mut self, world: &World, state: &State, inputs: &Inputs, report: &StepReport);
    /// Called when a copter is spawned, after the world changed.
    fn spawned(&mut self, _world: &World, _id: usize, _tick: u64) {}
    /// Called when a real-time step finished `late_s` after its deadline.
    fn overrun(&mut self, _tick: u64, _late_s: f64) {}
    /// Called for each accepted bus input, before it applies.
    fn bus_input(&mut self, _input: &BusInput) {}
    /// Called for each input the bus refused.
    fn input_rejected(&mut self, _tick: u64, _input: &BusInput, _reason: &str) {}
    /// Called for each Paparazzi text the loop sends.
    fn pprz_out(&mut self, _tick: u64, _out: &PprzOut) {}
    /// Called when a real aircraft's twin was spawned on its first telemetry.
    fn paired(&mut self, _tick: u64, _ac_id: u8, _id: usize, _copter: &str) {}
    /// Called when a step's frame was dropped because the publisher was behind: its states
    /// were not published and its `pprz_lost` Paparazzi texts (already given to
    /// [`StepObserver::pprz_out`]) were not sent.
    fn frame_dropped(&mut self, _tick: u64, _pprz_lost: u64) {}
    /// Called for each failsafe transition (lost links, controllers).
    fn failsafe(&mut self, _tick: u64, _world: &World, _event: &FailsafeEvent) {}
    /// Called when a lockstep controller did not answer tick `tick` in time.
    fn lockstep_timeout(&mut self, _tick: u64, _world: &World, _copter: usize, _client: &str) {}
}

/// No observer.
impl StepObserver for () {
    fn after_step(&mut self, _: &World, _: &State, _: &Inputs, _: &StepReport) {}
}

/// An observer lent to a flight.
impl<O: StepObserver + ?Sized> StepObserver for &mut O {
    fn after_step(&mut self, world: &World, state: &State, inputs: &Inputs, report: &StepReport) {
        (**self).after_step(world, state, inputs, report);
    }
    fn spawned(&mut self, world: &World, id: usize, tick: u64) {
        (**self).spawned(world, id, tick);
    }
    fn overrun(&mut self, tick: u64, late_s: f64) {
        (**self).overrun(tick, late_s);
    }
    fn bus_input(&mut self, input: &BusInput) {
        (**self).bus_input(input);
    }
    fn input_rejected(&mut self, tick: u64, input: &BusInput, reason: &str) {
        (**self).input_rejected(tick, input, reason);
    }
    fn pprz_out(&mut self, tick: u64, out: &PprzOut) {
        (**self).pprz_out(tick, out);
    }
    fn paired(&mut self, tick: u64, ac_id: u8, id: usize, copter: &str) {
        (**self).paired(tick, ac_id, id, copter);
    }
    fn frame_dropped(&mut self, tick: u64, pprz_lost: u64) {
        (**self).frame_dropped(tick, pprz_lost);
    }
    fn failsafe(&mut self, tick: u64, world: &World, event: &FailsafeEvent) {
        (**self).failsafe(tick, world, event);
    }
    fn lockstep_timeout(&mut self, tick: u64, world: &World, copter: usize, client: &str) {
        (**self).lockstep_timeout(tick, world, copter, client);
    }
}

/// What a flight leaves when its loop ends.
#[derive(Debug)]
pub struct Finished<W> {
    /// The world at the end (it grows on spawn).
    pub world: Arc<World>,
    /// The final state.
    pub state: State,
    /// The loop's counters.
    pub stats: LoopStats,
    /// The log and live view, to finish.
    pub recorder: Recorder,
    /// The front end's observer.
    pub watch: W,
}

/// Runs `flight` until `opts.ticks` steps, a stop request, or `stop_flag`: requests are applied
/// before each step, frames go out after it, and the clock or the lockstep paces it.
pub fn run_loop<W: StepObserver>(
    mut flight: Flight<W>,
    requests: Receiver<Request>,
    frames: Option<tokio::sync::mpsc::Sender<Frame>>,
    stop_flag: &AtomicBool,
    opts: &LoopOptions,
) -> Finished<W> {
    let dt = Duration::from_secs_f64(flight.world().params.control_dt_s);
    let mut lockstep = opts.lockstep.as_ref().filter(|_| frames.is_some()).map(|o| Lockstep::new(o.clone()));
    let stopped = |f: &Flight<W>| f.stats().stopped_early || stop_flag.load(Ordering::Relaxed);
    if let Some(ls) = lockstep.as_mut() {
        ls.wait_for_claims(&mut flight, &requests, stop_flag);
        if let Some(tx) = &frames {
            // The state the controllers answer first. The receiver is gone only when the
            // publisher stopped; then nobody is left to answer and the timeouts count it.
            let _ = tx.blocking_send(flight.initial_frame());
        }
        ls.started = true;
    }
    let mut start = Instant::now();
    for k in 0..opts.ticks {
        while let Ok(r) = requests.try_recv() {
            route(&mut flight, lockstep.as_mut(), r);
        }
        if let Some(ls) = lockstep.as_mut() {
            ls.wait_for_answers(&mut flight, &requests, stop_flag);
        }
        if stopped(&flight) {
            flight.stopped_early();
            break;
        }
        if k == 0 {
            // Real-time pacing starts with the first step, after any wait for claims.
            start = Instant::now();
        }
        let stepped = match flight.step() {
            Ok(s) => s,
            Err(halt) => {
                match halt {
                    Halt::Shard(e) => flight.shard_error(e),
                    Halt::Checkpoint(e) => flight.checkpoint_error(e),
                    Halt::Log => {}
                }
                flight.stopped_early();
                break;
            }
        };
        if let Some(tx) = &frames {
            let frame = flight.frame(stepped.sensed, stepped.pprz_out);
            if lockstep.is_some() {
                // Lockstep: the controllers wait for this frame; never drop it.
                let _ = tx.blocking_send(frame);
            } else if let Err(e) = tx.try_send(frame) {
                flight.frame_dropped(e.into_inner());
            }
        }
        if opts.realtime {
            let deadline = start + dt * (k as u32 + 1);
            let now = Instant::now();
            if now > deadline {
                flight.overrun((now - deadline).as_secs_f64());
            } else {
                std::thread::sleep(deadline - now);
            }
        }
    }
    // What arrived too late for a step: logged, so that no received input goes unrecorded.
    let (world, state, mut stats, recorder, watch) = flight.finish(requests.try_iter());
    stats.lockstep = lockstep.map(|l| l.stats);
    Finished { world, state, stats, recorder, watch }
}

/// [`run_loop`] of a new flight that records nothing, watched by `watch`: for tests,
/// evaluations and benchmarks. Returns the world, the state, the counters and the watch.
#[allow(clippy::too_many_arguments)]
pub fn run_watched<W: StepObserver>(
    world: World,
    state: State,
    inputs: Inputs,
    requests: Receiver<Request>,
    frames: Option<tokio::sync::mpsc::Sender<Frame>>,
    watch: W,
    stop_flag: &AtomicBool,
    opts: &LoopOptions,
) -> (Arc<World>, State, LoopStats, W) {
    let flight = Flight::new(world, state, inputs, opts, Recorder::default(), watch);
    let end = run_loop(flight, requests, frames, stop_flag, opts);
    (end.world, end.state, end.stats, end.watch)
}

/// Hands a request to the flight, through the lockstep's bookkeeping when there is one.
fn route<W: StepObserver>(flight: &mut Flight<W>, lockstep: Option<&mut Lockstep>, r: Request) {
    match lockstep {
        Some(ls) => {
            if let Some(r) = ls.sort(flight, r) {
                flight.apply(r);
            }
        }
        None => flight.apply(r),
    }
}

/// The lockstep's view of the run: who controls which copter, who has answered the current
/// tick.
#[derive(Debug)]
struct Lockstep {
    opts: LockstepOptions,
    /// Controller (client name) by copter id, and the first tick it must answer: the copters
    /// the loop waits for.
    controllers: BTreeMap<usize, (String, u64)>,
    /// Whether the first state (tick 0) has gone out: a claim made later is waited for from
    /// the next tick on, the first state its controller is sure to see.
    started: bool,
    /// Copters whose controller answered the current tick.
    answered: std::collections::BTreeSet<usize>,
    /// The tick `answered` is for.
    tick: u64,
    stats: LockstepStats,
}

impl Lockstep {
    fn new(opts: LockstepOptions) -> Self {
        Self {
            opts,
            controllers: BTreeMap::new(),
            started: false,
            answered: Default::default(),
            tick: 0,
            stats: LockstepStats::default(),
        }
    }

    /// Files a request: claims change whom the loop waits for; a claimed copter's commands
    /// must answer the current tick. Returns what the flight should apply (a refused command
    /// comes back as [`Request::Rejected`], for the log).
    fn sort<W: StepObserver>(&mut self, flight: &Flight<W>, r: Request) -> Option<Request> {
        let tick = flight.state().tick;
        self.at(tick);
        match r {
            Request::Controller { ref copter, ref client, .. } => {
                let world = flight.world();
                // Twins are paced by their real copters, never held by the lockstep.
                if let Some(id) = world.copter_id(copter).filter(|&id| world.copters[id].kind == CopterKind::Virtual) {
                    let from = if self.started { tick + 1 } else { 0 };
                    match client {
                        Some(c) => self.controllers.insert(id, (c.clone(), from)),
                        None => self.controllers.remove(&id),
                    };
                }
                Some(r)
            }
            Request::Command { copter, cmd, origin } => {
                let Some(id) = flight.world().copter_id(&copter).filter(|id| self.controllers.contains_key(id)) else {
                    return Some(Request::Command { copter, cmd, origin });
                };
                let refuse = |reason: String| Request::Rejected { origin: origin.clone(), reason };
                match cmd.tick {
                    Some(t) if t == tick => {
                        self.stats.answers += u64::from(self.answered.insert(id));
                        Some(Request::Command { copter, cmd, origin })
                    }
                    Some(t) if t < tick => {
                        self.stats.late += 1;
                        Some(refuse(format!("lockstep: the answer to tick {t} came after tick {tick} had begun")))
                    }
                    t => {
                        self.stats.refused += 1;
                        Some(refuse(match t {
                            Some(t) => format!("lockstep: tick {t} is ahead of the simulator's tick {tick}"),
                            None => format!("lockstep: a command to claimed copter {copter:?} must carry \"tick\""),
                        }))
                    }
                }
            }
            r => Some(r),
        }
    }

    /// The answers so far are for `tick`: a new tick starts with none.
    fn at(&mut self, tick: u64) {
        if tick != self.tick {
            self.tick = tick;
            self.answered.clear();
        }
    }

    /// The controllers that owe an answer for the current tick and have not given it.
    fn silent(&self) -> impl Iterator<Item = (usize, &str)> {
        (self.controllers.iter())
            .filter(|(id, (_, from))| *from <= self.tick && !self.answered.contains(id))
            .map(|(&id, (client, _))| (id, client.as_str()))
    }

    fn all_answered(&self) -> bool {
        self.silent().next().is_none()
    }

    /// Holds the first step until the copters of `wait_claims` have controllers.
    fn wait_for_claims<W: StepObserver>(
        &mut self,
        flight: &mut Flight<W>,
        requests: &Receiver<Request>,
        stop: &AtomicBool,
    ) {
        let missing = |ls: &Self, f: &Flight<W>| -> Vec<String> {
            let w = f.world();
            let claimed = |n: &String| w.copter_id(n).is_some_and(|id| ls.controllers.contains_key(&id));
            ls.opts.wait_claims.iter().filter(|n| !claimed(n)).cloned().collect()
        };
        let mut told = false;
        while !missing(self, flight).is_empty() && !stop.load(Ordering::Relaxed) && !flight.stats().stopped_early {
            if !told {
                tracing::info!("lockstep: waiting for claims on {}", missing(self, flight).join(", "));
                told = true;
            }
            match requests.recv_timeout(Duration::from_millis(100)) {
                Ok(r) => route(flight, Some(self), r),
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => return,
            }
        }
    }

    /// Waits until every controller answered the current tick, or the timeout: then each
    /// silent controller is counted and logged, and its copter keeps its last command.
    fn wait_for_answers<W: StepObserver>(
        &mut self,
        flight: &mut Flight<W>,
        requests: &Receiver<Request>,
        stop: &AtomicBool,
    ) {
        self.at(flight.state().tick);
        if self.all_answered() {
            return;
        }
        let stopped = |f: &Flight<W>| stop.load(Ordering::Relaxed) || f.stats().stopped_early;
        if stopped(flight) {
            return;
        }
        self.stats.steps_held += 1;
        let began = Instant::now();
        let deadline = began + self.opts.timeout;
        while !self.all_answered() && !stopped(flight) {
            // The deadline holds even while other traffic keeps the queue busy.
            let now = Instant::now();
            if now >= deadline {
                let silent: Vec<(usize, String)> = self.silent().map(|(id, c)| (id, c.to_owned())).collect();
                for (id, client) in silent {
                    *self.stats.timeouts.entry(client.clone()).or_default() += 1;
                    flight.lockstep_timeout(id, &client);
                }
                break;
            }
            // Short slices, so that a stop signal is seen.
            match requests.recv_timeout((deadline - now).min(Duration::from_millis(100))) {
                Ok(r) => route(flight, Some(self), r),
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => break,
            }
        }
        self.stats.wait_s += began.elapsed().as_secs_f64();
    }
}
