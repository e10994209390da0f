//! Smoke runs of the fuzz harnesses (`dagfmt::fuzzing`, the bodies of the
//! `reader`, `validator`, `transport` and `batch` targets in `fuzz/`), so that
//! `cargo test` exercises them without libFuzzer:
//!
//! - over every committed regression input (`fuzz/regressions/<target>/`),
//!   seed (`fuzz/seeds/<target>/`) and conformance case that fits the target;
//! - over a few thousand inputs made here from valid files (built with the
//!   builder) by deterministic mutations: bit flips, byte overwrites,
//!   truncations, extensions and hostile header and section-table fields.
//!
//! A failure names the input (a file, or the mutation's number and kind) so
//! that it can be reproduced and committed under `fuzz/regressions/`.

use std::path::{Path, PathBuf};

use dagfmt::batch::{self, Hit, Ray};
use dagfmt::fuzzing;
use dagfmt::layout::{HEADER_SIZE, SECTION_ENTRY_SIZE};
use dagfmt::{AttributeKind, DagBuilder, transport};

/// A small deterministic generator (SplitMix64).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Every file directly under `dir` (none when it does not exist), except READMEs.
fn files_in(dir: &Path) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut files: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && p.file_name().is_some_and(|n| n != "README.md"))
        .collect();
    files.sort();
    files
}

/// The committed inputs of `target`: regressions, seeds and the conformance
/// cases with the given extensions.
fn committed_inputs(target: &str, case_extensions: &[&str]) -> Vec<PathBuf> {
    let root = repo();
    let mut files = files_in(&root.join("fuzz/regressions").join(target));
    files.extend(files_in(&root.join("fuzz/seeds").join(target)));
    for dir in ["conformance/cases/trace", "conformance/cases/validate"] {
        files.extend(files_in(&root.join(dir)).into_iter().filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| case_extensions.contains(&e))
        }));
    }
    files
}

/// Runs `harness` over every committed input of `target`; returns how many.
fn run_committed(target: &str, case_extensions: &[&str], harness: fn(&[u8])) -> usize {
    let files = committed_inputs(target, case_extensions);
    for path in &files {
        let bytes = std::fs::read(path).unwrap();
        eprintln!("{target}: {}", path.display());
        harness(&bytes);
    }
    files.len()
}

/// Small valid files from the builder: several depths, both attribute kinds,
/// with and without colours, empty and full volumes.
fn valid_files() -> Vec<Vec<u8>> {
    let mut rng = Rng(7);
    let mut files = Vec::new();
    for depth in 2..=6u8 {
        for kind in [AttributeKind::None, AttributeKind::VoxelCount] {
            let r = 1u32 << depth;
            let n = 1 + rng.below(40);
            let voxels: Vec<[u32; 3]> = (0..n)
                .map(|_| [0; 3].map(|_: u32| rng.below(r as usize) as u32))
                .collect();
            let mut built = DagBuilder::from_voxels(depth, kind, voxels).unwrap();
            if kind == AttributeKind::VoxelCount && depth % 2 == 0 {
                let colors = (0..built.voxel_count())
                    .map(|i| [i as u8, 1, 2, 255])
                    .collect();
                built.set_colors(colors).unwrap();
            } else if kind == AttributeKind::VoxelCount {
                let colors: Vec<[u8; 4]> = (0..built.voxel_count())
                    .map(|i| [(i * 37) as u8, (i / 3) as u8, 2, 255 - (i % 2) as u8])
                    .collect();
                built.set_packed_colors(&colors, depth).unwrap();
            }
            files.push(built.to_bytes());
        }
    }
    for depth in [2u8, 3, 21] {
        files.push(
            DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, [])
                .unwrap()
                .to_bytes(),
        );
    }
    files.push(
        DagBuilder::from_fn(4, AttributeKind::VoxelCount, |x, y, z| (x ^ y ^ z) & 1 == 0)
            .unwrap()
            .to_bytes(),
    );
    files.push(
        DagBuilder::from_fn(3, AttributeKind::None, |_, _, _| true)
            .unwrap()
            .to_bytes(),
    );
    // Every file also as format 2.0.
    let v2: Vec<Vec<u8>> = files
        .iter()
        .map(|f| dagfmt::v2file::upgrade(&dagfmt::Dag::open(f).unwrap()).unwrap())
        .collect();
    files.extend(v2);
    files
}

/// Byte positions worth attacking: header fields and every section entry's
/// offset, length and item count.
fn field_positions(file: &[u8]) -> Vec<(usize, usize)> {
    let mut fields = vec![(24, 1), (26, 2), (64, 8), (72, 8), (12, 4)];
    let count = file
        .get(26..28)
        .map_or(0, |b| u16::from_le_bytes([b[0], b[1]]));
    for i in 0..usize::from(count.min(64)) {
        let at = HEADER_SIZE + i * SECTION_ENTRY_SIZE;
        fields.extend([
            (at, 4),
            (at + 4, 1),
            (at + 5, 1),
            (at + 8, 8),
            (at + 16, 8),
            (at + 24, 8),
        ]);
    }
    fields.retain(|&(at, len)| at + len <= file.len());
    fields
}

/// One mutation of `file`; the name says which, for failure messages.
fn mutate(rng: &mut Rng, file: &[u8]) -> (String, Vec<u8>) {
    let mut out = file.to_vec();
    let len = out.len();
    let name = match rng.below(7) {
        0 => {
            let bit = rng.below(len * 8);
            out[bit / 8] ^= 1 << (bit % 8);
            format!("flip bit {bit}")
        }
        1 => {
            let n = 1 + rng.below(4);
            for _ in 0..n {
                let at = rng.below(len);
                out[at] = rng.next() as u8;
            }
            format!("{n} random bytes")
        }
        2 => {
            let cut = rng.below(len);
            out.truncate(cut);
            format!("truncated to {cut}")
        }
        3 => {
            let extra = 1 + rng.below(64);
            out.extend((0..extra).map(|_| rng.next() as u8));
            format!("{extra} bytes appended")
        }
        _ if field_positions(&out).is_empty() => {
            let at = rng.below(len);
            out[at] = !out[at];
            format!("byte {at} inverted")
        }
        _ => {
            // A hostile header or section-table field: huge, zero, all ones,
            // or just past the end of the file.
            let fields = field_positions(&out);
            let (at, width) = fields[rng.below(fields.len())];
            let value: u64 = match rng.below(5) {
                0 => u64::MAX,
                1 => 0,
                2 => len as u64 + rng.below(64) as u64,
                3 => 1 << rng.below(64),
                _ => rng.next(),
            };
            out[at..at + width].copy_from_slice(&value.to_le_bytes()[..width]);
            // Keep the file's own size field in step half of the time, so
            // that the checks behind E010 are reached too.
            if rng.below(2) == 0 && out.len() >= 72 {
                let l = out.len() as u64;
                out[64..72].copy_from_slice(&l.to_le_bytes());
            }
            format!("field at byte {at} ({width} bytes) set to {value:#x}")
        }
    };
    (name, out)
}

/// Runs `harness` over `per_file` mutations of each valid file.
fn run_mutations(target: &str, harness: fn(&[u8]), per_file: usize) -> usize {
    let files = valid_files();
    let mut rng = Rng(0x5EED ^ target.len() as u64);
    let mut runs = 0;
    for (f, file) in files.iter().enumerate() {
        harness(file);
        for m in 0..per_file {
            let (name, input) = mutate(&mut rng, file);
            let result = std::panic::catch_unwind(|| harness(&input));
            if let Err(panic) = result {
                eprintln!("{target}: valid file {f}, mutation {m} ({name}) failed");
                std::panic::resume_unwind(panic);
            }
            runs += 1;
        }
    }
    runs
}

#[test]
fn reader_harness_over_committed_and_mutated_files() {
    let committed = run_committed("reader", &["vdag"], fuzzing::reader);
    assert!(committed > 50, "the conformance cases are missing");
    let mutated = run_mutations("reader", fuzzing::reader, 300);
    assert!(mutated >= 4000, "{mutated} mutations");
}

#[test]
fn validator_harness_over_committed_and_mutated_files() {
    let committed = run_committed("validator", &["vdag"], fuzzing::validator);
    assert!(committed > 50, "the conformance cases are missing");
    let mutated = run_mutations("validator", fuzzing::validator, 300);
    assert!(mutated >= 4000, "{mutated} mutations");
}

#[test]
fn packed_colors_harness_over_committed_random_and_mutated_sections() {
    let committed = run_committed("packed_colors", &["bin"], fuzzing::packed_colors);
    let mut rng = Rng(0xC010);
    let mut runs = 0;
    for _ in 0..300 {
        // A valid section of random colours, then mutations of it.
        let n = rng.below(300);
        let colors: Vec<[u8; 4]> = (0..n)
            .map(|i| {
                let base = (i / (1 + rng.below(20))) as u8;
                [base, base.wrapping_mul(3), rng.below(4) as u8, 255]
            })
            .collect();
        let bound = rng.below(12) as u8;
        let (section, _) = dagfmt::packed_colors::encode(&colors, bound).unwrap();
        let mut input = (n as u16).to_le_bytes().to_vec();
        input.extend_from_slice(&section);
        fuzzing::packed_colors(&input);
        for _ in 0..10 {
            let mut m = input.clone();
            let at = rng.below(m.len());
            m[at] ^= 1 << rng.below(8);
            fuzzing::packed_colors(&m);
            runs += 1;
        }
    }
    assert!(committed + runs >= 3000);
}

#[test]
fn transport_harness_over_committed_packed_and_random_inputs() {
    run_committed("transport", &[], fuzzing::transport);
    let mut rng = Rng(3);
    for (f, file) in valid_files().iter().enumerate() {
        let packed = transport::pack(file, 3).unwrap();
        fuzzing::transport(&packed);
        for m in 0..60 {
            let (name, input) = mutate(&mut rng, &packed);
            let result = std::panic::catch_unwind(|| fuzzing::transport(&input));
            if let Err(panic) = result {
                eprintln!("transport: packed file {f}, mutation {m} ({name}) failed");
                std::panic::resume_unwind(panic);
            }
        }
    }
    // Random bytes behind the zstd magic.
    for n in 0..500 {
        let len = rng.below(200);
        let mut input = transport::ZSTD_MAGIC.to_vec();
        input.extend((0..len).map(|_| rng.next() as u8));
        let result = std::panic::catch_unwind(|| fuzzing::transport(&input));
        if let Err(panic) = result {
            eprintln!("transport: random frame {n} failed: {input:02x?}");
            std::panic::resume_unwind(panic);
        }
    }
}

/// Random rays and hits in both forms, some fields extreme.
fn random_batches(rng: &mut Rng) -> Vec<Vec<u8>> {
    let special = [
        0.0,
        -0.0,
        1.0,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::NAN,
        f32::MIN_POSITIVE,
        1e-45,
        f32::MAX,
    ];
    let float = |rng: &mut Rng| {
        if rng.below(3) == 0 {
            special[rng.below(special.len())]
        } else {
            f32::from_bits(rng.next() as u32)
        }
    };
    let mut batches = Vec::new();
    for _ in 0..40 {
        let n = rng.below(6);
        let rays: Vec<Ray> = (0..n)
            .map(|_| Ray {
                origin: [float(rng), float(rng), float(rng)],
                dir: [float(rng), float(rng), float(rng)],
                tmin: float(rng),
                tmax: float(rng),
                level: (rng.below(2) == 0).then(|| 1 + rng.below(21) as u8),
            })
            .collect();
        let hits: Vec<Hit> = (0..n)
            .map(|_| {
                if rng.below(3) == 0 {
                    Hit::MISS
                } else {
                    Hit {
                        hit: true,
                        t: float(rng),
                        voxel: [rng.next() as u32, rng.next() as u32, rng.next() as u32],
                        level: 1 + rng.below(21) as u8,
                        face: rng.below(7) as u8,
                        index: (rng.below(2) == 0).then(|| rng.next() >> 1),
                    }
                }
            })
            .collect();
        let mut out = Vec::new();
        batch::write_rays_text(&mut out, &rays).unwrap();
        batches.push(std::mem::take(&mut out));
        batch::write_rays_binary(&mut out, &rays).unwrap();
        batches.push(std::mem::take(&mut out));
        batch::write_hits_text(&mut out, &hits).unwrap();
        batches.push(std::mem::take(&mut out));
        batch::write_hits_binary(&mut out, &hits).unwrap();
        batches.push(out);
    }
    batches
}

#[test]
fn batch_harness_over_committed_random_and_mutated_batches() {
    run_committed("batch", &["rays"], fuzzing::batch);
    let mut rng = Rng(11);
    let batches = random_batches(&mut rng);
    for (b, bytes) in batches.iter().enumerate() {
        fuzzing::batch(bytes);
        if bytes.is_empty() {
            continue;
        }
        for m in 0..25 {
            let (name, input) = mutate(&mut rng, bytes);
            let result = std::panic::catch_unwind(|| fuzzing::batch(&input));
            if let Err(panic) = result {
                eprintln!("batch: batch {b}, mutation {m} ({name}) failed");
                std::panic::resume_unwind(panic);
            }
        }
    }
    // Binary headers with hostile counts.
    for magic in [batch::RAYS_MAGIC, batch::HITS_MAGIC] {
        for count in [u64::MAX, u64::MAX / 32, 1 << 40, 1, 2] {
            let mut bytes = magic.to_vec();
            bytes.extend_from_slice(&1u32.to_le_bytes());
            bytes.extend_from_slice(&count.to_le_bytes());
            bytes.extend_from_slice(&[0; 40]);
            fuzzing::batch(&bytes);
        }
    }
}
