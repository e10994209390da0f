//! Replacing a file never changes the bytes of an existing memory map of it:
//! the tools write a temporary file and rename it over the old name
//! (spec/VDAG.md §18), so a reader that mapped the old file keeps reading the
//! old, complete content, while a new open sees the new file.

use dagfmt::mmap::MappedFile;

use crate::common::{box_mesh, run_ok};

#[test]
fn replacing_a_mapped_file_leaves_the_map_unchanged() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let small = d.join("small.obj");
    box_mesh([0.0; 3], [1.0; 3]).write(&small);
    let other = d.join("other.obj");
    box_mesh([0.0; 3], [3.0, 1.0, 2.0]).write(&other);
    let vdag = d.join("scene.vdag");
    let p = vdag.to_str().unwrap();
    run_ok(&[
        "convert",
        small.to_str().unwrap(),
        "-o",
        p,
        "--depth",
        "6",
        "-q",
    ]);
    let map = MappedFile::open(&vdag).unwrap();
    let before = map.bytes().to_vec();
    assert!(dagfmt::validate::validate(map.bytes()).is_empty());

    // convert --force replaces it with a different (longer) DAG ...
    run_ok(&[
        "convert",
        other.to_str().unwrap(),
        "-o",
        p,
        "--depth",
        "7",
        "--force",
        "-q",
    ]);
    let replaced = std::fs::read(&vdag).unwrap();
    assert_ne!(replaced, before, "the file on disk is the new one");
    // ... and the old map still reads the old, valid file, every byte of it.
    assert_eq!(map.bytes(), before.as_slice());
    assert!(dagfmt::validate::validate(map.bytes()).is_empty());

    // The same for unpack --force over a mapped file.
    let zst = d.join("scene.vdag.zst");
    run_ok(&["pack", p, zst.to_str().unwrap()]);
    let second = MappedFile::open(&vdag).unwrap();
    assert_eq!(second.bytes(), replaced.as_slice());
    let older = d.join("older.vdag");
    std::fs::write(&older, &before).unwrap();
    let older_zst = d.join("older.vdag.zst");
    run_ok(&["pack", older.to_str().unwrap(), older_zst.to_str().unwrap()]);
    run_ok(&["unpack", older_zst.to_str().unwrap(), p, "--force"]);
    assert_eq!(std::fs::read(&vdag).unwrap(), before);
    assert_eq!(second.bytes(), replaced.as_slice());
    assert_eq!(map.bytes(), before.as_slice());
}
