//! The step loop on its own thread, fed and drained through bounded channels.
//!
//! - Requests (commands, spawns, stop) arrive on a bounded channel and are applied at the
//!   start of the next control step.
//! - After each step a [`Frame`] goes out on a bounded channel with `try_send`: publishing never
//!   blocks the step loop; frames that do not fit are dropped and counted.
//! - Real-time mode paces control steps against absolute wall-clock deadlines (`start + k·dt`),
//!   so there is no drift; a step that ends after its deadline counts as an overrun.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, TryRecvError};
use std::time::{Duration, Instant};

use sim_core::scene::CopterSpec;
use sim_core::{Inputs, State, StepReport, World, step_into};

use crate::failsafe::{Failsafe, FailsafeEvent, FailsafeKind, FailsafeOptions};
use crate::mixed::{Outbox, OutboxOptions, PprzOut, Sample, Summary};
use crate::sync::{SyncOptions, SyncStats, TwinSync};
use crate::wire::{CommandMsg, SensorsMsg, StateMsg, sensors_msg, state_msg};

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
}

/// No observer.
impl StepObserver for () {
    fn after_step(&mut self, _: &World, _: &State, _: &Inputs, _: &StepReport) {}
}

/// Runs the loop until `ticks` steps, a stop request, or `stop_flag`. Returns the final state.
#[allow(clippy::too_many_arguments)]
pub fn run_loop(
    world: World,
    mut state: State,
    mut inputs: Inputs,
    requests: Receiver<Request>,
    frames: Option<tokio::sync::mpsc::Sender<Frame>>,
    observer: &mut dyn StepObserver,
    stop_flag: &AtomicBool,
    opts: &LoopOptions,
) -> (Arc<World>, State, LoopStats) {
    let mut world = Arc::new(world);
    let mut stats = LoopStats::default();
    let dt = Duration::from_secs_f64(world.params.control_dt_s);
    let start = Instant::now();
    let sonar_period = world.sensors.spec.sonar.period_steps.max(1) as u64;
    let mut outbox = opts.outbox.clone().map(Outbox::new);
    let mut failsafe = Failsafe::new(opts.failsafe.clone());
    let mut fs_events: Vec<FailsafeEvent> = Vec::new();
    // One report for the whole run: its event list keeps its capacity.
    let mut report = StepReport::default();
    let mut sync = opts.sync.clone().and_then(|o| match TwinSync::new(&world, o) {
        Ok(s) => Some(s),
        Err(e) => {
            tracing::warn!("twin synchronisation is off: {e}");
            None
        }
    });
    // A shard: which copters it owned after the last step.
    let mut owned: Vec<bool> = Vec::new();
    for k in 0..opts.ticks {
        // Requests, applied before this step.
        loop {
            match requests.try_recv() {
                Ok(Request::Command { copter, cmd, origin }) => match world.copter_id(&copter) {
                    Some(id) => {
                        observer.bus_input(&origin);
                        failsafe.commanded(id, &mut inputs, &mut fs_events);
                        cmd.apply(&mut inputs.commands[id]);
                        stats.commands_applied += 1;
                    }
                    None => {
                        stats.commands_unknown_copter += 1;
                        observer.input_rejected(state.tick, &origin, &format!("no copter named {copter:?}"));
                    }
                },
                Ok(Request::Rejected { origin, reason }) => {
                    stats.inputs_rejected += 1;
                    observer.input_rejected(state.tick, &origin, &reason);
                }
                Ok(Request::Ignored { origin, reason: _ }) => {
                    stats.inputs_ignored += 1;
                    observer.bus_input(&origin);
                }
                Ok(Request::Spawn { spec, reply }) if state.shard().is_some() => {
                    stats.spawns_failed += 1;
                    let _ = reply.send(Err(format!(
                        "cannot spawn {:?}: a sharded run's copters are fixed by its scene",
                        spec.name
                    )));
                }
                Ok(Request::Spawn { spec, reply }) => {
                    let answer = spawn(&mut world, &mut state, &mut inputs, &spec, observer, &mut stats);
                    if let Err(e) = &answer {
                        stats.spawns_failed += 1;
                        tracing::warn!("spawn of {:?} refused: {e}", spec.name);
                    }
                    // The requester may have given up (it waits 5 s); the spawn stands and is
                    // logged either way.
                    let _ = reply.send(answer.map(|_| spec.name.clone()));
                }
                Ok(Request::Tracking { copter, pos_m, origin }) => {
                    let Some(id) = world.copter_id(&copter) else {
                        observer.input_rejected(state.tick, &origin, &format!("no copter named {copter:?}"));
                        continue;
                    };
                    observer.bus_input(&origin);
                    if let Some(sync) = sync.as_mut() {
                        let t = state.time_s(&world);
                        sync.on_tracking(&world, &state, id, t, pos_m);
                    }
                }
                Ok(Request::Twin { copter, spawn: spec, cmd, observed_rpy, sonar_m, yaw_rad, origin }) => {
                    if world.copter_id(&copter).is_none()
                        && let Some(spec) = spec
                    {
                        match spawn(&mut world, &mut state, &mut inputs, &spec, observer, &mut stats) {
                            Ok(()) => {
                                observer.paired(state.tick, spec.ac_id.unwrap_or(0), world.copters.len() - 1, &copter);
                                stats.twins.entry(copter.clone()).or_default().spawned = true;
                            }
                            Err(e) => tracing::warn!("cannot spawn twin `{copter}`: {e}"),
                        }
                    }
                    let Some(id) = world.copter_id(&copter) else {
                        observer.input_rejected(state.tick, &origin, &format!("no copter named {copter:?}"));
                        continue;
                    };
                    observer.bus_input(&origin);
                    let twin = stats.twins.entry(copter).or_default();
                    let cmd_attitude = cmd.as_ref().map(|c| [c.pitch, c.roll, c.yaw]);
                    if let Some(cmd) = cmd {
                        failsafe.telemetry(id, Instant::now(), &mut inputs, &mut fs_events);
                        cmd.apply(&mut inputs.commands[id]);
                        twin.inputs_applied += 1;
                        let now = crate::log::now_unix_ns();
                        twin.latencies_ms.push(now.saturating_sub(origin.received_unix_ns) as f32 / 1e6);
                    }
                    if let Some(rpy) = observed_rpy {
                        twin.observed = Some((rpy, Instant::now()));
                    }
                    if let Some(sync) = sync.as_mut() {
                        if let Some([p, r, y]) = cmd_attitude {
                            sync.on_command(&world, &state, id, p, r, y);
                        }
                        if let Some(y) = yaw_rad {
                            let t = state.time_s(&world);
                            sync.on_yaw(&world, &state, id, t, y);
                        }
                        if let Some(r) = sonar_m {
                            sync.on_sonar(&world, &state, id, r);
                        }
                    }
                }
                Ok(Request::Controller { copter, client, lost }) => {
                    let Some(id) = world.copter_id(&copter) else {
                        tracing::warn!("controller change for {copter:?}, which is not in the world");
                        continue;
                    };
                    match (client, lost) {
                        (None, Some(lost)) => {
                            failsafe.client_lost(&world, &state, id, &lost, &mut inputs, &mut fs_events);
                        }
                        (client, _) => failsafe.controller(id, client, &mut fs_events),
                    }
                }
                Ok(Request::Stop) => {
                    stats.stopped_early = true;
                }
                Err(TryRecvError::Empty | TryRecvError::Disconnected) => break,
            }
        }
        if stats.stopped_early || stop_flag.load(Ordering::Relaxed) {
            stats.stopped_early = true;
            break;
        }
        let sensed = state.tick.is_multiple_of(sonar_period);
        if let Some(sync) = &sync {
            sync.adjust_commands(&mut inputs);
        }
        if let Some(link) = &opts.shard {
            let exchanged = crate::lock(link).exchange(&mut state);
            if let Err(e) = exchanged {
                stats.shard_error = Some(e.to_string());
                stats.stopped_early = true;
                break;
            }
        }
        step_into(&world, &mut state, &inputs, &mut report);
        observer.after_step(&world, &state, &inputs, &report);
        if let Some(view) = state.shard() {
            if report.shard_violations > 0 {
                stats.shard_error = Some(format!(
                    "at tick {} {} copter(s) were in a contact cluster or a wake wider than the halo ({:.1} m) \
                     allows: the run would no longer be the one-process run",
                    report.tick,
                    report.shard_violations,
                    view.partition.halo_m()
                ));
                stats.stopped_early = true;
                break;
            }
            owned.resize(world.copters.len(), false);
            for (i, o) in owned.iter_mut().enumerate() {
                let now = state.owns(i);
                stats.shard_taken_over += u64::from(now && !*o && k > 0);
                *o = now;
            }
        }
        stats.steps += 1;
        track_twins(&world, &state, &mut stats.twins);
        if let Some(sync) = sync.as_mut() {
            sync.after_step(&world, &mut state, &inputs);
        }
        failsafe.after_step(&world, &state, &mut inputs, Instant::now(), &mut fs_events);
        for e in fs_events.drain(..) {
            if let FailsafeKind::Hold { .. } = e.kind {
                if let Some(t) = stats.twins.get_mut(&world.copters[e.copter].name) {
                    t.link_lost += 1;
                }
                if let Some(sync) = sync.as_mut() {
                    sync.on_link_lost(e.copter);
                }
            }
            tracing::warn!("failsafe: {}", e.message(&world));
            observer.failsafe(state.tick, &world, &e);
        }
        let mut pprz_out = Vec::new();
        if let Some(outbox) = outbox.as_mut() {
            outbox.after_step(&world, &state, &inputs, sensed, &mut pprz_out);
            for out in &pprz_out {
                observer.pprz_out(state.tick, out);
            }
            stats.pprz_sent += pprz_out.len() as u64;
        }
        if let Some(tx) = &frames {
            let n = world.copters.len();
            let ids: Vec<u32> = (0..n).filter(|&i| state.owns(i)).map(|i| i as u32).collect();
            let frame = Frame {
                world: world.clone(),
                tick: state.tick,
                time_s: state.time_s(&world),
                states: ids.iter().map(|&i| state_msg(&world, &state, &inputs, i as usize)).collect(),
                sensors: if sensed {
                    ids.iter().map(|&i| sensors_msg(&world, &state, i as usize)).collect()
                } else {
                    Vec::new()
                },
                ids,
                report: report.clone(),
                pprz_out,
                stepped_at: Instant::now(),
            };
            if let Err(e) = tx.try_send(frame) {
                stats.frames_dropped += 1;
                let lost = e.into_inner().pprz_out.len() as u64;
                stats.pprz_sent -= lost;
                stats.pprz_dropped += lost;
                observer.frame_dropped(state.tick, lost);
            }
        }
        if opts.realtime {
            let deadline = start + dt * (k as u32 + 1);
            let now = Instant::now();
            if now > deadline {
                stats.overruns += 1;
                observer.overrun(state.tick, (now - deadline).as_secs_f64());
            } else {
                std::thread::sleep(deadline - now);
            }
        }
    }
    // What arrived too late for a step: logged, so that no received input goes unrecorded.
    while let Ok(r) = requests.try_recv() {
        if let Request::Command { origin, .. }
        | Request::Twin { origin, .. }
        | Request::Tracking { origin, .. }
        | Request::Rejected { origin, .. }
        | Request::Ignored { origin, .. } = &r
        {
            stats.inputs_after_end += 1;
            observer.input_rejected(state.tick, origin, "arrived after the last step");
        }
    }
    stats.failsafe = failsafe.counts.clone();
    if let Some(sync) = &sync {
        stats.sync = sync.stats().into_iter().map(|(id, s)| (world.copters[id].name.clone(), s)).collect();
    }
    for t in stats.twins.values_mut() {
        t.input_latency_ms = t.latencies_ms.summary();
        let n = t.attitude_samples.max(1) as f64;
        t.attitude_rms_deg = t.sq_sum.map(|s| (s / n).sqrt().to_degrees());
    }
    (world, state, stats)
}

/// Adds a copter to the running world.
fn spawn(
    world: &mut Arc<World>,
    state: &mut State,
    inputs: &mut Inputs,
    spec: &CopterSpec,
    observer: &mut dyn StepObserver,
    stats: &mut LoopStats,
) -> Result<(), String> {
    let w = world.with_spawned(state, spec).map_err(|e| e.to_string())?;
    let id = w.copters.len() - 1;
    state.add_copters(&w);
    inputs.commands.push(w.copters[id].initial_command.clone());
    *world = Arc::new(w);
    observer.spawned(world, id, state.tick);
    stats.spawned += 1;
    Ok(())
}

/// Accumulates each twin's attitude error against its real copter's latest attitude.
fn track_twins(world: &World, state: &State, twins: &mut BTreeMap<String, TwinStats>) {
    for (name, t) in twins.iter_mut() {
        let Some((rpy, at)) = t.observed else { continue };
        if at.elapsed().as_secs_f64() > 0.2 {
            continue;
        }
        let Some(id) = world.copter_id(name) else { continue };
        if state.copters[id].crash.is_some() {
            continue;
        }
        let twin = state.pose(id).rpy_rad;
        for k in 0..2 {
            let e = f64::from(sim_core::math::wrap_angle_rad(twin[k] - rpy[k]));
            t.sq_sum[k] += e * e;
        }
        t.attitude_samples += 1;
    }
}
