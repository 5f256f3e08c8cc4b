//! `twinswarm replay FILE`: republishes a run log's bus traffic onto Zenoh with its original
//! timing, so ground tools can watch a flight again.
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
use crate::runner::{BusOptions, zenoh_config};

/// `twinswarm replay` arguments.
#[derive(Debug, clap::Args)]
pub struct ReplayArgs {
    /// The MCAP log of a run.
    pub file: PathBuf,
    /// Playback speed: 2 plays twice as fast, 0.5 half as fast (> 0).
    #[arg(long, value_name = "X", default_value_t = 1.0, allow_negative_numbers = true)]
    pub speed: f64,
    /// A full Zenoh configuration file (JSON5), instead of the embedded default (peer mode,
    /// listen on tcp/127.0.0.1:7447, multicast scouting off).
    #[arg(long, value_name = "FILE.json5")]
    pub zenoh_config: Option<PathBuf>,
    /// Zenoh endpoint to listen on (repeatable; overrides the config).
    #[arg(long, value_name = "ENDPOINT")]
    pub listen: Vec<String>,
    /// Zenoh endpoint to connect to (repeatable; overrides the config).
    #[arg(long, value_name = "ENDPOINT")]
    pub connect: Vec<String>,
    /// Key-expression prefix (default: the one recorded in the log, else twinswarm/<world>).
    #[arg(long, value_name = "KEY")]
    pub prefix: Option<String>,
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
    /// Do not republish on Zenoh (with `--foxglove`: the live view only).
    #[arg(long, requires = "foxglove")]
    pub no_bus: bool,
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
fn wait_until(stop: &AtomicBool, deadline: Instant) -> bool {
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

/// Replays into a Zenoh session, a live view, or both.
struct Replayer<'a> {
    session: Option<&'a zenoh::Session>,
    live: Option<LiveReplay>,
    prefix: String,
    recorded: Option<String>,
    publishers: HashMap<String, zenoh::pubsub::Publisher<'static>>,
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

impl Replayer<'_> {
    fn publisher(&mut self, key: &str) -> anyhow::Result<&zenoh::pubsub::Publisher<'static>> {
        if !self.publishers.contains_key(key) {
            let session = self.session.ok_or_else(|| anyhow::anyhow!("no Zenoh session (--no-bus)"))?;
            let p = session
                .declare_publisher(key.to_owned())
                .congestion_control(CongestionControl::Block)
                .wait()
                .map_err(|e| anyhow::anyhow!("{e}"))
                .with_context(|| format!("cannot declare a publisher on {key}"))?;
            self.publishers.insert(key.to_owned(), p);
        }
        Ok(&self.publishers[key])
    }

    fn put(&mut self, key: &str, payload: Vec<u8>) -> anyhow::Result<()> {
        self.publisher(key)?
            .put(payload)
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))
            .with_context(|| format!("put {key}"))
    }

    /// Sleeps until the deadline of `log_time_ns`; false if stopped meanwhile.
    fn wait_until(&self, log_time_ns: u64) -> bool {
        let offset_s = log_time_ns.saturating_sub(self.t0_ns) as f64 / 1e9 / self.speed;
        wait_until(&self.stop, self.start + Duration::from_secs_f64(offset_s))
    }

    fn put_clock(&mut self, tick: u64) -> anyhow::Result<()> {
        let clock = ClockMsg { tick, time_s: (tick * self.dt_ns) as f64 / 1e9 };
        self.put(&format!("{}/clock", self.prefix), serde_json::to_vec(&clock)?)?;
        self.counts.clock += 1;
        Ok(())
    }

    /// Sends again, with `tick`'s tick and time, the state of every copter the log held on
    /// that step (its last state is older).
    fn put_held(&mut self, tick: u64, bad: &impl Fn(String) -> anyhow::Error) -> anyhow::Result<()> {
        let held: Vec<proto::CopterState> = self.latest.values().filter(|s| s.tick < tick).cloned().collect();
        for mut s in held {
            (s.tick, s.t_s) = (tick, (tick * self.dt_ns) as f64 / 1e9);
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
            if !self.wait_until(epoch + k * self.dt_ns) {
                return Ok(false);
            }
            self.last_clock_tick = Some(k);
            self.put_clock(k)?;
            self.put_held(k, bad)?;
            k += every;
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
        if self.session.is_none() {
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

/// `twinswarm replay FILE`.
pub fn run(args: ReplayArgs) -> anyhow::Result<()> {
    let bad = |msg: String| anyhow::Error::new(BadInput(anyhow::anyhow!(msg)));
    if !args.speed.is_finite() || args.speed <= 0.0 {
        return Err(bad(format!("--speed must be a positive finite number, got {}", args.speed)));
    }
    if let Some(w) = args.wait_for_subscriber
        && (!w.is_finite() || w < 0.0)
    {
        return Err(bad(format!("--wait-for-subscriber must be a non-negative number of seconds, got {w}")));
    }
    let path = args.file.as_path();
    let file = LogFile::open(path).map_err(read_error)?;
    let info = file.info().map_err(read_error)?;
    let meta = info.metadata.get("twinswarm");
    let recorded = recorded_prefix(meta);
    let Some(prefix) = args.prefix.clone().or_else(|| recorded.clone()) else {
        return Err(bad(format!(
            "{}: no `twinswarm` metadata record (not written by twinswarm run?); give --prefix",
            path.display()
        )));
    };
    let count = |topic: &str| info.channels.iter().find(|c| c.topic == topic).map_or(0, |c| c.messages);
    let replayable = if args.foxglove.is_some() {
        info.messages
    } else {
        count("/copters/state") + count("/copters/sensors") + count("/bus")
    };
    let Some((t0_ns, t1_ns)) = info.time_range_ns.filter(|_| replayable > 0) else {
        return Err(bad(format!("{}: no state, sensor or bus messages to replay", path.display())));
    };
    let span_s = (t1_ns - t0_ns) as f64 / 1e9;
    // The step, and whether the log may hold copters (logs from before say neither).
    let field = |key: &str| meta.and_then(|m| m.get(key));
    let dt_s = field("control_dt_s")
        .and_then(|t| t.parse::<f64>().ok())
        .filter(|dt| dt.is_finite() && *dt > 0.0 && *dt < 3600.0);
    let dt_ns = dt_s.map_or(50_000_000, |dt| (dt * 1e9).round() as u64);
    let every_ticks =
        field("log_every_ticks").and_then(|t| t.parse::<u64>().ok()).filter(|n| (1..=1_000_000).contains(n));
    let copter_list = field("copters").and_then(|s| serde_json::from_str::<Vec<serde_json::Value>>(s).ok());
    let copters: Vec<String> =
        (copter_list.iter().flatten()).filter_map(|c| c["name"].as_str().map(str::to_owned)).collect();
    // Entries present but not understood: said, and replayed with the defaults (a 50 ms step,
    // no held copters), never dropped without a word.
    let unreadable: Vec<&str> = [
        ("control_dt_s", dt_s.is_some()),
        ("log_every_ticks", every_ticks.is_some()),
        ("copters", copter_list.is_some()),
    ]
    .into_iter()
    .filter(|&(key, ok)| field(key).is_some() && !ok)
    .map(|(key, _)| key)
    .collect();
    if !unreadable.is_empty() {
        eprintln!(
            "replay: {}: {} unreadable `twinswarm` metadata entries ({}); replaying with their defaults",
            path.display(),
            unreadable.len(),
            unreadable.join(", ")
        );
    }

    let stop = crate::logcmd::install_stop_flag()?;
    let bus = BusOptions {
        no_bus: false,
        zenoh_config: args.zenoh_config.clone(),
        listen: args.listen.clone(),
        connect: args.connect.clone(),
        prefix: Some(prefix.clone()),
        ..BusOptions::default()
    };
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
    let live = match &args.foxglove {
        None => None,
        Some(a) => {
            let addr: std::net::SocketAddr =
                a.parse().map_err(|e| bad(format!("--foxglove: {a:?} is not an address like 127.0.0.1:8765: {e}")))?;
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
            Some(LiveReplay { server: Arc::new(server), channels, last_time: None, sent: 0 })
        }
    };
    let session = match args.no_bus {
        true => None,
        false => Some(
            zenoh::open(zenoh_config(&bus)?)
                .wait()
                .map_err(|e| anyhow::anyhow!("{e}"))
                .context("cannot open the Zenoh session")?,
        ),
    };
    let mut r = Replayer {
        session: session.as_ref(),
        live,
        prefix: prefix.clone(),
        recorded,
        publishers: HashMap::new(),
        last_sonar_tick: HashMap::new(),
        last_clock_tick: None,
        latest: std::collections::BTreeMap::new(),
        dt_ns,
        every_ticks,
        epoch_ns: None,
        counts: Counts::default(),
        start: Instant::now(),
        t0_ns,
        t1_ns,
        speed: args.speed,
        stop: stop.clone(),
    };
    outln!(
        "replay {}: {:.2} s of log at speed {} ({:.2} s), prefix {prefix}",
        path.display(),
        span_s,
        args.speed,
        span_s / args.speed
    );
    let result = replay(&mut r, &file, &copters, &args);
    let wall_s = r.start.elapsed().as_secs_f64();
    let counts = r.counts;
    let live = r.live.take();
    let publishers = std::mem::take(&mut r.publishers);
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
    if let Some(l) = &live {
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
    if !unreadable.is_empty() {
        outln!(
            "  {} unreadable metadata entries ({}): replayed with their defaults",
            unreadable.len(),
            unreadable.join(", ")
        );
    }
    if interrupted {
        outln!(
            "  interrupted by a signal after {wall_s:.2} s wall (speed {}); the session was closed cleanly",
            args.speed
        );
    } else {
        outln!(
            "  {:.2} s of log in {:.2} s wall at speed {} ({:.2}x effective)",
            span_s,
            wall_s,
            args.speed,
            if wall_s > 0.0 { span_s / wall_s } else { 0.0 }
        );
    }
    Ok(())
}

/// Waits for subscribers, then replays. `Ok(true)`: interrupted by a signal.
fn replay(r: &mut Replayer<'_>, file: &LogFile, copters: &[String], args: &ReplayArgs) -> anyhow::Result<bool> {
    let mut keys = Vec::new();
    if r.session.is_some() {
        keys.push(format!("{}/clock", r.prefix));
        for c in copters {
            keys.push(format!("{}/copters/{c}/state", r.prefix));
            keys.push(format!("{}/copters/{c}/sensors", r.prefix));
        }
    }
    for k in &keys {
        r.publisher(k)?;
    }
    if let Some(wait_s) = args.wait_for_subscriber {
        outln!("  waiting up to {wait_s} s for a subscriber");
        let until = Instant::now() + Duration::from_secs_f64(wait_s);
        let matched = |r: &Replayer<'_>| {
            r.live.as_ref().is_some_and(|l| l.server.active())
                || keys.iter().any(|k| r.publishers[k].matching_status().wait().is_ok_and(|m| m.matching()))
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
    if r.session.is_some() {
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
