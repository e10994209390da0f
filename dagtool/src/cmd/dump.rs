//! `dagtool dump FILE`: an annotated byte listing (offset | bytes | meaning)
//! of the header, the section table and the first nodes of every level, for
//! people writing their own readers.
//!
//! Works on damaged files too: it lists whatever bytes exist, checks the
//! checksums it can, and reports where the structure stops making sense.

use std::fmt::Write as _;
use std::path::Path;

use dagfmt::layout::{self, HEADER_CRC_OFFSET, HEADER_SIZE, SECTION_ENTRY_SIZE, SectionKind};
use dagfmt::v2::{self, Child};
use dagfmt::{AnyDag, Dag2, LeafMask};

use super::FileBytes;
use crate::error::ConvertError;

/// The annotated listing of `path`, with the first `nodes` records of each level.
pub fn run(path: &Path, nodes: u64) -> Result<String, ConvertError> {
    let file = FileBytes::open(path)?;
    Ok(dump(
        &path.display().to_string(),
        file.bytes(),
        nodes,
        file.was_packed(),
    ))
}

fn hex(bytes: &[u8]) -> String {
    let mut s = String::with_capacity(bytes.len() * 3);
    for (i, b) in bytes.iter().enumerate() {
        if i > 0 {
            s.push(' ');
        }
        let _ = write!(s, "{b:02x}");
    }
    s
}

struct Listing<'a> {
    bytes: &'a [u8],
    out: String,
}

impl Listing<'_> {
    /// One line for `len` bytes at `at`. Long runs are shortened.
    fn line(&mut self, at: u64, len: usize, meaning: impl std::fmt::Display) {
        let start = at as usize;
        let end = start.saturating_add(len).min(self.bytes.len());
        let shown = if start >= self.bytes.len() {
            "(past end of file)".to_string()
        } else if end - start > 16 {
            let all_zero = self.bytes[start..end].iter().all(|&b| b == 0);
            if all_zero {
                format!("00 x {}", end - start)
            } else {
                format!("{} ...", hex(&self.bytes[start..start + 12]))
            }
        } else {
            hex(&self.bytes[start..end])
        };
        let _ = writeln!(self.out, "{at:#010x}  {shown:<36}  {meaning}");
    }

    fn heading(&mut self, text: impl std::fmt::Display) {
        let _ = writeln!(self.out, "\n== {text} ==");
    }

    fn u8_at(&self, at: usize) -> Option<u8> {
        self.bytes.get(at).copied()
    }

    fn u16_at(&self, at: usize) -> Option<u16> {
        self.bytes
            .get(at..at + 2)
            .map(|b| u16::from_le_bytes([b[0], b[1]]))
    }

    fn u32_at(&self, at: usize) -> Option<u32> {
        self.bytes
            .get(at..at + 4)
            .map(|b| u32::from_le_bytes(b.try_into().expect("4")))
    }

    fn u64_at(&self, at: usize) -> Option<u64> {
        self.bytes
            .get(at..at + 8)
            .map(|b| u64::from_le_bytes(b.try_into().expect("8")))
    }
}

fn opt<T: std::fmt::Display>(v: Option<T>) -> String {
    v.map_or_else(|| "?".to_string(), |v| v.to_string())
}

/// The listing of `bytes` (named `name`).
pub fn dump(name: &str, bytes: &[u8], nodes: u64, packed: bool) -> String {
    let mut l = Listing {
        bytes,
        out: String::new(),
    };
    let _ = writeln!(
        l.out,
        "# {name}: {} bytes{}; all integers little-endian",
        bytes.len(),
        if packed {
            " (unpacked from zstd transport)"
        } else {
            ""
        }
    );
    let _ = write!(
        l.out,
        "# offset     bytes                                 meaning"
    );
    l.heading("header (128 bytes)");
    let magic_ok = bytes.get(..8) == Some(&layout::MAGIC[..]);
    l.line(
        0,
        8,
        format!(
            "magic \"\\x89VDAG\\r\\n\\x1a\"{}",
            if magic_ok { "" } else { "  <-- WRONG" }
        ),
    );
    l.line(8, 2, format!("version_major = {}", opt(l.u16_at(8))));
    l.line(10, 2, format!("version_minor = {}", opt(l.u16_at(10))));
    l.line(
        12,
        4,
        format!(
            "header_size = {} (section table starts here)",
            opt(l.u32_at(12))
        ),
    );
    l.line(
        16,
        4,
        format!(
            "required_features = {}",
            opt(l.u32_at(16).map(|v| format!("{v:#x}")))
        ),
    );
    l.line(
        20,
        4,
        format!(
            "optional_features = {}",
            opt(l.u32_at(20).map(|v| format!("{v:#x}")))
        ),
    );
    let depth = l.u8_at(24);
    l.line(
        24,
        1,
        format!(
            "depth D = {} ({} voxels per axis)",
            opt(depth),
            opt(depth.filter(|&d| d < 64).map(|d| 1u64 << d))
        ),
    );
    l.line(
        25,
        1,
        format!(
            "attribute_kind = {}",
            match l.u8_at(25) {
                Some(0) => "0 (none)".to_string(),
                Some(1) => "1 (voxel count in the 24 attribute bits)".to_string(),
                v => format!("{} (unknown)", opt(v)),
            }
        ),
    );
    let section_count = l.u16_at(26);
    l.line(26, 2, format!("section_count = {}", opt(section_count)));
    l.line(28, 4, "reserved0 (zero)");
    for (i, axis) in ["x", "y", "z"].iter().enumerate() {
        let at = 32 + 8 * i;
        l.line(
            at as u64,
            8,
            format!(
                "root_min.{axis} = {} (f64)",
                opt(l.u64_at(at).map(f64::from_bits))
            ),
        );
    }
    l.line(
        56,
        8,
        format!(
            "root_size = {} (f64)",
            opt(l.u64_at(56).map(f64::from_bits))
        ),
    );
    l.line(64, 8, format!("file_size = {}", opt(l.u64_at(64))));
    l.line(72, 8, format!("voxel_count = {}", opt(l.u64_at(72))));
    l.line(80, 44, "reserved1 (44 zero bytes)");
    let count = usize::from(section_count.unwrap_or(0)).min(layout::MAX_SECTIONS as usize);
    let table_end = HEADER_SIZE + count * SECTION_ENTRY_SIZE;
    let crc_note = match (
        l.u32_at(HEADER_CRC_OFFSET),
        bytes.get(..HEADER_SIZE),
        bytes.get(HEADER_SIZE..table_end),
    ) {
        (Some(stored), Some(h), Some(table)) => {
            let header: &[u8; HEADER_SIZE] = h.try_into().expect("128 bytes");
            let computed = layout::header_checksum(header, table);
            if computed == stored {
                format!("{stored:#010x} (ok)")
            } else {
                format!("{stored:#010x} (MISMATCH: computed {computed:#010x})")
            }
        }
        (stored, _, _) => format!(
            "{} (cannot check: file too short)",
            opt(stored.map(|v| format!("{v:#010x}")))
        ),
    };
    l.line(
        HEADER_CRC_OFFSET as u64,
        4,
        format!("header_crc = {crc_note}; CRC-32C of bytes 0..124 then the section table"),
    );

    l.heading(format!(
        "section table ({count} entries of 40 bytes at {HEADER_SIZE:#x})"
    ));
    for i in 0..count {
        let at = HEADER_SIZE + i * SECTION_ENTRY_SIZE;
        if at >= bytes.len() {
            let _ = writeln!(l.out, "(entry {i} lies past the end of the file)");
            break;
        }
        let kind = l.u32_at(at);
        let kind_name = match kind.map(SectionKind::from_raw) {
            Some(Some(SectionKind::NodeLevel)) => "NODE_LEVEL",
            Some(Some(SectionKind::LeafLevel)) => "LEAF_LEVEL",
            Some(Some(SectionKind::VoxelColors)) => "VOXEL_COLORS",
            Some(Some(SectionKind::PackedColors)) => "PACKED_COLORS",
            Some(Some(SectionKind::UnknownOptional(_))) => "unknown optional",
            Some(None) => "unknown required",
            None => "?",
        };
        let _ = writeln!(l.out, "-- entry {i}");
        l.line(at as u64, 4, format!("kind = {} ({kind_name})", opt(kind)));
        l.line(
            at as u64 + 4,
            1,
            format!("level = {}", opt(l.u8_at(at + 4))),
        );
        let v2 = bytes.get(8..10) == Some(&[2, 0]);
        if v2 {
            // Format 2.0 (spec §23.10): bytes 5..8 are a node level's widths.
            l.line(
                at as u64 + 5,
                3,
                format!(
                    "widths = {} / {} / {} bits (2.0 node level; 0 otherwise)",
                    opt(l.u8_at(at + 5)),
                    opt(l.u8_at(at + 6)),
                    opt(l.u8_at(at + 7))
                ),
            );
        } else {
            l.line(
                at as u64 + 5,
                1,
                format!("pointer_width = {} bytes", opt(l.u8_at(at + 5))),
            );
            l.line(at as u64 + 6, 2, "reserved (zero)");
        }
        let offset = l.u64_at(at + 8);
        let length = l.u64_at(at + 16);
        l.line(
            at as u64 + 8,
            8,
            format!("offset = {}", opt(offset.map(|v| format!("{v} ({v:#x})")))),
        );
        l.line(at as u64 + 16, 8, format!("length = {} bytes", opt(length)));
        l.line(
            at as u64 + 24,
            8,
            format!("item_count = {}", opt(l.u64_at(at + 24))),
        );
        let stored = l.u32_at(at + 32);
        let check = match (stored, offset, length) {
            (Some(s), Some(o), Some(n)) => match o
                .checked_add(n)
                .and_then(|e| bytes.get(o as usize..e as usize))
            {
                Some(data) => {
                    let c = crc32c::crc32c(data);
                    if c == s {
                        "(ok)".to_string()
                    } else {
                        format!("(MISMATCH: computed {c:#010x})")
                    }
                }
                None => "(section out of bounds)".to_string(),
            },
            _ => String::new(),
        };
        l.line(
            at as u64 + 32,
            4,
            format!(
                "crc = {} {check}; CRC-32C of the section bytes",
                opt(stored.map(|v| format!("{v:#010x}")))
            ),
        );
        l.line(at as u64 + 36, 4, "reserved (zero)");
    }

    // Either version; a file the reader rejects is named by the reader's
    // finding for its version (E010 for a truncated 2.0 file, not E003).
    let dag = match AnyDag::open(bytes) {
        Ok(AnyDag::V2(dag)) => {
            dump_v2_levels(&mut l, &dag, nodes);
            return l.out;
        }
        Ok(AnyDag::V1(d)) => d,
        Err(e) => {
            let _ = writeln!(
                l.out,
                "\n(the reader rejects the file, so the levels are not listed: {e})"
            );
            return l.out;
        }
    };
    let leaf_level = dag.leaf_level();
    for section in dag.levels() {
        if section.is_leaf {
            l.heading(format!(
                "level {} = leaf level: {} leaves of 8 bytes at {:#x}; bit c1*8+c2 (c1 = 2^3 sub-brick, c2 = voxel in it; child index = x | y<<1 | z<<2)",
                section.level, section.node_count, section.file_offset
            ));
            for i in 0..section.node_count.min(nodes) {
                let at = section.file_offset + i * 8;
                match dag.leaf(i as u32) {
                    Ok(mask) => {
                        let subs: Vec<String> = (0..8u32)
                            .filter(|&c| mask.sub_brick(c) != 0)
                            .map(|c| format!("{c}:{:08b}", mask.sub_brick(c)))
                            .collect();
                        l.line(
                            at,
                            8,
                            format!(
                                "leaf {i}: {} voxels; sub-bricks {}",
                                LeafMask::count(mask),
                                subs.join(" ")
                            ),
                        );
                    }
                    Err(e) => {
                        let _ = writeln!(l.out, "(leaf {i}: {e})");
                        break;
                    }
                }
            }
        } else {
            let child_is_leaf = section.level + 1 == leaf_level;
            let next = if child_is_leaf {
                "leaf indices"
            } else {
                "word offsets into the next level"
            };
            l.heading(format!(
                "level {}: {} nodes, {} bytes at {:#x}, pointers of {} bytes ({next})",
                section.level,
                section.node_count,
                section.bytes.len(),
                section.file_offset,
                section.pointer_width
            ));
            let mut word = 0u32;
            for i in 0..section.node_count.min(nodes) {
                let node = match dag.node(section.level, word) {
                    Ok(n) => n,
                    Err(e) => {
                        let _ = writeln!(l.out, "(node {i}: {e})");
                        break;
                    }
                };
                let at = section.file_offset + u64::from(word) * 4;
                let children: Vec<String> = (0..8u32)
                    .filter(|c| node.child_mask() >> c & 1 != 0)
                    .map(|c| c.to_string())
                    .collect();
                l.line(
                    at,
                    4,
                    format!(
                        "node {i} (word {word}): child mask {:08b} (children {}), attribute {}",
                        node.child_mask(),
                        children.join(","),
                        node.attribute()
                    ),
                );
                let width = usize::from(node.pointer_width);
                let mut p = at + 4;
                for (rank, c) in children.iter().enumerate() {
                    let target = node.pointer_at(rank as u32);
                    let meaning = if child_is_leaf {
                        format!("  child {c} -> leaf {target}")
                    } else {
                        format!(
                            "  child {c} -> level {} word {target} (byte {})",
                            section.level + 1,
                            u64::from(target) * 4
                        )
                    };
                    l.line(p, width, meaning);
                    p += width as u64;
                }
                let size = node.record_size();
                let end = at + size;
                if p < end {
                    l.line(p, (end - p) as usize, "  padding to a multiple of 4 (zero)");
                }
                word += (size / 4) as u32;
            }
        }
        if section.node_count > nodes {
            let _ = writeln!(l.out, "... {} more", section.node_count - nodes);
        }
    }
    if let Some(colors) = dag.colors() {
        let offset = colors.as_ptr() as usize - bytes.as_ptr() as usize;
        l.heading(format!(
            "voxel colours: {} RGBA8 values at {offset:#x}, dense voxel index order",
            colors.len() / 4
        ));
        for i in 0..(colors.len() as u64 / 4).min(nodes) {
            let at = offset as u64 + 4 * i;
            let c = &colors[4 * i as usize..4 * i as usize + 4];
            l.line(
                at,
                4,
                format!("voxel {i}: rgba({}, {}, {}, {})", c[0], c[1], c[2], c[3]),
            );
        }
    }
    if let Some(packed) = dag.packed_colors() {
        let offset = packed.bytes().as_ptr() as usize - bytes.as_ptr() as usize;
        let t = packed.trailer();
        l.heading(format!(
            "packed colours: {} colours in {} bytes at {offset:#x} (error bound {}, measured {}), dense voxel index order, decoded",
            packed.len(),
            packed.bytes().len(),
            t.error_bound,
            t.max_error
        ));
        for (i, c) in packed.iter().take(nodes as usize).enumerate() {
            let _ = writeln!(
                l.out,
                "voxel {i}: rgba({}, {}, {}, {})",
                c[0], c[1], c[2], c[3]
            );
        }
    }
    l.out
}

/// The levels of a 2.0 file (spec §23.2): each record's header, codes and
/// references, decoded by `dagfmt::v2::decode_node`.
fn dump_v2_levels(l: &mut Listing<'_>, dag: &Dag2<'_>, nodes: u64) {
    let levels = dag.levels();
    for (level, view) in levels.iter().enumerate() {
        let offset = dag.sections()[level].offset;
        if view.is_leaf {
            l.heading(format!(
                "level {level} = leaf level: {} leaves of 8 bytes at {offset:#x} (2.0: read under the path's reflection, §23.4)",
                view.item_count
            ));
            for i in 0..view.item_count.min(nodes) {
                let at = offset + i * 8;
                let mask = view
                    .bytes
                    .get(i as usize * 8..i as usize * 8 + 8)
                    .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")));
                match mask {
                    Some(m) => l.line(at, 8, format!("leaf {i}: {} voxels", m.count_ones())),
                    None => {
                        let _ = writeln!(l.out, "(leaf {i} lies past the level)");
                        break;
                    }
                }
            }
        } else {
            let next = if levels[level + 1].is_leaf {
                "leaf indices"
            } else {
                "byte offsets into the next level"
            };
            l.heading(format!(
                "level {level}: {} records, {} bytes at {offset:#x}, widths {}/{}/{} bits ({next})",
                view.item_count,
                view.bytes.len(),
                view.widths[0],
                view.widths[1],
                view.widths[2]
            ));
            let mut at = 0u64;
            for i in 0..view.item_count.min(nodes) {
                let node = match v2::decode_node(view.bytes, at, view.widths) {
                    Ok(n) => n,
                    Err(e) => {
                        let _ = writeln!(l.out, "(record {i}: {e})");
                        break;
                    }
                };
                l.line(
                    offset + at,
                    4,
                    format!(
                        "record {i} (byte {at}): child mask {:08b} (physical slots), attribute {}",
                        node.child_mask(),
                        node.attribute()
                    ),
                );
                let refs: Vec<String> = node
                    .children
                    .iter()
                    .enumerate()
                    .filter_map(|(slot, c)| {
                        c.map(|c| match c {
                            Child::Shared { target, reflection } => {
                                format!("{slot}->{target} r{reflection}")
                            }
                            Child::Sequential { base, index } => {
                                format!("{slot}->seq {index} from {base}")
                            }
                        })
                    })
                    .collect();
                l.line(
                    offset + at + 4,
                    node.size as usize - 4,
                    format!("  codes and references: {}", refs.join(", ")),
                );
                at += u64::from(node.size);
            }
        }
        if view.item_count > nodes {
            let _ = writeln!(l.out, "... {} more", view.item_count - nodes);
        }
    }
    if let Some(colors) = dag.colors() {
        l.heading(format!(
            "voxel colours: {} RGBA8 values, dense voxel index order (as in 1.0)",
            colors.len() / 4
        ));
    }
    if let Some(packed) = dag.packed_colors() {
        l.heading(format!(
            "packed colours: {} colours in {} bytes (as in 1.0)",
            packed.len(),
            packed.bytes().len()
        ));
    }
}
