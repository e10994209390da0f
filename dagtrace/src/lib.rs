//! `dagtrace`: ray tracing `.vdag` sparse voxel DAGs.
#![deny(missing_docs)]
