//! `twinswarm replay FLIGHT.data`: plays a real flight's Paparazzi log onto Ivy and Zenoh as
//! `link` delivered it, so a recorded real flight is a real copter for a live `twinswarm run`
//! (as Paparazzi's own log player does).
//!
//! Each message of the `.data` goes out as its Ivy text (`<ac_id> <NAME> <fields…>`), at
//! `start + (t − t_from) / speed` (absolute deadlines, no drift): on the Ivy bus with `--ivy`
//! (the agent `twinswarm-replay`), on Zenoh under `<prefix>/pprz/<sender>/<NAME>` unless
//! `--no-bus`. `--from`/`--to` choose a log-time window; `--ac-id` one aircraft.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use anyhow::Context;
use bridge::paparazzi::flightlog::FlightLog;
use bridge::paparazzi::ivy::{IvyAgent, IvyOptions};
use zenoh::Wait;

use crate::BadInput;
use crate::replay::ReplayArgs;

/// What a replay sent.
#[derive(Debug, Default)]
struct Sent {
    ivy: u64,
    zenoh: u64,
    failed: u64,
}

/// Replays a Paparazzi log (see the module docs).
pub fn run(args: &ReplayArgs) -> anyhow::Result<()> {
    let bad = |m: String| anyhow::Error::new(BadInput(anyhow::anyhow!(m)));
    if !args.speed.is_finite() || args.speed <= 0.0 {
        return Err(bad(format!("--speed must be a positive finite number, got {}", args.speed)));
    }
    if args.foxglove.is_some() {
        return Err(bad("--foxglove serves MCAP logs; `twinswarm log import` turns this log into one".into()));
    }
    let log = FlightLog::open(&args.file).map_err(|e| BadInput(e.into()))?;
    let (t_first, t_last) = log.span_s().ok_or_else(|| bad(format!("{}: no readable message", args.file.display())))?;
    let from = args.from.unwrap_or(t_first);
    let to = args.to.unwrap_or(t_last);
    if !(from.is_finite() && to.is_finite() && from <= to) {
        return Err(bad(format!("--from {from} must not be after --to {to}")));
    }
    let picked: Vec<usize> = (0..log.records.len())
        .filter(|&i| {
            let r = &log.records[i];
            r.time_s >= from && r.time_s <= to && args.ac_id.is_none_or(|a| r.sender.ac_id() == Some(a))
        })
        .collect();
    let stop = crate::logcmd::install_stop_flag()?;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
    let mut bus_name = String::new();
    let ivy = match args.ivy.bus()? {
        None => None,
        Some(addr) => {
            bus_name =
                format!("{}:{}", addr.domains.iter().map(ToString::to_string).collect::<Vec<_>>().join(","), addr.port);
            let agent = rt.block_on(IvyAgent::start(IvyOptions::new(addr, "twinswarm-replay")))?;
            Some(Arc::new(agent))
        }
    };
    let session = if args.no_bus {
        None
    } else {
        let config = args.zenoh.config(crate::transport::ZenohRole::Peer)?;
        Some(zenoh::open(config).wait().map_err(|e| anyhow::anyhow!("{e}")).context("cannot open the Zenoh session")?)
    };
    let prefix = args.zenoh.prefix.clone().unwrap_or_else(|| "twinswarm/paparazzi-log".to_owned());
    if let Some(agent) = &ivy
        && let Some(w) = args.wait_for_subscriber
    {
        // An Ivy peer that binds the telemetry: the texts would otherwise go nowhere.
        let deadline = Instant::now() + Duration::from_secs_f64(w.max(0.0));
        while agent.peers().is_empty() && Instant::now() < deadline && !stop.load(Ordering::Relaxed) {
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    std::thread::sleep(Duration::from_millis(args.start_delay_ms));
    outln!(
        "replay {}: {} messages, log {:.2}-{:.2} s at speed {} ({:.2} s){}{}",
        args.file.display(),
        picked.len(),
        from,
        to,
        args.speed,
        (to - from) / args.speed,
        if ivy.is_some() { format!(", Ivy {bus_name}") } else { String::new() },
        if session.is_some() { format!(", Zenoh prefix {prefix}") } else { String::new() }
    );
    let start = Instant::now();
    let mut sent = Sent::default();
    let mut interrupted = false;
    for &i in &picked {
        let r = &log.records[i];
        let deadline = start + Duration::from_secs_f64((r.time_s - from) / args.speed);
        if !crate::replay::wait_until(&stop, deadline) {
            interrupted = true;
            break;
        }
        let text = log.text(r);
        if let Some(agent) = &ivy {
            match agent.send(text) {
                Ok(_) => sent.ivy += 1,
                Err(_) => sent.failed += 1,
            }
        }
        if let Some(s) = &session {
            let put = bridge::zenoh_net::keyexpr::key_for_text(&prefix, text).map(|key| s.put(key, text).wait());
            match put {
                Ok(Ok(())) => sent.zenoh += 1,
                _ => sent.failed += 1,
            }
        }
    }
    let wall_s = start.elapsed().as_secs_f64();
    std::thread::sleep(Duration::from_millis(200));
    if let Some(s) = session {
        s.close().wait().map_err(|e| anyhow::anyhow!("{e}")).context("closing the Zenoh session")?;
    }
    drop(ivy);
    outln!(
        "  sent {} texts on Ivy, {} on Zenoh, {} failed; {} unreadable lines skipped{}",
        sent.ivy,
        sent.zenoh,
        sent.failed,
        log.errors.total(),
        if interrupted { format!("; interrupted after {wall_s:.2} s wall") } else { format!("; {wall_s:.2} s wall") }
    );
    Ok(())
}
