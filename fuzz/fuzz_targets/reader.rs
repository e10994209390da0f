//! Fuzz target `reader`: runs `dagfmt::fuzzing::reader` (see that function for the
//! properties checked) on every input.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| dagfmt::fuzzing::reader(data));
