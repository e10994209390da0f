//! `Dag.trace`: numpy rays through `dagtrace`'s batch API or its GPU tracer.

use std::sync::Arc;

use dagfmt::AnyDag;
use dagfmt::batch::{Hit, Ray};
use dagtrace::gpu::{GpuOptions, GpuTracer};
use dagtrace::{TraceError, Tracer};
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use rayon::prelude::*;

use crate::errors;
use crate::file::PyDag;

/// Rows of an (N, 3) float array as read: a borrowed float32 or float64
/// buffer (zero-copy), or a float32 copy made by numpy for any other dtype
/// or layout.
enum Points<'py> {
    F32(PyReadonlyArray2<'py, f32>),
    F64(PyReadonlyArray2<'py, f64>),
}

/// A borrowed contiguous view of [`Points`], which may cross into the
/// GIL-free part.
#[derive(Clone, Copy)]
enum Flat<'a> {
    F32(&'a [f32]),
    F64(&'a [f64]),
}

impl Flat<'_> {
    /// Row `i` as f32 (float64 rounds to nearest, as the batch formats hold f32).
    #[inline]
    fn row(self, i: usize) -> [f32; 3] {
        match self {
            Flat::F32(v) => [v[3 * i], v[3 * i + 1], v[3 * i + 2]],
            Flat::F64(v) => [v[3 * i] as f32, v[3 * i + 1] as f32, v[3 * i + 2] as f32],
        }
    }
}

impl<'py> Points<'py> {
    /// Reads `array` as (N, 3) floats: C-contiguous float32 and float64
    /// arrays are borrowed; anything else goes through
    /// `numpy.ascontiguousarray(array, dtype=float32)`.
    fn extract(name: &str, array: &Bound<'py, PyAny>) -> PyResult<Self> {
        let contiguous = |a: &Bound<'py, PyAny>| -> bool {
            a.cast::<numpy::PyUntypedArray>()
                .is_ok_and(|u| u.is_c_contiguous())
        };
        let points = if let Ok(a) = array.extract::<PyReadonlyArray2<'py, f32>>()
            && contiguous(array)
        {
            Points::F32(a)
        } else if let Ok(a) = array.extract::<PyReadonlyArray2<'py, f64>>()
            && contiguous(array)
        {
            Points::F64(a)
        } else {
            let numpy = array.py().import("numpy")?;
            let converted =
                numpy.call_method1("ascontiguousarray", (array, numpy.getattr("float32")?))?;
            Points::F32(
                converted
                    .extract::<PyReadonlyArray2<'py, f32>>()
                    .map_err(|_| {
                        PyValueError::new_err(format!("{name} must be an (N, 3) array of floats"))
                    })?,
            )
        };
        let shape = match &points {
            Points::F32(a) => a.shape().to_vec(),
            Points::F64(a) => a.shape().to_vec(),
        };
        if shape.len() != 2 || shape[1] != 3 {
            return Err(PyValueError::new_err(format!(
                "{name} must be an (N, 3) array, got shape {shape:?}"
            )));
        }
        Ok(points)
    }

    fn rows(&self) -> usize {
        match self {
            Points::F32(a) => a.shape()[0],
            Points::F64(a) => a.shape()[0],
        }
    }

    fn flat(&self) -> PyResult<Flat<'_>> {
        let not_contiguous = |_| PyValueError::new_err("array is not contiguous");
        Ok(match self {
            Points::F32(a) => Flat::F32(a.as_slice().map_err(not_contiguous)?),
            Points::F64(a) => Flat::F64(a.as_slice().map_err(not_contiguous)?),
        })
    }
}

/// The answers of `Dag.trace`, one row per ray: `hit` (bool), `t`
/// (float32, the entry parameter), `cell` ((N, 3) uint32, the cell's
/// coordinates at the traced level), `level` (uint8), `face` (uint8, 0 =
/// started inside, 1..6 = -X +X -Y +Y -Z +Z) and `index` (int64, the dense
/// attribute index of the cell's first voxel, -1 for none). A miss has
/// `hit` False, `t` 0, `cell` (0, 0, 0), `level` 0, `face` 0 and `index` -1,
/// as in the binary hit batch of spec/VDAG.md §21.4.
#[derive(Debug)]
#[pyclass(frozen, module = "vdag", get_all)]
pub struct TraceResult {
    /// Whether the ray hit an occupied cell.
    hit: Py<PyArray1<bool>>,
    /// Entry parameter into the cell.
    t: Py<PyArray1<f32>>,
    /// Cell coordinates at the traced level.
    cell: Py<PyArray2<u32>>,
    /// The traced level.
    level: Py<PyArray1<u8>>,
    /// Entry face.
    face: Py<PyArray1<u8>>,
    /// Attribute index, -1 for none.
    index: Py<PyArray1<i64>>,
}

#[pymethods]
impl TraceResult {
    /// The answers as a dict of arrays (`hit`, `t`, `cell`, `level`, `face`, `index`).
    fn as_dict<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, pyo3::types::PyDict>> {
        let d = pyo3::types::PyDict::new(py);
        d.set_item("hit", &self.hit)?;
        d.set_item("t", &self.t)?;
        d.set_item("cell", &self.cell)?;
        d.set_item("level", &self.level)?;
        d.set_item("face", &self.face)?;
        d.set_item("index", &self.index)?;
        Ok(d)
    }

    /// The number of rays answered.
    fn __len__(&self, py: Python<'_>) -> usize {
        self.hit.bind(py).len()
    }

    /// `vdag.TraceResult(N rays)`.
    fn __repr__(&self, py: Python<'_>) -> String {
        format!("vdag.TraceResult({} rays)", self.hit.bind(py).len())
    }
}

/// Rays traced at a time on the CPU: the rays and hits of a chunk (20 MiB)
/// are set up, traced and split into columns, each on all cores, without
/// holding those of the whole batch.
const CHUNK_RAYS: usize = 1 << 18;

/// The answers as columns, filled chunk by chunk.
struct Columns {
    hit: Vec<bool>,
    t: Vec<f32>,
    cell: Vec<u32>,
    level: Vec<u8>,
    face: Vec<u8>,
    index: Vec<i64>,
}

impl Columns {
    fn new(n: usize) -> Self {
        Columns {
            hit: vec![false; n],
            t: vec![0.0; n],
            cell: vec![0; 3 * n],
            level: vec![0; n],
            face: vec![0; n],
            index: vec![-1; n],
        }
    }

    /// Writes the answers of rays `first..first + hits.len()`, on all
    /// cores; misses keep the zero / -1 they were made with.
    fn fill(&mut self, first: usize, hits: &[Hit]) {
        const PART: usize = 4096;
        let end = first + hits.len();
        self.hit[first..end]
            .par_chunks_mut(PART)
            .zip(self.t[first..end].par_chunks_mut(PART))
            .zip(self.cell[3 * first..3 * end].par_chunks_mut(3 * PART))
            .zip(self.level[first..end].par_chunks_mut(PART))
            .zip(self.face[first..end].par_chunks_mut(PART))
            .zip(self.index[first..end].par_chunks_mut(PART))
            .zip(hits.par_chunks(PART))
            .for_each(|((((((hit, t), cell), level), face), index), hits)| {
                for (i, h) in hits.iter().enumerate().filter(|(_, h)| h.hit) {
                    hit[i] = true;
                    t[i] = h.t;
                    cell[3 * i..3 * i + 3].copy_from_slice(&h.voxel);
                    level[i] = h.level;
                    face[i] = h.face;
                    index[i] = h.index.map_or(-1, |x| i64::try_from(x).unwrap_or(i64::MAX));
                }
            });
    }

    fn into_result(self, py: Python<'_>) -> TraceResult {
        let n = self.hit.len();
        TraceResult {
            hit: self.hit.into_pyarray(py).unbind(),
            t: self.t.into_pyarray(py).unbind(),
            cell: Array2::from_shape_vec((n, 3), self.cell)
                .expect("three coordinates per hit")
                .into_pyarray(py)
                .unbind(),
            level: self.level.into_pyarray(py).unbind(),
            face: self.face.into_pyarray(py).unbind(),
            index: self.index.into_pyarray(py).unbind(),
        }
    }
}

impl PyDag {
    /// The GPU tracer of this file, made on first use.
    pub(crate) fn gpu_tracer(&self, py: Python<'_>) -> PyResult<Arc<GpuTracer>> {
        let mut slot = self
            .gpu
            .lock()
            .map_err(|_| pyo3::exceptions::PyRuntimeError::new_err("GPU tracer poisoned"))?;
        if let Some(gpu) = slot.as_ref() {
            return Ok(Arc::clone(gpu));
        }
        let dag = self.dag(py)?;
        let options = GpuOptions::default();
        let made = py.detach(|| match &dag {
            AnyDag::V1(d) => GpuTracer::new(d, &options),
            AnyDag::V2(d) => GpuTracer::new_v2(d.header(), d.levels(), d.color_table(), &options),
        });
        let gpu = Arc::new(
            made.map_err(|e| errors::plain(py, "GpuError", format!("backend=\"gpu\": {e}")))?,
        );
        *slot = Some(Arc::clone(&gpu));
        Ok(gpu)
    }
}

/// Checks a level of detail against the file's depth.
/// The CPU tracer of a file of either version, with the answers of the 1.0
/// file of the same voxels: a 2.0 file is traced through its expanded levels
/// (spec §23.12), made once per `Dag` and kept in `expansion`, or in place
/// where they do not expand.
pub(crate) fn cpu_tracer<'a>(
    dag: &AnyDag<'a>,
    expansion: &std::sync::OnceLock<Option<dagtrace::Expansion>>,
) -> Result<Tracer<'a>, TraceError> {
    match dag {
        AnyDag::V1(d) => Tracer::new(d),
        AnyDag::V2(d) => match expansion.get_or_init(|| dagtrace::Expansion::new(d.levels())) {
            Some(e) => Tracer::from_v2_expansion(d, e),
            None => Tracer::from_v2_in_place(d),
        },
    }
}

pub(crate) fn check_level(level: Option<u8>, depth: u8) -> PyResult<()> {
    match level {
        Some(l) if !(1..=depth).contains(&l) => Err(PyValueError::new_err(format!(
            "level {l} is outside 1..={depth} (the file's depth)"
        ))),
        _ => Ok(()),
    }
}

impl PyDag {
    /// `Dag.trace` (file.rs holds its Python signature and docstring).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn trace_rays(
        &self,
        py: Python<'_>,
        origins: &Bound<'_, PyAny>,
        directions: &Bound<'_, PyAny>,
        tmin: f64,
        tmax: f64,
        level: Option<u8>,
        backend: &str,
    ) -> PyResult<TraceResult> {
        let dag = self.dag(py)?;
        check_level(level, dag.header().depth)?;
        if tmin.is_nan() || tmax.is_nan() {
            return Err(PyValueError::new_err("tmin and tmax must not be NaN"));
        }
        let origins = Points::extract("origins", origins)?;
        let directions = Points::extract("directions", directions)?;
        if origins.rows() != directions.rows() {
            return Err(PyValueError::new_err(format!(
                "origins has {} rows but directions has {}",
                origins.rows(),
                directions.rows()
            )));
        }
        let gpu = match backend {
            "cpu" => None,
            "gpu" => Some(self.gpu_tracer(py)?),
            other => {
                return Err(PyValueError::new_err(format!(
                    "backend must be \"cpu\" or \"gpu\", not {other:?}"
                )));
            }
        };
        let (o, d) = (origins.flat()?, directions.flat()?);
        let n = origins.rows();
        let (tmin, tmax) = (tmin as f32, tmax as f32);
        let ray = |i: usize| Ray {
            origin: o.row(i),
            dir: d.row(i),
            tmin,
            tmax,
            level,
        };
        let traced = py.detach(|| -> Result<Columns, String> {
            let mut columns = Columns::new(n);
            match gpu {
                // The GPU tracer streams a batch in chunks of its own.
                Some(gpu) => {
                    let rays: Vec<Ray> = (0..n).into_par_iter().map(ray).collect();
                    columns.fill(0, &gpu.trace(&rays).map_err(|e| e.to_string())?);
                }
                None => {
                    let tracer = cpu_tracer(&dag, &self.expansion).map_err(|e| e.to_string())?;
                    let mut rays = Vec::with_capacity(CHUNK_RAYS.min(n));
                    let mut hits = vec![Hit::MISS; CHUNK_RAYS.min(n)];
                    for first in (0..n).step_by(CHUNK_RAYS) {
                        let end = (first + CHUNK_RAYS).min(n);
                        rays.clear();
                        rays.par_extend((first..end).into_par_iter().map(ray));
                        let hits = &mut hits[..end - first];
                        tracer
                            .trace_batch_into(&rays, hits)
                            .map_err(|e| e.to_string())?;
                        columns.fill(first, hits);
                    }
                }
            }
            Ok(columns)
        });
        let columns =
            traced.map_err(|m| errors::plain(py, "TraceError", format!("{}: {m}", self.path)))?;
        Ok(columns.into_result(py))
    }
}
