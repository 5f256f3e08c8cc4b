//! `twinswarm run`: a short composition of the engine's parts. Arguments become a world, bus
//! options and a pace; a [`Recorder`] (log, live view) and a [`RunWatch`] (summary, progress)
//! follow the [`bridge::engine::flight::Flight`] that [`runner::run`] flies; the summary is printed
//! last.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use bridge::engine::checkpoint::{self, Checkpoint, CheckpointError, CheckpointOptions, RunKey};
use bridge::engine::failsafe::{ClientLostAction, FailsafeOptions};
use bridge::engine::flight::Recorder;
use bridge::engine::{Finished, LockstepOptions};
use bridge::live::LiveServer;
use sim_core::World;
use sim_core::scene::{self, SceneSpec};
use twinswarm::transport::{self, IvyArgs, ZenohArgs};
use twinswarm::{BadInput, logcmd};

use crate::runner::{self, Pace, RunOutcome};
use crate::{report, shardcmd};

#[derive(Debug, clap::Args)]
#[command(mut_arg("ivy", |a| a.help(transport::ivy_help(IVY_PURPOSE))))]
pub(crate) struct RunArgs {
    /// Step only shard K of N of the swarm (a region of the arena), trading ghosts with the
    /// other shards over Zenoh (`--connect` to their router). Each shard logs its own copters
    /// (`log merge` joins the shards' logs) and publishes them on the client bus.
    #[arg(long, value_name = "K/N", value_parser = shardcmd::parse_shard)]
    shard: Option<(usize, usize)>,
    /// Also be the ROS 2 node `/twinswarm` on the Zenoh session, as rmw_zenoh (Jazzy) sees
    /// nodes: per copter `/<c>/pose`, `odom`, `imu`, `sonar/<side>`, `ir`, `battery`, and
    /// `/clock`, `/tf`, `/tf_static`, `/arena`; it takes `/<c>/cmd_vel` and `/<c>/goal_pose`
    /// (docs/ros2.md).
    #[arg(long)]
    ros2: bool,
    /// With `--ros2`: the ROS domain (`ROS_DOMAIN_ID`).
    #[arg(long, value_name = "N", default_value_t = 0, requires = "ros2")]
    ros_domain: u32,
    /// With `--ros2`: send pose, odometry, IMU and tf at most HZ times per simulated second
    /// (default: every control step).
    #[arg(long, value_name = "HZ", requires = "ros2")]
    ros2_rate: Option<f64>,
    /// With `--shard`: stop with an error when a neighbouring shard stays silent this long, s.
    #[arg(long, value_name = "S", default_value_t = 30.0)]
    barrier_timeout: f64,
    /// With `--shard`: when a neighbouring shard's liveliness token goes away, `stop` with an
    /// error (every log finished), or `hold` at the barrier until it is back (a router
    /// restarting, a network partition), for at most `--barrier-timeout`.
    #[arg(long, value_name = "WHAT", default_value = "stop")]
    on_shard_lost: OnShardLost,
    /// Write a checkpoint every S simulated seconds into `--checkpoint-dir`: at the tick
    /// multiples of round(S / control dt), after the step, the same ticks in every shard; the
    /// newest two per shard are kept. Needs `--checkpoint-dir`. Not with `--ivy`, `--pairing`
    /// or twins (their state between steps is not saved).
    #[arg(long, value_name = "S", requires = "checkpoint_dir")]
    checkpoint_every: Option<f64>,
    /// Where `--checkpoint-every` writes: DIR/shard-K-of-N-tick-T.ckpt (DIR/run-tick-T.ckpt
    /// for one process), atomically (a temporary file, fsync, rename).
    #[arg(long, value_name = "DIR")]
    checkpoint_dir: Option<PathBuf>,
    /// Go on from this checkpoint to the end of `--duration`, with the same bits as the
    /// uninterrupted run. It must be of the same scene, seed and `--shard K/N` (else it is
    /// refused, naming the file). The log, a new file, continues the checkpointed run's time
    /// base (unless TWINSWARM_LOG_EPOCH_NS is set) from the step after the checkpoint.
    #[arg(long, value_name = "FILE.ckpt")]
    resume: Option<PathBuf>,
    /// The scene file (TOML); default: the embedded FINken lab.
    scene: Option<PathBuf>,
    /// Simulated duration, s (default: the scene's `sim.duration_s`).
    #[arg(long, value_name = "S")]
    duration: Option<f64>,
    /// Seed of all random draws (default: the scene's `sim.seed`).
    #[arg(long, value_name = "N")]
    seed: Option<u64>,
    /// Pace control steps against the wall clock (1 simulated second per second). With
    /// `--lockstep`: a step runs at its deadline or when every answer is in, whichever is
    /// later (slow controllers show as overruns).
    #[arg(long)]
    realtime: bool,
    /// Lockstep with external controllers (docs/lockstep.md): each step waits until every
    /// copter claimed over Zenoh has answered the last state with a command carrying its
    /// `tick`, or until `--lockstep-timeout`. Same seed, same answers: the same bits.
    #[arg(long)]
    lockstep: bool,
    /// With `--lockstep`: how long a step waits for the answers, s; a controller that misses
    /// it is counted and logged, and its copter keeps its last command.
    #[arg(long, value_name = "S", default_value_t = 1.0)]
    lockstep_timeout: f64,
    /// With `--lockstep`: hold the first step until these copters are claimed, so that a run
    /// is reproducible from its start.
    #[arg(long, value_name = "COPTER,...", value_delimiter = ',')]
    wait_claims: Vec<String>,
    /// Where copters of kind `autopilot` wait for their outside autopilots (Paparazzi NPS
    /// with Twinswarm's flight model, `TWINSWARM_FDM`; docs/paparazzi.md). Each step then
    /// waits for every autopilot's motor commands, and nothing waits on the wall clock.
    /// ADDR:PORT over TCP, or unix:PATH, a Unix-domain socket (faster, both on one machine;
    /// `unix` alone: a fresh one in a temporary folder, printed; removed at the end).
    #[arg(long, value_name = "ADDR:PORT|unix:PATH", default_value = bridge::autopilot::DEFAULT_LISTEN)]
    autopilot_listen: bridge::autopilot::Listen,
    /// How long the first step waits for every autopilot to connect, s.
    #[arg(long, value_name = "S", default_value_t = 60.0)]
    autopilot_timeout: f64,
    /// Worker threads of a step (default: the scene's `sim.threads`); results are the same
    /// bits for any count.
    #[arg(long, value_name = "N")]
    threads: Option<usize>,
    /// Print the summary as JSON on stdout.
    #[arg(long)]
    json: bool,
    /// Log to this MCAP file (default: runs/<scene name>-<UTC timestamp>.mcap).
    #[arg(long, value_name = "FILE", conflicts_with = "no_log")]
    log: Option<PathBuf>,
    /// Do not write a log.
    #[arg(long)]
    no_log: bool,
    /// Run without Zenoh (with `--ivy`, on the Ivy bus alone).
    #[arg(long)]
    no_bus: bool,
    /// `--ivy`, `--ivy-bus`: Paparazzi's ground segment, with or without Zenoh.
    #[command(flatten)]
    ivy: IvyArgs,
    /// `--zenoh-config`, `--listen`, `--connect`, `--prefix`.
    #[command(flatten)]
    zenoh: ZenohArgs,
    /// Pairing file (XML): real aircraft and their twins, virtual aircraft, spawn rules.
    #[arg(long, value_name = "FILE.xml")]
    pairing: Option<PathBuf>,
    /// Paparazzi telemetry file for virtual copters (default: the embedded
    /// assets/paparazzi/telemetry.xml).
    #[arg(long, value_name = "FILE.xml")]
    telemetry: Option<PathBuf>,
    /// Mode of the telemetry file (default: its first mode).
    #[arg(long, value_name = "NAME")]
    telemetry_mode: Option<String>,
    /// Period of the virtual sonar readings sent to each real copter, s (default: every sonar
    /// update of its twin).
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    virtual_sonar_period: f64,
    /// A lab's Paparazzi messages.xml, or a Paparazzi server log (NAME.log) whose definitions
    /// to use (default: the embedded assets/paparazzi/messages.xml):
    /// it decodes real copters' telemetry, encodes virtual copters' and chooses each twin's
    /// virtual-sonar uplink (SONAR_UPLINK or VIRTUAL_SONAR, whichever its datalink class has).
    #[arg(long, value_name = "FILE.xml")]
    messages: Option<PathBuf>,
    /// The virtual-sonar uplink of one aircraft, AC_ID=sonar_uplink|virtual_sonar|none
    /// (repeatable; default: the one the messages.xml defines).
    #[arg(long, value_name = "AC_ID=KIND", value_parser = crate::parse_uplink)]
    uplink: Vec<(u8, bridge::paparazzi::convert::Uplink)>,
    /// Which telemetry sets twins' attitude targets: `setpoint` (FINKEN_ACTUATORS_SET_POINT,
    /// what the real copter asks for) or `measured` (ATTITUDE, AHRS_EULER_INT, what it does).
    /// Either way a twin falls back, source by source, on what its aircraft sends.
    #[arg(long, value_name = "SOURCE", default_value = "setpoint", value_parser = crate::parse_twin_attitude)]
    twin_attitude: bridge::mixed::interpreter::TwinAttitude,
    /// How twins are kept where their real copters are: `medusa` (the real copter's sonars and
    /// yaw), `tracking` (poses on …/copters/<name>/tracking), both, or `off` (command
    /// prediction only).
    #[arg(long, value_name = "SOURCES", default_value = "medusa,tracking")]
    sync: String,
    /// Lag of the tracking poses, s.
    #[arg(long, value_name = "S", default_value_t = 0.2)]
    tracking_lag: f64,
    /// A twin whose telemetry stays silent this long levels out and holds its height, s (or four
    /// of its aircraft's own telemetry periods, as they arrive, if that is longer).
    #[arg(long, value_name = "S", default_value_t = FailsafeOptions::default().hold_after_s)]
    link_hold: f64,
    /// A twin whose telemetry stays silent this long descends and lands, s.
    #[arg(long, value_name = "S", default_value_t = FailsafeOptions::default().land_after_s)]
    link_land: f64,
    /// Descent rate of a failsafe landing, m/s.
    #[arg(long, value_name = "M_S", default_value_t = FailsafeOptions::default().descent_m_s)]
    descent: f32,
    /// What a virtual copter does when the client controlling it over Zenoh disappears:
    /// `hover` where it is, `land`, or go back to its `scene` command.
    #[arg(long, value_name = "ACTION", default_value = "hover")]
    on_client_lost: ClientLostAction,
    /// When the log cannot be written (disk full, file-size limit): `stop` the run (exit code
    /// 1), or `continue` flying without a log. Either way the file keeps what was written,
    /// readable after `twinswarm log recover`.
    #[arg(long, value_name = "WHAT", default_value = "stop")]
    on_log_error: OnLogError,
    /// Log the per-step messages (state, sensors, command, control, transforms) at this rate,
    /// Hz, instead of every control step (20 Hz); events, log lines and bus traffic are always
    /// logged. E.g. `--log-rate 5` cuts a file to a quarter.
    #[arg(long, value_name = "HZ")]
    log_rate: Option<f64>,
    /// The log's zstd level, 1–19, fixed for the whole run. 3 by default; 2 writes files 3–14 %
    /// larger (less where many wrecks are held) for about a quarter less of the writer's CPU,
    /// for fast runs of large swarms that must not wait for their log (see docs/logging.md's
    /// logging figures).
    #[arg(long, value_name = "L", default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=19))]
    log_zstd_level: u32,
    /// A copter whose logged values have not changed since its last message (a wreck at rest:
    /// its sensors stop) is written again only every this many seconds, and a reader holds its
    /// last message until then; 0 writes every copter at every logged step.
    #[arg(long, value_name = "SECONDS", default_value_t = 1.0)]
    log_unchanged: f64,
    /// Serve a live view on the Foxglove WebSocket protocol at ADDR (default
    /// 127.0.0.1:8765): in Foxglove, "Open connection", "Foxglove WebSocket",
    /// ws://ADDR. The same channels as the log; a slow client loses messages (counted), the
    /// run never waits for it.
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = bridge::live::DEFAULT_ADDR)]
    foxglove: Option<String>,
}

/// What `run --ivy` does on the bus.
const IVY_PURPOSE: &str = "Join a Paparazzi Ivy bus as agent `Twinswarm`: real aircraft's telemetry from `link` drives \
                           their twins, VIRTUAL_SONAR goes back, virtual copters send telemetry; with Zenoh on, texts \
                           are bridged both ways";

/// `--on-shard-lost`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum OnShardLost {
    /// Stop with an error.
    Stop,
    /// Hold at the barrier until the neighbour is back.
    Hold,
}

/// `--on-log-error`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum OnLogError {
    Stop,
    Continue,
}

/// `twinswarm run`.
pub(crate) fn run(args: RunArgs) -> anyhow::Result<()> {
    let (origin, world, mixed) = prepare_world(&args)?;
    let bus = bus_options(&args, mixed)?;
    let pace = pace(&args, &world)?;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let live = start_live(&args, &rt)?;
    let resume = load_resume(&args, &world)?;
    let epoch_ns = resume.as_ref().and_then(|c| c.log_epoch_ns);
    let mut log = start_log(&args, &world, &origin, live.clone(), epoch_ns)?;
    let durability = durability(&args, &world, resume, log.as_mut())?;
    let stop = logcmd::install_stop_flag()?;
    let recorder = Recorder::new(log, (args.on_log_error == OnLogError::Stop).then(|| stop.clone()));
    let watch = RunWatch::new(&world, progress_bar(&args, pace.ticks));
    let (started, cpu_at_start) = (Instant::now(), bridge::process_cpu_s());
    let outcome = runner::run(&rt, world, &pace, &bus, durability, recorder, watch, stop)?;
    let wall_s = started.elapsed().as_secs_f64();
    let cpu_s = bridge::process_cpu_s().zip(cpu_at_start).map(|(end, start)| end - start);
    report_run(&args, &origin, outcome, live, (wall_s, cpu_s))
}

/// The scene with the command line's seed, threads, duration and pairing applied, compiled;
/// and the mixed-reality options.
fn prepare_world(args: &RunArgs) -> anyhow::Result<(String, World, runner::MixedOptions)> {
    let (origin, mut spec, _) = crate::load_scene(args.scene.as_deref())?;
    if let Some(seed) = args.seed {
        spec.sim.seed = seed;
    }
    if let Some(n) = args.threads {
        if !(1..=256).contains(&n) {
            return Err(BadInput(anyhow::anyhow!("--threads must be 1 to 256, got {n}")).into());
        }
        spec.sim.threads = n;
    }
    if let Some(d) = args.duration {
        if !d.is_finite() || d <= 0.0 {
            return Err(BadInput(anyhow::anyhow!("--duration must be a positive number of seconds, got {d}")).into());
        }
        spec.sim.duration_s = d;
    }
    if args.shard.is_some() {
        check_shardable(args, &spec)?;
    }
    check_checkpointable(args, &spec)?;
    let mixed = crate::load_mixed(
        args.pairing.as_deref(),
        args.telemetry.as_deref(),
        args.telemetry_mode.as_deref(),
        args.virtual_sonar_period,
    )?;
    let mixed = runner::MixedOptions {
        messages: crate::load_messages(args.messages.as_deref())?,
        uplinks: args.uplink.iter().copied().collect(),
        twin_attitude: args.twin_attitude,
        sync: crate::parse_sync(&args.sync, args.tracking_lag)?,
        ..mixed
    };
    if let (Some(p), Some(path)) = (&mixed.pairing, &args.pairing) {
        bridge::mixed::router::apply_pairing(&mut spec, p)
            .map_err(|e| BadInput(anyhow::anyhow!("{}: {e}", path.display())))?;
    }
    let world = scene::compile(&spec).map_err(|e| {
        let e = anyhow::Error::new(e);
        let e = match &args.pairing {
            Some(p) => e.context(format!("{origin} with the copters of pairing {}", p.display())),
            None => e,
        };
        anyhow::Error::new(BadInput(e))
    })?;
    Ok((origin, world, mixed))
}

/// Zenoh, Ivy, failsafe and shard options.
fn bus_options(args: &RunArgs, mixed: runner::MixedOptions) -> anyhow::Result<runner::BusOptions> {
    let failsafe = FailsafeOptions {
        hold_after_s: args.link_hold,
        land_after_s: args.link_land,
        descent_m_s: args.descent,
        client_lost: args.on_client_lost,
    };
    failsafe.validate().map_err(|e| BadInput(anyhow::anyhow!("--link-hold/--link-land/--descent: {e}")))?;
    let ivy = args.ivy.bus()?;
    if args.ros2 && args.no_bus {
        return Err(BadInput(anyhow::anyhow!(
            "--ros2 needs the Zenoh bus: ROS 2 nodes reach it over Zenoh (drop --no-bus)"
        ))
        .into());
    }
    if let Some(hz) = args.ros2_rate
        && !(hz.is_finite() && hz > 0.0)
    {
        return Err(BadInput(anyhow::anyhow!(
            "--ros2-rate must be a positive number of messages per second, got {hz}"
        ))
        .into());
    }
    if args.ros_domain > 232 {
        return Err(BadInput(anyhow::anyhow!(
            "--ros-domain must be 0 to 232 (ROS 2's domain ids), got {}",
            args.ros_domain
        ))
        .into());
    }
    Ok(runner::BusOptions {
        ros2: args.ros2.then_some(bridge::ros2::Ros2Options { domain: args.ros_domain, max_rate_hz: args.ros2_rate }),
        ivy,
        no_bus: args.no_bus,
        zenoh: args.zenoh.clone(),
        mixed,
        failsafe,
        shard: args.shard.map(|(shard, shards)| runner::ShardOptions {
            shard,
            shards,
            timeout: Duration::from_secs_f64(args.barrier_timeout),
            on_lost: match args.on_shard_lost {
                OnShardLost::Stop => bridge::shard::OnLost::Stop,
                OnShardLost::Hold => bridge::shard::OnLost::Hold,
            },
        }),
    })
}

/// How long, and how: free running, real time, lockstep.
fn pace(args: &RunArgs, world: &World) -> anyhow::Result<Pace> {
    let bad = |m: String| anyhow::Error::new(BadInput(anyhow::anyhow!(m)));
    let lockstep = match args.lockstep {
        false if !args.wait_claims.is_empty() => return Err(bad("--wait-claims needs --lockstep".into())),
        false => None,
        true => {
            if args.no_bus {
                return Err(bad(
                    "--lockstep needs the Zenoh bus: its controllers answer over it (drop --no-bus)".into()
                ));
            }
            if args.shard.is_some() {
                return Err(bad("--lockstep is not available for a shard yet".into()));
            }
            let t = args.lockstep_timeout;
            if !(t.is_finite() && t > 0.0 && t <= 3600.0) {
                return Err(bad(format!("--lockstep-timeout must be in (0, 3600] s, got {t}")));
            }
            for name in &args.wait_claims {
                match world.copter_id(name) {
                    None => return Err(bad(format!("--wait-claims: no copter named {name:?} in the scene"))),
                    Some(id) if world.copters[id].kind == sim_core::CopterKind::Real => {
                        return Err(bad(format!(
                            "--wait-claims: {name:?} is a twin: its real copter sets its pace, not a controller"
                        )));
                    }
                    Some(_) => {}
                }
            }
            Some(LockstepOptions { timeout: Duration::from_secs_f64(t), wait_claims: args.wait_claims.clone() })
        }
    };
    let autopilots = world.copters.iter().any(|c| c.kind == sim_core::CopterKind::Autopilot);
    let autopilots = match autopilots {
        false => None,
        true if args.shard.is_some() => {
            return Err(bad("--shard: scenes with autopilot copters need one process for now".into()));
        }
        true => {
            let t = args.autopilot_timeout;
            if !(t.is_finite() && t > 0.0 && t <= 3600.0) {
                return Err(bad(format!("--autopilot-timeout must be in (0, 3600] s, got {t}")));
            }
            Some(bridge::autopilot::AutopilotOptions {
                listen: args.autopilot_listen.clone(),
                connect_timeout: Duration::from_secs_f64(t),
                ..Default::default()
            })
        }
    };
    Ok(Pace { ticks: world.default_ticks(), realtime: args.realtime, lockstep, autopilots })
}

/// `--foxglove`: the live view's server.
fn start_live(args: &RunArgs, rt: &tokio::runtime::Runtime) -> anyhow::Result<Option<Arc<LiveServer>>> {
    let Some(a) = &args.foxglove else { return Ok(None) };
    let addr: std::net::SocketAddr = a
        .parse()
        .map_err(|e| BadInput(anyhow::anyhow!("--foxglove: {a:?} is not an address like 127.0.0.1:8765: {e}")))?;
    let server = LiveServer::start(addr, "twinswarm", rt.handle())
        .with_context(|| format!("--foxglove: cannot listen on {addr}"))?;
    if !args.json {
        eprintln!("live view: ws://{} (Foxglove: Open connection, Foxglove WebSocket)", server.local_addr());
    }
    Ok(Some(Arc::new(server)))
}

/// The run's log (and the live view's feed), as the log options say.
fn start_log(
    args: &RunArgs,
    world: &World,
    origin: &str,
    live: Option<Arc<LiveServer>>,
    epoch_ns: Option<u64>,
) -> anyhow::Result<Option<bridge::log::Logger>> {
    let every_ticks = match args.log_rate {
        None => 1,
        Some(hz) => bridge::log::LogOptions::every_ticks_for_rate(hz, world.params.control_dt_s)
            .ok_or_else(|| BadInput(anyhow::anyhow!("--log-rate: {hz} is not a positive rate in Hz")))?,
    };
    if !(args.log_unchanged.is_finite() && args.log_unchanged >= 0.0) {
        return Err(BadInput(anyhow::anyhow!(
            "--log-unchanged: {} is not a number of seconds (0 or more)",
            args.log_unchanged
        ))
        .into());
    }
    let options = bridge::log::LogOptions {
        every_ticks,
        zstd_level: args.log_zstd_level,
        unchanged_every_s: args.log_unchanged,
        ..Default::default()
    };
    let scene = args.scene.as_deref();
    logcmd::start_run_log(args.log.as_deref(), args.no_log, options, world, scene, origin, live, epoch_ns)
}

fn progress_bar(args: &RunArgs, ticks: u64) -> Option<indicatif::ProgressBar> {
    (!args.json && !args.realtime && std::io::stderr().is_terminal()).then(|| {
        let bar = indicatif::ProgressBar::new(ticks);
        bar.set_style(
            indicatif::ProgressStyle::with_template("{spinner} [{bar:40}] {pos}/{len} steps  {per_sec}  eta {eta}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        bar
    })
}

/// Why a run stopped before its end.
fn stop_reason(stats: &bridge::engine::LoopStats) -> &'static str {
    if stats.shard_error.is_some() {
        "stopped by its shard link (the error follows)"
    } else if stats.checkpoint_error.is_some() {
        "stopped: a checkpoint could not be written (the error follows)"
    } else {
        "interrupted by a signal or a stop request"
    }
}

/// Finishes the log and prints the summary; the run's error, if any, comes last.
fn report_run(
    args: &RunArgs,
    origin: &str,
    outcome: RunOutcome<RunWatch>,
    live: Option<Arc<LiveServer>>,
    (wall_s, cpu_s): (f64, Option<f64>),
) -> anyhow::Result<()> {
    let RunOutcome { end, bus, link } = outcome;
    let Finished { world, state, stats, recorder, watch } = end;
    let RunWatch { tracker, failsafe_events, progress } = watch;
    if let Some(bar) = progress {
        bar.finish_and_clear();
    }
    let log_path = recorder.path().map(|p| p.to_owned());
    let (mut log, log_error) = recorder.into_parts();
    let interrupted = (stats.stopped_early && log_error.is_none()).then_some(state.tick);
    let why = stop_reason(&stats);
    if let (Some(l), Some(b)) = (&mut log, &bus) {
        // The drop counts belong in the log too: what never reached the loop is only there.
        let mut detail = serde_json::to_value(b)?;
        detail["inputs"] = inputs_json(&stats);
        let event = bridge::log::LogEvent {
            tick: state.tick,
            kind: bridge::log::EventKind::BusReport,
            copter: None,
            message: format!(
                "bus: {} commands accepted, {} rejected, {} inputs dropped (queue full), {} telemetry texts dropped",
                b.commands_accepted, b.commands_rejected, b.requests_dropped, b.telemetry.queue_full
            ),
            detail: Some(detail),
        };
        if let Err(e) = l.log_event(event) {
            tracing::warn!("could not log the bus report: {e}");
        }
    }
    let log_stats = logcmd::finish_run_log(log, interrupted.map(|t| (t, why)))?;
    let live_stats = live.as_ref().map(|l| l.stats());
    drop(live);
    let log_error = log_error.map(|(tick, e)| {
        let path = log_path.as_ref().map_or("the log".to_owned(), |p| p.display().to_string());
        let what = match args.on_log_error {
            OnLogError::Stop => format!("the run stopped at control step {tick}"),
            OnLogError::Continue => format!("the run went on without a log from control step {tick} to {}", state.tick),
        };
        anyhow::Error::new(e).context(format!(
            "logging failed at control step {tick}; {what}. {path} holds what was written before the failure: \
             `twinswarm log recover {path} FIXED.mcap` makes it a complete log"
        ))
    });
    let summary = tracker.summary(&world, &state, origin, (wall_s, cpu_s), stats.steps, stats.overruns);
    let shard = shardcmd::section(&state, &stats, link.as_ref());
    if args.json {
        let mut json = serde_json::to_value(&summary)?;
        json["log"] = log_stats.as_ref().map_or(serde_json::Value::Null, |l| l.path.display().to_string().into());
        json["live"] = serde_json::to_value(&live_stats)?;
        json["interrupted"] = interrupted.is_some().into();
        json["bus"] = serde_json::to_value(&bus)?;
        json["frames_dropped"] = stats.frames_dropped.into();
        json["twins"] = serde_json::to_value(&stats.twins)?;
        json["sync"] = serde_json::to_value(&stats.sync)?;
        json["pprz_sent"] = stats.pprz_sent.into();
        json["failsafe"] = serde_json::to_value(&stats.failsafe)?;
        json["inputs"] = inputs_json(&stats);
        json["lockstep"] = serde_json::to_value(&stats.lockstep)?;
        json["autopilots"] = serde_json::to_value(&stats.autopilots)?;
        json["autopilots_refused"] = serde_json::to_value(&stats.autopilots_refused)?;
        json["autopilot_wait_s"] = stats.autopilot_wait_s.into();
        json["log_error"] = log_error.as_ref().map_or(serde_json::Value::Null, |e| format!("{e:#}").into());
        json["shard"] = serde_json::to_value(shard)?;
        json["checkpoints"] = checkpoints_json(args, &stats);
        outln!("{}", serde_json::to_string_pretty(&json)?);
    } else {
        out!("{}", summary.to_text());
        if let Some(s) = &shard {
            shardcmd::print_section(s);
        }
        if let Some(last) = &stats.last_checkpoint {
            outln!("  checkpoints: {} written, the last {}", stats.checkpoints_written, last.display());
        }
        outln!("  log: {}", log_stats.as_ref().map_or("off (--no-log)".into(), logcmd::describe));
        print_live(live_stats.as_ref());
        print_bus(bus.as_ref(), &stats);
        print_inputs(&stats, &failsafe_events);
        if interrupted.is_some() {
            outln!("  {why} after {:.2} s simulated; the log was finished cleanly", state.time_s(&world));
        }
    }
    if let Some(e) = &stats.checkpoint_error {
        anyhow::bail!("stopped at control step {}: {e}", state.tick);
    }
    if let Some(e) = &stats.shard_error {
        // The log and the summary hold everything up to here.
        anyhow::bail!("shard stopped at control step {}: {e}", state.tick);
    }
    match log_error {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

/// `--json`'s `checkpoints`: written, the last one, and the one this run went on from.
fn checkpoints_json(args: &RunArgs, stats: &bridge::engine::LoopStats) -> serde_json::Value {
    serde_json::json!({
        "written": stats.checkpoints_written,
        "last": stats.last_checkpoint.as_ref().map(|p| p.display().to_string()),
        "resumed_from": args.resume.as_ref().map(|p| p.display().to_string()),
    })
}

/// The live view's line of the text summary.
fn print_live(live_stats: Option<&bridge::live::LiveStats>) {
    if let Some(l) = live_stats {
        outln!(
            "  live view: ws://{}; {} clients, {} subscriptions, {} messages sent, {} dropped (slow clients), {} steps skipped (encoder behind), {} protocol errors ({} clients closed), {} handshakes refused",
            l.address,
            l.clients,
            l.subscriptions,
            l.messages_sent,
            l.messages_dropped,
            l.steps_skipped,
            l.protocol_errors,
            l.clients_closed,
            l.handshakes_refused
        );
    }
}

/// The bus's lines of the text summary: Zenoh, ROS 2, Ivy, Paparazzi, synchronisation, twins.
fn print_bus(bus: Option<&runner::BusReport>, stats: &bridge::engine::LoopStats) {
    match bus.map(|b| (b, &b.prefix)) {
        Some((b, Some(prefix))) => {
            outln!(
                "  bus: zenoh, prefix {prefix}; {} commands accepted, {} rejected ({} not from the copter's controller); {} samples published; {} clients seen",
                b.commands_accepted,
                b.commands_rejected,
                b.commands_not_controller,
                b.published,
                b.clients_seen
            );
            if b.tracking_rejected + b.requests_dropped + b.spawns_rejected + b.publish_failed + b.replies_failed > 0 {
                outln!(
                    "    {} tracking poses rejected, {} spawn requests refused; {} inputs dropped (step loop's queue full); {} frames not fully published; {} query replies not sent",
                    b.tracking_rejected,
                    b.spawns_rejected,
                    b.requests_dropped,
                    b.publish_failed,
                    b.replies_failed
                );
            }
        }
        _ => outln!("  bus: zenoh off (--no-bus)"),
    }
    if let Some(r) = bus.and_then(|b| b.ros2.as_ref()) {
        outln!(
            "  ros 2: node /twinswarm on domain {}, {} publishers, {} subscriptions; {} messages sent to subscribers",
            r.domain,
            r.publishers,
            r.subscriptions,
            r.sent
        );
    }
    if let Some(i) = bus.and_then(|b| b.ivy.as_ref()) {
        print_ivy(i);
    }
    if let Some(b) = bus {
        print_paparazzi(b, stats);
    }
    print_twins(stats);
}

/// The Ivy lines of the text summary.
fn print_ivy(i: &runner::IvyReport) {
    outln!(
        "  ivy: {} as {}; {} peers joined, {} left, at the end: {}; {} texts sent ({} msgs to peers), {} received, {} delivered",
        i.bus,
        i.app_name,
        i.peers_joined,
        i.peers_left,
        if i.peers_at_end.is_empty() { "none".to_owned() } else { i.peers_at_end.join(", ") },
        i.texts_sent,
        i.msgs_sent,
        i.msgs_received,
        i.delivered
    );
    if i.bridged_ivy_to_zenoh + i.bridged_zenoh_to_ivy + i.bridge_dropped > 0 {
        outln!(
            "    bridged: {} ivy -> zenoh, {} zenoh -> ivy, {} dropped",
            i.bridged_ivy_to_zenoh,
            i.bridged_zenoh_to_ivy,
            i.bridge_dropped
        );
    }
    for (why, n) in &i.dropped {
        outln!("    dropped {n}: {why}");
    }
}

/// The Paparazzi lines of the text summary: what went out, what came in from each aircraft.
fn print_paparazzi(b: &runner::BusReport, stats: &bridge::engine::LoopStats) {
    outln!("  paparazzi: {} messages sent (virtual sonar, virtual telemetry)", stats.pprz_sent);
    for a in &b.telemetry.arrivals {
        outln!(
            "    from ac_id {:<3} {:<27} {:>6} received, every {:.1} ms (p50 {:.1}, p99 {:.1})",
            a.ac_id,
            a.message,
            a.count,
            a.gap_ms.mean,
            a.gap_ms.p50,
            a.gap_ms.p99
        );
    }
    let t = &b.telemetry;
    for (ac, line) in t.source_lines() {
        outln!("    aircraft {ac} drove its twin: {line}");
    }
    if !t.unknown_dropped.is_empty()
        || t.own_virtual_dropped > 0
        || t.decode_errors > 0
        || t.rejected > 0
        || t.queue_full > 0
    {
        outln!(
            "    not used (logged): unknown aircraft {:?}, as our virtual aircraft {}, undecodable {}, out of range {}; dropped (queue full) {}",
            t.unknown_dropped,
            t.own_virtual_dropped,
            t.decode_errors,
            t.rejected,
            t.queue_full
        );
    }
    if let Some(z) = &b.zenoh_texts
        && z.unmatched + z.not_utf8 > 0
    {
        outln!("    zenoh: {} texts matched no binding, {} payloads not UTF-8 (dropped)", z.unmatched, z.not_utf8);
    }
}

/// The synchronisation and twin lines of the text summary.
fn print_twins(stats: &bridge::engine::LoopStats) {
    for (name, s) in &stats.sync {
        outln!(
            "  sync {name}: {} MEDUSA updates ({} not used), {} tracking poses; moved {:.2} m in {} steps",
            s.medusa_updates,
            s.medusa_rejected,
            s.tracking_updates,
            s.corrected_m,
            s.corrected_steps
        );
        if let Some(why) = &s.medusa_off {
            outln!("    MEDUSA off for {name}: {why}");
        }
        if s.medusa_errors + s.sonar_superseded > 0 {
            outln!(
                "    {} MEDUSA updates failed, {} sonar readings superseded before use",
                s.medusa_errors,
                s.sonar_superseded
            );
        }
    }
    for (name, t) in &stats.twins {
        outln!(
            "  twin {name}{}: {} telemetry inputs, latency p50 {:.1} ms, p99 {:.1} ms; attitude RMS roll {:.2}°, pitch {:.2}° ({} steps)",
            if t.spawned { " (spawned on first telemetry)" } else { "" },
            t.inputs_applied,
            t.input_latency_ms.p50,
            t.input_latency_ms.p99,
            t.attitude_rms_deg[0],
            t.attitude_rms_deg[1],
            t.attitude_samples
        );
    }
}

/// Inputs, failsafe and lockstep lines of the text summary.
fn print_inputs(stats: &bridge::engine::LoopStats, failsafe_events: &[(u64, String)]) {
    let st = stats;
    if st.inputs_rejected + st.inputs_ignored + st.inputs_after_end + st.frames_dropped + st.spawns_failed > 0 {
        outln!(
            "  inputs: {} rejected, {} logged but not used (not ours), {} after the last step; {} spawns refused; {} frames not published ({} Paparazzi texts not sent)",
            st.inputs_rejected,
            st.inputs_ignored,
            st.inputs_after_end,
            st.spawns_failed,
            st.frames_dropped,
            st.pprz_dropped
        );
    }
    if !stats.failsafe.is_empty() {
        let counts: Vec<String> = stats.failsafe.iter().map(|(k, n)| format!("{n} {k}")).collect();
        outln!("  failsafe: {}", counts.join(", "));
        for (tick, message) in failsafe_events {
            outln!("    step {tick}: {message}");
        }
        let total: u64 = stats.failsafe.values().sum();
        if total > failsafe_events.len() as u64 {
            outln!("    … {} more in the log (/events)", total - failsafe_events.len() as u64);
        }
    }
    print_autopilots(stats);
    if let Some(l) = &stats.lockstep {
        let timeouts: u64 = l.timeouts.values().sum();
        outln!(
            "  lockstep: {} steps held, {} answers, {} timeouts ({} controllers), {} late and {} refused commands; {:.2} s waited",
            l.steps_held,
            l.answers,
            timeouts,
            l.timeouts.len(),
            l.late,
            l.refused,
            l.wait_s
        );
    }
}

/// The outside autopilots in a few lines, whatever their number: how many flew, their steps,
/// the time waited for them, and the first few that left early.
fn print_autopilots(stats: &bridge::engine::LoopStats) {
    let aps = &stats.autopilots;
    for r in stats.autopilots_refused.iter().take(5) {
        let ac = r.ac_id.map_or_else(|| "an autopilot".to_owned(), |a| format!("aircraft {a}"));
        outln!("  refused {ac} from {}: {}", r.peer, r.why);
    }
    if stats.autopilots_refused.len() > 5 {
        outln!("  … {} more refused in --json", stats.autopilots_refused.len() - 5);
    }
    if aps.is_empty() {
        return;
    }
    let steps = aps.iter().map(|a| a.steps);
    let (lo, hi) = (steps.clone().min().unwrap_or(0), steps.max().unwrap_or(0));
    let left: Vec<_> = aps.iter().filter_map(|a| a.left.as_ref().map(|l| (a, l))).collect();
    outln!(
        "  autopilots: {} flew ({} to {} steps each), {} left early; {:.2} s waited for their commands",
        aps.len(),
        lo,
        hi,
        left.len(),
        stats.autopilot_wait_s
    );
    for (a, (tick, why)) in left.iter().take(5) {
        outln!("    aircraft {} ({}) left at step {tick}: {why}", a.ac_id, a.copter);
    }
    if left.len() > 5 {
        outln!("    … {} more in --json", left.len() - 5);
    }
}

/// What became of the inputs that reached the loop, for `--json` and the log's `bus_report`.
fn inputs_json(st: &bridge::engine::LoopStats) -> serde_json::Value {
    serde_json::json!({
        "commands_applied": st.commands_applied,
        "commands_unknown_copter": st.commands_unknown_copter,
        "rejected": st.inputs_rejected,
        "ignored": st.inputs_ignored,
        "after_end": st.inputs_after_end,
        "spawns_failed": st.spawns_failed,
        "frames_dropped": st.frames_dropped,
        "pprz_dropped": st.pprz_dropped,
    })
}

/// Follows the flight for the summary: tracker, the first failsafe transitions, progress bar.
#[derive(Debug)]
pub(crate) struct RunWatch {
    tracker: report::Tracker,
    /// The first failsafe transitions, for the summary.
    failsafe_events: Vec<(u64, String)>,
    progress: Option<indicatif::ProgressBar>,
}

impl RunWatch {
    fn new(world: &World, progress: Option<indicatif::ProgressBar>) -> Self {
        Self { tracker: report::Tracker::new(world), failsafe_events: Vec::new(), progress }
    }
}

impl bridge::engine::StepObserver for RunWatch {
    fn after_step(
        &mut self,
        world: &sim_core::World,
        state: &sim_core::State,
        _inputs: &sim_core::Inputs,
        report: &sim_core::StepReport,
    ) {
        self.tracker.observe(world, state, report);
        if let Some(bar) = &self.progress
            && state.tick.is_multiple_of(20)
        {
            bar.set_position(state.tick);
        }
    }

    fn failsafe(&mut self, tick: u64, world: &sim_core::World, event: &bridge::engine::failsafe::FailsafeEvent) {
        if self.failsafe_events.len() < MAX_SUMMARY_EVENTS {
            self.failsafe_events.push((tick, event.message(world)));
        }
    }
}

/// Failsafe transitions the text summary lists one by one (the log has them all).
const MAX_SUMMARY_EVENTS: usize = 8;

/// `--resume`: the checkpoint, checked against this run (scene, seed, `--shard`).
fn load_resume(args: &RunArgs, world: &World) -> anyhow::Result<Option<Checkpoint>> {
    let Some(path) = &args.resume else { return Ok(None) };
    let key = RunKey::of(world, args.shard);
    let ckpt = checkpoint::load(path, &key).map_err(|e| match e {
        CheckpointError::Io { .. } => anyhow::Error::new(e),
        e => BadInput(e.into()).into(),
    })?;
    Ok(Some(ckpt))
}

/// `--checkpoint-every`; and a resumed run's first log event, which says where it went on from.
fn durability(
    args: &RunArgs,
    world: &World,
    resume: Option<Checkpoint>,
    log: Option<&mut bridge::log::Logger>,
) -> anyhow::Result<runner::Durability> {
    let checkpoint = match (args.checkpoint_every, &args.checkpoint_dir) {
        (Some(every_s), Some(dir)) => {
            let every_ticks =
                CheckpointOptions::every_ticks_for(every_s, world.params.control_dt_s).ok_or_else(|| {
                    BadInput(anyhow::anyhow!("--checkpoint-every: {every_s} is not a positive number of seconds"))
                })?;
            let log_epoch_ns = log.as_ref().filter(|l| l.has_file()).map(|l| l.epoch_ns());
            Some(CheckpointOptions { dir: dir.clone(), every_ticks, key: RunKey::of(world, args.shard), log_epoch_ns })
        }
        _ => None,
    };
    if let (Some(c), Some(path), Some(log)) = (&resume, &args.resume, log) {
        log.log_event(bridge::log::LogEvent {
            tick: c.tick,
            kind: bridge::log::EventKind::Resumed,
            copter: None,
            detail: Some(serde_json::json!({ "checkpoint": path.display().to_string(), "tick": c.tick })),
            message: format!("resumed from checkpoint {} at control step {}", path.display(), c.tick),
        })?;
    }
    Ok(runner::Durability { resume, checkpoint })
}

/// Checkpoints save what a plain or sharded run carries between steps; twins, `--ivy` and
/// `--pairing` carry more (synchronisation filters, telemetry timers).
fn check_checkpointable(args: &RunArgs, spec: &SceneSpec) -> anyhow::Result<()> {
    let flag = match (args.checkpoint_every.is_some(), args.resume.is_some()) {
        (_, true) => "--resume",
        (true, false) => "--checkpoint-every",
        (false, false) => return Ok(()),
    };
    let twins = spec.copters.iter().any(|c| c.kind == sim_core::CopterKind::Real);
    let unsaved = [(args.ivy.ivy.is_some(), "--ivy"), (args.pairing.is_some(), "--pairing"), (twins, "twins")];
    match unsaved.iter().find(|(on, _)| *on) {
        Some((_, what)) => {
            Err(BadInput(anyhow::anyhow!("{flag}: not available with {what} (their state between steps is not saved)"))
                .into())
        }
        None => Ok(()),
    }
}

/// What a shard cannot do yet.
fn check_shardable(args: &RunArgs, spec: &SceneSpec) -> anyhow::Result<()> {
    let unsharded = [(args.ivy.ivy.is_some(), "--ivy"), (args.pairing.is_some(), "--pairing"), (args.ros2, "--ros2")];
    if let Some((_, flag)) = unsharded.iter().find(|(on, _)| *on) {
        return Err(BadInput(anyhow::anyhow!("--shard: {flag} is not available for a shard yet")).into());
    }
    if spec.copters.iter().any(|c| c.kind == sim_core::CopterKind::Real) {
        return Err(
            BadInput(anyhow::anyhow!("--shard: scenes with twins (kind = \"real\") need one process for now")).into()
        );
    }
    if !(args.barrier_timeout.is_finite() && args.barrier_timeout > 0.0) {
        return Err(BadInput(anyhow::anyhow!("--barrier-timeout must be a positive number of seconds")).into());
    }
    Ok(())
}
