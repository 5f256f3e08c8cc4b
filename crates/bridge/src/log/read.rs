//! Reading logs back: [`LogFile`] (checked, with its summary) for `log info` and `plot`, and
//! [`recover`] for truncated files.

use std::collections::BTreeMap;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use mcap::records::Record;
use mcap::{Attachment, Compression, McapError, WriteOptions};

/// Why a log file cannot be read.
#[derive(Debug, thiserror::Error)]
pub enum LogReadError {
    /// The file cannot be opened or read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The file is empty.
    #[error("{path} is empty (0 bytes): not an MCAP log")]
    Empty {
        /// The file.
        path: PathBuf,
    },
    /// The file does not start with the MCAP magic.
    #[error("{path} is not an MCAP file (it does not start with the MCAP magic bytes)")]
    NotMcap {
        /// The file.
        path: PathBuf,
    },
    /// The file has no footer: the run was killed, or the file was cut.
    #[error(
        "{path} is truncated or unfinished ({len} bytes, no MCAP footer): the run was probably killed; \
         `twinswarm log recover {path} FIXED.mcap` rescues every complete chunk"
    )]
    Truncated {
        /// The file.
        path: PathBuf,
        /// Its length, bytes.
        len: u64,
    },
    /// The file ends properly but has no summary section.
    #[error("{path} has no MCAP summary section (it was not finished by its writer)")]
    NoSummary {
        /// The file.
        path: PathBuf,
    },
    /// The MCAP structure is damaged.
    #[error("{path} is damaged: {source}")]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// The MCAP reader's error.
        source: McapError,
    },
    /// A record's length (or a chunk's uncompressed size) is more than the file can hold: the
    /// bytes are damaged. Checked before the `mcap` reader sees them, which would try to
    /// allocate that much.
    #[error("{path} is damaged at byte {offset}: {what}")]
    Damaged {
        /// The file.
        path: PathBuf,
        /// Where the bad record starts.
        offset: u64,
        /// What is wrong.
        what: String,
    },
    /// A message does not parse.
    #[error("{path}: a message on {topic} is not valid JSON for this program: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// Its topic.
        topic: String,
        /// The JSON error.
        source: serde_json::Error,
    },
    /// Writing the recovered file failed.
    #[error("cannot write {path}: {source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// The MCAP writer's error.
        source: McapError,
    },
}

/// One channel in [`LogInfo`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ChannelInfo {
    /// Topic.
    pub topic: String,
    /// Schema name (empty if none).
    pub schema: String,
    /// Message encoding.
    pub encoding: String,
    /// Messages on it.
    pub messages: u64,
}

/// What `twinswarm log info` shows.
#[derive(Clone, Debug, Default)]
pub struct LogInfo {
    /// File size, bytes.
    pub file_bytes: u64,
    /// Channels, by topic.
    pub channels: Vec<ChannelInfo>,
    /// All messages.
    pub messages: u64,
    /// Chunks.
    pub chunks: u64,
    /// Compression of the chunks (e.g. `zstd`).
    pub compression: String,
    /// First and last log time, ns.
    pub time_range_ns: Option<(u64, u64)>,
    /// Attachments: name, media type, bytes.
    pub attachments: Vec<(String, String, u64)>,
    /// Metadata records by name.
    pub metadata: BTreeMap<String, BTreeMap<String, String>>,
}

/// A complete (finished) MCAP log, read into memory, with its summary.
#[derive(Debug)]
pub struct LogFile {
    path: PathBuf,
    data: Vec<u8>,
    summary: mcap::Summary,
}

/// The largest uncompressed chunk accepted: ours are 1 MiB, the `mcap` crate's and
/// Foxglove's writers default to about as much, so 64 MiB leaves a wide margin while a
/// crafted length cannot make the reader allocate more than that per chunk.
const MAX_CHUNK_BYTES: u64 = 64 << 20;

/// What [`walk_records`] found.
#[derive(Debug, Default)]
struct Walk {
    /// Where the complete records end.
    end: usize,
    /// The last record, cut by the end of the file (a killed run), if it was.
    cut: Option<String>,
    /// Offset of the DataEnd record and the data-section CRC it holds.
    data_end: Option<(usize, u32)>,
    /// Offset of the Footer record.
    footer: Option<usize>,
}

/// Walks the records of an MCAP file (after the magic) by their length prefixes, up to the
/// footer or to a last record cut by the end of the file. The `mcap` crate allocates what a
/// record's length (and a chunk's uncompressed size) says before it checks anything, so a
/// damaged length would abort the process; this refuses lengths the file cannot hold, and
/// chunks said to unpack to more than [`MAX_CHUNK_BYTES`]. A cut last record is an error
/// unless `cut_ok` (a killed run).
fn walk_records(data: &[u8], cut_ok: bool) -> Result<Walk, (u64, String)> {
    const CHUNK: u8 = 0x06;
    const FOOTER: u8 = 0x02;
    const DATA_END: u8 = 0x0F;
    let mut walk = Walk::default();
    let mut pos = mcap::MAGIC.len();
    while pos < data.len() {
        let Some(head) = data.get(pos..pos + 9) else {
            let what = format!("a record header at byte {pos} is cut off by the end of the file");
            return if cut_ok { Ok(Walk { end: pos, cut: Some(what), ..walk }) } else { Err((pos as u64, what)) };
        };
        let opcode = head[0];
        let len = u64::from_le_bytes(head[1..9].try_into().unwrap_or_default());
        let room = (data.len() - pos - 9) as u64;
        if len > room {
            if cut_ok && opcode != FOOTER {
                let what = format!("record 0x{opcode:02x} at byte {pos} is cut off by the end of the file");
                return Ok(Walk { end: pos, cut: Some(what), ..walk });
            }
            return Err((pos as u64, format!("record 0x{opcode:02x} says {len} bytes, the file has {room} left")));
        }
        let body = &data[pos + 9..pos + 9 + len as usize];
        let u32_at = |i: usize| body.get(i..i + 4).map(|b| u32::from_le_bytes(b.try_into().unwrap_or_default()));
        let u64_at = |i: usize| body.get(i..i + 8).map(|b| u64::from_le_bytes(b.try_into().unwrap_or_default()));
        match opcode {
            CHUNK => match u64_at(16) {
                Some(u) if u <= MAX_CHUNK_BYTES => {}
                Some(u) => return Err((pos as u64, format!("a chunk says it unpacks to {u} bytes"))),
                None => return Err((pos as u64, "a chunk record is too short".into())),
            },
            DATA_END => walk.data_end = u32_at(0).map(|crc| (pos, crc)),
            FOOTER => walk.footer = Some(pos),
            _ => {}
        }
        pos += 9 + len as usize;
        if opcode == FOOTER {
            break;
        }
    }
    walk.end = pos;
    Ok(walk)
}

/// Checks the data-section CRC (in DataEnd) and the summary CRC (in the footer) where the
/// writer set them; the `mcap` crate checks neither, and damage outside the chunks (message
/// indexes, attachments) would go unnoticed.
fn check_section_crcs(data: &[u8], walk: &Walk) -> Result<(), (u64, String)> {
    if let Some((at, crc)) = walk.data_end
        && crc != 0
        && crc32fast::hash(&data[..at]) != crc
    {
        return Err((0, "the data section does not match its CRC".into()));
    }
    if let Some(f) = walk.footer {
        let field =
            |i: usize| data.get(f + 9 + i..f + 9 + i + 8).map(|b| u64::from_le_bytes(b.try_into().unwrap_or_default()));
        let crc = data.get(f + 25..f + 29).map(|b| u32::from_le_bytes(b.try_into().unwrap_or_default()));
        if let (Some(start), Some(crc)) = (field(0), crc)
            && start != 0
            && crc != 0
            && (start as usize) <= f
            && crc32fast::hash(&data[start as usize..f + 25]) != crc
        {
            return Err((start, "the summary section does not match its CRC".into()));
        }
    }
    Ok(())
}

fn read_checked(path: &Path) -> Result<Vec<u8>, LogReadError> {
    let data = std::fs::read(path).map_err(|source| LogReadError::Io { path: path.to_owned(), source })?;
    if data.is_empty() {
        return Err(LogReadError::Empty { path: path.to_owned() });
    }
    if !data.starts_with(mcap::MAGIC) {
        return Err(LogReadError::NotMcap { path: path.to_owned() });
    }
    Ok(data)
}

impl LogFile {
    /// Reads and checks a finished log: MCAP magic at both ends, a readable summary.
    pub fn open(path: &Path) -> Result<Self, LogReadError> {
        let data = read_checked(path)?;
        if data.len() < 2 * mcap::MAGIC.len() || !data.ends_with(mcap::MAGIC) {
            return Err(LogReadError::Truncated { path: path.to_owned(), len: data.len() as u64 });
        }
        let damaged = |(offset, what)| LogReadError::Damaged { path: path.to_owned(), offset, what };
        let walk = walk_records(&data, false).map_err(damaged)?;
        check_section_crcs(&data, &walk).map_err(damaged)?;
        let corrupt = |source| LogReadError::Corrupt { path: path.to_owned(), source };
        let summary = mcap::Summary::read(&data)
            .map_err(corrupt)?
            .ok_or_else(|| LogReadError::NoSummary { path: path.to_owned() })?;
        Ok(Self { path: path.to_owned(), data, summary })
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Channels, counts, time range, attachments and metadata.
    pub fn info(&self) -> Result<LogInfo, LogReadError> {
        let corrupt = |source| LogReadError::Corrupt { path: self.path.clone(), source };
        let s = &self.summary;
        let stats = s.stats.clone().unwrap_or_default();
        let mut channels: Vec<ChannelInfo> = s
            .channels
            .values()
            .map(|c| ChannelInfo {
                topic: c.topic.clone(),
                schema: c.schema.as_ref().map(|s| s.name.clone()).unwrap_or_default(),
                encoding: c.message_encoding.clone(),
                messages: stats.channel_message_counts.get(&c.id).copied().unwrap_or(0),
            })
            .collect();
        channels.sort_by(|a, b| a.topic.cmp(&b.topic));
        let mut attachments = Vec::new();
        for idx in &s.attachment_indexes {
            attachments.push((idx.name.clone(), idx.media_type.clone(), idx.data_size));
        }
        let mut metadata = BTreeMap::new();
        for idx in &s.metadata_indexes {
            let m = mcap::read::metadata(&self.data, idx).map_err(corrupt)?;
            metadata.insert(m.name, m.metadata);
        }
        let mut compression: Vec<&str> = s.chunk_indexes.iter().map(|c| c.compression.as_str()).collect();
        compression.sort_unstable();
        compression.dedup();
        Ok(LogInfo {
            file_bytes: self.data.len() as u64,
            channels,
            messages: stats.message_count,
            chunks: s.chunk_indexes.len() as u64,
            compression: compression.join(", "),
            time_range_ns: (stats.message_count > 0).then_some((stats.message_start_time, stats.message_end_time)),
            attachments,
            metadata,
        })
    }

    /// The bytes of the attachment with this name.
    pub fn attachment(&self, name: &str) -> Result<Option<Vec<u8>>, LogReadError> {
        let corrupt = |source| LogReadError::Corrupt { path: self.path.clone(), source };
        for idx in &self.summary.attachment_indexes {
            if idx.name == name {
                return Ok(Some(mcap::read::attachment(&self.data, idx).map_err(corrupt)?.data.into_owned()));
            }
        }
        Ok(None)
    }

    /// Calls `f(topic, log_time_ns, payload)` for every message on one of `topics`, in file
    /// order (chunk CRCs checked).
    pub fn for_each_message(
        &self,
        topics: &[&str],
        mut f: impl FnMut(&str, u64, &[u8]) -> Result<(), LogReadError>,
    ) -> Result<(), LogReadError> {
        let corrupt = |source| LogReadError::Corrupt { path: self.path.clone(), source };
        let stream = mcap::MessageStream::new_with_options(&self.data, mcap::read::Options::ValidateChunkCrcs.into())
            .map_err(corrupt)?;
        for m in stream {
            let m = m.map_err(corrupt)?;
            if topics.contains(&m.channel.topic.as_str()) {
                f(&m.channel.topic, m.log_time, &m.data)?;
            }
        }
        Ok(())
    }

    /// Parses every message on `topic` as `T`.
    pub fn messages<T: serde::de::DeserializeOwned>(&self, topic: &str) -> Result<Vec<(u64, T)>, LogReadError> {
        let mut out = Vec::new();
        self.for_each_message(&[topic], |topic, t, data| {
            let v = serde_json::from_slice(data).map_err(|source| LogReadError::Json {
                path: self.path.clone(),
                topic: topic.to_owned(),
                source,
            })?;
            out.push((t, v));
            Ok(())
        })?;
        Ok(out)
    }
}

/// What [`recover`] rescued.
#[derive(Clone, Debug, Default)]
pub struct RecoverReport {
    /// Bytes of the input.
    pub input_bytes: u64,
    /// Messages rescued, per topic.
    pub messages: BTreeMap<String, u64>,
    /// Schemas, channels, attachments and metadata records rescued.
    pub schemas: u64,
    /// Channels rescued.
    pub channels: u64,
    /// Attachments rescued.
    pub attachments: u64,
    /// Metadata records rescued.
    pub metadata: u64,
    /// First and last log time rescued, ns.
    pub time_range_ns: Option<(u64, u64)>,
    /// Whether the input was complete (its data section ended cleanly).
    pub complete: bool,
    /// Why reading stopped early, if it did.
    pub stopped_by: Option<String>,
}

impl RecoverReport {
    /// All messages rescued.
    pub fn total_messages(&self) -> u64 {
        self.messages.values().sum()
    }
}

/// Reads every complete record of a possibly truncated MCAP file (schemas, channels,
/// attachments, metadata, and the messages of every chunk whose CRC checks) and writes them
/// to a new, complete file (zstd chunks, indexes, summary).
pub fn recover(broken: &Path, fixed: &Path) -> Result<RecoverReport, LogReadError> {
    let mut data = read_checked(broken)?;
    // Only complete records, and none from a damaged one on: the cut last record of a killed
    // run, or a record whose length is garbage, ends what is read.
    let damage = match walk_records(&data, true) {
        Ok(walk) => {
            data.truncate(walk.end);
            walk.cut
        }
        Err((offset, what)) => {
            data.truncate(offset as usize);
            Some(format!("damaged at byte {offset}: {what}"))
        }
    };
    let file = std::fs::File::create(fixed).map_err(|source| LogReadError::Io { path: fixed.to_owned(), source })?;
    let werr = |source| LogReadError::Write { path: fixed.to_owned(), source };
    let mut out = WriteOptions::new()
        .compression(Some(Compression::Zstd))
        .compression_level(1)
        .compression_threads(0)
        .library(format!("twinswarm {} (log recover)", env!("CARGO_PKG_VERSION")))
        .create(BufWriter::new(file))
        .map_err(werr)?;
    let input_bytes = std::fs::metadata(broken).map_or(data.len() as u64, |m| m.len());
    let mut report = RecoverReport { input_bytes, stopped_by: damage, ..RecoverReport::default() };
    let mut topics: BTreeMap<u16, String> = BTreeMap::new();
    let opts = mcap::read::Options::IgnoreEndMagic | mcap::read::Options::ValidateChunkCrcs;
    let reader = mcap::read::ChunkFlattener::new_with_options(&data, opts)
        .map_err(|source| LogReadError::Corrupt { path: broken.to_owned(), source })?;
    for record in reader {
        let record = match record {
            Ok(r) => r,
            Err(e) => {
                report.stopped_by = Some(e.to_string());
                break;
            }
        };
        match record {
            Record::Schema { header, data } => {
                out.add_schema_with_id(header.id, &header.name, &header.encoding, &data).map_err(werr)?;
                report.schemas += 1;
            }
            Record::Channel(c) if !topics.contains_key(&c.id) => {
                out.add_channel_with_id(c.id, c.schema_id, &c.topic, &c.message_encoding, &c.metadata).map_err(werr)?;
                topics.insert(c.id, c.topic);
                report.channels += 1;
            }
            Record::Message { header, data } => {
                let Some(topic) = topics.get(&header.channel_id) else { continue };
                out.write_to_known_channel(&header, &data).map_err(werr)?;
                *report.messages.entry(topic.clone()).or_insert(0) += 1;
                report.time_range_ns = Some(match report.time_range_ns {
                    None => (header.log_time, header.log_time),
                    Some((a, b)) => (a.min(header.log_time), b.max(header.log_time)),
                });
            }
            Record::Attachment { header, data, .. } => {
                out.attach(&Attachment {
                    log_time: header.log_time,
                    create_time: header.create_time,
                    name: header.name,
                    media_type: header.media_type,
                    data,
                })
                .map_err(werr)?;
                report.attachments += 1;
            }
            Record::Metadata(m) => {
                out.write_metadata(&m).map_err(werr)?;
                report.metadata += 1;
            }
            Record::DataEnd(_) => {
                report.complete = true;
                break;
            }
            _ => {}
        }
    }
    out.finish().map_err(werr)?;
    Ok(report)
}
