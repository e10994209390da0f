//! The batch traversal with eight rays to an AVX2 vector, or sixteen to an
//! AVX-512 vector.
//!
//! [`trace_lanes`] is what [`Tracer::trace_lanes`] runs where the processor
//! has AVX2 (checked at run time). Every ray goes through the very same steps
//! as [`Tracer::resume`], computed with the very same f32 operations (no fused
//! multiply-adds), so the answers are identical to [`Tracer::trace`]; only the
//! bookkeeping differs:
//!
//! - A [`Group`] holds eight rays in structure-of-arrays form. One call of
//!   [`step`] advances every busy ray of a group by one step: the visit of a
//!   node (its header gathered, the plane parameters and the `CHAIN` key
//!   computed for all eight at once); when no child is left, the step back to
//!   the nearest ancestor with children left, at once (a per-lane bit mask of
//!   the levels whose frames have children left finds it; the scalar walk
//!   climbs one level at a time through the same frames); then the choice of
//!   the next child (`FIRST`), its rank (popcount) and its pointer (gathered).
//! - Where the processor has AVX-512 ([`wide_available`], [`crate::Lanes`]),
//!   a group holds sixteen rays and [`step_wide`] advances them with the
//!   same operations per lane on 512-bit vectors; two such groups take
//!   turns (`WIDE_GROUPS`). Why it pays: a step is one chain of dependent
//!   reads (header, then stack frames, `FIRST` entry and pointer, each
//!   waiting on the one before), and the eight-lane steps were not bound by
//!   memory: on an Intel Xeon a lane's step took 16.5 ns in a 1 MB DAG that
//!   stays in the L2 cache and 18.1 ns in a 14 MB one. Sixteen lanes do the
//!   same chain and about the same instructions for twice the rays: d12
//!   random rays in 0.76–0.80 of the time (dagtrace/BENCHMARKS.md).
//! - Four groups take turns (each group's scalar work, then its step), and
//!   the node each ray goes to next is prefetched, so the memory latency of
//!   one group's reads is spent on the other groups (32 reads in flight;
//!   with two groups, d12 random rays took 7–8 % more time and d14 tiles
//!   10 % more, for the same instructions, on an Intel Xeon with 2 MB of L2
//!   per core). DAGs small enough to stay in the caches take two groups
//!   (`SMALL_DAG_GROUPS`): there more only cost bookkeeping.
//! - Rays are set up four at a time in `f64` vectors ([`setup4`]), with the
//!   very same operations as [`Tracer::setup`], when they are usual (full
//!   depth, finite, no far origin, no direction component treated as zero).
//! - The line of the hit of the ray 64 rays on is prefetched for writing
//!   whenever a ray is handed out (`HITS_AHEAD`).
//! - The six reads of eight lanes' words a step (header, two stack words,
//!   `CHAIN` and `FIRST` entries, pointer) are AVX2 gather instructions, or,
//!   on processors whose gathers are microcoded and slow (AMD's Zen 1 and 2:
//!   [`crate::cpu::slow_gathers`]), eight scalar loads put together ([`gather`],
//!   [`crate::Gathers`]). Both are compiled (`run`'s `LOADS`), and the tests
//!   check both on every processor with AVX2.
//! - What is rare or branchy stays scalar, done by the tracer's own functions
//!   for one ray at a time: the set-up of unusual rays ([`Tracer::begin`]),
//!   the 4³ brick at the end of a descent ([`Tracer::brick`]), the answer
//!   ([`Tracer::finish`]), and pointers whose 32-bit load would leave the
//!   file or that lie outside their section (`Sections::fast_limit`).
//! - A read outside its level (a malformed file) or any error stops the
//!   vector traversal, and the whole batch is traced again by
//!   [`Tracer::trace_lanes_scalar`], which reports the error exactly as it
//!   always does.
//!
//! Gathers address all level sections from one base pointer with 32-bit
//! offsets, so files whose sections span more than 2 GiB use the scalar lanes.
//!
//! The sixteen-lane code is [`step`]'s, instruction for instruction, in
//! 512-bit form with mask registers (a comparison gives a `__mmask16`, not a
//! vector of all-ones lanes); `run` is shared through [`StepLanes`]. The
//! tests run every path, eight and sixteen lanes (where the processor has
//! AVX-512), gather instruction and scalar loads, against `trace()`.
//!
//! The lanes gather the DAG's words themselves, but what the words mean (the
//! child mask in a header, where a child's reference lies and how wide it
//! is) comes from `node::lanes`, the vector forms of `node`, the tracer's
//! one decoding module; references the vector step cannot read are read by
//! `node::Level::reference_or_fault` in the scalar tail.
//!
//! Format 2.0 (spec §23) runs in the eight lanes, [`step`] compiled with
//! `V2` (1.0's copy has none of it): each lane carries the accumulated
//! reflection R of its node and traces it in octant `neg ^ R` (the
//! `CHAIN` and `FIRST` keys, the child's corner), R goes into the frame's
//! last byte (`Frame::reflection`), node addresses are byte offsets, and
//! [`v2_reference`] decodes the chosen child's reference with
//! `node::lanes::Avx2`'s 2.0 forms (three to four gathers; a sequential
//! child of a node level from the child level's record starts,
//! `node::RecordStarts`, lane by lane, else two gathers per sequential
//! sibling before it); references near their section's end, or wider than
//! 32 bits, go to `node::Level::child_or_fault` in the scalar tail. The
//! sixteen lanes ([`step_wide`] with `V2`) trace 2.0 likewise, decoding a
//! reference with [`v2_reference`] on each half of their lanes. A 2.0 DAG
//! traced through its expanded levels (spec §23.12, `Sections::expanded`:
//! the tracer holds them and a copy of the leaf level in one allocation,
//! addressed from one base) runs the same `V2` steps, but a child's
//! reference is one gathered word ([`expanded_reference`], in 512-bit form
//! in [`step_wide`]), decoded by `node::lanes`' expanded forms.
//!
//! Left to do: `step` and `step_wide` still repeat each other's ~250 lines
//! in 256- and 512-bit intrinsics (their 2.0 reference decoding is shared:
//! `v2_reference`). Writing them once (a lane-width trait whose two forms
//! wrap the intrinsics, inlined into `run` and `run_wide`) was not done
//! when the sixteen-lane path was written, on a machine without AVX-512;
//! its 2.0 copy was written and tested on one with it (an Intel Xeon).

use std::arch::x86_64::*;

use dagfmt::batch::{Hit, Ray};
use glam::{BVec3A, Vec3A};

use crate::cpu::wide_available;
use crate::node::HEADER_BYTES;
use crate::node::lanes::{Avx2, Avx512, HEADER_SHIFT, LEAF_SHIFT};
use crate::tables::{CHAIN_PADDED, FIRST_PADDED};
use crate::walk::{
    Begun, Cell, Frame, LEVEL_SLOTS, Prepared, Stack, TINY_DIRECTION, TraceError, Tracer, Walk,
    prefetch_address,
};

/// Rays to an AVX2 vector.
const W: usize = 8;
/// Rays to an AVX-512 vector: the wide lanes.
const WIDE: usize = 16;
/// Groups of [`WIDE`] rays in flight, for every DAG: on an Intel Xeon
/// (AVX-512, 2 MB of L2 a core), three groups took 0.98–0.99 of two's time
/// for random rays at d12 and d14 (within the noise), and one group 1.01 of
/// two's at d10 (a 1 MB DAG, every one of eight alternating rounds slower).
const WIDE_GROUPS: usize = 2;
/// Groups of [`W`] rays in flight, taking turns, for DAGs larger than
/// [`crate::walk::SMALL_DAG_BYTES`].
const GROUPS: usize = 4;
/// Groups of [`W`] rays in flight for the small DAGs, which mostly stay in
/// the caches.
const SMALL_DAG_GROUPS: usize = 2;

/// What a lane of a group is doing: the values of [`Group::state`].
mod state {
    /// No ray.
    pub const IDLE: i32 = 0;
    /// To visit the node `target` of `level`.
    pub const VISIT: i32 = 1;
    /// Stands on the node of `level`, whose `word`, `mask` and `remaining`
    /// children are in the lane.
    pub const CONT: i32 = 2;
    /// To test the brick (leaf mask `target`) at `brick` below the node of
    /// `level` (scalar, [`super::Tracer::brick`]); then `CONT`.
    pub const BRICK: i32 = 3;
    /// Found: the cell at `brick` of the ray's level, leaf `target`.
    pub const FOUND: i32 = 4;
    /// No occupied cell on the ray.
    pub const MISS: i32 = 5;
}

/// Entries of the per-level tables, more than the most stored levels (20):
/// four AVX2 vectors (the eight lanes read the first three) or two AVX-512
/// vectors.
const LEVEL_TABLE: usize = 32;

/// The level sections as gathers address them: byte offsets from one base.
struct Sections {
    base: *const u8,
    /// Depth D of the DAG.
    depth: i32,
    /// Per level: byte offset of the section from `base`.
    offset: [i32; LEVEL_TABLE],
    /// Per level: section length in bytes.
    len: [i32; LEVEL_TABLE],
    /// Per level: pointer width in bytes.
    width: [i32; LEVEL_TABLE],
    /// Per level: the largest byte offset in the section of a pointer that
    /// one 32-bit gather reads: the pointer inside the section and the four
    /// bytes inside the file (`Level::readable`). -1 when there is none.
    /// Pointers past it are read by the scalar `Level::pointer_or_fault`,
    /// which also reports the ones outside the section. (With the section's
    /// own end as the limit, d12 random rays sent 4 % of their pointers,
    /// those of the small top levels, down the scalar path.)
    fast_limit: [i32; LEVEL_TABLE],
    /// Per level: the node addresses below it have a whole header in the
    /// section (1.0: `len / 4` words; 2.0: `len - 3` bytes).
    nodes: [i32; LEVEL_TABLE],
    /// 2.0, per level: the byte offsets below it have eight readable bytes
    /// (in the section or the file after it, `Level::readable`): the lanes
    /// gather the 32 bits after a header, and a reference's 64 bits, there,
    /// and check that what they decode lies in the section (`len`); the
    /// scalar `Level::child_or_fault` reads the others.
    v2_end: [i32; LEVEL_TABLE],
    /// 2.0, per level: the widths w_1, w_2, w_3 of its references.
    v2_width: [[i32; LEVEL_TABLE]; 3],
    /// Whether the 2.0 node levels are expanded (spec §23.12): a child's
    /// reference is then one word, read by [`expanded_reference`].
    expanded: bool,
    /// Expanded levels, per level: the shift from a reference's index to
    /// the child's address (`node::Level::expanded_shift`).
    expanded_shift: [i32; LEVEL_TABLE],
    /// The leaf level.
    leaf_level: i32,
    /// An offset from `base` with eight readable bytes (the first leaf):
    /// where the lanes out of a [`gather_pair`] with `LOADS` read.
    spare: i32,
}

impl Sections {
    /// `None` when the sections cannot be addressed with 32-bit offsets.
    fn new(tracer: &Tracer<'_>) -> Option<Sections> {
        let used = &tracer.levels[..=usize::from(tracer.leaf_level)];
        let base = used
            .iter()
            .filter(|l| !l.bytes.is_empty())
            .map(|l| l.bytes.as_ptr())
            .min()?;
        let mut s = Sections {
            base,
            depth: i32::from(tracer.depth),
            offset: [0; LEVEL_TABLE],
            len: [0; LEVEL_TABLE],
            width: [0; LEVEL_TABLE],
            fast_limit: [-1; LEVEL_TABLE],
            nodes: [0; LEVEL_TABLE],
            v2_end: [0; LEVEL_TABLE],
            v2_width: [[0; LEVEL_TABLE]; 3],
            expanded: tracer.v2 && used[0].expanded_shift().is_some(),
            expanded_shift: [0; LEVEL_TABLE],
            leaf_level: i32::from(tracer.leaf_level),
            spare: 0,
        };
        for (l, level) in used.iter().enumerate() {
            if level.bytes.is_empty() {
                continue;
            }
            let offset = level.bytes.as_ptr() as usize - base as usize;
            // Room for a pointer read of up to 32 bytes past a valid header.
            if offset + level.bytes.len() > i32::MAX as usize - 64 {
                return None;
            }
            s.offset[l] = offset as i32;
            s.len[l] = level.bytes.len() as i32;
            s.width[l] = level.width as i32;
            let in_section = level.bytes.len() as i64 - i64::from(level.width);
            // (At most 64 bytes past the section: the room checked above.)
            let in_file = level.readable.len().min(level.bytes.len() + 64) as i64 - 4;
            s.fast_limit[l] = in_section.min(in_file).max(-1) as i32;
            let len = level.bytes.len() as i32;
            s.nodes[l] = if tracer.v2 {
                (len - 3).max(0)
            } else {
                len >> 2
            };
            // (At most 64 bytes past the section: the room checked above.)
            let readable = level.readable.len().min(level.bytes.len() + 64) as i32;
            s.v2_end[l] = (readable - 7).max(0);
            for (j, w) in level.v2_widths().into_iter().enumerate() {
                s.v2_width[j][l] = w;
            }
            s.expanded_shift[l] = level.expanded_shift().unwrap_or(0) as i32;
        }
        if tracer.v2 {
            let leaves = &used[used.len() - 1];
            if leaves.bytes.len() < 8 {
                return None;
            }
            s.spare = s.offset[used.len() - 1];
        }
        Some(s)
    }
}

/// `W` rays in flight (eight, or sixteen for the wide lanes): the vector
/// state (one array element per lane) and, for the scalar parts, each ray's
/// walk and stack.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Group<const W: usize> {
    // The ray (mirrored grid frame, clipped), as in `Prepared`.
    ox: [f32; W],
    oy: [f32; W],
    oz: [f32; W],
    ix: [f32; W],
    iy: [f32; W],
    iz: [f32; W],
    tmin: [f32; W],
    tmax: [f32; W],
    // Lower corner and edge of the node of `level`.
    px: [f32; W],
    py: [f32; W],
    pz: [f32; W],
    size: [f32; W],
    // Lower corner of the brick or found cell (in the lanes that are `BRICK`
    // or `FOUND`; the others hold the corner of their last child).
    bx: [f32; W],
    by: [f32; W],
    bz: [f32; W],
    neg: [i32; W],
    /// Level where the descent stops (`Walk::stop`).
    stop: [i32; W],
    /// -1 when `stop` is the ray's level (the cell there is the answer),
    /// 0 when it is the leaf level above a finer ray level (a brick to test).
    report: [i32; W],
    level: [i32; W],
    target: [i32; W],
    state: [i32; W],
    // The node the lane stands on: word, child mask, children left.
    word: [i32; W],
    mask: [i32; W],
    remaining: [i32; W],
    /// Bit `l` set when the frame of level `l` on the path has children left.
    pending: [i32; W],
    /// The accumulated reflection R (spec §23.4; 0 in 1.0) of the node the
    /// lane stands on, and of `target`.
    reflection: [i32; W],
    target_reflection: [i32; W],
    /// Each ray as the scalar parts take it: clipped (`Walk::q`), and its
    /// own `tmin` (`Walk::ray_tmin`). The rest of its `Walk` lives in the
    /// vectors above.
    prepared: [Prepared; W],
    ray_tmin: [f32; W],
    stacks: [Stack; W],
    ray: [usize; W],
}

impl<const W: usize> Default for Group<W> {
    fn default() -> Self {
        Group {
            ox: [0.0; W],
            oy: [0.0; W],
            oz: [0.0; W],
            ix: [0.0; W],
            iy: [0.0; W],
            iz: [0.0; W],
            tmin: [0.0; W],
            tmax: [0.0; W],
            px: [0.0; W],
            py: [0.0; W],
            pz: [0.0; W],
            size: [0.0; W],
            bx: [0.0; W],
            by: [0.0; W],
            bz: [0.0; W],
            neg: [0; W],
            stop: [0; W],
            report: [0; W],
            level: [0; W],
            target: [0; W],
            state: [state::IDLE; W],
            word: [0; W],
            mask: [0; W],
            remaining: [0; W],
            pending: [0; W],
            reflection: [0; W],
            target_reflection: [0; W],
            prepared: [Prepared::default(); W],
            ray_tmin: [0.0; W],
            stacks: [Stack::default(); W],
            ray: [0; W],
        }
    }
}

impl<const W: usize> Group<W> {
    /// Puts the walk of ray `ray` into `lane` (its stack was filled by
    /// [`Tracer::begin`]).
    fn load(&mut self, lane: usize, ray: usize, walk: Walk) {
        let q = &walk.q;
        self.ox[lane] = q.origin.x;
        self.oy[lane] = q.origin.y;
        self.oz[lane] = q.origin.z;
        self.ix[lane] = q.inv_dir.x;
        self.iy[lane] = q.inv_dir.y;
        self.iz[lane] = q.inv_dir.z;
        self.tmin[lane] = q.tmin;
        self.tmax[lane] = q.tmax;
        self.px[lane] = walk.pos.x;
        self.py[lane] = walk.pos.y;
        self.pz[lane] = walk.pos.z;
        self.size[lane] = walk.size;
        self.neg[lane] = (q.neg & 7) as i32;
        self.stop[lane] = i32::from(walk.stop);
        self.report[lane] = if walk.stop == q.level { -1 } else { 0 };
        self.level[lane] = i32::from(walk.level);
        self.target[lane] = walk.target as i32;
        self.target_reflection[lane] = i32::from(walk.reflection);
        self.state[lane] = state::VISIT;
        self.pending[lane] = 0;
        self.prepared[lane] = walk.q;
        self.ray_tmin[lane] = walk.ray_tmin;
        self.ray[lane] = ray;
    }
}

/// Why the vector traversal gave up on a batch.
struct Abandon;

/// [`Tracer::trace_lanes`] with eight rays to a vector. Call only where
/// [`crate::cpu::available`] is true.
pub(crate) fn trace_lanes(
    tracer: &Tracer<'_>,
    rays: &[Ray],
    hits: &mut [Hit],
) -> Result<(), TraceError> {
    // A fault or an error (or sections that 32-bit offsets cannot address):
    // trace the batch again one ray at a time, which reports the first error
    // met exactly as it always does.
    try_trace_lanes(tracer, rays, hits).or_else(|Abandon| tracer.trace_lanes_scalar(rays, hits))
}

/// [`trace_lanes`] without the scalar fallback.
fn try_trace_lanes(tracer: &Tracer<'_>, rays: &[Ray], hits: &mut [Hit]) -> Result<(), Abandon> {
    let how = LaneChoice {
        small: tracer.small,
        loads: tracer.gather_loads,
        wide: tracer.wide_lanes,
    };
    try_trace_lanes_with(tracer, rays, hits, how)
}

/// How [`try_trace_lanes_with`] runs the lanes.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LaneChoice {
    /// The small DAGs' number of groups of eight lanes, or the others'
    /// (sixteen lanes take [`WIDE_GROUPS`] for every DAG).
    pub(crate) small: bool,
    /// Scalar loads, or the gather instruction.
    pub(crate) loads: bool,
    /// Sixteen lanes (where [`wide_available`]), or eight.
    pub(crate) wide: bool,
}

/// [`try_trace_lanes`] run as `how` says.
fn try_trace_lanes_with(
    tracer: &Tracer<'_>,
    rays: &[Ray],
    hits: &mut [Hit],
    how: LaneChoice,
) -> Result<(), Abandon> {
    let sections = Sections::new(tracer).ok_or(Abandon)?;
    if tracer.v2 {
        // A 2.0 DAG (spec §23): the steps' `V2` copies decode its records.
        if how.wide && wide_available() {
            // SAFETY: `wide_available()` found the features.
            return unsafe {
                if how.loads {
                    run_wide::<WIDE_GROUPS, true, true>(tracer, &sections, rays, hits)
                } else {
                    run_wide::<WIDE_GROUPS, false, true>(tracer, &sections, rays, hits)
                }
            };
        }
        // SAFETY: only called where `available()` found the features.
        return unsafe {
            match (how.small, how.loads) {
                (true, false) => {
                    run::<SMALL_DAG_GROUPS, false, true>(tracer, &sections, rays, hits)
                }
                (true, true) => run::<SMALL_DAG_GROUPS, true, true>(tracer, &sections, rays, hits),
                (false, false) => run::<GROUPS, false, true>(tracer, &sections, rays, hits),
                (false, true) => run::<GROUPS, true, true>(tracer, &sections, rays, hits),
            }
        };
    }
    if how.wide && wide_available() {
        // SAFETY: `wide_available()` found the features.
        return unsafe {
            if how.loads {
                run_wide::<WIDE_GROUPS, true, false>(tracer, &sections, rays, hits)
            } else {
                run_wide::<WIDE_GROUPS, false, false>(tracer, &sections, rays, hits)
            }
        };
    }
    // SAFETY: only called where `available()` found the features.
    unsafe {
        match (how.small, how.loads) {
            (true, false) => run::<SMALL_DAG_GROUPS, false, false>(tracer, &sections, rays, hits),
            (true, true) => run::<SMALL_DAG_GROUPS, true, false>(tracer, &sections, rays, hits),
            (false, false) => run::<GROUPS, false, false>(tracer, &sections, rays, hits),
            (false, true) => run::<GROUPS, true, false>(tracer, &sections, rays, hits),
        }
    }
}

/// [`trace_lanes`] without the scalar fallback, run as `how` says whatever
/// the DAG's size and the tracer's choices (sixteen lanes only where
/// [`wide_available`]): `false` when the vector traversal gave up (on valid
/// DAGs it never should).
#[cfg(test)]
pub(crate) fn trace_lanes_or_give_up(
    tracer: &Tracer<'_>,
    rays: &[Ray],
    hits: &mut [Hit],
    how: LaneChoice,
) -> bool {
    try_trace_lanes_with(tracer, rays, hits, how).is_ok()
}

/// A group's step: [`step`] for eight lanes, [`step_wide`] for sixteen.
trait StepLanes {
    /// One step of every busy lane of the group: the lanes that now need
    /// scalar work.
    ///
    /// # Safety
    ///
    /// The processor must have the features of the step function (AVX2,
    /// and AVX-512 for sixteen lanes).
    unsafe fn step<const LOADS: bool, const V2: bool>(
        &mut self,
        tracer: &Tracer<'_>,
        sections: &Sections,
    ) -> Result<u32, Abandon>;
}

impl StepLanes for Group<W> {
    #[inline(always)]
    unsafe fn step<const LOADS: bool, const V2: bool>(
        &mut self,
        tracer: &Tracer<'_>,
        sections: &Sections,
    ) -> Result<u32, Abandon> {
        // SAFETY: the caller's.
        unsafe { step::<LOADS, V2>(tracer, sections, self) }
    }
}

impl StepLanes for Group<WIDE> {
    #[inline(always)]
    unsafe fn step<const LOADS: bool, const V2: bool>(
        &mut self,
        tracer: &Tracer<'_>,
        sections: &Sections,
    ) -> Result<u32, Abandon> {
        // SAFETY: the caller's.
        unsafe { step_wide::<LOADS, V2>(tracer, sections, self) }
    }
}

/// [`run_groups`] with eight lanes to a group, compiled for AVX2.
#[target_feature(enable = "avx2,bmi1,bmi2,popcnt,lzcnt,fma")]
unsafe fn run<const G: usize, const LOADS: bool, const V2: bool>(
    tracer: &Tracer<'_>,
    sections: &Sections,
    rays: &[Ray],
    hits: &mut [Hit],
) -> Result<(), Abandon> {
    // SAFETY: compiled with the features `step` needs.
    unsafe { run_groups::<W, G, LOADS, V2>(tracer, sections, rays, hits) }
}

/// [`run_groups`] with sixteen lanes to a group, compiled for AVX-512 (and
/// AVX2 for the code they share with eight lanes).
#[target_feature(
    enable = "avx512f,avx512bw,avx512vl,avx512dq,avx512cd,avx2,bmi1,bmi2,popcnt,lzcnt,fma"
)]
unsafe fn run_wide<const G: usize, const LOADS: bool, const V2: bool>(
    tracer: &Tracer<'_>,
    sections: &Sections,
    rays: &[Ray],
    hits: &mut [Hit],
) -> Result<(), Abandon> {
    // SAFETY: compiled with the features `step_wide` needs.
    unsafe { run_groups::<WIDE, G, LOADS, V2>(tracer, sections, rays, hits) }
}

/// The vector traversal of `rays` into `hits`: `G` groups of `N` lanes step
/// in turn, and between their steps the lanes they flagged get their scalar
/// work (a brick test, an answer, a new ray). `Err` when a fault or an error
/// stopped it.
///
/// # Safety
///
/// The processor must have the features of `Group<N>`'s step; inlined into
/// [`run`] and [`run_wide`], which are compiled with them.
#[inline(always)]
unsafe fn run_groups<const N: usize, const G: usize, const LOADS: bool, const V2: bool>(
    tracer: &Tracer<'_>,
    sections: &Sections,
    rays: &[Ray],
    hits: &mut [Hit],
) -> Result<(), Abandon>
where
    Group<N>: StepLanes,
{
    const { assert!(N <= 32) };
    let mut groups = [Group::<N>::default(); G];
    let count = rays.len().min(hits.len());
    let mut ahead = Ahead::default();
    // Per group: the lanes that need scalar work (an answer, a brick, a new ray).
    let mut attention = [(1u32 << N) - 1; G];
    let mut busy = [0u32; G];
    loop {
        for (g, group) in groups.iter_mut().enumerate() {
            let mut lanes = attention[g];
            while lanes != 0 {
                let lane = lanes.trailing_zeros() as usize;
                lanes &= lanes - 1;
                // The answer of a lane that is done (`None` for an idle lane).
                let answer: Option<Option<Cell>> = match group.state[lane] {
                    state::BRICK => {
                        let leaf = group.target[lane] as u32;
                        let at = Vec3A::new(group.bx[lane], group.by[lane], group.bz[lane]);
                        let mut fault = None;
                        let reflection = group.target_reflection[lane] as u8;
                        let found =
                            tracer.brick(&group.prepared[lane], leaf, reflection, at, &mut fault);
                        if fault.is_some() {
                            return Err(Abandon);
                        }
                        match found {
                            Some((cell, level)) => Some(Some((cell, level, leaf))),
                            None => {
                                group.state[lane] = state::CONT;
                                continue;
                            }
                        }
                    }
                    state::FOUND => {
                        let at = Vec3A::new(group.bx[lane], group.by[lane], group.bz[lane]);
                        Some(Some((
                            at,
                            group.stop[lane] as u8,
                            group.target[lane] as u32,
                        )))
                    }
                    state::MISS => Some(None),
                    // Idle: only at the start (steps flag the three states above).
                    other => {
                        debug_assert_eq!(other, state::IDLE);
                        None
                    }
                };
                if let Some(cell) = answer {
                    let ray = Prepared {
                        tmin: group.ray_tmin[lane],
                        ..group.prepared[lane]
                    };
                    hits[group.ray[lane]] = tracer
                        .finish(&ray, cell, &group.stacks[lane], None)
                        .map_err(|_| Abandon)?;
                }
                // A new ray for the lane, if any is left.
                group.state[lane] = state::IDLE;
                busy[g] &= !(1 << lane);
                refill(tracer, group, lane, &mut ahead, &rays[..count], hits)?;
                if group.state[lane] != state::IDLE {
                    busy[g] |= 1 << lane;
                }
            }
            // The group's step right after its scalar work, so that every
            // group's next scalar work comes the same G - 1 steps after
            // its step: time for the leaf masks prefetched for its bricks to
            // arrive. (With the scalar work of all groups, then a step of
            // each, the last group's bricks came right after its step; d12
            // random rays took 7 % more time, alternating frames in one
            // process.)
            attention[g] = if busy[g] == 0 {
                0
            } else {
                // SAFETY: the caller's: the processor has the step's features.
                unsafe { group.step::<LOADS, V2>(tracer, sections) }?
            };
        }
        if busy.iter().all(|&b| b == 0) {
            return Ok(());
        }
    }
}

/// How many rays ahead of the one it hands out [`refill`] prefetches the
/// line of a hit, for writing.
const HITS_AHEAD: usize = 64;

/// Rays set up ahead, four at a time ([`setup4`]), for [`refill`].
#[derive(Default)]
struct Ahead {
    /// Index of the first ray of the block.
    first: usize,
    /// Rays in the block, and how many of them were handed out.
    len: usize,
    taken: usize,
    /// Bit `k`: ray `first + k` was set up in `prepared[k]`; the others go
    /// through the scalar [`Tracer::begin`].
    usual: u32,
    prepared: [Prepared; 4],
}

/// Gives `lane` the next ray that needs a traversal, answering on the spot
/// those that do not; leaves it idle when the rays run out.
#[inline(always)]
fn refill<const N: usize>(
    tracer: &Tracer<'_>,
    group: &mut Group<N>,
    lane: usize,
    ahead: &mut Ahead,
    rays: &[Ray],
    hits: &mut [Hit],
) -> Result<(), Abandon> {
    loop {
        if ahead.taken == ahead.len {
            let first = ahead.first + ahead.len;
            if first >= rays.len() {
                return Ok(());
            }
            let len = (rays.len() - first).min(4);
            ahead.first = first;
            ahead.len = len;
            ahead.taken = 0;
            ahead.usual = 0;
            if let Some(block) = rays[first..].first_chunk::<4>()
                && !tracer.empty
            {
                // SAFETY: `trace_lanes` is only called where `available()`
                // found AVX2.
                ahead.usual = unsafe { setup4(tracer, block, &mut ahead.prepared) };
            }
        }
        let k = ahead.taken;
        ahead.taken += 1;
        let i = ahead.first + k;
        // The hits of the rays handed out next are written soon: fetch their
        // lines, for writing, now. A large batch's hits (40 bytes each) are
        // not in the caches, and without this the stores right after a hit's
        // (those of `Group::load`) took 5 % of d12 random rays' time (perf
        // samples), held up behind it; with it 1.7 %, and the batch took
        // 5.6 % less time (alternating frames in one process).
        // Only inside the batch: past its end, the hits may be another
        // thread's, whose lines a prefetch for writing would take from it.
        let later = (i + HITS_AHEAD).min(rays.len() - 1);
        // SAFETY: a prefetch never faults, whatever the address.
        unsafe { _mm_prefetch::<_MM_HINT_ET0>(hits.as_ptr().wrapping_add(later).cast()) };
        let mut fault = None;
        let stack = &mut group.stacks[lane];
        let begun = if ahead.usual >> k & 1 == 1 {
            tracer.begin_prepared(&ahead.prepared[k & 3], stack, &mut fault)
        } else {
            tracer.begin(&rays[i], stack, &mut fault)
        };
        match begun.map_err(|_| Abandon)? {
            Begun::Done(hit) => hits[i] = hit,
            Begun::Walk(walk) => {
                group.load(lane, i, walk);
                return Ok(());
            }
        }
    }
}

/// [`Tracer::setup`] of four rays at once, in `f64` vectors with the very
/// same operations, for the usual rays: full depth, ordered finite bounds,
/// finite origin not far from the cube, and no direction component small
/// enough to be treated as zero. Writes the prepared ray of each usual ray
/// (exactly what `setup` gives) and returns them as a bit mask; the others
/// are left to `setup`.
///
/// # Safety
///
/// The processor must have AVX2.
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn setup4(tracer: &Tracer<'_>, rays: &[Ray; 4], out: &mut [Prepared; 4]) -> u32 {
    let f = |get: &dyn Fn(&Ray) -> f32| {
        _mm256_setr_pd(
            f64::from(get(&rays[0])),
            f64::from(get(&rays[1])),
            f64::from(get(&rays[2])),
            f64::from(get(&rays[3])),
        )
    };
    let o = [
        f(&|r| r.origin[0]),
        f(&|r| r.origin[1]),
        f(&|r| r.origin[2]),
    ];
    let d = [f(&|r| r.dir[0]), f(&|r| r.dir[1]), f(&|r| r.dir[2])];
    let (tmin, tmax) = (f(&|r| r.tmin), f(&|r| r.tmax));
    let full_depth = rays
        .iter()
        .enumerate()
        .fold(0, |m, (k, r)| m | u32::from(r.level.is_none()) << k);

    let scale = _mm256_set1_pd(tracer.grid_scale);
    let origin: [__m256d; 3] = std::array::from_fn(|a| {
        _mm256_mul_pd(
            _mm256_sub_pd(o[a], _mm256_set1_pd(tracer.root_min[a])),
            scale,
        )
    });
    let dir = d.map(|d| _mm256_mul_pd(d, scale));
    let abs = |v: __m256d| _mm256_andnot_pd(_mm256_set1_pd(-0.0), v);
    let resolution = (1u64 << tracer.depth) as f64;
    let largest = _mm256_max_pd(_mm256_max_pd(abs(dir[0]), abs(dir[1])), abs(dir[2]));
    // Every test is written so that a NaN fails it.
    let mut usual = _mm256_cmp_pd::<_CMP_LE_OQ>(tmin, tmax);
    let below = |v: __m256d, limit: f64| _mm256_cmp_pd::<_CMP_LT_OQ>(v, _mm256_set1_pd(limit));
    for a in 0..3 {
        // Finite and not far: |o| <= 16 cube sizes (so `setup` does not re-base).
        let near = _mm256_cmp_pd::<_CMP_LE_OQ>(abs(origin[a]), _mm256_set1_pd(resolution * 16.0));
        // Not treated as zero: |d| >= largest * TINY_DIRECTION.
        let moving = _mm256_cmp_pd::<_CMP_GE_OQ>(
            abs(dir[a]),
            _mm256_mul_pd(largest, _mm256_set1_pd(TINY_DIRECTION)),
        );
        usual = _mm256_and_pd(usual, _mm256_and_pd(near, moving));
        usual = _mm256_and_pd(usual, below(abs(dir[a]), f64::INFINITY));
    }
    // A largest component that is normal and whose power-of-two scale has
    // an inverse (exponent 1 ..= 2045), as in `prepare`.
    usual = _mm256_and_pd(
        usual,
        _mm256_cmp_pd::<_CMP_GE_OQ>(largest, _mm256_set1_pd(f64::MIN_POSITIVE)),
    );
    usual = _mm256_and_pd(usual, below(largest, f64::from_bits(2046 << 52)));
    let usual = _mm256_movemask_pd(usual) as u32 & full_depth;
    if usual == 0 {
        return 0;
    }

    // `prepare`, with base 0.
    let scale_bits = _mm256_and_si256(
        _mm256_castpd_si256(largest),
        _mm256_set1_epi64x(0x7ff0_0000_0000_0000),
    );
    let exponent = _mm256_srli_epi64::<52>(scale_bits);
    let inv_scale = _mm256_castsi256_pd(_mm256_slli_epi64::<52>(_mm256_sub_epi64(
        _mm256_set1_epi64x(2046),
        exponent,
    )));
    let scale = _mm256_castsi256_pd(scale_bits);
    let scaled = dir.map(|d| _mm256_mul_pd(abs(d), inv_scale));
    let reciprocal = _mm256_div_pd(
        _mm256_set1_pd(1.0),
        _mm256_mul_pd(_mm256_mul_pd(scaled[0], scaled[1]), scaled[2]),
    );
    let inverse = [
        _mm256_mul_pd(_mm256_mul_pd(reciprocal, scaled[1]), scaled[2]),
        _mm256_mul_pd(_mm256_mul_pd(reciprocal, scaled[0]), scaled[2]),
        _mm256_mul_pd(_mm256_mul_pd(reciprocal, scaled[0]), scaled[1]),
    ];
    let mut neg = [0u32; 4];
    let mut o32 = [[0f32; 4]; 3];
    let mut inv32 = [[0f32; 4]; 3];
    for a in 0..3 {
        // origin + base * dir with base 0, then mirrored where dir < 0.
        let o = _mm256_add_pd(origin[a], _mm256_mul_pd(_mm256_setzero_pd(), dir[a]));
        let negative = _mm256_cmp_pd::<_CMP_LT_OQ>(dir[a], _mm256_setzero_pd());
        let o = _mm256_blendv_pd(o, _mm256_sub_pd(_mm256_set1_pd(resolution), o), negative);
        let bits = _mm256_movemask_pd(negative) as u32;
        for (k, n) in neg.iter_mut().enumerate() {
            *n |= (bits >> k & 1) << a;
        }
        // SAFETY: stores of four floats into four-float arrays.
        unsafe {
            _mm_storeu_ps(o32[a].as_mut_ptr(), _mm256_cvtpd_ps(o));
            _mm_storeu_ps(inv32[a].as_mut_ptr(), _mm256_cvtpd_ps(inverse[a]));
        }
    }
    let mut t = [[0f32; 4]; 2];
    let mut inv_scales = [0f64; 4];
    // SAFETY: stores of four values into four-value arrays.
    unsafe {
        _mm_storeu_ps(
            t[0].as_mut_ptr(),
            _mm256_cvtpd_ps(_mm256_mul_pd(tmin, scale)),
        );
        _mm_storeu_ps(
            t[1].as_mut_ptr(),
            _mm256_cvtpd_ps(_mm256_mul_pd(tmax, scale)),
        );
        _mm256_storeu_pd(inv_scales.as_mut_ptr(), inv_scale);
    }
    for (k, p) in out.iter_mut().enumerate() {
        *p = Prepared {
            origin: Vec3A::new(o32[0][k], o32[1][k], o32[2][k]),
            inv_dir: Vec3A::new(inv32[0][k], inv32[1][k], inv32[2][k]),
            tmin: t[0][k],
            tmax: t[1][k],
            neg: neg[k] as usize,
            moving: BVec3A::new(true, true, true),
            level: tracer.depth,
            inv_scale: inv_scales[k],
            base: 0.0,
        };
    }
    usual
}

/// What a step of `N` lanes leaves to its scalar tail ([`StepOut::write_back`]),
/// per lane.
struct StepOut<const N: usize> {
    /// The frame of the node the lane stands on, as `Frame`'s eight bytes.
    frame: [u64; N],
    /// Where it goes: its byte offset in the group's stacks.
    frame_at: [i32; N],
    /// Byte offset from the sections' base of the child's header or the
    /// brick's leaf mask, to prefetch.
    fetch: [i32; N],
    /// For the pointers the gather left: the node's word, its level and the
    /// child's rank (stored only when some lane needs them); in 2.0 the
    /// child's physical slot instead of its rank, and the node's mask and
    /// accumulated reflection.
    word: [i32; N],
    level: [i32; N],
    rank: [i32; N],
    mask: [i32; N],
    reflection: [i32; N],
}

impl<const N: usize> StepOut<N> {
    #[inline(always)]
    fn new() -> Self {
        StepOut {
            frame: [0; N],
            frame_at: [0; N],
            fetch: [0; N],
            word: [0; N],
            level: [0; N],
            rank: [0; N],
            mask: [0; N],
            reflection: [0; N],
        }
    }

    /// A step's scalar tail: each lane's frame stored and its next read
    /// prefetched, then the pointers of the lanes in `slow` read one by one
    /// (near the file's end, or outside their section in malformed files;
    /// `V2`: 2.0 references near their section's end or too wide for the
    /// vector decoding, read by `Level::child_or_fault`, which also sets the
    /// child's accumulated reflection).
    ///
    /// # Safety
    ///
    /// `frame_at[lane]` must be `256 * lane + 8 * level` with `level <
    /// LEVEL_SLOTS`, for every lane.
    #[inline(always)]
    unsafe fn write_back<const V2: bool>(
        &self,
        tracer: &Tracer<'_>,
        s: &Sections,
        g: &mut Group<N>,
        slow: u32,
    ) -> Result<(), Abandon> {
        const { assert!(std::mem::size_of::<Stack>() == 256) };
        let stacks: *mut u8 = g.stacks.as_mut_ptr().cast();
        for lane in 0..N {
            // SAFETY: the caller's: the frame of a level < LEVEL_SLOTS in the
            // stack of lane `lane < N` (`Stack` is 256 bytes, `Frame` 8),
            // written as the eight bytes of a `Frame` (`repr(C)`, plain
            // integers).
            unsafe {
                stacks
                    .add(self.frame_at[lane] as usize)
                    .cast::<u64>()
                    .write_unaligned(self.frame[lane]);
            }
            // A prefetch never faults: lanes without a child fetch some byte
            // of the file, and a wrong pointer just fetches a useless line.
            prefetch_address(s.base.wrapping_add(self.fetch[lane] as u32 as usize));
        }
        let mut lanes = slow;
        while lanes != 0 {
            let lane = lanes.trailing_zeros() as usize;
            lanes &= lanes - 1;
            let level = self.level[lane] as usize & (LEVEL_SLOTS - 1);
            let mut fault = None;
            let reference = if V2 {
                tracer.levels[level].child_or_fault::<true>(
                    level as u8,
                    self.word[lane] as u32,
                    self.mask[lane] as u8,
                    self.rank[lane] as u32,
                    &mut fault,
                )
            } else {
                tracer.levels[level].reference_or_fault(
                    level as u8,
                    self.word[lane] as u32,
                    self.rank[lane] as u32,
                    &mut fault,
                )
            };
            if fault.is_some() {
                return Err(Abandon);
            }
            g.target[lane] = reference.node as i32;
            if V2 {
                g.target_reflection[lane] =
                    (self.reflection[lane] ^ i32::from(reference.reflection)) & 7;
            }
        }
        Ok(())
    }
}

macro_rules! ldf {
    ($a:expr) => {
        _mm256_loadu_ps($a.as_ptr())
    };
}
macro_rules! ldi {
    ($a:expr) => {
        _mm256_loadu_si256($a.as_ptr().cast())
    };
}
macro_rules! stf {
    ($a:expr, $v:expr) => {
        _mm256_storeu_ps($a.as_mut_ptr(), $v)
    };
}
macro_rules! sti {
    ($a:expr, $v:expr) => {
        _mm256_storeu_si256($a.as_mut_ptr().cast(), $v)
    };
}

/// One step of every busy lane of `group` (see the module docs). Returns the
/// lanes that now need scalar work (found, missed, or at a brick).
///
/// # Safety
///
/// The processor must have AVX2.
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn step<const LOADS: bool, const V2: bool>(
    tracer: &Tracer<'_>,
    s: &Sections,
    g: &mut Group<W>,
) -> Result<u32, Abandon> {
    let g_ptr: *mut Group<W> = g;
    let mut out = StepOut::<W>::new();
    let (choose_bits, slow_bits, done_bits);
    // SAFETY: the loads and stores are of whole `[_; W]` arrays of the group
    // and of local arrays. Every gather reads only lanes whose mask is set:
    // table entries at in-range indices (`neg` < 8 and keys < 512 or masks <
    // 256 in the padded tables; stack frames of levels < LEVEL_SLOTS of
    // lanes < W), and node words checked against their section's length just
    // before (headers: `target < len / 4`; pointers: `at <= fast_limit`, so
    // the four bytes lie in the file's bytes, `Level::readable`), at
    // offsets from `s.base` that `Sections::new` checked to address the
    // sections. With scalar loads (`LOADS`) the other lanes read the first
    // four bytes at each gather's base instead: the first section's first
    // node or leaf (`s.base` is the start of a non-empty section, and nodes
    // and leaves are at least four bytes), a lane's stack, or a table.
    unsafe {
        let g = &mut *g_ptr;
        let zero = _mm256_setzero_si256();
        let one = _mm256_set1_epi32(1);
        let byte = _mm256_set1_epi32(0xff);
        let base: *const i32 = s.base.cast();
        let tables = |t: &[i32; LEVEL_TABLE]| {
            [0, 8, 16].map(|i| _mm256_loadu_si256(t[i..i + 8].as_ptr().cast()))
        };
        let (offsets, nodes, widths) = (tables(&s.offset), tables(&s.nodes), tables(&s.width));
        let fast_limits = tables(&s.fast_limit);

        let state = ldi!(g.state);
        let visit = _mm256_cmpeq_epi32(state, _mm256_set1_epi32(state::VISIT));
        let cont = _mm256_cmpeq_epi32(state, _mm256_set1_epi32(state::CONT));
        let mut level = ldi!(g.level);
        let target = ldi!(g.target);
        let neg = ldi!(g.neg);
        // 2.0: the accumulated reflection R of the node each lane visits or
        // stands on, which is traced as a 1.0 node in octant `neg ^ R` (spec
        // §23.4, `node`'s docs); 0 in 1.0.
        let mut reflection = if V2 {
            blend(ldi!(g.reflection), ldi!(g.target_reflection), visit)
        } else {
            zero
        };

        // Visit: the header, bounds-checked like `Level::header_or_fault`.
        let inside = lt_u32(target, by_level(&nodes, level));
        if _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_andnot_si256(inside, visit))) != 0 {
            return Err(Abandon);
        }
        // (A 2.0 node's address is its header's byte offset.)
        let header_at = if V2 { target } else { Avx2::header_at(target) };
        let header = gather::<LOADS>(
            zero,
            base,
            _mm256_add_epi32(by_level(&offsets, level), header_at),
            visit,
        );
        let (ox, oy, oz) = (ldf!(g.ox), ldf!(g.oy), ldf!(g.oz));
        let (ix, iy, iz) = (ldf!(g.ix), ldf!(g.iy), ldf!(g.iz));
        let (mut px, mut py, mut pz) = (ldf!(g.px), ldf!(g.py), ldf!(g.pz));
        let mut size = ldf!(g.size);
        let half = _mm256_mul_ps(size, _mm256_set1_ps(0.5));
        // The plane parameters, as `resume` computes them: (p - o) * inv.
        let plane = |p: __m256, o: __m256, i: __m256| _mm256_mul_ps(_mm256_sub_ps(p, o), i);
        let t_lo = [plane(px, ox, ix), plane(py, oy, iy), plane(pz, oz, iz)];
        let t_mid = [
            plane(_mm256_add_ps(px, half), ox, ix),
            plane(_mm256_add_ps(py, half), oy, iy),
            plane(_mm256_add_ps(pz, half), oz, iz),
        ];
        let t_hi = [
            plane(_mm256_add_ps(px, size), ox, ix),
            plane(_mm256_add_ps(py, size), oy, iy),
            plane(_mm256_add_ps(pz, size), oz, iz),
        ];
        let (enter, exit) = segment(t_lo, t_hi, ldf!(g.tmin), ldf!(g.tmax));
        let nonempty = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LE_OQ>(enter, exit));
        // The CHAIN key, as `chain` computes it.
        let le_enter = t_mid.map(|t| _mm256_cmp_ps::<_CMP_LE_OQ>(t, enter));
        let crossing = t_mid.map(|t| {
            _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GT_OQ>(t, enter),
                _mm256_cmp_ps::<_CMP_LE_OQ>(t, exit),
            )
        });
        let order = [
            _mm256_cmp_ps::<_CMP_LT_OQ>(t_mid[0], t_mid[1]),
            _mm256_cmp_ps::<_CMP_LT_OQ>(t_mid[0], t_mid[2]),
            _mm256_cmp_ps::<_CMP_LT_OQ>(t_mid[1], t_mid[2]),
        ];
        let key = _mm256_or_si256(
            _mm256_or_si256(bits3(le_enter), _mm256_slli_epi32::<3>(bits3(crossing))),
            _mm256_slli_epi32::<6>(bits3(order)),
        );
        let chain = table_bytes::<LOADS>(
            &CHAIN_PADDED,
            _mm256_or_si256(
                _mm256_slli_epi32::<9>(_mm256_xor_si256(neg, reflection)),
                key,
            ),
            visit,
        );
        let node_mask = Avx2::child_mask(header);
        let visited = _mm256_and_si256(_mm256_and_si256(chain, node_mask), nonempty);
        let mut word = blend(ldi!(g.word), target, visit);
        let mut mask = blend(ldi!(g.mask), node_mask, visit);
        let mut remaining = blend(ldi!(g.remaining), visited, visit);

        // No child left: back to the nearest node of the path that has
        // children left (the levels with bits in `pending`), at once. The
        // scalar walk steps back one level at a time through the same frames.
        let mut pending = ldi!(g.pending);
        let active = _mm256_or_si256(visit, cont);
        let empty = _mm256_and_si256(active, _mm256_cmpeq_epi32(remaining, zero));
        let above = _mm256_and_si256(
            pending,
            _mm256_sub_epi32(_mm256_sllv_epi32(one, level), one),
        );
        let at_top = _mm256_and_si256(empty, _mm256_cmpeq_epi32(above, zero));
        let pop = _mm256_andnot_si256(at_top, empty);
        // The highest set bit of `above`: the exponent of its (exact) float.
        let highest = _mm256_sub_epi32(
            _mm256_srli_epi32::<23>(_mm256_castps_si256(_mm256_cvtepi32_ps(above))),
            _mm256_set1_epi32(127),
        );
        level = blend(level, highest, pop);
        let lane_bytes = _mm256_setr_epi32(0, 256, 512, 768, 1024, 1280, 1536, 1792);
        const _: () = assert!(std::mem::size_of::<Stack>() == 256);
        const _: () = assert!(std::mem::size_of::<Frame>() == 8);
        let frame_at = _mm256_add_epi32(lane_bytes, _mm256_slli_epi32::<3>(level));
        let stacks: *const i32 = g.stacks.as_ptr().cast();
        word = gather::<LOADS>(word, stacks, frame_at, pop);
        let f_bits = gather::<LOADS>(zero, stacks.add(1), frame_at, pop);
        mask = blend(mask, _mm256_and_si256(f_bits, byte), pop);
        if V2 {
            // `Frame::reflection`, the frame's last byte.
            reflection = blend(reflection, _mm256_srli_epi32::<24>(f_bits), pop);
        }
        let node_neg = _mm256_xor_si256(neg, reflection);
        remaining = blend(
            remaining,
            _mm256_and_si256(_mm256_srli_epi32::<8>(f_bits), byte),
            pop,
        );
        // That node's corner and edge: the corner of the cell of its level
        // that holds the current one (exact integers).
        let edge = _mm256_sllv_epi32(one, _mm256_sub_epi32(_mm256_set1_epi32(s.depth), level));
        let corner = |p: __m256| {
            let cell = _mm256_and_si256(_mm256_cvttps_epi32(p), _mm256_sub_epi32(zero, edge));
            _mm256_blendv_ps(p, _mm256_cvtepi32_ps(cell), _mm256_castsi256_ps(pop))
        };
        px = corner(px);
        py = corner(py);
        pz = corner(pz);
        size = _mm256_blendv_ps(size, _mm256_cvtepi32_ps(edge), _mm256_castsi256_ps(pop));
        let half = _mm256_mul_ps(size, _mm256_set1_ps(0.5));

        // The next child, front to back, and its pointer.
        let choose = _mm256_andnot_si256(at_top, active);
        let child = table_bytes::<LOADS>(
            &FIRST_PADDED,
            _mm256_or_si256(_mm256_slli_epi32::<8>(node_neg), remaining),
            choose,
        );
        let bit = _mm256_and_si256(_mm256_sllv_epi32(one, child), choose);
        remaining = _mm256_andnot_si256(bit, remaining);
        let level_bit = _mm256_sllv_epi32(one, level);
        pending = _mm256_or_si256(
            _mm256_andnot_si256(level_bit, pending),
            _mm256_andnot_si256(_mm256_cmpeq_epi32(remaining, zero), level_bit),
        );
        let rank = popcount8(_mm256_and_si256(mask, _mm256_sub_epi32(bit, one)));
        // The child's reference: its target and (2.0) the reflection it
        // carries; `cut`: the lanes whose reference is read by the scalar
        // tail.
        let (pointer, child_reflection, cut) = if V2 && s.expanded {
            expanded_reference::<LOADS>(s, base, level, word, rank, choose)
        } else if V2 {
            v2_reference::<LOADS>(tracer, s, base, level, word, mask, rank, choose)
        } else {
            let fast_limit = by_level(&fast_limits, level);
            let width = by_level(&widths, level);
            let pointer_mask = Avx2::reference_mask(width);
            let at = Avx2::reference_at(word, rank, width);
            let cut = _mm256_cmpgt_epi32(at, fast_limit);
            let fast = _mm256_andnot_si256(cut, choose);
            let pointer = _mm256_and_si256(
                gather::<LOADS>(
                    zero,
                    base,
                    _mm256_add_epi32(by_level(&offsets, level), at),
                    fast,
                ),
                pointer_mask,
            );
            (pointer, zero, cut)
        };
        let m = axis_masks(_mm256_xor_si256(child, node_neg));
        let cx = _mm256_add_ps(px, _mm256_and_ps(half, m[0]));
        let cy = _mm256_add_ps(py, _mm256_and_ps(half, m[1]));
        let cz = _mm256_add_ps(pz, _mm256_and_ps(half, m[2]));
        // The frame of this node, to come back to: written below, lane by
        // lane (the lanes that choose no child write to the unused last slot).
        let frame_bits = _mm256_or_si256(
            _mm256_or_si256(mask, _mm256_slli_epi32::<8>(remaining)),
            _mm256_or_si256(
                _mm256_slli_epi32::<16>(child),
                _mm256_slli_epi32::<24>(reflection),
            ),
        );
        // `Frame`'s bytes (`repr(C)`: `word`, then the bits), lanes 0, 1, 4, 5
        // and 2, 3, 6, 7, put back in lane order.
        let frames_a = _mm256_unpacklo_epi32(word, frame_bits);
        let frames_b = _mm256_unpackhi_epi32(word, frame_bits);
        sti!(
            out.frame[..4],
            _mm256_permute2x128_si256::<0x20>(frames_a, frames_b)
        );
        sti!(
            out.frame[4..],
            _mm256_permute2x128_si256::<0x31>(frames_a, frames_b)
        );
        let frame_level = blend(_mm256_set1_epi32(LEVEL_SLOTS as i32 - 1), level, choose);
        sti!(
            out.frame_at,
            _mm256_add_epi32(lane_bytes, _mm256_slli_epi32::<3>(frame_level))
        );
        let child_level = _mm256_add_epi32(level, one);
        let at_stop = _mm256_and_si256(choose, _mm256_cmpeq_epi32(child_level, ldi!(g.stop)));
        // What to prefetch: the child's header, or the brick's leaf mask.
        let scale = _mm256_blendv_epi8(
            _mm256_set1_epi32(if V2 { 0 } else { HEADER_SHIFT }),
            _mm256_set1_epi32(LEAF_SHIFT),
            at_stop,
        );
        sti!(
            out.fetch,
            _mm256_add_epi32(
                by_level(&offsets, child_level),
                _mm256_sllv_epi32(pointer, scale)
            )
        );
        let report = ldi!(g.report);
        let found = _mm256_and_si256(at_stop, report);
        let brick = _mm256_andnot_si256(report, at_stop);
        let descend = _mm256_andnot_si256(at_stop, choose);
        let mut next = blend(state, _mm256_set1_epi32(state::CONT), active);
        next = blend(next, _mm256_set1_epi32(state::VISIT), descend);
        next = blend(next, _mm256_set1_epi32(state::BRICK), brick);
        next = blend(next, _mm256_set1_epi32(state::FOUND), found);
        next = blend(next, _mm256_set1_epi32(state::MISS), at_top);
        let descend_f = _mm256_castsi256_ps(descend);
        sti!(g.state, next);
        sti!(g.level, blend(level, child_level, descend));
        stf!(g.px, _mm256_blendv_ps(px, cx, descend_f));
        stf!(g.py, _mm256_blendv_ps(py, cy, descend_f));
        stf!(g.pz, _mm256_blendv_ps(pz, cz, descend_f));
        stf!(g.size, _mm256_blendv_ps(size, half, descend_f));
        // Every lane's child corner, though only the lanes at their stop
        // level read it (as `BRICK` or `FOUND`, right after this step):
        // blended with the old values, the stores became masked stores
        // (`vmaskmovps`), which are slow on AMD's Zen.
        stf!(g.bx, cx);
        stf!(g.by, cy);
        stf!(g.bz, cz);
        sti!(g.target, blend(target, pointer, choose));
        if V2 {
            sti!(g.reflection, reflection);
            sti!(
                g.target_reflection,
                blend(
                    ldi!(g.target_reflection),
                    _mm256_xor_si256(reflection, child_reflection),
                    choose
                )
            );
        }
        sti!(g.word, word);
        sti!(g.mask, mask);
        sti!(g.remaining, remaining);
        sti!(g.pending, pending);
        let lanes = |v: __m256i| _mm256_movemask_ps(_mm256_castsi256_ps(v)) as u32;
        choose_bits = lanes(choose);
        slow_bits = lanes(_mm256_and_si256(cut, choose));
        // Only for the scalar pointer reads, which are rare: at the end of
        // the file, or outside a section (malformed files).
        if slow_bits != 0 {
            sti!(out.word, word);
            sti!(out.level, frame_level);
            if V2 {
                // The child's physical slot, its node's mask and R.
                sti!(out.rank, child);
                sti!(out.mask, mask);
                sti!(out.reflection, reflection);
            } else {
                sti!(out.rank, rank);
            }
        }
        done_bits = lanes(_mm256_or_si256(at_stop, at_top));
    }

    // SAFETY: `out.frame_at` holds `256 * lane + 8 * level` with `level <
    // LEVEL_SLOTS` in every lane (`frame_level` above).
    unsafe { out.write_back::<V2>(tracer, s, g, slow_bits & choose_bits) }?;
    Ok(done_bits)
}

/// The reference of the child of rank `rank` of each lane's node (at byte
/// offset `word` of level `level`) in expanded 2.0 levels (spec §23.12): one
/// gathered word, `index << 3 | r`, decoded by `node::lanes::Avx2`'s
/// expanded forms, as `node::Level::child_or_fault` decodes it; the lanes
/// whose word lies past `Sections::fast_limit` are left to that (`cut`).
/// Returns the child addresses, reflections and `cut`.
///
/// # Safety
///
/// The processor must have AVX2; the levels as `step` has them (`Sections`
/// addressing every level from `base`).
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn expanded_reference<const LOADS: bool>(
    s: &Sections,
    base: *const i32,
    level: __m256i,
    word: __m256i,
    rank: __m256i,
    lanes: __m256i,
) -> (__m256i, __m256i, __m256i) {
    let at = Avx2::expanded_reference_at(word, rank);
    let cut = _mm256_cmpgt_epi32(at, by_level(&level_table(&s.fast_limit), level));
    // SAFETY: the lanes read four bytes at `at <= fast_limit`, inside the
    // readable bytes of a level that `Sections` addresses from `base`; with
    // `LOADS` the others read `base` itself (as in `step`).
    let reference = unsafe {
        gather::<LOADS>(
            _mm256_setzero_si256(),
            base,
            _mm256_add_epi32(by_level(&level_table(&s.offset), level), at),
            _mm256_andnot_si256(cut, lanes),
        )
    };
    let (pointer, reflection) =
        Avx2::expanded_child(reference, by_level(&level_table(&s.expanded_shift), level));
    (pointer, reflection, cut)
}

/// The per-level table `t` as [`by_level`] reads it.
#[inline]
#[target_feature(enable = "avx2")]
fn level_table(t: &[i32; LEVEL_TABLE]) -> [__m256i; 3] {
    // SAFETY: loads of eight values inside the table.
    [0, 8, 16].map(|i| unsafe { _mm256_loadu_si256(t[i..i + 8].as_ptr().cast()) })
}

/// 2.0 (spec §23.2, §23.3): the reference of the child of rank `rank` of
/// each lane's node `word` (a byte offset) of `level`, whose child mask is
/// `mask`, in the lanes of `lanes`, decoded as `node::Level::child_or_fault`
/// decodes it (the meaning of the words from `node::lanes::Avx2`): its
/// target, the reflection it carries, and the lanes left to that scalar
/// decoding: words near the end of their section (the gathers read eight
/// bytes), and values that do not fit in 32 bits.
///
/// A sequential child of a node level is found in the child level's record
/// starts (`node::Level::sequential_in_index`, spec §23.8), lane by lane;
/// where that does not answer, by adding the sizes of its sequential
/// siblings before it, read from their headers and codes, all lanes at
/// once, one sibling a round.
///
/// # Safety
///
/// The processor must have AVX2; `word` and the levels as `step` has them
/// (`Sections` addressing every level from `base`).
#[inline]
#[target_feature(enable = "avx2")]
#[allow(clippy::too_many_arguments)]
unsafe fn v2_reference<const LOADS: bool>(
    tracer: &Tracer<'_>,
    s: &Sections,
    base: *const i32,
    level: __m256i,
    word: __m256i,
    mask: __m256i,
    rank: __m256i,
    lanes: __m256i,
) -> (__m256i, __m256i, __m256i) {
    let zero = _mm256_setzero_si256();
    let one = _mm256_set1_epi32(1);
    let four = _mm256_set1_epi32(HEADER_BYTES as i32);
    let ends = level_table(&s.v2_end);
    let lens = level_table(&s.len);
    let offsets = level_table(&s.offset);
    let widths = [
        level_table(&s.v2_width[0]),
        level_table(&s.v2_width[1]),
        level_table(&s.v2_width[2]),
    ];
    let w = [
        by_level(&widths[0], level),
        by_level(&widths[1], level),
        by_level(&widths[2], level),
    ];
    let offset = by_level(&offsets, level);
    let end = by_level(&ends, level);
    // The 32 bits after the header: the codes.
    let inside = lt_u32(word, end);
    let mut slow = _mm256_andnot_si256(inside, lanes);
    let mut live = _mm256_and_si256(inside, lanes);
    // SAFETY: the lanes in `live` read four of the eight readable bytes at
    // an offset below `end` (`Sections::v2_end`) of a level that `Sections`
    // addresses from `base`; with `LOADS` the others read `base` itself
    // (the start of a non-empty section).
    let after = unsafe {
        gather::<LOADS>(
            zero,
            base,
            _mm256_add_epi32(offset, _mm256_add_epi32(word, four)),
            live,
        )
    };
    let (codes, count) = Avx2::v2_codes(mask, after);
    let c = Avx2::v2_child(codes, count, mask, rank, w);
    // The 64 bits holding the reference, from its first byte.
    let byte = _mm256_add_epi32(word, _mm256_add_epi32(four, _mm256_srli_epi32::<3>(c.bit)));
    let inside = lt_u32(byte, end);
    // What the scalar decoding reads lies in the section (else it faults):
    // the codes (2k + 2 bits) and the reference.
    let len = by_level(&lens, level);
    let codes_end = _mm256_add_epi32(
        _mm256_add_epi32(word, four),
        _mm256_srli_epi32::<3>(_mm256_add_epi32(
            _mm256_slli_epi32::<1>(Avx2::popcount(mask)),
            _mm256_set1_epi32(9),
        )),
    );
    let reference_end = _mm256_add_epi32(
        _mm256_add_epi32(word, four),
        _mm256_srli_epi32::<3>(_mm256_add_epi32(
            _mm256_add_epi32(c.bit, c.width),
            _mm256_set1_epi32(7),
        )),
    );
    let past = _mm256_or_si256(lt_u32(len, codes_end), lt_u32(len, reference_end));
    let inside = _mm256_andnot_si256(past, inside);
    slow = _mm256_or_si256(slow, _mm256_andnot_si256(inside, live));
    live = _mm256_and_si256(inside, live);
    // SAFETY: the lanes in `live` read the eight readable bytes at `byte`,
    // below `end`; with `LOADS` the others those at `s.spare` (a leaf).
    let (lo, hi) =
        unsafe { gather_pair::<LOADS>(base, s.spare, _mm256_add_epi32(offset, byte), live) };
    let (value, high) = Avx2::v2_value(
        lo,
        hi,
        _mm256_and_si256(c.bit, _mm256_set1_epi32(7)),
        c.width,
    );
    // A shared child: `target << 3 | r`; the base reference: `target`.
    // Targets above 32 bits (the scalar decoding reads them as past the
    // level) go to the scalar decoding.
    let high_bits = _mm256_blendv_epi8(_mm256_srli_epi32::<3>(high), high, c.sequential);
    let wide = _mm256_xor_si256(_mm256_cmpeq_epi32(high_bits, zero), _mm256_set1_epi32(-1));
    slow = _mm256_or_si256(slow, _mm256_and_si256(wide, live));
    live = _mm256_andnot_si256(wide, live);
    let reflection =
        _mm256_andnot_si256(c.sequential, _mm256_and_si256(value, _mm256_set1_epi32(7)));
    let mut target = _mm256_blendv_epi8(
        _mm256_or_si256(_mm256_srli_epi32::<3>(value), _mm256_slli_epi32::<29>(high)),
        value,
        c.sequential,
    );
    // Sequential children of the leaf level: leaf `base + index`.
    let child_level = _mm256_add_epi32(level, one);
    let to_leaf = _mm256_cmpeq_epi32(child_level, _mm256_set1_epi32(s.leaf_level));
    let sequential = _mm256_and_si256(live, c.sequential);
    let leaf = _mm256_and_si256(sequential, to_leaf);
    let sum = _mm256_add_epi32(target, c.index);
    // (A sum past 32 bits is past the level: the scalar decoding says so.)
    let wraps = _mm256_and_si256(leaf, lt_u32(sum, target));
    slow = _mm256_or_si256(slow, wraps);
    target = blend(target, sum, _mm256_andnot_si256(wraps, leaf));
    // Sequential children of a node level: the record starts of the child
    // level, else the sizes of the siblings before.
    let mut todo = _mm256_andnot_si256(
        to_leaf,
        _mm256_and_si256(sequential, _mm256_cmpgt_epi32(c.index, zero)),
    );
    let mut indexed = _mm256_movemask_ps(_mm256_castsi256_ps(todo)) as u32;
    if indexed != 0 {
        let (mut targets, mut indices, mut levels) = ([0i32; W], [0i32; W], [0i32; W]);
        // SAFETY: stores of eight lanes into eight-value arrays.
        unsafe {
            _mm256_storeu_si256(targets.as_mut_ptr().cast(), target);
            _mm256_storeu_si256(indices.as_mut_ptr().cast(), c.index);
            _mm256_storeu_si256(levels.as_mut_ptr().cast(), level);
        }
        let mut lanes = indexed;
        while lanes != 0 {
            let lane = lanes.trailing_zeros() as usize;
            lanes &= lanes - 1;
            let node = &tracer.levels[levels[lane] as usize & (LEVEL_SLOTS - 1)];
            match node.sequential_in_index(u64::from(targets[lane] as u32), indices[lane] as u32) {
                // (A record start is inside its level, which `Sections`
                // addresses with 32-bit offsets.)
                Some(at) => targets[lane] = at as i32,
                None => indexed &= !(1 << lane),
            }
        }
        // SAFETY: a load of eight lanes from an eight-value array.
        target = unsafe { _mm256_loadu_si256(targets.as_ptr().cast()) };
        let lane_bits = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
        let found = _mm256_cmpeq_epi32(
            _mm256_and_si256(_mm256_set1_epi32(indexed as i32), lane_bits),
            lane_bits,
        );
        todo = _mm256_andnot_si256(found, todo);
    }
    if _mm256_movemask_ps(_mm256_castsi256_ps(todo)) != 0 {
        let next_offset = by_level(&offsets, child_level);
        let next_end = by_level(&ends, child_level);
        let next_len = by_level(&lens, child_level);
        let next_w = [
            by_level(&widths[0], child_level),
            by_level(&widths[1], child_level),
            by_level(&widths[2], child_level),
        ];
        let mut round = zero;
        loop {
            let inside = lt_u32(target, next_end);
            slow = _mm256_or_si256(slow, _mm256_andnot_si256(inside, todo));
            todo = _mm256_and_si256(inside, todo);
            if _mm256_movemask_ps(_mm256_castsi256_ps(todo)) == 0 {
                break;
            }
            let at = _mm256_add_epi32(next_offset, target);
            // SAFETY: the lanes in `todo` read the eight readable bytes at
            // `target`, below `next_end`; with `LOADS` the others those at
            // `s.spare` (a leaf).
            let (header, after) = unsafe { gather_pair::<LOADS>(base, s.spare, at, todo) };
            let sibling_mask = Avx2::child_mask(header);
            // The header, and the codes (2k + 2 bits, none without
            // children), lie in the section, as the scalar decoding needs.
            let two_k = _mm256_slli_epi32::<1>(Avx2::popcount(sibling_mask));
            let codes_bytes = _mm256_andnot_si256(
                _mm256_cmpeq_epi32(two_k, zero),
                _mm256_srli_epi32::<3>(_mm256_add_epi32(two_k, _mm256_set1_epi32(9))),
            );
            let past = lt_u32(
                next_len,
                _mm256_add_epi32(_mm256_add_epi32(target, four), codes_bytes),
            );
            slow = _mm256_or_si256(slow, _mm256_and_si256(past, todo));
            todo = _mm256_andnot_si256(past, todo);
            let (codes, count) = Avx2::v2_codes(sibling_mask, after);
            let size = Avx2::v2_size(codes, count, next_w);
            target = blend(target, _mm256_add_epi32(target, size), todo);
            round = _mm256_add_epi32(round, one);
            todo = _mm256_and_si256(todo, _mm256_cmpgt_epi32(c.index, round));
        }
    }
    (target, reflection, slow)
}

/// The part of each lane's segment `[tmin, tmax]` inside a box whose lower and
/// upper planes the lane crosses at `t_lo` and `t_hi`: its entry and exit, as
/// the scalar traversal computes them (`max`/`min` of walk.rs are
/// `_mm256_max_ps`/`_mm256_min_ps` exactly: the second operand unless the
/// first is strictly greater/less).
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) fn segment(
    t_lo: [__m256; 3],
    t_hi: [__m256; 3],
    tmin: __m256,
    tmax: __m256,
) -> (__m256, __m256) {
    let enter = _mm256_max_ps(
        _mm256_max_ps(_mm256_max_ps(t_lo[0], t_lo[1]), t_lo[2]),
        tmin,
    );
    let exit = _mm256_min_ps(
        _mm256_min_ps(_mm256_min_ps(t_hi[0], t_hi[1]), t_hi[2]),
        tmax,
    );
    (enter, exit)
}

/// The entries of a per-level table (`[i32; LEVEL_TABLE]` as three vectors)
/// for each lane's level (< `LEVEL_TABLE`), by in-register permutes.
#[inline]
#[target_feature(enable = "avx2")]
fn by_level(table: &[__m256i; 3], level: __m256i) -> __m256i {
    let low = _mm256_permutevar8x32_epi32(table[0], level);
    let mid = _mm256_permutevar8x32_epi32(table[1], level);
    let high = _mm256_permutevar8x32_epi32(table[2], level);
    let v = blend(low, mid, _mm256_cmpgt_epi32(level, _mm256_set1_epi32(7)));
    blend(v, high, _mm256_cmpgt_epi32(level, _mm256_set1_epi32(15)))
}

/// Byte `index` of `table` for the lanes in `lanes`, 0 in the others.
///
/// # Safety
///
/// The processor must have AVX2, and `index + 4 <= table.len()` in the lanes
/// of `lanes` (the gather loads 32 bits; the tables are padded for it).
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn table_bytes<const LOADS: bool>(table: &[u8], index: __m256i, lanes: __m256i) -> __m256i {
    let zero = _mm256_setzero_si256();
    // SAFETY: the caller keeps the loads of the lanes in `lanes` inside the table.
    let words = unsafe { gather::<LOADS>(zero, table.as_ptr().cast(), index, lanes) };
    _mm256_and_si256(words, _mm256_set1_epi32(0xff))
}

/// The 32-bit words at byte offsets `offsets` from `base` in the lanes of
/// `lanes`, `src`'s in the others: `_mm256_mask_i32gather_epi32::<1>`, or,
/// where `LOADS`, eight scalar loads put together (see
/// [`crate::Gathers::ScalarLoads`]).
///
/// # Safety
///
/// The processor must have AVX2. The four bytes at `base + offset` must be
/// readable for the offsets of the lanes in `lanes`, and, where `LOADS`, the
/// four bytes at `base` itself (the other lanes load those).
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn gather<const LOADS: bool>(
    src: __m256i,
    base: *const i32,
    offsets: __m256i,
    lanes: __m256i,
) -> __m256i {
    if !LOADS {
        // SAFETY: the caller keeps the reads of the lanes in `lanes` readable.
        return unsafe { _mm256_mask_i32gather_epi32::<1>(src, base, offsets, lanes) };
    }
    let pairs = offset_pairs(_mm256_and_si256(offsets, lanes));
    let base: *const u8 = base.cast();
    // SAFETY: the caller keeps these four bytes readable: those of a lane in
    // `lanes`, or `base` itself for the others (their offsets are masked to 0).
    let word = |offset: u64| unsafe {
        base.add(offset as u32 as usize)
            .cast::<i32>()
            .read_unaligned()
    };
    let words = _mm256_setr_epi32(
        word(pairs[0]),
        word(pairs[0] >> 32),
        word(pairs[1]),
        word(pairs[1] >> 32),
        word(pairs[2]),
        word(pairs[2] >> 32),
        word(pairs[3]),
        word(pairs[3] >> 32),
    );
    blend(src, words, lanes)
}

/// Eight lanes' offsets two to a 64-bit word (lane `2i` in the low half of
/// word `i`), out of the vector by register moves (a store and eight loads
/// of the offsets took longer): for the scalar loads of [`gather`] and
/// [`gather_pair`].
#[inline]
#[target_feature(enable = "avx2")]
fn offset_pairs(at: __m256i) -> [u64; 4] {
    let (lo, hi) = (
        _mm256_castsi256_si128(at),
        _mm256_extracti128_si256::<1>(at),
    );
    [
        _mm_cvtsi128_si64(lo) as u64,
        _mm_extract_epi64::<1>(lo) as u64,
        _mm_cvtsi128_si64(hi) as u64,
        _mm_extract_epi64::<1>(hi) as u64,
    ]
}

/// The 64 bits at byte offsets `offsets` from `base` in the lanes of
/// `lanes` as their low and high 32 bits (0 in the other lanes): two
/// [`gather`]s, or, where `LOADS`, eight 64-bit scalar loads put together.
///
/// # Safety
///
/// The processor must have AVX2. The eight bytes at `base + offset` must be
/// readable for the offsets of the lanes in `lanes`, and, where `LOADS`, the
/// eight bytes at `base + spare` (the other lanes load those).
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn gather_pair<const LOADS: bool>(
    base: *const i32,
    spare: i32,
    offsets: __m256i,
    lanes: __m256i,
) -> (__m256i, __m256i) {
    let zero = _mm256_setzero_si256();
    if !LOADS {
        // SAFETY: the caller keeps the eight bytes of the lanes readable.
        return unsafe {
            (
                gather::<false>(zero, base, offsets, lanes),
                gather::<false>(
                    zero,
                    base,
                    _mm256_add_epi32(offsets, _mm256_set1_epi32(4)),
                    lanes,
                ),
            )
        };
    }
    let pairs = offset_pairs(blend(_mm256_set1_epi32(spare), offsets, lanes));
    let base: *const u8 = base.cast();
    // SAFETY: the caller keeps these eight bytes readable: those of a lane in
    // `lanes`, or `base + spare` for the others.
    let word = |offset: u64| unsafe {
        base.add(offset as u32 as usize)
            .cast::<i64>()
            .read_unaligned()
    };
    let first = _mm256_setr_epi64x(
        word(pairs[0]),
        word(pairs[0] >> 32),
        word(pairs[1]),
        word(pairs[1] >> 32),
    );
    let second = _mm256_setr_epi64x(
        word(pairs[2]),
        word(pairs[2] >> 32),
        word(pairs[3]),
        word(pairs[3] >> 32),
    );
    // The even (low) and odd (high) 32-bit halves, then back in lane order
    // (the shuffle works within 128-bit halves).
    let (a, b) = (_mm256_castsi256_ps(first), _mm256_castsi256_ps(second));
    let low = _mm256_castps_si256(_mm256_shuffle_ps::<0b10_00_10_00>(a, b));
    let high = _mm256_castps_si256(_mm256_shuffle_ps::<0b11_01_11_01>(a, b));
    let low = _mm256_permute4x64_epi64::<0b11_01_10_00>(low);
    let high = _mm256_permute4x64_epi64::<0b11_01_10_00>(high);
    (_mm256_and_si256(low, lanes), _mm256_and_si256(high, lanes))
}

/// `a < b` as unsigned 32-bit integers.
#[inline]
#[target_feature(enable = "avx2")]
fn lt_u32(a: __m256i, b: __m256i) -> __m256i {
    let sign = _mm256_set1_epi32(i32::MIN);
    _mm256_cmpgt_epi32(_mm256_xor_si256(b, sign), _mm256_xor_si256(a, sign))
}

/// `b` where `m` is set, else `a` (per 32-bit lane; `m` all ones or zeros).
#[inline]
#[target_feature(enable = "avx2")]
fn blend(a: __m256i, b: __m256i, m: __m256i) -> __m256i {
    _mm256_blendv_epi8(a, b, m)
}

/// Three comparison masks as bits 0, 1 and 2.
#[inline]
#[target_feature(enable = "avx2")]
fn bits3(m: [__m256; 3]) -> __m256i {
    let bit = |m: __m256, b: i32| _mm256_and_si256(_mm256_castps_si256(m), _mm256_set1_epi32(b));
    _mm256_or_si256(_mm256_or_si256(bit(m[0], 1), bit(m[1], 2)), bit(m[2], 4))
}

/// Per axis, all ones where bit `axis` of the child index `c` is set: the
/// upper half on that axis.
#[inline]
#[target_feature(enable = "avx2")]
fn axis_masks(c: __m256i) -> [__m256; 3] {
    [1, 2, 4].map(|b| {
        let b = _mm256_set1_epi32(b);
        _mm256_castsi256_ps(_mm256_cmpeq_epi32(_mm256_and_si256(c, b), b))
    })
}

/// Set bits of each lane's low byte (the lanes hold values below 256).
#[inline]
#[target_feature(enable = "avx2")]
fn popcount8(v: __m256i) -> __m256i {
    let nibbles = _mm256_setr_epi8(
        0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4, 0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3,
        3, 4,
    );
    let low = _mm256_set1_epi32(0x0f);
    let lo = _mm256_shuffle_epi8(nibbles, _mm256_and_si256(v, low));
    let hi = _mm256_shuffle_epi8(nibbles, _mm256_and_si256(_mm256_srli_epi32::<4>(v), low));
    _mm256_add_epi32(lo, hi)
}

macro_rules! ldf_wide {
    ($a:expr) => {
        _mm512_loadu_ps($a.as_ptr())
    };
}
macro_rules! ldi_wide {
    ($a:expr) => {
        _mm512_loadu_si512($a.as_ptr().cast())
    };
}
macro_rules! stf_wide {
    ($a:expr, $v:expr) => {
        _mm512_storeu_ps($a.as_mut_ptr(), $v)
    };
}
macro_rules! sti_wide {
    ($a:expr, $v:expr) => {
        _mm512_storeu_si512($a.as_mut_ptr().cast(), $v)
    };
}

/// [`step`] for a group of sixteen lanes: the same operations per lane, on
/// 512-bit vectors, with mask registers where [`step`] has vectors of
/// all-ones lanes. Returns the lanes that now need scalar work.
///
/// # Safety
///
/// The processor must have the features of [`wide_available`].
#[inline]
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512dq,avx512cd")]
unsafe fn step_wide<const LOADS: bool, const V2: bool>(
    tracer: &Tracer<'_>,
    s: &Sections,
    g: &mut Group<WIDE>,
) -> Result<u32, Abandon> {
    let g_ptr: *mut Group<WIDE> = g;
    let mut out = StepOut::<WIDE>::new();
    let (choose_bits, slow_bits, done_bits);
    // SAFETY: as in `step`: whole `[_; WIDE]` arrays of the group and of
    // local arrays are loaded and stored, and every gather reads only the
    // lanes of its mask, at the offsets `step` reads (table entries at
    // in-range indices, stack frames of levels < LEVEL_SLOTS of lanes <
    // WIDE, node words checked against their section's length just before,
    // pointers at offsets <= `fast_limit`); with scalar loads the other
    // lanes read the four bytes at the gather's base (`gather_wide`).
    unsafe {
        let g = &mut *g_ptr;
        let zero = _mm512_setzero_si512();
        let one = _mm512_set1_epi32(1);
        let byte = _mm512_set1_epi32(0xff);
        let base: *const i32 = s.base.cast();
        let tables = |t: &[i32; LEVEL_TABLE]| {
            [0, 16].map(|i| _mm512_loadu_si512(t[i..i + 16].as_ptr().cast()))
        };
        let (offsets, nodes, widths) = (tables(&s.offset), tables(&s.nodes), tables(&s.width));
        let fast_limits = tables(&s.fast_limit);

        let state = ldi_wide!(g.state);
        let visit = _mm512_cmpeq_epi32_mask(state, _mm512_set1_epi32(state::VISIT));
        let cont = _mm512_cmpeq_epi32_mask(state, _mm512_set1_epi32(state::CONT));
        let mut level = ldi_wide!(g.level);
        let target = ldi_wide!(g.target);
        let neg = ldi_wide!(g.neg);
        // 2.0: the accumulated reflection R of the node each lane visits or
        // stands on (as in `step`); 0 in 1.0.
        let mut reflection = if V2 {
            _mm512_mask_blend_epi32(
                visit,
                ldi_wide!(g.reflection),
                ldi_wide!(g.target_reflection),
            )
        } else {
            zero
        };

        // Visit: the header, bounds-checked like `Level::header_or_fault`.
        let inside = _mm512_cmplt_epu32_mask(target, by_level_wide(&nodes, level));
        if visit & !inside != 0 {
            return Err(Abandon);
        }
        // (A 2.0 node's address is its header's byte offset.)
        let header_at = if V2 {
            target
        } else {
            Avx512::header_at(target)
        };
        let header = gather_wide::<LOADS>(
            zero,
            base,
            _mm512_add_epi32(by_level_wide(&offsets, level), header_at),
            visit,
        );
        let (ox, oy, oz) = (ldf_wide!(g.ox), ldf_wide!(g.oy), ldf_wide!(g.oz));
        let (ix, iy, iz) = (ldf_wide!(g.ix), ldf_wide!(g.iy), ldf_wide!(g.iz));
        let (mut px, mut py, mut pz) = (ldf_wide!(g.px), ldf_wide!(g.py), ldf_wide!(g.pz));
        let mut size = ldf_wide!(g.size);
        let half = _mm512_mul_ps(size, _mm512_set1_ps(0.5));
        // The plane parameters, as `resume` computes them: (p - o) * inv.
        let plane = |p: __m512, o: __m512, i: __m512| _mm512_mul_ps(_mm512_sub_ps(p, o), i);
        let t_lo = [plane(px, ox, ix), plane(py, oy, iy), plane(pz, oz, iz)];
        let t_mid = [
            plane(_mm512_add_ps(px, half), ox, ix),
            plane(_mm512_add_ps(py, half), oy, iy),
            plane(_mm512_add_ps(pz, half), oz, iz),
        ];
        let t_hi = [
            plane(_mm512_add_ps(px, size), ox, ix),
            plane(_mm512_add_ps(py, size), oy, iy),
            plane(_mm512_add_ps(pz, size), oz, iz),
        ];
        // `segment`: `_mm512_max_ps`/`_mm512_min_ps` are `max`/`min` of
        // walk.rs exactly, as their 256-bit forms are.
        let enter = _mm512_max_ps(
            _mm512_max_ps(_mm512_max_ps(t_lo[0], t_lo[1]), t_lo[2]),
            ldf_wide!(g.tmin),
        );
        let exit = _mm512_min_ps(
            _mm512_min_ps(_mm512_min_ps(t_hi[0], t_hi[1]), t_hi[2]),
            ldf_wide!(g.tmax),
        );
        let nonempty = _mm512_cmp_ps_mask::<_CMP_LE_OQ>(enter, exit);
        // The CHAIN key, as `chain` computes it.
        let le_enter = t_mid.map(|t| _mm512_cmp_ps_mask::<_CMP_LE_OQ>(t, enter));
        let crossing = t_mid.map(|t| {
            _mm512_cmp_ps_mask::<_CMP_GT_OQ>(t, enter) & _mm512_cmp_ps_mask::<_CMP_LE_OQ>(t, exit)
        });
        let order = [
            _mm512_cmp_ps_mask::<_CMP_LT_OQ>(t_mid[0], t_mid[1]),
            _mm512_cmp_ps_mask::<_CMP_LT_OQ>(t_mid[0], t_mid[2]),
            _mm512_cmp_ps_mask::<_CMP_LT_OQ>(t_mid[1], t_mid[2]),
        ];
        let key = _mm512_or_si512(
            _mm512_or_si512(bits3_wide(le_enter, 0), bits3_wide(crossing, 3)),
            bits3_wide(order, 6),
        );
        let chain = table_bytes_wide::<LOADS>(
            &CHAIN_PADDED,
            _mm512_or_si512(
                _mm512_slli_epi32::<9>(_mm512_xor_si512(neg, reflection)),
                key,
            ),
            visit,
        );
        let node_mask = Avx512::child_mask(header);
        let visited = _mm512_maskz_and_epi32(nonempty, chain, node_mask);
        let mut word = _mm512_mask_blend_epi32(visit, ldi_wide!(g.word), target);
        let mut mask = _mm512_mask_blend_epi32(visit, ldi_wide!(g.mask), node_mask);
        let mut remaining = _mm512_mask_blend_epi32(visit, ldi_wide!(g.remaining), visited);

        // No child left: back to the nearest node of the path that has
        // children left, at once (as in `step`).
        let mut pending = ldi_wide!(g.pending);
        let active = visit | cont;
        let empty = active & _mm512_cmpeq_epi32_mask(remaining, zero);
        let above = _mm512_and_si512(
            pending,
            _mm512_sub_epi32(_mm512_sllv_epi32(one, level), one),
        );
        let at_top = empty & _mm512_cmpeq_epi32_mask(above, zero);
        let pop = empty & !at_top;
        // The highest set bit of `above` (non-zero where `pop`).
        let highest = _mm512_sub_epi32(_mm512_set1_epi32(31), _mm512_lzcnt_epi32(above));
        level = _mm512_mask_blend_epi32(pop, level, highest);
        let lane_bytes = _mm512_setr_epi32(
            0, 256, 512, 768, 1024, 1280, 1536, 1792, 2048, 2304, 2560, 2816, 3072, 3328, 3584,
            3840,
        );
        let frame_at = _mm512_add_epi32(lane_bytes, _mm512_slli_epi32::<3>(level));
        let stacks: *const i32 = g.stacks.as_ptr().cast();
        word = gather_wide::<LOADS>(word, stacks, frame_at, pop);
        let f_bits = gather_wide::<LOADS>(zero, stacks.add(1), frame_at, pop);
        mask = _mm512_mask_blend_epi32(pop, mask, _mm512_and_si512(f_bits, byte));
        remaining = _mm512_mask_blend_epi32(
            pop,
            remaining,
            _mm512_and_si512(_mm512_srli_epi32::<8>(f_bits), byte),
        );
        if V2 {
            // `Frame::reflection`, the frame's last byte.
            reflection = _mm512_mask_blend_epi32(pop, reflection, _mm512_srli_epi32::<24>(f_bits));
        }
        let node_neg = _mm512_xor_si512(neg, reflection);
        // That node's corner and edge (exact integers).
        let edge = _mm512_sllv_epi32(one, _mm512_sub_epi32(_mm512_set1_epi32(s.depth), level));
        let corner = |p: __m512| {
            let cell = _mm512_and_si512(_mm512_cvttps_epi32(p), _mm512_sub_epi32(zero, edge));
            _mm512_mask_blend_ps(pop, p, _mm512_cvtepi32_ps(cell))
        };
        px = corner(px);
        py = corner(py);
        pz = corner(pz);
        size = _mm512_mask_blend_ps(pop, size, _mm512_cvtepi32_ps(edge));
        let half = _mm512_mul_ps(size, _mm512_set1_ps(0.5));

        // The next child, front to back, and its pointer.
        let choose = active & !at_top;
        let child = table_bytes_wide::<LOADS>(
            &FIRST_PADDED,
            _mm512_or_si512(_mm512_slli_epi32::<8>(node_neg), remaining),
            choose,
        );
        let bit = _mm512_maskz_sllv_epi32(choose, one, child);
        remaining = _mm512_andnot_si512(bit, remaining);
        let level_bit = _mm512_sllv_epi32(one, level);
        pending = _mm512_or_si512(
            _mm512_andnot_si512(level_bit, pending),
            _mm512_maskz_mov_epi32(_mm512_cmpneq_epi32_mask(remaining, zero), level_bit),
        );
        let rank = popcount8_wide(_mm512_and_si512(mask, _mm512_sub_epi32(bit, one)));
        // The child's reference: its target and (2.0) the reflection it
        // carries; `cut`: the lanes whose reference is read by the scalar
        // tail.
        let (pointer, child_reflection, cut) = if V2 && s.expanded {
            // `expanded_reference` of `step` on sixteen lanes.
            let fast_limit = by_level_wide(&fast_limits, level);
            let at = Avx512::expanded_reference_at(word, rank);
            let cut = _mm512_cmpgt_epi32_mask(at, fast_limit);
            let reference = gather_wide::<LOADS>(
                zero,
                base,
                _mm512_add_epi32(by_level_wide(&offsets, level), at),
                choose & !cut,
            );
            let shifts =
                [0, 16].map(|i| _mm512_loadu_si512(s.expanded_shift[i..i + 16].as_ptr().cast()));
            let (pointer, reflection) =
                Avx512::expanded_child(reference, by_level_wide(&shifts, level));
            (pointer, reflection, cut)
        } else if V2 {
            // The 2.0 decoding of `step`, `v2_reference`, on each half of
            // the lanes: the very same operations per lane.
            let halves =
                |v: __m512i| (_mm512_castsi512_si256(v), _mm512_extracti64x4_epi64::<1>(v));
            let join =
                |lo: __m256i, hi: __m256i| _mm512_inserti64x4::<1>(_mm512_castsi256_si512(lo), hi);
            let (level_lo, level_hi) = halves(level);
            let (word_lo, word_hi) = halves(word);
            let (mask_lo, mask_hi) = halves(mask);
            let (rank_lo, rank_hi) = halves(rank);
            let (choose_lo, choose_hi) = halves(_mm512_movm_epi32(choose));
            let (p_lo, r_lo, cut_lo) = v2_reference::<LOADS>(
                tracer, s, base, level_lo, word_lo, mask_lo, rank_lo, choose_lo,
            );
            let (p_hi, r_hi, cut_hi) = v2_reference::<LOADS>(
                tracer, s, base, level_hi, word_hi, mask_hi, rank_hi, choose_hi,
            );
            (
                join(p_lo, p_hi),
                join(r_lo, r_hi),
                _mm512_movepi32_mask(join(cut_lo, cut_hi)),
            )
        } else {
            let fast_limit = by_level_wide(&fast_limits, level);
            let width = by_level_wide(&widths, level);
            let pointer_mask = Avx512::reference_mask(width);
            let at = Avx512::reference_at(word, rank, width);
            let cut = _mm512_cmpgt_epi32_mask(at, fast_limit);
            let fast = choose & !cut;
            let pointer = _mm512_and_si512(
                gather_wide::<LOADS>(
                    zero,
                    base,
                    _mm512_add_epi32(by_level_wide(&offsets, level), at),
                    fast,
                ),
                pointer_mask,
            );
            (pointer, zero, cut)
        };
        let mirrored = _mm512_xor_si512(child, node_neg);
        let m = [1, 2, 4].map(|b| _mm512_test_epi32_mask(mirrored, _mm512_set1_epi32(b)));
        // `p + (half & mask)` as in `step`: +0.0 in the other lanes.
        let cx = _mm512_add_ps(px, _mm512_maskz_mov_ps(m[0], half));
        let cy = _mm512_add_ps(py, _mm512_maskz_mov_ps(m[1], half));
        let cz = _mm512_add_ps(pz, _mm512_maskz_mov_ps(m[2], half));
        // The frame of this node, to come back to: `Frame`'s bytes (`word`,
        // then the bits), interleaved into eight 64-bit words a vector.
        let frame_bits = _mm512_or_si512(
            _mm512_or_si512(mask, _mm512_slli_epi32::<8>(remaining)),
            _mm512_or_si512(
                _mm512_slli_epi32::<16>(child),
                _mm512_slli_epi32::<24>(reflection),
            ),
        );
        let low_lanes = _mm512_setr_epi32(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23);
        let high_lanes =
            _mm512_setr_epi32(8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31);
        sti_wide!(
            out.frame[..8],
            _mm512_permutex2var_epi32(word, low_lanes, frame_bits)
        );
        sti_wide!(
            out.frame[8..],
            _mm512_permutex2var_epi32(word, high_lanes, frame_bits)
        );
        let frame_level =
            _mm512_mask_blend_epi32(choose, _mm512_set1_epi32(LEVEL_SLOTS as i32 - 1), level);
        sti_wide!(
            out.frame_at,
            _mm512_add_epi32(lane_bytes, _mm512_slli_epi32::<3>(frame_level))
        );
        let child_level = _mm512_add_epi32(level, one);
        let at_stop = choose & _mm512_cmpeq_epi32_mask(child_level, ldi_wide!(g.stop));
        // What to prefetch: the child's header, or the brick's leaf mask.
        let scale = _mm512_mask_blend_epi32(
            at_stop,
            _mm512_set1_epi32(if V2 { 0 } else { HEADER_SHIFT }),
            _mm512_set1_epi32(LEAF_SHIFT),
        );
        sti_wide!(
            out.fetch,
            _mm512_add_epi32(
                by_level_wide(&offsets, child_level),
                _mm512_sllv_epi32(pointer, scale)
            )
        );
        let report = ldi_wide!(g.report);
        let reports = _mm512_test_epi32_mask(report, report);
        let found = at_stop & reports;
        let brick = at_stop & !reports;
        let descend = choose & !at_stop;
        let mut next = _mm512_mask_blend_epi32(active, state, _mm512_set1_epi32(state::CONT));
        next = _mm512_mask_blend_epi32(descend, next, _mm512_set1_epi32(state::VISIT));
        next = _mm512_mask_blend_epi32(brick, next, _mm512_set1_epi32(state::BRICK));
        next = _mm512_mask_blend_epi32(found, next, _mm512_set1_epi32(state::FOUND));
        next = _mm512_mask_blend_epi32(at_top, next, _mm512_set1_epi32(state::MISS));
        sti_wide!(g.state, next);
        sti_wide!(
            g.level,
            _mm512_mask_blend_epi32(descend, level, child_level)
        );
        stf_wide!(g.px, _mm512_mask_blend_ps(descend, px, cx));
        stf_wide!(g.py, _mm512_mask_blend_ps(descend, py, cy));
        stf_wide!(g.pz, _mm512_mask_blend_ps(descend, pz, cz));
        stf_wide!(g.size, _mm512_mask_blend_ps(descend, size, half));
        // Every lane's child corner (see `step`).
        stf_wide!(g.bx, cx);
        stf_wide!(g.by, cy);
        stf_wide!(g.bz, cz);
        sti_wide!(g.target, _mm512_mask_blend_epi32(choose, target, pointer));
        if V2 {
            sti_wide!(g.reflection, reflection);
            sti_wide!(
                g.target_reflection,
                _mm512_mask_blend_epi32(
                    choose,
                    ldi_wide!(g.target_reflection),
                    _mm512_xor_si512(reflection, child_reflection)
                )
            );
        }
        sti_wide!(g.word, word);
        sti_wide!(g.mask, mask);
        sti_wide!(g.remaining, remaining);
        sti_wide!(g.pending, pending);
        choose_bits = u32::from(choose);
        slow_bits = u32::from(cut & choose);
        // Only for the scalar pointer reads, which are rare.
        if slow_bits != 0 {
            sti_wide!(out.word, word);
            sti_wide!(out.level, frame_level);
            if V2 {
                // The child's physical slot, its node's mask and R.
                sti_wide!(out.rank, child);
                sti_wide!(out.mask, mask);
                sti_wide!(out.reflection, reflection);
            } else {
                sti_wide!(out.rank, rank);
            }
        }
        done_bits = u32::from(at_stop | at_top);
    }
    // SAFETY: as in `step`: `out.frame_at` holds `256 * lane + 8 * level`
    // with `level < LEVEL_SLOTS` in every lane.
    unsafe { out.write_back::<V2>(tracer, s, g, slow_bits & choose_bits) }?;
    Ok(done_bits)
}

/// [`by_level`] for sixteen lanes: one two-vector permute (levels < 32).
#[inline]
#[target_feature(enable = "avx512f")]
fn by_level_wide(table: &[__m512i; 2], level: __m512i) -> __m512i {
    _mm512_permutex2var_epi32(table[0], level, table[1])
}

/// [`bits3`] for sixteen lanes, shifted left by `shift`.
#[inline]
#[target_feature(enable = "avx512f")]
fn bits3_wide(m: [__mmask16; 3], shift: i32) -> __m512i {
    let bit = |m: __mmask16, b: i32| _mm512_maskz_mov_epi32(m, _mm512_set1_epi32(b << shift));
    _mm512_or_si512(_mm512_or_si512(bit(m[0], 1), bit(m[1], 2)), bit(m[2], 4))
}

/// [`popcount8`] for sixteen lanes.
#[inline]
#[target_feature(enable = "avx512f,avx512bw")]
fn popcount8_wide(v: __m512i) -> __m512i {
    // Bits set in 0..16, a byte each, in every 128-bit lane.
    let nibbles = _mm512_set4_epi32(0x0403_0302, 0x0302_0201, 0x0302_0201, 0x0201_0100);
    let low = _mm512_set1_epi32(0x0f);
    let lo = _mm512_shuffle_epi8(nibbles, _mm512_and_si512(v, low));
    let hi = _mm512_shuffle_epi8(nibbles, _mm512_and_si512(_mm512_srli_epi32::<4>(v), low));
    _mm512_add_epi32(lo, hi)
}

/// [`table_bytes`] for sixteen lanes.
///
/// # Safety
///
/// The processor must have AVX-512F, and `index + 4 <= table.len()` in the
/// lanes of `lanes`.
#[inline]
#[target_feature(enable = "avx512f")]
unsafe fn table_bytes_wide<const LOADS: bool>(
    table: &[u8],
    index: __m512i,
    lanes: __mmask16,
) -> __m512i {
    let zero = _mm512_setzero_si512();
    // SAFETY: the caller keeps the loads of the lanes in `lanes` inside the table.
    let words = unsafe { gather_wide::<LOADS>(zero, table.as_ptr().cast(), index, lanes) };
    _mm512_and_si512(words, _mm512_set1_epi32(0xff))
}

/// [`gather`] for sixteen lanes: the 32-bit words at byte offsets `offsets`
/// from `base` in the lanes of `lanes`, `src`'s in the others; with `LOADS`,
/// sixteen scalar loads put together.
///
/// # Safety
///
/// The processor must have AVX-512F. The four bytes at `base + offset` must
/// be readable for the offsets of the lanes in `lanes`, and, where `LOADS`,
/// the four bytes at `base` itself (the other lanes load those).
#[inline]
#[target_feature(enable = "avx512f")]
unsafe fn gather_wide<const LOADS: bool>(
    src: __m512i,
    base: *const i32,
    offsets: __m512i,
    lanes: __mmask16,
) -> __m512i {
    if !LOADS {
        // SAFETY: the caller keeps the reads of the lanes in `lanes` readable.
        return unsafe { _mm512_mask_i32gather_epi32::<1>(src, lanes, offsets, base) };
    }
    let mut at = [0u32; WIDE];
    // SAFETY: a store of sixteen 32-bit words into a sixteen-word array.
    unsafe {
        _mm512_storeu_si512(
            at.as_mut_ptr().cast(),
            _mm512_maskz_mov_epi32(lanes, offsets),
        )
    };
    let base: *const u8 = base.cast();
    // SAFETY: the caller keeps these four bytes readable: those of a lane in
    // `lanes`, or `base` itself for the others (their offsets are 0).
    let words: [i32; WIDE] =
        std::array::from_fn(|k| unsafe { base.add(at[k] as usize).cast::<i32>().read_unaligned() });
    // SAFETY: a load of sixteen 32-bit words from a sixteen-word array.
    let words = unsafe { _mm512_loadu_si512(words.as_ptr().cast()) };
    _mm512_mask_blend_epi32(lanes, src, words)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::cpu::available;
    use crate::testing::Rng;
    use crate::walk::Setup;
    use dagfmt::Dag;
    use dagfmt::builder::DagBuilder;
    use dagfmt::layout::AttributeKind;

    /// The pointers the gathers read (`at <= fast_limit`) lie inside their
    /// section, and their 32-bit loads inside the file, whatever lies after
    /// the section; short levels followed by more of the file gather all
    /// their pointers.
    #[test]
    fn gathered_pointers_stay_in_their_section_and_the_file() {
        let mut rng = Rng(0x90);
        for depth in [3u8, 6, 9, 13] {
            let side = 1u64 << depth;
            let cells: Vec<[u32; 3]> = (0..400)
                .map(|_| [0; 3].map(|_| (rng.next() % side) as u32))
                .collect();
            let built = DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, cells)
                .expect("valid voxels");
            let bytes = built.to_bytes();
            let dag = Dag::open(&bytes).expect("built DAG opens");
            let tracer = Tracer::new(&dag).expect("tracer");
            let s = Sections::new(&tracer).expect("small files are addressable");
            let file_end = bytes.as_ptr() as usize + bytes.len();
            for (l, level) in tracer.levels[..usize::from(tracer.leaf_level)]
                .iter()
                .enumerate()
            {
                let limit = i64::from(s.fast_limit[l]);
                let (len, width) = (level.bytes.len() as i64, i64::from(level.width));
                assert!(limit + width <= len, "level {l}: {limit} + {width} > {len}");
                let last_byte = s.base as usize + s.offset[l] as usize + (limit + 4) as usize;
                assert!(
                    limit < 0 || last_byte <= file_end,
                    "level {l} reads past the file"
                );
                let start = level.bytes.as_ptr() as usize;
                if start + len as usize + 4 <= file_end {
                    assert_eq!(
                        limit,
                        len - width,
                        "level {l} sends pointers to the scalar path"
                    );
                }
            }
        }
    }

    /// A float that is often one of the values the set-up treats specially.
    pub(crate) fn special(rng: &mut Rng, usual: f32) -> f32 {
        match rng.next() % 16 {
            0 => 0.0,
            1 => -0.0,
            2 => f32::NAN,
            3 => f32::INFINITY,
            4 => 1e-30,
            5 => 3e37,
            6 => usual * 1e-19,
            7 => usual * 1e6,
            _ => usual,
        }
    }

    #[test]
    fn vector_set_up_is_the_set_up_of_each_ray() {
        if !available() {
            eprintln!("no AVX2 on this processor: the vector set-up was not tested");
            return;
        }
        let built = DagBuilder::from_voxels(
            9,
            AttributeKind::VoxelCount,
            vec![[3, 4, 5], [200, 100, 50], [511, 0, 300]],
        )
        .expect("valid voxels");
        let bytes = built.to_bytes();
        let dag = Dag::open(&bytes).expect("built DAG opens");
        let tracer = Tracer::new(&dag).expect("tracer");
        let mut rng = Rng(5);
        let (mut usual, mut unusual) = (0, 0);
        for round in 0..20_000 {
            let rays: [Ray; 4] = std::array::from_fn(|_| {
                let odd = round % 4 == 0;
                let mut value = |lo: f32, hi: f32| {
                    let v = rng.range(lo, hi);
                    if odd { special(&mut rng, v) } else { v }
                };
                Ray {
                    origin: [value(-20.0, 20.0), value(-1.0, 2.0), value(-1.0, 2.0)],
                    dir: [value(-1.0, 1.0), value(-1.0, 1.0), value(-1.0, 1.0)],
                    tmin: value(-1.0, 1.0),
                    tmax: value(-1.0, 5.0),
                    level: None,
                }
            });
            let mut rays = rays;
            for ray in &mut rays {
                if rng.next().is_multiple_of(3) {
                    ray.tmax = f32::INFINITY;
                }
                if rng.next().is_multiple_of(13) {
                    ray.level = Some((rng.next() % 10) as u8);
                }
            }
            let mut prepared = [Prepared::default(); 4];
            // SAFETY: AVX2 was found above.
            let mask = unsafe { setup4(&tracer, &rays, &mut prepared) };
            for (k, ray) in rays.iter().enumerate() {
                if mask >> k & 1 == 1 {
                    usual += 1;
                    match tracer.setup(ray) {
                        Ok(Setup::Trace(p)) => assert_eq!(p, prepared[k], "{ray:?}"),
                        _ => panic!("set up in vectors, but not traced by setup: {ray:?}"),
                    }
                } else {
                    unusual += 1;
                }
            }
        }
        assert!(
            usual > 40_000 && unusual > 5_000,
            "{usual} usual, {unusual} not"
        );
    }
}
