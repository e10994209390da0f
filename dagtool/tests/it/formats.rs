//! The input formats other than OBJ (`dagtool::input`): every file of
//! `../shared/formats` (written by third-party libraries) converts, validates
//! and verifies; the same mesh gives the same voxels whatever its format;
//! colours come from glTF materials and textures, PLY vertex colours and
//! `.vox` palettes; point clouds set exactly the voxels of their points.

use std::path::{Path, PathBuf};

use crate::common::{convert, meshes_dir, run, run_ok, voxel_codes};

/// The folder of shared files in other formats, or `None` (with a message).
pub fn formats_dir() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/formats");
    if dir.is_dir() {
        Some(dir)
    } else {
        eprintln!(
            "skipping: shared formats not found at {} (these tests need ../shared/formats)",
            dir.display()
        );
        None
    }
}

/// The colours of a `.vdag` file (RGBA8 per voxel, Morton order).
fn colours(path: &Path) -> Vec<[u8; 4]> {
    let bytes = std::fs::read(path).unwrap();
    let dag = dagfmt::AnyDag::open(&bytes).unwrap();
    crate::common::colour_bytes(&dag)
        .expect("a colour section")
        .chunks_exact(4)
        .map(|c| [c[0], c[1], c[2], c[3]])
        .collect()
}

fn header(path: &Path) -> dagfmt::reader::Header {
    let bytes = std::fs::read(path).unwrap();
    dagfmt::AnyDag::open(&bytes).unwrap().header().clone()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Every file converts and validates; meshes pass `verify`'s ray casts and
/// point clouds its exact point checks.
#[test]
fn every_shared_file_converts_validates_and_verifies() {
    let Some(formats) = formats_dir() else { return };
    let dir = tempfile::tempdir().unwrap();
    let mut seen = 0;
    for name in crate::common::dir_entries(&formats) {
        let kind = match name.rsplit('.').next().unwrap() {
            "glb" | "gltf" | "stl" | "obj" => "mesh",
            "ply" if name.contains("points") => "points",
            "ply" => "mesh",
            "las" | "laz" => "points",
            "vox" | "binvox" => "grid",
            _ => continue,
        };
        seen += 1;
        let input = formats.join(&name);
        let out = dir.path().join(format!("{name}.vdag"));
        convert(&input, &out, 8, &["--colors"]);
        run_ok(&["validate", s(&out)]);
        // Point clouds are verified in
        // `point_clouds_set_exactly_their_points_voxels`.
        if kind == "mesh" {
            run_ok(&["verify", s(&input), s(&out), "--rays", "20000"]);
        }
    }
    assert_eq!(seen, 12, "every file of the README is tried");
}

/// Converts `a` and `b` at `depth` and asserts they give the same file.
fn same_file(a: &Path, b: &Path, depth: u8, extra: &[&str]) {
    let dir = tempfile::tempdir().unwrap();
    let (oa, ob) = (dir.path().join("a.vdag"), dir.path().join("b.vdag"));
    convert(a, &oa, depth, extra);
    convert(b, &ob, depth, extra);
    crate::common::assert_same_voxels(
        &voxel_codes(&ob),
        &voxel_codes(&oa),
        &format!("{} vs {} at depth {depth}", b.display(), a.display()),
    );
    // Same vertices (float32 in every file), same placement: the same bytes.
    assert_eq!(
        std::fs::read(&oa).unwrap(),
        std::fs::read(&ob).unwrap(),
        "{} vs {}",
        a.display(),
        b.display()
    );
}

#[test]
fn ply_and_stl_meshes_give_the_voxels_of_their_obj() {
    let (Some(formats), Some(meshes)) = (formats_dir(), meshes_dir()) else {
        return;
    };
    for depth in 8..=12 {
        same_file(
            &meshes.join("bunny.obj"),
            &formats.join("bunny.ply"),
            depth,
            &[],
        );
    }
    same_file(
        &meshes.join("teapot.obj"),
        &formats.join("teapot.stl"),
        10,
        &[],
    );
    same_file(
        &meshes.join("cow.obj"),
        &formats.join("cow_ascii.ply"),
        10,
        &[],
    );
    same_file(
        &meshes.join("armadillo.obj"),
        &formats.join("armadillo_ascii.stl"),
        9,
        &[],
    );
}

/// The glTF node's matrix (column-major), as its JSON states it.
fn node_matrix(gltf: &Path) -> [f64; 16] {
    let json: serde_json::Value = serde_json::from_slice(&std::fs::read(gltf).unwrap()).unwrap();
    let m: Vec<f64> = json["nodes"][0]["matrix"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    m.try_into().unwrap()
}

#[test]
fn gltf_node_transform_is_applied() {
    let (Some(formats), Some(meshes)) = (formats_dir(), meshes_dir()) else {
        return;
    };
    let gltf = formats.join("dragon_res2_rotated.gltf");
    let m = node_matrix(&gltf);
    // The README's transform: scale 2, 0.7 rad about +y.
    let (sin, cos) = 0.7f64.sin_cos();
    let expected = [
        2.0 * cos,
        0.0,
        -2.0 * sin,
        0.0,
        0.0,
        2.0,
        0.0,
        0.0,
        2.0 * sin,
        0.0,
        2.0 * cos,
        0.0,
        0.0,
        0.0,
        0.0,
        1.0,
    ];
    for (a, b) in m.iter().zip(expected) {
        assert!((a - b).abs() < 1e-9, "{m:?}");
    }
    // The OBJ with the transform applied, written with every digit.
    let dir = tempfile::tempdir().unwrap();
    let obj = std::fs::read_to_string(meshes.join("dragon_res2.obj")).unwrap();
    let mut moved = String::new();
    for line in obj.lines() {
        if let Some(rest) = line.strip_prefix("v ") {
            let p: Vec<f64> = rest
                .split_whitespace()
                .map(|w| f64::from(w.parse::<f32>().unwrap()))
                .collect();
            let q = [0, 1, 2].map(|r| m[r] * p[0] + m[4 + r] * p[1] + m[8 + r] * p[2] + m[12 + r]);
            moved.push_str(&format!("v {} {} {}\n", q[0], q[1], q[2]));
        } else if line.starts_with("f ") {
            moved.push_str(line);
            moved.push('\n');
        }
    }
    let moved_obj = dir.path().join("moved.obj");
    std::fs::write(&moved_obj, moved).unwrap();
    for depth in [8, 10] {
        let (a, b) = (dir.path().join("a.vdag"), dir.path().join("b.vdag"));
        convert(&moved_obj, &a, depth, &["--force"]);
        convert(&gltf, &b, depth, &["--force"]);
        // The OBJ's vertices are read back as float32 (tobj), the glTF's
        // transformed in f64: a voxel may differ where the surface grazes
        // a voxel's face, never by more than one voxel.
        let (ca, cb) = (voxel_codes(&a), voxel_codes(&b));
        let (ha, hb) = (header(&a), header(&b));
        for k in 0..3 {
            assert!((ha.root_min[k] - hb.root_min[k]).abs() < 1e-5 * ha.root_size);
        }
        assert!((ha.root_size - hb.root_size).abs() < 1e-5 * ha.root_size);
        let set_a: std::collections::HashSet<u64> = ca.iter().copied().collect();
        let set_b: std::collections::HashSet<u64> = cb.iter().copied().collect();
        let near = |v: u64, set: &std::collections::HashSet<u64>| {
            let p = dagfmt::morton::decode(v);
            (-1i64..=1).any(|dx| {
                (-1i64..=1).any(|dy| {
                    (-1i64..=1).any(|dz| {
                        let q = [p[0] as i64 + dx, p[1] as i64 + dy, p[2] as i64 + dz];
                        q.iter().all(|&c| c >= 0)
                            && set.contains(&dagfmt::morton::encode(
                                q[0] as u32,
                                q[1] as u32,
                                q[2] as u32,
                            ))
                    })
                })
            })
        };
        let differing: Vec<u64> = set_a.symmetric_difference(&set_b).copied().collect();
        assert!(
            differing.len() * 1000 <= ca.len(),
            "depth {depth}: {} of {} voxels differ",
            differing.len(),
            ca.len()
        );
        for v in differing {
            let other = if set_a.contains(&v) { &set_b } else { &set_a };
            assert!(
                near(v, other),
                "voxel {:?} is far from the other set",
                dagfmt::morton::decode(v)
            );
        }
    }
}

#[test]
fn glb_texture_gives_the_colours_of_the_textured_obj() {
    let Some(formats) = formats_dir() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("obj.vdag"), dir.path().join("glb.vdag"));
    for depth in [7, 9] {
        convert(
            &formats.join("spot_textured.obj"),
            &a,
            depth,
            &["--colors", "--force"],
        );
        convert(
            &formats.join("spot_textured.glb"),
            &b,
            depth,
            &["--colors", "--force"],
        );
        assert_eq!(voxel_codes(&a), voxel_codes(&b), "depth {depth}");
        let (ca, cb) = (colours(&a), colours(&b));
        assert_eq!(ca.len(), cb.len());
        // The same texel, up to the glTF's flipped v (1 - (1 - v) may differ
        // from v in the last bit, which moves a sample on a texel boundary).
        let same = ca.iter().zip(&cb).filter(|(x, y)| x == y).count();
        assert!(
            same * 1000 >= ca.len() * 999,
            "depth {depth}: only {same} of {} colours agree",
            ca.len()
        );
        // Not all white: the texture was read.
        assert!(cb.iter().filter(|c| **c != [255; 4]).count() * 2 > cb.len());
    }
}

#[test]
fn vox_voxels_carry_their_palette_colours() {
    let Some(formats) = formats_dir() else { return };
    let path = formats.join("spot.vox");
    let data = dot_vox::load(path.to_str().unwrap()).unwrap();
    assert_eq!(data.models.len(), 1);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("spot.vdag");
    run_ok(&["convert", s(&path), "-o", s(&out), "--colors", "-q"]);
    // No scene graph: the model's voxels as they are, from the lowest.
    let model = &data.models[0];
    let lo = [0, 1, 2].map(|a| {
        model
            .voxels
            .iter()
            .map(|v| [v.x, v.y, v.z][a])
            .min()
            .unwrap()
    });
    let mut expected: Vec<(u64, [u8; 4])> = model
        .voxels
        .iter()
        .map(|v| {
            let c = data.palette[usize::from(v.i)];
            (
                dagfmt::morton::encode(
                    u32::from(v.x - lo[0]),
                    u32::from(v.y - lo[1]),
                    u32::from(v.z - lo[2]),
                ),
                [c.r, c.g, c.b, c.a],
            )
        })
        .collect();
    expected.sort_by_key(|e| e.0);
    let h = header(&out);
    // The smallest depth holding 67 x 119 x 121 voxels; one voxel per unit.
    assert_eq!(h.depth, 7);
    assert_eq!(h.root_size, 128.0);
    let codes = voxel_codes(&out);
    let got: Vec<(u64, [u8; 4])> = codes.into_iter().zip(colours(&out)).collect();
    assert_eq!(got.len(), expected.len());
    assert!(got == expected, "colours differ from the palette's");
    // --depth below the scene's is refused; above, the same voxels.
    let small = run(&[
        "convert",
        s(&path),
        "-o",
        s(&dir.path().join("x.vdag")),
        "--depth",
        "6",
    ]);
    assert_eq!(small.status.code(), Some(2));
    assert!(!dir.path().join("x.vdag").exists());
    let big = dir.path().join("big.vdag");
    convert(&path, &big, 9, &[]);
    assert_eq!(
        voxel_codes(&big),
        got.iter().map(|g| g.0).collect::<Vec<_>>()
    );
}

#[test]
fn binvox_grid_keeps_its_cube() {
    let (Some(formats), Some(meshes)) = (formats_dir(), meshes_dir()) else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("b.vdag");
    run_ok(&[
        "convert",
        s(&formats.join("bunny_128.binvox")),
        "-o",
        s(&out),
        "-q",
    ]);
    let h = header(&out);
    assert_eq!((h.depth, h.root_min, h.root_size), (7, [0.0; 3], 1.0));
    // binvox voxelized bunny.obj scaled into its 128³ grid: the grid's
    // voxels span the mesh's bounding box along the same axes (y runs
    // fastest in the file, then z, then x), in proportion.
    let obj = std::fs::read_to_string(meshes.join("bunny.obj")).unwrap();
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for line in obj.lines().filter(|l| l.starts_with("v ")) {
        for (a, w) in line.split_whitespace().skip(1).take(3).enumerate() {
            let c: f64 = w.parse().unwrap();
            lo[a] = lo[a].min(c);
            hi[a] = hi[a].max(c);
        }
    }
    let longest = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
    let mut vlo = [u32::MAX; 3];
    let mut vhi = [0u32; 3];
    for c in voxel_codes(&out) {
        let v = dagfmt::morton::decode(c);
        for a in 0..3 {
            vlo[a] = vlo[a].min(v[a]);
            vhi[a] = vhi[a].max(v[a]);
        }
    }
    for a in 0..3 {
        let expected = (hi[a] - lo[a]) / longest * 128.0;
        let got = f64::from(vhi[a] - vlo[a] + 1);
        assert!(
            (got - expected).abs() <= 1.5,
            "axis {a}: {got} voxels, mesh {expected:.1}"
        );
    }
}

/// Exactly the voxels of the points: every point's voxel is set, every set
/// voxel holds a point (checked by `verify` on the whole cloud) — and a
/// splat radius sets the voxels within it.
#[test]
fn point_clouds_set_exactly_their_points_voxels() {
    let Some(formats) = formats_dir() else { return };
    let dir = tempfile::tempdir().unwrap();
    for (name, depth) in [
        ("sponza_points.las", 11),
        ("sponza_points.laz", 9),
        ("dragon_points.ply", 10),
    ] {
        let input = formats.join(name);
        let out = dir.path().join(format!("{name}.vdag"));
        convert(&input, &out, depth, &["--colors"]);
        let v = run_ok(&["verify", s(&input), s(&out), "--json"]);
        let report: serde_json::Value = serde_json::from_slice(&v.stdout).unwrap();
        assert_eq!(report["passed"], true, "{name}: {report}");
        assert_eq!(report["uncovered_points"], 0);
        assert_eq!(report["empty_voxels"], 0);
        assert_eq!(report["outside_root_cube"], 0);
        // Colours came along: the photos are not white.
        let c = colours(&out);
        assert!(
            c.iter().filter(|c| **c != [255; 4]).count() * 2 > c.len(),
            "{name}"
        );
    }
    // A splat radius of 1.5 voxels: verify at the radius passes, at 0 it
    // finds the voxels set by the balls only.
    let input = formats.join("sponza_points.las");
    let out = dir.path().join("splat.vdag");
    let plain = dir.path().join("plain.vdag");
    convert(&input, &plain, 8, &[]);
    let size = header(&plain).root_size;
    let radius = format!("{}", 1.5 * size / 256.0);
    convert(&input, &out, 8, &["--point-radius", &radius]);
    let v = run_ok(&[
        "verify",
        s(&input),
        s(&out),
        "--point-radius",
        &radius,
        "--json",
    ]);
    let report: serde_json::Value = serde_json::from_slice(&v.stdout).unwrap();
    assert_eq!(report["passed"], true, "{report}");
    let v = run(&["verify", s(&input), s(&out), "--json"]);
    assert_eq!(v.status.code(), Some(1));
    assert!(voxel_codes(&out).len() > voxel_codes(&plain).len());
}

/// `--bounds` puts tiles of one scene on one grid: the two halves of a
/// cloud, converted with the whole cloud's cube, together set exactly the
/// whole cloud's voxels.
#[test]
fn bounds_put_tiles_on_one_grid() {
    let dir = tempfile::tempdir().unwrap();
    // A small ASCII PLY cloud, and its two halves by x.
    let points: Vec<[f64; 3]> = (0..2000)
        .map(|i| {
            let t = f64::from(i) * 0.01;
            [t.sin() * 3.0 + t * 0.1, t.cos() * 2.0, (t * 0.7).sin()]
        })
        .collect();
    let write = |name: &str, pts: &[[f64; 3]]| {
        let mut text = format!(
            "ply\nformat ascii 1.0\nelement vertex {}\nproperty double x\nproperty double y\nproperty double z\nend_header\n",
            pts.len()
        );
        for p in pts {
            text.push_str(&format!("{:?} {:?} {:?}\n", p[0], p[1], p[2]));
        }
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        path
    };
    let whole = write("whole.ply", &points);
    let left: Vec<_> = points.iter().copied().filter(|p| p[0] < 0.5).collect();
    let right: Vec<_> = points.iter().copied().filter(|p| p[0] >= 0.5).collect();
    let (l, r) = (write("left.ply", &left), write("right.ply", &right));
    let bounds = "-4,-4,-4,10";
    let out = |n: &str| dir.path().join(n);
    for (input, o) in [
        (&whole, "whole.vdag"),
        (&l, "left.vdag"),
        (&r, "right.vdag"),
    ] {
        convert(input, &out(o), 7, &["--bounds", bounds]);
        let h = header(&out(o));
        assert_eq!((h.root_min, h.root_size), ([-4.0; 3], 10.0));
    }
    let mut union = voxel_codes(&out("left.vdag"));
    union.extend(voxel_codes(&out("right.vdag")));
    union.sort_unstable();
    union.dedup();
    assert_eq!(union, voxel_codes(&out("whole.vdag")));
    // Points outside the cube are skipped with a warning; a mesh outside it
    // is refused.
    let o = run_ok(&[
        "convert",
        s(&whole),
        "-o",
        s(&out("part.vdag")),
        "--depth",
        "6",
        "--bounds",
        "0,-4,-4,10",
    ]);
    assert!(String::from_utf8_lossy(&o.stdout).contains("outside --bounds"));
}

/// A glTF document with one buffer embedded as a data URI.
struct Gltf {
    buffer: Vec<u8>,
    views: Vec<serde_json::Value>,
    accessors: Vec<serde_json::Value>,
}

impl Gltf {
    fn new() -> Self {
        Gltf {
            buffer: Vec::new(),
            views: Vec::new(),
            accessors: Vec::new(),
        }
    }

    /// Adds `bytes` as a buffer view and an accessor over it; returns the
    /// accessor's index.
    fn accessor(
        &mut self,
        bytes: &[u8],
        component: u32,
        kind: &str,
        count: usize,
        normalized: bool,
    ) -> usize {
        while !self.buffer.len().is_multiple_of(4) {
            self.buffer.push(0);
        }
        self.views.push(serde_json::json!({
            "buffer": 0, "byteOffset": self.buffer.len(), "byteLength": bytes.len()
        }));
        self.buffer.extend_from_slice(bytes);
        self.accessors.push(serde_json::json!({
            "bufferView": self.views.len() - 1, "componentType": component, "type": kind,
            "count": count, "normalized": normalized
        }));
        self.accessors.len() - 1
    }

    fn floats(&mut self, values: &[f32], kind: &str) -> usize {
        let n = if kind == "VEC3" { 3 } else { 2 };
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let a = self.accessor(&bytes, 5126, kind, values.len() / n, false);
        if n == 3 {
            self.bound(a, values.chunks(3).map(|c| [c[0], c[1], c[2]]));
        }
        a
    }

    /// Sets an accessor's `min` and `max` (which glTF requires of positions).
    fn bound(&mut self, accessor: usize, values: impl Iterator<Item = [f32; 3]>) {
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for v in values {
            for a in 0..3 {
                lo[a] = lo[a].min(v[a]);
                hi[a] = hi[a].max(v[a]);
            }
        }
        self.accessors[accessor]["min"] = serde_json::json!(lo);
        self.accessors[accessor]["max"] = serde_json::json!(hi);
    }

    /// The document with `rest` merged in (meshes, nodes, materials …).
    fn json(&self, rest: serde_json::Value) -> String {
        use base64::Engine as _;
        let mut doc = serde_json::json!({
            "asset": {"version": "2.0"},
            "scene": 0,
            "scenes": [{"nodes": [0]}],
            "buffers": [{
                "byteLength": self.buffer.len(),
                "uri": format!("data:application/octet-stream;base64,{}",
                    base64::engine::general_purpose::STANDARD.encode(&self.buffer))
            }],
            "bufferViews": self.views,
            "accessors": self.accessors,
        });
        for (k, v) in rest.as_object().unwrap() {
            doc[k] = v.clone();
        }
        doc.to_string()
    }
}

/// A 4 x 4 PNG whose texel (x, y) (y from the top) is (60x + 10, 60y + 10, 77, 255).
fn checker_png() -> (Vec<u8>, image::RgbaImage) {
    let img = image::RgbaImage::from_fn(4, 4, |x, y| {
        image::Rgba([(60 * x + 10) as u8, (60 * y + 10) as u8, 77, 255])
    });
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    (png, img)
}

/// Colours from a glTF material: baseColorFactor × the baseColorTexture on
/// its texture coordinate set, with the sampler's wrap modes and
/// KHR_texture_transform, equal a direct lookup of the texture.
#[test]
fn gltf_texture_colours_equal_a_direct_texture_lookup() {
    use base64::Engine as _;
    let dir = tempfile::tempdir().unwrap();
    let mut g = Gltf::new();
    // One triangle covering the square [0, 1]² of the plane z = 0.
    let pos = g.floats(&[0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 2.0, 0.0], "VEC3");
    // Set 0 is a decoy; set 1 maps (x, y) to (2x, 2y).
    let decoy = g.floats(&[0.5, 0.5, 0.5, 0.5, 0.5, 0.5], "VEC2");
    let uv = g.floats(&[0.0, 0.0, 4.0, 0.0, 0.0, 4.0], "VEC2");
    let (png, img) = checker_png();
    let doc = g.json(serde_json::json!({
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{
            "attributes": {"POSITION": pos, "TEXCOORD_0": decoy, "TEXCOORD_1": uv},
            "material": 0
        }]}],
        "materials": [{"pbrMetallicRoughness": {
            "baseColorFactor": [1.0, 0.5, 1.0, 1.0],
            "baseColorTexture": {"index": 0, "texCoord": 1, "extensions": {
                "KHR_texture_transform": {"offset": [0.25, 0.0]}
            }}
        }}],
        "textures": [{"source": 0, "sampler": 0}],
        "samplers": [{"wrapS": 33648, "wrapT": 10497}],
        "images": [{"uri": format!("data:image/png;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&png))}],
        "extensionsUsed": ["KHR_texture_transform"],
        "extensionsRequired": ["KHR_texture_transform"]
    }));
    let path = dir.path().join("tri.gltf");
    std::fs::write(&path, doc).unwrap();
    let out = dir.path().join("tri.vdag");
    let depth = 6;
    convert(&path, &out, depth, &["--colors"]);
    let h = header(&out);
    let voxel = h.root_size / f64::from(1u32 << depth);
    let codes = voxel_codes(&out);
    let cols = colours(&out);
    let mut checked = 0;
    for (&code, &c) in codes.iter().zip(&cols) {
        let v = dagfmt::morton::decode(code);
        let [x, y] = [0, 1].map(|a| h.root_min[a] + (f64::from(v[a]) + 0.5) * voxel);
        // Only voxels whose centre lies over the triangle's inside (where
        // the closest point is the centre's projection), away from texel
        // boundaries (where rounding could pick either texel).
        let (u, t) = (2.0 * x + 0.25, 2.0 * y);
        let (fu, fv) = ((u * 4.0).fract(), (t * 4.0).fract());
        if x <= 0.0
            || y <= 0.0
            || x + y >= 2.0
            || !(0.05..0.95).contains(&fu)
            || !(0.05..0.95).contains(&fv)
        {
            continue;
        }
        // Mirrored repeat along u, repeat along v (v runs down the image).
        let mirrored = if (u.floor() as i64).rem_euclid(2) == 0 {
            u.fract()
        } else {
            1.0 - u.fract()
        };
        let tx = ((mirrored * 4.0) as u32).min(3);
        let ty = ((t.fract() * 4.0) as u32).min(3);
        let texel = img.get_pixel(tx, ty).0;
        let factor = [255u16, 128, 255, 255];
        let expected = [0, 1, 2, 3].map(|k| ((u16::from(texel[k]) * factor[k] + 127) / 255) as u8);
        assert_eq!(c, expected, "voxel {v:?} at ({x}, {y})");
        checked += 1;
    }
    assert!(checked > 200, "only {checked} voxels checked");
}

/// The same square as triangles, a strip and a fan, with u8, u16, u32 or no
/// indices, and with quantized positions (normalized shorts under a node
/// scale, KHR_mesh_quantization): the same voxels.
#[test]
fn gltf_primitive_modes_and_accessor_types_give_the_same_voxels() {
    let dir = tempfile::tempdir().unwrap();
    let corners: [[f32; 3]; 4] = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.3],
        [1.0, 1.0, 0.6],
        [0.0, 1.0, 0.2],
    ];
    let mut results = Vec::new();
    let variants: Vec<(&str, Vec<u32>, u32)> = vec![
        // (mode name, indices into corners, index component type or 0 for none)
        ("triangles", vec![0, 1, 2, 0, 2, 3], 5121),
        ("triangles", vec![0, 1, 2, 0, 2, 3], 5123),
        ("triangles", vec![0, 1, 2, 0, 2, 3], 5125),
        ("triangles", vec![0, 1, 2, 0, 2, 3], 0),
        ("strip", vec![1, 2, 0, 3], 5123),
        ("fan", vec![0, 1, 2, 3], 5121),
        ("quantized", vec![0, 1, 2, 0, 2, 3], 5123),
    ];
    for (i, (mode, idx, itype)) in variants.iter().enumerate() {
        let mut g = Gltf::new();
        let mut node = serde_json::json!({"mesh": 0});
        let pos = if *mode == "quantized" {
            // Normalized i16 in [-1, 1], scaled back by the node.
            let bytes: Vec<u8> = idx
                .iter()
                .flat_map(|&k| {
                    let c = corners[k as usize];
                    let q: Vec<u8> = c
                        .iter()
                        .flat_map(|&x| ((x * 32767.0).round() as i16).to_le_bytes())
                        .chain([0, 0])
                        .collect();
                    q
                })
                .collect();
            // Stride 8 (three shorts and padding).
            let a = g.accessor(&bytes, 5122, "VEC3", idx.len(), true);
            g.views[a]["byteStride"] = serde_json::json!(8);
            g.bound(
                a,
                idx.iter()
                    .map(|&k| corners[k as usize].map(|x| (x * 32767.0).round())),
            );
            node["scale"] = serde_json::json!([32767.0 / 32767.0, 1.0, 1.0]);
            a
        } else if *itype == 0 {
            let flat: Vec<f32> = idx.iter().flat_map(|&k| corners[k as usize]).collect();
            g.floats(&flat, "VEC3")
        } else {
            let flat: Vec<f32> = corners.iter().flatten().copied().collect();
            g.floats(&flat, "VEC3")
        };
        let mut prim = serde_json::json!({"attributes": {"POSITION": pos}, "mode": match *mode {
            "strip" => 5, "fan" => 6, _ => 4
        }});
        if *itype != 0 && *mode != "quantized" {
            let bytes: Vec<u8> = match itype {
                5121 => idx.iter().map(|&k| k as u8).collect(),
                5123 => idx.iter().flat_map(|&k| (k as u16).to_le_bytes()).collect(),
                _ => idx.iter().flat_map(|&k| k.to_le_bytes()).collect(),
            };
            prim["indices"] =
                serde_json::json!(g.accessor(&bytes, *itype, "SCALAR", idx.len(), false));
        }
        let mut extra = serde_json::json!({"nodes": [node], "meshes": [{"primitives": [prim]}]});
        if *mode == "quantized" {
            extra["extensionsRequired"] = serde_json::json!(["KHR_mesh_quantization"]);
            extra["extensionsUsed"] = serde_json::json!(["KHR_mesh_quantization"]);
        }
        let path = dir.path().join(format!("v{i}.gltf"));
        std::fs::write(&path, g.json(extra)).unwrap();
        let out = dir.path().join(format!("v{i}.vdag"));
        // One grid for all: the quantized corners move the bounding box.
        convert(&path, &out, 6, &["--bounds", "-0.0731,-0.0731,-0.0731,1.3"]);
        results.push((format!("{mode}/{itype}"), voxel_codes(&out)));
    }
    for (what, codes) in &results[1..] {
        // The quantized corners are within 2^-15 of the float ones: on
        // this grid that moves no voxel of this square.
        assert_eq!(codes, &results[0].1, "{what}");
    }
}

/// Bad input in every format: one `dagtool: error:` line naming the file,
/// exit status 1, nothing written.
#[test]
fn bad_input_in_every_format_is_a_one_line_error_and_no_output() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();
    let write = |name: &str, bytes: &[u8]| {
        let p = dir.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    };
    let mut cases: Vec<(PathBuf, &str)> = Vec::new();
    let ply_head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n";
    let mut nan_ply = ply_head
        .replace("ascii", "binary_little_endian")
        .into_bytes();
    for v in [0.0f32, 0.0, 0.0, 1.0, f32::NAN, 0.0, 0.0, 1.0, 0.0] {
        nan_ply.extend_from_slice(&v.to_le_bytes());
    }
    nan_ply.push(3);
    for i in [0i32, 1, 2] {
        nan_ply.extend_from_slice(&i.to_le_bytes());
    }
    cases.push((write("nan.ply", &nan_ply), "non-finite"));
    cases.push((
        write(
            "index.ply",
            format!("{ply_head}0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n").as_bytes(),
        ),
        "uses vertex 8",
    ));
    cases.push((
        write("short.ply", format!("{ply_head}0 0 0\n1 0 0\n").as_bytes()),
        "vertex 3",
    ));
    cases.push((
        write("magic.ply", b"plx\nformat ascii 1.0\nend_header\n"),
        "PLY",
    ));
    let points = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\ninf 1 1\n";
    cases.push((write("inf_points.ply", points.as_bytes()), "vertex 2"));
    cases.push((write("nan.stl", b"solid s\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 NaN 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid s\n"), "NaN"));
    cases.push((write("short.stl", &[0u8; 90]), "not an STL"));
    cases.push((write("draco.gltf", br#"{"asset":{"version":"2.0"},"extensionsUsed":["KHR_draco_mesh_compression"],"extensionsRequired":["KHR_draco_mesh_compression"]}"#), "KHR_draco_mesh_compression"));
    cases.push((
        write(
            "nobuffer.gltf",
            br#"{"asset":{"version":"2.0"},"buffers":[{"uri":"missing.bin","byteLength":12}]}"#,
        ),
        "missing.bin",
    ));
    let mut g = Gltf::new();
    let pos = g.floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0], "VEC3");
    let idx = g.accessor(&[0, 1, 9], 5121, "SCALAR", 3, false);
    let doc = g.json(serde_json::json!({"nodes": [{"mesh": 0}], "meshes": [{"primitives": [{"attributes": {"POSITION": pos}, "indices": idx}]}]}));
    cases.push((write("index.gltf", doc.as_bytes()), "out of range"));
    let mut g = Gltf::new();
    let pos = g.floats(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0], "VEC3");
    let uv = g.floats(&[0.0; 6], "VEC2");
    let doc = g.json(serde_json::json!({"nodes": [{"mesh": 0}], "meshes": [{"primitives": [{"attributes": {"POSITION": pos, "TEXCOORD_0": uv}, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}], "textures": [{"source": 0}], "images": [{"uri": "gone.png"}]}));
    cases.push((write("notexture.gltf", doc.as_bytes()), "gone.png"));
    if let Some(formats) = formats_dir() {
        let glb = std::fs::read(formats.join("spot_textured.glb")).unwrap();
        cases.push((write("cut.glb", &glb[..glb.len() / 2]), "GLB"));
        let ply = std::fs::read(formats.join("bunny.ply")).unwrap();
        cases.push((write("cut.ply", &ply[..ply.len() / 2]), "PLY"));
        let las = std::fs::read(formats.join("sponza_points.las")).unwrap();
        cases.push((write("cut.las", &las[..las.len() / 2]), "truncated"));
        let laz = std::fs::read(formats.join("sponza_points.laz")).unwrap();
        cases.push((write("cut.laz", &laz[..laz.len() / 2]), "LA"));
        let vox = std::fs::read(formats.join("spot.vox")).unwrap();
        cases.push((write("cut.vox", &vox[..vox.len() / 2]), "VOX"));
        let binvox = std::fs::read(formats.join("bunny_128.binvox")).unwrap();
        cases.push((
            write("cut.binvox", &binvox[..binvox.len() / 2]),
            "binvox data",
        ));
    }
    cases.push((write("magic.las", b"LASX not a las file at all"), "LAS"));
    for (input, needle) in &cases {
        let output = out_dir.join("o.vdag");
        let o = run(&[
            "convert",
            s(input),
            "-o",
            s(&output),
            "--depth",
            "6",
            "--colors",
            "-q",
        ]);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{}: {stderr}", input.display());
        assert!(!stderr.contains("panicked"), "{stderr}");
        assert_eq!(stderr.lines().count(), 1, "{}: {stderr}", input.display());
        assert!(stderr.starts_with("dagtool: error: "), "{stderr}");
        assert!(
            stderr.contains(needle),
            "{}: `{needle}` not in {stderr}",
            input.display()
        );
        assert!(
            stderr.contains(s(input)),
            "{stderr} does not name the input"
        );
        assert!(
            crate::common::dir_entries(&out_dir).is_empty(),
            "{}: output left",
            input.display()
        );
    }
}
