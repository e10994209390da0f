//! The secondary-ray workload of a lit render (`dagtrace render --shade
//! lit`): primary, shadow and ambient-occlusion rays per second, on the CPU
//! batch tracer and, with `--mesh`, on obvhs's CWBVH over the source mesh
//! for the very same world-space rays, in one run; with `--gpu`, the GPU's
//! three lit passes (which make their rays on the GPU) on the same view.
//!
//! ```text
//! cargo run --release -p dagtrace --example lit_bench -- \
//!     dragon12.vdag --mesh ../shared/meshes/dragon.obj --gpu
//! ```
//!
//! The rays: primary rays of a WxH image (default 1024x768, one per pixel,
//! in the 8x8 tiles `render` uses) through the automatic camera; for each
//! hit, the shadow ray towards the default sun and `--ao-rays` (default 8)
//! ambient-occlusion rays of the default radius (the grid's edge / 32), from
//! 1.5 voxels above the hit (`dagtrace::lit`). dagtrace traces each set
//! with its batch API on all cores (closest hit, no attribute index); obvhs
//! traces primary rays with `ray_traverse` (closest hit) and shadow and AO
//! rays with `ray_traverse_miss` (its occlusion query, which stops at the
//! first triangle), over rayon chunks of 1024 rays. Runs alternate
//! between the tracers; every figure is the median over `--runs`, each timed
//! run right after an untimed one of the same tracer.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use clap::Parser;
use dagfmt::AnyDag;
use dagfmt::batch::Ray;
use dagfmt::mmap::MappedFile;
use dagtrace::Tracer;
use dagtrace::camera::Camera;
use dagtrace::lit::{self, LitOptions};
use glam::Vec3A;
use obvhs::BvhBuildParams;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::ray::RayHit;
use obvhs::triangle::Triangle;
use rayon::prelude::*;

#[derive(Parser, Debug)]
#[command(about = "Primary, shadow and AO rays/s of a lit render (dagtrace, obvhs, GPU)")]
struct Args {
    /// The .vdag file.
    vdag: PathBuf,
    /// The mesh it was converted from (OBJ): also time obvhs on it.
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Also time the GPU's lit passes.
    #[arg(long)]
    gpu: bool,
    /// Runs per measurement (the median is reported).
    #[arg(long, default_value_t = 5)]
    runs: usize,
    /// Image width.
    #[arg(long, default_value_t = 1024)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 768)]
    height: u32,
    /// Ambient-occlusion rays per hit.
    #[arg(long, default_value_t = 8)]
    ao_rays: u32,
}

fn main() {
    if let Err(e) = run(Args::parse()) {
        eprintln!("lit_bench: error: {e}");
        std::process::exit(1);
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Rays/s of one call of `f` tracing `rays` rays (wall clock).
fn rate(rays: usize, f: &mut dyn FnMut()) -> f64 {
    let t0 = Instant::now();
    f();
    rays as f64 / t0.elapsed().as_secs_f64().max(1e-9)
}

struct Mesh {
    bvh: obvhs::cwbvh::CwBvh,
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
        let bvh = build_cwbvh_from_tris(
            &triangles,
            BvhBuildParams::medium_build(),
            &mut Duration::default(),
        );
        let triangles = bvh
            .primitive_indices
            .iter()
            .map(|&i| triangles[i as usize])
            .collect();
        Ok(Mesh { bvh, triangles })
    }

    fn ray(ray: &Ray) -> obvhs::ray::Ray {
        obvhs::ray::Ray::new(
            Vec3A::from_array(ray.origin),
            Vec3A::from_array(ray.dir),
            ray.tmin,
            ray.tmax,
        )
    }

    /// Closest hit: whether the ray hit.
    fn closest(&self, ray: &Ray) -> bool {
        let mut hit = RayHit::none();
        self.bvh.ray_traverse(Self::ray(ray), &mut hit, |r, id| {
            self.triangles[id].intersect(r)
        })
    }

    /// Occlusion: whether the ray hit anything.
    fn occluded(&self, ray: &Ray) -> bool {
        !self
            .bvh
            .ray_traverse_miss(Self::ray(ray), |r, id| self.triangles[id].intersect(r))
    }

    /// Counts the hits of `rays` on all cores.
    fn trace_all(&self, rays: &[Ray], occlusion: bool) -> usize {
        rays.par_chunks(1024)
            .map(|chunk| {
                chunk
                    .iter()
                    .filter(|r| {
                        if occlusion {
                            self.occluded(r)
                        } else {
                            self.closest(r)
                        }
                    })
                    .count()
            })
            .sum()
    }
}

fn run(args: Args) -> Result<(), String> {
    let file = MappedFile::open(&args.vdag).map_err(|e| format!("{}: {e}", args.vdag.display()))?;
    // Either version (a 2.0 file traced through its expanded levels).
    let dag = AnyDag::open(file.bytes()).map_err(|e| format!("{}: {e}", args.vdag.display()))?;
    let tracer = Tracer::from_any(&dag)
        .map_err(|e| e.to_string())?
        .with_index(false);
    let (w, h) = (args.width, args.height);
    let aspect = f64::from(w) / f64::from(h);
    // The automatic camera, as `dagtrace render` makes it.
    let camera = match &dag {
        AnyDag::V1(d) => Camera::automatic(d, aspect),
        AnyDag::V2(d) => match tracer.occupied_box() {
            Some((lo, hi)) => Camera::looking_at_box(lo, hi, aspect),
            None => Camera::looking_at_cube(d.header().root_min, d.header().root_size, aspect),
        },
    };
    let frame = camera.frame().map_err(|e| e.to_string())?;
    let options = LitOptions {
        ao_rays: args.ao_rays,
        ..LitOptions::default()
    };
    let (primary, owners) = lit::primary_rays(&frame, w, h, 0..h, 1, None);
    let hits = tracer.trace_batch(&primary).map_err(|e| e.to_string())?;
    let (shadow, ao) = lit::secondary_rays(&tracer, &primary, &hits, &owners, None, &options)
        .map_err(|e| e.to_string())?;
    let mesh = args.mesh.as_ref().map(Mesh::load).transpose()?;
    println!(
        "{}: depth {}, {w}x{h}, {} threads, median of {} runs",
        args.vdag.display(),
        dag.header().depth,
        rayon::current_num_threads(),
        args.runs
    );
    println!(
        "rays: {} primary ({} hit), {} shadow, {} AO ({} per hit, radius {} voxels)",
        primary.len(),
        hits.iter().filter(|h| h.hit).count(),
        shadow.len(),
        ao.len(),
        args.ao_rays,
        options.ao_radius_cells(dag.header().depth)
    );
    println!(
        "{:>8}  {:>16}  {:>16}  {:>8}  {:>12}  {:>12}",
        "rays", "dagtrace Mrays/s", "obvhs Mrays/s", "x", "dag hit %", "mesh hit %"
    );
    for (name, rays, occlusion) in [
        ("primary", &primary, false),
        ("shadow", &shadow, true),
        ("AO", &ao, true),
    ] {
        if rays.is_empty() {
            continue;
        }
        let mut dag_hits = 0;
        let mut mesh_hits = 0;
        let (mut dag_rates, mut mesh_rates) = (Vec::new(), Vec::new());
        for _ in 0..args.runs.max(1) {
            let mut dag_run = || {
                dag_hits = tracer
                    .trace_batch(rays)
                    .map(|h| h.iter().filter(|h| h.hit).count())
                    .unwrap_or(0);
            };
            dag_run();
            dag_rates.push(rate(rays.len(), &mut dag_run));
            if let Some(mesh) = &mesh {
                let mut mesh_run = || mesh_hits = mesh.trace_all(rays, occlusion);
                mesh_run();
                mesh_rates.push(rate(rays.len(), &mut mesh_run));
            }
        }
        let dag_rate = median(dag_rates.clone());
        let percent = |n: usize| 100.0 * n as f64 / rays.len() as f64;
        if mesh.is_some() {
            let ratios = dag_rates
                .iter()
                .zip(&mesh_rates)
                .map(|(a, b)| a / b)
                .collect();
            println!(
                "{name:>8}  {:>16.2}  {:>16.2}  {:>7.2}x  {:>12.1}  {:>12.1}",
                dag_rate / 1e6,
                median(mesh_rates) / 1e6,
                median(ratios),
                percent(dag_hits),
                percent(mesh_hits)
            );
        } else {
            println!(
                "{name:>8}  {:>16.2}  {:>16}  {:>8}  {:>12.1}",
                dag_rate / 1e6,
                "-",
                "-",
                percent(dag_hits)
            );
        }
    }
    if args.gpu {
        gpu(&dag, &camera, w, h, &options, args.runs)?;
    }
    Ok(())
}

#[cfg(feature = "gpu")]
fn gpu(
    dag: &AnyDag<'_>,
    camera: &Camera,
    w: u32,
    h: u32,
    options: &LitOptions,
    runs: usize,
) -> Result<(), String> {
    use dagtrace::gpu::{GpuOptions, GpuTracer};
    let options_gpu = GpuOptions {
        compute_index: false,
        ..GpuOptions::default()
    };
    let gpu = match dag {
        AnyDag::V1(d) => GpuTracer::new(d, &options_gpu),
        AnyDag::V2(d) => GpuTracer::new_v2(d.header(), d.levels(), d.color_table(), &options_gpu),
    }
    .map_err(|e| e.to_string())?;
    // Compile and warm up.
    gpu.time_lit(camera, w, h, options, 1)
        .map_err(|e| e.to_string())?;
    let times = gpu
        .time_lit(camera, w, h, options, runs.max(1))
        .map_err(|e| e.to_string())?;
    let per_s = |rays: u64, d: Duration| rays as f64 / d.as_secs_f64().max(1e-9) / 1e6;
    let first = times[0];
    println!(
        "GPU {}: {} primary, {} shadow, {} AO rays per run",
        gpu.context().adapter_name(),
        first.primary_rays,
        first.shadow_rays,
        first.ao_rays
    );
    println!(
        "GPU Mrays/s: primary {:.2} (with the normals' lookups), shadow {:.2}, AO {:.2}",
        median(
            times
                .iter()
                .map(|t| per_s(t.primary_rays, t.primary))
                .collect()
        ),
        median(
            times
                .iter()
                .map(|t| per_s(t.shadow_rays, t.shadow))
                .collect()
        ),
        median(times.iter().map(|t| per_s(t.ao_rays, t.ao)).collect()),
    );
    Ok(())
}

#[cfg(not(feature = "gpu"))]
fn gpu(_: &AnyDag<'_>, _: &Camera, _: u32, _: u32, _: &LitOptions, _: usize) -> Result<(), String> {
    Err("dagtrace was built without the `gpu` feature".into())
}
