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
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                "not a regular file",
            ));
        }
        if meta.len() == 0 {
            return Ok(MappedFile { map: None });
        }
        // SAFETY: the map is read-only (nothing is ever written through it)
        // and lives as long as `MappedFile`, which hands out only shared
        // borrows of it. `Mmap::map` is unsafe because the bytes are only
        // stable while no one changes the file: if another process truncates
        // it while it is mapped, touching a page wholly past the new end
        // raises SIGBUS and kills this process; if it rewrites the file in
        // place, the new bytes show through the map (after validation, under
        // a `&[u8]` that was meant to be immutable). No reader can prevent
        // that from inside the process. spec/VDAG.md §18 (Memory-mapped
        // files and replacing files) forbids writers to modify a .vdag in
        // place; ours write a temporary file and rename it, which leaves an
        // existing map on the old, unchanged file. Callers that cannot trust
        // the writers of a file read it into memory instead.
        let map = unsafe { memmap2::Mmap::map(&file)? };
        Ok(MappedFile { map: Some(map) })
    }

    /// The mapped bytes.
    pub fn bytes(&self) -> &[u8] {
        self.map.as_deref().unwrap_or(&[])
    }
}
