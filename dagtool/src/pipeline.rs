//! The out-of-core, parallel voxelization pipeline.
//!
//! The volume is split into chunks of `2^c` voxels per axis (subtrees at
//! level `D - c`). Triangles are binned into the chunks they touch (exactly:
//! the same conservative test at chunk size). Chunks are voxelized on all
//! cores in batches, and each batch's bricks come out in Morton order, so the
//! caller can push them into one streaming [`dagfmt::builder::DagBuilder`]
//! whose per-level hash tables deduplicate across chunks. Memory is the mesh,
//! the bins, one chunk buffer per worker and two batches in flight; it never
//! grows with the resolution.

use std::ops::Range;
use std::sync::Mutex;
use std::sync::mpsc::sync_channel;

use rayon::prelude::*;

use crate::geom::SUBVOXEL;
use crate::mesh::SnappedMesh;
use crate::solid::{ChunkCrossings, ColumnParity, fill_inside};
use crate::voxelize::{ChunkBuffer, ChunkPlace, rasterize_triangle};

/// How to fill the interior.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SolidMode {
    /// Surface only.
    Surface,
    /// Inside = odd number of crossings along z (for closed meshes).
    ParityZ,
    /// Inside = odd number of crossings along at least two of x, y, z (open meshes).
    Vote,
}

impl SolidMode {
    fn axes(self) -> &'static [usize] {
        match self {
            SolidMode::Surface => &[],
            SolidMode::ParityZ => &[2],
            SolidMode::Vote => &[0, 1, 2],
        }
    }
}

/// Settings of one voxelization.
#[derive(Clone, Copy, Debug)]
pub struct VoxelizeConfig {
    /// Depth D of the volume.
    pub depth: u8,
    /// log2 of the chunk side (2 ..= 7, at most D).
    pub chunk_bits: u32,
    /// Surface or solid.
    pub solid: SolidMode,
    /// Keep, per voxel, the index of the first triangle that set it (for colours).
    pub tags: bool,
    /// Chunks per parallel batch.
    pub batch: usize,
}

impl VoxelizeConfig {
    /// Chunk levels: the chunk grid is `2^(D - c)` chunks per axis.
    pub fn chunk_levels(&self) -> u32 {
        u32::from(self.depth) - self.chunk_bits
    }

    /// Shift from a chunk's Morton code to the brick codes inside it.
    pub fn brick_shift(&self) -> u32 {
        3 * (self.chunk_bits - 2)
    }
}

/// The triangles of each non-empty chunk, chunks in Morton order.
#[derive(Debug, Default)]
pub struct Bins {
    /// Morton code of each non-empty chunk, increasing.
    pub codes: Vec<u64>,
    /// Range in `triangles` of each chunk's triangles.
    pub ranges: Vec<Range<usize>>,
    /// Triangle indices, increasing within each chunk.
    pub triangles: Vec<u32>,
}

impl Bins {
    /// Bins every triangle of `mesh` into the chunks of side `2^bits` voxels
    /// whose closed cube it intersects.
    pub fn new(mesh: &SnappedMesh, depth: u8, bits: u32) -> Bins {
        Bins::new_within(mesh, depth, bits, None)
    }

    /// Bins the triangles of `mesh` into the chunks of side `2^bits` voxels
    /// whose closed cube they intersect, only for the chunks of the box
    /// `within` (inclusive chunk coordinates; `None`: every chunk). The bins
    /// are exactly those of [`Bins::new`] for the chunks of the box: a
    /// triangle's chunks are clipped to the box before the exact test, and a
    /// triangle whose bounding box misses the box costs a comparison.
    pub fn new_within(
        mesh: &SnappedMesh,
        depth: u8,
        bits: u32,
        within: Option<([i64; 3], [i64; 3])>,
    ) -> Bins {
        let levels = u32::from(depth) - bits;
        let last = (1i64 << levels) - 1;
        let (lo, hi) = within.map_or(([0; 3], [last; 3]), |(lo, hi)| {
            (lo.map(|c| c.max(0)), hi.map(|c| c.min(last)))
        });
        let s = SUBVOXEL << bits;
        let mut pairs: Vec<(u64, u32)> = (0..mesh.triangles.len() as u32)
            .into_par_iter()
            .with_min_len(1024)
            .fold(Vec::new, |mut out, t| {
                let tri = mesh.triangle(t);
                rasterize_triangle(&tri, s, lo, hi, &mut |c: [i64; 3]| {
                    out.push((
                        dagfmt::morton::encode(c[0] as u32, c[1] as u32, c[2] as u32),
                        t,
                    ));
                });
                out
            })
            .reduce(Vec::new, |mut a, mut b| {
                if a.len() < b.len() {
                    std::mem::swap(&mut a, &mut b);
                }
                a.extend_from_slice(&b);
                a
            });
        pairs.par_sort_unstable();
        let mut bins = Bins {
            triangles: Vec::with_capacity(pairs.len()),
            ..Default::default()
        };
        let mut start = 0;
        for (i, &(code, t)) in pairs.iter().enumerate() {
            if i > 0 && pairs[i - 1].0 != code {
                bins.codes.push(pairs[i - 1].0);
                bins.ranges.push(start..i);
                start = i;
            }
            bins.triangles.push(t);
        }
        if let Some(&(code, _)) = pairs.last() {
            bins.codes.push(code);
            bins.ranges.push(start..pairs.len());
        }
        bins
    }

    /// Keeps only the chunks whose Morton code passes `keep`.
    pub fn retain(&mut self, mut keep: impl FnMut(u64) -> bool) {
        let old = std::mem::take(self);
        for (i, &code) in old.codes.iter().enumerate() {
            if keep(code) {
                let start = self.triangles.len();
                self.triangles
                    .extend_from_slice(&old.triangles[old.ranges[i].clone()]);
                self.codes.push(code);
                self.ranges.push(start..self.triangles.len());
            }
        }
    }

    /// Bytes held.
    pub fn heap_bytes(&self) -> usize {
        self.codes.len() * (8 + 16) + self.triangles.len() * 4
    }

    /// Triangle-chunk pairs.
    pub fn len(&self) -> usize {
        self.triangles.len()
    }

    /// Whether no triangle touches any chunk.
    pub fn is_empty(&self) -> bool {
        self.triangles.is_empty()
    }
}

/// The voxels of one chunk, ready for the builder.
#[derive(Debug, Default)]
pub struct ChunkOutput {
    /// Morton code of the chunk in the chunk grid.
    pub code: u64,
    /// Non-empty bricks: (brick Morton code inside the chunk, 64-bit mask), in order.
    pub bricks: Vec<(u32, u64)>,
    /// With tags: per set voxel in Morton order, the first triangle that set it
    /// ([`crate::voxelize::NO_TAG`] for voxels of the solid fill).
    pub tags: Vec<u32>,
}

/// A pool of chunk buffers shared by the workers.
struct BufferPool {
    bits: u32,
    tags: bool,
    free: Mutex<Vec<ChunkBuffer>>,
}

impl BufferPool {
    fn take(&self) -> ChunkBuffer {
        let buf = self.free.lock().expect("pool lock").pop();
        buf.unwrap_or_else(|| ChunkBuffer::new(self.bits, self.tags))
    }

    fn put(&self, buf: ChunkBuffer) {
        self.free.lock().expect("pool lock").push(buf);
    }
}

fn place_of(cfg: &VoxelizeConfig, code: u64) -> ChunkPlace {
    let c = dagfmt::morton::decode(code);
    ChunkPlace {
        depth: u32::from(cfg.depth),
        bits: cfg.chunk_bits,
        origin: c.map(|v| i64::from(v) << cfg.chunk_bits),
    }
}

fn drain(buf: &mut ChunkBuffer, code: u64, tags: bool) -> ChunkOutput {
    let mut out = ChunkOutput {
        code,
        ..Default::default()
    };
    buf.drain(|brick, mask, t| {
        out.bricks.push((brick, mask));
        if tags && let Some(t) = t {
            let mut bits = mask;
            while bits != 0 {
                out.tags.push(t[bits.trailing_zeros() as usize]);
                bits &= bits - 1;
            }
        }
    });
    out
}

/// Counters of one run.
#[derive(Clone, Copy, Debug, Default)]
pub struct PipelineReport {
    /// Chunks holding triangles.
    pub surface_chunks: u64,
    /// Chunks without triangles filled by the solid fill.
    pub fill_chunks: u64,
    /// Peak bytes of the solid column parity state.
    pub parity_bytes: usize,
}

/// Voxelizes `mesh` chunk by chunk and hands the chunk outputs, in Morton
/// order, to `sink` (on the calling thread, while the workers go on with the
/// next batch). `progress` is called with the number of surface chunks done.
/// Stops at the first error of `sink`.
pub fn run<E: Send>(
    mesh: &SnappedMesh,
    bins: &Bins,
    cfg: &VoxelizeConfig,
    progress: &(dyn Fn(u64) + Sync),
    mut sink: impl FnMut(Vec<ChunkOutput>) -> Result<(), E>,
) -> Result<PipelineReport, E> {
    let (tx, rx) = sync_channel::<Vec<ChunkOutput>>(2);
    let pool = BufferPool {
        bits: cfg.chunk_bits,
        tags: cfg.tags,
        free: Mutex::new(Vec::new()),
    };
    std::thread::scope(|scope| {
        let producer = scope.spawn(|| {
            let tx = tx;
            let mut report = PipelineReport::default();
            match cfg.solid {
                SolidMode::Surface => {
                    for batch in bins.codes.chunks(cfg.batch.max(1)).enumerate() {
                        let (bi, codes) = batch;
                        let first = bi * cfg.batch.max(1);
                        let outs: Vec<ChunkOutput> = codes
                            .par_iter()
                            .enumerate()
                            .map(|(i, &code)| {
                                let mut buf = pool.take();
                                let place = place_of(cfg, code);
                                for &t in &bins.triangles[bins.ranges[first + i].clone()] {
                                    buf.add_triangle(&place, &mesh.triangle(t), t);
                                }
                                let out = drain(&mut buf, code, cfg.tags);
                                pool.put(buf);
                                out
                            })
                            .collect();
                        report.surface_chunks += codes.len() as u64;
                        progress(report.surface_chunks);
                        if tx.send(outs).is_err() {
                            break;
                        }
                    }
                }
                SolidMode::ParityZ | SolidMode::Vote => {
                    solid_producer(mesh, bins, cfg, &pool, progress, &tx, &mut report);
                }
            }
            report
        });
        let mut result = Ok(());
        for outs in rx.iter() {
            if let Err(e) = sink(outs) {
                result = Err(e);
                break;
            }
        }
        // Dropping the receiver stops the producer at its next send.
        drop(rx);
        let report = producer.join().expect("voxelization worker panicked");
        result.map(|()| report)
    })
}

/// A chunk on its way through the solid fill.
struct SolidJob {
    code: u64,
    buf: Option<ChunkBuffer>,
    crossings: Vec<ChunkCrossings>,
    incoming: Vec<Option<Box<[u64]>>>,
}

fn solid_producer(
    mesh: &SnappedMesh,
    bins: &Bins,
    cfg: &VoxelizeConfig,
    pool: &BufferPool,
    progress: &(dyn Fn(u64) + Sync),
    tx: &std::sync::mpsc::SyncSender<Vec<ChunkOutput>>,
    report: &mut PipelineReport,
) {
    let axes = cfg.solid.axes();
    let batch = cfg.batch.max(1);
    let mut parity: Vec<ColumnParity> = axes.iter().map(|_| ColumnParity::default()).collect();
    let total_chunks: u64 = 1u64 << (3 * cfg.chunk_levels());
    let mut next_code = 0u64;
    let mut pending: Vec<SolidJob> = Vec::new();
    let flush = |pending: &mut Vec<SolidJob>| -> bool {
        let jobs = std::mem::take(pending);
        let outs: Vec<ChunkOutput> = jobs
            .into_par_iter()
            .map(|job| {
                let mut buf = job.buf.unwrap_or_else(|| pool.take());
                let crossings: Vec<Option<&ChunkCrossings>> = if job.crossings.is_empty() {
                    vec![None; axes.len()]
                } else {
                    job.crossings.iter().map(Some).collect()
                };
                let incoming: Vec<Option<&[u64]>> =
                    job.incoming.iter().map(|b| b.as_deref()).collect();
                fill_inside(&mut buf, cfg.chunk_bits, axes, &crossings, &incoming);
                let out = drain(&mut buf, job.code, cfg.tags);
                pool.put(buf);
                out
            })
            .collect();
        tx.send(outs).is_ok()
    };
    let mut bi = 0usize;
    loop {
        // Phase 1 (parallel): surface voxels and crossings of the next batch
        // of chunks that hold triangles.
        let end = (bi + batch).min(bins.codes.len());
        let phase1: Vec<SolidJob> = (bi..end)
            .into_par_iter()
            .map(|j| {
                let code = bins.codes[j];
                let place = place_of(cfg, code);
                let mut buf = pool.take();
                let mut crossings: Vec<ChunkCrossings> = axes
                    .iter()
                    .map(|&a| ChunkCrossings::new(cfg.chunk_bits, a))
                    .collect();
                for &t in &bins.triangles[bins.ranges[j].clone()] {
                    let tri = mesh.triangle(t);
                    buf.add_triangle(&place, &tri, t);
                    for c in &mut crossings {
                        c.add_triangle(&place, &tri);
                    }
                }
                SolidJob {
                    code,
                    buf: Some(buf),
                    crossings,
                    incoming: Vec::new(),
                }
            })
            .collect();
        let upto = if end < bins.codes.len() {
            bins.codes[end - 1]
        } else {
            total_chunks - 1
        };
        // Phase 2 (in Morton order): the parity entering each chunk; chunks
        // without triangles below the surface are filled too.
        let mut phase1 = phase1.into_iter().peekable();
        let mut code = next_code;
        while code <= upto && code < total_chunks {
            if parity.iter().all(ColumnParity::is_empty) {
                // Nothing below is inside: jump to the next chunk with triangles.
                match phase1.peek() {
                    Some(j) if j.code > code => code = j.code,
                    Some(_) => {}
                    None => break,
                }
            }
            let coords = dagfmt::morton::decode(code).map(u64::from);
            if phase1.peek().is_some_and(|j| j.code == code) {
                let mut job = phase1.next().expect("peeked");
                job.incoming = axes
                    .iter()
                    .enumerate()
                    .map(|(i, &a)| parity[i].enter(a, coords, Some(job.crossings[i].through())))
                    .collect();
                pending.push(job);
            } else if axes
                .iter()
                .enumerate()
                .any(|(i, &a)| parity[i].is_active(a, coords))
            {
                let incoming = axes
                    .iter()
                    .enumerate()
                    .map(|(i, &a)| parity[i].enter(a, coords, None))
                    .collect();
                pending.push(SolidJob {
                    code,
                    buf: None,
                    crossings: Vec::new(),
                    incoming,
                });
                report.fill_chunks += 1;
            }
            if pending.len() >= batch && !flush(&mut pending) {
                return;
            }
            code += 1;
        }
        report.parity_bytes = report
            .parity_bytes
            .max(parity.iter().map(ColumnParity::heap_bytes).sum());
        next_code = upto + 1;
        report.surface_chunks += (end - bi) as u64;
        progress(report.surface_chunks);
        bi = end;
        if bi >= bins.codes.len() && next_code >= total_chunks {
            break;
        }
    }
    if !pending.is_empty() {
        flush(&mut pending);
    }
}
