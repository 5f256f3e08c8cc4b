//! CDR as ROS 2 puts it on the wire (classic CDR, XCDR1, as Fast-CDR writes it for
//! rmw_zenoh): a 4-byte encapsulation header, then the fields, each primitive aligned to its
//! size counted from the end of the header; strings as a `u32` length that counts a closing
//! NUL; sequences as a `u32` count; nested messages inline. No padding at the end.

/// Little-endian CDR, options 0.
pub const HEADER_LE: [u8; 4] = [0, 1, 0, 0];

/// A CDR message being written (little-endian).
#[derive(Clone, Debug)]
pub struct CdrWriter {
    buf: Vec<u8>,
}

impl Default for CdrWriter {
    fn default() -> Self {
        Self::new()
    }
}

impl CdrWriter {
    /// An empty message: the header only.
    pub fn new() -> Self {
        Self { buf: HEADER_LE.to_vec() }
    }

    /// The bytes written, header included.
    pub fn into_bytes(self) -> Vec<u8> {
        self.buf
    }

    fn align(&mut self, n: usize) {
        let pad = (n - (self.buf.len() - 4) % n) % n;
        self.buf.resize(self.buf.len() + pad, 0);
    }

    /// A `uint8` (or `byte`, `char`).
    pub fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }

    /// A `bool`.
    pub fn bool(&mut self, v: bool) {
        self.buf.push(u8::from(v));
    }

    /// An `int32`.
    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    /// A `uint32` (also sequence counts).
    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    /// A `float32`.
    pub fn f32(&mut self, v: f32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    /// A `float64`.
    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }

    /// `float64[N]` (no count).
    pub fn f64s(&mut self, v: &[f64]) {
        for &x in v {
            self.f64(x);
        }
    }

    /// A `string`: length with the NUL, bytes, NUL.
    pub fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.buf.extend_from_slice(s.as_bytes());
        self.buf.push(0);
    }

    /// A sequence's count (its elements follow).
    pub fn seq(&mut self, n: usize) {
        self.u32(n as u32);
    }
}

/// Why a CDR message could not be read.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum CdrError {
    /// Fewer bytes than the message needs.
    #[error("CDR: message ends at byte {len}, {need} more needed for {what}")]
    Short {
        /// What was being read.
        what: &'static str,
        /// Bytes missing.
        need: usize,
        /// The message's length.
        len: usize,
    },
    /// An encapsulation this reader does not know.
    #[error("CDR: encapsulation {0:02x?} is not CDR (00 00 or 00 01)")]
    Encapsulation([u8; 2]),
    /// A string that is not UTF-8 or not NUL-terminated.
    #[error("CDR: a string is {0}")]
    BadString(&'static str),
}

/// A CDR message being read (either byte order).
#[derive(Debug)]
pub struct CdrReader<'a> {
    data: &'a [u8],
    pos: usize,
    little: bool,
}

impl<'a> CdrReader<'a> {
    /// Checks the encapsulation header.
    pub fn new(data: &'a [u8]) -> Result<Self, CdrError> {
        let short = || CdrError::Short { what: "the header", need: 4usize.saturating_sub(data.len()), len: data.len() };
        let head = data.get(..4).ok_or_else(short)?;
        let little = match [head[0], head[1]] {
            [0, 1] => true,
            [0, 0] => false,
            other => return Err(CdrError::Encapsulation(other)),
        };
        Ok(Self { data, pos: 4, little })
    }

    fn take<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], CdrError> {
        let pad = (N - (self.pos - 4) % N) % N;
        let start = self.pos + pad;
        let bytes = self.data.get(start..start + N).ok_or_else(|| CdrError::Short {
            what,
            need: (start + N).saturating_sub(self.data.len()),
            len: self.data.len(),
        })?;
        self.pos = start + N;
        let mut out = [0u8; N];
        out.copy_from_slice(bytes);
        if !self.little {
            out.reverse();
        }
        Ok(out)
    }

    /// An `int32`.
    pub fn i32(&mut self, what: &'static str) -> Result<i32, CdrError> {
        self.take::<4>(what).map(i32::from_le_bytes)
    }

    /// A `uint32`.
    pub fn u32(&mut self, what: &'static str) -> Result<u32, CdrError> {
        self.take::<4>(what).map(u32::from_le_bytes)
    }

    /// A `float64`.
    pub fn f64(&mut self, what: &'static str) -> Result<f64, CdrError> {
        self.take::<8>(what).map(f64::from_le_bytes)
    }

    /// A `string`.
    pub fn string(&mut self, what: &'static str) -> Result<&'a str, CdrError> {
        let n = self.u32(what)? as usize;
        let bytes = self.data.get(self.pos..self.pos.saturating_add(n)).ok_or_else(|| CdrError::Short {
            what,
            need: self.pos.saturating_add(n).saturating_sub(self.data.len()),
            len: self.data.len(),
        })?;
        self.pos += n;
        let text = bytes.strip_suffix(&[0]).ok_or(CdrError::BadString("not NUL-terminated"))?;
        std::str::from_utf8(text).map_err(|_| CdrError::BadString("not UTF-8"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn time_and_strings_match_rosbags_bytes() {
        // builtin_interfaces/Time{1700000000, 123456789} and std_msgs/String{"hi"}, as
        // rosbags' serialize_cdr writes them.
        let mut w = CdrWriter::new();
        w.i32(1_700_000_000);
        w.u32(123_456_789);
        assert_eq!(w.into_bytes(), [0, 1, 0, 0, 0x00, 0xf1, 0x53, 0x65, 0x15, 0xcd, 0x5b, 0x07]);
        let mut w = CdrWriter::new();
        w.string("hi");
        assert_eq!(w.into_bytes(), [0, 1, 0, 0, 3, 0, 0, 0, b'h', b'i', 0]);
    }

    #[test]
    fn doubles_align_to_eight_after_the_header() {
        let mut w = CdrWriter::new();
        w.string("odom"); // 4 + 5 bytes: the double starts at 16 (8-aligned), after 7 zeros
        w.f64(1.0);
        let b = w.into_bytes();
        assert_eq!(b.len(), 4 + 24);
        assert_eq!(&b[13..20], &[0; 7]);
        let mut r = CdrReader::new(&b).unwrap();
        assert_eq!(r.string("s").unwrap(), "odom");
        assert_eq!(r.f64("x").unwrap(), 1.0);
        assert!(matches!(r.f64("y"), Err(CdrError::Short { .. })));
    }

    #[test]
    fn big_endian_reads_and_bad_headers_are_errors() {
        let mut be = vec![0, 0, 0, 0];
        be.extend_from_slice(&7i32.to_be_bytes());
        assert_eq!(CdrReader::new(&be).unwrap().i32("n").unwrap(), 7);
        assert_eq!(CdrReader::new(&[0, 7, 0, 0]).unwrap_err(), CdrError::Encapsulation([0, 7]));
        assert!(CdrReader::new(&[0, 1]).is_err());
        let mut r = CdrReader::new(&[0, 1, 0, 0, 200, 0, 0, 0, b'a']).unwrap();
        assert!(matches!(r.string("s"), Err(CdrError::Short { .. })));
    }
}
