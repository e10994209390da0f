//! `vdag._vdag`: the native half of the Python package `vdag` (python/vdag/).
//!
//! The Python package re-exports what is registered here; its `.pyi` stubs
//! (python/vdag/*.pyi) describe every class and function for type checkers,
//! and the docstrings below are what `help()` shows. Each submodule wraps
//! one part of the Rust workspace:
//!
//! - `file`: `open` and the `Dag` class (header, level table, voxels,
//!   colours, point queries) over `dagfmt`'s memory-mapped reader;
//! - `trace`: `Dag.trace`, numpy rays through `dagtrace`'s batch API (CPU,
//!   all cores, without the GIL) or its GPU tracer;
//! - `render`: `Dag.render` and `render`, the images of `dagtrace render`;
//! - `convert`: `convert`, `dagtool convert` with a progress callable;
//! - `errors`: the exceptions (defined in Python, `vdag/errors.py`), raised
//!   with the spec's error codes.
#![deny(missing_docs)]

use pyo3::prelude::*;

mod convert;
mod errors;
mod file;
mod render;
mod trace;

/// The extension module: classes and functions the `vdag` package re-exports.
#[pymodule]
fn _vdag(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<file::PyDag>()?;
    m.add_class::<file::VoxelChunks>()?;
    m.add_class::<trace::TraceResult>()?;
    m.add_function(wrap_pyfunction!(file::open, m)?)?;
    m.add_function(wrap_pyfunction!(file::validate, m)?)?;
    m.add_function(wrap_pyfunction!(convert::convert, m)?)?;
    m.add_function(wrap_pyfunction!(render::render, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
