//! Decoding the stored DAG: the one place of the CPU tracer that knows how a
//! node record, its child references and a leaf mask are laid out (spec §8,
//! §10).
//!
//! Every traversal path reads the DAG through this module: the per-ray walk
//! and the attribute index (`walk`), the packets (`packet`), the scalar
//! tails of the vector lanes and, in [`lanes`], the few vector operations
//! that the eight- and sixteen-lane steps (`simd`) use to decode the node
//! words they gather. `occupancy_around` and the saturated counts go through
//! the same functions. The WGSL decoder (`gpu/trace.wgsl`) is checked against
//! this module by a test (`gpu::decode_check`).
//!
//! # The interface
//!
//! - [`Level`]: one stored level, of a 1.0 file ([`Level::new`]), of a 2.0
//!   DAG read in place ([`Level::new_v2`]), or of a 2.0 DAG's expanded levels
//!   ([`Level::new_expanded`], [`Level::new_leaves`]; see below). [`Level::header`] reads a node's header,
//!   [`child_mask`] and [`attribute`] split it; [`Level::child`] finds the
//!   reference of a child (by its *physical* slot in the child mask) and
//!   returns a [`ChildRef`]: the child's address in the next level, and the
//!   reflection the reference carries; [`Level::reference`] reads the
//!   `rank`-th stored reference (to walk all of a node's children);
//!   [`Level::leaf`] reads a leaf mask. The `_or_fault` forms are the
//!   traversal's: a read outside the level records a [`Fault`] and reads as
//!   an empty node or leaf.
//! - Leaf masks: [`voxel_bit`], [`sub_brick_mask`], [`voxels_below`];
//!   [`logical_leaf`] reflects a 2.0 leaf's mask.
//!
//! # Format 2.0
//!
//! Format 2.0 (spec §23) gives each reference a 3-bit reflection `r` (bit 0
//! mirrors x, bit 1 y, bit 2 z), stores references bit-packed in three
//! widths per level, and names a node's *sequential* children (stored once,
//! right after each other) by one base reference. A node's address is its
//! byte offset (records are unaligned), a 1.0 node's its word offset.
//! [`Level::child`] decodes a 2.0 reference through `dagfmt::v2::Coding`,
//! the one decoder of 2.0 records (dagfmt's `decode_node` reads through it
//! too); a sequential child of an interior level is the `j`-th record start
//! after its base in the child level's [`RecordStarts`] (an index made when
//! the tracer is made), or, where that index does not answer (a malformed
//! level), found by adding the sizes of its sequential siblings before it,
//! read from their headers and codes in the child level. [`ChildRef::reflection`] is 0 for every 1.0
//! file.
//!
//! # Expanded 2.0 levels
//!
//! A tracer of a 2.0 DAG normally traces its *expanded* node levels (spec
//! §23.12, `dagfmt::expand::expand_levels`, made once when the tracer is
//! made, held by the tracer with a copy of the leaf level in one
//! allocation): one aligned 32-bit word per header and per child, the child
//! of rank k of a node being the word `index << 3 | r` at its byte offset
//! `4 + 4k`. [`Level::new_expanded`] keeps 2.0's addressing (a node's
//! address is its header's byte offset, so that every `V2` path runs
//! unchanged) and decodes a reference as `index << 2` (a record's byte
//! offset in the expanded child level) or `index` (a leaf), with its
//! reflection `r`: one load where the in-place decoding takes popcounts,
//! unaligned bit reads and, for a sequential child, the record starts.
//! [`Level::child_or_fault`], [`Level::child`] and [`Level::reference`]
//! read either form; [`lanes`]' `expanded_reference_at` and
//! `expanded_child` are the vector lanes' forms. Levels that do not expand
//! (malformed ones) are read in place, reporting what they meet as before.
//!
//! The traversal contract (spec §23.4, §23.5):
//!
//! - reflections compose by XOR; descending through a reference with
//!   reflection `r` from a node reached with accumulated reflection `R`
//!   reaches the child with `R' = R ^ r`;
//! - in a node reached with `R`, logical child `c` (spec §8.1) is at physical
//!   slot `c ^ R`; in a leaf, logical bit `b` (spec §10) is physical bit
//!   `b ^ (R | R << 3)`;
//! - the attribute index sums the counts of the children at physical slots
//!   `p` with `(p ^ R) < c` ([`SIBLINGS_BEFORE`]), and in a leaf popcounts
//!   the mask reflected by `R` ([`logical_leaf`]) below `b`.
//!
//! How the tracer follows it:
//!
//! 1. The traversal (`walk`) mirrors every ray into the octant where its
//!    direction is positive, and all its node-level lookups (`CHAIN`,
//!    `FIRST`, the child positions) are indexed by that octant, `neg`, in
//!    the physical child numbering. A node reached with `R` is therefore
//!    traced exactly like a 1.0 node by a ray whose octant is `neg ^ R`: the
//!    physical slot of logical child `c` seen from the mirrored frame is
//!    `c ^ neg ^ R`. So each stack frame (`Frame::reflection`) and the walk's
//!    next target (`Walk::reflection`) carry `R`, the walk uses `neg ^ R`
//!    where 1.0 used `neg`, and a child's `R` is its parent's `R ^
//!    ChildRef::reflection`. The brick test likewise uses `neg ^ R` for both
//!    of its levels (the sub-brick byte and the voxel bit inside it are each
//!    indexed by three axis bits, so reflecting both is `b ^ (R | R << 3)`).
//!    In 1.0, `R` is 0 everywhere.
//! 2. The attribute index (`Tracer::index_from`), `Tracer::occupancy_around`
//!    (through `Tracer::lookup`), the occupied box and the saturated counts
//!    take the logical child `c` of the cell's path at physical slot `c ^
//!    R`, the earlier siblings from [`SIBLINGS_BEFORE`], and the leaf's rank
//!    from [`voxels_below`] of [`logical_leaf`].
//! 3. The eight vector lanes (`simd::step` with `V2`) keep each lane's R
//!    (`Group::reflection`, and `target_reflection` for the node it goes
//!    to), store it in the frame's last byte and trace in octant `neg ^ R`
//!    as the walk does; they decode a 2.0 reference with [`lanes::Avx2`]'s
//!    forms of [`Coding`]'s steps (`v2_codes`, `v2_child`, `v2_value`,
//!    `v2_size`: the 32 bits after a header gathered for the codes, the 64
//!    bits of the reference gathered, the sizes of a sequential child's
//!    siblings added one sibling a round), and leave to
//!    [`Level::child_or_fault`] the references whose words lie within
//!    eight bytes of their section's end or whose value passes 32 bits.
//!    A sequential child of a node level comes from the child level's
//!    [`RecordStarts`] (spec §23.8), built when the tracer is made. The
//!    sixteen lanes decode 2.0 references with the same eight-lane forms,
//!    on each half of their lanes.
//!    Through expanded levels, both take the child's word with one gather
//!    (`simd::expanded_reference`, [`lanes::Avx2::expanded_child`], and
//!    [`lanes::Avx512`]'s forms for the sixteen lanes).
//!    The packets (`packet`) carry R in every frame of the beam walk and of
//!    the cells' walks (`BeamFrame`, `BeamCell`, `SubtreeFrame`) and in the
//!    brick test (`Tracer::brick_in_node`), reading references through
//!    [`Level::child`].

use dagfmt::layout::{CHILD_MASK_BITS, leaf_bit};
use dagfmt::v2::{Child, Coding, LevelView};

use crate::tables::POPCOUNT8;

/// Bytes of a node header (child mask and attribute), before its references.
pub(crate) const HEADER_BYTES: u32 = 4;

/// Bytes of a leaf mask.
pub(crate) const LEAF_BYTES: u32 = 8;

/// A bounds-check failure inside the traversal: small and `Copy` so that the
/// hot path's `Result` stays cheap; turned into a [`dagfmt::FormatError`] at
/// the API.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Fault {
    pub(crate) level: u8,
    /// Byte offset inside the level section of the read that failed.
    pub(crate) at: u64,
    /// Whether a node record (header or pointers) was cut by the section end,
    /// as opposed to a pointer to a record outside the section.
    pub(crate) truncated: bool,
}

/// Keeps the first fault; reads as 0.
#[cold]
pub(crate) fn record(fault: &mut Option<Fault>, f: Fault) -> u32 {
    fault.get_or_insert(f);
    0
}

/// A child's reference: where the child is in the next level (a node's word
/// offset, or a leaf's index on the leaf level) and the reflection the
/// reference carries (see the module docs; always 0 in format 1.0).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct ChildRef {
    pub(crate) node: u32,
    pub(crate) reflection: u8,
}

/// The child mask of a node header.
#[inline(always)]
pub(crate) fn child_mask(header: u32) -> u8 {
    header as u8
}

/// The 24 attribute bits of a node header (the voxel count, for kind 1).
#[inline(always)]
pub(crate) fn attribute(header: u32) -> u32 {
    header >> CHILD_MASK_BITS
}

/// The number of children of `mask` before slot `child` (0..8): the rank of
/// that child's reference among the node's references. (A table lookup:
/// this code is built for the x86-64 baseline, whose `count_ones` is a dozen
/// instructions.)
#[inline(always)]
pub(crate) fn child_rank(mask: u8, child: u32) -> u32 {
    u32::from(POPCOUNT8[usize::from(mask & ((1u8 << (child & 7)) - 1))])
}

/// The number of children of `mask`.
#[inline(always)]
pub(crate) fn child_count(mask: u8) -> u32 {
    u32::from(POPCOUNT8[usize::from(mask)])
}

/// The bit of a leaf mask holding the voxel at brick coordinates `cell & 3`.
#[inline(always)]
pub(crate) fn voxel_bit(cell: [u32; 3]) -> u32 {
    leaf_bit(cell[0] & 3, cell[1] & 3, cell[2] & 3)
}

/// The byte (sub-brick) of a leaf mask holding the 2³ cell `child` (0..8).
#[inline(always)]
pub(crate) fn sub_brick(bits: u64, child: u32) -> u8 {
    (bits >> (8 * (child & 7))) as u8
}

/// Bit `c` set when byte `c` (sub-brick `c`) of a leaf mask is non-zero.
#[inline(always)]
pub(crate) fn sub_brick_mask(bits: u64) -> u8 {
    let mut x = bits;
    x |= x >> 4;
    x |= x >> 2;
    x |= x >> 1;
    x &= 0x0101_0101_0101_0101;
    (x.wrapping_mul(0x0102_0408_1020_4080) >> 56) as u8
}

/// The set bits of a leaf mask below bit `bit` (0..64): the voxels of the
/// brick before it in Morton order.
#[inline(always)]
pub(crate) fn voxels_below(bits: u64, bit: u32) -> u32 {
    (bits & ((1u64 << (bit & 63)) - 1)).count_ones()
}

/// Whether the cell `cell` of a level below the leaf level is occupied in
/// the leaf mask `bits` of its brick: the voxel (`full_depth`, level D) or
/// the 2³ sub-brick (level D-1).
#[inline(always)]
pub(crate) fn brick_cell_occupied(bits: u64, cell: [u32; 3], full_depth: bool) -> bool {
    if full_depth {
        bits >> voxel_bit(cell) & 1 != 0
    } else {
        sub_brick(bits, child_at(cell, 0)) != 0
    }
}

/// Child slot of the path of `cell` taken at coordinate bit `shift`.
#[inline(always)]
pub(crate) fn child_at(cell: [u32; 3], shift: u8) -> u32 {
    let s = u32::from(shift);
    (cell[0] >> s & 1) | (cell[1] >> s & 1) << 1 | (cell[2] >> s & 1) << 2
}

/// One stored level: its bytes and how its references are coded (1.0:
/// pointers of one width; 2.0: the level's [`Coding`] and, for sequential
/// children, the child level's records).
///
/// A node's *address* is its word offset in 1.0 (records are 4-byte
/// aligned) and its byte offset in 2.0 (records are unaligned):
/// `byte = address << address_shift`.
#[derive(Clone, Debug, Default)]
pub(crate) struct Level<'a> {
    pub(crate) bytes: &'a [u8],
    /// The file from the section's first byte to its end (`bytes` when the
    /// section is not inside the file's bytes): where the vector lanes may
    /// load 32 bits past the end of a short pointer at the end of the section,
    /// masking the bytes that follow it away.
    pub(crate) readable: &'a [u8],
    pub(crate) file_offset: u64,
    /// Pointer width in bytes (1.0 node levels; 0 in 2.0).
    pub(crate) width: u32,
    /// Mask keeping the low `width` bytes of a 32-bit load.
    pointer_mask: u32,
    /// Shift from a node's address to its byte offset: 2 in 1.0, 0 in 2.0.
    address_shift: u32,
    /// The 2.0 form of a node level, `None` in 1.0, for leaves and for
    /// expanded levels.
    v2: Option<Coded<'a>>,
    /// An expanded 2.0 node level (spec §23.12, [`Level::new_expanded`]):
    /// `bytes` are its 32-bit words, a node's address is its header's byte
    /// offset (as in 2.0), and a reference word `index << 3 | r` names the
    /// child at address `index << shift`, with `shift` = 2 (a record's
    /// byte offset in the expanded child level) or 0 (a leaf's index).
    /// `None` for every other level.
    expanded: Option<u32>,
}

/// What a 2.0 node level needs to find its children (spec §23.2, §23.3).
#[derive(Clone, Debug)]
struct Coded<'a> {
    coding: Coding,
    /// The level's widths w_1, w_2, w_3 in bits, for the vector lanes.
    widths: [u8; 3],
    /// The child level's records, where sequential children of an interior
    /// child level are found by adding their siblings' sizes; `None` when
    /// the child level is the leaf level (sequential leaf `base + j`).
    next: Option<(&'a [u8], Coding)>,
    /// The index of where the child level's records start, which finds a
    /// sequential child without reading its siblings (`None` with `next`).
    starts: Option<std::sync::Arc<RecordStarts>>,
}

/// The record starts of a 2.0 node level (spec §23.8): bit `b` is set where
/// a record starts at byte `b`, found by following the records' sizes from
/// byte 0, so that the `j`-th sequential child after a base reference is the
/// `j`-th set bit after the base (a few word reads) rather than the sum of
/// its siblings' sizes (a header and codes read for each). An index of the
/// file made when the tracer is made (an eighth of the level's bytes), as
/// the GPU tracer makes one at upload; not part of the file.
///
/// On any level it gives what the sum gives, or nothing: [`RecordStarts::nth`]
/// answers only from a base that is a record start of the chain from byte 0,
/// and from there the set bits are the very records the sum steps over
/// (each size read from its header and codes); where the chain stops (a
/// record cut by the section's end) no bit follows, and the caller adds the
/// sizes, reporting the fault as it always did.
#[derive(Debug, Default)]
pub(crate) struct RecordStarts {
    words: Box<[u64]>,
}

/// The most bytes of a 2.0 record (spec §23.2: 4 + ceil((18 + 8 · 40) / 8)):
/// no sequential child lies further than seven of them after its base.
const MAX_RECORD_BYTES: u64 = 47;

impl RecordStarts {
    /// The record starts of the level `level` with coding `coding`.
    pub(crate) fn new(level: &[u8], coding: Coding) -> Self {
        let mut words = vec![0u64; level.len().div_ceil(64)];
        let len = level.len() as u64;
        let mut at = 0u64;
        while at < len {
            words[(at / 64) as usize] |= 1 << (at % 64);
            match coding.record_size(level, at) {
                Some(size) => at += size,
                None => break,
            }
        }
        RecordStarts {
            words: words.into_boxed_slice(),
        }
    }

    /// The byte offset of the `index`-th record (from 0) starting at or
    /// after `base`, where `base` is a record start; `None` when it is not,
    /// or the record is not found within the words a valid level needs.
    #[inline]
    pub(crate) fn nth(&self, base: u64, index: u32) -> Option<u64> {
        let mut word = usize::try_from(base / 64).ok()?;
        let mut bits = *self.words.get(word)? >> (base % 64);
        if bits & 1 == 0 {
            return None;
        }
        // The bit position of bit 0 of `bits`. (Clearing the lowest set bit
        // `index` times, at most 7, rather than counting bits: a popcount is
        // a dozen instructions where the code is built for the x86-64
        // baseline.)
        let mut at = base;
        let last = base + MAX_RECORD_BYTES * u64::from(index);
        for _ in 0..index {
            bits &= bits - 1;
            while bits == 0 {
                word += 1;
                at = word as u64 * 64;
                if at > last {
                    return None;
                }
                bits = *self.words.get(word)?;
            }
        }
        Some(at + u64::from(bits.trailing_zeros()))
    }
}

/// `section` and the bytes of `file` after it, where `section` is a part of
/// `file`; else `section` alone.
fn readable_in<'a>(file: &'a [u8], section: &'a [u8]) -> &'a [u8] {
    let start = (section.as_ptr() as usize).wrapping_sub(file.as_ptr() as usize);
    match file.get(start..) {
        Some(rest) if rest.as_ptr() == section.as_ptr() && rest.len() >= section.len() => rest,
        _ => section,
    }
}

impl<'a> Level<'a> {
    /// The level `section` of the 1.0 file whose bytes are `file`.
    pub(crate) fn new(file: &'a [u8], section: &dagfmt::LevelSection<'a>) -> Self {
        let width = u32::from(section.pointer_width);
        // The file from the section's offset on, where that is the section's
        // own memory (the reader hands out sub-slices of the file's bytes).
        let readable = match file.get(section.file_offset as usize..) {
            Some(rest)
                if rest.as_ptr() == section.bytes.as_ptr() && rest.len() >= section.bytes.len() =>
            {
                rest
            }
            _ => section.bytes,
        };
        Level {
            bytes: section.bytes,
            readable,
            file_offset: section.file_offset,
            width,
            pointer_mask: reference_mask(width),
            address_shift: HEADER_BYTES.trailing_zeros(),
            v2: None,
            expanded: None,
        }
    }

    /// Level `this` of a 2.0 DAG (spec §23), whose child level is `next`
    /// (`None` for the leaf level), in the file `file` where the caller has
    /// it (`readable`: the vector lanes may then gather the words of the
    /// records at the section's end from the bytes after it). Fails when a
    /// node level's widths are not a valid coding or its items cannot all be
    /// addressed by the tracer's 32-bit addresses.
    pub(crate) fn new_v2(
        this: &LevelView<'a>,
        next: Option<&LevelView<'a>>,
        file: Option<&'a [u8]>,
    ) -> Result<Self, dagfmt::FormatError> {
        let coding = |v: &LevelView<'a>| -> Result<Coding, dagfmt::FormatError> {
            if v.is_leaf || v.bytes.is_empty() {
                // Leaves, or a node level without records (an empty DAG):
                // nothing is decoded with it.
                return Ok(Coding::default());
            }
            Coding::new(v.widths)
        };
        // Addresses are u32: byte offsets of records, indices of leaves.
        let items = if this.is_leaf {
            this.bytes.len() as u64 / u64::from(LEAF_BYTES)
        } else {
            this.bytes.len() as u64
        };
        if items > u64::from(u32::MAX) {
            return Err(dagfmt::FormatError::new(
                dagfmt::ErrorCode::LevelTooLarge,
                0,
                format!(
                    "a 2.0 level of {} bytes is more than the tracer addresses (4 GiB of records)",
                    this.bytes.len()
                ),
            ));
        }
        let v2 = if this.is_leaf {
            None
        } else {
            let next = match next {
                Some(n) if !n.is_leaf => Some((n.bytes, coding(n)?)),
                _ => None,
            };
            let starts =
                next.map(|(bytes, coding)| std::sync::Arc::new(RecordStarts::new(bytes, coding)));
            Some(Coded {
                coding: coding(this)?,
                widths: this.widths,
                next,
                starts,
            })
        };
        Ok(Level {
            bytes: this.bytes,
            readable: file.map_or(this.bytes, |f| readable_in(f, this.bytes)),
            file_offset: 0,
            width: 0,
            pointer_mask: 0,
            address_shift: 0,
            v2,
            expanded: None,
        })
    }

    /// An expanded 2.0 node level (spec §23.12): `bytes` are the level's
    /// words as `dagfmt::expand::expand_levels` gives them (little-endian),
    /// `readable` the memory from its first byte to the end of the
    /// allocation holding it (where the vector lanes may read past the
    /// section), and `leaf_children` says whether the child level is the
    /// leaf level (a reference's index is then a leaf's index, else the
    /// word index of a record).
    pub(crate) fn new_expanded(bytes: &'a [u8], readable: &'a [u8], leaf_children: bool) -> Self {
        Level {
            bytes,
            readable,
            file_offset: 0,
            width: 4,
            pointer_mask: u32::MAX,
            address_shift: 0,
            v2: None,
            expanded: Some(if leaf_children { 0 } else { 2 }),
        }
    }

    /// The leaf level of a 2.0 DAG traced through expanded node levels: a
    /// copy of the file's leaf masks beside the expanded levels (see
    /// `readable` at [`Level::new_expanded`]).
    pub(crate) fn new_leaves(bytes: &'a [u8], readable: &'a [u8]) -> Self {
        Level {
            bytes,
            readable,
            ..Level::default()
        }
    }

    /// For an expanded 2.0 node level, the shift from a reference's index
    /// to the child's address (see [`Level::new_expanded`]); `None` for
    /// every other level.
    #[inline(always)]
    pub(crate) fn expanded_shift(&self) -> Option<u32> {
        self.expanded
    }

    /// The widths w_1, w_2, w_3 in bits of a 2.0 node level's references
    /// (spec §23.2): what the vector lanes decode with (`lanes::Avx2`);
    /// zeros for a 1.0 level and for leaves.
    pub(crate) fn v2_widths(&self) -> [i32; 3] {
        self.v2.as_ref().map_or([0; 3], |c| c.widths.map(i32::from))
    }

    /// Whether the level is a 2.0 node level, in place or expanded.
    #[inline(always)]
    pub(crate) fn is_v2(&self) -> bool {
        self.v2.is_some() || self.expanded.is_some()
    }

    /// The byte offset in the level of the node at `address`.
    #[inline(always)]
    pub(crate) fn node_byte(&self, address: u32) -> usize {
        (address as usize) << self.address_shift
    }

    /// [`Level::node_byte`] where the caller knows the format: `V2` for a
    /// 2.0 node level, else 1.0 (the walk is compiled once for each, so
    /// that 1.0's copy has no 2.0 tests).
    #[inline(always)]
    pub(crate) fn node_byte_in<const V2: bool>(&self, address: u32) -> usize {
        if V2 {
            address as usize
        } else {
            address as usize * HEADER_BYTES as usize
        }
    }

    /// [`Level::header`] for the traversal: an out-of-range read records the
    /// fault (the first one) and reads as 0, a node without children, which
    /// ends that branch; the caller reports the fault when it is done. This
    /// keeps `Result` plumbing out of the inner loop.
    /// `V2`: whether the level is 2.0 (see [`Level::node_byte_in`]).
    #[inline(always)]
    pub(crate) fn header_or_fault<const V2: bool>(
        &self,
        level: u8,
        word: u32,
        fault: &mut Option<Fault>,
    ) -> u32 {
        let at = self.node_byte_in::<V2>(word);
        match self.read_u32(at) {
            Some(v) => v,
            None => record(
                fault,
                Fault {
                    level,
                    at: at as u64,
                    truncated: false,
                },
            ),
        }
    }

    /// [`Level::child`] for the traversal (see [`Level::header_or_fault`]);
    /// `V2`: whether the level is 2.0 (see [`Level::node_byte_in`]).
    #[inline(always)]
    pub(crate) fn child_or_fault<const V2: bool>(
        &self,
        level: u8,
        word: u32,
        mask: u8,
        child: u32,
        fault: &mut Option<Fault>,
    ) -> ChildRef {
        if V2 {
            if let Some(shift) = self.expanded {
                // One aligned load (spec §23.12).
                return match self.expanded_reference(level, word, child_rank(mask, child), shift) {
                    Ok(v) => v,
                    Err(f) => ChildRef {
                        node: record(fault, f),
                        reflection: 0,
                    },
                };
            }
            match self.child_v2(level, word, child) {
                Ok(v) => v,
                Err(f) => ChildRef {
                    node: record(fault, f),
                    reflection: 0,
                },
            }
        } else {
            match self.read_u32(self.reference_at(word, child_rank(mask, child))) {
                Some(v) => ChildRef {
                    node: v & self.pointer_mask,
                    reflection: 0,
                },
                None => self.reference_near_end(level, word, child_rank(mask, child), fault),
            }
        }
    }

    #[inline(always)]
    fn read_u32(&self, at: usize) -> Option<u32> {
        match self.bytes.get(at..at + 4) {
            Some(&[a, b, c, d]) => Some(u32::from_le_bytes([a, b, c, d])),
            _ => None,
        }
    }

    /// Byte offset in the level of reference number `rank` of the node at `word`.
    #[inline(always)]
    fn reference_at(&self, word: u32, rank: u32) -> usize {
        word as usize * HEADER_BYTES as usize + HEADER_BYTES as usize + (rank * self.width) as usize
    }

    /// The header word of the node at `word`.
    #[inline(always)]
    pub(crate) fn header(&self, level: u8, word: u32) -> Result<u32, Fault> {
        let at = self.node_byte(word);
        self.read_u32(at).ok_or(Fault {
            level,
            at: at as u64,
            truncated: false,
        })
    }

    /// Reference number `rank` (counting the node's children from slot 0) of
    /// the node at `word`.
    #[inline(always)]
    pub(crate) fn reference(&self, level: u8, word: u32, rank: u32) -> Result<ChildRef, Fault> {
        if let Some(shift) = self.expanded {
            return self.expanded_reference(level, word, rank, shift);
        }
        if self.is_v2() {
            let mask = child_mask(self.header(level, word)?);
            return self.child_v2(level, word, nth_slot(mask, rank));
        }
        let at = self.reference_at(word, rank);
        // Fast path: one 32-bit load, masked to the pointer width. The bytes
        // after the pointer belong to the same record's padding or to the next
        // record and are masked away.
        if let Some(v) = self.read_u32(at) {
            return Ok(ChildRef {
                node: v & self.pointer_mask,
                reflection: 0,
            });
        }
        // Near the end of the section: assemble the pointer byte by byte.
        let bytes = self.bytes.get(at..at + self.width as usize).ok_or(Fault {
            level,
            at: at as u64,
            truncated: true,
        })?;
        Ok(ChildRef {
            node: bytes.iter().rev().fold(0u32, |v, &b| v << 8 | u32::from(b)),
            reflection: 0,
        })
    }

    /// The reference of the child at slot `child` (0..8, set in `mask`) of
    /// the node at `word`, whose child mask is `mask`.
    #[inline(always)]
    pub(crate) fn child(
        &self,
        level: u8,
        word: u32,
        mask: u8,
        child: u32,
    ) -> Result<ChildRef, Fault> {
        if let Some(shift) = self.expanded {
            return self.expanded_reference(level, word, child_rank(mask, child), shift);
        }
        if self.is_v2() {
            return self.child_v2(level, word, child);
        }
        self.reference(level, word, child_rank(mask, child))
    }

    /// Reference number `rank` of the node at byte offset `address` of an
    /// expanded level (spec §23.12): the word `index << 3 | r` after the
    /// header, naming the child at `index << shift` (see
    /// [`Level::new_expanded`]).
    #[inline(always)]
    fn expanded_reference(
        &self,
        level: u8,
        address: u32,
        rank: u32,
        shift: u32,
    ) -> Result<ChildRef, Fault> {
        let at = address as usize + (HEADER_BYTES + 4 * rank) as usize;
        match self.read_u32(at) {
            Some(v) => Ok(ChildRef {
                node: (v >> 3) << shift,
                reflection: (v & 7) as u8,
            }),
            // (An expanded level's references all lie in it: only a node
            // address from outside the level gets here.)
            None => Err(Fault {
                level,
                at: u64::from(address),
                truncated: true,
            }),
        }
    }

    /// [`Level::child`] in a 2.0 level: the reference of physical slot
    /// `slot` decoded by [`Coding`]; a sequential child's address is the
    /// base reference's, plus (interior child level) the sizes of the
    /// sequential siblings before it: found in the child level's
    /// [`RecordStarts`], else added up from their headers and codes.
    #[inline(never)]
    fn child_v2(&self, level: u8, address: u32, slot: u32) -> Result<ChildRef, Fault> {
        #[cfg(target_arch = "x86_64")]
        if crate::cpu::available() {
            // SAFETY: `available()` found POPCNT, BMI1/2 and LZCNT.
            return unsafe { self.child_v2_popcnt(level, address, slot) };
        }
        self.child_v2_body(level, address, slot)
    }

    /// [`Level::child_v2`] compiled with the processor's bit-counting
    /// instructions: `Coding`'s popcounts (five to eight a reference) are
    /// one instruction each instead of a dozen (the code is built for the
    /// x86-64 baseline). 2.0 camera rays at depth 12 spent 15 % of their
    /// time in `child_v2` (perf).
    ///
    /// # Safety
    ///
    /// The processor must have POPCNT, BMI1, BMI2 and LZCNT.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "popcnt,bmi1,bmi2,lzcnt")]
    unsafe fn child_v2_popcnt(
        &self,
        level: u8,
        address: u32,
        slot: u32,
    ) -> Result<ChildRef, Fault> {
        self.child_v2_body(level, address, slot)
    }

    /// The body of [`Level::child_v2`], inlined into its two copies.
    #[inline(always)]
    fn child_v2_body(&self, level: u8, address: u32, slot: u32) -> Result<ChildRef, Fault> {
        let Some(coded) = &self.v2 else {
            return Ok(ChildRef::default());
        };
        let offset = u64::from(address);
        let cut = Fault {
            level,
            at: offset,
            truncated: true,
        };
        let codes = coded.coding.codes(self.bytes, offset).ok_or(cut)?;
        let (target, reflection) = match coded.coding.child(self.bytes, offset, &codes, slot) {
            None => return Err(cut),
            Some(Child::Shared { target, reflection }) => (target, reflection),
            Some(Child::Sequential { base, index }) => match coded.next {
                None => (base.saturating_add(u64::from(index)), 0),
                Some((next, coding)) => {
                    let indexed = self.sequential_in_index(base, index);
                    let mut at = indexed.unwrap_or(base);
                    let index = if indexed.is_some() { 0 } else { index };
                    for _ in 0..index {
                        let size = coding.record_size(next, at).ok_or(Fault {
                            level: level + 1,
                            at,
                            truncated: true,
                        })?;
                        at += size;
                    }
                    (at, 0)
                }
            },
        };
        // A target past the 32-bit addresses is past the level too (see
        // `Level::new_v2`): it reads as an address the next read rejects.
        let node = u32::try_from(target).unwrap_or(u32::MAX);
        Ok(ChildRef { node, reflection })
    }

    /// The byte offset of the `index`-th sequential child whose base
    /// reference is `base`, from the child level's [`RecordStarts`] (a 2.0
    /// node level whose child level holds nodes); `None` where the index
    /// does not answer, and the caller adds the siblings' sizes.
    #[inline]
    pub(crate) fn sequential_in_index(&self, base: u64, index: u32) -> Option<u64> {
        self.v2.as_ref()?.starts.as_deref()?.nth(base, index)
    }

    /// [`Level::reference`] for the traversal (see [`Level::header_or_fault`]):
    /// a read outside the level reads as node 0.
    #[inline(always)]
    pub(crate) fn reference_or_fault(
        &self,
        level: u8,
        word: u32,
        rank: u32,
        fault: &mut Option<Fault>,
    ) -> ChildRef {
        if self.is_v2() {
            // (In place or expanded: `reference` reads either.)
            return match self.reference(level, word, rank) {
                Ok(v) => v,
                Err(f) => ChildRef {
                    node: record(fault, f),
                    reflection: 0,
                },
            };
        }
        match self.read_u32(self.reference_at(word, rank)) {
            Some(v) => ChildRef {
                node: v & self.pointer_mask,
                reflection: 0,
            },
            None => self.reference_near_end(level, word, rank, fault),
        }
    }

    /// The rare reference whose 32-bit load would cross the end of the section.
    #[cold]
    #[inline(never)]
    fn reference_near_end(
        &self,
        level: u8,
        word: u32,
        rank: u32,
        fault: &mut Option<Fault>,
    ) -> ChildRef {
        match self.reference(level, word, rank) {
            Ok(v) => v,
            Err(f) => ChildRef {
                node: record(fault, f),
                reflection: 0,
            },
        }
    }

    /// [`Level::leaf`] for the traversal: an out-of-range leaf reads as empty.
    #[inline(always)]
    pub(crate) fn leaf_or_fault(&self, level: u8, index: u32, fault: &mut Option<Fault>) -> u64 {
        match self.leaf(level, index) {
            Ok(v) => v,
            Err(f) => u64::from(record(fault, f)),
        }
    }

    /// The leaf mask at `index` (leaf level).
    #[inline(always)]
    pub(crate) fn leaf(&self, level: u8, index: u32) -> Result<u64, Fault> {
        let at = index as usize * LEAF_BYTES as usize;
        match self.bytes.get(at..at + LEAF_BYTES as usize) {
            Some(&[a, b, c, d, e, f, g, h]) => Ok(u64::from_le_bytes([a, b, c, d, e, f, g, h])),
            _ => Err(Fault {
                level,
                at: at as u64,
                truncated: false,
            }),
        }
    }
}

/// The physical slot of the `rank`-th child (from 0) of `mask`; 8 when
/// `mask` has no more children.
#[inline]
fn nth_slot(mask: u8, rank: u32) -> u32 {
    let mut m = mask;
    for _ in 0..rank {
        m &= m.wrapping_sub(1);
    }
    m.trailing_zeros()
}

/// The leaf mask `bits` of a leaf reached with accumulated reflection `r`
/// as its logical brick: bit `b` is stored bit `b ^ (r | r << 3)` (spec
/// §23.4). The identity for `r` = 0 (every 1.0 leaf).
#[inline(always)]
pub(crate) fn logical_leaf(bits: u64, r: u8) -> u64 {
    if r == 0 {
        bits
    } else {
        dagfmt::symmetry::reflect_leaf(bits, r)
    }
}

/// `SIBLINGS_BEFORE[r][c]`: the physical slots `p` with `p ^ r < c`, the
/// logical siblings before logical child `c` in a node reached with
/// accumulated reflection `r` (spec §23.5). `(1 << c) - 1` for `r` = 0.
pub(crate) static SIBLINGS_BEFORE: [[u8; 8]; 8] = {
    let mut t = [[0u8; 8]; 8];
    let mut r = 0;
    while r < 8 {
        let mut c = 0;
        while c < 8 {
            let mut q = 0;
            while q < c {
                t[r][c] |= 1 << (q ^ r);
                q += 1;
            }
            c += 1;
        }
        r += 1;
    }
    t
};

/// The mask keeping the low `width` bytes (1 to 4) of a 32-bit load.
#[inline]
fn reference_mask(width: u32) -> u32 {
    if width >= 4 {
        u32::MAX
    } else {
        (1u32 << (8 * width)) - 1
    }
}

/// The vector forms of the decoding, for the vector lanes (`simd`): eight
/// lanes to an AVX2 vector ([`lanes::Avx2`]) and sixteen to an AVX-512
/// vector ([`lanes::Avx512`]), each lane decoding what [`Level`] decodes for
/// one ray. The lanes gather the words themselves (from one base pointer,
/// see `simd::Sections`); these functions say what the words mean.
#[cfg(target_arch = "x86_64")]
pub(crate) mod lanes {
    use std::arch::x86_64::*;

    use super::{CHILD_MASK_BITS, HEADER_BYTES, LEAF_BYTES};

    /// Decoding on eight 32-bit lanes.
    pub(crate) struct Avx2;

    /// Decoding on sixteen 32-bit lanes.
    pub(crate) struct Avx512;

    const _: () = assert!(HEADER_BYTES == 4 && LEAF_BYTES == 8 && CHILD_MASK_BITS == 8);

    /// Shift from a node's word offset to its header's byte offset.
    pub(crate) const HEADER_SHIFT: i32 = HEADER_BYTES.trailing_zeros() as i32;
    /// Shift from a leaf's index to its mask's byte offset.
    pub(crate) const LEAF_SHIFT: i32 = LEAF_BYTES.trailing_zeros() as i32;

    impl Avx2 {
        /// Each lane's child mask, from its header word.
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(crate) fn child_mask(header: __m256i) -> __m256i {
            _mm256_and_si256(header, _mm256_set1_epi32((1 << CHILD_MASK_BITS) - 1))
        }

        /// Each lane's byte offset in its level of the header of node `word`.
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(crate) fn header_at(word: __m256i) -> __m256i {
            _mm256_slli_epi32::<HEADER_SHIFT>(word)
        }

        /// Each lane's byte offset in its level of reference number `rank`
        /// of node `word`, with references of `width` bytes.
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(crate) fn reference_at(word: __m256i, rank: __m256i, width: __m256i) -> __m256i {
            _mm256_add_epi32(
                _mm256_add_epi32(
                    Self::header_at(word),
                    _mm256_set1_epi32(HEADER_BYTES as i32),
                ),
                _mm256_mullo_epi32(rank, width),
            )
        }

        /// Each lane's mask keeping the low `width` bytes of a 32-bit load:
        /// all of them for width 4 (a shift by 32 gives 0).
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(crate) fn reference_mask(width: __m256i) -> __m256i {
            let one = _mm256_set1_epi32(1);
            _mm256_sub_epi32(_mm256_sllv_epi32(one, _mm256_slli_epi32::<3>(width)), one)
        }

        /// Expanded 2.0 levels (spec §23.12, [`super::Level::new_expanded`]):
        /// each lane's byte offset in its level of reference number `rank`
        /// of the node at byte offset `address`.
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(crate) fn expanded_reference_at(address: __m256i, rank: __m256i) -> __m256i {
            _mm256_add_epi32(
                _mm256_add_epi32(address, _mm256_set1_epi32(HEADER_BYTES as i32)),
                _mm256_slli_epi32::<2>(rank),
            )
        }

        /// Expanded 2.0 levels: each lane's child address and reflection
        /// from its reference word `index << 3 | r`, the address `index <<
        /// shift` (`shift` per lane: 2 for a node, 0 for a leaf).
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(crate) fn expanded_child(reference: __m256i, shift: __m256i) -> (__m256i, __m256i) {
            (
                _mm256_sllv_epi32(_mm256_srli_epi32::<3>(reference), shift),
                _mm256_and_si256(reference, _mm256_set1_epi32(7)),
            )
        }
    }

    /// Bits 0, 2, 4, … of a 2.0 code word: the low bit of each 2-bit code
    /// (as in `dagfmt::v2`'s decoder).
    const LOW_BITS: i32 = 0x5_5555;

    /// Format 2.0 (spec §23.2), what [`super::Level`] decodes through
    /// `dagfmt::v2::Coding`, one record to a lane: the record's codes, the
    /// bit position and width of a child's reference, a record's size. The
    /// lanes gather the words (the 32 bits after a header, the 64 bits
    /// holding a reference) themselves; a lane whose words lie too near the
    /// end of its section is decoded by [`super::Level::child_or_fault`].
    /// The three widths of a level are given per lane, `w[j - 1]` for code
    /// `j`.
    impl Avx2 {
        /// Set bits of each lane (the lanes hold values below 2^24).
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(crate) fn popcount(v: __m256i) -> __m256i {
            let nibbles = _mm256_setr_epi8(
                0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4, 0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3,
                2, 3, 3, 4,
            );
            let low = _mm256_set1_epi8(0x0f);
            let lo = _mm256_shuffle_epi8(nibbles, _mm256_and_si256(v, low));
            let hi = _mm256_shuffle_epi8(nibbles, _mm256_and_si256(_mm256_srli_epi32::<4>(v), low));
            // Per byte, then the bytes of each lane added up (at most 24).
            let bytes = _mm256_add_epi8(lo, hi);
            let sum = _mm256_add_epi8(bytes, _mm256_srli_epi32::<8>(bytes));
            let sum = _mm256_add_epi8(sum, _mm256_srli_epi32::<16>(sum));
            _mm256_and_si256(sum, _mm256_set1_epi32(0xff))
        }

        /// `(1 << bits) - 1` per lane (all ones from 32 bits on).
        #[inline]
        #[target_feature(enable = "avx2")]
        fn low_mask(bits: __m256i) -> __m256i {
            let one = _mm256_set1_epi32(1);
            _mm256_sub_epi32(_mm256_sllv_epi32(one, bits), one)
        }

        /// A record's codes (`Coding::codes`) from its child mask and the
        /// 32 bits that follow its header: the m codes (code i in bits 2i
        /// and 2i + 1, a base code of 0 read as 1) and m.
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(crate) fn v2_codes(mask: __m256i, after: __m256i) -> (__m256i, __m256i) {
            let low_bits = _mm256_set1_epi32(LOW_BITS);
            let k = Self::popcount(mask);
            let two_k = _mm256_slli_epi32::<1>(k);
            let k_codes = _mm256_and_si256(after, Self::low_mask(two_k));
            let shared = Self::popcount(_mm256_and_si256(
                _mm256_or_si256(k_codes, _mm256_srli_epi32::<1>(k_codes)),
                low_bits,
            ));
            // All ones where a code is 0: the record has a base reference.
            let has_base = _mm256_cmpgt_epi32(k, shared);
            let count = _mm256_sub_epi32(k, has_base);
            let mut codes = _mm256_and_si256(after, Self::low_mask(_mm256_slli_epi32::<1>(count)));
            let base_zero = _mm256_and_si256(
                has_base,
                _mm256_cmpeq_epi32(_mm256_srlv_epi32(codes, two_k), _mm256_setzero_si256()),
            );
            codes = _mm256_or_si256(
                codes,
                _mm256_and_si256(base_zero, _mm256_sllv_epi32(_mm256_set1_epi32(1), two_k)),
            );
            (codes, count)
        }

        /// The bits of the references of the codes in `codes`
        /// (`Coding::reference_bits`): `n_1·w_1 + n_2·w_2 + n_3·w_3`.
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(crate) fn v2_reference_bits(codes: __m256i, w: [__m256i; 3]) -> __m256i {
            let low_bits = _mm256_set1_epi32(LOW_BITS);
            let low = _mm256_and_si256(codes, low_bits);
            let high = _mm256_and_si256(_mm256_srli_epi32::<1>(codes), low_bits);
            let n1 = Self::popcount(_mm256_andnot_si256(high, low));
            let n2 = Self::popcount(_mm256_andnot_si256(low, high));
            let n3 = Self::popcount(_mm256_and_si256(low, high));
            _mm256_add_epi32(
                _mm256_add_epi32(_mm256_mullo_epi32(n1, w[0]), _mm256_mullo_epi32(n2, w[1])),
                _mm256_mullo_epi32(n3, w[2]),
            )
        }

        /// Bytes of a record with codes `codes` and `count` of them
        /// (`Coding::size`).
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(crate) fn v2_size(codes: __m256i, count: __m256i, w: [__m256i; 3]) -> __m256i {
            let bits = _mm256_add_epi32(
                _mm256_slli_epi32::<1>(count),
                Self::v2_reference_bits(codes, w),
            );
            _mm256_add_epi32(
                _mm256_set1_epi32(HEADER_BYTES as i32),
                _mm256_srli_epi32::<3>(_mm256_add_epi32(bits, _mm256_set1_epi32(7))),
            )
        }

        /// The width of the references of code `code` (0 for code 0).
        #[inline]
        #[target_feature(enable = "avx2")]
        fn v2_width(code: __m256i, w: [__m256i; 3]) -> __m256i {
            let is = |c: i32| _mm256_cmpeq_epi32(code, _mm256_set1_epi32(c));
            _mm256_or_si256(
                _mm256_or_si256(_mm256_and_si256(is(1), w[0]), _mm256_and_si256(is(2), w[1])),
                _mm256_and_si256(is(3), w[2]),
            )
        }

        /// Where the reference of the child of rank `rank` (among the
        /// record's children, in physical slot order) lies (`Coding::child`):
        /// its bit offset from the end of the header and its width, all ones
        /// where the child is sequential (the reference is then the base
        /// reference), and its index among the sequential children.
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(crate) fn v2_child(
            codes: __m256i,
            count: __m256i,
            mask: __m256i,
            rank: __m256i,
            w: [__m256i; 3],
        ) -> V2Child {
            let three = _mm256_set1_epi32(3);
            let two_rank = _mm256_slli_epi32::<1>(rank);
            let code = _mm256_and_si256(_mm256_srlv_epi32(codes, two_rank), three);
            let before = _mm256_and_si256(codes, Self::low_mask(two_rank));
            let sequential = _mm256_cmpeq_epi32(code, _mm256_setzero_si256());
            let two_k = _mm256_slli_epi32::<1>(Self::popcount(mask));
            let base_code = _mm256_and_si256(_mm256_srlv_epi32(codes, two_k), three);
            // Shared: the references of the codes before it; sequential: the
            // base reference, after those of all the children.
            let prefix = _mm256_blendv_epi8(
                before,
                _mm256_and_si256(codes, Self::low_mask(two_k)),
                sequential,
            );
            let bit = _mm256_add_epi32(
                _mm256_slli_epi32::<1>(count),
                Self::v2_reference_bits(prefix, w),
            );
            let width = Self::v2_width(_mm256_blendv_epi8(code, base_code, sequential), w);
            let shared_before = Self::popcount(_mm256_and_si256(
                _mm256_or_si256(before, _mm256_srli_epi32::<1>(before)),
                _mm256_set1_epi32(LOW_BITS),
            ));
            V2Child {
                bit,
                width,
                sequential,
                index: _mm256_sub_epi32(rank, shared_before),
            }
        }

        /// The `width` (1 ..= 40) bits from bit `shift` (0 ..= 7) of the 64
        /// bits `lo | hi << 32`: the low 32 and the high bits of the value.
        #[inline]
        #[target_feature(enable = "avx2")]
        pub(crate) fn v2_value(
            lo: __m256i,
            hi: __m256i,
            shift: __m256i,
            width: __m256i,
        ) -> (__m256i, __m256i) {
            // (A shift by 32 gives 0: `hi` adds nothing where `shift` is 0.)
            let value_lo = _mm256_or_si256(
                _mm256_srlv_epi32(lo, shift),
                _mm256_sllv_epi32(hi, _mm256_sub_epi32(_mm256_set1_epi32(32), shift)),
            );
            let value_hi = _mm256_srlv_epi32(hi, shift);
            let above = _mm256_max_epi32(
                _mm256_sub_epi32(width, _mm256_set1_epi32(32)),
                _mm256_setzero_si256(),
            );
            (
                _mm256_and_si256(value_lo, Self::low_mask(width)),
                _mm256_and_si256(value_hi, Self::low_mask(above)),
            )
        }
    }

    /// A child's reference as [`Avx2::v2_child`] finds it, per lane.
    pub(crate) struct V2Child {
        /// Bit offset of the reference from the end of the record's header.
        pub(crate) bit: __m256i,
        /// Its width in bits.
        pub(crate) width: __m256i,
        /// All ones where the child is sequential: `bit` and `width` are the
        /// base reference's.
        pub(crate) sequential: __m256i,
        /// A sequential child's index among the record's sequential children.
        pub(crate) index: __m256i,
    }

    impl Avx512 {
        /// [`Avx2::child_mask`] on sixteen lanes.
        #[inline]
        #[target_feature(enable = "avx512f")]
        pub(crate) fn child_mask(header: __m512i) -> __m512i {
            _mm512_and_si512(header, _mm512_set1_epi32((1 << CHILD_MASK_BITS) - 1))
        }

        /// [`Avx2::header_at`] on sixteen lanes.
        #[inline]
        #[target_feature(enable = "avx512f")]
        pub(crate) fn header_at(word: __m512i) -> __m512i {
            _mm512_slli_epi32::<{ HEADER_SHIFT as u32 }>(word)
        }

        /// [`Avx2::reference_at`] on sixteen lanes.
        #[inline]
        #[target_feature(enable = "avx512f")]
        pub(crate) fn reference_at(word: __m512i, rank: __m512i, width: __m512i) -> __m512i {
            _mm512_add_epi32(
                _mm512_add_epi32(
                    Self::header_at(word),
                    _mm512_set1_epi32(HEADER_BYTES as i32),
                ),
                _mm512_mullo_epi32(rank, width),
            )
        }

        /// [`Avx2::reference_mask`] on sixteen lanes.
        #[inline]
        #[target_feature(enable = "avx512f")]
        pub(crate) fn reference_mask(width: __m512i) -> __m512i {
            let one = _mm512_set1_epi32(1);
            _mm512_sub_epi32(_mm512_sllv_epi32(one, _mm512_slli_epi32::<3>(width)), one)
        }

        /// [`Avx2::expanded_reference_at`] on sixteen lanes.
        #[inline]
        #[target_feature(enable = "avx512f")]
        pub(crate) fn expanded_reference_at(address: __m512i, rank: __m512i) -> __m512i {
            _mm512_add_epi32(
                _mm512_add_epi32(address, _mm512_set1_epi32(HEADER_BYTES as i32)),
                _mm512_slli_epi32::<2>(rank),
            )
        }

        /// [`Avx2::expanded_child`] on sixteen lanes.
        #[inline]
        #[target_feature(enable = "avx512f")]
        pub(crate) fn expanded_child(reference: __m512i, shift: __m512i) -> (__m512i, __m512i) {
            (
                _mm512_sllv_epi32(_mm512_srli_epi32::<3>(reference), shift),
                _mm512_and_si512(reference, _mm512_set1_epi32(7)),
            )
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::Rng;
    use dagfmt::Dag;
    use dagfmt::builder::DagBuilder;
    use dagfmt::layout::{AttributeKind, encode_node_record};

    /// A node record: word offset, child mask, attribute, references.
    type Record = (u32, u8, u32, Vec<u32>);

    /// A level of random node records written by dagfmt's encoder (the
    /// independent side), with the records' word offsets and contents.
    fn random_records(rng: &mut Rng, width: u8) -> (Vec<u8>, Vec<Record>) {
        let mut bytes = Vec::new();
        let mut records = Vec::new();
        let limit = if width == 4 {
            u32::MAX
        } else {
            (1 << (8 * width)) - 1
        };
        for _ in 0..200 {
            let mask = (rng.next() % 255 + 1) as u8;
            let attribute = (rng.next() % (1 << 24)) as u32;
            let children: Vec<u32> = (0..mask.count_ones())
                .map(|_| (rng.next() as u32) & limit)
                .collect();
            records.push(((bytes.len() / 4) as u32, mask, attribute, children.clone()));
            encode_node_record(mask, attribute, &children, width, &mut bytes);
        }
        (bytes, records)
    }

    #[test]
    fn nodes_decode_as_dagfmt_encodes_them() {
        let mut rng = Rng(0x0de);
        for width in 1..=4u8 {
            let (bytes, records) = random_records(&mut rng, width);
            // `readable` as long as the section: the last record's references
            // are read byte by byte near the end.
            let section = dagfmt::LevelSection {
                level: 3,
                bytes: &bytes,
                file_offset: 0,
                node_count: records.len() as u64,
                pointer_width: width,
                is_leaf: false,
            };
            let level = Level::new(&bytes, &section);
            for (word, mask, attr, children) in &records {
                let header = level.header(3, *word).unwrap();
                assert_eq!(child_mask(header), *mask);
                assert_eq!(attribute(header), *attr);
                assert_eq!(child_count(*mask) as usize, children.len());
                let mut fault = None;
                assert_eq!(level.header_or_fault::<false>(3, *word, &mut fault), header);
                let slots = (0..8).filter(|c| mask >> c & 1 == 1);
                for (rank, child) in slots.enumerate() {
                    let expected = ChildRef {
                        node: children[rank],
                        reflection: 0,
                    };
                    assert_eq!(child_rank(*mask, child), rank as u32);
                    assert_eq!(level.child(3, *word, *mask, child).unwrap(), expected);
                    assert_eq!(level.reference(3, *word, rank as u32).unwrap(), expected);
                    assert_eq!(
                        level.child_or_fault::<false>(3, *word, *mask, child, &mut fault),
                        expected
                    );
                }
                assert!(fault.is_none());
            }
            // Reads past the end fault, and the traversal's forms read 0.
            let end = (bytes.len() / 4) as u32;
            assert!(level.header(3, end).is_err());
            let mut fault = None;
            assert_eq!(level.header_or_fault::<false>(3, end, &mut fault), 0);
            let f = fault.expect("a fault");
            assert_eq!((f.level, f.at, f.truncated), (3, u64::from(end) * 4, false));
            let mut fault = None;
            assert_eq!(level.reference_or_fault(3, end, 0, &mut fault).node, 0);
            assert!(fault.expect("a fault").truncated);
        }
    }

    #[test]
    fn leaf_helpers_count_like_the_bits() {
        let mut rng = Rng(0x1eaf);
        for _ in 0..200 {
            let bits = rng.next() & rng.next();
            let mut voxels = 0;
            for z in 0..4 {
                for y in 0..4 {
                    for x in 0..4 {
                        let cell = [x, y, z];
                        let bit = voxel_bit(cell);
                        let set = dagfmt::reader::LeafMask(bits).is_set(x, y, z);
                        assert_eq!(brick_cell_occupied(bits, cell, true), set);
                        let below = (0..bit).filter(|b| bits >> b & 1 == 1).count();
                        assert_eq!(voxels_below(bits, bit) as usize, below);
                        voxels += usize::from(set);
                        // The 2³ cell of the level above holding this voxel.
                        let sub = child_at(cell, 1);
                        let any = (0..8).any(|v| bits >> (8 * sub + v) & 1 == 1);
                        assert_eq!(brick_cell_occupied(bits, cell.map(|c| c >> 1), false), any);
                        assert_eq!(sub_brick_mask(bits) >> sub & 1 == 1, any);
                        assert_eq!(sub_brick(bits, sub) != 0, any);
                    }
                }
            }
            assert_eq!(voxels, bits.count_ones() as usize);
        }
    }

    #[test]
    fn sub_brick_mask_gathers_non_zero_bytes() {
        assert_eq!(sub_brick_mask(0), 0);
        assert_eq!(sub_brick_mask(1), 1);
        assert_eq!(sub_brick_mask(0x80), 1);
        assert_eq!(sub_brick_mask(0x8000_0000_0000_0000), 0x80);
        assert_eq!(sub_brick_mask(0x0000_0100_0000_ff00), 0b0010_0010);
        assert_eq!(sub_brick_mask(u64::MAX), 0xff);
    }

    /// The 2.0 encoding of `count` random voxels of a depth-`depth` volume
    /// and of their mirror images along `axis`: shared, reflected subtrees.
    fn mirrored_v2(rng: &mut Rng, depth: u32, count: usize, axis: usize) -> dagfmt::v2::Encoded {
        let side = 1u32 << depth;
        let mut voxels: Vec<[u32; 3]> = (0..count)
            .map(|_| [0; 3].map(|_| (rng.next() % u64::from(side)) as u32))
            .collect();
        let mirrored: Vec<[u32; 3]> = voxels
            .iter()
            .map(|&v| {
                let mut m = v;
                m[axis] = side - 1 - v[axis];
                m
            })
            .collect();
        voxels.extend(mirrored);
        let bytes = DagBuilder::from_voxels(depth as u8, AttributeKind::VoxelCount, voxels)
            .expect("valid voxels")
            .to_bytes();
        dagfmt::v2::encode(&Dag::open(&bytes).unwrap()).unwrap()
    }

    /// The record starts of every interior level of random 2.0 DAGs give
    /// what adding the records' sizes gives (dagfmt's `decode_node`), from
    /// every record and for every count of siblings up to 7, and nothing
    /// from a byte inside a record; in a level cut inside a record they
    /// stop at the cut record.
    #[test]
    fn record_starts_give_the_summed_sizes() {
        let mut rng = Rng(0x57a);
        let mut answered = 0;
        for round in 0..4 {
            let enc = mirrored_v2(&mut rng, 5 + round % 3, 300 << round, 2);
            for view in enc.views().iter().filter(|v| !v.is_leaf) {
                let coding = Coding::new(view.widths).unwrap();
                let starts = RecordStarts::new(view.bytes, coding);
                let mut records = Vec::new();
                let mut at = 0u64;
                while at < view.bytes.len() as u64 {
                    records.push(at);
                    at += u64::from(
                        dagfmt::v2::decode_node(view.bytes, at, view.widths)
                            .unwrap()
                            .size,
                    );
                }
                for (i, &record) in records.iter().enumerate() {
                    for j in 0..8u32 {
                        let expected = records.get(i + j as usize).copied();
                        assert_eq!(
                            starts.nth(record, j),
                            expected,
                            "record {record}, sibling {j}"
                        );
                        answered += usize::from(expected.is_some());
                    }
                    if let Some(&next) = records.get(i + 1) {
                        for inside in record + 1..next {
                            assert_eq!(starts.nth(inside, 0), None);
                        }
                    }
                }
                // Cut inside the last record but one: its start stays, the
                // last record's does not.
                if records.len() >= 2 {
                    let cut_record = records[records.len() - 2];
                    let cut = &view.bytes[..cut_record as usize + 5];
                    let starts = RecordStarts::new(cut, coding);
                    assert_eq!(starts.nth(cut_record, 0), Some(cut_record));
                    assert_eq!(starts.nth(cut_record, 1), None);
                }
            }
        }
        assert!(answered > 1000, "{answered}");
    }

    /// Every reference of the 2.0 encoding of random DAGs read through
    /// [`Level::child`] and [`Level::reference`] as dagfmt's decoder reads it
    /// (`decode_node`, `child_address`), sequential children included.
    #[test]
    fn every_v2_reference_reads_as_dagfmt_decodes_it() {
        let mut rng = Rng(0x2e2);
        let (mut sequential, mut reflected) = (0, 0);
        for round in 0..6 {
            let enc = mirrored_v2(&mut rng, 4 + round % 3, 200 << round, 0);
            let views = enc.views();
            for (l, view) in views.iter().enumerate().filter(|(_, v)| !v.is_leaf) {
                let level = Level::new_v2(view, views.get(l + 1), None).unwrap();
                let next = views[l + 1];
                let child_level = (!next.is_leaf).then_some((next.bytes, next.widths));
                let mut at = 0u64;
                while at < view.bytes.len() as u64 {
                    let node = dagfmt::v2::decode_node(view.bytes, at, view.widths).unwrap();
                    let word = at as u32;
                    let header = level.header(l as u8, word).unwrap();
                    assert_eq!(header, node.header);
                    let mut rank = 0;
                    for slot in 0..8u32 {
                        let Some(child) = node.children[slot as usize] else {
                            continue;
                        };
                        sequential += usize::from(matches!(child, Child::Sequential { .. }));
                        let (target, r) = dagfmt::v2::child_address(child, child_level).unwrap();
                        reflected += usize::from(r != 0);
                        let expected = ChildRef {
                            node: target as u32,
                            reflection: r,
                        };
                        let mask = child_mask(header);
                        assert_eq!(level.child(l as u8, word, mask, slot).unwrap(), expected);
                        assert_eq!(level.reference(l as u8, word, rank).unwrap(), expected);
                        let mut fault = None;
                        assert_eq!(
                            level.child_or_fault::<true>(l as u8, word, mask, slot, &mut fault),
                            expected
                        );
                        assert!(fault.is_none());
                        rank += 1;
                    }
                    at += u64::from(node.size);
                }
            }
        }
        assert!(
            sequential > 0 && reflected > 0,
            "{sequential} sequential, {reflected} reflected"
        );
    }

    /// The vector forms of the 2.0 decoding (`lanes::Avx2`) on every record
    /// and child of the 2.0 encoding of random DAGs, one record to a lane,
    /// against dagfmt's decoder: the codes and size of each record, and for
    /// each child where its reference lies, its width, whether it is
    /// sequential and its index, and the value read from there.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn vector_v2_decoding_reads_as_dagfmt_decodes() {
        use std::arch::x86_64::*;
        if !crate::cpu::available() {
            eprintln!("no AVX2 on this processor: the vector 2.0 decoding was not tested");
            return;
        }
        let lane = |v: __m256i| -> [u32; 8] {
            let mut out = [0u32; 8];
            // SAFETY: a store of eight lanes into eight values.
            unsafe { _mm256_storeu_si256(out.as_mut_ptr().cast(), v) };
            out
        };
        let mut rng = Rng(0x7ec2);
        let (mut shared, mut sequential) = (0, 0);
        for round in 0..6 {
            let enc = mirrored_v2(&mut rng, 5 + round % 3, 300 << round, 1);
            for view in enc.views().iter().filter(|v| !v.is_leaf) {
                let w = view.widths.map(i32::from);
                let mut at = 0u64;
                while at < view.bytes.len() as u64 {
                    let node = dagfmt::v2::decode_node(view.bytes, at, view.widths).unwrap();
                    let mut padded = view.bytes[at as usize..].to_vec();
                    padded.resize(padded.len().max(64), 0);
                    let word = |i: usize| u32::from_le_bytes(padded[i..i + 4].try_into().unwrap());
                    let mask = u32::from(node.child_mask());
                    // SAFETY: AVX2 was found above.
                    let (codes, count, size) = unsafe {
                        let ws = w.map(|w| _mm256_set1_epi32(w));
                        let (codes, count) = lanes::Avx2::v2_codes(
                            _mm256_set1_epi32(mask as i32),
                            _mm256_set1_epi32(word(4) as i32),
                        );
                        (codes, count, lanes::Avx2::v2_size(codes, count, ws))
                    };
                    assert_eq!(lane(size)[0], node.size, "record at {at}");
                    let mut rank = 0;
                    for slot in 0..8 {
                        let Some(child) = node.children[slot] else {
                            continue;
                        };
                        // SAFETY: AVX2 was found above.
                        let c = unsafe {
                            lanes::Avx2::v2_child(
                                codes,
                                count,
                                _mm256_set1_epi32(mask as i32),
                                _mm256_set1_epi32(rank),
                                w.map(|w| _mm256_set1_epi32(w)),
                            )
                        };
                        let bit = lane(c.bit)[0] as usize;
                        let byte = 4 + bit / 8;
                        // SAFETY: AVX2 was found above.
                        let (value, high) = unsafe {
                            lanes::Avx2::v2_value(
                                _mm256_set1_epi32(word(byte) as i32),
                                _mm256_set1_epi32(word(byte + 4) as i32),
                                _mm256_set1_epi32((bit % 8) as i32),
                                c.width,
                            )
                        };
                        let value = u64::from(lane(value)[0]) | u64::from(lane(high)[0]) << 32;
                        let is_sequential = lane(c.sequential)[0] != 0;
                        match child {
                            Child::Shared { target, reflection } => {
                                shared += 1;
                                assert!(!is_sequential);
                                assert_eq!(value, target << 3 | u64::from(reflection));
                            }
                            Child::Sequential { base, index } => {
                                sequential += 1;
                                assert!(is_sequential);
                                assert_eq!(value, base);
                                assert_eq!(lane(c.index)[0], index);
                            }
                        }
                        rank += 1;
                    }
                    at += u64::from(node.size);
                }
            }
        }
        assert!(
            shared > 100 && sequential > 100,
            "{shared} shared, {sequential} sequential"
        );
    }

    /// Every node and leaf of a random DAG read through this module and
    /// through dagfmt's reader (`Dag::node`, `Dag::leaf`).
    #[test]
    fn every_node_of_random_dags_reads_as_dagfmt_reads_it() {
        let mut rng = Rng(0xda9);
        for round in 0..6 {
            let depth = 4 + round % 4;
            let side = 1u64 << depth;
            let voxels: Vec<[u32; 3]> = (0..300 << round)
                .map(|_| [0; 3].map(|_| (rng.next() % side) as u32))
                .collect();
            let bytes = DagBuilder::from_voxels(depth as u8, AttributeKind::VoxelCount, voxels)
                .expect("valid voxels")
                .to_bytes();
            let dag = Dag::open(&bytes).expect("built DAG opens");
            let levels: Vec<Level> = dag.levels().iter().map(|s| Level::new(&bytes, s)).collect();
            let leaf_level = dag.leaf_level();
            let mut pending = vec![(0u8, 0u32)];
            let mut seen = std::collections::HashSet::new();
            while let Some((l, word)) = pending.pop() {
                if !seen.insert((l, word)) {
                    continue;
                }
                if l == leaf_level {
                    let bits = levels[usize::from(l)].leaf(l, word).unwrap();
                    assert_eq!(bits, dag.leaf(word).unwrap().0);
                    continue;
                }
                let node = dag.node(l, word).unwrap();
                let header = levels[usize::from(l)].header(l, word).unwrap();
                assert_eq!(child_mask(header), node.child_mask());
                assert_eq!(attribute(header), node.attribute());
                for child in 0..8 {
                    let Some(pointer) = node.child_pointer(child) else {
                        continue;
                    };
                    let got = levels[usize::from(l)]
                        .child(l, word, child_mask(header), child)
                        .unwrap();
                    assert_eq!(
                        got,
                        ChildRef {
                            node: pointer,
                            reflection: 0
                        }
                    );
                    pending.push((l + 1, pointer));
                }
            }
        }
    }
}
