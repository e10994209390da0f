//! `dagtool info FILE`: header, per-level table, totals, and the size of the
//! same DAG in the classic 32-bit layout and as an SVO.

use std::fmt::Write as _;
use std::path::Path;

use dagfmt::Dag;
use dagfmt::stats::{self, DagStats};

use super::FileBytes;
use crate::error::ConvertError;

/// The `info` report of `path`, as text or JSON.
pub fn run(path: &Path, json: bool) -> Result<String, ConvertError> {
    let file = FileBytes::open(path)?;
    let dag = Dag::open(file.bytes()).map_err(|e| {
        ConvertError::Input(format!(
            "{}: not a readable .vdag file: {e}",
            path.display()
        ))
    })?;
    let stats = stats::analyze(&dag)
        .map_err(|e| ConvertError::Input(format!("{}: malformed DAG: {e}", path.display())))?;
    Ok(if json {
        render_json(path, &dag, &stats, file.was_packed())
    } else {
        render_text(path, &dag, &stats, file.was_packed())
    })
}

fn ratio(a: u128, b: u64) -> f64 {
    if b == 0 { 0.0 } else { a as f64 / b as f64 }
}

fn render_text(path: &Path, dag: &Dag<'_>, s: &DagStats, packed: bool) -> String {
    let h = dag.header();
    let mut out = String::new();
    let _ = writeln!(
        out,
        "file:            {}{}",
        path.display(),
        if packed {
            " (zstd transport, unpacked)"
        } else {
            ""
        }
    );
    let _ = writeln!(
        out,
        "version:         {}.{}",
        h.version_major, h.version_minor
    );
    let _ = writeln!(
        out,
        "depth:           {} ({}^3 voxels)",
        h.depth,
        1u64 << h.depth
    );
    let _ = writeln!(
        out,
        "attributes:      kind {} ({})",
        h.attribute_kind.to_raw(),
        match h.attribute_kind {
            dagfmt::AttributeKind::None => "none",
            dagfmt::AttributeKind::VoxelCount => "voxel count",
        }
    );
    let _ = writeln!(
        out,
        "root cube:       min [{}, {}, {}], size {}",
        h.root_min[0], h.root_min[1], h.root_min[2], h.root_size
    );
    let _ = writeln!(
        out,
        "voxel size:      {}",
        h.root_size / (1u64 << h.depth) as f64
    );
    let _ = writeln!(out, "voxels:          {}", h.voxel_count);
    let _ = writeln!(
        out,
        "features:        required {:#x}, optional {:#x}",
        h.required_features, h.optional_features
    );
    let _ = writeln!(
        out,
        "sections:        {}{}",
        h.section_count,
        if dag.colors().is_some() {
            " (with voxel colours)"
        } else {
            ""
        }
    );
    let _ = writeln!(out, "header crc:      {:#010x}", h.header_crc);
    let _ = writeln!(out);
    let _ = writeln!(
        out,
        "{:>5} {:>6} {:>14} {:>16} {:>5} {:>22} {:>10}",
        "level", "kind", "nodes", "bytes", "width", "tree nodes", "dedup"
    );
    let leaf = s.levels.len().saturating_sub(1);
    for l in &s.levels {
        let _ = writeln!(
            out,
            "{:>5} {:>6} {:>14} {:>16} {:>5} {:>22} {:>10.2}",
            l.level,
            if usize::from(l.level) == leaf {
                "leaf"
            } else {
                "node"
            },
            l.node_count,
            l.bytes,
            if usize::from(l.level) == leaf {
                "-".to_string()
            } else {
                l.pointer_width.to_string()
            },
            l.tree_nodes,
            l.dedup_ratio()
        );
    }
    let _ = writeln!(out);
    let _ = writeln!(
        out,
        "total nodes:     {} stored, {} in the equivalent tree (dedup x{:.2})",
        s.dag_nodes,
        s.tree_nodes,
        s.dedup_ratio()
    );
    let _ = writeln!(
        out,
        "this file:       {:>16} bytes ({} in level sections)",
        s.file_bytes, s.level_bytes
    );
    let _ = writeln!(
        out,
        "classic 32-bit:  {:>16} bytes (x{:.2} this file)",
        s.classic_svdag_bytes,
        ratio(s.classic_svdag_bytes, s.file_bytes)
    );
    let _ = writeln!(
        out,
        "SVO (no dedup):  {:>16} bytes (x{:.2} this file)",
        s.svo_bytes,
        ratio(s.svo_bytes, s.file_bytes)
    );
    // How far pointer coding alone could go with the same headers and leaves.
    let _ = write!(
        out,
        "entropy bound:   {:>16} bytes (x{:.2} this file; {:.3} of classic): 32-bit headers + leaves + the pointers' zero-order entropy",
        s.pointer_entropy_bound_bytes,
        ratio(s.pointer_entropy_bound_bytes, s.file_bytes),
        s.pointer_entropy_bound_bytes as f64 / s.classic_svdag_bytes.max(1) as f64
    );
    out
}

/// A `u128` count as a JSON number when it fits a `u64` (always, for files
/// that fit in memory), else as a decimal string.
fn big(v: u128) -> serde_json::Value {
    match u64::try_from(v) {
        Ok(v) => serde_json::Value::from(v),
        Err(_) => serde_json::Value::from(v.to_string()),
    }
}

fn render_json(path: &Path, dag: &Dag<'_>, s: &DagStats, packed: bool) -> String {
    let h = dag.header();
    let leaf = s.levels.len().saturating_sub(1);
    let levels: Vec<serde_json::Value> = s
        .levels
        .iter()
        .map(|l| {
            serde_json::json!({
                "level": l.level,
                "kind": if usize::from(l.level) == leaf { "leaf" } else { "node" },
                "nodes": l.node_count,
                "bytes": l.bytes,
                "pointer_width": l.pointer_width,
                "tree_nodes": big(l.tree_nodes),
                "dedup_ratio": l.dedup_ratio(),
            })
        })
        .collect();
    let doc = serde_json::json!({
        "file": path.display().to_string(),
        "packed": packed,
        "version": [h.version_major, h.version_minor],
        "depth": h.depth,
        "resolution": 1u64 << h.depth,
        "attribute_kind": h.attribute_kind.to_raw(),
        "root_min": h.root_min,
        "root_size": h.root_size,
        "voxel_count": h.voxel_count,
        "required_features": h.required_features,
        "optional_features": h.optional_features,
        "section_count": h.section_count,
        "has_colors": dag.colors().is_some(),
        "file_bytes": s.file_bytes,
        "level_bytes": s.level_bytes,
        "dag_nodes": s.dag_nodes,
        "tree_nodes": big(s.tree_nodes),
        "dedup_ratio": s.dedup_ratio(),
        "classic_svdag_bytes": big(s.classic_svdag_bytes),
        "svo_bytes": big(s.svo_bytes),
        "pointer_entropy_bound_bytes": big(s.pointer_entropy_bound_bytes),
        "levels": levels,
    });
    serde_json::to_string_pretty(&doc).expect("JSON values serialize")
}
