//! File surgery on format 2.0 files (spec §23): a 2.0 file as items that
//! name their children by index ([`Model2`]), edited and laid out again with
//! every offset, base reference, width, item count and checksum recomputed,
//! so that a malformed case breaks the one rule its edit aims at.
//!
//! The layout ([`Model2::encode`]) is written here from §23.2–§23.3 and
//! shares only [`dagfmt::v2::best_widths`] (the minimising triple) with the
//! library's encoder.

use dagfmt::ErrorCode;
use dagfmt::FormatError;
use dagfmt::layout::HEADER_SIZE;
use dagfmt::v2::{self, Child};

use crate::model::{RawFile, entry};

/// How an item names one child.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ChildRef {
    /// A shared reference to item `item` of the level below, reflection `r`.
    Shared {
        /// Index of the item in the level below.
        item: usize,
        /// Reflection (§23.4).
        r: u8,
    },
    /// A sequential child: item `item` of the level below (the parent's
    /// sequential children are consecutive items, in slot order).
    Sequential {
        /// Index of the item in the level below.
        item: usize,
    },
}

/// One interior record.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Record {
    /// The 24 attribute bits.
    pub attribute: u32,
    /// Per physical slot, the child.
    pub children: [Option<ChildRef>; 8],
}

/// A 2.0 file as items.
#[derive(Clone, Debug)]
pub struct Model2 {
    /// The file it came from: header and the sections after the levels.
    pub raw: RawFile,
    /// Interior levels, root first.
    pub levels: Vec<Vec<Record>>,
    /// Leaf masks.
    pub leaves: Vec<u64>,
}

/// Edits applied while laying out: for tests of the width rules.
#[derive(Clone, Debug, Default)]
pub struct Layout2Options {
    /// Per level: widths to use instead of the minimising triple.
    pub widths: Vec<(usize, [u8; 3])>,
    /// (level, record, reference rank): this reference uses code 3.
    pub widen: Option<(usize, usize, usize)>,
}

impl Model2 {
    /// Decodes a valid 2.0 file.
    pub fn decode(bytes: &[u8]) -> Result<Model2, FormatError> {
        let dag = dagfmt::Dag2::open(bytes)?;
        let raw = RawFile::split(bytes)?;
        let levels_v = dag.levels();
        let leaf = levels_v.len() - 1;
        // Item index of each offset, per level.
        let mut starts: Vec<Vec<u64>> = Vec::new();
        for lv in levels_v {
            let mut s = Vec::new();
            if !lv.is_leaf {
                let mut at = 0u64;
                while at < lv.bytes.len() as u64 {
                    s.push(at);
                    at += u64::from(v2::decode_node(lv.bytes, at, lv.widths)?.size);
                }
            }
            starts.push(s);
        }
        let bad =
            |what: &str| FormatError::new(ErrorCode::ReferenceOutOfRange2, 0, what.to_string());
        let mut levels = Vec::new();
        for l in 0..leaf {
            let lv = &levels_v[l];
            let mut recs = Vec::new();
            for &at in &starts[l] {
                let node = v2::decode_node(lv.bytes, at, lv.widths)?;
                let item_of = |target: u64| -> Result<usize, FormatError> {
                    if l + 1 == leaf {
                        Ok(target as usize)
                    } else {
                        starts[l + 1]
                            .binary_search(&target)
                            .map_err(|_| bad("target"))
                    }
                };
                let mut children = [None; 8];
                for (slot, c) in node.children.iter().enumerate() {
                    children[slot] = match c {
                        None => None,
                        Some(Child::Shared { target, reflection }) => Some(ChildRef::Shared {
                            item: item_of(*target)?,
                            r: *reflection,
                        }),
                        Some(Child::Sequential { base, index }) => Some(ChildRef::Sequential {
                            item: item_of(*base)? + *index as usize,
                        }),
                    };
                }
                recs.push(Record {
                    attribute: node.attribute(),
                    children,
                });
            }
            levels.push(recs);
        }
        let leaves = levels_v[leaf]
            .bytes
            .chunks_exact(8)
            .map(|m| u64::from_le_bytes(m.try_into().expect("8")))
            .collect();
        Ok(Model2 {
            raw,
            levels,
            leaves,
        })
    }

    /// Lays the file out as §23.2–§23.3 say, with minimal widths.
    pub fn encode(&self) -> Vec<u8> {
        self.encode_with(&Layout2Options::default())
    }

    /// Lays the file out with `options`' edits.
    pub fn encode_with(&self, options: &Layout2Options) -> Vec<u8> {
        let leaf = self.levels.len();
        let mut level_bytes: Vec<Vec<u8>> = vec![Vec::new(); leaf + 1];
        let mut widths: Vec<[u8; 3]> = vec![[0; 3]; leaf + 1];
        for m in &self.leaves {
            level_bytes[leaf].extend_from_slice(&m.to_le_bytes());
        }
        // Address of each item of the level below.
        let mut addr: Vec<u64> = (0..self.leaves.len() as u64).collect();
        for l in (0..leaf).rev() {
            // (header, references: (value, is_base)).
            let mut recs = Vec::new();
            let mut hist = [0u64; 65];
            let bits = |v: u64| (64 - v.leading_zeros()).max(1) as usize;
            for rec in &self.levels[l] {
                let mut mask = 0u8;
                let mut values = Vec::new();
                let mut codes_zero = Vec::new();
                let mut first_seq = None;
                for (slot, c) in rec.children.iter().enumerate() {
                    let Some(c) = c else { continue };
                    mask |= 1 << slot;
                    match *c {
                        ChildRef::Shared { item, r } => {
                            let v = addr.get(item).copied().unwrap_or(addr.len() as u64) << 3
                                | u64::from(r);
                            values.push(v);
                            codes_zero.push(false);
                        }
                        ChildRef::Sequential { item } => {
                            first_seq.get_or_insert(item);
                            codes_zero.push(true);
                        }
                    }
                }
                if let Some(item) = first_seq {
                    values.push(addr.get(item).copied().unwrap_or(addr.len() as u64));
                }
                for &v in &values {
                    hist[bits(v)] += 1;
                }
                recs.push((mask as u32 | rec.attribute << 8, codes_zero, values));
            }
            let w = options
                .widths
                .iter()
                .find(|(lv, _)| *lv == l)
                .map(|(_, w)| *w)
                .unwrap_or_else(|| v2::best_widths(&hist).expect("fits 40 bits"));
            widths[l] = w;
            let mut bytes = Vec::new();
            let mut next_addr = Vec::new();
            for (index, (header, codes_zero, values)) in recs.iter().enumerate() {
                next_addr.push(bytes.len() as u64);
                let code_of = |v: u64| {
                    w.iter()
                        .position(|&x| x as usize >= bits(v))
                        .map_or(3, |i| i as u8 + 1)
                };
                let mut codes: Vec<u8> = Vec::new();
                let mut vi = 0;
                for &z in codes_zero {
                    if z {
                        codes.push(0);
                    } else {
                        codes.push(code_of(values[vi]));
                        vi += 1;
                    }
                }
                if codes_zero.iter().any(|&z| z) {
                    codes.push(code_of(values[values.len() - 1]));
                }
                let mut value_codes: Vec<u8> = codes.iter().copied().filter(|&c| c != 0).collect();
                if let Some((wl, wr, rank)) = options.widen
                    && wl == l
                    && wr == index
                {
                    value_codes[rank] = 3;
                    let mut seen = 0;
                    for c in codes.iter_mut() {
                        if *c != 0 {
                            if seen == rank {
                                *c = 3;
                            }
                            seen += 1;
                        }
                    }
                }
                let mut bw = BitWriter::default();
                for &c in &codes {
                    bw.put(u64::from(c), 2);
                }
                for (&v, &c) in values.iter().zip(&value_codes) {
                    bw.put(v, u32::from(w[usize::from(c) - 1]));
                }
                bytes.extend_from_slice(&header.to_le_bytes());
                bytes.extend_from_slice(&bw.bytes);
            }
            level_bytes[l] = bytes;
            addr = next_addr;
        }
        let mut raw = self.raw.clone();
        for (l, bytes) in level_bytes.into_iter().enumerate() {
            let s = &mut raw.sections[l];
            s.entry.item_count = if l == leaf {
                self.leaves.len() as u64
            } else {
                self.levels[l].len() as u64
            };
            s.entry.pointer_width = widths[l][0];
            s.entry.reserved0 = u16::from_le_bytes([widths[l][1], widths[l][2]]);
            s.bytes = bytes;
        }
        raw.join(&Default::default())
    }

    /// Offset in the file and stream bits of record `index` of `level`.
    pub fn record(bytes: &[u8], level: usize, index: usize) -> (usize, u64) {
        let dag = dagfmt::Dag2::open(bytes).expect("valid 2.0");
        let lv = dag.levels()[level];
        let mut at = 0u64;
        for _ in 0..index {
            at += u64::from(
                v2::decode_node(lv.bytes, at, lv.widths)
                    .expect("record")
                    .size,
            );
        }
        let (_, bits) = v2::record_references(lv.bytes, at, lv.widths).expect("record");
        let section = dag.sections()[level].offset as usize;
        (section + at as usize, bits)
    }

    /// References naming each item of the level below `level`: (shared, sequential).
    pub fn naming(&self, level: usize) -> Vec<(u32, u32)> {
        let n = if level + 1 == self.levels.len() {
            self.leaves.len()
        } else {
            self.levels[level + 1].len()
        };
        let mut out = vec![(0u32, 0u32); n];
        for rec in &self.levels[level] {
            for c in rec.children.iter().flatten() {
                match *c {
                    ChildRef::Shared { item, .. } => out[item].0 += 1,
                    ChildRef::Sequential { item } => out[item].1 += 1,
                }
            }
        }
        out
    }
}

/// Byte offset of the table entry of `level`'s section.
pub fn entry_of(level: usize) -> usize {
    HEADER_SIZE + level * dagfmt::layout::SECTION_ENTRY_SIZE + entry::WIDTH
}

#[derive(Default)]
struct BitWriter {
    bytes: Vec<u8>,
    bit: u64,
}

impl BitWriter {
    fn put(&mut self, value: u64, width: u32) {
        for i in 0..width {
            if self.bit.is_multiple_of(8) {
                self.bytes.push(0);
            }
            if value >> i & 1 != 0 {
                let last = self.bytes.len() - 1;
                self.bytes[last] |= 1 << (self.bit % 8);
            }
            self.bit += 1;
        }
    }
}
