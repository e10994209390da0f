//! The CPU ray tracer: front-to-back DAG traversal in grid space.
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

use dagfmt::layout::{AttributeKind, COUNT_SATURATED, leaf_bit};
use dagfmt::{Dag, ErrorCode, FormatError};
use glam::{BVec3A, Vec3A, Vec3Swizzles};
use rustc_hash::FxHashMap;

use crate::tables::{CHAIN, CHILD_BITS, FIRST, POPCOUNT8};
use dagfmt::batch::{Hit, Ray};

/// Most levels a file can have (depth 21 has levels 0 ..= 19 stored).
const MAX_STORED_LEVELS: usize = 20;

/// Length of the per-level arrays: a power of two above the number of levels,
/// so that indexing with `level & LEVEL_INDEX` needs no bounds check.
const LEVEL_SLOTS: usize = 32;
const LEVEL_INDEX: usize = LEVEL_SLOTS - 1;

/// Direction given to axes whose direction is (treated as) zero, relative to a
/// largest component in `[1, 2)`.
const TINY_DIRECTION: f64 = 1.0 / (1u64 << 60) as f64;

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

/// A bounds-check failure inside the traversal: small and `Copy` so that the
/// hot path's `Result` stays cheap; turned into a [`FormatError`] at the API.
#[derive(Clone, Copy, Debug)]
struct Fault {
    level: u8,
    /// Byte offset inside the level section of the read that failed.
    at: u64,
    /// Whether a node record (header or pointers) was cut by the section end,
    /// as opposed to a pointer to a record outside the section.
    truncated: bool,
}

/// Keeps the first fault; reads as 0.
#[cold]
fn record(fault: &mut Option<Fault>, f: Fault) -> u32 {
    fault.get_or_insert(f);
    0
}

/// One stored level: its bytes and pointer width.
#[derive(Clone, Copy, Debug, Default)]
struct Level<'a> {
    bytes: &'a [u8],
    file_offset: u64,
    /// Pointer width in bytes (node levels).
    width: u32,
    /// Mask keeping the low `width` bytes of a 32-bit load.
    pointer_mask: u32,
}

impl Level<'_> {
    #[inline(always)]
    fn read_u32(&self, at: usize) -> Option<u32> {
        match self.bytes.get(at..at + 4) {
            Some(&[a, b, c, d]) => Some(u32::from_le_bytes([a, b, c, d])),
            _ => None,
        }
    }

    /// The header word of the node at `word`.
    #[inline(always)]
    fn header(&self, level: u8, word: u32) -> Result<u32, Fault> {
        let at = word as usize * 4;
        self.read_u32(at).ok_or(Fault {
            level,
            at: at as u64,
            truncated: false,
        })
    }

    /// Pointer number `rank` of the node at `word`.
    #[inline(always)]
    fn pointer(&self, level: u8, word: u32, rank: u32) -> Result<u32, Fault> {
        let at = word as usize * 4 + 4 + (rank * self.width) as usize;
        // Fast path: one 32-bit load, masked to the pointer width. The bytes
        // after the pointer belong to the same record's padding or to the next
        // record and are masked away.
        if let Some(v) = self.read_u32(at) {
            return Ok(v & self.pointer_mask);
        }
        // Near the end of the section: assemble the pointer byte by byte.
        let bytes = self.bytes.get(at..at + self.width as usize).ok_or(Fault {
            level,
            at: at as u64,
            truncated: true,
        })?;
        Ok(bytes.iter().rev().fold(0u32, |v, &b| v << 8 | u32::from(b)))
    }

    /// [`Level::header`] for the traversal: an out-of-range read records the
    /// fault (the first one) and reads as 0, a node without children, which
    /// ends that branch; the caller reports the fault when it is done. This
    /// keeps `Result` plumbing out of the inner loop.
    #[inline(always)]
    fn header_or_fault(&self, level: u8, word: u32, fault: &mut Option<Fault>) -> u32 {
        match self.read_u32(word as usize * 4) {
            Some(v) => v,
            None => record(
                fault,
                Fault {
                    level,
                    at: u64::from(word) * 4,
                    truncated: false,
                },
            ),
        }
    }

    /// [`Level::pointer`] for the traversal (see [`Level::header_or_fault`]).
    #[inline(always)]
    fn pointer_or_fault(&self, level: u8, word: u32, rank: u32, fault: &mut Option<Fault>) -> u32 {
        let at = word as usize * 4 + 4 + (rank * self.width) as usize;
        match self.read_u32(at) {
            Some(v) => v & self.pointer_mask,
            None => self.pointer_near_end(level, word, rank, fault),
        }
    }

    /// The rare pointer whose 32-bit load would cross the end of the section.
    #[cold]
    #[inline(never)]
    fn pointer_near_end(&self, level: u8, word: u32, rank: u32, fault: &mut Option<Fault>) -> u32 {
        match self.pointer(level, word, rank) {
            Ok(v) => v,
            Err(f) => record(fault, f),
        }
    }

    /// [`Level::leaf`] for the traversal: an out-of-range leaf reads as empty.
    #[inline(always)]
    fn leaf_or_fault(&self, level: u8, index: u32, fault: &mut Option<Fault>) -> u64 {
        match self.leaf(level, index) {
            Ok(v) => v,
            Err(f) => u64::from(record(fault, f)),
        }
    }

    /// The leaf mask at `index` (leaf level).
    #[inline(always)]
    fn leaf(&self, level: u8, index: u32) -> Result<u64, Fault> {
        let at = index as usize * 8;
        match self.bytes.get(at..at + 8) {
            Some(&[a, b, c, d, e, f, g, h]) => Ok(u64::from_le_bytes([a, b, c, d, e, f, g, h])),
            _ => Err(Fault {
                level,
                at: at as u64,
                truncated: false,
            }),
        }
    }
}

/// One entry of the traversal stack: an interior node on the current path.
#[derive(Clone, Copy, Debug, Default)]
struct Frame {
    /// Word offset of the node in its level.
    word: u32,
    /// The node's child mask.
    mask: u8,
    /// Children the ray passes through that are still to be visited.
    remaining: u8,
    /// The child (file index) being visited below this node, to step back to
    /// this node's position when the visit ends.
    last: u8,
    /// Explicit padding, so that a stack of frames is zeroed with a memset.
    _pad: u8,
}

type Stack = [Frame; LEVEL_SLOTS];

/// The ray in the traversal's f32 mirrored grid frame.
#[derive(Clone, Copy, Debug)]
struct Prepared {
    /// Origin (mirrored, re-based, grid units).
    origin: Vec3A,
    /// 1 / direction (all positive).
    inv_dir: Vec3A,
    tmin: f32,
    tmax: f32,
    /// Direction octant: bit i set when axis i is mirrored.
    neg: usize,
    /// Axes whose direction is not (treated as) zero.
    moving: BVec3A,
    /// Level traced.
    level: u8,
    /// The traversal's parameter is `t' = (t - base) * scale`: `1 / scale`.
    inv_scale: f64,
    base: f64,
}

/// What set-up decided about a ray.
enum Setup {
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

/// A ray tracer over one DAG. Cheap to share between threads (`Sync`).
///
/// It borrows the file's bytes (zero-copy); the only thing computed when it is
/// made is, for attribute kind 1, the voxel counts of the nodes whose stored
/// count is saturated (at most one entry per such node in the file).
#[derive(Clone, Debug)]
pub struct Tracer<'a> {
    levels: [Level<'a>; LEVEL_SLOTS],
    depth: u8,
    leaf_level: u8,
    empty: bool,
    attribute_kind: AttributeKind,
    root_min: [f64; 3],
    /// Grid units per world unit: 2^D / root_size.
    grid_scale: f64,
    /// Edge length in grid units of a cell of each level: 2^(D - level).
    cell_size: [f32; MAX_STORED_LEVELS + 2],
    /// Voxel counts of saturated nodes, keyed by (level, word).
    saturated: FxHashMap<(u8, u32), u64>,
    compute_index: bool,
    colors: Option<&'a [u8]>,
}

impl<'a> Tracer<'a> {
    /// Makes a tracer for `dag`. Fails only when, for attribute kind 1, the
    /// nodes with saturated counts lead to a pointer outside their level.
    pub fn new(dag: &Dag<'a>) -> Result<Self, TraceError> {
        let depth = dag.header().depth;
        let mut levels = [Level::default(); LEVEL_SLOTS];
        for (slot, section) in levels.iter_mut().zip(dag.levels()) {
            let width = u32::from(section.pointer_width);
            *slot = Level {
                bytes: section.bytes,
                file_offset: section.file_offset,
                width,
                pointer_mask: if width >= 4 {
                    u32::MAX
                } else {
                    (1u32 << (8 * width)) - 1
                },
            };
        }
        let mut cell_size = [0f32; MAX_STORED_LEVELS + 2];
        for (level, size) in cell_size
            .iter_mut()
            .enumerate()
            .take(usize::from(depth) + 1)
        {
            *size = (1u32 << (u32::from(depth) - level as u32)) as f32;
        }
        let header = dag.header();
        let mut tracer = Tracer {
            levels,
            depth,
            leaf_level: depth - 2,
            empty: dag.is_empty(),
            attribute_kind: header.attribute_kind,
            root_min: header.root_min,
            grid_scale: (1u64 << depth) as f64 / header.root_size,
            cell_size,
            saturated: FxHashMap::default(),
            compute_index: true,
            colors: dag.colors(),
        };
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

    /// Whether hits carry the attribute index (default true). Turning it off
    /// saves the sibling-count walk when only geometry is wanted.
    pub fn with_index(mut self, compute_index: bool) -> Self {
        self.compute_index = compute_index;
        self
    }

    /// Depth D of the DAG.
    pub fn depth(&self) -> u8 {
        self.depth
    }

    /// The voxel colour section (RGBA8 per voxel in dense index order), if any.
    pub fn colors(&self) -> Option<&'a [u8]> {
        self.colors
    }

    /// The RGBA colour of the voxel with dense index `index`, if the file has colours.
    pub fn color(&self, index: u64) -> Option<[u8; 4]> {
        let at = usize::try_from(index).ok()?.checked_mul(4)?;
        match self.colors?.get(at..at + 4)? {
            &[r, g, b, a] => Some([r, g, b, a]),
            _ => None,
        }
    }

    /// Grid-space (voxel units) position of a world-space point.
    pub fn world_to_grid(&self, p: [f64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|i| (p[i] - self.root_min[i]) * self.grid_scale)
    }

    /// Traces one ray: the occupied cell with the smallest entry parameter.
    pub fn trace(&self, ray: &Ray) -> Result<Hit, TraceError> {
        let mut stack = [Frame::default(); LEVEL_SLOTS];
        let (found, level, t, face) = match self.setup(ray)? {
            Setup::Miss => return Ok(Hit::MISS),
            Setup::Point {
                origin,
                tmin,
                level,
            } => match self.point_cell(origin, level, &mut stack)? {
                None => return Ok(Hit::MISS),
                Some(found) => (found, level, tmin, 0),
            },
            Setup::Trace(prepared) => match self
                .traverse(&prepared, &mut stack)
                .map_err(|f| self.fault_error(f))?
            {
                None => return Ok(Hit::MISS),
                Some((found, t, face)) => (found, prepared.level, t, face),
            },
        };
        let index = self
            .index(&found, level, &stack)
            .map_err(|f| self.fault_error(f))?;
        Ok(Hit {
            hit: true,
            t,
            voxel: found.cell,
            level,
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
        self.lookup(cell, level, stack)
            .map_err(|f| self.fault_error(f))
    }

    fn index_kind(&self) -> bool {
        self.compute_index && self.attribute_kind == AttributeKind::VoxelCount
    }

    fn fault_error(&self, fault: Fault) -> TraceError {
        let level = self.levels[usize::from(fault.level).min(MAX_STORED_LEVELS - 1)];
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
    fn setup(&self, ray: &Ray) -> Result<Setup, TraceError> {
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
        // Also false for a NaN bound.
        if !(ray.tmin <= ray.tmax) || self.empty {
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
        Ok(Setup::Trace(Prepared {
            origin: Vec3A::from_array(o32),
            inv_dir: Vec3A::from_array(inv32),
            tmin: (tmin * scale) as f32,
            tmax: (tmax * scale) as f32,
            neg,
            moving: BVec3A::new(moving[0], moving[1], moving[2]),
            level,
            inv_scale,
            base,
        }))
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
        let leaf_level = self.leaf_level;
        let neg = p.neg;
        let (origin, inv_dir) = (p.origin, p.inv_dir);
        // The root cube: is it met at all?
        let root_size = self.cell_size[0];
        let root_lo = (Vec3A::ZERO - origin) * inv_dir;
        let root_hi = (Vec3A::splat(root_size) - origin) * inv_dir;
        if max(root_lo.max_element(), p.tmin) > min(root_hi.min_element(), p.tmax) {
            return None;
        }
        if p.level == 0 {
            return Some(self.found(p, Vec3A::ZERO, 0, 0));
        }
        if leaf_level == 0 {
            return self
                .brick(p, 0, Vec3A::ZERO, fault)
                .map(|(cell, level)| self.found(p, cell, level, 0));
        }
        // The level where the descent stops: the ray's level, or the leaf
        // level whose bricks are answered from their masks.
        let stop = p.level.min(leaf_level);
        let mut level = 0u8;
        // Mirrored grid position of the current node's lower corner (exact
        // integers in f32) and its edge length.
        let mut pos = Vec3A::ZERO;
        let mut size = root_size;
        let mut word = 0u32;
        'descend: loop {
            let l = usize::from(level) & LEVEL_INDEX;
            let header = self.levels[l].header_or_fault(level, word, fault);
            let t_lo = (pos - origin) * inv_dir;
            let t_mid = (pos + Vec3A::splat(size * 0.5) - origin) * inv_dir;
            let t_hi = (pos + Vec3A::splat(size) - origin) * inv_dir;
            let t_enter = max(t_lo.max_element(), p.tmin);
            let t_exit = min(t_hi.min_element(), p.tmax);
            let mask = header as u8;
            let remaining = if t_enter <= t_exit {
                chain(neg, t_enter, t_exit, t_mid) & mask
            } else {
                0
            };
            stack[l] = Frame {
                word,
                mask,
                remaining,
                last: 0,
                _pad: 0,
            };
            loop {
                let frame = &mut stack[usize::from(level) & LEVEL_INDEX];
                if frame.remaining == 0 {
                    if level == 0 {
                        return None;
                    }
                    // Back to the parent: undo the step into this node.
                    level -= 1;
                    let parent = stack[usize::from(level) & LEVEL_INDEX];
                    pos -= CHILD_STEPS[(usize::from(parent.last) ^ neg) & 7] * size;
                    size *= 2.0;
                    continue;
                }
                let child = FIRST[neg][usize::from(frame.remaining)];
                frame.remaining &= !(1 << child);
                frame.last = child;
                let rank = u32::from(POPCOUNT8[usize::from(frame.mask & ((1u8 << child) - 1))]);
                let pointer = self.levels[usize::from(level) & LEVEL_INDEX]
                    .pointer_or_fault(level, frame.word, rank, fault);
                let half = size * 0.5;
                let child_pos = pos + CHILD_STEPS[(usize::from(child) ^ neg) & 7] * half;
                let child_level = level + 1;
                if child_level == stop {
                    if stop == p.level {
                        return Some(self.found(p, child_pos, child_level, pointer));
                    }
                    if let Some((cell, cell_level)) = self.brick(p, pointer, child_pos, fault) {
                        return Some(self.found(p, cell, cell_level, pointer));
                    }
                    continue;
                }
                level = child_level;
                pos = child_pos;
                size = half;
                word = pointer;
                continue 'descend;
            }
        }
    }

    /// The answer for the cell of `level` whose lower corner is at mirrored
    /// grid position `pos`: the cell in the file's frame, its entry parameter
    /// and its entry face.
    #[inline]
    fn found(&self, p: &Prepared, pos: Vec3A, level: u8, leaf: u32) -> (Found, f32, u8) {
        // Entry: the latest slab start of the moving axes, or tmin (face 0).
        let t_lo = (pos - p.origin) * p.inv_dir;
        let t_lo = Vec3A::select(p.moving, t_lo, Vec3A::NEG_INFINITY);
        let [x, y, z] = t_lo.to_array();
        let (near, axis) = if x >= y && x >= z {
            (x, 0)
        } else if y >= z {
            (y, 1)
        } else {
            (z, 2)
        };
        let (t, face) = if near < p.tmin {
            (p.tmin, 0)
        } else {
            (near, 1 + 2 * axis + (p.neg >> axis & 1) as u8)
        };
        let t = (f64::from(t) * p.inv_scale + p.base) as f32;
        // Cell coordinates: the position over the cell size (exact).
        let m = (pos * (1.0 / self.cell_size[usize::from(level)]))
            .to_array()
            .map(|v| v as u32);
        let last = (1u32 << level) - 1;
        let cell = [0, 1, 2].map(|i| {
            if p.neg >> i & 1 == 1 {
                last - m[i]
            } else {
                m[i]
            }
        });
        (Found { cell, leaf }, t, face)
    }

    /// The last two levels: the first set sub-brick (level D-1) or voxel
    /// (level D) of the 4³ brick `leaf` whose lower corner is at mirrored grid
    /// position `pos`, answered from the leaf mask alone. Returns the cell's
    /// mirrored position and level.
    #[inline(always)]
    fn brick(
        &self,
        p: &Prepared,
        leaf: u32,
        pos: Vec3A,
        fault: &mut Option<Fault>,
    ) -> Option<(Vec3A, u8)> {
        let bits = self.levels[usize::from(self.leaf_level) & LEVEL_INDEX].leaf_or_fault(
            self.leaf_level,
            leaf,
            fault,
        );
        let neg = p.neg;
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
            let sub_pos = pos + CHILD_STEPS[m] * 2.0;
            if p.level < self.depth {
                return Some((sub_pos, self.depth - 1));
            }
            let upper = BVec3A::new(m & 1 != 0, m & 2 != 0, m & 4 != 0);
            let s_lo = Vec3A::select(upper, t2, t0);
            let s_mid = Vec3A::select(upper, t3, t1);
            let s_hi = Vec3A::select(upper, t4, t2);
            let s_enter = max(s_lo.max_element(), p.tmin);
            let s_exit = min(s_hi.min_element(), p.tmax);
            if s_enter > s_exit {
                continue;
            }
            let voxels = chain(neg, s_enter, s_exit, s_mid) & (bits >> (8 * sub)) as u8;
            if voxels != 0 {
                let v = (usize::from(FIRST[neg][usize::from(voxels)]) ^ neg) & 7;
                return Some((sub_pos + CHILD_STEPS[v], self.depth));
            }
        }
        None
    }

    /// Follows the path of `cell` (at `level`) from the root, filling `stack`
    /// with the interior nodes on the way. `None` when the cell is empty.
    fn lookup(&self, cell: [u32; 3], level: u8, stack: &mut Stack) -> Result<Option<Found>, Fault> {
        let mut word = 0u32;
        for l in 0..level.min(self.leaf_level) {
            let header = self.levels[usize::from(l)].header(l, word)?;
            let mask = header as u8;
            let child = child_at(cell, level - 1 - l);
            stack[usize::from(l)] = Frame {
                word,
                mask,
                remaining: 0,
                last: child as u8,
                _pad: 0,
            };
            if mask >> child & 1 == 0 {
                return Ok(None);
            }
            let rank = u32::from(POPCOUNT8[usize::from(mask & ((1u8 << child) - 1))]);
            word = self.levels[usize::from(l)].pointer(l, word, rank)?;
        }
        if level <= self.leaf_level {
            return Ok(Some(Found { cell, leaf: word }));
        }
        let bits = self.levels[usize::from(self.leaf_level)].leaf(self.leaf_level, word)?;
        let occupied = if level == self.depth {
            bits >> leaf_bit(cell[0] & 3, cell[1] & 3, cell[2] & 3) & 1 != 0
        } else {
            (bits >> (8 * child_at(cell, 0))) & 0xff != 0
        };
        Ok(occupied.then_some(Found { cell, leaf: word }))
    }

    /// The dense index of the first voxel of the found cell, from the path in
    /// `stack`: the counts of the earlier siblings on every level plus the set
    /// bits before it in its leaf.
    fn index(&self, found: &Found, level: u8, stack: &Stack) -> Result<Option<u64>, Fault> {
        if !self.index_kind() {
            return Ok(None);
        }
        let mut index = 0u64;
        for l in 0..level.min(self.leaf_level) {
            let frame = stack[usize::from(l)];
            let child = child_at(found.cell, level - 1 - l);
            let mut before = frame.mask & ((1u8 << child) - 1);
            let mut rank = 0;
            while before != 0 {
                before &= before - 1;
                let pointer = self.levels[usize::from(l)].pointer(l, frame.word, rank)?;
                index = index.saturating_add(self.count(l + 1, pointer)?);
                rank += 1;
            }
        }
        if level > self.leaf_level {
            let bits =
                self.levels[usize::from(self.leaf_level)].leaf(self.leaf_level, found.leaf)?;
            let c = found.cell;
            let below = if level == self.depth {
                leaf_bit(c[0] & 3, c[1] & 3, c[2] & 3)
            } else {
                8 * child_at(c, 0)
            };
            index += u64::from((bits & ((1u64 << below) - 1)).count_ones());
        }
        Ok(Some(index))
    }

    /// Voxel count of a node or leaf: stored count, or the precomputed sum
    /// for saturated nodes.
    fn count(&self, level: u8, pointer: u32) -> Result<u64, Fault> {
        let section = &self.levels[usize::from(level)];
        if level == self.leaf_level {
            return Ok(u64::from(section.leaf(level, pointer)?.count_ones()));
        }
        let attribute = section.header(level, pointer)? >> 8;
        if attribute != COUNT_SATURATED {
            return Ok(u64::from(attribute));
        }
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
        if header >> 8 != COUNT_SATURATED {
            return Ok(u64::from(header >> 8));
        }
        if let Some(&n) = memo.get(&(level, word)) {
            return Ok(n);
        }
        let mut total = 0u64;
        for rank in 0..(header as u8).count_ones() {
            let pointer = section.pointer(level, word, rank)?;
            total = total.saturating_add(self.count_saturated(level + 1, pointer, memo)?);
        }
        memo.insert((level, word), total);
        Ok(total)
    }
}

/// Child index (file frame) of the path of `cell` taken at coordinate bit `shift`.
#[inline]
fn child_at(cell: [u32; 3], shift: u8) -> u32 {
    let s = u32::from(shift);
    (cell[0] >> s & 1) | (cell[1] >> s & 1) << 1 | (cell[2] >> s & 1) << 2
}

/// The chain of children (file frame mask) a ray passes through inside a node
/// entered at `t_enter` and left at `t_exit`, whose mid-planes it crosses at `t_mid`.
#[inline(always)]
fn chain(neg: usize, t_enter: f32, t_exit: f32, t_mid: Vec3A) -> u8 {
    let enter = Vec3A::splat(t_enter);
    let exit = Vec3A::splat(t_exit);
    let first = t_mid.cmple(enter).bitmask();
    // A crossing exactly at the exit still touches the next (closed) child.
    let crossing = (t_mid.cmpgt(enter) & t_mid.cmple(exit)).bitmask();
    let order = t_mid.xxy().cmplt(t_mid.yzz()).bitmask();
    CHAIN[neg][((first | crossing << 3 | order << 6) & 511) as usize]
}

/// Bit `c` set when byte `c` (sub-brick `c`) of a leaf mask is non-zero.
#[inline(always)]
fn sub_brick_mask(bits: u64) -> u8 {
    let mut x = bits;
    x |= x >> 4;
    x |= x >> 2;
    x |= x >> 1;
    x &= 0x0101_0101_0101_0101;
    (x.wrapping_mul(0x0102_0408_1020_4080) >> 56) as u8
}

/// `a.max(b)` without NaN handling (the traversal has no NaN): one `maxss`.
#[inline(always)]
fn max(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

/// `a.min(b)` without NaN handling: one `minss`.
#[inline(always)]
fn min(a: f32, b: f32) -> f32 {
    if a < b { a } else { b }
}

/// Unit steps to the eight children, by child index (x, y, z = bits 0, 1, 2).
const CHILD_STEPS: [Vec3A; 8] = {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sub_brick_mask_gathers_non_zero_bytes() {
        assert_eq!(sub_brick_mask(0), 0);
        assert_eq!(sub_brick_mask(1), 1);
        assert_eq!(sub_brick_mask(0x80), 1);
        assert_eq!(sub_brick_mask(0x8000_0000_0000_0000), 0x80);
        assert_eq!(sub_brick_mask(0x0000_0100_0000_ff00), 0b0010_0010);
        assert_eq!(sub_brick_mask(u64::MAX), 0xff);
    }
}
