//! `dagtool verify`: a conversion passes against its own mesh, and fails
//! against a different or moved mesh.

use std::path::Path;

use crate::common::{ObjMesh, box_mesh, convert, run, sphere_mesh};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Runs `verify --json` and returns the exit code and the report.
fn verify_json(mesh: &Path, file: &Path, rays: usize) -> (Option<i32>, serde_json::Value) {
    let n = rays.to_string();
    let o = run(&["verify", s(mesh), s(file), "--rays", &n, "--json"]);
    let doc = serde_json::from_slice(&o.stdout).unwrap_or_else(|e| {
        panic!(
            "verify printed no JSON ({e}): {}\n{}",
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        )
    });
    (o.status.code(), doc)
}

/// A closed mesh: a sphere with a box fused onto it (concave corners, flat
/// axis-aligned faces, curved parts).
fn sample_mesh() -> ObjMesh {
    let mut m = sphere_mesh([0.0; 3], 1.0, 3);
    m.append(&box_mesh([0.3, -0.35, -0.3], [1.6, 0.25, 0.4]));
    m
}

fn criterion(doc: &serde_json::Value, name: &str) -> bool {
    doc["criteria"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["name"] == name)
        .unwrap_or_else(|| panic!("no criterion {name}: {doc}"))["passed"]
        .as_bool()
        .unwrap()
}

#[test]
fn a_conversion_verifies_against_its_mesh() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("m.obj");
    sample_mesh().write(&obj);
    for depth in [5u8, 7] {
        let file = dir.path().join(format!("m{depth}.vdag"));
        convert(&obj, &file, depth, &[]);
        let (code, doc) = verify_json(&obj, &file, 20_000);
        assert_eq!(code, Some(0), "depth {depth}: {doc:#}");
        assert_eq!(doc["passed"], true);
        assert_eq!(doc["depth"], depth);
        assert_eq!(doc["placement_offset_voxels"].as_f64(), Some(0.0));
        let rays = &doc["rays"];
        assert_eq!(
            rays["total"].as_u64(),
            Some(20_000),
            "random rays make up the total: {doc:#}"
        );
        assert!(rays["camera"].as_u64().unwrap() > 9_000);
        // Real numbers: most rays count, many hit, errors within a few voxels.
        let included = doc["agreement"]["included"].as_u64().unwrap();
        assert!(included > 15_000, "{doc:#}");
        assert!(doc["agreement"]["percent"].as_f64().unwrap() >= 99.9);
        let clean = doc["hits"]["clean"].as_u64().unwrap();
        assert!(clean > 5_000, "{doc:#}");
        let err = &doc["error_voxels"];
        let (median, max) = (
            err["median"].as_f64().unwrap(),
            err["max"].as_f64().unwrap(),
        );
        assert!(median > 0.0 && median < 1.5, "{doc:#}");
        assert!(max < 4.0 * 3f64.sqrt() + 0.5, "{doc:#}");
        assert!(doc["depth_error_voxels"]["max"].as_f64().unwrap() <= 3f64.sqrt() + 0.2);
        // The DAG is never behind the mesh (beyond rounding).
        assert!(doc["max_late_voxels"].as_f64().unwrap() < 0.1, "{doc:#}");
        // The file is 2.0 (the default); its 1.0 form verifies with the same
        // findings, ray for ray (the tracer's answers are the same).
        let bytes = std::fs::read(&file).unwrap();
        assert_eq!(dagfmt::AnyDag::open(&bytes).unwrap().version_major(), 2);
        let v1 = dir.path().join(format!("m{depth}-v1.vdag"));
        convert(&obj, &v1, depth, &["--format-version", "1"]);
        let (code1, doc1) = verify_json(&obj, &v1, 20_000);
        assert_eq!(code1, Some(0));
        for key in [
            "rays",
            "agreement",
            "hits",
            "error_voxels",
            "depth_error_voxels",
            "max_late_voxels",
            "criteria",
        ] {
            assert_eq!(doc[key], doc1[key], "depth {depth}: {key}");
        }
    }
}

#[test]
fn the_text_report_names_the_criteria() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("m.obj");
    sample_mesh().write(&obj);
    let file = dir.path().join("m.vdag");
    convert(&obj, &file, 5, &[]);
    let o = run(&["verify", s(&obj), s(&file), "--rays", "2000", "--seed", "7"]);
    assert_eq!(o.status.code(), Some(0));
    let text = String::from_utf8_lossy(&o.stdout);
    for needle in [
        "PASS agreement",
        "PASS no-late-hits",
        "PASS hit-points-near-surface",
        "PASS depth-error",
        "verify: PASS",
    ] {
        assert!(text.contains(needle), "{needle} missing:\n{text}");
    }
}

#[test]
fn a_moved_or_different_mesh_fails() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("m.obj");
    let mesh = sample_mesh();
    mesh.write(&obj);
    let file = dir.path().join("m.vdag");
    convert(&obj, &file, 6, &[]);

    // The same mesh moved by about 3 voxels along x (the cube is ~2.6 units / 64 voxels).
    let mut moved = mesh.clone();
    for v in &mut moved.vertices {
        v[0] += 0.12;
    }
    let moved_obj = dir.path().join("moved.obj");
    moved.write(&moved_obj);
    let (code, doc) = verify_json(&moved_obj, &file, 20_000);
    assert_eq!(code, Some(1), "{doc:#}");
    assert_eq!(doc["passed"], false);
    assert!(doc["placement_offset_voxels"].as_f64().unwrap() > 2.0);
    assert!(!criterion(&doc, "agreement"), "{doc:#}");
    assert!(!criterion(&doc, "no-late-hits"), "{doc:#}");

    // A different mesh in the same place: a sphere alone.
    let sphere_obj = dir.path().join("sphere.obj");
    sphere_mesh([0.0; 3], 1.0, 3).write(&sphere_obj);
    let (code, doc) = verify_json(&sphere_obj, &file, 20_000);
    assert_eq!(code, Some(1), "{doc:#}");
    assert!(!criterion(&doc, "hit-points-near-surface"), "{doc:#}");
}

#[test]
fn bad_input_is_a_one_line_error_with_status_2() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("m.obj");
    sample_mesh().write(&obj);
    let file = dir.path().join("m.vdag");
    convert(&obj, &file, 4, &[]);
    let missing = dir.path().join("missing.vdag");
    let not_a_dag = dir.path().join("x.vdag");
    std::fs::write(&not_a_dag, b"not a dag at all").unwrap();
    let empty_obj = dir.path().join("empty.obj");
    std::fs::write(&empty_obj, b"# nothing\n").unwrap();
    for args in [
        vec!["verify", s(&obj), s(&missing)],
        vec!["verify", s(&obj), s(&not_a_dag)],
        vec!["verify", s(&empty_obj), s(&file)],
        vec!["verify", s(&obj), s(&file), "--rays", "0"],
        vec!["verify", s(&obj), s(&file), "--rays", "many"],
        vec!["verify", s(&obj), s(&file), "--rays", "60000000"],
    ] {
        let o = run(&args);
        assert_eq!(o.status.code(), Some(2), "{args:?}");
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(err.lines().count(), 1, "{args:?}: {err}");
        assert!(err.starts_with("dagtool: error: "), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
}

/// The shared closed meshes at a small depth (skipped without ../shared/meshes).
#[test]
fn shared_closed_meshes_verify() {
    let Some(meshes) = crate::common::meshes_dir() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    for name in ["cow", "spot"] {
        let obj = meshes.join(format!("{name}.obj"));
        let file = dir.path().join(format!("{name}.vdag"));
        convert(&obj, &file, 8, &[]);
        let (code, doc) = verify_json(&obj, &file, 20_000);
        assert_eq!(code, Some(0), "{name}: {doc:#}");
    }
}
