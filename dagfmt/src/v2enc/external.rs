//! The encoder's passes for a level whose working set does not fit the
//! memory budget (the passes in memory hold a whole level's forms, keys
//! and records at once).
//!
//! - **Merge and rank**: an external sort. The level's forms are made a
//!   chunk at a time (the chunk sized to the room left in the budget),
//!   each chunk is sorted in parallel and written as a run (form and 1.0
//!   node ordinal) to an unnamed scratch file, and the runs are merged
//!   k-way, so that equal forms come out adjacent and the classes in rank
//!   order. A class's rank is its position among the distinct sorted forms,
//!   as in memory, so the ranks (and the output) are the same by
//!   construction. The ranked keys go to the store's scratch file as they
//!   come out; what is held is a rank (u32) and a reflection (u8) per 1.0
//!   node, the stabilisers (u8 per class) and, for the level above, a bit
//!   per 1.0 word marking the node starts with a u32 count per 64 words
//!   (the ordinal of the node at a word) instead of 8 bytes per word.
//! - **Order**: the reference counts from the ranked keys read a chunk at a
//!   time; the keys in stored order gathered a chunk of positions at a
//!   time from chunks of ranks read back in turn, and written out as they
//!   are finished. Held: the stored order and the first sequential child
//!   per node of the level (8 + 8 bytes), the counts, stabilisers and the
//!   order of the level below (4 + 1 + 8 bytes per class below, the order
//!   counted twice: it grows by pushes).
//! - **Layout**: the records made a chunk at a time, twice (the widths'
//!   histogram, then the bytes, which go to the scratch file as they come
//!   with their CRC-32C). Held: the addresses by rank and position of the
//!   level below and of this level (8 bytes each).
//!
//! Each pass sizes its chunks to the room it is given from what it holds
//! ([`PassMemory`]: bytes whatever the chunks, buffers, bytes per item of a
//! chunk); with its least chunks that is the encoder's least
//! ([`least_for_merge`], [`least_for_order_and_layout`]).

use std::cmp::Ordering as CmpOrdering;
use std::collections::BinaryHeap;
use std::marker::PhantomData;
use std::ops::Range;

use super::*;

/// Fewest items in a chunk of an external pass (small, so that the tests'
/// small levels take several chunks).
const MIN_CHUNK: usize = 16;

/// Most sorted runs of one level: the chunk grows past the budget's room
/// rather than merging more (each run needs a read buffer).
const MAX_RUNS: usize = 256;

/// Most chunks of positions (or ranks) in the order pass: the gather reads
/// every rank chunk once per position chunk.
const MAX_GATHER_CHUNKS: usize = 8;

/// Bytes of read buffer shared by the runs of a merge.
const MERGE_BUFFER: usize = 16 << 20;

/// The slot values (§23.6) of a level's 1.0 nodes, which the level above
/// reads by pointer.
#[derive(Debug)]
pub(super) enum Slots {
    /// By node ordinal (by index for the leaves): the slot value and the
    /// class stabiliser of each node (`slot_and_stab`), the table of the
    /// merge in memory; `starts` names the node starting at a word (`None`:
    /// the leaves, whose pointers are their ordinals).
    ByOrdinal {
        slot_at: Vec<AtomicU64>,
        starts: Option<RecordStarts>,
    },
    /// By node ordinal: the rank of each node's class and its normalised
    /// reflection, the table of the merge out of core (5 bytes a node, not
    /// 8: the stabilisers are read by rank); `starts` as above.
    ByNode {
        starts: Option<RecordStarts>,
        rank: Vec<u32>,
        reflection: Vec<u8>,
    },
}

impl Slots {
    /// No table (a placeholder while one is taken).
    pub(super) fn none() -> Slots {
        Slots::ByNode {
            starts: None,
            rank: Vec::new(),
            reflection: Vec::new(),
        }
    }

    /// The slot value of the node at pointer `p` with its class stabiliser
    /// (as `slot_and_stab` makes them; `child_stabs`: the stabilisers of the
    /// classes by rank); 0 where no node starts.
    fn get(&self, p: u32, child_stabs: &[u8]) -> u64 {
        let ordinal = |starts: &Option<RecordStarts>| match starts {
            None => Some(p as usize),
            Some(index) => index.ordinal(p),
        };
        match self {
            Slots::ByOrdinal { slot_at, starts } => ordinal(starts)
                .and_then(|i| slot_at.get(i))
                .map_or(0, |s| s.load(Ordering::Relaxed)),
            Slots::ByNode {
                starts,
                rank,
                reflection,
            } => match ordinal(starts).and_then(|i| Some((*rank.get(i)?, reflection[i]))) {
                Some((r, t)) => by_ordinal(r, t, child_stabs),
                None => 0,
            },
        }
    }

    /// Bytes held.
    pub(super) fn bytes(&self) -> u64 {
        let index = |starts: &Option<RecordStarts>| starts.as_ref().map_or(0, RecordStarts::bytes);
        match self {
            Slots::ByOrdinal { slot_at, starts } => 8 * slot_at.len() as u64 + index(starts),
            Slots::ByNode { starts, rank, .. } => 5 * rank.len() as u64 + index(starts),
        }
    }

    /// The table by ordinal and the record starts that the merge in memory
    /// reads; `child_stabs`: the stabilisers of the classes, by rank.
    pub(super) fn into_by_ordinal(
        self,
        child_stabs: &[u8],
    ) -> (Vec<AtomicU64>, Option<RecordStarts>) {
        match self {
            Slots::ByOrdinal { slot_at, starts } => (slot_at, starts),
            Slots::ByNode {
                starts,
                rank,
                reflection,
            } => {
                let slot_at = rank
                    .par_iter()
                    .zip(&reflection)
                    .map(|(&r, &t)| AtomicU64::new(by_ordinal(r, t, child_stabs)))
                    .collect();
                (slot_at, starts)
            }
        }
    }
}

/// The value of [`Slots::ByOrdinal`] for a node of class `rank` reached by
/// normalised reflection `t` (already normalised, and normalising again
/// changes nothing).
fn by_ordinal(rank: u32, t: u8, child_stabs: &[u8]) -> u64 {
    slot_and_stab(rank as usize, t, child_stabs[rank as usize])
}

impl RecordStarts {
    /// No record start yet in a level of `units` words.
    fn new(units: u64) -> RecordStarts {
        RecordStarts {
            bits: vec![0; units.div_ceil(64) as usize],
            before: Vec::new(),
        }
    }

    fn mark(&mut self, word: u64) {
        self.bits[(word / 64) as usize] |= 1 << (word % 64);
    }

    /// Counts the starts before each block, once every start is marked.
    fn finish(&mut self) {
        let mut total = 0u32;
        self.before = self
            .bits
            .iter()
            .map(|b| {
                let before = total;
                total += b.count_ones();
                before
            })
            .collect();
    }

    /// Bytes held.
    fn bytes(&self) -> u64 {
        12 * self.bits.len() as u64
    }

    /// Bytes held over a level of `units` words.
    fn bytes_for(units: u64) -> u64 {
        record_starts_bytes(units)
    }
}

/// A table being appended to the scratch file, piece by piece; finished by
/// [`Store::finish`]. One at a time, and no other table is kept meanwhile.
pub(super) struct TableWriter<T> {
    at: u64,
    items: usize,
    item: PhantomData<T>,
}

impl Store {
    /// Starts a table written to the scratch file as it is made.
    pub(super) fn begin<T: Item>(&mut self) -> TableWriter<T> {
        TableWriter {
            at: self.end,
            items: 0,
            item: PhantomData,
        }
    }

    /// Appends `items` to the table `writer` writes.
    pub(super) fn append<T: Item>(
        &mut self,
        writer: &mut TableWriter<T>,
        items: &[T],
    ) -> io::Result<()> {
        debug_assert_eq!(writer.at + (writer.items * T::BYTES) as u64, self.end);
        let at = self.end;
        let file = self.file()?;
        file.seek(SeekFrom::Start(at))?;
        let mut buf = Vec::with_capacity(PIECE + T::BYTES);
        for piece in items.chunks((PIECE / T::BYTES).max(1)) {
            buf.clear();
            for x in piece {
                x.put(&mut buf);
            }
            file.write_all(&buf)?;
        }
        self.end += (items.len() * T::BYTES) as u64;
        writer.items += items.len();
        Ok(())
    }

    /// The table `writer` wrote.
    pub(super) fn finish<T>(&mut self, writer: TableWriter<T>) -> Table<T> {
        Table::Spilled {
            at: writer.at,
            items: writer.items,
        }
    }

    /// Items `range` of `table`, without taking it.
    fn read_range<T: Item>(&mut self, table: &Table<T>, range: Range<usize>) -> io::Result<Vec<T>> {
        match *table {
            Table::Held(ref v) => Ok(v[range].to_vec()),
            Table::Spilled { at, items } => {
                assert!(range.end <= items, "a range of the table");
                let mut out = Vec::with_capacity(range.len());
                self.read_pieces(
                    at + (range.start * T::BYTES) as u64,
                    range.len() * T::BYTES,
                    T::BYTES,
                    |piece| {
                        out.extend(piece.chunks_exact(T::BYTES).map(T::get));
                        Ok(())
                    },
                )?;
                Ok(out)
            }
        }
    }
}

impl<T> Table<T> {
    /// Items in the table.
    pub(super) fn len(&self) -> usize {
        match self {
            Table::Held(v) => v.len(),
            Table::Spilled { items, .. } => *items,
        }
    }
}

/// A form that an external sort writes in runs.
trait RunForm: Item {
    /// The order of the sort; equal forms are one class.
    fn order(&self, other: &Self) -> CmpOrdering;
}

/// A leaf's least mask, its ordinal and the reflection reaching the mask.
type LeafForm = (u64, u32, u8);

impl Item for LeafForm {
    const BYTES: usize = 13;
    fn put(&self, out: &mut Vec<u8>) {
        self.0.put(out);
        self.1.put(out);
        out.push(self.2);
    }
    fn get(bytes: &[u8]) -> Self {
        (u64::get(bytes), u32::get(&bytes[8..]), bytes[12])
    }
}

impl RunForm for LeafForm {
    fn order(&self, other: &Self) -> CmpOrdering {
        self.0.cmp(&other.0)
    }
}

impl Item for Form {
    const BYTES: usize = 40 + 6;
    fn put(&self, out: &mut Vec<u8>) {
        for word in self.key.0 {
            word.put(out);
        }
        self.node.put(out);
        out.push(self.reflection);
        out.push(self.stab);
    }
    fn get(bytes: &[u8]) -> Self {
        let k = 40;
        Form {
            key: PackedKey(std::array::from_fn(|i| u64::get(&bytes[8 * i..]))),
            node: u32::get(&bytes[k..]),
            reflection: bytes[k + 4],
            stab: bytes[k + 5],
        }
    }
}

impl RunForm for Form {
    fn order(&self, other: &Self) -> CmpOrdering {
        self.key.cmp(&other.key)
    }
}

/// A run's next form in the merge's heap (least first, then by run).
struct Head<F> {
    form: F,
    run: usize,
}

impl<F: RunForm> PartialEq for Head<F> {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == CmpOrdering::Equal
    }
}

impl<F: RunForm> Eq for Head<F> {}

impl<F: RunForm> PartialOrd for Head<F> {
    fn partial_cmp(&self, other: &Self) -> Option<CmpOrdering> {
        Some(self.cmp(other))
    }
}

impl<F: RunForm> Ord for Head<F> {
    fn cmp(&self, other: &Self) -> CmpOrdering {
        // Reversed: the heap pops its greatest.
        other.form.order(&self.form).then(other.run.cmp(&self.run))
    }
}

/// A sorted run in the runs' file, read a buffer at a time.
struct Run {
    /// Byte of the run's next unread item in the file.
    next: u64,
    /// Items not yet read from the file.
    left: usize,
    buf: Vec<u8>,
    pos: usize,
}

impl Run {
    fn pop<F: Item>(&mut self, file: &mut File, capacity: usize) -> io::Result<Option<F>> {
        if self.pos == self.buf.len() {
            if self.left == 0 {
                return Ok(None);
            }
            let n = capacity.min(self.left);
            self.buf.resize(n * F::BYTES, 0);
            file.seek(SeekFrom::Start(self.next))?;
            file.read_exact(&mut self.buf)?;
            self.next += (n * F::BYTES) as u64;
            self.left -= n;
            self.pos = 0;
        }
        let form = F::get(&self.buf[self.pos..]);
        self.pos += F::BYTES;
        Ok(Some(form))
    }
}

/// Creates an unnamed scratch file in `dir` (default: the system's
/// temporary directory).
fn scratch_file(dir: &Option<PathBuf>) -> io::Result<File> {
    let dir = dir.clone().unwrap_or_else(std::env::temp_dir);
    tempfile::tempfile_in(&dir).map_err(|e| {
        io::Error::new(
            e.kind(),
            format!("cannot create a scratch file in {}: {e}", dir.display()),
        )
    })
}

/// Items per chunk: what `room` bytes hold at `bytes` each, at least
/// `MIN_CHUNK` and at least `n / most` (so that there are at most `most`
/// chunks: the least the pass needs).
fn chunk_items(n: usize, room: u64, bytes: usize, most: usize) -> usize {
    let fit = usize::try_from(room / bytes.max(1) as u64).unwrap_or(usize::MAX);
    fit.max(n.div_ceil(most)).max(MIN_CHUNK)
}

/// What an out-of-core pass over `n` items holds: `held` bytes whatever its
/// chunks (its tables by node or class), `fixed` bytes of buffers, and
/// `per_item` bytes per item of a chunk, with at most `most` chunks.
#[derive(Clone, Copy, Debug)]
pub(super) struct PassMemory {
    n: usize,
    held: u64,
    fixed: u64,
    per_item: u64,
    most: usize,
}

impl PassMemory {
    /// Items per chunk within `room` bytes (see [`chunk_items`]).
    fn chunk(&self, room: u64) -> usize {
        let spare = room.saturating_sub(self.held + self.fixed);
        chunk_items(self.n, spare, self.per_item as usize, self.most)
    }

    /// The least the pass holds, with its least chunks: more than a budget
    /// below it, which the pass then exceeds.
    pub(super) fn least(&self) -> u64 {
        let chunk = self.n.div_ceil(self.most).max(MIN_CHUNK).min(self.n) as u64;
        self.held + self.fixed + chunk * self.per_item
    }
}

/// The buffers of an out-of-core merge of `n` forms of `bytes` bytes in
/// the runs' file: the runs' write piece and read buffers (at most all the
/// runs), the store's write piece and the pending ranked keys.
fn merge_buffers(n: usize, bytes: usize) -> u64 {
    (PIECE + bytes + MERGE_BUFFER.min(n * bytes) + PIECE + PENDING) as u64
}

/// The out-of-core merge of `n` leaves: a rank (4 bytes) and a reflection
/// (1) per leaf and a stabiliser per class (pushed: at most 2 a leaf); a
/// chunk's forms collected in parallel (3 × 16 bytes a form); the runs'
/// write piece, read buffers and the pending masks, and the store's piece.
pub(super) fn merge_leaves_memory(n: usize) -> PassMemory {
    PassMemory {
        n,
        held: 7 * n as u64,
        fixed: merge_buffers(n, LeafForm::BYTES),
        per_item: 3 * std::mem::size_of::<LeafForm>() as u64,
        most: MAX_RUNS,
    }
}

/// The out-of-core merge of a level of `n` 1.0 nodes and `units` words:
/// as the leaves' ([`merge_leaves_memory`]) with the record starts of the
/// level, and per item of a chunk its start word (4) and its form collected
/// in parallel (3 × 48). Not counted: the tables of the level below it
/// reads.
pub(super) fn merge_level_memory(n: usize, units: u64) -> PassMemory {
    PassMemory {
        n,
        held: 7 * n as u64 + RecordStarts::bytes_for(units),
        fixed: merge_buffers(n, <Form as Item>::BYTES),
        per_item: 4 + 3 * std::mem::size_of::<Form>() as u64,
        most: MAX_RUNS,
    }
}

/// The out-of-core order of a level of `classes` classes over `below`:
/// the stabilisers (1 byte), counts (4) and order (pushed: 2 × 8) of the
/// classes below; the stored order and the first sequential children of
/// this level (8 + 8); a chunk of keys as stored and one of ranked keys
/// read back (72 + 72 bytes an item); the store's read and write pieces.
pub(super) fn order_memory(classes: usize, below: usize) -> PassMemory {
    PassMemory {
        n: classes,
        held: 21 * below as u64 + 16 * classes as u64,
        fixed: 2 * PIECE as u64,
        per_item: 2 * std::mem::size_of::<NodeKey>() as u64,
        most: MAX_GATHER_CHUNKS,
    }
}

/// The out-of-core layout of a level of `n` records: their addresses by
/// position and by rank (8 + 8 bytes); per record of a chunk its key and
/// first sequential child read back (72 + 8), its offset (8) and its bytes
/// (pushed: twice at most [`RECORD_BYTES_MAX`]); the store's pieces. Not
/// counted: what it reads of the level below, the stored order and counts.
pub(super) fn layout_memory(n: usize) -> PassMemory {
    PassMemory {
        n,
        held: 16 * n as u64,
        fixed: 2 * PIECE as u64,
        per_item: std::mem::size_of::<NodeKey>() as u64 + 8 + 8 + 2 * RECORD_BYTES_MAX,
        most: MAX_RUNS,
    }
}

/// The least the merge holds for `dag`, whatever the budget: the largest,
/// over the levels, of what its out-of-core pass holds with its least
/// chunks, with the tables of the level below it reads (a stabiliser for
/// each of at most as many classes as 1.0 nodes), and of the root's merge
/// in memory.
pub(super) fn least_for_merge(dag: &Dag<'_>) -> u64 {
    let levels = dag.levels();
    let leaf_level = usize::from(dag.leaf_level());
    let n = |l: usize| levels[l].node_count as usize;
    let mut least = merge_leaves_memory(n(leaf_level)).least();
    for l in 0..leaf_level {
        let below = &levels[l + 1];
        // The table by node of the level below as an out-of-core merge
        // leaves it (5 bytes a node) and its classes' stabilisers.
        let starts_below = if below.is_leaf {
            0
        } else {
            RecordStarts::bytes_for(below.units())
        };
        let slots_below = 5 * n(l + 1) as u64 + starts_below + n(l + 1) as u64;
        least = least.max(if l == 0 {
            merge_work(dag, 0)
        } else {
            slots_below + merge_level_memory(n(l), levels[l].units()).least()
        });
    }
    least
}

/// The least the order and the layout hold for `dag` whose levels have
/// `classes` classes each, whatever the budget: the largest, over the
/// levels, of what their out-of-core passes hold with their least chunks
/// (the layout with the addresses of the level below it reads, and the
/// stored order and counts), and of the leaves' layout in memory.
pub(super) fn least_for_order_and_layout(dag: &Dag<'_>, classes: &[usize]) -> u64 {
    let leaf_level = usize::from(dag.leaf_level());
    let mut least = leaf_layout_work(classes[leaf_level]);
    for l in 0..leaf_level {
        let (c, below) = (classes[l], classes[l + 1]);
        // The addresses below by rank and, above a node level, by position.
        let addresses_below = if l + 1 == leaf_level { 8 } else { 16 } * below as u64;
        let layout = addresses_below + 12 * c as u64 + layout_memory(c).least();
        least = least.max(order_memory(c, below).least()).max(layout);
    }
    least
}

/// Sorts the forms of `n` 1.0 nodes, made a `chunk` of ordinals at a time
/// by `forms_of`: each chunk sorted in parallel and, when there is more
/// than one, written as a run to a scratch file in `dir`, the runs merged.
/// Calls `visit` with each form in sorted order, the rank of its class (its
/// position among the distinct forms) and whether it is its class's first.
fn rank_external<F: RunForm>(
    n: usize,
    chunk: usize,
    dir: &Option<PathBuf>,
    mut forms_of: impl FnMut(Range<usize>) -> Result<Vec<F>, ConvertError>,
    mut visit: impl FnMut(&F, usize, bool) -> Result<(), ConvertError>,
) -> Result<(), ConvertError> {
    let mut rank = 0usize;
    let mut previous: Option<F> = None;
    let mut next = |form: F| -> Result<(), ConvertError> {
        let first = previous
            .as_ref()
            .is_none_or(|p| p.order(&form) != CmpOrdering::Equal);
        if first && previous.is_some() {
            rank += 1;
        }
        visit(&form, rank, first)?;
        previous = Some(form);
        Ok(())
    };
    if n <= chunk {
        let mut forms = forms_of(0..n)?;
        forms.par_sort_unstable_by(F::order);
        for form in forms {
            next(form)?;
        }
        return Ok(());
    }
    let mut file = scratch_file(dir)?;
    let mut runs = Vec::with_capacity(n.div_ceil(chunk));
    let mut end = 0u64;
    let mut buf = Vec::with_capacity(PIECE + F::BYTES);
    for start in (0..n).step_by(chunk) {
        let mut forms = forms_of(start..(start + chunk).min(n))?;
        forms.par_sort_unstable_by(F::order);
        for piece in forms.chunks(PIECE / F::BYTES) {
            buf.clear();
            for f in piece {
                f.put(&mut buf);
            }
            file.write_all(&buf)?;
        }
        runs.push(Run {
            next: end,
            left: forms.len(),
            buf: Vec::new(),
            pos: 0,
        });
        end += (forms.len() * F::BYTES) as u64;
    }
    let capacity = (MERGE_BUFFER / runs.len() / F::BYTES).max(1);
    let mut heap = BinaryHeap::with_capacity(runs.len());
    for (i, run) in runs.iter_mut().enumerate() {
        if let Some(form) = run.pop::<F>(&mut file, capacity)? {
            heap.push(Head { form, run: i });
        }
    }
    while let Some(Head { form, run }) = heap.pop() {
        if let Some(f) = runs[run].pop::<F>(&mut file, capacity)? {
            heap.push(Head { form: f, run });
        }
        next(form)?;
    }
    Ok(())
}

/// Bytes held per ranked key or leaf mask before it is appended to the
/// store's scratch file.
const PENDING: usize = 1 << 16;

/// The leaves merged and ranked out of core (see [`merge_leaves`]): the
/// canonical masks in rank order (spilled), their stabilisers, and each 1.0
/// leaf's rank and normalised reflection. `room`: the bytes the pass may
/// hold.
#[allow(clippy::type_complexity)]
pub(super) fn merge_leaves_external(
    dag: &Dag<'_>,
    leaf_level: usize,
    room: u64,
    store: &mut Store,
) -> Result<(Table<u64>, Vec<u8>, Slots), ConvertError> {
    let n = dag.levels()[leaf_level].node_count;
    u32::try_from(n).map_err(|_| {
        FormatError::new(
            ErrorCode::LevelTooLarge,
            0,
            format!("{n} leaves are more than the encoder numbers"),
        )
    })?;
    let n = n as usize;
    let reflect = leaf_level > 0;
    let chunk = merge_leaves_memory(n).chunk(room);
    let mut rank = vec![0u32; n];
    let mut reflection = vec![0u8; n];
    let mut stabs = Vec::new();
    let mut writer = store.begin::<u64>();
    let mut pending: Vec<u64> = Vec::with_capacity(PENDING / 8);
    let dir = store.dir.clone();
    rank_external(
        n,
        chunk,
        &dir,
        |range| {
            Ok((range.start as u32..range.end as u32)
                .into_par_iter()
                .map(|i| {
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
                })
                .collect::<Result<_, FormatError>>()?)
        },
        |&(mask, i, r), class, first| {
            if first {
                stabs.push(leaf_stab(mask));
                pending.push(mask);
                if pending.len() == pending.capacity() {
                    store.append(&mut writer, &pending)?;
                    pending.clear();
                }
            }
            let stab = *stabs.last().expect("a class started");
            rank[i as usize] = class as u32;
            reflection[i as usize] = norm(r, stab);
            Ok(())
        },
    )?;
    store.append(&mut writer, &pending)?;
    let leaves = store.finish(writer);
    Ok((
        leaves,
        stabs,
        Slots::ByNode {
            starts: None,
            rank,
            reflection,
        },
    ))
}

/// Interior level `level` merged and ranked out of core (see
/// [`merge_level`]) through the slot values of the level below (`below`)
/// and its classes' stabilisers: the ranked keys (spilled), their
/// stabilisers, and the slot values of this level's 1.0 nodes. `room`: the
/// bytes the pass may hold besides `below` and `child_stabs`.
#[allow(clippy::type_complexity)]
pub(super) fn merge_level_external(
    dag: &Dag<'_>,
    level: usize,
    below: &Slots,
    child_stabs: &[u8],
    room: u64,
    store: &mut Store,
) -> Result<(Table<NodeKey>, Vec<u8>, Slots), ConvertError> {
    assert!(level > 0, "the root level is merged in memory");
    let section = &dag.levels()[level];
    let units = section.units();
    let level8 = level as u8;
    let n = usize::try_from(section.node_count).expect("a level's nodes are numbered in u32");
    u32::try_from(units).map_err(|_| {
        FormatError::new(
            ErrorCode::LevelTooLarge,
            section.file_offset,
            format!("level {level}: {units} words are more than the encoder numbers"),
        )
    })?;
    let chunk = merge_level_memory(n, units).chunk(room);
    let mut index = RecordStarts::new(units);
    let mut word = 0u64;
    let mut rank = vec![0u32; n];
    let mut reflection = vec![0u8; n];
    let mut stabs = Vec::new();
    let mut writer = store.begin::<NodeKey>();
    let mut pending: Vec<NodeKey> = Vec::with_capacity(PENDING / NodeKey::BYTES);
    let dir = store.dir.clone();
    let slot_bits = PackedKey::slot_bits(child_stabs.len());
    rank_external(
        n,
        chunk,
        &dir,
        |range| {
            // The node starts: each record's size is in its header.
            let mut starts = Vec::with_capacity(range.len());
            for i in range.clone() {
                if word >= units {
                    return Err(FormatError::new(
                        ErrorCode::ItemCountMismatch,
                        section.file_offset,
                        format!("level {level}: {n} nodes declared, the records end after {i}"),
                    )
                    .into());
                }
                starts.push(word as u32);
                index.mark(word);
                word += dag.node(level8, word as u32)?.record_size() / 4;
            }
            if range.end == n && word != units {
                return Err(FormatError::new(
                    ErrorCode::ItemCountMismatch,
                    section.file_offset,
                    format!("level {level}: more records than the {n} nodes declared"),
                )
                .into());
            }
            Ok(starts
                .par_iter()
                .enumerate()
                .map(|(j, &w)| {
                    let i = (range.start + j) as u32;
                    let node = dag.node(level8, w)?;
                    let mut key = NodeKey {
                        slots: [0; 8],
                        attribute: node.attribute(),
                    };
                    // The children's stabilisers, by slot (1 where none is).
                    let mut slot_stabs = [1u8; 8];
                    let mut k = 0;
                    for slot in 0..8u32 {
                        if node.child_mask() >> slot & 1 != 0 {
                            let p = node.pointer_at(k);
                            k += 1;
                            let s = below.get(p, child_stabs);
                            if s == 0 {
                                return Err(FormatError::new(
                                    ErrorCode::PointerOutOfRange,
                                    section.file_offset + u64::from(w) * 4,
                                    format!("level {level}: pointer {p} names no node"),
                                ));
                            }
                            key.slots[slot as usize] = s & ((1 << STAB_SHIFT) - 1);
                            slot_stabs[slot as usize] = (s >> STAB_SHIFT) as u8;
                        }
                    }
                    Ok(least_form(&key, &slot_stabs, i, slot_bits))
                })
                .collect::<Result<_, FormatError>>()?)
        },
        |f, class, first| {
            if first {
                stabs.push(f.stab);
                pending.push(f.key.unpack(slot_bits));
                if pending.len() == pending.capacity() {
                    store.append(&mut writer, &pending)?;
                    pending.clear();
                }
            }
            rank[f.node as usize] = class as u32;
            reflection[f.node as usize] = norm(f.reflection, f.stab);
            Ok(())
        },
    )?;
    store.append(&mut writer, &pending)?;
    index.finish();
    Ok((
        store.finish(writer),
        stabs,
        Slots::ByNode {
            starts: Some(index),
            rank,
            reflection,
        },
    ))
}

/// What the order pass of a level leaves for the layout and the level
/// below: the order of the level below, the first sequential child of each
/// stored node, the nodes as stored, and the reference counts of the level
/// below.
pub(super) type Ordered = (Vec<(u32, u8)>, Vec<u64>, Table<NodeKey>, Vec<u32>);

/// The order pass (§23.7) of a level out of core: its ranked keys `keys`,
/// the stabilisers of the `below` classes below, and its `stored` order.
/// `room`: the bytes the pass may hold.
pub(super) fn order_level_external(
    store: &mut Store,
    keys: Table<NodeKey>,
    child_stabs: Table<u8>,
    stored: &[(u32, u8)],
    below: usize,
    room: u64,
) -> Result<Ordered, ConvertError> {
    let child_stabs = store.take(child_stabs)?;
    let classes = keys.len();
    // A chunk of positions (out) and one of ranks (read) at a time.
    let chunk = order_memory(classes, below).chunk(room);
    let counts: Vec<AtomicU32> = (0..below).map(|_| AtomicU32::new(0)).collect();
    for start in (0..classes).step_by(chunk) {
        let part = store.read_range(&keys, start..(start + chunk).min(classes))?;
        count_references(&part, &counts);
    }
    let c: Vec<u32> = counts.into_iter().map(AtomicU32::into_inner).collect();
    let mut next = shared_by_count(&c);
    let mut firsts = Vec::with_capacity(classes);
    let mut writer = store.begin::<NodeKey>();
    for start in (0..stored.len()).step_by(chunk) {
        let want = &stored[start..(start + chunk).min(stored.len())];
        let mut out = vec![
            NodeKey {
                slots: [0; 8],
                attribute: 0,
            };
            want.len()
        ];
        for first in (0..classes).step_by(chunk) {
            let ranks = first..(first + chunk).min(classes);
            let part = store.read_range(&keys, ranks.clone())?;
            out.par_iter_mut()
                .zip(want)
                .for_each(|(o, &(rank, applied))| {
                    if ranks.contains(&(rank as usize)) {
                        let key = &part[rank as usize - first];
                        *o = if applied == 0 {
                            *key
                        } else {
                            reflect_key(key, applied, &child_stabs)
                        };
                    }
                });
        }
        for key in &out {
            firsts.push(next.len() as u64);
            for &s in &key.slots {
                if s != 0 {
                    let child = ((s - 1) >> 3) as u32;
                    if c[child as usize] == 1 {
                        next.push((child, ((s - 1) & 7) as u8));
                    }
                }
            }
        }
        store.append(&mut writer, &out)?;
    }
    Ok((next, firsts, store.finish(writer), c))
}

/// What the layout of a level gives the level above: its summary, its
/// bytes (spilled), and the addresses of its records by position and, for
/// shared classes, by rank.
pub(super) type LaidOut = (LevelSummary, Table<u8>, Vec<u64>, Vec<u64>);

/// The layout of node level `level` out of core: its `keys` and `firsts` in
/// stored order, its stored order, the reference counts of its classes and
/// the `classes` number, and what it reads of the level below.
/// `room`: the bytes the pass may hold.
#[allow(clippy::too_many_arguments)]
pub(super) fn layout_level_external(
    store: &mut Store,
    level: usize,
    keys: Table<NodeKey>,
    firsts: Table<u64>,
    stored_here: &[(u32, u8)],
    counts_here: &[u32],
    classes: usize,
    layout: &LevelLayout<'_>,
    room: u64,
) -> Result<LaidOut, ConvertError> {
    let n = keys.len();
    // A chunk's keys, firsts, records and their offsets.
    let chunk = layout_memory(n).chunk(room);
    let mut hist = [0u64; 65];
    for start in (0..n).step_by(chunk) {
        let range = start..(start + chunk).min(n);
        let keys = store.read_range(&keys, range.clone())?;
        let firsts = store.read_range(&firsts, range)?;
        let part = keys
            .par_chunks(LAYOUT_CHUNK)
            .zip(firsts.par_chunks(LAYOUT_CHUNK))
            .map(|(keys, firsts)| {
                let mut hist = [0u64; 65];
                for (key, &first) in keys.iter().zip(firsts) {
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
        for (x, y) in hist.iter_mut().zip(part) {
            *x += y;
        }
    }
    let widths = level_widths(&hist, level)?;
    let mut writer = store.begin::<u8>();
    let mut crc = 0u32;
    let mut length = 0u64;
    let mut addr_of_pos = Vec::with_capacity(n);
    for start in (0..n).step_by(chunk) {
        let range = start..(start + chunk).min(n);
        let keys = store.read_range(&keys, range.clone())?;
        let firsts = store.read_range(&firsts, range)?;
        let pieces: Vec<(Vec<u8>, Vec<u64>)> = keys
            .par_chunks(LAYOUT_CHUNK)
            .zip(firsts.par_chunks(LAYOUT_CHUNK))
            .map(|(keys, firsts)| {
                let mut out = Vec::new();
                let mut offsets = Vec::with_capacity(keys.len());
                for (key, &first) in keys.iter().zip(firsts) {
                    offsets.push(out.len() as u64);
                    layout.write(key, first, widths, &mut out);
                }
                (out, offsets)
            })
            .collect();
        drop(keys);
        drop(firsts);
        for (piece, offsets) in pieces {
            addr_of_pos.extend(offsets.iter().map(|o| length + o));
            crc = crc32c::crc32c_append(crc, &piece);
            length += piece.len() as u64;
            store.append(&mut writer, &piece)?;
        }
    }
    let mut addr_of_rank = vec![SEQUENTIAL; classes];
    for (&(rank, _), &offset) in stored_here.iter().zip(&addr_of_pos) {
        if level == 0 || counts_here[rank as usize] > 1 {
            addr_of_rank[rank as usize] = offset;
        }
    }
    Ok((
        LevelSummary {
            widths,
            item_count: n as u64,
            is_leaf: false,
            length,
            crc,
        },
        store.finish(writer),
        addr_of_pos,
        addr_of_rank,
    ))
}
