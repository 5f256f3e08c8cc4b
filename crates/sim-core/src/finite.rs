//! Whether every number in a value is finite: a serde serializer that writes nothing and
//! stops at the first NaN or infinity, naming where it is. States that arrive from outside
//! (a neighbour shard's ghosts) are checked with it before they reach the physics, whose
//! contact search panics on non-finite geometry.

use serde::ser::{self, Serialize};

/// Where the first non-finite number is (a path of field names), if there is one.
pub fn first_non_finite<T: Serialize + ?Sized>(value: &T) -> Option<String> {
    // Most values are finite: a walk that keeps no path says so; only a value that is not is
    // walked again to name the place.
    value.serialize(&mut Check { path: None }).err()?;
    match value.serialize(&mut Check { path: Some(Vec::new()) }) {
        Ok(()) => None,
        Err(NonFinite(p)) => Some(p),
    }
}

#[derive(Debug)]
struct NonFinite(String);

impl std::fmt::Display for NonFinite {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "a non-finite number at {}", self.0)
    }
}

impl std::error::Error for NonFinite {}

impl ser::Error for NonFinite {
    fn custom<M: std::fmt::Display>(msg: M) -> Self {
        NonFinite(msg.to_string())
    }
}

/// The walk: with a path, it keeps the field names down to where it is (for the message).
struct Check {
    path: Option<Vec<&'static str>>,
}

impl Check {
    #[inline]
    fn float(&self, v: f64) -> Result<(), NonFinite> {
        if v.is_finite() {
            Ok(())
        } else {
            Err(NonFinite(match &self.path {
                Some(path) if !path.is_empty() => path.join("."),
                _ => "the top".into(),
            }))
        }
    }

    #[inline]
    fn within<T: Serialize + ?Sized>(&mut self, name: &'static str, v: &T) -> Result<(), NonFinite> {
        if let Some(path) = &mut self.path {
            path.push(name);
        }
        v.serialize(&mut *self)?;
        if let Some(path) = &mut self.path {
            path.pop();
        }
        Ok(())
    }
}

macro_rules! fine {
    ($($name:ident: $t:ty),*) => {
        $(fn $name(self, _: $t) -> Result<(), NonFinite> { Ok(()) })*
    };
}

impl ser::Serializer for &mut Check {
    type Ok = ();
    type Error = NonFinite;
    type SerializeSeq = Self;
    type SerializeTuple = Self;
    type SerializeTupleStruct = Self;
    type SerializeTupleVariant = Self;
    type SerializeMap = Self;
    type SerializeStruct = Self;
    type SerializeStructVariant = Self;

    fine!(serialize_bool: bool, serialize_i8: i8, serialize_i16: i16, serialize_i32: i32, serialize_i64: i64,
        serialize_u8: u8, serialize_u16: u16, serialize_u32: u32, serialize_u64: u64, serialize_char: char,
        serialize_str: &str, serialize_bytes: &[u8], serialize_unit_struct: &'static str);

    fn serialize_f32(self, v: f32) -> Result<(), NonFinite> {
        self.float(f64::from(v))
    }
    fn serialize_f64(self, v: f64) -> Result<(), NonFinite> {
        self.float(v)
    }
    fn serialize_none(self) -> Result<(), NonFinite> {
        Ok(())
    }
    fn serialize_some<T: Serialize + ?Sized>(self, v: &T) -> Result<(), NonFinite> {
        v.serialize(self)
    }
    fn serialize_unit(self) -> Result<(), NonFinite> {
        Ok(())
    }
    fn serialize_unit_variant(self, _: &'static str, _: u32, _: &'static str) -> Result<(), NonFinite> {
        Ok(())
    }
    fn serialize_newtype_struct<T: Serialize + ?Sized>(self, _: &'static str, v: &T) -> Result<(), NonFinite> {
        v.serialize(self)
    }
    fn serialize_newtype_variant<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        _: u32,
        variant: &'static str,
        v: &T,
    ) -> Result<(), NonFinite> {
        self.within(variant, v)
    }
    fn serialize_seq(self, _: Option<usize>) -> Result<Self, NonFinite> {
        Ok(self)
    }
    fn serialize_tuple(self, _: usize) -> Result<Self, NonFinite> {
        Ok(self)
    }
    fn serialize_tuple_struct(self, _: &'static str, _: usize) -> Result<Self, NonFinite> {
        Ok(self)
    }
    fn serialize_tuple_variant(self, _: &'static str, _: u32, _: &'static str, _: usize) -> Result<Self, NonFinite> {
        Ok(self)
    }
    fn serialize_map(self, _: Option<usize>) -> Result<Self, NonFinite> {
        Ok(self)
    }
    fn serialize_struct(self, _: &'static str, _: usize) -> Result<Self, NonFinite> {
        Ok(self)
    }
    fn serialize_struct_variant(self, _: &'static str, _: u32, _: &'static str, _: usize) -> Result<Self, NonFinite> {
        Ok(self)
    }
}

macro_rules! elements {
    ($($tr:ident :: $m:ident),*) => {
        $(impl ser::$tr for &mut Check {
            type Ok = ();
            type Error = NonFinite;
            fn $m<T: Serialize + ?Sized>(&mut self, v: &T) -> Result<(), NonFinite> {
                v.serialize(&mut **self)
            }
            fn end(self) -> Result<(), NonFinite> {
                Ok(())
            }
        })*
    };
}

elements!(
    SerializeSeq::serialize_element,
    SerializeTuple::serialize_element,
    SerializeTupleStruct::serialize_field,
    SerializeTupleVariant::serialize_field
);

impl ser::SerializeMap for &mut Check {
    type Ok = ();
    type Error = NonFinite;
    fn serialize_key<T: Serialize + ?Sized>(&mut self, k: &T) -> Result<(), NonFinite> {
        k.serialize(&mut **self)
    }
    fn serialize_value<T: Serialize + ?Sized>(&mut self, v: &T) -> Result<(), NonFinite> {
        v.serialize(&mut **self)
    }
    fn end(self) -> Result<(), NonFinite> {
        Ok(())
    }
}

macro_rules! fields {
    ($($tr:ident),*) => {
        $(impl ser::$tr for &mut Check {
            type Ok = ();
            type Error = NonFinite;
            fn serialize_field<T: Serialize + ?Sized>(&mut self, key: &'static str, v: &T) -> Result<(), NonFinite> {
                self.within(key, v)
            }
            fn end(self) -> Result<(), NonFinite> {
                Ok(())
            }
        })*
    };
}

fields!(SerializeStruct, SerializeStructVariant);

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(serde::Serialize)]
    struct Inner {
        v: Vec<f32>,
    }

    #[derive(serde::Serialize)]
    struct Outer {
        a: f64,
        inner: Inner,
        o: Option<[f32; 2]>,
    }

    #[test]
    fn finds_the_first_non_finite_number_and_its_path() {
        let ok = Outer { a: 1.0, inner: Inner { v: vec![0.0, 2.0] }, o: Some([1.0, 2.0]) };
        assert_eq!(first_non_finite(&ok), None);
        let bad = Outer { a: 1.0, inner: Inner { v: vec![0.0, f32::NAN] }, o: None };
        assert_eq!(first_non_finite(&bad).as_deref(), Some("inner.v"));
        let bad = Outer { a: 1.0, inner: Inner { v: vec![] }, o: Some([f32::INFINITY, 0.0]) };
        assert_eq!(first_non_finite(&bad).as_deref(), Some("o"));
    }
}
