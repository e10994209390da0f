//! `dagtool pack` / `dagtool unpack`: the zstd transport form (`.vdag.zst`).
//!
//! Both directions validate the `.vdag` (before packing, after unpacking), so
//! a transport file always holds a valid file and an unpacked file is never
//! written unless it is valid.

use std::io::Write;
use std::path::Path;

use dagfmt::mmap::MappedFile;
use dagfmt::transport;
use dagfmt::validate::validate;

use crate::error::ConvertError;
use crate::output::{check_output, write_atomic};

fn check_valid(name: &Path, bytes: &[u8]) -> Result<(), ConvertError> {
    let errors = validate(bytes);
    if let Some(first) = errors.first() {
        return Err(ConvertError::Input(format!(
            "{} is not a valid .vdag ({} violation{}, first: {first})",
            name.display(),
            errors.len(),
            if errors.len() == 1 { "" } else { "s" }
        )));
    }
    Ok(())
}

/// Packs `input` (a `.vdag`) into `output` (a `.vdag.zst`) at zstd `level`.
/// Returns (input bytes, output bytes).
pub fn pack(
    input: &Path,
    output: &Path,
    level: i32,
    force: bool,
) -> Result<(u64, u64), ConvertError> {
    check_output(output, force)?;
    let map = MappedFile::open(input)
        .map_err(|e| ConvertError::io(format!("cannot open {}", input.display()), e))?;
    if transport::is_transport(map.bytes()) {
        return Err(ConvertError::Input(format!(
            "{} is already a zstd transport file",
            input.display()
        )));
    }
    check_valid(input, map.bytes())?;
    let packed = transport::pack(map.bytes(), level)
        .map_err(|e| ConvertError::Input(format!("cannot pack {}: {e}", input.display())))?;
    let written = write_atomic(output, force, |w| w.write_all(&packed))?;
    Ok((map.bytes().len() as u64, written))
}

/// Unpacks `input` (a `.vdag.zst`) into `output` (a `.vdag`), refusing frames
/// that declare more than `max_size` bytes. Returns (input bytes, output bytes).
pub fn unpack(
    input: &Path,
    output: &Path,
    max_size: u64,
    force: bool,
) -> Result<(u64, u64), ConvertError> {
    check_output(output, force)?;
    let map = MappedFile::open(input)
        .map_err(|e| ConvertError::io(format!("cannot open {}", input.display()), e))?;
    let bytes = transport::unpack(map.bytes(), max_size)
        .map_err(|e| ConvertError::Input(format!("cannot unpack {}: {e}", input.display())))?;
    check_valid(input, &bytes)?;
    let written = write_atomic(output, force, |w| w.write_all(&bytes))?;
    Ok((map.bytes().len() as u64, written))
}
