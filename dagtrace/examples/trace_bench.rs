//! Rays per second of the dagtrace CPU tracer, on one core and on all cores,
//! for 1920x1080 primary camera rays and for random rays through the cube; and,
//! with `--mesh`, obvhs's CWBVH closest-hit on the original triangle mesh with
//! the very same world-space rays, in the same run.
//!
//! ```text
//! cargo run --release -p dagtrace --example trace_bench -- \
//!     dragon10.vdag dragon12.vdag dragon14.vdag --mesh ../shared/meshes/dragon.obj
//! ```
//!
//! Ray sets: `camera` (primary rays row by row), `tiles` (the same rays in
//! 8x8 pixel tiles, the order `dagtrace render` uses, in which the batch API
//! traces them as packets) and `random`.
//!
//! Measured per file and ray set, `--runs` times each, the runs of the
//! different tracers alternating so that a busy machine slows them alike,
//! and each timed run right after an untimed one of the same tracer, so that
//! each is timed in its steady state (its own data in the caches, as when it
//! traces frame after frame) rather than after the other tracer's data
//! pushed its out:
//! - `trace()`: [`Tracer::trace`] called ray by ray on one thread;
//! - `1 core`: [`Tracer::trace_sequential_into`] on one thread (several rays in
//!   flight, switching between them at every read of the DAG);
//! - `all cores`: [`Tracer::trace_batch_into`] (rayon, all threads);
//! - obvhs: `CwBvh::ray_traverse` ray by ray on one thread, and over rayon
//!   chunks of 1024 rays on all threads.
//!
//! Every figure is the median over the runs: wall-clock rays/s, the rays/s
//! in the thread's CPU time (one-thread figures; it leaves out time the thread
//! spent descheduled), and the median of the per-run ratios dagtrace / obvhs.
//! The voxel tracer runs without the attribute index (closest hit: t, cell,
//! face), like obvhs's closest hit (t, triangle); `--index` adds the index.
//!
//! `--format2` instead compares format 2.0 with 1.0 (issue 42): it reads the
//! 2.0 file of the same voxels (`--v2-file`, one 1.0 file) or makes it in
//! memory (`dagfmt::v2file::upgrade`, what `dagtool upgrade` writes; its time
//! is printed), and times the batch API of two 2.0 tracers against the 1.0
//! tracer's: through the expanded levels ([`Tracer::from_v2`], spec §23.12;
//! the time and memory of the expansion are printed) and reading the file in
//! place ([`Tracer::from_v2_in_place`]), all on one core
//! ([`Tracer::trace_sequential_into`]) and on all cores
//! ([`Tracer::trace_batch_into`]), runs alternating as above, each with the
//! lanes of `--lanes` (`both` takes the tracers' own choice); it prints the
//! medians and the median of the per-run ratios 2.0 / 1.0 of the rates, and
//! checks that all give the same answers (up to the choice among exactly
//! tied cells that packets may make, counted).
//!
//! Without `--format2` a file may be of either version
//! ([`Tracer::from_any`]; obvhs needs the mesh).
//!
//! `--gathers both` times the batch API twice in every run, its vector lanes
//! reading with the gather instruction and with scalar loads
//! ([`dagtrace::Gathers`]), and adds the median of the per-run ratios of
//! their times; `--lanes both` likewise with eight and sixteen lanes to a
//! vector ([`dagtrace::Lanes`]). For such a comparison alone, many short runs
//! without the mesh (`--only random --random 200000 --runs 101`) beat a few
//! long ones on a noisy machine.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use clap::Parser;
use dagfmt::batch::{Hit, Ray};
use dagfmt::mmap::MappedFile;
use dagfmt::{AnyDag, Dag};
use dagtrace::camera::Camera;
use dagtrace::{Gathers, Lanes, Tracer};
use glam::Vec3A;
use obvhs::BvhBuildParams;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::ray::RayHit;
use obvhs::triangle::Triangle;
use rayon::prelude::*;

#[derive(Parser, Debug)]
#[command(about = "Rays/s of the dagtrace CPU tracer (and obvhs CWBVH on the mesh)")]
struct Args {
    /// The .vdag files (e.g. one mesh converted at several depths).
    #[arg(required = true)]
    vdags: Vec<PathBuf>,
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
    /// Only the ray sets whose name starts with this (`camera`, `tiles`, `random`).
    #[arg(long)]
    only: Option<String>,
    /// Also compute the attribute index of every hit.
    #[arg(long)]
    index: bool,
    /// How the vector lanes read eight rays' words at once: `auto` (the
    /// tracer's choice for this processor), `instruction`, `loads`, or
    /// `both` (each dagtrace batch figure twice, gather instruction then
    /// scalar loads, all alternating in the same run).
    #[arg(long, value_enum, default_value_t = GatherArg::Auto)]
    gathers: GatherArg,
    /// How many rays a step of the vector lanes advances: `auto` (the
    /// tracer's choice for this processor), `eight`, `sixteen` (AVX-512,
    /// where the processor has it), or `both` (each dagtrace batch figure
    /// twice, eight lanes then sixteen, all alternating in the same run).
    #[arg(long, value_enum, default_value_t = LaneArg::Auto)]
    lanes: LaneArg,
    /// Compare the batch rate of the format 2.0 encoding of each file's
    /// voxels with the 1.0 file's (no mesh, no `trace()` figures).
    #[arg(long)]
    format2: bool,
    /// With `--format2` and one 1.0 file: the 2.0 file of the same voxels
    /// (`dagtool convert --format-version 2`), read instead of encoding it.
    #[arg(long)]
    v2_file: Option<PathBuf>,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
enum LaneArg {
    Auto,
    Eight,
    Sixteen,
    Both,
}

impl LaneArg {
    /// The lane settings to time, with their names.
    fn modes(self) -> Vec<(Lanes, &'static str)> {
        match self {
            LaneArg::Auto => vec![(Lanes::Auto, "")],
            LaneArg::Eight => vec![(Lanes::Eight, "")],
            LaneArg::Sixteen => vec![(Lanes::Sixteen, "")],
            LaneArg::Both => vec![
                (Lanes::Eight, " [eight lanes]"),
                (Lanes::Sixteen, " [sixteen lanes]"),
            ],
        }
    }
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
enum GatherArg {
    Auto,
    Instruction,
    Loads,
    Both,
}

impl GatherArg {
    /// The tracer settings to time, with their names.
    fn modes(self) -> Vec<(Gathers, &'static str)> {
        match self {
            GatherArg::Auto => vec![(Gathers::Auto, "")],
            GatherArg::Instruction => vec![(Gathers::Instruction, "")],
            GatherArg::Loads => vec![(Gathers::ScalarLoads, "")],
            GatherArg::Both => vec![
                (Gathers::Instruction, " [gather instruction]"),
                (Gathers::ScalarLoads, " [scalar loads]"),
            ],
        }
    }
}

fn main() {
    if let Err(e) = run(Args::parse()) {
        eprintln!("trace_bench: error: {e}");
        std::process::exit(1);
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
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

/// Rays/s of one call of `f` tracing `rays` rays: wall-clock and calling
/// thread's CPU time (the wall-clock rate where that cannot be read).
fn measure(rays: usize, f: &mut dyn FnMut()) -> (f64, f64) {
    let (wall, cpu) = (Instant::now(), thread_cpu_time());
    f();
    let wall = wall.elapsed();
    let cpu = match (cpu, thread_cpu_time()) {
        (Some(a), Some(b)) => b.saturating_sub(a),
        _ => wall,
    };
    let per_s = |d: Duration| rays as f64 / d.as_secs_f64().max(1e-9);
    (per_s(wall), per_s(cpu))
}

/// The rays/s of every tracer in `tracers` over `runs` alternating runs,
/// each timed call right after an untimed call of the same tracer: per
/// tracer, the wall-clock and CPU-time rates of each run.
fn alternate(
    runs: usize,
    rays: usize,
    tracers: &mut [&mut dyn FnMut()],
) -> Vec<(Vec<f64>, Vec<f64>)> {
    let mut rates = vec![(Vec::new(), Vec::new()); tracers.len()];
    for _ in 0..runs.max(1) {
        for (f, (walls, cpus)) in tracers.iter_mut().zip(&mut rates) {
            // Without this, the all-cores runs of dagtrace came right after
            // obvhs's (whose BVH and triangles evict most of a d12 DAG from
            // a 32 MB L3) while its one-core runs came after its own
            // `trace()` runs: d12 random rays on two cores 0.75–0.92 of the
            // warm rate on machine D, obvhs 0.94–0.95.
            f();
            let (wall, cpu) = measure(rays, *f);
            walls.push(wall);
            cpus.push(cpu);
        }
    }
    rates
}

/// [`Tracer::trace_sequential_into`] or [`Tracer::trace_batch_into`].
type BatchApi<'t> = fn(&Tracer<'t>, &[Ray], &mut [Hit]) -> Result<(), dagtrace::TraceError>;

/// Per tracer setting, a call of `trace` (a batch API) that traces `rays`
/// into that setting's own hits (compared with `trace()`'s afterwards).
fn per_setting<'a, 't: 'a>(
    tracers: &'a [(Tracer<'t>, String)],
    rays: &'a [Ray],
    hits: &'a mut [Vec<Hit>],
    trace: BatchApi<'t>,
) -> Vec<impl FnMut() + 'a> {
    tracers
        .iter()
        .zip(hits.iter_mut())
        .map(move |((tracer, _), hits)| {
            move || {
                if let Err(e) = trace(tracer, rays, hits) {
                    eprintln!("trace_bench: {e}");
                }
            }
        })
        .collect()
}

/// Median of the per-run ratios `a[i] / b[i]`.
fn ratio(a: &[f64], b: &[f64]) -> f64 {
    median(a.iter().zip(b).map(|(a, b)| a / b).collect())
}

fn mrays(v: f64) -> String {
    format!("{:7.2}", v / 1e6)
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
    let mesh = args.mesh.as_ref().map(Mesh::load).transpose()?;
    println!(
        "{} threads; median of {} runs; Mrays/s (wall-clock / thread CPU time); x = dagtrace / obvhs (median of per-run ratios){}",
        rayon::current_num_threads(),
        args.runs,
        if args.index {
            "; with attribute index"
        } else {
            ""
        }
    );
    for path in &args.vdags {
        if args.format2 {
            bench_versions(&args, path)?;
        } else {
            bench_file(&args, path, mesh.as_ref())?;
        }
    }
    Ok(())
}

/// The automatic camera of a file of either version (`tracer` is its
/// tracer), as `dagtrace render` makes it.
fn automatic_camera(dag: &AnyDag<'_>, tracer: &Tracer<'_>, aspect: f64) -> Camera {
    match dag {
        AnyDag::V1(d) => Camera::automatic(d, aspect),
        AnyDag::V2(d) => match tracer.occupied_box() {
            Some((lo, hi)) => Camera::looking_at_box(lo, hi, aspect),
            None => Camera::looking_at_cube(d.header().root_min, d.header().root_size, aspect),
        },
    }
}

/// The ray sets of `dag` (whose tracer is `tracer`) that `args` asks for:
/// camera rays row by row, in tiles, random rays.
fn ray_sets(
    args: &Args,
    dag: &AnyDag<'_>,
    tracer: &Tracer<'_>,
) -> Result<Vec<(String, Vec<Ray>)>, String> {
    let header = dag.header();
    let aspect = f64::from(args.width) / f64::from(args.height);
    let camera = automatic_camera(dag, tracer, aspect)
        .frame()
        .map_err(|e| e.to_string())?;
    let sets = [
        (
            format!("camera {}x{}", args.width, args.height),
            camera.rays(args.width, args.height, None),
        ),
        (
            // The same rays in 8x8 pixel tiles, as `dagtrace render` traces
            // them (both tracers get this order).
            format!("tiles {}x{}", args.width, args.height),
            camera.rays_in_tiles(args.width, args.height, None).0,
        ),
        (
            format!("random {}", args.random),
            random_rays(header.root_min, header.root_size, args.random),
        ),
    ];
    Ok(sets
        .into_iter()
        .filter(|(name, _)| {
            args.only
                .as_ref()
                .is_none_or(|only| name.starts_with(only.as_str()))
        })
        .collect())
}

/// `--format2`: the batch rates of the 2.0 encoding of `path`'s voxels and
/// of the 1.0 file, alternating, with their per-run ratios.
fn bench_versions(args: &Args, path: &Path) -> Result<(), String> {
    let file = MappedFile::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let dag = Dag::open(file.bytes()).map_err(|e| format!("{}: {e}", path.display()))?;
    let start = Instant::now();
    // The whole 2.0 file, as a tracer reads it: its sections in one buffer.
    let (mapped, owned);
    let (v2_bytes, made): (&[u8], &str) = match &args.v2_file {
        Some(p) => {
            mapped = MappedFile::open(p).map_err(|e| format!("{}: {e}", p.display()))?;
            (mapped.bytes(), "read")
        }
        None => {
            owned =
                dagfmt::v2file::upgrade(&dag).map_err(|e| format!("{}: {e}", path.display()))?;
            (&owned, "encoded")
        }
    };
    let encode_s = start.elapsed().as_secs_f64();
    let dag2 = dagfmt::Dag2::open(v2_bytes).map_err(|e| format!("2.0 file: {e}"))?;
    if dag2.header().voxel_count != dag.header().voxel_count {
        return Err("the 2.0 file holds other voxels than the 1.0 file".to_string());
    }
    let v2_bytes: usize = dag2.levels().iter().map(|l| l.bytes.len()).sum();
    let lanes = args.lanes.modes()[0].0;
    let lanes = if args.lanes == LaneArg::Both {
        Lanes::Auto
    } else {
        lanes
    };
    let v1 = Tracer::new(&dag)
        .map_err(|e| e.to_string())?
        .with_index(args.index)
        .with_lanes(lanes);
    // The expansion's time: the expanded tracer's making less the in-place
    // one's (which builds the record starts), medians of three.
    let mut making = [Vec::new(), Vec::new()];
    for _ in 0..3 {
        for (k, expand) in [true, false].into_iter().enumerate() {
            let start = Instant::now();
            let t = if expand {
                Tracer::from_v2(&dag2)
            } else {
                Tracer::from_v2_in_place(&dag2)
            };
            making[k].push(start.elapsed().as_secs_f64());
            drop(t);
        }
    }
    let [made_expanded, made_in_place] = making.map(median);
    let v2 = Tracer::from_v2(&dag2)
        .map_err(|e| e.to_string())?
        .with_index(args.index)
        .with_lanes(lanes);
    let v2_in_place = Tracer::from_v2_in_place(&dag2)
        .map_err(|e| e.to_string())?
        .with_index(args.index)
        .with_lanes(lanes);
    if !v2.is_expanded() {
        return Err("the 2.0 file's levels do not expand".to_string());
    }
    let header = dag.header();
    let v1_bytes: usize = dag.levels().iter().map(|l| l.bytes.len()).sum();
    let v1_file = header.file_size;
    let v2_file = dag2.header().file_size;
    let expanded = v2.expanded_bytes();
    println!(
        "{}: depth {}, {} voxels; level bytes 1.0 {v1_bytes}, 2.0 {v2_bytes} ({:.3}x; {made} in {encode_s:.1} s); lanes {:?}",
        path.display(),
        header.depth,
        header.voxel_count,
        v2_bytes as f64 / v1_bytes as f64,
        v1.lanes(),
    );
    println!(
        "  expansion: {:.1} ms (tracer made in {:.1} ms expanded, {:.1} ms in place), {:.1} MB held = {:.3}x the 1.0 file ({:.1} MB), {:.3}x the 2.0 file ({:.1} MB)",
        (made_expanded - made_in_place) * 1e3,
        made_expanded * 1e3,
        made_in_place * 1e3,
        expanded as f64 / 1e6,
        expanded as f64 / v1_file as f64,
        v1_file as f64 / 1e6,
        expanded as f64 / v2_file as f64,
        v2_file as f64 / 1e6,
    );
    let any = AnyDag::open(file.bytes()).map_err(|e| format!("{}: {e}", path.display()))?;
    for (name, rays) in ray_sets(args, &any, &v1)? {
        let n = rays.len();
        let mut hits = [vec![Hit::MISS; n], vec![Hit::MISS; n], vec![Hit::MISS; n]];
        let tracers = [
            (v1.clone(), String::new()),
            (v2.clone(), String::new()),
            (v2_in_place.clone(), String::new()),
        ];
        let (one, all) = {
            let mut sequential =
                per_setting(&tracers, &rays, &mut hits, Tracer::trace_sequential_into);
            let mut timed: Vec<&mut dyn FnMut()> = sequential
                .iter_mut()
                .map(|f| f as &mut dyn FnMut())
                .collect();
            let one = alternate(args.runs, n, &mut timed);
            drop(sequential);
            let mut batch = per_setting(&tracers, &rays, &mut hits, Tracer::trace_batch_into);
            let mut timed: Vec<&mut dyn FnMut()> =
                batch.iter_mut().map(|f| f as &mut dyn FnMut()).collect();
            let all = alternate(args.runs, n, &mut timed);
            (one, all)
        };
        // Packets may pick another of exactly tied cells than `trace()`.
        let differ = [1, 2].map(|k| hits[0].iter().zip(&hits[k]).filter(|(a, b)| a != b).count());
        if differ.iter().any(|&d| d * 1000 > n) {
            return Err(format!(
                "{name}: 2.0 (expanded, in place) and 1.0 answer {differ:?} of {n} rays differently"
            ));
        }
        let hit_count = hits[1].iter().filter(|h| h.hit).count();
        let m = |v: &Vec<f64>| mrays(median(v.clone()));
        println!(
            "{name:>18}  1.0: 1 core {} / {}   all cores {}   ({:.1}% hit)",
            m(&one[0].0),
            m(&one[0].1),
            m(&all[0].0),
            100.0 * hit_count as f64 / n as f64
        );
        for (k, how) in [(1, "expanded"), (2, "in place")] {
            println!(
                "{name:>18}  2.0 {how}: 1 core {} / {}   all cores {}   ({} answers differ: ties)",
                m(&one[k].0),
                m(&one[k].1),
                m(&all[k].0),
                differ[k - 1],
            );
        }
        for (k, how) in [(1, "expanded"), (2, "in place")] {
            println!(
                "{name:>18}  2.0 {how} / 1.0 rate: 1 core {:.3} / {:.3}   all cores {:.3}   (median of per-run ratios)",
                ratio(&one[k].0, &one[0].0),
                ratio(&one[k].1, &one[0].1),
                ratio(&all[k].0, &all[0].0),
            );
        }
    }
    Ok(())
}

fn bench_file(args: &Args, path: &Path, mesh: Option<&Mesh>) -> Result<(), String> {
    let file = MappedFile::open(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let dag = AnyDag::open(file.bytes()).map_err(|e| format!("{}: {e}", path.display()))?;
    let tracer = Tracer::from_any(&dag)
        .map_err(|e| e.to_string())?
        .with_index(args.index);
    // Every combination of the gather and lane settings asked for.
    let mut tracers: Vec<(Tracer, String)> = Vec::new();
    for (gathers, gathers_name) in args.gathers.modes() {
        for (lanes, lanes_name) in args.lanes.modes() {
            let t = tracer.clone().with_gathers(gathers).with_lanes(lanes);
            tracers.push((t, format!("{gathers_name}{lanes_name}")));
        }
    }
    let header = dag.header();
    println!(
        "{}: depth {}, {} voxels, {} bytes; vector lanes read with {}; {} rays to a vector",
        path.display(),
        header.depth,
        header.voxel_count,
        header.file_size,
        match args.gathers {
            GatherArg::Both => "the gather instruction and with scalar loads, in turn",
            _ if tracers[0].0.gathers() == Gathers::ScalarLoads => "scalar loads",
            _ => "the gather instruction",
        },
        match args.lanes {
            LaneArg::Both if tracers[1].0.lanes() == Lanes::Eight => {
                "eight and eight (no AVX-512 here), in turn,"
            }
            LaneArg::Both => "eight and sixteen, in turn,",
            _ if tracers[0].0.lanes() == Lanes::Sixteen => "sixteen",
            _ => "eight",
        }
    );
    let sets = ray_sets(args, &dag, &tracer)?;
    for (name, rays) in &sets {
        let n = rays.len();
        let mut mode_hits = vec![vec![Hit::MISS; n]; tracers.len()];
        let mut single_hits = vec![Hit::MISS; n];
        let mut ts = vec![0f32; n];
        let mut mesh_ts = vec![0f32; n];
        let mut failed = None;
        // One thread.
        let mut single = || {
            for (ray, hit) in rays.iter().zip(single_hits.iter_mut()) {
                match tracer.trace(ray) {
                    Ok(h) => *hit = h,
                    Err(e) => failed = Some(e),
                }
            }
        };
        let mut sequential = per_setting(
            &tracers,
            rays,
            &mut mode_hits,
            Tracer::trace_sequential_into,
        );
        let mut mesh_one = || {
            if let Some(mesh) = mesh {
                for (ray, t) in rays.iter().zip(ts.iter_mut()) {
                    *t = mesh.trace(ray);
                }
            }
        };
        // trace(), the batch API in each setting, obvhs.
        let one = {
            let mut timed: Vec<&mut dyn FnMut()> = vec![&mut single];
            timed.extend(sequential.iter_mut().map(|f| f as &mut dyn FnMut()));
            timed.push(&mut mesh_one);
            alternate(args.runs, n, &mut timed)
        };
        drop(sequential);
        for mode in &mode_hits {
            if *mode != single_hits {
                return Err("trace() and trace_sequential_into() answer differently".into());
            }
        }
        // All threads.
        let mut batch = per_setting(&tracers, rays, &mut mode_hits, Tracer::trace_batch_into);
        let mut mesh_all = || {
            if let Some(mesh) = mesh {
                mesh_ts
                    .par_chunks_mut(1024)
                    .zip(rays.par_chunks(1024))
                    .for_each(|(ts, rays)| {
                        for (t, ray) in ts.iter_mut().zip(rays) {
                            *t = mesh.trace(ray);
                        }
                    });
            }
        };
        let all = {
            let mut timed: Vec<&mut dyn FnMut()> =
                batch.iter_mut().map(|f| f as &mut dyn FnMut()).collect();
            timed.push(&mut mesh_all);
            alternate(args.runs, n, &mut timed)
        };
        drop(batch);
        if let Some(e) = failed {
            return Err(e.to_string());
        }
        if mode_hits.iter().any(|mode| *mode != single_hits) {
            return Err("trace() and trace_batch_into() answer differently".into());
        }
        let hits = &single_hits;
        let hit_count = hits.iter().filter(|h| h.hit).count();
        let m = |v: &Vec<f64>| mrays(median(v.clone()));
        // Rates: `one` is trace(), then each setting, then obvhs; `all` each
        // setting, then obvhs.
        let settings = tracers.len();
        for (k, (_, mode)) in tracers.iter().enumerate() {
            println!(
                "{name:>18}  dagtrace trace() 1 thread {} / {}   1 core {} / {}   all cores {}   ({:.1}% hit){mode}",
                m(&one[0].0),
                m(&one[0].1),
                m(&one[1 + k].0),
                m(&one[1 + k].1),
                m(&all[k].0),
                100.0 * hit_count as f64 / n as f64
            );
        }
        if settings == 2 {
            // Time of the second setting over time of the first (the rates'
            // inverse ratio).
            let names = [&tracers[0].1, &tracers[1].1].map(|n| n.trim().trim_matches(['[', ']']));
            println!(
                "{name:>18}  {} / {}, time: 1 core {:.3} / {:.3}   all cores {:.3}   (median of per-run ratios)",
                names[1],
                names[0],
                ratio(&one[1].0, &one[2].0),
                ratio(&one[1].1, &one[2].1),
                ratio(&all[0].0, &all[1].0),
            );
        }
        if mesh.is_none() {
            continue;
        }
        let (mesh_one, mesh_all) = (&one[1 + settings], &all[settings]);
        let mesh_hits = ts.iter().filter(|t| t.is_finite()).count();
        println!(
            "{name:>18}  obvhs CWBVH                               1 core {} / {}   all cores {}   ({:.1}% hit)",
            m(&mesh_one.0),
            m(&mesh_one.1),
            m(&mesh_all.0),
            100.0 * mesh_hits as f64 / n as f64
        );
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
        for (k, (_, mode)) in tracers.iter().enumerate() {
            println!(
                "{name:>18}  speed-up x   trace() {:5.2}x / {:5.2}x          1 core {:5.2}x / {:5.2}x  all cores {:5.2}x   (hit both: {both}; |t_mesh - t_voxel| median {:.2}, p99 {:.2} voxels){mode}",
                ratio(&one[0].0, &mesh_one.0),
                ratio(&one[0].1, &mesh_one.1),
                ratio(&one[1 + k].0, &mesh_one.0),
                ratio(&one[1 + k].1, &mesh_one.1),
                ratio(&all[k].0, &mesh_all.0),
                gaps.get(both / 2).copied().unwrap_or(f64::NAN),
                gaps.get(both * 99 / 100).copied().unwrap_or(f64::NAN),
            );
        }
    }
    Ok(())
}
