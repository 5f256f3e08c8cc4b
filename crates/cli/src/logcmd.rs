//! `twinswarm log info|recover`, and the logging of `twinswarm run`: where the file goes,
//! the stop flag for SIGINT/SIGTERM, and the lines the summary prints.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use anyhow::Context;
use bridge::log::{
    EventKind, LogEvent, LogFile, LogMeta, LogOptions, LogReadError, LogStats, Logger, format_utc_basic, now_unix_ns,
};
use sim_core::World;

use crate::BadInput;

/// A log reading error is the input file's fault (exit code 2) unless it is about writing
/// the output.
pub fn read_error(e: LogReadError) -> anyhow::Error {
    match e {
        LogReadError::Write { .. } => anyhow::Error::new(e),
        other => anyhow::Error::new(BadInput(other.into())),
    }
}

/// The default log file: `runs/<world name>-<UTC timestamp>.mcap`, made unique with `-1`,
/// `-2`, … if needed.
pub fn default_log_path(world: &World, epoch_ns: u64) -> PathBuf {
    let name: String =
        world.name.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect();
    let stem = format!("{}-{}", if name.is_empty() { "run" } else { &name }, format_utc_basic(epoch_ns));
    let dir = Path::new("runs");
    let mut path = dir.join(format!("{stem}.mcap"));
    let mut k = 1;
    while path.exists() {
        path = dir.join(format!("{stem}-{k}.mcap"));
        k += 1;
    }
    path
}

/// The environment variable that sets a run log's epoch (Unix ns), as `cluster` does for its
/// shards.
pub const LOG_EPOCH_ENV: &str = "TWINSWARM_LOG_EPOCH_NS";

/// Starts the log of a run, unless `no_log`. `scene_path`: the scene file (`None`: the
/// embedded lab). `options`: rate and zstd level; `live` joins them. The epoch: the
/// launcher's ([`LOG_EPOCH_ENV`]), else `epoch_ns` (a resumed run's), else now.
#[allow(clippy::too_many_arguments)]
pub fn start_run_log(
    log: Option<&Path>,
    no_log: bool,
    options: LogOptions,
    world: &World,
    scene_path: Option<&Path>,
    scene_origin: &str,
    live: Option<Arc<bridge::live::LiveServer>>,
    epoch_ns: Option<u64>,
) -> anyhow::Result<Option<Logger>> {
    if no_log {
        return match live {
            Some(live) => Ok(Some(Logger::live_only(world, live, LogOptions { live: None, ..options })?)),
            None => Ok(None),
        };
    }
    // The shards of a cluster share one epoch (the launcher sets it), so that their logs share
    // one time base and merge without shifting.
    let epoch_ns = match std::env::var(LOG_EPOCH_ENV) {
        Ok(v) => v.parse().map_err(|e| BadInput(anyhow::anyhow!("{LOG_EPOCH_ENV}={v:?}: not a time in ns: {e}")))?,
        Err(_) => epoch_ns.unwrap_or_else(now_unix_ns),
    };
    let path = match log {
        Some(p) => p.to_owned(),
        None => default_log_path(world, epoch_ns),
    };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create log directory {}", dir.display()))?;
    }
    let scene_text = match scene_path {
        None => sim_core::scene::DEFAULT_SCENE_TOML.to_owned(),
        Some(p) => std::fs::read_to_string(p).with_context(|| format!("cannot read scene file {}", p.display()))?,
    };
    let meta = LogMeta {
        command_line: std::env::args().collect::<Vec<_>>().join(" "),
        scene_origin: scene_origin.to_owned(),
        epoch_ns: Some(epoch_ns),
    };
    Ok(Some(Logger::with_options(&path, world, &scene_text, meta, LogOptions { live, ..options })?))
}

/// SIGINT and SIGTERM set the returned flag (the run loop stops and finishes the log); a
/// second signal of the same kind exits at once.
///
/// SIGXFSZ (a write beyond the file-size limit, `ulimit -f`) is caught too: by default it
/// kills the process without a word (exit 153). Caught, the write fails with `EFBIG`
/// instead, and the log's error path says what happened and where the log ends.
pub fn install_stop_flag() -> anyhow::Result<Arc<AtomicBool>> {
    use signal_hook::consts::{SIGINT, SIGTERM, SIGXFSZ};
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [SIGINT, SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(sig, 130, Arc::clone(&stop))
            .context("cannot install the signal handler")?;
        signal_hook::flag::register(sig, Arc::clone(&stop)).context("cannot install the signal handler")?;
    }
    signal_hook::flag::register(SIGXFSZ, Arc::new(AtomicBool::new(false)))
        .context("cannot install the SIGXFSZ handler")?;
    Ok(stop)
}

/// Finishes a run's log; a run that stopped before its end (at a tick, why) says so in it.
pub fn finish_run_log(log: Option<Logger>, interrupted: Option<(u64, &str)>) -> anyhow::Result<Option<LogStats>> {
    let Some(mut log) = log else { return Ok(None) };
    if !log.has_file() {
        log.finish()?;
        return Ok(None);
    }
    if let Some((tick, why)) = interrupted {
        log.log_event(LogEvent {
            tick,
            kind: EventKind::Interrupted,
            copter: None,
            detail: None,
            message: format!("run {why}; log finished cleanly"),
        })?;
    }
    Ok(Some(log.finish()?))
}

/// The summary's log line: path and message count.
pub fn describe(stats: &LogStats) -> String {
    format!("{} ({} messages)", stats.path.display(), stats.total_messages())
}

/// `twinswarm log info FILE`.
pub fn info(path: &Path) -> anyhow::Result<()> {
    out!("{}", summarise(path)?);
    Ok(())
}

/// What `log info` prints about a log.
pub fn summarise(path: &Path) -> anyhow::Result<String> {
    use std::fmt::Write as _;
    let mut out = String::new();
    let file = LogFile::open(path).map_err(read_error)?;
    let info = file.info().map_err(read_error)?;
    writeln!(out, "{}: MCAP, {:.2} MB, {} chunks ({})", path.display(), info.file_bytes as f64 / 1e6, info.chunks, {
        if info.compression.is_empty() { "uncompressed" } else { &info.compression }
    })?;
    let meta = info.metadata.get("twinswarm");
    let get = |k: &str| meta.and_then(|m| m.get(k)).map(String::as_str).unwrap_or("?");
    if meta.is_some() {
        writeln!(
            out,
            "  twinswarm {}, world {:?}, seed {}, scene {}",
            get("version"),
            get("world"),
            get("seed"),
            get("scene_origin")
        )?;
        writeln!(out, "  command line: {}", get("command_line"))?;
        writeln!(out, "  started {} (log_time epoch)", get("epoch_utc"))?;
    } else {
        writeln!(out, "  no `twinswarm` metadata record: not written by twinswarm run")?;
    }
    let (dt_s, epoch) = (get("control_dt_s").parse::<f64>().ok(), get("epoch_unix_ns").parse::<u64>().ok());
    match info.time_range_ns {
        Some((a, b)) => {
            let sim_s = b.saturating_sub(a) as f64 / 1e9;
            let from_epoch = epoch.map(|e| {
                format!(
                    ", {:.2} s to {:.2} s simulated",
                    a.saturating_sub(e) as f64 / 1e9,
                    b.saturating_sub(e) as f64 / 1e9
                )
            });
            let steps = dt_s.map(|dt| format!(", control step {:.0} ms", dt * 1e3));
            writeln!(
                out,
                "  duration {sim_s:.2} s (sim){}{}",
                from_epoch.unwrap_or_default(),
                steps.unwrap_or_default()
            )?;
        }
        None => writeln!(out, "  no messages")?,
    }
    if let Some(Ok(serde_json::Value::Array(copters))) =
        meta.and_then(|m| m.get("copters")).map(|s| serde_json::from_str(s))
    {
        writeln!(out, "  {} copter(s):", copters.len())?;
        for c in &copters {
            writeln!(
                out,
                "    {:<12} {:<8} ac_id {}",
                c["name"].as_str().unwrap_or("?"),
                c["kind"].as_str().unwrap_or("?"),
                c["ac_id"].as_u64().map_or("-".into(), |a| a.to_string())
            )?;
        }
    }
    writeln!(out, "  {} messages on {} channels:", info.messages, info.channels.len())?;
    let w = info.channels.iter().map(|c| c.topic.len()).max().unwrap_or(0).max(18);
    writeln!(out, "    {:<w$} {:<26} {:<8} {:>10}", "topic", "schema", "encoding", "messages")?;
    for c in &info.channels {
        writeln!(out, "    {:<w$} {:<26} {:<8} {:>10}", c.topic, c.schema, c.encoding, c.messages)?;
    }
    writeln!(out, "  attachments:")?;
    for (name, media, bytes) in &info.attachments {
        writeln!(out, "    {name} ({media}, {bytes} bytes)")?;
    }
    if let Some(scene) = file.attachment("scene.toml").map_err(read_error)? {
        let text = String::from_utf8_lossy(&scene);
        let first: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty() && !l.starts_with('#')).take(3).collect();
        writeln!(out, "  scene.toml begins: {}", first.join(" | "))?;
    }
    Ok(out)
}

/// The aircraft a command reads from a Paparazzi log (`log import`, `validate`, `fit`): `ac_id`
/// if given, else the one that sent the most.
pub fn aircraft_of(
    log: &bridge::paparazzi::flightlog::FlightLog,
    ac_id: Option<u8>,
    file: &Path,
) -> anyhow::Result<u8> {
    match ac_id {
        Some(a) => Ok(a),
        None => log
            .busiest_sender()
            .ok_or_else(|| BadInput(anyhow::anyhow!("{}: no aircraft sent anything readable", file.display())).into()),
    }
}

/// `twinswarm log import`: a Paparazzi log as an MCAP log.
pub fn import(file: &Path, out: Option<&Path>, ac_id: Option<u8>) -> anyhow::Result<()> {
    let log = bridge::paparazzi::flightlog::FlightLog::open(file).map_err(|e| BadInput(e.into()))?;
    let ac_id = aircraft_of(&log, ac_id, file)?;
    let default_out;
    let out = match out {
        Some(o) => o,
        None => {
            default_out = std::path::PathBuf::from(file.with_extension("mcap").file_name().unwrap_or_default());
            &default_out
        }
    };
    // A unit the values contradict is said, never rescaled away.
    if let Some(w) = bridge::realflight::ir_unit_check(&log, ac_id) {
        eprintln!("warning: {}: {w}", file.display());
    }
    let command_line = std::env::args().collect::<Vec<_>>().join(" ");
    let s = bridge::log::import_flight(&log, ac_id, out, &command_line)?;
    outln!(
        "{}: {} lines ({} unreadable{}), aircraft {ac_id}: {} flights",
        file.display(),
        log.lines,
        log.errors.total(),
        if log.errors.total() > 0 { format!(": {:?}", log.errors.by_cause) } else { String::new() },
        s.flights.len()
    );
    for (k, f) in s.flights.iter().enumerate() {
        outln!("  flight {}: log {:.1}-{:.1} s ({:.1} s)", k + 1, f.start_s, f.end_s, f.duration_s());
    }
    outln!(
        "wrote {}: {} Paparazzi messages, {} states, {} sensor messages; arena {:.2} × {:.2} m (from the sonars)",
        out.display(),
        s.pprz_messages,
        s.states,
        s.sensors,
        s.arena_size_m[0],
        s.arena_size_m[1]
    );
    Ok(())
}

/// `twinswarm log merge -o OUT IN…`.
pub fn merge(inputs: &[std::path::PathBuf], out: &Path) -> anyhow::Result<()> {
    if inputs.iter().any(|i| i == out) {
        return Err(BadInput(anyhow::anyhow!("log merge: the output must differ from every input")).into());
    }
    let r = bridge::log::merge(inputs, out).map_err(read_error)?;
    let total: u64 = r.messages.values().sum();
    outln!(
        "{} logs -> {}: {} messages on {} topics, {} duplicates written once",
        inputs.len(),
        out.display(),
        total,
        r.messages.len(),
        r.duplicates
    );
    if r.shifts_ns.iter().any(|&s| s != 0) {
        outln!("  log times shifted onto the first log's epoch by {:?} ns", r.shifts_ns);
    }
    for (path, &n) in inputs.iter().zip(&r.undeclared).filter(|(_, n)| **n > 0) {
        outln!("  {n} messages of {} on channels it never declared: not written", path.display());
    }
    Ok(())
}

/// `twinswarm log recover BROKEN FIXED`.
pub fn recover(broken: &Path, fixed: &Path) -> anyhow::Result<()> {
    if broken == fixed {
        return Err(BadInput(anyhow::anyhow!("log recover: the output must differ from the input")).into());
    }
    let r = bridge::log::recover(broken, fixed).map_err(read_error)?;
    outln!(
        "{} -> {}: recovered {} messages on {} channels, {} schemas, {} attachments, {} metadata records",
        broken.display(),
        fixed.display(),
        r.total_messages(),
        r.channels,
        r.schemas,
        r.attachments,
        r.metadata
    );
    if let Some((a, b)) = r.time_range_ns {
        outln!("  log time span {:.2} s", (b - a) as f64 / 1e9);
    }
    for (topic, n) in &r.messages {
        outln!("    {topic:<18} {n:>10}");
    }
    match (&r.stopped_by, r.complete) {
        (_, true) => outln!("  the input was complete (its data section ended cleanly)"),
        (Some(why), false) => outln!("  the input was truncated; reading stopped at: {why}"),
        (None, false) => outln!("  the input ended without a data-end record"),
    }
    Ok(())
}
