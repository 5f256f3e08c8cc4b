//! `twinswarm ivy`: the Ivy tools Paparazzi users reach for, on the project's own Ivy agent.
//!
//! - `ivy probe REGEX...` binds each regex (sent to peers as is, as `ivyprobe` does) and
//!   prints the groups of every message, and peers joining and leaving;
//! - `ivy send TEXT...` joins, waits for the peers' regexes, sends each text and says how many
//!   peer regexes it matched;
//! - `ivy peers` joins, waits, and lists the agents on the bus with their regexes.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use bridge::paparazzi::ivy::{BusAddr, IvyAgent, IvyOptions};

use crate::BadInput;

/// Arguments of `twinswarm ivy`.
#[derive(Debug, clap::Args)]
pub struct IvyToolArgs {
    #[command(subcommand)]
    command: IvyCommand,
    /// The Ivy bus (`127.255.255.255:2010`, `127:2010`); default: `IVYBUS`, else
    /// 127.255.255.255:2010.
    #[arg(long, short = 'b', value_name = "ADDR:PORT", global = true)]
    bus: Option<String>,
    /// Agent name on the bus.
    #[arg(long, value_name = "NAME", global = true, default_value = "twinswarm-ivy")]
    name: String,
}

#[derive(Debug, clap::Subcommand)]
enum IvyCommand {
    /// Print what matches the regexes, like ivyprobe.
    Probe {
        /// Regexes (in the peers' syntax; Paparazzi's start with `^`).
        #[arg(required = true)]
        regex: Vec<String>,
        /// Stop after this many seconds (default: until Ctrl-C).
        #[arg(long, value_name = "S")]
        duration: Option<f64>,
        /// Stop after this many messages.
        #[arg(long, value_name = "N")]
        count: Option<u64>,
    },
    /// Send texts.
    Send {
        /// Texts, e.g. `ground_dl VIRTUAL_SONAR 5 120 65535 87 300`.
        #[arg(required = true)]
        text: Vec<String>,
        /// Wait this long for peers and their regexes before sending, s.
        #[arg(long, value_name = "S", default_value_t = 1.0)]
        wait: f64,
        /// Send each text this many times, as fast as possible, and report the rate (a load
        /// test; bounded to 10 million).
        #[arg(long, value_name = "N", default_value_t = 1)]
        repeat: u64,
    },
    /// List the agents on the bus and their regexes.
    Peers {
        /// Wait this long for peers, s.
        #[arg(long, value_name = "S", default_value_t = 1.0)]
        wait: f64,
        /// Print JSON.
        #[arg(long)]
        json: bool,
    },
}

fn seconds(s: f64, what: &str) -> anyhow::Result<Duration> {
    if !s.is_finite() || !(0.0..=86_400.0).contains(&s) {
        return Err(BadInput(anyhow::anyhow!("{what} must be in [0, 86400] s, got {s}")).into());
    }
    Ok(Duration::from_secs_f64(s))
}

/// Runs `twinswarm ivy`.
pub fn run(args: IvyToolArgs) -> anyhow::Result<()> {
    let addr = BusAddr::from_env_or(args.bus.as_deref()).map_err(|e| BadInput(e.into()))?;
    let stop = crate::logcmd::install_stop_flag()?;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let mut opts = IvyOptions::new(addr.clone(), args.name.clone());
    opts.on_die = Some(stop.clone());
    let agent = rt.block_on(IvyAgent::start(opts)).with_context(|| format!("cannot join the Ivy bus {addr}"))?;
    let result = match args.command {
        IvyCommand::Probe { regex, duration, count } => probe(&rt, &agent, &regex, duration, count, &stop),
        IvyCommand::Send { text, wait, repeat } => send(&rt, &agent, &text, wait, repeat),
        IvyCommand::Peers { wait, json } => peers(&rt, &agent, wait, json),
    };
    rt.block_on(agent.stop());
    result
}

fn probe(
    rt: &tokio::runtime::Runtime,
    agent: &IvyAgent,
    regexes: &[String],
    duration: Option<f64>,
    count: Option<u64>,
    stop: &Arc<AtomicBool>,
) -> anyhow::Result<()> {
    let duration = duration.map(|d| seconds(d, "--duration")).transpose()?;
    let seen = Arc::new(std::sync::atomic::AtomicU64::new(0));
    for r in regexes {
        let (r2, seen) = (r.clone(), seen.clone());
        let id = agent
            .bind_raw(r, move |groups| {
                if count.is_some_and(|c| seen.load(Ordering::Relaxed) >= c) {
                    return;
                }
                let quoted: Vec<String> = groups.iter().map(|g| format!("'{g}'")).collect();
                outln!("[{r2}] {}", quoted.join(" "));
                seen.fetch_add(1, Ordering::Relaxed);
            })
            .map_err(|e| BadInput(anyhow::anyhow!("regex `{r}`: {e}")))?;
        eprintln!("bound {id}: {r}");
    }
    let started = Instant::now();
    let mut events_shown = 0;
    while !stop.load(Ordering::Relaxed)
        && duration.is_none_or(|d| started.elapsed() < d)
        && count.is_none_or(|c| seen.load(Ordering::Relaxed) < c)
    {
        rt.block_on(async { tokio::time::sleep(Duration::from_millis(50)).await });
        let events = agent.events();
        for e in &events[events_shown..] {
            eprintln!(
                "{} {}{}",
                e.app_name,
                e.what,
                if e.why.is_empty() { String::new() } else { format!(" ({})", e.why) }
            );
        }
        events_shown = events.len();
    }
    Ok(())
}

fn send(
    rt: &tokio::runtime::Runtime,
    agent: &IvyAgent,
    texts: &[String],
    wait: f64,
    repeat: u64,
) -> anyhow::Result<()> {
    if !(1..=10_000_000).contains(&repeat) {
        return Err(BadInput(anyhow::anyhow!("--repeat must be in 1..=10000000, got {repeat}")).into());
    }
    let wait_for = seconds(wait, "--wait")?;
    rt.block_on(async { tokio::time::sleep(wait_for).await });
    for t in texts {
        let started = Instant::now();
        let mut n = 0;
        for _ in 0..repeat {
            n = agent.send(t).map_err(|e| BadInput(anyhow::anyhow!("`{t}`: {e}")))?;
        }
        if repeat > 1 {
            let s = started.elapsed().as_secs_f64();
            outln!("{n} peer regex(es) matched, {repeat} times in {s:.3} s ({:.0} texts/s): {t}", repeat as f64 / s);
        } else {
            outln!("{n} peer regex(es) matched: {t}");
        }
    }
    let dropped: u64 = agent.drops().iter().filter(|(k, _)| k.starts_with("peer not reading")).map(|(_, v)| v).sum();
    if dropped > 0 {
        outln!("{dropped} messages dropped: a peer did not read fast enough");
    }
    // Let the writers flush.
    rt.block_on(async { tokio::time::sleep(Duration::from_millis(300)).await });
    Ok(())
}

fn peers(rt: &tokio::runtime::Runtime, agent: &IvyAgent, wait: f64, json: bool) -> anyhow::Result<()> {
    let wait_for = seconds(wait, "--wait")?;
    rt.block_on(async { tokio::time::sleep(wait_for).await });
    let peers = agent.peers();
    if json {
        outln!("{}", serde_json::to_string_pretty(&peers)?);
        return Ok(());
    }
    if peers.is_empty() {
        outln!("no agent on the bus answered within {wait} s");
    }
    for p in &peers {
        outln!(
            "{} at {} (tcp port {}){}",
            p.app_name,
            p.addr,
            p.port,
            if p.ready { "" } else { ", handshake incomplete" }
        );
        for (id, r) in &p.regexes {
            outln!("  {id:>4}  {r}");
        }
        for (id, r) in &p.refused {
            outln!("  {id:>4}  {r}   (refused: not a regex this agent can run)");
        }
    }
    Ok(())
}
