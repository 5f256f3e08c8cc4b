//! The live view: a server speaking the Foxglove WebSocket protocol (`foxglove.websocket.v1`),
//! so that Foxglove (or any client of the protocol) watches a run while it flies, or a log
//! while it is replayed.
//!
//! # How it fits
//!
//! The server holds channels (topic, encoding, schema) and the clients' subscriptions.
//! [`LiveServer::publish`] is called by whoever encodes the messages, the log's writer thread
//! for a run (so a message is encoded once for the file and the view) and the replay loop for
//! a log, from any thread. It never blocks: each client has a bounded queue, a message that
//! finds it full is dropped and counted, and the stepping thread never waits for a client.
//! With no subscriber on a channel, publishing on it is one atomic load, and the run's
//! [`LiveServer::active`] tells the writer to skip the copying and encoding altogether.
//!
//! The server runs on the caller's tokio runtime: one task accepts connections and one task
//! per client moves its queue to the socket and reads its requests.
//!
//! # Protocol
//!
//! <https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md>. The server sends
//! `serverInfo` (capability `time`), `advertise` for every channel (and for channels added
//! later), binary message data (op 1: subscription id, timestamp, payload) and time (op 2:
//! each logged step's, before its messages; a client that connects or subscribes later gets the
//! last one first).
//! It accepts `subscribe` and `unsubscribe`. Anything else (an unknown op, malformed JSON, a
//! subscription to a channel that does not exist or with an id in use, an unsubscription of an
//! unknown id, a binary frame, the other ops of the protocol, which this server does not
//! advertise) is a protocol error: it gets a `status` message of level error naming it, and
//! is counted. A client that makes [`MAX_ERRORS_PER_CLIENT`] errors is closed (code 1008).
//! Frames over [`MAX_CLIENT_MESSAGE_BYTES`] close the connection too (counted).

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use futures_util::{SinkExt, StreamExt};
use serde::Serialize;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_tungstenite::tungstenite::handshake::server::{ErrorResponse, Request, Response};
use tokio_tungstenite::tungstenite::http::{HeaderValue, StatusCode};
use tokio_tungstenite::tungstenite::protocol::frame::coding::CloseCode;
use tokio_tungstenite::tungstenite::protocol::{CloseFrame, WebSocketConfig};
use tokio_tungstenite::tungstenite::{Bytes, Message, Utf8Bytes};

use crate::lock;

/// The subprotocol of the Foxglove WebSocket protocol.
pub const SUBPROTOCOL: &str = "foxglove.websocket.v1";

/// The default address of `--foxglove`.
pub const DEFAULT_ADDR: &str = "127.0.0.1:8765";

/// Messages queued for one client before new ones are dropped (and counted).
pub const CLIENT_QUEUE: usize = 8192;

/// Protocol errors after which a client is closed (code 1008, policy violation).
pub const MAX_ERRORS_PER_CLIENT: u64 = 100;

/// The largest frame or message a client may send, bytes; larger ones close the connection.
pub const MAX_CLIENT_MESSAGE_BYTES: usize = 64 * 1024;

/// A channel the server advertises.
#[derive(Clone, Debug)]
pub struct LiveChannel {
    /// Topic, e.g. `/copters/state`.
    pub topic: String,
    /// Message encoding: `json`, `protobuf`, …
    pub encoding: String,
    /// Schema name, e.g. `foxglove.SceneUpdate`.
    pub schema_name: String,
    /// Schema encoding: `jsonschema`, `protobuf`, … (empty: none).
    pub schema_encoding: String,
    /// The schema, as the protocol carries it (text; base64 for binary schemas).
    pub schema: String,
    /// Keep the last message and send it to each new subscriber (static scenes).
    pub latched: bool,
}

impl LiveChannel {
    /// A channel with a schema as a file stores it: text schemas (`jsonschema`, `ros2msg`, …)
    /// as they are, binary ones (`protobuf`, `flatbuffer`) in base64, as the protocol wants.
    pub fn from_schema_bytes(
        topic: &str,
        encoding: &str,
        schema_name: &str,
        schema_encoding: &str,
        schema: &[u8],
    ) -> Self {
        let schema = match schema_encoding {
            "protobuf" | "flatbuffer" => base64(schema),
            _ => String::from_utf8_lossy(schema).into_owned(),
        };
        Self {
            topic: topic.to_owned(),
            encoding: encoding.to_owned(),
            schema_name: schema_name.to_owned(),
            schema_encoding: schema_encoding.to_owned(),
            schema,
            latched: false,
        }
    }
}

/// Standard base64 with padding (RFC 4648).
fn base64(data: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(data.len().div_ceil(3) * 4);
    for chunk in data.chunks(3) {
        let b = [chunk[0], chunk.get(1).copied().unwrap_or(0), chunk.get(2).copied().unwrap_or(0)];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(ALPHABET[(n >> (18 - 6 * k)) as usize & 63] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// What the server did, for the run's summary.
#[derive(Clone, Debug, Default, Serialize)]
pub struct LiveStats {
    /// The address it listened on.
    pub address: String,
    /// Clients that completed the handshake.
    pub clients: u64,
    /// Connections refused at the handshake (no `foxglove.websocket.v1` subprotocol, not a
    /// WebSocket request).
    pub handshakes_refused: u64,
    /// Subscriptions made.
    pub subscriptions: u64,
    /// Messages queued for clients.
    pub messages_sent: u64,
    /// Messages dropped because a client's queue was full (a slow or stalled client).
    pub messages_dropped: u64,
    /// Protocol errors by clients (each answered with an error status).
    pub protocol_errors: u64,
    /// Clients closed for too many protocol errors or an oversized frame.
    pub clients_closed: u64,
    /// Control steps not encoded for the view because its encoder was behind (a run without
    /// a log file; with one, the file's writer sets the pace).
    pub steps_skipped: u64,
}

#[derive(Debug, Default)]
struct Counters {
    clients: AtomicU64,
    handshakes_refused: AtomicU64,
    subscriptions: AtomicU64,
    messages_sent: AtomicU64,
    messages_dropped: AtomicU64,
    protocol_errors: AtomicU64,
    clients_closed: AtomicU64,
    steps_skipped: AtomicU64,
}

#[derive(Debug)]
struct ChannelEntry {
    def: LiveChannel,
    /// Subscriptions to it, over all clients.
    subscribers: AtomicU32,
    /// The last message of a latched channel: (timestamp, payload).
    last: Mutex<Option<(u64, Vec<u8>)>>,
}

#[derive(Debug)]
struct ClientEntry {
    id: u64,
    tx: mpsc::Sender<Message>,
    /// (subscription id, channel id).
    subs: Vec<(u32, u32)>,
}

#[derive(Debug)]
struct Shared {
    name: String,
    session_id: String,
    /// Channel id `k` is `channels[k - 1]`.
    channels: Mutex<Vec<Arc<ChannelEntry>>>,
    clients: Mutex<Vec<ClientEntry>>,
    /// Subscriptions over all clients and channels.
    active: AtomicU32,
    /// The last time told to the clients (op 2), ns; 0 before the first.
    clock_ns: AtomicU64,
    next_client: AtomicU64,
    counters: Counters,
}

impl Shared {
    /// A server with no channels and no clients yet.
    fn new(name: &str, session_id: String) -> Self {
        Self {
            name: name.to_owned(),
            session_id,
            channels: Mutex::new(Vec::new()),
            clients: Mutex::new(Vec::new()),
            active: AtomicU32::new(0),
            clock_ns: AtomicU64::new(0),
            next_client: AtomicU64::new(1),
            counters: Counters::default(),
        }
    }
}

/// A running live-view server. Dropping it stops accepting clients and closes them.
#[derive(Debug)]
pub struct LiveServer {
    shared: Arc<Shared>,
    addr: SocketAddr,
    accept: tokio::task::JoinHandle<()>,
}

impl LiveServer {
    /// Listens on `addr` (port 0: a free port) with the tasks on `rt`.
    pub fn start(addr: SocketAddr, name: &str, rt: &tokio::runtime::Handle) -> std::io::Result<Self> {
        let listener = {
            let _guard = rt.enter();
            let std_listener = std::net::TcpListener::bind(addr)?;
            std_listener.set_nonblocking(true)?;
            TcpListener::from_std(std_listener)?
        };
        let addr = listener.local_addr()?;
        let shared = Arc::new(Shared::new(name, format!("{}", crate::log::now_unix_ns())));
        let accept = rt.spawn(accept_loop(listener, Arc::clone(&shared)));
        Ok(Self { shared, addr, accept })
    }

    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Adds a channel and advertises it to the clients connected; returns its id.
    pub fn add_channel(&self, def: LiveChannel) -> u32 {
        let entry = Arc::new(ChannelEntry { def, subscribers: AtomicU32::new(0), last: Mutex::new(None) });
        let id = {
            let mut channels = lock(&self.shared.channels);
            channels.push(Arc::clone(&entry));
            channels.len() as u32
        };
        let text = advertise_json(&[(id, &entry.def)]);
        for c in lock(&self.shared.clients).iter() {
            queue(&self.shared, c, Message::Text(text.clone().into()));
        }
        id
    }

    /// Whether any client subscribes to anything: when not, a publisher may skip encoding.
    #[inline]
    pub fn active(&self) -> bool {
        self.shared.active.load(Ordering::Relaxed) > 0
    }

    /// Sends a message of channel `id` with timestamp `time_ns` to its subscribers, without
    /// waiting: a client whose queue is full loses it (counted).
    pub fn publish(&self, id: u32, time_ns: u64, payload: &[u8]) {
        publish(&self.shared, id, time_ns, payload);
    }

    /// Tells the clients the current time (op 2), e.g. each control step's log time.
    /// A client that connects or subscribes later is told the last one before anything else:
    /// a client of the `time` capability stamps what it receives with the server's time
    /// (Foxglove Studio would otherwise take 0 for the messages before the first).
    pub fn broadcast_time(&self, time_ns: u64) {
        self.shared.clock_ns.store(time_ns, Ordering::Relaxed);
        let clients = lock(&self.shared.clients);
        if clients.is_empty() {
            return;
        }
        let frame = time_frame(time_ns);
        for c in clients.iter() {
            queue(&self.shared, c, Message::Binary(frame.clone()));
        }
    }

    /// The counters so far.
    pub fn stats(&self) -> LiveStats {
        let c = &self.shared.counters;
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        LiveStats {
            address: self.addr.to_string(),
            clients: l(&c.clients),
            handshakes_refused: l(&c.handshakes_refused),
            subscriptions: l(&c.subscriptions),
            messages_sent: l(&c.messages_sent),
            messages_dropped: l(&c.messages_dropped),
            protocol_errors: l(&c.protocol_errors),
            clients_closed: l(&c.clients_closed),
            steps_skipped: l(&c.steps_skipped),
        }
    }

    /// Counts a control step its publisher skipped because it was behind.
    pub fn count_skipped_step(&self) {
        self.shared.counters.steps_skipped.fetch_add(1, Ordering::Relaxed);
    }
}

impl Drop for LiveServer {
    fn drop(&mut self) {
        self.accept.abort();
        // Closing the queues ends each client's task, which closes its socket.
        lock(&self.shared.clients).clear();
    }
}

/// [`LiveServer::publish`].
fn publish(shared: &Shared, id: u32, time_ns: u64, payload: &[u8]) {
    let Some(entry) = lock(&shared.channels).get((id as usize).wrapping_sub(1)).cloned() else {
        return;
    };
    if entry.def.latched {
        *lock(&entry.last) = Some((time_ns, payload.to_vec()));
    }
    if entry.subscribers.load(Ordering::Relaxed) == 0 {
        return;
    }
    for c in lock(&shared.clients).iter() {
        for &(sub, ch) in &c.subs {
            if ch == id {
                queue(shared, c, Message::Binary(message_data(sub, time_ns, payload)));
            }
        }
    }
}

fn queue(shared: &Shared, c: &ClientEntry, m: Message) {
    match c.tx.try_send(m) {
        Ok(()) => shared.counters.messages_sent.fetch_add(1, Ordering::Relaxed),
        Err(mpsc::error::TrySendError::Full(_)) => shared.counters.messages_dropped.fetch_add(1, Ordering::Relaxed),
        // The client is going away; its task removes it.
        Err(mpsc::error::TrySendError::Closed(_)) => 0,
    };
}

/// Binary time: op 2, timestamp (u64 LE).
fn time_frame(time_ns: u64) -> Bytes {
    let mut frame = Vec::with_capacity(9);
    frame.push(2u8);
    frame.extend_from_slice(&time_ns.to_le_bytes());
    Bytes::from(frame)
}

/// Binary message data: op 1, subscription id (u32 LE), timestamp (u64 LE), payload.
fn message_data(sub: u32, time_ns: u64, payload: &[u8]) -> Bytes {
    let mut frame = Vec::with_capacity(13 + payload.len());
    frame.push(1u8);
    frame.extend_from_slice(&sub.to_le_bytes());
    frame.extend_from_slice(&time_ns.to_le_bytes());
    frame.extend_from_slice(payload);
    Bytes::from(frame)
}

fn advertise_json(channels: &[(u32, &LiveChannel)]) -> String {
    let list: Vec<serde_json::Value> = channels
        .iter()
        .map(|(id, c)| {
            serde_json::json!({
                "id": id,
                "topic": c.topic,
                "encoding": c.encoding,
                "schemaName": c.schema_name,
                "schema": c.schema,
                "schemaEncoding": c.schema_encoding,
            })
        })
        .collect();
    serde_json::json!({ "op": "advertise", "channels": list }).to_string()
}

fn status_json(level: u8, message: &str) -> String {
    serde_json::json!({ "op": "status", "level": level, "message": message }).to_string()
}

async fn accept_loop(listener: TcpListener, shared: Arc<Shared>) {
    loop {
        match listener.accept().await {
            Ok((stream, peer)) => {
                let _ = stream.set_nodelay(true);
                tokio::spawn(serve_client(stream, peer, Arc::clone(&shared)));
            }
            Err(e) => {
                // Out of file descriptors and the like: wait a little rather than spin.
                tracing::warn!("live view: accept failed: {e}");
                tokio::time::sleep(std::time::Duration::from_millis(50)).await;
            }
        }
    }
}

/// Accepts the handshake only with the protocol's subprotocol, and answers with it.
#[allow(clippy::result_large_err)] // the signature tungstenite's callback requires
fn choose_subprotocol(req: &Request, mut resp: Response) -> Result<Response, ErrorResponse> {
    let offered = req
        .headers()
        .get_all("sec-websocket-protocol")
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|p| p.trim() == SUBPROTOCOL);
    if !offered {
        let mut err = ErrorResponse::new(Some(format!("this server speaks the {SUBPROTOCOL} subprotocol only\n")));
        *err.status_mut() = StatusCode::BAD_REQUEST;
        return Err(err);
    }
    resp.headers_mut().insert("sec-websocket-protocol", HeaderValue::from_static(SUBPROTOCOL));
    Ok(resp)
}

async fn serve_client(stream: TcpStream, peer: SocketAddr, shared: Arc<Shared>) {
    let config = WebSocketConfig::default()
        .max_message_size(Some(MAX_CLIENT_MESSAGE_BYTES))
        .max_frame_size(Some(MAX_CLIENT_MESSAGE_BYTES));
    let ws = match tokio_tungstenite::accept_hdr_async_with_config(stream, choose_subprotocol, Some(config)).await {
        Ok(ws) => ws,
        Err(e) => {
            shared.counters.handshakes_refused.fetch_add(1, Ordering::Relaxed);
            tracing::debug!("live view: handshake with {peer} refused: {e}");
            return;
        }
    };
    shared.counters.clients.fetch_add(1, Ordering::Relaxed);
    let (mut sink, mut incoming) = ws.split();
    let (tx, mut rx) = mpsc::channel::<Message>(CLIENT_QUEUE);
    let id = shared.next_client.fetch_add(1, Ordering::Relaxed);
    // The hello and the channels known now, queued before the client is listed, so nothing
    // published for it can come first.
    let info = serde_json::json!({
        "op": "serverInfo",
        "name": shared.name,
        "capabilities": ["time"],
        "supportedEncodings": [],
        "metadata": { "version": env!("CARGO_PKG_VERSION") },
        "sessionId": shared.session_id,
    })
    .to_string();
    // The queue is new and empty: these two cannot find it full.
    let _ = tx.try_send(Message::Text(info.into()));
    {
        // Holding the channel list while listing the client: a channel added meanwhile is
        // either in this advertisement or advertised to the listed client.
        let channels = lock(&shared.channels);
        let defs: Vec<(u32, &LiveChannel)> = channels.iter().enumerate().map(|(k, c)| (k as u32 + 1, &c.def)).collect();
        let _ = tx.try_send(Message::Text(advertise_json(&defs).into()));
        // The time now, if there is one yet (the queue has room for a third).
        let clock = shared.clock_ns.load(Ordering::Relaxed);
        if clock > 0 {
            let _ = tx.try_send(Message::Binary(time_frame(clock)));
        }
        lock(&shared.clients).push(ClientEntry { id, tx: tx.clone(), subs: Vec::new() });
    }
    drop(tx);
    let mut errors = 0u64;
    let close = loop {
        tokio::select! {
            out = rx.recv() => match out {
                Some(m) => {
                    if sink.send(m).await.is_err() {
                        break None;
                    }
                }
                None => break None, // the server stopped
            },
            msg = incoming.next() => match msg {
                Some(Ok(Message::Text(text))) => {
                    if let Err(e) = handle_text(&shared, id, &text) {
                        errors += 1;
                        shared.counters.protocol_errors.fetch_add(1, Ordering::Relaxed);
                        if !reply(&shared, id, status_json(2, &e)) {
                            break None;
                        }
                    }
                }
                Some(Ok(Message::Binary(b))) => {
                    errors += 1;
                    shared.counters.protocol_errors.fetch_add(1, Ordering::Relaxed);
                    if !reply(&shared, id, status_json(2, &binary_refused(&b))) {
                        break None;
                    }
                }
                Some(Ok(Message::Close(_))) | None => break None,
                Some(Ok(_)) => {} // ping and pong: tungstenite answers pings itself
                Some(Err(e)) => {
                    // Oversized frames, bad framing, a reset connection.
                    shared.counters.protocol_errors.fetch_add(1, Ordering::Relaxed);
                    shared.counters.clients_closed.fetch_add(1, Ordering::Relaxed);
                    tracing::debug!("live view: client {peer}: {e}");
                    break Some(CloseFrame { code: CloseCode::Protocol, reason: Utf8Bytes::from(format!("{e}")) });
                }
            },
        }
        if errors >= MAX_ERRORS_PER_CLIENT {
            shared.counters.clients_closed.fetch_add(1, Ordering::Relaxed);
            break Some(CloseFrame {
                code: CloseCode::Policy,
                reason: Utf8Bytes::from(format!("{MAX_ERRORS_PER_CLIENT} protocol errors")),
            });
        }
    };
    remove_client(&shared, id);
    if let Some(frame) = close {
        let _ = sink.send(Message::Close(Some(frame))).await;
        // Read on (and discard) until the client answers the close: closing the socket with
        // its frames unread would reset the connection, and the client could lose the close
        // frame and its reason. Bounded by a timeout.
        let drain = async {
            while let Some(Ok(m)) = incoming.next().await
                && !m.is_close()
            {}
        };
        let _ = tokio::time::timeout(std::time::Duration::from_secs(2), drain).await;
    }
    let _ = sink.close().await;
}

/// Queues a reply for client `id`; false if the client is gone.
fn reply(shared: &Shared, id: u64, text: String) -> bool {
    let clients = lock(&shared.clients);
    match clients.iter().find(|c| c.id == id) {
        Some(c) => {
            queue(shared, c, Message::Text(text.into()));
            true
        }
        None => false,
    }
}

fn remove_client(shared: &Shared, id: u64) {
    let mut clients = lock(&shared.clients);
    if let Some(k) = clients.iter().position(|c| c.id == id) {
        let c = clients.swap_remove(k);
        let channels = lock(&shared.channels);
        for (_, ch) in c.subs {
            if let Some(entry) = channels.get(ch as usize - 1) {
                entry.subscribers.fetch_sub(1, Ordering::Relaxed);
            }
            shared.active.fetch_sub(1, Ordering::Relaxed);
        }
    }
}

/// Why a client's binary message is refused (the server advertises no client channels).
fn binary_refused(b: &[u8]) -> String {
    let op = b.first().map_or("empty".to_owned(), |op| format!("op {op:#04x}"));
    format!("binary message ({op}, {} bytes) not accepted: this server advertises no client channels", b.len())
}

/// A client's text message: `subscribe` and `unsubscribe`; anything else is an error, whose
/// text goes back in a status message.
fn handle_text(shared: &Shared, id: u64, text: &str) -> Result<(), String> {
    let v: serde_json::Value = serde_json::from_str(text).map_err(|e| format!("not JSON: {e}"))?;
    let op = v.get("op").and_then(|o| o.as_str()).ok_or("message without a string \"op\"")?;
    match op {
        "subscribe" => {
            let subs =
                v.get("subscriptions").and_then(|s| s.as_array()).ok_or("subscribe: no \"subscriptions\" array")?;
            let mut latched = Vec::new();
            let mut errors = Vec::new();
            {
                let channels = lock(&shared.channels);
                let mut clients = lock(&shared.clients);
                let Some(client) = clients.iter_mut().find(|c| c.id == id) else { return Ok(()) };
                for s in subs {
                    let (Some(sub), Some(ch)) = (
                        s.get("id").and_then(|x| x.as_u64()).and_then(|x| u32::try_from(x).ok()),
                        s.get("channelId").and_then(|x| x.as_u64()).and_then(|x| u32::try_from(x).ok()),
                    ) else {
                        errors.push(format!("subscribe: {s} needs an \"id\" and a \"channelId\" (u32)"));
                        continue;
                    };
                    let Some(entry) = channels.get((ch as usize).wrapping_sub(1)) else {
                        errors.push(format!("subscribe: channel {ch} does not exist"));
                        continue;
                    };
                    if client.subs.iter().any(|&(s, _)| s == sub) {
                        errors.push(format!("subscribe: subscription id {sub} is already in use"));
                        continue;
                    }
                    client.subs.push((sub, ch));
                    entry.subscribers.fetch_add(1, Ordering::Relaxed);
                    shared.active.fetch_add(1, Ordering::Relaxed);
                    shared.counters.subscriptions.fetch_add(1, Ordering::Relaxed);
                    if let Some((t, data)) = lock(&entry.last).as_ref() {
                        latched.push((*t, message_data(sub, *t, data)));
                    }
                }
                // A latched message goes out at once, after the time (the run's clock, or before
                // its first step the message's own).
                if let Some(t) = latched.iter().map(|(t, _)| *t).max() {
                    let clock = shared.clock_ns.load(Ordering::Relaxed);
                    queue(shared, client, Message::Binary(time_frame(if clock > 0 { clock } else { t })));
                }
                for (_, m) in latched {
                    queue(shared, client, Message::Binary(m));
                }
            }
            if errors.is_empty() { Ok(()) } else { Err(errors.join("; ")) }
        }
        "unsubscribe" => {
            let ids = v
                .get("subscriptionIds")
                .and_then(|s| s.as_array())
                .ok_or("unsubscribe: no \"subscriptionIds\" array")?;
            let channels = lock(&shared.channels);
            let mut clients = lock(&shared.clients);
            let Some(client) = clients.iter_mut().find(|c| c.id == id) else { return Ok(()) };
            let mut unknown = Vec::new();
            for sub in ids {
                let found = sub.as_u64().and_then(|s| client.subs.iter().position(|&(x, _)| u64::from(x) == s));
                match found {
                    Some(k) => {
                        let (_, ch) = client.subs.swap_remove(k);
                        if let Some(entry) = channels.get(ch as usize - 1) {
                            entry.subscribers.fetch_sub(1, Ordering::Relaxed);
                        }
                        shared.active.fetch_sub(1, Ordering::Relaxed);
                    }
                    None => unknown.push(sub.to_string()),
                }
            }
            if unknown.is_empty() {
                Ok(())
            } else {
                Err(format!("unsubscribe: unknown subscription ids {}", unknown.join(", ")))
            }
        }
        "advertise"
        | "unadvertise"
        | "getParameters"
        | "setParameters"
        | "subscribeParameterUpdates"
        | "unsubscribeParameterUpdates"
        | "subscribeConnectionGraph"
        | "unsubscribeConnectionGraph"
        | "fetchAsset"
        | "playbackControlRequest" => {
            Err(format!("op \"{op}\" is not supported by this server (see serverInfo capabilities)"))
        }
        other => Err(format!("unknown op \"{}\"", other.chars().take(64).collect::<String>())),
    }
}

/// The fuzz target of client messages (`crates/fuzz`, target `foxglove_client`): the
/// server's request handling without sockets.
#[doc(hidden)]
pub mod fuzzing {
    use super::*;

    /// Checks the subscription counts against the clients' subscription lists.
    fn check_counts(shared: &Shared) {
        let channels = lock(&shared.channels);
        let clients = lock(&shared.clients);
        let total: usize = clients.iter().map(|c| c.subs.len()).sum();
        assert_eq!(shared.active.load(Ordering::Relaxed) as usize, total, "active subscriptions");
        for (k, ch) in channels.iter().enumerate() {
            let n = clients.iter().flat_map(|c| &c.subs).filter(|&&(_, c)| c as usize == k + 1).count();
            assert_eq!(ch.subscribers.load(Ordering::Relaxed) as usize, n, "subscribers of channel {}", k + 1);
        }
        for c in clients.iter() {
            let mut ids: Vec<u32> = c.subs.iter().map(|&(s, _)| s).collect();
            ids.sort_unstable();
            ids.dedup();
            assert_eq!(ids.len(), c.subs.len(), "subscription ids of client {} are unique", c.id);
        }
    }

    /// Two clients on a server of three channels (one latched): `frames` come from client 1,
    /// text (`Ok`) or binary (`Err`), each answered as the server would; a message is
    /// published on every channel after each. The subscription counts must match the
    /// clients' lists throughout and fall to zero when the clients leave, and every text
    /// queued for a client must be JSON with an `op`.
    pub fn client_session<'a>(frames: impl IntoIterator<Item = Result<&'a str, &'a [u8]>>) {
        let shared = Shared::new("fuzz", "0".into());
        let defs = [("/a", false), ("/b", false), ("/arena", true)];
        for (topic, latched) in defs {
            let mut def = LiveChannel::from_schema_bytes(topic, "json", "s", "jsonschema", b"{}");
            def.latched = latched;
            let entry = Arc::new(ChannelEntry { def, subscribers: AtomicU32::new(0), last: Mutex::new(None) });
            lock(&shared.channels).push(entry);
        }
        *lock(&lock(&shared.channels)[2].last) = Some((5, b"{}".to_vec()));
        let (tx1, mut rx1) = mpsc::channel(CLIENT_QUEUE);
        let (tx2, mut rx2) = mpsc::channel(CLIENT_QUEUE);
        lock(&shared.clients).push(ClientEntry { id: 1, tx: tx1, subs: Vec::new() });
        lock(&shared.clients).push(ClientEntry { id: 2, tx: tx2, subs: Vec::new() });
        let _ = handle_text(&shared, 2, r#"{"op":"subscribe","subscriptions":[{"id":1,"channelId":1}]}"#);
        for (k, frame) in frames.into_iter().enumerate().take(1000) {
            let error = match frame {
                Ok(text) => handle_text(&shared, 1, text).err(),
                Err(bytes) => Some(binary_refused(bytes)),
            };
            if let Some(e) = error {
                assert!(reply(&shared, 1, status_json(2, &e)), "client 1 is listed");
            }
            check_counts(&shared);
            for ch in 1..=3 {
                publish(&shared, ch, k as u64, b"{}");
            }
        }
        for rx in [&mut rx1, &mut rx2] {
            while let Ok(m) = rx.try_recv() {
                if let Message::Text(t) = m {
                    let v: serde_json::Value = serde_json::from_str(&t).expect("a text sent is JSON");
                    assert!(v.get("op").and_then(|o| o.as_str()).is_some(), "a text sent has an op: {t}");
                }
            }
        }
        remove_client(&shared, 1);
        remove_client(&shared, 2);
        check_counts(&shared);
        assert_eq!(shared.active.load(Ordering::Relaxed), 0, "no subscription outlives its client");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_rfc4648_vectors() {
        let cases =
            [("", ""), ("f", "Zg=="), ("fo", "Zm8="), ("foo", "Zm9v"), ("foob", "Zm9vYg=="), ("fooba", "Zm9vYmE=")];
        for (plain, coded) in cases {
            assert_eq!(base64(plain.as_bytes()), coded, "{plain:?}");
        }
        assert_eq!(base64(&[0xfb, 0xff]), "+/8=");
    }
}
