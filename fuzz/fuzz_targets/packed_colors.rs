//! Fuzz target `packed_colors`: runs `dagfmt::fuzzing::packed_colors` (see that function for
//! the properties checked) on every input.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| dagfmt::fuzzing::packed_colors(data));
