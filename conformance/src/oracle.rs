//! The independent oracle: what a conforming tracer may answer for a ray.
//!
//! The oracle shares no code with any tracer. It decodes the occupied cells of
//! the traced level with a plain depth-first walk of the DAG (counting voxels
//! from the leaf masks, never trusting the stored attribute counts), then
//! intersects the ray with *every* occupied cell by brute force. There is no
//! hierarchy, no DDA, no stepping from cell to cell.
//!
//! # Acceptance rules (spec/CONFORMANCE.md § Tolerance)
//!
//! Everything happens in grid space (voxel units). With `eps` the position
//! tolerance of the ray and `eps_t = eps / |d_g|` its image in `t`:
//!
//! * `Occ` is the union of the occupied closed cells; a point `p` is *robustly
//!   inside* when the cube `[p - eps, p + eps]^3` lies in `Occ`. `T-` is the
//!   first `t` of the segment whose point is robustly inside (`inf` if none).
//! * For an occupied cell `C`, `e_C` and `x_C` are the entry and exit `t` of the
//!   segment into `C` grown by `eps` on every side (the slab test of DESIGN).
//! * A miss is accepted iff `T- = inf`. A hit on `C` with parameter `t` is
//!   accepted iff the segment meets the grown `C`, `e_C <= T- + eps_t` and
//!   `e_C - eps_t <= t <= min(x_C, T-) + eps_t`, the face is one of the faces
//!   computed by [`faces`](Oracle::expect), the level is the ray's level and the
//!   index is the dense index of the cell's first voxel (kind 1) or none.
//!
//! # Why f64 and not exact rationals
//!
//! Every decision above compares against geometry moved by `eps` (grown cells,
//! eroded occupancy). Exact ties of the unmoved geometry (a ray along a shared
//! face, edge or corner) are therefore never decision boundaries: they sit
//! `eps >= 2^-21 * max(2^D, |o_g|)` away from one. f32 inputs are exact in
//! f64, and the f64 rounding of the few operations per decision is below
//! `2^-50 * max(2^D, |o_g|)`, i.e. under `2^-29 * eps`. To make the verdicts
//! one-sided, the oracle inflates `eps` and `eps_t` by the factor
//! `1 + 2^-20` (see [`INFLATE`]): that margin dominates the rounding, so the
//! oracle can only be more lenient than the exact rules, by a relative `1e-6`
//! of the tolerance, never stricter.

use std::collections::HashMap;

use dagfmt::{AttributeKind, Dag, FormatError, morton};

/// Factor by which the oracle grows the tolerance to absorb its own f64
/// rounding (see the module documentation).
pub const INFLATE: f64 = 1.0 + 1.0 / (1u64 << 20) as f64;

/// The position tolerance of DESIGN, in grid units, for a ray whose grid-space
/// origin is `origin_g` in a depth-`depth` volume:
/// `2^-12 + 2^-21 * max(2^D, max_i |o_g,i|)`.
pub fn position_tolerance(depth: u8, origin_g: [f64; 3]) -> f64 {
    let resolution = (1u64 << depth) as f64;
    let reach = origin_g.iter().fold(resolution, |m, v| m.max(v.abs()));
    2f64.powi(-12) + 2f64.powi(-21) * reach
}

/// A ray in the form the oracle needs: world space, f32, level resolved.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OracleRay {
    /// World-space origin.
    pub origin: [f32; 3],
    /// World-space direction (any length, zero allowed).
    pub dir: [f32; 3],
    /// Start of the segment (`t`).
    pub tmin: f32,
    /// End of the segment (`t`).
    pub tmax: f32,
    /// Level traced, `1 ..= D`.
    pub level: u8,
}

/// What a conforming tracer must do with a ray.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Only a miss is accepted.
    Miss,
    /// Only a hit (on one of the listed cells) is accepted.
    Hit,
    /// The ray grazes occupied cells within the tolerance: a miss or a hit on
    /// one of the listed cells is accepted.
    Either,
}

impl Verdict {
    /// The keyword of the expectation format.
    pub fn keyword(self) -> &'static str {
        match self {
            Verdict::Miss => "miss",
            Verdict::Hit => "hit",
            Verdict::Either => "either",
        }
    }
}

/// One cell a tracer may report, with what may be reported with it.
#[derive(Clone, Debug, PartialEq)]
pub struct AcceptableCell {
    /// Cell coordinates at the traced level.
    pub cell: [u32; 3],
    /// Smallest acceptable `t`: the smallest f32 not below the exact bound
    /// (answers are f32, so rounding the bounds inward changes nothing).
    pub t_lo: f32,
    /// Largest acceptable `t`: the largest f32 not above the exact bound.
    pub t_hi: f32,
    /// Acceptable entry faces, bit `f` for face `f` (0 = inside, 1..=6 = -X..+Z).
    pub faces: u8,
    /// The attribute index to report (`None` for attribute kind 0).
    pub index: Option<u64>,
}

/// The oracle's answer for one ray.
#[derive(Clone, Debug, PartialEq)]
pub struct Expectation {
    /// Whether a hit, a miss or either is required.
    pub verdict: Verdict,
    /// The level every hit must report.
    pub level: u8,
    /// The cells a hit may report (empty for [`Verdict::Miss`]), sorted by
    /// `t_lo` then Morton code.
    pub cells: Vec<AcceptableCell>,
}

impl Expectation {
    /// The expectation of a ray that must miss.
    pub fn miss(level: u8) -> Self {
        Expectation {
            verdict: Verdict::Miss,
            level,
            cells: Vec::new(),
        }
    }
}

/// The occupied cells of one level, in Morton order.
#[derive(Clone, Debug)]
pub struct LevelCells {
    /// The level.
    pub level: u8,
    /// Morton codes of the occupied cells (3 bits per level), increasing.
    pub codes: Vec<u64>,
    /// Coordinates of each cell.
    pub coords: Vec<[u32; 3]>,
    /// Dense index of the first voxel (in Morton order) of each cell.
    pub first_index: Vec<u64>,
}

/// Occupancy of the cells of one level, as the tolerance rules need it: the
/// brute-force oracle answers from its decoded list, the judge
/// ([`crate::judge`]) from point queries into the DAG.
pub(crate) trait Occupancy {
    /// The level whose cells are queried.
    fn level(&self) -> u8;
    /// Whether the cell at signed coordinates `cell` is occupied (outside the
    /// volume nothing is).
    fn occupied(&self, cell: [i64; 3]) -> bool;
}

impl Occupancy for LevelCells {
    fn level(&self) -> u8 {
        self.level
    }

    fn occupied(&self, cell: [i64; 3]) -> bool {
        let n = 1i64 << self.level;
        if cell.iter().any(|&c| c < 0 || c >= n) {
            return false;
        }
        self.find(cell.map(|c| c as u32)).is_some()
    }
}

impl LevelCells {
    /// Position of the cell with these coordinates, if occupied.
    pub fn find(&self, cell: [u32; 3]) -> Option<usize> {
        self.codes
            .binary_search(&morton::encode(cell[0], cell[1], cell[2]))
            .ok()
    }

    /// Builds the list from voxel coordinates given in Morton order (used to
    /// cross-check [`Oracle::cells`] against [`Dag::voxels`]).
    pub fn from_morton_voxels(depth: u8, level: u8, voxels: &[[u32; 3]]) -> Self {
        let shift = 3 * u32::from(depth - level);
        let mut cells = LevelCells {
            level,
            codes: Vec::new(),
            coords: Vec::new(),
            first_index: Vec::new(),
        };
        for (index, v) in voxels.iter().enumerate() {
            let code = morton::encode(v[0], v[1], v[2]) >> shift;
            if cells.codes.last() != Some(&code) {
                cells.codes.push(code);
                cells.coords.push(morton::decode(code));
                cells.first_index.push(index as u64);
            }
        }
        cells
    }
}

/// The oracle for one file.
#[derive(Debug)]
pub struct Oracle {
    depth: u8,
    attribute_kind: AttributeKind,
    root_min: [f64; 3],
    root_size: f64,
    /// Occupied cells per level (index = level), decoded on first use.
    levels: Vec<Option<LevelCells>>,
}

/// Voxel counts of subtrees, memoised per (level, pointer), computed from the
/// leaf masks only.
struct Counter<'d, 'a> {
    dag: &'d Dag<'a>,
    memo: HashMap<(u8, u32), u64>,
}

impl Counter<'_, '_> {
    fn count(&mut self, level: u8, pointer: u32) -> Result<u64, FormatError> {
        if level == self.dag.leaf_level() {
            return Ok(u64::from(self.dag.leaf(pointer)?.count()));
        }
        if let Some(&n) = self.memo.get(&(level, pointer)) {
            return Ok(n);
        }
        let node = self.dag.node(level, pointer)?;
        let mut total = 0u64;
        for rank in 0..node.child_count() {
            total += self.count(level + 1, node.pointer_at(rank))?;
        }
        self.memo.insert((level, pointer), total);
        Ok(total)
    }

    /// Emits the occupied cells of `target` level below the node at
    /// (`level`, `pointer`) whose Morton prefix is `prefix` and whose first
    /// voxel has dense index `base`.
    fn walk(
        &mut self,
        target: u8,
        level: u8,
        pointer: u32,
        prefix: u64,
        base: u64,
        out: &mut LevelCells,
    ) -> Result<(), FormatError> {
        let leaf_level = self.dag.leaf_level();
        if level == target {
            out.codes.push(prefix);
            out.first_index.push(base);
            return Ok(());
        }
        if level == leaf_level {
            let mask = self.dag.leaf(pointer)?.0;
            if target == leaf_level + 1 {
                for sub in 0..8u32 {
                    if (mask >> (8 * sub)) & 0xff != 0 {
                        out.codes.push(prefix << 3 | u64::from(sub));
                        out.first_index.push(
                            base + u64::from((mask & ((1u64 << (8 * sub)) - 1)).count_ones()),
                        );
                    }
                }
            } else {
                let mut bits = mask;
                while bits != 0 {
                    let bit = bits.trailing_zeros();
                    bits &= bits - 1;
                    out.codes.push(prefix << 6 | u64::from(bit));
                    out.first_index
                        .push(base + u64::from((mask & ((1u64 << bit) - 1)).count_ones()));
                }
            }
            return Ok(());
        }
        let node = self.dag.node(level, pointer)?;
        let mut base = base;
        for child in 0..8u32 {
            if let Some(p) = node.child_pointer(child) {
                self.walk(
                    target,
                    level + 1,
                    p,
                    prefix << 3 | u64::from(child),
                    base,
                    out,
                )?;
                base += self.count(level + 1, p)?;
            }
        }
        Ok(())
    }
}

/// Slab interval of one axis of the box `[lo, hi]` for a ray coordinate
/// `o + t d`: `None` when the ray misses the slab.
#[inline]
pub(crate) fn slab(o: f64, d: f64, lo: f64, hi: f64) -> Option<(f64, f64)> {
    if d == 0.0 {
        return (lo <= o && o <= hi).then_some((f64::NEG_INFINITY, f64::INFINITY));
    }
    let a = (lo - o) / d;
    let b = (hi - o) / d;
    Some(if a <= b { (a, b) } else { (b, a) })
}

/// A ray in grid space, with its tolerances.
#[derive(Clone, Copy, Debug)]
pub(crate) struct GridRay {
    pub(crate) o: [f64; 3],
    /// Direction; all zero when the ray is a point query (spec/VDAG.md § 20.1:
    /// every component below 2^-1022 in magnitude).
    pub(crate) d: [f64; 3],
    pub(crate) tmin: f64,
    pub(crate) tmax: f64,
    /// Inflated position tolerance (grid units).
    pub(crate) eps: f64,
    /// Inflated `t` tolerance.
    pub(crate) eps_t: f64,
}

/// The frame of a file that rays are mapped into.
#[derive(Clone, Copy, Debug)]
pub(crate) struct GridFrame {
    pub(crate) depth: u8,
    pub(crate) root_min: [f64; 3],
    pub(crate) root_size: f64,
}

impl GridFrame {
    /// The grid-space form of `ray` with its (inflated) tolerances, or `None`
    /// for the invalid rays of spec/VDAG.md § 20.4, which must miss: a NaN, an
    /// infinite origin or direction component, or `tmin > tmax`.
    pub(crate) fn grid_ray(&self, ray: &OracleRay) -> Option<GridRay> {
        let bad_parameter = ray.tmin.is_nan() || ray.tmax.is_nan() || ray.tmin > ray.tmax;
        if bad_parameter || !ray.origin.iter().chain(&ray.dir).all(|v| v.is_finite()) {
            return None;
        }
        let scale = (1u64 << self.depth) as f64 / self.root_size;
        let o = [0, 1, 2].map(|i| (f64::from(ray.origin[i]) - self.root_min[i]) * scale);
        let mut d = [0, 1, 2].map(|i| f64::from(ray.dir[i]) * scale);
        // § 20.1: a direction whose grid-space components all lie below the
        // smallest normal binary64 number is zero (a point query).
        if d.iter().all(|v| v.abs() < f64::MIN_POSITIVE) {
            d = [0.0; 3];
        }
        let eps = position_tolerance(self.depth, o) * INFLATE;
        let norm = d.iter().map(|v| v * v).sum::<f64>().sqrt();
        let eps_t = if norm > 0.0 {
            eps / norm * INFLATE
        } else {
            0.0
        };
        Some(GridRay {
            o,
            d,
            tmin: f64::from(ray.tmin),
            tmax: f64::from(ray.tmax),
            eps,
            eps_t,
        })
    }
}

impl GridRay {
    /// Whether the ray is a point query (zero direction).
    pub(crate) fn is_point(&self) -> bool {
        self.d.iter().all(|&v| v == 0.0)
    }

    pub(crate) fn at(&self, t: f64) -> [f64; 3] {
        [0, 1, 2].map(|i| {
            if self.d[i] == 0.0 {
                self.o[i]
            } else {
                self.o[i] + t * self.d[i]
            }
        })
    }
}

/// One occupied cell whose grown box the segment meets.
#[derive(Clone, Copy, Debug)]
struct Candidate {
    index: usize,
    entry: f64,
    exit: f64,
}

impl Oracle {
    /// Reads what the oracle needs from an open file. Cells are decoded level
    /// by level on first use.
    pub fn new(dag: &Dag<'_>) -> Self {
        let header = dag.header();
        Oracle {
            depth: header.depth,
            attribute_kind: header.attribute_kind,
            root_min: header.root_min,
            root_size: header.root_size,
            levels: vec![None; usize::from(header.depth) + 1],
        }
    }

    /// Depth D of the file.
    pub fn depth(&self) -> u8 {
        self.depth
    }

    /// The occupied cells of `level` (1 ..= D), decoded from `dag` (which must
    /// be the file this oracle was made from) by a depth-first walk.
    pub fn cells(&mut self, dag: &Dag<'_>, level: u8) -> Result<&LevelCells, FormatError> {
        assert!(
            (1..=self.depth).contains(&level),
            "level {level} outside 1..={}",
            self.depth
        );
        let slot = usize::from(level);
        if self.levels[slot].is_none() {
            let mut cells = LevelCells {
                level,
                codes: Vec::new(),
                coords: Vec::new(),
                first_index: Vec::new(),
            };
            if !dag.is_empty() {
                let mut counter = Counter {
                    dag,
                    memo: HashMap::new(),
                };
                counter.walk(level, 0, 0, 0, 0, &mut cells)?;
            }
            cells.coords = cells.codes.iter().map(|&c| morton::decode(c)).collect();
            self.levels[slot] = Some(cells);
        }
        Ok(self.levels[slot].as_ref().expect("just filled"))
    }

    /// The expectation for `ray`. `dag` must be the file this oracle was made
    /// from. Fails on a malformed DAG or a level outside `1 ..= D`.
    pub fn expect(&mut self, dag: &Dag<'_>, ray: &OracleRay) -> Result<Expectation, String> {
        let level = ray.level;
        if !(1..=self.depth).contains(&level) {
            return Err(format!("level {level} is outside 1..={}", self.depth));
        }
        let frame = GridFrame {
            depth: self.depth,
            root_min: self.root_min,
            root_size: self.root_size,
        };
        // Invalid rays (spec/VDAG.md § 20.4) must miss.
        let Some(gray) = frame.grid_ray(ray) else {
            return Ok(Expectation::miss(level));
        };
        let attribute_kind = self.attribute_kind;
        let depth = self.depth;
        let cells = self.cells(dag, level).map_err(|e| e.to_string())?;
        Ok(expect_in(cells, depth, attribute_kind, &gray))
    }
}

/// The core of [`Oracle::expect`] for a grid-space ray with finite origin and
/// direction and `tmin <= tmax`.
fn expect_in(cells: &LevelCells, depth: u8, kind: AttributeKind, ray: &GridRay) -> Expectation {
    let level = cells.level;
    let s = (1u64 << (depth - level)) as f64;
    let eps = ray.eps;
    // Every occupied cell whose grown box the segment meets.
    let mut candidates = Vec::new();
    for (index, c) in cells.coords.iter().enumerate() {
        let mut near = f64::NEG_INFINITY;
        let mut far = f64::INFINITY;
        let mut hit = true;
        for (axis, &ca) in c.iter().enumerate() {
            let lo = f64::from(ca) * s - eps;
            let hi = f64::from(ca + 1) * s + eps;
            match slab(ray.o[axis], ray.d[axis], lo, hi) {
                Some((a, b)) => {
                    near = near.max(a);
                    far = far.min(b);
                }
                None => {
                    hit = false;
                    break;
                }
            }
        }
        let entry = ray.tmin.max(near);
        let exit = ray.tmax.min(far);
        if hit && entry <= exit {
            candidates.push(Candidate { index, entry, exit });
        }
    }
    candidates.sort_by(|a, b| {
        a.entry
            .total_cmp(&b.entry)
            .then(cells.codes[a.index].cmp(&cells.codes[b.index]))
    });
    // T-: the first robustly inside point of the segment.
    let zero_dir = ray.is_point();
    let mut first_robust = f64::INFINITY;
    for cand in &candidates {
        if cand.entry > first_robust {
            break;
        }
        let t = if zero_dir {
            robust(cells, ray.o, eps, s).then_some(cand.entry)
        } else {
            first_robust_in(
                cells,
                ray,
                cells.coords[cand.index],
                s,
                cand.entry,
                cand.exit,
            )
        };
        if let Some(t) = t {
            first_robust = first_robust.min(t);
        }
    }
    let eps_t = ray.eps_t;
    let mut accepted = Vec::new();
    for cand in &candidates {
        if cand.entry > first_robust + eps_t {
            continue;
        }
        let cell = cells.coords[cand.index];
        let (t_lo, t_hi) = if zero_dir {
            (ray.tmin, ray.tmin)
        } else {
            (cand.entry - eps_t, cand.exit.min(first_robust) + eps_t)
        };
        accepted.push(AcceptableCell {
            cell,
            t_lo: f32_at_least(t_lo),
            t_hi: f32_at_most(t_hi),
            faces: faces(ray, cell, s),
            index: match kind {
                AttributeKind::VoxelCount => Some(cells.first_index[cand.index]),
                AttributeKind::None => None,
            },
        });
    }
    let verdict = if first_robust < f64::INFINITY {
        Verdict::Hit
    } else if accepted.is_empty() {
        Verdict::Miss
    } else {
        Verdict::Either
    };
    Expectation {
        verdict,
        level,
        cells: accepted,
    }
}

/// The smallest f32 that is not below `v`; `-inf` when `v` lies below the
/// finite f32 range (spec/VDAG.md § 20.8: a bound beyond the f32 range is
/// reached by the f32 overflow, as IEEE rounding of such a `t` gives).
pub(crate) fn f32_at_least(v: f64) -> f32 {
    if v < -f64::from(f32::MAX) {
        return f32::NEG_INFINITY;
    }
    let f = v as f32;
    if f64::from(f) < v { f.next_up() } else { f }
}

/// The largest f32 that is not above `v`; `+inf` when `v` lies above the
/// finite f32 range (see [`f32_at_least`]).
pub(crate) fn f32_at_most(v: f64) -> f32 {
    if v > f64::from(f32::MAX) {
        return f32::INFINITY;
    }
    let f = v as f32;
    if f64::from(f) > v { f.next_down() } else { f }
}

/// Whether the point `p` is robustly inside the occupied cells: every cell
/// whose open interior meets the open cube `(p - eps, p + eps)^3` is occupied
/// (equivalently, the closed cube lies in the union of the occupied closed
/// cells).
pub(crate) fn robust<O: Occupancy + ?Sized>(cells: &O, p: [f64; 3], eps: f64, s: f64) -> bool {
    let n = (1i64 << cells.level()) as f64;
    // A cube wider than the volume (an origin so far away that eps_g spans
    // it) is never inside it.
    if 2.0 * eps > n * s {
        return false;
    }
    let mut lo = [0i64; 3];
    let mut hi = [0i64; 3];
    for axis in 0..3 {
        let a = ((p[axis] - eps) / s).floor();
        let b = ((p[axis] + eps) / s).ceil() - 1.0;
        if !(a >= 0.0 && b < n) {
            return false;
        }
        lo[axis] = a as i64;
        hi[axis] = b as i64;
    }
    for z in lo[2]..=hi[2] {
        for y in lo[1]..=hi[1] {
            for x in lo[0]..=hi[0] {
                if !cells.occupied([x, y, z]) {
                    return false;
                }
            }
        }
    }
    true
}

/// The first `t` in `[entry, exit]` (the segment inside the grown `cell`) whose
/// point is robustly inside, if any.
///
/// Robustness can only change where a coordinate crosses a plane `k s +- eps`;
/// between two such crossings it is constant, so testing each crossing and the
/// midpoint of each gap between crossings is exact (the set of robust points
/// is closed, so a robust gap makes its start robust too).
pub(crate) fn first_robust_in<O: Occupancy + ?Sized>(
    cells: &O,
    ray: &GridRay,
    cell: [u32; 3],
    s: f64,
    entry: f64,
    exit: f64,
) -> Option<f64> {
    let eps = ray.eps;
    let n = 1i64 << cells.level();
    if 2.0 * eps > n as f64 * s {
        // No cube of half size eps fits in the volume (see `robust`).
        return None;
    }
    // Only planes k s +- eps with 0 <= k <= n can change robustness: beyond
    // them the cube reaches out of the volume on both sides. (Clamping also
    // bounds the loop for far origins, whose eps spans many cells.)
    let reach = (2.0 * eps / s).ceil() as i64 + 1;
    let mut stops = vec![entry];
    for (axis, &ca) in cell.iter().enumerate() {
        if ray.d[axis] == 0.0 {
            continue;
        }
        let c = i64::from(ca);
        for k in (c - reach).max(0)..=(c + 1 + reach).min(n) {
            for plane in [k as f64 * s - eps, k as f64 * s + eps] {
                let t = (plane - ray.o[axis]) / ray.d[axis];
                if entry < t && t < exit {
                    stops.push(t);
                }
            }
        }
    }
    stops.push(exit);
    stops.sort_by(f64::total_cmp);
    stops.dedup();
    if robust(cells, ray.at(stops[0]), eps, s) {
        return Some(stops[0]);
    }
    for pair in stops.windows(2) {
        let mid = 0.5 * (pair[0] + pair[1]);
        if robust(cells, ray.at(mid), eps, s) {
            return Some(pair[0]);
        }
        if robust(cells, ray.at(pair[1]), eps, s) {
            return Some(pair[1]);
        }
    }
    None
}

/// The faces a tracer may report for a hit on `cell` (bit per face).
///
/// Face 0 ("starts inside") is accepted when the start of the segment lies in
/// the grown cell. The face of axis `a` (the one a ray moving along `d_a`
/// enters) is accepted when that axis can be the last slab entered within the
/// tolerance: its slab start for the shrunk cell is not before the latest slab
/// start for the grown cell, nor before `tmin`.
pub(crate) fn faces(ray: &GridRay, cell: [u32; 3], s: f64) -> u8 {
    let eps = ray.eps;
    let start = |axis: usize, grow: f64| -> f64 {
        let d = ray.d[axis];
        if d == 0.0 {
            f64::NEG_INFINITY
        } else if d > 0.0 {
            (f64::from(cell[axis]) * s - grow - ray.o[axis]) / d
        } else {
            (f64::from(cell[axis] + 1) * s + grow - ray.o[axis]) / d
        }
    };
    let latest_grown = (0..3)
        .map(|a| start(a, eps))
        .fold(f64::NEG_INFINITY, f64::max);
    let mut faces = 0u8;
    if latest_grown <= ray.tmin {
        faces |= 1;
    }
    for axis in 0..3 {
        let d = ray.d[axis];
        if d == 0.0 {
            continue;
        }
        let shrunk = start(axis, -eps);
        if shrunk >= latest_grown && shrunk >= ray.tmin {
            let face = 1 + 2 * axis as u32 + u32::from(d < 0.0);
            faces |= 1 << face;
        }
    }
    faces
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cells_of(level: u8, coords: &[[u32; 3]]) -> LevelCells {
        let mut v: Vec<[u32; 3]> = coords.to_vec();
        v.sort_by_key(|c| morton::encode(c[0], c[1], c[2]));
        LevelCells::from_morton_voxels(level, level, &v)
    }

    fn ray(o: [f64; 3], d: [f64; 3], depth: u8) -> GridRay {
        let eps = position_tolerance(depth, o) * INFLATE;
        let norm = d.iter().map(|v| v * v).sum::<f64>().sqrt();
        GridRay {
            o,
            d,
            tmin: 0.0,
            tmax: f64::INFINITY,
            eps,
            eps_t: eps / norm * INFLATE,
        }
    }

    #[test]
    fn ray_along_an_inner_face_of_a_solid_block_must_hit() {
        let mut all = Vec::new();
        for z in 0..4 {
            for y in 0..4 {
                for x in 0..4 {
                    all.push([x, y, z]);
                }
            }
        }
        let cells = cells_of(2, &all);
        let e = expect_in(
            &cells,
            2,
            AttributeKind::None,
            &ray([-1.0, 2.0, 2.0], [1.0, 0.0, 0.0], 2),
        );
        assert_eq!(e.verdict, Verdict::Hit);
        // The four cells around the line x = 0..1, y = 2, z = 2.
        let hit: Vec<_> = e.cells.iter().map(|c| c.cell).collect();
        assert_eq!(hit, vec![[0, 1, 1], [0, 2, 1], [0, 1, 2], [0, 2, 2]]);
        assert!(
            e.cells
                .iter()
                .all(|c| c.faces == 1 << 1 && c.t_lo < 1.0 && c.t_hi > 1.0 && c.t_hi < 1.01)
        );
    }

    #[test]
    fn ray_along_an_outer_face_grazes() {
        let cells = cells_of(2, &[[1, 1, 1]]);
        let e = expect_in(
            &cells,
            2,
            AttributeKind::None,
            &ray([-1.0, 2.0, 1.5], [1.0, 0.0, 0.0], 2),
        );
        assert_eq!(e.verdict, Verdict::Either);
        let e = expect_in(
            &cells,
            2,
            AttributeKind::None,
            &ray([-1.0, 2.01, 1.5], [1.0, 0.0, 0.0], 2),
        );
        assert_eq!(e.verdict, Verdict::Miss);
        let e = expect_in(
            &cells,
            2,
            AttributeKind::None,
            &ray([-1.0, 1.99, 1.5], [1.0, 0.0, 0.0], 2),
        );
        assert_eq!(e.verdict, Verdict::Hit);
    }

    #[test]
    fn diagonal_through_a_corner_accepts_tied_faces() {
        let cells = cells_of(2, &[[1, 1, 1]]);
        let e = expect_in(
            &cells,
            2,
            AttributeKind::None,
            &ray([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], 2),
        );
        assert_eq!(e.verdict, Verdict::Hit);
        assert_eq!(e.cells.len(), 1);
        assert_eq!(e.cells[0].faces, 0b0010_1010);
    }

    /// The closed cells containing `p` (several on shared faces).
    fn cells_at(cells: &LevelCells, p: [f64; 3]) -> Vec<usize> {
        let options = p.map(|v| {
            let f = v.floor();
            if f == v {
                vec![f as i64, f as i64 - 1]
            } else {
                vec![f as i64]
            }
        });
        let mut found = Vec::new();
        for &x in &options[0] {
            for &y in &options[1] {
                for &z in &options[2] {
                    let n = 1i64 << cells.level;
                    if [x, y, z].iter().all(|&c| (0..n).contains(&c))
                        && let Some(i) = cells.find([x as u32, y as u32, z as u32])
                    {
                        found.push(i);
                    }
                }
            }
        }
        found
    }

    /// The exact entry faces (eps = 0) of the ray into `cell`.
    fn exact_faces(ray: &GridRay, cell: [u32; 3]) -> u8 {
        let exact = GridRay { eps: 0.0, ..*ray };
        faces(&exact, cell, 1.0)
    }

    /// Checks the oracle against a method that shares nothing with it: dense
    /// sampling of the segment (step well under the tolerance).
    #[test]
    fn agrees_with_dense_sampling() {
        let mut rng = crate::rng::Rng::new(99);
        let mut verdicts = [0usize; 3];
        for _ in 0..60 {
            let density = rng.range(0.05, 0.6);
            let mut coords = Vec::new();
            for z in 0..8 {
                for y in 0..8 {
                    for x in 0..8 {
                        if rng.chance(density) {
                            coords.push([x, y, z]);
                        }
                    }
                }
            }
            let cells = cells_of(3, &coords);
            for _ in 0..25 {
                let snapped = rng.chance(0.5);
                let (o, d) = if snapped {
                    let o = [0; 3].map(|_| (rng.below(22) as f64 - 3.0) / 2.0);
                    let d = [0; 3].map(|_| rng.below(5) as f64 - 2.0);
                    if d == [0.0; 3] {
                        continue;
                    }
                    (o, d)
                } else {
                    ([0; 3].map(|_| rng.range(-3.0, 11.0)), rng.direction())
                };
                let eps = 0.05;
                let norm = d.iter().map(|v| v * v).sum::<f64>().sqrt();
                let tmin = if rng.chance(0.3) {
                    rng.range(-2.0, 4.0)
                } else {
                    0.0
                };
                let tmax = if rng.chance(0.3) {
                    tmin + rng.range(0.0, 8.0)
                } else {
                    40.0
                };
                let ray = GridRay {
                    o,
                    d,
                    tmin,
                    tmax,
                    eps,
                    eps_t: eps / norm,
                };
                let e = expect_in(&cells, 3, AttributeKind::VoxelCount, &ray);
                verdicts[e.verdict as usize] += 1;
                let step = ray.eps_t / 8.0;
                let mut first_inside = None;
                let mut t = tmin;
                while t <= tmax {
                    let p = ray.at(t);
                    if robust(&cells, p, eps * 1.02, 1.0) {
                        assert_eq!(
                            e.verdict,
                            Verdict::Hit,
                            "deep point at t {t} but {e:?} for {ray:?}"
                        );
                    }
                    if first_inside.is_none() && !cells_at(&cells, p).is_empty() {
                        first_inside = Some((t, cells_at(&cells, p)));
                    }
                    t += step;
                }
                match first_inside {
                    None => continue,
                    Some((t, inside)) => {
                        assert_ne!(
                            e.verdict,
                            Verdict::Miss,
                            "inside at t {t} but a miss is required: {ray:?}"
                        );
                        for i in inside {
                            let cell = cells.coords[i];
                            let c = e.cells.iter().find(|c| c.cell == cell).unwrap_or_else(|| {
                                panic!(
                                    "first cell {cell:?} at t {t} not acceptable: {e:?} for {ray:?}"
                                )
                            });
                            assert!(
                                c.t_lo as f64 <= t && t <= c.t_hi as f64,
                                "t {t} outside {c:?} for {ray:?}"
                            );
                            let exact = exact_faces(&ray, cell);
                            assert!(
                                exact & c.faces == exact,
                                "exact faces {exact:#b} not all in {c:?} for {ray:?}"
                            );
                        }
                    }
                }
            }
        }
        assert!(
            verdicts.iter().all(|&n| n > 50),
            "verdicts miss/hit/either: {verdicts:?}"
        );
    }

    #[test]
    fn start_inside_reports_face_zero() {
        let cells = cells_of(2, &[[1, 1, 1]]);
        let e = expect_in(
            &cells,
            2,
            AttributeKind::None,
            &ray([1.5, 1.5, 1.5], [1.0, 0.25, 0.0], 2),
        );
        assert_eq!(e.verdict, Verdict::Hit);
        assert_eq!(e.cells[0].faces, 1);
        assert!(e.cells[0].t_lo <= 0.0 && e.cells[0].t_hi >= 0.0 && e.cells[0].t_hi < 0.01);
    }
}
