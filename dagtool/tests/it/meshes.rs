//! Real meshes from ../shared/meshes (skipped with a message when absent).

use std::path::Path;

use crate::common::{assert_same_voxels, convert, meshes_dir, run, voxel_codes};
use crate::reference;
use crate::surface::Lcg;

fn check_against_reference(obj: &Path, depth: u8) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.vdag");
    convert(obj, &out, depth, &[]);
    let got = voxel_codes(&out);
    let refmesh = reference::load(obj);
    let expected = reference::surface_codes(&reference::snapped(&refmesh, depth), depth);
    let name = obj.file_name().unwrap().to_string_lossy();
    assert_same_voxels(&got, &expected, &format!("{name} at depth {depth}"));
    reference::check_against_f64(
        &got,
        &reference::in_voxels(&refmesh, depth),
        depth,
        1e-3,
        &name,
    );
}

#[test]
fn small_real_meshes_equal_the_reference() {
    let Some(dir) = meshes_dir() else { return };
    for (name, depths) in [
        ("teapot.obj", &[4u8, 6, 7][..]),
        ("suzanne.obj", &[5, 7]),
        ("cow.obj", &[5, 7]),
        ("spot.obj", &[6]),
        ("armadillo.obj", &[6]),
        ("bunny.obj", &[5]),
        ("sponza.obj", &[6]),
    ] {
        for &d in depths {
            check_against_reference(&dir.join(name), d);
        }
    }
}

/// Every point of every triangle lies in a set voxel: sample points on each
/// triangle of the original mesh (vertices, edge midpoints, random interior
/// points) and look their voxels up.
fn check_no_holes(obj: &Path, depth: u8, samples_per_triangle: usize) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.vdag");
    convert(obj, &out, depth, &[]);
    let bytes = std::fs::read(&out).unwrap();
    let dag = dagfmt::AnyDag::open(&bytes).unwrap();
    let refmesh = reference::load(obj);
    let tris = reference::in_voxels(&refmesh, depth);
    let mut rng = Lcg(3);
    let res = 1u32 << depth;
    let mut checked = 0u64;
    for t in &tris {
        let mut points: Vec<[f64; 3]> = t.to_vec();
        for i in 0..3 {
            points.push([0, 1, 2].map(|k| 0.5 * (t[i][k] + t[(i + 1) % 3][k])));
        }
        for _ in 0..samples_per_triangle {
            let (mut a, mut b) = (rng.next_f64(), rng.next_f64());
            if a + b > 1.0 {
                (a, b) = (1.0 - a, 1.0 - b);
            }
            points.push(
                [0, 1, 2].map(|k| t[0][k] + a * (t[1][k] - t[0][k]) + b * (t[2][k] - t[0][k])),
            );
        }
        for p in points {
            // Snapping moves vertices by at most 2^-17 voxel: any voxel within
            // 1e-4 of the point may hold it.
            let lo = p.map(|c| ((c - 1e-4).floor().max(0.0) as u32).min(res - 1));
            let hi = p.map(|c| ((c + 1e-4).floor().max(0.0) as u32).min(res - 1));
            let mut found = false;
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        found |= dag.is_set(x, y, z).unwrap();
                    }
                }
            }
            assert!(
                found,
                "{}: surface point {p:?} at depth {depth} is in no set voxel",
                obj.display()
            );
            checked += 1;
        }
    }
    assert!(checked > 0);
}

#[test]
fn thin_walls_have_no_holes() {
    let Some(dir) = meshes_dir() else { return };
    check_no_holes(&dir.join("sponza.obj"), 8, 4);
    check_no_holes(&dir.join("sponza.obj"), 10, 4);
    check_no_holes(&dir.join("teapot.obj"), 9, 20);
}

#[test]
fn zero_area_triangles_of_the_dragon() {
    let Some(dir) = meshes_dir() else { return };
    // dragon.obj has 108 zero-area triangles: they convert without trouble
    // and the summary counts them.
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("dragon.vdag");
    let o = run(&[
        "convert",
        dir.join("dragon.obj").to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--depth",
        "8",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("871414 triangles (108 degenerate)"), "{text}");
    assert!(dagfmt::validate::validate(&std::fs::read(&out).unwrap()).is_empty());
}

/// Converts every shared mesh at each depth and has `dagtool validate` accept it.
fn sweep(depths: std::ops::RangeInclusive<u8>) {
    let Some(dir) = meshes_dir() else { return };
    let mut names: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "obj"))
        .collect();
    names.sort();
    assert!(!names.is_empty());
    let tmp = tempfile::tempdir().unwrap();
    for obj in &names {
        for depth in depths.clone() {
            let out = tmp.path().join(format!(
                "{}-{depth}.vdag",
                obj.file_stem().unwrap().to_string_lossy()
            ));
            convert(obj, &out, depth, &[]);
            let o = run(&["validate", out.to_str().unwrap()]);
            assert_eq!(
                o.status.code(),
                Some(0),
                "{} at depth {depth}: {}",
                obj.display(),
                String::from_utf8_lossy(&o.stdout)
            );
            std::fs::remove_file(&out).unwrap();
        }
    }
}

#[test]
fn every_mesh_converts_to_valid_files_at_depths_8_to_10() {
    sweep(8..=10);
}

#[test]
#[ignore = "slow: the full sweep of every mesh at depths 8 to 14 (run with --release --ignored)"]
fn every_mesh_converts_to_valid_files_at_depths_8_to_14() {
    sweep(8..=14);
}
