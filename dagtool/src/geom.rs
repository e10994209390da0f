//! Exact geometry on snapped triangles.
//!
//! The converter never decides "does this triangle touch this voxel?" with
//! rounded arithmetic. Vertices are first snapped to a fixed-point lattice of
//! [`SUBVOXEL`] units per voxel (see [`crate::mesh::GridMapping`]); from then on
//! every predicate is evaluated exactly in integers (`i64` where the magnitudes
//! provably fit, `i128` otherwise). So the voxel set is a pure function of the
//! snapped mesh: independent of chunking, thread count and evaluation order, and
//! equal to any other exact evaluation of the same predicate (the test suite's
//! brute-force reference).

use std::ops::{Add, Mul, Neg, Sub};

/// log2 of the number of lattice units per voxel edge.
pub const SUBVOXEL_BITS: u32 = 16;
/// Lattice units per voxel edge: snapped vertices are multiples of `1/SUBVOXEL` voxel.
pub const SUBVOXEL: i64 = 1 << SUBVOXEL_BITS;

/// A snapped point in lattice units (voxel `k` spans `[k * SUBVOXEL, (k + 1) * SUBVOXEL]`).
pub type Point = [i64; 3];
/// A snapped triangle. It may be degenerate (a segment or a point).
pub type Triangle = [Point; 3];

/// `a - b` widened to `i128`.
#[inline]
pub fn sub128(a: Point, b: Point) -> [i128; 3] {
    [0, 1, 2].map(|i| i128::from(a[i]) - i128::from(b[i]))
}

/// Cross product in `i128`.
#[inline]
pub fn cross128(a: [i128; 3], b: [i128; 3]) -> [i128; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// The (unnormalised) normal `(v1 - v0) x (v2 - v0)`; zero for a degenerate triangle.
#[inline]
pub fn normal(tri: &Triangle) -> [i128; 3] {
    cross128(sub128(tri[1], tri[0]), sub128(tri[2], tri[0]))
}

/// Whether the closed triangle `tri` intersects the closed axis-aligned cube
/// `[lo, lo + size]` (lattice units), decided exactly by the separating axis
/// theorem with all 13 axes (Akenine-Möller): the 3 box normals, the triangle
/// normal and the 9 cross products of box edges with triangle edges. Degenerate
/// triangles need no special case: their zero axes never separate, and the
/// remaining axes are exactly those of a segment or a point.
///
/// Magnitudes: coordinates below 2^40 keep every product below 2^122.
pub fn triangle_overlaps_box(tri: &Triangle, lo: Point, size: i64) -> bool {
    for a in 0..3 {
        let mn = tri.iter().map(|p| p[a]).min().expect("3 vertices");
        let mx = tri.iter().map(|p| p[a]).max().expect("3 vertices");
        if mx < lo[a] || mn > lo[a] + size {
            return false;
        }
    }
    // Work relative to the box corner to keep magnitudes small.
    let v = tri.map(|p| sub128(p, lo));
    let size = i128::from(size);
    let separated = |axis: [i128; 3]| -> bool {
        let p = v.map(|q| axis[0] * q[0] + axis[1] * q[1] + axis[2] * q[2]);
        let pmin = p[0].min(p[1]).min(p[2]);
        let pmax = p[0].max(p[1]).max(p[2]);
        let rlo: i128 = axis.iter().map(|&c| c.min(0) * size).sum();
        let rhi: i128 = axis.iter().map(|&c| c.max(0) * size).sum();
        pmax < rlo || pmin > rhi
    };
    let e = [0, 1, 2].map(|i| {
        let a = v[i];
        let b = v[(i + 1) % 3];
        [b[0] - a[0], b[1] - a[1], b[2] - a[2]]
    });
    if separated(cross128(e[0], [-e[2][0], -e[2][1], -e[2][2]])) {
        return false;
    }
    for edge in e {
        let axes = [
            [0, -edge[2], edge[1]],
            [edge[2], 0, -edge[0]],
            [-edge[1], edge[0], 0],
        ];
        if axes.into_iter().any(separated) {
            return false;
        }
    }
    true
}

/// The integer arithmetic the per-voxel loops are generic over: `i64` when the
/// triangle is small enough for every product to fit, `i128` otherwise.
pub(crate) trait Int:
    Copy + Ord + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Neg<Output = Self>
{
    const ZERO: Self;
    const ONE: Self;
    fn from_i64(v: i64) -> Self;
    /// `floor(self / d)` for `d > 0`.
    fn div_floor(self, d: Self) -> Self;
    /// `ceil(self / d)` for `d > 0`.
    fn div_ceil_pos(self, d: Self) -> Self {
        -((-self).div_floor(d))
    }
    /// Clamps to the `i64` range.
    fn clamp_i64(self) -> i64;
}

impl Int for i64 {
    const ZERO: Self = 0;
    const ONE: Self = 1;
    #[inline]
    fn from_i64(v: i64) -> Self {
        v
    }
    #[inline]
    fn div_floor(self, d: Self) -> Self {
        self.div_euclid(d)
    }
    #[inline]
    fn clamp_i64(self) -> i64 {
        self
    }
}

impl Int for i128 {
    const ZERO: Self = 0;
    const ONE: Self = 1;
    #[inline]
    fn from_i64(v: i64) -> Self {
        i128::from(v)
    }
    #[inline]
    fn div_floor(self, d: Self) -> Self {
        self.div_euclid(d)
    }
    #[inline]
    fn clamp_i64(self) -> i64 {
        self.clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64
    }
}

/// `c * x` must lie in `[lo, hi]`: the integer range of `x`, or `None` when
/// `c == 0` and the constraint fails (an empty range is returned as lo > hi).
#[inline]
pub(crate) fn solve_linear<T: Int>(c: T, lo: T, hi: T) -> (i64, i64) {
    if c > T::ZERO {
        (lo.div_ceil_pos(c).clamp_i64(), hi.div_floor(c).clamp_i64())
    } else if c < T::ZERO {
        (
            (-hi).div_ceil_pos(-c).clamp_i64(),
            (-lo).div_floor(-c).clamp_i64(),
        )
    } else if lo <= T::ZERO && T::ZERO <= hi {
        (i64::MIN, i64::MAX)
    } else {
        (1, 0)
    }
}

/// One separating-axis constraint of a projected triangle edge against a
/// voxel square: `lo <= k1 * i1 + k2 * i2 <= hi`, with `(i1, i2)` the voxel's
/// integer coordinates (relative to the triangle's local origin) on the two
/// projection axes.
#[derive(Clone, Copy, Debug)]
pub(crate) struct EdgeConstraint<T> {
    pub k1: T,
    pub k2: T,
    pub lo: T,
    pub hi: T,
}

/// The constraints of the triangle projected along the third axis onto axes
/// `(a1, a2)`: for each non-degenerate edge, the axis perpendicular to it in
/// the projection plane (the box-edge x triangle-edge SAT axis). `p` holds
/// local lattice coordinates; `s` is the voxel size in lattice units.
pub(crate) fn edge_constraints<T: Int>(
    p: &[[T; 3]; 3],
    a1: usize,
    a2: usize,
    s: T,
) -> ([EdgeConstraint<T>; 3], usize) {
    let zero = EdgeConstraint {
        k1: T::ZERO,
        k2: T::ZERO,
        lo: T::ZERO,
        hi: T::ZERO,
    };
    let mut out = [zero; 3];
    let mut n = 0;
    for j in 0..3 {
        let a = p[j];
        let b = p[(j + 1) % 3];
        let c1 = -(b[a2] - a[a2]);
        let c2 = b[a1] - a[a1];
        if c1 == T::ZERO && c2 == T::ZERO {
            continue;
        }
        let t = p.map(|q| c1 * q[a1] + c2 * q[a2]);
        let tmin = t[0].min(t[1]).min(t[2]);
        let tmax = t[0].max(t[1]).max(t[2]);
        let rlo = s * (c1.min(T::ZERO) + c2.min(T::ZERO));
        let rhi = s * (c1.max(T::ZERO) + c2.max(T::ZERO));
        out[n] = EdgeConstraint {
            k1: s * c1,
            k2: s * c2,
            lo: tmin - rhi,
            hi: tmax - rlo,
        };
        n += 1;
    }
    (out, n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solve_linear_ranges() {
        assert_eq!(solve_linear::<i64>(3, -7, 7), (-2, 2));
        assert_eq!(solve_linear::<i64>(-3, -7, 7), (-2, 2));
        assert_eq!(solve_linear::<i64>(2, 1, 1), (1, 0));
        assert_eq!(solve_linear::<i64>(0, 1, 2), (1, 0));
        assert_eq!(solve_linear::<i64>(0, -1, 2), (i64::MIN, i64::MAX));
        assert_eq!(solve_linear::<i128>(-2, 4, 9), (-4, -2));
    }

    #[test]
    fn box_overlap_basics() {
        let s = SUBVOXEL;
        let tri = [[0, 0, 0], [s, 0, 0], [0, s, 0]];
        assert!(triangle_overlaps_box(&tri, [0, 0, 0], s));
        // Touching the face z = 0 from below counts (closed boxes).
        assert!(triangle_overlaps_box(&tri, [0, 0, -s], s));
        assert!(!triangle_overlaps_box(&tri, [0, 0, -2 * s], s));
        // The hypotenuse x + y = s touches the neighbouring box at (s, 0).
        assert!(triangle_overlaps_box(&tri, [s, 0, 0], s));
        assert!(!triangle_overlaps_box(&tri, [s, s, 0], s - 1));
        // A point.
        let p = [[5, 5, 5]; 3];
        assert!(triangle_overlaps_box(&p, [0, 0, 0], 5));
        assert!(!triangle_overlaps_box(&p, [0, 0, 0], 4));
    }
}
