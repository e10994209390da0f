//! Fuzzing harnesses for the importers: one function per fuzz target of
//! `fuzz/` (its own cargo workspace, run with `cargo fuzz`), kept in the
//! library so that the test suite runs the same checks over the committed
//! regression inputs and random inputs (`tests/it/fuzz_smoke.rs`).
//!
//! - [`obj_import`]: an OBJ held in memory loads or fails cleanly, and a mesh
//!   that passes [`Mesh::check`] can be placed in the root cube, snapped and
//!   tested for closedness without a panic, and textured colours of its
//!   triangles are texels;
//! - [`voxel_list`]: a voxel list held in memory (text or binary) loads or
//!   fails cleanly, and what loads is sorted, inside its volume, and comes
//!   back unchanged through the binary form.
//!
//! - [`gltf_import`], [`ply_import`], [`stl_import`], [`las_import`],
//!   [`vox_import`], [`binvox_import`]: each input format's reader on bytes
//!   held in memory (no file access) loads or fails cleanly, and what loads
//!   is consistent: meshes pass on to the checks of [`obj_import`], point
//!   clouds have finite points, voxel grids lie inside their depth.
//!
//! - [`part_placement`]: the PART_PLACEMENT section of a part (spec § 24)
//!   on any bytes: read or refused cleanly; on a valid file the part rules
//!   are checked without a panic, and an accepted placement is the
//!   section's bytes.
//!
//! Not part of the stable API.

use crate::input::{Input, PointSource, VoxelGrid};
use crate::mesh::{GridMapping, Mesh, SnappedMesh, Texture};
use crate::voxlist;

/// The depth the [`obj_import`] harness places meshes at.
pub const OBJ_DEPTH: u8 = 6;

/// The OBJ import harness.
pub fn obj_import(bytes: &[u8]) {
    let Ok(mesh) = crate::input::obj::load_bytes(bytes, "fuzz.obj") else {
        return;
    };
    check_mesh(mesh);
}

/// The glTF import harness (`.gltf` JSON or `.glb`; external files refused).
pub fn gltf_import(bytes: &[u8]) {
    if let Ok(mesh) = crate::input::gltf::load_bytes(bytes, "fuzz.glb", None, true) {
        check_mesh(mesh);
    }
}

/// The PLY import harness: meshes and point clouds.
pub fn ply_import(bytes: &[u8]) {
    match crate::input::ply::load_bytes(bytes, "fuzz.ply") {
        Ok(Input::Mesh(mesh)) => check_mesh(*mesh),
        Ok(Input::Points(points)) => check_points(points),
        Ok(Input::Voxels(_)) => panic!("PLY gives no voxel grid"),
        Err(_) => {}
    }
}

/// The STL import harness.
pub fn stl_import(bytes: &[u8]) {
    if let Ok(mesh) = crate::input::stl::load_bytes(bytes.to_vec(), "fuzz.stl") {
        check_mesh(mesh);
    }
}

/// The LAS/LAZ import harness.
pub fn las_import(bytes: &[u8]) {
    if let Ok(points) = crate::input::las::load_bytes(bytes, "fuzz.las") {
        check_points(points);
    }
}

/// The MagicaVoxel import harness.
pub fn vox_import(bytes: &[u8]) {
    if let Ok(grid) = crate::input::vox::load_bytes(bytes, "fuzz.vox") {
        check_grid(&grid);
    }
}

/// The binvox import harness.
pub fn binvox_import(bytes: &[u8]) {
    if let Ok(grid) = crate::input::binvox::load_bytes(bytes, "fuzz.binvox") {
        check_grid(&grid);
    }
}

/// A point cloud's points are all readable and finite, as many as declared.
fn check_points(mut points: Box<dyn PointSource>) {
    let mut all = Vec::new();
    loop {
        match points.read(&mut all, 1024) {
            Ok(0) => break,
            Ok(_) => {}
            Err(_) => return,
        }
    }
    assert_eq!(all.len() as u64, points.count());
    assert!(all.iter().all(|p| p.position.iter().all(|c| c.is_finite())));
}

/// A voxel grid lies inside its depth and has a usable placement.
fn check_grid(grid: &VoxelGrid) {
    assert!(!grid.voxels.is_empty());
    assert!((dagfmt::layout::MIN_DEPTH..=dagfmt::layout::MAX_DEPTH).contains(&grid.depth));
    let n = 1u64 << grid.depth;
    assert!(grid.voxels.iter().flatten().all(|&c| u64::from(c) < n));
    assert!(grid.colors.is_empty() || grid.colors.len() == grid.voxels.len());
    assert!(grid.voxel_size > 0.0 && grid.voxel_size.is_finite());
}

/// The checks of a loaded mesh (every importer's).
fn check_mesh(mesh: Mesh) {
    assert_eq!(mesh.triangles.len(), mesh.triangle_material.len());
    for t in 0..mesh.triangles.len() {
        let _ = mesh.triangle_color(t);
    }
    assert!(mesh.vertex_colors.is_empty() || mesh.vertex_colors.len() == mesh.vertices.len());
    let Ok(check) = mesh.check() else { return };
    assert!(
        mesh.triangles
            .iter()
            .flatten()
            .all(|&i| (i as usize) < mesh.vertices.len()),
        "a checked mesh uses a vertex it does not have"
    );
    assert!((0..3).all(|a| check.min[a] <= check.max[a]));
    assert!(check.degenerate < mesh.triangles.len() as u64);
    let Ok(mapping) = GridMapping::fit(check.min, check.max, OBJ_DEPTH) else {
        return;
    };
    let units = 1i64 << (u32::from(OBJ_DEPTH) + crate::geom::SUBVOXEL_BITS);
    let snapped = SnappedMesh::new(&mesh, &mapping);
    assert!(
        snapped
            .vertices
            .iter()
            .flatten()
            .all(|&c| (0..=units).contains(&c)),
        "a snapped vertex lies outside the lattice"
    );
    for t in 0..snapped.triangles.len() {
        let _ = snapped.triangle(t as u32);
    }
    let _ = snapped.is_closed();
    if !mesh.vertex_colors.is_empty() {
        for (t, tri) in mesh.triangles.iter().enumerate() {
            let p = mesh.vertices[tri[0] as usize];
            let _ = mesh.voxel_color(t, p, 1.0);
        }
    }
    textured_colors(mesh);
}

/// Gives every triangle of a checked mesh a 2 x 2 texture, with texture
/// coordinates taken from the vertices' x and y, and checks that the colour of
/// a voxel at each triangle's centroid and at a point off it, tiny or huge, is
/// one of the texels or their mean (the tint is white).
fn textured_colors(mut mesh: Mesh) {
    let texels: Vec<u8> = (0..16).map(|i| i * 16).collect();
    // The 1 x 1 mip level: per channel, the rounded mean of the four.
    let mean: [u8; 4] = [0, 1, 2, 3]
        .map(|c| (((0..4).map(|k| u32::from(texels[4 * k + c])).sum::<u32>() + 2) / 4) as u8);
    let Some(texture) = Texture::from_rgba(2, 2, texels.clone()) else {
        unreachable!("a 2 x 2 texture has 16 bytes");
    };
    mesh.vertex_colors.clear();
    mesh.colors = vec![[255; 4]];
    mesh.textures = vec![Some(texture)];
    mesh.triangle_material = vec![0; mesh.triangles.len()];
    mesh.texcoords = mesh.vertices.iter().map(|v| [v[0], v[1]]).collect();
    mesh.triangle_texcoords = mesh.triangles.clone();
    assert!(mesh.has_textures());
    for (t, tri) in mesh.triangles.iter().enumerate() {
        let v = tri.map(|i| mesh.vertices[i as usize]);
        let centroid = [0, 1, 2].map(|a| (v[0][a] + v[1][a] + v[2][a]) / 3.0);
        let off = [0, 1, 2].map(|a| v[0][a] * 1.5 - v[1][a] * 0.5 + 1.0);
        for (p, voxel) in [(centroid, 0.0), (off, 1e-3), (centroid, 1e9)] {
            let c = mesh.voxel_color(t, p, voxel);
            assert!(
                texels.chunks(4).any(|texel| texel == c) || c == mean,
                "colour {c:?} is no texel"
            );
        }
    }
}

/// The voxel list harness: reads `bytes` with no depth given and with the
/// depth 4 given, and checks what loads.
pub fn voxel_list(bytes: &[u8]) {
    for depth in [None, Some(4)] {
        let Ok(list) = voxlist::read_bytes(bytes, "fuzz.voxels", depth) else {
            continue;
        };
        if let Some(d) = depth {
            assert_eq!(list.depth, d);
        }
        // An empty list is valid: it converts to the empty volume.
        assert!(list.records >= list.codes.len() as u64);
        assert!(
            list.codes.windows(2).all(|w| w[0] < w[1]),
            "codes are not strictly increasing"
        );
        let resolution = 1u64 << list.depth;
        let voxels: Vec<[u32; 3]> = list
            .codes
            .iter()
            .map(|&c| dagfmt::morton::decode(c))
            .collect();
        assert!(
            voxels.iter().flatten().all(|&c| u64::from(c) < resolution),
            "a voxel lies outside the {resolution}^3 volume"
        );
        let mut binary = Vec::new();
        voxlist::write_binary(&mut binary, list.depth, &voxels).expect("writing to memory");
        let again = voxlist::read_bytes(&binary, "again", Some(list.depth))
            .expect("reading a written binary list");
        assert_eq!(again.codes, list.codes);
        assert_eq!(again.records, list.codes.len() as u64);
    }
}

/// The part placement harness.
pub fn part_placement(bytes: &[u8]) {
    let Ok(dag) = dagfmt::Dag::open(bytes) else {
        return;
    };
    let read = crate::region::read_placement(&dag);
    if !dagfmt::validate::validate(bytes).is_empty() {
        return;
    }
    let checked = crate::region::check_part(&dag);
    if let Ok(Some(p)) = checked {
        assert_eq!(read, Ok(Some(p.clone())));
        let s = dag
            .sections()
            .iter()
            .find(|s| s.kind.to_raw() == crate::region::PART_PLACEMENT_KIND)
            .expect("the placement's section");
        assert_eq!(
            &bytes[s.offset as usize..s.offset as usize + crate::region::PLACEMENT_LEN],
            &p.to_bytes()[..]
        );
        assert!(p.cells.start < p.cells.end && p.level + 2 <= dag.header().depth);
    }
}
