//! `dagtool upgrade IN -o OUT [--format-version 1|2]`: converts a file
//! between format 1.0 and format 2.0 (spec §23.11): voxels, attributes, root
//! cube, colour and optional sections are kept; the levels are re-encoded.

use std::io::Write as _;
use std::path::Path;

use dagfmt::AnyDag;
use dagfmt::v2file;

use super::FileBytes;
use crate::error::ConvertError;
use crate::output::write_atomic;

/// What an upgrade did.
#[derive(Clone, Copy, Debug)]
pub struct Upgraded {
    /// Major version of the input.
    pub from: u16,
    /// Major version written.
    pub to: u16,
    /// Bytes of the input (unpacked).
    pub input_bytes: u64,
    /// Bytes written.
    pub output_bytes: u64,
}

/// Writes the format-`version` file of `input`'s voxels to `output`. A file
/// already of that version is copied unchanged.
pub fn upgrade(
    input: &Path,
    output: &Path,
    version: u16,
    force: bool,
) -> Result<Upgraded, ConvertError> {
    if !(1..=2).contains(&version) {
        return Err(ConvertError::Usage(format!(
            "--format-version {version}: the format versions are 1 and 2"
        )));
    }
    crate::output::check_output(output, force)?;
    let file = FileBytes::open(input)?;
    let bytes = file.bytes();
    let named =
        |e: &dyn std::fmt::Display| ConvertError::Input(format!("{}: {e}", input.display()));
    let dag = AnyDag::open(bytes).map_err(|e| named(&e))?;
    let from = dag.version_major();
    let converted = match (&dag, version) {
        (AnyDag::V1(d), 2) => Some(v2file::upgrade(d).map_err(|e| named(&e))?),
        (AnyDag::V2(d), 1) => Some(v2file::downgrade(d).map_err(|e| named(&e))?),
        _ => None,
    };
    let out = converted.as_deref().unwrap_or(bytes);
    let output_bytes = write_atomic(output, force, |w| w.write_all(out))?;
    Ok(Upgraded {
        from,
        to: version,
        input_bytes: bytes.len() as u64,
        output_bytes,
    })
}

/// Writes the 2.0 file of the 1.0 file `input` to `output`, encoded within
/// what is left of the memory `limit` (the resident memory that `meter`
/// counts, the input file and a margin taken; the encoder's tables past it, and its
/// passes over levels whose working set does not fit, go through a scratch
/// file in `scratch_dir`), as `dagtool convert` encodes it: the bytes are
/// those of [`upgrade`].
pub fn upgrade_within(
    input: &Path,
    output: &Path,
    force: bool,
    limit: u64,
    meter: &crate::sysinfo::MemoryMeter,
    scratch_dir: &Path,
) -> Result<Upgraded, ConvertError> {
    crate::output::check_output(output, force)?;
    let file = FileBytes::open(input)?;
    let bytes = file.bytes();
    let named =
        |e: &dyn std::fmt::Display| ConvertError::Input(format!("{}: {e}", input.display()));
    let dag = dagfmt::Dag::open(bytes).map_err(|e| named(&e))?;
    let budget = limit.saturating_sub(
        meter.resident().unwrap_or(0) + bytes.len() as u64 + crate::convert::margin(limit),
    );
    let options = dagfmt::v2enc::EncodeOptions {
        memory_budget: Some(budget),
        refuse_below_least: false,
        scratch_dir: Some(scratch_dir.to_path_buf()),
    };
    let mut failure = None;
    let written = write_atomic(output, force, |w| {
        match v2file::upgrade_to(&dag, &options, w) {
            Ok(_) => Ok(()),
            Err(v2file::ConvertError::Io(e)) => Err(e),
            Err(e) => {
                let message = e.to_string();
                failure = Some(e);
                Err(std::io::Error::other(message))
            }
        }
    });
    if let Some(e) = failure {
        return Err(named(&e));
    }
    Ok(Upgraded {
        from: 1,
        to: 2,
        input_bytes: bytes.len() as u64,
        output_bytes: written?,
    })
}
