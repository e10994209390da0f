//! Fuzz target `gltf_import`: runs `dagtool::fuzzing::gltf_import` (see that function for
//! the properties checked) on every input.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| dagtool::fuzzing::gltf_import(data));
