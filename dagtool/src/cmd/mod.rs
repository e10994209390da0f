//! The file commands: `validate`, `info`, `dump`, `pack`, `unpack`, `recompress`,
//! `upgrade`.

pub mod dump;
pub mod info;
pub mod pack;
pub mod recompress;
pub mod upgrade;
pub mod validate;

use std::path::Path;

use dagfmt::mmap::MappedFile;
use dagfmt::transport;

use crate::error::ConvertError;

/// The bytes of a `.vdag` file: memory-mapped, or unpacked from a `.vdag.zst`
/// transport file.
#[derive(Debug)]
pub enum FileBytes {
    /// A memory map of a plain `.vdag` (or of anything that is not zstd).
    Mapped(MappedFile),
    /// The unpacked contents of a transport file.
    Unpacked(Vec<u8>),
}

impl FileBytes {
    /// Opens `path`: maps it, and unpacks it when it is a zstd frame.
    pub fn open(path: &Path) -> Result<FileBytes, ConvertError> {
        let map = MappedFile::open(path)
            .map_err(|e| ConvertError::io(format!("cannot open {}", path.display()), e))?;
        if transport::is_transport(map.bytes()) {
            let bytes =
                transport::unpack(map.bytes(), transport::DEFAULT_MAX_SIZE).map_err(|e| {
                    ConvertError::Input(format!("{}: cannot unpack: {e}", path.display()))
                })?;
            return Ok(FileBytes::Unpacked(bytes));
        }
        Ok(FileBytes::Mapped(map))
    }

    /// The `.vdag` bytes.
    pub fn bytes(&self) -> &[u8] {
        match self {
            FileBytes::Mapped(m) => m.bytes(),
            FileBytes::Unpacked(v) => v,
        }
    }

    /// Whether the file was a transport file.
    pub fn was_packed(&self) -> bool {
        matches!(self, FileBytes::Unpacked(_))
    }
}

/// The JSON form of a format error.
pub fn error_json(e: &dagfmt::FormatError) -> serde_json::Value {
    serde_json::json!({
        "code": e.code.code(),
        "name": e.code.name(),
        "offset": e.offset,
        "level": e.level,
        "node": e.node,
        "message": e.message,
    })
}
