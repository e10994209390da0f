//! The validator: checks every rule of spec/VDAG.md § Validation rules and
//! reports every violation it finds, not only the first.
//!
//! [`validate`] returns the list of [`FormatError`]s (empty when the file is
//! valid), sorted by byte offset; [`validate_with`] takes limits and says
//! whether the list was cut short.
//!
//! The work is linear in the file size: one pass of CRC-32C over every
//! section (on a second thread for large files, see
//! [`ValidateOptions::threads`]), one pass over each level's records (in 1.0,
//! a large level in contiguous parts on up to [`MAX_PARTS`] threads, with the
//! findings of one sequential pass), and per level a bitmap of record starts
//! and one of referenced records per part (together 1/8 of the level's
//! size) plus one subtree voxel count per two words of the
//! level (16, 32 or 64 bits as the level's depth needs: at most the level's
//! size). Only two levels' indexes are held at a time; nothing is allocated
//! per node.
//!
//! # What is checked, in order
//!
//! 1. The header and the section table (shared with the reader:
//!    `reader::check_layout`): E001-E013, E020-E026, E030, the leaf-level E043,
//!    E063, E080, E081 (a packed colour section's entry and trailer), the reserved fields (E009), the header checksum (E011) and the
//!    padding between the table, the sections and the end of the file (E023).
//! 2. Section checksums (E028), minimal pointer widths (E027) and the root
//!    level's node count (E040).
//! 3. The levels, leaf level first: empty leaf masks (E048); then each node
//!    level upwards: record framing (E041, E042, E044, E043 against the
//!    records found), pointers (E045, E046), attributes (E060, E061, from the
//!    exact subtree voxel counts computed on the way up) and, once a level's
//!    parent has been walked, records nobody points to (E047).
//! 4. The header's voxel count against the root's subtree count (E062).
//! 5. A format 2.0 file (spec §23.10) replaces steps 2 – 4 by the walk of
//!    `validate2` (E070 – E079 and the 1.0 rules that still apply).
//! 6. A packed colour section's directory and blocks (E082 – E087), unless
//!    its entry or trailer is wrong: after the first error in the directory,
//!    the blocks are not checked; after the first error in a block, the rest
//!    of that block is not checked.
//!
//! # After a fatal error
//!
//! - A file shorter than the header (E001), bad magic (E002) or another major
//!   version (E003) stops validation at once: nothing else can be interpreted.
//! - A depth out of range (E006), a section count out of range or a section
//!   table past the end of the file (E012) stop validation after the rest of
//!   the header has been checked (and the header checksum, when the table lies
//!   inside the file): without them the levels cannot be located.
//! - Every other header problem is reported and validation goes on: an
//!   unknown required feature (E004) or header size (E005) is checked as
//!   version 1.0 with the table at byte 128, an unknown attribute kind (E007)
//!   skips the attribute checks (E060, E061), a wrong file size (E010) or too
//!   large a file (E013) goes on with the bytes actually given.
//! - A section that lies outside the file (E020) is neither checksummed nor
//!   walked. A level section that cannot be interpreted (outside the file, an
//!   unknown required kind E025, not the right kind or level for its place
//!   E024, a node-level pointer width outside 1..=4 E026) is not walked:
//!   pointers into it are not checked (E045, E046, E027), its records are not
//!   checked for references (E047), and the voxel counts of the levels above
//!   it, hence E061 and E062, are not checked.
//! - A pointer that is out of range or not at a record start makes the
//!   subtree count of its node unknown: E061 is not checked for that node and
//!   its ancestors, nor E062, so one broken pointer is one finding.
//! - A record that runs past the end of its level (E042) ends the walk of that
//!   level; its record count is then not compared with the item count (E043).
//! - After [`ValidateOptions::max_errors`] findings validation stops and
//!   [`ValidationReport::truncated`] is set.
//!
//! Not checked: the contents of sections of unknown optional kinds (nor their
//! level, pointer width and item count fields, which a later minor version may
//! give a meaning), the values of raw colours, and the unknown optional feature bits
//! and minor version (readers ignore them).

use crate::error::{ErrorCode, FormatError};
use crate::layout::{self, AttributeKind, COUNT_SATURATED, MAX_FILE_SIZE, SectionKind};
use crate::packed_colors;
use crate::prefetch::prefetch;
use crate::reader::{self, LayoutChecks, SectionEntry};
use std::ops::ControlFlow;
use std::sync::atomic::{AtomicU8, AtomicU64, Ordering::Relaxed};

/// Limits for [`validate_with`].
#[derive(Clone, Debug)]
pub struct ValidateOptions {
    /// Stop after this many findings (default 100 000), so that validating a
    /// large file of garbage does not build an enormous list.
    pub max_errors: usize,
    /// Files longer than this are reported as
    /// [`ErrorCode::FileTooLarge`] (default [`MAX_FILE_SIZE`]).
    pub max_file_size: u64,
    /// Whether large files may be checksummed on a second thread while the
    /// levels are walked, a 1.0 file's large levels walked in parts on up to
    /// [`MAX_PARTS`] threads (as many as the machine has cores), and a 2.0
    /// file's canonical check run on rayon's threads (default true). The
    /// findings are the same either way.
    pub threads: bool,
}

impl Default for ValidateOptions {
    fn default() -> Self {
        ValidateOptions {
            max_errors: 100_000,
            max_file_size: MAX_FILE_SIZE,
            threads: true,
        }
    }
}

/// What [`validate_with`] found.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ValidationReport {
    /// Every violation found, sorted by byte offset (stable: at one offset,
    /// in the order found).
    pub errors: Vec<FormatError>,
    /// Whether validation stopped at [`ValidateOptions::max_errors`]: there
    /// is at least one more violation than listed.
    pub truncated: bool,
}

impl ValidationReport {
    /// Whether the file is valid (no violation found and none left unlisted).
    pub fn is_valid(&self) -> bool {
        self.errors.is_empty() && !self.truncated
    }

    /// Whether some finding has the given code.
    pub fn has(&self, code: ErrorCode) -> bool {
        self.errors.iter().any(|e| e.code == code)
    }
}

/// Checks every rule of the format; returns every violation found (empty when
/// the file is valid), sorted by byte offset. Uses [`ValidateOptions::default`].
pub fn validate(bytes: &[u8]) -> Vec<FormatError> {
    validate_with(bytes, &ValidateOptions::default()).errors
}

/// Checks every rule of the format with the given limits.
pub fn validate_with(bytes: &[u8], options: &ValidateOptions) -> ValidationReport {
    validate_walked(bytes, options, Walk::for_options(options))
}

/// [`validate_with`], the node levels of a 1.0 file walked as `walk` says.
fn validate_walked(bytes: &[u8], options: &ValidateOptions, walk: Walk) -> ValidationReport {
    let mut findings = Findings {
        errors: Vec::new(),
        max: options.max_errors,
        truncated: false,
    };
    // Err(Stop) only means the error limit was reached; the report says so.
    let _ = check_file(bytes, options, walk, &mut findings);
    let mut errors = findings.errors;
    errors.sort_by_key(|e| e.offset);
    ValidationReport {
        errors,
        truncated: findings.truncated,
    }
}

/// Validation stopped because the error limit was reached.
#[derive(Debug)]
pub(crate) struct Stop;

/// The findings so far.
pub(crate) struct Findings {
    pub(crate) errors: Vec<FormatError>,
    max: usize,
    truncated: bool,
}

impl Findings {
    #[cold]
    #[inline(never)]
    pub(crate) fn report(&mut self, e: FormatError) -> Result<(), Stop> {
        if self.errors.len() >= self.max {
            self.truncated = true;
            return Err(Stop);
        }
        self.errors.push(e);
        Ok(())
    }

    /// Stops as [`Findings::report`] does at the limit: findings were left
    /// out elsewhere.
    fn report_overflow(&mut self) -> Result<(), Stop> {
        self.truncated = true;
        Err(Stop)
    }
}

/// A subtree voxel count that cannot be known (a pointer of the subtree is
/// broken or leads into a level that was not walked). Saturating additions
/// keep it unknown.
const UNKNOWN: u64 = u64::MAX;

/// What the attribute bits of the nodes must hold.
#[derive(Clone, Copy, PartialEq, Eq)]
enum AttributeRule {
    /// Kind 0: zero.
    Zero,
    /// Kind 1: the subtree's voxel count, saturated.
    VoxelCount,
    /// Unknown kind (reported already): not checked.
    Unchecked,
}

fn check_file(
    bytes: &[u8],
    options: &ValidateOptions,
    walk: Walk,
    f: &mut Findings,
) -> Result<(), Stop> {
    let checks = LayoutChecks {
        thorough: true,
        max_file_size: options.max_file_size,
        accept_v2: true,
    };
    let mut stopped = false;
    let layout = reader::check_layout(bytes, checks, &mut |e| match f.report(e) {
        Ok(()) => ControlFlow::Continue(()),
        Err(Stop) => {
            stopped = true;
            ControlFlow::Break(())
        }
    });
    if stopped {
        return Err(Stop);
    }
    let Some(layout) = layout else {
        // A fatal problem, reported already.
        return Ok(());
    };
    let sections = &layout.sections;

    // Section checksums: on a second thread while the levels are walked,
    // when there is enough to gain.
    let checksummed: Vec<(&SectionEntry, &[u8])> = sections
        .iter()
        .filter_map(|e| section_bytes(bytes, e).map(|data| (e, data)))
        .collect();
    let checksum_bytes: usize = checksummed.iter().map(|(_, data)| data.len()).sum();
    let compute = || {
        checksummed
            .iter()
            .map(|(_, data)| crc32c::crc32c(data))
            .collect::<Vec<u32>>()
    };
    std::thread::scope(|scope| {
        let worker = (options.threads && checksum_bytes >= PARALLEL_CHECKSUM_BYTES)
            .then(|| {
                std::thread::Builder::new()
                    .name("vdag-checksums".into())
                    .spawn_scoped(scope, compute)
                    .ok()
            })
            .flatten();
        // A large packed colour section's blocks are checked on a thread of
        // their own while the levels are walked; a small one after the walk.
        let colors = (options.threads && packed_colors_count(&layout) >= PARALLEL_COLORS)
            .then(|| {
                let max = f.max;
                let layout = &layout;
                std::thread::Builder::new()
                    .name("vdag-colors".into())
                    .spawn_scoped(scope, move || {
                        let mut own = Findings {
                            errors: Vec::new(),
                            max,
                            truncated: false,
                        };
                        let _ = check_packed_colors(layout, bytes, &mut own);
                        own
                    })
                    .ok()
            })
            .flatten();
        let walked = if layout.header.version_major == layout::VERSION_MAJOR_2 {
            crate::validate2::check_levels(&layout, bytes, f, options.threads)
        } else {
            check_levels(&layout, bytes, f, walk)
        };
        let walked = match colors {
            Some(colors) => {
                let own = colors
                    .join()
                    .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
                walked.and_then(|()| {
                    for e in own.errors {
                        f.report(e)?;
                    }
                    if own.truncated {
                        f.report_overflow()
                    } else {
                        Ok(())
                    }
                })
            }
            None => walked.and_then(|()| check_packed_colors(&layout, bytes, f)),
        };
        let computed = match worker {
            Some(worker) => worker
                .join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic)),
            None => compute(),
        };
        walked?;
        for ((entry, _), computed) in checksummed.iter().zip(computed) {
            if computed != entry.crc {
                f.report(FormatError::new(
                    ErrorCode::SectionChecksum,
                    entry.entry_offset() + 32,
                    format!(
                        "section {} checksum is {:#010x}, its {} bytes give {computed:#010x}",
                        entry.index, entry.crc, entry.length
                    ),
                ))?;
            }
        }
        Ok(())
    })
}

/// The blocks and directory of a packed colour section (E082 – E087); its
/// entry and trailer (E080, E081) were checked with the layout.
fn check_packed_colors(
    layout: &reader::Layout,
    bytes: &[u8],
    f: &mut Findings,
) -> Result<(), Stop> {
    for entry in &layout.sections {
        if entry.kind != SectionKind::PackedColors || entry.item_count != layout.header.voxel_count
        {
            continue;
        }
        let Some(data) = section_bytes(bytes, entry) else {
            continue;
        };
        for (code, offset, message) in packed_colors::check_section(data, entry.item_count) {
            if matches!(
                code,
                ErrorCode::BadPackedColorSection | ErrorCode::BadColorTrailer
            ) {
                continue;
            }
            f.report(FormatError::new(code, entry.offset + offset, message))?;
        }
    }
    Ok(())
}

/// Sections totalling at least this many bytes are checksummed on a second
/// thread (below it, starting the thread costs more than it saves).
const PARALLEL_CHECKSUM_BYTES: usize = 32 << 20;

/// Packed colours from which their blocks are checked on a thread of their own.
const PARALLEL_COLORS: u64 = 1 << 22;

/// Colours in the packed colour sections [`check_packed_colors`] checks.
fn packed_colors_count(layout: &reader::Layout) -> u64 {
    layout
        .sections
        .iter()
        .filter(|e| {
            e.kind == SectionKind::PackedColors && e.item_count == layout.header.voxel_count
        })
        .map(|e| e.item_count)
        .sum()
}

/// Everything after the section table except the checksums: pointer widths,
/// the root level, the walk of the levels and the header's voxel count.
fn check_levels(
    layout: &reader::Layout,
    bytes: &[u8],
    f: &mut Findings,
    walk: Walk,
) -> Result<(), Stop> {
    let header = &layout.header;
    let sections = &layout.sections;
    let leaf_level = header.depth - 2;
    let level_count = usize::from(leaf_level) + 1;

    // The level sections that can be interpreted.
    let levels: Vec<Option<LevelView<'_>>> = (0..level_count)
        .map(|i| {
            let entry = &sections[i];
            if !layout.usable[i] {
                return None;
            }
            section_bytes(bytes, entry).map(|data| LevelView { entry, bytes: data })
        })
        .collect();

    // Minimal pointer widths.
    for l in 0..usize::from(leaf_level) {
        let (Some(own), Some(child)) = (&levels[l], &levels[l + 1]) else {
            continue;
        };
        let units = if l + 1 == usize::from(leaf_level) {
            child.bytes.len() as u64 / 8
        } else {
            child.bytes.len() as u64 / 4
        };
        if let Some(minimal) = layout::minimal_pointer_width(units)
            && minimal != own.entry.pointer_width
        {
            f.report(
                FormatError::new(
                    ErrorCode::PointerWidthNotMinimal,
                    own.entry.entry_offset() + 5,
                    format!(
                        "level {l} has pointer width {}, but {units} {} of level {} need {minimal}",
                        own.entry.pointer_width,
                        if l + 1 == usize::from(leaf_level) {
                            "leaves"
                        } else {
                            "words"
                        },
                        l + 1
                    ),
                )
                .at_level(l as u8),
            )?;
        }
    }

    // The root level: one node, or none with every level empty.
    let root_entry = &sections[0];
    let all_empty = sections[..level_count]
        .iter()
        .all(|e| e.item_count == 0 && e.length == 0);
    if root_entry.item_count > 1 || (root_entry.item_count == 0 && !all_empty) {
        f.report(
            FormatError::new(
                ErrorCode::BadRootLevel,
                root_entry.entry_offset() + 24,
                format!(
                    "the root level holds {} nodes; it must hold 1, or 0 with every level empty",
                    root_entry.item_count
                ),
            )
            .at_level(0),
        )?;
    }

    let attributes = if !layout.attribute_kind_known {
        AttributeRule::Unchecked
    } else if header.attribute_kind == AttributeKind::VoxelCount {
        AttributeRule::VoxelCount
    } else {
        AttributeRule::Zero
    };

    let root_count = walk_levels(f, &levels, attributes, walk)?;
    if let Some(total) = root_count
        && total != header.voxel_count
    {
        f.report(FormatError::new(
            ErrorCode::HeaderVoxelCount,
            72,
            format!(
                "the header counts {} voxels, the DAG holds {total}",
                header.voxel_count
            ),
        ))?;
    }
    Ok(())
}

/// The most parts one level's walk is split into, one thread each: a record
/// keeps one referenced bit per part ([`ValidateOptions::threads`]).
pub const MAX_PARTS: usize = 3;

/// Levels shorter than this are walked in one part: below it, starting the
/// threads and framing the level cost more than the other cores return.
const PARALLEL_LEVEL_BYTES: usize = 4 << 20;

/// How the node levels of a 1.0 file are walked.
#[derive(Clone, Copy, Debug)]
struct Walk {
    /// Parts a large level is split into, one thread each (1 to [`MAX_PARTS`]).
    parts: usize,
    /// Levels shorter than this many bytes are walked in one part.
    min_split_bytes: usize,
    /// Records framed from a guessed split point ([`SYNC_RECORDS`]).
    sync_records: usize,
}

impl Walk {
    fn for_options(options: &ValidateOptions) -> Walk {
        let parts = if options.threads {
            std::thread::available_parallelism()
                .map_or(1, |n| n.get())
                .min(MAX_PARTS)
        } else {
            1
        };
        Walk {
            parts,
            min_split_bytes: PARALLEL_LEVEL_BYTES,
            sync_records: SYNC_RECORDS,
        }
    }
}

/// Whether the CPU has the POPCNT instruction (the check is cached by std).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn has_popcnt() -> bool {
    std::arch::is_x86_feature_detected!("popcnt")
}

/// Walks the levels bottom-up; returns the root's subtree voxel count when
/// it can be known. Picks a build of the walk for the CPU it runs on.
fn walk_levels(
    f: &mut Findings,
    levels: &[Option<LevelView<'_>>],
    attributes: AttributeRule,
    walk: Walk,
) -> Result<Option<u64>, Stop> {
    #[cfg(target_arch = "x86_64")]
    if has_popcnt() {
        // SAFETY: the CPU has the POPCNT instruction (checked just above),
        // the only feature `walk_levels_popcnt` is compiled to use.
        return unsafe { walk_levels_popcnt(f, levels, attributes, walk) };
    }
    walk_levels_inline(f, levels, attributes, walk)
}

/// [`walk_levels_inline`] compiled with the POPCNT instruction: the walk
/// counts bits for every record (its size), every pointer (record ranks)
/// and every leaf, and the baseline x86-64 target emulates `count_ones`
/// with a dozen instructions. (The records themselves are walked by
/// [`walk_range`], which picks its own build: it may run on another thread.)
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "popcnt")]
fn walk_levels_popcnt(
    f: &mut Findings,
    levels: &[Option<LevelView<'_>>],
    attributes: AttributeRule,
    walk: Walk,
) -> Result<Option<u64>, Stop> {
    walk_levels_inline(f, levels, attributes, walk)
}

#[inline(always)]
fn walk_levels_inline(
    f: &mut Findings,
    levels: &[Option<LevelView<'_>>],
    attributes: AttributeRule,
    walk: Walk,
) -> Result<Option<u64>, Stop> {
    let leaf_level = levels.len() - 1;
    let mut below = match &levels[leaf_level] {
        Some(view) => Below::Leaves(walk_leaf_level(f, view)?),
        None => Below::Unusable,
    };
    let mut root_count = match (&below, &levels[0]) {
        (Below::Leaves(leaves), Some(view)) if leaf_level == 0 => {
            match (
                leaves.counts.len() as u64 == view.entry.item_count,
                leaves.counts.first(),
            ) {
                (false, _) => None,
                (true, None) => Some(0),
                (true, Some(c)) => Some(u64::from(c.load(Relaxed) & LEAF_COUNT_MASK)),
            }
        }
        _ => None,
    };
    for l in (0..leaf_level).rev() {
        let Some(view) = &levels[l] else {
            below = Below::Unusable;
            continue;
        };
        let walked = walk_node_level(f, view, &below, attributes, leaf_level - l, walk)?;
        check_unreferenced(f, &below, &levels[l + 1])?;
        if l == 0 && walked.complete && walked.records == view.entry.item_count {
            root_count = match walked.counts.first() {
                None => Some(0),
                Some(UNKNOWN) => None,
                Some(count) => Some(count),
            };
        }
        below = walked.into_below();
    }
    Ok(root_count)
}

/// The bytes of a section, `None` when it lies outside the file.
fn section_bytes<'a>(bytes: &'a [u8], entry: &SectionEntry) -> Option<&'a [u8]> {
    let start = usize::try_from(entry.offset).ok()?;
    let end = start.checked_add(usize::try_from(entry.length).ok()?)?;
    bytes.get(start..end)
}

/// A level section that can be interpreted.
struct LevelView<'a> {
    entry: &'a SectionEntry,
    bytes: &'a [u8],
}

impl LevelView<'_> {
    fn level(&self) -> u8 {
        self.entry.level
    }
}

/// The level below the one being walked, as its parent's pointers see it.
enum Below {
    /// A level that could not be interpreted (reported already).
    Unusable,
    /// The leaf level.
    Leaves(LeafLevel),
    /// A node level that has been walked, whose counts fit 16 bits.
    Nodes16(NodeLevel<u16>),
    /// The same, counts of 32 bits.
    Nodes32(NodeLevel<u32>),
    /// The same, counts of 64 bits.
    Nodes64(NodeLevel<u64>),
}

/// The leaf level, walked: per leaf one byte, its voxel count (0 to 64) with
/// [`LEAF_REFERENCED`] set once a pointer addresses it. One byte instead of
/// the 8-byte mask keeps the pointers' random accesses in cache. The parts
/// of the parent level's walk mark leaves from several threads; each stores
/// the same value (the count does not change), so a plain store, not a
/// locked read-modify-write, is enough.
struct LeafLevel {
    counts: Vec<AtomicU8>,
}

/// Set in a [`LeafLevel`] count byte when some pointer addresses the leaf.
const LEAF_REFERENCED: u8 = 0x80;
/// The voxel count bits of a [`LeafLevel`] count byte.
const LEAF_COUNT_MASK: u8 = 0x7F;

/// Per 64 words of a node level: which words start a record and which
/// records some pointer addresses. Kept together so that following a pointer
/// touches one cache line.
#[derive(Default)]
#[repr(C, align(32))]
struct WordBlock {
    starts: u64,
    /// Per part of the parent level's walk: the records its pointers
    /// address. Each word is written by its part's thread only (a plain
    /// load and store, no locked instruction; a shared word would lose
    /// marks), and the words are OR-ed when unreferenced records are looked
    /// for.
    referenced: [AtomicU64; MAX_PARTS],
}

impl WordBlock {
    /// The records some pointer addresses, whatever part it is in.
    fn referenced(&self) -> u64 {
        self.referenced
            .iter()
            .fold(0, |acc, r| acc | r.load(Relaxed))
    }
}

/// A node level, walked.
struct NodeLevel<T> {
    /// Words of the level (length / 4).
    words: u64,
    blocks: Vec<WordBlock>,
    /// Subtree voxel count of the record starting at word `w`, at index
    /// `w / 2` (`T::MAX` when it cannot be known). A valid record takes at
    /// least two words, so no two share an index; indexing by position rather
    /// than by record number lets a pointer's count be fetched without first
    /// ranking its record, so the two memory accesses of a pointer overlap.
    /// (Two records can share an index only after an invalid 4-byte record,
    /// E041; the index then holds `T::MAX`.) `T` is the narrowest type that
    /// holds the level's largest possible count, 8^(D - level): following
    /// pointers into a large level misses the cache, and a smaller array misses
    /// less.
    counts: Vec<T>,
}

/// An unsigned integer type holding subtree voxel counts, `MAX` meaning unknown.
trait CountSlot: Copy {
    /// The count ([`UNKNOWN`] for the unknown slot).
    fn get(self) -> u64;
    /// Stores `count`; a count the type cannot hold becomes unknown.
    fn put(count: u64) -> Self;
}

macro_rules! count_slot {
    ($($t:ty),*) => {$(
        impl CountSlot for $t {
            #[inline(always)]
            fn get(self) -> u64 {
                if self == <$t>::MAX { UNKNOWN } else { self as u64 }
            }
            #[inline(always)]
            fn put(count: u64) -> Self {
                <$t>::try_from(count).unwrap_or(<$t>::MAX)
            }
        }
    )*};
}
count_slot!(u16, u32, u64);

/// The counts of the level being walked, in the type its depth calls for.
enum OwnCounts {
    U16(Vec<u16>),
    U32(Vec<u32>),
    U64(Vec<u64>),
}

impl OwnCounts {
    /// Slots for a level of `len` bytes whose nodes cover `8^levels_above_leaves * 64` voxels at most.
    fn new(len: usize, levels_above_leaves: usize) -> Self {
        // A node of this level holds at most 8^(D - level) = 2^(3 * (levels_above_leaves + 2)) voxels.
        let bits = 3 * (levels_above_leaves + 2);
        let slots = len.div_ceil(8);
        if bits < 16 {
            OwnCounts::U16(vec![u16::MAX; slots])
        } else if bits < 32 {
            OwnCounts::U32(vec![u32::MAX; slots])
        } else {
            OwnCounts::U64(vec![u64::MAX; slots])
        }
    }

    /// The slots cut before each of `cuts` (increasing), one part each.
    fn split(&mut self, cuts: &[usize]) -> Vec<Slots<'_>> {
        match self {
            OwnCounts::U16(v) => split_at_cuts(v, cuts).into_iter().map(Slots::U16).collect(),
            OwnCounts::U32(v) => split_at_cuts(v, cuts).into_iter().map(Slots::U32).collect(),
            OwnCounts::U64(v) => split_at_cuts(v, cuts).into_iter().map(Slots::U64).collect(),
        }
    }

    /// Every slot unknown again, as [`OwnCounts::new`] makes them.
    fn reset(&mut self) {
        match self {
            OwnCounts::U16(v) => v.fill(u16::MAX),
            OwnCounts::U32(v) => v.fill(u32::MAX),
            OwnCounts::U64(v) => v.fill(u64::MAX),
        }
    }

    /// Makes slot `slot` unknown.
    fn set_unknown(&mut self, slot: usize) {
        self.split(&[])[0].set(slot, UNKNOWN);
    }

    fn first(&self) -> Option<u64> {
        match self {
            OwnCounts::U16(v) => v.first().map(|c| c.get()),
            OwnCounts::U32(v) => v.first().map(|c| c.get()),
            OwnCounts::U64(v) => v.first().map(|c| c.get()),
        }
    }
}

/// The count slots of one part of a level's walk.
enum Slots<'a> {
    U16(&'a mut [u16]),
    U32(&'a mut [u32]),
    U64(&'a mut [u64]),
}

impl Slots<'_> {
    /// Stores `count` in slot `slot`; false when the part has no such slot.
    #[inline(always)]
    fn set(&mut self, slot: usize, count: u64) -> bool {
        fn put<T: CountSlot>(v: &mut [T], slot: usize, count: u64) -> bool {
            v.get_mut(slot).map(|s| *s = T::put(count)).is_some()
        }
        match self {
            Slots::U16(v) => put(v, slot, count),
            Slots::U32(v) => put(v, slot, count),
            Slots::U64(v) => put(v, slot, count),
        }
    }
}

/// `v` cut before each of `cuts` (increasing, at most `v.len()`).
fn split_at_cuts<'a, T>(mut v: &'a mut [T], cuts: &[usize]) -> Vec<&'a mut [T]> {
    let mut parts = Vec::with_capacity(cuts.len() + 1);
    let mut done = 0;
    for &cut in cuts {
        let (part, rest) = std::mem::take(&mut v).split_at_mut(cut - done);
        parts.push(part);
        v = rest;
        done = cut;
    }
    parts.push(v);
    parts
}

/// What a pointer leads to.
enum Visit {
    /// A record whose subtree holds this many voxels (maybe [`UNKNOWN`]).
    Count(u64),
    /// Nothing: past the end of the level.
    OutOfRange,
    /// The middle of a record.
    NotAtNode,
}

/// The level a node level's pointers lead into, shared by the parts of the
/// walk.
trait ChildLevel: Sync {
    /// Follows pointer `p` of part `part` of the walk, marking its target
    /// referenced.
    fn visit(&self, p: u32, part: usize) -> Visit;
    /// Addressable units: words of a node level, leaves of the leaf level.
    fn units(&self) -> u64;
    /// Forgets every mark [`ChildLevel::visit`] made.
    fn clear_marks(&self);
    /// Asks for the cache lines [`ChildLevel::visit`] of `p` will read.
    fn prefetch(&self, p: u32);
    /// "word" or "leaf", for messages.
    const UNIT: &'static str;
}

/// Pointers into a level that was not walked lead to unknown counts.
struct Unchecked;

impl ChildLevel for Unchecked {
    #[inline(always)]
    fn visit(&self, _p: u32, _part: usize) -> Visit {
        Visit::Count(UNKNOWN)
    }
    fn units(&self) -> u64 {
        0
    }
    fn clear_marks(&self) {}
    #[inline(always)]
    fn prefetch(&self, _p: u32) {}
    const UNIT: &'static str = "unit";
}

impl ChildLevel for LeafLevel {
    #[inline(always)]
    fn visit(&self, p: u32, _part: usize) -> Visit {
        let Some(c) = self.counts.get(p as usize) else {
            return Visit::OutOfRange;
        };
        let count = c.load(Relaxed);
        c.store(count | LEAF_REFERENCED, Relaxed);
        Visit::Count(u64::from(count & LEAF_COUNT_MASK))
    }
    fn units(&self) -> u64 {
        self.counts.len() as u64
    }
    #[inline(always)]
    fn prefetch(&self, p: u32) {
        if let Some(c) = self.counts.get(p as usize) {
            prefetch(c);
        }
    }
    fn clear_marks(&self) {
        for c in &self.counts {
            c.store(c.load(Relaxed) & LEAF_COUNT_MASK, Relaxed);
        }
    }
    const UNIT: &'static str = "leaf";
}

impl<T: CountSlot + Sync> ChildLevel for NodeLevel<T> {
    #[inline(always)]
    fn visit(&self, p: u32, part: usize) -> Visit {
        let w = u64::from(p);
        if w >= self.words {
            return Visit::OutOfRange;
        }
        // `blocks` and `counts` cover every word, so these lookups succeed.
        let count = self
            .counts
            .get((w >> 1) as usize)
            .map_or(UNKNOWN, |c| c.get());
        let Some(block) = self.blocks.get((w >> 6) as usize) else {
            return Visit::OutOfRange;
        };
        let bit = 1u64 << (w & 63);
        if block.starts & bit == 0 {
            return Visit::NotAtNode;
        }
        let referenced = &block.referenced[part];
        referenced.store(referenced.load(Relaxed) | bit, Relaxed);
        Visit::Count(count)
    }
    fn units(&self) -> u64 {
        self.words
    }
    #[inline(always)]
    fn prefetch(&self, p: u32) {
        if let Some(c) = self.counts.get((p >> 1) as usize) {
            prefetch(c);
        }
        if let Some(b) = self.blocks.get((p >> 6) as usize) {
            prefetch(b);
        }
    }
    fn clear_marks(&self) {
        for r in self.blocks.iter().flat_map(|b| &b.referenced) {
            r.store(0, Relaxed);
        }
    }
    const UNIT: &'static str = "word";
}

/// Checks the leaf masks (E048) and indexes the leaf level.
#[inline(always)]
fn walk_leaf_level(f: &mut Findings, view: &LevelView<'_>) -> Result<LeafLevel, Stop> {
    let whole = view.bytes.len() / 8 * 8;
    let masks: &[[u8; 8]] = bytemuck::cast_slice(&view.bytes[..whole]);
    let counts: Vec<u8> = masks
        .iter()
        .map(|m| u64::from_ne_bytes(*m).count_ones() as u8)
        .collect();
    // A zero mask is the only one with count 0; look per leaf only where a chunk has one.
    for (c, chunk) in counts.chunks(256).enumerate() {
        if chunk.iter().fold(u8::MAX, |acc, &n| acc.min(n)) != 0 {
            continue;
        }
        for (i, _) in chunk.iter().enumerate().filter(|&(_, &n)| n == 0) {
            let index = (c * 256 + i) as u64;
            f.report(
                FormatError::new(
                    ErrorCode::EmptyLeafMask,
                    view.entry.offset + index * 8,
                    "leaf mask is zero (a leaf holds at least one voxel)",
                )
                .at_level(view.level())
                .at_node(index),
            )?;
        }
    }
    Ok(LeafLevel {
        counts: counts.into_iter().map(AtomicU8::new).collect(),
    })
}

/// The outcome of walking one node level.
struct WalkedLevel {
    words: u64,
    blocks: Vec<WordBlock>,
    counts: OwnCounts,
    /// Records found.
    records: u64,
    /// Whether the walk reached the end of the section (no truncated record).
    complete: bool,
}

impl WalkedLevel {
    fn into_below(self) -> Below {
        let WalkedLevel {
            words,
            blocks,
            counts,
            ..
        } = self;
        match counts {
            OwnCounts::U16(counts) => Below::Nodes16(NodeLevel {
                words,
                blocks,
                counts,
            }),
            OwnCounts::U32(counts) => Below::Nodes32(NodeLevel {
                words,
                blocks,
                counts,
            }),
            OwnCounts::U64(counts) => Below::Nodes64(NodeLevel {
                words,
                blocks,
                counts,
            }),
        }
    }
}

/// Walks node level `view`, `levels_above_leaves` levels above the leaf level.
#[inline(always)]
fn walk_node_level(
    f: &mut Findings,
    view: &LevelView<'_>,
    below: &Below,
    attributes: AttributeRule,
    levels_above_leaves: usize,
    walk: Walk,
) -> Result<WalkedLevel, Stop> {
    let counts = OwnCounts::new(view.bytes.len(), levels_above_leaves);
    match below {
        Below::Unusable => walk_width(f, view, &Unchecked, attributes, counts, walk),
        Below::Leaves(leaves) => walk_width(f, view, leaves, attributes, counts, walk),
        Below::Nodes16(nodes) => walk_width(f, view, nodes, attributes, counts, walk),
        Below::Nodes32(nodes) => walk_width(f, view, nodes, attributes, counts, walk),
        Below::Nodes64(nodes) => walk_width(f, view, nodes, attributes, counts, walk),
    }
}

#[inline(always)]
fn walk_width<C: ChildLevel>(
    f: &mut Findings,
    view: &LevelView<'_>,
    child: &C,
    attributes: AttributeRule,
    counts: OwnCounts,
    walk: Walk,
) -> Result<WalkedLevel, Stop> {
    match view.entry.pointer_width {
        1 => walk_parts::<1, C>(f, view, child, attributes, counts, walk),
        2 => walk_parts::<2, C>(f, view, child, attributes, counts, walk),
        3 => walk_parts::<3, C>(f, view, child, attributes, counts, walk),
        // A usable node level has width 1 to 4.
        _ => walk_parts::<4, C>(f, view, child, attributes, counts, walk),
    }
}

/// Records framed from a guessed split point before the part starts: two
/// framings of one level that start at different words land on a common
/// record start after a few records (the sizes are small and varied), so
/// the framing from the guess almost always reaches a true record start
/// within this many records. The part before confirms it by reaching it.
const SYNC_RECORDS: usize = 32;

/// Up to `parts - 1` positions, about `len / parts` bytes apart, where the
/// walk of a level of pointer width `W` is split: from a guess (a word near
/// the part's share), `sync_records` records are framed by their headers
/// alone (the child mask gives the size), and the part starts where that
/// framing ends. Nothing before the guess is read: the split is speculative,
/// and [`walk_parts`] keeps it only when the part before ends exactly
/// there (otherwise the level is walked again in one part). A guess whose
/// framing runs past the level's end gives no split.
#[inline(always)]
fn split_points<const W: usize>(sec: &[u8], parts: usize, sync_records: usize) -> Vec<usize> {
    let len = sec.len();
    let mut splits: Vec<usize> = Vec::with_capacity(parts.saturating_sub(1));
    'parts: for k in 1..parts {
        let mut pos = (len / parts * k) & !3;
        for _ in 0..sync_records {
            let Some(&mask) = sec.get(pos) else {
                break 'parts;
            };
            let size = 4 + (mask.count_ones() as usize * W).next_multiple_of(4);
            if size > len - pos {
                break 'parts;
            }
            pos += size;
        }
        if pos >= len {
            break;
        }
        if splits.last().is_none_or(|&s| s < pos) {
            splits.push(pos);
        }
    }
    splits
}

/// One part of a level's walk: records `from..to` (byte offsets; `to` is the
/// next part's start or the level's end), numbered from 0 (the part's first
/// record number is known once the part before has ended), with the count
/// slots and record-start blocks its records own.
struct Range<'a> {
    part: usize,
    from: usize,
    to: usize,
    /// Slots from `slot_base` on.
    slots: Slots<'a>,
    slot_base: usize,
    /// Blocks from `block_base` on; the starts in the block before it (which
    /// the previous part owns) go to [`RangeEnd::head`].
    blocks: &'a mut [WordBlock],
    block_base: usize,
}

/// How a part's walk ended.
struct RangeEnd {
    /// Records walked.
    records: u64,
    /// Where the walk ended: the start of the record after its last (at or
    /// past `to`), or of a record that runs past the level's end.
    end: usize,
    /// Whether it reached `to` (no truncated record).
    complete: bool,
    /// Record starts in the block before its own blocks.
    head: u64,
    /// Whether its last record's count slot is the next part's first (an
    /// invalid 4-byte record just before it): the slot's count is then
    /// unknown, as one walk would leave it.
    shared_tail: bool,
}

/// Walks the records of a node level with pointer width `W` in parts, on
/// [`Walk::parts`] threads when the level is large: framing, pointers,
/// attributes; indexes the level for its parent. Findings are reported in
/// record order as one walk would: the first part reports into `f`, the
/// others into lists of their own, appended after it in order (their record
/// numbers shifted by the records before them), so that the findings, their
/// order and where [`ValidateOptions::max_errors`] cuts them do not depend
/// on the parts. A part's start is a guess ([`split_points`]) that the part
/// before confirms by ending exactly there; when one is not confirmed (a
/// corrupted level), what the parts did is undone and the level is walked
/// again in one part.
#[inline(always)]
fn walk_parts<const W: usize, C: ChildLevel>(
    f: &mut Findings,
    view: &LevelView<'_>,
    child: &C,
    attributes: AttributeRule,
    mut counts: OwnCounts,
    walk: Walk,
) -> Result<WalkedLevel, Stop> {
    let len = view.bytes.len();
    let mut blocks: Vec<WordBlock> = std::iter::repeat_with(WordBlock::default)
        .take(len.div_ceil(4).div_ceil(64))
        .collect();
    let splits = if walk.parts > 1 && len >= walk.min_split_bytes {
        split_points::<W>(view.bytes, walk.parts.min(MAX_PARTS), walk.sync_records)
    } else {
        Vec::new()
    };
    let reported_before = f.errors.len();
    let mut ends = walk_split::<W, C>(
        f,
        view,
        child,
        attributes,
        &mut counts,
        &mut blocks,
        &splits,
    )?;
    if ends.len() < splits.len() + 1 {
        // A split was not confirmed: undo and walk the level in one part.
        f.errors.truncate(reported_before);
        child.clear_marks();
        counts.reset();
        blocks.iter_mut().for_each(|b| *b = WordBlock::default());
        ends = walk_split::<W, C>(f, view, child, attributes, &mut counts, &mut blocks, &[])?;
    }
    let block_cuts = splits.iter().map(|&s| (s / 4).div_ceil(64));
    for (end, cut) in ends.iter().skip(1).zip(block_cuts) {
        if end.head != 0 {
            blocks[cut - 1].starts |= end.head;
        }
    }
    for (end, &split) in ends.iter().zip(&splits) {
        if end.shared_tail {
            counts.set_unknown(split / 8);
        }
    }
    let records: u64 = ends.iter().map(|e| e.records).sum();
    let complete = ends.last().expect("the first part").complete;
    if complete && records != view.entry.item_count {
        let level = view.level();
        f.report(
            FormatError::new(
                ErrorCode::ItemCountMismatch,
                view.entry.entry_offset() + 24,
                format!(
                    "level {level} declares {} nodes, its bytes hold {records}",
                    view.entry.item_count
                ),
            )
            .at_level(level),
        )?;
    }
    Ok(WalkedLevel {
        words: len as u64 / 4,
        blocks,
        counts,
        records,
        complete,
    })
}

/// Walks a level in the parts that `splits` start, the first on this thread
/// and each other on a thread of its own (or after the first where no thread
/// can be started), and reports their findings in order. Returns how each
/// part ended, up to the first part whose start the part before did not
/// confirm (then fewer than the parts).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn walk_split<const W: usize, C: ChildLevel>(
    f: &mut Findings,
    view: &LevelView<'_>,
    child: &C,
    attributes: AttributeRule,
    counts: &mut OwnCounts,
    blocks: &mut [WordBlock],
    splits: &[usize],
) -> Result<Vec<RangeEnd>, Stop> {
    let len = view.bytes.len();
    // A part owns the slots and blocks from its first record's on; a block
    // its first record shares with the previous part stays the previous
    // part's (its starts come back as the head).
    let slot_cuts: Vec<usize> = splits.iter().map(|s| s / 8).collect();
    let block_cuts: Vec<usize> = splits.iter().map(|s| (s / 4).div_ceil(64)).collect();
    let mut ranges: Vec<Range<'_>> = counts
        .split(&slot_cuts)
        .into_iter()
        .zip(split_at_cuts(blocks, &block_cuts))
        .enumerate()
        .map(|(p, (slots, blocks))| {
            let (from, slot_base, block_base) = match p.checked_sub(1) {
                None => (0, 0, 0),
                Some(q) => (splits[q], slot_cuts[q], block_cuts[q]),
            };
            Range {
                part: p,
                from,
                to: splits.get(p).copied().unwrap_or(len),
                slots,
                slot_base,
                blocks,
                block_base,
            }
        })
        .collect();
    let first = ranges.remove(0);
    if ranges.is_empty() {
        return Ok(vec![walk_range::<W, C>(f, view, child, attributes, first)?]);
    }
    let max = f.max.saturating_sub(f.errors.len());
    let jobs: Vec<std::sync::Mutex<Option<Range<'_>>>> = ranges
        .into_iter()
        .map(|r| std::sync::Mutex::new(Some(r)))
        .collect();
    let run = |job: &std::sync::Mutex<Option<Range<'_>>>| {
        let range = job.lock().ok().and_then(|mut r| r.take())?;
        let mut own = Findings {
            errors: Vec::new(),
            max,
            truncated: false,
        };
        let end = walk_range::<W, C>(&mut own, view, child, attributes, range);
        Some((own, end))
    };
    let (first_end, others) = std::thread::scope(|scope| {
        let threads: Vec<_> = jobs
            .iter()
            .map(|job| {
                std::thread::Builder::new()
                    .name("vdag-walk".into())
                    .spawn_scoped(scope, || run(job))
                    .ok()
            })
            .collect();
        let first_end = walk_range::<W, C>(f, view, child, attributes, first);
        let others: Vec<_> = threads
            .into_iter()
            .zip(&jobs)
            .map(|(thread, job)| {
                let done = thread.map(|t| {
                    t.join()
                        .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
                });
                // A part whose thread did not start is still in its job.
                done.flatten().or_else(|| run(job))
            })
            .collect();
        (first_end, others)
    });
    let mut ends = vec![first_end?];
    let mut records_before = ends[0].records;
    for ((own, end), &split) in others.into_iter().flatten().zip(splits) {
        let before = ends.last().expect("the first part");
        if !before.complete || before.end != split {
            break;
        }
        for mut e in own.errors {
            e.node = e.node.map(|n| n + records_before);
            f.report(e)?;
        }
        if own.truncated {
            f.report_overflow()?;
        }
        let end = end?;
        records_before += end.records;
        ends.push(end);
    }
    Ok(ends)
}

/// How many records ahead of the walk [`prefetch_record`] runs.
const PREFETCH_RECORDS: usize = 12;

/// Asks for the cache lines the pointers of the record at `pos` read (when
/// it is before `to` and whole) and returns the next record's start.
#[inline(always)]
fn prefetch_record<const W: usize, C: ChildLevel>(
    sec: &[u8],
    pos: usize,
    to: usize,
    child: &C,
) -> usize {
    if pos >= to {
        return pos;
    }
    let Some(&mask) = sec.get(pos) else {
        return to;
    };
    let pointer_bytes = mask.count_ones() as usize * W;
    let size = 4 + pointer_bytes.next_multiple_of(4);
    let Some(pointers) = sec.get(pos + 4..pos + 4 + pointer_bytes) else {
        return to;
    };
    for chunk in pointers.chunks_exact(W) {
        let mut p = 0u32;
        for (j, &b) in chunk.iter().enumerate() {
            p |= u32::from(b) << (8 * j);
        }
        child.prefetch(p);
    }
    pos + size
}

/// Walks one part of a node level; picks a build for the CPU it runs on.
fn walk_range<const W: usize, C: ChildLevel>(
    f: &mut Findings,
    view: &LevelView<'_>,
    child: &C,
    attributes: AttributeRule,
    range: Range<'_>,
) -> Result<RangeEnd, Stop> {
    #[cfg(target_arch = "x86_64")]
    if has_popcnt() {
        // SAFETY: the CPU has the POPCNT instruction (checked just above),
        // the only feature `walk_range_popcnt` is compiled to use.
        return unsafe { walk_range_popcnt::<W, C>(f, view, child, attributes, range) };
    }
    walk_range_inline::<W, C>(f, view, child, attributes, range)
}

/// [`walk_range_inline`] compiled with the POPCNT instruction (a record's
/// size and a leaf's count are bit counts).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "popcnt")]
fn walk_range_popcnt<const W: usize, C: ChildLevel>(
    f: &mut Findings,
    view: &LevelView<'_>,
    child: &C,
    attributes: AttributeRule,
    range: Range<'_>,
) -> Result<RangeEnd, Stop> {
    walk_range_inline::<W, C>(f, view, child, attributes, range)
}

/// Walks the records of one part of a node level with pointer width `W`:
/// framing, pointers, attributes; indexes its records for the parent level.
#[inline(always)]
fn walk_range_inline<const W: usize, C: ChildLevel>(
    f: &mut Findings,
    view: &LevelView<'_>,
    child: &C,
    attributes: AttributeRule,
    range: Range<'_>,
) -> Result<RangeEnd, Stop> {
    let Range {
        part,
        from,
        to,
        mut slots,
        slot_base,
        blocks,
        block_base,
    } = range;
    let sec = view.bytes;
    let len = sec.len();
    let level = view.level();
    let base = view.entry.offset;
    let mut head = 0u64;
    // A part starts at a record with a slot of its own (`split_points`).
    let mut previous_slot = usize::MAX;
    let mut pos = from;
    let mut index = 0u64;
    let mut complete = true;
    let mut shared_tail = false;
    // A second framing runs `PREFETCH_RECORDS` records ahead and asks for
    // the cache lines its pointers will read, so that the misses of many
    // records overlap instead of those of the few the core looks ahead to.
    let mut ahead = from;
    for _ in 0..PREFETCH_RECORDS {
        ahead = prefetch_record::<W, C>(sec, ahead, to, child);
    }
    while pos < to {
        ahead = prefetch_record::<W, C>(sec, ahead, to, child);
        let Some(head_bytes) = sec.get(pos..pos + 4) else {
            complete = false;
            f.report(truncated_node(
                base + pos as u64,
                level,
                index,
                len - pos,
                4,
            ))?;
            break;
        };
        let header =
            u32::from_le_bytes([head_bytes[0], head_bytes[1], head_bytes[2], head_bytes[3]]);
        let mask = header & 0xff;
        let pointer_bytes = mask.count_ones() as usize * W;
        let size = 4 + pointer_bytes.next_multiple_of(4);
        let Some(record) = sec.get(pos..pos + size) else {
            complete = false;
            f.report(truncated_node(
                base + pos as u64,
                level,
                index,
                len - pos,
                size,
            ))?;
            break;
        };
        let word = pos / 4;
        let bit = 1u64 << (word & 63);
        match (word >> 6).checked_sub(block_base) {
            Some(b) => blocks[b].starts |= bit,
            None => head |= bit,
        }
        let at = base + pos as u64;
        if mask == 0 {
            f.report(
                FormatError::new(
                    ErrorCode::EmptyChildMask,
                    at,
                    "node has an empty child mask",
                )
                .at_level(level)
                .at_node(index),
            )?;
        }
        let mut count = 0u64;
        for (rank, chunk) in record[4..4 + pointer_bytes].chunks_exact(W).enumerate() {
            let mut p = 0u32;
            for (j, &b) in chunk.iter().enumerate() {
                p |= u32::from(b) << (8 * j);
            }
            match child.visit(p, part) {
                Visit::Count(c) => count = count.saturating_add(c),
                Visit::OutOfRange => {
                    count = UNKNOWN;
                    f.report(bad_pointer::<C>(
                        true,
                        at + 4 + (rank * W) as u64,
                        level,
                        index,
                        p,
                        child.units(),
                    ))?;
                }
                Visit::NotAtNode => {
                    count = UNKNOWN;
                    f.report(bad_pointer::<C>(
                        false,
                        at + 4 + (rank * W) as u64,
                        level,
                        index,
                        p,
                        child.units(),
                    ))?;
                }
            }
        }
        if let Some(i) = record[4 + pointer_bytes..].iter().position(|&b| b != 0) {
            f.report(
                FormatError::new(
                    ErrorCode::NonzeroNodePadding,
                    at + (4 + pointer_bytes + i) as u64,
                    "padding after the node's pointers is not zero",
                )
                .at_level(level)
                .at_node(index),
            )?;
        }
        let stored = header >> layout::CHILD_MASK_BITS;
        match attributes {
            AttributeRule::Zero if stored != 0 => f.report(
                FormatError::new(
                    ErrorCode::NonzeroAttribute,
                    at,
                    format!("attribute kind 0 but the node's attribute bits hold {stored:#x}"),
                )
                .at_level(level)
                .at_node(index),
            )?,
            AttributeRule::VoxelCount if count != UNKNOWN => {
                let expected = if count >= u64::from(COUNT_SATURATED) {
                    COUNT_SATURATED
                } else {
                    count as u32
                };
                if stored != expected {
                    f.report(wrong_count(at, level, index, stored, count))?;
                }
            }
            _ => {}
        }
        let slot = word / 2;
        // A slot shared with the previous record (after a 4-byte record)
        // stays unknown; so does one shared with the next part's first
        // record, the only one past the part's slots.
        shared_tail = !slots.set(
            slot - slot_base,
            if slot != previous_slot {
                count
            } else {
                UNKNOWN
            },
        );
        previous_slot = slot;
        pos += size;
        index += 1;
    }
    Ok(RangeEnd {
        records: index,
        end: pos,
        complete,
        head,
        shared_tail,
    })
}

#[cold]
fn truncated_node(at: u64, level: u8, index: u64, left: usize, needed: usize) -> FormatError {
    FormatError::new(
        ErrorCode::TruncatedNode,
        at,
        format!("node record needs {needed} bytes, only {left} remain in the level"),
    )
    .at_level(level)
    .at_node(index)
}

#[cold]
fn bad_pointer<C: ChildLevel>(
    out_of_range: bool,
    at: u64,
    level: u8,
    index: u64,
    p: u32,
    units: u64,
) -> FormatError {
    let e = if out_of_range {
        FormatError::new(
            ErrorCode::PointerOutOfRange,
            at,
            format!(
                "pointer {p} is past the end of level {} ({units} {}s)",
                level + 1,
                C::UNIT
            ),
        )
    } else {
        FormatError::new(
            ErrorCode::PointerNotAtNode,
            at,
            format!(
                "pointer {p} addresses no record start of level {}",
                level + 1
            ),
        )
    };
    e.at_level(level).at_node(index)
}

#[cold]
fn wrong_count(at: u64, level: u8, index: u64, stored: u32, count: u64) -> FormatError {
    let message = if count >= u64::from(COUNT_SATURATED) {
        format!(
            "node stores voxel count {stored:#x}; its subtree holds {count}, so it must store {COUNT_SATURATED:#x} (saturated)"
        )
    } else {
        format!("node stores voxel count {stored}; its subtree holds {count}")
    };
    FormatError::new(ErrorCode::WrongVoxelCount, at, message)
        .at_level(level)
        .at_node(index)
}

/// Reports the records of `below` (the level of `view`) that no pointer of the
/// level above addresses (E047).
#[inline(always)]
fn check_unreferenced(
    f: &mut Findings,
    below: &Below,
    view: &Option<LevelView<'_>>,
) -> Result<(), Stop> {
    let Some(view) = view else { return Ok(()) };
    let level = view.level();
    let report = |f: &mut Findings, index: u64, byte: u64, what: &str| {
        f.report(
            FormatError::new(
                ErrorCode::UnreferencedNode,
                view.entry.offset + byte,
                format!("{what} {index} of level {level} is referenced by no pointer"),
            )
            .at_level(level)
            .at_node(index),
        )
    };
    match below {
        Below::Unusable => {}
        Below::Leaves(leaves) => {
            for (c, chunk) in leaves.counts.chunks(256).enumerate() {
                if chunk
                    .iter()
                    .fold(LEAF_REFERENCED, |acc, n| acc & n.load(Relaxed))
                    != 0
                {
                    continue;
                }
                for (i, _) in chunk
                    .iter()
                    .enumerate()
                    .filter(|(_, n)| n.load(Relaxed) & LEAF_REFERENCED == 0)
                {
                    let index = (c * 256 + i) as u64;
                    report(f, index, index * 8, "leaf")?;
                }
            }
        }
        Below::Nodes16(NodeLevel { blocks, .. })
        | Below::Nodes32(NodeLevel { blocks, .. })
        | Below::Nodes64(NodeLevel { blocks, .. }) => {
            // Records before the current block, for the record numbers reported.
            let mut rank = 0u64;
            for (b, block) in blocks.iter().enumerate() {
                let mut missing = block.starts & !block.referenced();
                while missing != 0 {
                    let bit = missing.trailing_zeros();
                    missing &= missing - 1;
                    let index = rank + u64::from((block.starts & ((1u64 << bit) - 1)).count_ones());
                    let word = (b * 64) as u64 + u64::from(bit);
                    report(f, index, word * 4, "node")?;
                }
                rank += u64::from(block.starts.count_ones());
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{AttributeKind, Dag, DagBuilder};

    /// SplitMix64.
    fn mix(mut z: u64) -> u64 {
        z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// A valid 1.0 file of depth `depth`: each brick present with
    /// probability 1/`density`, half of the masks from a palette of 64 so
    /// that leaves and nodes are shared (pointers jump back) as in real
    /// scenes.
    fn build(depth: u8, density: u64, seed: u64, attributes: AttributeKind) -> Vec<u8> {
        let mut builder = DagBuilder::new(depth, attributes).expect("depth");
        let bricks = 1u64 << (3 * (u32::from(depth) - 2));
        for brick in 0..bricks {
            let h = mix(brick ^ seed << 40);
            if !h.is_multiple_of(density) {
                continue;
            }
            let mask = if (h >> 20) & 1 == 0 {
                mix((h >> 24) & 63) | 1
            } else {
                mix(h) | 1
            };
            builder.push_brick(brick, mask).expect("bricks in order");
        }
        builder.finish().expect("build").to_bytes()
    }

    /// The node level sections of a valid file: (offset, length, pointer width).
    fn node_levels(bytes: &[u8]) -> Vec<(usize, usize, u8)> {
        let dag = Dag::open(bytes).expect("valid");
        let leaf_level = usize::from(dag.leaf_level());
        dag.sections()[..leaf_level]
            .iter()
            .map(|e| (e.offset as usize, e.length as usize, e.pointer_width))
            .collect()
    }

    fn one_walk() -> Walk {
        Walk {
            parts: 1,
            min_split_bytes: usize::MAX,
            sync_records: SYNC_RECORDS,
        }
    }

    /// Every level split, however small, its parts starting
    /// `sync_records` records after the guesses.
    fn walk_in(parts: usize, sync_records: usize) -> Walk {
        Walk {
            parts,
            min_split_bytes: 0,
            sync_records,
        }
    }

    /// The record starts of a level, framed one by one.
    fn record_starts(sec: &[u8], width: usize) -> Vec<usize> {
        let mut starts = Vec::new();
        let mut pos = 0;
        while pos < sec.len() {
            starts.push(pos);
            pos += 4 + (sec[pos].count_ones() as usize * width).next_multiple_of(4);
        }
        starts
    }

    fn splits(sec: &[u8], width: u8, parts: usize, sync_records: usize) -> Vec<usize> {
        match width {
            1 => split_points::<1>(sec, parts, sync_records),
            2 => split_points::<2>(sec, parts, sync_records),
            3 => split_points::<3>(sec, parts, sync_records),
            _ => split_points::<4>(sec, parts, sync_records),
        }
    }

    #[test]
    fn guessed_split_points_reach_record_starts() {
        let (mut splits_found, mut record_starts_hit, mut unframed_hit) = (0, 0, 0);
        for seed in 0..4 {
            let bytes = build(7, 3, seed, AttributeKind::VoxelCount);
            for (offset, length, width) in node_levels(&bytes) {
                let sec = &bytes[offset..offset + length];
                let starts = record_starts(sec, usize::from(width));
                for parts in 2..=MAX_PARTS {
                    let found = splits(sec, width, parts, SYNC_RECORDS);
                    assert!(found.len() < parts);
                    assert!(found.windows(2).all(|w| w[0] < w[1]));
                    if starts.len() >= 4 * SYNC_RECORDS * parts {
                        assert_eq!(found.len(), parts - 1, "{} records", starts.len());
                    }
                    splits_found += found.len();
                    record_starts_hit += found
                        .iter()
                        .filter(|s| starts.binary_search(s).is_ok())
                        .count();
                    // Without framing from the guess, a split is a record
                    // start only by chance.
                    unframed_hit += splits(sec, width, parts, 0)
                        .iter()
                        .filter(|s| starts.binary_search(s).is_ok())
                        .count();
                }
            }
        }
        assert!(splits_found >= 20, "{splits_found} splits");
        assert!(
            record_starts_hit * 100 >= splits_found * 95,
            "{record_starts_hit} of {splits_found} splits are record starts"
        );
        println!(
            "{record_starts_hit} of {splits_found} splits are record starts, {unframed_hit} unframed"
        );
        assert!(unframed_hit < record_starts_hit, "{unframed_hit} unframed");
    }

    #[test]
    fn walks_in_parts_report_what_one_walk_reports() {
        let mut codes = std::collections::BTreeSet::new();
        let mut invalid = 0;
        for seed in 0..48u64 {
            let attributes = if seed % 4 == 3 {
                AttributeKind::None
            } else {
                AttributeKind::VoxelCount
            };
            let mut bytes = build(7, 2 + seed % 3, seed, attributes);
            let levels = node_levels(&bytes);
            // Corrupt node levels (and, for some seeds, the leaf level
            // after them): random bytes, zeroed runs, a record's mask.
            let first = levels.iter().map(|l| l.0).min().expect("levels");
            let end = bytes.len();
            let mut h = mix(seed ^ 0x5EED);
            for _ in 0..1 + seed % 5 {
                h = mix(h);
                let (offset, length, _) = levels[(h % levels.len() as u64) as usize];
                let at = if seed % 7 == 6 {
                    first + (h >> 8) as usize % (end - first)
                } else if length > 0 {
                    offset + (h >> 8) as usize % length
                } else {
                    continue;
                };
                match (h >> 40) % 3 {
                    0 => bytes[at] = (h >> 48) as u8,
                    1 => {
                        let run = 1 + (h >> 48) as usize % 12;
                        let run_end = (at + run).min(end);
                        bytes[at..run_end].fill(0);
                    }
                    _ => bytes[at] ^= 1 << ((h >> 48) % 8),
                }
            }
            if seed % 6 == 5 {
                // The last record of a level runs past its end (E042).
                let (offset, length, width) = levels[(h % levels.len() as u64) as usize];
                let sec = &bytes[offset..offset + length];
                if let Some(&last) = record_starts(sec, usize::from(width)).last() {
                    bytes[offset + last] = 0xff;
                }
            }
            for max_errors in [100_000, 1, 2, 5, 17] {
                let options = ValidateOptions {
                    max_errors,
                    ..ValidateOptions::default()
                };
                let one = validate_walked(&bytes, &options, one_walk());
                if max_errors == 100_000 {
                    invalid += usize::from(!one.is_valid());
                    codes.extend(one.errors.iter().map(|e| e.code));
                }
                // Parts from framed guesses (mostly confirmed), from the
                // guesses themselves (mostly not: walked again in one part)
                // and from one record after them.
                for parts in 2..=MAX_PARTS {
                    for sync_records in [SYNC_RECORDS, 0, 1] {
                        let split = validate_walked(&bytes, &options, walk_in(parts, sync_records));
                        assert_eq!(
                            split, one,
                            "seed {seed}, {parts} parts, sync {sync_records}, at most {max_errors} findings"
                        );
                    }
                }
            }
        }
        // The corruptions reach the rules the parts split.
        assert!(invalid >= 40, "only {invalid} files invalid");
        for code in [
            ErrorCode::PointerOutOfRange,
            ErrorCode::PointerNotAtNode,
            ErrorCode::UnreferencedNode,
            ErrorCode::WrongVoxelCount,
            ErrorCode::TruncatedNode,
            ErrorCode::NonzeroNodePadding,
        ] {
            assert!(codes.contains(&code), "no {code:?} in {codes:?}");
        }
    }

    #[test]
    fn valid_files_stay_valid_in_parts() {
        for seed in 0..4 {
            let bytes = build(8, 4, seed, AttributeKind::VoxelCount);
            let options = ValidateOptions::default();
            for walk in [one_walk(), walk_in(2, SYNC_RECORDS), walk_in(3, 0)] {
                let report = validate_walked(&bytes, &options, walk);
                assert!(report.is_valid(), "{walk:?}: {:?}", report.errors);
            }
        }
    }
}
