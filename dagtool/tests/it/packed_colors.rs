//! Packed colours (spec §12.6) in the tools: the converter's colour sink packs
//! the same bytes in memory and through a temporary file, `convert
//! --color-error` and `recompress` write the same file, every colour stays
//! within the bound (on generated points and on the shared test data), the
//! geometry is copied unchanged, and bad requests fail cleanly.

use std::path::Path;

use dagfmt::AnyDag;
use dagfmt::packed_colors::{PackedColors, encode};
use dagtool::external::{ColourSink, Scratch};

use crate::common::{run, run_ok};

/// Deterministic colours with runs and noise, some translucent.
fn sample_colors(n: usize) -> Vec<[u8; 4]> {
    let mut x = 0x2545_f491_4f6c_dd1du64;
    (0..n)
        .map(|i| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let run = (i / 37) as u8;
            [
                run.wrapping_mul(13),
                run.wrapping_add((x & 7) as u8),
                (x >> 8) as u8,
                if i % 1000 < 5 { 128 } else { 255 },
            ]
        })
        .collect()
}

fn sink_bytes(colors: &[[u8; 4]], cap: u64, bound: u8, tmp: &Path) -> (Vec<u8>, bool, u32) {
    let scratch = Scratch::new(tmp).unwrap();
    let mut sink = ColourSink::new(&scratch, cap, Some(bound));
    for part in colors.chunks(1000) {
        sink.write(part.as_flattened()).unwrap();
    }
    let colours = sink.finish().unwrap();
    let mut bytes = Vec::new();
    colours
        .emit(&mut |b| {
            bytes.extend_from_slice(b);
            Ok(())
        })
        .unwrap();
    let section = colours.section();
    assert_eq!(section.length, bytes.len() as u64);
    assert_eq!(section.item_count, colors.len() as u64);
    (bytes, colours.spilled(), section.crc)
}

#[test]
fn the_sink_packs_the_same_bytes_in_memory_and_spilled() {
    let dir = tempfile::tempdir().unwrap();
    let colors = sample_colors(70_000);
    for bound in [0u8, 8] {
        let (expected, _) = encode(&colors, bound).unwrap();
        let (in_memory, spilled, crc) = sink_bytes(&colors, 1 << 30, bound, dir.path());
        assert!(!spilled);
        assert_eq!(in_memory, expected);
        assert_eq!(crc, crc32c::crc32c(&expected));
        let (on_disk, spilled, _) = sink_bytes(&colors, 0, bound, dir.path());
        assert!(spilled);
        assert_eq!(on_disk, expected);
    }
}

/// An ASCII PLY point cloud of `n` coloured points in the unit cube.
fn write_cloud(path: &Path, n: usize) {
    let colors = sample_colors(n);
    let mut text = format!(
        "ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    );
    for (i, c) in colors.iter().enumerate() {
        let t = i as f64 / n as f64;
        let (x, y, z) = (t, (t * 37.0).fract(), (t * 1013.0).fract());
        text.push_str(&format!("{x} {y} {z} {} {} {}\n", c[0], c[1], c[2]));
    }
    std::fs::write(path, text).unwrap();
}

fn decoded(bytes: &[u8]) -> Vec<[u8; 4]> {
    AnyDag::open(bytes)
        .unwrap()
        .color_table()
        .unwrap()
        .iter()
        .collect()
}

/// A file's level sections (their bytes), whether it has raw colours, and
/// its packed colours, for either format version.
fn geometry_and_colours(bytes: &[u8]) -> (Vec<&[u8]>, bool, Option<PackedColors<'_>>) {
    match AnyDag::open(bytes).unwrap() {
        AnyDag::V1(d) => (
            d.levels().iter().map(|l| l.bytes).collect(),
            d.colors().is_some(),
            d.packed_colors(),
        ),
        AnyDag::V2(d) => (
            d.levels().iter().map(|l| l.bytes).collect(),
            d.colors().is_some(),
            d.packed_colors(),
        ),
    }
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn recompress_and_convert_agree_and_keep_the_bound() {
    // In both format versions: recompress keeps the file's version.
    for version in ["1", "2"] {
        recompress_and_convert_agree(version);
    }
}

fn recompress_and_convert_agree(version: &str) {
    let dir = tempfile::tempdir().unwrap();
    let cloud = dir.path().join("cloud.ply");
    write_cloud(&cloud, 5000);
    let raw = dir.path().join("raw.vdag");
    run_ok(&[
        "convert",
        s(&cloud),
        "-o",
        s(&raw),
        "-d",
        "7",
        "--colors",
        "-q",
        "--format-version",
        version,
    ]);
    let raw_bytes = std::fs::read(&raw).unwrap();
    let source = decoded(&raw_bytes);
    let (raw_levels, raw_colours, _) = geometry_and_colours(&raw_bytes);
    assert!(raw_colours);
    for bound in [0u8, 3, 8] {
        let e = bound.to_string();
        let packed = dir.path().join(format!("packed{bound}.vdag"));
        let out = run_ok(&["recompress", s(&raw), "-o", s(&packed), "--color-error", &e]);
        assert!(String::from_utf8_lossy(&out.stdout).contains("bits per voxel"));
        let bytes = std::fs::read(&packed).unwrap();
        assert!(dagfmt::validate::validate(&bytes).is_empty());
        assert_eq!(
            AnyDag::open(&bytes).unwrap().version_major().to_string(),
            version
        );
        let (levels, raw_colours, p) = geometry_and_colours(&bytes);
        assert!(!raw_colours);
        let p = p.expect("packed colours");
        assert_eq!(p.trailer().error_bound, bound);
        // The geometry is the same bytes.
        assert_eq!(levels, raw_levels);
        let colors = decoded(&bytes);
        assert_eq!(colors.len(), source.len());
        let mut max = 0;
        for (a, b) in source.iter().zip(&colors) {
            for c in 0..4 {
                max = max.max(a[c].abs_diff(b[c]));
            }
        }
        assert!(max <= bound, "max error {max} over bound {bound}");
        assert_eq!(max, p.trailer().max_error);
        if bound == 0 {
            assert_eq!(colors, source);
        }
        // The converter packs on the way out: the same file.
        let converted = dir.path().join(format!("converted{bound}.vdag"));
        run_ok(&[
            "convert",
            s(&cloud),
            "-o",
            s(&converted),
            "-d",
            "7",
            "--colors",
            "--color-error",
            &e,
            "-q",
            "--format-version",
            version,
        ]);
        assert!(
            std::fs::read(&converted).unwrap() == bytes,
            "bound {bound}, format {version}"
        );
        // info reports the size, the bound and the measured error.
        let info = run_ok(&["info", s(&packed)]);
        let text = String::from_utf8_lossy(&info.stdout);
        assert!(
            text.contains(&format!("error bound {bound}, measured max error {max}")),
            "{text}"
        );
    }
}

#[test]
fn recompress_refuses_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let cloud = dir.path().join("cloud.ply");
    write_cloud(&cloud, 500);
    let raw = dir.path().join("raw.vdag");
    let plain = dir.path().join("plain.vdag");
    run_ok(&[
        "convert",
        s(&cloud),
        "-o",
        s(&raw),
        "-d",
        "5",
        "--colors",
        "-q",
    ]);
    run_ok(&["convert", s(&cloud), "-o", s(&plain), "-d", "5", "-q"]);
    // No colours: an error, no output.
    let out_path = dir.path().join("out.vdag");
    let out = run(&["recompress", s(&plain), "-o", s(&out_path)]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no colours"));
    assert!(!out_path.exists());
    // An existing output is kept without --force.
    std::fs::write(&out_path, b"keep").unwrap();
    let out = run(&[
        "recompress",
        s(&raw),
        "-o",
        s(&out_path),
        "--color-error",
        "2",
    ]);
    assert!(!out.status.success());
    assert_eq!(std::fs::read(&out_path).unwrap(), b"keep");
    run_ok(&[
        "recompress",
        s(&raw),
        "-o",
        s(&out_path),
        "--color-error",
        "2",
        "--force",
    ]);
    // A bound over 127, and --color-error without --colors, are usage errors.
    let out = run(&[
        "recompress",
        s(&raw),
        "-o",
        s(&out_path),
        "--color-error",
        "128",
        "--force",
    ]);
    assert!(!out.status.success());
    let out = run(&[
        "convert",
        s(&cloud),
        "-o",
        s(&dir.path().join("x.vdag")),
        "-d",
        "5",
        "--color-error",
        "2",
    ]);
    assert!(!out.status.success());
    assert!(!dir.path().join("x.vdag").exists());
}

/// The shared photographic test data: every colour within the bound, random
/// access equal to sequential decoding (skipped when ../shared/formats is absent).
#[test]
fn shared_test_data_stays_within_the_bound() {
    let formats = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/formats");
    if !formats.is_dir() {
        eprintln!(
            "skipping: shared formats not found at {} (this test needs ../shared/formats)",
            formats.display()
        );
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    for (name, depth) in [("spot_textured.obj", "8"), ("dragon_points.ply", "8")] {
        let raw = dir.path().join(format!("{name}.vdag"));
        run_ok(&[
            "convert",
            s(&formats.join(name)),
            "-o",
            s(&raw),
            "-d",
            depth,
            "--colors",
            "-q",
        ]);
        let bytes = std::fs::read(&raw).unwrap();
        let source = decoded(&bytes);
        for bound in [0u8, 8] {
            let (section, summary) = encode(&source, bound).unwrap();
            let packed = PackedColors::new(&section, source.len() as u64).unwrap();
            assert!(dagfmt::packed_colors::check_section(&section, source.len() as u64).is_empty());
            for (i, (a, b)) in source.iter().zip(packed.iter()).enumerate() {
                assert_eq!(packed.get(i as u64), Some(b));
                for c in 0..4 {
                    assert!(
                        a[c].abs_diff(b[c]) <= bound,
                        "{name} colour {i}: {a:?} -> {b:?}"
                    );
                }
            }
            assert!(summary.trailer.max_error <= bound);
            // Smaller than raw 24-bit RGB.
            assert!(section.len() < source.len() * 3, "{name} E {bound}");
        }
    }
}
