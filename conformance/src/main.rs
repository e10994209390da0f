//! `conformance`: runs the `.vdag` conformance suite (spec/CONFORMANCE.md).
//!
//! ```text
//! conformance run [--tracer cpu|gpu [--short-stack N] | --exec 'CMD {dag} {rays} {hits}'] [--binary-rays] [--timeout S] [--format-version 1|2|all]
//! conformance validate [--exec 'CMD {file}'] [--lenient] [--timeout S]
//! conformance judge FILE.vdag --rays RAYS (--hits HITS | --exec 'CMD {dag} {rays} {hits}') [--timeout S]
//! conformance bless [-o DIR]
//! conformance list
//! conformance validate-file FILE
//! ```
//!
//! `run` and `validate` print each failing case with the expected and actual
//! answers, end with the line `N passed, N failed` and exit with status 1 when
//! a case fails (2 when the suite itself cannot run). `judge` judges any
//! answers on any file by the acceptance rule of spec/VDAG.md § 20.8: one line
//! per rejected ray, a summary, status 1 when an answer is rejected.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use clap::{Parser, Subcommand, ValueEnum};
use conformance::judge::Judge;
use conformance::suite::{
    self, ExecTracer, ExecValidator, FormatVersion, TraceBackend, ValidateBackend,
};
use conformance::{bless, expect, malformed};
use dagfmt::batch;

#[derive(Parser, Debug)]
#[command(
    name = "conformance",
    version,
    about = "The .vdag conformance suite: tracer and validator cases, and a runner"
)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum TracerKind {
    /// dagtrace's CPU tracer, in process.
    Cpu,
    /// dagtrace's GPU tracer (wgpu), in process, on the default adapter.
    Gpu,
}

/// `run --format-version`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum VersionChoice {
    /// Format 1.0 only (the committed files).
    #[value(name = "1")]
    V1,
    /// Format 2.0 only (the committed files upgraded).
    #[value(name = "2")]
    V2,
    /// Both, 1.0 first.
    All,
}

impl VersionChoice {
    fn versions(self) -> &'static [FormatVersion] {
        match self {
            VersionChoice::V1 => &[FormatVersion::V1],
            VersionChoice::V2 => &[FormatVersion::V2],
            VersionChoice::All => &FormatVersion::ALL,
        }
    }
}

#[derive(Subcommand, Debug)]
enum Cmd {
    /// Runs every tracer case against a tracer.
    Run {
        /// The in-process tracer to test (ignored with --exec).
        #[arg(long, value_enum, default_value = "cpu")]
        tracer: TracerKind,
        /// An external tracer: a shell command in which {dag}, {rays} and {hits}
        /// are replaced by the case's .vdag path, its rays path and the path
        /// the hits must be written to.
        #[arg(long, value_name = "COMMAND")]
        exec: Option<String>,
        /// With --tracer gpu: use the short-stack (restart) variant with this many entries.
        #[arg(long, value_name = "N")]
        short_stack: Option<u32>,
        /// Give the external tracer the rays in the binary batch format.
        #[arg(long, requires = "exec")]
        binary_rays: bool,
        /// Seconds one case of the external tracer may take; past it the
        /// case fails and the command's process group is killed.
        #[arg(long, value_name = "SECONDS", default_value = "60", value_parser = parse_timeout)]
        timeout: Duration,
        /// The cases directory (default: the committed one).
        #[arg(long, value_name = "DIR")]
        cases: Option<PathBuf>,
        /// Only cases whose name contains this text.
        #[arg(long, value_name = "TEXT")]
        filter: Option<String>,
        /// The format versions each case runs in: its committed 1.0 file, the
        /// same voxels upgraded to 2.0 (reported as `<case>@2.0`), or both.
        #[arg(long, value_enum, default_value = "all")]
        format_version: VersionChoice,
    },
    /// Runs every validator case against a validator.
    Validate {
        /// An external validator: a shell command in which {file} is replaced by
        /// the file's path. It must exit 0 for valid files, and exit non-zero
        /// printing the error code (such as E041) for invalid ones.
        #[arg(long, value_name = "COMMAND")]
        exec: Option<String>,
        /// Only require the expected code somewhere in the output. By default
        /// (strict) it must be reported with its byte offset, and no code
        /// outside the case's expected set may be reported.
        #[arg(long)]
        lenient: bool,
        /// Seconds the external validator may take per file; past it the case
        /// fails and the command's process group is killed.
        #[arg(long, value_name = "SECONDS", default_value = "60", value_parser = parse_timeout)]
        timeout: Duration,
        /// The cases directory (default: the committed one).
        #[arg(long, value_name = "DIR")]
        cases: Option<PathBuf>,
        /// Only cases whose name contains this text.
        #[arg(long, value_name = "TEXT")]
        filter: Option<String>,
    },
    /// Judges a tracer's answers for any file and rays by the acceptance rule
    /// of spec/VDAG.md § 20.8: prints one line per rejected answer and a
    /// summary; exits 1 when an answer is rejected.
    Judge {
        /// The .vdag file the rays were traced in (it must be valid).
        file: PathBuf,
        /// The rays (text or binary batch).
        #[arg(long, value_name = "RAYS")]
        rays: PathBuf,
        /// The answers (text or binary hit batch), one per ray.
        #[arg(
            long,
            value_name = "HITS",
            required_unless_present = "exec",
            conflicts_with = "exec"
        )]
        hits: Option<PathBuf>,
        /// Run a tracer first: a shell command in which {dag}, {rays} and
        /// {hits} are replaced by the file, the rays and the path the answers
        /// must be written to.
        #[arg(long, value_name = "COMMAND")]
        exec: Option<String>,
        /// Seconds the command may take; past it the judge gives up and the
        /// command's process group is killed.
        #[arg(long, value_name = "SECONDS", default_value = "60", value_parser = parse_timeout, requires = "exec")]
        timeout: Duration,
    },
    /// Regenerates every case file (deterministically) into the cases directory.
    Bless {
        /// Where to write (default: the committed cases directory; `--out` is
        /// an older spelling that still works).
        #[arg(short, long, alias = "out", value_name = "DIR")]
        output: Option<PathBuf>,
    },
    /// Lists the cases.
    List {
        /// The cases directory (default: the committed one).
        #[arg(long, value_name = "DIR")]
        cases: Option<PathBuf>,
    },
    /// Validates one file with dagfmt's validator, following the external
    /// validator protocol (a reference adapter: exit 0 if valid, else print the
    /// errors and exit 1).
    ValidateFile {
        /// The .vdag file.
        file: PathBuf,
    },
}

fn parse_timeout(text: &str) -> Result<Duration, String> {
    match text.parse::<f64>() {
        Ok(s) if s > 0.0 && s <= 1e9 => Ok(Duration::from_secs_f64(s)),
        _ => Err(format!("`{text}` is not a number of seconds in (0, 1e9]")),
    }
}

fn read_file(path: &Path) -> Result<Vec<u8>, String> {
    std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))
}

/// `conformance judge`: prints each rejected answer and a summary; `Ok(true)`
/// when every answer is accepted.
fn judge(
    file: &Path,
    rays_path: &Path,
    hits: Option<PathBuf>,
    exec: Option<String>,
    timeout: Duration,
) -> Result<bool, String> {
    let bytes = read_file(file)?;
    // The judge reads the voxels through the 1.0 reader: a 2.0 file is
    // judged on its 1.0 form, made in memory (the same voxels and indices).
    let named = |e: &dyn std::fmt::Display| format!("{}: {e}", file.display());
    let v1_form = match dagfmt::AnyDag::open(&bytes).map_err(|e| named(&e))? {
        dagfmt::AnyDag::V1(_) => None,
        dagfmt::AnyDag::V2(d) => Some(dagfmt::v2file::downgrade(&d).map_err(|e| named(&e))?),
    };
    let dag = dagfmt::Dag::open(v1_form.as_deref().unwrap_or(&bytes)).map_err(|e| named(&e))?;
    let judge = Judge::new(&dag).map_err(|e| format!("{}: {e}", file.display()))?;
    let rays = batch::parse_rays(&read_file(rays_path)?)
        .map_err(|e| format!("{}: {e}", rays_path.display()))?;
    judge
        .check_levels(&rays)
        .map_err(|e| format!("{}: {e}", rays_path.display()))?;
    let (hits_bytes, hits_name) = match (hits, exec) {
        (Some(path), _) => (read_file(&path)?, path.display().to_string()),
        (None, Some(command)) => {
            let temp = tempfile::tempdir()
                .map_err(|e| format!("cannot make a temporary directory: {e}"))?;
            let hits_path = temp.path().join("hits");
            let command = suite::substitute(
                &command,
                &[("dag", file), ("rays", rays_path), ("hits", &hits_path)],
            );
            let output = suite::run_with_timeout(&command, timeout)
                .map_err(|e| format!("the tracer command: {e}"))?;
            if !output.status.success() {
                let stderr = String::from_utf8_lossy(&output.stderr);
                return Err(format!(
                    "the tracer command failed ({}): {}",
                    output.status,
                    stderr.lines().last().unwrap_or("")
                ));
            }
            let bytes = std::fs::read(&hits_path)
                .map_err(|e| format!("the tracer command wrote no hits file: {e}"))?;
            (bytes, "the tracer's hits".to_string())
        }
        (None, None) => return Err("give --hits or --exec".into()),
    };
    let answers = batch::parse_hits(&hits_bytes).map_err(|e| format!("{hits_name}: {e}"))?;
    if answers.len() != rays.len() {
        return Err(format!(
            "{hits_name}: {} answers for {} rays",
            answers.len(),
            rays.len()
        ));
    }
    let verdicts = judge.judge_batch(&rays, &answers);
    let mut rejected = 0usize;
    let mut out = std::io::stdout().lock();
    for (i, verdict) in verdicts.iter().enumerate() {
        if let Some(rejection) = verdict {
            rejected += 1;
            use std::io::Write as _;
            // A closed standard output ends the listing, not the judgement.
            let _ = writeln!(
                out,
                "ray {i}: {} | answer: {} | {rejection}",
                bless::format_ray(&rays[i]),
                expect::format_answer(&answers[i])
            );
        }
    }
    drop(out);
    println!(
        "{} rays judged: {} accepted, {rejected} rejected",
        rays.len(),
        rays.len() - rejected
    );
    Ok(rejected == 0)
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::from(1),
        Err(message) => {
            eprintln!("conformance: {message}");
            ExitCode::from(2)
        }
    }
}

fn run(cli: Cli) -> Result<bool, String> {
    match cli.command {
        Cmd::Run {
            tracer,
            exec,
            binary_rays,
            timeout,
            short_stack,
            cases,
            filter,
            format_version,
        } => {
            let root = cases.unwrap_or_else(suite::default_cases_dir);
            let backend: Box<dyn TraceBackend> = match (exec, tracer) {
                (Some(command), _) => Box::new(ExecTracer {
                    command,
                    binary_rays,
                    timeout,
                }),
                (None, TracerKind::Cpu) => Box::new(suite::CpuTracer),
                (None, TracerKind::Gpu) => {
                    let gpu = suite::GpuTracer::new(short_stack)?;
                    println!("GPU adapter: {}", gpu.adapter_name());
                    Box::new(gpu)
                }
            };
            let cases = suite::trace_cases(&root, filter.as_deref())?;
            let outcomes: Vec<_> = format_version
                .versions()
                .iter()
                .flat_map(|&v| cases.iter().map(move |c| (c, v)))
                .map(|(c, v)| suite::run_trace_case_in(c, backend.as_ref(), v))
                .collect();
            Ok(suite::report(&outcomes, "rays"))
        }
        Cmd::Validate {
            exec,
            lenient,
            timeout,
            cases,
            filter,
        } => {
            let root = cases.unwrap_or_else(suite::default_cases_dir);
            let backend: Box<dyn ValidateBackend> = match exec {
                Some(command) => Box::new(ExecValidator { command, timeout }),
                None => Box::new(suite::InProcessValidator),
            };
            let strictness = if lenient {
                suite::Strictness::Lenient
            } else {
                suite::Strictness::Strict
            };
            let cases = suite::validate_cases(&root, filter.as_deref())?;
            let outcomes: Vec<_> = cases
                .iter()
                .map(|c| suite::run_validate_case(c, backend.as_ref(), strictness))
                .collect();
            Ok(suite::report(&outcomes, "files"))
        }
        Cmd::Judge {
            file,
            rays,
            hits,
            exec,
            timeout,
        } => judge(&file, &rays, hits, exec, timeout),
        Cmd::Bless { output } => {
            let root = output.unwrap_or_else(suite::default_cases_dir);
            let files = bless::generate()?;
            let written = bless::write(&root, &files)
                .map_err(|e| format!("cannot write {}: {e}", root.display()))?;
            println!("{written} case files in {}", root.display());
            Ok(true)
        }
        Cmd::List { cases } => {
            let root = cases.unwrap_or_else(suite::default_cases_dir);
            for case in suite::trace_cases(&root, None)? {
                let text = std::fs::read_to_string(&case.rays).unwrap_or_default();
                let about = text
                    .lines()
                    .nth(1)
                    .and_then(|l| l.strip_prefix("# "))
                    .unwrap_or(&case.name)
                    .to_string();
                println!("trace    {about}");
            }
            for case in suite::validate_cases(&root, Some("validate/"))? {
                let outcome = case
                    .expected
                    .map_or_else(|| "valid".to_string(), |c| c.to_string());
                println!("validate {} [{outcome}]: {}", case.name, case.description);
            }
            for (code, why) in malformed::UNTESTABLE {
                println!("untested {code}: {why}");
            }
            Ok(true)
        }
        Cmd::ValidateFile { file } => {
            let bytes =
                std::fs::read(&file).map_err(|e| format!("cannot read {}: {e}", file.display()))?;
            let errors = dagfmt::validate::validate(&bytes);
            for e in &errors {
                println!("{e}");
            }
            Ok(errors.is_empty())
        }
    }
}
