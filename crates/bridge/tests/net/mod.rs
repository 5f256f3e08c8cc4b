//! Helpers of the Zenoh integration tests: a free loopback port and awaits under a timeout.

#![allow(dead_code)]

use std::time::Duration;

/// The timeout of every await in the Zenoh tests.
pub const T: Duration = Duration::from_secs(10);

/// A TCP port free on 127.0.0.1 right now.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free loopback port")
}

/// Awaits `f`, panicking with `what` after [`T`].
pub async fn within<F: std::future::IntoFuture>(what: &str, f: F) -> F::Output {
    match tokio::time::timeout(T, f.into_future()).await {
        Ok(v) => v,
        Err(_) => panic!("timed out: {what}"),
    }
}

/// Waits until `cond` holds, polling every 10 ms, at most [`T`].
pub async fn eventually(what: &str, mut cond: impl FnMut() -> bool) {
    within(what, async {
        while !cond() {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await
}
