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

use sim_core::{CopterKind, Inputs, State, World};

use crate::engine::flight::{Flight, Halt, Recorder};
use crate::engine::loop_io::{Frame, LockstepOptions, LockstepStats, LoopOptions, LoopStats, StepObserver};
use crate::engine::request::Request;

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
    // Frames that carry an autopilot's counted uplink must reach `link`: never dropped.
    let hold_frames = lockstep.is_some() || flight.counts_uplinks();
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
                    Halt::Log | Halt::Stopped => {}
                }
                flight.stopped_early();
                break;
            }
        };
        if let Some(tx) = &frames {
            let frame = flight.frame(stepped.sensed, stepped.pprz_out);
            if hold_frames {
                // Lockstep: the controllers wait for this frame; never drop it. So do the
                // autopilots whose uplink is counted.
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
