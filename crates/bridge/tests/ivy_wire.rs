//! The Ivy wire protocol on real sockets over loopback: two of our agents, and hostile peers
//! written byte by byte (malformed hellos, binary garbage, over-long lines, regexes the
//! `regex` crate refuses or that are made to be slow, half-open connections, a peer that
//! never reads). Each is counted; none panics or stalls sending. Every bus is
//! `127.255.255.255` on a free UDP port; every await is under a timeout.

mod net;

use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bridge::paparazzi::ivy::{BusAddr, IvyAgent, IvyOptions};
use net::{eventually, within};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;

/// Texts received, with their groups.
type Received = Arc<Mutex<Vec<(String, Vec<String>)>>>;

fn bus() -> BusAddr {
    let port = std::net::UdpSocket::bind("127.0.0.1:0").and_then(|s| s.local_addr()).map(|a| a.port()).unwrap();
    BusAddr::parse(&format!("127.255.255.255:{port}")).unwrap()
}

fn drops(agent: &IvyAgent, reason: &str) -> u64 {
    agent.drops().get(reason).copied().unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_agents_find_each_other_exchange_groups_and_unbind() {
    let bus = bus();
    let a = within("start a", IvyAgent::start(IvyOptions::new(bus.clone(), "A"))).await.unwrap();
    let got: Received = Arc::default();
    let g = got.clone();
    let id = a
        .bind(r"^(\S*) ATTITUDE (\S+) (\S+)", move |d, _| {
            g.lock().unwrap().push((d.text.to_owned(), d.captures.iter().map(|s| s.to_string()).collect()));
        })
        .unwrap();
    let b = within("start b", IvyAgent::start(IvyOptions::new(bus.clone(), "B agent"))).await.unwrap();
    eventually("b knows a's regex", || b.peers().iter().any(|p| p.app_name == "A" && p.ready && !p.regexes.is_empty()))
        .await;
    // Who would take a text, without sending it.
    assert_eq!((b.takers("5 ATTITUDE 0.1 -0.2 0.3"), b.takers("5 ROTORCRAFT_FP 1 2 3")), (1, 0));
    assert_eq!(b.send("5 ATTITUDE 0.1 -0.2 0.3").unwrap(), 1);
    assert_eq!(b.send("5 ROTORCRAFT_FP 1 2 3").unwrap(), 0);
    eventually("delivery", || got.lock().unwrap().len() == 1).await;
    assert_eq!(
        got.lock().unwrap()[0],
        ("5 ATTITUDE 0.1 -0.2 0.3".to_owned(), vec!["5".to_owned(), "0.1".to_owned(), "-0.2".to_owned()])
    );
    // Names with spaces survive StartRegexp.
    assert!(a.peers().iter().any(|p| p.app_name == "B agent"));
    assert!(a.unbind(id));
    eventually("b saw DelRegexp", || b.peers().iter().all(|p| p.regexes.is_empty())).await;
    assert_eq!(b.send("5 ATTITUDE 1 2 3").unwrap(), 0);
    assert_eq!(b.takers("5 ATTITUDE 1 2 3"), 0);
    // Each saw its own hello once and dropped it.
    assert_eq!(drops(&a, "hello: our own"), 1);
    b.stop().await;
    eventually("a saw b leave", || a.events().iter().any(|e| e.what == "left" && e.why == "bye")).await;
}

/// `sync_with` returns once the named peer has taken in this agent's bindings (its Pong comes
/// after them), and false after the timeout when no such peer is on the bus.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sync_with_waits_until_the_named_peer_has_the_bindings() {
    let bus = bus();
    let a = Arc::new(within("start a", IvyAgent::start(IvyOptions::new(bus.clone(), "A"))).await.unwrap());
    let b = within("start b", IvyAgent::start(IvyOptions::new(bus.clone(), "Link"))).await.unwrap();
    a.bind(r"^(\S*) ATTITUDE", |_, _| {}).unwrap();
    let a2 = Arc::clone(&a);
    let synced = tokio::task::spawn_blocking(move || a2.sync_with("Link", Duration::from_secs(10))).await.unwrap();
    assert!(synced);
    // No waiting: b holds a's regex now.
    assert_eq!(b.takers("5 ATTITUDE 1 2 3"), 1);
    let a3 = Arc::clone(&a);
    let start = Instant::now();
    let none = tokio::task::spawn_blocking(move || a3.sync_with("nobody", Duration::from_millis(300))).await.unwrap();
    assert!(!none && start.elapsed() >= Duration::from_millis(300));
    b.stop().await;
}

/// A peer written by hand: connects to `agent` and introduces itself.
async fn raw_peer(
    agent: &IvyAgent,
    regexes: &[&str],
) -> (BufReader<tokio::net::tcp::OwnedReadHalf>, tokio::net::tcp::OwnedWriteHalf) {
    let s = within("connect", TcpStream::connect(("127.0.0.1", agent.port()))).await.unwrap();
    let (r, mut w) = s.into_split();
    let mut hs = b"6 1\x02raw\n".to_vec();
    for (i, r) in regexes.iter().enumerate() {
        hs.extend_from_slice(format!("1 {i}\x02{r}\n").as_bytes());
    }
    hs.extend_from_slice(b"5 0\x02\n");
    w.write_all(&hs).await.unwrap();
    (BufReader::new(r), w)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_input_is_counted_and_never_stalls_sending() {
    let bus = bus();
    let mut opts = IvyOptions::new(bus.clone(), "Target");
    opts.handshake_timeout = Duration::from_millis(500);
    let agent = within("start", IvyAgent::start(opts)).await.unwrap();

    // UDP: a malformed hello, another protocol version, binary garbage.
    let udp = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    udp.set_broadcast(true).unwrap();
    let to = format!("127.255.255.255:{}", bus.port);
    for d in [&b"3 notaport x y\n"[..], b"2 4000\n", b"\x00\xff\xfe garbage", &[b'9'; 4000]] {
        udp.send_to(d, &to).unwrap();
    }
    eventually("hellos counted", || {
        drops(&agent, "hello malformed") == 3 && drops(&agent, "hello of another protocol version") == 1
    })
    .await;

    // TCP: regexes this agent cannot run (look-behind, back-reference, oversize), one made to be
    // slow for backtracking engines, garbage lines and an over-long line.
    let (mut rd, mut wr) =
        raw_peer(&agent, &[r"(?<=x)ATTITUDE", r"^(\S+) \1", r"^(a{1000}){1000}", r"^(a+)+$", r"^(\S*) ATTITUDE (.*)"])
            .await;
    let mut errors = Vec::new();
    let mut line = String::new();
    while errors.len() < 3 {
        line.clear();
        within("error lines", rd.read_line(&mut line)).await.unwrap();
        if line.starts_with("3 ") {
            errors.push(line.clone());
        }
    }
    assert!(errors[0].starts_with("3 0\x02Error compiling"), "{errors:?}");
    assert_eq!(drops(&agent, "peer regex refused"), 3);
    wr.write_all(b"\x00\x01\x02 binary\n2 x\x02\n42 1\x02what\n").await.unwrap();
    wr.write_all(&vec![b'z'; 200_000]).await.unwrap();
    wr.write_all(b"\n9 77\x02\n").await.unwrap();
    // The agent still answers: the Ping after all that gets its Pong.
    loop {
        line.clear();
        within("pong", rd.read_line(&mut line)).await.unwrap();
        if line == "10 77\x02\n" {
            break;
        }
    }
    assert_eq!(drops(&agent, "line too long"), 1);
    assert_eq!(drops(&agent, "line malformed"), 2);
    assert_eq!(drops(&agent, "line of unknown type"), 1);
    // The slow-for-backtracking regex runs in linear time here.
    let t = Instant::now();
    let evil = format!("{}!", "a".repeat(3000));
    agent.send(&evil).unwrap();
    assert!(t.elapsed() < Duration::from_millis(200), "{:?}", t.elapsed());

    // Half-open: a connection that never introduces itself is closed after the timeout.
    let mut idle = within("connect idle", TcpStream::connect(("127.0.0.1", agent.port()))).await.unwrap();
    let mut buf = Vec::new();
    within("idle closed", tokio::io::AsyncReadExt::read_to_end(&mut idle, &mut buf)).await.unwrap();
    assert_eq!(drops(&agent, "connection closed: no handshake in time"), 1);

    // A peer that subscribes everything and never reads: sending never waits, drops are counted.
    let (_rd2, _wr2) = raw_peer(&agent, &[r"^(.*)$"]).await;
    eventually("raw peer regex known", || agent.peers().iter().filter(|p| p.app_name == "raw").count() == 2).await;
    let t = Instant::now();
    let text = format!("5 FILLER {}", "x".repeat(1000));
    for _ in 0..20_000 {
        agent.send(&text).unwrap();
    }
    let took = t.elapsed();
    assert!(took < Duration::from_secs(5), "sending waited: {took:?}");
    assert!(drops(&agent, "peer not reading (queue full)") > 0, "{:?}", agent.drops());
    // Texts Ivy cannot carry are refused, not sent broken.
    assert!(agent.send("5 A b\nc").is_err());
    assert_eq!(agent.counters().peer_regexes.load(Ordering::Relaxed), 6);
}
