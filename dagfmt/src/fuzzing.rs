//! Fuzzing harnesses: one function per fuzz target of `fuzz/` (its own cargo
//! workspace, run with `cargo fuzz`), kept in the library so that the test
//! suite runs the very same checks over the committed regression inputs and
//! random inputs (`tests/it/fuzz_smoke.rs`).
//!
//! Each harness takes arbitrary bytes, must never panic except through one of
//! its own assertions, and asserts properties that hold for every input:
//!
//! - [`reader`]: whatever [`Dag::open`] accepts can be walked (every distinct
//!   reachable node and leaf), queried and iterated without a panic, and the
//!   answers agree with each other; a 2.0 file that [`AnyDag::open`] accepts
//!   is decoded record by record, its voxels listed in Morton order and
//!   (when they are few) downgraded to 1.0 without a panic;
//! - [`validator`]: a file the validator accepts opens, walks and iterates
//!   without a single error and holds the voxel count its header states; a
//!   file the reader refuses is never accepted; the levels of a valid 2.0
//!   file are canonical: those of upgrade(downgrade(x));
//! - [`packed_colors`]: a packed colour section that its checks accept
//!   decodes the same at random and in sequence, every section decodes without
//!   a panic, and colours encoded from the input decode within the bound;
//! - [`transport`]: unpacking arbitrary bytes never panics nor returns more
//!   than the limit, and unpack(pack(x)) == x;
//! - [`batch`]: parse(write(parse(x))) == parse(x) for rays and hits, text
//!   and binary, and a binary batch that parses is written back byte for byte;
//!   the streamed ray reader agrees with the whole-batch parser.
//!
//! Not part of the stable API.

use std::collections::HashSet;

use crate::batch::{self, Hit, Ray};
use crate::layout::{HEADER_SIZE, MAGIC};
use crate::packed_colors;
use crate::reader::{Dag, NodeRef};
use crate::transport;
use crate::v2file::{self, AnyDag, Dag2};
use crate::validate::{self, ValidateOptions};
use crate::{AttributeKind, ErrorCode, stats};
use std::ops::ControlFlow;

/// Voxels the harnesses iterate at most per input, so that a tiny file
/// holding 2^63 voxels (a full volume) costs bounded time.
pub const VOXEL_LIMIT: usize = 4096;

/// Files of at most this depth are queried at every voxel of the volume
/// (2^(3 D) queries).
pub const EXHAUSTIVE_DEPTH: u8 = 4;

/// The output limit the [`transport`] harness unpacks with.
pub const TRANSPORT_LIMIT: u64 = 1 << 20;

/// What walking a DAG found.
#[derive(Debug, Default)]
struct Walk {
    /// Distinct nodes and leaves visited (including unreadable ones).
    visited: usize,
    /// Whether a node, leaf or pointer could not be read.
    failed: bool,
}

/// Visits every distinct node and leaf reachable from the root, once each,
/// checking what each reports about itself.
fn walk(dag: &Dag<'_>) -> Walk {
    let mut walk = Walk::default();
    let Some(root) = dag.root() else {
        return walk;
    };
    let leaf_level = dag.leaf_level();
    let mut seen: HashSet<NodeRef> = HashSet::new();
    let mut stack = vec![root];
    while let Some(node) = stack.pop() {
        if !seen.insert(node) {
            continue;
        }
        walk.visited += 1;
        if node.level == leaf_level {
            match dag.leaf(node.pointer) {
                Ok(leaf) => {
                    assert_eq!(leaf.count(), leaf.0.count_ones());
                    let sub = leaf.sub_brick_mask();
                    for child in 0..8 {
                        assert_eq!(sub >> child & 1 != 0, leaf.sub_brick(child) != 0);
                    }
                }
                Err(_) => walk.failed = true,
            }
            continue;
        }
        let n = match dag.node(node.level, node.pointer) {
            Ok(n) => n,
            Err(_) => {
                walk.failed = true;
                continue;
            }
        };
        assert_eq!(n.level, node.level);
        assert_eq!(n.word, node.pointer);
        assert!(n.record_size() >= 4 && n.record_size() % 4 == 0);
        let mut rank = 0;
        for child in 0..8 {
            match n.child_pointer(child) {
                Some(pointer) => {
                    assert_eq!(pointer, n.pointer_at(rank));
                    rank += 1;
                    stack.push(NodeRef {
                        level: node.level + 1,
                        pointer,
                    });
                }
                None => assert_eq!(n.child_mask() >> child & 1, 0),
            }
        }
        assert_eq!(rank, n.child_count());
    }
    walk
}

/// What iterating over the voxels found.
#[derive(Debug)]
struct Listing {
    /// The voxels listed (at most [`VOXEL_LIMIT`]).
    voxels: Vec<[u32; 3]>,
    /// Whether the iteration ended by itself without an error.
    complete: bool,
}

/// Iterates over at most [`VOXEL_LIMIT`] voxels, checking each against the
/// point queries.
fn list_voxels(dag: &Dag<'_>) -> Listing {
    let resolution = dag.resolution();
    let mut voxels = Vec::new();
    let mut previous: Option<u64> = None;
    let mut it = dag.voxels();
    let mut complete = false;
    let counts_exact = dag.header().attribute_kind == AttributeKind::None;
    loop {
        if voxels.len() == VOXEL_LIMIT {
            break;
        }
        let code = match it.next_morton() {
            None => {
                complete = true;
                break;
            }
            Some(Err(_)) => {
                // The iterator reports one error and then ends.
                assert!(
                    it.next_morton().is_none(),
                    "iteration goes on after an error"
                );
                break;
            }
            Some(Ok(code)) => code,
        };
        assert!(
            previous.is_none_or(|p| p < code),
            "voxels are not listed in increasing Morton order"
        );
        previous = Some(code);
        let [x, y, z] = crate::morton::decode(code);
        assert!(
            [x, y, z].iter().all(|&c| u64::from(c) < resolution),
            "voxel {x} {y} {z} is outside the {resolution}^3 volume"
        );
        assert_eq!(
            dag.is_set(x, y, z).ok(),
            Some(true),
            "listed voxel {x} {y} {z} is not set"
        );
        // Dense indices cost a walk with a fresh memo each: check the first
        // ones and a sample of the rest.
        let n = voxels.len();
        if n >= 256 && n % 61 != 0 {
            voxels.push([x, y, z]);
            continue;
        }
        let index = dag.voxel_index(x, y, z);
        if counts_exact {
            // Every voxel before this one has been listed without an error, so
            // the subtree counts of its predecessors are exact.
            assert_eq!(
                index.ok(),
                Some(Some(voxels.len() as u64)),
                "dense index of voxel {x} {y} {z}"
            );
        } else if let Ok(index) = index {
            assert!(index.is_some(), "a listed voxel has no dense index");
        }
        voxels.push([x, y, z]);
    }
    Listing { voxels, complete }
}

/// The reader harness: opens `bytes` and, when that succeeds, walks every
/// distinct reachable node, lists voxels, asks point queries and computes
/// the statistics `dagtool info` prints, checking that they agree.
pub fn reader(bytes: &[u8]) {
    let dag = match AnyDag::open(bytes) {
        Ok(AnyDag::V1(dag)) => dag,
        Ok(AnyDag::V2(dag)) => return reader_v2(&dag, bytes),
        Err(_) => return,
    };
    let depth = dag.header().depth;
    assert!((crate::layout::MIN_DEPTH..=crate::layout::MAX_DEPTH).contains(&depth));
    assert_eq!(dag.levels().len(), usize::from(depth) - 1);
    assert_eq!(dag.header().file_size, bytes.len() as u64);
    walk(&dag);
    let listing = list_voxels(&dag);
    let resolution = dag.resolution();
    let last = (resolution - 1) as u32;
    let outside = resolution.min(u64::from(u32::MAX)) as u32;
    for [x, y, z] in [
        [outside, 0, 0],
        [0, outside, 0],
        [0, 0, outside],
        [u32::MAX; 3],
    ] {
        assert_eq!(dag.is_set(x, y, z).ok(), Some(false));
        assert_eq!(dag.voxel_index(x, y, z).ok(), Some(None));
    }
    for [x, y, z] in [[0, 0, 0], [last, last, last], [last, 0, last]] {
        let _ = dag.is_set(x, y, z);
        let _ = dag.voxel_index(x, y, z);
    }
    if listing.complete && depth <= EXHAUSTIVE_DEPTH {
        let listed: HashSet<[u32; 3]> = listing.voxels.iter().copied().collect();
        let r = resolution as u32;
        for x in 0..r {
            for y in 0..r {
                for z in 0..r {
                    assert_eq!(
                        dag.is_set(x, y, z).ok(),
                        Some(listed.contains(&[x, y, z])),
                        "is_set({x}, {y}, {z}) disagrees with the listing"
                    );
                }
            }
        }
    }
    if let Some(root) = dag.root() {
        let count = dag.subtree_voxel_count(root);
        if listing.complete && dag.header().attribute_kind == AttributeKind::None {
            assert_eq!(count.ok(), Some(listing.voxels.len() as u64));
        }
    } else {
        assert!(listing.complete && listing.voxels.is_empty());
    }
    let _ = stats::analyze(&dag);
}

/// The voxels of a 2.0 file, at most [`VOXEL_LIMIT`] of them: (Morton codes,
/// whether the listing is complete).
fn list_voxels_v2(dag: &Dag2<'_>) -> (Vec<u64>, bool) {
    let mut codes = Vec::new();
    let mut full = false;
    let walked = dag.for_each_leaf(|prefix, mut mask| {
        while mask != 0 {
            if codes.len() == VOXEL_LIMIT {
                full = true;
                return ControlFlow::Break(());
            }
            codes.push(prefix << 6 | u64::from(mask.trailing_zeros()));
            mask &= mask - 1;
        }
        ControlFlow::Continue(())
    });
    (codes, walked.is_ok() && !full)
}

/// The reader harness on a 2.0 file.
fn reader_v2(dag: &Dag2<'_>, bytes: &[u8]) {
    let depth = dag.header().depth;
    assert_eq!(dag.levels().len(), usize::from(depth) - 1);
    assert_eq!(dag.header().file_size, bytes.len() as u64);
    // Every record of every level, in sequence, until one does not decode.
    for level in dag.levels().iter().filter(|l| !l.is_leaf) {
        let mut at = 0u64;
        while let Ok(node) = crate::v2::decode_node(level.bytes, at, level.widths) {
            assert!(at + u64::from(node.size) <= level.bytes.len() as u64);
            at += u64::from(node.size);
        }
    }
    let (codes, complete) = list_voxels_v2(dag);
    let limit = 1u128 << (3 * u32::from(depth));
    assert!(
        codes.windows(2).all(|w| w[0] < w[1]),
        "voxels out of Morton order"
    );
    assert!(codes.iter().all(|&c| u128::from(c) < limit));
    let attributes = dag.header().attribute_kind == AttributeKind::VoxelCount;
    for (rank, &code) in codes.iter().enumerate().step_by(17) {
        let [x, y, z] = crate::morton::decode(code);
        let index = dag.voxel_index(x, y, z);
        if complete && !attributes {
            assert_eq!(index.ok(), Some(Some(rank as u64)));
        }
    }
    let outside = (1u64 << depth).min(u64::from(u32::MAX)) as u32;
    assert_eq!(dag.voxel_index(outside, 0, 0).ok(), Some(None));
    if complete
        && codes.len() <= 512
        && let Ok(v1) = v2file::downgrade(dag)
    {
        let v1 = Dag::open(&v1).expect("a downgraded file opens");
        let listed: Vec<u64> = v1
            .voxels()
            .map(|v| {
                let [x, y, z] = v.expect("a downgraded file reads");
                crate::morton::encode(x, y, z)
            })
            .collect();
        assert_eq!(listed, codes, "the downgrade holds other voxels");
    }
}

/// The validator harness: validates `bytes`, checks the report's form, and
/// checks that what the validator accepts, the reader reads without a single
/// error (validator accepts ⇒ reader never fails), and that what the reader
/// refuses, the validator does not accept.
pub fn validator(bytes: &[u8]) {
    let options = ValidateOptions {
        max_errors: 1000,
        threads: false,
        ..ValidateOptions::default()
    };
    let report = validate::validate_with(bytes, &options);
    assert!(report.errors.len() <= options.max_errors);
    assert!(
        report.errors.windows(2).all(|w| w[0].offset <= w[1].offset),
        "findings are not sorted by offset"
    );
    let opened = match AnyDag::open(bytes) {
        Ok(AnyDag::V2(dag)) => {
            if report.is_valid() {
                validator_v2(&dag);
            } else if report.errors.iter().all(|e| {
                matches!(
                    e.code,
                    ErrorCode::DuplicateClass | ErrorCode::NotCanonical | ErrorCode::BadLevelOrder
                )
            }) {
                // Only the canonical form is wrong (§23.10 step 4, checked on
                // the file's records): the re-encoding of its voxels differs.
                if let Ok(v1) = v2file::downgrade(&dag)
                    && let Ok(again) = v2file::upgrade(&Dag::open(&v1).expect("a downgrade opens"))
                {
                    let again = Dag2::open(&again).expect("an upgraded file opens");
                    assert!(
                        again.levels() != dag.levels(),
                        "the validator reports a canonical file as not canonical"
                    );
                }
            }
            return;
        }
        Ok(AnyDag::V1(dag)) => Ok(dag),
        Err(e) => Err(e),
    };
    if !report.is_valid() {
        return;
    }
    let dag = match opened {
        Ok(dag) => dag,
        Err(e) => panic!("the validator accepts a file the reader refuses: {e}"),
    };
    let walked = walk(&dag);
    assert!(!walked.failed, "a node of a valid file cannot be read");
    let listing = list_voxels(&dag);
    let header_count = dag.header().voxel_count;
    if listing.complete {
        assert_eq!(listing.voxels.len() as u64, header_count);
    } else {
        assert_eq!(
            listing.voxels.len(),
            VOXEL_LIMIT,
            "listing the voxels of a valid file fails"
        );
        assert!(header_count >= VOXEL_LIMIT as u64);
    }
    if let Some(root) = dag.root() {
        assert_eq!(dag.subtree_voxel_count(root).ok(), Some(header_count));
    } else {
        assert_eq!(header_count, 0);
    }
    let analyzed = stats::analyze(&dag);
    assert!(
        analyzed.is_ok(),
        "statistics of a valid file fail: {analyzed:?}"
    );
    if let Some(table) = dag.color_table() {
        assert_eq!(table.len(), header_count);
        for (i, c) in table.iter().take(VOXEL_LIMIT).enumerate() {
            assert_eq!(table.get(i as u64), Some(c));
        }
    }
}

/// The validator harness on a valid 2.0 file.
fn validator_v2(dag: &Dag2<'_>) {
    let (codes, complete) = list_voxels_v2(dag);
    let header_count = dag.header().voxel_count;
    if complete {
        assert_eq!(codes.len() as u64, header_count);
    } else {
        assert_eq!(
            codes.len(),
            VOXEL_LIMIT,
            "listing the voxels of a valid file fails"
        );
    }
    if complete {
        let v1 = v2file::downgrade(dag).expect("a valid 2.0 file downgrades");
        assert!(
            validate::validate(&v1).is_empty(),
            "its downgrade is invalid"
        );
        let again = v2file::upgrade(&Dag::open(&v1).expect("opens")).expect("upgrades");
        // The levels are canonical; the header may carry what a validator
        // accepts leniently (a higher minor version, optional features and
        // sections), which a rewrite does not keep.
        let again = Dag2::open(&again).expect("an upgraded file opens");
        assert!(
            again.levels() == dag.levels(),
            "the levels of a valid 2.0 file are not canonical"
        );
    }
    if let Some(table) = dag.color_table() {
        assert_eq!(table.len(), header_count);
    }
}

/// The packed colour harness. The first two bytes are a colour count, the
/// rest a PACKED_COLORS section: whatever [`packed_colors::check_section`]
/// says, decoding never panics and random access agrees with sequential
/// decoding; a section it accepts also opens. Then the same rest, read as
/// RGBA colours, is encoded with the error bound of the third byte and must
/// decode within it.
pub fn packed_colors(bytes: &[u8]) {
    let Some((count, section)) = bytes.split_first_chunk::<2>() else {
        return;
    };
    let count = u64::from(u16::from_le_bytes(*count));
    let errors = packed_colors::check_section(section, count);
    match packed_colors::PackedColors::new(section, count) {
        Ok(colors) => {
            let mut n = 0;
            for (i, c) in colors.iter().enumerate() {
                assert_eq!(colors.get(i as u64), Some(c));
                n += 1;
            }
            assert_eq!(n, count);
        }
        Err(e) => assert!(
            errors.contains(&e),
            "open refused {e:?}, checks said {errors:?}"
        ),
    }
    let bound = section
        .first()
        .map_or(0, |b| b % (packed_colors::MAX_ERROR_BOUND + 1));
    let (colors, _) = section.as_chunks::<4>();
    let (encoded, summary) = packed_colors::encode(colors, bound).expect("bound in range");
    assert_eq!(summary.length, encoded.len() as u64);
    assert_eq!(
        packed_colors::check_section(&encoded, colors.len() as u64),
        vec![]
    );
    let decoded = packed_colors::PackedColors::new(&encoded, colors.len() as u64).expect("opens");
    for (i, (src, dec)) in colors.iter().zip(decoded.iter()).enumerate() {
        assert_eq!(decoded.get(i as u64), Some(dec));
        for c in 0..4 {
            assert!(
                src[c].abs_diff(dec[c]) <= bound,
                "{src:?} decoded as {dec:?}, bound {bound}"
            );
        }
    }
}

/// The transport harness: unpacks `bytes` with limit [`TRANSPORT_LIMIT`],
/// then packs a `.vdag`-shaped copy of the bytes and checks the round trip.
pub fn transport(bytes: &[u8]) {
    if let Ok(out) = transport::unpack(bytes, TRANSPORT_LIMIT) {
        assert!(out.len() as u64 <= TRANSPORT_LIMIT);
        assert!(out.len() as u64 <= transport::MAX_EXPANSION * bytes.len() as u64);
        assert!(out.starts_with(&MAGIC));
        if let Ok(again) = transport::pack(&out, 1) {
            assert_eq!(
                transport::unpack(&again, TRANSPORT_LIMIT).ok().as_deref(),
                Some(&out[..])
            );
        }
    }
    // Any bytes become packable once they carry the magic and their length.
    let mut file = bytes.to_vec();
    if file.len() < HEADER_SIZE {
        file.resize(HEADER_SIZE, 0);
    }
    file[..MAGIC.len()].copy_from_slice(&MAGIC);
    let len = file.len() as u64;
    file[64..72].copy_from_slice(&len.to_le_bytes());
    let packed = transport::pack(&file, 1).expect("packing a .vdag-shaped file");
    assert!(transport::is_transport(&packed));
    let unpacked = transport::unpack(&packed, len).expect("unpacking what was packed");
    assert_eq!(unpacked, file);
    if len > HEADER_SIZE as u64 {
        // One byte under the size it declares: refused before decoding.
        assert!(matches!(
            transport::unpack(&packed, len - 1),
            Err(transport::TransportError::TooLarge { .. })
        ));
    }
    // Cut short, or with a byte after the frame: refused.
    assert!(transport::unpack(&packed[..packed.len() - 1], len).is_err());
    let mut trailing = packed;
    trailing.push(0);
    assert!(matches!(
        transport::unpack(&trailing, len),
        Err(transport::TransportError::TrailingData(1))
    ));
}

/// Whether two floats are the same value, any NaN matching any NaN (the text
/// form writes every NaN as `NaN`).
fn same_f32(a: f32, b: f32) -> bool {
    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
}

fn same_rays(a: &[Ray], b: &[Ray]) -> bool {
    a.len() == b.len()
        && a.iter().zip(b).all(|(a, b)| {
            let fa = [a.origin, a.dir, [a.tmin, a.tmax, 0.0]];
            let fb = [b.origin, b.dir, [b.tmin, b.tmax, 0.0]];
            a.level == b.level
                && fa
                    .iter()
                    .flatten()
                    .zip(fb.iter().flatten())
                    .all(|(&x, &y)| same_f32(x, y))
        })
}

fn same_hits(a: &[Hit], b: &[Hit]) -> bool {
    a.len() == b.len()
        && a.iter().zip(b).all(|(a, b)| {
            a.hit == b.hit
                && same_f32(a.t, b.t)
                && a.voxel == b.voxel
                && a.level == b.level
                && a.face == b.face
                && a.index == b.index
        })
}

/// Reads `bytes` with [`batch::RayReader`] in chunks of `chunk` rays, with
/// or without the length.
fn read_streamed(
    bytes: &[u8],
    chunk: usize,
    known_length: bool,
) -> Result<Vec<Ray>, batch::BatchError> {
    let length = known_length.then_some(bytes.len() as u64);
    let mut reader = batch::RayReader::new(bytes, length)?;
    let (mut all, mut part) = (Vec::new(), Vec::new());
    loop {
        reader.read_chunk(chunk, &mut part)?;
        if part.is_empty() {
            return Ok(all);
        }
        assert!(
            part.len() <= chunk,
            "a chunk of {} rays for {chunk}",
            part.len()
        );
        all.extend_from_slice(&part);
    }
}

/// The batch harness: parses `bytes` as rays and as hits; whatever parses is
/// written in both forms and parsed again, and must come back the same. The
/// streamed ray reader reads the same rays, or fails with the same error
/// (given the length; without it, it may only find a bad count at the end).
pub fn batch(bytes: &[u8]) {
    let whole = batch::parse_rays(bytes);
    for chunk in [1, 3, 1000] {
        let streamed = read_streamed(bytes, chunk, true);
        match (&whole, &streamed) {
            (Ok(a), Ok(b)) => assert!(same_rays(a, b), "streamed rays differ (chunk {chunk})"),
            (Err(a), Err(b)) => assert_eq!(a, b, "streamed error differs (chunk {chunk})"),
            _ => panic!("parse_rays {whole:?} but streamed {streamed:?} (chunk {chunk})"),
        }
        let unknown = read_streamed(bytes, chunk, false);
        assert_eq!(
            whole.is_ok(),
            unknown.is_ok(),
            "streamed without the length: {unknown:?}, parse_rays {whole:?}"
        );
        if let (Ok(a), Ok(b)) = (&whole, &unknown) {
            assert!(same_rays(a, b), "streamed rays differ without the length");
        }
    }
    if let Ok(rays) = whole {
        let mut text = Vec::new();
        batch::write_rays_text(&mut text, &rays).expect("writing parsed rays as text");
        let again = batch::parse_rays(&text).expect("parsing written text rays");
        assert!(same_rays(&rays, &again), "text rays do not round-trip");
        let mut binary = Vec::new();
        batch::write_rays_binary(&mut binary, &rays).expect("writing parsed rays as binary");
        let again = batch::parse_rays(&binary).expect("parsing written binary rays");
        assert!(same_rays(&rays, &again), "binary rays do not round-trip");
        if bytes.starts_with(&batch::RAYS_MAGIC) {
            assert_eq!(
                binary, bytes,
                "a binary ray batch is not written back as read"
            );
        }
    }
    if let Ok(hits) = batch::parse_hits(bytes) {
        let mut text = Vec::new();
        batch::write_hits_text(&mut text, &hits).expect("writing parsed hits as text");
        let again = batch::parse_hits(&text).expect("parsing written text hits");
        assert!(same_hits(&hits, &again), "text hits do not round-trip");
        let mut binary = Vec::new();
        batch::write_hits_binary(&mut binary, &hits).expect("writing parsed hits as binary");
        let again = batch::parse_hits(&binary).expect("parsing written binary hits");
        assert!(same_hits(&hits, &again), "binary hits do not round-trip");
        if bytes.starts_with(&batch::HITS_MAGIC) {
            assert_eq!(
                binary, bytes,
                "a binary hit batch is not written back as read"
            );
        }
    }
}
