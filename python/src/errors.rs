//! Raising the package's exceptions from Rust errors.
//!
//! The exception classes are defined in Python (`vdag/errors.py`), so that
//! they are ordinary classes with typed attributes (`code`, `offset`,
//! `message`) that the stubs describe; Rust looks them up by name.

use dagfmt::FormatError;
use pyo3::prelude::*;
use pyo3::types::PyTuple;

/// Makes an instance of `vdag.errors.<class>(message, code, offset)`.
pub(crate) fn vdag_error(
    py: Python<'_>,
    class: &str,
    message: String,
    code: Option<&str>,
    offset: Option<u64>,
) -> PyErr {
    let made = py
        .import("vdag.errors")
        .and_then(|m| m.getattr(class))
        .and_then(|c| {
            let args = PyTuple::new(
                py,
                [
                    message.clone().into_pyobject(py)?.into_any(),
                    code.into_pyobject(py)?.into_any(),
                    offset.into_pyobject(py)?.into_any(),
                ],
            )?;
            c.call1(args)
        });
    match made {
        Ok(instance) => PyErr::from_value(instance),
        // The package is broken (vdag.errors missing): still say what failed.
        Err(e) => e,
    }
}

/// A format error of the file at `path`: `vdag.InvalidFileError` with the
/// spec's code and the byte offset.
pub(crate) fn format_error(py: Python<'_>, path: &str, e: &FormatError) -> PyErr {
    vdag_error(
        py,
        "InvalidFileError",
        format!("{path}: {e}"),
        Some(e.code.code()),
        Some(e.offset),
    )
}

/// Any other failure of the package, as `vdag.errors.<class>` without a code.
pub(crate) fn plain(py: Python<'_>, class: &str, message: impl Into<String>) -> PyErr {
    vdag_error(py, class, message.into(), None, None)
}
