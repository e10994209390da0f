//! The input formats of `dagtool convert` and `dagtool verify`: one module per
//! format, each turning a file into one of three common forms:
//!
//! - a triangle mesh ([`Mesh`]: triangles, materials, texture coordinates,
//!   vertex colours), voxelized like OBJ (OBJ, glTF, PLY with faces, STL);
//! - a point stream ([`PointSource`]: points read in batches, never held all
//!   at once), one voxel per point or a ball per point (PLY without faces,
//!   LAS/LAZ);
//! - a voxel grid ([`VoxelGrid`]: integer voxels with their own root cube and
//!   optional colours), one output voxel per input voxel (MagicaVoxel `.vox`,
//!   binvox).
//!
//! [`FORMATS`] is the registry: adding a format is one new module and one
//! line there. A file's format is recognised by its first bytes
//! ([`Format::magic`]), then by its extension; `--input-format` names it
//! outright. The text and binary voxel lists of [`crate::voxlist`] are
//! recognised here too but converted by `convert` itself.

pub mod binvox;
pub mod gltf;
pub mod las;
pub mod obj;
pub mod ply;
pub mod stl;
pub mod vox;

use std::io::Read;
use std::path::Path;

use crate::error::ConvertError;
use crate::mesh::Mesh;

/// One input format of the registry.
#[derive(Clone, Copy, Debug)]
pub struct Format {
    /// The name given to `--input-format` and used in messages.
    pub name: &'static str,
    /// What it is, for `--help` and messages.
    pub description: &'static str,
    /// Lower-case extensions, without the dot.
    pub extensions: &'static [&'static str],
    /// Whether the first bytes of a file (up to [`MAGIC_BYTES`]) are this
    /// format's; `None` for formats without a reliable signature.
    pub magic: Option<fn(&[u8]) -> bool>,
    /// Opens a file of this format.
    pub open: fn(&Path, &OpenOptions) -> Result<Input, ConvertError>,
}

/// Bytes read from the start of a file to recognise its format.
pub const MAGIC_BYTES: usize = 64;

/// The registry of the input formats, in the order their signatures are
/// tried (more specific first).
pub const FORMATS: &[Format] = &[
    gltf::GLB,
    gltf::GLTF,
    ply::FORMAT,
    las::FORMAT,
    vox::FORMAT,
    binvox::FORMAT,
    stl::FORMAT,
    obj::FORMAT,
];

/// What an input's reader needs beyond the file.
#[derive(Clone, Debug, Default)]
pub struct OpenOptions {
    /// Colours are wanted (`--colors`): textures are decoded, colour
    /// attributes kept.
    pub colors: bool,
}

/// An opened input in one of the three common forms.
pub enum Input {
    /// A triangle mesh, loaded whole.
    Mesh(Box<Mesh>),
    /// A point cloud, read in a stream.
    Points(Box<dyn PointSource>),
    /// A voxel grid, loaded whole.
    Voxels(VoxelGrid),
}

impl std::fmt::Debug for Input {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Input::Mesh(m) => write!(f, "Mesh({} triangles)", m.triangles.len()),
            Input::Points(_) => write!(f, "Points"),
            Input::Voxels(g) => write!(f, "Voxels({} voxels)", g.voxels.len()),
        }
    }
}

/// One point of a cloud: its position, and its colour when the cloud has
/// colours.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CloudPoint {
    /// World-space position.
    pub position: [f64; 3],
    /// RGBA8 colour (white when the cloud has none).
    pub rgba: [u8; 4],
}

/// A point cloud read in batches, so that clouds larger than memory convert.
pub trait PointSource {
    /// A description for the summary (format, point count, attributes).
    fn describe(&self) -> String;
    /// The number of points the file declares.
    fn count(&self) -> u64;
    /// The bounding box the file declares (LAS headers), if any: a reader
    /// that returns one checks every point against it while reading.
    fn declared_bounds(&self) -> Option<([f64; 3], [f64; 3])>;
    /// Whether the points carry colours.
    fn has_colors(&self) -> bool;
    /// Appends up to `max` points to `out`; returns how many (0 at the end).
    fn read(&mut self, out: &mut Vec<CloudPoint>, max: usize) -> Result<usize, ConvertError>;
    /// Starts again from the first point (for a second pass).
    fn rewind(&mut self) -> Result<(), ConvertError>;
}

/// Several point clouds read as one, in order (tiles of one survey): the
/// points of the first, then of the second, and so on. Colours only when
/// every cloud has them.
pub struct ChainedPoints {
    sources: Vec<Box<dyn PointSource>>,
    at: usize,
    colors: bool,
    skipped: usize,
}

impl std::fmt::Debug for ChainedPoints {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.describe())
    }
}

impl ChainedPoints {
    /// The clouds `sources`, in order; with `keep`, only those whose
    /// declared bounds (all must declare them) pass it (a region build reads
    /// only the tiles that meet its cell; the colours still depend on every
    /// cloud, as in the whole build).
    pub fn new(
        sources: Vec<Box<dyn PointSource>>,
        keep: Option<&dyn Fn([f64; 3], [f64; 3]) -> bool>,
    ) -> Self {
        let colors = sources.iter().all(|s| s.has_colors());
        let total = sources.len();
        let sources: Vec<_> = match keep {
            None => sources,
            Some(keep) => sources
                .into_iter()
                .filter(|s| s.declared_bounds().is_none_or(|(lo, hi)| keep(lo, hi)))
                .collect(),
        };
        ChainedPoints {
            skipped: total - sources.len(),
            sources,
            at: 0,
            colors,
        }
    }

    /// Clouds left out by `keep`.
    pub fn skipped(&self) -> usize {
        self.skipped
    }
}

impl PointSource for ChainedPoints {
    fn describe(&self) -> String {
        format!(
            "{} point clouds read as one ({} more left out: their bounds miss the region){}",
            self.sources.len(),
            self.skipped,
            self.sources
                .first()
                .map(|s| format!(", the first: {}", s.describe()))
                .unwrap_or_default()
        )
    }

    fn count(&self) -> u64 {
        self.sources.iter().map(|s| s.count()).sum()
    }

    fn declared_bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        let mut all: Option<([f64; 3], [f64; 3])> = None;
        for s in &self.sources {
            let (lo, hi) = s.declared_bounds()?;
            all = Some(match all {
                None => (lo, hi),
                Some((a, b)) => (
                    [0, 1, 2].map(|i| a[i].min(lo[i])),
                    [0, 1, 2].map(|i| b[i].max(hi[i])),
                ),
            });
        }
        all
    }

    fn has_colors(&self) -> bool {
        self.colors
    }

    fn read(&mut self, out: &mut Vec<CloudPoint>, max: usize) -> Result<usize, ConvertError> {
        while let Some(s) = self.sources.get_mut(self.at) {
            let start = out.len();
            let n = s.read(out, max)?;
            if n > 0 {
                if !self.colors {
                    for p in &mut out[start..] {
                        p.rgba = crate::mesh::DEFAULT_COLOR;
                    }
                }
                return Ok(n);
            }
            self.at += 1;
        }
        Ok(0)
    }

    fn rewind(&mut self) -> Result<(), ConvertError> {
        for s in &mut self.sources {
            s.rewind()?;
        }
        self.at = 0;
        Ok(())
    }
}

/// A grid of integer voxels with its own placement.
#[derive(Clone, Debug, Default)]
pub struct VoxelGrid {
    /// The voxels' integer coordinates (`0..2^depth`), in any order, possibly
    /// repeated (the first occurrence's colour counts).
    pub voxels: Vec<[u32; 3]>,
    /// Their colours (RGBA8), indexed like `voxels`; empty when the input has
    /// none.
    pub colors: Vec<[u8; 4]>,
    /// The smallest depth whose grid holds every voxel.
    pub depth: u8,
    /// World-space corner of voxel (0, 0, 0).
    pub origin: [f64; 3],
    /// World-space edge of one voxel.
    pub voxel_size: f64,
    /// A description for the summary.
    pub description: String,
}

/// The format named by `--input-format`, if any.
pub fn by_name(name: &str) -> Option<&'static Format> {
    FORMATS.iter().find(|f| f.name == name)
}

/// Recognises a file's format: by its first bytes, then by its extension.
pub fn detect(path: &Path) -> Option<&'static Format> {
    let mut head = Vec::with_capacity(MAGIC_BYTES);
    if let Ok(file) = std::fs::File::open(path) {
        let _ = file.take(MAGIC_BYTES as u64).read_to_end(&mut head);
    }
    detect_bytes(&head, path)
}

/// [`detect`] on the first bytes of a file and its path.
pub fn detect_bytes(head: &[u8], path: &Path) -> Option<&'static Format> {
    if let Some(f) = FORMATS
        .iter()
        .find(|f| f.magic.is_some_and(|magic| magic(head)))
    {
        return Some(f);
    }
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())?;
    FORMATS
        .iter()
        .find(|f| f.extensions.contains(&ext.as_str()))
}

/// The names of every format, for messages.
pub fn names() -> String {
    FORMATS
        .iter()
        .map(|f| f.name)
        .collect::<Vec<_>>()
        .join(", ")
}

/// Opens a file in the format it is recognised as, or `format`.
pub fn open(path: &Path, format: &Format, options: &OpenOptions) -> Result<Input, ConvertError> {
    (format.open)(path, options)
}

/// Reads a whole file, with the input's name in the error.
pub(crate) fn read_file(path: &Path, what: &str) -> Result<Vec<u8>, ConvertError> {
    std::fs::read(path)
        .map_err(|e| ConvertError::Input(format!("cannot read {what} {}: {e}", path.display())))
}

/// Checks that every coordinate of a position is finite.
pub(crate) fn check_finite(p: [f64; 3], what: impl FnOnce() -> String) -> Result<(), ConvertError> {
    if p.iter().all(|c| c.is_finite()) {
        Ok(())
    } else {
        Err(ConvertError::Input(format!(
            "{} has a non-finite coordinate {p:?}",
            what()
        )))
    }
}

/// A point cloud held in memory (for small clouds and tests).
#[derive(Clone, Debug, Default)]
pub struct MemoryCloud {
    /// The points.
    pub points: Vec<CloudPoint>,
    /// Whether they carry colours.
    pub colors: bool,
    /// Description.
    pub description: String,
    next: usize,
}

impl MemoryCloud {
    /// A cloud of `points`.
    pub fn new(points: Vec<CloudPoint>, colors: bool, description: String) -> Self {
        MemoryCloud {
            points,
            colors,
            description,
            next: 0,
        }
    }
}

impl PointSource for MemoryCloud {
    fn describe(&self) -> String {
        self.description.clone()
    }
    fn count(&self) -> u64 {
        self.points.len() as u64
    }
    fn declared_bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        None
    }
    fn has_colors(&self) -> bool {
        self.colors
    }
    fn read(&mut self, out: &mut Vec<CloudPoint>, max: usize) -> Result<usize, ConvertError> {
        let n = max.min(self.points.len() - self.next);
        out.extend_from_slice(&self.points[self.next..self.next + n]);
        self.next += n;
        Ok(n)
    }
    fn rewind(&mut self) -> Result<(), ConvertError> {
        self.next = 0;
        Ok(())
    }
}
