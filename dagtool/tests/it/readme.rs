//! The README's usage block, run line by line as a user would run it, so that
//! the README cannot drift from the tools: every command must succeed.
//!
//! The block is the first fenced block after the line
//! `<!-- usage: dagtool/tests/it/readme.rs runs every line of the next block -->`.
//! Its lines run with `sh` in a temporary folder, with `$B` the folder of the
//! binaries under test (where `cargo test --workspace` builds `dagtool`,
//! `dagtrace` and `conformance`) and two substitutions that keep the test
//! small: a small sphere mesh for the shared dragon, and depth 7 for 12.
//! `cargo build --release` is skipped (the binaries are already built).
//! Without a GPU adapter, a command that needs one is skipped with a message,
//! unless `VDAG_REQUIRE_GPU=1`.

use std::path::Path;
use std::process::Command;

use crate::common::sphere_mesh;

/// The README's mesh and depth, and what the test uses instead.
const SUBSTITUTIONS: [(&str, &str); 2] = [
    ("../shared/meshes/dragon.obj", "sphere.obj"),
    ("--depth 12", "--depth 7"),
];

const MARKER: &str = "<!-- usage: dagtool/tests/it/readme.rs runs every line of the next block -->";

/// The lines of the usage block.
fn usage_lines(readme: &str) -> Vec<String> {
    let after = readme
        .split_once(MARKER)
        .expect("the README has the usage marker")
        .1;
    let start = after.find("```").expect("a fenced block after the marker");
    let body = &after[start..];
    let body = &body[body.find('\n').expect("a fence line") + 1..];
    let end = body.find("```").expect("the fenced block ends");
    body[..end]
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(String::from)
        .collect()
}

#[test]
fn usage_block_is_found() {
    let readme = "x\n<!-- usage: dagtool/tests/it/readme.rs runs every line of the next block -->\n\
                  text\n```sh\n# comment\n$B/a b\n\n$B/c d  # e\n```\n```sh\nnot this\n```\n";
    assert_eq!(usage_lines(readme), ["$B/a b", "$B/c d  # e"]);
}

#[test]
fn every_command_of_the_readme_usage_block_runs() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let readme = std::fs::read_to_string(root.join("README.md")).expect("README.md");
    let lines = usage_lines(&readme);
    let bin_dir = Path::new(env!("CARGO_BIN_EXE_dagtool"))
        .parent()
        .expect("the binaries' folder");
    for tool in ["dagtrace", "conformance"] {
        if !bin_dir.join(tool).exists() {
            assert!(
                std::env::var_os("CI").is_none(),
                "{tool} is not built in {} (cargo test --workspace builds it)",
                bin_dir.display()
            );
            eprintln!(
                "skipping: {tool} is not built in {} (run cargo test --workspace)",
                bin_dir.display()
            );
            return;
        }
    }
    let require_gpu = std::env::var("VDAG_REQUIRE_GPU").is_ok_and(|v| v == "1");
    let dir = tempfile::tempdir().unwrap();
    sphere_mesh([0.0; 3], 1.0, 2).write(&dir.path().join("sphere.obj"));
    let mut ran = Vec::new();
    for line in &lines {
        if line.starts_with("cargo build") {
            continue;
        }
        if let Some(value) = line.strip_prefix("B=") {
            assert_eq!(value, "target/release", "the README's binaries folder");
            continue;
        }
        assert!(
            line.starts_with("$B/") || line.starts_with("printf "),
            "an unexpected line: {line}"
        );
        let mut command = line.clone();
        for (from, to) in SUBSTITUTIONS {
            command = command.replace(from, to);
        }
        let out = Command::new("sh")
            .arg("-c")
            .arg(&command)
            .env("B", bin_dir)
            .current_dir(dir.path())
            .output()
            .expect("sh runs");
        let stderr = String::from_utf8_lossy(&out.stderr);
        if !out.status.success() && stderr.contains("no GPU adapter") && !require_gpu {
            eprintln!("skipped (no GPU adapter; VDAG_REQUIRE_GPU=1 makes this an error): {line}");
            continue;
        }
        assert!(
            out.status.success(),
            "README command failed ({:?}): {line}\nran as: {command}\nstdout:\n{}\nstderr:\n{stderr}\n\
             (the binaries are those in {}: cargo test --workspace builds them fresh)",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            bin_dir.display()
        );
        ran.push(line.as_str());
    }
    // Every tool of the suite appears, and the files the block names were made.
    for tool in [
        "dagtool convert",
        "dagtool pack",
        "dagtrace render",
        "dagtrace trace",
        "conformance run",
    ] {
        assert!(
            lines.iter().any(|l| l.contains(tool)),
            "the usage block shows no `{tool}`"
        );
    }
    let d = dir.path();
    let vdag = std::fs::read(d.join("dragon.vdag")).expect("convert wrote dragon.vdag");
    assert_eq!(
        std::fs::read(d.join("dragon-copy.vdag")).expect("unpack wrote dragon-copy.vdag"),
        vdag
    );
    assert!(
        std::fs::read(d.join("dragon.png"))
            .expect("render wrote dragon.png")
            .starts_with(b"\x89PNG")
    );
    let hits = dagfmt::batch::parse_hits(&std::fs::read(d.join("hits.txt")).expect("hits.txt"))
        .expect("trace wrote a hit batch");
    assert_eq!(hits.len(), 1);
    assert!(ran.len() >= 10, "only {} commands ran", ran.len());
}
