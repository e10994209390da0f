//! Packed colours (spec §12.6) in the tracers: `Tracer::color` decodes them,
//! `render --shade color` (and the lit shading) shows the same image from a
//! lossless packed file as from raw colours, within the bound from a lossy
//! one, and the GPU back end (colours decoded on the device from the
//! section it holds as stored, by the attribute index of each hit) agrees
//! with the CPU: the same colour for every hit, bit for bit, and images that
//! differ only where the two traversals break exact ties differently.

use std::path::Path;
use std::process::Command;

use dagfmt::{AttributeKind, Dag, DagBuilder};
use dagtrace::Tracer;
use dagtrace::camera::Camera;
use dagtrace::render::{Shade, render};

/// A ball of depth 6, and one colour per voxel: smooth bands with noise.
fn ball() -> (dagfmt::builder::BuiltDag, Vec<[u8; 4]>) {
    let dag = DagBuilder::from_fn(6, AttributeKind::VoxelCount, |x, y, z| {
        let d = |c: u32| (f64::from(c) - 31.5).powi(2);
        let r = d(x) + d(y) + d(z);
        (400.0..900.0).contains(&r)
    })
    .expect("ball");
    let colors = (0..dag.voxel_count())
        .map(|i| {
            let band = (i / 50) as u8;
            [
                band.wrapping_mul(29),
                255 - band,
                (i * 7 % 23) as u8 * 11,
                255,
            ]
        })
        .collect();
    (dag, colors)
}

fn files() -> (Vec<u8>, Vec<u8>, Vec<u8>, Vec<[u8; 4]>) {
    let (mut dag, colors) = ball();
    dag.set_colors(colors.clone()).unwrap();
    let raw = dag.to_bytes();
    dag.set_packed_colors(&colors, 0).unwrap();
    let lossless = dag.to_bytes();
    dag.set_packed_colors(&colors, 8).unwrap();
    let lossy = dag.to_bytes();
    (raw, lossless, lossy, colors)
}

fn color_image(bytes: &[u8]) -> Vec<u8> {
    let dag = Dag::open(bytes).unwrap();
    let tracer = Tracer::new(&dag).unwrap();
    let frame = Camera::automatic(&dag, 4.0 / 3.0).frame().unwrap();
    render(&tracer, &frame, 80, 60, Shade::Color, None).unwrap()
}

#[test]
fn tracer_lookups_return_decoded_colours() {
    let (raw, lossless, lossy, colors) = files();
    for (bytes, bound) in [(&raw, 0u8), (&lossless, 0), (&lossy, 8)] {
        let dag = Dag::open(bytes).unwrap();
        let tracer = Tracer::new(&dag).unwrap();
        assert!(tracer.colors().is_some());
        for (i, want) in colors.iter().enumerate() {
            let got = tracer.color(i as u64).unwrap();
            for c in 0..4 {
                assert!(
                    want[c].abs_diff(got[c]) <= bound,
                    "voxel {i}: {want:?} -> {got:?}"
                );
            }
        }
        assert_eq!(tracer.color(colors.len() as u64), None);
    }
}

#[test]
fn color_renders_match_raw_colours() {
    let (raw, lossless, lossy, _) = files();
    let reference = color_image(&raw);
    assert_eq!(color_image(&lossless), reference);
    let lossy_image = color_image(&lossy);
    assert_eq!(lossy_image.len(), reference.len());
    // Shading scales a colour by at most 1, and rounds once.
    let worst = reference
        .iter()
        .zip(&lossy_image)
        .map(|(a, b)| a.abs_diff(*b))
        .max()
        .unwrap();
    assert!(worst <= 9, "a pixel differs by {worst}");
    assert_ne!(reference.iter().filter(|&&v| v != 0).count(), 0);
}

fn dagtrace(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_dagtrace"))
        .args(args)
        .output()
        .expect("run dagtrace")
}

fn png(dir: &Path, file: &Path, name: &str, shade: &str, backend: &str) -> Option<Vec<u8>> {
    let out_path = dir.join(name);
    let out = dagtrace(&[
        "render",
        file.to_str().unwrap(),
        "-o",
        out_path.to_str().unwrap(),
        "--width",
        "64",
        "--height",
        "48",
        "--shade",
        shade,
        "--backend",
        backend,
        "--force",
    ]);
    if !out.status.success() {
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(backend == "gpu", "{stderr}");
        if std::env::var("VDAG_REQUIRE_GPU").is_ok_and(|v| v == "1") {
            panic!("VDAG_REQUIRE_GPU=1 but the GPU render failed: {stderr}");
        }
        println!("skipped: no GPU render ({stderr})");
        return None;
    }
    Some(image::open(&out_path).unwrap().to_rgb8().into_raw())
}

#[test]
fn cpu_and_gpu_render_packed_colours_alike() {
    let dir = tempfile::tempdir().unwrap();
    let (raw, lossless, lossy, _) = files();
    let raw_path = dir.path().join("raw.vdag");
    let packed_path = dir.path().join("packed.vdag");
    let lossy_path = dir.path().join("lossy.vdag");
    std::fs::write(&raw_path, &raw).unwrap();
    std::fs::write(&packed_path, &lossless).unwrap();
    std::fs::write(&lossy_path, &lossy).unwrap();
    for shade in ["color", "lit"] {
        let cpu_raw = png(dir.path(), &raw_path, "a.png", shade, "cpu").unwrap();
        let cpu = png(dir.path(), &packed_path, "b.png", shade, "cpu").unwrap();
        assert!(cpu == cpu_raw, "{shade}: CPU, packed against raw");
        let Some(gpu_raw) = png(dir.path(), &raw_path, "d.png", shade, "gpu") else {
            return;
        };
        let gpu = png(dir.path(), &packed_path, "c.png", shade, "gpu").unwrap();
        assert!(gpu == gpu_raw, "{shade}: GPU, packed against raw");
        let cpu_lossy = png(dir.path(), &lossy_path, "e.png", shade, "cpu").unwrap();
        let gpu_lossy = png(dir.path(), &lossy_path, "f.png", shade, "gpu").unwrap();
        // The same camera rays on both back ends: the same pixels but where
        // the traversals break an exact tie differently (at most 2 %).
        for (what, cpu, gpu) in [
            ("raw", &cpu_raw, &gpu_raw),
            ("E = 0", &cpu, &gpu),
            ("E = 8", &cpu_lossy, &gpu_lossy),
        ] {
            let differ = cpu
                .chunks_exact(3)
                .zip(gpu.chunks_exact(3))
                .filter(|(a, b)| a != b)
                .count();
            assert!(
                differ * 50 <= 64 * 48,
                "{shade}, {what}: {differ} of 3072 pixels differ"
            );
        }
    }
}

/// The device's colours for the GPU's own hits are the CPU decoder's, bit
/// for bit, for raw, lossless and lossy files; so the images the two back
/// ends shade from the same hits are identical (`--shade color` and lit).
#[cfg(feature = "gpu")]
#[test]
fn gpu_decoded_colours_are_the_cpu_decoders() {
    use dagtrace::gpu::{GpuError, GpuOptions, GpuTracer};
    use dagtrace::lit::LitOptions;
    use dagtrace::render::{shade_hits, shade_hits_colored};
    let (raw, lossless, lossy, _) = files();
    for (name, bytes) in [("raw", &raw), ("E = 0", &lossless), ("E = 8", &lossy)] {
        let dag = Dag::open(bytes).unwrap();
        let tracer = Tracer::new(&dag).unwrap();
        let options = GpuOptions {
            colors: true,
            ..GpuOptions::default()
        };
        let gpu = match GpuTracer::new(&dag, &options) {
            Ok(gpu) => gpu,
            Err(GpuError::NoAdapter) => {
                if std::env::var("VDAG_REQUIRE_GPU").is_ok_and(|v| v == "1") {
                    panic!("VDAG_REQUIRE_GPU=1 but no GPU adapter");
                }
                println!("skipped: no GPU adapter");
                return;
            }
            Err(e) => panic!("{name}: {e}"),
        };
        assert!(gpu.has_colors(), "{name}");
        assert_eq!(gpu.color_bytes() as usize, {
            let table = dag.color_table().unwrap();
            match table {
                dagfmt::ColorTable::Raw(b) => b.len(),
                dagfmt::ColorTable::Packed(p) => p.bytes().len(),
            }
        });
        let camera = Camera::automatic(&dag, 4.0 / 3.0);
        let rays = camera.frame().unwrap().rays(80, 60, None);
        let hits = gpu.trace(&rays).unwrap();
        let colors = gpu.hit_colors(&hits).unwrap();
        let mut found = 0;
        for (hit, color) in hits.iter().zip(&colors) {
            let want = hit.index.filter(|_| hit.hit).and_then(|i| tracer.color(i));
            assert_eq!(*color, want, "{name}: {hit:?}");
            found += usize::from(color.is_some());
        }
        assert!(found > 500, "{name}: {found} coloured hits");
        // Every index, and some past the end.
        let n = dag.header().voxel_count;
        let all: Vec<u64> = (0..n + 5).chain([1 << 32, u64::MAX]).collect();
        let decoded = gpu.colors_of(&all).unwrap();
        for (&i, got) in all.iter().zip(&decoded) {
            assert_eq!(*got, tracer.color(i), "{name}: colour {i}");
        }
        assert_eq!(
            shade_hits_colored(&hits, Shade::Color, &colors),
            shade_hits(&hits, Shade::Color, tracer.colors()),
            "{name}"
        );
        let lit = LitOptions {
            samples: 2,
            ..LitOptions::default()
        };
        let on_device = gpu.render_lit_colored(&camera, 40, 30, None, &lit).unwrap();
        let on_host = gpu
            .render_lit(&camera, 40, 30, None, &lit, |i| tracer.color(i))
            .unwrap();
        assert_eq!(on_device, on_host, "{name}: lit");
    }
}
