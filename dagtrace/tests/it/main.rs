//! dagtrace's integration tests (one test binary, one module per concern).

mod bad_input;
mod cases;
mod cli;
mod common;
mod format2;
#[cfg(feature = "gpu")]
mod gpu;
mod lit;
mod oracle;
mod packed_colors;
mod props;
