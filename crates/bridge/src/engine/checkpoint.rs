//! Checkpoints: a run saved between two steps, bit for bit, so that a run (a shard of a
//! sharded run, above all) can go on after its process died.
//!
//! A checkpoint holds everything the step loop carries from one step to the next that the
//! result depends on: the [`State`] (random streams included), the [`Inputs`], a shard's
//! view ([`ShardSnapshot`]: roles and sleep flags, which a serialised `State` leaves out) and
//! the neighbours' ghost batches that already arrived for the next step ([`GhostBatch`]es in
//! the link's inbox). Restored and stepped, it gives the bytes of the uninterrupted run.
//!
//! What it does not hold, because it does not change the states: the counters, the summary's
//! aggregates and the log writer's memory of the last sample written per copter (a restored
//! run writes every copter at its first logged step, as a shard does on taking a copter
//! over). Twins, `--ivy` and `--pairing` carry state between steps that is not saved (twin
//! synchronisation filters, telemetry timers); a run with them does not checkpoint.
//!
//! # File
//! `<dir>/<stem>-tick-<tick, 12 digits>.ckpt`, with `<stem>` `shard-K-of-N` or `run`:
//! - 8 bytes magic and format version, `TWCKPT` `0x00` `0x04` (2: ghosts carry their holder; 3: one collider per copter, one fixed body per wall, floor and box; 4: the estimate holds the IR reading and the lab firmware's height loop);
//! - the payload's CRC-32 (little-endian u32) and length (little-endian u64);
//! - the payload, postcard: a [`RunKey`] first (what run it belongs to), then the tick, the
//!   state, the inputs, the shard view and the batches.
//!
//! Written atomically: a `.tmp` file, `fsync`, `rename`, then the directory is synced. The
//! newest [`KEEP`] of each stem are kept. All shards of a run checkpoint at the same ticks,
//! the multiples of [`Checkpointer::every_ticks`], after the step is complete.

use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sim_core::shard::ShardSnapshot;
use sim_core::{Inputs, State, World};

use crate::shard::GhostBatch;

/// Magic and format version at the start of every checkpoint file.
const MAGIC: &[u8; 8] = b"TWCKPT\x00\x04";

/// Header bytes: magic, CRC-32, payload length.
const HEADER: usize = 8 + 4 + 8;

/// Checkpoints kept per stem (shard).
pub const KEEP: usize = 2;

/// What a checkpoint can be restored into: the same effective scene (the seed included; the
/// duration and thread count do not change the bits), the same shard layout, the same build.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RunKey {
    /// The `twinswarm` version that wrote it (the state's layout is that build's).
    pub version: String,
    /// FNV-1a of the effective scene's TOML, duration, threads and seed left out.
    pub scene: u64,
    /// The seed of all random draws.
    pub seed: u64,
    /// Copters in the scene.
    pub copters: u32,
    /// `(K, N)`: shard K of N; `None`: one process.
    pub shard: Option<(u16, u16)>,
}

impl RunKey {
    /// The key of a run of `world`, as shard `shard` (K, N) or as one process.
    pub fn of(world: &World, shard: Option<(usize, usize)>) -> Self {
        let mut spec = world.spec.clone();
        spec.sim.duration_s = 0.0;
        spec.sim.threads = 1;
        spec.sim.seed = 0;
        Self {
            version: env!("CARGO_PKG_VERSION").to_owned(),
            scene: fnv(spec.to_toml().as_bytes()),
            seed: world.spec.sim.seed,
            copters: world.copters.len() as u32,
            shard: shard.map(|(k, n)| (k as u16, n as u16)),
        }
    }

    /// The file-name stem of this run's checkpoints.
    pub fn stem(&self) -> String {
        match self.shard {
            Some((k, n)) => format!("shard-{k}-of-{n}"),
            None => "run".to_owned(),
        }
    }

    /// What differs from `other`, in words (`None`: nothing).
    fn mismatch(&self, other: &RunKey) -> Option<String> {
        let layout = |s: Option<(u16, u16)>| s.map_or("one process".to_owned(), |(k, n)| format!("shard {k}/{n}"));
        if self.version != other.version {
            return Some(format!("it was written by twinswarm {}, this is {}", self.version, other.version));
        }
        if self.scene != other.scene || self.copters != other.copters {
            return Some(format!(
                "it is of another scene ({} copters, scene digest {:016x}; this run: {} copters, {:016x})",
                self.copters, self.scene, other.copters, other.scene
            ));
        }
        if self.seed != other.seed {
            return Some(format!("it is of seed {}, this run's is {}", self.seed, other.seed));
        }
        if self.shard != other.shard {
            return Some(format!("it is of {}, this run is {}", layout(self.shard), layout(other.shard)));
        }
        None
    }
}

fn fnv(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3))
}

/// Why a checkpoint could not be written or read. Every variant names the file.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// Reading, writing, syncing or renaming failed.
    #[error("checkpoint {path}: {source}")]
    Io {
        /// The file (or directory).
        path: PathBuf,
        /// What the OS said.
        source: std::io::Error,
    },
    /// Not a checkpoint, truncated, or its bytes do not match its CRC.
    #[error("checkpoint {path} is damaged: {what}")]
    Damaged {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        what: String,
    },
    /// A sound checkpoint of another run.
    #[error("checkpoint {path} does not belong to this run: {what}")]
    Mismatch {
        /// The file.
        path: PathBuf,
        /// What differs.
        what: String,
    },
    /// The state could not be encoded (a defect).
    #[error("checkpoint {path}: cannot encode the state: {what}")]
    Encode {
        /// The file.
        path: PathBuf,
        /// The encoder's message.
        what: String,
    },
}

/// What is written (by reference; read back as a [`Checkpoint`], field for field).
#[derive(Serialize)]
struct Parts<'a> {
    key: &'a RunKey,
    tick: u64,
    log_epoch_ns: Option<u64>,
    state: &'a State,
    inputs: &'a Inputs,
    shard: Option<ShardSnapshot>,
    early: &'a [&'a GhostBatch],
}

/// A checkpoint read back.
#[derive(Debug, Deserialize)]
pub struct Checkpoint {
    /// The run it belongs to.
    pub key: RunKey,
    /// The tick of the state (steps completed).
    pub tick: u64,
    /// The log's epoch of the run that wrote it, so that a resumed run's log continues its
    /// time base.
    pub log_epoch_ns: Option<u64>,
    /// The state after step `tick` (its shard view is in `shard`).
    pub state: State,
    /// The commands the next step flies.
    pub inputs: Inputs,
    /// A shard's view.
    pub shard: Option<ShardSnapshot>,
    /// Neighbours' batches that had arrived for the next steps.
    pub early: Vec<GhostBatch>,
}

/// `--checkpoint-every` and `--checkpoint-dir`.
#[derive(Clone, Debug)]
pub struct CheckpointOptions {
    /// Where the files go (created if missing).
    pub dir: PathBuf,
    /// Every this many control steps (at tick multiples of it).
    pub every_ticks: u64,
    /// The run they belong to.
    pub key: RunKey,
    /// The log's epoch, kept in each checkpoint.
    pub log_epoch_ns: Option<u64>,
}

impl CheckpointOptions {
    /// Every `every_s` of simulated time: `round(every_s / control_dt)` steps, at least one.
    /// `None` when `every_s` is not a positive number.
    pub fn every_ticks_for(every_s: f64, control_dt_s: f64) -> Option<u64> {
        (every_s.is_finite() && every_s > 0.0).then(|| ((every_s / control_dt_s).round() as u64).max(1))
    }
}

/// Writes a run's checkpoints.
#[derive(Debug)]
pub struct Checkpointer {
    opts: CheckpointOptions,
    /// Checkpoints written.
    pub written: u64,
    /// The last one.
    pub last: Option<PathBuf>,
}

impl Checkpointer {
    /// Writes as `opts` says (the directory is made at the first write).
    pub fn new(opts: CheckpointOptions) -> Self {
        Self { opts, written: 0, last: None }
    }

    /// Its period, control steps.
    pub fn every_ticks(&self) -> u64 {
        self.opts.every_ticks
    }

    /// Whether the state after step `tick` is checkpointed.
    pub fn due(&self, tick: u64) -> bool {
        tick > 0 && tick.is_multiple_of(self.opts.every_ticks)
    }

    /// Writes the checkpoint of `state` (after its step) and drops all but the newest
    /// [`KEEP`] of this run's.
    pub fn write(&mut self, state: &State, inputs: &Inputs, early: &[&GhostBatch]) -> Result<PathBuf, CheckpointError> {
        let path = self.opts.dir.join(format!("{}-tick-{:012}.ckpt", self.opts.key.stem(), state.tick));
        let parts = Parts {
            key: &self.opts.key,
            tick: state.tick,
            log_epoch_ns: self.opts.log_epoch_ns,
            state,
            inputs,
            shard: state.shard_snapshot(),
            early,
        };
        let dir = &self.opts.dir;
        std::fs::create_dir_all(dir).map_err(|source| CheckpointError::Io { path: dir.clone(), source })?;
        let payload = postcard::to_allocvec(&parts)
            .map_err(|e| CheckpointError::Encode { path: path.clone(), what: e.to_string() })?;
        write_atomically(&path, &payload)?;
        self.prune()?;
        self.written += 1;
        self.last = Some(path.clone());
        Ok(path)
    }

    /// Drops this run's checkpoints older than the newest [`KEEP`].
    fn prune(&self) -> Result<(), CheckpointError> {
        let all = list(&self.opts.dir, &self.opts.key.stem())?;
        for (_, old) in all.iter().rev().skip(KEEP) {
            std::fs::remove_file(old).map_err(|source| CheckpointError::Io { path: old.clone(), source })?;
        }
        Ok(())
    }
}

/// `.tmp`, write, fsync, rename, fsync the directory.
fn write_atomically(path: &Path, payload: &[u8]) -> Result<(), CheckpointError> {
    fn io(p: &Path) -> impl FnOnce(std::io::Error) -> CheckpointError + '_ {
        move |source| CheckpointError::Io { path: p.to_owned(), source }
    }
    let tmp = path.with_extension("ckpt.tmp");
    let mut f = std::fs::File::create(&tmp).map_err(io(&tmp))?;
    let mut header = [0u8; HEADER];
    header[..8].copy_from_slice(MAGIC);
    header[8..12].copy_from_slice(&crc32fast::hash(payload).to_le_bytes());
    header[12..].copy_from_slice(&(payload.len() as u64).to_le_bytes());
    f.write_all(&header).map_err(io(&tmp))?;
    f.write_all(payload).map_err(io(&tmp))?;
    f.sync_all().map_err(io(&tmp))?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(io(path))?;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        // The rename is durable once the directory is synced.
        std::fs::File::open(dir).and_then(|d| d.sync_all()).map_err(io(dir))?;
    }
    Ok(())
}

/// The checkpoints of `stem` in `dir`, oldest first, with their ticks (from their names).
pub fn list(dir: &Path, stem: &str) -> Result<Vec<(u64, PathBuf)>, CheckpointError> {
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(source) => return Err(CheckpointError::Io { path: dir.to_owned(), source }),
    };
    let prefix = format!("{stem}-tick-");
    let mut out = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|source| CheckpointError::Io { path: dir.to_owned(), source })?;
        let name = entry.file_name();
        let Some(tick) = name.to_str().and_then(|n| n.strip_prefix(&prefix)?.strip_suffix(".ckpt")?.parse().ok())
        else {
            continue;
        };
        out.push((tick, entry.path()));
    }
    out.sort();
    Ok(out)
}

/// Reads the checkpoint at `path` and checks that it belongs to the run `expected`.
pub fn load(path: &Path, expected: &RunKey) -> Result<Checkpoint, CheckpointError> {
    let bytes = std::fs::read(path).map_err(|source| CheckpointError::Io { path: path.to_owned(), source })?;
    let damaged = |what: String| CheckpointError::Damaged { path: path.to_owned(), what };
    if bytes.len() >= 8 && bytes[..6] == MAGIC[..6] && bytes[..8] != MAGIC[..] {
        let what = format!("format version {}, this build reads {}", bytes[7], MAGIC[7]);
        return Err(CheckpointError::Mismatch { path: path.to_owned(), what });
    }
    if bytes.len() < HEADER || &bytes[..8] != MAGIC {
        return Err(damaged("not a twinswarm checkpoint (no TWCKPT header)".into()));
    }
    let crc = u32::from_le_bytes(bytes[8..12].try_into().unwrap_or_default());
    let len = u64::from_le_bytes(bytes[12..HEADER].try_into().unwrap_or_default());
    let payload = &bytes[HEADER..];
    if payload.len() as u64 != len {
        return Err(damaged(format!("{} payload bytes, the header says {len} (truncated?)", payload.len())));
    }
    if crc32fast::hash(payload) != crc {
        return Err(damaged("its bytes do not match its CRC".into()));
    }
    let (key, _) =
        postcard::take_from_bytes::<RunKey>(payload).map_err(|e| damaged(format!("cannot read its run key: {e}")))?;
    if let Some(what) = key.mismatch(expected) {
        return Err(CheckpointError::Mismatch { path: path.to_owned(), what });
    }
    let ckpt: Checkpoint = postcard::from_bytes(payload).map_err(|e| damaged(format!("cannot read it: {e}")))?;
    if ckpt.tick != ckpt.state.tick {
        return Err(damaged(format!("its tick {} is not its state's {}", ckpt.tick, ckpt.state.tick)));
    }
    let n = expected.copters as usize;
    if ckpt.state.copters.len() != n || ckpt.inputs.commands.len() != n {
        return Err(damaged(format!(
            "it holds {} copter states and {} commands for {n} copters",
            ckpt.state.copters.len(),
            ckpt.inputs.commands.len()
        )));
    }
    Ok(ckpt)
}
