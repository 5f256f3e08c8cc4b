//! The tokio side of mixed reality: the [`Gateway`] binds the FINken telemetry on the Ivy-style
//! bus, on Zenoh ([`crate::zenoh_net::pprz_bus::ZenohBus`]), on a real Ivy bus
//! ([`crate::paparazzi::ivy::IvyAgent`]) or on both ([`PprzLinks`]), hands each text to its
//! [`Interpreter`] and queues the loop's requests (commands, observed attitude, automatic
//! spawns) without ever waiting. With both links it bridges every text between them. It also
//! sends the loop's Paparazzi texts on Ivy (Zenoh gets them from the node).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use sim_core::World;

use crate::engine::request::{BusInput, Request};
use crate::mixed::interpreter::{BOUND_TELEMETRY, GatewayReport, Interpreter, TwinAttitude};
use crate::mixed::outbox::PprzOut;
use crate::paparazzi::ivy::IvyAgent;
use crate::paparazzi::messages::MessageSet;
use crate::paparazzi::pairing::ResolvedPairing;
use crate::zenoh_net::pprz_bus::{ZenohBus, ZenohBusError};

/// Why the gateway could not bind.
#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    /// On Zenoh.
    #[error(transparent)]
    Zenoh(#[from] ZenohBusError),
    /// On Ivy.
    #[error(transparent)]
    Ivy(#[from] crate::paparazzi::ivy::IvyError),
}

/// Where Paparazzi texts travel: Zenoh (`<prefix>/pprz/<sender>/<NAME>`), a real Ivy bus, or
/// both, in which case the gateway also bridges every text between them.
#[derive(Clone, Debug, Default)]
pub struct PprzLinks {
    /// A Zenoh session and the key prefix.
    pub zenoh: Option<(zenoh::Session, String)>,
    /// An agent on a real Ivy bus.
    pub ivy: Option<Arc<IvyAgent>>,
}

/// Texts bridged between Zenoh and Ivy.
#[derive(Debug, Default)]
pub struct BridgeCounters {
    /// Texts from Ivy peers published on Zenoh.
    pub ivy_to_zenoh: AtomicU64,
    /// Texts from Zenoh sent to Ivy peers.
    pub zenoh_to_ivy: AtomicU64,
    /// Texts not bridged, by reason.
    pub dropped_queue_full: AtomicU64,
    /// Texts Ivy cannot carry (newline or separator).
    pub dropped_unsendable: AtomicU64,
    /// Ivy texts Zenoh refused to publish (the session closing).
    pub dropped_put_failed: AtomicU64,
}

/// The tokio side of mixed reality (see the module docs).
pub struct Gateway {
    zenoh: Option<ZenohBus>,
    ivy: Option<Arc<IvyAgent>>,
    shared: Arc<Mutex<Interpreter>>,
    bridged: Arc<BridgeCounters>,
    _forwarder: Option<tokio::task::JoinHandle<()>>,
}

impl std::fmt::Debug for Gateway {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Gateway").field("zenoh", &self.zenoh).field("ivy", &self.ivy).finish_non_exhaustive()
    }
}

/// A handler that interprets telemetry texts into loop requests.
fn telemetry_handler(
    shared: &Arc<Mutex<Interpreter>>,
    messages: &Arc<MessageSet>,
    requests: &SyncSender<Request>,
) -> impl FnMut(&crate::paparazzi::bus::Delivery<'_>, &mut crate::paparazzi::bus::Control) + Send + 'static {
    let (shared, messages, requests) = (shared.clone(), messages.clone(), requests.clone());
    move |d, _| {
        let received = Instant::now();
        let origin =
            BusInput { key: d.key.to_owned(), text: d.text.to_owned(), received_unix_ns: crate::log::now_unix_ns() };
        let mut sh = crate::lock(&shared);
        let request = sh.interpret(&messages, origin, received);
        if let Err(TrySendError::Full(r) | TrySendError::Disconnected(r)) = requests.try_send(request) {
            sh.stats.queue_full += 1;
            // A lost spawn would leave the aircraft routed to a twin that never exists: the
            // next text of the aircraft carries it again.
            if let Request::Twin { spawn: Some(spec), .. } = r {
                sh.pending_spawn.insert(spec.ac_id.unwrap_or(0), spec);
            }
            if sh.stats.queue_full.is_power_of_two() {
                tracing::warn!("{} telemetry texts dropped so far: the step loop's queue is full", sh.stats.queue_full);
            }
        }
    }
}

/// What the gateway binds to bridge every text: a sender and a name.
const ANY_TEXT: &str = r"^\S+ \S+";

impl Gateway {
    /// Binds the FINken telemetry on every link; requests go to the loop. With both links,
    /// every text is also bridged between them. No text loops: Zenoh subscribers take remote
    /// samples only and Ivy peers never receive their own texts, so a bridged text is never
    /// bridged back.
    pub async fn start(
        links: PprzLinks,
        world: Arc<World>,
        pairing: Option<ResolvedPairing>,
        messages: Arc<MessageSet>,
        requests: SyncSender<Request>,
        attitude: TwinAttitude,
    ) -> Result<Self, GatewayError> {
        let shared = Arc::new(Mutex::new(Interpreter::new(world, pairing, attitude)));
        let bridged = Arc::new(BridgeCounters::default());
        let zenoh = links.zenoh.map(|(session, prefix)| ZenohBus::new(session, prefix));
        for name in BOUND_TELEMETRY {
            let pattern = format!(r"^(\d+) {name} ");
            if let Some(z) = &zenoh {
                z.bind(&pattern, telemetry_handler(&shared, &messages, &requests)).await?;
            }
            if let Some(ivy) = &links.ivy {
                ivy.bind(&pattern, telemetry_handler(&shared, &messages, &requests))?;
            }
        }
        let mut forwarder = None;
        if let (Some(z), Some(ivy)) = (&zenoh, &links.ivy) {
            // Zenoh → Ivy: straight from the subscriber callback (sending never waits).
            let (ivy2, c) = (ivy.clone(), bridged.clone());
            z.bind(ANY_TEXT, move |d, _| match ivy2.send(d.text) {
                Ok(_) => {
                    c.zenoh_to_ivy.fetch_add(1, Ordering::Relaxed);
                }
                Err(_) => {
                    c.dropped_unsendable.fetch_add(1, Ordering::Relaxed);
                }
            })
            .await?;
            // Ivy → Zenoh: through a bounded queue to a publishing task.
            let (tx, mut rx) = tokio::sync::mpsc::channel::<String>(4096);
            let c = bridged.clone();
            ivy.bind(ANY_TEXT, move |d, _| {
                if tx.try_send(d.text.to_owned()).is_err() {
                    c.dropped_queue_full.fetch_add(1, Ordering::Relaxed);
                }
            })?;
            let (session, prefix, c) = (z.session().clone(), z.prefix().to_owned(), bridged.clone());
            forwarder = Some(tokio::spawn(async move {
                while let Some(text) = rx.recv().await {
                    let Ok(key) = crate::zenoh_net::keyexpr::key_for_text(&prefix, &text) else {
                        c.dropped_unsendable.fetch_add(1, Ordering::Relaxed);
                        continue;
                    };
                    match session.put(key, text).await {
                        Ok(()) => c.ivy_to_zenoh.fetch_add(1, Ordering::Relaxed),
                        Err(e) => {
                            tracing::debug!("bridging a text to Zenoh failed: {e}");
                            c.dropped_put_failed.fetch_add(1, Ordering::Relaxed)
                        }
                    };
                }
            }));
        }
        Ok(Self { zenoh, ivy: links.ivy, shared, bridged, _forwarder: forwarder })
    }

    /// Sends the loop's Paparazzi texts on Ivy (Zenoh gets them from the node).
    pub fn send_ivy(&self, out: &[PprzOut]) {
        if let Some(ivy) = &self.ivy {
            for o in out {
                // The agent counts what it cannot send (its drops); the outbox's texts hold
                // no newline or separator.
                let _ = ivy.send(&o.text);
            }
        }
    }

    /// Texts bridged between Zenoh and Ivy.
    pub fn bridged(&self) -> &BridgeCounters {
        &self.bridged
    }

    /// Tells the gateway about the world after a spawn (for command validation).
    pub fn set_world(&self, world: &Arc<World>) {
        crate::lock(&self.shared).set_world(world);
    }

    /// A copy of the statistics so far, and of the router's counters.
    pub fn report(&self) -> GatewayReport {
        crate::lock(&self.shared).report()
    }

    /// The Zenoh bus the gateway uses, if any (for counters).
    pub fn zenoh_bus(&self) -> Option<&ZenohBus> {
        self.zenoh.as_ref()
    }
}
