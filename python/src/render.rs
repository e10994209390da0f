//! `Dag.render` and `vdag.render`: the image `dagtrace render` writes, as an
//! (H, W, 3) uint8 array.
//!
//! The steps are `dagtrace render`'s (dagtrace/src/main.rs, `render_cmd`):
//! the same camera (framing the occupied box without `camera_pos`), the same
//! library calls for each shade and back end, so the pixels are the same.

use std::path::PathBuf;

use dagfmt::AnyDag;
use dagtrace::camera::Camera;
use dagtrace::lit::{LitOptions, render_lit};
use dagtrace::render::{Shade, render as render_shaded, shade_hits};
use numpy::IntoPyArray;
use numpy::PyArray3;
use numpy::ndarray::Array3;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

use crate::errors;
use crate::file::{PyDag, open};
use crate::trace::{check_level, cpu_tracer};

/// What `render` is asked for, beyond the file.
pub(crate) struct View {
    width: u32,
    height: u32,
    camera_pos: Option<[f64; 3]>,
    look_at: Option<[f64; 3]>,
    fov: f64,
    shade: Option<Shade>,
    lit: LitOptions,
    level: Option<u8>,
    gpu: bool,
}

#[allow(clippy::too_many_arguments)]
pub(crate) fn view(
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
) -> PyResult<View> {
    if !(1..=16384).contains(&width) || !(1..=16384).contains(&height) {
        return Err(PyValueError::new_err(format!(
            "width and height must be 1..=16384, got {width}x{height}"
        )));
    }
    if camera_pos.is_some() != look_at.is_some() {
        return Err(PyValueError::new_err(
            "camera_pos and look_at go together: give both or neither",
        ));
    }
    let shade = match shade {
        "lit" => None,
        "normal" => Some(Shade::Normal),
        "depth" => Some(Shade::Depth),
        "color" => Some(Shade::Color),
        other => {
            return Err(PyValueError::new_err(format!(
                "shade must be \"lit\", \"normal\", \"depth\" or \"color\", not {other:?}"
            )));
        }
    };
    let given = [
        ("sun", sun.is_some()),
        ("ao_rays", ao_rays.is_some()),
        ("ao_radius", ao_radius.is_some()),
        ("samples", samples.is_some()),
    ];
    if shade.is_some()
        && let Some((name, _)) = given.iter().find(|(_, g)| *g)
    {
        return Err(PyValueError::new_err(format!(
            "{name} applies to shade=\"lit\" only"
        )));
    }
    let defaults = LitOptions::default();
    let lit = LitOptions {
        sun: sun.unwrap_or(defaults.sun),
        ao_rays: ao_rays.unwrap_or(defaults.ao_rays),
        ao_radius,
        samples: samples.unwrap_or(defaults.samples),
    };
    lit.check()
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    let gpu = match backend {
        "cpu" => false,
        "gpu" => true,
        other => {
            return Err(PyValueError::new_err(format!(
                "backend must be \"cpu\" or \"gpu\", not {other:?}"
            )));
        }
    };
    Ok(View {
        width,
        height,
        camera_pos,
        look_at,
        fov,
        shade,
        lit,
        level,
        gpu,
    })
}

impl PyDag {
    /// Renders `view` into RGB8 rows from the top.
    pub(crate) fn render_view<'py>(
        &self,
        py: Python<'py>,
        v: &View,
    ) -> PyResult<Bound<'py, PyArray3<u8>>> {
        let dag = self.dag(py)?;
        check_level(v.level, dag.header().depth)?;
        let gpu = if v.gpu {
            Some(self.gpu_tracer(py)?)
        } else {
            None
        };
        let pixels = py.detach(|| -> Result<Vec<u8>, String> {
            let tracer = cpu_tracer(&dag, &self.expansion).map_err(|e| e.to_string())?;
            let aspect = f64::from(v.width) / f64::from(v.height);
            let camera = match (v.camera_pos, v.look_at) {
                (Some(position), Some(look_at)) => Camera {
                    position,
                    look_at,
                    up: [0.0, 1.0, 0.0],
                    fov_y_degrees: v.fov,
                },
                // The automatic view, as `dagtrace render` frames each version.
                _ => Camera {
                    fov_y_degrees: v.fov,
                    ..match &dag {
                        AnyDag::V1(d) => Camera::automatic(d, aspect),
                        AnyDag::V2(d) => match tracer.occupied_box() {
                            Some((lo, hi)) => Camera::looking_at_box(lo, hi, aspect),
                            None => Camera::looking_at_cube(
                                d.header().root_min,
                                d.header().root_size,
                                aspect,
                            ),
                        },
                    }
                },
            };
            let frame = camera.frame().map_err(|e| e.to_string())?;
            match (v.shade, &gpu) {
                (Some(shade), None) => {
                    render_shaded(&tracer, &frame, v.width, v.height, shade, v.level)
                        .map_err(|e| e.to_string())
                }
                (Some(shade), Some(gpu)) => {
                    // The f64 camera rays of the CPU path, as `dagtrace render` does.
                    let rays = frame.rays(v.width, v.height, v.level);
                    let hits = gpu.trace(&rays).map_err(|e| e.to_string())?;
                    Ok(shade_hits(&hits, shade, tracer.colors()))
                }
                (None, None) => render_lit(&tracer, &frame, v.width, v.height, v.level, &v.lit)
                    .map_err(|e| e.to_string()),
                (None, Some(gpu)) => gpu
                    .render_lit(&camera, v.width, v.height, v.level, &v.lit, |i| {
                        tracer.color(i)
                    })
                    .map_err(|e| e.to_string()),
            }
        });
        let pixels =
            pixels.map_err(|m| errors::plain(py, "TraceError", format!("{}: {m}", self.path)))?;
        let image = Array3::from_shape_vec((v.height as usize, v.width as usize, 3), pixels)
            .map_err(|e| errors::plain(py, "TraceError", e.to_string()))?;
        Ok(image.into_pyarray(py))
    }
}

/// Opens `path` (validating it) and renders it: `vdag.open(path).render(...)`.
/// Returns an (height, width, 3) uint8 array, the pixels `dagtrace render`
/// writes for the same options.
#[pyfunction]
#[pyo3(signature = (path, width = 1280, height = 720, camera_pos = None, look_at = None, fov = 40.0, shade = "lit", sun = None, ao_rays = None, ao_radius = None, samples = None, level = None, backend = "cpu"))]
#[allow(clippy::too_many_arguments)]
pub fn render<'py>(
    py: Python<'py>,
    path: PathBuf,
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
) -> PyResult<Bound<'py, PyArray3<u8>>> {
    let v = view(
        width, height, camera_pos, look_at, fov, shade, sun, ao_rays, ao_radius, samples, level,
        backend,
    )?;
    open(py, path, true)?.render_view(py, &v)
}
