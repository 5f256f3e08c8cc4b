//! Paparazzi message definitions (`messages.xml`).
//!
//! # Formats
//!
//! Two generations of the file are read by the same parser:
//!
//! * **pprzlink v1.0** (`message_definitions/v1.0/messages.xml`, also used by
//!   the pprzlink v2.0 transport): `<protocol>` holds `<msg_class name=".."
//!   id="..">` elements (ids 1..5 upstream: telemetry, datalink, ground,
//!   alert, intermcu).
//! * **FINken-era** `conf/messages.xml` (paparazzi before the pprzlink split,
//!   branch `FINken` of ovgu-FINken/paparazzi): the same element names, but
//!   `<msg_class name="..">` has **no `id`**. Older Paparazzi versions used
//!   `<class name="..">`; that spelling is accepted as an alias (as pprzlink's
//!   OCaml library does).
//!
//! Inside a class, `<message name=".." id=".." [link="forwarded|broadcasted"]>`
//! holds an optional `<description>` and `<field>`s. A field has `name`,
//! `type` and optionally `unit`, `alt_unit`, `alt_unit_coef`, `values`
//! (`|`-separated enumeration names), `format` (a printf format used by
//! Paparazzi's GUI) and a text description.
//!
//! Field types: `int8 uint8 int16 uint16 int32 uint32 int64 uint64 float
//! double char string`, plus arrays `T[]` (variable length, at most 255
//! elements on the binary link) and `T[N]` (fixed length).
//!
//! Field layouts differ between versions of the file (e.g. FINken-era and
//! upstream `ROTORCRAFT_FP` disagree on `carrot_psi`'s `alt_unit_coef`, and
//! many messages were added or removed), so layouts are always read from the
//! file in use and never hard-coded. Field names are kept verbatim, including
//! historic misspellings such as `distance_d_rigth` in `FINKEN_SENSOR_MODEL`.

use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::path::Path;

use serde::Serialize;

use crate::paparazzi::xml::{Doc, Element, XmlError};

/// Element type of a field (the part before any `[..]`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BaseType {
    /// `int8`
    Int8,
    /// `uint8`
    Uint8,
    /// `int16`
    Int16,
    /// `uint16`
    Uint16,
    /// `int32`
    Int32,
    /// `uint32`
    Uint32,
    /// `int64`
    Int64,
    /// `uint64`
    Uint64,
    /// `float` (IEEE-754 binary32)
    Float,
    /// `double` (IEEE-754 binary64)
    Double,
    /// `char` (one byte; arrays of it are text)
    Char,
    /// `string` (length-prefixed text on the binary link; bare token on Ivy)
    String,
}

impl BaseType {
    /// Parses a Paparazzi base type name.
    pub fn from_name(name: &str) -> Option<BaseType> {
        Some(match name {
            "int8" => BaseType::Int8,
            "uint8" => BaseType::Uint8,
            "int16" => BaseType::Int16,
            "uint16" => BaseType::Uint16,
            "int32" => BaseType::Int32,
            "uint32" => BaseType::Uint32,
            "int64" => BaseType::Int64,
            "uint64" => BaseType::Uint64,
            "float" => BaseType::Float,
            "double" => BaseType::Double,
            "char" => BaseType::Char,
            "string" => BaseType::String,
            _ => return None,
        })
    }

    /// The Paparazzi name of the type.
    pub fn name(self) -> &'static str {
        match self {
            BaseType::Int8 => "int8",
            BaseType::Uint8 => "uint8",
            BaseType::Int16 => "int16",
            BaseType::Uint16 => "uint16",
            BaseType::Int32 => "int32",
            BaseType::Uint32 => "uint32",
            BaseType::Int64 => "int64",
            BaseType::Uint64 => "uint64",
            BaseType::Float => "float",
            BaseType::Double => "double",
            BaseType::Char => "char",
            BaseType::String => "string",
        }
    }

    /// Inclusive integer range of the type, or `None` for non-integers.
    pub fn int_range(self) -> Option<(i128, i128)> {
        Some(match self {
            BaseType::Int8 => (i8::MIN.into(), i8::MAX.into()),
            BaseType::Uint8 => (0, u8::MAX.into()),
            BaseType::Int16 => (i16::MIN.into(), i16::MAX.into()),
            BaseType::Uint16 => (0, u16::MAX.into()),
            BaseType::Int32 => (i32::MIN.into(), i32::MAX.into()),
            BaseType::Uint32 => (0, u32::MAX.into()),
            BaseType::Int64 => (i64::MIN.into(), i64::MAX.into()),
            BaseType::Uint64 => (0, u64::MAX.into()),
            _ => return None,
        })
    }

    /// Whether this is one of the integer types.
    pub fn is_integer(self) -> bool {
        self.int_range().is_some()
    }
}

impl fmt::Display for BaseType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Shape of a field: scalar, variable-length array or fixed-length array.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
pub enum FieldType {
    /// `T`
    Scalar(BaseType),
    /// `T[]`
    Array(BaseType),
    /// `T[N]`
    FixedArray(BaseType, usize),
}

impl FieldType {
    /// Parses `T`, `T[]` or `T[N]`. Arrays of `string` are rejected.
    pub fn parse(text: &str) -> Result<FieldType, String> {
        let text = text.trim();
        let (base, suffix) = match text.find('[') {
            Some(i) => (&text[..i], Some(&text[i..])),
            None => (text, None),
        };
        let base_ty = BaseType::from_name(base.trim()).ok_or_else(|| format!("unknown base type `{}`", base.trim()))?;
        match suffix {
            None => Ok(FieldType::Scalar(base_ty)),
            Some(s) => {
                if base_ty == BaseType::String {
                    return Err("arrays of `string` are not supported".into());
                }
                let inner = s
                    .strip_prefix('[')
                    .and_then(|s| s.strip_suffix(']'))
                    .ok_or_else(|| format!("malformed array suffix `{s}`"))?;
                if inner.trim().is_empty() {
                    Ok(FieldType::Array(base_ty))
                } else {
                    let n: usize =
                        inner.trim().parse().map_err(|_| format!("array length `{inner}` is not a number"))?;
                    if n == 0 {
                        return Err("fixed array length must be at least 1".into());
                    }
                    Ok(FieldType::FixedArray(base_ty, n))
                }
            }
        }
    }

    /// Element or scalar type.
    pub fn base(self) -> BaseType {
        match self {
            FieldType::Scalar(b) | FieldType::Array(b) | FieldType::FixedArray(b, _) => b,
        }
    }

    /// Whether this is an array (fixed or variable).
    pub fn is_array(self) -> bool {
        !matches!(self, FieldType::Scalar(_))
    }

    /// Whether values of this type are text on Ivy (`char[]`, `char[N]`).
    pub fn is_char_array(self) -> bool {
        self.is_array() && self.base() == BaseType::Char
    }
}

impl fmt::Display for FieldType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FieldType::Scalar(b) => write!(f, "{b}"),
            FieldType::Array(b) => write!(f, "{b}[]"),
            FieldType::FixedArray(b, n) => write!(f, "{b}[{n}]"),
        }
    }
}

/// One `<field>` of a message.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FieldDef {
    /// Field name, verbatim from the file.
    pub name: String,
    /// Parsed type.
    pub ty: FieldType,
    /// `unit` attribute (unit of the transmitted value).
    pub unit: Option<String>,
    /// `alt_unit` attribute (display unit).
    pub alt_unit: Option<String>,
    /// `alt_unit_coef`: display value = coef × transmitted value.
    pub alt_unit_coef: Option<f64>,
    /// Enumeration names from `values="A|B|C"` (empty if absent).
    pub values: Vec<String>,
    /// `format` attribute (printf format used by Paparazzi tools).
    pub format: Option<String>,
    /// Text content of the element, trimmed, if not empty.
    pub description: Option<String>,
}

/// How the ground `link` agent handles a datalink message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum LinkMode {
    /// Sent to the aircraft named by the message's `ac_id` field.
    Forwarded,
    /// Sent to every aircraft.
    Broadcasted,
}

/// One `<message>`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MessageDef {
    /// Message name (upper case by convention).
    pub name: String,
    /// Message id within its class.
    pub id: u8,
    /// Name of the class (`telemetry`, `datalink`, `ground`, ...).
    pub class_name: String,
    /// Id of the class, if the file gives one (pprzlink v1.0 format).
    pub class_id: Option<u8>,
    /// `link` attribute of datalink messages.
    pub link: Option<LinkMode>,
    /// `<description>` text, trimmed.
    pub description: Option<String>,
    /// Fields in wire order.
    pub fields: Vec<FieldDef>,
    /// Line of the `<message>` element in the source file.
    pub source_line: u32,
}

impl MessageDef {
    /// Index of the field called `name`.
    pub fn field_index(&self, name: &str) -> Option<usize> {
        self.fields.iter().position(|f| f.name == name)
    }

    /// The field called `name`.
    pub fn field(&self, name: &str) -> Option<&FieldDef> {
        self.fields.iter().find(|f| f.name == name)
    }
}

/// One `<msg_class>` (or legacy `<class>`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MessageClass {
    /// Class name.
    pub name: String,
    /// Class id (absent in the FINken-era format).
    pub id: Option<u8>,
    /// Messages in file order.
    pub messages: Vec<MessageDef>,
}

/// Which generation of `messages.xml` a file is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum DefinitionFormat {
    /// Every class has an `id` (pprzlink v1.0 format).
    PprzlinkV1,
    /// Classes without ids (paparazzi `conf/messages.xml` before pprzlink).
    Legacy,
}

/// Reference to a message inside a [`MessageSet`]: class index and message
/// index.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct MessageRef {
    /// Index into [`MessageSet::classes`].
    pub class: usize,
    /// Index into that class's `messages`.
    pub message: usize,
}

/// All message definitions of one `messages.xml`.
#[derive(Debug, Clone)]
pub struct MessageSet {
    /// File label given at parse time.
    pub source: String,
    /// Detected format.
    pub format: DefinitionFormat,
    /// Classes in file order.
    pub classes: Vec<MessageClass>,
    by_name: HashMap<String, Vec<MessageRef>>,
}

impl MessageSet {
    /// Reads and parses a `messages.xml` file.
    pub fn from_file(path: impl AsRef<Path>) -> Result<MessageSet, XmlError> {
        let path = path.as_ref();
        let text = crate::paparazzi::xml::read_file(path)?;
        MessageSet::parse(&text, &path.display().to_string())
    }

    /// Parses the text of a `messages.xml`; `source` labels error locations.
    pub fn parse(text: &str, source: &str) -> Result<MessageSet, XmlError> {
        let doc = Doc::parse(text, source)?;
        let root = doc.expect_root("protocol")?;
        MessageSet::from_element(&doc, root, source)
    }

    /// The definitions under a `<protocol>` element of a parsed document (a `messages.xml`, or
    /// the copy a Paparazzi `server` log embeds).
    pub(crate) fn from_element(doc: &Doc, root: &Element, source: &str) -> Result<MessageSet, XmlError> {
        let mut classes = Vec::new();
        let mut class_lines: BTreeMap<String, u32> = BTreeMap::new();
        let mut class_id_lines: BTreeMap<u8, u32> = BTreeMap::new();
        for class_el in &root.children {
            if class_el.name != "msg_class" && class_el.name != "class" {
                return Err(doc.unexpected(root, class_el));
            }
            let name = doc.req_attr(class_el, "name")?.value.trim().to_owned();
            let line = doc.line(class_el.offset);
            if let Some(first) = class_lines.insert(name.clone(), line) {
                return Err(XmlError::Duplicate {
                    at: doc.loc(class_el.offset),
                    what: "message class",
                    name,
                    first_line: first,
                });
            }
            let id = match doc.attr(class_el, "id") {
                Some(a) => {
                    let id: u8 = doc.parse_attr(class_el, a, "a class id 0..255")?;
                    if let Some(first) = class_id_lines.insert(id, line) {
                        return Err(XmlError::Duplicate {
                            at: doc.loc(a.offset),
                            what: "message class id",
                            name: id.to_string(),
                            first_line: first,
                        });
                    }
                    Some(id)
                }
                None => None,
            };
            let messages = parse_class(doc, class_el, &name, id)?;
            classes.push(MessageClass { name, id, messages });
        }
        if classes.is_empty() {
            return Err(doc.invalid(root.offset, "<protocol> holds no message class"));
        }
        let format = if classes.iter().all(|c| c.id.is_some()) {
            DefinitionFormat::PprzlinkV1
        } else {
            DefinitionFormat::Legacy
        };
        let mut by_name: HashMap<String, Vec<MessageRef>> = HashMap::new();
        for (ci, class) in classes.iter().enumerate() {
            for (mi, m) in class.messages.iter().enumerate() {
                by_name.entry(m.name.clone()).or_default().push(MessageRef { class: ci, message: mi });
            }
        }
        Ok(MessageSet { source: source.to_owned(), format, classes, by_name })
    }

    /// The definition a reference points to.
    ///
    /// # Panics
    /// Only if `r` was not produced by this set.
    pub fn get(&self, r: MessageRef) -> &MessageDef {
        &self.classes[r.class].messages[r.message]
    }

    /// The class called `name`.
    pub fn class(&self, name: &str) -> Option<&MessageClass> {
        self.classes.iter().find(|c| c.name == name)
    }

    /// All messages called `name` (normally one; a name may repeat across
    /// classes in principle), in class order.
    pub fn refs_by_name(&self, name: &str) -> &[MessageRef] {
        self.by_name.get(name).map(Vec::as_slice).unwrap_or(&[])
    }

    /// The first message called `name`, in class order.
    pub fn by_name(&self, name: &str) -> Option<&MessageDef> {
        self.refs_by_name(name).first().map(|r| self.get(*r))
    }

    /// The message `name` in class `class`.
    pub fn by_class_and_name(&self, class: &str, name: &str) -> Option<&MessageDef> {
        self.refs_by_name(name).iter().map(|r| self.get(*r)).find(|m| m.class_name == class)
    }

    /// The message with id `id` in class `class`.
    pub fn by_class_and_id(&self, class: &str, id: u8) -> Option<&MessageDef> {
        self.class(class)?.messages.iter().find(|m| m.id == id)
    }

    /// Iterates over every message of every class, in file order.
    pub fn iter(&self) -> impl Iterator<Item = &MessageDef> {
        self.classes.iter().flat_map(|c| c.messages.iter())
    }

    /// Number of messages in all classes.
    pub fn len(&self) -> usize {
        self.classes.iter().map(|c| c.messages.len()).sum()
    }

    /// Whether the set holds no message at all (never true after parsing).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

fn parse_class(
    doc: &Doc,
    class_el: &Element,
    class_name: &str,
    class_id: Option<u8>,
) -> Result<Vec<MessageDef>, XmlError> {
    let mut messages = Vec::new();
    let mut ids: BTreeMap<u8, u32> = BTreeMap::new();
    let mut names: BTreeMap<String, u32> = BTreeMap::new();
    for msg_el in &class_el.children {
        if msg_el.name != "message" {
            return Err(doc.unexpected(class_el, msg_el));
        }
        let line = doc.line(msg_el.offset);
        let name_attr = doc.req_attr(msg_el, "name")?;
        let name = name_attr.value.trim().to_owned();
        if name.is_empty() || name.chars().any(char::is_whitespace) {
            return Err(doc.bad_attr(msg_el, name_attr, "message names must be one non-empty word"));
        }
        let id_attr = doc.req_attr(msg_el, "id")?;
        let id: u8 = doc.parse_attr(msg_el, id_attr, "a message id 0..255")?;
        if let Some(first) = ids.insert(id, line) {
            return Err(XmlError::Duplicate {
                at: doc.loc(id_attr.offset),
                what: "message id",
                name: format!("{id} in class {class_name}"),
                first_line: first,
            });
        }
        if let Some(first) = names.insert(name.clone(), line) {
            return Err(XmlError::Duplicate {
                at: doc.loc(name_attr.offset),
                what: "message name",
                name: format!("{name} in class {class_name}"),
                first_line: first,
            });
        }
        let link = match doc.attr(msg_el, "link") {
            None => None,
            Some(a) => Some(match a.value.trim() {
                "forwarded" => LinkMode::Forwarded,
                "broadcasted" => LinkMode::Broadcasted,
                _ => return Err(doc.bad_attr(msg_el, a, "expected `forwarded` or `broadcasted`")),
            }),
        };
        let mut description = None;
        let mut fields: Vec<FieldDef> = Vec::new();
        for child in &msg_el.children {
            match child.name.as_str() {
                "description" => description = non_empty(&child.text),
                "field" => {
                    let f = parse_field(doc, child)?;
                    if fields.iter().any(|g| g.name == f.name) {
                        return Err(
                            doc.invalid(child.offset, format!("duplicate field `{}` in message {name}", f.name))
                        );
                    }
                    fields.push(f);
                }
                _ => return Err(doc.unexpected(msg_el, child)),
            }
        }
        messages.push(MessageDef {
            name,
            id,
            class_name: class_name.to_owned(),
            class_id,
            link,
            description,
            fields,
            source_line: line,
        });
    }
    Ok(messages)
}

fn parse_field(doc: &Doc, el: &Element) -> Result<FieldDef, XmlError> {
    let name_attr = doc.req_attr(el, "name")?;
    let name = name_attr.value.trim().to_owned();
    if name.is_empty() || name.chars().any(char::is_whitespace) {
        return Err(doc.bad_attr(el, name_attr, "field names must be one non-empty word"));
    }
    let type_attr = doc.req_attr(el, "type")?;
    let ty = FieldType::parse(&type_attr.value).map_err(|reason| doc.bad_attr(el, type_attr, reason))?;
    let opt = |key: &str| doc.attr(el, key).map(|a| a.value.clone());
    let alt_unit_coef = match doc.attr(el, "alt_unit_coef") {
        Some(a) => Some(doc.parse_f64_attr(el, a)?),
        None => None,
    };
    let values =
        doc.attr(el, "values").map(|a| a.value.split('|').map(|s| s.trim().to_owned()).collect()).unwrap_or_default();
    Ok(FieldDef {
        name,
        ty,
        unit: opt("unit"),
        alt_unit: opt("alt_unit"),
        alt_unit_coef,
        values,
        format: opt("format"),
        description: non_empty(&el.text),
    })
}

fn non_empty(s: &str) -> Option<String> {
    let t = s.trim();
    if t.is_empty() { None } else { Some(t.to_owned()) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn field_types_parse() {
        assert_eq!(FieldType::parse("uint8"), Ok(FieldType::Scalar(BaseType::Uint8)));
        assert_eq!(FieldType::parse("float[]"), Ok(FieldType::Array(BaseType::Float)));
        assert_eq!(FieldType::parse("char[5]"), Ok(FieldType::FixedArray(BaseType::Char, 5)));
        assert!(FieldType::parse("quaternion").is_err());
        assert!(FieldType::parse("float[x]").is_err());
        assert!(FieldType::parse("string[]").is_err());
        assert!(FieldType::parse("uint8[0]").is_err());
    }

    #[test]
    fn legacy_and_v1_formats_are_detected() {
        let v1 = r#"<protocol><msg_class name="telemetry" id="1">
            <message name="A" id="1"><field name="x" type="uint8"/></message>
            </msg_class></protocol>"#;
        let legacy = r#"<protocol><class name="telemetry">
            <message name="A" id="1"><field name="x" type="uint8"/></message>
            </class></protocol>"#;
        assert_eq!(MessageSet::parse(v1, "v1").map(|s| s.format).ok(), Some(DefinitionFormat::PprzlinkV1));
        assert_eq!(MessageSet::parse(legacy, "l").map(|s| s.format).ok(), Some(DefinitionFormat::Legacy));
    }

    #[test]
    fn errors_carry_lines() {
        let dup = "<protocol>\n<msg_class name=\"t\" id=\"1\">\n<message name=\"A\" id=\"1\"/>\n<message name=\"B\" id=\"1\"/>\n</msg_class>\n</protocol>";
        let e = MessageSet::parse(dup, "dup.xml").expect_err("duplicate id");
        assert!(matches!(e, XmlError::Duplicate { first_line: 3, .. }), "{e}");
        assert_eq!(e.line(), Some(4));

        let bad_type = "<protocol>\n<msg_class name=\"t\" id=\"1\">\n<message name=\"A\" id=\"1\">\n  <field name=\"x\" type=\"uint7\"/>\n</message></msg_class></protocol>";
        let e = MessageSet::parse(bad_type, "bad.xml").expect_err("bad type");
        assert!(matches!(e, XmlError::BadAttribute { .. }), "{e}");
        assert_eq!(e.line(), Some(4));
        assert!(e.to_string().starts_with("bad.xml:4:"), "{e}");

        let missing =
            "<protocol>\n<msg_class name=\"t\" id=\"1\">\n<message name=\"A\">\n</message></msg_class></protocol>";
        let e = MessageSet::parse(missing, "m.xml").expect_err("missing id");
        assert!(matches!(e, XmlError::MissingAttribute { .. }), "{e}");
        assert_eq!(e.line(), Some(3));

        let big_id =
            "<protocol>\n<msg_class name=\"t\" id=\"1\">\n<message name=\"A\" id=\"256\"/></msg_class></protocol>";
        let e = MessageSet::parse(big_id, "b.xml").expect_err("id too big");
        assert_eq!(e.line(), Some(3));
    }
}
