//! Fuzz target `voxel_list`: runs `dagtool::fuzzing::voxel_list` (see that function for
//! the properties checked) on every input.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| dagtool::fuzzing::voxel_list(data));
