//! Packets of coherent rays: a beam pass that finds, for a group of rays
//! sharing an origin, the occupied cells of a coarse level that any of them
//! can meet, so that each ray is traced only through those cells.
//!
//! # Why
//!
//! Primary (camera) rays share their origin and differ little in direction.
//! Traced one by one, each of them descends from the root through the same
//! coarse nodes, and most of them, those that miss the object, explore the
//! same empty space around it. The beam pass does that coarse work once per
//! packet of up to [`PACKET_RAYS`] rays (the beam optimisation of Laine and
//! Karras's efficient sparse voxel octrees, done with interval arithmetic in
//! the manner of Wald et al.'s ray packets): a packet whose beam meets no
//! occupied cell is answered without any per-ray traversal, and every other ray
//! starts below the beam level, in the cells its beam met.
//!
//! # How
//!
//! 1. A packet is a run of consecutive rays with the same origin, `tmin`,
//!    `tmax` and level of detail, whose direction components all have the
//!    same signs and none is (treated as) zero, and whose directions spread
//!    so little that the beam stays at most [`BEAM_WIDTH_CELLS`] cells of
//!    32³ voxels wide across the cube (see [`Tracer::packet_shape`]). Its
//!    rays form groups of [`GROUP_RAYS`] consecutive rays (a 4×4 block of
//!    pixels in the Z order of [`crate::camera::CameraFrame::rays_in_tiles`]).
//! 2. The *beam* of the packet is the set of lines from the common origin
//!    whose inverse direction lies, per axis, between the smallest and the
//!    largest of the packet's. A cell can be met by a ray of the packet only
//!    if the interval slab test of the beam passes for it (interval
//!    arithmetic bounds every ray's slab parameters), so the beam walk — a
//!    depth-first walk of the DAG in the front-to-back child order of the
//!    packet's direction octant, down to the *beam level* [`Tracer::beam_level`]
//!    — lists every occupied cell of that level that any ray of the packet
//!    can meet, in an order that is front to back for every one of them.
//!    The test runs in `f64` on cells enlarged by far more than the `f32`
//!    rounding of the per-ray traversal, so it never drops a cell that a ray's
//!    own (rounded) test would enter. The cells are listed lazily, a few at a
//!    time, so that the beam walk stops as soon as every ray has hit.
//! 3. A listed cell is first tested against the beam of each group (one
//!    interval test for 16 rays); the rays of the groups that may meet it then
//!    walk its subtree *together*: one depth-first walk in the octant's
//!    child order, in which every node is read once and each ray that reached
//!    it computes its own chain of children (the children it passes through)
//!    from the very same plane parameters as [`Tracer::trace`], four rays at a
//!    time in SIMD (eight with AVX2), the chains of all eight children coming
//!    out, without branches, as one bit mask of rays per child
//!    ([`ChainTests`]). Each ray thus meets the nodes of its own traversal, in
//!    its own front-to-back order, and the first voxel it finds in a brick
//!    (read from the leaf mask, as by [`Tracer::trace`]) is its answer; a ray
//!    that meets none in any listed cell misses. The children a node's rays
//!    go on to are prefetched at the node's visit. The nodes just above the
//!    bricks are met by few rays each (2.6 on average in a d12 camera frame),
//!    so there each ray goes on alone ([`Tracer::visit_bottom`]): its chain
//!    of children, then its bricks in its own order, each brick tested with
//!    its outer plane parameters taken from the node's (the same numbers as
//!    [`Tracer::brick`] computes).
//!
//! The answers are those of [`Tracer::trace`] except where a ray passes
//! exactly through an edge or corner shared by cells of the beam level: there
//! the per-ray traversal visits one of the tied cells and the packet all of
//! them, and either answer is a correct one (spec/VDAG.md §20.4, ties).
//! Any fault (a pointer out of range) makes the packet fall back to ray-by-ray
//! tracing, so errors are reported exactly as [`Tracer::trace`] reports them.

use glam::{Vec3A, Vec4};

#[cfg(target_arch = "x86_64")]
mod avx2;

use crate::node::child_mask;
use crate::tables::FIRST;
use crate::walk::{
    CHILD_STEPS, Frame, LEVEL_SLOTS, Prepared, Stack, TINY_DIRECTION, Tracer, Walk, max, min,
    prefetch, prefetch_range,
};
use dagfmt::batch::{Hit, Ray};

/// Most rays in one packet.
pub(crate) const PACKET_RAYS: usize = 64;

/// Rays per group of a packet: each group has its own beam too, tested
/// against the cells of the packet's beam before its rays are. (Groups of 8
/// cost 3 % more instructions on dragon d12 tiles, of 4 7 % more: the `f64`
/// group tests outweigh the SIMD ray tests they save; 32 gains under 1 %.)
const GROUP_RAYS: usize = 16;

/// Groups in a packet.
const GROUPS: usize = PACKET_RAYS / GROUP_RAYS;
// `avx2::groups_meet` tests the groups' beams four to a vector.
const _: () = assert!(GROUPS == 4);

/// The bits of the first group in a mask of rays.
const GROUP_MASK: u64 = (1 << GROUP_RAYS) - 1;

/// Fewest rays worth a beam pass.
const MIN_PACKET_RAYS: usize = 8;

/// Widest beam, in cells of the beam level (at the far side of the cube),
/// for which a packet beats tracing its rays one by one.
const BEAM_WIDTH_CELLS: f64 = 16.0;

/// Cells of the beam level listed at a time before the rays are traced
/// through them. Most rays of a packet that meets cells hit in its first
/// few: the beam walk past them is wasted. (Instructions per d12 tiled
/// frame: 555 M with 2 or 3, 557 M with 4, 564 M with 8, 611 M with 16; 4
/// keeps more cells' node reads under way, and was no slower than 8 in
/// alternating runs.)
const CELLS_PER_ROUND: usize = 4;

/// Enlargement of the cells in the beam test, relative to `max(2^D, |origin|)`
/// in grid units: 2^-18, 64 times the largest rounding error of the `f32`
/// per-ray slab parameters (spec/VDAG.md §20.8 allows 8 such units).
const BEAM_MARGIN: f64 = 1.0 / (1u64 << 18) as f64;

/// The direction octant of `d`: bit `i` set when component `i` is negative
/// (the traversal's mirrored axes, `Prepared::neg`).
#[inline]
fn octant(d: [f32; 3]) -> usize {
    usize::from(d[0] < 0.0) | usize::from(d[1] < 0.0) << 1 | usize::from(d[2] < 0.0) << 2
}

/// One occupied cell of the beam level that the beam meets.
#[derive(Clone, Copy, Debug, Default)]
struct BeamCell {
    /// Word of its node in the level section.
    word: u32,
    /// Mirrored grid position of its lower corner (exact in `f32`).
    pos: Vec3A,
    /// Path of nodes above it: `path[start..start + beam level]` of the
    /// packet's path store.
    path: usize,
    /// Its node's accumulated reflection (spec §23.4; 0 in 1.0).
    reflection: u8,
}

/// The beam: the packet's common origin and the per-axis range of its
/// inverse directions, in the mirrored grid frame, in `f64`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Beam {
    pub(crate) origin: [f64; 3],
    pub(crate) inv_lo: [f64; 3],
    pub(crate) inv_hi: [f64; 3],
    pub(crate) tmin: f64,
    pub(crate) tmax: f64,
    pub(crate) margin: f64,
}

/// The inverse directions of a packet's group beams by axis and group
/// (`inv_lo[a][g]` for group `g`), for the vector test of all groups at once
/// (`avx2::groups_meet`); the rest of their beams is the packet's.
#[derive(Clone, Copy, Debug)]
pub(crate) struct GroupBeams {
    pub(crate) inv_lo: [[f64; GROUPS]; 3],
    pub(crate) inv_hi: [[f64; GROUPS]; 3],
}

impl GroupBeams {
    /// The inverse directions of `groups`, by axis.
    #[inline(always)]
    fn of(groups: &[Beam; GROUPS]) -> GroupBeams {
        let by_axis = |f: fn(&Beam) -> [f64; 3]| -> [[f64; GROUPS]; 3] {
            std::array::from_fn(|a| std::array::from_fn(|g| f(&groups[g])[a]))
        };
        GroupBeams {
            inv_lo: by_axis(|b| b.inv_lo),
            inv_hi: by_axis(|b| b.inv_hi),
        }
    }
}

impl Beam {
    /// Whether some line of the beam may meet the cube of edge `size` at
    /// `pos` (interval slab test on the enlarged cube).
    #[inline]
    fn meets(&self, pos: [f64; 3], size: f64) -> bool {
        self.meets_box(pos, pos.map(|p| p + size))
    }

    /// Whether some line of the beam may meet the box from `lower` to
    /// `upper` (the same test, on the enlarged box).
    #[inline]
    fn meets_box(&self, lower: [f64; 3], upper: [f64; 3]) -> bool {
        let mut enter = self.tmin;
        let mut exit = self.tmax;
        for a in 0..3 {
            enter = enter.max(self.near(a, lower[a] - self.margin - self.origin[a]));
            exit = exit.min(self.far(a, upper[a] + self.margin - self.origin[a]));
        }
        enter <= exit
    }

    /// The smallest parameter over the beam's lines at which axis `a` reaches
    /// the plane at offset `lo` from the origin (a box's entry plane).
    #[inline(always)]
    fn near(&self, a: usize, lo: f64) -> f64 {
        lo * if lo >= 0.0 {
            self.inv_lo[a]
        } else {
            self.inv_hi[a]
        }
    }

    /// The largest parameter over the beam's lines at which axis `a` reaches
    /// the plane at offset `hi` from the origin (a box's exit plane).
    #[inline(always)]
    fn far(&self, a: usize, hi: f64) -> f64 {
        hi * if hi >= 0.0 {
            self.inv_hi[a]
        } else {
            self.inv_lo[a]
        }
    }

    /// The children in `mask` (file indices, for direction octant `neg`) of
    /// the node of edge `size` at mirrored position `pos` that some line of the beam may
    /// meet: [`Beam::meets`] for each of them, with the products of the
    /// planes they share computed once (the very same expressions, so the
    /// same answers).
    #[inline(always)]
    fn children_met(&self, mask: u8, pos: [f64; 3], size: f64, neg: usize) -> u8 {
        #[cfg(target_arch = "x86_64")]
        if crate::cpu::available() {
            // SAFETY: `cpu::available` found AVX2.
            let met = unsafe { avx2::beam_children_met(self, pos, size * 0.5) };
            return unmirror(met, neg) & mask;
        }
        self.children_met_scalar(mask, pos, size, neg)
    }

    /// [`Beam::children_met`] without vectors (processors without AVX2).
    #[inline(always)]
    fn children_met_scalar(&self, mask: u8, pos: [f64; 3], size: f64, neg: usize) -> u8 {
        let half = size * 0.5;
        let mut near = [[0f64; 2]; 3];
        let mut far = [[0f64; 2]; 3];
        for a in 0..3 {
            let mid = pos[a] + half;
            let lo = [
                pos[a] - self.margin - self.origin[a],
                mid - self.margin - self.origin[a],
            ];
            let hi = [
                mid + self.margin - self.origin[a],
                mid + half + self.margin - self.origin[a],
            ];
            for k in 0..2 {
                near[a][k] = self.near(a, lo[k]);
                far[a][k] = self.far(a, hi[k]);
            }
        }
        // No NaN here (finite beams, finite planes): plain comparisons.
        let max = |a: f64, b: f64| if a > b { a } else { b };
        let min = |a: f64, b: f64| if a < b { a } else { b };
        // All eight children at once, indexed by mirrored child `m` (bit
        // `a` set for the upper half on axis `a`), four to a row so that the
        // comparisons become vector operations: row `z` holds `m = 4z..4z+4`.
        let mut met_mirrored = 0u32;
        for z in 0..2 {
            let mut met_row = 0u32;
            for k in 0..4 {
                let enter = max(
                    max(self.tmin, near[0][k & 1]),
                    max(near[1][k >> 1], near[2][z]),
                );
                let exit = min(
                    min(self.tmax, far[0][k & 1]),
                    min(far[1][k >> 1], far[2][z]),
                );
                met_row |= u32::from(enter <= exit) << k;
            }
            met_mirrored |= met_row << (4 * z);
        }
        unmirror(met_mirrored, neg) & mask
    }
}

/// Bits by child index from bits by mirrored child index (child `c` is
/// mirrored child `c ^ neg`): the bits of each pair, pair of pairs or nibble
/// swapped along the mirrored axes.
#[inline(always)]
fn unmirror(bits: u32, neg: usize) -> u8 {
    let mut b = bits;
    if neg & 1 != 0 {
        b = (b & 0x55) << 1 | (b >> 1) & 0x55;
    }
    if neg & 2 != 0 {
        b = (b & 0x33) << 2 | (b >> 2) & 0x33;
    }
    if neg & 4 != 0 {
        b = (b & 0x0f) << 4 | (b >> 4) & 0x0f;
    }
    b as u8
}

/// One node on the beam walk's path.
#[derive(Clone, Copy, Debug, Default)]
struct BeamFrame {
    word: u32,
    mask: u8,
    /// Children that the beam meets, not yet listed or walked.
    remaining: u8,
    /// Mirrored grid position of the node's lower corner.
    pos: [f64; 3],
    /// The node's accumulated reflection (spec §23.4; 0 in 1.0).
    reflection: u8,
}

/// One node on a packet's walk of a beam cell's subtree.
#[derive(Clone, Copy, Debug, Default)]
struct SubtreeFrame {
    word: u32,
    mask: u8,
    /// Children that some ray of the packet passes through, not yet visited.
    remaining: u8,
    /// Mirrored grid position of the node's lower corner.
    pos: Vec3A,
    /// Per child (file index): the rays that pass through it.
    rays: [u64; 8],
    /// Per child with rays: its pointer.
    pointers: [u32; 8],
    /// The node's accumulated reflection R (spec §23.4; 0 in 1.0): the
    /// packet's rays trace it in octant `neg ^ R`.
    reflection: u8,
    /// Per child with rays: its accumulated reflection.
    reflections: [u8; 8],
}

impl PacketShape {
    /// No packet.
    pub(crate) const NONE: PacketShape = PacketShape {
        len: 0,
        ranges: [(Vec3A::INFINITY, Vec3A::ZERO); GROUPS],
        all: (Vec3A::INFINITY, Vec3A::ZERO),
        origin: [0.0; 3],
    };
}

/// A packet found by [`Tracer::packet_shape`]: its length, and per group of
/// [`GROUP_RAYS`] rays the range of `|d_a|` (empty, `lo > hi`, for groups
/// past the end).
#[derive(Clone, Copy, Debug)]
pub(crate) struct PacketShape {
    pub(crate) len: usize,
    ranges: [(Vec3A, Vec3A); GROUPS],
    /// The union of `ranges`.
    all: (Vec3A, Vec3A),
    /// The rays' common origin in grid units (not mirrored).
    origin: [f64; 3],
}

/// The rays of a packet in the traversal's frame, one array entry per ray
/// (structure of arrays, loaded four or eight rays to a vector), for the
/// visits of [`Tracer::visit_subtree_node`].
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
pub(crate) struct PacketLanes {
    /// `1 / direction` per axis.
    pub(crate) inv: [[f32; PACKET_RAYS]; 3],
    /// The rays' clipped `tmin` and `tmax`.
    pub(crate) tmin: [f32; PACKET_RAYS],
    pub(crate) tmax: [f32; PACKET_RAYS],
}

impl Default for PacketLanes {
    fn default() -> Self {
        PacketLanes {
            inv: [[0.0; PACKET_RAYS]; 3],
            tmin: [0.0; PACKET_RAYS],
            tmax: [0.0; PACKET_RAYS],
        }
    }
}

impl PacketLanes {
    /// Rays `4k..4k + 4` of `v` as a vector.
    #[inline(always)]
    fn four(v: &[f32; PACKET_RAYS], k: usize) -> Vec4 {
        let k = k & (PACKET_RAYS / 4 - 1);
        Vec4::from_slice(&v[4 * k..4 * k + 4])
    }
}

/// The comparisons that make a ray's chain of children in a node (see
/// `walk::chain`), one bit per ray of a packet.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct ChainTests {
    /// The ray's segment meets the node: `t_enter <= t_exit`.
    pub(crate) inside: u64,
    /// Per (mirrored) axis: the mid-plane is at or before the entry
    /// (`t_mid <= t_enter`), so the ray starts in the upper half.
    pub(crate) first: [u64; 3],
    /// Per axis: `t_mid <= t_exit`.
    pub(crate) before_exit: [u64; 3],
    /// `t_mid.x < t_mid.y`, `t_mid.x < t_mid.z`, `t_mid.y < t_mid.z`.
    pub(crate) order: [u64; 3],
}

impl ChainTests {
    /// Whether `a`'s mid-plane crossing comes before `b`'s (`a != b`), in the
    /// order of `tables::CHAIN`: by parameter, ties to the higher axis.
    #[inline(always)]
    fn crosses_before(&self, a: usize, b: usize) -> u64 {
        match (a, b) {
            (0, 1) => self.order[0],
            (1, 0) => !self.order[0],
            (0, 2) => self.order[1],
            (2, 0) => !self.order[1],
            (1, 2) => self.order[2],
            _ => !self.order[2],
        }
    }

    /// Entry `m` of [`ChainTests::through_all`].
    #[cfg(test)]
    fn through(&self, m: usize) -> u64 {
        self.through_all()[m & 7]
    }

    /// Per child (mirrored index `m`), the rays whose chain holds it: `m` is
    /// the entry child plus the first crossings in order. Per axis `a` in
    /// `m`, the ray reaches the upper half (`t_mid <= t_exit`); per axis not
    /// in `m`, it enters in the lower half; and every crossing into `m` comes
    /// before every crossing out of it (an axis not in `m` crossed in the
    /// segment). All eight at once, without branches: the pair terms (axis
    /// `a` in the child crossed before axis `b` not in it) do not depend on
    /// the child, so each is computed once.
    #[inline(always)]
    fn through_all(&self) -> [u64; 8] {
        let up = self.before_exit;
        let low = self.first.map(|f| !f);
        let pair =
            |a: usize, b: usize| self.first[a] | !self.before_exit[b] | self.crosses_before(a, b);
        let (p01, p02, p10) = (pair(0, 1), pair(0, 2), pair(1, 0));
        let (p12, p20, p21) = (pair(1, 2), pair(2, 0), pair(2, 1));
        let i = self.inside;
        [
            i & low[0] & low[1] & low[2],
            i & up[0] & low[1] & low[2] & p01 & p02,
            i & low[0] & up[1] & low[2] & p10 & p12,
            i & up[0] & up[1] & low[2] & p02 & p12,
            i & low[0] & low[1] & up[2] & p20 & p21,
            i & up[0] & low[1] & up[2] & p01 & p21,
            i & low[0] & up[1] & up[2] & p10 & p20,
            i & up[0] & up[1] & up[2],
        ]
    }
}

/// The chain tests of the rays `rays` of a packet in a node whose lower,
/// middle and upper planes are at offsets `planes` from the packet's origin
/// (the same operations as `resume`, so the same roundings), four rays at a
/// time. Rays of the groups of four touched that are not in `rays` get
/// tests too, to be ignored (`inside` only counts `rays`' own).
#[inline(always)]
pub(crate) fn chain_tests(planes: [[f32; 3]; 3], lanes: &PacketLanes, rays: u64) -> ChainTests {
    let [d_lo, d_mid, d_hi] = planes.map(|p| p.map(Vec4::splat));
    let mut tests = ChainTests::default();
    let mut groups = rays;
    while groups != 0 {
        let g = groups.trailing_zeros() as usize / 4;
        groups &= !(0xf << (4 * g));
        let k = g & (PACKET_RAYS / 4 - 1);
        let inv = lanes.inv.each_ref().map(|v| PacketLanes::four(v, k));
        let t_lo: [Vec4; 3] = std::array::from_fn(|a| d_lo[a] * inv[a]);
        let t_mid: [Vec4; 3] = std::array::from_fn(|a| d_mid[a] * inv[a]);
        let t_hi: [Vec4; 3] = std::array::from_fn(|a| d_hi[a] * inv[a]);
        let enter = t_lo[0]
            .max(t_lo[1])
            .max(t_lo[2])
            .max(PacketLanes::four(&lanes.tmin, k));
        let exit = t_hi[0]
            .min(t_hi[1])
            .min(t_hi[2])
            .min(PacketLanes::four(&lanes.tmax, k));
        let shift = 4 * g;
        let bits = |m: glam::BVec4A| u64::from(m.bitmask()) << shift;
        tests.inside |= bits(enter.cmple(exit));
        for (a, t) in t_mid.iter().enumerate() {
            tests.first[a] |= bits(t.cmple(enter));
            tests.before_exit[a] |= bits(t.cmple(exit));
        }
        tests.order[0] |= bits(t_mid[0].cmplt(t_mid[1]));
        tests.order[1] |= bits(t_mid[0].cmplt(t_mid[2]));
        tests.order[2] |= bits(t_mid[1].cmplt(t_mid[2]));
    }
    tests.inside &= rays;
    tests
}

/// Levels of a beam cell's subtree above its bricks (the beam level is 5
/// levels above the voxels, the bricks 2), rounded up to a power of two.
const SUBTREE_SLOTS: usize = 4;

/// Rays that may join a packet, found by [`scan_ray`] (one ray) or
/// `avx2::scan_for_packet` (eight): how many of the scanned rays, from the
/// first, may join, and over those the ranges of `|d_a|` (empty ranges when
/// none may).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct ScannedRays {
    pub(crate) len: usize,
    pub(crate) lo: Vec3A,
    pub(crate) hi: Vec3A,
}

impl ScannedRays {
    /// No ray may join.
    pub(crate) const NONE: ScannedRays = ScannedRays {
        len: 0,
        lo: Vec3A::INFINITY,
        hi: Vec3A::ZERO,
    };
}

/// Whether `r` may join a packet that `first` starts: the same origin and
/// bounds bit for bit, the same level, the same signs of the direction (the
/// same octant), and no direction component treated as zero (or nearly), NaN
/// or infinite.
#[inline(always)]
pub(crate) fn scan_ray(r: &Ray, first: &Ray) -> ScannedRays {
    let bits = |r: &Ray| [r.origin[0], r.origin[1], r.origin[2], r.tmin, r.tmax].map(f32::to_bits);
    let (b, f) = (bits(r), bits(first));
    let differ = (b[0] ^ f[0])
        | (b[1] ^ f[1])
        | (b[2] ^ f[2])
        | (b[3] ^ f[3])
        | (b[4] ^ f[4])
        | ((r.dir[0].to_bits() ^ first.dir[0].to_bits())
            | (r.dir[1].to_bits() ^ first.dir[1].to_bits())
            | (r.dir[2].to_bits() ^ first.dir[2].to_bits()))
            >> 31;
    let d = Vec3A::from_array(r.dir);
    let m = d.abs();
    let d2 = d.length_squared();
    // Written so that a NaN fails (a NaN or infinite component makes `d2`
    // NaN or infinite).
    let regular = m.min_element() > m.max_element() * 1e-6 && d2 < f32::INFINITY;
    if differ != 0 || r.level != first.level || !regular {
        return ScannedRays::NONE;
    }
    ScannedRays {
        len: 1,
        lo: m,
        hi: m,
    }
}

/// Whether a packet may start at `rays[0]`: the test that most runs of rays
/// that are not packets fail, cheap enough to run before
/// [`Tracer::packet_shape`] at every ray of a batch — the ray
/// [`MIN_PACKET_RAYS`] on starts like the first (same origin, bounds and
/// level).
#[inline(always)]
pub(crate) fn may_start_packet(rays: &[Ray]) -> bool {
    let (Some(first), Some(last)) = (rays.first(), rays.get(MIN_PACKET_RAYS - 1)) else {
        return false;
    };
    let same = |x: f32, y: f32| x.to_bits() == y.to_bits();
    same(last.origin[0], first.origin[0])
        && same(last.origin[1], first.origin[1])
        && same(last.origin[2], first.origin[2])
        && same(last.tmin, first.tmin)
        && same(last.tmax, first.tmax)
        && last.level == first.level
}

/// The resumable depth-first beam walk.
struct BeamWalk {
    frames: [BeamFrame; LEVEL_SLOTS],
    /// Level of the node on top of the path; `None` when the walk is over.
    level: Option<u8>,
}

impl Tracer<'_> {
    /// The level whose occupied cells the beam pass lists: cells of 32³
    /// voxels, or none (0) for DAGs too shallow to gain from it.
    pub(crate) fn beam_level(&self) -> u8 {
        if self.depth >= 9 { self.depth - 5 } else { 0 }
    }

    /// The length of [`Tracer::packet_shape`].
    #[cfg(test)]
    pub(crate) fn packet_len(&self, rays: &[Ray]) -> usize {
        self.packet_shape(rays).len
    }

    /// The packet at the start of `rays`: the number of rays that form it (up
    /// to [`PACKET_RAYS`]) — the same origin, `tmin`, `tmax` and level (finer
    /// than the beam level), directions whose components are all far from
    /// zero and of the same signs, and spread little (checked a group at a
    /// time) — with the ranges of `|d_a|` of its groups, for the beams. The
    /// length is 0 when fewer than [`MIN_PACKET_RAYS`] rays qualify. One pass
    /// over the rays: it runs at every packet of a batch.
    #[inline(always)]
    pub(crate) fn packet_shape(&self, rays: &[Ray]) -> PacketShape {
        let none = PacketShape::NONE;
        if self.beam_level() == 0 {
            return none;
        }
        if !may_start_packet(rays) {
            return none;
        }
        let first = &rays[0];
        // Rays of a coarser level of detail than the beam's cells, and rays
        // of an impossible level (an error, reported ray by ray), go alone.
        if first
            .level
            .is_some_and(|l| l <= self.beam_level() || l > self.depth)
        {
            return none;
        }
        // The beam must stay narrow: where it is many cells of the beam level
        // wide, every ray would be tested against all of them. Its width at
        // the far side of the cube is at most the spread of the directions
        // (about the angle between them) times the distance to the cube's
        // farthest corner.
        let resolution = f64::from(self.cell_size[0]);
        let origin: [f64; 3] =
            [0, 1, 2].map(|a| (f64::from(first.origin[a]) - self.root_min[a]) * self.grid_scale);
        let far = origin
            .iter()
            .map(|&o| o.abs().max((resolution - o).abs()))
            .map(|d| d * d)
            .sum::<f64>()
            .sqrt();
        let cell = f64::from(self.cell_size[usize::from(self.depth - 5)]);
        let max_spread = (BEAM_WIDTH_CELLS * cell / far.max(cell)) as f32;
        // The spread of the directions is that of their components: per
        // axis, the range of |d_a| over the run, relative to the length of
        // the smallest |d_a| of each axis (no longer than any ray's |d|, and
        // found without a sum per ray).
        let spread_limit = max_spread * max_spread;
        let mut shape = PacketShape { origin, ..none };
        // The ranges of |d_a| of the groups before the current one, and of
        // the current one.
        let mut before = (Vec3A::INFINITY, Vec3A::ZERO);
        let mut group = before;
        // Written so that a NaN fails.
        let within = |lo: Vec3A, hi: Vec3A| {
            let spread = (hi - lo).max_element();
            spread * spread <= spread_limit * lo.length_squared()
        };
        let mut n = 0;
        let limit = rays.len().min(PACKET_RAYS);
        // The rays of the next packet are read soon, and a batch is mostly
        // too large for the caches: start their reads now (one packet ahead
        // hides the memory latency; the hardware prefetchers do not run that
        // far ahead of this stream).
        if let Some(next) = rays.get(PACKET_RAYS..(2 * PACKET_RAYS).min(rays.len())) {
            prefetch_range(next);
        }
        #[cfg(target_arch = "x86_64")]
        let vectors = crate::cpu::available();
        #[cfg(not(target_arch = "x86_64"))]
        let vectors = false;
        while n < limit {
            // Eight rays at a time in vectors where the processor can, else
            // one: the rays from `n` on that may join, a prefix.
            let step = if vectors && n % GROUP_RAYS == 0 && n + GROUP_RAYS <= limit {
                GROUP_RAYS
            } else if vectors && n + 8 <= limit {
                8
            } else {
                1
            };
            #[cfg(target_arch = "x86_64")]
            let scanned = if step == GROUP_RAYS {
                let group: &[Ray; GROUP_RAYS] =
                    rays[n..n + GROUP_RAYS].try_into().expect("a group of rays");
                // SAFETY: `cpu::available` found AVX2.
                unsafe { avx2::scan_group(group, first) }
            } else if step == 8 {
                let eight: &[Ray; 8] = rays[n..n + 8].try_into().expect("eight rays");
                // SAFETY: `cpu::available` found AVX2.
                unsafe { avx2::scan_for_packet(eight, first) }
            } else {
                scan_ray(&rays[n], first)
            };
            #[cfg(not(target_arch = "x86_64"))]
            let scanned = scan_ray(&rays[n], first);
            group = (group.0.min(scanned.lo), group.1.max(scanned.hi));
            n += scanned.len;
            // Steps of 16 and 8 start at multiples of theirs, so a group
            // ends at the end of a step that took all its rays.
            if scanned.len > 0 && n % GROUP_RAYS == 0 {
                // The spread, checked a group at a time: a group that makes
                // it too wide ends the packet before it.
                let (lo, hi) = (before.0.min(group.0), before.1.max(group.1));
                if !within(lo, hi) {
                    n -= GROUP_RAYS;
                    group = (Vec3A::INFINITY, Vec3A::ZERO);
                    break;
                }
                shape.ranges[n / GROUP_RAYS - 1] = group;
                before = (lo, hi);
                group = (Vec3A::INFINITY, Vec3A::ZERO);
            }
            if scanned.len < step {
                break;
            }
        }
        if n % GROUP_RAYS != 0 {
            if within(before.0.min(group.0), before.1.max(group.1)) {
                shape.ranges[n / GROUP_RAYS] = group;
            } else {
                n -= n % GROUP_RAYS;
            }
        }
        if n >= MIN_PACKET_RAYS {
            shape.len = n;
            for &(lo, hi) in &shape.ranges {
                if lo.x <= hi.x {
                    shape.all = (shape.all.0.min(lo), shape.all.1.max(hi));
                }
            }
            shape
        } else {
            none
        }
    }

    /// [`Tracer::trace_packet`] for tests: the packet's shape found here.
    #[cfg(test)]
    pub(crate) fn try_packet(&self, rays: &[Ray], hits: &mut [Hit]) -> bool {
        let shape = self.packet_shape(rays);
        shape.len == rays.len() && self.trace_packet(rays, hits, &shape)
    }

    /// Traces the packet `rays` (of `shape`, made by [`Tracer::packet_shape`])
    /// into `hits`. Returns `false`, having written nothing that matters,
    /// when the packet cannot be traced as one (a ray the set-up treats
    /// specially, or a fault on the way): the caller then traces its rays one
    /// by one.
    #[inline(never)]
    pub(crate) fn trace_packet(&self, rays: &[Ray], hits: &mut [Hit], shape: &PacketShape) -> bool {
        #[cfg(target_arch = "x86_64")]
        if crate::cpu::available() {
            // SAFETY: checked.
            return unsafe { self.trace_packet_avx2(rays, hits, shape) };
        }
        self.trace_packet_impl(rays, hits, shape)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,bmi1,bmi2,popcnt,lzcnt,fma")]
    unsafe fn trace_packet_avx2(
        &self,
        rays: &[Ray],
        hits: &mut [Hit],
        shape: &PacketShape,
    ) -> bool {
        self.trace_packet_impl(rays, hits, shape)
    }

    #[inline(always)]
    fn trace_packet_impl(&self, rays: &[Ray], hits: &mut [Hit], shape: &PacketShape) -> bool {
        let beam_level = self.beam_level();
        let n = rays.len().min(hits.len()).min(PACKET_RAYS);
        if n == 0 || self.empty {
            return false;
        }
        let rays = &rays[..n];
        // The beam first: most packets of a camera meet nothing, and then no
        // ray needs even its set-up.
        let Some(beam) = self.beams(&rays[0], shape, None) else {
            return false;
        };
        let neg = octant(rays[0].dir);
        let root_size = f64::from(self.cell_size[0]);
        // Every occupied cell lies in the box of the occupied cells of the
        // tracer's bounds level: most beams that miss the object miss it.
        let (lower, upper) = self.bounds[neg];
        let near_object = beam.meets_box(
            lower.to_array().map(f64::from),
            upper.to_array().map(f64::from),
        );
        if !near_object || !beam.meets([0.0; 3], root_size) {
            // No ray of the packet meets an occupied cell.
            hits[..n].fill(Hit::MISS);
            return true;
        }
        let mut walk = BeamWalk {
            frames: [BeamFrame::default(); LEVEL_SLOTS],
            level: None,
        };
        let Ok(header) = self.levels[0].header(0, 0) else {
            return false;
        };
        let mask = child_mask(header);
        walk.frames[0] = BeamFrame {
            word: 0,
            mask,
            remaining: beam.children_met(mask, [0.0; 3], root_size, neg),
            pos: [0.0; 3],
            reflection: 0,
        };
        walk.level = Some(0);
        let mut cells = [BeamCell::default(); CELLS_PER_ROUND];
        let mut paths = [Frame::default(); CELLS_PER_ROUND * LEVEL_SLOTS];
        let Ok(mut listed) =
            self.next_cells(&beam, neg, beam_level, &mut walk, &mut cells, &mut paths)
        else {
            return false;
        };
        if listed == 0 {
            // No ray of the packet meets an occupied cell of the beam level.
            hits[..n].fill(Hit::MISS);
            return true;
        }
        let mut groups = [beam; GROUPS];
        if self.beams(&rays[0], shape, Some(&mut groups)).is_none() {
            return false;
        }
        #[cfg(target_arch = "x86_64")]
        let group_beams = crate::cpu::available().then(|| GroupBeams::of(&groups));
        #[cfg(not(target_arch = "x86_64"))]
        let group_beams: Option<GroupBeams> = None;
        // The set-up of every ray, as `Tracer::setup` does it, with what the
        // rays share done once. Anything it would treat specially sends the
        // packet back to the ray-by-ray path.
        let first = &rays[0];
        let level = first.level.unwrap_or(self.depth);
        let resolution = f64::from(self.cell_size[0]);
        let origin = shape.origin;
        let (tmin, tmax) = (f64::from(first.tmin), f64::from(first.tmax));
        let usual = origin.iter().all(|o| o.abs() <= resolution * 16.0)
            && tmin <= tmax
            && level > beam_level
            && level <= self.depth;
        if !usual {
            return false;
        }
        let stop = level.min(self.leaf_level);
        // The usual case: the rays go down to the bricks, three node levels
        // below the beam level's cells (the leaf level).
        let bricks = stop != level;
        debug_assert!(!bricks || stop == beam_level + 3);
        let mut walks = [Walk::default(); PACKET_RAYS];
        // Rays still looking for their first hit, one bit per ray.
        let mut alive = 0u64;
        // Rays set up four at a time in vectors where the processor can
        // (the same numbers as `packet_ray`, for usual rays).
        let mut prepared = [Prepared::default(); 4];
        let mut usual = 0u32;
        for (i, ray) in rays.iter().enumerate() {
            if i % 4 == 0 {
                usual = self.set_up_four(&rays[i..], &mut prepared);
            }
            let set_up = if usual >> (i % 4) & 1 == 1 {
                let p = &prepared[i % 4];
                Ok(self.clip(p).map(|q| (q, p.tmin)))
            } else {
                self.packet_ray(origin, ray.dir, [tmin, tmax], level)
            };
            match set_up {
                Err(()) => return false,
                Ok(None) => hits[i] = Hit::MISS,
                Ok(Some((q, ray_tmin))) => {
                    if q.neg != neg {
                        return false;
                    }
                    walks[i & (PACKET_RAYS - 1)] = Walk {
                        q,
                        ray_tmin,
                        stop,
                        ..Walk::default()
                    };
                    alive |= 1 << i;
                }
            }
        }
        let beam_size = self.cell_size[usize::from(beam_level)];
        let mut lanes = PacketLanes::default();
        let mut set = alive;
        while set != 0 {
            let i = set.trailing_zeros() as usize & (PACKET_RAYS - 1);
            set &= set - 1;
            let q = &walks[i].q;
            for a in 0..3 {
                lanes.inv[a][i] = q.inv_dir[a];
            }
            lanes.tmin[i] = q.tmin;
            lanes.tmax[i] = q.tmax;
        }
        while alive != 0 && listed > 0 {
            for cell in &cells[..listed] {
                if alive == 0 {
                    break;
                }
                // The rays of the groups whose beam meets the cell: most rays
                // of a packet miss most of its cells, and one group's beam
                // test saves the slab tests of its rays.
                let pos = cell.pos.to_array().map(f64::from);
                let size = f64::from(beam_size);
                let mut rays = 0u64;
                #[cfg(target_arch = "x86_64")]
                if let Some(group_beams) = &group_beams {
                    // SAFETY: `group_beams` is only made where
                    // `cpu::available` found AVX2.
                    let met = unsafe { avx2::groups_meet(&beam, group_beams, pos, size) };
                    for g in 0..GROUPS {
                        if met >> g & 1 != 0 {
                            rays |= GROUP_MASK << (g * GROUP_RAYS);
                        }
                    }
                    rays &= alive;
                }
                if group_beams.is_none() {
                    for (g, group) in groups.iter().enumerate() {
                        let members = alive & (GROUP_MASK << (g * GROUP_RAYS));
                        if members != 0 && group.meets(pos, size) {
                            rays |= members;
                        }
                    }
                }
                if rays == 0 {
                    continue;
                }
                let path = &paths[cell.path..cell.path + usize::from(beam_level)];
                let walked = if bricks {
                    self.walk_cell_to_bricks(
                        cell, beam_level, path, &walks, &lanes, rays, &mut alive, hits,
                    )
                } else {
                    self.walk_cell(
                        cell, beam_level, path, &walks, &lanes, rays, &mut alive, hits,
                    )
                };
                if walked.is_err() {
                    return false;
                }
            }
            if alive != 0 {
                listed = match self
                    .next_cells(&beam, neg, beam_level, &mut walk, &mut cells, &mut paths)
                {
                    Ok(listed) => listed,
                    Err(()) => return false,
                };
            }
        }
        let mut missed = alive;
        while missed != 0 {
            hits[missed.trailing_zeros() as usize] = Hit::MISS;
            missed &= missed - 1;
        }
        true
    }

    /// The first four of `rays` set up in `prepared` by `simd::setup4`, where
    /// the processor has AVX2 and four rays are left: the mask of the usual
    /// rays it set up (0 otherwise; the others go through
    /// [`Tracer::packet_ray`]).
    #[inline(always)]
    fn set_up_four(&self, rays: &[Ray], prepared: &mut [Prepared; 4]) -> u32 {
        #[cfg(target_arch = "x86_64")]
        if let Some(four) = rays.first_chunk::<4>()
            && crate::cpu::available()
        {
            // SAFETY: `cpu::available` found AVX2.
            return unsafe { crate::simd::setup4(self, four, prepared) };
        }
        let _ = (rays, prepared);
        0
    }

    /// The set-up of a ray of a packet whose grid origin is `origin` (not
    /// far: no re-basing), as [`Tracer::setup`] and [`Tracer::start`] do it:
    /// the prepared ray clipped to the occupied box and its own `tmin`, or
    /// `None` when it misses the box. `Err` for a direction the set-up
    /// treats specially (a component treated as zero, or none finite).
    #[inline(always)]
    pub(crate) fn packet_ray(
        &self,
        origin: [f64; 3],
        dir: [f32; 3],
        bounds: [f64; 2],
        level: u8,
    ) -> Result<Option<(Prepared, f32)>, ()> {
        let dir = dir.map(|d| f64::from(d) * self.grid_scale);
        let largest = dir[0].abs().max(dir[1].abs()).max(dir[2].abs());
        let regular = largest.is_finite()
            && largest >= f64::MIN_POSITIVE
            && dir.iter().all(|d| d.abs() >= largest * TINY_DIRECTION);
        if !regular {
            return Err(());
        }
        let p = self.prepare(origin, dir, largest, [true; 3], bounds, 0.0, level);
        Ok(self.clip(&p).map(|q| (q, p.tmin)))
    }

    /// Walks the subtree of the beam cell `cell` for the rays `rays` (bits of
    /// `walks`, all still in `alive`) at once: one depth-first walk, in the front-to-back
    /// child order of the packet's octant, that visits the nodes any of them
    /// passes through. At each node every ray that reached it computes its
    /// own chain of children, with the very numbers [`Tracer::resume`] uses,
    /// so each ray sees the nodes of its own traversal in its own order, and
    /// its first occupied cell is its answer: it is written to `hits` and its
    /// bit cleared from `alive`. `path` holds the nodes above the cell.
    /// `Err` on a read out of range. For rays of a level of detail at or
    /// above the leaf level, whose walk stops at a node level; rays down to
    /// the bricks go through [`Tracer::walk_cell_to_bricks`].
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn walk_cell(
        &self,
        cell: &BeamCell,
        beam_level: u8,
        path: &[Frame],
        walks: &[Walk; PACKET_RAYS],
        lanes: &PacketLanes,
        rays: u64,
        alive: &mut u64,
        hits: &mut [Hit],
    ) -> Result<(), ()> {
        let first = &walks[rays.trailing_zeros() as usize & (PACKET_RAYS - 1)];
        let (origin, neg) = (first.q.origin, first.q.neg & 7);
        let (stop, ray_level) = (first.stop, first.q.level);
        let mut frames = [SubtreeFrame::default(); SUBTREE_SLOTS];
        let mut size = self.cell_size[usize::from(beam_level)];
        let mut level = beam_level;
        let mut top = 0;
        self.visit_subtree_node(
            &mut frames[0],
            level,
            cell.word,
            cell.pos,
            size,
            rays,
            lanes,
            origin,
            neg,
            cell.reflection,
            self.children_at(level + 1, stop, ray_level),
        )?;
        loop {
            let frame = &mut frames[top & (SUBTREE_SLOTS - 1)];
            if frame.remaining == 0 {
                if top == 0 {
                    return Ok(());
                }
                top -= 1;
                level -= 1;
                size *= 2.0;
                continue;
            }
            let node_neg = (neg ^ usize::from(frame.reflection)) & 7;
            let child = FIRST[node_neg][usize::from(frame.remaining)];
            frame.remaining &= !(1 << child);
            let child_rays = frame.rays[usize::from(child) & 7] & *alive;
            if child_rays == 0 {
                continue;
            }
            let pos = frame.pos;
            let pointer = frame.pointers[usize::from(child) & 7];
            let child_reflection = frame.reflections[usize::from(child) & 7];
            let half = size * 0.5;
            let child_pos = pos + CHILD_STEPS[(usize::from(child) ^ node_neg) & 7] * half;
            let child_level = level + 1;
            if child_level < stop {
                top += 1;
                self.visit_subtree_node(
                    &mut frames[top & (SUBTREE_SLOTS - 1)],
                    child_level,
                    pointer,
                    child_pos,
                    half,
                    child_rays,
                    lanes,
                    origin,
                    neg,
                    child_reflection,
                    self.children_at(child_level + 1, stop, ray_level),
                )?;
                level = child_level;
                size = half;
                continue;
            }
            // The stop level, the rays' own: the cell is the answer.
            let mut m = child_rays;
            while m != 0 {
                let r = m.trailing_zeros() as usize & (PACKET_RAYS - 1);
                m &= m - 1;
                let cell = (child_pos, child_level, pointer);
                hits[r] = self.packet_hit(&walks[r], cell, path, &frames[..=top], None)?;
                *alive &= !(1 << r);
            }
        }
    }

    /// The visit of a node whose children are bricks (the level above the
    /// leaf level) by the rays `rays` of a packet, one ray at a time: each
    /// ray's chain of children from the same plane parameters as
    /// [`Tracer::resume`], then its bricks in its own front-to-back order,
    /// tested as [`Tracer::brick`] tests them (the very same numbers: the
    /// brick's outer planes are the node's, see [`Tracer::brick_in_node`]),
    /// until one has a voxel. Hits go to `hits` and leave `alive`. `above`
    /// is the path to the node: the beam cell's and the subtree walk's
    /// frames, for the attribute index. `Err` on a read out of range.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn visit_bottom(
        &self,
        level: u8,
        word: u32,
        pos: Vec3A,
        size: f32,
        rays: u64,
        walks: &[Walk; PACKET_RAYS],
        origin: Vec3A,
        neg: usize,
        reflection: u8,
        above: (&[Frame], &[SubtreeFrame]),
        alive: &mut u64,
        hits: &mut [Hit],
    ) -> Result<(), ()> {
        let section = &self.levels[usize::from(level) & (LEVEL_SLOTS - 1)];
        let mask = child_mask(section.header(level, word).map_err(|_| ())?);
        // The node, and its bricks, are traced in octant `neg ^ R` (spec
        // §23.4); a brick's R is the node's and its reference's.
        let neg = (neg ^ usize::from(reflection)) & 7;
        let half = size * 0.5;
        // Offsets of the planes from the packet's origin, as `resume` and
        // `brick` compute them (so the same roundings).
        let d_lo = pos - origin;
        let d_mid = pos + Vec3A::splat(half) - origin;
        let d_hi = pos + Vec3A::splat(size) - origin;
        // The rays' chains: (ray, children) for the rays that pass through
        // some child.
        let mut chains = [(0u8, 0u8); PACKET_RAYS];
        let mut n = 0;
        let mut union = 0u8;
        let mut m = rays;
        while m != 0 {
            let r = m.trailing_zeros() as usize & (PACKET_RAYS - 1);
            m &= m - 1;
            let q = &walks[r].q;
            let t_lo = d_lo * q.inv_dir;
            let t_hi = d_hi * q.inv_dir;
            let t_enter = max(t_lo.max_element(), q.tmin);
            let t_exit = min(t_hi.min_element(), q.tmax);
            if t_enter <= t_exit {
                let chain = crate::walk::chain(neg, t_enter, t_exit, d_mid * q.inv_dir) & mask;
                chains[n & (PACKET_RAYS - 1)] = (r as u8, chain);
                n += usize::from(chain != 0);
                union |= chain;
            }
        }
        if union == 0 {
            return Ok(());
        }
        // The bricks' leaf masks are read soon: start all their reads now.
        let leaves = &self.levels[usize::from(self.leaf_level) & (LEVEL_SLOTS - 1)];
        let mut pointers = [0u32; 8];
        let mut reflections = [0u8; 8];
        let mut children = union;
        while children != 0 {
            let c = children.trailing_zeros() as usize & 7;
            children &= children - 1;
            let reference = section.child(level, word, mask, c as u32).map_err(|_| ())?;
            let pointer = reference.node;
            prefetch(leaves.bytes, pointer as usize * 8);
            pointers[c] = pointer;
            reflections[c] = (reflection ^ reference.reflection) & 7;
        }
        for &(r, chain) in &chains[..n] {
            let r = usize::from(r) & (PACKET_RAYS - 1);
            let q = &walks[r].q;
            let planes = (d_lo * q.inv_dir, d_mid * q.inv_dir, d_hi * q.inv_dir);
            let mut remaining = chain;
            while remaining != 0 {
                let c = FIRST[neg][usize::from(remaining)];
                remaining &= !(1 << c);
                let pointer = pointers[usize::from(c) & 7];
                let leaf_reflection = reflections[usize::from(c) & 7];
                let child = (usize::from(c) ^ neg) & 7;
                let brick_pos = pos + CHILD_STEPS[child] * half;
                let Some((cell_pos, cell_level)) =
                    self.brick_in_node(q, pointer, leaf_reflection, brick_pos, child, planes)?
                else {
                    continue;
                };
                let cell = (cell_pos, cell_level, pointer);
                let node = Frame {
                    word,
                    mask,
                    reflection,
                    ..Frame::default()
                };
                let (path, frames) = above;
                hits[r] = self.packet_hit(&walks[r], cell, path, frames, Some(node))?;
                *alive &= !(1 << r);
                break;
            }
        }
        Ok(())
    }

    /// [`Tracer::walk_cell`] for the usual packet, whose rays go down to the
    /// bricks three node levels below the beam level: the walk of the cell's
    /// two upper levels as two nested loops (no stack of frames), the level
    /// above the bricks by [`Tracer::visit_bottom`]. The same visits in the
    /// same order, so the same answers.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn walk_cell_to_bricks(
        &self,
        cell: &BeamCell,
        beam_level: u8,
        path: &[Frame],
        walks: &[Walk; PACKET_RAYS],
        lanes: &PacketLanes,
        rays: u64,
        alive: &mut u64,
        hits: &mut [Hit],
    ) -> Result<(), ()> {
        let first = &walks[rays.trailing_zeros() as usize & (PACKET_RAYS - 1)];
        let (origin, neg) = (first.q.origin, first.q.neg & 7);
        let (stop, ray_level) = (first.stop, first.q.level);
        let size = self.cell_size[usize::from(beam_level)];
        let (half, quarter) = (size * 0.5, size * 0.25);
        let (level, middle) = (beam_level, beam_level + 1);
        let mut frames = [SubtreeFrame::default(); 2];
        self.visit_subtree_node(
            &mut frames[0],
            level,
            cell.word,
            cell.pos,
            size,
            rays,
            lanes,
            origin,
            neg,
            cell.reflection,
            self.children_at(middle, stop, ray_level),
        )?;
        let mut remaining = frames[0].remaining;
        let cell_neg = (neg ^ usize::from(cell.reflection)) & 7;
        while remaining != 0 {
            let child = FIRST[cell_neg][usize::from(remaining)];
            remaining &= !(1 << child);
            let child = usize::from(child) & 7;
            let child_rays = frames[0].rays[child] & *alive;
            if child_rays == 0 {
                continue;
            }
            let child_pos = frames[0].pos + CHILD_STEPS[child ^ cell_neg] * half;
            let pointer = frames[0].pointers[child];
            let child_reflection = frames[0].reflections[child];
            let child_neg = (neg ^ usize::from(child_reflection)) & 7;
            self.visit_subtree_node(
                &mut frames[1],
                middle,
                pointer,
                child_pos,
                half,
                child_rays,
                lanes,
                origin,
                neg,
                child_reflection,
                self.children_at(middle + 1, stop, ray_level),
            )?;
            let mut inner = frames[1].remaining;
            while inner != 0 {
                let grandchild = FIRST[child_neg][usize::from(inner)];
                inner &= !(1 << grandchild);
                let grandchild = usize::from(grandchild) & 7;
                let grandchild_rays = frames[1].rays[grandchild] & *alive;
                if grandchild_rays == 0 {
                    continue;
                }
                self.visit_bottom(
                    middle + 1,
                    frames[1].pointers[grandchild],
                    frames[1].pos + CHILD_STEPS[grandchild ^ child_neg] * quarter,
                    quarter,
                    grandchild_rays,
                    walks,
                    origin,
                    neg,
                    frames[1].reflections[grandchild],
                    (path, &frames),
                    alive,
                    hits,
                )?;
            }
        }
        Ok(())
    }

    /// The hit of the packet ray `walk` that found `cell`, with its attribute
    /// index where hits carry one: the path to the cell is the nodes above
    /// the beam cell (`path`), the subtree walk's `frames` and, below them,
    /// `node`.
    #[inline(always)]
    fn packet_hit(
        &self,
        walk: &Walk,
        cell: crate::walk::Cell,
        path: &[Frame],
        frames: &[SubtreeFrame],
        node: Option<Frame>,
    ) -> Result<Hit, ()> {
        if !self.index_kind() {
            return self.walk_hit(walk, cell, None).map_err(|_| ());
        }
        let mut stack: Stack = [Frame::default(); LEVEL_SLOTS];
        stack[..path.len()].copy_from_slice(path);
        let walked = frames.iter().map(|f| Frame {
            word: f.word,
            mask: f.mask,
            reflection: f.reflection,
            ..Frame::default()
        });
        for (k, f) in walked.chain(node).enumerate() {
            stack[(path.len() + k) & (LEVEL_SLOTS - 1)] = f;
        }
        self.walk_hit(walk, cell, Some(&stack)).map_err(|_| ())
    }

    /// Where the nodes of `level` are read, for prefetching, and their record
    /// size: the node level, the leaf masks for the bricks below the stop
    /// level, or nothing when the walk stops there.
    #[inline(always)]
    fn children_at(&self, level: u8, stop: u8, ray_level: u8) -> (&[u8], usize) {
        if level < stop {
            let section = &self.levels[usize::from(level) & (LEVEL_SLOTS - 1)];
            // Bytes per unit of a node's address: 4 in 1.0, 1 in 2.0.
            (section.bytes, section.node_byte(1))
        } else if stop != ray_level {
            (
                self.levels[usize::from(self.leaf_level) & (LEVEL_SLOTS - 1)].bytes,
                8,
            )
        } else {
            (&[], 0)
        }
    }

    /// The visit of a node of a cell's subtree by the rays `rays` of a
    /// packet: the rays that pass through each child, as each ray's own
    /// traversal would find them ([`Tracer::resume`]: the chain of children
    /// from the same plane parameters), four or eight rays at a time.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn visit_subtree_node(
        &self,
        frame: &mut SubtreeFrame,
        level: u8,
        word: u32,
        pos: Vec3A,
        size: f32,
        rays: u64,
        lanes: &PacketLanes,
        origin: Vec3A,
        neg: usize,
        reflection: u8,
        children_at: (&[u8], usize),
    ) -> Result<(), ()> {
        let header = self.levels[usize::from(level) & (LEVEL_SLOTS - 1)]
            .header(level, word)
            .map_err(|_| ())?;
        // The node is traced in octant `neg ^ R` (spec §23.4).
        let neg = (neg ^ usize::from(reflection)) & 7;
        let mask = child_mask(header);
        // The plane offsets are common to the packet (one origin); the same
        // operations as `resume`, so the same roundings.
        let planes = [
            pos - origin,
            pos + Vec3A::splat(size * 0.5) - origin,
            pos + Vec3A::splat(size) - origin,
        ]
        .map(|p| p.to_array());
        #[cfg(target_arch = "x86_64")]
        let tests = if crate::cpu::available() {
            // SAFETY: `cpu::available` found AVX2.
            unsafe { avx2::chain_tests(planes, lanes, rays) }
        } else {
            chain_tests(planes, lanes, rays)
        };
        #[cfg(not(target_arch = "x86_64"))]
        let tests = chain_tests(planes, lanes, rays);
        // Only the entries of the children with rays are ever read.
        frame.word = word;
        frame.mask = mask;
        frame.remaining = 0;
        frame.pos = pos;
        frame.reflection = reflection;
        if tests.inside != 0 {
            let section = &self.levels[usize::from(level) & (LEVEL_SLOTS - 1)];
            let (child_bytes, record) = children_at;
            // All eight chains at once, without branches: a jump to a
            // per-child formula mispredicts often (d12 tiles 6 % slower).
            let through_all = tests.through_all();
            // The children (file indices) that rays pass through, found
            // without a branch per child (those branches mispredict often).
            let mut children = 0u8;
            for c in 0..8 {
                children |= u8::from(through_all[c ^ neg] != 0) << c;
            }
            children &= mask;
            frame.remaining = children;
            while children != 0 {
                let c = children.trailing_zeros() as usize & 7;
                children &= children - 1;
                // The children are read soon, and most miss the cache: start
                // all their reads now.
                let reference = section.child(level, word, mask, c as u32).map_err(|_| ())?;
                let pointer = reference.node;
                prefetch(child_bytes, pointer as usize * record);
                frame.rays[c] = through_all[(c ^ neg) & 7];
                frame.pointers[c] = pointer;
                frame.reflections[c] = (reflection ^ reference.reflection) & 7;
            }
        }
        Ok(())
    }

    /// The beam of the rays of a packet and, with `groups`, the beams of its
    /// groups of [`GROUP_RAYS`] consecutive rays (`groups[g]` for
    /// `rays[16g..16g + 16]`), or `None` when they have no finite extent
    /// (which [`Tracer::packet_shape`] rules out). Most packets of a camera
    /// meet nothing and need only the packet's beam.
    #[inline(always)]
    fn beams(
        &self,
        first: &Ray,
        shape: &PacketShape,
        groups: Option<&mut [Beam; GROUPS]>,
    ) -> Option<Beam> {
        let resolution = f64::from(self.cell_size[0]);
        let mut origin = shape.origin;
        for (a, o) in origin.iter_mut().enumerate() {
            if octant(first.dir) >> a & 1 == 1 {
                *o = resolution - *o;
            }
        }
        let scale = resolution.max(origin.iter().fold(0f64, |m, o| m.max(o.abs())));
        let empty = Beam {
            origin,
            inv_lo: [f64::INFINITY; 3],
            inv_hi: [0.0; 3],
            tmin: f64::from(first.tmin),
            tmax: f64::from(first.tmax),
            // Enlarge by the rounding margin, and by the one of the `f64`
            // arithmetic here (far smaller).
            margin: scale * BEAM_MARGIN,
        };
        // Grid units per unit of the ray's parameter t, 1 / |d_a|: its range
        // over a set of rays from the range of their |d_a| (a correctly
        // rounded division and the scaling by the grid are monotonic, so
        // this is exactly the range of the rays' own quotients).
        let beam_of = |(d_lo, d_hi): (Vec3A, Vec3A)| {
            let mut beam = empty;
            for a in 0..3 {
                beam.inv_lo[a] = 1.0 / (f64::from(d_hi[a]) * self.grid_scale);
                beam.inv_hi[a] = 1.0 / (f64::from(d_lo[a]) * self.grid_scale);
            }
            beam
        };
        let beam = beam_of(shape.all);
        if let Some(groups) = groups {
            for (group, &range) in groups.iter_mut().zip(&shape.ranges) {
                // A group without rays (`lo > hi`): a beam that meets nothing.
                *group = if range.0.x > range.1.x {
                    empty
                } else {
                    beam_of(range)
                };
            }
        }
        let finite =
            beam.inv_hi.iter().all(|v| v.is_finite()) && origin.iter().all(|v| v.is_finite());
        finite.then_some(beam)
    }

    /// Advances the beam walk to the next (up to [`CELLS_PER_ROUND`]) cells
    /// of the beam level it meets, in front-to-back order; writes them to
    /// `cells` and their paths to `paths`, and returns how many. `Err` on a
    /// read out of range.
    #[inline(always)]
    fn next_cells(
        &self,
        beam: &Beam,
        neg: usize,
        beam_level: u8,
        walk: &mut BeamWalk,
        cells: &mut [BeamCell; CELLS_PER_ROUND],
        paths: &mut [Frame; CELLS_PER_ROUND * LEVEL_SLOTS],
    ) -> Result<usize, ()> {
        let mut listed = 0;
        while let Some(level) = walk.level {
            if listed == CELLS_PER_ROUND {
                break;
            }
            let l = usize::from(level);
            let frame = walk.frames[l];
            if frame.remaining == 0 {
                walk.level = level.checked_sub(1);
                continue;
            }
            // A node reached with accumulated reflection R is traced in
            // octant `neg ^ R` (spec §23.4, `node`'s docs).
            let node_neg = (neg ^ usize::from(frame.reflection)) & 7;
            let child = FIRST[node_neg][usize::from(frame.remaining)];
            walk.frames[l].remaining &= !(1 << child);
            let m = usize::from(child) ^ node_neg;
            let half = f64::from(self.cell_size[l + 1]);
            let pos = [
                frame.pos[0] + (m & 1) as f64 * half,
                frame.pos[1] + (m >> 1 & 1) as f64 * half,
                frame.pos[2] + (m >> 2 & 1) as f64 * half,
            ];
            let reference = self.levels[l]
                .child(level, frame.word, frame.mask, u32::from(child))
                .map_err(|_| ())?;
            let pointer = reference.node;
            let reflection = (frame.reflection ^ reference.reflection) & 7;
            if level + 1 == beam_level {
                let path = listed * LEVEL_SLOTS;
                for (slot, f) in paths[path..path + l + 1].iter_mut().zip(&walk.frames) {
                    *slot = Frame {
                        word: f.word,
                        mask: f.mask,
                        reflection: f.reflection,
                        ..Frame::default()
                    };
                }
                let cell_level = &self.levels[l + 1];
                prefetch(cell_level.bytes, cell_level.node_byte(pointer));
                cells[listed] = BeamCell {
                    word: pointer,
                    pos: Vec3A::new(pos[0] as f32, pos[1] as f32, pos[2] as f32),
                    path,
                    reflection,
                };
                listed += 1;
                continue;
            }
            let header = self.levels[l + 1]
                .header(level + 1, pointer)
                .map_err(|_| ())?;
            let mask = child_mask(header);
            walk.frames[l + 1] = BeamFrame {
                word: pointer,
                mask,
                remaining: beam.children_met(mask, pos, half, neg ^ usize::from(reflection)),
                pos,
                reflection,
            };
            walk.level = Some(level + 1);
        }
        Ok(listed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use crate::walk::Setup;
    use dagfmt::Dag;
    use dagfmt::builder::DagBuilder;
    use dagfmt::layout::AttributeKind;

    /// splitmix64.
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        }

        fn unit(&mut self) -> f32 {
            (self.next() >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// A depth-10 scene of hollow balls (1024³ voxels, world cube [0, 1]³),
    /// and the balls' centres (world space).
    fn scene(rng: &mut Rng) -> (Vec<u8>, Vec<[f32; 3]>) {
        let mut voxels = Vec::new();
        let mut centres = Vec::new();
        for _ in 0..6 {
            let c = [0; 3].map(|_| 100.0 + rng.unit() * 824.0);
            centres.push(c.map(|v| v / 1024.0));
            let r = 20.0 + rng.unit() * 60.0;
            let lo = c.map(|v| (v - r - 2.0) as u32);
            let hi = c.map(|v| (v + r + 2.0) as u32);
            for z in lo[2]..hi[2] {
                for y in lo[1]..hi[1] {
                    for x in lo[0]..hi[0] {
                        let d2: f32 = [x, y, z]
                            .iter()
                            .zip(&c)
                            .map(|(&p, &c)| (p as f32 + 0.5 - c).powi(2))
                            .sum();
                        if d2 <= r * r && d2 >= (r - 1.5) * (r - 1.5) {
                            voxels.push([x, y, z]);
                        }
                    }
                }
            }
        }
        let mut built =
            DagBuilder::from_voxels(10, AttributeKind::VoxelCount, voxels).expect("valid voxels");
        built.set_root_cube([0.0; 3], 1.0).expect("valid cube");
        (built.to_bytes(), centres)
    }

    /// Packets of `count` rays from one origin in a narrow cone around a
    /// direction towards one of `centres`.
    fn packets(rng: &mut Rng, centres: &[[f32; 3]], packets: usize, count: usize) -> Vec<Ray> {
        let mut rays = Vec::new();
        for p in 0..packets {
            let origin = if p % 5 == 0 {
                // Inside the cube.
                [0; 3].map(|_| rng.unit())
            } else {
                [0; 3].map(|_| rng.unit() * 3.0 - 1.0)
            };
            let c = centres[(rng.next() % centres.len() as u64) as usize];
            let mut target = c.map(|v| v + (rng.unit() - 0.5) * 0.08);
            // Every component clearly non-zero, so that the cone stays in
            // one octant.
            for i in 0..3 {
                if (target[i] - origin[i]).abs() < 0.1 {
                    target[i] = origin[i] + if rng.next() & 1 == 0 { 0.1 } else { -0.1 };
                }
            }
            let spread = 0.002 + 0.02 * rng.unit();
            let (tmin, tmax) = match p % 4 {
                0 => (0.0, 0.8 + rng.unit()),
                1 => (rng.unit() * 0.5, f32::INFINITY),
                _ => (0.0, f32::INFINITY),
            };
            let level = (p % 7 == 3).then_some(8 + (rng.next() % 3) as u8);
            for _ in 0..count {
                let dir = [0, 1, 2].map(|i| target[i] - origin[i] + (rng.unit() - 0.5) * spread);
                rays.push(Ray {
                    origin,
                    dir,
                    tmin,
                    tmax,
                    level,
                });
            }
        }
        rays
    }

    #[test]
    fn packets_are_runs_of_coherent_rays() {
        let mut rng = Rng(3);
        let (bytes, centres) = scene(&mut rng);
        let dag = Dag::open(&bytes).unwrap();
        let tracer = Tracer::new(&dag).unwrap();
        assert_eq!(tracer.beam_level(), 5);
        let mut rays = packets(&mut rng, &centres, 1, 100);
        rays.iter_mut().for_each(|r| r.level = None);
        assert_eq!(tracer.packet_len(&rays), PACKET_RAYS);
        assert_eq!(tracer.packet_len(&rays[..MIN_PACKET_RAYS - 1]), 0);
        // Each difference ends the run.
        let mut other = rays.clone();
        other[10].origin[1] += 1e-6;
        assert_eq!(tracer.packet_len(&other), 10);
        let mut other = rays.clone();
        other[12].tmax = 5.0;
        assert_eq!(tracer.packet_len(&other), 12);
        let mut other = rays.clone();
        other[9].level = Some(9);
        assert_eq!(tracer.packet_len(&other), 9);
        let mut other = rays.clone();
        other[20].dir[2] = -other[20].dir[2];
        assert_eq!(tracer.packet_len(&other), 20);
        // Zero or NaN direction components, coarse or impossible levels: no packet.
        for change in 0..4 {
            let mut other = rays.clone();
            match change {
                0 => other[0].dir[1] = 0.0,
                1 => other[0].dir[0] = f32::NAN,
                2 => other.iter_mut().for_each(|r| r.level = Some(5)),
                _ => other.iter_mut().for_each(|r| r.level = Some(11)),
            }
            assert_eq!(tracer.packet_len(&other), 0, "change {change}");
        }
    }

    /// Format 2.0 (spec §23): packets trace the 2.0 encoding of the scenes
    /// (the beam walk and the cells' walks carrying each node's
    /// accumulated reflection) with the answers of the 1.0 tracer's single
    /// rays, attribute index included; most packets are traced as packets,
    /// through reflected references.
    #[test]
    fn packets_trace_format_2_like_1_0_single_rays() {
        let mut rng = Rng(0x2a);
        let (mut traced, mut hit_count, mut total, mut reflected) = (0, 0, 0, 0);
        for _ in 0..3 {
            let (bytes, centres) = scene(&mut rng);
            let dag = Dag::open(&bytes).unwrap();
            let v1 = Tracer::new(&dag).unwrap();
            let enc = dagfmt::v2::encode(&dag).unwrap();
            for level in enc.levels.iter().filter(|l| !l.is_leaf) {
                let mut at = 0u64;
                while at < level.bytes.len() as u64 {
                    let node = dagfmt::v2::decode_node(&level.bytes, at, level.widths).unwrap();
                    reflected += node
                        .children
                        .iter()
                        .flatten()
                        .filter(|c| {
                            matches!(c, dagfmt::v2::Child::Shared { reflection, .. } if *reflection != 0)
                        })
                        .count();
                    at += u64::from(node.size);
                }
            }
            // Through the expanded levels (spec §23.12) and in place.
            let expanded = Tracer::from_v2_levels(dag.header(), &enc.views(), None).unwrap();
            let in_place =
                Tracer::from_v2_levels_in_place(dag.header(), &enc.views(), None).unwrap();
            assert!(expanded.is_expanded() && !in_place.is_expanded());
            let rays = packets(&mut rng, &centres, 60, PACKET_RAYS);
            for v2 in [&expanded, &in_place] {
                for (p, chunk) in rays.chunks(PACKET_RAYS).enumerate() {
                    let mut hits = vec![Hit::MISS; chunk.len()];
                    if v2.try_packet(chunk, &mut hits) {
                        traced += 1;
                    } else {
                        v2.trace_lanes(chunk, &mut hits).unwrap();
                    }
                    for (ray, hit) in chunk.iter().zip(&hits) {
                        assert_eq!(*hit, v1.trace(ray).unwrap(), "packet {p}: {ray:?}");
                        hit_count += usize::from(hit.hit);
                        total += 1;
                    }
                }
            }
        }
        assert!(traced >= 240, "{traced} of 360 packets traced as packets");
        assert!(hit_count * 10 >= total, "{hit_count} of {total} hit");
        assert!(reflected > 0, "no reflected references");
    }

    #[test]
    fn packets_answer_like_single_rays() {
        let mut rng = Rng(5);
        let (mut traced, mut hit_count, mut total) = (0, 0, 0);
        for _ in 0..3 {
            let (bytes, centres) = scene(&mut rng);
            let dag = Dag::open(&bytes).unwrap();
            let tracer = Tracer::new(&dag).unwrap();
            let rays = packets(&mut rng, &centres, 60, PACKET_RAYS);
            for (p, chunk) in rays.chunks(PACKET_RAYS).enumerate() {
                assert_eq!(tracer.packet_len(chunk), PACKET_RAYS, "packet {p}");
                let mut hits = vec![Hit::MISS; chunk.len()];
                if tracer.try_packet(chunk, &mut hits) {
                    traced += 1;
                } else {
                    tracer.trace_lanes(chunk, &mut hits).unwrap();
                }
                for (ray, hit) in chunk.iter().zip(&hits) {
                    // Generic rays: no exact ties, so the very same answers.
                    assert_eq!(*hit, tracer.trace(ray).unwrap(), "packet {p}: {ray:?}");
                    hit_count += usize::from(hit.hit);
                    total += 1;
                }
            }
        }
        // Packets from inside the cube or with a far origin fall back; the
        // others go as packets, and the scenes are hit.
        assert!(traced >= 120, "{traced} of 180 packets traced as packets");
        assert!(hit_count * 5 > total, "{hit_count} of {total} rays hit");
    }

    #[test]
    fn malformed_dags_fail_in_packets_like_single_rays() {
        let mut rng = Rng(17);
        let (bytes, centres) = scene(&mut rng);
        let first = Dag::open(&bytes).unwrap().levels()[0].file_offset as usize;
        let rays = packets(&mut rng, &centres, 40, PACKET_RAYS);
        let mut errors = 0;
        for case in 0..60 {
            let mut corrupt = bytes.clone();
            for _ in 0..1 + case % 3 {
                let at = first + (rng.next() % (corrupt.len() - first) as u64) as usize;
                corrupt[at] = rng.next() as u8;
            }
            let Ok(dag) = Dag::open(&corrupt) else {
                continue;
            };
            let Ok(tracer) = Tracer::new(&dag) else {
                continue;
            };
            for chunk in rays.chunks(PACKET_RAYS) {
                let mut hits = vec![Hit::MISS; chunk.len()];
                let batch = tracer.trace_sequential_into(chunk, &mut hits);
                let single: Result<Vec<Hit>, _> = chunk.iter().map(|r| tracer.trace(r)).collect();
                match (single, batch) {
                    (Ok(single), Ok(())) => assert_eq!(single, hits),
                    (Err(a), Err(b)) => {
                        assert_eq!(a, b);
                        errors += 1;
                    }
                    (a, b) => panic!("single {a:?}, batch {b:?}"),
                }
            }
        }
        assert!(
            errors > 0,
            "some corruption must lead a pointer out of range"
        );
    }

    /// Camera rays row by row (traced tile by tile, module `grid`), with
    /// rays of another camera after them, through `trace_sequential_into`
    /// and `trace_batch`.
    fn image_rays(
        rng: &mut Rng,
        centres: &[[f32; 3]],
        width: u32,
        height: u32,
    ) -> (Vec<Ray>, usize) {
        let target = centres[(rng.next() % centres.len() as u64) as usize];
        let mut position = [0; 3].map(|_| rng.unit() * 4.0 - 1.5);
        if rng.next().is_multiple_of(3) {
            // Inside the cube: no packets.
            position = [0; 3].map(|_| 0.2 + rng.unit() * 0.6);
        }
        let camera = |position: [f32; 3], fov: f32| Camera {
            position: position.map(f64::from),
            look_at: target.map(f64::from),
            up: [0.0, 1.0, 0.0],
            fov_y_degrees: f64::from(10.0 + 40.0 * fov),
        };
        let fov = rng.unit();
        let mut rays = camera(position, fov)
            .frame()
            .unwrap()
            .rays(width, height, None);
        let image = rays.len();
        let other = [0; 3].map(|_| rng.unit() * 4.0 - 1.5);
        let frame = camera(other, fov).frame().unwrap();
        rays.extend(frame.rays(width / 2 + 3, 11, None));
        (rays, image)
    }

    #[test]
    fn row_major_images_answer_like_single_rays() {
        let mut rng = Rng(41);
        let (mut hit_count, mut total) = (0, 0);
        for (width, height) in [(61, 45), (128, 72), (40, 17), (16, 8), (200, 40)] {
            let (bytes, centres) = scene(&mut rng);
            let dag = Dag::open(&bytes).unwrap();
            let tracer = Tracer::new(&dag).unwrap();
            let (rays, image) = image_rays(&mut rng, &centres, width, height);
            assert_eq!(
                crate::grid::find_grid(&rays).map(|g| g.len()),
                Some(image),
                "{width}x{height}"
            );
            let single: Vec<Hit> = rays.iter().map(|r| tracer.trace(r).unwrap()).collect();
            let mut hits = vec![Hit::MISS; rays.len()];
            tracer.trace_sequential_into(&rays, &mut hits).unwrap();
            // Generic rays: no exact ties, so the very same answers.
            for (k, (a, b)) in single.iter().zip(&hits).enumerate() {
                assert_eq!(a, b, "{width}x{height}, ray {k}: {:?}", rays[k]);
            }
            assert_eq!(tracer.trace_batch(&rays).unwrap(), single);
            hit_count += single.iter().filter(|h| h.hit).count();
            total += rays.len();
        }
        assert!(hit_count * 50 > total, "{hit_count} of {total} rays hit");
    }

    #[test]
    fn malformed_dags_fail_in_images_like_single_rays() {
        let mut rng = Rng(43);
        let (bytes, centres) = scene(&mut rng);
        // The node levels' bytes (a changed leaf mask gives other answers,
        // not errors).
        let nodes: Vec<(usize, usize)> = {
            let dag = Dag::open(&bytes).unwrap();
            let levels = dag.levels();
            levels[..levels.len() - 1]
                .iter()
                .map(|l| (l.file_offset as usize, l.bytes.len()))
                .collect()
        };
        let mut errors = 0;
        for case in 0..60 {
            let (rays, _) = image_rays(&mut rng, &centres, 48, 24);
            let mut corrupt = bytes.clone();
            for _ in 0..1 + case % 3 {
                let (start, len) = nodes[(rng.next() % nodes.len() as u64) as usize];
                corrupt[start + (rng.next() % len as u64) as usize] = rng.next() as u8;
            }
            let Ok(dag) = Dag::open(&corrupt) else {
                continue;
            };
            let Ok(tracer) = Tracer::new(&dag) else {
                continue;
            };
            let single: Vec<_> = rays.iter().map(|r| tracer.trace(r)).collect();
            let mut hits = vec![Hit::MISS; rays.len()];
            for batch in [
                tracer.trace_sequential_into(&rays, &mut hits),
                tracer.trace_batch_into(&rays, &mut hits),
            ] {
                // The batch reports the error of one of its rays (the first
                // in the order it traces them).
                match batch {
                    Ok(()) => {
                        let single: Vec<Hit> = single.iter().map(|h| h.clone().unwrap()).collect();
                        assert_eq!(single, hits);
                    }
                    Err(e) => {
                        assert!(single.contains(&Err(e)));
                        errors += 1;
                    }
                }
            }
        }
        assert!(
            errors >= 10,
            "{errors}: corruption must often lead a pointer out of range"
        );
    }

    #[test]
    fn chain_tests_give_the_chains_of_the_table() {
        // Every arrangement of the three mid-plane crossings and the
        // segment's ends on a small grid of parameters, ties included.
        let values = [0.0f32, 1.0, 2.0, 3.0, 4.0];
        let mut arrangements = 0;
        for neg in 0..8 {
            for &x in &values {
                for &y in &values {
                    for &z in &values {
                        for &enter in &values {
                            for &exit in values.iter().filter(|&&e| e >= enter) {
                                let t_mid = Vec3A::new(x, y, z);
                                let expected = crate::walk::chain(neg, enter, exit, t_mid);
                                let m = [x, y, z];
                                let bit = |b: bool| u64::from(b);
                                let tests = ChainTests {
                                    inside: 1,
                                    first: m.map(|t| bit(t <= enter)),
                                    before_exit: m.map(|t| bit(t <= exit)),
                                    order: [bit(x < y), bit(x < z), bit(y < z)],
                                };
                                for c in 0..8 {
                                    assert_eq!(
                                        tests.through(c ^ neg) & 1,
                                        u64::from(expected >> c & 1),
                                        "child {c}, octant {neg}, t_mid {m:?}, [{enter}, {exit}]"
                                    );
                                }
                                arrangements += 1;
                            }
                        }
                    }
                }
            }
        }
        assert_eq!(arrangements, 8 * 125 * 15);
    }

    #[test]
    fn beam_children_are_the_children_the_beam_meets() {
        let mut rng = Rng(23);
        for _ in 0..2000 {
            let unit = |rng: &mut Rng| f64::from(rng.unit());
            let inv_lo = [0; 3].map(|_| 0.5 + unit(&mut rng));
            let beam = Beam {
                origin: [0; 3].map(|_| unit(&mut rng) * 300.0 - 100.0),
                inv_lo,
                inv_hi: inv_lo.map(|v| v * (1.0 + 0.2 * unit(&mut rng))),
                tmin: unit(&mut rng) * 10.0,
                tmax: if rng.next().is_multiple_of(3) {
                    f64::INFINITY
                } else {
                    40.0 + unit(&mut rng) * 200.0
                },
                margin: 1.0 / 64.0,
            };
            let size = f64::from(1u32 << (rng.next() % 7));
            let pos = [0; 3].map(|_| (rng.next() % 16) as f64 * size);
            let mask = rng.next() as u8;
            let neg = (rng.next() % 8) as usize;
            let met = beam.children_met(mask, pos, size, neg);
            assert_eq!(met, beam.children_met_scalar(mask, pos, size, neg));
            // The packet's four group tests at once, on the same cube.
            #[cfg(target_arch = "x86_64")]
            if crate::cpu::available() {
                let groups: [Beam; GROUPS] = std::array::from_fn(|g| Beam {
                    inv_hi: beam.inv_hi.map(|v| v * (1.0 + 0.05 * g as f64)),
                    ..beam
                });
                // SAFETY: checked.
                let met = unsafe { avx2::groups_meet(&beam, &GroupBeams::of(&groups), pos, size) };
                for (g, group) in groups.iter().enumerate() {
                    assert_eq!(met >> g & 1 == 1, group.meets(pos, size), "group {g}");
                }
            }
            for c in 0..8 {
                let m = c ^ neg;
                let half = size * 0.5;
                let child = [0, 1, 2].map(|a| pos[a] + (m >> a & 1) as f64 * half);
                let expected = mask >> c & 1 == 1 && beam.meets(child, half);
                assert_eq!(met >> c & 1 == 1, expected, "child {c} of {pos:?} ({size})");
            }
        }
    }

    #[test]
    fn packet_set_up_is_the_set_up_of_each_ray() {
        let mut rng = Rng(29);
        let (bytes, centres) = scene(&mut rng);
        let dag = Dag::open(&bytes).unwrap();
        let tracer = Tracer::new(&dag).unwrap();
        let rays = packets(&mut rng, &centres, 40, PACKET_RAYS);
        let mut compared = 0;
        for ray in &rays {
            let level = ray.level.unwrap_or(tracer.depth);
            let origin = [0, 1, 2]
                .map(|a| (f64::from(ray.origin[a]) - tracer.root_min[a]) * tracer.grid_scale);
            let bounds = [f64::from(ray.tmin), f64::from(ray.tmax)];
            let Ok(Setup::Trace(p)) = tracer.setup(ray) else {
                continue;
            };
            if p.base != 0.0 {
                // Far origins are re-based: never in packets.
                continue;
            }
            let expected = tracer.clip(&p).map(|q| (q, p.tmin));
            assert_eq!(
                tracer.packet_ray(origin, ray.dir, bounds, level),
                Ok(expected),
                "{ray:?}"
            );
            compared += 1;
        }
        assert!(compared > rays.len() / 2, "{compared} rays compared");
    }
}
