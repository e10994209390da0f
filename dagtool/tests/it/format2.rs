//! Format 2.0 through the command line (spec §23.11): `convert` (2.0 by
//! default, 1.0 with `--format-version 1`), `upgrade` both ways,
//! `--attributes none`, and `validate`, `info` and `dump` on 2.0 files.

use std::path::Path;

use crate::common::{box_mesh, convert, run, run_ok, sphere_mesh, voxel_codes};

/// The voxels (Morton codes), attribute kind and colour bytes of a file of
/// either version.
fn contents(path: &Path) -> (Vec<u64>, u8, Option<Vec<u8>>, u16) {
    let bytes = std::fs::read(path).unwrap();
    let dag = dagfmt::AnyDag::open(&bytes).unwrap();
    let colors = dag.color_table().map(|t| t.iter().flatten().collect());
    (
        dag.voxel_codes().unwrap(),
        dag.header().attribute_kind.to_raw(),
        colors,
        dag.version_major(),
    )
}

fn scene(dir: &Path) -> std::path::PathBuf {
    // A sphere and a box: mirror symmetries for the 2.0 merge to find.
    let mut mesh = sphere_mesh([0.0, 0.0, 0.0], 1.0, 2);
    mesh.append(&box_mesh([1.2, -0.5, -0.5], [1.8, 0.5, 0.5]));
    let path = dir.join("scene.obj");
    mesh.write(&path);
    path
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn convert_and_upgrade_round_trip_between_the_versions() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = scene(dir.path());
    let v1 = dir.path().join("a1.vdag");
    let v2 = dir.path().join("a2.vdag");
    convert(&mesh, &v1, 7, &["--colors", "--format-version", "1"]);
    convert(&mesh, &v2, 7, &["--colors"]);
    let (codes, kind, colors, version) = contents(&v1);
    assert_eq!(version, 1);
    assert!(codes.len() > 1000, "a real scene: {} voxels", codes.len());
    assert_eq!(contents(&v2), (codes.clone(), kind, colors.clone(), 2));
    let b1 = std::fs::read(&v1).unwrap();
    let b2 = std::fs::read(&v2).unwrap();
    assert!(
        b2.len() < b1.len(),
        "2.0 {} bytes, 1.0 {}",
        b2.len(),
        b1.len()
    );
    for f in [&v1, &v2] {
        run_ok(&["validate", s(f)]);
    }
    // The default is 2.0: `--format-version 2` writes the same bytes.
    let explicit = dir.path().join("explicit.vdag");
    convert(&mesh, &explicit, 7, &["--colors", "--format-version", "2"]);
    assert_eq!(std::fs::read(&explicit).unwrap(), b2);
    // Out of core (a spilled 1.0 build, and a 2.0 encoding whose tables all
    // go to the scratch file), the 2.0 output is the same, byte for byte, and
    // no temporary file is left.
    let spilled = dir.path().join("spilled.vdag");
    let tmp = dir.path().join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    convert(
        &mesh,
        &spilled,
        7,
        &[
            "--colors",
            "--spill-cells-per-run",
            "2",
            "--spill-buckets",
            "5",
            "--tmp-dir",
            s(&tmp),
        ],
    );
    assert_eq!(std::fs::read(&spilled).unwrap(), b2);
    assert_eq!(std::fs::read_dir(&tmp).unwrap().count(), 0);
    // upgrade 1 -> 2 gives what convert --format-version 2 wrote, and 2 -> 1
    // gives the original 1.0 bytes back.
    let up = dir.path().join("up.vdag");
    let down = dir.path().join("down.vdag");
    run_ok(&["upgrade", s(&v1), "-o", s(&up)]);
    assert_eq!(std::fs::read(&up).unwrap(), b2);
    run_ok(&["upgrade", s(&v2), "-o", s(&down), "--format-version", "1"]);
    assert_eq!(std::fs::read(&down).unwrap(), b1);
    // Nothing is overwritten without --force.
    let out = run(&["upgrade", s(&v1), "-o", s(&up)]);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("exists") && err.lines().count() == 1, "{err}");
    run_ok(&["upgrade", s(&v1), "-o", s(&up), "--force"]);
    // A file already of the version asked for is copied unchanged.
    let same = dir.path().join("same.vdag");
    let out = run_ok(&["upgrade", s(&v2), "-o", s(&same)]);
    assert!(String::from_utf8_lossy(&out.stdout).contains("copied"));
    assert_eq!(std::fs::read(&same).unwrap(), b2);
}

#[test]
fn attributes_none_in_both_versions() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = scene(dir.path());
    let counts = dir.path().join("counts.vdag");
    convert(&mesh, &counts, 6, &["--format-version", "1"]);
    let (codes, kind, _, _) = contents(&counts);
    assert_eq!(kind, 1);
    for version in ["1", "2"] {
        let none = dir.path().join(format!("none{version}.vdag"));
        convert(
            &mesh,
            &none,
            6,
            &["--attributes", "none", "--format-version", version],
        );
        run_ok(&["validate", s(&none)]);
        let (c, k, colors, v) = contents(&none);
        assert_eq!(
            (c, k, colors, v.to_string()),
            (codes.clone(), 0, None, version.to_string())
        );
    }
    // A 1.0 file without attributes is smaller than with them only in its
    // attribute bits (zero): the same size.
    assert_eq!(
        std::fs::metadata(dir.path().join("none1.vdag"))
            .unwrap()
            .len(),
        std::fs::metadata(&counts).unwrap().len()
    );
    // Colours need the counts.
    let out = run(&[
        "convert",
        s(&mesh),
        "-o",
        s(&dir.path().join("x.vdag")),
        "--depth",
        "6",
        "--colors",
        "--attributes",
        "none",
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(!dir.path().join("x.vdag").exists());
}

#[test]
fn info_dump_and_validate_read_2_0_files() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = scene(dir.path());
    let v1 = dir.path().join("b1.vdag");
    let v2 = dir.path().join("b2.vdag");
    convert(&mesh, &v1, 6, &["--format-version", "1"]);
    convert(&mesh, &v2, 6, &[]);
    let info = String::from_utf8(run_ok(&["info", s(&v2), "--json"]).stdout).unwrap();
    let doc: serde_json::Value = serde_json::from_str(&info).unwrap();
    let info1 = String::from_utf8(run_ok(&["info", s(&v1), "--json"]).stdout).unwrap();
    let doc1: serde_json::Value = serde_json::from_str(&info1).unwrap();
    assert_eq!(doc["version"][0], 2);
    assert_eq!(doc["file_bytes"], std::fs::metadata(&v2).unwrap().len());
    // The same voxels: the same classic, 1.0 and SSVDAG sizes from either file.
    for key in [
        "classic_svdag_bytes",
        "v1_bytes",
        "ssvdag_bytes",
        "voxel_count",
    ] {
        assert_eq!(doc[key], doc1[key], "{key}");
    }
    assert_eq!(doc1["v1_bytes"], std::fs::metadata(&v1).unwrap().len());
    assert_eq!(doc["v2_levels"].as_array().unwrap().len(), 5);
    let text = String::from_utf8(run_ok(&["info", s(&v2)]).stdout).unwrap();
    assert!(
        text.contains("this file (2.0)") && text.contains("SSVDAG"),
        "{text}"
    );
    let dump = String::from_utf8(run_ok(&["dump", s(&v2), "--nodes", "2"]).stdout).unwrap();
    assert!(
        dump.contains("widths = ") && dump.contains("record 0"),
        "{dump}"
    );
    // validate reports a 2.0 rule with its code.
    let mut bytes = std::fs::read(&v2).unwrap();
    let entry1 = 128 + 40;
    bytes[entry1 + 7] = 41; // w_3 over 40 bits
    let bad = dir.path().join("bad.vdag");
    std::fs::write(&bad, &bytes).unwrap();
    let out = run(&["validate", s(&bad)]);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stdout).contains("E070"));
    // The voxel helper of the other tests reads either version alike.
    assert!(!voxel_codes(&v1).is_empty());
    assert_eq!(voxel_codes(&v2), voxel_codes(&v1));
}
