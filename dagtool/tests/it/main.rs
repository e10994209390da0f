//! dagtool's integration tests: one binary, one module per concern.
//!
//! The voxel sets the converter writes are compared with `reference`, an
//! independent brute-force voxelizer (every voxel of a triangle's bounding box
//! tested with the textbook Akenine-Möller triangle/box test), on procedural
//! and real meshes; the command line is tested end to end through the binary.

mod common;
mod reference;

mod bad_input;
mod chunking;
mod cli_errors;
mod colors;
mod commands;
mod format2;
mod formats;
mod fuzz_smoke;
mod mapped_files;
mod meshes;
mod out_of_core;
mod packed_colors;
mod progress;
mod readme;
mod regions;
mod solid;
mod surface;
mod verify;
mod voxel_lists;
