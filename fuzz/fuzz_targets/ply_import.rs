//! Fuzz target `ply_import`: runs `dagtool::fuzzing::ply_import` (see that function for
//! the properties checked) on every input.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| dagtool::fuzzing::ply_import(data));
