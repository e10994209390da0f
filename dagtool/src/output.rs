//! Atomic output (a file appears complete under its name or not at all), by
//! [`dagfmt::output`], with dagtool's wording of its errors.
//!
//! Standard output goes through [`print_stdout`] and [`StdoutReport`]: a
//! reader that closes the pipe early (`dagtool info FILE | head -1`) ends the
//! output quietly instead of panicking in `println!`.

use std::fs::File;
use std::io::{self, BufWriter, ErrorKind, Write};
use std::path::Path;

use dagfmt::output::{self as atomic, OutputError};

use crate::error::ConvertError;

/// Words an output failure for `path` in dagtool's style.
fn output_error(path: &Path, error: OutputError) -> ConvertError {
    match error {
        OutputError::MissingDirectory(dir) => {
            ConvertError::Io(format!("output directory {} does not exist", dir.display()))
        }
        OutputError::IsDirectory => {
            ConvertError::Io(format!("output {} is a directory", path.display()))
        }
        OutputError::Exists => ConvertError::Io(format!(
            "output {} already exists (use --force to overwrite it)",
            path.display()
        )),
        OutputError::NoFileName => {
            ConvertError::Usage(format!("output {} has no file name", path.display()))
        }
        OutputError::CreateTemp(dir, e) => ConvertError::io(
            format!("cannot create a temporary file in {}", dir.display()),
            e,
        ),
        OutputError::Write(e) => ConvertError::io(format!("cannot write {}", path.display()), e),
        OutputError::Sync(e) => ConvertError::io(format!("cannot sync {}", path.display()), e),
        OutputError::Rename(e) => ConvertError::io(
            format!("cannot rename the temporary file to {}", path.display()),
            e,
        ),
    }
}

/// Checks, before any work is done, that `path` can be written: its directory
/// exists and it does not exist unless `force`.
pub fn check_output(path: &Path, force: bool) -> Result<(), ConvertError> {
    atomic::check_output(path, force).map_err(|e| output_error(path, e))
}

/// Writes `path` atomically with `write`, which gets a buffered writer.
/// Returns the number of bytes written.
pub fn write_atomic(
    path: &Path,
    force: bool,
    write: impl FnOnce(&mut BufWriter<&mut File>) -> std::io::Result<()>,
) -> Result<u64, ConvertError> {
    atomic::write_atomic(path, force, write).map_err(|e| output_error(path, e))
}

/// Writes `text` to standard output and flushes it. A closed pipe (the reader
/// has seen enough) is not an error: the rest of the output is dropped.
/// Any other write error is.
pub fn print_stdout(text: &str) -> Result<(), ConvertError> {
    let mut out = StdoutReport::new();
    out.write_all(text.as_bytes())
        .and_then(|()| out.flush())
        .map_err(|e| ConvertError::io("cannot write to standard output", e))
}

/// Standard output for a long report: after a write fails with a broken pipe
/// every further write is dropped silently, so the command finishes its work
/// (and its exit status still says what it found) once nobody is reading.
#[derive(Debug)]
pub struct StdoutReport {
    out: io::StdoutLock<'static>,
    closed: bool,
}

impl StdoutReport {
    /// Locks standard output.
    pub fn new() -> Self {
        StdoutReport {
            out: io::stdout().lock(),
            closed: false,
        }
    }

    fn quiet(&mut self, result: io::Result<()>) -> io::Result<()> {
        match result {
            Err(e) if e.kind() == ErrorKind::BrokenPipe => {
                self.closed = true;
                Ok(())
            }
            other => other,
        }
    }
}

impl Default for StdoutReport {
    fn default() -> Self {
        Self::new()
    }
}

impl Write for StdoutReport {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        if self.closed {
            return Ok(buf.len());
        }
        let result = self.out.write_all(buf);
        self.quiet(result).map(|()| buf.len())
    }

    fn flush(&mut self) -> io::Result<()> {
        if self.closed {
            return Ok(());
        }
        let result = self.out.flush();
        self.quiet(result)
    }
}
