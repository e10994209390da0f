//! Tracing many rays on all cores.

use rayon::prelude::*;

use crate::tracer::{TraceError, Tracer};
use dagfmt::batch::{Hit, Ray};

/// Rays handed to one rayon task: large enough to amortise scheduling, small
/// enough to balance rays of very different cost.
const CHUNK: usize = 1024;

impl Tracer<'_> {
    /// Traces every ray on all cores (rayon's global pool). Fails with the
    /// first error met (a malformed DAG, or a ray level deeper than the DAG).
    pub fn trace_batch(&self, rays: &[Ray]) -> Result<Vec<Hit>, TraceError> {
        let mut hits = vec![Hit::MISS; rays.len()];
        self.trace_batch_into(rays, &mut hits)?;
        Ok(hits)
    }

    /// [`Tracer::trace_batch`] into a caller's buffer (no allocation): hit `i`
    /// answers ray `i`; when the lengths differ only the common prefix is
    /// traced.
    pub fn trace_batch_into(&self, rays: &[Ray], hits: &mut [Hit]) -> Result<(), TraceError> {
        rays.par_chunks(CHUNK)
            .zip(hits.par_chunks_mut(CHUNK))
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
