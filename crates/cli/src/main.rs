//! `twinswarm`: the command-line front end. Thin glue: parse arguments into validated values,
//! load the scene, drive `sim-core`, report. Errors are printed with their whole chain and
//! mapped to exit codes: 0 ok, 2 bad input (usage or scene), 1 runtime failure.

#[macro_use]
extern crate twinswarm;

mod fitcmd;
mod ivycmd;
mod localize;
mod report;
mod runcmd;
mod runner;
mod shardcmd;
mod standin;
mod synceval;
mod validate;

use twinswarm::{BadInput, logcmd, plot, replay, replay_pprz};

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use anyhow::Context;
use clap::{Parser, Subcommand};
use sim_core::World;
use sim_core::scene::{self, SceneSpec};

/// Twinswarm: a deterministic simulator for swarms of FINken indoor quadcopters, with virtual
/// twins of real copters (mixed reality).
#[derive(Debug, Parser)]
#[command(name = "twinswarm", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Fly a scene (default: the embedded FINken lab) and print a summary.
    Run(Box<runcmd::RunArgs>),
    /// Start a Zenoh router and N local shard processes of one swarm (`run --shard K/N`),
    /// wait for them and merge their summaries. A launcher, not a scheduler.
    Cluster(ClusterArgs),
    /// Run a Zenoh router (multicast scouting off) for shards and clients on several machines:
    /// one per machine, connected to each other; `zenohd` does the same.
    Router {
        /// Endpoints to listen on.
        #[arg(long, value_name = "ENDPOINT", default_value = "tcp/127.0.0.1:7447")]
        listen: Vec<String>,
        /// Other machines' routers to connect to.
        #[arg(long, value_name = "ENDPOINT")]
        connect: Vec<String>,
    },
    /// Stand in for a real FINken: fly its own "reality", send telemetry, fuse virtual sonar.
    Copter(standin::CopterArgs),
    /// Ivy bus tools: probe (like ivyprobe), send, peers.
    Ivy(ivycmd::IvyToolArgs),
    /// Validate a scene file and explain what it contains.
    Check {
        /// The scene file (TOML).
        scene: PathBuf,
    },
    /// Write a generated swarm scene (TOML) to stdout: the benchmarks' experiments.
    Scene(SceneArgs),
    /// Print each copter's derived model: mass, inertia, rotor and particle numbers.
    Inspect {
        /// The scene file (TOML); default: the embedded FINken lab.
        scene: Option<PathBuf>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// MEDUSA sonar localization: `--eval` measures it on a simulated Wall-Avoid flight.
    Localize(localize::LocalizeArgs),
    /// Inspect or repair MCAP run logs.
    #[command(subcommand)]
    Log(LogCommand),
    /// Republish a run log's bus traffic (clock, states, sensors, /bus) onto Zenoh with its
    /// original timing.
    Replay(replay::ReplayArgs),
    /// Hold a real flight's Paparazzi log (NAME.data + NAME.log) against Twinswarm: the twin
    /// driven by the log's telemetry, with and without the sync correction, scored against the
    /// real sonars, AHRS and IR, per flight (and V-REP's twin beside it with `--vrep`).
    Validate(validate::ValidateArgs),
    /// Identify the horizontal flight model from real flights' Paparazzi logs (NAME.data +
    /// NAME.log): attitude-to-position delay, damping, signs and trim bias, leave one flight
    /// out, and the prediction errors 1, 2 and 4 s ahead against Twinswarm's current model.
    Fit(fitcmd::FitArgs),
    /// Plot a run log: position heat-map, pitch and roll, sonars and y position (PNG).
    Plot {
        /// The MCAP log.
        file: PathBuf,
        /// Per-copter position heat-map over the arena.
        #[arg(long, value_name = "OUT.png")]
        heatmap: Option<PathBuf>,
        /// Pitch and roll over time (twins: with the commanded attitude).
        #[arg(long, value_name = "OUT.png")]
        attitude: Option<PathBuf>,
        /// The four sonar distances and the y position over time.
        #[arg(long, value_name = "OUT.png")]
        sonar: Option<PathBuf>,
        /// The copter of the sonar plot (default: the first).
        #[arg(long, value_name = "NAME")]
        copter: Option<String>,
    },
}

#[derive(Debug, clap::Args)]
struct SceneArgs {
    /// `dense`: a 1.5 m grid taking off from the floor among 10 pillars, Wall-Avoid at 1 m
    /// (the experiment of `swarm_rt --scene dense`); `cruise`: a 2 m grid in the air, each
    /// copter heading its own way at 0.3 m/s; `hover`: a 2 m grid hovering at 0.8 m; `flock`:
    /// a 4 m grid in the air drifting 18 m along x in a minute (the sharding tests' scene);
    /// `boxes`: `dense`'s take-off among ten boxes of several sizes, heights and yaws (the
    /// sharding checks' scene with boxes).
    #[arg(value_enum)]
    kind: SceneKind,
    /// Number of copters.
    #[arg(long, value_name = "N")]
    n: usize,
    /// `dense` only: grid spacing, m.
    #[arg(long, value_name = "M", default_value_t = 1.5)]
    spacing: f32,
    /// `dense` only: start in the air at 1 m instead of on the floor.
    #[arg(long)]
    air: bool,
    /// `dense` only: number of pillars.
    #[arg(long, value_name = "K", default_value_t = 10)]
    pillars: usize,
    /// Seed of the scene (pillar placement and every random draw of the run).
    #[arg(long, value_name = "S", default_value_t = 1)]
    seed: u64,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum SceneKind {
    Dense,
    Cruise,
    Hover,
    Flock,
    Boxes,
}

/// `twinswarm scene`: the generated scene as TOML, checked by compiling it back.
fn scene_cmd(a: &SceneArgs) -> anyhow::Result<()> {
    anyhow::ensure!(a.n > 0, "--n must be at least 1");
    anyhow::ensure!(a.spacing.is_finite() && a.spacing > 0.0, "--spacing must be a positive number of metres");
    let mut spec = match a.kind {
        SceneKind::Dense => sim_core::scene::dense_swarm(a.n, a.spacing, !a.air, a.pillars, a.seed),
        SceneKind::Cruise => sim_core::scene::cruising_swarm(a.n, 1),
        SceneKind::Hover => sim_core::scene::grid_swarm(a.n, 2.0, 0.8, true),
        SceneKind::Flock => sim_core::scene::flock_swarm(a.n, a.seed),
        SceneKind::Boxes => sim_core::scene::boxes_swarm(a.n, a.seed),
    };
    spec.sim.seed = a.seed;
    let text = toml::to_string(&spec)?;
    sim_core::scene::load("generated scene", &text)?;
    print!("{text}");
    Ok(())
}

#[derive(Debug, Subcommand)]
enum LogCommand {
    /// Channels, message counts, duration, copters and scene of a log.
    Info {
        /// The MCAP log.
        file: PathBuf,
    },
    /// Rescue every complete chunk of a truncated log (e.g. after kill -9) into a new file.
    Recover {
        /// The truncated log.
        broken: PathBuf,
        /// The complete file to write.
        fixed: PathBuf,
    },
    /// Merge the logs of a sharded run (one per shard) into one log of the whole swarm.
    Merge {
        /// The merged log to write.
        #[arg(long, short, value_name = "OUT.mcap")]
        out: PathBuf,
        /// The shards' logs.
        #[arg(required = true, num_args = 1..)]
        inputs: Vec<PathBuf>,
    },
    /// Write a real flight's Paparazzi log (NAME.data with NAME.log beside it) as an MCAP log:
    /// its messages on /pprz/… at their recorded times, its sonars, IR and attitude as a
    /// copter's, for Foxglove, `plot` and `log info`.
    Import {
        /// The Paparazzi log (`.data` or `.log`).
        file: PathBuf,
        /// The MCAP log to write (default: NAME.mcap beside the working directory).
        #[arg(long, short, value_name = "OUT.mcap")]
        out: Option<PathBuf>,
        /// The aircraft that is the copter (default: the one that sent the most).
        #[arg(long, value_name = "AC_ID")]
        ac_id: Option<u8>,
    },
}

#[derive(Debug, clap::Args)]
struct ClusterArgs {
    /// The scene file (TOML); default: the embedded FINken lab.
    scene: Option<PathBuf>,
    /// How many shards (local processes).
    #[arg(long, value_name = "N")]
    shards: usize,
    /// Simulated duration, s (default: the scene's `sim.duration_s`).
    #[arg(long, value_name = "S")]
    duration: Option<f64>,
    /// Seed of all random draws (default: the scene's `sim.seed`).
    #[arg(long, value_name = "N")]
    seed: Option<u64>,
    /// Worker threads of each shard's step.
    #[arg(long, value_name = "N")]
    threads: Option<usize>,
    /// Pace the whole cluster against the wall clock (each shard paces, the barrier holds them
    /// together).
    #[arg(long)]
    realtime: bool,
    /// A shard that hears nothing from a neighbour this long stops with an error, s.
    #[arg(long, value_name = "S", default_value_t = 30.0)]
    barrier_timeout: f64,
    /// Shards without the client bus (no state, sensors or commands on Zenoh; ghosts still
    /// go over it).
    #[arg(long)]
    no_bus: bool,
    /// Each shard logs to DIR/shard-K-of-N.mcap (`twinswarm log merge` joins them); default:
    /// no logs.
    #[arg(long, value_name = "DIR")]
    log_dir: Option<PathBuf>,
    /// Checkpoint every S simulated seconds (each shard, at the same ticks), and restart the
    /// cluster when a shard process dies: all shards go on from the last checkpoint every
    /// shard has (from the start if there is none), with the bits of an uninterrupted run.
    /// After a restart R, shards log to DIR/shard-K-of-N.restart-R.mcap; the killed shards'
    /// logs are recovered in place, and `log merge` of all of them has every step once.
    #[arg(long, value_name = "S")]
    checkpoint_every: Option<f64>,
    /// Where the checkpoints go (default: LOG_DIR/checkpoints with `--log-dir`, else a
    /// directory under the system's temporary directory).
    #[arg(long, value_name = "DIR")]
    checkpoint_dir: Option<PathBuf>,
    /// With `--checkpoint-every`: restart the cluster at most this many times; a shard that
    /// dies once more stops the run (a crash that comes back every time must not loop).
    #[arg(long, value_name = "N", default_value_t = 3)]
    max_restarts: u32,
    /// Print the merged summary as JSON on stdout.
    #[arg(long)]
    json: bool,
}

/// `--sync` and `--tracking-lag` as options (`None`: off).
pub(crate) fn parse_sync(
    sources: &str,
    tracking_lag_s: f64,
) -> anyhow::Result<Option<bridge::mixed::sync::SyncOptions>> {
    let bad = |m: String| anyhow::Error::new(BadInput(anyhow::anyhow!(m)));
    if !tracking_lag_s.is_finite() || !(0.0..=2.5).contains(&tracking_lag_s) {
        return Err(bad(format!("--tracking-lag must be in [0, 2.5] s, got {tracking_lag_s}")));
    }
    let mut o = bridge::mixed::sync::SyncOptions { tracking_lag_s, ..bridge::mixed::sync::SyncOptions::off() };
    for part in sources.split(',').map(str::trim) {
        match part {
            "medusa" => o.medusa = true,
            "tracking" => o.tracking = true,
            "off" | "none" => {}
            other => {
                return Err(bad(format!("--sync: unknown source `{other}` (use medusa, tracking or off)")));
            }
        }
    }
    Ok((o.medusa || o.tracking).then_some(o))
}

pub(crate) fn parse_uplink(s: &str) -> Result<(u8, bridge::paparazzi::convert::Uplink), String> {
    let (ac, kind) = s.split_once('=').ok_or_else(|| format!("expected AC_ID=KIND, got `{s}`"))?;
    let ac: u8 = ac.trim().parse().map_err(|_| format!("`{ac}` is not an aircraft id 0..255"))?;
    Ok((ac, bridge::paparazzi::convert::Uplink::parse(kind.trim())?))
}

/// A lab's messages.xml, the definitions a Paparazzi server log (`.log`) carries, or the
/// embedded ones.
pub(crate) fn load_messages(
    path: Option<&std::path::Path>,
) -> anyhow::Result<Arc<bridge::paparazzi::messages::MessageSet>> {
    use bridge::paparazzi::flightlog::LogConfig;
    let Some(p) = path else { return Ok(Arc::new(bridge::paparazzi::convert::project_messages())) };
    let bytes = std::fs::read(p).map_err(|e| BadInput(anyhow::anyhow!("cannot read {}: {e}", p.display())))?;
    let text = String::from_utf8_lossy(&bytes);
    let source = p.display().to_string();
    let set = if text.contains("<configuration") {
        LogConfig::parse(&text, &source).map(|c| c.messages)
    } else {
        bridge::paparazzi::messages::MessageSet::parse(&text, &source)
    };
    Ok(Arc::new(set.map_err(|e| BadInput(e.into()))?))
}

pub(crate) fn parse_twin_attitude(s: &str) -> Result<bridge::mixed::interpreter::TwinAttitude, String> {
    match s {
        "setpoint" => Ok(bridge::mixed::interpreter::TwinAttitude::Setpoint),
        "measured" => Ok(bridge::mixed::interpreter::TwinAttitude::Measured),
        _ => Err(format!("expected `setpoint` or `measured`, got `{s}`")),
    }
}

/// Loads the mixed-reality options of `run` and `copter`: pairing (checked against its
/// conf.xml) and telemetry plan.
pub(crate) fn load_mixed(
    pairing: Option<&std::path::Path>,
    telemetry: Option<&std::path::Path>,
    mode: Option<&str>,
    virtual_sonar_period_s: f64,
) -> anyhow::Result<runner::MixedOptions> {
    let bad = |e: anyhow::Error| anyhow::Error::new(BadInput(e));
    if !virtual_sonar_period_s.is_finite() || virtual_sonar_period_s < 0.0 {
        return Err(bad(anyhow::anyhow!("--virtual-sonar-period must be >= 0 s, got {virtual_sonar_period_s}")));
    }
    let pairing = match pairing {
        None => None,
        Some(path) => {
            let p = bridge::Pairing::from_file(path).map_err(|e| bad(e.into()))?;
            let conf_path = p.conf_path_from(path);
            let conf = bridge::ConfXml::from_file(&conf_path)
                .map_err(|e| bad(anyhow::Error::new(e).context(format!("conf.xml named by {}", path.display()))))?;
            Some(p.resolve(&conf).map_err(|e| bad(e.into()))?)
        }
    };
    let plan = match telemetry {
        None if mode.is_none() => bridge::mixed::plan::TelemetryPlan::project_default(),
        None => {
            let t = bridge::Telemetry::parse(bridge::mixed::plan::TELEMETRY_XML, "assets/paparazzi/telemetry.xml")?;
            bridge::mixed::plan::TelemetryPlan::from_telemetry(&t, None, mode).map_err(|e| bad(anyhow::anyhow!(e)))?
        }
        Some(path) => {
            let t = bridge::Telemetry::from_file(path).map_err(|e| bad(e.into()))?;
            bridge::mixed::plan::TelemetryPlan::from_telemetry(&t, None, mode).map_err(|e| bad(anyhow::anyhow!(e)))?
        }
    };
    Ok(runner::MixedOptions { pairing, plan, virtual_sonar_period_s, ..Default::default() })
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            let code = if e.use_stderr() { 2 } else { 0 };
            // Printing fails only on a closed stdout or stderr: the exit code still tells.
            let _ = e.print();
            return ExitCode::from(code);
        }
    };
    let filter = match std::env::var("TWINSWARM_LOG") {
        Err(_) => tracing_subscriber::EnvFilter::new("warn"),
        Ok(v) => tracing_subscriber::EnvFilter::try_new(&v).unwrap_or_else(|e| {
            eprintln!("twinswarm: TWINSWARM_LOG={v:?} is not a log filter ({e}); using \"warn\"");
            tracing_subscriber::EnvFilter::new("warn")
        }),
    };
    tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr).init();
    // No subcommand: `run` with its defaults (parsed, so every default is clap's).
    let command = match cli.command {
        Some(c) => c,
        None => match Cli::try_parse_from(["twinswarm", "run"]).map(|c| c.command) {
            Ok(Some(c)) => c,
            _ => {
                eprintln!("error: cannot build the default `run` command");
                return ExitCode::from(1);
            }
        },
    };
    let result = match command {
        Command::Run(args) => runcmd::run(*args),
        Command::Copter(args) => standin::run(args),
        Command::Ivy(args) => ivycmd::run(args),
        Command::Check { scene } => check(&scene),
        Command::Scene(args) => scene_cmd(&args),
        Command::Cluster(args) => cluster_cmd(&args),
        Command::Router { listen, connect } => router_cmd(&listen, &connect),
        Command::Inspect { scene, json } => inspect(scene.as_deref(), json),
        Command::Localize(args) if args.sync_eval => synceval::run(&args),
        Command::Localize(args) => localize::run(args),
        Command::Log(LogCommand::Info { file }) => logcmd::info(&file),
        Command::Log(LogCommand::Recover { broken, fixed }) => logcmd::recover(&broken, &fixed),
        Command::Log(LogCommand::Merge { out, inputs }) => logcmd::merge(&inputs, &out),
        Command::Log(LogCommand::Import { file, out, ac_id }) => logcmd::import(&file, out.as_deref(), ac_id),
        // A Paparazzi log (NAME.data) replays onto Ivy as `link` delivered it; a run log
        // onto Zenoh.
        Command::Replay(args) if bridge::paparazzi::flightlog::is_flight_log(&args.file) => replay_pprz::run(&args),
        Command::Replay(args) => replay::run(args),
        Command::Validate(args) => validate::run(args),
        Command::Fit(args) => fitcmd::run(&args),
        Command::Plot { file, heatmap, attitude, sonar, copter } => plot::plot(
            &file,
            &plot::PlotRequest {
                heatmap: heatmap.as_deref(),
                attitude: attitude.as_deref(),
                sonar: sonar.as_deref(),
                copter: copter.as_deref(),
            },
        ),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            if let Some(bad) = e.downcast_ref::<BadInput>() {
                eprintln!("error: {bad}");
                ExitCode::from(2)
            } else {
                eprintln!("error: {e:#}");
                ExitCode::from(1)
            }
        }
    }
}

/// Loads a scene file, or the embedded default.
pub(crate) fn load_scene(path: Option<&std::path::Path>) -> anyhow::Result<(String, SceneSpec, World)> {
    match path {
        None => {
            let (spec, world) = scene::load_default();
            Ok((scene::DEFAULT_SCENE_ORIGIN.to_owned(), spec, world))
        }
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("cannot read scene file {}", path.display()))
                .map_err(|e| anyhow::Error::new(BadInput(e)))?;
            let origin = path.display().to_string();
            let (spec, world) = scene::load(&origin, &text).map_err(|e| anyhow::Error::new(BadInput(e.into())))?;
            Ok((origin, spec, world))
        }
    }
}

fn check(path: &std::path::Path) -> anyhow::Result<()> {
    let (origin, spec, world) = load_scene(Some(path))?;
    outln!("{origin}: OK");
    outln!(
        "  world {:?}: arena {} m x {} m x {} m high, walls {}",
        world.name,
        world.arena.size_m[0],
        world.arena.size_m[1],
        world.arena.height_m,
        if world.arena.walls { "on" } else { "off" }
    );
    outln!(
        "  stepping: physics {} ms x {} substeps = control {} ms; seed {}; duration {} s ({} control steps)",
        world.params.physics_dt_s * 1e3,
        world.params.substeps,
        world.params.control_dt_s * 1e3,
        world.params.seed,
        world.params.duration_s,
        world.default_ticks()
    );
    outln!("  {} static box(es):", world.boxes.len());
    for b in &world.boxes {
        outln!(
            "    {:<10} centre ({:.2}, {:.2}, {:.2}) m, size {:.2} x {:.2} x {:.2} m, yaw {:.1}°",
            b.name,
            b.center_m.x,
            b.center_m.y,
            b.center_m.z,
            2.0 * b.half_extents_m.x,
            2.0 * b.half_extents_m.y,
            2.0 * b.half_extents_m.z,
            b.yaw_rad.to_degrees()
        );
    }
    outln!("  {} copter(s):", world.copters.len());
    for (c, cs) in world.copters.iter().zip(&spec.copters) {
        let af = &world.airframes[c.airframe];
        let cmd = &c.initial_command;
        let vertical = if cmd.height_m > 0.0 {
            format!("holds {:.2} m", cmd.height_m)
        } else {
            format!("throttle {:.0} %", cmd.throttle * 100.0)
        };
        outln!(
            "    {:<10} {:?}{} at ({:.2}, {:.2}, {:.2}) m, yaw {:.1}°, {:.3} kg, mode {}, {}",
            c.name,
            c.kind,
            c.ac_id.map(|a| format!(" ac_id {a}")).unwrap_or_default(),
            c.start_pos_m.x,
            c.start_pos_m.y,
            c.start_pos_m.z,
            c.start_yaw_rad.to_degrees(),
            af.mass_kg,
            cmd.mode.as_str(),
            vertical
        );
        if let scene::AirframeRef::Named(name) = &cs.airframe {
            outln!("               airframe preset {name:?}");
        }
    }
    let s = &world.sensors.spec;
    outln!(
        "  sensors {}: sonar {}° cone, {}-{} m, sigma {} m, floor echoes {}; cross-talk {}; estimators {}",
        if s.enabled { "on" } else { "off" },
        s.sonar.opening_deg,
        s.sonar.min_range_m,
        s.sonar.max_range_m,
        if s.noise { s.sonar.noise_sigma_m } else { 0.0 },
        if s.sonar.floor_echo { "on" } else { "off" },
        if s.crosstalk.enabled {
            format!("on ({:?}, {} ms cycles)", s.crosstalk.phase, s.crosstalk.cycle_s * 1000.0)
        } else {
            "off".into()
        },
        if s.estimator.ideal { "ideal (ground truth)" } else { "IR height, AHRS, thrust adaptation" }
    );
    let a = &world.airflow.spec;
    outln!(
        "  airflow: downwash {}, ground effect {}",
        if a.downwash { "on" } else { "off" },
        if a.ground_effect { "on" } else { "off" }
    );
    Ok(())
}

fn inspect(path: Option<&std::path::Path>, json: bool) -> anyhow::Result<()> {
    let (_, _, world) = load_scene(path)?;
    let models: Vec<report::CopterModel> = world.copters.iter().map(|c| report::CopterModel::new(&world, c)).collect();
    if json {
        outln!("{}", serde_json::to_string_pretty(&models)?);
    } else {
        for m in &models {
            out!("{}", m.to_text());
        }
    }
    Ok(())
}

/// `cluster SCENE --shards N`.
fn cluster_cmd(args: &ClusterArgs) -> anyhow::Result<()> {
    if !(1..=64).contains(&args.shards) {
        return Err(BadInput(anyhow::anyhow!("--shards must be 1 to 64 local processes, got {}", args.shards)).into());
    }
    // Check the scene here, so that a bad one is one clear error rather than N.
    let (_, spec, _) = load_scene(args.scene.as_deref())?;
    sim_core::shard::Partition::new(&scene::compile(&spec).map_err(|e| BadInput(e.into()))?, args.shards)
        .map_err(|e| BadInput(e.into()))?;
    if let Some(every) = args.checkpoint_every
        && !(every.is_finite() && every > 0.0)
    {
        return Err(
            BadInput(anyhow::anyhow!("--checkpoint-every must be a positive number of seconds, got {every}")).into()
        );
    }
    let stop = logcmd::install_stop_flag()?;
    let opts = shardcmd::ClusterRun {
        scene: args.scene.clone(),
        shards: args.shards,
        duration: args.duration,
        seed: args.seed,
        threads: args.threads,
        timeout_s: args.barrier_timeout,
        realtime: args.realtime,
        log_dir: args.log_dir.clone(),
        no_bus: args.no_bus,
        checkpoint_every_s: args.checkpoint_every,
        checkpoint_dir: cluster_checkpoint_dir(args),
        max_restarts: args.max_restarts,
    };
    let s = shardcmd::run_cluster(&opts, &stop)?;
    if args.json {
        println!("{}", serde_json::to_string(&s)?);
        return Ok(());
    }
    println!(
        "cluster of {} shards (router {}): {} copters, {} crashed, {:.2} s wall, slowest shard {:.2}x real time",
        s.shards, s.router, s.copters_count, s.crashed, s.wall_s, s.real_time_factor
    );
    let cpu = |s: Option<f64>| s.map_or("CPU time unknown".to_owned(), |s| format!("{s:.2} s CPU"));
    for p in &s.per_shard {
        let (k, rtf, wall) = (p.shard.shard, p.real_time_factor, p.wall_time_s);
        println!("shard {k}: {rtf:.2}x real time, {wall:.2} s wall, {}", cpu(p.cpu_s));
        shardcmd::print_section(&p.shard);
    }
    if let Some(r) = s.cpu_per_sim_s {
        let launcher = s.launcher_cpu_s.unwrap_or(0.0);
        println!("CPU: {r:.2} s per simulated second, the shards' and the launcher's (its router: {launcher:.2} s)");
    }
    for r in &s.restarts {
        println!(
            "restarted after {:.1} s: shard {} died ({}); every shard went on from tick {}",
            r.at_wall_s, r.shard, r.status, r.from_tick
        );
    }
    println!("digest of the swarm: {}", s.digest);
    Ok(())
}

/// `cluster --checkpoint-dir`, or its default; `--checkpoint-every` checked.
fn cluster_checkpoint_dir(args: &ClusterArgs) -> PathBuf {
    match (&args.checkpoint_dir, &args.log_dir) {
        (Some(d), _) => d.clone(),
        (None, Some(logs)) => logs.join("checkpoints"),
        (None, None) => std::env::temp_dir().join(format!("twinswarm-checkpoints-{}", std::process::id())),
    }
}

/// `router`: a Zenoh router until SIGINT or SIGTERM.
fn router_cmd(listen: &[String], connect: &[String]) -> anyhow::Result<()> {
    use zenoh::Wait;
    let stop = logcmd::install_stop_flag()?;
    let session = zenoh::open(shardcmd::router_config(listen, connect)?)
        .wait()
        .map_err(|e| anyhow::anyhow!("cannot start the Zenoh router on {listen:?}: {e}"))?;
    eprintln!("zenoh router listening on {listen:?}, connected to {connect:?}; Ctrl-C stops it");
    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    session.close().wait().map_err(|e| anyhow::anyhow!("zenoh: {e}"))?;
    Ok(())
}
