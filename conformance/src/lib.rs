//! The `.vdag` conformance suite (spec/CONFORMANCE.md).
//!
//! - [`oracle`]: the independent oracle: what a tracer may answer for a ray,
//!   computed by brute force over the occupied cells, with the tolerance rules;
//! - [`expect`]: the expectation file format and the judge of answers;
//! - [`judge`]: judging any answers on any file by the acceptance rule
//!   itself, without expectations (scales to millions of rays);
//! - [`scenes`] and [`malformed`]: the tracer and validator cases;
//! - [`bless`]: writing the committed case files, reproducibly;
//! - [`suite`]: running the cases against in-process or external tracers and
//!   validators;
//! - [`model`], [`model2`] (format 2.0), [`mesh`], [`rng`]: file surgery, procedural meshes and a
//!   fixed random stream for the generators.
#![deny(missing_docs)]

pub mod bless;
pub mod expect;
pub mod judge;
pub mod malformed;
pub mod mesh;
pub mod model;
pub mod model2;
pub mod oracle;
pub mod rng;
pub mod scenes;
pub mod suite;
