//! A chunk of a level's pointers, radix-partitioned by target, so that
//! looking their targets up touches one cache-sized slice of the child
//! level's tables at a time (the 1.0 validator's walk of large levels,
//! `validate`).
//!
//! Following each pointer as the walk reaches it reads the target's entries
//! in tables as large as the child level (hundreds of MB at depth 16): two
//! DRAM misses a pointer. Instead, a chunk of the walk's pointers is first
//! appended, each to the bucket of its target's high bits
//! ([`Partition::push`]: a few hundred sequential streams); each bucket is
//! then resolved in one go ([`Partition::resolve`]), its targets falling in
//! one slice of the tables that stays in the cache, each target replaced by
//! its result (a `u32` code); the walk then reads each pointer's result back
//! from the bucket of its target ([`Partition::next`]): within a bucket the
//! results are in walk order, so one cursor a bucket finds them.
//!
//! Memory: 4 bytes per pointer of the chunk (plus the buckets' unused
//! capacity, address space until written), reused from chunk to chunk.

/// Pointer targets grouped by their high bits, each group in the order
/// pushed, with a read cursor per group. (Staging each bucket's targets in
/// a cache line and writing full lines with non-temporal stores was tried:
/// it cost more CPU time on machine J than plain pushes.)
pub(crate) struct Partition {
    /// A target `p` goes to bucket `p >> shift`.
    shift: u32,
    buckets: Vec<Vec<u32>>,
    /// Per bucket, the results read so far ([`Partition::next`]).
    cursors: Vec<usize>,
}

impl Partition {
    /// Buckets for targets `0..units`, `1 << shift` targets each.
    pub(crate) fn new(units: u64, shift: u32) -> Partition {
        let count = usize::try_from(units.div_ceil(1u64 << shift.min(63)))
            .unwrap_or(usize::MAX)
            .max(1);
        Partition {
            shift,
            buckets: (0..count).map(|_| Vec::new()).collect(),
            cursors: vec![0; count],
        }
    }

    /// Number of buckets.
    pub(crate) fn buckets(&self) -> usize {
        self.buckets.len()
    }

    /// Room for `per_bucket` more pointers in every bucket.
    pub(crate) fn reserve(&mut self, per_bucket: usize) {
        for bucket in &mut self.buckets {
            bucket.reserve(per_bucket);
        }
    }

    /// Empties every bucket (keeping their memory) for the next chunk.
    pub(crate) fn clear(&mut self) {
        self.buckets.iter_mut().for_each(Vec::clear);
        self.cursors.fill(0);
    }

    /// The bucket of target `p` (a target past the last bucket's goes to
    /// the last).
    #[inline(always)]
    fn bucket(&self, p: u32) -> usize {
        ((p >> self.shift.min(31)) as usize).min(self.buckets.len() - 1)
    }

    /// Appends target `p`.
    #[inline(always)]
    pub(crate) fn push(&mut self, p: u32) {
        let b = self.bucket(p);
        if let Some(bucket) = self.buckets.get_mut(b) {
            bucket.push(p);
        }
    }

    /// Replaces every target by `resolve(target)`, bucket after bucket
    /// (each bucket's targets fall in one slice of the child's tables),
    /// calling `slice(first, end)` with the bucket's targets `first..end`
    /// before a bucket that holds some: a sequential read of the slice
    /// brings it into the cache faster than the bucket's random reads do.
    #[inline(always)]
    pub(crate) fn resolve(
        &mut self,
        mut slice: impl FnMut(u64, u64),
        mut resolve: impl FnMut(u32) -> u32,
    ) {
        for (b, bucket) in (0u64..).zip(&mut self.buckets) {
            if bucket.is_empty() {
                continue;
            }
            slice(b << self.shift, (b + 1) << self.shift);
            for p in bucket.iter_mut() {
                *p = resolve(*p);
            }
        }
    }

    /// The result of the next pointer to target `p`, in the order pushed;
    /// `None` when the bucket of `p` holds no more (a walk that does not
    /// repeat the pushes; never in the validator).
    #[inline(always)]
    pub(crate) fn next(&mut self, p: u32) -> Option<u32> {
        let b = self.bucket(p);
        let cursor = self.cursors.get_mut(b)?;
        let bucket = self.buckets.get(b)?;
        let result = *bucket.get(*cursor)?;
        // Two cache lines ahead in the bucket: its results arrive before
        // they are read (the buckets are too many for the hardware's
        // stream prefetchers).
        if let Some(ahead) = bucket.get(*cursor + PREFETCH_AHEAD) {
            prefetch(ahead);
        }
        *cursor += 1;
        Some(result)
    }
}

/// How far ahead of its cursor a bucket is fetched: two cache lines.
const PREFETCH_AHEAD: usize = 32;

/// Asks for the cache line holding `*at` (a hint: no effect on results).
#[inline(always)]
fn prefetch<T>(at: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // SAFETY: SSE is part of the x86-64 baseline; a prefetch reads
        // nothing and faults on no address.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(std::ptr::from_ref(at).cast()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = at;
}

/// The shift that gives buckets whose slice of the child's tables holds
/// at most about `slice_bytes`, for targets `0..units` with tables of
/// `table_bytes` in all; at least 6 (64 units, one record-start block of a
/// node level).
pub(crate) fn shift_for(units: u64, table_bytes: u64, slice_bytes: u64) -> u32 {
    let slices = table_bytes.div_ceil(slice_bytes.max(1)).max(1);
    let per_bucket = units.div_ceil(slices).max(1);
    // The power of two at most `per_bucket`: slices no larger than asked.
    let shift = u64::BITS - 1 - per_bucket.leading_zeros();
    shift.max(6)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn results_come_back_in_push_order_per_target() {
        let units = 10_000u64;
        let mut partition = Partition::new(units, 7);
        assert_eq!(partition.buckets(), 79);
        let mut h = 1u64;
        for chunk in 0..3 {
            let mut targets = Vec::new();
            for _ in 0..20_000 {
                h = h
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let p = ((h >> 33) % units) as u32;
                targets.push(p);
                partition.push(p);
            }
            // Each result says which push it answers: its target and how
            // many pushes to the same bucket came before.
            let mut seen = vec![0u32; 79];
            let mut previous_bucket = 0;
            let mut slices = 0;
            partition.resolve(
                |_, _| slices += 1,
                |p| {
                    let b = (p >> 7) as usize;
                    // Bucket after bucket.
                    assert!(b >= previous_bucket);
                    previous_bucket = b;
                    seen[b] += 1;
                    p | (seen[b] - 1) << 14
                },
            );
            assert_eq!(slices, 79);
            let mut pushed = vec![0u32; 79];
            for &p in &targets {
                let b = (p >> 7) as usize;
                assert_eq!(
                    partition.next(p),
                    Some(p | pushed[b] << 14),
                    "chunk {chunk}"
                );
                pushed[b] += 1;
            }
            // Nothing more in any bucket.
            assert!(
                (0..units as u32)
                    .step_by(128)
                    .all(|p| partition.next(p).is_none())
            );
            partition.clear();
        }
    }

    #[test]
    fn shifts_give_slices_no_larger_than_asked() {
        for (units, table_bytes, slice) in [
            (1u64 << 28, 3u64 << 27, 1u64 << 20),
            (1_000_000, 1_500_000, 256 << 10),
            (100, 150, 1 << 20),
            (5_000_000_000, 1 << 33, 1 << 20),
        ] {
            let shift = shift_for(units, table_bytes, slice);
            assert!(shift >= 6);
            let buckets = units.div_ceil(1 << shift);
            let per_slice = table_bytes.div_ceil(buckets);
            if shift > 6 {
                assert!(
                    per_slice <= 2 * slice,
                    "{units} {table_bytes} {slice}: {shift}"
                );
                // Not needlessly small either.
                assert!(
                    per_slice * 4 > slice,
                    "{units} {table_bytes} {slice}: {shift}"
                );
            }
        }
    }
}
