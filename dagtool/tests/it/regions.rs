//! Region builds (`convert --region`) and `merge`: the merge of every
//! region's part is the whole conversion's file, byte for byte, whatever the
//! order of the parts and the shape of the merge tree; bad parts are refused
//! with their code and leave no output (spec/VDAG.md § 24).

use std::path::{Path, PathBuf};

use dagtool::convert::{Bounds, ConvertOptions, convert};
use dagtool::merge::{MergeOptions, merge};
use dagtool::region::Region;
use proptest::prelude::*;

use crate::common::{run, sphere_mesh};

/// A conversion's options: `input` at `depth` in the cube `bounds`, quiet.
fn options(input: &Path, output: &Path, depth: u8, bounds: &str) -> ConvertOptions {
    let mut o = ConvertOptions::new(input, output, Some(depth));
    o.bounds = Some(Bounds::parse(bounds).unwrap());
    // In process, beside the other tests: the limit is checked against the
    // whole test process's peak memory, so it is left at its default.
    o
}

/// Builds every region of level `k` with `base`'s options into `dir`; the
/// parts in Morton order.
fn build_parts(base: &ConvertOptions, k: u8, dir: &Path) -> Vec<PathBuf> {
    Region::all(k)
        .map(|r| {
            let mut o = base.clone();
            o.output = dir.join(format!("part-{}.vdag", r.index()));
            o.region = Some(r);
            convert(&o).unwrap_or_else(|e| panic!("region {r}: {e}"));
            o.output
        })
        .collect()
}

fn merged(parts: &[PathBuf], out: &Path) -> Vec<u8> {
    merge(parts, out, &MergeOptions::default()).unwrap_or_else(|e| panic!("{e}"));
    std::fs::read(out).unwrap()
}

/// The whole conversion, and the merge of all its level-`k` parts (in reverse
/// order, out of core in 3 buckets per level; in order, in memory; with a
/// memory limit too small for the in-memory merge), must be the same bytes.
fn check_identity(base: &ConvertOptions, k: u8, what: &str) -> Vec<PathBuf> {
    let stem = base.output.file_stem().unwrap().to_string_lossy();
    let dir = base
        .output
        .parent()
        .unwrap()
        .join(format!("parts-{stem}-{k}"));
    std::fs::create_dir_all(&dir).unwrap();
    convert(base).unwrap();
    let whole = std::fs::read(&base.output).unwrap();
    let parts = build_parts(base, k, &dir);
    let mut reversed = parts.clone();
    reversed.reverse();
    let out = dir.join("merged.vdag");
    let opts = MergeOptions {
        buckets: Some(3),
        ..Default::default()
    };
    let summary = merge(&reversed, &out, &opts).unwrap_or_else(|e| panic!("{what}: {e}"));
    assert!(summary.complete, "{what}");
    assert!(summary.voxels > 0, "{what}: a vacuous test");
    assert!(
        !summary.in_memory,
        "{what}: buckets force the out-of-core merge"
    );
    assert!(
        std::fs::read(&out).unwrap() == whole,
        "{what}: the merge of the level-{k} parts differs from the whole build"
    );
    let summary = merge(&parts, &out, &forced()).unwrap_or_else(|e| panic!("{what}: {e}"));
    assert!(summary.in_memory, "{what}: small parts merge in memory");
    assert!(
        std::fs::read(&out).unwrap() == whole,
        "{what}: the in-memory merge of the level-{k} parts differs from the whole build"
    );
    let tight = MergeOptions {
        memory_limit: Some(1 << 20),
        ..forced()
    };
    let summary = merge(&parts, &out, &tight).unwrap_or_else(|e| panic!("{what}: {e}"));
    assert!(
        !summary.in_memory,
        "{what}: 1 MiB is too little for the in-memory merge"
    );
    assert!(
        std::fs::read(&out).unwrap() == whole,
        "{what}: the merge of the level-{k} parts within 1 MiB differs from the whole build"
    );
    parts
}

/// Merge options that replace the output.
fn forced() -> MergeOptions {
    MergeOptions {
        force: true,
        ..Default::default()
    }
}

/// Merge options of one of the two level merges: in memory, or (`true`) out
/// of core in 2 buckets per level.
fn merge_path(out_of_core: bool) -> MergeOptions {
    MergeOptions {
        buckets: out_of_core.then_some(2),
        ..Default::default()
    }
}

fn two_colour_mesh(dir: &Path) -> PathBuf {
    // Two spheres, one red and one blue, crossing several cells.
    let mut text = String::from("mtllib m.mtl\n");
    let mut base = 0;
    for (name, c) in [("red", [0.2, 0.1, 0.3]), ("blue", [-0.3, -0.2, -0.1])] {
        let s = sphere_mesh(c, 0.55, 2);
        text.push_str(&format!("usemtl {name}\n"));
        for v in &s.vertices {
            text.push_str(&format!("v {} {} {}\n", v[0], v[1], v[2]));
        }
        for f in &s.faces {
            text.push('f');
            for i in f {
                text.push_str(&format!(" {}", i + 1 + base));
            }
            text.push('\n');
        }
        base += s.vertices.len();
    }
    std::fs::write(
        dir.join("m.mtl"),
        "newmtl red\nKd 1 0 0\nnewmtl blue\nKd 0 0 1\n",
    )
    .unwrap();
    let path = dir.join("two.obj");
    std::fs::write(&path, text).unwrap();
    path
}

fn coloured_cloud(dir: &Path) -> PathBuf {
    let mut text = String::new();
    let n = 3000;
    text.push_str(&format!(
        "ply\nformat ascii 1.0\nelement vertex {n}\nproperty double x\nproperty double y\nproperty double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    ));
    for i in 0..n {
        let t = f64::from(i) * 0.013;
        text.push_str(&format!(
            "{:?} {:?} {:?} {} {} {}\n",
            t.sin() * 0.9,
            (t * 1.3).cos() * 0.8,
            (t * 0.37).sin() * 0.9,
            i % 256,
            (i * 7) % 256,
            (i * 13) % 256
        ));
    }
    let path = dir.join("cloud.ply");
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn merged_regions_are_the_whole_mesh_build() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("sphere.obj");
    sphere_mesh([0.1, -0.2, 0.05], 0.7, 2).write(&obj);
    let base = options(&obj, &dir.path().join("whole.vdag"), 7, "-1,-1,-1,2");
    check_identity(&base, 1, "sphere, level 1");
    // Cells smaller than a chunk: the region keeps part of a chunk's bricks.
    let mut small = base.clone();
    small.chunk_bits = Some(6);
    small.output = dir.path().join("whole-small.vdag");
    let parts = check_identity(&small, 2, "sphere, level 2");
    // The sphere misses some cells of level 2: those parts are empty volumes.
    let empty = parts
        .iter()
        .filter(|p| {
            let bytes = std::fs::read(p).unwrap();
            dagfmt::Dag::open(&bytes).unwrap().is_empty()
        })
        .count();
    assert!(empty > 0 && empty < 64, "{empty} empty parts of 64");
}

#[test]
fn regions_of_many_chunks_bin_only_their_own_triangles() {
    // Cells of several chunks per axis: a region bins the triangles into
    // its own chunks only (the others are never voxelized), and the merge is
    // still the whole build, colours included.
    let dir = tempfile::tempdir().unwrap();
    let obj = two_colour_mesh(dir.path());
    let mut base = options(&obj, &dir.path().join("whole.vdag"), 8, "-1,-1,-1,2");
    base.chunk_bits = Some(3);
    base.colors = true;
    base.force = true;
    check_identity(&base, 1, "coloured mesh, 4^3 chunks per level-1 cell");
    base.output = dir.path().join("whole-2.vdag");
    let parts = check_identity(&base, 2, "coloured mesh, 2^3 chunks per level-2 cell");
    // The work summed over the regions is the whole build's: every chunk
    // with triangles is binned by exactly one region.
    let whole = convert(&base).unwrap();
    let mut entries = 0;
    let mut chunks = 0;
    for r in Region::all(2) {
        let mut o = base.clone();
        o.output = dir.path().join("again.vdag");
        o.force = true;
        o.region = Some(r);
        let s = convert(&o).unwrap();
        entries += s.bin_entries;
        chunks += s.surface_chunks;
    }
    assert_eq!(parts.len(), 64);
    assert_eq!(entries, whole.bin_entries);
    assert_eq!(chunks, whole.surface_chunks);
}

#[test]
fn a_cached_mesh_is_read_again_when_its_file_changes() {
    // cache_input keeps the parsed mesh for the next conversion of the same
    // file; another file, or the same path rewritten, is parsed afresh.
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("cached.obj");
    let fresh = |o: &ConvertOptions| {
        let mut o = o.clone();
        o.cache_input = false;
        o.output = dir.path().join("fresh.vdag");
        o.force = true;
        convert(&o).unwrap();
        std::fs::read(&o.output).unwrap()
    };
    for (i, (centre, radius)) in [([0.1, -0.2, 0.05], 0.7), ([-0.3, 0.2, 0.1], 0.5)]
        .into_iter()
        .enumerate()
    {
        sphere_mesh(centre, radius, 2).write(&obj);
        let mut o = options(&obj, &dir.path().join("cached.vdag"), 7, "-1,-1,-1,2");
        o.cache_input = true;
        o.force = true;
        for r in [None, Some(Region::parse("1:0,0,0").unwrap())] {
            o.region = r;
            // Twice: the second conversion reads the mesh kept by the first.
            for _ in 0..2 {
                convert(&o).unwrap();
                assert!(
                    std::fs::read(&o.output).unwrap() == fresh(&o),
                    "sphere {i}, region {r:?}: the cached mesh gave another file"
                );
            }
        }
    }
}

#[test]
fn merged_regions_keep_colours_raw_and_packed() {
    let dir = tempfile::tempdir().unwrap();
    let obj = two_colour_mesh(dir.path());
    let mut base = options(&obj, &dir.path().join("whole.vdag"), 7, "-1,-1,-1,2");
    base.colors = true;
    check_identity(&base, 1, "coloured mesh, raw");
    base.color_error = Some(3);
    base.output = dir.path().join("whole-packed.vdag");
    let parts = check_identity(&base, 1, "coloured mesh, packed within 3");
    // Parts keep raw colours; only the final file packs them.
    let bytes = std::fs::read(&parts[0]).unwrap();
    let dag = dagfmt::Dag::open(&bytes).unwrap();
    assert!(dag.packed_colors().is_none() && dag.colors().is_some());
    let whole = std::fs::read(&base.output).unwrap();
    let whole = dagfmt::AnyDag::open(&whole).unwrap();
    assert_eq!(whole.version_major(), 2, "the default format");
    assert!(
        whole
            .sections()
            .iter()
            .any(|s| s.kind == dagfmt::SectionKind::PackedColors)
    );
}

#[test]
fn merged_regions_are_the_whole_solid_build() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("sphere.obj");
    sphere_mesh([0.0, 0.1, -0.1], 0.8, 2).write(&obj);
    let mut base = options(&obj, &dir.path().join("whole.vdag"), 6, "-1,-1,-1,2");
    base.solid = true;
    check_identity(&base, 1, "solid sphere");
}

#[test]
fn merged_regions_are_the_whole_point_cloud_build() {
    let dir = tempfile::tempdir().unwrap();
    let cloud = coloured_cloud(dir.path());
    let mut base = options(&cloud, &dir.path().join("whole.vdag"), 7, "-1,-1,-1,2");
    base.colors = true;
    check_identity(&base, 2, "coloured point cloud");
}

#[test]
fn one_part_holding_everything_is_the_whole_file() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("sphere.obj");
    sphere_mesh([0.0; 3], 0.6, 1).write(&obj);
    let mut base = options(&obj, &dir.path().join("whole.vdag"), 6, "-1,-1,-1,2");
    base.format_version = 1;
    convert(&base).unwrap();
    let mut o = base.clone();
    o.output = dir.path().join("all.part");
    o.region = Some(Region::parse("0:0,0,0").unwrap());
    convert(&o).unwrap();
    // The part is the whole volume (in 1.0) plus its placement; merging it
    // alone drops the placement.
    let part = std::fs::read(&o.output).unwrap();
    let whole = std::fs::read(&base.output).unwrap();
    assert_eq!(part.len(), whole.len() + 40 + 48);
    let m1 = dir.path().join("m1.vdag");
    let one = MergeOptions {
        format_version: 1,
        ..Default::default()
    };
    let summary = merge(std::slice::from_ref(&o.output), &m1, &one).unwrap();
    assert!(summary.complete && summary.format_version == 1);
    assert_eq!(std::fs::read(&m1).unwrap(), whole);
    let out = dir.path().join("m-out-of-core.vdag");
    let one_out_of_core = MergeOptions {
        format_version: 1,
        ..merge_path(true)
    };
    merge(std::slice::from_ref(&o.output), &out, &one_out_of_core).unwrap();
    assert_eq!(std::fs::read(out).unwrap(), whole);
    // By default the merge writes the whole volume as convert does: 2.0.
    base.format_version = 2;
    base.output = dir.path().join("whole2.vdag");
    convert(&base).unwrap();
    assert_eq!(
        merged(&[o.output], &dir.path().join("m.vdag")),
        std::fs::read(&base.output).unwrap()
    );
}

#[test]
fn one_part_holding_everything_beside_empty_parts() {
    // A sphere inside cell 0 of level 1: part 0 holds every voxel, the other
    // seven are empty volumes; both merges, any order, give the whole file.
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("sphere.obj");
    sphere_mesh([-0.5, -0.5, -0.5], 0.3, 2).write(&obj);
    let base = options(&obj, &dir.path().join("whole.vdag"), 7, "-1,-1,-1,2");
    let parts = check_identity(&base, 1, "a sphere in one cell");
    let whole = std::fs::read(&base.output).unwrap();
    let empty = parts
        .iter()
        .filter(|p| {
            dagfmt::Dag::open(&std::fs::read(p).unwrap())
                .unwrap()
                .is_empty()
        })
        .count();
    assert_eq!(empty, 7, "one part holds everything");
    for out_of_core in [false, true] {
        let mut order = parts.clone();
        order.rotate_left(3);
        let out = dir.path().join(format!("m-{out_of_core}.vdag"));
        let s = merge(&order, &out, &merge_path(out_of_core)).unwrap();
        assert_eq!(s.in_memory, !out_of_core);
        assert_eq!(std::fs::read(&out).unwrap(), whole);
    }
}

#[test]
fn parts_of_parts_are_parts() {
    // The regions are level 1; a merge of the first three is a part that
    // validates (with the part rules) and merges with the rest.
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("sphere.obj");
    sphere_mesh([0.0; 3], 0.7, 2).write(&obj);
    let base = options(&obj, &dir.path().join("whole.vdag"), 6, "-1,-1,-1,2");
    let parts = check_identity(&base, 1, "sphere");
    let a = dir.path().join("a.part");
    // A part is format 1 whatever the version asked for the whole volume.
    let s = merge(&parts[..3], &a, &MergeOptions::default()).unwrap();
    assert!(!s.complete && s.format_version == 1);
    assert_eq!(s.cells, 0..3);
    let out = run(&["validate", a.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && text.contains("a part: cells 0..3 of level 1"),
        "{text}"
    );
    let mut rest = vec![a];
    rest.extend_from_slice(&parts[3..]);
    assert_eq!(
        merged(&rest, &dir.path().join("m.vdag")),
        std::fs::read(&base.output).unwrap()
    );
}

/// Parts of one coloured volume (level 2: 64 regions), built once.
fn shared_parts() -> &'static (tempfile::TempDir, Vec<PathBuf>, Vec<u8>) {
    static PARTS: std::sync::OnceLock<(tempfile::TempDir, Vec<PathBuf>, Vec<u8>)> =
        std::sync::OnceLock::new();
    PARTS.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let obj = two_colour_mesh(dir.path());
        let mut base = options(&obj, &dir.path().join("whole.vdag"), 6, "-1,-1,-1,2");
        base.colors = true;
        convert(&base).unwrap();
        let whole = std::fs::read(&base.output).unwrap();
        let parts = build_parts(&base, 2, dir.path());
        (dir, parts, whole)
    })
}

/// Merges `parts[range]` by a random binary tree whose leaves are single
/// parts, giving each merge its inputs in a random order and merging in
/// memory or out of core at random; returns the root's file.
fn tree_merge(
    parts: &[PathBuf],
    range: std::ops::Range<usize>,
    choices: &mut impl Iterator<Item = u64>,
    dir: &Path,
    serial: &mut usize,
) -> PathBuf {
    if range.len() == 1 {
        return parts[range.start].clone();
    }
    let c = choices.next().unwrap_or(0);
    let split = range.start + 1 + (c as usize % (range.len() - 1));
    let left = tree_merge(parts, range.start..split, choices, dir, serial);
    let right = tree_merge(parts, split..range.end, choices, dir, serial);
    *serial += 1;
    let out = dir.join(format!("t{serial}.vdag"));
    let inputs = if c & 1 << 40 == 0 {
        vec![left, right]
    } else {
        vec![right, left]
    };
    let summary =
        merge(&inputs, &out, &merge_path(c & 1 << 41 != 0)).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(summary.in_memory, c & 1 << 41 == 0);
    out
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 6, ..ProptestConfig::default() })]

    #[test]
    fn the_merge_does_not_depend_on_order_or_tree(
        choices in proptest::collection::vec(any::<u64>(), 64),
        order in Just((0..64usize).collect::<Vec<_>>()).prop_shuffle(),
    ) {
        let (_, parts, whole) = shared_parts();
        let dir = tempfile::tempdir().unwrap();
        // All at once, in a random order, in memory and out of core.
        let shuffled: Vec<PathBuf> = order.iter().map(|&i| parts[i].clone()).collect();
        prop_assert!(&merged(&shuffled, &dir.path().join("flat.vdag")) == whole);
        let flat = dir.path().join("flat-out-of-core.vdag");
        merge(&shuffled, &flat, &merge_path(true)).unwrap_or_else(|e| panic!("{e}"));
        prop_assert!(&std::fs::read(flat).unwrap() == whole);
        // By a random binary tree of partial merges.
        let mut serial = 0;
        let root = tree_merge(parts, 0..parts.len(), &mut choices.into_iter(), dir.path(), &mut serial);
        prop_assert!(&std::fs::read(root).unwrap() == whole);
    }
}

/// Runs `dagtool merge` and returns its exit code and stderr; asserts that
/// no output file was left.
fn merge_fails(parts: &[&Path], dir: &Path) -> (Option<i32>, String) {
    let out = dir.join("refused.vdag");
    let mut args = vec!["merge", "-o", out.to_str().unwrap()];
    args.extend(parts.iter().map(|p| p.to_str().unwrap()));
    let o = run(&args);
    assert!(!out.exists(), "a refused merge wrote {}", out.display());
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(err.lines().count(), 1, "one line: {err}");
    (o.status.code(), err)
}

/// Rewrites the PART_PLACEMENT bytes of a part, with its checksums.
fn with_placement(bytes: &[u8], edit: impl FnOnce(&mut [u8])) -> Vec<u8> {
    let mut b = bytes.to_vec();
    let dag = dagfmt::Dag::open(bytes).unwrap();
    let s = dag
        .sections()
        .iter()
        .find(|s| s.kind.to_raw() == dagtool::region::PART_PLACEMENT_KIND)
        .copied()
        .unwrap();
    let at = s.offset as usize;
    edit(&mut b[at..at + 48]);
    let crc = crc32c::crc32c(&b[at..at + 48]);
    let entry = s.entry_offset() as usize;
    b[entry + 32..entry + 36].copy_from_slice(&crc.to_le_bytes());
    let table_end = 128 + 40 * dag.sections().len();
    let header: [u8; 128] = b[..128].try_into().unwrap();
    let h = dagfmt::layout::header_checksum(&header, &b[128..table_end]);
    b[124..128].copy_from_slice(&h.to_le_bytes());
    b
}

#[test]
fn bad_parts_are_refused_with_their_code() {
    let (_, parts, _) = shared_parts();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Overlap, gap, not a part.
    let a = d.join("a.part");
    merge(&parts[0..4], &a, &MergeOptions::default()).unwrap();
    let (code, err) = merge_fails(&[&a, &parts[2]], d);
    assert!(
        code == Some(1) && err.contains("E096 parts-overlap"),
        "{err}"
    );
    let (_, err) = merge_fails(&[&parts[0], &parts[2]], d);
    assert!(err.contains("E097 parts-gap"), "{err}");
    // Ordinary files are not parts: the whole volume in 2.0 (convert's
    // default) and in 1.0.
    let whole2 = shared_parts().0.path().join("whole.vdag");
    let (_, err) = merge_fails(&[&whole2], d);
    assert!(
        err.contains("E098 not-a-part") && err.contains("2.0"),
        "{err}"
    );
    let whole1 = d.join("whole1.vdag");
    let o = run(&[
        "upgrade",
        whole2.to_str().unwrap(),
        "-o",
        whole1.to_str().unwrap(),
        "--format-version",
        "1",
    ]);
    assert!(o.status.success());
    let (_, err) = merge_fails(&[&whole1], d);
    assert!(err.contains("E098 not-a-part"), "{err}");
    // A different depth, and different colours, of the same mesh.
    let obj = two_colour_mesh(d);
    let mut other = options(&obj, &d.join("o.part"), 7, "-1,-1,-1,2");
    other.colors = true;
    other.region = Some(Region::from_index(2, 1));
    convert(&other).unwrap();
    let (_, err) = merge_fails(&[&parts[0], &other.output], d);
    assert!(
        err.contains("E095 parts-mismatch") && err.contains("depth"),
        "{err}"
    );
    let mut plain = options(&obj, &d.join("p.part"), 6, "-1,-1,-1,2");
    plain.region = Some(Region::from_index(2, 1));
    convert(&plain).unwrap();
    let (_, err) = merge_fails(&[&parts[0], &plain.output], d);
    assert!(
        err.contains("E095 parts-mismatch") && err.contains("colours"),
        "{err}"
    );
    // A flipped bit: the format's own finding (a checksum).
    let good = std::fs::read(&parts[0]).unwrap();
    let mut flipped = good.clone();
    let last = flipped.len() - 60;
    flipped[last] ^= 4;
    let bad = d.join("flipped.part");
    std::fs::write(&bad, &flipped).unwrap();
    let (_, err) = merge_fails(&[&bad, &parts[1]], d);
    assert!(err.contains("E0") && err.contains("flipped.part"), "{err}");
    // Part rules, with valid checksums: voxels outside the declared cell,
    // a bad version, an impossible range, a bad colour mode.
    let full = parts
        .iter()
        .map(|p| std::fs::read(p).unwrap())
        .find(|b| !dagfmt::Dag::open(b).unwrap().is_empty())
        .unwrap();
    type Edit = Box<dyn Fn(&mut [u8])>;
    let cases: [(&str, Edit); 5] = [
        (
            "E094 part-voxel-outside",
            Box::new(|p| {
                let first = u64::from_le_bytes(p[16..24].try_into().unwrap());
                let (s, e) = if first == 0 { (1u64, 2u64) } else { (0, 1) };
                p[16..24].copy_from_slice(&s.to_le_bytes());
                p[24..32].copy_from_slice(&e.to_le_bytes());
            }),
        ),
        ("E091 part-version", Box::new(|p| p[8] = 2)),
        (
            "E092 bad-part-region",
            Box::new(|p| p[24..32].copy_from_slice(&100u64.to_le_bytes())),
        ),
        ("E093 part-colours", Box::new(|p| p[11] = 0)),
        ("E090 bad-part-placement", Box::new(|p| p[40] = 1)),
    ];
    for (want, edit) in cases {
        let path = d.join("edited.part");
        std::fs::write(&path, with_placement(&full, edit)).unwrap();
        let (_, err) = merge_fails(&[&path], d);
        assert!(err.contains(want), "{want}: {err}");
        // validate reports it too, as an invalid file.
        let v = run(&["validate", path.to_str().unwrap()]);
        let text = String::from_utf8_lossy(&v.stdout);
        assert!(
            v.status.code() == Some(1) && text.contains(want),
            "{want}: {text}"
        );
    }
}

#[test]
fn region_command_line_errors() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("s.obj");
    sphere_mesh([0.0; 3], 0.5, 1).write(&obj);
    let out = dir.path().join("p.vdag");
    let (o, i) = (out.to_str().unwrap(), obj.to_str().unwrap());
    for (args, want) in [
        (vec!["--region", "1:0,0,0"], "needs --bounds"),
        (
            vec!["--region", "5:0,0,0", "--bounds", "-1,-1,-1,2"],
            "K must be at most D - 2",
        ),
        (
            vec!["--region", "7:0,0,0", "--bounds", "-1,-1,-1,2"],
            "K must be at most D - 2",
        ),
        (
            vec!["--region", "1:2,0,0", "--bounds", "-1,-1,-1,2"],
            "outside 0..2",
        ),
        (
            vec!["--region", "1:0,0", "--bounds", "-1,-1,-1,2"],
            "is not K:X,Y,Z",
        ),
        // A part is format 1: asking for 2.0 is refused (the default and
        // `--format-version 1` write the part).
        (
            vec![
                "--region",
                "1:0,0,0",
                "--bounds",
                "-1,-1,-1,2",
                "--format-version",
                "2",
            ],
            "which is format 1",
        ),
    ] {
        let mut a = vec!["convert", i, "-o", o, "--depth", "6", "-q"];
        a.extend(args);
        let r = run(&a);
        let err = String::from_utf8_lossy(&r.stderr);
        assert_eq!(r.status.code(), Some(2), "{a:?}: {err}");
        assert!(
            err.contains(want) && err.lines().count() == 1,
            "{a:?}: {err}"
        );
        assert!(!out.exists());
    }
}

/// Writes a LAS tile of coloured points.
fn las_tile(path: &Path, points: &[[f64; 3]], seed: u16) {
    let mut builder = las::Builder::from((1, 2));
    builder.point_format = las::point::Format::new(2).unwrap();
    let header = builder.into_header().unwrap();
    let mut writer = las::Writer::from_path(path, header).unwrap();
    for (i, p) in points.iter().enumerate() {
        let i = i as u16;
        writer
            .write_point(las::Point {
                x: p[0],
                y: p[1],
                z: p[2],
                color: Some(las::Color::new(
                    i.wrapping_mul(977),
                    seed.wrapping_mul(20000),
                    i.wrapping_mul(131),
                )),
                ..Default::default()
            })
            .unwrap();
    }
    writer.close().unwrap();
}

#[test]
fn las_tiles_convert_as_one_cloud_and_regions_read_only_theirs() {
    let dir = tempfile::tempdir().unwrap();
    // Four tiles, the quadrants of x and y; each region of level 1 meets
    // only the tiles of its quadrant.
    let mut tiles = Vec::new();
    for (q, (sx, sy)) in [(1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0)]
        .into_iter()
        .enumerate()
    {
        let pts: Vec<[f64; 3]> = (0..800)
            .map(|i| {
                let t = f64::from(i) * 0.011 + q as f64;
                [
                    sx * (0.05 + 0.9 * (t * 1.7).sin().abs()),
                    sy * (0.05 + 0.9 * (t * 0.9).cos().abs()),
                    0.8 * (t * 2.3).sin(),
                ]
            })
            .collect();
        let path = dir.path().join(format!("tile{q}.las"));
        las_tile(&path, &pts, q as u16);
        tiles.push(path);
    }
    let mut base = options(&tiles[0], &dir.path().join("whole.vdag"), 6, "-1,-1,-1,2");
    base.extra_inputs = tiles[1..].to_vec();
    base.colors = true;
    convert(&base).unwrap();
    let whole = std::fs::read(&base.output).unwrap();
    let mut parts = Vec::new();
    for r in Region::all(1) {
        let mut o = base.clone();
        o.region = Some(r);
        o.output = dir.path().join(format!("p{}.part", r.index()));
        let s = convert(&o).unwrap();
        assert!(
            s.input.contains("3 more left out"),
            "region {r} read more than its tile: {}",
            s.input
        );
        parts.push(o.output);
    }
    assert_eq!(merged(&parts, &dir.path().join("m.vdag")), whole);
    // The command line reads several tiles as one cloud too.
    let cli = dir.path().join("cli.vdag");
    let mut args = vec!["convert"];
    args.extend(tiles.iter().map(|t| t.to_str().unwrap()));
    args.extend([
        "-o",
        cli.to_str().unwrap(),
        "--depth",
        "6",
        "--bounds",
        "-1,-1,-1,2",
        "--colors",
        "-q",
    ]);
    let out = run(&args);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(std::fs::read(&cli).unwrap(), whole);
}
