//! Procedural meshes and a simple conservative surface voxelizer.
//!
//! The mesh cases need volumes that look like converter output. The project's
//! converter (dagtool) is developed in parallel, so the suite carries its own
//! small voxelizer: a voxel is set when its closed cube overlaps a triangle,
//! decided by the separating-axis test of Akenine-Möller ("Fast 3D
//! triangle-box overlap testing", 2001): the 3 box normals, the triangle
//! normal and the 9 edge cross products. Every voxel the surface touches is
//! set (conservative), the interior is left empty. The result only has to be
//! deterministic: the oracle judges tracers against the voxels actually
//! stored, whatever voxelizer made them.

/// A triangle soup.
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    /// Triangles, as three corner positions each.
    pub triangles: Vec<[[f64; 3]; 3]>,
}

/// Sine and cosine of `x` in `[-2pi, 2pi]` from their Taylor series, using
/// only correctly rounded IEEE operations, so that the generated meshes (and
/// the committed cases) are identical on every platform, whatever its libm.
fn sin_cos(x: f64) -> (f64, f64) {
    let x = if x > std::f64::consts::PI {
        x - 2.0 * std::f64::consts::PI
    } else {
        x
    };
    let (mut sin, mut cos) = (0.0, 0.0);
    let mut term = 1.0; // x^k / k!
    for k in 0..40u32 {
        match k % 4 {
            0 => cos += term,
            1 => sin += term,
            2 => cos -= term,
            _ => sin -= term,
        }
        term *= x / f64::from(k + 1);
    }
    (sin, cos)
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

impl Mesh {
    /// A UV sphere: `rings` bands of latitude, `segments` of longitude.
    pub fn sphere(center: [f64; 3], radius: f64, rings: u32, segments: u32) -> Mesh {
        let point = |ring: u32, seg: u32| {
            let theta = std::f64::consts::PI * f64::from(ring) / f64::from(rings);
            let phi = 2.0 * std::f64::consts::PI * f64::from(seg % segments) / f64::from(segments);
            let ((sin_t, cos_t), (sin_p, cos_p)) = (sin_cos(theta), sin_cos(phi));
            [
                center[0] + radius * sin_t * cos_p,
                center[1] + radius * cos_t,
                center[2] + radius * sin_t * sin_p,
            ]
        };
        let mut mesh = Mesh::default();
        for ring in 0..rings {
            for seg in 0..segments {
                let (a, b, c, d) = (
                    point(ring, seg),
                    point(ring, seg + 1),
                    point(ring + 1, seg),
                    point(ring + 1, seg + 1),
                );
                if ring != 0 {
                    mesh.triangles.push([a, b, d]);
                }
                if ring + 1 != rings {
                    mesh.triangles.push([a, d, c]);
                }
            }
        }
        mesh
    }

    /// A torus around the y axis through `center`: tube radius `minor`, ring
    /// radius `major`.
    pub fn torus(center: [f64; 3], major: f64, minor: f64, rings: u32, sides: u32) -> Mesh {
        let point = |ring: u32, side: u32| {
            let u = 2.0 * std::f64::consts::PI * f64::from(ring % rings) / f64::from(rings);
            let v = 2.0 * std::f64::consts::PI * f64::from(side % sides) / f64::from(sides);
            let ((sin_u, cos_u), (sin_v, cos_v)) = (sin_cos(u), sin_cos(v));
            let r = major + minor * cos_v;
            [
                center[0] + r * cos_u,
                center[1] + minor * sin_v,
                center[2] + r * sin_u,
            ]
        };
        let mut mesh = Mesh::default();
        for ring in 0..rings {
            for side in 0..sides {
                let (a, b, c, d) = (
                    point(ring, side),
                    point(ring + 1, side),
                    point(ring, side + 1),
                    point(ring + 1, side + 1),
                );
                mesh.triangles.push([a, b, d]);
                mesh.triangles.push([a, d, c]);
            }
        }
        mesh
    }

    /// The set voxels (in grid units, the grid spanning `[0, 2^depth)^3`) of a
    /// conservative surface voxelization. Triangles are given in grid units.
    /// The result is sorted and free of duplicates.
    pub fn voxelize(&self, depth: u8) -> Vec<[u32; 3]> {
        let n = 1i64 << depth;
        let mut out = Vec::new();
        for tri in &self.triangles {
            let mut lo = [0i64; 3];
            let mut hi = [0i64; 3];
            for axis in 0..3 {
                let min = tri.iter().map(|p| p[axis]).fold(f64::INFINITY, f64::min);
                let max = tri
                    .iter()
                    .map(|p| p[axis])
                    .fold(f64::NEG_INFINITY, f64::max);
                lo[axis] = (min.floor() as i64 - 1).max(0);
                hi[axis] = (max.floor() as i64 + 1).min(n - 1);
            }
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        let center = [x as f64 + 0.5, y as f64 + 0.5, z as f64 + 0.5];
                        if triangle_overlaps_box(tri, center, 0.5) {
                            out.push([x as u32, y as u32, z as u32]);
                        }
                    }
                }
            }
        }
        out.sort_unstable();
        out.dedup();
        out
    }
}

/// Whether the closed triangle `tri` overlaps the closed cube of half size
/// `half` around `center` (separating-axis test).
pub fn triangle_overlaps_box(tri: &[[f64; 3]; 3], center: [f64; 3], half: f64) -> bool {
    let v = tri.map(|p| sub(p, center));
    let edges = [sub(v[1], v[0]), sub(v[2], v[1]), sub(v[0], v[2])];
    let separated = |axis: [f64; 3]| {
        let p = v.map(|q| dot(q, axis));
        let r = half * (axis[0].abs() + axis[1].abs() + axis[2].abs());
        let min = p.iter().copied().fold(f64::INFINITY, f64::min);
        let max = p.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        min > r || max < -r
    };
    let unit = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    if unit.iter().any(|&a| separated(a)) {
        return false;
    }
    if separated(cross(edges[0], edges[1])) {
        return false;
    }
    for e in edges {
        for u in unit {
            if separated(cross(e, u)) {
                return false;
            }
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn series_matches_libm() {
        for i in 0..=200 {
            let x = std::f64::consts::TAU * (f64::from(i) / 100.0 - 1.0);
            let (s, c) = sin_cos(x);
            assert!(
                (s - x.sin()).abs() < 1e-13 && (c - x.cos()).abs() < 1e-13,
                "{x}"
            );
        }
    }

    #[test]
    fn overlap_test() {
        let tri = [[0.0, 0.0, 0.5], [1.0, 0.0, 0.5], [0.0, 1.0, 0.5]];
        assert!(triangle_overlaps_box(&tri, [0.5, 0.5, 0.5], 0.5));
        assert!(!triangle_overlaps_box(&tri, [0.5, 0.5, 2.5], 0.5));
        // The hypotenuse x + y = 1 touches the cube [0.5, 1]^2 at its corner.
        assert!(!triangle_overlaps_box(&tri, [0.75, 0.75, 0.5], 0.24));
        assert!(triangle_overlaps_box(&tri, [0.75, 0.75, 0.5], 0.25));
    }

    #[test]
    fn sphere_shell_is_closed_and_hollow() {
        let voxels = Mesh::sphere([8.0, 8.0, 8.0], 6.0, 16, 32).voxelize(4);
        assert!(voxels.contains(&[8, 14, 8]) || voxels.contains(&[8, 13, 8]));
        assert!(!voxels.contains(&[8, 8, 8]));
        // Every axis line through the centre crosses the shell.
        for axis in 0..3 {
            assert!(
                voxels
                    .iter()
                    .any(|v| v[(axis + 1) % 3] == 8 && v[(axis + 2) % 3] == 8 && v[axis] > 8)
            );
        }
    }
}
