//! The on-disk layout of a `.vdag` file: constants and fixed-size records.
//!
//! This module is the single source of truth for byte positions; spec/VDAG.md
//! describes the same layout in prose and every size here is pinned by a
//! compile-time assertion so that a field added by mistake cannot silently move
//! another one.
//!
//! All multi-byte integers and floats are little-endian. The raw records are
//! `#[repr(C)]` with no implicit padding and are read with
//! [`bytemuck::pod_read_unaligned`], so they work on any byte slice whatever its
//! alignment; their fields hold the little-endian bit patterns and the `decode`
//! functions convert them.

use bytemuck::{Pod, Zeroable};

/// The eight bytes every `.vdag` file starts with.
///
/// Like PNG's signature: a non-ASCII first byte catches 7-bit transfers, the
/// CR LF pair catches line-ending conversion and 0x1A stops `type` on DOS.
pub const MAGIC: [u8; 8] = *b"\x89VDAG\r\n\x1a";

/// Major version written by this library. Readers reject any other major version.
pub const VERSION_MAJOR: u16 = 1;
/// Major version of format 2.0 (spec §23): symmetry-aware records with
/// bit-packed references. Read by [`crate::AnyDag`], written by [`crate::v2file`].
pub const VERSION_MAJOR_2: u16 = 2;
/// Minor version written by this library. Readers accept any minor version of
/// their major version: minor versions only add optional features and sections.
pub const VERSION_MINOR: u16 = 0;
/// The minor version of a file holding a PACKED_COLORS section (kind 4, added
/// in format 1.1); files without one stay [`VERSION_MINOR`].
pub const VERSION_MINOR_PACKED_COLORS: u16 = 1;
/// The minor version of a file whose PACKED_COLORS section uses blocks of 128
/// or 256 colours or split sub-blocks (format 1.2).
pub const VERSION_MINOR_SPLIT_COLORS: u16 = 2;

/// Size in bytes of the fixed file header.
pub const HEADER_SIZE: usize = 128;
/// Size in bytes of one section table entry.
pub const SECTION_ENTRY_SIZE: usize = 40;
/// Byte offset of the header checksum field.
pub const HEADER_CRC_OFFSET: usize = 124;

/// Every section starts at a multiple of this many bytes (so that 64-bit leaf
/// masks are naturally aligned in a memory map). The bytes between two sections
/// are zero.
pub const SECTION_ALIGN: u64 = 8;

/// Node records inside a node-level section start at multiples of this many
/// bytes, so a GPU can fetch headers and pointers with 32-bit loads.
pub const NODE_ALIGN: u64 = 4;

/// Smallest depth a file may have: the root is then a single 4³ leaf brick.
pub const MIN_DEPTH: u8 = 2;
/// Largest depth a file may have. At depth 21 a full volume holds 2^63 voxels,
/// the most a 64-bit voxel count (and a 63-bit Morton code) can express.
pub const MAX_DEPTH: u8 = 21;

/// Most sections a file may declare: one per level plus optional sections.
pub const MAX_SECTIONS: u16 = 64;
/// Largest file a reader accepts (1 TiB).
pub const MAX_FILE_SIZE: u64 = 1 << 40;
/// Largest node-level section: word offsets of up to 4 bytes address 2^32 words.
pub const MAX_NODE_LEVEL_BYTES: u64 = 4 << 32;
/// Most leaves in the leaf level: leaf indices of up to 4 bytes address 2^32 leaves.
pub const MAX_LEAF_COUNT: u64 = 1 << 32;

/// Number of bits of the node header word that hold the child mask.
pub const CHILD_MASK_BITS: u32 = 8;
/// Mask of the attribute field once shifted down by [`CHILD_MASK_BITS`].
pub const ATTRIBUTE_MAX: u32 = 0x00FF_FFFF;
/// Stored in the attribute field of kind [`AttributeKind::VoxelCount`] when the
/// subtree holds `ATTRIBUTE_MAX` voxels or more; readers then sum the children.
pub const COUNT_SATURATED: u32 = ATTRIBUTE_MAX;

/// Required feature bits defined by this version (none). A reader rejects a
/// file that sets any required bit it does not know.
pub const KNOWN_REQUIRED_FEATURES: u32 = 0;
/// Optional feature bits defined by this version (none). Readers ignore unknown ones.
pub const KNOWN_OPTIONAL_FEATURES: u32 = 0;

/// Section kinds whose top bit is set are optional: readers that do not know
/// them skip them (their bytes are still covered by their checksum).
pub const SECTION_KIND_OPTIONAL_BIT: u32 = 0x8000_0000;

/// What a section holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum SectionKind {
    /// Node records of one interior level (levels `0 ..= depth - 3`).
    NodeLevel,
    /// The deduplicated 64-bit 4³ leaf masks (level `depth - 2`).
    LeafLevel,
    /// One RGBA8 colour per voxel, in dense voxel-index order (needs attribute
    /// kind [`AttributeKind::VoxelCount`]).
    VoxelColors,
    /// The voxel colours in compressed blocks with a directory
    /// ([`crate::packed_colors`]; needs attribute kind
    /// [`AttributeKind::VoxelCount`]).
    PackedColors,
    /// A kind this version does not define, with the optional bit set; skipped.
    UnknownOptional(u32),
}

impl SectionKind {
    /// The raw value of a node-level section.
    pub const NODE_LEVEL: u32 = 1;
    /// The raw value of the leaf-level section.
    pub const LEAF_LEVEL: u32 = 2;
    /// The raw value of the voxel colour section.
    pub const VOXEL_COLORS: u32 = 3;
    /// The raw value of the packed colour section.
    pub const PACKED_COLORS: u32 = 4;

    /// Interprets a raw kind; `None` for an unknown required kind.
    pub fn from_raw(raw: u32) -> Option<Self> {
        match raw {
            Self::NODE_LEVEL => Some(Self::NodeLevel),
            Self::LEAF_LEVEL => Some(Self::LeafLevel),
            Self::VOXEL_COLORS => Some(Self::VoxelColors),
            Self::PACKED_COLORS => Some(Self::PackedColors),
            r if r & SECTION_KIND_OPTIONAL_BIT != 0 => Some(Self::UnknownOptional(r)),
            _ => None,
        }
    }

    /// The raw value written to disk.
    pub fn to_raw(self) -> u32 {
        match self {
            Self::NodeLevel => Self::NODE_LEVEL,
            Self::LeafLevel => Self::LEAF_LEVEL,
            Self::VoxelColors => Self::VOXEL_COLORS,
            Self::PackedColors => Self::PACKED_COLORS,
            Self::UnknownOptional(r) => r,
        }
    }
}

/// What the 24 attribute bits of every node header mean (the attribute registry).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub enum AttributeKind {
    /// Kind 0: no attribute; the 24 bits are zero.
    None,
    /// Kind 1: the number of set voxels in the node's subtree, saturated at
    /// [`COUNT_SATURATED`]. Turns a voxel's path into a dense index.
    #[default]
    VoxelCount,
}

impl AttributeKind {
    /// Interprets a raw kind; `None` for a kind this version does not define.
    pub fn from_raw(raw: u8) -> Option<Self> {
        match raw {
            0 => Some(Self::None),
            1 => Some(Self::VoxelCount),
            _ => None,
        }
    }

    /// The raw value written to disk.
    pub fn to_raw(self) -> u8 {
        match self {
            Self::None => 0,
            Self::VoxelCount => 1,
        }
    }
}

/// The fixed 128-byte file header exactly as stored (little-endian fields).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct RawHeader {
    /// [`MAGIC`].
    pub magic: [u8; 8],
    /// [`VERSION_MAJOR`].
    pub version_major: u16,
    /// [`VERSION_MINOR`].
    pub version_minor: u16,
    /// [`HEADER_SIZE`]; the section table starts here.
    pub header_size: u32,
    /// Feature bits a reader must understand.
    pub required_features: u32,
    /// Feature bits a reader may ignore.
    pub optional_features: u32,
    /// Depth D: the volume is 2^D voxels along each axis.
    pub depth: u8,
    /// [`AttributeKind`] of the 24 attribute bits.
    pub attribute_kind: u8,
    /// Number of entries in the section table.
    pub section_count: u16,
    /// Zero.
    pub reserved0: u32,
    /// World-space minimum corner of the root cube (x, y, z), as f64 bit patterns.
    pub root_min: [u64; 3],
    /// World-space edge length of the root cube, as an f64 bit pattern.
    pub root_size: u64,
    /// Total length of the file in bytes.
    pub file_size: u64,
    /// Total number of set voxels.
    pub voxel_count: u64,
    /// Zero.
    pub reserved1: [u8; 44],
    /// CRC-32C of bytes `0..124` followed by the whole section table.
    pub header_crc: u32,
}

/// One entry of the section table exactly as stored (little-endian fields).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct RawSectionEntry {
    /// Raw [`SectionKind`].
    pub kind: u32,
    /// Level of a node-level or leaf-level section; zero otherwise.
    pub level: u8,
    /// Pointer width in bytes (1 to 4) of a node-level section; zero otherwise.
    pub pointer_width: u8,
    /// Zero.
    pub reserved0: u16,
    /// Byte offset of the section from the start of the file.
    pub offset: u64,
    /// Length of the section in bytes.
    pub length: u64,
    /// Nodes, leaves or colours in the section.
    pub item_count: u64,
    /// CRC-32C of the section's bytes.
    pub crc: u32,
    /// Zero.
    pub reserved1: u32,
}

const _: () = assert!(size_of::<RawHeader>() == HEADER_SIZE);
const _: () = assert!(size_of::<RawSectionEntry>() == SECTION_ENTRY_SIZE);
const _: () = assert!(std::mem::offset_of!(RawHeader, header_crc) == HEADER_CRC_OFFSET);
const _: () = assert!(std::mem::offset_of!(RawHeader, root_min) == 32);
const _: () = assert!(std::mem::offset_of!(RawHeader, reserved1) == 80);
const _: () = assert!(std::mem::offset_of!(RawSectionEntry, crc) == 32);

/// Smallest pointer width (bytes, 1 to 4) able to address `units` targets
/// (words of a node level, or leaves of the leaf level): the smallest `w` with
/// `units <= 256^w`. Returns `None` when even 4 bytes are not enough.
pub fn minimal_pointer_width(units: u64) -> Option<u8> {
    (1u8..=4).find(|&w| units <= 1u64 << (8 * u32::from(w)))
}

/// Size in bytes of a node record with `child_count` pointers of `width` bytes:
/// the 4-byte header plus the pointers, padded to [`NODE_ALIGN`].
pub fn node_record_size(child_count: u32, width: u8) -> u64 {
    let pointers = u64::from(child_count) * u64::from(width);
    4 + pointers.div_ceil(NODE_ALIGN) * NODE_ALIGN
}

/// Appends the bytes of one node record (§8) to `out`: the header word
/// `child_mask | attribute << 8`, then one pointer of `width` bytes per child
/// (`children`, in increasing child index order, as many as `child_mask` has
/// bits), then zero padding to [`NODE_ALIGN`]. Every writer of node levels
/// goes through here, so there is one encoding of records.
#[inline]
pub fn encode_node_record(
    child_mask: u8,
    attribute: u32,
    children: &[u32],
    width: u8,
    out: &mut Vec<u8>,
) {
    debug_assert_eq!(children.len() as u32, child_mask.count_ones());
    debug_assert!(attribute <= ATTRIBUTE_MAX);
    debug_assert!((1..=4).contains(&width));
    let header = u32::from(child_mask) | attribute << CHILD_MASK_BITS;
    out.extend_from_slice(&header.to_le_bytes());
    let width = usize::from(width);
    for &child in children {
        out.extend_from_slice(&child.to_le_bytes()[..width]);
    }
    let padding = (4 - (children.len() * width) % 4) % 4;
    out.extend_from_slice(&[0u8; 3][..padding]);
}

/// Rounds `offset` up to the next multiple of [`SECTION_ALIGN`].
pub fn align_section(offset: u64) -> u64 {
    offset.div_ceil(SECTION_ALIGN) * SECTION_ALIGN
}

/// Computes the header checksum: CRC-32C over `header[0..124]` then the table.
pub fn header_checksum(header: &[u8; HEADER_SIZE], section_table: &[u8]) -> u32 {
    let crc = crc32c::crc32c(&header[..HEADER_CRC_OFFSET]);
    crc32c::crc32c_append(crc, section_table)
}

/// Bit index of a voxel inside a 64-bit 4³ leaf mask, from its coordinates
/// within the brick (each 0..4): Morton order, so each 2³ sub-brick is one byte.
#[inline]
pub fn leaf_bit(x: u32, y: u32, z: u32) -> u32 {
    let hi = ((x >> 1) & 1) | (((y >> 1) & 1) << 1) | (((z >> 1) & 1) << 2);
    let lo = (x & 1) | ((y & 1) << 1) | ((z & 1) << 2);
    hi * 8 + lo
}

/// Child index (0..8) of the octant holding the given half along each axis:
/// bit 0 is x, bit 1 is y, bit 2 is z; a set bit means the upper half.
#[inline]
pub fn child_index(x_high: bool, y_high: bool, z_high: bool) -> u32 {
    u32::from(x_high) | (u32::from(y_high) << 1) | (u32::from(z_high) << 2)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn minimal_widths() {
        assert_eq!(minimal_pointer_width(0), Some(1));
        assert_eq!(minimal_pointer_width(256), Some(1));
        assert_eq!(minimal_pointer_width(257), Some(2));
        assert_eq!(minimal_pointer_width(1 << 16), Some(2));
        assert_eq!(minimal_pointer_width((1 << 16) + 1), Some(3));
        assert_eq!(minimal_pointer_width(1 << 32), Some(4));
        assert_eq!(minimal_pointer_width((1 << 32) + 1), None);
    }

    #[test]
    fn record_sizes() {
        assert_eq!(node_record_size(1, 1), 8);
        assert_eq!(node_record_size(4, 1), 8);
        assert_eq!(node_record_size(5, 1), 12);
        assert_eq!(node_record_size(8, 3), 28);
        assert_eq!(node_record_size(8, 4), 36);
    }

    #[test]
    fn leaf_bits_are_morton() {
        // Each 2x2x2 sub-brick occupies one byte.
        let mut seen = 0u64;
        for z in 0..4 {
            for y in 0..4 {
                for x in 0..4 {
                    let b = leaf_bit(x, y, z);
                    assert_eq!(b / 8, child_index(x >= 2, y >= 2, z >= 2));
                    assert_eq!(b % 8, child_index(x & 1 == 1, y & 1 == 1, z & 1 == 1));
                    seen |= 1 << b;
                }
            }
        }
        assert_eq!(seen, u64::MAX);
    }
}
