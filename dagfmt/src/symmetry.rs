//! Symmetry merging of a DAG (format 2.0, spec/VDAG.md §23): subtrees that are
//! mirror images of each other are stored once, in a canonical form, and
//! references carry the transform that turns the stored subtree into the
//! logical one.
//!
//! Transforms act on the octants of a cube (child indices, §8.1: bit 0 = x,
//! bit 1 = y, bit 2 = z). A transform is an axis permutation followed by a
//! reflection; the 8 pure reflections (`r` in 0..8, octant `o → o ^ r`) are
//! the ones format 2.0 stores, and the full group of 48 (6 axis permutations
//! × 8 reflections) exists here so that the size benchmark can measure what
//! permutations would add (spec §23.9).
//!
//! [`canonicalize`] merges a 1.0 DAG bottom-up, level by level: each node (or
//! leaf) is replaced by the least of its transformed forms (the order of
//! [`NodeKey`]; for a leaf the least transformed mask), and equal canonical
//! forms are stored once, numbered in order of first occurrence in the 1.0
//! level. Everything depends only on the voxels and on the 1.0 node order, so
//! the result is deterministic.

use hashbrown::HashMap;
use rustc_hash::FxBuildHasher;

use crate::error::FormatError;
use crate::reader::Dag;

/// A set of cube transforms closed under composition.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Group {
    /// The identity only: no merging beyond 1.0's.
    Identity,
    /// The 8 reflections (format 2.0).
    Reflections,
    /// All 48 axis permutations combined with reflections.
    Full,
}

impl Group {
    /// Number of transforms.
    pub fn order(self) -> u8 {
        match self {
            Group::Identity => 1,
            Group::Reflections => 8,
            Group::Full => 48,
        }
    }

    /// Bits a reference needs to name a transform of this group.
    pub fn transform_bits(self) -> u32 {
        match self {
            Group::Identity => 0,
            Group::Reflections => 3,
            Group::Full => 6,
        }
    }
}

/// The axis permutations, as the source axis of each destination axis:
/// destination bit `d` of an octant is source bit `PERMS[p][d]`. Index 0 is the identity.
const PERMS: [[u8; 3]; 6] = [
    [0, 1, 2],
    [1, 0, 2],
    [0, 2, 1],
    [2, 1, 0],
    [1, 2, 0],
    [2, 0, 1],
];

/// Transform `t` in 0..48: axis permutation `t / 8`, then reflection `t % 8`.
/// Transforms 0..8 are the pure reflections, transform `r` maps `o → o ^ r`.
#[derive(Clone, Debug)]
pub struct Transforms {
    /// `octant[t][o]`: the octant that octant `o` moves to under `t`.
    octant: [[u8; 8]; 48],
    /// `compose[a][b]`: the transform `a ∘ b` (first `b`, then `a`).
    compose: [[u8; 48]; 48],
    /// `inverse[t]`.
    inverse: [u8; 48],
    /// `byte[t][m]`: an 8-bit octant mask moved by `t`.
    byte: Vec<[u8; 256]>,
}

impl Default for Transforms {
    fn default() -> Self {
        Self::new()
    }
}

impl Transforms {
    /// Builds the tables.
    pub fn new() -> Self {
        let mut octant = [[0u8; 8]; 48];
        for (t, row) in octant.iter_mut().enumerate() {
            let perm = PERMS[t / 8];
            let reflection = (t % 8) as u8;
            for (o, out) in row.iter_mut().enumerate() {
                let mut p = 0u8;
                for (d, &s) in perm.iter().enumerate() {
                    p |= (((o >> s) & 1) as u8) << d;
                }
                *out = p ^ reflection;
            }
        }
        let find = |map: [u8; 8]| -> u8 {
            octant
                .iter()
                .position(|row| *row == map)
                .expect("the 48 transforms form a group") as u8
        };
        let mut compose = [[0u8; 48]; 48];
        let mut inverse = [0u8; 48];
        for a in 0..48 {
            for b in 0..48 {
                let mut map = [0u8; 8];
                for (o, m) in map.iter_mut().enumerate() {
                    *m = octant[a][usize::from(octant[b][o])];
                }
                compose[a][b] = find(map);
            }
            let mut map = [0u8; 8];
            for (o, &to) in octant[a].iter().enumerate() {
                map[usize::from(to)] = o as u8;
            }
            inverse[a] = find(map);
        }
        let mut byte = vec![[0u8; 256]; 48];
        for (t, table) in byte.iter_mut().enumerate() {
            for (m, out) in table.iter_mut().enumerate() {
                let mut v = 0u8;
                for (o, &to) in octant[t].iter().enumerate() {
                    if m >> o & 1 != 0 {
                        v |= 1 << to;
                    }
                }
                *out = v;
            }
        }
        Transforms {
            octant,
            compose,
            inverse,
            byte,
        }
    }

    /// The octant `o` moves to under `t`.
    #[inline]
    pub fn octant(&self, t: u8, o: u8) -> u8 {
        self.octant[usize::from(t)][usize::from(o)]
    }

    /// `a ∘ b`: first `b`, then `a`.
    #[inline]
    pub fn compose(&self, a: u8, b: u8) -> u8 {
        self.compose[usize::from(a)][usize::from(b)]
    }

    /// The inverse of `t`.
    #[inline]
    pub fn inverse(&self, t: u8) -> u8 {
        self.inverse[usize::from(t)]
    }

    /// A 4³ leaf mask (bit `8·c1 + c2`, §10) moved by `t`: both the sub-brick
    /// and the voxel within it move by the same octant map.
    #[inline]
    pub fn leaf(&self, t: u8, mask: u64) -> u64 {
        if t < 8 {
            return reflect_leaf(mask, t);
        }
        let table = &self.byte[usize::from(t)];
        let mut out = 0u64;
        for c1 in 0..8u8 {
            let b = (mask >> (8 * c1)) as u8;
            out |= u64::from(table[usize::from(b)]) << (8 * self.octant(t, c1));
        }
        out
    }
}

/// A leaf mask mirrored by reflection `r` (bit `i` of the result is bit
/// `i ^ (r | r << 3)` of `mask`), in at most six masked swaps.
#[inline]
pub fn reflect_leaf(mask: u64, r: u8) -> u64 {
    // Swapping the two halves of each group of 2^(k+1) bits XORs bit k of the index.
    const SWAPS: [(u64, u32); 6] = [
        (0x5555_5555_5555_5555, 1),
        (0x3333_3333_3333_3333, 2),
        (0x0F0F_0F0F_0F0F_0F0F, 4),
        (0x00FF_00FF_00FF_00FF, 8),
        (0x0000_FFFF_0000_FFFF, 16),
        (0x0000_0000_FFFF_FFFF, 32),
    ];
    let flips = u64::from(r & 7) | (u64::from(r & 7) << 3);
    let mut m = mask;
    for (k, &(lo, shift)) in SWAPS.iter().enumerate() {
        if flips >> k & 1 != 0 {
            m = ((m & lo) << shift) | ((m >> shift) & lo);
        }
    }
    m
}

/// A reference to a stored class of the next level: its index in the level
/// (order of first occurrence) and the transform from the stored form to the
/// logical child.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ClassRef {
    /// Index of the stored class in its level.
    pub class: u32,
    /// Transform (0..8 a reflection; below 48 with [`Group::Full`]).
    pub transform: u8,
}

/// A canonical node: its children by physical slot, as `class << 8 |
/// transform` plus one (0 = no child), and its 24 attribute bits. The derived
/// order (slot 0 first) is the one the canonical form minimises.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct NodeKey {
    /// Children by physical slot, `(class << 8 | transform) + 1`, 0 when absent.
    pub slots: [u64; 8],
    /// The 24 attribute bits (invariant under transforms for kinds 0 and 1).
    pub attribute: u32,
}

impl NodeKey {
    /// The 8-bit child mask.
    pub fn child_mask(&self) -> u8 {
        let mut m = 0u8;
        for (i, &s) in self.slots.iter().enumerate() {
            if s != 0 {
                m |= 1 << i;
            }
        }
        m
    }

    /// The child at physical slot `slot`, if present.
    pub fn child(&self, slot: usize) -> Option<ClassRef> {
        let s = self.slots[slot];
        (s != 0).then(|| ClassRef {
            class: ((s - 1) >> 8) as u32,
            transform: ((s - 1) & 0xff) as u8,
        })
    }

    fn encode(r: ClassRef) -> u64 {
        ((u64::from(r.class) << 8) | u64::from(r.transform)) + 1
    }
}

/// A DAG merged under a symmetry group: levels root first; each interior level
/// a list of canonical nodes, the last level the canonical leaf masks.
#[derive(Clone, Debug)]
pub struct SymDag {
    /// The group the classes were merged under (for leaves and nodes).
    pub leaf_group: Group,
    /// The group the interior nodes were merged under.
    pub node_group: Group,
    /// Interior levels, root first (the root level holds the root, not canonicalised).
    pub node_levels: Vec<Vec<NodeKey>>,
    /// The canonical leaf masks.
    pub leaves: Vec<u64>,
}

/// Merges `dag` bottom-up: leaves under `leaf_group`, interior nodes under
/// `node_group` (a subgroup of `leaf_group`'s transforms is not required: the
/// references' transforms are composed in the full group). The root is kept as
/// it is (identity), so the volume needs no root transform.
pub fn canonicalize(
    dag: &Dag<'_>,
    leaf_group: Group,
    node_group: Group,
) -> Result<SymDag, FormatError> {
    let tables = Transforms::new();
    let levels = dag.levels();
    let leaf_level = usize::from(dag.leaf_level());
    if dag.is_empty() {
        return Ok(SymDag {
            leaf_group,
            node_group,
            node_levels: vec![Vec::new(); leaf_level],
            leaves: Vec::new(),
        });
    }
    let is_root_only = leaf_level == 0;
    // Leaves: 1.0 leaf index -> reference to a class.
    let mut leaves = Vec::new();
    let mut refs: Vec<ClassRef> = Vec::new();
    // For an interior level below: `node_at_word[w]` is the ordinal (index in
    // `refs`) of the node whose record starts at word `w`, `u32::MAX` where
    // none does. One lookup per pointer, where a search of the sorted offsets
    // took a cache miss per step.
    let mut node_at_word: Vec<u32> = Vec::new();
    // Per class of the level below: its stabiliser, as a bit set of the
    // transforms that leave its stored member unchanged. References to a
    // symmetric class are normalised to the least transform of their coset,
    // so that mirror images compare equal.
    let mut stabs: Vec<u64> = Vec::new();
    {
        let mut classes: HashMap<u64, u32, FxBuildHasher> = HashMap::default();
        let section = &levels[leaf_level];
        for i in 0..section.node_count as u32 {
            let mask = dag.leaf(i)?.0;
            let (canon, t) = if is_root_only {
                (mask, 0)
            } else {
                let mut best = (mask, 0u8);
                for t in 1..leaf_group.order() {
                    let m = tables.leaf(t, mask);
                    if m < best.0 {
                        best = (m, t);
                    }
                }
                best
            };
            let next = classes.len() as u32;
            let class = *classes.entry(canon).or_insert_with(|| {
                leaves.push(canon);
                stabs.push(
                    (0..leaf_group.order())
                        .filter(|&t| tables.leaf(t, canon) == canon)
                        .fold(0u64, |a, t| a | 1 << t),
                );
                next
            });
            refs.push(ClassRef {
                class,
                transform: tables.inverse(t),
            });
        }
    }
    let mut node_levels = vec![Vec::new(); leaf_level];
    for level in (0..leaf_level).rev() {
        let section = &levels[level];
        let mut classes: HashMap<NodeKey, u32, FxBuildHasher> = HashMap::default();
        let mut stored: Vec<NodeKey> = Vec::new();
        // For the level above, which names these nodes by 1.0 word offset:
        // each node's ordinal by its offset, and each node's reference.
        let units = section.units();
        let mut next_node_at_word: Vec<u32> = if level > 0 {
            vec![u32::MAX; units as usize]
        } else {
            Vec::new()
        };
        let mut next_refs: Vec<ClassRef> = Vec::new();
        let mut next_stabs: Vec<u64> = Vec::new();
        let mut word = 0u64;
        while word < units {
            let node = dag.node(level as u8, word as u32)?;
            let mut key = NodeKey {
                slots: [0; 8],
                attribute: node.attribute(),
            };
            let mut rank = 0;
            for slot in 0..8u32 {
                if node.child_mask() >> slot & 1 != 0 {
                    let p = node.pointer_at(rank);
                    rank += 1;
                    let r = if level + 1 == leaf_level {
                        refs.get(p as usize).copied()
                    } else {
                        node_at_word
                            .get(p as usize)
                            .filter(|&&i| i != u32::MAX)
                            .map(|&i| refs[i as usize])
                    };
                    let Some(r) = r else {
                        return Err(FormatError::new(
                            crate::ErrorCode::PointerOutOfRange,
                            section.file_offset + word * 4,
                            format!("level {level}: pointer {p} names no node"),
                        ));
                    };
                    key.slots[slot as usize] = NodeKey::encode(ClassRef {
                        class: r.class,
                        transform: normalize(&tables, r.transform, stabs[r.class as usize]),
                    });
                }
            }
            // The least form under the transforms of the group (the root:
            // itself), the first transform reaching it on ties.
            let order = if level == 0 { 1 } else { node_group.order() };
            let (t, ties) = least_form(order, |u, j| {
                // Slot j of form u holds the child at the slot u moves to j.
                let slot = tables.octant(tables.inverse(u), j);
                key.child(usize::from(slot)).map_or(0, |r| {
                    NodeKey::encode(ClassRef {
                        class: r.class,
                        transform: normalize(
                            &tables,
                            tables.compose(u, r.transform),
                            stabs[r.class as usize],
                        ),
                    })
                })
            });
            let mut canon = NodeKey {
                slots: [0; 8],
                attribute: key.attribute,
            };
            for slot in 0..8u8 {
                if let Some(r) = key.child(usize::from(slot)) {
                    canon.slots[usize::from(tables.octant(t, slot))] = NodeKey::encode(ClassRef {
                        class: r.class,
                        transform: normalize(
                            &tables,
                            tables.compose(t, r.transform),
                            stabs[r.class as usize],
                        ),
                    });
                }
            }
            let next = classes.len() as u32;
            let class = *classes.entry(canon).or_insert_with(|| {
                stored.push(canon);
                // The transforms that leave the stored form unchanged: those
                // from it back to a form equal to it.
                let back = tables.inverse(t);
                next_stabs.push(
                    (0..order)
                        .filter(|&u| ties >> u & 1 != 0)
                        .fold(0u64, |a, u| a | 1 << tables.compose(u, back)),
                );
                next
            });
            let r = ClassRef {
                class,
                transform: tables.inverse(t),
            };
            if level > 0 {
                next_node_at_word[word as usize] = next_refs.len() as u32;
            }
            next_refs.push(r);
            word += node.record_size() / 4;
        }
        node_levels[level] = stored;
        refs = next_refs;
        node_at_word = next_node_at_word;
        stabs = next_stabs;
    }
    Ok(SymDag {
        leaf_group,
        node_group,
        node_levels,
        leaves,
    })
}

/// The least of the forms `0..order` (at most 64) of a node, compared slot
/// by slot as [`NodeKey`] orders them (the attribute is the same in every
/// form), where `slot(u, j)` is slot j of form u. Returns the first form
/// reaching the least value and the bit set of every form equal to it.
/// Compares only as far as ties remain: most nodes are decided by their
/// first slots, so this reads a few slots of each form, not all eight.
pub(crate) fn least_form(order: u8, mut slot: impl FnMut(u8, u8) -> u64) -> (u8, u64) {
    let mut candidates = if order >= 64 {
        u64::MAX
    } else {
        (1u64 << order) - 1
    };
    for j in 0..8u8 {
        if candidates.count_ones() == 1 {
            break;
        }
        let mut least = u64::MAX;
        let mut reaching = 0u64;
        let mut rest = candidates;
        while rest != 0 {
            let u = rest.trailing_zeros() as u8;
            rest &= rest - 1;
            let v = slot(u, j);
            if v < least {
                least = v;
                reaching = 1 << u;
            } else if v == least {
                reaching |= 1 << u;
            }
        }
        candidates = reaching;
    }
    (candidates.trailing_zeros() as u8, candidates)
}

/// The least transform of the coset `t ∘ stab`: the references `t ∘ s`,
/// `s` in the stabiliser of the target, all name the same logical child.
fn normalize(tables: &Transforms, t: u8, stab: u64) -> u8 {
    // Most classes have no symmetry: only the identity leaves them unchanged.
    if stab == 1 {
        return t;
    }
    (0..48u8)
        .filter(|&s| stab >> s & 1 != 0)
        .map(|s| tables.compose(t, s))
        .min()
        .unwrap_or(t)
}

impl SymDag {
    /// How many references of the level above name each class of `level`:
    /// interior levels are `0..node_levels.len()` (root first), the leaves are
    /// level `node_levels.len()`. The root level has no references (all 0).
    pub fn reference_counts(&self, level: usize) -> Vec<u64> {
        let n = match self.node_levels.get(level) {
            Some(nodes) => nodes.len(),
            None => self.leaves.len(),
        };
        let mut counts = vec![0u64; n];
        if level > 0 {
            for node in &self.node_levels[level - 1] {
                for slot in 0..8 {
                    if let Some(r) = node.child(slot) {
                        counts[r.class as usize] += 1;
                    }
                }
            }
        }
        counts
    }

    /// The classes of `level` (as in [`SymDag::reference_counts`]) by
    /// decreasing reference count, ties in class order: the order in which
    /// reference-ordered encodings store a level.
    pub fn classes_by_reference_count(&self, level: usize) -> Vec<u32> {
        let counts = self.reference_counts(level);
        let mut classes: Vec<u32> = (0..counts.len() as u32).collect();
        classes.sort_by(|&a, &b| counts[b as usize].cmp(&counts[a as usize]).then(a.cmp(&b)));
        classes
    }

    /// The Morton codes (§11) of the voxels the merged DAG describes, in
    /// increasing order: each stored subtree is expanded through the
    /// transforms of the references that reach it. Memoises nothing: for
    /// tests and small DAGs (the work is linear in the voxel count).
    pub fn morton_codes(&self) -> Vec<u64> {
        let tables = Transforms::new();
        let mut out = Vec::new();
        if self.node_levels.is_empty() {
            if let Some(&mask) = self.leaves.first() {
                push_leaf(&mut out, 0, mask);
            }
            return out;
        }
        if self.node_levels[0].is_empty() {
            return out;
        }
        self.expand(&tables, 0, 0, 0, 0, &mut out);
        out
    }

    fn expand(
        &self,
        tables: &Transforms,
        level: usize,
        class: u32,
        transform: u8,
        prefix: u64,
        out: &mut Vec<u64>,
    ) {
        if level == self.node_levels.len() {
            let mask = tables.leaf(transform, self.leaves[class as usize]);
            push_leaf(out, prefix, mask);
            return;
        }
        let node = &self.node_levels[level][class as usize];
        // Logical child c is stored slot s with octant(transform, s) = c.
        let inverse = tables.inverse(transform);
        for c in 0..8u8 {
            let slot = tables.octant(inverse, c);
            if let Some(r) = node.child(usize::from(slot)) {
                let t = tables.compose(transform, r.transform);
                self.expand(
                    tables,
                    level + 1,
                    r.class,
                    t,
                    prefix * 8 + u64::from(c),
                    out,
                );
            }
        }
    }
}

fn push_leaf(out: &mut Vec<u64>, prefix: u64, mask: u64) {
    let mut m = mask;
    while m != 0 {
        let bit = m.trailing_zeros();
        out.push(prefix * 64 + u64::from(bit));
        m &= m - 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::AttributeKind;
    use crate::builder::DagBuilder;
    use proptest::prelude::*;

    #[test]
    fn reflections_xor_the_bit_index() {
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        for _ in 0..200 {
            x = crate::builder::fmix64(x);
            for r in 0..8u8 {
                let m = reflect_leaf(x, r);
                let flips = u32::from(r) | (u32::from(r) << 3);
                for i in 0..64 {
                    assert_eq!(
                        m >> i & 1,
                        x >> (i ^ flips) & 1,
                        "mask {x:#x}, r {r}, bit {i}"
                    );
                }
            }
        }
    }

    #[test]
    fn transforms_form_a_group_whose_first_eight_are_the_reflections() {
        let t = Transforms::new();
        for a in 0..48u8 {
            assert_eq!(t.compose(t.inverse(a), a), 0);
            assert_eq!(t.compose(a, t.inverse(a)), 0);
            for o in 0..8u8 {
                if a < 8 {
                    assert_eq!(t.octant(a, o), o ^ a);
                }
            }
            for b in 0..48u8 {
                for o in 0..8u8 {
                    assert_eq!(t.octant(t.compose(a, b), o), t.octant(a, t.octant(b, o)));
                }
            }
        }
        // Reflections compose by XOR.
        for a in 0..8u8 {
            for b in 0..8u8 {
                assert_eq!(t.compose(a, b), a ^ b);
            }
        }
        // A leaf moved by a transform moves each voxel's octants.
        let mask = 0x0123_4567_89AB_CDEFu64;
        for a in 0..48u8 {
            let m = t.leaf(a, mask);
            for bit in 0..64u8 {
                let to = 8 * t.octant(a, bit / 8) + t.octant(a, bit % 8);
                assert_eq!(m >> to & 1, mask >> bit & 1);
            }
        }
    }

    fn codes_of(bytes: &[u8]) -> Vec<u64> {
        let dag = Dag::open(bytes).unwrap();
        dag.voxels()
            .map(|v| {
                let [x, y, z] = v.unwrap();
                crate::morton::encode(x, y, z)
            })
            .collect()
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        // Merging keeps the voxels, for every group, and a mirrored volume
        // merges into as many classes per level as the original.
        #[test]
        fn merging_keeps_the_voxels(
            depth in 2u8..=5,
            voxels in proptest::collection::vec((0u32..32, 0u32..32, 0u32..32), 0..300),
            mirror in 0u8..8,
        ) {
            let res = 1u32 << depth;
            let vs: Vec<[u32; 3]> = voxels.iter().map(|&(x, y, z)| [x % res, y % res, z % res]).collect();
            let bytes = DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, vs.iter().copied()).unwrap().to_bytes();
            let dag = Dag::open(&bytes).unwrap();
            let expected = codes_of(&bytes);
            for (lg, ng) in [
                (Group::Identity, Group::Identity),
                (Group::Reflections, Group::Reflections),
                (Group::Full, Group::Reflections),
                (Group::Full, Group::Full),
            ] {
                let sym = canonicalize(&dag, lg, ng).unwrap();
                prop_assert_eq!(sym.morton_codes(), expected.clone());
            }
            let flip = |c: u32, bit: u8| if mirror & bit != 0 { res - 1 - c } else { c };
            let mirrored: Vec<[u32; 3]> = vs.iter().map(|&[x, y, z]| [flip(x, 1), flip(y, 2), flip(z, 4)]).collect();
            let mbytes = DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, mirrored).unwrap().to_bytes();
            let a = canonicalize(&dag, Group::Reflections, Group::Reflections).unwrap();
            let b = canonicalize(&Dag::open(&mbytes).unwrap(), Group::Reflections, Group::Reflections).unwrap();
            prop_assert_eq!(a.leaves.len(), b.leaves.len());
            for (x, y) in a.node_levels.iter().zip(&b.node_levels).skip(1) {
                prop_assert_eq!(x.len(), y.len());
            }
        }
    }
}
