//! `twinswarm copter`: a stand-in for a real FINken, so mixed reality can be tested end to end
//! without hardware.
//!
//! It flies its own `sim-core` world, the "reality": the scene's arena and boxes **without**
//! the `virtual_only` ones and without the other copters, one copter, its own seed. Like the
//! firmware, it
//! - publishes its telemetry on the bus as aircraft `--ac-id`, at the periods of a telemetry
//!   plan (default: the embedded `Main/mixed` mode, 22 ms for what drives a twin), timed by
//!   the paper's measured link ([`bridge::mixed::link`]; `--jitter-ms`: every slot, a uniform delay)
//!   and dropped with a loss probability;
//! - receives `SONAR_UPLINK` (the 2015 FINken firmware's) or `VIRTUAL_SONAR`, whichever its
//!   `--messages` defines, for its `ac_id` and fuses it as `min(real, virtual)` into its
//!   own Wall-Avoid; a virtual reading older than [`VIRTUAL_STALE_S`] is ignored.
//!
//! With `--no-bus` it flies alone, as fast as it can (a control run).

use std::io::Write as _;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use bridge::mixed::link::{LinkClock, LinkTiming};
use bridge::mixed::plan::TelemetryPlan;
use bridge::paparazzi::convert::{TELEMETRY_MESSAGES, TelemetrySource, telemetry_text, uplink_readings};
use bridge::wire::{SensorsMsg, StateMsg, sensors_msg, state_msg};
use sim_core::rng::Rng32;
use sim_core::scene::{self, CommandSpec, CopterSpec, StartSpec};
use sim_core::{CopterKind, FlightMode, Setpoint, State, World};
use twinswarm::transport::{self, IvyArgs, NoListen, ZenohArgs, ZenohRole};

use crate::BadInput;

/// A virtual sonar reading older than this is ignored, s.
pub const VIRTUAL_STALE_S: f64 = 0.5;

/// Arguments of `twinswarm copter`.
#[derive(Debug, clap::Args)]
#[command(mut_arg("ivy", |a| a.help(transport::ivy_help(IVY_PURPOSE))))]
#[command(mut_arg("zenoh_config", |a| a.help(transport::zenoh_config_help(ZenohRole::StandIn))))]
pub struct CopterArgs {
    /// The scene whose arena and (non-virtual) boxes are the reality; default: the embedded
    /// FINken lab.
    scene: Option<PathBuf>,
    /// Paparazzi aircraft id to fly as.
    #[arg(long, value_name = "N")]
    ac_id: u8,
    /// Start pose `X,Y,YAW_DEG` (m, m, degrees); default: the pairing's twin pose for this
    /// ac_id, else the scene copter with this ac_id.
    #[arg(long, value_name = "X,Y,YAW", allow_hyphen_values = true)]
    start: Option<String>,
    /// Pairing file, for the start pose.
    #[arg(long, value_name = "FILE.xml")]
    pairing: Option<PathBuf>,
    /// Seed of the reality (default: the scene's seed + 1000 + ac_id).
    #[arg(long, value_name = "N")]
    seed: Option<u64>,
    /// Simulated duration, s (default: the scene's).
    #[arg(long, value_name = "S")]
    duration: Option<f64>,
    /// Height to hold, m.
    #[arg(long, value_name = "M", default_value_t = 0.8)]
    height: f32,
    /// The firmware's messages.xml (default: the embedded assets/paparazzi/messages.xml): its
    /// telemetry goes out in these layouts, and it takes whichever of SONAR_UPLINK and
    /// VIRTUAL_SONAR it defines.
    #[arg(long, value_name = "FILE.xml")]
    messages: Option<PathBuf>,
    /// Velocity to fly when no obstacle is near, body frame `FORWARD,LEFT`, m/s.
    #[arg(long, value_name = "FWD,LEFT", allow_hyphen_values = true)]
    velocity: Option<String>,
    /// A uniform link instead of the measured one: every message on time, up to this late, ms.
    #[arg(long, value_name = "MS")]
    jitter_ms: Option<f64>,
    /// The measured link: copters sharing the radio channel (each slows it a little).
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=16))]
    link_copters: u32,
    /// The measured link, saturated: the telemetry mode asks LOAD times what the modem carries
    /// (e.g. 1.27, the 2015 `vrep` mode on 38,400 baud: docs/real-flights.md). At most 1: the
    /// paper's link.
    #[arg(long, value_name = "LOAD", default_value_t = 1.0)]
    link_load: f64,
    /// Probability that a telemetry message is lost, 0..1.
    #[arg(long, value_name = "P", default_value_t = 0.0)]
    loss: f64,
    /// Paparazzi telemetry file (default: the embedded assets/paparazzi/telemetry.xml).
    #[arg(long, value_name = "FILE.xml")]
    telemetry: Option<PathBuf>,
    /// Mode of the telemetry file (default: its first mode).
    #[arg(long, value_name = "NAME")]
    telemetry_mode: Option<String>,
    /// Fly alone, as fast as possible, without Zenoh (a control run).
    #[arg(long, conflicts_with = "ivy")]
    no_bus: bool,
    /// `--ivy`, `--ivy-bus`: Ivy instead of Zenoh.
    #[command(flatten)]
    ivy: IvyArgs,
    /// `--zenoh-config`, `--connect`, `--prefix`: the stand-in only connects.
    #[command(flatten)]
    zenoh: ZenohArgs<NoListen>,
    /// Write the flown trajectory as CSV (one row per control step).
    #[arg(long, value_name = "FILE.csv")]
    track: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

/// What `copter --ivy` does on the bus.
const IVY_PURPOSE: &str = "Speak Ivy instead of Zenoh, as a real copter behind Paparazzi's `link` would: telemetry as \
                           `<ac_id> <NAME> ...`, VIRTUAL_SONAR bound with link's own regex";

/// The latest virtual sonar readings (front, right, back, left; m) and when they came.
type VirtualReading = ([f32; 4], Instant);

/// What the loop shares with the telemetry senders.
#[derive(Clone, Debug)]
struct Snapshot {
    state: StateMsg,
    sensors: SensorsMsg,
    setpoint: Setpoint,
}

/// The stand-in's summary.
#[derive(Debug, serde::Serialize)]
struct Summary {
    ac_id: u8,
    seed: u64,
    simulated_s: f64,
    steps: u64,
    crashed: Option<String>,
    final_pos_m: [f32; 3],
    telemetry_sent: u64,
    /// Simulated link loss (`--loss`).
    telemetry_lost: u64,
    /// Sends that failed (the link closing, a text the link refused).
    telemetry_send_failed: u64,
    /// `VIRTUAL_SONAR` texts that did not decode.
    virtual_sonar_rejected: u64,
    virtual_sonar_received: u64,
    steps_with_virtual_sonar: u64,
    overruns: u64,
}

fn parse_pair<const N: usize>(text: &str, what: &str) -> anyhow::Result<[f32; N]> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    let bad = || BadInput(anyhow::anyhow!("{what}: expected {N} comma-separated numbers, got {text:?}"));
    if parts.len() != N {
        return Err(bad().into());
    }
    let mut out = [0.0; N];
    for (o, p) in out.iter_mut().zip(&parts) {
        *o = p.parse::<f32>().ok().filter(|v| v.is_finite()).ok_or_else(bad)?;
    }
    Ok(out)
}

/// The reality: the scene without virtual-only boxes and other copters, plus this copter.
fn reality(args: &CopterArgs) -> anyhow::Result<(World, TelemetryPlan)> {
    let (_, mut spec, _) = crate::load_scene(args.scene.as_deref())?;
    let mixed =
        crate::load_mixed(args.pairing.as_deref(), args.telemetry.as_deref(), args.telemetry_mode.as_deref(), 0.0)?;
    let start = match &args.start {
        Some(s) => {
            let [x, y, yaw] = parse_pair::<3>(s, "--start")?;
            StartSpec { pos_m: [x, y], z_m: None, yaw_deg: yaw }
        }
        None => {
            let from_pairing = mixed.pairing.as_ref().and_then(|p| p.by_ac_id.get(&args.ac_id)).map(|a| StartSpec {
                pos_m: [a.pose.x_m as f32, a.pose.y_m as f32],
                z_m: None,
                yaw_deg: a.pose.yaw_rad.to_degrees() as f32,
            });
            let from_scene = || spec.copters.iter().find(|c| c.ac_id == Some(args.ac_id)).map(|c| c.start.clone());
            from_pairing.or_else(from_scene).ok_or_else(|| {
                BadInput(anyhow::anyhow!(
                    "no start pose for ac_id {}: give --start X,Y,YAW or a --pairing that twins it",
                    args.ac_id
                ))
            })?
        }
    };
    let velocity = args.velocity.as_deref().map(|v| parse_pair::<2>(v, "--velocity")).transpose()?;
    if !args.link_load.is_finite() || !(0.0..=10.0).contains(&args.link_load) {
        return Err(BadInput(anyhow::anyhow!("--link-load must be in [0, 10], got {}", args.link_load)).into());
    }
    if !(0.0..=1.0).contains(&args.loss) || args.jitter_ms.is_some_and(|j| !j.is_finite() || j < 0.0) {
        return Err(BadInput(anyhow::anyhow!("--loss must be in [0, 1] and --jitter-ms >= 0")).into());
    }
    spec.boxes.retain(|b| !b.virtual_only);
    spec.sim.seed = args.seed.unwrap_or(spec.sim.seed.wrapping_add(1000 + u64::from(args.ac_id)));
    if let Some(d) = args.duration {
        if !d.is_finite() || d <= 0.0 {
            return Err(BadInput(anyhow::anyhow!("--duration must be a positive number of seconds, got {d}")).into());
        }
        spec.sim.duration_s = d;
    }
    spec.copters = vec![CopterSpec {
        name: format!("ac_{}", args.ac_id),
        kind: CopterKind::Virtual,
        ac_id: Some(args.ac_id),
        airframe: Default::default(),
        start,
        mode: FlightMode::WallAvoid,
        command: CommandSpec { height_m: args.height, velocity_m_s: velocity, ..CommandSpec::default() },
    }];
    let world = scene::compile(&spec).map_err(|e| anyhow::Error::new(BadInput(e.into())))?;
    Ok((world, mixed.plan))
}

/// Runs `twinswarm copter`.
pub fn run(args: CopterArgs) -> anyhow::Result<()> {
    let (world, plan) = reality(&args)?;
    let stop = crate::logcmd::install_stop_flag()?;
    let mut track = match &args.track {
        Some(p) => Some(create_track(p)?),
        None => None,
    };
    let virt: Arc<Mutex<Option<VirtualReading>>> = Arc::new(Mutex::new(None));
    let received = Arc::new(AtomicU64::new(0));
    let mut state = world.initial_state();
    let mut inputs = world.initial_inputs();
    let shared = Arc::new(Mutex::new(snapshot(&world, &state, &inputs)));

    let bus = if args.no_bus { None } else { Some(open_link(&args, &world, &virt, &received)?) };

    // Telemetry senders, one task per message of the plan.
    let tally = SenderTally::default();
    let mut senders = Vec::new();
    if let Some((rt, link)) = &bus {
        senders = spawn_senders(&args, &world, &plan, rt, link, &shared, &tally)?;
    }

    // The flight.
    let realtime = bus.is_some();
    let (overruns, with_virtual) = fly(&world, &mut state, &mut inputs, &virt, &shared, &mut track, &stop, realtime)?;
    tally.done.store(true, Ordering::Relaxed);
    if let Some(w) = &mut track {
        w.flush()?;
    }
    if let Some((rt, link)) = bus {
        for s in &senders {
            s.abort();
        }
        rt.block_on(link.close())?;
    }
    let summary = Summary {
        ac_id: args.ac_id,
        seed: world.params.seed,
        simulated_s: state.time_s(&world),
        steps: state.tick,
        crashed: state.copters[0].crash.map(|c| format!("{c:?}")),
        final_pos_m: state.pose(0).pos_m.to_array(),
        telemetry_sent: tally.sent.load(Ordering::Relaxed),
        telemetry_lost: tally.lost.load(Ordering::Relaxed),
        telemetry_send_failed: tally.send_failed.load(Ordering::Relaxed),
        virtual_sonar_rejected: REJECTED.load(Ordering::Relaxed),
        virtual_sonar_received: received.load(Ordering::Relaxed),
        steps_with_virtual_sonar: with_virtual,
        overruns,
    };
    print_summary(&summary, args.json)?;
    if summary.crashed.is_some() {
        anyhow::bail!("the stand-in crashed: {}", summary.crashed.unwrap_or_default());
    }
    Ok(())
}

/// Creates the `--track` CSV file and writes its header.
fn create_track(path: &std::path::Path) -> anyhow::Result<std::io::BufWriter<std::fs::File>> {
    let f = std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    let mut w = std::io::BufWriter::new(f);
    writeln!(
        w,
        "t_s,x_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad,sonar_front_m,sonar_right_m,sonar_back_m,sonar_left_m,\
         fused_front_m,fused_right_m,fused_back_m,fused_left_m,virtual_fresh"
    )?;
    Ok(w)
}

/// What the telemetry senders count, and the flag that tells them the flight is over.
#[derive(Default)]
struct SenderTally {
    sent: Arc<AtomicU64>,
    send_failed: Arc<AtomicU64>,
    lost: Arc<AtomicU64>,
    done: Arc<AtomicBool>,
}

/// Spawns one telemetry sender on `rt` per message of `plan` the stand-in models: each sends
/// the latest snapshot at its period, timed by the link and dropped with `--loss`.
fn spawn_senders(
    args: &CopterArgs,
    world: &World,
    plan: &TelemetryPlan,
    rt: &tokio::runtime::Runtime,
    link: &Link,
    shared: &Arc<Mutex<Snapshot>>,
    tally: &SenderTally,
) -> anyhow::Result<Vec<tokio::task::JoinHandle<()>>> {
    let mut senders = Vec::new();
    let messages = crate::load_messages(args.messages.as_deref())?;
    for (k, (name, period)) in plan.periods.iter().enumerate() {
        if !TELEMETRY_MESSAGES.contains(&name.as_str()) {
            tracing::warn!("the stand-in cannot send {name} (not modelled)");
            continue;
        }
        let (link, messages, shared) = (link.clone(), messages.clone(), shared.clone());
        let (sent, lost, done, send_failed) =
            (tally.sent.clone(), tally.lost.clone(), tally.done.clone(), tally.send_failed.clone());
        let (name, period) = (name.clone(), Duration::from_secs_f64(*period));
        let (ac_id, loss) = (args.ac_id, args.loss as f32);
        let mut rng = Rng32::new(world.params.seed, 0x7e1e_0000 + k as u64);
        let timing = match args.jitter_ms {
            Some(_) => LinkTiming::from_args(args.jitter_ms, args.link_copters),
            None => LinkTiming::measured_with_load(args.link_copters, args.link_load),
        };
        let mut clock =
            LinkClock::new(period.as_secs_f64(), timing, Rng32::new(world.params.seed, 0x7e1f_0000 + k as u64));
        senders.push(rt.spawn(async move {
            let start = tokio::time::Instant::now();
            while !done.load(Ordering::Relaxed) {
                let due = start + Duration::from_secs_f64(clock.next_s());
                tokio::time::sleep_until(due).await;
                if rng.uniform() < loss {
                    lost.fetch_add(1, Ordering::Relaxed);
                    continue;
                }
                let text = {
                    let s = bridge::lock(&shared);
                    let src = TelemetrySource { state: &s.state, sensors: &s.sensors, setpoint: s.setpoint };
                    telemetry_text(&messages, ac_id, &name, &src)
                };
                match text {
                    Some(Ok(text)) => {
                        if link.send(text).await {
                            sent.fetch_add(1, Ordering::Relaxed);
                        } else {
                            send_failed.fetch_add(1, Ordering::Relaxed);
                        }
                    }
                    Some(Err(e)) => {
                        tracing::warn!("cannot encode {name}: {e}");
                        break;
                    }
                    None => break,
                }
            }
        }));
    }
    Ok(senders)
}

/// Flies the reality until its end, a crash or `stop`, fusing the fresh virtual sonar, sharing
/// each step's snapshot and tracking it; in `realtime`, paced by the wall clock. Returns the
/// overruns and the steps that had a virtual sonar reading.
#[allow(clippy::too_many_arguments)]
fn fly(
    world: &World,
    state: &mut State,
    inputs: &mut sim_core::Inputs,
    virt: &Mutex<Option<VirtualReading>>,
    shared: &Mutex<Snapshot>,
    track: &mut Option<std::io::BufWriter<std::fs::File>>,
    stop: &AtomicBool,
    realtime: bool,
) -> anyhow::Result<(u64, u64)> {
    let dt = Duration::from_secs_f64(world.params.control_dt_s);
    let ticks = world.default_ticks();
    let started = Instant::now();
    let (mut overruns, mut with_virtual) = (0u64, 0u64);
    for k in 0..ticks {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        let fresh =
            (*bridge::lock(virt)).filter(|(_, at)| at.elapsed().as_secs_f64() <= VIRTUAL_STALE_S).map(|(r, _)| r);
        inputs.commands[0].virtual_sonar_m = fresh;
        with_virtual += u64::from(fresh.is_some());
        sim_core::step(world, state, inputs);
        *bridge::lock(shared) = snapshot(world, state, inputs);
        if let Some(w) = track {
            write_track_row(w, world, state, fresh.is_some())?;
        }
        if state.copters[0].crash.is_some() {
            break;
        }
        if realtime {
            let deadline = started + dt * (k as u32 + 1);
            let now = Instant::now();
            if now > deadline {
                overruns += 1;
            } else {
                std::thread::sleep(deadline - now);
            }
        }
    }
    Ok((overruns, with_virtual))
}

/// Writes one row of the `--track` CSV: time, pose, raw and fused sonars, whether a fresh
/// virtual reading was fused.
fn write_track_row(
    w: &mut std::io::BufWriter<std::fs::File>,
    world: &World,
    state: &State,
    fresh: bool,
) -> std::io::Result<()> {
    let p = state.pose(0);
    let r = &state.copters[0].sensors;
    let row: Vec<String> = [state.time_s(world) as f32]
        .into_iter()
        .chain(p.pos_m.to_array())
        .chain(p.rpy_rad)
        .chain(r.sonar_m)
        .chain(r.sonar_fused_m)
        .map(|v| format!("{v:.4}"))
        .collect();
    writeln!(w, "{},{}", row.join(","), u8::from(fresh))
}

/// Prints the summary on stdout: JSON with `--json`, else two lines.
fn print_summary(summary: &Summary, json: bool) -> anyhow::Result<()> {
    if json {
        outln!("{}", serde_json::to_string_pretty(summary)?);
    } else {
        let [x, y, z] = summary.final_pos_m;
        outln!(
            "twinswarm copter: ac_id {} (seed {}), {:.1} s in {} steps, final position ({x:.2}, {y:.2}, {z:.2}) m, {}",
            summary.ac_id,
            summary.seed,
            summary.simulated_s,
            summary.steps,
            summary.crashed.as_deref().unwrap_or("no crash")
        );
        outln!(
            "  telemetry: {} sent, {} lost (simulated), {} failed to send; virtual sonar: {} received ({} undecodable), used in {} steps; {} overruns",
            summary.telemetry_sent,
            summary.telemetry_lost,
            summary.telemetry_send_failed,
            summary.virtual_sonar_received,
            summary.virtual_sonar_rejected,
            summary.steps_with_virtual_sonar,
            summary.overruns
        );
    }
    Ok(())
}

fn snapshot(world: &World, state: &State, inputs: &sim_core::Inputs) -> Snapshot {
    Snapshot {
        state: state_msg(world, state, inputs, 0),
        sensors: sensors_msg(world, state, 0),
        setpoint: state.copters[0].setpoint,
    }
}

/// How the stand-in reaches the simulator: Zenoh keys, or a real Ivy bus.
#[derive(Clone)]
enum Link {
    Zenoh { session: zenoh::Session, prefix: String, _bus: Arc<bridge::zenoh_net::pprz_bus::ZenohBus> },
    Ivy(Arc<bridge::paparazzi::ivy::IvyAgent>),
}

impl Link {
    /// Sends one telemetry text; whether it went out.
    async fn send(&self, text: String) -> bool {
        match self {
            Link::Zenoh { session, prefix, .. } => match bridge::key_for_text(prefix, &text) {
                Ok(key) => session.put(key, text).await.is_ok(),
                Err(_) => false,
            },
            Link::Ivy(agent) => agent.send(&text).is_ok(),
        }
    }

    async fn close(self) -> anyhow::Result<()> {
        match self {
            Link::Zenoh { session, _bus, .. } => {
                drop(_bus);
                session.close().await.map_err(|e| anyhow::anyhow!("{e}")).context("closing the Zenoh session")
            }
            Link::Ivy(agent) => {
                agent.stop().await;
                Ok(())
            }
        }
    }
}

/// Virtual-sonar texts (`SONAR_UPLINK`, `VIRTUAL_SONAR`) this process could not decode (one stand-in per process; the
/// handlers run in Zenoh's and the Ivy agent's callbacks).
static REJECTED: AtomicU64 = AtomicU64::new(0);

/// Records a VIRTUAL_SONAR text for `ac_id`.
fn on_virtual_sonar(
    messages: &bridge::MessageSet,
    text: &str,
    ac_id: u8,
    virt: &Mutex<Option<VirtualReading>>,
    received: &AtomicU64,
) {
    let Some((to, readings)) = messages.decode(text).ok().and_then(|msg| uplink_readings(&msg)) else {
        REJECTED.fetch_add(1, Ordering::Relaxed);
        return;
    };
    // For another aircraft: link forwards every VIRTUAL_SONAR; ours carries our ac_id.
    if to == ac_id {
        received.fetch_add(1, Ordering::Relaxed);
        *bridge::lock(virt) = Some((readings, Instant::now()));
    }
}

/// Opens the bus (Zenoh, or Ivy with `--ivy`) and binds the virtual sonar.
fn open_link(
    args: &CopterArgs,
    world: &World,
    virt: &Arc<Mutex<Option<VirtualReading>>>,
    received: &Arc<AtomicU64>,
) -> anyhow::Result<(tokio::runtime::Runtime, Link)> {
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let messages = crate::load_messages(args.messages.as_deref())?;
    let (virt, received, ac_id) = (virt.clone(), received.clone(), args.ac_id);
    if let Some(addr) = args.ivy.bus()? {
        let opts = bridge::paparazzi::ivy::IvyOptions::new(addr, format!("twinswarm-copter-{ac_id}"));
        let agent = rt.block_on(bridge::paparazzi::ivy::IvyAgent::start(opts)).context("cannot join the Ivy bus")?;
        // Exactly what Paparazzi's link binds for a datalink message it forwards
        // (link.ml: `^([^ ]*) +(NAME( .*|$))`), so the stand-in receives what a real
        // aircraft would.
        // Both uplinks: the original firmware's SONAR_UPLINK and this project's VIRTUAL_SONAR.
        for name in ["SONAR_UPLINK", "VIRTUAL_SONAR"] {
            let (messages, virt, received) = (messages.clone(), virt.clone(), received.clone());
            agent.bind_raw(&format!(r"^([^ ]*) +({name}( .*|$))"), move |g| {
                if let [sender, msg, ..] = g {
                    on_virtual_sonar(&messages, &format!("{sender} {msg}"), ac_id, &virt, &received);
                }
            })?;
        }
        return Ok((rt, Link::Ivy(Arc::new(agent))));
    }
    let config = args.zenoh.config(ZenohRole::StandIn)?;
    let prefix = args.zenoh.prefix.clone().unwrap_or_else(|| bridge::zenoh_net::node::default_prefix(world));
    let session = rt
        .block_on(async { zenoh::open(config).await })
        .map_err(|e| anyhow::anyhow!("{e}"))
        .context("cannot open the Zenoh session")?;
    let bus = bridge::zenoh_net::pprz_bus::ZenohBus::new(session.clone(), prefix.clone());
    for name in ["SONAR_UPLINK", "VIRTUAL_SONAR"] {
        let (messages, virt, received) = (messages.clone(), virt.clone(), received.clone());
        rt.block_on(bus.bind(&format!(r"^\S+ {name} {ac_id} "), move |d, _| {
            on_virtual_sonar(&messages, d.text, ac_id, &virt, &received);
        }))?;
    }
    Ok((rt, Link::Zenoh { session, prefix, _bus: Arc::new(bus) }))
}
