//! `validate`, `info`, `dump`, `pack` and `unpack` on real files.

use std::path::{Path, PathBuf};

use crate::common::{box_mesh, convert, run, run_ok, sphere_mesh};

/// A small valid file (of the default format, 2.0) and its directory.
fn sample() -> (tempfile::TempDir, PathBuf) {
    sample_with(&[])
}

/// The sample in format 1.0, for the tests of 1.0 records and statistics
/// (format2.rs tests `info` and `dump` on 2.0 files).
fn sample_v1() -> (tempfile::TempDir, PathBuf) {
    sample_with(&["--format-version", "1"])
}

fn sample_with(extra: &[&str]) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("s.obj");
    let mut m = sphere_mesh([0.0; 3], 1.0, 2);
    m.append(&box_mesh([-1.5, -0.2, -0.2], [-0.5, 0.2, 0.2]));
    m.write(&obj);
    let out = dir.path().join("s.vdag");
    convert(&obj, &out, 6, extra);
    (dir, out)
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Offset of the first leaf-level section byte (to corrupt a section), in a
/// file of either version.
fn leaf_section_offset(bytes: &[u8]) -> usize {
    let dag = dagfmt::AnyDag::open(bytes).unwrap();
    let leaf = dag
        .sections()
        .iter()
        .find(|s| s.kind == dagfmt::SectionKind::LeafLevel)
        .unwrap();
    leaf.offset as usize
}

#[test]
fn validate_reports_and_exit_codes() {
    let (dir, file) = sample();
    let o = run_ok(&["validate", s(&file)]);
    assert!(String::from_utf8_lossy(&o.stdout).contains("s.vdag: valid"));
    // Corrupt one byte of the leaf section: a section checksum error.
    let mut bytes = std::fs::read(&file).unwrap();
    let at = leaf_section_offset(&bytes);
    bytes[at] ^= 0x10;
    let bad = dir.path().join("bad.vdag");
    std::fs::write(&bad, &bytes).unwrap();
    let o = run(&["validate", s(&bad)]);
    assert_eq!(o.status.code(), Some(1));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.contains("INVALID") && text.contains("E028 section-checksum"),
        "{text}"
    );
    // Text lines name code, offset, level.
    assert!(
        text.lines()
            .any(|l| l.trim_start().starts_with("E028") && l.contains("at byte 0x")),
        "{text}"
    );
    // JSON.
    let o = run(&["validate", "--json", s(&file), s(&bad)]);
    assert_eq!(o.status.code(), Some(1));
    let doc: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(doc["valid"], false);
    assert_eq!(doc["files"][0]["valid"], true);
    assert_eq!(doc["files"][0]["errors"].as_array().unwrap().len(), 0);
    let errors = doc["files"][1]["errors"].as_array().unwrap();
    assert!(errors.iter().any(|e| e["code"] == "E028"
        && e["name"] == "section-checksum"
        && e["offset"].as_u64().is_some()));
    // A missing file: exit 2, one error line, the others still reported.
    let o = run(&["validate", s(&file), s(&dir.path().join("missing.vdag"))]);
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.starts_with("dagtool: error: cannot open") && err.lines().count() == 1,
        "{err}"
    );
    assert!(String::from_utf8_lossy(&o.stdout).contains("s.vdag: valid"));
    // Not a .vdag at all.
    let junk = dir.path().join("junk.vdag");
    std::fs::write(&junk, b"hello").unwrap();
    let o = run(&["validate", s(&junk)]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stdout).contains("E001"));
    // Usage error.
    let o = run(&["validate"]);
    assert_eq!(o.status.code(), Some(2));
}

#[test]
fn info_matches_the_statistics() {
    let (_dir, file) = sample_v1();
    let bytes = std::fs::read(&file).unwrap();
    let dag = dagfmt::Dag::open(&bytes).unwrap();
    let stats = dagfmt::stats::analyze(&dag).unwrap();
    let o = run_ok(&["info", "--json", s(&file)]);
    let doc: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(doc["depth"], 6);
    assert_eq!(doc["voxel_count"], dag.header().voxel_count);
    assert_eq!(doc["file_bytes"], bytes.len() as u64);
    assert_eq!(doc["classic_svdag_bytes"], stats.classic_svdag_bytes as u64);
    assert_eq!(doc["svo_bytes"], stats.svo_bytes as u64);
    assert_eq!(doc["root_size"], dag.header().root_size);
    let levels = doc["levels"].as_array().unwrap();
    assert_eq!(levels.len(), 5);
    for (l, want) in levels.iter().zip(&stats.levels) {
        assert_eq!(l["nodes"], want.node_count);
        assert_eq!(l["bytes"], want.bytes);
        assert_eq!(l["pointer_width"], want.pointer_width);
    }
    assert_eq!(levels[4]["kind"], "leaf");
    assert_eq!(levels[0]["nodes"], 1);
    let o = run_ok(&["info", s(&file)]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("depth:           6 (64^3 voxels)"), "{text}");
    assert!(text.contains(&format!("voxels:          {}", dag.header().voxel_count)));
    assert!(
        text.contains(&format!(
            "classic 32-bit:  {:>16} bytes",
            stats.classic_svdag_bytes
        )),
        "{text}"
    );
    assert!(
        text.contains(&format!("SVO (no dedup):  {:>16} bytes", stats.svo_bytes)),
        "{text}"
    );
    // One row per level with its node count.
    for l in &stats.levels {
        assert!(
            text.lines().any(|line| {
                let f: Vec<&str> = line.split_whitespace().collect();
                f.len() == 7
                    && f[0] == l.level.to_string()
                    && f[2] == l.node_count.to_string()
                    && f[3] == l.bytes.to_string()
            }),
            "level {} row missing:\n{text}",
            l.level
        );
    }
    let o = run(&["info", s(&file.with_extension("nope"))]);
    assert_eq!(o.status.code(), Some(1));
}

#[test]
fn dump_lists_real_bytes() {
    let (_dir, file) = sample_v1();
    let bytes = std::fs::read(&file).unwrap();
    let dag = dagfmt::Dag::open(&bytes).unwrap();
    let o = run_ok(&["dump", s(&file), "--nodes", "3"]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.contains("0x00000000  89 56 44 41 47 0d 0a 1a"),
        "{text}"
    );
    assert!(text.contains("depth D = 6 (64 voxels per axis)"));
    assert!(text.contains(&format!("voxel_count = {}", dag.header().voxel_count)));
    assert!(text.contains("header_crc = ") && text.contains("(ok)"));
    assert!(!text.contains("MISMATCH"));
    // The root node: mask and attribute as the reader sees them.
    let root = dag.node(0, 0).unwrap();
    let line = format!("node 0 (word 0): child mask {:08b}", root.child_mask());
    assert!(text.contains(&line), "{line} not in:\n{text}");
    assert!(text.contains(&format!("attribute {}", root.attribute())));
    // Three leaves are listed with their masks, then "... N more".
    let leaves = dag.levels().last().unwrap();
    let leaf0 = dag.leaf(0).unwrap();
    let off = leaves.file_offset;
    let hexed: Vec<String> = leaf0
        .0
        .to_le_bytes()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    assert!(
        text.contains(&format!("{off:#010x}  {}", hexed.join(" "))),
        "{text}"
    );
    assert!(text.contains(&format!("leaf 0: {} voxels", leaf0.count())));
    assert!(text.contains(&format!("... {} more", leaves.node_count - 3)));
    // Section entries with checksums checked.
    assert_eq!(text.matches("-- entry ").count(), dag.sections().len());
    // A corrupted file still dumps, flagging the checksum.
    let mut bad = bytes.clone();
    bad[leaf_section_offset(&bytes)] ^= 1;
    let p = file.with_file_name("bad.vdag");
    std::fs::write(&p, bad).unwrap();
    let text = String::from_utf8_lossy(&run_ok(&["dump", s(&p)]).stdout).into_owned();
    assert!(text.contains("MISMATCH"));
}

#[test]
fn pack_and_unpack_round_trip() {
    let (dir, file) = sample();
    let zst = dir.path().join("s.vdag.zst");
    run_ok(&["pack", s(&file), s(&zst)]);
    let packed = std::fs::read(&zst).unwrap();
    assert!(packed.len() < std::fs::metadata(&file).unwrap().len() as usize);
    // Any zstd decoder reads it.
    assert_eq!(
        zstd::decode_all(&packed[..]).unwrap(),
        std::fs::read(&file).unwrap()
    );
    // validate and info accept the transport form.
    let o = run_ok(&["validate", s(&zst)]);
    assert!(String::from_utf8_lossy(&o.stdout).contains("valid"));
    run_ok(&["info", s(&zst)]);
    let back = dir.path().join("back.vdag");
    run_ok(&["unpack", s(&zst), s(&back)]);
    assert_eq!(std::fs::read(&back).unwrap(), std::fs::read(&file).unwrap());
    // No overwrite without --force; a too-small limit is refused.
    let o = run(&["unpack", s(&zst), s(&back)]);
    assert_eq!(o.status.code(), Some(1));
    let o = run(&[
        "unpack",
        s(&zst),
        s(&dir.path().join("x.vdag")),
        "--max-size",
        "1K",
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("over the limit"));
    assert!(!dir.path().join("x.vdag").exists());
    // Packing an invalid file is refused.
    let mut bad = std::fs::read(&file).unwrap();
    let at = leaf_section_offset(&bad);
    bad[at] ^= 4;
    let badp = dir.path().join("bad.vdag");
    std::fs::write(&badp, bad).unwrap();
    let o = run(&["pack", s(&badp), s(&dir.path().join("bad.vdag.zst"))]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("not a valid .vdag"));
}

/// Every command that writes a file takes `-o/--output`; `pack` and `unpack`
/// also keep the second positional argument of earlier versions, with the
/// same bytes, and refuse a command that names neither or both.
#[test]
fn pack_and_unpack_take_dash_o_and_the_old_positional() {
    let (dir, file) = sample();
    let d = dir.path();
    let (short, long, positional) = (d.join("a.zst"), d.join("b.zst"), d.join("c.zst"));
    run_ok(&["pack", s(&file), "-o", s(&short)]);
    run_ok(&["pack", s(&file), "--output", s(&long)]);
    run_ok(&["pack", s(&file), s(&positional)]);
    let packed = std::fs::read(&short).unwrap();
    assert_eq!(packed, std::fs::read(&long).unwrap());
    assert_eq!(packed, std::fs::read(&positional).unwrap());
    let (back_short, back_positional) = (d.join("a.vdag"), d.join("c.vdag"));
    run_ok(&["unpack", s(&short), "-o", s(&back_short)]);
    run_ok(&["unpack", s(&short), s(&back_positional)]);
    let original = std::fs::read(&file).unwrap();
    assert_eq!(std::fs::read(&back_short).unwrap(), original);
    assert_eq!(std::fs::read(&back_positional).unwrap(), original);
    // Neither spelling: a usage error naming the option; both: a clap usage error.
    for command in ["pack", "unpack"] {
        let o = run(&[command, s(&short)]);
        assert_eq!(o.status.code(), Some(2), "{command} without an output");
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains("-o/--output"), "{command}: {err}");
        assert_eq!(err.trim_end().lines().count(), 1, "{command}: {err}");
        let o = run(&[command, s(&short), "-o", s(&d.join("x")), s(&d.join("y"))]);
        assert_eq!(o.status.code(), Some(2), "{command} with two outputs");
        assert!(!d.join("x").exists() && !d.join("y").exists());
    }
    // `demo` names its output folder with -o too (`--out` still works); its
    // help lists -o/--output and no longer --out.
    let o = run_ok(&["demo", "--help"]);
    let help = String::from_utf8_lossy(&o.stdout);
    assert!(help.contains("-o, --output"), "{help}");
    assert!(!help.contains("--out "), "{help}");
    for command in ["pack", "unpack"] {
        let o = run_ok(&[command, "--help"]);
        let help = String::from_utf8_lossy(&o.stdout);
        assert!(help.contains("-o, --output <FILE>"), "{command}: {help}");
    }
}
