//! Placing a DAG's words in GPU storage buffers.
//!
//! The shader sees one address space of 32-bit words: the level sections one
//! after the other (root first, the leaf level last), each from a word
//! boundary, then the table of saturated voxel counts. A format 2.0 level
//! (spec §23) is uploaded as its bytes, like a 1.0 level: its records are
//! unaligned, and the shader reads them with aligned word loads at byte
//! offsets ([`UploadLevel`] says how each level is addressed); after each
//! 2.0 level named by sequential runs comes its record-start bit vector
//! ([`record_starts`]). A 2.0 DAG's node levels may instead be uploaded
//! expanded (`dagfmt::expand`, spec §23.12: [`ExpandedWords`]), laid out and
//! addressed as 1.0 levels of 4-byte pointers, its leaf level in place. The
//! space is cut into pages of a power-of-two
//! number of words, one storage binding each, so that a DAG larger than the
//! largest storage binding still fits (`load_word` in the generated preamble
//! picks the page). Records may straddle pages: every word is looked up on its
//! own.
//!
//! The bytes go from the caller's (usually memory-mapped) file straight to the
//! GPU in bounded chunks: nothing proportional to the file is copied in RAM.

use super::GpuError;
use super::layout::MAX_STORED_LEVELS;
use dagfmt::layout::{AttributeKind, COUNT_SATURATED};
use dagfmt::v2::LevelView;
use dagfmt::{Dag, FormatError};
use rustc_hash::FxHashMap;

/// One level section as the shader addresses it (an entry of
/// `GpuParams::levels` besides its first word).
#[derive(Clone, Copy, Debug)]
pub(crate) struct UploadLevel<'a> {
    /// The section's bytes.
    pub bytes: &'a [u8],
    /// The widths word: 1.0 pointer bytes; 2.0 `w1 | w2 << 8 | w3 << 16`.
    pub widths: u32,
    /// Bound of a child address into this level: 1.0 words, 2.0 bytes, leaves.
    pub units: u64,
    /// 2.0 levels named by sequential runs: the record-start bit vector
    /// ([`record_starts`]), placed after the level's bytes.
    pub starts: Option<&'a [u32]>,
}

impl<'a> UploadLevel<'a> {
    /// The levels of a 1.0 DAG.
    pub fn v1(dag: &Dag<'a>) -> Vec<Self> {
        dag.levels()
            .iter()
            .map(|section| UploadLevel {
                bytes: section.bytes,
                widths: u32::from(section.pointer_width),
                units: if section.is_leaf {
                    section.bytes.len() as u64 / 8
                } else {
                    section.bytes.len() as u64 / 4
                },
                starts: None,
            })
            .collect()
    }

    /// The levels of a 2.0 DAG expanded (spec §23.12): the node levels'
    /// words (`words`, addressed in words like 1.0 levels of 4-byte
    /// pointers), then the leaf level of `levels` as stored.
    pub fn expanded(words: &'a ExpandedWords<'_>, levels: &[LevelView<'a>]) -> Vec<Self> {
        let mut out: Vec<Self> = words
            .levels
            .iter()
            .map(|bytes| UploadLevel {
                bytes: bytes.as_ref(),
                widths: 4,
                units: bytes.len() as u64 / 4,
                starts: None,
            })
            .collect();
        if let Some(leaf) = levels.last().filter(|l| l.is_leaf) {
            out.push(UploadLevel {
                bytes: leaf.bytes,
                widths: 0,
                units: leaf.bytes.len() as u64 / 8,
                starts: None,
            });
        }
        out
    }

    /// The levels of a 2.0 DAG (spec §23.2: records at byte offsets), with
    /// the record-start bit vectors `starts` (one per level, empty for none).
    pub fn v2(levels: &[LevelView<'a>], starts: &'a [Vec<u32>]) -> Vec<Self> {
        levels
            .iter()
            .zip(starts)
            .map(|(view, starts)| UploadLevel {
                bytes: view.bytes,
                widths: if view.is_leaf {
                    0
                } else {
                    u32::from(view.widths[0])
                        | u32::from(view.widths[1]) << 8
                        | u32::from(view.widths[2]) << 16
                },
                units: if view.is_leaf {
                    view.bytes.len() as u64 / 8
                } else {
                    view.bytes.len() as u64
                },
                starts: (!starts.is_empty()).then_some(starts.as_slice()),
            })
            .collect()
    }
}

/// The expanded node levels of a 2.0 DAG as the bytes the device holds:
/// each level's words, little-endian (borrowed from the expansion on a
/// little-endian host, so the largest levels are not copied).
pub(crate) struct ExpandedWords<'a> {
    levels: Vec<std::borrow::Cow<'a, [u8]>>,
}

impl<'a> ExpandedWords<'a> {
    /// The bytes of `expanded` (`dagfmt::expand::expand_levels`'s levels).
    pub fn new(expanded: &'a [dagfmt::expand::ExpandedLevel]) -> Self {
        ExpandedWords {
            levels: expanded
                .iter()
                .map(|level| {
                    if cfg!(target_endian = "little") {
                        std::borrow::Cow::Borrowed(bytemuck::cast_slice(&level.words))
                    } else {
                        level.words.iter().flat_map(|w| w.to_le_bytes()).collect()
                    }
                })
                .collect(),
        }
    }
}

/// The record-start bit vectors of the 2.0 node levels 1 ..= D − 3 (the
/// interior levels whose records parents name by sequential runs, spec
/// §23.3): bit b set when a record starts at byte b. With it the shader finds
/// the j-th sequential child of a run as the j-th set bit after the run's
/// base (one or two loads), instead of reading the headers and codes of the
/// j records before it; it is an index built at upload, like the table of
/// saturated counts, an eighth of the level's size. Empty for the other
/// levels, and where a record does not decode (a malformed level: the bits
/// found so far are kept).
pub(crate) fn record_starts(levels: &[LevelView<'_>]) -> Vec<Vec<u32>> {
    levels
        .iter()
        .enumerate()
        .map(|(l, view)| {
            if l == 0 || view.is_leaf || view.bytes.is_empty() {
                return Vec::new();
            }
            let Ok(coding) = dagfmt::v2::Coding::new(view.widths) else {
                return Vec::new();
            };
            let len = view.bytes.len() as u64;
            let mut bits = vec![0u32; len.div_ceil(32) as usize];
            let mut at = 0u64;
            while at < len {
                bits[(at / 32) as usize] |= 1 << (at % 32);
                match coding.record_size(view.bytes, at) {
                    Some(size) => at += size,
                    None => break,
                }
            }
            bits
        })
        .collect()
}

/// Bytes handed to one `Queue::write_buffer` call.
const CHUNK_BYTES: usize = 4 << 20;
/// Bytes written between two waits for the queue (bounds wgpu's staging memory).
const FLUSH_BYTES: usize = 64 << 20;

/// Where everything lies in the word address space.
#[derive(Clone, Debug)]
pub(crate) struct Placement {
    /// Per stored level: first word, widths, units, flags (see [`UploadLevel`]).
    pub levels: [[u32; 4]; MAX_STORED_LEVELS],
    /// First word of the saturated-count table.
    pub sat_base: u32,
    /// `(word address, count low, count high)`, sorted by address.
    pub saturated: Vec<[u32; 3]>,
    /// Words in all.
    pub total_words: u64,
    /// Words per page (a power of two) and the number of pages.
    pub page_words: u64,
    pub pages: u32,
}

impl Placement {
    /// Lays `dag_levels` out for pages of at most `max_page_bytes` bytes and
    /// at most `max_pages` pages.
    pub fn new(
        dag_levels: &[UploadLevel<'_>],
        saturated: Vec<(u8, u32, u64)>,
        max_page_bytes: u64,
        max_pages: u32,
    ) -> Result<Self, GpuError> {
        let mut levels = [[0u32; 4]; MAX_STORED_LEVELS];
        let mut next = 0u64;
        for (slot, section) in levels.iter_mut().zip(dag_levels) {
            let words = (section.bytes.len() as u64).div_ceil(4);
            let starts_at = next + words;
            *slot = [
                u32::try_from(next).map_err(|_| too_large(next))?,
                section.widths,
                u32::try_from(section.units).unwrap_or(u32::MAX),
                match section.starts {
                    Some(_) => u32::try_from(starts_at).map_err(|_| too_large(starts_at))?,
                    None => 0,
                },
            ];
            next = starts_at + section.starts.map_or(0, |s| s.len() as u64);
        }
        let sat_base = next;
        let mut table: Vec<[u32; 3]> = saturated
            .into_iter()
            .map(|(level, word, count)| {
                let address = u64::from(levels[usize::from(level)][0]) + u64::from(word);
                [address as u32, count as u32, (count >> 32) as u32]
            })
            .collect();
        table.sort_unstable();
        let total_words = sat_base + 3 * table.len() as u64;
        if total_words >= 1 << 32 {
            return Err(too_large(total_words));
        }
        let cap_words = (max_page_bytes / 4).max(4);
        let (page_words, pages) = if total_words <= cap_words {
            (total_words.max(4), 1)
        } else {
            let page_words = 1u64 << (63 - cap_words.leading_zeros());
            (page_words, total_words.div_ceil(page_words))
        };
        if pages > u64::from(max_pages) {
            return Err(GpuError::TooLarge(format!(
                "the DAG needs {} bytes in {pages} storage bindings of {} bytes; the device allows {max_pages}",
                total_words * 4,
                page_words * 4
            )));
        }
        Ok(Placement {
            levels,
            sat_base: sat_base as u32,
            saturated: table,
            total_words,
            page_words,
            pages: pages as u32,
        })
    }

    /// log2 of the words per page (meaningful with more than one page).
    pub fn page_shift(&self) -> u32 {
        self.page_words.trailing_zeros()
    }

    /// Size in bytes of page `page`'s buffer.
    pub fn page_bytes(&self, page: u32) -> u64 {
        let start = u64::from(page) * self.page_words;
        let words = (self.total_words.max(4) - start.min(self.total_words))
            .min(self.page_words)
            .max(4);
        words * 4
    }
}

fn too_large(words: u64) -> GpuError {
    GpuError::TooLarge(format!(
        "the DAG's {} bytes exceed the shader's 32-bit word addresses",
        words * 4
    ))
}

/// Voxel counts of the nodes whose stored count is saturated, as
/// `(level, word, count)`, reached from the root as the CPU tracer reaches
/// them (in a valid file every ancestor of a saturated node is saturated).
pub(crate) fn saturated_counts(dag: &Dag<'_>) -> Result<Vec<(u8, u32, u64)>, GpuError> {
    if dag.header().attribute_kind != AttributeKind::VoxelCount
        || dag.is_empty()
        || dag.leaf_level() == 0
    {
        return Ok(Vec::new());
    }
    let mut memo = FxHashMap::default();
    count(dag, 0, 0, &mut memo).map_err(GpuError::Malformed)?;
    let mut out: Vec<(u8, u32, u64)> = memo.into_iter().map(|((l, w), c)| (l, w, c)).collect();
    out.sort_unstable();
    Ok(out)
}

fn count(
    dag: &Dag<'_>,
    level: u8,
    word: u32,
    memo: &mut FxHashMap<(u8, u32), u64>,
) -> Result<u64, FormatError> {
    if level == dag.leaf_level() {
        return Ok(u64::from(dag.leaf(word)?.count()));
    }
    let node = dag.node(level, word)?;
    if node.attribute() != COUNT_SATURATED {
        return Ok(u64::from(node.attribute()));
    }
    if let Some(&n) = memo.get(&(level, word)) {
        return Ok(n);
    }
    let mut total = 0u64;
    for rank in 0..node.child_count() {
        total = total.saturating_add(count(dag, level + 1, node.pointer_at(rank), memo)?);
    }
    memo.insert((level, word), total);
    Ok(total)
}

/// Voxel counts of the records of a 2.0 DAG whose stored count is
/// saturated, as `(level, word of the record's first byte, count)`, reached
/// from the root (reflections do not change a count, spec §23.5). A record
/// is at least 5 bytes long, so no two start in one word.
pub(crate) fn saturated_counts_v2(
    levels: &[LevelView<'_>],
    attribute_kind: AttributeKind,
) -> Result<Vec<(u8, u32, u64)>, GpuError> {
    if attribute_kind != AttributeKind::VoxelCount || levels.len() < 2 || levels[0].item_count == 0
    {
        return Ok(Vec::new());
    }
    let mut memo = FxHashMap::default();
    count_v2(levels, 0, 0, &mut memo).map_err(GpuError::Malformed)?;
    let mut out: Vec<(u8, u32, u64)> = memo
        .into_iter()
        .map(|((l, offset), c)| (l, (offset >> 2) as u32, c))
        .collect();
    out.sort_unstable();
    Ok(out)
}

fn count_v2(
    levels: &[LevelView<'_>],
    level: u8,
    offset: u64,
    memo: &mut FxHashMap<(u8, u64), u64>,
) -> Result<u64, FormatError> {
    let l = usize::from(level);
    let view = &levels[l];
    if view.is_leaf {
        let at = usize::try_from(offset.saturating_mul(8)).unwrap_or(usize::MAX);
        let bytes = view
            .bytes
            .get(at..at.saturating_add(8))
            .ok_or_else(|| out_of_range(offset))?;
        let bits = u64::from_le_bytes(bytes.try_into().expect("8 bytes"));
        return Ok(u64::from(bits.count_ones()));
    }
    let node = dagfmt::v2::decode_node(view.bytes, offset, view.widths)?;
    if node.attribute() != COUNT_SATURATED {
        return Ok(u64::from(node.attribute()));
    }
    if let Some(&n) = memo.get(&(level, offset)) {
        return Ok(n);
    }
    let below = levels
        .get(l + 1)
        .filter(|v| !v.is_leaf)
        .map(|v| (v.bytes, v.widths));
    let mut total = 0u64;
    for child in node.children.iter().flatten() {
        let (target, _) = dagfmt::v2::child_address(*child, below)?;
        total = total.saturating_add(count_v2(levels, level + 1, target, memo)?);
    }
    memo.insert((level, offset), total);
    Ok(total)
}

/// Voxel counts of the records of an expanded 2.0 DAG (spec §23.12) whose
/// stored count is saturated, as `(level, word index of the record, count)`,
/// reached from the root, as [`saturated_counts`] gives them for 1.0 (a
/// reflection does not change a count, spec §23.5). `leaf` is the DAG's
/// leaf level; the expansion checked every reference.
pub(crate) fn saturated_counts_expanded(
    expanded: &[dagfmt::expand::ExpandedLevel],
    leaf: LevelView<'_>,
    attribute_kind: AttributeKind,
    empty: bool,
) -> Result<Vec<(u8, u32, u64)>, GpuError> {
    if attribute_kind != AttributeKind::VoxelCount || empty || expanded.is_empty() {
        return Ok(Vec::new());
    }
    let mut memo = FxHashMap::default();
    count_expanded(expanded, leaf, 0, 0, &mut memo).map_err(GpuError::Malformed)?;
    let mut out: Vec<(u8, u32, u64)> = memo
        .into_iter()
        .map(|((l, word), c)| (l, word as u32, c))
        .collect();
    out.sort_unstable();
    Ok(out)
}

fn count_expanded(
    expanded: &[dagfmt::expand::ExpandedLevel],
    leaf: LevelView<'_>,
    level: u8,
    word: u64,
    memo: &mut FxHashMap<(u8, u64), u64>,
) -> Result<u64, FormatError> {
    let Some(ex) = expanded.get(usize::from(level)) else {
        let at = usize::try_from(word.saturating_mul(8)).unwrap_or(usize::MAX);
        let bytes = leaf
            .bytes
            .get(at..at.saturating_add(8))
            .ok_or_else(|| out_of_range(word))?;
        let bits = u64::from_le_bytes(bytes.try_into().expect("8 bytes"));
        return Ok(u64::from(bits.count_ones()));
    };
    let header = *ex
        .words
        .get(word as usize)
        .ok_or_else(|| out_of_range(word))?;
    let count = header >> dagfmt::layout::CHILD_MASK_BITS;
    if count != COUNT_SATURATED {
        return Ok(u64::from(count));
    }
    if let Some(&n) = memo.get(&(level, word)) {
        return Ok(n);
    }
    let children = (header & 0xff).count_ones() as usize;
    let refs = ex
        .words
        .get(word as usize + 1..word as usize + 1 + children)
        .ok_or_else(|| out_of_range(word))?;
    let mut total = 0u64;
    for &r in refs {
        total = total.saturating_add(count_expanded(
            expanded,
            leaf,
            level + 1,
            u64::from(r >> 3),
            memo,
        )?);
    }
    memo.insert((level, word), total);
    Ok(total)
}

fn out_of_range(leaf: u64) -> FormatError {
    FormatError::new(
        dagfmt::ErrorCode::ReferenceOutOfRange2,
        0,
        format!("a 2.0 reference names leaf {leaf}, past the leaf level"),
    )
}

/// Writes the words of the levels and the saturated table into `pages`.
pub(crate) fn upload(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    placement: &Placement,
    levels: &[UploadLevel<'_>],
    pages: &[wgpu::Buffer],
) -> Result<(), GpuError> {
    let mut writer = PageWriter::new(device, queue, placement.page_words, pages);
    for (section, slot) in levels.iter().zip(&placement.levels) {
        writer.write(u64::from(slot[0]), section.bytes)?;
        if let Some(starts) = section.starts {
            let bytes: Vec<u8> = starts.iter().flat_map(|w| w.to_le_bytes()).collect();
            writer.write(u64::from(slot[3]), &bytes)?;
        }
    }
    let table: Vec<u8> = placement
        .saturated
        .iter()
        .flat_map(|e| e.iter().flat_map(|w| w.to_le_bytes()))
        .collect();
    writer.write(u64::from(placement.sat_base), &table)?;
    writer.flush()
}

/// Writes bytes into a word address space cut into pages of `page_words`
/// words, one buffer each (the DAG's here, the colour section's in
/// `colors.rs`).
pub(crate) struct PageWriter<'a> {
    device: &'a wgpu::Device,
    queue: &'a wgpu::Queue,
    page_words: u64,
    pages: &'a [wgpu::Buffer],
    since_flush: usize,
}

impl<'a> PageWriter<'a> {
    /// A writer into `pages`, each of `page_words` words (the last perhaps fewer).
    pub(crate) fn new(
        device: &'a wgpu::Device,
        queue: &'a wgpu::Queue,
        page_words: u64,
        pages: &'a [wgpu::Buffer],
    ) -> Self {
        PageWriter {
            device,
            queue,
            page_words,
            pages,
            since_flush: 0,
        }
    }

    /// Writes `bytes` at word address `word`, split at page boundaries and in
    /// bounded chunks. A length that is not a multiple of 4 (only in a
    /// malformed file) is padded with zeros.
    pub(crate) fn write(&mut self, mut word: u64, mut bytes: &[u8]) -> Result<(), GpuError> {
        while !bytes.is_empty() {
            let page = word / self.page_words;
            let in_page = word % self.page_words;
            let room = ((self.page_words - in_page) * 4) as usize;
            let n = bytes.len().min(room).min(CHUNK_BYTES);
            let (chunk, rest) = bytes.split_at(n);
            let buffer = &self.pages[page as usize];
            if n.is_multiple_of(4) {
                self.queue.write_buffer(buffer, in_page * 4, chunk);
            } else {
                let mut padded = chunk.to_vec();
                padded.resize(n.next_multiple_of(4), 0);
                self.queue.write_buffer(buffer, in_page * 4, &padded);
            }
            self.since_flush += n;
            if self.since_flush >= FLUSH_BYTES {
                self.flush()?;
            }
            word += n.div_ceil(4) as u64;
            bytes = rest;
        }
        Ok(())
    }

    /// Submits the pending writes and waits, so that wgpu frees their staging memory.
    pub(crate) fn flush(&mut self) -> Result<(), GpuError> {
        self.queue.submit([]);
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Device(e.to_string()))?;
        self.since_flush = 0;
        Ok(())
    }
}
