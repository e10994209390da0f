//! The conformance suite under `cargo test`: every committed case against the
//! in-process CPU tracer and validator, the runner binary against external
//! commands (dagtrace's binary, a validator adapter, deliberately broken
//! tracers), and the reproducibility of the committed case files.
//!
//! `BLESS=1 cargo test -p conformance` regenerates the committed cases first.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use conformance::suite::{
    self, CpuTracer, FormatVersion, InProcessValidator, Outcome, TraceBackend, TraceCaseFiles,
};
use conformance::{bless, model};
use dagfmt::batch::{Hit, Ray};

fn cases_dir() -> PathBuf {
    suite::default_cases_dir()
}

fn conformance_exe() -> &'static str {
    env!("CARGO_BIN_EXE_conformance")
}

/// With `BLESS=1`, regenerates the committed cases once before any test reads them.
fn committed_cases() -> &'static Path {
    static BLESSED: OnceLock<PathBuf> = OnceLock::new();
    BLESSED.get_or_init(|| {
        let dir = cases_dir();
        if std::env::var_os("BLESS").is_some_and(|v| v == "1") {
            let files = bless::generate().expect("generation succeeds");
            bless::write(&dir, &files).expect("writing the cases");
            eprintln!(
                "BLESS=1: rewrote {} case files in {}",
                files.len(),
                dir.display()
            );
        }
        dir
    })
}

fn show(outcomes: &[Outcome]) -> String {
    outcomes
        .iter()
        .filter(|o| !o.passed())
        .map(|o| format!("FAIL {}\n    {}", o.name, o.failures.join("\n    ")))
        .collect::<Vec<_>>()
        .join("\n")
}

fn run(args: &[&str]) -> Output {
    Command::new(conformance_exe())
        .args(args)
        .output()
        .expect("the conformance binary runs")
}

fn stdout(output: &Output) -> String {
    String::from_utf8_lossy(&output.stdout).into_owned()
}

/// The `N passed, N failed` line the runner must end with.
fn summary(output: &Output) -> (usize, usize) {
    let text = stdout(output);
    let last = text.lines().last().unwrap_or_default().to_string();
    let parsed = (|| {
        let (p, f) = last.split_once(" passed, ")?;
        Some((p.parse().ok()?, f.strip_suffix(" failed")?.parse().ok()?))
    })();
    parsed.unwrap_or_else(|| panic!("the output does not end with `N passed, N failed`:\n{text}"))
}

/// Every case, in format 1.0 (the committed file) and 2.0 (upgraded).
#[test]
fn cpu_tracer_passes_every_case() {
    let cases = suite::trace_cases(committed_cases(), None).expect("committed cases");
    assert!(cases.len() >= 40, "only {} tracer cases", cases.len());
    for version in FormatVersion::ALL {
        let outcomes: Vec<_> = cases
            .iter()
            .map(|c| suite::run_trace_case_in(c, &CpuTracer, version))
            .collect();
        let rays: usize = outcomes.iter().map(|o| o.checked).sum();
        assert!(rays >= 5000, "{version:?}: only {rays} rays");
        assert!(outcomes.iter().all(Outcome::passed), "{}", show(&outcomes));
    }
}

/// The 2.0 run really hands the tracer a 2.0 file, and the CPU tracer's
/// answers on the upgraded file are those on the committed one, hit for hit.
#[test]
fn the_2_0_run_traces_upgraded_files() {
    let cases = suite::trace_cases(committed_cases(), Some("random-sparse")).expect("case");
    let case = &cases[0];
    let file = std::fs::read(&case.dag).expect("read");
    let upgraded = FormatVersion::V2.file_bytes(file.clone()).expect("upgrade");
    assert!(matches!(
        dagfmt::AnyDag::open(&upgraded),
        Ok(dagfmt::AnyDag::V2(_))
    ));
    let rays = dagfmt::batch::parse_rays(&std::fs::read(&case.rays).expect("rays")).expect("rays");
    let key = |h: &Hit| (h.hit, h.t.to_bits(), h.voxel, h.level, h.face, h.index);
    let v1 = CpuTracer.trace(case, &file, &rays).expect("1.0");
    let v2 = CpuTracer.trace(case, &upgraded, &rays).expect("2.0");
    assert_eq!(
        v1.iter().map(key).collect::<Vec<_>>(),
        v2.iter().map(key).collect::<Vec<_>>()
    );
    assert!(v1.iter().filter(|h| h.hit).count() > 10);
    let outcome = suite::run_trace_case_in(case, &CpuTracer, FormatVersion::V2);
    assert_eq!(outcome.name, format!("{}@2.0", case.name));
    assert!(outcome.passed(), "{:?}", outcome.failures);
}

/// The GPU tracer (full stack and short stack) must pass every case too. Without
/// an adapter this says it was skipped, unless `VDAG_REQUIRE_GPU=1` (set by CI,
/// which installs Mesa's software Vulkan driver) makes that a failure.
#[test]
fn gpu_tracer_passes_every_case() {
    for short_stack in [None, Some(2)] {
        let gpu = match suite::GpuTracer::new(short_stack) {
            Ok(gpu) => gpu,
            Err(e) => {
                if std::env::var("VDAG_REQUIRE_GPU").is_ok_and(|v| v == "1") {
                    panic!("VDAG_REQUIRE_GPU=1 but {e}");
                }
                println!(
                    "skipped: no GPU adapter (set VDAG_REQUIRE_GPU=1 to make this an error): {e}"
                );
                return;
            }
        };
        // Every case in format 1.0 and 2.0.
        let cases = suite::trace_cases(committed_cases(), None).expect("cases load");
        let outcomes: Vec<_> = FormatVersion::ALL
            .iter()
            .flat_map(|&v| cases.iter().map(move |c| (c, v)))
            .map(|(c, v)| suite::run_trace_case_in(c, &gpu, v))
            .collect();
        assert!(
            outcomes.iter().all(Outcome::passed),
            "GPU tracer ({}, short stack {short_stack:?}) failed:\n{}",
            gpu.adapter_name(),
            show(&outcomes)
        );
    }
}

#[test]
fn validator_passes_every_case() {
    let cases = suite::validate_cases(committed_cases(), None).expect("committed cases");
    // One case (at least) for every error code but the untestable ones.
    for &code in dagfmt::ErrorCode::ALL {
        let covered = cases.iter().any(|c| c.expected == Some(code));
        let untestable = conformance::malformed::UNTESTABLE
            .iter()
            .any(|(c, _)| *c == code);
        assert!(
            covered != untestable,
            "{code}: covered {covered}, listed untestable {untestable}"
        );
    }
    let outcomes: Vec<_> = cases
        .iter()
        .map(|c| suite::run_validate_case(c, &InProcessValidator, suite::Strictness::Strict))
        .collect();
    assert!(outcomes.iter().all(Outcome::passed), "{}", show(&outcomes));
}

#[test]
fn malformed_files_break_only_their_rule() {
    // Where the edit can break one rule alone, dagfmt's validator (which
    // reports every finding) reports that code and no other.
    let cases =
        suite::validate_cases(committed_cases(), Some("validate/E")).expect("committed cases");
    let consequential = ["E030", "E042"];
    for case in cases {
        let expected = case.expected.expect("malformed");
        let bytes = std::fs::read(&case.path).expect("read");
        let mut codes: Vec<_> = dagfmt::validate::validate(&bytes)
            .iter()
            .map(|e| e.code)
            .collect();
        codes.dedup();
        if !consequential.contains(&expected.code()) {
            assert_eq!(codes, vec![expected], "{}", case.name);
        }
    }
}

#[test]
fn committed_cases_are_reproducible() {
    let committed = committed_cases();
    let temp = tempfile::tempdir().expect("temp dir");
    let output = run(&[
        "bless",
        "-o",
        temp.path().to_str().expect("UTF-8 temp path"),
    ]);
    assert!(
        output.status.success(),
        "bless failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    let list = |root: &Path| -> Vec<String> {
        let mut names = Vec::new();
        for dir in [bless::TRACE_DIR, bless::VALIDATE_DIR] {
            for entry in std::fs::read_dir(root.join(dir)).expect("list") {
                names.push(format!(
                    "{dir}/{}",
                    entry.expect("entry").file_name().to_string_lossy()
                ));
            }
        }
        names.sort();
        names
    };
    let fresh = list(temp.path());
    assert_eq!(
        fresh,
        list(committed),
        "the committed case files differ from bless's (run `BLESS=1 cargo test -p conformance`)"
    );
    for name in fresh {
        let a = std::fs::read(temp.path().join(&name)).expect("read");
        let b = std::fs::read(committed.join(&name)).expect("read");
        assert!(
            a == b,
            "{name} differs from what bless writes (run `BLESS=1 cargo test -p conformance`)"
        );
    }
    let total: u64 = ["trace", "validate"]
        .iter()
        .flat_map(|d| std::fs::read_dir(committed.join(d)).expect("list"))
        .map(|e| e.expect("entry").metadata().expect("metadata").len())
        .sum();
    assert!(total < 3 << 20, "the committed cases take {total} bytes");
}

#[test]
fn model_encoder_reproduces_builder_files() {
    for case in suite::trace_cases(committed_cases(), None).expect("cases") {
        if case.name.starts_with("reordered") || case.name.starts_with("undeduplicated") {
            continue;
        }
        let bytes = std::fs::read(&case.dag).expect("read");
        let decoded = model::DagModel::decode(&bytes).expect("decodes");
        assert!(
            decoded.encode() == bytes,
            "{}: decode + encode changes the file",
            case.name
        );
    }
}

/// A tracer that answers like the CPU tracer but with one thing changed.
struct Mutant(fn(&Ray, Hit) -> Hit);

impl TraceBackend for Mutant {
    fn trace(&self, case: &TraceCaseFiles, file: &[u8], rays: &[Ray]) -> Result<Vec<Hit>, String> {
        let hits = CpuTracer.trace(case, file, rays)?;
        Ok(rays.iter().zip(hits).map(|(r, h)| (self.0)(r, h)).collect())
    }
}

#[test]
fn the_judge_catches_wrong_answers() {
    let cases = suite::trace_cases(committed_cases(), None).expect("cases");
    type Mutation = fn(&Ray, Hit) -> Hit;
    let mutants: [(&str, Mutation); 8] = [
        ("every hit becomes a miss", |_, _| Hit::MISS),
        ("t a bit late", |_, h| Hit {
            t: h.t + 0.01 * h.t.abs().max(0.05),
            ..h
        }),
        ("t a bit early", |_, h| Hit {
            t: h.t - 0.01 * h.t.abs().max(0.05),
            ..h
        }),
        ("wrong face", |_, h| Hit {
            face: (h.face + 1) % 7,
            ..h
        }),
        ("wrong index", |_, h| Hit {
            index: h.index.map(|i| i + 1),
            ..h
        }),
        ("neighbouring cell", |_, h| Hit {
            voxel: [h.voxel[0] ^ 1, h.voxel[1], h.voxel[2]],
            ..h
        }),
        ("wrong level", |_, h| Hit {
            level: if h.level > 1 { h.level - 1 } else { 2 },
            ..h
        }),
        ("misses become hits", |r, h| {
            if h.hit {
                h
            } else {
                Hit {
                    hit: true,
                    t: r.tmin.max(0.0),
                    voxel: [0; 3],
                    level: r.level.unwrap_or(1),
                    face: 1,
                    index: Some(0),
                }
            }
        }),
    ];
    for (what, f) in mutants {
        let outcomes: Vec<_> = cases
            .iter()
            .map(|c| suite::run_trace_case(c, &Mutant(f)))
            .collect();
        let failed = outcomes.iter().filter(|o| !o.passed()).count();
        assert!(
            failed * 2 >= outcomes.len(),
            "mutant `{what}` fails only {failed} of {} cases",
            outcomes.len()
        );
    }
}

#[test]
fn runner_drives_an_external_validator() {
    let cases = committed_cases().to_str().expect("UTF-8").to_string();
    let command = format!("'{}' validate-file {{file}}", conformance_exe());
    let output = run(&["validate", "--cases", &cases, "--exec", &command]);
    let (passed, failed) = summary(&output);
    assert!(
        output.status.success() && failed == 0 && passed > 50,
        "{}",
        stdout(&output)
    );
    // A validator that accepts everything fails every malformed case.
    let output = run(&["validate", "--cases", &cases, "--exec", "true"]);
    let (_, failed) = summary(&output);
    assert_eq!(output.status.code(), Some(1));
    assert!(
        failed >= dagfmt::ErrorCode::ALL.len() - 1,
        "{}",
        stdout(&output)
    );
    assert!(stdout(&output).contains("accepted, expected rejection with E041"));
}

#[test]
fn runner_reports_broken_external_tracers() {
    let cases = committed_cases().to_str().expect("UTF-8").to_string();
    // A command that fails.
    let output = run(&[
        "run", "--cases", &cases, "--filter", "full", "--exec", "exit 3",
    ]);
    assert_eq!(output.status.code(), Some(1));
    let (passed, failed) = summary(&output);
    assert!(passed == 0 && failed >= 2, "{}", stdout(&output));
    // A tracer that answers `miss` to every ray.
    let all_miss = "{ echo vdag-hits 1; grep -v -e '^#' -e '^vdag-rays' -e '^$' {rays} | sed 's/.*/miss/'; } > {hits}";
    let output = run(&[
        "run", "--cases", &cases, "--filter", "full-d4", "--exec", all_miss,
    ]);
    assert_eq!(output.status.code(), Some(1));
    let text = stdout(&output);
    assert!(
        text.contains("FAIL full-d4")
            && text.contains("FAIL full-d4@2.0")
            && text.contains("a hit is required")
            && text.contains("expected: hit 4"),
        "{text}"
    );
    // The case in both format versions.
    assert_eq!(summary(&output), (0, 2));
}

#[test]
fn runner_passes_with_the_in_process_tracer() {
    let cases = committed_cases().to_str().expect("UTF-8").to_string();
    let output = run(&["run", "--tracer", "cpu", "--cases", &cases]);
    let (passed, failed) = summary(&output);
    // Every case in both versions.
    assert!(
        output.status.success() && failed == 0 && passed >= 80 && passed % 2 == 0,
        "{}",
        stdout(&output)
    );
    let only_2 = run(&[
        "run",
        "--tracer",
        "cpu",
        "--cases",
        &cases,
        "--format-version",
        "2",
    ]);
    assert_eq!(summary(&only_2), (passed / 2, 0), "{}", stdout(&only_2));
}

/// Newest modification time of any file under `dir` (recursively).
fn newest_mtime(dir: &Path) -> Option<std::time::SystemTime> {
    let mut newest = None;
    for entry in std::fs::read_dir(dir).ok()?.flatten() {
        let path = entry.path();
        let time = if path.is_dir() {
            newest_mtime(&path)
        } else {
            entry.metadata().ok().and_then(|m| m.modified().ok())
        };
        newest = newest.max(time);
    }
    newest
}

/// Returns binary `bin` of workspace package `package` from the target
/// directory this test runs from (next to the conformance binary).
///
/// `cargo test --workspace` has already built it there; it is rebuilt only
/// when missing or older than the package's sources (a nested `cargo build -p`
/// resolves features per package and could rebuild wgpu from scratch, which
/// costs minutes on a 2-core CI machine). `None` (with a message) while the
/// package has no such binary.
fn workspace_binary(package: &str, bin: &str) -> Option<PathBuf> {
    let ours = PathBuf::from(conformance_exe());
    let profile_dir = ours.parent().expect("binary directory");
    let target_dir = profile_dir.parent().expect("target directory");
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("workspace root");
    let binary = profile_dir.join(format!("{bin}{}", std::env::consts::EXE_SUFFIX));
    let built = std::fs::metadata(&binary).and_then(|m| m.modified()).ok();
    let sources = newest_mtime(&workspace.join(package).join("src"));
    if built.is_some() && sources.is_some() && built >= sources {
        return Some(binary);
    }
    let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
    let mut command = Command::new(cargo);
    command
        .current_dir(workspace)
        .args(["build", "-p", package, "--bin", bin]);
    command.env("CARGO_TARGET_DIR", target_dir);
    if profile_dir.file_name().is_some_and(|n| n == "release") {
        command.arg("--release");
    }
    let output = command.output().expect("cargo runs");
    let stderr = String::from_utf8_lossy(&output.stderr);
    if !output.status.success() {
        if stderr.contains(&format!("no bin target named `{bin}`")) {
            eprintln!("skipping: the {package} package has no `{bin}` binary yet");
            return None;
        }
        panic!("building the {bin} binary failed:\n{stderr}");
    }
    assert!(binary.exists(), "{} was not built", binary.display());
    Some(binary)
}

#[test]
fn runner_drives_the_dagtrace_binary() {
    let Some(dagtrace) = workspace_binary("dagtrace", "dagtrace") else {
        return;
    };
    let cases = committed_cases().to_str().expect("UTF-8").to_string();
    let quoted = suite::shell_quote(&dagtrace);
    for (format, extra) in [("text", &[][..]), ("binary", &["--binary-rays"][..])] {
        let command =
            format!("{quoted} trace {{dag}} --rays {{rays}} --out {{hits}} --format {format}");
        let mut args = vec!["run", "--cases", &cases, "--exec", &command];
        args.extend_from_slice(extra);
        let output = run(&args);
        let (passed, failed) = summary(&output);
        // Both versions: `dagtrace trace` reads the upgraded 2.0 files too.
        assert!(
            output.status.success() && failed == 0 && passed >= 80,
            "{format}: {}",
            stdout(&output)
        );
    }
}

#[test]
fn runner_drives_the_dagtool_validator() {
    let Some(dagtool) = workspace_binary("dagtool", "dagtool") else {
        return;
    };
    let cases = committed_cases().to_str().expect("UTF-8").to_string();
    let command = format!("{} validate {{file}}", suite::shell_quote(&dagtool));
    let output = run(&["validate", "--cases", &cases, "--exec", &command]);
    let (passed, failed) = summary(&output);
    assert!(
        output.status.success() && failed == 0 && passed > 50,
        "{}",
        stdout(&output)
    );
}

/// Writes an executable shell script into `dir`.
fn script(dir: &Path, name: &str, body: &str) -> String {
    use std::os::unix::fs::PermissionsExt;
    let path = dir.join(name);
    std::fs::write(&path, format!("#!/bin/sh\n{body}\n")).expect("write script");
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755)).expect("chmod");
    suite::shell_quote(&path)
}

#[test]
fn strict_mode_requires_offsets_and_no_foreign_codes() {
    let cases = committed_cases().to_str().expect("UTF-8").to_string();
    let temp = tempfile::tempdir().expect("temp dir");
    let reference = format!("'{}' validate-file", conformance_exe());
    let malformed = suite::validate_cases(committed_cases(), Some("validate/E"))
        .expect("cases")
        .len();
    // The reference validator passes strict mode (the default).
    let output = run(&[
        "validate",
        "--cases",
        &cases,
        "--filter",
        "validate/",
        "--exec",
        &format!("{reference} {{file}}"),
    ]);
    assert_eq!(summary(&output).1, 0, "{}", stdout(&output));
    // A validator that reports one code too many (E062 at its offset), and one
    // that reports the right codes at the wrong offsets.
    let extra = script(
        temp.path(),
        "extra.sh",
        &format!(
            "{reference} \"$1\" && exit 0; echo 'E062 header-voxel-count at byte 0x48: invented'; exit 1"
        ),
    );
    let shifted = script(
        temp.path(),
        "shifted.sh",
        &format!("{reference} \"$1\" | sed 's/at byte 0x[0-9a-f]*/at byte 0x3/'; exit 1"),
    );
    for (validator, complaint, spared) in [
        (&extra, "E062 outside the case's expected set", 1),
        (&shifted, "not reported at byte", 0),
    ] {
        let command = format!("{validator} {{file}}");
        let output = run(&[
            "validate",
            "--cases",
            &cases,
            "--filter",
            "validate/E",
            "--exec",
            &command,
        ]);
        let (_, failed) = summary(&output);
        assert_eq!(output.status.code(), Some(1));
        assert_eq!(failed, malformed - spared, "{}", stdout(&output));
        assert!(stdout(&output).contains(complaint), "{}", stdout(&output));
        // --lenient only asks for the code.
        let output = run(&[
            "validate",
            "--lenient",
            "--cases",
            &cases,
            "--filter",
            "validate/E",
            "--exec",
            &command,
        ]);
        assert_eq!(summary(&output), (malformed, 0), "{}", stdout(&output));
    }
}

/// Whether process `pid` is still running, after giving a killed one a moment
/// to go. A zombie counts as gone: in a container whose first process does not
/// reap orphans, a killed orphan stays one.
fn alive(pid: &str) -> bool {
    let stat = format!("/proc/{}/stat", pid.trim());
    for _ in 0..100 {
        let running = std::fs::read_to_string(&stat)
            .ok()
            .and_then(|s| s.rsplit_once(')').map(|(_, rest)| rest.trim().to_string()))
            .is_some_and(|rest| !rest.starts_with('Z') && !rest.starts_with('X'));
        if !running {
            return false;
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    true
}

#[test]
fn hanging_external_programs_time_out_and_their_group_is_killed() {
    let cases = committed_cases().to_str().expect("UTF-8").to_string();
    let temp = tempfile::tempdir().expect("temp dir");
    let pid_file = temp.path().join("pid");
    // The shell starts a sleeper in the background and waits for it: both
    // belong to the command's process group and must be gone afterwards.
    let hang = script(
        temp.path(),
        "hang.sh",
        &format!("sleep 60 & echo $! > '{}'; wait", pid_file.display()),
    );
    let started = std::time::Instant::now();
    let output = run(&[
        "run",
        "--cases",
        &cases,
        "--filter",
        "full-d4",
        "--timeout",
        "0.5",
        "--exec",
        &format!("{hang} {{dag}} {{rays}} {{hits}}"),
    ]);
    assert!(
        started.elapsed().as_secs() < 20,
        "the runner waited {:?}",
        started.elapsed()
    );
    assert_eq!(output.status.code(), Some(1));
    let text = stdout(&output);
    assert!(
        text.contains("FAIL full-d4") && text.contains("timed out after 0.5 s"),
        "{text}"
    );
    let pid = std::fs::read_to_string(&pid_file).expect("the script ran");
    assert!(
        !alive(&pid),
        "the background sleeper {pid} outlived the timeout"
    );
    // The same for validators and for `judge --exec`.
    let output = run(&[
        "validate",
        "--cases",
        &cases,
        "--filter",
        "validate/E041",
        "--timeout",
        "0.5",
        "--exec",
        &format!("{hang} {{file}}"),
    ]);
    assert_eq!(summary(&output), (0, 1), "{}", stdout(&output));
    assert!(stdout(&output).contains("timed out"), "{}", stdout(&output));
    let case = committed_cases().join("trace");
    let output = Command::new(conformance_exe())
        .args([
            "judge",
            case.join("full-d4.vdag").to_str().expect("UTF-8"),
            "--rays",
            case.join("full-d4.rays").to_str().expect("UTF-8"),
            "--timeout",
            "0.5",
            "--exec",
            &format!("{hang} {{dag}} {{rays}} {{hits}}"),
        ])
        .output()
        .expect("runs");
    assert_eq!(output.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&output.stderr).contains("timed out after 0.5 s"));
    let pid = std::fs::read_to_string(&pid_file).expect("the script ran");
    assert!(
        !alive(&pid),
        "the background sleeper {pid} outlived the timeout"
    );
}
