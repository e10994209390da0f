//! Region builds: a cell of the root cube, and the *part* file that holds
//! one (spec/VDAG.md § 24).
//!
//! A part is an ordinary `.vdag` of the full depth and root cube whose
//! voxels all lie in a contiguous Morton range of level-K cells, with one
//! optional PART_PLACEMENT section that says which: every 1.x reader opens
//! it as the partial volume it is, and [`crate::merge`] joins parts into the
//! file one conversion of the whole input would have written.

use std::fmt;
use std::ops::Range;

use dagfmt::Dag;
use dagfmt::assemble::SectionInfo;
use dagfmt::layout::{AttributeKind, SectionKind};

use crate::error::ConvertError;

/// The raw kind of the PART_PLACEMENT section (optional: bit 31 set).
pub const PART_PLACEMENT_KIND: u32 = 0x8000_0001;

/// Bytes of the PART_PLACEMENT section.
pub const PLACEMENT_LEN: usize = 48;

/// The magic at the start of the PART_PLACEMENT section.
pub const PLACEMENT_MAGIC: [u8; 8] = *b"VDAGPART";

/// The version of the placement this code writes and reads.
pub const PART_VERSION: u16 = 1;

/// One cell of level K of the root cube: `2^(D-K)` voxels per edge.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Region {
    /// The level K (0: the whole cube).
    pub level: u8,
    /// The cell's coordinates, each in `0 .. 2^K`.
    pub cell: [u32; 3],
}

impl fmt::Display for Region {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [x, y, z] = self.cell;
        write!(f, "{}:{x},{y},{z}", self.level)
    }
}

impl Region {
    /// Parses `K:X,Y,Z`. The cell is checked against K here, against the
    /// depth by [`Region::check`].
    pub fn parse(text: &str) -> Result<Region, ConvertError> {
        let bad = || {
            ConvertError::Usage(format!(
                "--region {text} is not K:X,Y,Z (a level and a cell of that level, e.g. 2:0,3,1)"
            ))
        };
        let (k, xyz) = text.split_once(':').ok_or_else(bad)?;
        let level: u8 = k.trim().parse().map_err(|_| bad())?;
        let cell: Vec<u32> = xyz
            .split(',')
            .map(|w| w.trim().parse::<u32>())
            .collect::<Result<_, _>>()
            .map_err(|_| bad())?;
        let [x, y, z] = cell[..] else {
            return Err(bad());
        };
        let region = Region {
            level,
            cell: [x, y, z],
        };
        if level > dagfmt::layout::MAX_DEPTH {
            return Err(ConvertError::Usage(format!(
                "--region {text}: level {level} is above the largest depth {}",
                dagfmt::layout::MAX_DEPTH
            )));
        }
        if region.cell.iter().any(|&c| u64::from(c) >= 1u64 << level) {
            return Err(ConvertError::Usage(format!(
                "--region {text}: the cell lies outside 0..{} on some axis at level {level}",
                1u64 << level
            )));
        }
        Ok(region)
    }

    /// The region from its level and Morton index.
    pub fn from_index(level: u8, index: u64) -> Region {
        Region {
            level,
            cell: dagfmt::morton::decode(index),
        }
    }

    /// Every region of level `level`, in Morton order.
    pub fn all(level: u8) -> impl Iterator<Item = Region> {
        (0..1u64 << (3 * u32::from(level))).map(move |i| Region::from_index(level, i))
    }

    /// The cell's Morton index among the `8^K` cells of its level.
    pub fn index(&self) -> u64 {
        dagfmt::morton::encode(self.cell[0], self.cell[1], self.cell[2])
    }

    /// Checks the region against the depth: a cell holds at least one 4³
    /// brick, so K ≤ D − 2.
    pub fn check(&self, depth: u8) -> Result<(), ConvertError> {
        if self.level > depth {
            return Err(ConvertError::Usage(format!(
                "--region {self}: level {} is below the voxels of depth {depth} (K must be at most D - 2)",
                self.level
            )));
        }
        if self.level + 2 > depth {
            return Err(ConvertError::Usage(format!(
                "--region {self}: level {} is finer than the 4^3 bricks of depth {depth} (K must be at most D - 2)",
                self.level
            )));
        }
        Ok(())
    }

    /// The Morton codes of the voxels of the cell at depth `depth`.
    pub fn voxel_codes(&self, depth: u8) -> Range<u64> {
        let shift = 3 * u32::from(depth - self.level);
        let i = self.index();
        (i << shift)..((i + 1) << shift)
    }

    /// The Morton codes of the 4³ bricks of the cell at depth `depth`.
    pub fn brick_codes(&self, depth: u8) -> Range<u64> {
        let r = self.voxel_codes(depth);
        (r.start >> 6)..(r.end >> 6)
    }
}

/// What the final file keeps of the colours of the parts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ColourMode {
    /// No colour section.
    None,
    /// A VOXEL_COLORS section.
    Raw,
    /// A PACKED_COLORS section, packed within this per-channel error when
    /// the parts are joined (parts keep raw colours).
    Packed(u8),
}

impl ColourMode {
    fn to_bytes(self) -> (u8, u8) {
        match self {
            ColourMode::None => (0, 0),
            ColourMode::Raw => (1, 0),
            ColourMode::Packed(e) => (2, e),
        }
    }

    /// The colour mode of a conversion: whether it writes colours, and the
    /// packing error bound it asks for.
    pub fn of(colours: bool, error: Option<u8>) -> ColourMode {
        match (colours, error) {
            (false, _) => ColourMode::None,
            (true, None) => ColourMode::Raw,
            (true, Some(e)) => ColourMode::Packed(e),
        }
    }
}

impl fmt::Display for ColourMode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ColourMode::None => write!(f, "no colours"),
            ColourMode::Raw => write!(f, "raw colours"),
            ColourMode::Packed(e) => write!(f, "colours packed within {e}"),
        }
    }
}

/// The PART_PLACEMENT section: which level-K cells a part covers.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Placement {
    /// The region level K.
    pub level: u8,
    /// The Morton indices of the level-K cells covered: a contiguous range.
    pub cells: Range<u64>,
    /// What the joined file does with the colours.
    pub colours: ColourMode,
}

/// A rule of spec § 24.4 broken: code, name, byte offset, message.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PartError {
    /// The code, `E090` ….
    pub code: &'static str,
    /// The rule's name.
    pub name: &'static str,
    /// Byte offset in the file (the placement section, or the section table
    /// entry, concerned).
    pub offset: u64,
    /// What is wrong.
    pub message: String,
}

impl fmt::Display for PartError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} {} at byte {:#x}: {}",
            self.code, self.name, self.offset, self.message
        )
    }
}

/// The part rules (spec § 24.4): code and name.
pub mod rules {
    /// The placement section is malformed, or there is more than one.
    pub const BAD_PLACEMENT: (&str, &str) = ("E090", "bad-part-placement");
    /// The placement's version is not one this reader knows.
    pub const PART_VERSION: (&str, &str) = ("E091", "part-version");
    /// The region level or the cell range is impossible for the depth.
    pub const BAD_REGION: (&str, &str) = ("E092", "bad-part-region");
    /// The colour mode is unknown or disagrees with the colour sections.
    pub const PART_COLOURS: (&str, &str) = ("E093", "part-colours");
    /// A set voxel lies outside the declared cells.
    pub const VOXEL_OUTSIDE: (&str, &str) = ("E094", "part-voxel-outside");
    /// Merge: the parts disagree on depth, root cube, attributes, region
    /// level or colours.
    pub const MISMATCH: (&str, &str) = ("E095", "parts-mismatch");
    /// Merge: two parts declare a common cell.
    pub const OVERLAP: (&str, &str) = ("E096", "parts-overlap");
    /// Merge: the parts' cells are not one contiguous Morton range.
    pub const GAP: (&str, &str) = ("E097", "parts-gap");
    /// Merge: an input has no placement (it is not a part).
    pub const NOT_A_PART: (&str, &str) = ("E098", "not-a-part");
}

fn part_error(rule: (&'static str, &'static str), offset: u64, message: String) -> PartError {
    PartError {
        code: rule.0,
        name: rule.1,
        offset,
        message,
    }
}

impl Placement {
    /// The section's entry in the section table.
    pub fn section(&self) -> SectionInfo {
        SectionInfo {
            kind: SectionKind::UnknownOptional(PART_PLACEMENT_KIND),
            level: 0,
            pointer_width: 0,
            length: PLACEMENT_LEN as u64,
            item_count: 1,
            crc: crc32c::crc32c(&self.to_bytes()),
            version_minor: 0,
        }
    }

    /// The section's bytes.
    pub fn to_bytes(&self) -> [u8; PLACEMENT_LEN] {
        let mut b = [0u8; PLACEMENT_LEN];
        b[0..8].copy_from_slice(&PLACEMENT_MAGIC);
        b[8..10].copy_from_slice(&PART_VERSION.to_le_bytes());
        b[10] = self.level;
        let (mode, error) = self.colours.to_bytes();
        b[11] = mode;
        b[12] = error;
        b[16..24].copy_from_slice(&self.cells.start.to_le_bytes());
        b[24..32].copy_from_slice(&self.cells.end.to_le_bytes());
        b
    }

    /// Whether the part covers every cell of its level (the whole cube).
    pub fn is_whole(&self) -> bool {
        self.cells == (0..1u64 << (3 * u32::from(self.level)))
    }

    /// The Morton codes of the voxels covered, at depth `depth`.
    pub fn voxel_codes(&self, depth: u8) -> Range<u64> {
        let shift = 3 * u32::from(depth - self.level);
        (self.cells.start << shift)..(self.cells.end << shift)
    }
}

/// Finds the placement of an opened (and, for [`check_part`], validated)
/// file: `Ok(None)` when it has no PART_PLACEMENT section (it is not a
/// part), an error of rules E090–E093 when the section is malformed.
pub fn read_placement(dag: &Dag<'_>) -> Result<Option<Placement>, PartError> {
    let mut found = None;
    for s in dag.sections() {
        if s.kind != SectionKind::UnknownOptional(PART_PLACEMENT_KIND) {
            continue;
        }
        let entry = s.entry_offset();
        if found.is_some() {
            return Err(part_error(
                rules::BAD_PLACEMENT,
                entry,
                "more than one PART_PLACEMENT section".into(),
            ));
        }
        found = Some(*s);
    }
    let Some(s) = found else { return Ok(None) };
    let entry = s.entry_offset();
    if s.length != PLACEMENT_LEN as u64 || s.item_count != 1 || s.level != 0 || s.pointer_width != 0
    {
        return Err(part_error(
            rules::BAD_PLACEMENT,
            entry,
            format!(
                "the PART_PLACEMENT section has {} bytes, {} items, level {} and width {} (expected {PLACEMENT_LEN}, 1, 0, 0)",
                s.length, s.item_count, s.level, s.pointer_width
            ),
        ));
    }
    let at = s.offset;
    let b = dag
        .bytes()
        .get(at as usize..at as usize + PLACEMENT_LEN)
        .ok_or_else(|| {
            part_error(
                rules::BAD_PLACEMENT,
                entry,
                "the PART_PLACEMENT section lies outside the file".into(),
            )
        })?;
    if b[0..8] != PLACEMENT_MAGIC {
        return Err(part_error(
            rules::BAD_PLACEMENT,
            at,
            "the PART_PLACEMENT section does not start with VDAGPART".into(),
        ));
    }
    let version = u16::from_le_bytes([b[8], b[9]]);
    if version != PART_VERSION {
        return Err(part_error(
            rules::PART_VERSION,
            at + 8,
            format!("part version {version} is not {PART_VERSION}"),
        ));
    }
    if b[13..16].iter().chain(&b[32..48]).any(|&x| x != 0) {
        return Err(part_error(
            rules::BAD_PLACEMENT,
            at + 13,
            "a reserved byte of the PART_PLACEMENT section is not 0".into(),
        ));
    }
    let level = b[10];
    let depth = dag.header().depth;
    let start = u64::from_le_bytes(b[16..24].try_into().expect("8 bytes"));
    let end = u64::from_le_bytes(b[24..32].try_into().expect("8 bytes"));
    if level + 2 > depth {
        return Err(part_error(
            rules::BAD_REGION,
            at + 10,
            format!(
                "region level {level} is above D - 2 = {}",
                depth.saturating_sub(2)
            ),
        ));
    }
    let cells = 1u64 << (3 * u32::from(level));
    if start >= end || end > cells {
        return Err(part_error(
            rules::BAD_REGION,
            at + 16,
            format!(
                "the cells {start}..{end} are not a non-empty range within 0..{cells} at level {level}"
            ),
        ));
    }
    let colours = match (b[11], b[12]) {
        (0, 0) => ColourMode::None,
        (1, 0) => ColourMode::Raw,
        (2, e) if e <= 127 => ColourMode::Packed(e),
        (m, e) => {
            return Err(part_error(
                rules::PART_COLOURS,
                at + 11,
                format!(
                    "colour mode {m} with error bound {e} is not one of 0, 1 (bound 0) or 2 (bound 0..=127)"
                ),
            ));
        }
    };
    let has_raw = dag.colors().is_some();
    let has_packed = dag.packed_colors().is_some();
    if has_packed || has_raw != (colours != ColourMode::None) {
        return Err(part_error(
            rules::PART_COLOURS,
            at + 11,
            format!(
                "the placement says {colours} but the part has {}",
                if has_packed {
                    "a PACKED_COLORS section (parts keep raw colours)"
                } else if has_raw {
                    "a VOXEL_COLORS section"
                } else {
                    "no colour section"
                }
            ),
        ));
    }
    Ok(Some(Placement {
        level,
        cells: start..end,
        colours,
    }))
}

/// Checks a part: its placement (E090–E093) and that every occupied cell of
/// its region level lies in the declared range (E094). The file must have
/// passed the format's validation: this walks its levels.
pub fn check_part(dag: &Dag<'_>) -> Result<Option<Placement>, PartError> {
    let Some(p) = read_placement(dag)? else {
        return Ok(None);
    };
    let section = dag
        .sections()
        .iter()
        .find(|s| s.kind == SectionKind::UnknownOptional(PART_PLACEMENT_KIND))
        .map_or(0, |s| s.offset);
    if dag.header().attribute_kind != AttributeKind::VoxelCount {
        // Parts need the counts to split the colours by cell.
        return Err(part_error(
            rules::BAD_PLACEMENT,
            25,
            "a part must have attribute kind 1 (voxel counts)".into(),
        ));
    }
    let outside = first_outside(dag, p.level, &p.cells)
        .map_err(|e| part_error(rules::VOXEL_OUTSIDE, e.offset, e.message))?;
    if let Some(index) = outside {
        let r = Region::from_index(p.level, index);
        return Err(part_error(
            rules::VOXEL_OUTSIDE,
            section + 16,
            format!(
                "cell {r} (index {index}) holds voxels but lies outside the declared cells {}..{}",
                p.cells.start, p.cells.end
            ),
        ));
    }
    Ok(Some(p))
}

/// The first occupied cell of `level` outside `cells`, if any. A node whose
/// cells all lie inside the range is not descended into, and one whose cells
/// all lie outside answers at once, so at most two nodes per level are
/// opened: the work does not grow with the volume (a few hundred bytes can
/// describe 8^19 occupied cells).
fn first_outside(
    dag: &Dag<'_>,
    level: u8,
    cells: &Range<u64>,
) -> Result<Option<u64>, dagfmt::FormatError> {
    fn walk(
        dag: &Dag<'_>,
        at: u8,
        pointer: u32,
        prefix: u64,
        level: u8,
        cells: &Range<u64>,
    ) -> Result<Option<u64>, dagfmt::FormatError> {
        let shift = 3 * u32::from(level - at);
        let (lo, hi) = (prefix << shift, (prefix + 1) << shift);
        debug_assert!(lo < hi);
        if cells.start <= lo && hi <= cells.end {
            return Ok(None);
        }
        if at == level {
            return Ok(Some(prefix));
        }
        let node = dag.node(at, pointer)?;
        for c in 0..8u32 {
            if let Some(p) = node.child_pointer(c) {
                let child = prefix << 3 | u64::from(c);
                let s = 3 * u32::from(level - at - 1);
                let (clo, chi) = (child << s, (child + 1) << s);
                if chi <= cells.start || cells.end <= clo {
                    // Occupied and wholly outside: its first occupied cell.
                    return first_cell(dag, at + 1, p, child, level).map(Some);
                }
                if let Some(found) = walk(dag, at + 1, p, child, level, cells)? {
                    return Ok(Some(found));
                }
            }
        }
        Ok(None)
    }
    match dag.root() {
        None => Ok(None),
        Some(root) => walk(dag, 0, root.pointer, 0, level, cells),
    }
}

/// The first occupied cell of `level` under a node: its first children down.
fn first_cell(
    dag: &Dag<'_>,
    mut at: u8,
    mut pointer: u32,
    mut prefix: u64,
    level: u8,
) -> Result<u64, dagfmt::FormatError> {
    while at < level {
        let node = dag.node(at, pointer)?;
        let c = node.child_mask().trailing_zeros();
        pointer = node.child_pointer(c).unwrap_or(0);
        prefix = prefix << 3 | u64::from(c);
        at += 1;
    }
    Ok(prefix)
}

/// Calls `f(index, node)` for every occupied cell of `level` (≤ D − 2), in
/// Morton order, with its node (the pointer of its record, or its leaf
/// index at the leaf level).
pub fn visit_cells(
    dag: &Dag<'_>,
    level: u8,
    f: &mut dyn FnMut(u64, u32),
) -> Result<(), dagfmt::FormatError> {
    fn walk(
        dag: &Dag<'_>,
        at: u8,
        pointer: u32,
        index: u64,
        level: u8,
        f: &mut dyn FnMut(u64, u32),
    ) -> Result<(), dagfmt::FormatError> {
        if at == level {
            f(index, pointer);
            return Ok(());
        }
        let node = dag.node(at, pointer)?;
        let mask = node.child_mask();
        for c in 0..8u32 {
            if let Some(p) = node.child_pointer(c) {
                debug_assert!(mask & (1 << c) != 0);
                walk(dag, at + 1, p, index << 3 | u64::from(c), level, f)?;
            }
        }
        Ok(())
    }
    match dag.root() {
        None => Ok(()),
        Some(root) => walk(dag, 0, root.pointer, 0, level, f),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parse_checks_the_cell_against_its_level() {
        let r = Region::parse("2:1,3,0").unwrap();
        assert_eq!(r.level, 2);
        assert_eq!(r.cell, [1, 3, 0]);
        assert_eq!(r.to_string(), "2:1,3,0");
        assert_eq!(Region::from_index(2, r.index()), r);
        assert!(Region::parse("2:4,0,0").is_err());
        assert!(Region::parse("2:1,1").is_err());
        assert!(Region::parse("x:1,1,1").is_err());
        assert!(Region::parse("1,1,1").is_err());
        assert!(Region::parse("22:0,0,0").is_err());
    }

    #[test]
    fn cells_tile_the_codes_in_morton_order() {
        let depth = 5;
        let mut next = 0;
        for r in Region::all(2) {
            r.check(depth).unwrap();
            let codes = r.voxel_codes(depth);
            assert_eq!(codes.start, next);
            next = codes.end;
            // The cell's voxels are those whose coordinates fall in it.
            let v = dagfmt::morton::decode(codes.start);
            assert_eq!(v.map(|c| c >> (depth - 2)), r.cell);
        }
        assert_eq!(next, 1 << (3 * depth));
        assert!(Region::parse("4:0,0,0").unwrap().check(5).is_err());
        assert!(Region::parse("3:0,0,0").unwrap().check(5).is_ok());
    }

    #[test]
    fn placement_bytes_round_trip() {
        let p = Placement {
            level: 3,
            cells: 5..77,
            colours: ColourMode::Packed(4),
        };
        let b = p.to_bytes();
        assert_eq!(&b[0..8], b"VDAGPART");
        assert_eq!(b[10], 3);
        assert_eq!((b[11], b[12]), (2, 4));
        assert!(!p.is_whole());
        assert!(
            Placement {
                level: 1,
                cells: 0..8,
                colours: ColourMode::None
            }
            .is_whole()
        );
    }
}
