//! `vdag.open`, `vdag.validate` and the `Dag` class: a memory-mapped file
//! of either format version (1.x or 2.0, spec §23) and the queries
//! `dagfmt`'s readers answer.

use std::ops::ControlFlow;
use std::path::PathBuf;
use std::sync::mpsc::{Receiver, SyncSender, sync_channel};
use std::sync::{Arc, Mutex};

use dagfmt::AnyDag;
use dagfmt::layout::SectionKind;
use dagfmt::mmap::MappedFile;
use numpy::ndarray::Array2;
use numpy::{AllowTypeChange, IntoPyArray, PyArray1, PyArray2, PyArrayLike2};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use rayon::prelude::*;

use crate::errors;

/// The bytes of a `.vdag` file: a read-only memory map, or the unpacked
/// transport form (`.vdag.zst`).
#[derive(Debug)]
pub(crate) enum Source {
    /// The file itself, mapped.
    Mapped(MappedFile),
    /// A `.vdag.zst` unpacked into memory.
    Unpacked(Vec<u8>),
}

impl Source {
    /// The file's bytes.
    pub(crate) fn bytes(&self) -> &[u8] {
        match self {
            Source::Mapped(m) => m.bytes(),
            Source::Unpacked(v) => v,
        }
    }

    /// Maps (or unpacks) the file at `path`; errors are one line naming it.
    pub(crate) fn open(path: &std::path::Path) -> Result<Source, String> {
        let map = MappedFile::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
        if dagfmt::transport::is_transport(map.bytes()) {
            let bytes = dagfmt::transport::unpack(map.bytes(), dagfmt::transport::DEFAULT_MAX_SIZE)
                .map_err(|e| format!("{}: {e}", path.display()))?;
            Ok(Source::Unpacked(bytes))
        } else {
            Ok(Source::Mapped(map))
        }
    }
}

/// A `.vdag` file opened for reading (`vdag.open`). The file stays mapped as
/// long as this object (or an iterator or array it made) lives.
#[derive(Debug)]
#[pyclass(frozen, module = "vdag", name = "Dag")]
pub struct PyDag {
    /// The file's bytes; shared with chunk iterators, which outlive calls.
    pub(crate) source: Arc<Source>,
    /// The path as given, for messages.
    pub(crate) path: String,
    /// The decoded header.
    pub(crate) header: dagfmt::reader::Header,
    /// The GPU tracer, made on the first `backend="gpu"` call and kept.
    pub(crate) gpu: Mutex<Option<Arc<dagtrace::gpu::GpuTracer>>>,
    /// A 2.0 file's expanded levels (spec §23.12), made on the first CPU
    /// trace or render and kept, so that each call's tracer does not expand
    /// the file again (`None` inside: the levels do not expand, and are
    /// traced in place).
    pub(crate) expansion: std::sync::OnceLock<Option<dagtrace::Expansion>>,
}

impl PyDag {
    /// The reader over the file's bytes, of the file's version. Opening is
    /// O(sections) and cannot fail once it has succeeded in `open` (the
    /// bytes are the same), but an error is still an exception, never a
    /// panic.
    pub(crate) fn dag(&self, py: Python<'_>) -> PyResult<AnyDag<'_>> {
        AnyDag::open(self.source.bytes()).map_err(|e| errors::format_error(py, &self.path, &e))
    }
}

/// Calls `voxel` with each set voxel's coordinates in Morton order, until it
/// answers [`ControlFlow::Break`]: the 1.x reader's iterator, or a 2.0
/// file's leaves under their reflections (`Dag2::for_each_leaf`).
fn for_each_voxel(
    dag: &AnyDag<'_>,
    mut voxel: impl FnMut([u32; 3]) -> ControlFlow<()>,
) -> Result<(), dagfmt::FormatError> {
    match dag {
        AnyDag::V1(d) => {
            for v in d.voxels() {
                if voxel(v?).is_break() {
                    break;
                }
            }
            Ok(())
        }
        AnyDag::V2(d) => d.for_each_leaf(|prefix, mut mask| {
            while mask != 0 {
                let code = prefix << 6 | u64::from(mask.trailing_zeros());
                voxel(dagfmt::morton::decode(code))?;
                mask &= mask - 1;
            }
            ControlFlow::Continue(())
        }),
    }
}

/// Opens a `.vdag` (or `.vdag.zst`) file of format 1.x or 2.0 and returns a
/// `Dag` (`version` says which; every method answers for both alike).
///
/// The file is memory-mapped (a `.vdag.zst` is unpacked into memory). With
/// `validate=True` (the default) every rule of the format is checked first,
/// as `dagtrace` does before tracing, and an invalid file raises
/// `InvalidFileError` with the first violation's code and byte offset.
/// `validate=False` only checks the header and section table: the reader
/// stays memory-safe on any bytes, but answers for a damaged file are
/// meaningless. An unreadable file raises `VdagError`.
#[pyfunction]
#[pyo3(signature = (path, validate = true))]
pub fn open(py: Python<'_>, path: PathBuf, validate: bool) -> PyResult<PyDag> {
    let name = path.display().to_string();
    let source = py
        .detach(|| Source::open(&path))
        .map_err(|m| errors::plain(py, "VdagError", m))?;
    if validate {
        let problems = py.detach(|| dagfmt::validate::validate(source.bytes()));
        if let Some(first) = problems.first() {
            return Err(errors::format_error(py, &name, first));
        }
    }
    let header = AnyDag::open(source.bytes())
        .map_err(|e| errors::format_error(py, &name, &e))?
        .header()
        .clone();
    Ok(PyDag {
        source: Arc::new(source),
        path: name,
        header,
        gpu: Mutex::new(None),
        expansion: std::sync::OnceLock::new(),
    })
}

/// Checks every rule of the format and returns the violations as a list of
/// `(code, offset, message)` tuples (the codes of spec/VDAG.md, such as
/// `"E012"`; `offset` the byte offset in the file), sorted by offset; an
/// empty list when the file is valid. The same findings as
/// `dagtool validate --json`. An unreadable file raises `VdagError`.
#[pyfunction]
pub fn validate(py: Python<'_>, path: PathBuf) -> PyResult<Vec<(String, u64, String)>> {
    let errors = py
        .detach(|| Source::open(&path).map(|source| dagfmt::validate::validate(source.bytes())))
        .map_err(|m| errors::plain(py, "VdagError", m))?;
    Ok(errors
        .into_iter()
        .map(|e| (e.code.code().to_string(), e.offset, e.message))
        .collect())
}

/// Reads the rows of an (N, 3) integer array as voxel coordinates; a
/// coordinate outside `0 .. resolution` (negative included) becomes `None`.
fn coordinates(
    xyz: &PyArrayLike2<'_, i64, AllowTypeChange>,
    resolution: u64,
) -> PyResult<Vec<Option<[u32; 3]>>> {
    let array = xyz.as_array();
    if array.ncols() != 3 {
        return Err(pyo3::exceptions::PyValueError::new_err(format!(
            "expected an (N, 3) array of voxel coordinates, got shape {:?}",
            array.shape()
        )));
    }
    let inside = |v: i64| {
        u64::try_from(v)
            .ok()
            .filter(|&v| v < resolution)
            .map(|v| v as u32)
    };
    Ok(array
        .rows()
        .into_iter()
        .map(|r| Some([inside(r[0])?, inside(r[1])?, inside(r[2])?]))
        .collect())
}

/// A chunk of voxels (x, y, z flattened), or the error that ended the walk.
type VoxelChunk = Result<Vec<u32>, dagfmt::FormatError>;

/// Flattens voxel coordinates into an (N, 3) uint32 array.
fn voxel_array(py: Python<'_>, flat: Vec<u32>) -> Bound<'_, PyArray2<u32>> {
    let rows = flat.len() / 3;
    Array2::from_shape_vec((rows, 3), flat)
        .expect("three coordinates per voxel")
        .into_pyarray(py)
}

/// Sends the voxels of `source` to `chunks` in Morton order, `chunk` at a
/// time; stops early when the receiver is gone.
fn stream_voxels(source: &Source, chunk: usize, chunks: &SyncSender<VoxelChunk>) {
    let dag = match AnyDag::open(source.bytes()) {
        Ok(dag) => dag,
        Err(e) => {
            let _ = chunks.send(Err(e));
            return;
        }
    };
    let mut buffer = Vec::with_capacity(chunk * 3);
    let mut receiver_gone = false;
    let walked = for_each_voxel(&dag, |v| {
        buffer.extend_from_slice(&v);
        if buffer.len() == chunk * 3 {
            let full = std::mem::replace(&mut buffer, Vec::with_capacity(chunk * 3));
            if chunks.send(Ok(full)).is_err() {
                receiver_gone = true;
                return ControlFlow::Break(());
            }
        }
        ControlFlow::Continue(())
    });
    if receiver_gone {
        return;
    }
    if let Err(e) = walked {
        let _ = chunks.send(Err(e));
        return;
    }
    if !buffer.is_empty() {
        let _ = chunks.send(Ok(buffer));
    }
}

#[pymethods]
impl PyDag {
    /// The path the file was opened from.
    #[getter]
    fn path(&self) -> &str {
        &self.path
    }

    /// The format version as `(major, minor)`: `(1, minor)` or `(2, 0)`.
    #[getter]
    fn version(&self) -> (u16, u16) {
        (self.header.version_major, self.header.version_minor)
    }

    /// The depth D: the grid has 2**D voxels along each axis.
    #[getter]
    fn depth(&self) -> u8 {
        self.header.depth
    }

    /// Voxels along each axis, 2**depth.
    #[getter]
    fn resolution(&self) -> u64 {
        1u64 << self.header.depth
    }

    /// The attribute kind: 0 (none) or 1 (voxel counts, which give the
    /// attribute index).
    #[getter]
    fn attribute_kind(&self) -> u8 {
        match self.header.attribute_kind {
            dagfmt::layout::AttributeKind::None => 0,
            dagfmt::layout::AttributeKind::VoxelCount => 1,
        }
    }

    /// The number of set voxels, from the header.
    #[getter]
    fn voxel_count(&self) -> u64 {
        self.header.voxel_count
    }

    /// The world-space minimum corner of the root cube, `(x, y, z)`.
    #[getter]
    fn root_min(&self) -> (f64, f64, f64) {
        let [x, y, z] = self.header.root_min;
        (x, y, z)
    }

    /// The world-space edge of the root cube.
    #[getter]
    fn root_size(&self) -> f64 {
        self.header.root_size
    }

    /// The file's size in bytes, from the header (of the unpacked form for a
    /// `.vdag.zst`).
    #[getter]
    fn file_size(&self) -> u64 {
        self.header.file_size
    }

    /// The required feature bits of the header.
    #[getter]
    fn required_features(&self) -> u32 {
        self.header.required_features
    }

    /// The optional feature bits of the header.
    #[getter]
    fn optional_features(&self) -> u32 {
        self.header.optional_features
    }

    /// The number of entries of the section table.
    #[getter]
    fn section_count(&self) -> u16 {
        self.header.section_count
    }

    /// The colour section's kind: `"raw"` (VOXEL_COLORS), `"packed"`
    /// (PACKED_COLORS) or `None` without colours.
    #[getter]
    fn color_format(&self, py: Python<'_>) -> PyResult<Option<&'static str>> {
        let dag = self.dag(py)?;
        Ok(dag.sections().iter().find_map(|s| match s.kind {
            SectionKind::VoxelColors => Some("raw"),
            SectionKind::PackedColors => Some("packed"),
            _ => None,
        }))
    }

    /// The per-level table: one dict per level section of the file, root
    /// first, with `level`, `kind` (`"node"` or `"leaf"`), `nodes` (node
    /// records, or 64-bit leaf masks), `bytes`, `offset` (the section's byte
    /// offset in the file), `pointer_width` (1.x: the bytes of a pointer, 0
    /// for the leaf level; 2.0: `None`) and `widths` (2.0: the level's three
    /// reference widths in bits, spec §23.2, `(0, 0, 0)` for the leaf level;
    /// 1.x: `None`). `nodes`, `bytes` and `pointer_width` are the keys of
    /// `dagtool info --json`'s `levels` for a 1.x file, `nodes` (`items`),
    /// `bytes` and `widths` those of its `v2_levels` for a 2.0 file.
    #[getter]
    fn levels<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyList>> {
        let dag = self.dag(py)?;
        let list = PyList::empty(py);
        match &dag {
            AnyDag::V1(dag) => {
                for level in dag.levels() {
                    let entry = PyDict::new(py);
                    entry.set_item("level", level.level)?;
                    entry.set_item("kind", if level.is_leaf { "leaf" } else { "node" })?;
                    entry.set_item("nodes", level.node_count)?;
                    entry.set_item("bytes", level.bytes.len())?;
                    entry.set_item("pointer_width", level.pointer_width)?;
                    entry.set_item("widths", py.None())?;
                    entry.set_item("offset", level.file_offset)?;
                    list.append(entry)?;
                }
            }
            AnyDag::V2(dag) => {
                // The level sections are the first D − 1 entries (§23.10).
                for (view, section) in dag.levels().iter().zip(dag.sections()) {
                    let entry = PyDict::new(py);
                    entry.set_item("level", section.level)?;
                    entry.set_item("kind", if view.is_leaf { "leaf" } else { "node" })?;
                    entry.set_item("nodes", view.item_count)?;
                    entry.set_item("bytes", view.bytes.len())?;
                    entry.set_item("pointer_width", py.None())?;
                    entry.set_item("widths", view.widths)?;
                    entry.set_item("offset", section.offset)?;
                    list.append(entry)?;
                }
            }
        }
        Ok(list)
    }

    /// Every set voxel as an (N, 3) uint32 array of grid coordinates
    /// `(x, y, z)`, in Morton order (the order of the attribute index and of
    /// `colors()`). Holds all N rows: for big files, `iter_voxels` streams
    /// them in chunks.
    fn voxels<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyArray2<u32>>> {
        let dag = self.dag(py)?;
        let flat = py.detach(|| {
            // The header's count sizes the buffer, bounded so that a damaged
            // header (with validate=False) cannot make it allocate at once.
            let mut flat = Vec::with_capacity(dag.header().voxel_count.min(1 << 24) as usize * 3);
            for_each_voxel(&dag, |v| {
                flat.extend_from_slice(&v);
                ControlFlow::Continue(())
            })?;
            Ok(flat)
        });
        match flat {
            Ok(flat) => Ok(voxel_array(py, flat)),
            Err(e) => Err(errors::format_error(py, &self.path, &e)),
        }
    }

    /// Iterates over the set voxels in Morton order, `chunk` at a time: each
    /// item is a (≤ chunk, 3) uint32 array. A thread walks the DAG ahead of
    /// the caller by at most one chunk, so memory is bounded by the chunk,
    /// not by the file.
    #[pyo3(signature = (chunk = 1 << 20))]
    fn iter_voxels(&self, chunk: usize) -> PyResult<VoxelChunks> {
        if chunk == 0 {
            return Err(pyo3::exceptions::PyValueError::new_err(
                "chunk must be at least 1",
            ));
        }
        let (sender, receiver) = sync_channel(1);
        let source = Arc::clone(&self.source);
        std::thread::Builder::new()
            .name("vdag-voxels".into())
            .spawn(move || stream_voxels(&source, chunk, &sender))
            .map_err(|e| pyo3::exceptions::PyOSError::new_err(e.to_string()))?;
        Ok(VoxelChunks {
            receiver: Mutex::new(Some(receiver)),
            path: self.path.clone(),
        })
    }

    /// Whether each voxel of an (N, 3) integer array of grid coordinates is
    /// set: a bool array of N. Coordinates outside the grid are not set.
    /// Runs on all cores without the GIL.
    fn contains<'py>(
        &self,
        py: Python<'py>,
        xyz: PyArrayLike2<'py, i64, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyArray1<bool>>> {
        let dag = self.dag(py)?;
        let cells = coordinates(&xyz, 1u64 << dag.header().depth)?;
        let set: Result<Vec<bool>, _> = py.detach(|| {
            cells
                .par_iter()
                .map(|c| c.map_or(Ok(false), |[x, y, z]| dag.is_set(x, y, z)))
                .collect()
        });
        set.map(|s| s.into_pyarray(py))
            .map_err(|e| errors::format_error(py, &self.path, &e))
    }

    /// The attribute index of each voxel of an (N, 3) integer array of grid
    /// coordinates: its rank among the set voxels in Morton order, which
    /// addresses per-voxel data such as `colors()`. An int64 array of N, -1
    /// where the voxel is not set (or lies outside the grid). Runs on all
    /// cores without the GIL.
    fn attribute_index<'py>(
        &self,
        py: Python<'py>,
        xyz: PyArrayLike2<'py, i64, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyArray1<i64>>> {
        let dag = self.dag(py)?;
        let cells = coordinates(&xyz, 1u64 << dag.header().depth)?;
        let index: Result<Vec<i64>, _> = py.detach(|| {
            cells
                .par_iter()
                .map(|c| match c {
                    None => Ok(-1),
                    Some([x, y, z]) => dag
                        .voxel_index(*x, *y, *z)
                        .map(|i| i.map_or(-1, |i| i64::try_from(i).unwrap_or(i64::MAX))),
                })
                .collect()
        });
        index
            .map(|i| i.into_pyarray(py))
            .map_err(|e| errors::format_error(py, &self.path, &e))
    }

    /// The voxel colours, raw or packed, decoded: an (N, 3) uint8 array of
    /// RGB in voxel (Morton) order, row i the colour of attribute index i;
    /// (N, 4) RGBA with `alpha=True`. `None` when the file has no colours.
    #[pyo3(signature = (alpha = false))]
    fn colors<'py>(
        &self,
        py: Python<'py>,
        alpha: bool,
    ) -> PyResult<Option<Bound<'py, PyArray2<u8>>>> {
        let dag = self.dag(py)?;
        let Some(table) = dag.color_table() else {
            return Ok(None);
        };
        let channels = if alpha { 4 } else { 3 };
        let flat = py.detach(|| {
            let mut flat = Vec::with_capacity(table.len().min(1 << 24) as usize * channels);
            for rgba in table.iter() {
                flat.extend_from_slice(&rgba[..channels]);
            }
            flat
        });
        let rows = flat.len() / channels;
        Ok(Some(
            Array2::from_shape_vec((rows, channels), flat)
                .expect("whole colours")
                .into_pyarray(py),
        ))
    }

    /// Traces N rays and returns a `TraceResult` of N answers.
    ///
    /// `origins` and `directions` are (N, 3) arrays in world space (any N,
    /// 0 included). C-contiguous float32 and float64 arrays are read in place
    /// (float64 rounded to float32, the precision of the tracer and of the
    /// batch formats); other dtypes and layouts are first converted by numpy.
    /// `tmin` and `tmax` bound every ray's segment; `level` (1..depth) traces
    /// the cells of that level instead of voxels. `backend="cpu"` traces on
    /// every core with dagtrace's batch API; `backend="gpu"` with its wgpu
    /// tracer (`GpuError` when there is no adapter). The GIL is released
    /// while tracing. The answers are those of `dagtrace trace` for the
    /// same rays.
    #[pyo3(signature = (origins, directions, tmin = 0.0, tmax = f64::INFINITY, level = None, backend = "cpu"))]
    #[allow(clippy::too_many_arguments)]
    fn trace(
        &self,
        py: Python<'_>,
        origins: &Bound<'_, PyAny>,
        directions: &Bound<'_, PyAny>,
        tmin: f64,
        tmax: f64,
        level: Option<u8>,
        backend: &str,
    ) -> PyResult<crate::trace::TraceResult> {
        self.trace_rays(py, origins, directions, tmin, tmax, level, backend)
    }

    /// Renders the file as `dagtrace render` does and returns the image as
    /// an (height, width, 3) uint8 array (RGB, rows from the top): the same
    /// pixels as the PNG `dagtrace render` writes with the same options.
    ///
    /// Without `camera_pos` and `look_at` (world-space points, both or
    /// neither) the view frames the occupied part of the volume. `fov` is
    /// the vertical field of view in degrees. `shade` is `"lit"` (sun,
    /// shadows, ambient occlusion; `sun`, `ao_rays`, `ao_radius`, `samples`
    /// apply to it only), `"normal"`, `"depth"` or `"color"`. `level` traces
    /// the cells of that level; `backend` is `"cpu"` or `"gpu"`.
    #[pyo3(signature = (width = 1280, height = 720, camera_pos = None, look_at = None, fov = 40.0, shade = "lit", sun = None, ao_rays = None, ao_radius = None, samples = None, level = None, backend = "cpu"))]
    #[allow(clippy::too_many_arguments)]
    fn render<'py>(
        &self,
        py: Python<'py>,
        width: u32,
        height: u32,
        camera_pos: Option<[f64; 3]>,
        look_at: Option<[f64; 3]>,
        fov: f64,
        shade: &str,
        sun: Option<[f64; 3]>,
        ao_rays: Option<u32>,
        ao_radius: Option<f64>,
        samples: Option<u32>,
        level: Option<u8>,
        backend: &str,
    ) -> PyResult<Bound<'py, numpy::PyArray3<u8>>> {
        let v = crate::render::view(
            width, height, camera_pos, look_at, fov, shade, sun, ao_rays, ao_radius, samples,
            level, backend,
        )?;
        self.render_view(py, &v)
    }

    /// `vdag.Dag(path, depth=…, voxel_count=…)`.
    fn __repr__(&self) -> String {
        format!(
            "vdag.Dag({:?}, depth={}, voxel_count={})",
            self.path, self.header.depth, self.header.voxel_count
        )
    }
}

/// The iterator `Dag.iter_voxels` returns: (≤ chunk, 3) uint32 arrays of
/// voxel coordinates in Morton order.
#[derive(Debug)]
#[pyclass(frozen, module = "vdag")]
pub struct VoxelChunks {
    /// The walking thread's chunks; `None` once they have all been read.
    receiver: Mutex<Option<Receiver<VoxelChunk>>>,
    /// The file, for messages.
    path: String,
}

#[pymethods]
impl VoxelChunks {
    /// The iterator itself.
    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    /// The next chunk of voxels; StopIteration after the last.
    fn __next__<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyArray2<u32>>>> {
        // The lock is taken without the GIL, so that a thread waiting for it
        // never holds the GIL that the thread holding it needs back.
        let next = py.detach(|| {
            let mut guard = self.receiver.lock().ok()?;
            let next = guard.as_ref()?.recv();
            if !matches!(next, Ok(Ok(_))) {
                *guard = None;
            }
            // A closed channel: the walk is over.
            next.ok()
        });
        match next {
            Some(Ok(flat)) => Ok(Some(voxel_array(py, flat))),
            Some(Err(e)) => Err(errors::format_error(py, &self.path, &e)),
            None => Ok(None),
        }
    }
}
