//! Helpers shared by the integration tests: locating the shared data
//! directory (skipping loudly, or failing under `CI=true`, when it is absent) and a
//! deterministic value generator.

#![allow(dead_code)]

use std::path::{Path, PathBuf};

use bridge::Value;
use bridge::paparazzi::messages::{BaseType, FieldType, MessageDef};

/// Where the shared data directory was expected, when it is absent.
#[derive(Debug)]
pub struct MissingSharedData {
    /// The path that was expected.
    pub expected: PathBuf,
    /// How it was chosen.
    pub how: String,
}

impl std::fmt::Display for MissingSharedData {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} ({})", self.expected.display(), self.how)
    }
}

/// `$TWINSWARM_SHARED_DATA` if set, else `shared/data` in the nearest ancestor of this crate
/// that has one (the repository's `../shared/data`; works from `/work/wip/bridge` and
/// `/work/main/crates/bridge`).
pub fn shared_data_dir() -> Result<PathBuf, MissingSharedData> {
    if let Some(p) = std::env::var_os("TWINSWARM_SHARED_DATA") {
        let p = PathBuf::from(p);
        return if p.is_dir() {
            Ok(p)
        } else {
            Err(MissingSharedData { expected: p, how: "from TWINSWARM_SHARED_DATA".into() })
        };
    }
    let start = Path::new(env!("CARGO_MANIFEST_DIR"));
    for d in start.ancestors() {
        let cand = d.join("shared").join("data");
        if cand.is_dir() {
            return Ok(cand);
        }
    }
    // crates/bridge -> crates -> the repository -> its parent.
    let expected = start.ancestors().nth(3).unwrap_or(start).join("shared").join("data");
    let how = format!("nor shared/data in any other ancestor of {}; TWINSWARM_SHARED_DATA unset", start.display());
    Err(MissingSharedData { expected, how })
}

/// Whether the tests run under CI (`CI=true` or `CI=1`, as CI services set it).
pub fn under_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| v.eq_ignore_ascii_case("true") || v == "1")
}

/// The shared data directory for `test`, or `None` after a loud skip notice when it is
/// absent. Under CI (see [`under_ci`]) an absent directory is a failure instead.
///
/// A skip writes one line, `test<TAB>path`, to the file named by `$TWINSWARM_SKIP_LOG` (if
/// set; `scripts/test.sh` sets it and counts the lines), and a notice straight to stderr:
/// `std::io::stderr()` bypasses libtest's capture, which would hide an `eprintln!` of a
/// passing test.
pub fn shared_data_or_skip(test: &str) -> Option<PathBuf> {
    use std::io::Write;
    let missing = match shared_data_dir() {
        Ok(d) => return Some(d),
        Err(missing) => missing,
    };
    if under_ci() {
        panic!(
            "{test}: shared data not found at {missing}; CI=true, so this is a failure, not a skip \
             (provide the directory or point TWINSWARM_SHARED_DATA at it)"
        );
    }
    let notice = format!("\nSKIPPED {test}: shared data not found at {missing}\n");
    let _ = std::io::stderr().write_all(notice.as_bytes());
    if let Some(log) = std::env::var_os("TWINSWARM_SKIP_LOG") {
        let line = format!("{test}\t{}\n", missing.expected.display());
        let appended = std::fs::OpenOptions::new().create(true).append(true).open(&log);
        if let Err(e) = appended.and_then(|mut f| f.write_all(line.as_bytes())) {
            panic!("{test}: cannot record the skip in TWINSWARM_SKIP_LOG={}: {e}", Path::new(&log).display());
        }
    }
    None
}

/// Returns the shared data dir, or returns from the calling test after
/// [`shared_data_or_skip`] (a loud skip; a failure under `CI=true`).
#[macro_export]
macro_rules! shared_or_skip {
    () => {{
        fn here() {}
        let name = std::any::type_name_of_val(&here);
        match common::shared_data_or_skip(name.strip_suffix("::here").unwrap_or(name)) {
            Some(d) => d,
            None => return,
        }
    }};
}

/// Path of a file in the crate's `assets/`.
pub fn asset(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets").join(rel)
}

/// All `.xml` files below `dir`, sorted.
pub fn xml_files(dir: &Path) -> Vec<PathBuf> {
    files_with_extension(dir, "xml")
}

/// All files below `dir` whose extension is `ext`, sorted.
pub fn files_with_extension(dir: &Path, ext: &str) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(rd) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == ext) {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

/// Deterministic xorshift64* generator.
pub struct Gen(u64);

impl Gen {
    pub fn new(seed: u64) -> Gen {
        Gen(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }

    pub fn next_u64(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        x.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    pub fn below(&mut self, n: u64) -> u64 {
        self.next_u64() % n.max(1)
    }

    fn pick<'a, T>(&mut self, items: &'a [T]) -> &'a T {
        &items[self.below(items.len() as u64) as usize]
    }

    fn int_in(&mut self, min: i128, max: i128) -> i128 {
        match self.below(5) {
            0 => min,
            1 => max,
            2 => 0.clamp(min, max),
            _ => {
                let span = (max - min) as u128 + 1;
                let r = ((u128::from(self.next_u64()) << 64) | u128::from(self.next_u64())) % span;
                min + r as i128
            }
        }
    }

    fn f64_any(&mut self) -> f64 {
        match self.below(8) {
            0 => 0.0,
            1 => -0.0,
            2 => 1.5,
            3 => -1234.5678,
            4 => 1e-300,
            5 => f64::MAX,
            _ => loop {
                let v = f64::from_bits(self.next_u64());
                if v.is_finite() {
                    break v;
                }
            },
        }
    }

    fn f32_any(&mut self) -> f32 {
        match self.below(8) {
            0 => 0.0,
            1 => -0.0,
            2 => 0.1,
            3 => -3.25,
            4 => f32::MIN_POSITIVE,
            5 => f32::MAX,
            _ => loop {
                let v = f32::from_bits(self.next_u64() as u32);
                if v.is_finite() {
                    break v;
                }
            },
        }
    }

    fn text(&mut self, alphabet: &[u8], min: usize, max: usize) -> String {
        let len = min + self.below((max - min + 1) as u64) as usize;
        (0..len).map(|_| *self.pick(alphabet) as char).collect()
    }

    pub fn scalar(&mut self, b: BaseType) -> Value {
        if let Some((min, max)) = b.int_range() {
            let n = self.int_in(min, max);
            return match b {
                BaseType::Int8 => Value::I8(n as i8),
                BaseType::Uint8 => Value::U8(n as u8),
                BaseType::Int16 => Value::I16(n as i16),
                BaseType::Uint16 => Value::U16(n as u16),
                BaseType::Int32 => Value::I32(n as i32),
                BaseType::Uint32 => Value::U32(n as u32),
                BaseType::Int64 => Value::I64(n as i64),
                _ => Value::U64(n as u64),
            };
        }
        match b {
            BaseType::Float => Value::F32(self.f32_any()),
            BaseType::Double => Value::F64(self.f64_any()),
            BaseType::Char => Value::Char(*self.pick(b"AZaz09_-+.:") as char),
            _ => Value::Text(self.text(b"ABCxyz0189_,.;:-", 1, 8)),
        }
    }

    /// A value for every field of `def`, covering arrays and texts.
    pub fn values(&mut self, def: &MessageDef) -> Vec<Value> {
        def.fields
            .iter()
            .map(|f| match f.ty {
                FieldType::Scalar(b) => self.scalar(b),
                FieldType::Array(BaseType::Char) => Value::Text(self.text(b"abc XYZ 09_-.", 0, 10)),
                FieldType::FixedArray(BaseType::Char, n) => Value::Text(self.text(b"abc XYZ 09_-.", 0, n)),
                FieldType::Array(b) => {
                    let n = 1 + self.below(5) as usize;
                    Value::Array((0..n).map(|_| self.scalar(b)).collect())
                }
                FieldType::FixedArray(b, n) => Value::Array((0..n).map(|_| self.scalar(b)).collect()),
            })
            .collect()
    }
}

/// Equality that compares floats by their bits (so -0.0 != 0.0).
pub fn same_bits(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::F32(x), Value::F32(y)) => x.to_bits() == y.to_bits(),
        (Value::F64(x), Value::F64(y)) => x.to_bits() == y.to_bits(),
        (Value::Array(x), Value::Array(y)) => x.len() == y.len() && x.iter().zip(y).all(|(p, q)| same_bits(p, q)),
        _ => a == b,
    }
}
