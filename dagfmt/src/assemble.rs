//! Assembling a `.vdag` file from a description of its sections: the one
//! writer of file headers and section tables.
//!
//! A [`FileLayout`] holds the header fields that do not follow from the
//! sections ([`FileHeader`]) and, per section, everything of its table entry
//! but the offset ([`SectionInfo`]): offsets follow from the lengths (§6). Its
//! constructor checks the sections against the format's rules (level order,
//! pointer widths, lengths, the colour section, the limits of §16), so a layout
//! always describes a file the validator accepts as far as the table goes.
//! [`FileLayout::write_to`] writes the header and the table, then streams the
//! bytes of each section from a callback and checks that they have the length
//! and CRC-32C the table declares; a writer whose section bytes come from
//! elsewhere (the temporary files of an out-of-core build) therefore cannot
//! produce a file whose table disagrees with its data.
//!
//! [`BuiltDag`](crate::builder::BuiltDag) writes through here too, and node
//! records are encoded by [`layout::encode_node_record`], so every file this
//! library writes has one writer of headers and one encoder of records.

use std::io::{self, Write};

use crate::builder::BuildError;
use crate::layout::{
    self, AttributeKind, HEADER_SIZE, MAGIC, MAX_DEPTH, MAX_FILE_SIZE, MAX_LEAF_COUNT,
    MAX_NODE_LEVEL_BYTES, MAX_SECTIONS, MIN_DEPTH, RawHeader, RawSectionEntry, SECTION_ENTRY_SIZE,
    SECTION_KIND_OPTIONAL_BIT, SectionKind,
};
use crate::packed_colors::BlockLayout;

/// One section of a file: its table entry without the offset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SectionInfo {
    /// What the section holds.
    pub kind: SectionKind,
    /// Level of a node-level or leaf-level section; 0 otherwise.
    pub level: u8,
    /// Pointer width (1 to 4) of a node-level section; 0 otherwise.
    pub pointer_width: u8,
    /// Length in bytes.
    pub length: u64,
    /// Records, leaves or colours in the section.
    pub item_count: u64,
    /// CRC-32C of the section's bytes.
    pub crc: u32,
    /// The lowest minor version of format 1 that defines the section's
    /// contents (§22.1): 0 for the sections of 1.0, 1 or 2 for packed colours.
    pub version_minor: u16,
}

impl SectionInfo {
    /// A node-level section of `level`: `item_count` records in `length`
    /// bytes with pointers of `pointer_width` bytes.
    pub fn node_level(
        level: u8,
        pointer_width: u8,
        length: u64,
        item_count: u64,
        crc: u32,
    ) -> Self {
        SectionInfo {
            kind: SectionKind::NodeLevel,
            level,
            pointer_width,
            length,
            item_count,
            crc,
            version_minor: 0,
        }
    }

    /// The leaf-level section (`level` = depth − 2) of `leaves` 64-bit masks.
    pub fn leaf_level(level: u8, leaves: u64, crc: u32) -> Self {
        SectionInfo {
            kind: SectionKind::LeafLevel,
            level,
            pointer_width: 0,
            length: leaves.saturating_mul(8),
            item_count: leaves,
            crc,
            version_minor: 0,
        }
    }

    /// A colour section of `colors` RGBA8 colours.
    pub fn voxel_colors(colors: u64, crc: u32) -> Self {
        SectionInfo {
            kind: SectionKind::VoxelColors,
            level: 0,
            pointer_width: 0,
            length: colors.saturating_mul(4),
            item_count: colors,
            crc,
            version_minor: 0,
        }
    }

    /// A packed colour section (kind 4) of `colors` colours in `length` bytes,
    /// its blocks laid out as `layout` says (format 1.1's layout, or one that
    /// needs format 1.2).
    pub fn packed_colors(colors: u64, length: u64, crc: u32, layout: BlockLayout) -> Self {
        SectionInfo {
            kind: SectionKind::PackedColors,
            level: 0,
            pointer_width: 0,
            length,
            item_count: colors,
            crc,
            version_minor: if layout.is_v1_1() {
                layout::VERSION_MINOR_PACKED_COLORS
            } else {
                layout::VERSION_MINOR_SPLIT_COLORS
            },
        }
    }

    /// Units a pointer into this section counts: words of a node level,
    /// leaves of the leaf level (§9.1).
    fn units(&self) -> u64 {
        match self.kind {
            SectionKind::LeafLevel => self.item_count,
            _ => self.length / 4,
        }
    }
}

/// The header fields of a file that do not follow from its sections.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FileHeader {
    /// Depth D (2 ..= 21).
    pub depth: u8,
    /// What the nodes' attribute bits mean.
    pub attributes: AttributeKind,
    /// World-space minimum corner of the root cube.
    pub root_min: [f64; 3],
    /// World-space edge of the root cube (finite, positive).
    pub root_size: f64,
    /// Set voxels in the volume.
    pub voxel_count: u64,
}

/// A checked description of a whole file: header fields and sections, with
/// the sections placed. See the [module documentation](self).
#[derive(Clone, Debug, PartialEq)]
pub struct FileLayout {
    header: FileHeader,
    sections: Vec<SectionInfo>,
    /// Format 2.0 (§23): each node level's reference widths, stored in
    /// bytes 5..8 of its entry; `None` for a 1.0 file.
    widths2: Option<Vec<[u8; 3]>>,
    offsets: Vec<u64>,
    file_size: u64,
}

fn invalid(what: String) -> BuildError {
    BuildError::Invalid { what }
}

impl FileLayout {
    /// Checks `sections` (the level sections root first, then the others)
    /// against the rules of the format and places them.
    pub fn new(header: FileHeader, sections: Vec<SectionInfo>) -> Result<Self, BuildError> {
        Self::place(header, sections, None)
    }

    /// A format 2.0 file (spec §23): like [`FileLayout::new`], with the
    /// reference widths of each node level (`widths[l]` for level `l`, root
    /// first) in place of the 1.0 pointer widths; the `pointer_width` of the
    /// node-level [`SectionInfo`]s is ignored.
    pub fn new_v2(
        header: FileHeader,
        mut sections: Vec<SectionInfo>,
        widths: Vec<[u8; 3]>,
    ) -> Result<Self, BuildError> {
        for (s, w) in sections.iter_mut().zip(&widths) {
            if s.kind == SectionKind::NodeLevel {
                s.pointer_width = w[0];
            }
        }
        Self::place(header, sections, Some(widths))
    }

    /// The major format version the layout writes: 1 or 2.
    pub fn version_major(&self) -> u16 {
        if self.widths2.is_some() { 2 } else { 1 }
    }

    fn place(
        header: FileHeader,
        sections: Vec<SectionInfo>,
        widths2: Option<Vec<[u8; 3]>>,
    ) -> Result<Self, BuildError> {
        check(&header, &sections, widths2.as_deref())?;
        let mut offsets = Vec::with_capacity(sections.len());
        let mut offset =
            layout::align_section((HEADER_SIZE + sections.len() * SECTION_ENTRY_SIZE) as u64);
        let mut file_size = offset;
        for s in &sections {
            offsets.push(offset);
            file_size = offset + s.length;
            offset = layout::align_section(file_size);
        }
        if file_size > MAX_FILE_SIZE {
            return Err(BuildError::TooLarge {
                what: format!("the file would be {file_size} bytes, over {MAX_FILE_SIZE}"),
            });
        }
        Ok(FileLayout {
            header,
            sections,
            widths2,
            offsets,
            file_size,
        })
    }

    /// The header fields.
    pub fn header(&self) -> &FileHeader {
        &self.header
    }

    /// The sections, in table order.
    pub fn sections(&self) -> &[SectionInfo] {
        &self.sections
    }

    /// Byte offset of each section in the file.
    pub fn offsets(&self) -> &[u64] {
        &self.offsets
    }

    /// Length of the file in bytes.
    pub fn file_size(&self) -> u64 {
        self.file_size
    }

    /// The same layout with one more section after the others (such as a
    /// colour section whose bytes come from elsewhere).
    pub fn with_section(&self, section: SectionInfo) -> Result<Self, BuildError> {
        let mut sections = self.sections.clone();
        sections.push(section);
        FileLayout::place(self.header, sections, self.widths2.clone())
    }

    /// The header and the section table, as they start the file.
    fn header_and_table(&self) -> Vec<u8> {
        let mut table = Vec::with_capacity(self.sections.len() * SECTION_ENTRY_SIZE);
        for (i, (s, &offset)) in self.sections.iter().zip(&self.offsets).enumerate() {
            // 2.0 node levels: w_2 and w_3 in bytes 6 and 7 (§23.2).
            let upper = match &self.widths2 {
                Some(w) if s.kind == SectionKind::NodeLevel => {
                    u16::from_le_bytes([w[i][1], w[i][2]])
                }
                _ => 0,
            };
            let entry = RawSectionEntry {
                kind: s.kind.to_raw().to_le(),
                level: s.level,
                pointer_width: s.pointer_width,
                reserved0: upper.to_le(),
                offset: offset.to_le(),
                length: s.length.to_le(),
                item_count: s.item_count.to_le(),
                crc: s.crc.to_le(),
                reserved1: 0,
            };
            table.extend_from_slice(bytemuck::bytes_of(&entry));
        }
        let h = &self.header;
        let mut raw = RawHeader {
            magic: MAGIC,
            version_major: self.version_major().to_le(),
            // The lowest version that has everything the file uses (§22.1);
            // 2.0 has every 1.x section kind.
            version_minor: if self.widths2.is_none() {
                self.sections
                    .iter()
                    .map(|s| s.version_minor)
                    .fold(layout::VERSION_MINOR, u16::max)
            } else {
                layout::VERSION_MINOR
            }
            .to_le(),
            header_size: (HEADER_SIZE as u32).to_le(),
            required_features: 0,
            optional_features: 0,
            depth: h.depth,
            attribute_kind: h.attributes.to_raw(),
            section_count: (self.sections.len() as u16).to_le(),
            reserved0: 0,
            root_min: h.root_min.map(|v| v.to_bits().to_le()),
            root_size: h.root_size.to_bits().to_le(),
            file_size: self.file_size.to_le(),
            voxel_count: h.voxel_count.to_le(),
            reserved1: [0; 44],
            header_crc: 0,
        };
        let header_bytes: [u8; HEADER_SIZE] = bytemuck::cast(raw);
        raw.header_crc = layout::header_checksum(&header_bytes, &table).to_le();
        let mut bytes = bytemuck::bytes_of(&raw).to_vec();
        bytes.extend_from_slice(&table);
        bytes
    }

    /// Writes the file: the header and section table, then for each section
    /// (in table order) the zero padding before it and the bytes that
    /// `emit(index, sink)` hands to `sink`, in as many pieces as it likes.
    ///
    /// Fails with [`io::ErrorKind::InvalidData`] when the bytes emitted for a
    /// section differ in length or CRC-32C from its [`SectionInfo`]; the
    /// caller then discards what was written (the tools write to a temporary
    /// file that is only renamed into place on success).
    pub fn write_to<W: Write + ?Sized>(
        &self,
        w: &mut W,
        mut emit: impl FnMut(usize, &mut dyn FnMut(&[u8]) -> io::Result<()>) -> io::Result<()>,
    ) -> io::Result<()> {
        let head = self.header_and_table();
        w.write_all(&head)?;
        let mut position = head.len() as u64;
        for (index, (s, &offset)) in self.sections.iter().zip(&self.offsets).enumerate() {
            const ZEROS: [u8; 8] = [0; 8];
            w.write_all(&ZEROS[..(offset - position) as usize])?;
            let mut written = 0u64;
            let mut crc = 0u32;
            emit(index, &mut |chunk: &[u8]| {
                written += chunk.len() as u64;
                crc = crc32c::crc32c_append(crc, chunk);
                w.write_all(chunk)
            })?;
            if written != s.length || crc != s.crc {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    format!(
                        "section {index} ({:?}, level {}): {written} bytes with CRC-32C {crc:#010x} \
                         were written where the table declares {} bytes with {:#010x}",
                        s.kind, s.level, s.length, s.crc
                    ),
                ));
            }
            position = offset + s.length;
        }
        Ok(())
    }
}

/// The format's rules on the section table (spec §4.7, §5, §7, §9.3, §12.5,
/// §16.1), as far as they can be checked without the section bytes.
fn check(
    h: &FileHeader,
    sections: &[SectionInfo],
    widths2: Option<&[[u8; 3]]>,
) -> Result<(), BuildError> {
    if !(MIN_DEPTH..=MAX_DEPTH).contains(&h.depth) {
        return Err(BuildError::DepthOutOfRange { depth: h.depth });
    }
    if !(h.root_min.iter().all(|v| v.is_finite()) && h.root_size.is_finite() && h.root_size > 0.0) {
        return Err(BuildError::BadRootCube {
            min: h.root_min,
            size: h.root_size,
        });
    }
    let levels = usize::from(h.depth) - 1;
    if sections.len() < levels || sections.len() > usize::from(MAX_SECTIONS) {
        return Err(invalid(format!(
            "{} sections for depth {}: a file has {levels} ..= {MAX_SECTIONS}",
            sections.len(),
            h.depth
        )));
    }
    let leaf_level = levels - 1;
    for (l, s) in sections[..levels].iter().enumerate() {
        let expected = if l == leaf_level {
            SectionKind::LeafLevel
        } else {
            SectionKind::NodeLevel
        };
        if s.kind != expected || usize::from(s.level) != l {
            return Err(invalid(format!(
                "section {l} is {:?} of level {}, not {expected:?} of level {l}",
                s.kind, s.level
            )));
        }
        if l == leaf_level {
            if s.item_count > MAX_LEAF_COUNT {
                return Err(BuildError::TooLarge {
                    what: format!(
                        "{} leaves exceed the limit of {MAX_LEAF_COUNT}",
                        s.item_count
                    ),
                });
            }
            if s.pointer_width != 0 || s.length != s.item_count * 8 {
                return Err(invalid(format!(
                    "the leaf level has width {} and {} bytes for {} leaves",
                    s.pointer_width, s.length, s.item_count
                )));
            }
        } else {
            if s.length > MAX_NODE_LEVEL_BYTES {
                return Err(BuildError::TooLarge {
                    what: format!("level {l} exceeds {MAX_NODE_LEVEL_BYTES} bytes"),
                });
            }
            if let Some(widths2) = widths2 {
                let w = widths2.get(l).copied().unwrap_or([0; 3]);
                let ok = 1 <= w[0]
                    && w[0] <= w[1]
                    && w[1] <= w[2]
                    && u32::from(w[2]) <= crate::v2::MAX_WIDTH;
                if !ok || s.item_count > s.length / 5 {
                    return Err(invalid(format!(
                        "2.0 level {l} has widths {w:?} and {} records in {} bytes",
                        s.item_count, s.length
                    )));
                }
                continue;
            }
            if s.length % 4 != 0 || s.item_count > s.length / 8 {
                return Err(invalid(format!(
                    "level {l} has {} records in {} bytes",
                    s.item_count, s.length
                )));
            }
            let units = sections[l + 1].units();
            let minimal =
                layout::minimal_pointer_width(units).ok_or_else(|| BuildError::TooLarge {
                    what: format!(
                        "level {} has {units} units, more than 4-byte pointers address",
                        l + 1
                    ),
                })?;
            if s.pointer_width != minimal {
                return Err(invalid(format!(
                    "level {l} has pointer width {} where {units} units need exactly {minimal}",
                    s.pointer_width
                )));
            }
        }
    }
    let empty = sections[..levels]
        .iter()
        .all(|s| s.item_count == 0 && s.length == 0);
    if empty {
        if h.voxel_count != 0 {
            return Err(invalid(format!(
                "an empty volume with a voxel count of {}",
                h.voxel_count
            )));
        }
    } else if sections[0].item_count != 1 || h.voxel_count == 0 {
        return Err(invalid(format!(
            "the root level holds {} records and the volume {} voxels (a non-empty volume has one root)",
            sections[0].item_count, h.voxel_count
        )));
    }
    let mut colors = 0;
    for s in &sections[levels..] {
        match s.kind {
            SectionKind::NodeLevel | SectionKind::LeafLevel => {
                return Err(invalid(format!(
                    "a {:?} section after the level sections",
                    s.kind
                )));
            }
            SectionKind::VoxelColors | SectionKind::PackedColors => {
                colors += 1;
                if colors > 1 {
                    return Err(invalid("more than one colour section".into()));
                }
                if h.attributes != AttributeKind::VoxelCount {
                    return Err(BuildError::ColorsNeedVoxelCount);
                }
                if s.item_count != h.voxel_count {
                    return Err(BuildError::ColorCount {
                        expected: h.voxel_count,
                        got: s.item_count,
                    });
                }
                let length_ok = if s.kind == SectionKind::VoxelColors {
                    s.length == s.item_count * 4
                } else {
                    s.length >= crate::packed_colors::min_section_len(s.item_count)
                };
                if s.level != 0 || s.pointer_width != 0 || !length_ok {
                    return Err(invalid(format!(
                        "a colour section with level {}, width {} and {} bytes for {} colours",
                        s.level, s.pointer_width, s.length, s.item_count
                    )));
                }
            }
            SectionKind::UnknownOptional(raw) => {
                if raw & SECTION_KIND_OPTIONAL_BIT == 0 {
                    return Err(invalid(format!("section kind {raw:#x} is not optional")));
                }
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Dag;

    fn header(depth: u8, voxel_count: u64) -> FileHeader {
        FileHeader {
            depth,
            attributes: AttributeKind::VoxelCount,
            root_min: [0.0; 3],
            root_size: 1.0,
            voxel_count,
        }
    }

    #[test]
    fn writes_a_file_the_reader_opens_and_checks_what_is_emitted() {
        // Depth 3: a root node with one child, a leaf holding voxel 0.
        let mut root = Vec::new();
        layout::encode_node_record(1, 1, &[0], 1, &mut root);
        let leaf = 1u64.to_le_bytes();
        let sections = vec![
            SectionInfo::node_level(0, 1, 8, 1, crc32c::crc32c(&root)),
            SectionInfo::leaf_level(1, 1, crc32c::crc32c(&leaf)),
        ];
        let file = FileLayout::new(header(3, 1), sections).unwrap();
        let mut bytes = Vec::new();
        file.write_to(&mut bytes, |i, sink| {
            sink(if i == 0 { &root } else { &leaf })
        })
        .unwrap();
        assert_eq!(bytes.len() as u64, file.file_size());
        let dag = Dag::open(&bytes).unwrap();
        assert!(dag.is_set(0, 0, 0).unwrap());
        assert!(crate::validate::validate(&bytes).is_empty());
        // Bytes that do not match the table are refused.
        let err = file
            .write_to(&mut Vec::new(), |i, sink| {
                sink(if i == 0 {
                    &root
                } else {
                    &[2, 0, 0, 0, 0, 0, 0, 0]
                })
            })
            .unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::InvalidData);
        let err = file
            .write_to(&mut Vec::new(), |i, sink| {
                sink(if i == 0 { &root } else { &leaf[..4] })
            })
            .unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::InvalidData);
    }

    #[test]
    fn refuses_tables_that_break_the_rules() {
        let ok = || {
            vec![
                SectionInfo::node_level(0, 1, 8, 1, 0),
                SectionInfo::leaf_level(1, 1, 0),
            ]
        };
        assert!(FileLayout::new(header(3, 1), ok()).is_ok());
        let mut wide = ok();
        wide[0].pointer_width = 2;
        assert!(matches!(
            FileLayout::new(header(3, 1), wide),
            Err(BuildError::Invalid { .. })
        ));
        let mut swapped = ok();
        swapped.swap(0, 1);
        assert!(FileLayout::new(header(3, 1), swapped).is_err());
        assert!(FileLayout::new(header(3, 0), ok()).is_err(), "no voxels");
        assert!(
            FileLayout::new(header(4, 1), ok()).is_err(),
            "too few sections"
        );
        let colors = FileLayout::new(header(3, 1), ok()).unwrap();
        assert!(colors.with_section(SectionInfo::voxel_colors(1, 0)).is_ok());
        assert!(matches!(
            colors.with_section(SectionInfo::voxel_colors(2, 0)),
            Err(BuildError::ColorCount { .. })
        ));
        let mut kind0 = header(3, 1);
        kind0.attributes = AttributeKind::None;
        assert!(matches!(
            FileLayout::new(kind0, ok())
                .unwrap()
                .with_section(SectionInfo::voxel_colors(1, 0)),
            Err(BuildError::ColorsNeedVoxelCount)
        ));
        let empty = vec![
            SectionInfo::node_level(0, 1, 0, 0, 0),
            SectionInfo::leaf_level(1, 0, 0),
        ];
        assert!(FileLayout::new(header(3, 0), empty).is_ok());
    }
}
