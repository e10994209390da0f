//! Exact deduplication of a level's records on every core: the in-memory
//! merge's tables ([`crate::external::MemoryMerge`]).
//!
//! A level's distinct records are kept in [`SHARDS`] open-addressing tables,
//! a record going to the shard its hash's top bits name, so that equal
//! records always meet in one shard. The merge gives the records of one part
//! and level as a *batch*; the shards look the batch up and insert what they
//! have not seen, each on its own thread, each in the batch's order. A record
//! new to the table then holds its position in the batch, and a record seen
//! earlier in the same batch finds that position. The caller numbers the
//! batch's first occurrences in one cheap pass in the batch's order (so the
//! indices are the serial merge's first-seen order, whatever the number of
//! shards or threads, and the output's bytes do not change), then
//! [`ShardedTable::settle`] replaces the positions by those indices.
//!
//! Each slot holds a 24-bit tag of the hash beside the value, so that a probe
//! reads a record's content only when the tags agree, and the slots of the
//! records a few places ahead are prefetched while one is looked up (the
//! lookups miss the cache: the tables are gigabytes).

use rayon::prelude::*;

/// Shards of every table: a fixed number, so that the tables' contents do
/// not depend on the machine.
pub const SHARDS: usize = 16;
/// Bits of a slot's value (an index of the level, or a batch position above
/// every index).
const VALUE_BITS: u32 = 40;
const VALUE_MASK: u64 = (1 << VALUE_BITS) - 1;
/// Most entries per ten slots.
const LOAD_TENTHS: usize = 7;
/// How many of a shard's records ahead the slot of a record is prefetched.
const AHEAD: usize = 8;

/// Bytes a table holds per entry it has room for, at its lowest load after
/// [`ShardedTable::reserve`] (10/7 slots of 16 bytes, and 1/8 for the
/// shards' unequal shares).
pub const BYTES_PER_ENTRY: u64 = 26;
/// Bytes of a batch's working arrays per record (its hash, shard position,
/// result and index).
pub const BATCH_BYTES_PER_RECORD: u64 = 32;

/// One slot: `tagged` is 0 when empty, else the hash's tag in its top 24
/// bits and the value plus one below; `key` is what the caller compares
/// (the leaf mask, or the offset of a record's words).
#[derive(Clone, Copy, Default)]
#[repr(C, align(16))]
struct Slot {
    tagged: u64,
    key: u64,
}

#[derive(Default)]
struct Shard {
    slots: Vec<Slot>,
    len: usize,
    /// Slots filled by the current batch, which hold batch positions.
    pending: Vec<usize>,
}

#[inline]
fn shard_of(hash: u64) -> usize {
    (hash >> 60) as usize
}

#[inline]
fn tag_of(hash: u64) -> u64 {
    ((hash >> 32) & 0xFF_FFFF) << VALUE_BITS
}

impl Shard {
    #[inline]
    fn bucket(&self, hash: u64) -> usize {
        ((u64::from(hash as u32) * self.slots.len() as u64) >> 32) as usize
    }

    /// Makes room for `entries` entries at the table's load; `rehash` gives a
    /// settled entry's hash from its key. Only between batches.
    fn ensure(&mut self, entries: usize, rehash: &(impl Fn(u64) -> u64 + Sync)) {
        debug_assert!(self.pending.is_empty());
        if entries * 10 <= self.slots.len() * LOAD_TENTHS {
            return;
        }
        let want = (entries * 10 / LOAD_TENTHS + 16)
            .max(self.slots.len() * 3 / 2)
            .min(u32::MAX as usize);
        let old = std::mem::replace(&mut self.slots, vec![Slot::default(); want]);
        let n = self.slots.len();
        for s in old.into_iter().filter(|s| s.tagged != 0) {
            let mut b = self.bucket(rehash(s.key));
            while self.slots[b].tagged != 0 {
                b += 1;
                if b == n {
                    b = 0;
                }
            }
            self.slots[b] = s;
        }
    }

    /// Looks up (and inserts) the batch records at `positions`, in order.
    fn run(
        &mut self,
        base: u64,
        positions: &[u32],
        hashes: &[u64],
        key: &(impl Fn(usize) -> u64 + Sync),
        same: &(impl Fn(usize, u64, u64) -> bool + Sync),
    ) -> Vec<u64> {
        let mut out = Vec::with_capacity(positions.len());
        let n = self.slots.len();
        for (k, &p) in positions.iter().enumerate() {
            if let Some(&q) = positions.get(k + AHEAD) {
                prefetch(&self.slots[self.bucket(hashes[q as usize])]);
            }
            let p = p as usize;
            let h = hashes[p];
            let tag = tag_of(h);
            let mut b = self.bucket(h);
            loop {
                let slot = self.slots[b];
                if slot.tagged == 0 {
                    let value = base + p as u64;
                    self.slots[b] = Slot {
                        tagged: tag | (value + 1),
                        key: key(p),
                    };
                    self.pending.push(b);
                    self.len += 1;
                    out.push(value);
                    break;
                }
                if slot.tagged & !VALUE_MASK == tag {
                    let value = (slot.tagged & VALUE_MASK) - 1;
                    if same(p, value, slot.key) {
                        out.push(value);
                        break;
                    }
                }
                b += 1;
                if b == n {
                    b = 0;
                }
            }
        }
        out
    }
}

/// Asks the cache for the line of `slot` (a hint: it changes no result).
#[inline(always)]
fn prefetch(slot: &Slot) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch reads nothing into the program and cannot fault;
    // the pointer comes from a reference anyway.
    unsafe {
        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
            (slot as *const Slot).cast::<i8>(),
        );
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = slot;
}

/// The distinct records of one level, sharded by hash. A value below the
/// level's record count (`base` of the current batch) is a record's index;
/// `base + p` is position `p` of the current batch.
pub struct ShardedTable {
    shards: Vec<Shard>,
}

impl std::fmt::Debug for ShardedTable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ShardedTable")
            .field("entries", &self.shards.iter().map(|s| s.len).sum::<usize>())
            .finish_non_exhaustive()
    }
}

impl Default for ShardedTable {
    fn default() -> Self {
        ShardedTable::new()
    }
}

impl ShardedTable {
    /// An empty table.
    pub fn new() -> Self {
        ShardedTable {
            shards: (0..SHARDS).map(|_| Shard::default()).collect(),
        }
    }

    /// Makes room for `more` entries beyond those held (so that the shards do
    /// not grow, briefly holding twice their size, while batches come);
    /// `rehash` gives a settled entry's hash from its key.
    pub fn reserve(&mut self, more: u64, rehash: impl Fn(u64) -> u64 + Sync) {
        let share = (more as usize / SHARDS) + (more as usize / SHARDS / 8) + 64;
        self.shards
            .par_iter_mut()
            .for_each(|s| s.ensure(s.len + share, &rehash));
    }

    /// Looks up a batch of records whose hashes are `hashes`, inserting those
    /// not found. `base` is the number of records the level holds; `key(i)`
    /// is what batch record `i`'s slot keeps while it is pending; `same(i,
    /// value, key)` says whether batch record `i` equals the entry holding
    /// `value` and `key` (a settled record when `value < base`, else batch
    /// record `value − base`); `rehash` gives a settled entry's hash from its
    /// key. Returns each record's value: the index of a record already held,
    /// or the batch position of the first record of the batch equal to it
    /// (plus `base`; its own when it is the first). Call
    /// [`ShardedTable::settle`] before the next batch.
    pub fn find_or_insert(
        &mut self,
        base: u64,
        hashes: &[u64],
        key: impl Fn(usize) -> u64 + Sync,
        same: impl Fn(usize, u64, u64) -> bool + Sync,
        rehash: impl Fn(u64) -> u64 + Sync,
    ) -> Vec<u64> {
        debug_assert!(hashes.len() < u32::MAX as usize && base < 1 << 33);
        assert_eq!(self.shards.len(), SHARDS, "a table of every shard");
        let mut lists: Vec<Vec<u32>> = vec![Vec::new(); SHARDS];
        let expected = hashes.len() / SHARDS + hashes.len() / SHARDS / 8 + 16;
        for l in &mut lists {
            l.reserve(expected);
        }
        for (i, &h) in hashes.iter().enumerate() {
            lists[shard_of(h)].push(i as u32);
        }
        let found: Vec<Vec<u64>> = self
            .shards
            .par_iter_mut()
            .zip(&lists)
            .map(|(s, positions)| {
                s.ensure(s.len + positions.len(), &rehash);
                s.run(base, positions, hashes, &key, &same)
            })
            .collect();
        let mut out = vec![0u64; hashes.len()];
        for (positions, values) in lists.iter().zip(&found) {
            for (&p, &v) in positions.iter().zip(values) {
                out[p as usize] = v;
            }
        }
        out
    }

    /// Settles the batch: each pending slot's batch position becomes the
    /// index `ids[position]` the caller gave the record, and its key
    /// `key(index, pending key)`.
    pub fn settle(&mut self, base: u64, ids: &[u32], key: impl Fn(u32, u64) -> u64 + Sync) {
        self.shards.par_iter_mut().for_each(|s| {
            for &b in &s.pending {
                let slot = &mut s.slots[b];
                let position = (slot.tagged & VALUE_MASK) - 1 - base;
                let id = ids[position as usize];
                slot.tagged = (slot.tagged & !VALUE_MASK) | (u64::from(id) + 1);
                slot.key = key(id, slot.key);
            }
            s.pending.clear();
        });
    }
}

/// Numbers a batch from what [`ShardedTable::find_or_insert`] found for it
/// (`found`, against `base`, the table's size before the batch): a record
/// held before keeps its index, a first occurrence in the batch gets the
/// index `first(position)` returns (called in the batch's order, so that
/// the indices are first-seen order), a later occurrence its first's. The
/// indices to give [`ShardedTable::settle`].
pub fn number_first_seen<E>(
    found: &[u64],
    base: u64,
    mut first: impl FnMut(usize) -> Result<u32, E>,
) -> Result<Vec<u32>, E> {
    let mut ids = vec![0u32; found.len()];
    for (i, &v) in found.iter().enumerate() {
        ids[i] = if v < base {
            v as u32
        } else if (v - base) as usize == i {
            first(i)?
        } else {
            debug_assert!(((v - base) as usize) < i, "a later first occurrence");
            ids[(v - base) as usize]
        };
    }
    Ok(ids)
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use proptest::prelude::*;

    use super::*;

    /// Deduplicates `batches` of values in one table (as the leaves are),
    /// `hash` the values' hash: each batch's indices.
    fn sharded(batches: &[Vec<u64>], hash: fn(u64) -> u64, reserve: u64) -> Vec<Vec<u32>> {
        let mut table = ShardedTable::new();
        table.reserve(reserve, hash);
        let mut held: Vec<u64> = Vec::new();
        batches
            .iter()
            .map(|batch| {
                let hashes: Vec<u64> = batch.iter().map(|&v| hash(v)).collect();
                let base = held.len() as u64;
                let found = table.find_or_insert(
                    base,
                    &hashes,
                    |i| batch[i],
                    |i, value, key| {
                        // The key is the value itself; check that a settled
                        // entry's index names it too.
                        assert!(value >= base || held[value as usize] == key);
                        key == batch[i]
                    },
                    hash,
                );
                let ids = number_first_seen(&found, base, |i| {
                    held.push(batch[i]);
                    Ok::<u32, ()>((held.len() - 1) as u32)
                })
                .unwrap();
                table.settle(base, &ids, |_, key| key);
                ids
            })
            .collect()
    }

    /// The serial first-seen indices.
    fn oracle(batches: &[Vec<u64>]) -> Vec<Vec<u32>> {
        let mut seen: HashMap<u64, u32> = HashMap::new();
        batches
            .iter()
            .map(|batch| {
                batch
                    .iter()
                    .map(|&v| {
                        let next = seen.len() as u32;
                        *seen.entry(v).or_insert(next)
                    })
                    .collect()
            })
            .collect()
    }

    fn mixed(v: u64) -> u64 {
        v.wrapping_mul(0x9e37_79b9_7f4a_7c15).rotate_left(29) ^ v
    }

    /// Every value in one shard, with one tag and few buckets: the probes
    /// compare contents and wrap around.
    fn colliding(v: u64) -> u64 {
        v % 3
    }

    proptest! {
        #[test]
        fn first_seen_indices(
            batches in prop::collection::vec(prop::collection::vec(0u64..200, 0..300), 0..6),
            reserve in 0u64..2000,
        ) {
            let want = oracle(&batches);
            prop_assert_eq!(&sharded(&batches, mixed, reserve), &want);
            prop_assert_eq!(&sharded(&batches, colliding, reserve), &want);
        }
    }

    #[test]
    fn large_batches_grow_the_shards() {
        // Three batches of 100 000 values of 150 000, no room reserved: the
        // shards grow between batches and keep their entries.
        let batches: Vec<Vec<u64>> = (0..3u64)
            .map(|b| {
                (0..100_000u64)
                    .map(|i| (i * 7 + b * 50_000) % 150_000)
                    .collect()
            })
            .collect();
        assert_eq!(sharded(&batches, mixed, 0), oracle(&batches));
    }
}
