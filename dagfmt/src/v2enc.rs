//! The format 2.0 level encoder (spec/VDAG.md §23.6–§23.7) on every core
//! and within a memory budget.
//!
//! It writes the bytes of [`crate::v2::encode_serial`], the reference
//! encoder (which merges through [`crate::symmetry::canonicalize`] and keeps
//! every table in memory), in three passes:
//!
//! 1. **Merge and rank**, bottom-up. Each 1.0 node (or leaf) of a level is
//!    described in intrinsic terms — its children as `1 + 8·rank + r` (§23.6)
//!    through the table of the level below — and turned into the least of its
//!    8 reflected forms, in parallel chunks. The level's forms are then sorted
//!    (in parallel): equal forms are one class, and a class's position among
//!    the distinct forms *is* its intrinsic rank, so merging and ranking are
//!    one sort, with no hash map and no class numbering to translate. The
//!    level's 1.0 nodes get their references (rank and least reflection) for
//!    the level above; the ranked keys and stabilisers are kept.
//! 2. **Order**, top-down (§23.7): reference counts, the shared classes by
//!    count, the sequential ones by parent.
//! 3. **Layout**, bottom-up: per level a histogram of the reference widths
//!    (in parallel), the widths, then the records, written in parallel
//!    chunks and joined in order.
//!
//! Every table a later pass needs (ranked keys, stabilisers, counts, the
//! stored order, the finished level bytes) goes through a `Store`: in
//! memory while the tables held fit the budget, else appended to one unnamed
//! scratch file and read back when its pass comes. Spilling changes where the
//! tables are, never what they hold, so the output does not depend on the
//! budget (nor on the number of threads: every parallel step is a map whose
//! results are joined in order, or a sort of distinct keys).
//!
//! Each pass over a level holds a working set that grows with the level
//! (`merge_work`, `order_work`, `layout_work`, counted from the pass's
//! allocations: at most 206 bytes per 1.0 node, 9 per node below and 3/16
//! per word of the two levels in the merge; at most 152 per class and 21–36
//! per class below in the order pass; about 100 per record, 16 per class
//! below and three times the level's bytes in the layout). A pass whose working set is
//! over the budget goes out of core instead (module `external`: the merge as an
//! external sort of the level's forms in runs, the order and the layout a
//! chunk at a time), within the budget; it makes the same tables, so the
//! bytes are again the same. The leaves' layout (48 bytes per leaf class)
//! and the root's merge are always in memory. What the out-of-core passes
//! still hold per node or class is the encoder's least ([`least_memory`]),
//! which a caller may have it refuse instead of exceeding.

use std::fs::File;
use std::io::{self, Read, Seek, SeekFrom, Write};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};

use rayon::prelude::*;

use crate::error::{ErrorCode, FormatError};
use crate::prefetch::prefetch;
use crate::reader::Dag;
use crate::symmetry::{NodeKey, reflect_leaf};
use crate::v2::{
    BitWriter, Encoded, EncodedLevel, best_widths, least_reflected_key_in, norm, reflect_key,
};
use crate::v2file::ConvertError;

mod external;
use external::Slots;

/// How [`encode_levels`] may use memory.
#[derive(Clone, Debug, Default)]
pub struct EncodeOptions {
    /// Bytes the encoder may hold (its per-level working set and the tables
    /// kept for later passes) before it moves finished tables to a scratch
    /// file; `None`: no limit, everything stays in memory. The mapped 1.0
    /// file is not counted. A budget below a pass's working set over a
    /// level spills every table and takes that pass out of core, sized to
    /// the budget; what such a pass still holds per item (a rank and a
    /// reflection per 1.0 node of the level in the merge, 16 bytes per class
    /// in the order and the layout, with the tables of the level below it
    /// reads at random) is the least it needs ([`least_memory`]), and a
    /// budget below that is exceeded by it.
    pub memory_budget: Option<u64>,
    /// Refuse a budget below the least the encoder holds
    /// ([`ConvertError::Budget`]) instead of exceeding it: checked for the
    /// merge before it starts (from the 1.0 levels), and for the order and
    /// the layout once the merge has counted the classes (their least is
    /// then exact, where [`least_memory`] counts a class per 1.0 node).
    pub refuse_below_least: bool,
    /// Directory of the scratch file (an unnamed temporary file); default:
    /// the system's temporary directory.
    pub scratch_dir: Option<PathBuf>,
}

// The working sets below count what each pass in memory allocates, at its
// largest moment, from the sizes of its items: a `Form` (48 bytes), a
// leaf's form (16), a `NodeKey` (72), a stored node (8: u32 rank, u8
// reflection, padded), a slot value (8), a count (4), an address (8). A
// vector collected from a parallel iterator of unknown length (`Result`s,
// `flat_map_iter`) is built in pieces that grow by doubling and are then
// joined: up to twice its bytes in pieces plus the joined copy, 3 times its
// bytes; a vector grown by pushes alone is counted at twice its bytes.
// Where a level's classes are not known yet (the merge), there are as many
// as 1.0 nodes, the most there can be.

/// Bytes of a merge pass's `Form`.
const FORM_BYTES: u64 = std::mem::size_of::<Form>() as u64;
/// Bytes of a ranked key.
const KEY_BYTES: u64 = std::mem::size_of::<NodeKey>() as u64;
/// Bytes of a stored node (class rank and reflection) in the stored order.
const STORED_BYTES: u64 = std::mem::size_of::<(u32, u8)>() as u64;
/// Bytes of a leaf's form in the merge of the leaves (mask, index,
/// reflection).
const LEAF_FORM_BYTES: u64 = std::mem::size_of::<(u64, u32, u8)>() as u64;
/// The most bytes of a 2.0 record (§23.2): its header, 9 two-bit codes (8
/// children and a base reference) and 9 references of the widest width.
const RECORD_BYTES_MAX: u64 = 4 + (9 * 2 + 9 * crate::v2::MAX_WIDTH as u64).div_ceil(8);

/// Bytes of [`RecordStarts`] over a level of `units` words: a bit per word
/// and a u32 count per 64 words.
fn record_starts_bytes(units: u64) -> u64 {
    12 * units.div_ceil(64)
}

/// What the merge of a level reads of the level below, `nodes` 1.0 nodes
/// (or leaves) of `units` words (`None` for the leaves, whose pointers are
/// their indices): the slot value of each node by ordinal (8 bytes), the
/// stabilisers of as many classes (1), the record starts. While the table
/// by ordinal is made from an out-of-core merge's ranks and reflections (5
/// bytes a node), both are held: `.1`.
fn merge_inputs(nodes: u64, units: Option<u64>) -> (u64, u64) {
    let held = 8 * nodes + nodes + units.map_or(0, record_starts_bytes);
    (held, held + 5 * nodes)
}

/// The working set of the merge pass in memory at level `level`: the
/// tables of the level below it reads, and the larger of its two moments:
/// the forms being collected (`Result`s in parallel: 3 times their bytes)
/// beside the record starts (4 bytes a node, and the bitmap of this level),
/// or the forms sorted, the table by ordinal being written (8 bytes a node)
/// and the ranked keys and stabilisers in chunks, then joined (2 × 73 bytes
/// a class).
fn merge_work(dag: &Dag<'_>, level: usize) -> u64 {
    let levels = dag.levels();
    let n = levels[level].node_count;
    if level == usize::from(dag.leaf_level()) {
        // The leaves' forms (3 × 16 while collected), or the forms, the
        // slot value by leaf (8) and the ranked masks and stabilisers
        // (2 × 9 a class).
        let collect = 3 * LEAF_FORM_BYTES * n;
        let rank = LEAF_FORM_BYTES * n + 8 * n + 2 * 9 * n;
        return collect.max(rank);
    }
    let below = &levels[level + 1];
    let (inputs, converting) =
        merge_inputs(below.node_count, (!below.is_leaf).then(|| below.units()));
    let starts = 4 * n + record_starts_bytes(levels[level].units());
    let collect = starts + 3 * FORM_BYTES * n;
    let rank = starts + FORM_BYTES * n + 8 * n + 2 * (KEY_BYTES + 1) * n;
    converting.max(inputs + collect.max(rank))
}

/// The working set of the order pass in memory at a node level of
/// `classes` classes over `below` classes: the stored order of the level
/// (8 bytes a class) throughout; first its ranked keys and the keys as
/// stored (72 + 72), with the stabilisers (1), the counts (4) and the
/// shared classes of the level below (a vector grown by pushes: 2 × 8);
/// then the keys as stored, the first sequential child of each in chunks
/// and joined (8 + 8) and the order below (2 × 8) in chunks and joined.
fn order_work(classes: usize, below: usize) -> u64 {
    let (c, b) = (classes as u64, below as u64);
    let keys = (STORED_BYTES + 2 * KEY_BYTES) * c + (1 + 4 + 2 * STORED_BYTES) * b;
    let firsts = (STORED_BYTES + KEY_BYTES + 8 + 8) * c + (4 + 2 * 2 * STORED_BYTES) * b;
    keys.max(firsts)
}

/// The working set of the layout in memory at node level `level` of
/// `classes` classes over `below` classes: the addresses of the level
/// below by rank and by position (8 + 8 a class below); the stored order
/// and counts of this level (8 + 4 a class); then either its keys and first
/// sequential children (72 + 8) with the chunks' records (pushed: twice
/// their bytes) and offsets (8), or the chunks' records, the joined level
/// and the addresses by position and by rank (8 + 8). The level's bytes
/// are at most those of its 1.0 nodes (4 a word) and at most
/// [`RECORD_BYTES_MAX`] a record.
fn layout_work(dag: &Dag<'_>, level: usize, classes: usize, below: usize) -> u64 {
    let (c, b) = (classes as u64, below as u64);
    let bytes = (4 * dag.levels()[level].units()).min(RECORD_BYTES_MAX * c);
    let held = 16 * b + (STORED_BYTES + 4) * c;
    let records = (KEY_BYTES + 8 + 8) * c + 2 * bytes;
    let joined = (8 + 8 + 8) * c + 3 * bytes;
    held + records.max(joined)
}

/// The working set of the leaves' layout over `leaves` leaf classes: their
/// stored order (8 bytes), masks (8) and addresses by rank (8), with their
/// counts (4) first, then the leaves' bytes collected in parallel (3 × 8).
fn leaf_layout_work(leaves: usize) -> u64 {
    let l = leaves as u64;
    let held = (STORED_BYTES + 8 + 8) * l;
    held + (4 * l).max(3 * 8 * l)
}

/// The largest working set of a pass in memory over the levels of `dag`,
/// with as many classes as 1.0 nodes (the most there can be). A level whose
/// pass does not fit the budget takes that pass out of core
/// (module `external`), within the budget; the leaves' layout and the root's
/// merge are always in memory.
fn working_set(dag: &Dag<'_>) -> u64 {
    let levels = dag.levels();
    let leaf_level = usize::from(dag.leaf_level());
    let n = |l: usize| levels[l].node_count as usize;
    (0..=leaf_level)
        .map(|l| {
            if l == leaf_level {
                return merge_work(dag, l).max(leaf_layout_work(n(l)));
            }
            merge_work(dag, l)
                .max(order_work(n(l), n(l + 1)))
                .max(layout_work(dag, l, n(l), n(l + 1)))
        })
        .max()
        .unwrap_or(0)
}

/// The most the encoder holds in memory at once for `dag` with no memory
/// budget's help: the largest working set of its passes in memory over a
/// level (see [`EncodeOptions::memory_budget`]), counted with as many
/// classes per level as 1.0 nodes. With a budget of at least this, every
/// pass runs in memory and the finished tables that do not fit what is
/// left go to the scratch file.
pub fn in_memory_working_set(dag: &Dag<'_>) -> u64 {
    working_set(dag)
}

/// The least the encoder holds in memory for `dag`, whatever the budget:
/// with a budget below [`in_memory_working_set`], the passes over the
/// largest levels go out of core in chunks sized to the budget, but each
/// still holds some bytes per 1.0 node or class of its level and the level
/// below (a rank and a reflection per node in the merge; the stored order,
/// counts and addresses in the order and the layout), its least chunks and
/// its buffers. This is the largest of those over the levels (with as many
/// classes as 1.0 nodes): a budget below it is exceeded by up to the
/// difference, so a caller bound by a memory limit should refuse one.
pub fn least_memory(dag: &Dag<'_>) -> u64 {
    if dag.is_empty() {
        return 0;
    }
    let nodes: Vec<usize> = dag.levels().iter().map(|s| s.node_count as usize).collect();
    external::least_for_merge(dag).max(external::least_for_order_and_layout(dag, &nodes))
}

/// A chunk's first-sequential-child positions and its sequential children
/// (class rank, reflection), in the top-down pass.
type FirstsAndSequential = (Vec<u64>, Vec<(u32, u8)>);

/// Records (or leaves) per parallel chunk of the layout.
const LAYOUT_CHUNK: usize = 1 << 15;

/// The encoded level sections, each in memory or in the scratch file, with
/// what the section table needs; [`EncodedLevels::write_level`] streams them.
#[derive(Debug)]
pub struct EncodedLevels {
    /// Depth D.
    pub depth: u8,
    /// Per level, root first: widths, items, leaf flag, length and CRC-32C.
    pub levels: Vec<LevelSummary>,
    bytes: Vec<Table<u8>>,
    store: Store,
    external_passes: usize,
}

/// What the section table says of one encoded level.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LevelSummary {
    /// The level's widths w_1 ≤ w_2 ≤ w_3 (0, 0, 0 for the leaf level).
    pub widths: [u8; 3],
    /// Records or leaves in the section.
    pub item_count: u64,
    /// Whether this is the leaf level.
    pub is_leaf: bool,
    /// Bytes of the section.
    pub length: u64,
    /// CRC-32C of the section's bytes.
    pub crc: u32,
}

impl EncodedLevels {
    /// Bytes of the tables that went to the scratch file (0: none did).
    pub fn spilled_bytes(&self) -> u64 {
        self.store.end
    }

    /// How many passes over a level (merge, order, layout) went out of core
    /// because their working set in memory was over the budget.
    pub fn external_passes(&self) -> usize {
        self.external_passes
    }

    /// Streams the bytes of level `level` to `sink`, in pieces.
    pub fn write_level(
        &mut self,
        level: usize,
        sink: &mut dyn FnMut(&[u8]) -> io::Result<()>,
    ) -> io::Result<()> {
        self.store.stream(&self.bytes[level], sink)
    }

    /// The levels in memory, as [`crate::v2::encode_serial`] returns them.
    pub fn into_encoded(mut self) -> io::Result<Encoded> {
        let mut levels = Vec::with_capacity(self.levels.len());
        for (summary, table) in self.levels.iter().zip(std::mem::take(&mut self.bytes)) {
            levels.push(EncodedLevel {
                bytes: self.store.take(table)?,
                widths: summary.widths,
                item_count: summary.item_count,
                is_leaf: summary.is_leaf,
            });
        }
        Ok(Encoded {
            depth: self.depth,
            levels,
        })
    }
}

/// A fixed-size item of a table that may go to the scratch file.
trait Item: Copy + Send + Sync {
    /// Bytes of one item in the file.
    const BYTES: usize;
    fn put(&self, out: &mut Vec<u8>);
    fn get(bytes: &[u8]) -> Self;
}

impl Item for u8 {
    const BYTES: usize = 1;
    fn put(&self, out: &mut Vec<u8>) {
        out.push(*self);
    }
    fn get(bytes: &[u8]) -> Self {
        bytes[0]
    }
}

impl Item for u32 {
    const BYTES: usize = 4;
    fn put(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes());
    }
    fn get(bytes: &[u8]) -> Self {
        u32::from_le_bytes(bytes[..4].try_into().expect("4 bytes"))
    }
}

impl Item for u64 {
    const BYTES: usize = 8;
    fn put(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes());
    }
    fn get(bytes: &[u8]) -> Self {
        u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes"))
    }
}

impl Item for (u32, u8) {
    const BYTES: usize = 5;
    fn put(&self, out: &mut Vec<u8>) {
        self.0.put(out);
        out.push(self.1);
    }
    fn get(bytes: &[u8]) -> Self {
        (u32::get(bytes), bytes[4])
    }
}

impl Item for NodeKey {
    const BYTES: usize = 68;
    fn put(&self, out: &mut Vec<u8>) {
        for s in &self.slots {
            s.put(out);
        }
        self.attribute.put(out);
    }
    fn get(bytes: &[u8]) -> Self {
        let mut slots = [0u64; 8];
        for (i, s) in slots.iter_mut().enumerate() {
            *s = u64::get(&bytes[8 * i..]);
        }
        NodeKey {
            slots,
            attribute: u32::get(&bytes[64..]),
        }
    }
}

/// A table kept for a later pass: in memory, or `items` items at byte `at`
/// of the scratch file.
#[derive(Debug)]
enum Table<T> {
    Held(Vec<T>),
    Spilled { at: u64, items: usize },
}

/// Where the finished tables wait: in memory while `held` stays within
/// `budget`, else in the scratch file (created when first needed, appended
/// to, never rewritten).
#[derive(Debug)]
struct Store {
    budget: Option<u64>,
    held: u64,
    dir: Option<PathBuf>,
    file: Option<File>,
    end: u64,
}

/// Bytes per piece when a table is written to or read from the scratch file.
const PIECE: usize = 1 << 20;

impl Store {
    fn file(&mut self) -> io::Result<&mut File> {
        if self.file.is_none() {
            let dir = self.dir.clone().unwrap_or_else(std::env::temp_dir);
            let file = tempfile::tempfile_in(&dir).map_err(|e| {
                io::Error::new(
                    e.kind(),
                    format!("cannot create a scratch file in {}: {e}", dir.display()),
                )
            })?;
            self.file = Some(file);
        }
        Ok(self.file.as_mut().expect("just created"))
    }

    /// Keeps `items` for a later pass.
    fn keep<T: Item>(&mut self, items: Vec<T>) -> io::Result<Table<T>> {
        let bytes = std::mem::size_of_val(items.as_slice()) as u64;
        if self.budget.is_none_or(|b| self.held + bytes <= b) {
            self.held += bytes;
            return Ok(Table::Held(items));
        }
        let at = self.end;
        let file = self.file()?;
        file.seek(SeekFrom::Start(at))?;
        let mut buf = Vec::with_capacity(PIECE + T::BYTES);
        for piece in items.chunks(PIECE / T::BYTES) {
            buf.clear();
            for x in piece {
                x.put(&mut buf);
            }
            file.write_all(&buf)?;
        }
        self.end += (items.len() * T::BYTES) as u64;
        Ok(Table::Spilled {
            at,
            items: items.len(),
        })
    }

    /// Gives back a table kept by [`Store::keep`].
    fn take<T: Item>(&mut self, table: Table<T>) -> io::Result<Vec<T>> {
        match table {
            Table::Held(v) => {
                self.held -= std::mem::size_of_val(v.as_slice()) as u64;
                Ok(v)
            }
            Table::Spilled { at, items } => {
                let mut out = Vec::with_capacity(items);
                self.read_pieces(at, items * T::BYTES, T::BYTES, |piece| {
                    out.extend(piece.chunks_exact(T::BYTES).map(T::get));
                    Ok(())
                })?;
                Ok(out)
            }
        }
    }

    /// Streams a table of bytes to `sink` without taking it.
    fn stream(
        &mut self,
        table: &Table<u8>,
        sink: &mut dyn FnMut(&[u8]) -> io::Result<()>,
    ) -> io::Result<()> {
        match *table {
            Table::Held(ref v) => sink(v),
            Table::Spilled { at, items } => self.read_pieces(at, items, 1, sink),
        }
    }

    /// Reads `len` bytes at `at` of the scratch file in pieces of a multiple
    /// of `unit` bytes.
    fn read_pieces(
        &mut self,
        at: u64,
        len: usize,
        unit: usize,
        mut piece: impl FnMut(&[u8]) -> io::Result<()>,
    ) -> io::Result<()> {
        let file = self.file()?;
        file.seek(SeekFrom::Start(at))?;
        let step = PIECE / unit * unit;
        let mut buf = vec![0u8; step.min(len)];
        let mut left = len;
        while left > 0 {
            let n = step.min(left);
            file.read_exact(&mut buf[..n])?;
            piece(&buf[..n])?;
            left -= n;
        }
        Ok(())
    }
}

/// A 1.0 node in intrinsic terms, least of its reflected forms.
#[derive(Clone, Copy, Debug)]
struct Form {
    /// The least form, packed so that it sorts as the [`NodeKey`] does.
    key: PackedKey,
    /// Ordinal of the 1.0 node in its level.
    node: u32,
    /// The reflection from the node to its least form (the same one turns
    /// the least form back into the node).
    reflection: u8,
    /// The stabiliser of the least form, as a bit set of reflections.
    stab: u8,
}

/// The form of 1.0 node `node` whose key is `key`: the least of its
/// reflected forms (the first reflection reaching it on ties), packed in
/// `slot_bits` bits a slot; `stabs`: the stabiliser of the child at each
/// slot (any value where a slot is empty).
fn least_form(key: &NodeKey, stabs: &[u8; 8], node: u32, slot_bits: u32) -> Form {
    let (key, reflection, stab) = least_reflected_key_in(key, stabs);
    Form {
        key: PackedKey::pack(&key, slot_bits),
        node,
        reflection,
        stab,
    }
}

/// A [`NodeKey`] as one 320-bit string, most significant bits first: the 8
/// slot values in `slot_bits` bits each, then the 32 attribute bits. Fields
/// of fixed widths, each below 2^width, so the strings (compared word by
/// word) are in the order of the keys, and equal exactly when the keys are:
/// the level's sort compares and moves 40 bytes, not 68 compared field by
/// field. A slot value is at most 2^35 (ranks are below 2^32), so 36 bits
/// always do and 8 · 36 + 32 = 320.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
struct PackedKey([u64; 5]);

impl PackedKey {
    /// Bits per slot for a level whose classes below number `classes_below`:
    /// the largest slot value is `8 · classes_below` (§23.6).
    fn slot_bits(classes_below: usize) -> u32 {
        bits_of(8 * classes_below as u64)
    }

    fn pack(key: &NodeKey, slot_bits: u32) -> PackedKey {
        let mut words = [0u64; 5];
        let mut at = 0u32;
        for &s in &key.slots {
            debug_assert!(bits_of(s) <= slot_bits);
            put_bits(&mut words, at, s, slot_bits);
            at += slot_bits;
        }
        put_bits(&mut words, at, u64::from(key.attribute), 32);
        PackedKey(words)
    }

    fn unpack(&self, slot_bits: u32) -> NodeKey {
        let mut key = NodeKey {
            slots: [0; 8],
            attribute: 0,
        };
        let mut at = 0u32;
        for s in &mut key.slots {
            *s = get_bits(&self.0, at, slot_bits);
            at += slot_bits;
        }
        key.attribute = get_bits(&self.0, at, 32) as u32;
        key
    }
}

/// ORs `value` (below 2^`bits`, `bits` 1..=64) into `words` at bit `at`,
/// counted from the most significant bit of `words[0]`.
fn put_bits(words: &mut [u64; 5], at: u32, value: u64, bits: u32) {
    let (i, off) = ((at / 64) as usize, at % 64);
    let end = off + bits;
    if end <= 64 {
        words[i] |= value << (64 - end);
    } else {
        words[i] |= value >> (end - 64);
        words[i + 1] |= value << (128 - end);
    }
}

/// The `bits` bits (1..=64) of `words` at bit `at`, as [`put_bits`] put them.
fn get_bits(words: &[u64; 5], at: u32, bits: u32) -> u64 {
    let (i, off) = ((at / 64) as usize, at % 64);
    let end = off + bits;
    let mask = u64::MAX >> (64 - bits);
    if end <= 64 {
        (words[i] >> (64 - end)) & mask
    } else {
        ((words[i] << (end - 64)) | (words[i + 1] >> (128 - end))) & mask
    }
}

/// The stabiliser of a leaf mask: the reflections that leave it unchanged.
fn leaf_stab(mask: u64) -> u8 {
    (0..8u8)
        .filter(|&r| reflect_leaf(mask, r) == mask)
        .fold(0, |a, r| a | 1 << r)
}

/// The slot value (§23.6) naming class `rank` reached by reflection `r`.
fn slot_value(rank: usize, r: u8) -> u64 {
    1 + ((rank as u64) << 3) + u64::from(r)
}

/// What the merge of a level leaves for the level above, by ordinal of each
/// of its 1.0 nodes (by index of each leaf): the slot value naming the node
/// in the low bits, and the stabiliser of its class in the top 8 (bits
/// [`STAB_SHIFT`]..), so that the level above reads one table per child,
/// not also the stabilisers by rank.
const STAB_SHIFT: u32 = 56;

/// The slot value and the class stabiliser kept for a node in `slot_at`.
fn slot_and_stab(rank: usize, r: u8, stab: u8) -> u64 {
    slot_value(rank, norm(r, stab)) | (u64::from(stab) << STAB_SHIFT)
}

/// Encodes the level sections of the 2.0 file of `dag`'s voxels (§23), the
/// bytes of [`crate::v2::encode_serial`], on the threads of the current
/// rayon pool and within `options`' memory budget.
pub fn encode_levels(
    dag: &Dag<'_>,
    options: &EncodeOptions,
) -> Result<EncodedLevels, ConvertError> {
    let depth = dag.depth() as u8;
    let leaf_level = usize::from(dag.leaf_level());
    // The largest per-level working set, which the budget must leave room
    // for; a pass whose working set is over the budget goes out of core.
    let budget = options.memory_budget;
    let refuse_below = |least: u64| match budget {
        Some(b) if options.refuse_below_least && b < least => {
            Err(ConvertError::Budget { least, budget: b })
        }
        _ => Ok(()),
    };
    if !dag.is_empty() {
        refuse_below(external::least_for_merge(dag))?;
    }
    let work = budget.map_or(0, |b| working_set(dag).min(b));
    let fits = |estimate: u64| budget.is_none_or(|b| estimate <= b);
    // What an out-of-core pass may hold: the budget less the tables held.
    let room = |store: &Store| budget.map_or(u64::MAX, |b| b.saturating_sub(store.held));
    let mut external_passes = 0usize;
    let mut store = Store {
        budget: budget.map(|b| b.saturating_sub(work)),
        held: 0,
        dir: options.scratch_dir.clone(),
        file: None,
        end: 0,
    };
    let mut summaries = Vec::with_capacity(leaf_level + 1);
    let mut bytes = Vec::with_capacity(leaf_level + 1);
    if dag.is_empty() {
        // An empty node level has no reference: its minimising widths are
        // the least triple, 1, 1, 1 (§23.2).
        for l in 0..=leaf_level {
            let is_leaf = l == leaf_level;
            summaries.push(LevelSummary {
                widths: if is_leaf { [0; 3] } else { [1; 3] },
                item_count: 0,
                is_leaf,
                length: 0,
                crc: crc32c::crc32c(&[]),
            });
            bytes.push(Table::Held(Vec::new()));
        }
        return Ok(EncodedLevels {
            depth,
            levels: summaries,
            bytes,
            store,
            external_passes: 0,
        });
    }

    // Pass 1: merge and rank, bottom-up.
    let (leaves, mut child_stabs, mut slots) = if fits(merge_work(dag, leaf_level)) {
        let (leaves, stabs, slot_at) = merge_leaves(dag, leaf_level)?;
        let slots = Slots::ByOrdinal {
            slot_at,
            starts: None,
        };
        (store.keep(leaves)?, stabs, slots)
    } else {
        external_passes += 1;
        external::merge_leaves_external(dag, leaf_level, room(&store), &mut store)?
    };
    let leaf_classes = leaves.len();
    let mut stabs: Vec<Option<Table<u8>>> = (0..=leaf_level).map(|_| None).collect();
    let mut canon: Vec<Option<Table<NodeKey>>> = (0..leaf_level).map(|_| None).collect();
    let mut class_counts = vec![0usize; leaf_level + 1];
    class_counts[leaf_level] = leaf_classes;
    for level in (0..leaf_level).rev() {
        // The root (one node) is stored as it is: always merged in memory.
        let (keys, level_stabs, next_slots) = if level == 0 || fits(merge_work(dag, level)) {
            // Below an external level, its ranks and reflections become the
            // table by ordinal (slot value and stabiliser) read here.
            let (slot_at, child_starts) =
                std::mem::replace(&mut slots, Slots::none()).into_by_ordinal(&child_stabs);
            let (keys, level_stabs, next_slot_at, starts) =
                merge_level(dag, level, &slot_at, child_starts.as_ref(), &child_stabs)?;
            drop(slot_at);
            drop(child_starts);
            (
                store.keep(keys)?,
                level_stabs,
                Slots::ByOrdinal {
                    slot_at: next_slot_at,
                    starts: Some(starts),
                },
            )
        } else {
            external_passes += 1;
            let room = room(&store).saturating_sub(slots.bytes() + child_stabs.len() as u64);
            external::merge_level_external(dag, level, &slots, &child_stabs, room, &mut store)?
        };
        slots = next_slots;
        class_counts[level] = keys.len();
        canon[level] = Some(keys);
        stabs[level + 1] = Some(store.keep(std::mem::replace(&mut child_stabs, level_stabs))?);
    }
    // The root's stabiliser is not needed: nothing refers to it.
    drop(child_stabs);
    drop(slots);
    refuse_below(external::least_for_order_and_layout(dag, &class_counts))?;

    // Pass 2: the order of each level, top-down (§23.7).
    let mut stored: Vec<(u32, u8)> = vec![(0, 0)];
    // Per level: its stored order, the first sequential child of each stored
    // node, each stored node as stored, and the reference counts of the level
    // below, for the layout.
    let mut kept_stored: Vec<Option<Table<(u32, u8)>>> = (0..=leaf_level).map(|_| None).collect();
    let mut kept_firsts: Vec<Option<Table<u64>>> = (0..leaf_level).map(|_| None).collect();
    let mut kept_keys: Vec<Option<Table<NodeKey>>> = (0..leaf_level).map(|_| None).collect();
    let mut kept_counts: Vec<Option<Table<u32>>> = (0..=leaf_level).map(|_| None).collect();
    for level in 0..leaf_level {
        if !fits(order_work(class_counts[level], class_counts[level + 1])) {
            external_passes += 1;
            let room = room(&store);
            let (next, firsts, as_stored, c) = external::order_level_external(
                &mut store,
                canon[level].take().expect("merged"),
                stabs[level + 1].take().expect("merged"),
                &stored,
                class_counts[level + 1],
                room,
            )?;
            kept_stored[level] = Some(store.keep(std::mem::replace(&mut stored, next))?);
            kept_firsts[level] = Some(store.keep(firsts)?);
            kept_keys[level] = Some(as_stored);
            kept_counts[level + 1] = Some(store.keep(c)?);
            continue;
        }
        let keys = store.take(canon[level].take().expect("merged"))?;
        let child_stabs = store.take(stabs[level + 1].take().expect("merged"))?;
        let counts: Vec<AtomicU32> = (0..class_counts[level + 1])
            .map(|_| AtomicU32::new(0))
            .collect();
        count_references(&keys, &counts);
        let c: Vec<u32> = counts.into_iter().map(AtomicU32::into_inner).collect();
        let mut next = shared_by_count(&c);
        // A ranked key's references are normalised already (merge_level
        // builds them so), so the identity leaves it as it is: shared nodes,
        // and most sequential ones, are stored without a reflection.
        let as_stored: Vec<NodeKey> = stored
            .par_iter()
            .enumerate()
            .map(|(i, &(rank, applied))| {
                // Two steps ahead: the key (72 bytes, two lines), then, once
                // it is near, the stabilisers a reflection of it reads.
                if let Some(&(ahead, _)) = stored.get(i + 2 * AHEAD) {
                    let key = &keys[ahead as usize];
                    prefetch(&key.slots[0]);
                    prefetch(&key.attribute);
                }
                if let Some(&(ahead, r)) = stored.get(i + AHEAD)
                    && r != 0
                {
                    for &s in &keys[ahead as usize].slots {
                        if s != 0 {
                            prefetch(&child_stabs[((s - 1) >> 3) as usize]);
                        }
                    }
                }
                let key = &keys[rank as usize];
                if applied == 0 {
                    *key
                } else {
                    reflect_key(key, applied, &child_stabs)
                }
            })
            .collect();
        drop(keys);
        drop(child_stabs);
        // Each chunk's sequential children and, per stored node, where its
        // first one is among them; joined in order.
        let parts: Vec<FirstsAndSequential> = as_stored
            .par_chunks(LAYOUT_CHUNK)
            .map(|chunk| {
                let mut firsts = Vec::with_capacity(chunk.len());
                let mut seq = Vec::new();
                for key in chunk {
                    firsts.push(seq.len() as u64);
                    for &s in &key.slots {
                        if s != 0 {
                            let child = ((s - 1) >> 3) as u32;
                            if c[child as usize] == 1 {
                                seq.push((child, ((s - 1) & 7) as u8));
                            }
                        }
                    }
                }
                (firsts, seq)
            })
            .collect();
        let mut firsts = Vec::with_capacity(as_stored.len());
        for (part_firsts, seq) in parts {
            let base = next.len() as u64;
            firsts.extend(part_firsts.iter().map(|f| base + f));
            next.extend_from_slice(&seq);
        }
        kept_stored[level] = Some(store.keep(std::mem::replace(&mut stored, next))?);
        kept_firsts[level] = Some(store.keep(firsts)?);
        kept_keys[level] = Some(store.keep(as_stored)?);
        kept_counts[level + 1] = Some(store.keep(c)?);
    }
    kept_stored[leaf_level] = Some(store.keep(stored)?);

    // Pass 3: the layout, bottom-up.
    let mut bytes: Vec<Option<Table<u8>>> = (0..=leaf_level).map(|_| None).collect();
    let mut summaries: Vec<Option<LevelSummary>> = vec![None; leaf_level + 1];
    let stored_leaves = store.take(kept_stored[leaf_level].take().expect("ordered"))?;
    // A root that is a leaf (depth 2) has no level above to count it.
    let c = match kept_counts[leaf_level].take() {
        Some(t) => store.take(t)?,
        None => vec![1],
    };
    let leaves = store.take(leaves)?;
    // Address of each shared child by rank (`SEQUENTIAL` for a child
    // referenced once); of each child by position (`None`: the position
    // itself, in the leaf level).
    let mut addr_of_rank = vec![SEQUENTIAL; leaf_classes];
    for (pos, &(rank, _)) in stored_leaves.iter().enumerate() {
        if c[rank as usize] > 1 {
            addr_of_rank[rank as usize] = pos as u64;
        }
    }
    drop(c);
    let leaf_bytes: Vec<u8> = stored_leaves
        .par_chunks(LAYOUT_CHUNK)
        .flat_map_iter(|chunk| {
            chunk.iter().flat_map(|&(rank, applied)| {
                reflect_leaf(leaves[rank as usize], applied).to_le_bytes()
            })
        })
        .collect();
    drop(leaves);
    summaries[leaf_level] = Some(LevelSummary {
        widths: [0; 3],
        item_count: stored_leaves.len() as u64,
        is_leaf: true,
        length: leaf_bytes.len() as u64,
        crc: crc32c::crc32c(&leaf_bytes),
    });
    bytes[leaf_level] = Some(store.keep(leaf_bytes)?);
    drop(stored_leaves);
    let mut addr_of_pos: Option<Vec<u64>> = None;
    for level in (0..leaf_level).rev() {
        let below = addr_of_rank.len();
        if !fits(layout_work(dag, level, class_counts[level], below)) {
            external_passes += 1;
            let stored_here = store.take(kept_stored[level].take().expect("ordered"))?;
            let counts_here = match kept_counts[level].take() {
                Some(t) => store.take(t)?,
                None => vec![1],
            };
            let layout = LevelLayout {
                addr_of_rank: &addr_of_rank,
                addr_of_pos: addr_of_pos.as_deref(),
            };
            // Held besides the pass's own tables: what it reads below, the
            // stored order and the counts.
            let held = 8 * (addr_of_rank.len() + addr_of_pos.as_ref().map_or(0, Vec::len)) as u64
                + 12 * stored_here.len() as u64;
            let room = room(&store).saturating_sub(held);
            let (summary, level_bytes, next_addr_of_pos, next_addr_of_rank) =
                external::layout_level_external(
                    &mut store,
                    level,
                    kept_keys[level].take().expect("ordered"),
                    kept_firsts[level].take().expect("ordered"),
                    &stored_here,
                    &counts_here,
                    class_counts[level],
                    &layout,
                    room,
                )?;
            summaries[level] = Some(summary);
            bytes[level] = Some(level_bytes);
            addr_of_pos = Some(next_addr_of_pos);
            addr_of_rank = next_addr_of_rank;
            continue;
        }
        let keys = store.take(kept_keys[level].take().expect("ordered"))?;
        let firsts = store.take(kept_firsts[level].take().expect("ordered"))?;
        let stored_here = store.take(kept_stored[level].take().expect("ordered"))?;
        let counts_here = match kept_counts[level].take() {
            Some(t) => store.take(t)?,
            None => vec![1],
        };
        let layout = LevelLayout {
            addr_of_rank: &addr_of_rank,
            addr_of_pos: addr_of_pos.as_deref(),
        };
        let hist = keys
            .par_chunks(LAYOUT_CHUNK)
            .zip(firsts.par_chunks(LAYOUT_CHUNK))
            .map(|(keys, firsts)| {
                let mut hist = [0u64; 65];
                for (i, (key, &first)) in keys.iter().zip(firsts).enumerate() {
                    if let Some(ahead) = keys.get(i + AHEAD) {
                        layout.prefetch(ahead);
                    }
                    layout.record(key, first, |v| hist[bits_of(v) as usize] += 1);
                }
                hist
            })
            .reduce(
                || [0u64; 65],
                |mut a, b| {
                    for (x, y) in a.iter_mut().zip(b) {
                        *x += y;
                    }
                    a
                },
            );
        let widths = level_widths(&hist, level)?;
        // Each chunk's bytes and its records' offsets within them.
        let pieces: Vec<(Vec<u8>, Vec<u64>)> = keys
            .par_chunks(LAYOUT_CHUNK)
            .zip(firsts.par_chunks(LAYOUT_CHUNK))
            .map(|(keys, firsts)| {
                let mut out = Vec::new();
                let mut offsets = Vec::with_capacity(keys.len());
                for (i, (key, &first)) in keys.iter().zip(firsts).enumerate() {
                    if let Some(ahead) = keys.get(i + AHEAD) {
                        layout.prefetch(ahead);
                    }
                    offsets.push(out.len() as u64);
                    layout.write(key, first, widths, &mut out);
                }
                (out, offsets)
            })
            .collect();
        drop(keys);
        drop(firsts);
        let length: u64 = pieces.iter().map(|p| p.0.len() as u64).sum();
        let mut level_bytes = Vec::with_capacity(length as usize);
        let mut next_addr_of_pos = Vec::with_capacity(stored_here.len());
        for (piece, offsets) in pieces {
            let base = level_bytes.len() as u64;
            next_addr_of_pos.extend(offsets.iter().map(|o| base + o));
            level_bytes.extend_from_slice(&piece);
        }
        let mut next_addr_of_rank = vec![SEQUENTIAL; class_counts[level]];
        for (&(rank, _), &offset) in stored_here.iter().zip(&next_addr_of_pos) {
            if level == 0 || counts_here[rank as usize] > 1 {
                next_addr_of_rank[rank as usize] = offset;
            }
        }
        summaries[level] = Some(LevelSummary {
            widths,
            item_count: stored_here.len() as u64,
            is_leaf: false,
            length,
            crc: crc32c::crc32c(&level_bytes),
        });
        bytes[level] = Some(store.keep(level_bytes)?);
        addr_of_pos = Some(next_addr_of_pos);
        addr_of_rank = next_addr_of_rank;
    }
    Ok(EncodedLevels {
        depth,
        levels: summaries
            .into_iter()
            .map(|s| s.expect("laid out"))
            .collect(),
        bytes: bytes.into_iter().map(|b| b.expect("laid out")).collect(),
        store,
        external_passes,
    })
}

/// The bits a reference value needs (at least 1).
fn bits_of(v: u64) -> u32 {
    (64 - v.leading_zeros()).max(1)
}

/// How many items ahead the gathers and scatters into tables in random
/// order (by rank, by ordinal) ask for their cache line: the encoder's
/// time goes mostly to these misses, and they are independent, so asking
/// early overlaps them.
const AHEAD: usize = 16;

/// The address of a class below in [`LevelLayout::addr_of_rank`] that is
/// referenced once: a sequential child, which has no reference of its own.
const SEQUENTIAL: u64 = u64::MAX;

/// What the layout of a level reads of the level below.
struct LevelLayout<'a> {
    /// Address of each shared class below, by rank; [`SEQUENTIAL`] for a
    /// class referenced once (one table, so that a child costs one random
    /// read, not one in its count and one in its address).
    addr_of_rank: &'a [u64],
    /// Address of each stored node below, by position (`None`: the leaf
    /// level, where it is the position).
    addr_of_pos: Option<&'a [u64]>,
}

impl LevelLayout<'_> {
    /// Asks the cache for what [`LevelLayout::record`] of `key` will read.
    #[inline]
    fn prefetch(&self, key: &NodeKey) {
        for &s in &key.slots {
            if s != 0 {
                prefetch(&self.addr_of_rank[((s - 1) >> 3) as usize]);
            }
        }
    }

    /// Calls `reference` with each shared child's reference value in
    /// physical slot order, then with the base reference, if any, of the
    /// record of `key` whose first sequential child is at position `first`.
    /// Returns the child mask.
    fn record(&self, key: &NodeKey, first: u64, mut reference: impl FnMut(u64)) -> u8 {
        let mut mask = 0u8;
        let mut any_seq = false;
        for (p, &s) in key.slots.iter().enumerate() {
            if s == 0 {
                continue;
            }
            mask |= 1 << p;
            let addr = self.addr_of_rank[((s - 1) >> 3) as usize];
            if addr == SEQUENTIAL {
                any_seq = true;
            } else {
                reference((addr << 3) | ((s - 1) & 7));
            }
        }
        if any_seq {
            let b = self
                .addr_of_pos
                .map_or(first, |a| a[usize::try_from(first).expect("a position")]);
            reference(b);
        }
        mask
    }

    /// Appends the record of `key` (§23.2) to `out`.
    fn write(&self, key: &NodeKey, first: u64, widths: [u8; 3], out: &mut Vec<u8>) {
        let code_of = |v: u64| -> (u8, u32) {
            let b = bits_of(v);
            let i = widths
                .iter()
                .position(|&w| u32::from(w) >= b)
                .expect("the widest holds all");
            (i as u8 + 1, u32::from(widths[i]))
        };
        // The shared references in slot order, then the base reference.
        let mut refs = [0u64; 9];
        let mut n = 0usize;
        let mask = self.record(key, first, |v| {
            refs[n] = v;
            n += 1;
        });
        let header = u32::from(mask) | (key.attribute << 8);
        out.extend_from_slice(&header.to_le_bytes());
        let mut w = BitWriter::new(out);
        let mut next = 0usize;
        for &s in &key.slots {
            if s == 0 {
                continue;
            }
            if self.addr_of_rank[((s - 1) >> 3) as usize] == SEQUENTIAL {
                w.put(0, 2);
            } else {
                w.put(u64::from(code_of(refs[next]).0), 2);
                next += 1;
            }
        }
        if next < n {
            // The base reference's code follows the children's.
            w.put(u64::from(code_of(refs[next]).0), 2);
        }
        for &v in &refs[..n] {
            w.put(v, code_of(v).1);
        }
        w.finish();
    }
}

/// The items of `results`, in order, or the error of the first one (by
/// position) that failed. Collected in place, one write an item: a
/// `collect::<Result<Vec<_>, _>>()` of a parallel iterator cannot know the
/// length (it stops at an error), so it fills a list of pieces and copies
/// them into the vector, and a level's forms (235 MB at level 11 of the d14
/// dragon) were written, faulted in and read twice. `placeholder` stands
/// in for a failed item until the error is returned.
fn collect_or_first_error<T: Copy + Send + Sync>(
    results: impl IndexedParallelIterator<Item = Result<T, FormatError>>,
    placeholder: T,
) -> Result<Vec<T>, FormatError> {
    let first_error: std::sync::Mutex<Option<(usize, FormatError)>> = Default::default();
    let mut items = Vec::new();
    results
        .enumerate()
        .map(|(i, r)| {
            r.unwrap_or_else(|e| {
                let mut first = first_error.lock().unwrap_or_else(|p| p.into_inner());
                if first.as_ref().is_none_or(|&(j, _)| i < j) {
                    *first = Some((i, e));
                }
                placeholder
            })
        })
        .collect_into_vec(&mut items);
    match first_error.into_inner().unwrap_or_else(|p| p.into_inner()) {
        Some((_, e)) => Err(e),
        None => Ok(items),
    }
}

/// The leaves, merged and ranked: the canonical masks in rank order, their
/// stabilisers, and each 1.0 leaf's slot value.
#[allow(clippy::type_complexity)]
fn merge_leaves(
    dag: &Dag<'_>,
    leaf_level: usize,
) -> Result<(Vec<u64>, Vec<u8>, Vec<AtomicU64>), FormatError> {
    let n = dag.levels()[leaf_level].node_count;
    let n32 = u32::try_from(n).map_err(|_| {
        FormatError::new(
            ErrorCode::LevelTooLarge,
            0,
            format!("{n} leaves are more than the encoder numbers"),
        )
    })?;
    // A root that is a leaf is stored as it is (§23.6).
    let reflect = leaf_level > 0;
    let mut forms: Vec<(u64, u32, u8)> = collect_or_first_error(
        (0..n32).into_par_iter().map(|i| {
            let mask = dag.leaf(i)?.0;
            let mut best = (mask, i, 0u8);
            if reflect {
                for r in 1..8u8 {
                    let m = reflect_leaf(mask, r);
                    if m < best.0 {
                        best = (m, i, r);
                    }
                }
            }
            Ok(best)
        }),
        (0, 0, 0),
    )?;
    forms.par_sort_unstable_by_key(|f| f.0);
    let slot_at: Vec<AtomicU64> = (0..n).map(|_| AtomicU64::new(0)).collect();
    let (leaves, stabs) = rank_sorted(
        &forms,
        |a, b| a.0 == b.0,
        |f| (f.0, leaf_stab(f.0)),
        |&(_, i, r), rank, &(_, stab)| {
            slot_at[i as usize].store(slot_and_stab(rank, r, stab), Ordering::Relaxed);
        },
        |&(_, i, _)| prefetch(&slot_at[i as usize]),
    );
    Ok((leaves, stabs, slot_at))
}

/// Numbers the classes of `forms`, sorted so that equal forms (`same`) are
/// adjacent, by their order: returns each class's two parts made by `class`
/// from its first form, in rank order, and calls `assign` with each form,
/// the rank of its class and the class's parts (and `ahead` with the form
/// [`AHEAD`] places later, to prefetch what `assign` will write). In
/// parallel chunks (the ranks at each chunk's start counted first); the
/// result does not depend on the chunks.
fn rank_sorted<F: Sync, A: Send + Sync + Copy, B: Send + Sync + Copy>(
    forms: &[F],
    same: impl Fn(&F, &F) -> bool + Sync,
    class: impl Fn(&F) -> (A, B) + Sync,
    assign: impl Fn(&F, usize, &(A, B)) + Sync,
    ahead: impl Fn(&F) + Sync,
) -> (Vec<A>, Vec<B>) {
    let starts_class = |i: usize| i == 0 || !same(&forms[i - 1], &forms[i]);
    let new_classes: Vec<usize> = forms
        .par_chunks(LAYOUT_CHUNK)
        .enumerate()
        .map(|(ci, chunk)| {
            (0..chunk.len())
                .filter(|&j| starts_class(ci * LAYOUT_CHUNK + j))
                .count()
        })
        .collect();
    let mut first_rank = Vec::with_capacity(new_classes.len());
    let mut total = 0usize;
    for n in &new_classes {
        first_rank.push(total);
        total += n;
    }
    let parts: Vec<(Vec<A>, Vec<B>)> = forms
        .par_chunks(LAYOUT_CHUNK)
        .enumerate()
        .map(|(ci, chunk)| {
            let mut a = Vec::with_capacity(new_classes[ci]);
            let mut b = Vec::with_capacity(new_classes[ci]);
            // The class of the form before the chunk continues into it.
            let mut rank = first_rank[ci].wrapping_sub(1);
            let mut current = (ci > 0).then(|| class(&forms[ci * LAYOUT_CHUNK - 1]));
            for (j, f) in chunk.iter().enumerate() {
                if let Some(later) = chunk.get(j + AHEAD) {
                    ahead(later);
                }
                if starts_class(ci * LAYOUT_CHUNK + j) {
                    rank = rank.wrapping_add(1);
                    let parts = class(f);
                    a.push(parts.0);
                    b.push(parts.1);
                    current = Some(parts);
                }
                assign(f, rank, current.as_ref().expect("a class started"));
            }
            (a, b)
        })
        .collect();
    let mut a = Vec::with_capacity(total);
    let mut b = Vec::with_capacity(total);
    for (pa, pb) in parts {
        a.extend_from_slice(&pa);
        b.extend_from_slice(&pb);
    }
    (a, b)
}

/// Where the records of a 1.0 node level start: a bit per word, set at each
/// record's first word, and the starts before each block of 64 words, so
/// that a pointer (a word) becomes the ordinal of its node with two reads of
/// small tables. The merge's tables by node are then by ordinal, 4–6 times
/// smaller than tables by word (a record is 1 + its pointers' words), and so
/// are the random reads and writes into them.
#[derive(Debug)]
struct RecordStarts {
    /// Bit `w % 64` of block `w / 64`: a record starts at word `w`.
    bits: Vec<u64>,
    /// Records starting before each block.
    before: Vec<u32>,
}

impl RecordStarts {
    /// The ordinal of the record starting at word `w`, if one does.
    #[inline]
    fn ordinal(&self, w: u32) -> Option<usize> {
        let (block, bit) = ((w / 64) as usize, w % 64);
        let bits = *self.bits.get(block)?;
        (bits >> bit & 1 != 0).then(|| {
            self.before[block] as usize + (bits & ((1u64 << bit) - 1)).count_ones() as usize
        })
    }
}

/// Interior level `level`, merged and ranked through `slot_at` (the slot
/// value and class stabiliser of each node of the level below by ordinal,
/// its record found through `child_starts`, or of each leaf by its index
/// when `child_starts` is `None`) and the stabilisers of the classes below
/// (`child_stabs`, by rank): the ranked keys, their stabilisers, the slot
/// value and stabiliser of each 1.0 node of this level by ordinal, and
/// where its records start.
#[allow(clippy::type_complexity)]
fn merge_level(
    dag: &Dag<'_>,
    level: usize,
    slot_at: &[AtomicU64],
    child_starts: Option<&RecordStarts>,
    child_stabs: &[u8],
) -> Result<(Vec<NodeKey>, Vec<u8>, Vec<AtomicU64>, RecordStarts), FormatError> {
    let section = &dag.levels()[level];
    let units = section.units();
    let level8 = level as u8;
    // The node starts: each record's size is in its header's child mask (a
    // table of the sizes by mask, in words, for this serial walk).
    let words_of: [u64; 256] = std::array::from_fn(|mask| {
        crate::layout::node_record_size((mask as u8).count_ones(), section.pointer_width) / 4
    });
    let mut starts: Vec<u32> = Vec::with_capacity(section.node_count as usize);
    let mut bits = vec![0u64; units.div_ceil(64) as usize];
    let mut word = 0u64;
    while word < units {
        let w = u32::try_from(word).expect("a 1.0 level has fewer than 2^32 words");
        starts.push(w);
        bits[(w / 64) as usize] |= 1 << (w % 64);
        word += words_of[usize::from(section.bytes[4 * w as usize])];
    }
    if word > units {
        // The last record runs past the level: the reader says how.
        dag.node(level8, *starts.last().expect("a record started"))?;
    }
    let mut before = Vec::with_capacity(bits.len());
    let mut count = 0u32;
    for b in &bits {
        before.push(count);
        count += b.count_ones();
    }
    let record_starts = RecordStarts { bits, before };
    let slot_bits = PackedKey::slot_bits(child_stabs.len());
    let ordinal_of = |p: u32| match child_starts {
        Some(starts) => starts.ordinal(p),
        None => Some(p as usize),
    };
    let no_form = Form {
        key: PackedKey([0; 5]),
        node: 0,
        reflection: 0,
        stab: 0,
    };
    let mut forms: Vec<Form> = collect_or_first_error(
        starts.par_iter().enumerate().map(|(i, &w)| {
            // The children of the node AHEAD places on, asked for early.
            if let Some(node) = starts
                .get(i + AHEAD)
                .and_then(|&a| dag.node(level8, a).ok())
            {
                for k in 0..node.child_mask().count_ones() {
                    if let Some(s) = ordinal_of(node.pointer_at(k)).and_then(|o| slot_at.get(o)) {
                        prefetch(s);
                    }
                }
            }
            let node = dag.node(level8, w)?;
            let mut key = NodeKey {
                slots: [0; 8],
                attribute: node.attribute(),
            };
            // The children's stabilisers, by slot (1 where none is).
            let mut stabs = [1u8; 8];
            let mut rank = 0;
            for slot in 0..8u32 {
                if node.child_mask() >> slot & 1 != 0 {
                    let p = node.pointer_at(rank);
                    rank += 1;
                    let s = ordinal_of(p)
                        .and_then(|o| slot_at.get(o))
                        .map_or(0, |s| s.load(Ordering::Relaxed));
                    if s == 0 {
                        return Err(FormatError::new(
                            ErrorCode::PointerOutOfRange,
                            section.file_offset + u64::from(w) * 4,
                            format!("level {level}: pointer {p} names no node"),
                        ));
                    }
                    key.slots[slot as usize] = s & ((1 << STAB_SHIFT) - 1);
                    stabs[slot as usize] = (s >> STAB_SHIFT) as u8;
                }
            }
            if level == 0 {
                // The root is stored as it is (§23.6).
                return Ok(Form {
                    key: PackedKey::pack(&key, slot_bits),
                    node: i as u32,
                    reflection: 0,
                    stab: 1,
                });
            }
            Ok(least_form(&key, &stabs, i as u32, slot_bits))
        }),
        no_form,
    )?;
    forms.par_sort_unstable_by(|a, b| a.key.cmp(&b.key));
    // The level above reads these by ordinal; the root has no level above.
    let next_slot_at: Vec<AtomicU64> = (0..if level > 0 { starts.len() } else { 0 })
        .map(|_| AtomicU64::new(0))
        .collect();
    let (keys, stabs) = rank_sorted(
        &forms,
        |a, b| a.key == b.key,
        |f| (f.key.unpack(slot_bits), f.stab),
        |f, rank, _| {
            if level > 0 {
                next_slot_at[f.node as usize]
                    .store(slot_and_stab(rank, f.reflection, f.stab), Ordering::Relaxed);
            }
        },
        |f| {
            if level > 0 {
                prefetch(&next_slot_at[f.node as usize]);
            }
        },
    );
    Ok((keys, stabs, next_slot_at, record_starts))
}

/// The reference widths of node level `level` from the histogram of its
/// references' bit lengths (§23.2), or the error of a level whose
/// references need more than the widest width.
fn level_widths(hist: &[u64; 65], level: usize) -> Result<[u8; 3], FormatError> {
    best_widths(hist).ok_or_else(|| {
        FormatError::new(
            ErrorCode::LevelTooLarge,
            0,
            format!(
                "level {level}: a reference needs more than {} bits",
                crate::v2::MAX_WIDTH
            ),
        )
    })
}

/// Adds each reference of `keys` to the count of the class it names in the
/// level below (a slot holds `1 + 8 * rank + r`, 0 for no child).
fn count_references(keys: &[NodeKey], counts: &[AtomicU32]) {
    keys.par_iter().for_each(|key| {
        for &s in &key.slots {
            if s != 0 {
                counts[((s - 1) >> 3) as usize].fetch_add(1, Ordering::Relaxed);
            }
        }
    });
}

/// The shared classes of a level (referenced more than once), in their
/// stored order (§23.7): by reference count, most first, then by rank; each
/// stored without a reflection. The sequential classes follow them, by
/// parent.
pub(crate) fn shared_by_count(counts: &[u32]) -> Vec<(u32, u8)> {
    let mut shared: Vec<(u32, u8)> = (0..counts.len() as u32)
        .filter(|&i| counts[i as usize] > 1)
        .map(|i| (i, 0))
        .collect();
    shared.par_sort_unstable_by(|a, b| {
        counts[b.0 as usize]
            .cmp(&counts[a.0 as usize])
            .then(a.0.cmp(&b.0))
    });
    shared
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::AttributeKind;
    use crate::builder::DagBuilder;
    use proptest::prelude::*;

    /// Voxels with mirrored solid blocks: shared, symmetric subtrees.
    fn scene(depth: u8, voxels: &[(u32, u32, u32)], blocks: &[(u32, u32, u32)]) -> Vec<[u32; 3]> {
        let res = 1u32 << depth;
        let mut vs: Vec<[u32; 3]> = voxels
            .iter()
            .map(|&(x, y, z)| [x % res, y % res, z % res])
            .collect();
        for &(bx, by, bz) in blocks {
            for d in 0..4 {
                vs.push([(bx * 4 + d) % res, (by * 4) % res, (bz * 4 + d) % res]);
                vs.push([
                    res - 1 - (bx * 4 + d) % res,
                    (by * 4) % res,
                    (bz * 4 + d) % res,
                ]);
                vs.push([(bx * 4 + d) % res, res - 1 - (by * 4) % res, (bz * 4) % res]);
            }
        }
        vs
    }

    /// A key whose slot values fit `slot_bits` bits, from raw draws.
    fn key_within(slot_bits: u32, slots: [u64; 8], attribute: u32) -> NodeKey {
        let max = (1u64 << slot_bits) - 1;
        NodeKey {
            slots: slots.map(|s| s & max),
            attribute,
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        // Packed keys give the key back and sort (and compare equal) as the
        // keys do, at every slot width the encoder uses.
        #[test]
        fn packed_keys_keep_the_keys_order(
            slot_bits in 1u32..=36,
            a in proptest::array::uniform8(any::<u64>()),
            b in proptest::array::uniform8(any::<u64>()),
            shared in 0usize..=8,
            attributes in (any::<u32>(), any::<u32>()),
        ) {
            let ka = key_within(slot_bits, a, attributes.0);
            let mut kb = key_within(slot_bits, b, attributes.1);
            // Keys that agree on their first slots, to reach the later fields.
            kb.slots[..shared].copy_from_slice(&ka.slots[..shared]);
            if shared == 8 && attributes.0 % 2 == 0 {
                kb.attribute = ka.attribute;
            }
            let (pa, pb) = (PackedKey::pack(&ka, slot_bits), PackedKey::pack(&kb, slot_bits));
            prop_assert_eq!(pa.unpack(slot_bits), ka);
            prop_assert_eq!(pb.unpack(slot_bits), kb);
            prop_assert_eq!(pa.cmp(&pb), ka.cmp(&kb));
            prop_assert_eq!(pa == pb, ka == kb);
        }
    }

    #[test]
    fn collecting_gives_the_items_in_order_or_the_first_error() {
        let n = 100_000u32;
        let all = collect_or_first_error((0..n).into_par_iter().map(Ok), 0).unwrap();
        assert_eq!(all, (0..n).collect::<Vec<_>>());
        // Several failures: the error of the lowest position, on any pool.
        let failing = |i: u32| {
            if i % 7919 == 5000 {
                Err(FormatError::new(
                    ErrorCode::PointerOutOfRange,
                    u64::from(i),
                    "no",
                ))
            } else {
                Ok(i)
            }
        };
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let e = pool
                .install(|| collect_or_first_error((0..n).into_par_iter().map(failing), 0))
                .unwrap_err();
            assert_eq!(e.offset, 5000);
        }
    }

    #[test]
    fn the_widest_slots_fit_the_packed_key() {
        // Ranks below 2^32: the largest slot value is 2^35, 36 bits.
        let bits = PackedKey::slot_bits(1 << 32);
        assert_eq!(bits, 36);
        let key = NodeKey {
            slots: [1 << 35; 8],
            attribute: u32::MAX,
        };
        assert_eq!(PackedKey::pack(&key, bits).unpack(bits), key);
        assert_eq!(PackedKey::slot_bits(1), 4);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        // The parallel encoder writes the reference encoder's bytes, on one
        // thread or several, in memory or with every table spilled; and the
        // streamed file is `upgrade`'s.
        #[test]
        fn parallel_spilled_and_serial_encodings_are_equal(
            depth in 2u8..=7,
            voxels in proptest::collection::vec((0u32..128, 0u32..128, 0u32..128), 0..600),
            blocks in proptest::collection::vec((0u32..16, 0u32..16, 0u32..16), 0..8),
            kind in prop_oneof![Just(AttributeKind::VoxelCount), Just(AttributeKind::None)],
        ) {
            let vs = scene(depth, &voxels, &blocks);
            let bytes = DagBuilder::from_voxels(depth, kind, vs).unwrap().to_bytes();
            let dag = Dag::open(&bytes).unwrap();
            let serial = crate::v2::encode_serial(&dag).unwrap();
            prop_assert_eq!(&crate::v2::encode(&dag).unwrap(), &serial);
            let one_thread = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
            let three_threads = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
            for pool in [&one_thread, &three_threads] {
                prop_assert_eq!(&pool.install(|| crate::v2::encode(&dag)).unwrap(), &serial);
            }
            let dir = tempfile::tempdir().unwrap();
            let spill_all = EncodeOptions {
                memory_budget: Some(0),
                refuse_below_least: false,
                scratch_dir: Some(dir.path().to_path_buf()),
            };
            let spilled = encode_levels(&dag, &spill_all).unwrap();
            prop_assert_eq!(spilled.spilled_bytes() > 0, !dag.is_empty());
            // No room at all: every pass but the root's merge out of core.
            let leaf_level = usize::from(dag.leaf_level());
            prop_assert_eq!(
                spilled.external_passes(),
                if dag.is_empty() { 0 } else { (3 * leaf_level).max(1) }
            );
            prop_assert_eq!(&spilled.into_encoded().unwrap(), &serial);
            for pool in [&one_thread, &three_threads] {
                let spilled = pool.install(|| encode_levels(&dag, &spill_all)).unwrap();
                prop_assert_eq!(&spilled.into_encoded().unwrap(), &serial);
            }
            let upgraded = crate::v2file::upgrade(&dag).unwrap();
            let mut streamed = Vec::new();
            crate::v2file::upgrade_to(&dag, &spill_all, &mut streamed).unwrap();
            prop_assert_eq!(streamed, upgraded);
            // The scratch file is unnamed: nothing is left in its directory.
            prop_assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        }
    }

    #[test]
    fn a_budget_between_nothing_and_everything_spills_some_tables() {
        let vs = scene(
            7,
            &[(3, 9, 100), (50, 60, 70), (127, 0, 64)],
            &[(1, 2, 3), (9, 9, 9), (15, 0, 7)],
        );
        let bytes = DagBuilder::from_voxels(7, AttributeKind::VoxelCount, vs)
            .unwrap()
            .to_bytes();
        let dag = Dag::open(&bytes).unwrap();
        let serial = crate::v2::encode_serial(&dag).unwrap();
        let all = encode_levels(&dag, &EncodeOptions::default()).unwrap();
        assert_eq!(all.spilled_bytes(), 0);
        let dir = tempfile::tempdir().unwrap();
        let everything = encode_levels(
            &dag,
            &EncodeOptions {
                memory_budget: Some(0),
                refuse_below_least: false,
                scratch_dir: Some(dir.path().to_path_buf()),
            },
        )
        .unwrap()
        .spilled_bytes();
        // The working set of the largest level, plus room for a few tables.
        let work = working_set(&dag);
        let some = encode_levels(
            &dag,
            &EncodeOptions {
                memory_budget: Some(work + everything / 3),
                refuse_below_least: false,
                scratch_dir: Some(dir.path().to_path_buf()),
            },
        )
        .unwrap();
        assert!(
            some.spilled_bytes() > 0 && some.spilled_bytes() < everything,
            "{} of {everything}",
            some.spilled_bytes()
        );
        assert_eq!(some.external_passes(), 0);
        assert_eq!(some.into_encoded().unwrap(), serial);
    }

    /// A DAG of `depth` from `n` random voxels, half of them in mirrored
    /// blocks.
    fn random_dag(depth: u8, n: usize, seed: u64) -> Vec<u8> {
        let mut x = seed;
        let mut next = move || {
            x = x
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (x >> 33) as u32
        };
        let voxels: Vec<(u32, u32, u32)> = (0..n).map(|_| (next(), next(), next())).collect();
        // Block coordinates are multiplied by 4 in `scene`: keep them small.
        let blocks: Vec<(u32, u32, u32)> = (0..n / 24)
            .map(|_| (next() >> 4, next() >> 4, next() >> 4))
            .collect();
        let vs = scene(depth, &voxels, &blocks);
        DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, vs)
            .unwrap()
            .to_bytes()
    }

    #[test]
    fn budgets_between_the_levels_take_the_large_passes_out_of_core() {
        for (depth, n, seed) in [(8u8, 6000, 1u64), (10, 20_000, 2), (9, 3000, 3)] {
            let bytes = random_dag(depth, n, seed);
            let dag = Dag::open(&bytes).unwrap();
            let serial = crate::v2::encode_serial(&dag).unwrap();
            let leaf_level = usize::from(dag.leaf_level());
            let passes = 3 * leaf_level + 1;
            // Budgets at each level's merge working set: the levels above it
            // fit, the larger ones go out of core, within what is left.
            let mut budgets: Vec<u64> = (0..=leaf_level).map(|l| merge_work(&dag, l)).collect();
            budgets.sort_unstable();
            budgets.dedup();
            let dir = tempfile::tempdir().unwrap();
            let one_thread = rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .build()
                .unwrap();
            let two_threads = rayon::ThreadPoolBuilder::new()
                .num_threads(2)
                .build()
                .unwrap();
            let mut mixed = 0;
            for &b in &budgets {
                let options = EncodeOptions {
                    memory_budget: Some(b),
                    refuse_below_least: false,
                    scratch_dir: Some(dir.path().to_path_buf()),
                };
                for pool in [&one_thread, &two_threads] {
                    let encoded = pool.install(|| encode_levels(&dag, &options)).unwrap();
                    let external = encoded.external_passes();
                    assert!(external < passes, "depth {depth}, budget {b}");
                    if external > 0 {
                        mixed += 1;
                    }
                    assert!(
                        encoded.into_encoded().unwrap() == serial,
                        "depth {depth}, budget {b}, {external} passes out of core"
                    );
                }
            }
            assert!(
                mixed > 0,
                "depth {depth}: no budget took a pass out of core"
            );
            assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        }
    }
}
