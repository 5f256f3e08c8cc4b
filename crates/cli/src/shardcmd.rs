//! `twinswarm run SCENE --shard K/N` (one shard of a swarm, see `sim_core::shard` and
//! `bridge::shard`) and `twinswarm cluster SCENE --shards N` (a Zenoh router and N local shard
//! processes: a launcher, not a scheduler).

use std::io::Read;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use bridge::shard::{LinkStats, ShardLink};
use serde::{Deserialize, Serialize};
use sim_core::shard::{Partition, Role};
use sim_core::{CopterState, State, World, step_into};
use twinswarm::BadInput;
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

/// What a shard run is told.
#[derive(Debug, Clone)]
pub struct ShardRun {
    pub shard: usize,
    pub shards: usize,
    pub ticks: u64,
    pub realtime: bool,
    pub connect: Vec<String>,
    pub listen: Vec<String>,
    pub prefix: String,
    pub timeout: Duration,
}

/// One copter at the end, as its owner had it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CopterEnd {
    pub id: usize,
    pub name: String,
    pub crashed: bool,
    /// FNV-1a over the bits of its motion, rotor speeds, battery charge, crash and the next
    /// draw of its random stream: equal digests, equal copters.
    pub digest: String,
}

/// A shard's summary (`--json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ShardSummary {
    pub shard: usize,
    pub shards: usize,
    pub grid: [u16; 2],
    pub halo_m: f32,
    pub ticks: u64,
    pub sim_s: f64,
    pub wall_s: f64,
    pub real_time_factor: f64,
    /// Time in `step`, s (the rest is the barrier and ghosts).
    pub step_s: f64,
    pub owned_at_end: usize,
    pub ghosts_at_end: usize,
    /// Copters that came to this shard from another during the run.
    pub taken_over: u64,
    pub link: Option<LinkStatsOut>,
    pub copters: Vec<CopterEnd>,
}

/// [`LinkStats`] with per-step figures.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LinkStatsOut {
    pub exchanges: u64,
    pub wait_s: f64,
    pub wait_max_s: f64,
    pub send_s: f64,
    pub ghosts_sent: u64,
    pub ghosts_received: u64,
    pub bytes_sent: u64,
    pub bytes_received: u64,
    pub bytes_sent_per_step: f64,
    pub barrier_ms_per_step: f64,
}

impl From<&LinkStats> for LinkStatsOut {
    fn from(s: &LinkStats) -> Self {
        let per = |v: f64| if s.exchanges == 0 { 0.0 } else { v / s.exchanges as f64 };
        Self {
            exchanges: s.exchanges,
            wait_s: s.wait_s,
            wait_max_s: s.wait_max_s,
            send_s: s.send_s,
            ghosts_sent: s.ghosts_sent,
            ghosts_received: s.ghosts_received,
            bytes_sent: s.bytes_sent,
            bytes_received: s.bytes_received,
            bytes_sent_per_step: per(s.bytes_sent as f64),
            barrier_ms_per_step: per((s.wait_s + s.send_s) * 1e3),
        }
    }
}

/// The digest of one copter (see [`CopterEnd::digest`]).
pub fn copter_digest(c: &CopterState) -> u64 {
    let m = &c.motion;
    let mut bits: Vec<u32> =
        [m.pos_m, m.vel_m_s, m.angvel_rad_s].iter().flat_map(|v| v.to_array()).map(f32::to_bits).collect();
    bits.extend(m.rot.to_array().map(f32::to_bits));
    bits.extend(c.rotor_speed_rad_s.map(f32::to_bits));
    bits.push(c.battery.charge.to_bits());
    bits.push(u32::from(c.crash.is_some()));
    bits.push(c.rng.clone().uniform().to_bits());
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in bits.iter().flat_map(|b| b.to_le_bytes()) {
        h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// Zenoh configuration of a shard, multicast scouting off: a client of the router it connects
/// to, or, with `--listen`, a peer listening there.
fn shard_config(listen: &[String], connect: &[String]) -> anyhow::Result<zenoh::Config> {
    let mut c = zenoh::Config::default();
    let set =
        |c: &mut zenoh::Config, k: &str, v: String| c.insert_json5(k, &v).map_err(|e| anyhow::anyhow!("{k}: {e}"));
    let mode = if listen.is_empty() { "\"client\"" } else { "\"peer\"" };
    set(&mut c, "mode", mode.into())?;
    set(&mut c, "scouting/multicast/enabled", "false".into())?;
    set(&mut c, "listen/endpoints", serde_json::to_string(listen)?)?;
    set(&mut c, "connect/endpoints", serde_json::to_string(connect)?)?;
    Ok(c)
}

/// Steps one shard of `world` to the end, trading ghosts with its neighbours every step.
pub fn run_shard(world: &World, opts: &ShardRun, stop: &Arc<AtomicBool>) -> anyhow::Result<ShardSummary> {
    let partition = Partition::new(world, opts.shards).map_err(|e| BadInput(e.into()))?;
    let mut state = world.initial_state();
    state.make_shard(partition.clone(), opts.shard).map_err(|e| BadInput(e.into()))?;
    let me = opts.shard as u16;
    let neighbours = partition.neighbours(me);
    let mut link = if neighbours.is_empty() {
        None
    } else {
        if opts.connect.is_empty() && opts.listen.is_empty() {
            return Err(BadInput(anyhow::anyhow!(
                "--shard {}/{}: a shard with neighbours needs --connect (a Zenoh router) or --listen",
                opts.shard,
                opts.shards
            ))
            .into());
        }
        let config = shard_config(&opts.listen, &opts.connect)?;
        let count = neighbours.len();
        let mut link = ShardLink::open(config, &opts.prefix, me, neighbours, opts.timeout)?;
        link.wait_for_neighbours()?;
        eprintln!("shard {}/{}: {count} neighbour(s) up, stepping", opts.shard, opts.shards);
        Some(link)
    };
    let inputs = world.initial_inputs();
    let mut report = sim_core::StepReport::default();
    let dt = world.params.control_dt_s;
    let start = Instant::now();
    let mut step_s = 0.0;
    let mut taken_over = 0u64;
    let mut owned: Vec<bool> = (0..world.copters.len()).map(|i| state.owns(i)).collect();
    let result = (|| -> anyhow::Result<()> {
        for _ in 0..opts.ticks {
            if stop.load(Ordering::Relaxed) {
                anyhow::bail!("stopped by a signal at tick {}", state.tick);
            }
            if let Some(link) = &mut link {
                link.exchange(&mut state)?;
            }
            let t0 = Instant::now();
            step_into(world, &mut state, &inputs, &mut report);
            step_s += t0.elapsed().as_secs_f64();
            if report.shard_violations > 0 {
                anyhow::bail!(
                    "shard {}: at tick {} {} copter(s) were in a contact cluster or wake wider than the halo \
                     ({:.1} m) allows: the run would no longer be the one-process run",
                    opts.shard,
                    report.tick,
                    report.shard_violations,
                    partition.halo_m()
                );
            }
            for (i, o) in owned.iter_mut().enumerate() {
                let now = state.owns(i);
                taken_over += u64::from(now && !*o);
                *o = now;
            }
            if opts.realtime {
                let due = start + Duration::from_secs_f64(state.tick as f64 * dt);
                if let Some(wait) = due.checked_duration_since(Instant::now()) {
                    std::thread::sleep(wait);
                }
            }
        }
        Ok(())
    })();
    let wall_s = start.elapsed().as_secs_f64();
    let link_stats = link.as_ref().map(|l| LinkStatsOut::from(l.stats()));
    if let Some(link) = link {
        // Closing withdraws the token: neighbours still waiting learn that this shard is gone.
        link.close()?;
    }
    result?;
    Ok(summary(world, &state, &partition, opts, wall_s, step_s, taken_over, link_stats))
}

#[allow(clippy::too_many_arguments)]
fn summary(
    world: &World,
    state: &State,
    partition: &Partition,
    opts: &ShardRun,
    wall_s: f64,
    step_s: f64,
    taken_over: u64,
    link: Option<LinkStatsOut>,
) -> ShardSummary {
    let view = state.shard();
    let roles = view.map(|v| &v.roles[..]).unwrap_or(&[]);
    let sim_s = world.time_at(state.tick);
    let (nx, ny) = partition.grid();
    ShardSummary {
        shard: opts.shard,
        shards: opts.shards,
        grid: [nx, ny],
        halo_m: partition.halo_m(),
        ticks: state.tick,
        sim_s,
        wall_s,
        real_time_factor: if wall_s > 0.0 { sim_s / wall_s } else { 0.0 },
        step_s,
        owned_at_end: roles.iter().filter(|r| **r == Role::Owned).count(),
        ghosts_at_end: roles.iter().filter(|r| **r == Role::Ghost).count(),
        taken_over,
        link,
        copters: (0..world.copters.len())
            .filter(|&i| state.owns(i))
            .map(|i| CopterEnd {
                id: i,
                name: world.copters[i].name.clone(),
                crashed: state.copters[i].crash.is_some(),
                digest: format!("{:016x}", copter_digest(&state.copters[i])),
            })
            .collect(),
    }
}

/// One digest over every copter's, in id order: the run's fingerprint.
pub fn swarm_digest(copters: &mut [CopterEnd]) -> String {
    copters.sort_by_key(|c| c.id);
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for c in copters.iter() {
        for b in (c.id as u64).to_le_bytes().into_iter().chain(c.digest.bytes()) {
            h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    format!("{h:016x}")
}

/// Prints a shard's summary: aggregates only.
pub fn print_shard(s: &ShardSummary) {
    let crashed = s.copters.iter().filter(|c| c.crashed).count();
    println!(
        "shard {}/{} (grid {}x{}, halo {:.1} m): {} steps, {:.1} s simulated in {:.2} s ({:.2}x real time, {:.2} s stepping)",
        s.shard, s.shards, s.grid[0], s.grid[1], s.halo_m, s.ticks, s.sim_s, s.wall_s, s.real_time_factor, s.step_s
    );
    println!(
        "  owns {} copters at the end ({} crashed), {} ghosts, took over {} during the run",
        s.owned_at_end, crashed, s.ghosts_at_end, s.taken_over
    );
    if let Some(l) = &s.link {
        println!(
            "  barrier: {:.3} ms per step (worst wait {:.1} ms); ghosts: {:.0} B sent per step, {} sent, {} received",
            l.barrier_ms_per_step,
            l.wait_max_s * 1e3,
            l.bytes_sent_per_step,
            l.ghosts_sent,
            l.ghosts_received
        );
    }
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
}

/// The merged summary of a cluster.
#[derive(Debug, Serialize)]
pub struct ClusterSummary {
    pub shards: usize,
    pub router: String,
    pub wall_s: f64,
    /// The slowest shard's.
    pub real_time_factor: f64,
    pub copters: usize,
    pub crashed: usize,
    /// [`swarm_digest`] over every shard's copters.
    pub digest: String,
    pub per_shard: Vec<ShardSummary>,
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
    let mut c = zenoh::Config::default();
    let set =
        |c: &mut zenoh::Config, k: &str, v: String| c.insert_json5(k, &v).map_err(|e| anyhow::anyhow!("{k}: {e}"));
    set(&mut c, "mode", "\"router\"".into())?;
    set(&mut c, "scouting/multicast/enabled", "false".into())?;
    set(&mut c, "listen/endpoints", serde_json::to_string(&[&endpoint])?)?;
    set(&mut c, "connect/endpoints", "[]".into())?;
    let router =
        zenoh::open(c).wait().map_err(|e| anyhow::anyhow!("cannot start the Zenoh router on {endpoint}: {e}"))?;
    let exe = std::env::current_exe().context("cannot find this binary to start the shards")?;
    let start = Instant::now();
    let prefix = format!("twinswarm/cluster-{port}");
    let mut children = Vec::new();
    for k in 0..opts.shards {
        let mut cmd = std::process::Command::new(&exe);
        cmd.arg("run");
        if let Some(s) = &opts.scene {
            cmd.arg(s);
        }
        cmd.args(["--shard", &format!("{k}/{}", opts.shards), "--connect", &endpoint, "--prefix", &prefix, "--json"]);
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
        let s: ShardSummary = serde_json::from_str(out.trim())
            .with_context(|| format!("shard {k} printed no summary; its stderr:\n{}", err.trim()))?;
        per_shard.push(s);
    }
    let mut all: Vec<CopterEnd> = per_shard.iter().flat_map(|s| s.copters.clone()).collect();
    let digest = swarm_digest(&mut all);
    Ok(ClusterSummary {
        shards: opts.shards,
        router: endpoint,
        wall_s: start.elapsed().as_secs_f64(),
        real_time_factor: per_shard.iter().map(|s| s.real_time_factor).fold(f64::INFINITY, f64::min),
        copters: all.len(),
        crashed: all.iter().filter(|c| c.crashed).count(),
        digest,
        per_shard,
    })
}
