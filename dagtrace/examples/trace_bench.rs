//! Rays per second of the dagtrace CPU tracer, on one core and on all cores,
//! for 1920x1080 primary camera rays and for random rays through the cube; and,
//! with `--mesh`, obvhs's CWBVH closest-hit on the original triangle mesh with
//! the very same world-space rays.
//!
//! ```text
//! cargo run --release -p dagtrace --example trace_bench -- dragon12.vdag --mesh ../shared/meshes/dragon.obj
//! ```
//!
//! Every figure is the median of `--runs` runs. The voxel tracer runs without
//! the attribute index (closest hit: t, cell, face), like obvhs's closest hit
//! (t, triangle); `--index` adds the index.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use clap::Parser;
use dagfmt::Dag;
use dagfmt::batch::{Hit, Ray};
use dagfmt::mmap::MappedFile;
use dagtrace::Tracer;
use dagtrace::camera::Camera;
use glam::Vec3A;
use obvhs::BvhBuildParams;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::ray::RayHit;
use obvhs::triangle::Triangle;
use rayon::prelude::*;

#[derive(Parser, Debug)]
#[command(about = "Rays/s of the dagtrace CPU tracer (and obvhs CWBVH on the mesh)")]
struct Args {
    /// The .vdag file.
    vdag: PathBuf,
    /// The mesh the .vdag was converted from (OBJ): also time obvhs on it.
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Runs per measurement (the median is reported).
    #[arg(long, default_value_t = 5)]
    runs: usize,
    /// Number of random rays.
    #[arg(long, default_value_t = 1_000_000)]
    random: usize,
    /// Camera image width.
    #[arg(long, default_value_t = 1920)]
    width: u32,
    /// Camera image height.
    #[arg(long, default_value_t = 1080)]
    height: u32,
    /// Also compute the attribute index of every hit.
    #[arg(long)]
    index: bool,
}

fn main() {
    if let Err(e) = run(Args::parse()) {
        eprintln!("trace_bench: error: {e}");
        std::process::exit(1);
    }
}

fn median(mut v: Vec<Duration>) -> Duration {
    v.sort();
    v[v.len() / 2]
}

/// CPU time of the calling thread (Linux: /proc/thread-self/schedstat), so
/// that single-core figures do not count time the thread spent descheduled on a
/// busy machine. `None` where unavailable.
fn thread_cpu_time() -> Option<Duration> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    Some(Duration::from_nanos(
        s.split_whitespace().next()?.parse().ok()?,
    ))
}

/// Median wall-clock time of `runs` calls of `f`.
fn time(runs: usize, mut f: impl FnMut()) -> Duration {
    f(); // warm the caches and the page cache of the map
    median(
        (0..runs.max(1))
            .map(|_| {
                let start = Instant::now();
                f();
                start.elapsed()
            })
            .collect(),
    )
}

/// Median wall-clock and median thread CPU time of `runs` calls of `f` (the
/// CPU time is the wall-clock time where it cannot be read).
fn time_one_core(runs: usize, mut f: impl FnMut()) -> (Duration, Duration) {
    f();
    let (mut walls, mut cpus) = (Vec::new(), Vec::new());
    for _ in 0..runs.max(1) {
        let (wall, cpu) = (Instant::now(), thread_cpu_time());
        f();
        let wall = wall.elapsed();
        walls.push(wall);
        cpus.push(match (cpu, thread_cpu_time()) {
            (Some(a), Some(b)) => b.saturating_sub(a),
            _ => wall,
        });
    }
    (median(walls), median(cpus))
}

fn rate(rays: usize, d: Duration) -> String {
    format!("{:8.2} Mrays/s", rays as f64 / d.as_secs_f64() / 1e6)
}

/// splitmix64.
struct Rng(u64);

impl Rng {
    fn unit(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Rays from random points on a sphere around the cube towards random points
/// inside it (unit directions).
fn random_rays(root_min: [f64; 3], size: f64, count: usize) -> Vec<Ray> {
    let mut rng = Rng(0x7261_7973);
    let center = [0, 1, 2].map(|i| root_min[i] + size * 0.5);
    (0..count)
        .map(|_| {
            let (u, v) = (rng.unit() * 2.0 - 1.0, rng.unit() * std::f64::consts::TAU);
            let r = (1.0 - u * u).sqrt();
            let on_sphere = [r * v.cos(), r * v.sin(), u];
            let origin = [0, 1, 2].map(|i| center[i] + on_sphere[i] * size);
            let target = [0, 1, 2].map(|i| root_min[i] + rng.unit() * size);
            let d = [0, 1, 2].map(|i| target[i] - origin[i]);
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            Ray {
                origin: origin.map(|v| v as f32),
                dir: d.map(|v| (v / len) as f32),
                tmin: 0.0,
                tmax: f32::INFINITY,
                level: None,
            }
        })
        .collect()
}

struct Mesh {
    bvh: obvhs::cwbvh::CwBvh,
    /// Triangles in the BVH's primitive order (no indirection when tracing).
    triangles: Vec<Triangle>,
}

impl Mesh {
    fn load(path: &PathBuf) -> Result<Mesh, String> {
        let (models, _) = tobj::load_obj(path, &tobj::GPU_LOAD_OPTIONS)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        let mut triangles = Vec::new();
        for model in &models {
            let p = &model.mesh.positions;
            let vertex = |i: u32| {
                let i = i as usize * 3;
                Vec3A::new(p[i], p[i + 1], p[i + 2])
            };
            for t in model.mesh.indices.chunks_exact(3) {
                triangles.push(Triangle {
                    v0: vertex(t[0]),
                    v1: vertex(t[1]),
                    v2: vertex(t[2]),
                });
            }
        }
        let start = Instant::now();
        let bvh = build_cwbvh_from_tris(
            &triangles,
            BvhBuildParams::medium_build(),
            &mut Duration::default(),
        );
        println!(
            "obvhs: {} triangles, CWBVH (medium_build) built in {:.2} s",
            triangles.len(),
            start.elapsed().as_secs_f64()
        );
        let triangles = bvh
            .primitive_indices
            .iter()
            .map(|&i| triangles[i as usize])
            .collect();
        Ok(Mesh { bvh, triangles })
    }

    fn trace(&self, ray: &Ray) -> f32 {
        let r = obvhs::ray::Ray::new(
            Vec3A::from_array(ray.origin),
            Vec3A::from_array(ray.dir),
            ray.tmin,
            ray.tmax,
        );
        let mut hit = RayHit::none();
        if self
            .bvh
            .ray_traverse(r, &mut hit, |r, id| self.triangles[id].intersect(r))
        {
            hit.t
        } else {
            f32::INFINITY
        }
    }
}

fn run(args: Args) -> Result<(), String> {
    let file = MappedFile::open(&args.vdag).map_err(|e| format!("{}: {e}", args.vdag.display()))?;
    let dag = Dag::open(file.bytes()).map_err(|e| format!("{}: {e}", args.vdag.display()))?;
    let tracer = Tracer::new(&dag)
        .map_err(|e| e.to_string())?
        .with_index(args.index);
    let header = dag.header();
    println!(
        "{}: depth {}, {} voxels, {} bytes; {} threads; median of {} runs{}",
        args.vdag.display(),
        header.depth,
        header.voxel_count,
        header.file_size,
        rayon::current_num_threads(),
        args.runs,
        if args.index {
            "; with attribute index"
        } else {
            ""
        }
    );
    let camera = Camera::automatic(&dag, f64::from(args.width) / f64::from(args.height))
        .frame()
        .map_err(|e| e.to_string())?;
    let sets = [
        (
            format!("camera {}x{}", args.width, args.height),
            camera.rays(args.width, args.height, None),
        ),
        (
            format!("random {}", args.random),
            random_rays(header.root_min, header.root_size, args.random),
        ),
    ];
    let mesh = args.mesh.as_ref().map(Mesh::load).transpose()?;
    for (name, rays) in &sets {
        let mut hits = vec![Hit::MISS; rays.len()];
        let (one, one_cpu) = time_one_core(args.runs, || {
            for (ray, hit) in rays.iter().zip(hits.iter_mut()) {
                *hit = tracer.trace(ray).expect("trace");
            }
        });
        let all = time(args.runs, || {
            tracer.trace_batch_into(rays, &mut hits).expect("trace");
        });
        let hit_count = hits.iter().filter(|h| h.hit).count();
        println!(
            "{name:>22}  dagtrace  1 core {} (cpu time {})   all cores {}   ({:.1}% hit)",
            rate(rays.len(), one),
            rate(rays.len(), one_cpu),
            rate(rays.len(), all),
            100.0 * hit_count as f64 / rays.len() as f64
        );
        if let Some(mesh) = &mesh {
            let mut ts = vec![0f32; rays.len()];
            let (mesh_one, mesh_one_cpu) = time_one_core(args.runs, || {
                for (ray, t) in rays.iter().zip(ts.iter_mut()) {
                    *t = mesh.trace(ray);
                }
            });
            let mesh_all = time(args.runs, || {
                ts.par_chunks_mut(1024)
                    .zip(rays.par_chunks(1024))
                    .for_each(|(ts, rays)| {
                        for (t, ray) in ts.iter_mut().zip(rays) {
                            *t = mesh.trace(ray);
                        }
                    });
            });
            let mesh_hits = ts.iter().filter(|t| t.is_finite()).count();
            // Agreement: rays hitting both, and how far apart the hits are in voxels.
            let voxel = header.root_size / (1u64 << header.depth) as f64;
            let mut gaps: Vec<f64> = hits
                .iter()
                .zip(&ts)
                .filter(|(h, t)| h.hit && t.is_finite())
                .map(|(h, t)| (f64::from(*t) - f64::from(h.t)).abs() / voxel)
                .collect();
            gaps.sort_by(f64::total_cmp);
            let both = gaps.len();
            println!(
                "{name:>22}  obvhs     1 core {} (cpu time {})   all cores {}   ({:.1}% hit)",
                rate(rays.len(), mesh_one),
                rate(rays.len(), mesh_one_cpu),
                rate(rays.len(), mesh_all),
                100.0 * mesh_hits as f64 / rays.len() as f64
            );
            println!(
                "{name:>22}  speed-up  1 core {:6.2}x (cpu time {:6.2}x)          all cores {:6.2}x   (hit both: {both}; |t_mesh - t_voxel| median {:.2}, p99 {:.2} voxels)",
                mesh_one.as_secs_f64() / one.as_secs_f64(),
                mesh_one_cpu.as_secs_f64() / one_cpu.as_secs_f64(),
                mesh_all.as_secs_f64() / all.as_secs_f64(),
                gaps.get(both / 2).copied().unwrap_or(f64::NAN),
                gaps.get(both * 99 / 100).copied().unwrap_or(f64::NAN),
            );
        }
    }
    Ok(())
}
