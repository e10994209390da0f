//! Voxels from points and voxel grids, out of core: each point sets the voxel
//! that contains it (or, with a splat radius, every voxel within the radius),
//! and the voxels' Morton codes go through an external sort — sorted runs
//! of a bounded buffer spilled to unnamed temporary files, merged at the end
//! — so that a cloud larger than memory converts within `--memory-limit`.
//!
//! Colours: a voxel takes the colour of the first point (in file order) that
//! sets it. Sorting is stable and the merge prefers earlier runs, so the
//! result does not depend on the buffer's size.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::io::{self, BufReader, BufWriter, Read, Write};

use rayon::slice::ParallelSliceMut;

use crate::error::ConvertError;
use crate::external::{CountedFile, Scratch};

/// Where points fall in the grid: the root cube, the depth and the splat
/// radius.
#[derive(Clone, Copy, Debug)]
pub struct Splat {
    /// World-space corner of the root cube.
    pub root_min: [f64; 3],
    /// World-space edge of the root cube.
    pub root_size: f64,
    /// Depth D.
    pub depth: u8,
    /// Splat radius in world units (0: the voxel containing the point).
    pub radius: f64,
}

impl Splat {
    /// Voxels per world unit.
    fn scale(&self) -> f64 {
        (1u64 << self.depth) as f64 / self.root_size
    }

    /// Calls `f` with every voxel the point `p` sets: with radius 0 the voxel
    /// `floor((p - root_min) 2^D / root_size)`, clamped to the grid (a point
    /// on the far face of the root cube belongs to the last voxel); with
    /// radius R > 0 every voxel of the grid whose closed cube lies within
    /// distance R of `p`. Returns `false` (and sets nothing) when `p` lies
    /// outside the root cube.
    pub fn voxels(&self, p: [f64; 3], mut f: impl FnMut([u32; 3])) -> bool {
        let n = 1u64 << self.depth;
        let scale = self.scale();
        let g = [0, 1, 2].map(|a| (p[a] - self.root_min[a]) * scale);
        if !g.iter().all(|&c| (0.0..=n as f64).contains(&c)) {
            return false;
        }
        let last = (n - 1) as f64;
        if self.radius <= 0.0 {
            f(g.map(|c| c.floor().min(last) as u32));
            return true;
        }
        let r = self.radius * scale;
        let lo = g.map(|c| (c - r).floor().clamp(0.0, last) as u32);
        let hi = g.map(|c| (c + r).floor().clamp(0.0, last) as u32);
        let r2 = r * r;
        for x in lo[0]..=hi[0] {
            let dx = axis_distance(g[0], x);
            for y in lo[1]..=hi[1] {
                let dy = axis_distance(g[1], y);
                if dx * dx + dy * dy > r2 {
                    continue;
                }
                for z in lo[2]..=hi[2] {
                    let dz = axis_distance(g[2], z);
                    if dx * dx + dy * dy + dz * dz <= r2 {
                        f([x, y, z]);
                    }
                }
            }
        }
        true
    }
}

/// Distance along one axis from grid coordinate `c` to the voxel `[k, k+1]`.
pub fn axis_distance(c: f64, k: u32) -> f64 {
    let k = f64::from(k);
    if c < k {
        k - c
    } else if c > k + 1.0 {
        c - k - 1.0
    } else {
        0.0
    }
}

/// Bytes of one spilled entry: code (8) and colour (4).
const ENTRY_BYTES: usize = 12;

/// Collects (Morton code, colour) pairs in a bounded buffer, spilling
/// sorted runs when it fills.
#[derive(Debug)]
pub struct VoxelSorter {
    scratch: Scratch,
    capacity: usize,
    buffer: Vec<(u64, u32)>,
    runs: Vec<CountedFile>,
}

impl VoxelSorter {
    /// A sorter whose buffer holds at most `bytes` bytes of pairs.
    pub fn new(scratch: &Scratch, bytes: u64) -> Self {
        let capacity = (bytes / 16).clamp(1 << 10, 1 << 34) as usize;
        VoxelSorter {
            scratch: scratch.clone(),
            capacity,
            buffer: Vec::new(),
            runs: Vec::new(),
        }
    }

    /// Runs spilled so far.
    pub fn runs(&self) -> usize {
        self.runs.len()
    }

    /// Adds a voxel with its colour (RGBA8 as a little-endian word).
    pub fn push(&mut self, code: u64, rgba: u32) -> Result<(), ConvertError> {
        if self.buffer.len() == self.capacity {
            self.compact()?;
        }
        if self.buffer.capacity() == 0 {
            self.buffer.reserve_exact(self.capacity.min(1 << 16));
        }
        self.buffer.push((code, rgba));
        Ok(())
    }

    /// Sorts and deduplicates the buffer; spills it when that freed less
    /// than half of it.
    fn compact(&mut self) -> Result<(), ConvertError> {
        sort_dedup(&mut self.buffer);
        if self.buffer.len() > self.capacity / 2 {
            self.spill().map_err(|e| self.scratch.error(e))?;
        }
        Ok(())
    }

    fn spill(&mut self) -> io::Result<()> {
        let mut file = self.scratch.counted_file()?;
        {
            let mut w = BufWriter::with_capacity(1 << 20, &mut file);
            for &(code, rgba) in &self.buffer {
                w.write_all(&code.to_le_bytes())?;
                w.write_all(&rgba.to_le_bytes())?;
            }
            w.flush()?;
        }
        self.runs.push(file);
        self.buffer.clear();
        Ok(())
    }

    /// The voxels, sorted by code without repeats, each with the colour of
    /// its first occurrence.
    pub fn finish(mut self) -> Result<SortedVoxels, ConvertError> {
        sort_dedup(&mut self.buffer);
        if self.runs.is_empty() {
            return Ok(SortedVoxels::Memory(self.buffer.into_iter()));
        }
        if !self.buffer.is_empty() {
            self.spill().map_err(|e| self.scratch.error(e))?;
        }
        self.buffer = Vec::new();
        let mut readers = Vec::with_capacity(self.runs.len());
        for run in &mut self.runs {
            let file = run.reader().map_err(|e| self.scratch.error(e))?;
            readers.push(BufReader::with_capacity(
                1 << 18,
                file.try_clone().map_err(|e| self.scratch.error(e))?,
            ));
        }
        let mut merge = Merge {
            scratch: self.scratch.clone(),
            _runs: self.runs,
            readers,
            heap: BinaryHeap::new(),
            last: None,
        };
        for i in 0..merge.readers.len() {
            merge.refill(i).map_err(|e| merge.scratch.error(e))?;
        }
        Ok(SortedVoxels::Merge(merge))
    }
}

/// Stable sort by code, then keep the first of each code.
fn sort_dedup(buffer: &mut Vec<(u64, u32)>) {
    buffer.par_sort_by_key(|e| e.0);
    buffer.dedup_by_key(|e| e.0);
}

/// The sorted voxels of a [`VoxelSorter`].
#[derive(Debug)]
pub enum SortedVoxels {
    /// Nothing was spilled.
    Memory(std::vec::IntoIter<(u64, u32)>),
    /// The merge of the spilled runs.
    Merge(Merge),
}

/// The k-way merge of sorted runs; on equal codes the earlier run wins.
#[derive(Debug)]
pub struct Merge {
    scratch: Scratch,
    _runs: Vec<CountedFile>,
    readers: Vec<BufReader<std::fs::File>>,
    heap: BinaryHeap<Reverse<(u64, usize, u32)>>,
    last: Option<u64>,
}

impl Merge {
    fn refill(&mut self, run: usize) -> io::Result<()> {
        let mut entry = [0u8; ENTRY_BYTES];
        match self.readers[run].read_exact(&mut entry) {
            Ok(()) => {
                let code = u64::from_le_bytes(entry[..8].try_into().expect("8 bytes"));
                let rgba = u32::from_le_bytes(entry[8..].try_into().expect("4 bytes"));
                self.heap.push(Reverse((code, run, rgba)));
                Ok(())
            }
            Err(e) if e.kind() == io::ErrorKind::UnexpectedEof => Ok(()),
            Err(e) => Err(e),
        }
    }
}

impl Iterator for SortedVoxels {
    type Item = Result<(u64, u32), ConvertError>;

    fn next(&mut self) -> Option<Self::Item> {
        match self {
            SortedVoxels::Memory(it) => it.next().map(Ok),
            SortedVoxels::Merge(m) => loop {
                let Reverse((code, run, rgba)) = m.heap.pop()?;
                if let Err(e) = m.refill(run) {
                    return Some(Err(m.scratch.error(e)));
                }
                if m.last == Some(code) {
                    continue;
                }
                m.last = Some(code);
                return Some(Ok((code, rgba)));
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spilled_runs_merge_to_the_in_memory_result() {
        let dir = tempfile::tempdir().unwrap();
        let scratch = Scratch::new(dir.path()).unwrap();
        // Codes repeat across the whole stream; the colour is the index of
        // the pair, so the first occurrence's must win.
        let pairs: Vec<(u64, u32)> = (0..20_000u32)
            .map(|i| ((u64::from(i) * 7919) % 3001, i))
            .collect();
        let mut expected = pairs.clone();
        sort_dedup(&mut expected);
        for bytes in [16 << 10, 1 << 30] {
            let mut sorter = VoxelSorter::new(&scratch, bytes);
            for &(c, v) in &pairs {
                sorter.push(c, v).unwrap();
            }
            let spilled = sorter.runs() > 0;
            assert_eq!(spilled, bytes < 1 << 20);
            let got: Vec<(u64, u32)> = sorter.finish().unwrap().map(Result::unwrap).collect();
            assert_eq!(got, expected);
        }
    }

    #[test]
    fn splats_set_the_voxels_within_the_radius() {
        let s = Splat {
            root_min: [0.0; 3],
            root_size: 8.0,
            depth: 3,
            radius: 0.0,
        };
        let mut got = Vec::new();
        assert!(s.voxels([8.0, 0.0, 3.5], |v| got.push(v)));
        assert_eq!(got, [[7, 0, 3]]);
        assert!(!s.voxels([8.1, 0.0, 0.0], |_| unreachable!()));
        // Radius 1 around the centre of voxel (3, 3, 3): every voxel of the
        // 3³ block around it (the corner ones are 0.5 √3 < 1 away, the next
        // ones 1.5).
        let s = Splat { radius: 1.0, ..s };
        let mut got = Vec::new();
        s.voxels([3.5, 3.5, 3.5], |v| got.push(v));
        assert_eq!(got.len(), 27);
        // Radius 0.6 from a corner point: the 8 voxels sharing the corner
        // (the next ones are 1.0 away).
        let s = Splat { radius: 0.6, ..s };
        let mut got = Vec::new();
        s.voxels([4.0, 4.0, 4.0], |v| got.push(v));
        assert_eq!(got.len(), 8);
    }
}
