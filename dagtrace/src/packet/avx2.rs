//! The packets' vector kernels (AVX2): the scan that decides which rays
//! join a packet, the beam's tests of a node's children, and the chain tests
//! of a packet's rays, each computing what its scalar form in `packet`
//! computes, with the same `f32` operations.

use std::arch::x86_64::*;

use dagfmt::batch::Ray;
use glam::Vec3A;

use crate::simd::segment;

use super::{Beam, ChainTests, GroupBeams, PacketLanes, ScannedRays};

/// `packet::scan_ray` of eight rays at once: how many of `rays`, from the
/// first, may join the packet that `first` starts, with the ranges of their
/// `|d_a|`, computed with the same `f32` operations (so the same packets).
///
/// # Safety
///
/// The processor must have AVX2.
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn scan_for_packet(rays: &[Ray; 8], first: &Ray) -> ScannedRays {
    // SAFETY: the caller's.
    let eight = unsafe { scan_eight(rays, first) };
    eight.fold(eight.joins.trailing_ones() as usize)
}

/// [`scan_for_packet`] of sixteen rays (a group of a packet), in two
/// vectors of eight folded once.
///
/// # Safety
///
/// The processor must have AVX2.
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn scan_group(rays: &[Ray; 16], first: &Ray) -> ScannedRays {
    // SAFETY: the caller's.
    if let Some(all) = unsafe { scan_whole_group(rays, first) } {
        return all;
    }
    let (a, b) = rays.split_at(8);
    // SAFETY: the caller's.
    let (a, b) = unsafe {
        (
            scan_eight(a.try_into().expect("eight"), first),
            scan_eight(b.try_into().expect("eight"), first),
        )
    };
    let len = (a.joins | b.joins << 8).trailing_ones() as usize;
    if len <= 8 {
        return a.fold(len);
    }
    // The first eight all join: the rays of both that join, as one vector.
    let keep = lanes_below(len - 8);
    let or_else = |v: __m256, other: f32| _mm256_blendv_ps(_mm256_set1_ps(other), v, keep);
    let lo: [__m256; 3] =
        std::array::from_fn(|i| _mm256_min_ps(a.m[i], or_else(b.m[i], f32::INFINITY)));
    let hi: [__m256; 3] = std::array::from_fn(|i| _mm256_max_ps(a.m[i], or_else(b.m[i], 0.0)));
    ScannedRays {
        len,
        lo: Vec3A::new(fold_min(lo[0]), fold_min(lo[1]), fold_min(lo[2])),
        hi: Vec3A::new(fold_max(hi[0]), fold_max(hi[1]), fold_max(hi[2])),
    }
}

/// [`scan_group`] where all sixteen rays may join, the usual case, or `None`
/// (then the ray-by-ray scan decides). Sufficient tests on the sixteen rays
/// at once, each ray's first 32 bytes one vector, with no transpose:
/// - their starts and direction signs equal `first`'s (the OR of the rays'
///   XORs with it);
/// - their `|d_a|` ranges, as the integer minimum and maximum of the bits
///   (the order of non-negative floats), with all components finite, none
///   above 2^60 (so every `|d|²` is finite), and the smallest component of
///   all above 10^-6 times the largest of all (so each ray's is above 10^-6
///   times its own largest: `packet::scan_ray`'s test, rounding being
///   monotonic);
/// - the same level.
///
/// When they hold, every ray passes `scan_ray`, and the ranges are the
/// same numbers.
///
/// # Safety
///
/// The processor must have AVX2.
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn scan_whole_group(rays: &[Ray; 16], first: &Ray) -> Option<ScannedRays> {
    // SAFETY: the first 32 bytes of each ray lie inside it (the assertion on
    // `Ray`'s layout below).
    let words = |r: &Ray| unsafe { _mm256_loadu_si256(std::ptr::from_ref(r).cast::<__m256i>()) };
    let f = words(first);
    let magnitude = _mm256_set1_epi32(0x7fff_ffff);
    let mut differ = _mm256_setzero_si256();
    let mut lo = magnitude;
    let mut hi = _mm256_setzero_si256();
    for r in rays {
        let v = words(r);
        differ = _mm256_or_si256(differ, _mm256_xor_si256(v, f));
        let m = _mm256_and_si256(v, magnitude);
        lo = _mm256_min_epi32(lo, m);
        hi = _mm256_max_epi32(hi, m);
    }
    // Lanes: origin x, y, z, direction x, y, z, tmin, tmax. The start must
    // be equal, the direction's sign bits too.
    let sign = i32::MIN;
    let must_match = _mm256_setr_epi32(-1, -1, -1, sign, sign, sign, -1, -1);
    let mut level = true;
    for r in rays {
        level &= r.level == first.level;
    }
    if _mm256_testz_si256(differ, must_match) == 0 || !level {
        return None;
    }
    // SAFETY: 32 bytes either way, and any bits are a `u32`.
    let lanes = |v: __m256i| -> [u32; 8] { unsafe { std::mem::transmute(v) } };
    let (lo, hi) = (lanes(lo), lanes(hi));
    let (lo, hi) = ([lo[3], lo[4], lo[5]], [hi[3], hi[4], hi[5]]);
    // 2^60: squares and their sum stay far below f32::MAX (2^128).
    let bound = (2f32.powi(60)).to_bits();
    if hi.iter().any(|&h| h > bound) {
        return None;
    }
    let lo = Vec3A::from_array(lo.map(f32::from_bits));
    let hi = Vec3A::from_array(hi.map(f32::from_bits));
    (lo.min_element() > hi.max_element() * 1e-6).then_some(ScannedRays { len: 16, lo, hi })
}

/// All ones in the lanes below `len` (at most 8).
#[inline]
#[target_feature(enable = "avx2")]
fn lanes_below(len: usize) -> __m256 {
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_set1_epi32(len as i32), lane))
}

/// Eight rays scanned for a packet ([`scan_eight`]), not yet folded.
#[derive(Clone, Copy)]
struct ScannedEight {
    /// Bit `k`: ray `k` may join.
    joins: u32,
    /// `|d_a|` per axis, per lane.
    m: [__m256; 3],
}

impl ScannedEight {
    /// The scan of the first `len` rays (all of which join).
    #[inline]
    #[target_feature(enable = "avx2")]
    fn fold(&self, len: usize) -> ScannedRays {
        if len == 0 {
            return ScannedRays::NONE;
        }
        // Over the rays that join: the ranges, the others replaced by the
        // neutral values.
        let keep = lanes_below(len);
        let or_else = |v: __m256, other: f32| _mm256_blendv_ps(_mm256_set1_ps(other), v, keep);
        let m = self.m;
        ScannedRays {
            len,
            lo: Vec3A::new(
                fold_min(or_else(m[0], f32::INFINITY)),
                fold_min(or_else(m[1], f32::INFINITY)),
                fold_min(or_else(m[2], f32::INFINITY)),
            ),
            hi: Vec3A::new(
                fold_max(or_else(m[0], 0.0)),
                fold_max(or_else(m[1], 0.0)),
                fold_max(or_else(m[2], 0.0)),
            ),
        }
    }
}

/// The per-ray tests of `packet::scan_ray` for eight rays, in vectors.
///
/// # Safety
///
/// The processor must have AVX2.
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn scan_eight(rays: &[Ray; 8], first: &Ray) -> ScannedEight {
    // SAFETY: the caller's.
    let [o0, o1, o2, d0, d1, d2, t0, t1] = unsafe { ray_words(rays) };
    let start_bits = [o0, o1, o2, t0, t1];
    let first_start = [
        first.origin[0],
        first.origin[1],
        first.origin[2],
        first.tmin,
        first.tmax,
    ];
    let d_bits = [d0, d1, d2];
    let splat = |v: f32| _mm256_set1_epi32(v.to_bits() as i32);
    // The same origin and bounds bit for bit, and the same signs of the
    // direction.
    let mut differ = _mm256_setzero_si256();
    for (b, f) in start_bits.iter().zip(first_start) {
        differ = _mm256_or_si256(differ, _mm256_xor_si256(*b, splat(f)));
    }
    let mut signs = _mm256_setzero_si256();
    for (b, f) in d_bits.iter().zip(first.dir) {
        signs = _mm256_or_si256(signs, _mm256_xor_si256(*b, splat(f)));
    }
    differ = _mm256_or_si256(differ, _mm256_srli_epi32::<31>(signs));
    let same = _mm256_castsi256_ps(_mm256_cmpeq_epi32(differ, _mm256_setzero_si256()));
    let d = d_bits.map(|b| _mm256_castsi256_ps(b));
    let m = d.map(|d| _mm256_andnot_ps(_mm256_set1_ps(-0.0), d));
    // `length_squared`: (x² + y²) + z².
    let d2 = _mm256_add_ps(
        _mm256_add_ps(_mm256_mul_ps(d[0], d[0]), _mm256_mul_ps(d[1], d[1])),
        _mm256_mul_ps(d[2], d[2]),
    );
    // With finite components (an infinite or NaN one fails the `d2` test),
    // the smallest and largest component in any order.
    let smallest = _mm256_min_ps(m[0], _mm256_min_ps(m[1], m[2]));
    let largest = _mm256_max_ps(m[0], _mm256_max_ps(m[1], m[2]));
    let regular = _mm256_and_ps(
        _mm256_cmp_ps::<_CMP_GT_OQ>(smallest, _mm256_mul_ps(largest, _mm256_set1_ps(1e-6))),
        _mm256_cmp_ps::<_CMP_LT_OQ>(d2, _mm256_set1_ps(f32::INFINITY)),
    );
    // The same level: for full-depth rays (the usual case) only `None`s.
    let mut level = 0u32;
    match first.level {
        None => {
            for (k, r) in rays.iter().enumerate() {
                level |= u32::from(r.level.is_none()) << k;
            }
        }
        Some(l) => {
            for (k, r) in rays.iter().enumerate() {
                level |= u32::from(r.level == Some(l)) << k;
            }
        }
    }
    ScannedEight {
        joins: _mm256_movemask_ps(_mm256_and_ps(same, regular)) as u32 & level,
        m,
    }
}

// A `Ray` (`#[repr(C)]`) starts with its origin, direction, `tmin` and
// `tmax`, eight 4-byte words: the layout `ray_words` reads.
const _: () = assert!(
    std::mem::offset_of!(Ray, origin) == 0
        && std::mem::offset_of!(Ray, dir) == 12
        && std::mem::offset_of!(Ray, tmin) == 24
        && std::mem::offset_of!(Ray, tmax) == 28
        && std::mem::size_of::<Ray>() >= 32
);

/// The origin (3), direction (3), `tmin` and `tmax` words of eight rays,
/// one vector per field, lane `k` from `rays[k]`. Eight loads of a ray's
/// first 32 bytes and a transpose: with a gather per field, the scan took
/// 12 % of the time of a d12 tiled frame on Zen 4 (whose gathers are slow),
/// without them 6 %.
///
/// # Safety
///
/// The processor must have AVX2.
#[inline]
#[target_feature(enable = "avx2")]
unsafe fn ray_words(rays: &[Ray; 8]) -> [__m256i; 8] {
    // SAFETY: the first 32 bytes of each ray lie inside it (the assertion
    // on `Ray`'s layout above).
    let row = |k: usize| unsafe {
        _mm256_castsi256_ps(_mm256_loadu_si256(
            std::ptr::from_ref(&rays[k]).cast::<__m256i>(),
        ))
    };
    let r: [__m256; 8] = std::array::from_fn(row);
    let t = [
        _mm256_unpacklo_ps(r[0], r[1]),
        _mm256_unpackhi_ps(r[0], r[1]),
        _mm256_unpacklo_ps(r[2], r[3]),
        _mm256_unpackhi_ps(r[2], r[3]),
        _mm256_unpacklo_ps(r[4], r[5]),
        _mm256_unpackhi_ps(r[4], r[5]),
        _mm256_unpacklo_ps(r[6], r[7]),
        _mm256_unpackhi_ps(r[6], r[7]),
    ];
    let u = [
        _mm256_shuffle_ps::<0x44>(t[0], t[2]),
        _mm256_shuffle_ps::<0xee>(t[0], t[2]),
        _mm256_shuffle_ps::<0x44>(t[1], t[3]),
        _mm256_shuffle_ps::<0xee>(t[1], t[3]),
        _mm256_shuffle_ps::<0x44>(t[4], t[6]),
        _mm256_shuffle_ps::<0xee>(t[4], t[6]),
        _mm256_shuffle_ps::<0x44>(t[5], t[7]),
        _mm256_shuffle_ps::<0xee>(t[5], t[7]),
    ];
    [
        _mm256_permute2f128_ps::<0x20>(u[0], u[4]),
        _mm256_permute2f128_ps::<0x20>(u[1], u[5]),
        _mm256_permute2f128_ps::<0x20>(u[2], u[6]),
        _mm256_permute2f128_ps::<0x20>(u[3], u[7]),
        _mm256_permute2f128_ps::<0x31>(u[0], u[4]),
        _mm256_permute2f128_ps::<0x31>(u[1], u[5]),
        _mm256_permute2f128_ps::<0x31>(u[2], u[6]),
        _mm256_permute2f128_ps::<0x31>(u[3], u[7]),
    ]
    .map(|v| _mm256_castps_si256(v))
}

/// The smallest of the eight lanes (none NaN).
#[inline]
#[target_feature(enable = "avx2")]
fn fold_min(v: __m256) -> f32 {
    let v = _mm_min_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
    let v = _mm_min_ps(v, _mm_movehl_ps(v, v));
    _mm_cvtss_f32(_mm_min_ps(v, _mm_shuffle_ps::<0b01>(v, v)))
}

/// The largest of the eight lanes (none NaN).
#[inline]
#[target_feature(enable = "avx2")]
fn fold_max(v: __m256) -> f32 {
    let v = _mm_max_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
    let v = _mm_max_ps(v, _mm_movehl_ps(v, v));
    _mm_cvtss_f32(_mm_max_ps(v, _mm_shuffle_ps::<0b01>(v, v)))
}

/// `packet::Beam::children_met` before its mirroring: bit `m` set when some
/// line of `beam` may meet the mirrored child `m` of the node of edge
/// `2 * half` at `pos`. The same `f64` operations as the scalar form, four
/// children to a vector (so the same answers).
///
/// # Safety
///
/// The processor must have AVX2.
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn beam_children_met(beam: &Beam, pos: [f64; 3], half: f64) -> u32 {
    let (origin, inv_lo, inv_hi) = (beam.origin, beam.inv_lo, beam.inv_hi);
    let (tmin, tmax, margin) = (beam.tmin, beam.tmax, beam.margin);
    let v = |a: [f64; 3]| _mm256_setr_pd(a[0], a[1], a[2], 0.0);
    let (origin, inv_lo, inv_hi, pos) = (v(origin), v(inv_lo), v(inv_hi), v(pos));
    let (margin, half) = (_mm256_set1_pd(margin), _mm256_set1_pd(half));
    let mid = _mm256_add_pd(pos, half);
    let lo0 = _mm256_sub_pd(_mm256_sub_pd(pos, margin), origin);
    let lo1 = _mm256_sub_pd(_mm256_sub_pd(mid, margin), origin);
    let hi0 = _mm256_sub_pd(_mm256_add_pd(mid, margin), origin);
    let hi1 = _mm256_sub_pd(_mm256_add_pd(_mm256_add_pd(mid, half), margin), origin);
    let zero = _mm256_setzero_pd();
    // `Beam::near` and `Beam::far`: the inverse direction by the plane's side.
    let near = |lo: __m256d| {
        let ahead = _mm256_cmp_pd::<_CMP_GE_OQ>(lo, zero);
        _mm256_mul_pd(lo, _mm256_blendv_pd(inv_hi, inv_lo, ahead))
    };
    let far = |hi: __m256d| {
        let ahead = _mm256_cmp_pd::<_CMP_GE_OQ>(hi, zero);
        _mm256_mul_pd(hi, _mm256_blendv_pd(inv_lo, inv_hi, ahead))
    };
    let (n0, n1, f0, f1) = (near(lo0), near(lo1), far(hi0), far(hi1));
    // Per row of four children (z fixed): lane k has x = k & 1, y = k >> 1.
    // `unpacklo` gives [a.x, b.x, a.z, b.z], `unpackhi` [a.y, b.y, .., ..].
    let (nxz, ny) = (_mm256_unpacklo_pd(n0, n1), _mm256_unpackhi_pd(n0, n1));
    let (fxz, fy) = (_mm256_unpacklo_pd(f0, f1), _mm256_unpackhi_pd(f0, f1));
    let nx = _mm256_permute4x64_pd::<0b01_00_01_00>(nxz);
    let fx = _mm256_permute4x64_pd::<0b01_00_01_00>(fxz);
    let ny = _mm256_permute4x64_pd::<0b01_01_00_00>(ny);
    let fy = _mm256_permute4x64_pd::<0b01_01_00_00>(fy);
    let (tmin, tmax) = (_mm256_set1_pd(tmin), _mm256_set1_pd(tmax));
    // `max(a, b)` is `a > b ? a : b` and `min(a, b)` is `a < b ? a : b`,
    // like the scalar closures (no NaN here).
    let enter_xy = _mm256_max_pd(tmin, nx);
    let exit_xy = _mm256_min_pd(tmax, fx);
    let row = |nz: __m256d, fz: __m256d| {
        let enter = _mm256_max_pd(enter_xy, _mm256_max_pd(ny, nz));
        let exit = _mm256_min_pd(exit_xy, _mm256_min_pd(fy, fz));
        _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LE_OQ>(enter, exit)) as u32
    };
    let low = row(
        _mm256_permute4x64_pd::<0b10_10_10_10>(nxz),
        _mm256_permute4x64_pd::<0b10_10_10_10>(fxz),
    );
    let high = row(
        _mm256_permute4x64_pd::<0b11_11_11_11>(nxz),
        _mm256_permute4x64_pd::<0b11_11_11_11>(fxz),
    );
    low | high << 4
}

/// `packet::Beam::meets` for a packet's four group beams at once, which
/// differ from the packet's `beam` only in their inverse directions
/// (`groups`), against the cube of edge `size` at `pos`: bit `g` set when
/// group `g`'s beam may meet it. The same `f64` operations, and like
/// `f64::max` and `f64::min` a NaN plane parameter is passed over.
///
/// # Safety
///
/// The processor must have AVX2.
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn groups_meet(
    beam: &Beam,
    groups: &GroupBeams,
    pos: [f64; 3],
    size: f64,
) -> u32 {
    let (origin, margin) = (beam.origin, beam.margin);
    let (inv_lo, inv_hi) = (&groups.inv_lo, &groups.inv_hi);
    let load = |v: &[f64; 4]| _mm256_setr_pd(v[0], v[1], v[2], v[3]);
    let mut enter = _mm256_set1_pd(beam.tmin);
    let mut exit = _mm256_set1_pd(beam.tmax);
    for a in 0..3 {
        let lo = pos[a] - margin - origin[a];
        let hi = pos[a] + size + margin - origin[a];
        let near = if lo >= 0.0 { &inv_lo[a] } else { &inv_hi[a] };
        let far = if hi >= 0.0 { &inv_hi[a] } else { &inv_lo[a] };
        let near = _mm256_mul_pd(_mm256_set1_pd(lo), load(near));
        let far = _mm256_mul_pd(_mm256_set1_pd(hi), load(far));
        // `maxpd(a, b)` is `a > b ? a : b`: the second operand when either
        // is NaN, so the running bound stays, as with `f64::max`.
        enter = _mm256_max_pd(near, enter);
        exit = _mm256_min_pd(far, exit);
    }
    _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LE_OQ>(enter, exit)) as u32
}

/// `packet::chain_tests` eight rays at a time, with the same `f32`
/// operations (so the same tests bit for bit).
///
/// # Safety
///
/// The processor must have AVX2.
#[inline]
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn chain_tests(
    planes: [[f32; 3]; 3],
    lanes: &PacketLanes,
    rays: u64,
) -> ChainTests {
    let splat = |p: [f32; 3]| {
        [
            _mm256_set1_ps(p[0]),
            _mm256_set1_ps(p[1]),
            _mm256_set1_ps(p[2]),
        ]
    };
    let [d_lo, d_mid, d_hi] = [splat(planes[0]), splat(planes[1]), splat(planes[2])];
    let mut tests = ChainTests::default();
    let mut groups = rays;
    while groups != 0 {
        let g = (groups.trailing_zeros() / 8) as usize & 7;
        groups &= !(0xff << (8 * g));
        // Rays 8g..8g + 8.
        macro_rules! load {
            ($v:expr) => {{
                let v: &[f32; 64] = &$v;
                // SAFETY: floats 8g..8g + 8 of the 64 in `v` (g < 8).
                unsafe { _mm256_loadu_ps(v.as_ptr().add(8 * g)) }
            }};
        }
        let inv = [
            load!(lanes.inv[0]),
            load!(lanes.inv[1]),
            load!(lanes.inv[2]),
        ];
        let t_lo: [__m256; 3] = std::array::from_fn(|a| _mm256_mul_ps(d_lo[a], inv[a]));
        let t_mid: [__m256; 3] = std::array::from_fn(|a| _mm256_mul_ps(d_mid[a], inv[a]));
        let t_hi: [__m256; 3] = std::array::from_fn(|a| _mm256_mul_ps(d_hi[a], inv[a]));
        let (enter, exit) = segment(t_lo, t_hi, load!(lanes.tmin), load!(lanes.tmax));
        let shift = 8 * g;
        macro_rules! bits {
            ($m:expr) => {
                u64::from(_mm256_movemask_ps($m) as u8) << shift
            };
        }
        tests.inside |= bits!(_mm256_cmp_ps::<_CMP_LE_OS>(enter, exit));
        for (a, &t) in t_mid.iter().enumerate() {
            tests.first[a] |= bits!(_mm256_cmp_ps::<_CMP_LE_OS>(t, enter));
            tests.before_exit[a] |= bits!(_mm256_cmp_ps::<_CMP_LE_OS>(t, exit));
        }
        tests.order[0] |= bits!(_mm256_cmp_ps::<_CMP_LT_OS>(t_mid[0], t_mid[1]));
        tests.order[1] |= bits!(_mm256_cmp_ps::<_CMP_LT_OS>(t_mid[0], t_mid[2]));
        tests.order[2] |= bits!(_mm256_cmp_ps::<_CMP_LT_OS>(t_mid[1], t_mid[2]));
    }
    tests.inside &= rays;
    tests
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cpu::available;
    use crate::simd::tests::special;
    use crate::testing::Rng;

    /// `scan_for_packet` against `packet::scan_ray` ray by ray, on runs of
    /// eight rays that mostly share their start, with the odd field changed.
    #[test]
    fn vector_packet_scan_is_the_scan_of_each_ray() {
        if !available() {
            eprintln!("skipped: this processor has no AVX2");
            return;
        }
        let mut rng = Rng(0x5ca7);
        let mut lengths = [0usize; 17];
        for case in 0..40_000 {
            let first = Ray {
                origin: [0, 1, 2].map(|_| rng.range(-3.0, 3.0)),
                dir: [0, 1, 2].map(|_| rng.range(-1.0, 1.0)),
                tmin: rng.range(0.0, 1.0),
                tmax: if rng.next().is_multiple_of(2) {
                    f32::INFINITY
                } else {
                    10.0
                },
                level: (case % 5 == 0).then_some(7),
            };
            let rare = 16 + rng.next() % 128;
            let rays: [Ray; 16] = std::array::from_fn(|_| {
                let mut r = first;
                r.dir = first.dir.map(|d| d + rng.range(-0.05, 0.05));
                match rng.next() % rare {
                    0 => r.origin[(rng.next() % 3) as usize] += 1e-6,
                    1 => r.tmin = special(&mut rng, r.tmin),
                    2 => r.tmax = special(&mut rng, r.tmax),
                    3 => r.level = Some((rng.next() % 4) as u8),
                    4 => r.level = None,
                    5 | 6 => {
                        let a = (rng.next() % 3) as usize;
                        r.dir[a] = special(&mut rng, r.dir[a]);
                    }
                    7 => {
                        let a = (rng.next() % 3) as usize;
                        r.dir[a] = -r.dir[a];
                    }
                    _ => {}
                }
                r
            });
            // The scan ray by ray, for the first `n` rays.
            let scalar = |n: usize| {
                let mut scalar = ScannedRays::NONE;
                for r in &rays[..n] {
                    let one = crate::packet::scan_ray(r, &rays[0]);
                    if one.len == 0 {
                        break;
                    }
                    scalar = ScannedRays {
                        len: scalar.len + 1,
                        lo: scalar.lo.min(one.lo),
                        hi: scalar.hi.max(one.hi),
                    };
                }
                scalar
            };
            let bits = |s: &ScannedRays| {
                (
                    s.len,
                    s.lo.to_array().map(f32::to_bits),
                    s.hi.to_array().map(f32::to_bits),
                )
            };
            let eight: &[Ray; 8] = rays[..8].try_into().unwrap();
            // SAFETY: AVX2 was found above.
            let (vector, group) = unsafe {
                (
                    scan_for_packet(eight, &rays[0]),
                    scan_group(&rays, &rays[0]),
                )
            };
            assert_eq!(bits(&vector), bits(&scalar(8)), "{rays:?}");
            assert_eq!(bits(&group), bits(&scalar(16)), "{rays:?}");
            lengths[group.len] += 1;
        }
        // Every length occurs, all sixteen joining most often.
        assert!(lengths.iter().all(|&n| n > 50), "{lengths:?}");
        assert!(lengths[16] == *lengths.iter().max().unwrap(), "{lengths:?}");
    }

    /// `chain_tests` against `packet::chain_tests` (four rays to a vector)
    /// on random packets, planes and ray sets, ties included.
    #[test]
    fn vector_chain_tests_are_the_chain_tests_of_four_ray_vectors() {
        if !available() {
            eprintln!("skipped: this processor has no AVX2");
            return;
        }
        let mut rng = Rng(0xc4a1);
        let mut inside = 0u32;
        for _ in 0..20_000 {
            let mut lanes = PacketLanes::default();
            for i in 0..64 {
                for a in 0..3 {
                    // Equal inverses now and then: ties between the axes.
                    lanes.inv[a][i] = if rng.next().is_multiple_of(8) {
                        1.0
                    } else {
                        rng.range(0.01, 4.0)
                    };
                }
                lanes.tmin[i] = rng.range(0.0, 2.0);
                lanes.tmax[i] = rng.range(1.0, 40.0);
            }
            let lo: [f32; 3] = std::array::from_fn(|_| rng.range(-4.0, 12.0).floor());
            let size = [1.0, 2.0, 4.0, 8.0][(rng.next() % 4) as usize];
            let planes = [lo, lo.map(|v| v + size * 0.5), lo.map(|v| v + size)];
            let rays = rng.next() & rng.next();
            // SAFETY: AVX2 was found above.
            let vector = unsafe { chain_tests(planes, &lanes, rays) };
            let scalar = crate::packet::chain_tests(planes, &lanes, rays);
            // Only the rays asked about count (the vectors cover more).
            let only = |t: ChainTests| ChainTests {
                inside: t.inside,
                first: t.first.map(|m| m & rays),
                before_exit: t.before_exit.map(|m| m & rays),
                order: t.order.map(|m| m & rays),
            };
            assert_eq!(only(vector), only(scalar), "{planes:?} {rays:x}");
            inside += vector.inside.count_ones();
        }
        assert!(inside > 10_000, "{inside} rays inside");
    }
}
