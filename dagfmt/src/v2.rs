//! Format 2.0 level encoding (spec/VDAG.md §23): the encoder of the
//! level sections from a 1.0 DAG, and [`decode_node`], the one decoder of a
//! 2.0 node record and its references.
//!
//! This module encodes and decodes the *level sections* of §23.2–§23.7 and
//! walks them ([`LevelView`], [`for_each_leaf`], [`voxel_index`]); the file
//! container (header, section table, open checks, the conversions between
//! the versions) is [`crate::v2file`], its validation [`crate::validate`].
//!
//! [`encode`] works level by level: it merges the 1.0 DAG under the
//! reflections ([`crate::symmetry::canonicalize`]), ranks each level's
//! classes by their intrinsic keys bottom-up (§23.6), orders the levels top
//! down (§23.7) and lays them out bottom-up. The result depends only on the
//! voxels (and attributes), not on the 1.0 file's node order.

use crate::error::{ErrorCode, FormatError};
use crate::reader::Dag;
use crate::symmetry::{Group, NodeKey, canonicalize, least_form, reflect_leaf};
use std::collections::HashMap;
use std::ops::ControlFlow;

/// Largest reference width in bits (§23.2).
pub const MAX_WIDTH: u32 = 40;

/// One encoded level section.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct EncodedLevel {
    /// The section bytes: records (interior level) or 64-bit leaf masks.
    pub bytes: Vec<u8>,
    /// The level's widths w_1 ≤ w_2 ≤ w_3 (0, 0, 0 for the leaf level).
    pub widths: [u8; 3],
    /// Records or leaves in the section.
    pub item_count: u64,
    /// Whether this is the leaf level.
    pub is_leaf: bool,
}

impl EncodedLevel {
    /// The level as a borrowed [`LevelView`].
    pub fn view(&self) -> LevelView<'_> {
        LevelView {
            bytes: &self.bytes,
            widths: self.widths,
            item_count: self.item_count,
            is_leaf: self.is_leaf,
        }
    }
}

/// One level of a 2.0 file (or of an [`Encoded`]) as borrowed bytes: the
/// shape of [`EncodedLevel`], which tracers decode with [`decode_node`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LevelView<'a> {
    /// The section bytes: records (interior level) or 64-bit leaf masks.
    pub bytes: &'a [u8],
    /// The level's widths w_1 ≤ w_2 ≤ w_3 (0, 0, 0 for the leaf level).
    pub widths: [u8; 3],
    /// Records or leaves in the section.
    pub item_count: u64,
    /// Whether this is the leaf level.
    pub is_leaf: bool,
}

/// The level sections of a 2.0 file, root first.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Encoded {
    /// Depth D.
    pub depth: u8,
    /// Level sections 0 ..= D − 2.
    pub levels: Vec<EncodedLevel>,
}

impl Encoded {
    /// Bytes of the level sections.
    pub fn level_bytes(&self) -> u64 {
        self.levels.iter().map(|l| l.bytes.len() as u64).sum()
    }
}

/// Where a child of a decoded node is (§23.2, §23.3).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Child {
    /// A shared child: the target (byte offset of a record, or leaf index)
    /// and the reference's reflection.
    Shared {
        /// Byte offset in the child level, or leaf index.
        target: u64,
        /// Reflection r (§23.4).
        reflection: u8,
    },
    /// The `index`-th sequential child (from 0, in physical slot order): it
    /// starts `index` records (or leaves) after the node's base reference;
    /// its reflection is 0.
    Sequential {
        /// The target of the node's base reference.
        base: u64,
        /// Position among the node's sequential children.
        index: u32,
    },
}

/// A decoded 2.0 node record.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Node2 {
    /// The 32-bit header word (child mask by physical slot, attribute).
    pub header: u32,
    /// Size of the record in bytes.
    pub size: u32,
    /// Per physical slot: the child, if present.
    pub children: [Option<Child>; 8],
}

impl Node2 {
    /// The child mask (by physical slot).
    pub fn child_mask(&self) -> u8 {
        self.header as u8
    }

    /// The 24 attribute bits.
    pub fn attribute(&self) -> u32 {
        self.header >> 8
    }
}

fn truncated(at: u64) -> FormatError {
    FormatError::new(
        ErrorCode::TruncatedRecord2,
        at,
        "2.0 node record runs past the end of its level".to_string(),
    )
}

/// Reads `width` (at most 56) bits at bit `bit` of `bytes`, least
/// significant bit first, with one unaligned 64-bit load where 8 bytes are
/// left. `None` when the bits run past the end of `bytes`.
#[inline(always)]
fn bits_at(bytes: &[u8], bit: u64, width: u32) -> Option<u64> {
    debug_assert!(width <= 56);
    let end = bit.checked_add(u64::from(width))?.div_ceil(8);
    if end > bytes.len() as u64 {
        return None;
    }
    let at = (bit / 8) as usize;
    let word = match bytes.get(at..at + 8) {
        Some(b) => u64::from_le_bytes(b.try_into().expect("8 bytes")),
        None => {
            // Within 8 bytes of the end: the missing bytes read as 0, and
            // `end` above keeps them out of the value.
            let rest = bytes.get(at..)?;
            let mut buf = [0u8; 8];
            buf[..rest.len()].copy_from_slice(rest);
            u64::from_le_bytes(buf)
        }
    };
    Some((word >> (bit % 8)) & ((1u64 << width) - 1))
}

/// Bits 0, 2, 4, … of the code word: the low bit of each 2-bit code.
const LOW_BITS: u32 = 0x5_5555;

/// A level's reference coding (§23.2) in the form the decoding uses: the
/// width in bits of the reference of each 2-bit code (code 0: none).
///
/// With [`Coding::codes`], [`Coding::child`] and [`Coding::record_size`] it
/// is the one decoder of 2.0 records: [`decode_node`] and the CPU tracer
/// (`dagtrace`) both read records through it. A reference is found without
/// a loop over the codes before it: the bit offset of a reference is `2m +
/// n_1·w_1 + n_2·w_2 + n_3·w_3` (§23.8), the `n_j` being popcounts of the
/// code word.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Coding {
    width: [u32; 4],
}

/// A record's header word and its 2-bit codes, read by [`Coding::codes`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Codes {
    /// The 32-bit header word (child mask by physical slot, attribute).
    pub header: u32,
    /// The m codes, code i in bits 2i and 2i + 1; no bits above them.
    codes: u32,
    /// m: the number of codes (k, or k + 1 with a base reference).
    count: u32,
}

impl Codes {
    /// The child mask (by physical slot).
    pub fn child_mask(&self) -> u8 {
        self.header as u8
    }
}

impl Coding {
    /// The coding of a level with widths `widths` (w_1, w_2, w_3). Fails when
    /// a width is 0 or above [`MAX_WIDTH`] (E070, §23.10).
    pub fn new(widths: [u8; 3]) -> Result<Self, FormatError> {
        if widths.iter().any(|&w| w == 0 || u32::from(w) > MAX_WIDTH) {
            return Err(FormatError::new(
                ErrorCode::BadWidths,
                0,
                format!("2.0 reference widths {widths:?} are not all in 1..={MAX_WIDTH} bits"),
            ));
        }
        Ok(Coding {
            width: [
                0,
                u32::from(widths[0]),
                u32::from(widths[1]),
                u32::from(widths[2]),
            ],
        })
    }

    /// The bits of the references of the codes in `codes` (a prefix of a
    /// record's code word).
    #[inline(always)]
    fn reference_bits(&self, codes: u32) -> u64 {
        let low = codes & LOW_BITS;
        let high = (codes >> 1) & LOW_BITS;
        u64::from((low & !high).count_ones()) * u64::from(self.width[1])
            + u64::from((high & !low).count_ones()) * u64::from(self.width[2])
            + u64::from((low & high).count_ones()) * u64::from(self.width[3])
    }

    /// The header and codes of the record at byte `offset` of `level`;
    /// `None` when they run past its end.
    #[inline(always)]
    pub fn codes(&self, level: &[u8], offset: u64) -> Option<Codes> {
        let start = usize::try_from(offset).ok()?;
        let header = crate::reader::read_u32(level, start)?;
        let k = (header as u8).count_ones();
        if k == 0 {
            return Some(Codes {
                header,
                codes: 0,
                count: 0,
            });
        }
        // k codes and the base code, if any: at most 18 bits, all within the
        // record (a record of k ≥ 2 shared children has at least 3k bits, one
        // of a single shared child at least a byte).
        let raw = bits_at(level, (offset + 4) * 8, 2 * k + 2)? as u32;
        let k_codes = raw & ((1 << (2 * k)) - 1);
        let shared = ((k_codes | k_codes >> 1) & LOW_BITS).count_ones();
        let count = k + u32::from(shared < k);
        let mut codes = raw & ((1 << (2 * count)) - 1);
        if count > k && codes >> (2 * k) == 0 {
            // The base reference's code is never 0 in a valid record; it
            // reads as code 1 if it is (the validator reports it).
            codes |= 1 << (2 * k);
        }
        Some(Codes {
            header,
            codes,
            count,
        })
    }

    /// Bytes of a record with codes `codes` (§23.2).
    #[inline(always)]
    pub fn size(&self, codes: &Codes) -> u64 {
        4 + (2 * u64::from(codes.count) + self.reference_bits(codes.codes)).div_ceil(8)
    }

    /// Bytes of the record at byte `offset` of `level`, from its header and
    /// codes; `None` when they run past its end.
    #[inline(always)]
    pub fn record_size(&self, level: &[u8], offset: u64) -> Option<u64> {
        Some(self.size(&self.codes(level, offset)?))
    }

    /// The child at physical slot `slot` (0..8, set in the child mask) of the
    /// record at byte `offset` of `level`, whose header and codes are
    /// `codes`; `None` when its reference runs past the end of `level`.
    #[inline(always)]
    pub fn child(&self, level: &[u8], offset: u64, codes: &Codes, slot: u32) -> Option<Child> {
        let mask = u32::from(codes.child_mask());
        let rank = (mask & ((1 << (slot & 7)) - 1)).count_ones();
        let code = (codes.codes >> (2 * rank)) & 3;
        let before = codes.codes & ((1 << (2 * rank)) - 1);
        let stream = (offset + 4) * 8 + 2 * u64::from(codes.count);
        if code != 0 {
            let v = bits_at(
                level,
                stream + self.reference_bits(before),
                self.width[code as usize],
            )?;
            return Some(Child::Shared {
                target: v >> 3,
                reflection: (v & 7) as u8,
            });
        }
        let k = mask.count_ones();
        let child_codes = codes.codes & ((1 << (2 * k)) - 1);
        let base_code = (codes.codes >> (2 * k)) & 3;
        let base = bits_at(
            level,
            stream + self.reference_bits(child_codes),
            self.width[base_code as usize],
        )?;
        let shared_before = ((before | before >> 1) & LOW_BITS).count_ones();
        Some(Child::Sequential {
            base,
            index: rank - shared_before,
        })
    }
}

/// Decodes the node record at byte `offset` of a 2.0 interior level with
/// `widths` (§23.2): its header, its size and each child's reference. Never
/// panics: a record that runs past `level` is an error (E071). Reads through
/// [`Coding`], as the tracer does.
pub fn decode_node(level: &[u8], offset: u64, widths: [u8; 3]) -> Result<Node2, FormatError> {
    let coding = Coding::new(widths).map_err(|e| FormatError::new(e.code, offset, e.message))?;
    let codes = coding
        .codes(level, offset)
        .ok_or_else(|| truncated(offset))?;
    let size = coding.size(&codes);
    if offset.saturating_add(size) > level.len() as u64 {
        return Err(truncated(offset));
    }
    let mut children = [None; 8];
    for (slot, child) in children.iter_mut().enumerate() {
        if codes.child_mask() >> slot & 1 != 0 {
            *child = Some(
                coding
                    .child(level, offset, &codes, slot as u32)
                    .ok_or_else(|| truncated(offset))?,
            );
        }
    }
    Ok(Node2 {
        header: codes.header,
        size: size as u32,
        children,
    })
}

/// The references of the record at byte `offset` of a 2.0 interior level,
/// as stored: per reference — the shared children's in physical slot order,
/// then the base reference — its code (1 ..= 3) and value; and B, the bits
/// of the record's stream (§23.2: codes and references, without the zero
/// bits up to the next byte). For the validator's width and padding rules.
pub fn record_references(
    level: &[u8],
    offset: u64,
    widths: [u8; 3],
) -> Result<(Vec<(u8, u64)>, u64), FormatError> {
    let (_, refs) = decode_node_references(level, offset, widths)?;
    Ok((refs.as_slice().to_vec(), refs.bits))
}

/// A record's references as stored, without an allocation: what
/// [`record_references`] returns.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct References {
    /// Per reference (at most 8 shared ones and a base): code and value;
    /// the first `count` entries are used.
    refs: [(u8, u64); 9],
    /// The references in `refs`.
    count: u8,
    /// B: the bits of the record's stream (codes and references).
    pub bits: u64,
}

impl References {
    /// Code (1 ..= 3) and value of each reference, in stored order.
    pub fn as_slice(&self) -> &[(u8, u64)] {
        &self.refs[..usize::from(self.count)]
    }
}

/// [`decode_node`] and [`record_references`] of one record with one
/// decoding of its header and codes: for the validator's walk, which needs
/// both of every record.
pub fn decode_node_references(
    level: &[u8],
    offset: u64,
    widths: [u8; 3],
) -> Result<(Node2, References), FormatError> {
    let node = decode_node(level, offset, widths)?;
    // decode_node checked that the whole record lies inside `level`.
    let stream = &level[offset as usize + 4..offset as usize + node.size as usize];
    let k = node.child_mask().count_ones() as u64;
    let has_base = node
        .children
        .iter()
        .flatten()
        .any(|c| matches!(c, Child::Sequential { .. }));
    let m = k + u64::from(has_base);
    let mut refs = References::default();
    let mut bit = 2 * m;
    for i in 0..m {
        let code = bits_at(stream, 2 * i, 2).ok_or_else(|| truncated(offset))? as u8;
        if code != 0 {
            let w = u32::from(widths[usize::from(code) - 1]);
            let v = bits_at(stream, bit, w).ok_or_else(|| truncated(offset))?;
            bit += u64::from(w);
            refs.refs[usize::from(refs.count)] = (code, v);
            refs.count += 1;
        }
    }
    refs.bits = bit;
    Ok((node, refs))
}

/// The address of a child found by [`decode_node`] in a child level whose
/// records are `child_level` (`None`: the child level is the leaf level, in
/// which sequential children are `base + index`). In an interior child level
/// a sequential child's offset adds the sizes of the sequential siblings
/// before it (§23.3).
pub fn child_address(
    child: Child,
    child_level: Option<(&[u8], [u8; 3])>,
) -> Result<(u64, u8), FormatError> {
    match child {
        Child::Shared { target, reflection } => Ok((target, reflection)),
        Child::Sequential { base, index } => match child_level {
            None => Ok((base.saturating_add(u64::from(index)), 0)),
            Some((bytes, widths)) => {
                let mut at = base;
                for _ in 0..index {
                    at = at.saturating_add(u64::from(decode_node(bytes, at, widths)?.size));
                }
                Ok((at, 0))
            }
        },
    }
}

/// A class of the merged DAG in intrinsic terms: children as `1 + 8·rank + r`
/// by canonical physical slot (0 = none), and the attribute.
type Key = NodeKey;

/// The least reflection in the coset `t ^ stab` (`stab` a bit set of reflections).
#[inline]
pub(crate) fn norm(t: u8, stab: u8) -> u8 {
    // Most classes have no symmetry: only the identity leaves them unchanged.
    if stab == 1 || stab == 0 {
        return t;
    }
    match NORM[usize::from(stab)].get(usize::from(t)) {
        Some(&least) => least,
        // Not a reflection (t < 8 everywhere in the encoder): as defined.
        None => (0..8u8)
            .filter(|s| stab >> s & 1 != 0)
            .map(|s| t ^ s)
            .min()
            .unwrap_or(t),
    }
}

/// [`norm`] of every non-empty stabiliser (a bit set of reflections) and
/// reflection: one load instead of a loop over the set, in the encoder's
/// inner loops.
static NORM: [[u8; 8]; 256] = norm_table();

const fn norm_table() -> [[u8; 8]; 256] {
    let mut table = [[0u8; 8]; 256];
    let mut stab = 0usize;
    while stab < 256 {
        let mut t = 0u8;
        while t < 8 {
            let mut least = u8::MAX;
            let mut s = 0u8;
            while s < 8 {
                if stab >> s & 1 != 0 && t ^ s < least {
                    least = t ^ s;
                }
                s += 1;
            }
            table[stab][t as usize] = least;
            t += 1;
        }
        stab += 1;
    }
    table
}

/// Reflects a key by `r`: slot p moves to p ^ r, each reference's reflection
/// is XORed with r and normalised in its child's stabiliser.
pub(crate) fn reflect_key(key: &Key, r: u8, child_stab: &[u8]) -> Key {
    reflect_key_in(key, r, &slot_stabs(key, child_stab))
}

/// The stabiliser of the child at each slot of `key` (1 where none is):
/// `child_stab` are the stabilisers of the classes below, by rank.
fn slot_stabs(key: &Key, child_stab: &[u8]) -> [u8; 8] {
    key.slots.map(|s| {
        if s == 0 {
            1
        } else {
            child_stab[((s - 1) >> 3) as usize]
        }
    })
}

/// [`reflect_key`] with the stabiliser of the child at each slot of `key`
/// given (`stabs`), so that no table of the level below is read again.
pub(crate) fn reflect_key_in(key: &Key, r: u8, stabs: &[u8; 8]) -> Key {
    let mut out = Key {
        slots: [0; 8],
        attribute: key.attribute,
    };
    for (p, (&s, &stab)) in key.slots.iter().zip(stabs).enumerate() {
        if s != 0 {
            out.slots[p ^ usize::from(r)] = reflect_slot(s, r, stab);
        }
    }
    out
}

/// Slot value `s` (§23.6, not 0) reflected by `r` and normalised in its
/// child's stabiliser `stab`.
#[inline]
fn reflect_slot(s: u64, r: u8, stab: u8) -> u64 {
    let t = norm(((s - 1) & 7) as u8 ^ r, stab);
    // The rank's bits are kept; only the low 3 (the reflection) change.
    ((s - 1) & !7) + 1 + u64::from(t)
}

/// The least of the 8 reflected forms of `key` (§23.6), with the first
/// reflection reaching it on ties (the same one turns the least form back
/// into `key`) and the symmetry group of the class (the reflections that
/// fix the least form); `child_stab` are the groups of the classes below,
/// by rank. The encoder ([`crate::v2enc`]) and the validator's canonical
/// check ([`crate::canonical2`]) both rank nodes by it.
pub(crate) fn least_reflected_key(key: &Key, child_stab: &[u8]) -> (Key, u8, u8) {
    least_reflected_key_in(key, &slot_stabs(key, child_stab))
}

/// [`least_reflected_key`] with the stabiliser of the child at each slot of
/// `key` given (`stabs`; any value where a slot is empty).
pub(crate) fn least_reflected_key_in(key: &Key, stabs: &[u8; 8]) -> (Key, u8, u8) {
    // Slot j of form r holds the child at slot j ^ r.
    let (best, ties) = least_form(8, |r, j| {
        let p = usize::from(j ^ r);
        let s = key.slots[p];
        if s == 0 {
            return 0;
        }
        reflect_slot(s, r, stabs[p])
    });
    let mut group = 0u8;
    for r in 0..8u8 {
        if ties >> r & 1 != 0 {
            group |= 1 << (r ^ best);
        }
    }
    (reflect_key_in(key, best, stabs), best, group)
}

/// Encodes the level sections of the 2.0 file of `dag`'s voxels (§23), in
/// memory, on the threads of the current rayon pool
/// ([`crate::v2enc::encode_levels`] without a memory budget; the bytes of
/// [`encode_serial`]).
pub fn encode(dag: &Dag<'_>) -> Result<Encoded, FormatError> {
    let unexpected = |e: std::io::Error| {
        FormatError::new(ErrorCode::LevelTooLarge, 0, format!("2.0 encoding: {e}"))
    };
    match crate::v2enc::encode_levels(dag, &crate::v2enc::EncodeOptions::default()) {
        Ok(levels) => levels.into_encoded().map_err(unexpected),
        Err(crate::v2file::ConvertError::Format(e)) => Err(e),
        Err(crate::v2file::ConvertError::Io(e)) => Err(unexpected(e)),
        Err(e) => Err(FormatError::new(
            ErrorCode::LevelTooLarge,
            0,
            format!("2.0 encoding: {e}"),
        )),
    }
}

/// The reference encoder of the level sections of the 2.0 file of `dag`'s
/// voxels (§23): single-threaded, every table in memory, the merge through
/// [`canonicalize`] (classes numbered by first occurrence, then ranked). The
/// oracle of [`encode`] in the tests.
pub fn encode_serial(dag: &Dag<'_>) -> Result<Encoded, FormatError> {
    let depth = dag.depth() as u8;
    let sym = canonicalize(dag, Group::Reflections, Group::Reflections)?;
    let leaf_level = sym.node_levels.len();
    if dag.is_empty() {
        // An empty node level has no reference: its minimising widths are
        // the least triple, 1, 1, 1 (§23.2).
        let mut levels = vec![
            EncodedLevel {
                bytes: Vec::new(),
                widths: [1; 3],
                item_count: 0,
                is_leaf: false,
            };
            leaf_level
        ];
        levels.push(EncodedLevel {
            bytes: Vec::new(),
            widths: [0; 3],
            item_count: 0,
            is_leaf: true,
        });
        return Ok(Encoded { depth, levels });
    }
    // Bottom-up: intrinsic ranks, canonical members, stabilisers.
    // Leaves: canonicalize stores the least reflected mask (§23.6).
    let mut order: Vec<u32> = (0..sym.leaves.len() as u32).collect();
    order.sort_unstable_by_key(|&c| sym.leaves[c as usize]);
    let leaves: Vec<u64> = order.iter().map(|&c| sym.leaves[c as usize]).collect();
    let mut rank_of = vec![0u32; order.len()];
    for (rank, &c) in order.iter().enumerate() {
        rank_of[c as usize] = rank as u32;
    }
    let mut stab: Vec<u8> = leaves
        .iter()
        .map(|&m| {
            (0..8u8)
                .filter(|&r| reflect_leaf(m, r) == m)
                .fold(0, |a, r| a | 1 << r)
        })
        .collect();
    // `adj[class]`: the reflection from the stored member of canonicalize's
    // class to the canonical member (0 for leaves).
    let mut adj = vec![0u8; order.len()];
    let mut canon_levels: Vec<Vec<Key>> = vec![Vec::new(); leaf_level];
    let mut stabs: Vec<Vec<u8>> = vec![Vec::new(); leaf_level + 1];
    for level in (0..leaf_level).rev() {
        let nodes = &sym.node_levels[level];
        let mut keys = Vec::with_capacity(nodes.len());
        let mut new_adj = Vec::with_capacity(nodes.len());
        let mut new_stab = Vec::with_capacity(nodes.len());
        for node in nodes {
            // The stored member in intrinsic terms.
            let mut key = Key {
                slots: [0; 8],
                attribute: node.attribute,
            };
            for p in 0..8 {
                if let Some(r) = node.child(p) {
                    let c = r.class as usize;
                    let rank = rank_of[c];
                    let t = norm(r.transform ^ adj[c], stab[rank as usize]);
                    key.slots[p] = 1 + (u64::from(rank) << 3) + u64::from(t);
                }
            }
            if level == 0 {
                keys.push(key);
                new_adj.push(0);
                new_stab.push(1);
                continue;
            }
            // The least of the 8 reflected forms, the first reflection reaching
            // it on ties; slot j of form r holds the child at slot j ^ r.
            let (best_r, ties) = least_form(8, |r, j| {
                let s = key.slots[usize::from(j ^ r)];
                if s == 0 {
                    return 0;
                }
                let rank = (s - 1) >> 3;
                let t = norm(((s - 1) & 7) as u8 ^ r, stab[rank as usize]);
                1 + (rank << 3) + u64::from(t)
            });
            let best = reflect_key(&key, best_r, &stab);
            let mut st = 0u8;
            for r in 0..8u8 {
                if ties >> r & 1 != 0 {
                    st |= 1 << (r ^ best_r);
                }
            }
            keys.push(best);
            new_adj.push(best_r);
            new_stab.push(st);
        }
        let mut order: Vec<u32> = (0..keys.len() as u32).collect();
        order.sort_unstable_by(|&a, &b| keys[a as usize].cmp(&keys[b as usize]));
        let mut new_rank_of = vec![0u32; order.len()];
        for (rank, &c) in order.iter().enumerate() {
            new_rank_of[c as usize] = rank as u32;
        }
        canon_levels[level] = order.iter().map(|&c| keys[c as usize]).collect();
        stabs[level + 1] = std::mem::take(&mut stab);
        stab = order.iter().map(|&c| new_stab[c as usize]).collect();
        adj = new_adj;
        rank_of = new_rank_of;
    }
    stabs[0] = stab;

    // Top-down: each level's order (rank, applied reflection) and, per
    // stored node, the position of its first sequential child.
    let mut counts: Vec<Vec<u32>> = vec![vec![1]];
    for (level, keys) in canon_levels.iter().enumerate() {
        let n = if level + 1 == leaf_level {
            leaves.len()
        } else {
            canon_levels[level + 1].len()
        };
        let mut c = vec![0u32; n];
        for key in keys {
            for &s in &key.slots {
                if s != 0 {
                    c[((s - 1) >> 3) as usize] += 1;
                }
            }
        }
        counts.push(c);
    }
    // stored[level]: (rank, reflection applied to the canonical member).
    let mut stored: Vec<Vec<(u32, u8)>> = vec![vec![(0, 0)]];
    let mut seq_first: Vec<Vec<u64>> = Vec::new();
    // stored_keys[level]: each stored node as stored (its canonical member
    // reflected), in stored order. Read once here from `canon_levels` in rank
    // order, which the stored order visits at random (a cache miss a node),
    // and kept for the layout instead of that level's ranked keys.
    let class_counts: Vec<usize> = canon_levels.iter().map(Vec::len).collect();
    let mut stored_keys: Vec<Vec<Key>> = Vec::with_capacity(leaf_level);
    for level in 0..leaf_level {
        let c = &counts[level + 1];
        let mut next: Vec<(u32, u8)> = (0..c.len() as u32)
            .filter(|&i| c[i as usize] > 1)
            .map(|i| (i, 0))
            .collect();
        next.sort_by(|a, b| c[b.0 as usize].cmp(&c[a.0 as usize]).then(a.0.cmp(&b.0)));
        let mut firsts = Vec::with_capacity(stored[level].len());
        let mut keys = Vec::with_capacity(stored[level].len());
        for &(rank, applied) in &stored[level] {
            let key = reflect_key(
                &canon_levels[level][rank as usize],
                applied,
                &stabs[level + 1],
            );
            keys.push(key);
            firsts.push(next.len() as u64);
            for &s in &key.slots {
                if s != 0 {
                    let child = ((s - 1) >> 3) as u32;
                    if c[child as usize] == 1 {
                        next.push((child, ((s - 1) & 7) as u8));
                    }
                }
            }
        }
        seq_first.push(firsts);
        stored.push(next);
        stored_keys.push(keys);
        canon_levels[level] = Vec::new();
    }

    // Bottom-up layout.
    let mut levels = vec![
        EncodedLevel {
            bytes: Vec::new(),
            widths: [0; 3],
            item_count: 0,
            is_leaf: false,
        };
        leaf_level + 1
    ];
    let mut leaf_bytes = Vec::with_capacity(8 * stored[leaf_level].len());
    // Address of each shared child by rank (sequential ones are found by position).
    let mut addr_of_rank = vec![0u64; leaves.len()];
    let mut addr_of_pos: Vec<u64> = Vec::with_capacity(stored[leaf_level].len());
    for (pos, &(rank, applied)) in stored[leaf_level].iter().enumerate() {
        leaf_bytes.extend_from_slice(&reflect_leaf(leaves[rank as usize], applied).to_le_bytes());
        if counts[leaf_level][rank as usize] > 1 {
            addr_of_rank[rank as usize] = pos as u64;
        }
        addr_of_pos.push(pos as u64);
    }
    levels[leaf_level] = EncodedLevel {
        item_count: stored[leaf_level].len() as u64,
        bytes: leaf_bytes,
        widths: [0; 3],
        is_leaf: true,
    };
    for level in (0..leaf_level).rev() {
        let c = &counts[level + 1];
        // Each record: its header, the end of its children's references in
        // `refs` (physical slot order, `None` for a sequential child) and its
        // base reference. Flat, so that a level allocates a few times, not
        // once per record.
        let mut records: Vec<(u32, usize, Option<u64>)> = Vec::with_capacity(stored[level].len());
        let mut refs: Vec<Option<u64>> = Vec::new();
        let mut hist = [0u64; 65];
        let bits_of = |v: u64| (64 - v.leading_zeros()).max(1);
        for (pos, key) in stored_keys[level].iter().enumerate() {
            let mut mask = 0u8;
            let mut any_seq = false;
            for (p, &s) in key.slots.iter().enumerate() {
                if s == 0 {
                    continue;
                }
                mask |= 1 << p;
                let child = ((s - 1) >> 3) as usize;
                if c[child] == 1 {
                    refs.push(None);
                    any_seq = true;
                } else {
                    let v = (addr_of_rank[child] << 3) | ((s - 1) & 7);
                    hist[bits_of(v) as usize] += 1;
                    refs.push(Some(v));
                }
            }
            let base = any_seq.then(|| addr_of_pos[seq_first[level][pos] as usize]);
            if let Some(b) = base {
                hist[bits_of(b) as usize] += 1;
            }
            records.push((u32::from(mask) | (key.attribute << 8), refs.len(), base));
        }
        let widths = best_widths(&hist).ok_or_else(|| {
            FormatError::new(
                ErrorCode::LevelTooLarge,
                0,
                format!("level {level}: a reference needs more than {MAX_WIDTH} bits"),
            )
        })?;
        let code_of = |v: u64| -> (u8, u32) {
            let b = bits_of(v);
            let i = widths
                .iter()
                .position(|&w| u32::from(w) >= b)
                .expect("the widest holds all");
            (i as u8 + 1, u32::from(widths[i]))
        };
        let mut bytes = Vec::new();
        let mut next_addr_of_pos = Vec::with_capacity(records.len());
        let mut next_addr_of_rank = vec![0u64; class_counts[level]];
        let mut first = 0usize;
        for (pos, &(header, end, base)) in records.iter().enumerate() {
            let record_refs = &refs[first..end];
            first = end;
            let offset = bytes.len() as u64;
            next_addr_of_pos.push(offset);
            let (rank, _) = stored[level][pos];
            if level == 0 || counts[level][rank as usize] > 1 {
                next_addr_of_rank[rank as usize] = offset;
            }
            bytes.extend_from_slice(&header.to_le_bytes());
            let mut w = BitWriter::new(&mut bytes);
            for r in record_refs {
                w.put(u64::from(r.map_or(0, |v| code_of(v).0)), 2);
            }
            if let Some(b) = base {
                w.put(u64::from(code_of(b).0), 2);
            }
            for &v in record_refs.iter().flatten() {
                w.put(v, code_of(v).1);
            }
            if let Some(b) = base {
                w.put(b, code_of(b).1);
            }
            w.finish();
        }
        levels[level] = EncodedLevel {
            item_count: records.len() as u64,
            bytes,
            widths,
            is_leaf: false,
        };
        addr_of_pos = next_addr_of_pos;
        addr_of_rank = next_addr_of_rank;
    }
    Ok(Encoded { depth, levels })
}

/// The widths of §23.2: the least triple (w_1 first) minimising the level's
/// reference bits, `hist[b]` references needing `b` bits. `None` when a
/// reference needs more than [`MAX_WIDTH`] bits.
pub fn best_widths(hist: &[u64; 65]) -> Option<[u8; 3]> {
    let max = (1..65).rev().find(|&b| hist[b] != 0).unwrap_or(1) as u32;
    if max > MAX_WIDTH {
        return None;
    }
    let mut best: Option<([u8; 3], u64)> = None;
    for w1 in 1..=max {
        for w2 in w1..=max {
            let ws = [w1, w2, max];
            let mut cost = 0u64;
            for (b, &n) in hist.iter().enumerate().skip(1) {
                if n != 0 {
                    let w = ws.iter().copied().find(|&w| w >= b as u32).unwrap_or(max);
                    cost += n * u64::from(w);
                }
            }
            if best.is_none_or(|(_, c)| cost < c) {
                best = Some(([w1 as u8, w2 as u8, max as u8], cost));
            }
        }
    }
    best.map(|(w, _)| w)
}

/// Appends a record's bit stream to a level's bytes, least significant bit
/// first (§23.2), a byte at a time.
pub(crate) struct BitWriter<'a> {
    bytes: &'a mut Vec<u8>,
    /// Bits not yet written, least significant first; fewer than 8 between calls.
    pending: u64,
    pending_bits: u32,
}

impl<'a> BitWriter<'a> {
    pub(crate) fn new(bytes: &'a mut Vec<u8>) -> Self {
        BitWriter {
            bytes,
            pending: 0,
            pending_bits: 0,
        }
    }

    /// Writes the low `width` bits of `value`, `width` ≤ 56.
    pub(crate) fn put(&mut self, value: u64, width: u32) {
        debug_assert!(width <= 56 && self.pending_bits < 8);
        let value = value & ((1u64 << width) - 1);
        self.pending |= value << self.pending_bits;
        self.pending_bits += width;
        while self.pending_bits >= 8 {
            self.bytes.push(self.pending as u8);
            self.pending >>= 8;
            self.pending_bits -= 8;
        }
    }

    /// Writes the last partial byte, zero-padded.
    pub(crate) fn finish(self) {
        if self.pending_bits > 0 {
            self.bytes.push(self.pending as u8);
        }
    }
}

impl Encoded {
    /// The levels as borrowed [`LevelView`]s, root first.
    pub fn views(&self) -> Vec<LevelView<'_>> {
        self.levels.iter().map(EncodedLevel::view).collect()
    }

    /// Walks the encoded levels from the root with the accumulated reflection
    /// of §23.4 and calls `leaf` with each leaf's Morton prefix (its brick's
    /// code) and logical mask, in Morton order. Decodes through
    /// [`decode_node`] and [`child_address`] only.
    pub fn for_each_leaf(&self, mut leaf: impl FnMut(u64, u64)) -> Result<(), FormatError> {
        for_each_leaf(&self.views(), |prefix, mask| {
            leaf(prefix, mask);
            ControlFlow::Continue(())
        })
    }

    /// The dense voxel index (§12.3) of the voxel with Morton code `code`, by
    /// the sibling sums of §23.5 (attribute kind 1 with unsaturated counts;
    /// for tests), or `None` when it is not set.
    pub fn voxel_index(&self, code: u64) -> Result<Option<u64>, FormatError> {
        voxel_index(&self.views(), code, true)
    }
}

fn leaf_mask(levels: &[LevelView<'_>], index: u64) -> Result<u64, FormatError> {
    let bytes = levels[levels.len() - 1].bytes;
    usize::try_from(index)
        .ok()
        .and_then(|i| i.checked_mul(8))
        .and_then(|i| crate::reader::read_u64(bytes, i))
        .ok_or_else(|| {
            FormatError::new(
                ErrorCode::ReferenceOutOfRange2,
                index,
                "leaf index past the leaf level".to_string(),
            )
        })
}

fn child_level<'a>(levels: &[LevelView<'a>], level: usize) -> Option<(&'a [u8], [u8; 3])> {
    let l = &levels[level + 1];
    (!l.is_leaf).then_some((l.bytes, l.widths))
}

/// Walks 2.0 `levels` (root first, the leaf level last) from the root with
/// the accumulated reflection of §23.4 and calls `leaf` with each leaf's
/// Morton prefix (its brick's code) and logical mask, in Morton order, until
/// it answers [`ControlFlow::Break`]. Never panics: a reference that leads
/// nowhere is an error.
pub fn for_each_leaf(
    levels: &[LevelView<'_>],
    mut leaf: impl FnMut(u64, u64) -> ControlFlow<()>,
) -> Result<(), FormatError> {
    let Some(last) = levels.len().checked_sub(1) else {
        return Ok(());
    };
    if levels[last].item_count == 0 || levels[0].item_count == 0 {
        return Ok(());
    }
    walk(levels, 0, 0, 0, 0, &mut leaf).map(|_| ())
}

fn walk(
    levels: &[LevelView<'_>],
    level: usize,
    at: u64,
    acc: u8,
    prefix: u64,
    leaf: &mut impl FnMut(u64, u64) -> ControlFlow<()>,
) -> Result<ControlFlow<()>, FormatError> {
    let last = levels.len() - 1;
    if level == last {
        return Ok(leaf(prefix, reflect_leaf(leaf_mask(levels, at)?, acc)));
    }
    let lv = &levels[level];
    let node = decode_node(lv.bytes, at, lv.widths)?;
    let below = child_level(levels, level);
    for c in 0..8u8 {
        if let Some(child) = node.children[usize::from(c ^ acc)] {
            let (target, r) = child_address(child, below)?;
            if walk(
                levels,
                level + 1,
                target,
                acc ^ r,
                prefix * 8 + u64::from(c),
                leaf,
            )?
            .is_break()
            {
                return Ok(ControlFlow::Break(()));
            }
        }
    }
    Ok(ControlFlow::Continue(()))
}

/// The voxels in the subtree at `target` of `level` (a leaf's popcount, or
/// the record's attribute when `attributes` says it holds an unsaturated
/// count, else the sum over the children): reflections do not change it.
/// Each record is counted once (the sums are remembered), so the work is at
/// most linear in the levels whatever the file says.
pub fn subtree_count(
    levels: &[LevelView<'_>],
    level: usize,
    target: u64,
    attributes: bool,
) -> Result<u64, FormatError> {
    subtree_count_memo(levels, level, target, attributes, &mut HashMap::new())
}

fn subtree_count_memo(
    levels: &[LevelView<'_>],
    level: usize,
    target: u64,
    attributes: bool,
    memo: &mut HashMap<(usize, u64), u64>,
) -> Result<u64, FormatError> {
    if let Some(&n) = memo.get(&(level, target)) {
        return Ok(n);
    }
    let n = subtree_count_uncached(levels, level, target, attributes, memo)?;
    memo.insert((level, target), n);
    Ok(n)
}

fn subtree_count_uncached(
    levels: &[LevelView<'_>],
    level: usize,
    target: u64,
    attributes: bool,
    memo: &mut HashMap<(usize, u64), u64>,
) -> Result<u64, FormatError> {
    let last = levels.len() - 1;
    if level == last {
        return Ok(u64::from(leaf_mask(levels, target)?.count_ones()));
    }
    let lv = &levels[level];
    let node = decode_node(lv.bytes, target, lv.widths)?;
    if attributes && node.attribute() != crate::layout::COUNT_SATURATED {
        return Ok(u64::from(node.attribute()));
    }
    let below = child_level(levels, level);
    let mut sum = 0u64;
    for child in node.children.iter().flatten() {
        let (t, _) = child_address(*child, below)?;
        sum = sum.saturating_add(subtree_count_memo(levels, level + 1, t, attributes, memo)?);
    }
    Ok(sum)
}

/// The dense voxel index (§12.3) of the voxel with Morton code `code` in 2.0
/// `levels`, by the sibling sums of §23.5, or `None` when it is not set.
/// `attributes`: the records' attributes are voxel counts (kind 1;
/// saturated counts are summed from the children).
pub fn voxel_index(
    levels: &[LevelView<'_>],
    code: u64,
    attributes: bool,
) -> Result<Option<u64>, FormatError> {
    let Some(last) = levels.len().checked_sub(1) else {
        return Ok(None);
    };
    if levels[last].item_count == 0 || levels[0].item_count == 0 {
        return Ok(None);
    }
    let mut at = 0u64;
    let mut acc = 0u8;
    let mut index = 0u64;
    let mut memo = HashMap::new();
    for level in 0..last {
        let lv = &levels[level];
        let node = decode_node(lv.bytes, at, lv.widths)?;
        let below = child_level(levels, level);
        let c = ((code >> (3 * (last - level) + 3)) & 7) as u8;
        for p in 0..8u8 {
            if let Some(child) = node.children[usize::from(p)].filter(|_| p ^ acc < c) {
                let (target, _) = child_address(child, below)?;
                index = index.saturating_add(subtree_count_memo(
                    levels,
                    level + 1,
                    target,
                    attributes,
                    &mut memo,
                )?);
            }
        }
        let Some(child) = node.children[usize::from(c ^ acc)] else {
            return Ok(None);
        };
        let (target, r) = child_address(child, below)?;
        at = target;
        acc ^= r;
    }
    let mask = reflect_leaf(leaf_mask(levels, at)?, acc);
    let bit = code & 63;
    Ok(
        (mask >> bit & 1 != 0)
            .then(|| index + u64::from((mask & ((1u64 << bit) - 1)).count_ones())),
    )
}

/// Whether the voxel with Morton code `code` is set in 2.0 `levels`: the
/// descent of [`voxel_index`] without its sibling sums (which a file without
/// voxel-count attributes pays a subtree walk for).
pub fn is_set(levels: &[LevelView<'_>], code: u64) -> Result<bool, FormatError> {
    let Some(last) = levels.len().checked_sub(1) else {
        return Ok(false);
    };
    if levels[last].item_count == 0 || levels[0].item_count == 0 {
        return Ok(false);
    }
    let mut at = 0u64;
    let mut acc = 0u8;
    for level in 0..last {
        let lv = &levels[level];
        let node = decode_node(lv.bytes, at, lv.widths)?;
        let c = ((code >> (3 * (last - level) + 3)) & 7) as u8;
        let Some(child) = node.children[usize::from(c ^ acc)] else {
            return Ok(false);
        };
        let (target, r) = child_address(child, child_level(levels, level))?;
        at = target;
        acc ^= r;
    }
    Ok(reflect_leaf(leaf_mask(levels, at)?, acc) >> (code & 63) & 1 != 0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::AttributeKind;
    use crate::builder::DagBuilder;
    use proptest::prelude::*;

    fn codes_from(enc: &Encoded) -> Vec<u64> {
        let mut out = Vec::new();
        enc.for_each_leaf(|prefix, mut mask| {
            while mask != 0 {
                out.push(prefix * 64 + u64::from(mask.trailing_zeros()));
                mask &= mask - 1;
            }
        })
        .unwrap();
        out
    }

    /// Reads `width` bits at bit `bit` of `bytes`, least significant bit first.
    fn read_bits(bytes: &[u8], bit: u64, width: u32) -> Option<u64> {
        let mut v = 0u64;
        let mut got = 0u32;
        let mut pos = bit;
        while got < width {
            let byte = *bytes.get(usize::try_from(pos / 8).ok()?)?;
            let shift = (pos % 8) as u32;
            let take = (8 - shift).min(width - got);
            let part = (u64::from(byte) >> shift) & ((1u64 << take) - 1);
            v |= part << got;
            got += take;
            pos += u64::from(take);
        }
        Some(v)
    }

    /// The first decoder of §23.2, bit by bit and code by code: the oracle
    /// of [`Coding`]. Decodes the node record at byte `offset` of a 2.0 interior level with
    /// `widths` (§23.2): its header, its size and each child's reference. Never
    /// panics: a record that runs past `level` is an error (E071).
    fn naive_decode_node(level: &[u8], offset: u64, widths: [u8; 3]) -> Result<Node2, FormatError> {
        if widths.iter().any(|&w| u32::from(w) > MAX_WIDTH) {
            return Err(FormatError::new(
                ErrorCode::BadWidths,
                offset,
                format!("2.0 reference widths {widths:?} exceed {MAX_WIDTH} bits"),
            ));
        }
        if offset >= level.len() as u64 {
            return Err(truncated(offset));
        }
        let start = offset as usize;
        let header = crate::reader::read_u32(level, start).ok_or_else(|| truncated(offset))?;
        let mask = header as u8;
        let k = mask.count_ones();
        let stream = level.get(start + 4..).ok_or_else(|| truncated(offset))?;
        let mut codes = [0u8; 9];
        for (i, c) in codes.iter_mut().enumerate().take(k as usize) {
            *c = read_bits(stream, 2 * i as u64, 2).ok_or_else(|| truncated(offset))? as u8;
        }
        let has_base = codes[..k as usize].contains(&0);
        let m = k + u32::from(has_base);
        if has_base {
            codes[k as usize] =
                read_bits(stream, 2 * u64::from(k), 2).ok_or_else(|| truncated(offset))? as u8;
        }
        let width = |code: u8| -> u32 { u32::from(widths[usize::from(code.max(1)) - 1]) };
        let mut bit = 2 * u64::from(m);
        let mut children = [None; 8];
        let mut rank = 0usize;
        for (slot, child) in children.iter_mut().enumerate() {
            if mask >> slot & 1 == 0 {
                continue;
            }
            let code = codes[rank];
            rank += 1;
            if code != 0 {
                let w = width(code);
                let v = read_bits(stream, bit, w).ok_or_else(|| truncated(offset))?;
                bit += u64::from(w);
                *child = Some(Child::Shared {
                    target: v >> 3,
                    reflection: (v & 7) as u8,
                });
            }
        }
        let base = if has_base {
            let w = width(codes[k as usize]);
            let v = read_bits(stream, bit, w).ok_or_else(|| truncated(offset))?;
            bit += u64::from(w);
            v
        } else {
            0
        };
        let mut index = 0u32;
        let mut rank = 0usize;
        for (slot, child) in children.iter_mut().enumerate() {
            if mask >> slot & 1 == 0 {
                continue;
            }
            if codes[rank] == 0 {
                *child = Some(Child::Sequential { base, index });
                index += 1;
            }
            rank += 1;
        }
        let size = 4 + bit.div_ceil(8);
        if start as u64 + size > level.len() as u64 {
            return Err(truncated(offset));
        }
        Ok(Node2 {
            header,
            size: size as u32,
            children,
        })
    }

    proptest! {
        // The fast decoder reads every record, or fails, as the bit-by-bit
        // one does.
        #[test]
        fn coding_decodes_as_the_bit_by_bit_decoder(
            bytes in proptest::collection::vec(any::<u8>(), 0..64),
            offset in 0u64..70,
            widths in proptest::array::uniform3(1u8..=44),
        ) {
            let fast = decode_node(&bytes, offset, widths).ok();
            let naive = naive_decode_node(&bytes, offset, widths).ok();
            prop_assert_eq!(fast, naive);
            // A width of 0 holds no reference (E070): refused.
            prop_assert!(decode_node(&bytes, offset, [0, widths[1], widths[2]]).is_err());
        }
    }

    proptest! {
        // The decoder never panics, whatever the bytes, offset and widths.
        #[test]
        fn decoding_any_bytes_never_panics(
            bytes in proptest::collection::vec(any::<u8>(), 0..64),
            offset in 0u64..80,
            widths in any::<[u8; 3]>(),
            index in 0u32..8,
        ) {
            if let Ok(node) = decode_node(&bytes, offset, widths) {
                prop_assert!(offset + u64::from(node.size) <= bytes.len() as u64);
                for child in node.children.iter().flatten() {
                    let _ = child_address(*child, Some((&bytes, widths)));
                    let _ = child_address(*child, None);
                }
            }
            let _ = child_address(Child::Sequential { base: u64::MAX - 3, index }, None);
            let _ = child_address(Child::Sequential { base: offset, index }, Some((&bytes, widths)));
        }
    }

    #[test]
    fn the_norm_table_is_the_least_of_the_coset() {
        for stab in 0..=255u8 {
            for t in 0..16u8 {
                let least = (0..8u8)
                    .filter(|s| stab >> s & 1 != 0)
                    .map(|s| t ^ s)
                    .min()
                    .unwrap_or(t);
                let expected = if stab == 1 { t } else { least };
                assert_eq!(norm(t, stab), expected, "t {t}, stabiliser {stab:#010b}");
            }
        }
    }
    #[test]
    fn widths_minimise_the_reference_bits() {
        let mut hist = [0u64; 65];
        hist[3] = 100;
        hist[12] = 10;
        hist[20] = 1;
        assert_eq!(best_widths(&hist), Some([3, 12, 20]));
        let mut hist = [0u64; 65];
        hist[5] = 1;
        assert_eq!(best_widths(&hist), Some([1, 1, 5]));
        hist[41] = 1;
        assert_eq!(best_widths(&hist), None);
    }

    #[test]
    fn mirrored_subtrees_are_stored_once_and_unique_ones_in_sequence() {
        // An asymmetric pattern in the lower-x half and its mirror image in
        // the upper-x half: the root's two children are one class.
        let pattern = [
            [1u32, 2, 3],
            [2, 2, 3],
            [5, 9, 1],
            [14, 3, 7],
            [6, 6, 12],
            [0, 15, 15],
        ];
        let mut vs = Vec::new();
        for &[x, y, z] in &pattern {
            vs.push([x, y, z]);
            vs.push([31 - x, y, z]);
        }
        let bytes = DagBuilder::from_voxels(5, AttributeKind::VoxelCount, vs)
            .unwrap()
            .to_bytes();
        let dag = Dag::open(&bytes).unwrap();
        assert_eq!(dag.levels()[1].node_count, 2);
        let enc = encode(&dag).unwrap();
        assert_eq!(enc.levels[1].item_count, 1);
        let root = decode_node(&enc.levels[0].bytes, 0, enc.levels[0].widths).unwrap();
        let reflections: Vec<u8> = root
            .children
            .iter()
            .flatten()
            .map(|c| match c {
                Child::Shared {
                    target: 0,
                    reflection,
                } => *reflection,
                other => panic!("root child {other:?}"),
            })
            .collect();
        // One stored member, reached mirrored in x from one child to the other.
        assert_eq!(reflections.len(), 2);
        assert_eq!(reflections[0] ^ reflections[1], 1);
        // Level 1's children are each named once: sequential.
        let node = decode_node(&enc.levels[1].bytes, 0, enc.levels[1].widths).unwrap();
        assert!(
            node.children
                .iter()
                .flatten()
                .all(|c| matches!(c, Child::Sequential { .. }))
        );
        assert_eq!(node.size as usize, enc.levels[1].bytes.len());
        assert_eq!(node.attribute(), pattern.len() as u32);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        // The 2.0 levels hold the 1.0 file's voxels, and the attribute index
        // under reflections (§23.5) is the 1.0 dense index of every voxel.
        #[test]
        fn encoding_keeps_voxels_and_indices(
            depth in 2u8..=6,
            voxels in proptest::collection::vec((0u32..64, 0u32..64, 0u32..64), 0..400),
            blocks in proptest::collection::vec((0u32..8, 0u32..8, 0u32..8), 0..6),
        ) {
            let res = 1u32 << depth;
            let mut vs: Vec<[u32; 3]> = voxels.iter().map(|&(x, y, z)| [x % res, y % res, z % res]).collect();
            // Solid blocks and their mirror images make shared, symmetric subtrees.
            for &(bx, by, bz) in &blocks {
                for d in 0..4 {
                    vs.push([(bx * 4 + d) % res, (by * 4) % res, (bz * 4 + d) % res]);
                    vs.push([res - 1 - (bx * 4 + d) % res, (by * 4) % res, (bz * 4 + d) % res]);
                }
            }
            let bytes = DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, vs.iter().copied()).unwrap().to_bytes();
            let dag = Dag::open(&bytes).unwrap();
            let enc = encode(&dag).unwrap();
            prop_assert_eq!(enc.levels.len(), usize::from(depth) - 1);
            let expected: Vec<u64> = dag.voxels().map(|v| {
                let [x, y, z] = v.unwrap();
                crate::morton::encode(x, y, z)
            }).collect();
            prop_assert_eq!(codes_from(&enc), expected.clone());
            for &code in expected.iter().step_by(7) {
                let [x, y, z] = crate::morton::decode(code);
                prop_assert_eq!(enc.voxel_index(code).unwrap(), dag.voxel_index(x, y, z).unwrap());
            }
            // Membership, set or not, as the 1.0 reader answers it.
            let views = enc.views();
            for &(x, y, z) in voxels.iter().take(64) {
                let [x, y, z] = [x % res, y % res, z % res];
                let code = crate::morton::encode(x, y, z);
                prop_assert_eq!(is_set(&views, code).unwrap(), dag.is_set(x, y, z).unwrap());
                let neighbour = crate::morton::encode((x + 1) % res, y, (z + 3) % res);
                let [nx, ny, nz] = crate::morton::decode(neighbour);
                prop_assert_eq!(is_set(&views, neighbour).unwrap(), dag.is_set(nx, ny, nz).unwrap());
            }
            // Deterministic.
            prop_assert_eq!(encode(&dag).unwrap(), enc.clone());
            // Without attributes: the same voxels and, record for record, the
            // same sizes (§23.9: the 24 bits are stored for every kind).
            let none = DagBuilder::from_voxels(depth, AttributeKind::None, vs.iter().copied()).unwrap().to_bytes();
            let enc0 = encode(&Dag::open(&none).unwrap()).unwrap();
            prop_assert_eq!(codes_from(&enc0), expected);
            for (a, b) in enc.levels.iter().zip(&enc0.levels) {
                prop_assert_eq!(a.bytes.len(), b.bytes.len());
                prop_assert_eq!(a.widths, b.widths);
            }
        }
    }
}
