//! A chunked MCAP writer built for throughput: the writer behind [`super::Logger`].
//!
//! The `mcap` crate's writer streams every field of every record through its zstd encoder
//! (several small calls per message), which cost as much as the compression itself at the
//! logging rate of a big swarm. This one appends a chunk's records to a plain buffer and
//! compresses the whole chunk in one call of a reused zstd context, then writes the chunk,
//! its message indexes and nothing else; the summary (schemas, channels, statistics, chunk,
//! attachment and metadata indexes, summary offsets) and the footer are written by
//! [`McapWriter::finish`]. Every CRC the format has is computed.
//!
//! The `mcap` crate stays the reader (`read.rs`) and the writer of `log recover`; the tests
//! read this writer's files with it and with the Python `mcap` reader, CRCs validated.
//!
//! Format: <https://mcap.dev/spec>. Layout written:
//!
//! ```text
//! magic, Header, (Schema | Channel | Attachment | Metadata | Chunk MessageIndex*)*, DataEnd,
//! summary: Schema*, Channel*, Statistics, ChunkIndex*, AttachmentIndex*, MetadataIndex*,
//!          SummaryOffset*, Footer, magic
//! ```
//!
//! Schemas and channels go into the data section before the first chunk that uses them (the
//! open chunk is finished first), so a truncated file keeps them (`log recover`).

use std::collections::BTreeMap;
use std::io::{self, Write};

use mcap::records::{MessageHeader, Metadata};
use mcap::{Attachment, MAGIC};

mod op {
    pub const HEADER: u8 = 0x01;
    pub const FOOTER: u8 = 0x02;
    pub const SCHEMA: u8 = 0x03;
    pub const CHANNEL: u8 = 0x04;
    pub const MESSAGE: u8 = 0x05;
    pub const CHUNK: u8 = 0x06;
    pub const MESSAGE_INDEX: u8 = 0x07;
    pub const CHUNK_INDEX: u8 = 0x08;
    pub const ATTACHMENT: u8 = 0x09;
    pub const ATTACHMENT_INDEX: u8 = 0x0A;
    pub const STATISTICS: u8 = 0x0B;
    pub const METADATA: u8 = 0x0C;
    pub const METADATA_INDEX: u8 = 0x0D;
    pub const SUMMARY_OFFSET: u8 = 0x0E;
    pub const DATA_END: u8 = 0x0F;
}

/// How chunks are cut and compressed.
#[derive(Clone, Debug)]
pub struct ChunkOptions {
    /// Finish a chunk once its uncompressed records pass this many bytes.
    pub chunk_size: usize,
    /// zstd level of every chunk.
    pub zstd_level: i32,
    /// The Header's `library` field.
    pub library: String,
}

/// Little-endian record fields appended to a buffer.
trait Put {
    fn u8(&mut self, v: u8);
    fn u16(&mut self, v: u16);
    fn u32(&mut self, v: u32);
    fn u64(&mut self, v: u64);
    fn str(&mut self, s: &str);
    fn map(&mut self, m: &BTreeMap<String, String>);
    /// A `Map<uint16, uint64>` (channel id → count or offset).
    fn map_u16_u64(&mut self, m: &[(u16, u64)]);
}

impl Put for Vec<u8> {
    fn u8(&mut self, v: u8) {
        self.push(v);
    }
    fn u16(&mut self, v: u16) {
        self.extend_from_slice(&v.to_le_bytes());
    }
    fn u32(&mut self, v: u32) {
        self.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.extend_from_slice(&v.to_le_bytes());
    }
    fn str(&mut self, s: &str) {
        self.u32(s.len() as u32);
        self.extend_from_slice(s.as_bytes());
    }
    fn map_u16_u64(&mut self, m: &[(u16, u64)]) {
        self.u32((m.len() * 10) as u32);
        for &(k, v) in m {
            self.u16(k);
            self.u64(v);
        }
    }
    fn map(&mut self, m: &BTreeMap<String, String>) {
        let len: usize = m.iter().map(|(k, v)| 8 + k.len() + v.len()).sum();
        self.u32(len as u32);
        for (k, v) in m {
            self.str(k);
            self.str(v);
        }
    }
}

/// A record: opcode, then a placeholder length patched by [`end_record`].
fn begin_record(buf: &mut Vec<u8>, opcode: u8) -> usize {
    buf.u8(opcode);
    buf.u64(0);
    buf.len()
}

fn end_record(buf: &mut [u8], body_start: usize) {
    let len = (buf.len() - body_start) as u64;
    buf[body_start - 8..body_start].copy_from_slice(&len.to_le_bytes());
}

/// The output: counts bytes and keeps the CRC of what it wrote since the last reset.
struct Out<W> {
    inner: W,
    pos: u64,
    crc: crc32fast::Hasher,
}

impl<W: Write> Out<W> {
    fn write(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.inner.write_all(bytes)?;
        self.crc.update(bytes);
        self.pos += bytes.len() as u64;
        Ok(())
    }

    fn take_crc(&mut self) -> u32 {
        std::mem::take(&mut self.crc).finalize()
    }
}

struct ChunkIndex {
    start_time: u64,
    end_time: u64,
    offset: u64,
    length: u64,
    message_index_offsets: Vec<(u16, u64)>,
    message_index_length: u64,
    compressed_size: u64,
    uncompressed_size: u64,
}

struct AttachmentIndex {
    offset: u64,
    length: u64,
    log_time: u64,
    create_time: u64,
    data_size: u64,
    name: String,
    media_type: String,
}

/// A channel: id, schema id, topic, message encoding, metadata.
struct Channel {
    id: u16,
    schema_id: u16,
    topic: String,
    encoding: String,
    metadata: BTreeMap<String, String>,
}

/// The open chunk: its records, uncompressed, and per channel the message index.
#[derive(Default)]
struct Chunk {
    records: Vec<u8>,
    start_time: u64,
    end_time: u64,
    /// Per channel id: `(log_time, offset in records)`; channels in first-use order.
    index: Vec<(u16, Vec<(u64, u64)>)>,
    /// Position in `index` of each channel id (`usize::MAX`: none yet).
    slot: Vec<usize>,
}

impl Chunk {
    fn is_empty(&self) -> bool {
        self.records.is_empty()
    }

    /// The index entries of channel `ch`, created on first use.
    fn entries(&mut self, ch: u16) -> &mut Vec<(u64, u64)> {
        let i = usize::from(ch);
        if self.slot.len() <= i {
            self.slot.resize(i + 1, usize::MAX);
        }
        if self.slot[i] == usize::MAX {
            self.slot[i] = self.index.len();
            self.index.push((ch, Vec::new()));
        }
        &mut self.index[self.slot[i]].1
    }
}

/// Writes one MCAP file. See the module docs.
pub struct McapWriter<W: Write> {
    out: Out<W>,
    options: ChunkOptions,
    zstd: zstd::bulk::Compressor<'static>,
    compressed: Vec<u8>,
    scratch: Vec<u8>,
    chunk: Chunk,
    /// `(id, name, encoding, data)`.
    schemas: Vec<(u16, String, String, Vec<u8>)>,
    channels: Vec<Channel>,
    channel_counts: BTreeMap<u16, u64>,
    message_count: u64,
    message_bounds: Option<(u64, u64)>,
    chunk_indexes: Vec<ChunkIndex>,
    attachment_indexes: Vec<AttachmentIndex>,
    /// `(offset, length, name)`.
    metadata_indexes: Vec<(u64, u64, String)>,
    finished: bool,
}

impl<W: Write> std::fmt::Debug for McapWriter<W> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("McapWriter").field("pos", &self.out.pos).field("messages", &self.message_count).finish()
    }
}

impl<W: Write> McapWriter<W> {
    /// Writes the magic and the Header.
    pub fn new(inner: W, options: ChunkOptions) -> io::Result<Self> {
        let zstd = zstd::bulk::Compressor::new(options.zstd_level)?;
        let mut w = Self {
            out: Out { inner, pos: 0, crc: crc32fast::Hasher::new() },
            options,
            zstd,
            compressed: Vec::new(),
            scratch: Vec::new(),
            chunk: Chunk::default(),
            schemas: Vec::new(),
            channels: Vec::new(),
            channel_counts: BTreeMap::new(),
            message_count: 0,
            message_bounds: None,
            chunk_indexes: Vec::new(),
            attachment_indexes: Vec::new(),
            metadata_indexes: Vec::new(),
            finished: false,
        };
        w.out.write(MAGIC)?;
        let mut b = Vec::new();
        let body = begin_record(&mut b, op::HEADER);
        b.str(""); // profile
        b.str(&w.options.library);
        end_record(&mut b, body);
        w.out.write(&b)?;
        Ok(w)
    }

    /// Adds a schema (the same name, encoding and data again give the same id).
    pub fn add_schema(&mut self, name: &str, encoding: &str, data: &[u8]) -> io::Result<u16> {
        if let Some(s) = self.schemas.iter().find(|s| s.1 == name && s.2 == encoding && s.3 == data) {
            return Ok(s.0);
        }
        let id = self.schemas.len() as u16 + 1;
        self.finish_chunk()?;
        let mut b = std::mem::take(&mut self.scratch);
        b.clear();
        schema_record(&mut b, id, name, encoding, data);
        let r = self.out.write(&b);
        self.scratch = b;
        r?;
        self.schemas.push((id, name.to_owned(), encoding.to_owned(), data.to_vec()));
        Ok(id)
    }

    /// Adds a channel (the same topic, schema, encoding and metadata again give the same id).
    pub fn add_channel(
        &mut self,
        schema_id: u16,
        topic: &str,
        message_encoding: &str,
        metadata: &BTreeMap<String, String>,
    ) -> io::Result<u16> {
        if let Some(c) = self.channels.iter().find(|c| {
            c.schema_id == schema_id && c.topic == topic && c.encoding == message_encoding && &c.metadata == metadata
        }) {
            return Ok(c.id);
        }
        let id = self.channels.len() as u16;
        self.finish_chunk()?;
        let mut b = std::mem::take(&mut self.scratch);
        b.clear();
        channel_record(&mut b, id, schema_id, topic, message_encoding, metadata);
        let r = self.out.write(&b);
        self.scratch = b;
        r?;
        self.channels.push(Channel {
            id,
            schema_id,
            topic: topic.to_owned(),
            encoding: message_encoding.to_owned(),
            metadata: metadata.clone(),
        });
        Ok(id)
    }

    /// Appends a message to the open chunk; finishes the chunk once it is big enough.
    pub fn write_to_known_channel(&mut self, header: &MessageHeader, data: &[u8]) -> io::Result<()> {
        let ch = header.channel_id;
        if usize::from(ch) >= self.channels.len() {
            return Err(io::Error::new(io::ErrorKind::InvalidInput, format!("unknown channel {ch}")));
        }
        let c = &mut self.chunk;
        if c.is_empty() {
            (c.start_time, c.end_time) = (header.log_time, header.log_time);
        } else {
            c.start_time = c.start_time.min(header.log_time);
            c.end_time = c.end_time.max(header.log_time);
        }
        let offset = c.records.len() as u64;
        c.entries(ch).push((header.log_time, offset));
        let r = &mut c.records;
        r.u8(op::MESSAGE);
        r.u64(22 + data.len() as u64);
        r.u16(ch);
        r.u32(header.sequence);
        r.u64(header.log_time);
        r.u64(header.publish_time);
        r.extend_from_slice(data);

        *self.channel_counts.entry(ch).or_insert(0) += 1;
        self.message_count += 1;
        self.message_bounds = Some(match self.message_bounds {
            None => (header.log_time, header.log_time),
            Some((a, b)) => (a.min(header.log_time), b.max(header.log_time)),
        });
        if self.chunk.records.len() >= self.options.chunk_size {
            self.finish_chunk()?;
        }
        Ok(())
    }

    /// Writes an attachment (after finishing the open chunk).
    pub fn attach(&mut self, a: &Attachment<'_>) -> io::Result<()> {
        self.finish_chunk()?;
        let mut b = Vec::with_capacity(64 + a.data.len());
        let body = begin_record(&mut b, op::ATTACHMENT);
        b.u64(a.log_time);
        b.u64(a.create_time);
        b.str(&a.name);
        b.str(&a.media_type);
        b.u64(a.data.len() as u64);
        b.extend_from_slice(&a.data);
        let crc = crc32fast::hash(&b[body..]);
        b.u32(crc);
        end_record(&mut b, body);
        let offset = self.out.pos;
        self.out.write(&b)?;
        self.attachment_indexes.push(AttachmentIndex {
            offset,
            length: b.len() as u64,
            log_time: a.log_time,
            create_time: a.create_time,
            data_size: a.data.len() as u64,
            name: a.name.clone(),
            media_type: a.media_type.clone(),
        });
        Ok(())
    }

    /// Writes a metadata record (after finishing the open chunk).
    pub fn write_metadata(&mut self, m: &Metadata) -> io::Result<()> {
        self.finish_chunk()?;
        let mut b = Vec::new();
        let body = begin_record(&mut b, op::METADATA);
        b.str(&m.name);
        b.map(&m.metadata);
        end_record(&mut b, body);
        let offset = self.out.pos;
        self.out.write(&b)?;
        self.metadata_indexes.push((offset, b.len() as u64, m.name.clone()));
        Ok(())
    }

    /// Finishes the open chunk and flushes the output: what was written so far is readable
    /// from the file.
    pub fn flush(&mut self) -> io::Result<()> {
        self.finish_chunk()?;
        self.out.inner.flush()
    }

    /// Compresses and writes the open chunk (if any) and its message indexes.
    fn finish_chunk(&mut self) -> io::Result<()> {
        if self.chunk.is_empty() {
            return Ok(());
        }
        let records = &self.chunk.records;
        let uncompressed_crc = crc32fast::hash(records);
        self.compressed.clear();
        self.compressed.reserve(zstd::zstd_safe::compress_bound(records.len()));
        self.zstd.compress_to_buffer(records, &mut self.compressed)?;

        let b = &mut self.scratch;
        b.clear();
        let body = begin_record(b, op::CHUNK);
        b.u64(self.chunk.start_time);
        b.u64(self.chunk.end_time);
        b.u64(records.len() as u64);
        b.u32(uncompressed_crc);
        b.str("zstd");
        b.u64(self.compressed.len() as u64);
        let head_len = b.len();
        let chunk_len = (head_len - body + self.compressed.len()) as u64;
        b[body - 8..body].copy_from_slice(&chunk_len.to_le_bytes());
        let offset = self.out.pos;
        let b = std::mem::take(&mut self.scratch);
        let r = self.out.write(&b).and_then(|()| self.out.write(&self.compressed));
        self.scratch = b;
        r?;

        // Message indexes, in channel-id order (channels idle in this chunk keep an empty,
        // reusable entry list and get no index).
        self.chunk.index.sort_by_key(|(ch, _)| *ch);
        let index_start = self.out.pos;
        let mut message_index_offsets = Vec::with_capacity(self.chunk.index.len());
        let b = &mut self.scratch;
        b.clear();
        for (ch, entries) in self.chunk.index.iter().filter(|(_, e)| !e.is_empty()) {
            message_index_offsets.push((*ch, index_start + b.len() as u64));
            let body = begin_record(b, op::MESSAGE_INDEX);
            b.u16(*ch);
            b.u32((entries.len() * 16) as u32);
            for &(t, o) in entries {
                b.u64(t);
                b.u64(o);
            }
            end_record(b, body);
        }
        let b = std::mem::take(&mut self.scratch);
        let r = self.out.write(&b);
        let message_index_length = b.len() as u64;
        self.scratch = b;
        r?;
        self.chunk_indexes.push(ChunkIndex {
            start_time: self.chunk.start_time,
            end_time: self.chunk.end_time,
            offset,
            length: 9 + chunk_len,
            message_index_offsets,
            message_index_length,
            compressed_size: self.compressed.len() as u64,
            uncompressed_size: self.chunk.records.len() as u64,
        });
        // Keep the buffers for the next chunk: no reallocation once warm.
        self.chunk.records.clear();
        let c = &mut self.chunk;
        for (i, (ch, entries)) in c.index.iter_mut().enumerate() {
            entries.clear();
            c.slot[usize::from(*ch)] = i;
        }
        Ok(())
    }

    /// Finishes the open chunk, writes DataEnd, the summary section, the footer and the
    /// closing magic, and flushes. Later calls do nothing.
    pub fn finish(&mut self) -> io::Result<()> {
        if self.finished {
            return Ok(());
        }
        self.finish_chunk()?;
        self.finished = true;

        let mut b = Vec::new();
        let body = begin_record(&mut b, op::DATA_END);
        b.u32(self.out.take_crc());
        end_record(&mut b, body);
        self.out.write(&b)?;
        self.out.take_crc(); // the summary CRC starts here

        let summary_start = self.out.pos;
        let mut groups: Vec<(u8, u64, u64)> = Vec::new();
        let mut group = |w: &mut Self, opcode: u8, b: &[u8]| -> io::Result<()> {
            if !b.is_empty() {
                groups.push((opcode, w.out.pos, b.len() as u64));
                w.out.write(b)?;
            }
            Ok(())
        };

        let mut b = Vec::new();
        for (id, name, encoding, data) in &self.schemas {
            schema_record(&mut b, *id, name, encoding, data);
        }
        group(self, op::SCHEMA, &b)?;

        let mut b = Vec::new();
        for c in &self.channels {
            channel_record(&mut b, c.id, c.schema_id, &c.topic, &c.encoding, &c.metadata);
        }
        group(self, op::CHANNEL, &b)?;

        let mut b = Vec::new();
        let body = begin_record(&mut b, op::STATISTICS);
        let (start, end) = self.message_bounds.unwrap_or((0, 0));
        b.u64(self.message_count);
        b.u16(self.schemas.len() as u16);
        b.u32(self.channels.len() as u32);
        b.u32(self.attachment_indexes.len() as u32);
        b.u32(self.metadata_indexes.len() as u32);
        b.u32(self.chunk_indexes.len() as u32);
        b.u64(start);
        b.u64(end);
        let counts: Vec<(u16, u64)> = self.channel_counts.iter().map(|(&ch, &n)| (ch, n)).collect();
        b.map_u16_u64(&counts);
        end_record(&mut b, body);
        group(self, op::STATISTICS, &b)?;

        let mut b = Vec::new();
        for c in &self.chunk_indexes {
            let body = begin_record(&mut b, op::CHUNK_INDEX);
            b.u64(c.start_time);
            b.u64(c.end_time);
            b.u64(c.offset);
            b.u64(c.length);
            b.map_u16_u64(&c.message_index_offsets);
            b.u64(c.message_index_length);
            b.str("zstd");
            b.u64(c.compressed_size);
            b.u64(c.uncompressed_size);
            end_record(&mut b, body);
        }
        group(self, op::CHUNK_INDEX, &b)?;

        let mut b = Vec::new();
        for a in &self.attachment_indexes {
            let body = begin_record(&mut b, op::ATTACHMENT_INDEX);
            b.u64(a.offset);
            b.u64(a.length);
            b.u64(a.log_time);
            b.u64(a.create_time);
            b.u64(a.data_size);
            b.str(&a.name);
            b.str(&a.media_type);
            end_record(&mut b, body);
        }
        group(self, op::ATTACHMENT_INDEX, &b)?;

        let mut b = Vec::new();
        for (offset, length, name) in &self.metadata_indexes {
            let body = begin_record(&mut b, op::METADATA_INDEX);
            b.u64(*offset);
            b.u64(*length);
            b.str(name);
            end_record(&mut b, body);
        }
        group(self, op::METADATA_INDEX, &b)?;

        let summary_offset_start = self.out.pos;
        let mut b = Vec::new();
        for (opcode, start, length) in groups {
            let body = begin_record(&mut b, op::SUMMARY_OFFSET);
            b.u8(opcode);
            b.u64(start);
            b.u64(length);
            end_record(&mut b, body);
        }
        // Footer: its CRC covers the summary section up to and including
        // `summary_offset_start`.
        let body = begin_record(&mut b, op::FOOTER);
        b.u64(summary_start);
        b.u64(summary_offset_start);
        end_record(&mut b, body);
        // The length field counts the CRC that follows.
        let len = (b.len() - body + 4) as u64;
        b[body - 8..body].copy_from_slice(&len.to_le_bytes());
        self.out.write(&b)?;
        let crc = self.out.take_crc();
        self.out.write(&crc.to_le_bytes())?;
        self.out.write(MAGIC)?;
        self.out.inner.flush()
    }

    /// The output, after [`McapWriter::finish`].
    #[cfg(test)]
    pub fn into_inner(self) -> W {
        self.out.inner
    }
}

fn schema_record(b: &mut Vec<u8>, id: u16, name: &str, encoding: &str, data: &[u8]) {
    let body = begin_record(b, op::SCHEMA);
    b.u16(id);
    b.str(name);
    b.str(encoding);
    b.u32(data.len() as u32);
    b.extend_from_slice(data);
    end_record(b, body);
}

fn channel_record(
    b: &mut Vec<u8>,
    id: u16,
    schema_id: u16,
    topic: &str,
    encoding: &str,
    meta: &BTreeMap<String, String>,
) {
    let body = begin_record(b, op::CHANNEL);
    b.u16(id);
    b.u16(schema_id);
    b.str(topic);
    b.str(encoding);
    b.map(meta);
    end_record(b, body);
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::borrow::Cow;

    fn options() -> ChunkOptions {
        ChunkOptions { chunk_size: 4096, zstd_level: 1, library: "test".into() }
    }

    /// A file with every kind of record, read back by the `mcap` crate: summary, statistics,
    /// indexes, CRCs (chunk, data section, summary, attachment), and every message in order.
    #[test]
    fn the_mcap_crate_reads_everything_back() {
        let mut w = McapWriter::new(Vec::new(), options()).unwrap();
        w.attach(&Attachment {
            log_time: 5,
            create_time: 6,
            name: "scene.toml".into(),
            media_type: "application/toml".into(),
            data: Cow::Borrowed(b"[sim]\nseed = 1\n"),
        })
        .unwrap();
        let mut meta = BTreeMap::new();
        meta.insert("seed".to_owned(), "1".to_owned());
        w.write_metadata(&Metadata { name: "twinswarm".into(), metadata: meta }).unwrap();
        let s = w.add_schema("a.A", "jsonschema", b"{}").unwrap();
        assert_eq!(w.add_schema("a.A", "jsonschema", b"{}").unwrap(), s, "same schema, same id");
        let c0 = w.add_channel(s, "/a", "json", &BTreeMap::new()).unwrap();
        let c1 = w.add_channel(s, "/b", "json", &BTreeMap::new()).unwrap();
        let mut sent = Vec::new();
        for i in 0..2000u64 {
            let ch = if i % 3 == 0 { c1 } else { c0 };
            if i == 1000 {
                w.flush().unwrap();
                let late = w.add_channel(s, "/late", "json", &BTreeMap::new()).unwrap();
                let h = MessageHeader { channel_id: late, sequence: 0, log_time: 10 * i, publish_time: 1 };
                w.write_to_known_channel(&h, b"{\"late\":true}").unwrap();
                sent.push((late, 10 * i, b"{\"late\":true}".to_vec()));
            }
            let data = format!("{{\"i\":{i}}}").into_bytes();
            let h = MessageHeader { channel_id: ch, sequence: i as u32, log_time: 10 * i, publish_time: 10 * i + 1 };
            w.write_to_known_channel(&h, &data).unwrap();
            sent.push((ch, 10 * i, data));
        }
        w.finish().unwrap();
        let bytes = w.into_inner();

        let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
        let stats = summary.stats.as_ref().expect("statistics");
        assert_eq!(stats.message_count, sent.len() as u64);
        assert_eq!((stats.schema_count, stats.channel_count, stats.attachment_count), (1, 3, 1));
        assert_eq!((stats.message_start_time, stats.message_end_time), (0, 19_990));
        assert!(summary.chunk_indexes.len() > 2, "{} chunks", summary.chunk_indexes.len());
        assert_eq!(summary.attachment_indexes.len(), 1);
        assert_eq!(summary.metadata_indexes.len(), 1);
        let att = mcap::read::attachment(&bytes, &summary.attachment_indexes[0]).unwrap();
        assert_eq!(&att.data[..], b"[sim]\nseed = 1\n");
        let m = mcap::read::metadata(&bytes, &summary.metadata_indexes[0]).unwrap();
        assert_eq!(m.metadata["seed"], "1");
        // Message indexes agree with the chunks.
        for ci in &summary.chunk_indexes {
            let idx = summary.read_message_indexes(&bytes, ci).unwrap();
            let n: usize = idx.values().map(Vec::len).sum();
            assert!(n > 0);
            for entries in idx.values() {
                for e in entries {
                    let msg = summary.seek_message(&bytes, ci, e).unwrap();
                    assert_eq!(msg.log_time, e.log_time);
                }
            }
        }
        // The data section and summary CRCs (the crate does not check them).
        let n = bytes.len();
        let footer = &bytes[n - 8 - 29..n - 8];
        assert_eq!(footer[0], op::FOOTER);
        let u64_at = |b: &[u8], i: usize| u64::from_le_bytes(b[i..i + 8].try_into().unwrap());
        let summary_start = u64_at(footer, 9) as usize;
        let data_end = &bytes[summary_start - 13..summary_start];
        assert_eq!(data_end[0], op::DATA_END);
        let data_crc = u32::from_le_bytes(data_end[9..13].try_into().unwrap());
        assert_eq!(data_crc, crc32fast::hash(&bytes[..summary_start - 13]));
        let summary_crc = u32::from_le_bytes(footer[25..29].try_into().unwrap());
        assert_eq!(summary_crc, crc32fast::hash(&bytes[summary_start..n - 8 - 4]));
        // Every message, in order, chunk CRCs checked.
        let opts = mcap::read::Options::ValidateChunkCrcs.into();
        let got: Vec<(u16, u64, Vec<u8>)> = mcap::MessageStream::new_with_options(&bytes, opts)
            .unwrap()
            .map(|m| {
                let m = m.unwrap();
                (m.channel.id, m.log_time, m.data.into_owned())
            })
            .collect();
        assert_eq!(got, sent);
    }

    #[test]
    fn an_empty_file_is_valid() {
        let mut w = McapWriter::new(Vec::new(), options()).unwrap();
        w.finish().unwrap();
        let bytes = w.into_inner();
        let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
        assert_eq!(summary.stats.unwrap().message_count, 0);
        assert_eq!(mcap::MessageStream::new(&bytes).unwrap().count(), 0);
    }
}
