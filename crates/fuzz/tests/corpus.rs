//! CI's smoke pass of every fuzz target: each file of its corpus, its regressions and the
//! project's own assets of its kind, then a few hundred deterministic mutations of them
//! (bit flips, cuts, splices, repeats). The long, coverage-guided runs are
//! `scripts/fuzz.sh`'s; their corpora land in `corpus/` and every crash they found in
//! `regressions/`, so this replays them all.

use std::panic::AssertUnwindSafe;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).to_owned()
}

/// The project's own files that are valid inputs of `target`.
fn assets(target: &str) -> Vec<PathBuf> {
    let a = root().join("../../assets");
    match target {
        "scene" => vec![a.join("scenes/finken_lab.toml"), a.join("scenes/mixed_lab.toml")],
        "messages_xml" => vec![a.join("paparazzi/messages.xml")],
        "conf_xml" => vec![a.join("paparazzi/conf.xml")],
        "pairing_xml" => vec![a.join("pairing/finken_lab.xml"), a.join("pairing/mixed_lab.xml")],
        "telemetry_xml" => vec![a.join("paparazzi/telemetry.xml")],
        "plot" => {
            files(&root().join("corpus/mcap")).into_iter().chain(files(&root().join("regressions/mcap"))).collect()
        }
        _ => Vec::new(),
    }
}

fn files(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = match std::fs::read_dir(dir) {
        Ok(rd) => rd.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_file()).collect(),
        Err(_) => Vec::new(),
    };
    v.sort();
    v
}

/// A small deterministic generator (xorshift64*), so the pass is the same on every run.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    fn below(&mut self, n: usize) -> usize {
        if n == 0 { 0 } else { (self.next() % n as u64) as usize }
    }
}

/// One mutation of `seed`, in the spirit of AFL's havoc stage.
fn mutate(seed: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut v = seed.to_vec();
    for _ in 0..1 + rng.below(4) {
        let n = v.len();
        match rng.below(6) {
            0 if n > 0 => {
                let i = rng.below(n);
                v[i] ^= 1 << rng.below(8);
            }
            1 if n > 0 => {
                let i = rng.below(n);
                v[i] = [0, 0xff, b'9', b'-', b'"', b'<', b'\n', b'[', 0x7f][rng.below(9)];
            }
            2 => v.truncate(rng.below(n + 1)),
            3 if n > 0 => {
                let (i, len) = (rng.below(n), 1 + rng.below(64));
                let chunk: Vec<u8> = v[i..(i + len).min(n)].to_vec();
                let at = rng.below(n + 1);
                v.splice(at..at, chunk);
            }
            4 if n > 0 => {
                let (i, len) = (rng.below(n), 1 + rng.below(32));
                v.drain(i..(i + len).min(n));
            }
            _ => {
                let at = rng.below(n + 1);
                let digits = ["1e308", "-1", "4294967296", "NaN", "99999999999999999999", "0"][rng.below(6)];
                v.splice(at..at, digits.bytes());
            }
        }
    }
    v
}

fn run_one(name: &str, f: fn(&[u8]), what: &str, data: &[u8]) {
    if std::panic::catch_unwind(AssertUnwindSafe(|| f(data))).is_err() {
        let keep = std::env::temp_dir().join(format!("twinswarm-fuzz-{name}-failure"));
        let _ = std::fs::write(&keep, data);
        panic!("fuzz target {name} panicked on {what} (input kept in {})", keep.display());
    }
}

#[test]
fn every_target_survives_its_corpus_and_mutations_of_it() {
    let mut report = Vec::new();
    for &(name, f) in twinswarm_fuzz::TARGETS {
        let mut seeds: Vec<(String, Vec<u8>)> = Vec::new();
        for p in assets(name)
            .into_iter()
            .chain(files(&root().join("corpus").join(name)))
            .chain(files(&root().join("regressions").join(name)))
        {
            let data = std::fs::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            seeds.push((p.display().to_string(), data));
        }
        for (k, data) in twinswarm_fuzz::seeds(name).into_iter().enumerate() {
            seeds.push((format!("generated seed {k}"), data));
        }
        assert!(!seeds.is_empty(), "fuzz target {name} has no corpus");
        for (what, data) in &seeds {
            run_one(name, f, what, data);
        }
        // The file-reading targets cost milliseconds an input; the parsers microseconds.
        let per_seed = match name {
            "mcap" | "plot" | "log" | "log_merge" => 12,
            "ghost_batch" => 40,
            _ => 150,
        };
        let mut rng = Rng(0x9E37_79B9_7F4A_7C15 ^ name.len() as u64);
        let mut runs = seeds.len();
        for (what, data) in &seeds {
            for k in 0..per_seed {
                let m = mutate(data, &mut rng);
                run_one(name, f, &format!("mutation {k} of {what}"), &m);
                runs += 1;
            }
        }
        report.push(format!("{name}: {} seeds, {runs} inputs", seeds.len()));
    }
    eprintln!("fuzz smoke pass: {}", report.join("; "));
}

#[test]
fn every_target_has_a_corpus_folder() {
    for &(name, _) in twinswarm_fuzz::TARGETS {
        let dir = root().join("corpus").join(name);
        assert!(dir.is_dir(), "missing {}", dir.display());
    }
}
