//! The Ivy-style bus over Zenoh: [`crate::paparazzi::bus::Bus`] bindings fed by Zenoh subscribers on the
//! narrowest key expressions their regexes allow.
//!
//! - [`ZenohBus::bind`] compiles the regex, narrows it to a key expression
//!   (`^(\S*) ATTITUDE …` → `<prefix>/pprz/*/ATTITUDE`, see [`crate::zenoh_net::keyexpr`]) and declares a
//!   subscriber on that expression unless one is already there. Zenoh drops everything else
//!   before it reaches this process: non-matching keys never arrive.
//! - The regex then runs on the text, and the handler receives the capture groups, as with
//!   Ivy's `IvyBindMsg`.
//! - [`ZenohBus::bind_from`] restricts a binding to one aircraft (key and sender token).
//! - [`ZenohBus::unbind`] works at runtime and drops the subscriber once no binding needs it.
//! - [`ZenohBus::send`] publishes a text under `<prefix>/pprz/<sender>/<NAME>`: telemetry under
//!   its aircraft id, datalink messages under `ground_dl` (their destination is in their
//!   `ac_id` field, as on the Ivy bus).
//!
//! Like Ivy, a process does not receive its own messages (subscribers accept remote samples
//! only). Handlers run on Zenoh's callback threads with the bus locked: keep them short, and
//! do not call `bind`/`unbind` from inside one (use [`Control`](crate::paparazzi::bus::Control)).

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use zenoh::sample::Locality;

use crate::ids::AcId;
use crate::paparazzi::bus::{BindId, Bus, BusError, Control, Delivery};
use crate::zenoh_net::keyexpr::key_for_text;

/// Errors of the Zenoh bus.
#[derive(Debug, thiserror::Error)]
pub enum ZenohBusError {
    /// The pattern or the text is not usable.
    #[error(transparent)]
    Bus(#[from] BusError),
    /// Zenoh failed.
    #[error("zenoh: {0}")]
    Zenoh(String),
}

/// Counters of a [`ZenohBus`].
#[derive(Debug, Default)]
pub struct ZenohBusCounters {
    /// Samples that reached this process's subscribers.
    pub samples_received: AtomicU64,
    /// Handler calls.
    pub delivered: AtomicU64,
    /// Texts sent.
    pub sent: AtomicU64,
    /// Samples dropped: their payload is not UTF-8 (Paparazzi texts are ASCII).
    pub dropped_not_utf8: AtomicU64,
    /// Texts on a subscribed key that no binding's regex matched.
    pub unmatched: AtomicU64,
}

struct Sub {
    users: usize,
    _subscriber: zenoh::pubsub::Subscriber<()>,
}

/// An Ivy-style bus on a Zenoh session.
pub struct ZenohBus {
    session: zenoh::Session,
    prefix: String,
    bus: Arc<Mutex<Bus>>,
    subs: Mutex<BTreeMap<String, Sub>>,
    /// The key expression each binding subscribed (its subscription delivers to it alone).
    key_of: Arc<Mutex<BTreeMap<BindId, String>>>,
    /// Counters.
    pub counters: Arc<ZenohBusCounters>,
}

impl std::fmt::Debug for ZenohBus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ZenohBus").field("prefix", &self.prefix).finish_non_exhaustive()
    }
}

impl ZenohBus {
    /// A bus on `session` under `prefix` (e.g. `twinswarm/lab`).
    pub fn new(session: zenoh::Session, prefix: impl Into<String>) -> Self {
        Self {
            session,
            prefix: prefix.into(),
            bus: Arc::new(Mutex::new(Bus::default())),
            subs: Mutex::new(BTreeMap::new()),
            key_of: Arc::default(),
            counters: Arc::new(ZenohBusCounters::default()),
        }
    }

    /// The session.
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    /// The key-expression prefix.
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// Binds `pattern`: `handler` receives the capture groups of every matching text.
    pub async fn bind(
        &self,
        pattern: &str,
        handler: impl FnMut(&Delivery<'_>, &mut Control) + Send + 'static,
    ) -> Result<BindId, ZenohBusError> {
        self.bind_inner(None, pattern, Box::new(handler)).await
    }

    /// Binds `pattern` for texts from aircraft `ac_id` only.
    pub async fn bind_from(
        &self,
        ac_id: AcId,
        pattern: &str,
        handler: impl FnMut(&Delivery<'_>, &mut Control) + Send + 'static,
    ) -> Result<BindId, ZenohBusError> {
        self.bind_inner(Some(ac_id), pattern, Box::new(handler)).await
    }

    async fn bind_inner(
        &self,
        from: Option<AcId>,
        pattern: &str,
        handler: crate::paparazzi::bus::Handler,
    ) -> Result<BindId, ZenohBusError> {
        let (id, key) = {
            let mut bus = crate::lock(&self.bus);
            let id = match from {
                Some(ac) => bus.bind_from(ac, pattern, handler)?,
                None => bus.bind(pattern, handler)?,
            };
            let key = bus
                .bindings()
                .into_iter()
                .find(|b| b.id == id)
                .map(|b| crate::zenoh_net::keyexpr::key_expr(&b.narrowing, &self.prefix));
            (id, key.unwrap_or_else(|| format!("{}/pprz/**", self.prefix)))
        };
        crate::lock(&self.key_of).insert(id, key.clone());
        if let Err(e) = self.subscribe(&key).await {
            self.unbind(id).await;
            return Err(e);
        }
        Ok(id)
    }

    async fn subscribe(&self, key: &str) -> Result<(), ZenohBusError> {
        if let Some(s) = crate::lock(&self.subs).get_mut(key) {
            s.users += 1;
            return Ok(());
        }
        let (bus, counters, key_of, my_key) =
            (self.bus.clone(), self.counters.clone(), self.key_of.clone(), key.to_owned());
        let subscriber = self
            .session
            .declare_subscriber(key.to_owned())
            .allowed_origin(Locality::Remote)
            .callback(move |sample| {
                counters.samples_received.fetch_add(1, Ordering::Relaxed);
                let payload = sample.payload().to_bytes();
                let Ok(text) = std::str::from_utf8(&payload) else {
                    let n = counters.dropped_not_utf8.fetch_add(1, Ordering::Relaxed) + 1;
                    if n.is_power_of_two() {
                        tracing::warn!("{n} non-UTF-8 payloads dropped so far (the last on {})", sample.key_expr());
                    }
                    return;
                };
                // Only this subscription's bindings: another subscription whose key expression
                // overlaps delivers the same sample to its own.
                let mine: Vec<BindId> =
                    crate::lock(&key_of).iter().filter(|(_, k)| **k == my_key).map(|(id, _)| *id).collect();
                let text = text.trim_end_matches(['\n', '\r']);
                let n = crate::lock(&bus).dispatch_among(sample.key_expr().as_str(), text, |id| mine.contains(&id));
                counters.delivered.fetch_add(n as u64, Ordering::Relaxed);
                if n == 0 {
                    counters.unmatched.fetch_add(1, Ordering::Relaxed);
                }
            })
            .await
            .map_err(|e| ZenohBusError::Zenoh(e.to_string()))?;
        let mut subs = crate::lock(&self.subs);
        // Another bind may have raced us to the same key: keep one subscriber.
        match subs.get_mut(key) {
            Some(s) => s.users += 1,
            None => {
                subs.insert(key.to_owned(), Sub { users: 1, _subscriber: subscriber });
            }
        }
        Ok(())
    }

    /// Removes a binding; its subscriber goes when no other binding uses its key expression.
    /// Returns `false` if it was not bound (e.g. it unbound itself from its handler; its
    /// subscriber is then released here).
    pub async fn unbind(&self, id: BindId) -> bool {
        let was_bound = crate::lock(&self.bus).unbind(id);
        let key = crate::lock(&self.key_of).remove(&id);
        if let Some(key) = key {
            let dead = {
                let mut subs = crate::lock(&self.subs);
                let last = subs.get_mut(&key).is_some_and(|s| {
                    s.users -= 1;
                    s.users == 0
                });
                if last { subs.remove(&key) } else { None }
            };
            drop(dead);
        }
        was_bound
    }

    /// The key expressions this bus is subscribed to.
    pub fn subscribed_keys(&self) -> Vec<String> {
        crate::lock(&self.subs).keys().cloned().collect()
    }

    /// Publishes `text` under its key (`<prefix>/pprz/<sender>/<NAME>`).
    pub async fn send(&self, text: &str) -> Result<(), ZenohBusError> {
        let key = key_for_text(&self.prefix, text)?;
        self.session.put(key, text.to_owned()).await.map_err(|e| ZenohBusError::Zenoh(e.to_string()))?;
        self.counters.sent.fetch_add(1, Ordering::Relaxed);
        Ok(())
    }

    /// Number of live bindings.
    pub fn len(&self) -> usize {
        crate::lock(&self.bus).len()
    }

    /// Whether there is no binding.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}
