//! Fuzz target `part_placement`: runs `dagtool::fuzzing::part_placement` (see that
//! function for the properties checked) on every input.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| dagtool::fuzzing::part_placement(data));
