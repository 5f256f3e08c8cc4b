//! Whether every number in a value is finite: a serde serializer that writes nothing and
//! stops at the first NaN or infinity, naming where it is. States that arrive from outside
//! (a neighbour shard's ghosts) are checked with it before they reach the physics, whose
//! contact search panics on non-finite geometry.

use serde::ser::{self, Serialize};

/// Where the first non-finite number is (a path of field names), if there is one.
pub fn first_non_finite<T: Serialize + ?Sized>(value: &T) -> Option<String> {
    // Most values are finite: a walk that keeps nothing and fails with nothing says so (it
    // compiles to a test per number); only a value that is not is walked again to name the place.
    value.serialize(&mut Check(Quick)).err()?;
    match value.serialize(&mut Check(Path(Vec::new()))) {
        Ok(()) => None,
        Err(NonFinite(p)) => Some(p),
    }
}

/// What a walk keeps on its way down and says at a non-finite number.
trait Walk {
    type Error: ser::Error;
    fn float(&self, v: f64) -> Result<(), Self::Error>;
    fn enter(&mut self, name: &'static str);
    fn leave(&mut self);
}

/// The first walk: nothing kept, nothing said.
struct Quick;

#[derive(Debug)]
struct NotFinite;

impl std::fmt::Display for NotFinite {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("a non-finite number")
    }
}

impl std::error::Error for NotFinite {}

impl ser::Error for NotFinite {
    fn custom<M: std::fmt::Display>(_: M) -> Self {
        NotFinite
    }
}

impl Walk for Quick {
    type Error = NotFinite;
    #[inline(always)]
    fn float(&self, v: f64) -> Result<(), NotFinite> {
        if v.is_finite() { Ok(()) } else { Err(NotFinite) }
    }
    #[inline(always)]
    fn enter(&mut self, _: &'static str) {}
    #[inline(always)]
    fn leave(&mut self) {}
}

/// The second walk: the field names down to where it is, for the message.
struct Path(Vec<&'static str>);

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

impl Walk for Path {
    type Error = NonFinite;
    fn float(&self, v: f64) -> Result<(), NonFinite> {
        if v.is_finite() {
            Ok(())
        } else {
            Err(NonFinite(if self.0.is_empty() { "the top".into() } else { self.0.join(".") }))
        }
    }
    fn enter(&mut self, name: &'static str) {
        self.0.push(name);
    }
    fn leave(&mut self) {
        self.0.pop();
    }
}

/// The serializer of either walk.
struct Check<W>(W);

impl<W: Walk> Check<W> {
    #[inline]
    fn within<T: Serialize + ?Sized>(&mut self, name: &'static str, v: &T) -> Result<(), W::Error> {
        self.0.enter(name);
        v.serialize(&mut *self)?;
        self.0.leave();
        Ok(())
    }
}

macro_rules! fine {
    ($($name:ident: $t:ty),*) => {
        $(fn $name(self, _: $t) -> Result<(), W::Error> { Ok(()) })*
    };
}

impl<W: Walk> ser::Serializer for &mut Check<W> {
    type Ok = ();
    type Error = W::Error;
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

    fn serialize_f32(self, v: f32) -> Result<(), W::Error> {
        self.0.float(f64::from(v))
    }
    fn serialize_f64(self, v: f64) -> Result<(), W::Error> {
        self.0.float(v)
    }
    fn serialize_none(self) -> Result<(), W::Error> {
        Ok(())
    }
    fn serialize_some<T: Serialize + ?Sized>(self, v: &T) -> Result<(), W::Error> {
        v.serialize(self)
    }
    fn serialize_unit(self) -> Result<(), W::Error> {
        Ok(())
    }
    fn serialize_unit_variant(self, _: &'static str, _: u32, _: &'static str) -> Result<(), W::Error> {
        Ok(())
    }
    fn serialize_newtype_struct<T: Serialize + ?Sized>(self, _: &'static str, v: &T) -> Result<(), W::Error> {
        v.serialize(self)
    }
    fn serialize_newtype_variant<T: Serialize + ?Sized>(
        self,
        _: &'static str,
        _: u32,
        variant: &'static str,
        v: &T,
    ) -> Result<(), W::Error> {
        self.within(variant, v)
    }
    fn serialize_seq(self, _: Option<usize>) -> Result<Self, W::Error> {
        Ok(self)
    }
    fn serialize_tuple(self, _: usize) -> Result<Self, W::Error> {
        Ok(self)
    }
    fn serialize_tuple_struct(self, _: &'static str, _: usize) -> Result<Self, W::Error> {
        Ok(self)
    }
    fn serialize_tuple_variant(self, _: &'static str, _: u32, _: &'static str, _: usize) -> Result<Self, W::Error> {
        Ok(self)
    }
    fn serialize_map(self, _: Option<usize>) -> Result<Self, W::Error> {
        Ok(self)
    }
    fn serialize_struct(self, _: &'static str, _: usize) -> Result<Self, W::Error> {
        Ok(self)
    }
    fn serialize_struct_variant(self, _: &'static str, _: u32, _: &'static str, _: usize) -> Result<Self, W::Error> {
        Ok(self)
    }
}

macro_rules! elements {
    ($($tr:ident :: $m:ident),*) => {
        $(impl<W: Walk> ser::$tr for &mut Check<W> {
            type Ok = ();
            type Error = W::Error;
            fn $m<T: Serialize + ?Sized>(&mut self, v: &T) -> Result<(), W::Error> {
                v.serialize(&mut **self)
            }
            fn end(self) -> Result<(), W::Error> {
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

impl<W: Walk> ser::SerializeMap for &mut Check<W> {
    type Ok = ();
    type Error = W::Error;
    fn serialize_key<T: Serialize + ?Sized>(&mut self, k: &T) -> Result<(), W::Error> {
        k.serialize(&mut **self)
    }
    fn serialize_value<T: Serialize + ?Sized>(&mut self, v: &T) -> Result<(), W::Error> {
        v.serialize(&mut **self)
    }
    fn end(self) -> Result<(), W::Error> {
        Ok(())
    }
}

macro_rules! fields {
    ($($tr:ident),*) => {
        $(impl<W: Walk> ser::$tr for &mut Check<W> {
            type Ok = ();
            type Error = W::Error;
            fn serialize_field<T: Serialize + ?Sized>(&mut self, key: &'static str, v: &T) -> Result<(), W::Error> {
                self.within(key, v)
            }
            fn end(self) -> Result<(), W::Error> {
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
