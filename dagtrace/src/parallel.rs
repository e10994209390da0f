//! Tracing many rays on all cores.

use rayon::prelude::*;

use crate::grid;
use crate::walk::{TraceError, Tracer};
use dagfmt::batch::{Hit, Ray};

/// The fewest rays handed to one rayon task: enough to amortise scheduling.
const CHUNK: usize = 1024;

/// Tasks per thread that [`Tracer::trace_batch_into`] aims at for batches
/// too small for tasks of [`MAX_CHUNK`] rays, so that every thread gets work.
const TASKS_PER_THREAD: usize = 8;

/// The most rays handed to one rayon task. Every task ends with its vector
/// lanes emptying one by one: with 1024 rays a task, that costs d12 random
/// rays 3.5 % more instructions than one batch, with 4096 about 0.9 %; and a
/// thread left without work at the end of a batch waits for at most one
/// task (4096 random d12 rays: about 1 ms).
const MAX_CHUNK: usize = 4096;

impl Tracer<'_> {
    /// Traces every ray on all cores (rayon's global pool). Fails with the
    /// first error met (a malformed DAG, or a ray level deeper than the DAG).
    /// Each call allocates the answers; to trace frame after frame, reuse a
    /// buffer with [`Tracer::trace_batch_into`].
    pub fn trace_batch(&self, rays: &[Ray]) -> Result<Vec<Hit>, TraceError> {
        // The answer vector is filled on all cores too: the first write to
        // each of its pages (a page fault, the page zeroed) costs more than
        // the write, and for a 1920x1080 frame (83 MB of answers) one
        // thread doing it all took a sizeable share of the frame.
        let mut hits = Vec::with_capacity(rays.len());
        hits.par_extend(rayon::iter::repeat_n(Hit::MISS, rays.len()));
        self.trace_batch_into(rays, &mut hits)?;
        Ok(hits)
    }

    /// [`Tracer::trace_batch`] into a caller's buffer (no allocation): hit `i`
    /// answers ray `i`; when the lengths differ only the common prefix is
    /// traced. Row-major images of rays (see [`Tracer::trace_sequential_into`])
    /// are split into strips of 8 rows, traced tile by tile; the other rays
    /// into chunks.
    pub fn trace_batch_into(&self, rays: &[Ray], hits: &mut [Hit]) -> Result<(), TraceError> {
        let count = rays.len().min(hits.len());
        let (rays, hits) = (&rays[..count], &mut hits[..count]);
        if !self.packets {
            return self.trace_chunks(rays, hits);
        }
        let mut done = 0;
        for (start, image) in grid::images(rays) {
            self.trace_chunks(&rays[done..start], &mut hits[done..start])?;
            let end = start + image.len();
            let strip = image.width * grid::TILE;
            rays[start..end]
                .par_chunks(strip)
                .zip(hits[start..end].par_chunks_mut(strip))
                .try_for_each(|(rays, hits)| {
                    let rows = rays.len() / image.width;
                    let strip = grid::ImageGrid {
                        width: image.width,
                        rows,
                    };
                    self.trace_image_sequential(rays, hits, strip)
                })?;
            done = end;
        }
        self.trace_chunks(&rays[done..], &mut hits[done..])
    }

    /// `rays` in chunks on all cores: of [`MAX_CHUNK`] rays, or fewer (down to
    /// [`CHUNK`]) for [`TASKS_PER_THREAD`] a thread.
    fn trace_chunks(&self, rays: &[Ray], hits: &mut [Hit]) -> Result<(), TraceError> {
        let chunk = (rays.len() / (rayon::current_num_threads() * TASKS_PER_THREAD))
            .clamp(CHUNK, MAX_CHUNK);
        rays.par_chunks(chunk)
            .zip(hits.par_chunks_mut(chunk))
            .try_for_each(|(rays, hits)| self.trace_sequential_into(rays, hits))
    }

    /// Any-hit queries for every ray on all cores: `true` where the ray is blocked.
    pub fn occluded_batch(&self, rays: &[Ray]) -> Result<Vec<bool>, TraceError> {
        let mut blocked = vec![false; rays.len()];
        rays.par_chunks(CHUNK)
            .zip(blocked.par_chunks_mut(CHUNK))
            .try_for_each(|(rays, out)| {
                for (ray, b) in rays.iter().zip(out) {
                    *b = self.occluded(ray)?;
                }
                Ok(())
            })?;
        Ok(blocked)
    }
}
