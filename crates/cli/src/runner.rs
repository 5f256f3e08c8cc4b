//! Runs a world: the step loop on its own thread, and, unless `--no-bus`, the Zenoh node on a
//! tokio multi-thread runtime publishing its frames and feeding it commands. The caller's stop
//! flag (set by SIGINT/SIGTERM) ends the loop after the current step; the session is then
//! closed explicitly.

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;
use bridge::mixed::{Gateway, GatewayReport, OutboxOptions, TelemetryPlan, TwinAttitude};
use bridge::node::{self, Node};
use bridge::pairing::ResolvedPairing;
use bridge::sim::{self, LoopOptions, LoopStats, Request, StepObserver};
use bridge::sync::SyncOptions;
use sim_core::{State, World};

/// Bus options from the command line.
#[derive(Debug, Clone, Default)]
pub struct BusOptions {
    /// Run without Zenoh.
    pub no_bus: bool,
    /// A full Zenoh configuration file (JSON5).
    pub zenoh_config: Option<PathBuf>,
    /// Endpoints to listen on (override).
    pub listen: Vec<String>,
    /// Endpoints to connect to (override).
    pub connect: Vec<String>,
    /// Key-expression prefix (default `twinswarm/<world>`).
    pub prefix: Option<String>,
    /// Mixed reality: pairing, telemetry plan, virtual sonar rate.
    pub mixed: MixedOptions,
}

/// Mixed-reality options (see `bridge::mixed`).
#[derive(Debug, Clone)]
pub struct MixedOptions {
    /// The pairing checked against its conf.xml.
    pub pairing: Option<ResolvedPairing>,
    /// What virtual copters send.
    pub plan: TelemetryPlan,
    /// `VIRTUAL_SONAR` period per twin, s; 0: at every sonar update.
    pub virtual_sonar_period_s: f64,
    /// Which telemetry sets twins' attitude targets.
    pub twin_attitude: TwinAttitude,
    /// How twins are kept where their real copters are (`None`: not at all).
    pub sync: Option<SyncOptions>,
}

impl Default for MixedOptions {
    fn default() -> Self {
        Self {
            pairing: None,
            plan: TelemetryPlan::project_default(),
            virtual_sonar_period_s: 0.0,
            twin_attitude: TwinAttitude::default(),
            sync: Some(SyncOptions::default()),
        }
    }
}

/// What a run leaves behind.
#[derive(Debug)]
pub struct RunOutcome {
    pub world: Arc<World>,
    pub state: State,
    pub stats: LoopStats,
    pub bus: Option<BusReport>,
}

/// Counters of the bus side.
#[derive(Debug, Clone, serde::Serialize)]
pub struct BusReport {
    pub prefix: String,
    pub commands_accepted: u64,
    pub commands_rejected: u64,
    pub published: u64,
    pub clients_seen: u64,
    pub telemetry: GatewayReport,
}

/// Builds the Zenoh configuration: the file if given (with `--listen`/`--connect` applied on
/// top), else the embedded default (peer, `tcp/127.0.0.1:7447`, multicast scouting off).
pub fn zenoh_config(opts: &BusOptions) -> anyhow::Result<zenoh::Config> {
    match &opts.zenoh_config {
        None => Ok(node::default_config(&opts.listen, &opts.connect)?),
        Some(path) => {
            let mut c = zenoh::Config::from_file(path)
                .map_err(|e| anyhow::anyhow!("{e}"))
                .with_context(|| format!("cannot load zenoh config {}", path.display()))?;
            if !opts.listen.is_empty() {
                c.insert_json5("listen/endpoints", &serde_json::to_string(&opts.listen)?)
                    .map_err(|e| anyhow::anyhow!("--listen: {e}"))?;
            }
            if !opts.connect.is_empty() {
                c.insert_json5("connect/endpoints", &serde_json::to_string(&opts.connect)?)
                    .map_err(|e| anyhow::anyhow!("--connect: {e}"))?;
            }
            Ok(c)
        }
    }
}

/// Runs `ticks` control steps of `world`.
pub fn run(
    world: World,
    ticks: u64,
    realtime: bool,
    bus: &BusOptions,
    observer: &mut (dyn StepObserver + Send),
    stop: Arc<AtomicBool>,
) -> anyhow::Result<RunOutcome> {
    let state = world.initial_state();
    let inputs = world.initial_inputs();
    let mut opts = LoopOptions { realtime, ticks, outbox: None, sync: None };
    let (req_tx, req_rx) = std::sync::mpsc::sync_channel::<Request>(1024);

    if bus.no_bus {
        let (world, state, stats) = sim::run_loop(world, state, inputs, req_rx, None, observer, &stop, &opts);
        drop(req_tx);
        return Ok(RunOutcome { world, state, stats, bus: None });
    }

    let config = zenoh_config(bus)?;
    let prefix = bus.prefix.clone().unwrap_or_else(|| node::default_prefix(&world));
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let world_arc = Arc::new(world.clone());
    let mut node = rt
        .block_on(Node::open(config, prefix.clone(), world_arc.clone(), req_tx.clone()))
        .with_context(|| format!("cannot start the Zenoh node (prefix {prefix})"))?;
    let messages = Arc::new(bridge::pprz::project_messages());
    let gateway = rt
        .block_on(Gateway::start(
            node.session().clone(),
            &prefix,
            world_arc.clone(),
            bus.mixed.pairing.clone(),
            messages.clone(),
            req_tx.clone(),
            bus.mixed.twin_attitude,
        ))
        .context("cannot bind the Paparazzi telemetry")?;
    opts.sync = bus.mixed.sync.clone();
    opts.outbox = Some(OutboxOptions {
        prefix: prefix.clone(),
        messages,
        plan: bus.mixed.plan.clone(),
        virtual_sonar_period_s: bus.mixed.virtual_sonar_period_s,
    });
    let (frame_tx, mut frame_rx) = tokio::sync::mpsc::channel(256);

    let outcome = std::thread::scope(|s| -> anyhow::Result<(Arc<World>, State, LoopStats)> {
        let stop_loop = stop.clone();
        let h =
            s.spawn(move || sim::run_loop(world, state, inputs, req_rx, Some(frame_tx), observer, &stop_loop, &opts));
        rt.block_on(async {
            // Publish until the loop ends (its frame sender drops).
            while let Some(frame) = frame_rx.recv().await {
                gateway.set_world(&frame.world);
                if let Err(e) = node.publish(&frame).await {
                    tracing::warn!("publish failed: {e}");
                }
            }
        });
        h.join().map_err(|_| anyhow::anyhow!("the step loop panicked"))
    })?;
    drop(req_tx);
    let c = &node.counters;
    let report = BusReport {
        prefix,
        commands_accepted: c.commands_accepted.load(Ordering::Relaxed),
        commands_rejected: c.commands_rejected.load(Ordering::Relaxed),
        published: c.published.load(Ordering::Relaxed),
        clients_seen: c.clients_seen.load(Ordering::Relaxed),
        telemetry: gateway.report(),
    };
    drop(gateway);
    rt.block_on(node.close()).context("closing the Zenoh session")?;
    let (world, state, stats) = outcome;
    Ok(RunOutcome { world, state, stats, bus: Some(report) })
}
