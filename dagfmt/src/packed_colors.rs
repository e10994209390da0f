//! Packed voxel colours: the PACKED_COLORS section (kind 4, spec §12.6).
//!
//! The colours of a file, in dense voxel-index order, cut into blocks of 64
//! consecutive colours. Each block is coded on its own, as whichever of two
//! forms is smaller:
//!
//! - a *palette*: the block's distinct (quantized) colours, then one index per
//!   colour, or one index for a run of 8 (a "uniform" sub-block);
//! - *direct*: one entry per colour.
//!
//! An entry is a per-channel offset from the block's base colour, in the
//! block's per-channel bit widths, counted in steps of `2E + 1` where `E` is the
//! section's error bound (0: lossless): a decoded channel is
//! `min(255, base + q·(2E + 1) + E)`, which is within `E` of the source. A
//! directory of 32 bytes per 16 blocks finds a block in O(1), so one colour
//! decodes from a fixed number of reads: the directory entry, the block header,
//! at most one index and one entry.
//!
//! [`PackedColorEncoder`] writes a section in one pass with bounded memory
//! (blocks are handed out as they fill; only the directory, 1/32 of a byte per
//! colour, stays until the end). [`PackedColors`] reads one: [`PackedColors::get`]
//! for random access, [`PackedColors::iter`] decodes block by block.
//! [`check_section`] checks every rule of the section (E080 – E087).

// Channels index parallel arrays (base, widths, quantized values) together.
#![allow(clippy::needless_range_loop)]

use crate::error::ErrorCode;

/// Colours per block (2^[`BLOCK_SHIFT`]).
pub const BLOCK_COLORS: usize = 64;
/// log2 of [`BLOCK_COLORS`], stored in the trailer.
pub const BLOCK_SHIFT: u8 = 6;
/// Blocks per directory entry.
pub const GROUP_BLOCKS: u64 = 16;
/// Bytes per directory entry.
pub const DIRECTORY_ENTRY_SIZE: u64 = 32;
/// Bytes of the trailer that ends the section.
pub const TRAILER_SIZE: u64 = 16;
/// The largest error bound: `2E + 1` must fit a byte.
pub const MAX_ERROR_BOUND: u8 = 127;
/// The largest channel width in bits.
const MAX_WIDTH: u8 = 8;
/// Bits of a block offset inside its directory entry's group.
const OFFSET_BITS: u32 = 13;
/// Bits of the group's base offset.
const BASE_BITS: u32 = 40;

/// Blocks needed for `count` colours.
pub fn block_count(count: u64) -> u64 {
    count.div_ceil(BLOCK_COLORS as u64)
}

/// Bytes of the directory for `count` colours.
pub fn directory_len(count: u64) -> u64 {
    block_count(count)
        .div_ceil(GROUP_BLOCKS)
        .saturating_mul(DIRECTORY_ENTRY_SIZE)
}

/// The smallest section for `count` colours: the directory and the trailer.
pub fn min_section_len(count: u64) -> u64 {
    directory_len(count).saturating_add(TRAILER_SIZE)
}

/// The trailer of a section: what its colours were coded with and how far they
/// are from the source.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Trailer {
    /// The error bound `E` (0 = lossless): every channel is within `E` of the source.
    pub error_bound: u8,
    /// The largest per-channel error the writer measured (≤ `error_bound`).
    pub max_error: u8,
    /// Σ over colours and the four channels of (decoded − source)², as measured
    /// by the writer.
    pub squared_error: u64,
}

impl Trailer {
    /// Encodes the 16 bytes.
    pub fn to_bytes(&self) -> [u8; 16] {
        let mut b = [0u8; 16];
        b[0] = self.error_bound;
        b[1] = BLOCK_SHIFT;
        b[2] = self.max_error;
        b[8..16].copy_from_slice(&self.squared_error.to_le_bytes());
        b
    }

    /// The peak signal-to-noise ratio in dB over `count` colours' R, G, B and
    /// A, from the measured squared error (infinite when lossless).
    pub fn psnr(&self, count: u64) -> f64 {
        if self.squared_error == 0 || count == 0 {
            return f64::INFINITY;
        }
        let mse = self.squared_error as f64 / (count as f64 * 4.0);
        10.0 * (255.0f64 * 255.0 / mse).log10()
    }
}

/// A rule broken inside the section: code, byte offset from the section's
/// start, message.
pub type SectionError = (ErrorCode, u64, String);

fn err(code: ErrorCode, at: u64, msg: impl Into<String>) -> SectionError {
    (code, at, msg.into())
}

/// Checks what a reader checks when opening (the length, the trailer) and
/// reads the trailer.
pub fn open_trailer(section: &[u8], count: u64) -> Result<Trailer, SectionError> {
    let len = section.len() as u64;
    let min = min_section_len(count);
    if len < min {
        return Err(err(
            ErrorCode::BadPackedColorSection,
            0,
            format!(
                "packed colour section of {len} bytes is shorter than the {min} bytes of the directory and trailer for {count} colours"
            ),
        ));
    }
    let t = &section[section.len() - TRAILER_SIZE as usize..];
    let at = len - TRAILER_SIZE;
    let trailer = Trailer {
        error_bound: t[0],
        max_error: t[2],
        squared_error: u64::from_le_bytes(t[8..16].try_into().expect("8 bytes")),
    };
    if t[1] != BLOCK_SHIFT {
        return Err(err(
            ErrorCode::BadColorTrailer,
            at + 1,
            format!("block shift {} (must be {BLOCK_SHIFT})", t[1]),
        ));
    }
    if trailer.error_bound > MAX_ERROR_BOUND {
        return Err(err(
            ErrorCode::BadColorTrailer,
            at,
            format!(
                "error bound {} exceeds {MAX_ERROR_BOUND}",
                trailer.error_bound
            ),
        ));
    }
    if trailer.max_error > trailer.error_bound {
        return Err(err(
            ErrorCode::BadColorTrailer,
            at + 2,
            format!(
                "measured error {} exceeds the bound {}",
                trailer.max_error, trailer.error_bound
            ),
        ));
    }
    if let Some(i) = t[3..8].iter().position(|&b| b != 0) {
        return Err(err(
            ErrorCode::BadColorTrailer,
            at + 3 + i as u64,
            "reserved trailer byte is not zero",
        ));
    }
    let bound = u64::from(trailer.max_error)
        .pow(2)
        .saturating_mul(count.saturating_mul(4));
    if trailer.squared_error > bound {
        return Err(err(
            ErrorCode::BadColorTrailer,
            at + 8,
            format!(
                "squared error {} exceeds what {count} colours within {} can have ({bound})",
                trailer.squared_error, trailer.max_error
            ),
        ));
    }
    Ok(trailer)
}

/// A zero-copy view of a PACKED_COLORS section. Never panics and never reads
/// out of bounds, whatever the bytes; on a section the validator rejects, the
/// colours it returns are unspecified.
#[derive(Clone, Copy, Debug)]
pub struct PackedColors<'a> {
    section: &'a [u8],
    directory: usize,
    count: u64,
    trailer: Trailer,
}

/// A block's decoded header: where its parts start and how to read them.
#[derive(Clone, Copy, Debug, Default)]
struct BlockHeader {
    /// Palette size (1 ..= 64), or 0 for a direct block.
    palette: u32,
    alpha: bool,
    widths: [u32; 4],
    base: [u32; 4],
    mask: u32,
    /// Byte offset (in the section) where the bit stream starts.
    bits: usize,
    /// Bytes of the header before the bit stream.
    header_len: usize,
}

impl BlockHeader {
    fn entry_bits(&self) -> u32 {
        self.widths.iter().sum()
    }

    fn index_width(&self) -> u32 {
        index_width(self.palette)
    }
}

fn index_width(palette: u32) -> u32 {
    if palette <= 1 {
        0
    } else {
        32 - (palette - 1).leading_zeros()
    }
}

/// Reads `n` ≤ 32 bits LSB first from bit `pos` of `bytes[start..]`; missing
/// bytes read as zero.
fn read_bits(bytes: &[u8], start: usize, pos: u64, n: u32) -> u32 {
    if n == 0 {
        return 0;
    }
    let byte = start as u64 + pos / 8;
    let shift = (pos % 8) as u32;
    // Fast path: eight bytes in range, one unaligned load.
    if let Some(b) = usize::try_from(byte)
        .ok()
        .and_then(|i| bytes.get(i..i.checked_add(8)?))
    {
        let word = u64::from_le_bytes(b.try_into().expect("8 bytes"));
        return ((word >> shift) & ((1u64 << n) - 1)) as u32;
    }
    let mut word = 0u64;
    for k in 0..5u64 {
        let b = usize::try_from(byte + k)
            .ok()
            .and_then(|i| bytes.get(i))
            .copied()
            .unwrap_or(0);
        word |= u64::from(b) << (8 * k);
    }
    ((word >> shift) & ((1u64 << n) - 1)) as u32
}

fn byte(bytes: &[u8], at: usize) -> u32 {
    bytes.get(at).copied().map_or(0, u32::from)
}

/// The position of colour `local` of a block among its indices (palette blocks).
fn index_slot(mask: u32, local: u32) -> u32 {
    let sub = local >> 3;
    let before = mask & ((1u32 << sub) - 1);
    let uniform = before.count_ones();
    let slot = uniform + (sub - uniform) * 8;
    if mask >> sub & 1 == 1 {
        slot
    } else {
        slot + (local & 7)
    }
}

impl<'a> PackedColors<'a> {
    /// A view of `section` holding `count` colours; checks the length and the
    /// trailer (E080, E081).
    pub fn new(section: &'a [u8], count: u64) -> Result<Self, SectionError> {
        let trailer = open_trailer(section, count)?;
        let directory = section.len() - (min_section_len(count) as usize);
        Ok(PackedColors {
            section,
            directory,
            count,
            trailer,
        })
    }

    /// The colours held.
    pub fn len(&self) -> u64 {
        self.count
    }

    /// Whether there are no colours.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// The trailer: error bound and measured error.
    pub fn trailer(&self) -> Trailer {
        self.trailer
    }

    /// The section's bytes.
    pub fn bytes(&self) -> &'a [u8] {
        self.section
    }

    /// The byte range of block `b` in the section, from the directory (not
    /// checked: the end may precede the start on a malformed section).
    fn block_range(&self, b: u64) -> (u64, u64) {
        let start = self.block_start(b);
        let end = if b + 1 < block_count(self.count) {
            self.block_start(b + 1)
        } else {
            self.directory as u64
        };
        (start, end)
    }

    fn block_start(&self, b: u64) -> u64 {
        let entry = self.directory as u64 + (b / GROUP_BLOCKS) * DIRECTORY_ENTRY_SIZE;
        let entry = entry as usize;
        let base = u64::from(read_bits(self.section, entry, 0, 32))
            | u64::from(read_bits(self.section, entry, 32, 8)) << 32;
        let j = b % GROUP_BLOCKS;
        if j == 0 {
            base
        } else {
            base + u64::from(read_bits(
                self.section,
                entry,
                u64::from(BASE_BITS) + u64::from(OFFSET_BITS) * (j - 1),
                OFFSET_BITS,
            ))
        }
    }

    fn header(&self, b: u64) -> BlockHeader {
        let start = usize::try_from(self.block_start(b)).unwrap_or(usize::MAX);
        decode_header(self.section, start)
    }

    /// Colours in block `b`.
    fn block_len(&self, b: u64) -> u32 {
        (self.count - b * BLOCK_COLORS as u64).min(BLOCK_COLORS as u64) as u32
    }

    /// Decodes colour `local` of a block.
    fn decode(&self, h: &BlockHeader, local: u32) -> [u8; 4] {
        let eb = h.entry_bits();
        let entry = match h.palette {
            0 => local,
            1 => 0,
            k => {
                let w = h.index_width();
                let pos = u64::from(k) * u64::from(eb)
                    + u64::from(index_slot(h.mask, local)) * u64::from(w);
                read_bits(self.section, h.bits, pos, w)
            }
        };
        let mut pos = u64::from(entry) * u64::from(eb);
        let e = u32::from(self.trailer.error_bound);
        let step = 2 * e + 1;
        let mut out = [255u8; 4];
        let channels = if h.alpha { 4 } else { 3 };
        for c in 0..channels {
            let q = read_bits(self.section, h.bits, pos, h.widths[c]);
            pos += u64::from(h.widths[c]);
            let v = u64::from(h.base[c]) + u64::from(q) * u64::from(step) + u64::from(e);
            out[c] = v.min(255) as u8;
        }
        out
    }

    /// The colour of the voxel with dense index `index`, or `None` past the end.
    pub fn get(&self, index: u64) -> Option<[u8; 4]> {
        if index >= self.count {
            return None;
        }
        let b = index / BLOCK_COLORS as u64;
        let h = self.header(b);
        Some(self.decode(&h, (index % BLOCK_COLORS as u64) as u32))
    }

    /// Decodes block `b` into `out` (its colours, up to 64); returns how many.
    pub fn decode_block(&self, b: u64, out: &mut [[u8; 4]; BLOCK_COLORS]) -> usize {
        if b >= block_count(self.count) {
            return 0;
        }
        let h = self.header(b);
        let n = self.block_len(b);
        for (local, slot) in out.iter_mut().enumerate().take(n as usize) {
            *slot = self.decode(&h, local as u32);
        }
        n as usize
    }

    /// All colours in order, decoded block by block.
    pub fn iter(&self) -> PackedColorsIter<'a> {
        PackedColorsIter {
            colors: *self,
            block: 0,
            buf: [[0; 4]; BLOCK_COLORS],
            at: 0,
            len: 0,
        }
    }
}

/// Sequential decoding of a [`PackedColors`]; see [`PackedColors::iter`].
#[derive(Clone, Debug)]
pub struct PackedColorsIter<'a> {
    colors: PackedColors<'a>,
    block: u64,
    buf: [[u8; 4]; BLOCK_COLORS],
    at: usize,
    len: usize,
}

impl Iterator for PackedColorsIter<'_> {
    type Item = [u8; 4];

    fn next(&mut self) -> Option<[u8; 4]> {
        if self.at == self.len {
            self.len = self.colors.decode_block(self.block, &mut self.buf);
            self.block += 1;
            self.at = 0;
            if self.len == 0 {
                return None;
            }
        }
        let c = self.buf[self.at];
        self.at += 1;
        Some(c)
    }
}

/// Decodes a block header at `start` (missing bytes read as zero).
fn decode_header(s: &[u8], start: usize) -> BlockHeader {
    let h0 = byte(s, start);
    let direct = h0 & 0x80 != 0;
    let alpha = h0 & 0x40 != 0;
    let k = (h0 & 0x3f) + 1;
    let mut at = start.saturating_add(1);
    let mut widths = [0u32; 4];
    if direct || k > 1 {
        let w0 = byte(s, at);
        let w1 = byte(s, at.saturating_add(1));
        widths = [w0 & 15, w0 >> 4, w1 & 15, w1 >> 4];
        if !alpha {
            widths[3] = 0;
        }
        for w in &mut widths {
            *w = (*w).min(u32::from(MAX_WIDTH));
        }
        at = at.saturating_add(2);
    }
    let mut base = [0u32; 4];
    let channels = if alpha { 4 } else { 3 };
    for (c, slot) in base.iter_mut().enumerate().take(channels) {
        *slot = byte(s, at.saturating_add(c));
    }
    at = at.saturating_add(channels);
    let mut mask = 0;
    if !direct && k > 1 {
        mask = byte(s, at);
        at = at.saturating_add(1);
    }
    BlockHeader {
        palette: if direct { 0 } else { k },
        alpha,
        widths,
        base,
        mask,
        bits: at,
        header_len: at.saturating_sub(start),
    }
}

/// Checks every rule of a section of `count` colours (the open checks too);
/// returns every violation found (offsets from the section's start).
pub fn check_section(section: &[u8], count: u64) -> Vec<SectionError> {
    let colors = match PackedColors::new(section, count) {
        Ok(c) => c,
        Err(e) => return vec![e],
    };
    let mut errors = Vec::new();
    let blocks = block_count(count);
    let dir = colors.directory as u64;
    // The directory: contiguous, increasing, unused bits zero.
    let groups = blocks.div_ceil(GROUP_BLOCKS);
    let mut expected = 0u64;
    let mut dir_ok = true;
    for g in 0..groups {
        let entry = dir + g * DIRECTORY_ENTRY_SIZE;
        let e = entry as usize;
        let in_group = (blocks - g * GROUP_BLOCKS).min(GROUP_BLOCKS);
        let base = colors.block_start(g * GROUP_BLOCKS);
        if base != expected {
            errors.push(err(
                ErrorCode::BadColorDirectory,
                entry,
                format!("block {} starts at {base}, must start at {expected} (the end of the block before)", g * GROUP_BLOCKS),
            ));
            dir_ok = false;
            break;
        }
        let used = BASE_BITS + OFFSET_BITS * (in_group as u32 - 1);
        let mut unused_nonzero = false;
        let mut pos = u64::from(used);
        while pos < 256 {
            let n = (256 - pos).min(8) as u32;
            if read_bits(section, e, pos, n) != 0 {
                unused_nonzero = true;
            }
            pos += u64::from(n);
        }
        if unused_nonzero {
            errors.push(err(
                ErrorCode::BadColorDirectory,
                entry + u64::from(used / 8),
                format!("unused bits of directory entry {g} are not zero"),
            ));
        }
        for j in 0..in_group {
            let b = g * GROUP_BLOCKS + j;
            let (start, end) = colors.block_range(b);
            if end <= start || end > dir {
                errors.push(err(
                    ErrorCode::BadColorDirectory,
                    entry,
                    format!(
                        "block {b} spans bytes {start} .. {end}, not a non-empty range before the directory at {dir}"
                    ),
                ));
                dir_ok = false;
                break;
            }
            expected = end;
        }
        if !dir_ok {
            break;
        }
    }
    if !dir_ok {
        return errors;
    }
    if blocks == 0 && dir != 0 {
        errors.push(err(
            ErrorCode::BadColorDirectory,
            0,
            format!("{dir} bytes of blocks for no colours"),
        ));
    } else if blocks > 0 && expected != dir {
        errors.push(err(
            ErrorCode::BadColorDirectory,
            dir,
            format!("the last block ends at {expected}, not at the directory ({dir})"),
        ));
    }
    for b in 0..blocks {
        let (start, end) = colors.block_range(b);
        check_block(&colors, b, start as usize, end as usize, &mut errors);
    }
    errors
}

fn check_block(
    colors: &PackedColors<'_>,
    b: u64,
    start: usize,
    end: usize,
    errors: &mut Vec<SectionError>,
) {
    let s = colors.section;
    let at = start as u64;
    let n = colors.block_len(b);
    let h0 = byte(s, start);
    let direct = h0 & 0x80 != 0;
    let alpha = h0 & 0x40 != 0;
    let k = (h0 & 0x3f) + 1;
    let h = decode_header(s, start);
    if direct && k != 1 {
        errors.push(err(
            ErrorCode::BadColorBlock,
            at,
            format!("direct block {b} has palette size {k} (must be stored as 0)"),
        ));
        return;
    }
    if !direct && k > n {
        errors.push(err(
            ErrorCode::BadColorBlock,
            at,
            format!("block {b} has a palette of {k} for {n} colours"),
        ));
        return;
    }
    if direct || k > 1 {
        let w0 = byte(s, start + 1);
        let w1 = byte(s, start + 2);
        let raw = [w0 & 15, w0 >> 4, w1 & 15, w1 >> 4];
        if let Some(c) = raw.iter().position(|&w| w > u32::from(MAX_WIDTH)) {
            errors.push(err(
                ErrorCode::BadColorBlock,
                at + 1 + (c / 2) as u64,
                format!("block {b}: channel {c} width {} exceeds 8", raw[c]),
            ));
            return;
        }
        if !alpha && raw[3] != 0 {
            errors.push(err(
                ErrorCode::BadColorBlock,
                at + 2,
                format!("block {b}: alpha width {} without alpha", raw[3]),
            ));
            return;
        }
    }
    let subs = n.div_ceil(8);
    if !direct && k > 1 && h.mask >> subs != 0 {
        errors.push(err(
            ErrorCode::BadColorBlock,
            (h.bits - 1) as u64,
            format!(
                "block {b}: uniform mask {:#04x} names sub-blocks past its {subs}",
                h.mask
            ),
        ));
        return;
    }
    let eb = u64::from(h.entry_bits());
    let entries = if direct { u64::from(n) } else { u64::from(k) };
    let index_slots = if direct || k == 1 {
        0
    } else {
        // The last colour's slot is the last slot.
        u64::from(index_slot(h.mask, n - 1)) + 1
    };
    let bits = entries * eb + index_slots * u64::from(h.index_width());
    let len = h.header_len as u64 + bits.div_ceil(8);
    if len != (end - start) as u64 {
        errors.push(err(
            ErrorCode::ColorBlockLength,
            at,
            format!(
                "block {b} holds {} bytes by its header, {} by the directory",
                len,
                end - start
            ),
        ));
        return;
    }
    if bits % 8 != 0 {
        let last = byte(s, end - 1);
        if last >> (bits % 8) != 0 {
            errors.push(err(
                ErrorCode::ColorBlockPadding,
                (end - 1) as u64,
                format!("block {b}: padding bits are not zero"),
            ));
        }
    }
    let step = 2 * u32::from(colors.trailer.error_bound) + 1;
    let channels = if alpha { 4 } else { 3 };
    for e in 0..entries {
        let mut pos = e * eb;
        for c in 0..channels {
            let q = read_bits(s, h.bits, pos, h.widths[c]);
            if h.base[c] + q * step > 255 {
                errors.push(err(
                    ErrorCode::ColorValueOutOfRange,
                    (h.bits as u64) + pos / 8,
                    format!(
                        "block {b}, entry {e}: channel {c} starts its interval at {} (> 255)",
                        h.base[c] + q * step
                    ),
                ));
                return;
            }
            pos += u64::from(h.widths[c]);
        }
    }
    if !direct && k > 1 {
        let w = h.index_width();
        for slot in 0..index_slots {
            let pos = u64::from(k) * eb + slot * u64::from(w);
            let i = read_bits(s, h.bits, pos, w);
            if i >= k {
                errors.push(err(
                    ErrorCode::ColorIndexOutOfRange,
                    (h.bits as u64) + pos / 8,
                    format!("block {b}: palette index {i} ≥ palette size {k}"),
                ));
                return;
            }
        }
    }
}

/// What a finished encoder measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PackedSummary {
    /// Colours encoded.
    pub count: u64,
    /// Bytes of the whole section.
    pub length: u64,
    /// The trailer written.
    pub trailer: Trailer,
}

/// Writes a PACKED_COLORS section in one pass. Feed colours with
/// [`push`](Self::push), which appends the bytes of every completed block to
/// `out`; [`finish`](Self::finish) appends the last block, the directory and
/// the trailer. The section is the concatenation of everything appended.
#[derive(Clone, Debug)]
pub struct PackedColorEncoder {
    error_bound: u8,
    pending: Vec<[u8; 4]>,
    directory: Vec<u8>,
    group_base: u64,
    offset: u64,
    blocks: u64,
    count: u64,
    max_error: u8,
    squared_error: u64,
    scratch: Scratch,
}

#[derive(Clone, Debug, Default)]
struct Scratch {
    keys: Vec<u32>,
    palette: Vec<u32>,
    index: Vec<u32>,
    quant: Vec<u32>,
}

/// Bit writer, LSB first.
struct Bits<'v> {
    out: &'v mut Vec<u8>,
    acc: u64,
    n: u32,
}

impl Bits<'_> {
    fn put(&mut self, v: u32, n: u32) {
        if n == 0 {
            return;
        }
        self.acc |= u64::from(v) << self.n;
        self.n += n;
        while self.n >= 8 {
            self.out.push(self.acc as u8);
            self.acc >>= 8;
            self.n -= 8;
        }
    }

    fn flush(self) {
        if self.n > 0 {
            self.out.push(self.acc as u8);
        }
    }
}

fn bits_for(v: u32) -> u32 {
    32 - v.leading_zeros()
}

impl PackedColorEncoder {
    /// An encoder whose colours are within `error_bound` of the source per
    /// channel (0: lossless); `None` if the bound exceeds [`MAX_ERROR_BOUND`].
    pub fn new(error_bound: u8) -> Option<Self> {
        (error_bound <= MAX_ERROR_BOUND).then(|| PackedColorEncoder {
            error_bound,
            pending: Vec::with_capacity(BLOCK_COLORS),
            directory: Vec::new(),
            group_base: 0,
            offset: 0,
            blocks: 0,
            count: 0,
            max_error: 0,
            squared_error: 0,
            scratch: Scratch::default(),
        })
    }

    /// Colours pushed so far.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Appends colours; the bytes of every block they complete go to `out`.
    pub fn push(&mut self, colors: &[[u8; 4]], out: &mut Vec<u8>) {
        let mut rest = colors;
        while !rest.is_empty() {
            let take = (BLOCK_COLORS - self.pending.len()).min(rest.len());
            self.pending.extend_from_slice(&rest[..take]);
            rest = &rest[take..];
            if self.pending.len() == BLOCK_COLORS {
                self.flush_block(out);
            }
        }
    }

    /// Appends colours given as RGBA bytes (a multiple of 4).
    pub fn push_bytes(&mut self, rgba: &[u8], out: &mut Vec<u8>) {
        let (colors, _) = rgba.as_chunks::<4>();
        self.push(colors, out);
    }

    /// Ends the section: the last block, the directory and the trailer go to `out`.
    pub fn finish(mut self, out: &mut Vec<u8>) -> PackedSummary {
        if !self.pending.is_empty() {
            self.flush_block(out);
        }
        let trailer = Trailer {
            error_bound: self.error_bound,
            max_error: self.max_error,
            squared_error: self.squared_error,
        };
        out.extend_from_slice(&self.directory);
        out.extend_from_slice(&trailer.to_bytes());
        PackedSummary {
            count: self.count,
            length: self.offset + self.directory.len() as u64 + TRAILER_SIZE,
            trailer,
        }
    }

    fn record_block_start(&mut self) {
        let j = self.blocks % GROUP_BLOCKS;
        if j == 0 {
            self.group_base = self.offset;
            let mut entry = [0u8; 32];
            entry[..5].copy_from_slice(&self.offset.to_le_bytes()[..5]);
            self.directory.extend_from_slice(&entry);
        } else {
            let rel = self.offset - self.group_base;
            debug_assert!(rel < 1 << OFFSET_BITS);
            let base = self.directory.len() - 32;
            let pos = BASE_BITS + OFFSET_BITS * (j as u32 - 1);
            for bit in 0..OFFSET_BITS {
                if rel >> bit & 1 == 1 {
                    let p = (pos + bit) as usize;
                    self.directory[base + p / 8] |= 1 << (p % 8);
                }
            }
        }
    }

    fn flush_block(&mut self, out: &mut Vec<u8>) {
        self.record_block_start();
        let before = out.len();
        let block = std::mem::take(&mut self.pending);
        self.encode_block(&block, out);
        self.offset += (out.len() - before) as u64;
        self.blocks += 1;
        self.count += block.len() as u64;
        self.pending = block;
        self.pending.clear();
    }

    fn encode_block(&mut self, block: &[[u8; 4]], out: &mut Vec<u8>) {
        let e = u32::from(self.error_bound);
        let step = 2 * e + 1;
        let n = block.len();
        let alpha = block.iter().any(|c| c[3] != 255);
        let channels = if alpha { 4 } else { 3 };
        let mut base = [0u32; 4];
        for c in 0..channels {
            let lo = block.iter().map(|x| u32::from(x[c])).min().unwrap_or(0);
            base[c] = lo.saturating_sub(e);
        }
        // Quantized offsets, packed 8 bits a channel into a key.
        let s = &mut self.scratch;
        s.quant.clear();
        let mut maxq = [0u32; 4];
        for x in block {
            let mut key = 0u32;
            for c in 0..channels {
                let q = (u32::from(x[c]) - base[c]) / step;
                maxq[c] = maxq[c].max(q);
                key |= q << (8 * c);
            }
            s.quant.push(key);
        }
        // Measured error.
        for (x, &key) in block.iter().zip(&s.quant) {
            for c in 0..4 {
                let rec = if c < channels {
                    (base[c] + (key >> (8 * c) & 255) * step + e).min(255)
                } else {
                    255
                };
                let d = rec.abs_diff(u32::from(x[c]));
                self.max_error = self.max_error.max(d as u8);
                self.squared_error += u64::from(d * d);
            }
        }
        let mut widths = [0u32; 4];
        for c in 0..channels {
            widths[c] = bits_for(maxq[c]);
        }
        let eb: u32 = widths.iter().sum();
        // The palette: distinct keys in order of first appearance.
        s.keys.clear();
        s.keys.extend_from_slice(&s.quant);
        s.keys.sort_unstable();
        s.keys.dedup();
        let k = s.keys.len() as u32;
        s.palette.clear();
        s.index.clear();
        for &key in &s.quant {
            let i = s.keys.binary_search(&key).expect("key present") as u32;
            s.index.push(i);
        }
        let w = index_width(k);
        let subs = n.div_ceil(8);
        let mut mask = 0u32;
        let mut index_slots = 0u32;
        for sub in 0..subs {
            let part = &s.index[sub * 8..(sub * 8 + 8).min(n)];
            if part.iter().all(|&i| i == part[0]) {
                mask |= 1 << sub;
                index_slots += 1;
            } else {
                index_slots += part.len() as u32;
            }
        }
        let palette_bits = if k == 1 {
            0
        } else {
            8 + 16 + k * eb + index_slots * w
        };
        let direct_bits = 16 + n as u32 * eb;
        let direct = k > 1 && direct_bits < palette_bits;
        let mut h0 = if direct { 0x80 } else { k - 1 };
        if alpha {
            h0 |= 0x40;
        }
        out.push(h0 as u8);
        if direct || k > 1 {
            out.push((widths[0] | widths[1] << 4) as u8);
            out.push((widths[2] | widths[3] << 4) as u8);
        }
        for &b in base.iter().take(channels) {
            out.push(b as u8);
        }
        if k == 1 && !direct {
            return;
        }
        if !direct {
            out.push(mask as u8);
        }
        let mut bits = Bits { out, acc: 0, n: 0 };
        let entries: &[u32] = if direct { &s.quant } else { &s.keys };
        for &key in entries {
            for c in 0..channels {
                bits.put(key >> (8 * c) & 255, widths[c]);
            }
        }
        if !direct {
            for sub in 0..subs {
                let part = &s.index[sub * 8..(sub * 8 + 8).min(n)];
                if mask >> sub & 1 == 1 {
                    bits.put(part[0], w);
                } else {
                    for &i in part {
                        bits.put(i, w);
                    }
                }
            }
        }
        bits.flush();
    }
}

/// Encodes `colors` into a whole section.
pub fn encode(colors: &[[u8; 4]], error_bound: u8) -> Option<(Vec<u8>, PackedSummary)> {
    let mut enc = PackedColorEncoder::new(error_bound)?;
    let mut out = Vec::new();
    enc.push(colors, &mut out);
    let summary = enc.finish(&mut out);
    Some((out, summary))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn check_round_trip(colors: &[[u8; 4]], e: u8) {
        let (bytes, summary) = encode(colors, e).unwrap();
        assert_eq!(summary.length, bytes.len() as u64);
        assert_eq!(check_section(&bytes, colors.len() as u64), vec![]);
        let packed = PackedColors::new(&bytes, colors.len() as u64).unwrap();
        let seq: Vec<_> = packed.iter().collect();
        assert_eq!(seq.len(), colors.len());
        let mut max = 0;
        for (i, (src, dec)) in colors.iter().zip(&seq).enumerate() {
            assert_eq!(packed.get(i as u64), Some(*dec), "random access at {i}");
            for c in 0..4 {
                let d = src[c].abs_diff(dec[c]);
                assert!(
                    d <= e,
                    "colour {i} channel {c}: {src:?} -> {dec:?} (E = {e})"
                );
                max = max.max(d);
            }
        }
        assert_eq!(packed.get(colors.len() as u64), None);
        assert_eq!(summary.trailer.max_error, max);
    }

    #[test]
    fn empty_and_small() {
        check_round_trip(&[], 0);
        check_round_trip(&[[1, 2, 3, 255]], 0);
        check_round_trip(&[[1, 2, 3, 4]], 5);
        check_round_trip(&[[255, 255, 255, 0]; 65], 127);
    }

    fn colors_strategy() -> impl Strategy<Value = Vec<[u8; 4]>> {
        // Smooth runs (like textures) mixed with noise (like point clouds),
        // opaque or not.
        (
            prop::collection::vec((any::<[u8; 4]>(), 1usize..40, 0u8..=255), 0..80),
            any::<bool>(),
        )
            .prop_map(|(runs, opaque)| {
                let mut v = Vec::new();
                for (c, len, jitter) in runs {
                    for i in 0..len {
                        let mut x = c;
                        for (ch, val) in x.iter_mut().enumerate() {
                            let d = (i as u32 * 7 + ch as u32 * 13) % (u32::from(jitter) + 1);
                            *val = val.wrapping_add(d as u8);
                        }
                        if opaque {
                            x[3] = 255;
                        }
                        v.push(x);
                    }
                }
                v
            })
    }

    proptest! {
        #[test]
        fn every_colour_within_the_bound(colors in colors_strategy(), e in prop_oneof![Just(0u8), Just(8u8), 0u8..=127]) {
            check_round_trip(&colors, e);
        }

        #[test]
        fn random_colours_within_the_bound(colors in prop::collection::vec(any::<[u8; 4]>(), 0..300), e in 0u8..=127) {
            check_round_trip(&colors, e);
        }
    }

    #[test]
    fn malformed_sections_never_panic() {
        let colors: Vec<[u8; 4]> = (0..300u32)
            .map(|i| {
                [
                    (i * 3) as u8,
                    (i / 7) as u8,
                    9,
                    if i % 50 == 0 { 7 } else { 255 },
                ]
            })
            .collect();
        let (bytes, _) = encode(&colors, 3).unwrap();
        for i in 0..bytes.len() {
            for bit in 0..8 {
                let mut b = bytes.clone();
                b[i] ^= 1 << bit;
                let errors = check_section(&b, colors.len() as u64);
                if let Ok(p) = PackedColors::new(&b, colors.len() as u64) {
                    let seq: Vec<_> = p.iter().collect();
                    assert_eq!(seq.len(), colors.len());
                    for (i, c) in seq.iter().enumerate() {
                        assert_eq!(p.get(i as u64), Some(*c));
                    }
                }
                let _ = errors;
            }
        }
    }
}
