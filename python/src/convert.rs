//! `vdag.convert`: `dagtool convert` from Python, with a progress callable.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use dagtool::ConvertError;
use dagtool::convert::{Bounds, ConvertOptions, ConvertProgress, ProgressHook};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::errors;

/// A memory limit given as bytes or as a size such as `"4G"`.
#[derive(FromPyObject)]
pub enum Size {
    /// Bytes.
    Bytes(u64),
    /// A size with a unit, as `--memory-limit` takes it.
    Text(String),
}

/// The one-line reason of a failed conversion as `vdag.ConvertError`, with
/// `kind` saying which (`"input"`, `"usage"`, `"io"` or `"limit"`).
pub(crate) fn convert_error(py: Python<'_>, e: &ConvertError) -> PyErr {
    let kind = match e {
        ConvertError::Input(_) => "input",
        ConvertError::Usage(_) => "usage",
        ConvertError::Io(_) => "io",
        ConvertError::Limit(_) => "limit",
    };
    let err = errors::plain(py, "ConvertError", e.to_string());
    // The kind is an extra attribute of ConvertError (vdag/errors.py).
    let _ = err.value(py).setattr("kind", kind);
    err
}

/// Converts a mesh, point cloud, voxel grid or voxel list to a `.vdag` file,
/// exactly as `dagtool convert` does with the same options (the output is
/// byte-identical), and returns a dict summarising it (`voxels`,
/// `file_bytes`, `depth`, `root_min`, `root_size`, `total_seconds`,
/// `peak_rss`, `warnings`).
///
/// `format_version` is the format written: 2 (the default, as `dagtool
/// convert`'s; spec §23) or 1.
///
/// `depth` is required for meshes; `colors` stores per-voxel colours
/// (`color_error` packs them within that per-channel error, 0 = lossless);
/// `solid` fills closed meshes; `memory_limit` is bytes or a size such as
/// `"4G"` (default: 3/4 of physical memory), the most the conversion itself
/// may hold: the process's resident memory above what it held when the
/// conversion started (what this process held or peaked at before, numpy
/// arrays or an earlier conversion, is not counted; the process's peak,
/// `VmHWM` on Linux, is reset at the start to measure it), and the returned
/// `peak_rss` is that peak; `bounds` is the root cube as
/// `(xmin, ymin, zmin, size)`; `point_radius` the radius of each point of a
/// point cloud. An existing output is only replaced with `force=True`, and
/// nothing is written when the conversion fails (`ConvertError`, whose
/// `kind` says why).
///
/// `progress`, if given, is called as `progress(phase, done, total)`:
/// `("voxelizing", chunks_done, chunks_total)` as a mesh's 128³ chunks are
/// voxelized, `("finishing", 0, 0)` when the DAG is being finished and
/// `("written", 1, 1)` when the file is in place. The GIL is released during
/// the conversion and taken only to call `progress`. If `progress` raises,
/// it is not called again and its exception is raised when the conversion
/// ends (the conversion itself is not interrupted).
#[pyfunction]
#[pyo3(signature = (input, output, depth = None, *, colors = false, solid = false, color_error = None, memory_limit = None, bounds = None, point_radius = 0.0, force = false, tmp_dir = None, progress = None, format_version = 2))]
#[allow(clippy::too_many_arguments)]
pub fn convert<'py>(
    py: Python<'py>,
    input: PathBuf,
    output: PathBuf,
    depth: Option<u32>,
    colors: bool,
    solid: bool,
    color_error: Option<u8>,
    memory_limit: Option<Size>,
    bounds: Option<(f64, f64, f64, f64)>,
    point_radius: f64,
    force: bool,
    tmp_dir: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
    format_version: u16,
) -> PyResult<Bound<'py, PyDict>> {
    let depth = depth
        .map(dagtool::convert::check_depth)
        .transpose()
        .map_err(|e| convert_error(py, &e))?;
    let mut opts = ConvertOptions::new(input, output, depth);
    opts.colors = colors;
    opts.solid = solid;
    opts.color_error = color_error;
    opts.force = force;
    opts.tmp_dir = tmp_dir;
    opts.point_radius = point_radius;
    opts.format_version = format_version;
    opts.memory_limit = match memory_limit {
        None => None,
        Some(Size::Bytes(b)) => Some(b),
        Some(Size::Text(s)) => Some(dagtool::sysinfo::parse_size(&s).ok_or_else(|| {
            PyValueError::new_err(format!(
                "memory_limit {s:?} is not a size such as \"4G\" or \"512M\""
            ))
        })?),
    };
    if let Some((x, y, z, size)) = bounds {
        opts.bounds =
            Some(Bounds::parse(&format!("{x},{y},{z},{size}")).map_err(|e| convert_error(py, &e))?);
    }
    // The first exception `progress` raised; after it, it is not called again.
    let failed: Arc<Mutex<Option<PyErr>>> = Arc::new(Mutex::new(None));
    if let Some(callback) = progress {
        let failed = Arc::clone(&failed);
        opts.progress_hook = Some(ProgressHook(Arc::new(move |step: ConvertProgress| {
            let (phase, done, total) = match step {
                ConvertProgress::Voxelizing { done, total } => ("voxelizing", done, total),
                ConvertProgress::Finishing => ("finishing", 0, 0),
                ConvertProgress::Written => ("written", 1, 1),
            };
            let Ok(mut failed) = failed.lock() else {
                return;
            };
            if failed.is_some() {
                return;
            }
            if let Err(e) = Python::attach(|py| callback.call1(py, (phase, done, total)).map(drop))
            {
                *failed = Some(e);
            }
        })));
    }
    let result = py.detach(|| dagtool::convert::convert(&opts));
    if let Some(e) = failed.lock().ok().and_then(|mut f| f.take()) {
        return Err(e);
    }
    let summary = result.map_err(|e| convert_error(py, &e))?;
    let d = PyDict::new(py);
    d.set_item("voxels", summary.voxels)?;
    d.set_item("file_bytes", summary.file_bytes)?;
    d.set_item("depth", summary.depth)?;
    d.set_item("root_min", summary.root_min.to_vec())?;
    d.set_item("root_size", summary.root_size)?;
    d.set_item("total_seconds", summary.total_seconds)?;
    d.set_item("peak_rss", summary.peak_rss)?;
    d.set_item("warnings", summary.warnings)?;
    Ok(d)
}
