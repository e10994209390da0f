//! `dagtool convert`: a mesh or a voxel list to a `.vdag` file.

use std::fmt::Write as _;
use std::io::IsTerminal;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use dagfmt::assemble::{FileHeader, FileLayout};
use dagfmt::builder::LevelStats;
use dagfmt::layout::{AttributeKind, MAX_DEPTH, MIN_DEPTH};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use rayon::prelude::*;

use crate::cloud::{SortedVoxels, Splat, VoxelSorter};
use crate::error::ConvertError;
use crate::external::{
    ColourSink, Colours, DagSink, FinishedDag, MIN_RUN_BUDGET, Scratch, SpillReport, SpillSettings,
};
use crate::mesh::{DEFAULT_COLOR, GridMapping, Mesh, SnappedMesh};
use crate::output::{check_output, write_atomic};
use crate::pipeline::{self, Bins, ChunkOutput, SolidMode, VoxelizeConfig};
use crate::region::{ColourMode, Placement, Region};
use crate::sysinfo::{
    MemoryMeter, human_bytes, process_cpu_seconds, thread_cpu_seconds, total_memory,
};
use crate::voxelize::{MAX_CHUNK_BITS, MIN_CHUNK_BITS, NO_TAG};
use crate::voxlist;

/// log2 of the side, in voxels, of the subtrees whose roots split the build
/// into runs when it spills (the split level is `depth - SPLIT_BITS`): the
/// default chunk size, so that a run boundary falls between two chunks and a
/// single subtree (at most 32³ bricks) is always small.
pub const SPLIT_BITS: u32 = 7;

/// What the input file is.
#[derive(Clone, Copy, Debug)]
pub enum InputFormat {
    /// Decide from the content and the extension.
    Auto,
    /// A text or binary voxel list.
    Voxels,
    /// A format of the registry ([`crate::input::FORMATS`]).
    Named(&'static crate::input::Format),
}

/// A root cube given on the command line (`--bounds xmin,ymin,zmin,size`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bounds {
    /// World-space minimum corner.
    pub min: [f64; 3],
    /// World-space edge.
    pub size: f64,
}

impl Bounds {
    /// Parses `xmin,ymin,zmin,size`.
    pub fn parse(text: &str) -> Result<Bounds, ConvertError> {
        let values: Vec<f64> = text
            .split(',')
            .map(|w| w.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| {
                ConvertError::Usage(format!(
                    "--bounds {text} is not four numbers xmin,ymin,zmin,size"
                ))
            })?;
        match values.as_slice() {
            [x, y, z, size] if [x, y, z, size].iter().all(|v| v.is_finite()) && *size > 0.0 => {
                Ok(Bounds {
                    min: [*x, *y, *z],
                    size: *size,
                })
            }
            _ => Err(ConvertError::Usage(format!(
                "--bounds {text} is not four finite numbers xmin,ymin,zmin,size with size > 0"
            ))),
        }
    }
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
    /// Pack the colours (PACKED_COLORS, spec §12.6) within this per-channel
    /// error (0: lossless); `None`: raw VOXEL_COLORS.
    pub color_error: Option<u8>,
    /// Replace an existing output file.
    pub force: bool,
    /// Show a progress bar (only on a terminal).
    pub progress: bool,
    /// Memory limit in bytes (`None`: 3/4 of physical memory), on the
    /// conversion's own memory: the process's resident memory above what
    /// was resident when the conversion started (see
    /// [`crate::sysinfo::MemoryMeter`]).
    pub memory_limit: Option<u64>,
    /// log2 of the chunk side (`None`: automatic).
    pub chunk_bits: Option<u32>,
    /// Directory of the temporary files (`None`: the output's directory).
    pub tmp_dir: Option<PathBuf>,
    /// Testing: spill whatever the memory, in runs and buckets of this shape.
    pub forced_spill: Option<ForcedSpill>,
    /// The root cube, instead of one fitted to the input.
    pub bounds: Option<Bounds>,
    /// Point clouds: the radius of the ball each point sets (world units;
    /// 0: the voxel containing the point).
    pub point_radius: f64,
    /// What the nodes' attribute bits hold (kind 1, voxel counts, unless
    /// `--attributes none`); colours need kind 1.
    pub attributes: AttributeKind,
    /// The major format version written: 2 (the default; spec §23: the 1.0
    /// DAG is built as usual, then upgraded in memory) or 1. It does not
    /// apply to a region build: a part is always format 1 (spec §24), and
    /// `dagtool merge` writes the whole volume in the version asked.
    pub format_version: u16,
    /// Build only this cell of the root cube, into a part (spec § 24); needs
    /// `bounds`, so that every part has the same root cube.
    pub region: Option<Region>,
    /// More point clouds read after `input` as one (the tiles of a survey);
    /// with `region`, only those whose declared bounds meet the cell are read.
    pub extra_inputs: Vec<PathBuf>,
    /// Told how the conversion proceeds, for callers without a terminal
    /// (the Python package's `progress` callable); `None`: nobody is.
    pub progress_hook: Option<ProgressHook>,
    /// Keep a mesh input in memory after the conversion, for the next one of
    /// the same file in this process (the region builds a worker process
    /// runs one after another: the file is parsed once per process, not once
    /// per region). See [`clear_input_cache`].
    pub cache_input: bool,
    /// Set by the 2.0 conversion for its 1.0 stage: the 1.0 file is left
    /// here, in memory, instead of written to `output`, when it fits the
    /// memory limit beside what is resident (no file written, synced,
    /// renamed and mapped again to be encoded); else it is written.
    v1_in_memory: Option<Arc<Mutex<Option<Vec<u8>>>>>,
    /// The conversion's memory, started by [`convert`] (and kept by the
    /// 2.0 conversion's 1.0 stage, so that both count from one start).
    meter: MemoryMeter,
}

/// The mesh kept by a conversion with [`ConvertOptions::cache_input`]: the
/// file it was read from (path, size, modification time), whether colours
/// were read, and the mesh.
type CachedMesh = (PathBuf, u64, Option<std::time::SystemTime>, bool, Arc<Mesh>);

static MESH_CACHE: Mutex<Option<CachedMesh>> = Mutex::new(None);

/// Frees the mesh kept by conversions with [`ConvertOptions::cache_input`];
/// returns whether one was kept.
pub fn clear_input_cache() -> bool {
    MESH_CACHE
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .take()
        .is_some()
}

/// The mesh of `path`: the cached one when the file (path, size and
/// modification time) and `colors` are those it was read with, else `load`'s,
/// which then replaces it. The lock is held while loading, so that threads
/// converting regions of one file at once parse it once.
fn cached_mesh(
    path: &Path,
    colors: bool,
    load: impl FnOnce() -> Result<Mesh, ConvertError>,
) -> Result<Arc<Mesh>, ConvertError> {
    let meta = std::fs::metadata(path)
        .map_err(|e| ConvertError::io(format!("cannot open input {}", path.display()), e))?;
    let path = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
    let (len, modified) = (meta.len(), meta.modified().ok());
    let mut cache = MESH_CACHE
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    if let Some((p, l, m, c, mesh)) = cache.as_ref()
        && *p == path
        && *l == len
        && *m == modified
        && modified.is_some()
        && *c == colors
    {
        return Ok(Arc::clone(mesh));
    }
    // The old mesh goes before the new one is read.
    *cache = None;
    let mesh = Arc::new(load()?);
    *cache = Some((path, len, modified, colors, Arc::clone(&mesh)));
    Ok(mesh)
}

/// A step of a conversion, as [`ProgressHook`] is told it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ConvertProgress {
    /// Voxelizing a mesh: `done` of `total` surface chunks (called from the
    /// voxelizing threads, as chunks finish).
    Voxelizing {
        /// Chunks voxelized.
        done: u64,
        /// Chunks to voxelize.
        total: u64,
    },
    /// Every voxel is in the builder; the DAG is being finished (in memory,
    /// or by merging the spilled runs level by level).
    Finishing,
    /// The output file is in place.
    Written,
}

/// A callback told each [`ConvertProgress`] step; it may be called from any
/// thread, so it must be `Send + Sync`.
#[derive(Clone)]
pub struct ProgressHook(pub std::sync::Arc<dyn Fn(ConvertProgress) + Send + Sync>);

impl std::fmt::Debug for ProgressHook {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ProgressHook(..)")
    }
}

impl ConvertOptions {
    /// Tells the hook, if any, of `step`.
    fn report(&self, step: ConvertProgress) {
        if let Some(hook) = &self.progress_hook {
            (hook.0)(step);
        }
    }
}

/// One line on a packed colour section: size per voxel, against raw RGB, and
/// the error measured while packing.
pub fn packed_line(p: &dagfmt::packed_colors::PackedSummary) -> String {
    let bits = if p.count == 0 {
        0.0
    } else {
        p.length as f64 * 8.0 / p.count as f64
    };
    format!(
        "packed, {} bytes for {} colours: {bits:.3} bits per voxel, {:.2} % of raw 24-bit RGB; error bound {}, max error {}, PSNR {}; {}",
        p.length,
        p.count,
        bits / 24.0 * 100.0,
        p.trailer.error_bound,
        p.trailer.max_error,
        psnr_text(p.trailer.psnr(p.count)),
        layout_text(p.trailer.layout)
    )
}

/// A packed colour section's block layout in words.
pub fn layout_text(layout: dagfmt::packed_colors::BlockLayout) -> String {
    format!(
        "blocks of {}{}",
        layout.block_colors(),
        if layout.split {
            ", split sub-blocks (format 1.2)"
        } else if layout.shift == 6 {
            " (format 1.1)"
        } else {
            " (format 1.2)"
        }
    )
}

/// PSNR in dB, or "lossless".
pub fn psnr_text(psnr: f64) -> String {
    if psnr.is_finite() {
        format!("{psnr:.2} dB")
    } else {
        "infinite (lossless)".into()
    }
}

/// Testing: a conversion that spills to temporary files whatever the memory
/// limit (the hidden `--spill-*` options), to check that the out-of-core
/// build makes the same file as the in-memory one.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ForcedSpill {
    /// Split level P (`None`: `depth - 7`, at least 1).
    pub split_level: Option<u8>,
    /// Level-P cells per run (`None`: 1).
    pub cells_per_run: Option<u64>,
    /// Buckets of every level's merge (`None`: sized to the budget).
    pub buckets: Option<u32>,
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
            color_error: None,
            force: false,
            progress: false,
            memory_limit: None,
            chunk_bits: None,
            tmp_dir: None,
            forced_spill: None,
            bounds: None,
            point_radius: 0.0,
            attributes: AttributeKind::VoxelCount,
            format_version: 2,
            region: None,
            extra_inputs: Vec::new(),
            progress_hook: None,
            cache_input: false,
            v1_in_memory: None,
            meter: MemoryMeter::whole_process(),
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
    /// Seconds reading and parsing the input (meshes; part of `load_seconds`).
    pub parse_seconds: f64,
    /// Seconds binning triangles into chunks (meshes; part of `load_seconds`).
    pub bin_seconds: f64,
    /// Seconds spent voxelizing and building.
    pub build_seconds: f64,
    /// Seconds spent writing.
    pub write_seconds: f64,
    /// Total seconds.
    pub total_seconds: f64,
    /// The conversion's peak resident set size: the process's peak
    /// (`VmHWM`) above what was resident when it started (see
    /// [`crate::sysinfo::MemoryMeter`]), which the memory limit bounds.
    pub peak_rss: Option<u64>,
    /// The memory limit in bytes.
    pub memory_limit: u64,
    /// Bytes the in-memory DAG builder could use before spilling a run.
    pub run_budget: u64,
    /// What spilling to temporary files did.
    pub spill: SpillReport,
    /// The directory of the temporary files.
    pub tmp_dir: PathBuf,
    /// Bytes written to temporary files (DAG runs, merge, colours).
    pub temp_bytes: u64,
    /// The most bytes the temporary files held at once.
    pub temp_peak_bytes: u64,
    /// Whether the colours went through a temporary file.
    pub colors_spilled: bool,
    /// The packed colour section's size and measured error, when packed.
    pub colors_packed: Option<dagfmt::packed_colors::PackedSummary>,
    /// CPU seconds of the whole process.
    pub cpu_seconds: Option<f64>,
    /// CPU seconds of the thread that runs the DAG builder (and loads, writes).
    pub main_thread_cpu_seconds: Option<f64>,
    /// Warnings (e.g. materials not loaded).
    pub warnings: Vec<String>,
    /// Format 2.0: the bytes of the 1.0 file it was upgraded from.
    pub v1_file_bytes: Option<u64>,
    /// Format 2.0: seconds spent encoding and writing the 2.0 file.
    pub upgrade_seconds: Option<f64>,
    /// Format 2.0: the encoder's passes over a level that went out of core
    /// (their working set over its budget) and the bytes of its scratch file.
    pub encoder_spill: Option<dagfmt::v2file::Spill>,
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
        if let (Some(v1), Some(secs)) = (self.v1_file_bytes, self.upgrade_seconds) {
            let _ = writeln!(
                s,
                "format:   2.0, {:.3} of the 1.0 file ({v1} bytes); encoded in {secs:.2} s{}",
                self.file_bytes as f64 / v1.max(1) as f64,
                match self.encoder_spill {
                    Some(sp) if sp.scratch_bytes > 0 => format!(
                        " ({} level passes out of core, {} through a scratch file)",
                        sp.external_passes,
                        human_bytes(sp.scratch_bytes)
                    ),
                    _ => String::new(),
                }
            );
        }
        let _ = writeln!(
            s,
            "time:     {:.2} s (load {:.2} s{}, voxelize and build {:.2} s, write {:.2} s)",
            self.total_seconds,
            self.load_seconds,
            if self.chunk_side > 0 {
                format!(
                    ": parse {:.2} s, bin {:.2} s",
                    self.parse_seconds, self.bin_seconds
                )
            } else {
                String::new()
            },
            self.build_seconds,
            self.write_seconds
        );
        if self.spill.runs == 0 {
            let _ = writeln!(
                s,
                "memory:   limit {}; the DAG was built in memory (up to {} allowed before spilling)",
                human_bytes(self.memory_limit),
                human_bytes(self.run_budget)
            );
        } else {
            let plural = |n: u64| if n == 1 { "" } else { "s" };
            let _ = writeln!(
                s,
                "memory:   limit {}; spilled {} run{} to temporary files, merged with up to {} bucket{} per level in {:.2} s",
                human_bytes(self.memory_limit),
                self.spill.runs,
                plural(self.spill.runs),
                self.spill.max_buckets,
                plural(self.spill.max_buckets),
                self.spill.merge_seconds
            );
        }
        if let Some(p) = &self.colors_packed {
            let _ = writeln!(s, "colours:  {}", packed_line(p));
        }
        if self.temp_bytes > 0 {
            let _ = writeln!(
                s,
                "temp:     {} ({} bytes) written to unnamed temporary files in {}, at most {} at once{}",
                human_bytes(self.temp_bytes),
                self.temp_bytes,
                self.tmp_dir.display(),
                human_bytes(self.temp_peak_bytes),
                if self.colors_spilled {
                    " (colours included)"
                } else {
                    ""
                }
            );
        }
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
        if let Some(peak) = self.peak_rss
            && peak > self.memory_limit
        {
            let _ = write!(
                s,
                "\nwarning:  peak RSS exceeded the memory limit of {}",
                human_bytes(self.memory_limit)
            );
        }
        for w in &self.warnings {
            let _ = write!(s, "\nwarning:  {w}");
        }
        s
    }
}

/// A spinner while the DAG is finished (in memory, or by merging the spilled
/// runs level by level), on a terminal with progress.
fn merge_spinner(opts: &ConvertOptions) -> ProgressBar {
    opts.report(ConvertProgress::Finishing);
    if !(opts.progress && std::io::stderr().is_terminal()) {
        return ProgressBar::hidden();
    }
    let spinner = ProgressBar::with_draw_target(None, ProgressDrawTarget::stderr());
    if let Ok(style) = ProgressStyle::with_template("{spinner} {msg}, {elapsed} elapsed") {
        spinner.set_style(style);
    }
    spinner.set_message("finishing the DAG");
    spinner.enable_steady_tick(std::time::Duration::from_millis(200));
    spinner
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

/// What `convert` makes of an input.
enum Source {
    VoxelList,
    Registered(&'static crate::input::Format),
}

fn detect_format(path: &Path, format: InputFormat) -> Result<Source, ConvertError> {
    match format {
        InputFormat::Voxels => return Ok(Source::VoxelList),
        InputFormat::Named(f) => return Ok(Source::Registered(f)),
        InputFormat::Auto => {}
    }
    if voxlist::is_binary(path) {
        return Ok(Source::VoxelList);
    }
    if let Some(f) = crate::input::detect(path) {
        return Ok(Source::Registered(f));
    }
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    match ext.as_str() {
        "txt" | "xyz" | "voxels" | "vox3" => Ok(Source::VoxelList),
        _ => Err(ConvertError::Usage(format!(
            "cannot tell the format of {} from its first bytes or its extension \
             (meshes: .obj .gltf .glb .ply .stl; points: .ply .las .laz; voxels: .vox .binvox .txt .xyz .voxels); \
             use --input-format",
            path.display()
        ))),
    }
}

/// Runs a conversion. Nothing is written unless it succeeds.
pub fn convert(opts: &ConvertOptions) -> Result<ConvertSummary, ConvertError> {
    if opts.colors && opts.attributes != AttributeKind::VoxelCount {
        return Err(ConvertError::Usage(
            "--colors needs the voxel-count attributes (they index the colours): drop --attributes none".into(),
        ));
    }
    if !(1..=2).contains(&opts.format_version) {
        return Err(ConvertError::Usage(format!(
            "--format-version {}: this tool writes format versions 1 and 2",
            opts.format_version
        )));
    }
    // The memory limit is on what the conversion adds to the process.
    let mut opts = opts.clone();
    opts.meter = MemoryMeter::start();
    // A region build writes a part, and parts are format 1 (spec §24): the
    // merge of all the parts writes the whole volume in `format_version`.
    if opts.format_version == 1 || opts.region.is_some() {
        convert_v1(&opts)
    } else {
        convert_v2(&opts)
    }
}

/// Format 2.0: the 1.0 file is built into a temporary file beside the
/// output (so the memory limit and the out-of-core build apply unchanged),
/// then upgraded (`dagfmt::v2file::upgrade_to`: on every core, within what
/// is left of the memory limit, finished tables spilled to a scratch file
/// past it) and written atomically; the temporary files are removed.
fn convert_v2(opts: &ConvertOptions) -> Result<ConvertSummary, ConvertError> {
    check_output(&opts.output, opts.force)?;
    let dir = dagfmt::output::output_dir(&opts.output);
    let temp = tempfile::Builder::new()
        .prefix(".vdag-1.0-")
        .suffix(".tmp")
        .tempfile_in(&dir)
        .map_err(|e| {
            ConvertError::io(
                format!("cannot create files in output directory {}", dir.display()),
                e,
            )
        })?;
    let mut inner = opts.clone();
    inner.output = temp.path().to_path_buf();
    inner.force = true;
    inner.format_version = 1;
    // The hidden --spill-* testing options take the out-of-core way here
    // too: the 1.0 file is written and mapped again.
    let in_memory = Arc::new(Mutex::new(None));
    if opts.forced_spill.is_none() {
        inner.v1_in_memory = Some(Arc::clone(&in_memory));
    }
    // The 1.0 stage's errors name the output the user asked for, not the
    // hidden temporary file (a write error there is one writing the output).
    let mut summary = convert_v1(&inner).map_err(|e| match e {
        ConvertError::Io(m) => ConvertError::Io(m.replace(
            &temp.path().display().to_string(),
            &format!("{} (its 1.0 stage)", opts.output.display()),
        )),
        other => other,
    })?;
    let start = Instant::now();
    // The 1.0 file is in memory when it fitted the limit, else in `temp`.
    let v1_bytes = in_memory.lock().unwrap_or_else(|e| e.into_inner()).take();
    let map = match v1_bytes {
        Some(_) => None,
        None => Some(
            dagfmt::mmap::MappedFile::open(temp.path())
                .map_err(|e| ConvertError::io("cannot read back the 1.0 file", e))?,
        ),
    };
    let bytes = match (&v1_bytes, &map) {
        (Some(v), _) => v.as_slice(),
        (None, Some(m)) => m.bytes(),
        (None, None) => unreachable!("the 1.0 file is in memory or mapped"),
    };
    let dag = dagfmt::Dag::open(bytes)
        .map_err(|e| ConvertError::Input(format!("the 1.0 file built does not open: {e}")))?;
    // The encoder's share of the limit: what the 1.0 build left resident
    // and the mapped 1.0 file (read whole) are taken; finished tables
    // beyond it go to a scratch file in the temporary files' directory.
    // The hidden --spill-* testing options spill every table.
    let limit = opts
        .memory_limit
        .unwrap_or_else(|| total_memory().map_or(8 << 30, |m| m / 4 * 3));
    let budget = if opts.forced_spill.is_some() {
        0
    } else {
        limit.saturating_sub(
            opts.meter.resident().unwrap_or(0)
                + map.as_ref().map_or(0, |m| m.bytes().len() as u64)
                + margin(limit),
        )
    };
    let options = dagfmt::v2enc::EncodeOptions {
        memory_budget: Some(budget),
        // Not refused: the encoder's least counts its vectors at their
        // largest and overshoots less than it says (dragon d12 within
        // 125M, refused at 22.5 MiB of least against a 20 MiB budget).
        refuse_below_least: false,
        scratch_dir: Some(opts.tmp_dir.clone().unwrap_or_else(|| dir.clone())),
    };
    let mut failure = None;
    summary.v1_file_bytes = Some(summary.file_bytes);
    let written = write_atomic(
        &opts.output,
        opts.force,
        |w| match dagfmt::v2file::upgrade_to(&dag, &options, w) {
            Ok(spill) => {
                summary.encoder_spill = Some(spill);
                Ok(())
            }
            Err(dagfmt::v2file::ConvertError::Io(e)) => Err(e),
            Err(e) => {
                let message = e.to_string();
                failure = Some(e);
                Err(std::io::Error::other(message))
            }
        },
    );
    if let Some(e) = failure {
        return Err(ConvertError::Limit(format!(
            "cannot encode format 2.0: {e}"
        )));
    }
    summary.file_bytes = written?;
    drop(dag);
    drop(v1_bytes);
    drop(map);
    drop(temp);
    let upgrade = start.elapsed().as_secs_f64();
    // The peak of the whole conversion, the encoding included.
    summary.peak_rss = opts.meter.peak();
    summary.upgrade_seconds = Some(upgrade);
    summary.total_seconds += upgrade;
    Ok(summary)
}

fn convert_v1(opts: &ConvertOptions) -> Result<ConvertSummary, ConvertError> {
    let start = Instant::now();
    if let Some(r) = opts.region {
        if opts.bounds.is_none() {
            return Err(ConvertError::Usage(format!(
                "--region {r} needs --bounds: every part of one volume must have the same root cube"
            )));
        }
        if let Some(d) = opts.depth {
            r.check(d)?;
        }
    }
    check_output(&opts.output, opts.force)?;
    let meta = std::fs::metadata(&opts.input)
        .map_err(|e| ConvertError::io(format!("cannot open input {}", opts.input.display()), e))?;
    if !meta.is_file() {
        return Err(ConvertError::Input(format!(
            "input {} is not a regular file",
            opts.input.display()
        )));
    }
    // Both directories are checked before any work: the temporary files'
    // (which the check makes one of), and the output's when it differs.
    let out_dir = dagfmt::output::output_dir(&opts.output);
    let tmp_dir = opts.tmp_dir.clone().unwrap_or_else(|| out_dir.clone());
    let scratch = Scratch::new(&tmp_dir)?;
    if tmp_dir != out_dir {
        tempfile::tempfile_in(&out_dir).map_err(|e| {
            ConvertError::io(
                format!(
                    "cannot create files in output directory {}",
                    out_dir.display()
                ),
                e,
            )
        })?;
    }
    let limit = opts
        .memory_limit
        .unwrap_or_else(|| total_memory().map_or(8 << 30, |m| m / 4 * 3));
    if !(opts.point_radius >= 0.0 && opts.point_radius.is_finite()) {
        return Err(ConvertError::Usage(format!(
            "--point-radius {} is not a finite number >= 0",
            opts.point_radius
        )));
    }
    let format = detect_format(&opts.input, opts.format)?;
    let mut summary = if !opts.extra_inputs.is_empty() {
        convert_tiles(opts, limit, &scratch)?
    } else {
        match format {
            Source::VoxelList => convert_voxels(opts, limit, &scratch)?,
            Source::Registered(format) => {
                let options = crate::input::OpenOptions {
                    colors: opts.colors,
                };
                let open = || crate::input::open(&opts.input, format, &options);
                match format.name {
                    // Formats that are meshes whatever their content load after
                    // the command line's checks.
                    "obj" | "stl" | "gltf" | "glb" => {
                        let load = || match open()? {
                            crate::input::Input::Mesh(m) => Ok(*m),
                            _ => Err(ConvertError::Input("not a mesh".into())),
                        };
                        convert_mesh(opts, limit, &scratch, || {
                            if opts.cache_input {
                                cached_mesh(&opts.input, opts.colors, load)
                            } else {
                                load().map(Arc::new)
                            }
                        })?
                    }
                    _ => match open()? {
                        crate::input::Input::Mesh(m) => {
                            convert_mesh(opts, limit, &scratch, || Ok(Arc::new(*m)))?
                        }
                        crate::input::Input::Points(points) => {
                            convert_points(opts, limit, &scratch, points)?
                        }
                        crate::input::Input::Voxels(grid) => {
                            convert_grid(opts, limit, &scratch, grid)?
                        }
                    },
                }
            }
        }
    };
    summary.memory_limit = limit;
    summary.tmp_dir = tmp_dir;
    summary.temp_bytes = scratch.bytes_written();
    summary.temp_peak_bytes = scratch.peak_bytes();
    summary.total_seconds = start.elapsed().as_secs_f64();
    summary.peak_rss = opts.meter.peak();
    summary.cpu_seconds = process_cpu_seconds();
    summary.main_thread_cpu_seconds = thread_cpu_seconds();
    opts.report(ConvertProgress::Written);
    Ok(summary)
}

/// Converts several point clouds read as one (`input`, then
/// `extra_inputs`); a region build opens every cloud's header but reads only
/// those whose declared bounds, grown by the point radius, meet its cell.
fn convert_tiles(
    opts: &ConvertOptions,
    limit: u64,
    scratch: &Scratch,
) -> Result<ConvertSummary, ConvertError> {
    let options = crate::input::OpenOptions {
        colors: opts.colors,
    };
    let mut sources: Vec<Box<dyn crate::input::PointSource>> = Vec::new();
    for path in std::iter::once(&opts.input).chain(&opts.extra_inputs) {
        let format = match detect_format(path, opts.format)? {
            Source::Registered(f) => f,
            Source::VoxelList => {
                return Err(ConvertError::Usage(format!(
                    "{}: several inputs must all be point clouds (LAS, LAZ or PLY tiles), not a voxel list",
                    path.display()
                )));
            }
        };
        match crate::input::open(path, format, &options)? {
            crate::input::Input::Points(p) => sources.push(p),
            _ => {
                return Err(ConvertError::Usage(format!(
                    "{}: several inputs must all be point clouds (LAS, LAZ or PLY tiles)",
                    path.display()
                )));
            }
        }
    }
    let cell = match (opts.region, opts.bounds, opts.depth) {
        (Some(r), Some(b), Some(_)) => {
            let side = b.size / f64::from(1u32 << r.level);
            let lo = [0, 1, 2].map(|a| b.min[a] + f64::from(r.cell[a]) * side);
            Some((lo, lo.map(|c| c + side)))
        }
        _ => None,
    };
    let grow = opts.point_radius;
    let meets = move |tlo: [f64; 3], thi: [f64; 3]| {
        cell.is_none_or(|(lo, hi): ([f64; 3], [f64; 3])| {
            (0..3).all(|a| tlo[a] - grow <= hi[a] && lo[a] <= thi[a] + grow)
        })
    };
    let chain = crate::input::ChainedPoints::new(sources, Some(&meets));
    convert_points(opts, limit, scratch, Box::new(chain))
}

/// Checks the conversion's peak memory so far against the limit: loading
/// the input is the minimal working set, which the limit cannot shrink.
fn check_memory(meter: &MemoryMeter, limit: u64, what: &str) -> Result<(), ConvertError> {
    if let Some(rss) = meter.peak()
        && rss > limit
    {
        return Err(ConvertError::Limit(format!(
            "memory limit of {} exceeded (the conversion held {}) while {what}; raise --memory-limit or lower the depth",
            human_bytes(limit),
            human_bytes(rss)
        )));
    }
    Ok(())
}

/// Room left for allocator slack, thread stacks and whatever the estimates
/// miss (the conversion's, the merge's and the upgrade's budgets).
pub(crate) fn margin(limit: u64) -> u64 {
    (limit / 16).max(24 << 20)
}

/// How the memory limit is shared out once the input is loaded.
#[derive(Clone, Copy, Debug)]
struct MemoryPlan {
    /// Bytes the in-memory DAG builder may hold before a run is spilled.
    run_budget: u64,
    /// Bytes of colours kept in memory before they go to a temporary file.
    colour_cap: u64,
}

/// Shares out `limit`: `fixed` is what the conversion holds whatever the DAG
/// (the resident memory once the input is loaded, the voxelization buffers,
/// the solid fill's column state), with `what` saying what it is made of.
fn plan_memory(
    limit: u64,
    fixed: u64,
    what: &str,
    colors: bool,
) -> Result<MemoryPlan, ConvertError> {
    let colour_cap = if colors {
        (limit / 16).clamp(1 << 20, 256 << 20)
    } else {
        0
    };
    let needed = fixed + colour_cap + margin(limit) + MIN_RUN_BUDGET;
    if needed > limit {
        let colours = if colors {
            format!(", {} of colours", human_bytes(colour_cap))
        } else {
            String::new()
        };
        return Err(ConvertError::Limit(format!(
            "memory limit of {} is below the minimal working set of {} ({what}{colours}, {} for the DAG builder and a margin of {}); raise --memory-limit",
            human_bytes(limit),
            human_bytes(needed),
            human_bytes(MIN_RUN_BUDGET),
            human_bytes(margin(limit)),
        )));
    }
    Ok(MemoryPlan {
        run_budget: limit - fixed - colour_cap - margin(limit),
        colour_cap,
    })
}

/// The settings of the DAG sink for a conversion at `depth`.
fn spill_settings(
    opts: &ConvertOptions,
    depth: u8,
    run_budget: u64,
) -> Result<SpillSettings, ConvertError> {
    let default_split = u32::from(depth).saturating_sub(SPLIT_BITS) as u8;
    match opts.forced_spill {
        None => Ok(SpillSettings {
            split_level: default_split,
            run_budget,
            cells_per_run: None,
            buckets: None,
        }),
        Some(f) => {
            let split = f.split_level.unwrap_or(default_split.max(1));
            if depth < 3 || !(1..=depth - 2).contains(&split) {
                return Err(ConvertError::Usage(format!(
                    "--spill-split-level {split} is outside 1..={} for depth {depth}",
                    depth.saturating_sub(2)
                )));
            }
            if f.cells_per_run == Some(0) || f.buckets == Some(0) {
                return Err(ConvertError::Usage(
                    "--spill-cells-per-run and --spill-buckets must be at least 1".into(),
                ));
            }
            Ok(SpillSettings {
                split_level: split,
                run_budget,
                cells_per_run: Some(f.cells_per_run.unwrap_or(1)),
                buckets: f.buckets,
            })
        }
    }
}

/// What the merge of spilled runs may use: the limit less what the
/// conversion holds once the voxelization's memory is freed.
fn merge_budget(meter: &MemoryMeter, limit: u64) -> u64 {
    limit.saturating_sub(meter.resident().unwrap_or(0) + margin(limit))
}

fn write_output(
    opts: &ConvertOptions,
    dag: &FinishedDag,
    colors: Option<&Colours>,
    header: FileHeader,
    summary: &mut ConvertSummary,
) -> Result<(), ConvertError> {
    let t = Instant::now();
    let placement = opts.region.map(|r| Placement {
        level: r.level,
        cells: r.index()..r.index() + 1,
        colours: ColourMode::of(colors.is_some(), opts.color_error),
    });
    summary.file_bytes = match opts.v1_in_memory.as_ref().filter(|_| placement.is_none()) {
        Some(slot) => {
            let (layout, emit) = dag_file(dag, colors, header, None)?;
            let limit = opts
                .memory_limit
                .unwrap_or_else(|| total_memory().map_or(8 << 30, |m| m / 4 * 3));
            let resident = opts.meter.resident().unwrap_or(0);
            if resident.saturating_add(layout.file_size()) + margin(limit) <= limit {
                let mut bytes = Vec::with_capacity(layout.file_size() as usize);
                layout
                    .write_to(&mut bytes, emit)
                    .map_err(|e| ConvertError::io("cannot assemble the 1.0 file in memory", e))?;
                let len = bytes.len() as u64;
                *slot.lock().unwrap_or_else(|e| e.into_inner()) = Some(bytes);
                len
            } else {
                write_atomic(&opts.output, opts.force, |w| layout.write_to(w, emit))?
            }
        }
        None => write_dag(
            &opts.output,
            opts.force,
            dag,
            colors,
            header,
            placement.as_ref(),
        )?,
    };
    summary.write_seconds = t.elapsed().as_secs_f64();
    summary.voxels = dag.voxel_count();
    summary.levels = dag.level_stats();
    summary.spill = dag.report().clone();
    summary.colors_spilled = colors.is_some_and(Colours::spilled);
    summary.colors_packed = colors.and_then(Colours::packed);
    Ok(())
}

/// Writes a finished DAG, its colours and, for a part, its placement
/// (spec § 24) atomically to `path`; returns the bytes written.
pub(crate) fn write_dag(
    path: &Path,
    force: bool,
    dag: &FinishedDag,
    colors: Option<&Colours>,
    header: FileHeader,
    placement: Option<&Placement>,
) -> Result<u64, ConvertError> {
    let (layout, emit) = dag_file(dag, colors, header, placement)?;
    write_atomic(path, force, |w| layout.write_to(w, emit))
}

/// What a section's bytes are handed to.
type Sink<'s> = &'s mut dyn FnMut(&[u8]) -> std::io::Result<()>;

/// Hands section `index`'s bytes to a sink (for [`FileLayout::write_to`]).
type SectionEmitter<'a> = Box<dyn FnMut(usize, Sink<'_>) -> std::io::Result<()> + 'a>;

/// The layout of the file of a finished DAG, its colours and, for a part,
/// its placement, with the function that hands section `index`'s bytes to
/// a sink (for [`FileLayout::write_to`]).
fn dag_file<'a>(
    dag: &'a FinishedDag,
    colors: Option<&'a Colours>,
    header: FileHeader,
    placement: Option<&'a Placement>,
) -> Result<(FileLayout, SectionEmitter<'a>), ConvertError> {
    let mut sections = dag.level_sections();
    let levels = sections.len();
    sections.extend(colors.map(Colours::section));
    let coloured = sections.len();
    sections.extend(placement.map(Placement::section));
    let layout = FileLayout::new(header, sections).map_err(build_error)?;
    let emit = Box::new(move |index: usize, sink: Sink<'_>| {
        if index < levels {
            dag.emit_level(index, sink)
        } else if index < coloured {
            colors.expect("a colour section").emit(sink)
        } else {
            sink(&placement.expect("a placement").to_bytes())
        }
    });
    Ok((layout, emit))
}

/// The Morton codes of the voxels a conversion keeps: those of the region,
/// or all (`None`). Checks the region against the depth.
fn kept_codes(opts: &ConvertOptions, depth: u8) -> Result<Option<Range<u64>>, ConvertError> {
    match opts.region {
        None => Ok(None),
        Some(r) => {
            r.check(depth)?;
            Ok(Some(r.voxel_codes(depth)))
        }
    }
}

/// The colour packing of a conversion: parts keep raw colours, packed only
/// when the parts are joined (the packing of a block must see the whole
/// volume's colours in order).
fn colour_error(opts: &ConvertOptions) -> Option<u8> {
    if opts.region.is_some() {
        None
    } else {
        opts.color_error
    }
}

fn convert_voxels(
    opts: &ConvertOptions,
    limit: u64,
    scratch: &Scratch,
) -> Result<ConvertSummary, ConvertError> {
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
    check_memory(&opts.meter, limit, "reading the voxel list")?;
    let resident = opts.meter.resident().unwrap_or(0);
    let plan = plan_memory(
        limit,
        resident,
        &format!("{} resident with the voxel list", human_bytes(resident)),
        false,
    )?;
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
        run_budget: plan.run_budget,
        ..Default::default()
    };
    let t = Instant::now();
    let settings = spill_settings(opts, list.depth, plan.run_budget)?;
    let mut sink = DagSink::new(list.depth, opts.attributes, settings, scratch)?;
    let kept = kept_codes(opts, list.depth)?;
    let mut i = 0;
    while i < list.codes.len() {
        let brick = list.codes[i] >> 6;
        let mut mask = 0u64;
        while i < list.codes.len() && list.codes[i] >> 6 == brick {
            mask |= 1 << (list.codes[i] & 63);
            i += 1;
        }
        if kept.as_ref().is_none_or(|k| k.contains(&(brick << 6))) {
            sink.push_brick(brick, mask)?;
        }
    }
    drop(list);
    let spinner = merge_spinner(opts);
    let dag = sink.finish(|| merge_budget(&opts.meter, limit), &|m| {
        spinner.set_message(m.to_string())
    })?;
    spinner.finish_and_clear();
    summary.build_seconds = t.elapsed().as_secs_f64();
    let header = FileHeader {
        depth: summary.depth,
        attributes: opts.attributes,
        root_min: summary.root_min,
        root_size: summary.root_size,
        voxel_count: dag.voxel_count(),
    };
    write_output(opts, &dag, None, header, &mut summary)?;
    Ok(summary)
}

/// Writes the empty volume of `depth` for a mesh without triangles: no
/// bounding box to fit, so the root cube is the unit cube at the origin.
fn convert_empty_mesh(
    opts: &ConvertOptions,
    depth: u8,
    triangles: usize,
    scratch: &Scratch,
) -> Result<ConvertSummary, ConvertError> {
    let mut summary = ConvertSummary {
        input: format!("{}: {triangles} triangles", opts.input.display()),
        fill: "none: the mesh has no triangles".into(),
        depth,
        root_min: [0.0; 3],
        root_size: 1.0,
        ..Default::default()
    };
    summary.warnings.push(
        "the mesh has no triangles: the file holds the empty volume (root cube [0, 1]^3)".into(),
    );
    kept_codes(opts, depth)?;
    let settings = spill_settings(opts, depth, 0)?;
    let sink = DagSink::new(depth, opts.attributes, settings, scratch)?;
    let dag = sink.finish(|| 0, &|_| {})?;
    let header = FileHeader {
        depth,
        attributes: opts.attributes,
        root_min: summary.root_min,
        root_size: summary.root_size,
        voxel_count: 0,
    };
    write_output(opts, &dag, None, header, &mut summary)?;
    Ok(summary)
}

/// The colours of a chunk's voxels (RGBA8, in the order of its tags) when the
/// mesh has textures: each tagged voxel's colour at its centre
/// ([`Mesh::voxel_color`]), white for the voxels of the solid fill.
fn textured_colors(
    mesh: &Mesh,
    out: &ChunkOutput,
    shift: u32,
    root_min: [f64; 3],
    voxel_size: f64,
) -> Vec<u8> {
    let mut rgba = Vec::with_capacity(out.tags.len() * 4);
    // The tags follow the bricks' set bits in Morton order.
    let mut tags = out.tags.iter();
    for &(brick, mask) in &out.bricks {
        let code = ((out.code << shift) | u64::from(brick)) << 6;
        let mut bits = mask;
        while bits != 0 {
            let voxel = dagfmt::morton::decode(code | u64::from(bits.trailing_zeros()));
            bits &= bits - 1;
            let Some(&t) = tags.next() else {
                return rgba;
            };
            rgba.extend_from_slice(&if t == NO_TAG {
                DEFAULT_COLOR
            } else {
                let centre =
                    [0, 1, 2].map(|a| root_min[a] + (f64::from(voxel[a]) + 0.5) * voxel_size);
                mesh.voxel_color(t as usize, centre, voxel_size)
            });
        }
    }
    rgba
}

fn convert_mesh(
    opts: &ConvertOptions,
    limit: u64,
    scratch: &Scratch,
    load: impl FnOnce() -> Result<Arc<Mesh>, ConvertError>,
) -> Result<ConvertSummary, ConvertError> {
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
    // Checked before any work, like the rest of the command line.
    spill_settings(opts, depth, 0)?;
    let t = Instant::now();
    let mesh = load()?;
    let parse_seconds = t.elapsed().as_secs_f64();
    if mesh.triangles.is_empty() {
        // An empty volume (spec/VDAG.md § 7), not an error: a tile of a larger
        // scene is often empty.
        return convert_empty_mesh(opts, depth, mesh.triangles.len(), scratch);
    }
    let check = mesh.check()?;
    let mapping = match opts.bounds {
        None => GridMapping::fit(check.min, check.max, depth)?,
        Some(b) => {
            let max = [0, 1, 2].map(|a| b.min[a] + b.size);
            if (0..3).any(|a| check.min[a] < b.min[a] || check.max[a] > max[a]) {
                return Err(ConvertError::Input(format!(
                    "the mesh (bounding box {:?} to {:?}) extends beyond --bounds (cube {:?} to {max:?}); \
                     meshes are not clipped",
                    check.min, check.max, b.min
                )));
            }
            GridMapping {
                depth,
                root_min: b.min,
                root_size: b.size,
            }
        }
    };
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
    if opts.colors {
        for w in &mesh.texture_warnings {
            summary
                .warnings
                .push(format!("{w}; its voxels take the material's Kd"));
        }
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
    // The column parity state holds one bit per voxel column of the
    // projected area, per axis; the chunk walk visits every chunk.
    let solid_state = if solid == SolidMode::Surface {
        0
    } else {
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
        state
    };
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
    let kept = kept_codes(opts, depth)?;
    let t_bin = Instant::now();
    // A surface chunk's voxels depend on its triangles only: a region bins
    // the triangles into the chunks of its cell alone and voxelizes those.
    // (The solid fill carries parity from chunk to chunk, so it bins and
    // voxelizes every chunk and keeps the region's bricks below.)
    let within = match (opts.region, solid) {
        (Some(r), SolidMode::Surface) => Some(region_chunks(r, depth, chunk_bits)),
        _ => None,
    };
    let mut bins = Bins::new_within(&snapped, depth, chunk_bits, within);
    if let (Some(k), SolidMode::Surface) = (&kept, solid) {
        // Every chunk of the box meets the cell; this keeps that so.
        bins.retain(|code| {
            let first = code << (3 * chunk_bits);
            first < k.end && first + (1 << (3 * chunk_bits)) > k.start
        });
    }
    let kept_bricks = kept.map(|k| (k.start >> 6)..(k.end >> 6));
    summary.bin_entries = bins.len() as u64;
    summary.bin_seconds = t_bin.elapsed().as_secs_f64();
    summary.parse_seconds = parse_seconds;
    summary.load_seconds = t.elapsed().as_secs_f64();
    check_memory(&opts.meter, limit, "binning triangles")?;

    let t = Instant::now();
    let threads = rayon::current_num_threads();
    // Worst-case bytes of one chunk on its way to the builder: its bricks
    // (code and mask) and, with colours, a triangle tag per voxel.
    let chunk_bytes = (1u64 << (3 * (chunk_bits - 2))) * 16
        + if opts.colors {
            4u64 << (3 * chunk_bits)
        } else {
            0
        };
    // Up to four batches are alive at once (one being voxelized, two queued,
    // one being consumed), plus a chunk buffer per thread: at most 1/32 of
    // the limit, or one chunk per thread when even that is more.
    let batch = ((limit / 128 / chunk_bytes.max(1)) as usize).clamp(threads, 8 * threads);
    // Chunks that go through the pipeline: those with triangles, and with
    // --solid possibly every chunk of the volume.
    let chunks = if solid == SolidMode::Surface {
        bins.codes.len() as u64
    } else {
        1u64 << (3 * (u32::from(depth) - chunk_bits))
    };
    let pipeline_bytes =
        (4 * batch as u64 + threads as u64).min(chunks + threads as u64) * chunk_bytes;
    let resident = opts.meter.resident().unwrap_or(0);
    let plan = plan_memory(
        limit,
        resident + pipeline_bytes + solid_state,
        &format!(
            "{} resident with the mesh and its triangle bins, {} of voxelization buffers, {} of solid fill state",
            human_bytes(resident),
            human_bytes(pipeline_bytes),
            human_bytes(solid_state)
        ),
        opts.colors,
    )?;
    summary.run_budget = plan.run_budget;
    let cfg = VoxelizeConfig {
        depth,
        chunk_bits,
        solid,
        tags: opts.colors,
        batch,
    };
    let settings = spill_settings(opts, depth, plan.run_budget)?;
    let mut sink = DagSink::new(depth, opts.attributes, settings, scratch)?;
    let mut colors = opts
        .colors
        .then(|| ColourSink::new(scratch, plan.colour_cap, colour_error(opts)));
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
    let voxel_size = mapping.root_size / (1u64 << depth) as f64;
    let mut rgba: Vec<u8> = Vec::new();
    let report = pipeline::run(
        &snapped,
        &bins,
        &cfg,
        &|done| {
            bar.set_position(done);
            opts.report(ConvertProgress::Voxelizing {
                done,
                total: bins.codes.len() as u64,
            });
        },
        |outs: Vec<ChunkOutput>| -> Result<(), ConvertError> {
            // Textured colours need a closest point per voxel: found for the
            // batch's chunks in parallel, written below in order.
            let textured: Vec<Vec<u8>> = if colors.is_some() && mesh.has_textures() {
                outs.par_iter()
                    .map(|out| textured_colors(&mesh, out, shift, mapping.root_min, voxel_size))
                    .collect()
            } else {
                Vec::new()
            };
            for (i, out) in outs.iter().enumerate() {
                let base = out.code << shift;
                let whole = kept_bricks
                    .as_ref()
                    .is_none_or(|k| k.start <= base && base + (1 << shift) <= k.end);
                let kept = |brick: u32| {
                    kept_bricks
                        .as_ref()
                        .is_none_or(|k| k.contains(&(base | u64::from(brick))))
                };
                for &(brick, mask) in &out.bricks {
                    if whole || kept(brick) {
                        sink.push_brick(base | u64::from(brick), mask)?;
                    }
                }
                if let Some(colors) = &mut colors {
                    let chunk: &[u8] = match textured.get(i) {
                        Some(part) => part,
                        None => {
                            rgba.clear();
                            for &t in &out.tags {
                                rgba.extend_from_slice(&if t == NO_TAG {
                                    DEFAULT_COLOR
                                } else {
                                    mesh.triangle_color(t as usize)
                                });
                            }
                            &rgba
                        }
                    };
                    if whole {
                        colors.write(chunk)?;
                    } else {
                        // The colours follow the bricks' set voxels in order.
                        let mut at = 0;
                        for &(brick, mask) in &out.bricks {
                            let n = 4 * mask.count_ones() as usize;
                            if kept(brick) {
                                colors.write(&chunk[at..at + n])?;
                            }
                            at += n;
                        }
                    }
                }
            }
            let runs = sink.runs();
            if runs > 0 {
                bar.set_message(format!("({runs} runs spilled)"));
            }
            Ok(())
        },
    );
    bar.finish_and_clear();
    let report = report?;
    summary.surface_chunks = report.surface_chunks;
    summary.threads = threads;
    summary.fill_chunks = report.fill_chunks;
    // The mesh and the bins are not needed any more: free them for the merge.
    drop(rgba);
    drop(bins);
    drop(snapped);
    drop(mesh);
    let colors = colors.map(ColourSink::finish).transpose()?;
    let spinner = merge_spinner(opts);
    let dag = sink.finish(|| merge_budget(&opts.meter, limit), &|m| {
        spinner.set_message(m.to_string())
    })?;
    spinner.finish_and_clear();
    summary.build_seconds = t.elapsed().as_secs_f64();
    let header = FileHeader {
        depth,
        attributes: opts.attributes,
        root_min: mapping.root_min,
        root_size: mapping.root_size,
        voxel_count: dag.voxel_count(),
    };
    write_output(opts, &dag, colors.as_ref(), header, &mut summary)?;
    Ok(summary)
}

/// The chunks (inclusive chunk coordinates, chunks of `2^chunk_bits`
/// voxels) that meet the cell of `region` at depth `depth`: the cell's
/// chunks, or the one chunk holding a cell smaller than a chunk.
fn region_chunks(region: Region, depth: u8, chunk_bits: u32) -> ([i64; 3], [i64; 3]) {
    let levels = u32::from(depth) - chunk_bits;
    let k = u32::from(region.level);
    let cell = region.cell.map(i64::from);
    if k <= levels {
        let s = levels - k;
        (cell.map(|c| c << s), cell.map(|c| ((c + 1) << s) - 1))
    } else {
        let c = cell.map(|c| c >> (k - levels));
        (c, c)
    }
}

/// Feeds sorted (code, colour) voxels to the DAG builder and, with colours,
/// the colour sink; returns the finished DAG and colours.
fn build_sorted(
    opts: &ConvertOptions,
    limit: u64,
    scratch: &Scratch,
    depth: u8,
    run_budget: u64,
    colour_cap: Option<u64>,
    voxels: SortedVoxels,
) -> Result<(FinishedDag, Option<Colours>), ConvertError> {
    let settings = spill_settings(opts, depth, run_budget)?;
    let mut sink = DagSink::new(depth, opts.attributes, settings, scratch)?;
    let mut colors = colour_cap.map(|cap| ColourSink::new(scratch, cap, opts.color_error));
    let mut rgba: Vec<u8> = Vec::new();
    let mut brick = None;
    let mut mask = 0u64;
    let kept = kept_codes(opts, depth)?;
    for v in voxels {
        let (code, colour) = v?;
        if kept.as_ref().is_some_and(|k| !k.contains(&code)) {
            continue;
        }
        if brick != Some(code >> 6) {
            if let Some(b) = brick {
                sink.push_brick(b, mask)?;
            }
            brick = Some(code >> 6);
            mask = 0;
        }
        mask |= 1 << (code & 63);
        if let Some(colors) = &mut colors {
            rgba.extend_from_slice(&colour.to_le_bytes());
            if rgba.len() >= 1 << 16 {
                colors.write(&rgba)?;
                rgba.clear();
            }
        }
    }
    if let Some(b) = brick {
        sink.push_brick(b, mask)?;
    }
    let colors = match colors {
        Some(mut c) => {
            c.write(&rgba)?;
            Some(c.finish()?)
        }
        None => None,
    };
    let spinner = merge_spinner(opts);
    let dag = sink.finish(|| merge_budget(&opts.meter, limit), &|m| {
        spinner.set_message(m.to_string())
    })?;
    spinner.finish_and_clear();
    Ok((dag, colors))
}

/// Points read per batch.
const POINT_BATCH: usize = 1 << 16;

fn convert_points(
    opts: &ConvertOptions,
    limit: u64,
    scratch: &Scratch,
    mut points: Box<dyn crate::input::PointSource>,
) -> Result<ConvertSummary, ConvertError> {
    let depth = opts.depth.ok_or_else(|| {
        ConvertError::Usage("converting a point cloud needs --depth D or --resolution N".into())
    })?;
    if opts.solid {
        return Err(ConvertError::Usage(
            "--solid needs a mesh input, not a point cloud".into(),
        ));
    }
    spill_settings(opts, depth, 0)?;
    let t = Instant::now();
    let radius = opts.point_radius;
    let mut batch = Vec::with_capacity(POINT_BATCH);
    // The root cube: given, or fitted (like a mesh's) to the points' box
    // grown by the radius: the header's box (LAS) or a first pass.
    let (root_min, root_size) = match opts.bounds {
        Some(b) => (b.min, b.size),
        None => {
            let (lo, hi) = match points.declared_bounds() {
                Some(b) => b,
                None => {
                    let mut lo = [f64::INFINITY; 3];
                    let mut hi = [f64::NEG_INFINITY; 3];
                    loop {
                        batch.clear();
                        if points.read(&mut batch, POINT_BATCH)? == 0 {
                            break;
                        }
                        for p in &batch {
                            for a in 0..3 {
                                lo[a] = lo[a].min(p.position[a]);
                                hi[a] = hi[a].max(p.position[a]);
                            }
                        }
                    }
                    points.rewind()?;
                    (lo, hi)
                }
            };
            if points.count() == 0 || !(0..3).all(|a| lo[a] <= hi[a]) {
                return Err(ConvertError::Input("the point cloud has no points".into()));
            }
            let lo = lo.map(|c| c - radius);
            let hi = hi.map(|c| c + radius);
            // A single point (or a flat cloud) still gets a cube.
            let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
            let (lo, hi) = if extent > 0.0 {
                (lo, hi)
            } else {
                (lo.map(|c| c - 0.5), hi.map(|c| c + 0.5))
            };
            let m = GridMapping::fit(lo, hi, depth)?;
            (m.root_min, m.root_size)
        }
    };
    let splat = Splat {
        root_min,
        root_size,
        depth,
        radius,
    };
    let colored = opts.colors && points.has_colors();
    let resident = opts.meter.resident().unwrap_or(0);
    // A quarter of the limit sorts the voxels; the DAG builder gets the rest.
    let sort_bytes = (limit / 4).max(16 << 20);
    let plan = plan_memory(
        limit,
        resident + sort_bytes,
        &format!(
            "{} resident, {} to sort the points' voxels",
            human_bytes(resident),
            human_bytes(sort_bytes)
        ),
        colored,
    )?;
    let mut sorter = VoxelSorter::new(scratch, sort_bytes);
    let kept = kept_codes(opts, depth)?;
    let mut read = 0u64;
    let mut outside = 0u64;
    let mut codes: Vec<Vec<(u64, u32)>> = Vec::new();
    loop {
        batch.clear();
        let n = points.read(&mut batch, POINT_BATCH)?;
        if n == 0 {
            break;
        }
        read += n as u64;
        // The batch's voxels in parallel, in order.
        codes.clear();
        batch
            .par_chunks(4096)
            .map(|chunk| {
                let mut out = Vec::with_capacity(chunk.len());
                let mut missed = 0u64;
                for p in chunk {
                    let rgba = u32::from_le_bytes(if colored { p.rgba } else { DEFAULT_COLOR });
                    if !splat.voxels(p.position, |v| {
                        out.push((dagfmt::morton::encode(v[0], v[1], v[2]), rgba));
                    }) {
                        missed += 1;
                    }
                }
                (out, missed)
            })
            .collect::<Vec<_>>()
            .into_iter()
            .for_each(|(out, missed)| {
                outside += missed;
                codes.push(out);
            });
        // A region sorts only its cell's voxels (the build keeps no other).
        for part in &codes {
            for &(code, rgba) in part {
                if kept.as_ref().is_none_or(|k| k.contains(&code)) {
                    sorter.push(code, rgba)?;
                }
            }
        }
    }
    if read != points.count() {
        return Err(ConvertError::Input(format!(
            "the point cloud declares {} points but has {read}",
            points.count()
        )));
    }
    // (A region build that read no tile, none meeting its cell, is an
    // empty part.)
    if outside == read && !(read == 0 && opts.region.is_some() && !opts.extra_inputs.is_empty()) {
        return Err(ConvertError::Input(format!(
            "all {read} points lie outside the root cube"
        )));
    }
    let mut summary = ConvertSummary {
        input: format!(
            "{}: {}{}",
            opts.input.display(),
            points.describe(),
            if radius > 0.0 {
                format!(", each a ball of radius {radius}")
            } else {
                String::new()
            }
        ),
        fill: if radius > 0.0 {
            format!("points: every voxel within {radius} of a point")
        } else {
            "points: the voxel containing each point".into()
        },
        depth,
        root_min,
        root_size,
        load_seconds: t.elapsed().as_secs_f64(),
        run_budget: plan.run_budget,
        ..Default::default()
    };
    if outside > 0 {
        summary.warnings.push(format!(
            "{outside} of {read} points lie outside --bounds and were skipped"
        ));
    }
    if opts.colors && !colored {
        summary
            .warnings
            .push("the points have no colours; voxels are white".into());
    }
    drop(batch);
    drop(codes);
    let sorted = sorter.finish()?;
    let t = Instant::now();
    let (dag, colors) = build_sorted(
        opts,
        limit,
        scratch,
        depth,
        plan.run_budget,
        colored.then_some(plan.colour_cap),
        sorted,
    )?;
    summary.build_seconds = t.elapsed().as_secs_f64();
    let header = FileHeader {
        depth,
        attributes: opts.attributes,
        root_min,
        root_size,
        voxel_count: dag.voxel_count(),
    };
    write_output(opts, &dag, colors.as_ref(), header, &mut summary)?;
    Ok(summary)
}

/// Converts a voxel grid (`.vox`, binvox). Without `--bounds` one input voxel
/// is one output voxel: the depth is the grid's smallest (`--depth` may only
/// ask for more, which places the same voxels in a larger root cube from
/// the same corner). With `--bounds` each input voxel sets the output voxel
/// containing its centre.
fn convert_grid(
    opts: &ConvertOptions,
    limit: u64,
    scratch: &Scratch,
    grid: crate::input::VoxelGrid,
) -> Result<ConvertSummary, ConvertError> {
    if opts.solid {
        return Err(ConvertError::Usage(
            "--solid needs a mesh input, not a voxel grid".into(),
        ));
    }
    let t = Instant::now();
    let depth = match (opts.depth, opts.bounds) {
        (Some(d), None) if d < grid.depth => {
            return Err(ConvertError::Usage(format!(
                "--depth {d} is below the input's depth {}: one input voxel is one output voxel, \
                 so the depth is at least the smallest that holds the grid (or give --bounds to resample)",
                grid.depth
            )));
        }
        (Some(d), _) => d,
        (None, None) => grid.depth,
        (None, Some(_)) => {
            return Err(ConvertError::Usage(
                "--bounds with a voxel grid needs --depth D or --resolution N".into(),
            ));
        }
    };
    spill_settings(opts, depth, 0)?;
    let colored = opts.colors && !grid.colors.is_empty();
    let (root_min, root_size) = match opts.bounds {
        Some(b) => (b.min, b.size),
        None => (grid.origin, grid.voxel_size * (1u64 << depth) as f64),
    };
    let resident = opts.meter.resident().unwrap_or(0);
    let sort_bytes = (grid.voxels.len() as u64 * 16).clamp(1 << 20, limit / 4);
    let plan = plan_memory(
        limit,
        resident + sort_bytes,
        &format!("{} resident with the voxel grid", human_bytes(resident)),
        colored,
    )?;
    let mut sorter = VoxelSorter::new(scratch, sort_bytes);
    let splat = Splat {
        root_min,
        root_size,
        depth,
        radius: 0.0,
    };
    let mut outside = 0u64;
    for (i, v) in grid.voxels.iter().enumerate() {
        let rgba = u32::from_le_bytes(if colored {
            grid.colors[i]
        } else {
            DEFAULT_COLOR
        });
        if opts.bounds.is_some() {
            let centre =
                [0, 1, 2].map(|a| grid.origin[a] + (f64::from(v[a]) + 0.5) * grid.voxel_size);
            let mut code = None;
            if splat.voxels(centre, |c| {
                code = Some(dagfmt::morton::encode(c[0], c[1], c[2]))
            }) {
                if let Some(c) = code {
                    sorter.push(c, rgba)?;
                }
            } else {
                outside += 1;
            }
        } else {
            sorter.push(dagfmt::morton::encode(v[0], v[1], v[2]), rgba)?;
        }
    }
    let mut summary = ConvertSummary {
        input: format!("{}: {}", opts.input.display(), grid.description),
        fill: if opts.bounds.is_some() {
            "voxel grid resampled: each voxel sets the output voxel containing its centre".into()
        } else {
            "voxel grid (one input voxel, one output voxel)".into()
        },
        depth,
        root_min,
        root_size,
        load_seconds: t.elapsed().as_secs_f64(),
        run_budget: plan.run_budget,
        ..Default::default()
    };
    if outside > 0 {
        summary.warnings.push(format!(
            "{outside} of {} voxels lie outside --bounds and were skipped",
            grid.voxels.len()
        ));
        if outside == grid.voxels.len() as u64 {
            return Err(ConvertError::Input(
                "every voxel lies outside --bounds".into(),
            ));
        }
    }
    if opts.colors && !colored {
        summary
            .warnings
            .push("the grid has no colours; voxels are white".into());
    }
    drop(grid);
    let t = Instant::now();
    let (dag, colors) = build_sorted(
        opts,
        limit,
        scratch,
        depth,
        plan.run_budget,
        colored.then_some(plan.colour_cap),
        sorter.finish()?,
    )?;
    summary.build_seconds = t.elapsed().as_secs_f64();
    let header = FileHeader {
        depth,
        attributes: opts.attributes,
        root_min,
        root_size,
        voxel_count: dag.voxel_count(),
    };
    write_output(opts, &dag, colors.as_ref(), header, &mut summary)?;
    Ok(summary)
}
