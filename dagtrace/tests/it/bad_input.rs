//! The `dagtrace` command line end to end on bad input, for both commands
//! (`render`, `trace`): a missing file, an unreadable one, a directory, an
//! empty file, a file that is not a `.vdag`, a truncated one (plain and
//! packed), a bad ray batch, an output in a missing folder, an output that is a
//! folder, a write error (a full disk, simulated with a file-size limit), and
//! a bad command line. Each case asserts the exact exit status, exactly one
//! `dagtrace: error: ` line on stderr naming the file, no panic, and that the
//! output folder is left empty (no partial output, no temporary file).

use std::path::{Path, PathBuf};
use std::process::Command;

use dagfmt::AttributeKind;

use crate::common::{Rng, build};

fn s(p: &Path) -> &str {
    p.to_str().expect("UTF-8 temp path")
}

fn names_in(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// One bad-input run: `dagtrace args` must exit with `status` and print one
/// error line containing `needle` and `names`.
struct Case {
    what: String,
    args: Vec<String>,
    status: i32,
    needle: &'static str,
    names: String,
    /// Run under a file-size limit of a few KiB (a write error).
    limited: bool,
}

fn case(what: &str, args: &[&str], status: i32, needle: &'static str, names: &str) -> Case {
    Case {
        what: what.to_string(),
        args: args.iter().map(|a| a.to_string()).collect(),
        status,
        needle,
        names: names.to_string(),
        limited: false,
    }
}

fn check(case: &Case, out_dir: &Path) {
    let what = &case.what;
    assert!(names_in(out_dir).is_empty(), "{what}: out dir not empty");
    let bin = env!("CARGO_BIN_EXE_dagtrace");
    let mut command = if case.limited {
        // Writes past 4 blocks fail with EFBIG (SIGXFSZ ignored, inherited
        // through exec), as a full disk fails with ENOSPC. /dev/full cannot
        // test this: outputs are written beside their name and renamed.
        let mut c = Command::new("sh");
        c.arg("-c")
            .arg(r#"trap "" XFSZ; ulimit -f 4 && exec "$0" "$@""#)
            .arg(bin);
        c
    } else {
        Command::new(bin)
    };
    let o = command.args(&case.args).output().expect("dagtrace runs");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(
        o.status.code(),
        Some(case.status),
        "{what}: dagtrace {:?}: {stderr}",
        case.args
    );
    assert!(!stderr.contains("panicked"), "{what}: {stderr}");
    assert_eq!(stderr.lines().count(), 1, "{what}: one line: {stderr:?}");
    assert!(stderr.starts_with("dagtrace: error: "), "{what}: {stderr}");
    assert!(
        stderr.contains(case.needle),
        "{what}: `{}` not in {stderr}",
        case.needle
    );
    assert!(
        stderr.contains(&case.names),
        "{what}: {stderr} does not name {}",
        case.names
    );
    assert!(o.stdout.is_empty(), "{what}: stdout");
    assert!(
        names_in(out_dir).is_empty(),
        "{what}: the output folder holds {:?}",
        names_in(out_dir)
    );
}

struct Inputs {
    valid: PathBuf,
    rays: PathBuf,
    many_rays: PathBuf,
}

/// A scene of 6000 scattered voxels at depth 7 (it renders to a PNG of well
/// over 4 KiB), its packed form, and ray batches.
fn inputs(dir: &Path) -> Inputs {
    let mut rng = Rng(11);
    let voxels: Vec<[u32; 3]> = (0..6000)
        .map(|_| [0; 3].map(|_: u32| rng.below(128) as u32))
        .collect();
    let valid = dir.join("scene.vdag");
    std::fs::write(
        &valid,
        build(7, AttributeKind::VoxelCount, &voxels, [0.0; 3], 1.0),
    )
    .unwrap();
    let rays = dir.join("rays.txt");
    std::fs::write(&rays, "vdag-rays 1\n0.5 0.5 -1 0 0 1 0 inf\n").unwrap();
    let many_rays = dir.join("many-rays.txt");
    let mut text = String::from("vdag-rays 1\n");
    for _ in 0..2000 {
        text.push_str(&format!(
            "{} {} -1 0 0 1 0 inf\n",
            rng.range(0.0, 1.0),
            rng.range(0.0, 1.0)
        ));
    }
    std::fs::write(&many_rays, text).unwrap();
    Inputs {
        valid,
        rays,
        many_rays,
    }
}

#[test]
fn both_commands_fail_cleanly_on_every_bad_input_and_output() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let inputs = inputs(d);
    let out_dir = d.join("out");
    std::fs::create_dir(&out_dir).unwrap();
    let png = out_dir.join("view.png");
    let hits = out_dir.join("hits.txt");
    let (png, hits) = (s(&png), s(&hits));
    let valid = s(&inputs.valid);
    let rays = s(&inputs.rays);

    // The bad .vdag inputs.
    let bytes = std::fs::read(&inputs.valid).unwrap();
    let missing = d.join("missing.vdag");
    // A path under a regular file (ENOTDIR): unreadable even for root, for
    // whom chmod 000 blocks nothing.
    let under_a_file = inputs.valid.join("x.vdag");
    let folder = d.join("folder.vdag");
    std::fs::create_dir(&folder).unwrap();
    let empty = d.join("empty.vdag");
    std::fs::write(&empty, b"").unwrap();
    let not_vdag = d.join("not-a.vdag");
    std::fs::write(&not_vdag, "v 0 0 0\n".repeat(40)).unwrap();
    let truncated = d.join("truncated.vdag");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let packed = dagfmt::transport::pack(&bytes, 3).unwrap();
    let truncated_zst = d.join("truncated.vdag.zst");
    std::fs::write(&truncated_zst, &packed[..packed.len() / 2]).unwrap();
    let mut bad: Vec<(&str, &Path, &str)> = vec![
        ("missing file", &missing, "No such file"),
        ("path under a file", &under_a_file, "Not a directory"),
        ("folder", &folder, "not a regular file"),
        ("empty file", &empty, "E001"),
        ("not a .vdag", &not_vdag, "E002"),
        ("truncated .vdag", &truncated, "E010"),
        ("truncated .vdag.zst", &truncated_zst, "corrupt zstd frame"),
    ];
    let unreadable = d.join("unreadable.vdag");
    std::fs::write(&unreadable, &bytes).unwrap();
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&unreadable, std::fs::Permissions::from_mode(0o000)).unwrap();
    }
    if std::fs::File::open(&unreadable).is_err() {
        bad.push(("unreadable file", &unreadable, "Permission denied"));
    } else {
        eprintln!(
            "note: chmod 000 does not stop this process reading (running as root?); \
             the unreadable case is the path under a file (ENOTDIR)"
        );
    }
    let mut cases = Vec::new();
    for &(what, path, needle) in &bad {
        let p = s(path);
        cases.push(case(
            &format!("render: {what}"),
            &["render", p, "-o", png],
            1,
            needle,
            p,
        ));
        cases.push(case(
            &format!("trace: {what}"),
            &["trace", p, "--rays", rays, "--out", hits],
            1,
            needle,
            p,
        ));
    }
    // Damaged files are refused by the reader even without validation.
    for (what, path, needle) in [
        ("empty file", &empty, "E001"),
        ("not a .vdag", &not_vdag, "E002"),
        ("truncated .vdag", &truncated, "E010"),
    ] {
        let p = s(path);
        cases.push(case(
            &format!("render --no-validate: {what}"),
            &["render", p, "-o", png, "--no-validate"],
            1,
            needle,
            p,
        ));
    }
    // Bad ray batches.
    let binary_garbage = d.join("garbage.rays");
    std::fs::write(&binary_garbage, [0xffu8, 0xfe, 0, 1, 2, 3]).unwrap();
    let truncated_binary = d.join("truncated.rays");
    let mut ray_bytes = Vec::new();
    let one_ray = dagfmt::batch::parse_rays(b"vdag-rays 1\n0 0 0 1 0 0 0 inf\n").unwrap();
    dagfmt::batch::write_rays_binary(&mut ray_bytes, &one_ray).unwrap();
    ray_bytes.pop();
    std::fs::write(&truncated_binary, &ray_bytes).unwrap();
    for (what, path, needle) in [
        ("missing rays", d.join("missing.rays"), "No such file"),
        ("rays are a folder", folder.clone(), "Is a directory"),
        ("empty rays", empty.clone(), "empty input"),
        ("rays are not a batch", not_vdag.clone(), "vdag-rays 1"),
        ("rays are not text", binary_garbage, "UTF-8"),
        ("truncated binary rays", truncated_binary, ""),
    ] {
        let p = s(&path).to_string();
        cases.push(case(
            &format!("trace: {what}"),
            &["trace", valid, "--rays", &p, "--out", hits],
            1,
            needle,
            &p,
        ));
    }
    // Bad outputs: a missing folder, a folder, a write error.
    let missing_dir = out_dir.join("no-such-folder");
    let in_missing = missing_dir.join("x");
    let x = s(&in_missing);
    let od = s(&out_dir);
    cases.extend([
        case(
            "render: missing out folder",
            &["render", valid, "-o", x],
            1,
            "does not exist",
            x,
        ),
        case(
            "trace: missing out folder",
            &["trace", valid, "--rays", rays, "--out", x],
            1,
            "does not exist",
            x,
        ),
        case(
            "render: out is a folder",
            &["render", valid, "-o", od, "--force"],
            1,
            "is a folder",
            od,
        ),
        case(
            "trace: out is a folder",
            &["trace", valid, "--rays", rays, "--out", od, "--force"],
            1,
            "is a folder",
            od,
        ),
    ]);
    let mut render_big = case(
        "render: write error",
        &[
            "render", valid, "-o", png, "--width", "256", "--height", "256",
        ],
        1,
        "File too large",
        png,
    );
    render_big.limited = true;
    let mut trace_big = case(
        "trace: write error",
        &[
            "trace",
            valid,
            "--rays",
            s(&inputs.many_rays),
            "--out",
            hits,
        ],
        1,
        "File too large",
        hits,
    );
    trace_big.limited = true;
    cases.extend([render_big, trace_big]);
    // Command-line errors are one line too, with status 2.
    cases.extend([
        case(
            "render: unknown flag",
            &["render", valid, "--bogus"],
            2,
            "--bogus",
            "--bogus",
        ),
        case(
            "trace: no rays",
            &["trace", valid, "--out", hits],
            2,
            "--rays",
            "--rays",
        ),
        case(
            "render: width 0",
            &["render", valid, "-o", png, "--width", "0"],
            2,
            "--width",
            "--width",
        ),
    ]);
    for case in &cases {
        check(case, &out_dir);
    }
    eprintln!("{} bad-input cases checked", cases.len());

    // Without the limit the same two writes succeed, so the limit is what failed them.
    for args in [
        vec![
            "render", valid, "-o", png, "--width", "256", "--height", "256",
        ],
        vec![
            "trace",
            valid,
            "--rays",
            s(&inputs.many_rays),
            "--out",
            hits,
        ],
    ] {
        let o = Command::new(env!("CARGO_BIN_EXE_dagtrace"))
            .args(&args)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    for name in ["view.png", "hits.txt"] {
        let len = std::fs::metadata(out_dir.join(name)).unwrap().len();
        assert!(
            len > 4096,
            "{name} is {len} bytes: too small to hit the limit"
        );
    }
}
