//! The `.vdag.zst` transport form: a whole `.vdag` file as one standard zstd
//! frame with the content size and content checksum flags set, so any zstd
//! tool can unpack it and a reader can refuse an oversized file before
//! decompressing anything.
//!
//! [`unpack`] only undoes the compression (and checks that the result starts
//! with the `.vdag` magic); callers validate the file they get
//! ([`crate::validate`]) as they would any other.

use std::io::{self, Read, Write};

use thiserror::Error;

use crate::layout::{HEADER_SIZE, MAGIC, MAX_FILE_SIZE};

/// The four bytes every zstd frame starts with.
pub const ZSTD_MAGIC: [u8; 4] = [0x28, 0xb5, 0x2f, 0xfd];

/// The compression level [`pack`] callers use unless told otherwise.
pub const DEFAULT_LEVEL: i32 = 19;

/// The size limit [`unpack`] callers use unless told otherwise.
pub const DEFAULT_MAX_SIZE: u64 = MAX_FILE_SIZE;

/// The most bytes one zstd frame can decode to, per byte of the frame: the
/// densest block is a 4-byte RLE block (3-byte block header and the byte to
/// repeat) that expands to at most 128 KiB. [`unpack`] refuses a frame that
/// declares more than this many times its own length, and never lets the
/// decoder open a window larger than that (see spec/VDAG.md § 16.2).
pub const MAX_EXPANSION: u64 = 32 * 1024;

/// The smallest and largest decoder windows (log2 bytes) zstd knows.
const WINDOW_LOG_RANGE: std::ops::RangeInclusive<u32> = 10..=31;

/// Why packing or unpacking failed.
#[derive(Debug, Error)]
pub enum TransportError {
    /// The input to pack is not a `.vdag` file (or its header's size is wrong).
    #[error("not a .vdag file: {0}")]
    NotVdag(String),
    /// The input to unpack is not a zstd frame.
    #[error("not a zstd frame (bad magic)")]
    NotZstd,
    /// The frame declares (or decodes to) more bytes than allowed.
    #[error("the unpacked file would be at least {size} bytes, over the limit of {limit}")]
    TooLarge {
        /// The declared size, or the bytes decoded when decoding passed the limit.
        size: u64,
        /// The limit.
        limit: u64,
    },
    /// Bytes follow the single frame.
    #[error("{0} bytes follow the zstd frame (a transport file is exactly one frame)")]
    TrailingData(u64),
    /// The frame is damaged or is not a standard zstd frame.
    #[error("corrupt zstd frame: {0}")]
    Corrupt(String),
    /// Reading or writing failed.
    #[error("I/O error: {0}")]
    Io(#[from] io::Error),
}

/// Whether `bytes` start with the zstd frame magic.
pub fn is_transport(bytes: &[u8]) -> bool {
    bytes.starts_with(&ZSTD_MAGIC)
}

/// The file size a `.vdag` header declares, after checking the magic.
fn declared_vdag_size(header: &[u8]) -> Result<u64, TransportError> {
    if header.len() < HEADER_SIZE || header[..8] != MAGIC {
        return Err(TransportError::NotVdag(
            "missing .vdag magic or header".into(),
        ));
    }
    Ok(u64::from_le_bytes(
        header[64..72].try_into().expect("8 bytes"),
    ))
}

/// Compresses a whole `.vdag` file at zstd `level` (1 to 22) into one frame
/// with its content size and checksum.
pub fn pack(vdag: &[u8], level: i32) -> Result<Vec<u8>, TransportError> {
    let declared = declared_vdag_size(vdag)?;
    if declared != vdag.len() as u64 {
        return Err(TransportError::NotVdag(format!(
            "header says {declared} bytes but {} were given",
            vdag.len()
        )));
    }
    let mut out = Vec::with_capacity(vdag.len() / 4 + 64);
    pack_to(vdag, &mut out, level)?;
    Ok(out)
}

/// Compresses a `.vdag` file read from `reader` into `writer`, streaming. The
/// size pledged in the frame header is the header's file size; a stream of
/// another length fails. Returns the bytes read. On error `writer` holds a
/// partial frame: write to a temporary file and rename it on success.
pub fn pack_to<R: Read, W: Write>(
    mut reader: R,
    writer: W,
    level: i32,
) -> Result<u64, TransportError> {
    let mut header = [0u8; HEADER_SIZE];
    reader.read_exact(&mut header).map_err(|e| match e.kind() {
        io::ErrorKind::UnexpectedEof => {
            TransportError::NotVdag("shorter than a .vdag header".into())
        }
        _ => TransportError::Io(e),
    })?;
    let size = declared_vdag_size(&header)?;
    let mut encoder = zstd::stream::write::Encoder::new(writer, level)?;
    encoder.include_checksum(true)?;
    encoder.include_contentsize(true)?;
    encoder.set_pledged_src_size(Some(size))?;
    encoder.write_all(&header)?;
    let copied = io::copy(&mut reader, &mut encoder)? + HEADER_SIZE as u64;
    if copied != size {
        return Err(TransportError::NotVdag(format!(
            "header says {size} bytes but the input has {copied}"
        )));
    }
    encoder.finish()?.flush()?;
    Ok(copied)
}

/// Decompresses a transport file into the `.vdag` bytes. Refuses a frame
/// whose declared content size exceeds `max_size` before decoding, and stops
/// decoding once the output would exceed `max_size` (for frames that do not
/// declare their size), so hostile input cannot make it allocate more than
/// `max_size` bytes. Also refuses trailing bytes after the frame and output
/// that is not a `.vdag` file.
///
/// Memory is bounded by the input as well (spec/VDAG.md § 16.2): a frame
/// cannot decode to more than [`MAX_EXPANSION`] times its length, so a frame
/// declaring more is refused as corrupt before decoding, and the decoder's
/// window (the one buffer zstd sizes from the frame header) is capped at the
/// smallest power of two holding `min(max_size, MAX_EXPANSION * zst.len())`.
/// In all, unpacking allocates at most about four times that bound plus a
/// constant (the decoder's state and one 128 KiB chunk).
pub fn unpack(zst: &[u8], max_size: u64) -> Result<Vec<u8>, TransportError> {
    if !is_transport(zst) {
        return Err(TransportError::NotZstd);
    }
    let declared = zstd::zstd_safe::get_frame_content_size(zst)
        .map_err(|_| TransportError::Corrupt("unreadable frame header".into()))?;
    let possible = MAX_EXPANSION.saturating_mul(zst.len() as u64);
    if let Some(size) = declared {
        if size > max_size {
            return Err(TransportError::TooLarge {
                size,
                limit: max_size,
            });
        }
        if size > possible {
            return Err(TransportError::Corrupt(format!(
                "the frame declares {size} bytes, more than a {}-byte frame can hold",
                zst.len()
            )));
        }
    }
    let output_bound = max_size.min(possible);
    let frame_len = zstd::zstd_safe::find_frame_compressed_size(zst).map_err(|code| {
        TransportError::Corrupt(zstd::zstd_safe::get_error_name(code).to_string())
    })?;
    if frame_len < zst.len() {
        return Err(TransportError::TrailingData((zst.len() - frame_len) as u64));
    }
    // Preallocate what the frame declares, but never more than a generous
    // multiple of its compressed size, so a lying header costs nothing; grow
    // by hand so that the buffer never exceeds the limit by more than a chunk.
    let guess = declared
        .unwrap_or(0)
        .min(zst.len() as u64 * 64)
        .min(max_size);
    let mut out: Vec<u8> = Vec::with_capacity(guess as usize);
    let mut decoder = zstd::stream::read::Decoder::with_buffer(zst)?.single_frame();
    // A frame never needs a window larger than its output, which is at most
    // `output_bound`; a larger window would only make zstd allocate it.
    let window_log = (u64::BITS - output_bound.saturating_sub(1).leading_zeros())
        .clamp(*WINDOW_LOG_RANGE.start(), *WINDOW_LOG_RANGE.end());
    decoder.window_log_max(window_log)?;
    let mut chunk = vec![0u8; 1 << 17];
    loop {
        let n = decoder
            .read(&mut chunk)
            .map_err(|e| TransportError::Corrupt(e.to_string()))?;
        if n == 0 {
            break;
        }
        if out.len() as u64 + n as u64 > max_size {
            return Err(TransportError::TooLarge {
                size: out.len() as u64 + n as u64,
                limit: max_size,
            });
        }
        if out.capacity() - out.len() < n {
            let wanted = out
                .capacity()
                .max(n)
                .min((max_size - out.len() as u64) as usize);
            out.reserve_exact(wanted.max(n));
        }
        out.extend_from_slice(&chunk[..n]);
    }
    if let Some(size) = declared
        && size != out.len() as u64
    {
        return Err(TransportError::Corrupt(format!(
            "frame declares {size} bytes but holds {}",
            out.len()
        )));
    }
    if out.len() < MAGIC.len() || out[..8] != MAGIC {
        return Err(TransportError::NotVdag(
            "the frame does not hold a .vdag file".into(),
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_non_zstd_and_garbage() {
        assert!(matches!(
            unpack(b"hello", 1000),
            Err(TransportError::NotZstd)
        ));
        let mut bad = ZSTD_MAGIC.to_vec();
        bad.extend_from_slice(&[0xff; 16]);
        assert!(unpack(&bad, 1000).is_err());
    }
}
