//! `dagtool verify MESH.obj FILE.vdag`: checks a conversion by casting the same
//! rays at the source mesh (obvhs CWBVH, exact `f64` triangle tests) and at the
//! DAG (the `dagtrace` CPU tracer).
//!
//! The criteria follow from what a conservative voxelization guarantees. Let
//! `S` be the mesh surface, `U` the union of the set voxels and `v` the voxel
//! edge, and `r = √3·v` the voxel diagonal. Every voxel that touches `S` is set,
//! so `S ⊆ U`; every set voxel touches `S`, so every point of `U` lies within
//! `r` of `S`. Along a ray this gives:
//!
//! 1. a ray that hits the mesh hits the DAG, no later: `t_dag ≤ t_mesh`;
//! 2. the DAG's hit point lies within `r` of the mesh;
//! 3. a ray that misses the mesh and stays farther than `r` from it misses the DAG;
//! 4. a ray that meets the surface at incidence θ (from the normal) and does not
//!    come within `r` of the surface before the last `r / cos θ` of its way to
//!    the hit (the stretch in which any ray is within `r` of a flat surface)
//!    enters the DAG in that stretch: `(t_mesh − t_dag)·cos θ ≤ r`.
//!
//! The command reports agreement over rays that are not *near misses* (3 decides
//! them; mesh hits always count, 1 decides them), the distribution of
//! `|t_dag − t_mesh|` over *clean* hits (4 holds, incidence at most 75°), and
//! checks 1, 2 and 4 with an allowance for rounding. See the README section
//! "Verifying a conversion".

use std::path::PathBuf;
use std::time::{Duration, Instant};

use dagfmt::AnyDag;
use dagfmt::batch::Ray;
use dagtrace::Tracer;
use dagtrace::camera::Camera;
use glam::{DVec3, Vec3A};
use obvhs::BvhBuildParams;
use obvhs::aabb::Aabb;
use obvhs::cwbvh::CwBvh;
use obvhs::cwbvh::builder::build_cwbvh;
use obvhs::ray::RayHit;
use rayon::prelude::*;

use crate::cmd::FileBytes;
use crate::error::ConvertError;
use crate::mesh::{GridMapping, Mesh};

/// The long help of `dagtool verify`: the rays and the criteria.
pub const HELP: &str = "\
RAYS
  Half of --rays are random rays through the root cube (from random points of
  the sphere of radius root_size around its centre towards uniformly random
  points inside it), half are camera rays: square 40-degree pinhole images of
  the mesh from 6 random directions. The same f32 rays (world space, which is
  the mesh's coordinate space: the header's root cube maps it onto the grid)
  go to the DAG (dagtrace CPU tracer, all cores) and to the mesh (obvhs CWBVH,
  exact f64 triangle tests). The first line of the report says how far the
  header's root cube is from where `convert` places this mesh (0 when the file
  was converted from it).

WHAT A CONSERVATIVE VOXELIZATION GUARANTEES
  Every voxel touching the surface S is set and every set voxel touches S, so
  with r = one voxel diagonal (sqrt 3 voxels):
    - a ray that hits the mesh hits the DAG, no later: t_dag <= t_mesh;
    - every DAG hit point is within r of the mesh;
    - a ray that misses the mesh and stays farther than r from it misses the DAG;
    - a ray meeting the surface at incidence theta (from the normal) that does
      not come within r of the surface before the final r / cos(theta) of its
      way (the stretch where any ray is within r of a flat surface) enters the
      DAG in that stretch: (t_mesh - t_dag) * cos(theta) <= r.
  Along the ray the error |t_dag - t_mesh| is only bounded by r / cos(theta):
  a ray at 60 degrees from the normal may legitimately be 2r early.

CLASSIFICATION (by the mesh alone, exact segment/triangle distances)
  near miss      misses the mesh but passes within R of it: excluded from
                 the agreement (the DAG may hit or miss);
  hit            hits the mesh: always counts for agreement;
    grazing      incidence above 75.5 degrees (cos < 0.25): not in the
                 error statistics;
    near approach comes within R of the surface before t_mesh - R / cos:
                 not in the error statistics;
    clean        the others: |t_dag - t_mesh| and the depth error
                 (t_mesh - t_dag) * cos are reported over these (voxels).
  R = r + an allowance for rounding (printed): 0.05 voxels plus four times
  the f32 tracer tolerance of spec section 20.8.

CRITERIA (exit status 1 when one fails)
  agreement                hit/miss agreement >= 99.9 % over all rays but
                           near misses;
  no-late-hits             no hit-hit ray with t_dag > t_mesh + allowance;
  hit-points-near-surface  every DAG hit point within R of the mesh;
  depth-error              (t_mesh - t_dag) * cos <= R on every clean hit.
  Meshes with holes or open boundaries still satisfy them: the guarantees do
  not need a closed surface (only --solid fills do, and they only add voxels
  behind the surface, which rays from outside do not see first).";

/// Required agreement, in percent, over the rays that are not near misses.
pub const MIN_AGREEMENT_PERCENT: f64 = 99.9;

/// Hits whose incidence is farther than this from the surface normal
/// (cos θ below it, θ > 75.5°) are *grazing*: they count for agreement but
/// not for the error statistics, where `|Δt|` can reach `r / cos θ`.
pub const GRAZING_COS: f64 = 0.25;

/// Most rays one run may cast (about 150 bytes of memory each).
pub const MAX_RAYS: usize = 50_000_000;

/// Number of camera viewpoints.
pub const CAMERA_VIEWS: usize = 6;

/// What to verify and how many rays to cast.
#[derive(Clone, Debug)]
pub struct VerifyOptions {
    /// The source mesh (any mesh format of [`crate::input`]) or point cloud.
    pub mesh: PathBuf,
    /// The `.vdag` (or `.vdag.zst`) file converted from it.
    pub dag: PathBuf,
    /// Total number of rays: half random rays through the root cube, half
    /// camera rays from [`CAMERA_VIEWS`] viewpoints.
    pub rays: usize,
    /// Seed of the random rays and of the camera viewpoints.
    pub seed: u64,
    /// Point clouds: the splat radius the cloud was converted with.
    pub point_radius: f64,
}

/// The source of a verification: a mesh, or a point cloud.
enum Source {
    Mesh(Box<Mesh>),
    Points(Box<dyn crate::input::PointSource>),
}

/// Opens the source in whichever format it is recognised as.
fn open_source(path: &std::path::Path) -> Result<Source, ConvertError> {
    let Some(format) = crate::input::detect(path) else {
        return Err(ConvertError::Usage(format!(
            "cannot tell the format of {} from its first bytes or its extension (one of {})",
            path.display(),
            crate::input::names()
        )));
    };
    match crate::input::open(path, format, &crate::input::OpenOptions::default())? {
        crate::input::Input::Mesh(m) => Ok(Source::Mesh(m)),
        crate::input::Input::Points(p) => Ok(Source::Points(p)),
        crate::input::Input::Voxels(_) => Err(ConvertError::Usage(format!(
            "{}: verify checks meshes and point clouds, not voxel grids",
            path.display()
        ))),
    }
}

/// One pass/fail criterion.
#[derive(Clone, Debug)]
pub struct Criterion {
    /// Short name.
    pub name: &'static str,
    /// What it demands, for people.
    pub rule: String,
    /// The measured value, for people.
    pub measured: String,
    /// Whether it holds.
    pub passed: bool,
}

/// Median, 99th percentile and maximum of a sample (NaN when empty).
#[derive(Clone, Copy, Debug, Default)]
pub struct Distribution {
    /// Number of values.
    pub count: usize,
    /// Median.
    pub median: f64,
    /// 99th percentile (nearest rank).
    pub p99: f64,
    /// Maximum.
    pub max: f64,
}

impl Distribution {
    fn of(mut values: Vec<f64>) -> Self {
        if values.is_empty() {
            return Distribution {
                count: 0,
                median: f64::NAN,
                p99: f64::NAN,
                max: f64::NAN,
            };
        }
        values.sort_by(f64::total_cmp);
        let n = values.len();
        let rank = |p: f64| values[((p * n as f64).ceil() as usize).clamp(1, n) - 1];
        Distribution {
            count: n,
            median: rank(0.5),
            p99: rank(0.99),
            max: values[n - 1],
        }
    }

    fn json(&self) -> serde_json::Value {
        let num = |v: f64| {
            if v.is_finite() {
                serde_json::json!(v)
            } else {
                serde_json::Value::Null
            }
        };
        serde_json::json!({
            "count": self.count,
            "median": num(self.median),
            "p99": num(self.p99),
            "max": num(self.max),
        })
    }
}

/// The outcome of [`verify`].
#[derive(Clone, Debug)]
pub struct VerifyReport {
    /// The mesh file.
    pub mesh: PathBuf,
    /// The DAG file.
    pub dag: PathBuf,
    /// Depth of the DAG.
    pub depth: u8,
    /// Voxel edge in world units.
    pub voxel: f64,
    /// Triangles of the mesh.
    pub triangles: usize,
    /// How far (in voxels) the header's root cube is from where `convert`
    /// places this mesh at this depth (0 for a file converted from it).
    pub placement_offset_voxels: f64,
    /// Random rays cast.
    pub random_rays: usize,
    /// Camera rays cast.
    pub camera_rays: usize,
    /// The allowance for rounding added to the voxel diagonal, in voxels.
    pub allowance_voxels: f64,
    /// Rays that miss the mesh but pass within a voxel diagonal of it.
    pub near_misses: usize,
    /// Rays that count for agreement.
    pub included: usize,
    /// Of those, rays where mesh and DAG agree on hit/miss.
    pub agreeing: usize,
    /// Rays that hit the mesh and miss the DAG.
    pub mesh_hit_dag_miss: usize,
    /// Rays that miss the mesh (clearly) and hit the DAG.
    pub mesh_miss_dag_hit: usize,
    /// Rays hitting both.
    pub both_hit: usize,
    /// Hit–hit rays at grazing incidence (not in the error statistics).
    pub grazing: usize,
    /// Hit–hit rays that come within a voxel diagonal of the surface before
    /// their final stretch (not in the error statistics).
    pub near_approaches: usize,
    /// `|t_dag − t_mesh|` in voxels over clean hit–hit rays.
    pub error: Distribution,
    /// `(t_mesh − t_dag)·cos θ` in voxels over clean hit–hit rays.
    pub depth_error: Distribution,
    /// Largest `t_dag − t_mesh` (voxels) over all hit–hit rays: a DAG hit behind the mesh.
    pub max_late: f64,
    /// Largest `t_mesh − t_dag` (voxels) over all hit–hit rays: a DAG hit in front of the mesh.
    pub max_early: f64,
    /// Hit–hit rays whose DAG hit is later than the mesh hit by more than the allowance.
    pub late_hits: usize,
    /// DAG hits (of any ray) farther than a voxel diagonal (plus allowance) from the mesh.
    pub far_hits: usize,
    /// The criteria.
    pub criteria: Vec<Criterion>,
    /// Seconds spent: building the BVH, tracing the mesh, tracing the DAG, classifying.
    pub seconds: [f64; 4],
}

impl VerifyReport {
    /// Whether every criterion holds.
    pub fn passed(&self) -> bool {
        self.criteria.iter().all(|c| c.passed)
    }

    /// Agreement in percent over the included rays.
    pub fn agreement_percent(&self) -> f64 {
        if self.included == 0 {
            100.0
        } else {
            100.0 * self.agreeing as f64 / self.included as f64
        }
    }

    /// The human report.
    pub fn render(&self) -> String {
        let total = self.random_rays + self.camera_rays;
        let pct = |n: usize, of: usize| 100.0 * n as f64 / of.max(1) as f64;
        let mut s = String::new();
        s += &format!(
            "mesh {} ({} triangles) vs {} (depth {}, voxel {:.6e})\n",
            self.mesh.display(),
            self.triangles,
            self.dag.display(),
            self.depth,
            self.voxel
        );
        s += &format!(
            "placement: header root cube is {:.3} voxels from the converter's placement of this mesh\n",
            self.placement_offset_voxels
        );
        s += &format!(
            "rays: {total} ({} random through the cube, {} camera from {CAMERA_VIEWS} views); \
             allowance for rounding {:.3} voxels\n",
            self.random_rays, self.camera_rays, self.allowance_voxels
        );
        s += &format!(
            "excluded from agreement: {} near misses ({:.3}%: miss the mesh within a voxel diagonal)\n",
            self.near_misses,
            pct(self.near_misses, total)
        );
        s += &format!(
            "agreement: {:.4}% of {} rays ({} hit mesh but not DAG, {} miss mesh but hit DAG)\n",
            self.agreement_percent(),
            self.included,
            self.mesh_hit_dag_miss,
            self.mesh_miss_dag_hit
        );
        s += &format!(
            "hit both: {}; clean {} ({} grazing, {} near approaches excluded from the error statistics)\n",
            self.both_hit, self.error.count, self.grazing, self.near_approaches
        );
        s += &format!(
            "|t_dag - t_mesh| (voxels, clean hits): median {:.3}, p99 {:.3}, max {:.3}\n",
            self.error.median, self.error.p99, self.error.max
        );
        s += &format!(
            "depth (t_mesh - t_dag)*cos (voxels, clean hits): median {:.3}, p99 {:.3}, max {:.3}\n",
            self.depth_error.median, self.depth_error.p99, self.depth_error.max
        );
        s += &format!(
            "signed, all hit-hit rays: DAG up to {:.3} voxels in front of the mesh, {:.4} behind\n",
            self.max_early, self.max_late
        );
        s += &format!(
            "time: BVH {:.2} s, mesh rays {:.2} s, DAG rays {:.2} s, classification {:.2} s\n",
            self.seconds[0], self.seconds[1], self.seconds[2], self.seconds[3]
        );
        for c in &self.criteria {
            s += &format!(
                "{} {}: {} (measured {})\n",
                if c.passed { "PASS" } else { "FAIL" },
                c.name,
                c.rule,
                c.measured
            );
        }
        s += if self.passed() {
            "verify: PASS"
        } else {
            "verify: FAIL"
        };
        s
    }

    /// The JSON report.
    pub fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "mesh": self.mesh.display().to_string(),
            "dag": self.dag.display().to_string(),
            "depth": self.depth,
            "voxel": self.voxel,
            "triangles": self.triangles,
            "placement_offset_voxels": self.placement_offset_voxels,
            "rays": {
                "total": self.random_rays + self.camera_rays,
                "random": self.random_rays,
                "camera": self.camera_rays,
            },
            "allowance_voxels": self.allowance_voxels,
            "near_misses": self.near_misses,
            "agreement": {
                "included": self.included,
                "agreeing": self.agreeing,
                "percent": self.agreement_percent(),
                "mesh_hit_dag_miss": self.mesh_hit_dag_miss,
                "mesh_miss_dag_hit": self.mesh_miss_dag_hit,
            },
            "hits": {
                "both": self.both_hit,
                "clean": self.error.count,
                "grazing": self.grazing,
                "near_approaches": self.near_approaches,
            },
            "error_voxels": self.error.json(),
            "depth_error_voxels": self.depth_error.json(),
            "max_late_voxels": finite_or_null(self.max_late),
            "max_early_voxels": finite_or_null(self.max_early),
            "late_hits": self.late_hits,
            "far_hits": self.far_hits,
            "criteria": self.criteria.iter().map(|c| serde_json::json!({
                "name": c.name,
                "rule": c.rule,
                "measured": c.measured,
                "passed": c.passed,
            })).collect::<Vec<_>>(),
            "seconds": {
                "bvh": self.seconds[0],
                "mesh_rays": self.seconds[1],
                "dag_rays": self.seconds[2],
                "classification": self.seconds[3],
            },
            "passed": self.passed(),
        })
    }
}

fn finite_or_null(v: f64) -> serde_json::Value {
    if v.is_finite() {
        serde_json::json!(v)
    } else {
        serde_json::Value::Null
    }
}

/// splitmix64: a small, seedable generator (the rays must be reproducible).
#[derive(Debug)]
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform on the unit sphere.
    fn direction(&mut self) -> DVec3 {
        let (u, phi) = (self.unit() * 2.0 - 1.0, self.unit() * std::f64::consts::TAU);
        let s = (1.0 - u * u).sqrt();
        DVec3::new(s * phi.cos(), s * phi.sin(), u)
    }
}

/// Rays from random points of the sphere of radius `root_size` around the
/// cube's centre towards uniformly random points of the cube (unit directions).
fn random_rays(rng: &mut Rng, root_min: DVec3, root_size: f64, count: usize) -> Vec<Ray> {
    let center = root_min + DVec3::splat(root_size * 0.5);
    (0..count)
        .map(|_| {
            let origin = center + rng.direction() * root_size;
            let target = root_min + DVec3::new(rng.unit(), rng.unit(), rng.unit()) * root_size;
            Ray::new(
                origin.as_vec3().to_array(),
                (target - origin).normalize().as_vec3().to_array(),
            )
        })
        .collect()
}

/// `views` square pinhole images (40° field of view) of the box `[min, max]`
/// from random directions, each framing the box's bounding sphere, with about
/// `count` rays in all.
fn camera_rays(
    rng: &mut Rng,
    min: DVec3,
    max: DVec3,
    count: usize,
    views: usize,
) -> Result<Vec<Ray>, ConvertError> {
    let side = ((count / views.max(1)) as f64).sqrt() as u32;
    if side == 0 {
        return Ok(Vec::new());
    }
    let center = (min + max) * 0.5;
    let radius = ((max - min).length() * 0.5).max(f64::MIN_POSITIVE);
    let fov_y_degrees = 40.0f64;
    let distance = radius / (fov_y_degrees.to_radians() * 0.5).sin() * 1.05;
    let mut rays = Vec::with_capacity((side * side) as usize * views);
    for _ in 0..views {
        let camera = Camera {
            position: (center + rng.direction() * distance).to_array(),
            look_at: center.to_array(),
            up: [0.0, 1.0, 0.0],
            fov_y_degrees,
        };
        let frame = camera
            .frame()
            .map_err(|e| ConvertError::Input(format!("cannot place a camera: {e}")))?;
        rays.extend(frame.rays(side, side, None));
    }
    Ok(rays)
}

/// The mesh in `f64` with two BVHs over it: `thin` (triangle boxes) for
/// closest hits and `fat` (boxes grown by the search radius) for "is any
/// triangle within distance R" queries.
struct MeshQuery {
    /// Triangles in the order of the mesh.
    triangles: Vec<[DVec3; 3]>,
    /// Unit normals (zero for zero-area triangles).
    normals: Vec<DVec3>,
    thin: CwBvh,
    fat: CwBvh,
    /// World-space radius of the proximity queries.
    radius: f64,
}

fn aabb_of(t: &[DVec3; 3], grow: f64) -> Aabb {
    let lo = t[0].min(t[1]).min(t[2]) - DVec3::splat(grow);
    let hi = t[0].max(t[1]).max(t[2]) + DVec3::splat(grow);
    // Round outwards to f32.
    let down = |v: f64| {
        let f = v as f32;
        if f64::from(f) > v { f.next_down() } else { f }
    };
    let up = |v: f64| {
        let f = v as f32;
        if f64::from(f) < v { f.next_up() } else { f }
    };
    Aabb::new(
        Vec3A::new(down(lo.x), down(lo.y), down(lo.z)),
        Vec3A::new(up(hi.x), up(hi.y), up(hi.z)),
    )
}

impl MeshQuery {
    fn new(mesh: &Mesh, radius: f64) -> Self {
        let triangles: Vec<[DVec3; 3]> = mesh
            .triangles
            .iter()
            .map(|t| t.map(|i| DVec3::from_array(mesh.vertices[i as usize])))
            .collect();
        let normals = triangles
            .iter()
            .map(|t| (t[1] - t[0]).cross(t[2] - t[0]).normalize_or_zero())
            .collect();
        // A small growth keeps f32 node tests conservative.
        let extent = triangles
            .iter()
            .flatten()
            .fold(0f64, |m, v| m.max(v.abs().max_element()));
        let slack = extent * 1e-6 + f64::from(f32::MIN_POSITIVE);
        let thin_boxes: Vec<Aabb> = triangles.iter().map(|t| aabb_of(t, slack)).collect();
        let fat_boxes: Vec<Aabb> = triangles
            .iter()
            .map(|t| aabb_of(t, radius * 1.01 + slack))
            .collect();
        let build = |boxes: &[Aabb]| {
            build_cwbvh(
                boxes,
                BvhBuildParams::medium_build(),
                &mut Duration::default(),
            )
        };
        let (thin, fat) = rayon::join(|| build(&thin_boxes), || build(&fat_boxes));
        MeshQuery {
            triangles,
            normals,
            thin,
            fat,
            radius,
        }
    }

    /// The closest hit of `ray` (over `[tmin, tmax]`): `t` and the triangle.
    fn closest_hit(&self, ray: &Ray) -> Option<(f64, usize)> {
        let o = DVec3::from_array(ray.origin.map(f64::from));
        let d = DVec3::from_array(ray.dir.map(f64::from));
        let (tmin, tmax) = (f64::from(ray.tmin), f64::from(ray.tmax));
        let mut best: Option<(f64, usize)> = None;
        let mut hit = RayHit::none();
        let bvh_ray = obvhs::ray::Ray::new(
            Vec3A::from_array(ray.origin),
            Vec3A::from_array(ray.dir),
            ray.tmin,
            ray.tmax,
        );
        self.thin.ray_traverse(bvh_ray, &mut hit, |_, id| {
            let tri = self.thin.primitive_indices[id] as usize;
            match intersect(o, d, &self.triangles[tri]) {
                Some(t) if t >= tmin && t <= tmax => {
                    if best.is_none_or(|(b, _)| t < b) {
                        best = Some((t, tri));
                    }
                    // Round up so that no node holding a slightly closer hit is culled.
                    (t as f32).next_up()
                }
                _ => f32::INFINITY,
            }
        });
        best
    }

    /// Whether some triangle lies within `self.radius` of the segment
    /// `o + t·d`, `t ∈ [t0, t1]` (a point when `t0 == t1`).
    fn near_segment(&self, ray: &Ray, t0: f64, t1: f64) -> bool {
        let o = DVec3::from_array(ray.origin.map(f64::from));
        let d = DVec3::from_array(ray.dir.map(f64::from));
        let (p, q) = (o + d * t0, o + d * t1);
        let to_f32_down = |v: f64| {
            let f = v as f32;
            if f64::from(f) > v { f.next_down() } else { f }
        };
        let to_f32_up = |v: f64| {
            let f = v as f32;
            if f64::from(f) < v { f.next_up() } else { f }
        };
        let bvh_ray = obvhs::ray::Ray::new(
            Vec3A::from_array(ray.origin),
            Vec3A::from_array(ray.dir),
            to_f32_down(t0),
            to_f32_up(t1),
        );
        let r2 = self.radius * self.radius;
        // `ray_traverse_miss` stops at the first primitive reported as hit.
        !self.fat.ray_traverse_miss(bvh_ray, |_, id| {
            let tri = self.fat.primitive_indices[id] as usize;
            if segment_triangle_within(p, q, &self.triangles[tri], self.normals[tri], r2) {
                f32::NEG_INFINITY
            } else {
                f32::INFINITY
            }
        })
    }
}

/// Möller–Trumbore in `f64`, edges included: the `t` where the line
/// `o + t·d` meets the triangle, if it does (not for zero-area triangles or
/// lines in the triangle's plane).
fn intersect(o: DVec3, d: DVec3, t: &[DVec3; 3]) -> Option<f64> {
    let e1 = t[1] - t[0];
    let e2 = t[2] - t[0];
    let p = d.cross(e2);
    let det = e1.dot(p);
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let inv = 1.0 / det;
    let s = o - t[0];
    let u = s.dot(p) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let q = s.cross(e1);
    let v = d.dot(q) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    Some(e2.dot(q) * inv)
}

/// Closest point of triangle `abc` to `p` (Ericson, Real-Time Collision
/// Detection, 5.1.5). The triangle must have a non-zero area.
fn closest_point_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(ap);
    let d2 = ac.dot(ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let d3 = ab.dot(bp);
    let d4 = ac.dot(bp);
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let d5 = ab.dot(cp);
    let d6 = ac.dot(cp);
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    a + ab * (vb * denom) + ac * (vc * denom)
}

/// Squared distance between segments `p1q1` and `p2q2` (Ericson 5.1.9;
/// either may be a point).
fn segment_segment_distance2(p1: DVec3, q1: DVec3, p2: DVec3, q2: DVec3) -> f64 {
    let d1 = q1 - p1;
    let d2 = q2 - p2;
    let r = p1 - p2;
    let a = d1.length_squared();
    let e = d2.length_squared();
    let f = d2.dot(r);
    let (s, t);
    if a <= f64::MIN_POSITIVE && e <= f64::MIN_POSITIVE {
        return r.length_squared();
    }
    if a <= f64::MIN_POSITIVE {
        s = 0.0;
        t = (f / e).clamp(0.0, 1.0);
    } else {
        let c = d1.dot(r);
        if e <= f64::MIN_POSITIVE {
            t = 0.0;
            s = (-c / a).clamp(0.0, 1.0);
        } else {
            let b = d1.dot(d2);
            let denom = a * e - b * b;
            let mut s0 = if denom > 0.0 {
                ((b * f - c * e) / denom).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let mut t0 = (b * s0 + f) / e;
            if t0 < 0.0 {
                t0 = 0.0;
                s0 = (-c / a).clamp(0.0, 1.0);
            } else if t0 > 1.0 {
                t0 = 1.0;
                s0 = ((b - c) / a).clamp(0.0, 1.0);
            }
            s = s0;
            t = t0;
        }
    }
    let c1 = p1 + d1 * s;
    let c2 = p2 + d2 * t;
    (c1 - c2).length_squared()
}

/// Whether the segment `pq` comes within `sqrt(r2)` of the closed triangle
/// `tri` (unit normal `n`, zero for a zero-area triangle). Exact up to
/// rounding: the distance between a segment and a triangle that it does not
/// cross is reached at an end of the segment or on an edge of the triangle.
fn segment_triangle_within(p: DVec3, q: DVec3, tri: &[DVec3; 3], n: DVec3, r2: f64) -> bool {
    let [a, b, c] = *tri;
    // Quick rejection with the bounding sphere around the centroid.
    let centre = (a + b + c) / 3.0;
    let rho = (a - centre)
        .length()
        .max((b - centre).length())
        .max((c - centre).length());
    let reach = r2.sqrt() + rho;
    if segment_segment_distance2(p, q, centre, centre) > reach * reach {
        return false;
    }
    if n != DVec3::ZERO {
        // Does the segment cross the triangle?
        let (dp, dq) = (n.dot(p - a), n.dot(q - a));
        if (dp <= 0.0 && dq >= 0.0) || (dp >= 0.0 && dq <= 0.0) {
            let x = if dp == dq {
                p
            } else {
                p + (q - p) * (dp / (dp - dq))
            };
            let inside = n.dot((b - a).cross(x - a)) >= 0.0
                && n.dot((c - b).cross(x - b)) >= 0.0
                && n.dot((a - c).cross(x - c)) >= 0.0;
            if inside {
                return true;
            }
        }
        for end in [p, q] {
            if (closest_point_triangle(end, a, b, c) - end).length_squared() <= r2 {
                return true;
            }
        }
    }
    [(a, b), (b, c), (c, a)]
        .iter()
        .any(|&(u, w)| segment_segment_distance2(p, q, u, w) <= r2)
}

/// Parameter range `[t0, t1]` of the ray inside the box `[lo, hi]`, if any.
fn clip_to_box(ray: &Ray, lo: DVec3, hi: DVec3) -> Option<(f64, f64)> {
    let o = DVec3::from_array(ray.origin.map(f64::from));
    let d = DVec3::from_array(ray.dir.map(f64::from));
    let (mut t0, mut t1) = (f64::from(ray.tmin), f64::from(ray.tmax));
    for i in 0..3 {
        if d[i] == 0.0 {
            if o[i] < lo[i] || o[i] > hi[i] {
                return None;
            }
            continue;
        }
        let a = (lo[i] - o[i]) / d[i];
        let b = (hi[i] - o[i]) / d[i];
        t0 = t0.max(a.min(b));
        t1 = t1.min(a.max(b));
    }
    (t0 <= t1).then_some((t0, t1))
}

/// What the mesh says about one ray.
#[derive(Clone, Copy, Debug)]
enum MeshAnswer {
    /// Misses the mesh and stays farther than R from it.
    ClearMiss,
    /// Misses the mesh within R.
    NearMiss,
    /// Hits at `t` with cosine of incidence `cos`; `clean` when the ray stays
    /// farther than R from the surface before `t − R / cos`.
    Hit { t: f64, cos: f64, clean: bool },
}

/// Verifies a conversion: see the module documentation.
pub fn verify(opts: &VerifyOptions) -> Result<VerifyReport, ConvertError> {
    match open_source(&opts.mesh)? {
        Source::Mesh(mesh) => verify_mesh(opts, *mesh),
        Source::Points(_) => Err(ConvertError::Usage(format!(
            "{} is a point cloud: use verify_points",
            opts.mesh.display()
        ))),
    }
}

fn verify_mesh(opts: &VerifyOptions, mesh: Mesh) -> Result<VerifyReport, ConvertError> {
    if !(1..=MAX_RAYS).contains(&opts.rays) {
        return Err(ConvertError::Usage(format!(
            "--rays {} is outside 1..={MAX_RAYS}",
            opts.rays
        )));
    }
    let bytes = FileBytes::open(&opts.dag)?;
    // Either format version: a 2.0 file is traced as it is (spec §23.4).
    let dag = AnyDag::open(bytes.bytes())
        .map_err(|e| ConvertError::Input(format!("{}: {e}", opts.dag.display())))?;
    let tracer = Tracer::from_any(&dag)
        .map_err(|e| ConvertError::Input(format!("{}: {e}", opts.dag.display())))?;
    let header = dag.header();
    let depth = header.depth;
    let voxel = header.root_size / (1u64 << depth) as f64;
    let root_min = DVec3::from_array(header.root_min);

    let check = mesh.check()?;
    let placement_offset_voxels = match GridMapping::fit(check.min, check.max, depth) {
        Ok(m) => {
            let dmin = (DVec3::from_array(m.root_min) - root_min)
                .abs()
                .max_element();
            dmin.max((m.root_size - header.root_size).abs()) / voxel
        }
        Err(_) => f64::INFINITY,
    };

    // Rays.
    let mut rng = Rng(opts.seed ^ 0x7665_7269_6679);
    let camera_target = opts.rays / 2;
    let mut rays = camera_rays(
        &mut rng,
        DVec3::from_array(check.min),
        DVec3::from_array(check.max),
        camera_target,
        CAMERA_VIEWS,
    )?;
    let camera_count = rays.len();
    rays.extend(random_rays(
        &mut rng,
        root_min,
        header.root_size,
        opts.rays - camera_count,
    ));

    // The allowance for rounding (voxels): snapping (2^-16 voxel), the f32
    // tracer's tolerance (spec §20.8, eps_g = 2^-12 + 2^-21·max(2^D, |o_g|)),
    // counted four times, and 0.05 voxels for the f32 ray and hit values.
    let max_origin_grid = rays
        .iter()
        .map(|r| {
            (DVec3::from_array(r.origin.map(f64::from)) - root_min)
                .abs()
                .max_element()
                / voxel
        })
        .fold((1u64 << depth) as f64, f64::max);
    let allowance = 0.05 + 4.0 * (2f64.powi(-12) + 2f64.powi(-21) * max_origin_grid);
    let diagonal = 3f64.sqrt();
    let radius_voxels = diagonal + allowance;
    let radius = radius_voxels * voxel;

    let start = Instant::now();
    let query = MeshQuery::new(&mesh, radius);
    let t_bvh = start.elapsed().as_secs_f64();

    let start = Instant::now();
    let mesh_hits: Vec<Option<(f64, usize)>> =
        rays.par_iter().map(|r| query.closest_hit(r)).collect();
    let t_mesh = start.elapsed().as_secs_f64();

    let start = Instant::now();
    let dag_hits = tracer
        .trace_batch(&rays)
        .map_err(|e| ConvertError::Input(format!("{}: {e}", opts.dag.display())))?;
    let t_dag = start.elapsed().as_secs_f64();

    // Classification (by the mesh alone) and the DAG hit points' distance.
    let start = Instant::now();
    let lo = DVec3::from_array(check.min) - DVec3::splat(2.0 * radius);
    let hi = DVec3::from_array(check.max) + DVec3::splat(2.0 * radius);
    let answers: Vec<(MeshAnswer, bool)> = rays
        .par_iter()
        .zip(mesh_hits.par_iter())
        .zip(dag_hits.par_iter())
        .map(|((ray, mesh_hit), dag_hit)| {
            let answer = match *mesh_hit {
                None => match clip_to_box(ray, lo, hi) {
                    Some((t0, t1)) if query.near_segment(ray, t0, t1) => MeshAnswer::NearMiss,
                    _ => MeshAnswer::ClearMiss,
                },
                Some((t, tri)) => {
                    let d = DVec3::from_array(ray.dir.map(f64::from));
                    let cos = (d.normalize_or_zero().dot(query.normals[tri])).abs();
                    let clean = if cos < GRAZING_COS {
                        false
                    } else {
                        // The final stretch, slightly lengthened so that a flat
                        // surface is not found at exactly R by rounding.
                        let end = t - 1.001 * radius / (cos * d.length());
                        match clip_to_box(ray, lo, hi) {
                            Some((t0, t1)) if end > t0 => !query.near_segment(ray, t0, end.min(t1)),
                            _ => true,
                        }
                    };
                    MeshAnswer::Hit { t, cos, clean }
                }
            };
            let far = dag_hit.hit && {
                let t = f64::from(dag_hit.t);
                !query.near_segment(ray, t, t)
            };
            (answer, far)
        })
        .collect();
    let t_classify = start.elapsed().as_secs_f64();

    let mut report = VerifyReport {
        mesh: opts.mesh.clone(),
        dag: opts.dag.clone(),
        depth,
        voxel,
        triangles: mesh.triangles.len(),
        placement_offset_voxels,
        random_rays: rays.len() - camera_count,
        camera_rays: camera_count,
        allowance_voxels: allowance,
        near_misses: 0,
        included: 0,
        agreeing: 0,
        mesh_hit_dag_miss: 0,
        mesh_miss_dag_hit: 0,
        both_hit: 0,
        grazing: 0,
        near_approaches: 0,
        error: Distribution::default(),
        depth_error: Distribution::default(),
        max_late: f64::NEG_INFINITY,
        max_early: f64::NEG_INFINITY,
        late_hits: 0,
        far_hits: 0,
        criteria: Vec::new(),
        seconds: [t_bvh, t_mesh, t_dag, t_classify],
    };
    let mut errors = Vec::new();
    let mut depths = Vec::new();
    let mut depth_violations = 0usize;
    for ((ray, (answer, far)), dag_hit) in rays.iter().zip(&answers).zip(&dag_hits) {
        report.far_hits += usize::from(*far);
        let scale = DVec3::from_array(ray.dir.map(f64::from)).length() / voxel;
        match *answer {
            MeshAnswer::NearMiss => report.near_misses += 1,
            MeshAnswer::ClearMiss => {
                report.included += 1;
                if dag_hit.hit {
                    report.mesh_miss_dag_hit += 1;
                } else {
                    report.agreeing += 1;
                }
            }
            MeshAnswer::Hit { t, cos, clean } => {
                report.included += 1;
                if !dag_hit.hit {
                    report.mesh_hit_dag_miss += 1;
                    continue;
                }
                report.agreeing += 1;
                report.both_hit += 1;
                let early = (t - f64::from(dag_hit.t)) * scale;
                report.max_early = report.max_early.max(early);
                report.max_late = report.max_late.max(-early);
                if -early > allowance {
                    report.late_hits += 1;
                }
                if cos < GRAZING_COS {
                    report.grazing += 1;
                } else if !clean {
                    report.near_approaches += 1;
                } else {
                    errors.push(early.abs());
                    depths.push(early * cos);
                    if early * cos > radius_voxels * 1.001 {
                        depth_violations += 1;
                    }
                }
            }
        }
    }
    report.error = Distribution::of(errors);
    report.depth_error = Distribution::of(depths);

    let agreement = report.agreement_percent();
    report.criteria = vec![
        Criterion {
            name: "agreement",
            rule: format!(
                "hit/miss agreement >= {MIN_AGREEMENT_PERCENT}% over rays that are not near misses"
            ),
            measured: format!("{agreement:.4}%"),
            passed: agreement >= MIN_AGREEMENT_PERCENT,
        },
        Criterion {
            name: "no-late-hits",
            rule: format!("no DAG hit behind the mesh hit by more than {allowance:.3} voxels"),
            measured: format!(
                "{} late, max t_dag - t_mesh {:.4} voxels",
                report.late_hits, report.max_late
            ),
            passed: report.late_hits == 0,
        },
        Criterion {
            name: "hit-points-near-surface",
            rule: format!(
                "every DAG hit point within one voxel diagonal (+{allowance:.3}) of the mesh"
            ),
            measured: format!("{} farther", report.far_hits),
            passed: report.far_hits == 0,
        },
        Criterion {
            name: "depth-error",
            rule: format!(
                "(t_mesh - t_dag)*cos <= one voxel diagonal (+{allowance:.3}) on clean hits"
            ),
            measured: format!(
                "max {:.3} voxels, {depth_violations} above",
                report.depth_error.max
            ),
            passed: depth_violations == 0,
        },
    ];
    Ok(report)
}

/// Runs `verify` and prints the report (text or JSON). Returns the exit
/// status: 0 when every criterion holds, 1 otherwise.
pub fn run(opts: &VerifyOptions, json: bool) -> Result<i32, ConvertError> {
    let report = match open_source(&opts.mesh)? {
        Source::Mesh(mesh) => verify_mesh(opts, *mesh)?,
        Source::Points(cloud) => {
            let report = crate::verify_points::verify_points(
                &opts.mesh,
                cloud,
                &opts.dag,
                opts.point_radius,
            )?;
            let text = if json {
                serde_json::to_string_pretty(&report.json())
                    .map_err(|e| ConvertError::Io(format!("cannot write the report: {e}")))?
            } else {
                report.render()
            };
            crate::output::print_stdout(&format!("{text}\n"))?;
            return Ok(if report.passed() { 0 } else { 1 });
        }
    };
    // Through `print_stdout`: a closed pipe (`dagtool verify ... | head`) ends
    // the output quietly instead of panicking.
    let text = if json {
        serde_json::to_string_pretty(&report.json())
            .map_err(|e| ConvertError::Io(format!("cannot write the report: {e}")))?
    } else {
        report.render()
    };
    crate::output::print_stdout(&format!("{text}\n"))?;
    Ok(if report.passed() { 0 } else { 1 })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn segment_triangle_distance() {
        let tri = [
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(1.0, 0.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
        ];
        let n = DVec3::Z;
        // A segment above the interior at height 0.5.
        let (p, q) = (DVec3::new(0.1, 0.1, 0.5), DVec3::new(0.3, 0.2, 0.5));
        assert!(segment_triangle_within(p, q, &tri, n, 0.26));
        assert!(!segment_triangle_within(p, q, &tri, n, 0.24));
        // Crossing the triangle.
        let (p, q) = (DVec3::new(0.2, 0.2, -1.0), DVec3::new(0.2, 0.2, 1.0));
        assert!(segment_triangle_within(p, q, &tri, n, 1e-12));
        // Passing beside the hypotenuse at distance sqrt(2)/2 * 0.5.
        let (p, q) = (DVec3::new(0.75, 0.75, -1.0), DVec3::new(0.75, 0.75, 1.0));
        let d = 0.5f64.sqrt() * 0.5;
        assert!(segment_triangle_within(p, q, &tri, n, d * d * 1.0001));
        assert!(!segment_triangle_within(p, q, &tri, n, d * d * 0.9999));
        // A zero-area triangle (a segment along x).
        let line = [DVec3::ZERO, DVec3::X, DVec3::X * 0.5];
        let (p, q) = (DVec3::new(0.5, -1.0, 0.3), DVec3::new(0.5, 1.0, 0.3));
        assert!(segment_triangle_within(p, q, &line, DVec3::ZERO, 0.0901));
        assert!(!segment_triangle_within(p, q, &line, DVec3::ZERO, 0.0899));
    }

    #[test]
    fn intersection_and_closest_point() {
        let tri = [DVec3::ZERO, DVec3::X, DVec3::Y];
        let t = intersect(DVec3::new(0.25, 0.25, 2.0), DVec3::NEG_Z, &tri);
        assert_eq!(t, Some(2.0));
        assert_eq!(
            intersect(DVec3::new(0.75, 0.75, 2.0), DVec3::NEG_Z, &tri),
            None
        );
        let c = closest_point_triangle(DVec3::new(2.0, -1.0, 3.0), tri[0], tri[1], tri[2]);
        assert_eq!(c, DVec3::X);
    }

    #[test]
    fn distribution_ranks() {
        let d = Distribution::of((1..=1000).map(f64::from).collect());
        assert_eq!((d.median, d.p99, d.max), (500.0, 990.0, 1000.0));
        assert!(Distribution::of(Vec::new()).max.is_nan());
    }
}
