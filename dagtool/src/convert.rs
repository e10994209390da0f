//! `dagtool convert`: a mesh or a voxel list to a `.vdag` file.

use std::fmt::Write as _;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Instant;

use dagfmt::builder::{BuiltDag, DagBuilder, LevelStats};
use dagfmt::layout::{AttributeKind, MAX_DEPTH, MIN_DEPTH};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::error::ConvertError;
use crate::mesh::{DEFAULT_COLOR, GridMapping, Mesh, SnappedMesh};
use crate::output::{check_output, write_atomic};
use crate::pipeline::{self, Bins, ChunkOutput, SolidMode, VoxelizeConfig};
use crate::sysinfo::{
    current_rss, human_bytes, peak_rss, process_cpu_seconds, thread_cpu_seconds, total_memory,
};
use crate::voxelize::{MAX_CHUNK_BITS, MIN_CHUNK_BITS, NO_TAG};
use crate::voxlist;

/// What the input file is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InputFormat {
    /// Decide from the content and the extension.
    Auto,
    /// Wavefront OBJ.
    Obj,
    /// A text or binary voxel list.
    Voxels,
}

/// Options of `dagtool convert`.
#[derive(Clone, Debug)]
pub struct ConvertOptions {
    /// Input file.
    pub input: PathBuf,
    /// Output `.vdag` file.
    pub output: PathBuf,
    /// Depth D; required for meshes.
    pub depth: Option<u8>,
    /// Input format.
    pub format: InputFormat,
    /// Fill the interior.
    pub solid: bool,
    /// Store per-voxel material colours.
    pub colors: bool,
    /// Replace an existing output file.
    pub force: bool,
    /// Show a progress bar (only on a terminal).
    pub progress: bool,
    /// Memory limit in bytes (`None`: 3/4 of physical memory).
    pub memory_limit: Option<u64>,
    /// log2 of the chunk side (`None`: automatic).
    pub chunk_bits: Option<u32>,
}

impl ConvertOptions {
    /// Options with defaults for `input` -> `output` at `depth`.
    pub fn new(input: impl Into<PathBuf>, output: impl Into<PathBuf>, depth: Option<u8>) -> Self {
        ConvertOptions {
            input: input.into(),
            output: output.into(),
            depth,
            format: InputFormat::Auto,
            solid: false,
            colors: false,
            force: false,
            progress: false,
            memory_limit: None,
            chunk_bits: None,
        }
    }
}

/// What a conversion did, for the summary.
#[derive(Clone, Debug, Default)]
pub struct ConvertSummary {
    /// Input description (triangles, or voxel records).
    pub input: String,
    /// Triangles in the mesh (0 for voxel lists).
    pub triangles: u64,
    /// Zero-area triangles.
    pub degenerate: u64,
    /// Whether the mesh is closed (checked only with `--solid`).
    pub closed: Option<bool>,
    /// How the interior was filled.
    pub fill: String,
    /// Depth.
    pub depth: u8,
    /// Root cube.
    pub root_min: [f64; 3],
    /// Root cube edge.
    pub root_size: f64,
    /// Chunk side in voxels (0 for voxel lists).
    pub chunk_side: u64,
    /// Chunks holding triangles.
    pub surface_chunks: u64,
    /// Chunks filled by the solid fill only.
    pub fill_chunks: u64,
    /// Worker threads.
    pub threads: usize,
    /// Triangle-chunk pairs.
    pub bin_entries: u64,
    /// Set voxels.
    pub voxels: u64,
    /// Per-level statistics.
    pub levels: Vec<LevelStats>,
    /// Bytes of the output file.
    pub file_bytes: u64,
    /// Seconds spent loading the input.
    pub load_seconds: f64,
    /// Seconds spent voxelizing and building.
    pub build_seconds: f64,
    /// Seconds spent writing.
    pub write_seconds: f64,
    /// Total seconds.
    pub total_seconds: f64,
    /// Peak resident set size (`VmHWM`).
    pub peak_rss: Option<u64>,
    /// CPU seconds of the whole process.
    pub cpu_seconds: Option<f64>,
    /// CPU seconds of the thread that runs the DAG builder (and loads, writes).
    pub main_thread_cpu_seconds: Option<f64>,
    /// Warnings (e.g. materials not loaded).
    pub warnings: Vec<String>,
}

impl ConvertSummary {
    /// The summary as text for people.
    pub fn render(&self, output: &Path) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "input:    {}", self.input);
        let _ = writeln!(
            s,
            "grid:     depth {} ({}^3 voxels), root cube min [{}, {}, {}] size {}",
            self.depth,
            1u64 << self.depth,
            self.root_min[0],
            self.root_min[1],
            self.root_min[2],
            self.root_size
        );
        if self.chunk_side > 0 {
            let _ = writeln!(
                s,
                "chunks:   {}^3 voxels each; {} with triangles ({} triangle-chunk pairs), {} filled inside; {} threads",
                self.chunk_side,
                self.surface_chunks,
                self.bin_entries,
                self.fill_chunks,
                self.threads
            );
        }
        let _ = writeln!(s, "fill:     {}", self.fill);
        let _ = writeln!(s, "voxels:   {}", self.voxels);
        let _ = writeln!(
            s,
            "{:>7} {:>12} {:>14} {:>6} {:>10}",
            "level", "nodes", "bytes", "width", "dedup"
        );
        for l in &self.levels {
            let _ = writeln!(
                s,
                "{:>7} {:>12} {:>14} {:>6} {:>10.2}",
                l.level,
                l.node_count,
                l.bytes,
                l.pointer_width,
                l.dedup_ratio()
            );
        }
        let _ = writeln!(
            s,
            "output:   {} ({} bytes, {})",
            output.display(),
            self.file_bytes,
            human_bytes(self.file_bytes)
        );
        let _ = writeln!(
            s,
            "time:     {:.2} s (load {:.2} s, voxelize and build {:.2} s, write {:.2} s)",
            self.total_seconds, self.load_seconds, self.build_seconds, self.write_seconds
        );
        if let (Some(all), Some(main)) = (self.cpu_seconds, self.main_thread_cpu_seconds) {
            let _ = writeln!(
                s,
                "cpu:      {all:.2} s in all threads, {main:.2} s in the main thread (load, DAG builder, write)"
            );
        }
        match self.peak_rss {
            Some(b) => {
                let _ = write!(s, "peak RSS: {} ({b} bytes)", human_bytes(b));
            }
            None => {
                let _ = write!(s, "peak RSS: unknown");
            }
        }
        for w in &self.warnings {
            let _ = write!(s, "\nwarning:  {w}");
        }
        s
    }
}

/// Checks a depth given on the command line.
pub fn check_depth(depth: u32) -> Result<u8, ConvertError> {
    if (u32::from(MIN_DEPTH)..=u32::from(MAX_DEPTH)).contains(&depth) {
        Ok(depth as u8)
    } else {
        Err(ConvertError::Usage(format!(
            "depth {depth} is outside {MIN_DEPTH}..={MAX_DEPTH}"
        )))
    }
}

/// The depth of a resolution given on the command line (a power of two).
pub fn depth_of_resolution(resolution: u64) -> Result<u8, ConvertError> {
    if !resolution.is_power_of_two() {
        return Err(ConvertError::Usage(format!(
            "resolution {resolution} is not a power of two"
        )));
    }
    let d = resolution.trailing_zeros();
    check_depth(d).map_err(|_| {
        ConvertError::Usage(format!(
            "resolution {resolution} is outside {}..={} (depth {MIN_DEPTH}..={MAX_DEPTH})",
            1u64 << MIN_DEPTH,
            1u64 << MAX_DEPTH
        ))
    })
}

fn build_error(e: dagfmt::builder::BuildError) -> ConvertError {
    ConvertError::Limit(format!("cannot build the DAG: {e}"))
}

fn detect_format(path: &Path, format: InputFormat) -> Result<InputFormat, ConvertError> {
    if format != InputFormat::Auto {
        return Ok(format);
    }
    if voxlist::is_binary(path) {
        return Ok(InputFormat::Voxels);
    }
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    match ext.as_str() {
        "obj" => Ok(InputFormat::Obj),
        "txt" | "xyz" | "voxels" | "vox3" => Ok(InputFormat::Voxels),
        _ => Err(ConvertError::Usage(format!(
            "cannot tell the format of {} from its extension (.obj for meshes, .txt/.xyz/.voxels for voxel lists); \
             use --input-format",
            path.display()
        ))),
    }
}

/// Runs a conversion. Nothing is written unless it succeeds.
pub fn convert(opts: &ConvertOptions) -> Result<ConvertSummary, ConvertError> {
    let start = Instant::now();
    check_output(&opts.output, opts.force)?;
    let meta = std::fs::metadata(&opts.input)
        .map_err(|e| ConvertError::io(format!("cannot open input {}", opts.input.display()), e))?;
    if !meta.is_file() {
        return Err(ConvertError::Input(format!(
            "input {} is not a regular file",
            opts.input.display()
        )));
    }
    let limit = opts
        .memory_limit
        .unwrap_or_else(|| total_memory().map_or(8 << 30, |m| m / 4 * 3));
    let format = detect_format(&opts.input, opts.format)?;
    let mut summary = match format {
        InputFormat::Voxels => convert_voxels(opts, limit)?,
        _ => convert_mesh(opts, limit)?,
    };
    summary.total_seconds = start.elapsed().as_secs_f64();
    summary.peak_rss = peak_rss();
    summary.cpu_seconds = process_cpu_seconds();
    summary.main_thread_cpu_seconds = thread_cpu_seconds();
    Ok(summary)
}

/// Checks the memory in use against the limit.
fn check_memory(limit: u64, what: &str) -> Result<(), ConvertError> {
    if let Some(rss) = current_rss()
        && rss > limit
    {
        return Err(ConvertError::Limit(format!(
            "memory limit of {} exceeded ({} resident) while {what}; raise --memory-limit or lower the depth",
            human_bytes(limit),
            human_bytes(rss)
        )));
    }
    Ok(())
}

fn write_output(
    opts: &ConvertOptions,
    built: &BuiltDag,
    summary: &mut ConvertSummary,
) -> Result<(), ConvertError> {
    let t = Instant::now();
    summary.file_bytes = write_atomic(&opts.output, opts.force, |w| built.write_to(w))?;
    summary.write_seconds = t.elapsed().as_secs_f64();
    summary.voxels = built.voxel_count();
    summary.levels = built.level_stats();
    Ok(())
}

fn convert_voxels(opts: &ConvertOptions, limit: u64) -> Result<ConvertSummary, ConvertError> {
    if opts.solid {
        return Err(ConvertError::Usage(
            "--solid needs a mesh input, not a voxel list".into(),
        ));
    }
    if opts.colors {
        return Err(ConvertError::Usage(
            "--colors needs a mesh input with materials, not a voxel list".into(),
        ));
    }
    let t = Instant::now();
    let list = voxlist::read(&opts.input, opts.depth)?;
    check_memory(limit, "reading the voxel list")?;
    let mut summary = ConvertSummary {
        input: format!(
            "{}: voxel list, {} records, {} distinct voxels",
            opts.input.display(),
            list.records,
            list.codes.len()
        ),
        fill: "voxel list (as given)".into(),
        depth: list.depth,
        root_min: [0.0; 3],
        root_size: (1u64 << list.depth) as f64,
        load_seconds: t.elapsed().as_secs_f64(),
        ..Default::default()
    };
    let t = Instant::now();
    let mut builder =
        DagBuilder::new(list.depth, AttributeKind::VoxelCount).map_err(build_error)?;
    builder.set_root_cube(summary.root_min, summary.root_size);
    let mut i = 0;
    while i < list.codes.len() {
        let brick = list.codes[i] >> 6;
        let mut mask = 0u64;
        while i < list.codes.len() && list.codes[i] >> 6 == brick {
            mask |= 1 << (list.codes[i] & 63);
            i += 1;
        }
        builder.push_brick(brick, mask).map_err(build_error)?;
    }
    drop(list);
    let built = builder.finish().map_err(build_error)?;
    summary.build_seconds = t.elapsed().as_secs_f64();
    write_output(opts, &built, &mut summary)?;
    Ok(summary)
}

fn convert_mesh(opts: &ConvertOptions, limit: u64) -> Result<ConvertSummary, ConvertError> {
    let depth = opts.depth.ok_or_else(|| {
        ConvertError::Usage("converting a mesh needs --depth D or --resolution N".into())
    })?;
    let chunk_bits = match opts.chunk_bits {
        Some(c) => {
            if !(MIN_CHUNK_BITS..=MAX_CHUNK_BITS).contains(&c) || c > u32::from(depth) {
                return Err(ConvertError::Usage(format!(
                    "chunk size 2^{c} must be between 2^{MIN_CHUNK_BITS} and 2^{} voxels (and at most the resolution)",
                    MAX_CHUNK_BITS
                )));
            }
            c
        }
        None => MAX_CHUNK_BITS.min(u32::from(depth)),
    };
    if opts.solid && u32::from(depth) - chunk_bits > 9 {
        return Err(ConvertError::Limit(format!(
            "--solid at depth {depth} is not supported: the solid fill visits every chunk of the volume, \
             so it is limited to {} chunks per axis (depth {} with the default chunk size)",
            1 << 9,
            9 + MAX_CHUNK_BITS
        )));
    }
    let t = Instant::now();
    let mesh = Mesh::load_obj(&opts.input)?;
    let check = mesh.check()?;
    let mapping = GridMapping::fit(check.min, check.max, depth)?;
    let snapped = SnappedMesh::new(&mesh, &mapping);
    let mut summary = ConvertSummary {
        triangles: mesh.triangles.len() as u64,
        degenerate: check.degenerate,
        depth,
        root_min: mapping.root_min,
        root_size: mapping.root_size,
        chunk_side: 1 << chunk_bits,
        ..Default::default()
    };
    if let Some(w) = &mesh.material_warning
        && opts.colors
    {
        summary
            .warnings
            .push(format!("{w}; voxels without a material are white"));
    }
    let solid = if opts.solid {
        let closed = snapped.is_closed();
        summary.closed = Some(closed);
        if closed {
            SolidMode::ParityZ
        } else {
            SolidMode::Vote
        }
    } else {
        SolidMode::Surface
    };
    summary.fill = match solid {
        SolidMode::Surface => "surface only (conservative)".into(),
        SolidMode::ParityZ => "solid: closed mesh, crossing parity along z".into(),
        SolidMode::Vote => {
            "solid: open mesh, majority of the crossing parities along x, y and z".into()
        }
    };
    if solid != SolidMode::Surface {
        // The column parity state holds one bit per voxel column of the
        // projected area, per axis; the chunk walk visits every chunk.
        let axes = if solid == SolidMode::Vote { 3 } else { 1 };
        let state = axes * (1u64 << (2 * u32::from(depth))) / 8;
        if state > limit / 2 {
            return Err(ConvertError::Limit(format!(
                "--solid at depth {depth} needs up to {} of column parity state (memory limit {}); \
                 use a smaller depth or raise --memory-limit",
                human_bytes(state),
                human_bytes(limit)
            )));
        }
    }
    summary.input = format!(
        "{}: {} triangles ({} degenerate){}",
        opts.input.display(),
        summary.triangles,
        summary.degenerate,
        match summary.closed {
            Some(true) => ", closed",
            Some(false) => ", not closed",
            None => "",
        }
    );
    let bins = Bins::new(&snapped, depth, chunk_bits);
    summary.bin_entries = bins.len() as u64;
    summary.load_seconds = t.elapsed().as_secs_f64();
    check_memory(limit, "binning triangles")?;

    let t = Instant::now();
    let threads = rayon::current_num_threads();
    let chunk_bytes = (1u64 << (3 * (chunk_bits - 2))) * 16
        + if opts.colors {
            4u64 << (3 * chunk_bits)
        } else {
            0
        };
    let batch = ((limit / 16 / chunk_bytes.max(1)) as usize).clamp(threads, 8 * threads);
    let cfg = VoxelizeConfig {
        depth,
        chunk_bits,
        solid,
        tags: opts.colors,
        batch,
    };
    let mut builder = DagBuilder::new(depth, AttributeKind::VoxelCount).map_err(build_error)?;
    builder.set_root_cube(mapping.root_min, mapping.root_size);
    let mut colors: Vec<[u8; 4]> = Vec::new();
    let bar = if opts.progress && std::io::stderr().is_terminal() {
        let bar = ProgressBar::with_draw_target(
            Some(bins.codes.len() as u64),
            ProgressDrawTarget::stderr(),
        );
        if let Ok(style) = ProgressStyle::with_template(
            "{spinner} voxelizing [{bar:40}] {pos}/{len} chunks, {elapsed} elapsed, eta {eta} {msg}",
        ) {
            bar.set_style(style.progress_chars("=> "));
        }
        bar
    } else {
        ProgressBar::hidden()
    };
    let shift = cfg.brick_shift();
    let mut batches = 0u64;
    let report = pipeline::run(
        &snapped,
        &bins,
        &cfg,
        &|done| bar.set_position(done),
        |outs: Vec<ChunkOutput>| -> Result<(), ConvertError> {
            for out in outs {
                let base = out.code << shift;
                for &(brick, mask) in &out.bricks {
                    builder
                        .push_brick(base | u64::from(brick), mask)
                        .map_err(build_error)?;
                }
                if opts.colors {
                    colors.extend(out.tags.iter().map(|&t| {
                        if t == NO_TAG {
                            DEFAULT_COLOR
                        } else {
                            mesh.triangle_color(t as usize)
                        }
                    }));
                }
            }
            batches += 1;
            if batches.is_multiple_of(8) {
                check_memory(limit, "voxelizing")?;
            }
            Ok(())
        },
    );
    bar.finish_and_clear();
    let report = report?;
    summary.surface_chunks = report.surface_chunks;
    summary.threads = threads;
    summary.fill_chunks = report.fill_chunks;
    drop(bins);
    drop(snapped);
    let mut built = builder.finish().map_err(build_error)?;
    if opts.colors {
        built.set_colors(colors).map_err(build_error)?;
    }
    summary.build_seconds = t.elapsed().as_secs_f64();
    check_memory(limit, "building the DAG")?;
    write_output(opts, &built, &mut summary)?;
    Ok(summary)
}
