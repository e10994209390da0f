//! `conformance`: runs the `.vdag` conformance suite (spec/CONFORMANCE.md).
//!
//! ```text
//! conformance run [--tracer cpu|gpu [--short-stack N] | --exec 'CMD {dag} {rays} {hits}'] [--binary-rays]
//! conformance validate [--exec 'CMD {file}']
//! conformance bless [-o DIR]
//! conformance list
//! conformance validate-file FILE
//! ```
//!
//! `run` and `validate` print each failing case with the expected and actual
//! answers, end with the line `N passed, N failed` and exit with status 1 when
//! a case fails (2 when the suite itself cannot run).

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand, ValueEnum};
use conformance::suite::{self, ExecTracer, ExecValidator, TraceBackend, ValidateBackend};
use conformance::{bless, malformed};

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
        /// The cases directory (default: the committed one).
        #[arg(long, value_name = "DIR")]
        cases: Option<PathBuf>,
        /// Only cases whose name contains this text.
        #[arg(long, value_name = "TEXT")]
        filter: Option<String>,
    },
    /// Runs every validator case against a validator.
    Validate {
        /// An external validator: a shell command in which {file} is replaced by
        /// the file's path. It must exit 0 for valid files, and exit non-zero
        /// printing the error code (such as E041) for invalid ones.
        #[arg(long, value_name = "COMMAND")]
        exec: Option<String>,
        /// The cases directory (default: the committed one).
        #[arg(long, value_name = "DIR")]
        cases: Option<PathBuf>,
        /// Only cases whose name contains this text.
        #[arg(long, value_name = "TEXT")]
        filter: Option<String>,
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
            short_stack,
            cases,
            filter,
        } => {
            let root = cases.unwrap_or_else(suite::default_cases_dir);
            let backend: Box<dyn TraceBackend> = match (exec, tracer) {
                (Some(command), _) => Box::new(ExecTracer {
                    command,
                    binary_rays,
                }),
                (None, TracerKind::Cpu) => Box::new(suite::CpuTracer),
                (None, TracerKind::Gpu) => {
                    let gpu = suite::GpuTracer::new(short_stack)?;
                    println!("GPU adapter: {}", gpu.adapter_name());
                    Box::new(gpu)
                }
            };
            let cases = suite::trace_cases(&root, filter.as_deref())?;
            let outcomes: Vec<_> = cases
                .iter()
                .map(|c| suite::run_trace_case(c, backend.as_ref()))
                .collect();
            Ok(suite::report(&outcomes, "rays"))
        }
        Cmd::Validate {
            exec,
            cases,
            filter,
        } => {
            let root = cases.unwrap_or_else(suite::default_cases_dir);
            let backend: Box<dyn ValidateBackend> = match exec {
                Some(command) => Box::new(ExecValidator { command }),
                None => Box::new(suite::InProcessValidator),
            };
            let cases = suite::validate_cases(&root, filter.as_deref())?;
            let outcomes: Vec<_> = cases
                .iter()
                .map(|c| suite::run_validate_case(c, backend.as_ref()))
                .collect();
            Ok(suite::report(&outcomes, "files"))
        }
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
