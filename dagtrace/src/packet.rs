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
//!    so little that the beam stays at most [`BEAM_WIDTH_CELLS`] cells of the
//!    beam level wide across the cube (see [`Tracer::packet_len`]).
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
//!    own (rounded) test would enter.
//! 3. Each ray is then traced, in that order, through the subtrees of the
//!    listed cells that it meets itself (its own slab test, before any node
//!    is read) with the very same steps as [`Tracer::trace`] (a [`Walk`]
//!    whose `top` is the cell), several rays in flight at once; its first hit
//!    is its answer, and a ray that meets none of them misses. The cells are
//!    listed lazily, a few at a time, so that the beam walk stops as soon as
//!    every ray of the packet has hit.
//!
//! The answers are those of [`Tracer::trace`] except where a ray passes
//! exactly through an edge or corner shared by cells of the beam level: there
//! the per-ray traversal visits one of the tied cells and the packet all of
//! them, and either answer is a correct one (spec/VDAG.md §20.4, ties).
//! Any fault (a pointer out of range) makes the packet fall back to ray-by-ray
//! tracing, so errors are reported exactly as [`Tracer::trace`] reports them.

use glam::Vec3A;

use crate::tables::FIRST;
use crate::tracer::{
    Begun, Frame, LANES, LEVEL_SLOTS, Pending, Stack, Tracer, Walk, max, min, prefetch,
};
use dagfmt::batch::{Hit, Ray};

/// Most rays in one packet.
pub(crate) const PACKET_RAYS: usize = 64;

/// Fewest rays worth a beam pass.
const MIN_PACKET_RAYS: usize = 8;

/// Widest beam, in cells of the beam level (at the far side of the cube),
/// for which a packet beats tracing its rays one by one.
const BEAM_WIDTH_CELLS: f64 = 16.0;

/// Cells of the beam level listed at a time before the rays are traced
/// through them.
const CELLS_PER_ROUND: usize = 8;

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
}

/// The beam: the packet's common origin and the per-axis range of its
/// inverse directions, in the mirrored grid frame, in `f64`.
#[derive(Clone, Copy, Debug)]
struct Beam {
    origin: [f64; 3],
    inv_lo: [f64; 3],
    inv_hi: [f64; 3],
    tmin: f64,
    tmax: f64,
    margin: f64,
}

impl Beam {
    /// Whether some line of the beam may meet the cube of edge `size` at
    /// `pos` (interval slab test on the enlarged cube).
    #[inline]
    fn meets(&self, pos: [f64; 3], size: f64) -> bool {
        let mut enter = self.tmin;
        let mut exit = self.tmax;
        for (a, &p) in pos.iter().enumerate() {
            let lo = p - self.margin - self.origin[a];
            let hi = p + size + self.margin - self.origin[a];
            // The smallest entry and the largest exit over the beam's lines.
            let near = lo
                * if lo >= 0.0 {
                    self.inv_lo[a]
                } else {
                    self.inv_hi[a]
                };
            let far = hi
                * if hi >= 0.0 {
                    self.inv_hi[a]
                } else {
                    self.inv_lo[a]
                };
            enter = enter.max(near);
            exit = exit.min(far);
        }
        enter <= exit
    }
}

/// One node on the beam walk's path.
#[derive(Clone, Copy, Debug, Default)]
struct BeamFrame {
    word: u32,
    mask: u8,
    /// Children not yet considered.
    remaining: u8,
    /// Mirrored grid position of the node's lower corner.
    pos: [f64; 3],
}

/// One ray of a packet in flight: its walk through one cell of the beam.
#[derive(Clone, Copy, Debug, Default)]
struct PacketLane {
    /// The ray's index in the packet.
    ray: u8,
    /// The cell walked, in this round's list.
    cell: u8,
    walk: Walk,
    stack: Stack,
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

    /// Number of rays from the start of `rays` that form a packet (up to
    /// [`PACKET_RAYS`]): the same origin, `tmin`, `tmax` and level (finer than
    /// the beam level), and directions whose components are all far from zero
    /// and of the same signs. 0 when there are fewer than [`MIN_PACKET_RAYS`].
    pub(crate) fn packet_len(&self, rays: &[Ray]) -> usize {
        if self.beam_level() == 0 {
            return 0;
        }
        let Some(first) = rays.first() else {
            return 0;
        };
        // The cheap tests first: this runs at every ray of a batch.
        let same_start = |r: &Ray| {
            r.origin.map(f32::to_bits) == first.origin.map(f32::to_bits)
                && r.tmin.to_bits() == first.tmin.to_bits()
                && r.tmax.to_bits() == first.tmax.to_bits()
                && r.level == first.level
        };
        let candidates = rays
            .iter()
            .take(PACKET_RAYS)
            .take_while(|r| same_start(r))
            .count();
        if candidates < MIN_PACKET_RAYS {
            return 0;
        }
        // Components treated as zero (or nearly) by the set-up, and NaNs,
        // keep a ray out of packets.
        let regular = |d: [f32; 3]| {
            let largest = d[0].abs().max(d[1].abs()).max(d[2].abs());
            largest.is_finite() && d.iter().all(|c| c.abs() > largest * 1e-6)
        };
        if !regular(first.dir) {
            return 0;
        }
        // Rays of a coarser level of detail than the beam's cells, and rays
        // of an impossible level (an error, reported ray by ray), go alone.
        if first
            .level
            .is_some_and(|l| l <= self.beam_level() || l > self.depth)
        {
            return 0;
        }
        // The beam must stay narrow: where it is many cells of the beam level
        // wide, every ray would be tested against all of them. Its width at
        // the far side of the cube is at most the spread of the directions
        // (the chord between unit directions, about the angle) times the
        // distance to the cube's farthest corner.
        let resolution = f64::from(self.cell_size[0]);
        let origin: [f64; 3] =
            [0, 1, 2].map(|a| (f64::from(first.origin[a]) - self.root_min[a]) * self.grid_scale);
        let far = origin
            .iter()
            .map(|&o| o.abs().max((resolution - o).abs()))
            .map(|d| d * d)
            .sum::<f64>()
            .sqrt();
        let cell = f64::from(self.cell_size[usize::from(self.beam_level())]);
        let max_spread = (BEAM_WIDTH_CELLS * cell / far.max(cell)) as f32;
        let unit = |d: [f32; 3]| {
            let length = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            d.map(|c| c / length)
        };
        let axis = unit(first.dir);
        let first_octant = octant(first.dir);
        let coherent = |r: &Ray| {
            let u = unit(r.dir);
            let chord =
                ((u[0] - axis[0]).powi(2) + (u[1] - axis[1]).powi(2) + (u[2] - axis[2]).powi(2))
                    .sqrt();
            regular(r.dir) && octant(r.dir) == first_octant && chord <= max_spread
        };
        let n = rays[..candidates]
            .iter()
            .take_while(|r| coherent(r))
            .count();
        if n >= MIN_PACKET_RAYS { n } else { 0 }
    }

    /// Traces the packet `rays` (made by [`Tracer::packet_len`]) into `hits`.
    /// Returns `false`, having written nothing that matters, when the packet
    /// cannot be traced as one (a ray the set-up treats specially, or a fault
    /// on the way): the caller then traces its rays one by one.
    pub(crate) fn try_packet(&self, rays: &[Ray], hits: &mut [Hit]) -> bool {
        let beam_level = self.beam_level();
        let n = rays.len().min(hits.len()).min(PACKET_RAYS);
        if n == 0 || self.empty {
            return false;
        }
        let rays = &rays[..n];
        // The beam first: most packets of a camera meet nothing, and then no
        // ray needs even its set-up.
        let Some(beam) = self.beam(rays) else {
            return false;
        };
        let neg = octant(rays[0].dir);
        let mut walk = BeamWalk {
            frames: [BeamFrame::default(); LEVEL_SLOTS],
            level: None,
        };
        if beam.meets([0.0; 3], f64::from(self.cell_size[0])) {
            let Ok(header) = self.levels[0].header(0, 0) else {
                return false;
            };
            walk.frames[0] = BeamFrame {
                word: 0,
                mask: header as u8,
                remaining: header as u8,
                pos: [0.0; 3],
            };
            walk.level = Some(0);
        }
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
        let mut walks = [Walk::default(); PACKET_RAYS];
        // Rays still looking for their first hit.
        let mut active = [0u8; PACKET_RAYS];
        let mut active_count = 0;
        let mut stack: Stack = [Frame::default(); LEVEL_SLOTS];
        for i in 0..n {
            let mut fault = None;
            let Ok(begun) = self.begin(&rays[i], &mut stack, &mut fault) else {
                return false;
            };
            if fault.is_some() {
                return false;
            }
            match begun {
                Begun::Done(hit) => hits[i] = hit,
                Begun::Walk(walk) => {
                    // The subtree walks start below the beam level, in the
                    // frame the beam was computed in.
                    if walk.stop <= beam_level
                        || walk.q.base != 0.0
                        || !walk.q.moving.all()
                        || walk.q.neg != neg
                    {
                        return false;
                    }
                    walks[i] = walk;
                    active[active_count] = i as u8;
                    active_count += 1;
                }
            }
        }
        let beam_size = self.cell_size[usize::from(beam_level)];
        let mut lanes = [PacketLane::default(); LANES];
        while active_count > 0 && listed > 0 {
            let round = &cells[..listed];
            // Every active ray through this round's cells, several in flight
            // at once (as in `Tracer::trace_lanes`): `lanes[..busy]` each walk
            // one ray through one cell; `next` is the next ray to start.
            let mut next = 0;
            let mut busy = 0;
            let mut done = [false; PACKET_RAYS];
            loop {
                while busy < LANES && next < active_count {
                    let i = usize::from(active[next]);
                    next += 1;
                    let lane = &mut lanes[busy];
                    lane.ray = i as u8;
                    lane.cell = 0;
                    if self.enter_cell(&walks[i], round, beam_size, beam_level, lane) {
                        busy += 1;
                    }
                }
                if busy == 0 {
                    break;
                }
                let mut k = 0;
                while k < busy {
                    let lane = &mut lanes[k];
                    let mut fault = None;
                    let step = self.resume(&mut lane.walk, &mut lane.stack, &mut fault);
                    if fault.is_some() {
                        return false;
                    }
                    match step {
                        None => k += 1,
                        Some(Some(cell)) => {
                            let i = usize::from(lane.ray);
                            let b = usize::from(beam_level);
                            let path = round[usize::from(lane.cell)].path;
                            lane.stack[..b].copy_from_slice(&paths[path..path + b]);
                            match self.finish(&walks[i].ray(), Some(cell), &lane.stack, None) {
                                Ok(hit) => hits[i] = hit,
                                Err(_) => return false,
                            }
                            done[i] = true;
                            busy -= 1;
                            lanes.swap(k, busy);
                        }
                        Some(None) => {
                            // Nothing in this cell: on to the ray's next one.
                            let i = usize::from(lane.ray);
                            lane.cell += 1;
                            if self.enter_cell(&walks[i], round, beam_size, beam_level, lane) {
                                k += 1;
                            } else {
                                busy -= 1;
                                lanes.swap(k, busy);
                            }
                        }
                    }
                }
            }
            // The rays that hit are answered; the others go on to the next round.
            let mut kept = 0;
            for k in 0..active_count {
                if !done[usize::from(active[k])] {
                    active[kept] = active[k];
                    kept += 1;
                }
            }
            active_count = kept;
            if active_count > 0 {
                listed = match self
                    .next_cells(&beam, neg, beam_level, &mut walk, &mut cells, &mut paths)
                {
                    Ok(listed) => listed,
                    Err(()) => return false,
                };
            }
        }
        for &i in &active[..active_count] {
            hits[usize::from(i)] = Hit::MISS;
        }
        true
    }

    /// Starts `lane`'s walk through the first of `cells[lane.cell..]` that
    /// the ray `walk` meets (the slab test its visit starts with, done here
    /// before the cell's header is read: most rays of a packet miss most of
    /// its cells). `false` when it meets none of them.
    #[inline(always)]
    fn enter_cell(
        &self,
        walk: &Walk,
        cells: &[BeamCell],
        size: f32,
        level: u8,
        lane: &mut PacketLane,
    ) -> bool {
        let q = &walk.q;
        while let Some(cell) = cells.get(usize::from(lane.cell)) {
            let t_lo = (cell.pos - q.origin) * q.inv_dir;
            let t_hi = (cell.pos + Vec3A::splat(size) - q.origin) * q.inv_dir;
            if max(t_lo.max_element(), q.tmin) <= min(t_hi.min_element(), q.tmax) {
                lane.walk = Walk {
                    top: level,
                    level,
                    pending: Pending::Node,
                    pos: cell.pos,
                    size,
                    target: cell.word,
                    ..*walk
                };
                return true;
            }
            lane.cell += 1;
        }
        false
    }

    /// The beam of the active rays of a packet, or `None` when it has no
    /// finite extent (which [`Tracer::packet_len`] rules out).
    fn beam(&self, rays: &[Ray]) -> Option<Beam> {
        let first = &rays[0];
        let resolution = f64::from(self.cell_size[0]);
        let mut origin = [0f64; 3];
        for (a, o) in origin.iter_mut().enumerate() {
            let g = (f64::from(first.origin[a]) - self.root_min[a]) * self.grid_scale;
            *o = if octant(first.dir) >> a & 1 == 1 {
                resolution - g
            } else {
                g
            };
        }
        let mut inv_lo = [f64::INFINITY; 3];
        let mut inv_hi = [0f64; 3];
        for ray in rays {
            for a in 0..3 {
                // Grid units per unit of the ray's parameter t.
                let inv = 1.0 / (f64::from(ray.dir[a]) * self.grid_scale).abs();
                inv_lo[a] = inv_lo[a].min(inv);
                inv_hi[a] = inv_hi[a].max(inv);
            }
        }
        let scale = resolution.max(origin.iter().fold(0f64, |m, o| m.max(o.abs())));
        let beam = Beam {
            origin,
            inv_lo,
            inv_hi,
            tmin: f64::from(first.tmin),
            tmax: f64::from(first.tmax),
            // Enlarge by the rounding margin, and by the one of the `f64`
            // arithmetic here (far smaller).
            margin: scale * BEAM_MARGIN,
        };
        let finite = inv_hi.iter().all(|v| v.is_finite()) && origin.iter().all(|v| v.is_finite());
        finite.then_some(beam)
    }

    /// Advances the beam walk to the next (up to [`CELLS_PER_ROUND`]) cells
    /// of the beam level it meets, in front-to-back order; writes them to
    /// `cells` and their paths to `paths`, and returns how many. `Err` on a
    /// read out of range.
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
            let child = FIRST[neg][usize::from(frame.remaining)];
            walk.frames[l].remaining &= !(1 << child);
            let m = usize::from(child) ^ neg;
            let half = f64::from(self.cell_size[l + 1]);
            let pos = [
                frame.pos[0] + (m & 1) as f64 * half,
                frame.pos[1] + (m >> 1 & 1) as f64 * half,
                frame.pos[2] + (m >> 2 & 1) as f64 * half,
            ];
            if !beam.meets(pos, half) {
                continue;
            }
            let rank = (frame.mask & ((1u8 << child) - 1)).count_ones();
            let pointer = self.levels[l]
                .pointer(level, frame.word, rank)
                .map_err(|_| ())?;
            if level + 1 == beam_level {
                let path = listed * LEVEL_SLOTS;
                for (slot, f) in paths[path..path + l + 1].iter_mut().zip(&walk.frames) {
                    *slot = Frame {
                        word: f.word,
                        mask: f.mask,
                        ..Frame::default()
                    };
                }
                prefetch(self.levels[l + 1].bytes, pointer as usize * 4);
                cells[listed] = BeamCell {
                    word: pointer,
                    pos: Vec3A::new(pos[0] as f32, pos[1] as f32, pos[2] as f32),
                    path,
                };
                listed += 1;
                continue;
            }
            let header = self.levels[l + 1]
                .header(level + 1, pointer)
                .map_err(|_| ())?;
            walk.frames[l + 1] = BeamFrame {
                word: pointer,
                mask: header as u8,
                remaining: header as u8,
                pos,
            };
            walk.level = Some(level + 1);
        }
        Ok(listed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
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
}
