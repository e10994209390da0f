//! The progress hook of `ConvertOptions` (what the Python package's
//! `progress` callable is told): its steps come in order, and a conversion
//! with a hook writes the same bytes as one without.

use std::sync::{Arc, Mutex};

use dagtool::convert::{ConvertOptions, ConvertProgress, ProgressHook, convert};

use crate::common::sphere_mesh;

/// Converts `input` at depth 7 into `output` with a hook; returns the steps.
fn steps_of(input: &std::path::Path, output: &std::path::Path) -> Vec<ConvertProgress> {
    let steps = Arc::new(Mutex::new(Vec::new()));
    let mut opts = ConvertOptions::new(input, output, Some(7));
    let seen = Arc::clone(&steps);
    opts.progress_hook = Some(ProgressHook(Arc::new(move |step| {
        seen.lock().unwrap().push(step)
    })));
    convert(&opts).unwrap();
    steps.lock().unwrap().clone()
}

#[test]
fn a_mesh_reports_its_chunks_then_finishing_then_written() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = dir.path().join("sphere.obj");
    sphere_mesh([0.0; 3], 1.0, 2).write(&mesh);
    let hooked = dir.path().join("hooked.vdag");
    let steps = steps_of(&mesh, &hooked);
    let plain = dir.path().join("plain.vdag");
    convert(&ConvertOptions::new(&mesh, &plain, Some(7))).unwrap();
    assert_eq!(
        std::fs::read(&hooked).unwrap(),
        std::fs::read(&plain).unwrap()
    );

    let chunks: Vec<(u64, u64)> = steps
        .iter()
        .filter_map(|s| match *s {
            ConvertProgress::Voxelizing { done, total } => Some((done, total)),
            _ => None,
        })
        .collect();
    assert!(!chunks.is_empty(), "{steps:?}");
    assert!(
        chunks
            .iter()
            .all(|&(done, total)| done >= 1 && done <= total)
    );
    assert!(chunks.windows(2).all(|w| w[0].0 <= w[1].0), "{chunks:?}");
    let tail = &steps[chunks.len()..];
    assert_eq!(tail, [ConvertProgress::Finishing, ConvertProgress::Written]);
}

#[test]
fn a_voxel_list_reports_finishing_then_written() {
    let dir = tempfile::tempdir().unwrap();
    let list = dir.path().join("voxels.txt");
    std::fs::write(&list, "0 0 0\n5 6 7\n127 127 127\n").unwrap();
    let steps = steps_of(&list, &dir.path().join("list.vdag"));
    assert_eq!(
        steps,
        [ConvertProgress::Finishing, ConvertProgress::Written]
    );
}
