//! `dagtool info FILE`: header, per-level table, totals, and the size of the
//! same voxels in the classic 32-bit layout, as an SVO, in the 1.0 layout and
//! in the SSVDAG encoding (`dagfmt::stats::format_sizes`). A 2.0 file is
//! described by its own levels; its totals and comparisons come from its
//! 1.0 form, rebuilt in memory.

use std::fmt::Write as _;
use std::path::Path;

use dagfmt::stats::{self, DagStats, FormatSizes};
use dagfmt::v2::LevelView;
use dagfmt::{AnyDag, Dag, Header};

use super::FileBytes;
use crate::error::ConvertError;

/// The `info` report of `path`, as text or JSON.
pub fn run(path: &Path, json: bool) -> Result<String, ConvertError> {
    let file = FileBytes::open(path)?;
    let unreadable = |e: &dyn std::fmt::Display| {
        ConvertError::Input(format!(
            "{}: not a readable .vdag file: {e}",
            path.display()
        ))
    };
    let malformed = |e: &dyn std::fmt::Display| {
        ConvertError::Input(format!("{}: malformed DAG: {e}", path.display()))
    };
    let opened = AnyDag::open(file.bytes()).map_err(|e| unreadable(&e))?;
    let v1_form;
    let (dag, v2) = match &opened {
        AnyDag::V1(dag) => (dag.clone(), None),
        AnyDag::V2(dag2) => {
            v1_form = dagfmt::v2file::downgrade(dag2).map_err(|e| malformed(&e))?;
            (
                Dag::open(&v1_form).map_err(|e| malformed(&e))?,
                Some(dag2.levels()),
            )
        }
    };
    let mut stats = stats::analyze(&dag).map_err(|e| malformed(&e))?;
    let sizes = stats::format_sizes(&dag, &stats).map_err(|e| malformed(&e))?;
    // The file described is the one given, not its 1.0 form.
    stats.file_bytes = file.bytes().len() as u64;
    if let Some(levels) = v2 {
        stats.level_bytes = levels.iter().map(|l| l.bytes.len() as u64).sum();
    }
    let info = Info {
        header: opened.header(),
        v2,
        sizes,
    };
    Ok(if json {
        render_json(path, &dag, &stats, &info, file.was_packed())
    } else {
        render_text(path, &dag, &stats, &info, file.was_packed())
    })
}

/// What the report needs besides the (1.0 form of the) DAG and its statistics.
struct Info<'a> {
    /// The file's own header.
    header: &'a Header,
    /// A 2.0 file's levels.
    v2: Option<&'a [LevelView<'a>]>,
    /// The sizes of the same voxels in other layouts.
    sizes: FormatSizes,
}

/// The lines comparing the file with the other layouts of its voxels.
fn sizes_text(out: &mut String, s: &DagStats, info: &Info<'_>) {
    let z = &info.sizes;
    let classic = z.classic_svdag_bytes.max(1) as f64;
    let _ = writeln!(out);
    let _ = writeln!(
        out,
        "the same voxels, as fractions of the classic 32-bit SVDAG layout:"
    );
    let _ = writeln!(
        out,
        "  this file ({}.{}): {:>16} bytes ({:.3})",
        info.header.version_major,
        info.header.version_minor,
        s.file_bytes,
        s.file_bytes as f64 / classic
    );
    let _ = writeln!(
        out,
        "  1.0 layout:       {:>16} bytes ({:.3}; levels, header and table)",
        z.v1_bytes,
        z.v1_bytes as f64 / classic
    );
    let _ = write!(
        out,
        "  SSVDAG:           {:>16} bytes ({:.3}; level data, no attributes)",
        z.ssvdag_bytes,
        z.ssvdag_bytes as f64 / classic
    );
}

fn ratio(a: u128, b: u64) -> f64 {
    if b == 0 { 0.0 } else { a as f64 / b as f64 }
}

fn render_text(path: &Path, dag: &Dag<'_>, s: &DagStats, info: &Info<'_>, packed: bool) -> String {
    let h = info.header;
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
        if dag.color_table().is_some() {
            " (with voxel colours)"
        } else {
            ""
        }
    );
    if let Some(line) = colors_line(dag) {
        let _ = writeln!(out, "colours:         {line}");
    }
    let _ = writeln!(out, "header crc:      {:#010x}", h.header_crc);
    let _ = writeln!(out);
    if let Some(levels) = info.v2 {
        let _ = writeln!(
            out,
            "{:>5} {:>6} {:>14} {:>16} {:>12}",
            "level", "kind", "items", "bytes", "widths"
        );
        for (l, level) in levels.iter().enumerate() {
            let _ = writeln!(
                out,
                "{l:>5} {:>6} {:>14} {:>16} {:>12}",
                if level.is_leaf { "leaf" } else { "node" },
                level.item_count,
                level.bytes.len(),
                if level.is_leaf {
                    "-".to_string()
                } else {
                    format!(
                        "{}/{}/{}",
                        level.widths[0], level.widths[1], level.widths[2]
                    )
                }
            );
        }
        let _ = writeln!(out);
        let _ = writeln!(out, "its 1.0 form (the same voxels, rebuilt in memory):");
    }
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
    sizes_text(&mut out, s, info);
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

fn render_json(path: &Path, dag: &Dag<'_>, s: &DagStats, info: &Info<'_>, packed: bool) -> String {
    let h = info.header;
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
        "has_colors": dag.color_table().is_some(),
        "colors": colors_json(dag),
        "file_bytes": s.file_bytes,
        "level_bytes": s.level_bytes,
        "dag_nodes": s.dag_nodes,
        "tree_nodes": big(s.tree_nodes),
        "dedup_ratio": s.dedup_ratio(),
        "classic_svdag_bytes": big(s.classic_svdag_bytes),
        "svo_bytes": big(s.svo_bytes),
        "pointer_entropy_bound_bytes": big(s.pointer_entropy_bound_bytes),
        "levels": levels,
        "v1_bytes": info.sizes.v1_bytes,
        "ssvdag_bytes": info.sizes.ssvdag_bytes,
        "v2_levels": info.v2.map(|levels| levels.iter().map(|l| serde_json::json!({
            "kind": if l.is_leaf { "leaf" } else { "node" },
            "items": l.item_count,
            "bytes": l.bytes.len(),
            "widths": l.widths,
        })).collect::<Vec<_>>()),
    });
    serde_json::to_string_pretty(&doc).expect("JSON values serialize")
}

/// Bits per voxel of the colour section, and that against raw 24-bit RGB.
fn color_bits(dag: &Dag<'_>, section_bytes: usize) -> (f64, f64) {
    let n = dag.header().voxel_count.max(1) as f64;
    let bits = section_bytes as f64 * 8.0 / n;
    (bits, bits / 24.0)
}

/// The colour section in one line: raw or packed, its size per voxel, and
/// (packed) the error bound, the measured maximum error and PSNR.
fn colors_line(dag: &Dag<'_>) -> Option<String> {
    if let Some(raw) = dag.colors() {
        let (bits, ratio) = color_bits(dag, raw.len());
        return Some(format!(
            "raw RGBA8, {} bytes: {bits:.3} bits per voxel, {:.2} % of raw 24-bit RGB",
            raw.len(),
            ratio * 100.0
        ));
    }
    let p = dag.packed_colors()?;
    let (bits, ratio) = color_bits(dag, p.bytes().len());
    let t = p.trailer();
    Some(format!(
        "packed, {} bytes: {bits:.3} bits per voxel, {:.2} % of raw 24-bit RGB; error bound {}, measured max error {}, PSNR {}; {}",
        p.bytes().len(),
        ratio * 100.0,
        t.error_bound,
        t.max_error,
        crate::convert::psnr_text(t.psnr(p.len())),
        crate::convert::layout_text(t.layout)
    ))
}

fn colors_json(dag: &Dag<'_>) -> serde_json::Value {
    if let Some(raw) = dag.colors() {
        let (bits, ratio) = color_bits(dag, raw.len());
        return serde_json::json!({
            "section": "VOXEL_COLORS",
            "bytes": raw.len(),
            "bits_per_voxel": bits,
            "ratio_to_rgb24": ratio,
            "error_bound": 0,
            "max_error": 0,
            "psnr_db": null,
        });
    }
    let Some(p) = dag.packed_colors() else {
        return serde_json::Value::Null;
    };
    let (bits, ratio) = color_bits(dag, p.bytes().len());
    let t = p.trailer();
    let psnr = t.psnr(p.len());
    serde_json::json!({
        "section": "PACKED_COLORS",
        "bytes": p.bytes().len(),
        "bits_per_voxel": bits,
        "ratio_to_rgb24": ratio,
        "error_bound": t.error_bound,
        "max_error": t.max_error,
        "psnr_db": psnr.is_finite().then_some(psnr),
        "block_colors": t.layout.block_colors(),
        "split_sub_blocks": t.layout.split,
    })
}
