//! `dagtool`'s library: the mesh-to-`.vdag` converter and the file commands.
//!
//! - [`geom`]: exact triangle/box predicates on a fixed-point lattice;
//! - [`input`]: the input formats, one module each (OBJ, glTF, PLY, STL,
//!   LAS/LAZ, MagicaVoxel, binvox), producing meshes, point streams or
//!   voxel grids;
//! - [`mesh`]: the common triangle mesh and its colours, the root cube,
//!   snapping;
//! - [`cloud`]: voxels of point clouds and voxel grids, sorted out of core;
//! - [`voxelize`]: conservative surface voxelization of triangles into chunks;
//! - [`solid`]: interior fill by exact crossing parity;
//! - [`pipeline`]: binning, parallel chunked voxelization in Morton order;
//! - [`voxlist`]: the text and binary voxel list formats;
//! - [`convert`]: the `convert` command (pipeline + builder + atomic output);
//! - [`external`]: the out-of-core DAG build (runs spilled to unnamed
//!   temporary files, merged level by level within a memory budget), and the
//!   in-memory merge of runs;
//! - [`dedup`]: the in-memory merge's hash-sharded tables, looked up on every
//!   core with first-seen indices;
//! - [`region`]: region builds: a cell of the root cube and the part file
//!   that holds one (its placement section);
//! - [`merge`]: the `merge` command (parts joined by the in-memory or the
//!   out-of-core level merge into the file of one whole conversion);
//! - [`output`]: atomic file output;
//! - [`demo`]: the whole pipeline on a built-in scene;
//! - [`cmd`]: `validate`, `info`, `dump`, `pack`, `unpack`;
//! - [`verify`]: the `verify` command (ray casts on the mesh and on the DAG);
//! - [`verify_points`]: `verify` for point clouds (exact voxel checks);
//! - `fuzzing` (hidden): the harnesses of the importer fuzz targets in `fuzz/`.
#![deny(missing_docs)]

pub mod cloud;
pub mod cmd;
pub mod convert;
pub mod dedup;
pub mod demo;
pub mod error;
pub mod external;
#[doc(hidden)]
pub mod fuzzing;
pub mod geom;
pub mod input;
pub mod merge;
pub mod mesh;
pub mod output;
pub mod pipeline;
pub mod region;
pub mod solid;
pub mod sysinfo;
pub mod verify;
pub mod verify_points;
pub mod voxelize;
pub mod voxlist;

pub use error::ConvertError;
