//! Host-side set-up of batch rays (f64), and the answers the host computes.
//!
//! The set-up is the CPU tracer's (`walk.rs`, `Tracer::setup` and
//! `Tracer::prepare`), with the very same f64 operations, so that the shader's
//! f32 traversal starts from the same numbers: world to grid space, rays that
//! cannot hit answered here (NaN, `tmin > tmax`, an empty volume), direction
//! components below 2^-60 of the largest treated as zero, the direction
//! scaled by a power of two (exact), and the frame mirrored so that every
//! direction component is non-negative; three reciprocals from one division.
//! The shader then reports the entry parameter and face as the CPU tracer
//! does (`batch.wgsl`), so for these rays the host does no more. The batch
//! path sets these usual rays up with [`setup_usual`]: the same operations
//! with the case analysis folded into one test, about a quarter less host
//! CPU time a ray than going through [`setup`] (BENCHMARKS.md); where the
//! processor has AVX2, four rays at a time with the same operations in
//! `f64` vectors (`setup4.rs`), declining the same rays.
//!
//! Rare rays keep the earlier f64 path, and their answers are computed here
//! from the cell the shader found ([`answer`]): rays with no direction (a
//! point query, sent as the centre of the cell that holds it, found here in
//! f64, so the shader's descent ends in the cell the CPU's f64 `floor`
//! picks), far origins (more than 16 cube sizes away: clipped to the cube and
//! re-based at the entry point), level 0 (answered here), scales beyond
//! [`MAX_SHADER_SCALE_EXPONENT`], and hits whose ray starts inside the cell.

use super::layout::{
    GpuRay, MAX_SHADER_SCALE_EXPONENT, PARAMETER_BOUND, RAY_HOST_ANSWER, RAY_MOVING_SHIFT,
    TINY_DIRECTION_INVERSE,
};
use dagfmt::batch::{Hit, Ray};

/// Direction components below this fraction of the largest count as zero.
pub(crate) const TINY_DIRECTION: f64 = 1.0 / (1u64 << 60) as f64;

/// What the shader needs to know about the DAG to set rays up.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Frame {
    pub depth: u8,
    pub root_min: [f64; 3],
    /// Grid units per world unit: 2^D / root_size.
    pub grid_scale: f64,
    pub empty: bool,
    /// Whether hits carry a dense index (attribute kind 1 and asked for).
    pub indexed: bool,
}

/// The ray in f64 grid space, kept for the final answer.
#[derive(Clone, Copy, Debug)]
pub(crate) struct GridRay {
    pub origin: [f64; 3],
    /// Direction with negligible components set to zero.
    pub dir: [f64; 3],
    pub tmin: f64,
    pub tmax: f64,
    /// Tolerance of the ray/hit semantics in grid units.
    pub eps: f64,
}

/// The outcome of setting a ray up.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Setup {
    /// Answered without the DAG.
    Done(Hit),
    /// To be traced by the shader; answered there too unless the ray is
    /// flagged [`RAY_HOST_ANSWER`] (then by [`host_answer`]).
    Trace(GpuRay),
}

/// A ray whose level of detail is deeper than the DAG.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct LevelTooDeep(pub u8);

/// Sets `ray` up for the shader (see the module documentation).
pub(crate) fn setup(frame: &Frame, ray: &Ray) -> Result<Setup, LevelTooDeep> {
    let depth = frame.depth;
    let level = match ray.level {
        None => depth,
        Some(l) if l <= depth => l,
        Some(l) => return Err(LevelTooDeep(l)),
    };
    let has_nan = ray
        .origin
        .iter()
        .chain(&ray.dir)
        .chain([&ray.tmin, &ray.tmax])
        .any(|v| v.is_nan());
    if has_nan || ray.tmin > ray.tmax || frame.empty {
        return Ok(Setup::Done(Hit::MISS));
    }
    let origin: [f64; 3] =
        std::array::from_fn(|i| (f64::from(ray.origin[i]) - frame.root_min[i]) * frame.grid_scale);
    let mut dir = ray.dir.map(|d| f64::from(d) * frame.grid_scale);
    if origin.iter().chain(&dir).any(|v| !v.is_finite()) {
        return Ok(Setup::Done(Hit::MISS));
    }
    let resolution = (1u64 << depth) as f64;
    let max_origin = origin.iter().fold(0f64, |m, v| m.max(v.abs()));
    let eps = tolerance(resolution, max_origin);
    let largest = dir.iter().fold(0f64, |m, v| m.max(v.abs()));
    let (tmin, tmax) = (f64::from(ray.tmin), f64::from(ray.tmax));
    if largest < f64::MIN_POSITIVE {
        // No direction: the ray is the point `origin`.
        let inside = origin.iter().all(|&o| (0.0..=resolution).contains(&o));
        let grid = GridRay {
            origin,
            dir: [0.0; 3],
            tmin,
            tmax,
            eps,
        };
        if !inside {
            return Ok(Setup::Done(Hit::MISS));
        }
        if level == 0 {
            return Ok(Setup::Done(root_hit(frame, &grid)));
        }
        let size = (1u64 << (depth - level)) as f64;
        let last = (1u64 << level) - 1;
        let centre = origin.map(|o| (((o / size).floor() as u64).min(last) as f64 + 0.5) * size);
        let gpu = GpuRay {
            origin: [centre[0] as f32, centre[1] as f32, centre[2] as f32, 0.0],
            inv_dir: [
                TINY_DIRECTION_INVERSE,
                TINY_DIRECTION_INVERSE,
                TINY_DIRECTION_INVERSE,
                0.0,
            ],
            octant: 0,
            level: u32::from(level),
            flags: RAY_HOST_ANSWER,
            scale_exponent: 0,
        };
        return Ok(Setup::Trace(gpu));
    }
    let mut moving = 0u32;
    for (i, d) in dir.iter_mut().enumerate() {
        if d.abs() < largest * TINY_DIRECTION {
            *d = 0.0;
        } else {
            moving |= 1 << i;
        }
    }
    // The power of two (exact scaling) that brings the largest component to
    // [1, 2), as `Tracer::prepare` takes it.
    let scale_bits = largest.to_bits() & 0x7ff0_0000_0000_0000;
    let exponent = (scale_bits >> 52) as i32 - 1023;
    if level > 0
        && max_origin <= resolution * 16.0
        && (1..=2045).contains(&(scale_bits >> 52))
        && exponent.abs() <= MAX_SHADER_SCALE_EXPONENT
    {
        return Ok(Setup::Trace(usual(
            origin,
            dir,
            [f64::from(ray.tmin), f64::from(ray.tmax)],
            scale_bits,
            resolution,
            moving,
            level,
        )));
    }
    let grid = GridRay {
        origin,
        dir,
        tmin,
        tmax,
        eps,
    };
    let Some((enter, exit)) = slab(&origin, &dir, [0.0; 3], [resolution; 3]) else {
        return Ok(Setup::Done(Hit::MISS));
    };
    let (start, end) = (tmin.max(enter), tmax.min(exit));
    // Also a miss when either bound is NaN.
    if start
        .partial_cmp(&end)
        .is_none_or(|o| o == std::cmp::Ordering::Greater)
    {
        return Ok(Setup::Done(Hit::MISS));
    }
    if level == 0 {
        return Ok(Setup::Done(root_hit(frame, &grid)));
    }
    let scale = f64::from_bits(scale_bits);
    let base = if max_origin > resolution * 16.0 {
        start
    } else {
        0.0
    };
    let mut octant = 0u32;
    let mut o32 = [0f32; 3];
    let mut inv32 = [0f32; 3];
    for i in 0..3 {
        let mut o = origin[i] + base * dir[i];
        let mut d = dir[i] / scale;
        if d < 0.0 {
            octant |= 1 << i;
            o = resolution - o;
            d = -d;
        }
        o32[i] = o as f32;
        inv32[i] = if d == 0.0 {
            TINY_DIRECTION_INVERSE
        } else {
            (1.0 / d) as f32
        };
    }
    let gpu = GpuRay {
        origin: [o32[0], o32[1], o32[2], ((start - base) * scale) as f32],
        inv_dir: [inv32[0], inv32[1], inv32[2], ((end - base) * scale) as f32],
        octant,
        level: u32::from(level),
        flags: RAY_HOST_ANSWER,
        scale_exponent: 0,
    };
    Ok(Setup::Trace(gpu))
}

/// [`setup`] for the usual ray, the one it hands to [`usual`] (a level of
/// detail from 1 to the depth, no NaN, `tmin <= tmax`, a non-empty volume,
/// a finite grid origin within 16 cube sizes and a direction whose largest
/// component in grid units is at least `f64::MIN_POSITIVE` and within
/// `2^±MAX_SHADER_SCALE_EXPONENT`); `None` for any other ray, which
/// [`setup`] then takes.
///
/// The same f64 operations in the same order as [`setup`] and [`usual`],
/// so the same [`GpuRay`] to the bit (a test checks it), with the tests
/// merged into one branch that is almost never taken: the batch path's
/// per-ray set-up is this function, and the cases [`setup`] tells apart
/// one after the other cost as much as the arithmetic.
#[inline(always)]
pub(crate) fn setup_usual(frame: &Frame, ray: &Ray) -> Option<GpuRay> {
    let level = match ray.level {
        None => frame.depth,
        Some(l) => l,
    };
    let origin: [f64; 3] =
        std::array::from_fn(|i| (f64::from(ray.origin[i]) - frame.root_min[i]) * frame.grid_scale);
    let dir = ray.dir.map(|d| f64::from(d) * frame.grid_scale);
    let resolution = (1u64 << frame.depth) as f64;
    let largest = dir[0].abs().max(dir[1].abs()).max(dir[2].abs());
    let max_origin = origin[0].abs().max(origin[1].abs()).max(origin[2].abs());
    let scale_bits = largest.to_bits() & 0x7ff0_0000_0000_0000;
    let exponent = (scale_bits >> 52) as i32 - 1023;
    // `max` ignores a NaN operand, so NaN components are tested on their own
    // (a NaN bound fails `tmin <= tmax`); an infinite component makes
    // `largest` or `max_origin` infinite, and a `largest` of at least
    // MIN_POSITIVE with |exponent| <= 64 has an exponent field within
    // 1..=2045, as `setup` asks.
    let nan = origin.iter().chain(&dir).any(|v| v.is_nan());
    let ordinary = !nan
        & (ray.tmin <= ray.tmax)
        & !frame.empty
        & (level >= 1)
        & (level <= frame.depth)
        & (max_origin <= resolution * 16.0)
        & (largest >= f64::MIN_POSITIVE)
        & (exponent.abs() <= MAX_SHADER_SCALE_EXPONENT);
    if !ordinary {
        return None;
    }
    let mut dir = dir;
    let mut moving = 0u32;
    for (i, d) in dir.iter_mut().enumerate() {
        if d.abs() < largest * TINY_DIRECTION {
            *d = 0.0;
        } else {
            moving |= 1 << i;
        }
    }
    Some(usual(
        origin,
        dir,
        [f64::from(ray.tmin), f64::from(ray.tmax)],
        scale_bits,
        resolution,
        moving,
        level,
    ))
}

/// `Tracer::prepare` with no re-basing, for a ray the shader answers: the
/// same f64 operations, rounded to f32 at the same points; infinite bounds
/// become [`PARAMETER_BOUND`] (the traversal is the same, see there).
#[inline(always)]
fn usual(
    origin: [f64; 3],
    dir: [f64; 3],
    [tmin, tmax]: [f64; 2],
    scale_bits: u64,
    resolution: f64,
    moving: u32,
    level: u8,
) -> GpuRay {
    let scale = f64::from_bits(scale_bits);
    // 1 / scale is a power of two too: negate the exponent (no division).
    let inv_scale = f64::from_bits((2046 - (scale_bits >> 52)) << 52);
    // |d| / scale (exact) in [2^-60, 2); zero axes count as 1 in the product.
    let scaled = dir.map(|d| if d == 0.0 { 1.0 } else { d.abs() * inv_scale });
    let reciprocal = 1.0 / (scaled[0] * scaled[1] * scaled[2]);
    let inverse = [
        reciprocal * scaled[1] * scaled[2],
        reciprocal * scaled[0] * scaled[2],
        reciprocal * scaled[0] * scaled[1],
    ];
    let mut octant = 0u32;
    let mut o32 = [0f32; 3];
    let mut inv32 = [0f32; 3];
    for i in 0..3 {
        let mut o = origin[i];
        if dir[i] < 0.0 {
            octant |= 1 << i;
            o = resolution - o;
        }
        o32[i] = o as f32;
        inv32[i] = if dir[i] == 0.0 {
            TINY_DIRECTION_INVERSE
        } else {
            inverse[i] as f32
        };
    }
    let limit = f64::from(PARAMETER_BOUND);
    let bound = |t: f64| (t * scale).clamp(-limit, limit) as f32;
    GpuRay {
        origin: [o32[0], o32[1], o32[2], bound(tmin)],
        inv_dir: [inv32[0], inv32[1], inv32[2], bound(tmax)],
        octant,
        level: u32::from(level),
        flags: moving << RAY_MOVING_SHIFT,
        scale_exponent: ((scale_bits >> 52) as i32 - 1023) as u32,
    }
}

/// The tolerance of the ray/hit semantics in grid units.
fn tolerance(resolution: f64, max_origin: f64) -> f64 {
    2f64.powi(-12) + 2f64.powi(-21) * resolution.max(max_origin)
}

/// The ray in f64 grid space as the set-up sees it (for a ray that
/// [`setup`] sends to the shader).
fn grid_ray(frame: &Frame, ray: &Ray) -> GridRay {
    let origin: [f64; 3] =
        std::array::from_fn(|i| (f64::from(ray.origin[i]) - frame.root_min[i]) * frame.grid_scale);
    let mut dir = ray.dir.map(|d| f64::from(d) * frame.grid_scale);
    let largest = dir.iter().fold(0f64, |m, v| m.max(v.abs()));
    for d in &mut dir {
        if largest < f64::MIN_POSITIVE || d.abs() < largest * TINY_DIRECTION {
            *d = 0.0;
        }
    }
    let max_origin = origin.iter().fold(0f64, |m, v| m.max(v.abs()));
    GridRay {
        origin,
        dir,
        tmin: f64::from(ray.tmin),
        tmax: f64::from(ray.tmax),
        eps: tolerance((1u64 << frame.depth) as f64, max_origin),
    }
}

/// Entry parameter and face of `ray`, which [`setup`] sent to the shader,
/// into the cell `cell` of `level` the shader found, in f64 (see [`answer`]).
pub(crate) fn host_answer(frame: &Frame, ray: &Ray, cell: [u32; 3], level: u8) -> (f32, u8) {
    answer(frame.depth, &grid_ray(frame, ray), cell, level)
}

/// The level-0 answer: the root cell itself.
fn root_hit(frame: &Frame, grid: &GridRay) -> Hit {
    let (t, face) = answer(frame.depth, grid, [0; 3], 0);
    Hit {
        hit: true,
        t,
        voxel: [0; 3],
        level: 0,
        face,
        index: frame.indexed.then_some(0),
    }
}

/// Entry parameter and face of the grid ray into cell `cell` of `level`, in
/// f64. The traversal is exact up to f32 rounding, so the cell may be missed
/// by a hair; then the cell grown by the tolerance is used.
fn answer(depth: u8, grid: &GridRay, cell: [u32; 3], level: u8) -> (f32, u8) {
    let s = (1u64 << (depth - level)) as f64;
    let lo = cell.map(|c| f64::from(c) * s);
    let hi = lo.map(|v| v + s);
    let entry = entry(grid, lo, hi)
        .or_else(|| entry(grid, lo.map(|v| v - grid.eps), hi.map(|v| v + grid.eps)));
    let (t, face) = entry.unwrap_or_else(|| {
        // Not met even by the grown cell (only for a malformed file).
        let (near, face) = near_face(grid, lo, hi);
        (grid.tmin.max(near).min(grid.tmax), face)
    });
    (t as f32, face)
}

/// Slab test of the line `o + t d` against the closed box `[lo, hi]`, zero
/// direction components giving all or nothing: `(t_near, t_far)` when the
/// slabs overlap.
fn slab(o: &[f64; 3], d: &[f64; 3], lo: [f64; 3], hi: [f64; 3]) -> Option<(f64, f64)> {
    let (mut near, mut far) = (f64::NEG_INFINITY, f64::INFINITY);
    for i in 0..3 {
        if d[i] == 0.0 {
            if o[i] < lo[i] || o[i] > hi[i] {
                return None;
            }
        } else {
            let a = (lo[i] - o[i]) / d[i];
            let b = (hi[i] - o[i]) / d[i];
            near = near.max(a.min(b));
            far = far.min(a.max(b));
        }
    }
    (near <= far).then_some((near, far))
}

/// The slab entry parameter and entry face of a box (without checking that
/// the ray meets it).
fn near_face(grid: &GridRay, lo: [f64; 3], hi: [f64; 3]) -> (f64, u8) {
    let mut near = f64::NEG_INFINITY;
    let mut face = 0u8;
    for i in 0..3 {
        let d = grid.dir[i];
        if d != 0.0 {
            let n = ((lo[i] - grid.origin[i]) / d).min((hi[i] - grid.origin[i]) / d);
            if n > near {
                near = n;
                face = 1 + 2 * i as u8 + u8::from(d < 0.0);
            }
        }
    }
    (near, if near < grid.tmin { 0 } else { face })
}

/// Entry parameter and face of the grid ray into the closed box `[lo, hi]`.
fn entry(grid: &GridRay, lo: [f64; 3], hi: [f64; 3]) -> Option<(f64, u8)> {
    let (near, far) = slab(&grid.origin, &grid.dir, lo, hi)?;
    let t = grid.tmin.max(near);
    if t > grid.tmax.min(far) {
        return None;
    }
    let (_, face) = near_face(grid, lo, hi);
    Some((t, face))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// SplitMix64.
    fn next(state: &mut u64) -> u64 {
        *state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = *state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn unit(state: &mut u64) -> f64 {
        (next(state) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// A ray component: mostly ordinary values around the cube, and the
    /// values where [`setup`]'s cases meet (zero, signed zero, tiny and huge
    /// magnitudes, subnormals, infinities, NaN, random bit patterns).
    fn component(state: &mut u64, centre: f64, size: f64) -> f32 {
        match next(state) % 48 {
            0 => 0.0,
            1 => -0.0,
            2 => f32::NAN,
            3 => [f32::INFINITY, f32::NEG_INFINITY][(next(state) % 2) as usize],
            4 => f32::from_bits(next(state) as u32),
            5 => f32::from_bits(next(state) as u32 & 0x807f_ffff),
            6 => ((unit(state) - 0.5) * 2f64.powi((next(state) % 260) as i32 - 130)) as f32,
            7 => (centre + size * 40.0 * (unit(state) - 0.5)) as f32,
            _ => (centre + size * (2.0 * unit(state) - 0.5)) as f32,
        }
    }

    /// A random ray around `frame`'s cube, often hostile (see [`component`]).
    pub(crate) fn random_ray(state: &mut u64, frame: &Frame) -> Ray {
        let size = (1u64 << frame.depth) as f64 / frame.grid_scale;
        let origin = std::array::from_fn(|i| component(state, frame.root_min[i], size));
        let dir: [f32; 3] = std::array::from_fn(|_| component(state, 0.0, size));
        // Now and then one component far below the others (the tiny-direction rule).
        let dir = if next(state).is_multiple_of(8) {
            let i = (next(state) % 3) as usize;
            let mut d = dir;
            d[i] = dir[(i + 1) % 3] * 2f32.powi(-(55 + (next(state) % 10) as i32));
            d
        } else {
            dir
        };
        let bound = |state: &mut u64| match next(state) % 6 {
            0 => 0.0,
            1 => f32::INFINITY,
            2 => f32::NEG_INFINITY,
            3 => f32::NAN,
            _ => (unit(state) * 4.0 - 1.0) as f32,
        };
        let (tmin, tmax) = match next(state) % 4 {
            0 => (bound(state), bound(state)),
            1 => (0.0, f32::INFINITY),
            _ => {
                let tmin = (unit(state) * 4.0 - 1.0) as f32;
                (tmin, tmin + unit(state) as f32 * 3.0)
            }
        };
        let level = match next(state) % 4 {
            0 => Some((next(state) % (u64::from(frame.depth) + 3)) as u8),
            _ => None,
        };
        Ray {
            origin,
            dir,
            tmin,
            tmax,
            level,
        }
    }

    /// Frames of several depths, origins and scales, and an empty one.
    pub(crate) fn frames() -> Vec<Frame> {
        [
            (12, [-0.53, 0.0, -1.7e-3], 1.3, false),
            (5, [0.0; 3], 1.0, false),
            (20, [1.0e3, -2.5e4, 7.0], 3.0e-2, false),
            (3, [-1.0, -1.0, -1.0], 7.0, true),
            (24, [0.1, 0.2, 0.3], 1.0e6, false),
        ]
        .into_iter()
        .map(|(depth, root_min, root_size, empty)| Frame {
            depth,
            root_min,
            grid_scale: (1u64 << depth) as f64 / root_size,
            empty,
            indexed: false,
        })
        .collect()
    }

    /// `setup_usual` gives the very record `setup` gives for every ray
    /// `setup` answers in the shader without the host, and declines every
    /// other ray.
    #[test]
    fn usual_set_up_is_setup_to_the_bit() {
        let mut state = 7u64;
        let mut usual = 0;
        for frame in frames() {
            for _ in 0..200_000 {
                let ray = random_ray(&mut state, &frame);
                let fast = setup_usual(&frame, &ray);
                match (fast, setup(&frame, &ray)) {
                    (Some(a), Ok(Setup::Trace(b))) => {
                        usual += 1;
                        assert_eq!(
                            bytemuck::bytes_of(&a),
                            bytemuck::bytes_of(&b),
                            "{ray:?} in {frame:?}"
                        );
                        assert_eq!(
                            b.flags & (RAY_HOST_ANSWER | super::super::layout::RAY_SKIP),
                            0
                        );
                    }
                    (None, Ok(Setup::Trace(b))) => {
                        assert_ne!(
                            b.flags & RAY_HOST_ANSWER,
                            0,
                            "{ray:?} in {frame:?}: declined"
                        )
                    }
                    (None, _) => {}
                    (Some(a), other) => panic!("{ray:?} in {frame:?}: {a:?} but {other:?}"),
                }
            }
        }
        // The usual rays are a good share of the sample.
        assert!(usual > 300_000, "{usual}");
    }
}
