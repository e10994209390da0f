//! Placing a DAG's words in GPU storage buffers.
//!
//! The shader sees one address space of 32-bit words: the level sections one
//! after the other (root first, the leaf level last), then the table of
//! saturated voxel counts. The space is cut into pages of a power-of-two
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
use dagfmt::{Dag, FormatError};
use rustc_hash::FxHashMap;

/// Bytes handed to one `Queue::write_buffer` call.
const CHUNK_BYTES: usize = 4 << 20;
/// Bytes written between two waits for the queue (bounds wgpu's staging memory).
const FLUSH_BYTES: usize = 64 << 20;

/// Where everything lies in the word address space.
#[derive(Clone, Debug)]
pub(crate) struct Placement {
    /// Per stored level: first word, pointer width, units (words, or leaves).
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
    /// Lays `dag` out for pages of at most `max_page_bytes` bytes and at most
    /// `max_pages` pages.
    pub fn new(
        dag: &Dag<'_>,
        saturated: Vec<(u8, u32, u64)>,
        max_page_bytes: u64,
        max_pages: u32,
    ) -> Result<Self, GpuError> {
        let mut levels = [[0u32; 4]; MAX_STORED_LEVELS];
        let mut next = 0u64;
        for (slot, section) in levels.iter_mut().zip(dag.levels()) {
            let words = (section.bytes.len() as u64).div_ceil(4);
            let units = if section.is_leaf {
                section.bytes.len() as u64 / 8
            } else {
                section.bytes.len() as u64 / 4
            };
            *slot = [
                u32::try_from(next).map_err(|_| too_large(next))?,
                u32::from(section.pointer_width),
                u32::try_from(units).unwrap_or(u32::MAX),
                0,
            ];
            next += words;
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

/// Writes the words of `dag` and the saturated table into `pages`.
pub(crate) fn upload(
    device: &wgpu::Device,
    queue: &wgpu::Queue,
    placement: &Placement,
    dag: &Dag<'_>,
    pages: &[wgpu::Buffer],
) -> Result<(), GpuError> {
    let mut writer = PageWriter::new(device, queue, placement.page_words, pages);
    for (section, slot) in dag.levels().iter().zip(&placement.levels) {
        writer.write(u64::from(slot[0]), section.bytes)?;
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
