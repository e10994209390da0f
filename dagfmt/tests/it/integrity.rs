//! Integrity: every single-bit flip anywhere in a valid file is reported by the
//! validator, and the reader survives every one of them.
//!
//! ARCHITECTURE.md states that every byte of a `.vdag` is either covered by a
//! CRC-32C or is required-zero padding (spec/VDAG.md §13, §6). These tests
//! prove it exhaustively on small files: every bit of every byte is flipped in
//! turn (no sampling), and for each flip
//!
//! - `validate` reports at least one error, of the family the flipped region
//!   calls for (header and section table: the header checksum E011 or a
//!   stopping error that ends validation before the checksum can be checked;
//!   section bytes: the section checksum E028; padding: E023);
//! - `Dag::open` either rejects the file or gives a reader on which a full walk
//!   (every reachable record and leaf, every voxel, the voxel counts, the
//!   colours) returns values or errors but never panics.
//!
//! The files cover attribute kinds 0 and 1, pointer widths 1 and 2, padding
//! between sections, and a colour section. The transport form is covered too:
//! a flip in a `.vdag.zst` is refused by `unpack`, or gives bytes the validator
//! rejects, or leaves the unpacked file unchanged (a flip in a field that does
//! not change the decoded content, which is harmless).
//!
//! Run with `--nocapture` to see which codes each region produced.

use std::collections::{BTreeMap, BTreeSet, HashSet};
use std::panic::{AssertUnwindSafe, catch_unwind};

use dagfmt::builder::BuiltDag;
use dagfmt::layout::{AttributeKind, HEADER_SIZE, SECTION_ENTRY_SIZE, SectionKind};
use dagfmt::reader::NodeRef;
use dagfmt::validate::{ValidateOptions, validate_with};
use dagfmt::{Dag, DagBuilder, ErrorCode, transport};

/// A small deterministic generator (SplitMix64), so the files are the same on
/// every run without a dependency.
struct SplitMix(u64);

impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d4_9bb8_4ce4_d049);
        z ^ (z >> 31)
    }
}

/// Depth 4, attribute kind 1, a ball with one colour per voxel: width-1
/// pointers and a VOXEL_COLORS section.
fn ball_with_colors() -> Vec<u8> {
    let mut dag = DagBuilder::from_fn(4, AttributeKind::VoxelCount, |x, y, z| {
        let d = |c: u32| (f64::from(c) - 7.5).powi(2);
        d(x) + d(y) + d(z) < 36.0
    })
    .expect("ball builds");
    let colors = (0..dag.voxel_count())
        .map(|i| [i as u8, (i >> 8) as u8, 0x80, 0xff])
        .collect();
    dag.set_colors(colors).expect("colours attach");
    dag.set_root_cube([-1.0, 2.0, 0.5], 3.0)
        .expect("cube is valid");
    dag.to_bytes()
}

/// The ball with its colours packed (lossy, E = 3; alpha varies so that
/// blocks store it): a PACKED_COLORS section with palette and direct blocks.
fn ball_with_packed_colors() -> Vec<u8> {
    let mut dag = DagBuilder::from_fn(4, AttributeKind::VoxelCount, |x, y, z| {
        let d = |c: u32| (f64::from(c) - 7.5).powi(2);
        d(x) + d(y) + d(z) < 36.0
    })
    .expect("ball builds");
    let colors: Vec<[u8; 4]> = (0..dag.voxel_count())
        .map(|i| {
            if i < 300 {
                [(i / 40) as u8 * 30, 200, (i / 90) as u8, 255]
            } else {
                [i as u8, ((i * 7) >> 3) as u8, 0x80, (i % 3) as u8 + 250]
            }
        })
        .collect();
    dag.set_packed_colors(&colors, 3).expect("colours attach");
    dag.to_bytes()
}

/// Depth 5, attribute kind 0, scattered voxels: the random sets are tried in
/// turn until one gives zero padding between two sections (a node level whose
/// length is 4 modulo 8).
fn scattered_with_padding() -> Vec<u8> {
    for seed in 0..64 {
        let mut rng = SplitMix(seed);
        let voxels: Vec<[u32; 3]> = (0..40)
            .map(|_| {
                let r = rng.next();
                [(r & 31) as u32, (r >> 8 & 31) as u32, (r >> 16 & 31) as u32]
            })
            .collect();
        let dag = DagBuilder::from_voxels(5, AttributeKind::None, voxels).expect("builds");
        let bytes = dag.to_bytes();
        if padding_bytes(&bytes) > 0 {
            return bytes;
        }
    }
    panic!("no seed gave a file with padding between sections");
}

/// Depth 6, attribute kind 1: about 200 distinct level-3 records over a palette
/// of 16 leaf masks, so that level 3 spans more than 256 words and level 2
/// needs 2-byte pointers.
fn two_byte_pointers() -> Vec<u8> {
    let mut rng = SplitMix(7);
    let palette: Vec<u64> = (0..16).map(|_| rng.next() | 1).collect();
    let mut builder = DagBuilder::new(6, AttributeKind::VoxelCount).expect("depth 6");
    // Bricks 0..1600 cover the first 200 level-3 nodes (8 bricks each).
    for brick in 0..1600u64 {
        let r = rng.next();
        if r % 8 < 3 {
            builder
                .push_brick(brick, palette[(r >> 8) as usize % 16])
                .expect("increasing bricks");
        }
    }
    let dag: BuiltDag = builder.finish().expect("builds");
    dag.to_bytes()
}

/// Bytes between the section table and the first section or between two sections.
fn padding_bytes(bytes: &[u8]) -> u64 {
    let dag = Dag::open(bytes).expect("valid file");
    let mut end = (HEADER_SIZE + dag.sections().len() * SECTION_ENTRY_SIZE) as u64;
    let mut padding = 0;
    for s in dag.sections() {
        padding += s.offset - end;
        end = s.offset + s.length;
    }
    padding
}

/// What part of the file a byte belongs to.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Region {
    /// A header field, by name.
    Header(&'static str),
    /// A section table entry field, by name.
    Table(&'static str),
    /// The bytes of a section, by kind.
    Section(&'static str),
    /// Zero bytes between sections.
    Padding,
}

impl std::fmt::Display for Region {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Region::Header(field) => write!(f, "header.{field}"),
            Region::Table(field) => write!(f, "table.{field}"),
            Region::Section(kind) => write!(f, "section.{kind}"),
            Region::Padding => write!(f, "padding"),
        }
    }
}

/// The region of every byte of a valid file.
fn regions(bytes: &[u8]) -> Vec<Region> {
    const HEADER_FIELDS: &[(usize, &str)] = &[
        (8, "magic"),
        (12, "version"),
        (16, "header_size"),
        (24, "features"),
        (25, "depth"),
        (26, "attribute_kind"),
        (28, "section_count"),
        (32, "reserved0"),
        (56, "root_min"),
        (64, "root_size"),
        (72, "file_size"),
        (80, "voxel_count"),
        (124, "reserved1"),
        (128, "header_crc"),
    ];
    const ENTRY_FIELDS: &[(usize, &str)] = &[
        (4, "kind"),
        (5, "level"),
        (6, "pointer_width"),
        (8, "reserved0"),
        (16, "offset"),
        (24, "length"),
        (32, "item_count"),
        (36, "crc"),
        (40, "reserved1"),
    ];
    let field = |fields: &[(usize, &'static str)], at: usize| {
        fields
            .iter()
            .find(|&&(end, _)| at < end)
            .map(|&(_, name)| name)
            .expect("field table covers the record")
    };
    let dag = dagfmt::AnyDag::open(bytes).expect("valid file");
    let mut map: Vec<Region> = (0..HEADER_SIZE)
        .map(|at| Region::Header(field(HEADER_FIELDS, at)))
        .collect();
    for _ in dag.sections() {
        map.extend((0..SECTION_ENTRY_SIZE).map(|at| Region::Table(field(ENTRY_FIELDS, at))));
    }
    for s in dag.sections() {
        map.resize(s.offset as usize, Region::Padding);
        let kind = match s.kind {
            SectionKind::NodeLevel => "node_level",
            SectionKind::LeafLevel => "leaf_level",
            SectionKind::VoxelColors => "voxel_colors",
            SectionKind::PackedColors => "packed_colors",
            SectionKind::UnknownOptional(_) => "optional",
        };
        map.resize((s.offset + s.length) as usize, Region::Section(kind));
    }
    assert_eq!(map.len(), bytes.len(), "the regions cover the whole file");
    map
}

/// Everything a consumer may do with an opened file: follow every reachable
/// pointer (each distinct record and leaf once), list every voxel, count them,
/// look up each voxel's set bit and dense index, and read the colours. Errors
/// are fine; only panics fail. Returns the number of voxels listed.
fn walk(bytes: &[u8]) -> u64 {
    let dag = match dagfmt::AnyDag::open(bytes) {
        Ok(dagfmt::AnyDag::V1(dag)) => dag,
        Ok(dagfmt::AnyDag::V2(dag)) => return walk_v2(&dag),
        Err(_) => return 0,
    };
    let leaf_level = dag.leaf_level();
    let mut seen = HashSet::new();
    let mut stack: Vec<NodeRef> = dag.root().into_iter().collect();
    while let Some(node) = stack.pop() {
        if !seen.insert(node) {
            continue;
        }
        if node.level == leaf_level {
            let _ = dag.leaf(node.pointer);
            continue;
        }
        if let Ok(n) = dag.node(node.level, node.pointer) {
            let _ = (n.attribute(), n.record_size());
            for child in 0..8 {
                if let Some(pointer) = n.child_pointer(child) {
                    stack.push(NodeRef {
                        level: node.level + 1,
                        pointer,
                    });
                }
            }
        }
    }
    if let Some(root) = dag.root() {
        let _ = dag.subtree_voxel_count(root);
    }
    let _ = dag.colors().map(|c| c.len());
    if let Some(table) = dag.color_table() {
        // Random access and sequential decoding agree, whatever the bytes.
        for (i, c) in table.iter().enumerate() {
            assert_eq!(table.get(i as u64), Some(c));
        }
    }
    let mut voxels = dag.voxels();
    let mut listed = 0u64;
    while let Some(next) = voxels.next_morton() {
        let Ok(code) = next else { break };
        listed += 1;
        // Look every 37th voxel up again by its coordinates.
        if listed % 37 == 1 {
            let [x, y, z] = dagfmt::morton::decode(code);
            let _ = dag.is_set(x, y, z);
            let _ = dag.voxel_index(x, y, z);
        }
    }
    listed
}

/// [`walk`] for a 2.0 file: every record decoded in sequence, every voxel
/// listed (each 37th looked up by its dense index), the colours read.
fn walk_v2(dag: &dagfmt::Dag2<'_>) -> u64 {
    for level in dag.levels().iter().filter(|l| !l.is_leaf) {
        let mut at = 0u64;
        while let Ok(node) = dagfmt::v2::decode_node(level.bytes, at, level.widths) {
            at += u64::from(node.size);
        }
    }
    if let Some(table) = dag.color_table() {
        for (i, c) in table.iter().enumerate() {
            assert_eq!(table.get(i as u64), Some(c));
        }
    }
    let mut listed = 0u64;
    let _ = dag.for_each_leaf(|prefix, mut mask| {
        while mask != 0 {
            listed += 1;
            if listed % 37 == 1 {
                let code = prefix << 6 | u64::from(mask.trailing_zeros());
                let [x, y, z] = dagfmt::morton::decode(code);
                let _ = dag.voxel_index(x, y, z);
            }
            mask &= mask - 1;
        }
        std::ops::ControlFlow::Continue(())
    });
    listed
}

/// The codes reported for a flip, grouped by region, for the summary.
type CodesByRegion = BTreeMap<String, BTreeMap<ErrorCode, u64>>;

/// Flips every bit of `original`, checking the validator and the reader on
/// each; returns the codes seen per region.
fn flip_every_bit(name: &str, original: &[u8]) -> CodesByRegion {
    assert!(
        validate_with(original, &ValidateOptions::default()).is_valid(),
        "{name}: the unflipped file is valid"
    );
    let regions = regions(original);
    let options = ValidateOptions {
        threads: false,
        ..ValidateOptions::default()
    };
    // Errors that end validation before the header checksum is compared
    // (spec/VDAG.md §17.3): bad magic, unsupported version, and a section
    // table that runs past the end of the file.
    let stops_before_header_crc = |codes: &BTreeSet<ErrorCode>| {
        codes.contains(&ErrorCode::BadMagic)
            || codes.contains(&ErrorCode::UnsupportedVersion)
            || codes.contains(&ErrorCode::BadSectionTable)
    };
    let mut summary = CodesByRegion::new();
    let mut bytes = original.to_vec();
    for (at, region) in regions.iter().enumerate() {
        for bit in 0..8 {
            bytes[at] ^= 1 << bit;
            let report = catch_unwind(AssertUnwindSafe(|| validate_with(&bytes, &options)))
                .unwrap_or_else(|_| panic!("{name}: validate panicked, byte {at} bit {bit}"));
            catch_unwind(AssertUnwindSafe(|| walk(&bytes)))
                .unwrap_or_else(|_| panic!("{name}: the reader panicked, byte {at} bit {bit}"));
            let codes: BTreeSet<ErrorCode> = report.errors.iter().map(|e| e.code).collect();
            assert!(
                !codes.is_empty(),
                "{name}: flipping byte {at} bit {bit} ({region}) went undetected"
            );
            let expected = match region {
                Region::Header(_) | Region::Table(_) => {
                    codes.contains(&ErrorCode::HeaderChecksum) || stops_before_header_crc(&codes)
                }
                Region::Section(_) => codes.contains(&ErrorCode::SectionChecksum),
                Region::Padding => codes.contains(&ErrorCode::BadPadding),
            };
            assert!(
                expected,
                "{name}: flipping byte {at} bit {bit} ({region}) gave {codes:?}, \
                 not the code its region calls for"
            );
            let counts = summary.entry(region.to_string()).or_default();
            for code in codes {
                *counts.entry(code).or_default() += 1;
            }
            bytes[at] ^= 1 << bit;
        }
    }
    assert_eq!(bytes, original);
    summary
}

fn print_summary(name: &str, bytes: &[u8], summary: &CodesByRegion) {
    println!("{name}: {} bytes, {} flips", bytes.len(), bytes.len() * 8);
    for (region, counts) in summary {
        let codes: Vec<String> = counts
            .iter()
            .map(|(code, n)| format!("{}×{n}", code.code()))
            .collect();
        println!("  {region:<24} {}", codes.join(" "));
    }
}

/// Checks what the three files are meant to cover, so that a builder change
/// cannot silently shrink the test.
#[test]
fn test_files_cover_kinds_widths_padding_and_colors() {
    let files = [
        ball_with_colors(),
        scattered_with_padding(),
        two_byte_pointers(),
    ];
    let mut kinds = BTreeSet::new();
    let mut widths = BTreeSet::new();
    let mut colors = false;
    for bytes in &files {
        assert!(
            bytes.len() <= 8192,
            "{} bytes: keep the files small",
            bytes.len()
        );
        let dag = Dag::open(bytes).expect("valid");
        kinds.insert(dag.header().attribute_kind.to_raw());
        widths.extend(
            dag.levels()
                .iter()
                .filter(|l| !l.is_leaf)
                .map(|l| l.pointer_width),
        );
        colors |= dag.colors().is_some();
    }
    assert_eq!(kinds, BTreeSet::from([0, 1]));
    assert!(widths.contains(&1) && widths.contains(&2), "{widths:?}");
    assert!(colors);
    assert!(padding_bytes(&files[1]) > 0);
}

#[test]
fn every_bit_flip_in_a_ball_with_colors_is_detected() {
    let bytes = ball_with_colors();
    let summary = flip_every_bit("ball", &bytes);
    print_summary("ball (depth 4, kind 1, colours)", &bytes, &summary);
    assert!(summary.contains_key("section.voxel_colors"));
}

#[test]
fn every_bit_flip_in_a_ball_with_packed_colors_is_detected() {
    let bytes = ball_with_packed_colors();
    let dag = Dag::open(&bytes).expect("valid");
    assert!(dag.packed_colors().is_some());
    let summary = flip_every_bit("packed", &bytes);
    print_summary("ball (depth 4, kind 1, packed colours)", &bytes, &summary);
    assert!(summary.contains_key("section.packed_colors"));
}

#[test]
fn every_bit_flip_in_a_file_with_padding_is_detected() {
    let bytes = scattered_with_padding();
    let summary = flip_every_bit("scattered", &bytes);
    print_summary("scattered (depth 5, kind 0, padding)", &bytes, &summary);
    assert!(summary.contains_key("padding"));
}

#[test]
fn every_bit_flip_in_a_file_with_two_byte_pointers_is_detected() {
    let bytes = two_byte_pointers();
    let summary = flip_every_bit("wide", &bytes);
    print_summary("wide (depth 6, kind 1, 2-byte pointers)", &bytes, &summary);
}

/// A flip anywhere in the transport form is refused by `unpack`, or gives a
/// file the validator rejects, or does not change the unpacked bytes at all.
#[test]
fn every_bit_flip_in_a_2_0_file_is_detected() {
    // Format 2.0 (spec §23.10): the same coverage by checksums and padding.
    let v1 = ball_with_colors();
    let bytes = dagfmt::v2file::upgrade(&Dag::open(&v1).expect("valid")).expect("2.0");
    assert_eq!(
        dagfmt::AnyDag::open(&bytes).expect("opens").version_major(),
        2
    );
    let summary = flip_every_bit("ball with colours, 2.0", &bytes);
    print_summary("ball with colours, 2.0", &bytes, &summary);
}

#[test]
fn every_bit_flip_in_the_transport_form_is_detected_or_harmless() {
    let original = ball_with_colors();
    let packed = transport::pack(&original, 3).expect("packs");
    let mut zst = packed.clone();
    let (mut refused, mut invalid) = (0u64, 0u64);
    // Flips the decoder does not see (the frame header's unused bit, unused
    // bits of entropy-table descriptions): the content and its checksum match.
    let mut unchanged = Vec::new();
    for at in 0..zst.len() {
        for bit in 0..8 {
            zst[at] ^= 1 << bit;
            let outcome = catch_unwind(AssertUnwindSafe(|| {
                transport::unpack(&zst, original.len() as u64 * 4)
            }))
            .unwrap_or_else(|_| panic!("unpack panicked, byte {at} bit {bit}"));
            match outcome {
                Err(_) => refused += 1,
                Ok(unpacked) if unpacked == original => unchanged.push(format!("{at}.{bit}")),
                Ok(unpacked) => {
                    assert!(
                        !dagfmt::validate::validate(&unpacked).is_empty(),
                        "transport byte {at} bit {bit}: a changed file passed validation"
                    );
                    invalid += 1;
                }
            }
            zst[at] ^= 1 << bit;
        }
    }
    println!(
        "transport: {} bytes, {} flips: {refused} refused by unpack, {invalid} rejected by \
         validate, {} decode to the identical file (byte.bit: {})",
        packed.len(),
        packed.len() * 8,
        unchanged.len(),
        unchanged.join(" ")
    );
    assert_eq!(
        refused + invalid + unchanged.len() as u64,
        packed.len() as u64 * 8
    );
    assert!(refused > 0);
}
