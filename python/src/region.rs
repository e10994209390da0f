//! Region builds and merges from Python: `convert_region` and `merge`, the
//! tasks `vdag.distributed` fans out over a Dask cluster (spec/VDAG.md § 24).

use std::path::PathBuf;

use dagtool::ConvertError;
use dagtool::convert::{Bounds, ConvertOptions};
use dagtool::merge::MergeOptions;
use dagtool::region::Region;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::convert::{Size, convert_error};

/// Registers the functions of this file.
pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(convert_region, m)?)?;
    m.add_function(wrap_pyfunction!(merge, m)?)?;
    m.add_function(wrap_pyfunction!(regions, m)?)?;
    m.add_function(wrap_pyfunction!(clear_input_cache, m)?)?;
    Ok(())
}

/// One input path, or several point-cloud tiles read as one.
#[derive(FromPyObject)]
pub enum InputArg {
    /// One file.
    One(PathBuf),
    /// Tiles, in order.
    Tiles(Vec<PathBuf>),
}

/// A region as `"K:X,Y,Z"` or `(K, X, Y, Z)`.
#[derive(FromPyObject)]
pub enum RegionArg {
    /// `"K:X,Y,Z"`.
    Text(String),
    /// `(K, X, Y, Z)`.
    Tuple((u8, u32, u32, u32)),
}

fn memory(limit: Option<Size>) -> PyResult<Option<u64>> {
    match limit {
        None => Ok(None),
        Some(Size::Bytes(b)) => Ok(Some(b)),
        Some(Size::Text(s)) => dagtool::sysinfo::parse_size(&s).map(Some).ok_or_else(|| {
            PyValueError::new_err(format!(
                "memory_limit {s:?} is not a size such as \"4G\" or \"512M\""
            ))
        }),
    }
}

/// The `vdag.ConvertError` of a failed region build or merge, with the
/// spec's code when the message starts with one (`E096 parts-overlap: …`).
fn region_error(py: Python<'_>, e: &ConvertError) -> PyErr {
    let err = convert_error(py, e);
    let text = e.to_string();
    let code = text
        .get(..4)
        .filter(|c| c.starts_with('E') && c[1..].bytes().all(|b| b.is_ascii_digit()));
    if let Some(code) = code {
        let _ = err.value(py).setattr("code", code);
    }
    err
}

/// Builds only the cell `region` (level K, cell X, Y, Z of the root cube)
/// of a conversion into a *part* (spec/VDAG.md § 24), as `dagtool convert
/// --region` does: the voxels the whole conversion with the same options has
/// in that cell, and no other. `input` is a file or a list of point-cloud
/// tiles read as one (only the tiles whose header bounds meet the cell are
/// read). `bounds` `(xmin, ymin, zmin, size)` is
/// required, so that every part has the same root cube. Returns a dict
/// (`region`, `index`, `voxels`, `file_bytes`, `seconds`, and where the
/// time went: `parse_seconds`, `bin_seconds` (meshes), `load_seconds` (all
/// before voxelizing), `build_seconds`, `write_seconds`; `peak_rss`, the
/// build's own peak, which `memory_limit` bounds as in `convert`).
/// With `cache_input` (the default) a mesh input stays in this process's
/// memory for the next region of the same file (same path, size and
/// modification time): a worker parses it once, not once per region;
/// `clear_input_cache()` frees it.
/// Raises `vdag.ConvertError` (nothing written) when it fails.
#[pyfunction]
#[pyo3(signature = (input, output, depth, region, *, bounds, colors = false, solid = false, color_error = None, memory_limit = None, point_radius = 0.0, force = false, tmp_dir = None, cache_input = true))]
#[allow(clippy::too_many_arguments)]
pub fn convert_region<'py>(
    py: Python<'py>,
    input: InputArg,
    output: PathBuf,
    depth: u32,
    region: RegionArg,
    bounds: (f64, f64, f64, f64),
    colors: bool,
    solid: bool,
    color_error: Option<u8>,
    memory_limit: Option<Size>,
    point_radius: f64,
    force: bool,
    tmp_dir: Option<PathBuf>,
    cache_input: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let region = match region {
        RegionArg::Text(t) => Region::parse(&t),
        RegionArg::Tuple((k, x, y, z)) => Region::parse(&format!("{k}:{x},{y},{z}")),
    }
    .map_err(|e| region_error(py, &e))?;
    let depth = dagtool::convert::check_depth(depth).map_err(|e| region_error(py, &e))?;
    let (first, more) = match input {
        InputArg::One(p) => (p, Vec::new()),
        InputArg::Tiles(mut t) if !t.is_empty() => (t.remove(0), t),
        InputArg::Tiles(_) => return Err(PyValueError::new_err("no input file given")),
    };
    let mut opts = ConvertOptions::new(first, output, Some(depth));
    opts.extra_inputs = more;
    let (x, y, z, size) = bounds;
    opts.bounds =
        Some(Bounds::parse(&format!("{x},{y},{z},{size}")).map_err(|e| region_error(py, &e))?);
    opts.region = Some(region);
    opts.colors = colors;
    opts.solid = solid;
    opts.color_error = color_error;
    opts.memory_limit = memory(memory_limit)?;
    opts.point_radius = point_radius;
    opts.force = force;
    opts.tmp_dir = tmp_dir;
    opts.cache_input = cache_input;
    let summary = py
        .detach(|| dagtool::convert::convert(&opts))
        .map_err(|e| region_error(py, &e))?;
    let d = PyDict::new(py);
    d.set_item("region", region.to_string())?;
    d.set_item("index", region.index())?;
    d.set_item("voxels", summary.voxels)?;
    d.set_item("file_bytes", summary.file_bytes)?;
    d.set_item("seconds", summary.total_seconds)?;
    d.set_item("parse_seconds", summary.parse_seconds)?;
    d.set_item("bin_seconds", summary.bin_seconds)?;
    d.set_item("load_seconds", summary.load_seconds)?;
    d.set_item("build_seconds", summary.build_seconds)?;
    d.set_item("write_seconds", summary.write_seconds)?;
    d.set_item("peak_rss", summary.peak_rss)?;
    Ok(d)
}

/// Joins parts (from `convert_region` or earlier merges, in any order) into
/// `output`, as `dagtool merge` does: a part covering their cells or, when
/// they cover the whole root cube, the file one conversion of the whole input
/// writes, byte for byte. Parts are validated first; bad, overlapping or
/// mismatched parts raise `vdag.ConvertError` with the spec's code
/// (E090 – E098, or the format's). `format_version` is the format of the
/// whole-volume file: 2 (the default, as `dagtool merge`'s and `convert`'s)
/// or 1; a merge that does not cover the whole root cube writes a part,
/// which is always format 1. `memory_limit` bounds what the merge adds to
/// this process's memory, as in `convert`. Returns a dict (`complete`, `cells`,
/// `format_version` (of the file written), `voxels`, `file_bytes`,
/// `input_bytes`, `seconds`).
#[pyfunction]
#[pyo3(signature = (parts, output, *, memory_limit = None, force = false, tmp_dir = None, format_version = 2))]
pub fn merge<'py>(
    py: Python<'py>,
    parts: Vec<PathBuf>,
    output: PathBuf,
    memory_limit: Option<Size>,
    force: bool,
    tmp_dir: Option<PathBuf>,
    format_version: u16,
) -> PyResult<Bound<'py, PyDict>> {
    let opts = MergeOptions {
        memory_limit: memory(memory_limit)?,
        force,
        tmp_dir,
        buckets: None,
        format_version,
    };
    let summary = py
        .detach(|| dagtool::merge::merge(&parts, &output, &opts))
        .map_err(|e| region_error(py, &e))?;
    let d = PyDict::new(py);
    d.set_item("complete", summary.complete)?;
    d.set_item("cells", (summary.cells.start, summary.cells.end))?;
    d.set_item("format_version", summary.format_version)?;
    d.set_item("voxels", summary.voxels)?;
    d.set_item("file_bytes", summary.file_bytes)?;
    d.set_item("input_bytes", summary.input_bytes)?;
    d.set_item("seconds", summary.total_seconds)?;
    Ok(d)
}

/// The regions of level `level` in Morton order, as `(K, X, Y, Z)` tuples:
/// the order in which parts must be merged to stay contiguous.
#[pyfunction]
pub fn regions(level: u8) -> PyResult<Vec<(u8, u32, u32, u32)>> {
    if level > 7 {
        return Err(PyValueError::new_err(format!(
            "region level {level} would make {} regions; use at most 7",
            1u64 << (3 * u32::from(level))
        )));
    }
    Ok(Region::all(level)
        .map(|r| (r.level, r.cell[0], r.cell[1], r.cell[2]))
        .collect())
}

/// Frees the mesh `convert_region` keeps in this process (`cache_input`);
/// returns whether one was kept.
#[pyfunction]
pub fn clear_input_cache() -> bool {
    dagtool::convert::clear_input_cache()
}
