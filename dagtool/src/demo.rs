//! `dagtool demo`: the whole pipeline on a built-in scene, for a first run.
//!
//! Makes a procedural mesh in code (a torus and a sphere on a thin floor plate),
//! converts it with the real converter, validates the file, renders it on the
//! GPU when an adapter exists (else on the CPU), writes a PNG, and runs the
//! conformance suite against the in-process tracers and validator.

use std::f64::consts::TAU;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use conformance::suite::{self, TraceBackend};
use dagfmt::Dag;
use dagfmt::mmap::MappedFile;
use dagtrace::camera::Camera;
use dagtrace::lit::LitOptions;

use crate::convert::{ConvertOptions, convert};

/// `println!` that tolerates a closed standard output (`dagtool demo | head`):
/// the demo's lines are progress for a person, so once nobody reads them they
/// are dropped instead of panicking.
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($arg)*);
    }};
}
use crate::error::ConvertError;
use crate::output::write_atomic;

/// Options of `dagtool demo`.
#[derive(Clone, Debug)]
pub struct DemoOptions {
    /// Directory the demo writes into (created when missing).
    pub out_dir: PathBuf,
    /// Depth of the conversion.
    pub depth: u8,
    /// Image size.
    pub width: u32,
    /// Image size.
    pub height: u32,
    /// Use the CPU tracer even when a GPU adapter exists.
    pub cpu_only: bool,
}

/// A marker file that says a directory belongs to the demo, so that running the
/// demo again may replace its files but never anybody else's.
const MARKER: &str = ".vdag-demo";

/// The built-in scene as OBJ text: a torus and a sphere resting on a plate.
pub fn scene_obj() -> String {
    let mut obj = String::from("# dagtool demo scene: torus, sphere and a thin plate\n");
    let mut base = 1u32;
    let mut add = |obj: &mut String, verts: &[[f64; 3]], tris: &[[u32; 3]]| {
        for v in verts {
            let _ = writeln!(obj, "v {:.6} {:.6} {:.6}", v[0], v[1], v[2]);
        }
        for t in tris {
            let _ = writeln!(obj, "f {} {} {}", t[0] + base, t[1] + base, t[2] + base);
        }
        base += verts.len() as u32;
    };
    // Torus around the y axis.
    let (n, m) = (96u32, 32u32);
    let mut verts = Vec::new();
    let mut tris = Vec::new();
    for i in 0..n {
        let u = TAU * f64::from(i) / f64::from(n);
        for j in 0..m {
            let v = TAU * f64::from(j) / f64::from(m);
            let r = 1.0 + 0.35 * v.cos();
            verts.push([-0.6 + r * u.cos(), 0.75 + 0.35 * v.sin(), r * u.sin()]);
            let (a, b) = (i * m + j, ((i + 1) % n) * m + j);
            let (c, d) = (i * m + (j + 1) % m, ((i + 1) % n) * m + (j + 1) % m);
            tris.push([a, b, d]);
            tris.push([a, d, c]);
        }
    }
    add(&mut obj, &verts, &tris);
    // UV sphere.
    let (n, m) = (64u32, 32u32);
    let (mut verts, mut tris) = (vec![[1.4, 1.55, 0.0]], Vec::new());
    for j in 1..m {
        let phi = std::f64::consts::PI * f64::from(j) / f64::from(m);
        for i in 0..n {
            let th = TAU * f64::from(i) / f64::from(n);
            verts.push([
                1.4 + 0.8 * phi.sin() * th.cos(),
                0.75 + 0.8 * phi.cos(),
                0.8 * phi.sin() * th.sin(),
            ]);
        }
    }
    verts.push([1.4, -0.05, 0.0]);
    let bottom = verts.len() as u32 - 1;
    let ring = |j: u32, i: u32| 1 + (j - 1) * n + i % n;
    for i in 0..n {
        tris.push([0, ring(1, i + 1), ring(1, i)]);
        tris.push([bottom, ring(m - 1, i), ring(m - 1, i + 1)]);
        for j in 1..m - 1 {
            tris.push([ring(j, i), ring(j, i + 1), ring(j + 1, i + 1)]);
            tris.push([ring(j, i), ring(j + 1, i + 1), ring(j + 1, i)]);
        }
    }
    add(&mut obj, &verts, &tris);
    // A plate: two triangles, thinner than a voxel (conservative voxelization keeps it whole).
    let plate = [
        [-2.6, -0.06, -2.0],
        [2.6, -0.06, -2.0],
        [2.6, -0.06, 2.0],
        [-2.6, -0.06, 2.0],
    ];
    add(&mut obj, &plate, &[[0, 2, 1], [0, 3, 2]]);
    obj
}

fn io(what: String) -> impl FnOnce(std::io::Error) -> ConvertError {
    move |e| ConvertError::io(what, e)
}

/// Runs the demo; returns whether the conformance suite passed.
pub fn run(opts: &DemoOptions) -> Result<bool, ConvertError> {
    let dir = &opts.out_dir;
    prepare_dir(dir)?;
    let mesh_path = dir.join("scene.obj");
    let dag_path = dir.join("scene.vdag");
    let png_path = dir.join("scene.png");
    let obj = scene_obj();
    write_atomic(&mesh_path, true, |w| {
        std::io::Write::write_all(w, obj.as_bytes())
    })?;
    say!(
        "1. mesh       {} (procedural torus, sphere and plate)",
        mesh_path.display()
    );

    let mut convert_opts = ConvertOptions::new(&mesh_path, &dag_path, Some(opts.depth));
    convert_opts.force = true;
    let started = Instant::now();
    let summary = convert(&convert_opts)?;
    say!(
        "2. convert    {} at depth {} ({}³): {} voxels, {} bytes, {:.2} s",
        dag_path.display(),
        opts.depth,
        1u64 << opts.depth,
        summary.voxels,
        summary.file_bytes,
        started.elapsed().as_secs_f64()
    );

    let map =
        MappedFile::open(&dag_path).map_err(io(format!("cannot map {}", dag_path.display())))?;
    let errors = dagfmt::validate::validate(map.bytes());
    if let Some(first) = errors.first() {
        return Err(ConvertError::Usage(format!(
            "the converted file is invalid: {first}"
        )));
    }
    say!("3. validate   valid ({} bytes checked)", map.bytes().len());

    let cannot_open = |e: &dyn std::fmt::Display| {
        ConvertError::Usage(format!("cannot open {}: {e}", dag_path.display()))
    };
    // The file is 2.0 (convert's default); the GPU's lit render reads 1.0,
    // so the image is rendered from its 1.0 form, made in memory: the same
    // voxels, the same pixels.
    let v1_form = match dagfmt::AnyDag::open(map.bytes()).map_err(|e| cannot_open(&e))? {
        dagfmt::AnyDag::V1(_) => None,
        dagfmt::AnyDag::V2(d) => Some(dagfmt::v2file::downgrade(&d).map_err(|e| cannot_open(&e))?),
    };
    let dag = Dag::open(v1_form.as_deref().unwrap_or(map.bytes())).map_err(|e| cannot_open(&e))?;
    let (w, h) = (opts.width, opts.height);
    let camera = Camera::automatic(&dag, f64::from(w) / f64::from(h));
    let started = Instant::now();
    let (rgb, backend) = render_image(&dag, &camera, w, h, opts.cpu_only)?;
    let elapsed = started.elapsed().as_secs_f64();
    let mut png = Vec::new();
    image::write_buffer_with_format(
        &mut std::io::Cursor::new(&mut png),
        &rgb,
        w,
        h,
        image::ExtendedColorType::Rgb8,
        image::ImageFormat::Png,
    )
    .map_err(|e| ConvertError::Usage(format!("cannot encode the PNG: {e}")))?;
    write_atomic(&png_path, true, |out| std::io::Write::write_all(out, &png))?;
    say!(
        "4. render     {} ({w}x{h}, {backend}, {elapsed:.2} s)",
        png_path.display()
    );

    say!("5. conformance suite (spec/CONFORMANCE.md):");
    let root = suite::default_cases_dir();
    let trace_cases = suite::trace_cases(&root, None).map_err(ConvertError::Usage)?;
    let mut outcomes: Vec<_> = trace_cases
        .iter()
        .map(|c| suite::run_trace_case(c, &suite::CpuTracer))
        .collect();
    if !opts.cpu_only {
        match suite::GpuTracer::new(None) {
            Ok(gpu) => {
                say!("   GPU tracer on {}", gpu.adapter_name());
                let gpu: &dyn TraceBackend = &gpu;
                outcomes.extend(trace_cases.iter().map(|c| {
                    let mut o = suite::run_trace_case(c, gpu);
                    o.name = format!("gpu/{}", o.name);
                    o
                }));
            }
            Err(e) => say!("   GPU tracer skipped: {e}"),
        }
    }
    let validate_cases = suite::validate_cases(&root, None).map_err(ConvertError::Usage)?;
    outcomes.extend(validate_cases.iter().map(|c| {
        suite::run_validate_case(c, &suite::InProcessValidator, suite::Strictness::Strict)
    }));
    Ok(suite::report(&outcomes, "rays and files"))
}

/// Renders the lit image (`dagtrace render --shade lit`'s defaults) on the
/// GPU when possible, else on the CPU. Returns RGB8 and a label.
fn render_image(
    dag: &Dag<'_>,
    camera: &Camera,
    w: u32,
    h: u32,
    cpu_only: bool,
) -> Result<(Vec<u8>, String), ConvertError> {
    let options = LitOptions::default();
    let tracer = dagtrace::Tracer::new(dag).map_err(|e| ConvertError::Usage(e.to_string()))?;
    if !cpu_only {
        match dagtrace::gpu::GpuTracer::new(dag, &dagtrace::gpu::GpuOptions::default()) {
            Ok(gpu) => {
                let rgb = gpu
                    .render_lit(camera, w, h, None, &options, |i| tracer.color(i))
                    .map_err(|e| ConvertError::Usage(format!("GPU render failed: {e}")))?;
                return Ok((rgb, format!("GPU: {}", gpu.context().adapter_name())));
            }
            Err(e) => say!("   (no GPU tracer: {e}; using the CPU)"),
        }
    }
    let frame = camera
        .frame()
        .map_err(|e| ConvertError::Usage(e.to_string()))?;
    let rgb = dagtrace::lit::render_lit(&tracer, &frame, w, h, None, &options)
        .map_err(|e| ConvertError::Usage(format!("CPU render failed: {e}")))?;
    Ok((
        rgb,
        format!("CPU, {} threads", rayon::current_num_threads()),
    ))
}

/// Creates `dir`, or accepts it when it is empty or was made by the demo.
fn prepare_dir(dir: &Path) -> Result<(), ConvertError> {
    if dir.exists() {
        let empty = dir
            .read_dir()
            .map_err(io(format!("cannot read {}", dir.display())))?
            .next()
            .is_none();
        if !empty && !dir.join(MARKER).exists() {
            return Err(ConvertError::Usage(format!(
                "{} exists and was not made by the demo; choose another -o/--output",
                dir.display()
            )));
        }
    } else {
        std::fs::create_dir_all(dir).map_err(io(format!("cannot create {}", dir.display())))?;
    }
    std::fs::write(
        dir.join(MARKER),
        "made by `dagtool demo`; its files may be replaced by the next run\n",
    )
    .map_err(io(format!("cannot write into {}", dir.display())))
}
