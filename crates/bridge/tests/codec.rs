//! Codec tests that need no shared data: our own messages.xml, a synthetic
//! definition covering every type, and malformed texts.

mod common;

use bridge::Value;
use bridge::paparazzi::codec::{CodecError, Sender, encode};
use bridge::paparazzi::messages::{BaseType, DefinitionFormat, LinkMode, MessageSet};

use common::{Gen, asset, same_bits};

fn ours() -> MessageSet {
    MessageSet::from_file(asset("paparazzi/messages.xml")).unwrap_or_else(|e| panic!("{e}"))
}

const EVERY_TYPE: &str = r#"<?xml version="1.0"?>
<protocol>
  <msg_class name="telemetry" id="1">
    <message name="ALL_SCALARS" id="1">
      <field name="a" type="int8"/>
      <field name="b" type="uint8"/>
      <field name="c" type="int16"/>
      <field name="d" type="uint16"/>
      <field name="e" type="int32"/>
      <field name="f" type="uint32"/>
      <field name="g" type="int64"/>
      <field name="h" type="uint64"/>
      <field name="i" type="float"/>
      <field name="j" type="double"/>
      <field name="k" type="char"/>
      <field name="l" type="string"/>
    </message>
    <message name="ALL_ARRAYS" id="2">
      <field name="a" type="int8[]"/>
      <field name="b" type="uint8[2]"/>
      <field name="c" type="int16[]"/>
      <field name="d" type="uint16[3]"/>
      <field name="e" type="int32[]"/>
      <field name="f" type="uint32[1]"/>
      <field name="g" type="int64[]"/>
      <field name="h" type="uint64[2]"/>
      <field name="i" type="float[]"/>
      <field name="j" type="double[4]"/>
      <field name="k" type="char[]"/>
      <field name="l" type="char[6]"/>
    </message>
    <message name="EMPTY" id="3"/>
  </msg_class>
  <msg_class name="ground" id="3">
    <message name="G" id="1"><field name="ac_id" type="string"/></message>
  </msg_class>
</protocol>"#;

#[test]
fn every_type_round_trips_with_generated_values() {
    let set = MessageSet::parse(EVERY_TYPE, "every_type.xml").unwrap_or_else(|e| panic!("{e}"));
    for def in set.iter() {
        for seed in 0..200u64 {
            let mut g = Gen::new(seed);
            let values = g.values(def);
            let sender = if def.class_name == "telemetry" { Sender::Aircraft(seed as u8) } else { Sender::ground() };
            let text = encode(&sender, def, &values).unwrap_or_else(|e| panic!("{e}"));
            let back = set.decode(&text).unwrap_or_else(|e| panic!("`{text}`: {e}"));
            assert_eq!(back.def.name, def.name);
            for (a, b) in values.iter().zip(&back.values) {
                assert!(same_bits(a, b), "{a:?} vs {b:?} in `{text}`");
            }
        }
    }
}

#[test]
fn our_messages_round_trip() {
    let set = ours();
    for def in set.iter() {
        for seed in 0..50u64 {
            let values = Gen::new(seed).values(def);
            let text = encode(&Sender::Aircraft(5), def, &values).unwrap_or_else(|e| panic!("{e}"));
            let back = set.decode(&text).unwrap_or_else(|e| panic!("`{text}`: {e}"));
            assert!(values.iter().zip(&back.values).all(|(a, b)| same_bits(a, b)), "{text}");
        }
    }
}

#[test]
fn our_messages_xml_has_what_twinswarm_uses() {
    let set = ours();
    assert_eq!(set.format, DefinitionFormat::PprzlinkV1);
    let expect = [
        ("telemetry", "ATTITUDE", 6, 3),
        ("telemetry", "ROTORCRAFT_FP", 147, 15),
        ("telemetry", "SONAR_ARRAY", 216, 4),
        ("telemetry", "FINKEN_SENSOR_MODEL", 217, 21),
        ("telemetry", "FINKEN_ACTUATORS_SET_POINT", 250, 4),
        ("telemetry", "FINKEN_IR_ADC", 252, 2),
        ("telemetry", "ALIVE", 2, 1),
        ("telemetry", "INS_REF", 154, 8),
        ("telemetry", "ROTORCRAFT_STATUS", 231, 12),
        ("datalink", "VIRTUAL_SONAR", 210, 5),
    ];
    for (class, name, id, n_fields) in expect {
        let d = set.by_class_and_name(class, name).unwrap_or_else(|| panic!("{name} missing"));
        assert_eq!((d.id, d.fields.len()), (id, n_fields), "{name}");
    }
    assert_eq!(set.len(), expect.len());
    let fsm = set.by_name("FINKEN_SENSOR_MODEL").expect("FSM");
    assert_eq!(fsm.fields[1].name, "distance_d_rigth");
    let vs = set.by_name("VIRTUAL_SONAR").expect("VIRTUAL_SONAR");
    assert_eq!(vs.link, Some(LinkMode::Forwarded));
    assert_eq!(vs.class_id, Some(2));
    let names: Vec<&str> = vs.fields.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, ["ac_id", "front_cm", "right_cm", "back_cm", "left_cm"]);
    assert!(vs.fields[1..].iter().all(|f| f.ty.base() == BaseType::Uint16 && f.unit.as_deref() == Some("cm")));
}

#[test]
fn virtual_sonar_text_form() {
    let set = ours();
    let vals = [Value::U8(5), Value::U16(120), Value::U16(65535), Value::U16(87), Value::U16(300)];
    let text = set.encode(&Sender::Agent("ground_dl".into()), "VIRTUAL_SONAR", &vals).expect("encodes");
    assert_eq!(text, "ground_dl VIRTUAL_SONAR 5 120 65535 87 300");
    let m = set.decode(&text).expect("decodes");
    assert_eq!(m.get("right_cm"), Some(&Value::U16(65535)));
    let json = serde_json::to_value(&m).expect("json");
    assert_eq!(json["sender"], "ground_dl");
    assert_eq!(json["fields"]["front_cm"], 120);
}

#[test]
fn malformed_texts_give_typed_errors() {
    let set = ours();
    type Check = fn(&CodecError) -> bool;
    let cases: Vec<(&str, Check)> = vec![
        ("", |e| *e == CodecError::Empty),
        ("   ", |e| *e == CodecError::Empty),
        ("5", |e| matches!(e, CodecError::MissingName { sender } if sender == "5")),
        ("5 NO_SUCH_MESSAGE 1 2", |e| matches!(e, CodecError::UnknownMessage { name } if name == "NO_SUCH_MESSAGE")),
        (
            "5 ATTITUDE 0.1 0.2",
            |e| matches!(e, CodecError::FieldCount { message, expected: 3, found: 2 } if message == "ATTITUDE"),
        ),
        ("5 ATTITUDE 0.1 0.2 0.3 0.4", |e| matches!(e, CodecError::FieldCount { expected: 3, found: 4, .. })),
        (
            "5 ATTITUDE 0.1 zero 0.3",
            |e| matches!(e, CodecError::BadNumber { field, text, ty: BaseType::Float, .. } if field == "psi" && text == "zero"),
        ),
        (
            "5 SONAR_ARRAY 1 2 3 65536",
            |e| matches!(e, CodecError::OutOfRange { field, ty: BaseType::Uint16, .. } if field == "sonar_left"),
        ),
        ("5 SONAR_ARRAY -1 2 3 4", |e| matches!(e, CodecError::OutOfRange { field, .. } if field == "sonar_front")),
        ("5 SONAR_ARRAY 1.5 2 3 4", |e| matches!(e, CodecError::BadNumber { ty: BaseType::Uint16, .. })),
        ("5 FINKEN_IR_ADC 1e39 4", |e| matches!(e, CodecError::OutOfRange { ty: BaseType::Float, .. })),
        ("5 FINKEN_IR_ADC 1.5 0x10", |e| matches!(e, CodecError::BadNumber { field, .. } if field == "ir_measurement")),
        ("256 ATTITUDE 0 0 0", |e| matches!(e, CodecError::BadSender { sender } if sender == "256")),
        ("ground_dl VIRTUAL_SONAR 5 1 2 3 99999999999999999999999999999999999999999", |e| {
            matches!(e, CodecError::OutOfRange { .. } | CodecError::BadNumber { .. })
        }),
    ];
    for (text, check) in cases {
        match set.decode(text) {
            Ok(m) => panic!("`{text}` decoded to {m:?}"),
            Err(e) => assert!(check(&e), "`{text}` gave the wrong error: {e:?}"),
        }
    }
}

#[test]
fn malformed_arrays_and_quotes_give_typed_errors() {
    let set = MessageSet::parse(EVERY_TYPE, "every_type.xml").unwrap_or_else(|e| panic!("{e}"));
    let good = r#"1 ALL_ARRAYS -1,2 1,2 3 1,2,3 4 5 6 7,8 1.5 1,2,3,4 "a b" "abc""#;
    assert!(set.decode(good).is_ok(), "{:?}", set.decode(good));
    let e = set
        .decode(r#"1 ALL_ARRAYS -1,2 1,2,3 3 1,2,3 4 5 6 7,8 1.5 1,2,3,4 "a b" "abc""#)
        .expect_err("uint8[2] with 3");
    assert!(matches!(e, CodecError::ArrayLength { expected: 2, found: 3, .. }), "{e:?}");
    let e = set.decode(r#"1 ALL_ARRAYS -1,x 1,2 3 1,2,3 4 5 6 7,8 1.5 1,2,3,4 "a b" "abc""#).expect_err("bad element");
    assert!(matches!(e, CodecError::BadNumber { index: Some(1), .. }), "{e:?}");
    let e = set
        .decode(r#"1 ALL_ARRAYS -1,2 1,2 3 1,2,3 4 5 6 7,8 1.5 1,2,3,4 "a b" "abcdefgh""#)
        .expect_err("char[6] too long");
    assert!(matches!(e, CodecError::ArrayLength { expected: 6, found: 8, .. }), "{e:?}");
    let e = set.decode(r#"1 ALL_ARRAYS -1,2 1,2 3 1,2,3 4 5 6 7,8 1.5 1,2,3,4 "a b "#).expect_err("unterminated");
    assert!(matches!(e, CodecError::UnterminatedQuote { quote: '"', .. }), "{e:?}");
    let e = set.decode("1 ALL_SCALARS 1 2 3 4 5 6 7 8 9.5 10.5 xy s").expect_err("char");
    assert!(matches!(e, CodecError::BadChar { .. }), "{e:?}");
    let e = set.decode("1 ALL_SCALARS 1 2 3 4 5 6 7 18446744073709551616 9.5 10.5 x s").expect_err("u64 overflow");
    assert!(matches!(e, CodecError::OutOfRange { ty: BaseType::Uint64, .. }), "{e:?}");
    let e = set.decode("1 ALL_SCALARS 1 2 3 4 5 6 7 8 9.5 10.5 x s extra").expect_err("extra");
    assert!(matches!(e, CodecError::FieldCount { expected: 12, found: 13, .. }), "{e:?}");
}

#[test]
fn encoding_refuses_values_without_a_text_form() {
    let set = MessageSet::parse(EVERY_TYPE, "every_type.xml").unwrap_or_else(|e| panic!("{e}"));
    let g = set.by_name("G").expect("G");
    let e = encode(&Sender::ground(), g, &[Value::Text("a b".into())]).expect_err("space");
    assert!(matches!(e, CodecError::Unencodable { .. }), "{e:?}");
    let e = encode(&Sender::ground(), g, &[Value::Text(String::new())]).expect_err("empty");
    assert!(matches!(e, CodecError::Unencodable { .. }), "{e:?}");
    let e = encode(&Sender::ground(), g, &[Value::U8(1)]).expect_err("type");
    assert!(matches!(e, CodecError::ValueType { .. }), "{e:?}");
    let e = encode(&Sender::ground(), g, &[]).expect_err("count");
    assert!(matches!(e, CodecError::FieldCount { expected: 1, found: 0, .. }), "{e:?}");
    let arrays = set.by_name("ALL_ARRAYS").expect("arrays");
    let mut vals = Gen::new(3).values(arrays);
    vals[0] = Value::Array(vec![]);
    let e = encode(&Sender::Aircraft(1), arrays, &vals).expect_err("empty array");
    assert!(matches!(e, CodecError::Unencodable { .. }), "{e:?}");
    let mut vals = Gen::new(3).values(arrays);
    vals[10] = Value::Text("say \"hi\"".into());
    let e = encode(&Sender::Aircraft(1), arrays, &vals).expect_err("quote");
    assert!(matches!(e, CodecError::Unencodable { .. }), "{e:?}");
    let mut vals = Gen::new(3).values(arrays);
    vals[1] = Value::Array(vec![Value::U8(1)]);
    let e = encode(&Sender::Aircraft(1), arrays, &vals).expect_err("fixed length");
    assert!(matches!(e, CodecError::ArrayLength { expected: 2, found: 1, .. }), "{e:?}");
    let empty = set.by_name("EMPTY").expect("EMPTY");
    assert_eq!(encode(&Sender::Aircraft(9), empty, &[]).as_deref(), Ok("9 EMPTY"));
}

#[test]
fn decoding_never_panics_on_garbage() {
    let set = MessageSet::parse(EVERY_TYPE, "every_type.xml").unwrap_or_else(|e| panic!("{e}"));
    let alphabet = b" \t,\"|-+.0123456789eEaxyzALL_SCALARSARRAYSGground\xc3\xa9";
    let mut g = Gen::new(42);
    for _ in 0..20_000 {
        let len = g.below(60) as usize;
        let bytes: Vec<u8> = (0..len).map(|_| alphabet[g.below(alphabet.len() as u64) as usize]).collect();
        let text = String::from_utf8_lossy(&bytes);
        let _ = set.decode(&text);
        let _ = set.decode(&format!("1 ALL_SCALARS {text}"));
        let _ = set.decode(&format!("1 ALL_ARRAYS {text}"));
    }
}
