//! The step loop on its own thread, fed and drained through bounded channels.
//!
//! - Requests (commands, spawns, stop) arrive on a bounded channel and are applied at the
//!   start of the next control step.
//! - After each step a [`Frame`] goes out on a bounded channel with `try_send`: publishing never
//!   blocks the step loop; frames that do not fit are dropped and counted.
//! - Real-time mode paces control steps against absolute wall-clock deadlines (`start + k·dt`),
//!   so there is no drift; a step that ends after its deadline counts as an overrun.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, TryRecvError};
use std::time::{Duration, Instant};

use sim_core::scene::CopterSpec;
use sim_core::{Inputs, State, StepReport, World, step};

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
    /// Per-copter state.
    pub states: Vec<StateMsg>,
    /// Per-copter sensors, when the sonars updated this step.
    pub sensors: Vec<SensorsMsg>,
    /// Events of the step.
    pub report: StepReport,
    /// Wall-clock instant the step finished.
    pub stepped_at: Instant,
}

/// How the loop runs.
#[derive(Clone, Debug)]
pub struct LoopOptions {
    /// Pace against the wall clock.
    pub realtime: bool,
    /// Stop after this many control steps.
    pub ticks: u64,
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
    /// Copters spawned.
    pub spawned: u64,
    /// Whether it stopped early (stop request or signal).
    pub stopped_early: bool,
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
    for k in 0..opts.ticks {
        // Requests, applied before this step.
        loop {
            match requests.try_recv() {
                Ok(Request::Command { copter, cmd, origin }) => match world.copter_id(&copter) {
                    Some(id) => {
                        observer.bus_input(&origin);
                        cmd.apply(&mut inputs.commands[id]);
                        stats.commands_applied += 1;
                    }
                    None => {
                        stats.commands_unknown_copter += 1;
                        observer.input_rejected(state.tick, &origin, &format!("no copter named {copter:?}"));
                    }
                },
                Ok(Request::Rejected { origin, reason }) => observer.input_rejected(state.tick, &origin, &reason),
                Ok(Request::Spawn { spec, reply }) => {
                    let answer = match world.with_spawned(&state, &spec) {
                        Ok(w) => {
                            let id = w.copters.len() - 1;
                            state.add_copters(&w);
                            inputs.commands.push(w.copters[id].initial_command.clone());
                            world = Arc::new(w);
                            observer.spawned(&world, id, state.tick);
                            stats.spawned += 1;
                            Ok(spec.name.clone())
                        }
                        Err(e) => Err(e.to_string()),
                    };
                    let _ = reply.send(answer);
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
        let report = step(&world, &mut state, &inputs);
        observer.after_step(&world, &state, &inputs, &report);
        stats.steps += 1;
        if let Some(tx) = &frames {
            let n = world.copters.len();
            let frame = Frame {
                world: world.clone(),
                tick: state.tick,
                time_s: state.time_s(&world),
                states: (0..n).map(|i| state_msg(&world, &state, &inputs, i)).collect(),
                sensors: if sensed { (0..n).map(|i| sensors_msg(&world, &state, i)).collect() } else { Vec::new() },
                report,
                stepped_at: Instant::now(),
            };
            if tx.try_send(frame).is_err() {
                stats.frames_dropped += 1;
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
    (world, state, stats)
}
