//! Voxelizing triangles into one chunk (a cube of `2^c` voxels, `c <= 7`).
//!
//! Surface: every voxel whose closed cube intersects a closed triangle is set
//! (conservative voxelization). The test is the 13-axis separating axis test
//! evaluated exactly (see [`crate::geom`]), organised like Schwarz and Seidel's
//! "Fast parallel surface and solid voxelization on GPUs" (2010) so that it
//! costs a few integer operations per voxel:
//!
//! - `w` is the axis along which the triangle's normal is largest, `u`, `v` the
//!   other two;
//! - for each row of voxels along `u` (fixed `v`), the three edge axes of the
//!   projection along `w` give the exact span of `u` (one division per edge
//!   and row);
//! - for each column `(u, v)` in that span, the triangle's plane gives the exact
//!   range of `w` (tracked incrementally along the row: no division);
//! - each voxel of that range is checked against the six edge axes of the
//!   projections along `u` and `v`.
//!
//! The voxel bounding box supplies the three box axes. Degenerate triangles
//! (segments, points) go through the same code: their zero axes never separate.
//!
//! Solid: see [`crate::solid`].

use crate::geom::{Int, SUBVOXEL, Triangle, edge_constraints, normal, solve_linear};

/// Largest chunk side, log2 (so that one column of a chunk fits a `u128`).
pub const MAX_CHUNK_BITS: u32 = 7;
/// Smallest chunk side, log2 (one 4^3 brick).
pub const MIN_CHUNK_BITS: u32 = 2;

/// `SPREAD[x]` spreads the 7 bits of `x` to bits 0, 3, 6, ... (local Morton codes).
const SPREAD: [u32; 128] = {
    let mut t = [0u32; 128];
    let mut i = 0;
    while i < 128 {
        let mut v = 0u32;
        let mut b = 0;
        while b < 7 {
            v |= ((i as u32 >> b) & 1) << (3 * b);
            b += 1;
        }
        t[i] = v;
        i += 1;
    }
    t
};

/// Local Morton code of a voxel inside a chunk.
#[inline]
pub fn local_morton(x: u32, y: u32, z: u32) -> u32 {
    SPREAD[x as usize] | (SPREAD[y as usize] << 1) | (SPREAD[z as usize] << 2)
}

/// Where a chunk lies in the volume.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ChunkPlace {
    /// Depth of the volume.
    pub depth: u32,
    /// log2 of the chunk side in voxels.
    pub bits: u32,
    /// Voxel coordinates of the chunk's minimum corner.
    pub origin: [i64; 3],
}

impl ChunkPlace {
    /// Side length in voxels.
    #[inline]
    pub fn side(&self) -> i64 {
        1 << self.bits
    }
}

/// Voxel occupancy of one chunk in 4^3 bricks, indexed by local brick Morton
/// code so that draining it yields bricks in Morton order.
#[derive(Debug)]
pub struct ChunkBuffer {
    bits: u32,
    bricks: Vec<u64>,
    occupied: Vec<u64>,
    /// Per voxel (local Morton code): the tag of the first triangle that set it.
    tags: Option<Vec<u32>>,
}

/// Tag of voxels set by the solid fill (no triangle).
pub const NO_TAG: u32 = u32::MAX;

impl ChunkBuffer {
    /// An empty buffer for chunks of side `2^bits`; `with_tags` keeps, per voxel,
    /// the tag of the first triangle that set it (for colours).
    pub fn new(bits: u32, with_tags: bool) -> Self {
        assert!((MIN_CHUNK_BITS..=MAX_CHUNK_BITS).contains(&bits));
        let bricks = 1usize << (3 * (bits - 2));
        ChunkBuffer {
            bits,
            bricks: vec![0; bricks],
            occupied: vec![0; bricks.div_ceil(64)],
            tags: with_tags.then(|| vec![NO_TAG; 1 << (3 * bits)]),
        }
    }

    /// log2 of the chunk side.
    pub fn bits(&self) -> u32 {
        self.bits
    }

    /// Sets the voxel with local Morton code `m`.
    #[inline(always)]
    pub fn set(&mut self, m: u32, tag: u32) {
        let brick = (m >> 6) as usize;
        let bit = 1u64 << (m & 63);
        match &mut self.tags {
            None => {
                // Branch-free: which voxels are already set is unpredictable.
                self.bricks[brick] |= bit;
                self.occupied[brick >> 6] |= 1 << (brick & 63);
            }
            Some(tags) => {
                let old = self.bricks[brick];
                if old & bit == 0 {
                    self.bricks[brick] = old | bit;
                    self.occupied[brick >> 6] |= 1 << (brick & 63);
                    tags[m as usize] = tag;
                }
            }
        }
    }

    /// ORs a whole brick mask in (voxels not set before get `tag`).
    #[inline]
    pub fn or_brick(&mut self, brick: usize, mask: u64, tag: u32) {
        let old = self.bricks[brick];
        let new = mask & !old;
        if new == 0 {
            return;
        }
        if old == 0 {
            self.occupied[brick >> 6] |= 1 << (brick & 63);
        }
        self.bricks[brick] = old | new;
        if let Some(tags) = &mut self.tags {
            let mut bits = new;
            while bits != 0 {
                let b = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                tags[brick * 64 + b] = tag;
            }
        }
    }

    /// Whether any voxel is set.
    pub fn is_empty(&self) -> bool {
        self.occupied.iter().all(|&w| w == 0)
    }

    /// Calls `f(local_brick, mask, tags)` for every non-empty brick in Morton
    /// order (`tags` holds the brick's 64 voxel tags when kept) and clears the
    /// buffer.
    pub fn drain(&mut self, mut f: impl FnMut(u32, u64, Option<&[u32]>)) {
        for wi in 0..self.occupied.len() {
            let mut word = std::mem::take(&mut self.occupied[wi]);
            while word != 0 {
                let brick = wi * 64 + word.trailing_zeros() as usize;
                word &= word - 1;
                let mask = std::mem::take(&mut self.bricks[brick]);
                match &mut self.tags {
                    Some(tags) => {
                        let t = &mut tags[brick * 64..brick * 64 + 64];
                        f(brick as u32, mask, Some(t));
                        t.fill(NO_TAG);
                    }
                    None => f(brick as u32, mask, None),
                }
            }
        }
    }

    /// Sets every voxel of `place` whose closed cube intersects the closed
    /// triangle `tri` (lattice units, global), tagging new voxels with `tag`.
    pub fn add_triangle(&mut self, place: &ChunkPlace, tri: &Triangle, tag: u32) {
        debug_assert_eq!(place.bits, self.bits);
        let last = (1i64 << place.depth) - 1;
        let lo = place.origin.map(|o| o.max(0));
        let hi = place.origin.map(|o| (o + place.side() - 1).min(last));
        let mut sink = ChunkSink {
            buf: self,
            origin: place.origin,
            tag,
        };
        rasterize_triangle(tri, SUBVOXEL, lo, hi, &mut sink);
    }
}

/// Receives the voxels found by [`rasterize_triangle`] as runs along one axis.
pub trait RunVisitor {
    /// Voxels `c` with `c[w]` in `w0 ..= w1` (the other two coordinates as in `c`).
    fn run(&mut self, c: [i64; 3], w: usize, w0: i64, w1: i64);
}

impl<F: FnMut([i64; 3])> RunVisitor for F {
    #[inline]
    fn run(&mut self, mut c: [i64; 3], w: usize, w0: i64, w1: i64) {
        for k in w0..=w1 {
            c[w] = k;
            self(c);
        }
    }
}

struct ChunkSink<'a> {
    buf: &'a mut ChunkBuffer,
    origin: [i64; 3],
    tag: u32,
}

impl RunVisitor for ChunkSink<'_> {
    #[inline(always)]
    fn run(&mut self, c: [i64; 3], w: usize, w0: i64, w1: i64) {
        let mut fixed = 0u32;
        for a in 0..3 {
            if a != w {
                fixed |= SPREAD[(c[a] - self.origin[a]) as usize] << a;
            }
        }
        if self.buf.tags.is_some() {
            for k in w0..=w1 {
                let m = fixed | (SPREAD[(k - self.origin[w]) as usize] << w);
                self.buf.set(m, self.tag);
            }
            return;
        }
        // Without tags: set the bits, and mark each brick occupied once per
        // run rather than once per voxel (a run stays in a brick for up to 4
        // voxels; the repeated read-modify-write of one word was the cost).
        let mut previous = usize::MAX;
        for k in w0..=w1 {
            let m = fixed | (SPREAD[(k - self.origin[w]) as usize] << w);
            let brick = (m >> 6) as usize;
            self.buf.bricks[brick] |= 1u64 << (m & 63);
            if brick != previous {
                self.buf.occupied[brick >> 6] |= 1 << (brick & 63);
                previous = brick;
            }
        }
    }
}

/// Tracks `floor(n(i) / m)` exactly while `n` grows by a constant step per
/// increment of `i`: one addition and one comparison per step, no division.
#[derive(Clone, Copy, Debug)]
struct FloorTracker<T> {
    q: T,
    r: T,
    qd: T,
    rd: T,
    m: T,
}

impl<T: Int> FloorTracker<T> {
    /// Starts at `n0 / m` with step `step` (`m > 0`).
    #[inline]
    fn new(n0: T, step: T, m: T) -> Self {
        let q = n0.div_floor(m);
        let qd = step.div_floor(m);
        FloorTracker {
            q,
            r: n0 - q * m,
            qd,
            rd: step - qd * m,
            m,
        }
    }

    /// Restarts at `n0` with the same step.
    #[inline]
    fn reset(&mut self, n0: T) {
        self.q = n0.div_floor(self.m);
        self.r = n0 - self.q * self.m;
    }

    #[inline(always)]
    fn advance(&mut self) {
        self.q = self.q + self.qd;
        self.r = self.r + self.rd;
        if self.r >= self.m {
            self.r = self.r - self.m;
            self.q = self.q + T::ONE;
        }
    }
}

/// Calls `visit` with every voxel of size `s` (lattice units; voxel `k`
/// spans `[k s, (k + 1) s]`) inside the inclusive box `[lo, hi]` whose closed
/// cube intersects the closed triangle `tri`, as runs along one axis.
///
/// Exact for any lattice coordinates below 2^40 and `s` a power of two up to
/// 2^40. Used with `s = SUBVOXEL` for voxels and `s = SUBVOXEL * C` to find the
/// chunks a triangle touches.
pub fn rasterize_triangle(
    tri: &Triangle,
    s: i64,
    lo: [i64; 3],
    hi: [i64; 3],
    visit: &mut impl RunVisitor,
) {
    let mut lo = lo;
    let mut hi = hi;
    let mut base = [0i64; 3];
    let mut extent = 0i64;
    for a in 0..3 {
        let mn = tri[0][a].min(tri[1][a]).min(tri[2][a]);
        let mx = tri[0][a].max(tri[1][a]).max(tri[2][a]);
        // Voxel k's closed cube [k s, (k+1) s] meets [mn, mx] iff
        // ceil(mn / s) - 1 <= k <= floor(mx / s).
        lo[a] = lo[a].max(mn.div_euclid(s) + i64::from(mn.rem_euclid(s) != 0) - 1);
        hi[a] = hi[a].min(mx.div_euclid(s));
        if lo[a] > hi[a] {
            return;
        }
        base[a] = mn.div_euclid(s) - 1;
        extent = extent.max(mx - base[a] * s);
    }
    // Local lattice coordinates lie in [0, extent]; voxel corners in
    // [0, extent + s]. Every product of the edge tests is below
    // 2 (extent + 2 s)^2, so i64 suffices below 2^30.
    if extent + 2 * s < 1 << 30 {
        rasterize_local::<i64>(tri, s, lo, hi, base, visit);
    } else {
        rasterize_local::<i128>(tri, s, lo, hi, base, visit);
    }
}

fn rasterize_local<T: Int>(
    tri: &Triangle,
    s: i64,
    lo: [i64; 3],
    hi: [i64; 3],
    base: [i64; 3],
    visit: &mut impl RunVisitor,
) {
    let st = T::from_i64(s);
    // Local lattice coordinates (relative to voxel `base`).
    let local: Triangle = tri.map(|p| [0, 1, 2].map(|a| p[a] - base[a] * s));
    let p: [[T; 3]; 3] = local.map(|q| q.map(T::from_i64));
    let mut n = normal(&local);
    let w = if n[2].abs() >= n[0].abs() && n[2].abs() >= n[1].abs() {
        2
    } else if n[0].abs() >= n[1].abs() {
        0
    } else {
        1
    };
    let u = (w + 1) % 3;
    let v = (w + 2) % 3;
    // Local voxel index ranges (relative to `base`).
    let lo_l = [0, 1, 2].map(|a| lo[a] - base[a]);
    let hi_l = [0, 1, 2].map(|a| hi[a] - base[a]);
    // Projection along w, axes (u, v): per row (fixed v), a span of u.
    let (cw, ncw) = edge_constraints(&p, u, v, st);
    let cw = &cw[..ncw];
    // Projection along u, axes (v, w): per row, an interval of w.
    let (cu, ncu) = edge_constraints(&p, v, w, st);
    let cu = &cu[..ncu];
    // Projection along v, axes (w, u): per column, an interval of w that moves
    // with u, tracked exactly; constraints without w restrict u for all rows.
    let (cv, ncv) = edge_constraints(&p, w, u, st);
    let mut u_lo = lo_l[u];
    let mut u_hi = hi_l[u];
    // (lower-bound numerator at u = 0, upper-bound numerator at u = 0, step, divisor)
    let mut vbounds: [(T, T, T, T); 3] = [(T::ZERO, T::ZERO, T::ZERO, T::ONE); 3];
    let mut nvb = 0;
    for c in &cv[..ncv] {
        // lo <= k1 w + k2 u <= hi
        if c.k1 == T::ZERO {
            let (a, b) = solve_linear(c.k2, c.lo, c.hi);
            u_lo = u_lo.max(a);
            u_hi = u_hi.min(b);
        } else if c.k1 > T::ZERO {
            // w >= ceil((lo - k2 u) / k1) = floor((lo - k2 u + k1 - 1) / k1); w <= floor((hi - k2 u) / k1)
            vbounds[nvb] = (c.lo + c.k1 - T::ONE, c.hi, -c.k2, c.k1);
            nvb += 1;
        } else {
            // (-k1) w in [k2 u - hi, k2 u - lo]
            let m = -c.k1;
            vbounds[nvb] = (-c.hi + m - T::ONE, -c.lo, c.k2, m);
            nvb += 1;
        }
    }
    if u_lo > u_hi {
        return;
    }
    // The w interval of each u from the projection along v does not depend
    // on v: computed once per triangle (exactly, by tracking the quotients).
    let nu = (u_hi - u_lo + 1) as usize;
    let mut vproj: Vec<(i64, i64)> = Vec::new();
    if nvb > 0 {
        vproj.reserve_exact(nu);
        let ut = T::from_i64(u_lo);
        let mut tracks: [(FloorTracker<T>, FloorTracker<T>); 3] = std::array::from_fn(|i| {
            let (a, b, step, m) = if i < nvb {
                vbounds[i]
            } else {
                (T::ZERO, T::ZERO, T::ZERO, T::ONE)
            };
            (
                FloorTracker::new(a + step * ut, step, m),
                FloorTracker::new(b + step * ut, step, m),
            )
        });
        for _ in 0..nu {
            let mut wa = lo_l[w];
            let mut wb = hi_l[w];
            for t in &mut tracks[..nvb] {
                wa = wa.max(t.0.q.clamp_i64());
                wb = wb.min(t.1.q.clamp_i64());
                t.0.advance();
                t.1.advance();
            }
            vproj.push((wa, wb));
        }
    }

    // Plane: normalise so n_w >= 0. With n = 0 (degenerate) there is no plane axis.
    if n[w] < 0 {
        n = n.map(|c| -c);
    }
    let s128 = i128::from(s);
    let d: i128 = (0..3).map(|a| n[a] * i128::from(local[0][a])).sum();
    let rlo: i128 = n.iter().map(|&c| c.min(0) * s128).sum();
    let rhi: i128 = n.iter().map(|&c| c.max(0) * s128).sum();
    let m = n[w] * s128; // > 0 unless degenerate
    let plane = m > 0;
    // s n_w w in [A(u), A(u) + rhi - rlo] with A(u) = d - rhi - s n_u u - s n_v v.
    let mut plane_lo = FloorTracker::<i128>::new(0, -s128 * n[u], m.max(1));
    let mut plane_hi = plane_lo;
    let clamp = |x: i128| x.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64;

    let mut c = [0i64; 3];
    for iv in lo_l[v]..=hi_l[v] {
        // Span of u from the projection along w.
        let mut ua = u_lo;
        let mut ub = u_hi;
        let ivt = T::from_i64(iv);
        for e in cw {
            let k2v = e.k2 * ivt;
            let (a, b) = solve_linear(e.k1, e.lo - k2v, e.hi - k2v);
            ua = ua.max(a);
            ub = ub.min(b);
        }
        if ua > ub {
            continue;
        }
        // Interval of w from the projection along u (fixed for the row).
        let mut row_wa = lo_l[w];
        let mut row_wb = hi_l[w];
        for e in cu {
            let k1v = e.k1 * ivt;
            let (a, b) = solve_linear(e.k2, e.lo - k1v, e.hi - k1v);
            row_wa = row_wa.max(a);
            row_wb = row_wb.min(b);
        }
        if row_wa > row_wb {
            continue;
        }
        if plane {
            let a0 = d - rhi - s128 * n[u] * i128::from(ua) - s128 * n[v] * i128::from(iv);
            plane_lo.reset(a0 + m - 1);
            plane_hi.reset(a0 + (rhi - rlo));
        }
        c[v] = iv + base[v];
        for iu in ua..=ub {
            let mut wa = row_wa;
            let mut wb = row_wb;
            if plane {
                wa = wa.max(clamp(plane_lo.q));
                wb = wb.min(clamp(plane_hi.q));
                plane_lo.advance();
                plane_hi.advance();
            }
            if let Some(&(a, b)) = vproj.get((iu - u_lo) as usize) {
                wa = wa.max(a);
                wb = wb.min(b);
            }
            if wa <= wb {
                c[u] = iu + base[u];
                visit.run(c, w, wa + base[w], wb + base[w]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::triangle_overlaps_box;
    use proptest::prelude::*;

    /// Voxels of `tri` in the window `[lo, hi]` by the rasterizer with number type `T`.
    fn raster<T: Int>(tri: &Triangle, s: i64, lo: [i64; 3], hi: [i64; 3]) -> Vec<[i64; 3]> {
        let mut out = Vec::new();
        let mut lo_c = lo;
        let mut hi_c = hi;
        let mut base = [0i64; 3];
        for a in 0..3 {
            let mn = tri.iter().map(|p| p[a]).min().unwrap();
            let mx = tri.iter().map(|p| p[a]).max().unwrap();
            lo_c[a] = lo_c[a].max(mn.div_euclid(s) + i64::from(mn.rem_euclid(s) != 0) - 1);
            hi_c[a] = hi_c[a].min(mx.div_euclid(s));
            if lo_c[a] > hi_c[a] {
                return out;
            }
            base[a] = mn.div_euclid(s) - 1;
        }
        rasterize_local::<T>(tri, s, lo_c, hi_c, base, &mut |c: [i64; 3]| out.push(c));
        out.sort();
        out
    }

    /// The same by testing every voxel of the window with the plain 13-axis test.
    fn brute(tri: &Triangle, s: i64, lo: [i64; 3], hi: [i64; 3]) -> Vec<[i64; 3]> {
        let mut out = Vec::new();
        for x in lo[0]..=hi[0] {
            for y in lo[1]..=hi[1] {
                for z in lo[2]..=hi[2] {
                    if triangle_overlaps_box(tri, [x * s, y * s, z * s], s) {
                        out.push([x, y, z]);
                    }
                }
            }
        }
        out
    }

    fn point() -> impl Strategy<Value = [i64; 3]> {
        // Mostly voxel-aligned coordinates (multiples of s/4) to hit exact
        // boundaries, sometimes arbitrary ones.
        prop_oneof![
            prop::array::uniform3(0i64..40).prop_map(|p| p.map(|c| c * SUBVOXEL / 4)),
            prop::array::uniform3(0i64..10 * SUBVOXEL),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]
        #[test]
        fn rasterizer_equals_plain_test(a in point(), b in point(), c in point(), degenerate in 0u8..4) {
            let mut tri = [a, b, c];
            match degenerate {
                1 => tri[2] = tri[1],
                2 => tri[2] = [0, 1, 2].map(|k| 2 * tri[1][k] - tri[0][k]).map(|v| v.max(0)),
                _ => {}
            }
            let lo = [0; 3];
            let hi = [11; 3];
            let expected = brute(&tri, SUBVOXEL, lo, hi);
            prop_assert_eq!(&raster::<i64>(&tri, SUBVOXEL, lo, hi), &expected);
            prop_assert_eq!(&raster::<i128>(&tri, SUBVOXEL, lo, hi), &expected);
        }
    }

    #[test]
    fn large_triangles_use_exact_wide_arithmetic() {
        // Triangles spanning up to 2^20 voxels at depth 21 (lattice coordinates
        // near 2^37): the i128 path, checked in windows along the triangle.
        let big = 1i64 << 37;
        let tris: [Triangle; 3] = [
            [
                [3, 5, 7],
                [big - 11, 1 << 20, 12345],
                [1 << 30, big - 3, big / 3],
            ],
            [
                [big / 2, big / 2, 0],
                [big / 2 + 1, big / 2, big - 1],
                [big / 2, big / 2 + 7 * SUBVOXEL, big - 1],
            ],
            [
                [0, 0, big / 5],
                [big - 1, 0, big / 5],
                [0, big - 1, big / 5 + 1],
            ],
        ];
        for tri in &tris {
            for step in 0..6 {
                // A window around a point of the triangle.
                let t = step as i64;
                let p = [0, 1, 2].map(|k| {
                    tri[0][k] + (tri[1][k] - tri[0][k]) / 6 * t + (tri[2][k] - tri[0][k]) / 7
                });
                let lo = p.map(|c| c / SUBVOXEL - 3);
                let hi = lo.map(|c| c + 6);
                let got = raster::<i128>(tri, SUBVOXEL, lo, hi);
                assert_eq!(got, brute(tri, SUBVOXEL, lo, hi), "window at {lo:?}");
            }
        }
    }

    #[test]
    fn chunk_buffer_drains_in_morton_order() {
        let mut buf = ChunkBuffer::new(4, true);
        let place = ChunkPlace {
            depth: 6,
            bits: 4,
            origin: [16, 0, 32],
        };
        let s = SUBVOXEL;
        let tri = [
            [17 * s, s, 33 * s],
            [30 * s, 2 * s, 40 * s],
            [20 * s, 15 * s, 47 * s],
        ];
        buf.add_triangle(&place, &tri, 5);
        let mut last = None;
        let mut n = 0;
        buf.drain(|brick, mask, tags| {
            assert!(last.is_none_or(|l| brick > l));
            last = Some(brick);
            assert_ne!(mask, 0);
            let tags = tags.unwrap();
            for (b, &tag) in tags.iter().enumerate() {
                assert_eq!(tag == 5, mask >> b & 1 == 1);
            }
            n += mask.count_ones();
        });
        assert!(n > 0);
        assert!(buf.is_empty());
    }
}
