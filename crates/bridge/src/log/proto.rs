//! The project's own log messages, field for field as in `crates/bridge/proto/twinswarm.proto`
//! (hand-written prost types: no protoc in the build). The descriptor set made from that file
//! ([`DESCRIPTOR_SET`]) is the schema of every channel that uses them.
//!
//! They also read the JSON logs written before protobuf (same field names): `Deserialize`
//! with every field defaulted, and the few fields whose JSON shape differs converted.

use serde::{Deserialize, Deserializer};

/// `twinswarm.fds`: the descriptor set of `twinswarm.proto` and its imports
/// (`scripts/gen-proto.sh`).
pub const DESCRIPTOR_SET: &[u8] = include_bytes!("../../proto/twinswarm.fds");

/// `twinswarm.CopterState` (`/copters/state`).
#[derive(Clone, PartialEq, prost::Message, Deserialize)]
#[serde(default)]
pub struct CopterState {
    #[prost(uint64, tag = "1")]
    pub tick: u64,
    #[prost(double, tag = "2")]
    pub t_s: f64,
    #[prost(string, tag = "3")]
    pub copter: String,
    #[prost(uint32, tag = "4")]
    pub id: u32,
    #[prost(uint32, optional, tag = "5")]
    pub ac_id: Option<u32>,
    #[prost(string, tag = "6")]
    pub kind: String,
    #[prost(string, tag = "7")]
    pub mode: String,
    #[prost(bool, tag = "8")]
    pub crashed: bool,
    /// JSON of the cause; empty while flying.
    #[prost(string, tag = "9")]
    #[serde(deserialize_with = "any_as_json_text")]
    pub crash_cause: String,
    #[prost(bool, tag = "10")]
    pub took_off: bool,
    #[prost(float, repeated, tag = "11")]
    pub pos_m: Vec<f32>,
    #[prost(float, repeated, tag = "12")]
    pub vel_m_s: Vec<f32>,
    #[prost(float, repeated, tag = "13")]
    pub rpy_rad: Vec<f32>,
    #[prost(float, repeated, tag = "14")]
    pub angvel_rad_s: Vec<f32>,
    #[prost(float, repeated, tag = "15")]
    pub quat_xyzw: Vec<f32>,
    #[prost(float, repeated, tag = "16")]
    pub rotor_thrust_n: Vec<f32>,
    #[prost(float, repeated, tag = "17")]
    pub rotor_speed_rad_s: Vec<f32>,
}

/// `twinswarm.CopterSensors` (`/copters/sensors`).
#[derive(Clone, PartialEq, prost::Message, Deserialize)]
#[serde(default)]
pub struct CopterSensors {
    #[prost(uint64, tag = "1")]
    pub tick: u64,
    #[prost(double, tag = "2")]
    pub t_s: f64,
    #[prost(string, tag = "3")]
    pub copter: String,
    #[prost(uint32, tag = "4")]
    pub id: u32,
    #[prost(uint64, tag = "5")]
    pub sonar_tick: u64,
    #[prost(float, repeated, tag = "6")]
    pub sonar_truth_m: Vec<f32>,
    #[prost(float, repeated, tag = "7")]
    pub sonar_m: Vec<f32>,
    #[prost(float, repeated, tag = "8")]
    pub sonar_fused_m: Vec<f32>,
    #[prost(bool, repeated, tag = "9")]
    pub sonar_crosstalk: Vec<bool>,
    #[prost(float, optional, tag = "10")]
    pub ir_m: Option<f32>,
    #[prost(float, optional, tag = "11")]
    pub ir_truth_m: Option<f32>,
    #[prost(float, repeated, tag = "12")]
    pub attitude_rad: Vec<f32>,
    #[prost(float, tag = "13")]
    pub yaw_bias_rad: f32,
    #[prost(float, repeated, tag = "14")]
    pub rate_body_rad_s: Vec<f32>,
    #[prost(float, repeated, tag = "15")]
    pub accel_body_m_s2: Vec<f32>,
    #[prost(float, tag = "16")]
    pub height_est_m: f32,
    #[prost(float, tag = "17")]
    pub battery_v: f32,
    #[prost(float, tag = "18")]
    pub battery_charge: f32,
    #[prost(float, tag = "19")]
    pub battery_a: f32,
}

/// `twinswarm.CopterCommand` (`/copters/command`).
#[derive(Clone, PartialEq, prost::Message, Deserialize)]
#[serde(default)]
pub struct CopterCommand {
    #[prost(uint64, tag = "1")]
    pub tick: u64,
    #[prost(double, tag = "2")]
    pub t_s: f64,
    #[prost(string, tag = "3")]
    pub copter: String,
    #[prost(uint32, tag = "4")]
    pub id: u32,
    #[prost(string, tag = "5")]
    pub mode: String,
    #[prost(float, tag = "6")]
    pub roll_rad: f32,
    #[prost(float, tag = "7")]
    pub pitch_rad: f32,
    #[prost(float, tag = "8")]
    pub yaw_rad: f32,
    #[prost(float, tag = "9")]
    pub throttle: f32,
    #[prost(float, tag = "10")]
    pub height_m: f32,
    #[prost(float, repeated, tag = "11")]
    #[serde(deserialize_with = "null_as_empty")]
    pub target_m: Vec<f32>,
    #[prost(float, repeated, tag = "12")]
    #[serde(deserialize_with = "null_as_empty")]
    pub velocity_m_s: Vec<f32>,
    #[prost(float, repeated, tag = "13")]
    #[serde(deserialize_with = "null_as_empty")]
    pub virtual_sonar_m: Vec<f32>,
}

/// `twinswarm.CopterControl` (`/copters/control`).
#[derive(Clone, PartialEq, prost::Message, Deserialize)]
#[serde(default)]
pub struct CopterControl {
    #[prost(uint64, tag = "1")]
    pub tick: u64,
    #[prost(double, tag = "2")]
    pub t_s: f64,
    #[prost(string, tag = "3")]
    pub copter: String,
    #[prost(uint32, tag = "4")]
    pub id: u32,
    #[prost(message, optional, tag = "5")]
    pub setpoint: Option<Setpoint>,
    #[prost(message, optional, tag = "6")]
    pub wall_avoid: Option<WallAvoid>,
}

/// `twinswarm.CopterControl.Setpoint`.
#[derive(Clone, PartialEq, prost::Message, Deserialize)]
#[serde(default)]
pub struct Setpoint {
    #[prost(float, tag = "1")]
    pub roll_rad: f32,
    #[prost(float, tag = "2")]
    pub pitch_rad: f32,
    #[prost(float, tag = "3")]
    pub yaw_rad: f32,
    #[prost(float, tag = "4")]
    pub height_m: f32,
    #[prost(float, tag = "5")]
    pub throttle: f32,
}

/// `twinswarm.CopterControl.WallAvoid`.
#[derive(Clone, PartialEq, prost::Message, Deserialize)]
#[serde(default)]
pub struct WallAvoid {
    #[prost(bool, tag = "1")]
    pub engaged: bool,
    #[prost(float, repeated, tag = "2")]
    pub out_rad: Vec<f32>,
    #[prost(float, repeated, tag = "3")]
    pub last_m: Vec<f32>,
    #[prost(float, repeated, tag = "4")]
    pub rate_m_s: Vec<f32>,
}

/// `twinswarm.Event` (`/events`).
#[derive(Clone, PartialEq, prost::Message, Deserialize)]
#[serde(default)]
pub struct Event {
    #[prost(uint64, tag = "1")]
    pub tick: u64,
    #[prost(double, tag = "2")]
    pub t_s: f64,
    #[prost(string, tag = "3")]
    pub kind: String,
    #[prost(string, optional, tag = "4")]
    pub copter: Option<String>,
    #[prost(uint32, optional, tag = "5")]
    pub id: Option<u32>,
    #[prost(message, optional, tag = "6")]
    #[serde(deserialize_with = "json_as_struct")]
    pub detail: Option<prost_types::Struct>,
    #[prost(string, tag = "7")]
    pub message: String,
}

/// `twinswarm.BusMessage` (`/bus`).
#[derive(Clone, PartialEq, prost::Message, Deserialize)]
#[serde(default)]
pub struct BusMessage {
    #[prost(uint64, tag = "1")]
    pub tick: u64,
    #[prost(string, tag = "2")]
    pub key: String,
    #[prost(string, tag = "3")]
    pub direction: String,
    #[prost(string, tag = "4")]
    pub text: String,
}

/// `twinswarm.PprzText` (`/pprz/<sender>/<NAME>`).
#[derive(Clone, PartialEq, prost::Message, Deserialize)]
#[serde(default)]
pub struct PprzText {
    #[prost(uint64, tag = "1")]
    pub tick: u64,
    #[prost(string, tag = "2")]
    pub direction: String,
    #[prost(string, tag = "3")]
    pub key: String,
    #[prost(string, tag = "4")]
    pub text: String,
}

/// `twinswarm.PprzDecoded` (`/pprz/<sender>/<NAME>/decoded`).
#[derive(Clone, PartialEq, prost::Message, Deserialize)]
#[serde(default)]
pub struct PprzDecoded {
    #[prost(uint64, tag = "1")]
    pub tick: u64,
    #[prost(string, tag = "2")]
    pub direction: String,
    #[prost(string, tag = "3")]
    pub sender: String,
    #[prost(string, tag = "4")]
    pub name: String,
    #[prost(string, tag = "5")]
    pub class: String,
    #[prost(message, optional, tag = "6")]
    #[serde(deserialize_with = "json_as_struct")]
    pub fields: Option<prost_types::Struct>,
}

/// A message of a log in either encoding: `protobuf` (today's logs) or `json` (logs written
/// before; same field names).
pub trait LogRecord: prost::Message + Default + serde::de::DeserializeOwned {
    /// Decodes `data` written with `encoding`.
    fn decode_as(encoding: &str, data: &[u8]) -> Result<Self, String> {
        match encoding {
            "protobuf" => Self::decode(data).map_err(|e| format!("not a valid protobuf message: {e}")),
            "json" => serde_json::from_slice(data).map_err(|e| format!("not valid JSON for this program: {e}")),
            other => Err(format!("message encoding {other:?} is not one this program reads (protobuf, json)")),
        }
    }
}

impl<T: prost::Message + Default + serde::de::DeserializeOwned> LogRecord for T {}

/// A fixed-size vector field (`pos_m`, …) as an array; an error naming the field if the
/// message has another count.
pub fn fixed<const N: usize>(field: &str, v: &[f32]) -> Result<[f32; N], String> {
    v.try_into().map_err(|_| format!("{field} has {} values, expected {N}", v.len()))
}

/// A JSON value as a protobuf `Value`.
pub fn json_to_value(v: &serde_json::Value) -> prost_types::Value {
    use prost_types::value::Kind;
    let kind = match v {
        serde_json::Value::Null => Kind::NullValue(0),
        serde_json::Value::Bool(b) => Kind::BoolValue(*b),
        serde_json::Value::Number(n) => Kind::NumberValue(n.as_f64().unwrap_or(f64::NAN)),
        serde_json::Value::String(s) => Kind::StringValue(s.clone()),
        serde_json::Value::Array(a) => {
            Kind::ListValue(prost_types::ListValue { values: a.iter().map(json_to_value).collect() })
        }
        serde_json::Value::Object(o) => Kind::StructValue(json_object_to_struct(o)),
    };
    prost_types::Value { kind: Some(kind) }
}

/// A JSON object as a protobuf `Struct`.
pub fn json_object_to_struct(o: &serde_json::Map<String, serde_json::Value>) -> prost_types::Struct {
    prost_types::Struct { fields: o.iter().map(|(k, v)| (k.clone(), json_to_value(v))).collect() }
}

/// A JSON value as a `Struct`: an object as itself, anything else (not `null`) under `value`.
pub fn json_to_struct(v: &serde_json::Value) -> Option<prost_types::Struct> {
    match v {
        serde_json::Value::Null => None,
        serde_json::Value::Object(o) => Some(json_object_to_struct(o)),
        other => Some(prost_types::Struct { fields: [("value".to_owned(), json_to_value(other))].into() }),
    }
}

/// A protobuf `Value` as JSON (whole numbers as integers, non-finite ones as `null`).
pub fn value_to_json(v: &prost_types::Value) -> serde_json::Value {
    use prost_types::value::Kind;
    match &v.kind {
        None | Some(Kind::NullValue(_)) => serde_json::Value::Null,
        Some(Kind::BoolValue(b)) => (*b).into(),
        // A whole number (a count, an id) back as an integer, as it was before the `Struct`.
        Some(Kind::NumberValue(n)) if n.fract() == 0.0 && n.abs() < 9.007_199_254_740_992e15 => (*n as i64).into(),
        Some(Kind::NumberValue(n)) => serde_json::Number::from_f64(*n).map_or(serde_json::Value::Null, Into::into),
        Some(Kind::StringValue(s)) => s.clone().into(),
        Some(Kind::ListValue(l)) => l.values.iter().map(value_to_json).collect(),
        Some(Kind::StructValue(s)) => struct_to_json(s),
    }
}

/// A protobuf `Struct` as a JSON object.
pub fn struct_to_json(s: &prost_types::Struct) -> serde_json::Value {
    s.fields.iter().map(|(k, v)| (k.clone(), value_to_json(v))).collect::<serde_json::Map<_, _>>().into()
}

fn null_as_empty<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<f32>, D::Error> {
    Ok(Option::<Vec<f32>>::deserialize(d)?.unwrap_or_default())
}

fn any_as_json_text<'de, D: Deserializer<'de>>(d: D) -> Result<String, D::Error> {
    Ok(match serde_json::Value::deserialize(d)? {
        serde_json::Value::Null => String::new(),
        v => v.to_string(),
    })
}

fn json_as_struct<'de, D: Deserializer<'de>>(d: D) -> Result<Option<prost_types::Struct>, D::Error> {
    Ok(json_to_struct(&serde_json::Value::deserialize(d)?))
}

#[cfg(test)]
mod tests {
    use super::*;
    use prost::Message as _;

    #[test]
    fn the_descriptor_set_declares_every_message() {
        let set = prost_types::FileDescriptorSet::decode(DESCRIPTOR_SET).expect("a descriptor set");
        let file = set.file.iter().find(|f| f.package() == "twinswarm").expect("the twinswarm file");
        let names: Vec<&str> = file.message_type.iter().map(|m| m.name()).collect();
        for n in ["CopterState", "CopterSensors", "CopterCommand", "CopterControl", "Event", "BusMessage"] {
            assert!(names.contains(&n), "{n} missing from {names:?}");
        }
        assert!(set.file.iter().any(|f| f.name() == "google/protobuf/struct.proto"), "imports included");
    }

    /// Each field's number and wire type in the descriptor set agree with the Rust types:
    /// a message with every field set, decoded with the descriptor's numbers, keeps them all.
    #[test]
    fn field_numbers_and_types_agree_with_the_descriptor() {
        use prost_types::field_descriptor_proto::{Label, Type};
        let set = prost_types::FileDescriptorSet::decode(DESCRIPTOR_SET).expect("a descriptor set");
        let file = set.file.iter().find(|f| f.package() == "twinswarm").expect("the twinswarm file");
        let state = CopterState {
            tick: 1,
            t_s: 2.0,
            copter: "c".into(),
            id: 3,
            ac_id: Some(4),
            kind: "k".into(),
            mode: "m".into(),
            crashed: true,
            crash_cause: "x".into(),
            took_off: true,
            pos_m: vec![1.0],
            vel_m_s: vec![1.0],
            rpy_rad: vec![1.0],
            angvel_rad_s: vec![1.0],
            quat_xyzw: vec![1.0],
            rotor_thrust_n: vec![1.0],
            rotor_speed_rad_s: vec![1.0],
        };
        let bytes = state.encode_to_vec();
        // Walk the wire: (field number, wire type) in order.
        let mut seen = Vec::new();
        let mut buf = &bytes[..];
        while !buf.is_empty() {
            let key = prost::encoding::decode_varint(&mut buf).expect("a key");
            let (num, wt) = ((key >> 3) as i32, (key & 7) as u8);
            seen.push((num, wt));
            let skip = match wt {
                0 => {
                    prost::encoding::decode_varint(&mut buf).expect("a varint");
                    0
                }
                1 => 8,
                2 => prost::encoding::decode_varint(&mut buf).expect("a length") as usize,
                5 => 4,
                _ => panic!("wire type {wt}"),
            };
            buf = &buf[skip..];
        }
        let msg = file.message_type.iter().find(|m| m.name() == "CopterState").expect("CopterState");
        assert_eq!(seen.len(), msg.field.len(), "every field of the descriptor is written once");
        for (f, (num, wt)) in msg.field.iter().zip(&seen) {
            assert_eq!(f.number(), *num, "field {} is number {}", f.name(), f.number());
            let expected = if f.label() == Label::Repeated {
                2
            } else {
                match f.r#type() {
                    Type::Double | Type::Fixed64 => 1,
                    Type::Float | Type::Fixed32 => 5,
                    Type::String | Type::Message | Type::Bytes => 2,
                    _ => 0,
                }
            };
            assert_eq!(expected, *wt, "field {} has wire type {wt}", f.name());
        }
    }

    #[test]
    fn json_logs_of_before_decode_into_the_same_types() {
        let json = br#"{"tick":3,"t_s":0.15,"copter":"finken1","id":0,"ac_id":null,"kind":"virtual",
            "mode":"wall_avoid","crashed":true,"crash_cause":{"kind":"box","index":2},"took_off":true,
            "pos_m":[1,2,3],"unknown_later_field":7}"#;
        let s = CopterState::decode_as("json", json).expect("decodes");
        assert_eq!((s.tick, s.ac_id, s.pos_m.as_slice()), (3, None, &[1.0, 2.0, 3.0][..]));
        assert_eq!(s.crash_cause, r#"{"index":2,"kind":"box"}"#);
        let c = CopterCommand::decode_as("json", br#"{"target_m":null,"virtual_sonar_m":[1,2,3,4]}"#).unwrap();
        assert!(c.target_m.is_empty());
        assert_eq!(c.virtual_sonar_m.len(), 4);
        let e = Event::decode_as("json", br#"{"kind":"crashed","detail":{"kind":"wall"}}"#).unwrap();
        assert_eq!(struct_to_json(e.detail.as_ref().unwrap()), serde_json::json!({"kind": "wall"}));
        let p = CopterState::decode_as("protobuf", &s.encode_to_vec()).unwrap();
        assert_eq!(p, s);
        let err = CopterState::decode_as("cbor", b"").unwrap_err();
        assert!(err.contains("cbor"), "{err}");
    }
}
