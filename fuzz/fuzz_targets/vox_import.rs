//! Fuzz target `vox_import`: runs `dagtool::fuzzing::vox_import` (see that function for
//! the properties checked) on every input.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| dagtool::fuzzing::vox_import(data));
