//! `dagtrace`: render `.vdag` files to PNG and trace ray batches.
//!
//! Errors are one line on stderr with exit status 1 (2 for usage errors);
//! outputs are written to a temporary file in the same folder and renamed into
//! place, so a failed run leaves no partial file, and an existing file is only
//! replaced with `--force`.

use std::fs::File;
use std::io::{BufReader, BufWriter};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand, ValueEnum};
use dagfmt::Dag;
use dagfmt::batch::RayReader;
use dagfmt::mmap::MappedFile;
use dagfmt::output::OutputError;
use dagtrace::Tracer;
use dagtrace::camera::Camera;
use dagtrace::lit::{LitOptions, render_lit};
use dagtrace::render::{Shade, render};

#[derive(Parser, Debug)]
#[command(
    name = "dagtrace",
    version,
    about = "Ray trace .vdag sparse voxel DAGs on the CPU or the GPU"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Render a view of a .vdag (or .vdag.zst) file to a PNG image.
    Render(RenderArgs),
    /// Trace a batch of rays (text or binary, see spec/VDAG.md) and write the hits.
    Trace(TraceArgs),
}

/// Which tracer does the work.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum BackendArg {
    /// The CPU reference tracer, on all cores.
    Cpu,
    /// The wgpu compute-shader tracer (an error when there is no adapter).
    Gpu,
    /// The GPU when an adapter exists (a software one included), else the CPU.
    Auto,
}

#[derive(Args, Debug)]
struct BackendArgs {
    /// The tracer to use.
    #[arg(long, value_enum, default_value_t = BackendArg::Cpu)]
    backend: BackendArg,
    /// GPU only: use a short traversal stack of this many entries (a power of
    /// two, 1 to 16) that restarts from the root when it runs out, instead of
    /// one entry per level. Answers are identical.
    #[arg(long, value_name = "ENTRIES")]
    short_stack: Option<u32>,
}

#[derive(Args, Debug)]
struct OpenArgs {
    /// Skip the full validation of the file (the tracer stays memory-safe on
    /// any bytes, but answers for a damaged file are meaningless).
    #[arg(long)]
    no_validate: bool,
    /// Replace an existing output file.
    #[arg(long)]
    force: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum ShadeArg {
    /// Sunlight with hard shadows, ambient occlusion and smooth normals,
    /// in the file's colours when it has them.
    Lit,
    /// Colour by entry face.
    Normal,
    /// Grey level by distance.
    Depth,
    /// The file's voxel colours (VOXEL_COLORS), grey without them.
    Color,
}

#[derive(Args, Debug)]
struct RenderArgs {
    /// The .vdag (or .vdag.zst) file.
    file: PathBuf,
    /// The PNG image to write.
    #[arg(short, long)]
    output: PathBuf,
    /// Image width in pixels.
    #[arg(long, default_value_t = 1280, value_parser = clap::value_parser!(u32).range(1..=16384))]
    width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 720, value_parser = clap::value_parser!(u32).range(1..=16384))]
    height: u32,
    /// Camera position `x,y,z` (world space). Without it the view frames the
    /// occupied part of the volume automatically.
    #[arg(long, value_parser = parse_point, requires = "look_at", allow_hyphen_values = true)]
    camera_pos: Option<[f64; 3]>,
    /// Point the camera looks at, `x,y,z` (world space).
    #[arg(long, value_parser = parse_point, requires = "camera_pos", allow_hyphen_values = true)]
    look_at: Option<[f64; 3]>,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = 40.0)]
    fov: f64,
    /// How hit pixels are coloured.
    #[arg(long, value_enum, default_value_t = ShadeArg::Lit)]
    shade: ShadeArg,
    /// Lit: direction towards the sun, `x,y,z` (world space) [default: -0.35,1,0.45].
    #[arg(long, value_parser = parse_point, allow_hyphen_values = true)]
    sun: Option<[f64; 3]>,
    /// Lit: ambient-occlusion rays per sample (0 turns ambient occlusion off) [default: 8].
    #[arg(long, value_name = "N")]
    ao_rays: Option<u32>,
    /// Lit: length of the ambient-occlusion rays in voxels (cells of the
    /// traced level) [default: the grid's edge / 32].
    #[arg(long, value_name = "VOXELS")]
    ao_radius: Option<f64>,
    /// Lit: rays per pixel, spread over the pixel and averaged (anti-aliasing) [default: 1].
    #[arg(long, value_name = "N")]
    samples: Option<u32>,
    /// Level of detail: trace the cells of this level (1..=depth) instead of voxels.
    #[arg(long)]
    level: Option<u8>,
    #[command(flatten)]
    backend: BackendArgs,
    #[command(flatten)]
    open: OpenArgs,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum HitFormat {
    /// `vdag-hits 1` text.
    Text,
    /// `VHIT` binary records.
    Binary,
}

#[derive(Args, Debug)]
struct TraceArgs {
    /// The .vdag (or .vdag.zst) file.
    file: PathBuf,
    /// The ray batch (text `vdag-rays 1` or binary `VRAY`, detected).
    #[arg(long)]
    rays: PathBuf,
    /// The hit batch to write (`--out` is an older spelling that still works).
    #[arg(short, long, alias = "out")]
    output: PathBuf,
    /// Format of the hit batch.
    #[arg(long, value_enum, default_value_t = HitFormat::Text)]
    format: HitFormat,
    /// Rays read, traced and written at a time: memory is bounded by this,
    /// not by the batch.
    #[arg(long, default_value_t = 1 << 20, value_name = "RAYS", value_parser = clap::value_parser!(u32).range(1..=(1 << 26)))]
    chunk_rays: u32,
    /// Print the rays traced, the time and the peak resident memory on stderr.
    #[arg(long)]
    stats: bool,
    #[command(flatten)]
    backend: BackendArgs,
    #[command(flatten)]
    open: OpenArgs,
}

fn parse_point(s: &str) -> Result<[f64; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [x, y, z] = parts.as_slice() else {
        return Err(format!(
            "expected three comma-separated numbers x,y,z, got `{s}`"
        ));
    };
    let parse = |v: &str| match v.parse::<f64>() {
        Ok(f) if f.is_finite() => Ok(f),
        _ => Err(format!("`{v}` is not a finite number")),
    };
    Ok([parse(x)?, parse(y)?, parse(z)?])
}

/// A one-line error for the user.
struct Failure(String);

impl<E: std::fmt::Display> From<E> for Failure {
    fn from(e: E) -> Self {
        Failure(e.to_string())
    }
}

fn fail<T>(message: impl Into<String>) -> Result<T, Failure> {
    Err(Failure(message.into()))
}

/// The bytes of a `.vdag` file: a memory map, or the unpacked transport form.
enum Source {
    Mapped(MappedFile),
    Unpacked(Vec<u8>),
}

impl Source {
    fn bytes(&self) -> &[u8] {
        match self {
            Source::Mapped(m) => m.bytes(),
            Source::Unpacked(v) => v,
        }
    }
}

/// Maps (or unpacks) and, unless told not to, validates the file.
fn open_source(path: &Path, validate: bool) -> Result<Source, Failure> {
    let map = MappedFile::open(path).map_err(|e| Failure(format!("{}: {e}", path.display())))?;
    let source = if dagfmt::transport::is_transport(map.bytes()) {
        let bytes = dagfmt::transport::unpack(map.bytes(), dagfmt::transport::DEFAULT_MAX_SIZE)
            .map_err(|e| Failure(format!("{}: {e}", path.display())))?;
        Source::Unpacked(bytes)
    } else {
        Source::Mapped(map)
    };
    if validate {
        let errors = dagfmt::validate::validate(source.bytes());
        if let Some(first) = errors.first() {
            let more = match errors.len() {
                1 => String::new(),
                n => format!(
                    " (and {} more problems; `dagtool validate` lists them)",
                    n - 1
                ),
            };
            return fail(format!("{}: invalid .vdag: {first}{more}", path.display()));
        }
    }
    Ok(source)
}

/// Words an output failure for `path` in dagtrace's style.
fn output_failure(path: &Path, error: OutputError) -> Failure {
    Failure(match error {
        OutputError::MissingDirectory(dir) => format!(
            "{}: the output folder {} does not exist",
            path.display(),
            dir.display()
        ),
        OutputError::IsDirectory => format!("{}: the output is a folder", path.display()),
        OutputError::Exists => format!(
            "{} already exists (use --force to replace it)",
            path.display()
        ),
        OutputError::NoFileName => format!("{}: the output names no file", path.display()),
        OutputError::CreateTemp(dir, e) => {
            format!("{}: cannot create a file there: {e}", dir.display())
        }
        OutputError::Write(e) | OutputError::Sync(e) | OutputError::Rename(e) => {
            format!("{}: {e}", path.display())
        }
    })
}

/// Refuses an output in a missing folder, an output that is a folder, and
/// replacing `path` without `--force`; checked before any work is done.
fn check_output(path: &Path, force: bool) -> Result<(), Failure> {
    dagfmt::output::check_output(path, force).map_err(|e| output_failure(path, e))
}

/// Writes `path` through a temporary file in the same folder, renamed into
/// place only when `write` succeeds.
fn write_atomically(
    path: &Path,
    force: bool,
    write: impl FnOnce(&mut BufWriter<&mut File>) -> std::io::Result<()>,
) -> Result<(), Failure> {
    dagfmt::output::write_atomic(path, force, write)
        .map(drop)
        .map_err(|e| output_failure(path, e))
}

/// A tracer that runs on some back end.
#[cfg(feature = "gpu")]
type GpuBackend = dagtrace::gpu::GpuTracer;

/// Without the `gpu` feature there is no GPU back end.
#[cfg(not(feature = "gpu"))]
enum GpuBackend {}

/// The GPU tracer when the back end asks for one (and one can be made), or
/// `None` for the CPU. Says on stderr which adapter traces, or why `auto`
/// fell back to the CPU.
///
/// With `colors`, the file's colour section goes to the device as it is
/// stored (compressed, for PACKED_COLORS), and colours are decoded there; a
/// section the device cannot hold is refused in one line (`--backend gpu`)
/// or sends `auto` to the CPU.
fn pick_gpu(
    dag: &Opened<'_>,
    backend: &BackendArgs,
    compute_index: bool,
    colors: bool,
) -> Result<Option<GpuBackend>, Failure> {
    if backend.backend == BackendArg::Cpu {
        if backend.short_stack.is_some() {
            return fail("--short-stack applies to the GPU tracer only (use --backend gpu)");
        }
        return Ok(None);
    }
    #[cfg(feature = "gpu")]
    {
        use dagtrace::gpu::{GpuOptions, GpuTracer, StackMode};
        let options = GpuOptions {
            stack: backend
                .short_stack
                .map_or(StackMode::Full, StackMode::Short),
            compute_index,
            colors,
            ..GpuOptions::default()
        };
        let made = match dag {
            Opened::V1(d) => GpuTracer::new(d, &options),
            Opened::V2(d) => GpuTracer::new_v2(d.header(), d.levels(), d.color_table(), &options),
        };
        match made {
            Ok(gpu) => {
                eprintln!(
                    "dagtrace: tracing on the GPU: {}",
                    gpu.context().adapter_name()
                );
                Ok(Some(gpu))
            }
            Err(e) if backend.backend == BackendArg::Auto => {
                eprintln!("dagtrace: no GPU tracer ({e}); tracing on the CPU");
                Ok(None)
            }
            Err(e) => fail(format!("--backend gpu: {e}")),
        }
    }
    #[cfg(not(feature = "gpu"))]
    {
        let _ = (dag, compute_index, colors);
        if backend.backend == BackendArg::Auto {
            return Ok(None);
        }
        fail("--backend gpu: this dagtrace was built without the `gpu` feature")
    }
}

/// The file's DAG, either format version (spec §4.2): a 1.x file as a
/// [`Dag`], a 2.0 file's levels (spec §23), for every back end and
/// shading.
enum Opened<'a> {
    V1(Dag<'a>),
    V2(dagfmt::Dag2<'a>),
}

impl<'a> Opened<'a> {
    fn open(bytes: &'a [u8], path: &Path) -> Result<Self, Failure> {
        match dagfmt::AnyDag::open(bytes) {
            Ok(dagfmt::AnyDag::V1(dag)) => Ok(Opened::V1(dag)),
            Ok(dagfmt::AnyDag::V2(dag)) => Ok(Opened::V2(dag)),
            Err(e) => Err(Failure(format!("{}: {e}", path.display()))),
        }
    }

    fn depth(&self) -> u8 {
        match self {
            Opened::V1(d) => d.header().depth,
            Opened::V2(d) => d.header().depth,
        }
    }

    fn tracer(&self, path: &Path) -> Result<Tracer<'a>, Failure> {
        match self {
            Opened::V1(d) => Tracer::new(d),
            Opened::V2(d) => Tracer::from_v2(d),
        }
        .map_err(|e| Failure(format!("{}: {e}", path.display())))
    }

    /// The GPU tracer, if the back end asks for one (either format version).
    fn gpu(
        &self,
        backend: &BackendArgs,
        compute_index: bool,
        colors: bool,
    ) -> Result<Option<GpuBackend>, Failure> {
        pick_gpu(self, backend, compute_index, colors)
    }
}

fn render_cmd(args: RenderArgs) -> Result<(), Failure> {
    check_output(&args.output, args.open.force)?;
    let source = open_source(&args.file, !args.open.no_validate)?;
    let dag = Opened::open(source.bytes(), &args.file)?;
    let depth = dag.depth();
    if let Some(level) = args.level
        && !(1..=depth).contains(&level)
    {
        return fail(format!(
            "--level {level} is outside 1..={depth} (the file's depth)"
        ));
    }
    let tracer = dag.tracer(&args.file)?;
    let aspect = f64::from(args.width) / f64::from(args.height);
    let camera = match (args.camera_pos, args.look_at) {
        (Some(position), Some(look_at)) => Camera {
            position,
            look_at,
            up: [0.0, 1.0, 0.0],
            fov_y_degrees: args.fov,
        },
        _ => Camera {
            fov_y_degrees: args.fov,
            ..match &dag {
                Opened::V1(d) => Camera::automatic(d, aspect),
                Opened::V2(d) => match tracer.occupied_box() {
                    Some((lo, hi)) => Camera::looking_at_box(lo, hi, aspect),
                    None => {
                        Camera::looking_at_cube(d.header().root_min, d.header().root_size, aspect)
                    }
                },
            }
        },
    };
    let frame = camera.frame()?;
    let lit_flags = [
        ("--sun", args.sun.is_some()),
        ("--ao-rays", args.ao_rays.is_some()),
        ("--ao-radius", args.ao_radius.is_some()),
        ("--samples", args.samples.is_some()),
    ];
    let shade = match args.shade {
        ShadeArg::Lit => None,
        ShadeArg::Normal => Some(Shade::Normal),
        ShadeArg::Depth => Some(Shade::Depth),
        ShadeArg::Color => Some(Shade::Color),
    };
    let pixels = match shade {
        Some(shade) => {
            if let Some((flag, _)) = lit_flags.iter().find(|(_, given)| *given) {
                return fail(format!("{flag} applies to --shade lit only"));
            }
            let colored = shade == Shade::Color && tracer.colors().is_some();
            match dag.gpu(&args.backend, shade == Shade::Color, colored)? {
                None => render(&tracer, &frame, args.width, args.height, shade, args.level)
                    .map_err(|e| Failure(format!("{}: {e}", args.file.display())))?,
                Some(gpu) => {
                    // The same f64 camera rays as the CPU path, so both back ends
                    // render the same image (up to the spec's tolerance).
                    let rays = frame.rays(args.width, args.height, args.level);
                    shade_on_gpu(&gpu, &rays, shade)?
                }
            }
        }
        None => {
            let defaults = LitOptions::default();
            let options = LitOptions {
                sun: args.sun.unwrap_or(defaults.sun),
                ao_rays: args.ao_rays.unwrap_or(defaults.ao_rays),
                ao_radius: args.ao_radius,
                samples: args.samples.unwrap_or(defaults.samples),
            };
            options.check()?;
            let colored = tracer.colors().is_some();
            match dag.gpu(&args.backend, colored, colored)? {
                None => render_lit(
                    &tracer,
                    &frame,
                    args.width,
                    args.height,
                    args.level,
                    &options,
                )
                .map_err(|e| Failure(format!("{}: {e}", args.file.display())))?,
                Some(gpu) => lit_on_gpu(&gpu, &camera, &args, &options, &tracer)?,
            }
        }
    };
    write_atomically(&args.output, args.open.force, |out| {
        image::write_buffer_with_format(
            out,
            &pixels,
            args.width,
            args.height,
            image::ExtendedColorType::Rgb8,
            image::ImageFormat::Png,
        )
        .map_err(std::io::Error::other)
    })
}

/// A `--shade normal|depth|color` image on the GPU: the hits traced there,
/// and with colours on the device, the hit voxels' colours decoded there
/// from their attribute indices; shaded on the host as the CPU path shades.
#[cfg(feature = "gpu")]
fn shade_on_gpu(
    gpu: &GpuBackend,
    rays: &[dagfmt::batch::Ray],
    shade: Shade,
) -> Result<Vec<u8>, Failure> {
    let hits = gpu.trace(rays)?;
    let colors = if gpu.has_colors() && shade == Shade::Color {
        gpu.hit_colors(&hits)?
    } else {
        Vec::new()
    };
    Ok(dagtrace::render::shade_hits_colored(&hits, shade, &colors))
}

#[cfg(not(feature = "gpu"))]
fn shade_on_gpu(gpu: &GpuBackend, _: &[dagfmt::batch::Ray], _: Shade) -> Result<Vec<u8>, Failure> {
    match *gpu {}
}

/// The lit image on the GPU; the colours decoded there when the file has
/// them.
#[cfg(feature = "gpu")]
fn lit_on_gpu(
    gpu: &GpuBackend,
    camera: &Camera,
    args: &RenderArgs,
    options: &LitOptions,
    tracer: &Tracer<'_>,
) -> Result<Vec<u8>, Failure> {
    if gpu.has_colors() {
        return Ok(gpu.render_lit_colored(camera, args.width, args.height, args.level, options)?);
    }
    Ok(
        gpu.render_lit(camera, args.width, args.height, args.level, options, |i| {
            tracer.color(i)
        })?,
    )
}

#[cfg(not(feature = "gpu"))]
fn lit_on_gpu(
    gpu: &GpuBackend,
    _: &Camera,
    _: &RenderArgs,
    _: &LitOptions,
    _: &Tracer<'_>,
) -> Result<Vec<u8>, Failure> {
    match *gpu {}
}

fn trace_cmd(args: TraceArgs) -> Result<(), Failure> {
    check_output(&args.output, args.open.force)?;
    let source = open_source(&args.file, !args.open.no_validate)?;
    let dag = Opened::open(source.bytes(), &args.file)?;
    let depth = dag.depth();
    let rays_failure = |e: &dyn std::fmt::Display| Failure(format!("{}: {e}", args.rays.display()));
    let file = File::open(&args.rays).map_err(|e| rays_failure(&e))?;
    let length = file.metadata().map_err(|e| rays_failure(&e))?.len();
    let mut reader = RayReader::new(BufReader::with_capacity(1 << 20, file), Some(length))
        .map_err(|e| rays_failure(&e))?;
    let gpu = dag.gpu(&args.backend, true, false)?;
    let cpu = match gpu {
        Some(_) => None,
        None => Some(dag.tracer(&args.file)?),
    };
    let started = std::time::Instant::now();
    // The batch streams through in chunks: rays read, traced and their hits
    // written one chunk at a time, so memory does not grow with the batch.
    // A failure inside the output's writer is kept here, and the writer
    // stops, leaving no output file.
    let mut failure = None;
    let mut traced = 0u64;
    let written = write_atomically(&args.output, args.open.force, |out| {
        let mut stop = |f: Failure| {
            failure = Some(f);
            std::io::Error::other("stopped")
        };
        let declared = reader.declared_count();
        match args.format {
            HitFormat::Text => dagfmt::batch::write_hits_text_header(out)?,
            // Without a count in the rays (text), it is written at the end.
            HitFormat::Binary => {
                dagfmt::batch::write_hits_binary_header(out, declared.unwrap_or(0))?
            }
        }
        let (mut rays, mut hits) = (Vec::new(), Vec::new());
        loop {
            reader
                .read_chunk(args.chunk_rays as usize, &mut rays)
                .map_err(|e| stop(rays_failure(&e)))?;
            if rays.is_empty() {
                break;
            }
            if let Some((i, level)) = rays
                .iter()
                .enumerate()
                .find_map(|(i, r)| r.level.filter(|&l| l > depth).map(|l| (i, l)))
            {
                return Err(stop(Failure(format!(
                    "{}: ray {} asks for level {level}, deeper than the file's depth {depth}",
                    args.rays.display(),
                    traced + i as u64 + 1
                ))));
            }
            hits.resize(rays.len(), dagfmt::batch::Hit::MISS);
            match (&gpu, &cpu) {
                (Some(gpu), _) => trace_on_gpu(gpu, &rays, &mut hits, traced).map_err(&mut stop)?,
                (None, Some(cpu)) => cpu
                    .trace_batch_into(&rays, &mut hits)
                    .map_err(|e| stop(Failure(format!("{}: {e}", args.file.display()))))?,
                (None, None) => unreachable!("a tracer on one back end or the other"),
            }
            let first = traced as usize;
            match args.format {
                HitFormat::Text => dagfmt::batch::write_hits_text_records(out, &hits, first)?,
                HitFormat::Binary => dagfmt::batch::write_hits_binary_records(out, &hits, first)?,
            }
            traced += rays.len() as u64;
        }
        if args.format == HitFormat::Binary && declared.is_none() {
            use std::io::{Seek, SeekFrom, Write};
            out.seek(SeekFrom::Start(8))?;
            out.write_all(&traced.to_le_bytes())?;
            out.seek(SeekFrom::End(0))?;
        }
        Ok(())
    });
    if let Some(f) = failure {
        return Err(f);
    }
    written?;
    if args.stats {
        let seconds = started.elapsed().as_secs_f64();
        eprintln!(
            "dagtrace: traced {traced} rays in {seconds:.3} s ({:.2} Mrays/s, reading and writing included); peak resident memory {}",
            traced as f64 / seconds.max(1e-9) / 1e6,
            dagtrace::cli::peak_rss_mib()
                .map_or_else(|| "unknown".to_string(), |m| format!("{m:.1} MiB"))
        );
    }
    Ok(())
}

/// Traces one chunk on the GPU; ray numbers in errors count from `first`.
#[cfg(feature = "gpu")]
fn trace_on_gpu(
    gpu: &GpuBackend,
    rays: &[dagfmt::batch::Ray],
    hits: &mut [dagfmt::batch::Hit],
    first: u64,
) -> Result<(), Failure> {
    use dagtrace::gpu::GpuError;
    gpu.trace_into_with_stats(rays, hits)
        .map(drop)
        .map_err(|e| {
            let shift = |ray: usize| ray + first as usize;
            Failure(
                match e {
                    GpuError::MalformedPointer { ray } => {
                        GpuError::MalformedPointer { ray: shift(ray) }
                    }
                    GpuError::IterationLimit { ray, limit } => GpuError::IterationLimit {
                        ray: shift(ray),
                        limit,
                    },
                    GpuError::LevelTooDeep { ray, level, depth } => GpuError::LevelTooDeep {
                        ray: shift(ray),
                        level,
                        depth,
                    },
                    other => other,
                }
                .to_string(),
            )
        })
}

#[cfg(not(feature = "gpu"))]
fn trace_on_gpu(
    gpu: &GpuBackend,
    _: &[dagfmt::batch::Ray],
    _: &mut [dagfmt::batch::Hit],
    _: u64,
) -> Result<(), Failure> {
    match *gpu {}
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => {
            if !e.use_stderr() {
                // --help and --version.
                let _ = e.print();
                return ExitCode::SUCCESS;
            }
            // Usage errors are one line too, with status 2.
            let first = dagtrace::cli::usage_error_line(&e);
            eprintln!("dagtrace: error: {first} (see dagtrace --help)");
            return ExitCode::from(2);
        }
    };
    let result = match cli.command {
        Command::Render(args) => render_cmd(args),
        Command::Trace(args) => trace_cmd(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(Failure(message)) => {
            eprintln!("dagtrace: error: {message}");
            ExitCode::FAILURE
        }
    }
}
