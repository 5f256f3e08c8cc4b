//! The simulator as a ROS 2 node on its own Zenoh session, following rmw_zenoh's design for
//! Jazzy (ros2/rmw_zenoh `docs/design.md` at 99a6a2b; liveliness and attachment formats of
//! `rmw_zenoh_cpp` ≥ 0.2.4): the node `/twinswarm`, a publisher per topic, a subscriber per
//! command topic, each with its liveliness token, so that `ros2 node list`, `ros2 topic
//! list|echo`, rviz2 and ROS nodes with `RMW_IMPLEMENTATION=rmw_zenoh_cpp` see it.
//!
//! - Data: `<domain>/<topic without its leading />/<pkg>::msg::dds_::<Name>_/RIHS01_<hash>`,
//!   CDR little-endian, with rmw_zenoh's 33-byte attachment (sequence number per publisher
//!   from 1, wall-clock ns, a 16-byte GID).
//! - Graph: `@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS>/%/%/twinswarm[/<topic
//!   with / as %>/<type>/<hash>/<qos>]`.
//! - Cost: a topic no ROS subscription in the graph asks for is not encoded, and its Zenoh
//!   publisher is declared only when one first does; the graph's tokens are declared on a
//!   thread that runs on idle cores.
//!
//! Topics (per copter `<c>`, its name made a valid ROS name): `/<c>/pose`, `/<c>/odom`,
//! `/<c>/imu`, `/<c>/sonar/{front,right,back,left}`, `/<c>/ir`, `/<c>/battery`; once:
//! `/clock`, `/tf`, `/tf_static` and `/arena` (latched). In: `/<c>/cmd_vel`,
//! `/<c>/goal_pose`. Frames: `world` (x, y on the floor, z up), `<c>/base_link` (x forward,
//! y left, z up, REP 103), `<c>/sonar_<side>`, `<c>/ir`.

use std::collections::HashMap;
use std::sync::atomic::AtomicU64;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::{Arc, Mutex};

use sim_core::FlightMode;
use sim_core::World;
use zenoh::Wait;
use zenoh_ext::{AdvancedPublisher, AdvancedPublisherBuilderExt, CacheConfig, MissDetectionConfig};

use super::msgs::{self, Cube, Pose, RangeSensor, Stamp};
use super::types::{dds_name, type_hash};
use crate::engine::loop_io::Frame;
use crate::engine::request::BusInput;
use crate::wire::{CommandError, CommandMsg, SensorsMsg, StateMsg};
use crate::zenoh_net::node::{CommandSink, NodeError};

/// The node's name.
pub const NODE_NAME: &str = "twinswarm";

/// QoS of sensor topics: best effort, volatile, keep last 5 (rmw_zenoh's key encoding).
pub const QOS_SENSOR: &str = "2::,5:,:,:,,";
/// QoS of `/tf`: reliable, volatile, keep last 100 (tf2's broadcaster).
pub const QOS_TF: &str = "::,100:,:,:,,";
/// QoS of `/clock`: best effort, keep last 1 (rclcpp's `ClockQoS`).
pub const QOS_CLOCK: &str = "2::,1:,:,:,,";
/// QoS of latched topics: reliable, transient local, keep last 1.
pub const QOS_LATCHED: &str = ":1:,1:,:,:,,";
/// QoS of the command subscriptions: reliable, volatile, keep last 10 (rclcpp's default).
pub const QOS_COMMAND: &str = "::,10:,:,:,,";

/// A `cmd_vel`'s vertical speed and yaw rate become a height and a heading this far ahead
/// of the copter's own, s: the height and yaw controllers then fly about that rate.
pub const RATE_LOOKAHEAD_S: f32 = 1.0;

/// `--ros2` options.
#[derive(Clone, Debug, Default)]
pub struct Ros2Options {
    /// `ROS_DOMAIN_ID`.
    pub domain: u32,
    /// Pose, odometry, IMU and tf at most this often per simulated second (`None`: every
    /// control step).
    pub max_rate_hz: Option<f64>,
}

fn zerr(e: impl std::fmt::Display) -> NodeError {
    NodeError::Zenoh(e.to_string())
}

/// A copter's name as a ROS name segment: letters, digits and `_`, not starting with a digit.
pub fn ros_name(copter: &str) -> String {
    let mut s: String = copter.chars().map(|c| if c.is_ascii_alphanumeric() { c } else { '_' }).collect();
    if s.is_empty() || s.starts_with(|c: char| c.is_ascii_digit()) {
        s.insert_str(0, "c_");
    }
    s
}

/// The data key of `topic` (a fully qualified name) with type `ty` on `domain`.
pub fn data_key(domain: u32, topic: &str, ty: &str) -> String {
    let t = topic.strip_prefix('/').unwrap_or(topic);
    format!("{domain}/{}/{}/{}", t.strip_suffix('/').unwrap_or(t), dds_name(ty), type_hash(ty))
}

/// rmw_zenoh's attachment: sequence number and wall-clock time (i64 LE each), then the GID
/// with its length (zenoh-ext's serialisation of `(i64, i64, [u8; 16])`).
pub fn attachment(seq: i64, gid: &[u8; 16]) -> Vec<u8> {
    let mut a = Vec::with_capacity(33);
    a.extend_from_slice(&seq.to_le_bytes());
    a.extend_from_slice(&(crate::log::now_unix_ns() as i64).to_le_bytes());
    a.push(16);
    a.extend_from_slice(gid);
    a
}

/// The GID in an attachment (this format or rmw_zenoh's earlier, keyed one).
pub fn attachment_gid(a: &[u8]) -> Option<[u8; 16]> {
    match a.len() {
        33 if a[16] == 16 => a[17..].try_into().ok(),
        77 => a[61..].try_into().ok(),
        _ => None,
    }
}

/// The liveliness keys of the node's entities, and their tokens.
struct Graph {
    session: zenoh::Session,
    domain: u32,
    zid: String,
    next_id: u32,
    /// Tokens declared so far (they undeclare when dropped).
    tokens: Arc<Mutex<Vec<zenoh::liveliness::LivelinessToken>>>,
    /// Keys waiting for [`Graph::declare_pending`].
    pending: Vec<String>,
    /// Threads declaring pending tokens, and their stop flag.
    declarers: Vec<std::thread::JoinHandle<()>>,
    stop: Arc<AtomicBool>,
    /// The subscriptions in the graph, by topic.
    demand: Demand,
}

impl Graph {
    fn node_key(&self) -> String {
        format!("@ros2_lv/{}/{}/0/0/NN/%/%/{NODE_NAME}", self.domain, self.zid)
    }

    /// The token key of a new publisher (`MP`) or subscription (`MS`).
    fn entity_key(&mut self, kind: &str, topic: &str, ty: &str, qos: &str) -> String {
        self.next_id += 1;
        format!(
            "@ros2_lv/{}/{}/0/{}/{kind}/%/%/{NODE_NAME}/{}/{}/{}/{qos}",
            self.domain,
            self.zid,
            self.next_id,
            topic.replace('/', "%"),
            dds_name(ty),
            type_hash(ty)
        )
    }

    /// Declares a token now.
    fn token(&self, key: &str) -> Result<(), NodeError> {
        let t = self.session.liveliness().declare_token(key.to_owned()).wait().map_err(zerr)?;
        crate::lock(&self.tokens).push(t);
        Ok(())
    }

    /// Queues a token for [`Graph::declare_pending`].
    fn token_later(&mut self, key: &str) {
        self.pending.push(key.to_owned());
    }

    /// Declares the queued tokens on a thread of their own, which runs only on a core the
    /// run leaves idle: Zenoh's routing matches each new key against its siblings, so
    /// declaring 11 tokens per copter costs time quadratic in the swarm (6 s of a core at
    /// 1,000 copters), which the run need not wait for. The topics appear in the graph as
    /// they are declared.
    fn declare_pending(&mut self) {
        let keys = std::mem::take(&mut self.pending);
        if keys.is_empty() {
            return;
        }
        let (session, tokens, stop) = (self.session.clone(), self.tokens.clone(), self.stop.clone());
        self.declarers.push(std::thread::spawn(move || {
            idle_priority();
            for key in keys {
                if stop.load(Ordering::Relaxed) {
                    return;
                }
                match session.liveliness().declare_token(key.clone()).wait() {
                    Ok(t) => crate::lock(&tokens).push(t),
                    Err(e) => tracing::warn!("ROS 2 graph: cannot declare {key}: {e}"),
                }
            }
        }));
    }
}

impl Graph {
    /// Stops declaring tokens.
    fn stop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for d in self.declarers.drain(..) {
            let _ = d.join();
        }
    }
}

impl Drop for Graph {
    fn drop(&mut self) {
        self.stop();
    }
}

/// Puts the calling thread in Linux's `SCHED_IDLE` class: it runs when a core would
/// otherwise idle.
#[cfg(target_os = "linux")]
#[allow(unsafe_code)]
fn idle_priority() {
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: `param` is a valid `sched_param` for the call's duration; pid 0 is this thread.
    if unsafe { libc::sched_setscheduler(0, libc::SCHED_IDLE, &param) } != 0 {
        tracing::debug!("ROS 2 graph: SCHED_IDLE refused: {}", std::io::Error::last_os_error());
    }
}

#[cfg(not(target_os = "linux"))]
fn idle_priority() {}

/// An entity's GID as `rmw_zenoh_cpp` makes it: the XXH3-128 of its liveliness key, the low
/// 64 bits first, each in the machine's (little-endian) byte order.
pub fn gid_of(key: &str) -> [u8; 16] {
    let h = xxhash_rust::xxh3::xxh3_128(key.as_bytes());
    let mut g = [0u8; 16];
    g[..8].copy_from_slice(&(h as u64).to_le_bytes());
    g[8..].copy_from_slice(&((h >> 64) as u64).to_le_bytes());
    g
}

enum Sender {
    /// A Zenoh publisher declared the first time a ROS subscription to the topic is in the
    /// graph (declaring 9 per copter up front costs Zenoh time quadratic in the swarm).
    Plain {
        session: zenoh::Session,
        key: String,
        congestion: zenoh::qos::CongestionControl,
        publisher: Option<zenoh::pubsub::Publisher<'static>>,
        /// ROS subscriptions to it in the graph.
        demand: Arc<AtomicU32>,
    },
    Latched(AdvancedPublisher<'static>),
}

/// One ROS publisher: its Zenoh publisher, GID and sequence number (its token is the
/// graph's).
struct RosPub {
    sender: Sender,
    gid: [u8; 16],
    seq: i64,
}

impl RosPub {
    fn declare(graph: &mut Graph, topic: &str, ty: &str, qos: &str) -> Result<Self, NodeError> {
        let key = data_key(graph.domain, topic, ty);
        let sender = if qos == QOS_LATCHED {
            let p = (graph.session.declare_publisher(key))
                .cache(CacheConfig::default().max_samples(1))
                .sample_miss_detection(
                    MissDetectionConfig::default().sporadic_heartbeat(std::time::Duration::from_millis(500)),
                )
                .publisher_detection()
                .wait()
                .map_err(zerr)?;
            Sender::Latched(p)
        } else {
            let congestion =
                if qos == QOS_TF { zenoh::qos::CongestionControl::Block } else { zenoh::qos::CongestionControl::Drop };
            let demand = graph.demand.of(topic, ty);
            Sender::Plain { session: graph.session.clone(), key, congestion, publisher: None, demand }
        };
        let token_key = graph.entity_key("MP", topic, ty, qos);
        graph.token_later(&token_key);
        Ok(Self { sender, gid: gid_of(&token_key), seq: 0 })
    }

    /// Whether a ROS subscription to it is in the graph (a latched topic: always, for those
    /// who come later).
    fn wanted(&self) -> bool {
        match &self.sender {
            Sender::Plain { demand, .. } => demand.load(Ordering::Relaxed) > 0,
            Sender::Latched(_) => true,
        }
    }

    fn put(&mut self, payload: Vec<u8>) -> Result<(), NodeError> {
        self.seq += 1;
        let att = attachment(self.seq, &self.gid);
        match &mut self.sender {
            Sender::Plain { session, key, congestion, publisher, .. } => {
                let p = match publisher {
                    Some(p) => p,
                    None => publisher.insert(
                        session.declare_publisher(key.clone()).congestion_control(*congestion).wait().map_err(zerr)?,
                    ),
                };
                p.put(payload).attachment(att).wait().map_err(zerr)
            }
            Sender::Latched(p) => p.put(payload).attachment(att).wait().map_err(zerr),
        }
    }

    /// Encodes and sends, if anyone subscribes.
    fn send(&mut self, encode: impl FnOnce() -> Vec<u8>) -> Result<bool, NodeError> {
        if !self.wanted() {
            return Ok(false);
        }
        self.put(encode())?;
        Ok(true)
    }
}

/// Who subscribes to what, as the ROS graph says (rmw_zenoh's `count_subscribers` reads
/// its graph cache the same way): the subscription tokens (`MS`) of every session, counted
/// by topic, type and hash. A plain Zenoh subscriber that declares no token is not a ROS
/// subscription and is not served. The publishers of commands (`MP` tokens) go to
/// [`RosClaims`].
#[derive(Clone)]
struct Demand {
    counts: Arc<Mutex<HashMap<String, Arc<AtomicU32>>>>,
    claims: Arc<RosClaims>,
}

impl Demand {
    /// The count of subscriptions to `topic` of type `ty`.
    fn of(&self, topic: &str, ty: &str) -> Arc<AtomicU32> {
        let key = format!("{}/{}/{}", topic.replace('/', "%"), dds_name(ty), type_hash(ty));
        crate::lock(&self.counts).entry(key).or_default().clone()
    }

    /// A graph token came (`put`) or went.
    fn on_token(&self, key: &str, put: bool) {
        let parts: Vec<&str> = key.split('/').collect();
        if parts.len() != 13 {
            return;
        }
        match parts[5] {
            "MS" => {
                let count = crate::lock(&self.counts).entry(parts[9..12].join("/")).or_default().clone();
                if put {
                    count.fetch_add(1, Ordering::Relaxed);
                } else {
                    let _ = count.fetch_update(Ordering::Relaxed, Ordering::Relaxed, |c| c.checked_sub(1));
                }
            }
            "MP" => self.claims.on_publisher(key, &parts, put),
            _ => {}
        }
    }

    /// Follows the graph of `domain` from now on, with the tokens already there.
    fn follow(&self, session: &zenoh::Session, domain: u32) -> Result<zenoh::pubsub::Subscriber<()>, NodeError> {
        let demand = self.clone();
        session
            .liveliness()
            .declare_subscriber(format!("@ros2_lv/{domain}/**"))
            .history(true)
            .callback(move |s| demand.on_token(s.key_expr().as_str(), s.kind() == zenoh::sample::SampleKind::Put))
            .wait()
            .map_err(zerr)
    }
}

/// The ROS side's claims. A ROS node with a publisher on `/<c>/cmd_vel` (a `Twist`) or
/// `/<c>/goal_pose` (a `PoseStamped`) in the graph (its `MP` token) claims copter `c` the way
/// a Zenoh client's liveliness token does: the copter takes commands from that node only,
/// `--lockstep` holds each step for its answer, and `--on-client-lost` applies when the
/// node's last such publisher leaves. The client's name is `ros2:<node>@<zid>/<node id>`.
///
/// A command's attachment carries its publisher's GID, which `rmw_zenoh_cpp` makes from the
/// publisher's token ([`gid_of`]), so a command is its node's. A client that makes GIDs
/// otherwise (zenoh-ros2-sdk draws them at random) is known by a GID first seen while its
/// node alone published commands to the copter, and keeps it while that claim lasts.
struct RosClaims {
    sink: CommandSink,
    book: Mutex<ClaimBook>,
}

#[derive(Default)]
struct ClaimBook {
    /// Command publishers in the graph by GID: their copter (ROS name) and client.
    publishers: HashMap<[u8; 16], (String, String)>,
    /// GIDs not made from a token, learned from commands: their copter and client.
    learned: HashMap<[u8; 16], (String, String)>,
    /// By copter (ROS name): its clients, each with its count of command publishers.
    clients: HashMap<String, std::collections::BTreeMap<String, u32>>,
    /// Scene names of the copters known so far, by ROS name.
    names: HashMap<String, String>,
}

/// [`Ros2Node::tick`] before the first frame: a command then answers no tick (under
/// `--lockstep`, a claimed copter refuses it).
const NO_FRAME: u64 = u64::MAX;

/// The command topics, with the type each must have to be one.
const COMMAND_TOPICS: [(&str, &str); 2] =
    [("cmd_vel", "geometry_msgs/msg/Twist"), ("goal_pose", "geometry_msgs/msg/PoseStamped")];

impl RosClaims {
    /// A publisher's token came (`put`) or went; `parts` is `key` split at `/`. Claims are
    /// filed under the book's lock, so that they reach the sink in the book's order.
    fn on_publisher(&self, key: &str, parts: &[&str], put: bool) {
        let Some((copter, topic)) = parts[9].strip_prefix('%').and_then(|t| t.split_once('%')) else { return };
        let is_command =
            |(t, ty): &(&str, &str)| *t == topic && parts[10] == dds_name(ty) && parts[11] == type_hash(ty);
        if !COMMAND_TOPICS.iter().any(is_command) {
            return; // the simulator's own topics among them: 9 per copter
        }
        let client = ros_client(parts);
        let gid = gid_of(key);
        let mut book = crate::lock(&self.book);
        let book = &mut *book;
        let changed = if put {
            if book.publishers.insert(gid, (copter.to_owned(), client.clone())).is_some() {
                return;
            }
            let n = book.clients.entry(copter.to_owned()).or_default().entry(client.clone()).or_default();
            *n += 1;
            *n == 1
        } else {
            if book.publishers.remove(&gid).is_none() {
                return;
            }
            let clients = book.clients.entry(copter.to_owned()).or_default();
            let n = clients.entry(client.clone()).or_default();
            *n = n.saturating_sub(1);
            let gone = *n == 0;
            if gone {
                clients.remove(&client);
                book.learned.retain(|_, (c, k)| !(c == copter && *k == client));
            }
            gone
        };
        if let Some(name) = book.names.get(copter).filter(|_| changed) {
            self.sink.claim(name, &client, put);
        }
    }

    /// Copter `name` (`ros_name` in ROS) is known: the claims on it so far are filed.
    fn copter_added(&self, ros_name: &str, name: &str) {
        let mut book = crate::lock(&self.book);
        book.names.insert(ros_name.to_owned(), name.to_owned());
        for client in book.clients.get(ros_name).into_iter().flat_map(|c| c.keys()) {
            self.sink.claim(name, client, true);
        }
    }

    /// The client a command to `ros_name` with GID `gid` comes from: the node of the
    /// publisher with that GID, the node it was learned for, or the one node that publishes
    /// commands to the copter (learned then).
    fn client_of(&self, ros_name: &str, gid: &[u8; 16]) -> Option<String> {
        let mut book = crate::lock(&self.book);
        if let Some((copter, client)) = book.publishers.get(gid).or_else(|| book.learned.get(gid)) {
            return (copter == ros_name).then(|| client.clone());
        }
        let only = match book.clients.get(ros_name).map(|c| c.keys().collect::<Vec<_>>()).as_deref() {
            Some([only]) => (*only).clone(),
            _ => return None,
        };
        book.learned.insert(*gid, (ros_name.to_owned(), only.clone()));
        Some(only)
    }
}

/// The client name of the node of an entity token split at `/`: `ros2:<node>@<zid>/<node id>`.
fn ros_client(parts: &[&str]) -> String {
    let ns = parts[7].replace('%', "/");
    let node = if ns.ends_with('/') { format!("{ns}{}", parts[8]) } else { format!("{ns}/{}", parts[8]) };
    format!("ros2:{node}@{}/{}", parts[2], parts[3])
}

const SIDES: [&str; 4] = ["front", "right", "back", "left"];

/// One copter's topics.
struct CopterTopics {
    /// Its ROS name.
    name: String,
    /// Its frames: the body, the sonars, the IR sensor.
    base_frame: String,
    sonar_frames: [String; 4],
    ir_frame: String,
    pose: RosPub,
    odom: RosPub,
    imu: RosPub,
    sonar: [RosPub; 4],
    ir: RosPub,
    battery: RosPub,
    /// Simulated time of its last battery message, s.
    battery_at_s: Option<f64>,
}

/// A command topic's message (CDR) as a command, given the copter's height and yaw; with the
/// message as text, for the log.
type Convert = fn(&[u8], (f32, f32)) -> Result<(CommandMsg, String), String>;

/// What the command callbacks need of a copter: by ROS name, its id, scene name, and latest
/// height and yaw.
type Latest = Arc<Mutex<HashMap<String, (usize, String, (f32, f32))>>>;

/// Counts of what the ROS side sent, for the run's summary.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Ros2Stats {
    /// The domain.
    pub domain: u32,
    /// Publishers and subscriptions declared.
    pub publishers: usize,
    /// Subscriptions declared.
    pub subscriptions: usize,
    /// Messages sent (encoded for a subscriber).
    pub sent: u64,
}

/// The simulator's ROS 2 node.
pub struct Ros2Node {
    graph: Graph,
    opts: Ros2Options,
    commands: CommandSink,
    clock: RosPub,
    tf: RosPub,
    tf_static: RosPub,
    arena: RosPub,
    copters: Vec<CopterTopics>,
    latest: Latest,
    claims: Arc<RosClaims>,
    /// The tick of the last frame published: the tick a ROS command answers (`--lockstep`);
    /// [`NO_FRAME`] before the first.
    tick: Arc<AtomicU64>,
    _command_subs: Vec<zenoh::pubsub::Subscriber<()>>,
    _graph_sub: zenoh::pubsub::Subscriber<()>,
    /// Simulated time before which pose, odometry, IMU and tf are not sent again.
    next_due_s: f64,
    stats: Ros2Stats,
}

impl std::fmt::Debug for Ros2Node {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Ros2Node").field("domain", &self.graph.domain).finish_non_exhaustive()
    }
}

impl Ros2Node {
    /// Declares the node, its topics for every copter of `world`, and sends the latched ones.
    pub fn open(
        session: &zenoh::Session,
        world: &World,
        commands: CommandSink,
        opts: Ros2Options,
    ) -> Result<Self, NodeError> {
        let claims = Arc::new(RosClaims { sink: commands.clone(), book: Mutex::default() });
        let mut graph = Graph {
            session: session.clone(),
            domain: opts.domain,
            zid: session.zid().to_string(),
            next_id: 0,
            tokens: Arc::default(),
            pending: Vec::new(),
            declarers: Vec::new(),
            stop: Arc::default(),
            demand: Demand { counts: Arc::default(), claims: claims.clone() },
        };
        let graph_sub = graph.demand.follow(session, opts.domain)?;
        graph.token(&graph.node_key())?;
        let clock = RosPub::declare(&mut graph, "/clock", "rosgraph_msgs/msg/Clock", QOS_CLOCK)?;
        let tf = RosPub::declare(&mut graph, "/tf", "tf2_msgs/msg/TFMessage", QOS_TF)?;
        let tf_static = RosPub::declare(&mut graph, "/tf_static", "tf2_msgs/msg/TFMessage", QOS_LATCHED)?;
        let arena = RosPub::declare(&mut graph, "/arena", "visualization_msgs/msg/MarkerArray", QOS_LATCHED)?;
        let stats = Ros2Stats { domain: opts.domain, ..Ros2Stats::default() };
        let mut node = Self {
            graph,
            opts,
            commands,
            clock,
            tf,
            tf_static,
            arena,
            copters: Vec::new(),
            latest: Latest::default(),
            claims,
            tick: Arc::new(AtomicU64::new(NO_FRAME)),
            _command_subs: Vec::new(),
            _graph_sub: graph_sub,
            next_due_s: 0.0,
            stats,
        };
        node._command_subs = vec![
            node.subscribe("cmd_vel", "geometry_msgs/msg/Twist", twist_command)?,
            node.subscribe("goal_pose", "geometry_msgs/msg/PoseStamped", goal_command)?,
        ];
        node.add_copters(world)?;
        node.arena.put(msgs::marker_array(Stamp::default(), "world", &arena_cubes(world)))?;
        Ok(node)
    }

    /// Stops declaring the graph. Closing the session first, then dropping the node, takes
    /// the graph's tokens away at once: undeclared one by one, each costs Zenoh time linear
    /// in the count (a second at 1,000 copters).
    pub fn stop_graph(&mut self) {
        self.graph.stop();
    }

    /// What was sent so far.
    pub fn stats(&self) -> Ros2Stats {
        let mut s = self.stats.clone();
        s.publishers = 4 + 9 * self.copters.len();
        s.subscriptions = 2 * self.copters.len();
        s
    }

    /// Declares the topics of copters added to `world` since, and sends `/tf_static` anew.
    fn add_copters(&mut self, world: &World) -> Result<(), NodeError> {
        for i in self.copters.len()..world.copters.len() {
            let name = &world.copters[i].name;
            let topics = self.copter_topics(name)?;
            crate::lock(&self.latest).insert(topics.name.clone(), (i, name.clone(), (0.0, 0.0)));
            self.claims.copter_added(&topics.name, name);
            self.copters.push(topics);
        }
        self.graph.declare_pending();
        let statics = static_transforms(world, &self.copters);
        let entries = statics.iter().map(|(child, pose)| (child.as_str(), *pose));
        self.tf_static.put(msgs::tf(Stamp::default(), "", entries))?;
        Ok(())
    }

    fn copter_topics(&mut self, copter: &str) -> Result<CopterTopics, NodeError> {
        let name = ros_name(copter);
        let g = &mut self.graph;
        let t = |s: &str| format!("/{name}/{s}");
        let range = "sensor_msgs/msg/Range";
        let sonar = SIDES.map(|side| RosPub::declare(g, &t(&format!("sonar/{side}")), range, QOS_SENSOR));
        let [s0, s1, s2, s3] = sonar;
        let cmd_vel = g.entity_key("MS", &t("cmd_vel"), "geometry_msgs/msg/Twist", QOS_COMMAND);
        let goal = g.entity_key("MS", &t("goal_pose"), "geometry_msgs/msg/PoseStamped", QOS_COMMAND);
        // In the graph; one Zenoh subscriber each serves every copter (`Ros2Node::subscribe`).
        g.token_later(&cmd_vel);
        g.token_later(&goal);
        Ok(CopterTopics {
            pose: RosPub::declare(g, &t("pose"), "geometry_msgs/msg/PoseStamped", QOS_SENSOR)?,
            odom: RosPub::declare(g, &t("odom"), "nav_msgs/msg/Odometry", QOS_SENSOR)?,
            imu: RosPub::declare(g, &t("imu"), "sensor_msgs/msg/Imu", QOS_SENSOR)?,
            sonar: [s0?, s1?, s2?, s3?],
            ir: RosPub::declare(g, &t("ir"), range, QOS_SENSOR)?,
            battery: RosPub::declare(g, &t("battery"), "sensor_msgs/msg/BatteryState", QOS_SENSOR)?,
            battery_at_s: None,
            base_frame: format!("{name}/base_link"),
            sonar_frames: SIDES.map(|side| format!("{name}/sonar_{side}")),
            ir_frame: format!("{name}/ir"),
            name,
        })
    }

    /// The subscription to every copter's `/<c>/<topic>`: one Zenoh subscriber whose key
    /// names any copter (declaring one per copter costs Zenoh time quadratic in the count).
    /// `convert` turns a message into a command, submitted like Zenoh's, from the client
    /// [`RosClaims::client_of`] finds (else the GID in hex), answering the tick of the last
    /// `/clock` sent.
    fn subscribe(
        &mut self,
        topic: &str,
        ty: &str,
        convert: Convert,
    ) -> Result<zenoh::pubsub::Subscriber<()>, NodeError> {
        let (commands, latest) = (self.commands.clone(), self.latest.clone());
        let (claims, tick) = (self.claims.clone(), self.tick.clone());
        let key = data_key(self.graph.domain, &format!("/*/{topic}"), ty);
        self.graph
            .session
            .declare_subscriber(key)
            .callback(move |sample| {
                let answers = Some(tick.load(Ordering::Acquire)).filter(|&t| t != NO_FRAME);
                let key = sample.key_expr().as_str();
                let ros_name = key.split('/').nth(1).unwrap_or_default();
                let gid = sample.attachment().and_then(|a| attachment_gid(&a.to_bytes()));
                let client = gid.map(|g| claims.client_of(ros_name, &g).unwrap_or_else(|| hex(&g)));
                // A name no copter has: submitted as it is, rejected as an unknown copter.
                let found = crate::lock(&latest).get(ros_name).cloned();
                let (copter, now) = found.map_or((ros_name.to_owned(), (0.0, 0.0)), |(_, name, now)| (name, now));
                let payload = sample.payload().to_bytes();
                let converted = convert(&payload, now);
                let text = match &converted {
                    Ok((_, text)) => text.clone(),
                    Err(_) => format!("CDR {}", hex(&payload[..payload.len().min(64)])),
                };
                let origin = BusInput { key: key.to_owned(), text, received_unix_ns: crate::log::now_unix_ns() };
                commands.submit(
                    &copter,
                    |world| {
                        let (mut cmd, _) = converted.map_err(CommandError::Malformed)?;
                        cmd.client = client;
                        cmd.tick = answers;
                        if let Some(h) = cmd.height.as_mut() {
                            *h = h.clamp(0.0, world.arena.height_m);
                        }
                        cmd.validate(world)?;
                        Ok(cmd)
                    },
                    origin,
                );
            })
            .wait()
            .map_err(zerr)
    }

    /// Publishes what is due of one frame.
    pub fn publish(&mut self, frame: &Frame) -> Result<(), NodeError> {
        if frame.world.copters.len() > self.copters.len() {
            self.add_copters(&frame.world)?;
        }
        // What commands answering this frame need, before `/clock` tells of it.
        {
            let mut latest = crate::lock(&self.latest);
            for (&i, s) in frame.ids.iter().zip(&frame.states) {
                if let Some(l) = latest.get_mut(&self.copters[i as usize].name) {
                    l.2 = (s.pos_m[2], s.attitude_rad[2]);
                }
            }
        }
        self.tick.store(frame.tick, Ordering::Release);
        let stamp = Stamp::from_secs(frame.time_s);
        let mut sent = u64::from(self.clock.send(|| msgs::clock(stamp))?);
        let due = frame.time_s + 1e-9 >= self.next_due_s;
        if due && let Some(hz) = self.opts.max_rate_hz {
            self.next_due_s = frame.time_s + 1.0 / hz;
        }
        if due {
            for (&i, s) in frame.ids.iter().zip(&frame.states) {
                sent += self.copters[i as usize].send_state(stamp, s)?;
            }
            if self.tf.wanted() {
                let copters = &self.copters;
                let children = (frame.ids.iter().zip(&frame.states))
                    .map(|(&i, s)| (copters[i as usize].base_frame.as_str(), pose_of(s)));
                self.tf.put(msgs::tf(stamp, "world", children))?;
                sent += 1;
            }
        }
        if !frame.sensors.is_empty() {
            let spec = &frame.world.sensors.spec;
            let fresh = sim_core::fresh_sonars(spec, frame.tick.saturating_sub(1), true);
            for ((&i, s), st) in frame.ids.iter().zip(&frame.sensors).zip(&frame.states) {
                let fresh = if st.crashed { [false; 4] } else { fresh };
                sent += self.copters[i as usize].send_sensors(stamp, &frame.world, s, fresh, due)?;
            }
        }
        self.stats.sent += sent;
        Ok(())
    }
}

impl CopterTopics {
    fn send_state(&mut self, stamp: Stamp, s: &StateMsg) -> Result<u64, NodeError> {
        let pose = pose_of(s);
        let frame = &self.base_frame;
        let mut sent = u64::from(self.pose.send(|| msgs::pose_stamped(stamp, "world", &pose))?);
        sent += u64::from(self.odom.send(|| {
            let r = rotation(s.quat_xyzw);
            let lin = r.transpose() * nalgebra::Vector3::from(s.vel_m_s.map(f64::from));
            let ang = r.transpose() * nalgebra::Vector3::from(s.angvel_rad_s.map(f64::from));
            msgs::odometry(stamp, "world", frame, &pose, lin.into(), ang.into())
        })?);
        Ok(sent)
    }

    fn send_sensors(
        &mut self,
        stamp: Stamp,
        world: &World,
        s: &SensorsMsg,
        fresh: [bool; 4],
        due: bool,
    ) -> Result<u64, NodeError> {
        let spec = &world.sensors.spec;
        let base = &self.base_frame;
        let mut sent = 0;
        if due {
            sent += u64::from(self.imu.send(|| {
                let var = |sigma: f32| f64::from(sigma).powi(2);
                let variances = [
                    var(spec.imu.attitude_noise_deg.to_radians()),
                    var(spec.imu.rate_noise_deg_s.to_radians()),
                    var(spec.imu.accel_noise_m_s2),
                ];
                let q = quat_of_rpy(s.attitude_rad);
                let (gyro, accel) = (s.rate_body_rad_s.map(f64::from), s.accel_body_m_s2.map(f64::from));
                msgs::imu(stamp, base, q, gyro, accel, variances)
            })?);
        }
        let sonar = RangeSensor {
            radiation_type: 0,
            field_of_view: spec.sonar.opening_deg.to_radians(),
            min_range: spec.sonar.min_range_m,
            max_range: spec.sonar.max_range_m,
        };
        let readings = [s.sonar_m.front, s.sonar_m.right, s.sonar_m.back, s.sonar_m.left];
        let sonar_var = spec.sonar.noise_sigma_m.powi(2);
        for k in (0..4).filter(|&k| fresh[k]) {
            let r = if readings[k] >= sonar.max_range { f32::INFINITY } else { readings[k] };
            let frame = &self.sonar_frames[k];
            sent += u64::from(self.sonar[k].send(|| msgs::range(stamp, frame, &sonar, r, sonar_var))?);
        }
        let ir = RangeSensor {
            radiation_type: 1,
            field_of_view: 0.05,
            min_range: spec.ir.min_range_m,
            max_range: spec.ir.max_range_m,
        };
        let frame = &self.ir_frame;
        let ir_var = spec.ir.noise_sigma_m.powi(2);
        sent += u64::from(self.ir.send(|| msgs::range(stamp, frame, &ir, s.ir_m.unwrap_or(f32::INFINITY), ir_var))?);
        let t = f64::from(stamp.sec) + f64::from(stamp.nanosec) * 1e-9;
        if self.battery_at_s.is_none_or(|at| t >= at + 1.0) {
            self.battery_at_s = Some(t);
            sent += u64::from(self.battery.send(|| msgs::battery(stamp, base, s.battery_v, s.battery_charge))?);
        }
        Ok(sent)
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn rotation(q: [f32; 4]) -> nalgebra::Matrix3<f64> {
    let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        f64::from(q[3]),
        f64::from(q[0]),
        f64::from(q[1]),
        f64::from(q[2]),
    ));
    q.to_rotation_matrix().into_inner()
}

fn quat_of_rpy(rpy: [f32; 3]) -> [f64; 4] {
    let q = nalgebra::UnitQuaternion::from_euler_angles(f64::from(rpy[0]), f64::from(rpy[1]), f64::from(rpy[2]));
    [q.i, q.j, q.k, q.w]
}

fn yaw_of(q: [f64; 4]) -> f64 {
    let [x, y, z, w] = q;
    (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z))
}

fn pose_of(s: &StateMsg) -> Pose {
    Pose { pos: s.pos_m.map(f64::from), quat: s.quat_xyzw.map(f64::from) }
}

fn wrap_pi(a: f32) -> f32 {
    (a + std::f32::consts::PI).rem_euclid(std::f32::consts::TAU) - std::f32::consts::PI
}

/// `cmd_vel` (forward, left and vertical speed, yaw rate) as a velocity-mode command; `now`
/// is the copter's height and yaw.
fn twist_command(cdr: &[u8], (z, yaw): (f32, f32)) -> Result<(CommandMsg, String), String> {
    let (lin, ang) = msgs::decode_twist(cdr).map_err(|e| format!("cmd_vel: {e}"))?;
    let cmd = CommandMsg {
        mode: Some(FlightMode::Velocity),
        velocity: Some([lin[0] as f32, lin[1] as f32]),
        height: Some(z + lin[2] as f32 * RATE_LOOKAHEAD_S),
        yaw: Some(wrap_pi(yaw + ang[2] as f32 * RATE_LOOKAHEAD_S)),
        ..CommandMsg::default()
    };
    Ok((cmd, format!("Twist linear {lin:?} angular {ang:?}")))
}

/// `goal_pose` (in `world`) as a target-mode command.
fn goal_command(cdr: &[u8], _: (f32, f32)) -> Result<(CommandMsg, String), String> {
    let (frame, pose) = msgs::decode_pose_stamped(cdr).map_err(|e| format!("goal_pose: {e}"))?;
    if !frame.is_empty() && frame != "world" {
        return Err(format!("goal_pose: frame {frame:?} is not \"world\""));
    }
    let cmd = CommandMsg {
        mode: Some(FlightMode::Target),
        target: Some(pose.pos.map(|v| v as f32)),
        yaw: Some(yaw_of(pose.quat) as f32),
        ..CommandMsg::default()
    };
    Ok((cmd, format!("PoseStamped {:?} {:?}", pose.pos, pose.quat)))
}

/// Each copter's sensor frames on its body: the sonars facing their sides, the IR down.
fn static_transforms(world: &World, copters: &[CopterTopics]) -> Vec<(String, Pose)> {
    let d = f64::from(world.sensors.spec.sonar.mount_offset_m);
    let mut out = Vec::new();
    for c in copters {
        for (k, side) in SIDES.iter().enumerate() {
            let yaw = -(k as f64) * std::f64::consts::FRAC_PI_2;
            let q = nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, yaw);
            let pose = Pose { pos: [d * yaw.cos(), d * yaw.sin(), 0.0], quat: [q.i, q.j, q.k, q.w] };
            out.push((format!("{}/sonar_{side}", c.name), pose));
        }
        let down = nalgebra::UnitQuaternion::from_euler_angles(0.0, std::f64::consts::FRAC_PI_2, 0.0);
        out.push((format!("{}/ir", c.name), Pose { pos: [0.0; 3], quat: [down.i, down.j, down.k, down.w] }));
    }
    out
}

/// The arena as cubes: floor, walls (if any), boxes.
fn arena_cubes(world: &World) -> Vec<Cube> {
    let a = &world.arena;
    let [sx, sy] = a.size_m.map(f64::from);
    let (h, t) = (f64::from(a.height_m), f64::from(a.wall_thickness_m));
    let level = Pose { pos: [0.0; 3], quat: [0.0, 0.0, 0.0, 1.0] };
    let cube = |ns: &str, id: i32, pos: [f64; 3], size: [f64; 3], rgba: [f32; 4]| Cube {
        ns: ns.into(),
        id,
        pose: Pose { pos, ..level },
        size,
        rgba,
    };
    let mut cubes = vec![cube("floor", 0, [0.0, 0.0, -t / 2.0], [sx, sy, t], [0.5, 0.5, 0.5, 1.0])];
    if a.walls {
        let wall = [0.7, 0.7, 0.8, 0.3];
        cubes.push(cube("walls", 0, [(sx + t) / 2.0, 0.0, h / 2.0], [t, sy, h], wall));
        cubes.push(cube("walls", 1, [-(sx + t) / 2.0, 0.0, h / 2.0], [t, sy, h], wall));
        cubes.push(cube("walls", 2, [0.0, (sy + t) / 2.0, h / 2.0], [sx, t, h], wall));
        cubes.push(cube("walls", 3, [0.0, -(sy + t) / 2.0, h / 2.0], [sx, t, h], wall));
    }
    for (k, b) in world.spec.boxes.iter().enumerate() {
        let q = nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, f64::from(b.yaw_deg).to_radians());
        let size = b.size_m.map(f64::from);
        let pos = [f64::from(b.pos_m[0]), f64::from(b.pos_m[1]), f64::from(b.z_m) + size[2] / 2.0];
        let rgba = if b.virtual_only { [0.2, 0.6, 1.0, 0.5] } else { [0.8, 0.5, 0.2, 1.0] };
        cubes.push(Cube { pose: Pose { pos, quat: [q.i, q.j, q.k, q.w] }, ..cube("boxes", k as i32, pos, size, rgba) });
    }
    cubes
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_and_names_follow_rmw_zenoh() {
        assert_eq!(ros_name("finken-1"), "finken_1");
        assert_eq!(ros_name("7up"), "c_7up");
        assert_eq!(
            data_key(0, "/robot1/pose", "geometry_msgs/msg/PoseStamped"),
            "0/robot1/pose/geometry_msgs::msg::dds_::PoseStamped_/\
             RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"
        );
        let gid: [u8; 16] = std::array::from_fn(|k| k as u8);
        let a = attachment(1, &gid);
        assert_eq!((a.len(), &a[..8], a[16]), (33, &1i64.to_le_bytes()[..], 16));
        assert_eq!(attachment_gid(&a), Some(gid));
        assert_eq!(attachment_gid(&a[..20]), None);
    }

    #[test]
    fn gids_are_rmw_zenoh_cpps() {
        // XXH3-128 of "": 99aa06d3014798d8 6001c324468d497f (xxHash's own test vector).
        let want = [0x6001_c324_468d_497f_u64.to_le_bytes(), 0x99aa_06d3_0147_98d8_u64.to_le_bytes()].concat();
        assert_eq!(gid_of("")[..], want[..]);
        let parts: Vec<&str> = "@ros2_lv/0/1f2e/3/7/MP/%/%ns/pilot/%f1%cmd_vel/t/h/q".split('/').collect();
        assert_eq!(ros_client(&parts), "ros2:/ns/pilot@1f2e/3");
        let parts: Vec<&str> = "@ros2_lv/0/1f2e/0/7/MP/%/%/pilot/%f1%cmd_vel/t/h/q".split('/').collect();
        assert_eq!(ros_client(&parts), "ros2:/pilot@1f2e/0");
    }

    #[test]
    fn a_nodes_command_publishers_claim_its_copters_and_name_its_commands() {
        let world = Arc::new(sim_core::scene::load_default().1);
        let (tx, rx) = std::sync::mpsc::sync_channel(64);
        let claims = RosClaims { sink: CommandSink::detached(world, tx), book: Mutex::default() };
        let token = |nid: u32, eid: u32, node: &str, topic: &str, ty: &str| {
            let (t, h) = (dds_name(ty), type_hash(ty));
            format!("@ros2_lv/0/ab12/{nid}/{eid}/MP/%/%/{node}/%finken1%{topic}/{t}/{h}/::,10:,:,:,,")
        };
        let on = |key: &str, put: bool| claims.on_publisher(key, &key.split('/').collect::<Vec<_>>(), put);
        let controllers = || -> Vec<Option<String>> {
            rx.try_iter()
                .filter_map(|r| match r {
                    crate::engine::request::Request::Controller { client, .. } => Some(client),
                    _ => None,
                })
                .collect()
        };
        let (twist, goal_ty) = ("geometry_msgs/msg/Twist", "geometry_msgs/msg/PoseStamped");
        // Tokens before the copter is known (the graph's history): filed when it is. Neither
        // a pose publisher nor a cmd_vel of another type is a claim.
        let (vel, goal) = (token(1, 5, "pilot", "cmd_vel", twist), token(1, 6, "pilot", "goal_pose", goal_ty));
        on(&vel, true);
        on(&token(1, 7, "pilot", "pose", goal_ty), true);
        on(&token(3, 5, "stamped", "cmd_vel", "geometry_msgs/msg/TwistStamped"), true);
        assert!(controllers().is_empty());
        claims.copter_added("finken1", "finken1");
        let pilot = Some("ros2:/pilot@ab12/1".to_owned());
        assert_eq!(controllers(), std::slice::from_ref(&pilot));
        // A GID not made from a token, while the pilot alone publishes: learned as the pilot's.
        assert_eq!(claims.client_of("finken1", &[9; 16]), pilot);
        // Its second command publisher is the same claim; a second node queues behind it.
        on(&goal, true);
        on(&vel, true); // a duplicate put
        let other = token(2, 5, "other", "cmd_vel", twist);
        on(&other, true);
        assert!(controllers().is_empty());
        // Commands are known by their rmw_zenoh GIDs or learned ones; a new GID is nobody's
        // with two nodes on the copter.
        assert_eq!(claims.client_of("finken1", &gid_of(&goal)), pilot);
        assert_eq!(claims.client_of("finken1", &[9; 16]), pilot);
        assert_eq!(claims.client_of("finken1", &gid_of(&other)).as_deref(), Some("ros2:/other@ab12/2"));
        assert_eq!(claims.client_of("finken1", &[7; 16]), None);
        assert_eq!(claims.client_of("finken2", &gid_of(&goal)), None);
        // The pilot goes: the other node takes over, and is then the one node on finken1.
        on(&vel, false);
        assert!(controllers().is_empty(), "goal_pose still claims");
        on(&goal, false);
        assert_eq!(controllers(), [Some("ros2:/other@ab12/2".to_owned())]);
        assert_eq!(claims.client_of("finken1", &[9; 16]).as_deref(), Some("ros2:/other@ab12/2"));
        on(&other, false);
        assert_eq!(controllers(), [None]);
    }

    #[test]
    fn commands_from_twist_and_goal_pose() {
        let mut w = super::super::cdr::CdrWriter::new();
        w.f64s(&[0.3, -0.1, 0.2, 0.0, 0.0, 0.5]);
        let (cmd, _) = twist_command(&w.into_bytes(), (1.0, 3.0)).unwrap();
        assert_eq!((cmd.mode, cmd.velocity, cmd.height), (Some(FlightMode::Velocity), Some([0.3, -0.1]), Some(1.2)));
        assert!((cmd.yaw.unwrap() - (3.5 - std::f32::consts::TAU)).abs() < 1e-5, "{:?}", cmd.yaw);
        let q = nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, 0.7);
        let pose = Pose { pos: [1.0, 0.5, 1.2], quat: [q.i, q.j, q.k, q.w] };
        let (cmd, _) = goal_command(&msgs::pose_stamped(Stamp::default(), "world", &pose), (0.0, 0.0)).unwrap();
        assert_eq!(cmd.target, Some([1.0, 0.5, 1.2]));
        assert!((cmd.yaw.unwrap() - 0.7).abs() < 1e-6);
        let err = goal_command(&msgs::pose_stamped(Stamp::default(), "map", &pose), (0.0, 0.0)).unwrap_err();
        assert!(err.contains("\"map\""), "{err}");
        assert!(twist_command(&[0, 1, 0, 0], (0.0, 0.0)).unwrap_err().contains("cmd_vel"));
    }
}
