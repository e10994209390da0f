//! dagfmt's integration tests (one test binary, one module per concern).

mod fuzz_smoke;
mod integrity;
mod resource_bounds;
mod roundtrip;
mod rules;
