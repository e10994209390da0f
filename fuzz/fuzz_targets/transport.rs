//! Fuzz target `transport`: runs `dagfmt::fuzzing::transport` (see that function for the
//! properties checked) on every input.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| dagfmt::fuzzing::transport(data));
