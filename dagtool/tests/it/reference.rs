//! The independent reference: a brute-force voxelizer written from the
//! documented rules, sharing no code with the converter.
//!
//! - Placement (dagtool convert --help): root cube centred on the bounding box
//!   of the used vertices, edge `extent * 2^D / (2^D - 1)`; vertices snapped to
//!   `round((p - min) * 2^(D+16) / size)`.
//! - Surface: a voxel is set iff its closed cube overlaps a closed triangle,
//!   decided by the textbook Akenine-Möller test (tribox3: 9 edge axes, the box
//!   normals, the plane) around the box centre. Evaluated in exact integer
//!   arithmetic on the snapped mesh (doubled coordinates make box centres
//!   integers), and in `f64` with a margin on the original mesh.
//! - Every voxel of each triangle's bounding box is tested (the bounding box is
//!   the box-normal part of the same test, so nothing is skipped).

use std::collections::BTreeSet;
use std::path::Path;

/// A mesh loaded for the reference (f64 positions from the OBJ's f32).
pub struct RefMesh {
    pub vertices: Vec<[f64; 3]>,
    pub triangles: Vec<[usize; 3]>,
    pub materials: Vec<Option<usize>>,
    pub colors: Vec<[u8; 4]>,
}

pub fn load(path: &Path) -> RefMesh {
    let opts = tobj::LoadOptions {
        triangulate: true,
        single_index: false,
        ..Default::default()
    };
    let (models, mats) = tobj::load_obj(path, &opts).expect("reference loads the OBJ");
    let colors: Vec<[u8; 4]> = mats
        .map(|m| {
            m.iter()
                .map(|m| match m.diffuse {
                    Some(kd) => {
                        let c = kd.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
                        let a = m
                            .dissolve
                            .map_or(255, |d| (d.clamp(0.0, 1.0) * 255.0).round() as u8);
                        [c[0], c[1], c[2], a]
                    }
                    None => [255; 4],
                })
                .collect()
        })
        .unwrap_or_default();
    let mut mesh = RefMesh {
        vertices: Vec::new(),
        triangles: Vec::new(),
        materials: Vec::new(),
        colors,
    };
    for model in models {
        let base = mesh.vertices.len();
        for p in model.mesh.positions.chunks(3) {
            mesh.vertices.push([p[0] as f64, p[1] as f64, p[2] as f64]);
        }
        for t in model.mesh.indices.chunks(3) {
            mesh.triangles.push([
                t[0] as usize + base,
                t[1] as usize + base,
                t[2] as usize + base,
            ]);
            mesh.materials.push(model.mesh.material_id);
        }
    }
    mesh
}

/// The root cube of the documented placement rule: (min corner, edge).
pub fn root_cube(mesh: &RefMesh, depth: u8) -> ([f64; 3], f64) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for t in &mesh.triangles {
        for &i in t {
            for a in 0..3 {
                lo[a] = lo[a].min(mesh.vertices[i][a]);
                hi[a] = hi[a].max(mesh.vertices[i][a]);
            }
        }
    }
    let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
    let res = (1u64 << depth) as f64;
    let size = extent * res / (res - 1.0);
    let min = [0, 1, 2].map(|a| 0.5 * (lo[a] + hi[a]) - 0.5 * size);
    (min, size)
}

pub const SUB: i64 = 1 << 16;

/// Snapped triangles (lattice units of 1/65536 voxel).
pub fn snapped(mesh: &RefMesh, depth: u8) -> Vec<[[i64; 3]; 3]> {
    let (min, size) = root_cube(mesh, depth);
    let units = (1u64 << (depth as u32 + 16)) as f64;
    let scale = units / size;
    mesh.triangles
        .iter()
        .map(|t| {
            t.map(|i| {
                [0, 1, 2].map(|a| {
                    ((mesh.vertices[i][a] - min[a]) * scale)
                        .round()
                        .clamp(0.0, units) as i64
                })
            })
        })
        .collect()
}

/// Triangles in voxel units, unsnapped (f64).
pub fn in_voxels(mesh: &RefMesh, depth: u8) -> Vec<[[f64; 3]; 3]> {
    let (min, size) = root_cube(mesh, depth);
    let scale = (1u64 << depth) as f64 / size;
    mesh.triangles
        .iter()
        .map(|t| t.map(|i| [0, 1, 2].map(|a| (mesh.vertices[i][a] - min[a]) * scale)))
        .collect()
}

/// Numbers the textbook test runs on.
pub trait Num:
    Copy
    + PartialOrd
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::Neg<Output = Self>
{
    const ZERO: Self;
    const ONE: Self;
    fn abs(self) -> Self {
        if self < Self::ZERO { -self } else { self }
    }
}
impl Num for i128 {
    const ZERO: Self = 0;
    const ONE: Self = 1;
}
impl Num for f64 {
    const ZERO: Self = 0.0;
    const ONE: Self = 1.0;
}

fn cross<T: Num>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot<T: Num>(a: [T; 3], b: [T; 3]) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Akenine-Möller's triangle/box overlap (tribox3) for the box centred at
/// `center` with half-size `h`; touching counts as overlapping (closed sets).
pub fn tri_box<T: Num>(tri: [[T; 3]; 3], center: [T; 3], h: T) -> bool {
    let v = tri.map(|p| [p[0] - center[0], p[1] - center[1], p[2] - center[2]]);
    let e = [0, 1, 2].map(|i| {
        let a = v[i];
        let b = v[(i + 1) % 3];
        [b[0] - a[0], b[1] - a[1], b[2] - a[2]]
    });
    // 9 axes: unit axis x edge.
    for edge in e {
        for k in 0..3 {
            let mut unit = [T::ZERO; 3];
            unit[k] = T::ONE;
            let axis = cross(unit, edge);
            let p = v.map(|q| dot(axis, q));
            let mn = min3(p);
            let mx = max3(p);
            let rad = h * (axis[0].abs() + axis[1].abs() + axis[2].abs());
            if mn > rad || mx < -rad {
                return false;
            }
        }
    }
    // Box normals: the triangle's bounding box against [-h, h]^3.
    for a in 0..3 {
        let p = v.map(|q| q[a]);
        if min3(p) > h || max3(p) < -h {
            return false;
        }
    }
    // The plane.
    let normal = cross(e[0], e[1]);
    let mut vmin = [T::ZERO; 3];
    let mut vmax = [T::ZERO; 3];
    for q in 0..3 {
        if normal[q] > T::ZERO {
            vmin[q] = -h - v[0][q];
            vmax[q] = h - v[0][q];
        } else {
            vmin[q] = h - v[0][q];
            vmax[q] = -h - v[0][q];
        }
    }
    if dot(normal, vmin) > T::ZERO {
        return false;
    }
    dot(normal, vmax) >= T::ZERO
}

fn min3<T: Num>(p: [T; 3]) -> T {
    let m = if p[0] < p[1] { p[0] } else { p[1] };
    if m < p[2] { m } else { p[2] }
}

fn max3<T: Num>(p: [T; 3]) -> T {
    let m = if p[0] > p[1] { p[0] } else { p[1] };
    if m > p[2] { m } else { p[2] }
}

/// Voxel index range of a triangle's bounding box (closed cubes), clamped.
fn bbox(lo: f64, hi: f64, res: i64) -> (i64, i64) {
    (
        ((lo.ceil() as i64) - 1).max(0),
        (hi.floor() as i64).min(res - 1),
    )
}

/// The exact reference surface voxelization of the snapped mesh; per voxel
/// (Morton code), the index of the first triangle that overlaps it.
pub fn surface(tris: &[[[i64; 3]; 3]], depth: u8) -> std::collections::BTreeMap<u64, usize> {
    let res = 1i64 << depth;
    let mut out = std::collections::BTreeMap::new();
    for (ti, t) in tris.iter().enumerate() {
        // Doubled coordinates: box centre (2k + 1) * SUB, half size SUB.
        let d = t.map(|p| p.map(|c| 2 * i128::from(c)));
        let mut r = [(0, 0); 3];
        for a in 0..3 {
            let lo = t.iter().map(|p| p[a]).min().unwrap() as f64 / SUB as f64;
            let hi = t.iter().map(|p| p[a]).max().unwrap() as f64 / SUB as f64;
            r[a] = bbox(lo, hi, res);
        }
        for z in r[2].0..=r[2].1 {
            for y in r[1].0..=r[1].1 {
                for x in r[0].0..=r[0].1 {
                    let center = [x, y, z].map(|k| i128::from(2 * k + 1) * i128::from(SUB));
                    if tri_box(d, center, i128::from(SUB)) {
                        out.entry(dagfmt::morton::encode(x as u32, y as u32, z as u32))
                            .or_insert(ti);
                    }
                }
            }
        }
    }
    out
}

/// Morton codes of the exact reference surface, sorted.
pub fn surface_codes(tris: &[[[i64; 3]; 3]], depth: u8) -> Vec<u64> {
    surface(tris, depth).into_keys().collect()
}

/// Voxels overlapping the unsnapped triangles with the box grown by `margin`
/// voxels (f64); `margin < 0` shrinks it.
pub fn surface_f64(tris: &[[[f64; 3]; 3]], depth: u8, margin: f64) -> BTreeSet<u64> {
    let res = 1i64 << depth;
    let mut out = BTreeSet::new();
    for t in tris {
        let mut r = [(0, 0); 3];
        for a in 0..3 {
            let lo = t.iter().map(|p| p[a]).fold(f64::INFINITY, f64::min) - margin.max(0.0);
            let hi = t.iter().map(|p| p[a]).fold(f64::NEG_INFINITY, f64::max) + margin.max(0.0);
            r[a] = bbox(lo, hi, res);
        }
        for z in r[2].0..=r[2].1 {
            for y in r[1].0..=r[1].1 {
                for x in r[0].0..=r[0].1 {
                    let center = [x, y, z].map(|k| k as f64 + 0.5);
                    if tri_box(*t, center, 0.5 + margin) {
                        out.insert(dagfmt::morton::encode(x as u32, y as u32, z as u32));
                    }
                }
            }
        }
    }
    out
}

/// Checks `got` against the original (unsnapped) geometry: every voxel set
/// lies within `margin` of a triangle, and every voxel that overlaps a
/// triangle by more than `margin` is set.
pub fn check_against_f64(got: &[u64], tris: &[[[f64; 3]; 3]], depth: u8, margin: f64, what: &str) {
    let grown = surface_f64(tris, depth, margin);
    let shrunk = surface_f64(tris, depth, -margin);
    let got_set: BTreeSet<u64> = got.iter().copied().collect();
    let spurious: Vec<[u32; 3]> = got_set
        .difference(&grown)
        .take(5)
        .map(|&c| dagfmt::morton::decode(c))
        .collect();
    assert!(
        spurious.is_empty(),
        "{what}: voxels farther than {margin} from every triangle: {spurious:?}"
    );
    let holes: Vec<[u32; 3]> = shrunk
        .difference(&got_set)
        .take(5)
        .map(|&c| dagfmt::morton::decode(c))
        .collect();
    assert!(
        holes.is_empty(),
        "{what}: voxels overlapping a triangle by more than {margin} are missing: {holes:?}"
    );
}

/// Generalized winding number of `p` with respect to the triangles (f64):
/// the sum of signed solid angles over 4 pi (Van Oosterom and Strackee).
pub fn winding_number(tris: &[[[f64; 3]; 3]], p: [f64; 3]) -> f64 {
    let mut total = 0.0;
    for t in tris {
        let a = [0, 1, 2].map(|k| t[0][k] - p[k]);
        let b = [0, 1, 2].map(|k| t[1][k] - p[k]);
        let c = [0, 1, 2].map(|k| t[2][k] - p[k]);
        let la = dot(a, a).sqrt();
        let lb = dot(b, b).sqrt();
        let lc = dot(c, c).sqrt();
        let num = dot(a, cross(b, c));
        let den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb;
        total += 2.0 * num.atan2(den);
    }
    total / (4.0 * std::f64::consts::PI)
}

/// The expected solid voxelization of a closed mesh: the exact surface plus
/// every voxel whose centre has winding number above 1/2. (Centres within
/// half a voxel of the surface are surface voxels anyway, so the winding
/// number is only decisive far from the surface, where f64 is reliable.)
pub fn solid_codes(snapped: &[[[i64; 3]; 3]], unsnapped: &[[[f64; 3]; 3]], depth: u8) -> Vec<u64> {
    let mut set: BTreeSet<u64> = surface_codes(snapped, depth).into_iter().collect();
    let res = 1u32 << depth;
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for t in unsnapped {
        for p in t {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
    }
    for z in 0..res {
        for y in 0..res {
            for x in 0..res {
                let c = [x, y, z].map(|k| k as f64 + 0.5);
                if (0..3).any(|a| c[a] < lo[a] || c[a] > hi[a]) {
                    continue;
                }
                let code = dagfmt::morton::encode(x, y, z);
                if !set.contains(&code) && winding_number(unsnapped, c) > 0.5 {
                    set.insert(code);
                }
            }
        }
    }
    set.into_iter().collect()
}
