//! `--solid`: the interior of closed meshes equals the brute-force inside
//! test; open meshes follow the documented majority rule.

use crate::common::{
    ObjMesh, assert_same_voxels, box_mesh, convert, run_ok, sphere_mesh, voxel_codes,
};
use crate::reference;

fn check_solid(name: &str, mesh: &ObjMesh, depths: &[u8]) {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join(format!("{name}.obj"));
    mesh.write(&obj);
    let refmesh = reference::load(&obj);
    for &depth in depths {
        let out = dir.path().join(format!("{name}-{depth}.vdag"));
        convert(&obj, &out, depth, &["--solid"]);
        let got = voxel_codes(&out);
        let expected = reference::solid_codes(
            &reference::snapped(&refmesh, depth),
            &reference::in_voxels(&refmesh, depth),
            depth,
        );
        assert_same_voxels(&got, &expected, &format!("solid {name} at depth {depth}"));
        let surface = reference::surface_codes(&reference::snapped(&refmesh, depth), depth);
        if depth >= 4 {
            assert!(
                got.len() > surface.len(),
                "{name}: the interior adds voxels"
            );
        }
    }
}

#[test]
fn closed_cube() {
    check_solid(
        "cube",
        &box_mesh([0.1, 0.2, 0.3], [2.9, 2.2, 1.7]),
        &[3, 4, 5, 6],
    );
}

#[test]
fn closed_sphere() {
    check_solid("sphere", &sphere_mesh([0.0, 0.0, 0.0], 1.0, 2), &[4, 5, 6]);
}

#[test]
fn hollow_shell() {
    // An outer box and an inner box facing inwards: the cavity stays empty.
    let mut m = box_mesh([0.0, 0.0, 0.0], [4.0, 3.5, 3.0]);
    let mut inner = box_mesh([1.1, 1.2, 0.9], [2.9, 2.3, 2.1]);
    for f in &mut inner.faces {
        f.reverse();
    }
    m.append(&inner);
    check_solid("shell", &m, &[4, 5, 6]);
}

#[test]
fn closed_mesh_is_reported_closed() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("cube.obj");
    box_mesh([0.0; 3], [1.0, 2.0, 3.0]).write(&obj);
    let out = dir.path().join("cube.vdag");
    let o = run_ok(&[
        "convert",
        obj.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--depth",
        "5",
        "--solid",
    ]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.contains("closed mesh, crossing parity along z"),
        "{text}"
    );
}

#[test]
fn open_box_uses_the_majority_rule() {
    // A box without its top face is not closed. Inside it, the parities along
    // x, y and z all say inside; above it only z does (one vote of three), so
    // the result equals the closed box's solid.
    let dir = tempfile::tempdir().unwrap();
    let closed = box_mesh([0.13, 0.07, 0.21], [3.1, 2.6, 2.2]);
    let mut open = closed.clone();
    // Face 1 is the +z face.
    open.faces.remove(1);
    // Keep the bounding box identical: the +z face's vertices are still used by the sides.
    let (a, b) = (dir.path().join("closed.obj"), dir.path().join("open.obj"));
    closed.write(&a);
    open.write(&b);
    for depth in [4u8, 5, 6] {
        let (va, vb) = (
            dir.path().join(format!("c{depth}.vdag")),
            dir.path().join(format!("o{depth}.vdag")),
        );
        convert(&a, &va, depth, &["--solid"]);
        let o = run_ok(&[
            "convert",
            b.to_str().unwrap(),
            "-o",
            vb.to_str().unwrap(),
            "--depth",
            &depth.to_string(),
            "--solid",
        ]);
        let text = String::from_utf8_lossy(&o.stdout);
        assert!(
            text.contains("not closed") && text.contains("majority"),
            "{text}"
        );
        // The open box lacks the top face's surface voxels that the sides do not cover.
        let refmesh = reference::load(&b);
        let surface = reference::surface_codes(&reference::snapped(&refmesh, depth), depth);
        let closed_solid = voxel_codes(&va);
        let open_solid = voxel_codes(&vb);
        let top_only: Vec<u64> = closed_solid
            .iter()
            .copied()
            .filter(|c| !open_solid.contains(c))
            .collect();
        // Every voxel of the closed solid that the open one lacks lies on the
        // missing top face (its centre is above the box top or on the surface).
        for c in &top_only {
            let [_, _, z] = dagfmt::morton::decode(*c);
            assert!(!surface.contains(c));
            let (min, size) = reference::root_cube(&refmesh, depth);
            let top = (2.2 - min[2]) * (1u64 << depth) as f64 / size;
            assert!(
                (z as f64 + 0.5) >= top - 1.0,
                "voxel {:?} missing well below the open top",
                dagfmt::morton::decode(*c)
            );
        }
        assert!(
            open_solid.iter().all(|c| closed_solid.contains(c)),
            "the open box fills nothing outside the closed one"
        );
        assert!(open_solid.len() as f64 > 0.8 * closed_solid.len() as f64);
    }
}

#[test]
fn columns_through_vertices_and_edges() {
    // With the bounding box anchored at 0 ..= R - 1, mesh coordinate p maps to
    // grid p + 1/2: integer vertices sit exactly on voxel centres, so columns
    // pass through vertices and along edges, and faces pass through centres.
    for depth in [3u8, 4, 5, 6] {
        let r = (1u64 << depth) as f64;
        let c = (r / 2.0).floor();
        let mut m = ObjMesh::default();
        // Anchors (a degenerate triangle: its edge is used twice, so the mesh stays closed).
        m.add_triangle([0.0; 3], [r - 1.0; 3], [0.0; 3]);
        let base = [
            [1.0, 1.0, 1.0],
            [r - 2.0, 1.0, 1.0],
            [r - 2.0, r - 2.0, 1.0],
            [1.0, r - 2.0, 1.0],
        ];
        let ids: Vec<usize> = base.iter().map(|&p| m.add_vertex(p)).collect();
        let apex = m.add_vertex([c, c, r - 2.0]);
        let bottom = m.add_vertex([c, c - 1.0, 0.0]);
        for i in 0..4 {
            m.faces.push(vec![ids[i], ids[(i + 1) % 4], apex]);
            m.faces.push(vec![ids[(i + 1) % 4], ids[i], bottom]);
        }
        check_solid(&format!("pyramid{depth}"), &m, &[depth]);
    }
}

#[test]
fn columns_along_a_shared_ridge() {
    // A house roof whose ridge runs exactly along a row of voxel centres: the
    // two slopes meet there from opposite sides, and the tie rule must count
    // the ridge once.
    for depth in [3u8, 4, 5, 6] {
        let r = (1u64 << depth) as f64;
        let c = (r / 2.0).floor();
        let mut m = ObjMesh::default();
        m.add_triangle([0.0; 3], [r - 1.0; 3], [0.0; 3]);
        let b: Vec<usize> = [
            [1.0, 1.0, 1.0],
            [r - 2.0, 1.0, 1.0],
            [r - 2.0, r - 2.0, 1.0],
            [1.0, r - 2.0, 1.0],
        ]
        .iter()
        .map(|&p| m.add_vertex(p))
        .collect();
        let r0 = m.add_vertex([2.0, c, r - 2.0]);
        let r1 = m.add_vertex([r - 3.0, c, r - 2.0]);
        m.faces.push(vec![b[0], b[1], r1, r0]);
        m.faces.push(vec![b[2], b[3], r0, r1]);
        m.faces.push(vec![b[1], b[2], r1]);
        m.faces.push(vec![b[3], b[0], r0]);
        m.faces.push(vec![b[0], b[3], b[2], b[1]]);
        check_solid(&format!("roof{depth}"), &m, &[depth]);
    }
}
