//! Bad input: one `dagtool: error: ...` line, a non-zero exit status, no
//! output file and no temporary file left behind.

use std::path::Path;

use crate::common::{box_mesh, dir_entries, run};

/// Runs `args` and asserts the failure contract; returns the message.
fn fails(args: &[&str], out_dir: &Path, status: i32) -> String {
    let before = dir_entries(out_dir);
    let o = run(args);
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    assert_eq!(o.status.code(), Some(status), "dagtool {args:?}: {stderr}");
    assert_eq!(
        stderr.lines().count(),
        1,
        "one line on stderr, got: {stderr:?}"
    );
    assert!(stderr.starts_with("dagtool: error: "), "{stderr:?}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(o.stdout.is_empty(), "nothing on stdout");
    assert_eq!(
        dir_entries(out_dir),
        before,
        "the output directory is unchanged"
    );
    stderr
}

fn write(dir: &Path, name: &str, text: &str) -> String {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p.to_str().unwrap().to_string()
}

#[test]
fn bad_meshes() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = d.join("out.vdag");
    let out = out.to_str().unwrap();
    let cases: &[(&str, &str, &str)] = &[
        (
            "nan.obj",
            "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n",
            "non-finite",
        ),
        (
            "inf.obj",
            "v 0 0 0\nv 1 0 0\nv 0 inf 0\nf 1 2 3\n",
            "non-finite",
        ),
        (
            "degenerate.obj",
            "v 0 0 0\nv 1 1 1\nv 2 2 2\nv 3 3 3\nf 1 2 3\nf 2 3 4\nf 1 1 4\n",
            "degenerate",
        ),
        (
            "bad-index.obj",
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n",
            "cannot read OBJ",
        ),
        ("garbage.obj", "v 0 0 zero\nf 1 2 3\n", "cannot read OBJ"),
    ];
    for (name, text, expected) in cases {
        let input = write(d, name, text);
        let msg = fails(&["convert", &input, "-o", out, "--depth", "6"], d, 1);
        assert!(msg.contains(expected), "{name}: {msg}");
    }
}

#[test]
fn bad_arguments() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let obj = d.join("cube.obj");
    box_mesh([0.0; 3], [1.0; 3]).write(&obj);
    let obj = obj.to_str().unwrap();
    let out = d.join("out.vdag");
    let out = out.to_str().unwrap();
    let msg = fails(&["convert", obj, "-o", out, "--depth", "22"], d, 2);
    assert!(msg.contains("depth 22 is outside 2..=21"), "{msg}");
    let msg = fails(&["convert", obj, "-o", out, "--depth", "1"], d, 2);
    assert!(msg.contains("outside 2..=21"), "{msg}");
    let msg = fails(&["convert", obj, "-o", out, "--resolution", "1000"], d, 2);
    assert!(msg.contains("not a power of two"), "{msg}");
    let msg = fails(
        &["convert", obj, "-o", out, "--resolution", "4194304"],
        d,
        2,
    );
    assert!(msg.contains("outside"), "{msg}");
    let msg = fails(&["convert", obj, "-o", out], d, 2);
    assert!(msg.contains("--depth"), "{msg}");
    let msg = fails(
        &[
            "convert",
            obj,
            "-o",
            out,
            "--depth",
            "5",
            "--memory-limit",
            "lots",
        ],
        d,
        2,
    );
    assert!(msg.contains("--memory-limit"), "{msg}");
    let msg = fails(
        &[
            "convert",
            obj,
            "-o",
            out,
            "--depth",
            "5",
            "--chunk-bits",
            "9",
        ],
        d,
        2,
    );
    assert!(msg.contains("chunk"), "{msg}");
    let msg = fails(
        &["convert", obj, "-o", out, "--depth", "5", "--no-such-flag"],
        d,
        2,
    );
    assert!(msg.contains("--no-such-flag"), "{msg}");
    let msg = fails(
        &[
            "convert",
            obj,
            "-o",
            out,
            "--depth",
            "5",
            "--resolution",
            "32",
        ],
        d,
        2,
    );
    assert!(msg.contains("cannot be used with"), "{msg}");
    let unknown = write(d, "mesh.fbx", "solid x\n");
    let msg = fails(&["convert", &unknown, "-o", out, "--depth", "5"], d, 2);
    assert!(msg.contains("--input-format"), "{msg}");
}

#[test]
fn bad_paths() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let obj = d.join("cube.obj");
    box_mesh([0.0; 3], [1.0; 3]).write(&obj);
    let obj = obj.to_str().unwrap();
    let missing = d.join("missing.obj");
    let out = d.join("out.vdag");
    let msg = fails(
        &[
            "convert",
            missing.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--depth",
            "5",
        ],
        d,
        1,
    );
    assert!(
        msg.contains("cannot open input") && msg.contains("missing.obj"),
        "{msg}"
    );
    let nodir = d.join("no/such/dir/out.vdag");
    let msg = fails(
        &[
            "convert",
            obj,
            "-o",
            nodir.to_str().unwrap(),
            "--depth",
            "5",
        ],
        d,
        1,
    );
    assert!(msg.contains("does not exist"), "{msg}");
    // An existing output is never replaced without --force ...
    std::fs::write(&out, b"precious").unwrap();
    let msg = fails(
        &["convert", obj, "-o", out.to_str().unwrap(), "--depth", "5"],
        d,
        1,
    );
    assert!(
        msg.contains("already exists") && msg.contains("--force"),
        "{msg}"
    );
    assert_eq!(std::fs::read(&out).unwrap(), b"precious");
    // ... and is with it.
    let o = run(&[
        "convert",
        obj,
        "-o",
        out.to_str().unwrap(),
        "--depth",
        "5",
        "--force",
        "-q",
    ]);
    assert!(o.status.success());
    assert!(dagfmt::validate::validate(&std::fs::read(&out).unwrap()).is_empty());
    assert_eq!(
        dir_entries(d),
        vec!["cube.obj".to_string(), "out.vdag".to_string()],
        "no temporary files left"
    );
    // The output is a directory.
    let msg = fails(
        &[
            "convert",
            obj,
            "-o",
            d.to_str().unwrap(),
            "--depth",
            "5",
            "--force",
        ],
        d,
        1,
    );
    assert!(msg.contains("directory"), "{msg}");
}

#[test]
fn solid_mesh_too_deep_is_refused_before_work() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let obj = d.join("cube.obj");
    box_mesh([0.0; 3], [1.0; 3]).write(&obj);
    let out = d.join("out.vdag");
    let msg = fails(
        &[
            "convert",
            obj.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--depth",
            "21",
            "--solid",
            "--memory-limit",
            "1G",
        ],
        d,
        1,
    );
    assert!(msg.contains("--solid at depth 21"), "{msg}");
}

#[test]
fn memory_limit_is_enforced() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let obj = d.join("sphere.obj");
    crate::common::sphere_mesh([0.0; 3], 1.0, 3).write(&obj);
    let out = d.join("out.vdag");
    // 1 MiB is below what any process needs: the conversion stops cleanly.
    let msg = fails(
        &[
            "convert",
            obj.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--depth",
            "9",
            "--memory-limit",
            "1M",
        ],
        d,
        1,
    );
    assert!(msg.contains("memory limit"), "{msg}");
}
