//! The validator cases: valid files that must be accepted and malformed files
//! that must be rejected with a given error code.
//!
//! Each malformed file is made from a valid base file by one edit aimed at one
//! rule of spec/VDAG.md § Validation rules; every checksum that the rule is not
//! about is recomputed afterwards, so that (as far as the rule allows) the file
//! breaks exactly that rule. Some rules cannot be broken alone (a truncated
//! header also has the wrong length); the expected code is then the rule the
//! edit targets, which a validator checks first.

use dagfmt::builder::DagBuilder;
use dagfmt::layout::{self, SectionKind};
use dagfmt::packed_colors::BlockLayout;
use dagfmt::{AttributeKind, ErrorCode, morton};

use crate::model::{
    self, DagModel, EncodeOptions, JoinOptions, Placement, RawFile, RawSection, entry, entry_field,
    put_u16, put_u32, put_u64,
};
use crate::model2::{self, ChildRef, Layout2Options, Model2};

/// One validator case.
#[derive(Clone, Debug)]
pub struct ValidateCase {
    /// File stem (`validate/<name>.vdag`).
    pub name: String,
    /// What the file is, for people.
    pub description: String,
    /// The file.
    pub file: Vec<u8>,
    /// `None`: valid; else the code a validator must report.
    pub expected: Option<ErrorCode>,
}

/// Rules no file-based case can exercise, with the reason (listed in
/// spec/CONFORMANCE.md and by `conformance list`).
pub const UNTESTABLE: &[(ErrorCode, &str)] = &[(
    ErrorCode::FileTooLarge,
    "needs a file over the 1 TiB reader limit",
)];

/// The voxels of the base file: a motif repeated in several places (so that
/// level-2 nodes and leaves are shared by several parents), single voxels
/// (nodes with one child, hence padding), and a few bricks of their own.
fn base_voxels() -> Vec<[u32; 3]> {
    let mut voxels = Vec::new();
    let motif = [
        [0, 0, 0],
        [1, 0, 0],
        [3, 2, 1],
        [2, 3, 3],
        [5, 4, 6],
        [6, 6, 2],
        [9, 1, 12],
        [13, 13, 13],
    ];
    for base in [
        [0, 0, 0],
        [32, 0, 0],
        [0, 32, 32],
        [48, 16, 0],
        [16, 48, 48],
    ] {
        for m in motif {
            voxels.push([base[0] + m[0], base[1] + m[1], base[2] + m[2]]);
        }
    }
    voxels.extend([
        [17, 3, 29],
        [62, 62, 62],
        [9, 22, 5],
        [40, 41, 42],
        [33, 60, 7],
    ]);
    for x in 20..28 {
        for y in 36..40 {
            voxels.push([x, y, (x * 3 + y) % 64]);
        }
    }
    voxels.sort_by_key(|v| morton::encode(v[0], v[1], v[2]));
    voxels
}

fn build(kind: AttributeKind) -> Vec<u8> {
    DagBuilder::from_voxels(6, kind, base_voxels())
        .expect("base volume")
        .to_bytes()
}

fn colors(count: u64) -> Vec<u8> {
    (0..count)
        .flat_map(|i| [(i * 37) as u8, (i * 11) as u8, (i * 5 + 3) as u8, 255])
        .collect()
}

fn with_colors(bytes: &[u8]) -> Vec<u8> {
    let mut model = DagModel::decode(bytes).expect("base decodes");
    model.extra.push(model::ExtraSection {
        kind: SectionKind::VOXEL_COLORS,
        item_count: model.voxel_count,
        bytes: colors(model.voxel_count),
    });
    model.encode()
}

/// Colours for a PACKED_COLORS section of the base file: block 0 a palette of
/// three colours (R widths 5, G 4, B 0; index width 2; sub-block 2 mixed, the
/// others uniform: 15 bytes, the last with 7 padding bits), block 1 (the rest)
/// direct.
fn packable_colors(count: u64) -> Vec<[u8; 4]> {
    (0..count)
        .map(|i| match i {
            0..20 => [200, 100, 50, 255],
            20..40 => [210, 100, 50, 255],
            40..64 => [220, 110, 50, 255],
            _ => [(i * 37) as u8, (i * 11) as u8, (i * 5 + 3) as u8, 255],
        })
        .collect()
}

/// The base file with a PACKED_COLORS section holding `section` for
/// `item_count` colours.
fn with_packed_section(bytes: &[u8], item_count: u64, section: Vec<u8>) -> Vec<u8> {
    let mut model = DagModel::decode(bytes).expect("base decodes");
    model.extra.push(model::ExtraSection {
        kind: SectionKind::PACKED_COLORS,
        item_count,
        bytes: section,
    });
    model.encode()
}

/// The base file's colours packed losslessly in format 1.1's layout (64
/// colours a block, no split sub-blocks), as a 1.1 writer wrote them.
fn packed_v1_1(colors: &[[u8; 4]]) -> Vec<u8> {
    dagfmt::packed_colors::encode_with_layout(colors, 0, BlockLayout::V1_1)
        .expect("bound 0")
        .0
}

/// A packed section of the base file's colours, lossless, in format 1.1's
/// layout, edited by `f`.
fn packed_edit(bytes: &[u8], f: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
    let count = DagModel::decode(bytes).expect("base decodes").voxel_count;
    let mut section = packed_v1_1(&packable_colors(count));
    f(&mut section);
    with_packed_section(bytes, count, section)
}

/// Colours for a format 1.2 section of the base file: runs of 5 that make
/// the sub-blocks of 8 split (two indices and a position) or uniform.
fn split_colors(count: u64) -> Vec<[u8; 4]> {
    (0..count)
        .map(|i| {
            let c = (i / 5 % 3) as u8;
            [40 * c, 200 - 30 * c, 90, 255]
        })
        .collect()
}

/// A lossless format 1.2 section of the base file's colours (blocks of 128
/// colours with split sub-blocks), edited by `f`.
fn split_edit(bytes: &[u8], f: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
    let count = DagModel::decode(bytes).expect("base decodes").voxel_count;
    let layout = BlockLayout {
        shift: 7,
        split: true,
    };
    let (mut section, _) =
        dagfmt::packed_colors::encode_with_layout(&split_colors(count), 0, layout)
            .expect("bound 0");
    f(&mut section);
    with_packed_section(bytes, count, section)
}

/// Edits bytes in place and recomputes every checksum.
fn edit(bytes: &[u8], f: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
    let mut out = bytes.to_vec();
    f(&mut out);
    model::fix_checksums(&mut out);
    out
}

/// Edits bytes in place and recomputes only the header checksum.
fn edit_keep_section_crcs(bytes: &[u8], f: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
    let mut out = bytes.to_vec();
    f(&mut out);
    model::fix_header_checksum(&mut out);
    out
}

/// How many pointers reference each node of the level below `level`.
fn reference_counts(m: &DagModel, level: usize) -> Vec<u32> {
    let len = if level + 1 == m.levels.len() {
        m.leaves.len()
    } else {
        m.levels[level + 1].len()
    };
    let mut refs = vec![0u32; len];
    for node in &m.levels[level] {
        for &c in &node.children {
            refs[c as usize] += 1;
        }
    }
    refs
}

/// Byte offset in the file of the node record `index` of interior `level`.
fn record_offset(bytes: &[u8], level: usize, index: usize) -> usize {
    let dag = dagfmt::Dag::open(bytes).expect("valid");
    let section = &dag.levels()[level];
    let mut word = 0u32;
    for _ in 0..index {
        word += (dag.node(level as u8, word).expect("record").record_size() / 4) as u32;
    }
    section.file_offset as usize + word as usize * 4
}

/// Word offset of node `index` in interior `level`.
fn record_word(bytes: &[u8], level: usize, index: usize) -> u32 {
    let dag = dagfmt::Dag::open(bytes).expect("valid");
    let start = dag.levels()[level].file_offset as usize;
    ((record_offset(bytes, level, index) - start) / 4) as u32
}

fn case(name: &str, description: &str, file: Vec<u8>, expected: Option<ErrorCode>) -> ValidateCase {
    ValidateCase {
        name: name.into(),
        description: description.into(),
        file,
        expected,
    }
}

/// Every validator case, in a fixed order.
pub fn validate_cases() -> Vec<ValidateCase> {
    let base = build(AttributeKind::VoxelCount);
    let base0 = build(AttributeKind::None);
    let colored = with_colors(&base);
    let model = DagModel::decode(&base).expect("base decodes");
    let raw = RawFile::split(&base).expect("base splits");
    let depth = usize::from(model.depth);
    let leaf_level = depth - 2;
    let mut cases = Vec::new();
    let mut bad = |code: ErrorCode, suffix: &str, description: &str, file: Vec<u8>| {
        let name = if suffix.is_empty() {
            format!("{}-{}", code.code(), code.name())
        } else {
            format!("{}-{}-{suffix}", code.code(), code.name())
        };
        cases.push(case(&name, description, file, Some(code)));
    };

    // ---- Header.
    bad(
        ErrorCode::TruncatedHeader,
        "",
        "the file is cut after 100 bytes",
        base[..100].to_vec(),
    );
    bad(
        ErrorCode::BadMagic,
        "",
        "the second magic byte is 'W' instead of 'V'",
        edit(&base, |b| b[1] = b'W'),
    );
    bad(
        ErrorCode::UnsupportedVersion,
        "",
        "major version 3",
        edit(&base, |b| put_u16(b, 8, 3)),
    );
    bad(
        ErrorCode::UnknownRequiredFeature,
        "",
        "required feature bit 0 set",
        edit(&base, |b| put_u32(b, 16, 1)),
    );
    bad(
        ErrorCode::BadHeaderSize,
        "",
        "header size 136",
        edit(&base, |b| put_u32(b, 12, 136)),
    );
    bad(
        ErrorCode::DepthOutOfRange,
        "",
        "depth 22",
        edit(&base, |b| b[24] = 22),
    );
    bad(
        ErrorCode::UnknownAttributeKind,
        "",
        "attribute kind 9",
        edit(&base, |b| b[25] = 9),
    );
    bad(
        ErrorCode::BadRootCube,
        "zero-size",
        "root cube size 0",
        edit(&base, |b| put_u64(b, 56, 0f64.to_bits())),
    );
    bad(
        ErrorCode::BadRootCube,
        "nan-min",
        "root cube corner y is NaN",
        edit(&base, |b| put_u64(b, 40, f64::NAN.to_bits())),
    );
    bad(
        ErrorCode::NonzeroReserved,
        "header",
        "header reserved0 is 1",
        edit(&base, |b| put_u32(b, 28, 1)),
    );
    bad(
        ErrorCode::NonzeroReserved,
        "header-tail",
        "a byte of the 44 reserved header bytes is 1",
        edit(&base, |b| b[100] = 1),
    );
    bad(
        ErrorCode::NonzeroReserved,
        "section-entry",
        "the second reserved field of section 1 is 1",
        edit(&base, |b| put_u32(b, entry_field(1, entry::RESERVED1), 1)),
    );
    bad(
        ErrorCode::FileSizeMismatch,
        "",
        "the header's file size is 8 bytes more than the file's length",
        {
            edit(&base, |b| {
                let size = model::get_u64(b, 64);
                put_u64(b, 64, size + 8)
            })
        },
    );
    bad(
        ErrorCode::HeaderChecksum,
        "",
        "the header checksum has one bit flipped",
        {
            let mut b = base.clone();
            b[layout::HEADER_CRC_OFFSET] ^= 1;
            b
        },
    );
    bad(
        ErrorCode::BadSectionTable,
        "",
        "65 sections declared (more than 64)",
        edit(&base, |b| put_u16(b, 26, 65)),
    );

    // ---- Section table and placement.
    let last = raw.sections.len() - 1;
    bad(
        ErrorCode::SectionOutOfBounds,
        "",
        "the leaf level declares one more leaf, running 8 bytes past the end of the file",
        {
            let mut r = raw.clone();
            r.sections[last].entry.length += 8;
            r.sections[last].entry.item_count += 1;
            r.join(&JoinOptions {
                keep_length: vec![last],
                ..JoinOptions::default()
            })
        },
    );
    // A section whose predecessor ends 4 bytes past a multiple of 8, stored
    // right after it (no padding): misaligned, nothing else wrong.
    let odd = (0..last).find(|&i| raw.sections[i].bytes.len() % 8 == 4);
    if let Some(i) = odd {
        bad(
            ErrorCode::SectionMisaligned,
            "",
            &format!(
                "section {} starts right after section {i}, 4 bytes past a multiple of 8",
                i + 1
            ),
            raw.join(&JoinOptions {
                placement: vec![(i + 1, Placement::Packed)],
                ..JoinOptions::default()
            }),
        );
        bad(
            ErrorCode::BadPadding,
            "nonzero",
            &format!("a padding byte after section {i} is 0x5a"),
            {
                let mut b = base.clone();
                let end = model::get_u64(&b, entry_field(i, entry::OFFSET))
                    + model::get_u64(&b, entry_field(i, entry::LENGTH));
                b[end as usize + 1] = 0x5a;
                b
            },
        );
    }
    bad(
        ErrorCode::BadPadding,
        "not-minimal",
        "8 extra zero bytes before section 2 (padding must be minimal)",
        raw.join(&JoinOptions {
            placement: vec![(2, Placement::Gap(8))],
            ..JoinOptions::default()
        }),
    );
    bad(
        ErrorCode::SectionOverlap,
        "",
        "an optional section made of the last 8 bytes of the leaf level (it overlaps the leaf level)",
        {
            let mut r = raw.clone();
            let tail = r.sections[last].bytes[r.sections[last].bytes.len() - 8..].to_vec();
            r.sections.push(RawSection::new(0x8000_0042, 0, 0, 1, tail));
            let mut b = r.join(&JoinOptions::default());
            let leaf_end = model::get_u64(&b, entry_field(last, entry::OFFSET))
                + model::get_u64(&b, entry_field(last, entry::LENGTH));
            put_u64(&mut b, entry_field(last + 1, entry::OFFSET), leaf_end - 8);
            b.truncate(leaf_end as usize);
            put_u64(&mut b, 64, leaf_end);
            model::fix_header_checksum(&mut b);
            b
        },
    );
    bad(
        ErrorCode::BadLevelSections,
        "level",
        "section 1 claims level 2",
        edit(&base, |b| b[entry_field(1, entry::LEVEL)] = 2),
    );
    bad(
        ErrorCode::BadLevelSections,
        "kind",
        "section 0 is a leaf-level section",
        edit(&base, |b| {
            put_u32(b, entry_field(0, entry::KIND), SectionKind::LEAF_LEVEL)
        }),
    );
    bad(
        ErrorCode::UnknownSectionKind,
        "",
        "an extra section of unknown required kind 0x44",
        {
            let mut r = raw.clone();
            r.sections
                .push(RawSection::new(0x44, 0, 0, 1, vec![1, 2, 3, 4, 5, 6, 7, 8]));
            r.join(&JoinOptions::default())
        },
    );
    bad(
        ErrorCode::BadPointerWidth,
        "node",
        "level 1 declares pointer width 5",
        edit(&base, |b| b[entry_field(1, entry::WIDTH)] = 5),
    );
    bad(
        ErrorCode::BadPointerWidth,
        "leaf",
        "the leaf level declares pointer width 1",
        edit(&base, |b| b[entry_field(leaf_level, entry::WIDTH)] = 1),
    );
    let mut widths = vec![None; leaf_level];
    widths[leaf_level - 1] = Some(2);
    bad(
        ErrorCode::PointerWidthNotMinimal,
        "",
        &format!(
            "level {} uses 2-byte pointers where 1 byte addresses every leaf",
            leaf_level - 1
        ),
        model.encode_with(&EncodeOptions { widths }),
    );
    bad(
        ErrorCode::SectionChecksum,
        "",
        "the stored checksum of section 2 has one bit flipped",
        edit_keep_section_crcs(&base, |b| b[entry_field(2, entry::CRC)] ^= 1),
    );
    bad(
        ErrorCode::LevelTooLarge,
        "",
        "the leaf level declares 2^32 + 1 leaves",
        {
            edit(&base, |b| {
                put_u64(b, entry_field(leaf_level, entry::ITEM_COUNT), (1 << 32) + 1)
            })
        },
    );

    // ---- Nodes and pointers.
    bad(
        ErrorCode::BadRootLevel,
        "",
        "level 0 holds two copies of the root",
        {
            let mut m = model.clone();
            let root = m.levels[0][0].clone();
            m.levels[0].push(root);
            m.encode()
        },
    );
    // A level-(D-3) node with one child whose leaf other nodes also reference.
    let refs = reference_counts(&model, leaf_level - 1);
    let lone = model.levels[leaf_level - 1]
        .iter()
        .position(|n| n.children.len() == 1 && refs[n.children[0] as usize] > 1)
        .expect("the base has a one-child node over a shared leaf");
    bad(
        ErrorCode::EmptyChildMask,
        "",
        &format!(
            "node {lone} of level {} has an empty child mask (its leaf stays referenced)",
            leaf_level - 1
        ),
        {
            let mut m = model.clone();
            m.levels[leaf_level - 1][lone].mask = 0;
            m.levels[leaf_level - 1][lone].children.clear();
            m.recompute_counts();
            m.encode()
        },
    );
    bad(
        ErrorCode::TruncatedNode,
        "",
        "the last record of level 1 loses its pointers (the section ends after its header)",
        {
            let mut r = raw.clone();
            let bytes = &mut r.sections[1].bytes;
            let last_start =
                record_offset(&base, 1, model.levels[1].len() - 1) - raw_offset(&base, 1);
            bytes.truncate(last_start + 4);
            r.join(&JoinOptions::default())
        },
    );
    bad(
        ErrorCode::ItemCountMismatch,
        "node",
        "level 2 declares one node fewer than it holds",
        {
            edit(&base, |b| {
                let at = entry_field(2, entry::ITEM_COUNT);
                let count = model::get_u64(b, at);
                put_u64(b, at, count - 1)
            })
        },
    );
    bad(
        ErrorCode::ItemCountMismatch,
        "leaf",
        "the leaf level declares one leaf more than it holds",
        {
            edit(&base, |b| {
                let at = entry_field(leaf_level, entry::ITEM_COUNT);
                let count = model::get_u64(b, at);
                put_u64(b, at, count + 1)
            })
        },
    );
    bad(
        ErrorCode::NonzeroNodePadding,
        "",
        &format!(
            "the padding after the pointer of node {lone} of level {} is 1",
            leaf_level - 1
        ),
        {
            edit(&base, |b| {
                let at = record_offset(&base, leaf_level - 1, lone);
                b[at + 7] = 1
            })
        },
    );
    bad(
        ErrorCode::PointerOutOfRange,
        "",
        &format!(
            "node {lone} of level {} points to leaf {} (past the last leaf)",
            leaf_level - 1,
            model.leaves.len()
        ),
        {
            edit(&base, |b| {
                let at = record_offset(&base, leaf_level - 1, lone);
                b[at + 4] = model.leaves.len() as u8
            })
        },
    );
    // A level-2 node referenced more than once, and one parent pointer to it.
    let refs2 = reference_counts(&model, 1);
    let shared = refs2
        .iter()
        .position(|&r| r > 1)
        .expect("the base shares a level-2 node");
    let (parent, rank) = model.levels[1]
        .iter()
        .enumerate()
        .find_map(|(i, n)| {
            n.children
                .iter()
                .position(|&c| c as usize == shared)
                .map(|r| (i, r))
        })
        .expect("a parent");
    bad(
        ErrorCode::PointerNotAtNode,
        "",
        &format!(
            "a pointer of node {parent} of level 1 addresses the middle of a shared level-2 record"
        ),
        {
            edit(&base, |b| {
                let at = record_offset(&base, 1, parent) + 4 + rank;
                b[at] = (record_word(&base, 2, shared) + 1) as u8
            })
        },
    );
    bad(
        ErrorCode::UnreferencedNode,
        "",
        "an extra leaf that no pointer references",
        {
            let mut m = model.clone();
            m.leaves.push(0x8000_0000_0000_0001);
            m.encode()
        },
    );
    bad(
        ErrorCode::EmptyLeafMask,
        "",
        "a leaf mask is zero (counts above it adjusted)",
        {
            let mut m = model.clone();
            let leaf = m
                .leaves
                .iter()
                .position(|&l| l.count_ones() > 1)
                .expect("a leaf");
            m.leaves[leaf] = 0;
            m.recompute_counts();
            m.encode()
        },
    );

    // ---- Attributes and colours.
    bad(
        ErrorCode::NonzeroAttribute,
        "",
        "attribute kind 0 but a level-1 node's attribute is 5",
        {
            let mut m = DagModel::decode(&base0).expect("decodes");
            m.levels[1][0].attribute = 5;
            m.encode()
        },
    );
    bad(
        ErrorCode::WrongVoxelCount,
        "",
        "a level-2 node's voxel count is one too high",
        {
            let mut m = model.clone();
            m.levels[2][0].attribute += 1;
            m.encode()
        },
    );
    bad(
        ErrorCode::HeaderVoxelCount,
        "",
        "the header's voxel count is one too high",
        {
            edit(&base, |b| {
                let count = model::get_u64(b, 72);
                put_u64(b, 72, count + 1)
            })
        },
    );
    bad(
        ErrorCode::BadColorSection,
        "twice",
        "two colour sections",
        {
            let mut m = DagModel::decode(&colored).expect("decodes");
            let c = m.extra[0].clone();
            m.extra.push(c);
            m.encode()
        },
    );
    bad(
        ErrorCode::BadColorSection,
        "count",
        "the colour section holds one colour fewer than there are voxels",
        {
            let mut m = DagModel::decode(&colored).expect("decodes");
            m.extra[0].item_count -= 1;
            let len = m.extra[0].bytes.len();
            m.extra[0].bytes.truncate(len - 4);
            m.encode()
        },
    );
    bad(
        ErrorCode::BadColorSection,
        "kind0",
        "a colour section in a file with attribute kind 0",
        {
            let mut m = DagModel::decode(&base0).expect("decodes");
            m.extra.push(model::ExtraSection {
                kind: SectionKind::VOXEL_COLORS,
                item_count: m.voxel_count,
                bytes: colors(m.voxel_count),
            });
            m.encode()
        },
    );

    // ---- Packed colours (§12.6). The base file's section: block 0 at 0
    // (15 bytes: header 0x02, widths 0x45 0x00, base 200 100 50, uniform
    // 0xfb, then 27 bits of entries and 30 of indices), block 1 direct, the
    // directory's one entry, the trailer.
    let packed_count = model.voxel_count;
    let directory_at = |section: &[u8]| section.len() - 16 - 32;
    bad(
        ErrorCode::BadPackedColorSection,
        "twice",
        "a VOXEL_COLORS and a PACKED_COLORS section",
        with_packed_section(
            &colored,
            packed_count,
            packed_v1_1(&packable_colors(packed_count)),
        ),
    );
    bad(
        ErrorCode::BadPackedColorSection,
        "count",
        "the packed colour section's item count is one less than the voxels",
        with_packed_section(
            &base,
            packed_count - 1,
            packed_v1_1(&packable_colors(packed_count - 1)),
        ),
    );
    bad(
        ErrorCode::BadPackedColorSection,
        "kind0",
        "a packed colour section in a file with attribute kind 0",
        with_packed_section(
            &base0,
            packed_count,
            packed_v1_1(&packable_colors(packed_count)),
        ),
    );
    bad(
        ErrorCode::BadPackedColorSection,
        "short",
        "a packed colour section of 40 bytes, shorter than its directory and trailer (48)",
        packed_edit(&base, |s| {
            let tail = s.split_off(s.len() - 16);
            s.truncate(24);
            s.extend_from_slice(&tail);
        }),
    );
    bad(
        ErrorCode::BadColorTrailer,
        "shift",
        "the trailer's block shift is 5 (6, 7 or 8 are allowed)",
        packed_edit(&base, |s| {
            let at = s.len() - 15;
            s[at] = 5;
        }),
    );
    bad(
        ErrorCode::BadColorTrailer,
        "bound",
        "the trailer's error bound is 200",
        packed_edit(&base, |s| {
            let at = s.len() - 16;
            s[at] = 200;
        }),
    );
    bad(
        ErrorCode::BadColorTrailer,
        "measured",
        "the trailer's measured error, 1, exceeds its bound, 0",
        packed_edit(&base, |s| {
            let at = s.len() - 14;
            s[at] = 1;
        }),
    );
    bad(
        ErrorCode::BadColorTrailer,
        "reserved",
        "a reserved trailer byte (offset 4) is 1",
        packed_edit(&base, |s| {
            let at = s.len() - 12;
            s[at] = 1;
        }),
    );
    bad(
        ErrorCode::BadColorTrailer,
        "flags",
        "the trailer's flags have bit 1 set, which no version defines",
        packed_edit(&base, |s| {
            let at = s.len() - 13;
            s[at] = 2;
        }),
    );
    bad(
        ErrorCode::BadColorTrailer,
        "squared",
        "a squared error of 1 with a measured error of 0",
        packed_edit(&base, |s| {
            let at = s.len() - 8;
            s[at] = 1;
        }),
    );
    bad(
        ErrorCode::BadColorDirectory,
        "empty-block",
        "block 1 starts at 0, leaving block 0 empty",
        packed_edit(&base, |s| {
            let d = directory_at(s);
            // Bits 40 .. 53 of the entry: block 1's offset.
            s[d + 5] = 0;
            s[d + 6] &= !0x1f;
        }),
    );
    bad(
        ErrorCode::BadColorDirectory,
        "unused-bits",
        "the last, unused bit of the directory entry is set",
        packed_edit(&base, |s| {
            let d = directory_at(s);
            s[d + 31] = 0x80;
        }),
    );
    bad(
        ErrorCode::BadColorBlock,
        "width",
        "block 0's red width is 9",
        packed_edit(&base, |s| s[1] = 0x49),
    );
    bad(
        ErrorCode::BadColorBlock,
        "palette",
        "block 1, of 13 colours, claims a palette of 16",
        packed_edit(&base, |s| {
            let d = directory_at(s);
            let block1 = usize::from(s[d + 5]) | usize::from(s[d + 6] & 0x1f) << 8;
            s[block1] = 15;
        }),
    );
    bad(
        ErrorCode::ColorBlockLength,
        "",
        "block 0's red width is 8, which makes it 16 bytes long; the directory says 15",
        packed_edit(&base, |s| s[1] = 0x48),
    );
    bad(
        ErrorCode::ColorBlockPadding,
        "",
        "the last padding bit of block 0 is set",
        packed_edit(&base, |s| s[14] |= 0x80),
    );
    bad(
        ErrorCode::ColorIndexOutOfRange,
        "",
        "block 0's first palette index is 3, its palette holds 3 colours",
        packed_edit(&base, |s| s[10] |= 0x18),
    );
    bad(
        ErrorCode::ColorValueOutOfRange,
        "",
        "block 0's red base is 250, so its third entry (20 steps up) starts past 255",
        packed_edit(&base, |s| s[3] = 250),
    );
    // ---- Format 1.2: the base file's colours in one block of 128 with
    // split sub-blocks (header 0x02, widths 0x67 0x00, base 0 140 90, the
    // uniform mask 0x0000, then the stream from byte 8: ten split flags, the
    // palette's three 13-bit entries, and sub-block 0, which is split: index
    // a, index b (2 bits each) and its 3-bit position, 5).
    bad(
        ErrorCode::BadSplitSubBlock,
        "position",
        "sub-block 0 of block 0 is split at position 0, not inside its colours",
        split_edit(&base, |s| {
            let stream = 1 + 2 + 3 + 2;
            let at = 10 + 3 * 13 + 2 * 2;
            for bit in at..at + 3 {
                s[stream + bit / 8] &= !(1 << (bit % 8));
            }
        }),
    );

    // ---- Format 2.0 (spec §23.10), from the base volume upgraded.
    let base2 = dagfmt::v2file::upgrade(&dagfmt::Dag::open(&base).expect("base")).expect("2.0");
    let m2 = Model2::decode(&base2).expect("base 2.0 decodes");
    assert_eq!(
        m2.encode(),
        base2,
        "the 2.0 model lays the base file out as the encoder"
    );
    let leaf2 = m2.levels.len();
    bad(
        ErrorCode::BadWidths,
        "",
        "2.0: level 1's widths are w1 > w2",
        edit(&base2, |b| {
            let at = model2::entry_of(1);
            b[at] = b[at + 1] + 1;
        }),
    );
    bad(
        ErrorCode::BadWidths,
        "leaf",
        "2.0: byte 6 of the leaf level's entry is 1",
        edit(&base2, |b| b[model2::entry_of(leaf2) + 1] = 1),
    );
    bad(
        ErrorCode::TruncatedRecord2,
        "",
        "2.0: level 1 ends with one byte of a record",
        {
            let mut r = RawFile::split(&base2).expect("splits");
            r.sections[1].bytes.push(0x01);
            r.join(&JoinOptions::default())
        },
    );
    bad(
        ErrorCode::NonzeroBitPadding,
        "",
        "2.0: the last bit of a record of level 1 whose references end inside its last byte is set",
        {
            let dag = dagfmt::Dag2::open(&base2).expect("2.0");
            let n = dag.levels()[1].item_count as usize;
            let (index, (at, bits)) = (0..n)
                .map(|i| (i, Model2::record(&base2, 1, i)))
                .find(|(_, (_, bits))| bits % 8 != 0)
                .expect("a record with padding bits");
            let _ = index;
            let size = 4 + bits.div_ceil(8) as usize;
            edit(&base2, |b| b[at + size - 1] |= 0x80)
        },
    );
    bad(
        ErrorCode::ReferenceOutOfRange2,
        "",
        "2.0: a shared reference of the deepest node level names a leaf past the leaf level",
        {
            let mut m = m2.clone();
            let last = leaf2 - 1;
            let n = m.leaves.len();
            'found: for rec in &mut m.levels[last] {
                for c in rec.children.iter_mut().flatten() {
                    if let ChildRef::Shared { item, .. } = c {
                        *item = n + 5;
                        break 'found;
                    }
                }
            }
            m.encode()
        },
    );
    bad(
        ErrorCode::WidthNotMinimal,
        "level",
        "2.0: level 1's widest width is one more than its references need",
        {
            let dag = dagfmt::Dag2::open(&base2).expect("2.0");
            let mut w = dag.levels()[1].widths;
            w[2] += 1;
            m2.encode_with(&Layout2Options {
                widths: vec![(1, w)],
                ..Default::default()
            })
        },
    );
    bad(
        ErrorCode::WidthNotMinimal,
        "reference",
        "2.0: the root's first reference uses code 3 where a narrower width holds it",
        m2.encode_with(&Layout2Options {
            widen: Some((0, 0, 0)),
            ..Default::default()
        }),
    );
    // A shared leaf named at least four times: split into two copies.
    let naming = m2.naming(leaf2 - 1);
    bad(
        ErrorCode::DuplicateClass,
        "",
        "2.0: a leaf named by four or more references is stored twice, each copy named twice or more",
        {
            let mut m = m2.clone();
            let item = naming
                .iter()
                .position(|&(s, _)| s >= 4)
                .expect("a leaf named 4 times");
            let copy = m.leaves.len();
            m.leaves.push(m.leaves[item]);
            let mut moved = 0;
            for rec in &mut m.levels[leaf2 - 1] {
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
            m.encode()
        },
    );
    bad(
        ErrorCode::NotCanonical,
        "",
        "2.0: a shared leaf is stored mirrored in x, and every reference to it carries the mirror",
        {
            let mut m = m2.clone();
            let item = (0..m.leaves.len())
                .find(|&i| {
                    naming[i].0 >= 2
                        && dagfmt::symmetry::reflect_leaf(m.leaves[i], 1) != m.leaves[i]
                })
                .expect("an asymmetric shared leaf");
            m.leaves[item] = dagfmt::symmetry::reflect_leaf(m.leaves[item], 1);
            for rec in &mut m.levels[leaf2 - 1] {
                for c in rec.children.iter_mut().flatten() {
                    if let ChildRef::Shared { item: i, r } = c
                        && *i == item
                    {
                        *r ^= 1;
                    }
                }
            }
            m.encode()
        },
    );
    bad(
        ErrorCode::BadLevelOrder,
        "",
        "2.0: the first two shared leaves, named by different numbers of references, are swapped",
        {
            let mut m = m2.clone();
            let a = 0;
            let b = (1..m.leaves.len())
                .find(|&i| naming[i].0 >= 2 && naming[i].0 != naming[a].0)
                .expect("two shared leaves with different counts");
            m.leaves.swap(a, b);
            for rec in &mut m.levels[leaf2 - 1] {
                for c in rec.children.iter_mut().flatten() {
                    if let ChildRef::Shared { item: i, .. } = c {
                        if *i == a {
                            *i = b;
                        } else if *i == b {
                            *i = a;
                        }
                    }
                }
            }
            m.encode()
        },
    );
    bad(
        ErrorCode::BadSharing,
        "",
        "2.0: the last sequential child of a record of the deepest node level is named by a shared reference instead (one reference)",
        {
            let mut m = m2.clone();
            'found: for rec in &mut m.levels[leaf2 - 1] {
                if let Some(c) = rec
                    .children
                    .iter_mut()
                    .rev()
                    .flatten()
                    .find(|c| matches!(c, ChildRef::Sequential { .. }))
                {
                    let ChildRef::Sequential { item } = *c else {
                        unreachable!()
                    };
                    *c = ChildRef::Shared { item, r: 0 };
                    break 'found;
                }
            }
            m.encode()
        },
    );
    bad(
        ErrorCode::ItemCountMismatch2,
        "",
        "2.0: level 1 declares one record more than it holds",
        edit(&base2, |b| {
            let at = entry_field(1, entry::ITEM_COUNT);
            let n = model::get_u64(b, at);
            put_u64(b, at, n + 1);
        }),
    );

    // ---- Valid files that exercise the lenient parts of the format.
    let mut good = vec![
        case(
            "valid-base",
            "the base file every malformed case is made from (depth 6, attribute kind 1)",
            base.clone(),
            None,
        ),
        case(
            "valid-kind0",
            "the base volume with attribute kind 0",
            base0.clone(),
            None,
        ),
        case(
            "valid-colors",
            "the base file with a voxel colour section",
            colored.clone(),
            None,
        ),
    ];
    good.push(case(
        "valid-v2",
        "the base file as format 2.0 (dagtool upgrade)",
        base2.clone(),
        None,
    ));
    good.push(case(
        "valid-v2-kind0",
        "the base volume with attribute kind 0, as format 2.0",
        dagfmt::v2file::upgrade(&dagfmt::Dag::open(&base0).expect("kind 0")).expect("2.0"),
        None,
    ));
    good.push(case(
        "valid-v2-colors",
        "the base file with a voxel colour section, as format 2.0",
        dagfmt::v2file::upgrade(&dagfmt::Dag::open(&colored).expect("colours")).expect("2.0"),
        None,
    ));
    good.push(case(
        "valid-v2-empty",
        "an empty depth-5 volume as format 2.0",
        dagfmt::v2file::upgrade(
            &dagfmt::Dag::open(
                &DagBuilder::from_voxels(5, AttributeKind::VoxelCount, [])
                    .expect("empty")
                    .to_bytes(),
            )
            .expect("empty"),
        )
        .expect("2.0"),
        None,
    ));
    good.push(case(
        "valid-packed-colors",
        "the base file with a lossless PACKED_COLORS section: a palette block and a direct block",
        packed_edit(&base, |_| {}),
        None,
    ));
    good.push(case(
        "valid-packed-colors-split",
        "the base file with a lossless format 1.2 PACKED_COLORS section: one block of 128 colours with split sub-blocks",
        split_edit(&base, |_| {}),
        None,
    ));
    good.push(case(
        "valid-packed-colors-lossy",
        "the base file with a PACKED_COLORS section within 3 per channel, with alpha",
        {
            let colors: Vec<[u8; 4]> = (0..model.voxel_count)
                .map(|i| [(i * 37) as u8, (i * 3) as u8, 7, 200 + (i % 5) as u8])
                .collect();
            let (section, _) =
                dagfmt::packed_colors::encode_with_layout(&colors, 3, BlockLayout::V1_1)
                    .expect("E 3");
            with_packed_section(&base, model.voxel_count, section)
        },
        None,
    ));
    let mut m = model.clone();
    m.extra.push(model::ExtraSection {
        kind: 0x8000_0123,
        item_count: 3,
        bytes: b"optional data, skip me!\0".to_vec(),
    });
    good.push(case(
        "valid-optional-section",
        "an unknown optional section (kind 0x80000123) after the levels",
        m.encode(),
        None,
    ));
    let mut m = model.clone();
    m.version_minor = 7;
    m.optional_features = 0x10;
    good.push(case(
        "valid-minor-version",
        "minor version 7 with an unknown optional feature bit set",
        m.encode(),
        None,
    ));
    let mut m = model.clone();
    m.root_min = [-1e6, 0.5, 3.25];
    m.root_size = 1e-3;
    good.push(case(
        "valid-root-cube",
        "an unusual root cube (corner -1e6, size 1e-3)",
        m.encode(),
        None,
    ));
    good.push(case(
        "valid-empty-d21",
        "an empty volume of the largest depth, 21",
        DagBuilder::from_voxels(21, AttributeKind::VoxelCount, [])
            .expect("empty")
            .to_bytes(),
        None,
    ));
    good.push(case(
        "valid-corner-d21",
        "one voxel at the far corner of a depth-21 volume",
        DagBuilder::from_voxels(21, AttributeKind::VoxelCount, [[(1 << 21) - 1; 3]])
            .expect("one voxel")
            .to_bytes(),
        None,
    ));
    good.extend(cases);
    good
}

/// Byte offset in the file of the section of interior `level`.
fn raw_offset(bytes: &[u8], level: usize) -> usize {
    model::get_u64(bytes, entry_field(level, entry::OFFSET)) as usize
}
