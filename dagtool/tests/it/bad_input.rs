//! The command line end to end on bad input, for every subcommand that reads
//! or writes files (`convert`, `validate`, `info`, `dump`, `pack`, `unpack`):
//! a missing file, an unreadable one, a directory, an empty file, a file that
//! is not a `.vdag`, a truncated one, an OBJ with NaN vertices, an output in a
//! missing directory, an output that is a directory, and a write error (a full
//! disk, simulated with a file-size limit). Each case asserts the exact exit
//! status, exactly one `dagtool: error: ` line on stderr naming the file, no
//! panic, and that the output directory is left empty (no partial output, no
//! temporary file). Also: a closed standard output (`dagtool info F | head`)
//! ends the output quietly.
//!
//! Two commands answer some bad inputs with a report instead of an error, by
//! design: `validate` lists the violations of a file it could read on stdout
//! (status 1, nothing on stderr), and `dump` lists whatever bytes a damaged
//! file has, says where the structure stops making sense, and succeeds.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use crate::common::{box_mesh, dagtool, dir_entries, run_ok};

/// What a run must print.
#[derive(Clone, Copy, Debug)]
enum Says {
    /// Exactly one `dagtool: error: ` line on stderr containing this, and
    /// nothing on stdout.
    Error(&'static str),
    /// A report on stdout containing this, and nothing on stderr.
    Report(&'static str),
}

/// One bad-input run.
struct Case {
    /// What the case is, for failure messages.
    what: String,
    args: Vec<String>,
    status: i32,
    says: Says,
    /// A path the message must name.
    names: String,
    /// Run under a file-size limit of a few KiB (a write error).
    limited: bool,
}

fn case(what: &str, args: &[&str], status: i32, says: Says, names: &Path) -> Case {
    Case {
        what: what.to_string(),
        args: args.iter().map(|a| a.to_string()).collect(),
        status,
        says,
        names: s(names).to_string(),
        limited: false,
    }
}

fn s(p: &Path) -> &str {
    p.to_str().expect("UTF-8 temp path")
}

/// Runs `command` with a file-size limit of 4 blocks (2 or 4 KiB, depending
/// on the shell) and SIGXFSZ ignored, so that writing past the limit fails
/// with EFBIG ("File too large"), as a full disk fails with ENOSPC. (Writing
/// to /dev/full cannot test this: outputs are written beside their final name
/// and renamed.) The ignored signal is inherited through `exec`.
pub fn with_file_size_limit(command: &Command) -> Command {
    let mut limited = Command::new("sh");
    limited
        .arg("-c")
        .arg(r#"trap "" XFSZ; ulimit -f 4 && exec "$0" "$@""#)
        .arg(command.get_program())
        .args(command.get_args());
    limited
}

/// Runs the case and checks the failure contract; `out_dir` must be empty
/// before and after.
fn check(case: &Case, out_dir: &Path) {
    assert!(
        dir_entries(out_dir).is_empty(),
        "{}: out dir not empty",
        case.what
    );
    let mut command = dagtool();
    command.args(&case.args);
    if case.limited {
        command = with_file_size_limit(&command);
    }
    let o: Output = command.output().expect("dagtool runs");
    let stdout = String::from_utf8_lossy(&o.stdout);
    let stderr = String::from_utf8_lossy(&o.stderr);
    let what = &case.what;
    assert_eq!(
        o.status.code(),
        Some(case.status),
        "{what}: dagtool {:?}\nstdout: {stdout}\nstderr: {stderr}",
        case.args
    );
    assert!(!stderr.contains("panicked"), "{what}: {stderr}");
    match case.says {
        Says::Error(needle) => {
            assert_eq!(stderr.lines().count(), 1, "{what}: one line: {stderr:?}");
            assert!(stderr.starts_with("dagtool: error: "), "{what}: {stderr}");
            assert!(
                stderr.contains(needle),
                "{what}: `{needle}` not in {stderr}"
            );
            assert!(
                stderr.contains(&case.names),
                "{what}: {stderr} does not name {}",
                case.names
            );
            assert!(stdout.is_empty(), "{what}: stdout: {stdout}");
        }
        Says::Report(needle) => {
            assert!(stderr.is_empty(), "{what}: stderr: {stderr}");
            assert!(
                stdout.contains(needle),
                "{what}: `{needle}` not in {stdout}"
            );
            assert!(
                stdout.contains(&case.names),
                "{what}: {stdout} does not name {}",
                case.names
            );
        }
    }
    assert!(
        dir_entries(out_dir).is_empty(),
        "{what}: the output directory holds {:?}",
        dir_entries(out_dir)
    );
}

/// The bad inputs, written into `dir`.
struct Inputs {
    missing: PathBuf,
    /// A path that cannot be opened for reading although its name exists:
    /// under a regular file (ENOTDIR), which blocks root too.
    under_a_file: PathBuf,
    /// A file without read permission, when permissions block this process
    /// (not when it runs as root, which reads it anyway).
    unreadable: Option<PathBuf>,
    directory: PathBuf,
    empty: PathBuf,
    not_vdag: PathBuf,
    truncated: PathBuf,
    truncated_zst: PathBuf,
    valid: PathBuf,
    valid_zst: PathBuf,
    obj: PathBuf,
    nan_obj: PathBuf,
    /// A large voxel list and its `.vdag` and `.vdag.zst` (each well over
    /// the file-size limit of the write-error cases).
    voxels: PathBuf,
    big: PathBuf,
    big_zst: PathBuf,
}

fn inputs(dir: &Path) -> Inputs {
    let obj = dir.join("cube.obj");
    box_mesh([0.0; 3], [1.0; 3]).write(&obj);
    let valid = dir.join("cube.vdag");
    crate::common::convert(&obj, &valid, 5, &[]);
    let valid_zst = dir.join("cube.vdag.zst");
    run_ok(&["pack", s(&valid), s(&valid_zst)]);
    let bytes = std::fs::read(&valid).unwrap();
    let truncated = dir.join("truncated.vdag");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    let zst = std::fs::read(&valid_zst).unwrap();
    let truncated_zst = dir.join("truncated.vdag.zst");
    std::fs::write(&truncated_zst, &zst[..zst.len() / 2]).unwrap();
    let empty = dir.join("empty.vdag");
    std::fs::write(&empty, b"").unwrap();
    let not_vdag = dir.join("mesh-not-vdag.vdag");
    std::fs::write(&not_vdag, box_mesh([0.0; 3], [2.0; 3]).to_obj()).unwrap();
    assert!(
        std::fs::metadata(&not_vdag).unwrap().len() > 128,
        "longer than a header"
    );
    let directory = dir.join("folder.vdag");
    std::fs::create_dir(&directory).unwrap();
    let nan_obj = dir.join("nan.obj");
    std::fs::write(&nan_obj, "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
    let unreadable = dir.join("unreadable.vdag");
    std::fs::copy(&valid, &unreadable).unwrap();
    let unreadable = if permissions_block_reads(&unreadable) {
        Some(unreadable)
    } else {
        eprintln!(
            "note: chmod 000 does not stop this process reading (running as root?); \
             the unreadable-file case uses a path under a regular file (ENOTDIR) only"
        );
        std::fs::remove_file(&unreadable).unwrap();
        None
    };
    // 20 000 scattered voxels: about 140 KB as .vdag, still over 100 KB packed.
    let voxels = dir.join("scattered.txt");
    let mut state = 1u64;
    let mut text = String::new();
    for _ in 0..20_000 {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let r = state >> 16;
        text.push_str(&format!(
            "{} {} {}\n",
            r & 127,
            (r >> 8) & 127,
            (r >> 16) & 127
        ));
    }
    std::fs::write(&voxels, text).unwrap();
    let big = dir.join("scattered.vdag");
    crate::common::convert(&voxels, &big, 7, &[]);
    let big_zst = dir.join("scattered.vdag.zst");
    run_ok(&["pack", "--level", "1", s(&big), s(&big_zst)]);
    assert!(std::fs::metadata(&big_zst).unwrap().len() > 16 << 10);
    Inputs {
        missing: dir.join("missing.vdag"),
        under_a_file: obj.join("x.vdag"),
        unreadable,
        directory,
        empty,
        not_vdag,
        truncated,
        truncated_zst,
        valid,
        valid_zst,
        obj,
        nan_obj,
        voxels,
        big,
        big_zst,
    }
}

/// Removes every permission from `path` and says whether that stops this
/// process from opening it.
fn permissions_block_reads(path: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o000)).unwrap();
    std::fs::File::open(path).is_err()
}

#[test]
fn every_reading_command_fails_cleanly_on_every_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let inputs = inputs(dir.path());
    let out_dir = dir.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();
    let out_vdag = out_dir.join("out.vdag");
    let out_zst = out_dir.join("out.vdag.zst");
    let (out_vdag, out_zst) = (s(&out_vdag), s(&out_zst));

    // Inputs that cannot be opened at all: the same error from every command.
    let mut unopenable: Vec<(&str, &Path, &str)> = vec![
        ("missing file", &inputs.missing, "No such file"),
        ("path under a file", &inputs.under_a_file, "Not a directory"),
        ("directory", &inputs.directory, "not a regular file"),
    ];
    if let Some(unreadable) = &inputs.unreadable {
        unopenable.push(("unreadable file", unreadable, "Permission denied"));
    }
    let mut cases = Vec::new();
    for &(what, path, needle) in &unopenable {
        let p = s(path);
        let error = Says::Error(needle);
        cases.extend([
            case(&format!("info: {what}"), &["info", p], 1, error, path),
            case(&format!("dump: {what}"), &["dump", p], 1, error, path),
            // validate: 2 means the file could not be read (1 is "invalid").
            case(
                &format!("validate: {what}"),
                &["validate", p],
                2,
                error,
                path,
            ),
            case(
                &format!("pack: {what}"),
                &["pack", p, out_zst],
                1,
                error,
                path,
            ),
            case(
                &format!("unpack: {what}"),
                &["unpack", p, out_vdag],
                1,
                error,
                path,
            ),
            case(
                &format!("convert: {what}"),
                &[
                    "convert",
                    p,
                    "-o",
                    out_vdag,
                    "--depth",
                    "5",
                    "--input-format",
                    "obj",
                ],
                1,
                error,
                path,
            ),
        ]);
    }

    // Files that open but are not valid .vdag files.
    let damaged: [(&str, &Path, &str); 4] = [
        ("empty file", &inputs.empty, "E001"),
        ("not a .vdag", &inputs.not_vdag, "E002"),
        ("truncated .vdag", &inputs.truncated, "E010"),
        (
            "truncated .vdag.zst",
            &inputs.truncated_zst,
            "cannot unpack",
        ),
    ];
    for (what, path, needle) in damaged {
        let p = s(path);
        cases.push(case(
            &format!("info: {what}"),
            &["info", p],
            1,
            Says::Error(needle),
            path,
        ));
        if what == "truncated .vdag.zst" {
            cases.push(case(
                &format!("pack: {what}"),
                &["pack", p, out_zst],
                1,
                Says::Error("already a zstd transport file"),
                path,
            ));
            // The transport form cannot be read at all: an error, not a report.
            cases.extend([
                case(
                    &format!("validate: {what}"),
                    &["validate", p],
                    2,
                    Says::Error(needle),
                    path,
                ),
                case(
                    &format!("dump: {what}"),
                    &["dump", p],
                    1,
                    Says::Error(needle),
                    path,
                ),
            ]);
        } else {
            cases.extend([
                case(
                    &format!("pack: {what}"),
                    &["pack", p, out_zst],
                    1,
                    Says::Error(needle),
                    path,
                ),
                case(
                    &format!("validate: {what}"),
                    &["validate", p],
                    1,
                    Says::Report(needle),
                    path,
                ),
                // dump lists damaged files and says why the reader rejects them.
                case(
                    &format!("dump: {what}"),
                    &["dump", p],
                    0,
                    Says::Report(needle),
                    path,
                ),
            ]);
        }
    }
    // unpack wants a transport file; everything else is refused before writing.
    for (what, path, needle) in [
        ("empty file", &inputs.empty, "not a zstd frame"),
        ("plain .vdag", &inputs.valid, "not a zstd frame"),
        (
            "truncated .vdag.zst",
            &inputs.truncated_zst,
            "corrupt zstd frame",
        ),
    ] {
        cases.push(case(
            &format!("unpack: {what}"),
            &["unpack", s(path), out_vdag],
            1,
            Says::Error(needle),
            path,
        ));
    }
    // pack refuses what is packed already.
    cases.push(case(
        "pack: a .vdag.zst",
        &["pack", s(&inputs.valid_zst), out_zst],
        1,
        Says::Error("already a zstd transport file"),
        &inputs.valid_zst,
    ));
    // convert: a mesh with NaN vertices, a .vdag given as input. (An empty
    // mesh is the empty volume: voxel_lists::empty_inputs_make_the_empty_volume.)
    for (what, path, format, needle) in [
        ("NaN vertices", &inputs.nan_obj, "obj", "non-finite"),
        ("a .vdag as a mesh", &inputs.valid, "obj", "cannot read OBJ"),
    ] {
        cases.push(case(
            &format!("convert: {what}"),
            &[
                "convert",
                s(path),
                "-o",
                out_vdag,
                "--depth",
                "5",
                "--input-format",
                format,
            ],
            1,
            Says::Error(needle),
            path,
        ));
    }
    cases.push(case(
        "convert: a .vdag without --input-format",
        &["convert", s(&inputs.valid), "-o", out_vdag, "--depth", "5"],
        2,
        Says::Error("--input-format"),
        &inputs.valid,
    ));
    for case in &cases {
        check(case, &out_dir);
    }
    eprintln!("{} bad-input cases checked", cases.len());
}

#[test]
fn every_writing_command_fails_cleanly_on_every_bad_output() {
    let dir = tempfile::tempdir().unwrap();
    let inputs = inputs(dir.path());
    let out_dir = dir.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();
    let missing_dir = out_dir.join("no-such-dir");
    let valid = s(&inputs.valid);
    let valid_zst = s(&inputs.valid_zst);
    let obj = s(&inputs.obj);
    let mut cases = Vec::new();

    // An output in a directory that does not exist, checked before any work.
    let in_missing = missing_dir.join("x");
    let x = s(&in_missing);
    let no_dir = Says::Error("does not exist");
    cases.extend([
        case(
            "pack: missing out dir",
            &["pack", valid, x],
            1,
            no_dir,
            &missing_dir,
        ),
        case(
            "unpack: missing out dir",
            &["unpack", valid_zst, x],
            1,
            no_dir,
            &missing_dir,
        ),
        case(
            "convert: missing out dir",
            &["convert", obj, "-o", x, "--depth", "5"],
            1,
            no_dir,
            &missing_dir,
        ),
    ]);

    // A write error part-way through (EFBIG under a file-size limit; a full
    // disk fails the same way, with ENOSPC): no partial output remains.
    let out = out_dir.join("big.out");
    let o = s(&out);
    let too_large = Says::Error("File too large");
    for (what, args) in [
        ("pack", vec!["pack", "--level", "1", s(&inputs.big), o]),
        ("unpack", vec!["unpack", s(&inputs.big_zst), o]),
        (
            "convert",
            vec!["convert", s(&inputs.voxels), "-o", o, "--depth", "7", "-q"],
        ),
    ] {
        let mut c = case(&format!("{what}: write error"), &args, 1, too_large, &out);
        c.limited = true;
        cases.push(c);
    }
    for case in &cases {
        check(case, &out_dir);
    }

    // An output that is a directory (here, the output directory itself).
    let od = s(&out_dir);
    let is_dir = Says::Error("is a directory");
    for case in [
        case(
            "pack: out is a dir",
            &["pack", valid, od, "--force"],
            1,
            is_dir,
            &out_dir,
        ),
        case(
            "unpack: out is a dir",
            &["unpack", valid_zst, od, "--force"],
            1,
            is_dir,
            &out_dir,
        ),
        case(
            "convert: out is a dir",
            &["convert", obj, "-o", od, "--depth", "5", "--force"],
            1,
            is_dir,
            &out_dir,
        ),
    ] {
        check(&case, &out_dir);
    }
}

/// The limit of the write-error cases really is small: the same command
/// without it succeeds, and a tiny output under it does too.
#[test]
fn the_file_size_limit_only_fails_large_writes() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("cube.obj");
    box_mesh([0.0; 3], [1.0; 3]).write(&obj);
    let out = dir.path().join("cube.vdag");
    let mut command = dagtool();
    command.args(["convert", s(&obj), "-o", s(&out), "--depth", "4", "-q"]);
    let o = with_file_size_limit(&command).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(std::fs::metadata(&out).unwrap().len() < 2048);
}

/// Runs `dagtool args` with its stdout a pipe whose reading end is already
/// closed, so the first write fails with EPIPE (`dagtool info F | head -0`).
fn run_into_closed_pipe(args: &[&str]) -> Output {
    let (reader, writer) = std::io::pipe().expect("pipe");
    drop(reader);
    let child = dagtool()
        .args(args)
        .stdout(writer)
        .stderr(Stdio::piped())
        .spawn()
        .expect("dagtool runs");
    child.wait_with_output().expect("dagtool ends")
}

#[test]
fn a_closed_stdout_ends_the_output_quietly() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("cube.obj");
    box_mesh([0.0; 3], [1.0; 3]).write(&obj);
    let valid = dir.path().join("cube.vdag");
    crate::common::convert(&obj, &valid, 6, &[]);
    let mut bytes = std::fs::read(&valid).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    let damaged = dir.path().join("damaged.vdag");
    std::fs::write(&damaged, bytes).unwrap();
    let zst = dir.path().join("cube.vdag.zst");
    let v = s(&valid);
    for (args, status) in [
        (vec!["info", v], 0),
        (vec!["info", "--json", v], 0),
        (vec!["dump", v, "--nodes", "1000"], 0),
        (vec!["validate", v], 0),
        (vec!["validate", "--json", v], 0),
        // The exit status still says what validation found.
        (vec!["validate", v, s(&damaged)], 1),
        (vec!["pack", v, s(&zst)], 0),
    ] {
        let o = run_into_closed_pipe(&args);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(status), "dagtool {args:?}: {stderr}");
        assert!(stderr.is_empty(), "dagtool {args:?}: {stderr}");
    }
    // pack did its work although nobody read its summary.
    assert!(zst.is_file());
}

/// Standard output on a full disk is an error (one line, status 1; 2 for
/// validate, whose 1 means "invalid").
#[test]
fn a_full_stdout_is_a_one_line_error() {
    let full = Path::new("/dev/full");
    if !full.exists() {
        eprintln!("skipping: no /dev/full");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("cube.obj");
    box_mesh([0.0; 3], [1.0; 3]).write(&obj);
    let valid = dir.path().join("cube.vdag");
    crate::common::convert(&obj, &valid, 5, &[]);
    for (command, status) in [("info", 1), ("dump", 1), ("validate", 2)] {
        let o = dagtool()
            .args([command, s(&valid)])
            .stdout(std::fs::File::create(full).unwrap())
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(status), "{command}: {stderr}");
        assert_eq!(stderr.lines().count(), 1, "{command}: {stderr}");
        assert!(
            stderr.contains("No space left on device"),
            "{command}: {stderr}"
        );
    }
}
