//! `dagtool`: convert meshes and voxel lists to `.vdag`, validate, inspect.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand, ValueEnum};
use dagtool::ConvertError;
use dagtool::cmd;
use dagtool::convert::{self, Bounds, ConvertOptions, InputFormat};
use dagtool::output::{StdoutReport, print_stdout};
use dagtool::sysinfo::parse_size;

const CONVERT_HELP: &str = "\
INPUTS
  Recognised by their first bytes, then their extension; --input-format names one.

  Wavefront OBJ (.obj): every model and group; polygons are triangulated as fans;
  points and lines become zero-area triangles. Materials (Kd, d, map_Kd) are read
  for --colors.

  glTF 2.0 (.gltf with external or data: URI buffers, .glb): every mesh instance
  of the default scene (all scenes without one), node transforms composed;
  triangles, strips and fans; u8/u16/u32 or no indices; normalized, quantized
  (KHR_mesh_quantization) and sparse accessors. --colors: baseColorFactor x
  baseColorTexture (its texCoord set, sampler wrap modes, KHR_texture_transform)
  x COLOR_0. Required extensions it does not support (Draco, meshopt, KTX2,
  WebP, ...) are refused, by name; a texture that cannot be read is an error.

  PLY (.ply, ASCII or binary, either byte order): with faces a mesh (polygons as
  fans), without a point cloud. Vertex colours red green blue [alpha] (uchar,
  ushort or float in [0, 1]) for --colors.

  STL (.stl, ASCII or binary): triangles; no colours.

  LAS 1.0-1.4 (.las) and LAZ (.laz), point formats 0-10: point clouds; RGB is
  16-bit in LAS and becomes 8-bit as round(v / 257).

  Point clouds (PLY, LAS, LAZ) are read in a stream and need --depth. Each point
  sets the voxel containing it; --point-radius R sets every voxel within R of a
  point. A voxel takes the colour of the first point (in file order) setting it.
  The voxels go through an external sort within --memory-limit (sorted runs
  spilled to temporary files), so clouds larger than memory convert.

  MagicaVoxel (.vox): every model, placed by the scene graph (nTRN translations
  and rotations, nGRP, nSHP; first frame); palette colours for --colors.
  binvox (.binvox): the occupancy grid; its translate and scale are the root
  cube. For both, one input voxel is one output voxel at the smallest depth that
  holds the grid; --depth may only be larger (the same voxels in a larger cube
  from the same corner). With --bounds each input voxel sets the output voxel
  holding its centre.

  Text voxel list (.txt, .xyz, .voxels): one voxel per line, `x y z` as unsigned
  integers; `#` starts a comment; blank lines are ignored. Without --depth the
  smallest depth holding every voxel is used.

  Binary voxel list (any extension, recognised by its magic), little-endian:
    offset 0   4 bytes   magic \"VVOX\"
    offset 4   u32       version = 1
    offset 8   u32       depth D (2..=21)
    offset 12  u64       count N
    offset 20  N x 12    records: u32 x, u32 y, u32 z (each < 2^D)
  The file is exactly 20 + 12 N bytes. Duplicates are allowed in both forms.
  Voxel lists map to the root cube min (0,0,0), size 2^D (world units = voxels).

PLACEMENT (meshes and point clouds)
  --bounds xmin,ymin,zmin,size fixes the root cube, so that tiles of one scene
  convert onto one grid: points outside it are skipped (with a warning), a mesh
  that leaves it is refused (meshes are not clipped). Without it the root cube
  is centred on the bounding box (of a point cloud: grown by the radius) with edge
  max_extent * 2^D / (2^D - 1): along the longest axis the mesh spans 2^D - 1
  voxels with half a voxel of padding on each side. It is stored in the header,
  so hit points map back to mesh coordinates. Vertices are snapped to 1/65536
  of a voxel; from there on every test is exact integer arithmetic.

VOXELIZATION
  Conservative: every voxel whose closed cube intersects a closed triangle is set
  (13-axis separating axis test, exact). Zero-area triangles count as segments
  or points. --solid also sets every voxel whose centre is inside the mesh by
  crossing parity. If every edge of the mesh (after welding equal vertices) is
  used an even number of times the mesh is closed and parity along z decides;
  otherwise inside means odd parity along at least two of the x, y and z axes.
  --solid works up to depth 16; its time grows with the interior volume (every
  interior 4^3 brick goes through the DAG builder).

ATTRIBUTES
  Nodes store subtree voxel counts (attribute kind 1). --colors adds a colour
  section: each surface voxel takes the diffuse colour (Kd, alpha from d) of
  the lowest-numbered triangle touching it; voxels with no material and
  interior voxels of --solid are white. When the material has a diffuse
  texture (map_Kd: PNG, JPEG, TGA or BMP, relative to the OBJ's folder; the last
  word of the statement, `\\` read as `/`) and the triangle has texture
  coordinates, the voxel takes the texel nearest to the texture coordinates of
  the triangle's point closest to the voxel centre (repeating outside [0, 1)),
  times Kd. The texel comes from the box-filtered mip level whose texels are
  nearest the voxel's footprint in size (voxel edge times the triangle's
  texels-per-length), so voxels larger than texels take their mean. A texture
  that cannot be read is a warning and its material keeps Kd. Colours take 4
  bytes per voxel; beyond 1/16 of --memory-limit (at most 256 MiB) they are
  streamed to a temporary file.

MEMORY, TEMPORARY FILES AND OUTPUT
  The volume is processed in chunks of 128^3 voxels in Morton order on all cores.
  --memory-limit (default: 3/4 of physical memory) sizes the work: the mesh, its
  triangle bins, the voxelization buffers and the solid fill state come first
  (a limit below them is refused before voxelizing, with what they need); the
  rest goes to the DAG builder. When the DAG's distinct nodes outgrow it, the
  build continues in runs of whole 128^3 subtrees, each written to temporary
  files, and the runs are merged level by level with exact deduplication: the
  file is the same, byte for byte, as one built in memory, whatever the limit.
  The limit bounds the conversion's own memory: its peak resident memory above
  what the process held when it started (the same as the process's peak for
  the command line; in a library or Python process, memory held or peaked at
  before the conversion is not counted).
  The summary says how many runs were spilled, how many bytes were written to
  temporary files, and the conversion's peak resident memory.
  Temporary files go to --tmp-dir (default: the output's directory); they need
  up to about three times the output's size, which the summary reports as the
  most they held at once. They are unnamed (O_TMPFILE on Linux): nothing is left
  behind on success, on error, or if the process is killed. The output is
  written to a temporary file beside it, synced and renamed: it is either
  complete or absent. An existing output is never replaced without --force.

FORMAT VERSION
  The output is format 2.0 (spec section 23; the 1.0 DAG is built as above,
  then upgraded in memory). --format-version 1 writes format 1.0 for 1.x
  readers; `dagtool upgrade` converts between them. A --region build writes a
  part, which is always format 1; `dagtool merge` writes the whole volume in
  2.0 (or 1.0 with --format-version 1).";

#[derive(Parser, Debug)]
#[command(
    name = "dagtool",
    version,
    about = "Convert meshes and voxel lists to .vdag sparse voxel DAGs; validate and inspect .vdag files"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Convert a mesh (OBJ, glTF, PLY, STL), a point cloud (PLY, LAS, LAZ),
    /// a voxel grid (MagicaVoxel, binvox) or a voxel list to a .vdag file.
    #[command(after_long_help = CONVERT_HELP)]
    Convert(ConvertArgs),
    /// Join parts (made by convert --region, or by earlier merges) into a
    /// larger part or, when they cover the whole root cube, into the .vdag one
    /// conversion of the whole input writes, byte for byte.
    Merge {
        /// The parts, in any order.
        #[arg(required = true)]
        parts: Vec<PathBuf>,
        /// The file to write.
        #[arg(short, long)]
        output: PathBuf,
        /// Memory to work in (e.g. 4G, 512M), counted as what the merge adds
        /// to the process's resident memory; default: 3/4 of physical memory.
        #[arg(long)]
        memory_limit: Option<String>,
        /// Directory of the (unnamed) temporary files; default: the output's
        /// directory.
        #[arg(long, value_name = "DIR")]
        tmp_dir: Option<PathBuf>,
        /// Testing: merge every level in this many buckets.
        #[arg(long, hide = true)]
        buckets: Option<u32>,
        /// The format version of the whole-volume file: 2 (default, as
        /// `convert` writes) or 1. A merge that does not cover the whole
        /// root cube writes a part, which is always format 1.
        #[arg(long, value_name = "1|2", default_value_t = 2, value_parser = clap::value_parser!(u16).range(1..=2))]
        format_version: u16,
        /// Replace an existing output file.
        #[arg(long)]
        force: bool,
        /// No summary.
        #[arg(short, long)]
        quiet: bool,
    },
    /// Check .vdag (or .vdag.zst) files against every rule of the format.
    /// Exit status: 0 all valid, 1 some invalid, 2 usage or I/O error.
    Validate {
        /// Files to check.
        #[arg(required = true)]
        files: Vec<PathBuf>,
        /// Print one JSON document instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Show the header, a per-level table, totals, and the size of the same
    /// voxels with 32-bit pointers, as a sparse voxel octree, in the 1.0 layout
    /// and in the SSVDAG encoding (a merge under reflections: time and memory
    /// linear in the DAG). Reads format 1.0 and 2.0 files.
    Info {
        /// The .vdag (or .vdag.zst) file.
        file: PathBuf,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Annotated listing (offset | bytes | meaning) of the header, section table
    /// and the first nodes of every level.
    Dump {
        /// The .vdag (or .vdag.zst) file.
        file: PathBuf,
        /// Records listed per level.
        #[arg(long, default_value_t = 8)]
        nodes: u64,
    },
    /// Compress a .vdag into the zstd transport form (.vdag.zst).
    Pack {
        /// The .vdag file.
        input: PathBuf,
        /// The .vdag.zst file to write.
        #[command(flatten)]
        output: OutputArg,
        /// zstd level (1..=22).
        #[arg(long, default_value_t = dagfmt::transport::DEFAULT_LEVEL)]
        level: i32,
        /// Replace an existing output file.
        #[arg(long)]
        force: bool,
    },
    /// Re-encode a file's colours (raw or packed) as a PACKED_COLORS section
    /// within a per-channel error; the geometry is copied unchanged.
    Recompress {
        /// The .vdag (or .vdag.zst) file with colours.
        input: PathBuf,
        /// The .vdag file to write.
        #[command(flatten)]
        output: OutputArg,
        /// Each channel within E of the input's colours (0..=127; 0 = lossless).
        #[arg(long, value_name = "E", default_value_t = 0, value_parser = clap::value_parser!(u8).range(0..=127))]
        color_error: u8,
        /// Replace an existing output file.
        #[arg(long)]
        force: bool,
    },
    /// Convert a .vdag (or .vdag.zst) between format 1.0 and format 2.0
    /// (spec §23): the voxels, attributes, root cube and colours stay; the
    /// levels are re-encoded. A file already of the version asked for is
    /// copied unchanged.
    Upgrade {
        /// The .vdag (or .vdag.zst) file.
        input: PathBuf,
        /// The .vdag file to write.
        #[command(flatten)]
        output: OutputArg,
        /// The format version to write: 2 (symmetry-aware, smaller) or 1
        /// (what every tracer reads today).
        #[arg(long, value_name = "1|2", default_value_t = 2, value_parser = clap::value_parser!(u16).range(1..=2))]
        format_version: u16,
        /// Replace an existing output file.
        #[arg(long)]
        force: bool,
    },
    /// Decompress a .vdag.zst transport file (and validate it).
    Unpack {
        /// The .vdag.zst file.
        input: PathBuf,
        /// The .vdag file to write.
        #[command(flatten)]
        output: OutputArg,
        /// Refuse files that would unpack to more than this many bytes (e.g. 4G).
        #[arg(long)]
        max_size: Option<String>,
        /// Replace an existing output file.
        #[arg(long)]
        force: bool,
    },
    /// Check a conversion: cast the same rays at the source mesh (obvhs) and at
    /// the DAG (CPU tracer) and compare hits. Exit status: 0 every criterion
    /// holds, 1 some criterion fails, 2 usage or I/O error.
    #[command(after_long_help = dagtool::verify::HELP)]
    Verify {
        /// The source mesh (OBJ, glTF, PLY, STL) or point cloud (PLY, LAS,
        /// LAZ), in the coordinates it was converted from.
        mesh: PathBuf,
        /// The .vdag (or .vdag.zst) file converted from it.
        file: PathBuf,
        /// Rays in all (1..=50000000): half random rays through the root cube,
        /// half camera rays.
        #[arg(long, default_value_t = 1_000_000)]
        rays: usize,
        /// Seed of the random rays and camera viewpoints.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
        /// Point clouds: the --point-radius the cloud was converted with.
        #[arg(long, value_name = "R", default_value_t = 0.0)]
        point_radius: f64,
    },
    /// The whole pipeline on a built-in scene: make a procedural mesh, convert,
    /// validate, render a PNG (GPU when an adapter exists, else CPU), and run
    /// the conformance suite. Exit status 1 when a conformance case fails.
    Demo {
        /// Directory to write into (created; only a directory made by the demo
        /// is ever written into again).
        #[arg(short, long, alias = "out", default_value = "vdag-demo")]
        output: PathBuf,
        /// Conversion depth.
        #[arg(long, default_value_t = 10)]
        depth: u32,
        /// Image width.
        #[arg(long, default_value_t = 960)]
        width: u32,
        /// Image height.
        #[arg(long, default_value_t = 540)]
        height: u32,
        /// Use the CPU tracer even when a GPU adapter exists.
        #[arg(long)]
        cpu: bool,
    },
}

/// The output file of `pack` and `unpack`: `-o/--output FILE`, as for every
/// command that writes a file. The second positional argument of earlier
/// versions still works (hidden from the help).
#[derive(Args, Debug)]
struct OutputArg {
    /// The file to write.
    #[arg(short, long, value_name = "FILE", conflicts_with = "positional")]
    output: Option<PathBuf>,
    /// The file to write (the older spelling, kept working).
    #[arg(hide = true, value_name = "OUTPUT")]
    positional: Option<PathBuf>,
}

impl OutputArg {
    /// The output path, however it was given.
    fn path(self) -> Result<PathBuf, ConvertError> {
        self.output.or(self.positional).ok_or_else(|| {
            ConvertError::Usage("the output file is missing: give -o/--output FILE".into())
        })
    }
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum AttributesArg {
    /// Attribute kind 1: each node's subtree voxel count.
    Counts,
    /// Attribute kind 0: no attributes (zero bits).
    None,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
enum FormatArg {
    /// From the magic and the extension.
    Auto,
    /// Wavefront OBJ.
    Obj,
    /// glTF 2.0, JSON (.gltf).
    Gltf,
    /// glTF 2.0, binary (.glb).
    Glb,
    /// PLY mesh or point cloud.
    Ply,
    /// STL mesh, ASCII or binary.
    Stl,
    /// LAS or LAZ point cloud.
    Las,
    /// MagicaVoxel .vox.
    Vox,
    /// binvox voxel grid.
    Binvox,
    /// Text or binary voxel list.
    Voxels,
}

#[derive(Args, Debug)]
struct ConvertArgs {
    /// Input: a mesh (.obj .gltf .glb .ply .stl), a point cloud (.ply .las
    /// .laz), a voxel grid (.vox .binvox) or a text/binary voxel list; or
    /// several point clouds (tiles), read as one in this order.
    #[arg(required = true, num_args = 1..)]
    input: Vec<PathBuf>,
    /// Output .vdag file.
    #[arg(short, long)]
    output: PathBuf,
    /// Depth D (2..=21): 2^D voxels per axis.
    #[arg(short, long, conflicts_with = "resolution")]
    depth: Option<u32>,
    /// Resolution N = 2^D voxels per axis (a power of two, 4..=2097152).
    #[arg(short, long)]
    resolution: Option<u64>,
    /// Fill the interior (see below for open meshes).
    #[arg(long)]
    solid: bool,
    /// Store per-voxel colours (materials, textures, vertex, point and palette colours).
    #[arg(long)]
    colors: bool,
    /// What the nodes' 24 attribute bits hold: `counts` (attribute kind 1,
    /// subtree voxel counts, which index colours) or `none` (kind 0, zero).
    #[arg(long, value_enum, default_value_t = AttributesArg::Counts, conflicts_with = "colors")]
    attributes: AttributesArg,
    /// The format version to write: 2 (default; spec §23: symmetry-aware
    /// records, about half the size of 1.0; every reader and tracer of this
    /// suite reads it, `dagtrace render --shade lit` lights it on the CPU)
    /// or 1 (what 1.x readers elsewhere read; `dagtool upgrade` converts
    /// between them). A --region build writes a part, which is always
    /// format 1; `dagtool merge` writes the whole volume in 2.0 (default).
    #[arg(long, value_name = "1|2", value_parser = clap::value_parser!(u16).range(1..=2))]
    format_version: Option<u16>,
    /// With --colors: store them packed (a PACKED_COLORS section, about a
    /// tenth of the raw size), each channel within E of the source (0..=127;
    /// 0 = lossless). Without it colours are stored raw, 4 bytes per voxel.
    #[arg(long, value_name = "E", requires = "colors", value_parser = clap::value_parser!(u8).range(0..=127))]
    color_error: Option<u8>,
    /// Input format.
    #[arg(long, value_enum, default_value_t = FormatArg::Auto)]
    input_format: FormatArg,
    /// The root cube, instead of one fitted to the input: its minimum corner
    /// and edge in the input's units, so that tiles of one scene convert
    /// onto one grid.
    #[arg(long, value_name = "XMIN,YMIN,ZMIN,SIZE", allow_hyphen_values = true)]
    bounds: Option<String>,
    /// Point clouds: set every voxel within this distance (input units) of
    /// a point, not only the voxel containing it.
    #[arg(long, value_name = "R", default_value_t = 0.0)]
    point_radius: f64,
    /// Build only cell X,Y,Z of level K of the root cube (each in 0..2^K,
    /// K <= D-2) into a part for `dagtool merge`; needs --bounds.
    #[arg(long, value_name = "K:X,Y,Z")]
    region: Option<String>,
    /// Memory to work in (e.g. 4G, 512M), counted as what the conversion adds
    /// to the process's resident memory: beyond it the DAG is built in runs
    /// spilled to temporary files; default: 3/4 of physical memory.
    #[arg(long)]
    memory_limit: Option<String>,
    /// Directory of the (unnamed) temporary files; default: the output's
    /// directory.
    #[arg(long, value_name = "DIR")]
    tmp_dir: Option<PathBuf>,
    /// Testing: spill whatever the memory, with subtrees rooted at this level.
    #[arg(long, hide = true)]
    spill_split_level: Option<u8>,
    /// Testing: spill whatever the memory, after this many subtrees per run.
    #[arg(long, hide = true)]
    spill_cells_per_run: Option<u64>,
    /// Testing: spill whatever the memory, merging in this many buckets.
    #[arg(long, hide = true)]
    spill_buckets: Option<u32>,
    /// Chunk side as log2 of voxels (2..=7; default 7 = 128^3). The output
    /// does not depend on it.
    #[arg(long)]
    chunk_bits: Option<u32>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Replace an existing output file.
    #[arg(long)]
    force: bool,
    /// No progress bar and no summary.
    #[arg(short, long)]
    quiet: bool,
}

fn format_of(arg: FormatArg) -> InputFormat {
    let named = |name: &str| {
        InputFormat::Named(dagtool::input::by_name(name).expect("every format is registered"))
    };
    match arg {
        FormatArg::Auto => InputFormat::Auto,
        FormatArg::Obj => named("obj"),
        FormatArg::Gltf => named("gltf"),
        FormatArg::Glb => named("glb"),
        FormatArg::Ply => named("ply"),
        FormatArg::Stl => named("stl"),
        FormatArg::Las => named("las"),
        FormatArg::Vox => named("vox"),
        FormatArg::Binvox => named("binvox"),
        FormatArg::Voxels => InputFormat::Voxels,
    }
}

fn convert_cmd(args: ConvertArgs) -> Result<(), ConvertError> {
    let depth = match (args.depth, args.resolution) {
        (Some(d), _) => Some(convert::check_depth(d)?),
        (None, Some(r)) => Some(convert::depth_of_resolution(r)?),
        (None, None) => None,
    };
    let memory_limit = match &args.memory_limit {
        Some(s) => Some(parse_size(s).ok_or_else(|| {
            ConvertError::Usage(format!(
                "--memory-limit {s} is not a size such as 4G or 512M"
            ))
        })?),
        None => None,
    };
    let mut opts = ConvertOptions::new(&args.input[0], &args.output, depth);
    opts.extra_inputs = args.input[1..].to_vec();
    opts.format = format_of(args.input_format);
    opts.bounds = args.bounds.as_deref().map(Bounds::parse).transpose()?;
    opts.point_radius = args.point_radius;
    opts.region = args
        .region
        .as_deref()
        .map(dagtool::region::Region::parse)
        .transpose()?;
    opts.solid = args.solid;
    opts.colors = args.colors;
    opts.attributes = match args.attributes {
        AttributesArg::Counts => dagfmt::AttributeKind::VoxelCount,
        AttributesArg::None => dagfmt::AttributeKind::None,
    };
    opts.format_version = match (args.format_version, &opts.region) {
        (Some(2), Some(_)) => {
            return Err(ConvertError::Usage(
                "--region writes a part, which is format 1 (spec §24): drop --format-version 2; `dagtool merge` writes the whole volume as 2.0".into(),
            ));
        }
        (Some(v), _) => v,
        (None, _) => opts.format_version,
    };
    opts.color_error = args.color_error;
    opts.force = args.force;
    opts.progress = !args.quiet;
    opts.memory_limit = memory_limit;
    opts.chunk_bits = args.chunk_bits;
    opts.tmp_dir = args.tmp_dir;
    if args.spill_split_level.is_some()
        || args.spill_cells_per_run.is_some()
        || args.spill_buckets.is_some()
    {
        opts.forced_spill = Some(convert::ForcedSpill {
            split_level: args.spill_split_level,
            cells_per_run: args.spill_cells_per_run,
            buckets: args.spill_buckets,
        });
    }
    match args.threads {
        Some(0) => return Err(ConvertError::Usage("--threads must be at least 1".into())),
        // The global pool: the pipeline's producer thread uses it too.
        Some(n) => rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()
            .map_err(|e| ConvertError::Usage(format!("cannot start {n} threads: {e}")))?,
        None => {}
    }
    let summary = convert::convert(&opts).map_err(|e| name_the_input(e, &args.input[0]))?;
    if !args.quiet {
        print_stdout(&format!("{}\n", summary.render(&args.output)))?;
    }
    Ok(())
}

/// Makes a message about the input's contents name the input ("the mesh has
/// no triangles" becomes "cube.obj: the mesh has no triangles").
fn name_the_input(error: ConvertError, input: &std::path::Path) -> ConvertError {
    match error {
        ConvertError::Input(message) if !message.contains(&*input.to_string_lossy()) => {
            ConvertError::Input(format!("{}: {message}", input.display()))
        }
        other => other,
    }
}

fn run(cli: Cli) -> Result<i32, ConvertError> {
    match cli.command {
        Command::Convert(args) => convert_cmd(args).map(|()| 0),
        Command::Merge {
            parts,
            output,
            memory_limit,
            tmp_dir,
            buckets,
            format_version,
            force,
            quiet,
        } => {
            let memory_limit = match &memory_limit {
                Some(s) => Some(parse_size(s).ok_or_else(|| {
                    ConvertError::Usage(format!(
                        "--memory-limit {s} is not a size such as 4G or 512M"
                    ))
                })?),
                None => None,
            };
            let opts = dagtool::merge::MergeOptions {
                memory_limit,
                force,
                tmp_dir,
                buckets,
                format_version,
            };
            let summary = dagtool::merge::merge(&parts, &output, &opts)?;
            if !quiet {
                print_stdout(&summary.render(&output))?;
            }
            Ok(0)
        }
        Command::Validate { files, json } => {
            let stderr = std::io::stderr();
            // 1 means "invalid", so failing to write the report is 2.
            match cmd::validate::run(&files, json, &mut StdoutReport::new(), &mut stderr.lock()) {
                Ok(outcome) => Ok(outcome.exit_code()),
                Err(e) => {
                    eprintln!("dagtool: error: cannot write the report: {e}");
                    Ok(2)
                }
            }
        }
        Command::Info { file, json } => {
            print_stdout(&format!("{}\n", cmd::info::run(&file, json)?))?;
            Ok(0)
        }
        Command::Dump { file, nodes } => {
            print_stdout(&cmd::dump::run(&file, nodes)?)?;
            Ok(0)
        }
        Command::Pack {
            input,
            output,
            level,
            force,
        } => {
            if !(1..=22).contains(&level) {
                return Err(ConvertError::Usage(format!(
                    "zstd level {level} is outside 1..=22"
                )));
            }
            let output = output.path()?;
            let (a, b) = cmd::pack::pack(&input, &output, level, force)?;
            print_stdout(&format!(
                "{}: {a} bytes -> {}: {b} bytes ({:.1}%)\n",
                input.display(),
                output.display(),
                100.0 * b as f64 / a.max(1) as f64
            ))?;
            Ok(0)
        }
        Command::Recompress {
            input,
            output,
            color_error,
            force,
        } => {
            let output = output.path()?;
            let r = cmd::recompress::recompress(&input, &output, color_error, force)?;
            print_stdout(&format!(
                "{}: {} bytes (colours {}) -> {}: {} bytes\ncolours:  {}\n",
                input.display(),
                r.input_bytes,
                r.input_color_bytes,
                output.display(),
                r.output_bytes,
                convert::packed_line(&r.packed)
            ))?;
            Ok(0)
        }
        Command::Demo {
            output,
            depth,
            width,
            height,
            cpu,
        } => {
            if width == 0 || height == 0 || width > 16384 || height > 16384 {
                return Err(ConvertError::Usage(format!(
                    "image size {width}x{height} is outside 1..=16384"
                )));
            }
            let opts = dagtool::demo::DemoOptions {
                out_dir: output,
                depth: convert::check_depth(depth)?,
                width,
                height,
                cpu_only: cpu,
            };
            Ok(if dagtool::demo::run(&opts)? { 0 } else { 1 })
        }
        Command::Verify {
            mesh,
            file,
            rays,
            seed,
            json,
            point_radius,
        } => {
            let opts = dagtool::verify::VerifyOptions {
                mesh,
                dag: file,
                rays,
                seed,
                point_radius,
            };
            // Like `validate`: 1 means "fails the criteria", so every error is 2.
            match dagtool::verify::run(&opts, json) {
                Ok(code) => Ok(code),
                Err(e) => {
                    eprintln!("dagtool: error: {e}");
                    Ok(2)
                }
            }
        }
        Command::Upgrade {
            input,
            output,
            format_version,
            force,
        } => {
            let output = output.path()?;
            let r = cmd::upgrade::upgrade(&input, &output, format_version, force)?;
            print_stdout(&format!(
                "{}: format {}.0, {} bytes -> {}: format {}.0, {} bytes ({:.3}){}\n",
                input.display(),
                r.from,
                r.input_bytes,
                output.display(),
                r.to,
                r.output_bytes,
                r.output_bytes as f64 / r.input_bytes.max(1) as f64,
                if r.from == r.to {
                    " (already that version: copied)"
                } else {
                    ""
                }
            ))?;
            Ok(0)
        }
        Command::Unpack {
            input,
            output,
            max_size,
            force,
        } => {
            let max = match max_size {
                Some(s) => parse_size(&s).ok_or_else(|| {
                    ConvertError::Usage(format!("--max-size {s} is not a size such as 4G"))
                })?,
                None => dagfmt::transport::DEFAULT_MAX_SIZE,
            };
            let output = output.path()?;
            let (a, b) = cmd::pack::unpack(&input, &output, max, force)?;
            print_stdout(&format!(
                "{}: {a} bytes -> {}: {b} bytes (valid)\n",
                input.display(),
                output.display()
            ))?;
            Ok(0)
        }
    }
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
            let first = dagtrace::cli::usage_error_line(&e);
            eprintln!("dagtool: error: {first} (see dagtool --help)");
            return ExitCode::from(2);
        }
    };
    match run(cli) {
        Ok(code) => ExitCode::from(code as u8),
        Err(e) => {
            eprintln!("dagtool: error: {e}");
            ExitCode::from(e.exit_code() as u8)
        }
    }
}
