//! The Zenoh side: configuration, key expressions, publishing frames, the command subscriber,
//! queryables and liveliness.
//!
//! Key expressions, under a prefix (default `twinswarm/<world>`):
//!
//! | key | direction | payload |
//! |---|---|---|
//! | `…/clock` | out, every control step | [`ClockMsg`] |
//! | `…/copters/<name>/state` | out, every control step | [`StateMsg`](crate::wire::StateMsg) |
//! | `…/copters/<name>/sensors` | out, at the sonar rate | [`SensorsMsg`](crate::wire::SensorsMsg) |
//! | `…/copters/<name>/cmd` | in | [`CommandMsg`] |
//! | `…/copters/<name>/tracking` | in | [`TrackingMsg`](crate::wire::TrackingMsg) |
//! | `…/pprz/<ac_id>/<MSG_NAME>` | both | Paparazzi Ivy text |
//! | `…/scene` | queryable | the scene as JSON |
//! | `…/copters` | queryable | [`CopterListEntry`] list |
//! | `…/spawn` | queryable | JSON copter table in, name or error out |
//! | `…/alive/sim` | liveliness token of the simulator | |
//! | `…/alive/copters/<name>` | liveliness token of a client attached to a copter | |
//! | `…/alive/copters/<name>/<client>` | liveliness claim: `client` wants to command the copter | |
//!
//! **Who may command.** A copter that no client has claimed takes commands from anyone on
//! the bus (an open lab). Once a client declares the liveliness token
//! `…/alive/copters/<name>/<client>`, the copter takes commands only from it: commands must
//! carry `"client": "<client>"`, and any other is rejected, counted
//! ([`NodeCounters::commands_not_controller`]) and logged. Claims queue in the order they
//! arrive; when the controller's token disappears (it left, or its process or link died) the
//! next claim takes over, or, if there is none, the copter's lost-client failsafe applies
//! (see [`crate::engine::failsafe`]). This keeps two well-meaning clients from fighting over a copter;
//! against a hostile client, lock the bus with Zenoh's access control (`docs/security.md`).

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::SyncSender;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use sim_core::World;
use sim_core::scene::CopterSpec;
use zenoh::Wait;
use zenoh::sample::SampleKind;

use crate::engine::loop_io::Frame;
use crate::engine::request::Request;
use crate::wire::{ClockMsg, CommandMsg, CopterListEntry};

/// The default Zenoh endpoint the simulator listens on.
pub const DEFAULT_LISTEN: &str = "tcp/127.0.0.1:7447";

/// Errors of the Zenoh side.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    /// The Zenoh configuration is invalid.
    #[error("zenoh configuration: {0}")]
    Config(String),
    /// Zenoh failed to open or declare.
    #[error("zenoh: {0}")]
    Zenoh(String),
}

fn zerr(e: impl std::fmt::Display) -> NodeError {
    NodeError::Zenoh(e.to_string())
}

/// A Zenoh configuration in `mode` (`peer`, `client` or `router`), listening on `listen` and
/// connecting to `connect`, multicast scouting off: every configuration the project makes.
/// The data priority's transmission queue is Zenoh's largest, 16 batches of 64 kB per link
/// (allocated as they fill, Zenoh's default): a shard's ghost batch, a few hundred kB a step,
/// is handed to the link without waiting for the socket to drain the two batches of the
/// default (at 10,000 copters, 2 shards: encode and send 1.1-1.3 -> 0.6-0.9 ms a step).
pub fn config(mode: &str, listen: &[String], connect: &[String]) -> Result<zenoh::Config, NodeError> {
    let mut c = zenoh::Config::default();
    let json = |r: serde_json::Result<String>| r.map_err(|e| NodeError::Config(e.to_string()));
    for (k, v) in [
        ("mode", json(serde_json::to_string(mode))?),
        ("scouting/multicast/enabled", "false".to_owned()),
        ("listen/endpoints", json(serde_json::to_string(listen))?),
        ("connect/endpoints", json(serde_json::to_string(connect))?),
        ("transport/link/tx/queue/size/data", "16".to_owned()),
    ] {
        c.insert_json5(k, &v).map_err(|e| NodeError::Config(format!("{k}: {e}")))?;
    }
    Ok(c)
}

/// The embedded default configuration: peer mode, listening on `listen` (default
/// [`DEFAULT_LISTEN`]), connecting to `connect`, multicast scouting off.
pub fn default_config(listen: &[String], connect: &[String]) -> Result<zenoh::Config, NodeError> {
    let listen: Vec<String> = if listen.is_empty() { vec![DEFAULT_LISTEN.to_owned()] } else { listen.to_vec() };
    config("peer", &listen, connect)
}

/// A client configuration for tests and tools: client-less peer that only connects to
/// `connect`, listens nowhere, multicast scouting off.
pub fn client_config(connect: &[String]) -> Result<zenoh::Config, NodeError> {
    config("peer", &[], connect)
}

/// Counters shared between Zenoh callbacks and the reporter.
#[derive(Debug, Default)]
pub struct NodeCounters {
    /// Commands accepted and queued.
    pub commands_accepted: AtomicU64,
    /// Commands rejected (malformed, not finite, out of range, unknown copter, queue full).
    pub commands_rejected: AtomicU64,
    /// Samples published.
    pub published: AtomicU64,
    /// Clients seen through liveliness.
    pub clients_seen: AtomicU64,
    /// Commands rejected because another client controls the copter (also in
    /// `commands_rejected`).
    pub commands_not_controller: AtomicU64,
    /// Tracking poses rejected (malformed, out of range).
    pub tracking_rejected: AtomicU64,
    /// Spawn requests refused before they reached the loop (malformed, queue full).
    pub spawns_rejected: AtomicU64,
    /// Frames whose publishing failed part-way (the session closing, a Zenoh error).
    pub publish_failed: AtomicU64,
    /// Requests for the step loop dropped because its queue was full (commands, tracking,
    /// controller changes, rejections for the log).
    pub requests_dropped: AtomicU64,
    /// Queryable replies that could not be sent (the querier gone, the session closing).
    pub replies_failed: AtomicU64,
}

/// Counts a queryable reply that could not be sent.
fn count_failed<E>(counters: &NodeCounters, sent: Result<(), E>) {
    if sent.is_err() {
        counters.replies_failed.fetch_add(1, Ordering::Relaxed);
    }
}

/// Logs at most once per `period` (plus a count of what was suppressed).
#[derive(Debug)]
struct RateLimiter {
    last: Mutex<Option<Instant>>,
    suppressed: AtomicU64,
    period: Duration,
}

impl RateLimiter {
    fn new(period: Duration) -> Self {
        Self { last: Mutex::new(None), suppressed: AtomicU64::new(0), period }
    }
    fn warn(&self, what: &str) {
        let now = Instant::now();
        let mut last = crate::lock(&self.last);
        if last.is_none_or(|t| now.duration_since(t) >= self.period) {
            *last = Some(now);
            let n = self.suppressed.swap(0, Ordering::Relaxed);
            tracing::warn!("{what} ({n} similar messages suppressed)");
        } else {
            self.suppressed.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// Where commands from the bus go (Zenoh's `…/cmd`, ROS 2's `cmd_vel` and `goal_pose`):
/// checked against the world and the copter's claims, then queued for the step loop, or
/// rejected, counted and logged.
#[derive(Clone, Debug)]
pub struct CommandSink {
    world: Arc<Mutex<Arc<World>>>,
    counters: Arc<NodeCounters>,
    requests: SyncSender<Request>,
    controllers: Arc<Mutex<BTreeMap<String, Vec<String>>>>,
    limiter: Arc<RateLimiter>,
}

impl CommandSink {
    /// The world commands are checked against now.
    pub fn world(&self) -> Arc<World> {
        crate::lock(&self.world).clone()
    }

    /// A sink with no Zenoh session behind it, for tests of what submits to one.
    #[cfg(test)]
    pub(crate) fn detached(world: Arc<World>, requests: SyncSender<Request>) -> Self {
        Self {
            world: Arc::new(Mutex::new(world)),
            counters: Arc::default(),
            requests,
            controllers: Arc::default(),
            limiter: Arc::new(RateLimiter::new(Duration::from_secs(1))),
        }
    }

    /// Files (`put`) or withdraws a claim of `client` on copter `copter`, as a liveliness
    /// claim on `…/alive/copters/<copter>/<client>` does: the first claim of a copter is its
    /// controller, and a change of controller goes to the step loop.
    pub fn claim(&self, copter: &str, client: &str, put: bool) {
        let change = {
            let mut map = crate::lock(&self.controllers);
            let queue = map.entry(copter.to_owned()).or_default();
            let before = queue.first().cloned();
            if put {
                if !queue.iter().any(|c| c == client) {
                    queue.push(client.to_owned());
                }
            } else {
                queue.retain(|c| c != client);
            }
            let after = queue.first().cloned();
            (before != after).then(|| {
                let lost = before.filter(|b| !queue.contains(b));
                (after, lost)
            })
        };
        if let Some((client, lost)) = change {
            tracing::info!("copter {copter}: controller {client:?} (was {lost:?})");
            let request = Request::Controller { copter: copter.to_owned(), client, lost };
            if self.requests.try_send(request).is_err() {
                self.counters.requests_dropped.fetch_add(1, Ordering::Relaxed);
                tracing::warn!("controller change of {copter} dropped: the step loop's queue is full");
            }
        }
    }

    /// Submits a command for copter `name`, made by `make` from the current world (its error
    /// is the rejection). `origin` is the input as the log keeps it.
    pub fn submit(
        &self,
        name: &str,
        make: impl FnOnce(&World) -> Result<CommandMsg, crate::wire::CommandError>,
        origin: crate::engine::request::BusInput,
    ) {
        let (counters, requests, limiter) = (&self.counters, &self.requests, &self.limiter);
        let world = self.world();
        let result = match world.copter_id(name) {
            None => Err(crate::wire::CommandError::UnknownCopter(name.to_owned())),
            Some(_) => make(&world),
        };
        let key = origin.key.clone();
        let controller = crate::lock(&self.controllers).get(name).and_then(|v| v.first().cloned());
        if let (Ok(cmd), Some(owner)) = (&result, controller)
            && cmd.client.as_deref() != Some(owner.as_str())
        {
            counters.commands_rejected.fetch_add(1, Ordering::Relaxed);
            counters.commands_not_controller.fetch_add(1, Ordering::Relaxed);
            let reason = match &cmd.client {
                Some(c) => format!("copter {name:?} is controlled by client {owner:?}, not {c:?}"),
                None => format!("copter {name:?} is controlled by client {owner:?}; this command names no client"),
            };
            limiter.warn(&format!("rejected command on {key}: {reason}"));
            if requests.try_send(Request::Rejected { origin, reason }).is_err() {
                counters.requests_dropped.fetch_add(1, Ordering::Relaxed);
            }
            return;
        }
        match result {
            Ok(cmd) => match requests.try_send(Request::Command { copter: name.to_owned(), cmd, origin }) {
                Ok(()) => {
                    counters.commands_accepted.fetch_add(1, Ordering::Relaxed);
                }
                Err(_) => {
                    counters.commands_rejected.fetch_add(1, Ordering::Relaxed);
                    counters.requests_dropped.fetch_add(1, Ordering::Relaxed);
                    limiter.warn("command dropped: the step loop's queue is full");
                }
            },
            Err(e) => {
                counters.commands_rejected.fetch_add(1, Ordering::Relaxed);
                limiter.warn(&format!("rejected command on {key}: {e}"));
                // For the log; if the queue is full, the counters still have it.
                if requests.try_send(Request::Rejected { origin, reason: e.to_string() }).is_err() {
                    counters.requests_dropped.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
    }
}

/// The simulator's Zenoh node.
pub struct Node {
    session: zenoh::Session,
    prefix: String,
    world: Arc<Mutex<Arc<World>>>,
    /// Counters.
    pub counters: Arc<NodeCounters>,
    /// Names of attached clients (liveliness).
    pub clients: Arc<Mutex<BTreeSet<String>>>,
    /// Each copter's claims, in arrival order: the first is its controller.
    pub controllers: Arc<Mutex<BTreeMap<String, Vec<String>>>>,
    _token: zenoh::liveliness::LivelinessToken,
    _cmd_sub: zenoh::pubsub::Subscriber<()>,
    _tracking_sub: zenoh::pubsub::Subscriber<()>,
    _alive_sub: zenoh::pubsub::Subscriber<()>,
    _queryables: Vec<zenoh::query::Queryable<()>>,
    publishers: Vec<(zenoh::pubsub::Publisher<'static>, zenoh::pubsub::Publisher<'static>)>,
    clock_pub: zenoh::pubsub::Publisher<'static>,
    scene_json: Arc<Mutex<String>>,
    commands: CommandSink,
}

impl std::fmt::Debug for Node {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Node").field("prefix", &self.prefix).field("counters", &self.counters).finish_non_exhaustive()
    }
}

/// A sample on `<prefix>/copters/<name><suffix>`: the copter's name, the payload, and the
/// sample as a bus input (key, text, arrival time) for the log.
fn copter_sample(
    sample: &zenoh::sample::Sample,
    prefix_len: usize,
    suffix: &str,
) -> (String, Vec<u8>, crate::engine::request::BusInput) {
    let key = sample.key_expr().as_str();
    let name = key[prefix_len..].trim_start_matches("/copters/").trim_end_matches(suffix).to_owned();
    let payload = sample.payload().to_bytes().into_owned();
    let origin = crate::engine::request::BusInput {
        key: key.to_owned(),
        text: String::from_utf8_lossy(&payload).into_owned(),
        received_unix_ns: crate::log::now_unix_ns(),
    };
    (name, payload, origin)
}

/// The default key-expression prefix of a world.
pub fn default_prefix(world: &World) -> String {
    format!("twinswarm/{}", world.name)
}

impl Node {
    /// Opens the session and declares everything. `requests` feeds the step loop.
    pub async fn open(
        config: zenoh::Config,
        prefix: String,
        world: Arc<World>,
        requests: SyncSender<Request>,
    ) -> Result<Self, NodeError> {
        let session = zenoh::open(config).await.map_err(zerr)?;
        let counters = Arc::new(NodeCounters::default());
        let world_cell = Arc::new(Mutex::new(world.clone()));
        let scene_json = Arc::new(Mutex::new(serde_json::to_string(&world.spec).unwrap_or_default()));

        // Commands.
        let limiter = Arc::new(RateLimiter::new(Duration::from_secs(1)));
        let controllers: Arc<Mutex<BTreeMap<String, Vec<String>>>> = Arc::default();
        let commands = CommandSink {
            world: world_cell.clone(),
            counters: counters.clone(),
            requests: requests.clone(),
            controllers: controllers.clone(),
            limiter: limiter.clone(),
        };
        let cmd_sub = declare_command_subscriber(&session, &prefix, commands.clone()).await?;

        // Tracking poses of real copters (e.g. a camera system), for twin synchronisation.
        let tracking_sub =
            declare_tracking_subscriber(&session, &prefix, counters.clone(), requests.clone(), limiter.clone()).await?;

        // Liveliness: our token, and the clients'.
        let token = session.liveliness().declare_token(format!("{prefix}/alive/sim")).await.map_err(zerr)?;
        let clients = Arc::new(Mutex::new(BTreeSet::new()));
        let alive_sub =
            declare_alive_subscriber(&session, &prefix, clients.clone(), counters.clone(), commands.clone()).await?;

        // Queryables.
        let queryables = vec![
            declare_scene_queryable(&session, &prefix, scene_json.clone(), counters.clone()).await?,
            declare_copters_queryable(&session, &prefix, world_cell.clone(), counters.clone()).await?,
            declare_spawn_queryable(&session, &prefix, requests.clone(), counters.clone(), limiter.clone()).await?,
        ];

        let clock_pub = session.declare_publisher(format!("{prefix}/clock")).await.map_err(zerr)?;
        let mut node = Self {
            session,
            prefix,
            world: world_cell,
            counters,
            clients,
            controllers,
            _token: token,
            _cmd_sub: cmd_sub,
            _tracking_sub: tracking_sub,
            _alive_sub: alive_sub,
            _queryables: queryables,
            publishers: Vec::new(),
            clock_pub,
            scene_json,
            commands,
        };
        node.declare_copter_publishers(&world).await?;
        Ok(node)
    }

    /// The key-expression prefix.
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// The session (for the Paparazzi side).
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    /// Where commands go (for the ROS 2 side).
    pub fn commands(&self) -> CommandSink {
        self.commands.clone()
    }

    async fn declare_copter_publishers(&mut self, world: &World) -> Result<(), NodeError> {
        for c in &world.copters[self.publishers.len()..] {
            let state = self
                .session
                .declare_publisher(format!("{}/copters/{}/state", self.prefix, c.name))
                .await
                .map_err(zerr)?;
            let sensors = self
                .session
                .declare_publisher(format!("{}/copters/{}/sensors", self.prefix, c.name))
                .await
                .map_err(zerr)?;
            self.publishers.push((state, sensors));
        }
        Ok(())
    }

    /// Publishes one frame: clock, then each copter's state and sensors.
    pub async fn publish(&mut self, frame: &Frame) -> Result<(), NodeError> {
        if frame.world.copters.len() != self.publishers.len() {
            *crate::lock(&self.world) = frame.world.clone();
            // A SceneSpec always serialises (a test round-trips it).
            *crate::lock(&self.scene_json) = serde_json::to_string(&frame.world.spec).unwrap_or_default();
            let world = frame.world.clone();
            self.declare_copter_publishers(&world).await?;
        }
        let clock = ClockMsg { tick: frame.tick, time_s: frame.time_s };
        self.clock_pub.put(serde_json::to_vec(&clock).unwrap_or_default()).await.map_err(zerr)?;
        // A shard's frame holds its own copters only: each goes out on its copter's keys.
        for (&i, s) in frame.ids.iter().zip(&frame.states) {
            let payload = serde_json::to_vec(s).unwrap_or_default();
            self.publishers[i as usize].0.put(payload).await.map_err(zerr)?;
        }
        for (&i, s) in frame.ids.iter().zip(&frame.sensors) {
            let payload = serde_json::to_vec(s).unwrap_or_default();
            self.publishers[i as usize].1.put(payload).await.map_err(zerr)?;
        }
        for out in &frame.pprz_out {
            self.session.put(out.key.as_str(), out.text.as_str()).await.map_err(zerr)?;
        }
        self.counters
            .published
            .fetch_add((1 + frame.states.len() + frame.sensors.len() + frame.pprz_out.len()) as u64, Ordering::Relaxed);
        Ok(())
    }

    /// Undeclares everything and closes the session.
    pub async fn close(self) -> Result<(), NodeError> {
        let Node { session, _token, _cmd_sub, _tracking_sub, _alive_sub, _queryables, publishers, clock_pub, .. } =
            self;
        drop((_cmd_sub, _tracking_sub, _alive_sub, _queryables, publishers, clock_pub));
        _token.undeclare().await.map_err(zerr)?;
        session.close().await.map_err(zerr)
    }
}

/// Declares the subscriber on `<prefix>/copters/*/cmd`, which submits each command to `commands`.
async fn declare_command_subscriber(
    session: &zenoh::Session,
    prefix: &str,
    commands: CommandSink,
) -> Result<zenoh::pubsub::Subscriber<()>, NodeError> {
    let prefix_len = prefix.len();
    session
        .declare_subscriber(format!("{prefix}/copters/*/cmd"))
        .callback(move |sample| {
            let (name, payload, origin) = copter_sample(&sample, prefix_len, "/cmd");
            commands.submit(&name, |world| CommandMsg::parse(&payload, world), origin);
        })
        .await
        .map_err(zerr)
}

/// Declares the subscriber on `<prefix>/copters/*/tracking`, which queues each tracking pose
/// (or its rejection) for the step loop.
async fn declare_tracking_subscriber(
    session: &zenoh::Session,
    prefix: &str,
    counters: Arc<NodeCounters>,
    requests: SyncSender<Request>,
    limiter: Arc<RateLimiter>,
) -> Result<zenoh::pubsub::Subscriber<()>, NodeError> {
    let prefix_len = prefix.len();
    session
        .declare_subscriber(format!("{prefix}/copters/*/tracking"))
        .callback(move |sample| {
            let (name, payload, origin) = copter_sample(&sample, prefix_len, "/tracking");
            let request = match crate::wire::TrackingMsg::parse(&payload) {
                Ok(t) => Request::Tracking { copter: name, pos_m: [t.pos_m[0], t.pos_m[1]], origin },
                Err(e) => {
                    counters.tracking_rejected.fetch_add(1, Ordering::Relaxed);
                    limiter.warn(&format!("rejected tracking pose on {}: {e}", origin.key));
                    Request::Rejected { origin, reason: e.to_string() }
                }
            };
            if requests.try_send(request).is_err() {
                counters.requests_dropped.fetch_add(1, Ordering::Relaxed);
                limiter.warn("tracking pose dropped: the step loop's queue is full");
            }
        })
        .await
        .map_err(zerr)
}

/// Declares the liveliness subscriber on `<prefix>/alive/copters/**` (with history): it keeps
/// `clients` and files each `<copter>/<client>` claim with `commands`.
async fn declare_alive_subscriber(
    session: &zenoh::Session,
    prefix: &str,
    clients: Arc<Mutex<BTreeSet<String>>>,
    counters: Arc<NodeCounters>,
    commands: CommandSink,
) -> Result<zenoh::pubsub::Subscriber<()>, NodeError> {
    let base = format!("{prefix}/alive/copters/");
    session
        .liveliness()
        .declare_subscriber(format!("{prefix}/alive/copters/**"))
        .history(true)
        .callback(move |sample| {
            let rest = sample.key_expr().as_str().trim_start_matches(base.as_str()).to_owned();
            let put = sample.kind() == SampleKind::Put;
            {
                let mut c = crate::lock(&clients);
                if put {
                    if c.insert(rest.clone()) {
                        counters.clients_seen.fetch_add(1, Ordering::Relaxed);
                        tracing::info!("client attached: {rest}");
                    }
                } else {
                    c.remove(&rest);
                    tracing::info!("client left: {rest}");
                }
            }
            // A claim: `<copter>/<client>`.
            if let Some((copter, client)) = rest.split_once('/') {
                commands.claim(copter, client, put);
            }
        })
        .await
        .map_err(zerr)
}

/// Declares the queryable `<prefix>/scene`, which answers with the scene as JSON.
async fn declare_scene_queryable(
    session: &zenoh::Session,
    prefix: &str,
    scene_json: Arc<Mutex<String>>,
    counters: Arc<NodeCounters>,
) -> Result<zenoh::query::Queryable<()>, NodeError> {
    session
        .declare_queryable(format!("{prefix}/scene"))
        .callback(move |q| {
            let body = crate::lock(&scene_json).clone();
            // A reply fails only when the querier is gone or the session is closing:
            // nobody is left to tell, so it is counted (the same below).
            count_failed(&counters, q.reply(q.key_expr().clone(), body).wait());
        })
        .await
        .map_err(zerr)
}

/// Declares the queryable `<prefix>/copters`, which answers with the list of copters as JSON.
async fn declare_copters_queryable(
    session: &zenoh::Session,
    prefix: &str,
    world_cell: Arc<Mutex<Arc<World>>>,
    counters: Arc<NodeCounters>,
) -> Result<zenoh::query::Queryable<()>, NodeError> {
    session
        .declare_queryable(format!("{prefix}/copters"))
        .callback(move |q| {
            let list: Vec<CopterListEntry> = crate::lock(&world_cell)
                .copters
                .iter()
                .enumerate()
                .map(|(id, c)| CopterListEntry {
                    id,
                    name: c.name.clone(),
                    kind: crate::wire::kind_str(c.kind).into(),
                    ac_id: c.ac_id,
                    crashed: false,
                })
                .collect();
            // Strings and numbers: serialising cannot fail.
            let body = serde_json::to_string(&list).unwrap_or_default();
            count_failed(&counters, q.reply(q.key_expr().clone(), body).wait());
        })
        .await
        .map_err(zerr)
}

/// Declares the queryable `<prefix>/spawn`: a JSON copter table in, queued for the step loop,
/// and its answer (the name or an error) replied from a task.
async fn declare_spawn_queryable(
    session: &zenoh::Session,
    prefix: &str,
    requests: SyncSender<Request>,
    counters: Arc<NodeCounters>,
    limiter: Arc<RateLimiter>,
) -> Result<zenoh::query::Queryable<()>, NodeError> {
    session
        .declare_queryable(format!("{prefix}/spawn"))
        .callback(move |q| {
            // No payload is an empty request: parsing it fails and the querier is told.
            let payload = q.payload().map(|p| p.to_bytes().into_owned()).unwrap_or_default();
            let spec: CopterSpec = match serde_json::from_slice(&payload) {
                Ok(s) => s,
                Err(e) => {
                    counters.spawns_rejected.fetch_add(1, Ordering::Relaxed);
                    limiter.warn(&format!("rejected a spawn request: {e}"));
                    count_failed(&counters, q.reply_err(format!("malformed spawn request: {e}")).wait());
                    return;
                }
            };
            let (tx, rx) = tokio::sync::oneshot::channel();
            if requests.try_send(Request::Spawn { spec: Box::new(spec), reply: tx }).is_err() {
                counters.spawns_rejected.fetch_add(1, Ordering::Relaxed);
                counters.requests_dropped.fetch_add(1, Ordering::Relaxed);
                count_failed(&counters, q.reply_err("the step loop is busy or stopped").wait());
                return;
            }
            // Answer from a task: the step loop replies at its next step.
            let counters = counters.clone();
            tokio::spawn(async move {
                let answer = tokio::time::timeout(Duration::from_secs(5), rx).await;
                let sent = match answer {
                    Ok(Ok(Ok(name))) => {
                        q.reply(q.key_expr().clone(), serde_json::json!({ "spawned": name }).to_string()).await
                    }
                    Ok(Ok(Err(e))) => q.reply_err(e).await,
                    _ => q.reply_err("the step loop did not answer").await,
                };
                count_failed(&counters, sent);
            });
        })
        .await
        .map_err(zerr)
}
