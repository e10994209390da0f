//! The batch API of [`Tracer`]: many rays on one thread, in vector lanes or
//! packets ([`Tracer::trace_sequential_into`]; [`Tracer::trace_batch`], in
//! module `parallel`, runs it on every core).
//!
//! The layers of the CPU tracer, each using only those below it:
//!
//! 1. `node`: the decoding of node records, references and leaf masks (the
//!    one place that knows the file's layout of them);
//! 2. `walk`: the [`Tracer`] itself, its traversal state (`Walk`, `Frame`,
//!    `Prepared`) and the scalar steps every path runs (`begin`, `resume`,
//!    `brick`, `finish`), which [`Tracer::trace`] runs ray by ray; `cpu`
//!    (processor features) beside it;
//! 3. `simd` (eight or sixteen rays to a vector) and `packet` (coherent rays
//!    sharing one walk of the coarse levels, with its own vector kernels in
//!    `packet::avx2`; it sets rays up with `simd::setup4`), and `grid`;
//! 4. this module: which rays go to packets, to the lanes or one by one.

use dagfmt::batch::{Hit, Ray};

use crate::walk::{TraceError, Tracer, prefetch_range};

/// The most rays [`Tracer::trace_runs`] looks at for packets before it
/// traces those that start none in the lanes. Looking at every ray of a
/// large incoherent batch first and tracing them afterwards read the rays
/// from memory twice: on machine G, one call for 1 M random d12 rays took
/// 169–176 ms against 159–164 ms with this limit (three alternating rounds
/// of nine; 8,192 and 32,768 did as well). 16,384 rays (512 KiB) stay in a
/// second-level cache. The lanes empty at the end of each run: for tasks of
/// 4,096 rays that cost 0.9 % more instructions (see `parallel::MAX_CHUNK`),
/// here a quarter of it.
const LANES_RUN_MAX: usize = 16_384;

impl Tracer<'_> {
    /// Traces every ray on the calling thread: hit `i` answers ray `i` (when
    /// the lengths differ only the common prefix is traced). The answers are
    /// those of [`Tracer::trace`] (up to the choice among tied cells where a
    /// ray of a packet passes exactly through a shared edge or corner, see
    /// below). It is faster than calling it for each ray because it keeps
    /// several rays in flight, eight to an AVX2 vector where the processor
    /// has it, so that the memory latency of one ray's reads is spent
    /// advancing the others; and because, in DAGs small enough for the caches
    /// (64 MiB, `PACKET_MAX_DAG_BYTES`), runs of up to 64 consecutive rays with the
    /// same origin, bounds and level and directions in one octant (primary
    /// rays, best in tiles: [`crate::camera::CameraFrame::rays_in_tiles`]) are
    /// traced as packets, sharing one walk of the coarse levels. The rays of
    /// an image row by row (a run of rays from one origin whose directions
    /// step smoothly along rows of at least 16, module `grid`) are traced
    /// tile by tile, each 8×8 tile as a packet. Where the processor has AVX2
    /// all of this runs in code compiled for it (with BMI, POPCNT and LZCNT).
    /// Fails with the first error met, in the order the rays are traced.
    pub fn trace_sequential_into(&self, rays: &[Ray], hits: &mut [Hit]) -> Result<(), TraceError> {
        let count = rays.len().min(hits.len());
        let (rays, hits) = (&rays[..count], &mut hits[..count]);
        if !self.packets {
            return self.trace_lanes(rays, hits);
        }
        #[cfg(target_arch = "x86_64")]
        if crate::cpu::available() {
            // SAFETY: `cpu::available` found the features.
            return unsafe { self.trace_runs_avx2(rays, hits) };
        }
        self.trace_runs::<true>(rays, hits)
    }

    /// [`Tracer::trace_runs`] compiled for the processors with AVX2 (and the
    /// bit-manipulation instructions that come with it).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,bmi1,bmi2,popcnt,lzcnt,fma")]
    unsafe fn trace_runs_avx2(&self, rays: &[Ray], hits: &mut [Hit]) -> Result<(), TraceError> {
        self.trace_runs::<true>(rays, hits)
    }

    /// The rays of a row-major image `grid` (module `grid`) on the calling
    /// thread, tile by tile; for the batch API's tasks.
    pub(crate) fn trace_image_sequential(
        &self,
        rays: &[Ray],
        hits: &mut [Hit],
        grid: crate::grid::ImageGrid,
    ) -> Result<(), TraceError> {
        #[cfg(target_arch = "x86_64")]
        if crate::cpu::available() {
            // SAFETY: `cpu::available` found the features.
            return unsafe { self.trace_image_avx2(rays, hits, grid) };
        }
        self.trace_image(rays, hits, grid)
    }

    /// [`Tracer::trace_image`] compiled like [`Tracer::trace_runs_avx2`].
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,bmi1,bmi2,popcnt,lzcnt,fma")]
    unsafe fn trace_image_avx2(
        &self,
        rays: &[Ray],
        hits: &mut [Hit],
        grid: crate::grid::ImageGrid,
    ) -> Result<(), TraceError> {
        self.trace_image(rays, hits, grid)
    }

    /// The batch with packets: row-major images of rays (with `IMAGES`) are
    /// traced tile by tile (module `grid`), other runs of coherent rays as
    /// packets (module `packet`), the rest through the interleaved lanes.
    #[inline(always)]
    fn trace_runs<const IMAGES: bool>(
        &self,
        rays: &[Ray],
        hits: &mut [Hit],
    ) -> Result<(), TraceError> {
        let count = rays.len().min(hits.len());
        let mut i = 0;
        let mut run = 0;
        // The start (origin, bounds, level) of the last run looked at for an
        // image: each run is looked at once.
        let mut looked_at: Option<&Ray> = None;
        while i < count {
            // The rays looked at are traced before the look goes much
            // further, while they are still in the caches (see
            // `LANES_RUN_MAX`).
            if i - run >= LANES_RUN_MAX {
                self.trace_lanes(&rays[run..i], &mut hits[run..i])?;
                run = i;
            }
            if !crate::packet::may_start_packet(&rays[i..count]) {
                i += 1;
                continue;
            }
            if IMAGES && looked_at.is_none_or(|r| !crate::grid::same_start(r, &rays[i])) {
                looked_at = Some(&rays[i]);
                if let Some(grid) = crate::grid::find_grid(&rays[i..count]) {
                    self.trace_lanes(&rays[run..i], &mut hits[run..i])?;
                    let end = i + grid.len();
                    self.trace_image(&rays[i..end], &mut hits[i..end], grid)?;
                    i = end;
                    run = i;
                    continue;
                }
            }
            let shape = self.packet_shape(&rays[i..count]);
            let n = shape.len;
            if n == 0 {
                i += 1;
                continue;
            }
            self.trace_lanes(&rays[run..i], &mut hits[run..i])?;
            // The next packet's hits are written soon.
            prefetch_range(
                hits.get(i + n..(i + n + crate::packet::PACKET_RAYS).min(count))
                    .unwrap_or_default(),
            );
            if !self.trace_packet(&rays[i..i + n], &mut hits[i..i + n], &shape) {
                self.trace_lanes(&rays[i..i + n], &mut hits[i..i + n])?;
            }
            i += n;
            run = i;
        }
        self.trace_lanes(&rays[run..count], &mut hits[run..count])
    }

    /// The rays of a row-major image (`grid`, found by `grid::find_grid`),
    /// tile by tile: each tile's rays are gathered, traced as a batch of
    /// their own (a packet where they make one), and their hits scattered
    /// back.
    #[inline(always)]
    fn trace_image(
        &self,
        rays: &[Ray],
        hits: &mut [Hit],
        grid: crate::grid::ImageGrid,
    ) -> Result<(), TraceError> {
        const TILE_RAYS: usize = crate::grid::TILE_WIDTH * crate::grid::TILE_HEIGHT;
        let mut tile_rays = [rays[0]; TILE_RAYS];
        let mut tile_hits = [Hit::MISS; TILE_RAYS];
        let tiles = crate::grid::tiles(grid);
        let mut ahead = tiles.clone();
        ahead.next();
        for tile in tiles {
            // The next tile's rays and hits, in rows far apart, are read and
            // written soon: start their reads now (the hardware prefetchers
            // do not follow this many streams).
            if let Some(next) = ahead.next() {
                if next.is_full() {
                    next.for_each_block_row(|_, i| {
                        prefetch_range(rays.get(i..i + 4).unwrap_or_default());
                        prefetch_range(hits.get(i..i + 4).unwrap_or_default());
                    });
                } else {
                    let next = next.runs();
                    for &(i, len) in &next.runs[..next.len] {
                        prefetch_range(rays.get(i..i + len).unwrap_or_default());
                        prefetch_range(hits.get(i..i + len).unwrap_or_default());
                    }
                }
            }
            if tile.is_full() {
                // The usual tile: its sixteen 4-ray runs copied as arrays,
                // from the positions of its blocks' rows.
                tile.for_each_block_row(|n, i| {
                    let from: &[Ray; 4] = rays[i..i + 4].try_into().expect("four");
                    let to: &mut [Ray; 4] = (&mut tile_rays[n..n + 4]).try_into().expect("four");
                    *to = *from;
                });
                self.trace_tile(&tile_rays, &mut tile_hits)?;
                tile.for_each_block_row(|n, i| {
                    let from: &[Hit; 4] = tile_hits[n..n + 4].try_into().expect("four");
                    let to: &mut [Hit; 4] = (&mut hits[i..i + 4]).try_into().expect("four");
                    *to = *from;
                });
                continue;
            }
            // A tile at an edge, run by run.
            let tile_runs = tile.runs();
            let runs = &tile_runs.runs[..tile_runs.len];
            let mut n = 0;
            for &(i, len) in runs {
                tile_rays[n..n + len].copy_from_slice(&rays[i..i + len]);
                n += len;
            }
            self.trace_tile(&tile_rays[..n], &mut tile_hits[..n])?;
            let mut n = 0;
            for &(i, len) in runs {
                hits[i..i + len].copy_from_slice(&tile_hits[n..n + len]);
                n += len;
            }
        }
        Ok(())
    }

    /// The rays of one tile of an image, gathered: mostly one packet of the
    /// whole tile, else run by run.
    #[inline(always)]
    fn trace_tile(&self, tile: &[Ray], hits: &mut [Hit]) -> Result<(), TraceError> {
        let shape = if crate::packet::may_start_packet(tile) {
            self.packet_shape(tile)
        } else {
            crate::packet::PacketShape::NONE
        };
        if shape.len != tile.len() || !self.trace_packet(tile, hits, &shape) {
            self.trace_runs::<false>(tile, hits)?;
        }
        Ok(())
    }

    /// [`Tracer::trace_sequential_into`] without packets: several rays in
    /// flight, eight to a vector where the processor has AVX2 (module `simd`),
    /// else [`Tracer::trace_lanes_scalar`]. The answers are the same either way.
    pub(crate) fn trace_lanes(&self, rays: &[Ray], hits: &mut [Hit]) -> Result<(), TraceError> {
        // Often empty: `trace_sequential_into` calls it for the rays between
        // two packets. Setting up the lanes costs some kilobytes of stores.
        if rays.is_empty() || hits.is_empty() {
            return Ok(());
        }
        #[cfg(target_arch = "x86_64")]
        if crate::cpu::available() {
            return crate::simd::trace_lanes(self, rays, hits);
        }
        self.trace_lanes_scalar(rays, hits)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Lanes;
    use crate::testing::Rng;
    use crate::walk::{CHILD_STEPS, Setup};
    use dagfmt::Dag;
    use dagfmt::builder::DagBuilder;
    use dagfmt::layout::AttributeKind;
    use glam::Vec3A;

    /// A DAG of depth 6 with random clusters of voxels, counts in the nodes.
    fn scene(rng: &mut Rng) -> Vec<u8> {
        let mut voxels = Vec::new();
        for _ in 0..6 {
            let center = [0; 3].map(|_| (rng.next() % 64) as i64);
            for _ in 0..200 {
                let v = center.map(|c| (c + (rng.next() % 9) as i64 - 4).clamp(0, 63) as u32);
                voxels.push(v);
            }
        }
        let built =
            DagBuilder::from_voxels(6, AttributeKind::VoxelCount, voxels).expect("valid voxels");
        built.to_bytes()
    }

    #[test]
    fn brick_in_node_is_brick() {
        let mut rng = Rng(0xb41c);
        let bytes = scene(&mut rng);
        let dag = Dag::open(&bytes).expect("built DAG opens");
        let tracer = Tracer::new(&dag).expect("tracer");
        let leaves = tracer.levels[usize::from(tracer.leaf_level)].bytes.len() / 8;
        let (mut compared, mut found) = (0, 0);
        for i in 0..100_000 {
            // Generic rays, and rays on the grid's planes with small integer
            // directions: ties between planes, ends on faces.
            let (origin, dir) = if i % 2 == 0 {
                (
                    [0; 3].map(|_| rng.range(-0.5, 1.5)),
                    [0; 3].map(|_| rng.range(-1.0, 1.0)),
                )
            } else {
                (
                    [0; 3].map(|_| (rng.next() % 80) as f32 / 64.0 - 0.1),
                    [0; 3].map(|_| (rng.next() % 5) as f32 - 2.0),
                )
            };
            let ray = Ray {
                origin,
                dir,
                tmin: if i % 3 == 0 { rng.range(0.0, 0.5) } else { 0.0 },
                tmax: if i % 5 == 0 {
                    rng.range(0.2, 2.0)
                } else {
                    f32::INFINITY
                },
                level: (i % 7 == 0).then_some(5),
            };
            let Ok(Setup::Trace(p)) = tracer.setup(&ray) else {
                continue;
            };
            // A node of edge 8 on the ray's path through the occupied box.
            let Some(q) = tracer.clip(&p) else {
                continue;
            };
            let t = rng.range(q.tmin, q.tmax);
            let point = q.origin + Vec3A::splat(t) / q.inv_dir;
            let node = point
                .to_array()
                .map(|v| ((v / 8.0).floor() * 8.0).clamp(0.0, 56.0));
            let pos = Vec3A::from_array(node);
            let planes = (
                (pos - p.origin) * p.inv_dir,
                (pos + Vec3A::splat(4.0) - p.origin) * p.inv_dir,
                (pos + Vec3A::splat(8.0) - p.origin) * p.inv_dir,
            );
            let child = (rng.next() % 8) as usize;
            let brick_pos = pos + CHILD_STEPS[child] * 4.0;
            let leaf = (rng.next() % leaves as u64) as u32;
            let mut fault = None;
            let expected = tracer.brick(&p, leaf, 0, brick_pos, &mut fault);
            assert!(fault.is_none());
            let got = tracer.brick_in_node(&p, leaf, 0, brick_pos, child, planes);
            assert_eq!(got, Ok(expected), "{ray:?} node {node:?} child {child}");
            compared += 1;
            found += usize::from(expected.is_some());
        }
        assert!(
            compared > 25_000 && found > 2500,
            "{compared} compared, {found} found"
        );
        // A leaf outside its level.
        let p = match tracer.setup(&Ray {
            origin: [-1.0; 3],
            dir: [1.0; 3],
            tmin: 0.0,
            tmax: f32::INFINITY,
            level: None,
        }) {
            Ok(Setup::Trace(p)) => p,
            _ => unreachable!("a ray through the cube"),
        };
        let z = Vec3A::ZERO;
        assert_eq!(
            tracer.brick_in_node(&p, leaves as u32, 0, z, 0, (z, z, z)),
            Err(())
        );
    }

    /// Rays from around the cube towards it, some with a level of detail,
    /// some with a zero direction or a bounded segment.
    fn rays(rng: &mut Rng, count: usize) -> Vec<Ray> {
        (0..count)
            .map(|i| {
                let origin = [0; 3].map(|_| rng.range(-0.5, 1.5));
                let target = [0; 3].map(|_| rng.range(0.0, 1.0));
                let dir = if i % 97 == 0 {
                    [0.0; 3]
                } else {
                    [0, 1, 2].map(|a| target[a] - origin[a])
                };
                Ray {
                    origin,
                    dir,
                    tmin: if i % 5 == 0 { rng.range(0.0, 0.5) } else { 0.0 },
                    tmax: if i % 7 == 0 {
                        rng.range(0.2, 1.5)
                    } else {
                        f32::INFINITY
                    },
                    level: (i % 11 == 0).then(|| (rng.next() % 7) as u8),
                }
            })
            .collect()
    }

    #[test]
    fn interleaved_batches_answer_like_single_rays() {
        let mut rng = Rng(7);
        for _ in 0..8 {
            let bytes = scene(&mut rng);
            let dag = Dag::open(&bytes).expect("built DAG opens");
            let tracer = Tracer::new(&dag).expect("tracer");
            let rays = rays(&mut rng, 3000);
            let hits = lanes_agree_with_single_rays(&tracer, &rays);
            let hit_count = hits.iter().filter(|h| h.hit).count();
            assert!(hit_count > rays.len() / 10, "{hit_count} hits");
        }
    }

    /// A batch of several times `LANES_RUN_MAX` rays, incoherent rays with
    /// runs of one origin among them (packets) on either side of the points
    /// where the lanes' runs are cut: every answer is `trace()`'s.
    #[test]
    fn long_batches_cut_into_lane_runs_answer_like_single_rays() {
        let mut rng = Rng(41);
        // Deep enough for packets: six solid boxes of 24³ voxels in 1024³.
        let mut voxels = Vec::new();
        for _ in 0..6 {
            let corner = [0; 3].map(|_| (rng.next() % 1000) as u32);
            for i in 0..24 * 24 * 24 {
                let offset = [i % 24, i / 24 % 24, i / 576];
                voxels.push([0, 1, 2].map(|a| corner[a] + offset[a]));
            }
        }
        let bytes = DagBuilder::from_voxels(10, AttributeKind::VoxelCount, voxels)
            .expect("valid voxels")
            .to_bytes();
        let dag = Dag::open(&bytes).expect("built DAG opens");
        let tracer = Tracer::new(&dag).expect("tracer");
        let mut batch = Vec::new();
        let mut packets = 0;
        while batch.len() < 6 * LANES_RUN_MAX {
            // Stretches of incoherent rays up to 2.5 lane runs long.
            let incoherent = LANES_RUN_MAX / 2 + (rng.next() % (2 * LANES_RUN_MAX as u64)) as usize;
            batch.extend(rays(&mut rng, incoherent));
            // A run of 64 rays from one origin below the cube's corner, in
            // a narrow cone towards it (a packet).
            let origin = [0; 3].map(|_| rng.range(-0.4, -0.1));
            let aim = [0; 3].map(|_| rng.range(0.2, 0.8));
            let start = batch.len();
            batch.extend((0..64).map(|i| {
                let step = [i % 4, i / 4 % 4, i / 16].map(|k| 0.002 * k as f32);
                Ray {
                    origin,
                    dir: [0, 1, 2].map(|a| aim[a] + step[a] - origin[a]),
                    tmin: 0.0,
                    tmax: f32::INFINITY,
                    level: None,
                }
            }));
            packets += usize::from(tracer.packet_len(&batch[start..]) == 64);
        }
        assert!(packets >= 3, "{packets} packets");
        // No answer of a trace: a ray left out shows.
        let untraced = Hit {
            hit: true,
            t: -1.0,
            voxel: [u32::MAX; 3],
            ..Hit::MISS
        };
        let mut hits = vec![untraced; batch.len()];
        tracer
            .trace_sequential_into(&batch, &mut hits)
            .expect("valid DAG traces");
        let mut hit_count = 0;
        for (ray, hit) in batch.iter().zip(&hits) {
            assert_eq!(
                *hit,
                tracer.trace(ray).expect("valid DAG traces"),
                "{ray:?}"
            );
            hit_count += usize::from(hit.hit);
        }
        assert!(hit_count > batch.len() / 100, "{hit_count} hits");
    }

    /// Traces `rays` with the batch API, its scalar and (where the processor
    /// has it) vector lanes, and checks every answer against `trace()`.
    fn lanes_agree_with_single_rays(tracer: &Tracer<'_>, rays: &[Ray]) -> Vec<Hit> {
        let single: Vec<Hit> = rays
            .iter()
            .map(|r| tracer.trace(r).expect("valid DAG traces"))
            .collect();
        let mut hits = vec![Hit::MISS; rays.len()];
        tracer
            .trace_sequential_into(rays, &mut hits)
            .expect("valid DAG traces");
        for ((ray, a), b) in rays.iter().zip(&single).zip(&hits) {
            assert_eq!(a, b, "batch: {ray:?}");
        }
        let mut scalar = vec![Hit::MISS; rays.len()];
        tracer
            .trace_lanes_scalar(rays, &mut scalar)
            .expect("valid DAG traces");
        for ((ray, a), b) in rays.iter().zip(&single).zip(&scalar) {
            assert_eq!(a, b, "scalar lanes: {ray:?}");
        }
        #[cfg(target_arch = "x86_64")]
        if crate::cpu::available() {
            // Both numbers of groups in flight, whatever the DAG's size, both
            // ways of gathering, whatever the processor, and eight and (where
            // the processor has AVX-512) sixteen lanes.
            let widths: &[bool] = if crate::cpu::wide_available() {
                &[false, true]
            } else {
                eprintln!("no AVX-512 on this processor: the sixteen lanes were not tested");
                &[false]
            };
            for &wide in widths {
                // (Sixteen lanes take the same groups for every DAG.)
                let smalls: &[bool] = if wide { &[false] } else { &[true, false] };
                for &small in smalls {
                    for loads in [false, true] {
                        let mut vector = vec![Hit::MISS; rays.len()];
                        let how = crate::simd::LaneChoice { small, loads, wide };
                        assert!(
                            crate::simd::trace_lanes_or_give_up(tracer, rays, &mut vector, how),
                            "the vector lanes gave up on a valid DAG"
                        );
                        for ((ray, a), b) in rays.iter().zip(&single).zip(&vector) {
                            assert_eq!(a, b, "vector lanes ({how:?}): {ray:?}");
                        }
                    }
                }
            }
        } else {
            eprintln!("no AVX2 on this processor: the vector lanes were not tested");
        }
        single
    }

    #[test]
    fn lanes_answer_like_single_rays_in_deep_dags() {
        // Scattered voxels make wide levels (pointers of 2 and 3 bytes) and
        // long descents; depths up to 21, the deepest the format allows.
        let mut rng = Rng(23);
        for (depth, voxels) in [(10u8, 3000usize), (14, 60_000), (17, 120_000), (21, 2000)] {
            let side = 1u64 << depth;
            let mut cells = Vec::with_capacity(voxels);
            for i in 0..voxels {
                // Half in a few dense clumps, half scattered.
                let v = if i % 2 == 0 {
                    [0; 3].map(|_| (rng.next() % side) as u32)
                } else {
                    let clump = (i / 2 % 5) as u64 * side / 6 + side / 12;
                    [0; 3].map(|_| (clump + rng.next() % 16) as u32)
                };
                cells.push(v);
            }
            let built = DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, cells)
                .expect("valid voxels");
            let bytes = built.to_bytes();
            let dag = Dag::open(&bytes).expect("built DAG opens");
            let widths: Vec<u8> = dag.levels().iter().map(|l| l.pointer_width).collect();
            let tracer = Tracer::new(&dag).expect("tracer");
            // A third of the rays aimed into the cube from their origin.
            let mut rays = rays(&mut rng, 1500);
            for (i, ray) in rays.iter_mut().enumerate().filter(|(i, _)| i % 3 == 0) {
                let v = [0; 3].map(|_| rng.range(0.0, 1.0));
                ray.dir = [0, 1, 2].map(|a| v[a] - ray.origin[a]);
                // Some from far away (re-based by the set-up), some nearly
                // parallel to an axis (a component treated as zero).
                if i % 4 == 0 {
                    ray.origin = [0, 1, 2].map(|a| v[a] - ray.dir[a] * 300.0);
                } else if i % 5 == 0 {
                    ray.dir[i % 3] *= 1e-19;
                }
            }
            let hits = lanes_agree_with_single_rays(&tracer, &rays);
            assert!(hits.iter().any(|h| h.hit), "depth {depth}: no hit");
            if depth == 17 {
                assert!(
                    widths.iter().any(|&w| w >= 3),
                    "depth {depth}: widths {widths:?}"
                );
            }
        }
    }

    /// Format 2.0 (spec §23): the vector lanes trace the 2.0 encoding of
    /// random scenes (shared, reflected and sequential children, wide
    /// references in the deep ones) without giving up, with the per-ray
    /// answers, which are the 1.0 tracer's.
    #[test]
    fn lanes_trace_format_2_like_single_rays_and_like_1_0() {
        let mut rng = Rng(0x2f2);
        for round in 0..6 {
            let bytes = if round % 2 == 0 {
                scene(&mut rng)
            } else {
                // Scattered voxels and clumps, each mirrored in x.
                let depth = if round == 5 { 13u8 } else { 10 };
                let side = 1u32 << depth;
                let mut cells: Vec<[u32; 3]> = (0..20_000)
                    .map(|i| {
                        if i % 2 == 0 {
                            [0; 3].map(|_| (rng.next() % u64::from(side)) as u32)
                        } else {
                            let clump = (i / 2 % 5) * side / 6 + side / 12;
                            [0; 3].map(|_| clump + (rng.next() % 24) as u32)
                        }
                    })
                    .collect();
                let mirrored: Vec<[u32; 3]> = cells
                    .iter()
                    .map(|&[x, y, z]| [side - 1 - x, y, z])
                    .collect();
                cells.extend(mirrored);
                DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, cells)
                    .expect("valid voxels")
                    .to_bytes()
            };
            let dag = Dag::open(&bytes).expect("built DAG opens");
            let enc = dagfmt::v2::encode(&dag).expect("valid DAG encodes");
            let v1 = Tracer::new(&dag).expect("tracer");
            // The levels alone (the lanes read each section only), and the
            // 2.0 file (whose records at the end of a section the lanes
            // gather with the bytes after it). Both from one buffer: levels
            // in separate allocations may lie too far apart for the lanes'
            // 32-bit offsets (then the batch goes to the scalar steps).
            let file = dagfmt::v2file::upgrade(&dag).expect("valid DAG upgrades");
            let dag2 = dagfmt::Dag2::open(&file).expect("2.0 file opens");
            assert!(
                dag2.levels()
                    .iter()
                    .zip(enc.views())
                    .all(|(a, b)| a.bytes == b.bytes)
            );
            // Through the expanded levels (spec §23.12), made here or
            // shared, and in place.
            let expansion = crate::Expansion::new(dag2.levels()).expect("a valid DAG expands");
            let tracers = [
                Tracer::from_v2_levels(dag2.header(), dag2.levels(), None).expect("2.0 tracer"),
                Tracer::from_v2(&dag2).expect("2.0 tracer of the file"),
                Tracer::from_v2_expansion(&dag2, &expansion).expect("2.0 tracer, shared"),
                Tracer::from_v2_levels_in_place(dag2.header(), dag2.levels(), None)
                    .expect("2.0 tracer"),
                Tracer::from_v2_in_place(&dag2).expect("2.0 tracer of the file"),
            ];
            for (i, v2) in tracers.iter().enumerate() {
                assert_eq!(v2.is_expanded(), i < 3);
            }
            assert_eq!(tracers[2].expanded_bytes(), expansion.bytes());
            // An expansion of other levels is refused, not traced.
            let other = dagfmt::v2file::upgrade(&Dag::open(&scene(&mut rng)).unwrap()).unwrap();
            let other = dagfmt::Dag2::open(&other).unwrap();
            assert!(Tracer::from_v2_expansion(&other, &expansion).is_err());
            let rays = rays(&mut rng, 3000);
            for v2 in &tracers {
                let hits = lanes_agree_with_single_rays(v2, &rays);
                for (ray, hit) in rays.iter().zip(&hits) {
                    assert_eq!(*hit, v1.trace(ray).expect("1.0 traces"), "{ray:?}");
                }
                assert!(hits.iter().filter(|h| h.hit).count() > 100, "round {round}");
            }
        }
    }

    /// Format 2.0 files with random bytes of their level sections changed
    /// (references, codes and headers that name records elsewhere, cut the
    /// chain of record starts or run past a section): the batch API in
    /// eight and (where the processor has AVX-512) sixteen lanes gives each
    /// ray the answer or the error of a single ray, and a batch fails
    /// exactly when one of its rays does.
    #[test]
    fn lanes_report_malformed_2_0_dags_like_single_rays() {
        let mut rng = Rng(0x2ba);
        let bytes = scene(&mut rng);
        let file = dagfmt::v2file::upgrade(&Dag::open(&bytes).unwrap()).expect("upgrades");
        let dag2 = dagfmt::Dag2::open(&file).expect("2.0 file opens");
        let levels: Vec<(usize, usize)> = dag2
            .levels()
            .iter()
            .map(|l| {
                (
                    l.bytes.as_ptr() as usize - file.as_ptr() as usize,
                    l.bytes.len(),
                )
            })
            .collect();
        let (first, end) = (levels[0].0, levels.last().map(|&(o, n)| o + n).unwrap());
        let (mut errors, mut traced) = (0, 0);
        for case in 0..200 {
            let mut corrupt = file.clone();
            for _ in 0..1 + case % 3 {
                let at = first + (rng.next() % (end - first) as u64) as usize;
                corrupt[at] = rng.next() as u8;
            }
            let Ok(dag) = dagfmt::Dag2::open(&corrupt) else {
                continue;
            };
            let Ok(tracer) = Tracer::from_v2(&dag) else {
                continue;
            };
            let rays = rays(&mut rng, 40);
            errors += malformed_lanes_agree_with_single_rays(&tracer, &rays);
            // In place, whether or not the levels expanded.
            let in_place = Tracer::from_v2_in_place(&dag).expect("made as the other");
            errors += malformed_lanes_agree_with_single_rays(&in_place, &rays);
            traced += 2;
        }
        assert!(
            traced > 100 && errors > 0,
            "{traced} traced, {errors} errors"
        );
    }

    #[test]
    fn interleaved_batches_report_malformed_dags_like_single_rays() {
        let mut rng = Rng(11);
        let bytes = scene(&mut rng);
        let first = Dag::open(&bytes).expect("built DAG opens").levels()[0].file_offset as usize;
        let mut errors = 0;
        for case in 0..200 {
            let mut corrupt = bytes.clone();
            for _ in 0..1 + case % 4 {
                let at = first + (rng.next() % (corrupt.len() - first) as u64) as usize;
                corrupt[at] = rng.next() as u8;
            }
            let Ok(dag) = Dag::open(&corrupt) else {
                continue;
            };
            let Ok(tracer) = Tracer::new(&dag) else {
                continue;
            };
            let rays = rays(&mut rng, 40);
            errors += malformed_lanes_agree_with_single_rays(&tracer, &rays);
        }
        assert!(
            errors > 0,
            "some corruption must lead a pointer out of range"
        );
    }

    /// In eight and (where the processor has AVX-512) sixteen lanes, each ray
    /// of a batch gets the answer or the error of a single ray, and a whole
    /// batch fails exactly when one of its rays does. Returns the errors seen.
    fn malformed_lanes_agree_with_single_rays(tracer: &Tracer<'_>, rays: &[Ray]) -> usize {
        let mut errors = 0;
        for lanes in [Lanes::Eight, Lanes::Sixteen] {
            let tracer = tracer.clone().with_lanes(lanes);
            for ray in rays {
                let mut hit = [Hit::MISS];
                let batch = tracer.trace_sequential_into(std::slice::from_ref(ray), &mut hit);
                match (tracer.trace(ray), batch) {
                    (Ok(single), Ok(())) => assert_eq!(single, hit[0], "{lanes:?}: {ray:?}"),
                    (Err(a), Err(b)) => {
                        assert_eq!(a, b);
                        errors += 1;
                    }
                    (a, b) => panic!("{lanes:?}: single {a:?}, batch {b:?}"),
                }
            }
            let mut hits = vec![Hit::MISS; rays.len()];
            let any_error = rays.iter().any(|r| tracer.trace(r).is_err());
            assert_eq!(
                tracer.trace_sequential_into(rays, &mut hits).is_err(),
                any_error
            );
        }
        errors
    }
}
