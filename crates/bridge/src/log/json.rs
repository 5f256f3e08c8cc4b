//! A minimal JSON writer for the per-step messages, which are most of a log's bytes.
//!
//! serde_json spends much of its time on what is fixed here: it escapes every key and every
//! name. This writer appends keys as literals and names pre-escaped ([`quoted`]), and formats
//! numbers as serde_json does (`itoa`; `zmij`'s shortest round-trip floats, `null` for NaN
//! and infinities), so the output is the same text byte for byte (tested in `encode.rs`
//! against serde's encoding of reference structs).

use serde::Serialize;

/// Appends JSON to a reused buffer.
pub(crate) struct Json<'a>(pub &'a mut Vec<u8>);

impl<'a> Json<'a> {
    /// A writer on `buf`, emptied and then holding `head`.
    pub fn starting(buf: &'a mut Vec<u8>, head: &[u8]) -> Self {
        buf.clear();
        buf.extend_from_slice(head);
        Json(buf)
    }

    /// Literal JSON text: punctuation and keys, e.g. `,"pos_m":`.
    #[inline]
    pub fn raw(&mut self, text: &str) -> &mut Self {
        self.0.extend_from_slice(text.as_bytes());
        self
    }

    #[inline]
    pub fn u64(&mut self, v: u64) -> &mut Self {
        self.raw(itoa::Buffer::new().format(v))
    }

    #[inline]
    pub fn f32(&mut self, v: f32) -> &mut Self {
        if v.to_bits() == 0 {
            self.raw("0.0") // common (idle commands, zero rates), and what zmij would write
        } else if v.is_finite() {
            self.raw(zmij::Buffer::new().format_finite(v))
        } else {
            self.raw("null")
        }
    }

    #[inline]
    pub fn f64(&mut self, v: f64) -> &mut Self {
        if v.is_finite() { self.raw(zmij::Buffer::new().format_finite(v)) } else { self.raw("null") }
    }

    #[inline]
    pub fn bool(&mut self, v: bool) -> &mut Self {
        self.raw(if v { "true" } else { "false" })
    }

    /// `[a,b,…]`, each element written by `item`.
    fn seq<T: Copy>(&mut self, v: &[T], item: fn(&mut Self, T) -> &mut Self) -> &mut Self {
        self.0.push(b'[');
        for (i, &x) in v.iter().enumerate() {
            if i > 0 {
                self.0.push(b',');
            }
            item(self, x);
        }
        self.raw("]")
    }

    /// `[a,b,…]`.
    pub fn f32s(&mut self, v: &[f32]) -> &mut Self {
        self.seq(v, Self::f32)
    }

    pub fn bools(&mut self, v: &[bool]) -> &mut Self {
        self.seq(v, Self::bool)
    }

    pub fn opt_f32(&mut self, v: Option<f32>) -> &mut Self {
        match v {
            Some(x) => self.f32(x),
            None => self.raw("null"),
        }
    }

    pub fn opt_f32s(&mut self, v: Option<&[f32]>) -> &mut Self {
        match v {
            Some(x) => self.f32s(x),
            None => self.raw("null"),
        }
    }

    /// `{"sec":…,"nsec":…}` of a time in ns.
    pub fn time(&mut self, ns: u64) -> &mut Self {
        self.raw("{\"sec\":").u64(ns / 1_000_000_000).raw(",\"nsec\":").u64(ns % 1_000_000_000).raw("}")
    }

    /// An object of floats: `keys[k]` is the text before value `k` (`{"x":`, `,"y":`, …).
    fn floats<const N: usize>(&mut self, keys: [&str; N], v: [f32; N]) -> &mut Self {
        for (key, x) in keys.into_iter().zip(v) {
            self.raw(key).f32(x);
        }
        self.raw("}")
    }

    /// `{"x":…,"y":…,"z":…}`.
    pub fn xyz(&mut self, v: [f32; 3]) -> &mut Self {
        self.floats(["{\"x\":", ",\"y\":", ",\"z\":"], v)
    }

    /// `{"x":…,"y":…,"z":…,"w":…}`.
    pub fn xyzw(&mut self, v: [f32; 4]) -> &mut Self {
        self.floats(["{\"x\":", ",\"y\":", ",\"z\":", ",\"w\":"], v)
    }

    /// `{"r":…,"g":…,"b":…,"a":…}`.
    pub fn rgba(&mut self, c: [f32; 4]) -> &mut Self {
        self.floats(["{\"r\":", ",\"g\":", ",\"b\":", ",\"a\":"], c)
    }

    /// Anything else (enums, the rare crash cause), through serde.
    pub fn serde<T: Serialize + ?Sized>(&mut self, v: &T) -> &mut Self {
        // Serialising plain enums and structs of numbers into a Vec cannot fail.
        let _ = serde_json::to_writer(&mut *self.0, v);
        self
    }
}

/// A string as a JSON string literal, quotes included: computed once per name.
pub(crate) fn quoted(s: &str) -> String {
    serde_json::to_string(s).unwrap_or_else(|_| "\"?\"".to_owned())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_match_serde_json() {
        let mut buf = Vec::new();
        let floats = [0.0f32, -0.0, 1.0, 0.1, -1.47e-5, 1.1899999, 3.4e38, f32::NAN, f32::INFINITY, f32::MIN_POSITIVE];
        Json(&mut buf).f32s(&floats);
        assert_eq!(String::from_utf8(buf).unwrap(), serde_json::to_string(&floats).unwrap());
        let mut buf = Vec::new();
        Json(&mut buf).f64(0.05).raw(",").u64(u64::MAX).raw(",").opt_f32(None).raw(",").bools(&[true, false]);
        assert_eq!(String::from_utf8(buf).unwrap(), "0.05,18446744073709551615,null,[true,false]");
        assert_eq!(quoted("a\"b\\c"), r#""a\"b\\c""#);
    }
}
