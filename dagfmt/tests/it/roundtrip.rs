//! Builder → bytes → reader round trips (property tests), and the transport,
//! batch and statistics modules.
//!
//! The container is checked by an oracle written here from spec/VDAG.md (not by
//! the crate's validator): checksums, placement and padding, minimal pointer
//! widths, pointer targets, references, stored voxel counts, and that no level
//! holds two identical records (deduplication). Voxel sets are compared with
//! the input through the reader's `voxels`, `is_set` and `voxel_index`, and the
//! tree-node counts of the statistics with the number of distinct Morton
//! prefixes of the input.

use std::collections::{BTreeSet, HashMap, HashSet};

use dagfmt::batch::{self, BatchError, Hit, Ray};
use dagfmt::builder::{BuildError, BuiltDag};
use dagfmt::layout::{self, AttributeKind, COUNT_SATURATED};
use dagfmt::reader::NodeRef;
use dagfmt::transport::{self, TransportError};
use dagfmt::{Dag, DagBuilder, ErrorCode, morton, stats};
use proptest::prelude::*;

// ------------------------------------------------------------------ oracle

/// A node record as parsed by the oracle.
struct Record {
    word: u64,
    mask: u32,
    attribute: u32,
    pointers: Vec<u64>,
}

/// Checks every container and graph rule the builder must satisfy.
fn check_container(bytes: &[u8]) {
    let dag = Dag::open(bytes).expect("builder output opens");
    let h = dag.header().clone();
    assert_eq!(h.file_size, bytes.len() as u64);
    assert_eq!(h.required_features, 0);
    assert_eq!(h.optional_features, 0);
    assert!(bytes[28..32].iter().all(|&b| b == 0), "reserved0");
    assert!(bytes[80..124].iter().all(|&b| b == 0), "reserved1");
    let n = usize::from(h.section_count);
    let table_end = layout::HEADER_SIZE + n * layout::SECTION_ENTRY_SIZE;
    let header: [u8; 128] = bytes[..128].try_into().unwrap();
    assert_eq!(
        layout::header_checksum(&header, &bytes[128..table_end]),
        h.header_crc,
        "header crc"
    );
    let mut position = table_end as u64;
    for s in dag.sections() {
        let entry = &bytes[s.entry_offset() as usize..][..40];
        assert_eq!(&entry[6..8], &[0, 0], "entry reserved0");
        assert_eq!(&entry[36..40], &[0, 0, 0, 0], "entry reserved1");
        assert_eq!(
            s.offset,
            layout::align_section(position),
            "section {} placement",
            s.index
        );
        assert!(
            bytes[position as usize..s.offset as usize]
                .iter()
                .all(|&b| b == 0),
            "padding"
        );
        let data = &bytes[s.offset as usize..(s.offset + s.length) as usize];
        assert_eq!(crc32c::crc32c(data), s.crc, "section {} crc", s.index);
        position = s.offset + s.length;
    }
    assert_eq!(
        position,
        bytes.len() as u64,
        "file ends at the last section"
    );

    let levels = dag.levels();
    let leaf_level = levels.len() - 1;
    // Parse every interior level.
    let mut parsed: Vec<Vec<Record>> = Vec::new();
    for (l, section) in levels[..leaf_level].iter().enumerate() {
        let child_units = levels[l + 1].units();
        assert_eq!(
            Some(section.pointer_width),
            layout::minimal_pointer_width(child_units),
            "level {l} pointer width"
        );
        let w = usize::from(section.pointer_width);
        let mut records = Vec::new();
        let mut at = 0usize;
        while at < section.bytes.len() {
            let header = u32::from_le_bytes(section.bytes[at..at + 4].try_into().unwrap());
            let mask = header & 0xff;
            assert_ne!(mask, 0, "empty child mask");
            let k = mask.count_ones() as usize;
            let pointers = (0..k)
                .map(|i| {
                    let p = &section.bytes[at + 4 + i * w..at + 4 + (i + 1) * w];
                    p.iter().rev().fold(0u64, |acc, &b| acc << 8 | u64::from(b))
                })
                .collect();
            let size = layout::node_record_size(k as u32, section.pointer_width) as usize;
            assert!(
                section.bytes[at + 4 + k * w..at + size]
                    .iter()
                    .all(|&b| b == 0),
                "node padding"
            );
            records.push(Record {
                word: (at / 4) as u64,
                mask,
                attribute: header >> 8,
                pointers,
            });
            at += size;
        }
        assert_eq!(at, section.bytes.len());
        assert_eq!(
            records.len() as u64,
            section.node_count,
            "level {l} item count"
        );
        let distinct: HashSet<(u32, &[u64])> =
            records.iter().map(|r| (r.mask, &r.pointers[..])).collect();
        assert_eq!(
            distinct.len(),
            records.len(),
            "level {l} holds duplicate nodes"
        );
        parsed.push(records);
    }
    let leaves: Vec<u64> = levels[leaf_level]
        .bytes
        .chunks_exact(8)
        .map(|c| u64::from_le_bytes(c.try_into().unwrap()))
        .collect();
    assert_eq!(leaves.len() as u64, levels[leaf_level].node_count);
    assert!(leaves.iter().all(|&m| m != 0), "empty leaf");
    assert_eq!(
        leaves.iter().collect::<HashSet<_>>().len(),
        leaves.len(),
        "duplicate leaves"
    );
    if dag.is_empty() {
        assert!(
            levels
                .iter()
                .all(|l| l.node_count == 0 && l.bytes.is_empty())
        );
        assert_eq!(h.voxel_count, 0);
        return;
    }
    assert_eq!(levels[0].node_count, 1, "one root");
    // Counts bottom-up, pointer targets and references.
    let mut counts: Vec<u64> = leaves.iter().map(|m| u64::from(m.count_ones())).collect();
    let mut child_index: HashMap<u64, usize> = (0..leaves.len()).map(|i| (i as u64, i)).collect();
    for l in (0..leaf_level).rev() {
        let mut referenced = vec![false; counts.len()];
        let mut level_counts = Vec::new();
        for r in &parsed[l] {
            let mut total = 0u64;
            for &p in &r.pointers {
                let &target = child_index
                    .get(&p)
                    .unwrap_or_else(|| panic!("level {l}: pointer {p} not at a record"));
                referenced[target] = true;
                total += counts[target];
            }
            match h.attribute_kind {
                AttributeKind::None => assert_eq!(r.attribute, 0),
                AttributeKind::VoxelCount => {
                    assert_eq!(
                        u64::from(r.attribute),
                        total.min(u64::from(COUNT_SATURATED)),
                        "level {l} count"
                    )
                }
            }
            level_counts.push(total);
        }
        assert!(
            referenced.iter().all(|&r| r),
            "level {} has an unreferenced node",
            l + 1
        );
        child_index = parsed[l]
            .iter()
            .enumerate()
            .map(|(i, r)| (r.word, i))
            .collect();
        counts = level_counts;
    }
    assert_eq!(counts, vec![h.voxel_count], "header voxel count");
}

/// Morton codes of `voxels`, sorted and deduplicated.
fn morton_set(voxels: &[[u32; 3]]) -> Vec<u64> {
    let set: BTreeSet<u64> = voxels
        .iter()
        .map(|v| morton::encode(v[0], v[1], v[2]))
        .collect();
    set.into_iter().collect()
}

/// Builds `voxels`, checks the container and everything the reader says.
fn check_roundtrip(
    depth: u8,
    kind: AttributeKind,
    voxels: &[[u32; 3]],
    probes: &[[u32; 3]],
) -> Vec<u8> {
    let built = DagBuilder::from_voxels(depth, kind, voxels.iter().copied()).unwrap();
    let bytes = built.to_bytes();
    let mut streamed = Vec::new();
    built.write_to(&mut streamed).unwrap();
    assert_eq!(streamed, bytes, "write_to == to_bytes");
    assert_eq!(built.file_size(), bytes.len() as u64);
    check_container(&bytes);

    let codes = morton_set(voxels);
    assert_eq!(built.voxel_count(), codes.len() as u64);
    let dag = Dag::open(&bytes).unwrap();
    assert_eq!(dag.header().voxel_count, codes.len() as u64);
    let iterated: Vec<u64> = dag
        .voxels()
        .map(|v| v.unwrap())
        .map(|v| morton::encode(v[0], v[1], v[2]))
        .collect();
    assert_eq!(iterated, codes, "voxels() in Morton order");
    for (rank, &code) in codes.iter().enumerate() {
        let [x, y, z] = morton::decode(code);
        assert!(dag.is_set(x, y, z).unwrap());
        if kind == AttributeKind::VoxelCount {
            assert_eq!(
                dag.voxel_index(x, y, z).unwrap(),
                Some(rank as u64),
                "dense index of {:?}",
                [x, y, z]
            );
        }
    }
    let members: HashSet<u64> = codes.iter().copied().collect();
    for p in probes {
        if !members.contains(&morton::encode(p[0], p[1], p[2])) {
            assert!(
                !dag.is_set(p[0], p[1], p[2]).unwrap(),
                "non-member {p:?} reads as set"
            );
            assert_eq!(dag.voxel_index(p[0], p[1], p[2]).unwrap(), None);
        }
    }

    // Statistics: the reader-side analysis agrees with the builder's, and the
    // tree-node count of each level is the number of distinct Morton prefixes.
    let report = stats::analyze(&dag).unwrap();
    assert_eq!(report.levels, built.level_stats());
    for s in &report.levels {
        let shift = 3 * (u32::from(depth) - u32::from(s.level));
        let prefixes: BTreeSet<u64> = codes.iter().map(|c| c >> shift).collect();
        assert_eq!(
            s.tree_nodes,
            prefixes.len() as u128,
            "level {} tree nodes",
            s.level
        );
    }
    bytes
}

// --------------------------------------------------------------- strategies

fn kind_strategy() -> impl Strategy<Value = AttributeKind> {
    prop_oneof![Just(AttributeKind::None), Just(AttributeKind::VoxelCount)]
}

fn coords(depth: u8, max_len: usize) -> impl Strategy<Value = Vec<[u32; 3]>> {
    let side = 1u32 << depth;
    prop::collection::vec(prop::array::uniform3(0..side), 0..max_len)
}

/// A random voxel set at a random depth, plus probe points.
fn random_case() -> impl Strategy<Value = (u8, AttributeKind, Vec<[u32; 3]>, Vec<[u32; 3]>)> {
    (2u8..=8, kind_strategy()).prop_flat_map(|(depth, kind)| {
        (
            Just(depth),
            Just(kind),
            coords(depth, 300),
            coords(depth, 64),
        )
    })
}

/// A small pattern repeated at block-aligned positions: many identical
/// subtrees, so deduplication has work to do.
fn repeated_case() -> impl Strategy<Value = (u8, AttributeKind, Vec<[u32; 3]>, Vec<[u32; 3]>)> {
    (3u8..=8, 2u8..=3, kind_strategy()).prop_flat_map(|(depth, block_log, kind)| {
        let block_log = block_log.min(depth - 1);
        let block = 1u32 << block_log;
        let blocks = 1u32 << (depth - block_log);
        let pattern = prop::collection::vec(prop::array::uniform3(0..block), 1..12);
        let places = prop::collection::vec(prop::array::uniform3(0..blocks), 1..24);
        (Just(depth), Just(kind), pattern, places, coords(depth, 64)).prop_map(
            move |(d, k, pattern, places, probes)| {
                let voxels = places
                    .iter()
                    .flat_map(|p| {
                        pattern
                            .iter()
                            .map(move |v| [0, 1, 2].map(|i| p[i] * block + v[i]))
                    })
                    .collect();
                (d, k, voxels, probes)
            },
        )
    })
}

/// A sparse set at depth 12 or 21.
fn deep_case() -> impl Strategy<Value = (u8, AttributeKind, Vec<[u32; 3]>, Vec<[u32; 3]>)> {
    (prop_oneof![Just(12u8), Just(21u8)], kind_strategy()).prop_flat_map(|(depth, kind)| {
        (
            Just(depth),
            Just(kind),
            coords(depth, 40),
            coords(depth, 40),
        )
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn random_sets_round_trip((depth, kind, voxels, probes) in random_case()) {
        check_roundtrip(depth, kind, &voxels, &probes);
    }

    #[test]
    fn repeated_patterns_round_trip_and_dedup((depth, kind, voxels, probes) in repeated_case()) {
        let bytes = check_roundtrip(depth, kind, &voxels, &probes);
        // Neighbours of members are the likeliest false positives.
        let dag = Dag::open(&bytes).unwrap();
        let members: HashSet<[u32; 3]> = voxels.iter().copied().collect();
        for v in &voxels {
            for axis in 0..3 {
                let mut n = *v;
                n[axis] ^= 1;
                prop_assert_eq!(dag.is_set(n[0], n[1], n[2]).unwrap(), members.contains(&n));
            }
        }
    }

    #[test]
    fn deep_sparse_sets_round_trip((depth, kind, voxels, probes) in deep_case()) {
        check_roundtrip(depth, kind, &voxels, &probes);
    }

    /// Statistics and the reader never panic on a corrupted file.
    #[test]
    fn stats_and_reader_survive_corruption(
        (depth, kind, voxels, _probes) in random_case(),
        flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 1..6),
    ) {
        let mut bytes = DagBuilder::from_voxels(depth, kind, voxels).unwrap().to_bytes();
        for (at, xor) in flips {
            let i = at.index(bytes.len());
            bytes[i] ^= xor;
        }
        if let Ok(dag) = Dag::open(&bytes) {
            let _ = stats::analyze(&dag);
            for v in dag.voxels().take(2000) {
                if v.is_err() { break; }
            }
            let _ = dag.is_set(0, 0, 0);
        }
    }

    #[test]
    fn colours_round_trip((depth, voxels) in (2u8..=6).prop_flat_map(|d| (Just(d), coords(d, 200)))) {
        let codes = morton_set(&voxels);
        let colour = |v: [u32; 3]| [v[0] as u8, v[1] as u8, v[2] as u8, 0x80 | (v[0] ^ v[2]) as u8];
        let mut built = DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, voxels.iter().copied()).unwrap();
        built.set_colors(codes.iter().map(|&c| colour(morton::decode(c))).collect()).unwrap();
        let bytes = built.to_bytes();
        let mut streamed = Vec::new();
        built.write_to(&mut streamed).unwrap();
        prop_assert_eq!(&streamed, &bytes);
        check_container(&bytes);
        let dag = Dag::open(&bytes).unwrap();
        let colours = dag.colors().expect("colour section present");
        prop_assert_eq!(colours.len(), codes.len() * 4);
        for v in &voxels {
            let index = dag.voxel_index(v[0], v[1], v[2]).unwrap().unwrap() as usize;
            prop_assert_eq!(&colours[index * 4..index * 4 + 4], &colour(*v)[..]);
        }
    }
}

// --------------------------------------------------------- builder, exact

#[test]
fn empty_volumes() {
    for depth in 2..=21u8 {
        for kind in [AttributeKind::None, AttributeKind::VoxelCount] {
            let built = DagBuilder::new(depth, kind).unwrap().finish().unwrap();
            let bytes = built.to_bytes();
            check_container(&bytes);
            // Header, table, no section data.
            assert_eq!(
                bytes.len() as u64,
                layout::align_section(128 + 40 * (u64::from(depth) - 1))
            );
            let dag = Dag::open(&bytes).unwrap();
            assert!(dag.is_empty());
            assert_eq!(dag.voxels().count(), 0);
            assert!(!dag.is_set(0, 0, 0).unwrap());
            assert_eq!(built.voxel_count(), 0);
            assert!(
                built
                    .level_stats()
                    .iter()
                    .all(|s| s.node_count == 0 && s.bytes == 0 && s.tree_nodes == 0)
            );
        }
    }
    let none = DagBuilder::from_voxels(5, AttributeKind::VoxelCount, []).unwrap();
    assert_eq!(Dag::open(&none.to_bytes()).unwrap().root(), None);
    // Zero masks add nothing.
    let mut b = DagBuilder::new(4, AttributeKind::VoxelCount).unwrap();
    b.push_brick(3, 0).unwrap();
    assert_eq!(b.finish().unwrap().voxel_count(), 0);
}

#[test]
fn full_volumes_share_one_node_per_level() {
    for depth in 2..=6u8 {
        let built = DagBuilder::from_fn(depth, AttributeKind::VoxelCount, |_, _, _| true).unwrap();
        let bytes = built.to_bytes();
        check_container(&bytes);
        let dag = Dag::open(&bytes).unwrap();
        assert_eq!(dag.header().voxel_count, 1 << (3 * depth));
        for s in built.level_stats() {
            assert_eq!(s.node_count, 1);
            assert_eq!(s.tree_nodes, 1u128 << (3 * s.level));
        }
        let side = 1u32 << depth;
        let last = dag.voxel_index(side - 1, side - 1, side - 1).unwrap();
        assert_eq!(last, Some((1u64 << (3 * depth)) - 1));
    }
}

#[test]
fn saturated_counts_at_depth_8() {
    // 2^24 voxels: the root's count (16777216) saturates, its children's (2^21) do not.
    let mut b = DagBuilder::new(8, AttributeKind::VoxelCount).unwrap();
    for brick in 0..1u64 << 18 {
        b.push_brick(brick, u64::MAX).unwrap();
    }
    let bytes = b.finish().unwrap().to_bytes();
    check_container(&bytes);
    let dag = Dag::open(&bytes).unwrap();
    let root = dag.node(0, 0).unwrap();
    assert_eq!(root.attribute(), COUNT_SATURATED);
    assert_eq!(
        dag.node(1, root.child_pointer(0).unwrap())
            .unwrap()
            .attribute(),
        1 << 21
    );
    assert_eq!(
        dag.subtree_voxel_count(NodeRef {
            level: 0,
            pointer: 0
        })
        .unwrap(),
        1 << 24
    );
    assert_eq!(dag.voxel_index(255, 255, 255).unwrap(), Some((1 << 24) - 1));
    assert_eq!(dag.voxel_index(0, 0, 128).unwrap(), Some(4 << 21));
}

#[test]
fn push_morton_and_push_brick_agree() {
    // A sphere shell at depth 6, once voxel by voxel and once brick by brick.
    let inside = |x: u32, y: u32, z: u32| {
        let d = [x, y, z].map(|c| f64::from(c) + 0.5 - 32.0);
        let r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
        (20.0 * 20.0..=23.0 * 23.0).contains(&r2)
    };
    let by_fn = DagBuilder::from_fn(6, AttributeKind::VoxelCount, inside)
        .unwrap()
        .to_bytes();
    let mut by_voxel = DagBuilder::new(6, AttributeKind::VoxelCount).unwrap();
    let mut by_brick = DagBuilder::new(6, AttributeKind::VoxelCount).unwrap();
    for brick in 0..1u64 << 12 {
        let mut mask = 0u64;
        for bit in 0..64 {
            let [x, y, z] = morton::decode(brick << 6 | bit);
            if inside(x, y, z) {
                mask |= 1 << bit;
                by_voxel.push_morton(brick << 6 | bit).unwrap();
            }
        }
        by_brick.push_brick(brick, mask).unwrap();
    }
    assert_eq!(by_voxel.finish().unwrap().to_bytes(), by_fn);
    assert_eq!(by_brick.finish().unwrap().to_bytes(), by_fn);
    check_container(&by_fn);
}

#[test]
fn root_cube_is_written() {
    let mut b = DagBuilder::new(3, AttributeKind::None).unwrap();
    b.set_root_cube([-1.5, 2.0, 1e9], 0.25);
    b.push_morton(7).unwrap();
    let bytes = b.finish().unwrap().to_bytes();
    let dag = Dag::open(&bytes).unwrap();
    assert_eq!(dag.header().root_min, [-1.5, 2.0, 1e9]);
    assert_eq!(dag.header().root_size, 0.25);
    let mut bad = DagBuilder::new(3, AttributeKind::None).unwrap();
    bad.set_root_cube([0.0; 3], 0.0);
    assert!(matches!(bad.finish(), Err(BuildError::BadRootCube { .. })));
}

#[test]
fn builder_errors() {
    let e = DagBuilder::from_voxels(3, AttributeKind::None, [[8, 0, 0]]).unwrap_err();
    assert!(matches!(
        e,
        BuildError::VoxelOutOfVolume {
            voxel: [8, 0, 0],
            resolution: 8
        }
    ));
    let mut b = DagBuilder::new(4, AttributeKind::None).unwrap();
    b.push_brick(5, 1).unwrap();
    let e = b.push_brick(5, 1).unwrap_err();
    assert_eq!(
        e,
        BuildError::NotIncreasing {
            unit: "brick",
            previous: 5,
            code: 5
        }
    );
    assert!(!e.to_string().contains('\n'));
    let mut colourless: BuiltDag =
        DagBuilder::from_voxels(3, AttributeKind::None, [[1, 1, 1]]).unwrap();
    assert_eq!(
        colourless.set_colors(vec![[0; 4]]),
        Err(BuildError::ColorsNeedVoxelCount)
    );
    let mut built =
        DagBuilder::from_voxels(3, AttributeKind::VoxelCount, [[1, 1, 1], [2, 2, 2]]).unwrap();
    assert_eq!(
        built.set_colors(vec![[0; 4]]),
        Err(BuildError::ColorCount {
            expected: 2,
            got: 1
        })
    );
    for e in [
        BuildError::DepthOutOfRange { depth: 30 },
        BuildError::ColorsNeedVoxelCount,
    ] {
        assert!(!e.to_string().is_empty() && !e.to_string().contains('\n'));
    }
}

// ---------------------------------------------------------------- stats

#[test]
fn stats_of_a_full_depth_4_volume() {
    let built = DagBuilder::from_fn(4, AttributeKind::VoxelCount, |_, _, _| true).unwrap();
    let bytes = built.to_bytes();
    let dag = Dag::open(&bytes).unwrap();
    let s = stats::analyze(&dag).unwrap();
    // One node per level: root (8 children) -> one level-1 node (8 children) -> one full leaf.
    // This file: header 128 + 3 entries * 40 = 248; level 0 is 4 + 8 one-byte pointers = 12 bytes
    // at 248, level 1 likewise at 264 (260 aligned), the leaf (8 bytes) at 280: 288 bytes.
    assert_eq!(s.file_bytes, 288);
    assert_eq!(s.level_bytes, 12 + 12 + 8);
    // Classic SVDAG: 2 interior nodes of 4 + 8 * 4 = 36 bytes, one 8-byte leaf: 80.
    assert_eq!(s.classic_svdag_bytes, 80);
    // SVO: 1 + 8 interior nodes of 36 bytes, 64 leaves of 8: 324 + 512 = 836.
    assert_eq!(s.svo_bytes, 836);
    assert_eq!(
        s.levels.iter().map(|l| l.tree_nodes).collect::<Vec<_>>(),
        vec![1, 8, 64]
    );
    assert_eq!(
        s.levels.iter().map(|l| l.dedup_ratio()).collect::<Vec<_>>(),
        vec![1.0, 8.0, 64.0]
    );
    assert_eq!(
        s.levels.iter().map(|l| l.pointer_width).collect::<Vec<_>>(),
        vec![1, 1, 0]
    );
    assert_eq!(s.dag_nodes, 3);
    assert_eq!(s.tree_nodes, 73);
    assert!(s.to_string().contains("836"));
    // Every pointer of a level names the one node of the next: no entropy,
    // so the bound is the headers and the leaf alone.
    assert_eq!(s.pointer_entropy_bits, vec![0, 0]);
    assert_eq!(s.pointer_entropy_bound_bytes, 4 + 4 + 8);
}

#[test]
fn stats_of_two_far_corners() {
    // Depth 5, voxels (0,0,0) and (31,31,31): nothing is shared. Root with 2 pointers (12 bytes
    // classic), 2 nodes with 1 pointer at levels 1 and 2 (8 bytes each), 2 leaves: 12 + 16 + 16 + 16.
    let built = DagBuilder::from_voxels(5, AttributeKind::None, [[0, 0, 0], [31, 31, 31]]).unwrap();
    let bytes = built.to_bytes();
    let s = stats::analyze(&Dag::open(&bytes).unwrap()).unwrap();
    assert_eq!(s.classic_svdag_bytes, 60);
    assert_eq!(s.svo_bytes, 60);
    assert_eq!(s.dag_nodes, 7);
    assert_eq!(s.tree_nodes, 7);
    // The root's two pointers name two nodes once each: 1 bit each; the
    // lower levels' single pointers name one of two nodes once each: 2 bits
    // per level. Headers 5 * 4, leaves 2 * 8, pointers ceil(6 / 8) = 1 byte.
    assert_eq!(s.pointer_entropy_bits, vec![2, 2, 2]);
    assert_eq!(s.pointer_entropy_bound_bytes, 20 + 16 + 1);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    /// The pointer entropy bound never exceeds the file's own level sections
    /// (fixed-width pointers are one way of coding each pointer on its own) nor
    /// the classic layout, and it is at least the headers and the leaves.
    #[test]
    fn pointer_entropy_bound_is_below_the_file(depth in 3u8..=7, count in 1usize..400, seed in any::<u64>()) {
        let mut state = seed;
        let mut next = || {
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        };
        let n = 1u64 << depth;
        let voxels: Vec<[u32; 3]> = (0..count)
            .map(|_| [0; 3].map(|_| (next() % n) as u32))
            .collect();
        let built = DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, voxels).unwrap();
        let bytes = built.to_bytes();
        let s = stats::analyze(&Dag::open(&bytes).unwrap()).unwrap();
        let interior: u64 = s.levels[..s.levels.len() - 1].iter().map(|l| l.node_count).sum();
        let leaves = s.levels.last().unwrap().node_count;
        prop_assert!(s.pointer_entropy_bound_bytes <= u128::from(s.level_bytes));
        prop_assert!(s.pointer_entropy_bound_bytes <= s.classic_svdag_bytes);
        prop_assert!(s.pointer_entropy_bound_bytes >= u128::from(4 * interior + 8 * leaves));
        prop_assert_eq!(s.pointer_entropy_bits.len(), s.levels.len() - 1);
    }
}

#[test]
fn stats_report_bad_pointers() {
    let built = DagBuilder::from_fn(4, AttributeKind::VoxelCount, |_, _, _| true).unwrap();
    let bytes = built.to_bytes();
    let root_section = Dag::open(&bytes).unwrap().levels()[0].file_offset as usize;
    // The root's first pointer (one byte, after the 4-byte header): into the middle of the
    // 3-word level-1 record, then past the level.
    for (value, code) in [
        (1u8, ErrorCode::PointerNotAtNode),
        (200, ErrorCode::PointerOutOfRange),
    ] {
        let mut bad = bytes.clone();
        bad[root_section + 4] = value;
        let dag = Dag::open(&bad).unwrap();
        assert_eq!(stats::analyze(&dag).unwrap_err().code, code);
    }
    // A node count that disagrees with the records.
    let mut bad = bytes.clone();
    let entry = 128 + 40; // level 1's table entry; item_count at +24
    bad[entry + 24] = 0;
    if let Ok(dag) = Dag::open(&bad) {
        assert_eq!(
            stats::analyze(&dag).unwrap_err().code,
            ErrorCode::ItemCountMismatch
        );
    }
}

// ------------------------------------------------------------ transport

fn sample_file() -> Vec<u8> {
    DagBuilder::from_fn(6, AttributeKind::VoxelCount, |x, y, z| {
        (x * 7 + y * 3 + z) % 5 == 0 || x == y
    })
    .unwrap()
    .to_bytes()
}

#[test]
fn transport_round_trip_and_flags() {
    let bytes = sample_file();
    let packed = transport::pack(&bytes, 19).unwrap();
    assert!(transport::is_transport(&packed));
    assert!(!transport::is_transport(&bytes));
    // Content size and checksum flags (frame header descriptor: bits 6-7 size field, bit 2 checksum).
    assert_eq!(
        zstd::zstd_safe::get_frame_content_size(&packed).unwrap(),
        Some(bytes.len() as u64)
    );
    assert_ne!(packed[4] & 0x04, 0, "content checksum flag");
    // Any zstd decoder unpacks it.
    assert_eq!(zstd::decode_all(&packed[..]).unwrap(), bytes);
    assert_eq!(
        transport::unpack(&packed, bytes.len() as u64).unwrap(),
        bytes
    );
    // Streaming gives a decodable frame too.
    let mut streamed = Vec::new();
    assert_eq!(
        transport::pack_to(&bytes[..], &mut streamed, 3).unwrap(),
        bytes.len() as u64
    );
    assert_eq!(transport::unpack(&streamed, u64::MAX).unwrap(), bytes);
}

#[test]
fn transport_refuses_bad_input() {
    let bytes = sample_file();
    let packed = transport::pack(&bytes, 3).unwrap();
    // The declared size is over the limit: refused before decoding.
    let e = transport::unpack(&packed, bytes.len() as u64 - 1).unwrap_err();
    assert!(
        matches!(e, TransportError::TooLarge { size, .. } if size == bytes.len() as u64),
        "{e}"
    );
    // A frame without a declared size is stopped once it passes the limit.
    let mut big = bytes.clone();
    big.resize(4 << 20, 0);
    let mut encoder = zstd::stream::write::Encoder::new(Vec::new(), 1).unwrap();
    encoder.include_contentsize(false).unwrap();
    std::io::Write::write_all(&mut encoder, &big).unwrap();
    let undeclared = encoder.finish().unwrap();
    assert_eq!(
        zstd::zstd_safe::get_frame_content_size(&undeclared).unwrap(),
        None
    );
    assert!(matches!(
        transport::unpack(&undeclared, 1 << 20),
        Err(TransportError::TooLarge { .. })
    ));
    assert_eq!(transport::unpack(&undeclared, 4 << 20).unwrap(), big);
    // Trailing bytes, truncation, not zstd, not a .vdag inside.
    let mut trailing = packed.clone();
    trailing.extend_from_slice(&packed);
    assert!(matches!(
        transport::unpack(&trailing, u64::MAX),
        Err(TransportError::TrailingData(_))
    ));
    assert!(transport::unpack(&packed[..packed.len() - 3], u64::MAX).is_err());
    assert!(matches!(
        transport::unpack(&bytes, u64::MAX),
        Err(TransportError::NotZstd)
    ));
    let not_vdag = zstd::encode_all(&b"just some text, not a voxel file"[..], 3).unwrap();
    assert!(matches!(
        transport::unpack(&not_vdag, u64::MAX),
        Err(TransportError::NotVdag(_))
    ));
    // Corrupted payload: the checksum or the decoder notices.
    let mut flipped = packed.clone();
    let middle = flipped.len() / 2;
    flipped[middle] ^= 0x10;
    assert!(transport::unpack(&flipped, u64::MAX).is_err());
    // Packing refuses what is not a .vdag, or a length that disagrees with the header.
    assert!(matches!(
        transport::pack(b"hello", 3),
        Err(TransportError::NotVdag(_))
    ));
    assert!(matches!(
        transport::pack(&bytes[..bytes.len() - 8], 3),
        Err(TransportError::NotVdag(_))
    ));
    let mut sink = Vec::new();
    assert!(transport::pack_to(&bytes[..bytes.len() - 8], &mut sink, 3).is_err());
}

// ---------------------------------------------------------------- batches

fn any_f32() -> impl Strategy<Value = f32> {
    prop_oneof![
        4 => any::<u32>().prop_map(f32::from_bits),
        2 => -1e3f32..1e3,
        1 => Just(f32::INFINITY),
        1 => Just(f32::NEG_INFINITY),
        1 => Just(-0.0f32),
    ]
}

fn ray_strategy() -> impl Strategy<Value = Ray> {
    (
        prop::array::uniform3(any_f32()),
        prop::array::uniform3(any_f32()),
        any_f32(),
        any_f32(),
        prop::option::of(1u8..=21),
    )
        .prop_map(|(origin, dir, tmin, tmax, level)| Ray {
            origin,
            dir,
            tmin,
            tmax,
            level,
        })
}

fn hit_strategy() -> impl Strategy<Value = Hit> {
    prop_oneof![
        1 => Just(Hit::MISS),
        3 => (any_f32(), prop::array::uniform3(any::<u32>()), 1u8..=21, 0u8..=6, prop::option::of(0..u64::MAX))
            .prop_map(|(t, voxel, level, face, index)| Hit { hit: true, t, voxel, level, face, index }),
    ]
}

/// Same bits, except that any NaN equals any NaN (text keeps no NaN payload).
fn same_f32(a: f32, b: f32) -> bool {
    (a.is_nan() && b.is_nan()) || a.to_bits() == b.to_bits()
}

fn same_ray(a: &Ray, b: &Ray) -> bool {
    let fa = [a.origin, a.dir]
        .concat()
        .into_iter()
        .chain([a.tmin, a.tmax]);
    let fb: Vec<f32> = [b.origin, b.dir]
        .concat()
        .into_iter()
        .chain([b.tmin, b.tmax])
        .collect();
    fa.zip(fb).all(|(x, y)| same_f32(x, y)) && a.level == b.level
}

fn same_hit(a: &Hit, b: &Hit) -> bool {
    a.hit == b.hit
        && (!a.hit
            || (same_f32(a.t, b.t)
                && a.voxel == b.voxel
                && a.level == b.level
                && a.face == b.face
                && a.index == b.index))
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

    #[test]
    fn rays_round_trip(rays in prop::collection::vec(ray_strategy(), 0..40)) {
        let mut text = Vec::new();
        batch::write_rays_text(&mut text, &rays).unwrap();
        let back = batch::parse_rays(&text).unwrap();
        prop_assert_eq!(back.len(), rays.len());
        prop_assert!(rays.iter().zip(&back).all(|(a, b)| same_ray(a, b)), "text: {:?}", String::from_utf8_lossy(&text));
        let mut binary = Vec::new();
        batch::write_rays_binary(&mut binary, &rays).unwrap();
        prop_assert_eq!(binary.len(), 16 + 40 * rays.len());
        let back = batch::parse_rays(&binary).unwrap();
        // Binary keeps every bit, NaN payloads included.
        for (a, b) in rays.iter().zip(&back) {
            prop_assert_eq!(a.origin.map(f32::to_bits), b.origin.map(f32::to_bits));
            prop_assert_eq!(a.dir.map(f32::to_bits), b.dir.map(f32::to_bits));
            prop_assert_eq!((a.tmin.to_bits(), a.tmax.to_bits(), a.level), (b.tmin.to_bits(), b.tmax.to_bits(), b.level));
        }
    }

    #[test]
    fn hits_round_trip(hits in prop::collection::vec(hit_strategy(), 0..40)) {
        let mut text = Vec::new();
        batch::write_hits_text(&mut text, &hits).unwrap();
        let back = batch::parse_hits(&text).unwrap();
        prop_assert_eq!(back.len(), hits.len());
        prop_assert!(hits.iter().zip(&back).all(|(a, b)| same_hit(a, b)));
        let mut binary = Vec::new();
        batch::write_hits_binary(&mut binary, &hits).unwrap();
        prop_assert_eq!(binary.len(), 16 + 32 * hits.len());
        let back = batch::parse_hits(&binary).unwrap();
        prop_assert!(hits.iter().zip(&back).all(|(a, b)| same_hit(a, b) && (a.hit || *b == Hit::MISS)));
    }

    /// Arbitrary bytes never panic the parsers.
    #[test]
    fn batch_parsers_never_panic(prefix in prop_oneof![Just(&b"VRAY"[..]), Just(&b"VHIT"[..]), Just(&b"vdag-rays 1\n"[..]), Just(&b""[..])],
                                 tail in prop::collection::vec(any::<u8>(), 0..200)) {
        let bytes = [prefix, &tail[..]].concat();
        let _ = batch::parse_rays(&bytes);
        let _ = batch::parse_hits(&bytes);
    }
}

fn text_error(bytes: &[u8], hits: bool) -> (u64, String) {
    let e = if hits {
        batch::parse_hits(bytes).unwrap_err()
    } else {
        batch::parse_rays(bytes).unwrap_err()
    };
    assert!(!e.to_string().contains('\n'), "one line: {e}");
    match e {
        BatchError::Text { line, message } => (line, message),
        other => panic!("expected a text error, got {other}"),
    }
}

fn binary_error(bytes: &[u8], hits: bool) -> (u64, String) {
    let e = if hits {
        batch::parse_hits(bytes).unwrap_err()
    } else {
        batch::parse_rays(bytes).unwrap_err()
    };
    assert!(!e.to_string().contains('\n'), "one line: {e}");
    match e {
        BatchError::Binary { offset, message } => (offset, message),
        other => panic!("expected a binary error, got {other}"),
    }
}

#[test]
fn text_batch_errors() {
    assert_eq!(text_error(b"", false).0, 1);
    assert_eq!(text_error(b"# only a comment\n", false).0, 1);
    let (line, m) = text_error(b"# c\n0 0 0 1 0 0 0 1\n", false);
    assert_eq!(line, 2);
    assert!(m.contains("vdag-rays 1"), "{m}");
    assert!(text_error(b"vdag-rays 2\n", false).1.contains("version"));
    assert!(text_error(b"vdag-hits 1\n", false).1.contains("vdag-hits"));
    let (line, m) = text_error(b"vdag-rays 1\n0 0 0 1 0 0 0 1\n\n0 0 0 1 0 0 0\n", false);
    assert_eq!(line, 4);
    assert!(m.contains("found 7"), "{m}");
    let (line, m) = text_error(b"vdag-rays 1\n0 0 zero 1 0 0 0 1\n", false);
    assert_eq!(line, 2);
    assert!(m.contains("oz") && m.contains("zero"), "{m}");
    assert!(
        text_error(b"vdag-rays 1\n0 0 0 1 0 0 0 1 0\n", false)
            .1
            .contains("level 0")
    );
    assert!(
        text_error(b"vdag-rays 1\n0 0 0 1 0 0 0 1 22\n", false)
            .1
            .contains("level 22")
    );
    assert!(
        text_error(b"vdag-rays 1\n0 0 0 1 0 0 0 1 x\n", false)
            .1
            .contains("level")
    );
    assert_eq!(
        text_error(b"vdag-rays 1\n\xff\n", false),
        (2, "not UTF-8 text".into())
    );

    assert!(text_error(b"vdag-rays 1\n", true).1.contains("vdag-rays"));
    assert_eq!(text_error(b"vdag-hits 1\nmiss\nhit 1 2 3\n", true).0, 3);
    assert_eq!(text_error(b"vdag-hits 1\nmiss 1\n", true).0, 2);
    assert!(
        text_error(b"vdag-hits 1\nhit 1 2 3 4 5 7 -\n", true)
            .1
            .contains("face 7")
    );
    assert!(
        text_error(b"vdag-hits 1\nhit 1 2 3 4 5 1 x\n", true)
            .1
            .contains("index")
    );
    assert!(
        text_error(b"vdag-hits 1\nhit 1 -2 3 4 5 1 -\n", true)
            .1
            .contains("`-2`")
    );
    assert!(text_error(b"vdag-hits 1\nhat\n", true).1.contains("hat"));
    let ok =
        batch::parse_hits(b"vdag-hits 1\nhit inf 1 2 3 4 0 -\nhit 0.5 0 0 0 21 6 17 # c\nmiss\n")
            .unwrap();
    assert_eq!(ok[0].t, f32::INFINITY);
    assert_eq!(ok[1].index, Some(17));
    assert_eq!(ok[2], Hit::MISS);
}

#[test]
fn binary_batch_errors() {
    let mut rays = Vec::new();
    batch::write_rays_binary(&mut rays, &[Ray::new([0.0; 3], [1.0, 0.0, 0.0]); 2]).unwrap();
    let mut hits = Vec::new();
    batch::write_hits_binary(
        &mut hits,
        &[
            Hit::MISS,
            Hit {
                hit: true,
                t: 1.0,
                voxel: [1, 2, 3],
                level: 4,
                face: 2,
                index: None,
            },
        ],
    )
    .unwrap();
    // Truncated header.
    assert_eq!(binary_error(&rays[..10], false).0, 10);
    // Wrong version.
    let mut v2 = rays.clone();
    v2[4] = 2;
    assert_eq!(binary_error(&v2, false).0, 4);
    // Truncated records, and a hostile count that must not be allocated.
    assert_eq!(binary_error(&rays[..rays.len() - 1], false).0, 8);
    let mut huge = rays[..16].to_vec();
    huge[8..16].copy_from_slice(&u64::MAX.to_le_bytes());
    let (offset, m) = binary_error(&huge, false);
    assert_eq!(offset, 8);
    assert!(m.contains("18446744073709551615"), "{m}");
    let mut huge_hits = hits[..16].to_vec();
    huge_hits[8..16].copy_from_slice(&(u64::MAX / 32 + 1).to_le_bytes());
    assert_eq!(binary_error(&huge_hits, true).0, 8);
    // Trailing bytes after the declared records.
    let mut trailing = rays.clone();
    trailing.push(0);
    assert_eq!(binary_error(&trailing, false).0, 16 + 80);
    // Bad level, nonzero flags.
    let mut bad_level = rays.clone();
    bad_level[16 + 40 + 32..16 + 40 + 36].copy_from_slice(&22u32.to_le_bytes());
    assert_eq!(binary_error(&bad_level, false).0, 16 + 40 + 32);
    let mut flags = rays.clone();
    flags[16 + 36] = 1;
    assert_eq!(binary_error(&flags, false).0, 16 + 36);
    // Hits: the wrong kind of batch, a non-canonical miss, a bad face, reserved flag bits.
    assert_eq!(binary_error(&hits, false).0, 0);
    assert_eq!(binary_error(&rays, true).0, 0);
    let mut dirty_miss = hits.clone();
    dirty_miss[16 + 8] = 1;
    assert_eq!(binary_error(&dirty_miss, true).0, 16);
    let mut face = hits.clone();
    face[16 + 32 + 21] = 9;
    assert_eq!(binary_error(&face, true).0, 16 + 32 + 21);
    let mut reserved = hits.clone();
    reserved[16 + 32] |= 2;
    assert_eq!(binary_error(&reserved, true).0, 16 + 32);
    // Writers refuse what the format cannot hold.
    let mut sink = Vec::new();
    let bad_ray = Ray {
        level: Some(0),
        ..Ray::new([0.0; 3], [1.0; 3])
    };
    assert!(batch::write_rays_text(&mut sink, &[bad_ray]).is_err());
    let bad_hit = Hit {
        hit: true,
        t: 0.0,
        voxel: [0; 3],
        level: 3,
        face: 7,
        index: None,
    };
    assert!(batch::write_hits_binary(&mut sink, &[bad_hit]).is_err());
}
