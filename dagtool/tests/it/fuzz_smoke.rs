//! Smoke runs of the importer fuzz harnesses (`dagtool::fuzzing`, the bodies
//! of the `obj_import` and `voxel_list` targets in `fuzz/`), so that
//! `cargo test` exercises them without libFuzzer: over every committed
//! regression input and seed (`fuzz/regressions/<target>/`,
//! `fuzz/seeds/<target>/`), then over a few thousand deterministic mutations
//! of the seeds and of generated inputs.

use std::path::{Path, PathBuf};

use dagtool::fuzzing;
use dagtool::voxlist;

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

/// The committed regression inputs and seeds of `target`, with their bytes.
fn committed(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let fuzz = Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz");
    let mut files = Vec::new();
    for kind in ["regressions", "seeds"] {
        let Ok(entries) = std::fs::read_dir(fuzz.join(kind).join(target)) else {
            continue;
        };
        let mut paths: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_file() && p.file_name().is_some_and(|n| n != "README.md"))
            .collect();
        paths.sort();
        for path in paths {
            let bytes = std::fs::read(&path).unwrap();
            files.push((path, bytes));
        }
    }
    files
}

/// Tokens that OBJ and voxel-list parsers treat specially, spliced in by
/// the mutations.
const TOKENS: &[&[u8]] = &[
    b"\n",
    b" ",
    b"/",
    b"-",
    b"#",
    b"f ",
    b"v ",
    b"l ",
    b"p ",
    b"o x\n",
    b"g\n",
    b"mtllib a.mtl\n",
    b"usemtl m\n",
    b"-1",
    b"0",
    b"4294967296",
    b"-9223372036854775808",
    b"9223372036854775807",
    b"1e39",
    b"nan",
    b"inf",
    b"//",
    b"\t",
    b"\r\n",
    b"VVOX",
    b"\xff\xfe",
    b"element face 99\n",
    b"property list uchar int vertex_indices\n",
    b"solid ",
    b"facet normal 0 0 1\n",
    b"\"mode\":5,",
    b"\"extensionsRequired\":[\"KHR_draco_mesh_compression\"],",
    b"nTRN",
    b"XYZI",
    b"\xff\xff\xff\x7f",
];

/// One mutation of `input`: a bit flip, a random or token insertion, a
/// deletion, a truncation or a duplicated range.
fn mutate(rng: &mut Rng, input: &[u8]) -> Vec<u8> {
    let mut out = input.to_vec();
    let len = out.len();
    match rng.below(6) {
        0 if len > 0 => {
            let bit = rng.below(len * 8);
            out[bit / 8] ^= 1 << (bit % 8);
        }
        1 => {
            let token = TOKENS[rng.below(TOKENS.len())];
            let at = rng.below(len + 1);
            out.splice(at..at, token.iter().copied());
        }
        2 if len > 0 => {
            let at = rng.below(len);
            let n = 1 + rng.below(8.min(len - at));
            out.drain(at..at + n);
        }
        3 => out.truncate(rng.below(len + 1)),
        4 if len > 0 => {
            let at = rng.below(len);
            let n = 1 + rng.below(32.min(len - at));
            let copy = out[at..at + n].to_vec();
            out.splice(at..at, copy);
        }
        _ => {
            let at = rng.below(len + 1);
            out.insert(at, rng.next() as u8);
        }
    }
    out
}

/// Runs `harness` over each committed input and `per_input` chains of
/// mutations of it (each chain applying up to four mutations).
fn run(target: &str, harness: fn(&[u8]), extra: Vec<Vec<u8>>, per_input: usize) -> usize {
    let mut inputs: Vec<(String, Vec<u8>)> = committed(target)
        .into_iter()
        .map(|(p, b)| (p.display().to_string(), b))
        .collect();
    inputs.extend(
        extra
            .into_iter()
            .enumerate()
            .map(|(i, b)| (format!("generated input {i}"), b)),
    );
    assert!(inputs.len() >= 3, "{target}: the seeds are missing");
    let mut rng = Rng(target.len() as u64);
    let mut runs = 0;
    for (name, input) in &inputs {
        harness(input);
        for m in 0..per_input {
            let mut mutated = input.clone();
            for _ in 0..1 + rng.below(4) {
                mutated = mutate(&mut rng, &mutated);
            }
            if let Err(panic) = std::panic::catch_unwind(|| harness(&mutated)) {
                eprintln!(
                    "{target}: mutation {m} of {name} failed on {:?}",
                    String::from_utf8_lossy(&mutated)
                );
                std::panic::resume_unwind(panic);
            }
            runs += 1;
        }
    }
    runs
}

#[test]
fn obj_import_harness_over_committed_and_mutated_meshes() {
    // A generated grid of quads, and polygons with relative indices.
    let mut grid = String::new();
    for y in 0..4 {
        for x in 0..4 {
            grid.push_str(&format!("v {x} {y} {}\n", (x * y) % 3));
        }
    }
    for y in 0..3 {
        for x in 0..3 {
            let i = 1 + y * 4 + x;
            grid.push_str(&format!("f {i} {} {} {}\n", i + 1, i + 5, i + 4));
        }
    }
    let fan = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 0.5 1\nf -5 -4 -3 -2\nf -1 -5 -4\n";
    let runs = run(
        "obj_import",
        fuzzing::obj_import,
        vec![grid.into_bytes(), fan.as_bytes().to_vec()],
        400,
    );
    assert!(runs >= 2000, "{runs} runs");
}

#[test]
fn voxel_list_harness_over_committed_and_mutated_lists() {
    let mut binary = Vec::new();
    voxlist::write_binary(
        &mut binary,
        5,
        &[[0, 0, 0], [31, 30, 29], [7, 8, 9], [7, 8, 9]],
    )
    .unwrap();
    let text = b"# generated\n0 0 0\n3 1 2\n3 1 2 # again\n15 0 7\n".to_vec();
    let runs = run("voxel_list", fuzzing::voxel_list, vec![binary, text], 600);
    assert!(runs >= 2000, "{runs} runs");
    // Hostile binary counts: checked against the length before allocating.
    for count in [u64::MAX, u64::MAX / 12, 1 << 40, 2] {
        let mut bytes = voxlist::BINARY_MAGIC.to_vec();
        bytes.extend_from_slice(&1u32.to_le_bytes());
        bytes.extend_from_slice(&5u32.to_le_bytes());
        bytes.extend_from_slice(&count.to_le_bytes());
        bytes.extend_from_slice(&[0; 12]);
        let result = voxlist::read_bytes(&bytes, "hostile", None);
        assert!(
            result.is_err(),
            "count {count} over one record was accepted"
        );
        fuzzing::voxel_list(&bytes);
    }
}

#[test]
fn obj_indices_tobj_cannot_handle_are_refused_with_the_line() {
    for (obj, expected) in [
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/-5 2/-5 3/-5\n",
            "line 5: texture coordinate index -5",
        ),
        (
            "v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//9223372036854775807 2//1 3//1\n",
            "line 5: normal index 9223372036854775807",
        ),
        ("v 0 0 0\nf -4 1 1\n", "line 2: vertex index -4"),
        ("v 0 0 0\nl 0 1\n", "line 2: vertex index 0"),
    ] {
        let err = dagtool::input::obj::load_bytes(obj.as_bytes(), "t.obj")
            .unwrap_err()
            .to_string();
        assert!(err.contains(expected), "{err}");
        assert!(err.starts_with("t.obj: "), "{err}");
    }
    // Relative indices within range, and forward references, still load.
    let ok = "v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf -3/-1 -2/-1 -1/-1\nf 1 2 3\n";
    assert_eq!(
        dagtool::input::obj::load_bytes(ok.as_bytes(), "t.obj")
            .unwrap()
            .triangles
            .len(),
        2
    );
}

/// A small LAS (or LAZ) file in point format `format`, written by the `las`
/// crate: a few points with colours where the format has them.
pub fn las_bytes(format: u8, laz: bool) -> Vec<u8> {
    let mut f = las::point::Format::new(format).unwrap();
    f.is_compressed = laz;
    let mut builder = las::Builder::from((1, 4));
    builder.point_format = f;
    let header = builder.into_header().unwrap();
    let mut writer = las::Writer::new(std::io::Cursor::new(Vec::new()), header).unwrap();
    {
        for i in 0..7u16 {
            let mut p = las::Point {
                x: f64::from(i) * 0.5,
                y: 1.0 - f64::from(i),
                z: f64::from(i * i) * 0.01,
                ..Default::default()
            };
            if f.has_color {
                p.color = Some(las::Color::new(i * 9000, 65535 - i * 9000, 257 * i));
            }
            if f.has_gps_time {
                p.gps_time = Some(f64::from(i));
            }
            if f.has_nir {
                p.nir = Some(i);
            }
            if f.has_waveform {
                p.waveform = Some(las::raw::point::Waveform {
                    wave_packet_descriptor_index: 1,
                    byte_offset_to_waveform_data: u64::from(i) * 64,
                    waveform_packet_size_in_bytes: 64,
                    ..Default::default()
                });
            }
            writer.write_point(p).unwrap();
        }
    }
    writer.into_inner().unwrap().into_inner()
}

/// `DAGTOOL_FUZZ_SCALE=N` runs N times the mutations (a longer campaign
/// without libFuzzer; the default keeps `cargo test` fast).
fn scale() -> usize {
    std::env::var("DAGTOOL_FUZZ_SCALE")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1)
}

#[test]
fn input_format_harnesses_over_committed_and_mutated_files() {
    let n = 300 * scale();
    let runs = run("ply_import", fuzzing::ply_import, Vec::new(), n)
        + run("stl_import", fuzzing::stl_import, Vec::new(), n)
        + run("gltf_import", fuzzing::gltf_import, Vec::new(), n)
        + run("vox_import", fuzzing::vox_import, Vec::new(), n)
        + run("binvox_import", fuzzing::binvox_import, Vec::new(), n)
        + run(
            "las_import",
            fuzzing::las_import,
            vec![las_bytes(0, false), las_bytes(7, true), las_bytes(3, false)],
            n / 2,
        );
    assert!(runs >= 5000, "{runs} runs");
    // Found by libFuzzer: a LAS 1.4 extended record declaring 52 TB.
    let evlr = std::fs::read(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../fuzz/regressions/las_import/evlr-length-52TB.las"),
    )
    .unwrap();
    let err = dagtool::input::las::load_bytes(&evlr, "e.las")
        .err()
        .expect("the 52 TB record was accepted")
        .to_string();
    assert!(
        err.starts_with("e.las: the extended variable-length record at byte "),
        "{err}"
    );
}

/// The `laz` decompressor asserts that the points asked for are whole records
/// of its items: a header whose record length disagrees with the LAZ record is
/// refused first, naming both lengths.
#[test]
fn laz_items_of_another_record_length_are_refused() {
    let mut bytes = las_bytes(7, true);
    // Point data record length: u16 at byte 105 of the LAS header.
    let length = u16::from_le_bytes([bytes[105], bytes[106]]);
    bytes[105..107].copy_from_slice(&(length + 2).to_le_bytes());
    let err = dagtool::input::las::load_bytes(&bytes, "t.laz")
        .err()
        .expect("a record length the LAZ items do not make was accepted")
        .to_string();
    assert_eq!(
        err,
        format!(
            "t.laz: the LAZ record's items make points of {length} bytes, but the header says {}",
            length + 2
        )
    );
}

/// Every LAS point format, 0 to 10 (the waveform formats 4, 5, 9 and 10
/// included), plain and LAZ: the points written by the `las` crate come back
/// at their quantized positions, with their colours mapped to 8 bits by
/// `round(v / 257)` where the format has colours and white where it has none.
#[test]
fn every_las_point_format_reads_back_plain_and_compressed() {
    for format in 0..=10u8 {
        let has_color = las::point::Format::new(format).unwrap().has_color;
        for laz in [false, true] {
            let what = format!("format {format}{}", if laz { " LAZ" } else { "" });
            let bytes = las_bytes(format, laz);
            let mut cloud = dagtool::input::las::load_bytes(&bytes, "t.las")
                .unwrap_or_else(|e| panic!("{what}: {e}"));
            assert_eq!(cloud.count(), 7, "{what}");
            assert_eq!(cloud.has_colors(), has_color, "{what}");
            let mut points = Vec::new();
            while cloud.read(&mut points, 3).unwrap() > 0 {}
            assert_eq!(points.len(), 7, "{what}");
            for (i, p) in points.iter().enumerate() {
                let i = i as u16;
                let expected = [
                    f64::from(i) * 0.5,
                    1.0 - f64::from(i),
                    f64::from(i * i) * 0.01,
                ];
                for (a, want) in expected.iter().enumerate() {
                    // The las crate's default scale is 0.001.
                    assert!(
                        (p.position[a] - want).abs() <= 0.0005 + 1e-9,
                        "{what}: point {i} axis {a}: {:?}",
                        p.position
                    );
                }
                let rgba = if has_color {
                    let c = |v: u16| ((f64::from(v) / 257.0).round()) as u8;
                    [c(i * 9000), c(65535 - i * 9000), c(257 * i), 255]
                } else {
                    [255; 4]
                };
                assert_eq!(p.rgba, rgba, "{what}: point {i}");
            }
        }
    }
}

/// The part placement harness over the committed parts and their mutations,
/// and over placements edited with their checksums repaired (which random
/// mutations, stopped by a checksum, rarely reach).
#[test]
fn part_placement_harness_over_committed_and_edited_parts() {
    let seeds = committed("part_placement");
    let mut rng = Rng(45);
    let mut edited = Vec::new();
    for (_, bytes) in &seeds {
        let dag = dagfmt::Dag::open(bytes).unwrap();
        let s = *dag
            .sections()
            .iter()
            .find(|s| s.kind.to_raw() == dagtool::region::PART_PLACEMENT_KIND)
            .unwrap();
        for _ in 0..200 {
            let mut b = bytes.clone();
            let at = s.offset as usize + rng.below(48);
            b[at] = match rng.below(3) {
                0 => rng.next() as u8,
                1 => b[at] ^ (1 << rng.below(8)),
                _ => b[at].wrapping_add(1),
            };
            let crc = crc32c::crc32c(&b[s.offset as usize..s.offset as usize + 48]);
            let entry = s.entry_offset() as usize;
            b[entry + 32..entry + 36].copy_from_slice(&crc.to_le_bytes());
            let end = 128 + 40 * dag.sections().len();
            let header: [u8; 128] = b[..128].try_into().unwrap();
            let h = dagfmt::layout::header_checksum(&header, &b[128..end]);
            b[124..128].copy_from_slice(&h.to_le_bytes());
            edited.push(b);
        }
    }
    let runs = run(
        "part_placement",
        fuzzing::part_placement,
        edited,
        100 * scale(),
    );
    assert!(runs >= 60_000 / 100, "{runs} runs");
}
