//! Helpers: running the binary, writing meshes, reading voxel sets back.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The `dagtool` binary under test.
pub fn dagtool() -> Command {
    Command::new(env!("CARGO_BIN_EXE_dagtool"))
}

/// Runs `dagtool` with `args`.
pub fn run(args: &[&str]) -> Output {
    dagtool().args(args).output().expect("dagtool runs")
}

/// Runs `dagtool` and asserts success.
pub fn run_ok(args: &[&str]) -> Output {
    let out = run(args);
    assert!(
        out.status.success(),
        "dagtool {args:?} failed ({:?}):\n{}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Converts `input` to `output` (quietly) with extra arguments; asserts success.
pub fn convert(input: &Path, output: &Path, depth: u8, extra: &[&str]) {
    let d = depth.to_string();
    let mut args = vec![
        "convert",
        input.to_str().unwrap(),
        "-o",
        output.to_str().unwrap(),
        "--depth",
        &d,
        "-q",
    ];
    args.extend_from_slice(extra);
    run_ok(&args);
}

/// The folder of shared test meshes, or `None` (with a message) when absent.
pub fn meshes_dir() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/meshes");
    if dir.is_dir() {
        Some(dir)
    } else {
        eprintln!(
            "skipping: shared meshes not found at {} (tests on real meshes need ../shared/meshes)",
            dir.display()
        );
        None
    }
}

/// A simple triangle mesh for writing OBJ files.
#[derive(Clone, Debug, Default)]
pub struct ObjMesh {
    pub vertices: Vec<[f64; 3]>,
    pub faces: Vec<Vec<usize>>,
}

impl ObjMesh {
    pub fn add_vertex(&mut self, v: [f64; 3]) -> usize {
        self.vertices.push(v);
        self.vertices.len() - 1
    }

    pub fn add_triangle(&mut self, a: [f64; 3], b: [f64; 3], c: [f64; 3]) {
        let i = self.add_vertex(a);
        let j = self.add_vertex(b);
        let k = self.add_vertex(c);
        self.faces.push(vec![i, j, k]);
    }

    /// Appends another mesh.
    pub fn append(&mut self, other: &ObjMesh) {
        let base = self.vertices.len();
        self.vertices.extend_from_slice(&other.vertices);
        self.faces.extend(
            other
                .faces
                .iter()
                .map(|f| f.iter().map(|i| i + base).collect()),
        );
    }

    /// OBJ text (1-based indices; numbers printed exactly).
    pub fn to_obj(&self) -> String {
        let mut s = String::new();
        for v in &self.vertices {
            let _ = writeln!(s, "v {:?} {:?} {:?}", v[0], v[1], v[2]);
        }
        for f in &self.faces {
            let idx: Vec<String> = f.iter().map(|i| (i + 1).to_string()).collect();
            let _ = writeln!(s, "f {}", idx.join(" "));
        }
        s
    }

    pub fn write(&self, path: &Path) {
        std::fs::write(path, self.to_obj()).unwrap();
    }
}

/// An axis-aligned box as 6 quads (12 triangles after triangulation),
/// outward-facing, sharing vertices.
pub fn box_mesh(min: [f64; 3], max: [f64; 3]) -> ObjMesh {
    let mut m = ObjMesh::default();
    for i in 0..8 {
        m.add_vertex([
            if i & 1 == 0 { min[0] } else { max[0] },
            if i & 2 == 0 { min[1] } else { max[1] },
            if i & 4 == 0 { min[2] } else { max[2] },
        ]);
    }
    for f in [
        [0, 2, 3, 1],
        [4, 5, 7, 6],
        [0, 1, 5, 4],
        [2, 6, 7, 3],
        [0, 4, 6, 2],
        [1, 3, 7, 5],
    ] {
        m.faces.push(f.to_vec());
    }
    m
}

/// An icosphere (subdivided icosahedron) of `radius` around `center`.
pub fn sphere_mesh(center: [f64; 3], radius: f64, subdivisions: u32) -> ObjMesh {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut verts: Vec<[f64; 3]> = vec![
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ];
    let mut faces: Vec<[usize; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut cache = std::collections::HashMap::new();
        let mut mid = |a: usize, b: usize, verts: &mut Vec<[f64; 3]>| -> usize {
            *cache.entry((a.min(b), a.max(b))).or_insert_with(|| {
                let p = [0, 1, 2].map(|k| (verts[a][k] + verts[b][k]) / 2.0);
                verts.push(p);
                verts.len() - 1
            })
        };
        let mut next = Vec::new();
        for [a, b, c] in faces {
            let ab = mid(a, b, &mut verts);
            let bc = mid(b, c, &mut verts);
            let ca = mid(c, a, &mut verts);
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        faces = next;
    }
    let mut m = ObjMesh::default();
    for v in verts {
        let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        m.add_vertex([0, 1, 2].map(|k| center[k] + radius * v[k] / len));
    }
    m.faces = faces.into_iter().map(|f| f.to_vec()).collect();
    m
}

/// The voxels of a `.vdag` file of either version as sorted Morton codes.
pub fn voxel_codes(path: &Path) -> Vec<u64> {
    let bytes = std::fs::read(path).unwrap();
    let codes = dagfmt::AnyDag::open(&bytes).unwrap().voxel_codes().unwrap();
    assert!(
        codes.windows(2).all(|w| w[0] < w[1]),
        "voxels come in Morton order"
    );
    codes
}

/// Asserts two sorted voxel code lists are equal, showing the first differences.
pub fn assert_same_voxels(got: &[u64], expected: &[u64], what: &str) {
    if got == expected {
        return;
    }
    let g: std::collections::BTreeSet<u64> = got.iter().copied().collect();
    let e: std::collections::BTreeSet<u64> = expected.iter().copied().collect();
    let extra: Vec<[u32; 3]> = g
        .difference(&e)
        .take(8)
        .map(|&c| dagfmt::morton::decode(c))
        .collect();
    let missing: Vec<[u32; 3]> = e
        .difference(&g)
        .take(8)
        .map(|&c| dagfmt::morton::decode(c))
        .collect();
    panic!(
        "{what}: converter has {} voxels, reference {}; {} extra (e.g. {extra:?}), {} missing (e.g. {missing:?})",
        got.len(),
        expected.len(),
        g.difference(&e).count(),
        e.difference(&g).count()
    );
}

/// Files in `dir` (names).
pub fn dir_entries(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// The voxel colours (RGBA8 in voxel order, raw or packed, decoded) of a
/// file of either version, or `None` without colours.
pub fn colour_bytes(dag: &dagfmt::AnyDag<'_>) -> Option<Vec<u8>> {
    dag.color_table().map(|t| t.iter().flatten().collect())
}
