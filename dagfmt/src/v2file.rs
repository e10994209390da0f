//! Format 2.0 files (spec §23): the zero-copy reader [`Dag2`], [`AnyDag`] —
//! the one entry point that opens files of both versions and says which —,
//! the writer [`write_v2`] and the conversions [`upgrade`] (1.0 → 2.0) and
//! [`downgrade`] (2.0 → 1.0).
//!
//! The level sections are encoded and decoded by [`crate::v2`]; headers and
//! section tables are written by [`crate::assemble::FileLayout`] as for 1.0,
//! and the open checks are the reader's (`reader::check_layout`) with the
//! 2.0 rules of §23.10 for the section entries. [`Dag::open`] stays a 1.0
//! reader: it rejects a 2.0 file with E003, so no 1.0-only consumer misreads
//! one; such a consumer can open any file with [`AnyDag::open`] and
//! [`downgrade`] a 2.0 one in memory.

use std::io::{self, Write};
use std::ops::ControlFlow;

use crate::assemble::{FileHeader, FileLayout, SectionInfo};
use crate::builder::{BuildError, DagBuilder};
use crate::error::{ErrorCode, FormatError};
use crate::layout::{AttributeKind, SectionKind, VERSION_MAJOR_2};
use crate::packed_colors::PackedColors;
use crate::reader::{ColorTable, Dag, Header, Layout, SectionEntry, parse_layout};
use crate::v2::{self, Encoded, LevelView};
use crate::v2enc::{EncodeOptions, LevelSummary, encode_levels};

/// A memory-safe, zero-copy view of a format 2.0 `.vdag` file.
///
/// [`Dag2::open`] checks the header and the section table (§17.2 with the
/// entry rules of §23.10: O(sections)); every later access decodes through
/// [`v2::decode_node`] and is bounds-checked, so the reader never panics on
/// any bytes. Proving a file correct is the validator's job.
#[derive(Clone, Debug)]
pub struct Dag2<'a> {
    bytes: &'a [u8],
    header: Header,
    sections: Vec<SectionEntry>,
    levels: Vec<LevelView<'a>>,
    colors: Option<&'a [u8]>,
    packed: Option<PackedColors<'a>>,
}

impl<'a> Dag2<'a> {
    /// Opens a 2.0 file held in `bytes`; a 1.0 file is refused with E003
    /// (use [`AnyDag::open`] for either).
    pub fn open(bytes: &'a [u8]) -> Result<Self, FormatError> {
        let layout = parse_layout(bytes, true)?;
        Self::from_layout(bytes, layout)
    }

    fn from_layout(bytes: &'a [u8], layout: Layout) -> Result<Self, FormatError> {
        let Layout {
            header, sections, ..
        } = layout;
        if header.version_major != VERSION_MAJOR_2 {
            return Err(FormatError::new(
                ErrorCode::UnsupportedVersion,
                8,
                format!(
                    "major version {} is not 2 (open it with AnyDag::open)",
                    header.version_major
                ),
            ));
        }
        let mut levels = Vec::with_capacity(usize::from(header.depth) - 1);
        let mut colors = None;
        let mut packed = None;
        for entry in &sections {
            // parse_layout checked that every section lies inside the file.
            let range = entry.offset as usize..(entry.offset + entry.length) as usize;
            match entry.kind {
                SectionKind::NodeLevel | SectionKind::LeafLevel => levels.push(LevelView {
                    bytes: &bytes[range],
                    widths: if entry.kind == SectionKind::NodeLevel {
                        entry.widths
                    } else {
                        [0; 3]
                    },
                    item_count: entry.item_count,
                    is_leaf: entry.kind == SectionKind::LeafLevel,
                }),
                SectionKind::VoxelColors => colors = Some(&bytes[range]),
                SectionKind::PackedColors => {
                    packed = Some(
                        PackedColors::new(&bytes[range], entry.item_count)
                            .expect("checked by parse_layout"),
                    )
                }
                SectionKind::UnknownOptional(_) => {}
            }
        }
        let root = &levels[0];
        let empty = root.item_count == 0;
        if root.item_count > 1
            || (empty
                && levels
                    .iter()
                    .any(|l| l.item_count != 0 || !l.bytes.is_empty()))
        {
            return Err(FormatError::new(
                ErrorCode::BadRootLevel,
                sections[0].entry_offset() + 24,
                format!(
                    "the root level holds {} records; it must hold 1, or 0 with every level empty",
                    root.item_count
                ),
            )
            .at_level(0));
        }
        if !empty && (root.bytes.is_empty() || levels[levels.len() - 1].item_count == 0) {
            return Err(FormatError::new(
                ErrorCode::TruncatedRecord2,
                sections[0].offset,
                "the root level declares a record but a level below it is empty",
            )
            .at_level(0));
        }
        Ok(Dag2 {
            bytes,
            header,
            sections,
            levels,
            colors,
            packed,
        })
    }

    /// The whole file.
    pub fn bytes(&self) -> &'a [u8] {
        self.bytes
    }

    /// The decoded header (`version_major` is 2).
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// The section table.
    pub fn sections(&self) -> &[SectionEntry] {
        &self.sections
    }

    /// Depth D.
    pub fn depth(&self) -> u32 {
        u32::from(self.header.depth)
    }

    /// Whether the volume holds no voxel.
    pub fn is_empty(&self) -> bool {
        self.levels[0].item_count == 0
    }

    /// The level sections, root first (D − 1 of them; the last is the leaf
    /// level): bytes, widths, item count and leaf flag, as a tracer decodes
    /// them with [`v2::decode_node`] and [`v2::child_address`].
    pub fn levels(&self) -> &[LevelView<'a>] {
        &self.levels
    }

    /// The raw voxel colour section (RGBA8 per voxel, dense index order), if present.
    pub fn colors(&self) -> Option<&'a [u8]> {
        self.colors
    }

    /// The packed colour section (kind 4), if present.
    pub fn packed_colors(&self) -> Option<PackedColors<'a>> {
        self.packed
    }

    /// The voxel colours, raw or packed, if the file has any.
    pub fn color_table(&self) -> Option<ColorTable<'a>> {
        ColorTable::from_sections(self.colors, self.packed)
    }

    /// Calls `leaf` with each non-empty 4³ brick (its Morton prefix: the
    /// Morton code of its voxels shifted right by 6) and its logical mask
    /// ([`crate::layout::leaf_bit`] order), in Morton order, until it answers
    /// [`ControlFlow::Break`].
    pub fn for_each_leaf(
        &self,
        leaf: impl FnMut(u64, u64) -> ControlFlow<()>,
    ) -> Result<(), FormatError> {
        v2::for_each_leaf(&self.levels, leaf)
    }

    /// The Morton codes of the set voxels, in order (memory: 8 bytes a voxel).
    pub fn voxel_codes(&self) -> Result<Vec<u64>, FormatError> {
        let mut out = Vec::new();
        self.for_each_leaf(|prefix, mut mask| {
            while mask != 0 {
                out.push(prefix << 6 | u64::from(mask.trailing_zeros()));
                mask &= mask - 1;
            }
            ControlFlow::Continue(())
        })?;
        Ok(out)
    }

    /// The dense voxel index (§12.3) of voxel `(x, y, z)` — its rank in
    /// Morton order, which indexes the colours —, or `None` when it is not
    /// set or outside the volume.
    pub fn voxel_index(&self, x: u32, y: u32, z: u32) -> Result<Option<u64>, FormatError> {
        if [x, y, z]
            .iter()
            .any(|&c| u64::from(c) >> self.header.depth != 0)
        {
            return Ok(None);
        }
        v2::voxel_index(
            &self.levels,
            crate::morton::encode(x, y, z),
            self.header.attribute_kind == AttributeKind::VoxelCount,
        )
    }

    /// Whether voxel `(x, y, z)` is set (`false` outside the volume).
    pub fn is_set(&self, x: u32, y: u32, z: u32) -> Result<bool, FormatError> {
        if [x, y, z]
            .iter()
            .any(|&c| u64::from(c) >> self.header.depth != 0)
        {
            return Ok(false);
        }
        v2::is_set(&self.levels, crate::morton::encode(x, y, z))
    }

    /// The sections after the level sections (colours, optional sections)
    /// with their bytes, in table order.
    fn extra_sections(&self) -> Vec<(SectionInfo, &'a [u8])> {
        extra_sections(self.bytes, &self.sections, self.header.depth)
    }
}

/// The sections after the level sections, as [`SectionInfo`]s with their bytes.
fn extra_sections<'a>(
    bytes: &'a [u8],
    sections: &[SectionEntry],
    depth: u8,
) -> Vec<(SectionInfo, &'a [u8])> {
    sections[usize::from(depth) - 1..]
        .iter()
        .map(|e| {
            let data = &bytes[e.offset as usize..(e.offset + e.length) as usize];
            // A packed colour section needs the minor version of its layout.
            let version_minor = match e.kind {
                SectionKind::PackedColors => {
                    match crate::packed_colors::open_trailer(data, e.item_count) {
                        Ok(t) if !t.layout.is_v1_1() => crate::layout::VERSION_MINOR_SPLIT_COLORS,
                        _ => crate::layout::VERSION_MINOR_PACKED_COLORS,
                    }
                }
                _ => 0,
            };
            let info = SectionInfo {
                kind: e.kind,
                level: e.level,
                pointer_width: e.pointer_width,
                length: e.length,
                item_count: e.item_count,
                crc: e.crc,
                version_minor,
            };
            (info, data)
        })
        .collect()
}

/// A `.vdag` file of either version, as opened by [`AnyDag::open`].
#[derive(Clone, Debug)]
pub enum AnyDag<'a> {
    /// A 1.x file.
    V1(Dag<'a>),
    /// A 2.x file.
    V2(Dag2<'a>),
}

impl<'a> AnyDag<'a> {
    /// Opens a file of either version (the open checks of §17.2, and of
    /// §23.10 for the entries of a 2.0 file). Never panics on any bytes.
    pub fn open(bytes: &'a [u8]) -> Result<Self, FormatError> {
        let layout = parse_layout(bytes, true)?;
        if layout.header.version_major == VERSION_MAJOR_2 {
            Dag2::from_layout(bytes, layout).map(AnyDag::V2)
        } else {
            Dag::open(bytes).map(AnyDag::V1)
        }
    }

    /// The major version: 1 or 2.
    pub fn version_major(&self) -> u16 {
        self.header().version_major
    }

    /// The decoded header.
    pub fn header(&self) -> &Header {
        match self {
            AnyDag::V1(d) => d.header(),
            AnyDag::V2(d) => d.header(),
        }
    }

    /// The section table.
    pub fn sections(&self) -> &[SectionEntry] {
        match self {
            AnyDag::V1(d) => d.sections(),
            AnyDag::V2(d) => d.sections(),
        }
    }

    /// The voxel colours, raw or packed, if the file has any.
    pub fn color_table(&self) -> Option<ColorTable<'a>> {
        match self {
            AnyDag::V1(d) => d.color_table(),
            AnyDag::V2(d) => d.color_table(),
        }
    }

    /// The dense voxel index of voxel `(x, y, z)`, or `None` when it is not set.
    pub fn voxel_index(&self, x: u32, y: u32, z: u32) -> Result<Option<u64>, FormatError> {
        match self {
            AnyDag::V1(d) => d.voxel_index(x, y, z),
            AnyDag::V2(d) => d.voxel_index(x, y, z),
        }
    }

    /// Whether voxel `(x, y, z)` is set (`false` outside the volume).
    pub fn is_set(&self, x: u32, y: u32, z: u32) -> Result<bool, FormatError> {
        match self {
            AnyDag::V1(d) => d.is_set(x, y, z),
            AnyDag::V2(d) => d.is_set(x, y, z),
        }
    }

    /// The Morton codes of the set voxels, in order.
    pub fn voxel_codes(&self) -> Result<Vec<u64>, FormatError> {
        match self {
            AnyDag::V1(d) => d
                .voxels()
                .map(|v| v.map(|[x, y, z]| crate::morton::encode(x, y, z)))
                .collect(),
            AnyDag::V2(d) => d.voxel_codes(),
        }
    }
}

/// Why a conversion between the versions failed.
#[derive(Debug)]
pub enum ConvertError {
    /// The source file is malformed where the conversion had to read it.
    Format(FormatError),
    /// The result cannot be built (limits of §16).
    Build(BuildError),
    /// Writing the result failed.
    Io(io::Error),
    /// The memory budget is below the least the encoder holds (with
    /// [`crate::v2enc::EncodeOptions::refuse_below_least`]).
    Budget {
        /// The least the encoder holds, in bytes.
        least: u64,
        /// The budget it was given, in bytes.
        budget: u64,
    },
}

impl std::fmt::Display for ConvertError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ConvertError::Format(e) => write!(f, "{e}"),
            ConvertError::Build(e) => write!(f, "{e}"),
            ConvertError::Io(e) => write!(f, "{e}"),
            ConvertError::Budget { least, budget } => write!(
                f,
                "the 2.0 encoder needs at least {least} bytes of memory for this file, more than its budget of {budget}"
            ),
        }
    }
}

impl std::error::Error for ConvertError {}

impl From<FormatError> for ConvertError {
    fn from(e: FormatError) -> Self {
        ConvertError::Format(e)
    }
}

impl From<io::Error> for ConvertError {
    fn from(e: io::Error) -> Self {
        ConvertError::Io(e)
    }
}

impl From<BuildError> for ConvertError {
    fn from(e: BuildError) -> Self {
        ConvertError::Build(e)
    }
}

/// The layout of the 2.0 file holding `encoded`'s levels, the header fields
/// `header` and, after the levels, `extra` (colour and optional sections, as
/// they are in the source file).
pub fn layout_v2(
    encoded: &Encoded,
    header: FileHeader,
    extra: &[(SectionInfo, &[u8])],
) -> Result<FileLayout, BuildError> {
    let levels: Vec<LevelSummary> = encoded
        .levels
        .iter()
        .map(|l| LevelSummary {
            widths: l.widths,
            item_count: l.item_count,
            is_leaf: l.is_leaf,
            length: l.bytes.len() as u64,
            crc: crc32c::crc32c(&l.bytes),
        })
        .collect();
    layout_levels(&levels, header, extra)
}

/// The layout of a 2.0 file of levels `levels` (root first, the leaf level
/// last), the header fields `header` and the sections `extra`.
fn layout_levels(
    levels: &[LevelSummary],
    header: FileHeader,
    extra: &[(SectionInfo, &[u8])],
) -> Result<FileLayout, BuildError> {
    let last = levels.len() - 1;
    let mut sections = Vec::with_capacity(levels.len() + extra.len());
    let mut widths = Vec::with_capacity(last);
    for (l, level) in levels.iter().enumerate() {
        if l == last {
            sections.push(SectionInfo::leaf_level(
                l as u8,
                level.item_count,
                level.crc,
            ));
        } else {
            sections.push(SectionInfo::node_level(
                l as u8,
                level.widths[0],
                level.length,
                level.item_count,
                level.crc,
            ));
            widths.push(level.widths);
        }
    }
    sections.extend(extra.iter().map(|(info, _)| *info));
    FileLayout::new_v2(header, sections, widths)
}

/// Writes the 2.0 file of `encoded` (see [`layout_v2`]) to `w`.
pub fn write_v2<W: Write + ?Sized>(
    encoded: &Encoded,
    header: FileHeader,
    extra: &[(SectionInfo, &[u8])],
    w: &mut W,
) -> Result<(), ConvertError> {
    let layout = layout_v2(encoded, header, extra)?;
    let levels = encoded.levels.len();
    layout
        .write_to(w, |index, sink| {
            if index < levels {
                sink(&encoded.levels[index].bytes)
            } else {
                sink(extra[index - levels].1)
            }
        })
        .map_err(ConvertError::Io)
}

/// The header fields of `header` that a converted file keeps.
fn file_header(header: &Header) -> FileHeader {
    FileHeader {
        depth: header.depth,
        attributes: header.attribute_kind,
        root_min: header.root_min,
        root_size: header.root_size,
        voxel_count: header.voxel_count,
    }
}

/// The 2.0 file of the voxels, attributes, colours and root cube of the 1.0
/// file `dag` (`dagtool upgrade`): its levels encoded by [`v2::encode`], its
/// colour and optional sections copied byte for byte.
pub fn upgrade(dag: &Dag<'_>) -> Result<Vec<u8>, ConvertError> {
    let mut out = Vec::new();
    upgrade_to(dag, &EncodeOptions::default(), &mut out)?;
    Ok(out)
}

/// Writes the 2.0 file of [`upgrade`] to `w`, its levels encoded by
/// [`encode_levels`] within `options`' memory budget and streamed to `w`
/// (from the scratch file, where they went there). The bytes are those of
/// [`upgrade`] whatever the budget. Returns what went through the
/// encoder's scratch file.
pub fn upgrade_to<W: Write + ?Sized>(
    dag: &Dag<'_>,
    options: &EncodeOptions,
    w: &mut W,
) -> Result<Spill, ConvertError> {
    let mut encoded = encode_levels(dag, options)?;
    let extra = extra_sections(dag.bytes(), dag.sections(), dag.header().depth);
    let layout = layout_levels(&encoded.levels, file_header(dag.header()), &extra)?;
    let levels = encoded.levels.len();
    layout
        .write_to(w, |index, sink| {
            if index < levels {
                encoded.write_level(index, sink)
            } else {
                sink(extra[index - levels].1)
            }
        })
        .map_err(ConvertError::Io)?;
    Ok(Spill {
        scratch_bytes: encoded.spilled_bytes(),
        external_passes: encoded.external_passes(),
    })
}

/// What went through the 2.0 encoder's scratch file ([`upgrade_to`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Spill {
    /// Bytes written to the scratch file (0: none).
    pub scratch_bytes: u64,
    /// Passes over a level (merge, order, layout) that went out of core
    /// because their working set was over the budget.
    pub external_passes: usize,
}

/// The 1.0 file of the voxels, attributes, colours and root cube of the 2.0
/// file `dag`: the reflections applied and the DAG rebuilt by
/// [`DagBuilder`], the colour and optional sections copied byte for byte.
/// A 1.0 file that [`DagBuilder`] wrote comes back byte for byte from
/// `downgrade(upgrade(file))`.
pub fn downgrade(dag: &Dag2<'_>) -> Result<Vec<u8>, ConvertError> {
    let header = dag.header();
    let mut builder = DagBuilder::new(header.depth, header.attribute_kind)?;
    builder.set_root_cube(header.root_min, header.root_size);
    let mut failed = None;
    dag.for_each_leaf(|brick, mask| match builder.push_brick(brick, mask) {
        Ok(()) => ControlFlow::Continue(()),
        Err(e) => {
            failed = Some(e);
            ControlFlow::Break(())
        }
    })?;
    if let Some(e) = failed {
        return Err(e.into());
    }
    let built = builder.finish()?;
    if built.voxel_count() != header.voxel_count {
        return Err(FormatError::new(
            ErrorCode::HeaderVoxelCount,
            72,
            format!(
                "the header counts {} voxels, the DAG holds {}",
                header.voxel_count,
                built.voxel_count()
            ),
        )
        .into());
    }
    let extra = dag.extra_sections();
    let mut layout = built.layout().clone();
    for (info, _) in &extra {
        layout = layout.with_section(*info)?;
    }
    let levels = usize::from(header.depth) - 1;
    let mut out = Vec::with_capacity(layout.file_size() as usize);
    layout
        .write_to(&mut out, |index, sink| {
            if index < levels {
                built.emit_section(index, sink)
            } else {
                sink(extra[index - levels].1)
            }
        })
        .map_err(|e| -> ConvertError {
            if e.kind() == io::ErrorKind::InvalidData {
                // A copied section whose bytes disagree with its entry's CRC.
                FormatError::new(ErrorCode::SectionChecksum, 0, e.to_string()).into()
            } else {
                ConvertError::Io(e)
            }
        })?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::validate::validate;
    use proptest::prelude::*;

    fn build(depth: u8, kind: AttributeKind, voxels: &[[u32; 3]], colors: u8) -> Vec<u8> {
        let mut built = DagBuilder::from_voxels(depth, kind, voxels.iter().copied()).unwrap();
        built.set_root_cube([-1.5, 2.0, 0.25], 3.0).unwrap();
        let n = built.voxel_count() as usize;
        let rgba: Vec<[u8; 4]> = (0..n).map(|i| [i as u8, (i * 7) as u8, 3, 255]).collect();
        match colors {
            1 => built.set_colors(rgba).unwrap(),
            2 => {
                built.set_packed_colors(&rgba, 0).unwrap();
            }
            _ => {}
        }
        built.to_bytes()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        // 1.0 → 2.0 → 1.0 gives the builder's bytes back; the 2.0 file is
        // valid, opens as version 2 and holds the same voxels, dense indices
        // and colour bytes.
        #[test]
        fn upgrade_then_downgrade_gives_the_original_bytes(
            depth in 2u8..=6,
            voxels in proptest::collection::vec((0u32..64, 0u32..64, 0u32..64), 0..300),
            kind in 0u8..2,
            colors in 0u8..3,
        ) {
            let res = 1u32 << depth;
            let vs: Vec<[u32; 3]> = voxels.iter().map(|&(x, y, z)| [x % res, y % res, z % res]).collect();
            let kind = if kind == 0 { AttributeKind::None } else { AttributeKind::VoxelCount };
            let colors = if kind == AttributeKind::None { 0 } else { colors };
            let v1 = build(depth, kind, &vs, colors);
            let dag = Dag::open(&v1).unwrap();
            let v2 = upgrade(&dag).unwrap();
            prop_assert_eq!(validate(&v2), vec![]);
            let AnyDag::V2(dag2) = AnyDag::open(&v2).unwrap() else {
                panic!("a 2.0 file opens as 2.0");
            };
            prop_assert!(matches!(AnyDag::open(&v1).unwrap(), AnyDag::V1(_)));
            prop_assert_eq!(Dag::open(&v2).unwrap_err().code, ErrorCode::UnsupportedVersion);
            prop_assert_eq!(dag2.header().voxel_count, dag.header().voxel_count);
            prop_assert_eq!(dag2.header().root_min, dag.header().root_min);
            let codes = dag2.voxel_codes().unwrap();
            let expected: Vec<u64> = dag.voxels().map(|v| {
                let [x, y, z] = v.unwrap();
                crate::morton::encode(x, y, z)
            }).collect();
            prop_assert_eq!(&codes, &expected);
            for &code in codes.iter().step_by(5) {
                let [x, y, z] = crate::morton::decode(code);
                prop_assert_eq!(dag2.voxel_index(x, y, z).unwrap(), dag.voxel_index(x, y, z).unwrap());
            }
            prop_assert_eq!(dag2.colors(), dag.colors());
            prop_assert_eq!(dag2.packed_colors().map(|p| p.len()), dag.packed_colors().map(|p| p.len()));
            prop_assert_eq!(downgrade(&dag2).unwrap(), v1);
        }
    }
}
