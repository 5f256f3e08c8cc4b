//! `twinswarm replay FILE`: republishes a run log's bus traffic onto Zenoh with its original
//! timing, so ground tools can watch a flight again. A Paparazzi log (`NAME.data`) goes to
//! [`crate::replay_pprz`] instead.
//!
//! What goes out, under the prefix (default: a `prefix` entry of the log's `twinswarm` metadata,
//! else `--prefix` from the recorded command line, else `twinswarm/<world>`; `--prefix`
//! overrides):
//!
//! - `…/clock` ([`ClockMsg`]) once per logged control step, before that step's states;
//! - `…/copters/<name>/state` ([`StateMsg`]) from `/copters/state`, every step. Every field of
//!   the live message is in the log (`copter` → `name`, `t_s` → `time_s`, `rpy_rad` →
//!   `attitude_rad`, kind `real` → `twin`); nothing is invented. A copter the log held on a
//!   step (unchanged since its last message, e.g. a wreck at rest) gets its last state again
//!   with that step's tick and time, as the live simulator sends every copter every step;
//! - `…/copters/<name>/sensors` ([`SensorsMsg`]) from `/copters/sensors`, only on steps whose
//!   sonar reading is fresh (its `sonar_tick` changed), i.e. at the sonar rate like the live
//!   simulator (the log holds the held reading every step);
//! - every `/bus` message (raw text) on its original key; keys under the recorded prefix are
//!   moved under the replay prefix, others go out unchanged. These are the inputs the simulator
//!   received (e.g. `…/copters/<name>/cmd`): a live simulator on the same prefix obeys them.
//!
//! Timing: a step logged at `log_time` goes out at `start + (log_time − t0) / speed` (absolute
//! deadlines, no drift). Messages come in file order, which is `log_time` order for logs written
//! by `twinswarm run` (and `log recover`); a message earlier than its predecessor goes out at
//! once. `--wait-for-subscriber S` waits (up to S s) until some subscriber matches the clock,
//! state or sensors keys before sending, so a tool started alongside sees the first step.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use bridge::log::proto::{self, LogRecord};
use bridge::log::{LogFile, LogReadError};
use bridge::wire::{ClockMsg, SensorsMsg, SonarMsg, StateMsg};
use zenoh::Wait;
use zenoh::qos::CongestionControl;

use crate::BadInput;
use crate::logcmd::read_error;
use crate::transport::{self, IvyArgs, ZenohArgs, ZenohRole};

/// `twinswarm replay` arguments.
#[derive(Debug, clap::Args)]
#[command(mut_arg("prefix", |a| a.help("Key-expression prefix (default: the one recorded in the log, else twinswarm/<world>)")))]
#[command(mut_arg("ivy", |a| a.help(transport::ivy_help("A Paparazzi log: also play it onto a Paparazzi Ivy bus"))))]
pub struct ReplayArgs {
    /// The MCAP log of a run.
    pub file: PathBuf,
    /// Playback speed: 2 plays twice as fast, 0.5 half as fast (> 0).
    #[arg(long, value_name = "X", default_value_t = 1.0, allow_negative_numbers = true)]
    pub speed: f64,
    /// `--zenoh-config`, `--listen`, `--connect`, `--prefix`.
    #[command(flatten)]
    pub zenoh: ZenohArgs,
    /// Before sending, wait up to S seconds for a subscriber to the clock, state or sensors
    /// keys (then start anyway).
    #[arg(long, value_name = "S")]
    pub wait_for_subscriber: Option<f64>,
    /// Wait this long after opening the session (and after any subscriber wait) before sending.
    #[arg(long, value_name = "MS", default_value_t = 0)]
    pub start_delay_ms: u64,
    /// Also serve the log on the Foxglove WebSocket protocol at ADDR (default
    /// 127.0.0.1:8765): every channel, with the file's schemas, at the log's pace (`--speed`).
    /// With `--wait-for-subscriber`, waits for a live subscription too.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = bridge::live::DEFAULT_ADDR)]
    pub foxglove: Option<String>,
    /// Do not republish on Zenoh (with `--foxglove`: the live view only; a Paparazzi log:
    /// on Ivy only).
    #[arg(long)]
    pub no_bus: bool,
    /// `--ivy`, `--ivy-bus`: a Paparazzi log only.
    #[command(flatten)]
    pub ivy: IvyArgs,
    /// A Paparazzi log: start at this log time, s.
    #[arg(long, value_name = "S", allow_negative_numbers = true)]
    pub from: Option<f64>,
    /// A Paparazzi log: stop after this log time, s.
    #[arg(long, value_name = "S", allow_negative_numbers = true)]
    pub to: Option<f64>,
    /// A Paparazzi log: only this aircraft's messages.
    #[arg(long, value_name = "AC_ID")]
    pub ac_id: Option<u8>,
}

/// The live state message of a logged `twinswarm.CopterState` (either encoding).
fn state_msg(s: proto::CopterState) -> Result<StateMsg, String> {
    Ok(StateMsg {
        kind: if s.kind == "real" { "twin".into() } else { s.kind },
        ac_id: s.ac_id.and_then(|a| u8::try_from(a).ok()),
        tick: s.tick,
        time_s: s.t_s,
        mode: s.mode,
        pos_m: proto::fixed("pos_m", &s.pos_m)?,
        vel_m_s: proto::fixed("vel_m_s", &s.vel_m_s)?,
        attitude_rad: proto::fixed("rpy_rad", &s.rpy_rad)?,
        angvel_rad_s: proto::fixed("angvel_rad_s", &s.angvel_rad_s)?,
        quat_xyzw: proto::fixed("quat_xyzw", &s.quat_xyzw)?,
        rotor_thrust_n: proto::fixed("rotor_thrust_n", &s.rotor_thrust_n)?,
        crashed: s.crashed,
        name: s.copter,
    })
}

/// The live sensors message of a logged `twinswarm.CopterSensors` (either encoding; logs
/// written before the estimators and the battery have zeros there).
fn sensors_msg(s: proto::CopterSensors) -> Result<SensorsMsg, String> {
    Ok(SensorsMsg {
        tick: s.tick,
        time_s: s.t_s,
        sonar_m: SonarMsg::from(proto::fixed::<4>("sonar_m", &s.sonar_m)?),
        sonar_fused_m: SonarMsg::from(proto::fixed::<4>("sonar_fused_m", &s.sonar_fused_m)?),
        ir_m: s.ir_m,
        attitude_rad: proto::fixed("attitude_rad", &s.attitude_rad)?,
        rate_body_rad_s: proto::fixed("rate_body_rad_s", &s.rate_body_rad_s)?,
        accel_body_m_s2: proto::fixed("accel_body_m_s2", &s.accel_body_m_s2)?,
        height_est_m: s.height_est_m,
        battery_v: s.battery_v,
        battery_charge: s.battery_charge,
        name: s.copter,
    })
}

/// Messages republished, per key class.
#[derive(Debug, Default, Clone, Copy)]
struct Counts {
    clock: u64,
    state: u64,
    sensors: u64,
    bus: u64,
    /// Bus messages whose key is not a valid key expression.
    skipped: u64,
}

/// The prefix the run published under, as far as the log tells.
fn recorded_prefix(meta: Option<&std::collections::BTreeMap<String, String>>) -> Option<String> {
    let meta = meta?;
    if let Some(p) = meta.get("prefix").filter(|p| !p.is_empty()) {
        return Some(p.clone());
    }
    let words: Vec<&str> = meta.get("command_line").map(|c| c.split_whitespace().collect()).unwrap_or_default();
    for (i, w) in words.iter().enumerate() {
        if let Some(p) = w.strip_prefix("--prefix=") {
            return Some(p.to_owned());
        }
        if *w == "--prefix"
            && let Some(p) = words.get(i + 1)
        {
            return Some((*p).to_owned());
        }
    }
    meta.get("world").map(|w| format!("twinswarm/{w}"))
}

/// Sleeps until `deadline`; false if `stop` is set meanwhile.
pub(crate) fn wait_until(stop: &AtomicBool, deadline: Instant) -> bool {
    loop {
        if stop.load(Ordering::Relaxed) {
            return false;
        }
        let now = Instant::now();
        if now >= deadline {
            return true;
        }
        std::thread::sleep((deadline - now).min(Duration::from_millis(100)));
    }
}

/// Moves a logged bus key from the recorded prefix to the replay prefix.
fn rekey(key: &str, recorded: Option<&str>, prefix: &str) -> String {
    match recorded.and_then(|r| key.strip_prefix(r)) {
        Some(rest) if rest.is_empty() || rest.starts_with('/') => format!("{prefix}{rest}"),
        _ => key.to_owned(),
    }
}

/// The live view of a replay: the server and its channel id per topic.
struct LiveReplay {
    server: Arc<bridge::live::LiveServer>,
    channels: HashMap<String, u32>,
    /// The log time last announced (time messages go out once per log time).
    last_time: Option<u64>,
    sent: u64,
}

/// Where a replay's bus messages go.
enum Out<'a> {
    /// Nowhere (`--no-bus`: the live view only).
    None,
    /// A Zenoh session, a publisher per key.
    Zenoh { session: &'a zenoh::Session, publishers: HashMap<String, zenoh::pubsub::Publisher<'static>> },
    /// Memory, at most `limit` messages ([`replay_in_memory`]).
    Memory { sent: Vec<(String, Vec<u8>)>, limit: usize },
}

/// Replays into a Zenoh session (or memory), a live view, or both.
struct Replayer<'a> {
    out: Out<'a>,
    live: Option<LiveReplay>,
    prefix: String,
    recorded: Option<String>,
    last_sonar_tick: HashMap<String, u64>,
    last_clock_tick: Option<u64>,
    /// Each copter's last logged state, by id: a copter the log holds (unchanged since its
    /// last message) goes out again with each step's tick, as the live simulator sends it.
    latest: std::collections::BTreeMap<u32, proto::CopterState>,
    /// The log's control step, ns.
    dt_ns: u64,
    /// Its logged ticks (`log_every_ticks`); `None` for logs from before copters were held,
    /// which are not expanded.
    every_ticks: Option<u64>,
    /// Log time of tick 0 (from the first state), ns.
    epoch_ns: Option<u64>,
    counts: Counts,
    start: Instant,
    t0_ns: u64,
    /// The log's last log time, ns.
    t1_ns: u64,
    speed: f64,
    stop: Arc<AtomicBool>,
}

/// The publisher of `key` in `publishers`, declared on first use.
fn publisher<'p>(
    session: &zenoh::Session,
    publishers: &'p mut HashMap<String, zenoh::pubsub::Publisher<'static>>,
    key: &str,
) -> anyhow::Result<&'p zenoh::pubsub::Publisher<'static>> {
    if !publishers.contains_key(key) {
        let p = session
            .declare_publisher(key.to_owned())
            .congestion_control(CongestionControl::Block)
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))
            .with_context(|| format!("cannot declare a publisher on {key}"))?;
        publishers.insert(key.to_owned(), p);
    }
    Ok(&publishers[key])
}

impl Replayer<'_> {
    fn has_bus(&self) -> bool {
        !matches!(self.out, Out::None)
    }

    fn put(&mut self, key: &str, payload: Vec<u8>) -> anyhow::Result<()> {
        match &mut self.out {
            Out::None => Ok(()),
            Out::Zenoh { session, publishers } => publisher(session, publishers, key)?
                .put(payload)
                .wait()
                .map_err(|e| anyhow::anyhow!("{e}"))
                .with_context(|| format!("put {key}")),
            Out::Memory { sent, limit } => {
                if sent.len() >= *limit {
                    anyhow::bail!("more than {limit} messages to replay");
                }
                sent.push((key.to_owned(), payload));
                Ok(())
            }
        }
    }

    /// Sleeps until the deadline of `log_time_ns`; false if stopped meanwhile.
    fn wait_until(&self, log_time_ns: u64) -> bool {
        let offset_s = log_time_ns.saturating_sub(self.t0_ns) as f64 / 1e9 / self.speed;
        wait_until(&self.stop, self.start + Duration::from_secs_f64(offset_s))
    }

    fn put_clock(&mut self, tick: u64) -> anyhow::Result<()> {
        let clock = ClockMsg { tick, time_s: tick as f64 * self.dt_ns as f64 / 1e9 };
        self.put(&format!("{}/clock", self.prefix), serde_json::to_vec(&clock)?)?;
        self.counts.clock += 1;
        Ok(())
    }

    /// Sends again, with `tick`'s tick and time, the state of every copter the log held on
    /// that step (its last state is older).
    fn put_held(&mut self, tick: u64, bad: &impl Fn(String) -> anyhow::Error) -> anyhow::Result<()> {
        let held: Vec<proto::CopterState> = self.latest.values().filter(|s| s.tick < tick).cloned().collect();
        for mut s in held {
            (s.tick, s.t_s) = (tick, tick as f64 * self.dt_ns as f64 / 1e9);
            let key = format!("{}/copters/{}/state", self.prefix, s.copter);
            self.put(&key, serde_json::to_vec(&state_msg(s).map_err(bad)?)?)?;
            self.counts.state += 1;
        }
        Ok(())
    }

    /// Finishes the step last sent (its held copters), then sends every logged step before
    /// `next` (or up to the log's end, `None`) that has no state in the log because every
    /// copter was held: its clock and the held states, at its deadline. `Ok(false)`: stopped.
    fn catch_up(&mut self, next: Option<u64>, bad: &impl Fn(String) -> anyhow::Error) -> anyhow::Result<bool> {
        let (Some(last), Some(epoch), Some(every)) = (self.last_clock_tick, self.epoch_ns, self.every_ticks) else {
            return Ok(true);
        };
        self.put_held(last, bad)?;
        let end = match next {
            Some(t) => t,
            None => self.t1_ns.saturating_sub(epoch) / self.dt_ns.max(1) + 1,
        };
        let mut k = last + every;
        while k < end {
            if !self.wait_until(epoch.saturating_add(k.saturating_mul(self.dt_ns))) {
                return Ok(false);
            }
            self.last_clock_tick = Some(k);
            self.put_clock(k)?;
            self.put_held(k, bad)?;
            k = k.saturating_add(every);
        }
        Ok(true)
    }

    /// Handles one message. `Ok(false)`: stopped by a signal.
    fn message(
        &mut self,
        path: &Path,
        (topic, encoding): (&str, &str),
        log_time: u64,
        data: &[u8],
    ) -> anyhow::Result<bool> {
        if let Some(live) = &mut self.live
            && let Some(&id) = live.channels.get(topic)
        {
            let offset_s = log_time.saturating_sub(self.t0_ns) as f64 / 1e9 / self.speed;
            if !wait_until(&self.stop, self.start + Duration::from_secs_f64(offset_s)) {
                return Ok(false);
            }
            if live.last_time != Some(log_time) {
                live.last_time = Some(log_time);
                live.server.broadcast_time(log_time);
            }
            live.server.publish(id, log_time, data);
            live.sent += 1;
        }
        if !self.has_bus() {
            return Ok(true);
        }
        let bad = |what: String| {
            read_error(LogReadError::Decode { path: path.to_owned(), topic: topic.to_owned(), log_time, what })
        };
        match topic {
            "/copters/state" => {
                let s = proto::CopterState::decode_as(encoding, data).map_err(bad)?;
                self.epoch_ns.get_or_insert(log_time.saturating_sub(s.tick.saturating_mul(self.dt_ns)));
                if self.last_clock_tick.is_some_and(|c| s.tick > c) && !self.catch_up(Some(s.tick), &bad)? {
                    return Ok(false);
                }
                if !self.wait_until(log_time) {
                    return Ok(false);
                }
                if self.last_clock_tick != Some(s.tick) {
                    self.last_clock_tick = Some(s.tick);
                    self.put_clock(s.tick)?;
                }
                self.latest.insert(s.id, s.clone());
                let key = format!("{}/copters/{}/state", self.prefix, s.copter);
                self.put(&key, serde_json::to_vec(&state_msg(s).map_err(bad)?)?)?;
                self.counts.state += 1;
            }
            "/copters/sensors" => {
                let s = proto::CopterSensors::decode_as(encoding, data).map_err(bad)?;
                if self.last_sonar_tick.get(&s.copter) == Some(&s.sonar_tick) {
                    return Ok(true);
                }
                self.last_sonar_tick.insert(s.copter.clone(), s.sonar_tick);
                if !self.wait_until(log_time) {
                    return Ok(false);
                }
                let key = format!("{}/copters/{}/sensors", self.prefix, s.copter);
                self.put(&key, serde_json::to_vec(&sensors_msg(s).map_err(bad)?)?)?;
                self.counts.sensors += 1;
            }
            "/bus" => {
                let b = proto::BusMessage::decode_as(encoding, data).map_err(bad)?;
                let key = rekey(&b.key, self.recorded.as_deref(), &self.prefix);
                if zenoh::key_expr::KeyExpr::try_from(key.as_str()).is_err() {
                    tracing::warn!("skipping a /bus message: {key:?} is not a valid key expression");
                    self.counts.skipped += 1;
                    return Ok(true);
                }
                if !self.wait_until(log_time) {
                    return Ok(false);
                }
                self.put(&key, b.text.into_bytes())?;
                self.counts.bus += 1;
            }
            _ => {}
        }
        Ok(true)
    }
}

/// What a log says about replaying it.
struct Plan {
    prefix: String,
    /// The prefix the run published under, as far as the log tells.
    recorded: Option<String>,
    /// The control step, ns (50 ms if the log does not say).
    dt_ns: u64,
    /// Logged ticks (`log_every_ticks`), if the log says.
    every_ticks: Option<u64>,
    copters: Vec<String>,
    /// First and last log time, ns.
    t0_ns: u64,
    t1_ns: u64,
    /// `twinswarm` metadata entries present but not understood (replayed with defaults).
    unreadable: Vec<&'static str>,
}

fn bad_input(msg: String) -> anyhow::Error {
    anyhow::Error::new(BadInput(anyhow::anyhow!(msg)))
}

/// Reads the replay's parameters from the log's metadata and summary. `everything`: every
/// channel is replayed (the live view), not only state, sensors and bus.
fn plan(file: &LogFile, prefix: Option<&str>, everything: bool) -> anyhow::Result<Plan> {
    let path = file.path();
    let info = file.info().map_err(read_error)?;
    let meta = info.metadata.get("twinswarm");
    let recorded = recorded_prefix(meta);
    let Some(prefix) = prefix.map(str::to_owned).or_else(|| recorded.clone()) else {
        return Err(bad_input(format!(
            "{}: no `twinswarm` metadata record (not written by twinswarm run?); give --prefix",
            path.display()
        )));
    };
    let count = |topic: &str| info.channels.iter().find(|c| c.topic == topic).map_or(0, |c| c.messages);
    let replayable =
        if everything { info.messages } else { count("/copters/state") + count("/copters/sensors") + count("/bus") };
    let Some((t0_ns, t1_ns)) = info.time_range_ns.filter(|_| replayable > 0) else {
        return Err(bad_input(format!("{}: no state, sensor or bus messages to replay", path.display())));
    };
    // The step, and whether the log may hold copters (logs from before say neither). A step
    // under a microsecond is not one a run takes (and would round to nothing).
    let field = |key: &str| meta.and_then(|m| m.get(key));
    let dt_s = field("control_dt_s")
        .and_then(|t| t.parse::<f64>().ok())
        .filter(|dt| dt.is_finite() && *dt >= 1e-6 && *dt < 3600.0);
    let every_ticks =
        field("log_every_ticks").and_then(|t| t.parse::<u64>().ok()).filter(|n| (1..=1_000_000).contains(n));
    let copter_list = field("copters").and_then(|s| serde_json::from_str::<Vec<serde_json::Value>>(s).ok());
    let copters = (copter_list.iter().flatten()).filter_map(|c| c["name"].as_str().map(str::to_owned)).collect();
    // Entries present but not understood: said, and replayed with the defaults (a 50 ms step,
    // no held copters), never dropped without a word.
    let unreadable = [
        ("control_dt_s", dt_s.is_some()),
        ("log_every_ticks", every_ticks.is_some()),
        ("copters", copter_list.is_some()),
    ]
    .into_iter()
    .filter(|&(key, ok)| field(key).is_some() && !ok)
    .map(|(key, _)| key)
    .collect();
    Ok(Plan {
        prefix,
        recorded,
        dt_ns: dt_s.map_or(50_000_000, |dt| (dt * 1e9).round() as u64),
        every_ticks,
        copters,
        t0_ns,
        t1_ns,
        unreadable,
    })
}

impl Plan {
    /// The log's span, s.
    fn span_s(&self) -> f64 {
        (self.t1_ns - self.t0_ns) as f64 / 1e9
    }
}

impl<'a> Replayer<'a> {
    fn new(plan: &Plan, out: Out<'a>, live: Option<LiveReplay>, speed: f64, stop: Arc<AtomicBool>) -> Self {
        Replayer {
            out,
            live,
            prefix: plan.prefix.clone(),
            recorded: plan.recorded.clone(),
            last_sonar_tick: HashMap::new(),
            last_clock_tick: None,
            latest: std::collections::BTreeMap::new(),
            dt_ns: plan.dt_ns,
            every_ticks: plan.every_ticks,
            epoch_ns: None,
            counts: Counts::default(),
            start: Instant::now(),
            t0_ns: plan.t0_ns,
            t1_ns: plan.t1_ns,
            speed,
            stop,
        }
    }
}

/// Replays `path` into memory, as fast as it reads: every (key, payload) that `twinswarm
/// replay` would put on Zenoh, in order, under the log's own prefix. More than `limit`
/// messages is an error. (The fuzz target of logs, and tests.)
pub fn replay_in_memory(path: &Path, limit: usize) -> anyhow::Result<Vec<(String, Vec<u8>)>> {
    let file = LogFile::open(path).map_err(read_error)?;
    let plan = plan(&file, None, false)?;
    let out = Out::Memory { sent: Vec::new(), limit };
    let mut r = Replayer::new(&plan, out, None, f64::INFINITY, Arc::new(AtomicBool::new(false)));
    replay_messages(&mut r, &file)?;
    match r.out {
        Out::Memory { sent, .. } => Ok(sent),
        _ => unreachable!("a memory replay"),
    }
}

/// `twinswarm replay FILE` for a run log (a Paparazzi log goes to [`crate::replay_pprz::run`]).
pub fn run(args: ReplayArgs) -> anyhow::Result<()> {
    check_args(&args)?;
    let path = args.file.as_path();
    let file = LogFile::open(path).map_err(read_error)?;
    let plan = plan(&file, args.zenoh.prefix.as_deref(), args.foxglove.is_some())?;
    let span_s = plan.span_s();
    if !plan.unreadable.is_empty() {
        eprintln!(
            "replay: {}: {} unreadable `twinswarm` metadata entries ({}); replaying with their defaults",
            path.display(),
            plan.unreadable.len(),
            plan.unreadable.join(", ")
        );
    }

    let stop = crate::logcmd::install_stop_flag()?;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
    let live = match &args.foxglove {
        None => None,
        Some(addr) => Some(start_live(addr, &file, &rt)?),
    };
    let session = match args.no_bus {
        true => None,
        false => Some(
            zenoh::open(args.zenoh.config(ZenohRole::Peer)?)
                .wait()
                .map_err(|e| anyhow::anyhow!("{e}"))
                .context("cannot open the Zenoh session")?,
        ),
    };
    let out = match &session {
        Some(session) => Out::Zenoh { session, publishers: HashMap::new() },
        None => Out::None,
    };
    let mut r = Replayer::new(&plan, out, live, args.speed, stop.clone());
    outln!(
        "replay {}: {:.2} s of log at speed {} ({:.2} s), prefix {}",
        path.display(),
        span_s,
        args.speed,
        span_s / args.speed,
        plan.prefix
    );
    let result = replay(&mut r, &file, &plan.copters, &args);
    let wall_s = r.start.elapsed().as_secs_f64();
    let counts = r.counts;
    let live = r.live.take();
    let publishers = match std::mem::replace(&mut r.out, Out::None) {
        Out::Zenoh { publishers, .. } => publishers,
        _ => HashMap::new(),
    };
    drop(r);
    // Let the last samples leave the transmission queue (and the live clients' queues), then
    // close explicitly.
    std::thread::sleep(Duration::from_millis(200));
    drop(publishers);
    let closed = match session {
        Some(s) => s.close().wait().map_err(|e| anyhow::anyhow!("{e}")).context("closing the Zenoh session"),
        None => Ok(()),
    };
    let interrupted = result?;
    closed?;
    print_report(&plan, live.as_ref(), &counts, args.speed, wall_s, interrupted);
    Ok(())
}

/// The flags a run log's replay refuses.
fn check_args(args: &ReplayArgs) -> anyhow::Result<()> {
    let bad = bad_input;
    if args.no_bus && args.foxglove.is_none() {
        return Err(bad("--no-bus needs --foxglove for a run log (nothing would be replayed)".into()));
    }
    if args.ivy.ivy.is_some() || args.from.is_some() || args.to.is_some() || args.ac_id.is_some() {
        return Err(bad("--ivy, --from, --to and --ac-id replay Paparazzi logs (NAME.data)".into()));
    }
    if !args.speed.is_finite() || args.speed <= 0.0 {
        return Err(bad(format!("--speed must be a positive finite number, got {}", args.speed)));
    }
    if let Some(w) = args.wait_for_subscriber
        && (!w.is_finite() || w < 0.0)
    {
        return Err(bad(format!("--wait-for-subscriber must be a non-negative number of seconds, got {w}")));
    }
    Ok(())
}

/// `--foxglove ADDR`: the live view, with a channel for each of the file's.
fn start_live(addr: &str, file: &LogFile, rt: &tokio::runtime::Runtime) -> anyhow::Result<LiveReplay> {
    let addr: std::net::SocketAddr = addr
        .parse()
        .map_err(|e| bad_input(format!("--foxglove: {addr:?} is not an address like 127.0.0.1:8765: {e}")))?;
    let server = bridge::live::LiveServer::start(addr, "twinswarm replay", rt.handle())
        .with_context(|| format!("--foxglove: cannot listen on {addr}"))?;
    let mut channels = HashMap::new();
    for c in file.channel_defs() {
        let def = bridge::live::LiveChannel::from_schema_bytes(
            &c.topic,
            &c.encoding,
            &c.schema_name,
            &c.schema_encoding,
            &c.schema,
        );
        channels.insert(c.topic.clone(), server.add_channel(def));
    }
    outln!("  live view: ws://{} ({} channels)", server.local_addr(), channels.len());
    Ok(LiveReplay { server: Arc::new(server), channels, last_time: None, sent: 0 })
}

/// The replay's summary: the live view's, what went out, and how fast.
fn print_report(plan: &Plan, live: Option<&LiveReplay>, counts: &Counts, speed: f64, wall_s: f64, interrupted: bool) {
    if let Some(l) = live {
        let st = l.server.stats();
        outln!(
            "  live view: {} messages published; {} clients, {} subscriptions, {} messages sent, {} dropped (slow clients), {} protocol errors",
            l.sent,
            st.clients,
            st.subscriptions,
            st.messages_sent,
            st.messages_dropped,
            st.protocol_errors
        );
    }
    outln!(
        "  republished {} messages: {} clock, {} state, {} sensors, {} bus{}",
        counts.clock + counts.state + counts.sensors + counts.bus,
        counts.clock,
        counts.state,
        counts.sensors,
        counts.bus,
        if counts.skipped > 0 {
            format!(" ({} bus messages with invalid keys skipped)", counts.skipped)
        } else {
            String::new()
        }
    );
    if !plan.unreadable.is_empty() {
        outln!(
            "  {} unreadable metadata entries ({}): replayed with their defaults",
            plan.unreadable.len(),
            plan.unreadable.join(", ")
        );
    }
    if interrupted {
        outln!("  interrupted by a signal after {wall_s:.2} s wall (speed {speed}); the session was closed cleanly");
    } else {
        let span_s = plan.span_s();
        outln!(
            "  {:.2} s of log in {:.2} s wall at speed {} ({:.2}x effective)",
            span_s,
            wall_s,
            speed,
            if wall_s > 0.0 { span_s / wall_s } else { 0.0 }
        );
    }
}

/// Waits for subscribers, then replays. `Ok(true)`: interrupted by a signal.
fn replay(r: &mut Replayer<'_>, file: &LogFile, copters: &[String], args: &ReplayArgs) -> anyhow::Result<bool> {
    let mut keys = Vec::new();
    if let Out::Zenoh { session, publishers } = &mut r.out {
        keys.push(format!("{}/clock", r.prefix));
        for c in copters {
            keys.push(format!("{}/copters/{c}/state", r.prefix));
            keys.push(format!("{}/copters/{c}/sensors", r.prefix));
        }
        for k in &keys {
            publisher(session, publishers, k)?;
        }
    }
    if let Some(wait_s) = args.wait_for_subscriber {
        outln!("  waiting up to {wait_s} s for a subscriber");
        let until = Instant::now() + Duration::from_secs_f64(wait_s);
        let matched = |r: &Replayer<'_>| {
            let bus = match &r.out {
                Out::Zenoh { publishers, .. } => {
                    keys.iter().any(|k| publishers[k].matching_status().wait().is_ok_and(|m| m.matching()))
                }
                _ => false,
            };
            bus || r.live.as_ref().is_some_and(|l| l.server.active())
        };
        while !matched(r) {
            if r.stop.load(Ordering::Relaxed) {
                return Ok(true);
            }
            if Instant::now() >= until {
                tracing::warn!("no subscriber after {wait_s} s; replaying anyway");
                break;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    let delay_until = Instant::now() + Duration::from_millis(args.start_delay_ms);
    while Instant::now() < delay_until {
        if r.stop.load(Ordering::Relaxed) {
            return Ok(true);
        }
        std::thread::sleep((delay_until - Instant::now()).min(Duration::from_millis(50)));
    }
    r.start = Instant::now();
    replay_messages(r, file)
}

/// Sends every message of the log, at its time. `Ok(true)`: interrupted by a signal.
fn replay_messages(r: &mut Replayer<'_>, file: &LogFile) -> anyhow::Result<bool> {
    // The reader's callback can only fail with a `LogReadError`: our own failures and a stop
    // are parked here and signalled with a placeholder error.
    let mut failure: Option<anyhow::Result<bool>> = None;
    let path = file.path().to_owned();
    let sentinel = || LogReadError::Io { path: path.clone(), source: std::io::Error::other("replay stopped") };
    let all = r.live.is_some();
    let wanted = |t: &str| all || ["/copters/state", "/copters/sensors", "/bus"].contains(&t);
    let read = file.for_each_message_where(wanted, |topic, log_time, data| {
        match r.message(&path, (topic, file.encoding(topic).unwrap_or("")), log_time, data) {
            Ok(true) => Ok(()),
            Ok(false) => {
                failure = Some(Ok(true));
                Err(sentinel())
            }
            Err(e) => {
                failure = Some(Err(e));
                Err(sentinel())
            }
        }
    });
    if let Some(f) = failure {
        return f;
    }
    read.map_err(read_error)?;
    // The log's last steps, if every copter was held on them.
    if r.has_bus() {
        let t1_ns = r.t1_ns;
        let bad = |what: String| {
            read_error(LogReadError::Decode {
                path: path.clone(),
                topic: "/copters/state".into(),
                log_time: t1_ns,
                what,
            })
        };
        if !r.catch_up(None, &bad)? {
            return Ok(true);
        }
    }
    Ok(false)
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;

    #[test]
    fn prefix_from_metadata_and_rekeying() {
        let mut m = BTreeMap::new();
        m.insert("world".to_owned(), "lab".to_owned());
        m.insert("command_line".to_owned(), "twinswarm run --no-bus".to_owned());
        assert_eq!(recorded_prefix(Some(&m)).as_deref(), Some("twinswarm/lab"));
        m.insert("command_line".to_owned(), "twinswarm run --prefix demo/x --log a.mcap".to_owned());
        assert_eq!(recorded_prefix(Some(&m)).as_deref(), Some("demo/x"));
        m.insert("prefix".to_owned(), "rec/p".to_owned());
        assert_eq!(recorded_prefix(Some(&m)).as_deref(), Some("rec/p"));
        assert_eq!(recorded_prefix(None), None);
        assert_eq!(rekey("twinswarm/lab/copters/a/cmd", Some("twinswarm/lab"), "r/x"), "r/x/copters/a/cmd");
        assert_eq!(rekey("twinswarm/labx/a", Some("twinswarm/lab"), "r/x"), "twinswarm/labx/a");
        assert_eq!(rekey("other/a", Some("twinswarm/lab"), "r/x"), "other/a");
    }

    #[test]
    fn a_log_replays_in_memory_every_step_under_its_prefix() {
        use bridge::log::{LogMeta, LogOptions, Logger};
        let text = sim_core::scene::DEFAULT_SCENE_TOML;
        let (_, world) = sim_core::scene::load("lab.toml", text).unwrap();
        let (mut state, inputs) = (world.initial_state(), world.initial_inputs());
        let path = std::env::temp_dir().join(format!("twinswarm-replay-mem-{}.mcap", std::process::id()));
        let meta = LogMeta { command_line: "twinswarm run --prefix mem/lab".into(), ..LogMeta::default() };
        // Every second step logged: the replay still sends every logged step's clock.
        let options = LogOptions { every_ticks: 2, ..LogOptions::default() };
        let mut log = Logger::with_options(&path, &world, text, meta, options).unwrap();
        for _ in 0..20 {
            let r = sim_core::step(&world, &mut state, &inputs);
            log.log_step(&world, &state, &inputs, &r).unwrap();
        }
        log.finish().unwrap();
        let sent = replay_in_memory(&path, 10_000).unwrap();
        let count =
            |suffix: &str| sent.iter().filter(|(k, _)| k.starts_with("mem/lab/") && k.ends_with(suffix)).count();
        let n = world.copters.len();
        assert_eq!((count("/clock"), count("/state")), (10, 10 * n), "{:?}", &sent[..4]);
        assert!(count("/sensors") > 0);
        let err = replay_in_memory(&path, 5).unwrap_err();
        assert!(format!("{err:#}").contains("more than 5 messages"), "{err:#}");
        let _ = std::fs::remove_file(&path);
    }

    #[test]
    fn logged_state_maps_to_the_live_shape() {
        let logged = proto::CopterState {
            tick: 3,
            t_s: 0.15,
            copter: "finken1".into(),
            ac_id: Some(201),
            kind: "real".into(),
            mode: "wall_avoid".into(),
            pos_m: vec![1.0, 2.0, 3.0],
            vel_m_s: vec![0.0; 3],
            rpy_rad: vec![0.1, 0.2, 0.3],
            angvel_rad_s: vec![0.0; 3],
            quat_xyzw: vec![0.0, 0.0, 0.0, 1.0],
            rotor_thrust_n: vec![0.5; 4],
            ..Default::default()
        };
        let s = state_msg(logged.clone()).expect("a whole state");
        assert_eq!(
            (s.name.as_str(), s.kind.as_str(), s.time_s, s.attitude_rad, s.ac_id),
            ("finken1", "twin", 0.15, [0.1, 0.2, 0.3], Some(201))
        );
        let short = proto::CopterState { pos_m: vec![1.0], ..logged };
        let err = state_msg(short).unwrap_err();
        assert!(err.contains("pos_m") && err.contains('1'), "{err}");
    }
}
