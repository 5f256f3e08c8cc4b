//! The simulator ↔ Paparazzi mapping: real copters' telemetry into twin commands, virtual sonar
//! readings back, and virtual copters' own telemetry, all in the Ivy text form of the project's
//! `assets/paparazzi/messages.xml`.
//!
//! **Frames.** Paparazzi's body frame is FRD and its attitude NED (`theta > 0` nose up,
//! `psi` clockwise). The simulator's body frame is FLU with ZYX Euler (`pitch > 0` nose down,
//! yaw counter-clockwise from +x). With the arena's +x as Paparazzi's north and +y as its west:
//! `roll = phi`, `pitch = −theta`, `yaw = −psi`. Positions: `north = x`, `east = −y`, `up = z`.

use sim_core::Setpoint;

use crate::paparazzi::codec::{CodecError, Message, Sender, encode};
use crate::paparazzi::messages::{BaseType, FieldDef, MessageDef, MessageSet};
use crate::paparazzi::value::Value;
use crate::wire::{CommandMsg, SensorsMsg, StateMsg};

/// The project's own message definitions (FINken telemetry, `ATTITUDE`, `ROTORCRAFT_FP`,
/// `VIRTUAL_SONAR`).
pub const MESSAGES_XML: &str = include_str!("../../../../assets/paparazzi/messages.xml");

/// Parses [`MESSAGES_XML`].
pub fn project_messages() -> MessageSet {
    match MessageSet::parse(MESSAGES_XML, "assets/paparazzi/messages.xml") {
        Ok(m) => m,
        // Checked by a test; reaching this is a build defect.
        Err(e) => panic!("the embedded messages.xml is invalid: {e}"),
    }
}

/// A real copter's own sonar readings (front, right, back, left), m, from `SONAR_ARRAY` or
/// `FINKEN_SENSOR_MODEL` (whose field for the right sonar is spelled `distance_d_rigth`);
/// `u16::MAX` (no echo) is `INFINITY`.
pub fn real_sonar(msg: &Message<'_>) -> Option<[f32; 4]> {
    let names: [&str; 4] = match msg.def.name.as_str() {
        "SONAR_ARRAY" => ["sonar_front", "sonar_right", "sonar_back", "sonar_left"],
        "FINKEN_SENSOR_MODEL" => ["distance_d_front", "distance_d_rigth", "distance_d_back", "distance_d_left"],
        _ => return None,
    };
    let mut out = [f32::INFINITY; 4];
    for (o, n) in out.iter_mut().zip(names) {
        let cm = msg.get(n).and_then(Value::as_f64)?;
        if cm < f64::from(NO_OBSTACLE_CM) {
            *o = cm as f32 / 100.0;
        }
    }
    Some(out)
}

/// A real copter's yaw estimate in the simulator's frame (counter-clockwise from +x), rad,
/// from `ATTITUDE.psi`, `FINKEN_SENSOR_MODEL.pos_yaw` or `AHRS_EULER_INT.body_psi` (NED,
/// clockwise).
pub fn real_yaw(msg: &Message<'_>) -> Option<f32> {
    match msg.def.name.as_str() {
        "ATTITUDE" => f(msg, "psi"),
        "FINKEN_SENSOR_MODEL" => f(msg, "pos_yaw"),
        "AHRS_EULER_INT" => display_value(msg, "body_psi").map(f32::to_radians),
        _ => None,
    }
    .map(|p| wrap(-p))
}

/// Sonar value meaning "no virtual obstacle in range" in `VIRTUAL_SONAR`.
pub const NO_OBSTACLE_CM: u16 = u16::MAX;

fn f(msg: &Message<'_>, field: &str) -> Option<f32> {
    msg.get(field).and_then(Value::as_f64).map(|v| v as f32).filter(|v| v.is_finite())
}

/// The unit of `FINKEN_IR_ADC.ir_distance` where its definition gives none: metres. The FINken
/// firmware sends metres (`finken_ir_adc.c`: "in meters!", a lookup table of 0.20-1.30 m,
/// clamped), and every real log shows it: the values agree with `FINKEN_SENSOR_MODEL.pos_z`,
/// the same height ([`crate::realflight::ir_unit_check`]). The fork's definition says
/// `alt_unit="cm"`, which is Paparazzi's display unit, not the unit of the value.
pub const IR_DISTANCE_UNIT: &str = "m";

/// Metres in one `unit` of length (`m`, `dm`, `cm`, `mm`); `None` for any other.
pub fn metres_per(unit: &str) -> Option<f64> {
    match unit.trim() {
        "m" => Some(1.0),
        "dm" => Some(0.1),
        "cm" => Some(0.01),
        "mm" => Some(0.001),
        _ => None,
    }
}

/// The unit a field's transmitted values are in: its definition's `unit` where it gives one,
/// else `default`. Never its `alt_unit`: that is the unit Paparazzi displays it in, reached by
/// `alt_unit_coef`.
pub fn value_unit<'a>(field: Option<&'a FieldDef>, default: &'a str) -> &'a str {
    field.and_then(|f| f.unit.as_deref()).map(str::trim).filter(|u| !u.is_empty()).unwrap_or(default)
}

/// Metres per transmitted unit of `FINKEN_IR_ADC.ir_distance` in `def` (a `FINKEN_IR_ADC`):
/// its `unit`, else [`IR_DISTANCE_UNIT`]; `None` where that unit is not a length (read as
/// nothing rather than guessed).
pub fn ir_distance_metres_per(def: &MessageDef) -> Option<f64> {
    metres_per(value_unit(def.field("ir_distance"), IR_DISTANCE_UNIT))
}

/// What a real copter's telemetry message says about how to drive its twin, if anything.
///
/// - `FINKEN_ACTUATORS_SET_POINT` (deg, %): attitude targets and throttle;
/// - `FINKEN_SENSOR_MODEL`: `pos_z` (m, the IR height) the height to hold; where the lab's
///   definition has them (the 2015 fork's), `pos_roll`, `pos_pitch`, `pos_yaw` (rad, the AHRS);
/// - `FINKEN_IR_ADC` `ir_distance` (in its definition's `unit`, else metres: see
///   [`IR_DISTANCE_UNIT`]): the height to hold;
/// - `ATTITUDE` (rad) and `AHRS_EULER_INT` (`body_phi`, `body_theta`, `body_psi`, fixed point
///   scaled by the definitions' `alt_unit_coef`, deg): the measured attitude;
/// - `ROTORCRAFT_FP` (fixed point): attitude, the height (`up`) and the throttle (`thrust` out
///   of Paparazzi's `MAX_PPRZ`, 9600).
///
/// Which of them drives the twin when several speak is the gateway's choice
/// ([`crate::mixed::interpreter::Interpreter`]).
pub fn twin_command(msg: &Message<'_>) -> Option<CommandMsg> {
    let rad_ned = |roll: Option<f32>, pitch: Option<f32>, yaw: Option<f32>| CommandMsg {
        roll,
        pitch: pitch.map(|t| -t),
        yaw: yaw.map(|p| wrap(-p)),
        ..CommandMsg::default()
    };
    let deg = |field: &str| display_value(msg, field).map(f32::to_radians);
    let cmd = match msg.def.name.as_str() {
        "FINKEN_ACTUATORS_SET_POINT" => CommandMsg {
            pitch: f(msg, "pitch").map(|d| -d.to_radians()),
            roll: f(msg, "roll").map(f32::to_radians),
            yaw: f(msg, "yaw").map(|d| crate::paparazzi::convert::wrap(-d.to_radians())),
            throttle: f(msg, "thrust").map(|p| (p / 100.0).clamp(0.0, 1.0)),
            ..CommandMsg::default()
        },
        "FINKEN_SENSOR_MODEL" => CommandMsg {
            height: f(msg, "pos_z").filter(|z| *z > 0.0),
            ..rad_ned(f(msg, "pos_roll"), f(msg, "pos_pitch"), f(msg, "pos_yaw"))
        },
        "FINKEN_IR_ADC" => CommandMsg {
            height: ir_distance_metres_per(msg.def)
                .and_then(|per| f(msg, "ir_distance").map(|v| (f64::from(v) * per) as f32))
                .filter(|z| *z > 0.0 && z.is_finite()),
            ..CommandMsg::default()
        },
        "ATTITUDE" => rad_ned(f(msg, "phi"), f(msg, "theta"), f(msg, "psi")),
        "AHRS_EULER_INT" => rad_ned(deg("body_phi"), deg("body_theta"), deg("body_psi")),
        "ROTORCRAFT_FP" => CommandMsg {
            height: display_value(msg, "up").filter(|z| *z > 0.0),
            throttle: f(msg, "thrust").map(|t| (t / MAX_PPRZ).clamp(0.0, 1.0)),
            ..rad_ned(deg("phi"), deg("theta"), deg("psi"))
        },
        _ => return None,
    };
    (cmd != CommandMsg::default()).then_some(cmd)
}

/// Paparazzi's full-scale command (`MAX_PPRZ`): `ROTORCRAFT_FP.thrust` counts in it.
pub const MAX_PPRZ: f32 = 9600.0;

fn wrap(a: f32) -> f32 {
    sim_core::math::wrap_angle_rad(a)
}

fn cm(m: f32) -> u16 {
    if !m.is_finite() || m < 0.0 { NO_OBSTACLE_CM } else { (m * 100.0).floor().min(65_534.0) as u16 }
}

/// How a twin's virtual sonar readings reach its real aircraft: the datalink message its
/// firmware understands, which its `messages.xml` defines (Paparazzi's `link` forwards only
/// those, and drops the rest silently).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Uplink {
    /// `SONAR_UPLINK` (datalink id 153 in the FINken mixed-reality fork, 2015): `ac_id`,
    /// `unused` (255), `front`, `left`, `back`, `right` in cm, sent as the original Java bridge
    /// did, `dl SONAR_UPLINK <ac_id> 255 <front> <left> <back> <right>`.
    SonarUplink,
    /// `VIRTUAL_SONAR` (this project's `messages.xml`): `ac_id`, `front_cm`, `right_cm`,
    /// `back_cm`, `left_cm`, from `ground_dl`.
    VirtualSonar,
    /// Nothing: the aircraft's `messages.xml` defines neither.
    None,
}

impl Uplink {
    /// The uplink a `messages.xml` defines: `SONAR_UPLINK` if its datalink class has it, else
    /// `VIRTUAL_SONAR`, else none.
    pub fn defined_by(messages: &MessageSet) -> Uplink {
        let has = |name: &str| messages.by_class_and_name("datalink", name).is_some();
        if has("SONAR_UPLINK") {
            Uplink::SonarUplink
        } else if has("VIRTUAL_SONAR") {
            Uplink::VirtualSonar
        } else {
            Uplink::None
        }
    }

    /// Parses `sonar_uplink`, `virtual_sonar` or `none`.
    pub fn parse(s: &str) -> Result<Uplink, String> {
        match s {
            "sonar_uplink" | "SONAR_UPLINK" => Ok(Uplink::SonarUplink),
            "virtual_sonar" | "VIRTUAL_SONAR" => Ok(Uplink::VirtualSonar),
            "none" => Ok(Uplink::None),
            _ => Err(format!("expected `sonar_uplink`, `virtual_sonar` or `none`, got `{s}`")),
        }
    }

    /// The message name, if any.
    pub fn message(self) -> Option<&'static str> {
        match self {
            Uplink::SonarUplink => Some("SONAR_UPLINK"),
            Uplink::VirtualSonar => Some("VIRTUAL_SONAR"),
            Uplink::None => None,
        }
    }

    /// The Ivy sender it goes out as.
    pub fn sender(self) -> &'static str {
        match self {
            Uplink::SonarUplink => "dl",
            _ => "ground_dl",
        }
    }
}

/// `SONAR_UPLINK`'s "no virtual obstacle", cm: the MB1232's longest reading, so that the
/// firmware's `min(real, virtual)` keeps the real one whatever integer type it stores.
pub const SONAR_UPLINK_NONE_CM: u16 = 765;

/// The uplink text for a real aircraft: virtual readings (front, right, back, left), m;
/// `INFINITY` for "nothing virtual in range". `Ok(None)` for [`Uplink::None`].
pub fn uplink_text(
    messages: &MessageSet,
    uplink: Uplink,
    ac_id: u8,
    readings_m: [f32; 4],
) -> Result<Option<String>, CodecError> {
    match uplink {
        Uplink::None => Ok(None),
        Uplink::VirtualSonar => virtual_sonar_text(messages, ac_id, readings_m).map(Some),
        Uplink::SonarUplink => {
            let [front, right, back, left] = readings_m.map(|m| cm(m).min(SONAR_UPLINK_NONE_CM));
            let values = [ac_id, 255].map(Value::U8).into_iter().chain([front, left, back, right].map(Value::U16));
            let def = messages
                .by_class_and_name("datalink", "SONAR_UPLINK")
                .ok_or_else(|| CodecError::UnknownMessage { name: "SONAR_UPLINK".to_owned() })?;
            encode(&Sender::Agent("dl".to_owned()), def, &values.collect::<Vec<_>>()).map(Some)
        }
    }
}

/// `VIRTUAL_SONAR` for a real aircraft: virtual readings (front, right, back, left), m;
/// `INFINITY` for "nothing virtual in range".
pub fn virtual_sonar_text(messages: &MessageSet, ac_id: u8, readings_m: [f32; 4]) -> Result<String, CodecError> {
    let mut values = vec![Value::U8(ac_id)];
    values.extend(readings_m.iter().map(|&m| Value::U16(cm(m))));
    let def = messages
        .by_class_and_name("datalink", "VIRTUAL_SONAR")
        .or_else(|| messages.by_name("VIRTUAL_SONAR"))
        .ok_or_else(|| CodecError::UnknownMessage { name: "VIRTUAL_SONAR".to_owned() })?;
    crate::paparazzi::codec::encode(&Sender::ground_dl(), def, &values)
}

/// Reads a `SONAR_UPLINK` or `VIRTUAL_SONAR` message back into metres (front, right, back,
/// left; `INFINITY` for no obstacle).
pub fn uplink_readings(msg: &Message<'_>) -> Option<(u8, [f32; 4])> {
    if msg.def.name != "SONAR_UPLINK" {
        return virtual_sonar_readings(msg);
    }
    readings_m(msg, ["front", "right", "back", "left"], SONAR_UPLINK_NONE_CM)
}

/// Reads a `VIRTUAL_SONAR` message back into metres (`INFINITY` for no obstacle).
pub fn virtual_sonar_readings(msg: &Message<'_>) -> Option<(u8, [f32; 4])> {
    if msg.def.name != "VIRTUAL_SONAR" {
        return None;
    }
    readings_m(msg, ["front_cm", "right_cm", "back_cm", "left_cm"], NO_OBSTACLE_CM)
}

/// `ac_id` and the four fields `names` (cm) in metres, `INFINITY` from `none_cm` up.
fn readings_m(msg: &Message<'_>, names: [&str; 4], none_cm: u16) -> Option<(u8, [f32; 4])> {
    let ac = msg.get("ac_id").and_then(Value::as_f64)? as u8;
    let mut out = [f32::INFINITY; 4];
    for (o, name) in out.iter_mut().zip(names) {
        let v = msg.get(name).and_then(Value::as_f64)?;
        if v < f64::from(none_cm) {
            *o = v as f32 / 100.0;
        }
    }
    Some((ac, out))
}

/// What a copter's telemetry is made of: its state, its latest sensor readings and what its
/// outer loop asks of its attitude and thrust controllers.
#[derive(Clone, Copy, Debug)]
pub struct TelemetrySource<'a> {
    /// State (true pose; the telemetry of a simulated copter reports its truth).
    pub state: &'a StateMsg,
    /// Latest sensor readings.
    pub sensors: &'a SensorsMsg,
    /// Attitude and thrust set points of the outer loop.
    pub setpoint: Setpoint,
}

/// The telemetry messages [`telemetry_text`] can produce.
pub const TELEMETRY_MESSAGES: [&str; 9] = [
    "FINKEN_ACTUATORS_SET_POINT",
    "FINKEN_IR_ADC",
    "FINKEN_SENSOR_MODEL",
    "SONAR_ARRAY",
    "ATTITUDE",
    "ROTORCRAFT_FP",
    "ALIVE",
    "INS_REF",
    "ROTORCRAFT_STATUS",
];

/// The arena's origin on Earth, for `INS_REF`: latitude and longitude (degrees, WGS84) and
/// height above mean sea level (m). Paparazzi's server places `ROTORCRAFT_FP` positions (local
/// north, east, up) relative to it. This is the FINken lab at Otto von Guericke University
/// Magdeburg; the lab's flight plan for its virtual aircraft must use the same `lat0`/`lon0`
/// (see `docs/paparazzi_ground.md`).
pub const ARENA_ORIGIN_LLA: (f64, f64, f64) = (52.139_86, 11.645_48, 50.0);

/// WGS84 geodetic → ECEF, m.
fn ecef_of(lat_deg: f64, lon_deg: f64, h_m: f64) -> [f64; 3] {
    const A: f64 = 6_378_137.0;
    const E2: f64 = 6.694_379_990_14e-3;
    let (lat, lon) = (lat_deg.to_radians(), lon_deg.to_radians());
    let n = A / (1.0 - E2 * lat.sin().powi(2)).sqrt();
    [(n + h_m) * lat.cos() * lon.cos(), (n + h_m) * lat.cos() * lon.sin(), (n * (1.0 - E2) + h_m) * lat.sin()]
}

/// `ALIVE` with an all-zero md5: Paparazzi's server accepts it with a warning ("MD5 is ZERO"),
/// since a simulated aircraft has no built configuration to sign.
fn alive_text(messages: &MessageSet, ac_id: u8) -> Result<String, CodecError> {
    let def = messages.by_name("ALIVE").ok_or_else(|| CodecError::UnknownMessage { name: "ALIVE".to_owned() })?;
    crate::paparazzi::codec::encode(&Sender::Aircraft(ac_id), def, &[Value::Array(vec![Value::U8(0); 16])])
}

/// The value of a field in its transmitted unit: `display / alt_unit_coef`, cast to the
/// field's type (saturating; integers rounded towards zero).
fn wire_value(field: &FieldDef, display: f64) -> Value {
    let v = field.alt_unit_coef.filter(|c| *c != 0.0).map_or(display, |c| display / c);
    let v = if v.is_finite() { v } else { 0.0 };
    match field.ty.base() {
        BaseType::Int8 => Value::I8(v as i8),
        BaseType::Uint8 => Value::U8(v as u8),
        BaseType::Int16 => Value::I16(v as i16),
        BaseType::Uint16 => Value::U16(v as u16),
        BaseType::Int32 => Value::I32(v as i32),
        BaseType::Uint32 => Value::U32(v as u32),
        BaseType::Int64 => Value::I64(v as i64),
        BaseType::Uint64 => Value::U64(v as u64),
        BaseType::Double => Value::F64(v),
        _ => Value::F32(v as f32),
    }
}

/// The value of a field in its display unit (`alt_unit_coef × transmitted`).
fn display_value(msg: &Message<'_>, field: &str) -> Option<f32> {
    let coef = msg.def.field(field).and_then(|f| f.alt_unit_coef).unwrap_or(1.0);
    msg.get(field).and_then(Value::as_f64).map(|v| (v * coef) as f32).filter(|v| v.is_finite())
}

/// Encodes message `name` from `ac_id` with each field's display value from `value_of`; the
/// field layout comes from the definitions, never from here. A field `value_of` does not know
/// is an error.
fn encode_by_field(
    messages: &MessageSet,
    ac_id: u8,
    name: &str,
    value_of: impl Fn(&str) -> Option<f64>,
) -> Result<String, CodecError> {
    let def = messages.by_name(name).ok_or_else(|| CodecError::UnknownMessage { name: name.to_owned() })?;
    let mut values = Vec::with_capacity(def.fields.len());
    for f in &def.fields {
        let v = value_of(&f.name).ok_or_else(|| CodecError::Unencodable {
            message: name.to_owned(),
            field: f.name.clone(),
            reason: "the simulator has no value for this field",
        })?;
        values.push(wire_value(f, v));
    }
    crate::paparazzi::codec::encode(&Sender::Aircraft(ac_id), def, &values)
}

/// The firmware's `distance_diff_*` of two opposite sonar readings, cm: each clamped to
/// 20–300 cm and capped at the 120 cm goal distance, `a − b`.
fn diff_cm(a: f64, b: f64) -> f64 {
    let side = |d: f64| d.clamp(20.0, 300.0).min(120.0);
    side(a) - side(b)
}

/// The Ivy text of telemetry message `name` for aircraft `ac_id`, from `src`; `None` for a
/// message the simulator cannot produce (see [`TELEMETRY_MESSAGES`]).
///
/// Units are the messages' display units (`alt_unit`) but for `FINKEN_IR_ADC.ir_distance`, sent
/// in its definition's `unit` (else metres, [`IR_DISTANCE_UNIT`]) as the firmware sends it;
/// frames are converted to Paparazzi's (see the module docs). What is not modelled is sent as
/// 0: `FINKEN_IR_ADC.ir_measurement` (the raw ADC count) and the `carrot_*` fields of
/// `ROTORCRAFT_FP`.
pub fn telemetry_text(
    messages: &MessageSet,
    ac_id: u8,
    name: &str,
    src: &TelemetrySource<'_>,
) -> Option<Result<String, CodecError>> {
    let st = src.state;
    let se = src.sensors;
    let sp = src.setpoint;
    // The attitude the copter reports is its AHRS's (bias, noise and all), as a real FINken's
    // is; its position is the truth (a FINken has no horizontal position estimate of its own),
    // its height the IR estimate.
    let [roll, pitch, yaw] = se.attitude_rad.map(f64::from);
    let (phi, theta, psi) = (roll, -pitch, f64::from(wrap(-yaw as f32)));
    let [x, y, z] = st.pos_m.map(f64::from);
    let [vx, vy, vz] = st.vel_m_s.map(f64::from);
    let sonar = [se.sonar_m.front, se.sonar_m.right, se.sonar_m.back, se.sonar_m.left].map(|m| f64::from(cm(m)));
    let ir_m = se.ir_m.map_or(0.0, f64::from);
    // ir_distance in its own unit, in the display form `wire_value` expects (× alt_unit_coef).
    let ir_def = messages.by_name("FINKEN_IR_ADC");
    let ir_per_m = ir_def.and_then(ir_distance_metres_per);
    let ir_coef = ir_def.and_then(|d| d.field("ir_distance")).and_then(|f| f.alt_unit_coef).unwrap_or(1.0);
    let thrust_n: f32 = st.rotor_thrust_n.iter().sum();
    let [gx, gy, gz] = se.rate_body_rad_s.map(f64::from);
    let [ax, ay, az] = se.accel_body_m_s2.map(f64::from);
    let ecef = ecef_of(ARENA_ORIGIN_LLA.0, ARENA_ORIGIN_LLA.1, ARENA_ORIGIN_LLA.2);
    let value_of = |field: &str| -> Option<f64> {
        Some(match (name, field) {
            ("FINKEN_ACTUATORS_SET_POINT", "pitch") => -f64::from(sp.pitch_rad).to_degrees(),
            ("FINKEN_ACTUATORS_SET_POINT", "roll") => f64::from(sp.roll_rad).to_degrees(),
            ("FINKEN_ACTUATORS_SET_POINT", "yaw") => -f64::from(sp.yaw_rad).to_degrees(),
            ("FINKEN_ACTUATORS_SET_POINT", "thrust") => f64::from(sp.throttle) * 100.0,
            ("FINKEN_IR_ADC", "ir_distance") => ir_m / ir_per_m? * ir_coef,
            ("FINKEN_IR_ADC", "ir_measurement") => 0.0,
            ("SONAR_ARRAY", "sonar_front") | ("FINKEN_SENSOR_MODEL", "distance_d_front") => sonar[0],
            ("SONAR_ARRAY", "sonar_right") | ("FINKEN_SENSOR_MODEL", "distance_d_rigth") => sonar[1],
            ("SONAR_ARRAY", "sonar_back") | ("FINKEN_SENSOR_MODEL", "distance_d_back") => sonar[2],
            ("SONAR_ARRAY", "sonar_left") | ("FINKEN_SENSOR_MODEL", "distance_d_left") => sonar[3],
            // The firmware's sign and clamp (`finken_sonar_filter`): readings held to
            // 20–300 cm, each side capped at the 120 cm goal distance; x = back − front,
            // y = right − left. (The firmware averages three readings first; these are the
            // latest readings.)
            ("FINKEN_SENSOR_MODEL", "distance_diff_x") => diff_cm(sonar[2], sonar[0]),
            ("FINKEN_SENSOR_MODEL", "distance_diff_y") => diff_cm(sonar[1], sonar[3]),
            ("FINKEN_SENSOR_MODEL", "pos_x") => x,
            ("FINKEN_SENSOR_MODEL", "pos_y") => y,
            ("FINKEN_SENSOR_MODEL", "pos_z") => f64::from(se.height_est_m),
            ("FINKEN_SENSOR_MODEL", "pos_pitch") | ("ATTITUDE" | "ROTORCRAFT_FP", "theta") => theta,
            ("FINKEN_SENSOR_MODEL", "pos_roll") | ("ATTITUDE" | "ROTORCRAFT_FP", "phi") => phi,
            ("FINKEN_SENSOR_MODEL", "pos_yaw") | ("ATTITUDE" | "ROTORCRAFT_FP", "psi") => psi,
            ("FINKEN_SENSOR_MODEL", "velocity_x") => vx,
            ("FINKEN_SENSOR_MODEL", "velocity_y") => vy,
            ("FINKEN_SENSOR_MODEL", "velocity_z") => vz,
            ("FINKEN_SENSOR_MODEL", "velocity_pitch") => -gy,
            ("FINKEN_SENSOR_MODEL", "velocity_roll") => gx,
            ("FINKEN_SENSOR_MODEL", "velocity_yaw") => -gz,
            ("FINKEN_SENSOR_MODEL", "acceleration_x") => ax,
            ("FINKEN_SENSOR_MODEL", "acceleration_y") => ay,
            ("FINKEN_SENSOR_MODEL", "acceleration_z") => az,
            ("ROTORCRAFT_FP", "east") => -y,
            ("ROTORCRAFT_FP", "north") => x,
            ("ROTORCRAFT_FP", "up") => z,
            ("ROTORCRAFT_FP", "veast") => -vy,
            ("ROTORCRAFT_FP", "vnorth") => vx,
            ("ROTORCRAFT_FP", "vup") => vz,
            ("ROTORCRAFT_FP", "carrot_east" | "carrot_north" | "carrot_up" | "carrot_psi") => 0.0,
            ("ROTORCRAFT_FP", "thrust") => f64::from(thrust_n) * 1000.0,
            ("ROTORCRAFT_FP", "flight_time") => st.time_s.min(65_535.0),
            ("INS_REF", "ecef_x0") => ecef[0],
            ("INS_REF", "ecef_y0") => ecef[1],
            ("INS_REF", "ecef_z0") => ecef[2],
            ("INS_REF", "lat0") => ARENA_ORIGIN_LLA.0,
            ("INS_REF", "lon0") => ARENA_ORIGIN_LLA.1,
            // Height above the ellipsoid is taken as hmsl (the geoid separation is not modelled).
            ("INS_REF", "alt0" | "hmsl0") => ARENA_ORIGIN_LLA.2,
            ("INS_REF", "baro_qfe") => 101_325.0,
            ("ROTORCRAFT_STATUS", "link_imu_nb_err" | "motor_nb_err" | "rc_status") => 0.0,
            ("ROTORCRAFT_STATUS", "frame_rate") => 20.0,
            // No GPS on a FINken.
            ("ROTORCRAFT_STATUS", "gps_status") => 0.0,
            // MODULE: the FINken's flight modes are a module.
            ("ROTORCRAFT_STATUS", "ap_mode") => 17.0,
            ("ROTORCRAFT_STATUS", "ap_in_flight") => f64::from(u8::from(z > 0.05)),
            ("ROTORCRAFT_STATUS", "ap_motors_on") => f64::from(u8::from(thrust_n > 0.0)),
            ("ROTORCRAFT_STATUS", "ap_h_mode" | "ap_v_mode") => 6.0,
            // Decivolts.
            ("ROTORCRAFT_STATUS", "vsupply") => (f64::from(se.battery_v) * 10.0).round(),
            ("ROTORCRAFT_STATUS", "cpu_time") => st.time_s.min(65_535.0),
            _ => return None,
        })
    };
    if !TELEMETRY_MESSAGES.contains(&name) {
        return None;
    }
    if name == "ALIVE" {
        return Some(alive_text(messages, ac_id));
    }
    // ATTITUDE's angles and the FINKEN_SENSOR_MODEL pose are radians; ROTORCRAFT_FP's display
    // unit is degrees.
    let value_of = |field: &str| {
        let v = value_of(field)?;
        Some(if name == "ROTORCRAFT_FP" && matches!(field, "phi" | "theta" | "psi") { v.to_degrees() } else { v })
    };
    Some(encode_by_field(messages, ac_id, name, value_of))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distance_diff_follows_the_firmwares_sign_and_clamp() {
        // A wall 50 cm ahead, nothing behind: x = min(back, 120) − min(front, 120) = 70 cm,
        // which the firmware turns into a pitch up (backwards).
        assert_eq!(diff_cm(765.0, 50.0), 70.0);
        assert_eq!(diff_cm(10.0, 765.0), 20.0 - 120.0, "readings under 20 cm count as 20 cm");
        assert_eq!(diff_cm(250.0, 130.0), 0.0, "both beyond the goal distance");
    }

    #[test]
    fn the_embedded_definitions_parse_and_have_what_the_bridge_uses() {
        let m = project_messages();
        for name in [
            "SONAR_ARRAY",
            "FINKEN_SENSOR_MODEL",
            "FINKEN_ACTUATORS_SET_POINT",
            "FINKEN_IR_ADC",
            "ATTITUDE",
            "ROTORCRAFT_FP",
            "VIRTUAL_SONAR",
            "ALIVE",
            "INS_REF",
            "ROTORCRAFT_STATUS",
        ] {
            assert!(m.by_name(name).is_some(), "{name}");
        }
    }

    #[test]
    fn ins_ref_holds_the_arena_origin_in_ecef() {
        // ECEF of 52.13986 N, 11.64548 E, 50 m, by hand: N = a / sqrt(1 - e² sin²φ).
        let [x, y, z] = ecef_of(52.139_86, 11.645_48, 50.0);
        assert!((x.hypot(y).hypot(z) - 6_365_049.0).abs() < 2_000.0, "{x} {y} {z}");
        assert!((y.atan2(x).to_degrees() - 11.645_48).abs() < 1e-9);
        // The origin of the ECEF frame sits on the equator plane: z > 0 in the north.
        assert!(z > 5.0e6);
        assert_eq!(ecef_of(0.0, 0.0, 0.0), [6_378_137.0, 0.0, 0.0]);
    }

    #[test]
    fn actuator_set_points_become_twin_commands_in_the_simulators_frame() {
        let m = project_messages();
        let msg = m.decode("7 FINKEN_ACTUATORS_SET_POINT 10 -5 90 55").unwrap();
        let c = twin_command(&msg).unwrap();
        assert!((c.pitch.unwrap() + 10f32.to_radians()).abs() < 1e-6, "nose up in NED is nose up here: pitch < 0");
        assert!((c.roll.unwrap() + 5f32.to_radians()).abs() < 1e-6);
        assert!((c.yaw.unwrap() + 90f32.to_radians()).abs() < 1e-6, "clockwise psi is negative yaw");
        assert!((c.throttle.unwrap() - 0.55).abs() < 1e-6);
        // ir_distance is metres, as the firmware sends it (the project's definition says
        // `unit="m"`; its `alt_unit="cm"` is only how Paparazzi displays it).
        let ir = m.decode("7 FINKEN_IR_ADC 0.805 512").unwrap();
        assert_eq!(twin_command(&ir).unwrap().height, Some(0.805));
        assert!(twin_command(&m.decode("7 SONAR_ARRAY 1 2 3 4").unwrap()).is_none());
    }

    #[test]
    fn ir_distance_is_read_in_its_definitions_unit_never_its_alt_unit() {
        let xml = |unit: &str| {
            format!(
                r#"<protocol><msg_class name="telemetry" id="1"><message name="FINKEN_IR_ADC" id="252">
                <field name="ir_distance" type="float" {unit} alt_unit="cm"/>
                <field name="ir_measurement" type="uint16"/>
                </message></msg_class></protocol>"#
            )
        };
        let height = |unit: &str, text: &str| {
            let m = MessageSet::parse(&xml(unit), "t.xml").unwrap();
            twin_command(&m.decode(text).unwrap()).and_then(|c| c.height)
        };
        // The FINken fork's definition: no `unit`, `alt_unit="cm"`; the firmware sends metres.
        assert_eq!(height("", "6 FINKEN_IR_ADC 0.5 512"), Some(0.5));
        // A definition that gives a `unit` is read in it.
        assert_eq!(height(r#"unit="cm""#, "6 FINKEN_IR_ADC 50 512"), Some(0.5));
        assert_eq!(height(r#"unit="m""#, "6 FINKEN_IR_ADC 0.5 512"), Some(0.5));
        // A `unit` that is no length is not guessed at.
        assert_eq!(height(r#"unit="adc""#, "6 FINKEN_IR_ADC 50 512"), None);
        assert_eq!(metres_per("mm"), Some(0.001));
        assert_eq!(value_unit(None, IR_DISTANCE_UNIT), "m");
    }

    #[test]
    fn virtual_sonar_round_trips_through_its_ivy_text() {
        let m = project_messages();
        let text = virtual_sonar_text(&m, 7, [1.234, f32::INFINITY, 0.5, 3.0]).unwrap();
        assert_eq!(text, "ground_dl VIRTUAL_SONAR 7 123 65535 50 300");
        let (ac, back) = virtual_sonar_readings(&m.decode(&text).unwrap()).unwrap();
        assert_eq!(ac, 7);
        assert_eq!(back, [1.23, f32::INFINITY, 0.5, 3.0]);
    }
}
