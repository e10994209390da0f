//! The validator's canonical-form check of format 2.0 (spec §23.10 step 4,
//! E075 – E077), which works on the file's own records, against an
//! independent oracle: the file's voxels downgraded to 1.0, encoded again by
//! `dagfmt::v2::encode` and compared with the file byte for byte, deepest
//! level first (the rule as §23.10 states it).
//!
//! Inputs: random DAGs whose subtrees repeat in mirrored copies (valid files:
//! nothing may be reported), and those files with items swapped, reflected,
//! duplicated or references given other reflections ([`Model2`] lays each
//! edit out again with every offset and width recomputed). Where steps 1 – 3
//! find something the canonical check does not run; every other file must
//! get the oracle's code.

use conformance::model2::{ChildRef, Model2};
use conformance::rng::Rng;
use dagfmt::symmetry::reflect_leaf;
use dagfmt::v2::{self, LevelView};
use dagfmt::{AttributeKind, Dag, Dag2, DagBuilder, ErrorCode};

/// The oracle: re-encodes the file's voxels and compares level by level
/// from the leaves up. At the deepest level that differs: more items than
/// the canonical encoding is E075, the same records in another order E077,
/// otherwise E076; at the first item that differs.
fn oracle(bytes: &[u8]) -> Option<(ErrorCode, u64)> {
    let dag2 = Dag2::open(bytes).expect("opens");
    let v1 = dagfmt::v2file::downgrade(&dag2).expect("downgrades");
    let dag1 = Dag::open(&v1).expect("1.0 opens");
    let canonical = v2::encode(&dag1).expect("encodes");
    let views = dag2.levels();
    for l in (0..views.len()).rev() {
        let file = &views[l];
        let canon = canonical.levels[l].view();
        if file.bytes == canon.bytes && file.widths == canon.widths {
            continue;
        }
        let file_items = split_items(file);
        let canon_items = split_items(&canon);
        let first_diff = file_items
            .iter()
            .zip(&canon_items)
            .position(|(a, b)| a.1 != b.1)
            .unwrap_or(file_items.len().min(canon_items.len()));
        let offset = dag2.sections()[l].offset
            + file_items
                .get(first_diff)
                .map_or(file.bytes.len() as u64, |i| i.0);
        let code = if file_items.len() > canon_items.len() {
            ErrorCode::DuplicateClass
        } else {
            let mut a: Vec<&[u8]> = file_items.iter().map(|i| i.1).collect();
            let mut b: Vec<&[u8]> = canon_items.iter().map(|i| i.1).collect();
            a.sort_unstable();
            b.sort_unstable();
            if a == b {
                ErrorCode::BadLevelOrder
            } else {
                ErrorCode::NotCanonical
            }
        };
        return Some((code, offset));
    }
    None
}

/// The items of a level: (offset in the level, bytes).
fn split_items<'a>(view: &LevelView<'a>) -> Vec<(u64, &'a [u8])> {
    if view.is_leaf {
        return (0..view.bytes.len() / 8)
            .map(|i| (i as u64 * 8, &view.bytes[i * 8..i * 8 + 8]))
            .collect();
    }
    let mut out = Vec::new();
    let mut at = 0u64;
    while at < view.bytes.len() as u64 {
        let node = v2::decode_node(view.bytes, at, view.widths).expect("decodes");
        let end = at + u64::from(node.size);
        out.push((at, &view.bytes[at as usize..end as usize]));
        at = end;
    }
    out
}

/// The validator's finding of the canonical check, or `None` when steps
/// 1 – 3 found something (the check does not run).
fn validator(bytes: &[u8]) -> Option<Option<(ErrorCode, u64)>> {
    let errors = dagfmt::validate::validate(bytes);
    let canonical = [
        ErrorCode::DuplicateClass,
        ErrorCode::NotCanonical,
        ErrorCode::BadLevelOrder,
    ];
    if errors.iter().any(|e| !canonical.contains(&e.code)) {
        return None;
    }
    assert!(
        errors.len() <= 1,
        "one canonical finding at most: {errors:?}"
    );
    Some(errors.first().map(|e| (e.code, e.offset)))
}

/// A random 2.0 file whose subtrees repeat: tiles of 2^k voxels, each one
/// of a few random patterns in a random reflection, or empty.
fn random_file(rng: &mut Rng) -> Vec<u8> {
    let depth = 3 + rng.below(3) as u8;
    let k = 2 + rng.below(u64::from(depth) - 1) as u32;
    let k = k.min(u32::from(depth));
    let tile = 1u32 << k;
    let patterns: Vec<Vec<bool>> = (0..1 + rng.below(3))
        .map(|_| {
            let density = 0.2 + 0.6 * rng.unit();
            (0..tile * tile * tile)
                .map(|_| rng.unit() < density)
                .collect()
        })
        .collect();
    let tiles_per_axis = 1u32 << (u32::from(depth) - k);
    let choice: Vec<Option<(usize, u32)>> = (0..tiles_per_axis.pow(3))
        .map(|_| {
            (rng.below(4) != 0).then(|| {
                (
                    rng.below(patterns.len() as u64) as usize,
                    rng.below(8) as u32,
                )
            })
        })
        .collect();
    let kind = if rng.below(2) == 0 {
        AttributeKind::VoxelCount
    } else {
        AttributeKind::None
    };
    let built = DagBuilder::from_fn(depth, kind, |x, y, z| {
        let t = ((x >> k) * tiles_per_axis + (y >> k)) * tiles_per_axis + (z >> k);
        let Some((p, r)) = choice[t as usize] else {
            return false;
        };
        let m = tile - 1;
        let (mut lx, mut ly, mut lz) = (x & m, y & m, z & m);
        if r & 1 != 0 {
            lx = m - lx;
        }
        if r & 2 != 0 {
            ly = m - ly;
        }
        if r & 4 != 0 {
            lz = m - lz;
        }
        patterns[p][((lx * tile + ly) * tile + lz) as usize]
    })
    .expect("builds");
    let mut v1 = Vec::new();
    built.write_to(&mut v1).expect("writes");
    let dag = Dag::open(&v1).expect("opens");
    dagfmt::v2file::upgrade(&dag).expect("upgrades")
}

/// Every reference of the level above `level` to item `i`, remapped by `map`.
fn remap(m: &mut Model2, level: usize, map: impl Fn(usize) -> usize) {
    if level == 0 {
        return;
    }
    for rec in &mut m.levels[level - 1] {
        for c in rec.children.iter_mut().flatten() {
            match c {
                ChildRef::Shared { item, .. } | ChildRef::Sequential { item } => *item = map(*item),
            }
        }
    }
}

fn level_len(m: &Model2, level: usize) -> usize {
    if level == m.levels.len() {
        m.leaves.len()
    } else {
        m.levels[level].len()
    }
}

/// One random edit of a canonical file.
fn mutate(m: &mut Model2, rng: &mut Rng) {
    let leaf = m.levels.len();
    let level = 1 + rng.below(leaf as u64) as usize;
    let n = level_len(m, level);
    if n == 0 {
        return;
    }
    let a = rng.below(n as u64) as usize;
    match rng.below(5) {
        // Swap two items (references follow).
        0 => {
            let b = rng.below(n as u64) as usize;
            if level == leaf {
                m.leaves.swap(a, b);
            } else {
                m.levels[level].swap(a, b);
            }
            remap(m, level, |i| {
                if i == a {
                    b
                } else if i == b {
                    a
                } else {
                    i
                }
            });
        }
        // Store an item reflected; shared references compensate.
        1 | 2 => {
            let s = 1 + rng.below(7) as u8;
            if level == leaf {
                m.leaves[a] = reflect_leaf(m.leaves[a], s);
            } else {
                let rec = &mut m.levels[level][a];
                let old = rec.children;
                for (p, c) in old.iter().enumerate() {
                    rec.children[p ^ usize::from(s)] = c.map(|c| match c {
                        ChildRef::Shared { item, r } => ChildRef::Shared { item, r: r ^ s },
                        seq => seq,
                    });
                }
            }
            for rec in &mut m.levels[level - 1] {
                for c in rec.children.iter_mut().flatten() {
                    if let ChildRef::Shared { item, r } = c
                        && *item == a
                    {
                        *r ^= s;
                    }
                }
            }
        }
        // Another reflection on one reference.
        3 => {
            let s = 1 + rng.below(7) as u8;
            let above = &mut m.levels[level - 1];
            let p = rng.below(above.len() as u64) as usize;
            if let Some(ChildRef::Shared { r, .. }) = above[p]
                .children
                .iter_mut()
                .flatten()
                .find(|c| matches!(c, ChildRef::Shared { .. }))
            {
                *r ^= s;
            }
        }
        // Store a shared item twice, half of its references to the copy.
        _ => {
            let naming = m.naming(level - 1);
            let Some(item) = (0..n)
                .find(|&i| naming[(a + i) % n].0 >= 4)
                .map(|i| (a + i) % n)
            else {
                return;
            };
            let copy = n;
            if level == leaf {
                m.leaves.push(m.leaves[item]);
            } else {
                let rec = m.levels[level][item].clone();
                m.levels[level].push(rec);
            }
            let mut moved = 0;
            for rec in &mut m.levels[level - 1] {
                for c in rec.children.iter_mut().flatten() {
                    if let ChildRef::Shared { item: i, .. } = c
                        && *i == item
                        && moved < 2
                    {
                        *i = copy;
                        moved += 1;
                    }
                }
            }
        }
    }
}

#[test]
fn canonical_check_agrees_with_the_rebuild() {
    let mut rng = Rng::new(0x0e07_5077);
    let mut seen = std::collections::BTreeMap::<&'static str, usize>::new();
    let mut same_offset = 0usize;
    for case in 0..300 {
        let bytes = random_file(&mut rng);
        assert_eq!(
            dagfmt::validate::validate(&bytes),
            vec![],
            "case {case}: a canonical file validates"
        );
        let model = Model2::decode(&bytes).expect("decodes");
        if model.levels.is_empty() {
            continue;
        }
        for _ in 0..6 {
            let mut m = model.clone();
            for _ in 0..1 + rng.below(2) {
                mutate(&mut m, &mut rng);
            }
            let edited = m.encode();
            let Some(found) = validator(&edited) else {
                *seen.entry("steps 1-3").or_default() += 1;
                continue;
            };
            let expected = oracle(&edited);
            assert_eq!(
                found.map(|f| f.0),
                expected.map(|e| e.0),
                "case {case}: the validator's code against the rebuild's"
            );
            if found.map(|f| f.1) == expected.map(|e| e.1) {
                same_offset += 1;
            }
            *seen
                .entry(expected.map_or("none", |e| e.0.code()))
                .or_default() += 1;
        }
    }
    eprintln!("outcomes: {seen:?}; same offset as the rebuild: {same_offset}");
    for code in ["E075", "E076", "E077"] {
        assert!(
            seen.get(code).copied().unwrap_or(0) >= 5,
            "{code} reached too rarely: {seen:?}"
        );
    }
}
