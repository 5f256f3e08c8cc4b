//! `twinswarm run SCENE --shard K/N` (one shard of a swarm: `sim_core::shard` steps it,
//! `bridge::shard` trades its ghosts; the rest of `run`, bus, log and live view, is the usual
//! one, for the shard's own copters) and `twinswarm cluster SCENE --shards N` (a Zenoh router
//! and N local shard processes: a launcher, not a scheduler).

use std::io::Read;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use bridge::shard::LinkStats;
use bridge::sim::LoopStats;
use serde::{Deserialize, Serialize};
use sim_core::shard::Role;
use sim_core::{CopterState, State};
use zenoh::Wait;

/// `K/N`: shard K of N.
pub fn parse_shard(s: &str) -> Result<(usize, usize), String> {
    let (k, n) = s.split_once('/').ok_or_else(|| format!("{s:?} is not K/N (e.g. 0/4)"))?;
    let k: usize = k.trim().parse().map_err(|e| format!("{s:?}: shard {k:?}: {e}"))?;
    let n: usize = n.trim().parse().map_err(|e| format!("{s:?}: count {n:?}: {e}"))?;
    if n == 0 || k >= n {
        return Err(format!("{s:?}: K must be in 0..N and N at least 1"));
    }
    Ok((k, n))
}

/// A shard's part of the run summary (`--json`: `shard`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ShardSection {
    pub shard: usize,
    pub shards: usize,
    pub grid: [u16; 2],
    pub halo_m: f32,
    pub owned_at_end: usize,
    pub ghosts_at_end: usize,
    /// Copters that came to this shard from another during the run.
    pub taken_over: u64,
    /// Why it stopped early, if it did.
    pub error: Option<String>,
    pub link: Option<LinkStatsOut>,
}

/// The shard section of a run's summary, if the run was a shard.
pub fn section(state: &State, stats: &LoopStats, link: Option<&LinkStats>) -> Option<ShardSection> {
    let view = state.shard()?;
    let (nx, ny) = view.partition.grid();
    Some(ShardSection {
        shard: usize::from(view.me),
        shards: view.partition.shards(),
        grid: [nx, ny],
        halo_m: view.partition.halo_m(),
        owned_at_end: view.roles.iter().filter(|r| **r == Role::Owned).count(),
        ghosts_at_end: view.roles.iter().filter(|r| matches!(r, Role::Ghost | Role::Far)).count(),
        taken_over: stats.shard_taken_over,
        error: stats.shard_error.clone(),
        link: link.map(LinkStatsOut::from),
    })
}

/// Prints a shard's section: aggregates only.
pub fn print_section(s: &ShardSection) {
    println!(
        "  shard {}/{} (regions {}x{}, halo {:.1} m): owns {} copters at the end, sees {} ghosts, took over {} during the run",
        s.shard, s.shards, s.grid[0], s.grid[1], s.halo_m, s.owned_at_end, s.ghosts_at_end, s.taken_over
    );
    if let Some(l) = &s.link {
        println!(
            "    barrier: {:.3} ms per step (worst wait {:.1} ms); ghosts: {:.0} B sent per step, {} sent, {} received",
            l.barrier_ms_per_step,
            l.totals.wait_max_s * 1e3,
            l.bytes_sent_per_step,
            l.totals.ghosts_sent,
            l.totals.ghosts_received
        );
    }
}

/// [`LinkStats`] with per-step figures.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LinkStatsOut {
    #[serde(flatten)]
    pub totals: LinkStats,
    pub bytes_sent_per_step: f64,
    pub barrier_ms_per_step: f64,
}

impl From<&LinkStats> for LinkStatsOut {
    fn from(s: &LinkStats) -> Self {
        let per = |v: f64| if s.exchanges == 0 { 0.0 } else { v / s.exchanges as f64 };
        Self {
            totals: s.clone(),
            bytes_sent_per_step: per(s.bytes_sent as f64),
            barrier_ms_per_step: per((s.wait_s + s.send_s) * 1e3),
        }
    }
}

/// A copter's digest ([`CopterState::digest`]) as the summaries print it.
pub fn copter_digest(c: &CopterState) -> String {
    format!("{:016x}", c.digest())
}

fn fnv(bytes: impl IntoIterator<Item = u8>) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in bytes {
        h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// One copter of a run's summary, as `cluster` reads it.
#[derive(Debug, Clone, Deserialize, Serialize)]
pub struct CopterEnd {
    pub id: usize,
    pub crashed: bool,
    pub digest: String,
}

/// One digest over every copter's `(id, digest)`, in id order: the swarm's fingerprint.
pub fn swarm_digest(copters: &mut [CopterEnd]) -> String {
    copters.sort_by_key(|c| c.id);
    let bytes = copters
        .iter()
        .flat_map(|c| (c.id as u64).to_le_bytes().into_iter().chain(c.digest.bytes().collect::<Vec<_>>()));
    format!("{:016x}", fnv(bytes))
}

/// What `cluster` reads of each shard's run summary.
#[derive(Debug, Clone, Deserialize, Serialize)]
pub struct ShardRun {
    pub real_time_factor: f64,
    pub wall_time_s: f64,
    pub shard: ShardSection,
    #[serde(skip_serializing)]
    pub copters: Vec<CopterEnd>,
}

/// What `cluster` is told.
#[derive(Debug, Clone)]
pub struct ClusterRun {
    pub scene: Option<PathBuf>,
    pub shards: usize,
    pub duration: Option<f64>,
    pub seed: Option<u64>,
    pub threads: Option<usize>,
    pub timeout_s: f64,
    pub realtime: bool,
    /// Each shard logs to `shard-K-of-N.mcap` here (`None`: no logs).
    pub log_dir: Option<PathBuf>,
    /// Shards without the client bus.
    pub no_bus: bool,
}

/// The merged summary of a cluster.
#[derive(Debug, Serialize)]
pub struct ClusterSummary {
    pub shards: usize,
    pub router: String,
    pub wall_s: f64,
    /// The slowest shard's.
    pub real_time_factor: f64,
    pub copters_count: usize,
    pub crashed: usize,
    /// [`swarm_digest`] over every shard's copters.
    pub digest: String,
    /// Every copter, in id order, as its shard had it at the end.
    pub copters: Vec<CopterEnd>,
    pub per_shard: Vec<ShardRun>,
}

/// A Zenoh router's configuration: listening and connecting where told, multicast scouting
/// off.
pub fn router_config(listen: &[String], connect: &[String]) -> anyhow::Result<zenoh::Config> {
    Ok(bridge::zenoh_net::node::config("router", listen, connect)?)
}

/// A free TCP port on 127.0.0.1.
fn free_port() -> anyhow::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

/// Starts a Zenoh router on a free loopback port and `shards` shard processes of this binary
/// connected to it, waits for all of them and merges their summaries. A shard that fails
/// stops the others (they would only wait for it until the barrier timeout).
pub fn run_cluster(opts: &ClusterRun, stop: &Arc<AtomicBool>) -> anyhow::Result<ClusterSummary> {
    let port = free_port()?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let router = zenoh::open(router_config(std::slice::from_ref(&endpoint), &[])?)
        .wait()
        .map_err(|e| anyhow::anyhow!("cannot start the Zenoh router on {endpoint}: {e}"))?;
    let exe = std::env::current_exe().context("cannot find this binary to start the shards")?;
    let start = Instant::now();
    let prefix = format!("twinswarm/cluster-{port}");
    let mut children = Vec::new();
    let epoch_ns = bridge::log::now_unix_ns().to_string();
    for k in 0..opts.shards {
        let mut cmd = std::process::Command::new(&exe);
        cmd.arg("run");
        if let Some(s) = &opts.scene {
            cmd.arg(s);
        }
        cmd.args(["--shard", &format!("{k}/{}", opts.shards), "--connect", &endpoint, "--prefix", &prefix, "--json"]);
        match &opts.log_dir {
            Some(dir) => cmd.arg("--log").arg(dir.join(format!("shard-{k}-of-{}.mcap", opts.shards))),
            None => cmd.arg("--no-log"),
        };
        cmd.args(["--barrier-timeout", &opts.timeout_s.to_string()]);
        if let Some(d) = opts.duration {
            cmd.args(["--duration", &d.to_string()]);
        }
        if let Some(s) = opts.seed {
            cmd.args(["--seed", &s.to_string()]);
        }
        if let Some(t) = opts.threads {
            cmd.args(["--threads", &t.to_string()]);
        }
        if opts.realtime {
            cmd.arg("--realtime");
        }
        if opts.no_bus {
            cmd.arg("--no-bus");
        }
        cmd.env(twinswarm::logcmd::LOG_EPOCH_ENV, &epoch_ns);
        cmd.stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::piped());
        children.push(cmd.spawn().with_context(|| format!("cannot start shard {k}"))?);
    }
    // Read each child's output on its own thread (a full pipe would block it).
    let readers: Vec<_> = children
        .iter_mut()
        .map(|ch| {
            let (mut out, mut err) = (ch.stdout.take(), ch.stderr.take());
            std::thread::spawn(move || {
                let (mut o, mut e) = (String::new(), String::new());
                if let Some(out) = out.as_mut() {
                    let _ = out.read_to_string(&mut o);
                }
                if let Some(err) = err.as_mut() {
                    let _ = err.read_to_string(&mut e);
                }
                (o, e)
            })
        })
        .collect();
    let mut status: Vec<Option<std::process::ExitStatus>> = vec![None; opts.shards];
    let mut failed: Option<usize> = None;
    while status.iter().any(Option::is_none) {
        for (k, ch) in children.iter_mut().enumerate() {
            if status[k].is_none()
                && let Some(s) = ch.try_wait()?
            {
                status[k] = Some(s);
                if !s.success() && failed.is_none() {
                    failed = Some(k);
                }
            }
        }
        if failed.is_some() || stop.load(Ordering::Relaxed) {
            for (k, ch) in children.iter_mut().enumerate() {
                if status[k].is_none() {
                    let _ = ch.kill();
                    status[k] = ch.wait().ok();
                }
            }
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let outputs: Vec<(String, String)> = readers.into_iter().map(|r| r.join().unwrap_or_default()).collect();
    let _ = router.close().wait();
    if let Some(k) = failed {
        let err = outputs[k].1.trim();
        anyhow::bail!(
            "shard {k}/{} failed ({}); the others were stopped:\n{err}",
            opts.shards,
            status[k].map_or("killed".into(), |s| s.to_string())
        );
    }
    if stop.load(Ordering::Relaxed) {
        anyhow::bail!("stopped by a signal; the shards were stopped");
    }
    let mut per_shard = Vec::new();
    for (k, (out, err)) in outputs.iter().enumerate() {
        let s: ShardRun = serde_json::from_str(out.trim())
            .with_context(|| format!("shard {k} printed no summary; its stderr:\n{}", err.trim()))?;
        per_shard.push(s);
    }
    let mut all: Vec<CopterEnd> = per_shard.iter().flat_map(|s| s.copters.iter().cloned()).collect();
    let digest = swarm_digest(&mut all);
    Ok(ClusterSummary {
        shards: opts.shards,
        router: endpoint,
        wall_s: start.elapsed().as_secs_f64(),
        real_time_factor: per_shard.iter().map(|s| s.real_time_factor).fold(f64::INFINITY, f64::min),
        copters_count: all.len(),
        crashed: all.iter().filter(|c| c.crashed).count(),
        digest,
        copters: all,
        per_shard,
    })
}
