//! `twinswarm`: the command-line front end. Thin glue: parse arguments into validated values,
//! load the scene, drive `sim-core`, report. Errors are printed with their whole chain and
//! mapped to exit codes: 0 ok, 2 bad input (usage or scene), 1 runtime failure.

#[macro_use]
extern crate twinswarm;

mod ivycmd;
mod localize;
mod replay;
mod report;
mod runner;
mod shardcmd;
mod standin;
mod synceval;

use twinswarm::{BadInput, logcmd, plot};

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Context;
use bridge::failsafe::{ClientLostAction, FailsafeOptions};
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
    Run(RunArgs),
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
    Ivy(ivycmd::IvyArgs),
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
    /// a 4 m grid in the air drifting 18 m along x in a minute (the sharding tests' scene).
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
    /// Print the merged summary as JSON on stdout.
    #[arg(long)]
    json: bool,
}

#[derive(Debug, clap::Args)]
struct RunArgs {
    /// Step only shard K of N of the swarm (a region of the arena), trading ghosts with the
    /// other shards over Zenoh (`--connect` to their router). Logging, the client bus and the
    /// live view are not sharded yet: a shard runs without them.
    #[arg(long, value_name = "K/N", value_parser = shardcmd::parse_shard)]
    shard: Option<(usize, usize)>,
    /// With `--shard`: stop with an error when a neighbouring shard stays silent this long, s.
    #[arg(long, value_name = "S", default_value_t = 30.0)]
    barrier_timeout: f64,
    /// With `--shard`: when a neighbouring shard's liveliness token goes away, `stop` with an
    /// error (every log finished), or `hold` at the barrier until it is back (a router
    /// restarting, a network partition), for at most `--barrier-timeout`.
    #[arg(long, value_name = "WHAT", default_value = "stop")]
    on_shard_lost: OnShardLost,
    /// The scene file (TOML); default: the embedded FINken lab.
    scene: Option<PathBuf>,
    /// Simulated duration, s (default: the scene's `sim.duration_s`).
    #[arg(long, value_name = "S")]
    duration: Option<f64>,
    /// Seed of all random draws (default: the scene's `sim.seed`).
    #[arg(long, value_name = "N")]
    seed: Option<u64>,
    /// Pace control steps against the wall clock (1 simulated second per second).
    #[arg(long)]
    realtime: bool,
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
    /// Join a Paparazzi Ivy bus as agent `Twinswarm`: real aircraft's telemetry from `link`
    /// drives their twins, VIRTUAL_SONAR goes back, virtual copters send telemetry. BUS as in
    /// Paparazzi (`127.255.255.255:2010`, `127:2010`); default: `--ivy-bus`, else `IVYBUS`,
    /// else 127.255.255.255:2010. With Zenoh on, texts are bridged both ways.
    #[arg(long, value_name = "BUS", num_args = 0..=1, default_missing_value = "")]
    ivy: Option<String>,
    /// The Ivy bus address (same syntax as Paparazzi's `-b`); implies nothing without `--ivy`.
    #[arg(long, value_name = "ADDR:PORT")]
    ivy_bus: Option<String>,
    /// A full Zenoh configuration file (JSON5), instead of the embedded default (peer mode,
    /// listen on tcp/127.0.0.1:7447, multicast scouting off).
    #[arg(long, value_name = "FILE.json5")]
    zenoh_config: Option<PathBuf>,
    /// Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7448 (repeatable; overrides the config).
    #[arg(long, value_name = "ENDPOINT")]
    listen: Vec<String>,
    /// Zenoh endpoint to connect to (repeatable; overrides the config).
    #[arg(long, value_name = "ENDPOINT")]
    connect: Vec<String>,
    /// Key-expression prefix (default: twinswarm/<world name>).
    #[arg(long, value_name = "KEY")]
    prefix: Option<String>,
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
    /// Which telemetry sets twins' attitude targets: `setpoint` (FINKEN_ACTUATORS_SET_POINT,
    /// what the real copter asks for) or `measured` (ATTITUDE, what it does).
    #[arg(long, value_name = "SOURCE", default_value = "setpoint", value_parser = parse_twin_attitude)]
    twin_attitude: bridge::mixed::TwinAttitude,
    /// How twins are kept where their real copters are: `medusa` (the real copter's sonars and
    /// yaw), `tracking` (poses on …/copters/<name>/tracking), both, or `off` (command
    /// prediction only).
    #[arg(long, value_name = "SOURCES", default_value = "medusa,tracking")]
    sync: String,
    /// Lag of the tracking poses, s.
    #[arg(long, value_name = "S", default_value_t = 0.2)]
    tracking_lag: f64,
    /// A twin whose telemetry stays silent this long levels out and holds its height, s.
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
    /// for fast runs of large swarms that must not wait for their log (see the README's
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

/// `--on-log-error`.
/// `--on-shard-lost`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum OnShardLost {
    /// Stop with an error.
    Stop,
    /// Hold at the barrier until the neighbour is back.
    Hold,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
enum OnLogError {
    Stop,
    Continue,
}

/// `--sync` and `--tracking-lag` as options (`None`: off).
pub(crate) fn parse_sync(sources: &str, tracking_lag_s: f64) -> anyhow::Result<Option<bridge::sync::SyncOptions>> {
    let bad = |m: String| anyhow::Error::new(BadInput(anyhow::anyhow!(m)));
    if !tracking_lag_s.is_finite() || !(0.0..=2.5).contains(&tracking_lag_s) {
        return Err(bad(format!("--tracking-lag must be in [0, 2.5] s, got {tracking_lag_s}")));
    }
    let mut o = bridge::sync::SyncOptions { tracking_lag_s, ..bridge::sync::SyncOptions::off() };
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

fn parse_twin_attitude(s: &str) -> Result<bridge::mixed::TwinAttitude, String> {
    match s {
        "setpoint" => Ok(bridge::mixed::TwinAttitude::Setpoint),
        "measured" => Ok(bridge::mixed::TwinAttitude::Measured),
        _ => Err(format!("expected `setpoint` or `measured`, got `{s}`")),
    }
}

/// Loads the mixed-reality options of `run` and `copter`: pairing (checked against its
/// conf.xml) and telemetry plan.
fn load_mixed(
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
        None if mode.is_none() => bridge::mixed::TelemetryPlan::project_default(),
        None => {
            let t = bridge::Telemetry::parse(bridge::mixed::TELEMETRY_XML, "assets/paparazzi/telemetry.xml")?;
            bridge::mixed::TelemetryPlan::from_telemetry(&t, None, mode).map_err(|e| bad(anyhow::anyhow!(e)))?
        }
        Some(path) => {
            let t = bridge::Telemetry::from_file(path).map_err(|e| bad(e.into()))?;
            bridge::mixed::TelemetryPlan::from_telemetry(&t, None, mode).map_err(|e| bad(anyhow::anyhow!(e)))?
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
        Command::Run(args) => run(args),
        Command::Copter(args) => standin::run(args),
        Command::Ivy(args) => ivycmd::run(args),
        Command::Check { scene } => check(&scene),
        Command::Scene(args) => scene_cmd(&args),
        Command::Cluster(args) => cluster_cmd(&args),
        Command::Router { listen, connect } => router_cmd(&listen, &connect),
        Command::Inspect { scene, json } => inspect(scene.as_deref(), json),
        Command::Localize(args) => localize::run(args),
        Command::Log(LogCommand::Info { file }) => logcmd::info(&file),
        Command::Log(LogCommand::Recover { broken, fixed }) => logcmd::recover(&broken, &fixed),
        Command::Log(LogCommand::Merge { out, inputs }) => logcmd::merge(&inputs, &out),
        Command::Replay(args) => replay::run(args),
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
fn load_scene(path: Option<&std::path::Path>) -> anyhow::Result<(String, SceneSpec, World)> {
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

fn run(args: RunArgs) -> anyhow::Result<()> {
    let (origin, mut spec, _) = load_scene(args.scene.as_deref())?;
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
        check_shardable(&args, &spec)?;
    }
    let mixed = load_mixed(
        args.pairing.as_deref(),
        args.telemetry.as_deref(),
        args.telemetry_mode.as_deref(),
        args.virtual_sonar_period,
    )?;
    let mixed = runner::MixedOptions {
        twin_attitude: args.twin_attitude,
        sync: parse_sync(&args.sync, args.tracking_lag)?,
        ..mixed
    };
    if let (Some(p), Some(path)) = (&mixed.pairing, &args.pairing) {
        bridge::mixed::apply_pairing(&mut spec, p).map_err(|e| BadInput(anyhow::anyhow!("{}: {e}", path.display())))?;
    }
    let world = scene::compile(&spec).map_err(|e| {
        let e = anyhow::Error::new(e);
        let e = match &args.pairing {
            Some(p) => e.context(format!("{origin} with the copters of pairing {}", p.display())),
            None => e,
        };
        anyhow::Error::new(BadInput(e))
    })?;
    let failsafe = FailsafeOptions {
        hold_after_s: args.link_hold,
        land_after_s: args.link_land,
        descent_m_s: args.descent,
        client_lost: args.on_client_lost,
    };
    failsafe.validate().map_err(|e| BadInput(anyhow::anyhow!("--link-hold/--link-land/--descent: {e}")))?;
    let log_every = match args.log_rate {
        None => 1,
        Some(hz) => bridge::log::LogOptions::every_ticks_for_rate(hz, world.params.control_dt_s)
            .ok_or_else(|| BadInput(anyhow::anyhow!("--log-rate: {hz} is not a positive rate in Hz")))?,
    };
    let ticks = world.default_ticks();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let live = match &args.foxglove {
        None => None,
        Some(a) => {
            let addr: std::net::SocketAddr = a.parse().map_err(|e| {
                BadInput(anyhow::anyhow!("--foxglove: {a:?} is not an address like 127.0.0.1:8765: {e}"))
            })?;
            let server = bridge::live::LiveServer::start(addr, "twinswarm", rt.handle())
                .with_context(|| format!("--foxglove: cannot listen on {addr}"))?;
            if !args.json {
                eprintln!("live view: ws://{} (Foxglove: Open connection, Foxglove WebSocket)", server.local_addr());
            }
            Some(std::sync::Arc::new(server))
        }
    };
    if !(args.log_unchanged.is_finite() && args.log_unchanged >= 0.0) {
        return Err(BadInput(anyhow::anyhow!(
            "--log-unchanged: {} is not a number of seconds (0 or more)",
            args.log_unchanged
        ))
        .into());
    }
    let log_options = bridge::log::LogOptions {
        every_ticks: log_every,
        zstd_level: args.log_zstd_level,
        unchanged_every_s: args.log_unchanged,
        ..Default::default()
    };
    let log = logcmd::start_run_log(
        args.log.as_deref(),
        args.no_log,
        log_options,
        &world,
        args.scene.as_deref(),
        &origin,
        live.clone(),
    )?;
    let stop = logcmd::install_stop_flag()?;
    let progress = (!args.json && !args.realtime && std::io::stderr().is_terminal()).then(|| {
        let bar = indicatif::ProgressBar::new(ticks);
        bar.set_style(
            indicatif::ProgressStyle::with_template("{spinner} [{bar:40}] {pos}/{len} steps  {per_sec}  eta {eta}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        bar
    });
    let ivy = match &args.ivy {
        None => None,
        Some(b) => {
            let explicit = if b.is_empty() { args.ivy_bus.as_deref() } else { Some(b.as_str()) };
            Some(bridge::paparazzi::ivy::BusAddr::from_env_or(explicit).map_err(|e| BadInput(e.into()))?)
        }
    };
    let bus = runner::BusOptions {
        ivy,
        no_bus: args.no_bus,
        zenoh_config: args.zenoh_config.clone(),
        listen: args.listen.clone(),
        connect: args.connect.clone(),
        prefix: args.prefix.clone(),
        mixed,
        failsafe,
        shard: args.shard.map(|(shard, shards)| runner::ShardOptions {
            shard,
            shards,
            timeout: std::time::Duration::from_secs_f64(args.barrier_timeout),
            on_lost: match args.on_shard_lost {
                OnShardLost::Stop => bridge::shard::OnLost::Stop,
                OnShardLost::Hold => bridge::shard::OnLost::Hold,
            },
        }),
    };
    let stop_on_log_error = (args.on_log_error == OnLogError::Stop).then(|| stop.clone());
    let log_path = log.as_ref().filter(|l| l.has_file()).map(|l| l.path().to_owned());
    let mut observer = RunObserver {
        tracker: report::Tracker::new(&world),
        log,
        log_error: None,
        log_error_tick: None,
        stop_on_log_error,
        failsafe_events: Vec::new(),
        tick: 0,
        progress,
    };
    let started = Instant::now();
    let outcome = runner::run(&rt, world, ticks, args.realtime, &bus, &mut observer, stop)?;
    let wall_s = started.elapsed().as_secs_f64();
    let RunObserver { tracker, log, log_error, log_error_tick, failsafe_events, progress, .. } = observer;
    if let Some(bar) = progress {
        bar.finish_and_clear();
    }
    let interrupted = (outcome.stats.stopped_early && log_error.is_none()).then_some(outcome.state.tick);
    let mut log = log;
    if let (Some(l), Some(b)) = (&mut log, &outcome.bus) {
        // The drop counts belong in the log too: what never reached the loop is only there.
        let mut detail = serde_json::to_value(b)?;
        detail["inputs"] = inputs_json(&outcome.stats);
        let event = bridge::log::LogEvent {
            tick: outcome.state.tick,
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
    let log_stats = logcmd::finish_run_log(log, interrupted)?;
    let live_stats = live.as_ref().map(|l| l.stats());
    drop(live);
    let log_error = log_error.map(|e| {
        let tick = log_error_tick.unwrap_or(0);
        let path = log_path.as_ref().map_or("the log".to_owned(), |p| p.display().to_string());
        let what = match args.on_log_error {
            OnLogError::Stop => format!("the run stopped at control step {tick}"),
            OnLogError::Continue => {
                format!("the run went on without a log from control step {tick} to {}", outcome.state.tick)
            }
        };
        e.context(format!(
            "logging failed at control step {tick}; {what}. {path} holds what was written before the failure: \
             `twinswarm log recover {path} FIXED.mcap` makes it a complete log"
        ))
    });
    let summary = tracker.summary(&outcome.world, &outcome.state, &origin, wall_s, outcome.stats.overruns);
    if args.json {
        let mut json = serde_json::to_value(&summary)?;
        json["log"] = log_stats.as_ref().map_or(serde_json::Value::Null, |l| l.path.display().to_string().into());
        json["live"] = serde_json::to_value(&live_stats)?;
        json["interrupted"] = interrupted.is_some().into();
        json["bus"] = serde_json::to_value(&outcome.bus)?;
        json["frames_dropped"] = outcome.stats.frames_dropped.into();
        json["twins"] = serde_json::to_value(&outcome.stats.twins)?;
        json["sync"] = serde_json::to_value(&outcome.stats.sync)?;
        json["pprz_sent"] = outcome.stats.pprz_sent.into();
        json["failsafe"] = serde_json::to_value(&outcome.stats.failsafe)?;
        json["inputs"] = inputs_json(&outcome.stats);
        json["log_error"] = log_error.as_ref().map_or(serde_json::Value::Null, |e| format!("{e:#}").into());
        json["shard"] = serde_json::to_value(shardcmd::section(&outcome.state, &outcome.stats, outcome.link.as_ref()))?;
        outln!("{}", serde_json::to_string_pretty(&json)?);
    } else {
        out!("{}", summary.to_text());
        if let Some(s) = shardcmd::section(&outcome.state, &outcome.stats, outcome.link.as_ref()) {
            shardcmd::print_section(&s);
        }
        outln!("  log: {}", log_stats.as_ref().map_or("off (--no-log)".into(), logcmd::describe));
        if let Some(l) = &live_stats {
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
        match outcome.bus.as_ref().map(|b| (b, &b.prefix)) {
            Some((b, Some(prefix))) => {
                outln!(
                    "  bus: zenoh, prefix {prefix}; {} commands accepted, {} rejected ({} not from the copter's controller); {} samples published; {} clients seen",
                    b.commands_accepted,
                    b.commands_rejected,
                    b.commands_not_controller,
                    b.published,
                    b.clients_seen
                );
                if b.tracking_rejected + b.requests_dropped + b.spawns_rejected + b.publish_failed > 0 {
                    outln!(
                        "    {} tracking poses rejected, {} spawn requests refused; {} inputs dropped (step loop's queue full); {} frames not fully published",
                        b.tracking_rejected,
                        b.spawns_rejected,
                        b.requests_dropped,
                        b.publish_failed
                    );
                }
            }
            _ => outln!("  bus: zenoh off (--no-bus)"),
        }
        if let Some(i) = outcome.bus.as_ref().and_then(|b| b.ivy.as_ref()) {
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
        if let Some(b) = &outcome.bus {
            outln!("  paparazzi: {} messages sent (virtual sonar, virtual telemetry)", outcome.stats.pprz_sent);
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
                outln!(
                    "    zenoh: {} texts matched no binding, {} payloads not UTF-8 (dropped)",
                    z.unmatched,
                    z.not_utf8
                );
            }
        }
        for (name, s) in &outcome.stats.sync {
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
        for (name, t) in &outcome.stats.twins {
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
        let st = &outcome.stats;
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
        if !outcome.stats.failsafe.is_empty() {
            let counts: Vec<String> = outcome.stats.failsafe.iter().map(|(k, n)| format!("{n} {k}")).collect();
            outln!("  failsafe: {}", counts.join(", "));
            for (tick, message) in &failsafe_events {
                outln!("    step {tick}: {message}");
            }
            let total: u64 = outcome.stats.failsafe.values().sum();
            if total > failsafe_events.len() as u64 {
                outln!("    … {} more in the log (/events)", total - failsafe_events.len() as u64);
            }
        }
        if interrupted.is_some() {
            outln!(
                "  interrupted by a signal after {:.2} s simulated; the log was finished cleanly",
                outcome.state.time_s(&outcome.world)
            );
        }
    }
    if let Some(e) = &outcome.stats.shard_error {
        // The log and the summary hold everything up to here.
        anyhow::bail!("shard stopped at control step {}: {e}", outcome.state.tick);
    }
    match log_error {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

/// What became of the inputs that reached the loop, for `--json` and the log's `bus_report`.
fn inputs_json(st: &bridge::sim::LoopStats) -> serde_json::Value {
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

/// Follows the step loop: summary tracker, MCAP log, progress bar.
struct RunObserver {
    tracker: report::Tracker,
    log: Option<bridge::log::Logger>,
    log_error: Option<anyhow::Error>,
    /// The control step at which the log failed.
    log_error_tick: Option<u64>,
    /// `--on-log-error stop`: the run's stop flag, set when the log fails.
    stop_on_log_error: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>,
    /// The first failsafe transitions, for the summary.
    failsafe_events: Vec<(u64, String)>,
    /// The last control step observed.
    tick: u64,
    progress: Option<indicatif::ProgressBar>,
}

impl RunObserver {
    /// Logs an event, if logging.
    fn log_event(&mut self, event: bridge::log::LogEvent) {
        let tick = event.tick;
        if let Some(log) = &mut self.log
            && let Err(e) = log.log_event(event)
        {
            self.log_failed(tick, e.into());
        }
    }

    /// The log failed: keep the first error, stop logging, and stop the run if asked to.
    fn log_failed(&mut self, tick: u64, e: anyhow::Error) {
        if self.log_error.is_none() {
            tracing::error!("logging failed at control step {tick}: {e:#}");
            self.log_error = Some(e);
            self.log_error_tick = Some(tick);
        }
        self.log = None;
        if let Some(stop) = &self.stop_on_log_error {
            stop.store(true, std::sync::atomic::Ordering::Relaxed);
        }
    }
}

impl bridge::sim::StepObserver for RunObserver {
    fn after_step(
        &mut self,
        world: &sim_core::World,
        state: &sim_core::State,
        inputs: &sim_core::Inputs,
        report: &sim_core::StepReport,
    ) {
        self.tracker.observe(world, state, report);
        self.tick = state.tick;
        if let Some(log) = &mut self.log
            && let Err(e) = log.log_step(world, state, inputs, report)
        {
            self.log_failed(state.tick, e.into());
        }
        if let Some(bar) = &self.progress
            && state.tick.is_multiple_of(20)
        {
            bar.set_position(state.tick);
        }
    }

    fn bus_input(&mut self, input: &bridge::sim::BusInput) {
        if let Some(log) = &mut self.log
            && let Err(e) = log.log_bus_message(&input.key, true, &input.text, input.received_unix_ns)
        {
            self.log_failed(self.tick, e.into());
        }
    }

    fn input_rejected(&mut self, tick: u64, input: &bridge::sim::BusInput, reason: &str) {
        self.bus_input(input);
        self.log_event(bridge::log::LogEvent {
            tick,
            kind: bridge::log::EventKind::InputRejected,
            copter: None,
            detail: Some(serde_json::json!({ "key": input.key, "reason": reason })),
            message: format!("rejected input on {}: {reason}", input.key),
        });
    }

    fn spawned(&mut self, world: &sim_core::World, id: usize, tick: u64) {
        self.log_event(bridge::log::LogEvent {
            tick,
            kind: bridge::log::EventKind::Spawned,
            copter: Some(id),
            detail: None,
            message: format!("spawned copter {:?}", world.copters[id].name),
        });
    }

    fn pprz_out(&mut self, tick: u64, out: &bridge::mixed::PprzOut) {
        if let Some(log) = &mut self.log
            && let Err(e) = log.log_bus_message(&out.key, false, &out.text, bridge::log::now_unix_ns())
        {
            self.log_failed(tick, e.into());
        }
    }

    fn paired(&mut self, tick: u64, ac_id: u8, id: usize, copter: &str) {
        self.log_event(bridge::log::LogEvent {
            tick,
            kind: bridge::log::EventKind::Paired,
            copter: Some(id),
            detail: Some(serde_json::json!({ "ac_id": ac_id, "copter": copter, "spawned": true })),
            message: format!("aircraft {ac_id} paired with its new twin {copter:?} (spawned on first telemetry)"),
        });
    }

    fn overrun(&mut self, tick: u64, late_s: f64) {
        if let Err(e) = logcmd::log_overrun(&mut self.log, tick, late_s) {
            self.log_failed(tick, e);
        }
    }

    fn frame_dropped(&mut self, tick: u64, pprz_lost: u64) {
        self.log_event(bridge::log::LogEvent {
            tick,
            kind: bridge::log::EventKind::FrameDropped,
            copter: None,
            detail: Some(serde_json::json!({ "pprz_lost": pprz_lost })),
            message: format!("step {tick} not published (publisher behind); {pprz_lost} Paparazzi texts not sent"),
        });
    }

    fn failsafe(&mut self, tick: u64, world: &sim_core::World, event: &bridge::failsafe::FailsafeEvent) {
        let message = event.message(world);
        if self.failsafe_events.len() < MAX_SUMMARY_EVENTS {
            self.failsafe_events.push((tick, message.clone()));
        }
        self.log_event(bridge::log::LogEvent {
            tick,
            kind: bridge::log::EventKind::Failsafe,
            copter: Some(event.copter),
            detail: serde_json::to_value(&event.kind).ok(),
            message,
        });
    }
}

/// Failsafe transitions the text summary lists one by one (the log has them all).
const MAX_SUMMARY_EVENTS: usize = 8;

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

/// What a shard cannot do yet.
fn check_shardable(args: &RunArgs, spec: &SceneSpec) -> anyhow::Result<()> {
    let unsharded = [(args.ivy.is_some(), "--ivy"), (args.pairing.is_some(), "--pairing")];
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

/// `cluster SCENE --shards N`.
fn cluster_cmd(args: &ClusterArgs) -> anyhow::Result<()> {
    if !(1..=64).contains(&args.shards) {
        return Err(BadInput(anyhow::anyhow!("--shards must be 1 to 64 local processes, got {}", args.shards)).into());
    }
    // Check the scene here, so that a bad one is one clear error rather than N.
    let (_, spec, _) = load_scene(args.scene.as_deref())?;
    sim_core::shard::Partition::new(&scene::compile(&spec).map_err(|e| BadInput(e.into()))?, args.shards)
        .map_err(|e| BadInput(e.into()))?;
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
    for p in &s.per_shard {
        println!("shard {}: {:.2}x real time, {:.2} s wall", p.shard.shard, p.real_time_factor, p.wall_time_s);
        shardcmd::print_section(&p.shard);
    }
    println!("digest of the swarm: {}", s.digest);
    Ok(())
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
