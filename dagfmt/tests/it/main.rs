//! dagfmt's integration tests (one test binary, one module per concern).

mod roundtrip;
mod rules;
