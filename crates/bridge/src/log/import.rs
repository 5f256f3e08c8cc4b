//! A real flight's Paparazzi log as an MCAP log ([`import_flight`]), so Foxglove, `twinswarm
//! plot` and `log info` read it as they read a run.
//!
//! - every message the log holds on `/pprz/<sender>/<NAME>` (its Ivy text) and
//!   `/pprz/<sender>/<NAME>/decoded` (its fields, by the log's own definitions), at its recorded
//!   time: `log_time = time_of_day + t`;
//! - the aircraft as copter 0 (`kind` `real`): `/copters/sensors` for each sonar or IR message
//!   (sonars, IR, the attitude it carries; `sonar_m` empty for a message without sonars, such
//!   as `FINKEN_IR_ADC`), `/copters/state` for each attitude: the AHRS's (`AHRS_EULER_INT`,
//!   `ATTITUDE`), or, in a telemetry mode that sends no AHRS message (`default`), the attitude
//!   `FINKEN_SENSOR_MODEL` carries, as [`Series::of`] reads it. A FINken has no positioning:
//!   `pos_m` is `[NaN, NaN, IR height]`, and the metadata says so;
//! - the `twinswarm` metadata record a run has, with the arena its sonars describe
//!   ([`crate::realflight::derive_arena`]) and a `paparazzi_log` record (source, aircraft,
//!   unreadable lines).

use std::collections::BTreeMap;
use std::path::Path;

use mcap::records::{MessageHeader, Metadata};
use prost::Message as _;
use serde::Serialize;

use super::encode::schema_data;
use super::mcap_out::McapOut;
use super::pprz::PprzChannels;
use super::proto::{CopterSensors, CopterState};
use super::writer::LogError;
use crate::ids::AcId;
use crate::paparazzi::flightlog::FlightLog;
use crate::realflight::{Flight, Series};

/// What an import wrote.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ImportStats {
    /// Paparazzi messages (each as text and decoded).
    pub pprz_messages: u64,
    /// `/copters/state` messages.
    pub states: u64,
    /// `/copters/sensors` messages.
    pub sensors: u64,
    /// The flights found.
    pub flights: Vec<Flight>,
    /// The arena written into the metadata, m.
    pub arena_size_m: [f32; 2],
}

/// Writes `log` as an MCAP log at `out`, with aircraft `ac_id` as the copter.
pub fn import_flight(log: &FlightLog, ac_id: AcId, out: &Path, command_line: &str) -> Result<ImportStats, LogError> {
    let create = |source| LogError::Create { path: out.to_path_buf(), source };
    let write = |source| LogError::Write { path: out.to_path_buf(), source };
    let file = std::fs::File::create(out).map_err(create)?;
    let mut mcap = McapOut::create(file, 3, 1 << 20).map_err(create)?;
    let series = Series::of(log, ac_id);
    // Where the attitude comes from: the AHRS messages, or where the log has none (the `default`
    // telemetry mode), the sensor messages, as `Series::of` reads it.
    let ahrs = log.from_aircraft(ac_id).any(|r| !Series::of_record(log, r).attitude.is_empty());
    let flights = crate::realflight::flights(&series);
    let whole = log.span_s().map(|(a, b)| vec![Flight { start_s: a, end_s: b }]).unwrap_or_default();
    let offset = sim_core::sensors::SonarSpec::default().mount_offset_m;
    let arena = crate::realflight::derive_arena(&series, if flights.is_empty() { &whole } else { &flights }, offset);
    let arena_size_m = arena.as_ref().map_or([4.0, 3.0], |a| a.size_m);
    let epoch_ns = log.config.time_of_day.map_or(0, |t| (t * 1e9) as u64);
    let at = |t: f64| epoch_ns.saturating_add((t.max(0.0) * 1e9) as u64);
    mcap.write_metadata(&metadata(log, ac_id, arena_size_m, epoch_ns, command_line, ahrs)).map_err(write)?;
    let name = log.config.aircraft(ac_id).map_or_else(|| format!("ac{ac_id}"), |a| a.name.clone());
    let mut stats = ImportStats { flights, arena_size_m, ..ImportStats::default() };
    let mut pprz = PprzChannels::with_messages(log.config.messages.clone());
    let state_ch = channel(&mut mcap, "twinswarm.CopterState", "/copters/state").map_err(write)?;
    let sensors_ch = channel(&mut mcap, "twinswarm.CopterSensors", "/copters/sensors").map_err(write)?;
    let mut ir = f32::NAN;
    for (tick, r) in log.records.iter().enumerate() {
        let t = at(r.time_s);
        let key = format!("paparazzi-log/pprz/{}", log.text(r).split(' ').take(2).collect::<Vec<_>>().join("/"));
        pprz.write(&mut mcap, tick as u64, t, t, &key, "in", log.text(r)).map_err(write)?;
        if r.sender.ac_id() != Some(ac_id) {
            continue;
        }
        let one = Series::of_record(log, r);
        let header =
            |channel_id, seq: u64| MessageHeader { channel_id, sequence: seq as u32, log_time: t, publish_time: t };
        for s in &one.sensors {
            ir = s.ir_m.unwrap_or(ir);
            let msg = CopterSensors {
                tick: tick as u64,
                t_s: r.time_s,
                copter: name.clone(),
                sonar_tick: tick as u64,
                sonar_m: s.sonar_m.map(|v| v.to_vec()).unwrap_or_default(),
                ir_m: s.ir_m,
                attitude_rad: s.rpy_rad.map(|v| v.to_vec()).unwrap_or_default(),
                ..CopterSensors::default()
            };
            mcap.write_to_known_channel(&header(sensors_ch, stats.sensors), &msg.encode_to_vec()).map_err(write)?;
            stats.sensors += 1;
        }
        let attitude = if ahrs { &one.attitude } else { &one.sensors };
        for s in attitude.iter().filter(|s| s.rpy_rad.is_some()) {
            let msg = CopterState {
                tick: tick as u64,
                t_s: r.time_s,
                copter: name.clone(),
                ac_id: Some(u32::from(ac_id)),
                kind: "real".into(),
                mode: "paparazzi".into(),
                pos_m: vec![f32::NAN, f32::NAN, ir],
                rpy_rad: s.rpy_rad.map(|v| v.to_vec()).unwrap_or_default(),
                ..CopterState::default()
            };
            mcap.write_to_known_channel(&header(state_ch, stats.states), &msg.encode_to_vec()).map_err(write)?;
            stats.states += 1;
        }
    }
    stats.pprz_messages = pprz.written;
    mcap.finish().map_err(write)?;
    Ok(stats)
}

fn channel(mcap: &mut McapOut, schema: &str, topic: &str) -> std::io::Result<u16> {
    let id = mcap.add_schema(schema, "protobuf", &schema_data(schema).unwrap_or_default())?;
    mcap.add_channel(id, topic, "protobuf", &BTreeMap::new())
}

fn metadata(log: &FlightLog, ac_id: AcId, arena: [f32; 2], epoch_ns: u64, command_line: &str, ahrs: bool) -> Metadata {
    let a = log.config.aircraft(ac_id);
    let name = a.map_or_else(|| format!("ac{ac_id}"), |a| a.name.clone());
    let copters = serde_json::json!([{ "id": 0, "name": name, "kind": "real", "ac_id": ac_id }]);
    let mut m = BTreeMap::new();
    let mut put = |k: &str, v: String| {
        m.insert(k.to_owned(), v);
    };
    put("version", env!("CARGO_PKG_VERSION").to_owned());
    put("command_line", command_line.to_owned());
    put("scene_origin", format!("paparazzi log {}", log.data_source));
    put("world", name);
    put("copters", copters.to_string());
    put("boxes", "[]".into());
    put("arena_size_m", serde_json::json!(arena).to_string());
    put("arena_height_m", "2.5".into());
    put("control_dt_s", "0.05".into());
    put("epoch_unix_ns", epoch_ns.to_string());
    put("epoch_utc", super::format_utc_iso(epoch_ns));
    put(
        "time",
        "log_time = epoch_unix_ns + the message's time in the Paparazzi log (epoch: its time_of_day); tick: the \
         message's index in the log"
            .into(),
    );
    let attitude = if ahrs {
        "/copters/state rpy_rad: the AHRS (AHRS_EULER_INT, ATTITUDE)"
    } else {
        "/copters/state rpy_rad: FINKEN_SENSOR_MODEL pos_roll, pos_pitch, pos_yaw (the log has no AHRS message)"
    };
    put(
        "paparazzi_log",
        serde_json::json!({
            "data": log.data_source,
            "log": log.config.source,
            "ac_id": ac_id,
            "airframe": a.map(|a| a.airframe_file.clone()),
            "telemetry": a.map(|a| a.telemetry_file.clone()),
            "lines": log.lines,
            "unreadable": log.errors,
            "arena": "derived from the sonars (bridge::realflight::derive_arena)",
            "position": "unknown: a FINken has no positioning; /copters/state pos_m is [NaN, NaN, IR height]",
            "attitude": attitude,
            "sonars": "/copters/sensors sonar_m (front, right, back, left); empty: none in the message (FINKEN_IR_ADC)",
        })
        .to_string(),
    );
    Metadata { name: "twinswarm".into(), metadata: m }
}
