//! Packed voxel colours: the PACKED_COLORS section (kind 4, spec §12.6).
//!
//! The colours of a file, in dense voxel-index order, cut into blocks of 64,
//! 128 or 256 consecutive colours (the trailer's block shift). Each block is
//! coded on its own, as whichever of two forms is smaller:
//!
//! - a *palette*: the block's distinct (quantized) colours, then per
//!   sub-block of 8 colours either one index ("uniform"), two indices and the
//!   position where the second starts ("split", format 1.2), or one index per
//!   colour;
//! - *direct*: one entry per colour.
//!
//! An entry is a per-channel offset from the block's base colour, in the
//! block's per-channel bit widths, counted in steps of `2E + 1` where `E` is the
//! section's error bound (0: lossless): a decoded channel is
//! `min(255, base + q·(2E + 1) + E)`, which is within `E` of the source. A
//! directory of 32 bytes per 16 blocks finds a block in O(1), so one colour
//! decodes from a fixed number of reads: the directory entry, the block header,
//! at most three index reads and one entry.
//!
//! [`PackedColorEncoder`] writes a section in one pass with bounded memory
//! (blocks are handed out as they fill; only the directory, at most 1/32 of a
//! byte per colour, stays until the end). It picks the block shift from the
//! first [`SHIFT_SAMPLE`] colours, and each block's base colour so that the
//! quantization grid puts the fewest intervals under the block's colours.
//! [`PackedColors`] reads a section: [`PackedColors::get`] for random access,
//! [`PackedColors::iter`] decodes block by block. [`check_section`] checks
//! every rule of the section (E080 – E088).

// Channels index parallel arrays (base, widths, quantized values) together.
#![allow(clippy::needless_range_loop)]

use crate::error::ErrorCode;

/// Colours per block in format 1.1's layout ([`BlockLayout::V1_1`]).
pub const BLOCK_COLORS: usize = 64;
/// The most colours a block holds (block shift 8).
pub const MAX_BLOCK_COLORS: usize = 256;
/// Blocks per directory entry.
pub const GROUP_BLOCKS: u64 = 16;
/// Bytes per directory entry.
pub const DIRECTORY_ENTRY_SIZE: u64 = 32;
/// Bytes of the trailer that ends the section.
pub const TRAILER_SIZE: u64 = 16;
/// The largest error bound: `2E + 1` must fit a byte.
pub const MAX_ERROR_BOUND: u8 = 127;
/// Colours the encoder reads before it chooses its block shift.
pub const SHIFT_SAMPLE: usize = 1 << 16;
/// The largest channel width in bits.
const MAX_WIDTH: u8 = 8;
/// The largest palette: its size less one fills 6 bits of the block header.
const MAX_PALETTE: u32 = 64;
/// Colours per sub-block.
const SUB_BLOCK: u32 = 8;
/// Bits of a split sub-block's position.
const SPLIT_POSITION_BITS: u32 = 3;
/// Bits of the group's base offset.
const BASE_BITS: u32 = 40;
/// Trailer flag bit: palette blocks carry split flags (format 1.2).
const FLAG_SPLIT: u8 = 1;

/// How a section's blocks are laid out: the trailer's block shift and flags.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct BlockLayout {
    /// log2 of the colours per block: 6, 7 or 8.
    pub shift: u8,
    /// Palette blocks carry split flags after the uniform mask (format 1.2).
    pub split: bool,
}

impl BlockLayout {
    /// Format 1.1's only layout: 64 colours a block, no split sub-blocks.
    pub const V1_1: BlockLayout = BlockLayout {
        shift: 6,
        split: false,
    };

    /// The layouts format 1.2 writers choose from: every block shift, with split
    /// sub-blocks.
    pub const CHOICES: [BlockLayout; 3] = [
        BlockLayout {
            shift: 6,
            split: true,
        },
        BlockLayout {
            shift: 7,
            split: true,
        },
        BlockLayout {
            shift: 8,
            split: true,
        },
    ];

    /// Whether the shift is one of 6, 7, 8.
    pub fn is_valid(self) -> bool {
        (6..=8).contains(&self.shift)
    }

    /// Whether a format 1.1 reader reads this layout (it needs format 1.2 otherwise).
    pub fn is_v1_1(self) -> bool {
        self == Self::V1_1
    }

    /// Colours per block.
    pub fn block_colors(self) -> u64 {
        1 << self.shift
    }

    /// Blocks needed for `count` colours.
    pub fn block_count(self, count: u64) -> u64 {
        count.div_ceil(self.block_colors())
    }

    /// Bytes of the directory for `count` colours.
    pub fn directory_len(self, count: u64) -> u64 {
        self.block_count(count)
            .div_ceil(GROUP_BLOCKS)
            .saturating_mul(DIRECTORY_ENTRY_SIZE)
    }

    /// The smallest section for `count` colours: the directory and the trailer.
    pub fn min_section_len(self, count: u64) -> u64 {
        self.directory_len(count).saturating_add(TRAILER_SIZE)
    }

    /// Bits of a block's offset from its group's first block: the largest
    /// block (a direct block of 32-bit entries and its header) fifteen times
    /// over must fit (O of spec §12.6: 13 for S = 6 and 7, 14 for S = 8).
    pub fn offset_bits(self) -> u32 {
        if self.shift >= 8 { 14 } else { 13 }
    }

    /// Bytes of a palette block's uniform mask.
    fn mask_bytes(self) -> usize {
        1 << (self.shift.clamp(6, 8) - 6)
    }

    fn flags(self) -> u8 {
        if self.split { FLAG_SPLIT } else { 0 }
    }
}

/// The smallest section for `count` colours in any layout (the directory of
/// the largest blocks and the trailer).
pub fn min_section_len(count: u64) -> u64 {
    BlockLayout {
        shift: 8,
        split: true,
    }
    .min_section_len(count)
}

/// The trailer of a section: its layout, what its colours were coded with and
/// how far they are from the source.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Trailer {
    /// The error bound `E` (0 = lossless): every channel is within `E` of the source.
    pub error_bound: u8,
    /// The block shift and flags.
    pub layout: BlockLayout,
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
        b[1] = self.layout.shift;
        b[2] = self.max_error;
        b[3] = self.layout.flags();
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

fn too_short(len: u64, min: u64, count: u64) -> SectionError {
    err(
        ErrorCode::BadPackedColorSection,
        0,
        format!(
            "packed colour section of {len} bytes is shorter than the {min} bytes of the directory and trailer for {count} colours"
        ),
    )
}

/// Checks what a reader checks when opening (the length, the trailer) and
/// reads the trailer.
pub fn open_trailer(section: &[u8], count: u64) -> Result<Trailer, SectionError> {
    let len = section.len() as u64;
    let min = min_section_len(count);
    if len < min {
        return Err(too_short(len, min, count));
    }
    let t = &section[section.len() - TRAILER_SIZE as usize..];
    let at = len - TRAILER_SIZE;
    let trailer = Trailer {
        error_bound: t[0],
        layout: BlockLayout {
            shift: t[1],
            split: t[3] & FLAG_SPLIT != 0,
        },
        max_error: t[2],
        squared_error: u64::from_le_bytes(t[8..16].try_into().expect("8 bytes")),
    };
    if !trailer.layout.is_valid() {
        return Err(err(
            ErrorCode::BadColorTrailer,
            at + 1,
            format!("block shift {} (must be 6, 7 or 8)", t[1]),
        ));
    }
    if t[3] & !FLAG_SPLIT != 0 {
        return Err(err(
            ErrorCode::BadColorTrailer,
            at + 3,
            format!("unknown trailer flags {:#04x}", t[3] & !FLAG_SPLIT),
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
    if let Some(i) = t[4..8].iter().position(|&b| b != 0) {
        return Err(err(
            ErrorCode::BadColorTrailer,
            at + 4 + i as u64,
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
    let min = trailer.layout.min_section_len(count);
    if len < min {
        return Err(too_short(len, min, count));
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
    /// Sub-blocks coded by one index.
    uniform: u32,
    /// One bit per sub-block not uniform, in order: set when it is coded by
    /// two indices and a position.
    split_flags: u32,
    /// Bits of the stream before the entries (the split flags).
    lead: u32,
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

    /// Bit position of the first entry in the stream.
    fn entries_at(&self) -> u64 {
        u64::from(self.lead)
    }

    /// Bit position, in the bit stream, of sub-block `t`'s indices (palette
    /// blocks of two entries or more), and how it is coded.
    fn sub_block(&self, t: u32) -> (u64, SubBlock) {
        let w = u64::from(self.index_width());
        let below = (1u64 << t) - 1;
        let uniform = u64::from((u64::from(self.uniform) & below).count_ones());
        // Sub-block t's flag is the one after those of the sub-blocks before
        // it that are not uniform.
        let rank = u64::from(t) - uniform;
        let split = u64::from((u64::from(self.split_flags) & ((1u64 << rank) - 1)).count_ones());
        let full = rank - split;
        let pos = self.entries_at()
            + u64::from(self.palette) * u64::from(self.entry_bits())
            + uniform * w
            + split * (2 * w + u64::from(SPLIT_POSITION_BITS))
            + full * u64::from(SUB_BLOCK) * w;
        let kind = if self.uniform >> t & 1 == 1 {
            SubBlock::Uniform
        } else if u64::from(self.split_flags) >> rank & 1 == 1 {
            SubBlock::Split
        } else {
            SubBlock::Full
        };
        (pos, kind)
    }
}

/// How a sub-block's palette indices are coded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum SubBlock {
    /// One index for every colour.
    Uniform,
    /// Index a, index b, and the position p (3 bits): colours before p are a.
    Split,
    /// One index per colour.
    Full,
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

/// Reads `n` ≤ 56 bits LSB first from bit `pos` of `bytes[start..]`; missing
/// bytes read as zero.
fn read_bits64(bytes: &[u8], start: usize, pos: u64, n: u32) -> u64 {
    debug_assert!(n <= 56);
    if n <= 32 {
        return u64::from(read_bits(bytes, start, pos, n));
    }
    u64::from(read_bits(bytes, start, pos, 32))
        | u64::from(read_bits(bytes, start, pos + 32, n - 32)) << 32
}

/// Whether each of `count` indices of `w` bits (1 ≤ w ≤ 7) at bit `pos` of the
/// stream at `start` is below `k` (1 ≤ k < 2^w). Several indices a read:
/// the even and the odd ones are spread into slots of 2w bits, and
/// `index + 2^w − k` carries into bit w of its slot exactly when index ≥ k.
fn indices_below(bytes: &[u8], start: usize, mut pos: u64, count: u64, w: u32, k: u32) -> bool {
    debug_assert!((1..=7).contains(&w) && k >= 1 && k < 1 << w);
    let per = u64::from(56 / w);
    let (mut slots, mut add, mut high) = (0u64, 0u64, 0u64);
    let mut at = 0;
    while at + 2 * w <= 64 {
        slots |= ((1u64 << w) - 1) << at;
        add |= u64::from((1u32 << w) - k) << at;
        high |= 1u64 << (at + w);
        at += 2 * w;
    }
    let mut left = count;
    while left > 0 {
        let n = left.min(per);
        let word = read_bits64(bytes, start, pos, n as u32 * w);
        let even = word & slots;
        let odd = (word >> w) & slots;
        if ((even + add) | (odd + add)) & high != 0 {
            return false;
        }
        pos += n * u64::from(w);
        left -= n;
    }
    true
}

fn byte(bytes: &[u8], at: usize) -> u32 {
    bytes.get(at).copied().map_or(0, u32::from)
}

/// Reads a little-endian mask of `n` ≤ 4 bytes at `at` (missing bytes read as zero).
fn mask(bytes: &[u8], at: usize, n: usize) -> u32 {
    (0..n).fold(0, |m, i| m | byte(bytes, at.saturating_add(i)) << (8 * i))
}

impl<'a> PackedColors<'a> {
    /// A view of `section` holding `count` colours; checks the length and the
    /// trailer (E080, E081).
    pub fn new(section: &'a [u8], count: u64) -> Result<Self, SectionError> {
        let trailer = open_trailer(section, count)?;
        let directory = section.len() - (trailer.layout.min_section_len(count) as usize);
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

    /// The trailer: layout, error bound and measured error.
    pub fn trailer(&self) -> Trailer {
        self.trailer
    }

    /// The section's bytes.
    pub fn bytes(&self) -> &'a [u8] {
        self.section
    }

    /// Byte offset of the directory in the section.
    pub fn directory_offset(&self) -> usize {
        self.directory
    }

    fn layout(&self) -> BlockLayout {
        self.trailer.layout
    }

    /// Blocks in the section.
    pub fn block_count(&self) -> u64 {
        self.layout().block_count(self.count)
    }

    /// The byte range of block `b` in the section, from the directory (not
    /// checked: the end may precede the start on a malformed section).
    fn block_range(&self, b: u64) -> (u64, u64) {
        let start = self.block_start(b);
        let end = if b + 1 < self.block_count() {
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
            let bits = self.layout().offset_bits();
            base + u64::from(read_bits(
                self.section,
                entry,
                u64::from(BASE_BITS) + u64::from(bits) * (j - 1),
                bits,
            ))
        }
    }

    fn header(&self, b: u64) -> BlockHeader {
        let start = usize::try_from(self.block_start(b)).unwrap_or(usize::MAX);
        decode_header(self.section, start, self.layout(), self.block_len(b))
    }

    /// Colours in block `b`.
    fn block_len(&self, b: u64) -> u32 {
        let size = self.layout().block_colors();
        (self.count - b * size).min(size) as u32
    }

    /// Decodes colour `local` of a block.
    fn decode(&self, h: &BlockHeader, local: u32) -> [u8; 4] {
        let eb = h.entry_bits();
        let entry = match h.palette {
            0 => local,
            1 => 0,
            _ => {
                let w = h.index_width();
                let (pos, kind) = h.sub_block(local / SUB_BLOCK);
                let at = local % SUB_BLOCK;
                let slot = match kind {
                    SubBlock::Uniform => 0,
                    SubBlock::Split => {
                        let p = read_bits(
                            self.section,
                            h.bits,
                            pos + 2 * u64::from(w),
                            SPLIT_POSITION_BITS,
                        );
                        u32::from(at >= p)
                    }
                    SubBlock::Full => at,
                };
                read_bits(
                    self.section,
                    h.bits,
                    pos + u64::from(slot) * u64::from(w),
                    w,
                )
            }
        };
        let mut pos = h.entries_at() + u64::from(entry) * u64::from(eb);
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
        let shift = self.layout().shift;
        let h = self.header(index >> shift);
        Some(self.decode(&h, (index & ((1 << shift) - 1)) as u32))
    }

    /// Random access that remembers the last block it read: lookups in the
    /// block of the lookup before skip the directory and the block header.
    /// Neighbouring pixels of a render mostly fall in one block.
    pub fn cursor(&self) -> PackedColorsCursor<'a> {
        PackedColorsCursor {
            colors: *self,
            block: u64::MAX,
            header: BlockHeader::default(),
        }
    }

    /// Decodes block `b` into `out` (its colours, up to 256); returns how many.
    pub fn decode_block(&self, b: u64, out: &mut [[u8; 4]; MAX_BLOCK_COLORS]) -> usize {
        if b >= self.block_count() {
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
            buf: Box::new([[0; 4]; MAX_BLOCK_COLORS]),
            at: 0,
            len: 0,
        }
    }
}

/// Random access with the last block's header kept; see [`PackedColors::cursor`].
#[derive(Clone, Debug)]
pub struct PackedColorsCursor<'a> {
    colors: PackedColors<'a>,
    /// The block whose header is kept (`u64::MAX`: none yet).
    block: u64,
    header: BlockHeader,
}

impl PackedColorsCursor<'_> {
    /// The colour of the voxel with dense index `index`, or `None` past the
    /// end; the same as [`PackedColors::get`].
    pub fn get(&mut self, index: u64) -> Option<[u8; 4]> {
        if index >= self.colors.count {
            return None;
        }
        let shift = self.colors.layout().shift;
        let b = index >> shift;
        if b != self.block {
            self.header = self.colors.header(b);
            self.block = b;
        }
        Some(
            self.colors
                .decode(&self.header, (index & ((1 << shift) - 1)) as u32),
        )
    }
}

/// Sequential decoding of a [`PackedColors`]; see [`PackedColors::iter`].
#[derive(Clone, Debug)]
pub struct PackedColorsIter<'a> {
    colors: PackedColors<'a>,
    block: u64,
    buf: Box<[[u8; 4]; MAX_BLOCK_COLORS]>,
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

/// The sub-blocks (8 colours, the last perhaps fewer) of a block of `n` colours.
fn sub_blocks(n: u32) -> u32 {
    n.div_ceil(SUB_BLOCK)
}

/// The split flags of a palette block of `n` colours with this uniform mask:
/// one for each sub-block that is not uniform.
fn split_flag_count(n: u32, uniform: u32) -> u32 {
    let subs = sub_blocks(n);
    let valid = if subs >= 32 {
        u32::MAX
    } else {
        (1 << subs) - 1
    };
    subs - (uniform & valid).count_ones()
}

/// Decodes the header of a block of `n` colours at `start` (missing bytes
/// read as zero).
fn decode_header(s: &[u8], start: usize, layout: BlockLayout, n: u32) -> BlockHeader {
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
    let (mut uniform, mut split_flags, mut lead) = (0, 0, 0);
    if !direct && k > 1 {
        let bytes = layout.mask_bytes();
        uniform = mask(s, at, bytes);
        at = at.saturating_add(bytes);
        if layout.split {
            // The flags open the bit stream.
            lead = split_flag_count(n, uniform);
            split_flags = read_bits(s, at, 0, lead);
        }
    }
    BlockHeader {
        palette: if direct { 0 } else { k },
        alpha,
        widths,
        base,
        uniform,
        split_flags,
        lead,
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
    let blocks = colors.block_count();
    let offset_bits = colors.layout().offset_bits();
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
        let used = BASE_BITS + offset_bits * (in_group as u32 - 1);
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
    errors.extend(check_blocks(&colors, blocks));
    errors
}

/// Blocks from which [`check_section`] checks them on several threads.
const PARALLEL_BLOCKS: u64 = 1 << 14;

/// The violations of every block, in block order: on every core for many
/// blocks (a block is checked on its own, from its directory entry), since a
/// tool that validates before it renders waits for this.
fn check_blocks(colors: &PackedColors<'_>, blocks: u64) -> Vec<SectionError> {
    let check = |range: std::ops::Range<u64>| {
        let mut errors = Vec::new();
        for b in range {
            let (start, end) = colors.block_range(b);
            check_block(colors, b, start as usize, end as usize, &mut errors);
        }
        errors
    };
    let threads = std::thread::available_parallelism()
        .map_or(1, |n| n.get() as u64)
        .min(blocks / PARALLEL_BLOCKS.max(1));
    if threads < 2 {
        return check(0..blocks);
    }
    let per = blocks.div_ceil(threads);
    std::thread::scope(|scope| {
        let workers: Vec<_> = (1..threads)
            .map(|t| {
                let range = t * per..((t + 1) * per).min(blocks);
                scope.spawn(move || check(range))
            })
            .collect();
        let mut errors = check(0..per.min(blocks));
        for worker in workers {
            errors.extend(
                worker
                    .join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic)),
            );
        }
        errors
    })
}

fn check_block(
    colors: &PackedColors<'_>,
    b: u64,
    start: usize,
    end: usize,
    errors: &mut Vec<SectionError>,
) {
    let s = colors.section;
    let layout = colors.layout();
    let at = start as u64;
    let n = colors.block_len(b);
    let h0 = byte(s, start);
    let direct = h0 & 0x80 != 0;
    let alpha = h0 & 0x40 != 0;
    let k = (h0 & 0x3f) + 1;
    let h = decode_header(s, start, layout, n);
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
    let subs = sub_blocks(n);
    let palette_masks = !direct && k > 1;
    if palette_masks {
        let uniform_at = h.bits - layout.mask_bytes();
        if subs < 32 && h.uniform >> subs != 0 {
            errors.push(err(
                ErrorCode::BadColorBlock,
                uniform_at as u64,
                format!(
                    "block {b}: uniform mask {:#x} names sub-blocks past its {subs}",
                    h.uniform
                ),
            ));
            return;
        }
    }
    let eb = u64::from(h.entry_bits());
    let entries = if direct { u64::from(n) } else { u64::from(k) };
    let w = u64::from(h.index_width());
    let bits = if direct || k == 1 {
        entries * eb
    } else {
        // The last sub-block's indices end the stream.
        let last = subs - 1;
        let (pos, kind) = h.sub_block(last);
        pos + match kind {
            SubBlock::Uniform => w,
            SubBlock::Split => 2 * w + u64::from(SPLIT_POSITION_BITS),
            SubBlock::Full => u64::from(n - last * SUB_BLOCK) * w,
        }
    };
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
        let mut pos = h.entries_at() + e * eb;
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
    if palette_masks {
        // Sub-blocks in order, their codes' position kept as we go. With a
        // palette of a power of two every index of w bits is < k.
        let check_indices = !k.is_power_of_two();
        if !check_indices && h.split_flags == 0 {
            // Nothing in the codes can be wrong: every index is in range and
            // no sub-block is split (a split's position is the only other field).
            return;
        }
        let mut pos = h.entries_at() + u64::from(k) * eb;
        if check_indices && h.split_flags == 0 {
            // No split: the codes are one run of indices (one per uniform
            // sub-block, one per colour of the others). Checked a word at a
            // time; the loop below finds the culprit only when one is out of
            // range.
            let mut count = 0u64;
            for t in 0..subs {
                count += if h.uniform >> t & 1 == 1 {
                    1
                } else {
                    u64::from((n - t * SUB_BLOCK).min(SUB_BLOCK))
                };
            }
            if indices_below(s, h.bits, pos, count, w as u32, k) {
                return;
            }
        }
        let mut rank = 0;
        for t in 0..subs {
            let len = (n - t * SUB_BLOCK).min(SUB_BLOCK);
            let kind = if h.uniform >> t & 1 == 1 {
                SubBlock::Uniform
            } else {
                rank += 1;
                if h.split_flags >> (rank - 1) & 1 == 1 {
                    SubBlock::Split
                } else {
                    SubBlock::Full
                }
            };
            let (indices, size) = match kind {
                SubBlock::Uniform => (1, w),
                SubBlock::Split => (2, 2 * w + u64::from(SPLIT_POSITION_BITS)),
                SubBlock::Full => (len, u64::from(len) * w),
            };
            if kind == SubBlock::Split {
                let p_at = pos + 2 * w;
                let p = read_bits(s, h.bits, p_at, SPLIT_POSITION_BITS);
                if p == 0 || p >= len {
                    errors.push(err(
                        ErrorCode::BadSplitSubBlock,
                        (h.bits as u64) + p_at / 8,
                        format!(
                            "block {b}, sub-block {t}: split at {p}, not inside its {len} colours"
                        ),
                    ));
                    return;
                }
            }
            if check_indices {
                // The sub-block's indices (at most 8 of 6 bits) in one read.
                let word = read_bits64(s, h.bits, pos, (u64::from(indices) * w) as u32);
                let mask = (1u64 << w) - 1;
                if let Some(slot) =
                    (0..u64::from(indices)).find(|j| word >> (j * w) & mask >= u64::from(k))
                {
                    let i_at = pos + slot * w;
                    let i = read_bits(s, h.bits, i_at, w as u32);
                    errors.push(err(
                        ErrorCode::ColorIndexOutOfRange,
                        (h.bits as u64) + i_at / 8,
                        format!("block {b}: palette index {i} ≥ palette size {k}"),
                    ));
                    return;
                }
            }
            pos += size;
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
    /// The layout; `None` until the first [`SHIFT_SAMPLE`] colours chose it.
    layout: Option<BlockLayout>,
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
    index: Vec<u32>,
    quant: Vec<u32>,
    kinds: Vec<SubBlock>,
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

/// The base of one channel of a block: of the bases `lo − j` (j = 0 ..= 2E,
/// not below 0) that keep every value at or above the base, the one whose
/// grid of intervals `[base + q·s, base + q·s + 2E]` covers the block's
/// values with the fewest intervals, then the smallest largest `q`, then the
/// `j` nearest `E` (the grid centred on the values, which keeps the mean error
/// low). Fewer distinct quantized values make smaller palettes.
fn best_base(distinct: &[u8], e: u32) -> u32 {
    let lo = u32::from(distinct[0]);
    if e == 0 {
        return lo;
    }
    let step = 2 * e + 1;
    let mut best = (u32::MAX, u32::MAX, u32::MAX, lo);
    for j in 0..=(2 * e).min(lo) {
        let base = lo - j;
        let mut intervals = 0;
        let mut last = u32::MAX;
        for &v in distinct {
            let q = (u32::from(v) - base) / step;
            if q != last {
                intervals += 1;
                last = q;
            }
        }
        let key = (intervals, last, j.abs_diff(e), base);
        if key < best {
            best = key;
        }
    }
    best.3
}

impl PackedColorEncoder {
    /// An encoder whose colours are within `error_bound` of the source per
    /// channel (0: lossless), choosing its layout from the first
    /// [`SHIFT_SAMPLE`] colours; `None` if the bound exceeds [`MAX_ERROR_BOUND`].
    pub fn new(error_bound: u8) -> Option<Self> {
        Self::build(error_bound, None)
    }

    /// An encoder that writes `layout` (format 1.1's [`BlockLayout::V1_1`] for
    /// readers of 1.1); `None` if the bound exceeds [`MAX_ERROR_BOUND`] or the
    /// layout is not valid.
    pub fn with_layout(error_bound: u8, layout: BlockLayout) -> Option<Self> {
        if !layout.is_valid() {
            return None;
        }
        Self::build(error_bound, Some(layout))
    }

    fn build(error_bound: u8, layout: Option<BlockLayout>) -> Option<Self> {
        (error_bound <= MAX_ERROR_BOUND).then(|| PackedColorEncoder {
            error_bound,
            layout,
            pending: Vec::with_capacity(MAX_BLOCK_COLORS),
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
        self.count + self.pending.len() as u64
    }

    /// Appends colours; the bytes of every block they complete go to `out`.
    pub fn push(&mut self, colors: &[[u8; 4]], out: &mut Vec<u8>) {
        let mut rest = colors;
        if self.layout.is_none() {
            let take = (SHIFT_SAMPLE - self.pending.len()).min(rest.len());
            self.pending.extend_from_slice(&rest[..take]);
            rest = &rest[take..];
            if self.pending.len() < SHIFT_SAMPLE {
                return;
            }
            self.choose_layout(out);
        }
        let size = self.block_size();
        while !rest.is_empty() {
            let take = (size - self.pending.len()).min(rest.len());
            self.pending.extend_from_slice(&rest[..take]);
            rest = &rest[take..];
            if self.pending.len() == size {
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
        if self.layout.is_none() {
            self.choose_layout(out);
        }
        if !self.pending.is_empty() {
            self.flush_block(out);
        }
        let trailer = Trailer {
            error_bound: self.error_bound,
            layout: self.layout.expect("chosen"),
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

    fn block_size(&self) -> usize {
        1 << self.layout.expect("chosen").shift
    }

    /// Picks the layout that codes the sample (the colours pending, the first
    /// [`SHIFT_SAMPLE`] at most) in the fewest bytes, directory included (the
    /// smaller shift on ties), then encodes the complete blocks of the sample.
    fn choose_layout(&mut self, out: &mut Vec<u8>) {
        let sample = std::mem::take(&mut self.pending);
        let mut best: Option<(u64, BlockLayout)> = None;
        for layout in BlockLayout::CHOICES {
            let mut trial = Self::build(self.error_bound, Some(layout)).expect("valid bound");
            let mut bytes = Vec::new();
            trial.push(&sample, &mut bytes);
            let summary = trial.finish(&mut bytes);
            if best.is_none_or(|(len, _)| summary.length < len) {
                best = Some((summary.length, layout));
            }
        }
        self.layout = best.map(|(_, layout)| layout);
        self.pending = Vec::with_capacity(MAX_BLOCK_COLORS);
        self.push(&sample, out);
    }

    fn record_block_start(&mut self) {
        let j = self.blocks % GROUP_BLOCKS;
        if j == 0 {
            self.group_base = self.offset;
            let mut entry = [0u8; 32];
            entry[..5].copy_from_slice(&self.offset.to_le_bytes()[..5]);
            self.directory.extend_from_slice(&entry);
        } else {
            let offset_bits = self.layout.expect("chosen").offset_bits();
            let rel = self.offset - self.group_base;
            debug_assert!(rel < 1 << offset_bits);
            let base = self.directory.len() - 32;
            let pos = BASE_BITS + offset_bits * (j as u32 - 1);
            for bit in 0..offset_bits {
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
        let layout = self.layout.expect("chosen");
        let e = u32::from(self.error_bound);
        let step = 2 * e + 1;
        let n = block.len();
        let alpha = block.iter().any(|c| c[3] != 255);
        let channels = if alpha { 4 } else { 3 };
        let mut base = [0u32; 4];
        let mut present = [0u8; 256];
        let mut distinct = Vec::with_capacity(n);
        for c in 0..channels {
            present.fill(0);
            for x in block {
                present[usize::from(x[c])] = 1;
            }
            distinct.clear();
            distinct.extend((0..=255u8).filter(|&v| present[usize::from(v)] != 0));
            base[c] = best_base(&distinct, e);
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
        // The palette: distinct keys in increasing order.
        s.keys.clear();
        s.keys.extend_from_slice(&s.quant);
        s.keys.sort_unstable();
        s.keys.dedup();
        let k = s.keys.len() as u32;
        s.index.clear();
        for &key in &s.quant {
            let i = s.keys.binary_search(&key).expect("key present") as u32;
            s.index.push(i);
        }
        let w = index_width(k);
        let subs = n.div_ceil(SUB_BLOCK as usize);
        let (mut uniform, mut split_flags, mut flags) = (0u32, 0u32, 0u32);
        let mut index_bits = 0u32;
        s.kinds.clear();
        for sub in 0..subs {
            let part = &s.index[sub * 8..(sub * 8 + 8).min(n)];
            let changes = part.windows(2).filter(|p| p[0] != p[1]).count();
            let full = part.len() as u32 * w;
            let kind = if changes == 0 {
                uniform |= 1 << sub;
                index_bits += w;
                SubBlock::Uniform
            } else if layout.split && changes == 1 && 2 * w + SPLIT_POSITION_BITS < full {
                split_flags |= 1 << flags;
                flags += 1;
                index_bits += 2 * w + SPLIT_POSITION_BITS;
                SubBlock::Split
            } else {
                flags += 1;
                index_bits += full;
                SubBlock::Full
            };
            s.kinds.push(kind);
        }
        let masks = 8 * layout.mask_bytes() as u32 + if layout.split { flags } else { 0 };
        let palette_bits = if k == 1 {
            0
        } else {
            16 + masks + k * eb + index_bits
        };
        let direct_bits = 16 + n as u32 * eb;
        let direct = k > MAX_PALETTE || (k > 1 && direct_bits < palette_bits);
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
            let n = layout.mask_bytes();
            out.extend_from_slice(&uniform.to_le_bytes()[..n]);
        }
        let mut bits = Bits { out, acc: 0, n: 0 };
        if !direct && layout.split {
            bits.put(split_flags, flags);
        }
        let entries: &[u32] = if direct { &s.quant } else { &s.keys };
        for &key in entries {
            for c in 0..channels {
                bits.put(key >> (8 * c) & 255, widths[c]);
            }
        }
        if !direct {
            for (sub, kind) in s.kinds.iter().enumerate() {
                let part = &s.index[sub * 8..(sub * 8 + 8).min(n)];
                match kind {
                    SubBlock::Uniform => bits.put(part[0], w),
                    SubBlock::Split => {
                        let p = part.iter().position(|&i| i != part[0]).expect("a change");
                        bits.put(part[0], w);
                        bits.put(part[p], w);
                        bits.put(p as u32, SPLIT_POSITION_BITS);
                    }
                    SubBlock::Full => {
                        for &i in part {
                            bits.put(i, w);
                        }
                    }
                }
            }
        }
        bits.flush();
    }
}

/// Encodes `colors` into a whole section, the layout chosen by the encoder.
pub fn encode(colors: &[[u8; 4]], error_bound: u8) -> Option<(Vec<u8>, PackedSummary)> {
    encode_with(PackedColorEncoder::new(error_bound)?, colors)
}

/// Encodes `colors` into a whole section in `layout`.
pub fn encode_with_layout(
    colors: &[[u8; 4]],
    error_bound: u8,
    layout: BlockLayout,
) -> Option<(Vec<u8>, PackedSummary)> {
    encode_with(
        PackedColorEncoder::with_layout(error_bound, layout)?,
        colors,
    )
}

fn encode_with(
    mut enc: PackedColorEncoder,
    colors: &[[u8; 4]],
) -> Option<(Vec<u8>, PackedSummary)> {
    let mut out = Vec::new();
    enc.push(colors, &mut out);
    let summary = enc.finish(&mut out);
    Some((out, summary))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// The word-at-a-time index check answers as a check of each index
        /// read on its own, at any bit offset, near the end of the bytes too.
        #[test]
        fn indices_below_checks_every_index(
            bytes in proptest::collection::vec(any::<u8>(), 0..80),
            start in 0usize..8,
            pos in 0u64..64,
            count in 0u64..300,
            w in 1u32..=6,
            k_seed in any::<u32>(),
        ) {
            let k = 1 + k_seed % ((1 << w) - 1);
            let each = (0..count).all(|i| read_bits(&bytes, start, pos + i * u64::from(w), w) < k);
            prop_assert_eq!(indices_below(&bytes, start, pos, count, w, k), each);
        }
    }

    fn check_round_trip(colors: &[[u8; 4]], e: u8) {
        check_layout_round_trip(colors, e, None);
        for layout in [BlockLayout::V1_1, BlockLayout::CHOICES[2]] {
            check_layout_round_trip(colors, e, Some(layout));
        }
    }

    fn check_layout_round_trip(colors: &[[u8; 4]], e: u8, layout: Option<BlockLayout>) {
        let (bytes, summary) = match layout {
            None => encode(colors, e).unwrap(),
            Some(layout) => encode_with_layout(colors, e, layout).unwrap(),
        };
        if let Some(layout) = layout {
            assert_eq!(summary.trailer.layout, layout);
        }
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
        // The cursor agrees with random access, in order and scattered.
        let mut cursor = packed.cursor();
        for i in (0..colors.len() as u64 + 1).chain((0..colors.len() as u64).rev().step_by(7)) {
            assert_eq!(cursor.get(i), packed.get(i), "cursor at {i}");
        }
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

    /// Colours in runs of 5: most sub-blocks of 8 change once.
    fn runs_of_five(n: u32) -> Vec<[u8; 4]> {
        (0..n)
            .map(|i| {
                let c = (i / 5 % 3) as u8;
                [40 * c, 200 - 30 * c, 90, 255]
            })
            .collect()
    }

    #[test]
    fn runs_make_split_sub_blocks() {
        let colors = runs_of_five(1000);
        for layout in BlockLayout::CHOICES {
            let (bytes, _) = encode_with_layout(&colors, 0, layout).unwrap();
            let packed = PackedColors::new(&bytes, colors.len() as u64).unwrap();
            let h = packed.header(0);
            assert!(h.palette > 1 && h.split_flags != 0, "{layout:?}: {h:?}");
            check_layout_round_trip(&colors, 0, Some(layout));
        }
        // Without split sub-blocks the same colours take more bytes.
        let plain = encode_with_layout(&colors, 0, BlockLayout::V1_1).unwrap().0;
        let split = encode_with_layout(&colors, 0, BlockLayout::CHOICES[0])
            .unwrap()
            .0;
        assert!(
            split.len() < plain.len(),
            "{} >= {}",
            split.len(),
            plain.len()
        );
    }

    #[test]
    fn the_encoder_keeps_the_smallest_layout() {
        for colors in [
            runs_of_five(70_000),
            (0..70_000u32)
                .map(|i| [(i * 97) as u8, (i * 13) as u8, (i >> 3) as u8, 255])
                .collect(),
        ] {
            let auto = encode(&colors, 0).unwrap().1;
            let smallest = BlockLayout::CHOICES
                .iter()
                .map(|&l| encode_with_layout(&colors[..SHIFT_SAMPLE], 0, l).unwrap().1)
                .min_by_key(|s| s.length)
                .unwrap();
            assert_eq!(auto.trailer.layout, smallest.trailer.layout);
        }
    }

    #[test]
    fn malformed_sections_never_panic() {
        for layout in [BlockLayout::V1_1, BlockLayout::CHOICES[1]] {
            let (bytes, _) = encode_with_layout(&runs_of_five(300), 0, layout).unwrap();
            flip_every_bit(&bytes, 300);
        }
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
        flip_every_bit(&bytes, colors.len() as u64);
    }

    /// Flips each bit of a section in turn: the checks and the decoders never
    /// panic, and random access agrees with sequential decoding.
    fn flip_every_bit(bytes: &[u8], count: u64) {
        for i in 0..bytes.len() {
            for bit in 0..8 {
                let mut b = bytes.to_vec();
                b[i] ^= 1 << bit;
                let errors = check_section(&b, count);
                if let Ok(p) = PackedColors::new(&b, count) {
                    let seq: Vec<_> = p.iter().collect();
                    assert_eq!(seq.len() as u64, count);
                    for (i, c) in seq.iter().enumerate() {
                        assert_eq!(p.get(i as u64), Some(*c));
                    }
                }
                let _ = errors;
            }
        }
    }
}
