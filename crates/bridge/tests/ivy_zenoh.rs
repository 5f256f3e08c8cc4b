//! The Ivy-style bus on real Zenoh sessions over loopback: capture groups, `bind_from`,
//! `unbind` at runtime, and key-expression narrowing (texts on non-matching keys never reach
//! the subscribing process). Every await is under a timeout.

mod net;

use std::sync::{Arc, Mutex};
use std::time::Duration;

use bridge::zenoh_net::node;
use bridge::zenoh_net::pprz_bus::ZenohBus;
use net::{eventually, free_port, within};

type Log = Arc<Mutex<Vec<Vec<String>>>>;

fn recorder() -> (Log, impl FnMut(&bridge::Delivery<'_>, &mut bridge::Control) + Send + 'static) {
    let log: Log = Arc::default();
    let l = log.clone();
    (log, move |d: &bridge::Delivery<'_>, _: &mut bridge::Control| {
        l.lock().unwrap().push(d.captures.iter().map(|s| s.to_string()).collect());
    })
}

/// A listening session and a client session on a free loopback port, and a bus on each under
/// the prefix `<tag>-<port>`.
async fn buses(tag: &str) -> (zenoh::Session, zenoh::Session, ZenohBus, ZenohBus) {
    let port = free_port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let prefix = format!("{tag}-{port}");
    let listener =
        within("open listener", zenoh::open(node::default_config(std::slice::from_ref(&endpoint), &[]).unwrap()))
            .await
            .unwrap();
    let talker = within("open talker", zenoh::open(node::client_config(std::slice::from_ref(&endpoint)).unwrap()))
        .await
        .unwrap();
    let rx = ZenohBus::new(listener.clone(), prefix.clone());
    let tx = ZenohBus::new(talker.clone(), prefix);
    (listener, talker, rx, tx)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bind_bind_from_unbind_and_narrowing_over_zenoh() {
    let (listener, talker, rx, tx) = buses("ivy-test").await;
    let prefix = rx.prefix().to_owned();

    // Capture groups, Ivy style; the pattern narrows to <prefix>/pprz/*/ATTITUDE.
    let (attitude, h) = recorder();
    let id_att = within("bind", rx.bind(r"^(\S*) ATTITUDE (\S+) (\S+) (\S+)", h)).await.unwrap();
    // Only aircraft 6: narrows to <prefix>/pprz/6/SONAR_ARRAY.
    let (sonar6, h) = recorder();
    within("bind_from", rx.bind_from(6, r"^\S+ SONAR_ARRAY (\d+) (\d+)", h)).await.unwrap();
    let mut keys = rx.subscribed_keys();
    keys.sort();
    assert_eq!(keys, [format!("{prefix}/pprz/*/ATTITUDE"), format!("{prefix}/pprz/6/SONAR_ARRAY")]);

    // Matching routes on both sides need a moment to propagate.
    tokio::time::sleep(Duration::from_millis(300)).await;
    let before = rx.counters.samples_received.load(std::sync::atomic::Ordering::Relaxed);
    // Texts on keys nobody bound: they must never reach the listener's process.
    for text in ["5 ROTORCRAFT_FP 1 2 3", "5 SONAR_ARRAY 1 2 3 4", "7 SONAR_ARRAY 9 9 9 9", "ground PING"] {
        within("send", tx.send(text)).await.unwrap();
    }
    // Texts it bound.
    within("send", tx.send("5 ATTITUDE 0.1 -0.2 0.3")).await.unwrap();
    within("send", tx.send("6 SONAR_ARRAY 120 85 300 44")).await.unwrap();
    within("send", tx.send("6 ATTITUDE 1 2 3")).await.unwrap();
    eventually("deliveries", || attitude.lock().unwrap().len() == 2 && sonar6.lock().unwrap().len() == 1).await;
    // Give stragglers time to arrive (they must not).
    tokio::time::sleep(Duration::from_millis(300)).await;
    let received = rx.counters.samples_received.load(std::sync::atomic::Ordering::Relaxed) - before;
    assert_eq!(received, 3, "only the three bound texts may reach the process");
    assert_eq!(
        *attitude.lock().unwrap(),
        vec![vec!["5", "0.1", "-0.2", "0.3"], vec!["6", "1", "2", "3"]]
            .into_iter()
            .map(|v| v.into_iter().map(String::from).collect::<Vec<_>>())
            .collect::<Vec<_>>()
    );
    assert_eq!(*sonar6.lock().unwrap(), vec![vec!["120".to_string(), "85".to_string()]]);

    // Unbind at runtime: the subscriber goes, and so do further deliveries.
    assert!(within("unbind", rx.unbind(id_att)).await);
    assert!(!within("unbind again", rx.unbind(id_att)).await);
    assert_eq!(rx.subscribed_keys(), [format!("{prefix}/pprz/6/SONAR_ARRAY")]);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let before = rx.counters.samples_received.load(std::sync::atomic::Ordering::Relaxed);
    within("send", tx.send("5 ATTITUDE 9 9 9")).await.unwrap();
    within("send", tx.send("6 SONAR_ARRAY 1 2 3 4")).await.unwrap();
    eventually("sonar after unbind", || sonar6.lock().unwrap().len() == 2).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(attitude.lock().unwrap().len(), 2, "no ATTITUDE after unbind");
    assert_eq!(rx.counters.samples_received.load(std::sync::atomic::Ordering::Relaxed) - before, 1);

    // A text without a usable key is an error, not a panic.
    assert!(tx.send("no-name").await.is_err());
    assert!(tx.send("5 BAD/NAME 1").await.is_err());
    // A bad pattern is an error.
    assert!(rx.bind("(unclosed", |_, _| {}).await.is_err());

    drop((rx, tx));
    within("close talker", talker.close()).await.unwrap();
    within("close listener", listener.close()).await.unwrap();
}

/// Found by the flood test: two bindings whose key expressions overlap (`…/pprz/*/ATTITUDE`
/// and `…/pprz/**`) have two subscriptions that both receive a text; each must deliver it to
/// its own bindings only, so that every handler runs once per text, not once per subscription.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn overlapping_subscriptions_deliver_each_text_once_to_each_binding() {
    let (listener, talker, rx, tx) = buses("ivy-overlap").await;
    let (attitude, h) = recorder();
    within("bind", rx.bind(r"^(\d+) ATTITUDE ", h)).await.unwrap();
    let (any, h) = recorder();
    within("bind any", rx.bind(r"^(\S+) \S+", h)).await.unwrap();
    assert_eq!(rx.subscribed_keys().len(), 2);
    tokio::time::sleep(Duration::from_millis(300)).await;
    for k in 0..10 {
        within("send", tx.send(&format!("{k} ATTITUDE 0.1 0.2 0.3"))).await.unwrap();
    }
    within("send", tx.send("5 SONAR_ARRAY 1 2 3 4")).await.unwrap();
    eventually("deliveries", || attitude.lock().unwrap().len() >= 10 && any.lock().unwrap().len() >= 11).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert_eq!(attitude.lock().unwrap().len(), 10, "each ATTITUDE once to its binding");
    assert_eq!(any.lock().unwrap().len(), 11, "each text once to the catch-all binding");
    within("close", listener.close()).await.unwrap();
    within("close", talker.close()).await.unwrap();
}
