//! Memory-mapping a file for [`crate::Dag`]: the only file I/O in this crate.

use std::fs::File;
use std::io;
use std::path::Path;

/// A read-only memory map of a whole file.
#[derive(Debug)]
pub struct MappedFile {
    map: Option<memmap2::Mmap>,
}

impl MappedFile {
    /// Maps `path` read-only. An empty file gives an empty slice (mapping zero
    /// bytes is an error on most systems, so nothing is mapped then).
    pub fn open(path: &Path) -> io::Result<Self> {
        let file = File::open(path)?;
        let meta = file.metadata()?;
        if !meta.is_file() {
            return Err(io::Error::new(io::ErrorKind::InvalidInput, "not a regular file"));
        }
        if meta.len() == 0 {
            return Ok(MappedFile { map: None });
        }
        // SAFETY: the map is read-only and lives as long as `MappedFile`. The
        // remaining hazard is another process truncating or rewriting the file
        // while it is mapped: reads past a truncation raise SIGBUS and rewrites
        // show through. The reader cannot defend against that from inside the
        // process; spec/VDAG.md § Memory-mapped files states the rule (never
        // modify a .vdag in place; writers replace files by rename, as ours do).
        let map = unsafe { memmap2::Mmap::map(&file)? };
        Ok(MappedFile { map: Some(map) })
    }

    /// The mapped bytes.
    pub fn bytes(&self) -> &[u8] {
        self.map.as_deref().unwrap_or(&[])
    }
}
