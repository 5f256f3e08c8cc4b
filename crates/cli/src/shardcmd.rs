//! `twinswarm run SCENE --shard K/N` (one shard of a swarm: `sim_core::shard` steps it,
//! `bridge::shard` trades its ghosts; the rest of `run`, bus, log and live view, is the usual
//! one, for the shard's own copters) and `twinswarm cluster SCENE --shards N` (a Zenoh router
//! and N local shard processes: a launcher, not a scheduler).

use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use bridge::engine::LoopStats;
use bridge::shard::LinkStats;
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
        let per_step = |s: f64| s * 1e3 / l.totals.exchanges.max(1) as f64;
        println!(
            "    barrier: {:.3} ms per step (encode and send {:.2}, wait {:.2}, take in {:.2}; decode {:.2} on \
             Zenoh's threads; worst wait {:.1} ms); a batch {:.2} ms in transit (worst {:.1})",
            l.barrier_ms_per_step,
            per_step(l.totals.send_s),
            per_step(l.totals.wait_s),
            per_step(l.totals.take_s),
            per_step(l.totals.decode_s),
            l.totals.wait_max_s * 1e3,
            l.transit_ms_per_batch,
            l.totals.transit_max_s * 1e3,
        );
        println!(
            "    ghosts: {:.0} B sent per step, {} sent, {} received; {} of {} batches came in shared memory",
            l.bytes_sent_per_step,
            l.totals.ghosts_sent,
            l.totals.ghosts_received,
            l.totals.batches_in_shm,
            l.totals.batches_received
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
    /// [`LinkStats::transit_s`] per batch received, ms.
    pub transit_ms_per_batch: f64,
}

impl From<&LinkStats> for LinkStatsOut {
    fn from(s: &LinkStats) -> Self {
        let per = |v: f64| if s.exchanges == 0 { 0.0 } else { v / s.exchanges as f64 };
        Self {
            totals: s.clone(),
            bytes_sent_per_step: per(s.bytes_sent as f64),
            barrier_ms_per_step: per((s.send_s + s.wait_s + s.take_s) * 1e3),
            transit_ms_per_batch: s.transit_s * 1e3 / s.batches_timed.max(1) as f64,
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
    /// The shard process's CPU time over its run, s.
    #[serde(default)]
    pub cpu_s: Option<f64>,
    /// The simulated time it reached, s.
    #[serde(default)]
    pub sim_time_s: f64,
    /// The simulated time it stepped, s (from its checkpoint, after a restart): the cluster's
    /// CPU per simulated second divides by it.
    #[serde(default)]
    pub flown_s: f64,
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
    /// Each shard logs to `shard-K-of-N.mcap` here (`None`: no logs); after a restart R, to
    /// `shard-K-of-N.restart-R.mcap`.
    pub log_dir: Option<PathBuf>,
    /// Shards without the client bus.
    pub no_bus: bool,
    /// Checkpoints every so many simulated seconds, and a shard that dies restarts the
    /// cluster from the last one all shards have (`None`: a shard that dies stops the run).
    pub checkpoint_every_s: Option<f64>,
    /// Where the checkpoints go.
    pub checkpoint_dir: PathBuf,
    /// At most this many restarts; then a shard that dies stops the run.
    pub max_restarts: u32,
}

/// A restart of the cluster after a shard died.
#[derive(Debug, Clone, Serialize)]
pub struct Restart {
    /// The shard that died.
    pub shard: usize,
    /// How (exit status, or killed).
    pub status: String,
    /// The last lines of its stderr.
    pub error: String,
    /// The tick every shard went on from (0: from the start, no checkpoint all had).
    pub from_tick: u64,
    /// Seconds into the cluster's run.
    pub at_wall_s: f64,
}

/// The merged summary of a cluster.
#[derive(Debug, Serialize)]
pub struct ClusterSummary {
    pub shards: usize,
    pub router: String,
    pub wall_s: f64,
    /// The slowest shard's (its last segment's).
    pub real_time_factor: f64,
    pub copters_count: usize,
    pub crashed: usize,
    /// [`swarm_digest`] over every shard's copters.
    pub digest: String,
    /// Every copter, in id order, as its shard had it at the end.
    pub copters: Vec<CopterEnd>,
    /// Restarts after a shard died, in order.
    pub restarts: Vec<Restart>,
    /// Each shard's summary (of its last segment, after restarts).
    pub per_shard: Vec<ShardRun>,
    /// The launcher's own CPU time while the last segment's shards ran (its Zenoh router, which
    /// carries the ghosts between the shards), s: its start-up, earlier segments and the merging
    /// of the summaries apart.
    pub launcher_cpu_s: Option<f64>,
    /// CPU seconds per simulated second, the shards' (of the last segment) and the launcher's
    /// together, per simulated second of that segment. Beside one process's `cpu_per_sim_s` on
    /// the same scene, what the split costs in work, whatever the cores' waits.
    pub cpu_per_sim_s: Option<f64>,
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

/// The cluster's fixed parts: router endpoint, prefix, log epoch, this binary.
struct Launch<'a> {
    opts: &'a ClusterRun,
    exe: PathBuf,
    endpoint: String,
    prefix: String,
    epoch_ns: String,
}

/// One set of N shard processes (the first, or one after a restart), their output read on
/// threads (a full pipe would block a shard).
struct Segment {
    children: Vec<std::process::Child>,
    readers: Vec<std::thread::JoinHandle<(String, String)>>,
    logs: Vec<PathBuf>,
}

/// How a segment ended.
struct Ended {
    status: Vec<Option<std::process::ExitStatus>>,
    outputs: Vec<(String, String)>,
    /// The first shard that failed.
    failed: Option<usize>,
}

/// Starts a Zenoh router on a free loopback port and `shards` shard processes of this binary
/// connected to it, waits for all of them and merges their summaries. A shard that fails
/// stops the others (they would only wait for it until the barrier timeout). With
/// checkpoints, the cluster then starts all N again from the last checkpoint every shard has
/// (at most `max_restarts` times).
pub fn run_cluster(opts: &ClusterRun, stop: &Arc<AtomicBool>) -> anyhow::Result<ClusterSummary> {
    let port = free_port()?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let router = zenoh::open(router_config(std::slice::from_ref(&endpoint), &[])?)
        .wait()
        .map_err(|e| anyhow::anyhow!("cannot start the Zenoh router on {endpoint}: {e}"))?;
    let launch = Launch {
        opts,
        exe: std::env::current_exe().context("cannot find this binary to start the shards")?,
        prefix: format!("twinswarm/cluster-{port}"),
        endpoint,
        epoch_ns: bridge::log::now_unix_ns().to_string(),
    };
    if opts.checkpoint_every_s.is_some() {
        clear_checkpoints(&opts.checkpoint_dir, opts.shards)?;
    }
    let start = Instant::now();
    let mut restarts: Vec<Restart> = Vec::new();
    let mut from: Option<(u64, Vec<PathBuf>)> = None;
    // The launcher's CPU while the last segment's shards run (its router carrying the ghosts),
    // as their own CPU is the last segment's: not its start-up, the restarts before, nor the
    // merging (like `run`'s `cpu_s`, the step loop's).
    let (ended, cpu_at_start) = loop {
        let cpu_at_start = bridge::process_cpu_s();
        let segment = launch.start(restarts.len(), from.as_ref())?;
        let logs = segment.logs.clone();
        let ended = segment.wait(stop);
        let Some(k) = ended.failed else { break (ended, cpu_at_start) };
        let can_restart = opts.checkpoint_every_s.is_some() && restarts.len() < opts.max_restarts as usize;
        if !can_restart || stop.load(Ordering::Relaxed) {
            break (ended, cpu_at_start);
        }
        recover_logs(&logs);
        launch.wait_for_tokens_gone(&router);
        from = restart_point(&opts.checkpoint_dir, opts.shards)?;
        let r = Restart {
            shard: k,
            status: ended.status[k].map_or("killed".into(), |s| s.to_string()),
            error: last_lines(&ended.outputs[k].1, 5),
            from_tick: from.as_ref().map_or(0, |f| f.0),
            at_wall_s: start.elapsed().as_secs_f64(),
        };
        eprintln!(
            "cluster: shard {k}/{} died ({}); restarting all {} shards from tick {} (restart {} of at most {})",
            opts.shards,
            r.status,
            opts.shards,
            r.from_tick,
            restarts.len() + 1,
            opts.max_restarts
        );
        restarts.push(r);
    };
    let launcher_cpu_s = bridge::process_cpu_s().zip(cpu_at_start).map(|(end, start)| end - start);
    let _ = router.close().wait();
    summarise(opts, launch.endpoint, ended, restarts, (start, launcher_cpu_s), stop)
}

impl Launch<'_> {
    /// The command of shard `k` in segment `segment`, going on from `resume` if given.
    fn command(&self, k: usize, segment: usize, resume: Option<&PathBuf>) -> (std::process::Command, Option<PathBuf>) {
        let opts = self.opts;
        let n = opts.shards;
        let mut cmd = std::process::Command::new(&self.exe);
        cmd.arg("run");
        if let Some(s) = &opts.scene {
            cmd.arg(s);
        }
        cmd.args(["--shard", &format!("{k}/{n}"), "--connect", &self.endpoint, "--prefix", &self.prefix, "--json"]);
        let log = opts.log_dir.as_ref().map(|dir| match segment {
            0 => dir.join(format!("shard-{k}-of-{n}.mcap")),
            r => dir.join(format!("shard-{k}-of-{n}.restart-{r}.mcap")),
        });
        match &log {
            Some(path) => cmd.arg("--log").arg(path),
            None => cmd.arg("--no-log"),
        };
        cmd.args(["--barrier-timeout", &opts.timeout_s.to_string()]);
        if let Some(every) = opts.checkpoint_every_s {
            cmd.args(["--checkpoint-every", &every.to_string()]).arg("--checkpoint-dir").arg(&opts.checkpoint_dir);
        }
        if let Some(file) = resume {
            cmd.arg("--resume").arg(file);
        }
        let flags =
            [(opts.duration.map(|d| d.to_string()), "--duration"), (opts.seed.map(|s| s.to_string()), "--seed")];
        let threads = opts.threads.map(|t| t.to_string());
        for (value, flag) in flags.into_iter().chain([(threads, "--threads")]) {
            if let Some(v) = value {
                cmd.args([flag, &v]);
            }
        }
        if opts.realtime {
            cmd.arg("--realtime");
        }
        if opts.no_bus {
            cmd.arg("--no-bus");
        }
        cmd.env(twinswarm::logcmd::LOG_EPOCH_ENV, &self.epoch_ns);
        cmd.stdout(std::process::Stdio::piped()).stderr(std::process::Stdio::piped());
        (cmd, log)
    }

    /// Starts every shard, from the checkpoints in `from` (tick, one file per shard) if given.
    /// Each shard's pid goes to stderr.
    fn start(&self, segment: usize, from: Option<&(u64, Vec<PathBuf>)>) -> anyhow::Result<Segment> {
        let n = self.opts.shards;
        let mut seg = Segment { children: Vec::new(), readers: Vec::new(), logs: Vec::new() };
        for k in 0..n {
            let (mut cmd, log) = self.command(k, segment, from.map(|f| &f.1[k]));
            let mut child = cmd.spawn().with_context(|| format!("cannot start shard {k}"))?;
            eprintln!(
                "cluster: shard {k}/{n} started, pid {} (segment {segment}, from tick {})",
                child.id(),
                from.map_or(0, |f| f.0)
            );
            let (mut out, mut err) = (child.stdout.take(), child.stderr.take());
            seg.readers.push(std::thread::spawn(move || {
                let (mut o, mut e) = (String::new(), String::new());
                // A pipe that fails to read leaves what was read: the summary or the error
                // check below then says so.
                if let Some(out) = out.as_mut() {
                    let _ = out.read_to_string(&mut o);
                }
                if let Some(err) = err.as_mut() {
                    let _ = err.read_to_string(&mut e);
                }
                (o, e)
            }));
            seg.children.push(child);
            seg.logs.extend(log);
        }
        Ok(seg)
    }

    /// Waits (at most 10 s) until the router no longer holds a liveliness token of a shard of
    /// this cluster: the shards just killed are gone before their successors look for
    /// neighbours.
    fn wait_for_tokens_gone(&self, router: &zenoh::Session) {
        let key = format!("{}/shard/alive/*", self.prefix);
        let deadline = Instant::now() + Duration::from_secs(10);
        while Instant::now() < deadline {
            let alive = match router.liveliness().get(&key).timeout(Duration::from_millis(500)).wait() {
                Ok(replies) => replies.iter().filter(|r| r.result().is_ok()).count(),
                Err(_) => 0,
            };
            if alive == 0 {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        tracing::warn!("cluster: shard tokens still held by the router after 10 s; starting anyway");
    }
}

impl Segment {
    /// Waits for every shard; the first that fails (or a stop) kills the others.
    fn wait(mut self, stop: &AtomicBool) -> Ended {
        let n = self.children.len();
        let mut status: Vec<Option<std::process::ExitStatus>> = vec![None; n];
        let mut failed: Option<usize> = None;
        while status.iter().any(Option::is_none) {
            for (k, ch) in self.children.iter_mut().enumerate() {
                if status[k].is_none()
                    && let Ok(Some(s)) = ch.try_wait()
                {
                    status[k] = Some(s);
                    if !s.success() && failed.is_none() {
                        failed = Some(k);
                    }
                }
            }
            if failed.is_some() || stop.load(Ordering::Relaxed) {
                for (k, ch) in self.children.iter_mut().enumerate() {
                    if status[k].is_none() {
                        // Already gone if this fails; `wait` reaps it either way.
                        let _ = ch.kill();
                        status[k] = ch.wait().ok();
                    }
                }
                break;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let outputs = self.readers.into_iter().map(|r| r.join().unwrap_or_default()).collect();
        Ended { status, outputs, failed }
    }
}

/// The last tick for which every shard has a checkpoint, and those files (`None`: there is no
/// such tick; the shards start again from the beginning).
fn restart_point(dir: &Path, shards: usize) -> anyhow::Result<Option<(u64, Vec<PathBuf>)>> {
    let mut per_shard = Vec::new();
    for k in 0..shards {
        let stem = bridge::engine::checkpoint::RunKey { shard: Some((k as u16, shards as u16)), ..key_stub() }.stem();
        per_shard.push(bridge::engine::checkpoint::list(dir, &stem)?);
    }
    let common =
        per_shard[0].iter().rev().map(|(t, _)| *t).find(|t| per_shard.iter().all(|l| l.iter().any(|(u, _)| u == t)));
    Ok(common.map(|t| {
        let files =
            per_shard.iter().map(|l| l.iter().find(|(u, _)| *u == t).map(|(_, p)| p.clone()).unwrap_or_default());
        (t, files.collect())
    }))
}

/// Removes the checkpoints of an earlier cluster of this layout from `dir`: a restart must
/// only find this run's.
fn clear_checkpoints(dir: &Path, shards: usize) -> anyhow::Result<()> {
    for k in 0..shards {
        let stem = bridge::engine::checkpoint::RunKey { shard: Some((k as u16, shards as u16)), ..key_stub() }.stem();
        for (_, path) in bridge::engine::checkpoint::list(dir, &stem)? {
            std::fs::remove_file(&path)
                .with_context(|| format!("cannot remove the old checkpoint {}", path.display()))?;
        }
    }
    Ok(())
}

/// A key whose only use is its [`bridge::engine::checkpoint::RunKey::stem`].
fn key_stub() -> bridge::engine::checkpoint::RunKey {
    bridge::engine::checkpoint::RunKey { version: String::new(), scene: 0, seed: 0, copters: 0, shard: None }
}

/// The logs of shards that were killed are torn: each is made whole again (`log recover`) in
/// place, so that `log merge` takes every file of the directory. A log that cannot be made
/// whole is moved aside (`.damaged`) and said so.
fn recover_logs(logs: &[PathBuf]) {
    for path in logs {
        if !path.exists() || bridge::log::LogFile::open(path).is_ok() {
            continue;
        }
        let fixed = path.with_extension("recovered.mcap");
        let outcome = bridge::log::recover(path, &fixed).map_err(anyhow::Error::new).and_then(|_| {
            std::fs::rename(&fixed, path).with_context(|| format!("cannot move {} over it", fixed.display()))
        });
        if let Err(e) = outcome {
            let aside = path.with_extension("mcap.damaged");
            let moved = std::fs::rename(path, &aside)
                .map_or_else(|e| format!("not moved: {e}"), |_| format!("moved to {}", aside.display()));
            eprintln!("cluster: the log {} of a killed shard cannot be recovered ({e:#}); {moved}", path.display());
        }
    }
}

/// The last `n` lines of `text`.
fn last_lines(text: &str, n: usize) -> String {
    let lines: Vec<&str> = text.trim().lines().collect();
    lines[lines.len().saturating_sub(n)..].join("\n")
}

/// The cluster's summary from its last segment's shard summaries, or the error of the shard
/// that failed.
fn summarise(
    opts: &ClusterRun,
    router: String,
    ended: Ended,
    restarts: Vec<Restart>,
    (start, launcher_cpu_s): (Instant, Option<f64>),
    stop: &AtomicBool,
) -> anyhow::Result<ClusterSummary> {
    let Ended { status, outputs, failed } = ended;
    if let Some(k) = failed {
        let err = outputs[k].1.trim();
        let after = match restarts.len() {
            0 => String::new(),
            r => format!(" after {r} restart(s)"),
        };
        anyhow::bail!(
            "shard {k}/{} failed ({}){after}; the others were stopped:\n{err}",
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
    let shards_cpu_s: Option<f64> = per_shard.iter().map(|s| s.cpu_s).sum();
    let sim_s = per_shard.iter().map(|s| s.flown_s).fold(f64::INFINITY, f64::min);
    let cpu_per_sim_s = shards_cpu_s.zip(launcher_cpu_s).map(|(a, b)| (a + b) / sim_s).filter(|r| r.is_finite());
    Ok(ClusterSummary {
        shards: opts.shards,
        router,
        wall_s: start.elapsed().as_secs_f64(),
        real_time_factor: per_shard.iter().map(|s| s.real_time_factor).fold(f64::INFINITY, f64::min),
        copters_count: all.len(),
        crashed: all.iter().filter(|c| c.crashed).count(),
        digest,
        copters: all,
        restarts,
        per_shard,
        launcher_cpu_s,
        cpu_per_sim_s,
    })
}
