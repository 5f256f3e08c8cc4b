//! What goes into and comes out of the step loop besides its requests: how it runs
//! ([`LoopOptions`], [`LockstepOptions`]), what each step produced for publishing ([`Frame`]),
//! what it reports ([`LoopStats`], [`TwinStats`], [`LockstepStats`]), and the observer that
//! sees every step ([`StepObserver`]). [`crate::engine::flight`] produces them,
//! [`crate::engine::run_loop`] paces and routes them.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use sim_core::{Inputs, State, StepReport, World};

use crate::engine::failsafe::{FailsafeEvent, FailsafeOptions};
use crate::engine::request::BusInput;
use crate::mixed::outbox::{OutboxOptions, PprzOut};
use crate::mixed::stats::{Sample, Summary};
use crate::mixed::sync::{SyncOptions, SyncStats};
use crate::wire::{SensorsMsg, StateMsg};

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
    /// Mixed reality: send virtual sonar and virtual telemetry (see [`crate::mixed::outbox`]).
    pub outbox: Option<OutboxOptions>,
    /// Keep twins where their real copters are (see [`crate::mixed::sync`]).
    pub sync: Option<SyncOptions>,
    /// Lost links: twins' telemetry, virtual copters' controllers (see [`crate::engine::failsafe`]).
    pub failsafe: FailsafeOptions,
    /// A shard's link to its neighbours (see [`crate::shard`]): the state must be a shard's;
    /// every step first trades ghosts through it.
    pub shard: Option<Arc<std::sync::Mutex<crate::shard::ShardLink>>>,
    /// Hold each step for the claimed copters' controllers (needs a frame channel).
    pub lockstep: Option<LockstepOptions>,
    /// Write a checkpoint every so many steps (see [`crate::engine::checkpoint`]).
    pub checkpoint: Option<crate::engine::checkpoint::CheckpointOptions>,
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
    /// Texts logged that drive nothing (see [`crate::engine::Request::Ignored`]).
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
    /// Autopilots the world turned away at their hello.
    pub autopilots_refused: Vec<crate::autopilot::Refusal>,
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
