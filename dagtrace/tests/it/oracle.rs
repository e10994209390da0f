//! An independent, slow reference for the ray/hit semantics of spec/VDAG.md:
//! brute force over every occupied cell with an f64 slab test, and the
//! acceptance rules (tolerance eps_g) that conformance applies.

use dagfmt::batch::{Hit, Ray};
use dagfmt::{AttributeKind, Dag};

/// The occupied cells of every level of a small DAG, from `Dag::voxels()`.
pub struct Reference {
    depth: u8,
    root_min: [f64; 3],
    root_size: f64,
    kind: AttributeKind,
    /// Set voxels sorted by Morton code (the dense index order).
    mortons: Vec<u64>,
    /// Per level 0..=D: the occupied cells (sorted, unique).
    cells: Vec<Vec<[u32; 3]>>,
}

/// The ray in f64 grid space.
#[derive(Clone, Copy, Debug)]
pub struct GridRay {
    pub o: [f64; 3],
    pub d: [f64; 3],
    pub tmin: f64,
    pub tmax: f64,
}

/// Entry and exit of the segment into a closed box, per spec/VDAG.md's slab test.
pub fn entry_exit(r: &GridRay, lo: [f64; 3], hi: [f64; 3]) -> Option<(f64, f64, f64)> {
    if (0..3).any(|i| lo[i] > hi[i]) {
        return None; // a box shrunk to nothing
    }
    let (mut near, mut far) = (f64::NEG_INFINITY, f64::INFINITY);
    for i in 0..3 {
        if r.d[i] == 0.0 {
            if !(lo[i] <= r.o[i] && r.o[i] <= hi[i]) {
                return None;
            }
        } else {
            let a = (lo[i] - r.o[i]) / r.d[i];
            let b = (hi[i] - r.o[i]) / r.d[i];
            near = near.max(a.min(b));
            far = far.min(a.max(b));
        }
    }
    let enter = r.tmin.max(near);
    let exit = r.tmax.min(far);
    (enter <= exit).then_some((enter, exit, near))
}

/// The faces a tracer may report for a hit on the cell `[lo, hi]` (grid
/// units): face 0 when the segment starts inside the grown cell; the face of
/// axis `a` when that axis can be the last slab entered within the tolerance
/// (its slab start for the shrunk cell is not before the latest slab start
/// for the grown cell, nor before tmin). The exact cell's entry face always
/// satisfies this.
fn faces(r: &GridRay, lo: [f64; 3], hi: [f64; 3], eps: f64) -> Vec<u8> {
    let start = |axis: usize, grow: f64| -> f64 {
        let d = r.d[axis];
        if d == 0.0 {
            f64::NEG_INFINITY
        } else if d > 0.0 {
            (lo[axis] - grow - r.o[axis]) / d
        } else {
            (hi[axis] + grow - r.o[axis]) / d
        }
    };
    let latest_grown = (0..3)
        .map(|a| start(a, eps))
        .fold(f64::NEG_INFINITY, f64::max);
    let mut out = Vec::new();
    if latest_grown <= r.tmin {
        out.push(0);
    }
    for axis in 0..3 {
        let shrunk = start(axis, -eps);
        if r.d[axis] != 0.0 && shrunk >= latest_grown && shrunk >= r.tmin {
            out.push(1 + 2 * axis as u8 + u8::from(r.d[axis] < 0.0));
        }
    }
    out
}

impl Reference {
    pub fn new(dag: &Dag<'_>) -> Self {
        let depth = dag.header().depth;
        let voxels: Vec<[u32; 3]> = dag.voxels().map(|v| v.expect("valid test DAG")).collect();
        let mut mortons: Vec<u64> = voxels
            .iter()
            .map(|v| dagfmt::morton::encode(v[0], v[1], v[2]))
            .collect();
        mortons.sort_unstable();
        let cells = (0..=depth)
            .map(|level| {
                let shift = depth - level;
                let mut c: Vec<[u32; 3]> = voxels.iter().map(|v| v.map(|x| x >> shift)).collect();
                c.sort_unstable();
                c.dedup();
                c
            })
            .collect();
        Reference {
            depth,
            root_min: dag.header().root_min,
            root_size: dag.header().root_size,
            kind: dag.header().attribute_kind,
            mortons,
            cells,
        }
    }

    pub fn grid_ray(&self, ray: &Ray) -> GridRay {
        let scale = (1u64 << self.depth) as f64 / self.root_size;
        GridRay {
            o: [0, 1, 2].map(|i| (f64::from(ray.origin[i]) - self.root_min[i]) * scale),
            d: ray.dir.map(|d| f64::from(d) * scale),
            tmin: f64::from(ray.tmin),
            tmax: f64::from(ray.tmax),
        }
    }

    /// eps_g and eps_t of spec/VDAG.md, grown by a relative 2^-20 to absorb the
    /// reference's own f64 rounding (it can only make the reference more lenient
    /// by a millionth of the tolerance).
    pub fn tolerance(&self, r: &GridRay) -> (f64, f64) {
        let max_o = r.o.iter().fold(0f64, |m, v| m.max(v.abs()));
        let eps_g = (2f64.powi(-12) + 2f64.powi(-21) * ((1u64 << self.depth) as f64).max(max_o))
            * (1.0 + 2f64.powi(-20));
        let norm = (r.d[0] * r.d[0] + r.d[1] * r.d[1] + r.d[2] * r.d[2]).sqrt();
        (eps_g, eps_g / norm)
    }

    fn cell_box(&self, cell: [u32; 3], level: u8, grow: f64) -> ([f64; 3], [f64; 3]) {
        let s = (1u64 << (self.depth - level)) as f64;
        (
            cell.map(|c| f64::from(c) * s - grow),
            cell.map(|c| (f64::from(c) + 1.0) * s + grow),
        )
    }

    /// The exact answer: smallest entry t over occupied cells and every cell
    /// entered at that t (ties), or `None` for a miss.
    pub fn exact(&self, ray: &Ray) -> Option<(f64, Vec<[u32; 3]>)> {
        let level = ray.level.unwrap_or(self.depth);
        let r = self.grid_ray(ray);
        if ray
            .origin
            .iter()
            .chain(&ray.dir)
            .chain([&ray.tmin, &ray.tmax])
            .any(|v| v.is_nan())
            || r.tmin > r.tmax
        {
            return None;
        }
        let mut best: Option<(f64, Vec<[u32; 3]>)> = None;
        for &cell in &self.cells[usize::from(level)] {
            let (lo, hi) = self.cell_box(cell, level, 0.0);
            if let Some((t, _, _)) = entry_exit(&r, lo, hi) {
                match &mut best {
                    Some((bt, ties)) if t == *bt => ties.push(cell),
                    Some((bt, _)) if t > *bt => {}
                    _ => best = Some((t, vec![cell])),
                }
            }
        }
        best
    }

    /// The dense index of the first voxel of a cell (rank of its Morton prefix).
    pub fn index_of(&self, cell: [u32; 3], level: u8) -> u64 {
        let first = dagfmt::morton::encode(cell[0], cell[1], cell[2])
            << (3 * u32::from(self.depth - level));
        self.mortons.partition_point(|&m| m < first) as u64
    }

    fn occupied(&self, level: u8, cell: [i64; 3]) -> bool {
        let n = 1i64 << level;
        cell.iter().all(|&c| (0..n).contains(&c))
            && self.cells[usize::from(level)]
                .binary_search(&cell.map(|c| c as u32))
                .is_ok()
    }

    /// Whether the cube `[p - eps, p + eps]^3` lies in the union of the
    /// occupied closed cells: every cell whose open interior meets the open
    /// cube is occupied.
    fn robust(&self, level: u8, p: [f64; 3], eps: f64) -> bool {
        let s = (1u64 << (self.depth - level)) as f64;
        let mut lo = [0i64; 3];
        let mut hi = [0i64; 3];
        for axis in 0..3 {
            lo[axis] = ((p[axis] - eps) / s).floor() as i64;
            hi[axis] = ((p[axis] + eps) / s).ceil() as i64 - 1;
        }
        (lo[2]..=hi[2]).all(|z| {
            (lo[1]..=hi[1]).all(|y| (lo[0]..=hi[0]).all(|x| self.occupied(level, [x, y, z])))
        })
    }

    /// T-: the first parameter of the segment whose point is robustly inside
    /// the occupied cells (infinity if none). Robustness only changes where a
    /// coordinate crosses a plane `k s +- eps`, so testing those crossings and
    /// the gaps between them inside each grown occupied cell is exact.
    fn first_robust(&self, r: &GridRay, level: u8, eps: f64) -> f64 {
        let s = (1u64 << (self.depth - level)) as f64;
        if r.d.iter().all(|&d| d == 0.0) {
            return if self.robust(level, r.o, eps) {
                r.tmin
            } else {
                f64::INFINITY
            };
        }
        let at = |t: f64| {
            [0, 1, 2].map(|i| {
                if r.d[i] == 0.0 {
                    r.o[i]
                } else {
                    r.o[i] + t * r.d[i]
                }
            })
        };
        let mut best = f64::INFINITY;
        for &cell in &self.cells[usize::from(level)] {
            let (lo, hi) = self.cell_box(cell, level, eps);
            let Some((entry, exit, _)) = entry_exit(r, lo, hi) else {
                continue;
            };
            if entry >= best {
                continue;
            }
            let reach = (2.0 * eps / s).ceil() as i64 + 1;
            let mut stops = vec![entry, exit];
            for (axis, &c) in cell.iter().enumerate() {
                if r.d[axis] == 0.0 {
                    continue;
                }
                let c = i64::from(c);
                for k in c - reach..=c + 1 + reach {
                    for plane in [k as f64 * s - eps, k as f64 * s + eps] {
                        let t = (plane - r.o[axis]) / r.d[axis];
                        if entry < t && t < exit {
                            stops.push(t);
                        }
                    }
                }
            }
            stops.sort_by(f64::total_cmp);
            stops.dedup();
            let mut found = None;
            for (i, &t) in stops.iter().enumerate() {
                if self.robust(level, at(t), eps) {
                    found = Some(t);
                    break;
                }
                if let Some(&next) = stops.get(i + 1)
                    && self.robust(level, at(0.5 * (t + next)), eps)
                {
                    found = Some(t);
                    break;
                }
            }
            if let Some(t) = found {
                best = best.min(t);
            }
        }
        best
    }

    /// Checks a hit against spec/VDAG.md's acceptance rules; `Err` says why not.
    pub fn check(&self, ray: &Ray, hit: &Hit) -> Result<(), String> {
        let level = ray.level.unwrap_or(self.depth);
        let r = self.grid_ray(ray);
        let invalid = ray
            .origin
            .iter()
            .chain(&ray.dir)
            .chain([&ray.tmin, &ray.tmax])
            .any(|v| v.is_nan())
            || r.tmin > r.tmax;
        if invalid {
            return if hit.hit {
                Err("NaN or tmin > tmax must miss".into())
            } else {
                Ok(())
            };
        }
        let (eps_g, eps_t) = self.tolerance(&r);
        let cells = &self.cells[usize::from(level)];
        let t_minus = self.first_robust(&r, level, eps_g);
        if !hit.hit {
            return if t_minus == f64::INFINITY {
                Ok(())
            } else {
                Err(format!(
                    "missed, but the point at t = {t_minus} is robustly inside; exact: {:?}",
                    self.exact(ray)
                ))
            };
        }
        if hit.level != level {
            return Err(format!(
                "level {} reported for a ray of level {level}",
                hit.level
            ));
        }
        if cells.binary_search(&hit.voxel).is_err() {
            return Err(format!(
                "cell {:?} is not occupied; exact: {:?}",
                hit.voxel,
                self.exact(ray)
            ));
        }
        let (lo, hi) = self.cell_box(hit.voxel, level, eps_g);
        let Some((e_plus, x_plus, _)) = entry_exit(&r, lo, hi) else {
            return Err(format!(
                "the ray does not meet the grown cell {:?}; exact: {:?}",
                hit.voxel,
                self.exact(ray)
            ));
        };
        if e_plus > t_minus + eps_t {
            return Err(format!(
                "cell {:?} entered at {e_plus} (grown) but an occupied shrunk cell at {t_minus} (eps_t {eps_t}); exact: {:?}",
                hit.voxel,
                self.exact(ray)
            ));
        }
        let t = f64::from(hit.t);
        let zero_dir = r.d.iter().all(|&d| d == 0.0);
        let upper = if zero_dir {
            r.tmin
        } else {
            x_plus.min(t_minus) + eps_t
        };
        let lower = if zero_dir { r.tmin } else { e_plus - eps_t };
        if !(lower <= t && t <= upper) {
            return Err(format!(
                "t = {t} outside [{}, {upper}] for cell {:?}; exact: {:?}",
                lower,
                hit.voxel,
                self.exact(ray)
            ));
        }
        let (lo, hi) = self.cell_box(hit.voxel, level, 0.0);
        let ok_faces = faces(&r, lo, hi, eps_g);
        if !ok_faces.contains(&hit.face) {
            return Err(format!(
                "face {} not among {ok_faces:?} for cell {:?}",
                hit.face, hit.voxel
            ));
        }
        let expected_index = match self.kind {
            AttributeKind::VoxelCount => Some(self.index_of(hit.voxel, level)),
            AttributeKind::None => None,
        };
        if hit.index != expected_index {
            return Err(format!(
                "index {:?}, expected {expected_index:?}",
                hit.index
            ));
        }
        Ok(())
    }
}
