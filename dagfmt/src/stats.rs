//! Size statistics of a DAG: per level, and compared with the classic SVDAG
//! layout and with an uncompressed sparse voxel octree.
//!
//! The comparisons use the layout of the original SVDAG paper (Kämpe, Sintorn
//! and Assarsson 2013): every interior node is a 32-bit header plus one 32-bit
//! pointer per child, every leaf a 64-bit 4³ mask. The SVO is the same layout
//! without deduplication, i.e. every node once per path that reaches it.
//!
//! Tree-node counts come from propagating reference multiplicities top-down.
//! A node has at most 8 pointers, so a level-`l` node occurs at most 8^l times
//! (8^19 < 2^57 at the deepest leaf level): multiplicities fit a `u64`, and
//! totals are summed in `u128`.

use std::fmt;

use crate::error::{ErrorCode, FormatError};
use crate::layout::{self, AttributeKind};
use crate::reader::{Dag, LevelSection, read_u32};

/// Statistics of one level of a DAG.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LevelStats {
    /// Level number (0 is the root; the last level holds the leaves).
    pub level: u8,
    /// Distinct nodes (or leaves) stored.
    pub node_count: u64,
    /// Bytes of the level's section.
    pub bytes: u64,
    /// Pointer width in bytes; 0 for the leaf level.
    pub pointer_width: u8,
    /// Nodes the level would hold in a tree without deduplication.
    pub tree_nodes: u128,
}

impl LevelStats {
    /// Tree nodes per stored node (1 when nothing was shared or the level is empty).
    pub fn dedup_ratio(&self) -> f64 {
        if self.node_count == 0 {
            1.0
        } else {
            self.tree_nodes as f64 / self.node_count as f64
        }
    }
}

/// Statistics of a whole DAG.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DagStats {
    /// Depth D.
    pub depth: u8,
    /// Attribute kind of the nodes.
    pub attribute_kind: AttributeKind,
    /// Set voxels (from the header).
    pub voxel_count: u64,
    /// Per level, root first.
    pub levels: Vec<LevelStats>,
    /// Bytes of the whole file.
    pub file_bytes: u64,
    /// Bytes of the level sections alone.
    pub level_bytes: u64,
    /// Stored nodes and leaves, all levels.
    pub dag_nodes: u64,
    /// Nodes and leaves of the equivalent tree, all levels.
    pub tree_nodes: u128,
    /// The same DAG in the classic SVDAG layout (32-bit headers and pointers, 64-bit leaves).
    pub classic_svdag_bytes: u128,
    /// The equivalent sparse voxel octree in the same 32-bit layout (no deduplication).
    pub svo_bytes: u128,
    /// Per interior level (root first): the zero-order entropy, in bits
    /// (rounded up), of the level's pointers, i.e. of which node of the next
    /// level each of them names, by how often each is named.
    pub pointer_entropy_bits: Vec<u64>,
    /// A lower bound for any layout of this DAG that keeps a 32-bit header
    /// per interior node and a 64-bit mask per leaf and codes each pointer on
    /// its own (any code per level, variable-length, even without byte
    /// alignment or random access): headers + leaves + the pointer entropy.
    /// It shows how much pointer coding alone could still gain.
    pub pointer_entropy_bound_bytes: u128,
}

impl DagStats {
    /// Whole-DAG deduplication ratio: tree nodes per stored node.
    pub fn dedup_ratio(&self) -> f64 {
        if self.dag_nodes == 0 {
            1.0
        } else {
            self.tree_nodes as f64 / self.dag_nodes as f64
        }
    }
}

impl fmt::Display for DagStats {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "depth {} ({}^3), attribute kind {}, {} voxels",
            self.depth,
            1u64 << self.depth,
            self.attribute_kind.to_raw(),
            self.voxel_count
        )?;
        writeln!(
            f,
            "{:>5} {:>14} {:>16} {:>5} {:>22} {:>12}",
            "level", "nodes", "bytes", "width", "tree nodes", "dedup"
        )?;
        for l in &self.levels {
            writeln!(
                f,
                "{:>5} {:>14} {:>16} {:>5} {:>22} {:>12.2}",
                l.level,
                l.node_count,
                l.bytes,
                l.pointer_width,
                l.tree_nodes,
                l.dedup_ratio()
            )?;
        }
        writeln!(
            f,
            "nodes: {} stored, {} in the tree (x{:.2})",
            self.dag_nodes,
            self.tree_nodes,
            self.dedup_ratio()
        )?;
        writeln!(
            f,
            "this file:          {:>22} bytes ({} in level sections)",
            self.file_bytes, self.level_bytes
        )?;
        writeln!(
            f,
            "classic SVDAG:      {:>22} bytes",
            self.classic_svdag_bytes
        )?;
        writeln!(f, "SVO (no dedup):     {:>22} bytes", self.svo_bytes)?;
        write!(
            f,
            "pointer entropy bound: {:>19} bytes",
            self.pointer_entropy_bound_bytes
        )
    }
}

/// Parses the records of an interior level in storage order: the word offset
/// of each node. Fails on a record that runs past the section.
fn node_starts(section: &LevelSection<'_>) -> Result<Vec<u32>, FormatError> {
    let bytes = section.bytes;
    let mut starts = Vec::with_capacity(
        usize::try_from(section.node_count)
            .unwrap_or(0)
            .min(bytes.len() / 8),
    );
    let mut at = 0usize;
    while at < bytes.len() {
        let header = read_u32(bytes, at).ok_or_else(|| {
            FormatError::new(
                ErrorCode::TruncatedNode,
                section.file_offset + at as u64,
                format!(
                    "node record at byte {at} of level {} is cut off",
                    section.level
                ),
            )
            .at_level(section.level)
            .at_node(starts.len() as u64)
        })?;
        let size =
            layout::node_record_size((header & 0xff).count_ones(), section.pointer_width) as usize;
        if at + size > bytes.len() {
            return Err(FormatError::new(
                ErrorCode::TruncatedNode,
                section.file_offset + at as u64,
                format!(
                    "node record at byte {at} of level {} runs past the end of its section",
                    section.level
                ),
            )
            .at_level(section.level)
            .at_node(starts.len() as u64));
        }
        starts.push((at / 4) as u32);
        at += size;
    }
    if starts.len() as u64 != section.node_count {
        return Err(FormatError::new(
            ErrorCode::ItemCountMismatch,
            section.file_offset,
            format!(
                "level {} declares {} nodes but holds {}",
                section.level,
                section.node_count,
                starts.len()
            ),
        )
        .at_level(section.level));
    }
    Ok(starts)
}

/// Computes the statistics of `dag`. Linear in the file size; malformed
/// structure (a record cut off, a pointer outside its level or into the middle
/// of a record, a node count that differs from the records) is an error.
pub fn analyze(dag: &Dag<'_>) -> Result<DagStats, FormatError> {
    let sections = dag.levels();
    let leaf_level = sections.len() - 1;
    let mut levels = Vec::with_capacity(sections.len());
    let mut classic = 0u128;
    let mut svo = 0u128;
    let mut entropy_bits = Vec::with_capacity(leaf_level);
    let mut headers = 0u128;
    // How many times each node of the current level occurs in the tree.
    let mut multiplicity: Vec<u64> = if dag.is_empty() { Vec::new() } else { vec![1] };
    let mut starts = if leaf_level > 0 {
        node_starts(&sections[0])?
    } else {
        Vec::new()
    };
    if starts.len() != multiplicity.len() && leaf_level > 0 {
        return Err(FormatError::new(
            ErrorCode::BadRootLevel,
            sections[0].file_offset,
            format!("the root level holds {} nodes", starts.len()),
        )
        .at_level(0));
    }
    for level in 0..leaf_level {
        let child = &sections[level + 1];
        // For a node level, maps word offsets to node indices (u32::MAX: not a record start).
        let (child_starts, child_count, word_to_index) = if child.is_leaf {
            (Vec::new(), child.node_count, Vec::new())
        } else {
            let child_starts = node_starts(child)?;
            let mut map = vec![u32::MAX; child.bytes.len() / 4];
            for (index, &word) in child_starts.iter().enumerate() {
                map[word as usize] = index as u32;
            }
            let count = child_starts.len() as u64;
            (child_starts, count, map)
        };
        let mut next = vec![0u64; child_count as usize];
        // How many pointers of this level name each node of the next.
        let mut named = vec![0u32; child_count as usize];
        for (index, (&word, &m)) in starts.iter().zip(&multiplicity).enumerate() {
            let node = dag.node(level as u8, word)?;
            let record = 4 + 4 * u128::from(node.child_count());
            headers += 4;
            classic += record;
            svo += record * u128::from(m);
            for rank in 0..node.child_count() {
                let pointer = node.pointer_at(rank);
                let target = if child.is_leaf {
                    (u64::from(pointer) < child_count).then_some(pointer as usize)
                } else {
                    match word_to_index.get(pointer as usize) {
                        None => None,
                        Some(&u32::MAX) => {
                            return Err(FormatError::new(
                                ErrorCode::PointerNotAtNode,
                                sections[level].file_offset + u64::from(word) * 4,
                                format!("pointer {pointer} does not address the start of a node of level {}", level + 1),
                            )
                            .at_level(level as u8)
                            .at_node(index as u64));
                        }
                        Some(&i) => Some(i as usize),
                    }
                };
                let Some(target) = target else {
                    return Err(FormatError::new(
                        ErrorCode::PointerOutOfRange,
                        sections[level].file_offset + u64::from(word) * 4,
                        format!(
                            "pointer {pointer} lies outside level {} ({} units)",
                            level + 1,
                            child.units()
                        ),
                    )
                    .at_level(level as u8)
                    .at_node(index as u64));
                };
                next[target] = next[target].saturating_add(m);
                named[target] = named[target].saturating_add(1);
            }
        }
        entropy_bits.push(entropy_bits_of(&named));
        let section = &sections[level];
        levels.push(LevelStats {
            level: level as u8,
            node_count: starts.len() as u64,
            bytes: section.bytes.len() as u64,
            pointer_width: section.pointer_width,
            tree_nodes: multiplicity.iter().map(|&m| u128::from(m)).sum(),
        });
        multiplicity = next;
        starts = child_starts;
    }
    let leaves = &sections[leaf_level];
    if multiplicity.len() as u64 != leaves.node_count {
        return Err(FormatError::new(
            ErrorCode::BadRootLevel,
            leaves.file_offset,
            format!(
                "the root level is the leaf level and holds {} leaves",
                leaves.node_count
            ),
        )
        .at_level(0));
    }
    let tree_leaves: u128 = multiplicity.iter().map(|&m| u128::from(m)).sum();
    classic += 8 * u128::from(leaves.node_count);
    svo += 8 * tree_leaves;
    levels.push(LevelStats {
        level: leaf_level as u8,
        node_count: leaves.node_count,
        bytes: leaves.bytes.len() as u64,
        pointer_width: 0,
        tree_nodes: tree_leaves,
    });
    let header = dag.header();
    let pointer_bits: u128 = entropy_bits.iter().map(|&b| u128::from(b)).sum();
    let pointer_entropy_bound_bytes =
        headers + 8 * u128::from(leaves.node_count) + pointer_bits.div_ceil(8);
    Ok(DagStats {
        depth: header.depth,
        attribute_kind: header.attribute_kind,
        voxel_count: header.voxel_count,
        file_bytes: dag.bytes().len() as u64,
        level_bytes: levels.iter().map(|l| l.bytes).sum(),
        dag_nodes: levels.iter().map(|l| l.node_count).sum(),
        tree_nodes: levels.iter().map(|l| l.tree_nodes).sum(),
        classic_svdag_bytes: classic,
        svo_bytes: svo,
        pointer_entropy_bits: entropy_bits,
        pointer_entropy_bound_bytes,
        levels,
    })
}

/// Total zero-order entropy, in bits rounded up, of a sequence of symbols
/// that holds symbol `i` `counts[i]` times: `sum(n_i * log2(N / n_i))`.
fn entropy_bits_of(counts: &[u32]) -> u64 {
    let total: f64 = counts.iter().map(|&c| f64::from(c)).sum();
    if total == 0.0 {
        return 0;
    }
    let bits: f64 = counts
        .iter()
        .filter(|&&c| c > 0)
        .map(|&c| f64::from(c) * (total / f64::from(c)).log2())
        .sum();
    bits.ceil() as u64
}

/// The size of one set of voxels in the layouts that format 2.0 is measured
/// against (spec §23.9): what `dagtool info` lists and the size benchmark
/// (`examples/format2_sizes.rs`) tabulates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FormatSizes {
    /// The classic SVDAG layout (32-bit headers and pointers, 64-bit leaves).
    pub classic_svdag_bytes: u128,
    /// The 1.0 file of the voxels: its level sections with header, table and
    /// section padding (no colour or optional section).
    pub v1_bytes: u64,
    /// The SSVDAG encoding (Villanueva, Marton and Gobbetti 2016) of the
    /// voxels merged under the 8 reflections, level data only
    /// ([`ssvdag_bytes`]).
    pub ssvdag_bytes: u64,
}

/// The sizes of [`FormatSizes`] for the voxels of the 1.0 DAG `dag` (with
/// its statistics `stats`). Merging under the reflections takes time and
/// memory linear in the DAG (spec §23.7).
pub fn format_sizes(dag: &Dag<'_>, stats: &DagStats) -> Result<FormatSizes, FormatError> {
    let levels = stats.levels.len() as u64;
    let v1_bytes = layout::HEADER_SIZE as u64
        + layout::SECTION_ENTRY_SIZE as u64 * levels
        + stats
            .levels
            .iter()
            .map(|l| l.bytes.div_ceil(8) * 8)
            .sum::<u64>();
    let sym = crate::symmetry::canonicalize(
        dag,
        crate::symmetry::Group::Reflections,
        crate::symmetry::Group::Reflections,
    )?;
    Ok(FormatSizes {
        classic_svdag_bytes: stats.classic_svdag_bytes,
        v1_bytes,
        ssvdag_bytes: ssvdag_bytes(&sym),
    })
}

/// Bytes of the SSVDAG encoding of the merged DAG `dag`, level data only, as
/// the authors' public encoder lays it out: a 16-bit header per interior
/// node (2 bits per child: none, 16-bit or 32-bit reference); references of
/// 16 bits (13 address bits + 3 reflection bits) when the target's address
/// is below 2^13, else 32 bits; interior addresses count 16-bit words within
/// the level, leaves are 64-bit masks addressed by index; each level sorted
/// by how many references of the level above name a node (ties: first
/// occurrence).
pub fn ssvdag_bytes(dag: &crate::symmetry::SymDag) -> u64 {
    let leaf_level = dag.node_levels.len();
    let mut total = 8 * dag.leaves.len() as u64;
    let mut addr = vec![0u64; dag.leaves.len()];
    for (pos, &class) in dag
        .classes_by_reference_count(leaf_level)
        .iter()
        .enumerate()
    {
        addr[class as usize] = pos as u64;
    }
    for level in (0..leaf_level).rev() {
        let nodes = &dag.node_levels[level];
        let mut next_addr = vec![0u64; nodes.len()];
        let mut offset = 0u64;
        for &class in &dag.classes_by_reference_count(level) {
            let node = &nodes[class as usize];
            let mut size = 2u64;
            for s in 0..8 {
                if let Some(r) = node.child(s) {
                    size += if addr[r.class as usize] < 1 << 13 {
                        2
                    } else {
                        4
                    };
                }
            }
            next_addr[class as usize] = offset / 2;
            offset += size;
        }
        total += offset;
        addr = next_addr;
    }
    total
}

#[cfg(test)]
mod format_size_tests {
    use super::*;
    use crate::builder::DagBuilder;

    fn sizes(voxels: &[[u32; 3]]) -> FormatSizes {
        let bytes = DagBuilder::from_voxels(3, AttributeKind::VoxelCount, voxels.iter().copied())
            .unwrap()
            .to_bytes();
        let dag = Dag::open(&bytes).unwrap();
        format_sizes(&dag, &analyze(&dag).unwrap()).unwrap()
    }

    #[test]
    fn ssvdag_sizes_by_hand() {
        // Depth 3: a root record over 4³ leaves. One voxel: one leaf (8
        // bytes), a root of a 16-bit header and one 16-bit reference.
        let one = sizes(&[[0, 0, 0]]);
        assert_eq!(one.ssvdag_bytes, 8 + 2 + 2);
        // Classic: a 4-byte header and one 4-byte pointer, one 8-byte leaf.
        assert_eq!(one.classic_svdag_bytes, 8 + 8);
        // 1.0: header, two entries, the 8-byte root record and the leaf.
        assert_eq!(one.v1_bytes, 128 + 80 + 8 + 8);
        // Two mirror images in x: one leaf class, two references.
        let mirrored = sizes(&[[0, 0, 0], [7, 0, 0]]);
        assert_eq!(mirrored.ssvdag_bytes, 8 + 2 + 2 * 2);
        assert_eq!(mirrored.classic_svdag_bytes, 4 + 2 * 4 + 2 * 8);
    }
}
