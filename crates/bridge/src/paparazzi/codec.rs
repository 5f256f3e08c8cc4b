//! The Ivy text form of Paparazzi messages: encode and decode.
//!
//! # Text form
//!
//! An Ivy message is one line of ASCII text:
//!
//! ```text
//! <sender> <MSG_NAME> <field1> <field2> ...
//! 5 ATTITUDE 0.1 -1.5 0.02            telemetry from aircraft 5
//! ground FLIGHT_PARAM 5 0.1 ...        ground-class message
//! ground_dl VIRTUAL_SONAR 5 120 ...    datalink message to aircraft 5
//! ```
//!
//! These conventions follow pprzlink's own libraries (OCaml `pprzLink.ml`
//! `message_send` / `values_of_string` / `string_of_value`, Python
//! `message.py` `payload_to_ivy_string` / `ivy_string_to_payload` and
//! `ivy.py` `send`):
//!
//! * The **sender** comes first: the aircraft id in decimal for telemetry,
//!   the agent or class name otherwise (`ground`, `ground_dl` as used by the
//!   Paparazzi server for datalink messages, `datalink` as used by the
//!   Python library). Then the message **name**, then every field in
//!   definition order, separated by single spaces. A message without fields
//!   is `<sender> <NAME>` (pprzlink-Python appends one trailing space; the
//!   decoder accepts both).
//! * Decoding splits fields on runs of spaces and tabs (`[ \t]+`).
//! * Arrays of numbers are **comma-joined** without spaces: `1,2,3`.
//!   Empty pieces (`1,,2`, trailing comma) are ignored on decode, as in
//!   both reference decoders.
//! * `char[]` / `char[N]` arrays are **double-quoted** text: `"foo bar"`.
//!   The old `|foo bar|` delimiters are accepted on decode. Because neither
//!   reference decoder supports escapes, text containing `"` or `|` cannot be
//!   encoded and is an error.
//! * `string` fields are a **bare token** (e.g. the `csv` strings of ground
//!   messages, `1,2,3`), so they cannot contain whitespace and cannot be
//!   empty; the encoder refuses such values rather than emit a message that
//!   would decode with the wrong field count.
//! * Integers are decimal. Floats are written in the shortest form that
//!   reads back to the same bits (Rust `Display`), not with the field's
//!   `format` (e.g. `%.2f`), which is a display hint and would lose
//!   precision; any decimal or exponent form is accepted on decode.
//! * Texts never contain line breaks (Ivy ends a message at `\n`).
//!
//! Every error is a [`CodecError`]; decoding never panics on any input.

use std::fmt::Write as _;

use serde::ser::SerializeMap;
use serde::{Serialize, Serializer};

use crate::ids::AcId;
use crate::paparazzi::messages::{BaseType, FieldType, MessageDef, MessageSet};
use crate::paparazzi::value::Value;

/// Longest variable-length array the binary link can carry (uint8 length).
pub const MAX_VAR_ARRAY_LEN: usize = 255;

/// Who sent a message: an aircraft (numeric sender) or a named agent.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Sender {
    /// Telemetry from aircraft `ac_id` (sender token is the decimal id).
    Aircraft(AcId),
    /// A ground agent or class name, e.g. `ground`, `ground_dl`.
    Agent(String),
}

impl Sender {
    /// The `ground` sender used for ground-class messages.
    pub fn ground() -> Sender {
        Sender::Agent("ground".to_owned())
    }

    /// The `ground_dl` sender of datalink messages on the Ivy bus (the `link` agent forwards
    /// them to the aircraft named in their `ac_id` field).
    pub fn ground_dl() -> Sender {
        Sender::Agent("ground_dl".to_owned())
    }

    /// Parses a sender token: all-digit tokens are aircraft ids (0..=255),
    /// anything else without whitespace is an agent name.
    pub fn parse(token: &str) -> Result<Sender, CodecError> {
        if token.is_empty() || token.chars().any(|c| c.is_whitespace() || c.is_control()) {
            return Err(CodecError::BadSender { sender: token.to_owned() });
        }
        if token.bytes().all(|b| b.is_ascii_digit()) {
            token.parse::<AcId>().map(Sender::Aircraft).map_err(|_| CodecError::BadSender { sender: token.to_owned() })
        } else {
            Ok(Sender::Agent(token.to_owned()))
        }
    }

    /// The aircraft id, if the sender is an aircraft.
    pub fn ac_id(&self) -> Option<AcId> {
        match self {
            Sender::Aircraft(id) => Some(*id),
            Sender::Agent(_) => None,
        }
    }
}

impl std::fmt::Display for Sender {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Sender::Aircraft(id) => write!(f, "{id}"),
            Sender::Agent(name) => f.write_str(name),
        }
    }
}

impl Serialize for Sender {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Sender::Aircraft(id) => s.serialize_u8(*id),
            Sender::Agent(name) => s.serialize_str(name),
        }
    }
}

/// Errors of the Ivy text codec.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CodecError {
    /// The text is empty or only whitespace.
    #[error("empty Ivy message")]
    Empty,
    /// Only a sender, no message name.
    #[error("Ivy message from `{sender}` has no message name")]
    MissingName {
        /// The sender token.
        sender: String,
    },
    /// The sender token is not usable (e.g. an all-digit id above 255).
    #[error("bad sender `{sender}` (aircraft ids are 0..=255)")]
    BadSender {
        /// The sender token.
        sender: String,
    },
    /// The message name is not in the definitions.
    #[error("unknown message `{name}`")]
    UnknownMessage {
        /// The name.
        name: String,
    },
    /// Wrong number of fields.
    #[error("message {message}: expected {expected} fields, found {found}")]
    FieldCount {
        /// Message name.
        message: String,
        /// Number of fields in the definition.
        expected: usize,
        /// Number found.
        found: usize,
    },
    /// A number that does not parse.
    #[error("message {message}, field {field}{}: `{text}` is not a valid {ty}", index_suffix(*.index))]
    BadNumber {
        /// Message name.
        message: String,
        /// Field name.
        field: String,
        /// Array element index, for arrays.
        index: Option<usize>,
        /// The offending text.
        text: String,
        /// Expected type.
        ty: BaseType,
    },
    /// An integer outside the range of its type.
    #[error("message {message}, field {field}{}: {text} is out of range for {ty}", index_suffix(*.index))]
    OutOfRange {
        /// Message name.
        message: String,
        /// Field name.
        field: String,
        /// Array element index, for arrays.
        index: Option<usize>,
        /// The offending text.
        text: String,
        /// Field type.
        ty: BaseType,
    },
    /// A `char` field that is not exactly one character.
    #[error("message {message}, field {field}: `{text}` is not a single character")]
    BadChar {
        /// Message name.
        message: String,
        /// Field name.
        field: String,
        /// The offending text.
        text: String,
    },
    /// A fixed-length array (or `char[N]` text) of the wrong length.
    #[error("message {message}, field {field}: expected {expected} elements, found {found}")]
    ArrayLength {
        /// Message name.
        message: String,
        /// Field name.
        field: String,
        /// Required length (for `char[N]`: the maximum).
        expected: usize,
        /// Found length.
        found: usize,
    },
    /// A variable-length array longer than the link allows.
    #[error("message {message}, field {field}: {found} elements exceed the maximum of {max}")]
    ArrayTooLong {
        /// Message name.
        message: String,
        /// Field name.
        field: String,
        /// Maximum length.
        max: usize,
        /// Found length.
        found: usize,
    },
    /// A quoted text that is never closed.
    #[error("message {message}: unterminated {quote} quote starting at byte {offset} of the payload")]
    UnterminatedQuote {
        /// Message name.
        message: String,
        /// The quote character.
        quote: char,
        /// Byte offset of the opening quote in the payload.
        offset: usize,
    },
    /// A value whose type does not match the field (encoding).
    #[error("message {message}, field {field}: expected a {expected} value, got {found}")]
    ValueType {
        /// Message name.
        message: String,
        /// Field name.
        field: String,
        /// Field type.
        expected: String,
        /// Kind of the given value.
        found: String,
    },
    /// A value that has no Ivy text form (encoding).
    #[error("message {message}, field {field}: cannot encode: {reason}")]
    Unencodable {
        /// Message name.
        message: String,
        /// Field name.
        field: String,
        /// Why.
        reason: &'static str,
    },
}

fn index_suffix(index: Option<usize>) -> String {
    index.map(|i| format!("[{i}]")).unwrap_or_default()
}

/// Splits an Ivy text into `(sender, name, payload)` at the first two runs
/// of spaces. Only the space character separates the header (every
/// Paparazzi agent writes single spaces); this is the same split the bus
/// and the key-expression narrowing use. Returns `None` when the text has no
/// name.
pub fn split_header(text: &str) -> Option<(&str, &str, &str)> {
    let (sender, rest) = text.split_once(' ')?;
    let rest = rest.trim_start_matches(' ');
    let (name, payload) = match rest.split_once(' ') {
        Some((n, p)) => (n, p),
        None => (rest, ""),
    };
    if sender.is_empty() || name.is_empty() {
        return None;
    }
    Some((sender, name, payload))
}

/// A decoded message: who sent it, its definition, and one value per field.
#[derive(Debug, Clone, PartialEq)]
pub struct Message<'d> {
    /// Sender.
    pub sender: Sender,
    /// Definition (borrowed from the [`MessageSet`]).
    pub def: &'d MessageDef,
    /// Values, one per field, in definition order.
    pub values: Vec<Value>,
}

impl<'d> Message<'d> {
    /// Builds a message, checking that the values fit the definition.
    pub fn new(sender: Sender, def: &'d MessageDef, values: Vec<Value>) -> Result<Self, CodecError> {
        check_values(def, &values)?;
        Ok(Message { sender, def, values })
    }

    /// The value of field `name`.
    pub fn get(&self, name: &str) -> Option<&Value> {
        self.def.field_index(name).and_then(|i| self.values.get(i))
    }

    /// Encodes the message into its Ivy text.
    pub fn to_ivy(&self) -> Result<String, CodecError> {
        encode(&self.sender, self.def, &self.values)
    }
}

impl Serialize for Message<'_> {
    /// `{"sender": 5, "class": "telemetry", "name": "ATTITUDE", "id": 6,
    /// "fields": {"phi": 0.1, ...}}` with fields in definition order.
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        struct Fields<'a, 'd>(&'a Message<'d>);
        impl Serialize for Fields<'_, '_> {
            fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
                let mut map = s.serialize_map(Some(self.0.values.len()))?;
                for (f, v) in self.0.def.fields.iter().zip(&self.0.values) {
                    map.serialize_entry(&f.name, v)?;
                }
                map.end()
            }
        }
        let mut map = s.serialize_map(Some(5))?;
        map.serialize_entry("sender", &self.sender)?;
        map.serialize_entry("class", &self.def.class_name)?;
        map.serialize_entry("name", &self.def.name)?;
        map.serialize_entry("id", &self.def.id)?;
        map.serialize_entry("fields", &Fields(self))?;
        map.end()
    }
}

/// Checks count and types of `values` against `def` (and array lengths).
fn check_values(def: &MessageDef, values: &[Value]) -> Result<(), CodecError> {
    if values.len() != def.fields.len() {
        return Err(CodecError::FieldCount {
            message: def.name.clone(),
            expected: def.fields.len(),
            found: values.len(),
        });
    }
    for (f, v) in def.fields.iter().zip(values) {
        if !v.fits(f.ty) {
            return Err(CodecError::ValueType {
                message: def.name.clone(),
                field: f.name.clone(),
                expected: f.ty.to_string(),
                found: v.kind(),
            });
        }
        let len = match v {
            Value::Array(items) => Some(items.len()),
            Value::Text(t) if f.ty.is_char_array() => Some(t.len()),
            _ => None,
        };
        if let Some(found) = len {
            match f.ty {
                FieldType::FixedArray(BaseType::Char, n) if found > n => {
                    return Err(CodecError::ArrayLength {
                        message: def.name.clone(),
                        field: f.name.clone(),
                        expected: n,
                        found,
                    });
                }
                FieldType::FixedArray(b, n) if b != BaseType::Char && found != n => {
                    return Err(CodecError::ArrayLength {
                        message: def.name.clone(),
                        field: f.name.clone(),
                        expected: n,
                        found,
                    });
                }
                FieldType::Array(_) if found > MAX_VAR_ARRAY_LEN => {
                    return Err(CodecError::ArrayTooLong {
                        message: def.name.clone(),
                        field: f.name.clone(),
                        max: MAX_VAR_ARRAY_LEN,
                        found,
                    });
                }
                _ => {}
            }
        }
    }
    Ok(())
}

/// Encodes `values` of message `def` from `sender` into Ivy text.
pub fn encode(sender: &Sender, def: &MessageDef, values: &[Value]) -> Result<String, CodecError> {
    let mut out = String::with_capacity(16 + 12 * values.len());
    encode_into(&mut out, sender, def, values)?;
    Ok(out)
}

/// Like [`encode`], appending to `out` (which is left unchanged on error).
pub fn encode_into(out: &mut String, sender: &Sender, def: &MessageDef, values: &[Value]) -> Result<(), CodecError> {
    check_values(def, values)?;
    let start = out.len();
    let result = (|| {
        // Writing into a String cannot fail.
        let _ = write!(out, "{sender} {}", def.name);
        for (f, v) in def.fields.iter().zip(values) {
            out.push(' ');
            let unencodable =
                |reason| CodecError::Unencodable { message: def.name.clone(), field: f.name.clone(), reason };
            match (f.ty, v) {
                (FieldType::Scalar(BaseType::String), Value::Text(t)) => {
                    if t.is_empty() {
                        return Err(unencodable("empty `string` values have no Ivy form"));
                    }
                    if t.chars().any(|c| c.is_whitespace() || c.is_control()) {
                        return Err(unencodable("`string` values cannot contain whitespace"));
                    }
                    if t.starts_with('"') || t.starts_with('|') {
                        return Err(unencodable("`string` values cannot start with a quote"));
                    }
                    out.push_str(t);
                }
                (_, Value::Text(t)) => {
                    if t.contains(['"', '|']) {
                        return Err(unencodable("char arrays cannot contain `\"` or `|`"));
                    }
                    if t.chars().any(char::is_control) {
                        return Err(unencodable("char arrays cannot contain control characters"));
                    }
                    out.push('"');
                    out.push_str(t);
                    out.push('"');
                }
                (_, Value::Char(c)) => {
                    if c.is_whitespace() || c.is_control() || *c == '"' || *c == '|' {
                        return Err(unencodable("this `char` has no Ivy text form"));
                    }
                    out.push(*c);
                }
                (_, Value::Array(items)) => {
                    if items.is_empty() {
                        return Err(unencodable("empty arrays have no Ivy text form"));
                    }
                    let _ = write!(out, "{v}");
                }
                _ => {
                    let _ = write!(out, "{v}");
                }
            }
        }
        Ok(())
    })();
    if result.is_err() {
        out.truncate(start);
    }
    result
}

/// One payload token: its text (without quotes).
#[derive(Debug, Clone, Copy)]
struct Token<'a> {
    text: &'a str,
}

fn tokenize<'a>(payload: &'a str, message: &str, out: &mut Vec<Token<'a>>) -> Result<(), CodecError> {
    let bytes = payload.as_bytes();
    let mut i = 0;
    while i < bytes.len() {
        let b = bytes[i];
        if b == b' ' || b == b'\t' {
            i += 1;
            continue;
        }
        if b == b'"' || b == b'|' {
            let close = payload[i + 1..].find(b as char).ok_or(CodecError::UnterminatedQuote {
                message: message.to_owned(),
                quote: b as char,
                offset: i,
            })?;
            out.push(Token { text: &payload[i + 1..i + 1 + close] });
            i += close + 2;
        } else {
            let end = payload[i..].find([' ', '\t']).map(|e| i + e).unwrap_or(bytes.len());
            out.push(Token { text: &payload[i..end] });
            i = end;
        }
    }
    Ok(())
}

fn parse_scalar(
    text: &str,
    ty: BaseType,
    message: &str,
    field: &str,
    index: Option<usize>,
) -> Result<Value, CodecError> {
    let bad = || CodecError::BadNumber {
        message: message.to_owned(),
        field: field.to_owned(),
        index,
        text: text.to_owned(),
        ty,
    };
    if let Some((min, max)) = ty.int_range() {
        let n: i128 = text.parse().map_err(|_| bad())?;
        if n < min || n > max {
            return Err(CodecError::OutOfRange {
                message: message.to_owned(),
                field: field.to_owned(),
                index,
                text: text.to_owned(),
                ty,
            });
        }
        // The range check above makes every conversion below exact.
        let v = match ty {
            BaseType::Int8 => i8::try_from(n).map(Value::I8).ok(),
            BaseType::Uint8 => u8::try_from(n).map(Value::U8).ok(),
            BaseType::Int16 => i16::try_from(n).map(Value::I16).ok(),
            BaseType::Uint16 => u16::try_from(n).map(Value::U16).ok(),
            BaseType::Int32 => i32::try_from(n).map(Value::I32).ok(),
            BaseType::Uint32 => u32::try_from(n).map(Value::U32).ok(),
            BaseType::Int64 => i64::try_from(n).map(Value::I64).ok(),
            BaseType::Uint64 => u64::try_from(n).map(Value::U64).ok(),
            _ => None,
        };
        return v.ok_or_else(bad);
    }
    // A finite literal too large for the type parses to infinity: refuse it.
    let overflow = |infinite: bool| infinite && !text.to_ascii_lowercase().contains("inf");
    let out_of_range = || CodecError::OutOfRange {
        message: message.to_owned(),
        field: field.to_owned(),
        index,
        text: text.to_owned(),
        ty,
    };
    match ty {
        BaseType::Float => match text.parse::<f32>() {
            Ok(v) if overflow(v.is_infinite()) => Err(out_of_range()),
            Ok(v) => Ok(Value::F32(v)),
            Err(_) => Err(bad()),
        },
        BaseType::Double => match text.parse::<f64>() {
            Ok(v) if overflow(v.is_infinite()) => Err(out_of_range()),
            Ok(v) => Ok(Value::F64(v)),
            Err(_) => Err(bad()),
        },
        BaseType::Char => {
            let mut chars = text.chars();
            match (chars.next(), chars.next()) {
                (Some(c), None) => Ok(Value::Char(c)),
                _ => Err(CodecError::BadChar {
                    message: message.to_owned(),
                    field: field.to_owned(),
                    text: text.to_owned(),
                }),
            }
        }
        BaseType::String => Ok(Value::Text(text.to_owned())),
        _ => Err(bad()),
    }
}

/// Decodes the payload (fields only, after sender and name) of `def`.
pub fn decode_payload(def: &MessageDef, payload: &str) -> Result<Vec<Value>, CodecError> {
    let mut tokens = Vec::with_capacity(def.fields.len());
    tokenize(payload, &def.name, &mut tokens)?;
    if tokens.len() != def.fields.len() {
        return Err(CodecError::FieldCount {
            message: def.name.clone(),
            expected: def.fields.len(),
            found: tokens.len(),
        });
    }
    let mut values = Vec::with_capacity(tokens.len());
    for (f, tok) in def.fields.iter().zip(&tokens) {
        let v = match f.ty {
            FieldType::Scalar(b) => parse_scalar(tok.text, b, &def.name, &f.name, None)?,
            t if t.is_char_array() => {
                if let FieldType::FixedArray(_, n) = t
                    && tok.text.len() > n
                {
                    return Err(CodecError::ArrayLength {
                        message: def.name.clone(),
                        field: f.name.clone(),
                        expected: n,
                        found: tok.text.len(),
                    });
                }
                Value::Text(tok.text.to_owned())
            }
            FieldType::Array(b) | FieldType::FixedArray(b, _) => {
                let mut items = Vec::new();
                for (i, piece) in tok.text.split(',').filter(|p| !p.is_empty()).enumerate() {
                    items.push(parse_scalar(piece, b, &def.name, &f.name, Some(i))?);
                }
                match f.ty {
                    FieldType::FixedArray(_, n) if items.len() != n => {
                        return Err(CodecError::ArrayLength {
                            message: def.name.clone(),
                            field: f.name.clone(),
                            expected: n,
                            found: items.len(),
                        });
                    }
                    FieldType::Array(_) if items.len() > MAX_VAR_ARRAY_LEN => {
                        return Err(CodecError::ArrayTooLong {
                            message: def.name.clone(),
                            field: f.name.clone(),
                            max: MAX_VAR_ARRAY_LEN,
                            found: items.len(),
                        });
                    }
                    _ => {}
                }
                Value::Array(items)
            }
        };
        values.push(v);
    }
    Ok(values)
}

impl MessageSet {
    /// Decodes one Ivy text into a [`Message`].
    ///
    /// If a name exists in several classes, telemetry is preferred for
    /// aircraft senders and the first non-telemetry class otherwise.
    pub fn decode(&self, text: &str) -> Result<Message<'_>, CodecError> {
        let trimmed = text.trim_matches(|c| c == ' ' || c == '\t' || c == '\r' || c == '\n');
        if trimmed.is_empty() {
            return Err(CodecError::Empty);
        }
        let Some((sender, name, payload)) = split_header(trimmed) else {
            let sender = trimmed.split(' ').next().unwrap_or("").to_owned();
            return Err(CodecError::MissingName { sender });
        };
        let sender = Sender::parse(sender)?;
        let refs = self.refs_by_name(name);
        let def = match refs {
            [] => {
                return Err(CodecError::UnknownMessage { name: name.to_owned() });
            }
            [one] => self.get(*one),
            many => {
                let is_tm = |r: &&crate::paparazzi::messages::MessageRef| self.get(**r).class_name == "telemetry";
                let pick =
                    if sender.ac_id().is_some() { many.iter().find(is_tm) } else { many.iter().find(|r| !is_tm(r)) };
                self.get(*pick.unwrap_or(&many[0]))
            }
        };
        let values = decode_payload(def, payload)?;
        Ok(Message { sender, def, values })
    }

    /// Encodes message `name` (looked up like [`MessageSet::decode`] does).
    pub fn encode(&self, sender: &Sender, name: &str, values: &[Value]) -> Result<String, CodecError> {
        let def = self.by_name(name).ok_or_else(|| CodecError::UnknownMessage { name: name.to_owned() })?;
        encode(sender, def, values)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set() -> MessageSet {
        let xml = r#"<protocol>
          <msg_class name="telemetry" id="1">
            <message name="PONG" id="3"/>
            <message name="T" id="9">
              <field name="a" type="uint8"/>
              <field name="b" type="float[]"/>
              <field name="c" type="char[]"/>
              <field name="d" type="int16[3]"/>
              <field name="e" type="string"/>
            </message>
          </msg_class>
        </protocol>"#;
        MessageSet::parse(xml, "test").expect("valid")
    }

    #[test]
    fn encode_follows_pprzlink_conventions() {
        let s = set();
        let vals = vec![
            Value::U8(7),
            Value::Array(vec![Value::F32(1.5), Value::F32(-2.0)]),
            Value::Text("foo bar".into()),
            Value::Array(vec![Value::I16(1), Value::I16(-2), Value::I16(3)]),
            Value::Text("x,y".into()),
        ];
        let text = s.encode(&Sender::Aircraft(5), "T", &vals).expect("encodes");
        assert_eq!(text, r#"5 T 7 1.5,-2 "foo bar" 1,-2,3 x,y"#);
        let m = s.decode(&text).expect("decodes");
        assert_eq!(m.values, vals);
        assert_eq!(s.encode(&Sender::Aircraft(5), "PONG", &[]).as_deref(), Ok("5 PONG"));
        assert!(s.decode("5 PONG ").is_ok(), "python-style trailing space");
        assert!(s.decode("5 T 7 1.5 |old style| 1,2,3 z").is_ok());
    }

    #[test]
    fn json_form_has_field_names_in_order() {
        let s = set();
        let m = s.decode(r#"5 T 7 1.5,2 "hi" 1,2,3 z"#).expect("decodes");
        let json = serde_json::to_string(&m).expect("json");
        assert_eq!(
            json,
            r#"{"sender":5,"class":"telemetry","name":"T","id":9,"fields":{"a":7,"b":[1.5,2.0],"c":"hi","d":[1,2,3],"e":"z"}}"#
        );
    }
}
