//! The log file's MCAP writer: the `mcap` crate's, with one fixed set of options and its
//! errors as I/O errors. The writer thread (`writer`), the Paparazzi channels (`pprz`) and
//! `log import` write through it.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;

use mcap::Attachment;
use mcap::records::{MessageHeader, Metadata};

/// The file's MCAP writer: the `mcap` crate's, its errors as I/O errors.
pub(super) struct McapOut(mcap::Writer<BufWriter<File>>, File);

fn io_error(e: mcap::McapError) -> std::io::Error {
    match e {
        mcap::McapError::Io(e) => e,
        other => std::io::Error::other(other),
    }
}

impl McapOut {
    /// zstd chunks at one `zstd_level`, finished at `chunk_size` bytes or at each flush; every
    /// CRC; the compression on the writer thread itself (no zstd worker threads).
    pub(super) fn create(file: File, zstd_level: u32, chunk_size: usize) -> std::io::Result<Self> {
        let sync_handle = file.try_clone()?;
        let w = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(zstd_level)
            .compression_threads(0)
            .chunk_size(Some(chunk_size as u64))
            // Message indexes are optional in MCAP (readers fall back to the chunk indexes and
            // read whole chunks); at 16 bytes per message, outside the compression, they were
            // a fifth of a swarm's file.
            .emit_message_indexes(false)
            .library(format!("twinswarm {}", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::with_capacity(1 << 16, file))
            .map_err(io_error)?;
        Ok(Self(w, sync_handle))
    }

    pub(super) fn add_schema(&mut self, name: &str, encoding: &str, data: &[u8]) -> std::io::Result<u16> {
        self.0.add_schema(name, encoding, data).map_err(io_error)
    }

    pub(super) fn add_channel(
        &mut self,
        schema: u16,
        topic: &str,
        encoding: &str,
        metadata: &BTreeMap<String, String>,
    ) -> std::io::Result<u16> {
        self.0.add_channel(schema, topic, encoding, metadata).map_err(io_error)
    }

    pub(super) fn write_to_known_channel(&mut self, header: &MessageHeader, data: &[u8]) -> std::io::Result<()> {
        self.0.write_to_known_channel(header, data).map_err(io_error)
    }

    pub(super) fn attach(&mut self, a: &Attachment<'_>) -> std::io::Result<()> {
        self.0.attach(a).map_err(io_error)
    }

    pub(super) fn write_metadata(&mut self, m: &Metadata) -> std::io::Result<()> {
        self.0.write_metadata(m).map_err(io_error)
    }

    /// Finishes the open chunk and flushes the file: what was written is readable.
    pub(super) fn flush(&mut self) -> std::io::Result<()> {
        self.0.flush().map_err(io_error)
    }

    /// [`McapOut::flush`], then `fsync`: what was written survives the machine.
    pub(super) fn sync(&mut self) -> std::io::Result<()> {
        self.flush()?;
        self.1.sync_data()
    }

    /// The summary section and the footer.
    pub(super) fn finish(&mut self) -> std::io::Result<()> {
        self.0.finish().map(drop).map_err(io_error)
    }
}
