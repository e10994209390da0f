//! Fuzz target `validator`: runs `dagfmt::fuzzing::validator` (see that function for the
//! properties checked) on every input.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| dagfmt::fuzzing::validator(data));
