//! [`Logger`]: the MCAP file of a run, written by a writer thread.

use std::collections::BTreeMap;
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::thread::JoinHandle;

use mcap::Attachment;
use mcap::records::{MessageHeader, Metadata};
use sim_core::{Inputs, State, StepReport, World};

use super::capture::StepFrame;
use super::encode::{Encoder, LogEvent, Topic, schema_data};
use super::mcap_out::McapOut;
use super::pprz::PprzChannels;
use super::time::{format_utc_iso, now_unix_ns, thread_cpu_ns};
use crate::live::{LiveChannel, LiveServer};

/// Why logging failed.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    /// The file could not be created.
    #[error("cannot create log file {path}")]
    Create {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// Writing MCAP failed (disk full, I/O error).
    #[error("cannot write log file {path}")]
    Write {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The writer thread ended early (it panicked).
    #[error("the log writer thread for {path} stopped unexpectedly")]
    WriterGone {
        /// The file.
        path: PathBuf,
    },
}

/// Who made the run: goes into the `twinswarm` metadata record.
#[derive(Clone, Debug, Default)]
pub struct LogMeta {
    /// The command line, as typed (arguments joined with spaces).
    pub command_line: String,
    /// Where the scene came from (a path, or `<embedded finken_lab.toml>`).
    pub scene_origin: String,
    /// Unix time of tick 0, ns; `None`: now.
    pub epoch_ns: Option<u64>,
}

/// Tuning of the writer.
#[derive(Clone, Debug)]
pub struct LogOptions {
    /// Finish the chunk and flush the file every this many simulated seconds (default 1).
    pub flush_interval_s: f64,
    /// zstd level of every chunk (default 3, zstd's own default). Fixed: a writer that falls
    /// behind holds the stepping thread back rather than compress worse.
    pub zstd_level: u32,
    /// Per-step messages (state, sensors, command, control, transforms, the copters' view) are
    /// written on every this many control steps (default 1: every step); events, log lines
    /// and bus traffic always. See [`LogOptions::every_ticks_for_rate`].
    pub every_ticks: u64,
    /// A chunk is finished once it holds this many bytes of records (default 8 MiB), or at
    /// the flush interval. Big chunks let zstd find a copter's previous step.
    pub chunk_size: usize,
    /// A copter whose logged values did not change since it was last written (a wreck at
    /// rest: its pose, rotors, readings and command all stay as they were) is written again
    /// only every this many simulated seconds (default 1; the period in ticks is rounded up
    /// to a multiple of `every_ticks`, see [`LogOptions::unchanged_every_ticks`]), and on every
    /// step the live view gets. A reader holds a copter's last message until its next. 0 writes
    /// every copter on every logged step.
    pub unchanged_every_s: f64,
    /// Steps that may wait for the writer thread before `log_step` blocks (default 4).
    pub queue_steps: usize,
    /// A live view that gets every message too, as it is encoded for the file (the channels
    /// are added to it when the logger starts; `/bus` on first use).
    pub live: Option<Arc<LiveServer>>,
    /// The live view gets a step's messages at most this often per second of wall-clock time
    /// (default 30: about a display's rate; a `--realtime` run at 20 Hz sends every step).
    /// A run faster than real time is sampled; the file still gets every step.
    pub live_max_hz: f64,
}

impl Default for LogOptions {
    fn default() -> Self {
        Self {
            flush_interval_s: 1.0,
            zstd_level: 3,
            every_ticks: 1,
            chunk_size: 8 << 20,
            unchanged_every_s: 1.0,
            queue_steps: 4,
            live: None,
            live_max_hz: 30.0,
        }
    }
}

/// What was written.
#[derive(Clone, Debug, Default)]
pub struct LogStats {
    /// The file.
    pub path: PathBuf,
    /// Messages written, per topic (in [`Topic::ALL`] order).
    pub messages: [u64; Topic::ALL.len()],
    /// Last tick logged.
    pub last_tick: u64,
    /// Copter samples (five messages each) not written because they had not changed; see
    /// [`LogOptions::unchanged_every_s`].
    pub held_samples: u64,
    /// Paparazzi messages on `/pprz/…` channels (each also on `/bus`).
    pub pprz_messages: u64,
    /// CPU time of the writer thread (encoding, compression, I/O), s; `None` where the
    /// platform does not tell.
    pub writer_cpu_s: Option<f64>,
}

impl LogOptions {
    /// The [`LogOptions::every_ticks`] that logs steps at `rate_hz` (at most the control
    /// rate; the nearest whole number of steps). `None` if `rate_hz` is not a positive
    /// number.
    pub fn every_ticks_for_rate(rate_hz: f64, control_dt_s: f64) -> Option<u64> {
        (rate_hz.is_finite() && rate_hz > 0.0).then(|| ((1.0 / (rate_hz * control_dt_s)).round() as u64).max(1))
    }

    /// The period, in ticks, on which unchanged copters are written again: a whole multiple
    /// of [`LogOptions::every_ticks`], so that it falls on logged steps; 1 for every step.
    pub fn unchanged_every_ticks(&self, control_dt_s: f64) -> u64 {
        let every = self.every_ticks.max(1);
        let s = self.unchanged_every_s;
        if !(s.is_finite() && s > 0.0) {
            return 1;
        }
        let steps = (s / control_dt_s).round().max(1.0) as u64;
        steps.div_ceil(every).saturating_mul(every)
    }
}

impl LogStats {
    /// All messages.
    pub fn total_messages(&self) -> u64 {
        self.messages.iter().sum()
    }
}

enum Job {
    Step(Box<StepFrame>),
    Event(LogEvent),
    /// Bus messages of one step, in arrival order.
    Bus(Vec<BusJob>),
    Flush,
    /// Flush, `fsync`, and say so: everything logged before is on disk.
    Sync(std::sync::mpsc::SyncSender<std::io::Result<()>>),
}

/// One bus message to log.
#[derive(Debug)]
struct BusJob {
    tick: u64,
    key: String,
    direction: &'static str,
    text: String,
    received_ns: u64,
}

/// Bus messages go to the writer in batches of at most this many (and at each step, event or
/// flush): one job per message would hand the loop thread to the writer thread at every
/// message of a flood (the job queue holds a few steps), and miss real-time deadlines.
const BUS_BATCH: usize = 1024;

/// The MCAP log of one run.
///
/// ```no_run
/// # fn main() -> Result<(), bridge::log::LogError> {
/// let (_, world) = sim_core::scene::load_default();
/// let mut state = world.initial_state();
/// let inputs = world.initial_inputs();
/// let meta = bridge::log::LogMeta::default();
/// let mut log = bridge::log::Logger::create("run.mcap".as_ref(), &world, sim_core::scene::DEFAULT_SCENE_TOML, meta)?;
/// for _ in 0..100 {
///     let report = sim_core::step(&world, &mut state, &inputs);
///     log.log_step(&world, &state, &inputs, &report)?;
/// }
/// log.finish()?;
/// # Ok(()) }
/// ```
#[derive(Debug)]
pub struct Logger {
    path: PathBuf,
    /// The live view's sampling without a file ([`Logger::live_step_due`]).
    live_last: Option<std::time::Instant>,
    live_every: std::time::Duration,
    /// Whether there is a file (else the messages go to the live view only).
    has_file: bool,
    live: Option<Arc<LiveServer>>,
    jobs: Option<SyncSender<Job>>,
    free: Receiver<Box<StepFrame>>,
    thread: Option<JoinHandle<Result<LogStats, LogError>>>,
    /// Steps sent to the writer thread and not yet encoded by it.
    pending: Arc<AtomicUsize>,
    /// Bus messages not yet handed to the writer (see [`BUS_BATCH`]).
    bus: Vec<BusJob>,
    last_tick: u64,
    epoch_ns: u64,
    dt_ns: u64,
    every_ticks: u64,
}

impl Logger {
    /// Creates the file and writes the header, the scene attachments, the `twinswarm`
    /// metadata, every schema and channel and the static scene, flushed; then starts the
    /// writer thread.
    pub fn create(path: &Path, world: &World, scene_text: &str, meta: LogMeta) -> Result<Self, LogError> {
        Self::with_options(path, world, scene_text, meta, LogOptions::default())
    }

    /// [`Logger::create`] with options.
    pub fn with_options(
        path: &Path,
        world: &World,
        scene_text: &str,
        meta: LogMeta,
        options: LogOptions,
    ) -> Result<Self, LogError> {
        Self::start(Some(path), world, scene_text, meta, options)
    }

    /// A logger without a file: the messages go to the live view only, and only while a
    /// client subscribes to something (else [`Logger::log_step`] does nothing).
    pub fn live_only(world: &World, live: Arc<LiveServer>, options: LogOptions) -> Result<Self, LogError> {
        let options = LogOptions { live: Some(live), ..options };
        Self::start(None, world, "", LogMeta::default(), options)
    }

    fn start(
        file_path: Option<&Path>,
        world: &World,
        scene_text: &str,
        meta: LogMeta,
        options: LogOptions,
    ) -> Result<Self, LogError> {
        let path = file_path.map_or_else(|| PathBuf::from("<live view>"), Path::to_owned);
        let werr = |source| LogError::Write { path: path.clone(), source };
        let epoch_ns = meta.epoch_ns.unwrap_or_else(now_unix_ns);
        let mut encoder = Encoder::new(world, epoch_ns);
        let unchanged_every = options.unchanged_every_ticks(world.params.control_dt_s);
        encoder.set_unchanged_every(unchanged_every);
        let (out, channels) = match file_path {
            None => (None, [0u16; Topic::ALL.len()]),
            Some(p) => {
                let file = File::create(p).map_err(|source| LogError::Create { path: path.clone(), source })?;
                let mut out = McapOut::create(file, options.zstd_level, options.chunk_size).map_err(werr)?;
                attach_scene(&mut out, world, scene_text, epoch_ns).map_err(werr)?;
                let sampling =
                    Sampling { every_ticks: options.every_ticks.max(1), unchanged_every_ticks: unchanged_every };
                out.write_metadata(&metadata_record(world, &meta, epoch_ns, encoder.control_dt_ns(), sampling))
                    .map_err(werr)?;
                let channels = add_file_channels(&mut out).map_err(werr)?;
                (Some(out), channels)
            }
        };
        let live = options.live.clone().map(live_out);
        let live_every = std::time::Duration::from_secs_f64(1.0 / options.live_max_hz.max(1e-3));
        let mut state = WriterState {
            out,
            channels,
            live,
            live_due: true,
            sequences: [0; Topic::ALL.len()],
            stats: LogStats { path: path.clone(), ..LogStats::default() },
            publish_override: None,
            pprz: PprzChannels::new(),
        };
        let dt_ns = encoder.control_dt_ns();
        encoder.encode_arena(world, &mut |topic, lt, data: &[u8]| state.write(topic, lt, data)).map_err(werr)?;
        state.flush().map_err(werr)?;

        let flush_every = ((options.flush_interval_s / world.params.control_dt_s).round() as u64).max(1);
        let (jobs, rx) = sync_channel::<Job>(options.queue_steps.max(1));
        let (free_tx, free) = sync_channel::<Box<StepFrame>>(options.queue_steps.max(1) + 2);
        let pending = Arc::new(AtomicUsize::new(0));
        let writer = WriterThread {
            state,
            encoder,
            free_tx,
            backlog: Arc::clone(&pending),
            path: path.clone(),
            live_every,
            flush_every,
            since_flush: 0,
            epoch_ns,
            dt_ns,
        };
        let thread = std::thread::Builder::new()
            .name("mcap-writer".into())
            .spawn(move || writer.run(rx))
            .map_err(|source| LogError::Create { path: path.clone(), source })?;
        Ok(Self {
            live_last: None,
            live_every,
            has_file: file_path.is_some(),
            live: options.live,
            path,
            jobs: Some(jobs),
            free,
            thread: Some(thread),
            pending,
            bus: Vec::new(),
            last_tick: 0,
            epoch_ns,
            dt_ns: (world.params.control_dt_s * 1e9).round() as u64,
            every_ticks: options.every_ticks.max(1),
        })
    }

    /// The file (`<live view>` without one).
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether it writes a file (else it feeds a live view only).
    pub fn has_file(&self) -> bool {
        self.has_file
    }

    /// Whether messages are wanted now: always with a file, else while a live client
    /// subscribes to something.
    #[inline]
    fn wanted(&self) -> bool {
        self.has_file || self.live.as_ref().is_some_and(|l| l.active())
    }

    /// Without a file: whether this step is due for the live view ([`LogOptions::live_max_hz`]
    /// of wall-clock time), so that a run faster than real time is sampled on the stepping
    /// thread before anything is copied.
    fn live_step_due(&mut self) -> bool {
        let now = std::time::Instant::now();
        if self.live_last.is_some_and(|t| now.duration_since(t) < self.live_every) {
            return false;
        }
        self.live_last = Some(now);
        true
    }

    /// Unix time of tick 0, ns.
    pub fn epoch_ns(&self) -> u64 {
        self.epoch_ns
    }

    /// Log time of a tick, ns.
    pub fn log_time(&self, tick: u64) -> u64 {
        self.epoch_ns + tick * self.dt_ns
    }

    /// Logs a step just taken: per copter its state, sensors, command, controller outputs and
    /// transform, the copters' 3D view, and the step's events. Cheap: copies numbers into a
    /// reused frame and queues it; blocks only if the writer thread is several steps behind.
    pub fn log_step(
        &mut self,
        world: &World,
        state: &State,
        inputs: &Inputs,
        report: &StepReport,
    ) -> Result<(), LogError> {
        self.last_tick = state.tick;
        if !state.tick.is_multiple_of(self.every_ticks) {
            // Not a logged step; its events still go out.
            return report.events.iter().try_for_each(|e| self.log_event(LogEvent::from_step(world, state.tick, e)));
        }
        if !self.wanted() || (!self.has_file && !self.live_step_due()) {
            return Ok(());
        }
        // A frame the writer has finished with, or a new one while the pool fills.
        let mut frame = self.free.try_recv().unwrap_or_default();
        frame.capture(world, state, inputs, report);
        self.pending.fetch_add(1, Ordering::Relaxed);
        if self.has_file {
            return self.send(Job::Step(frame));
        }
        // The live view alone is lossy: a step the encoder has no room for is skipped (and
        // counted) rather than waited for.
        self.send_bus_batch()?;
        let Some(jobs) = &self.jobs else { return Err(LogError::WriterGone { path: self.path.clone() }) };
        match jobs.try_send(Job::Step(frame)) {
            Ok(()) => Ok(()),
            Err(std::sync::mpsc::TrySendError::Full(_)) => {
                self.pending.fetch_sub(1, Ordering::Relaxed);
                if let Some(live) = &self.live {
                    live.count_skipped_step();
                }
                Ok(())
            }
            Err(std::sync::mpsc::TrySendError::Disconnected(job)) => self.send_job(job),
        }
    }

    /// Logs an event (spawn, pairing, rejected input, step overrun, interruption) on
    /// `/events` and `/log`.
    pub fn log_event(&mut self, event: LogEvent) -> Result<(), LogError> {
        if !self.wanted() {
            return Ok(());
        }
        self.send(Job::Event(event))
    }

    /// Logs a bus message on `/bus`: `log_time` is the simulated time of the last logged step,
    /// `publish_time` the wall-clock receive time (Unix ns).
    pub fn log_bus_message(
        &mut self,
        key: &str,
        incoming: bool,
        text: &str,
        received_unix_ns: u64,
    ) -> Result<(), LogError> {
        if self.jobs.is_none() {
            return Err(LogError::WriterGone { path: self.path.clone() });
        }
        if !self.wanted() {
            return Ok(());
        }
        self.bus.push(BusJob {
            tick: self.last_tick,
            key: key.to_owned(),
            direction: if incoming { "in" } else { "out" },
            text: text.to_owned(),
            received_ns: received_unix_ns,
        });
        if self.bus.len() >= BUS_BATCH { self.send_bus_batch() } else { Ok(()) }
    }

    /// Finishes the current chunk and flushes the file now.
    pub fn flush(&mut self) -> Result<(), LogError> {
        self.send(Job::Flush)
    }

    /// Writes everything logged so far to the file and `fsync`s it, and waits for that: a
    /// checkpoint taken after this has its log on disk up to the same step.
    pub fn sync(&mut self) -> Result<(), LogError> {
        if !self.has_file {
            return Ok(());
        }
        let (done, wait) = std::sync::mpsc::sync_channel(1);
        self.send(Job::Sync(done))?;
        match wait.recv() {
            Ok(Ok(())) => Ok(()),
            Ok(Err(source)) => Err(LogError::Write { path: self.path.clone(), source }),
            // The writer stopped before it got there: its error says why.
            Err(_) => {
                self.jobs = None;
                Err(self.join().err().unwrap_or(LogError::WriterGone { path: self.path.clone() }))
            }
        }
    }

    /// Hands the bus messages waiting for a batch to the writer.
    fn send_bus_batch(&mut self) -> Result<(), LogError> {
        if self.bus.is_empty() {
            return Ok(());
        }
        let room = BUS_BATCH.min(self.bus.len() * 2);
        let batch = std::mem::replace(&mut self.bus, Vec::with_capacity(room));
        self.send_job(Job::Bus(batch))
    }

    /// Sends `job`, after the bus messages waiting for a batch (so that the file keeps their
    /// order with steps and events).
    fn send(&mut self, job: Job) -> Result<(), LogError> {
        self.send_bus_batch()?;
        self.send_job(job)
    }

    fn send_job(&mut self, job: Job) -> Result<(), LogError> {
        let Some(jobs) = &self.jobs else { return Err(LogError::WriterGone { path: self.path.clone() }) };
        if jobs.send(job).is_ok() {
            return Ok(());
        }
        // The writer thread has stopped: report why.
        self.jobs = None;
        match self.join() {
            Err(e) => Err(e),
            Ok(_) => Err(LogError::WriterGone { path: self.path.clone() }),
        }
    }

    fn join(&mut self) -> Result<LogStats, LogError> {
        match self.thread.take() {
            Some(t) => t.join().unwrap_or_else(|_| Err(LogError::WriterGone { path: self.path.clone() })),
            None => Err(LogError::WriterGone { path: self.path.clone() }),
        }
    }

    /// Writes everything queued, the summary section and the footer; closes the file.
    pub fn finish(mut self) -> Result<LogStats, LogError> {
        self.send_bus_batch()?;
        self.jobs = None;
        self.join()
    }
}

impl Drop for Logger {
    fn drop(&mut self) {
        // Finish the file even when the run ends with an error; the error of `finish` was
        // returned to whoever called it. Bus messages still batched go first (if the writer
        // is gone, its error was reported by the call that found it gone).
        let _ = self.send_bus_batch();
        self.jobs = None;
        if let Some(t) = self.thread.take() {
            // A panicked writer thread already reported itself through the panic hook.
            let _ = t.join();
        }
    }
}

struct WriterState {
    out: Option<McapOut>,
    channels: [u16; Topic::ALL.len()],
    live: Option<LiveOut>,
    /// Whether a step's messages go to the live view too (a step not sampled for it does
    /// not; events, log lines, the static scene and bus messages always do).
    live_due: bool,
    sequences: [u32; Topic::ALL.len()],
    stats: LogStats,
    publish_override: Option<u64>,
    pprz: PprzChannels,
}

/// The live view's side of the writer: the server and its channel id per topic.
struct LiveOut {
    server: Arc<LiveServer>,
    channels: [u32; Topic::ALL.len()],
    /// When the view last got a step.
    last: Option<std::time::Instant>,
}

impl WriterState {
    fn write(&mut self, topic: Topic, log_time: u64, data: &[u8]) -> std::io::Result<()> {
        let i = topic.index();
        let seq = self.sequences[i];
        self.sequences[i] = seq.wrapping_add(1);
        self.stats.messages[i] += 1;
        if let Some(live) = &self.live
            && (self.live_due || matches!(topic, Topic::Events | Topic::Log | Topic::SceneArena | Topic::Bus))
        {
            live.server.publish(live.channels[i], log_time, data);
        }
        let Some(out) = &mut self.out else { return Ok(()) };
        let header = MessageHeader {
            channel_id: self.channels[i],
            sequence: seq,
            log_time,
            publish_time: self.publish_override.unwrap_or(log_time),
        };
        out.write_to_known_channel(&header, data)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.out.as_mut().map_or(Ok(()), McapOut::flush)
    }

    /// `/bus`, in the file and the live view, on first use.
    fn add_bus_channel(&mut self) -> std::io::Result<()> {
        let i = Topic::Bus.index();
        if let Some(live) = &mut self.live
            && live.channels[i] == 0
        {
            live.channels[i] = live.server.add_channel(live_channel(Topic::Bus));
        }
        if let Some(out) = &mut self.out
            && self.channels[i] == 0
        {
            self.channels[i] = add_channel(out, Topic::Bus)?;
        }
        Ok(())
    }
}

/// Attaches the scene to the file: as given (`scene.toml`) and as compiled
/// (`scene.effective.toml`).
fn attach_scene(out: &mut McapOut, world: &World, scene_text: &str, epoch_ns: u64) -> std::io::Result<()> {
    let now = now_unix_ns();
    for (name, text) in [("scene.toml", scene_text.to_owned()), ("scene.effective.toml", world.spec.to_toml())] {
        out.attach(&Attachment {
            log_time: epoch_ns,
            create_time: now,
            name: name.into(),
            media_type: "application/toml".into(),
            data: text.into_bytes().into(),
        })?;
    }
    Ok(())
}

/// Adds every topic's schema and channel to the file but `/bus` (added on first use); the
/// channel ids by topic.
fn add_file_channels(out: &mut McapOut) -> std::io::Result<[u16; Topic::ALL.len()]> {
    let mut channels = [0u16; Topic::ALL.len()];
    for topic in Topic::ALL {
        if topic == Topic::Bus {
            continue; // added on first use
        }
        channels[topic.index()] = add_channel(out, topic)?;
    }
    Ok(channels)
}

/// The live view's side of the writer on `server`: every topic's channel but `/bus` (added on
/// first use).
fn live_out(server: Arc<LiveServer>) -> LiveOut {
    let mut ids = [0u32; Topic::ALL.len()];
    for topic in Topic::ALL {
        if topic != Topic::Bus {
            ids[topic.index()] = server.add_channel(live_channel(topic));
        }
    }
    LiveOut { server, channels: ids, last: None }
}

/// The writer thread: encodes the jobs into the file and the live view, in order.
struct WriterThread {
    state: WriterState,
    encoder: Encoder,
    /// Encoded frames go back to the logger for reuse.
    free_tx: SyncSender<Box<StepFrame>>,
    /// The logger's count of steps not yet encoded.
    backlog: Arc<AtomicUsize>,
    path: PathBuf,
    live_every: std::time::Duration,
    flush_every: u64,
    since_flush: u64,
    epoch_ns: u64,
    dt_ns: u64,
}

impl WriterThread {
    /// Encodes every job until the logger hangs up, then finishes the file; the statistics.
    fn run(mut self, rx: Receiver<Job>) -> Result<LogStats, LogError> {
        let path = self.path.clone();
        let werr = |source| LogError::Write { path: path.clone(), source };
        let cpu0 = thread_cpu_ns();
        for job in rx {
            match job {
                Job::Step(frame) => self.write_step(frame).map_err(werr)?,
                Job::Event(ev) => {
                    let state = &mut self.state;
                    self.encoder.encode_event(&ev, &mut |t, lt, d: &[u8]| state.write(t, lt, d)).map_err(werr)?
                }
                Job::Bus(batch) => self.write_bus(batch).map_err(werr)?,
                Job::Flush => self.state.flush().map_err(werr)?,
                Job::Sync(done) => self.sync(done).map_err(werr)?,
            }
        }
        if let Some(out) = &mut self.state.out {
            out.finish().map_err(werr)?;
        }
        if let (Some(a), Some(b)) = (cpu0, thread_cpu_ns()) {
            self.state.stats.writer_cpu_s = Some(b.saturating_sub(a) as f64 * 1e-9);
        }
        Ok(self.state.stats.clone())
    }

    /// Encodes one step (whole, when the live view is due for one), hands its frame back for
    /// reuse, and flushes every `flush_every` steps.
    fn write_step(&mut self, frame: Box<StepFrame>) -> std::io::Result<()> {
        let state = &mut self.state;
        let now = std::time::Instant::now();
        // Without a file the stepping thread has sampled already.
        let live_only = state.out.is_none();
        state.live_due = state.live.as_ref().is_some_and(|l| {
            l.server.active() && (live_only || l.last.is_none_or(|t| now.duration_since(t) >= self.live_every))
        });
        // The step's time first: a client stamps the step's messages with it.
        if let Some(live) = &mut state.live
            && state.live_due
        {
            live.last = Some(now);
            live.server.broadcast_time(self.encoder.log_time(frame.tick));
        }
        // A live step is whole: a client sees each copter at its rate.
        let full = state.live_due;
        self.encoder.encode_step(&frame, full, &mut |t, lt, d: &[u8]| state.write(t, lt, d))?;
        state.stats.held_samples = self.encoder.held();
        state.live_due = true;
        self.backlog.fetch_sub(1, Ordering::Relaxed);
        state.stats.last_tick = frame.tick;
        // Recycling only: with the pool full (or the Logger gone) the frame
        // is freed and `log_step` allocates a new one.
        let _ = self.free_tx.try_send(frame);
        self.since_flush += 1;
        if self.since_flush >= self.flush_every {
            state.flush()?;
            self.since_flush = 0;
        }
        Ok(())
    }

    /// Encodes a batch of bus messages, each also as a Paparazzi text in the file.
    fn write_bus(&mut self, batch: Vec<BusJob>) -> std::io::Result<()> {
        let state = &mut self.state;
        state.add_bus_channel()?;
        for BusJob { tick, key, direction, text, received_ns } in batch {
            state.publish_override = Some(received_ns);
            let r = self.encoder.encode_bus(tick, &key, direction, &text, &mut |t, lt, d: &[u8]| state.write(t, lt, d));
            state.publish_override = None;
            r?;
            let log_time = self.epoch_ns + tick * self.dt_ns;
            if let Some(out) = &mut state.out {
                state.pprz.write(out, tick, log_time, received_ns, &key, direction, &text)?;
            }
        }
        state.stats.pprz_messages = state.pprz.written;
        Ok(())
    }

    /// Flushes and `fsync`s the file and tells `done` how that went; a failure also ends the
    /// writer.
    fn sync(&mut self, done: SyncSender<std::io::Result<()>>) -> std::io::Result<()> {
        let r = self.state.out.as_mut().map_or(Ok(()), McapOut::sync);
        let failed = r.as_ref().err().map(|e| std::io::Error::new(e.kind(), e.to_string()));
        // The caller may be gone (its run ended); the error is returned below too.
        let _ = done.send(r);
        if let Some(e) = failed {
            return Err(e);
        }
        Ok(())
    }
}

/// A topic's channel in the live view: the log's encoding and schema; the static scene is
/// latched (each new subscriber gets it).
fn live_channel(topic: Topic) -> LiveChannel {
    let schema = schema_data(topic.schema()).unwrap_or_default();
    let channel = LiveChannel::from_schema_bytes(topic.name(), "protobuf", topic.schema(), "protobuf", &schema);
    LiveChannel { latched: topic == Topic::SceneArena, ..channel }
}

fn add_channel(out: &mut McapOut, topic: Topic) -> std::io::Result<u16> {
    let schema = schema_data(topic.schema()).unwrap_or_default();
    let schema_id = out.add_schema(topic.schema(), "protobuf", &schema)?;
    out.add_channel(schema_id, topic.name(), "protobuf", &BTreeMap::new())
}

/// How often the per-step messages were written, for the metadata record.
#[derive(Clone, Copy, Debug)]
struct Sampling {
    every_ticks: u64,
    unchanged_every_ticks: u64,
}

fn metadata_record(world: &World, meta: &LogMeta, epoch_ns: u64, dt_ns: u64, sampling: Sampling) -> Metadata {
    let copters: Vec<serde_json::Value> = world
        .copters
        .iter()
        .enumerate()
        .map(|(id, c)| {
            serde_json::json!({
                "id": id,
                "name": c.name,
                "kind": c.kind,
                "ac_id": c.ac_id,
                "mass_kg": world.airframes[c.airframe].mass_kg,
                "start_pos_m": [c.start_pos_m.x, c.start_pos_m.y, c.start_pos_m.z],
            })
        })
        .collect();
    let boxes: Vec<serde_json::Value> = world
        .boxes
        .iter()
        .map(|b| {
            serde_json::json!({
                "name": b.name,
                "center_m": [b.center_m.x, b.center_m.y, b.center_m.z],
                "size_m": [2.0 * b.half_extents_m.x, 2.0 * b.half_extents_m.y, 2.0 * b.half_extents_m.z],
                "yaw_rad": b.yaw_rad,
            })
        })
        .collect();
    let mut m = BTreeMap::new();
    let mut put = |k: &str, v: String| {
        m.insert(k.to_owned(), v);
    };
    put("version", env!("CARGO_PKG_VERSION").to_owned());
    put("seed", world.params.seed.to_string());
    put("command_line", meta.command_line.clone());
    put("scene_origin", meta.scene_origin.clone());
    put("world", world.name.clone());
    put("copters", serde_json::Value::Array(copters).to_string());
    put("boxes", serde_json::Value::Array(boxes).to_string());
    put("arena_size_m", serde_json::json!(world.arena.size_m).to_string());
    put("arena_height_m", world.arena.height_m.to_string());
    put("control_dt_s", world.params.control_dt_s.to_string());
    put("physics_dt_s", world.params.physics_dt_s.to_string());
    put("log_every_ticks", sampling.every_ticks.to_string());
    put("unchanged_every_ticks", sampling.unchanged_every_ticks.to_string());
    put(
        "sampling",
        "per-copter messages on ticks that are multiples of log_every_ticks; a copter whose values had not changed \
         since its last message is left out except on multiples of unchanged_every_ticks (and on steps sent to a \
         live view): its last message holds until its next"
            .to_owned(),
    );
    put("epoch_unix_ns", epoch_ns.to_string());
    put("epoch_utc", format_utc_iso(epoch_ns));
    put(
        "time",
        format!(
            "log_time = epoch_unix_ns + tick * {dt_ns} ns (tick: control steps since the start; epoch: wall-clock UTC \
             at the start of the run); publish_time = log_time for simulator messages, the wall-clock receive time \
             for bus messages"
        ),
    );
    Metadata { name: "twinswarm".into(), metadata: m }
}

#[cfg(test)]
mod tests {
    use super::LogOptions;

    #[test]
    fn unchanged_copters_come_back_on_logged_steps() {
        let period = |every_ticks, unchanged_every_s| {
            LogOptions { every_ticks, unchanged_every_s, ..LogOptions::default() }.unchanged_every_ticks(0.05)
        };
        assert_eq!(period(1, 1.0), 20, "a second of 50 ms steps");
        assert_eq!(period(3, 1.0), 21, "the first logged step at or after the second");
        assert_eq!(period(40, 1.0), 40, "slower logging than the period: every logged step");
        assert_eq!(period(1, 0.0), 1, "0: every copter on every step");
        assert_eq!(period(4, 0.0), 1);
        assert_eq!(period(1, 0.01), 1, "less than a step: every step");
        assert_eq!(period(1, f64::NAN), 1);
        assert_eq!(period(2, 1e30), u64::MAX, "absurdly long: never again, no overflow");
    }
}
