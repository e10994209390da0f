//! The CPU ray tracer ([`Tracer`]) and its traversal: front-to-back DAG
//! traversal in grid space, the state of a traversal in progress ([`Walk`],
//! [`Frame`], [`Prepared`]) and the scalar steps that every path (one ray,
//! the vector lanes of `simd`, the packets of `packet`) runs. It reads the
//! DAG only through `node`; the batch API that chooses among the paths is in
//! `tracer`.
//!
//! # How a ray is traced
//!
//! 1. **Set-up (f64, one division).** The world-space ray is mapped to grid
//!    space (`g(p) = (p - root_min) * 2^D / root_size`), scaled by a power of
//!    two so that its largest direction component lies in `[1, 2)` (exact),
//!    re-based to its entry into the cube when the origin is far away (more
//!    than 16 cube sizes), *mirrored* so that every direction component is
//!    non-negative, and rounded to f32. Direction components smaller than
//!    `2^-60` times the largest are treated as zero (over the part of the ray
//!    inside the cube they move it by far less than the tolerance of the
//!    ray/hit semantics) and get the direction `2^-60` in the traversal, so
//!    that no `0 * inf` NaN can arise.
//! 2. **Traversal (f32).** A per-level stack of (node, child mask, children
//!    still to visit). At a node the entry and exit parameters and the three
//!    mid-plane crossings are computed from exact integer plane positions
//!    (`t = (p - o) * inv_d`), so a child's interval is computed from the very
//!    same numbers its parent used to decide that the ray passes through it. The
//!    children passed through form a chain (entry octant, then one axis flipped
//!    per crossing, in crossing order), looked up in the table `CHAIN` and
//!    ANDed with the child mask; `FIRST` gives the next child front to back; the child
//!    pointer is found by rank (popcount of the mask bits below the child). The
//!    last two levels (the 4³ brick) are answered from the 64-bit leaf mask with
//!    the same two tables, without touching the stack. Ties: a point of the ray
//!    that lies exactly on a boundary between cells belongs to the cell the ray
//!    moves into (so a ray starting exactly on the face of a voxel and leaving
//!    it does not hit it, and a `tmax` exactly at a cell's entry does). Both
//!    answers are within the tolerance of the semantics.
//!
//!    The traversal is a resumable [`Walk`]: it stops before every read of a
//!    node or leaf below the root, after prefetching it. [`Tracer::trace`]
//!    resumes at once; the batch API ([`Tracer::trace_sequential_into`], and
//!    so [`Tracer::trace_batch`], which runs it on every core) keeps several
//!    rays in flight, so that the cache misses of one ray, which bound the
//!    traversal of large DAGs, overlap with the work on the others: where the
//!    processor has AVX2, 16 rays, eight to a vector, stepped together with
//!    gathered reads (module `simd`); elsewhere [`LANES`] rays resumed in
//!    turn. Every ray runs through the very same steps either way, so the
//!    answers are identical. In DAGs of at most [`PACKET_MAX_DAG_BYTES`], runs
//!    of coherent rays (a shared origin, such as a camera's) are traced as
//!    packets instead (module `packet`): one beam pass per packet finds the
//!    coarse occupied cells any of its rays can meet, and each ray is traced
//!    only through those, with the same steps; an image given row by row is
//!    traced tile by tile (module `grid`).
//! 3. **Answer.** The first occupied cell found is reported with its entry
//!    parameter and face, computed from the same plane parameters (the latest
//!    slab entry of the moving axes, or `tmin` and face 0 when that is earlier),
//!    and, for attribute kind 1, the dense index of its first voxel.
//!
//! # Precision
//!
//! Plane positions are exact integers in f32 (at most 2^21), so every plane
//! parameter `(p - o) * inv_d` carries two roundings plus the one of `inv_d`,
//! and the origin one (relative 2^-24 of its magnitude, at most 16 cube sizes,
//! or of the cube size after re-basing): a few f32 units in the last place of
//! `max(2^D, |o_g|)`, below the tolerance of the semantics (`2^-21 * max(2^D,
//! |o_g|)` grid units, i.e. 8 such units). The property tests check the answers
//! against an f64 reference at depths 2 to 6 and 16, 20 and 21.
//!
//! # Malformed files
//!
//! The tracer never panics and never loops forever on any bytes: every read is
//! bounds-checked, and pointers only lead from one level to the next, so a ray
//! visits at most one node per cell it crosses on each level. A read outside
//! its level ends that branch of the traversal (it reads as an empty node) and
//! the ray is answered with [`TraceError::Malformed`] (with the
//! [`FormatError`] code `E045` or `E042`). Other damage a validator would catch
//! (pointers into the middle of records, wrong counts) gives wrong answers, not
//! crashes: run `dagfmt::validate` first when the file is not trusted.

use dagfmt::layout::{AttributeKind, COUNT_SATURATED};
use dagfmt::{ColorTable, Dag, ErrorCode, FormatError};
use glam::{BVec3A, Vec3A, Vec3Swizzles};
use rustc_hash::FxHashMap;

use crate::node::{
    Fault, Level, SIBLINGS_BEFORE, attribute, brick_cell_occupied, child_at, child_count,
    child_mask, logical_leaf, sub_brick, sub_brick_mask, voxel_bit, voxels_below,
};
use crate::tables::{CHAIN, CHILD_BITS, FIRST};
use dagfmt::batch::{Hit, Ray};

/// Most levels a file can have (depth 21 has levels 0 ..= 19 stored).
const MAX_STORED_LEVELS: usize = 20;

/// Length of the per-level arrays: a power of two above the number of levels,
/// so that indexing with `level & LEVEL_INDEX` needs no bounds check.
pub(crate) const LEVEL_SLOTS: usize = 32;
const LEVEL_INDEX: usize = LEVEL_SLOTS - 1;

/// The number of the next [`Tracer`] made (0 is no tracer's).
static NEXT_TRACER_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

/// The running sums of the last attribute index computed on a thread, so that
/// the next hit nearby (the next pixel's, mostly) adds up only the levels
/// below the first one where the two paths part. The node at each level of a
/// path is fixed by the root and the cell coordinates' higher bits, so two
/// cells of one tracer and level whose coordinates agree above bit `b` share
/// the sibling counts of every level whose child index is read above `b`.
#[derive(Clone, Copy)]
struct IndexMemo {
    /// [`Tracer::id`] of the tracer that computed it; 0: nothing memoised.
    tracer: u64,
    /// The traced level and the cell's coordinates at that level.
    level: u8,
    cell: [u32; 3],
    /// The cell's index.
    index: u64,
    /// `sums[l]`: the counts of the earlier siblings on levels `0..l`.
    sums: [u64; LEVEL_SLOTS],
}

thread_local! {
    static INDEX_MEMO: std::cell::RefCell<IndexMemo> = const {
        std::cell::RefCell::new(IndexMemo {
            tracer: 0,
            level: 0,
            cell: [0; 3],
            index: 0,
            sums: [0; LEVEL_SLOTS],
        })
    };
}

/// Level of the cells whose bounding box rays are clipped to: 1/64 of the cube.
const BOUNDS_LEVEL: u8 = 6;

/// Largest DAG (bytes of its level sections) whose batches trace coherent
/// runs of rays as packets. Packets read each node once for many rays, which
/// wins while the DAG stays in the caches; beyond them, memory latency
/// dominates and the vector lanes, which keep 16 independent reads in flight,
/// win. Measured on dragon (trace_bench, machine A): packets were 1.9× the
/// lanes' rate on 8×8 tiles at depth 10 (1 MB) and 1.4× at depth 12 (14 MB),
/// but 0.6× at depth 14 (172 MB), and 0.44× on row-order camera rays there.
pub(crate) const PACKET_MAX_DAG_BYTES: usize = 64 << 20;

/// DAGs of at most this many bytes mostly stay in a core's L2 cache: their
/// vector lanes keep fewer reads in flight (`simd::trace_lanes`), since
/// more groups of rays only add bookkeeping there (machine C, Intel, 2 MB
/// of L2 a core: dragon d10 random rays, 1 MB, 3–5 % faster with two groups
/// than with four; d12, 14 MB, 7–8 % slower).
pub(crate) const SMALL_DAG_BYTES: usize = 4 << 20;

/// Direction given to axes whose direction is (treated as) zero, relative to a
/// largest component in `[1, 2)`.
pub(crate) const TINY_DIRECTION: f64 = 1.0 / (1u64 << 60) as f64;

/// Why a ray could not be traced.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TraceError {
    /// The DAG has a pointer leading outside its level (or a truncated node).
    #[error("malformed DAG: {0}")]
    Malformed(FormatError),
    /// The ray asks for a level of detail deeper than the DAG.
    #[error("ray level {level} is deeper than the DAG's depth {depth}")]
    LevelTooDeep {
        /// The level asked for.
        level: u8,
        /// The DAG's depth.
        depth: u8,
    },
}

/// One entry of the traversal stack: an interior node on the current path.
///
/// `repr(C)`: the vector traversal (`simd`) reads a frame as two 32-bit words,
/// `word` and then `mask | remaining << 8 | last << 16`.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C)]
pub(crate) struct Frame {
    /// Address of the node in its level (word offset in 1.0, byte offset
    /// in 2.0, see `node::Level`).
    pub(crate) word: u32,
    /// The node's child mask.
    pub(crate) mask: u8,
    /// Children the ray passes through that are still to be visited.
    pub(crate) remaining: u8,
    /// The child (physical slot) being visited below this node, to step
    /// back to this node's position when the visit ends.
    pub(crate) last: u8,
    /// The node's accumulated reflection R (spec §23.4; 0 in 1.0): the
    /// traversal sees it as a 1.0 node traced in octant `neg ^ R`.
    pub(crate) reflection: u8,
}

const _: () = assert!(std::mem::size_of::<Frame>() == 8);

pub(crate) type Stack = [Frame; LEVEL_SLOTS];

/// The ray in the traversal's f32 mirrored grid frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct Prepared {
    /// Origin (mirrored, re-based, grid units).
    pub(crate) origin: Vec3A,
    /// 1 / direction (all positive).
    pub(crate) inv_dir: Vec3A,
    pub(crate) tmin: f32,
    pub(crate) tmax: f32,
    /// Direction octant: bit i set when axis i is mirrored.
    pub(crate) neg: usize,
    /// Axes whose direction is not (treated as) zero.
    pub(crate) moving: BVec3A,
    /// Level traced.
    pub(crate) level: u8,
    /// The traversal's parameter is `t' = (t - base) * scale`: `1 / scale`.
    pub(crate) inv_scale: f64,
    pub(crate) base: f64,
}

/// A first occupied cell as the traversal finds it: the mirrored grid
/// position of its lower corner, its level and the leaf reached.
pub(crate) type Cell = (Vec3A, u8, u32);

/// The read a suspended [`Walk`] resumes with.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) enum Pending {
    /// The header of node `target` of the walk's level (the node it stands on).
    #[default]
    Node,
    /// The leaf mask `target` of the brick at `brick_pos`, a child of the
    /// node the walk stands on.
    Brick,
}

/// A traversal in progress that can be suspended before each read of the
/// DAG, so that one thread can advance several rays in turn while their
/// reads are under way (see [`Tracer::trace_sequential_into`]). The path of
/// nodes lives in a separate [`Stack`].
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Walk {
    /// The ray, clipped to the occupied box.
    pub(crate) q: Prepared,
    /// The ray's own `tmin` (for the entry face of the answer).
    pub(crate) ray_tmin: f32,
    /// Level where the descent stops (see [`Tracer::start`]).
    pub(crate) stop: u8,
    /// Level of the node whose subtree is walked (the walk ends when it would
    /// step back above it): 0, the root, but for the walks of packet rays
    /// through the cells of their beam (see `packet`).
    pub(crate) top: u8,
    /// Level of the node the walk stands on.
    pub(crate) level: u8,
    pub(crate) pending: Pending,
    /// Mirrored grid position of that node's lower corner, and its edge.
    pub(crate) pos: Vec3A,
    pub(crate) size: f32,
    /// The node address or leaf index to read next.
    pub(crate) target: u32,
    /// The accumulated reflection of `target` (spec §23.4; 0 in 1.0).
    pub(crate) reflection: u8,
    /// Mirrored grid position of the brick to read next.
    pub(crate) brick_pos: Vec3A,
}

impl Walk {
    /// The prepared ray with its own `tmin`, for [`Tracer::found`].
    pub(crate) fn ray(&self) -> Prepared {
        Prepared {
            tmin: self.ray_tmin,
            ..self.q
        }
    }
}

/// Rays in flight at once in [`Tracer::trace_sequential_into`]: enough to
/// cover the latency of a read from memory with the work of the others.
pub(crate) const LANES: usize = 8;

/// One ray in flight in [`Tracer::trace_sequential_into`].
#[derive(Clone, Copy, Debug, Default)]
struct Lane {
    walk: Walk,
    stack: Stack,
    /// Index of the ray in the batch.
    ray: usize,
}

/// What [`Tracer::begin`] made of a ray.
pub(crate) enum Begun {
    /// Answered without a traversal.
    Done(Hit),
    /// To be traversed.
    Walk(Walk),
}

/// What set-up decided about a ray.
pub(crate) enum Setup {
    Miss,
    /// Direction zero: the answer is the cell of `level` holding the grid
    /// point `origin`, if occupied, entered at `tmin` from inside.
    Point {
        origin: [f64; 3],
        tmin: f32,
        level: u8,
    },
    Trace(Prepared),
}

/// The first occupied cell found by the traversal.
#[derive(Clone, Copy, Debug)]
struct Found {
    /// Cell coordinates at the traced level, in the file's (unmirrored) frame.
    cell: [u32; 3],
    /// The leaf reached (levels D-1 and D).
    leaf: u32,
}

/// How the batch API's vector lanes (processors with AVX2) read the words of
/// eight rays at once: node headers, child pointers, stack frames and table
/// entries ([`Tracer::with_gathers`]). The answers are identical; the speed
/// is not.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Gathers {
    /// [`Gathers::ScalarLoads`] on processors whose gather instructions are
    /// measured to be slower than eight loads (AMD Zen to Zen 4, Hygon
    /// Dhyana), else [`Gathers::Instruction`].
    #[default]
    Auto,
    /// AVX2's gather instruction (`vpgatherdd`), one for eight words.
    Instruction,
    /// Eight scalar loads put together into a vector.
    ScalarLoads,
}

impl Gathers {
    /// Whether the lanes read with scalar loads.
    fn loads(self) -> bool {
        match self {
            Gathers::Instruction => false,
            Gathers::ScalarLoads => true,
            Gathers::Auto => {
                #[cfg(target_arch = "x86_64")]
                {
                    static SLOW: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
                    *SLOW.get_or_init(crate::cpu::slow_gathers)
                }
                #[cfg(not(target_arch = "x86_64"))]
                false
            }
        }
    }
}

/// How many rays one step of the batch API's vector lanes advances at once
/// ([`Tracer::with_lanes`]): eight to an AVX2 vector or sixteen to an AVX-512
/// vector. The answers are identical; the speed is not. Coherent rays traced
/// as packets do not use the lanes (the rays a packet does not take do).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Lanes {
    /// [`Lanes::Sixteen`] where the processor has AVX-512 (F, BW, VL, DQ, CD)
    /// and fast gather instructions (not AMD's Zen 4, whose 512-bit
    /// operations run as two halves and whose gathers [`Gathers::Auto`]
    /// replaces by scalar loads: not measured there), else [`Lanes::Eight`].
    #[default]
    Auto,
    /// Eight rays to an AVX2 vector.
    Eight,
    /// Sixteen rays to an AVX-512 vector, where the processor has AVX-512
    /// (else eight).
    Sixteen,
}

impl Lanes {
    /// Whether the lanes are sixteen to a vector on this processor.
    fn wide(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            match self {
                Lanes::Eight => false,
                Lanes::Sixteen => crate::cpu::wide_available(),
                Lanes::Auto => {
                    static WIDE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
                    *WIDE
                        .get_or_init(|| crate::cpu::wide_available() && !crate::cpu::slow_gathers())
                }
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = self;
            false
        }
    }
}

/// A ray tracer over one DAG. Cheap to share between threads (`Sync`).
///
/// It borrows the file's bytes (zero-copy); what it computes when it is made
/// is, for attribute kind 1, the voxel counts of the nodes whose stored count
/// is saturated (at most one entry per such node in the file), and for a 2.0
/// file its expanded levels (spec §23.12, [`Tracer::from_v2_levels`]; shared
/// by the tracer's clones) or, read in place, its record starts (§23.8).
#[derive(Clone, Debug)]
pub struct Tracer<'a> {
    pub(crate) levels: [Level<'a>; LEVEL_SLOTS],
    pub(crate) depth: u8,
    pub(crate) leaf_level: u8,
    pub(crate) empty: bool,
    attribute_kind: AttributeKind,
    pub(crate) root_min: [f64; 3],
    /// Grid units per world unit: 2^D / root_size.
    pub(crate) grid_scale: f64,
    /// Edge length in grid units of a cell of each level: 2^(D - level).
    pub(crate) cell_size: [f32; MAX_STORED_LEVELS + 2],
    /// Whether the levels are format 2.0 (spec §23): the walks carry the
    /// accumulated reflection, the vector lanes run the 2.0 copies of
    /// `simd::step` and `simd::step_wide`.
    pub(crate) v2: bool,
    /// The expanded node levels and the copy of the leaf level (spec
    /// §23.12) that `levels` borrow, when a 2.0 DAG is traced through them
    /// (see [`Expansion`]); `None` when `levels` borrow the file.
    expanded: Option<Expansion>,
    /// Voxel counts of saturated nodes, keyed by (level, word).
    saturated: FxHashMap<(u8, u32), u64>,
    /// This tracer's number (shared by its clones, which read the same
    /// bytes): the key of the per-thread [`IndexMemo`].
    id: u64,
    compute_index: bool,
    /// Whether batches trace coherent runs as packets: only for DAGs of at
    /// most [`PACKET_MAX_DAG_BYTES`] (see there).
    pub(crate) packets: bool,
    /// Whether the DAG has at most [`SMALL_DAG_BYTES`].
    pub(crate) small: bool,
    /// Whether the vector lanes read with scalar loads rather than gather
    /// instructions ([`Gathers`], resolved).
    pub(crate) gather_loads: bool,
    /// Whether the vector lanes are sixteen to an AVX-512 vector ([`Lanes`],
    /// resolved).
    pub(crate) wide_lanes: bool,
    colors: Option<ColorTable<'a>>,
    /// Level of the cells whose union `bounds` encloses.
    bounds_level: u8,
    /// Per direction octant: the box (grid units, mirrored frame) of the
    /// occupied cells of `bounds_level`. Rays are clipped to it before the
    /// traversal: most rays that miss the object never reach the root node.
    pub(crate) bounds: [(Vec3A, Vec3A); 8],
}

/// The expanded node levels of a 2.0 DAG and a copy of its leaf level
/// (spec §23.12), in one allocation, so that the vector lanes address every
/// level with 32-bit offsets from one base: level after level, each from a
/// multiple of 8 bytes, then 64 zero bytes (where the lanes' loads near the
/// end of the leaf level may read). The tracer that holds it (and its
/// clones, which share it) borrows its levels from it as `Level`s.
///
/// Made by [`Expansion::new`] for tracers that share it
/// ([`Tracer::from_v2_expansion`]): a program that makes many tracers of one
/// file (the Python package makes one per call) expands it once.
#[derive(Clone)]
pub struct Expansion {
    /// The words, little-endian in memory (as a file's bytes are).
    words: std::sync::Arc<[u32]>,
    /// Per level, root first, the leaf level last: its first word and its
    /// words.
    spans: Vec<(usize, usize)>,
    /// The byte lengths of the level sections it was made from, which a
    /// tracer checks it is given with.
    source: Vec<usize>,
}

impl std::fmt::Debug for Expansion {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Expansion")
            .field("bytes", &(self.words.len() * 4))
            .field("spans", &self.spans)
            .finish()
    }
}

/// Whether a 2.0 tracer reads expanded levels, and whose.
#[derive(Clone, Copy)]
enum Expand<'e> {
    /// Read the level sections in place.
    No,
    /// Expand them (where they expand).
    Here,
    /// Read this expansion of them.
    Given(&'e Expansion),
}

impl Expansion {
    /// The expansion of the 2.0 levels `levels` (root first, the leaf level
    /// last, as a 2.0 reader gives them); `None` where
    /// `dagfmt::expand::expand_levels` refuses them or the leaves are more
    /// than 32-bit indices address (the tracer then reads them in place,
    /// which reports what it meets).
    pub fn new(levels: &[dagfmt::v2::LevelView<'_>]) -> Option<Self> {
        let expanded = dagfmt::expand::expand_levels(levels).ok()?;
        let leaves = levels.last()?.bytes;
        let leaf_words = leaves.len() / 8 * 2;
        if leaf_words / 2 > u32::MAX as usize {
            return None;
        }
        let mut spans = Vec::with_capacity(expanded.len() + 1);
        let mut total = 0usize;
        for len in expanded.iter().map(|l| l.words.len()).chain([leaf_words]) {
            spans.push((total, len));
            total += len.next_multiple_of(2);
        }
        let mut words = Vec::with_capacity(total + 16);
        for (level, &(start, _)) in expanded.into_iter().zip(&spans) {
            words.resize(start, 0);
            words.extend(level.words.into_iter().map(u32::to_le));
        }
        words.resize(spans[spans.len() - 1].0, 0);
        // The leaf masks' bytes as they are in the file.
        words.extend(
            leaves[..leaf_words * 4]
                .chunks_exact(4)
                .map(|b| u32::from_ne_bytes([b[0], b[1], b[2], b[3]])),
        );
        words.resize(total + 16, 0);
        Some(Expansion {
            words: words.into(),
            spans,
            source: levels.iter().map(|l| l.bytes.len()).collect(),
        })
    }

    /// Bytes of memory it holds: the expanded words and the copy of the
    /// leaf level.
    pub fn bytes(&self) -> usize {
        self.words.len() * 4
    }

    /// The levels, root first, as the tracer reads them: the expanded node
    /// levels ([`Level::new_expanded`]) and the leaf level
    /// ([`Level::new_leaves`]).
    ///
    /// # Safety
    ///
    /// The `Level`s borrow `self.words` for `'a`, which the borrow checker
    /// cannot see: the caller must keep `self` (or a clone, which shares the
    /// words) alive as long as it holds them, and hand no slice of them out
    /// for longer. `Tracer` does: it holds its `Expansion` beside its
    /// `levels`, its clones clone both, and `Level` is private to the crate;
    /// the words are never written (an `Arc<[u32]>`: the allocation neither
    /// moves nor changes while it lives).
    unsafe fn levels<'a>(&self) -> Vec<Level<'a>> {
        // SAFETY: the words' memory, as bytes (any bytes are valid `u8`s),
        // for as long as the caller keeps `self` (see above).
        let all: &'a [u8] = unsafe {
            std::slice::from_raw_parts(self.words.as_ptr().cast::<u8>(), self.words.len() * 4)
        };
        let nodes = self.spans.len() - 1;
        self.spans
            .iter()
            .enumerate()
            .map(|(i, &(start, len))| {
                let bytes = &all[start * 4..(start + len) * 4];
                let readable = &all[start * 4..];
                if i < nodes {
                    Level::new_expanded(bytes, readable, i + 1 == nodes)
                } else {
                    Level::new_leaves(bytes, readable)
                }
            })
            .collect()
    }
}

impl<'a> Tracer<'a> {
    /// Makes a tracer for `dag`. Fails only when, for attribute kind 1, the
    /// nodes with saturated counts lead to a pointer outside their level.
    pub fn new(dag: &Dag<'a>) -> Result<Self, TraceError> {
        let file = dag.bytes();
        let mut levels: [Level<'a>; LEVEL_SLOTS] = std::array::from_fn(|_| Level::default());
        for (slot, section) in levels.iter_mut().zip(dag.levels()) {
            *slot = Level::new(file, section);
        }
        let header = dag.header();
        let dag_bytes = dag.levels().iter().map(|l| l.bytes.len()).sum::<usize>();
        Self::from_parts(
            levels,
            header,
            dag.is_empty(),
            dag_bytes,
            false,
            dag.color_table(),
            None,
        )
    }

    /// Makes a tracer for a format 2.0 DAG (spec §23) whose level sections
    /// are `levels` (root first, the leaf level last, as
    /// `dagfmt::v2::Encoded::views` or a 2.0 reader gives them), with the
    /// header fields of `header` (depth, root cube, attribute kind; the rest
    /// is not read) and colours `colors`. Answers are those of the 1.0 DAG
    /// of the same voxels.
    ///
    /// The node levels are expanded once, here (spec §23.12,
    /// `dagfmt::expand::expand_levels`): every path then reads a child's
    /// reference as one aligned 32-bit word, as in 1.0, from memory the
    /// tracer holds (4 bytes per node and per child, and a copy of the leaf
    /// level, so that the vector lanes address every level from one base;
    /// [`Tracer::expanded_bytes`]). Where the levels do not expand (a
    /// malformed DAG), the tracer traces the level sections in place, as
    /// [`Tracer::from_v2_levels_in_place`] does, and reports what it meets
    /// there.
    ///
    /// Fails when the levels do not fit the depth or a level cannot be
    /// decoded (its widths), or as [`Tracer::new`]. The offsets that errors
    /// of a malformed DAG report are inside the level section named (the
    /// tracer does not know where the sections lie in a file).
    /// [`Tracer::from_v2`] makes the tracer of a 2.0 file.
    pub fn from_v2_levels(
        header: &dagfmt::Header,
        levels: &[dagfmt::v2::LevelView<'a>],
        colors: Option<ColorTable<'a>>,
    ) -> Result<Self, TraceError> {
        Self::from_v2_parts(header, levels, colors, None, Expand::Here)
    }

    /// [`Tracer::from_v2_levels`] without the expansion: the tracer reads
    /// the level sections in place, decoding each child's reference from
    /// the bit-packed records (spec §23.2, §23.3; a sequential child of a
    /// node level from the child level's record starts, §23.8). The same
    /// answers, for less memory and more time a child. (The vector lanes
    /// address all levels with 32-bit offsets from one base: levels in
    /// separate allocations further apart than that leave the batches to
    /// the scalar steps, with the same answers.)
    pub fn from_v2_levels_in_place(
        header: &dagfmt::Header,
        levels: &[dagfmt::v2::LevelView<'a>],
        colors: Option<ColorTable<'a>>,
    ) -> Result<Self, TraceError> {
        Self::from_v2_parts(header, levels, colors, None, Expand::No)
    }

    /// The tracer of a file of either version: [`Tracer::new`] for 1.x,
    /// [`Tracer::from_v2`] for 2.0.
    pub fn from_any(dag: &dagfmt::AnyDag<'a>) -> Result<Self, TraceError> {
        match dag {
            dagfmt::AnyDag::V1(d) => Self::new(d),
            dagfmt::AnyDag::V2(d) => Self::from_v2(d),
        }
    }

    /// The tracer of the 2.0 file `dag`: [`Tracer::from_v2_levels`] of its
    /// levels, header and colours (its node levels expanded where they
    /// expand).
    pub fn from_v2(dag: &dagfmt::Dag2<'a>) -> Result<Self, TraceError> {
        Self::from_v2_parts(
            dag.header(),
            dag.levels(),
            dag.color_table(),
            Some(dag.bytes()),
            Expand::Here,
        )
    }

    /// The tracer of the 2.0 file `dag` through `expansion`, the
    /// [`Expansion`] of its levels made before (and shared: nothing is
    /// expanded here). Fails when `expansion` was made from other level
    /// sections, or as [`Tracer::from_v2`].
    pub fn from_v2_expansion(
        dag: &dagfmt::Dag2<'a>,
        expansion: &Expansion,
    ) -> Result<Self, TraceError> {
        Self::from_v2_parts(
            dag.header(),
            dag.levels(),
            dag.color_table(),
            Some(dag.bytes()),
            Expand::Given(expansion),
        )
    }

    /// The tracer of the 2.0 file `dag` reading its level sections in place
    /// ([`Tracer::from_v2_levels_in_place`]; knowing the whole file, the
    /// vector lanes gather the records at the end of a level section with
    /// the bytes that follow it, rather than read them one by one).
    pub fn from_v2_in_place(dag: &dagfmt::Dag2<'a>) -> Result<Self, TraceError> {
        Self::from_v2_parts(
            dag.header(),
            dag.levels(),
            dag.color_table(),
            Some(dag.bytes()),
            Expand::No,
        )
    }

    /// Whether the tracer traces a 2.0 DAG through its expanded levels
    /// (spec §23.12; see [`Tracer::from_v2_levels`]).
    pub fn is_expanded(&self) -> bool {
        self.expanded.is_some()
    }

    /// Bytes of the memory the tracer holds for the expanded levels: their
    /// words and the copy of the leaf level (0 when it reads the file in
    /// place).
    pub fn expanded_bytes(&self) -> usize {
        self.expanded.as_ref().map_or(0, |e| e.words.len() * 4)
    }

    /// [`Tracer::from_v2_levels`] (`expand`) or
    /// [`Tracer::from_v2_levels_in_place`] of levels inside `file`, where
    /// known.
    fn from_v2_parts(
        header: &dagfmt::Header,
        levels: &[dagfmt::v2::LevelView<'a>],
        colors: Option<ColorTable<'a>>,
        file: Option<&'a [u8]>,
        expand: Expand<'_>,
    ) -> Result<Self, TraceError> {
        let malformed = |message: String| {
            TraceError::Malformed(FormatError::new(ErrorCode::BadLevelSections, 0, message))
        };
        let depth = header.depth;
        let shape_ok = (2..=21).contains(&depth)
            && levels.len() == usize::from(depth) - 1
            && levels
                .iter()
                .enumerate()
                .all(|(i, l)| l.is_leaf == (i + 1 == levels.len()));
        if !shape_ok {
            return Err(malformed(format!(
                "a depth-{depth} 2.0 DAG needs {} levels, the last one the leaves; {} given",
                depth.saturating_sub(1),
                levels.len()
            )));
        }
        let empty = levels.last().is_none_or(|l| l.bytes.is_empty());
        let expanded = match expand {
            Expand::No => None,
            Expand::Here => Expansion::new(levels),
            Expand::Given(e) => {
                let same = e.source.len() == levels.len()
                    && e.source
                        .iter()
                        .zip(levels)
                        .all(|(&n, l)| n == l.bytes.len());
                if !same {
                    return Err(malformed(
                        "the expansion given was made from other level sections".to_string(),
                    ));
                }
                Some(e.clone())
            }
        };
        if let Some(expanded) = expanded {
            let mut slots: [Level<'a>; LEVEL_SLOTS] = std::array::from_fn(|_| Level::default());
            // SAFETY: `expanded` goes into the tracer with the levels that
            // borrow it (`Expansion::levels`).
            for (slot, level) in slots.iter_mut().zip(unsafe { expanded.levels() }) {
                *slot = level;
            }
            let dag_bytes = expanded.words.len() * 4;
            return Self::from_parts(
                slots,
                header,
                empty,
                dag_bytes,
                true,
                colors,
                Some(expanded),
            );
        }
        let mut slots: [Level<'a>; LEVEL_SLOTS] = std::array::from_fn(|_| Level::default());
        for (i, (slot, view)) in slots.iter_mut().zip(levels).enumerate() {
            *slot = Level::new_v2(view, levels.get(i + 1), file)
                .map_err(|e| TraceError::Malformed(e.at_level(i as u8)))?;
        }
        let dag_bytes = levels.iter().map(|l| l.bytes.len()).sum::<usize>();
        Self::from_parts(slots, header, empty, dag_bytes, true, colors, None)
    }

    /// The rest of [`Tracer::new`] and [`Tracer::from_v2_levels`].
    fn from_parts(
        levels: [Level<'a>; LEVEL_SLOTS],
        header: &dagfmt::Header,
        empty: bool,
        dag_bytes: usize,
        v2: bool,
        colors: Option<ColorTable<'a>>,
        expanded: Option<Expansion>,
    ) -> Result<Self, TraceError> {
        let depth = header.depth;
        let mut cell_size = [0f32; MAX_STORED_LEVELS + 2];
        for (level, size) in cell_size
            .iter_mut()
            .enumerate()
            .take(usize::from(depth) + 1)
        {
            *size = (1u32 << (u32::from(depth) - level as u32)) as f32;
        }
        let mut tracer = Tracer {
            levels,
            depth,
            leaf_level: depth - 2,
            empty,
            attribute_kind: header.attribute_kind,
            root_min: header.root_min,
            grid_scale: (1u64 << depth) as f64 / header.root_size,
            cell_size,
            v2,
            expanded,
            saturated: FxHashMap::default(),
            id: NEXT_TRACER_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            compute_index: true,
            packets: dag_bytes <= PACKET_MAX_DAG_BYTES,
            small: dag_bytes <= SMALL_DAG_BYTES,
            gather_loads: Gathers::Auto.loads(),
            wide_lanes: Lanes::Auto.wide(),
            colors,
            bounds_level: 0,
            bounds: [(Vec3A::ZERO, Vec3A::splat((1u32 << depth) as f32)); 8],
        };
        if !tracer.empty {
            let level = BOUNDS_LEVEL.min(tracer.leaf_level);
            if let Some((lo, hi)) = tracer.occupied_cells(level) {
                let resolution = (1u32 << depth) as f32;
                let cell = tracer.cell_size[usize::from(level)];
                let lo = Vec3A::from_array(lo.map(|c| c as f32)) * cell;
                let hi = Vec3A::from_array(hi.map(|c| c as f32)) * cell;
                for (neg, slot) in tracer.bounds.iter_mut().enumerate() {
                    let mirrored = BVec3A::new(neg & 1 != 0, neg & 2 != 0, neg & 4 != 0);
                    let m_lo = Vec3A::select(mirrored, Vec3A::splat(resolution) - hi, lo);
                    let m_hi = Vec3A::select(mirrored, Vec3A::splat(resolution) - lo, hi);
                    *slot = (m_lo, m_hi);
                }
                tracer.bounds_level = level;
            }
        }
        if tracer.attribute_kind == AttributeKind::VoxelCount
            && !tracer.empty
            && tracer.leaf_level > 0
        {
            let mut saturated = FxHashMap::default();
            tracer
                .count_saturated(0, 0, &mut saturated)
                .map_err(|f| tracer.fault_error(f))?;
            tracer.saturated = saturated;
        }
        Ok(tracer)
    }

    /// The box (inclusive lower, exclusive upper cell coordinates) of the
    /// occupied cells of `level`, by a walk of the tree down to that level (at
    /// most 8^level nodes); `None` when a read fails (a damaged file).
    fn occupied_cells(&self, level: u8) -> Option<([u32; 3], [u32; 3])> {
        let mut lo = [u32::MAX; 3];
        let mut hi = [0u32; 3];
        let mut pending = vec![(0u8, 0u32, 0u8, [0u32; 3])];
        while let Some((l, word, r, cell)) = pending.pop() {
            if l == level {
                for i in 0..3 {
                    lo[i] = lo[i].min(cell[i]);
                    hi[i] = hi[i].max(cell[i] + 1);
                }
                continue;
            }
            let section = &self.levels[usize::from(l) & LEVEL_INDEX];
            let mask = child_mask(section.header(l, word).ok()?);
            for slot in 0..8u32 {
                if mask >> slot & 1 == 1 {
                    let reference = section.child(l, word, mask, slot).ok()?;
                    // The logical child of physical slot `slot` (spec §23.4).
                    let child = slot ^ u32::from(r);
                    pending.push((
                        l + 1,
                        reference.node,
                        r ^ reference.reflection,
                        [0, 1, 2].map(|i| cell[i] * 2 + (child >> i & 1)),
                    ));
                }
            }
        }
        (lo[0] <= hi[0]).then_some((lo, hi))
    }

    /// Whether hits carry the attribute index (default true). Turning it off
    /// saves the sibling-count walk when only geometry is wanted.
    pub fn with_index(mut self, compute_index: bool) -> Self {
        self.compute_index = compute_index;
        self
    }

    /// How the batch API's vector lanes read the nodes of their rays
    /// (default [`Gathers::Auto`]). The answers are the same either way; only
    /// the speed differs, by processor.
    pub fn with_gathers(mut self, gathers: Gathers) -> Self {
        self.gather_loads = gathers.loads();
        self
    }

    /// How the batch API's vector lanes read: [`Gathers::Instruction`] or
    /// [`Gathers::ScalarLoads`] (what [`Gathers::Auto`] chose, where set so).
    pub fn gathers(&self) -> Gathers {
        if self.gather_loads {
            Gathers::ScalarLoads
        } else {
            Gathers::Instruction
        }
    }

    /// How many rays a step of the batch API's vector lanes advances at once
    /// (default [`Lanes::Auto`]). The answers are the same either way; only
    /// the speed differs, by processor.
    pub fn with_lanes(mut self, lanes: Lanes) -> Self {
        self.wide_lanes = lanes.wide();
        self
    }

    /// How many rays a step of the vector lanes advances at once on this
    /// processor: [`Lanes::Eight`] or [`Lanes::Sixteen`] (what [`Lanes::Auto`]
    /// chose, where set so; eight where the processor has no AVX-512).
    pub fn lanes(&self) -> Lanes {
        if self.wide_lanes {
            Lanes::Sixteen
        } else {
            Lanes::Eight
        }
    }

    /// Depth D of the DAG.
    pub fn depth(&self) -> u8 {
        self.depth
    }

    /// World-space box of the occupied cells of level `min(6, leaf level)`
    /// (the box `camera::occupied_box` gives for a 1.0 file), or `None` for
    /// an empty volume or a damaged one; for either format version.
    pub fn occupied_box(&self) -> Option<([f64; 3], [f64; 3])> {
        if self.empty {
            return None;
        }
        let level = 6.min(self.leaf_level);
        let (lo, hi) = self.occupied_cells(level)?;
        // Grid units per cell of `level`, then world units per grid unit.
        let cell = f64::from(1u32 << (self.depth - level)) / self.grid_scale;
        Some((
            [0, 1, 2].map(|i| self.root_min[i] + f64::from(lo[i]) * cell),
            [0, 1, 2].map(|i| self.root_min[i] + f64::from(hi[i]) * cell),
        ))
    }

    /// The voxel colours (raw or packed, by dense index), if any.
    pub fn colors(&self) -> Option<ColorTable<'a>> {
        self.colors
    }

    /// The RGBA colour of the voxel with dense index `index`, if the file has
    /// colours: read from a raw section, or decoded from a packed one (a fixed
    /// number of reads, spec §12.6).
    pub fn color(&self, index: u64) -> Option<[u8; 4]> {
        self.colors?.get(index)
    }

    /// Grid-space (voxel units) position of a world-space point.
    pub fn world_to_grid(&self, p: [f64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|i| (p[i] - self.root_min[i]) * self.grid_scale)
    }

    /// Traces one ray: the occupied cell with the smallest entry parameter.
    pub fn trace(&self, ray: &Ray) -> Result<Hit, TraceError> {
        let mut stack = [Frame::default(); LEVEL_SLOTS];
        let mut fault = None;
        match self.begin(ray, &mut stack, &mut fault)? {
            Begun::Done(hit) => Ok(hit),
            Begun::Walk(mut walk) => {
                let cell = loop {
                    if let Some(cell) = self.resume(&mut walk, &mut stack, &mut fault) {
                        break cell;
                    }
                };
                self.finish(&walk.ray(), cell, &stack, fault)
            }
        }
    }

    /// [`Tracer::trace_lanes`] one ray at a time: [`LANES`] rays in flight,
    /// switching between them at every read of the DAG.
    pub(crate) fn trace_lanes_scalar(
        &self,
        rays: &[Ray],
        hits: &mut [Hit],
    ) -> Result<(), TraceError> {
        let count = rays.len().min(hits.len());
        // The lanes never move (a lane is 400 bytes); `order[..active]` lists
        // the busy ones and `order[active..]` the free ones.
        let mut lanes = [Lane::default(); LANES];
        let mut order: [usize; LANES] = std::array::from_fn(|i| i);
        let mut active = 0;
        let mut next = 0;
        loop {
            // Fill the free lanes with rays that need a traversal; the others
            // are answered on the spot.
            while active < LANES && next < count {
                let lane = &mut lanes[order[active] & (LANES - 1)];
                let mut fault = None;
                match self.begin(&rays[next], &mut lane.stack, &mut fault)? {
                    Begun::Done(hit) => hits[next] = hit,
                    Begun::Walk(walk) => {
                        lane.walk = walk;
                        lane.ray = next;
                        active += 1;
                    }
                }
                next += 1;
            }
            if active == 0 {
                return Ok(());
            }
            // One step of every lane, in turn; a finished lane is answered and
            // its slot freed.
            let mut k = 0;
            while k < active {
                let lane = &mut lanes[order[k] & (LANES - 1)];
                let mut fault = None;
                match self.resume(&mut lane.walk, &mut lane.stack, &mut fault) {
                    None if fault.is_none() => k += 1,
                    cell => {
                        let cell = cell.flatten();
                        hits[lane.ray] = self.finish(&lane.walk.ray(), cell, &lane.stack, fault)?;
                        active -= 1;
                        order.swap(k, active);
                    }
                }
            }
        }
    }

    /// Set-up of a ray: its answer when that needs no traversal of the nodes,
    /// or its walk from the root.
    #[inline(always)]
    pub(crate) fn begin(
        &self,
        ray: &Ray,
        stack: &mut Stack,
        fault: &mut Option<Fault>,
    ) -> Result<Begun, TraceError> {
        match self.setup(ray)? {
            Setup::Miss => Ok(Begun::Done(Hit::MISS)),
            Setup::Point {
                origin,
                tmin,
                level,
            } => match self.point_cell(origin, level, stack)? {
                None => Ok(Begun::Done(Hit::MISS)),
                Some(found) => {
                    let index = self
                        .index(&found, level, stack)
                        .map_err(|f| self.fault_error(f))?;
                    Ok(Begun::Done(Hit {
                        hit: true,
                        t: tmin,
                        voxel: found.cell,
                        level,
                        face: 0,
                        index,
                    }))
                }
            },
            Setup::Trace(prepared) => self.begin_prepared(&prepared, stack, fault),
        }
    }

    /// The end of [`Tracer::begin`] for a ray that is traced: the answer
    /// when no node needs a read, else the walk from the root.
    #[inline(always)]
    pub(crate) fn begin_prepared(
        &self,
        prepared: &Prepared,
        stack: &mut Stack,
        fault: &mut Option<Fault>,
    ) -> Result<Begun, TraceError> {
        match self.start(prepared, fault) {
            Ok(walk) => Ok(Begun::Walk(walk)),
            Err(cell) => self.finish(prepared, cell, stack, *fault).map(Begun::Done),
        }
    }

    /// The hit for the first occupied cell found by the traversal of `p`
    /// (whose path is in `stack`), or the fault met on the way.
    #[inline(always)]
    pub(crate) fn finish(
        &self,
        p: &Prepared,
        cell: Option<Cell>,
        stack: &Stack,
        fault: Option<Fault>,
    ) -> Result<Hit, TraceError> {
        if let Some(f) = fault {
            return Err(self.fault_error(f));
        }
        let Some((pos, level, leaf)) = cell else {
            return Ok(Hit::MISS);
        };
        let (found, t, face) = self.found(p, pos, level, leaf);
        let index = if self.index_kind() {
            self.index(&found, p.level, stack)
                .map_err(|f| self.fault_error(f))?
        } else {
            None
        };
        Ok(Hit {
            hit: true,
            t,
            voxel: found.cell,
            level: p.level,
            face,
            index,
        })
    }

    /// [`Tracer::finish`] for the walk `walk` that found `cell`: its hit,
    /// with the attribute index from the path in `stack` (given only where
    /// hits carry one, see [`Tracer::index_kind`]).
    #[inline(always)]
    pub(crate) fn walk_hit(
        &self,
        walk: &Walk,
        cell: Cell,
        stack: Option<&Stack>,
    ) -> Result<Hit, TraceError> {
        let (pos, level, leaf) = cell;
        let p = &walk.q;
        let (found, t, face) = self.found_from(p, walk.ray_tmin, pos, level, leaf);
        let index = match stack {
            Some(stack) if self.index_kind() => self
                .index(&found, p.level, stack)
                .map_err(|f| self.fault_error(f))?,
            _ => None,
        };
        Ok(Hit {
            hit: true,
            t,
            voxel: found.cell,
            level: p.level,
            face,
            index,
        })
    }

    /// Any-hit (shadow) query: whether the ray meets any occupied cell.
    pub fn occluded(&self, ray: &Ray) -> Result<bool, TraceError> {
        let mut stack = [Frame::default(); LEVEL_SLOTS];
        match self.setup(ray)? {
            Setup::Miss => Ok(false),
            Setup::Point { origin, level, .. } => {
                Ok(self.point_cell(origin, level, &mut stack)?.is_some())
            }
            Setup::Trace(prepared) => Ok(self
                .traverse(&prepared, &mut stack)
                .map_err(|f| self.fault_error(f))?
                .is_some()),
        }
    }

    /// Occupancy of the 5 × 5 × 5 cells of `level` centred on `cell`: bit
    /// `(dx + 2) + 5 (dy + 2) + 25 (dz + 2)` is set when cell `cell + (dx, dy,
    /// dz)` is occupied (cells outside the grid count as empty). The lit
    /// renderer estimates shading normals from it ([`crate::lit`]). Below the
    /// leaf level the few 4³ leaves the window overlaps are read once each.
    pub fn occupancy_around(&self, cell: [u32; 3], level: u8) -> Result<u128, TraceError> {
        if level > self.depth {
            return Err(TraceError::LevelTooDeep {
                level,
                depth: self.depth,
            });
        }
        let mut stack = [Frame::default(); LEVEL_SLOTS];
        let last = (1i64 << level) - 1;
        let centre = cell.map(i64::from);
        let mut bits = 0u128;
        if self.empty || level == 0 {
            // Level 0: the root cell alone, occupied unless the volume is empty.
            if !self.empty && centre.iter().all(|&c| c == 0) {
                bits |= 1 << 62;
            }
            return Ok(bits);
        }
        // Leaves (level `leaf_level`) overlapped by the window, read lazily.
        let shift = level.saturating_sub(self.leaf_level);
        let mut leaves: [(i64, i64, i64, Option<u64>); 27] = [(-1, -1, -1, None); 27];
        let mut cached = 0;
        for dz in -2..=2i64 {
            for dy in -2..=2i64 {
                for dx in -2..=2i64 {
                    let c = [centre[0] + dx, centre[1] + dy, centre[2] + dz];
                    if c.iter().any(|&v| v < 0 || v > last) {
                        continue;
                    }
                    let cell = c.map(|v| v as u32);
                    let occupied = if shift == 0 {
                        self.lookup(cell, level, &mut stack)
                            .map_err(|f| self.fault_error(f))?
                            .is_some()
                    } else {
                        let key = (c[0] >> shift, c[1] >> shift, c[2] >> shift);
                        let at = match leaves[..cached].iter().position(|l| (l.0, l.1, l.2) == key)
                        {
                            Some(at) => at,
                            None => {
                                let leaf_cell = cell.map(|v| v >> shift);
                                let bits = match self
                                    .lookup(leaf_cell, self.leaf_level, &mut stack)
                                    .map_err(|f| self.fault_error(f))?
                                {
                                    None => None,
                                    Some((found, reflection)) => Some(logical_leaf(
                                        self.levels[usize::from(self.leaf_level)]
                                            .leaf(self.leaf_level, found.leaf)
                                            .map_err(|f| self.fault_error(f))?,
                                        reflection,
                                    )),
                                };
                                leaves[cached] = (key.0, key.1, key.2, bits);
                                cached += 1;
                                cached - 1
                            }
                        };
                        leaves[at].3.is_some_and(|leaf| {
                            brick_cell_occupied(leaf, cell, level == self.depth)
                        })
                    };
                    if occupied {
                        bits |= 1 << ((dx + 2) + 5 * (dy + 2) + 25 * (dz + 2));
                    }
                }
            }
        }
        Ok(bits)
    }

    /// The occupied cell of `level` holding the grid point `origin` (a ray with no direction).
    fn point_cell(
        &self,
        origin: [f64; 3],
        level: u8,
        stack: &mut Stack,
    ) -> Result<Option<Found>, TraceError> {
        let s = f64::from(self.cell_size[usize::from(level)]);
        let cell = origin.map(|o| ((o / s).floor() as u32).min((1u32 << level) - 1));
        if level == 0 {
            return Ok(Some(Found { cell, leaf: 0 }));
        }
        Ok(self
            .lookup(cell, level, stack)
            .map_err(|f| self.fault_error(f))?
            .map(|(found, _)| found))
    }

    /// Whether hits carry an attribute index (which needs the path to the cell).
    pub(crate) fn index_kind(&self) -> bool {
        self.compute_index && self.attribute_kind == AttributeKind::VoxelCount
    }

    fn fault_error(&self, fault: Fault) -> TraceError {
        let level = &self.levels[usize::from(fault.level).min(MAX_STORED_LEVELS - 1)];
        let offset = level.file_offset + fault.at;
        let error = if fault.truncated {
            FormatError::new(
                ErrorCode::TruncatedNode,
                offset,
                "a node record runs past the end of its level",
            )
        } else {
            FormatError::new(
                ErrorCode::PointerOutOfRange,
                offset,
                format!(
                    "a pointer leads to byte {} of level {}, outside its {} bytes",
                    fault.at,
                    fault.level,
                    level.bytes.len()
                ),
            )
        };
        TraceError::Malformed(error.at_level(fault.level))
    }

    /// Maps the ray to the traversal's frame and decides how to trace it.
    /// Always inlined: returning the prepared ray through memory costs a
    /// store-forwarding stall larger than the whole set-up.
    #[inline(always)]
    pub(crate) fn setup(&self, ray: &Ray) -> Result<Setup, TraceError> {
        let level = match ray.level {
            None => self.depth,
            Some(l) if l <= self.depth => l,
            Some(l) => {
                return Err(TraceError::LevelTooDeep {
                    level: l,
                    depth: self.depth,
                });
            }
        };
        // A NaN bound, or tmin > tmax: no segment.
        let ordered = matches!(
            ray.tmin.partial_cmp(&ray.tmax),
            Some(std::cmp::Ordering::Less | std::cmp::Ordering::Equal)
        );
        if !ordered || self.empty {
            return Ok(Setup::Miss);
        }
        let origin =
            [0, 1, 2].map(|i| (f64::from(ray.origin[i]) - self.root_min[i]) * self.grid_scale);
        let mut dir = ray.dir.map(|d| f64::from(d) * self.grid_scale);
        if !origin.iter().chain(&dir).all(|v| v.is_finite()) {
            // NaN, or outside what the grid can express (an infinite origin,
            // or a root cube so small that the direction overflows): a miss.
            return Ok(Setup::Miss);
        }
        let resolution = (1u64 << self.depth) as f64;
        let largest = dir[0].abs().max(dir[1].abs()).max(dir[2].abs());
        if largest < f64::MIN_POSITIVE {
            // A zero (or denormal) direction: the ray is the point `origin`.
            let inside = origin.iter().all(|&o| (0.0..=resolution).contains(&o));
            return Ok(if inside {
                Setup::Point {
                    origin,
                    tmin: ray.tmin,
                    level,
                }
            } else {
                Setup::Miss
            });
        }
        let mut moving = [true; 3];
        for (d, m) in dir.iter_mut().zip(&mut moving) {
            if d.abs() < largest * TINY_DIRECTION {
                *d = 0.0;
                *m = false;
            }
        }
        let (mut tmin, mut tmax) = (f64::from(ray.tmin), f64::from(ray.tmax));
        let mut base = 0.0;
        let far = origin.iter().any(|o| o.abs() > resolution * 16.0);
        if far {
            // Far origins are moved to the ray's entry into the cube so that
            // the f32 origin keeps its precision and plane parameters stay in
            // range; the tolerance is proportional to |o_g| there anyway.
            let Some(enter) = slab_entry(&origin, &dir, tmin, tmax, resolution) else {
                return Ok(Setup::Miss);
            };
            base = enter;
            tmin -= base;
            tmax -= base;
        }
        Ok(Setup::Trace(self.prepare(
            origin,
            dir,
            largest,
            moving,
            [tmin, tmax],
            base,
            level,
        )))
    }

    /// The end of [`Tracer::setup`] for a ray that is traced: scaled,
    /// mirrored and rounded to the traversal's f32 frame. `dir` has its
    /// (treated as) zero components zeroed; `largest` is its largest
    /// magnitude; `bounds` are `tmin` and `tmax` re-based by `base`.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub(crate) fn prepare(
        &self,
        origin: [f64; 3],
        dir: [f64; 3],
        largest: f64,
        moving: [bool; 3],
        bounds: [f64; 2],
        base: f64,
        level: u8,
    ) -> Prepared {
        let [tmin, tmax] = bounds;
        let resolution = (1u64 << self.depth) as f64;
        // Scale the direction by a power of two (exact) so that its largest
        // component lies in [1, 2): t' = (t - base) * scale.
        let scale_bits = largest.to_bits() & 0x7ff0_0000_0000_0000;
        let scale = f64::from_bits(scale_bits);
        // 1 / scale is a power of two too: negate the exponent (no division).
        let exponent = scale_bits >> 52;
        let inv_scale = if (1..=2045).contains(&exponent) {
            f64::from_bits((2046 - exponent) << 52)
        } else {
            1.0 / scale
        };
        // |d| / scale (exact) in [2^-60, 2); zero axes count as 1 in the product.
        let scaled = dir.map(|d| if d == 0.0 { 1.0 } else { d.abs() * inv_scale });
        // Three reciprocals from one division; the few f64 roundings are far
        // below the one f32 rounding that follows.
        let reciprocal = 1.0 / (scaled[0] * scaled[1] * scaled[2]);
        let inverse = [
            reciprocal * scaled[1] * scaled[2],
            reciprocal * scaled[0] * scaled[2],
            reciprocal * scaled[0] * scaled[1],
        ];
        let mut neg = 0usize;
        let mut o32 = [0f32; 3];
        let mut inv32 = [0f32; 3];
        for i in 0..3 {
            let mut o = origin[i] + base * dir[i];
            if dir[i] < 0.0 {
                neg |= 1 << i;
                o = resolution - o;
            }
            o32[i] = o as f32;
            inv32[i] = if dir[i] == 0.0 {
                (1.0 / TINY_DIRECTION) as f32
            } else {
                inverse[i] as f32
            };
        }
        Prepared {
            origin: Vec3A::from_array(o32),
            inv_dir: Vec3A::from_array(inv32),
            tmin: (tmin * scale) as f32,
            tmax: (tmax * scale) as f32,
            neg,
            moving: BVec3A::new(moving[0], moving[1], moving[2]),
            level,
            inv_scale,
            base,
        }
    }

    /// The front-to-back traversal. Returns the first occupied cell at the
    /// ray's level with its entry parameter and face; `stack[..min(level,
    /// leaf_level)]` then holds its path.
    #[inline]
    fn traverse(&self, p: &Prepared, stack: &mut Stack) -> Result<Option<(Found, f32, u8)>, Fault> {
        let mut fault = None;
        let found = self.traverse_recording(p, stack, &mut fault);
        match fault {
            Some(f) => Err(f),
            None => Ok(found),
        }
    }

    /// [`Tracer::traverse`] with faults recorded in `fault` rather than returned.
    #[inline(always)]
    fn traverse_recording(
        &self,
        p: &Prepared,
        stack: &mut Stack,
        fault: &mut Option<Fault>,
    ) -> Option<(Found, f32, u8)> {
        let cell = match self.start(p, fault) {
            Err(done) => done,
            Ok(mut walk) => loop {
                if let Some(done) = self.resume(&mut walk, stack, fault) {
                    break done;
                }
            },
        };
        cell.map(|(pos, level, leaf)| self.found(p, pos, level, leaf))
    }

    /// Starts the traversal of `p`: clips it to the occupied box and answers
    /// the rays that need no node read (`Err`: the first occupied cell as
    /// [`Tracer::resume`] gives it), or returns the walk from the root.
    #[inline(always)]
    fn start(&self, p: &Prepared, fault: &mut Option<Fault>) -> Result<Walk, Option<Cell>> {
        let leaf_level = self.leaf_level;
        let root_size = self.cell_size[0];
        // Clip the segment to the box of the occupied cells (to the cube for
        // rays coarser than the box's cells): a ray that misses it misses
        // everything. The clipped bounds drive the traversal; `p` keeps the
        // ray's own `tmin` for the entry face of the answer.
        let Some(q) = self.clip(p) else {
            return Err(None);
        };
        if p.level == 0 {
            return Err(Some((Vec3A::ZERO, 0, 0)));
        }
        if leaf_level == 0 {
            return Err(self
                .brick(&q, 0, 0, Vec3A::ZERO, fault)
                .map(|(cell, level)| (cell, level, 0)));
        }
        Ok(Walk {
            q,
            ray_tmin: p.tmin,
            // The level where the descent stops: the ray's level, or the leaf
            // level whose bricks are answered from their masks.
            stop: p.level.min(leaf_level),
            top: 0,
            level: 0,
            pending: Pending::Node,
            pos: Vec3A::ZERO,
            size: root_size,
            target: 0,
            reflection: 0,
            brick_pos: Vec3A::ZERO,
        })
    }

    /// `p` with its segment clipped to the box of the occupied cells (to the
    /// cube for rays coarser than the box's cells), or `None` when it misses
    /// the box: a ray that misses it misses everything.
    #[inline(always)]
    pub(crate) fn clip(&self, p: &Prepared) -> Option<Prepared> {
        let (lo, hi) = if p.level >= self.bounds_level {
            self.bounds[p.neg & 7]
        } else {
            (Vec3A::ZERO, Vec3A::splat(self.cell_size[0]))
        };
        let enter = max(((lo - p.origin) * p.inv_dir).max_element(), p.tmin);
        let exit = min(((hi - p.origin) * p.inv_dir).min_element(), p.tmax);
        (enter <= exit).then_some(Prepared {
            tmin: enter,
            tmax: exit,
            ..*p
        })
    }

    /// Runs `walk` up to its next read of a node or leaf that may miss the
    /// cache: that read is prefetched and `None` returned, to be resumed
    /// later. `Some` when the walk is over: the first occupied cell, or `None`
    /// when there is none.
    #[inline(always)]
    pub(crate) fn resume(
        &self,
        walk: &mut Walk,
        stack: &mut Stack,
        fault: &mut Option<Fault>,
    ) -> Option<Option<Cell>> {
        if self.v2 {
            self.resume_in::<true>(walk, stack, fault)
        } else {
            self.resume_in::<false>(walk, stack, fault)
        }
    }

    /// [`Tracer::resume`] compiled for one format: `V2` for 2.0, else 1.0,
    /// whose copy carries no reflection (R = 0 everywhere) and reads nodes
    /// without 2.0 tests.
    #[inline(always)]
    fn resume_in<const V2: bool>(
        &self,
        walk: &mut Walk,
        stack: &mut Stack,
        fault: &mut Option<Fault>,
    ) -> Option<Option<Cell>> {
        let q = &walk.q;
        // The ray's octant; a node reached with accumulated reflection R is
        // traced as a 1.0 node in octant `ray_neg ^ R` (spec §23.4): `neg`
        // and `reflection` are the node's.
        let ray_neg = q.neg & 7;
        let (origin, inv_dir) = (q.origin, q.inv_dir);
        let stop = walk.stop;
        let mut level = walk.level;
        let mut pos = walk.pos;
        let mut size = walk.size;
        let (mut word, mut mask, mut remaining, mut reflection);
        if walk.pending == Pending::Node {
            // Visit the node: the children the ray passes through.
            word = walk.target;
            reflection = if V2 { walk.reflection } else { 0 };
            let neg = ray_neg ^ usize::from(reflection & 7);
            let header = self.levels[usize::from(level) & LEVEL_INDEX]
                .header_or_fault::<V2>(level, word, fault);
            let t_lo = (pos - origin) * inv_dir;
            let t_mid = (pos + Vec3A::splat(size * 0.5) - origin) * inv_dir;
            let t_hi = (pos + Vec3A::splat(size) - origin) * inv_dir;
            let t_enter = max(t_lo.max_element(), q.tmin);
            let t_exit = min(t_hi.min_element(), q.tmax);
            mask = child_mask(header);
            remaining = if t_enter <= t_exit {
                chain(neg, t_enter, t_exit, t_mid) & mask
            } else {
                0
            };
        } else {
            // A brick below the node the walk stands on, whose frame is on
            // the stack.
            let leaf = walk.target;
            let leaf_reflection = if V2 { walk.reflection } else { 0 };
            if let Some((cell, cell_level)) =
                self.brick(q, leaf, leaf_reflection, walk.brick_pos, fault)
            {
                return Some(Some((cell, cell_level, leaf)));
            }
            let frame = stack[usize::from(level) & LEVEL_INDEX];
            word = frame.word;
            mask = frame.mask;
            remaining = frame.remaining;
            reflection = if V2 { frame.reflection } else { 0 };
        }
        while remaining == 0 {
            if level == walk.top {
                return Some(None);
            }
            // Back to the parent: undo the step into this node.
            level -= 1;
            let parent = stack[usize::from(level) & LEVEL_INDEX];
            let parent_reflection = if V2 { parent.reflection } else { 0 };
            let parent_neg = ray_neg ^ usize::from(parent_reflection);
            pos -= CHILD_STEPS[(usize::from(parent.last) ^ parent_neg) & 7] * size;
            size *= 2.0;
            word = parent.word;
            mask = parent.mask;
            remaining = parent.remaining;
            reflection = parent_reflection;
        }
        let neg = (ray_neg ^ usize::from(reflection)) & 7;
        let child = FIRST[neg][usize::from(remaining)];
        remaining &= !(1 << child);
        let l = usize::from(level) & LEVEL_INDEX;
        let reference =
            self.levels[l].child_or_fault::<V2>(level, word, mask, u32::from(child), fault);
        let pointer = reference.node;
        let half = size * 0.5;
        let child_pos = pos + CHILD_STEPS[(usize::from(child) ^ neg) & 7] * half;
        stack[l] = Frame {
            word,
            mask,
            remaining,
            last: child,
            reflection,
        };
        let child_reflection = if V2 {
            (reflection ^ reference.reflection) & 7
        } else {
            0
        };
        let child_level = level + 1;
        if child_level == stop {
            if stop == q.level {
                return Some(Some((child_pos, child_level, pointer)));
            }
            // The brick is read on resumption; the walk stays at its parent.
            let leaf_level = usize::from(self.leaf_level) & LEVEL_INDEX;
            prefetch(self.levels[leaf_level].bytes, pointer as usize * 8);
            walk.pending = Pending::Brick;
            walk.target = pointer;
            walk.reflection = child_reflection;
            walk.brick_pos = child_pos;
            walk.level = level;
            walk.pos = pos;
            walk.size = size;
            return None;
        }
        let next = &self.levels[usize::from(child_level) & LEVEL_INDEX];
        prefetch(next.bytes, next.node_byte_in::<V2>(pointer));
        walk.pending = Pending::Node;
        walk.target = pointer;
        walk.reflection = child_reflection;
        walk.level = child_level;
        walk.pos = child_pos;
        walk.size = half;
        None
    }

    /// The answer for the cell of `level` whose lower corner is at mirrored
    /// grid position `pos`: the cell in the file's frame, its entry parameter
    /// and its entry face.
    #[inline(always)]
    fn found(&self, p: &Prepared, pos: Vec3A, level: u8, leaf: u32) -> (Found, f32, u8) {
        self.found_from(p, p.tmin, pos, level, leaf)
    }

    /// [`Tracer::found`] for the ray `p` with its segment starting at `tmin`.
    #[inline(always)]
    fn found_from(
        &self,
        p: &Prepared,
        tmin: f32,
        pos: Vec3A,
        level: u8,
        leaf: u32,
    ) -> (Found, f32, u8) {
        // Entry: the latest slab start of the moving axes, or tmin (face 0).
        let t_lo = (pos - p.origin) * p.inv_dir;
        let t_lo = Vec3A::select(p.moving, t_lo, Vec3A::NEG_INFINITY);
        let [x, y, z] = t_lo.to_array();
        // The first axis of the largest, without branches: x if x >= y and
        // x >= z, else y if y >= z, else z.
        let (x_largest, y_next) = (x >= y && x >= z, y >= z);
        let axis = usize::from(!x_largest) * (2 - usize::from(y_next));
        let near = [x, y, z][axis];
        let axis = axis as u8;
        let (t, face) = if near < tmin {
            (tmin, 0)
        } else {
            (near, 1 + 2 * axis + (p.neg >> axis & 1) as u8)
        };
        let t = (f64::from(t) * p.inv_scale + p.base) as f32;
        // Cell coordinates: the position (an exact multiple of the cell
        // size, a power of two) over the cell size.
        let shift = u32::from(self.depth.saturating_sub(level)) & 31;
        let [px, py, pz] = pos.to_array();
        let m = [px as u32 >> shift, py as u32 >> shift, pz as u32 >> shift];
        let last = (1u32 << (level & 31)) - 1;
        // Mirrored back on the axes of negative direction: `last - m`, which
        // is `last ^ m` (m <= last), chosen without a branch (a coin toss
        // per axis for the branch predictor).
        debug_assert!(
            m.iter().all(|&v| v <= last),
            "a cell outside the grid: {m:?}"
        );
        let flip = |i: usize| last & 0u32.wrapping_sub((p.neg >> i & 1) as u32);
        let cell = [m[0] ^ flip(0), m[1] ^ flip(1), m[2] ^ flip(2)];
        (Found { cell, leaf }, t, face)
    }

    /// The last two levels: the first set sub-brick (level D-1) or voxel
    /// (level D) of the 4³ brick `leaf` whose lower corner is at mirrored grid
    /// position `pos`, answered from the leaf mask alone. Returns the cell's
    /// mirrored position and level.
    #[inline(always)]
    pub(crate) fn brick(
        &self,
        p: &Prepared,
        leaf: u32,
        reflection: u8,
        pos: Vec3A,
        fault: &mut Option<Fault>,
    ) -> Option<(Vec3A, u8)> {
        let bits = self.levels[usize::from(self.leaf_level) & LEVEL_INDEX].leaf_or_fault(
            self.leaf_level,
            leaf,
            fault,
        );
        // The sub-brick byte and the voxel bit in it are each indexed by
        // three axis bits: a leaf reached with R is traced in octant
        // `neg ^ R` on both (spec §23.4).
        let neg = (p.neg ^ usize::from(reflection)) & 7;
        let t0 = (pos - p.origin) * p.inv_dir;
        let t1 = (pos + Vec3A::splat(1.0) - p.origin) * p.inv_dir;
        let t2 = (pos + Vec3A::splat(2.0) - p.origin) * p.inv_dir;
        let t3 = (pos + Vec3A::splat(3.0) - p.origin) * p.inv_dir;
        let t4 = (pos + Vec3A::splat(4.0) - p.origin) * p.inv_dir;
        let t_enter = max(t0.max_element(), p.tmin);
        let t_exit = min(t4.min_element(), p.tmax);
        if t_enter > t_exit {
            return None;
        }
        let mut remaining = chain(neg, t_enter, t_exit, t2) & sub_brick_mask(bits);
        while remaining != 0 {
            let sub = usize::from(FIRST[neg][usize::from(remaining)]);
            remaining &= !(1 << sub);
            let m = (sub ^ neg) & 7;
            let step = CHILD_STEPS[m];
            let sub_pos = pos + step * 2.0;
            if p.level < self.depth {
                return Some((sub_pos, self.depth - 1));
            }
            // The axes on which the sub-brick is the upper half.
            let upper = step.cmpgt(Vec3A::ZERO);
            let s_lo = Vec3A::select(upper, t2, t0);
            let s_mid = Vec3A::select(upper, t3, t1);
            let s_hi = Vec3A::select(upper, t4, t2);
            let s_enter = max(s_lo.max_element(), p.tmin);
            let s_exit = min(s_hi.min_element(), p.tmax);
            if s_enter > s_exit {
                continue;
            }
            let voxels = chain(neg, s_enter, s_exit, s_mid) & sub_brick(bits, sub as u32);
            if voxels != 0 {
                let v = (usize::from(FIRST[neg][usize::from(voxels)]) ^ neg) & 7;
                return Some((sub_pos + CHILD_STEPS[v], self.depth));
            }
        }
        None
    }

    /// [`Tracer::brick`] for the brick `leaf` at mirrored position `pos`,
    /// mirrored child `child` of a node whose plane parameters `planes`
    /// (lower, middle, upper) the ray's visit of the node computed: the
    /// brick's outer planes are among the node's (the same numbers, since
    /// every plane parameter is `(plane - origin) * inv` of the same exact
    /// plane), so only its inner planes are computed here. The very same
    /// answers as `brick`; `Err` for a leaf outside its level. (The loop over
    /// the sub-bricks repeats `brick`'s: sharing it through one inlined
    /// helper cost the vector lanes 2.6 % more instructions on random rays,
    /// through different code generation in `simd::run`.)
    #[inline(always)]
    pub(crate) fn brick_in_node(
        &self,
        p: &Prepared,
        leaf: u32,
        reflection: u8,
        pos: Vec3A,
        child: usize,
        planes: (Vec3A, Vec3A, Vec3A),
    ) -> Result<Option<(Vec3A, u8)>, ()> {
        let bits = self.levels[usize::from(self.leaf_level) & LEVEL_INDEX]
            .leaf(self.leaf_level, leaf)
            .map_err(|_| ())?;
        // As in `brick`: a leaf reached with R is traced in octant `neg ^ R`.
        let neg = (p.neg ^ usize::from(reflection)) & 7;
        let upper = CHILD_STEPS[child & 7].cmpgt(Vec3A::ZERO);
        let (t_lo, t_mid, t_hi) = planes;
        let t0 = Vec3A::select(upper, t_mid, t_lo);
        let t4 = Vec3A::select(upper, t_hi, t_mid);
        let t_enter = max(t0.max_element(), p.tmin);
        let t_exit = min(t4.min_element(), p.tmax);
        if t_enter > t_exit {
            return Ok(None);
        }
        let t2 = (pos + Vec3A::splat(2.0) - p.origin) * p.inv_dir;
        let mut remaining = chain(neg, t_enter, t_exit, t2) & sub_brick_mask(bits);
        if remaining == 0 {
            return Ok(None);
        }
        if p.level < self.depth {
            let sub = usize::from(FIRST[neg][usize::from(remaining)]);
            return Ok(Some((
                pos + CHILD_STEPS[(sub ^ neg) & 7] * 2.0,
                self.depth - 1,
            )));
        }
        let t1 = (pos + Vec3A::splat(1.0) - p.origin) * p.inv_dir;
        let t3 = (pos + Vec3A::splat(3.0) - p.origin) * p.inv_dir;
        while remaining != 0 {
            let sub = usize::from(FIRST[neg][usize::from(remaining)]);
            remaining &= !(1 << sub);
            let m = (sub ^ neg) & 7;
            let step = CHILD_STEPS[m];
            let sub_pos = pos + step * 2.0;
            // The axes on which the sub-brick is the upper half.
            let upper = step.cmpgt(Vec3A::ZERO);
            let s_lo = Vec3A::select(upper, t2, t0);
            let s_mid = Vec3A::select(upper, t3, t1);
            let s_hi = Vec3A::select(upper, t4, t2);
            let s_enter = max(s_lo.max_element(), p.tmin);
            let s_exit = min(s_hi.min_element(), p.tmax);
            if s_enter > s_exit {
                continue;
            }
            let voxels = chain(neg, s_enter, s_exit, s_mid) & sub_brick(bits, sub as u32);
            if voxels != 0 {
                let v = (usize::from(FIRST[neg][usize::from(voxels)]) ^ neg) & 7;
                return Ok(Some((sub_pos + CHILD_STEPS[v], self.depth)));
            }
        }
        Ok(None)
    }

    /// Follows the path of `cell` (at `level`) from the root, filling `stack`
    /// with the interior nodes on the way. `None` when the cell is empty.
    /// With the cell, the accumulated reflection of the node or leaf
    /// reached (spec §23.4).
    fn lookup(
        &self,
        cell: [u32; 3],
        level: u8,
        stack: &mut Stack,
    ) -> Result<Option<(Found, u8)>, Fault> {
        let mut word = 0u32;
        let mut reflection = 0u8;
        for l in 0..level.min(self.leaf_level) {
            let mask = child_mask(self.levels[usize::from(l)].header(l, word)?);
            // The logical child's physical slot.
            let slot = child_at(cell, level - 1 - l) ^ u32::from(reflection);
            stack[usize::from(l)] = Frame {
                word,
                mask,
                remaining: 0,
                last: slot as u8,
                reflection,
            };
            if mask >> slot & 1 == 0 {
                return Ok(None);
            }
            let reference = self.levels[usize::from(l)].child(l, word, mask, slot)?;
            word = reference.node;
            reflection ^= reference.reflection;
        }
        let found = Found { cell, leaf: word };
        if level <= self.leaf_level {
            return Ok(Some((found, reflection)));
        }
        let bits = self.levels[usize::from(self.leaf_level)].leaf(self.leaf_level, word)?;
        let occupied =
            brick_cell_occupied(logical_leaf(bits, reflection), cell, level == self.depth);
        Ok(occupied.then_some((found, reflection)))
    }

    /// The dense index of the first voxel of the found cell, from the path in
    /// `stack`: the counts of the earlier siblings on every level plus the set
    /// bits before it in its leaf.
    fn index(&self, found: &Found, level: u8, stack: &Stack) -> Result<Option<u64>, Fault> {
        if !self.index_kind() {
            return Ok(None);
        }
        INDEX_MEMO.with_borrow_mut(|memo| {
            let index = self.index_from(found, level, stack, memo);
            if index.is_err() {
                // Its sums are half rewritten.
                memo.tracer = 0;
            }
            index.map(Some)
        })
    }

    /// [`Tracer::index`], reusing (and then replacing) the sums in `memo`
    /// for the levels its cell's path shares with this one.
    #[inline(always)]
    fn index_from(
        &self,
        found: &Found,
        level: u8,
        stack: &Stack,
        memo: &mut IndexMemo,
    ) -> Result<u64, Fault> {
        let top = level.min(self.leaf_level);
        // Levels `0..shared` are summed in `memo` already.
        let mut shared = 0;
        if memo.tracer == self.id && memo.level == level {
            let differ = (memo.cell[0] ^ found.cell[0])
                | (memo.cell[1] ^ found.cell[1])
                | (memo.cell[2] ^ found.cell[2]);
            if differ == 0 {
                return Ok(memo.index);
            }
            // Level `l` reads its child index from bit `level - 1 - l`.
            let highest = 31 - differ.leading_zeros();
            shared = u32::from(level)
                .saturating_sub(highest + 1)
                .min(u32::from(top)) as u8;
        }
        let mut index = memo.sums[usize::from(shared) & LEVEL_INDEX];
        for l in shared..top {
            let frame = stack[usize::from(l) & LEVEL_INDEX];
            let section = &self.levels[usize::from(l) & LEVEL_INDEX];
            let child = child_at(found.cell, level - 1 - l);
            // The logical siblings before the child, as physical slots
            // (spec §23.5; a prefix of the mask in 1.0).
            let before =
                SIBLINGS_BEFORE[usize::from(frame.reflection & 7)][child as usize & 7] & frame.mask;
            let rank = child_count(before);
            let children = child_count(frame.mask);
            // The earlier siblings' counts or, where that reads fewer, the
            // node's own count (its header is on the path, read already)
            // less those of the child and the later siblings: the same
            // number in a valid file, whose counts add up.
            let earlier = rank <= children - rank;
            let mut sum = 0u64;
            if section.is_v2() {
                let mut slots = if earlier {
                    before
                } else {
                    frame.mask & !before
                };
                while slots != 0 {
                    let slot = slots.trailing_zeros();
                    slots &= slots - 1;
                    let pointer = section.child(l, frame.word, frame.mask, slot)?.node;
                    sum = sum.saturating_add(self.count(l + 1, pointer)?);
                }
            } else {
                for r in if earlier { 0..rank } else { rank..children } {
                    let pointer = section.reference(l, frame.word, r)?.node;
                    sum = sum.saturating_add(self.count(l + 1, pointer)?);
                }
            }
            if !earlier {
                sum = self.count(l, frame.word)?.saturating_sub(sum);
            }
            index = index.saturating_add(sum);
            memo.sums[usize::from(l + 1) & LEVEL_INDEX] = index;
        }
        if level > self.leaf_level {
            let mut bits =
                self.levels[usize::from(self.leaf_level)].leaf(self.leaf_level, found.leaf)?;
            if self.v2 && self.leaf_level > 0 {
                // The leaf's accumulated reflection: its parent's, on the
                // path, and that of the reference to it.
                let l = self.leaf_level - 1;
                let frame = stack[usize::from(l) & LEVEL_INDEX];
                let slot = child_at(found.cell, level - 1 - l) ^ u32::from(frame.reflection);
                let reference = self.levels[usize::from(l) & LEVEL_INDEX]
                    .child(l, frame.word, frame.mask, slot)?;
                bits = logical_leaf(bits, frame.reflection ^ reference.reflection);
            }
            let c = found.cell;
            let below = if level == self.depth {
                voxel_bit(c)
            } else {
                8 * child_at(c, 0)
            };
            index += u64::from(voxels_below(bits, below));
        }
        memo.tracer = self.id;
        memo.level = level;
        memo.cell = found.cell;
        memo.index = index;
        Ok(index)
    }

    /// Voxel count of a node or leaf: stored count, or the precomputed sum
    /// for saturated nodes.
    #[inline(always)]
    fn count(&self, level: u8, pointer: u32) -> Result<u64, Fault> {
        let section = &self.levels[usize::from(level) & LEVEL_INDEX];
        if level == self.leaf_level {
            return Ok(u64::from(section.leaf(level, pointer)?.count_ones()));
        }
        let count = attribute(section.header(level, pointer)?);
        if count != COUNT_SATURATED {
            return Ok(u64::from(count));
        }
        self.saturated_count(level, pointer)
    }

    /// [`Tracer::count`] of a node whose stored count is saturated: a few
    /// nodes near the root, kept out of line.
    #[inline(never)]
    fn saturated_count(&self, level: u8, pointer: u32) -> Result<u64, Fault> {
        match self.saturated.get(&(level, pointer)) {
            Some(&n) => Ok(n),
            // Not reached from the root by saturated nodes: only in a file
            // whose counts are wrong. Count it now (the map is read-only here).
            None => {
                let mut scratch = FxHashMap::default();
                self.count_saturated(level, pointer, &mut scratch)
            }
        }
    }

    /// Computes (memoised in `memo`) the voxel count of a node whose stored
    /// count may be saturated, summing its children where it is.
    fn count_saturated(
        &self,
        level: u8,
        word: u32,
        memo: &mut FxHashMap<(u8, u32), u64>,
    ) -> Result<u64, Fault> {
        let section = &self.levels[usize::from(level)];
        if level == self.leaf_level {
            return Ok(u64::from(section.leaf(level, word)?.count_ones()));
        }
        let header = section.header(level, word)?;
        if attribute(header) != COUNT_SATURATED {
            return Ok(u64::from(attribute(header)));
        }
        if let Some(&n) = memo.get(&(level, word)) {
            return Ok(n);
        }
        let mut total = 0u64;
        let mask = child_mask(header);
        for slot in (0..8).filter(|s| mask >> s & 1 != 0) {
            let pointer = section.child(level, word, mask, slot)?.node;
            total = total.saturating_add(self.count_saturated(level + 1, pointer, memo)?);
        }
        memo.insert((level, word), total);
        Ok(total)
    }
}

/// The chain of children (file frame mask) a ray passes through inside a node
/// entered at `t_enter` and left at `t_exit`, whose mid-planes it crosses at `t_mid`.
#[inline(always)]
pub(crate) fn chain(neg: usize, t_enter: f32, t_exit: f32, t_mid: Vec3A) -> u8 {
    let enter = Vec3A::splat(t_enter);
    let exit = Vec3A::splat(t_exit);
    let first = t_mid.cmple(enter).bitmask();
    // A crossing exactly at the exit still touches the next (closed) child.
    let crossing = (t_mid.cmpgt(enter) & t_mid.cmple(exit)).bitmask();
    let order = t_mid.xxy().cmplt(t_mid.yzz()).bitmask();
    CHAIN[neg][((first | crossing << 3 | order << 6) & 511) as usize]
}

/// Hints the processor to load the cache line holding `bytes[at]` (nothing
/// when `at` is out of range).
#[inline(always)]
pub(crate) fn prefetch(bytes: &[u8], at: usize) {
    #[cfg(target_arch = "x86_64")]
    if at < bytes.len() {
        let address = bytes.as_ptr().wrapping_add(at);
        // SAFETY: `prefetch` is only a hint: it reads nothing the program
        // sees, never faults, and `sse` is part of the x86-64 baseline.
        unsafe {
            std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(address.cast())
        };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (bytes, at);
}

/// `_mm_prefetch`'s hint for the first-level cache (`_MM_HINT_T0`).
const INTO_L1: i32 = 3;
/// `_mm_prefetch`'s hint for the second-level cache (`_MM_HINT_T1`).
const INTO_L2: i32 = 2;
// The hints are spelled out so that they exist on every target; on x86-64
// they must be the intrinsics' own.
#[cfg(target_arch = "x86_64")]
const _: () =
    assert!(INTO_L1 == std::arch::x86_64::_MM_HINT_T0 && INTO_L2 == std::arch::x86_64::_MM_HINT_T1);

/// Hints the processor to load the cache line holding `at`, which need not
/// be a valid address, into the cache that `HINT` names ([`INTO_L1`] or
/// [`INTO_L2`]).
#[inline(always)]
fn prefetch_into<const HINT: i32>(at: *const u8) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: `prefetch` is only a hint: it reads nothing the program sees
    // and never faults, whatever the address; `sse` is part of the x86-64
    // baseline.
    unsafe {
        std::arch::x86_64::_mm_prefetch::<HINT>(at.cast())
    };
    #[cfg(not(target_arch = "x86_64"))]
    let _ = at;
}

/// Hints the processor to load the cache line holding `at`, which need not
/// be a valid address.
#[inline(always)]
pub(crate) fn prefetch_address(at: *const u8) {
    prefetch_into::<INTO_L1>(at);
}

/// Hints the processor to load the cache lines that hold `items` into the
/// second-level cache: for the streams of rays and hits, read or written
/// some thousand cycles later. Into the first-level cache, as
/// [`prefetch_address`] does, they were slower: d12 camera frames in row
/// order 0.96 of this rate on one core, tiles 0.95 on two (alternating runs
/// on machine G); likely because a tile's 85 lines took the first-level
/// cache's few miss buffers from the reads of the DAG.
#[inline(always)]
pub(crate) fn prefetch_range<T>(items: &[T]) {
    let (start, bytes) = (items.as_ptr().cast::<u8>(), std::mem::size_of_val(items));
    if bytes == 0 {
        return;
    }
    let mut at = 0;
    while at < bytes {
        prefetch_into::<INTO_L2>(start.wrapping_add(at));
        at += 64;
    }
    // The last line, where the items do not start on a line.
    prefetch_into::<INTO_L2>(start.wrapping_add(bytes - 1));
}

/// `a.max(b)` without NaN handling (the traversal has no NaN): one `maxss`.
#[inline(always)]
pub(crate) fn max(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

/// `a.min(b)` without NaN handling: one `minss`.
#[inline(always)]
pub(crate) fn min(a: f32, b: f32) -> f32 {
    if a < b { a } else { b }
}

/// Unit steps to the eight children, by child index (x, y, z = bits 0, 1, 2).
pub(crate) const CHILD_STEPS: [Vec3A; 8] = {
    let mut t = [Vec3A::ZERO; 8];
    let mut c = 0;
    while c < 8 {
        t[c] = Vec3A::new(
            CHILD_BITS[c][0] as f32,
            CHILD_BITS[c][1] as f32,
            CHILD_BITS[c][2] as f32,
        );
        c += 1;
    }
    t
};

/// Entry parameter (not before `tmin`) of the line `o + t d` into the cube
/// `[0, size]^3` over `[tmin, tmax]` (f64; zero direction components give all
/// or nothing), or `None` when the segment misses it.
fn slab_entry(o: &[f64; 3], d: &[f64; 3], tmin: f64, tmax: f64, size: f64) -> Option<f64> {
    let (mut near, mut far) = (tmin, tmax);
    for i in 0..3 {
        if d[i] == 0.0 {
            if o[i] < 0.0 || o[i] > size {
                return None;
            }
        } else {
            let a = (0.0 - o[i]) / d[i];
            let b = (size - o[i]) / d[i];
            near = near.max(a.min(b));
            far = far.min(a.max(b));
        }
    }
    (near <= far).then_some(near)
}
