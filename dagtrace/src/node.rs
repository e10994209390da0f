//! Decoding the stored DAG: the one place of the CPU tracer that knows how a
//! node record, its child references and a leaf mask are laid out (spec §8,
//! §10).
//!
//! Every traversal path reads the DAG through this module: the per-ray walk
//! and the attribute index (`tracer`), the packets (`packet`), the scalar
//! tails of the vector lanes and, in [`lanes`], the few vector operations
//! that the eight- and sixteen-lane steps (`simd`) use to decode the node
//! words they gather. `occupancy_around` and the saturated counts go through
//! the same functions. The WGSL decoder (`gpu/trace.wgsl`) is checked against
//! this module by a test (`gpu::decode_check`).
//!
//! # The interface
//!
//! - [`Level`]: one stored level. [`Level::header`] reads a node's header,
//!   [`child_mask`] and [`attribute`] split it; [`Level::child`] finds the
//!   reference of a child (by its slot in the child mask) and returns a
//!   [`ChildRef`]: where the child is in the next level, and the reflection
//!   the reference carries; [`Level::reference`] reads the `rank`-th stored
//!   reference (to walk all of a node's children); [`Level::leaf`] reads a
//!   leaf mask. The `_or_fault` forms are the traversal's: a read outside the
//!   level records a [`Fault`] and reads as an empty node or leaf.
//! - Leaf masks: [`voxel_bit`], [`sub_brick_mask`], [`voxels_below`].
//!
//! # How format 2.0 plugs in (the plan)
//!
//! Format 2.0 (issue 42) gives each reference a 3-bit reflection `r` (bit 0
//! mirrors x, bit 1 y, bit 2 z) and stores references with variable lengths.
//! The contract shared with the format:
//!
//! - reflections compose by XOR; descending through a reference with
//!   reflection `r` from a node reached with accumulated reflection `R`
//!   reaches the child with `R' = R ^ r`;
//! - in a node reached with `R`, logical child `c` (spec §8.1) is at physical
//!   slot `c ^ R`; in a leaf, logical bit `b` (spec §10) is physical bit
//!   `b ^ (R | R << 3)`;
//! - the attribute index sums the counts of the children at physical slots
//!   `p` with `(p ^ R) < c`, and in a leaf popcounts the mask reflected by
//!   `R` below `b`.
//!
//! What changes, and where:
//!
//! 1. Here: [`Level::child`] and [`Level::reference`] decode the 2.0
//!    reference (its length from its tag, its reflection) instead of
//!    `rank * width`, and fill [`ChildRef::reflection`], which is 0 for every
//!    1.0 file. `Level` gains the per-level reference coding; the vector
//!    forms in [`lanes`] gain the same decoding (or the vector steps hand
//!    2.0 references to the scalar tail, as they already do for references
//!    near a section's end).
//! 2. In the traversal state: the traversal mirrors every ray into the octant
//!    where its direction is positive, and all its node-level lookups
//!    (`CHAIN`, `FIRST`, the child positions) are indexed by that octant,
//!    `neg`, in the *physical* child numbering. A node reached with `R` is
//!    therefore traced exactly like a 1.0 node by a ray whose octant is
//!    `neg ^ R`: the physical slot of logical child `c` seen from the mirrored
//!    frame is `c ^ neg ^ R`. So the walk carries `R` in each stack frame
//!    (`Frame::_pad` is free) and uses `neg ^ R` where it now uses `neg`; a
//!    child's `R` is the frame's `R ^ ChildRef::reflection`. The brick test
//!    likewise uses `neg ^ R` for both of its levels (the sub-brick byte and
//!    the voxel bit inside it are each indexed by three axis bits, so
//!    reflecting both is `b ^ (R | R << 3)`).
//! 3. In the attribute index (`Tracer::index_from`) and
//!    `Tracer::occupancy_around`: the logical child of the cell's path is
//!    `c`, the physical slot `c ^ R`; the earlier siblings are the physical
//!    slots `p` with `p ^ R < c` (no longer a prefix of the mask), and the
//!    leaf's rank is [`voxels_below`] of the reflected mask.
//!
//! The accumulated reflection is not carried yet: a 1.0 file has none, and
//! carrying it belongs with the code that reads 2.0 references, so that it
//! is tested against real mirrored subtrees rather than left as an
//! untested path.

use dagfmt::layout::{CHILD_MASK_BITS, leaf_bit};

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

/// One stored level: its bytes and pointer width.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Level<'a> {
    pub(crate) bytes: &'a [u8],
    /// The file from the section's first byte to its end (`bytes` when the
    /// section is not inside the file's bytes): where the vector lanes may
    /// load 32 bits past the end of a short pointer at the end of the section,
    /// masking the bytes that follow it away.
    pub(crate) readable: &'a [u8],
    pub(crate) file_offset: u64,
    /// Pointer width in bytes (node levels).
    pub(crate) width: u32,
    /// Mask keeping the low `width` bytes of a 32-bit load.
    pointer_mask: u32,
}

impl<'a> Level<'a> {
    /// The level `section` of the file whose bytes are `file`.
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
        let at = word as usize * HEADER_BYTES as usize;
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
        self.reference(level, word, child_rank(mask, child))
    }

    /// [`Level::header`] for the traversal: an out-of-range read records the
    /// fault (the first one) and reads as 0, a node without children, which
    /// ends that branch; the caller reports the fault when it is done. This
    /// keeps `Result` plumbing out of the inner loop.
    #[inline(always)]
    pub(crate) fn header_or_fault(&self, level: u8, word: u32, fault: &mut Option<Fault>) -> u32 {
        match self.read_u32(word as usize * HEADER_BYTES as usize) {
            Some(v) => v,
            None => record(
                fault,
                Fault {
                    level,
                    at: u64::from(word) * u64::from(HEADER_BYTES),
                    truncated: false,
                },
            ),
        }
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
        match self.read_u32(self.reference_at(word, rank)) {
            Some(v) => ChildRef {
                node: v & self.pointer_mask,
                reflection: 0,
            },
            None => self.reference_near_end(level, word, rank, fault),
        }
    }

    /// [`Level::child`] for the traversal (see [`Level::header_or_fault`]).
    #[inline(always)]
    pub(crate) fn child_or_fault(
        &self,
        level: u8,
        word: u32,
        mask: u8,
        child: u32,
        fault: &mut Option<Fault>,
    ) -> ChildRef {
        self.reference_or_fault(level, word, child_rank(mask, child), fault)
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
                assert_eq!(level.header_or_fault(3, *word, &mut fault), header);
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
                        level.child_or_fault(3, *word, *mask, child, &mut fault),
                        expected
                    );
                }
                assert!(fault.is_none());
            }
            // Reads past the end fault, and the traversal's forms read 0.
            let end = (bytes.len() / 4) as u32;
            assert!(level.header(3, end).is_err());
            let mut fault = None;
            assert_eq!(level.header_or_fault(3, end, &mut fault), 0);
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
