//! The `dagtrace` command line: outputs, refusals and one-line errors.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use dagfmt::batch::{self, Ray};
use dagfmt::{AttributeKind, Dag};
use dagtrace::Tracer;
use dagtrace::render::BACKGROUND;

use crate::common::{Rng, build};
use crate::props::{random_ray, scene_voxels};

fn dagtrace(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dagtrace"))
        .args(args)
        .output()
        .expect("run dagtrace")
}

fn s(p: &Path) -> &str {
    p.to_str().expect("UTF-8 temp path")
}

/// A small scene written to `dir/scene.vdag`, with its voxels.
fn scene(dir: &Path) -> (PathBuf, Vec<[u32; 3]>) {
    let mut rng = Rng(42);
    let voxels = scene_voxels(5, 1, &mut rng);
    let path = dir.join("scene.vdag");
    std::fs::write(
        &path,
        build(5, AttributeKind::VoxelCount, &voxels, [1.0, -2.0, 0.5], 4.0),
    )
    .unwrap();
    (path, voxels)
}

/// Only the expected files in the folder: no temporary leftovers.
fn assert_files(dir: &Path, expected: &[&str]) {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    let mut expected: Vec<String> = expected.iter().map(|s| s.to_string()).collect();
    expected.sort();
    assert_eq!(names, expected);
}

fn assert_one_line_error(out: &Output, needle: &str) {
    assert_eq!(
        out.status.code(),
        Some(1),
        "stderr: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(stderr.lines().count(), 1, "one line: {stderr}");
    assert!(stderr.starts_with("dagtrace: error: "), "{stderr}");
    assert!(stderr.contains(needle), "`{needle}` not in {stderr}");
}

#[test]
fn render_writes_a_png_of_the_scene() {
    let dir = tempfile::tempdir().unwrap();
    let (vdag, _) = scene(dir.path());
    let png = dir.path().join("out.png");
    for shade in ["lit", "normal", "depth", "color"] {
        let out = dagtrace(&[
            "render",
            s(&vdag),
            "-o",
            s(&png),
            "--width",
            "96",
            "--height",
            "64",
            "--shade",
            shade,
            "--force",
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let image = image::open(&png).unwrap().to_rgb8();
        assert_eq!(image.dimensions(), (96, 64));
        // The automatic view frames the object: the centre is hit, a corner is not.
        assert_ne!(image.get_pixel(48, 32).0, BACKGROUND, "{shade}");
        assert_eq!(image.get_pixel(0, 0).0, BACKGROUND, "{shade}");
    }
    // An explicit camera looking away from the volume sees only background.
    let out = dagtrace(&[
        "render",
        s(&vdag),
        "-o",
        s(&png),
        "--width",
        "16",
        "--height",
        "16",
        "--camera-pos",
        "100,0,0",
        "--look-at",
        "200,0,0",
        "--force",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let image = image::open(&png).unwrap().to_rgb8();
    assert!(image.pixels().all(|p| p.0 == BACKGROUND));
    assert_files(dir.path(), &["scene.vdag", "out.png"]);
}

#[test]
fn lit_is_the_default_and_its_options_are_checked() {
    let dir = tempfile::tempdir().unwrap();
    let (vdag, _) = scene(dir.path());
    let render = |name: &str, extra: &[&str]| {
        let png = dir.path().join(name);
        let mut args = vec!["render", s(&vdag), "-o", s(&png)];
        args.extend_from_slice(&["--width", "48", "--height", "32"]);
        args.extend_from_slice(extra);
        (dagtrace(&args), png)
    };
    let (out, default) = render("default.png", &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (out, lit) = render("lit.png", &["--shade", "lit"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        std::fs::read(&default).unwrap(),
        std::fs::read(&lit).unwrap()
    );
    let (out, options) = render(
        "options.png",
        &[
            "--sun=-1,2,0.5",
            "--ao-rays",
            "4",
            "--ao-radius",
            "3",
            "--samples",
            "4",
        ],
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let image = image::open(&options).unwrap().to_rgb8();
    assert_ne!(image.get_pixel(24, 16).0, BACKGROUND);
    assert_eq!(image.get_pixel(0, 0).0, BACKGROUND);
    for (args, needle) in [
        (&["--samples", "0"][..], "samples per pixel"),
        (&["--ao-rays", "100000"][..], "ambient-occlusion rays"),
        (&["--ao-radius=-2"][..], "ambient-occlusion radius"),
        (&["--sun", "0,0,0"][..], "sun direction"),
        (
            &["--shade", "depth", "--ao-rays", "4"][..],
            "--ao-rays applies to --shade lit",
        ),
    ] {
        let (out, png) = render("bad.png", args);
        assert_one_line_error(&out, needle);
        assert!(!png.exists(), "{args:?}");
    }
}

#[test]
fn outputs_are_never_overwritten_without_force() {
    let dir = tempfile::tempdir().unwrap();
    let (vdag, _) = scene(dir.path());
    let png = dir.path().join("out.png");
    std::fs::write(&png, b"keep me").unwrap();
    let out = dagtrace(&[
        "render",
        s(&vdag),
        "-o",
        s(&png),
        "--width",
        "8",
        "--height",
        "8",
    ]);
    assert_one_line_error(&out, "already exists");
    assert_eq!(std::fs::read(&png).unwrap(), b"keep me");
    let rays = dir.path().join("rays.txt");
    std::fs::write(&rays, "vdag-rays 1\n0 0 0 1 0 0 0 inf\n").unwrap();
    let out = dagtrace(&["trace", s(&vdag), "--rays", s(&rays), "--out", s(&png)]);
    assert_one_line_error(&out, "already exists");
    assert_eq!(std::fs::read(&png).unwrap(), b"keep me");
    assert_files(dir.path(), &["scene.vdag", "out.png", "rays.txt"]);
}

#[test]
fn trace_writes_what_the_library_answers() {
    let dir = tempfile::tempdir().unwrap();
    let (vdag, voxels) = scene(dir.path());
    let mut rng = Rng(3);
    let rays: Vec<Ray> = (0..500)
        .map(|_| random_ray(5, &voxels, [1.0, -2.0, 0.5], 4.0, &mut rng))
        .collect();
    let bytes = std::fs::read(&vdag).unwrap();
    let dag = Dag::open(&bytes).unwrap();
    let expected = Tracer::new(&dag).unwrap().trace_batch(&rays).unwrap();
    assert!(expected.iter().any(|h| h.hit) && expected.iter().any(|h| !h.hit));
    let text_rays = dir.path().join("rays.txt");
    let mut buf = Vec::new();
    batch::write_rays_text(&mut buf, &rays).unwrap();
    std::fs::write(&text_rays, buf).unwrap();
    let binary_rays = dir.path().join("rays.bin");
    let mut buf = Vec::new();
    batch::write_rays_binary(&mut buf, &rays).unwrap();
    std::fs::write(&binary_rays, buf).unwrap();
    // Every input and output format, the output named by `-o`, `--output`
    // and the older `--out`, and the batch streamed in chunks of 1, 7 and
    // the default (one chunk): the same answers.
    for (rays_path, format, output, chunk) in [
        (&text_rays, "text", "--out", "1048576"),
        (&binary_rays, "binary", "-o", "1048576"),
        (&text_rays, "binary", "--output", "1048576"),
        (&text_rays, "text", "-o", "7"),
        (&binary_rays, "binary", "-o", "7"),
        (&text_rays, "binary", "-o", "1"),
        (&binary_rays, "text", "-o", "1"),
    ] {
        let hits_path = dir.path().join("hits.out");
        let out = dagtrace(&[
            "trace",
            s(&vdag),
            "--rays",
            s(rays_path),
            output,
            s(&hits_path),
            "--format",
            format,
            "--chunk-rays",
            chunk,
            "--force",
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let written = std::fs::read(&hits_path).unwrap();
        assert_eq!(written.starts_with(b"VHIT"), format == "binary");
        let hits = batch::parse_hits(&written).unwrap();
        assert_eq!(hits.len(), expected.len());
        for (got, want) in hits.iter().zip(&expected) {
            assert_eq!(got.hit, want.hit);
            if want.hit {
                assert_eq!(got, want);
            }
        }
    }
}

#[test]
fn bad_inputs_fail_with_one_line_and_no_output() {
    let dir = tempfile::tempdir().unwrap();
    let (vdag, _) = scene(dir.path());
    let hits = dir.path().join("hits.txt");
    let rays = dir.path().join("rays.txt");
    // A malformed ray batch names the line.
    std::fs::write(&rays, "vdag-rays 1\n0 0 0 1 0\n").unwrap();
    let out = dagtrace(&["trace", s(&vdag), "--rays", s(&rays), "--out", s(&hits)]);
    assert_one_line_error(&out, "line 2");
    // A level deeper than the file.
    std::fs::write(
        &rays,
        "vdag-rays 1\n0 0 0 1 0 0 0 inf 5\n0 0 0 1 0 0 0 inf 6\n",
    )
    .unwrap();
    let out = dagtrace(&["trace", s(&vdag), "--rays", s(&rays), "--out", s(&hits)]);
    assert_one_line_error(&out, "ray 2 asks for level 6");
    // A damaged file is caught by validation and names the rule.
    let mut bytes = std::fs::read(&vdag).unwrap();
    let last = bytes.len() - 3;
    bytes[last] ^= 0x10;
    let damaged = dir.path().join("damaged.vdag");
    std::fs::write(&damaged, &bytes).unwrap();
    std::fs::write(&rays, "vdag-rays 1\n0 0 0 1 0 0 0 inf\n").unwrap();
    let out = dagtrace(&["trace", s(&damaged), "--rays", s(&rays), "--out", s(&hits)]);
    assert_one_line_error(&out, "E0");
    let out = dagtrace(&["render", s(&damaged), "-o", s(&dir.path().join("x.png"))]);
    assert_one_line_error(&out, "invalid .vdag");
    // Not a .vdag at all.
    let out = dagtrace(&[
        "render",
        s(&rays),
        "-o",
        s(&dir.path().join("x.png")),
        "--no-validate",
    ]);
    assert_one_line_error(&out, "E001");
    // A missing input, and a level out of range.
    let out = dagtrace(&[
        "render",
        s(&dir.path().join("none.vdag")),
        "-o",
        s(&dir.path().join("x.png")),
    ]);
    assert_one_line_error(&out, "none.vdag");
    let out = dagtrace(&[
        "render",
        s(&vdag),
        "-o",
        s(&dir.path().join("x.png")),
        "--level",
        "9",
    ]);
    assert_one_line_error(&out, "--level 9");
    assert_files(dir.path(), &["scene.vdag", "rays.txt", "damaged.vdag"]);
}

/// A batch streams through `trace` in chunks: the process's peak memory
/// stays far below the batch (rays and hits of 2 M rays would need 152 MB in
/// memory; the input file alone is 80 MB), and the hits are all there.
#[test]
fn trace_streams_large_batches_in_bounded_memory() {
    let dir = tempfile::tempdir().unwrap();
    let (vdag, _) = scene(dir.path());
    let count = 2_000_000u64;
    // Rays through the scene's cube, from a few origins (cheap to trace:
    // the point is the streaming), written record by record.
    let rays_path = dir.path().join("rays.bin");
    {
        use std::io::Write as _;
        let mut w = std::io::BufWriter::new(std::fs::File::create(&rays_path).unwrap());
        batch::write_rays_binary(&mut w, &[]).unwrap();
        for i in 0..count {
            let ray = sample_ray(i);
            let mut record = Vec::with_capacity(40);
            batch::write_rays_binary(&mut record, &[ray]).unwrap();
            w.write_all(&record[batch::BINARY_HEADER_SIZE..]).unwrap();
        }
        w.flush().unwrap();
        let mut f = w.into_inner().unwrap();
        use std::io::{Seek, SeekFrom};
        f.seek(SeekFrom::Start(8)).unwrap();
        f.write_all(&count.to_le_bytes()).unwrap();
    }
    let hits_path = dir.path().join("hits.bin");
    let out = dagtrace(&[
        "trace",
        s(&vdag),
        "--rays",
        s(&rays_path),
        "-o",
        s(&hits_path),
        "--format",
        "binary",
        "--chunk-rays",
        "65536",
        "--stats",
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let peak: f64 = stderr
        .split("peak resident memory ")
        .nth(1)
        .and_then(|r| r.split(" MiB").next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no peak memory in: {stderr}"));
    assert!(
        peak < 60.0,
        "peak resident memory {peak} MiB for 2 M rays in chunks of 65536"
    );
    let hits = batch::parse_hits(&std::fs::read(&hits_path).unwrap()).unwrap();
    assert_eq!(hits.len() as u64, count);
    // The answers are the library's (checked on the first and last rays).
    let bytes = std::fs::read(&vdag).unwrap();
    let dag = Dag::open(&bytes).unwrap();
    let tracer = Tracer::new(&dag).unwrap();
    for i in (0..1000).chain(count - 1000..count) {
        assert_eq!(
            hits[i as usize],
            tracer.trace(&sample_ray(i)).unwrap(),
            "ray {i}"
        );
    }
}

/// Ray `i` of the large batch: from points around the scene's cube (root
/// corner (1, -2, 0.5), size 4) towards its middle.
fn sample_ray(i: u64) -> Ray {
    let origin = [-3.0 + (i % 11) as f32, -6.0 + (i / 11 % 13) as f32, -8.0];
    let target = [3.0, 0.0, 2.5];
    Ray::new(origin, [0, 1, 2].map(|k| target[k] - origin[k]))
}

/// A format 2.0 file (spec §23) through the command line: `trace` writes the
/// hits of its 1.0 file byte for byte on every conformance trace case tried,
/// and `render` the same picture (on the GPU, plain and lit, see
/// `gpu::command_line_gpu_backend_gives_the_cpu_answers`).
#[test]
fn format_2_files_trace_and_render_like_their_1_0_file() {
    let dir = tempfile::tempdir().unwrap();
    let cases = Path::new(env!("CARGO_MANIFEST_DIR")).join("../conformance/cases/trace");
    let mut traced = 0;
    let names = [
        "checker-d3",
        "checker2-d4",
        "corner-5-d3",
        "lod-blobs-d6",
        "mesh-sphere-d6",
        "mesh-torus-d6",
        "random-offset-root-d6",
        "random-sparse-d6",
        "saturated-full-d9",
    ];
    for name in names {
        let v1 = cases.join(format!("{name}.vdag"));
        let bytes = std::fs::read(&v1).unwrap();
        let v2 = dir.path().join(format!("{name}-2.vdag"));
        let upgraded = dagfmt::v2file::upgrade(&Dag::open(&bytes).unwrap()).unwrap();
        assert_eq!(u16::from_le_bytes([upgraded[8], upgraded[9]]), 2);
        std::fs::write(&v2, upgraded).unwrap();
        let rays = v1.with_extension("rays");
        let mut hits = Vec::new();
        for file in [&v1, &v2] {
            let out_path = dir.path().join(format!("{name}-{}.hits", hits.len()));
            let out = dagtrace(&[
                "trace",
                s(file),
                "--rays",
                s(&rays),
                "--out",
                s(&out_path),
                "--format",
                "binary",
                "--backend",
                "cpu",
            ]);
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
            hits.push(std::fs::read(&out_path).unwrap());
        }
        assert_eq!(hits[0], hits[1], "{name}: 2.0 hits differ from 1.0");
        traced += 1;
    }
    assert_eq!(traced, names.len());
    // A picture.
    let v1 = cases.join("checker2-d4.vdag");
    let v2 = dir.path().join("checker2-d4-2.vdag");
    let mut pictures = Vec::new();
    for file in [&v1, &v2] {
        let png = dir.path().join(format!("p{}.png", pictures.len()));
        let out = dagtrace(&[
            "render",
            s(file),
            "-o",
            s(&png),
            "--width",
            "64",
            "--height",
            "48",
            "--backend",
            "cpu",
        ]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        pictures.push(std::fs::read(&png).unwrap());
    }
    assert_eq!(pictures[0], pictures[1], "2.0 render differs from 1.0");
}
