//! Sharding over Zenoh ([`sim_core::shard`] does the stepping): each shard sends each
//! neighbour its ghosts once per control step, and waits for every neighbour's before it steps
//! on. That exchange *is* the lockstep barrier: a shard at tick T has had every neighbour's
//! state at T. Liveliness tokens tell a shard that a neighbour is gone: it stops with an
//! error instead of waiting for ever ([`OnLost::Stop`]), or holds at the barrier until the
//! neighbour is back ([`OnLost::Hold`], bounded by the barrier timeout). A shard waiting longer
//! than [`RESEND`] sends its batch again, so that a batch lost while the link was down (a
//! router restarting, a network partition) does not hold the cluster for ever; batches are
//! idempotent, keyed by (tick, sender).
//!
//! Keys, under the run's prefix:
//! - `<prefix>/shard/<from>/to/<to>`: a [`GhostBatch`] (postcard), reliable, express, blocking
//!   under congestion (a lost batch would be a lost barrier); its attachment, the sender's wall
//!   clock when it put it (ns since the Unix epoch, 8 bytes little-endian), for
//!   [`LinkStats::transit_s`];
//! - `<prefix>/shard/alive/<k>`: liveliness token of shard `k` (declared after its subscriber,
//!   so a shard that sees it may publish to it);
//! - `<prefix>/shard/<k>/done`: shard `k` took its neighbours' batches for its last step (the
//!   tick, 8 bytes little-endian). A shard leaves only when each neighbour has said so
//!   ([`ShardLink::finish`]): its own last batch may still be in its session's shared memory.
//!
//! No home-made transport and no discovery: the sessions connect to a Zenoh router (or to each
//! other) as configured, multicast scouting off by default.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, mpsc};
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use sim_core::State;
use sim_core::shard::{Ghost, GhostRef, ShardError, ShardId};
use zenoh::Wait;
use zenoh::qos::CongestionControl;
use zenoh::sample::SampleKind;

use crate::log::now_unix_ns;

/// One shard's ghosts for one neighbour at one tick.
#[derive(Debug, Serialize, Deserialize)]
pub struct GhostBatch {
    /// The tick the ghosts' state is at (before stepping it).
    pub tick: u64,
    /// The sending shard.
    pub from: ShardId,
    /// Its copters near the receiver's region.
    pub ghosts: Vec<Ghost>,
}

/// A [`GhostBatch`] as its sender serialises it, the copters' states borrowed: the same bytes.
#[derive(Serialize)]
#[serde(rename = "GhostBatch")]
struct GhostBatchRef<'a> {
    tick: u64,
    from: ShardId,
    ghosts: &'a [GhostRef<'a>],
}

/// Why a shard cannot go on.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// Zenoh failed.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// A neighbour's batch could not be read.
    #[error("shard {me}: a batch on {key} is not a ghost batch: {what}")]
    Decode {
        /// This shard.
        me: ShardId,
        /// Where it came from.
        key: String,
        /// What was wrong.
        what: String,
    },
    /// A neighbour ended its run before this shard's tick: the shards were not given the same
    /// duration.
    #[error(
        "shard {shard} ended its run at tick {at}, and shard {me} is at tick {tick}: the shards were given different durations"
    )]
    Ended {
        /// This shard.
        me: ShardId,
        /// The neighbour.
        shard: ShardId,
        /// Its last tick.
        at: u64,
        /// This shard's tick.
        tick: u64,
    },
    /// A neighbour's liveliness token went away.
    #[error("shard {shard} left the cluster at tick {tick} (its liveliness token is gone)")]
    Left {
        /// The neighbour.
        shard: ShardId,
        /// This shard's tick.
        tick: u64,
    },
    /// A stop request or a signal came while this shard waited for its neighbours (before its
    /// first step, at a step's barrier, or for their word after its last).
    #[error("shard {me}: stopped while waiting for its neighbours at tick {tick}")]
    Stopped {
        /// This shard.
        me: ShardId,
        /// This shard's tick.
        tick: u64,
    },
    /// Neighbours did not come, or did not send, in time.
    #[error("shard {me}: no word from shard(s) {missing:?} for {waited_s:.1} s at tick {tick}")]
    Timeout {
        /// This shard.
        me: ShardId,
        /// Who is missing.
        missing: Vec<ShardId>,
        /// This shard's tick.
        tick: u64,
        /// How long it waited, s.
        waited_s: f64,
    },
    /// The ghosts broke an invariant of sharding.
    #[error(transparent)]
    Shard(#[from] ShardError),
}

/// How long a neighbour that left may still deliver its last batch (or its word that it is done).
pub const LEFT_GRACE: Duration = Duration::from_secs(2);

/// A shard still waiting for a neighbour after this long sends its batch again.
pub const RESEND: Duration = Duration::from_secs(1);

/// What a shard does when a neighbour's liveliness token goes away.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum OnLost {
    /// Stop with [`LinkError::Left`] (after a grace for its last batch).
    #[default]
    Stop,
    /// Hold at the barrier until it is back (its token and its batch), up to the barrier
    /// timeout: for a link that drops and returns. A shard process that died cannot return
    /// (it is restarted from a checkpoint, with all the others: [`crate::engine::checkpoint`]), and the
    /// hold ends at the timeout.
    Hold,
}

/// How often a waiting shard looks at neighbours that left.
const POLL: Duration = Duration::from_millis(50);

fn zerr(e: impl std::fmt::Display) -> LinkError {
    LinkError::Zenoh(e.to_string())
}

enum Incoming {
    /// A batch as it arrived.
    Batch(Arrived),
    Bad(String, String),
    Joined(ShardId),
    Left(ShardId),
    /// A neighbour took every batch of its last step, that of this tick.
    Done(ShardId, u64),
}

/// A neighbour's batch, decoded on Zenoh's thread.
struct Arrived {
    batch: GhostBatch,
    /// Its size, bytes.
    bytes: usize,
    /// The time it took to decode, s.
    decode_s: f64,
    /// Whether its bytes came in shared memory (a neighbour on this machine) rather than
    /// over the socket.
    in_shm: bool,
    /// From its sender's put to its arrival here, s, by the two wall clocks (`None`: no
    /// timestamp attached).
    transit_s: Option<f64>,
}

/// What the barrier cost, for the run's summary.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct LinkStats {
    /// Exchanges done (one per step).
    pub exchanges: u64,
    /// Time spent waiting for neighbours after sending, s (total and worst).
    pub wait_s: f64,
    /// The longest single wait, s.
    pub wait_max_s: f64,
    /// Time encoding and sending, s.
    pub send_s: f64,
    /// Time decoding the neighbours' batches, s (on Zenoh's threads, as they arrive).
    #[serde(default)]
    pub decode_s: f64,
    /// Time taking the neighbours' ghosts into the state, s (after the wait).
    #[serde(default)]
    pub take_s: f64,
    /// The batches' time in transit, from their sender's put to their arrival here, s (total
    /// over `batches_timed`; by the two wall clocks: exact on one machine, off by the clocks'
    /// offset across machines, a receiver's clock behind counting 0). It runs whether or not
    /// this shard waits: a batch that arrives while this shard still steps costs nothing. A
    /// long wait with short transits is a neighbour still stepping; a wait about as long as
    /// the transits, the link.
    #[serde(default)]
    pub transit_s: f64,
    /// The longest transit of a batch, s.
    #[serde(default)]
    pub transit_max_s: f64,
    /// The batches that carried their put time (`transit_s` is over them).
    #[serde(default)]
    pub batches_timed: u64,
    /// Time after the last step waiting for the neighbours' word that they are done
    /// ([`ShardLink::finish`]), s.
    #[serde(default)]
    pub finish_s: f64,
    /// Ghosts sent and received.
    pub ghosts_sent: u64,
    /// Ghosts received.
    pub ghosts_received: u64,
    /// Payload bytes sent and received.
    pub bytes_sent: u64,
    /// Payload bytes received.
    pub bytes_received: u64,
    /// Batches received (stale ones included).
    #[serde(default)]
    pub batches_received: u64,
    /// Of them, those whose bytes came in shared memory, not over the socket: Zenoh puts a
    /// message of 3 kB or more there when both ends of a link are on one machine with shared
    /// memory enabled (the default; `transport/shared_memory` in a Zenoh configuration file).
    #[serde(default)]
    pub batches_in_shm: u64,
    /// Batches sent again while waiting (see [`RESEND`]).
    #[serde(default)]
    pub resent: u64,
    /// Batches that came for a step already taken (a batch sent again that crossed the first,
    /// or a neighbour's defect): dropped, counted.
    #[serde(default)]
    pub stale_batches: u64,
    /// Times a neighbour left and this shard held for it ([`OnLost::Hold`]).
    #[serde(default)]
    pub holds: u64,
    /// Time spent holding for neighbours that had left, s.
    #[serde(default)]
    pub held_s: f64,
}

/// The subscriber to the batches sent to shard `me`.
fn declare_batches(
    session: &zenoh::Session,
    prefix: &str,
    me: ShardId,
    tx: mpsc::Sender<Incoming>,
) -> Result<zenoh::pubsub::Subscriber<()>, LinkError> {
    session
        .declare_subscriber(format!("{prefix}/shard/*/to/{me}"))
        .callback(move |sample| {
            let key = sample.key_expr().to_string();
            let (start, arrived_ns) = (Instant::now(), now_unix_ns());
            let sent_ns = sample.attachment().and_then(|a| <[u8; 8]>::try_from(&a.to_bytes()[..]).ok());
            let transit_s = sent_ns.map(|t| arrived_ns.saturating_sub(u64::from_le_bytes(t)) as f64 * 1e-9);
            let in_shm = sample.payload().as_shm().is_some();
            let bytes = sample.payload().to_bytes();
            let msg = match postcard::from_bytes::<GhostBatch>(&bytes) {
                Ok(batch) => {
                    let decode_s = start.elapsed().as_secs_f64();
                    Incoming::Batch(Arrived { batch, bytes: bytes.len(), decode_s, in_shm, transit_s })
                }
                Err(e) => Incoming::Bad(key, e.to_string()),
            };
            let _ = tx.send(msg);
        })
        .wait()
        .map_err(zerr)
}

/// Puts a batch, with the time it was put attached.
fn put(publisher: &zenoh::pubsub::Publisher<'static>, bytes: &[u8]) -> Result<(), LinkError> {
    publisher.put(bytes).attachment(now_unix_ns().to_le_bytes().to_vec()).wait().map_err(zerr)
}

/// The subscriber to the neighbours' word that they are done ([`ShardLink::finish`]).
fn declare_done(
    session: &zenoh::Session,
    prefix: &str,
    tx: mpsc::Sender<Incoming>,
) -> Result<zenoh::pubsub::Subscriber<()>, LinkError> {
    session
        .declare_subscriber(format!("{prefix}/shard/*/done"))
        .callback(move |sample| {
            let from = sample.key_expr().as_str().rsplit('/').nth(1).and_then(|k| k.parse().ok());
            let tick = <[u8; 8]>::try_from(&sample.payload().to_bytes()[..]).ok().map(u64::from_le_bytes);
            if let (Some(k), Some(tick)) = (from, tick) {
                let _ = tx.send(Incoming::Done(k, tick));
            }
        })
        .wait()
        .map_err(zerr)
}

/// One publisher per neighbour, in `neighbours` order.
fn declare_publishers(
    session: &zenoh::Session,
    prefix: &str,
    me: ShardId,
    neighbours: &[ShardId],
) -> Result<Vec<zenoh::pubsub::Publisher<'static>>, LinkError> {
    neighbours
        .iter()
        .map(|t| {
            session
                .declare_publisher(format!("{prefix}/shard/{me}/to/{t}"))
                .congestion_control(CongestionControl::Block)
                .express(true)
                .wait()
                .map_err(zerr)
        })
        .collect()
}

impl std::fmt::Debug for ShardLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ShardLink").field("me", &self.me).field("neighbours", &self.neighbours).finish_non_exhaustive()
    }
}

/// A shard's link to its neighbours.
pub struct ShardLink {
    session: zenoh::Session,
    prefix: String,
    me: ShardId,
    neighbours: Vec<ShardId>,
    publishers: Vec<zenoh::pubsub::Publisher<'static>>,
    tx: mpsc::Sender<Incoming>,
    inbox: mpsc::Receiver<Incoming>,
    subscriber: zenoh::pubsub::Subscriber<()>,
    _alive: zenoh::liveliness::LivelinessToken,
    _watch: zenoh::pubsub::Subscriber<()>,
    _done: zenoh::pubsub::Subscriber<()>,
    /// Neighbours that took every batch of their last step, and that step's tick.
    done: Vec<(ShardId, u64)>,
    /// Batches that came early (a neighbour one step ahead), by (tick, from).
    early: BTreeMap<(u64, ShardId), GhostBatch>,
    /// The last step whose batches were taken: a batch for it or before is stale.
    taken_tick: Option<u64>,
    joined: Vec<ShardId>,
    /// Neighbours whose token went away, and when this shard learnt it.
    left: Vec<(ShardId, Instant)>,
    /// A neighbour that had left is back: declare the routes anew and send again.
    rejoined: bool,
    timeout: Duration,
    on_lost: OnLost,
    /// Set by a stop request or a signal: ends every wait for neighbours.
    stop: Option<Arc<AtomicBool>>,
    /// This step's batch for each neighbour, kept to send again.
    sent: Vec<Vec<u8>>,
    /// The previous step's batches. A neighbour may still wait for one: this shard took
    /// its batch for that step and moved on, while this shard's own was lost on the way (a
    /// router restart between the two). Neighbours are never more than one step apart.
    sent_before: Vec<Vec<u8>>,
    stats: LinkStats,
}

impl ShardLink {
    /// Opens a session with `config`, declares this shard's subscriber, then its liveliness
    /// token, and watches its neighbours'. `timeout` bounds every wait.
    pub fn open(
        config: zenoh::Config,
        prefix: &str,
        me: ShardId,
        neighbours: Vec<ShardId>,
        timeout: Duration,
    ) -> Result<Self, LinkError> {
        let session = zenoh::open(config).wait().map_err(zerr)?;
        Self::on(session, prefix, me, neighbours, timeout)
    }

    /// [`ShardLink::open`] on a session already open (the run's node's).
    pub fn on(
        session: zenoh::Session,
        prefix: &str,
        me: ShardId,
        neighbours: Vec<ShardId>,
        timeout: Duration,
    ) -> Result<Self, LinkError> {
        let (tx, inbox) = mpsc::channel();
        let subscriber = declare_batches(&session, prefix, me, tx.clone())?;
        let done = declare_done(&session, prefix, tx.clone())?;
        let alive = session.liveliness().declare_token(format!("{prefix}/shard/alive/{me}")).wait().map_err(zerr)?;
        let watch_tx = tx.clone();
        let watch = session
            .liveliness()
            .declare_subscriber(format!("{prefix}/shard/alive/*"))
            .history(true)
            .callback(move |sample| {
                let Some(k) = sample.key_expr().as_str().rsplit('/').next().and_then(|k| k.parse().ok()) else {
                    return;
                };
                let _ = watch_tx.send(match sample.kind() {
                    SampleKind::Put => Incoming::Joined(k),
                    SampleKind::Delete => Incoming::Left(k),
                });
            })
            .wait()
            .map_err(zerr)?;
        let publishers = declare_publishers(&session, prefix, me, &neighbours)?;
        Ok(Self {
            session,
            prefix: prefix.to_owned(),
            me,
            neighbours,
            publishers,
            tx,
            inbox,
            subscriber,
            _alive: alive,
            _watch: watch,
            _done: done,
            done: Vec::new(),
            early: BTreeMap::new(),
            taken_tick: None,
            joined: Vec::new(),
            left: Vec::new(),
            rejoined: false,
            timeout,
            on_lost: OnLost::Stop,
            stop: None,
            sent: Vec::new(),
            sent_before: Vec::new(),
            stats: LinkStats::default(),
        })
    }

    /// Declares this shard's batch subscriber and publishers afresh, so that their routes are
    /// declared anew to a router that restarted (a client's publisher may otherwise keep
    /// believing nobody listens).
    fn redeclare(&mut self) -> Result<(), LinkError> {
        self.subscriber = declare_batches(&self.session, &self.prefix, self.me, self.tx.clone())?;
        self.publishers = declare_publishers(&self.session, &self.prefix, self.me, &self.neighbours)?;
        Ok(())
    }

    /// A hold for neighbours that had left, begun at `since`, is over.
    fn end_hold(&mut self, since: Instant, tick: u64) {
        self.stats.held_s += since.elapsed().as_secs_f64();
        eprintln!("shard {}: neighbours back at tick {tick}", self.me);
    }

    /// What this shard does when a neighbour leaves (default [`OnLost::Stop`]).
    pub fn on_lost(mut self, on_lost: OnLost) -> Self {
        self.on_lost = on_lost;
        self
    }

    /// Ends every wait for neighbours once `stop` is set: before the first step
    /// ([`ShardLink::wait_for_neighbours`]), at a step's barrier ([`ShardLink::exchange`],
    /// which then leaves the state untouched), and after the last ([`ShardLink::finish`]). A
    /// neighbour held by a frozen or lost shard would otherwise keep a stopped run for the
    /// barrier timeout.
    pub fn stop_on(mut self, stop: Arc<AtomicBool>) -> Self {
        self.stop = Some(stop);
        self
    }

    fn stopped(&self) -> bool {
        self.stop.as_ref().is_some_and(|s| s.load(Ordering::Relaxed))
    }

    /// Waits until every neighbour is up (its liveliness token seen) and every publisher has
    /// a matching subscriber, so that the first batch is not lost.
    pub fn wait_for_neighbours(&mut self) -> Result<(), LinkError> {
        let start = Instant::now();
        loop {
            while let Ok(msg) = self.inbox.try_recv() {
                self.take(msg)?;
            }
            let missing: Vec<ShardId> = self.neighbours.iter().copied().filter(|k| !self.joined.contains(k)).collect();
            self.gone(&missing, 0)?;
            let unmatched = self.publishers.iter().any(|p| !p.matching_status().wait().is_ok_and(|m| m.matching()));
            if missing.is_empty() && !unmatched {
                return Ok(());
            }
            if self.stopped() {
                return Err(LinkError::Stopped { me: self.me, tick: 0 });
            }
            if start.elapsed() > self.timeout {
                let missing = if missing.is_empty() { self.neighbours.clone() } else { missing };
                return Err(LinkError::Timeout {
                    me: self.me,
                    missing,
                    tick: 0,
                    waited_s: start.elapsed().as_secs_f64(),
                });
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    fn take(&mut self, msg: Incoming) -> Result<(), LinkError> {
        match msg {
            Incoming::Batch(Arrived { batch: b, bytes, decode_s, in_shm, transit_s }) => {
                self.stats.bytes_received += bytes as u64;
                if let Some(transit_s) = transit_s {
                    self.stats.transit_s += transit_s;
                    self.stats.transit_max_s = self.stats.transit_max_s.max(transit_s);
                    self.stats.batches_timed += 1;
                }
                self.stats.decode_s += decode_s;
                self.stats.batches_received += 1;
                self.stats.batches_in_shm += u64::from(in_shm);
                if self.taken_tick.is_some_and(|t| b.tick <= t) {
                    self.stats.stale_batches += 1;
                    return Ok(());
                }
                self.stats.ghosts_received += b.ghosts.len() as u64;
                self.early.insert((b.tick, b.from), b);
            }
            Incoming::Bad(key, what) => return Err(LinkError::Decode { me: self.me, key, what }),
            Incoming::Joined(k) => {
                if !self.joined.contains(&k) {
                    self.joined.push(k);
                }
                // Back (a link that dropped and returned).
                if self.left.iter().any(|(l, _)| *l == k) {
                    self.left.retain(|(l, _)| *l != k);
                    self.rejoined = true;
                }
            }
            Incoming::Done(k, tick) => {
                if self.neighbours.contains(&k) && !self.done.contains(&(k, tick)) {
                    self.done.push((k, tick));
                }
            }
            Incoming::Left(k) => {
                // Not an error yet: its last batch may still be on its way (see `exchange`).
                if self.neighbours.contains(&k) && !self.left.iter().any(|(l, _)| *l == k) {
                    self.left.push((k, Instant::now()));
                }
            }
        }
        Ok(())
    }

    /// A missing neighbour that left more than [`LEFT_GRACE`] ago: it is not coming back, or,
    /// when holding, not yet. Returns whether this shard is holding for one.
    fn gone(&self, missing: &[ShardId], tick: u64) -> Result<bool, LinkError> {
        match self.left.iter().find(|(k, at)| missing.contains(k) && at.elapsed() > LEFT_GRACE) {
            Some(&(shard, _)) if self.on_lost == OnLost::Stop => Err(LinkError::Left { shard, tick }),
            Some(_) => Ok(true),
            None => Ok(false),
        }
    }

    /// The barrier: sends each neighbour its ghosts for `state.tick`, waits for all of theirs,
    /// and takes them into `state`.
    pub fn exchange(&mut self, state: &mut State) -> Result<(), LinkError> {
        let tick = state.tick;
        let t0 = Instant::now();
        std::mem::swap(&mut self.sent, &mut self.sent_before);
        self.sent.resize_with(self.neighbours.len(), Vec::new);
        self.sent_before.resize_with(self.neighbours.len(), Vec::new);
        let mut ghosts = Vec::new();
        for (k, (&t, publisher)) in self.neighbours.iter().zip(&self.publishers).enumerate() {
            ghosts.clear();
            state.ghost_refs_for(t, &mut ghosts);
            let batch = GhostBatchRef { tick, from: self.me, ghosts: &ghosts };
            // The buffer of two steps ago, no longer sent again.
            let mut buffer = std::mem::take(&mut self.sent[k]);
            buffer.clear();
            let bytes = postcard::to_extend(&batch, buffer).map_err(zerr)?;
            self.stats.ghosts_sent += ghosts.len() as u64;
            self.stats.bytes_sent += bytes.len() as u64;
            put(publisher, bytes.as_slice())?;
            self.sent[k] = bytes;
        }
        let t1 = Instant::now();
        self.stats.send_s += (t1 - t0).as_secs_f64();
        let (mut last_send, mut holding_since) = (t1, None::<Instant>);
        loop {
            let missing: Vec<ShardId> =
                self.neighbours.iter().copied().filter(|&k| !self.early.contains_key(&(tick, k))).collect();
            if missing.is_empty() {
                break;
            }
            if self.stopped() {
                return Err(LinkError::Stopped { me: self.me, tick });
            }
            if let Some(&(shard, at)) = self.done.iter().find(|(k, at)| missing.contains(k) && *at < tick) {
                return Err(LinkError::Ended { me: self.me, shard, at, tick });
            }
            match (self.gone(&missing, tick)?, holding_since) {
                (true, None) => {
                    holding_since = Some(Instant::now());
                    self.stats.holds += 1;
                    eprintln!(
                        "shard {}: shard(s) {missing:?} left at tick {tick}; holding until back (at most {:.0} s)",
                        self.me,
                        self.timeout.as_secs_f64()
                    );
                }
                (false, Some(since)) => {
                    self.end_hold(since, tick);
                    holding_since = None;
                }
                _ => {}
            }
            let remaining = self.timeout.saturating_sub(t1.elapsed());
            if remaining.is_zero() {
                return Err(LinkError::Timeout { me: self.me, missing, tick, waited_s: t1.elapsed().as_secs_f64() });
            }
            self.resend_when_due(&mut last_send)?;
            // Wake at least every POLL to look at neighbours that left.
            if let Ok(msg) = self.inbox.recv_timeout(remaining.min(POLL)) {
                self.take(msg)?;
            }
        }
        if let Some(since) = holding_since {
            self.end_hold(since, tick);
        }
        let wait = t1.elapsed().as_secs_f64();
        self.stats.wait_s += wait;
        self.stats.wait_max_s = self.stats.wait_max_s.max(wait);
        self.stats.exchanges += 1;
        let mut batches = Vec::with_capacity(self.neighbours.len());
        for &k in &self.neighbours {
            if let Some(b) = self.early.remove(&(tick, k)) {
                batches.push(b);
            }
        }
        // Anything older than this tick is a defect of the sender; nothing waits for it.
        let before = self.early.len();
        self.early.retain(|&(t, _), _| t > tick);
        self.stats.stale_batches += (before - self.early.len()) as u64;
        self.taken_tick = Some(tick);
        let t2 = Instant::now();
        state.receive_ghosts(batches.into_iter().flat_map(|b| b.ghosts))?;
        self.stats.take_s += t2.elapsed().as_secs_f64();
        Ok(())
    }

    /// Ends this shard's part after its last exchange: tells its neighbours it is done, and
    /// waits until each of them is done with the same tick, sending its last batches again
    /// every [`RESEND`]. A neighbour that is done has taken this shard's last batch; leaving
    /// before could lose it, as a batch in shared memory goes with its sender's session. A
    /// neighbour whose token went away counts as done after [`LEFT_GRACE`] (it failed, or its
    /// word was lost), except when holding for neighbours ([`OnLost::Hold`]: it may be back).
    /// Bounded by the barrier timeout, and ended by a stop ([`ShardLink::stop_on`]); the time
    /// goes to [`LinkStats::finish_s`].
    pub fn finish(&mut self) -> Result<(), LinkError> {
        self.finish_within(self.timeout)
    }

    /// [`ShardLink::finish`], waiting at most `timeout`.
    pub fn finish_within(&mut self, timeout: Duration) -> Result<(), LinkError> {
        let Some(tick) = self.taken_tick else { return Ok(()) };
        let start = Instant::now();
        let done = self.await_done(tick, timeout);
        self.stats.finish_s += start.elapsed().as_secs_f64();
        done
    }

    fn await_done(&mut self, tick: u64, timeout: Duration) -> Result<(), LinkError> {
        let key = format!("{}/shard/{}/done", self.prefix, self.me);
        let say_done = |session: &zenoh::Session| {
            let put = session.put(&key, tick.to_le_bytes().to_vec());
            put.congestion_control(CongestionControl::Block).wait().map_err(zerr)
        };
        // Said first: a neighbour may be done already, and wait for this shard's word.
        say_done(&self.session)?;
        let (start, mut last_send) = (Instant::now(), Instant::now());
        loop {
            while let Ok(msg) = self.inbox.try_recv() {
                self.take(msg)?;
            }
            let hold = self.on_lost == OnLost::Hold;
            let gone = |k: &ShardId| {
                self.done.contains(&(*k, tick))
                    || (!hold && self.left.iter().any(|(l, at)| l == k && at.elapsed() > LEFT_GRACE))
            };
            let missing: Vec<ShardId> = self.neighbours.iter().copied().filter(|k| !gone(k)).collect();
            if missing.is_empty() {
                return Ok(());
            }
            if self.stopped() {
                return Err(LinkError::Stopped { me: self.me, tick });
            }
            if start.elapsed() > timeout {
                return Err(LinkError::Timeout { me: self.me, missing, tick, waited_s: start.elapsed().as_secs_f64() });
            }
            if self.resend_when_due(&mut last_send)? {
                say_done(&self.session)?;
            }
            if let Ok(msg) = self.inbox.recv_timeout(POLL) {
                self.take(msg)?;
            }
        }
    }

    /// Sends this step's and the previous step's batches again once [`RESEND`] has passed since
    /// `last_send`, or at once after a neighbour came back (on routes declared anew): a batch
    /// lost while a link was down; the receiver keeps one per (tick, sender). Returns whether
    /// it sent.
    fn resend_when_due(&mut self, last_send: &mut Instant) -> Result<bool, LinkError> {
        let back = std::mem::take(&mut self.rejoined);
        if back {
            self.redeclare()?;
        }
        if !back && last_send.elapsed() < RESEND {
            return Ok(false);
        }
        self.resend()?;
        *last_send = Instant::now();
        Ok(true)
    }

    /// Sends this step's and the previous step's batches again.
    fn resend(&mut self) -> Result<(), LinkError> {
        for (k, publisher) in self.publishers.iter().enumerate() {
            for bytes in [&self.sent_before[k], &self.sent[k]].into_iter().filter(|b| !b.is_empty()) {
                put(publisher, bytes.as_slice())?;
                self.stats.resent += 1;
            }
        }
        Ok(())
    }

    /// The neighbours' batches that arrived for steps not yet taken (those still in the
    /// inbox included), by tick and sender: what a checkpoint keeps of the link.
    pub fn pending(&mut self) -> Result<Vec<&GhostBatch>, LinkError> {
        while let Ok(msg) = self.inbox.try_recv() {
            self.take(msg)?;
        }
        Ok(self.early.values().collect())
    }

    /// Takes back the batches a checkpoint kept ([`ShardLink::pending`]) for a state at
    /// `tick`: those for `tick` and later. Neighbours send theirs again from `tick` on; a batch
    /// is keyed by (tick, sender), so the same batch twice is one.
    pub fn preload(&mut self, batches: Vec<GhostBatch>, tick: u64) {
        for b in batches.into_iter().filter(|b| b.tick >= tick) {
            self.early.insert((b.tick, b.from), b);
        }
    }

    /// What the barrier has cost so far.
    pub fn stats(&self) -> &LinkStats {
        &self.stats
    }

    /// Closes the session (its token goes: neighbours learn this shard is gone).
    pub fn close(self) -> Result<(), LinkError> {
        self.session.close().wait().map_err(zerr)
    }

    /// Withdraws this shard's token and subscribers, leaving the session open (the node's).
    pub fn leave(self) {
        let Self { _alive, subscriber, _watch, _done, publishers, .. } = self;
        let _ = _alive.undeclare().wait();
        drop((subscriber, _watch, _done, publishers));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sim_core::shard::{GhostState, Partition};

    /// A batch serialised from borrowed states is byte for byte the owned batch the receiver
    /// decodes, with whole and far ghosts alike.
    #[test]
    fn borrowed_batches_are_the_owned_bytes() {
        let world = sim_core::scene::compile(&sim_core::scene::dense_swarm(200, 1.5, true, 2, 3)).unwrap();
        let mut state = world.initial_state();
        state.make_shard(Partition::new(&world, 2).unwrap(), 0).unwrap();
        let inputs = world.initial_inputs();
        for _ in 0..20 {
            sim_core::step(&world, &mut state, &inputs);
        }
        let mut refs = Vec::new();
        state.ghost_refs_for(1, &mut refs);
        let owned: Vec<Ghost> = refs.iter().map(GhostRef::to_ghost).collect();
        let full = owned.iter().filter(|g| matches!(g.state, GhostState::Full(_))).count();
        assert!(full > 0 && full < owned.len(), "{full} whole ghosts of {}", owned.len());
        let borrowed = postcard::to_allocvec(&GhostBatchRef { tick: 20, from: 0, ghosts: &refs }).unwrap();
        let batch = GhostBatch { tick: 20, from: 0, ghosts: owned };
        assert_eq!(borrowed, postcard::to_allocvec(&batch).unwrap());
        let back: GhostBatch = postcard::from_bytes(&borrowed).unwrap();
        let digests = |b: &GhostBatch| -> Vec<(u32, Option<u64>)> {
            let digest = |g: &Ghost| match &g.state {
                GhostState::Full(c) => Some(c.digest()),
                GhostState::Seen(_) => None,
            };
            b.ghosts.iter().map(|g| (g.id, digest(g))).collect()
        };
        assert_eq!(digests(&back), digests(&batch));
    }
}
