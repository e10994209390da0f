//! `dagtrace`: ray tracing `.vdag` sparse voxel DAGs on the CPU.
//!
//! [`Tracer`] traces rays against a [`dagfmt::Dag`] opened zero-copy (usually
//! over a [`dagfmt::mmap::MappedFile`]), following the ray/hit semantics of
//! spec/VDAG.md: the answer is the occupied cell (of the ray's level of detail)
//! with the smallest entry parameter, its entry face, and for attribute kind 1
//! the dense index of its first voxel.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use dagtrace::{Ray, Tracer};
//! let file = dagfmt::mmap::MappedFile::open("model.vdag".as_ref())?;
//! let dag = dagfmt::Dag::open(file.bytes())?;
//! let tracer = Tracer::new(&dag)?;
//! let ray = Ray { origin: [0.0, 0.5, 0.5], dir: [1.0, 0.0, 0.0], tmin: 0.0, tmax: f32::INFINITY, level: None };
//! let hit = tracer.trace(&ray)?;
//! # Ok(()) }
//! ```
//!
//! Batches are traced on all cores with rayon ([`Tracer::trace_batch`]);
//! [`camera`] makes primary rays, [`render`] shades them into an image and
//! [`lit`] renders with shadows and ambient occlusion.
#![deny(missing_docs)]

pub mod camera;
pub mod cli;
#[cfg(target_arch = "x86_64")]
mod cpu;
#[cfg(feature = "gpu")]
pub mod gpu;
mod grid;
pub mod lit;
mod node;
mod packet;
mod parallel;
pub mod render;
#[cfg(target_arch = "x86_64")]
mod simd;
mod tables;
#[cfg(test)]
mod testing;
mod tracer;
mod walk;

pub use dagfmt::batch::{Hit, Ray};
pub use walk::{Expansion, Gathers, Lanes, TraceError, Tracer};
