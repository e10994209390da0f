//! Atomic output: a file appears complete under its name or not at all.
//!
//! The data goes to a temporary file in the output's directory (named
//! `NAME.tmpXXXXXX`), is flushed and fsynced, and is then renamed over the
//! final name; the directory is fsynced after the rename. On any error the
//! temporary file is removed. Without `force` an existing file is never
//! replaced (the rename itself refuses, so a file that appears meanwhile is
//! safe too).

use std::fs::File;
use std::io::{BufWriter, Write};
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
    let mut tmp = tempfile::Builder::new()
        .prefix(&format!("{name}.tmp"))
        .tempfile_in(&dir)
        .map_err(|e| {
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
