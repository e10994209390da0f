//! Text and binary voxel lists convert to exactly the listed voxels.

use std::collections::BTreeSet;

use crate::common::{dir_entries, run, run_ok, voxel_codes};
use crate::surface::Lcg;

fn random_voxels(n: usize, res: u32, seed: u64) -> Vec<[u32; 3]> {
    let mut rng = Lcg(seed);
    (0..n)
        .map(|_| [0, 1, 2].map(|_| (rng.next_f64() * res as f64) as u32))
        .collect()
}

fn codes(voxels: &[[u32; 3]]) -> Vec<u64> {
    let set: BTreeSet<u64> = voxels
        .iter()
        .map(|v| dagfmt::morton::encode(v[0], v[1], v[2]))
        .collect();
    set.into_iter().collect()
}

#[test]
fn text_list() {
    let dir = tempfile::tempdir().unwrap();
    let mut voxels = random_voxels(3000, 100, 1);
    voxels.push(voxels[0]); // a duplicate
    let mut text = String::from("# a voxel list\n\n");
    for (i, v) in voxels.iter().enumerate() {
        if i % 7 == 0 {
            text.push_str(&format!("{}\t{}  {} # comment\n", v[0], v[1], v[2]));
        } else {
            text.push_str(&format!("{} {} {}\n", v[0], v[1], v[2]));
        }
    }
    let input = dir.path().join("v.txt");
    std::fs::write(&input, text).unwrap();
    // Without --depth: the smallest depth holding coordinate 99 is 7.
    let out = dir.path().join("v.vdag");
    run_ok(&[
        "convert",
        input.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "-q",
    ]);
    let bytes = std::fs::read(&out).unwrap();
    let dag = dagfmt::AnyDag::open(&bytes).unwrap();
    assert_eq!(dag.header().depth, 7);
    assert_eq!(dag.header().root_min, [0.0; 3]);
    assert_eq!(dag.header().root_size, 128.0);
    assert_eq!(voxel_codes(&out), codes(&voxels));
    // With --depth 9.
    let out9 = dir.path().join("v9.vdag");
    run_ok(&[
        "convert",
        input.to_str().unwrap(),
        "-o",
        out9.to_str().unwrap(),
        "--depth",
        "9",
        "-q",
    ]);
    assert_eq!(voxel_codes(&out9), codes(&voxels));
}

#[test]
fn binary_list() {
    let dir = tempfile::tempdir().unwrap();
    let voxels = random_voxels(5000, 1 << 10, 2);
    let input = dir.path().join("v.bin");
    let mut bytes = Vec::new();
    dagtool::voxlist::write_binary(&mut bytes, 10, &voxels).unwrap();
    // The documented layout, byte for byte.
    assert_eq!(&bytes[..4], b"VVOX");
    assert_eq!(u32::from_le_bytes(bytes[4..8].try_into().unwrap()), 1);
    assert_eq!(u32::from_le_bytes(bytes[8..12].try_into().unwrap()), 10);
    assert_eq!(u64::from_le_bytes(bytes[12..20].try_into().unwrap()), 5000);
    assert_eq!(bytes.len(), 20 + 12 * 5000);
    assert_eq!(
        u32::from_le_bytes(bytes[20..24].try_into().unwrap()),
        voxels[0][0]
    );
    std::fs::write(&input, &bytes).unwrap();
    let out = dir.path().join("v.vdag");
    run_ok(&[
        "convert",
        input.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "-q",
    ]);
    assert_eq!(voxel_codes(&out), codes(&voxels));
    let file = std::fs::read(&out).unwrap();
    assert_eq!(dagfmt::AnyDag::open(&file).unwrap().header().depth, 10);
    assert!(dagfmt::validate::validate(&file).is_empty());
}

#[test]
fn bad_lists() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = d.join("out.vdag");
    let cases: Vec<(&str, Vec<u8>, Vec<&str>, &str)> = vec![
        (
            "a.txt",
            b"1 2 3\n4 5\n".to_vec(),
            vec![],
            "a.txt:2: expected three coordinates",
        ),
        (
            "b.txt",
            b"1 2 3\n4 -5 6\n".to_vec(),
            vec![],
            "b.txt:2: `-5` is not a non-negative integer",
        ),
        ("c.txt", b"1 2 3 4\n".to_vec(), vec![], "unexpected `4`"),
        (
            "d.txt",
            b"1 2 40\n".to_vec(),
            vec!["--depth", "5"],
            "outside the volume",
        ),
        (
            "f.bin",
            [
                &b"VVOX"[..],
                &1u32.to_le_bytes(),
                &4u32.to_le_bytes(),
                &2u64.to_le_bytes(),
                &[0u8; 12],
            ]
            .concat(),
            vec![],
            "declares 2 voxels",
        ),
        (
            "g.bin",
            [
                &b"VVOX"[..],
                &1u32.to_le_bytes(),
                &2u32.to_le_bytes(),
                &1u64.to_le_bytes(),
                &[9u8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0],
            ]
            .concat(),
            vec![],
            "outside the 4^3 volume",
        ),
        (
            "h.bin",
            [
                &b"VVOX"[..],
                &2u32.to_le_bytes(),
                &2u32.to_le_bytes(),
                &0u64.to_le_bytes(),
            ]
            .concat(),
            vec![],
            "not a version-1",
        ),
        (
            "i.bin",
            [
                &b"VVOX"[..],
                &1u32.to_le_bytes(),
                &30u32.to_le_bytes(),
                &0u64.to_le_bytes(),
            ]
            .concat(),
            vec![],
            "depth 30",
        ),
        ("j.bin", b"VVOX\x01".to_vec(), vec![], "shorter than"),
    ];
    for (name, content, extra, expected) in cases {
        let p = d.join(name);
        std::fs::write(&p, content).unwrap();
        let before = dir_entries(d);
        let mut args = vec!["convert", p.to_str().unwrap(), "-o", out.to_str().unwrap()];
        args.extend(extra);
        let o = run(&args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{name}: {err}");
        assert_eq!(err.lines().count(), 1);
        assert!(
            err.starts_with("dagtool: error: ") && err.contains(expected),
            "{name}: {err}"
        );
        assert_eq!(dir_entries(d), before);
    }
    // A binary list's depth must match --depth when given.
    let p = d.join("k.bin");
    let mut bytes = Vec::new();
    dagtool::voxlist::write_binary(&mut bytes, 4, &[[1, 2, 3]]).unwrap();
    std::fs::write(&p, bytes).unwrap();
    let o = run(&[
        "convert",
        p.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--depth",
        "6",
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("depth-4 voxel list but --depth 6"));
    // --solid and --colors need a mesh.
    let o = run(&[
        "convert",
        p.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--solid",
    ]);
    assert_eq!(o.status.code(), Some(2));
}

/// An empty voxel list (text or binary) and a mesh without triangles are an
/// empty volume, not an error (spec/VDAG.md § 7): a tile of a larger scene is
/// often empty. The files validate, hold no voxel, and every ray misses them.
#[test]
fn empty_inputs_make_the_empty_volume() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let binary_empty = [
        &b"VVOX"[..],
        &1u32.to_le_bytes(),
        &7u32.to_le_bytes(),
        &0u64.to_le_bytes(),
    ]
    .concat();
    let inputs: Vec<(&str, Vec<u8>, Vec<&str>, u8)> = vec![
        ("comments.txt", b"# only comments\n".to_vec(), vec![], 2),
        ("blank.txt", Vec::new(), vec!["--depth", "12"], 12),
        ("empty.bin", binary_empty, vec![], 7),
        (
            "nothing.obj",
            b"# nothing here\n".to_vec(),
            vec!["--depth", "5"],
            5,
        ),
        // In format 1.0: the smallest file of spec § 15 (checked below).
        (
            "points.obj",
            b"v 0 0 0\nv 1 0 0\n".to_vec(),
            vec!["--depth", "2", "--format-version", "1"],
            2,
        ),
    ];
    for (name, bytes, extra, depth) in inputs {
        let input = d.join(name);
        std::fs::write(&input, bytes).unwrap();
        let out = d.join(format!("{name}.vdag"));
        let mut args = vec![
            "convert",
            input.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ];
        args.extend(extra);
        run_ok(&args);
        let file = std::fs::read(&out).unwrap();
        assert!(dagfmt::validate::validate(&file).is_empty(), "{name}");
        let dag = dagfmt::AnyDag::open(&file).unwrap();
        assert!(dag.voxel_codes().unwrap().is_empty(), "{name}");
        assert_eq!(dag.header().depth, depth, "{name}");
        assert_eq!(dag.header().voxel_count, 0, "{name}");
        let ray = dagfmt::batch::Ray::new([-1.0, 0.5, 0.5], [1.0, 0.0, 0.0]);
        let hits = dagtrace::Tracer::from_any(&dag)
            .unwrap()
            .trace_batch(&[ray])
            .unwrap();
        assert!(!hits[0].hit, "{name}");
    }
    // The empty mesh at depth 2 is the smallest valid file of spec/VDAG.md § 15,
    // byte for byte in its header checksum.
    let smallest = std::fs::read(d.join("points.obj.vdag")).unwrap();
    assert_eq!(smallest.len(), 168);
    assert_eq!(smallest[124..128], 0x48EE_91C3u32.to_le_bytes());
}
