//! Runs a world: the step loop on its own thread, and, unless `--no-bus`, the Zenoh node on a
//! tokio multi-thread runtime publishing its frames and feeding it commands. The caller's stop
//! flag (set by SIGINT/SIGTERM) ends the loop after the current step; the session is then
//! closed explicitly.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;
use bridge::engine::failsafe::FailsafeOptions;
use bridge::engine::flight::{Flight, Recorder};
use bridge::engine::{self, LoopOptions, Request, StepObserver};
use bridge::mixed::gateway::{Gateway, PprzLinks};
use bridge::mixed::interpreter::{GatewayReport, TwinAttitude};
use bridge::mixed::outbox::OutboxOptions;
use bridge::mixed::plan::TelemetryPlan;
use bridge::mixed::sync::SyncOptions;
use bridge::paparazzi::ivy::{IvyAgent, IvyOptions};
use bridge::paparazzi::pairing::ResolvedPairing;
use bridge::shard::ShardLink;
use bridge::zenoh_net::node::{self, Node};
use sim_core::World;
use sim_core::shard::Partition;
use std::sync::Mutex;
use twinswarm::BadInput;
use twinswarm::transport::{ZenohArgs, ZenohRole};
use zenoh::Wait;

/// Bus options from the command line.
#[derive(Debug, Clone, Default)]
pub struct BusOptions {
    /// Run without Zenoh.
    pub no_bus: bool,
    /// The Zenoh flags: configuration, endpoints, key-expression prefix (default
    /// `twinswarm/<world>`).
    pub zenoh: ZenohArgs,
    /// Mixed reality: pairing, telemetry plan, virtual sonar rate.
    pub mixed: MixedOptions,
    /// Join this Ivy bus (Paparazzi's ground segment) as well, or instead of Zenoh with
    /// `no_bus`.
    pub ivy: Option<bridge::paparazzi::ivy::BusAddr>,
    /// Lost links and lost controllers.
    pub failsafe: FailsafeOptions,
    /// Step only one shard of the swarm (see `sim_core::shard`).
    pub shard: Option<ShardOptions>,
    /// Also be a ROS 2 node on the Zenoh session (see `bridge::ros2`).
    pub ros2: Option<bridge::ros2::Ros2Options>,
}

/// `--shard K/N` and its barrier timeout.
#[derive(Debug, Clone)]
pub struct ShardOptions {
    pub shard: usize,
    pub shards: usize,
    pub timeout: std::time::Duration,
    /// When a neighbour's liveliness token goes away: stop, or hold until it is back.
    pub on_lost: bridge::shard::OnLost,
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
    /// The message definitions of the lab's Paparazzi.
    pub messages: Arc<bridge::paparazzi::messages::MessageSet>,
    /// Per aircraft, a virtual-sonar uplink other than the one `messages` defines.
    pub uplinks: std::collections::BTreeMap<u8, bridge::paparazzi::convert::Uplink>,
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
            messages: Arc::new(bridge::paparazzi::convert::project_messages()),
            uplinks: Default::default(),
            twin_attitude: TwinAttitude::default(),
            sync: Some(SyncOptions::default()),
        }
    }
}

/// What a run leaves behind.
#[derive(Debug)]
pub struct RunOutcome<W> {
    /// The flight at its end.
    pub end: engine::Finished<W>,
    pub bus: Option<BusReport>,
    /// A shard: what its barrier cost.
    pub link: Option<bridge::shard::LinkStats>,
}

/// Counters of the bus side.
#[derive(Debug, Clone, serde::Serialize)]
pub struct BusReport {
    /// `None` without Zenoh.
    pub prefix: Option<String>,
    pub commands_accepted: u64,
    pub commands_rejected: u64,
    pub published: u64,
    pub clients_seen: u64,
    /// Commands rejected because another client controls the copter.
    pub commands_not_controller: u64,
    pub tracking_rejected: u64,
    pub spawns_rejected: u64,
    /// Frames whose publishing failed part-way.
    pub publish_failed: u64,
    /// Inputs dropped because the step loop's queue was full.
    pub requests_dropped: u64,
    /// Queryable replies (scene, copters, spawn) that could not be sent.
    pub replies_failed: u64,
    pub telemetry: GatewayReport,
    /// Paparazzi texts on Zenoh (`None` without Zenoh).
    pub zenoh_texts: Option<ZenohTexts>,
    pub ivy: Option<IvyReport>,
    /// The ROS 2 node's figures (`None` without `--ros2`).
    pub ros2: Option<bridge::ros2::Ros2Stats>,
}

/// Paparazzi texts on Zenoh: samples received, handler calls, texts on a subscribed key that no
/// binding matched, payloads dropped for not being UTF-8.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ZenohTexts {
    pub received: u64,
    pub delivered: u64,
    pub unmatched: u64,
    pub not_utf8: u64,
}

/// What the Ivy side saw.
#[derive(Debug, Clone, serde::Serialize)]
pub struct IvyReport {
    pub bus: String,
    pub app_name: String,
    pub peers_joined: u64,
    pub peers_left: u64,
    pub peers_at_end: Vec<String>,
    pub lines_received: u64,
    pub msgs_received: u64,
    pub delivered: u64,
    pub texts_sent: u64,
    pub msgs_sent: u64,
    pub peer_regexes: u64,
    pub bridged_ivy_to_zenoh: u64,
    pub bridged_zenoh_to_ivy: u64,
    pub bridge_dropped: u64,
    /// Dropped hellos, lines and messages by reason.
    pub dropped: std::collections::BTreeMap<String, u64>,
    pub events: Vec<bridge::paparazzi::ivy::PeerEvent>,
}

impl IvyReport {
    fn of(agent: &IvyAgent, bus: &str, gateway: &Gateway) -> Self {
        let c = agent.counters();
        let b = gateway.bridged();
        let l = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
        Self {
            bus: bus.to_owned(),
            app_name: IVY_APP_NAME.to_owned(),
            peers_joined: l(&c.peers_joined),
            peers_left: l(&c.peers_left),
            peers_at_end: agent.peers().into_iter().map(|p| p.app_name).collect(),
            lines_received: l(&c.lines),
            msgs_received: l(&c.msgs_received),
            delivered: l(&c.delivered),
            texts_sent: l(&c.texts_sent),
            msgs_sent: l(&c.msgs_sent),
            peer_regexes: l(&c.peer_regexes),
            bridged_ivy_to_zenoh: l(&b.ivy_to_zenoh),
            bridged_zenoh_to_ivy: l(&b.zenoh_to_ivy),
            bridge_dropped: l(&b.dropped_queue_full) + l(&b.dropped_unsendable) + l(&b.dropped_put_failed),
            dropped: agent.drops().into_iter().map(|(k, v)| (k.to_owned(), v)).collect(),
            events: agent.events(),
        }
    }
}

/// Inputs the step loop's queue holds between two steps.
pub const REQUEST_QUEUE: usize = 8192;

/// The simulator's app name on an Ivy bus.
pub const IVY_APP_NAME: &str = "Twinswarm";

/// The Zenoh configuration of `run`: a peer's, or a shard's with `--shard`.
fn zenoh_config(opts: &BusOptions) -> anyhow::Result<zenoh::Config> {
    opts.zenoh.config(if opts.shard.is_some() { ZenohRole::Shard } else { ZenohRole::Peer })
}

/// How `run` paces the flight.
#[derive(Debug, Clone, Default)]
pub struct Pace {
    /// Control steps to run.
    pub ticks: u64,
    /// Against the wall clock.
    pub realtime: bool,
    /// Hold each step for the claimed copters' controllers.
    pub lockstep: Option<bridge::engine::LockstepOptions>,
    /// Wait for the outside autopilots of the `autopilot` copters, and step with them.
    pub autopilots: Option<bridge::autopilot::AutopilotOptions>,
}

/// Where a run starts and what it saves: a checkpoint to go on from (`--resume`), and
/// checkpoints to write (`--checkpoint-every`).
#[derive(Debug, Default)]
pub struct Durability {
    pub resume: Option<bridge::engine::checkpoint::Checkpoint>,
    pub checkpoint: Option<bridge::engine::checkpoint::CheckpointOptions>,
}

/// The first state, its inputs, a shard's neighbours and the batches a checkpoint kept:
/// `world`'s initial state, or the checkpoint's (made the shard it was).
fn start_state(
    world: &World,
    bus: &BusOptions,
    resume: Option<bridge::engine::checkpoint::Checkpoint>,
) -> anyhow::Result<(sim_core::State, sim_core::Inputs, Vec<u16>, Vec<bridge::shard::GhostBatch>)> {
    let (mut state, inputs, snapshot, early) = match resume {
        Some(c) => (c.state, c.inputs, c.shard, c.early),
        None => (world.initial_state(), world.initial_inputs(), None, Vec::new()),
    };
    let Some(o) = &bus.shard else { return Ok((state, inputs, Vec::new(), early)) };
    let partition = Partition::new(world, o.shards).map_err(|e| BadInput(e.into()))?;
    let neighbours = partition.neighbours(o.shard as u16);
    match snapshot {
        Some(snap) => state.restore_shard(partition, snap),
        None => state.make_shard(partition, o.shard),
    }
    .map_err(|e| BadInput(e.into()))?;
    if !neighbours.is_empty() && !bus.zenoh.names_endpoints() {
        return Err(BadInput(anyhow::anyhow!(
            "--shard {}/{}: a shard with neighbours needs --connect (a Zenoh router) or --listen",
            o.shard,
            o.shards
        ))
        .into());
    }
    Ok((state, inputs, neighbours, early))
}

/// Flies `world` for `pace.ticks` control steps (the rest of them, from a checkpoint),
/// recording into `recorder`, with `watch` following every step.
#[allow(clippy::too_many_arguments)]
pub fn run<W: StepObserver + Send>(
    rt: &tokio::runtime::Runtime,
    world: World,
    pace: &Pace,
    bus: &BusOptions,
    durability: Durability,
    recorder: Recorder,
    watch: W,
    stop: Arc<AtomicBool>,
) -> anyhow::Result<RunOutcome<W>> {
    let (state, inputs, neighbours, early) = start_state(&world, bus, durability.resume)?;
    let mut opts = loop_options(&world, pace, bus, durability.checkpoint, state.tick)?;
    // Room for 8,192 inputs between two steps: 160,000 per second at 50 ms, five times the
    // flood test's 30,000 (scripts/flood.sh); beyond, inputs are dropped and counted.
    let (req_tx, req_rx) = std::sync::mpsc::sync_channel::<Request>(REQUEST_QUEUE);
    let prefix = bus.zenoh.prefix.clone().unwrap_or_else(|| node::default_prefix(&world));
    let early = Mutex::new(Some(early));
    let link_at = LinkAt { prefix: &prefix, neighbours: &neighbours, early: &early, tick: state.tick, stop: &stop };
    let open_link = |session: zenoh::Session| open_shard_link(session, bus, &link_at);

    if bus.no_bus && bus.ivy.is_none() {
        let session = match neighbours.is_empty() {
            true => None,
            false => Some(zenoh::open(zenoh_config(bus)?).wait().map_err(|e| anyhow::anyhow!("zenoh: {e}"))?),
        };
        opts.shard = session.clone().map(&open_link).transpose()?;
        let flight = Flight::new(world, state, inputs, &opts, recorder, watch);
        let end = engine::run_loop(flight, req_rx, None, &stop, &opts);
        drop(req_tx);
        let link_stats = opts.shard.take().map(|l| bridge::lock(&l).stats().clone());
        if let Some(s) = session {
            // Closing withdraws the shard's token: neighbours still waiting learn it is gone.
            s.close().wait().map_err(|e| anyhow::anyhow!("zenoh: {e}"))?;
        }
        return Ok(RunOutcome { end, bus: None, link: link_stats });
    }

    let world_arc = Arc::new(world.clone());
    let mut node = open_node(rt, bus, &prefix, &world_arc, &req_tx)?;
    let mut ros = match (&bus.ros2, &node) {
        (Some(o), Some(n)) => Some(
            bridge::ros2::Ros2Node::open(n.session(), &world_arc, n.commands(), o.clone())
                .context("cannot start the ROS 2 node")?,
        ),
        _ => None,
    };
    if !neighbours.is_empty() {
        let session = match &node {
            Some(n) => n.session().clone(),
            None => zenoh::open(zenoh_config(bus)?).wait().map_err(|e| anyhow::anyhow!("zenoh: {e}"))?,
        };
        opts.shard = Some(open_link(session)?);
    }
    let ivy = join_ivy(rt, bus, &stop)?;
    let gateway = start_gateway(rt, bus, &node, &ivy, &prefix, &world_arc, &req_tx)?;
    opts.sync = bus.mixed.sync.clone();
    opts.outbox = Some(outbox_options(bus, &prefix, &world_arc));
    if let (Some(aps), Some(ivy), Some(outbox)) = (&opts.autopilots, &ivy, &opts.outbox) {
        // The autopilots' uplink goes on the Ivy bus, through Paparazzi's link: in the lockstep.
        let none = bridge::paparazzi::convert::Uplink::None;
        bridge::lock(aps)
            .count_uplinks(ivy, |ac| outbox.uplink_for(ac) != none)
            .context("cannot watch the Ivy bus for the autopilots' telemetry")?;
    }
    let (frame_tx, mut frame_rx) = tokio::sync::mpsc::channel(256);
    let opts_link = opts.shard.clone();
    let flight = Flight::new(world, state, inputs, &opts, recorder, watch);

    let end = std::thread::scope(|s| -> anyhow::Result<engine::Finished<W>> {
        let stop_loop = stop.clone();
        let h = s.spawn(move || engine::run_loop(flight, req_rx, Some(frame_tx), &stop_loop, &opts));
        rt.block_on(publish_frames(&mut frame_rx, &gateway, &mut node, &mut ros));
        h.join().map_err(|_| anyhow::anyhow!("the step loop panicked"))
    })?;
    drop(req_tx);
    let report = bus_report(bus, node.as_ref(), prefix, &gateway, ivy.as_ref(), ros.as_ref());
    if let Some(r) = &mut ros {
        r.stop_graph();
    }
    drop(gateway);
    if let Some(agent) = ivy {
        rt.block_on(agent.stop());
    }
    if let Some(node) = node {
        rt.block_on(node.close()).context("closing the Zenoh session")?;
    }
    // After the session: its tokens then go with it, not one by one.
    drop(ros);
    let link = opts_link.map(|l| bridge::lock(&l).stats().clone());
    Ok(RunOutcome { end, bus: Some(report), link })
}

/// The step loop's options for the flight from `tick` on; with `--autopilots`, waits until the
/// outside autopilots have connected.
fn loop_options(
    world: &World,
    pace: &Pace,
    bus: &BusOptions,
    checkpoint: Option<bridge::engine::checkpoint::CheckpointOptions>,
    tick: u64,
) -> anyhow::Result<LoopOptions> {
    let mut opts = LoopOptions {
        realtime: pace.realtime,
        ticks: pace.ticks.saturating_sub(tick),
        failsafe: bus.failsafe.clone(),
        lockstep: pace.lockstep.clone(),
        checkpoint,
        ..Default::default()
    };
    if let Some(o) = &pace.autopilots {
        let n = world.copters.iter().filter(|c| c.kind == sim_core::CopterKind::Autopilot).count();
        let aps = bridge::autopilot::Autopilots::accept_with(world, o, |at| {
            eprintln!("waiting for {n} autopilot(s) on {at} (at most {:.0} s)", o.connect_timeout.as_secs_f64());
        })?;
        eprintln!("{} autopilot(s) connected, stepping", aps.len());
        opts.autopilots = Some(Arc::new(Mutex::new(aps)));
    }
    Ok(opts)
}

/// Where a shard's link is opened: under `prefix`, to `neighbours`, preloaded with the batches
/// a checkpoint kept (`early`, taken once) for the state at `tick`; its waits for neighbours end
/// on `stop`.
struct LinkAt<'a> {
    prefix: &'a str,
    neighbours: &'a [u16],
    early: &'a Mutex<Option<Vec<bridge::shard::GhostBatch>>>,
    tick: u64,
    stop: &'a Arc<AtomicBool>,
}

/// The shard's link to its neighbours, on `session`; it waits until they are all up.
fn open_shard_link(
    session: zenoh::Session,
    bus: &BusOptions,
    at: &LinkAt<'_>,
) -> anyhow::Result<Arc<Mutex<ShardLink>>> {
    let o = bus.shard.as_ref().expect("only for shards");
    let mut link = ShardLink::on(session, at.prefix, o.shard as u16, at.neighbours.to_vec(), o.timeout)?
        .on_lost(o.on_lost)
        .stop_on(at.stop.clone());
    link.preload(bridge::lock(at.early).take().unwrap_or_default(), at.tick);
    link.wait_for_neighbours()?;
    let n = at.neighbours.len();
    tracing::info!("shard {}/{}: {n} neighbour(s) up, stepping", o.shard, o.shards);
    eprintln!("shard {}/{}: {n} neighbour(s) up, stepping", o.shard, o.shards);
    Ok(Arc::new(Mutex::new(link)))
}

/// The Zenoh node under `prefix`, feeding `requests`; `None` with `--no-bus`.
fn open_node(
    rt: &tokio::runtime::Runtime,
    bus: &BusOptions,
    prefix: &str,
    world: &Arc<World>,
    requests: &std::sync::mpsc::SyncSender<Request>,
) -> anyhow::Result<Option<Node>> {
    match bus.no_bus {
        true => Ok(None),
        false => {
            let config = zenoh_config(bus)?;
            Ok(Some(
                rt.block_on(Node::open(config, prefix.to_owned(), world.clone(), requests.clone()))
                    .with_context(|| format!("cannot start the Zenoh node (prefix {prefix})"))?,
            ))
        }
    }
}

/// Joins the Ivy bus of `--ivy` (its peers' die message sets `stop`); `None` without one.
fn join_ivy(
    rt: &tokio::runtime::Runtime,
    bus: &BusOptions,
    stop: &Arc<AtomicBool>,
) -> anyhow::Result<Option<Arc<IvyAgent>>> {
    match &bus.ivy {
        None => Ok(None),
        Some(addr) => {
            let mut o = IvyOptions::new(addr.clone(), IVY_APP_NAME);
            o.on_die = Some(stop.clone());
            Ok(Some(Arc::new(rt.block_on(IvyAgent::start(o)).context("cannot join the Ivy bus")?)))
        }
    }
}

/// Binds the Paparazzi telemetry on the Zenoh node's session and the Ivy bus, whichever there are.
fn start_gateway(
    rt: &tokio::runtime::Runtime,
    bus: &BusOptions,
    node: &Option<Node>,
    ivy: &Option<Arc<IvyAgent>>,
    prefix: &str,
    world: &Arc<World>,
    requests: &std::sync::mpsc::SyncSender<Request>,
) -> anyhow::Result<Gateway> {
    let links = PprzLinks { zenoh: node.as_ref().map(|n| (n.session().clone(), prefix.to_owned())), ivy: ivy.clone() };
    rt.block_on(Gateway::start(
        links,
        world.clone(),
        bus.mixed.pairing.clone(),
        bus.mixed.messages.clone(),
        requests.clone(),
        bus.mixed.twin_attitude,
    ))
    .context("cannot bind the Paparazzi telemetry")
}

/// What the step loop sends Paparazzi (virtual copters' telemetry, twins' virtual sonar);
/// the twins' uplinks are noted on stderr.
fn outbox_options(bus: &BusOptions, prefix: &str, world: &World) -> OutboxOptions {
    let outbox = OutboxOptions {
        prefix: prefix.to_owned(),
        messages: bus.mixed.messages.clone(),
        plan: bus.mixed.plan.clone(),
        virtual_sonar_period_s: bus.mixed.virtual_sonar_period_s,
        uplinks: bus.mixed.uplinks.clone(),
    };
    // Stderr, like the other start-up notes: stdout is the summary (and `--json`).
    for line in outbox.uplink_lines(world) {
        eprintln!("twin {line}");
    }
    outbox
}

/// Publishes the step loop's frames (Ivy, Zenoh, ROS 2) until the loop ends (its frame sender
/// drops).
async fn publish_frames(
    frame_rx: &mut tokio::sync::mpsc::Receiver<engine::Frame>,
    gateway: &Gateway,
    node: &mut Option<Node>,
    ros: &mut Option<bridge::ros2::Ros2Node>,
) {
    while let Some(frame) = frame_rx.recv().await {
        gateway.set_world(&frame.world);
        gateway.send_ivy(&frame.pprz_out);
        if let Some(node) = node {
            // Each side publishes whatever the other's fate: a ROS controller under
            // lockstep waits for its `/clock`.
            let mut published = node.publish(&frame).await;
            if let Some(ros) = ros {
                published = published.and(ros.publish(&frame));
            }
            if let Err(e) = published {
                let n = node.counters.publish_failed.fetch_add(1, Ordering::Relaxed) + 1;
                if n.is_power_of_two() {
                    tracing::warn!("{n} frames not fully published so far: {e}");
                }
            }
        }
    }
}

/// The bus side's counters at the end of the run.
fn bus_report(
    bus: &BusOptions,
    node: Option<&Node>,
    prefix: String,
    gateway: &Gateway,
    ivy: Option<&Arc<IvyAgent>>,
    ros: Option<&bridge::ros2::Ros2Node>,
) -> BusReport {
    let l = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
    let counters = node.map(|n| n.counters.clone());
    BusReport {
        prefix: node.map(|_| prefix),
        commands_accepted: counters.as_ref().map_or(0, |c| l(&c.commands_accepted)),
        commands_rejected: counters.as_ref().map_or(0, |c| l(&c.commands_rejected)),
        published: counters.as_ref().map_or(0, |c| l(&c.published)),
        clients_seen: counters.as_ref().map_or(0, |c| l(&c.clients_seen)),
        commands_not_controller: counters.as_ref().map_or(0, |c| l(&c.commands_not_controller)),
        tracking_rejected: counters.as_ref().map_or(0, |c| l(&c.tracking_rejected)),
        spawns_rejected: counters.as_ref().map_or(0, |c| l(&c.spawns_rejected)),
        publish_failed: counters.as_ref().map_or(0, |c| l(&c.publish_failed)),
        requests_dropped: counters.as_ref().map_or(0, |c| l(&c.requests_dropped)),
        replies_failed: counters.as_ref().map_or(0, |c| l(&c.replies_failed)),
        telemetry: gateway.report(),
        zenoh_texts: gateway.zenoh_bus().map(|z| {
            let c = &z.counters;
            ZenohTexts {
                received: l(&c.samples_received),
                delivered: l(&c.delivered),
                unmatched: l(&c.unmatched),
                not_utf8: l(&c.dropped_not_utf8),
            }
        }),
        ivy: ivy.zip(bus.ivy.as_ref()).map(|(a, addr)| IvyReport::of(a, &addr.to_string(), gateway)),
        ros2: ros.map(|r| r.stats()),
    }
}
