//! One test per validation rule, and corruption properties.
//!
//! Files are assembled here by hand (`assemble`, from section contents) so that
//! each malformed file breaks exactly the rule it is about: after a field is
//! changed, `fix_checksums` recomputes every checksum, and the test asserts
//! that the validator reports that rule's code and nothing else (a few rules
//! cannot be broken alone; their cases list the codes that necessarily come
//! along). The section contents come from `oracle_spec`, a small independent
//! DAG writer (per-level deduplication, minimal widths), so these tests do not
//! depend on the crate's builder; the builder's own output is checked at the end.

use std::collections::{BTreeSet, HashMap};

use dagfmt::layout::{self, ATTRIBUTE_MAX, HEADER_SIZE, MAGIC, SECTION_ENTRY_SIZE, SectionKind};
use dagfmt::validate::{ValidateOptions, validate, validate_with};
use dagfmt::{AttributeKind, Dag, ErrorCode, morton};
use proptest::prelude::*;

// ---------------------------------------------------------------------------
// File assembly
// ---------------------------------------------------------------------------

/// One section to lay out.
#[derive(Clone, Debug)]
struct Sec {
    kind: u32,
    level: u8,
    width: u8,
    items: u64,
    data: Vec<u8>,
    /// Bytes added to (or, negative, taken from) the minimal offset.
    shift: i64,
}

impl Sec {
    fn new(kind: u32, level: u8, width: u8, items: u64, data: Vec<u8>) -> Self {
        Sec {
            kind,
            level,
            width,
            items,
            data,
            shift: 0,
        }
    }
}

/// A whole file to lay out.
#[derive(Clone, Debug)]
struct Spec {
    depth: u8,
    attribute_kind: u8,
    voxel_count: u64,
    sections: Vec<Sec>,
}

impl Spec {
    /// The voxel colour section appended, one colour per voxel.
    fn with_colors(mut self) -> Self {
        let data = (0..self.voxel_count)
            .flat_map(|i| [i as u8, (i >> 8) as u8, 7, 255])
            .collect();
        self.sections.push(Sec::new(
            SectionKind::VOXEL_COLORS,
            0,
            0,
            self.voxel_count,
            data,
        ));
        self
    }

    /// An optional section of unknown kind appended.
    fn with_optional(mut self, data: Vec<u8>) -> Self {
        let len = data.len() as u64;
        self.sections.push(Sec::new(0x8000_0042, 0, 0, len, data));
        self
    }
}

/// Lays the file out: header, table, sections at minimal aligned offsets
/// (plus each section's shift), zero padding, checksums, file size.
fn assemble(spec: &Spec) -> Vec<u8> {
    let n = spec.sections.len();
    let table_end = (HEADER_SIZE + n * SECTION_ENTRY_SIZE) as u64;
    let mut offsets = Vec::with_capacity(n);
    let mut end = table_end;
    for s in &spec.sections {
        let offset = (layout::align_section(end) as i64 + s.shift) as u64;
        offsets.push(offset);
        end = offset + s.data.len() as u64;
    }
    let file_len = offsets
        .iter()
        .zip(&spec.sections)
        .map(|(o, s)| o + s.data.len() as u64)
        .max()
        .unwrap_or(table_end);
    let file_len = file_len.max(table_end);
    let mut bytes = vec![0u8; file_len as usize];
    bytes[..8].copy_from_slice(&MAGIC);
    put16(&mut bytes, 8, 1);
    put16(&mut bytes, 10, 0);
    put32(&mut bytes, 12, HEADER_SIZE as u32);
    bytes[24] = spec.depth;
    bytes[25] = spec.attribute_kind;
    put16(&mut bytes, 26, n as u16);
    put64(&mut bytes, 56, 1.0f64.to_bits());
    put64(&mut bytes, 64, file_len);
    put64(&mut bytes, 72, spec.voxel_count);
    for (i, (s, &offset)) in spec.sections.iter().zip(&offsets).enumerate() {
        let at = entry(i);
        put32(&mut bytes, at, s.kind);
        bytes[at + 4] = s.level;
        bytes[at + 5] = s.width;
        put64(&mut bytes, at + 8, offset);
        put64(&mut bytes, at + 16, s.data.len() as u64);
        put64(&mut bytes, at + 24, s.items);
        bytes[offset as usize..offset as usize + s.data.len()].copy_from_slice(&s.data);
    }
    fix_checksums(&mut bytes);
    bytes
}

/// Byte offset of section table entry `i`.
fn entry(i: usize) -> usize {
    HEADER_SIZE + i * SECTION_ENTRY_SIZE
}

fn put16(b: &mut [u8], at: usize, v: u16) {
    b[at..at + 2].copy_from_slice(&v.to_le_bytes());
}
fn put32(b: &mut [u8], at: usize, v: u32) {
    b[at..at + 4].copy_from_slice(&v.to_le_bytes());
}
fn put64(b: &mut [u8], at: usize, v: u64) {
    b[at..at + 8].copy_from_slice(&v.to_le_bytes());
}
fn get64(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().unwrap())
}

/// Recomputes every section checksum (for sections inside the file) and then
/// the header checksum (when the table lies inside the file).
fn fix_checksums(bytes: &mut [u8]) {
    let n = usize::from(u16::from_le_bytes([bytes[26], bytes[27]]));
    let table_end = entry(n);
    if table_end > bytes.len() {
        return;
    }
    for i in 0..n {
        let at = entry(i);
        let (offset, length) = (get64(bytes, at + 8), get64(bytes, at + 16));
        if let Some(end) = offset
            .checked_add(length)
            .filter(|&e| e <= bytes.len() as u64)
        {
            let crc = crc32c::crc32c(&bytes[offset as usize..end as usize]);
            put32(bytes, at + 32, crc);
        }
    }
    let head: [u8; HEADER_SIZE] = bytes[..HEADER_SIZE].try_into().unwrap();
    let crc = layout::header_checksum(&head, &bytes[HEADER_SIZE..table_end]);
    put32(bytes, layout::HEADER_CRC_OFFSET, crc);
}

/// Offset and length of section `i`, from the table.
fn section_range(bytes: &[u8], i: usize) -> (usize, usize) {
    (
        get64(bytes, entry(i) + 8) as usize,
        get64(bytes, entry(i) + 16) as usize,
    )
}

// ---------------------------------------------------------------------------
// An independent writer (the oracle)
// ---------------------------------------------------------------------------

/// The sections of a DAG holding `voxels`, written the simplest way: a
/// recursive build over sorted Morton codes with per-level deduplication,
/// nodes in first-seen (post-)order, minimal pointer widths unless
/// `widths` overrides one level's.
fn oracle_spec(
    depth: u8,
    kind: AttributeKind,
    voxels: &[[u32; 3]],
    widths: Option<(u8, u8)>,
) -> Spec {
    let mut codes: Vec<u64> = voxels
        .iter()
        .map(|v| morton::encode(v[0], v[1], v[2]))
        .collect();
    codes.sort_unstable();
    codes.dedup();
    let leaf_level = depth - 2;
    let mut b = OracleBuild {
        depth,
        leaf_level,
        leaves: Vec::new(),
        leaf_ids: HashMap::new(),
        nodes: vec![Vec::new(); usize::from(leaf_level)],
        node_ids: vec![HashMap::new(); usize::from(leaf_level)],
    };
    if !codes.is_empty() {
        b.build(0, &codes);
    }
    let mut sections = Vec::new();
    let leaf_data: Vec<u8> = b.leaves.iter().flat_map(|m| m.to_le_bytes()).collect();
    sections.push(Sec::new(
        SectionKind::LEAF_LEVEL,
        leaf_level,
        0,
        b.leaves.len() as u64,
        leaf_data,
    ));
    // Where each record of the level below starts (word offsets / leaf indices).
    let mut child_positions: Vec<u32> = (0..b.leaves.len() as u32).collect();
    let mut child_units = b.leaves.len() as u64;
    for l in (0..leaf_level).rev() {
        let minimal = layout::minimal_pointer_width(child_units).unwrap();
        let w = match widths {
            Some((level, w)) if level == l => w,
            _ => minimal,
        };
        let mut data = Vec::new();
        let mut positions = Vec::new();
        for (mask, children, count) in &b.nodes[usize::from(l)] {
            positions.push((data.len() / 4) as u32);
            let attribute = match kind {
                AttributeKind::None => 0,
                AttributeKind::VoxelCount => (*count).min(u64::from(ATTRIBUTE_MAX)) as u32,
            };
            data.extend_from_slice(&(u32::from(*mask) | attribute << 8).to_le_bytes());
            let start = data.len();
            for &c in children {
                data.extend_from_slice(
                    &child_positions[c as usize].to_le_bytes()[..usize::from(w)],
                );
            }
            data.resize(start + (data.len() - start).next_multiple_of(4), 0);
        }
        child_units = data.len() as u64 / 4;
        child_positions = positions;
        sections.push(Sec::new(
            SectionKind::NODE_LEVEL,
            l,
            w,
            b.nodes[usize::from(l)].len() as u64,
            data,
        ));
    }
    sections.reverse();
    Spec {
        depth,
        attribute_kind: kind.to_raw(),
        voxel_count: codes.len() as u64,
        sections,
    }
}

type OracleNode = (u8, Vec<u32>, u64);

struct OracleBuild {
    depth: u8,
    leaf_level: u8,
    leaves: Vec<u64>,
    leaf_ids: HashMap<u64, u32>,
    nodes: Vec<Vec<OracleNode>>,
    node_ids: Vec<HashMap<(u8, Vec<u32>), u32>>,
}

impl OracleBuild {
    /// Builds the node of `level` holding `codes` (sorted, same prefix); returns its id and voxel count.
    fn build(&mut self, level: u8, codes: &[u64]) -> (u32, u64) {
        if level == self.leaf_level {
            let mask = codes.iter().fold(0u64, |m, c| m | 1 << (c & 63));
            let next = self.leaves.len() as u32;
            let id = *self.leaf_ids.entry(mask).or_insert(next);
            if id == next {
                self.leaves.push(mask);
            }
            return (id, u64::from(mask.count_ones()));
        }
        let shift = 3 * u32::from(self.depth - 1 - level);
        let mut mask = 0u8;
        let mut children = Vec::new();
        let mut count = 0;
        let mut rest = codes;
        while let Some(&first) = rest.first() {
            let child = (first >> shift) & 7;
            let n = rest
                .iter()
                .take_while(|&&c| (c >> shift) & 7 == child)
                .count();
            let (id, c) = self.build(level + 1, &rest[..n]);
            mask |= 1 << child;
            children.push(id);
            count += c;
            rest = &rest[n..];
        }
        let l = usize::from(level);
        let next = self.nodes[l].len() as u32;
        let id = *self.node_ids[l]
            .entry((mask, children.clone()))
            .or_insert(next);
        if id == next {
            self.nodes[l].push((mask, children, count));
        }
        (id, count)
    }
}

/// A volume entirely set: one node per level, every mask full. At depth 9 it
/// holds 2^27 voxels, so the two top levels store saturated counts.
fn full_spec(depth: u8) -> Spec {
    let leaf_level = depth - 2;
    let mut sections = Vec::new();
    for l in 0..leaf_level {
        let count = 1u64 << (3 * u32::from(depth - l));
        let attribute = count.min(u64::from(ATTRIBUTE_MAX)) as u32;
        let mut data = (0xFF | attribute << 8).to_le_bytes().to_vec();
        data.extend_from_slice(&[0; 8]);
        sections.push(Sec::new(SectionKind::NODE_LEVEL, l, 1, 1, data));
    }
    sections.push(Sec::new(
        SectionKind::LEAF_LEVEL,
        leaf_level,
        0,
        1,
        u64::MAX.to_le_bytes().to_vec(),
    ));
    Spec {
        depth,
        attribute_kind: 1,
        voxel_count: 1 << (3 * u32::from(depth)),
        sections,
    }
}

/// A fixed depth-4 voxel set with shared subtrees at every level: three
/// copies (root octants 0, 1, 6) of an 8³ pattern made of three copies of one
/// brick, a diagonal line and two lone voxels.
fn sample_voxels() -> Vec<[u32; 3]> {
    let mut v = Vec::new();
    for octant in [[0, 0, 0], [8, 0, 0], [0, 8, 8]] {
        for brick in [[0, 0, 0], [4, 0, 0], [0, 4, 4]] {
            for p in [[0, 0, 0], [1, 0, 0], [1, 1, 0], [2, 3, 1], [3, 3, 3]] {
                v.push([0, 1, 2].map(|i| octant[i] + brick[i] + p[i]));
            }
        }
    }
    for i in 0..16 {
        v.push([i, i, 15 - i]);
    }
    v.push([15, 0, 15]);
    v.push([9, 14, 2]);
    v
}

fn sample_spec(kind: AttributeKind) -> Spec {
    oracle_spec(4, kind, &sample_voxels(), None)
}

fn sample(kind: AttributeKind) -> Vec<u8> {
    assemble(&sample_spec(kind))
}

// ---------------------------------------------------------------------------
// Looking at records
// ---------------------------------------------------------------------------

/// One node record as found in a file.
#[derive(Clone, Debug)]
struct Record {
    /// File offset of the header word.
    at: usize,
    mask: u8,
    /// (file offset, value) of each pointer.
    pointers: Vec<(usize, u32)>,
    /// File offset and length of the padding after the pointers.
    padding: (usize, usize),
}

/// The records of node level `level` (section `level`), parsed independently.
fn records(bytes: &[u8], level: usize) -> Vec<Record> {
    let (offset, length) = section_range(bytes, level);
    let w = usize::from(bytes[entry(level) + 5]);
    let mut out = Vec::new();
    let mut pos = 0;
    while pos < length {
        let at = offset + pos;
        let mask = bytes[at];
        let k = mask.count_ones() as usize;
        let pointers = (0..k)
            .map(|i| {
                let p = at + 4 + i * w;
                let mut v = [0u8; 4];
                v[..w].copy_from_slice(&bytes[p..p + w]);
                (p, u32::from_le_bytes(v))
            })
            .collect();
        let size = layout::node_record_size(k as u32, w as u8) as usize;
        out.push(Record {
            at,
            mask,
            pointers,
            padding: (at + 4 + k * w, size - 4 - k * w),
        });
        pos += size;
    }
    out
}

/// How many pointers of `level` address each target.
fn reference_counts(bytes: &[u8], level: usize) -> HashMap<u32, usize> {
    let mut counts = HashMap::new();
    for r in records(bytes, level) {
        for (_, p) in r.pointers {
            *counts.entry(p).or_insert(0) += 1;
        }
    }
    counts
}

/// The codes reported for `bytes`, sorted and deduplicated.
fn codes(bytes: &[u8]) -> BTreeSet<ErrorCode> {
    validate(bytes).into_iter().map(|e| e.code).collect()
}

// ---------------------------------------------------------------------------
// One case per rule
// ---------------------------------------------------------------------------

/// A malformed file and, where the case pins it, the byte offset the finding must name.
struct Crafted {
    bytes: Vec<u8>,
    at: Option<u64>,
}

fn crafted(bytes: Vec<u8>) -> Crafted {
    Crafted { bytes, at: None }
}

fn crafted_at(bytes: Vec<u8>, at: usize) -> Crafted {
    Crafted {
        bytes,
        at: Some(at as u64),
    }
}

/// A valid sample with one edit applied, checksums fixed afterwards.
fn edited(kind: AttributeKind, edit: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
    let mut b = sample(kind);
    edit(&mut b);
    fix_checksums(&mut b);
    b
}

/// A rule's case: how to break it, the options to validate with, and the
/// other codes that necessarily come along (empty for most rules).
struct Case {
    code: ErrorCode,
    craft: fn() -> Vec<Crafted>,
    options: fn() -> ValidateOptions,
    also: &'static [ErrorCode],
}

fn check_case(case: &Case) {
    let variants = (case.craft)();
    assert!(!variants.is_empty());
    for (i, v) in variants.iter().enumerate() {
        let report = validate_with(&v.bytes, &(case.options)());
        let found: BTreeSet<ErrorCode> = report.errors.iter().map(|e| e.code).collect();
        assert!(
            found.contains(&case.code),
            "{} variant {i}: not reported; found {:?}",
            case.code,
            report.errors
        );
        let allowed: BTreeSet<ErrorCode> = case.also.iter().copied().chain([case.code]).collect();
        assert!(
            found.is_subset(&allowed),
            "{} variant {i}: unexpected codes in {:?}",
            case.code,
            report.errors
        );
        if let Some(at) = v.at {
            assert!(
                report
                    .errors
                    .iter()
                    .any(|e| e.code == case.code && e.offset == at),
                "{} variant {i}: expected at byte {at}, got {:?}",
                case.code,
                report.errors
            );
        }
        // Whatever the validator says, the reader must not panic.
        exercise_reader(&v.bytes);
    }
}

macro_rules! rule_cases {
    ($( $test:ident: $code:ident => $craft:expr $(, options $options:expr)? $(, also [$($also:ident),*])? ; )*) => {
        /// Every rule's case, for the coverage meta-test.
        const CASES: &[Case] = &[$(
            Case {
                code: ErrorCode::$code,
                craft: $craft,
                options: rule_cases!(@options $($options)?),
                also: &[$($(ErrorCode::$also),*)?],
            },
        )*];
        $(
            #[test]
            fn $test() {
                let case = CASES.iter().find(|c| c.code == ErrorCode::$code).unwrap();
                check_case(case);
            }
        )*
    };
    (@options) => { ValidateOptions::default };
    (@options $options:expr) => { $options };
}

rule_cases! {
    e001_truncated_header: TruncatedHeader => || {
        let b = sample(AttributeKind::VoxelCount);
        vec![crafted_at(b[..100].to_vec(), 100), crafted_at(Vec::new(), 0)]
    };
    e002_bad_magic: BadMagic => || {
        let mut b = sample(AttributeKind::VoxelCount);
        b[1] = b'W';
        let mut text = b"hello, this is not a vdag file".repeat(8);
        text.truncate(200);
        vec![crafted_at(b, 0), crafted(text)]
    };
    e003_unsupported_version: UnsupportedVersion => || {
        vec![crafted_at(edited(AttributeKind::VoxelCount, |b| put16(b, 8, 3)), 8)]
    };
    e004_unknown_required_feature: UnknownRequiredFeature => || {
        vec![crafted_at(edited(AttributeKind::VoxelCount, |b| put32(b, 16, 1 << 7)), 16)]
    };
    e005_bad_header_size: BadHeaderSize => || {
        vec![crafted_at(edited(AttributeKind::VoxelCount, |b| put32(b, 12, 136)), 12)]
    };
    e006_depth_out_of_range: DepthOutOfRange => || {
        vec![
            crafted_at(edited(AttributeKind::VoxelCount, |b| b[24] = 22), 24),
            crafted_at(edited(AttributeKind::VoxelCount, |b| b[24] = 1), 24),
            crafted_at(edited(AttributeKind::VoxelCount, |b| b[24] = 0), 24),
        ]
    };
    e007_unknown_attribute_kind: UnknownAttributeKind => || {
        vec![crafted_at(edited(AttributeKind::VoxelCount, |b| b[25] = 9), 25)]
    };
    e008_bad_root_cube: BadRootCube => || {
        vec![
            crafted_at(edited(AttributeKind::VoxelCount, |b| put64(b, 56, (-1.0f64).to_bits())), 32),
            crafted_at(edited(AttributeKind::VoxelCount, |b| put64(b, 56, 0.0f64.to_bits())), 32),
            crafted_at(edited(AttributeKind::VoxelCount, |b| put64(b, 40, f64::NAN.to_bits())), 32),
            crafted_at(edited(AttributeKind::VoxelCount, |b| put64(b, 32, f64::INFINITY.to_bits())), 32),
        ]
    };
    e009_nonzero_reserved: NonzeroReserved => || {
        vec![
            crafted_at(edited(AttributeKind::VoxelCount, |b| b[29] = 1), 28),
            crafted_at(edited(AttributeKind::VoxelCount, |b| b[100] = 0x80), 100),
            crafted_at(edited(AttributeKind::VoxelCount, |b| b[entry(1) + 7] = 1), entry(1) + 6),
            crafted_at(edited(AttributeKind::VoxelCount, |b| b[entry(2) + 39] = 4), entry(2) + 36),
        ]
    };
    e010_file_size_mismatch: FileSizeMismatch => || {
        vec![crafted_at(edited(AttributeKind::VoxelCount, |b| {
            let n = get64(b, 64);
            put64(b, 64, n + 8);
        }), 64)]
    };
    e011_header_checksum: HeaderChecksum => || {
        let mut a = sample(AttributeKind::VoxelCount);
        a[124] ^= 1;
        let mut b = sample(AttributeKind::VoxelCount);
        b[40] ^= 0x10; // root_min.y stays finite: only the checksum notices
        vec![crafted_at(a, 124), crafted_at(b, 124)]
    };
    e012_bad_section_table: BadSectionTable => || {
        vec![
            // Depth 4 needs 3 level sections.
            crafted_at(edited(AttributeKind::VoxelCount, |b| put16(b, 26, 2)), 26),
            crafted_at(edited(AttributeKind::VoxelCount, |b| put16(b, 26, 65)), 128),
            crafted_at(edited(AttributeKind::VoxelCount, |b| put16(b, 26, 2000)), 128),
            crafted_at(edited(AttributeKind::VoxelCount, |b| {
                b.resize(entry(70), 0);
                let n = b.len() as u64;
                put64(b, 64, n);
                put16(b, 26, 65);
            }), 26),
        ]
    };
    e013_file_too_large: FileTooLarge => || {
        vec![crafted_at(sample(AttributeKind::VoxelCount), 0)]
    }, options || ValidateOptions { max_file_size: 256, ..ValidateOptions::default() };
    e020_section_out_of_bounds: SectionOutOfBounds => || {
        let base = sample_spec(AttributeKind::VoxelCount).with_optional(vec![1; 16]);
        let mut long = assemble(&base);
        put64(&mut long, entry(3) + 16, 24);
        fix_checksums(&mut long);
        let mut far = assemble(&base);
        put64(&mut far, entry(3) + 8, u64::MAX - 7);
        fix_checksums(&mut far);
        vec![crafted_at(long, entry(3) + 8), crafted_at(far, entry(3) + 8)]
    }, also [SectionOverlap];
    e021_section_misaligned: SectionMisaligned => || {
        let mut spec = sample_spec(AttributeKind::VoxelCount).with_optional(vec![1; 12]);
        spec.sections[3].shift = 4;
        vec![crafted_at(assemble(&spec), entry(3) + 8)]
    };
    e022_section_overlap: SectionOverlap => || {
        let mut spec = sample_spec(AttributeKind::VoxelCount).with_optional(vec![1; 16]).with_optional(vec![2; 16]);
        spec.sections[4].shift = -8;
        vec![crafted_at(assemble(&spec), entry(4) + 8)]
    };
    e023_bad_padding: BadPadding => || {
        // Padding that is not minimal.
        let mut wide = sample_spec(AttributeKind::VoxelCount).with_optional(vec![1; 8]);
        wide.sections[3].shift = 8;
        let wide = assemble(&wide);
        // Minimal padding that is not zero: a 3-byte section leaves 5 bytes before the next.
        let mut dirty = assemble(&sample_spec(AttributeKind::VoxelCount).with_optional(vec![1; 3]).with_optional(vec![2; 8]));
        let (o, l) = section_range(&dirty, 3);
        dirty[o + l + 2] = 0x20;
        fix_checksums(&mut dirty);
        // Bytes after the last section.
        let mut tail = sample(AttributeKind::VoxelCount);
        let tail_at = tail.len();
        tail.extend_from_slice(&[0; 8]);
        let n = tail.len() as u64;
        put64(&mut tail, 64, n);
        fix_checksums(&mut tail);
        // More padding than needed between the table and the first section.
        let mut first = sample_spec(AttributeKind::VoxelCount);
        first.sections[0].shift = 8;
        // (Table entries are 40 bytes, so the table always ends on a multiple of 8:
        // minimal padding after it is empty.)
        vec![
            crafted_at(wide, entry(3) + 8),
            crafted_at(dirty, o + l + 2),
            crafted_at(tail, tail_at),
            crafted_at(assemble(&first), entry(0) + 8),
        ]
    };
    e024_bad_level_sections: BadLevelSections => || {
        vec![
            crafted_at(edited(AttributeKind::VoxelCount, |b| put32(b, entry(1), SectionKind::LEAF_LEVEL)), entry(1)),
            crafted_at(edited(AttributeKind::VoxelCount, |b| b[entry(1) + 4] = 2), entry(1)),
            crafted_at(edited(AttributeKind::VoxelCount, |b| put32(b, entry(2), 0x8000_0001)), entry(2)),
            {
                let mut spec = sample_spec(AttributeKind::VoxelCount);
                let extra = spec.sections[1].clone();
                spec.sections.push(extra);
                crafted_at(assemble(&spec), entry(3))
            },
        ]
    };
    e025_unknown_section_kind: UnknownSectionKind => || {
        let mut spec = sample_spec(AttributeKind::VoxelCount).with_optional(vec![5; 8]);
        spec.sections[3].kind = 0x42;
        vec![crafted_at(assemble(&spec), entry(3))]
    };
    e026_bad_pointer_width: BadPointerWidth => || {
        vec![
            crafted_at(edited(AttributeKind::VoxelCount, |b| b[entry(0) + 5] = 5), entry(0) + 5),
            crafted_at(edited(AttributeKind::VoxelCount, |b| b[entry(1) + 5] = 0), entry(1) + 5),
            crafted_at(edited(AttributeKind::VoxelCount, |b| b[entry(2) + 5] = 1), entry(2) + 5),
            crafted_at(assemble(&{
                let mut s = sample_spec(AttributeKind::VoxelCount).with_colors();
                s.sections[3].width = 4;
                s
            }), entry(3) + 5),
        ]
    };
    e027_pointer_width_not_minimal: PointerWidthNotMinimal => || {
        let v = sample_voxels();
        vec![
            crafted_at(assemble(&oracle_spec(4, AttributeKind::VoxelCount, &v, Some((0, 2)))), entry(0) + 5),
            crafted_at(assemble(&oracle_spec(4, AttributeKind::VoxelCount, &v, Some((1, 4)))), entry(1) + 5),
        ]
    };
    e028_section_checksum: SectionChecksum => || {
        let mut a = sample(AttributeKind::VoxelCount);
        a[entry(1) + 33] ^= 0x40;
        fix_header_only(&mut a);
        // A changed byte in an optional section nobody else looks at.
        let mut b = assemble(&sample_spec(AttributeKind::VoxelCount).with_optional(vec![6; 24]));
        let (o, _) = section_range(&b, 3);
        b[o + 5] = 7;
        vec![crafted_at(a, entry(1) + 32), crafted_at(b, entry(3) + 32)]
    };
    e030_level_too_large: LevelTooLarge => || {
        let mut leaf = sample(AttributeKind::VoxelCount);
        put64(&mut leaf, entry(2) + 24, (1 << 32) + 1);
        put64(&mut leaf, entry(2) + 16, ((1 << 32) + 1) * 8);
        fix_checksums(&mut leaf);
        let mut node = sample(AttributeKind::VoxelCount);
        put64(&mut node, entry(1) + 16, (4 << 32) + 8);
        fix_checksums(&mut node);
        vec![crafted_at(leaf, entry(2) + 24), crafted_at(node, entry(1) + 16)]
    }, also [SectionOutOfBounds, SectionOverlap];
    e040_bad_root_level: BadRootLevel => || {
        // Two root records (the root twice).
        let mut spec = sample_spec(AttributeKind::VoxelCount);
        let root = spec.sections[0].data.clone();
        spec.sections[0].data.extend_from_slice(&root);
        spec.sections[0].items = 2;
        vec![crafted_at(assemble(&spec), entry(0) + 24)]
    };
    e041_empty_child_mask: EmptyChildMask => || {
        // Depth 3: a root with no children over an empty leaf level.
        let spec = Spec {
            depth: 3,
            attribute_kind: 1,
            voxel_count: 0,
            sections: vec![
                Sec::new(SectionKind::NODE_LEVEL, 0, 1, 1, vec![0; 4]),
                Sec::new(SectionKind::LEAF_LEVEL, 1, 0, 0, vec![]),
            ],
        };
        let b = assemble(&spec);
        let at = section_range(&b, 0).0;
        vec![crafted_at(b, at)]
    };
    e042_truncated_node: TruncatedNode => || {
        // A record header at the end of level 1 whose pointers are missing.
        let mut spec = sample_spec(AttributeKind::VoxelCount);
        let at = spec.sections[1].data.len();
        spec.sections[1].data.extend_from_slice(&[0x0F, 0, 0, 0]);
        let b = assemble(&spec);
        let file_at = section_range(&b, 1).0 + at;
        vec![crafted_at(b, file_at)]
    };
    e043_item_count_mismatch: ItemCountMismatch => || {
        vec![
            crafted_at(edited(AttributeKind::VoxelCount, |b| {
                let n = get64(b, entry(1) + 24);
                put64(b, entry(1) + 24, n + 1);
            }), entry(1) + 24),
            crafted_at(edited(AttributeKind::VoxelCount, |b| {
                let n = get64(b, entry(1) + 24);
                put64(b, entry(1) + 24, n - 1);
            }), entry(1) + 24),
            crafted_at(edited(AttributeKind::VoxelCount, |b| {
                let n = get64(b, entry(2) + 24);
                put64(b, entry(2) + 24, n - 1);
            }), entry(2) + 24),
        ]
    };
    e044_nonzero_node_padding: NonzeroNodePadding => || {
        let mut b = sample(AttributeKind::VoxelCount);
        let r = records(&b, 0).into_iter().chain(records(&b, 1)).find(|r| r.padding.1 > 0).unwrap();
        let at = r.padding.0 + r.padding.1 - 1;
        b[at] = 0x01;
        fix_checksums(&mut b);
        vec![crafted_at(b, at)]
    };
    e045_pointer_out_of_range: PointerOutOfRange => || {
        // A pointer to a shared target, so that the target stays referenced.
        let mut out = Vec::new();
        for level in [0, 1] {
            let mut b = sample(AttributeKind::VoxelCount);
            let refs = reference_counts(&b, level);
            let (at, _) = records(&b, level)
                .into_iter()
                .flat_map(|r| r.pointers)
                .find(|(_, p)| refs[p] > 1)
                .unwrap();
            let mut edge = b.clone();
            b[at] = 0xFF;
            fix_checksums(&mut b);
            out.push(crafted_at(b, at));
            // Just past the end: the leaf count, or the words of level 1.
            let (_, length) = section_range(&edge, level + 1);
            edge[at] = (if level == 1 { length / 8 } else { length / 4 }) as u8;
            fix_checksums(&mut edge);
            out.push(crafted_at(edge, at));
        }
        out
    };
    e046_pointer_not_at_node: PointerNotAtNode => || {
        let mut b = sample(AttributeKind::VoxelCount);
        let refs = reference_counts(&b, 0);
        let (at, p) = records(&b, 0).into_iter().flat_map(|r| r.pointers).find(|(_, p)| refs[p] > 1).unwrap();
        b[at] = (p + 1) as u8; // every record is at least two words long
        fix_checksums(&mut b);
        vec![crafted_at(b, at)]
    };
    e047_unreferenced_node: UnreferencedNode => || {
        // A copy of a level-1 record, and a copy of a leaf, that nothing points to.
        let mut node = sample_spec(AttributeKind::VoxelCount);
        let first = records(&assemble(&node), 1)[0].clone();
        let size = layout::node_record_size(first.mask.count_ones(), node.sections[1].width) as usize;
        let copy = node.sections[1].data[..size].to_vec();
        let node_at = node.sections[1].data.len();
        node.sections[1].data.extend_from_slice(&copy);
        node.sections[1].items += 1;
        let node_bytes = assemble(&node);
        let node_at = section_range(&node_bytes, 1).0 + node_at;
        let mut leaf = sample_spec(AttributeKind::VoxelCount);
        let copy = leaf.sections[2].data[..8].to_vec();
        let leaf_at = leaf.sections[2].data.len();
        leaf.sections[2].data.extend_from_slice(&copy);
        leaf.sections[2].items += 1;
        let leaf_bytes = assemble(&leaf);
        let leaf_at = section_range(&leaf_bytes, 2).0 + leaf_at;
        vec![crafted_at(node_bytes, node_at), crafted_at(leaf_bytes, leaf_at)]
    };
    e048_empty_leaf_mask: EmptyLeafMask => || {
        // Kind 0 (no stored counts); the header count follows the change.
        let mut b = sample(AttributeKind::None);
        let (o, _) = section_range(&b, 2);
        let at = o + 8;
        b[at..at + 8].fill(0);
        let total = count_voxels(&b);
        put64(&mut b, 72, total);
        fix_checksums(&mut b);
        vec![crafted_at(b, at)]
    };
    e060_nonzero_attribute: NonzeroAttribute => || {
        let mut b = sample(AttributeKind::None);
        let r = records(&b, 1).pop().unwrap();
        b[r.at + 3] = 0x80;
        fix_checksums(&mut b);
        vec![crafted_at(b, r.at)]
    };
    e061_wrong_voxel_count: WrongVoxelCount => || {
        let mut inner = sample(AttributeKind::VoxelCount);
        let r = records(&inner, 1)[1].clone();
        inner[r.at + 1] ^= 1;
        fix_checksums(&mut inner);
        let mut root = sample(AttributeKind::VoxelCount);
        let r0 = records(&root, 0)[0].clone();
        root[r0.at + 1] = root[r0.at + 1].wrapping_add(1);
        fix_checksums(&mut root);
        // Saturation: 2^27 voxels must store 0xFFFFFF, not their low bits or 0xFFFFFE.
        let full = assemble(&full_spec(9));
        let root_at = section_range(&full, 0).0;
        let mut low = full.clone();
        put32(&mut low, root_at, 0xFF | (((1u32 << 27) & ATTRIBUTE_MAX) << 8));
        fix_checksums(&mut low);
        let mut under = full.clone();
        put32(&mut under, root_at, 0xFF | ((ATTRIBUTE_MAX - 1) << 8));
        fix_checksums(&mut under);
        // 2^21 voxels (level 2) are stored exactly, so 0xFFFFFF is wrong.
        let mut over = full;
        let level2 = section_range(&over, 2).0;
        put32(&mut over, level2, 0xFF | (ATTRIBUTE_MAX << 8));
        fix_checksums(&mut over);
        vec![
            crafted_at(inner, r.at),
            crafted_at(root, r0.at),
            crafted_at(low, root_at),
            crafted_at(under, root_at),
            crafted_at(over, level2),
        ]
    };
    e062_header_voxel_count: HeaderVoxelCount => || {
        let plus = edited(AttributeKind::VoxelCount, |b| {
            let n = get64(b, 72);
            put64(b, 72, n + 1);
        });
        let none = edited(AttributeKind::None, |b| {
            let n = get64(b, 72);
            put64(b, 72, n - 1);
        });
        let mut full = assemble(&full_spec(9));
        put64(&mut full, 72, (1 << 27) - 1);
        fix_checksums(&mut full);
        vec![crafted_at(plus, 72), crafted_at(none, 72), crafted_at(full, 72)]
    };
    e063_bad_color_section: BadColorSection => || {
        let colored = sample_spec(AttributeKind::VoxelCount).with_colors();
        let mut short = colored.clone();
        let n = short.sections[3].data.len();
        short.sections[3].data.truncate(n - 4);
        short.sections[3].items -= 1;
        let mut odd_length = colored.clone();
        odd_length.sections[3].data.push(0);
        let mut kind0 = sample_spec(AttributeKind::None).with_colors();
        kind0.sections[3].items = kind0.voxel_count;
        let twice = colored.clone().with_colors();
        let mut level = colored.clone();
        level.sections[3].level = 1;
        vec![
            crafted_at(assemble(&short), entry(3)),
            crafted_at(assemble(&odd_length), entry(3)),
            crafted_at(assemble(&kind0), entry(3)),
            crafted_at(assemble(&twice), entry(4)),
            crafted_at(assemble(&level), entry(3) + 4),
        ]
    };
    e080_bad_packed_color_section: BadPackedColorSection => || {
        let mut twice = sample_spec(AttributeKind::VoxelCount).with_colors();
        let packed = packed_sample(|_| {});
        let dag = Dag::open(&packed).unwrap();
        let data = dag.packed_colors().unwrap().bytes().to_vec();
        twice.sections.push(Sec::new(SectionKind::PACKED_COLORS, 0, 0, twice.voxel_count, data.clone()));
        let mut kind0 = sample_spec(AttributeKind::None);
        kind0.sections.push(Sec::new(SectionKind::PACKED_COLORS, 0, 0, kind0.voxel_count, data.clone()));
        let mut level = sample_spec(AttributeKind::VoxelCount);
        let mut s = Sec::new(SectionKind::PACKED_COLORS, 0, 0, level.voxel_count, data);
        s.level = 2;
        level.sections.push(s);
        vec![
            crafted_at(assemble(&twice), entry(4)),
            crafted_at(assemble(&kind0), entry(3)),
            crafted_at(assemble(&level), entry(3) + 4),
            crafted(packed_sample(|d| d.truncate(20))),
        ]
    };
    e081_bad_color_trailer: BadColorTrailer => || {
        vec![
            crafted(packed_sample(|d| { let n = d.len(); d[n - 15] = 9 })),
            crafted(packed_sample(|d| { let n = d.len(); d[n - 13] = 2 })),
            crafted(packed_sample(|d| { let n = d.len(); d[n - 16] = 128 })),
            crafted(packed_sample(|d| { let n = d.len(); d[n - 14] = 1 })),
            crafted(packed_sample(|d| { let n = d.len(); d[n - 9] = 1 })),
            crafted(packed_sample(|d| { let n = d.len(); d[n - 1] = 1 })),
        ]
    };
    e082_bad_color_directory: BadColorDirectory => || packed_breaking(ErrorCode::BadColorDirectory);
    e083_bad_color_block: BadColorBlock => || packed_breaking(ErrorCode::BadColorBlock);
    e084_color_block_length: ColorBlockLength => || packed_breaking(ErrorCode::ColorBlockLength);
    e085_color_block_padding: ColorBlockPadding => || packed_breaking(ErrorCode::ColorBlockPadding);
    e086_color_index_out_of_range: ColorIndexOutOfRange => || packed_breaking(ErrorCode::ColorIndexOutOfRange);
    e087_color_value_out_of_range: ColorValueOutOfRange => || packed_breaking(ErrorCode::ColorValueOutOfRange);
    e088_bad_split_sub_block: BadSplitSubBlock => || breaking(ErrorCode::BadSplitSubBlock, split_sample);
    e070_bad_widths: BadWidths => || v2_cases(ErrorCode::BadWidths);
    e071_truncated_record_2: TruncatedRecord2 => || v2_cases(ErrorCode::TruncatedRecord2);
    e072_nonzero_bit_padding: NonzeroBitPadding => || v2_cases(ErrorCode::NonzeroBitPadding);
    e073_reference_out_of_range_2: ReferenceOutOfRange2 => || v2_cases(ErrorCode::ReferenceOutOfRange2);
    e074_width_not_minimal: WidthNotMinimal => || v2_cases(ErrorCode::WidthNotMinimal);
    e075_duplicate_class: DuplicateClass => || v2_cases(ErrorCode::DuplicateClass);
    e076_not_canonical: NotCanonical => || v2_cases(ErrorCode::NotCanonical);
    e077_bad_level_order: BadLevelOrder => || v2_cases(ErrorCode::BadLevelOrder);
    e078_bad_sharing: BadSharing => || v2_cases(ErrorCode::BadSharing);
    e079_item_count_mismatch_2: ItemCountMismatch2 => || v2_cases(ErrorCode::ItemCountMismatch2);
}

/// The sample with a lossless format 1.2 PACKED_COLORS section (blocks of
/// 128, split sub-blocks: runs of 5 colours change once in most sub-blocks of
/// 8), whose bytes `edit` changes.
fn split_sample(edit: &mut dyn FnMut(&mut Vec<u8>)) -> Vec<u8> {
    let mut spec = sample_spec(AttributeKind::VoxelCount);
    let colors: Vec<[u8; 4]> = (0..spec.voxel_count)
        .map(|i| [30 * (i / 5 % 4) as u8, 100, 7, 255])
        .collect();
    let layout = dagfmt::packed_colors::BlockLayout {
        shift: 7,
        split: true,
    };
    let (mut data, _) = dagfmt::packed_colors::encode_with_layout(&colors, 0, layout).unwrap();
    edit(&mut data);
    spec.sections.push(Sec::new(
        SectionKind::PACKED_COLORS,
        0,
        0,
        spec.voxel_count,
        data,
    ));
    assemble(&spec)
}

/// The format 2.0 rules (spec §23.10): their malformed files are made by the
/// conformance suite's 2.0 file surgery (`conformance::model2`), which lays a
/// 2.0 file out again after an edit; they are read from its committed cases.
fn v2_cases(code: ErrorCode) -> Vec<Crafted> {
    let dir =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../conformance/cases/validate");
    let prefix = format!("{}-", code.code());
    let mut files: Vec<_> = std::fs::read_dir(&dir)
        .expect("conformance cases")
        .map(|e| e.expect("entry").path())
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with(&prefix))
        })
        .collect();
    files.sort();
    files
        .into_iter()
        .map(|p| crafted(std::fs::read(p).expect("read case")))
        .collect()
}

/// The sample (attribute kind 1) with a lossless PACKED_COLORS section as
/// section 3, whose bytes `edit` changes; checksums fixed afterwards.
fn packed_sample(edit: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
    let mut spec = sample_spec(AttributeKind::VoxelCount);
    let colors: Vec<[u8; 4]> = (0..spec.voxel_count)
        .map(|i| [200 + 10 * (i / 8 % 3) as u8, 100, (i % 2) as u8, 255])
        .collect();
    let (mut data, _) = dagfmt::packed_colors::encode(&colors, 0).unwrap();
    edit(&mut data);
    spec.sections.push(Sec::new(
        SectionKind::PACKED_COLORS,
        0,
        0,
        spec.voxel_count,
        data,
    ));
    assemble(&spec)
}

/// The first one-byte edit of the packed sample's section (each bit flipped,
/// then the byte set to 0xff) after which the validator reports `code` and
/// nothing else: a file breaking that rule alone.
fn packed_breaking(code: ErrorCode) -> Vec<Crafted> {
    breaking(code, |edit| packed_sample(edit))
}

/// The first one-byte edit of a sample's section (each bit flipped, then the
/// byte set to 0xff) after which the validator reports `code` and nothing
/// else.
fn breaking(
    code: ErrorCode,
    sample: impl Fn(&mut dyn FnMut(&mut Vec<u8>)) -> Vec<u8>,
) -> Vec<Crafted> {
    let len = sample(&mut |_| {}).len();
    for at in 0..len {
        for edit in (0..8).map(|b| 1u8 << b).chain([0xff]) {
            let mut hit = false;
            let bytes = sample(&mut |d| {
                if let Some(x) = d.get_mut(at) {
                    *x = if edit == 0xff { 0xff } else { *x ^ edit };
                    hit = true;
                }
            });
            if !hit {
                continue;
            }
            let found = codes(&bytes);
            if found == BTreeSet::from([code]) {
                return vec![crafted(bytes)];
            }
        }
    }
    panic!("no one-byte edit breaks {code} alone");
}

/// Recomputes the header checksum only (section checksums left as they are).
fn fix_header_only(bytes: &mut [u8]) {
    let n = usize::from(u16::from_le_bytes([bytes[26], bytes[27]]));
    let head: [u8; HEADER_SIZE] = bytes[..HEADER_SIZE].try_into().unwrap();
    let crc = layout::header_checksum(&head, &bytes[HEADER_SIZE..entry(n)]);
    put32(bytes, layout::HEADER_CRC_OFFSET, crc);
}

/// Voxels in the file by the reader's subtree count (the file must open).
fn count_voxels(bytes: &[u8]) -> u64 {
    // (The voxel iterator stops at an empty leaf; the subtree count sums it as 0.)
    let dag = Dag::open(bytes).unwrap();
    dag.root()
        .map_or(0, |root| dag.subtree_voxel_count(root).unwrap())
}

/// Runs the reader over `bytes` the way a user would; it must not panic.
fn exercise_reader(bytes: &[u8]) {
    let Ok(dag) = Dag::open(bytes) else { return };
    let mut seen = Vec::new();
    for v in dag.voxels().take(20_000) {
        match v {
            Ok(v) => seen.push(v),
            Err(_) => break,
        }
    }
    let r = dag.resolution() as u32;
    for v in seen.iter().take(200).copied().chain([
        [0, 0, 0],
        [r - 1, r - 1, r - 1],
        [r, 0, 0],
        [1, 2, 3],
    ]) {
        let _ = dag.is_set(v[0], v[1], v[2]);
        let _ = dag.voxel_index(v[0], v[1], v[2]);
    }
}

#[test]
fn every_code_has_a_case() {
    let covered: BTreeSet<ErrorCode> = CASES.iter().map(|c| c.code).collect();
    let missing: Vec<_> = ErrorCode::ALL
        .iter()
        .filter(|c| !covered.contains(c))
        .collect();
    assert!(
        missing.is_empty(),
        "codes without a malformed-file case: {missing:?}"
    );
    assert_eq!(CASES.len(), ErrorCode::ALL.len(), "one case per code");
}

// ---------------------------------------------------------------------------
// Valid files
// ---------------------------------------------------------------------------

#[test]
fn hand_assembled_samples_are_valid() {
    for kind in [AttributeKind::None, AttributeKind::VoxelCount] {
        let spec = sample_spec(kind);
        assert_eq!(validate(&assemble(&spec)), vec![]);
        if kind == AttributeKind::VoxelCount {
            assert_eq!(validate(&assemble(&spec.clone().with_colors())), vec![]);
        }
        assert_eq!(
            validate(&assemble(
                &spec
                    .clone()
                    .with_optional(vec![9; 13])
                    .with_optional(vec![])
            )),
            vec![]
        );
    }
    // Saturated counts, exact total beyond 24 bits.
    assert_eq!(validate(&assemble(&full_spec(9))), vec![]);
    assert_eq!(validate(&assemble(&full_spec(2))), vec![]);
    // Empty volumes at the smallest and another depth, with an empty colour section.
    for depth in [2, 3, 7] {
        let spec = oracle_spec(depth, AttributeKind::VoxelCount, &[], None);
        assert_eq!(validate(&assemble(&spec)), vec![]);
        assert_eq!(validate(&assemble(&spec.with_colors())), vec![]);
    }
}

#[test]
fn sample_has_what_the_cases_rely_on() {
    let b = sample(AttributeKind::VoxelCount);
    // Shared targets at both node levels, width 1, padding somewhere.
    for level in [0, 1] {
        assert!(reference_counts(&b, level).values().any(|&n| n > 1));
        assert_eq!(b[entry(level) + 5], 1);
    }
    assert!(records(&b, 1).iter().any(|r| r.padding.1 > 0));
    assert!(records(&b, 1).len() >= 2);
    let expected: BTreeSet<[u32; 3]> = sample_voxels().into_iter().collect();
    let dag = Dag::open(&b).unwrap();
    let got: BTreeSet<[u32; 3]> = dag.voxels().map(|v| v.unwrap()).collect();
    assert_eq!(got, expected);
}

#[test]
fn every_finding_is_reported_not_only_the_first() {
    let mut b = sample(AttributeKind::VoxelCount);
    b[29] = 1; // E009
    let recs = records(&b, 1);
    let pad = recs.iter().find(|r| r.padding.1 > 0).unwrap();
    b[pad.padding.0] = 3; // E044
    put64(&mut b, 72, 5); // E062
    fix_checksums(&mut b);
    b[entry(0) + 33] ^= 1; // E028 (stale section checksum); the header checksum is stale too (E011)
    let found = codes(&b);
    let expected: BTreeSet<ErrorCode> = [
        ErrorCode::NonzeroReserved,
        ErrorCode::NonzeroNodePadding,
        ErrorCode::HeaderVoxelCount,
        ErrorCode::SectionChecksum,
        ErrorCode::HeaderChecksum,
    ]
    .into_iter()
    .collect();
    assert_eq!(found, expected);
    // Level and node are named for node findings.
    let e = validate(&b)
        .into_iter()
        .find(|e| e.code == ErrorCode::NonzeroNodePadding)
        .unwrap();
    assert_eq!(e.level, Some(1));
    let index = recs.iter().position(|r| r.at == pad.at).unwrap() as u64;
    assert_eq!(e.node, Some(index));
    assert_eq!(e.offset, pad.padding.0 as u64);
}

#[test]
fn error_limit_truncates() {
    // Every leaf zeroed: one finding per leaf, more than the limit allows.
    let mut b = sample(AttributeKind::None);
    let (o, l) = section_range(&b, 2);
    b[o..o + l].fill(0);
    fix_checksums(&mut b);
    let all = validate(&b);
    assert!(all.len() > 3);
    let report = validate_with(
        &b,
        &ValidateOptions {
            max_errors: 3,
            ..ValidateOptions::default()
        },
    );
    assert_eq!(report.errors.len(), 3);
    assert!(report.truncated);
    assert!(!report.is_valid());
    let full = validate_with(&b, &ValidateOptions::default());
    assert!(!full.truncated);
}

// ---------------------------------------------------------------------------
// Properties
// ---------------------------------------------------------------------------

/// Random voxel sets: clustered (so that subtrees repeat) or scattered.
fn voxel_sets() -> impl Strategy<Value = (u8, Vec<[u32; 3]>)> {
    (2u8..=8).prop_flat_map(|depth| {
        let r = 1u32 << depth;
        let scattered = prop::collection::vec([0..r, 0..r, 0..r], 0..200);
        let cell = 4u32.min(r);
        let clustered = (
            prop::collection::vec([0..cell, 0..cell, 0..cell], 1..12),
            prop::collection::vec([0..r / cell, 0..r / cell, 0..r / cell], 1..20),
        )
            .prop_map(move |(pattern, places)| {
                places
                    .iter()
                    .flat_map(|p| {
                        pattern.iter().map(move |v| {
                            [p[0] * cell + v[0], p[1] * cell + v[1], p[2] * cell + v[2]]
                        })
                    })
                    .collect::<Vec<_>>()
            });
        (Just(depth), prop_oneof![scattered, clustered])
    })
}

fn kinds() -> impl Strategy<Value = (AttributeKind, bool)> {
    prop_oneof![
        Just((AttributeKind::None, false)),
        Just((AttributeKind::VoxelCount, false)),
        Just((AttributeKind::VoxelCount, true))
    ]
}

fn oracle_file(depth: u8, voxels: &[[u32; 3]], kind: AttributeKind, colors: bool) -> Vec<u8> {
    let spec = oracle_spec(depth, kind, voxels, None);
    assemble(&if colors { spec.with_colors() } else { spec })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

    /// Independently written files of any shape are valid, and read back.
    #[test]
    fn oracle_files_are_valid((depth, voxels) in voxel_sets(), (kind, colors) in kinds()) {
        let b = oracle_file(depth, &voxels, kind, colors);
        prop_assert_eq!(validate(&b), vec![]);
        let dag = Dag::open(&b).unwrap();
        let got: BTreeSet<[u32; 3]> = dag.voxels().map(|v| v.unwrap()).collect();
        let expected: BTreeSet<[u32; 3]> = voxels.iter().copied().collect();
        prop_assert_eq!(got, expected);
    }

    /// Any single changed byte is reported (every byte is under a checksum or
    /// is required-zero padding), and the reader survives it.
    #[test]
    fn any_changed_byte_is_reported((depth, voxels) in voxel_sets(), (kind, colors) in kinds(), pos in any::<prop::sample::Index>(), value in any::<u8>()) {
        let mut b = oracle_file(depth, &voxels, kind, colors);
        let at = pos.index(b.len());
        prop_assume!(b[at] != value);
        b[at] = value;
        prop_assert!(!validate(&b).is_empty(), "byte {} set to {:#x} not reported", at, value);
        exercise_reader(&b);
    }

    /// A changed byte whose checksums are then fixed: whatever it did, a file
    /// the validator accepts reads back consistently.
    #[test]
    fn accepted_after_change_means_consistent((depth, voxels) in voxel_sets(), (kind, colors) in kinds(), pos in any::<prop::sample::Index>(), value in any::<u8>()) {
        let mut b = oracle_file(depth, &voxels, kind, colors);
        let at = pos.index(b.len());
        b[at] = value;
        fix_checksums(&mut b);
        if validate(&b).is_empty() {
            assert_consistent(&b);
        } else {
            exercise_reader(&b);
        }
    }
}

/// What a valid file guarantees a reader: it opens, every voxel is reached
/// without error, the count and dense indices agree with the header.
fn assert_consistent(b: &[u8]) {
    let dag = Dag::open(b).expect("a valid file opens");
    let voxels: Vec<[u32; 3]> = dag
        .voxels()
        .map(|v| v.expect("a valid file iterates"))
        .collect();
    assert_eq!(voxels.len() as u64, dag.header().voxel_count);
    let mut previous = None;
    for (i, v) in voxels.iter().enumerate() {
        let code = morton::encode(v[0], v[1], v[2]);
        assert!(previous < Some(code), "Morton order");
        previous = Some(code);
        assert!(dag.is_set(v[0], v[1], v[2]).unwrap());
        if dag.header().attribute_kind == AttributeKind::VoxelCount {
            assert_eq!(dag.voxel_index(v[0], v[1], v[2]).unwrap(), Some(i as u64));
        }
    }
    if let Some(colors) = dag.colors() {
        assert_eq!(colors.len() as u64, 4 * dag.header().voxel_count);
    }
}

#[test]
fn every_single_bit_flip_is_reported() {
    let files = [
        sample(AttributeKind::VoxelCount),
        assemble(
            &sample_spec(AttributeKind::VoxelCount)
                .with_colors()
                .with_optional(vec![3; 5]),
        ),
        sample(AttributeKind::None),
        assemble(&full_spec(9)),
        assemble(&oracle_spec(
            2,
            AttributeKind::VoxelCount,
            &[[1, 2, 3], [0, 0, 0]],
            None,
        )),
        assemble(&oracle_spec(5, AttributeKind::VoxelCount, &[], None)),
    ];
    for file in &files {
        assert_eq!(validate(file), vec![]);
        for at in 0..file.len() {
            for bit in 0..8 {
                let mut b = file.clone();
                b[at] ^= 1 << bit;
                assert!(
                    !validate(&b).is_empty(),
                    "flip of bit {bit} of byte {at} (of {}) not reported",
                    file.len()
                );
            }
        }
    }
}

#[test]
fn truncations_are_reported() {
    let file = assemble(&sample_spec(AttributeKind::VoxelCount).with_colors());
    for len in 0..file.len() {
        let found = codes(&file[..len]);
        assert!(!found.is_empty(), "truncation to {len} bytes not reported");
        exercise_reader(&file[..len]);
    }
}

// ---------------------------------------------------------------------------
// The crate's builder
// ---------------------------------------------------------------------------

fn built_file(depth: u8, voxels: &[[u32; 3]], kind: AttributeKind, colors: bool) -> Vec<u8> {
    let mut built = dagfmt::DagBuilder::from_voxels(depth, kind, voxels.iter().copied()).unwrap();
    if colors {
        let n = built.voxel_count();
        built
            .set_colors((0..n).map(|i| [i as u8, (i >> 8) as u8, 3, 255]).collect())
            .unwrap();
    }
    built.to_bytes()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// The validator accepts everything the builder writes.
    #[test]
    fn built_files_are_valid((depth, voxels) in voxel_sets(), (kind, colors) in kinds()) {
        let b = built_file(depth, &voxels, kind, colors);
        prop_assert_eq!(validate(&b), vec![]);
        assert_consistent(&b);
    }

    /// Any single changed byte of a built file is reported; the reader survives it.
    #[test]
    fn any_changed_byte_of_a_built_file_is_reported((depth, voxels) in voxel_sets(), (kind, colors) in kinds(), pos in any::<prop::sample::Index>(), value in any::<u8>()) {
        let mut b = built_file(depth, &voxels, kind, colors);
        let at = pos.index(b.len());
        prop_assume!(b[at] != value);
        b[at] = value;
        prop_assert!(!validate(&b).is_empty(), "byte {} set to {:#x} not reported", at, value);
        exercise_reader(&b);
    }
}

#[test]
fn every_single_bit_flip_of_built_files_is_reported() {
    let sample = sample_voxels();
    let files = [
        built_file(4, &sample, AttributeKind::VoxelCount, true),
        built_file(4, &sample, AttributeKind::None, false),
        built_file(2, &[[3, 3, 3]], AttributeKind::VoxelCount, false),
        built_file(6, &[], AttributeKind::VoxelCount, true),
    ];
    for file in &files {
        assert_eq!(validate(file), vec![]);
        for at in 0..file.len() {
            for bit in 0..8 {
                let mut b = file.clone();
                b[at] ^= 1 << bit;
                assert!(
                    !validate(&b).is_empty(),
                    "flip of bit {bit} of byte {at} (of {}) not reported",
                    file.len()
                );
                exercise_reader(&b);
            }
        }
    }
}

#[test]
fn checksums_on_a_second_thread_agree() {
    // A 40 MiB optional section makes the file large enough for the checksum thread.
    let mut b =
        assemble(&sample_spec(AttributeKind::VoxelCount).with_optional(vec![0x5A; 40 << 20]));
    let threaded = ValidateOptions::default();
    let single = ValidateOptions {
        threads: false,
        ..ValidateOptions::default()
    };
    assert!(validate_with(&b, &threaded).is_valid());
    assert!(validate_with(&b, &single).is_valid());
    let (o, _) = section_range(&b, 3);
    b[o + (20 << 20)] ^= 4;
    for options in [threaded, single] {
        let report = validate_with(&b, &options);
        let found: Vec<_> = report.errors.iter().map(|e| (e.code, e.offset)).collect();
        assert_eq!(
            found,
            vec![(ErrorCode::SectionChecksum, (entry(3) + 32) as u64)]
        );
    }
}

/// A file written by the format 1.1 writer (the conformance suite's lossy
/// packed colour case of revision 1.2, kept byte for byte) still opens,
/// validates and decodes within its bound: 1.2 readers read 1.1 sections.
#[test]
fn format_1_1_packed_colours_still_read() {
    let bytes = std::fs::read(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/packed-colors-1.1-lossy.vdag"
    ))
    .unwrap();
    assert_eq!(validate(&bytes), vec![]);
    let dag = Dag::open(&bytes).unwrap();
    let packed = dag.packed_colors().unwrap();
    assert_eq!(
        packed.trailer().layout,
        dagfmt::packed_colors::BlockLayout::V1_1
    );
    assert_eq!(packed.trailer().error_bound, 3);
    assert_eq!(packed.len(), 77);
    for (i, c) in packed.iter().enumerate() {
        let i = i as u64;
        let source = [(i * 37) as u8, (i * 3) as u8, 7, 200 + (i % 5) as u8];
        for ch in 0..4 {
            assert!(
                source[ch].abs_diff(c[ch]) <= 3,
                "colour {i}: {c:?} from {source:?}"
            );
        }
        assert_eq!(packed.get(i), Some(c));
    }
}

/// A packed colour section of 2^22 colours or more is checked on a thread of
/// its own while the levels are walked: the findings are those of the
/// single-threaded validation, on a valid file and on one with a broken block.
#[test]
fn large_packed_sections_are_checked_alike_on_their_own_thread() {
    let mut dag =
        dagfmt::builder::DagBuilder::from_fn(8, AttributeKind::VoxelCount, |_, _, z| z < 65)
            .unwrap();
    let n = dag.voxel_count();
    assert!(n >= 1 << 22, "{n} colours");
    let colors: Vec<[u8; 4]> = (0..n)
        .map(|i| [(i / 9 % 7 * 30) as u8, (i >> 12) as u8, 3, 255])
        .collect();
    dag.set_packed_colors(&colors, 0).unwrap();
    let mut bytes = dag.to_bytes();
    let serial = ValidateOptions {
        threads: false,
        ..ValidateOptions::default()
    };
    assert!(validate_with(&bytes, &ValidateOptions::default()).is_valid());
    // The last section (after the 6 node levels and the leaf level) holds the colours.
    let (at, len) = section_range(&bytes, 7);
    assert_eq!(
        Dag::open(&bytes)
            .unwrap()
            .packed_colors()
            .unwrap()
            .bytes()
            .len(),
        len
    );
    bytes[at + len / 2] ^= 0x5a;
    fix_checksums(&mut bytes);
    let threaded = validate_with(&bytes, &ValidateOptions::default());
    assert!(!threaded.is_valid());
    assert_eq!(threaded, validate_with(&bytes, &serial));
}
