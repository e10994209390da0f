//! The batch path's usual-ray set-up four rays at a time, in AVX2 `f64`
//! vectors ([`setup4`]).
//!
//! The very operations of [`prepare::setup_usual`](super::prepare::setup_usual)
//! (and `usual`), in the same order, on four lanes: IEEE `f64` addition,
//! multiplication and division are correctly rounded whether scalar or
//! vector, `f32` to `f64` is exact, `f64` to `f32` rounds to nearest as
//! `as f32` does (the default MXCSR, which Rust never changes), and `max`
//! and `min` agree with `f64::max` and `clamp` for the operands they get
//! here (no NaN: such lanes are not usual; no negative zero among the
//! absolute values). So each record is `setup_usual`'s to the bit; a test
//! checks it on hostile rays (NaN, infinities, signed zeros, subnormals,
//! tiny components, far origins, extreme scales, every level).
//!
//! The rays are read eight `f32`s at a time (origin, direction, bounds:
//! the first 32 bytes of a [`Ray`], which is `#[repr(C)]`) and turned
//! into structure-of-arrays form by shuffles; the records are written
//! from registers, three 16-byte stores each, in [`GpuRay`]'s layout
//! (`layout.rs`, checked below at compile time). Lanes that are not usual
//! are left to the caller, which sets them up one by one with
//! [`prepare::setup`](super::prepare::setup).

use std::arch::x86_64::*;
use std::mem::offset_of;

use dagfmt::batch::Ray;

use super::layout::{
    GpuRay, MAX_SHADER_SCALE_EXPONENT, PARAMETER_BOUND, RAY_MOVING_SHIFT, TINY_DIRECTION_INVERSE,
};
use super::prepare::{Frame, TINY_DIRECTION};

// The loads read a ray's first eight `f32`s in this order, and the stores
// write the record's three 16-byte rows in this order.
const _: () = {
    assert!(offset_of!(Ray, origin) == 0);
    assert!(offset_of!(Ray, dir) == 12);
    assert!(offset_of!(Ray, tmin) == 24);
    assert!(offset_of!(Ray, tmax) == 28);
    assert!(size_of::<Ray>() >= 32);
    assert!(offset_of!(GpuRay, origin) == 0);
    assert!(offset_of!(GpuRay, inv_dir) == 16);
    assert!(offset_of!(GpuRay, octant) == 32);
    assert!(offset_of!(GpuRay, level) == 36);
    assert!(offset_of!(GpuRay, flags) == 40);
    assert!(offset_of!(GpuRay, scale_exponent) == 44);
    assert!(size_of::<GpuRay>() == 48);
};

/// Whether [`setup4`] can run on this processor (AVX2, checked at run time).
pub(crate) fn available() -> bool {
    is_x86_feature_detected!("avx2")
}

/// The 4×4 transpose of four rows of four 32-bit values.
#[inline]
#[target_feature(enable = "avx2")]
fn transpose(rows: [__m128; 4]) -> [__m128; 4] {
    let a = _mm_unpacklo_ps(rows[0], rows[1]);
    let b = _mm_unpackhi_ps(rows[0], rows[1]);
    let c = _mm_unpacklo_ps(rows[2], rows[3]);
    let d = _mm_unpackhi_ps(rows[2], rows[3]);
    [
        _mm_movelh_ps(a, c),
        _mm_movehl_ps(c, a),
        _mm_movelh_ps(b, d),
        _mm_movehl_ps(d, b),
    ]
}

/// The low 32 bits of each 64-bit lane.
#[inline]
#[target_feature(enable = "avx2")]
fn narrow(v: __m256i) -> __m128i {
    let low = _mm256_permutevar8x32_epi32(v, _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6));
    _mm256_castsi256_si128(low)
}

/// Sets the four `rays` up as [`prepare::setup_usual`](super::prepare::setup_usual)
/// does, writing the record of each usual one to `out[k]`; returns the
/// mask of the usual lanes (bit `k` for `rays[k]`). The records of the
/// other lanes are left unwritten or written with meaningless values: the
/// caller must write them.
///
/// # Safety
///
/// The processor must have AVX2 ([`available`]), and `out` must be valid
/// for writes of four consecutive [`GpuRay`] records (192 bytes, no
/// alignment needed) that nothing else accesses during the call.
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn setup4(frame: &Frame, rays: &[Ray; 4], out: *mut GpuRay) -> u32 {
    let mut levels = [0i32; 4];
    let mut level_ok = 0u32;
    for (k, ray) in rays.iter().enumerate() {
        let level = ray.level.unwrap_or(frame.depth);
        levels[k] = i32::from(level);
        level_ok |= u32::from(level >= 1 && level <= frame.depth) << k;
    }
    if frame.empty || level_ok == 0 {
        return 0;
    }
    let base = rays.as_ptr().cast::<u8>();
    // SAFETY: each load reads the first 32 bytes of one of the four rays,
    // its origin, direction, `tmin` and `tmax` (eight initialised `f32`s,
    // laid out as the assertions above check), within the array.
    let r: [__m256; 4] = std::array::from_fn(|k| unsafe {
        _mm256_loadu_ps(base.add(k * size_of::<Ray>()).cast::<f32>())
    });
    // Rows of (ox oy oz dx | dy dz tmin tmax) to columns of four rays.
    let t0 = _mm256_unpacklo_ps(r[0], r[1]);
    let t1 = _mm256_unpackhi_ps(r[0], r[1]);
    let t2 = _mm256_unpacklo_ps(r[2], r[3]);
    let t3 = _mm256_unpackhi_ps(r[2], r[3]);
    let u0 = _mm256_shuffle_ps::<0x44>(t0, t2); // ox | dy
    let u1 = _mm256_shuffle_ps::<0xee>(t0, t2); // oy | dz
    let u2 = _mm256_shuffle_ps::<0x44>(t1, t3); // oz | tmin
    let u3 = _mm256_shuffle_ps::<0xee>(t1, t3); // dx | tmax
    let low = |v: __m256| _mm256_cvtps_pd(_mm256_castps256_ps128(v));
    let high = |v: __m256| _mm256_cvtps_pd(_mm256_extractf128_ps::<1>(v));
    let o = [low(u0), low(u1), low(u2)];
    let d = [low(u3), high(u0), high(u1)];
    let (tmin, tmax) = (high(u2), high(u3));

    let grid_scale = _mm256_set1_pd(frame.grid_scale);
    let origin: [__m256d; 3] = std::array::from_fn(|a| {
        _mm256_mul_pd(
            _mm256_sub_pd(o[a], _mm256_set1_pd(frame.root_min[a])),
            grid_scale,
        )
    });
    let dir = d.map(|d| _mm256_mul_pd(d, grid_scale));
    let sign = _mm256_set1_pd(-0.0);
    let abs = |v: __m256d| _mm256_andnot_pd(sign, v);
    let resolution = (1u64 << frame.depth) as f64;
    let largest = _mm256_max_pd(_mm256_max_pd(abs(dir[0]), abs(dir[1])), abs(dir[2]));
    let max_origin = _mm256_max_pd(
        _mm256_max_pd(abs(origin[0]), abs(origin[1])),
        abs(origin[2]),
    );
    // The test of `setup_usual`: every comparison is false for NaN.
    let mut usual = _mm256_cmp_pd::<_CMP_LE_OQ>(tmin, tmax);
    for v in origin.iter().chain(&dir) {
        usual = _mm256_and_pd(usual, _mm256_cmp_pd::<_CMP_ORD_Q>(*v, *v));
    }
    usual = _mm256_and_pd(
        usual,
        _mm256_cmp_pd::<_CMP_LE_OQ>(max_origin, _mm256_set1_pd(resolution * 16.0)),
    );
    usual = _mm256_and_pd(
        usual,
        _mm256_cmp_pd::<_CMP_GE_OQ>(largest, _mm256_set1_pd(f64::MIN_POSITIVE)),
    );
    // |exponent| <= MAX_SHADER_SCALE_EXPONENT: 2^-M <= largest < 2^(M+1)
    // (exact powers of two).
    usual = _mm256_and_pd(
        usual,
        _mm256_cmp_pd::<_CMP_GE_OQ>(
            largest,
            _mm256_set1_pd(2f64.powi(-MAX_SHADER_SCALE_EXPONENT)),
        ),
    );
    usual = _mm256_and_pd(
        usual,
        _mm256_cmp_pd::<_CMP_LT_OQ>(
            largest,
            _mm256_set1_pd(2f64.powi(MAX_SHADER_SCALE_EXPONENT + 1)),
        ),
    );
    let usual = _mm256_movemask_pd(usual) as u32 & level_ok;
    if usual == 0 {
        return 0;
    }

    // Components below largest * 2^-60 become (positive) zero.
    let tiny_limit = _mm256_mul_pd(largest, _mm256_set1_pd(TINY_DIRECTION));
    let tiny = dir.map(|d| _mm256_cmp_pd::<_CMP_LT_OQ>(abs(d), tiny_limit));
    let dir: [__m256d; 3] = std::array::from_fn(|a| _mm256_andnot_pd(tiny[a], dir[a]));

    // `usual`.
    let scale_bits = _mm256_and_si256(
        _mm256_castpd_si256(largest),
        _mm256_set1_epi64x(0x7ff0_0000_0000_0000),
    );
    let scale = _mm256_castsi256_pd(scale_bits);
    let inv_scale =
        _mm256_castsi256_pd(_mm256_sub_epi64(_mm256_set1_epi64x(2046 << 52), scale_bits));
    let one = _mm256_set1_pd(1.0);
    let scaled: [__m256d; 3] = std::array::from_fn(|a| {
        _mm256_blendv_pd(_mm256_mul_pd(abs(dir[a]), inv_scale), one, tiny[a])
    });
    let reciprocal = _mm256_div_pd(
        one,
        _mm256_mul_pd(_mm256_mul_pd(scaled[0], scaled[1]), scaled[2]),
    );
    let inverse = [
        _mm256_mul_pd(_mm256_mul_pd(reciprocal, scaled[1]), scaled[2]),
        _mm256_mul_pd(_mm256_mul_pd(reciprocal, scaled[0]), scaled[2]),
        _mm256_mul_pd(_mm256_mul_pd(reciprocal, scaled[0]), scaled[1]),
    ];
    let tiny_inverse = _mm256_set1_pd(f64::from(TINY_DIRECTION_INVERSE));
    let resolution = _mm256_set1_pd(resolution);
    let mut octant = _mm_setzero_si128();
    let mut flags = _mm_setzero_si128();
    let mut o32 = [_mm_setzero_ps(); 3];
    let mut inv32 = [_mm_setzero_ps(); 3];
    for a in 0..3 {
        let negative = _mm256_cmp_pd::<_CMP_LT_OQ>(dir[a], _mm256_setzero_pd());
        let o = _mm256_blendv_pd(origin[a], _mm256_sub_pd(resolution, origin[a]), negative);
        o32[a] = _mm256_cvtpd_ps(o);
        inv32[a] = _mm256_cvtpd_ps(_mm256_blendv_pd(inverse[a], tiny_inverse, tiny[a]));
        let negative = narrow(_mm256_castpd_si256(negative));
        octant = _mm_or_si128(octant, _mm_and_si128(negative, _mm_set1_epi32(1 << a)));
        let still = narrow(_mm256_castpd_si256(tiny[a]));
        flags = _mm_or_si128(
            flags,
            _mm_andnot_si128(still, _mm_set1_epi32(1 << (RAY_MOVING_SHIFT + a as u32))),
        );
    }
    let limit = f64::from(PARAMETER_BOUND);
    let bound = |t: __m256d| {
        let t = _mm256_mul_pd(t, scale);
        let t = _mm256_min_pd(
            _mm256_max_pd(t, _mm256_set1_pd(-limit)),
            _mm256_set1_pd(limit),
        );
        _mm256_cvtpd_ps(t)
    };
    let (t_start, t_end) = (bound(tmin), bound(tmax));
    let exponent = narrow(_mm256_sub_epi64(
        _mm256_srli_epi64::<52>(scale_bits),
        _mm256_set1_epi64x(1023),
    ));
    let level = _mm_setr_epi32(levels[0], levels[1], levels[2], levels[3]);

    let rows = [
        transpose([o32[0], o32[1], o32[2], t_start]),
        transpose([inv32[0], inv32[1], inv32[2], t_end]),
        transpose([
            _mm_castsi128_ps(octant),
            _mm_castsi128_ps(level),
            _mm_castsi128_ps(flags),
            _mm_castsi128_ps(exponent),
        ]),
    ];
    let out = out.cast::<f32>();
    for k in 0..4 {
        for (row, values) in rows.iter().enumerate() {
            // SAFETY: record `k`'s row `row` (16 bytes at 48 k + 16 row),
            // within the four records the caller lets us write.
            unsafe { _mm_storeu_ps(out.add(12 * k + 4 * row), values[k]) };
        }
    }
    usual
}

#[cfg(test)]
mod tests {
    use super::super::prepare::setup_usual;
    use super::super::prepare::tests::{frames, random_ray};
    use super::*;

    /// Every lane [`setup4`] takes is one `setup_usual` takes, with the same
    /// record to the bit, and every lane it declines is one `setup_usual`
    /// declines, on hostile rays.
    #[test]
    fn four_lanes_are_setup_usual_to_the_bit() {
        if !available() {
            eprintln!("no AVX2 here: the four-lane set-up is not used, nothing to check");
            return;
        }
        let mut state = 11u64;
        let mut taken = 0;
        for frame in frames() {
            for _ in 0..50_000 {
                let rays: [Ray; 4] = std::array::from_fn(|_| random_ray(&mut state, &frame));
                let mut out = [GpuRay::zeroed(); 4];
                // SAFETY: AVX2 is available; `out` holds four records.
                let usual = unsafe { setup4(&frame, &rays, out.as_mut_ptr()) };
                for (k, ray) in rays.iter().enumerate() {
                    match (usual & (1 << k) != 0, setup_usual(&frame, ray)) {
                        (true, Some(one)) => {
                            taken += 1;
                            assert_eq!(
                                bytemuck::bytes_of(&out[k]),
                                bytemuck::bytes_of(&one),
                                "{ray:?} in {frame:?}"
                            );
                        }
                        (false, None) => {}
                        (lanes, one) => {
                            panic!("{ray:?} in {frame:?}: four lanes {lanes}, one by one {one:?}")
                        }
                    }
                }
            }
        }
        assert!(taken > 250_000, "{taken}");
    }

    use bytemuck::Zeroable as _;
}
