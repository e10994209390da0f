//! Running the committed cases against a tracer or a validator.

use std::io::{Read, Seek, SeekFrom};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};

use dagfmt::ErrorCode;
use dagfmt::batch::{self, Hit, Ray};

use crate::bless::{self, TRACE_DIR, VALIDATE_DIR, VALIDATE_INDEX};
use crate::expect;

/// The files of one tracer case on disk.
#[derive(Clone, Debug)]
pub struct TraceCaseFiles {
    /// Case name (file stem).
    pub name: String,
    /// The `.vdag` file.
    pub dag: PathBuf,
    /// The rays (text format).
    pub rays: PathBuf,
    /// The expectations.
    pub expect: PathBuf,
}

/// One validator case on disk.
#[derive(Clone, Debug)]
pub struct ValidateCaseFile {
    /// Case name: `validate/<stem>` or `trace/<stem>` (tracer files must be valid too).
    pub name: String,
    /// The file.
    pub path: PathBuf,
    /// `None`: must be accepted; else the code it must be rejected with.
    pub expected: Option<ErrorCode>,
    /// The byte offset (spec/VDAG.md § 17.4) at which strict mode requires
    /// the expected code to be reported.
    pub offset: Option<u64>,
    /// Other codes the defect also breaks, which a validator may report too.
    pub also: Vec<ErrorCode>,
    /// What the case is.
    pub description: String,
}

/// Parses `0x1c8` or `456`.
fn parse_offset(text: &str) -> Option<u64> {
    match text.strip_prefix("0x").or_else(|| text.strip_prefix("0X")) {
        Some(hex) => u64::from_str_radix(hex, 16).ok(),
        None if text.bytes().all(|b| b.is_ascii_digit()) => text.parse().ok(),
        None => None,
    }
}

/// The default cases directory: the one committed next to this crate's sources.
pub fn default_cases_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("cases")
}

fn matches(name: &str, filter: Option<&str>) -> bool {
    filter.is_none_or(|f| name.contains(f))
}

/// The tracer cases under `root`, sorted by name; `filter` keeps names
/// containing it.
pub fn trace_cases(root: &Path, filter: Option<&str>) -> Result<Vec<TraceCaseFiles>, String> {
    let dir = root.join(TRACE_DIR);
    let entries =
        std::fs::read_dir(&dir).map_err(|e| format!("cannot list {}: {e}", dir.display()))?;
    let mut cases = Vec::new();
    for entry in entries {
        let path = entry
            .map_err(|e| format!("cannot list {}: {e}", dir.display()))?
            .path();
        if path.extension().is_some_and(|e| e == "vdag") {
            let name = path
                .file_stem()
                .and_then(|s| s.to_str())
                .unwrap_or_default()
                .to_string();
            if matches(&name, filter) {
                cases.push(TraceCaseFiles {
                    rays: path.with_extension("rays"),
                    expect: path.with_extension("expect"),
                    dag: path,
                    name,
                });
            }
        }
    }
    cases.sort_by(|a, b| a.name.cmp(&b.name));
    if cases.is_empty() {
        return Err(format!("no tracer cases in {} match", dir.display()));
    }
    Ok(cases)
}

/// The validator cases under `root`: the files listed in
/// `validate/expected.txt`, then every tracer case file (valid).
pub fn validate_cases(root: &Path, filter: Option<&str>) -> Result<Vec<ValidateCaseFile>, String> {
    let index_path = root.join(VALIDATE_DIR).join(VALIDATE_INDEX);
    let index = std::fs::read_to_string(&index_path)
        .map_err(|e| format!("cannot read {}: {e}", index_path.display()))?;
    let mut cases = Vec::new();
    for (number, line) in index.lines().enumerate() {
        let (content, comment) = line.split_once('#').unwrap_or((line, ""));
        let fields: Vec<&str> = content.split_ascii_whitespace().collect();
        if fields.is_empty() {
            continue;
        }
        let at = || format!("{}:{}", index_path.display(), number + 1);
        let (file, outcome, others) = match fields[..] {
            [file, outcome, ref others @ ..] => (file, outcome, others),
            _ => {
                return Err(format!(
                    "{}: expected `FILE valid|CODE@OFFSET [CODE...]`",
                    at()
                ));
            }
        };
        let code = |text: &str| {
            ErrorCode::parse(text).ok_or_else(|| format!("{}: unknown error code `{text}`", at()))
        };
        let (expected, offset) = match outcome {
            "valid" if others.is_empty() => (None, None),
            "valid" => return Err(format!("{}: a valid file lists codes", at())),
            outcome => {
                let (name, offset) = outcome
                    .split_once('@')
                    .ok_or_else(|| format!("{}: `{outcome}` is not CODE@OFFSET", at()))?;
                let offset = parse_offset(offset)
                    .ok_or_else(|| format!("{}: bad offset in `{outcome}`", at()))?;
                (Some(code(name)?), Some(offset))
            }
        };
        let also = others
            .iter()
            .map(|c| code(c))
            .collect::<Result<Vec<_>, _>>()?;
        let name = format!("{VALIDATE_DIR}/{}", file.trim_end_matches(".vdag"));
        if matches(&name, filter) {
            cases.push(ValidateCaseFile {
                name,
                path: root.join(VALIDATE_DIR).join(file),
                expected,
                offset,
                also,
                description: comment.trim().to_string(),
            });
        }
    }
    for case in trace_cases(root, None)? {
        let name = format!("{TRACE_DIR}/{}", case.name);
        if matches(&name, filter) {
            cases.push(ValidateCaseFile {
                name,
                path: case.dag,
                expected: None,
                offset: None,
                also: Vec::new(),
                description: "a tracer case's file".into(),
            });
        }
    }
    if cases.is_empty() {
        return Err(format!("no validator cases in {} match", root.display()));
    }
    Ok(cases)
}

/// Result of one case.
#[derive(Clone, Debug)]
pub struct Outcome {
    /// Case name.
    pub name: String,
    /// Rays (or files) checked.
    pub checked: usize,
    /// Problems found, one line each (empty: passed).
    pub failures: Vec<String>,
}

impl Outcome {
    /// Whether the case passed.
    pub fn passed(&self) -> bool {
        self.failures.is_empty()
    }

    fn error(name: &str, message: String) -> Self {
        Outcome {
            name: name.into(),
            checked: 0,
            failures: vec![message],
        }
    }
}

/// A tracer to run the cases against.
pub trait TraceBackend {
    /// Answers every ray of a case: one hit per ray, in order.
    fn trace(&self, case: &TraceCaseFiles, file: &[u8], rays: &[Ray]) -> Result<Vec<Hit>, String>;
}

/// The in-process CPU tracer (`dagtrace`).
#[derive(Clone, Copy, Debug, Default)]
pub struct CpuTracer;

impl TraceBackend for CpuTracer {
    fn trace(&self, _case: &TraceCaseFiles, file: &[u8], rays: &[Ray]) -> Result<Vec<Hit>, String> {
        let dag = dagfmt::AnyDag::open(file).map_err(|e| format!("the file does not open: {e}"))?;
        let tracer = dagtrace::Tracer::from_any(&dag)
            .map_err(|e| format!("the tracer refuses the file: {e}"))?;
        tracer
            .trace_batch(rays)
            .map_err(|e| format!("tracing failed: {e}"))
    }
}

/// dagtrace's GPU tracer, in process. One device (and its compiled shaders) is
/// shared by every case; each case uploads its own DAG.
#[derive(Debug)]
pub struct GpuTracer {
    context: dagtrace::gpu::GpuContext,
    options: dagtrace::gpu::GpuOptions,
}

impl GpuTracer {
    /// Opens the default adapter (hardware first, else a software one).
    /// `short_stack` selects the short-stack (restart) variant with that many entries.
    pub fn new(short_stack: Option<u32>) -> Result<Self, String> {
        let options = dagtrace::gpu::GpuOptions {
            stack: match short_stack {
                Some(n) => dagtrace::gpu::StackMode::Short(n),
                None => dagtrace::gpu::StackMode::Full,
            },
            ..Default::default()
        };
        let context = dagtrace::gpu::GpuContext::new(options.adapter)
            .map_err(|e| format!("no GPU tracer: {e}"))?;
        Ok(GpuTracer { context, options })
    }

    /// The adapter's name, for reports.
    pub fn adapter_name(&self) -> String {
        self.context.adapter_name()
    }
}

impl TraceBackend for GpuTracer {
    fn trace(&self, _case: &TraceCaseFiles, file: &[u8], rays: &[Ray]) -> Result<Vec<Hit>, String> {
        let dag = dagfmt::AnyDag::open(file).map_err(|e| format!("the file does not open: {e}"))?;
        let tracer = match &dag {
            dagfmt::AnyDag::V1(d) => {
                dagtrace::gpu::GpuTracer::with_context(&self.context, d, &self.options)
            }
            dagfmt::AnyDag::V2(d) => dagtrace::gpu::GpuTracer::with_context_v2(
                &self.context,
                d.header(),
                d.levels(),
                d.color_table(),
                &self.options,
            ),
        }
        .map_err(|e| format!("the GPU tracer refuses the file: {e}"))?;
        tracer
            .trace(rays)
            .map_err(|e| format!("GPU tracing failed: {e}"))
    }
}

/// Quotes a path for `sh`.
pub fn shell_quote(path: &Path) -> String {
    format!("'{}'", path.to_string_lossy().replace('\'', r"'\''"))
}

/// The default time limit of one external command (`--timeout`).
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(60);

/// What an external command did.
#[derive(Debug)]
pub struct CommandOutput {
    /// How it ended.
    pub status: ExitStatus,
    /// What it wrote to its standard output.
    pub stdout: Vec<u8>,
    /// What it wrote to its standard error.
    pub stderr: Vec<u8>,
}

/// Replaces each `{name}` of `template` by its quoted path.
pub fn substitute(template: &str, substitutions: &[(&str, &Path)]) -> String {
    let mut command = template.to_string();
    for (name, path) in substitutions {
        command = command.replace(&format!("{{{name}}}"), &shell_quote(path));
    }
    command
}

/// Runs `command` with `sh -c` in a process group of its own and waits at
/// most `timeout` for it. When the time is up the whole group is killed (the
/// shell and everything it started) and the error says so.
///
/// The output goes to unnamed temporary files rather than pipes, so that a
/// background process that keeps a pipe open cannot keep the runner waiting.
pub fn run_with_timeout(command: &str, timeout: Duration) -> Result<CommandOutput, String> {
    let temp = |what: &str| {
        tempfile::tempfile().map_err(|e| format!("cannot make a temporary file for {what}: {e}"))
    };
    let (mut stdout, mut stderr) = (temp("standard output")?, temp("standard error")?);
    let out_handle = stdout
        .try_clone()
        .map_err(|e| format!("cannot share a temporary file: {e}"))?;
    let err_handle = stderr
        .try_clone()
        .map_err(|e| format!("cannot share a temporary file: {e}"))?;
    let mut child = Command::new("sh")
        .arg("-c")
        .arg(command)
        .stdin(Stdio::null())
        .stdout(out_handle)
        .stderr(err_handle)
        .process_group(0)
        .spawn()
        .map_err(|e| format!("cannot run `sh -c {command}`: {e}"))?;
    let deadline = Instant::now() + timeout;
    let mut pause = Duration::from_millis(1);
    let status = loop {
        match child.try_wait() {
            Ok(Some(status)) => break status,
            Ok(None) => {}
            Err(e) => return Err(format!("cannot wait for `sh -c {command}`: {e}")),
        }
        let now = Instant::now();
        if now >= deadline {
            kill_group(&mut child);
            return Err(format!(
                "timed out after {} s (the command's process group was killed)",
                timeout.as_secs_f64()
            ));
        }
        std::thread::sleep(pause.min(deadline - now));
        pause = (pause * 2).min(Duration::from_millis(50));
    };
    // The shell is gone; whatever it left running in its group goes too, so
    // that no stray process outlives its case.
    kill_group(&mut child);
    let read = |file: &mut std::fs::File| -> Vec<u8> {
        let mut bytes = Vec::new();
        let _ = file.seek(SeekFrom::Start(0));
        let _ = file.read_to_end(&mut bytes);
        bytes
    };
    Ok(CommandOutput {
        status,
        stdout: read(&mut stdout),
        stderr: read(&mut stderr),
    })
}

/// Kills the process group led by `child` and reaps the child.
fn kill_group(child: &mut Child) {
    if let Ok(pid) = libc::pid_t::try_from(child.id()) {
        // SAFETY: kill(2) with a negative pid signals the process group
        // `pid`, which `process_group(0)` made the child's own; it touches no
        // memory of ours. A group that is already gone makes it fail with
        // ESRCH, which is fine.
        unsafe {
            libc::kill(-pid, libc::SIGKILL);
        }
    }
    let _ = child.wait();
}

/// Runs `command` with `sh -c` after replacing each `{name}` by its quoted
/// path, with a time limit.
fn run_command(
    template: &str,
    substitutions: &[(&str, &Path)],
    timeout: Duration,
) -> Result<CommandOutput, String> {
    run_with_timeout(&substitute(template, substitutions), timeout)
}

fn tail(bytes: &[u8]) -> String {
    let text = String::from_utf8_lossy(bytes);
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(5)..].join(" | ")
}

/// An external tracer driven through the batch protocol.
#[derive(Clone, Debug)]
pub struct ExecTracer {
    /// Command template with `{dag}`, `{rays}` and `{hits}`.
    pub command: String,
    /// Hand the rays over in the binary format instead of the case's text file.
    pub binary_rays: bool,
    /// How long one case may run.
    pub timeout: Duration,
}

impl TraceBackend for ExecTracer {
    fn trace(&self, case: &TraceCaseFiles, _file: &[u8], rays: &[Ray]) -> Result<Vec<Hit>, String> {
        let temp =
            tempfile::tempdir().map_err(|e| format!("cannot make a temporary directory: {e}"))?;
        let hits_path = temp.path().join("hits");
        let rays_path = if self.binary_rays {
            let path = temp.path().join("rays.bin");
            let mut bytes = Vec::new();
            batch::write_rays_binary(&mut bytes, rays).map_err(|e| e.to_string())?;
            std::fs::write(&path, bytes)
                .map_err(|e| format!("cannot write {}: {e}", path.display()))?;
            path
        } else {
            case.rays.clone()
        };
        let output = run_command(
            &self.command,
            &[
                ("dag", &case.dag),
                ("rays", &rays_path),
                ("hits", &hits_path),
            ],
            self.timeout,
        )?;
        if !output.status.success() {
            return Err(format!(
                "the tracer command failed ({}): {}",
                output.status,
                tail(&output.stderr)
            ));
        }
        let bytes =
            std::fs::read(&hits_path).map_err(|e| format!("the tracer wrote no hits file: {e}"))?;
        let hits =
            batch::parse_hits(&bytes).map_err(|e| format!("the hits file is malformed: {e}"))?;
        if hits.len() != rays.len() {
            return Err(format!("{} answers for {} rays", hits.len(), rays.len()));
        }
        Ok(hits)
    }
}

/// At most this many failing rays are listed per case.
pub const MAX_LISTED: usize = 10;

/// The format version a tracer case is run in (CONFORMANCE.md § 1): the
/// committed files are 1.0; the same voxels in 2.0 (VDAG.md § 23) are the
/// committed file upgraded, and every answer expected of the 1.0 file is
/// expected of it too (the attribute index is the same Morton rank).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FormatVersion {
    /// The committed file as it is.
    V1,
    /// The committed file upgraded to format 2.0 (`dagfmt::upgrade`).
    V2,
}

impl FormatVersion {
    /// Both versions, in the order the runner runs them.
    pub const ALL: [FormatVersion; 2] = [FormatVersion::V1, FormatVersion::V2];

    /// The name a case run in this version is reported under: the case's own
    /// name for 1.0, `<case>@2.0` for 2.0.
    pub fn case_name(self, name: &str) -> String {
        match self {
            FormatVersion::V1 => name.to_string(),
            FormatVersion::V2 => format!("{name}@2.0"),
        }
    }

    /// The case file's bytes in this version. A 1.0 file upgrades; a file
    /// already in this version is returned as it is.
    pub fn file_bytes(self, file: Vec<u8>) -> Result<Vec<u8>, String> {
        match (self, dagfmt::AnyDag::open(&file)) {
            (_, Err(e)) => Err(format!("the case file does not open: {e}")),
            (FormatVersion::V1, Ok(dagfmt::AnyDag::V1(_)))
            | (FormatVersion::V2, Ok(dagfmt::AnyDag::V2(_))) => Ok(file),
            (FormatVersion::V2, Ok(dagfmt::AnyDag::V1(dag))) => dagfmt::v2file::upgrade(&dag)
                .map_err(|e| format!("the case file does not upgrade to 2.0: {e}")),
            (FormatVersion::V1, Ok(dagfmt::AnyDag::V2(dag))) => dagfmt::v2file::downgrade(&dag)
                .map_err(|e| format!("the case file does not downgrade to 1.0: {e}")),
        }
    }
}

/// Runs one tracer case on its committed file (format 1.0).
pub fn run_trace_case(case: &TraceCaseFiles, backend: &dyn TraceBackend) -> Outcome {
    run_trace_case_in(case, backend, FormatVersion::V1)
}

/// Runs one tracer case in `version`: a 2.0 run hands the tracer the upgraded
/// file (an external tracer gets it as a temporary `.vdag` in `{dag}`) and
/// judges its answers against the same expectations.
pub fn run_trace_case_in(
    case: &TraceCaseFiles,
    backend: &dyn TraceBackend,
    version: FormatVersion,
) -> Outcome {
    let name = version.case_name(&case.name);
    let read = |p: &Path| std::fs::read(p).map_err(|e| format!("cannot read {}: {e}", p.display()));
    let (file, rays_bytes, expect_text) =
        match (read(&case.dag), read(&case.rays), read(&case.expect)) {
            (Ok(a), Ok(b), Ok(c)) => (a, b, String::from_utf8_lossy(&c).into_owned()),
            (Err(e), _, _) | (_, Err(e), _) | (_, _, Err(e)) => {
                return Outcome::error(&name, e);
            }
        };
    let file = match version.file_bytes(file) {
        Ok(f) => f,
        Err(e) => return Outcome::error(&name, format!("{}: {e}", case.dag.display())),
    };
    // The converted file on disk, for tracers that read a path.
    let temp = match version {
        FormatVersion::V1 => None,
        FormatVersion::V2 => match tempfile::tempdir() {
            Ok(t) => Some(t),
            Err(e) => {
                return Outcome::error(&name, format!("cannot make a temporary directory: {e}"));
            }
        },
    };
    let converted;
    let case = match &temp {
        None => case,
        Some(dir) => {
            let path = dir.path().join(format!("{}.vdag", case.name));
            if let Err(e) = std::fs::write(&path, &file) {
                return Outcome::error(&name, format!("cannot write {}: {e}", path.display()));
            }
            converted = TraceCaseFiles {
                name: name.clone(),
                dag: path,
                ..case.clone()
            };
            &converted
        }
    };
    let rays = match batch::parse_rays(&rays_bytes) {
        Ok(r) => r,
        Err(e) => return Outcome::error(&name, format!("{}: {e}", case.rays.display())),
    };
    let expectations = match expect::parse_case(&expect_text) {
        Ok(expect::CaseExpectation::RejectBatch) => {
            // § 20.2: a level deeper than the file makes the batch an error.
            let failures = match backend.trace(case, &file, &rays) {
                Err(_) => Vec::new(),
                Ok(_) => vec![
                    "the batch has a ray whose level is deeper than the file: the tracer must reject the whole batch (fail, write no answers), but it answered"
                        .to_string(),
                ],
            };
            return Outcome {
                name: name.clone(),
                checked: rays.len(),
                failures,
            };
        }
        Ok(expect::CaseExpectation::Answers(e)) if e.len() == rays.len() => e,
        Ok(expect::CaseExpectation::Answers(e)) => {
            return Outcome::error(
                &name,
                format!("{} expectations for {} rays", e.len(), rays.len()),
            );
        }
        Err(e) => return Outcome::error(&name, format!("{}: {e}", case.expect.display())),
    };
    let hits = match backend.trace(case, &file, &rays) {
        Ok(h) => h,
        Err(e) => return Outcome::error(&name, e),
    };
    let mut failures = Vec::new();
    let mut failed = 0usize;
    for (i, ((ray, expected), hit)) in rays.iter().zip(&expectations).zip(&hits).enumerate() {
        if let Err(reason) = expect::judge(expected, hit) {
            failed += 1;
            if failures.len() < MAX_LISTED {
                failures.push(format!(
                    "ray {i}: {}\n      expected: {}\n      got:      {}\n      because:  {reason}",
                    bless::format_ray(ray),
                    expect::format_expectation(expected),
                    expect::format_answer(hit)
                ));
            }
        }
    }
    if failed > failures.len() {
        failures.push(format!(
            "... and {} more failing rays ({failed} of {} in all)",
            failed - failures.len(),
            rays.len()
        ));
    }
    Outcome {
        name,
        checked: rays.len(),
        failures,
    }
}

/// A validator to run the cases against.
pub trait ValidateBackend {
    /// `Ok(codes)`: the file was rejected with these codes (empty: accepted).
    /// `Err`: the validator could not be run.
    fn validate(&self, path: &Path, file: &[u8]) -> Result<Verdict, String>;
}

/// What a validator said about a file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Accepted.
    Valid,
    /// Rejected; the text it printed (searched for the expected code).
    Invalid(String),
}

/// The in-process validator (`dagfmt::validate`).
#[derive(Clone, Copy, Debug, Default)]
pub struct InProcessValidator;

impl ValidateBackend for InProcessValidator {
    fn validate(&self, _path: &Path, file: &[u8]) -> Result<Verdict, String> {
        let errors = dagfmt::validate::validate(file);
        if errors.is_empty() {
            Ok(Verdict::Valid)
        } else {
            Ok(Verdict::Invalid(
                errors
                    .iter()
                    .map(|e| e.to_string())
                    .collect::<Vec<_>>()
                    .join("\n"),
            ))
        }
    }
}

/// An external validator: `{file}` in the command is replaced by the file's path.
#[derive(Clone, Debug)]
pub struct ExecValidator {
    /// Command template with `{file}`.
    pub command: String,
    /// How long one file may take.
    pub timeout: Duration,
}

impl ValidateBackend for ExecValidator {
    fn validate(&self, path: &Path, _file: &[u8]) -> Result<Verdict, String> {
        let output = run_command(&self.command, &[("file", path)], self.timeout)?;
        if output.status.success() {
            return Ok(Verdict::Valid);
        }
        if output.status.code().is_none() {
            return Err(format!("the validator was killed ({})", output.status));
        }
        let mut text = String::from_utf8_lossy(&output.stdout).into_owned();
        text.push('\n');
        text.push_str(&String::from_utf8_lossy(&output.stderr));
        Ok(Verdict::Invalid(text))
    }
}

/// Whether `text` contains `code` (such as `E041`) as a word of its own.
pub fn mentions_code(text: &str, code: &str) -> bool {
    text.match_indices(code).any(|(at, _)| {
        let before = text[..at].chars().next_back();
        let after = text[at + code.len()..].chars().next();
        !before.is_some_and(|c| c.is_ascii_alphanumeric())
            && !after.is_some_and(|c| c.is_ascii_alphanumeric())
    })
}

/// How strictly a validator's report is checked (spec/CONFORMANCE.md § 6).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Strictness {
    /// The expected code must be reported with its byte offset, and no code
    /// outside the case's expected set may be reported.
    Strict,
    /// The expected code must be reported, anywhere.
    Lenient,
}

/// One error a validator reported: the code and, when the line gives one, the
/// byte offset (`byte N` or `byte 0xN` after the code on the same line).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ReportedError {
    /// The code, such as `E041`.
    pub code: String,
    /// The byte offset, if the line names one.
    pub offset: Option<u64>,
}

/// The errors in a validator's output: every `E` + three digits standing as a
/// word of its own, with the first `byte OFFSET` that follows it on its line.
pub fn reported_errors(text: &str) -> Vec<ReportedError> {
    let mut found = Vec::new();
    for line in text.lines() {
        let words: Vec<&str> = line
            .split(|c: char| !c.is_ascii_alphanumeric())
            .filter(|w| !w.is_empty())
            .collect();
        for (i, word) in words.iter().enumerate() {
            let is_code = word.len() == 4
                && word.starts_with('E')
                && word[1..].bytes().all(|b| b.is_ascii_digit());
            if !is_code {
                continue;
            }
            let offset = words[i + 1..]
                .windows(2)
                .take_while(|w| !(w[0].len() == 4 && w[0].starts_with('E')))
                .find(|w| w[0] == "byte")
                .and_then(|w| parse_offset(w[1]));
            found.push(ReportedError {
                code: (*word).to_string(),
                offset,
            });
        }
    }
    found
}

/// Why a rejection's report does not satisfy strict mode, if it does not.
fn strict_failure(case: &ValidateCaseFile, code: ErrorCode, text: &str) -> Option<String> {
    let reported = reported_errors(text);
    let show =
        |o: Option<u64>| o.map_or_else(|| "no offset".to_string(), |o| format!("byte {o:#x}"));
    let expected_offset = case.offset;
    let mut problems = Vec::new();
    let at_offset = reported.iter().any(|r| {
        r.code == code.code() && (expected_offset.is_none() || r.offset == expected_offset)
    });
    if !at_offset {
        let seen: Vec<String> = reported
            .iter()
            .filter(|r| r.code == code.code())
            .map(|r| show(r.offset))
            .collect();
        problems.push(format!(
            "{code} not reported at {} (reported at: {})",
            show(expected_offset),
            seen.join(", ")
        ));
    }
    let mut foreign: Vec<&str> = reported
        .iter()
        .map(|r| r.code.as_str())
        .filter(|c| *c != code.code() && !case.also.iter().any(|a| a.code() == *c))
        .collect();
    foreign.sort_unstable();
    foreign.dedup();
    if !foreign.is_empty() {
        let mut allowed = vec![code.code()];
        allowed.extend(case.also.iter().map(|c| c.code()));
        problems.push(format!(
            "reported {} outside the case's expected set ({})",
            foreign.join(", "),
            allowed.join(", ")
        ));
    }
    (!problems.is_empty()).then(|| format!("strict: {}", problems.join("; ")))
}

/// Runs one validator case.
pub fn run_validate_case(
    case: &ValidateCaseFile,
    backend: &dyn ValidateBackend,
    strictness: Strictness,
) -> Outcome {
    let file = match std::fs::read(&case.path) {
        Ok(f) => f,
        Err(e) => {
            return Outcome::error(
                &case.name,
                format!("cannot read {}: {e}", case.path.display()),
            );
        }
    };
    let verdict = match backend.validate(&case.path, &file) {
        Ok(v) => v,
        Err(e) => return Outcome::error(&case.name, e),
    };
    let failure = match (&case.expected, verdict) {
        (None, Verdict::Valid) => None,
        (None, Verdict::Invalid(text)) => Some(format!(
            "a valid file was rejected: {}",
            tail(text.as_bytes())
        )),
        (Some(code), Verdict::Valid) => Some(format!("accepted, expected rejection with {code}")),
        (Some(code), Verdict::Invalid(text)) if mentions_code(&text, code.code()) => {
            match strictness {
                Strictness::Lenient => None,
                Strictness::Strict => strict_failure(case, *code, &text),
            }
        }
        (Some(code), Verdict::Invalid(text)) => Some(format!(
            "rejected without reporting {code}; reported: {}",
            tail(text.as_bytes())
        )),
    };
    Outcome {
        name: case.name.clone(),
        checked: 1,
        failures: failure.into_iter().collect(),
    }
}

/// Prints the failures of `outcomes` and the summary line; returns whether all passed.
pub fn report(outcomes: &[Outcome], what: &str) -> bool {
    let mut passed = 0;
    let mut failed = 0;
    let mut checked = 0;
    for o in outcomes {
        checked += o.checked;
        if o.passed() {
            passed += 1;
        } else {
            failed += 1;
            println!("FAIL {}", o.name);
            for f in &o.failures {
                println!("    {f}");
            }
        }
    }
    println!("{checked} {what} checked in {} cases", outcomes.len());
    println!("{passed} passed, {failed} failed");
    failed == 0
}
