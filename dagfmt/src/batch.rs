//! The ray and hit batch formats (spec/VDAG.md § Ray and hit batches), text
//! and binary, in both directions.
//!
//! Text rays: a `vdag-rays 1` line, then one ray per line,
//! `ox oy oz dx dy dz tmin tmax [level]`. Text hits: a `vdag-hits 1` line,
//! then per ray `miss` or `hit T X Y Z LEVEL FACE INDEX` (`INDEX` is `-` when
//! there is none). `#` starts a comment; blank lines are ignored.
//!
//! Binary rays: `VRAY`, u32 version 1, u64 count, then 40-byte records
//! (`f32 origin[3]`, `f32 dir[3]`, f32 tmin, f32 tmax, u32 level or `0xFFFFFFFF`,
//! u32 flags = 0). Binary hits: `VHIT`, u32 version 1, u64 count, then
//! 32-byte records (u32 flags with bit 0 = hit, f32 t, u32 x, y, z, u8 level,
//! u8 face, u16 reserved = 0, u64 index or `u64::MAX`). Little-endian.
//!
//! Parsers never panic and never allocate from a count they have not checked
//! against the input's length; errors name the line (text) or byte offset
//! (binary).

use std::io::{self, BufRead as _, Read as _, Write};

use thiserror::Error;

use crate::layout::MAX_DEPTH;

/// First line of a text ray batch.
pub const RAYS_TEXT_HEADER: &str = "vdag-rays 1";
/// First line of a text hit batch.
pub const HITS_TEXT_HEADER: &str = "vdag-hits 1";
/// First four bytes of a binary ray batch.
pub const RAYS_MAGIC: [u8; 4] = *b"VRAY";
/// First four bytes of a binary hit batch.
pub const HITS_MAGIC: [u8; 4] = *b"VHIT";
/// Version of both binary formats.
pub const BATCH_VERSION: u32 = 1;
/// Bytes before the first binary record: magic, version, count.
pub const BINARY_HEADER_SIZE: usize = 16;
/// Bytes per binary ray record.
pub const RAY_RECORD_SIZE: usize = 40;
/// Bytes per binary hit record.
pub const HIT_RECORD_SIZE: usize = 32;
/// Binary ray level meaning "the file's full depth".
pub const LEVEL_FULL_DEPTH: u32 = u32::MAX;
/// Binary hit index meaning "no attribute index".
pub const NO_INDEX: u64 = u64::MAX;
/// Largest entry-face code (0 = started inside, 1..=6 = -X +X -Y +Y -Z +Z).
pub const MAX_FACE: u8 = 6;

/// A ray segment `origin + t * dir`, `t` in `[tmin, tmax]`, in world space.
///
/// `#[repr(C)]`: the fields lie in this order, so vector code may read a
/// ray's first 32 bytes as its origin, direction, `tmin` and `tmax` words.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub struct Ray {
    /// Origin.
    pub origin: [f32; 3],
    /// Direction (not necessarily normalised).
    pub dir: [f32; 3],
    /// Start of the segment.
    pub tmin: f32,
    /// End of the segment (may be infinite).
    pub tmax: f32,
    /// Tracing level 1..=D; `None` = the full depth D.
    pub level: Option<u8>,
}

impl Ray {
    /// A ray over `[0, inf]` at full depth.
    pub fn new(origin: [f32; 3], dir: [f32; 3]) -> Self {
        Ray {
            origin,
            dir,
            tmin: 0.0,
            tmax: f32::INFINITY,
            level: None,
        }
    }
}

/// The answer to one ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Whether an occupied cell was hit; the other fields are meaningless otherwise.
    pub hit: bool,
    /// Entry parameter of the ray into the cell.
    pub t: f32,
    /// Cell coordinates at `level`.
    pub voxel: [u32; 3],
    /// Tracing level 1..=D.
    pub level: u8,
    /// Entry face: 0 = started inside, 1..=6 = -X +X -Y +Y -Z +Z.
    pub face: u8,
    /// Dense index of the cell's first voxel (attribute kind 1), if any.
    pub index: Option<u64>,
}

impl Hit {
    /// A miss, as the parsers return it.
    pub const MISS: Hit = Hit {
        hit: false,
        t: 0.0,
        voxel: [0; 3],
        level: 0,
        face: 0,
        index: None,
    };
}

/// A malformed batch: where and what.
#[derive(Clone, Debug, Error, PartialEq, Eq)]
pub enum BatchError {
    /// In a text batch, at a 1-based line number.
    #[error("line {line}: {message}")]
    Text {
        /// 1-based line number.
        line: u64,
        /// What is wrong.
        message: String,
    },
    /// In a binary batch, at a byte offset.
    #[error("byte {offset}: {message}")]
    Binary {
        /// Byte offset of the offending field.
        offset: u64,
        /// What is wrong.
        message: String,
    },
}

fn text_error(line: u64, message: impl Into<String>) -> BatchError {
    BatchError::Text {
        line,
        message: message.into(),
    }
}

fn binary_error(offset: usize, message: impl Into<String>) -> BatchError {
    BatchError::Binary {
        offset: offset as u64,
        message: message.into(),
    }
}

/// Formats an f32 as the shortest string that parses back to the same value
/// (plain or scientific notation, whichever is shorter).
pub fn format_f32(v: f32) -> String {
    let plain = format!("{v}");
    let scientific = format!("{v:e}");
    if scientific.len() < plain.len() {
        scientific
    } else {
        plain
    }
}

// ---------------------------------------------------------------- text input

/// The content lines of a text batch: (1-based line number, fields), comments
/// and blank lines dropped.
struct TextLines<'a> {
    lines: NumberedLines<'a>,
}

/// Fields kept per text line: one more than any record has.
const MAX_FIELDS: usize = 10;

/// `n` fields kept of a line, for messages: the line may hold more when
/// [`MAX_FIELDS`] were kept.
fn field_count(n: usize) -> String {
    if n + 1 >= MAX_FIELDS {
        format!("{n} or more")
    } else {
        n.to_string()
    }
}

/// Lines of a byte slice split at `\n`, numbered from 0.
type NumberedLines<'a> = std::iter::Enumerate<std::slice::Split<'a, u8, fn(&u8) -> bool>>;

impl<'a> TextLines<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        let newline: fn(&u8) -> bool = |&b| b == b'\n';
        TextLines {
            lines: bytes.split(newline).enumerate(),
        }
    }
}

/// The fields of text line number `line` (its bytes without the `\n`):
/// `None` for a blank or comment-only line.
fn line_fields(line: u64, raw: &[u8]) -> Result<Option<Vec<&str>>, BatchError> {
    // § 21.1: a UTF-8 byte-order mark at the very start is ignored.
    let raw = if line == 1 {
        raw.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(raw)
    } else {
        raw
    };
    // A CR that ends the line belongs to its CR LF line end.
    let raw = raw.strip_suffix(b"\r").unwrap_or(raw);
    let text = std::str::from_utf8(raw).map_err(|_| text_error(line, "not UTF-8 text"))?;
    // Fields are separated by spaces and tabs only; any other control
    // character is an error, named, rather than a field that fails to
    // parse somewhere else (a file with CR-only line ends would
    // otherwise read as one long header line).
    if let Some(&byte) = raw.iter().find(|&&b| (b < 0x20 && b != b'\t') || b == 0x7f) {
        let message = if byte == b'\r' {
            "a CR that does not end a CR LF line end: lines must end with LF or CR LF, \
             not CR alone"
                .to_string()
        } else {
            format!(
                "control character {} is not allowed (fields are separated by spaces and tabs)",
                control_name(byte)
            )
        };
        return Err(text_error(line, message));
    }
    let content = text.split('#').next().unwrap_or("");
    // No record has more than 9 fields: keep at most 10 (enough to
    // say "too many"), so a line of a million fields costs no memory.
    let fields: Vec<&str> = content
        .split([' ', '\t'])
        .filter(|f| !f.is_empty())
        .take(MAX_FIELDS)
        .collect();
    Ok((!fields.is_empty()).then_some(fields))
}

/// Names a control character for messages.
fn control_name(byte: u8) -> String {
    const NAMES: [&str; 32] = [
        "NUL", "SOH", "STX", "ETX", "EOT", "ENQ", "ACK", "BEL", "BS", "HT", "LF", "VT", "FF", "CR",
        "SO", "SI", "DLE", "DC1", "DC2", "DC3", "DC4", "NAK", "SYN", "ETB", "CAN", "EM", "SUB",
        "ESC", "FS", "GS", "RS", "US",
    ];
    let name = NAMES.get(usize::from(byte)).copied().unwrap_or("DEL");
    format!("U+{byte:04X} ({name})")
}

impl<'a> Iterator for TextLines<'a> {
    type Item = Result<(u64, Vec<&'a str>), BatchError>;

    fn next(&mut self) -> Option<Self::Item> {
        for (index, raw) in self.lines.by_ref() {
            let line = index as u64 + 1;
            match line_fields(line, raw) {
                Err(e) => return Some(Err(e)),
                Ok(Some(fields)) => return Some(Ok((line, fields))),
                Ok(None) => {}
            }
        }
        None
    }
}

/// Checks the header line of a text batch.
fn text_header(lines: &mut TextLines<'_>, expected: &str, other: &str) -> Result<(), BatchError> {
    match lines.next() {
        None => Err(missing_header(expected)),
        Some(r) => {
            let (line, fields) = r?;
            header_fields(line, &fields, expected, other)
        }
    }
}

/// The error for a text batch with no content line.
fn missing_header(expected: &str) -> BatchError {
    text_error(
        1,
        format!("empty input: missing the `{expected}` header line"),
    )
}

/// Checks the fields of the first content line of a text batch.
fn header_fields(
    line: u64,
    fields: &[&str],
    expected: &str,
    other: &str,
) -> Result<(), BatchError> {
    let expected_tag = expected.split(' ').next().unwrap_or(expected);
    let other_tag = other.split(' ').next().unwrap_or(other);
    if fields[0] == other_tag {
        return Err(text_error(
            line,
            format!("this is a `{other_tag}` batch, expected `{expected_tag}`"),
        ));
    }
    if fields[0] != expected_tag {
        return Err(text_error(
            line,
            format!(
                "missing the `{expected}` header line (found `{}`)",
                fields[0]
            ),
        ));
    }
    if fields.len() != 2 || fields[1] != "1" {
        return Err(text_error(
            line,
            format!(
                "unsupported `{expected_tag}` version `{}` (this reader reads version 1)",
                fields[1..].join(" ")
            ),
        ));
    }
    Ok(())
}

fn parse_f32(line: u64, name: &str, field: &str) -> Result<f32, BatchError> {
    // Rust rounds the decimal straight to the nearest f32, as § 21.1 requires
    // (never through f64, which could round twice).
    field.parse::<f32>().map_err(|_| {
        let hint = if field.is_ascii() {
            ""
        } else {
            " (it holds non-ASCII characters: only ASCII spaces and tabs separate fields)"
        };
        text_error(line, format!("{name}: `{field}` is not a number{hint}"))
    })
}

/// An unsigned decimal integer: ASCII digits only (§ 21.1: no sign; leading
/// zeros are allowed).
fn parse_int<T: std::str::FromStr>(line: u64, name: &str, field: &str) -> Result<T, BatchError> {
    let digits = !field.is_empty() && field.bytes().all(|b| b.is_ascii_digit());
    let value = if digits {
        field.parse::<T>().ok()
    } else {
        None
    };
    value.ok_or_else(|| {
        let why = if field.starts_with(['+', '-']) {
            " (integers carry no sign)"
        } else {
            ""
        };
        text_error(
            line,
            format!("{name}: `{field}` is not a valid integer{why}"),
        )
    })
}

fn check_level(level: u32) -> Result<u8, String> {
    if (1..=u32::from(MAX_DEPTH)).contains(&level) {
        Ok(level as u8)
    } else {
        Err(format!("level {level} is outside 1..={MAX_DEPTH}"))
    }
}

/// The ray of the text line number `line` with these fields.
fn text_ray(line: u64, fields: &[&str]) -> Result<Ray, BatchError> {
    const NAMES: [&str; 8] = ["ox", "oy", "oz", "dx", "dy", "dz", "tmin", "tmax"];
    if fields.len() != 8 && fields.len() != 9 {
        return Err(text_error(
            line,
            format!(
                "a ray needs 8 or 9 fields (ox oy oz dx dy dz tmin tmax [level]), found {}",
                field_count(fields.len())
            ),
        ));
    }
    let mut values = [0f32; 8];
    for (i, value) in values.iter_mut().enumerate() {
        *value = parse_f32(line, NAMES[i], fields[i])?;
    }
    let level = match fields.get(8) {
        None => None,
        Some(f) => {
            Some(check_level(parse_int(line, "level", f)?).map_err(|m| text_error(line, m))?)
        }
    };
    Ok(Ray {
        origin: [values[0], values[1], values[2]],
        dir: [values[3], values[4], values[5]],
        tmin: values[6],
        tmax: values[7],
        level,
    })
}

fn parse_text_rays(bytes: &[u8]) -> Result<Vec<Ray>, BatchError> {
    let mut lines = TextLines::new(bytes);
    text_header(&mut lines, RAYS_TEXT_HEADER, HITS_TEXT_HEADER)?;
    let mut rays = Vec::new();
    for entry in lines {
        let (line, fields) = entry?;
        rays.push(text_ray(line, &fields)?);
    }
    Ok(rays)
}

fn parse_text_hits(bytes: &[u8]) -> Result<Vec<Hit>, BatchError> {
    let mut lines = TextLines::new(bytes);
    text_header(&mut lines, HITS_TEXT_HEADER, RAYS_TEXT_HEADER)?;
    let mut hits = Vec::new();
    for entry in lines {
        let (line, fields) = entry?;
        match fields[0] {
            "miss" if fields.len() == 1 => hits.push(Hit::MISS),
            "miss" => {
                return Err(text_error(
                    line,
                    format!(
                        "`miss` takes no fields, found {}",
                        field_count(fields.len() - 1)
                    ),
                ));
            }
            "hit" if fields.len() == 8 => {
                let t = parse_f32(line, "t", fields[1])?;
                let x = parse_int(line, "x", fields[2])?;
                let y = parse_int(line, "y", fields[3])?;
                let z = parse_int(line, "z", fields[4])?;
                let level = check_level(parse_int(line, "level", fields[5])?)
                    .map_err(|m| text_error(line, m))?;
                let face: u8 = parse_int(line, "face", fields[6])?;
                if face > MAX_FACE {
                    return Err(text_error(
                        line,
                        format!("face {face} is outside 0..={MAX_FACE}"),
                    ));
                }
                let index = match fields[7] {
                    "-" => None,
                    f => {
                        let i: u64 = parse_int(line, "index", f)?;
                        if i == NO_INDEX {
                            return Err(text_error(
                                line,
                                "index 18446744073709551615 is reserved (write `-` for none)",
                            ));
                        }
                        Some(i)
                    }
                };
                hits.push(Hit {
                    hit: true,
                    t,
                    voxel: [x, y, z],
                    level,
                    face,
                    index,
                });
            }
            "hit" => {
                return Err(text_error(
                    line,
                    format!(
                        "a hit needs 7 fields (T X Y Z LEVEL FACE INDEX), found {}",
                        field_count(fields.len() - 1)
                    ),
                ));
            }
            other => {
                return Err(text_error(
                    line,
                    format!("expected `hit` or `miss`, found `{other}`"),
                ));
            }
        }
    }
    Ok(hits)
}

// -------------------------------------------------------------- binary input

fn u32_at(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes"))
}

fn f32_at(bytes: &[u8], at: usize) -> f32 {
    f32::from_bits(u32_at(bytes, at))
}

fn u64_at(bytes: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(bytes[at..at + 8].try_into().expect("8 bytes"))
}

/// Checks a binary header and returns the record count, checked against the
/// bytes that follow.
fn binary_header(
    bytes: &[u8],
    magic: [u8; 4],
    record_size: usize,
    what: &str,
) -> Result<usize, BatchError> {
    let head = &bytes[..bytes.len().min(BINARY_HEADER_SIZE)];
    binary_header_of_length(head, bytes.len() as u64, magic, record_size, what)
        .map(|count| count as usize)
}

/// [`binary_header`] from the header's bytes (`head`, all of them when the
/// batch has that many) and the batch's length in bytes.
fn binary_header_of_length(
    head: &[u8],
    length: u64,
    magic: [u8; 4],
    record_size: usize,
    what: &str,
) -> Result<u64, BatchError> {
    let bytes = head;
    if length < BINARY_HEADER_SIZE as u64 || bytes.len() < BINARY_HEADER_SIZE {
        return Err(binary_error(
            bytes.len(),
            format!(
                "truncated header: {} bytes, a binary {what} batch starts with {BINARY_HEADER_SIZE}",
                bytes.len()
            ),
        ));
    }
    if bytes[..4] != magic {
        return Err(binary_error(
            0,
            format!("bad magic: not a binary {what} batch"),
        ));
    }
    let version = u32_at(bytes, 4);
    if version != BATCH_VERSION {
        return Err(binary_error(
            4,
            format!("unsupported version {version} (this reader reads version {BATCH_VERSION})"),
        ));
    }
    let count = u64_at(bytes, 8);
    let available = length - BINARY_HEADER_SIZE as u64;
    let needed = count.checked_mul(record_size as u64);
    match needed {
        // The records are in memory (or in a file the caller reads): the
        // count fits an address.
        Some(n) if n == available && usize::try_from(count).is_ok() => Ok(count),
        Some(n) if n < available => Err(binary_error(
            (BINARY_HEADER_SIZE as u64 + n) as usize,
            format!(
                "{} bytes follow the {count} declared {what} records",
                available - n
            ),
        )),
        _ => Err(binary_error(
            8,
            format!(
                "truncated: {count} {what} records need {} bytes but {available} follow the header",
                u128::from(count) * record_size as u128
            ),
        )),
    }
}

/// Binary ray record number `i` (40 bytes).
fn binary_ray(record: &[u8], i: usize) -> Result<Ray, BatchError> {
    let at = BINARY_HEADER_SIZE + i * RAY_RECORD_SIZE;
    let f = |k: usize| f32_at(record, 4 * k);
    let level = match u32_at(record, 32) {
        LEVEL_FULL_DEPTH => None,
        l => Some(check_level(l).map_err(|m| binary_error(at + 32, format!("ray {i}: {m}")))?),
    };
    let flags = u32_at(record, 36);
    if flags != 0 {
        return Err(binary_error(
            at + 36,
            format!("ray {i}: reserved flags {flags:#x} are not zero"),
        ));
    }
    Ok(Ray {
        origin: [f(0), f(1), f(2)],
        dir: [f(3), f(4), f(5)],
        tmin: f(6),
        tmax: f(7),
        level,
    })
}

fn parse_binary_rays(bytes: &[u8]) -> Result<Vec<Ray>, BatchError> {
    let count = binary_header(bytes, RAYS_MAGIC, RAY_RECORD_SIZE, "ray")?;
    let mut rays = Vec::with_capacity(count);
    for (i, record) in bytes[BINARY_HEADER_SIZE..]
        .chunks_exact(RAY_RECORD_SIZE)
        .enumerate()
    {
        rays.push(binary_ray(record, i)?);
    }
    Ok(rays)
}

fn parse_binary_hits(bytes: &[u8]) -> Result<Vec<Hit>, BatchError> {
    let count = binary_header(bytes, HITS_MAGIC, HIT_RECORD_SIZE, "hit")?;
    let mut hits = Vec::with_capacity(count);
    for (i, record) in bytes[BINARY_HEADER_SIZE..]
        .chunks_exact(HIT_RECORD_SIZE)
        .enumerate()
    {
        let at = BINARY_HEADER_SIZE + i * HIT_RECORD_SIZE;
        let flags = u32_at(record, 0);
        if flags & !1 != 0 {
            return Err(binary_error(
                at,
                format!("hit {i}: reserved flag bits {:#x} are set", flags & !1),
            ));
        }
        let index = u64_at(record, 24);
        if flags == 0 {
            if record[..24].iter().any(|&b| b != 0) || index != NO_INDEX {
                return Err(binary_error(
                    at,
                    format!("hit {i}: a miss record must be zero except an index of {NO_INDEX:#x}"),
                ));
            }
            hits.push(Hit::MISS);
            continue;
        }
        let level = check_level(u32::from(record[20]))
            .map_err(|m| binary_error(at + 20, format!("hit {i}: {m}")))?;
        let face = record[21];
        if face > MAX_FACE {
            return Err(binary_error(
                at + 21,
                format!("hit {i}: face {face} is outside 0..={MAX_FACE}"),
            ));
        }
        if record[22..24] != [0, 0] {
            return Err(binary_error(
                at + 22,
                format!("hit {i}: reserved bytes are not zero"),
            ));
        }
        hits.push(Hit {
            hit: true,
            t: f32_at(record, 4),
            voxel: [u32_at(record, 8), u32_at(record, 12), u32_at(record, 16)],
            level,
            face,
            index: (index != NO_INDEX).then_some(index),
        });
    }
    Ok(hits)
}

// -------------------------------------------------------------- public parse

/// Parses a ray batch, binary when it starts with `VRAY`, else text.
pub fn parse_rays(bytes: &[u8]) -> Result<Vec<Ray>, BatchError> {
    if bytes.starts_with(&RAYS_MAGIC) {
        parse_binary_rays(bytes)
    } else if bytes.starts_with(&HITS_MAGIC) {
        Err(binary_error(0, "this is a binary hit batch, expected rays"))
    } else {
        parse_text_rays(bytes)
    }
}

/// Parses a hit batch, binary when it starts with `VHIT`, else text.
pub fn parse_hits(bytes: &[u8]) -> Result<Vec<Hit>, BatchError> {
    if bytes.starts_with(&HITS_MAGIC) {
        parse_binary_hits(bytes)
    } else if bytes.starts_with(&RAYS_MAGIC) {
        Err(binary_error(0, "this is a binary ray batch, expected hits"))
    } else {
        parse_text_hits(bytes)
    }
}

// ----------------------------------------------------------- streamed input

/// A ray batch read a chunk of rays at a time, so that a batch of any size
/// is traced in bounded memory. Reads exactly what [`parse_rays`] reads,
/// with the same errors, in the same order (binary when the input starts
/// with `VRAY`, else text).
///
/// ```
/// use dagfmt::batch::RayReader;
/// let text = b"vdag-rays 1\n0 0 0 1 0 0 0 inf\n1 1 1 0 1 0 0 inf 3\n";
/// let mut reader = RayReader::new(&text[..], Some(text.len() as u64)).unwrap();
/// let mut rays = Vec::new();
/// reader.read_chunk(1, &mut rays).unwrap();
/// assert_eq!(rays.len(), 1);
/// reader.read_chunk(1, &mut rays).unwrap();
/// assert_eq!(rays[0].level, Some(3));
/// reader.read_chunk(1, &mut rays).unwrap();
/// assert!(rays.is_empty());
/// ```
#[derive(Debug)]
pub struct RayReader<R> {
    input: io::Chain<io::Cursor<Vec<u8>>, R>,
    form: StreamForm,
    /// One line or one chunk of records.
    buffer: Vec<u8>,
}

#[derive(Clone, Copy, Debug)]
enum StreamForm {
    /// Records `next..count` are still to be read.
    Binary {
        next: u64,
        count: u64,
        /// The batch's length in bytes, when the caller knew it.
        length: Option<u64>,
    },
    /// Lines up to `line` (1-based) have been read; `header` once the
    /// header line has been.
    Text { line: u64, header: bool },
}

fn read_error(e: &io::Error) -> BatchError {
    BatchError::Binary {
        offset: 0,
        message: format!("cannot read the batch: {e}"),
    }
}

impl<R: io::BufRead> RayReader<R> {
    /// Starts reading a ray batch. `length`, the batch's length in bytes when
    /// known (a file's), lets a binary batch's count be checked against it
    /// before any ray is read, as [`parse_rays`] checks it; without it, a
    /// count that does not match is found at the end.
    pub fn new(mut input: R, length: Option<u64>) -> Result<Self, BatchError> {
        let mut head = Vec::with_capacity(BINARY_HEADER_SIZE);
        (&mut input)
            .take(BINARY_HEADER_SIZE as u64)
            .read_to_end(&mut head)
            .map_err(|e| read_error(&e))?;
        let form = if head.starts_with(&RAYS_MAGIC) {
            let known = length.unwrap_or(head.len() as u64);
            let count = if length.is_some() || head.len() < BINARY_HEADER_SIZE {
                binary_header_of_length(&head, known, RAYS_MAGIC, RAY_RECORD_SIZE, "ray")?
            } else {
                // Checked against the records as they come.
                binary_header_of_length(
                    &head,
                    u64_at(&head, 8)
                        .checked_mul(RAY_RECORD_SIZE as u64)
                        .and_then(|n| n.checked_add(BINARY_HEADER_SIZE as u64))
                        // A count no input can hold: as if nothing followed.
                        .unwrap_or(BINARY_HEADER_SIZE as u64),
                    RAYS_MAGIC,
                    RAY_RECORD_SIZE,
                    "ray",
                )?
            };
            head.clear();
            StreamForm::Binary {
                next: 0,
                count,
                length,
            }
        } else if head.starts_with(&HITS_MAGIC) {
            return Err(binary_error(0, "this is a binary hit batch, expected rays"));
        } else {
            StreamForm::Text {
                line: 0,
                header: false,
            }
        };
        Ok(RayReader {
            input: io::Cursor::new(head).chain(input),
            form,
            buffer: Vec::new(),
        })
    }

    /// The number of rays of a binary batch (a text batch does not say).
    pub fn declared_count(&self) -> Option<u64> {
        match self.form {
            StreamForm::Binary { count, .. } => Some(count),
            StreamForm::Text { .. } => None,
        }
    }

    /// Replaces `rays` with the next at most `max` (at least 1) rays of the
    /// batch; leaves it empty at the end.
    pub fn read_chunk(&mut self, max: usize, rays: &mut Vec<Ray>) -> Result<(), BatchError> {
        rays.clear();
        let max = max.max(1);
        match &mut self.form {
            StreamForm::Binary {
                next,
                count,
                length,
            } => {
                let n = (*count - *next).min(max as u64) as usize;
                self.buffer.resize(n * RAY_RECORD_SIZE, 0);
                let read =
                    read_full(&mut self.input, &mut self.buffer).map_err(|e| read_error(&e))?;
                if read < self.buffer.len() {
                    // Only without a known length: the batch ends early.
                    let follow = *next * RAY_RECORD_SIZE as u64 + read as u64;
                    return Err(binary_error(
                        8,
                        format!(
                            "truncated: {count} ray records need {} bytes but {follow} follow the header",
                            u128::from(*count) * RAY_RECORD_SIZE as u128
                        ),
                    ));
                }
                for (k, record) in self.buffer.chunks_exact(RAY_RECORD_SIZE).enumerate() {
                    rays.push(binary_ray(record, (*next as usize) + k)?);
                }
                *next += n as u64;
                if *next == *count && length.is_none() {
                    let mut extra = 0u64;
                    let mut probe = [0u8; 4096];
                    loop {
                        match self.input.read(&mut probe) {
                            Ok(0) => break,
                            Ok(k) => extra += k as u64,
                            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                            Err(e) => return Err(read_error(&e)),
                        }
                    }
                    if extra > 0 {
                        let records = *count * RAY_RECORD_SIZE as u64;
                        return Err(binary_error(
                            (BINARY_HEADER_SIZE as u64 + records) as usize,
                            format!("{extra} bytes follow the {count} declared ray records"),
                        ));
                    }
                }
                Ok(())
            }
            StreamForm::Text { line, header } => {
                while rays.len() < max {
                    self.buffer.clear();
                    let read = self
                        .input
                        .read_until(b'\n', &mut self.buffer)
                        .map_err(|e| read_error(&e))?;
                    if read == 0 {
                        if !*header {
                            return Err(missing_header(RAYS_TEXT_HEADER));
                        }
                        break;
                    }
                    *line += 1;
                    let raw = self.buffer.strip_suffix(b"\n").unwrap_or(&self.buffer);
                    let Some(fields) = line_fields(*line, raw)? else {
                        continue;
                    };
                    if *header {
                        rays.push(text_ray(*line, &fields)?);
                    } else {
                        header_fields(*line, &fields, RAYS_TEXT_HEADER, HITS_TEXT_HEADER)?;
                        *header = true;
                    }
                }
                Ok(())
            }
        }
    }
}

/// Reads until `buffer` is full or the input ends; returns the bytes read.
fn read_full(input: &mut impl io::Read, buffer: &mut [u8]) -> io::Result<usize> {
    let mut done = 0;
    while done < buffer.len() {
        match input.read(&mut buffer[done..]) {
            Ok(0) => break,
            Ok(n) => done += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(done)
}

// ------------------------------------------------------------------- output

fn invalid(message: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidInput, message)
}

fn check_ray(i: usize, ray: &Ray) -> io::Result<()> {
    if let Some(level) = ray.level {
        check_level(u32::from(level)).map_err(|m| invalid(format!("ray {i}: {m}")))?;
    }
    Ok(())
}

fn check_hit(i: usize, hit: &Hit) -> io::Result<()> {
    if !hit.hit {
        return Ok(());
    }
    check_level(u32::from(hit.level)).map_err(|m| invalid(format!("hit {i}: {m}")))?;
    if hit.face > MAX_FACE {
        return Err(invalid(format!(
            "hit {i}: face {} is outside 0..={MAX_FACE}",
            hit.face
        )));
    }
    if hit.index == Some(NO_INDEX) {
        return Err(invalid(format!(
            "hit {i}: index {NO_INDEX} is reserved for none"
        )));
    }
    Ok(())
}

/// Writes rays as a text batch. Fails (`InvalidInput`) on a level outside 1..=21.
pub fn write_rays_text<W: Write>(w: &mut W, rays: &[Ray]) -> io::Result<()> {
    writeln!(w, "{RAYS_TEXT_HEADER}")?;
    for (i, ray) in rays.iter().enumerate() {
        check_ray(i, ray)?;
        let values = [
            ray.origin[0],
            ray.origin[1],
            ray.origin[2],
            ray.dir[0],
            ray.dir[1],
            ray.dir[2],
            ray.tmin,
            ray.tmax,
        ];
        let mut line = values.map(format_f32).join(" ");
        if let Some(level) = ray.level {
            line.push(' ');
            line.push_str(&level.to_string());
        }
        writeln!(w, "{line}")?;
    }
    Ok(())
}

/// Writes rays as a binary batch. Fails (`InvalidInput`) on a level outside 1..=21.
pub fn write_rays_binary<W: Write>(w: &mut W, rays: &[Ray]) -> io::Result<()> {
    w.write_all(&RAYS_MAGIC)?;
    w.write_all(&BATCH_VERSION.to_le_bytes())?;
    w.write_all(&(rays.len() as u64).to_le_bytes())?;
    let mut record = [0u8; RAY_RECORD_SIZE];
    for (i, ray) in rays.iter().enumerate() {
        check_ray(i, ray)?;
        let values = [
            ray.origin[0],
            ray.origin[1],
            ray.origin[2],
            ray.dir[0],
            ray.dir[1],
            ray.dir[2],
            ray.tmin,
            ray.tmax,
        ];
        for (k, v) in values.iter().enumerate() {
            record[4 * k..4 * k + 4].copy_from_slice(&v.to_bits().to_le_bytes());
        }
        let level = ray.level.map_or(LEVEL_FULL_DEPTH, u32::from);
        record[32..36].copy_from_slice(&level.to_le_bytes());
        record[36..40].copy_from_slice(&0u32.to_le_bytes());
        w.write_all(&record)?;
    }
    Ok(())
}

/// Writes hits as a text batch (a `Hit` with `hit == false` is written as
/// `miss`). Fails (`InvalidInput`) on a level outside 1..=21, a face over 6 or
/// an index of `u64::MAX`.
pub fn write_hits_text<W: Write>(w: &mut W, hits: &[Hit]) -> io::Result<()> {
    write_hits_text_header(w)?;
    write_hits_text_records(w, hits, 0)
}

/// The first line of a text hit batch, for writing one in parts:
/// [`write_hits_text`] is this, then [`write_hits_text_records`].
pub fn write_hits_text_header<W: Write>(w: &mut W) -> io::Result<()> {
    writeln!(w, "{HITS_TEXT_HEADER}")
}

/// The lines of `hits`, the first being hit number `first` of the batch
/// (for messages); see [`write_hits_text_header`].
pub fn write_hits_text_records<W: Write>(w: &mut W, hits: &[Hit], first: usize) -> io::Result<()> {
    for (i, hit) in (first..).zip(hits) {
        check_hit(i, hit)?;
        if !hit.hit {
            writeln!(w, "miss")?;
            continue;
        }
        let index = hit.index.map_or_else(|| "-".to_string(), |i| i.to_string());
        writeln!(
            w,
            "hit {} {} {} {} {} {} {index}",
            format_f32(hit.t),
            hit.voxel[0],
            hit.voxel[1],
            hit.voxel[2],
            hit.level,
            hit.face
        )?;
    }
    Ok(())
}

/// Writes hits as a binary batch (a `Hit` with `hit == false` is written as
/// the canonical miss record). Fails like [`write_hits_text`].
pub fn write_hits_binary<W: Write>(w: &mut W, hits: &[Hit]) -> io::Result<()> {
    write_hits_binary_header(w, hits.len() as u64)?;
    write_hits_binary_records(w, hits, 0)
}

/// The header of a binary hit batch of `count` records, for writing one in
/// parts: [`write_hits_binary`] is this, then [`write_hits_binary_records`].
/// The count is bytes 8..16 (little-endian), for a writer that learns it at
/// the end.
pub fn write_hits_binary_header<W: Write>(w: &mut W, count: u64) -> io::Result<()> {
    w.write_all(&HITS_MAGIC)?;
    w.write_all(&BATCH_VERSION.to_le_bytes())?;
    w.write_all(&count.to_le_bytes())
}

/// The records of `hits`, the first being hit number `first` of the batch
/// (for messages); see [`write_hits_binary_header`].
pub fn write_hits_binary_records<W: Write>(
    w: &mut W,
    hits: &[Hit],
    first: usize,
) -> io::Result<()> {
    for (i, hit) in (first..).zip(hits) {
        check_hit(i, hit)?;
        let mut record = [0u8; HIT_RECORD_SIZE];
        if hit.hit {
            record[0..4].copy_from_slice(&1u32.to_le_bytes());
            record[4..8].copy_from_slice(&hit.t.to_bits().to_le_bytes());
            for k in 0..3 {
                record[8 + 4 * k..12 + 4 * k].copy_from_slice(&hit.voxel[k].to_le_bytes());
            }
            record[20] = hit.level;
            record[21] = hit.face;
        }
        let index = if hit.hit {
            hit.index.unwrap_or(NO_INDEX)
        } else {
            NO_INDEX
        };
        record[24..32].copy_from_slice(&index.to_le_bytes());
        w.write_all(&record)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shortest_float_formatting_round_trips() {
        for v in [
            0.0f32,
            -0.0,
            1.0,
            0.1,
            1e30,
            -3.5e-20,
            f32::MAX,
            f32::MIN_POSITIVE,
            1e-45,
            f32::INFINITY,
            f32::NEG_INFINITY,
        ] {
            let s = format_f32(v);
            assert_eq!(
                s.parse::<f32>().unwrap().to_bits(),
                v.to_bits(),
                "{v} -> {s}"
            );
        }
        assert_eq!(format_f32(1e30), "1e30");
        assert_eq!(format_f32(0.5), "0.5");
        assert_eq!(format_f32(f32::INFINITY), "inf");
    }

    #[test]
    fn plain_form_wins_a_tie_with_the_exponent_form() {
        // § 21.2: `0.01` and `1e-2` are both four characters: the plain one.
        assert_eq!(format_f32(0.01), "0.01");
        assert_eq!(format_f32(0.001), "1e-3");
        assert_eq!(format_f32(0.0001), "1e-4");
        assert_eq!(format_f32(100.0), "100", "`100` and `1e2`: a tie");
        assert_eq!(format_f32(1000.0), "1e3");
    }

    #[test]
    fn decimals_round_once_to_f32() {
        // Just above the midpoint between 1 and the next f32: through f64 it
        // would round to the midpoint, then (ties to even) to 1.
        let text = b"vdag-rays 1\n0 0 0 0 0 0 1.0000000596046447753906250000001 inf\n";
        let rays = parse_rays(text).unwrap();
        assert_eq!(rays[0].tmin, 1.0f32.next_up());
        let via_f64 = "1.0000000596046447753906250000001".parse::<f64>().unwrap() as f32;
        assert_eq!(via_f64, 1.0, "the example does round twice through f64");
    }

    #[test]
    fn lexical_decisions_of_section_21_1() {
        let ok = |text: &[u8]| parse_rays(text).unwrap_or_else(|e| panic!("{e}"));
        let err = |text: &[u8]| parse_rays(text).unwrap_err().to_string();
        // A byte-order mark at the start, tabs, CR LF: fine.
        let rays = ok(b"\xEF\xBB\xBFvdag-rays 1\r\n0\t0 0 1 0 0 0 inf 003\r\n");
        assert_eq!(rays[0].level, Some(3), "leading zeros are allowed");
        // CR alone ends nothing: an error naming line 1, not a version.
        let e = err(b"vdag-rays 1\r1 -10 -3.5 0 1 0 0 inf\r");
        assert!(
            e.starts_with("line 1: a CR that does not end") && e.contains("CR alone"),
            "{e}"
        );
        // Other control characters, whatever they are, are named.
        for (byte, name) in [
            (0x0b, "VT"),
            (0x0c, "FF"),
            (0x1c, "FS"),
            (0x1f, "US"),
            (0x7f, "DEL"),
        ] {
            let mut text = b"vdag-rays 1\n0 0 0 1 0 0 0 inf\n0 0".to_vec();
            text.push(byte);
            text.extend_from_slice(b"0 1 0 0 0 inf\n");
            let e = err(&text);
            assert!(
                e.starts_with("line 3: control character") && e.contains(name),
                "{e}"
            );
        }
        // NBSP is not whitespace: the field does not parse, and the message says why.
        let e = err("vdag-rays 1\n0\u{a0}0 0 0 1 0 0 0 inf\n".as_bytes());
        assert!(e.contains("non-ASCII"), "{e}");
        // A sign on an integer field.
        for level in ["+3", "-3"] {
            let e = err(format!("vdag-rays 1\n0 0 0 1 0 0 0 inf {level}\n").as_bytes());
            assert!(e.contains("carry no sign"), "{e}");
        }
        let e = parse_hits(b"vdag-hits 1\nhit 1 +1 0 0 3 1 0\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("x: `+1`"), "{e}");
        // A BOM anywhere else is not whitespace.
        assert!(parse_rays("vdag-rays 1\n\u{feff}0 0 0 1 0 0 0 inf\n".as_bytes()).is_err());
    }

    #[test]
    fn text_comments_and_blank_lines() {
        let text = b"# rays\n\nvdag-rays 1 # header\n0 0 0 1 0 0 0 inf\r\n  # nothing\n1 2 3 0 0 -1 -inf inf 4\n";
        let rays = parse_rays(text).unwrap();
        assert_eq!(rays.len(), 2);
        assert_eq!(rays[0].tmax, f32::INFINITY);
        assert_eq!(rays[1].tmin, f32::NEG_INFINITY);
        assert_eq!(rays[1].level, Some(4));
    }
}
