//! One flight: the engine behind `twinswarm run`, the Python package and lockstep.
//!
//! A [`Flight`] owns everything a run changes: the world (it grows on spawn), the state, the
//! inputs, the machinery that runs between two steps (requests, failsafe, twin
//! synchronisation, Paparazzi output, a shard's link), the counters, and its [`Recorder`] (the
//! MCAP log and the live view). Front ends only drive it:
//! - [`crate::engine::run_loop`] feeds it bus requests and publishes its frames (the CLI's `run`,
//!   free running, real time or lockstep);
//! - the Python package (`crates/py`) writes commands and steps it directly.
//!
//! A front end's own bookkeeping (a summary, a progress bar) watches the same steps as the
//! recorder through `W`, a [`StepObserver`].

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use sim_core::scene::CopterSpec;
use sim_core::{CopterKind, Inputs, State, StepReport, World, step_into};

use crate::engine::checkpoint::Checkpointer;
use crate::engine::failsafe::{Failsafe, FailsafeEvent, FailsafeKind};
use crate::engine::loop_io::{Frame, LoopOptions, LoopStats, StepObserver, TwinStats};
use crate::engine::request::{BusInput, Request};
use crate::log::{EventKind, LogError, LogEvent, Logger};
use crate::mixed::outbox::{Outbox, PprzOut};
use crate::mixed::sync::TwinSync;
use crate::shard::{LinkError, ShardLink};
use crate::wire::{CommandError, CommandMsg, sensors_msg, state_msg};

/// Why a step did not happen.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Halt {
    /// A shard could not go on (a neighbour gone or silent, a broken invariant).
    Shard(String),
    /// The recorder failed and the run was told to stop on log errors.
    Log,
    /// A checkpoint could not be written (the run was asked for them).
    Checkpoint(String),
    /// A stop request or a signal ended a shard's wait at its barrier: the step was not taken.
    Stopped,
}

/// What one step produced besides the new state.
#[derive(Debug, Default)]
pub struct Stepped {
    /// Whether the sonars updated in this step.
    pub sensed: bool,
    /// Paparazzi texts to send (virtual sonar, virtual copters' telemetry).
    pub pprz_out: Vec<PprzOut>,
}

/// One flight (see the module docs).
#[derive(Debug)]
pub struct Flight<W: StepObserver = ()> {
    core: Core,
    /// The log and the live view.
    pub recorder: Recorder,
    /// The front end's own observer.
    pub watch: W,
}

/// A flight's world, state and machinery, without its observers.
#[derive(Debug)]
struct Core {
    world: Arc<World>,
    state: State,
    inputs: Inputs,
    report: StepReport,
    failsafe: Failsafe,
    fs_events: Vec<FailsafeEvent>,
    sync: Option<TwinSync>,
    outbox: Option<Outbox>,
    shard: Option<Arc<Mutex<ShardLink>>>,
    autopilots: Option<Arc<Mutex<crate::autopilot::Autopilots>>>,
    /// A shard: which copters it owned after the last step.
    owned: Vec<bool>,
    checkpoints: Option<Checkpointer>,
    stats: LoopStats,
}

impl<W: StepObserver> Flight<W> {
    /// A flight of `world` from `state` with `inputs`; `opts` says which machinery runs
    /// between steps (its pacing fields are the loop's business).
    pub fn new(world: World, state: State, inputs: Inputs, opts: &LoopOptions, recorder: Recorder, watch: W) -> Self {
        let sync = opts.sync.clone().and_then(|o| match TwinSync::new(&world, o) {
            Ok(s) => Some(s),
            Err(e) => {
                tracing::warn!("twin synchronisation is off: {e}");
                None
            }
        });
        let core = Core {
            world: Arc::new(world),
            state,
            inputs,
            report: StepReport::default(),
            failsafe: Failsafe::new(opts.failsafe.clone()),
            fs_events: Vec::new(),
            sync,
            outbox: opts.outbox.clone().map(Outbox::new),
            shard: opts.shard.clone(),
            autopilots: opts.autopilots.clone(),
            owned: Vec::new(),
            checkpoints: opts.checkpoint.clone().map(Checkpointer::new),
            stats: LoopStats::default(),
        };
        Self { core, recorder, watch }
    }

    /// The world (it changes only on spawn).
    pub fn world(&self) -> &Arc<World> {
        &self.core.world
    }

    /// The state after the last step.
    pub fn state(&self) -> &State {
        &self.core.state
    }

    /// The commands the next step flies.
    pub fn inputs(&self) -> &Inputs {
        &self.core.inputs
    }

    /// The events of the last step.
    pub fn report(&self) -> &StepReport {
        &self.core.report
    }

    /// The counters so far.
    pub fn stats(&self) -> &LoopStats {
        &self.core.stats
    }

    /// Whether an autopilot's uplink is counted in the lockstep: then no frame may be dropped
    /// (its texts must reach `link`).
    pub fn counts_uplinks(&self) -> bool {
        self.core.autopilots.as_ref().is_some_and(|a| crate::lock(a).counts_uplinks())
    }

    /// Marks the run as stopped before its end (a stop request or a signal).
    pub fn stopped_early(&mut self) {
        self.core.stats.stopped_early = true;
    }

    /// Replaces the state and the inputs (a restored snapshot, a reset). The world must be the
    /// one they belong to: same copters.
    pub fn restore(&mut self, state: State, inputs: Inputs) {
        self.core.state = state;
        self.core.inputs = inputs;
        self.core.report = StepReport::default();
    }

    /// Applies a validated command to copter `id`, as a bus command does: it counts, and it
    /// tells the failsafe that the copter is commanded. Twins take commands from their
    /// telemetry only.
    pub fn command(&mut self, id: usize, cmd: &CommandMsg) -> Result<(), CommandError> {
        let c = &mut self.core;
        let Some(def) = c.world.copters.get(id) else {
            return Err(CommandError::UnknownCopter(format!("#{id}")));
        };
        if def.kind == CopterKind::Real {
            return Err(CommandError::Malformed(format!(
                "copter {:?} is a twin: its real copter's telemetry drives it",
                def.name
            )));
        }
        cmd.validate(&c.world)?;
        c.failsafe.commanded(id, &mut c.inputs, &mut c.fs_events);
        cmd.apply(&mut c.inputs.commands[id]);
        c.stats.commands_applied += 1;
        Ok(())
    }

    /// Applies one request from the bus before the next step.
    pub fn apply(&mut self, request: Request) {
        let mut obs = Tee(&mut self.recorder, &mut self.watch);
        self.core.apply(request, &mut obs);
    }

    /// Runs one control step and what follows it: failsafe, twin synchronisation, Paparazzi
    /// output, observers. `Err` when the step could not or should not happen.
    pub fn step(&mut self) -> Result<Stepped, Halt> {
        if self.recorder.halted() {
            return Err(Halt::Log);
        }
        let mut obs = Tee(&mut self.recorder, &mut self.watch);
        let stepped = self.core.step(&mut obs)?;
        if self.core.checkpoints.as_ref().is_some_and(|c| c.due(self.core.state.tick)) {
            // The log first: a run resumed from this checkpoint logs from the next step on.
            self.recorder.sync();
            self.core.checkpoint().map_err(Halt::Checkpoint)?;
        }
        Ok(stepped)
    }

    /// The frame of the last step, for publishing.
    pub fn frame(&self, sensed: bool, pprz_out: Vec<PprzOut>) -> Frame {
        self.core.frame(sensed, pprz_out)
    }

    /// A frame published before the first step (lockstep: the state controllers answer
    /// first).
    pub fn initial_frame(&self) -> Frame {
        self.core.frame(true, Vec::new())
    }

    /// A frame could not be published: counts it and tells the observers.
    pub fn frame_dropped(&mut self, frame: Frame) {
        let lost = frame.pprz_out.len() as u64;
        let st = &mut self.core.stats;
        st.frames_dropped += 1;
        st.pprz_sent -= lost;
        st.pprz_dropped += lost;
        let tick = self.core.state.tick;
        Tee(&mut self.recorder, &mut self.watch).frame_dropped(tick, lost);
    }

    /// A real-time step finished `late_s` after its deadline.
    pub fn overrun(&mut self, late_s: f64) {
        self.core.stats.overruns += 1;
        let tick = self.core.state.tick;
        Tee(&mut self.recorder, &mut self.watch).overrun(tick, late_s);
    }

    /// A shard stopped: why.
    pub fn shard_error(&mut self, why: String) {
        self.core.stats.shard_error = Some(why);
    }

    /// A checkpoint could not be written: why.
    pub fn checkpoint_error(&mut self, why: String) {
        self.core.stats.checkpoint_error = Some(why);
    }

    /// Lockstep: `client`, copter `id`'s controller, did not answer the current tick in time.
    pub fn lockstep_timeout(&mut self, id: usize, client: &str) {
        let tick = self.core.state.tick;
        tracing::warn!("lockstep: {client:?} did not answer tick {tick} for copter {id} in time");
        Tee(&mut self.recorder, &mut self.watch).lockstep_timeout(tick, &self.core.world, id, client);
    }

    /// Tells the observers about an input refused before it reached the flight.
    pub fn input_rejected(&mut self, input: &BusInput, reason: &str) {
        let tick = self.core.state.tick;
        Tee(&mut self.recorder, &mut self.watch).input_rejected(tick, input, reason);
    }

    /// Ends the flight: what arrived too late for a step is logged, the counters are
    /// completed. The recorder and the watch stay with the caller.
    pub fn finish(mut self, late: impl IntoIterator<Item = Request>) -> (Arc<World>, State, LoopStats, Recorder, W) {
        let c = &mut self.core;
        let mut obs = Tee(&mut self.recorder, &mut self.watch);
        for r in late {
            if let Request::Command { origin, .. }
            | Request::Twin { origin, .. }
            | Request::Tracking { origin, .. }
            | Request::Rejected { origin, .. }
            | Request::Ignored { origin, .. } = &r
            {
                c.stats.inputs_after_end += 1;
                obs.input_rejected(c.state.tick, origin, "arrived after the last step");
            }
        }
        if let (Some(link), false) = (&c.shard, c.stats.stopped_early) {
            // Every step done: stay until the neighbours have this shard's last batch. A
            // neighbour that did not say so fails on its own; this shard's flight is whole.
            if let Err(e) = crate::lock(link).finish() {
                tracing::warn!("shard: leaving without every neighbour's word: {e}");
            }
        }
        c.stats.failsafe = c.failsafe.counts.clone();
        if let Some(a) = &c.autopilots {
            let a = crate::lock(a);
            c.stats.autopilots = a.stats();
            c.stats.autopilots_refused = a.refused();
            c.stats.autopilot_wait_s = a.wait_s();
        }
        if let Some(sync) = &c.sync {
            c.stats.sync = sync.stats().into_iter().map(|(id, s)| (c.world.copters[id].name.clone(), s)).collect();
        }
        for t in c.stats.twins.values_mut() {
            t.finish();
        }
        let Flight { core, recorder, watch } = self;
        (core.world, core.state, core.stats, recorder, watch)
    }
}

impl Core {
    fn apply(&mut self, request: Request, obs: &mut dyn StepObserver) {
        let tick = self.state.tick;
        match request {
            Request::Command { copter, cmd, origin } => match self.world.copter_id(&copter) {
                Some(id) => {
                    obs.bus_input(&origin);
                    self.failsafe.commanded(id, &mut self.inputs, &mut self.fs_events);
                    cmd.apply(&mut self.inputs.commands[id]);
                    self.stats.commands_applied += 1;
                }
                None => {
                    self.stats.commands_unknown_copter += 1;
                    obs.input_rejected(tick, &origin, &format!("no copter named {copter:?}"));
                }
            },
            Request::Rejected { origin, reason } => {
                self.stats.inputs_rejected += 1;
                obs.input_rejected(tick, &origin, &reason);
            }
            Request::Ignored { origin, reason: _ } => {
                self.stats.inputs_ignored += 1;
                obs.bus_input(&origin);
            }
            Request::Spawn { spec, reply } if self.state.shard().is_some() => {
                self.stats.spawns_failed += 1;
                // The requester may have given up; nothing changed either way.
                let _ = reply
                    .send(Err(format!("cannot spawn {:?}: a sharded run's copters are fixed by its scene", spec.name)));
            }
            Request::Spawn { spec, reply } => {
                let answer = self.spawn(&spec, obs);
                if let Err(e) = &answer {
                    self.stats.spawns_failed += 1;
                    tracing::warn!("spawn of {:?} refused: {e}", spec.name);
                }
                // The requester may have given up (it waits 5 s); the spawn stands and is
                // logged either way.
                let _ = reply.send(answer.map(|_| spec.name.clone()));
            }
            Request::Tracking { copter, pos_m, origin } => {
                let Some(id) = self.world.copter_id(&copter) else {
                    obs.input_rejected(tick, &origin, &format!("no copter named {copter:?}"));
                    return;
                };
                obs.bus_input(&origin);
                if let Some(sync) = self.sync.as_mut() {
                    let t = self.state.time_s(&self.world);
                    sync.on_tracking(&self.world, &self.state, id, t, pos_m);
                }
            }
            twin @ Request::Twin { .. } => self.twin(twin, obs),
            Request::Controller { copter, client, lost } => {
                let Some(id) = self.world.copter_id(&copter) else {
                    tracing::warn!("controller change for {copter:?}, which is not in the world");
                    return;
                };
                match (client, lost) {
                    (None, Some(lost)) => {
                        self.failsafe.client_lost(
                            &self.world,
                            &self.state,
                            id,
                            &lost,
                            &mut self.inputs,
                            &mut self.fs_events,
                        );
                    }
                    (client, _) => self.failsafe.controller(id, client, &mut self.fs_events),
                }
            }
            Request::Stop => self.stats.stopped_early = true,
        }
    }

    /// Telemetry of a real copter for its twin ([`Request::Twin`]): spawn it on first
    /// telemetry if paired so, apply its command, feed synchronisation.
    fn twin(&mut self, request: Request, obs: &mut dyn StepObserver) {
        let Request::Twin { copter, spawn, cmd, observed_rpy, sonar_m, yaw_rad, origin } = request else { return };
        if self.world.copter_id(&copter).is_none()
            && let Some(spec) = spawn
        {
            match self.spawn(&spec, obs) {
                Ok(()) => {
                    obs.paired(self.state.tick, spec.ac_id.unwrap_or(0), self.world.copters.len() - 1, &copter);
                    self.stats.twins.entry(copter.clone()).or_default().spawned = true;
                }
                Err(e) => tracing::warn!("cannot spawn twin `{copter}`: {e}"),
            }
        }
        let Some(id) = self.world.copter_id(&copter) else {
            obs.input_rejected(self.state.tick, &origin, &format!("no copter named {copter:?}"));
            return;
        };
        obs.bus_input(&origin);
        let twin = self.stats.twins.entry(copter).or_default();
        let cmd_attitude = cmd.as_ref().map(|c| [c.pitch, c.roll, c.yaw]);
        if let Some(cmd) = cmd {
            self.failsafe.telemetry(id, Instant::now(), &mut self.inputs, &mut self.fs_events);
            cmd.apply(&mut self.inputs.commands[id]);
            twin.applied(origin.received_unix_ns);
        }
        if let Some(rpy) = observed_rpy {
            twin.observe(rpy);
        }
        if let Some(sync) = self.sync.as_mut() {
            if let Some([p, r, y]) = cmd_attitude {
                sync.on_command(&self.world, &self.state, id, p, r, y);
            }
            if let Some(y) = yaw_rad {
                let t = self.state.time_s(&self.world);
                sync.on_yaw(&self.world, &self.state, id, t, y);
            }
            if let Some(r) = sonar_m {
                sync.on_sonar(&self.world, &self.state, id, r);
            }
        }
    }

    fn step(&mut self, obs: &mut dyn StepObserver) -> Result<Stepped, Halt> {
        let sonar_period = self.world.sensors.spec.sonar.period_steps.max(1) as u64;
        let sensed = self.state.tick.is_multiple_of(sonar_period);
        if let Some(sync) = &self.sync {
            sync.adjust_commands(&mut self.inputs);
        }
        if let Some(link) = &self.shard {
            crate::lock(link).exchange(&mut self.state).map_err(|e| match e {
                LinkError::Stopped { .. } => Halt::Stopped,
                e => Halt::Shard(e.to_string()),
            })?;
        }
        let mut autopilots = self.autopilots.as_ref().map(|a| crate::lock(a));
        if let Some(a) = autopilots.as_mut() {
            a.commands(&self.world, &self.state, &mut self.inputs);
        }
        step_into(&self.world, &mut self.state, &self.inputs, &mut self.report);
        if let Some(a) = autopilots.as_mut() {
            a.answer(&self.world, &self.state);
        }
        drop(autopilots);
        obs.after_step(&self.world, &self.state, &self.inputs, &self.report);
        self.check_shard().map_err(Halt::Shard)?;
        self.stats.steps += 1;
        track_twins(&self.world, &self.state, &mut self.stats.twins);
        if let Some(sync) = self.sync.as_mut() {
            sync.after_step(&self.world, &mut self.state, &self.inputs);
        }
        self.failsafe.after_step(&self.world, &self.state, &mut self.inputs, Instant::now(), &mut self.fs_events);
        for e in self.fs_events.drain(..) {
            if let FailsafeKind::Hold { .. } = e.kind {
                if let Some(t) = self.stats.twins.get_mut(&self.world.copters[e.copter].name) {
                    t.link_lost += 1;
                }
                if let Some(sync) = self.sync.as_mut() {
                    sync.on_link_lost(e.copter);
                }
            }
            tracing::warn!("failsafe: {}", e.message(&self.world));
            obs.failsafe(self.state.tick, &self.world, &e);
        }
        let mut pprz_out = Vec::new();
        if let Some(outbox) = self.outbox.as_mut() {
            outbox.after_step(&self.world, &self.state, &self.inputs, sensed, &mut pprz_out);
            if let Some(a) = &self.autopilots {
                // An autopilot aircraft's uplink through `link`: counted, or held back before
                // its start (crate::autopilot, "The uplink in the lockstep").
                let mut a = crate::lock(a);
                let t = self.state.time_s(&self.world);
                pprz_out.retain(|o| o.uplink_to.is_none_or(|ac| a.uplink(ac, &o.text, t)));
            }
            for out in &pprz_out {
                obs.pprz_out(self.state.tick, out);
            }
            self.stats.pprz_sent += pprz_out.len() as u64;
        }
        Ok(Stepped { sensed, pprz_out })
    }

    /// Writes a checkpoint of the state after the last step, with the neighbours' batches
    /// already in for the next.
    fn checkpoint(&mut self) -> Result<(), String> {
        let Some(ckpt) = self.checkpoints.as_mut() else { return Ok(()) };
        let mut link = self.shard.as_ref().map(|l| crate::lock(l));
        let early = match link.as_mut() {
            Some(l) => l.pending().map_err(|e| e.to_string())?,
            None => Vec::new(),
        };
        let path = ckpt.write(&self.state, &self.inputs, &early).map_err(|e| e.to_string())?;
        tracing::debug!("checkpoint {} written", path.display());
        self.stats.checkpoints_written = ckpt.written;
        self.stats.last_checkpoint = Some(path);
        Ok(())
    }

    /// A shard: stop on a broken invariant; count the copters taken over.
    fn check_shard(&mut self) -> Result<(), String> {
        let Some(view) = self.state.shard() else { return Ok(()) };
        if self.report.shard_violations > 0 {
            return Err(format!(
                "at tick {} {} copter(s) were in a contact cluster or a wake wider than the halo ({:.1} m) \
                 allows: the run would no longer be the one-process run",
                self.report.tick,
                self.report.shard_violations,
                view.partition.halo_m()
            ));
        }
        let first = self.owned.is_empty();
        self.owned.resize(self.world.copters.len(), false);
        for (i, o) in self.owned.iter_mut().enumerate() {
            let now = self.state.owns(i);
            self.stats.shard_taken_over += u64::from(now && !*o && !first);
            *o = now;
        }
        Ok(())
    }

    fn frame(&self, sensed: bool, pprz_out: Vec<PprzOut>) -> Frame {
        let (world, state, inputs) = (&self.world, &self.state, &self.inputs);
        let ids: Vec<u32> = (0..world.copters.len()).filter(|&i| state.owns(i)).map(|i| i as u32).collect();
        Frame {
            world: world.clone(),
            tick: state.tick,
            time_s: state.time_s(world),
            states: ids.iter().map(|&i| state_msg(world, state, inputs, i as usize)).collect(),
            sensors: match sensed {
                true => ids.iter().map(|&i| sensors_msg(world, state, i as usize)).collect(),
                false => Vec::new(),
            },
            ids,
            report: self.report.clone(),
            pprz_out,
            stepped_at: Instant::now(),
        }
    }

    /// Adds a copter to the running world.
    fn spawn(&mut self, spec: &CopterSpec, obs: &mut dyn StepObserver) -> Result<(), String> {
        let w = self.world.with_spawned(&self.state, spec).map_err(|e| e.to_string())?;
        let id = w.copters.len() - 1;
        self.state.add_copters(&w);
        self.inputs.commands.push(w.copters[id].initial_command.clone());
        self.world = Arc::new(w);
        obs.spawned(&self.world, id, self.state.tick);
        self.stats.spawned += 1;
        Ok(())
    }
}

/// Accumulates each twin's attitude error against its real copter's latest attitude.
fn track_twins(world: &World, state: &State, twins: &mut BTreeMap<String, TwinStats>) {
    for (name, t) in twins.iter_mut() {
        let Some(id) = world.copter_id(name) else { continue };
        if state.copters[id].crash.is_some() {
            continue;
        }
        t.track(state.pose(id).rpy_rad);
    }
}

/// Two observers of the same steps.
struct Tee<'a, W: StepObserver>(&'a mut Recorder, &'a mut W);

impl<W: StepObserver> StepObserver for Tee<'_, W> {
    fn after_step(&mut self, world: &World, state: &State, inputs: &Inputs, report: &StepReport) {
        self.0.after_step(world, state, inputs, report);
        self.1.after_step(world, state, inputs, report);
    }
    fn spawned(&mut self, world: &World, id: usize, tick: u64) {
        self.0.spawned(world, id, tick);
        self.1.spawned(world, id, tick);
    }
    fn overrun(&mut self, tick: u64, late_s: f64) {
        self.0.overrun(tick, late_s);
        self.1.overrun(tick, late_s);
    }
    fn bus_input(&mut self, input: &BusInput) {
        self.0.bus_input(input);
        self.1.bus_input(input);
    }
    fn input_rejected(&mut self, tick: u64, input: &BusInput, reason: &str) {
        self.0.input_rejected(tick, input, reason);
        self.1.input_rejected(tick, input, reason);
    }
    fn pprz_out(&mut self, tick: u64, out: &PprzOut) {
        self.0.pprz_out(tick, out);
        self.1.pprz_out(tick, out);
    }
    fn paired(&mut self, tick: u64, ac_id: u8, id: usize, copter: &str) {
        self.0.paired(tick, ac_id, id, copter);
        self.1.paired(tick, ac_id, id, copter);
    }
    fn frame_dropped(&mut self, tick: u64, pprz_lost: u64) {
        self.0.frame_dropped(tick, pprz_lost);
        self.1.frame_dropped(tick, pprz_lost);
    }
    fn failsafe(&mut self, tick: u64, world: &World, event: &FailsafeEvent) {
        self.0.failsafe(tick, world, event);
        self.1.failsafe(tick, world, event);
    }
    fn lockstep_timeout(&mut self, tick: u64, world: &World, copter: usize, client: &str) {
        self.0.lockstep_timeout(tick, world, copter, client);
        self.1.lockstep_timeout(tick, world, copter, client);
    }
}

/// A flight's MCAP log and live view (a [`Logger`] may have no file and feed only the view).
/// The first log error is kept; logging stops there, and the run stops too if asked to.
#[derive(Debug, Default)]
pub struct Recorder {
    log: Option<Logger>,
    /// The log file's path, kept after a failure (the error message names it).
    path: Option<std::path::PathBuf>,
    error: Option<(u64, LogError)>,
    stop_on_error: Option<Arc<AtomicBool>>,
    /// The last control step observed.
    tick: u64,
}

impl Recorder {
    /// Records into `log`, if any. With `stop_on_error`, a log error sets that flag (and
    /// [`Flight::step`] refuses further steps).
    pub fn new(log: Option<Logger>, stop_on_error: Option<Arc<AtomicBool>>) -> Self {
        let path = log.as_ref().filter(|l| l.has_file()).map(|l| l.path().to_owned());
        Self { log, path, error: None, stop_on_error, tick: 0 }
    }

    /// Whether it logs (a file or the live view).
    pub fn is_logging(&self) -> bool {
        self.log.is_some()
    }

    /// The log's path, if it writes (or wrote, until it failed) a file.
    pub fn path(&self) -> Option<&std::path::Path> {
        self.path.as_deref()
    }

    /// The first log error and the control step it happened at.
    pub fn error(&self) -> Option<&(u64, LogError)> {
        self.error.as_ref()
    }

    /// Hands over the logger (to finish it) and the first error.
    pub fn into_parts(self) -> (Option<Logger>, Option<(u64, LogError)>) {
        (self.log, self.error)
    }

    /// Everything logged so far to disk (flushed and `fsync`ed), waited for. A failure is a
    /// log error like any other (kept; the run stops if asked to).
    pub fn sync(&mut self) {
        if let Some(log) = &mut self.log
            && let Err(e) = log.sync()
        {
            self.failed(self.tick, e);
        }
    }

    fn halted(&self) -> bool {
        self.error.is_some() && self.stop_on_error.is_some()
    }

    /// Logs an event, if logging.
    pub fn event(&mut self, event: LogEvent) {
        let tick = event.tick;
        if let Some(log) = &mut self.log
            && let Err(e) = log.log_event(event)
        {
            self.failed(tick, e);
        }
    }

    fn failed(&mut self, tick: u64, e: LogError) {
        if self.error.is_none() {
            tracing::error!("logging failed at control step {tick}: {e}");
            self.error = Some((tick, e));
        }
        self.log = None;
        if let Some(stop) = &self.stop_on_error {
            stop.store(true, Ordering::Relaxed);
        }
    }
}

impl StepObserver for Recorder {
    fn after_step(&mut self, world: &World, state: &State, inputs: &Inputs, report: &StepReport) {
        self.tick = state.tick;
        if let Some(log) = &mut self.log
            && let Err(e) = log.log_step(world, state, inputs, report)
        {
            self.failed(state.tick, e);
        }
    }

    fn bus_input(&mut self, input: &BusInput) {
        if let Some(log) = &mut self.log
            && let Err(e) = log.log_bus_message(&input.key, true, &input.text, input.received_unix_ns)
        {
            self.failed(self.tick, e);
        }
    }

    fn input_rejected(&mut self, tick: u64, input: &BusInput, reason: &str) {
        self.bus_input(input);
        self.event(LogEvent {
            tick,
            kind: EventKind::InputRejected,
            copter: None,
            detail: Some(serde_json::json!({ "key": input.key, "reason": reason })),
            message: format!("rejected input on {}: {reason}", input.key),
        });
    }

    fn spawned(&mut self, world: &World, id: usize, tick: u64) {
        self.event(LogEvent {
            tick,
            kind: EventKind::Spawned,
            copter: Some(id),
            detail: None,
            message: format!("spawned copter {:?}", world.copters[id].name),
        });
    }

    fn pprz_out(&mut self, tick: u64, out: &PprzOut) {
        if let Some(log) = &mut self.log
            && let Err(e) = log.log_bus_message(&out.key, false, &out.text, crate::log::now_unix_ns())
        {
            self.failed(tick, e);
        }
    }

    fn paired(&mut self, tick: u64, ac_id: u8, id: usize, copter: &str) {
        self.event(LogEvent {
            tick,
            kind: EventKind::Paired,
            copter: Some(id),
            detail: Some(serde_json::json!({ "ac_id": ac_id, "copter": copter, "spawned": true })),
            message: format!("aircraft {ac_id} paired with its new twin {copter:?} (spawned on first telemetry)"),
        });
    }

    fn overrun(&mut self, tick: u64, late_s: f64) {
        self.event(LogEvent {
            tick,
            kind: EventKind::StepOverrun,
            copter: None,
            detail: Some(serde_json::json!({ "late_s": late_s })),
            message: format!("control step {tick} finished {:.1} ms after its deadline", late_s * 1e3),
        });
    }

    fn frame_dropped(&mut self, tick: u64, pprz_lost: u64) {
        self.event(LogEvent {
            tick,
            kind: EventKind::FrameDropped,
            copter: None,
            detail: Some(serde_json::json!({ "pprz_lost": pprz_lost })),
            message: format!("step {tick} not published (publisher behind); {pprz_lost} Paparazzi texts not sent"),
        });
    }

    fn failsafe(&mut self, tick: u64, world: &World, event: &FailsafeEvent) {
        self.event(LogEvent {
            tick,
            kind: EventKind::Failsafe,
            copter: Some(event.copter),
            detail: serde_json::to_value(&event.kind).ok(),
            message: event.message(world),
        });
    }

    fn lockstep_timeout(&mut self, tick: u64, world: &World, copter: usize, client: &str) {
        let name = &world.copters[copter].name;
        self.event(LogEvent {
            tick,
            kind: EventKind::LockstepTimeout,
            copter: Some(copter),
            detail: Some(serde_json::json!({ "copter": name, "client": client })),
            message: format!(
                "lockstep: {client:?} did not answer tick {tick} for {name:?} in time; it keeps its last command"
            ),
        });
    }
}
