//! Surface voxelization of procedural meshes equals the brute-force reference.

use crate::common::{ObjMesh, assert_same_voxels, box_mesh, convert, sphere_mesh, voxel_codes};
use crate::reference;

/// Converts `mesh` at each depth and compares with the exact reference (and
/// with the unsnapped geometry within 1e-3 voxel).
fn check_mesh(name: &str, mesh: &ObjMesh, depths: &[u8]) {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join(format!("{name}.obj"));
    mesh.write(&obj);
    let refmesh = reference::load(&obj);
    for &depth in depths {
        let out = dir.path().join(format!("{name}-{depth}.vdag"));
        convert(&obj, &out, depth, &[]);
        let got = voxel_codes(&out);
        let expected = reference::surface_codes(&reference::snapped(&refmesh, depth), depth);
        assert!(!expected.is_empty());
        assert_same_voxels(&got, &expected, &format!("{name} at depth {depth}"));
        reference::check_against_f64(
            &got,
            &reference::in_voxels(&refmesh, depth),
            depth,
            1e-3,
            name,
        );
        // The header's root cube is the documented one, exactly.
        let bytes = std::fs::read(&out).unwrap();
        let dag = dagfmt::AnyDag::open(&bytes).unwrap();
        let (min, size) = reference::root_cube(&refmesh, depth);
        assert_eq!(dag.header().root_min, min, "{name}: root cube corner");
        assert_eq!(dag.header().root_size, size, "{name}: root cube size");
        assert_eq!(dag.header().voxel_count, got.len() as u64);
    }
}

#[test]
fn tetrahedron() {
    let mut m = ObjMesh::default();
    let p = [
        [0.1, 0.2, 0.3],
        [3.7, 0.4, 1.1],
        [1.3, 2.9, 0.2],
        [1.6, 1.2, 3.3],
    ];
    for [a, b, c] in [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]] {
        m.add_triangle(p[a], p[b], p[c]);
    }
    check_mesh("tetrahedron", &m, &[2, 3, 4, 5, 6, 7]);
}

#[test]
fn cube_and_sphere() {
    check_mesh(
        "cube",
        &box_mesh([-1.3, 0.25, 2.0], [0.9, 1.7, 3.1]),
        &[2, 4, 6, 7],
    );
    check_mesh("sphere", &sphere_mesh([0.3, -0.2, 0.1], 1.7, 2), &[3, 5, 6]);
}

#[test]
fn thin_quads() {
    // Two parallel sheets 1e-4 apart and a slanted sheet crossing them: a
    // conservative voxelization has no holes however thin the wall.
    let mut m = ObjMesh::default();
    for z in [0.5, 0.5001] {
        let a = m.add_vertex([0.0, 0.0, z]);
        let b = m.add_vertex([4.0, 0.3, z]);
        let c = m.add_vertex([4.1, 3.9, z]);
        let d = m.add_vertex([0.2, 4.0, z]);
        m.faces.push(vec![a, b, c, d]);
    }
    let a = m.add_vertex([0.3, 0.1, 0.0]);
    let b = m.add_vertex([3.9, 0.2, 1.0]);
    let c = m.add_vertex([3.8, 3.7, 1.01]);
    let d = m.add_vertex([0.1, 3.95, 0.01]);
    m.faces.push(vec![a, b, c, d]);
    check_mesh("thin-quads", &m, &[3, 5, 7]);
}

#[test]
fn degenerate_triangles() {
    // A real triangle, a collinear one, one with a repeated vertex, a point,
    // and OBJ lines and points (tobj turns them into zero-area triangles).
    let obj = "\
v 0 0 0
v 3 0.2 0.1
v 0.4 2.9 0.3
v 0.5 0.5 0.5
v 1.5 1.2 0.9
v 2.5 1.9 1.3
v 2.2 0.3 2.7
v 0.7 2.1 1.9
f 1 2 3
f 4 5 6
f 4 7 7
f 8 8 8
l 2 7
p 3
";
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("degenerate.obj");
    std::fs::write(&path, obj).unwrap();
    let refmesh = reference::load(&path);
    assert!(
        refmesh.triangles.len() >= 5,
        "lines and points load as zero-area triangles"
    );
    for depth in [2, 4, 6, 7] {
        let out = dir.path().join(format!("d{depth}.vdag"));
        convert(&path, &out, depth, &[]);
        let got = voxel_codes(&out);
        let expected = reference::surface_codes(&reference::snapped(&refmesh, depth), depth);
        assert_same_voxels(&got, &expected, &format!("degenerate at depth {depth}"));
        reference::check_against_f64(
            &got,
            &reference::in_voxels(&refmesh, depth),
            depth,
            1e-3,
            "degenerate",
        );
        // The isolated point (vertex 8) is set: its voxel is in the output.
        let (min, size) = reference::root_cube(&refmesh, depth);
        let g = [0.7, 2.1, 1.9]
            .iter()
            .enumerate()
            .map(|(a, &p)| ((p - min[a]) * (1u64 << depth) as f64 / size) as u32)
            .collect::<Vec<_>>();
        assert!(
            got.contains(&dagfmt::morton::encode(g[0], g[1], g[2])),
            "the point triangle is voxelized"
        );
    }
}

/// A mesh whose placement maps `p` to grid `p + 0.5` exactly (bounding box
/// 0 ..= R - 1), with axis-aligned triangles on voxel faces, edges and corners.
fn boundary_mesh(depth: u8) -> ObjMesh {
    let r = (1u64 << depth) as f64;
    let mut m = ObjMesh::default();
    // Anchors the bounding box: a segment from corner to corner.
    m.add_triangle(
        [0.0, 0.0, 0.0],
        [r - 1.0, r - 1.0, r - 1.0],
        [0.0, 0.0, 0.0],
    );
    let g = |x: f64| x - 0.5; // grid coordinate -> mesh coordinate
    // On the plane z = 1 (a voxel face plane), spanning whole voxels.
    m.add_triangle(
        [g(1.0), g(1.0), g(1.0)],
        [g(r - 1.0), g(1.0), g(1.0)],
        [g(1.0), g(r - 2.0), g(1.0)],
    );
    // On x = 2, with edges along voxel edges and a vertex on a voxel corner.
    m.add_triangle(
        [g(2.0), g(1.0), g(1.0)],
        [g(2.0), g(3.0), g(1.0)],
        [g(2.0), g(1.0), g(r - 1.0)],
    );
    // On y = r/2, half-voxel offsets along z.
    m.add_triangle(
        [g(1.0), g(r / 2.0), g(1.5)],
        [g(r - 1.5), g(r / 2.0), g(1.5)],
        [g(1.0), g(r / 2.0), g(r - 1.5)],
    );
    // A diagonal triangle through voxel corners (x + y = const).
    m.add_triangle(
        [g(1.0), g(3.0), g(2.0)],
        [g(3.0), g(1.0), g(2.0)],
        [g(3.0), g(1.0), g(r - 1.0)],
    );
    m
}

#[test]
fn triangles_on_voxel_boundaries() {
    for depth in [3u8, 4, 5, 6] {
        let mesh = boundary_mesh(depth);
        check_mesh(&format!("boundaries{depth}"), &mesh, &[depth]);
        // The plane z = 1 sets the voxels on both sides (closed cubes).
        let dir = tempfile::tempdir().unwrap();
        let obj = dir.path().join("b.obj");
        mesh.write(&obj);
        let out = dir.path().join("b.vdag");
        convert(&obj, &out, depth, &[]);
        let bytes = std::fs::read(&out).unwrap();
        let dag = dagfmt::AnyDag::open(&bytes).unwrap();
        assert_eq!(dag.header().root_min, [-0.5; 3]);
        assert_eq!(dag.header().root_size, (1u64 << depth) as f64);
        assert!(
            dag.is_set(2, 2, 0).unwrap() && dag.is_set(2, 2, 1).unwrap(),
            "both sides of z = 1"
        );
    }
}

/// A tiny deterministic generator (no dependency needed for a fixed stream).
pub struct Lcg(pub u64);

impl Lcg {
    pub fn next_f64(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

#[test]
fn random_triangles() {
    // Triangles of every size and shape, including slivers and near-degenerate ones.
    let mut rng = Lcg(7);
    let mut m = ObjMesh::default();
    for i in 0..60 {
        let c = [
            rng.next_f64() * 10.0,
            rng.next_f64() * 10.0,
            rng.next_f64() * 10.0,
        ];
        let scale = [0.01, 0.3, 2.0, 8.0][i % 4];
        let mut p = [[0.0; 3]; 3];
        for v in &mut p {
            *v = [0, 1, 2].map(|k| c[k] + (rng.next_f64() - 0.5) * scale);
        }
        if i % 7 == 0 {
            // A sliver: the third vertex almost on the first edge.
            p[2] = [0, 1, 2].map(|k| 0.5 * (p[0][k] + p[1][k]) + 1e-6 * scale);
        }
        m.add_triangle(p[0], p[1], p[2]);
    }
    check_mesh("random", &m, &[3, 5, 6]);
}
