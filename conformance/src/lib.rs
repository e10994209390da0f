//! The `.vdag` conformance suite.
#![deny(missing_docs)]
