//! `dagfmt`: the `.vdag` sparse voxel DAG format (spec/VDAG.md).
//!
//! - [`layout`]: byte positions, constants and the fixed-size on-disk records;
//! - [`reader`]: [`Dag`], a zero-copy view over `&[u8]` that never panics;
//! - [`builder`]: [`DagBuilder`], which makes a file from voxels with
//!   per-level deduplication (also in runs of subtrees, for out-of-core builds);
//! - [`assemble`]: [`assemble::FileLayout`], the one writer of headers and
//!   section tables, which streams section bytes from callbacks;
//! - [`v2`]: the format 2.0 level encoding (§23): the encoder, the one
//!   record decoder [`v2::decode_node`] and the walks over 2.0 levels;
//! - [`v2enc`]: the 2.0 level encoder on every core, within a memory budget
//!   (finished tables spilled to a scratch file);
//! - [`v2file`]: 2.0 files: [`Dag2`], [`AnyDag`] (opens both versions),
//!   the 2.0 writer and the conversions 1.0 ↔ 2.0;
//! - [`validate`]: checks every rule of the spec and reports every violation;
//! - [`packed_colors`]: the compressed colour section (encoder, random-access
//!   decoder, checks);
//! - [`transport`]: the zstd-compressed transport form;
//! - [`batch`]: the text and binary ray and hit batch formats;
//! - [`morton`]: Morton codes, the order of voxels in the DAG;
//! - `fuzzing` (hidden): the harnesses of the fuzz targets in `fuzz/`, also
//!   run by the test suite.
//!
//! The library does no file I/O except two helpers for the tools, [`mmap`]
//! (feature `mmap`), which memory-maps a file for the reader, and [`output`]
//! (feature `output`), which writes a file atomically, and the scratch file
//! of [`v2enc`] when its memory budget is exceeded.
#![deny(missing_docs)]

pub mod assemble;
pub mod batch;
pub mod builder;
mod canonical2;
pub mod error;
pub mod expand;
#[doc(hidden)]
pub mod fuzzing;
pub mod layout;
#[cfg(feature = "mmap")]
pub mod mmap;
pub mod morton;
#[cfg(feature = "output")]
pub mod output;
pub mod packed_colors;
mod prefetch;
pub mod reader;
pub mod stats;
pub mod symmetry;
pub mod transport;
pub mod v2;
pub mod v2enc;
pub mod v2file;
pub mod validate;
mod validate2;

pub use builder::DagBuilder;
pub use error::{ErrorCode, FormatError};
pub use layout::{AttributeKind, SectionKind};
pub use reader::{ColorCursor, ColorTable, Dag, Header, LeafMask, LevelSection, Node, NodeRef};
pub use v2file::{AnyDag, Dag2};
