//! Voxel lists: the text and binary inputs of `dagtool convert`.
//!
//! Text (`.txt`, `.xyz`, `.voxels`): one voxel per line, three unsigned
//! decimal integers `x y z` separated by spaces or tabs; `#` starts a comment
//! (whole line or after the numbers); blank lines are ignored.
//!
//! Binary (any extension; recognised by its magic), little-endian:
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 4 | magic `VVOX` (0x56 0x56 0x4F 0x58) |
//! | 4 | 4 | u32 version = 1 |
//! | 8 | 4 | u32 depth D (2..=21) |
//! | 12 | 8 | u64 count N |
//! | 20 | 12 N | N records of u32 x, u32 y, u32 z (each < 2^D) |
//!
//! The file is exactly `20 + 12 N` bytes. Duplicates are allowed in both forms
//! (a voxel is set once). The voxels' world space is the grid itself: root
//! cube corner (0, 0, 0), edge 2^D.

use std::fs::File;
use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;

use dagfmt::layout::{MAX_DEPTH, MIN_DEPTH};

use crate::error::ConvertError;

/// Magic of the binary voxel list.
pub const BINARY_MAGIC: [u8; 4] = *b"VVOX";
/// Version of the binary voxel list.
pub const BINARY_VERSION: u32 = 1;
/// Size of the binary header.
pub const BINARY_HEADER_SIZE: usize = 20;

/// A voxel list read from a file.
#[derive(Clone, Debug)]
pub struct VoxelList {
    /// Depth of the volume.
    pub depth: u8,
    /// Morton codes of the voxels, increasing, without duplicates.
    pub codes: Vec<u64>,
    /// Records read (duplicates included).
    pub records: u64,
}

/// Whether `path` starts with the binary voxel list magic.
pub fn is_binary(path: &Path) -> bool {
    let mut magic = [0u8; 4];
    File::open(path)
        .and_then(|mut f| f.read_exact(&mut magic))
        .is_ok()
        && magic == BINARY_MAGIC
}

/// Smallest depth (at least 2) whose volume holds coordinate `max`.
fn depth_for(max: u32) -> u8 {
    let bits = 32 - max.leading_zeros();
    (bits as u8).max(MIN_DEPTH)
}

fn finish(mut codes: Vec<u64>, records: u64, depth: u8) -> VoxelList {
    use rayon::slice::ParallelSliceMut;
    codes.par_sort_unstable();
    codes.dedup();
    VoxelList {
        depth,
        codes,
        records,
    }
}

/// Reads a voxel list, binary or text. `depth` (from the command line) is the
/// volume's depth; for text lists without it the smallest depth holding every
/// voxel is used, for binary lists it must match the file's depth if given.
pub fn read(path: &Path, depth: Option<u8>) -> Result<VoxelList, ConvertError> {
    if is_binary(path) {
        read_binary(path, depth)
    } else {
        read_text(path, depth)
    }
}

/// Reads a voxel list held in memory, binary (by its magic) or text; `name`
/// names it in messages. Like [`read`], without touching the file system.
pub fn read_bytes(bytes: &[u8], name: &str, depth: Option<u8>) -> Result<VoxelList, ConvertError> {
    if bytes.starts_with(&BINARY_MAGIC) {
        read_binary_from(bytes, bytes.len() as u64, name, depth)
    } else {
        read_text_from(bytes, name, depth)
    }
}

/// Reads a text voxel list.
pub fn read_text(path: &Path, depth: Option<u8>) -> Result<VoxelList, ConvertError> {
    let file = File::open(path)
        .map_err(|e| ConvertError::io(format!("cannot open {}", path.display()), e))?;
    let reader = BufReader::with_capacity(1 << 20, file);
    read_text_from(reader, &path.display().to_string(), depth)
}

/// Reads a text voxel list from `reader`; `name` names it in messages.
///
/// Memory: one line at a time plus 8 bytes per voxel line (each at least 6
/// bytes long), so at most a small multiple of the input.
pub fn read_text_from(
    mut reader: impl BufRead,
    name: &str,
    depth: Option<u8>,
) -> Result<VoxelList, ConvertError> {
    let limit: u64 = 1u64 << depth.unwrap_or(MAX_DEPTH);
    let mut codes = Vec::new();
    let mut max = 0u32;
    let mut line = String::new();
    let mut number = 0u64;
    loop {
        line.clear();
        let n = reader
            .read_line(&mut line)
            .map_err(|e| ConvertError::io(format!("cannot read {name}"), e))?;
        if n == 0 {
            break;
        }
        number += 1;
        let content = line.split('#').next().unwrap_or("");
        let mut fields = content.split_ascii_whitespace();
        let Some(first) = fields.next() else { continue };
        let mut c = [0u32; 3];
        let parse = |s: Option<&str>| -> Result<u32, ConvertError> {
            let s = s.ok_or_else(|| {
                ConvertError::Input(format!(
                    "{name}:{number}: expected three coordinates `x y z`"
                ))
            })?;
            let v: u64 = s.parse().map_err(|_| {
                ConvertError::Input(format!(
                    "{name}:{number}: `{s}` is not a non-negative integer"
                ))
            })?;
            if v >= limit {
                return Err(ConvertError::Input(format!(
                    "{name}:{number}: coordinate {v} is outside the volume (must be below {limit})"
                )));
            }
            Ok(v as u32)
        };
        c[0] = parse(Some(first))?;
        c[1] = parse(fields.next())?;
        c[2] = parse(fields.next())?;
        if let Some(extra) = fields.next() {
            return Err(ConvertError::Input(format!(
                "{name}:{number}: unexpected `{extra}` after three coordinates"
            )));
        }
        max = max.max(c[0]).max(c[1]).max(c[2]);
        codes.push(dagfmt::morton::encode(c[0], c[1], c[2]));
    }
    // An empty list is an empty volume (spec/VDAG.md § 7), not an error: a
    // tile of a larger scene is often empty.
    let records = codes.len() as u64;
    Ok(finish(
        codes,
        records,
        depth.unwrap_or_else(|| depth_for(max)),
    ))
}

/// Reads a binary voxel list.
pub fn read_binary(path: &Path, depth: Option<u8>) -> Result<VoxelList, ConvertError> {
    let file = File::open(path)
        .map_err(|e| ConvertError::io(format!("cannot open {}", path.display()), e))?;
    let len = file
        .metadata()
        .map_err(|e| ConvertError::io(format!("cannot stat {}", path.display()), e))?
        .len();
    let reader = BufReader::with_capacity(1 << 20, file);
    read_binary_from(reader, len, &path.display().to_string(), depth)
}

/// Reads a binary voxel list of `len` bytes from `reader`; `name` names it in
/// messages.
///
/// The count in the header is checked against `len` before anything is
/// allocated from it, so memory is 8 bytes per 12-byte record.
pub fn read_binary_from(
    mut reader: impl Read,
    len: u64,
    name: &str,
    depth: Option<u8>,
) -> Result<VoxelList, ConvertError> {
    let mut header = [0u8; BINARY_HEADER_SIZE];
    reader.read_exact(&mut header).map_err(|_| {
        ConvertError::Input(format!(
            "{name}: shorter than the {BINARY_HEADER_SIZE}-byte voxel list header"
        ))
    })?;
    let u32_at = |i: usize| u32::from_le_bytes(header[i..i + 4].try_into().expect("4 bytes"));
    let version = u32_at(4);
    if header[..4] != BINARY_MAGIC || version != BINARY_VERSION {
        return Err(ConvertError::Input(format!(
            "{name}: not a version-{BINARY_VERSION} binary voxel list (magic VVOX)"
        )));
    }
    let file_depth = u32_at(8);
    if !(u32::from(MIN_DEPTH)..=u32::from(MAX_DEPTH)).contains(&file_depth) {
        return Err(ConvertError::Input(format!(
            "{name}: depth {file_depth} is outside {MIN_DEPTH}..={MAX_DEPTH}"
        )));
    }
    let file_depth = file_depth as u8;
    if let Some(d) = depth
        && d != file_depth
    {
        return Err(ConvertError::Usage(format!(
            "{name} is a depth-{file_depth} voxel list but --depth {d} was given"
        )));
    }
    let count = u64::from_le_bytes(header[12..20].try_into().expect("8 bytes"));
    let expected = count
        .checked_mul(12)
        .and_then(|b| b.checked_add(BINARY_HEADER_SIZE as u64));
    if expected != Some(len) {
        return Err(ConvertError::Input(format!(
            "{name}: header declares {count} voxels but the file has {len} bytes (expected 20 + 12 x count)"
        )));
    }
    let limit = 1u64 << file_depth;
    let mut codes = Vec::with_capacity(usize::try_from(count).unwrap_or(0));
    let mut record = [0u8; 12 * 4096];
    let mut left = count;
    let mut index = 0u64;
    while left > 0 {
        let n = left.min(4096) as usize;
        reader
            .read_exact(&mut record[..12 * n])
            .map_err(|e| ConvertError::io(format!("cannot read {name}"), e))?;
        for r in record[..12 * n].chunks_exact(12) {
            let c = [0, 4, 8].map(|i| u32::from_le_bytes(r[i..i + 4].try_into().expect("4 bytes")));
            if c.iter().any(|&v| u64::from(v) >= limit) {
                return Err(ConvertError::Input(format!(
                    "{name}: voxel {index} {c:?} is outside the {limit}^3 volume"
                )));
            }
            codes.push(dagfmt::morton::encode(c[0], c[1], c[2]));
            index += 1;
        }
        left -= n as u64;
    }
    Ok(finish(codes, count, file_depth))
}

/// Writes a binary voxel list.
pub fn write_binary(w: &mut impl Write, depth: u8, voxels: &[[u32; 3]]) -> std::io::Result<()> {
    w.write_all(&BINARY_MAGIC)?;
    w.write_all(&BINARY_VERSION.to_le_bytes())?;
    w.write_all(&u32::from(depth).to_le_bytes())?;
    w.write_all(&(voxels.len() as u64).to_le_bytes())?;
    for v in voxels {
        for c in v {
            w.write_all(&c.to_le_bytes())?;
        }
    }
    Ok(())
}
