//! Fuzz target `binvox_import`: runs `dagtool::fuzzing::binvox_import` (see that function for
//! the properties checked) on every input.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| dagtool::fuzzing::binvox_import(data));
