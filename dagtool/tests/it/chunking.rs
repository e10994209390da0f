//! The output does not depend on the chunk size or the thread count.

use crate::common::{ObjMesh, box_mesh, convert, meshes_dir, sphere_mesh};
use crate::surface::Lcg;

fn bytes_with(obj: &std::path::Path, depth: u8, extra: &[&str]) -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out.vdag");
    convert(obj, &out, depth, extra);
    std::fs::read(&out).unwrap()
}

fn check_invariant(obj: &std::path::Path, depth: u8, extra: &[&str]) {
    // Chunk 2^depth is the whole volume: unchunked.
    let whole_bits = depth.to_string();
    let mut reference = vec!["--chunk-bits", whole_bits.as_str()];
    reference.extend_from_slice(extra);
    let whole = bytes_with(obj, depth, &reference);
    for bits in ["2", "3", "5"] {
        let mut args = vec!["--chunk-bits", bits];
        args.extend_from_slice(extra);
        assert!(
            whole == bytes_with(obj, depth, &args),
            "{} chunk 2^{bits} {extra:?} differs from unchunked",
            obj.display()
        );
    }
    let mut args = vec!["--threads", "1", "--chunk-bits", "4"];
    args.extend_from_slice(extra);
    assert!(whole == bytes_with(obj, depth, &args), "one thread differs");
}

#[test]
fn chunked_equals_unchunked() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Lcg(99);
    let mut m = sphere_mesh([0.0, 0.0, 0.0], 2.0, 2);
    m.append(&box_mesh([-1.0, -0.5, -3.0], [3.0, 0.5, -1.5]));
    let mut extra = ObjMesh::default();
    for _ in 0..20 {
        let p = [0, 1, 2].map(|_| [0, 1, 2].map(|_| rng.next_f64() * 6.0 - 3.0));
        extra.add_triangle(p[0], p[1], p[2]);
    }
    m.append(&extra);
    let obj = dir.path().join("mix.obj");
    m.write(&obj);
    check_invariant(&obj, 7, &[]);
    let closed = dir.path().join("closed.obj");
    let mut c = sphere_mesh([0.0, 0.0, 0.0], 2.0, 2);
    c.append(&box_mesh([-1.0, -0.5, -3.0], [3.0, 0.5, -1.5]));
    c.write(&closed);
    check_invariant(&closed, 7, &["--solid"]);
    // Open (the random triangles): the majority rule.
    check_invariant(&obj, 6, &["--solid"]);
}

#[test]
fn chunked_equals_unchunked_on_real_meshes() {
    let Some(dir) = meshes_dir() else { return };
    for name in ["cow.obj", "suzanne.obj"] {
        let obj = dir.join(name);
        check_invariant(&obj, 7, &[]);
        check_invariant(&obj, 6, &["--solid"]);
    }
}
