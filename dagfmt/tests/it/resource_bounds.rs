//! Resource bounds (spec/VDAG.md § 16.2): hostile headers and section tables
//! (huge counts, depth 255, sections past the end) get their exact error code
//! without the reader or the validator allocating in proportion to the
//! counts; frames that declare huge sizes are refused before decoding; the
//! voxel iterator cannot be made to spin over empty paths.
//!
//! Memory is measured with a counting global allocator: per thread, the peak
//! of live heap bytes while a closure runs.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use dagfmt::layout::{self, HEADER_SIZE, MAGIC, SECTION_ENTRY_SIZE, SectionKind};
use dagfmt::transport::{self, TransportError};
use dagfmt::validate::{ValidateOptions, validate_with};
use dagfmt::{AttributeKind, Dag, DagBuilder, ErrorCode};

/// Counts the live heap bytes of each thread.
struct CountingAllocator;

thread_local! {
    static LIVE: Cell<isize> = const { Cell::new(0) };
    static PEAK: Cell<isize> = const { Cell::new(0) };
}

fn note(delta: isize) {
    // `try_with`: the thread-local is gone while a thread shuts down.
    let _ = LIVE.try_with(|live| {
        let now = live.get() + delta;
        live.set(now);
        let _ = PEAK.try_with(|peak| peak.set(peak.get().max(now)));
    });
}

// SAFETY: every call is forwarded unchanged to the system allocator; the
// bookkeeping only touches thread-local counters and never allocates.
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: same contract as ours, forwarded.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            note(layout.size() as isize);
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: same contract as ours, forwarded.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            note(layout.size() as isize);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as ours, forwarded.
        unsafe { System.dealloc(ptr, layout) };
        note(-(layout.size() as isize));
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: same contract as ours, forwarded.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            note(new_size as isize - layout.size() as isize);
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: CountingAllocator = CountingAllocator;

/// Runs `f` and returns its result with the most heap bytes it held at once
/// (on this thread) beyond what was live before.
fn peak_heap<R>(f: impl FnOnce() -> R) -> (R, usize) {
    let start = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(start));
    let result = f();
    let peak = PEAK.with(Cell::get);
    (result, (peak - start).max(0) as usize)
}

/// The bound this test holds the reader and validator to on hostile files:
/// a fixed allowance (error messages, the section table) plus a small
/// multiple of the file (spec/VDAG.md § 16.2).
fn allowance(file_len: usize) -> usize {
    64 * 1024 + 4 * file_len
}

/// A valid file to damage: depth 6, a few hundred voxels.
fn sample() -> Vec<u8> {
    DagBuilder::from_fn(6, AttributeKind::VoxelCount, |x, y, z| {
        (x * 7 + y * 3 + z) % 11 == 0
    })
    .unwrap()
    .to_bytes()
}

fn put(bytes: &mut [u8], at: usize, value: &[u8]) {
    bytes[at..at + value.len()].copy_from_slice(value);
}

fn entry(index: usize) -> usize {
    HEADER_SIZE + index * SECTION_ENTRY_SIZE
}

/// Recomputes the header checksum, so that a damaged field is the only finding.
fn fix_header_crc(bytes: &mut [u8]) {
    let count = usize::from(u16::from_le_bytes([bytes[26], bytes[27]]));
    let table_end = entry(count).min(bytes.len());
    let head: [u8; HEADER_SIZE] = bytes[..HEADER_SIZE].try_into().unwrap();
    let crc = layout::header_checksum(&head, &bytes[HEADER_SIZE..table_end]);
    put(bytes, layout::HEADER_CRC_OFFSET, &crc.to_le_bytes());
}

/// Opens and validates `bytes`, each under the allocation allowance; returns
/// the reader's error code and the validator's codes.
fn check_hostile(what: &str, bytes: &[u8]) -> (ErrorCode, Vec<ErrorCode>) {
    let (opened, open_peak) = peak_heap(|| dagfmt::AnyDag::open(bytes).map(|_| ()));
    let options = ValidateOptions {
        threads: false,
        ..ValidateOptions::default()
    };
    let (report, validate_peak) = peak_heap(|| validate_with(bytes, &options));
    let limit = allowance(bytes.len());
    assert!(
        open_peak <= 16 * 1024,
        "{what}: opening allocated {open_peak} bytes"
    );
    assert!(
        validate_peak <= limit,
        "{what}: validating allocated {validate_peak} bytes, over {limit}"
    );
    let code = opened.expect_err(what).code;
    let mut codes: Vec<ErrorCode> = report.errors.iter().map(|e| e.code).collect();
    codes.sort();
    codes.dedup();
    (code, codes)
}

#[test]
fn the_sample_is_valid_and_cheap() {
    let bytes = sample();
    let (report, peak) = peak_heap(|| {
        validate_with(
            &bytes,
            &ValidateOptions {
                threads: false,
                ..ValidateOptions::default()
            },
        )
    });
    assert!(report.is_valid(), "{:?}", report.errors);
    assert!(peak <= allowance(bytes.len()), "{peak} bytes");
    let (dag, peak) = peak_heap(|| Dag::open(&bytes).map(|d| d.depth()));
    assert_eq!(dag.unwrap(), 6);
    assert!(peak <= 16 * 1024, "{peak} bytes");
}

/// The sample as format 2.0.
fn sample_v2() -> Vec<u8> {
    dagfmt::v2file::upgrade(&Dag::open(&sample()).unwrap()).unwrap()
}

#[test]
fn the_2_0_sample_is_valid_and_cheap() {
    let bytes = sample_v2();
    let options = ValidateOptions {
        threads: false,
        ..ValidateOptions::default()
    };
    let (report, _) = peak_heap(|| validate_with(&bytes, &options));
    assert!(report.is_valid(), "{:?}", report.errors);
    let (dag, peak) = peak_heap(|| dagfmt::AnyDag::open(&bytes).map(|d| d.version_major()));
    assert_eq!(dag.unwrap(), 2);
    assert!(peak <= 16 * 1024, "{peak} bytes");
}

#[test]
fn huge_node_count_2_0() {
    let mut bytes = sample_v2();
    put(&mut bytes, entry(1) + 24, &u64::MAX.to_le_bytes());
    fix_header_crc(&mut bytes);
    let (code, codes) = check_hostile("2.0 node level with 2^64 - 1 records", &bytes);
    assert_eq!(code, ErrorCode::ItemCountMismatch2);
    assert_eq!(codes, [ErrorCode::ItemCountMismatch2]);
}

#[test]
fn huge_leaf_count_2_0() {
    let mut bytes = sample_v2();
    put(&mut bytes, entry(4) + 24, &(u64::MAX / 8).to_le_bytes());
    fix_header_crc(&mut bytes);
    let (code, _) = check_hostile("2.0 leaf level with 2^61 leaves", &bytes);
    assert_eq!(code, ErrorCode::LevelTooLarge);
}

#[test]
fn node_level_longer_than_the_limit_2_0() {
    let mut bytes = sample_v2();
    put(
        &mut bytes,
        entry(1) + 16,
        &(layout::MAX_NODE_LEVEL_BYTES + 8).to_le_bytes(),
    );
    fix_header_crc(&mut bytes);
    let (code, codes) = check_hostile("2.0 node level over 2^34 bytes", &bytes);
    // The section also runs past the end of the file (E020, checked first).
    assert_eq!(code, ErrorCode::SectionOutOfBounds);
    assert!(codes.contains(&ErrorCode::LevelTooLarge), "{codes:?}");
}

#[test]
fn widths_over_40_bits_2_0() {
    let mut bytes = sample_v2();
    bytes[entry(1) + 7] = 41;
    fix_header_crc(&mut bytes);
    let (code, codes) = check_hostile("2.0 widths over 40 bits", &bytes);
    assert_eq!(code, ErrorCode::BadWidths);
    assert_eq!(codes, [ErrorCode::BadWidths]);
}

#[test]
fn huge_node_count() {
    let mut bytes = sample();
    put(&mut bytes, entry(1) + 24, &u64::MAX.to_le_bytes());
    fix_header_crc(&mut bytes);
    let (code, codes) = check_hostile("node level with 2^64 - 1 nodes", &bytes);
    assert_eq!(code, ErrorCode::ItemCountMismatch);
    assert_eq!(codes, [ErrorCode::ItemCountMismatch]);
}

#[test]
fn huge_leaf_count() {
    let mut bytes = sample();
    let leaf = 6 - 2;
    put(&mut bytes, entry(leaf) + 24, &(u64::MAX / 8).to_le_bytes());
    fix_header_crc(&mut bytes);
    let (code, codes) = check_hostile("leaf level with 2^61 leaves", &bytes);
    assert_eq!(code, ErrorCode::LevelTooLarge);
    assert_eq!(
        codes,
        [ErrorCode::LevelTooLarge, ErrorCode::ItemCountMismatch]
    );
}

#[test]
fn depth_255() {
    let mut bytes = sample();
    bytes[24] = 255;
    fix_header_crc(&mut bytes);
    let (code, codes) = check_hostile("depth 255", &bytes);
    assert_eq!(code, ErrorCode::DepthOutOfRange);
    assert_eq!(codes, [ErrorCode::DepthOutOfRange]);
}

#[test]
fn section_count_65535() {
    let mut bytes = sample();
    put(&mut bytes, 26, &u16::MAX.to_le_bytes());
    fix_header_crc(&mut bytes);
    let (code, codes) = check_hostile("65535 sections", &bytes);
    assert_eq!(code, ErrorCode::BadSectionTable);
    assert_eq!(codes, [ErrorCode::BadSectionTable]);
}

#[test]
fn section_past_the_end() {
    for (what, offset, length) in [
        ("offset near 2^64", u64::MAX - 7, 8),
        ("length near 2^64", 0, u64::MAX - 7),
        ("one byte past the end", 0, 1),
    ] {
        let mut bytes = sample();
        let leaf = 6 - 2;
        let start =
            u64::from_le_bytes(bytes[entry(leaf) + 8..entry(leaf) + 16].try_into().unwrap());
        let offset = if offset == 0 { start } else { offset };
        let length = if length == 1 {
            bytes.len() as u64 - start + 8
        } else {
            length
        };
        put(&mut bytes, entry(leaf) + 8, &offset.to_le_bytes());
        put(&mut bytes, entry(leaf) + 16, &length.to_le_bytes());
        fix_header_crc(&mut bytes);
        let (code, codes) = check_hostile(what, &bytes);
        assert_eq!(code, ErrorCode::SectionOutOfBounds, "{what}");
        assert!(
            codes.contains(&ErrorCode::SectionOutOfBounds),
            "{what}: {codes:?}"
        );
    }
}

#[test]
fn node_level_longer_than_the_limit() {
    let mut bytes = sample();
    put(&mut bytes, entry(2) + 16, &(1u64 << 40).to_le_bytes());
    fix_header_crc(&mut bytes);
    let (code, codes) = check_hostile("node level of 2^40 bytes", &bytes);
    assert_eq!(code, ErrorCode::SectionOutOfBounds);
    assert!(codes.contains(&ErrorCode::LevelTooLarge), "{codes:?}");
}

#[test]
fn huge_file_size_field() {
    let mut bytes = sample();
    put(&mut bytes, 64, &u64::MAX.to_le_bytes());
    fix_header_crc(&mut bytes);
    let (code, codes) = check_hostile("file size 2^64 - 1", &bytes);
    assert_eq!(code, ErrorCode::FileSizeMismatch);
    assert_eq!(codes, [ErrorCode::FileSizeMismatch]);
}

/// A depth-`depth` file whose interior nodes each have all eight children,
/// every pointer leading to the one node of the next level, and whose one
/// leaf is empty: 8^(D - 2) paths, not one voxel.
fn empty_paths(depth: u8) -> Vec<u8> {
    let levels = usize::from(depth) - 1;
    let table_end = entry(levels);
    let mut sections: Vec<Vec<u8>> = (0..levels - 1)
        .map(|_| {
            let mut record = 0xFFu32.to_le_bytes().to_vec();
            record.extend_from_slice(&[0; 8]);
            record
        })
        .collect();
    sections.push(0u64.to_le_bytes().to_vec());
    let mut bytes = vec![0u8; table_end];
    for (i, data) in sections.iter().enumerate() {
        let offset = layout::align_section(bytes.len() as u64);
        bytes.resize(offset as usize, 0);
        let leaf = i == levels - 1;
        let at = entry(i);
        let kind = if leaf {
            SectionKind::LEAF_LEVEL
        } else {
            SectionKind::NODE_LEVEL
        };
        put(&mut bytes, at, &kind.to_le_bytes());
        bytes[at + 4] = i as u8;
        bytes[at + 5] = if leaf { 0 } else { 1 };
        put(&mut bytes, at + 8, &offset.to_le_bytes());
        put(&mut bytes, at + 16, &(data.len() as u64).to_le_bytes());
        put(&mut bytes, at + 24, &1u64.to_le_bytes());
        put(&mut bytes, at + 32, &crc32c::crc32c(data).to_le_bytes());
        bytes.extend_from_slice(data);
    }
    put(&mut bytes, 0, &MAGIC);
    put(&mut bytes, 8, &layout::VERSION_MAJOR.to_le_bytes());
    put(&mut bytes, 12, &(HEADER_SIZE as u32).to_le_bytes());
    bytes[24] = depth;
    put(&mut bytes, 26, &(levels as u16).to_le_bytes());
    put(&mut bytes, 56, &1.0f64.to_le_bytes());
    let len = bytes.len() as u64;
    put(&mut bytes, 64, &len.to_le_bytes());
    fix_header_crc(&mut bytes);
    bytes
}

#[test]
fn empty_paths_end_the_voxel_iteration_at_once() {
    let bytes = empty_paths(21);
    let dag = Dag::open(&bytes).expect("the open checks do not look at nodes");
    let start = std::time::Instant::now();
    let mut voxels = dag.voxels();
    let first = voxels.next().expect("an error, not the end");
    assert_eq!(first.unwrap_err().code, ErrorCode::EmptyLeafMask);
    assert!(voxels.next().is_none());
    // Without the check this would walk 8^19 paths.
    assert!(start.elapsed().as_secs() < 5);
    // The point queries and counts follow one path or memoise.
    assert!(!dag.is_set(5, 6, 7).unwrap());
    assert_eq!(dag.subtree_voxel_count(dag.root().unwrap()).unwrap(), 0);
    let report = validate_with(&bytes, &ValidateOptions::default());
    assert!(report.has(ErrorCode::EmptyLeafMask), "{:?}", report.errors);
    // The committed regression input of the `reader` fuzz target is this file.
    let committed = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz/regressions/reader/empty-paths-depth-21.vdag");
    assert_eq!(std::fs::read(committed).unwrap(), bytes);
}

/// A zstd frame header: magic, descriptor, then `rest`.
fn frame(descriptor: u8, rest: &[u8]) -> Vec<u8> {
    let mut f = transport::ZSTD_MAGIC.to_vec();
    f.push(descriptor);
    f.extend_from_slice(rest);
    f
}

/// A last RLE block of `size` copies of `byte`.
fn rle_block(size: u32, byte: u8) -> [u8; 4] {
    let header = 1 | (1 << 1) | (size << 3);
    let h = header.to_le_bytes();
    [h[0], h[1], h[2], byte]
}

#[test]
fn transport_refuses_huge_declared_sizes_before_decoding() {
    // Single segment, 8-byte content size: 2^41 bytes, over the default limit.
    let mut rest = (1u64 << 41).to_le_bytes().to_vec();
    rest.extend_from_slice(&rle_block(100, 0));
    let huge = frame(0b1110_0000, &rest);
    let (result, peak) = peak_heap(|| transport::unpack(&huge, transport::DEFAULT_MAX_SIZE));
    assert!(
        matches!(result, Err(TransportError::TooLarge { size, .. }) if size == 1 << 41),
        "{result:?}"
    );
    assert!(peak < 4096, "{peak} bytes");

    // 64 MiB, under the limit and zstd's default window maximum, but far more
    // than 17 bytes of frame can hold (zstd would allocate it as its buffer).
    let mut rest = (1u64 << 26).to_le_bytes().to_vec();
    rest.extend_from_slice(&rle_block(100, 0));
    let lying = frame(0b1110_0000, &rest);
    let (result, peak) = peak_heap(|| transport::unpack(&lying, transport::DEFAULT_MAX_SIZE));
    assert!(
        matches!(result, Err(TransportError::Corrupt(_))),
        "{result:?}"
    );
    assert!(peak < 4096, "{peak} bytes");

    // The largest size such a frame can hold is accepted up to decoding.
    let possible = transport::MAX_EXPANSION * lying.len() as u64;
    let mut rest = possible.to_le_bytes().to_vec();
    rest.extend_from_slice(&rle_block(100, 0));
    let honest_size = frame(0b1110_0000, &rest);
    assert!(!matches!(
        transport::unpack(&honest_size, transport::DEFAULT_MAX_SIZE),
        Err(TransportError::TooLarge { .. })
    ));
}

#[test]
fn transport_refuses_a_window_larger_than_the_frame_can_fill() {
    // No content size, window descriptor 2^27 (zstd's default maximum): zstd
    // would allocate the 128 MiB window for these 10 bytes.
    let mut rest = vec![17 << 3];
    rest.extend_from_slice(&rle_block(100, 0));
    let wide = frame(0, &rest);
    let result = transport::unpack(&wide, transport::DEFAULT_MAX_SIZE);
    assert!(
        matches!(result, Err(TransportError::Corrupt(_))),
        "{result:?}"
    );
    // The same frame with a 1 KiB window decodes (and is then no .vdag).
    let mut rest = vec![0];
    rest.extend_from_slice(&rle_block(100, 0));
    let narrow = frame(0, &rest);
    let result = transport::unpack(&narrow, transport::DEFAULT_MAX_SIZE);
    assert!(
        matches!(result, Err(TransportError::NotVdag(_))),
        "{result:?}"
    );
}

#[test]
fn transport_output_stays_under_the_limit_without_a_declared_size() {
    // 300 blocks of 100 zero bytes, no content size: stops at the limit.
    let mut rest = vec![0];
    for i in 0..300 {
        let last = u32::from(i == 299);
        let header = last | (1 << 1) | (100 << 3);
        let h = header.to_le_bytes();
        rest.extend_from_slice(&[h[0], h[1], h[2], 0]);
    }
    let many = frame(0, &rest);
    let (result, peak) = peak_heap(|| transport::unpack(&many, 5000));
    assert!(
        matches!(result, Err(TransportError::TooLarge { limit: 5000, .. })),
        "{result:?}"
    );
    // The 128 KiB read chunk, the output (at most the limit) and a message.
    assert!(peak < (128 << 10) + 2 * 5000 + 4096, "{peak} bytes");
}

/// Voxels of a cube of side 2^`depth` set at random (about one in three): its
/// leaves, and the nodes above them, are nearly all distinct, so that the
/// 2.0 encoder's estimates (which count a class per 1.0 node, the most there
/// can be) meet the passes' real tables.
fn dense_random_dag(depth: u8) -> Vec<u8> {
    DagBuilder::from_fn(depth, AttributeKind::VoxelCount, |x, y, z| {
        // SplitMix64's finaliser of the coordinates.
        let mut h = (u64::from(x) << 42 | u64::from(y) << 21 | u64::from(z))
            .wrapping_add(0x9E37_79B9_7F4A_7C15);
        h = (h ^ (h >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h = (h ^ (h >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        (h ^ (h >> 31)) % 3 == 0
    })
    .unwrap()
    .to_bytes()
}

/// The encoder's heap peak over `dag` with `options` on one thread (so that
/// every allocation of its parallel steps is on the thread measured), and
/// how many passes went out of core.
fn encoder_peak(dag: &Dag<'_>, options: &dagfmt::v2enc::EncodeOptions) -> (usize, usize) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let (passes, peak) = pool.install(|| {
        peak_heap(|| {
            dagfmt::v2enc::encode_levels(dag, options)
                .unwrap()
                .external_passes()
        })
    });
    (peak, passes)
}

/// Room for what the estimates leave out: the store's pieces written to and
/// read from the scratch file (1 MiB each), the small per-chunk vectors.
const ENCODER_SLACK: usize = 3 << 20;

#[test]
fn the_2_0_encoder_s_working_set_estimate_bounds_its_peak_closely() {
    let bytes = dense_random_dag(8);
    let dag = Dag::open(&bytes).unwrap();
    let estimate = dagfmt::v2enc::in_memory_working_set(&dag) as usize;
    let dir = tempfile::tempdir().unwrap();
    // A budget of the estimate: every pass in memory, every finished table
    // in the scratch file, so the peak is the largest pass's.
    let options = dagfmt::v2enc::EncodeOptions {
        memory_budget: Some(estimate as u64),
        refuse_below_least: true,
        scratch_dir: Some(dir.path().to_path_buf()),
    };
    let (peak, passes) = encoder_peak(&dag, &options);
    eprintln!(
        "in memory: estimate {estimate}, peak {peak}; nodes {:?}",
        dag.levels()
            .iter()
            .map(|l| l.node_count)
            .collect::<Vec<_>>()
    );
    assert_eq!(
        passes, 0,
        "a budget of the estimate keeps every pass in memory"
    );
    assert!(
        peak <= estimate + ENCODER_SLACK,
        "peak {peak} over the estimate {estimate}"
    );
    // Close: the estimate counts vectors grown by doubling at twice their
    // bytes, which they reach only at a power of two; no more than a fifth
    // over the peak.
    assert!(
        estimate <= peak + peak / 5,
        "the estimate {estimate} over-counts the peak {peak}"
    );
}

#[test]
fn the_2_0_encoder_s_least_memory_bounds_its_peak_out_of_core() {
    let bytes = dense_random_dag(8);
    let dag = Dag::open(&bytes).unwrap();
    let least = dagfmt::v2enc::least_memory(&dag) as usize;
    let dir = tempfile::tempdir().unwrap();
    let options = |budget: u64, refuse_below_least| dagfmt::v2enc::EncodeOptions {
        memory_budget: Some(budget),
        refuse_below_least,
        scratch_dir: Some(dir.path().to_path_buf()),
    };
    // No budget: every pass but the root's merge and the leaves' layout out
    // of core, with its least chunks.
    let (peak, passes) = encoder_peak(&dag, &options(0, false));
    eprintln!("out of core: least {least}, peak {peak}");
    assert_eq!(passes, 3 * usize::from(dag.leaf_level()));
    assert!(peak <= least + ENCODER_SLACK, "peak {peak} over {least}");
    assert!(least <= dagfmt::v2enc::in_memory_working_set(&dag) as usize);
    // Asked to, the encoder refuses such a budget, naming what it needs (a
    // class per 1.0 node at most).
    match dagfmt::v2enc::encode_levels(&dag, &options(0, true)) {
        Err(dagfmt::v2file::ConvertError::Budget { least: l, budget }) => {
            assert_eq!(budget, 0);
            assert!(0 < l && l as usize <= least, "{l} against {least}");
        }
        other => panic!("not refused: {:?}", other.map(|e| e.external_passes())),
    }
    // And takes the least it names.
    dagfmt::v2enc::encode_levels(&dag, &options(least as u64, true)).unwrap();
}
