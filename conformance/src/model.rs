//! A decoded, editable model of a `.vdag` file and byte-level helpers, used to
//! make the malformed files (and a few unusual valid ones) from valid files.
//!
//! [`DagModel::decode`] turns a file into node lists with child *indices*;
//! [`DagModel::encode`] lays it out again (minimal pointer widths unless told
//! otherwise, sections packed as the spec requires, every checksum computed).
//! Encoding an unedited model reproduces the builder's bytes exactly, which the
//! tests check. The byte helpers edit single fields and then recompute the
//! checksums so that an edit breaks exactly the rule it is meant to break.

use dagfmt::layout::{
    self, HEADER_CRC_OFFSET, HEADER_SIZE, RawSectionEntry, SECTION_ENTRY_SIZE, SectionKind,
};
use dagfmt::{Dag, FormatError};

/// One interior node.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ModelNode {
    /// Child mask.
    pub mask: u8,
    /// 24-bit attribute field.
    pub attribute: u32,
    /// Index of each child (in mask order) in the next level's node list (or
    /// the leaf list).
    pub children: Vec<u32>,
}

/// A section other than a level section (colours, optional sections).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ExtraSection {
    /// Raw kind.
    pub kind: u32,
    /// Item count to declare.
    pub item_count: u64,
    /// Contents.
    pub bytes: Vec<u8>,
}

/// An editable `.vdag` file.
#[derive(Clone, Debug, PartialEq)]
pub struct DagModel {
    /// Depth D.
    pub depth: u8,
    /// Raw attribute kind.
    pub attribute_kind: u8,
    /// Minor version to write.
    pub version_minor: u16,
    /// Optional feature bits to write.
    pub optional_features: u32,
    /// Root cube corner.
    pub root_min: [f64; 3],
    /// Root cube size.
    pub root_size: f64,
    /// Header voxel count.
    pub voxel_count: u64,
    /// Interior levels `0 ..= D - 3`, nodes in storage order.
    pub levels: Vec<Vec<ModelNode>>,
    /// Leaf masks in storage order.
    pub leaves: Vec<u64>,
    /// Sections after the level sections.
    pub extra: Vec<ExtraSection>,
}

/// How to lay out a model.
#[derive(Clone, Debug, Default)]
pub struct EncodeOptions {
    /// Pointer width per interior level (`None`: the minimal one).
    pub widths: Vec<Option<u8>>,
}

fn err(message: impl Into<String>) -> FormatError {
    FormatError::new(dagfmt::ErrorCode::TruncatedNode, 0, message)
}

impl DagModel {
    /// Decodes a file the reader accepts into a model.
    pub fn decode(bytes: &[u8]) -> Result<DagModel, FormatError> {
        let dag = Dag::open(bytes)?;
        let header = dag.header();
        let leaf_level = usize::from(dag.leaf_level());
        // Records of each interior level: (word offset, node).
        let mut raw_levels: Vec<Vec<(u32, ModelNode)>> = Vec::new();
        for section in &dag.levels()[..leaf_level] {
            let mut records = Vec::new();
            let mut word = 0u32;
            while (word as usize) * 4 < section.bytes.len() {
                let node = dag.node(section.level, word)?;
                let children = (0..node.child_count())
                    .map(|r| node.pointer_at(r))
                    .collect();
                records.push((
                    word,
                    ModelNode {
                        mask: node.child_mask(),
                        attribute: node.attribute(),
                        children,
                    },
                ));
                word += (node.record_size() / 4) as u32;
            }
            raw_levels.push(records);
        }
        let leaf_section = &dag.levels()[leaf_level];
        let leaves: Vec<u64> = leaf_section
            .bytes
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect();
        // Pointers (word offsets / leaf indices) to indices.
        let mut levels = Vec::with_capacity(leaf_level);
        for l in 0..leaf_level {
            let next_words: Option<Vec<u32>> = raw_levels
                .get(l + 1)
                .map(|r| r.iter().map(|(w, _)| *w).collect());
            let mut nodes = Vec::new();
            for (_, node) in &raw_levels[l] {
                let mut node = node.clone();
                if let Some(words) = &next_words {
                    for c in &mut node.children {
                        *c = words
                            .binary_search(c)
                            .map_err(|_| err(format!("level {l}: pointer {c} is not a record")))?
                            as u32;
                    }
                }
                nodes.push(node);
            }
            levels.push(nodes);
        }
        let mut extra = Vec::new();
        for entry in &dag.sections()[leaf_level + 1..] {
            extra.push(ExtraSection {
                kind: entry.kind.to_raw(),
                item_count: entry.item_count,
                bytes: bytes[entry.offset as usize..(entry.offset + entry.length) as usize]
                    .to_vec(),
            });
        }
        Ok(DagModel {
            depth: header.depth,
            attribute_kind: header.attribute_kind.to_raw(),
            version_minor: header.version_minor,
            optional_features: header.optional_features,
            root_min: header.root_min,
            root_size: header.root_size,
            voxel_count: header.voxel_count,
            levels,
            leaves,
            extra,
        })
    }

    /// Voxel count of every node of every level (interior levels then the
    /// leaves), from the leaf masks.
    pub fn subtree_counts(&self) -> Vec<Vec<u64>> {
        let mut counts = vec![Vec::new(); self.levels.len() + 1];
        counts[self.levels.len()] = self
            .leaves
            .iter()
            .map(|m| u64::from(m.count_ones()))
            .collect();
        for l in (0..self.levels.len()).rev() {
            counts[l] = self.levels[l]
                .iter()
                .map(|n| n.children.iter().map(|&c| counts[l + 1][c as usize]).sum())
                .collect();
        }
        counts
    }

    /// Sets every attribute to what the structure implies (voxel counts,
    /// saturated, for kind 1; zero otherwise) and the header voxel count.
    pub fn recompute_counts(&mut self) {
        let counts = self.subtree_counts();
        for (l, nodes) in self.levels.iter_mut().enumerate() {
            for (node, &count) in nodes.iter_mut().zip(&counts[l]) {
                node.attribute = if self.attribute_kind == 1 {
                    count.min(u64::from(layout::COUNT_SATURATED)) as u32
                } else {
                    0
                };
            }
        }
        self.voxel_count = counts[0].first().copied().unwrap_or(0);
    }

    /// Lays the model out with minimal pointer widths and no extra padding.
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(&EncodeOptions::default())
    }

    /// Lays the model out as `options` say; every checksum is correct.
    pub fn encode_with(&self, options: &EncodeOptions) -> Vec<u8> {
        let leaf_level = self.levels.len();
        // Sections of the levels, bottom-up: (bytes, item count, width, word offsets).
        let mut level_bytes = vec![Vec::new(); leaf_level + 1];
        let mut widths = vec![0u8; leaf_level + 1];
        level_bytes[leaf_level] = self.leaves.iter().flat_map(|m| m.to_le_bytes()).collect();
        let mut child_offsets: Vec<u32> = (0..self.leaves.len() as u32).collect();
        let mut child_units = self.leaves.len() as u64;
        for l in (0..leaf_level).rev() {
            let width = options.widths.get(l).copied().flatten().unwrap_or_else(|| {
                layout::minimal_pointer_width(child_units).expect("small test files")
            });
            widths[l] = width;
            let mut bytes = Vec::new();
            let mut offsets = Vec::with_capacity(self.levels[l].len());
            for node in &self.levels[l] {
                offsets.push((bytes.len() / 4) as u32);
                let header = u32::from(node.mask) | node.attribute << 8;
                bytes.extend_from_slice(&header.to_le_bytes());
                for &c in &node.children {
                    let pointer = child_offsets.get(c as usize).copied().unwrap_or(c);
                    bytes.extend_from_slice(&pointer.to_le_bytes()[..usize::from(width)]);
                }
                while bytes.len() % 4 != 0 {
                    bytes.push(0);
                }
            }
            child_units = bytes.len() as u64 / 4;
            child_offsets = offsets;
            level_bytes[l] = bytes;
        }
        let mut sections = Vec::new();
        for (l, bytes) in level_bytes.into_iter().enumerate() {
            let (kind, count) = if l == leaf_level {
                (SectionKind::LEAF_LEVEL, self.leaves.len() as u64)
            } else {
                (SectionKind::NODE_LEVEL, self.levels[l].len() as u64)
            };
            sections.push(RawSection::new(kind, l as u8, widths[l], count, bytes));
        }
        for e in &self.extra {
            sections.push(RawSection::new(e.kind, 0, 0, e.item_count, e.bytes.clone()));
        }
        let mut header = [0u8; HEADER_SIZE];
        header[..8].copy_from_slice(&layout::MAGIC);
        put_u16(&mut header, 8, layout::VERSION_MAJOR);
        put_u16(&mut header, 10, self.version_minor);
        put_u32(&mut header, 12, HEADER_SIZE as u32);
        put_u32(&mut header, 20, self.optional_features);
        header[24] = self.depth;
        header[25] = self.attribute_kind;
        for i in 0..3 {
            put_u64(&mut header, 32 + 8 * i, self.root_min[i].to_bits());
        }
        put_u64(&mut header, 56, self.root_size.to_bits());
        put_u64(&mut header, 72, self.voxel_count);
        RawFile { header, sections }.join(&JoinOptions::default())
    }
}

/// One section of a [`RawFile`]: its table entry (native values) and bytes.
#[derive(Clone, Debug)]
pub struct RawSection {
    /// The table entry; `offset`, `length` and `crc` are set by [`RawFile::join`].
    pub entry: RawSectionEntry,
    /// The section's bytes.
    pub bytes: Vec<u8>,
}

impl RawSection {
    /// A section of `kind` with its bytes.
    pub fn new(kind: u32, level: u8, pointer_width: u8, item_count: u64, bytes: Vec<u8>) -> Self {
        RawSection {
            entry: RawSectionEntry {
                kind,
                level,
                pointer_width,
                reserved0: 0,
                offset: 0,
                length: bytes.len() as u64,
                item_count,
                crc: 0,
                reserved1: 0,
            },
            bytes,
        }
    }
}

/// Where [`RawFile::join`] puts a section.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Placement {
    /// At the next multiple of 8 (what the spec requires).
    Aligned,
    /// Right after the previous section, aligned or not.
    Packed,
    /// At the next multiple of 8 plus this many bytes.
    Gap(u64),
}

/// How [`RawFile::join`] lays the sections out.
#[derive(Clone, Debug, Default)]
pub struct JoinOptions {
    /// Placement of each section (by table index); missing: aligned.
    pub placement: Vec<(usize, Placement)>,
    /// Storage order of the sections (table indices); empty: table order.
    pub order: Vec<usize>,
    /// Keep the table's `length` of these sections instead of their byte count.
    pub keep_length: Vec<usize>,
}

/// A file as its header and sections, to be laid out again.
#[derive(Clone, Debug)]
pub struct RawFile {
    /// The 128 header bytes (file size, section count and checksum are set by `join`).
    pub header: [u8; HEADER_SIZE],
    /// The sections, in table order.
    pub sections: Vec<RawSection>,
}

impl RawFile {
    /// Splits a file the reader accepts.
    pub fn split(bytes: &[u8]) -> Result<RawFile, FormatError> {
        let dag = dagfmt::AnyDag::open(bytes)?;
        let header: [u8; HEADER_SIZE] = bytes[..HEADER_SIZE].try_into().expect("header");
        let sections = dag
            .sections()
            .iter()
            .map(|e| {
                let at = HEADER_SIZE + usize::from(e.index) * SECTION_ENTRY_SIZE;
                let raw: RawSectionEntry =
                    bytemuck::pod_read_unaligned(&bytes[at..at + SECTION_ENTRY_SIZE]);
                RawSection {
                    entry: entry_from_le(&raw),
                    bytes: bytes[e.offset as usize..(e.offset + e.length) as usize].to_vec(),
                }
            })
            .collect();
        Ok(RawFile { header, sections })
    }

    /// Lays the file out: sections packed as `options` say (by default as the
    /// spec requires), lengths, checksums, file size, section count and the
    /// header checksum computed.
    pub fn join(&self, options: &JoinOptions) -> Vec<u8> {
        let table_end = (HEADER_SIZE + self.sections.len() * SECTION_ENTRY_SIZE) as u64;
        let order: Vec<usize> = if options.order.is_empty() {
            (0..self.sections.len()).collect()
        } else {
            options.order.clone()
        };
        let mut entries: Vec<RawSectionEntry> = self.sections.iter().map(|s| s.entry).collect();
        let mut position = table_end;
        for &i in &order {
            let placement = options
                .placement
                .iter()
                .find(|(k, _)| *k == i)
                .map_or(Placement::Aligned, |(_, p)| *p);
            let offset = match placement {
                Placement::Aligned => layout::align_section(position),
                Placement::Packed => position,
                Placement::Gap(g) => layout::align_section(position) + g,
            };
            let bytes = &self.sections[i].bytes;
            entries[i].offset = offset;
            if !options.keep_length.contains(&i) {
                entries[i].length = bytes.len() as u64;
            }
            entries[i].crc = crc32c::crc32c(bytes);
            position = offset + bytes.len() as u64;
        }
        let mut out = vec![0u8; position.max(table_end) as usize];
        out[..HEADER_SIZE].copy_from_slice(&self.header);
        put_u16(&mut out, 26, self.sections.len() as u16);
        let file_size = out.len() as u64;
        put_u64(&mut out, 64, file_size);
        for (i, entry) in entries.iter().enumerate() {
            let at = HEADER_SIZE + i * SECTION_ENTRY_SIZE;
            out[at..at + SECTION_ENTRY_SIZE]
                .copy_from_slice(bytemuck::bytes_of(&entry_to_le(entry)));
            let bytes = &self.sections[i].bytes;
            out[entry.offset as usize..entry.offset as usize + bytes.len()].copy_from_slice(bytes);
        }
        fix_header_checksum(&mut out);
        out
    }
}

fn entry_from_le(e: &RawSectionEntry) -> RawSectionEntry {
    entry_to_le(e)
}

fn entry_to_le(e: &RawSectionEntry) -> RawSectionEntry {
    RawSectionEntry {
        kind: e.kind.to_le(),
        level: e.level,
        pointer_width: e.pointer_width,
        reserved0: e.reserved0.to_le(),
        offset: e.offset.to_le(),
        length: e.length.to_le(),
        item_count: e.item_count.to_le(),
        crc: e.crc.to_le(),
        reserved1: e.reserved1.to_le(),
    }
}

/// Writes a little-endian u16 at `at`.
pub fn put_u16(bytes: &mut [u8], at: usize, v: u16) {
    bytes[at..at + 2].copy_from_slice(&v.to_le_bytes());
}

/// Writes a little-endian u32 at `at`.
pub fn put_u32(bytes: &mut [u8], at: usize, v: u32) {
    bytes[at..at + 4].copy_from_slice(&v.to_le_bytes());
}

/// Writes a little-endian u64 at `at`.
pub fn put_u64(bytes: &mut [u8], at: usize, v: u64) {
    bytes[at..at + 8].copy_from_slice(&v.to_le_bytes());
}

/// Reads a little-endian u16 at `at`.
pub fn get_u16(bytes: &[u8], at: usize) -> u16 {
    u16::from_le_bytes(bytes[at..at + 2].try_into().expect("2 bytes"))
}

/// Reads a little-endian u32 at `at`.
pub fn get_u32(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes"))
}

/// Reads a little-endian u64 at `at`.
pub fn get_u64(bytes: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(bytes[at..at + 8].try_into().expect("8 bytes"))
}

/// Byte offset of field `field_offset` of section table entry `index`.
pub fn entry_field(index: usize, field_offset: usize) -> usize {
    HEADER_SIZE + index * SECTION_ENTRY_SIZE + field_offset
}

/// Offsets of the fields of a section table entry.
pub mod entry {
    /// `kind` (u32).
    pub const KIND: usize = 0;
    /// `level` (u8).
    pub const LEVEL: usize = 4;
    /// `pointer_width` (u8).
    pub const WIDTH: usize = 5;
    /// `reserved0` (u16).
    pub const RESERVED0: usize = 6;
    /// `offset` (u64).
    pub const OFFSET: usize = 8;
    /// `length` (u64).
    pub const LENGTH: usize = 16;
    /// `item_count` (u64).
    pub const ITEM_COUNT: usize = 24;
    /// `crc` (u32).
    pub const CRC: usize = 32;
    /// `reserved1` (u32).
    pub const RESERVED1: usize = 36;
}

/// The number of section table entries the header declares.
pub fn section_count(bytes: &[u8]) -> usize {
    usize::from(get_u16(bytes, 26))
}

/// Recomputes the header checksum (over bytes `0..124` and the declared
/// section table, as far as the file holds it).
pub fn fix_header_checksum(bytes: &mut [u8]) {
    if bytes.len() < HEADER_SIZE {
        return;
    }
    let table_end = (HEADER_SIZE + section_count(bytes) * SECTION_ENTRY_SIZE).min(bytes.len());
    let header: [u8; HEADER_SIZE] = bytes[..HEADER_SIZE].try_into().expect("header");
    let crc = layout::header_checksum(&header, &bytes[HEADER_SIZE..table_end]);
    put_u32(bytes, HEADER_CRC_OFFSET, crc);
}

/// Recomputes every section checksum whose section lies in the file, then
/// the header checksum.
pub fn fix_checksums(bytes: &mut [u8]) {
    let count = section_count(bytes);
    for i in 0..count {
        if entry_field(i, SECTION_ENTRY_SIZE) > bytes.len() {
            break;
        }
        let offset = get_u64(bytes, entry_field(i, entry::OFFSET));
        let length = get_u64(bytes, entry_field(i, entry::LENGTH));
        if let Some(end) = offset
            .checked_add(length)
            .filter(|&e| e <= bytes.len() as u64)
        {
            let crc = crc32c::crc32c(&bytes[offset as usize..end as usize]);
            put_u32(bytes, entry_field(i, entry::CRC), crc);
        }
    }
    fix_header_checksum(bytes);
}
