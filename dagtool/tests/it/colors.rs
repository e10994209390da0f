//! `--colors`: per-voxel material colours in dense (Morton) order.

use std::path::{Path, PathBuf};

use crate::common::{colour_bytes, convert, voxel_codes};
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
        let dag = dagfmt::AnyDag::open(&bytes).unwrap();
        let colors = colour_bytes(&dag).expect("a colour section");
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
    let dag = dagfmt::AnyDag::open(&bytes).unwrap();
    assert!(colour_bytes(&dag).unwrap().iter().all(|&b| b == 255));
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
    let dag = dagfmt::AnyDag::open(&bytes).unwrap();
    let colors = colour_bytes(&dag).unwrap();
    let green = colors.chunks(4).filter(|c| *c == [0, 255, 0, 255]).count();
    let white = colors.chunks(4).filter(|c| *c == [255; 4]).count();
    assert_eq!(green + white, colors.len() / 4);
    assert!(green > 0 && white > 0);
    // The centre voxel is interior (white).
    let i = dag.voxel_index(16, 16, 16).unwrap().expect("centre is set") as usize;
    assert_eq!(colors[4 * i..4 * i + 4], [255; 4]);
}

/// A 4 x 4 square (slightly folded along its diagonal) whose texture
/// coordinates map it into the middle of a 2 x 2 texture.
const TEXTURED_OBJ: &str = "\
mtllib t.mtl
v 0 0 0
v 4 0 0
v 0 4 0
v 4 4 0.5
vt 0.1 0.1
vt 0.9 0.1
vt 0.1 0.9
vt 0.9 0.9
usemtl checker
f 1/1 2/2 3/3
f 2/2 4/4 3/3
";

/// The 2 x 2 texture, rows from the top of the image.
const TEXELS: [[[u8; 4]; 2]; 2] = [
    [[255, 0, 0, 255], [0, 255, 0, 255]],
    [[0, 0, 255, 255], [255, 255, 255, 128]],
];

fn textured_square(dir: &Path, map_kd: &str) -> PathBuf {
    let mut image = image::RgbaImage::new(2, 2);
    for (y, row) in TEXELS.iter().enumerate() {
        for (x, texel) in row.iter().enumerate() {
            image.put_pixel(x as u32, y as u32, image::Rgba(*texel));
        }
    }
    textured_square_with(dir, map_kd, &image)
}

/// The square with `image` as `tex/checker.png`.
fn textured_square_with(dir: &Path, map_kd: &str, image: &image::RgbaImage) -> PathBuf {
    let obj = dir.join("t.obj");
    std::fs::write(&obj, TEXTURED_OBJ).unwrap();
    std::fs::write(
        dir.join("t.mtl"),
        format!("newmtl checker\nKd 1 0.5 1\nmap_Kd {map_kd}\n"),
    )
    .unwrap();
    std::fs::create_dir_all(dir.join("tex")).unwrap();
    image.save(dir.join("tex/checker.png")).unwrap();
    obj
}

/// The point of triangle `v` nearest to `p`, by brute force over a fine grid
/// of barycentric samples: its weights.
fn nearest_sample(p: [f64; 3], v: [[f64; 3]; 3]) -> [f64; 3] {
    const N: usize = 120;
    let mut best = (f64::INFINITY, [1.0, 0.0, 0.0]);
    for i in 0..=N {
        for j in 0..=N - i {
            let w = [
                i as f64 / N as f64,
                j as f64 / N as f64,
                (N - i - j) as f64 / N as f64,
            ];
            let q = [0, 1, 2].map(|a| w[0] * v[0][a] + w[1] * v[1][a] + w[2] * v[2][a]);
            let d: f64 = (0..3).map(|a| (q[a] - p[a]).powi(2)).sum();
            if d < best.0 {
                best = (d, w);
            }
        }
    }
    best.1
}

#[test]
fn textures_are_sampled_at_the_nearest_point_of_the_triangle() {
    let dir = tempfile::tempdir().unwrap();
    // Options before the file name, as exporters write them.
    let obj = textured_square(dir.path(), "-s 1 1 1 tex/checker.png");
    let refmesh = reference::load(&obj);
    let uv = [[0.1, 0.1], [0.9, 0.1], [0.1, 0.9], [0.9, 0.9]];
    let tint = [255u16, 128, 255, 255];
    for depth in [4u8, 5] {
        let out = dir.path().join(format!("t{depth}.vdag"));
        convert(&obj, &out, depth, &["--colors"]);
        let bytes = std::fs::read(&out).unwrap();
        let dag = dagfmt::AnyDag::open(&bytes).unwrap();
        let colors = colour_bytes(&dag).expect("a colour section");
        let (root_min, size) = reference::root_cube(&refmesh, depth);
        let voxel = size / f64::from(1u32 << depth);
        let expected = reference::surface(&reference::snapped(&refmesh, depth), depth);
        assert_eq!(
            voxel_codes(&out),
            expected.keys().copied().collect::<Vec<_>>()
        );
        let (mut checked, mut seen) = (0, std::collections::BTreeSet::new());
        for (i, (&code, &tri)) in expected.iter().enumerate() {
            let cell = dagfmt::morton::decode(code);
            let centre = [0, 1, 2].map(|a| root_min[a] + (f64::from(cell[a]) + 0.5) * voxel);
            let corners = refmesh.triangles[tri];
            let w = nearest_sample(centre, corners.map(|k| refmesh.vertices[k]));
            let tex = [0, 1].map(|a| (0..3).map(|k| w[k] * uv[corners[k]][a]).sum::<f64>());
            // The brute-force point is a grid sample: skip voxels whose point
            // lies next to a texel boundary.
            if (tex[0] - 0.5).abs() < 0.02 || (tex[1] - 0.5).abs() < 0.02 {
                continue;
            }
            let texel = TEXELS[usize::from(tex[1] < 0.5)][usize::from(tex[0] >= 0.5)];
            let want = [0, 1, 2, 3].map(|c| ((u16::from(texel[c]) * tint[c] + 127) / 255) as u8);
            assert_eq!(
                colors[4 * i..4 * i + 4],
                want,
                "voxel {cell:?} (triangle {tri})"
            );
            checked += 1;
            seen.insert(want);
        }
        assert!(
            checked * 10 > expected.len() * 8,
            "{checked} of {}",
            expected.len()
        );
        assert_eq!(seen.len(), 4, "every texel shows");
    }
}

#[test]
fn voxels_larger_than_texels_take_their_mean() {
    // A one-texel black and white checker of 64 x 64 over the square: at
    // depth 4 a voxel spans about 3.4 texels, so it reads the mip level of
    // 4 x 4 texel means, an even grey; at depth 8 (0.2 texels) the texels.
    let image = image::RgbaImage::from_fn(64, 64, |x, y| {
        image::Rgba(if (x + y) % 2 == 0 {
            [0, 0, 0, 255]
        } else {
            [255; 4]
        })
    });
    let dir = tempfile::tempdir().unwrap();
    let obj = textured_square_with(dir.path(), "tex/checker.png", &image);
    let tinted = |v: u16| [v, v * 128 / 255, v, 255].map(|c| c as u8);
    let grey = [128, 64, 128, 255];
    for (depth, allowed) in [(4u8, vec![grey]), (8, vec![tinted(0), tinted(255)])] {
        let out = dir.path().join(format!("g{depth}.vdag"));
        convert(&obj, &out, depth, &["--colors"]);
        let bytes = std::fs::read(&out).unwrap();
        let dag = dagfmt::AnyDag::open(&bytes).unwrap();
        let colors = colour_bytes(&dag).unwrap();
        let mut seen = std::collections::BTreeSet::new();
        for c in colors.chunks(4) {
            assert!(allowed.iter().any(|a| a == c), "depth {depth}: {c:?}");
            seen.insert(c);
        }
        assert_eq!(seen.len(), allowed.len(), "depth {depth}");
    }
}

#[test]
fn unreadable_texture_falls_back_to_kd_with_a_warning() {
    // A missing file, a folder, and bytes that are no image.
    for (k, (map_kd, why)) in [
        ("tex/missing.png", "missing.png"),
        ("tex", "not a regular file"),
        ("t.mtl", "image format"),
    ]
    .into_iter()
    .enumerate()
    {
        let dir = tempfile::tempdir().unwrap();
        let obj = textured_square(dir.path(), map_kd);
        let out = dir.path().join(format!("m{k}.vdag"));
        let o = crate::common::run_ok(&[
            "convert",
            obj.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--depth",
            "4",
            "--colors",
        ]);
        let text =
            String::from_utf8_lossy(&o.stdout).into_owned() + &String::from_utf8_lossy(&o.stderr);
        let warnings: Vec<&str> = text.lines().filter(|l| l.contains("warning:")).collect();
        assert!(
            warnings.len() == 1 && warnings[0].contains(why) && warnings[0].contains("Kd"),
            "{map_kd}: {text}"
        );
        let bytes = std::fs::read(&out).unwrap();
        let dag = dagfmt::AnyDag::open(&bytes).unwrap();
        assert!(
            colour_bytes(&dag)
                .unwrap()
                .chunks(4)
                .all(|c| c == [255, 128, 255, 255])
        );
    }
}
