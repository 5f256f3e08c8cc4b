//! An Ivy agent on tokio: UDP discovery, one TCP connection per peer, sender-side matching.
//!
//! - **Discovery.** At start the agent listens on TCP (127.0.0.1 on a loopback bus, an
//!   ephemeral port), then sends one hello to each bus domain. Every agent already on the bus
//!   connects to it; it connects to every agent whose hello it hears later (ivy-c `ivy.c`
//!   `BroadcastReceive`, ivy-python `IvyServer.serve_forever`/`_IvyBroadcastHandler`). Hellos
//!   of another version, malformed ones and our own (same app id) are dropped and counted. A
//!   hello from an agent already connected (same app id, or same address and port) is ignored,
//!   which ivy-python does by `(ip, port)` only.
//! - **Handshake.** On every new connection, accepted or made, both sides send at once,
//!   without waiting: StartRegexp (own TCP port, app name), one AddRegexp per binding,
//!   EndRegexp (ivy-python `IvyHandler.handle`, ivy-c `SendSubscriptions`; ivy-java's accepting
//!   side waits for the peer to speak first, so a connector must not wait).
//! - **Sending** ([`IvyAgent::send`]): the agent matches the text against every regex every
//!   peer subscribed and queues one Msg per match with the captured groups, as Ivy does
//!   (sender-side matching; a group that did not take part is sent empty, as ivy-python does).
//!   Peer regexes are compiled by the `regex` crate within [`bus`](crate::paparazzi::bus)'s
//!   size limits, so no regex can stall matching; one that does not compile (a PCRE
//!   look-around, a back-reference, an oversize one) gets an Error line back and is counted,
//!   as ivy-c does (`ivy.c` `AddRegexp` → `MsgSendTo(... Error, "Error compiling ...")`).
//!   Searching is unanchored (ivy-c); ivy-python's `re.match` anchors at the start and
//!   ivy-java needs a full match, so Paparazzi's regexes all start with `^`.
//! - **Receiving.** A text binding ([`IvyAgent::bind`]) is sent to peers wrapped as
//!   `^(.*?(?:P).*)$`, so its first group is the whole text; the agent then runs its own regex
//!   `P` on it for the handler's groups. A raw binding ([`IvyAgent::bind_raw`]) is sent as is
//!   and its handler receives the peer's groups (what `ivyprobe` prints).
//! - **Never stalls the caller.** Each peer has a bounded queue of lines; a peer that does not
//!   read loses messages (counted), the sender never waits. Lines longer than
//!   [`MAX_LINE_BYTES`](super::frame::MAX_LINE_BYTES) are dropped and counted; a connection
//!   that does not introduce itself within [`IvyOptions::handshake_timeout`] is closed; at most
//!   [`IvyOptions::max_peers`] connections are kept.
//! - **Die** sets the caller's stop flag (the simulator then ends its run cleanly) and the
//!   agent leaves the bus with Bye, as ivy-python does.

use std::collections::{BTreeMap, BTreeSet};
use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use regex::{CaptureLocations, Regex};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream, UdpSocket};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

use super::busaddr::BusAddr;
use super::frame::{Frame, FrameError, Hello, Line, LineSplitter, PROTOCOL_VERSION, encode_msg};
use crate::paparazzi::bus::{BindId, Bus, BusError, Control, Delivery, compile};
use crate::paparazzi::codec::split_header;

/// A connection that has not sent StartRegexp after this long is closed (default).
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// Lines queued per peer before messages to it are dropped.
pub const PEER_QUEUE_LINES: usize = 4096;

/// Options of an [`IvyAgent`].
#[derive(Clone, Debug)]
pub struct IvyOptions {
    /// The bus.
    pub bus: BusAddr,
    /// Application name, as peers show it (`ivyprobe`, Paparazzi's `server`).
    pub app_name: String,
    /// Most peers connected at once; further connections are refused and counted.
    pub max_peers: usize,
    /// Set when a peer sends Die.
    pub on_die: Option<Arc<AtomicBool>>,
    /// A connection that has not sent StartRegexp after this long is closed.
    pub handshake_timeout: Duration,
}

impl IvyOptions {
    /// Options for `app_name` on `bus`, with at most 256 peers.
    pub fn new(bus: BusAddr, app_name: impl Into<String>) -> Self {
        Self { bus, app_name: app_name.into(), max_peers: 256, on_die: None, handshake_timeout: HANDSHAKE_TIMEOUT }
    }
}

/// Errors of the agent.
#[derive(Debug, thiserror::Error)]
pub enum IvyError {
    /// A regex the agent binds is not usable.
    #[error(transparent)]
    Bus(#[from] BusError),
    /// A socket could not be opened.
    #[error("ivy bus {bus}: {what}: {source}")]
    Io {
        /// The bus.
        bus: String,
        /// What was being done.
        what: &'static str,
        /// The error.
        source: std::io::Error,
    },
    /// The text cannot travel on Ivy (it holds a newline or a separator).
    #[error("text holds a newline, \\x02 or \\x03 and cannot be sent on Ivy")]
    Unsendable,
}

/// Counters of an agent; every received line and hello is counted once, in exactly one of
/// the accepted or the dropped counters.
#[derive(Debug, Default)]
pub struct IvyCounters {
    /// Hellos received (all, ours included).
    pub hellos: AtomicU64,
    /// Peers that completed the handshake.
    pub peers_joined: AtomicU64,
    /// Peers gone (Bye, closed, error).
    pub peers_left: AtomicU64,
    /// Lines received from peers.
    pub lines: AtomicU64,
    /// Msg lines received.
    pub msgs_received: AtomicU64,
    /// Texts handed to local handlers.
    pub delivered: AtomicU64,
    /// Texts sent ([`IvyAgent::send`] calls that were sendable).
    pub texts_sent: AtomicU64,
    /// Msg lines queued to peers (one per matching peer regex).
    pub msgs_sent: AtomicU64,
    /// Regexes peers subscribed.
    pub peer_regexes: AtomicU64,
    /// Errors received from peers.
    pub errors_received: AtomicU64,
    /// Direct messages received.
    pub direct_msgs: AtomicU64,
}

/// One peer, as [`IvyAgent::peers`] lists it.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct PeerInfo {
    /// App name (from StartRegexp).
    pub app_name: String,
    /// App id (from its hello; empty for a peer that connected to us).
    pub app_id: String,
    /// Its address.
    pub addr: String,
    /// Its TCP port (from StartRegexp).
    pub port: u16,
    /// Whether its EndRegexp arrived.
    pub ready: bool,
    /// Its regexes, by id.
    pub regexes: Vec<(u32, String)>,
    /// Its regexes that did not compile here, by id.
    pub refused: Vec<(u32, String)>,
    /// Messages to it dropped because it did not read.
    pub dropped: u64,
}

/// A peer joining or leaving.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PeerEvent {
    /// Seconds since the agent started.
    pub t_s: f64,
    /// `joined` or `left`.
    pub what: &'static str,
    /// The peer's app name.
    pub app_name: String,
    /// Why it left (`bye`, `closed`, `error: ...`).
    pub why: String,
}

/// A raw binding's handler: the peer's captured groups.
pub type RawHandler = Box<dyn FnMut(&[String]) + Send>;

enum LocalKind {
    /// Dispatched through the local bus (its id there).
    Text(BindId),
    /// The peer's groups as they are.
    Raw(RawHandler),
}

struct Local {
    bus: Bus,
    next_id: u32,
    /// By wire id: the regex sent to peers, and what to do with a Msg for it.
    wire: BTreeMap<u32, (String, LocalKind)>,
}

struct PeerRegex {
    regex: Regex,
    locs: CaptureLocations,
    /// The exact message name every match has, if known (skips the regex otherwise).
    name: Option<String>,
    text: String,
}

struct Peer {
    app_name: String,
    app_id: String,
    addr: SocketAddr,
    port: u16,
    ready: bool,
    regexes: BTreeMap<u32, PeerRegex>,
    refused: BTreeMap<u32, String>,
    tx: mpsc::Sender<Vec<u8>>,
    dropped: u64,
}

struct Inner {
    opts: IvyOptions,
    app_id: String,
    port: u16,
    started: Instant,
    local: Mutex<Local>,
    peers: Mutex<BTreeMap<u64, Peer>>,
    next_peer: AtomicU64,
    counters: IvyCounters,
    drops: Mutex<BTreeMap<&'static str, u64>>,
    events: Mutex<Vec<PeerEvent>>,
    /// The Pongs heard, by ping id ([`IvyAgent::sync_with`]), and who waits for them.
    pongs: Mutex<BTreeSet<u32>>,
    pong_heard: Condvar,
    next_ping: AtomicU32,
}

/// Keeps at most this many peer events.
const MAX_EVENTS: usize = 10_000;

impl Inner {
    fn drop_one(&self, reason: &'static str) {
        *crate::lock(&self.drops).entry(reason).or_insert(0) += 1;
    }

    fn event(&self, what: &'static str, app_name: &str, why: &str) {
        tracing::info!("ivy: {app_name} {what}{}", if why.is_empty() { String::new() } else { format!(" ({why})") });
        let mut e = crate::lock(&self.events);
        if e.len() < MAX_EVENTS {
            e.push(PeerEvent {
                t_s: self.started.elapsed().as_secs_f64(),
                what,
                app_name: app_name.to_owned(),
                why: why.to_owned(),
            });
        }
    }
}

/// An agent on an Ivy bus (see the module docs). Dropping it leaves the bus without Bye; call
/// [`IvyAgent::stop`] to say Bye first.
pub struct IvyAgent {
    inner: Arc<Inner>,
    tasks: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for IvyAgent {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("IvyAgent")
            .field("app_name", &self.inner.opts.app_name)
            .field("bus", &self.inner.opts.bus.to_string())
            .field("port", &self.inner.port)
            .finish_non_exhaustive()
    }
}

fn io_err(bus: &BusAddr, what: &'static str) -> impl FnOnce(std::io::Error) -> IvyError {
    let bus = bus.to_string();
    move |source| IvyError::Io { bus, what, source }
}

/// The UDP socket that receives hellos: address and port reusable by every agent on this
/// machine, broadcast allowed. On a single-domain loopback bus it is bound to that domain, so
/// nothing outside loopback reaches it.
fn hello_socket(bus: &BusAddr) -> std::io::Result<UdpSocket> {
    use socket2::{Domain, Protocol, Socket, Type};
    let s = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
    s.set_reuse_address(true)?;
    s.set_reuse_port(true)?;
    s.set_broadcast(true)?;
    let ip = match bus.domains.as_slice() {
        [d] if d.is_loopback() => *d,
        _ => Ipv4Addr::UNSPECIFIED,
    };
    for d in &bus.domains {
        if d.is_multicast() {
            s.join_multicast_v4(d, &Ipv4Addr::UNSPECIFIED)?;
            s.set_multicast_ttl_v4(64)?;
        }
    }
    s.bind(&SocketAddr::V4(SocketAddrV4::new(ip, bus.port)).into())?;
    s.set_nonblocking(true)?;
    UdpSocket::from_std(s.into())
}

impl IvyAgent {
    /// Joins the bus: listens on TCP, sends the hello, and starts answering peers. Must run
    /// inside a tokio runtime.
    pub async fn start(opts: IvyOptions) -> Result<IvyAgent, IvyError> {
        let bus = opts.bus.clone();
        let loopback = bus.is_loopback();
        let tcp_ip = if loopback { Ipv4Addr::LOCALHOST } else { Ipv4Addr::UNSPECIFIED };
        let listener = TcpListener::bind((tcp_ip, 0)).await.map_err(io_err(&bus, "TCP listen"))?;
        let port = listener.local_addr().map_err(io_err(&bus, "TCP listen"))?.port();
        let udp = hello_socket(&bus).map_err(io_err(&bus, "UDP bind"))?;
        let unix_ms = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_millis());
        let app_id = format!("twinswarm_{}_{unix_ms}_{port}", std::process::id());
        let inner = Arc::new(Inner {
            opts,
            app_id,
            port,
            started: Instant::now(),
            local: Mutex::new(Local { bus: Bus::new(), next_id: 0, wire: BTreeMap::new() }),
            peers: Mutex::new(BTreeMap::new()),
            next_peer: AtomicU64::new(0),
            counters: IvyCounters::default(),
            drops: Mutex::new(BTreeMap::new()),
            events: Mutex::new(Vec::new()),
            pongs: Mutex::new(BTreeSet::new()),
            pong_heard: Condvar::new(),
            next_ping: AtomicU32::new(1),
        });
        // The hello goes out from a socket of its own: on loopback its source is 127.0.0.1,
        // the address peers then connect to.
        let sender = if loopback {
            let s = std::net::UdpSocket::bind((Ipv4Addr::LOCALHOST, 0)).map_err(io_err(&bus, "UDP send socket"))?;
            s.set_broadcast(true).map_err(io_err(&bus, "UDP send socket"))?;
            s.set_nonblocking(true).map_err(io_err(&bus, "UDP send socket"))?;
            Some(UdpSocket::from_std(s).map_err(io_err(&bus, "UDP send socket"))?)
        } else {
            None
        };
        let hello = Hello {
            version: PROTOCOL_VERSION,
            port,
            app_id: inner.app_id.clone(),
            app_name: inner.opts.app_name.clone(),
        }
        .encode();
        let mut tasks = Vec::new();
        tasks.push(tokio::spawn(accept_loop(inner.clone(), listener)));
        let udp = Arc::new(udp);
        tasks.push(tokio::spawn(hello_loop(inner.clone(), udp.clone())));
        for d in &bus.domains {
            let to = SocketAddr::V4(SocketAddrV4::new(*d, bus.port));
            let sent = match &sender {
                Some(s) => s.send_to(&hello, to).await,
                None => udp.send_to(&hello, to).await,
            };
            sent.map_err(io_err(&bus, "sending the hello"))?;
        }
        tracing::info!("ivy: joined {} as `{}` (tcp port {port})", bus, inner.opts.app_name);
        Ok(IvyAgent { inner, tasks })
    }

    /// The agent's TCP port.
    pub fn port(&self) -> u16 {
        self.inner.port
    }

    /// The agent's app id (in its hello).
    pub fn app_id(&self) -> &str {
        &self.inner.app_id
    }

    /// Counters.
    pub fn counters(&self) -> &IvyCounters {
        &self.inner.counters
    }

    /// Dropped hellos, lines and messages, by reason.
    pub fn drops(&self) -> BTreeMap<&'static str, u64> {
        crate::lock(&self.inner.drops).clone()
    }

    /// Peers joining and leaving, in order.
    pub fn events(&self) -> Vec<PeerEvent> {
        crate::lock(&self.inner.events).clone()
    }

    /// The peers connected now, by app name.
    pub fn peers(&self) -> Vec<PeerInfo> {
        let peers = crate::lock(&self.inner.peers);
        let mut v: Vec<PeerInfo> = peers
            .values()
            .map(|p| PeerInfo {
                app_name: p.app_name.clone(),
                app_id: p.app_id.clone(),
                addr: p.addr.to_string(),
                port: p.port,
                ready: p.ready,
                regexes: p.regexes.iter().map(|(id, r)| (*id, r.text.clone())).collect(),
                refused: p.refused.iter().map(|(id, r)| (*id, r.clone())).collect(),
                dropped: p.dropped,
            })
            .collect();
        v.sort_by(|a, b| a.app_name.cmp(&b.app_name).then(a.port.cmp(&b.port)));
        v
    }

    /// Binds `pattern` (the `regex` crate's syntax, which for Paparazzi's patterns is also
    /// PCRE's, Python's and Java's): `handler` receives each matching text whole, with the
    /// groups of `pattern`, like [`Bus::bind`].
    pub fn bind(
        &self,
        pattern: &str,
        handler: impl FnMut(&Delivery<'_>, &mut Control) + Send + 'static,
    ) -> Result<u32, IvyError> {
        let wire = format!("^(.*?(?:{pattern}).*)$");
        let mut local = crate::lock(&self.inner.local);
        let bind_id = local.bus.bind(pattern, handler)?;
        Ok(self.add_wire(&mut local, wire, LocalKind::Text(bind_id)))
    }

    /// Binds `pattern` as Ivy's `IvyBindMsg` does: peers compile it (in their own syntax) and
    /// `handler` receives their captured groups.
    pub fn bind_raw(&self, pattern: &str, handler: impl FnMut(&[String]) + Send + 'static) -> Result<u32, IvyError> {
        if pattern.contains(['\n', '\x02']) {
            return Err(IvyError::Unsendable);
        }
        let mut local = crate::lock(&self.inner.local);
        Ok(self.add_wire(&mut local, pattern.to_owned(), LocalKind::Raw(Box::new(handler))))
    }

    fn add_wire(&self, local: &mut Local, wire: String, kind: LocalKind) -> u32 {
        let id = local.next_id;
        local.next_id += 1;
        let mut line = Vec::new();
        Frame::AddRegexp { id, regex: wire.clone() }.encode(&mut line);
        local.wire.insert(id, (wire, kind));
        // Lock order: local, then peers (as in the handshake).
        for p in crate::lock(&self.inner.peers).values_mut() {
            queue(&self.inner, p, line.clone());
        }
        id
    }

    /// Removes binding `id` and tells every peer (DelRegexp). Returns whether it was bound.
    pub fn unbind(&self, id: u32) -> bool {
        let mut local = crate::lock(&self.inner.local);
        let Some((_, kind)) = local.wire.remove(&id) else { return false };
        if let LocalKind::Text(b) = kind {
            local.bus.unbind(b);
        }
        let mut line = Vec::new();
        Frame::DelRegexp { id }.encode(&mut line);
        for p in crate::lock(&self.inner.peers).values_mut() {
            queue(&self.inner, p, line.clone());
        }
        true
    }

    /// Sends `text` to every peer regex it matches; returns the number of Msg lines queued.
    /// Never waits: a peer whose queue is full loses the message (counted).
    pub fn send(&self, text: &str) -> Result<usize, IvyError> {
        if text.contains(['\n', '\x02', '\x03']) {
            self.inner.drop_one("unsendable text (newline or separator)");
            return Err(IvyError::Unsendable);
        }
        self.inner.counters.texts_sent.fetch_add(1, Ordering::Relaxed);
        let name = split_header(text).map(|(_, n, _)| n);
        let mut n = 0;
        let mut peers = crate::lock(&self.inner.peers);
        let mut groups: Vec<&str> = Vec::new();
        for p in peers.values_mut() {
            let mut out = Vec::new();
            for (id, r) in p.regexes.iter_mut() {
                if let Some(want) = &r.name
                    && Some(want.as_str()) != name
                {
                    continue;
                }
                if r.regex.captures_read(&mut r.locs, text).is_none() {
                    continue;
                }
                groups.clear();
                groups.extend((1..r.locs.len()).map(|g| r.locs.get(g).map_or("", |(s, e)| &text[s..e])));
                if encode_msg(*id, &groups, &mut out).is_ok() {
                    n += 1;
                }
            }
            if !out.is_empty() {
                queue(&self.inner, p, out);
            }
        }
        self.inner.counters.msgs_sent.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }

    /// How many peers have a regex that `text` matches (`send` would reach them), without
    /// sending it.
    pub fn takers(&self, text: &str) -> usize {
        let name = split_header(text).map(|(_, n, _)| n);
        let peers = crate::lock(&self.inner.peers);
        peers
            .values()
            .filter(|p| {
                p.regexes
                    .values()
                    .any(|r| r.name.as_ref().is_none_or(|want| Some(want.as_str()) == name) && r.regex.is_match(text))
            })
            .count()
    }

    /// Sends a direct message to every peer named `app_name`; returns how many.
    pub fn send_direct(&self, app_name: &str, id: u32, text: &str) -> usize {
        let mut line = Vec::new();
        Frame::DirectMsg { id, text: text.to_owned() }.encode(&mut line);
        self.for_peers_named(app_name, &line)
    }

    /// Waits, up to `timeout`, until a peer named `app_name` is connected and has taken in
    /// everything this agent sent it so far (its bindings included): a Ping, queued after them,
    /// comes back as a Pong, and Ivy agents handle a connection's lines in order. Returns
    /// whether it did. Blocks the calling thread (not one of the runtime's).
    pub fn sync_with(&self, app_name: &str, timeout: Duration) -> bool {
        let deadline = Instant::now() + timeout;
        let id = self.inner.next_ping.fetch_add(1, Ordering::Relaxed);
        let mut line = Vec::new();
        Frame::Ping { id }.encode(&mut line);
        // A peer's name is known once its StartRegexp has come.
        while self.for_peers_named(app_name, &line) == 0 {
            if Instant::now() >= deadline {
                return false;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let mut pongs = crate::lock(&self.inner.pongs);
        loop {
            if pongs.remove(&id) {
                return true;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return false;
            }
            pongs = self.inner.pong_heard.wait_timeout(pongs, left).unwrap_or_else(|e| e.into_inner()).0;
        }
    }

    /// Asks every peer named `app_name` to quit (Die); returns how many.
    pub fn send_die(&self, app_name: &str) -> usize {
        let mut line = Vec::new();
        Frame::Die { id: 0, text: String::new() }.encode(&mut line);
        self.for_peers_named(app_name, &line)
    }

    fn for_peers_named(&self, app_name: &str, line: &[u8]) -> usize {
        let mut peers = crate::lock(&self.inner.peers);
        let mut n = 0;
        for p in peers.values_mut().filter(|p| p.app_name == app_name) {
            queue(&self.inner, p, line.to_vec());
            n += 1;
        }
        n
    }

    /// Leaves the bus: Bye to every peer, then closes everything (after at most 1 s).
    pub async fn stop(&self) {
        let mut bye = Vec::new();
        Frame::Bye.encode(&mut bye);
        let txs: Vec<mpsc::Sender<Vec<u8>>> = crate::lock(&self.inner.peers)
            .values_mut()
            .map(|p| {
                queue(&self.inner, p, bye.clone());
                p.tx.clone()
            })
            .collect();
        // Give the writers a moment to flush the Bye.
        let deadline = tokio::time::Instant::now() + Duration::from_secs(1);
        for tx in txs {
            while tx.capacity() < tx.max_capacity() && tokio::time::Instant::now() < deadline {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
        for t in &self.tasks {
            t.abort();
        }
        crate::lock(&self.inner.peers).clear();
    }
}

impl Drop for IvyAgent {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
        crate::lock(&self.inner.peers).clear();
    }
}

fn queue(inner: &Inner, p: &mut Peer, line: Vec<u8>) {
    if p.tx.try_send(line).is_err() {
        p.dropped += 1;
        inner.drop_one("peer not reading (queue full)");
    }
}

async fn accept_loop(inner: Arc<Inner>, listener: TcpListener) {
    loop {
        match listener.accept().await {
            Ok((stream, addr)) => {
                tokio::spawn(run_peer(inner.clone(), stream, addr, None));
            }
            Err(e) => {
                tracing::warn!("ivy: accept failed: {e}");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
}

async fn hello_loop(inner: Arc<Inner>, udp: Arc<UdpSocket>) {
    let mut buf = vec![0u8; super::frame::MAX_HELLO_BYTES + 1];
    loop {
        let Ok((n, from)) = udp.recv_from(&mut buf).await else {
            tokio::time::sleep(Duration::from_millis(100)).await;
            continue;
        };
        inner.counters.hellos.fetch_add(1, Ordering::Relaxed);
        let hello = match Hello::parse(&buf[..n]) {
            Ok(h) => h,
            Err(e) => {
                tracing::debug!("ivy: bad hello from {from}: {e}");
                inner.drop_one("hello malformed");
                continue;
            }
        };
        if hello.version != PROTOCOL_VERSION {
            inner.drop_one("hello of another protocol version");
            continue;
        }
        if hello.app_id == inner.app_id {
            inner.drop_one("hello: our own");
            continue;
        }
        let addr = SocketAddr::new(from.ip(), hello.port);
        let known = crate::lock(&inner.peers)
            .values()
            .any(|p| p.app_id == hello.app_id || (p.addr.ip() == addr.ip() && p.port == hello.port));
        if known {
            inner.drop_one("hello: agent already connected");
            continue;
        }
        if !inner.opts.bus.is_loopback() || from.ip().is_loopback() {
            let inner = inner.clone();
            tokio::spawn(async move {
                match tokio::time::timeout(Duration::from_secs(3), TcpStream::connect(addr)).await {
                    Ok(Ok(stream)) => run_peer(inner, stream, addr, Some(hello)).await,
                    _ => inner.drop_one("hello: agent unreachable"),
                }
            });
        } else {
            inner.drop_one("hello: not from loopback on a loopback bus");
        }
    }
}

/// Serves one connection until it ends.
async fn run_peer(inner: Arc<Inner>, stream: TcpStream, addr: SocketAddr, hello: Option<Hello>) {
    // Latency only: the connection works with Nagle too.
    let _ = stream.set_nodelay(true);
    let (tx, rx) = mpsc::channel::<Vec<u8>>(PEER_QUEUE_LINES);
    let key = inner.next_peer.fetch_add(1, Ordering::Relaxed);
    {
        // The handshake is queued under the local lock, so no binding made meanwhile is missed.
        let local = crate::lock(&inner.local);
        let mut peers = crate::lock(&inner.peers);
        if peers.len() >= inner.opts.max_peers {
            inner.drop_one("connection refused: too many peers");
            return;
        }
        let mut hs = Vec::new();
        Frame::StartRegexp { port: inner.port, app_name: inner.opts.app_name.clone() }.encode(&mut hs);
        for (id, (regex, _)) in &local.wire {
            Frame::AddRegexp { id: *id, regex: regex.clone() }.encode(&mut hs);
        }
        Frame::EndRegexp.encode(&mut hs);
        // A fresh channel of PEER_QUEUE_LINES slots: the handshake always fits.
        let _ = tx.try_send(hs);
        peers.insert(
            key,
            Peer {
                app_name: hello.as_ref().map(|h| h.app_name.clone()).unwrap_or_default(),
                app_id: hello.as_ref().map(|h| h.app_id.clone()).unwrap_or_default(),
                addr,
                port: hello.as_ref().map_or(0, |h| h.port),
                ready: false,
                regexes: BTreeMap::new(),
                refused: BTreeMap::new(),
                tx,
                dropped: 0,
            },
        );
    }
    let (mut rd, wr) = stream.into_split();
    let writer = tokio::spawn(write_loop(wr, rx));
    let why = read_loop(&inner, key, &mut rd).await;
    writer.abort();
    let name = crate::lock(&inner.peers).remove(&key).map(|p| (p.app_name, p.ready));
    if let Some((name, ready)) = name
        && ready
    {
        inner.counters.peers_left.fetch_add(1, Ordering::Relaxed);
        inner.event("left", &name, &why);
    }
}

async fn write_loop(mut wr: tokio::net::tcp::OwnedWriteHalf, mut rx: mpsc::Receiver<Vec<u8>>) {
    while let Some(mut buf) = rx.recv().await {
        // Batch what is already queued into one write.
        while buf.len() < 64 * 1024 {
            match rx.try_recv() {
                Ok(more) => buf.extend_from_slice(&more),
                Err(_) => break,
            }
        }
        if wr.write_all(&buf).await.is_err() {
            break;
        }
    }
    // Best effort: the peer may be gone already.
    let _ = wr.shutdown().await;
}

/// Reads lines until the peer leaves; returns why it ended.
async fn read_loop(inner: &Arc<Inner>, key: u64, rd: &mut tokio::net::tcp::OwnedReadHalf) -> String {
    let mut splitter = LineSplitter::default();
    let mut buf = vec![0u8; 16 * 1024];
    let opened = tokio::time::Instant::now();
    let mut introduced = false;
    loop {
        let read = if introduced {
            rd.read(&mut buf).await
        } else {
            match tokio::time::timeout_at(opened + inner.opts.handshake_timeout, rd.read(&mut buf)).await {
                Ok(r) => r,
                Err(_) => {
                    inner.drop_one("connection closed: no handshake in time");
                    return "no handshake".into();
                }
            }
        };
        let n = match read {
            Ok(0) => return "closed".into(),
            Ok(n) => n,
            Err(e) => return format!("error: {e}"),
        };
        let mut end: Option<String> = None;
        splitter.push(&buf[..n], |line| {
            if end.is_some() {
                return;
            }
            inner.counters.lines.fetch_add(1, Ordering::Relaxed);
            match line {
                Line::TooLong(_) => inner.drop_one("line too long"),
                Line::Complete(bytes) => match Frame::parse(bytes) {
                    Ok(frame) => {
                        if matches!(frame, Frame::StartRegexp { .. }) {
                            introduced = true;
                        }
                        end = handle_frame(inner, key, frame);
                    }
                    Err(FrameError::NotUtf8) => inner.drop_one("line not UTF-8"),
                    Err(FrameError::UnknownType(_)) => inner.drop_one("line of unknown type"),
                    Err(_) => inner.drop_one("line malformed"),
                },
            }
        });
        if let Some(why) = end {
            return why;
        }
    }
}

/// Acts on one frame from peer `key`; `Some(why)` ends the connection.
fn handle_frame(inner: &Arc<Inner>, key: u64, frame: Frame) -> Option<String> {
    match frame {
        Frame::Msg { id, args } => {
            inner.counters.msgs_received.fetch_add(1, Ordering::Relaxed);
            deliver(inner, id, &args);
        }
        Frame::AddRegexp { id, regex } => {
            inner.counters.peer_regexes.fetch_add(1, Ordering::Relaxed);
            let compiled = compile(&regex);
            let mut peers = crate::lock(&inner.peers);
            let p = peers.get_mut(&key)?;
            match compiled {
                Ok((re, narrowing)) => {
                    let locs = re.capture_locations();
                    let name = narrowing.name.exact().map(str::to_owned);
                    // A reused id replaces the old regex (the protocol's meaning).
                    p.refused.remove(&id);
                    p.regexes.insert(id, PeerRegex { regex: re, locs, name, text: regex });
                }
                Err(e) => {
                    tracing::warn!("ivy: {} subscribed a regex this agent cannot run: {e}", p.app_name);
                    inner.drop_one("peer regex refused");
                    let mut line = Vec::new();
                    Frame::Error { id, text: format!("Error compiling '{regex}': {e}") }.encode(&mut line);
                    p.regexes.remove(&id);
                    p.refused.insert(id, regex);
                    queue(inner, p, line);
                }
            }
        }
        Frame::DelRegexp { id } => {
            if let Some(p) = crate::lock(&inner.peers).get_mut(&key) {
                p.regexes.remove(&id);
                p.refused.remove(&id);
            }
        }
        Frame::StartRegexp { port, app_name } => {
            if let Some(p) = crate::lock(&inner.peers).get_mut(&key) {
                p.app_name = app_name;
                p.port = port;
            }
        }
        Frame::EndRegexp => {
            let name = crate::lock(&inner.peers).get_mut(&key).filter(|p| !p.ready).map(|p| {
                p.ready = true;
                p.app_name.clone()
            });
            if let Some(name) = name {
                inner.counters.peers_joined.fetch_add(1, Ordering::Relaxed);
                inner.event("joined", &name, "");
            }
        }
        Frame::Ping { id } => {
            let mut line = Vec::new();
            Frame::Pong { id }.encode(&mut line);
            if let Some(p) = crate::lock(&inner.peers).get_mut(&key) {
                queue(inner, p, line);
            }
        }
        Frame::Pong { id } => {
            crate::lock(&inner.pongs).insert(id);
            inner.pong_heard.notify_all();
        }
        Frame::Error { id, text } => {
            inner.counters.errors_received.fetch_add(1, Ordering::Relaxed);
            tracing::warn!("ivy: a peer reports an error about regex {id}: {text}");
        }
        Frame::DirectMsg { id, text } => {
            inner.counters.direct_msgs.fetch_add(1, Ordering::Relaxed);
            tracing::info!("ivy: direct message {id}: {text}");
        }
        Frame::Die { .. } => {
            tracing::warn!("ivy: a peer asked this agent to quit (Die)");
            if let Some(flag) = &inner.opts.on_die {
                flag.store(true, Ordering::Relaxed);
            }
            return Some("die".into());
        }
        Frame::Bye => return Some("bye".into()),
    }
    None
}

/// Hands a Msg for local binding `id` to its handler.
fn deliver(inner: &Inner, id: u32, args: &[String]) {
    let mut local = crate::lock(&inner.local);
    let Local { bus, wire, .. } = &mut *local;
    match wire.get_mut(&id) {
        None => inner.drop_one("msg for a regex id not bound (late after unbind, or bogus)"),
        Some((_, LocalKind::Raw(handler))) => {
            handler(args);
            inner.counters.delivered.fetch_add(1, Ordering::Relaxed);
        }
        Some((_, LocalKind::Text(bind_id))) => {
            let Some(text) = args.first() else {
                inner.drop_one("msg without the text group");
                return;
            };
            // The key names the transport and, like a Zenoh key, the sender and the name, so the
            // log files Ivy traffic under the same `/pprz/<sender>/<NAME>` channels.
            let key = match split_header(text) {
                Some((sender, name, _)) => format!("ivy/pprz/{sender}/{name}"),
                None => "ivy".to_owned(),
            };
            if bus.deliver_to(*bind_id, &key, text) {
                inner.counters.delivered.fetch_add(1, Ordering::Relaxed);
            } else {
                inner.drop_one("msg the local regex does not match (peer's regex engine differs)");
            }
        }
    }
}
