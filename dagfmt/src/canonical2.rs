//! The canonical form of a 2.0 file (spec §23.6, §23.7; E075 – E077 of
//! §23.10 step 4), checked on the file's own records.
//!
//! The check runs only on a file whose steps 1 – 3 found nothing, so every
//! record decodes and every reference names an item of the level below.
//!
//! Records are read from the walk's flat arrays ([`Flat`]), not decoded
//! again.
//!
//! 1. **Bottom-up**, per level: each item's key (§23.6) from its record and
//!    the ranks, symmetry groups and reflections to the canonical member of
//!    its children, computed in parallel; the level's intrinsic ranks by a
//!    parallel sort of the keys (equal keys: one class), packed two slots to
//!    a word where the ranks allow. Per item this keeps its class's rank,
//!    the least reflection turning it into its class's canonical member,
//!    its class's symmetry group (a bit set of the reflections that fix it)
//!    and whether its shared references carry least reflections: 8 bytes
//!    an item.
//! 2. **Top-down**, per level: what the canonical encoding stores there, as
//!    (class, stored reflection) in stored order (§23.7), from the reference
//!    counts of the classes of the level above (each class counted once, in
//!    one of its items) and the canonical order of that level; each level is
//!    compared with it item by item as it is made. An item is the canonical
//!    one when it is of the same class, stored in the same reflection (up to
//!    the class's symmetry), every shared reference carries the least
//!    reflection of its coset and every child is named (shared or
//!    sequential) as the canonical reference counts say.
//! 3. The **deepest** level that differs gives the one finding: E075 when
//!    it holds more items than classes (two items of one class), else E076
//!    when an item is stored in another reflection than the canonical
//!    encoding stores its class or a reference does not carry the least
//!    reflection, else E077 (the same records in another order); at the
//!    first item that differs.
//!
//! Where the levels below are canonical, a level's records equal the
//! canonical encoding's byte for byte exactly when they equal it item by
//! item in these terms, so the finding is the one a re-encoding of the
//! file's voxels and a byte comparison would give (the conformance tests
//! check this against that rebuild).

use crate::symmetry::{NodeKey, reflect_leaf};
use crate::v2::{self, LevelView, norm, reflect_key};
use rayon::prelude::*;
use std::borrow::Cow;

use crate::error::{ErrorCode, FormatError};
use crate::reader::SectionEntry;
use crate::validate::{Findings, Stop};
use crate::validate2::{Flat, NO_ITEM, SHARED};

/// A child of a record as an item of the level below.
#[derive(Clone, Copy)]
struct ChildItem {
    /// Index of the item in the level below.
    item: u32,
    /// The reference's reflection (0 for a sequential child).
    reflection: u8,
    /// Shared (named by a reference) or sequential.
    shared: bool,
}

type Children = [Option<ChildItem>; 8];

/// One level of the file as the check reads it: the walk's decoding.
struct FileLevel<'a> {
    view: &'a LevelView<'a>,
    /// The records as the walk decoded them (interior), and the times each
    /// item is named.
    flat: &'a Flat,
    /// Items in the level.
    len: usize,
}

impl FileLevel<'_> {
    /// The offset of item `i` in its section.
    fn item_offset(&self, i: usize) -> u64 {
        if self.view.is_leaf {
            i as u64 * 8
        } else {
            self.flat.starts[i]
        }
    }

    /// The leaf mask of item `i` (leaf level).
    fn mask(&self, i: usize) -> u64 {
        let b = &self.view.bytes[i * 8..i * 8 + 8];
        u64::from_le_bytes(b.try_into().expect("8 bytes"))
    }

    /// Record `i`'s header and its children as items of the level below
    /// (`None` when a reference names no item; steps 1 – 3 rule it out).
    fn record(&self, i: usize) -> Option<(u32, Children)> {
        let header = *self.flat.headers.get(i)?;
        let from = usize::try_from(*self.flat.first.get(i)?).ok()?;
        let to = usize::try_from(*self.flat.first.get(i + 1)?).ok()?;
        let kids = self.flat.kids.get(from..to)?;
        let bits = self.flat.kid_bits.get(from..to)?;
        let mut out = [None; 8];
        let mut mask = header & 0xff;
        for (&item, &b) in kids.iter().zip(bits) {
            if mask == 0 || item == NO_ITEM {
                return None;
            }
            out[mask.trailing_zeros() as usize] = Some(ChildItem {
                item,
                reflection: b & 7,
                shared: b & SHARED != 0,
            });
            mask &= mask - 1;
        }
        (mask == 0).then_some((header, out))
    }
}

/// What the bottom-up pass knows of one item, together so that following a
/// reference to it costs one cache miss.
#[derive(Clone, Copy, Default)]
struct ItemInfo {
    /// The intrinsic rank of its class.
    rank: u32,
    /// The least reflection turning it into its class's canonical member
    /// (the member attains the key).
    to_canonical: u8,
    /// Its class's symmetry group, bit s set when reflection s maps the
    /// class onto itself.
    group: u8,
    /// Whether each of its shared references carries the least reflection
    /// of its coset (true for a leaf): found while its key is built, which
    /// reads the same children, so that the comparison with the canonical
    /// level needs no second pass over the references.
    least_references: bool,
}

/// What the bottom-up pass knows of a level's items and classes.
struct Ranked {
    /// Per item.
    items: Vec<ItemInfo>,
    /// Per class (by rank): its symmetry group.
    group: Vec<u8>,
    /// Per class (by rank): its first item.
    first: Vec<u32>,
}

impl Ranked {
    /// Ranks sorted `(key, item)` pairs: equal keys are one class.
    /// `items` holds each item's reflection and group; its ranks are set here.
    fn from_sorted<K: PartialEq>(sorted: &[(K, u32)], mut items: Vec<ItemInfo>) -> Ranked {
        let mut group = Vec::new();
        let mut first = Vec::new();
        for (i, (key, item)) in sorted.iter().enumerate() {
            if i == 0 || sorted[i - 1].0 != *key {
                group.push(items[*item as usize].group);
                first.push(*item);
            }
            items[*item as usize].rank = (first.len() - 1) as u32;
        }
        Ranked {
            items,
            group,
            first,
        }
    }
}

/// Ranks the leaf level: key = the least of the 8 reflected masks.
fn rank_leaves(level: &FileLevel<'_>) -> Ranked {
    let per_leaf: Vec<(u64, u8, u8)> = (0..level.len)
        .into_par_iter()
        .map(|i| {
            let m = level.mask(i);
            let (mut key, mut to_canonical, mut group) = (u64::MAX, 0u8, 0u8);
            for r in 0..8u8 {
                let x = reflect_leaf(m, r);
                if x < key {
                    key = x;
                    to_canonical = r;
                }
                if x == m {
                    group |= 1 << r;
                }
            }
            (key, to_canonical, group)
        })
        .collect();
    let mut sorted: Vec<(u64, u32)> = per_leaf
        .par_iter()
        .enumerate()
        .map(|(i, p)| (p.0, i as u32))
        .collect();
    sorted.par_sort_unstable();
    let items = per_leaf
        .iter()
        .map(|p| ItemInfo {
            rank: 0,
            to_canonical: p.1,
            group: p.2,
            least_references: true,
        })
        .collect();
    Ranked::from_sorted(&sorted, items)
}

/// The key of record `i` as stored (reflection 0): its slots in terms of
/// its children's classes, and its attribute; and whether each of its
/// shared references carries the least reflection of its coset.
fn stored_key(header: u32, children: &Children, below: &Ranked) -> (NodeKey, bool) {
    let mut key = NodeKey {
        slots: [0; 8],
        attribute: header >> 8,
    };
    let mut least = true;
    for (p, c) in children.iter().enumerate() {
        if let Some(c) = c {
            let info = below.items[c.item as usize];
            let t = norm(info.to_canonical ^ c.reflection, info.group);
            key.slots[p] = 1 + (u64::from(info.rank) << 3) + u64::from(t);
            least &= !c.shared || norm(c.reflection, info.group) == c.reflection;
        }
    }
    (key, least)
}

/// Ranks interior level `l` (the root, l = 0, is its own canonical member:
/// §23.6). `None` when a record does not decode (steps 1 – 3 rule it out).
fn rank_nodes(level: &FileLevel<'_>, below_ranked: &Ranked, is_root: bool) -> Option<Ranked> {
    let key_of = |i: usize| -> Option<(NodeKey, ItemInfo)> {
        let (header, children) = level.record(i)?;
        let (key, least_references) = stored_key(header, &children, below_ranked);
        let (key, to_canonical, group) = if is_root {
            (key, 0, 1)
        } else {
            v2::least_reflected_key(&key, &below_ranked.group)
        };
        Some((
            key,
            ItemInfo {
                rank: 0,
                to_canonical,
                group,
                least_references,
            },
        ))
    };
    // A slot value is below 8 × (classes below) + 1: with fewer than 2^29
    // classes below, two slots fit a 64-bit word, and the sort moves and
    // compares 40 bytes an item instead of 80.
    if below_ranked.first.len() < 1 << 29 {
        rank_keys(level.len, key_of, packed_key)
    } else {
        rank_keys(level.len, key_of, |k| *k)
    }
}

/// A key's slots two to a word (slot 2w in the high half of word w) and
/// its attribute: the same order as [`NodeKey`]'s when every slot value is
/// below 2^32.
fn packed_key(key: &NodeKey) -> ([u64; 4], u32) {
    let mut words = [0u64; 4];
    for (w, pair) in words.iter_mut().zip(key.slots.chunks_exact(2)) {
        *w = pair[0] << 32 | pair[1];
    }
    (words, key.attribute)
}

/// Ranks items `0..n` by the keys `key_of` gives them, compared in the form
/// `pack` gives (which keeps their order).
fn rank_keys<K: Ord + Send>(
    n: usize,
    key_of: impl Fn(usize) -> Option<(NodeKey, ItemInfo)> + Sync,
    pack: impl Fn(&NodeKey) -> K + Sync,
) -> Option<Ranked> {
    let keyed: Vec<((K, u32), ItemInfo)> = (0..n)
        .into_par_iter()
        .map(|i| {
            let (key, info) = key_of(i)?;
            Some(((pack(&key), i as u32), info))
        })
        .collect::<Option<_>>()?;
    let (mut sorted, items): (Vec<(K, u32)>, Vec<ItemInfo>) = keyed.into_par_iter().unzip();
    sorted.par_sort_unstable();
    Some(Ranked::from_sorted(&sorted, items))
}

/// The key of class `rank` of interior level `l` as the canonical encoding
/// stores it: its canonical member reflected by `stored`. (Reflecting by
/// a and then by b is reflecting by a ^ b: a reference's reflection is
/// normalised in a group, so normalising twice is normalising once.)
fn class_key(
    level: &FileLevel<'_>,
    ranked: &Ranked,
    rank: u32,
    stored: u8,
    below_ranked: &Ranked,
) -> Option<NodeKey> {
    let item = ranked.first[rank as usize];
    let (header, children) = level.record(item as usize)?;
    let (key, _) = stored_key(header, &children, below_ranked);
    Some(reflect_key(
        &key,
        ranked.items[item as usize].to_canonical ^ stored,
        &below_ranked.group,
    ))
}

/// Whether reflection `t` maps a class of symmetry group `group` onto itself.
fn fixes(group: u8, t: u8) -> bool {
    group >> t & 1 != 0
}

/// How a level differs from the canonical one.
struct Difference {
    code: ErrorCode,
    /// First item that differs.
    item: usize,
    canonical_items: usize,
}

/// Compares level `level` with `canonical` ((class, stored reflection) in
/// stored order). `counts_below`: the canonical reference counts of the
/// classes of the level below (interior levels).
fn compare(
    level: &FileLevel<'_>,
    ranked: &Ranked,
    canonical: &[(u32, u8)],
    below: Option<(&Ranked, &[u32])>,
) -> Option<Difference> {
    // Where no level of the two holds two items of one class, each item
    // below is named as its class is counted, and the walk found every
    // item named by one sequential run or by shared references, two or
    // more (E078): the naming then agrees with the counts.
    let naming_follows = below.is_none_or(|(below_ranked, _)| {
        ranked.group.len() == ranked.items.len()
            && below_ranked.group.len() == below_ranked.items.len()
    });
    // Whether item i's references carry least reflections, and (`check_naming`)
    // whether it names each child as the canonical counts say.
    let references_ok = |i: usize, check_naming: bool| -> bool {
        let Some((below_ranked, counts)) = below else {
            return true;
        };
        if !ranked.items[i].least_references {
            return false;
        }
        if !check_naming || naming_follows {
            return true;
        }
        let Some((_, children)) = level.record(i) else {
            return false;
        };
        children.iter().flatten().all(|c| {
            let info = below_ranked.items[c.item as usize];
            c.shared == (counts[info.rank as usize] > 1)
        })
    };
    let same = |i: usize| -> bool {
        let (rank, stored) = canonical[i];
        let info = ranked.items[i];
        info.rank == rank && fixes(info.group, info.to_canonical ^ stored) && references_ok(i, true)
    };
    let common = level.len.min(canonical.len());
    let first = (0..common).into_par_iter().position_first(|i| !same(i));
    if first.is_none() && level.len == canonical.len() {
        return None;
    }
    let item = first.unwrap_or(common);
    let code = if level.len > canonical.len() {
        ErrorCode::DuplicateClass
    } else {
        let mut stored_of_class = vec![0u8; ranked.group.len()];
        for &(rank, stored) in canonical {
            stored_of_class[rank as usize] = stored;
        }
        let misstored = (0..level.len).into_par_iter().any(|i| {
            let info = ranked.items[i];
            !fixes(
                info.group,
                info.to_canonical ^ stored_of_class[info.rank as usize],
            ) || !references_ok(i, false)
        });
        if misstored {
            ErrorCode::NotCanonical
        } else {
            ErrorCode::BadLevelOrder
        }
    };
    Some(Difference {
        code,
        item,
        canonical_items: canonical.len(),
    })
}

/// The canonical reference counts of the classes of level `l + 1`: each
/// class of level `l` counted once, every reference of it.
///
/// Read in item order, without a random access per reference where that
/// can be avoided: when every item of level `l` is the only one of its
/// class (a canonical level), the counts are the times the walk found each
/// item of level `l + 1` named, summed per class; otherwise the items of
/// level `l + 1` are counted from the classes' first items, in one
/// sequential pass, and then summed per class.
fn reference_counts(
    level: &FileLevel<'_>,
    ranked: &Ranked,
    below: &FileLevel<'_>,
    below_ranked: &Ranked,
) -> Option<Vec<u32>> {
    let per_item: Cow<'_, [u32]> = if ranked.first.len() == level.len {
        if below.flat.named.len() != below.len {
            return None;
        }
        Cow::Borrowed(&below.flat.named)
    } else {
        let mut is_first = vec![false; level.len];
        for &item in &ranked.first {
            is_first[item as usize] = true;
        }
        let mut per_item = vec![0u32; below.len];
        for (i, _) in is_first.iter().enumerate().filter(|(_, f)| **f) {
            let from = usize::try_from(level.flat.first[i]).ok()?;
            let to = usize::try_from(level.flat.first[i + 1]).ok()?;
            for &c in &level.flat.kids[from..to] {
                let n = per_item.get_mut(c as usize)?;
                *n = n.saturating_add(1);
            }
        }
        Cow::Owned(per_item)
    };
    let mut counts = vec![0u32; below_ranked.first.len()];
    for (info, &n) in below_ranked.items.iter().zip(per_item.iter()) {
        let r = info.rank as usize;
        counts[r] = counts[r].saturating_add(n);
    }
    Some(counts)
}

/// The canonical order of level `l + 1` (§23.7) from that of level `l`.
fn next_canonical(
    level: &FileLevel<'_>,
    ranked: &Ranked,
    canonical: &[(u32, u8)],
    below_ranked: &Ranked,
    counts: &[u32],
) -> Option<Vec<(u32, u8)>> {
    // The shared classes by reference count, as the writer orders them.
    let mut next = crate::v2enc::shared_by_count(counts);
    // The sequential children, in the order of their parents: chunks of
    // the parents on rayon's threads, concatenated in order.
    let sequential: Vec<Vec<(u32, u8)>> = canonical
        .par_chunks(1 << 14)
        .map(|parents| {
            let mut out = Vec::new();
            for &(rank, stored) in parents {
                let key = class_key(level, ranked, rank, stored, below_ranked)?;
                for &s in &key.slots {
                    if s != 0 {
                        let child = ((s - 1) >> 3) as u32;
                        if counts[child as usize] == 1 {
                            out.push((child, ((s - 1) & 7) as u8));
                        }
                    }
                }
            }
            Some(out)
        })
        .collect::<Option<_>>()?;
    next.reserve(sequential.iter().map(Vec::len).sum());
    for part in sequential {
        next.extend(part);
    }
    Some(next)
}

/// Step 4 of §23.10 on a file whose steps 1 – 3 found nothing: reports at
/// most one of E075 – E077. `flats[l]`: level `l` as the walk decoded it.
pub(crate) fn check(
    f: &mut Findings,
    entries: &[&SectionEntry],
    views: &[LevelView<'_>],
    flats: &[Flat],
) -> Result<(), Stop> {
    let leaf_level = views.len() - 1;
    let levels: Vec<FileLevel<'_>> = views
        .iter()
        .zip(flats)
        .map(|(view, flat)| FileLevel {
            view,
            flat,
            len: if view.is_leaf {
                view.bytes.len() / 8
            } else {
                flat.starts.len()
            },
        })
        .collect();
    // Item indices are u32 (§16.1 allows more leaves than that only in
    // levels no build makes); a larger level is not checked.
    if levels.iter().any(|l| u32::try_from(l.len).is_err()) || levels[0].len == 0 {
        return Ok(());
    }
    let mut ranked: Vec<Option<Ranked>> = (0..=leaf_level).map(|_| None).collect();
    ranked[leaf_level] = Some(rank_leaves(&levels[leaf_level]));
    for l in (0..leaf_level).rev() {
        let below = ranked[l + 1].as_ref().expect("ranked");
        let Some(r) = rank_nodes(&levels[l], below, l == 0) else {
            return Ok(());
        };
        ranked[l] = Some(r);
    }
    let ranked: Vec<Ranked> = ranked.into_iter().map(|r| r.expect("ranked")).collect();

    let mut deepest: Option<(usize, Difference)> = None;
    let mut canonical: Vec<(u32, u8)> = vec![(0, 0)];
    for l in 0..=leaf_level {
        if l == leaf_level {
            if let Some(d) = compare(&levels[l], &ranked[l], &canonical, None) {
                deepest = Some((l, d));
            }
            break;
        }
        let (level, below) = (&levels[l], &levels[l + 1]);
        let Some(counts) = reference_counts(level, &ranked[l], below, &ranked[l + 1]) else {
            return Ok(());
        };
        if let Some(d) = compare(
            level,
            &ranked[l],
            &canonical,
            Some((&ranked[l + 1], &counts)),
        ) {
            deepest = Some((l, d));
        }
        let Some(next) = next_canonical(level, &ranked[l], &canonical, &ranked[l + 1], &counts)
        else {
            return Ok(());
        };
        canonical = next;
    }
    let Some((l, d)) = deepest else {
        return Ok(());
    };
    let level = &levels[l];
    let offset = entries[l].offset
        + if d.item < level.len {
            level.item_offset(d.item)
        } else {
            level.view.bytes.len() as u64
        };
    let message = match d.code {
        ErrorCode::DuplicateClass => format!(
            "level {l} stores {} items where its subtrees form {} classes under reflection",
            level.len, d.canonical_items
        ),
        ErrorCode::BadLevelOrder => format!(
            "level {l} is not in the order of §23.7 (item {} differs)",
            d.item
        ),
        _ => format!(
            "item {} of level {l} is not stored as the canonical encoding stores its class, or a reference does not carry the least reflection",
            d.item
        ),
    };
    f.report(
        FormatError::new(d.code, offset, message)
            .at_level(l as u8)
            .at_node(d.item as u64),
    )
}
