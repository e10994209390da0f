//! Solid voxelization: which voxel centres lie inside the mesh.
//!
//! A voxel is inside when a ray from its centre crosses the surface an odd
//! number of times. The converter counts crossings along columns of voxel
//! centres, one axis at a time, chunk by chunk:
//!
//! - each crossing of a column (a line through voxel centres parallel to axis
//!   `w`) with a triangle is computed exactly; a column that passes exactly
//!   through an edge or a vertex of the projected mesh is decided by a
//!   top-left rule, which is the same as moving the column by an infinitesimal
//!   `(-1, -delta)` in its `(u, v)` plane; so on a closed surface every column
//!   crosses it an even number of times and no crossing is counted twice or lost;
//! - a crossing belongs to the chunk whose half-open range `[w0, w0 + C)`
//!   (lattice units) contains its `w` coordinate; it toggles the parity of the
//!   column's voxels whose centres lie above it;
//! - chunks are visited in Morton order, which visits the chunk below (smaller
//!   `w`, same `u`, `v`) first, so the parity entering a chunk is the XOR of the
//!   parity changes of the chunks below it in the same column of chunks, kept in
//!   a `C x C` bitmap per column of chunks ([`ColumnParity`]).
//!
//! Closed meshes (every edge used an even number of times) use columns along
//! `z` only. For open meshes "inside" is not well defined; the converter then
//! takes the majority of the three parities along `x`, `y` and `z` (voxels
//! inside by at least two of them), which fills watertight parts correctly and
//! fills no more than one axis' worth of spill-out behind holes.

use std::collections::HashMap;

use crate::geom::{SUBVOXEL, Triangle, normal};
use crate::voxelize::{ChunkBuffer, ChunkPlace, NO_TAG, local_morton};

/// Crossings of the columns of one chunk along one axis.
#[derive(Debug, Clone)]
pub struct ChunkCrossings {
    /// Column axis: 0 = x, 1 = y, 2 = z.
    pub axis: usize,
    bits: u32,
    /// Per column (`cu + C * cv`): bit `k` set when the parity toggles at voxel `k`.
    toggles: Vec<u128>,
    /// Per column: parity of all crossings in the chunk (1 bit per column).
    through: Vec<u64>,
}

impl ChunkCrossings {
    /// No crossings yet, for chunks of side `2^bits`, columns along `axis`.
    pub fn new(bits: u32, axis: usize) -> Self {
        let cols = 1usize << (2 * bits);
        ChunkCrossings {
            axis,
            bits,
            toggles: vec![0; cols],
            through: vec![0; cols.div_ceil(64)],
        }
    }

    /// The per-column parity change across the chunk (bit per column).
    pub fn through(&self) -> &[u64] {
        &self.through
    }

    /// Adds the crossings of triangle `tri` with the chunk's columns.
    pub fn add_triangle(&mut self, place: &ChunkPlace, tri: &Triangle) {
        let w = self.axis;
        let u = (w + 1) % 3;
        let v = (w + 2) % 3;
        let mut t = *tri;
        let mut n = normal(&t);
        if n[w] == 0 {
            // Parallel to the columns: a column moved off its exact position
            // never meets it.
            return;
        }
        if n[w] < 0 {
            t.swap(1, 2);
            n = n.map(|c| -c);
        }
        let s = i128::from(SUBVOXEL);
        let side = place.side();
        // Columns whose centre (k + 1/2) s lies in the projected bounding box.
        let mut krange = [(0i64, 0i64); 2];
        for (slot, a) in [u, v].into_iter().enumerate() {
            let mn = t.iter().map(|p| p[a]).min().expect("3");
            let mx = t.iter().map(|p| p[a]).max().expect("3");
            // (2k + 1) s >= 2 mn  <=>  k >= ceil((2 mn - s) / 2s)
            let s64 = SUBVOXEL;
            let k0 = -((-(2 * mn - s64)).div_euclid(2 * s64));
            let k1 = (2 * mx - s64).div_euclid(2 * s64);
            let lo = k0.max(place.origin[a]);
            let hi = k1.min(place.origin[a] + side - 1);
            if lo > hi {
                return;
            }
            krange[slot] = (lo, hi);
        }
        // Doubled coordinates make column centres integers.
        let p2 = t.map(|p| p.map(|c| 2 * i128::from(c)));
        let edges = [0, 1, 2].map(|j| {
            let a = p2[j];
            let b = p2[(j + 1) % 3];
            let du = b[u] - a[u];
            let dv = b[v] - a[v];
            // Top-left rule: an edge owns the points exactly on it iff the
            // column moved by (-1, -delta) falls inside.
            let owns = dv > 0 || (dv == 0 && du < 0);
            (a, du, dv, owns)
        });
        let w0 = place.origin[w];
        let z0 = i128::from(w0) * s; // chunk range [z0, z1) in lattice units
        let z1 = i128::from(w0 + side) * s;
        let nw = n[w];
        for kv in krange[1].0..=krange[1].1 {
            let pv = (2 * i128::from(kv) + 1) * s;
            for ku in krange[0].0..=krange[0].1 {
                let pu = (2 * i128::from(ku) + 1) * s;
                let inside = edges.iter().all(|&(a, du, dv, owns)| {
                    let e = du * (pv - a[v]) - dv * (pu - a[u]);
                    e > 0 || (e == 0 && owns)
                });
                if !inside {
                    continue;
                }
                // Plane: n . (P - p0) = 0 with P = (pu/2, pv/2, z):
                // 2 z n_w = 2 p0w n_w - (n_u (pu - 2 p0u) + n_v (pv - 2 p0v)) =: y.
                let a0 = p2[0];
                let y = a0[w] * nw - (n[u] * (pu - a0[u]) + n[v] * (pv - a0[v]));
                if y < 2 * z0 * nw || y >= 2 * z1 * nw {
                    continue;
                }
                // First voxel whose centre is above: (2k + 1) s n_w > y.
                let k_start = (y - s * nw).div_euclid(2 * s * nw) + 1;
                let col = ((ku - place.origin[u]) + (kv - place.origin[v]) * side) as usize;
                let rel = k_start - i128::from(w0);
                if rel < i128::from(side) {
                    self.toggles[col] ^= 1u128 << rel;
                }
                self.through[col >> 6] ^= 1 << (col & 63);
            }
        }
    }

    /// The inside bits of column `col` given the parity entering the chunk.
    #[inline]
    fn inside(&self, col: usize, incoming: bool) -> u128 {
        let mut x = self.toggles[col];
        // Prefix XOR: bit k = XOR of toggles at 0..=k.
        x ^= x << 1;
        x ^= x << 2;
        x ^= x << 4;
        x ^= x << 8;
        x ^= x << 16;
        x ^= x << 32;
        x ^= x << 64;
        if incoming {
            x = !x;
        }
        let side = 1u32 << self.bits;
        if side < 128 {
            x & ((1u128 << side) - 1)
        } else {
            x
        }
    }
}

/// Parity entering each chunk, per column of chunks, for one axis.
#[derive(Debug, Default)]
pub struct ColumnParity {
    /// Key: the chunk's coordinates along (u, v); value: one bit per voxel column.
    state: HashMap<(u64, u64), Box<[u64]>>,
}

impl ColumnParity {
    /// The parity entering the chunk at `chunk` (chunk coordinates) for
    /// columns along `axis`, then records the chunk's own change `through`.
    /// Returns `None` when every column enters with parity 0.
    pub fn enter(
        &mut self,
        axis: usize,
        chunk: [u64; 3],
        through: Option<&[u64]>,
    ) -> Option<Box<[u64]>> {
        let key = (chunk[(axis + 1) % 3], chunk[(axis + 2) % 3]);
        let incoming = self.state.get(&key).cloned();
        if let Some(t) = through.filter(|t| t.iter().any(|&w| w != 0)) {
            let entry = self
                .state
                .entry(key)
                .or_insert_with(|| vec![0u64; t.len()].into_boxed_slice());
            for (e, &x) in entry.iter_mut().zip(t) {
                *e ^= x;
            }
            if entry.iter().all(|&w| w == 0) {
                self.state.remove(&key);
            }
        }
        incoming
    }

    /// Whether the chunk at `chunk` has non-zero incoming parity.
    pub fn is_active(&self, axis: usize, chunk: [u64; 3]) -> bool {
        self.state
            .contains_key(&(chunk[(axis + 1) % 3], chunk[(axis + 2) % 3]))
    }

    /// Whether every column enters every chunk with parity 0.
    pub fn is_empty(&self) -> bool {
        self.state.is_empty()
    }

    /// Bytes held.
    pub fn heap_bytes(&self) -> usize {
        self.state.values().map(|b| b.len() * 8 + 48).sum()
    }
}

/// `NIBBLE_MASKS[w][j * 4 + i][n]`: the leaf mask bits of the voxels of a 4^3
/// brick in the column at `(u, v) = (i, j)` (with `u = w + 1`, `v = w + 2`
/// mod 3) whose positions along `w` are the set bits of the nibble `n`.
static NIBBLE_MASKS: [[[u64; 16]; 16]; 3] = {
    let mut t = [[[0u64; 16]; 16]; 3];
    let mut w = 0;
    while w < 3 {
        let u = (w + 1) % 3;
        let v = (w + 2) % 3;
        let mut g = 0;
        while g < 16 {
            let mut n = 0;
            while n < 16 {
                let mut mask = 0u64;
                let mut k = 0;
                while k < 4 {
                    if n >> k & 1 != 0 {
                        let mut c = [0u32; 3];
                        c[u] = (g % 4) as u32;
                        c[v] = (g / 4) as u32;
                        c[w] = k as u32;
                        let hi =
                            ((c[0] >> 1) & 1) | (((c[1] >> 1) & 1) << 1) | (((c[2] >> 1) & 1) << 2);
                        let lo = (c[0] & 1) | ((c[1] & 1) << 1) | ((c[2] & 1) << 2);
                        mask |= 1u64 << (hi * 8 + lo);
                    }
                    k += 1;
                }
                t[w][g][n] = mask;
                n += 1;
            }
            g += 1;
        }
        w += 1;
    }
    t
};

/// Sets the inside voxels of a chunk in `buf`: with one axis, those of odd
/// parity; with three, those of odd parity along at least two axes.
/// `crossings[i]` and `incoming[i]` belong to the same axis; `None` crossings
/// mean the chunk has no crossings along that axis.
pub fn fill_inside(
    buf: &mut ChunkBuffer,
    bits: u32,
    axes: &[usize],
    crossings: &[Option<&ChunkCrossings>],
    incoming: &[Option<&[u64]>],
) {
    let side = 1usize << bits;
    let cols = side * side;
    let nbricks = 1usize << (3 * (bits - 2));
    // Inside masks per axis in brick layout.
    let mut votes: Vec<Vec<u64>> = Vec::with_capacity(axes.len());
    for (i, &w) in axes.iter().enumerate() {
        let u = (w + 1) % 3;
        let v = (w + 2) % 3;
        // Inside bits of every column first, then whole bricks at once: the
        // 4-bit slice of each of a brick's 16 columns maps to its mask
        // through a table (no per-voxel work).
        let mut inside = vec![0u128; cols];
        let mut any = false;
        for (col, slot) in inside.iter_mut().enumerate() {
            let inc = incoming[i].is_some_and(|b| b[col >> 6] >> (col & 63) & 1 != 0);
            *slot = match crossings[i] {
                Some(c) => c.inside(col, inc),
                None if inc => {
                    if side < 128 {
                        (1u128 << side) - 1
                    } else {
                        u128::MAX
                    }
                }
                None => 0,
            };
            any |= *slot != 0;
        }
        let mut vol = Vec::new();
        if any {
            vol = vec![0u64; nbricks];
            let table = &NIBBLE_MASKS[w];
            let quarter = side / 4;
            for bv in 0..quarter {
                for bu in 0..quarter {
                    let mut group = [0u128; 16];
                    let mut nonzero = false;
                    for j in 0..4 {
                        for i2 in 0..4 {
                            let col = (4 * bu + i2) + side * (4 * bv + j);
                            group[j * 4 + i2] = inside[col];
                            nonzero |= inside[col] != 0;
                        }
                    }
                    if !nonzero {
                        continue;
                    }
                    for bw in 0..quarter {
                        let mut mask = 0u64;
                        for (g, &column) in group.iter().enumerate() {
                            mask |= table[g][((column >> (4 * bw)) & 15) as usize];
                        }
                        if mask != 0 {
                            let mut c = [0u32; 3];
                            c[u] = 4 * bu as u32;
                            c[v] = 4 * bv as u32;
                            c[w] = 4 * bw as u32;
                            vol[(local_morton(c[0], c[1], c[2]) >> 6) as usize] = mask;
                        }
                    }
                }
            }
        }
        votes.push(vol);
    }
    let get = |v: &Vec<u64>, i: usize| if v.is_empty() { 0 } else { v[i] };
    for brick in 0..nbricks {
        let mask = if votes.len() == 1 {
            get(&votes[0], brick)
        } else {
            let (a, b, c) = (
                get(&votes[0], brick),
                get(&votes[1], brick),
                get(&votes[2], brick),
            );
            (a & b) | (a & c) | (b & c)
        };
        if mask != 0 {
            buf.or_brick(brick, mask, NO_TAG);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nibble_masks_follow_leaf_bits() {
        for w in 0..3 {
            let u = (w + 1) % 3;
            let v = (w + 2) % 3;
            for g in 0..16u32 {
                for k in 0..4u32 {
                    let mut c = [0u32; 3];
                    c[u] = g % 4;
                    c[v] = g / 4;
                    c[w] = k;
                    let bit = dagfmt::layout::leaf_bit(c[0], c[1], c[2]);
                    assert_eq!(NIBBLE_MASKS[w][g as usize][1 << k], 1u64 << bit);
                }
                assert_eq!(NIBBLE_MASKS[w][g as usize][15].count_ones(), 4);
            }
        }
    }
}
