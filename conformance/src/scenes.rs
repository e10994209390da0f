//! The tracer cases: volumes and rays, generated from fixed seeds.
//!
//! Every case is a volume (built with `dagfmt`'s builder, or re-encoded with
//! [`crate::model`] for the unusual-but-valid layouts) and groups of rays with
//! a comment saying what each group probes. Rays are designed in grid space
//! (voxel units) and converted to the case's world space as f32; the oracle
//! judges the f32 rays actually written, so the conversion needs no care.

use dagfmt::batch::Ray;
use dagfmt::builder::DagBuilder;
use dagfmt::{AttributeKind, morton};

use crate::mesh::Mesh;
use crate::model::DagModel;
use crate::rng::Rng;

/// A group of rays with a comment saying what they probe.
#[derive(Clone, Debug)]
pub struct RayGroup {
    /// One line, written as a comment before the rays.
    pub comment: String,
    /// The rays.
    pub rays: Vec<Ray>,
    /// Where not empty, the text of each ray's line in the `.rays` file (one
    /// per ray), for rays whose spelling matters (a decimal that rounds twice
    /// through binary64, a level with leading zeros); it must parse to the ray.
    pub literals: Vec<String>,
}

/// One tracer case.
#[derive(Clone, Debug)]
pub struct TraceCase {
    /// File stem (`trace/<name>.vdag` ...).
    pub name: String,
    /// One line saying what the case is.
    pub description: String,
    /// The `.vdag` file.
    pub file: Vec<u8>,
    /// The voxels the file is meant to hold (Morton order), checked against
    /// the decoded file; `None` when too many to list.
    pub voxels: Option<Vec<[u32; 3]>>,
    /// The rays, in groups.
    pub groups: Vec<RayGroup>,
    /// Whether the batch as a whole must be rejected (a ray's level is deeper
    /// than the file, spec/VDAG.md § 20.2): the `.expect` file then says
    /// `reject-batch` instead of one line per ray.
    pub reject_batch: bool,
}

/// A volume being described.
#[derive(Clone, Debug)]
struct Volume {
    depth: u8,
    kind: AttributeKind,
    root_min: [f64; 3],
    root_size: f64,
    voxels: Vec<[u32; 3]>,
}

impl Volume {
    fn new(depth: u8, voxels: Vec<[u32; 3]>) -> Self {
        let mut voxels = voxels;
        voxels.sort_by_key(|v| morton::encode(v[0], v[1], v[2]));
        voxels.dedup();
        Volume {
            depth,
            kind: AttributeKind::VoxelCount,
            root_min: [0.0; 3],
            root_size: 1.0,
            voxels,
        }
    }

    fn from_fn(depth: u8, f: impl Fn(u32, u32, u32) -> bool) -> Self {
        let n = 1u32 << depth;
        let mut voxels = Vec::new();
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    if f(x, y, z) {
                        voxels.push([x, y, z]);
                    }
                }
            }
        }
        Volume::new(depth, voxels)
    }

    fn root(mut self, min: [f64; 3], size: f64) -> Self {
        self.root_min = min;
        self.root_size = size;
        self
    }

    fn kind(mut self, kind: AttributeKind) -> Self {
        self.kind = kind;
        self
    }

    fn n(&self) -> f64 {
        (1u64 << self.depth) as f64
    }

    fn build(&self) -> Vec<u8> {
        let mut built = DagBuilder::from_voxels(self.depth, self.kind, self.voxels.iter().copied())
            .expect("case volumes are valid");
        built
            .set_root_cube(self.root_min, self.root_size)
            .expect("finite root cube");
        built.to_bytes()
    }

    /// A ray over `[0, inf)` given in grid space.
    fn ray(&self, o: [f64; 3], d: [f64; 3]) -> Ray {
        let scale = self.root_size / self.n();
        Ray {
            origin: [0, 1, 2].map(|i| (self.root_min[i] + o[i] * scale) as f32),
            dir: [0, 1, 2].map(|i| (d[i] * scale) as f32),
            tmin: 0.0,
            tmax: f32::INFINITY,
            level: None,
        }
    }

    fn case(&self, name: &str, description: &str, groups: Vec<RayGroup>) -> TraceCase {
        TraceCase {
            name: name.into(),
            description: description.into(),
            file: self.build(),
            voxels: Some(self.voxels.clone()),
            groups,
            reject_batch: false,
        }
    }
}

fn seg(mut r: Ray, tmin: f32, tmax: f32) -> Ray {
    r.tmin = tmin;
    r.tmax = tmax;
    r
}

fn lod(mut r: Ray, level: u8) -> Ray {
    r.level = Some(level);
    r
}

fn group(comment: &str, rays: Vec<Ray>) -> RayGroup {
    RayGroup {
        comment: comment.into(),
        rays,
        literals: Vec::new(),
    }
}

/// Puts `(a, u, v)` into axis order: coordinate `a` on `axis`, then the next two axes cyclically.
fn on_axis(axis: usize, a: f64, u: f64, v: f64) -> [f64; 3] {
    let mut p = [0.0; 3];
    p[axis] = a;
    p[(axis + 1) % 3] = u;
    p[(axis + 2) % 3] = v;
    p
}

fn unit(axis: usize, sign: f64) -> [f64; 3] {
    on_axis(axis, sign, 0.0, 0.0)
}

/// Axis-aligned rays from outside through the points `(u, v)` of the other
/// two axes, along all six directions.
fn axis_rays(vol: &Volume, pairs: &[(f64, f64)]) -> Vec<Ray> {
    let n = vol.n();
    let mut rays = Vec::new();
    for axis in 0..3 {
        for sign in [1.0, -1.0] {
            for &(u, v) in pairs {
                let start = if sign > 0.0 { -1.0 } else { n + 1.0 };
                rays.push(vol.ray(on_axis(axis, start, u, v), unit(axis, sign)));
            }
        }
    }
    rays
}

/// A random cell centre of the volume.
fn random_centre(rng: &mut Rng, n: f64) -> f64 {
    rng.below(n as u64) as f64 + 0.5
}

/// The standard probe rays for a hand-made volume: every family of the
/// suite's ray list. `small` keeps a reduced set for the many tiny cases.
fn probe_rays(vol: &Volume, rng: &mut Rng, small: bool) -> Vec<RayGroup> {
    let n = vol.n();
    let h = n / 2.0;
    let mut groups = Vec::new();

    let mut centres = vec![(0.5, 0.5), (h - 0.5, h + 0.5), (n - 0.5, 0.5)];
    if !small {
        centres.push((h + 0.5, n - 0.5));
        centres.push((random_centre(rng, n), random_centre(rng, n)));
        centres.push((random_centre(rng, n), random_centre(rng, n)));
    }
    groups.push(group(
        "axis-aligned rays through cell centres, all six directions",
        axis_rays(vol, &centres),
    ));

    let mut lines = vec![(h, h), (1.0, h + 0.5)];
    if !small {
        lines.push((h - 1.0, n - 1.0));
        lines.push((1.0, 1.0));
    }
    groups.push(group(
        "axis-aligned rays along shared cell faces and edges (integer coordinates)",
        axis_rays(vol, &lines),
    ));

    // Grazing the root cube: in its faces and edges, and 1/64 voxel inside and outside.
    let delta = 1.0 / 64.0;
    let mut graze = Vec::new();
    for axis in 0..3 {
        let mut spots = vec![(0.0, h + 0.5), (n, n), (delta, h + 0.5), (-delta, h + 0.5)];
        if !small {
            spots.extend([(0.0, 0.0), (n, h - 0.5), (n - delta, 0.5), (n + delta, 0.5)]);
        }
        for (u, v) in spots {
            graze.push(vol.ray(on_axis(axis, -1.0, u, v), unit(axis, 1.0)));
        }
    }
    groups.push(group(
        "rays grazing the root cube: in its faces and edges, 1/64 voxel inside and outside",
        graze,
    ));

    let mut diag = vec![
        vol.ray([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]),
        vol.ray([n + 1.0, -1.0, -1.0], [-1.0, 1.0, 1.0]),
        vol.ray([-1.0, n + 1.0, -1.0], [1.0, -1.0, 1.0]),
        vol.ray([-1.0, -1.0, n + 1.0], [1.0, 1.0, -1.0]),
        vol.ray([-1.0, -2.0, -3.0], [1.0, 2.0, 3.0]),
    ];
    let planes: &[f64] = if small { &[h] } else { &[0.5, h, h + 0.5] };
    for axis in 0..3 {
        for &c in planes {
            diag.push(vol.ray(on_axis(axis, c, -1.0, -1.0), on_axis(axis, 0.0, 1.0, 1.0)));
            diag.push(vol.ray(
                on_axis(axis, c, -1.0, n + 1.0),
                on_axis(axis, 0.0, 1.0, -1.0),
            ));
        }
    }
    if !small {
        diag.push(vol.ray([h, h, h], [1.0, 1.0, 1.0]));
        diag.push(vol.ray([h, h, h], [-1.0, -1.0, -1.0]));
        diag.push(vol.ray([h + 1.0, h - 1.0, -2.0], [-1.0, 1.0, 2.0]));
        diag.push(vol.ray([-2.0, 0.0, 1.0], [2.0, 1.0, 0.0]));
    }
    groups.push(group(
        "diagonals through exact lattice corners and along shared edges (ties between cells and faces)",
        diag,
    ));

    let mut zeros = vec![
        vol.ray([-1.0, h + 0.5, h - 0.5], [1.0, 0.0, -0.0]),
        vol.ray([h - 0.5, n + 1.0, 0.5], [-0.0, -1.0, 0.0]),
        vol.ray([0.5, h + 0.5, -1.0], [0.0, -0.0, 1.0]),
        vol.ray([-1.0, n + 1.0, h + 0.5], [1.0, -1.0, -0.0]),
    ];
    if !small {
        zeros.push(vol.ray([n + 1.0, h - 0.5, -1.0], [-1.0, -0.0, 1.0]));
        zeros.push(vol.ray([h, -1.0, h], [-0.0, 1.0, 0.0]));
        zeros.push(vol.ray([-1.0, h, h + 0.5], [2.0, -0.0, -0.0]));
    }
    groups.push(group(
        "direction components of zero and negative zero",
        zeros,
    ));

    let mut inside = Vec::new();
    for v in vol
        .voxels
        .iter()
        .step_by((vol.voxels.len() / 3).max(1))
        .take(3)
    {
        let c = v.map(|x| f64::from(x) + 0.5);
        inside.push(vol.ray(c, rng.direction()));
    }
    let interior = if small { 2 } else { 5 };
    for _ in 0..interior {
        let o = [rng.range(0.0, n), rng.range(0.0, n), rng.range(0.0, n)];
        inside.push(vol.ray(o, rng.direction()));
    }
    inside.push(vol.ray([h, h, h], rng.direction()));
    inside.push(vol.ray([1.0, 1.0, 1.0], [1.0, 0.5, 0.25]));
    if !small {
        inside.push(vol.ray([n, h, h], [-1.0, 0.0, 0.0]));
        inside.push(vol.ray([0.0, 0.0, 0.0], [1.0, 1.0, 1.0]));
    }
    groups.push(group(
        "rays starting inside the volume: voxel centres, random points, lattice corners, the root boundary",
        inside,
    ));

    let mut behind = vec![
        vol.ray([-1.0, h + 0.5, h + 0.5], [-1.0, 0.1, 0.2]),
        seg(
            vol.ray([-1.0, h + 0.5, h + 0.5], [-1.0, 0.0, 0.0]),
            -1e4,
            f32::INFINITY,
        ),
        vol.ray([n + 3.0, n + 3.0, n + 3.0], [1.0, 1.0, 1.0]),
        seg(
            vol.ray([n + 3.0, n + 3.0, n + 3.0], [1.0, 1.0, 1.0]),
            f32::NEG_INFINITY,
            0.0,
        ),
    ];
    if !small {
        behind.push(seg(
            vol.ray([h + 0.5, h + 0.5, -5.0], [0.0, 0.0, -1.0]),
            -1e3,
            -2.0,
        ));
        behind.push(vol.ray([h + 0.5, -5.0, h + 0.5], [0.0, -2.0, 0.0]));
    }
    groups.push(group(
        "rays behind the volume or pointing away, and negative tmin reaching back",
        behind,
    ));

    let line = |y: f64, z: f64| vol.ray([-1.0, y, z], [1.0, 0.0, 0.0]);
    let (y, z) = (h + 0.5, h - 0.5);
    let mut clip = vec![
        seg(line(y, z), 0.0, 0.5),
        seg(line(y, z), n as f32 + 2.0, f32::INFINITY),
        seg(line(y, z), 0.0, 1.0),
        seg(line(y, z), (h + 1.0) as f32, (h + 1.0) as f32),
        seg(line(y, z), 3.0, 2.0),
        seg(line(y, z), f32::NEG_INFINITY, f32::INFINITY),
    ];
    if !small {
        clip.push(seg(line(y, z), (h + 1.0) as f32, (h + 3.0) as f32));
        clip.push(seg(line(0.5, 0.5), 1.5, 2.5));
        clip.push(seg(line(n - 0.5, n - 0.5), n as f32, n as f32 + 1.0));
        clip.push(seg(line(y, z), 1.0 + 1.0 / 1024.0, f32::INFINITY));
        clip.push(seg(line(y, z), f32::NEG_INFINITY, 1.0 - 1.0 / 1024.0));
    }
    groups.push(group(
        "tmin/tmax clipping: segments ending before, starting after, ending exactly at a face, points, empty",
        clip,
    ));

    if !small {
        let mut scaled = Vec::new();
        for s in [1.0 / 1024.0, 1e-3, 3.7, 1024.0, 1e5] {
            scaled.push(vol.ray([-1.0, h + 0.5, h - 0.5], [s, 0.0, 0.0]));
            scaled.push(vol.ray([-1.0, -1.5, 0.25], [s, s * 1.25, s * 0.5]));
        }
        groups.push(group(
            "unnormalised directions: t scales with 1/|d|",
            scaled,
        ));
    }

    let centre = vol
        .voxels
        .first()
        .map(|v| v.map(|x| f64::from(x) + 0.5))
        .unwrap_or([h, h, h]);
    let mut degenerate = vec![
        Ray {
            origin: [f32::NAN, 0.5, 0.5],
            ..vol.ray([0.0, h, h], [1.0, 0.0, 0.0])
        },
        Ray {
            dir: [1.0, f32::NAN, 0.0],
            ..vol.ray([-1.0, h, h], [1.0, 0.0, 0.0])
        },
        seg(
            vol.ray([-1.0, h + 0.5, h + 0.5], [1.0, 0.0, 0.0]),
            f32::NAN,
            f32::INFINITY,
        ),
        seg(
            vol.ray([-1.0, h + 0.5, h + 0.5], [1.0, 0.0, 0.0]),
            0.0,
            f32::NAN,
        ),
        seg(vol.ray(centre, [0.0, 0.0, 0.0]), 0.0, 1.0),
        seg(vol.ray(centre, [0.0, -0.0, 0.0]), 2.5, 2.5),
    ];
    if !small {
        degenerate.push(Ray {
            origin: [f32::NEG_INFINITY, 0.5, 0.5],
            ..vol.ray([0.0, h, h], [1.0, 0.0, 0.0])
        });
        degenerate.push(Ray {
            dir: [0.0, f32::INFINITY, 0.0],
            ..vol.ray(centre, [0.0, 1.0, 0.0])
        });
        degenerate.push(seg(vol.ray(centre, [0.0, 0.0, 0.0]), 1.0, 0.0));
        degenerate.push(seg(
            vol.ray([n + 1.0, h, h], [0.0, 0.0, 0.0]),
            0.0,
            f32::INFINITY,
        ));
    }
    groups.push(group("NaN or infinite origin or direction (miss), zero direction vectors (a point query at t = tmin)", degenerate));
    groups
}

/// The same rays traced at every coarser level.
fn coarser_levels(
    vol: &Volume,
    rays: &[Ray],
    levels: impl Iterator<Item = u8> + Clone,
) -> RayGroup {
    let mut out = Vec::new();
    for r in rays {
        for level in levels.clone() {
            if level <= vol.depth {
                out.push(lod(*r, level));
            }
        }
    }
    group(
        "level of detail: the rays above at coarser levels (and the full depth given explicitly)",
        out,
    )
}

/// Random rays: from outside aimed at random points inside, from inside in
/// random directions, random segments and lengths.
fn random_rays(vol: &Volume, rng: &mut Rng, count: usize) -> Vec<Ray> {
    let n = vol.n();
    let mut rays = Vec::with_capacity(count);
    for i in 0..count {
        let target = [rng.range(0.0, n), rng.range(0.0, n), rng.range(0.0, n)];
        let (o, d) = match i % 4 {
            0 | 1 => {
                let dir = rng.direction();
                let o = [0, 1, 2].map(|k| n / 2.0 + dir[k] * n * rng.range(0.9, 2.0));
                (o, [0, 1, 2].map(|k| target[k] - o[k]))
            }
            2 => (target, rng.direction()),
            _ => {
                let o = [
                    rng.range(-0.5 * n, 1.5 * n),
                    rng.range(-0.5 * n, 1.5 * n),
                    rng.range(-0.5 * n, 1.5 * n),
                ];
                (o, [0, 1, 2].map(|k| target[k] - o[k]))
            }
        };
        let length = 2f64.powi(rng.below(9) as i32 - 4);
        let d = d.map(|x| x * length);
        let mut ray = vol.ray(o, d);
        if rng.chance(0.2) {
            let a = rng.range(-0.5, 1.5) as f32;
            let b = a + rng.range(0.0, 1.5) as f32;
            ray = seg(ray, a, b);
        }
        rays.push(ray);
    }
    rays
}

/// Rays with tie-prone coordinates: lattice or half-lattice origins and small
/// integer directions, so they pass exactly through edges and corners.
fn snapped_rays(vol: &Volume, rng: &mut Rng, count: usize) -> Vec<Ray> {
    let n = vol.n() as u64;
    let mut rays = Vec::with_capacity(count);
    while rays.len() < count {
        let o = [0; 3].map(|_| (rng.below(2 * n + 5) as f64 - 2.0) / 2.0);
        let d = [0; 3].map(|_| rng.below(5) as f64 - 2.0);
        if d == [0.0; 3] {
            continue;
        }
        rays.push(vol.ray(o, d));
    }
    rays
}

/// Rays from far away (10 to 10^4 volume sizes) aimed at random points inside.
fn far_rays(vol: &Volume, rng: &mut Rng, count: usize) -> Vec<Ray> {
    let n = vol.n();
    (0..count)
        .map(|i| {
            let distance = n * [10.0, 100.0, 1000.0, 10000.0][i % 4];
            let dir = rng.direction();
            let o = [0, 1, 2].map(|k| n / 2.0 + dir[k] * distance);
            let target = [rng.range(0.0, n), rng.range(0.0, n), rng.range(0.0, n)];
            let d = [0, 1, 2].map(|k| target[k] - o[k]);
            let length = d.iter().map(|v| v * v).sum::<f64>().sqrt();
            vol.ray(o, d.map(|v| v / length))
        })
        .collect()
}

/// Rays along an axis with tiny other components, from outside through cell
/// centres and along cell faces.
fn nearly_axis_rays(vol: &Volume, rng: &mut Rng, count: usize) -> Vec<Ray> {
    let n = vol.n();
    (0..count)
        .map(|i| {
            let axis = i % 3;
            let sign = if rng.chance(0.5) { 1.0 } else { -1.0 };
            let start = if sign > 0.0 { -1.0 } else { n + 1.0 };
            let on_face = rng.chance(0.5);
            let place = |rng: &mut Rng| {
                let c = rng.below(n as u64) as f64;
                if on_face { c } else { c + 0.5 }
            };
            let (u, v) = (place(rng), place(rng));
            let tiny = |rng: &mut Rng| {
                // Parsed from decimal: exactly the same value on every platform.
                let magnitude: f64 = format!("1e-{}", 7 + rng.below(24))
                    .parse()
                    .expect("a number");
                if rng.chance(0.5) {
                    magnitude
                } else {
                    -magnitude
                }
            };
            let (du, dv) = (tiny(rng), if rng.chance(0.5) { tiny(rng) } else { 0.0 });
            vol.ray(on_axis(axis, start, u, v), on_axis(axis, sign, du, dv))
        })
        .collect()
}

fn seed_of(name: &str) -> u64 {
    // FNV-1a: a fixed seed per case name, independent of case order.
    name.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

fn hand_made(name: &str, description: &str, vol: Volume, small: bool, with_lod: bool) -> TraceCase {
    let mut rng = Rng::new(seed_of(name));
    let mut groups = probe_rays(&vol, &mut rng, small);
    if with_lod {
        let base: Vec<Ray> = groups[0]
            .rays
            .iter()
            .chain(&groups[3].rays)
            .copied()
            .collect();
        groups.push(coarser_levels(&vol, &base, 1..=vol.depth));
    }
    vol.case(name, description, groups)
}

/// The reduced probe rays plus rays aimed at the volume's single voxel `v`.
fn aimed(name: &str, description: &str, vol: Volume, v: [u32; 3]) -> TraceCase {
    let mut rng = Rng::new(seed_of(name));
    let mut groups = probe_rays(&vol, &mut rng, true);
    groups.extend(single_voxel_rays(&vol, v, &mut rng).into_iter().take(4));
    vol.case(name, description, groups)
}

/// Rays aimed at a single voxel: through its centre, a quarter voxel inside a
/// face, 1.5 voxels beside it, along its edges, and at coarser levels.
fn single_voxel_rays(vol: &Volume, v: [u32; 3], rng: &mut Rng) -> Vec<RayGroup> {
    let n = vol.n();
    let c = v.map(|x| f64::from(x) + 0.5);
    let mut through = Vec::new();
    let mut offset = Vec::new();
    let mut beside = Vec::new();
    let mut edges = Vec::new();
    for axis in 0..3 {
        let (u, w) = ((axis + 1) % 3, (axis + 2) % 3);
        for sign in [1.0, -1.0] {
            let start = if sign > 0.0 { -1.0 } else { n + 1.0 };
            through.push(vol.ray(on_axis(axis, start, c[u], c[w]), unit(axis, sign)));
            offset.push(vol.ray(
                on_axis(axis, start, c[u] + 0.25, c[w] - 0.25),
                unit(axis, sign),
            ));
            beside.push(vol.ray(on_axis(axis, start, c[u] + 1.5, c[w]), unit(axis, sign)));
            beside.push(vol.ray(on_axis(axis, start, c[u], c[w] - 1.5), unit(axis, sign)));
            edges.push(vol.ray(
                on_axis(axis, start, c[u] + 0.5, c[w] + 0.5),
                unit(axis, sign),
            ));
        }
    }
    let mut diagonal = Vec::new();
    for _ in 0..4 {
        let dir = rng.direction();
        let o = [0, 1, 2].map(|k| c[k] - dir[k] * n * 0.75);
        diagonal.push(vol.ray(o, dir));
    }
    let depth = vol.depth;
    let coarse: Vec<Ray> = through
        .iter()
        .chain(&beside[..4])
        .flat_map(|r| [depth - 1, depth.div_ceil(2), 1].map(|l| lod(*r, l)))
        .collect();
    vec![
        group(
            "axis-aligned rays through the voxel centre, all six directions",
            through,
        ),
        group(
            "axis-aligned rays a quarter voxel inside the voxel's faces",
            offset,
        ),
        group(
            "axis-aligned rays passing 1.5 voxels beside the voxel (must miss at full depth)",
            beside,
        ),
        group("axis-aligned rays along the voxel's edges (grazing)", edges),
        group(
            "rays from random directions through the voxel centre",
            diagonal,
        ),
        group(
            "level of detail: the centre and beside rays at levels D-1, ceil(D/2) and 1",
            coarse,
        ),
    ]
}

/// Every tracer case of the suite, in a fixed order.
pub fn trace_cases() -> Vec<TraceCase> {
    let mut cases = vec![
        hand_made(
            "empty-d4",
            "an empty depth-4 volume: every ray misses",
            Volume::new(4, Vec::new()),
            false,
            false,
        ),
        hand_made(
            "full-d4",
            "a completely full depth-4 volume",
            Volume::from_fn(4, |_, _, _| true),
            false,
            true,
        ),
    ];
    cases.push(hand_made(
        "full-d5-offset-root",
        "a full depth-5 volume whose root cube is not at the origin and not of size 1",
        Volume::from_fn(5, |_, _, _| true).root([-3.5, 0.25, 1024.0], 6.0),
        true,
        false,
    ));
    cases.push(hand_made(
        "tiny-d2",
        "a depth-2 volume (the root is a single 4^3 leaf brick) with a few voxels",
        Volume::new(
            2,
            vec![[0, 0, 0], [3, 1, 2], [1, 3, 3], [2, 2, 2], [3, 3, 0]],
        ),
        false,
        true,
    ));
    for corner in 0..8u32 {
        let v = [corner & 1, (corner >> 1) & 1, corner >> 2].map(|b| b * 7);
        cases.push(aimed(
            &format!("corner-{corner}-d3"),
            &format!("a single voxel at the corner {v:?} of a depth-3 volume"),
            Volume::new(3, vec![v]),
            v,
        ));
    }
    for octant in 0..8u32 {
        let v = [octant & 1, (octant >> 1) & 1, octant >> 2].map(|b| b * 8 + 3);
        cases.push(aimed(
            &format!("octant-{octant}-d4"),
            &format!("a single voxel {v:?} inside octant {octant} of a depth-4 volume"),
            Volume::new(4, vec![v]),
            v,
        ));
    }
    cases.push(hand_made(
        "checker-d3",
        "a 3D checkerboard of single voxels (x + y + z even), depth 3",
        Volume::from_fn(3, |x, y, z| (x + y + z) % 2 == 0),
        false,
        true,
    ));
    cases.push(hand_made(
        "checker2-d4",
        "a 3D checkerboard of 2^3 blocks, depth 4 (a full volume at level 3's parity)",
        Volume::from_fn(4, |x, y, z| (x / 2 + y / 2 + z / 2) % 2 == 0),
        false,
        true,
    ));
    cases.push(walls_case());
    cases.push(hand_made(
        "slab-kind0-d5",
        "a half-full depth-5 volume (z < 16) with attribute kind 0: hits carry no index",
        Volume::from_fn(5, |_, _, z| z < 16).kind(AttributeKind::None),
        false,
        true,
    ));

    for depth in 2..=21u8 {
        let n = 1u64 << depth;
        let v = [n * 5 / 16, n * 9 / 16, n * 7 / 16].map(|c| c as u32 + u32::from(depth % 3 == 1));
        let vol = Volume::new(depth, vec![v]).root([-1.0, -1.0, -1.0], 2.0);
        let mut rng = Rng::new(seed_of(&format!("single-d{depth}")));
        let groups = single_voxel_rays(&vol, v, &mut rng);
        cases.push(vol.case(
            &format!("single-d{depth:02}"),
            &format!("a single voxel {v:?} in a depth-{depth} volume spanning [-1, 1]^3 (float precision)"),
            groups,
        ));
    }

    cases.extend(random_cases());
    cases.extend(mesh_cases());
    cases.push(saturated_case());
    cases.extend(relayout_cases());
    cases.extend(empty_cases());
    cases.extend(decided_cases());
    cases
}

/// Empty volumes (spec/VDAG.md § 7) of other depths than `empty-d4`: the
/// smallest (the root level is the leaf level), a middle one and the deepest.
fn empty_cases() -> Vec<TraceCase> {
    [2u8, 9, 21]
        .into_iter()
        .map(|depth| {
            hand_made(
                &format!("empty-d{depth:02}"),
                &format!("an empty depth-{depth} volume: every ray misses, at every level"),
                Volume::new(depth, Vec::new()).root([-1.0, -1.0, -1.0], 2.0),
                true,
                true,
            )
        })
        .collect()
}

/// Cases for the decisions of spec 1.1 (VDAG.md § 22.2): point queries with
/// infinite `tmin`, directions that are zero in binary64, decimals that round
/// twice through binary64, level fields with leading zeros, and a batch with
/// a level deeper than the file.
fn decided_cases() -> Vec<TraceCase> {
    // Depth 3, voxels (1, 1, 1) and (2, 1, 1) in the root cube [0, 8]^3.
    let vol = Volume::new(3, vec![[1, 1, 1], [2, 1, 1]]).root([0.0; 3], 8.0);
    let point = |o: [f64; 3], tmin: f32, tmax: f32| seg(vol.ray(o, [0.0; 3]), tmin, tmax);
    let inf = f32::INFINITY;
    let infinite_tmin = group(
        "zero direction with infinite tmin (§ 20.4): a hit reports t = tmin, inf or -inf, face 0; outside the voxels a miss",
        vec![
            point([1.5, 1.5, 1.5], -inf, inf),
            point([1.5, 1.5, 1.5], inf, inf),
            point([1.5, 1.5, 1.5], -inf, -inf),
            point([2.0, 1.5, 1.5], -inf, 0.0),
            point([4.5, 1.5, 1.5], -inf, inf),
            lod(point([3.5, 1.5, 1.5], -inf, inf), 1),
        ],
    );
    // Literal spellings (§ 21.1): the reader rounds each decimal once, to f32.
    let midpoint_plus = "1.0000000596046447753906250000001";
    let spelled = RayGroup {
        comment: format!(
            "spelling (§ 21.1): tmin {midpoint_plus} is just above the midpoint of 1 and the next f32, so t = 1.0000001 (through binary64 it would round twice, to 1); levels with leading zeros"
        ),
        rays: vec![
            point([1.5, 1.5, 1.5], 1.0f32.next_up(), inf),
            lod(vol.ray([-1.0, 1.5, 1.5], [1.0, 0.0, 0.0]), 3),
            lod(vol.ray([-1.0, 1.5, 1.5], [1.0, 0.0, 0.0]), 1),
        ],
        literals: vec![
            format!("1.5 1.5 1.5 0 0 0 {midpoint_plus} inf"),
            "-1 1.5 1.5 1 0 0 0 inf 003".into(),
            "-1 1.5 1.5 1 0 0 0 inf 01".into(),
        ],
    };
    let decided = vol.case(
        "decided-d3",
        "two voxels, depth 3, root cube [0, 8]^3: the cases of the decisions of spec 1.1",
        vec![infinite_tmin, spelled],
    );
    // A root cube of size 2^1000 centred on the origin: grid = (world +
    // 2^999) * 2^-997, so every f32 origin lies at the grid centre (4, 4, 4),
    // inside the 2^3 block of voxels around it, and a direction component of
    // 2^-60 is 2^-1057 grid units, below the smallest normal binary64 number:
    // zero (§ 20.1). A component of 1 is 2^-997: the ray moves.
    let huge = 2f64.powi(1000);
    let block: Vec<[u32; 3]> = (0..8u32)
        .map(|c| [3 + (c & 1), 3 + ((c >> 1) & 1), 3 + (c >> 2)])
        .collect();
    let tiny_vol = Volume::new(3, block).root([-huge / 2.0; 3], huge);
    let world = |d: [f32; 3], tmin: f32| Ray {
        origin: [1.0; 3],
        dir: d,
        tmin,
        tmax: inf,
        level: None,
    };
    let tiny = 2f32.powi(-60);
    let underflow = tiny_vol.case(
        "underflow-d3",
        "a root cube of size 2^1000 around the origin and the 2^3 voxels at its centre: directions whose grid-space components are below 2^-1022 are zero (§ 20.1)",
        vec![group(
            "from the centre: directions of 2^-60 (grid 2^-1057) are point queries, t = tmin, face 0; a direction of 1 (grid 2^-997) moves, entering through face 1 when tmin = -inf",
            vec![
                world([tiny, 0.0, 0.0], f32::NEG_INFINITY),
                world([tiny, -tiny, 0.0], 0.0),
                world([0.0, 0.0, -tiny], 5.0),
                world([1.0, 0.0, 0.0], f32::NEG_INFINITY),
                world([1.0, 0.0, 0.0], 0.0),
            ],
        )],
    );
    // A batch one of whose rays asks for level 4 of a depth-3 file.
    let mut deep = vol.case(
        "level-too-deep-d3",
        "a batch whose third ray asks for level 4 of a depth-3 file: the whole batch is rejected (§ 20.2)",
        vec![group(
            "valid rays, then one at level 4: the tracer must fail and write no answers",
            vec![
                vol.ray([-1.0, 1.5, 1.5], [1.0, 0.0, 0.0]),
                lod(vol.ray([-1.0, 1.5, 1.5], [1.0, 0.0, 0.0]), 2),
                lod(vol.ray([-1.0, 1.5, 1.5], [1.0, 0.0, 0.0]), 4),
            ],
        )],
    );
    deep.reject_batch = true;
    vec![decided, underflow, deep]
}

fn walls_case() -> TraceCase {
    // One-voxel-thin walls: the plane x = 9, half the plane y = 20 (z < 16),
    // and a staircase x == y (z >= 16) whose voxels touch only along edges.
    let vol = Volume::from_fn(5, |x, y, z| {
        x == 9 || (y == 20 && z < 16) || (x == y && z >= 16)
    });
    let mut rng = Rng::new(seed_of("walls-d5"));
    let mut groups = probe_rays(&vol, &mut rng, false);
    groups.push(group(
        "rays perpendicular to and inside the thin walls",
        vec![
            vol.ray([-1.0, 3.5, 7.5], [1.0, 0.0, 0.0]),
            vol.ray([40.0, 3.5, 7.5], [-1.0, 0.0, 0.0]),
            vol.ray([9.5, -1.0, 7.5], [0.0, 1.0, 0.0]),
            vol.ray([9.5, 3.5, 7.5], [0.0, 1.0, 0.0]),
            vol.ray([3.5, -1.0, 3.5], [0.0, 1.0, 0.0]),
            vol.ray([3.5, 20.5, -1.0], [0.0, 0.0, 1.0]),
            vol.ray([-1.0, 20.5, 15.5], [1.0, 0.0, 0.0]),
        ],
    ));
    groups.push(group(
        "rays grazing the walls' surfaces (in the planes x = 9 and x = 10, y = 20 and y = 21)",
        vec![
            vol.ray([9.0, -1.0, 7.5], [0.0, 1.0, 0.0]),
            vol.ray([10.0, 40.0, 7.5], [0.0, -1.0, 0.0]),
            vol.ray([9.0, 3.5, -1.0], [0.0, 0.0, 1.0]),
            vol.ray([3.5, 20.0, -1.0], [0.0, 0.0, 1.0]),
            vol.ray([-1.0, 21.0, 7.5], [1.0, 0.0, 0.0]),
        ],
    ));
    groups.push(group(
        "rays through the staircase x == y: between its edge-touching voxels (grazing) and into them",
        vec![
            vol.ray([-1.0, 1.0, 20.5], [1.0, -1.0, 0.0]),
            vol.ray([3.0, 5.0, 20.5], [1.0, -1.0, 0.0]),
            vol.ray([12.0, 12.0, 20.5], [1.0, -1.0, 0.0]),
            vol.ray([12.5, 11.5, 20.5], [1.0, -1.0, 0.0]),
            vol.ray([30.0, 0.0, 24.5], [-1.0, 1.0, 0.0]),
            vol.ray([4.0, 5.0, 33.0], [0.0, 0.0, -1.0]),
            vol.ray([5.0, 5.0, 33.0], [0.0, 0.0, -1.0]),
            vol.ray([-1.0, -1.0, 18.0], [1.0, 1.0, 0.0]),
        ],
    ));
    groups.push(group(
        "oblique rays through the one-voxel walls (no leaks at shallow angles)",
        (0..12)
            .map(|i| {
                let a = f64::from(i) / 12.0;
                vol.ray(
                    [-1.0, 2.0 + a, 3.0 + 0.5 * a],
                    [1.0, 0.03 * (a + 0.1), 0.05],
                )
            })
            .collect(),
    ));
    vol.case(
        "walls-d5",
        "one-voxel-thin walls: a full plane, a half plane and an edge-connected staircase",
        groups,
    )
}

fn random_cases() -> Vec<TraceCase> {
    let mut cases = Vec::new();
    /// Name, description, depth, density, root cube, attribute kind, ray count.
    type Spec = (
        &'static str,
        &'static str,
        u8,
        f64,
        Option<([f64; 3], f64)>,
        AttributeKind,
        usize,
    );
    let specs: [Spec; 4] = [
        (
            "random-sparse-d6",
            "random voxels, 3% dense, depth 6",
            6,
            0.03,
            None,
            AttributeKind::VoxelCount,
            300,
        ),
        (
            "random-dense-d5",
            "random voxels, 50% dense, depth 5",
            5,
            0.5,
            None,
            AttributeKind::VoxelCount,
            300,
        ),
        (
            "random-offset-root-d6",
            "random voxels, 10% dense, depth 6, root cube at (-12.5, 3.25, 100) of size 7.5",
            6,
            0.1,
            Some(([-12.5, 3.25, 100.0], 7.5)),
            AttributeKind::VoxelCount,
            300,
        ),
        (
            "random-kind0-d5",
            "random voxels, 20% dense, depth 5, attribute kind 0",
            5,
            0.2,
            None,
            AttributeKind::None,
            200,
        ),
    ];
    for (name, description, depth, density, root, kind, count) in specs {
        let mut rng = Rng::new(seed_of(name));
        let n = 1u32 << depth;
        let mut voxels = Vec::new();
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    if rng.chance(density) {
                        voxels.push([x, y, z]);
                    }
                }
            }
        }
        let mut vol = Volume::new(depth, voxels).kind(kind);
        if let Some((min, size)) = root {
            vol = vol.root(min, size);
        }
        let rays = random_rays(&vol, &mut rng, count);
        let snapped = snapped_rays(&vol, &mut rng, count / 3);
        let far = far_rays(&vol, &mut rng, count / 10);
        let nearly = nearly_axis_rays(&vol, &mut rng, count / 10);
        cases.push(vol.case(
            name,
            description,
            vec![
                group("random rays: from outside aimed inside, from inside, random segments and lengths", rays),
                group("tie-prone rays: lattice and half-lattice origins, small integer directions", snapped),
                group("far-away origins (10 to 10^4 volume sizes away) aimed at the volume", far),
                group("nearly axis-aligned directions (other components 1e-7 to 1e-30 of the main one)", nearly),
            ],
        ));
    }

    // Solid blobs (balls and boxes) for level of detail.
    let mut rng = Rng::new(seed_of("lod-blobs-d6"));
    let mut shapes = Vec::new();
    for _ in 0..6 {
        let c = [
            rng.range(8.0, 56.0),
            rng.range(8.0, 56.0),
            rng.range(8.0, 56.0),
        ];
        let r = rng.range(3.0, 12.0);
        shapes.push((c, r, rng.chance(0.5)));
    }
    let vol = Volume::from_fn(6, |x, y, z| {
        let p = [x, y, z].map(|v| f64::from(v) + 0.5);
        shapes.iter().any(|&(c, r, ball)| {
            let d = [0, 1, 2].map(|k| (p[k] - c[k]).abs());
            if ball {
                d.iter().map(|v| v * v).sum::<f64>() <= r * r
            } else {
                d.iter().all(|&v| v <= r * 0.8)
            }
        })
    });
    let base = random_rays(&vol, &mut rng, 48);
    let mut groups = vec![group("random rays at full depth", base.clone())];
    groups.push(coarser_levels(&vol, &base, 1..=6));
    groups.push(group(
        "tie-prone rays at level 4",
        snapped_rays(&vol, &mut rng, 40)
            .into_iter()
            .map(|r| lod(r, 4))
            .collect(),
    ));
    cases.push(vol.case(
        "lod-blobs-d6",
        "solid balls and boxes, depth 6, traced at every level of detail",
        groups,
    ));
    cases
}

fn mesh_cases() -> Vec<TraceCase> {
    let mut cases = Vec::new();
    let depth = 6u8;
    let meshes = [
        (
            "mesh-sphere-d6",
            "a conservatively voxelized UV sphere (hollow shell), depth 6",
            Mesh::sphere([31.3, 32.6, 30.9], 25.0, 24, 48),
        ),
        (
            "mesh-torus-d6",
            "a conservatively voxelized torus (hollow shell), depth 6",
            Mesh::torus([32.2, 31.7, 32.9], 20.0, 7.0, 48, 16),
        ),
    ];
    for (name, description, mesh) in meshes {
        let mut rng = Rng::new(seed_of(name));
        // The mesh lives in a world cube of size 2 around the origin, as a converter would place it.
        let vol = Volume::new(depth, mesh.voxelize(depth)).root([-1.0, -1.0, -1.0], 2.0);
        let n = vol.n();
        let mut towards = Vec::new();
        for _ in 0..60 {
            let dir = rng.direction();
            let o = [0, 1, 2].map(|k| n / 2.0 - dir[k] * n);
            let jitter = [
                rng.range(-6.0, 6.0),
                rng.range(-6.0, 6.0),
                rng.range(-6.0, 6.0),
            ];
            towards.push(vol.ray(o, [0, 1, 2].map(|k| dir[k] * n / 2.0 + jitter[k] / 4.0)));
        }
        let from_inside: Vec<Ray> = (0..30)
            .map(|_| {
                vol.ray(
                    [
                        n / 2.0 + rng.range(-3.0, 3.0),
                        n / 2.0 + 0.25,
                        n / 2.0 - 0.75,
                    ],
                    rng.direction(),
                )
            })
            .collect();
        let random = random_rays(&vol, &mut rng, 60);
        let coarse = coarser_levels(&vol, &towards[..12], [2u8, 4, 5].into_iter());
        cases.push(vol.case(
            name,
            description,
            vec![
                group("rays from all around aimed at the centre", towards),
                group("rays from inside the shell outwards", from_inside),
                group("random rays", random),
                coarse,
            ],
        ));
    }
    cases
}

/// A full depth-9 volume: 2^27 voxels, so the root and level-1 counts are
/// saturated (0xFFFFFF) and indices past the first octant need the children's
/// counts summed.
fn saturated_case() -> TraceCase {
    let depth = 9u8;
    let mut builder = DagBuilder::new(depth, AttributeKind::VoxelCount).expect("depth 9");
    for brick in 0..1u64 << (3 * (depth - 2)) {
        builder
            .push_brick(brick, u64::MAX)
            .expect("increasing bricks");
    }
    let file = builder.finish().expect("small DAG").to_bytes();
    let vol = Volume {
        depth,
        kind: AttributeKind::VoxelCount,
        root_min: [0.0; 3],
        root_size: 1.0,
        voxels: Vec::new(),
    };
    let mut rng = Rng::new(seed_of("saturated-full-d9"));
    let n = vol.n();
    let mut rays = Vec::new();
    for level in [2u8, 3, 5] {
        let s = (1u64 << (depth - level)) as f64;
        for _ in 0..8 {
            let o = [rng.range(0.0, n), rng.range(0.0, n), rng.range(0.0, n)];
            rays.push(lod(vol.ray(o, rng.direction()), level));
        }
        for axis in 0..3 {
            rays.push(lod(
                vol.ray(
                    on_axis(axis, n + 1.0, n - s / 2.0, n / 2.0 + s / 2.0),
                    unit(axis, -1.0),
                ),
                level,
            ));
        }
    }
    TraceCase {
        name: "saturated-full-d9".into(),
        description: "a full depth-9 volume (2^27 voxels): saturated counts at levels 0 and 1, traced at levels 2, 3, 5".into(),
        file,
        voxels: None,
        groups: vec![group("rays from inside and from the far corner, at levels 2, 3 and 5", rays)],
        reject_batch: false,
    }
}

/// Valid files laid out differently from the builder's: nodes of every level
/// in reverse order, and a file whose subtrees are not deduplicated.
fn relayout_cases() -> Vec<TraceCase> {
    let mut rng = Rng::new(seed_of("relayout"));
    let vol = Volume::from_fn(5, |x, y, z| {
        let h = (x * 7 + y * 13 + z * 5) % 11;
        h < 3 || (x / 4 + y / 4) % 3 == 0 && z < 20
    });
    let model = DagModel::decode(&vol.build()).expect("builder output decodes");
    let mut reversed = model.clone();
    reverse_levels(&mut reversed);
    let mut undeduplicated = model.clone();
    expand_shared(&mut undeduplicated);
    let rays = random_rays(&vol, &mut rng, 120);
    let snapped = snapped_rays(&vol, &mut rng, 40);
    let groups = vec![
        group("random rays", rays),
        group(
            "tie-prone rays: lattice and half-lattice origins, small integer directions",
            snapped,
        ),
    ];
    vec![
        TraceCase {
            name: "reordered-d5".into(),
            description: "nodes of every level stored in reverse order (node order is free)".into(),
            file: reversed.encode(),
            voxels: Some(vol.voxels.clone()),
            groups: groups.clone(),
            reject_batch: false,
        },
        TraceCase {
            name: "undeduplicated-d5".into(),
            description:
                "identical subtrees stored once per parent reference (deduplication is optional)"
                    .into(),
            file: undeduplicated.encode(),
            voxels: Some(vol.voxels.clone()),
            groups,
            reject_batch: false,
        },
    ]
}

/// Stores the nodes of every level in reverse order.
pub fn reverse_levels(model: &mut DagModel) {
    let leaf_level = model.levels.len();
    let leaf_count = model.leaves.len() as u32;
    model.leaves.reverse();
    for l in 0..leaf_level {
        let child_count = if l + 1 == leaf_level {
            leaf_count
        } else {
            model.levels[l + 1].len() as u32
        };
        for node in &mut model.levels[l] {
            for c in &mut node.children {
                *c = child_count - 1 - *c;
            }
        }
        model.levels[l].reverse();
    }
}

/// Turns the DAG into a tree below level 1: every reference gets its own copy
/// of the child (only levels where that stays small are expanded).
pub fn expand_shared(model: &mut DagModel) {
    let leaf_level = model.levels.len();
    for l in 0..leaf_level {
        let mut next_nodes = Vec::new();
        let mut next_leaves = Vec::new();
        let below = model.levels.get(l + 1).cloned().unwrap_or_default();
        for node in &mut model.levels[l] {
            for c in &mut node.children {
                if l + 1 == leaf_level {
                    next_leaves.push(model.leaves[*c as usize]);
                    *c = next_leaves.len() as u32 - 1;
                } else {
                    next_nodes.push(below[*c as usize].clone());
                    *c = next_nodes.len() as u32 - 1;
                }
            }
        }
        if l + 1 == leaf_level {
            model.leaves = next_leaves;
        } else {
            model.levels[l + 1] = next_nodes;
        }
    }
}
