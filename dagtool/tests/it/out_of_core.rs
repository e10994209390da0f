//! The out-of-core build (`dagtool::external`): a conversion that spills its
//! DAG to temporary files in runs and merges them makes the same file as the
//! in-memory build (the same distinct nodes per level, section lengths,
//! widths, voxels and colours; in fact the same bytes), its temporary files
//! leave nothing behind, and a bad `--tmp-dir` is a clean error.

use std::path::Path;

use dagfmt::AnyDag;
use dagfmt::assemble::{FileHeader, FileLayout};
use dagfmt::builder::DagBuilder;
use dagfmt::layout::AttributeKind;
use dagtool::external::{DagSink, Scratch, SpillSettings};
use proptest::prelude::*;

use crate::common::{
    ObjMesh, box_mesh, colour_bytes, dir_entries, meshes_dir, run, run_ok, sphere_mesh,
};
use crate::surface::Lcg;

/// Builds the DAG of `voxels` through a [`DagSink`] with `settings`, and
/// writes it the way the converter does.
fn sink_bytes(
    depth: u8,
    attributes: AttributeKind,
    voxels: &[[u32; 3]],
    settings: SpillSettings,
    tmp: &Path,
) -> (Vec<u8>, u64) {
    let mut codes: Vec<u64> = voxels
        .iter()
        .map(|v| dagfmt::morton::encode(v[0], v[1], v[2]))
        .collect();
    codes.sort_unstable();
    codes.dedup();
    let scratch = Scratch::new(tmp).unwrap();
    let mut sink = DagSink::new(depth, attributes, settings, &scratch).unwrap();
    let mut i = 0;
    while i < codes.len() {
        let brick = codes[i] >> 6;
        let mut mask = 0u64;
        while i < codes.len() && codes[i] >> 6 == brick {
            mask |= 1 << (codes[i] & 63);
            i += 1;
        }
        sink.push_brick(brick, mask).unwrap();
    }
    // A small merge budget: the forced bucket count decides anyway.
    let dag = sink.finish(|| 1 << 20, &|_| {}).unwrap();
    let runs = dag.report().runs;
    let header = FileHeader {
        depth,
        attributes,
        root_min: [0.0; 3],
        root_size: 1.0,
        voxel_count: dag.voxel_count(),
    };
    let layout = FileLayout::new(header, dag.level_sections()).unwrap();
    let mut bytes = Vec::new();
    layout
        .write_to(&mut bytes, |i, sink| dag.emit_level(i, sink))
        .unwrap();
    (bytes, runs)
}

/// The voxels of a file of either version, in Morton order.
fn voxels_of(dag: &AnyDag<'_>) -> Vec<u64> {
    dag.voxel_codes().unwrap()
}

/// Asserts that two files hold the same DAG level by level (distinct nodes,
/// bytes and pointer or reference widths of every section), the same voxels
/// and the same
/// colour per voxel, that both validate, and finally that they are the same
/// bytes (the merge lays every level out in the in-memory build's order).
fn assert_same_dag(in_core: &[u8], external: &[u8], what: &str) {
    assert!(
        dagfmt::validate::validate(in_core).is_empty(),
        "{what}: in-core file invalid"
    );
    let report = dagfmt::validate::validate(external);
    assert!(
        report.is_empty(),
        "{what}: out-of-core file invalid: {report:?}"
    );
    let (a, b) = (
        AnyDag::open(in_core).unwrap(),
        AnyDag::open(external).unwrap(),
    );
    assert_eq!(a.version_major(), b.version_major(), "{what}: version");
    assert_eq!(a.sections().len(), b.sections().len(), "{what}: sections");
    for (sa, sb) in a.sections().iter().zip(b.sections()) {
        assert_eq!(
            (
                sa.kind,
                sa.level,
                sa.item_count,
                sa.length,
                sa.pointer_width,
                sa.widths
            ),
            (
                sb.kind,
                sb.level,
                sb.item_count,
                sb.length,
                sb.pointer_width,
                sb.widths
            ),
            "{what}: section of level {}",
            sa.level
        );
    }
    let (va, vb) = (voxels_of(&a), voxels_of(&b));
    assert_eq!(va.len(), vb.len(), "{what}: voxel count");
    assert!(va == vb, "{what}: voxel sets differ");
    assert_eq!(
        colour_bytes(&a),
        colour_bytes(&b),
        "{what}: colours per voxel"
    );
    assert!(in_core == external, "{what}: bytes differ");
}

fn random_voxels(rng: &mut Lcg, n: usize, side: u32, clustered: bool) -> Vec<[u32; 3]> {
    let mut out = Vec::with_capacity(n);
    let mut centre = [0u32; 3];
    for i in 0..n {
        if clustered && i % 64 == 0 {
            centre = [0, 1, 2].map(|_| (rng.next_f64() * f64::from(side)) as u32);
        }
        out.push([0, 1, 2].map(|k| {
            if clustered {
                let d = (rng.next_f64() * 9.0) as u32;
                (centre[k] + d).min(side - 1)
            } else {
                (rng.next_f64() * f64::from(side)) as u32
            }
        }));
    }
    out
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// The core property of the merge: random voxel sets (scattered, or in
    /// clumps that share subtrees), random split levels, random run
    /// boundaries and bucket counts, both attribute kinds: the same file as
    /// one in-memory build.
    #[test]
    fn runs_merge_into_the_in_memory_file(
        depth in 3u8..=9,
        split_pick in 0u8..8,
        cells_per_run in 1u64..6,
        buckets in 1u32..10,
        n in 1usize..1500,
        clustered in any::<bool>(),
        counts in any::<bool>(),
        seed in any::<u64>(),
    ) {
        let split = 1 + split_pick % (depth - 2);
        let attributes = if counts { AttributeKind::VoxelCount } else { AttributeKind::None };
        let mut rng = Lcg(seed);
        let voxels = random_voxels(&mut rng, n, 1 << depth, clustered);
        let expected = DagBuilder::from_voxels(depth, attributes, voxels.iter().copied())
            .unwrap()
            .to_bytes();
        let tmp = tempfile::tempdir().unwrap();
        let settings = SpillSettings {
            split_level: split,
            run_budget: 0,
            cells_per_run: Some(cells_per_run),
            buckets: Some(buckets),
        };
        let (bytes, runs) = sink_bytes(depth, attributes, &voxels, settings, tmp.path());
        prop_assert!(runs >= 1);
        assert_same_dag(&expected, &bytes, &format!(
            "depth {depth} split {split} cells/run {cells_per_run} buckets {buckets} n {n}"
        ));
        prop_assert!(dir_entries(tmp.path()).is_empty());
    }
}

#[test]
fn a_tiny_run_budget_spills_at_every_cell_and_sizes_the_buckets() {
    // No forced shape: the run budget (0) ends a run at every cell boundary
    // and the 1 MiB merge budget (raised to the minimum) sizes the buckets.
    let mut rng = Lcg(5);
    let voxels = random_voxels(&mut rng, 40_000, 1 << 10, false);
    let expected = DagBuilder::from_voxels(10, AttributeKind::VoxelCount, voxels.iter().copied())
        .unwrap()
        .to_bytes();
    let tmp = tempfile::tempdir().unwrap();
    let settings = SpillSettings {
        split_level: 3,
        run_budget: 0,
        cells_per_run: None,
        buckets: None,
    };
    let (bytes, runs) = sink_bytes(10, AttributeKind::VoxelCount, &voxels, settings, tmp.path());
    assert_eq!(runs, 512, "one run per level-3 cell");
    assert_same_dag(&expected, &bytes, "budget-driven runs");
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Converts `input` in memory and with forced spills of each shape; every
/// out-of-core file must equal the in-memory one.
fn check_conversions(input: &Path, depth: u8, extra: &[&str], shapes: &[&[&str]]) {
    let dir = tempfile::tempdir().unwrap();
    let tmp = dir.path().join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    let d = depth.to_string();
    let reference = dir.path().join("in-core.vdag");
    let mut args = vec![
        "convert",
        s(input),
        "-o",
        s(&reference),
        "--depth",
        &d,
        "-q",
    ];
    args.extend_from_slice(extra);
    run_ok(&args);
    let in_core = std::fs::read(&reference).unwrap();
    for shape in shapes {
        let out = dir.path().join("external.vdag");
        let mut args = vec![
            "convert",
            s(input),
            "-o",
            s(&out),
            "--depth",
            &d,
            "--tmp-dir",
            s(&tmp),
            "--force",
        ];
        args.extend_from_slice(extra);
        args.extend_from_slice(shape);
        let o = run_ok(&args);
        let summary = String::from_utf8_lossy(&o.stdout);
        assert!(summary.contains("spilled"), "{summary}");
        assert!(
            summary.contains("written to unnamed temporary files"),
            "{summary}"
        );
        let what = format!("{} depth {depth} {extra:?} {shape:?}", input.display());
        assert_same_dag(&in_core, &std::fs::read(&out).unwrap(), &what);
        assert!(dir_entries(&tmp).is_empty(), "{what}: temporary files left");
    }
}

const SHAPES: &[&[&str]] = &[
    &["--spill-split-level", "1", "--spill-buckets", "3"],
    &["--spill-cells-per-run", "2", "--spill-buckets", "5"],
    &[
        "--spill-split-level",
        "3",
        "--spill-cells-per-run",
        "1",
        "--spill-buckets",
        "17",
    ],
];

#[test]
fn procedural_meshes_out_of_core() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Lcg(3);
    let mut mix = sphere_mesh([0.0, 0.0, 0.0], 2.0, 3);
    mix.append(&box_mesh([-1.0, -0.5, -3.0], [3.0, 0.5, -1.5]));
    let mut loose = ObjMesh::default();
    for _ in 0..30 {
        let p = [0, 1, 2].map(|_| [0, 1, 2].map(|_| rng.next_f64() * 6.0 - 3.0));
        loose.add_triangle(p[0], p[1], p[2]);
    }
    let mut open = mix.clone();
    open.append(&loose);
    let open_obj = dir.path().join("open.obj");
    open.write(&open_obj);
    // A closed mesh with two materials, so that --colors has more than one
    // colour: the sphere red, the box blue.
    let closed_obj = dir.path().join("closed.obj");
    let sphere = sphere_mesh([0.0, 0.0, 0.0], 2.0, 3);
    let mut both = sphere.clone();
    both.append(&box_mesh([-1.0, -0.5, -3.0], [3.0, 0.5, -1.5]));
    let mut text = String::from("mtllib m.mtl\nusemtl red\n");
    let mut face = 0;
    for line in both.to_obj().lines() {
        if line.starts_with("f ") {
            if face == sphere.faces.len() {
                text.push_str("usemtl blue\n");
            }
            face += 1;
        }
        text.push_str(line);
        text.push('\n');
    }
    std::fs::write(&closed_obj, text).unwrap();
    std::fs::write(
        dir.path().join("m.mtl"),
        "newmtl red\nKd 1 0 0\nnewmtl blue\nKd 0 0 1\n",
    )
    .unwrap();
    check_conversions(&open_obj, 9, &[], SHAPES);
    check_conversions(&closed_obj, 10, &["--colors"], SHAPES);
    check_conversions(&closed_obj, 8, &["--solid", "--colors"], SHAPES);
    check_conversions(&open_obj, 7, &["--solid"], SHAPES);
    check_conversions(&open_obj, 5, &["--chunk-bits", "3"], SHAPES);
}

#[test]
fn voxel_lists_out_of_core() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Lcg(11);
    for (depth, n, clustered) in [(5u8, 300, false), (8, 20_000, true), (12, 60_000, false)] {
        let voxels = random_voxels(&mut rng, n, 1 << depth, clustered);
        let list = dir.path().join(format!("v{depth}.bin"));
        let mut f = std::fs::File::create(&list).unwrap();
        dagtool::voxlist::write_binary(&mut f, depth, &voxels).unwrap();
        drop(f);
        check_conversions(&list, depth, &[], SHAPES);
    }
}

#[test]
fn real_meshes_out_of_core() {
    let Some(meshes) = meshes_dir() else { return };
    check_conversions(&meshes.join("cow.obj"), 10, &[], SHAPES);
    check_conversions(&meshes.join("suzanne.obj"), 9, &["--solid"], SHAPES);
    check_conversions(&meshes.join("teapot.obj"), 9, &["--colors"], SHAPES);
}

/// The summary's figure for `label` ("peak RSS: 1.2 MiB (1234 bytes)").
fn summary_bytes(summary: &str, label: &str) -> u64 {
    let line = summary
        .lines()
        .find(|l| l.starts_with(label))
        .unwrap_or_else(|| panic!("no {label} line in {summary}"));
    let inner = &line[line.rfind('(').unwrap() + 1..];
    inner.split(' ').next().unwrap().parse().unwrap()
}

#[test]
fn the_memory_limit_sizes_the_build_and_bounds_the_peak() {
    // 800 000 scattered voxels at depth 13: about 1.6 M distinct nodes, some
    // 65 MB resident when built in memory. Under a 48 MiB limit the converter
    // spills (for real: no forced shape), stays under the limit, and still
    // makes the in-memory file.
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Lcg(21);
    let voxels = random_voxels(&mut rng, 800_000, 1 << 13, false);
    let list = dir.path().join("v.bin");
    let mut f = std::fs::File::create(&list).unwrap();
    dagtool::voxlist::write_binary(&mut f, 13, &voxels).unwrap();
    drop(f);
    let limit = 48u64 << 20;
    let in_core = dir.path().join("a.vdag");
    let o = run_ok(&["convert", s(&list), "-o", s(&in_core)]);
    let summary = String::from_utf8_lossy(&o.stdout);
    assert!(summary.contains("built in memory"), "{summary}");
    assert!(
        summary_bytes(&summary, "peak RSS:") > limit,
        "the test needs an in-memory build over the limit: {summary}"
    );
    let external = dir.path().join("b.vdag");
    let o = run_ok(&[
        "convert",
        s(&list),
        "-o",
        s(&external),
        "--memory-limit",
        "48M",
    ]);
    let summary = String::from_utf8_lossy(&o.stdout);
    assert!(summary.contains("spilled"), "{summary}");
    assert!(summary_bytes(&summary, "peak RSS:") < limit, "{summary}");
    assert!(!summary.contains("warning"), "{summary}");
    assert_same_dag(
        &std::fs::read(&in_core).unwrap(),
        &std::fs::read(&external).unwrap(),
        "48 MiB limit",
    );
    assert_eq!(
        dir_entries(dir.path()),
        ["a.vdag", "b.vdag", "v.bin"],
        "no temporary files left"
    );
}

/// Runs `args`, expecting one `dagtool: error:` line with `status`; returns it.
fn one_line_error(args: &[&str], status: i32) -> String {
    let o = run(args);
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(o.status.code(), Some(status), "dagtool {args:?}: {stderr}");
    assert_eq!(stderr.lines().count(), 1, "{stderr:?}");
    assert!(stderr.starts_with("dagtool: error: "), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(o.stdout.is_empty());
    stderr
}

#[test]
fn a_bad_tmp_dir_is_refused_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let obj = d.join("cube.obj");
    box_mesh([0.0; 3], [1.0; 3]).write(&obj);
    let out = d.join("out.vdag");
    let missing = d.join("no-such-dir");
    let refused = |tmp: &str| {
        one_line_error(
            &[
                "convert",
                s(&obj),
                "-o",
                s(&out),
                "--depth",
                "6",
                "--tmp-dir",
                tmp,
            ],
            1,
        )
    };
    let msg = refused(s(&missing));
    assert!(
        msg.contains("does not exist") && msg.contains(s(&missing)),
        "{msg}"
    );
    let msg = refused(s(&obj));
    assert!(
        msg.contains("not a directory") && msg.contains(s(&obj)),
        "{msg}"
    );
    // A directory nobody can create files in (root included).
    if Path::new("/proc/self").is_dir() {
        let msg = refused("/proc");
        assert!(
            msg.contains("cannot create temporary files in /proc"),
            "{msg}"
        );
    }
    assert_eq!(dir_entries(d), ["cube.obj"], "nothing written");
}

#[test]
fn an_unwritable_output_directory_is_refused_before_any_work() {
    // With the temporary files elsewhere, the output's directory is still
    // checked before voxelizing, not after.
    if !Path::new("/proc/self").is_dir() {
        eprintln!("skipping: no /proc");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("cube.obj");
    box_mesh([0.0; 3], [1.0; 3]).write(&obj);
    let tmp = dir.path().join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    let msg = one_line_error(
        &[
            "convert",
            s(&obj),
            "-o",
            "/proc/out.vdag",
            "--depth",
            "6",
            "--tmp-dir",
            s(&tmp),
        ],
        1,
    );
    assert!(
        msg.contains("cannot create files in output directory /proc"),
        "{msg}"
    );
    assert!(dir_entries(&tmp).is_empty());
}

#[test]
fn a_failed_spill_leaves_no_file() {
    // Temporary files over the file-size limit fail with EFBIG, as a full
    // disk fails with ENOSPC: a one-line error naming the temporary
    // directory, and neither an output nor a temporary file is left.
    let dir = tempfile::tempdir().unwrap();
    let (out_dir, tmp) = (dir.path().join("out"), dir.path().join("tmp"));
    std::fs::create_dir(&out_dir).unwrap();
    std::fs::create_dir(&tmp).unwrap();
    let mut rng = Lcg(8);
    let voxels = random_voxels(&mut rng, 20_000, 1 << 9, false);
    let list = dir.path().join("v.bin");
    let mut f = std::fs::File::create(&list).unwrap();
    dagtool::voxlist::write_binary(&mut f, 9, &voxels).unwrap();
    drop(f);
    let out = out_dir.join("v.vdag");
    let mut command = crate::common::dagtool();
    command.args([
        "convert",
        s(&list),
        "-o",
        s(&out),
        "--tmp-dir",
        s(&tmp),
        "--spill-cells-per-run",
        "1",
        "-q",
    ]);
    let o = crate::bad_input::with_file_size_limit(&command)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{stderr}");
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(
        stderr.contains("cannot write temporary files in") && stderr.contains(s(&tmp)),
        "{stderr}"
    );
    assert!(stderr.contains("File too large"), "{stderr}");
    assert!(dir_entries(&out_dir).is_empty());
    assert!(dir_entries(&tmp).is_empty());
}

#[test]
fn the_minimal_working_set_is_a_clear_error() {
    // Enough memory to load a small mesh, not enough for the buffers and a
    // DAG builder: refused before voxelizing, with what it needs.
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("sphere.obj");
    sphere_mesh([0.0; 3], 1.0, 3).write(&obj);
    let out = dir.path().join("out.vdag");
    let msg = one_line_error(
        &[
            "convert",
            s(&obj),
            "-o",
            s(&out),
            "--depth",
            "9",
            "--memory-limit",
            "32M",
        ],
        1,
    );
    assert!(
        msg.contains("memory limit of 32.00 MiB is below the minimal working set"),
        "{msg}"
    );
    assert!(msg.contains("raise --memory-limit"), "{msg}");
    assert_eq!(dir_entries(dir.path()), ["sphere.obj"]);
}
