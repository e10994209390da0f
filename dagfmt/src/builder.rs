//! [`DagBuilder`]: makes a `.vdag` file from voxels, bottom-up, with
//! per-level deduplication of identical subtrees.
//!
//! # How it works
//!
//! Voxels (or whole 4³ bricks) arrive in increasing Morton order. The builder
//! keeps one *pending* node per interior level (the node whose children are
//! still arriving); when a voxel arrives whose path leaves a pending node, that
//! node is complete and is *interned*: looked up in its level's hash table and
//! either found (a duplicate, so its existing id is reused) or appended to the
//! level's arena. Children are interned before their parents, so two subtrees
//! are identical exactly when their child masks and child ids are identical,
//! and one hash-table probe per node decides it.
//!
//! Memory therefore grows with the number of *distinct* nodes, never with the
//! resolution (the pending state is one node per level): per distinct interior
//! node about 40 to 50 bytes (its mask and child ids, an 8-byte start, an
//! 8-byte voxel count for attribute kind 1, and its hash-table entry), per
//! distinct leaf about 20, plus the slack of growing vectors. A 16384³ sphere
//! shell (69 M bricks, 11 M distinct nodes) peaks at about 850 MiB.
//!
//! # Out-of-core use
//!
//! A converter for meshes too large to voxelize at once only needs to emit
//! bricks in increasing Morton order, e.g. by voxelizing one block of 2^k
//! bricks per axis at a time, visiting the blocks in Morton order and sorting
//! each block's bricks before pushing them. [`DagBuilder::memory_bytes`] and
//! [`DagBuilder::distinct_nodes`] report the builder's footprint as it grows;
//! [`BuiltDag::write_to`] streams the file without a whole-file buffer.
//!
//! When the distinct nodes themselves do not fit in memory, the build can be
//! split into *runs* of complete subtrees rooted at a split level P: a builder
//! that [records subtrees](DagBuilder::record_subtrees) hands out, at a cell
//! boundary of level P, the distinct nodes of levels P ..= D − 2 with
//! builder-local ids and the roots ([`DagBuilder::finish_subtrees`]); the
//! caller stores them, starts a new builder for the next Morton range, and
//! later deduplicates the runs' nodes level by level, bottom up, encoding the
//! records with [`layout::encode_node_record`]. [`UpperBuilder`] then builds
//! levels 0 .. P from the roots, and [`FileLayout`] writes the file from the
//! sections' lengths and checksums. This module does no file I/O: `dagtool`'s
//! converter does the storing and merging (`dagtool/src/external.rs`).
//!
//! Nodes are written in first-seen order (post-order of the Morton-order
//! build); any order is valid.

use std::io::{self, Write};

use hashbrown::HashTable;
use thiserror::Error;

use crate::assemble::{FileHeader, FileLayout, SectionInfo};
use crate::layout::{
    self, AttributeKind, MAX_DEPTH, MAX_LEAF_COUNT, MAX_NODE_LEVEL_BYTES, MIN_DEPTH,
};
use crate::morton;
pub use crate::stats::LevelStats;

/// Why a DAG could not be built.
#[derive(Clone, Debug, Error, PartialEq)]
pub enum BuildError {
    /// The depth is outside `2 ..= 21`.
    #[error("depth {depth} is outside {MIN_DEPTH}..={MAX_DEPTH}")]
    DepthOutOfRange {
        /// The depth asked for.
        depth: u8,
    },
    /// A Morton code was not greater than the one pushed before it.
    #[error(
        "{unit} Morton code {code:#x} is not greater than the previous {previous:#x} (codes must be strictly increasing)"
    )]
    NotIncreasing {
        /// `"voxel"` or `"brick"`.
        unit: &'static str,
        /// The previous code, in the same unit.
        previous: u64,
        /// The offending code.
        code: u64,
    },
    /// A Morton code lies outside the volume.
    #[error("{unit} Morton code {code:#x} is outside a depth-{depth} volume")]
    OutOfVolume {
        /// `"voxel"` or `"brick"`.
        unit: &'static str,
        /// The offending code.
        code: u64,
        /// The builder's depth.
        depth: u8,
    },
    /// Voxel coordinates lie outside the volume.
    #[error("voxel {voxel:?} is outside the {resolution}^3 volume")]
    VoxelOutOfVolume {
        /// The offending coordinates.
        voxel: [u32; 3],
        /// Voxels along each axis.
        resolution: u64,
    },
    /// The number of colours differs from the number of voxels.
    #[error("{got} colours given for {expected} voxels (one RGBA colour per voxel is needed)")]
    ColorCount {
        /// Voxels in the DAG.
        expected: u64,
        /// Colours given.
        got: u64,
    },
    /// A colour error bound over 127 (packed colours).
    #[error("colour error bound {0} exceeds 127")]
    ErrorBound(u8),
    /// Colours were given for a DAG without voxel-count attributes.
    #[error("a colour section needs attribute kind 1 (voxel counts) to index the colours")]
    ColorsNeedVoxelCount,
    /// The root cube is not finite with a positive size.
    #[error("root cube min {min:?} size {size} is not finite with a positive size")]
    BadRootCube {
        /// The corner given.
        min: [f64; 3],
        /// The size given.
        size: f64,
    },
    /// The DAG exceeds a limit of the format.
    #[error("too large: {what}")]
    TooLarge {
        /// Which limit, and by how much.
        what: String,
    },
    /// The pieces given do not make a valid file (a section table that breaks
    /// a rule of the format, a subtree without voxels, a bad split level).
    #[error("{what}")]
    Invalid {
        /// What is wrong.
        what: String,
    },
}

/// One interior node whose children are still arriving.
#[derive(Clone, Copy, Debug, Default)]
struct PendingNode {
    /// Morton prefix of the node (its code at its own level).
    prefix: u64,
    /// Child mask so far; zero when no node is pending.
    mask: u8,
    /// Number of children so far.
    len: u8,
    /// Child ids in increasing child index order.
    children: [u32; 8],
    /// Voxels in the children so far.
    count: u64,
}

/// The distinct nodes of one interior level, as they are being built.
#[derive(Debug, Default)]
struct NodeArena {
    /// Per node: the child mask, then the child ids (in child index order).
    words: Vec<u32>,
    /// Index in `words` of each node's mask word.
    starts: Vec<u64>,
    /// Voxels in each node's subtree (empty for attribute kind 0).
    counts: Vec<u64>,
}

impl NodeArena {
    fn len(&self) -> usize {
        self.starts.len()
    }

    /// Mask and children of node `id`.
    #[inline]
    fn node(&self, id: u32) -> (u32, &[u32]) {
        let start = self.starts[id as usize] as usize;
        let mask = self.words[start];
        (
            mask,
            &self.words[start + 1..start + 1 + mask.count_ones() as usize],
        )
    }

    fn heap_bytes(&self) -> usize {
        self.words.capacity() * 4 + self.starts.capacity() * 8 + self.counts.capacity() * 8
    }
}

/// 64-bit finaliser of MurmurHash3: every input bit affects every output bit,
/// which hashbrown needs (it takes the bucket from the low bits and a tag from
/// the top seven). Public for builders outside this crate that deduplicate
/// records the same way (`dagtool`'s out-of-core merge).
#[inline]
pub fn fmix64(mut x: u64) -> u64 {
    x ^= x >> 33;
    x = x.wrapping_mul(0xff51_afd7_ed55_8ccd);
    x ^= x >> 33;
    x = x.wrapping_mul(0xc4ce_b9fe_1a85_ec53);
    x ^ (x >> 33)
}

#[inline]
fn hash_leaf(mask: u64) -> u32 {
    (fmix64(mask) >> 32) as u32
}

#[inline]
fn hash_node(mask: u32, children: &[u32]) -> u32 {
    const K: u64 = 0x9e37_79b9_7f4a_7c15;
    let mut h = u64::from(mask).wrapping_mul(K);
    for pair in children.chunks(2) {
        let word = u64::from(pair[0]) | pair.get(1).map_or(0, |&c| u64::from(c) << 32);
        h = (h ^ word).wrapping_mul(K).rotate_left(31);
    }
    (fmix64(h) >> 32) as u32
}

/// A dedup table entry: the node's 32-bit content hash (high half) and its
/// id (low half). Keeping the hash in the entry lets the table grow without
/// reading the arenas, and rejects most mismatches without touching them.
type Entry = u64;

#[inline]
fn entry(hash: u32, id: u32) -> Entry {
    u64::from(hash) << 32 | u64::from(id)
}

#[inline]
fn entry_id(e: Entry) -> u32 {
    e as u32
}

#[inline]
fn entry_hash(e: Entry) -> u32 {
    (e >> 32) as u32
}

/// The 64-bit hash hashbrown wants, from a 32-bit content hash: the table
/// takes bucket bits from the bottom and a 7-bit tag from the top, so both
/// halves carry the hash.
#[inline]
fn table_hash(hash: u32) -> u64 {
    u64::from(hash) << 32 | u64::from(hash)
}

fn check_depth(depth: u8) -> Result<(), BuildError> {
    if (MIN_DEPTH..=MAX_DEPTH).contains(&depth) {
        Ok(())
    } else {
        Err(BuildError::DepthOutOfRange { depth })
    }
}

fn check_root_cube(min: [f64; 3], size: f64) -> Result<(), BuildError> {
    if min.iter().all(|v| v.is_finite()) && size.is_finite() && size > 0.0 {
        Ok(())
    } else {
        Err(BuildError::BadRootCube { min, size })
    }
}

/// Streaming builder of a `.vdag` DAG from voxels or 4³ bricks pushed in
/// increasing Morton order. See the [module documentation](self).
#[derive(Debug)]
pub struct DagBuilder {
    depth: u8,
    attributes: AttributeKind,
    root_min: [f64; 3],
    root_size: f64,
    /// Interior levels `0 .. depth - 2`.
    arenas: Vec<NodeArena>,
    /// Dedup table of each interior level: node ids keyed by content.
    tables: Vec<HashTable<Entry>>,
    /// The distinct leaf masks (level `depth - 2`).
    leaves: Vec<u64>,
    leaf_table: HashTable<Entry>,
    /// The pending node of each interior level.
    pending: Vec<PendingNode>,
    /// The brick being filled by `push_morton`, and its mask (0: none).
    current_brick: u64,
    current_mask: u64,
    /// The greatest voxel code covered by the pushes so far.
    last_voxel: Option<u64>,
    /// Exclusive upper bound of brick codes: 8^(depth - 2).
    brick_limit: u64,
    voxel_count: u64,
    /// The level whose completed nodes are recorded as subtree roots.
    split: Option<u8>,
    roots: Vec<SubtreeRoot>,
}

impl DagBuilder {
    /// A builder for a volume of 2^`depth` voxels per axis (`depth` in 2..=21)
    /// whose nodes carry `attributes`.
    pub fn new(depth: u8, attributes: AttributeKind) -> Result<Self, BuildError> {
        check_depth(depth)?;
        let interior = usize::from(depth - 2);
        Ok(DagBuilder {
            depth,
            attributes,
            root_min: [0.0; 3],
            root_size: 1.0,
            arenas: (0..interior).map(|_| NodeArena::default()).collect(),
            tables: (0..interior).map(|_| HashTable::new()).collect(),
            leaves: Vec::new(),
            leaf_table: HashTable::new(),
            pending: vec![PendingNode::default(); interior],
            current_brick: 0,
            current_mask: 0,
            last_voxel: None,
            brick_limit: 1u64 << (3 * u32::from(depth - 2)),
            voxel_count: 0,
            split: None,
            roots: Vec::new(),
        })
    }

    /// Sets the world-space cube the volume spans (default: corner `[0, 0, 0]`,
    /// size 1). [`DagBuilder::finish`] rejects a cube that is not finite with a
    /// positive size.
    pub fn set_root_cube(&mut self, min: [f64; 3], size: f64) {
        self.root_min = min;
        self.root_size = size;
    }

    /// Depth D of the volume being built.
    pub fn depth(&self) -> u8 {
        self.depth
    }

    /// Voxels pushed so far.
    pub fn voxel_count(&self) -> u64 {
        self.voxel_count + u64::from(self.current_mask.count_ones())
    }

    /// Distinct nodes interned so far, per level (root first, leaves last).
    pub fn distinct_nodes(&self) -> Vec<u64> {
        let mut counts: Vec<u64> = self.arenas.iter().map(|a| a.len() as u64).collect();
        counts.push(self.leaves.len() as u64);
        counts
    }

    /// Approximate heap memory held by the builder, in bytes (the capacity
    /// of its vectors and hash tables).
    pub fn memory_bytes(&self) -> usize {
        let tables: usize = self.tables.iter().map(|t| t.allocation_size()).sum();
        let arenas: usize = self.arenas.iter().map(NodeArena::heap_bytes).sum();
        tables
            + arenas
            + self.leaf_table.allocation_size()
            + self.leaves.capacity() * 8
            + self.roots.capacity() * size_of::<SubtreeRoot>()
    }

    /// The largest extra allocation the next push can make while the old one
    /// is still held: a hash table that grows allocates its new table (twice
    /// the size) before freeing the old. So `memory_bytes() + growth_bytes()`
    /// bounds the builder's heap during the next push. (Vectors grow by
    /// reallocation, which allocators do for large blocks by remapping pages,
    /// and the pages of new capacity are not resident until written.)
    pub fn growth_bytes(&self) -> usize {
        self.tables
            .iter()
            .chain(std::iter::once(&self.leaf_table))
            .map(|t| 2 * t.allocation_size())
            .max()
            .unwrap_or(0)
    }

    /// Records every completed node of `split` (`1 ..= depth - 2`) as the
    /// root of a subtree, for [`DagBuilder::finish_subtrees`]. Call it before
    /// the first push. The builder still builds the whole DAG, so
    /// [`DagBuilder::finish`] works as usual: a caller can decide at the end
    /// whether it wants the file or the subtrees.
    pub fn record_subtrees(&mut self, split: u8) -> Result<(), BuildError> {
        check_split(self.depth, split)?;
        if self.last_voxel.is_some() {
            return Err(BuildError::Invalid {
                what: "record_subtrees must be called before the first push".into(),
            });
        }
        self.split = Some(split);
        Ok(())
    }

    /// Completes the nodes of the split level and below, and returns the
    /// distinct nodes of those levels with the recorded roots
    /// ([`DagBuilder::record_subtrees`]). Meant to be called after a push
    /// that completed a split-level cell, so that the subtrees are whole
    /// (the next push of the same volume would start a new cell); the levels
    /// above the split level are dropped.
    pub fn finish_subtrees(mut self) -> Result<Subtrees, BuildError> {
        let split = self.split.ok_or_else(|| BuildError::Invalid {
            what: "finish_subtrees needs record_subtrees".into(),
        })?;
        if self.current_mask != 0 {
            self.commit_brick(self.current_brick, self.current_mask)?;
            self.current_mask = 0;
        }
        for level in (usize::from(split)..self.arenas.len()).rev() {
            if self.pending[level].mask != 0 {
                self.complete_pending(level)?;
            }
        }
        drop(std::mem::take(&mut self.tables));
        drop(std::mem::take(&mut self.leaf_table));
        Ok(Subtrees {
            depth: self.depth,
            split,
            attributes: self.attributes,
            levels: self.arenas.split_off(usize::from(split)),
            leaves: self.leaves,
            roots: self.roots,
        })
    }

    /// Adds the voxel with Morton code `code` ([`morton::encode`]). Codes must
    /// be strictly increasing (also across [`DagBuilder::push_brick`] calls).
    pub fn push_morton(&mut self, code: u64) -> Result<(), BuildError> {
        let brick = code >> 6;
        if brick >= self.brick_limit {
            return Err(BuildError::OutOfVolume {
                unit: "voxel",
                code,
                depth: self.depth,
            });
        }
        if let Some(previous) = self.last_voxel
            && code <= previous
        {
            return Err(BuildError::NotIncreasing {
                unit: "voxel",
                previous,
                code,
            });
        }
        self.last_voxel = Some(code);
        if self.current_mask != 0 && brick != self.current_brick {
            self.commit_brick(self.current_brick, self.current_mask)?;
            self.current_mask = 0;
        }
        self.current_brick = brick;
        self.current_mask |= 1 << (code & 63);
        Ok(())
    }

    /// Adds the voxels of 4³ brick `brick` (the Morton code of its voxels
    /// shifted right by 6) given by `mask` (bit [`layout::leaf_bit`]). Bricks
    /// must be strictly increasing, and after every voxel pushed before; a zero
    /// mask adds nothing.
    #[inline]
    pub fn push_brick(&mut self, brick: u64, mask: u64) -> Result<(), BuildError> {
        if brick >= self.brick_limit {
            return Err(BuildError::OutOfVolume {
                unit: "brick",
                code: brick,
                depth: self.depth,
            });
        }
        if let Some(previous) = self.last_voxel
            && brick <= previous >> 6
        {
            return Err(BuildError::NotIncreasing {
                unit: "brick",
                previous: previous >> 6,
                code: brick,
            });
        }
        self.last_voxel = Some(brick << 6 | 63);
        if self.current_mask != 0 {
            self.commit_brick(self.current_brick, self.current_mask)?;
            self.current_mask = 0;
        }
        if mask != 0 {
            self.commit_brick(brick, mask)?;
        }
        Ok(())
    }

    /// Interns a complete leaf and hands it to its parent.
    #[inline]
    fn commit_brick(&mut self, brick: u64, mask: u64) -> Result<(), BuildError> {
        let count = u64::from(mask.count_ones());
        self.voxel_count += count;
        let id = self.intern_leaf(mask)?;
        if self.split == Some(self.depth - 2) {
            self.roots.push(SubtreeRoot {
                code: brick,
                id,
                count,
            });
        }
        if self.arenas.is_empty() {
            // Depth 2: the leaf is the root; there is only brick 0.
            return Ok(());
        }
        self.add_child(self.arenas.len() - 1, brick, id, count)
    }

    #[inline]
    fn intern_leaf(&mut self, mask: u64) -> Result<u32, BuildError> {
        let leaves = &mut self.leaves;
        let hash = hash_leaf(mask);
        let found = self.leaf_table.entry(
            table_hash(hash),
            |&e| entry_hash(e) == hash && leaves[entry_id(e) as usize] == mask,
            |&e| table_hash(entry_hash(e)),
        );
        match found {
            hashbrown::hash_table::Entry::Occupied(e) => Ok(entry_id(*e.get())),
            hashbrown::hash_table::Entry::Vacant(e) => {
                let id = leaves.len() as u64;
                if id >= MAX_LEAF_COUNT {
                    return Err(BuildError::TooLarge {
                        what: format!("more than {MAX_LEAF_COUNT} distinct leaves"),
                    });
                }
                leaves.push(mask);
                e.insert(entry(hash, id as u32));
                Ok(id as u32)
            }
        }
    }

    /// Adds child `id` (holding `count` voxels, Morton code `code` at level
    /// `level + 1`) to the pending node of `level`, completing that node first
    /// when the child lies outside it.
    fn add_child(
        &mut self,
        level: usize,
        code: u64,
        id: u32,
        count: u64,
    ) -> Result<(), BuildError> {
        let parent = code >> 3;
        let pending = self.pending[level];
        if pending.mask != 0 && pending.prefix != parent {
            self.complete_pending(level)?;
        }
        let node = &mut self.pending[level];
        node.prefix = parent;
        node.mask |= 1 << (code & 7);
        node.children[usize::from(node.len)] = id;
        node.len += 1;
        node.count += count;
        Ok(())
    }

    /// Interns the pending node of `level` and hands it to its parent.
    fn complete_pending(&mut self, level: usize) -> Result<(), BuildError> {
        let node = std::mem::take(&mut self.pending[level]);
        let id = self.intern_node(level, &node)?;
        if self.split == Some(level as u8) {
            self.roots.push(SubtreeRoot {
                code: node.prefix,
                id,
                count: node.count,
            });
        }
        if level > 0 {
            self.add_child(level - 1, node.prefix, id, node.count)?;
        }
        Ok(())
    }

    fn intern_node(&mut self, level: usize, node: &PendingNode) -> Result<u32, BuildError> {
        let arena = &mut self.arenas[level];
        let mask = u32::from(node.mask);
        let children = &node.children[..usize::from(node.len)];
        let hash = hash_node(mask, children);
        let found = self.tables[level].entry(
            table_hash(hash),
            |&e| entry_hash(e) == hash && arena.node(entry_id(e)) == (mask, children),
            |&e| table_hash(entry_hash(e)),
        );
        match found {
            hashbrown::hash_table::Entry::Occupied(e) => Ok(entry_id(*e.get())),
            hashbrown::hash_table::Entry::Vacant(e) => {
                let id = u32::try_from(arena.len()).map_err(|_| BuildError::TooLarge {
                    what: format!("more than {} distinct nodes in level {level}", u32::MAX),
                })?;
                arena.starts.push(arena.words.len() as u64);
                arena.words.push(mask);
                arena.words.extend_from_slice(children);
                if self.attributes == AttributeKind::VoxelCount {
                    arena.counts.push(node.count);
                }
                e.insert(entry(hash, id));
                Ok(id)
            }
        }
    }

    /// Completes the DAG: interns the pending nodes, lays the file out and
    /// computes the section checksums.
    pub fn finish(mut self) -> Result<BuiltDag, BuildError> {
        check_root_cube(self.root_min, self.root_size)?;
        if self.current_mask != 0 {
            self.commit_brick(self.current_brick, self.current_mask)?;
            self.current_mask = 0;
        }
        for level in (0..self.arenas.len()).rev() {
            if self.pending[level].mask != 0 {
                self.complete_pending(level)?;
            }
        }
        // The dedup tables are no longer needed: free them before laying out.
        drop(std::mem::take(&mut self.tables));
        drop(std::mem::take(&mut self.leaf_table));
        let mut built = BuiltDag {
            depth: self.depth,
            attributes: self.attributes,
            root_min: self.root_min,
            root_size: self.root_size,
            voxel_count: self.voxel_count,
            levels: self
                .arenas
                .into_iter()
                .map(|arena| BuiltLevel {
                    arena,
                    offsets: Vec::new(),
                })
                .collect(),
            leaves: self.leaves,
            widths: Vec::new(),
            lengths: Vec::new(),
            crcs: Vec::new(),
            colors: None,
            colors_crc: 0,
            packed: None,
            packed_layout: crate::packed_colors::BlockLayout::V1_1,
            file: None,
        };
        built.lay_out()?;
        Ok(built)
    }

    /// Builds the DAG of the voxels where `f(x, y, z)` is true, calling `f`
    /// once for every voxel of the volume (8^depth calls: for small depths).
    pub fn from_fn(
        depth: u8,
        attributes: AttributeKind,
        mut f: impl FnMut(u32, u32, u32) -> bool,
    ) -> Result<BuiltDag, BuildError> {
        let mut builder = DagBuilder::new(depth, attributes)?;
        let offsets: [[u32; 3]; 64] = std::array::from_fn(|bit| morton::decode(bit as u64));
        for brick in 0..builder.brick_limit {
            let [bx, by, bz] = morton::decode(brick).map(|c| c * 4);
            let mut mask = 0u64;
            for (bit, [x, y, z]) in offsets.iter().enumerate() {
                if f(bx + x, by + y, bz + z) {
                    mask |= 1 << bit;
                }
            }
            builder.push_brick(brick, mask)?;
        }
        builder.finish()
    }

    /// Builds the DAG of the given voxels, in any order, duplicates allowed.
    pub fn from_voxels(
        depth: u8,
        attributes: AttributeKind,
        voxels: impl IntoIterator<Item = [u32; 3]>,
    ) -> Result<BuiltDag, BuildError> {
        let mut builder = DagBuilder::new(depth, attributes)?;
        let resolution = 1u64 << depth;
        let mut codes = Vec::new();
        for voxel in voxels {
            if voxel.iter().any(|&c| u64::from(c) >= resolution) {
                return Err(BuildError::VoxelOutOfVolume { voxel, resolution });
            }
            codes.push(morton::encode(voxel[0], voxel[1], voxel[2]));
        }
        codes.sort_unstable();
        codes.dedup();
        for code in codes {
            builder.push_morton(code)?;
        }
        builder.finish()
    }
}

/// One interior level of a finished DAG.
#[derive(Debug)]
struct BuiltLevel {
    arena: NodeArena,
    /// Word offset of each node's record in the section.
    offsets: Vec<u32>,
}

/// Widths, record offsets and lengths of consecutive interior levels whose
/// last level points into a level of `bottom_units` units (leaves, or words of
/// a node level built elsewhere). Returns the width and byte length of each.
fn lay_out_levels(
    levels: &mut [BuiltLevel],
    bottom_units: u64,
) -> Result<(Vec<u8>, Vec<u64>), BuildError> {
    let mut widths = vec![0; levels.len()];
    let mut lengths = vec![0; levels.len()];
    let mut child_units = bottom_units;
    for level in (0..levels.len()).rev() {
        let width =
            layout::minimal_pointer_width(child_units).ok_or_else(|| BuildError::TooLarge {
                what: format!(
                    "level {} has {child_units} units, more than 4-byte pointers address",
                    level + 1
                ),
            })?;
        let arena = &levels[level].arena;
        let mut offsets = Vec::with_capacity(arena.len());
        let mut words = 0u64;
        for id in 0..arena.len() {
            offsets.push(words as u32);
            let children = arena.node(id as u32).0.count_ones();
            words += layout::node_record_size(children, width) / 4;
            if words * 4 > MAX_NODE_LEVEL_BYTES {
                return Err(BuildError::TooLarge {
                    what: format!("level {level} exceeds {MAX_NODE_LEVEL_BYTES} bytes"),
                });
            }
        }
        levels[level].offsets = offsets;
        widths[level] = width;
        lengths[level] = words * 4;
        child_units = words;
    }
    Ok((widths, lengths))
}

/// Generates the records of `levels[index]` in chunks. Child ids become the
/// record offsets of `levels[index + 1]`; those of the last level are written
/// as they are (leaf indices, or pointers into a level built elsewhere).
fn emit_node_level(
    levels: &[BuiltLevel],
    index: usize,
    width: u8,
    attributes: AttributeKind,
    sink: &mut dyn FnMut(&[u8]) -> io::Result<()>,
) -> io::Result<()> {
    let level = &levels[index];
    let child_offsets = levels.get(index + 1).map(|l| &l.offsets[..]);
    let with_counts = attributes == AttributeKind::VoxelCount;
    let mut buffer = Vec::with_capacity(CHUNK + 64);
    let mut pointers = [0u32; 8];
    for id in 0..level.arena.len() {
        let (mask, children) = level.arena.node(id as u32);
        let attribute = if with_counts {
            level.arena.counts[id].min(u64::from(layout::COUNT_SATURATED)) as u32
        } else {
            0
        };
        for (p, &child) in pointers.iter_mut().zip(children) {
            *p = match child_offsets {
                Some(offsets) => offsets[child as usize],
                None => child,
            };
        }
        layout::encode_node_record(
            mask as u8,
            attribute,
            &pointers[..children.len()],
            width,
            &mut buffer,
        );
        if buffer.len() >= CHUNK {
            sink(&buffer)?;
            buffer.clear();
        }
    }
    if !buffer.is_empty() {
        sink(&buffer)?;
    }
    Ok(())
}

/// The CRC-32C of the bytes `emit` generates.
fn crc_of(emit: impl FnOnce(&mut dyn FnMut(&[u8]) -> io::Result<()>) -> io::Result<()>) -> u32 {
    let mut crc = 0u32;
    emit(&mut |chunk| {
        crc = crc32c::crc32c_append(crc, chunk);
        Ok(())
    })
    .expect("the checksum sink cannot fail");
    crc
}

/// A finished DAG, ready to be written. Made by [`DagBuilder::finish`].
#[derive(Debug)]
pub struct BuiltDag {
    depth: u8,
    attributes: AttributeKind,
    root_min: [f64; 3],
    root_size: f64,
    voxel_count: u64,
    /// Interior levels `0 .. depth - 2`.
    levels: Vec<BuiltLevel>,
    /// Leaf masks of level `depth - 2`, in leaf index order.
    leaves: Vec<u64>,
    /// Pointer width of each interior level.
    widths: Vec<u8>,
    /// Byte length of each level section (interior levels, then the leaf level).
    lengths: Vec<u64>,
    /// CRC-32C of each level section.
    crcs: Vec<u32>,
    colors: Option<Vec<[u8; 4]>>,
    colors_crc: u32,
    /// A packed colour section's bytes, instead of `colors`.
    packed: Option<Vec<u8>>,
    /// The packed section's block layout.
    packed_layout: crate::packed_colors::BlockLayout,
    /// The file as it will be written (placed by [`FileLayout`]).
    file: Option<FileLayout>,
}

/// Bytes gathered before handing them to a sink while generating a section.
const CHUNK: usize = 1 << 16;

impl BuiltDag {
    /// Number of set voxels.
    pub fn voxel_count(&self) -> u64 {
        self.voxel_count
    }

    /// Depth D.
    pub fn depth(&self) -> u8 {
        self.depth
    }

    /// The attribute kind of the nodes.
    pub fn attributes(&self) -> AttributeKind {
        self.attributes
    }

    /// Sets the world-space root cube (see [`DagBuilder::set_root_cube`]).
    pub fn set_root_cube(&mut self, min: [f64; 3], size: f64) -> Result<(), BuildError> {
        check_root_cube(min, size)?;
        self.root_min = min;
        self.root_size = size;
        self.place()
    }

    /// Attaches one RGBA8 colour per voxel, in dense index (Morton) order, as
    /// a `VOXEL_COLORS` section. Needs attribute kind 1.
    pub fn set_colors(&mut self, rgba: Vec<[u8; 4]>) -> Result<(), BuildError> {
        if self.attributes != AttributeKind::VoxelCount {
            return Err(BuildError::ColorsNeedVoxelCount);
        }
        if rgba.len() as u64 != self.voxel_count {
            return Err(BuildError::ColorCount {
                expected: self.voxel_count,
                got: rgba.len() as u64,
            });
        }
        self.colors_crc = crc32c::crc32c(rgba.as_flattened());
        self.colors = Some(rgba);
        if let Err(e) = self.place() {
            self.colors = None;
            self.colors_crc = 0;
            self.place()?;
            return Err(e);
        }
        Ok(())
    }

    /// Attaches one RGBA8 colour per voxel, in dense index (Morton) order, as
    /// a PACKED_COLORS section coded within `error_bound` per channel (0:
    /// lossless; at most [`crate::packed_colors::MAX_ERROR_BOUND`]). Needs
    /// attribute kind 1. Replaces colours attached before.
    pub fn set_packed_colors(
        &mut self,
        rgba: &[[u8; 4]],
        error_bound: u8,
    ) -> Result<crate::packed_colors::PackedSummary, BuildError> {
        if self.attributes != AttributeKind::VoxelCount {
            return Err(BuildError::ColorsNeedVoxelCount);
        }
        if rgba.len() as u64 != self.voxel_count {
            return Err(BuildError::ColorCount {
                expected: self.voxel_count,
                got: rgba.len() as u64,
            });
        }
        let (bytes, summary) = crate::packed_colors::encode(rgba, error_bound)
            .ok_or(BuildError::ErrorBound(error_bound))?;
        self.colors_crc = crc32c::crc32c(&bytes);
        self.colors = None;
        self.packed = Some(bytes);
        self.packed_layout = summary.trailer.layout;
        if let Err(e) = self.place() {
            self.packed = None;
            self.colors_crc = 0;
            self.place()?;
            return Err(e);
        }
        Ok(summary)
    }

    /// Per-level statistics (root first, leaf level last), including the node
    /// count a tree without deduplication would have.
    pub fn level_stats(&self) -> Vec<LevelStats> {
        let leaf_level = self.levels.len();
        let mut stats = Vec::with_capacity(leaf_level + 1);
        // Multiplicity of each node: how many times it occurs in the tree.
        let mut multiplicity: Vec<u64> = if self.voxel_count == 0 {
            Vec::new()
        } else {
            vec![1]
        };
        for (level, built) in self.levels.iter().enumerate() {
            let child_count = match self.levels.get(level + 1) {
                Some(next) => next.arena.len(),
                None => self.leaves.len(),
            };
            let mut next = vec![0u64; child_count];
            for (id, &m) in multiplicity.iter().enumerate() {
                for &child in built.arena.node(id as u32).1 {
                    next[child as usize] = next[child as usize].saturating_add(m);
                }
            }
            stats.push(LevelStats {
                level: level as u8,
                node_count: built.arena.len() as u64,
                bytes: self.lengths[level],
                pointer_width: self.widths[level],
                tree_nodes: multiplicity.iter().map(|&m| u128::from(m)).sum(),
            });
            multiplicity = next;
        }
        stats.push(LevelStats {
            level: leaf_level as u8,
            node_count: self.leaves.len() as u64,
            bytes: self.lengths[leaf_level],
            pointer_width: 0,
            tree_nodes: multiplicity.iter().map(|&m| u128::from(m)).sum(),
        });
        stats
    }

    /// Size of the file in bytes.
    pub fn file_size(&self) -> u64 {
        self.layout().file_size()
    }

    /// The file's header fields and sections, as [`BuiltDag::write_to`]
    /// writes them. A caller that adds a section of its own (a colour section
    /// streamed from elsewhere, with [`FileLayout::with_section`]) writes the
    /// file with [`FileLayout::write_to`], taking the bytes of this DAG's
    /// sections from [`BuiltDag::emit_section`].
    pub fn layout(&self) -> &FileLayout {
        self.file
            .as_ref()
            .expect("a BuiltDag is placed when it is made")
    }

    /// Writes the file. Sections are generated in chunks: no whole-file buffer.
    pub fn write_to<W: Write>(&self, w: &mut W) -> io::Result<()> {
        self.layout()
            .write_to(w, |index, sink| self.emit_section(index, sink))
    }

    /// The whole file in memory.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut bytes = Vec::with_capacity(self.file_size() as usize);
        self.write_to(&mut bytes)
            .expect("writing to a Vec cannot fail");
        bytes
    }

    /// Computes pointer widths, record offsets and level checksums.
    fn lay_out(&mut self) -> Result<(), BuildError> {
        let leaf_level = self.levels.len();
        if self.leaves.len() as u64 > MAX_LEAF_COUNT {
            return Err(BuildError::TooLarge {
                what: format!(
                    "{} leaves exceed the limit of {MAX_LEAF_COUNT}",
                    self.leaves.len()
                ),
            });
        }
        let (widths, mut lengths) = lay_out_levels(&mut self.levels, self.leaves.len() as u64)?;
        lengths.push(self.leaves.len() as u64 * 8);
        self.widths = widths;
        self.lengths = lengths;
        self.crcs = (0..=leaf_level)
            .map(|index| crc_of(|sink| self.emit_section(index, sink)))
            .collect();
        self.place()
    }

    /// Places the sections (the level sections, then the colours if any).
    fn place(&mut self) -> Result<(), BuildError> {
        let leaf_level = self.levels.len();
        let mut sections: Vec<SectionInfo> = (0..leaf_level)
            .map(|level| {
                SectionInfo::node_level(
                    level as u8,
                    self.widths[level],
                    self.lengths[level],
                    self.levels[level].arena.len() as u64,
                    self.crcs[level],
                )
            })
            .collect();
        sections.push(SectionInfo::leaf_level(
            leaf_level as u8,
            self.leaves.len() as u64,
            self.crcs[leaf_level],
        ));
        if let Some(colors) = &self.colors {
            sections.push(SectionInfo::voxel_colors(
                colors.len() as u64,
                self.colors_crc,
            ));
        }
        if let Some(packed) = &self.packed {
            sections.push(SectionInfo::packed_colors(
                self.voxel_count,
                packed.len() as u64,
                self.colors_crc,
                self.packed_layout,
            ));
        }
        let header = FileHeader {
            depth: self.depth,
            attributes: self.attributes,
            root_min: self.root_min,
            root_size: self.root_size,
            voxel_count: self.voxel_count,
        };
        self.file = Some(FileLayout::new(header, sections)?);
        Ok(())
    }

    /// Generates the bytes of section `index` (in [`BuiltDag::layout`]'s
    /// order: the levels root first, then the colours) in chunks.
    pub fn emit_section(
        &self,
        index: usize,
        sink: &mut dyn FnMut(&[u8]) -> io::Result<()>,
    ) -> io::Result<()> {
        let leaf_level = self.levels.len();
        if index > leaf_level {
            let colors = match (&self.colors, &self.packed) {
                (Some(colors), _) => colors.as_flattened(),
                (None, Some(packed)) => packed,
                (None, None) => &[],
            };
            for chunk in colors.chunks(CHUNK) {
                sink(chunk)?;
            }
            return Ok(());
        }
        if index < leaf_level {
            return emit_node_level(
                &self.levels,
                index,
                self.widths[index],
                self.attributes,
                sink,
            );
        }
        let mut buffer = Vec::with_capacity(CHUNK);
        for chunk in self.leaves.chunks(CHUNK / 8) {
            buffer.clear();
            for &leaf in chunk {
                buffer.extend_from_slice(&leaf.to_le_bytes());
            }
            sink(&buffer)?;
        }
        Ok(())
    }
}

/// A completed level-`split` node of a [`DagBuilder`] that records subtrees
/// ([`DagBuilder::record_subtrees`]): the root of one complete subtree.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SubtreeRoot {
    /// Morton code of the node's cell at the split level (§11).
    pub code: u64,
    /// The node's id in its level of the [`Subtrees`] (a leaf index when the
    /// split level is the leaf level).
    pub id: u32,
    /// Set voxels in the subtree.
    pub count: u64,
}

/// The distinct nodes of the levels `split ..= depth - 2` of a Morton range
/// of complete subtrees, with builder-local ids, and their roots. Made by
/// [`DagBuilder::finish_subtrees`]; an out-of-core converter stores them and
/// merges several of them later (see the [module documentation](self)).
#[derive(Debug)]
pub struct Subtrees {
    depth: u8,
    split: u8,
    attributes: AttributeKind,
    /// Interior levels `split .. depth - 2`.
    levels: Vec<NodeArena>,
    leaves: Vec<u64>,
    roots: Vec<SubtreeRoot>,
}

impl Subtrees {
    /// Depth D of the volume.
    pub fn depth(&self) -> u8 {
        self.depth
    }

    /// The level of the roots.
    pub fn split_level(&self) -> u8 {
        self.split
    }

    /// Distinct nodes of `level` (`split ..= depth - 2`; the last is the leaf level).
    pub fn node_count(&self, level: u8) -> usize {
        if level == self.depth - 2 {
            self.leaves.len()
        } else {
            self.levels[usize::from(level - self.split)].len()
        }
    }

    /// Node `id` of interior `level` (`split ..= depth - 3`): its header word
    /// as a file stores it (child mask | attribute << 8, the attribute being
    /// the saturated voxel count for attribute kind 1) and its children's ids
    /// in the next level, in child index order. Panics when out of range.
    pub fn node(&self, level: u8, id: u32) -> (u32, &[u32]) {
        let arena = &self.levels[usize::from(level - self.split)];
        let (mask, children) = arena.node(id);
        let attribute = match self.attributes {
            AttributeKind::VoxelCount => {
                arena.counts[id as usize].min(u64::from(layout::COUNT_SATURATED)) as u32
            }
            AttributeKind::None => 0,
        };
        (mask | attribute << layout::CHILD_MASK_BITS, children)
    }

    /// The distinct leaf masks, in leaf id order.
    pub fn leaves(&self) -> &[u64] {
        &self.leaves
    }

    /// The roots, in Morton order.
    pub fn roots(&self) -> &[SubtreeRoot] {
        &self.roots
    }
}

/// Builds the levels above a split level from the roots of complete
/// subtrees whose level-`split` records are laid out elsewhere: the top of an
/// out-of-core build. Subtrees arrive in increasing Morton order as
/// (code, pointer, voxel count), the pointer being the position (word offset,
/// or leaf index when the split level is the leaf level) of the subtree's root
/// in the split level's section. Deduplicates like [`DagBuilder`], which it
/// uses, so it makes the same levels a whole build would.
#[derive(Debug)]
pub struct UpperBuilder {
    inner: DagBuilder,
    split: u8,
    last: Option<u64>,
    max_pointer: Option<u32>,
}

impl UpperBuilder {
    /// Builds levels `0 .. split` of a depth-`depth` volume (`split` in
    /// `1 ..= depth - 2`).
    pub fn new(depth: u8, attributes: AttributeKind, split: u8) -> Result<Self, BuildError> {
        let inner = DagBuilder::new(depth, attributes)?;
        check_split(depth, split)?;
        Ok(UpperBuilder {
            inner,
            split,
            last: None,
            max_pointer: None,
        })
    }

    /// Adds the subtree whose root is the level-`split` cell `code`, stored at
    /// `pointer`, holding `count` voxels (at least one). Codes must be
    /// strictly increasing.
    pub fn push_subtree(&mut self, code: u64, pointer: u32, count: u64) -> Result<(), BuildError> {
        if code >> (3 * u32::from(self.split)) != 0 {
            return Err(BuildError::OutOfVolume {
                unit: "subtree",
                code,
                depth: self.inner.depth,
            });
        }
        if let Some(previous) = self.last
            && code <= previous
        {
            return Err(BuildError::NotIncreasing {
                unit: "subtree",
                previous,
                code,
            });
        }
        if count == 0 {
            return Err(BuildError::Invalid {
                what: format!("subtree {code:#x} holds no voxels"),
            });
        }
        self.last = Some(code);
        self.max_pointer = self.max_pointer.max(Some(pointer));
        self.inner.voxel_count += count;
        self.inner
            .add_child(usize::from(self.split) - 1, code, pointer, count)
    }

    /// Completes the upper levels. `split_units` is the number of units of
    /// the split level's section (its words, or its leaves), which sets the
    /// pointer width of the level above it; every pointer given must be below it.
    pub fn finish(mut self, split_units: u64) -> Result<UpperLevels, BuildError> {
        if let Some(p) = self.max_pointer
            && u64::from(p) >= split_units
        {
            return Err(BuildError::Invalid {
                what: format!("pointer {p} is outside a split level of {split_units} units"),
            });
        }
        let split = usize::from(self.split);
        for level in (0..split).rev() {
            if self.inner.pending[level].mask != 0 {
                self.inner.complete_pending(level)?;
            }
        }
        let attributes = self.inner.attributes;
        let voxel_count = self.inner.voxel_count;
        let mut levels: Vec<BuiltLevel> = self
            .inner
            .arenas
            .into_iter()
            .take(split)
            .map(|arena| BuiltLevel {
                arena,
                offsets: Vec::new(),
            })
            .collect();
        let (widths, lengths) = lay_out_levels(&mut levels, split_units)?;
        let mut upper = UpperLevels {
            attributes,
            voxel_count,
            levels,
            widths,
            lengths,
            crcs: Vec::new(),
        };
        upper.crcs = (0..split)
            .map(|level| crc_of(|sink| upper.emit_section(level, sink)))
            .collect();
        Ok(upper)
    }
}

/// The levels `0 .. split` made by an [`UpperBuilder`], laid out.
#[derive(Debug)]
pub struct UpperLevels {
    attributes: AttributeKind,
    voxel_count: u64,
    levels: Vec<BuiltLevel>,
    widths: Vec<u8>,
    lengths: Vec<u64>,
    crcs: Vec<u32>,
}

impl UpperLevels {
    /// Set voxels in all the subtrees.
    pub fn voxel_count(&self) -> u64 {
        self.voxel_count
    }

    /// The section of each level, root first.
    pub fn sections(&self) -> Vec<SectionInfo> {
        (0..self.levels.len())
            .map(|l| {
                SectionInfo::node_level(
                    l as u8,
                    self.widths[l],
                    self.lengths[l],
                    self.levels[l].arena.len() as u64,
                    self.crcs[l],
                )
            })
            .collect()
    }

    /// Generates the bytes of the section of `level` in chunks.
    pub fn emit_section(
        &self,
        level: usize,
        sink: &mut dyn FnMut(&[u8]) -> io::Result<()>,
    ) -> io::Result<()> {
        emit_node_level(
            &self.levels,
            level,
            self.widths[level],
            self.attributes,
            sink,
        )
    }
}

fn check_split(depth: u8, split: u8) -> Result<(), BuildError> {
    if split >= 1 && split <= depth.saturating_sub(2) {
        Ok(())
    } else {
        Err(BuildError::Invalid {
            what: format!(
                "split level {split} is outside 1..={} for depth {depth}",
                depth.saturating_sub(2)
            ),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Dag;

    #[test]
    fn single_voxel_depth_2_and_3() {
        for depth in [2u8, 3] {
            let built =
                DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, [[1, 2, 3]]).unwrap();
            let bytes = built.to_bytes();
            assert_eq!(bytes.len() as u64, built.file_size());
            let dag = Dag::open(&bytes).unwrap();
            assert!(dag.is_set(1, 2, 3).unwrap());
            assert!(!dag.is_set(1, 2, 2).unwrap());
            assert_eq!(dag.header().voxel_count, 1);
        }
    }

    #[test]
    fn rejects_bad_order_and_range() {
        let mut b = DagBuilder::new(3, AttributeKind::None).unwrap();
        b.push_morton(5).unwrap();
        assert!(matches!(
            b.push_morton(5),
            Err(BuildError::NotIncreasing { .. })
        ));
        assert!(matches!(
            b.push_brick(0, 1),
            Err(BuildError::NotIncreasing { .. })
        ));
        b.push_brick(1, 1).unwrap();
        assert!(matches!(
            b.push_morton(100),
            Err(BuildError::NotIncreasing { .. })
        ));
        assert!(matches!(
            b.push_brick(8, 1),
            Err(BuildError::OutOfVolume { .. })
        ));
        assert!(matches!(
            b.push_morton(512),
            Err(BuildError::OutOfVolume { .. })
        ));
        assert!(matches!(
            DagBuilder::new(1, AttributeKind::None),
            Err(BuildError::DepthOutOfRange { depth: 1 })
        ));
        assert!(matches!(
            DagBuilder::new(22, AttributeKind::None),
            Err(BuildError::DepthOutOfRange { depth: 22 })
        ));
    }

    #[test]
    fn hash_of_node_depends_on_every_child() {
        let a = hash_node(3, &[1, 2]);
        assert_ne!(a, hash_node(3, &[2, 1]));
        assert_ne!(a, hash_node(5, &[1, 2]));
    }

    fn some_voxels(depth: u8) -> Vec<[u32; 3]> {
        let mut state = 3u64;
        let side = 1u64 << depth;
        (0..400)
            .map(|i| {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
                let r = state >> 11;
                // Clumps of neighbours, so that subtrees repeat.
                let base = if i % 3 == 0 { r } else { r & !0x0303_0303 };
                [0, 16, 32].map(|s| ((base >> s) % side) as u32)
            })
            .collect()
    }

    /// One run of subtrees holds the levels below the split exactly as the
    /// whole build does (same ids); laid out in id order, with the upper
    /// levels from an `UpperBuilder` and the file from a `FileLayout`, it
    /// makes the same bytes.
    #[test]
    fn one_run_of_subtrees_rebuilds_the_file() {
        for (depth, split) in [(6u8, 2u8), (6, 4), (5, 1), (4, 2)] {
            let voxels = some_voxels(depth);
            let whole =
                DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, voxels.clone()).unwrap();
            let mut codes: Vec<u64> = voxels
                .iter()
                .map(|v| morton::encode(v[0], v[1], v[2]))
                .collect();
            codes.sort_unstable();
            codes.dedup();
            let mut b = DagBuilder::new(depth, AttributeKind::VoxelCount).unwrap();
            b.record_subtrees(split).unwrap();
            for &c in &codes {
                b.push_morton(c).unwrap();
            }
            let sub = b.finish_subtrees().unwrap();
            let leaf = depth - 2;
            let counts = whole.level_stats();
            for level in split..=leaf {
                assert_eq!(
                    sub.node_count(level) as u64,
                    counts[usize::from(level)].node_count
                );
            }
            assert_eq!(
                sub.roots().len() as u128,
                counts[usize::from(split)].tree_nodes
            );
            assert_eq!(
                sub.roots().iter().map(|r| r.count).sum::<u64>(),
                whole.voxel_count()
            );
            // Lay out the lower levels in id order, bottom up.
            let mut lower = Vec::new();
            let mut leaf_bytes = Vec::new();
            for &m in sub.leaves() {
                leaf_bytes.extend_from_slice(&m.to_le_bytes());
            }
            lower.push((
                SectionInfo::leaf_level(
                    leaf,
                    sub.leaves().len() as u64,
                    crc32c::crc32c(&leaf_bytes),
                ),
                leaf_bytes,
            ));
            let mut offsets: Vec<u32> = (0..sub.leaves().len() as u32).collect();
            let mut units = sub.leaves().len() as u64;
            for level in (split..leaf).rev() {
                let width = layout::minimal_pointer_width(units).unwrap();
                let (mut bytes, mut next) = (Vec::new(), Vec::new());
                for id in 0..sub.node_count(level) as u32 {
                    next.push((bytes.len() / 4) as u32);
                    let (header, children) = sub.node(level, id);
                    let pointers: Vec<u32> =
                        children.iter().map(|&c| offsets[c as usize]).collect();
                    layout::encode_node_record(
                        header as u8,
                        header >> layout::CHILD_MASK_BITS,
                        &pointers,
                        width,
                        &mut bytes,
                    );
                }
                let info = SectionInfo::node_level(
                    level,
                    width,
                    bytes.len() as u64,
                    next.len() as u64,
                    crc32c::crc32c(&bytes),
                );
                units = bytes.len() as u64 / 4;
                offsets = next;
                lower.push((info, bytes));
            }
            lower.reverse();
            let mut upper = UpperBuilder::new(depth, AttributeKind::VoxelCount, split).unwrap();
            for r in sub.roots() {
                upper
                    .push_subtree(r.code, offsets[r.id as usize], r.count)
                    .unwrap();
            }
            let upper = upper.finish(units).unwrap();
            assert_eq!(upper.voxel_count(), whole.voxel_count());
            let mut sections = upper.sections();
            sections.extend(lower.iter().map(|(info, _)| *info));
            let header = FileHeader {
                depth,
                attributes: AttributeKind::VoxelCount,
                root_min: [0.0; 3],
                root_size: 1.0,
                voxel_count: whole.voxel_count(),
            };
            let file = FileLayout::new(header, sections).unwrap();
            let mut bytes = Vec::new();
            file.write_to(&mut bytes, |i, sink| {
                match i.checked_sub(usize::from(split)) {
                    None => upper.emit_section(i, sink),
                    Some(j) => sink(&lower[j].1),
                }
            })
            .unwrap();
            assert!(bytes == whole.to_bytes(), "depth {depth} split {split}");
        }
    }

    #[test]
    fn subtree_and_upper_builders_refuse_misuse() {
        let mut b = DagBuilder::new(5, AttributeKind::VoxelCount).unwrap();
        assert!(matches!(
            b.record_subtrees(0),
            Err(BuildError::Invalid { .. })
        ));
        assert!(b.record_subtrees(4).is_err(), "past the leaf level");
        b.push_morton(1).unwrap();
        assert!(b.record_subtrees(1).is_err(), "after a push");
        assert!(b.finish_subtrees().is_err(), "never asked to record");
        assert!(UpperBuilder::new(5, AttributeKind::None, 0).is_err());
        let mut u = UpperBuilder::new(5, AttributeKind::None, 2).unwrap();
        u.push_subtree(3, 0, 1).unwrap();
        assert!(matches!(
            u.push_subtree(3, 8, 1),
            Err(BuildError::NotIncreasing { .. })
        ));
        assert!(matches!(
            u.push_subtree(64, 8, 1),
            Err(BuildError::OutOfVolume { .. })
        ));
        assert!(matches!(
            u.push_subtree(5, 8, 0),
            Err(BuildError::Invalid { .. })
        ));
        u.push_subtree(5, 8, 2).unwrap();
        assert!(
            matches!(u.finish(8), Err(BuildError::Invalid { .. })),
            "pointer 8 is outside 8 units"
        );
    }
}
