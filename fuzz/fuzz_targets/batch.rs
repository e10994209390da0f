//! Fuzz target `batch`: runs `dagfmt::fuzzing::batch` (see that function for the
//! properties checked) on every input.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| dagfmt::fuzzing::batch(data));
