//! The zero-copy reader.
//!
//! [`Dag::open`] checks the header and the section table (O(sections) work,
//! nothing allocated in proportion to the file) and then hands out views into
//! the caller's bytes. Every access that follows a pointer is bounds-checked and
//! returns a [`FormatError`] instead of panicking, so the reader is safe on any
//! input; proving a file fully correct is the validator's job
//! ([`crate::validate`]).

use crate::error::{ErrorCode, FormatError};
use crate::layout::{
    self, AttributeKind, COUNT_SATURATED, HEADER_SIZE, MAGIC, MAX_DEPTH, MAX_FILE_SIZE,
    MAX_LEAF_COUNT, MAX_NODE_LEVEL_BYTES, MAX_SECTIONS, MIN_DEPTH, RawHeader, RawSectionEntry,
    SECTION_ALIGN, SECTION_ENTRY_SIZE, SectionKind,
};
use crate::morton;
use crate::packed_colors::PackedColors;
use std::ops::ControlFlow;

/// The decoded file header.
#[derive(Clone, Debug, PartialEq)]
pub struct Header {
    /// Major format version (1).
    pub version_major: u16,
    /// Minor format version.
    pub version_minor: u16,
    /// Required feature bits.
    pub required_features: u32,
    /// Optional feature bits.
    pub optional_features: u32,
    /// Depth D: 2^D voxels along each axis.
    pub depth: u8,
    /// Meaning of the 24 attribute bits.
    pub attribute_kind: AttributeKind,
    /// Number of section table entries.
    pub section_count: u16,
    /// World-space minimum corner of the root cube.
    pub root_min: [f64; 3],
    /// World-space edge length of the root cube.
    pub root_size: f64,
    /// Total file length in bytes.
    pub file_size: u64,
    /// Total number of set voxels.
    pub voxel_count: u64,
    /// Stored header checksum.
    pub header_crc: u32,
}

/// One decoded section table entry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SectionEntry {
    /// Position in the section table.
    pub index: u16,
    /// What the section holds.
    pub kind: SectionKind,
    /// Level (level sections), else 0.
    pub level: u8,
    /// Pointer width in bytes (node levels), else 0.
    pub pointer_width: u8,
    /// Bytes 5..8 of the entry: a 2.0 node level's reference widths
    /// w_1, w_2, w_3 (§23.2); in 1.0 the pointer width and the reserved bytes.
    pub widths: [u8; 3],
    /// Byte offset from the start of the file.
    pub offset: u64,
    /// Length in bytes.
    pub length: u64,
    /// Nodes, leaves or colours held.
    pub item_count: u64,
    /// Stored CRC-32C of the section bytes.
    pub crc: u32,
}

impl SectionEntry {
    /// Byte offset of this entry in the file.
    pub fn entry_offset(&self) -> u64 {
        (HEADER_SIZE + usize::from(self.index) * SECTION_ENTRY_SIZE) as u64
    }
}

/// The bytes of one level of the DAG.
#[derive(Clone, Copy, Debug)]
pub struct LevelSection<'a> {
    /// Level number: 0 is the root.
    pub level: u8,
    /// The section bytes.
    pub bytes: &'a [u8],
    /// Byte offset of the section in the file.
    pub file_offset: u64,
    /// Nodes (or leaves) in the level.
    pub node_count: u64,
    /// Pointer width of a node level; 0 for the leaf level.
    pub pointer_width: u8,
    /// Whether this is the leaf level (64-bit 4³ masks).
    pub is_leaf: bool,
}

impl LevelSection<'_> {
    /// Number of addressable units: 4-byte words of a node level, leaves of the leaf level.
    pub fn units(&self) -> u64 {
        if self.is_leaf {
            self.bytes.len() as u64 / 8
        } else {
            self.bytes.len() as u64 / 4
        }
    }
}

/// An interior node record.
#[derive(Clone, Copy, Debug)]
pub struct Node<'a> {
    /// Level of the node.
    pub level: u8,
    /// Offset of the record in its level, in 4-byte words.
    pub word: u32,
    /// The 32-bit header word.
    pub header: u32,
    /// Pointer width in bytes.
    pub pointer_width: u8,
    /// The pointer bytes (exactly `child_count * pointer_width`).
    pointers: &'a [u8],
}

impl Node<'_> {
    /// The 8-bit child mask (bit i set when child i exists).
    #[inline]
    pub fn child_mask(&self) -> u8 {
        self.header as u8
    }

    /// The 24 attribute bits.
    #[inline]
    pub fn attribute(&self) -> u32 {
        self.header >> layout::CHILD_MASK_BITS
    }

    /// Number of children.
    #[inline]
    pub fn child_count(&self) -> u32 {
        self.child_mask().count_ones()
    }

    /// The pointer stored at `rank` (0 = first set mask bit).
    #[inline]
    pub fn pointer_at(&self, rank: u32) -> u32 {
        let w = usize::from(self.pointer_width);
        let start = rank as usize * w;
        let mut v = 0u32;
        for (i, &b) in self.pointers[start..start + w].iter().enumerate() {
            v |= u32::from(b) << (8 * i);
        }
        v
    }

    /// The pointer to child `child` (0..8), or `None` when the child is empty.
    #[inline]
    pub fn child_pointer(&self, child: u32) -> Option<u32> {
        let mask = u32::from(self.child_mask());
        if child >= 8 || mask & (1 << child) == 0 {
            return None;
        }
        Some(self.pointer_at((mask & ((1 << child) - 1)).count_ones()))
    }

    /// Size of the record in bytes, padding included.
    pub fn record_size(&self) -> u64 {
        layout::node_record_size(self.child_count(), self.pointer_width)
    }
}

/// A 64-bit occupancy mask of a 4³ brick (bit [`layout::leaf_bit`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct LeafMask(pub u64);

impl LeafMask {
    /// Whether the voxel at brick coordinates (each 0..4) is set.
    #[inline]
    pub fn is_set(self, x: u32, y: u32, z: u32) -> bool {
        self.0 >> layout::leaf_bit(x & 3, y & 3, z & 3) & 1 != 0
    }

    /// The 8-bit mask of the 2³ sub-bricks that hold a voxel (bit = child index).
    #[inline]
    pub fn sub_brick_mask(self) -> u8 {
        let mut m = 0u8;
        for i in 0..8 {
            if (self.0 >> (8 * i)) & 0xff != 0 {
                m |= 1 << i;
            }
        }
        m
    }

    /// The 8-bit voxel mask of sub-brick `child` (0..8).
    #[inline]
    pub fn sub_brick(self, child: u32) -> u8 {
        (self.0 >> (8 * child)) as u8
    }

    /// Number of set voxels.
    #[inline]
    pub fn count(self) -> u32 {
        self.0.count_ones()
    }
}

/// A reference to a node of any level: a word offset for interior levels, an
/// index for the leaf level.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct NodeRef {
    /// Level of the node.
    pub level: u8,
    /// Word offset (interior level) or leaf index (leaf level).
    pub pointer: u32,
}

/// The colours of a file, whichever section holds them, by dense voxel index.
#[derive(Clone, Copy, Debug)]
pub enum ColorTable<'a> {
    /// A VOXEL_COLORS section: 4 bytes per colour.
    Raw(&'a [u8]),
    /// A PACKED_COLORS section.
    Packed(PackedColors<'a>),
}

impl<'a> ColorTable<'a> {
    /// The colour table of a file's colour sections: the raw section if it
    /// has one (a valid file holds at most one of the two), else the packed one.
    pub fn from_sections(raw: Option<&'a [u8]>, packed: Option<PackedColors<'a>>) -> Option<Self> {
        match (raw, packed) {
            (Some(raw), _) => Some(ColorTable::Raw(raw)),
            (None, Some(p)) => Some(ColorTable::Packed(p)),
            (None, None) => None,
        }
    }

    /// Colours held.
    pub fn len(&self) -> u64 {
        match self {
            ColorTable::Raw(b) => b.len() as u64 / 4,
            ColorTable::Packed(p) => p.len(),
        }
    }

    /// Whether there are no colours.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The colour (RGBA8) of the voxel with dense index `index`, `None` past the end.
    pub fn get(&self, index: u64) -> Option<[u8; 4]> {
        match self {
            ColorTable::Raw(b) => {
                let at = usize::try_from(index).ok()?.checked_mul(4)?;
                b.get(at..at + 4).map(|c| [c[0], c[1], c[2], c[3]])
            }
            ColorTable::Packed(p) => p.get(index),
        }
    }

    /// Random access for lookups that come in runs of neighbours (a render's
    /// pixels): a packed section keeps the last block's header.
    pub fn cursor(&self) -> ColorCursor<'a> {
        match *self {
            ColorTable::Raw(b) => ColorCursor::Raw(b),
            ColorTable::Packed(p) => ColorCursor::Packed(p.cursor()),
        }
    }

    /// Every colour in order.
    pub fn iter(&self) -> Box<dyn Iterator<Item = [u8; 4]> + 'a> {
        match *self {
            ColorTable::Raw(b) => Box::new(b.chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]])),
            ColorTable::Packed(p) => Box::new(p.iter()),
        }
    }
}

/// Random access to a [`ColorTable`] that remembers the last packed block;
/// see [`ColorTable::cursor`].
#[derive(Clone, Debug)]
pub enum ColorCursor<'a> {
    /// A VOXEL_COLORS section.
    Raw(&'a [u8]),
    /// A PACKED_COLORS section.
    Packed(crate::packed_colors::PackedColorsCursor<'a>),
}

impl ColorCursor<'_> {
    /// The colour of the voxel with dense index `index`, `None` past the end;
    /// the same as [`ColorTable::get`].
    pub fn get(&mut self, index: u64) -> Option<[u8; 4]> {
        match self {
            ColorCursor::Raw(b) => ColorTable::Raw(b).get(index),
            ColorCursor::Packed(p) => p.get(index),
        }
    }
}

/// A memory-safe, zero-copy view of a `.vdag` file.
#[derive(Clone, Debug)]
pub struct Dag<'a> {
    bytes: &'a [u8],
    header: Header,
    sections: Vec<SectionEntry>,
    levels: Vec<LevelSection<'a>>,
    colors: Option<&'a [u8]>,
    packed: Option<PackedColors<'a>>,
}

#[inline]
pub(crate) fn read_u32(bytes: &[u8], at: usize) -> Option<u32> {
    bytes
        .get(at..at + 4)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

pub(crate) fn read_u64(bytes: &[u8], at: usize) -> Option<u64> {
    bytes
        .get(at..at + 8)
        .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
}

/// Decodes the header without judging it.
pub fn decode_header(raw: &RawHeader) -> Result<Header, FormatError> {
    let kind = AttributeKind::from_raw(raw.attribute_kind).ok_or_else(|| {
        FormatError::new(
            ErrorCode::UnknownAttributeKind,
            25,
            format!(
                "attribute kind {} is not in the registry",
                raw.attribute_kind
            ),
        )
    })?;
    Ok(decode_header_fields(raw, kind))
}

/// Decodes the header fields, taking the attribute kind from the caller.
fn decode_header_fields(raw: &RawHeader, attribute_kind: AttributeKind) -> Header {
    Header {
        version_major: u16::from_le(raw.version_major),
        version_minor: u16::from_le(raw.version_minor),
        required_features: u32::from_le(raw.required_features),
        optional_features: u32::from_le(raw.optional_features),
        depth: raw.depth,
        attribute_kind,
        section_count: u16::from_le(raw.section_count),
        root_min: raw.root_min.map(|b| f64::from_bits(u64::from_le(b))),
        root_size: f64::from_bits(u64::from_le(raw.root_size)),
        file_size: u64::from_le(raw.file_size),
        voxel_count: u64::from_le(raw.voxel_count),
        header_crc: u32::from_le(raw.header_crc),
    }
}

/// Decodes one section table entry without judging it.
pub fn decode_section_entry(
    index: u16,
    raw: &RawSectionEntry,
) -> Result<SectionEntry, FormatError> {
    let entry_offset = (HEADER_SIZE + usize::from(index) * SECTION_ENTRY_SIZE) as u64;
    let raw_kind = u32::from_le(raw.kind);
    let kind = SectionKind::from_raw(raw_kind).ok_or_else(|| {
        FormatError::new(
            ErrorCode::UnknownSectionKind,
            entry_offset,
            format!("section {index} has unknown required kind {raw_kind:#x}"),
        )
    })?;
    Ok(decode_section_fields(index, raw, kind))
}

/// Decodes one section table entry, taking the kind from the caller.
fn decode_section_fields(index: u16, raw: &RawSectionEntry, kind: SectionKind) -> SectionEntry {
    SectionEntry {
        index,
        kind,
        level: raw.level,
        pointer_width: raw.pointer_width,
        widths: {
            let [b6, b7] = u16::from_le(raw.reserved0).to_le_bytes();
            [raw.pointer_width, b6, b7]
        },
        offset: u64::from_le(raw.offset),
        length: u64::from_le(raw.length),
        item_count: u64::from_le(raw.item_count),
        crc: u32::from_le(raw.crc),
    }
}

/// The structure of a file as far as the header and section table tell it.
#[derive(Clone, Debug)]
pub(crate) struct Layout {
    pub header: Header,
    pub sections: Vec<SectionEntry>,
    /// Whether the header's attribute kind is in the registry. Always true in a
    /// layout [`parse_layout`] returns; when false, `header.attribute_kind` is a
    /// placeholder ([`AttributeKind::None`]).
    pub attribute_kind_known: bool,
    /// Per section: whether its bytes can be interpreted as its kind says: it
    /// lies inside the file, its kind is known, it is in its place among the
    /// level sections and (node levels) its pointer width is 1 to 4. Always all
    /// true in a layout [`parse_layout`] returns. An entry with an unknown
    /// required kind appears as [`SectionKind::UnknownOptional`] and is not usable.
    pub usable: Vec<bool>,
}

/// How much [`check_layout`] looks at.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LayoutChecks {
    /// Also check what a lenient reader can live with: reserved fields, the
    /// header checksum and the padding between sections. Costs O(header +
    /// table + padding), never O(file).
    pub thorough: bool,
    /// Files longer than this are rejected ([`ErrorCode::FileTooLarge`]).
    pub max_file_size: u64,
    /// Whether major version 2 (§23) is accepted besides 1.
    pub accept_v2: bool,
}

/// Parses and checks the header and section table, stopping at the first
/// problem: what [`Dag::open`] needs.
///
/// Problems that a lenient reader can live with (reserved fields, checksums,
/// padding, non-minimal pointer widths) are left to the validator and not
/// looked at here.
pub(crate) fn parse_layout(bytes: &[u8], accept_v2: bool) -> Result<Layout, FormatError> {
    let mut first = None;
    let checks = LayoutChecks {
        thorough: false,
        max_file_size: MAX_FILE_SIZE,
        accept_v2,
    };
    let layout = check_layout(bytes, checks, &mut |e| {
        first = Some(e);
        ControlFlow::Break(())
    });
    match (layout, first) {
        (Some(layout), None) => Ok(layout),
        (_, Some(e)) => Err(e),
        (None, None) => unreachable!("check_layout stops only after reporting a problem"),
    }
}

/// Checks the header and section table, handing every problem found to
/// `sink`; the reader ([`parse_layout`]) and the validator share it.
///
/// Returns `None` when it stopped early: because `sink` answered
/// [`ControlFlow::Break`], or because a problem leaves nothing further to
/// interpret (file shorter than the header, bad magic, other major version,
/// depth out of range, a section count out of range or a table past the end of
/// the file; the header checksum is still checked first where the table lies
/// inside the file). Otherwise every section entry has been checked and the
/// returned layout says which sections are usable.
pub(crate) fn check_layout(
    bytes: &[u8],
    checks: LayoutChecks,
    sink: &mut dyn FnMut(FormatError) -> ControlFlow<()>,
) -> Option<Layout> {
    macro_rules! report {
        ($e:expr) => {
            if sink($e).is_break() {
                return None;
            }
        };
    }
    let len = bytes.len() as u64;
    if bytes.len() < HEADER_SIZE {
        let _ = sink(FormatError::new(
            ErrorCode::TruncatedHeader,
            len,
            format!("file is {len} bytes, shorter than the {HEADER_SIZE}-byte header"),
        ));
        return None;
    }
    if bytes[..8] != MAGIC {
        let _ = sink(FormatError::new(
            ErrorCode::BadMagic,
            0,
            "not a .vdag file (bad magic)",
        ));
        return None;
    }
    let raw: RawHeader = bytemuck::pod_read_unaligned(&bytes[..HEADER_SIZE]);
    let major = u16::from_le(raw.version_major);
    if major != layout::VERSION_MAJOR && !(checks.accept_v2 && major == layout::VERSION_MAJOR_2) {
        let message = if major == layout::VERSION_MAJOR_2 {
            "major version 2 is not supported by this 1.0 reader (open it with dagfmt::AnyDag::open, or downgrade it with `dagtool upgrade --format-version 1`)".to_string()
        } else {
            format!("major version {major} is not supported (this reader reads versions 1 and 2)")
        };
        let _ = sink(FormatError::new(ErrorCode::UnsupportedVersion, 8, message));
        return None;
    }
    let v2 = major == layout::VERSION_MAJOR_2;
    let (header, attribute_kind_known) = match decode_header(&raw) {
        Ok(header) => (header, true),
        Err(e) => {
            report!(e);
            (decode_header_fields(&raw, AttributeKind::None), false)
        }
    };
    if header.required_features & !layout::KNOWN_REQUIRED_FEATURES != 0 {
        report!(FormatError::new(
            ErrorCode::UnknownRequiredFeature,
            16,
            format!(
                "unknown required feature bits {:#x}",
                header.required_features
            ),
        ));
    }
    let header_size = u32::from_le(raw.header_size);
    if header_size as usize != HEADER_SIZE {
        report!(FormatError::new(
            ErrorCode::BadHeaderSize,
            12,
            format!("header size is {header_size}, expected {HEADER_SIZE}"),
        ));
    }
    let depth_ok = (MIN_DEPTH..=MAX_DEPTH).contains(&header.depth);
    if !depth_ok {
        report!(FormatError::new(
            ErrorCode::DepthOutOfRange,
            24,
            format!(
                "depth {} is outside {MIN_DEPTH}..={MAX_DEPTH}",
                header.depth
            ),
        ));
    }
    if !header.root_min.iter().all(|v| v.is_finite())
        || !header.root_size.is_finite()
        || header.root_size <= 0.0
    {
        report!(FormatError::new(
            ErrorCode::BadRootCube,
            32,
            format!(
                "root cube min {:?} size {} is not finite with a positive size",
                header.root_min, header.root_size
            ),
        ));
    }
    if checks.thorough {
        if raw.reserved0 != 0 {
            report!(FormatError::new(
                ErrorCode::NonzeroReserved,
                28,
                "header reserved field at byte 28 is not zero"
            ));
        }
        if let Some(i) = raw.reserved1.iter().position(|&b| b != 0) {
            let at = std::mem::offset_of!(RawHeader, reserved1) + i;
            report!(FormatError::new(
                ErrorCode::NonzeroReserved,
                at as u64,
                format!("header reserved byte {at} is not zero"),
            ));
        }
    }
    if len > checks.max_file_size {
        report!(FormatError::new(
            ErrorCode::FileTooLarge,
            0,
            format!(
                "file is {len} bytes, over the {}-byte limit",
                checks.max_file_size
            ),
        ));
    }
    if header.file_size != len {
        report!(FormatError::new(
            ErrorCode::FileSizeMismatch,
            64,
            format!(
                "header says {} bytes but the file has {len}",
                header.file_size
            ),
        ));
    }
    let count = header.section_count;
    let level_sections = u16::from(header.depth).saturating_sub(1);
    let count_ok = count <= MAX_SECTIONS && (!depth_ok || count >= level_sections);
    if !count_ok {
        report!(FormatError::new(
            ErrorCode::BadSectionTable,
            26,
            format!(
                "{count} sections declared; depth {} needs {level_sections} level sections and at most {MAX_SECTIONS} in all",
                header.depth
            ),
        ));
    }
    let table_end = HEADER_SIZE + usize::from(count) * SECTION_ENTRY_SIZE;
    if table_end > bytes.len() {
        let _ = sink(FormatError::new(
            ErrorCode::BadSectionTable,
            HEADER_SIZE as u64,
            format!("the section table of {count} entries runs past the end of the file"),
        ));
        return None;
    }
    if checks.thorough {
        let head: &[u8; HEADER_SIZE] = bytes[..HEADER_SIZE]
            .try_into()
            .expect("length checked above");
        let computed = layout::header_checksum(head, &bytes[HEADER_SIZE..table_end]);
        if computed != header.header_crc {
            report!(FormatError::new(
                ErrorCode::HeaderChecksum,
                layout::HEADER_CRC_OFFSET as u64,
                format!(
                    "header checksum is {:#010x}, the header and section table give {computed:#010x}",
                    header.header_crc
                ),
            ));
        }
    }
    if !depth_ok || !count_ok {
        return None;
    }
    let attribute_kind = attribute_kind_known.then_some(header.attribute_kind);
    let mut sections = Vec::with_capacity(usize::from(count));
    let mut usable = Vec::with_capacity(usize::from(count));
    let mut previous_end = table_end as u64;
    let mut seen_colors = false;
    let mut seen_packed = false;
    for index in 0..count {
        let at = HEADER_SIZE + usize::from(index) * SECTION_ENTRY_SIZE;
        let raw: RawSectionEntry =
            bytemuck::pod_read_unaligned(&bytes[at..at + SECTION_ENTRY_SIZE]);
        let (entry, kind_known) = match decode_section_entry(index, &raw) {
            Ok(entry) => (entry, true),
            Err(e) => {
                report!(e);
                let kind = SectionKind::UnknownOptional(u32::from_le(raw.kind));
                (decode_section_fields(index, &raw, kind), false)
            }
        };
        if checks.thorough {
            // In 2.0, bytes 6 and 7 of a known kind's entry are widths (E070).
            let reserved0 =
                if v2 && kind_known && !matches!(entry.kind, SectionKind::UnknownOptional(_)) {
                    0
                } else {
                    u32::from(u16::from_le(raw.reserved0))
                };
            for (field, value) in [(6, reserved0), (36, u32::from_le(raw.reserved1))] {
                if value != 0 {
                    report!(FormatError::new(
                        ErrorCode::NonzeroReserved,
                        (at + field) as u64,
                        format!(
                            "reserved field at byte {field} of section entry {index} is not zero"
                        ),
                    ));
                }
            }
        }
        let mut ok = kind_known;
        let place = EntryPlace {
            bytes,
            previous_end,
            attribute_kind,
            kind_known,
            v2,
        };
        ok &= check_section_entry(&header, &entry, &place, checks, sink)?;
        // (A colour section among the level sections was reported as misplaced.)
        let colour_kind = matches!(
            entry.kind,
            SectionKind::VoxelColors | SectionKind::PackedColors
        );
        if colour_kind && index > u16::from(header.depth) - 2 {
            if seen_colors {
                // E063 among raw colour sections; E080 once a packed one is involved.
                let code = if entry.kind == SectionKind::VoxelColors && !seen_packed {
                    ErrorCode::BadColorSection
                } else {
                    ErrorCode::BadPackedColorSection
                };
                report!(FormatError::new(
                    code,
                    entry.entry_offset(),
                    format!("section {index} is a second colour section"),
                ));
            }
            seen_colors = true;
            seen_packed |= entry.kind == SectionKind::PackedColors;
        }
        previous_end = entry.offset.saturating_add(entry.length);
        sections.push(entry);
        usable.push(ok);
    }
    if checks.thorough && previous_end < len {
        report!(FormatError::new(
            ErrorCode::BadPadding,
            previous_end,
            format!(
                "{} bytes follow the end of the last section",
                len - previous_end
            ),
        ));
    }
    Some(Layout {
        header,
        sections,
        attribute_kind_known,
        usable,
    })
}

/// What [`check_section_entry`] needs to know besides the entry.
struct EntryPlace<'a> {
    /// The whole file.
    bytes: &'a [u8],
    /// End of the previous section, or of the section table for the first entry.
    previous_end: u64,
    /// The header's attribute kind, `None` when it is not in the registry.
    attribute_kind: Option<AttributeKind>,
    /// Whether the entry's kind is known (an unknown required kind was reported already).
    kind_known: bool,
    /// Whether the file is version 2.0 (§23).
    v2: bool,
}

/// The checks on one section entry: placement and, for level sections, kind,
/// level, width and size limits. Returns `None` when `sink` asked to stop, else
/// whether the section's bytes can be interpreted as its kind says.
fn check_section_entry(
    header: &Header,
    entry: &SectionEntry,
    place: &EntryPlace<'_>,
    checks: LayoutChecks,
    sink: &mut dyn FnMut(FormatError) -> ControlFlow<()>,
) -> Option<bool> {
    macro_rules! report {
        ($e:expr) => {
            if sink($e).is_break() {
                return None;
            }
        };
    }
    let at = entry.entry_offset();
    let index = entry.index;
    let file_len = place.bytes.len() as u64;
    let previous_end = place.previous_end;
    let mut usable = true;
    let in_bounds = entry
        .offset
        .checked_add(entry.length)
        .is_some_and(|e| e <= file_len);
    if !in_bounds {
        report!(FormatError::new(
            ErrorCode::SectionOutOfBounds,
            at + 8,
            format!(
                "section {index} spans {}+{} bytes, past the end of the {file_len}-byte file",
                entry.offset, entry.length
            ),
        ));
        usable = false;
    }
    let aligned = entry.offset.is_multiple_of(SECTION_ALIGN);
    if !aligned {
        report!(FormatError::new(
            ErrorCode::SectionMisaligned,
            at + 8,
            format!(
                "section {index} starts at {}, not a multiple of {SECTION_ALIGN}",
                entry.offset
            ),
        ));
    }
    if entry.offset < previous_end {
        report!(FormatError::new(
            ErrorCode::SectionOverlap,
            at + 8,
            format!(
                "section {index} starts at {} before the previous section (or the table) ends at {previous_end}",
                entry.offset
            ),
        ));
    } else if checks.thorough && in_bounds {
        // (The placement of a section outside the file is reported once, as E020.)
        let expected = layout::align_section(previous_end);
        if aligned && entry.offset != expected {
            report!(FormatError::new(
                ErrorCode::BadPadding,
                at + 8,
                format!(
                    "section {index} starts at {}; minimal padding puts it at {expected}",
                    entry.offset
                ),
            ));
        }
        // Empty when the previous section already ran past the end of the file.
        let gap = place
            .bytes
            .get(previous_end as usize..entry.offset.min(file_len) as usize)
            .unwrap_or(&[]);
        if let Some(i) = gap.iter().position(|&b| b != 0) {
            let byte = previous_end + i as u64;
            report!(FormatError::new(
                ErrorCode::BadPadding,
                byte,
                format!("padding byte {byte} before section {index} is not zero"),
            ));
        }
    }
    let leaf_level = header.depth - 2;
    if index <= u16::from(leaf_level) {
        let level = index as u8;
        let expected = if level == leaf_level {
            SectionKind::LeafLevel
        } else {
            SectionKind::NodeLevel
        };
        if !place.kind_known {
            usable = false;
        } else if entry.kind != expected || entry.level != level {
            // A misplaced section is reported once, not checked as what it claims to be.
            report!(FormatError::new(
                ErrorCode::BadLevelSections,
                at,
                format!(
                    "section {index} must be the {} section of level {level}, found {:?} of level {}",
                    if expected == SectionKind::LeafLevel { "leaf" } else { "node" },
                    entry.kind,
                    entry.level
                ),
            )
            .at_level(level));
            return Some(false);
        }
    } else if matches!(entry.kind, SectionKind::NodeLevel | SectionKind::LeafLevel) {
        report!(FormatError::new(
            ErrorCode::BadLevelSections,
            at,
            format!(
                "section {index}: extra level section after the {} level sections",
                leaf_level + 1
            ),
        ));
        return Some(false);
    }
    if place.v2 && !matches!(entry.kind, SectionKind::UnknownOptional(_)) {
        let w = entry.widths;
        let ok = if entry.kind == SectionKind::NodeLevel {
            1 <= w[0] && w[0] <= w[1] && w[1] <= w[2] && u32::from(w[2]) <= crate::v2::MAX_WIDTH
        } else {
            w == [0; 3]
        };
        if !ok {
            report!(
                FormatError::new(
                    ErrorCode::BadWidths,
                    at + 5,
                    if entry.kind == SectionKind::NodeLevel {
                        format!(
                            "level {} has reference widths {w:?}, not 1 <= w1 <= w2 <= w3 <= {}",
                            entry.level,
                            crate::v2::MAX_WIDTH
                        )
                    } else {
                        format!(
                            "section {index} ({:?}) has bytes 5..8 {w:?}, must be 0",
                            entry.kind
                        )
                    },
                )
                .at_level(entry.level)
            );
            if entry.kind == SectionKind::NodeLevel {
                usable = false;
            }
        }
    }
    match entry.kind {
        SectionKind::NodeLevel if place.v2 => {
            if entry.length > MAX_NODE_LEVEL_BYTES {
                report!(
                    FormatError::new(
                        ErrorCode::LevelTooLarge,
                        at + 16,
                        format!(
                            "level {} has {} bytes, over the limit of {MAX_NODE_LEVEL_BYTES}",
                            entry.level, entry.length
                        ),
                    )
                    .at_level(entry.level)
                );
            } else if !checks.thorough && entry.item_count > entry.length / 5 {
                // The validator counts the records instead.
                report!(
                    FormatError::new(
                        ErrorCode::ItemCountMismatch2,
                        at + 24,
                        format!(
                            "level {} declares {} records in {} bytes (each takes at least 5)",
                            entry.level, entry.item_count, entry.length
                        ),
                    )
                    .at_level(entry.level)
                );
            }
        }
        SectionKind::NodeLevel => {
            if !(1..=4).contains(&entry.pointer_width) {
                report!(
                    FormatError::new(
                        ErrorCode::BadPointerWidth,
                        at + 5,
                        format!(
                            "level {} has pointer width {}, not 1 to 4",
                            entry.level, entry.pointer_width
                        ),
                    )
                    .at_level(entry.level)
                );
                usable = false;
            }
            if entry.length > MAX_NODE_LEVEL_BYTES {
                report!(
                    FormatError::new(
                        ErrorCode::LevelTooLarge,
                        at + 16,
                        format!(
                            "level {} has {} bytes, over the limit of {MAX_NODE_LEVEL_BYTES}",
                            entry.level, entry.length
                        ),
                    )
                    .at_level(entry.level)
                );
            } else if !checks.thorough && entry.item_count > entry.length / 8 {
                // The validator counts the records instead.
                report!(
                    FormatError::new(
                        ErrorCode::ItemCountMismatch,
                        at + 24,
                        format!(
                            "level {} declares {} nodes in {} bytes (each node takes at least 8)",
                            entry.level, entry.item_count, entry.length
                        ),
                    )
                    .at_level(entry.level)
                );
            }
        }
        SectionKind::LeafLevel => {
            if entry.pointer_width != 0 && !place.v2 {
                report!(
                    FormatError::new(
                        ErrorCode::BadPointerWidth,
                        at + 5,
                        format!(
                            "the leaf level has pointer width {}, must be 0",
                            entry.pointer_width
                        ),
                    )
                    .at_level(entry.level)
                );
            }
            if entry.item_count > MAX_LEAF_COUNT {
                report!(
                    FormatError::new(
                        ErrorCode::LevelTooLarge,
                        at + 24,
                        format!(
                            "{} leaves exceed the limit of {MAX_LEAF_COUNT}",
                            entry.item_count
                        ),
                    )
                    .at_level(entry.level)
                );
            }
            if entry.item_count.checked_mul(8) != Some(entry.length) {
                report!(
                    FormatError::new(
                        ErrorCode::ItemCountMismatch,
                        at + 24,
                        format!(
                            "{} leaves need {} bytes, section has {}",
                            entry.item_count,
                            entry.item_count.saturating_mul(8),
                            entry.length
                        ),
                    )
                    .at_level(entry.level)
                );
            }
        }
        SectionKind::VoxelColors => {
            if entry.pointer_width != 0 && !place.v2 {
                report!(FormatError::new(
                    ErrorCode::BadPointerWidth,
                    at + 5,
                    format!(
                        "the colour section has pointer width {}, must be 0",
                        entry.pointer_width
                    ),
                ));
            }
            let kind_wrong = place
                .attribute_kind
                .is_some_and(|k| k != AttributeKind::VoxelCount);
            if kind_wrong
                || entry.item_count != header.voxel_count
                || entry.item_count.checked_mul(4) != Some(entry.length)
            {
                report!(FormatError::new(
                    ErrorCode::BadColorSection,
                    at,
                    format!(
                        "colour section of {} colours in {} bytes; needs attribute kind 1 and one 4-byte colour per voxel ({} voxels)",
                        entry.item_count, entry.length, header.voxel_count
                    ),
                ));
            } else if checks.thorough && entry.level != 0 {
                report!(FormatError::new(
                    ErrorCode::BadColorSection,
                    at + 4,
                    format!("colour section has level {}, must be 0", entry.level),
                ));
            }
        }
        SectionKind::PackedColors => {
            if entry.pointer_width != 0 && !place.v2 {
                report!(FormatError::new(
                    ErrorCode::BadPointerWidth,
                    at + 5,
                    format!(
                        "the packed colour section has pointer width {}, must be 0",
                        entry.pointer_width
                    ),
                ));
            }
            let kind_wrong = place
                .attribute_kind
                .is_some_and(|k| k != AttributeKind::VoxelCount);
            if kind_wrong || entry.item_count != header.voxel_count {
                report!(FormatError::new(
                    ErrorCode::BadPackedColorSection,
                    at,
                    format!(
                        "packed colour section of {} colours; needs attribute kind 1 and one colour per voxel ({} voxels)",
                        entry.item_count, header.voxel_count
                    ),
                ));
                usable = false;
            } else if let Some(Err((code, offset, message))) = in_bounds
                .then(|| {
                    place
                        .bytes
                        .get(entry.offset as usize..(entry.offset + entry.length) as usize)
                })
                .flatten()
                .map(|section| crate::packed_colors::open_trailer(section, entry.item_count))
            {
                report!(FormatError::new(code, entry.offset + offset, message));
                usable = false;
            }
            if checks.thorough && entry.level != 0 {
                report!(FormatError::new(
                    ErrorCode::BadPackedColorSection,
                    at + 4,
                    format!("packed colour section has level {}, must be 0", entry.level),
                ));
            }
        }
        SectionKind::UnknownOptional(_) => {}
    }
    Some(usable)
}

impl<'a> Dag<'a> {
    /// Opens a `.vdag` held in `bytes` (typically a memory map).
    ///
    /// Checks the header and section table only: O(number of sections).
    /// Checksums, padding and the node graph are checked by
    /// [`crate::validate::validate`], and every later access is bounds-checked.
    pub fn open(bytes: &'a [u8]) -> Result<Self, FormatError> {
        let Layout {
            header, sections, ..
        } = parse_layout(bytes, false)?;
        let level_count = usize::from(header.depth) - 1;
        let mut levels = Vec::with_capacity(level_count);
        let mut colors = None;
        let mut packed = None;
        for entry in &sections {
            let range = entry.offset as usize..(entry.offset + entry.length) as usize;
            match entry.kind {
                SectionKind::NodeLevel | SectionKind::LeafLevel => levels.push(LevelSection {
                    level: entry.level,
                    bytes: &bytes[range],
                    file_offset: entry.offset,
                    node_count: entry.item_count,
                    pointer_width: entry.pointer_width,
                    is_leaf: entry.kind == SectionKind::LeafLevel,
                }),
                // parse_layout rejects a second colour section.
                SectionKind::VoxelColors => colors = Some(&bytes[range]),
                SectionKind::PackedColors => {
                    packed = Some(
                        PackedColors::new(&bytes[range], entry.item_count)
                            .expect("checked by parse_layout"),
                    )
                }
                SectionKind::UnknownOptional(_) => {}
            }
        }
        let dag = Dag {
            bytes,
            header,
            sections,
            levels,
            colors,
            packed,
        };
        let root = &dag.levels[0];
        let empty = root.node_count == 0;
        if root.node_count > 1
            || (empty
                && dag
                    .levels
                    .iter()
                    .any(|l| l.node_count != 0 || !l.bytes.is_empty()))
        {
            return Err(FormatError::new(
                ErrorCode::BadRootLevel,
                dag.sections[0].entry_offset() + 24,
                format!(
                    "the root level holds {} nodes; it must hold 1, or 0 with every level empty",
                    root.node_count
                ),
            )
            .at_level(0));
        }
        if !empty && root.bytes.is_empty() {
            return Err(FormatError::new(
                ErrorCode::TruncatedNode,
                root.file_offset,
                "the root level is empty but declares a node",
            )
            .at_level(0));
        }
        Ok(dag)
    }

    /// The whole file.
    pub fn bytes(&self) -> &'a [u8] {
        self.bytes
    }

    /// The decoded header.
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// The section table.
    pub fn sections(&self) -> &[SectionEntry] {
        &self.sections
    }

    /// Depth D.
    pub fn depth(&self) -> u32 {
        u32::from(self.header.depth)
    }

    /// Voxels along each axis: 2^D.
    pub fn resolution(&self) -> u64 {
        1 << self.header.depth
    }

    /// Level of the leaf masks: D - 2.
    pub fn leaf_level(&self) -> u8 {
        self.header.depth - 2
    }

    /// Whether the volume holds no voxel.
    pub fn is_empty(&self) -> bool {
        self.levels[0].node_count == 0
    }

    /// The level sections, root first (D - 1 of them; the last is the leaf level).
    pub fn levels(&self) -> &[LevelSection<'a>] {
        &self.levels
    }

    /// The raw voxel colour section (RGBA8 per voxel, dense index order), if present.
    pub fn colors(&self) -> Option<&'a [u8]> {
        self.colors
    }

    /// The packed colour section (kind 4), if present.
    pub fn packed_colors(&self) -> Option<PackedColors<'a>> {
        self.packed
    }

    /// The voxel colours, raw or packed, if the file has any.
    pub fn color_table(&self) -> Option<ColorTable<'a>> {
        ColorTable::from_sections(self.colors, self.packed)
    }

    /// The root node, or `None` for an empty volume.
    pub fn root(&self) -> Option<NodeRef> {
        (!self.is_empty()).then_some(NodeRef {
            level: 0,
            pointer: 0,
        })
    }

    /// The interior node at `word` of interior level `level`.
    pub fn node(&self, level: u8, word: u32) -> Result<Node<'a>, FormatError> {
        let section = self
            .levels
            .get(usize::from(level))
            .filter(|s| !s.is_leaf)
            .ok_or_else(|| {
                FormatError::new(
                    ErrorCode::PointerOutOfRange,
                    0,
                    format!("level {level} is not an interior level"),
                )
            })?;
        let at = word as usize * 4;
        let header = read_u32(section.bytes, at).ok_or_else(|| {
            FormatError::new(
                ErrorCode::PointerOutOfRange,
                section.file_offset + at as u64,
                format!(
                    "word {word} is outside level {level} ({} bytes)",
                    section.bytes.len()
                ),
            )
            .at_level(level)
        })?;
        let width = section.pointer_width;
        let pointer_bytes = (header as u8).count_ones() as usize * usize::from(width);
        let pointers = section
            .bytes
            .get(at + 4..at + 4 + pointer_bytes)
            .ok_or_else(|| {
                FormatError::new(
                    ErrorCode::TruncatedNode,
                    section.file_offset + at as u64,
                    format!("node at word {word} runs past the end of level {level}"),
                )
                .at_level(level)
            })?;
        Ok(Node {
            level,
            word,
            header,
            pointer_width: width,
            pointers,
        })
    }

    /// The leaf mask at `index` of the leaf level.
    pub fn leaf(&self, index: u32) -> Result<LeafMask, FormatError> {
        let section = self
            .levels
            .last()
            .expect("depth >= 2 gives at least one level");
        read_u64(section.bytes, index as usize * 8)
            .map(LeafMask)
            .ok_or_else(|| {
                FormatError::new(
                    ErrorCode::PointerOutOfRange,
                    section.file_offset + u64::from(index) * 8,
                    format!(
                        "leaf {index} is outside the leaf level ({} leaves)",
                        section.units()
                    ),
                )
                .at_level(section.level)
            })
    }

    /// World-space position of grid point `p` (voxel units, 0..2^D per axis).
    pub fn grid_to_world(&self, p: [f64; 3]) -> [f64; 3] {
        let scale = self.header.root_size / self.resolution() as f64;
        [0, 1, 2].map(|i| self.header.root_min[i] + p[i] * scale)
    }

    /// Grid position (voxel units) of world-space point `p`.
    pub fn world_to_grid(&self, p: [f64; 3]) -> [f64; 3] {
        let scale = self.resolution() as f64 / self.header.root_size;
        [0, 1, 2].map(|i| (p[i] - self.header.root_min[i]) * scale)
    }

    /// Follows the path of voxel `(x, y, z)` from the root. Calls `visit` with
    /// each interior node and the child index taken, and returns the leaf mask
    /// reached, or `None` when the path leaves the DAG earlier.
    fn descend(
        &self,
        x: u32,
        y: u32,
        z: u32,
        mut visit: impl FnMut(&Node<'a>, u32) -> Result<(), FormatError>,
    ) -> Result<Option<LeafMask>, FormatError> {
        let depth = self.depth();
        if self.is_empty() || [x, y, z].iter().any(|&c| u64::from(c) >= self.resolution()) {
            return Ok(None);
        }
        let leaf_level = self.leaf_level();
        let mut pointer = 0u32;
        for level in 0..leaf_level {
            let node = self.node(level, pointer)?;
            let shift = depth - 1 - u32::from(level);
            let child = ((x >> shift) & 1) | (((y >> shift) & 1) << 1) | (((z >> shift) & 1) << 2);
            visit(&node, child)?;
            match node.child_pointer(child) {
                Some(p) => pointer = p,
                None => return Ok(None),
            }
        }
        self.leaf(pointer).map(Some)
    }

    /// Whether voxel `(x, y, z)` is set. Coordinates outside the volume are not set.
    pub fn is_set(&self, x: u32, y: u32, z: u32) -> Result<bool, FormatError> {
        Ok(self
            .descend(x, y, z, |_, _| Ok(()))?
            .is_some_and(|leaf| leaf.is_set(x, y, z)))
    }

    /// Number of voxels in the subtree of `node`, using stored counts where the
    /// attribute kind is 1 and they are not saturated, else summing the children.
    ///
    /// Sums are memoised per node, so the work is linear in the number of nodes
    /// visited even when long chains of saturated counts share subtrees (a full
    /// volume at depth 21 is a few hundred bytes but has 2^63 voxels).
    pub fn subtree_voxel_count(&self, node: NodeRef) -> Result<u64, FormatError> {
        self.subtree_voxel_count_memo(node, &mut rustc_hash::FxHashMap::default())
    }

    fn subtree_voxel_count_memo(
        &self,
        node: NodeRef,
        memo: &mut rustc_hash::FxHashMap<NodeRef, u64>,
    ) -> Result<u64, FormatError> {
        if node.level == self.leaf_level() {
            return Ok(u64::from(self.leaf(node.pointer)?.count()));
        }
        let n = self.node(node.level, node.pointer)?;
        if self.header.attribute_kind == AttributeKind::VoxelCount
            && n.attribute() != COUNT_SATURATED
        {
            return Ok(u64::from(n.attribute()));
        }
        if let Some(&known) = memo.get(&node) {
            return Ok(known);
        }
        let mut total = 0u64;
        for rank in 0..n.child_count() {
            let child = NodeRef {
                level: node.level + 1,
                pointer: n.pointer_at(rank),
            };
            total = total.saturating_add(self.subtree_voxel_count_memo(child, memo)?);
        }
        memo.insert(node, total);
        Ok(total)
    }

    /// The dense index of voxel `(x, y, z)`: its rank among the set voxels in
    /// Morton order, which addresses per-voxel attribute arrays. `None` when the
    /// voxel is not set. Needs attribute kind 1 to be fast; works for any kind.
    pub fn voxel_index(&self, x: u32, y: u32, z: u32) -> Result<Option<u64>, FormatError> {
        let mut index = 0u64;
        let mut memo = rustc_hash::FxHashMap::default();
        let leaf = self.descend(x, y, z, |node, child| {
            for c in 0..child {
                if let Some(p) = node.child_pointer(c) {
                    let sibling = NodeRef {
                        level: node.level + 1,
                        pointer: p,
                    };
                    index =
                        index.saturating_add(self.subtree_voxel_count_memo(sibling, &mut memo)?);
                }
            }
            Ok(())
        })?;
        Ok(leaf.filter(|l| l.is_set(x, y, z)).map(|l| {
            let bit = layout::leaf_bit(x & 3, y & 3, z & 3);
            index + u64::from((l.0 & ((1u64 << bit) - 1)).count_ones())
        }))
    }

    /// Iterates over the set voxels in Morton order, yielding their coordinates.
    pub fn voxels(&self) -> Voxels<'_, 'a> {
        Voxels::new(self)
    }
}

/// Iterator over the set voxels of a [`Dag`], in Morton order. Yields an error
/// (once, then ends) when it meets a pointer that leads out of bounds, or an
/// empty child mask or leaf mask (which a valid file never holds, E041 and
/// E048). Refusing empty nodes bounds the work between two items by the depth:
/// every node entered leads to a voxel within D − 2 steps, so a hostile file
/// cannot make the iterator spin through 8^D empty paths without yielding.
#[derive(Debug)]
pub struct Voxels<'d, 'a> {
    dag: &'d Dag<'a>,
    /// Per interior level: the node and the children not yet visited.
    stack: Vec<(Node<'a>, u8)>,
    /// Morton prefix of each stack entry's node.
    prefix: Vec<u64>,
    /// The current leaf's remaining bits and its Morton prefix.
    leaf: Option<(u64, u64)>,
    failed: bool,
    /// An error met before the first item (an unreadable or empty root),
    /// yielded by the first call.
    pending: Option<FormatError>,
}

impl<'d, 'a> Voxels<'d, 'a> {
    fn new(dag: &'d Dag<'a>) -> Self {
        let mut it = Voxels {
            dag,
            stack: Vec::new(),
            prefix: Vec::new(),
            leaf: None,
            failed: false,
            pending: None,
        };
        if !dag.is_empty() {
            // A root that cannot be read (or is empty) is the first and
            // only item.
            let root = if dag.leaf_level() == 0 {
                dag.leaf(0)
                    .and_then(|l| it.nonempty_leaf(0, l))
                    .map(|l| it.leaf = Some((l.0, 0)))
            } else {
                dag.node(0, 0)
                    .and_then(|n| it.nonempty_node(n))
                    .map(|root| {
                        it.stack.push((root, root.child_mask()));
                        it.prefix.push(0);
                    })
            };
            if let Err(e) = root {
                it.failed = true;
                it.pending = Some(e);
            }
        }
        it
    }

    /// `node`, or an error when its child mask is empty.
    fn nonempty_node(&self, node: Node<'a>) -> Result<Node<'a>, FormatError> {
        if node.child_mask() != 0 {
            return Ok(node);
        }
        let section = &self.dag.levels[usize::from(node.level)];
        Err(FormatError::new(
            ErrorCode::EmptyChildMask,
            section.file_offset + u64::from(node.word) * 4,
            format!(
                "node at word {} of level {} has an empty child mask",
                node.word, node.level
            ),
        )
        .at_level(node.level))
    }

    /// `leaf` (at `index` of the leaf level), or an error when it is empty.
    fn nonempty_leaf(&self, index: u32, leaf: LeafMask) -> Result<LeafMask, FormatError> {
        if leaf.0 != 0 {
            return Ok(leaf);
        }
        let section = self
            .dag
            .levels
            .last()
            .expect("depth >= 2 gives a leaf level");
        Err(FormatError::new(
            ErrorCode::EmptyLeafMask,
            section.file_offset + u64::from(index) * 8,
            format!("leaf {index} is empty (a leaf holds at least one voxel)"),
        )
        .at_level(section.level))
    }

    /// The next voxel's Morton code.
    pub fn next_morton(&mut self) -> Option<Result<u64, FormatError>> {
        if let Some(e) = self.pending.take() {
            return Some(Err(e));
        }
        loop {
            if let Some((bits, prefix)) = &mut self.leaf {
                if *bits != 0 {
                    let b = bits.trailing_zeros();
                    *bits &= *bits - 1;
                    return Some(Ok(*prefix << 6 | u64::from(b)));
                }
                self.leaf = None;
            }
            if self.failed {
                return None;
            }
            let (node, remaining) = self.stack.last_mut()?;
            if *remaining == 0 {
                self.stack.pop();
                self.prefix.pop();
                continue;
            }
            let child = remaining.trailing_zeros();
            *remaining &= *remaining - 1;
            let node = *node;
            let prefix = self.prefix.last().copied().unwrap_or(0) << 3 | u64::from(child);
            let pointer = node.child_pointer(child).expect("bit is in the mask");
            let next = if node.level + 1 == self.dag.leaf_level() {
                self.dag
                    .leaf(pointer)
                    .and_then(|l| self.nonempty_leaf(pointer, l))
                    .map(|l| self.leaf = Some((l.0, prefix)))
            } else {
                self.dag
                    .node(node.level + 1, pointer)
                    .and_then(|n| self.nonempty_node(n))
                    .map(|n| {
                        self.stack.push((n, n.child_mask()));
                        self.prefix.push(prefix);
                    })
            };
            if let Err(e) = next {
                self.failed = true;
                self.stack.clear();
                return Some(Err(e));
            }
        }
    }
}

impl Iterator for Voxels<'_, '_> {
    type Item = Result<[u32; 3], FormatError>;

    fn next(&mut self) -> Option<Self::Item> {
        self.next_morton().map(|r| r.map(morton::decode))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::{SECTION_ENTRY_SIZE, node_record_size};

    /// A full volume at depth 21: one node per level, every count saturated.
    fn full_volume_depth_21() -> Vec<u8> {
        let depth = MAX_DEPTH;
        let levels = usize::from(depth) - 1;
        let table_end = HEADER_SIZE + levels * SECTION_ENTRY_SIZE;
        let mut sections: Vec<Vec<u8>> = Vec::new();
        for _ in 0..levels - 1 {
            let mut rec = (0xFFu32 | COUNT_SATURATED << 8).to_le_bytes().to_vec();
            rec.extend_from_slice(&[0u8; 8]);
            assert_eq!(rec.len() as u64, node_record_size(8, 1));
            sections.push(rec);
        }
        sections.push(u64::MAX.to_le_bytes().to_vec());
        let mut file = vec![0u8; table_end];
        let mut offset = table_end as u64;
        for (i, sec) in sections.iter().enumerate() {
            let leaf = i == levels - 1;
            // Sections start at multiples of 8 (the 12-byte records leave gaps).
            offset = layout::align_section(offset);
            file.resize(offset as usize, 0);
            let entry = RawSectionEntry {
                kind: if leaf {
                    SectionKind::LEAF_LEVEL
                } else {
                    SectionKind::NODE_LEVEL
                },
                level: i as u8,
                pointer_width: if leaf { 0 } else { 1 },
                reserved0: 0,
                offset,
                length: sec.len() as u64,
                item_count: 1,
                crc: crc32c::crc32c(sec),
                reserved1: 0,
            };
            let at = HEADER_SIZE + i * SECTION_ENTRY_SIZE;
            file[at..at + SECTION_ENTRY_SIZE].copy_from_slice(bytemuck::bytes_of(&entry));
            file.extend_from_slice(sec);
            offset += sec.len() as u64;
        }
        let mut header: RawHeader = bytemuck::Zeroable::zeroed();
        header.magic = MAGIC;
        header.version_major = layout::VERSION_MAJOR;
        header.header_size = HEADER_SIZE as u32;
        header.depth = depth;
        header.attribute_kind = 1;
        header.section_count = levels as u16;
        header.root_size = 1.0f64.to_bits();
        header.file_size = file.len() as u64;
        header.voxel_count = 1u64 << 63;
        file[..HEADER_SIZE].copy_from_slice(bytemuck::bytes_of(&header));
        let head: [u8; HEADER_SIZE] = file[..HEADER_SIZE].try_into().unwrap();
        let crc = layout::header_checksum(&head, &file[HEADER_SIZE..table_end]);
        file[layout::HEADER_CRC_OFFSET..HEADER_SIZE].copy_from_slice(&crc.to_le_bytes());
        file
    }

    #[test]
    fn saturated_counts_are_summed_in_linear_time() {
        let bytes = full_volume_depth_21();
        let dag = Dag::open(&bytes).unwrap();
        assert_eq!(
            dag.subtree_voxel_count(NodeRef {
                level: 0,
                pointer: 0
            })
            .unwrap(),
            1 << 63
        );
        let last = (1u32 << 21) - 1;
        // Without memoisation this walks 8^19 paths and never finishes.
        assert_eq!(
            dag.voxel_index(last, last, last).unwrap(),
            Some((1u64 << 63) - 1)
        );
        assert_eq!(dag.voxel_index(1, 0, 0).unwrap(), Some(1));
    }
}
