//! A cache hint shared by the passes that read tables in an order the file
//! chooses (the validator's walks, the 2.0 encoder's gathers and scatters):
//! their time goes mostly to independent cache misses, which asking early
//! overlaps.

/// Asks the cache for the line holding `*at` (a hint: it changes no result).
#[inline(always)]
pub(crate) fn prefetch<T>(at: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        // SAFETY: SSE is part of the x86-64 baseline; a prefetch reads
        // nothing into the program and faults on no address (the pointer
        // comes from a reference anyway).
        unsafe { _mm_prefetch::<_MM_HINT_T0>(std::ptr::from_ref(at).cast()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = at;
}
