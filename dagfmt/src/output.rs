//! Atomic output files, for the command-line tools (feature `output`): a file
//! appears complete under its name or not at all.
//!
//! The data goes to a temporary file in the output's directory (named
//! `NAME.tmpXXXXXX`), is flushed and fsynced, and is then renamed over the
//! final name; the directory is fsynced after the rename. On any error the
//! temporary file is removed. Without `force` an existing file is never
//! replaced (the rename itself refuses, so a file that appears meanwhile is
//! safe too). Renaming, rather than writing in place, also means a file that
//! another process has memory-mapped is never changed underneath it
//! (spec/VDAG.md § 18).
//!
//! Errors are structured, not worded: each tool words them in its own style.

use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};

/// Why an output file cannot be, or was not, written.
#[derive(Debug)]
pub enum OutputError {
    /// The output's directory does not exist (or is not a directory).
    MissingDirectory(PathBuf),
    /// The output path is a directory.
    IsDirectory,
    /// The output exists and replacing it was not allowed.
    Exists,
    /// The path names no file (such as `dir/..`).
    NoFileName,
    /// No temporary file could be created in this directory.
    CreateTemp(PathBuf, io::Error),
    /// Writing or flushing the data failed.
    Write(io::Error),
    /// Syncing the written data to disk (or reading its size back) failed.
    Sync(io::Error),
    /// Renaming the temporary file into place failed.
    Rename(io::Error),
}

/// The directory `path` is written into (`.` for a bare file name).
pub fn output_dir(path: &Path) -> PathBuf {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Checks, before any work is done, that `path` can be written: its directory
/// exists, it is not a directory, and it does not exist unless `force`.
pub fn check_output(path: &Path, force: bool) -> Result<(), OutputError> {
    let dir = output_dir(path);
    if !dir.is_dir() {
        return Err(OutputError::MissingDirectory(dir));
    }
    if path.is_dir() {
        return Err(OutputError::IsDirectory);
    }
    if !force && path.symlink_metadata().is_ok() {
        return Err(OutputError::Exists);
    }
    if path.file_name().is_none() {
        return Err(OutputError::NoFileName);
    }
    Ok(())
}

/// Writes `path` atomically with `write`, which gets a buffered writer, after
/// [`check_output`]. Returns the number of bytes written.
pub fn write_atomic(
    path: &Path,
    force: bool,
    write: impl FnOnce(&mut BufWriter<&mut File>) -> io::Result<()>,
) -> Result<u64, OutputError> {
    check_output(path, force)?;
    let dir = output_dir(path);
    let name = path.file_name().ok_or(OutputError::NoFileName)?;
    let prefix = format!("{}.tmp", name.to_string_lossy());
    let mut builder = tempfile::Builder::new();
    builder.prefix(&prefix);
    // tempfile creates files readable by their owner only; the output gets the
    // ordinary permissions of a new file (0666 less the umask), like `cp`.
    #[cfg(unix)]
    builder.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
    let mut tmp = builder
        .tempfile_in(&dir)
        .map_err(|e| OutputError::CreateTemp(dir.clone(), e))?;
    {
        let mut w = BufWriter::with_capacity(1 << 20, tmp.as_file_mut());
        write(&mut w)
            .and_then(|()| w.flush())
            .map_err(OutputError::Write)?;
    }
    tmp.as_file().sync_all().map_err(OutputError::Sync)?;
    let len = tmp.as_file().metadata().map_err(OutputError::Sync)?.len();
    let persisted = if force {
        tmp.persist(path)
    } else {
        tmp.persist_noclobber(path)
    };
    persisted.map_err(|e| match e.error.kind() {
        io::ErrorKind::AlreadyExists => OutputError::Exists,
        _ => OutputError::Rename(e.error),
    })?;
    // Make the rename durable. Some file systems do not support fsync on a
    // directory; the data itself is already synced, so that is not an error.
    if let Ok(d) = File::open(&dir) {
        let _ = d.sync_all();
    }
    Ok(len)
}
