//! The one error type of the tool: a one-line message and an exit status.

use std::fmt;

/// What went wrong, as one line for people. `Display` is the line printed
/// after `dagtool: error: `.
#[derive(Debug, thiserror::Error)]
pub enum ConvertError {
    /// The input file is unusable (missing, malformed, empty, non-finite, ...).
    #[error("{0}")]
    Input(String),
    /// The command line asks for something impossible (depth out of range, ...).
    #[error("{0}")]
    Usage(String),
    /// Reading or writing a file failed.
    #[error("{0}")]
    Io(String),
    /// A resource limit (memory, format limits) would be exceeded.
    #[error("{0}")]
    Limit(String),
}

impl ConvertError {
    /// Wraps an I/O error with what was being done.
    pub fn io(what: impl fmt::Display, err: std::io::Error) -> Self {
        ConvertError::Io(format!("{what}: {err}"))
    }

    /// The process exit status for this error: 2 for usage errors, 1 otherwise.
    pub fn exit_code(&self) -> i32 {
        match self {
            ConvertError::Usage(_) => 2,
            _ => 1,
        }
    }
}
