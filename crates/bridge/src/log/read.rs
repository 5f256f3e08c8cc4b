//! Reading logs back: [`LogFile`] (checked, with its summary) for `log info` and `plot`, and
//! [`recover`] for truncated files.

use std::collections::BTreeMap;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use mcap::records::Record;
use mcap::{Attachment, Compression, McapError, WriteOptions};

use super::proto::LogRecord;

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
    /// A message does not decode.
    #[error("{path}: a message on {topic} at log time {log_time} ns is {what}")]
    Decode {
        /// The file.
        path: PathBuf,
        /// Its topic.
        topic: String,
        /// Its log time, ns.
        log_time: u64,
        /// What is wrong (`not a valid protobuf message: …`).
        what: String,
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

/// A channel of a log with its schema ([`LogFile::channel_defs`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ChannelDef {
    /// Topic.
    pub topic: String,
    /// Message encoding (`json`, `protobuf`, …).
    pub encoding: String,
    /// Schema name (empty if none).
    pub schema_name: String,
    /// Schema encoding (`jsonschema`, `protobuf`, …; empty if none).
    pub schema_encoding: String,
    /// The schema's bytes.
    pub schema: Vec<u8>,
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
    const ATTACHMENT: u8 = 0x09;
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
                Some(u) if u <= MAX_CHUNK_BYTES => {
                    check_uncompressed_chunk(body).map_err(|what| (pos as u64, what))?;
                }
                Some(u) => return Err((pos as u64, format!("a chunk says it unpacks to {u} bytes"))),
                None => return Err((pos as u64, "a chunk record is too short".into())),
            },
            ATTACHMENT if !attachment_fits(body) => {
                return Err((pos as u64, "an attachment record is shorter than its header says".into()));
            }
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

/// A chunk stored without compression: its records must fit in it. The `mcap` crate
/// subtracts each inner record's length from what is left of the chunk without checking
/// (an overflow, found by fuzzing); zstd chunks are checked by the decompressing reader.
fn check_uncompressed_chunk(body: &[u8]) -> Result<(), String> {
    let u32_at = |i: usize| body.get(i..i + 4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize);
    let u64_at = |i: usize| body.get(i..i + 8).and_then(|b| b.try_into().ok()).map(u64::from_le_bytes);
    // start, end, uncompressed size (8 each), uncompressed CRC (4), compression (string).
    let Some(name_len) = u32_at(28) else { return Err("a chunk record is too short".into()) };
    let Some(compression) = body.get(32..32 + name_len) else { return Err("a chunk's compression name is cut".into()) };
    let records_at = 32 + name_len + 8;
    let Some(compressed) = u64_at(32 + name_len) else { return Err("a chunk record is too short".into()) };
    if !compression.is_empty() {
        return Ok(());
    }
    let Some(records) = usize::try_from(compressed).ok().and_then(|n| body.get(records_at..records_at.checked_add(n)?))
    else {
        return Err(format!("a chunk says it holds {compressed} bytes of records, more than the record has"));
    };
    let mut at = 0;
    while at < records.len() {
        let len = records.get(at + 1..at + 9).and_then(|b| b.try_into().ok()).map(u64::from_le_bytes);
        match len.and_then(|l| usize::try_from(l).ok()).and_then(|l| (at + 9).checked_add(l)) {
            Some(end) if end <= records.len() => at = end,
            _ => return Err(format!("a record inside a chunk, at byte {at} of its records, overruns the chunk")),
        }
    }
    Ok(())
}

/// Whether an attachment record's body holds what its header says: the `mcap` crate slices
/// it without checking, and panics on a short one (found by fuzzing).
fn attachment_fits(body: &[u8]) -> bool {
    let str_end = |at: usize| -> Option<usize> {
        let n = body.get(at..at + 4).map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)?;
        (at + 4).checked_add(n)
    };
    // log time, create time (8 each), name, media type, data length (8), data, CRC (4).
    let header_len = str_end(16).and_then(str_end).map(|at| at + 8);
    header_len.is_some_and(|h| h + 4 <= body.len())
}

/// The records of an MCAP file's data section, chunks flattened, with every record and chunk
/// length capped at [`MAX_CHUNK_BYTES`].
///
/// The `mcap` crate's `ChunkFlattener` and `MessageStream` set no length limit on the records
/// inside a chunk, so a crafted inner length makes them allocate whatever it says (found by
/// fuzzing `log recover` and `plot`). This drives the crate's sans-I/O reader the way they
/// do, with the limit its own `LinearReader` uses.
fn bounded_records(
    data: &[u8],
    ignore_end_magic: bool,
) -> impl Iterator<Item = Result<Record<'static>, McapError>> + '_ {
    use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};
    let limit = usize::try_from(MAX_CHUNK_BYTES).unwrap_or(usize::MAX).min(data.len().max(1 << 20));
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_record_length_limit(limit)
            .with_skip_end_magic(ignore_end_magic)
            .with_validate_chunk_crcs(true),
    );
    let mut rest = data;
    std::iter::from_fn(move || {
        while let Some(event) = reader.next_event() {
            match event {
                Ok(LinearReadEvent::ReadRequest(need)) => {
                    let len = need.min(rest.len());
                    reader.insert(len).copy_from_slice(&rest[..len]);
                    reader.notify_read(len);
                    rest = &rest[len..];
                }
                Ok(LinearReadEvent::Record { data, opcode }) => {
                    if opcode == 0x09 && !attachment_fits(data) {
                        return Some(Err(McapError::UnexpectedEoc));
                    }
                    return Some(mcap::parse_record(opcode, data).map(|r| r.into_owned()));
                }
                Err(e) => return Some(Err(e)),
            }
        }
        None
    })
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
            // The crate adds offset and length unchecked (an overflow): check them first.
            if idx.offset.checked_add(idx.length).is_none_or(|end| end > self.data.len() as u64) {
                return Err(corrupt(McapError::BadIndex));
            }
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
                // The index may point anywhere: check the record there before the crate
                // slices it.
                let at = usize::try_from(idx.offset).unwrap_or(usize::MAX);
                let head = self.data.get(at..at.saturating_add(9));
                let body = head.and_then(|h| {
                    let len = usize::try_from(u64::from_le_bytes(h[1..9].try_into().ok()?)).ok()?;
                    (h[0] == 0x09).then(|| self.data.get(at + 9..(at + 9).checked_add(len)?)).flatten()
                });
                // The crate adds offset and length unchecked too.
                let in_file = idx.offset.checked_add(idx.length).is_some_and(|end| end <= self.data.len() as u64);
                if !in_file || !body.is_some_and(attachment_fits) {
                    return Err(LogReadError::Damaged {
                        path: self.path.clone(),
                        offset: idx.offset,
                        what: format!("the summary's index of attachment {name:?} points at no attachment"),
                    });
                }
                return Ok(Some(mcap::read::attachment(&self.data, idx).map_err(corrupt)?.data.into_owned()));
            }
        }
        Ok(None)
    }

    /// Every channel with its encoding and schema, in channel id order.
    pub fn channel_defs(&self) -> Vec<ChannelDef> {
        let mut channels: Vec<_> = self.summary.channels.values().collect();
        channels.sort_by_key(|c| c.id);
        channels
            .into_iter()
            .map(|c| ChannelDef {
                topic: c.topic.clone(),
                encoding: c.message_encoding.clone(),
                schema_name: c.schema.as_ref().map_or(String::new(), |s| s.name.clone()),
                schema_encoding: c.schema.as_ref().map_or(String::new(), |s| s.encoding.clone()),
                schema: c.schema.as_ref().map_or(Vec::new(), |s| s.data.to_vec()),
            })
            .collect()
    }

    /// Calls `f(topic, log_time_ns, payload)` for every message on one of `topics`, in file
    /// order (chunk CRCs checked).
    pub fn for_each_message(
        &self,
        topics: &[&str],
        f: impl FnMut(&str, u64, &[u8]) -> Result<(), LogReadError>,
    ) -> Result<(), LogReadError> {
        self.for_each_message_where(|t| topics.contains(&t), f)
    }

    /// [`LogFile::for_each_message`] for the topics `wanted` accepts.
    pub fn for_each_message_where(
        &self,
        wanted: impl Fn(&str) -> bool,
        mut f: impl FnMut(&str, u64, &[u8]) -> Result<(), LogReadError>,
    ) -> Result<(), LogReadError> {
        let corrupt = |source| LogReadError::Corrupt { path: self.path.clone(), source };
        let mut channels: BTreeMap<u16, String> = BTreeMap::new();
        for record in bounded_records(&self.data, false) {
            match record.map_err(corrupt)? {
                Record::Channel(c) => {
                    channels.insert(c.id, c.topic);
                }
                Record::Message { header, data } => match channels.get(&header.channel_id) {
                    Some(topic) if wanted(topic) => f(topic, header.log_time, &data)?,
                    Some(_) => {}
                    None => return Err(corrupt(McapError::UnknownChannel(header.sequence, header.channel_id))),
                },
                Record::DataEnd(_) => break,
                _ => {}
            }
        }
        Ok(())
    }

    /// The message encoding of `topic` (`protobuf`, or `json` in logs written before).
    pub fn encoding(&self, topic: &str) -> Option<&str> {
        self.summary.channels.values().find(|c| c.topic == topic).map(|c| c.message_encoding.as_str())
    }

    /// Decodes every message on `topic` as `T` (either encoding).
    pub fn messages<T: LogRecord>(&self, topic: &str) -> Result<Vec<(u64, T)>, LogReadError> {
        let encoding = self.encoding(topic).unwrap_or("");
        let mut out = Vec::new();
        self.for_each_message(&[topic], |topic, log_time, data| {
            let decoded = T::decode_as(encoding, data).map_err(|what| LogReadError::Decode {
                path: self.path.clone(),
                topic: topic.to_owned(),
                log_time,
                what,
            })?;
            out.push((log_time, decoded));
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

/// Writes an attachment record read from another file.
fn copy_attachment<W: std::io::Write + std::io::Seek>(
    w: &mut mcap::Writer<W>,
    header: mcap::records::AttachmentHeader,
    data: std::borrow::Cow<'_, [u8]>,
) -> Result<(), McapError> {
    w.attach(&Attachment {
        log_time: header.log_time,
        create_time: header.create_time,
        name: header.name,
        media_type: header.media_type,
        data,
    })
}

/// A new MCAP file at `path` for a tool's output: zstd chunks at `level`, indexes and summary,
/// the tool named in the header.
fn create_mcap(path: &Path, level: u32, tool: &str) -> Result<mcap::Writer<BufWriter<std::fs::File>>, LogReadError> {
    let file = std::fs::File::create(path).map_err(|source| LogReadError::Io { path: path.to_owned(), source })?;
    WriteOptions::new()
        .compression(Some(Compression::Zstd))
        .compression_level(level)
        .compression_threads(0)
        .library(format!("twinswarm {} ({tool})", env!("CARGO_PKG_VERSION")))
        .create(BufWriter::new(file))
        .map_err(|source| LogReadError::Write { path: path.to_owned(), source })
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
    let werr = |source| LogReadError::Write { path: fixed.to_owned(), source };
    let mut out = create_mcap(fixed, 1, "log recover")?;
    let input_bytes = std::fs::metadata(broken).map_or(data.len() as u64, |m| m.len());
    let mut report = RecoverReport { input_bytes, stopped_by: damage, ..RecoverReport::default() };
    let mut topics: BTreeMap<u16, String> = BTreeMap::new();
    for record in bounded_records(&data, true) {
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
                copy_attachment(&mut out, header, data).map_err(werr)?;
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

/// What [`merge`] did.
#[derive(Debug, Default, Clone, serde::Serialize)]
pub struct MergeReport {
    /// Messages written, per topic.
    pub messages: BTreeMap<String, u64>,
    /// Messages dropped as exact duplicates of another input's (same topic, log time and
    /// bytes: the static scene, events every shard saw).
    pub duplicates: u64,
    /// Log time shift applied to each input to put it on the first one's epoch, ns.
    pub shifts_ns: Vec<i64>,
    /// Messages on a channel their input never declared (a damaged writer), per input: not
    /// written, since nothing says what they are.
    pub undeclared: Vec<u64>,
}

/// Messages [`merge`] wrote at one log time under one (channel, CRC and length) key: the
/// input and bytes of each.
type Sent = Vec<(usize, Vec<u8>)>;

/// A schema as [`merge`] matches them: name, encoding, data.
type SchemaKey = (String, String, Vec<u8>);

/// One input of a merge: its bytes and where its epoch is.
struct MergeInput {
    path: PathBuf,
    data: Vec<u8>,
    shift_ns: i64,
}

/// The `epoch_unix_ns` of a twinswarm log's `twinswarm` metadata, if it has one.
fn epoch_of(data: &[u8]) -> Option<i64> {
    for record in bounded_records(data, false) {
        match record {
            Ok(Record::Metadata(m)) => {
                if let Some(e) = m.metadata.get("epoch_unix_ns").and_then(|v| v.parse().ok()) {
                    return Some(e);
                }
            }
            Ok(Record::DataEnd(_)) | Err(_) => return None,
            _ => {}
        }
    }
    None
}

/// Merges the logs of a sharded run (one per shard) into one: every message of every input,
/// in log-time order, on one set of channels (inputs' channels with the same topic, encoding
/// and schema become one), each input's log times shifted onto the first input's epoch.
/// Messages that are exact duplicates across inputs at one log time (the static scene, the
/// same event seen by two shards) are written once. Metadata and attachments come from the
/// first input, plus a `merge` metadata record naming the sources. Every input is read whole
/// and CRC-checked; a damaged one is an error naming it (`log recover` it first).
pub fn merge(inputs: &[PathBuf], out: &Path) -> Result<MergeReport, LogReadError> {
    use std::collections::HashMap;
    let mut loaded = Vec::new();
    for path in inputs {
        let data = read_checked(path)?;
        // Whole and finished: `LogFile::open` checks the footer and summary.
        LogFile::open(path)?;
        loaded.push(MergeInput { path: path.clone(), shift_ns: 0, data });
    }
    let base = loaded.first().and_then(|i| epoch_of(&i.data));
    for input in &mut loaded {
        input.shift_ns = match (base, epoch_of(&input.data)) {
            (Some(b), Some(e)) => b - e,
            _ => 0,
        };
    }
    let werr = |source| LogReadError::Write { path: out.to_owned(), source };
    let mut w = create_mcap(out, 3, "log merge")?;
    let mut report = MergeReport {
        shifts_ns: loaded.iter().map(|i| i.shift_ns).collect(),
        undeclared: vec![0; loaded.len()],
        ..MergeReport::default()
    };
    // Per input: its records, the head message, its schemas and channels mapped to the output's.
    let mut streams: Vec<_> = loaded.iter().map(|i| bounded_records(&i.data, false).peekable()).collect();
    let mut schemas: Vec<HashMap<u16, SchemaKey>> = vec![HashMap::new(); loaded.len()];
    let mut channels: Vec<HashMap<u16, u16>> = vec![HashMap::new(); loaded.len()];
    let mut out_schemas: HashMap<SchemaKey, u16> = HashMap::new();
    let mut out_channels: HashMap<(String, String, u16), u16> = HashMap::new();
    let mut topics: HashMap<u16, String> = HashMap::new();
    let mut heads: Vec<Option<(mcap::records::MessageHeader, Vec<u8>)>> = vec![None; loaded.len()];
    let mut attachments: std::collections::HashSet<String> = std::collections::HashSet::new();
    // What went out at the current log time: (channel, crc and length) → the inputs and bytes
    // of the messages with that key. The CRC only narrows the search: messages are duplicates
    // when their bytes are equal.
    let mut seen_at: (u64, HashMap<(u16, u64), Sent>) = (0, HashMap::new());
    let corrupt = |k: usize, e: McapError| LogReadError::Corrupt { path: loaded[k].path.clone(), source: e };
    loop {
        // Refill each input's head: the next message, taking in its definitions on the way.
        for k in 0..loaded.len() {
            while heads[k].is_none() {
                let Some(record) = streams[k].next() else { break };
                match record.map_err(|e| corrupt(k, e))? {
                    Record::Schema { header, data } => {
                        schemas[k].insert(header.id, (header.name, header.encoding, data.into_owned()));
                    }
                    Record::Channel(c) => {
                        let Some(schema) = schemas[k].get(&c.schema_id).cloned() else {
                            return Err(LogReadError::Corrupt {
                                path: loaded[k].path.clone(),
                                source: McapError::UnknownSchema(c.topic.clone(), c.schema_id),
                            });
                        };
                        let sid = match out_schemas.get(&schema) {
                            Some(&id) => id,
                            None => {
                                let id = w.add_schema(&schema.0, &schema.1, &schema.2).map_err(werr)?;
                                out_schemas.insert(schema, id);
                                id
                            }
                        };
                        let key = (c.topic.clone(), c.message_encoding.clone(), sid);
                        let cid = match out_channels.get(&key) {
                            Some(&id) => id,
                            None => {
                                let id =
                                    w.add_channel(sid, &c.topic, &c.message_encoding, &c.metadata).map_err(werr)?;
                                out_channels.insert(key, id);
                                topics.insert(id, c.topic.clone());
                                id
                            }
                        };
                        channels[k].insert(c.id, cid);
                    }
                    Record::Message { header, data } => {
                        let Some(&cid) = channels[k].get(&header.channel_id) else {
                            report.undeclared[k] += 1;
                            continue;
                        };
                        let log_time = header.log_time.saturating_add_signed(loaded[k].shift_ns);
                        let publish_time = header.publish_time.saturating_add_signed(loaded[k].shift_ns);
                        let h = mcap::records::MessageHeader { channel_id: cid, log_time, publish_time, ..header };
                        heads[k] = Some((h, data.into_owned()));
                    }
                    Record::Attachment { header, data, .. } if k == 0 && attachments.insert(header.name.clone()) => {
                        copy_attachment(&mut w, header, data).map_err(werr)?;
                    }
                    Record::Metadata(m) if k == 0 => w.write_metadata(&m).map_err(werr)?,
                    Record::DataEnd(_) => break,
                    _ => {}
                }
            }
        }
        // The earliest head (ties: the lower input) goes out.
        let Some(k) =
            (0..loaded.len()).filter(|&k| heads[k].is_some()).min_by_key(|&k| heads[k].as_ref().map(|h| h.0.log_time))
        else {
            break;
        };
        let Some((header, data)) = heads[k].take() else { break };
        if seen_at.0 != header.log_time {
            seen_at = (header.log_time, Default::default());
        }
        let digest = u64::from(crc32fast::hash(&data)) << 32 | data.len() as u64;
        let same = seen_at.1.entry((header.channel_id, digest)).or_default();
        if same.iter().any(|(j, bytes)| *j != k && *bytes == data) {
            report.duplicates += 1;
            continue;
        }
        same.push((k, data.clone()));
        w.write_to_known_channel(&header, &data).map_err(werr)?;
        *report.messages.entry(topics.get(&header.channel_id).cloned().unwrap_or_default()).or_insert(0) += 1;
    }
    let mut meta = BTreeMap::new();
    meta.insert("sources".to_owned(), inputs.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join("\n"));
    meta.insert("duplicates_dropped".to_owned(), report.duplicates.to_string());
    meta.insert("undeclared_channel_messages".to_owned(), format!("{:?}", report.undeclared));
    w.write_metadata(&mcap::records::Metadata { name: "merge".into(), metadata: meta }).map_err(werr)?;
    w.finish().map_err(werr)?;
    Ok(report)
}
