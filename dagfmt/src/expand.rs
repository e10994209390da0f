//! The expanded form of a 2.0 DAG's node levels: every reference spelled
//! out as one aligned 32-bit word, for tracers (spec §23.12).
//!
//! A 2.0 record is a bit stream (§23.2): finding a child costs popcounts of
//! the codes, an unaligned read of 1 to 40 bits, and for a sequential child
//! the sizes of its siblings (§23.3). A tracer that opens a 2.0 file may
//! instead expand its node levels once, into the layout of a 1.0 level with
//! 4-byte references that keep the reflection (§23.12):
//!
//! - a record is its header word, then one word per child in physical slot
//!   order, `index << 3 | r`: `index` is the child's record in the expanded
//!   child level (its first word's index) or the leaf index on the leaf
//!   level, `r` the reference's reflection (0 for a sequential child);
//! - records follow one another in the file's order, so that record `i` of
//!   the file is record `i` of the expanded level;
//! - the leaf level is not copied: its 64-bit masks are read in place.
//!
//! The expansion is an index of the file, like the record starts of §23.8:
//! it holds what the file says, decoded. It succeeds only where the levels
//! decode completely: each node level a chain of whole records from byte 0
//! to its end, every reference naming a record start (or a leaf) of the
//! child level, and every index below 2^29. Anything else is an error, and
//! a tracer traces such a file's bytes in place, where it reports each
//! fault it meets as it always did.

use crate::error::{ErrorCode, FormatError};
use crate::v2::{Child, Coding, LevelView};

/// Largest index a 32-bit expanded reference holds beside its 3 reflection
/// bits.
pub const MAX_INDEX: u64 = (1 << 29) - 1;

/// One expanded node level (see the module docs).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ExpandedLevel {
    /// The records: header word, then a reference word per child.
    pub words: Vec<u32>,
    /// Records in the level (the 2.0 level's record count).
    pub records: u64,
}

/// Expands the node levels 0 ..= D − 3 of a 2.0 DAG whose level sections
/// are `levels` (root first, the leaf level last, as [`crate::Dag2::levels`]
/// gives them); the result has one entry per node level, in the same order.
/// Fails (without panicking, on any bytes) where a level does not decode
/// completely or an index does not fit in 29 bits (see the module docs);
/// the error names the level's byte that stopped it (the first such byte
/// in the level's record order, whatever the number of threads).
///
/// Each level is framed once (its records' sizes, from byte 0), then its
/// records are expanded in chunks on every core; a reference finds its
/// child's record by a rank over the child level's record starts.
pub fn expand_levels(levels: &[LevelView<'_>]) -> Result<Vec<ExpandedLevel>, FormatError> {
    use rayon::prelude::*;
    let nodes = levels.iter().take_while(|l| !l.is_leaf).count();
    // Framed side by side; the first failing level in order is reported.
    let chains: Vec<Result<Chain, FormatError>> = levels[..nodes]
        .par_iter()
        .enumerate()
        .map(|(depth, view)| record_chain(view, depth))
        .collect();
    let chains = chains.into_iter().collect::<Result<Vec<_>, _>>()?;
    let leaf_count = levels.get(nodes).map(|l| l.bytes.len() as u64 / 8);
    let mut out = Vec::with_capacity(nodes);
    for depth in 0..nodes {
        let view = &levels[depth];
        let chain = &chains[depth];
        let coding = level_coding(view, depth)?;
        let child = chains.get(depth + 1);
        let mut words = vec![0u32; chain.words as usize];
        // Disjoint pieces of `words`, one per chunk of records.
        let mut pieces = Vec::with_capacity(chain.chunks.len());
        let mut rest = words.as_mut_slice();
        for (i, &(ordinal, _)) in chain.chunks.iter().enumerate() {
            let end = chain.chunks.get(i + 1).map_or(chain.words, |&(o, _)| {
                u64::from(chain.first_word[o as usize])
            });
            let begin = u64::from(chain.first_word[ordinal as usize]);
            let (piece, tail) = rest.split_at_mut((end - begin) as usize);
            pieces.push(piece);
            rest = tail;
        }
        let expand_chunk = |(i, piece): (usize, &mut [u32])| -> Result<(), FormatError> {
            let (first, mut offset) = chain.chunks[i];
            let last = chain.chunks.get(i + 1).map_or(chain.records(), |&(o, _)| o);
            let mut w = 0usize;
            for _ in first..last {
                let codes = coding
                    .codes(view.bytes, offset)
                    .ok_or_else(|| stop(depth, offset, "its record runs past the level's end"))?;
                piece[w] = codes.header;
                w += 1;
                let mask = codes.child_mask();
                for slot in 0..8u32 {
                    if mask >> slot & 1 == 0 {
                        continue;
                    }
                    let found =
                        coding
                            .child(view.bytes, offset, &codes, slot)
                            .ok_or_else(|| {
                                stop(depth, offset, "its record runs past the level's end")
                            })?;
                    piece[w] = reference_word(found, child, leaf_count, depth, offset)?;
                    w += 1;
                }
                offset += coding.size(&codes);
            }
            Ok(())
        };
        // Every chunk runs; the first error in record order is reported.
        let results: Vec<Result<(), FormatError>> = pieces
            .into_par_iter()
            .enumerate()
            .map(expand_chunk)
            .collect();
        results.into_iter().collect::<Result<(), _>>()?;
        out.push(ExpandedLevel {
            words,
            records: chain.records(),
        });
    }
    Ok(out)
}

/// The expanded word of a child found at a record at byte `offset` of node
/// level `depth`, whose child level is framed by `child` (`None`: the leaf
/// level, of `leaf_count` leaves).
fn reference_word(
    found: Child,
    child: Option<&Chain>,
    leaf_count: Option<u64>,
    depth: usize,
    offset: u64,
) -> Result<u32, FormatError> {
    let (index, reflection) = match (found, child) {
        (Child::Shared { target, reflection }, None) => (target, reflection),
        // Sequential leaves are consecutive leaf indices.
        (Child::Sequential { base, index }, None) => (base.saturating_add(u64::from(index)), 0),
        (Child::Shared { target, reflection }, Some(c)) => {
            let ordinal = c
                .ordinal(target)
                .ok_or_else(|| stop(depth, offset, "a reference names no record start"))?;
            (u64::from(c.first_word[ordinal as usize]), reflection)
        }
        // The `index`-th record after the base's.
        (Child::Sequential { base, index }, Some(c)) => {
            let ordinal = c
                .ordinal(base)
                .ok_or_else(|| stop(depth, offset, "a base reference names no record start"))?
                + u64::from(index);
            let word = c
                .first_word
                .get(ordinal as usize)
                .ok_or_else(|| stop(depth, offset, "a sequential child lies past the level"))?;
            (u64::from(*word), 0)
        }
    };
    if child.is_none() && leaf_count.is_none_or(|n| index >= n) {
        return Err(stop(depth, offset, "a reference names no leaf"));
    }
    if index > MAX_INDEX {
        return Err(stop(depth, offset, "an index does not fit in 29 bits"));
    }
    Ok((index as u32) << 3 | u32::from(reflection))
}

/// The coding of node level `depth`; the empty root level of an empty DAG
/// decodes nothing.
fn level_coding(view: &LevelView<'_>, depth: usize) -> Result<Coding, FormatError> {
    if view.bytes.is_empty() {
        return Ok(Coding::default());
    }
    Coding::new(view.widths).map_err(|e| stop(depth, 0, &e.message))
}

/// Records a chunk of the parallel expansion holds.
const CHUNK_RECORDS: u64 = 1 << 14;

/// A node level framed: where its records start and where each begins when
/// expanded.
struct Chain {
    /// Bit `b` set where a record starts at byte `b`.
    starts: Vec<u64>,
    /// Records starting before each word of `starts` (a rank directory).
    before: Vec<u64>,
    /// The expanded word index of each record.
    first_word: Vec<u32>,
    /// Words of the expanded level.
    words: u64,
    /// Each chunk's first record: its ordinal and byte offset.
    chunks: Vec<(u64, u64)>,
}

impl Chain {
    /// Records in the level.
    fn records(&self) -> u64 {
        self.first_word.len() as u64
    }

    /// The ordinal of the record starting at byte `offset`, if one does.
    #[inline]
    fn ordinal(&self, offset: u64) -> Option<u64> {
        let word = usize::try_from(offset / 64).ok()?;
        let bits = *self.starts.get(word)?;
        let bit = offset % 64;
        if bits >> bit & 1 == 0 {
            return None;
        }
        Some(self.before[word] + u64::from((bits & ((1u64 << bit) - 1)).count_ones()))
    }
}

/// Follows node level `depth`'s records from byte 0 to its end.
fn record_chain(view: &LevelView<'_>, depth: usize) -> Result<Chain, FormatError> {
    let coding = level_coding(view, depth)?;
    let len = view.bytes.len() as u64;
    let mut starts = vec![0u64; len.div_ceil(64) as usize];
    let mut first_word = Vec::new();
    let mut chunks = Vec::new();
    let mut at = 0u64;
    let mut words = 0u64;
    while at < len {
        let codes = coding
            .codes(view.bytes, at)
            .ok_or_else(|| stop(depth, at, "its record runs past the level's end"))?;
        let size = coding.size(&codes);
        if at + size > len {
            return Err(stop(depth, at, "its record runs past the level's end"));
        }
        if words > MAX_INDEX {
            return Err(stop(depth, at, "the expanded level is over 2^29 words"));
        }
        let ordinal = first_word.len() as u64;
        if ordinal.is_multiple_of(CHUNK_RECORDS) {
            chunks.push((ordinal, at));
        }
        starts[(at / 64) as usize] |= 1 << (at % 64);
        first_word.push(words as u32);
        words += 1 + u64::from(codes.child_mask().count_ones());
        at += size;
    }
    if words > MAX_INDEX + 1 {
        return Err(stop(depth, 0, "the expanded level is over 2^29 words"));
    }
    let mut before = Vec::with_capacity(starts.len());
    let mut count = 0u64;
    for bits in &starts {
        before.push(count);
        count += u64::from(bits.count_ones());
    }
    Ok(Chain {
        starts,
        before,
        first_word,
        words,
        chunks,
    })
}

/// Why a level did not expand.
fn stop(depth: usize, at: u64, why: &str) -> FormatError {
    FormatError::new(
        ErrorCode::TruncatedRecord2,
        at,
        format!("level {depth} does not expand at byte {at}: {why}"),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::AttributeKind;
    use crate::builder::DagBuilder;
    use crate::reader::Dag;
    use crate::v2::{child_address, decode_node, encode};
    use proptest::prelude::*;

    /// Every record of every node level, decoded by [`decode_node`] and
    /// [`child_address`], against its expanded words.
    fn check_against_decoder(levels: &[LevelView<'_>], expanded: &[ExpandedLevel]) {
        for (depth, ex) in expanded.iter().enumerate() {
            let view = &levels[depth];
            let child = levels.get(depth + 1).filter(|l| !l.is_leaf);
            // Expanded word index of each record start of the child level.
            let mut child_words = std::collections::HashMap::new();
            if let Some(c) = child {
                let (mut at, mut w) = (0u64, 0u64);
                while at < c.bytes.len() as u64 {
                    let n = decode_node(c.bytes, at, c.widths).unwrap();
                    child_words.insert(at, w);
                    w += 1 + u64::from(n.child_mask().count_ones());
                    at += u64::from(n.size);
                }
            }
            let (mut at, mut w) = (0u64, 0usize);
            let mut records = 0;
            while at < view.bytes.len() as u64 {
                let node = decode_node(view.bytes, at, view.widths).unwrap();
                assert_eq!(ex.words[w], node.header);
                w += 1;
                for c in node.children.iter().flatten() {
                    let (target, r) =
                        child_address(*c, child.map(|l| (l.bytes, l.widths))).unwrap();
                    let index = match child {
                        None => target,
                        Some(_) => child_words[&target],
                    };
                    assert_eq!(ex.words[w], (index as u32) << 3 | u32::from(r));
                    w += 1;
                }
                at += u64::from(node.size);
                records += 1;
            }
            assert_eq!(w, ex.words.len());
            assert_eq!(ex.records, records);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        #[test]
        fn expanded_words_are_what_the_decoder_reads(
            depth in 2u8..=7,
            voxels in proptest::collection::vec((0u32..128, 0u32..128, 0u32..128), 0..400),
            blocks in proptest::collection::vec((0u32..8, 0u32..8, 0u32..8), 0..6),
        ) {
            let res = 1u32 << depth;
            let mut vs: Vec<[u32; 3]> =
                voxels.iter().map(|&(x, y, z)| [x % res, y % res, z % res]).collect();
            // Mirrored blocks make shared, reflected references.
            for &(bx, by, bz) in &blocks {
                for d in 0..4 {
                    vs.push([(bx * 4 + d) % res, (by * 4) % res, (bz * 4 + d) % res]);
                    vs.push([res - 1 - (bx * 4 + d) % res, (by * 4) % res, (bz * 4 + d) % res]);
                }
            }
            let bytes = DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, vs)
                .unwrap()
                .to_bytes();
            let enc = encode(&Dag::open(&bytes).unwrap()).unwrap();
            let views = enc.views();
            let expanded = expand_levels(&views).unwrap();
            prop_assert_eq!(expanded.len(), views.len() - 1);
            check_against_decoder(&views, &expanded);
        }

        // Any bytes: an expansion or an error, never a panic; and where
        // it expands, what it holds is what the decoder reads.
        #[test]
        fn edited_levels_expand_or_fail_cleanly(
            seed_voxels in proptest::collection::vec((0u32..32, 0u32..32, 0u32..32), 1..120),
            edits in proptest::collection::vec((any::<u16>(), any::<u8>()), 1..4),
            cut in any::<u16>(),
        ) {
            let bytes = DagBuilder::from_voxels(5, AttributeKind::VoxelCount,
                seed_voxels.iter().map(|&(x, y, z)| [x, y, z]))
                .unwrap()
                .to_bytes();
            let mut enc = encode(&Dag::open(&bytes).unwrap()).unwrap();
            let n = enc.levels.len();
            for &(at, value) in &edits {
                let level = &mut enc.levels[usize::from(at) % n];
                if !level.bytes.is_empty() {
                    let i = usize::from(at) % level.bytes.len();
                    level.bytes[i] = value;
                }
            }
            let last = &mut enc.levels[usize::from(cut) % n];
            let keep = last.bytes.len().saturating_sub(usize::from(cut % 3));
            last.bytes.truncate(keep);
            let views = enc.views();
            if let Ok(expanded) = expand_levels(&views) {
                // What expanded is what the decoder reads, record by record.
                prop_assert_eq!(expanded.len(), views.len() - 1);
                check_against_decoder(&views, &expanded);
            }
        }
    }

    #[test]
    fn a_cut_record_is_refused() {
        let vs: Vec<[u32; 3]> = (0..40)
            .map(|i| [i % 16, (i * 7) % 16, (i * 3) % 16])
            .collect();
        let bytes = DagBuilder::from_voxels(4, AttributeKind::VoxelCount, vs)
            .unwrap()
            .to_bytes();
        let enc = encode(&Dag::open(&bytes).unwrap()).unwrap();
        let views = enc.views();
        assert!(expand_levels(&views).is_ok());
        // The last node level cut by one byte: its last record is cut.
        let mut cut = enc.clone();
        let last = cut.levels.len() - 2;
        cut.levels[last].bytes.pop();
        let err = expand_levels(&cut.views()).unwrap_err();
        assert!(err.message.contains("does not expand"), "{}", err.message);
    }
}
