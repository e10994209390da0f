//! Full validation of the levels of a format 2.0 file (spec §23.10): the
//! part of [`crate::validate`] after the header, the section table and the
//! checksums, which are shared with 1.0.
//!
//! # What is checked, in order
//!
//! 1. The root level's record count (E040).
//! 2. The leaf level: empty masks (E048).
//! 3. Each node level, leaves first: every record decodes within its level
//!    (E071; the walk of the level stops there), has children (E041), zero
//!    bits after its last reference (E072), references in the smallest
//!    width that holds them (E074, at the record) and targets that are
//!    record starts or leaves (E073, also for each sequential run); the
//!    records found against the item count (E079); the level's widths
//!    against the minimising triple of its references (E074, at the entry);
//!    then, for the level below, every node named as §23.3 says (E078);
//!    and the attributes (E060, E061) from the exact subtree counts.
//! 4. The header's voxel count (E062).
//! 5. Only when nothing above was found: the canonical form (E075 – E077),
//!    on the file's own records ([`crate::canonical2`]): the intrinsic keys
//!    and ranks of every level bottom-up, the canonical order of every level
//!    top-down, each level compared with it item by item; the deepest level
//!    that differs gives E075 (two items of one class), E076 (an item stored
//!    in another reflection than the canonical one, or a reference without
//!    its least reflection) or E077 (another order), at its first item that
//!    differs. Time O(n log n) in the items; memory, besides the walk's
//!    arrays, 8 bytes an item plus one level's packed keys (40 bytes an
//!    item).
//!
//! The walk decodes each record once and keeps it in flat arrays ([`Flat`]:
//! about 28 bytes a record and 5 a child), which step 5 reads instead of
//! the records.
//!
//! A level that cannot be interpreted (E020, E024, E025, E070) is not
//! walked, and neither are the rules that need it (E073 and E078 into it,
//! the counts above it, E062, step 5).

use crate::error::{ErrorCode, FormatError};
use crate::layout::{AttributeKind, COUNT_SATURATED};
use crate::prefetch::prefetch;
use crate::reader::{self, SectionEntry};
use crate::v2::{self, Child, LevelView, Node2, References};
use crate::validate::{Findings, Stop};

/// The record starts of a 2.0 node level as a bitmap with ranks, so that
/// the item a byte offset names is found in O(1): a binary search over the
/// starts misses the cache at most of its steps in a large level, which made
/// it the walk's largest cost.
#[derive(Default)]
pub(crate) struct StartIndex {
    /// Per 64 bytes of the level: which bytes start a record, and the
    /// records that start before them.
    blocks: Vec<(u64, u64)>,
}

impl StartIndex {
    /// The index of `starts` (increasing) in a level of `len` bytes.
    pub(crate) fn new(starts: &[u64], len: u64) -> StartIndex {
        let mut blocks = vec![(0u64, 0u64); len.div_ceil(64) as usize];
        for &at in starts {
            blocks[(at / 64) as usize].0 |= 1 << (at % 64);
        }
        let mut before = 0u64;
        for b in &mut blocks {
            b.1 = before;
            before += u64::from(b.0.count_ones());
        }
        StartIndex { blocks }
    }

    /// The record that starts at byte `offset`, if one does.
    #[inline]
    pub(crate) fn item(&self, offset: u64) -> Option<usize> {
        let (bits, before) = *self.blocks.get(usize::try_from(offset / 64).ok()?)?;
        let bit = offset % 64;
        if bits >> bit & 1 == 0 {
            return None;
        }
        let below = bits & ((1u64 << bit) - 1);
        usize::try_from(before + u64::from(below.count_ones())).ok()
    }
}

/// A level as the walk decoded it, kept for the canonical check (step 5)
/// so that it reads every record from flat arrays instead of decoding it
/// again (it reads each record several times, some at random).
#[derive(Default)]
pub(crate) struct Flat {
    /// Byte offset (interior) of each record, in order; for the leaf level
    /// empty (items are indices).
    pub(crate) starts: Vec<u64>,
    /// The header word of each record (interior).
    pub(crate) headers: Vec<u32>,
    /// Record `i`'s children are `kids[first[i]..first[i + 1]]`, in physical
    /// slot order (interior; `first` has one entry more than the records).
    pub(crate) first: Vec<u64>,
    /// Each child as an item of the level below; [`NO_ITEM`] where its
    /// reference names none (E073) or the level below was not walked.
    pub(crate) kids: Vec<u32>,
    /// Each child's reflection (bits 0 – 2) and [`SHARED`] when a
    /// reference names it (a sequential child has reflection 0).
    pub(crate) kid_bits: Vec<u8>,
    /// Per item: the references and sequential runs of the level above that
    /// name it (empty for the root level): in a file without findings, the
    /// times it is named.
    pub(crate) named: Vec<u32>,
}

/// [`Flat::kids`] of a child whose reference names no item.
pub(crate) const NO_ITEM: u32 = u32::MAX;

/// [`Flat::kid_bits`]: the child is shared.
pub(crate) const SHARED: u8 = 8;

/// A level as the walk found it.
struct Walked {
    /// The records as decoded.
    flat: Flat,
    /// `flat.starts` indexed by offset (interior).
    index: StartIndex,
    /// Per item: its subtree voxel count, and how the level above names it.
    items: Vec<Tally>,
    /// Whether every item could be read.
    complete: bool,
}

/// What the walk knows of one item: its subtree count, which its parents
/// read, and the references and runs naming it, which they write; in one
/// 16-byte entry, so that following a reference to the item costs one
/// cache miss instead of three (the walk's largest cost in a large level).
#[derive(Clone, Copy)]
struct Tally {
    /// Subtree voxel count; [`UNKNOWN_COUNT`] when unknown. (A subtree of
    /// depth at most 21 holds at most 2^63 voxels, so no count reaches it.)
    count: u64,
    /// Shared references naming the item (saturating).
    shared: u32,
    /// Sequential runs through the item (saturating).
    runs: u32,
}

/// [`Tally::count`] of an item whose subtree count is unknown.
const UNKNOWN_COUNT: u64 = u64::MAX;

impl Tally {
    /// An item of subtree count `count` (`None`: unknown), not yet named.
    fn new(count: Option<u64>) -> Tally {
        Tally {
            count: count.unwrap_or(UNKNOWN_COUNT),
            shared: 0,
            runs: 0,
        }
    }

    /// The subtree count, if known.
    fn count(&self) -> Option<u64> {
        (self.count != UNKNOWN_COUNT).then_some(self.count)
    }
}

impl Walked {
    /// The item a reference's target names: a record start, or a leaf index.
    fn item(&self, is_leaf: bool, target: u64) -> Option<usize> {
        if is_leaf {
            usize::try_from(target)
                .ok()
                .filter(|&i| i < self.items.len())
        } else {
            self.index.item(target)
        }
    }
}

fn bits_of(v: u64) -> u32 {
    (64 - v.leading_zeros()).max(1)
}

/// Checks the levels of a 2.0 file; `levels[l]` is `None` when level `l`
/// cannot be interpreted (reported already).
pub(crate) fn check_levels(
    layout: &reader::Layout,
    bytes: &[u8],
    f: &mut Findings,
    threads: bool,
) -> Result<(), Stop> {
    let header = &layout.header;
    let sections = &layout.sections;
    let leaf_level = usize::from(header.depth) - 2;
    let entries: Vec<&SectionEntry> = sections[..=leaf_level].iter().collect();
    let views: Vec<Option<LevelView<'_>>> = entries
        .iter()
        .enumerate()
        .map(|(i, e)| {
            if !layout.usable[i] {
                return None;
            }
            let start = usize::try_from(e.offset).ok()?;
            let end = start.checked_add(usize::try_from(e.length).ok()?)?;
            Some(LevelView {
                bytes: bytes.get(start..end)?,
                widths: if i == leaf_level { [0; 3] } else { e.widths },
                item_count: e.item_count,
                is_leaf: i == leaf_level,
            })
        })
        .collect();

    let root = entries[0];
    let all_empty = entries.iter().all(|e| e.item_count == 0 && e.length == 0);
    if root.item_count > 1 || (root.item_count == 0 && !all_empty) {
        f.report(
            FormatError::new(
                ErrorCode::BadRootLevel,
                root.entry_offset() + 24,
                format!(
                    "the root level holds {} records; it must hold 1, or 0 with every level empty",
                    root.item_count
                ),
            )
            .at_level(0),
        )?;
    }
    let attributes = if !layout.attribute_kind_known {
        None
    } else {
        Some(header.attribute_kind)
    };

    // The leaf level.
    let mut below: Option<Walked> = views[leaf_level].as_ref().map(|view| {
        let items = view
            .bytes
            .chunks_exact(8)
            .map(|m| {
                Tally::new(Some(u64::from(
                    u64::from_le_bytes(m.try_into().expect("8")).count_ones(),
                )))
            })
            .collect();
        Walked {
            flat: Flat::default(),
            index: StartIndex::default(),
            items,
            complete: true,
        }
    });
    if let Some(view) = &views[leaf_level] {
        for (i, m) in view.bytes.chunks_exact(8).enumerate() {
            if m == [0; 8] {
                f.report(
                    FormatError::new(
                        ErrorCode::EmptyLeafMask,
                        entries[leaf_level].offset + i as u64 * 8,
                        "leaf mask is zero (a leaf holds at least one voxel)",
                    )
                    .at_level(leaf_level as u8)
                    .at_node(i as u64),
                )?;
            }
        }
    }

    let mut root_count = None;
    // Every level as decoded, for the canonical form (step 5).
    let mut flats: Vec<Flat> = (0..=leaf_level).map(|_| Flat::default()).collect();
    for l in (0..leaf_level).rev() {
        let Some(view) = &views[l] else {
            if let Some(done) = below.take() {
                flats[l + 1] = done.flat;
            }
            continue;
        };
        let (walked, named_below) = walk_level(
            f,
            (entries[l], entries[l + 1]),
            view,
            l,
            below.as_mut(),
            leaf_level,
            attributes,
        )?;
        if l == 0 && walked.complete && walked.items.len() as u64 == view.item_count {
            root_count = match walked.items.first() {
                None => Some(0),
                Some(c) => c.count(),
            };
        }
        if let Some(mut done) = below.replace(walked) {
            done.flat.named = named_below;
            flats[l + 1] = done.flat;
        }
    }
    if leaf_level > 0
        && let Some(root) = below.take()
    {
        flats[0] = root.flat;
    }
    if leaf_level == 0 {
        root_count = below
            .as_ref()
            .filter(|w| w.items.len() as u64 == entries[0].item_count)
            .map(|w| w.items.first().and_then(Tally::count).unwrap_or(0));
    }
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
    if f.errors.is_empty()
        && root_count.is_some()
        && views.iter().all(Option::is_some)
        && leaf_level > 0
    {
        let views: Vec<LevelView<'_>> = views.iter().flatten().copied().collect();
        let check = |f: &mut Findings| crate::canonical2::check(f, &entries, &views, &flats);
        if threads {
            check(f)?;
        } else {
            // The same work on one thread.
            match rayon::ThreadPoolBuilder::new().num_threads(1).build() {
                Ok(pool) => pool.install(|| check(f))?,
                Err(_) => check(f)?,
            }
        }
    }
    Ok(())
}

/// How many records ahead of the walk [`prefetch_children`] asks for
/// tallies (and twice as many for record starts).
const PREFETCH_RECORDS: usize = 8;

/// What [`prefetch_children`] asks for.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Stage {
    /// The record-start blocks of the children's targets.
    Starts,
    /// Their tallies (the blocks were asked for earlier).
    Tallies,
}

/// Records decoded ahead of the walk: offset and decoding.
type Ahead = std::collections::VecDeque<(u64, Result<(Node2, References), FormatError>)>;

/// Decodes the record at `*ahead` into `ring` and asks for the record-start
/// blocks of its children's targets; moves `*ahead` to the next record (to
/// the level's end after a record that does not decode, which the walk
/// reports when it reaches it).
fn decode_ahead(
    view: &LevelView<'_>,
    ring: &mut Ahead,
    ahead: &mut u64,
    below: Option<&Walked>,
    child_is_leaf: bool,
) {
    let len = view.bytes.len() as u64;
    if *ahead >= len {
        return;
    }
    let decoded = v2::decode_node_references(view.bytes, *ahead, view.widths);
    let at = *ahead;
    match &decoded {
        Ok((node, _)) => {
            if let Some(b) = below {
                prefetch_children(node, b, child_is_leaf, Stage::Starts);
            }
            *ahead += u64::from(node.size);
        }
        Err(_) => *ahead = len,
    }
    ring.push_back((at, decoded));
}

/// Asks for the cache lines the walk of `node` will read in the level
/// below (a hint: no effect on results).
fn prefetch_children(node: &Node2, below: &Walked, child_is_leaf: bool, stage: Stage) {
    for child in node.children.iter().flatten() {
        let target = match *child {
            Child::Shared { target, .. } => target,
            Child::Sequential { index: 0, base } => base,
            Child::Sequential { .. } => continue,
        };
        if child_is_leaf || stage == Stage::Tallies {
            if let Some(tally) = below
                .item(child_is_leaf, target)
                .and_then(|i| below.items.get(i))
            {
                prefetch(tally);
            }
        } else if let Some(block) = usize::try_from(target / 64)
            .ok()
            .and_then(|b| below.index.blocks.get(b))
        {
            prefetch(block);
        }
    }
}

/// Walks node level `l` (E071, E041, E072, E073, E074, E079, E060, E061)
/// and then checks how the level below is named (E078). Returns the level
/// as walked and, per item of the level below, the references and runs
/// naming it.
fn walk_level(
    f: &mut Findings,
    (entry, below_entry): (&SectionEntry, &SectionEntry),
    view: &LevelView<'_>,
    l: usize,
    mut below: Option<&mut Walked>,
    leaf_level: usize,
    attributes: Option<AttributeKind>,
) -> Result<(Walked, Vec<u32>), Stop> {
    let child_is_leaf = l + 1 == leaf_level;
    let level = l as u8;
    let base_offset = entry.offset;
    let mut flat = Flat::default();
    flat.first.push(0);
    let mut items = Vec::new();
    let mut complete = true;
    let mut hist = [0u64; 65];
    let child_items = below.as_ref().map_or(0, |b| b.items.len());
    let len = view.bytes.len() as u64;
    // The records are decoded 2K records ahead of the walk, which asks then
    // for the record-start blocks of their children's targets and, K
    // records ahead (when those have arrived), for their tallies, so that
    // the misses of many records overlap.
    let mut ring: Ahead = std::collections::VecDeque::with_capacity(2 * PREFETCH_RECORDS + 1);
    let mut ahead = 0u64;
    for _ in 0..2 * PREFETCH_RECORDS {
        decode_ahead(view, &mut ring, &mut ahead, below.as_deref(), child_is_leaf);
    }
    while let Some((at, decoded)) = ring.pop_front() {
        decode_ahead(view, &mut ring, &mut ahead, below.as_deref(), child_is_leaf);
        if let (Some(b), Some((_, Ok((node, _))))) =
            (below.as_deref(), ring.get(PREFETCH_RECORDS - 1))
        {
            prefetch_children(node, b, child_is_leaf, Stage::Tallies);
        }
        let index = flat.starts.len() as u64;
        let record_at = base_offset + at;
        let report_at = |code, message: String| {
            FormatError::new(code, record_at, message)
                .at_level(level)
                .at_node(index)
        };
        let (node, refs) = match decoded {
            Ok(decoded) => decoded,
            Err(e) => {
                f.report(report_at(ErrorCode::TruncatedRecord2, e.message))?;
                complete = false;
                break;
            }
        };
        let bits = refs.bits;
        flat.starts.push(at);
        flat.headers.push(node.header);
        if node.child_mask() == 0 {
            f.report(report_at(
                ErrorCode::EmptyChildMask,
                "record has no children".to_string(),
            ))?;
        }
        // E072: the bits after B in the record's last byte.
        let used = bits % 8;
        if used != 0 {
            let last = view.bytes[(at + u64::from(node.size) - 1) as usize];
            if last >> used != 0 {
                f.report(
                    FormatError::new(
                        ErrorCode::NonzeroBitPadding,
                        record_at + u64::from(node.size) - 1,
                        format!(
                            "the {} bits after the record's references are not zero",
                            8 - used
                        ),
                    )
                    .at_level(level)
                    .at_node(index),
                )?;
            }
        }
        // E074 per reference.
        for &(code, value) in refs.as_slice() {
            hist[bits_of(value) as usize] += 1;
            let least = view
                .widths
                .iter()
                .position(|&w| u32::from(w) >= bits_of(value))
                .map_or(code, |i| i as u8 + 1);
            if least != code {
                f.report(report_at(
                    ErrorCode::WidthNotMinimal,
                    format!(
                        "a reference of {} bits uses code {code} (width {}) where code {least} (width {}) holds it",
                        bits_of(value),
                        view.widths[usize::from(code) - 1],
                        view.widths[usize::from(least) - 1]
                    ),
                ))?;
                break;
            }
        }
        // E073 and the naming of the level below; the subtree count.
        let mut sum = Some(0u64);
        if let Some(b) = below.as_deref_mut() {
            let mut bad = None;
            let mut seq_index = 0usize;
            let mut seq_at = None::<usize>;
            for child in node.children.iter().flatten() {
                let item = match *child {
                    Child::Shared { target, reflection } => {
                        flat.kid_bits.push(reflection | SHARED);
                        let item = b.item(child_is_leaf, target);
                        if let Some(i) = item {
                            b.items[i].shared = b.items[i].shared.saturating_add(1);
                        } else {
                            bad = Some(format!(
                                "a reference names {target}, not a record start or leaf of level {}",
                                l + 1
                            ));
                        }
                        item
                    }
                    Child::Sequential { base, .. } => {
                        flat.kid_bits.push(0);
                        let item = match seq_at {
                            None => b.item(child_is_leaf, base),
                            Some(prev) => Some(prev + 1).filter(|&i| i < b.items.len()),
                        };
                        seq_index += 1;
                        match item {
                            Some(i) => {
                                b.items[i].runs = b.items[i].runs.saturating_add(1);
                                seq_at = Some(i);
                            }
                            None => {
                                bad = Some(format!(
                                    "sequential child {} (run from {base}) is not in level {}",
                                    seq_index - 1,
                                    l + 1
                                ));
                                seq_at = Some(usize::MAX - 1);
                            }
                        }
                        item
                    }
                };
                flat.kids
                    .push(item.and_then(|i| u32::try_from(i).ok()).unwrap_or(NO_ITEM));
                sum = match (sum, item.and_then(|i| b.items[i].count())) {
                    (Some(s), Some(c)) => Some(s.saturating_add(c)),
                    _ => None,
                };
            }
            if let Some(message) = bad {
                f.report(report_at(ErrorCode::ReferenceOutOfRange2, message))?;
            }
        } else {
            sum = None;
        }
        let attribute = node.attribute();
        match attributes {
            Some(AttributeKind::None) if attribute != 0 => {
                f.report(report_at(
                    ErrorCode::NonzeroAttribute,
                    format!("attribute kind 0 but the record's attribute is {attribute}"),
                ))?;
            }
            Some(AttributeKind::VoxelCount) => {
                if let Some(s) = sum {
                    let expected = s.min(u64::from(COUNT_SATURATED)) as u32;
                    if attribute != expected {
                        f.report(report_at(
                            ErrorCode::WrongVoxelCount,
                            format!("the record stores a voxel count of {attribute}, its subtree holds {s}"),
                        ))?;
                    }
                }
            }
            _ => {}
        }
        items.push(Tally::new(sum));
        flat.first.push(flat.kids.len() as u64);
    }
    if complete && flat.starts.len() as u64 != entry.item_count {
        f.report(
            FormatError::new(
                ErrorCode::ItemCountMismatch2,
                entry.entry_offset() + 24,
                format!(
                    "level {l} declares {} records, its bytes hold {}",
                    entry.item_count,
                    flat.starts.len()
                ),
            )
            .at_level(level),
        )?;
    }
    if complete
        && let Some(minimal) = v2::best_widths(&hist)
        && minimal != view.widths
    {
        f.report(
            FormatError::new(
                ErrorCode::WidthNotMinimal,
                entry.entry_offset() + 5,
                format!(
                    "level {l} has widths {:?}; its references need {minimal:?}",
                    view.widths
                ),
            )
            .at_level(level),
        )?;
    }
    // E078 for the level below, once its every parent has been read.
    if complete && let Some(b) = below.as_deref() {
        for i in 0..child_items {
            let (s, r) = (b.items[i].shared, b.items[i].runs);
            let ok = (s == 0 && r == 1) || (s >= 2 && r == 0);
            if !ok {
                let (offset, what) = if child_is_leaf {
                    (i as u64 * 8, "leaf")
                } else {
                    (b.flat.starts[i], "record")
                };
                f.report(
                    FormatError::new(
                        ErrorCode::BadSharing,
                        below_entry.offset + offset,
                        format!(
                            "{what} {i} of level {} is named by {s} references and {r} sequential runs (a node is named by one run, or by at least two references)",
                            l + 1
                        ),
                    )
                    .at_level(level + 1)
                    .at_node(i as u64),
                )?;
            }
        }
    }
    let named = below.map_or_else(Vec::new, |b| {
        b.items
            .iter()
            .map(|t| t.shared.saturating_add(t.runs))
            .collect()
    });
    Ok((
        Walked {
            index: StartIndex::new(&flat.starts, len),
            flat,
            items,
            complete,
        },
        named,
    ))
}
