//! The size benchmark of format 2.0 (spec/VDAG.md §23.9): merges 1.0 files
//! under symmetry groups and computes, exactly, the bytes of candidate
//! encodings of the merged DAG next to the classic 32-bit SVDAG layout, the
//! 1.0 file and the SSVDAG encoding (Villanueva, Marton and Gobbetti 2016) of
//! the same voxels.
//!
//! ```text
//! cargo run --release -p dagfmt --example format2_sizes -- FILE.vdag...
//! ```
//!
//! Columns (fractions of the classic layout; candidate sizes add the 128-byte
//! header, the section table and at most 7 bytes of padding per level):
//! - `1.0`: the level sections of the 1.0 file, with header and table;
//! - `SSVDAG`: [`dagfmt::stats::ssvdag_bytes`], the SSVDAG encoding of the
//!   voxels merged under the 8 reflections, level data only: a 16-bit header (2 bits per child: none,
//!   16-bit or 32-bit reference), references of 16 bits (13 address bits +
//!   3 reflection bits) when the target's address is below 2^13, else 32
//!   bits; interior addresses count 16-bit words within the level, leaves are
//!   64-bit masks addressed by index; each level sorted by how many
//!   references of the level above name a node (ties: first occurrence);
//! - `refl u2`: merged under reflections; a 32-bit header (child mask + 24
//!   attribute bits), a 2-bit length code per child (1 to 4 bytes, ceil(k/4)
//!   bytes), references `address << 3 | reflection`, records unaligned
//!   (interior addresses in bytes, leaves by index), levels sorted by
//!   reference count;
//! - `refl a2`: the same with records padded to 4 bytes, addresses in words;
//! - `refl bits`: references bit-packed with a 2-bit code choosing one of four
//!   widths per level (the best four), records padded to whole bytes;
//! - `full48 u2`: `refl u2` merged under all 48 axis permutations and
//!   reflections (6 transform bits per reference);
//! - `refl seq bytes`: nodes named by a single reference ("sequential") are
//!   stored after the level's shared nodes, in the order of their parents and
//!   of the children within a parent; a parent names its first sequential
//!   child by one base reference (address only), the others follow it (code
//!   0, no reference); the other references take `b`, `b + 1` or `b + 2`
//!   bytes (codes 1..=3, the level's `b` in 1..=2);
//! - **`2.0`** (`refl seq bits`, the encoding of format 2.0, spec §23): the
//!   same with references bit-packed in the level's three widths (codes
//!   1..=3, the best three for the level), records padded to whole bytes;
//!   `full48 seq bits` is it under the 48 transforms (6 transform bits).
//!
//! `encoder bytes` is what `dagfmt::v2::encode` actually produces for the
//! file (level sections plus header, table and padding): it breaks ties of
//! the reference order by intrinsic rank where the estimate above uses first
//! occurrence. Merge time (`merge s`) is the reflection merge of the whole
//! file, `encode s` the whole 2.0 encoding (merge included), one thread.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use dagfmt::Dag;
use dagfmt::symmetry::{Group, SymDag, canonicalize};

/// How references and records are coded.
#[derive(Clone, Copy)]
enum Scheme {
    Unaligned,
    Aligned,
    /// Bit-packed references with a 2-bit code choosing one of four widths
    /// per level (chosen to minimise the level); records padded to bytes.
    BitsPadded,
}

/// The four widths (bits) minimising `Σ hist[b] · (2 + width ≥ b)`; with
/// `three`, the last is the same as the third (code 0 has another use).
fn best_widths(hist: &[u64; 65], three: bool) -> ([u32; 4], u64) {
    let max = (0..65).rev().find(|&b| hist[b] != 0).unwrap_or(1).max(1) as u32;
    let mut best = ([max; 4], u64::MAX);
    for w1 in 1..=max {
        for w2 in w1..=max {
            for w3 in w2..=max {
                if three && w3 != max {
                    continue;
                }
                let ws = [w1, w2, w3, max];
                let mut cost = 0u64;
                for (b, &n) in hist.iter().enumerate() {
                    if n != 0 {
                        let w = ws.iter().copied().find(|&w| w >= b as u32).unwrap_or(max);
                        cost += n * u64::from(w + 2);
                    }
                }
                if cost < best.1 {
                    best = (ws, cost);
                }
            }
        }
    }
    best
}

fn bytes_for(value: u64) -> u64 {
    match value {
        0..=0xFF => 1,
        0x100..=0xFFFF => 2,
        0x1_0000..=0xFF_FFFF => 3,
        _ => 4,
    }
}

/// Bytes of the level data of `dag` coded by `scheme`, each level sorted by
/// reference count, with `tbits` transform bits per reference.
fn encoded_bytes(dag: &SymDag, scheme: Scheme, tbits: u32) -> u64 {
    let leaf_level = dag.node_levels.len();
    // Address of each class of the level below, in that level's units.
    let mut total = 8 * dag.leaves.len() as u64;
    let mut addr = vec![0u64; dag.leaves.len()];
    for (pos, &class) in dag
        .classes_by_reference_count(leaf_level)
        .iter()
        .enumerate()
    {
        addr[class as usize] = pos as u64;
    }
    for level in (0..leaf_level).rev() {
        let nodes = &dag.node_levels[level];
        let mut widths = [32u32; 4];
        if let Scheme::BitsPadded = scheme {
            let mut hist = [0u64; 65];
            for node in nodes {
                for s in 0..8 {
                    if let Some(r) = node.child(s) {
                        let v = (addr[r.class as usize] << tbits) | 7;
                        hist[(64 - v.leading_zeros()) as usize] += 1;
                    }
                }
            }
            widths = best_widths(&hist, false).0;
        }
        let mut next_addr = vec![0u64; nodes.len()];
        let mut offset = 0u64;
        for &class in &dag.classes_by_reference_count(level) {
            let node = &nodes[class as usize];
            let mut size = 0u64;
            let mut k = 0u64;
            for s in 0..8 {
                if let Some(r) = node.child(s) {
                    k += 1;
                    let a = addr[r.class as usize];
                    size += match scheme {
                        Scheme::Unaligned | Scheme::Aligned => bytes_for(a << tbits),
                        Scheme::BitsPadded => {
                            let b = 64 - ((a << tbits) | 7).leading_zeros();
                            u64::from(2 + widths.iter().copied().find(|&w| w >= b).unwrap_or(64))
                        }
                    };
                }
            }
            let (record, unit) = match scheme {
                Scheme::Unaligned => (4 + k.div_ceil(4) + size, 1),
                Scheme::Aligned => ((4 + k.div_ceil(4) + size).div_ceil(4) * 4, 4),
                Scheme::BitsPadded => (4 + size.div_ceil(8), 1),
            };
            next_addr[class as usize] = offset / unit;
            offset += record;
        }
        total += offset;
        addr = next_addr;
    }
    total
}

fn main() -> ExitCode {
    let files: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    if files.is_empty() {
        eprintln!("usage: format2_sizes FILE.vdag...");
        return ExitCode::FAILURE;
    }
    println!("Sizes as fractions of the classic 32-bit SVDAG layout of the same voxels.");
    println!(
        "| file | D | classic bytes | 1.0 | SSVDAG | refl u2 | refl a2 | refl bits | full48 u2 | refl seq bytes | full48 seq bits | **2.0** (refl seq bits) | 2.0 bytes | 2.0 / SSVDAG | encoder bytes | merge s | encode s |"
    );
    println!(
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    );
    for path in files {
        let map = match dagfmt::mmap::MappedFile::open(&path) {
            Ok(m) => m,
            Err(e) => {
                eprintln!("error: {}: {e}", path.display());
                return ExitCode::FAILURE;
            }
        };
        let dag = match Dag::open(map.bytes()) {
            Ok(d) => d,
            Err(e) => {
                eprintln!("error: {}: {e}", path.display());
                return ExitCode::FAILURE;
            }
        };
        let stats = match dagfmt::stats::analyze(&dag) {
            Ok(s) => s,
            Err(e) => {
                eprintln!("error: {}: {e}", path.display());
                return ExitCode::FAILURE;
            }
        };
        let classic = stats.classic_svdag_bytes as f64;
        let levels = usize::from(dag.leaf_level()) + 1;
        // Header, table and padding of a file with the level sections only.
        let overhead = 128 + 40 * levels as u64 + 7 * levels as u64;
        let v1 = 128
            + 40 * levels as u64
            + stats
                .levels
                .iter()
                .map(|l| l.bytes.div_ceil(8) * 8)
                .sum::<u64>();
        let start = Instant::now();
        let refl = match canonicalize(&dag, Group::Reflections, Group::Reflections) {
            Ok(s) => s,
            Err(e) => {
                eprintln!("error: {}: {e}", path.display());
                return ExitCode::FAILURE;
            }
        };
        let secs = start.elapsed().as_secs_f64();
        let full = canonicalize(&dag, Group::Full, Group::Full)
            .expect("the file merged under reflections");
        // Shared with `dagtool info` (dagfmt::stats::format_sizes).
        let ssvdag = dagfmt::stats::ssvdag_bytes(&refl);
        let u2 = encoded_bytes(&refl, Scheme::Unaligned, 3) + overhead;
        let a2 = encoded_bytes(&refl, Scheme::Aligned, 3) + overhead;
        let bits = encoded_bytes(&refl, Scheme::BitsPadded, 3) + overhead;
        let full_u2 = encoded_bytes(&full, Scheme::Unaligned, 6) + overhead;
        let seq_bytes = implicit_bytes(&refl, 3, false) + overhead;
        let full_seq = implicit_bytes(&full, 6, true) + overhead;
        let v2 = implicit_bytes(&refl, 3, true) + overhead;
        let start = Instant::now();
        let encoded = match dagfmt::v2::encode(&dag) {
            Ok(e) => e,
            Err(e) => {
                eprintln!("error: {}: {e}", path.display());
                return ExitCode::FAILURE;
            }
        };
        let encode_secs = start.elapsed().as_secs_f64();
        let real = encoded.level_bytes() + overhead;
        let f = |b: u64| format!("{:.3}", b as f64 / classic);
        println!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | **{}** | {} | {:.3} | {} | {:.1} | {:.1} |",
            path.file_name().unwrap_or_default().to_string_lossy(),
            dag.depth(),
            stats.classic_svdag_bytes,
            f(v1),
            f(ssvdag),
            f(u2),
            f(a2),
            f(bits),
            f(full_u2),
            f(seq_bytes),
            f(full_seq),
            f(v2),
            v2,
            v2 as f64 / ssvdag as f64,
            real,
            secs,
            encode_secs
        );
    }
    ExitCode::SUCCESS
}

/// Estimate: children referenced once are stored right after each other, in
/// the order their parents are stored, after the level's shared nodes; a
/// parent names its first such child by one base reference, the others follow
/// it (2-bit code each, no reference). `bits`: references bit-packed with
/// four widths per level, else 1–4 bytes.
fn implicit_bytes(dag: &SymDag, tbits: u32, bits: bool) -> u64 {
    let leaf_level = dag.node_levels.len();
    let n_of = |level: usize| {
        if level == leaf_level {
            dag.leaves.len()
        } else {
            dag.node_levels[level].len()
        }
    };
    let mut counts: Vec<Vec<u64>> = vec![Vec::new()];
    for level in 1..=leaf_level {
        let mut c = vec![0u64; n_of(level)];
        for node in &dag.node_levels[level - 1] {
            for s in 0..8 {
                if let Some(r) = node.child(s) {
                    c[r.class as usize] += 1;
                }
            }
        }
        counts.push(c);
    }
    let mut orders: Vec<Vec<u32>> = vec![vec![0]];
    for level in 1..=leaf_level {
        let c = &counts[level];
        let implicit = |class: u32| c[class as usize] == 1;
        let mut multi: Vec<u32> = (0..c.len() as u32).filter(|&i| !implicit(i)).collect();
        multi.sort_by(|&a, &b| c[b as usize].cmp(&c[a as usize]).then(a.cmp(&b)));
        for &p in &orders[level - 1] {
            let node = &dag.node_levels[level - 1][p as usize];
            for s in 0..8 {
                if let Some(r) = node.child(s).filter(|r| implicit(r.class)) {
                    multi.push(r.class);
                }
            }
        }
        orders.push(multi);
    }
    let mut total = 8 * dag.leaves.len() as u64;
    let mut addr = vec![0u64; n_of(leaf_level)];
    for (pos, &class) in orders[leaf_level].iter().enumerate() {
        addr[class as usize] = pos as u64;
    }
    for level in (0..leaf_level).rev() {
        let c = &counts[level + 1];
        let nodes = &dag.node_levels[level];
        // (value, is explicit) of every coded reference, per node.
        let mut widths = [32u32; 4];
        if bits {
            let mut hist = [0u64; 65];
            for &p in &orders[level] {
                let node = &nodes[p as usize];
                let mut base = None;
                for s in 0..8 {
                    if let Some(r) = node.child(s) {
                        let a = addr[r.class as usize];
                        if c[r.class as usize] == 1 {
                            base.get_or_insert(a);
                        } else {
                            let v = (a << tbits) | 7;
                            hist[(64 - v.leading_zeros()) as usize] += 1;
                        }
                    }
                }
                if let Some(a) = base {
                    hist[(64 - (a | 1).leading_zeros()) as usize] += 1;
                }
            }
            widths = best_widths(&hist, true).0;
        }
        let cost_bits = |v: u64| -> u64 {
            let b = 64 - v.leading_zeros();
            u64::from(widths.iter().copied().find(|&w| w >= b).unwrap_or(64))
        };
        // Byte references: lengths {b, b + 1, b + 2} for the level's b in
        // 1..=2 (code 0 is "sequential"), the smaller level that fits.
        let byte_len =
            |v: u64, b: u64| -> Option<u64> { (b..=b + 2).find(|&l| l == 8 || v >> (8 * l) == 0) };
        let mut best: Option<(u64, Vec<u64>)> = None;
        for b in [1u64, 2] {
            if bits && b == 2 {
                break;
            }
            let mut next_addr = vec![0u64; nodes.len()];
            let mut offset = 0u64;
            let mut feasible = true;
            for &p in &orders[level] {
                let node = &nodes[p as usize];
                let mut k = 0u64;
                let mut size = 0u64;
                let mut base = None;
                for s in 0..8 {
                    if let Some(r) = node.child(s) {
                        k += 1;
                        let a = addr[r.class as usize];
                        if c[r.class as usize] == 1 {
                            base.get_or_insert(a);
                        } else if bits {
                            size += cost_bits((a << tbits) | 7);
                        } else if let Some(l) = byte_len(a << tbits, b) {
                            size += 8 * l;
                        } else {
                            feasible = false;
                        }
                    }
                }
                if let Some(a) = base {
                    k += 1;
                    if bits {
                        size += cost_bits(a | 1);
                    } else if let Some(l) = byte_len(a, b) {
                        size += 8 * l;
                    } else {
                        feasible = false;
                    }
                }
                let record = 4 + (size + 2 * k).div_ceil(8);
                next_addr[p as usize] = offset;
                offset += record;
            }
            if feasible && best.as_ref().is_none_or(|(o, _)| offset < *o) {
                best = Some((offset, next_addr));
            }
        }
        let (offset, next_addr) = best.expect("lengths of 2 to 4 bytes fit every level");
        total += offset;
        addr = next_addr;
    }
    total
}
