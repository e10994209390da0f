//! `dagtool recompress`: re-encodes a file's colours as a PACKED_COLORS
//! section (spec §12.6) within an error bound, from raw VOXEL_COLORS or from
//! packed colours. The geometry's sections are copied byte for byte, in the
//! file's format version (1.x or 2.0).

use std::path::Path;

use dagfmt::assemble::{FileHeader, FileLayout, SectionInfo};
use dagfmt::packed_colors::{MAX_ERROR_BOUND, PackedColorEncoder, PackedSummary};
use dagfmt::validate::validate;
use dagfmt::{AnyDag, SectionKind};

use crate::cmd::FileBytes;
use crate::error::ConvertError;
use crate::output::{check_output, write_atomic};

/// What a recompression did.
#[derive(Clone, Copy, Debug)]
pub struct RecompressSummary {
    /// Bytes of the input file.
    pub input_bytes: u64,
    /// Bytes of the output file.
    pub output_bytes: u64,
    /// Bytes of the input's colour section.
    pub input_color_bytes: u64,
    /// The packed section written, with the error measured against the
    /// input's (decoded) colours.
    pub packed: PackedSummary,
}

/// Colours encoded per call to the encoder.
const CHUNK: usize = 1 << 16;

/// Reads `input` (validated first), packs its colours within `error_bound`
/// and writes `output` (refusing to replace a file without `force`).
pub fn recompress(
    input: &Path,
    output: &Path,
    error_bound: u8,
    force: bool,
) -> Result<RecompressSummary, ConvertError> {
    if error_bound > MAX_ERROR_BOUND {
        return Err(ConvertError::Usage(format!(
            "--color-error {error_bound} exceeds {MAX_ERROR_BOUND}"
        )));
    }
    check_output(output, force)?;
    let file = FileBytes::open(input)?;
    let bytes = file.bytes();
    let errors = validate(bytes);
    if let Some(first) = errors.first() {
        return Err(ConvertError::Input(format!(
            "{} is not a valid .vdag ({} violation{}, first: {first})",
            input.display(),
            errors.len(),
            if errors.len() == 1 { "" } else { "s" }
        )));
    }
    let dag = AnyDag::open(bytes)
        .map_err(|e| ConvertError::Input(format!("{}: {e}", input.display())))?;
    let Some(table) = dag.color_table() else {
        return Err(ConvertError::Input(format!(
            "{} has no colours to recompress",
            input.display()
        )));
    };
    // The packed section, in memory (about a tenth of the raw colours).
    let mut encoder = PackedColorEncoder::new(error_bound).expect("bound checked");
    let mut section = Vec::new();
    let mut chunk = Vec::with_capacity(CHUNK);
    for c in table.iter() {
        chunk.push(c);
        if chunk.len() == CHUNK {
            encoder.push(&chunk, &mut section);
            chunk.clear();
        }
    }
    encoder.push(&chunk, &mut section);
    let packed = encoder.finish(&mut section);
    let header = dag.header();
    let mut sections = Vec::new();
    let mut sources: Vec<&[u8]> = Vec::new();
    let mut input_color_bytes = 0;
    // A 2.0 file's node levels keep their reference widths (spec §23.10).
    let mut widths = Vec::new();
    for entry in dag.sections() {
        let data = &bytes[entry.offset as usize..(entry.offset + entry.length) as usize];
        match entry.kind {
            SectionKind::VoxelColors | SectionKind::PackedColors => {
                input_color_bytes = entry.length;
                sections.push(SectionInfo::packed_colors(
                    packed.count,
                    section.len() as u64,
                    crc32c::crc32c(&section),
                    packed.trailer.layout,
                ));
                sources.push(&section);
            }
            kind => {
                if kind == SectionKind::NodeLevel {
                    widths.push(entry.widths);
                }
                sections.push(SectionInfo {
                    kind,
                    level: entry.level,
                    pointer_width: entry.pointer_width,
                    length: entry.length,
                    item_count: entry.item_count,
                    crc: entry.crc,
                    version_minor: 0,
                });
                sources.push(data);
            }
        }
    }
    let file_header = FileHeader {
        depth: header.depth,
        attributes: header.attribute_kind,
        root_min: header.root_min,
        root_size: header.root_size,
        voxel_count: header.voxel_count,
    };
    let layout = match dag {
        AnyDag::V1(_) => FileLayout::new(file_header, sections),
        AnyDag::V2(_) => FileLayout::new_v2(file_header, sections, widths),
    }
    .map_err(|e| ConvertError::Input(format!("{}: {e}", input.display())))?;
    let output_bytes = write_atomic(output, force, |w| {
        layout.write_to(w, |index, sink| {
            for part in sources[index].chunks(1 << 20) {
                sink(part)?;
            }
            Ok(())
        })
    })?;
    Ok(RecompressSummary {
        input_bytes: bytes.len() as u64,
        output_bytes,
        input_color_bytes,
        packed,
    })
}
