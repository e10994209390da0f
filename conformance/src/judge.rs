//! Judging any tracer's answers on any file, ray by ray, by the acceptance
//! rule of spec/VDAG.md § 20.8.
//!
//! The committed cases carry precomputed expectations ([`crate::expect`]); a
//! judge needs none. It evaluates the rule directly for each ray and answer,
//! so it works for any file and any rays, and it scales to millions of rays
//! on deep files: instead of the oracle's loop over every occupied cell it
//! finds the cells near the ray by a best-first descent of the DAG (a node is
//! visited only when the segment meets its cube grown by `eps_g`, in order of
//! entry, and the descent stops at the first robustly inside point), and it
//! tests occupancy by point queries into the DAG.
//!
//! The geometry (grid-space rays and tolerances, the slab test, robust
//! insideness, `T⁻` within one cell, the face sets) is the oracle's own code
//! ([`crate::oracle`]), so the judge and the committed expectations accept
//! exactly the same answers; `tests/judge.rs` checks that they agree. Like the
//! oracle it shares no code with any tracer: the descent here is a plain
//! priority-queue walk over `dagfmt`'s reader.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let bytes = std::fs::read("scene.vdag")?;
//! let dag = dagfmt::Dag::open(&bytes)?;
//! let judge = conformance::judge::Judge::new(&dag)?;
//! let rays = dagfmt::batch::parse_rays(&std::fs::read("scene.rays")?)?;
//! let hits = dagfmt::batch::parse_hits(&std::fs::read("scene.hits")?)?;
//! for (i, rejection) in judge.judge_batch(&rays, &hits).iter().enumerate() {
//!     if let Some(r) = rejection {
//!         println!("ray {i}: {r}");
//!     }
//! }
//! # Ok(())
//! # }
//! ```

use std::cell::RefCell;
use std::cmp::Ordering;
use std::collections::BinaryHeap;
use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering as AtomicOrdering};

use dagfmt::batch::{Hit, Ray, format_f32};
use dagfmt::{AttributeKind, Dag};

use crate::oracle::{
    GridFrame, GridRay, Occupancy, OracleRay, f32_at_least, f32_at_most, faces, first_robust_in,
    robust, slab,
};

/// Why the judge cannot judge a file or a batch at all.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct JudgeError(pub String);

impl fmt::Display for JudgeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for JudgeError {}

/// Which condition of spec/VDAG.md § 20.8 an answer breaks.
#[derive(Clone, Debug, PartialEq)]
pub enum Reason {
    /// The ray asks for a level deeper than the file: no answer is defined;
    /// the whole batch must be rejected (§ 20.2).
    LevelTooDeep {
        /// The ray's level.
        level: u8,
        /// The file's depth.
        depth: u8,
    },
    /// The ray is invalid (§ 20.4: a NaN, an infinite origin or direction
    /// component, or `tmin > tmax`) and accepts only a miss.
    InvalidRayMustMiss,
    /// A miss, but the ray reaches a robustly inside point (`T⁻ < +∞`).
    MissNotAccepted,
    /// Condition 1: the answer's level is not the ray's.
    WrongLevel {
        /// The level reported.
        reported: u8,
    },
    /// Condition 1: the cell lies outside the level's `2^L` cells per axis.
    CellOutsideVolume,
    /// Condition 1: the cell is not occupied.
    EmptyCell,
    /// Condition 2: the ray does not meet the cell grown by `eps_g`.
    MissesGrownCell,
    /// Condition 3: the cell is entered after `T⁻ + eps_t`.
    NotFirst {
        /// The entry `e_C` into the grown cell.
        entry: f64,
    },
    /// Condition 4: `t` is outside the accepted range.
    TOutOfRange,
    /// Condition 5: the face is not in A(C).
    Face {
        /// The accepted faces, bit `f` for face `f`.
        accepted: u8,
    },
    /// Condition 6: the attribute index is not the cell's.
    Index {
        /// The cell's index (`None` for attribute kind 0).
        expected: Option<u64>,
    },
}

/// A rejected answer: why, with the ray's `T⁻` and the accepted `t` range of
/// the cell answered where the rule defines one.
#[derive(Clone, Debug, PartialEq)]
pub struct Rejection {
    /// The condition broken.
    pub reason: Reason,
    /// The answer judged.
    pub answer: Hit,
    /// The level the ray traces.
    pub level: u8,
    /// `T⁻`, the first robustly inside point of the ray (`+∞` if none; `NaN`
    /// where undefined: an invalid ray or a level deeper than the file).
    pub t_minus: f64,
    /// The accepted range of `t` for the cell answered, as `f32` bounds
    /// (inclusive), where conditions 1 and 2 hold.
    pub t_range: Option<(f32, f32)>,
}

fn show_index(i: Option<u64>) -> String {
    i.map_or_else(|| "-".into(), |i| i.to_string())
}

fn show_faces(faces: u8) -> String {
    let list: Vec<String> = (0..7)
        .filter(|f| faces & (1 << f) != 0)
        .map(|f: u8| f.to_string())
        .collect();
    format!("{{{}}}", list.join(", "))
}

fn show_t(t: f64) -> String {
    if t.is_nan() {
        "undefined".into()
    } else {
        // The exact f64 value is noise for a reader; its f32 is what tracers
        // report and compare with.
        format_f32(t as f32)
    }
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let a = &self.answer;
        let cell = format!("cell ({}, {}, {})", a.voxel[0], a.voxel[1], a.voxel[2]);
        match &self.reason {
            Reason::LevelTooDeep { level, depth } => write!(
                f,
                "the ray's level {level} is deeper than the file's depth {depth}: the batch must be rejected"
            )?,
            Reason::InvalidRayMustMiss => f.write_str(
                "an invalid ray (NaN, infinite origin or direction component, or tmin > tmax) accepts only a miss",
            )?,
            Reason::MissNotAccepted => f.write_str(
                "a miss is not accepted: the ray reaches a robustly inside point",
            )?,
            Reason::WrongLevel { reported } => write!(
                f,
                "condition 1: level {reported} reported, the ray traces level {}",
                self.level
            )?,
            Reason::CellOutsideVolume => write!(
                f,
                "condition 1: {cell} lies outside level {} (coordinates below {})",
                self.level,
                1u64 << self.level
            )?,
            Reason::EmptyCell => write!(f, "condition 1: {cell} of level {} is empty", self.level)?,
            Reason::MissesGrownCell => write!(
                f,
                "condition 2: the ray does not meet {cell} grown by eps_g"
            )?,
            Reason::NotFirst { entry } => write!(
                f,
                "condition 3: {cell} is entered at e_C = {}, later than T⁻ + eps_t",
                show_t(*entry)
            )?,
            Reason::TOutOfRange => write!(f, "condition 4: t {} is outside the accepted range", format_f32(a.t))?,
            Reason::Face { accepted } => write!(
                f,
                "condition 5: face {} is not in the accepted set {}",
                a.face,
                show_faces(*accepted)
            )?,
            Reason::Index { expected } => write!(
                f,
                "condition 6: index {} reported, the cell's index is {}",
                show_index(a.index),
                show_index(*expected)
            )?,
        }
        if !self.t_minus.is_nan() {
            write!(f, "; T⁻ = {}", show_t(self.t_minus))?;
        }
        if let Some((lo, hi)) = self.t_range {
            write!(
                f,
                ", accepted t for {cell}: [{}, {}]",
                format_f32(lo),
                format_f32(hi)
            )?;
        }
        Ok(())
    }
}

/// What a node of the descent is.
#[derive(Clone, Copy, Debug)]
enum Handle {
    /// An interior node: its word offset in its level.
    Node(u32),
    /// A 4³ brick (level D − 2): its mask.
    Brick(u64),
    /// A 2³ sub-brick (level D − 1): its voxel mask.
    SubBrick(u8),
    /// A voxel (level D).
    Voxel,
}

/// A node waiting in the descent, ordered by its entry parameter.
#[derive(Clone, Copy, Debug)]
struct Pending {
    entry: f64,
    exit: f64,
    level: u8,
    cell: [u32; 3],
    handle: Handle,
}

impl PartialEq for Pending {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}

impl Eq for Pending {}

impl PartialOrd for Pending {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Pending {
    /// Reversed, so that [`BinaryHeap`] pops the smallest entry first.
    fn cmp(&self, other: &Self) -> Ordering {
        other.entry.total_cmp(&self.entry)
    }
}

/// Marks a subtree voxel count not yet computed.
const UNKNOWN: u64 = u64::MAX;

/// The judge of one file: evaluates spec/VDAG.md § 20.8 for any ray and
/// answer. Shareable between threads ([`Judge::judge_batch`] uses them all).
#[derive(Debug)]
pub struct Judge<'a> {
    dag: Dag<'a>,
    frame: GridFrame,
    kind: AttributeKind,
    leaf_level: u8,
    /// Voxel counts of the subtrees of interior nodes, per level, indexed by
    /// word offset, filled on first use ([`UNKNOWN`] until then). Computed
    /// from the leaf masks: stored attribute counts saturate.
    counts: Vec<Vec<AtomicU64>>,
}

/// The judge's occupancy queries at one level: point queries into the DAG,
/// the last few answers remembered (the robustness tests of one cell ask for
/// the same few neighbours again and again).
struct DagCells<'j, 'a> {
    judge: &'j Judge<'a>,
    level: u8,
    recent: RefCell<Vec<([i64; 3], bool)>>,
}

/// Occupancy answers [`DagCells`] remembers.
const RECENT: usize = 27;

impl<'j, 'a> DagCells<'j, 'a> {
    fn new(judge: &'j Judge<'a>, level: u8) -> Self {
        DagCells {
            judge,
            level,
            recent: RefCell::new(Vec::with_capacity(RECENT)),
        }
    }
}

impl Occupancy for DagCells<'_, '_> {
    fn level(&self) -> u8 {
        self.level
    }

    fn occupied(&self, cell: [i64; 3]) -> bool {
        let n = 1i64 << self.level;
        if cell.iter().any(|&c| c < 0 || c >= n) {
            return false;
        }
        let mut recent = self.recent.borrow_mut();
        if let Some(&(_, occupied)) = recent.iter().find(|(c, _)| *c == cell) {
            return occupied;
        }
        let occupied = self
            .judge
            .lookup(self.level, cell.map(|c| c as u32), false)
            .is_some();
        if recent.len() == RECENT {
            recent.remove(0);
        }
        recent.push((cell, occupied));
        occupied
    }
}

/// The child index (§ 8.1) taken at level `l` on the path to `cell` of level `level`.
fn child_on_path(cell: [u32; 3], level: u8, l: u8) -> u32 {
    let shift = u32::from(level - 1 - l);
    ((cell[0] >> shift) & 1) | (((cell[1] >> shift) & 1) << 1) | (((cell[2] >> shift) & 1) << 2)
}

impl<'a> Judge<'a> {
    /// A judge for `dag`, which must be valid: the file is validated in full
    /// first (answers are only specified for valid files, § 20.7).
    pub fn new(dag: &Dag<'a>) -> Result<Self, JudgeError> {
        if let Some(first) = dagfmt::validate::validate(dag.bytes()).first() {
            return Err(JudgeError(format!(
                "the file is not valid, answers on it are unspecified: {first}"
            )));
        }
        let header = dag.header();
        let counts = dag
            .levels()
            .iter()
            .map(|section| {
                if section.is_leaf {
                    Vec::new()
                } else {
                    (0..section.units())
                        .map(|_| AtomicU64::new(UNKNOWN))
                        .collect()
                }
            })
            .collect();
        Ok(Judge {
            dag: dag.clone(),
            frame: GridFrame {
                depth: header.depth,
                root_min: header.root_min,
                root_size: header.root_size,
            },
            kind: header.attribute_kind,
            leaf_level: dag.leaf_level(),
            counts,
        })
    }

    /// Depth D of the file.
    pub fn depth(&self) -> u8 {
        self.frame.depth
    }

    /// Checks that every ray's level exists in the file (§ 20.2: a batch with a
    /// deeper level is rejected as a whole).
    pub fn check_levels(&self, rays: &[Ray]) -> Result<(), JudgeError> {
        match rays
            .iter()
            .enumerate()
            .find(|(_, r)| r.level.is_some_and(|l| l > self.depth()))
        {
            Some((i, r)) => Err(JudgeError(format!(
                "ray {i}: level {} is deeper than the file's depth {}",
                r.level.unwrap_or(0),
                self.depth()
            ))),
            None => Ok(()),
        }
    }

    /// Judges every answer, on all cores; `answers[i]` answers `rays[i]`.
    /// Returns one entry per ray: `None` when accepted.
    ///
    /// # Panics
    ///
    /// When `rays` and `answers` differ in length.
    pub fn judge_batch(&self, rays: &[Ray], answers: &[Hit]) -> Vec<Option<Rejection>> {
        assert_eq!(rays.len(), answers.len(), "one answer per ray");
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        // Small chunks keep the threads busy to the end: rays differ widely in cost.
        let chunk = rays.len().div_ceil(threads * 16).max(256);
        let mut out: Vec<Option<Rejection>> = vec![None; rays.len()];
        let jobs: Vec<_> = out
            .chunks_mut(chunk)
            .zip(rays.chunks(chunk).zip(answers.chunks(chunk)))
            .collect();
        let queue = std::sync::Mutex::new(jobs);
        std::thread::scope(|scope| {
            for _ in 0..threads {
                scope.spawn(|| {
                    loop {
                        let job = queue.lock().expect("no panics while holding it").pop();
                        let Some((slots, (rays, answers))) = job else {
                            break;
                        };
                        for ((slot, ray), answer) in slots.iter_mut().zip(rays).zip(answers) {
                            *slot = self.judge(ray, answer).err();
                        }
                    }
                });
            }
        });
        out
    }

    /// Judges one answer: `Ok` when § 20.8 accepts it.
    pub fn judge(&self, ray: &Ray, answer: &Hit) -> Result<(), Rejection> {
        let depth = self.depth();
        let level = ray.level.unwrap_or(depth);
        let reject = |reason, t_minus, t_range| {
            Err(Rejection {
                reason,
                answer: *answer,
                level,
                t_minus,
                t_range,
            })
        };
        if level > depth || level == 0 {
            return reject(Reason::LevelTooDeep { level, depth }, f64::NAN, None);
        }
        let oracle_ray = OracleRay {
            origin: ray.origin,
            dir: ray.dir,
            tmin: ray.tmin,
            tmax: ray.tmax,
            level,
        };
        let Some(gray) = self.frame.grid_ray(&oracle_ray) else {
            return if answer.hit {
                reject(Reason::InvalidRayMustMiss, f64::NAN, None)
            } else {
                Ok(())
            };
        };
        if !answer.hit {
            let t_minus = self.t_minus(&gray, level, f64::INFINITY);
            return if t_minus == f64::INFINITY {
                Ok(())
            } else {
                reject(Reason::MissNotAccepted, t_minus, None)
            };
        }
        let full = |judge: &Self| judge.t_minus(&gray, level, f64::INFINITY);
        // Condition 1.
        if answer.level != level {
            return reject(
                Reason::WrongLevel {
                    reported: answer.level,
                },
                full(self),
                None,
            );
        }
        let cell = answer.voxel;
        if cell.iter().any(|&c| u64::from(c) >= 1u64 << level) {
            return reject(Reason::CellOutsideVolume, full(self), None);
        }
        let Some(index) = self.lookup(level, cell, true) else {
            return reject(Reason::EmptyCell, full(self), None);
        };
        // Condition 2.
        let s = (1u64 << (depth - level)) as f64;
        let Some((entry, exit)) = grown_entry(&gray, cell, s) else {
            return reject(Reason::MissesGrownCell, full(self), None);
        };
        // Conditions 3 and 4 accept whenever T⁻ >= max(e_C, t), so the
        // descent may stop there: below that bound `bounded` is T⁻ itself,
        // at or above it both conditions hold with it as with T⁻.
        let t = f64::from(answer.t);
        let needed = if t.is_nan() { entry } else { entry.max(t) };
        let bounded = self.t_minus(&gray, level, needed);
        let range = |t_minus: f64| {
            if gray.is_point() {
                (f32_at_least(gray.tmin), f32_at_most(gray.tmin))
            } else {
                (
                    f32_at_least(entry - gray.eps_t),
                    f32_at_most(exit.min(t_minus) + gray.eps_t),
                )
            }
        };
        if entry > bounded + gray.eps_t {
            // No t is accepted for a cell that is not (nearly) first.
            return reject(Reason::NotFirst { entry }, bounded, None);
        }
        let (lo, hi) = range(bounded);
        if !(lo <= answer.t && answer.t <= hi) {
            // For the report: `bounded` may stand above T⁻.
            let t_minus = full(self);
            return reject(Reason::TOutOfRange, t_minus, Some(range(t_minus)));
        }
        // Condition 5.
        let accepted = faces(&gray, cell, s);
        if answer.face > 6 || accepted & (1 << answer.face) == 0 {
            let t_minus = full(self);
            return reject(Reason::Face { accepted }, t_minus, Some(range(t_minus)));
        }
        // Condition 6.
        let expected = match self.kind {
            AttributeKind::VoxelCount => Some(index),
            AttributeKind::None => None,
        };
        if answer.index != expected {
            let t_minus = full(self);
            return reject(Reason::Index { expected }, t_minus, Some(range(t_minus)));
        }
        Ok(())
    }

    /// `T⁻` of the ray at `level`: the first `t` of the segment at a robustly
    /// inside point, or `+∞`. The search stops once it is known that
    /// `T⁻ >= bound`; the result is then some value `>= bound` (`+∞` when the
    /// ray has no robust point before the bound).
    ///
    /// Best-first: nodes whose grown cube the segment meets are visited in
    /// order of entry; an occupied cell of the level is searched for its
    /// first robust point ([`first_robust_in`], the oracle's). A cell's grown
    /// box lies in its parent's, so a parent is never entered later than its
    /// children, and no cell entered after the best point found can hold an
    /// earlier one.
    fn t_minus(&self, ray: &GridRay, level: u8, bound: f64) -> f64 {
        let cells = DagCells::new(self, level);
        let depth = self.depth();
        if self.dag.is_empty() {
            return f64::INFINITY;
        }
        if ray.is_point() {
            let s = (1u64 << (depth - level)) as f64;
            return if robust(&cells, ray.o, ray.eps, s) {
                ray.tmin
            } else {
                f64::INFINITY
            };
        }
        let root = if self.leaf_level == 0 {
            match self.dag.leaf(0) {
                Ok(mask) => Handle::Brick(mask.0),
                Err(_) => return f64::INFINITY,
            }
        } else {
            Handle::Node(0)
        };
        let mut best = f64::INFINITY;
        let mut heap = BinaryHeap::new();
        if let Some((entry, exit)) = grown_entry(ray, [0; 3], (1u64 << depth) as f64) {
            heap.push(Pending {
                entry,
                exit,
                level: 0,
                cell: [0; 3],
                handle: root,
            });
        }
        while let Some(p) = heap.pop() {
            if p.entry > best.min(bound) {
                break;
            }
            if p.level == level {
                let s = (1u64 << (depth - level)) as f64;
                if let Some(t) = first_robust_in(&cells, ray, p.cell, s, p.entry, p.exit) {
                    best = best.min(t);
                }
                continue;
            }
            let child_level = p.level + 1;
            let s = (1u64 << (depth - child_level)) as f64;
            let mut push = |child: u32, handle: Handle| {
                let cell = [0, 1, 2].map(|a| p.cell[a] * 2 + ((child >> a) & 1));
                if let Some((entry, exit)) = grown_entry(ray, cell, s)
                    && entry <= best.min(bound)
                {
                    heap.push(Pending {
                        entry,
                        exit,
                        level: child_level,
                        cell,
                        handle,
                    });
                }
            };
            match p.handle {
                Handle::Node(word) => {
                    // The file was validated: reads cannot fail.
                    let Ok(node) = self.dag.node(p.level, word) else {
                        continue;
                    };
                    for child in 0..8 {
                        let Some(pointer) = node.child_pointer(child) else {
                            continue;
                        };
                        let handle = if child_level == self.leaf_level {
                            match self.dag.leaf(pointer) {
                                Ok(mask) => Handle::Brick(mask.0),
                                Err(_) => continue,
                            }
                        } else {
                            Handle::Node(pointer)
                        };
                        push(child, handle);
                    }
                }
                Handle::Brick(mask) => {
                    for child in 0..8 {
                        let sub = (mask >> (8 * child)) as u8;
                        if sub != 0 {
                            push(child, Handle::SubBrick(sub));
                        }
                    }
                }
                Handle::SubBrick(bits) => {
                    for child in 0..8 {
                        if bits >> child & 1 != 0 {
                            push(child, Handle::Voxel);
                        }
                    }
                }
                Handle::Voxel => {}
            }
        }
        best
    }

    /// The dense index of the first voxel of `cell` of `level` (§ 12.3) when
    /// the cell is occupied (0 unless `with_index`: occupancy queries, the
    /// bulk of them, need no voxel counts). `cell` must lie inside the level.
    fn lookup(&self, level: u8, cell: [u32; 3], with_index: bool) -> Option<u64> {
        if self.dag.is_empty() {
            return None;
        }
        let mut index = 0u64;
        let mut word = 0u32;
        // At depth 2 the root is the brick.
        let mut mask = if self.leaf_level == 0 {
            self.dag.leaf(0).ok()?.0
        } else {
            0
        };
        let mut sub = 0u8;
        for l in 0..level {
            let child = child_on_path(cell, level, l);
            if l < self.leaf_level {
                let node = self.dag.node(l, word).ok()?;
                let pointer = node.child_pointer(child)?;
                if with_index {
                    for earlier in 0..child {
                        if let Some(p) = node.child_pointer(earlier) {
                            index += self.count(l + 1, p);
                        }
                    }
                }
                word = pointer;
                if l + 1 == self.leaf_level {
                    mask = self.dag.leaf(word).ok()?.0;
                }
            } else if l == self.leaf_level {
                sub = (mask >> (8 * child)) as u8;
                if sub == 0 {
                    return None;
                }
                index += u64::from((mask & ((1u64 << (8 * child)) - 1)).count_ones());
            } else {
                if sub >> child & 1 == 0 {
                    return None;
                }
                index += u64::from((sub & ((1u8 << child) - 1)).count_ones());
            }
        }
        Some(index)
    }

    /// Voxels in the subtree of the node at (`level`, `pointer`).
    fn count(&self, level: u8, pointer: u32) -> u64 {
        if level == self.leaf_level {
            return self.dag.leaf(pointer).map_or(0, |m| u64::from(m.count()));
        }
        let slot = &self.counts[usize::from(level)][pointer as usize];
        let known = slot.load(AtomicOrdering::Relaxed);
        if known != UNKNOWN {
            return known;
        }
        let Ok(node) = self.dag.node(level, pointer) else {
            return 0;
        };
        let total = (0..node.child_count())
            .map(|rank| self.count(level + 1, node.pointer_at(rank)))
            .sum();
        // Every thread computes the same number: a race only repeats work.
        slot.store(total, AtomicOrdering::Relaxed);
        total
    }
}

/// Entry and exit of the segment into `cell` (edge `s`) grown by `eps_g`, by
/// the slab rule, exactly as the oracle computes them; `None` if it misses.
fn grown_entry(ray: &GridRay, cell: [u32; 3], s: f64) -> Option<(f64, f64)> {
    let mut near = f64::NEG_INFINITY;
    let mut far = f64::INFINITY;
    for (axis, &ca) in cell.iter().enumerate() {
        let lo = f64::from(ca) * s - ray.eps;
        let hi = f64::from(ca + 1) * s + ray.eps;
        let (a, b) = slab(ray.o[axis], ray.d[axis], lo, hi)?;
        near = near.max(a);
        far = far.min(b);
    }
    let entry = ray.tmin.max(near);
    let exit = ray.tmax.min(far);
    (entry <= exit).then_some((entry, exit))
}
