//! Atomic output: a file appears complete under its name or not at all.
//!
//! The data goes to a temporary file in the output's directory (named
//! `NAME.tmpXXXXXX`), is flushed and fsynced, and is then renamed over the
//! final name; the directory is fsynced after the rename. On any error the
//! temporary file is removed. Without `force` an existing file is never
//! replaced (the rename itself refuses, so a file that appears meanwhile is
//! safe too).
//!
//! Standard output goes through [`print_stdout`] and [`StdoutReport`]: a
//! reader that closes the pipe early (`dagtool info FILE | head -1`) ends the
//! output quietly instead of panicking in `println!`.

use std::fs::File;
use std::io::{self, BufWriter, ErrorKind, Write};
use std::path::{Path, PathBuf};

use crate::error::ConvertError;

/// Checks, before any work is done, that `path` can be written: its directory
/// exists and it does not exist unless `force`.
pub fn check_output(path: &Path, force: bool) -> Result<(), ConvertError> {
    let dir = parent_dir(path);
    if !dir.is_dir() {
        return Err(ConvertError::Io(format!(
            "output directory {} does not exist",
            dir.display()
        )));
    }
    if path.is_dir() {
        return Err(ConvertError::Io(format!(
            "output {} is a directory",
            path.display()
        )));
    }
    if !force && path.symlink_metadata().is_ok() {
        return Err(ConvertError::Io(format!(
            "output {} already exists (use --force to overwrite it)",
            path.display()
        )));
    }
    if path.file_name().is_none() {
        return Err(ConvertError::Usage(format!(
            "output {} has no file name",
            path.display()
        )));
    }
    Ok(())
}

fn parent_dir(path: &Path) -> PathBuf {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Writes `path` atomically with `write`, which gets a buffered writer.
/// Returns the number of bytes written.
pub fn write_atomic(
    path: &Path,
    force: bool,
    write: impl FnOnce(&mut BufWriter<&mut File>) -> std::io::Result<()>,
) -> Result<u64, ConvertError> {
    check_output(path, force)?;
    let dir = parent_dir(path);
    let name = path
        .file_name()
        .expect("checked")
        .to_string_lossy()
        .into_owned();
    let prefix = format!("{name}.tmp");
    let mut builder = tempfile::Builder::new();
    builder.prefix(&prefix);
    // tempfile creates files readable by their owner only; the output gets the
    // ordinary permissions of a new file (0666 less the umask), like `cp`.
    #[cfg(unix)]
    builder.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
    let mut tmp = builder.tempfile_in(&dir).map_err(|e| {
        ConvertError::io(
            format!("cannot create a temporary file in {}", dir.display()),
            e,
        )
    })?;
    {
        let mut w = BufWriter::with_capacity(1 << 20, tmp.as_file_mut());
        write(&mut w)
            .and_then(|()| w.flush())
            .map_err(|e| ConvertError::io(format!("cannot write {}", path.display()), e))?;
    }
    tmp.as_file()
        .sync_all()
        .map_err(|e| ConvertError::io(format!("cannot sync {}", path.display()), e))?;
    let len = tmp
        .as_file()
        .metadata()
        .map_err(|e| ConvertError::io(format!("cannot stat {}", path.display()), e))?
        .len();
    let persisted = if force {
        tmp.persist(path)
    } else {
        tmp.persist_noclobber(path)
    };
    persisted.map_err(|e| {
        if e.error.kind() == std::io::ErrorKind::AlreadyExists {
            ConvertError::Io(format!(
                "output {} already exists (use --force to overwrite it)",
                path.display()
            ))
        } else {
            ConvertError::io(
                format!("cannot rename the temporary file to {}", path.display()),
                e.error,
            )
        }
    })?;
    // Make the rename durable. Some file systems do not support fsync on a
    // directory; the data itself is already synced, so that is not an error.
    if let Ok(d) = File::open(&dir) {
        let _ = d.sync_all();
    }
    Ok(len)
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
