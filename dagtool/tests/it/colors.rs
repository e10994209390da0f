//! `--colors`: per-voxel material colours in dense (Morton) order.

use crate::common::{convert, voxel_codes};
use crate::reference;

const OBJ: &str = "\
mtllib two.mtl
v 0 0 0
v 4 0 0.2
v 0 4 0.4
v 4 4 0.1
v 1 1 -0.3
v 3 2 1.8
usemtl red
f 1 2 3
usemtl blue
f 2 4 3
f 5 6 4
o loose
f 1 5 6
";

const MTL: &str = "\
newmtl red
Kd 1 0 0
newmtl blue
Kd 0 0 1
d 0.5
";

#[test]
fn first_triangle_colour_wins() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("two.obj");
    std::fs::write(&obj, OBJ).unwrap();
    std::fs::write(dir.path().join("two.mtl"), MTL).unwrap();
    let refmesh = reference::load(&obj);
    assert_eq!(refmesh.colors.len(), 2);
    for depth in [3u8, 5, 6] {
        let out = dir.path().join(format!("c{depth}.vdag"));
        convert(&obj, &out, depth, &["--colors"]);
        let bytes = std::fs::read(&out).unwrap();
        let dag = dagfmt::Dag::open(&bytes).unwrap();
        let colors = dag.colors().expect("a colour section");
        let expected = reference::surface(&reference::snapped(&refmesh, depth), depth);
        let codes = voxel_codes(&out);
        assert_eq!(colors.len(), 4 * codes.len());
        assert_eq!(codes, expected.keys().copied().collect::<Vec<_>>());
        for (i, (_, &tri)) in expected.iter().enumerate() {
            let want = match refmesh.materials[tri] {
                Some(m) => refmesh.colors[m],
                None => [255; 4],
            };
            assert_eq!(colors[4 * i..4 * i + 4], want, "voxel {i} (triangle {tri})");
        }
        // Both materials and the material-less object occur.
        let distinct: std::collections::BTreeSet<&[u8]> = colors.chunks(4).collect();
        assert!(
            distinct.contains(&[255u8, 0, 0, 255][..])
                && distinct.contains(&[0u8, 0, 255, 128][..])
        );
        assert!(dagfmt::validate::validate(&bytes).is_empty());
    }
}

#[test]
fn missing_material_library_is_white() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("two.obj");
    std::fs::write(&obj, OBJ).unwrap();
    let out = dir.path().join("w.vdag");
    convert(&obj, &out, 4, &["--colors"]);
    let bytes = std::fs::read(&out).unwrap();
    let dag = dagfmt::Dag::open(&bytes).unwrap();
    assert!(dag.colors().unwrap().iter().all(|&b| b == 255));
}

#[test]
fn solid_interior_is_white() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("cube.obj");
    let mut text = String::from("mtllib c.mtl\nusemtl g\n");
    text.push_str(&crate::common::box_mesh([0.0; 3], [1.0; 3]).to_obj());
    std::fs::write(&obj, text).unwrap();
    std::fs::write(dir.path().join("c.mtl"), "newmtl g\nKd 0 1 0\n").unwrap();
    let out = dir.path().join("s.vdag");
    convert(&obj, &out, 5, &["--colors", "--solid"]);
    let bytes = std::fs::read(&out).unwrap();
    let dag = dagfmt::Dag::open(&bytes).unwrap();
    let colors = dag.colors().unwrap();
    let green = colors.chunks(4).filter(|c| *c == [0, 255, 0, 255]).count();
    let white = colors.chunks(4).filter(|c| *c == [255; 4]).count();
    assert_eq!(green + white, colors.len() / 4);
    assert!(green > 0 && white > 0);
    // The centre voxel is interior (white).
    let i = dag.voxel_index(16, 16, 16).unwrap().expect("centre is set") as usize;
    assert_eq!(colors[4 * i..4 * i + 4], [255; 4]);
}
