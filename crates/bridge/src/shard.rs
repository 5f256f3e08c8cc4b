//! Sharding over Zenoh ([`sim_core::shard`] does the stepping): each shard sends each
//! neighbour its ghosts once per control step, and waits for every neighbour's before it steps
//! on. That exchange *is* the lockstep barrier: a shard at tick T has had every neighbour's
//! state at T. Liveliness tokens tell a shard that a neighbour is gone, so it stops with an
//! error instead of waiting for ever.
//!
//! Keys, under the run's prefix:
//! - `<prefix>/shard/<from>/to/<to>`: a [`GhostBatch`] (postcard), reliable, express, blocking
//!   under congestion (a lost batch would be a lost barrier);
//! - `<prefix>/shard/alive/<k>`: liveliness token of shard `k` (declared after its subscriber,
//!   so a shard that sees it may publish to it).
//!
//! No home-made transport and no discovery: the sessions connect to a Zenoh router (or to each
//! other) as configured, multicast scouting off by default.

use std::collections::BTreeMap;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use sim_core::State;
use sim_core::shard::{Ghost, ShardError, ShardId};
use zenoh::Wait;
use zenoh::qos::CongestionControl;
use zenoh::sample::SampleKind;

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
    /// A neighbour's liveliness token went away.
    #[error("shard {shard} left the cluster at tick {tick} (its liveliness token is gone)")]
    Left {
        /// The neighbour.
        shard: ShardId,
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

/// How long a neighbour that left may still deliver its last batch.
const LEFT_GRACE: Duration = Duration::from_secs(2);

/// How often a waiting shard looks at neighbours that left.
const POLL: Duration = Duration::from_millis(50);

fn zerr(e: impl std::fmt::Display) -> LinkError {
    LinkError::Zenoh(e.to_string())
}

enum Incoming {
    Batch(GhostBatch, usize),
    Bad(String, String),
    Joined(ShardId),
    Left(ShardId),
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
    /// Ghosts sent and received.
    pub ghosts_sent: u64,
    /// Ghosts received.
    pub ghosts_received: u64,
    /// Payload bytes sent and received.
    pub bytes_sent: u64,
    /// Payload bytes received.
    pub bytes_received: u64,
}

impl std::fmt::Debug for ShardLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ShardLink").field("me", &self.me).field("neighbours", &self.neighbours).finish_non_exhaustive()
    }
}

/// A shard's link to its neighbours.
pub struct ShardLink {
    session: zenoh::Session,
    me: ShardId,
    neighbours: Vec<ShardId>,
    publishers: Vec<zenoh::pubsub::Publisher<'static>>,
    inbox: mpsc::Receiver<Incoming>,
    _subscriber: zenoh::pubsub::Subscriber<()>,
    _alive: zenoh::liveliness::LivelinessToken,
    _watch: zenoh::pubsub::Subscriber<()>,
    /// Batches that came early (a neighbour one step ahead), by (tick, from).
    early: BTreeMap<(u64, ShardId), GhostBatch>,
    joined: Vec<ShardId>,
    /// Neighbours whose token went away, and when this shard learnt it.
    left: Vec<(ShardId, Instant)>,
    timeout: Duration,
    ghosts: Vec<Ghost>,
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
        let sub_tx = tx.clone();
        let subscriber = session
            .declare_subscriber(format!("{prefix}/shard/*/to/{me}"))
            .callback(move |sample| {
                let key = sample.key_expr().to_string();
                let bytes = sample.payload().to_bytes();
                let msg = match postcard::from_bytes::<GhostBatch>(&bytes) {
                    Ok(b) => Incoming::Batch(b, bytes.len()),
                    Err(e) => Incoming::Bad(key, e.to_string()),
                };
                let _ = sub_tx.send(msg);
            })
            .wait()
            .map_err(zerr)?;
        let alive = session.liveliness().declare_token(format!("{prefix}/shard/alive/{me}")).wait().map_err(zerr)?;
        let watch = session
            .liveliness()
            .declare_subscriber(format!("{prefix}/shard/alive/*"))
            .history(true)
            .callback(move |sample| {
                let Some(k) = sample.key_expr().as_str().rsplit('/').next().and_then(|k| k.parse().ok()) else {
                    return;
                };
                let _ = tx.send(match sample.kind() {
                    SampleKind::Put => Incoming::Joined(k),
                    SampleKind::Delete => Incoming::Left(k),
                });
            })
            .wait()
            .map_err(zerr)?;
        let mut publishers = Vec::new();
        for &t in &neighbours {
            let p = session
                .declare_publisher(format!("{prefix}/shard/{me}/to/{t}"))
                .congestion_control(CongestionControl::Block)
                .express(true)
                .wait()
                .map_err(zerr)?;
            publishers.push(p);
        }
        Ok(Self {
            session,
            me,
            neighbours,
            publishers,
            inbox,
            _subscriber: subscriber,
            _alive: alive,
            _watch: watch,
            early: BTreeMap::new(),
            joined: Vec::new(),
            left: Vec::new(),
            timeout,
            ghosts: Vec::new(),
            stats: LinkStats::default(),
        })
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
            Incoming::Batch(b, bytes) => {
                self.stats.bytes_received += bytes as u64;
                self.stats.ghosts_received += b.ghosts.len() as u64;
                self.early.insert((b.tick, b.from), b);
            }
            Incoming::Bad(key, what) => return Err(LinkError::Decode { me: self.me, key, what }),
            Incoming::Joined(k) => {
                if !self.joined.contains(&k) {
                    self.joined.push(k);
                }
            }
            Incoming::Left(k) => {
                // Not an error yet: a neighbour that finished its last step leaves right after
                // sending its last batch, which may still be on its way (see `exchange`).
                if self.neighbours.contains(&k) && !self.left.iter().any(|(l, _)| *l == k) {
                    self.left.push((k, Instant::now()));
                }
            }
        }
        Ok(())
    }

    /// A missing neighbour that left more than [`LEFT_GRACE`] ago: it is not coming back.
    fn gone(&self, missing: &[ShardId], tick: u64) -> Result<(), LinkError> {
        match self.left.iter().find(|(k, at)| missing.contains(k) && at.elapsed() > LEFT_GRACE) {
            Some(&(shard, _)) => Err(LinkError::Left { shard, tick }),
            None => Ok(()),
        }
    }

    /// The barrier: sends each neighbour its ghosts for `state.tick`, waits for all of theirs,
    /// and takes them into `state`.
    pub fn exchange(&mut self, state: &mut State) -> Result<(), LinkError> {
        let tick = state.tick;
        let t0 = Instant::now();
        for (&t, publisher) in self.neighbours.iter().zip(&self.publishers) {
            self.ghosts.clear();
            state.ghosts_for(t, &mut self.ghosts);
            let batch = GhostBatch { tick, from: self.me, ghosts: std::mem::take(&mut self.ghosts) };
            let bytes = postcard::to_allocvec(&batch).map_err(zerr)?;
            self.stats.ghosts_sent += batch.ghosts.len() as u64;
            self.stats.bytes_sent += bytes.len() as u64;
            self.ghosts = batch.ghosts;
            publisher.put(bytes).wait().map_err(zerr)?;
        }
        let t1 = Instant::now();
        self.stats.send_s += (t1 - t0).as_secs_f64();
        loop {
            let missing: Vec<ShardId> =
                self.neighbours.iter().copied().filter(|&k| !self.early.contains_key(&(tick, k))).collect();
            if missing.is_empty() {
                break;
            }
            self.gone(&missing, tick)?;
            let remaining = self.timeout.saturating_sub(t1.elapsed());
            if remaining.is_zero() {
                return Err(LinkError::Timeout { me: self.me, missing, tick, waited_s: t1.elapsed().as_secs_f64() });
            }
            // Wake at least every POLL to look at neighbours that left.
            if let Ok(msg) = self.inbox.recv_timeout(remaining.min(POLL)) {
                self.take(msg)?;
            }
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
        self.early.retain(|&(t, _), _| t > tick);
        state.receive_ghosts(batches.into_iter().flat_map(|b| b.ghosts))?;
        Ok(())
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
        let Self { _alive, _subscriber, _watch, publishers, .. } = self;
        let _ = _alive.undeclare().wait();
        drop((_subscriber, _watch, publishers));
    }
}
