//! Typed field values of decoded Paparazzi messages.

use std::fmt;

use serde::{Serialize, Serializer};

use crate::paparazzi::messages::{BaseType, FieldType};

/// The value of one field. Integer variants match the field's declared
/// width exactly; `char[]`/`char[N]` fields are [`Value::Text`]; other arrays
/// are [`Value::Array`] whose elements are all of the field's base type.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    /// `int8`
    I8(i8),
    /// `uint8`
    U8(u8),
    /// `int16`
    I16(i16),
    /// `uint16`
    U16(u16),
    /// `int32`
    I32(i32),
    /// `uint32`
    U32(u32),
    /// `int64`
    I64(i64),
    /// `uint64`
    U64(u64),
    /// `float`
    F32(f32),
    /// `double`
    F64(f64),
    /// `char`
    Char(char),
    /// `string`, or a `char[]` / `char[N]` array.
    Text(String),
    /// Any other array, elements of the field's base type.
    Array(Vec<Value>),
}

impl Value {
    /// The numeric value as `f64`, for scalars of numeric type.
    pub fn as_f64(&self) -> Option<f64> {
        Some(match *self {
            Value::I8(v) => v.into(),
            Value::U8(v) => v.into(),
            Value::I16(v) => v.into(),
            Value::U16(v) => v.into(),
            Value::I32(v) => v.into(),
            Value::U32(v) => v.into(),
            Value::I64(v) => v as f64,
            Value::U64(v) => v as f64,
            Value::F32(v) => v.into(),
            Value::F64(v) => v,
            _ => return None,
        })
    }

    /// The value as `i128`, for scalars of integer type.
    pub fn as_i128(&self) -> Option<i128> {
        Some(match *self {
            Value::I8(v) => v.into(),
            Value::U8(v) => v.into(),
            Value::I16(v) => v.into(),
            Value::U16(v) => v.into(),
            Value::I32(v) => v.into(),
            Value::U32(v) => v.into(),
            Value::I64(v) => v.into(),
            Value::U64(v) => v.into(),
            _ => return None,
        })
    }

    /// The text, for `string` and char-array values.
    pub fn as_str(&self) -> Option<&str> {
        match self {
            Value::Text(s) => Some(s),
            _ => None,
        }
    }

    /// The elements, for non-char arrays.
    pub fn as_array(&self) -> Option<&[Value]> {
        match self {
            Value::Array(v) => Some(v),
            _ => None,
        }
    }

    /// The base type a scalar value belongs to (`None` for text and arrays).
    pub fn scalar_type(&self) -> Option<BaseType> {
        Some(match self {
            Value::I8(_) => BaseType::Int8,
            Value::U8(_) => BaseType::Uint8,
            Value::I16(_) => BaseType::Int16,
            Value::U16(_) => BaseType::Uint16,
            Value::I32(_) => BaseType::Int32,
            Value::U32(_) => BaseType::Uint32,
            Value::I64(_) => BaseType::Int64,
            Value::U64(_) => BaseType::Uint64,
            Value::F32(_) => BaseType::Float,
            Value::F64(_) => BaseType::Double,
            Value::Char(_) => BaseType::Char,
            Value::Text(_) | Value::Array(_) => return None,
        })
    }

    /// Short description of the value's kind, for error messages.
    pub fn kind(&self) -> String {
        match self {
            Value::Text(_) => "text".to_owned(),
            Value::Array(v) => match v.first().and_then(Value::scalar_type) {
                Some(t) => format!("{t}[{}]", v.len()),
                None => format!("array[{}]", v.len()),
            },
            other => other.scalar_type().map(|t| t.name().to_owned()).unwrap_or_default(),
        }
    }

    /// Whether the value has the shape and type `ty` requires (lengths of
    /// arrays are checked separately by the codec).
    pub fn fits(&self, ty: FieldType) -> bool {
        match (ty, self) {
            (FieldType::Scalar(BaseType::String), Value::Text(_)) => true,
            (FieldType::Scalar(b), v) => v.scalar_type() == Some(b),
            (t, Value::Text(_)) if t.is_char_array() => true,
            (FieldType::Array(b) | FieldType::FixedArray(b, _), Value::Array(items)) => {
                b != BaseType::Char && items.iter().all(|v| v.scalar_type() == Some(b))
            }
            _ => false,
        }
    }
}

impl Serialize for Value {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Value::I8(v) => s.serialize_i8(*v),
            Value::U8(v) => s.serialize_u8(*v),
            Value::I16(v) => s.serialize_i16(*v),
            Value::U16(v) => s.serialize_u16(*v),
            Value::I32(v) => s.serialize_i32(*v),
            Value::U32(v) => s.serialize_u32(*v),
            Value::I64(v) => s.serialize_i64(*v),
            Value::U64(v) => s.serialize_u64(*v),
            Value::F32(v) => s.serialize_f32(*v),
            Value::F64(v) => s.serialize_f64(*v),
            Value::Char(c) => s.serialize_char(*c),
            Value::Text(t) => s.serialize_str(t),
            Value::Array(items) => items.serialize(s),
        }
    }
}

impl fmt::Display for Value {
    /// Ivy text form of the value (see [`crate::paparazzi::codec`]).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Value::I8(v) => write!(f, "{v}"),
            Value::U8(v) => write!(f, "{v}"),
            Value::I16(v) => write!(f, "{v}"),
            Value::U16(v) => write!(f, "{v}"),
            Value::I32(v) => write!(f, "{v}"),
            Value::U32(v) => write!(f, "{v}"),
            Value::I64(v) => write!(f, "{v}"),
            Value::U64(v) => write!(f, "{v}"),
            Value::F32(v) => write!(f, "{v}"),
            Value::F64(v) => write!(f, "{v}"),
            Value::Char(c) => write!(f, "{c}"),
            Value::Text(t) => f.write_str(t),
            Value::Array(items) => {
                for (i, v) in items.iter().enumerate() {
                    if i > 0 {
                        f.write_str(",")?;
                    }
                    write!(f, "{v}")?;
                }
                Ok(())
            }
        }
    }
}
