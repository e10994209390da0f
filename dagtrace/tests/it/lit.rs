//! Lit rendering (`dagtrace::lit`): the neighbourhood query against the
//! voxels, shading normals against the analytic normals of a sphere and of
//! tilted planes, and the GPU's lit surfaces and image against the CPU's.

use dagfmt::batch::Ray;
use dagfmt::{AttributeKind, Dag};
use dagtrace::Tracer;
use dagtrace::camera::Camera;
use dagtrace::lit::{self, LitOptions};

use crate::common::{Rng, build};

fn unit(v: [f64; 3]) -> [f64; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    v.map(|c| c / l)
}

fn dot(a: [f64; 3], b: [f32; 3]) -> f64 {
    a[0] * f64::from(b[0]) + a[1] * f64::from(b[1]) + a[2] * f64::from(b[2])
}

/// A solid ball of voxel centres within `radius` of `centre` at `depth`.
fn ball(depth: u8, centre: [f64; 3], radius: f64) -> Vec<[u32; 3]> {
    let n = 1u32 << depth;
    let mut voxels = Vec::new();
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let d = [x, y, z].map(f64::from);
                let r2: f64 = (0..3).map(|i| (d[i] + 0.5 - centre[i]).powi(2)).sum();
                if r2 <= radius * radius {
                    voxels.push([x, y, z]);
                }
            }
        }
    }
    voxels
}

/// Statistics of the angles (degrees) between estimated and true normals.
struct Angles(Vec<f64>);

impl Angles {
    fn mean(&self) -> f64 {
        self.0.iter().sum::<f64>() / self.0.len() as f64
    }
    fn quantile(&self, q: f64) -> f64 {
        let mut v = self.0.clone();
        v.sort_by(f64::total_cmp);
        v[((v.len() - 1) as f64 * q) as usize]
    }
}

/// The shading normal (as the lit renderer computes it) at the hit of
/// `ray`, with the hit point (grid = world units here).
fn normal_at(tracer: &Tracer<'_>, ray: &Ray) -> Option<([f64; 3], [f32; 3])> {
    let hit = tracer.trace(ray).expect("trace");
    if !hit.hit || hit.face == 0 {
        return None;
    }
    let occupancy = tracer
        .occupancy_around(hit.voxel, tracer.depth())
        .expect("occupancy");
    let normal = lit::normal_from_occupancy(occupancy, hit.face);
    let p = [0, 1, 2].map(|i| f64::from(ray.origin[i]) + f64::from(hit.t) * f64::from(ray.dir[i]));
    Some((p, normal))
}

#[test]
fn occupancy_around_matches_the_voxels_on_every_level() {
    let mut rng = Rng(7);
    let depth = 6u8;
    let n = 1u32 << depth;
    let mut voxels: Vec<[u32; 3]> = ball(depth, [30.0, 34.0, 29.0], 17.0);
    for _ in 0..300 {
        voxels.push([0, 1, 2].map(|_| rng.below(u64::from(n)) as u32));
    }
    let bytes = build(depth, AttributeKind::VoxelCount, &voxels, [0.0; 3], 64.0);
    let dag = Dag::open(&bytes).expect("open");
    let tracer = Tracer::new(&dag).expect("tracer");
    let mut set = std::collections::HashSet::new();
    set.extend(voxels.iter().copied());
    for level in 1..=depth {
        let shift = depth - level;
        let cells: std::collections::HashSet<[u32; 3]> =
            set.iter().map(|v| v.map(|c| c >> shift)).collect();
        let last = (1i64 << level) - 1;
        for _ in 0..300 {
            // Centres near the edges of the grid too.
            let centre = [0, 1, 2].map(|_| rng.below(1 << level) as u32);
            let bits = tracer.occupancy_around(centre, level).expect("occupancy");
            for dz in -2..=2i64 {
                for dy in -2..=2i64 {
                    for dx in -2..=2i64 {
                        let c = [
                            i64::from(centre[0]) + dx,
                            i64::from(centre[1]) + dy,
                            i64::from(centre[2]) + dz,
                        ];
                        let expected = c.iter().all(|&v| (0..=last).contains(&v))
                            && cells.contains(&c.map(|v| v as u32));
                        let bit = (dx + 2) + 5 * (dy + 2) + 25 * (dz + 2);
                        assert_eq!(
                            bits >> bit & 1 == 1,
                            expected,
                            "level {level} centre {centre:?} offset {:?}",
                            [dx, dy, dz]
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn sphere_normals_match_the_analytic_normal() {
    let depth = 7u8;
    let centre = [64.0, 64.0, 64.0];
    let radius = 40.0;
    let bytes = build(
        depth,
        AttributeKind::VoxelCount,
        &ball(depth, centre, radius),
        [0.0; 3],
        128.0,
    );
    let dag = Dag::open(&bytes).expect("open");
    let tracer = Tracer::new(&dag).expect("tracer");
    let mut rng = Rng(11);
    let mut angles = Vec::new();
    while angles.len() < 3000 {
        // From a random point outside towards a random point of the ball.
        let d = unit([0, 1, 2].map(|_| rng.range(-1.0, 1.0)));
        let target = [0, 1, 2].map(|i| centre[i] + rng.range(-20.0, 20.0));
        let origin = [0, 1, 2].map(|i| target[i] + d[i] * 60.0);
        let ray = Ray {
            origin: origin.map(|v| v as f32),
            dir: d.map(|v| -v as f32),
            tmin: 0.0,
            tmax: f32::INFINITY,
            level: None,
        };
        if let Some((p, normal)) = normal_at(&tracer, &ray) {
            let truth = unit([0, 1, 2].map(|i| p[i] - centre[i]));
            angles.push(dot(truth, normal).clamp(-1.0, 1.0).acos().to_degrees());
        }
    }
    let a = Angles(angles);
    println!(
        "sphere r = 40 voxels: angle to the analytic normal: mean {:.2}°, 95% {:.2}°, max {:.2}°",
        a.mean(),
        a.quantile(0.95),
        a.quantile(1.0)
    );
    assert!(a.mean() < 6.0, "mean {}", a.mean());
    assert!(a.quantile(0.95) < 12.0, "95% {}", a.quantile(0.95));
    assert!(a.quantile(1.0) < 20.0, "max {}", a.quantile(1.0));
}

#[test]
fn plane_normals_match_the_analytic_normal() {
    let depth = 6u8;
    let n = 1u32 << depth;
    for (k, normal) in [
        [0.0, 1.0, 0.0],
        [1.0, 2.0, 3.0],
        [-0.3, 1.0, 0.2],
        [0.0, 1.0, 1.0],
    ]
    .into_iter()
    .enumerate()
    {
        let normal = unit(normal);
        let origin_point = [32.0, 32.0, 32.0];
        let mut voxels = Vec::new();
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let p = [x, y, z].map(|c| f64::from(c) + 0.5);
                    let s: f64 = (0..3).map(|i| (p[i] - origin_point[i]) * normal[i]).sum();
                    if s <= 0.0 {
                        voxels.push([x, y, z]);
                    }
                }
            }
        }
        let bytes = build(depth, AttributeKind::VoxelCount, &voxels, [0.0; 3], 64.0);
        let dag = Dag::open(&bytes).expect("open");
        let tracer = Tracer::new(&dag).expect("tracer");
        let mut rng = Rng(100 + k as u64);
        let mut angles = Vec::new();
        while angles.len() < 1000 {
            // Rays from above the plane to points on it away from the grid's
            // edges (where the missing outside skews the neighbourhood).
            let target = [0, 1, 2].map(|i| origin_point[i] + rng.range(-12.0, 12.0));
            let s: f64 = (0..3)
                .map(|i| (target[i] - origin_point[i]) * normal[i])
                .sum();
            let on_plane = [0, 1, 2].map(|i| target[i] - s * normal[i]);
            let tilt = unit([0, 1, 2].map(|i| normal[i] + rng.range(-0.5, 0.5)));
            let origin = [0, 1, 2].map(|i| on_plane[i] + tilt[i] * 20.0);
            let ray = Ray {
                origin: origin.map(|v| v as f32),
                dir: tilt.map(|v| -v as f32),
                tmin: 0.0,
                tmax: f32::INFINITY,
                level: None,
            };
            if let Some((_, estimate)) = normal_at(&tracer, &ray) {
                angles.push(dot(normal, estimate).clamp(-1.0, 1.0).acos().to_degrees());
            }
        }
        let a = Angles(angles);
        println!(
            "plane {normal:.3?}: angle to the analytic normal: mean {:.2}°, 95% {:.2}°, max {:.2}°",
            a.mean(),
            a.quantile(0.95),
            a.quantile(1.0)
        );
        assert!(a.mean() < 6.0, "{normal:?}: mean {}", a.mean());
        assert!(
            a.quantile(1.0) < 15.0,
            "{normal:?}: max {}",
            a.quantile(1.0)
        );
    }
}

/// A ball on a slab, with a post beside it, at depth 7.
pub fn lit_scene() -> Vec<u8> {
    let depth = 7u8;
    let mut voxels = ball(depth, [60.0, 58.0, 64.0], 26.0);
    for z in 16..112 {
        for x in 16..112 {
            for y in 28..34 {
                voxels.push([x, y, z]);
            }
        }
    }
    for y in 34..90 {
        for z in 90..100 {
            for x in 90..100 {
                voxels.push([x, y, z]);
            }
        }
    }
    build(
        depth,
        AttributeKind::VoxelCount,
        &voxels,
        [-1.0, 0.0, 2.0],
        8.0,
    )
}

#[test]
fn lit_render_shows_sun_shadow_and_ambient_occlusion() {
    let bytes = lit_scene();
    let dag = Dag::open(&bytes).expect("open");
    let tracer = Tracer::new(&dag).expect("tracer");
    let (w, h) = (64, 48);
    let camera = Camera::automatic(&dag, f64::from(w) / f64::from(h));
    let frame = camera.frame().expect("frame");
    let options = LitOptions {
        samples: 2,
        ao_rays: 6,
        ..LitOptions::default()
    };
    let surfaces = lit::trace_surfaces(&tracer, &frame, w, h, None, &options).expect("render");
    assert_eq!(surfaces.len(), (w * h * 2) as usize);
    let hits: Vec<_> = surfaces.iter().filter(|s| s.hit).collect();
    assert!(
        hits.len() > surfaces.len() / 5,
        "the scene fills the view: {} of {}",
        hits.len(),
        surfaces.len()
    );
    for s in &hits {
        let len: f32 = s.normal.iter().map(|c| c * c).sum::<f32>().sqrt();
        assert!((len - 1.0).abs() < 1e-5, "unit normals: {s:?}");
        assert!(s.ao_open <= 6);
    }
    let lit_count = hits.iter().filter(|s| s.sun_visible).count();
    let shadowed = hits.len() - lit_count;
    assert!(
        lit_count > hits.len() / 3 && shadowed > 10,
        "{lit_count} lit, {shadowed} in shadow"
    );
    // The slab's open middle sees most of the sky; its corners at the ball
    // and post see less.
    assert!(hits.iter().any(|s| s.ao_open == 6) && hits.iter().any(|s| s.ao_open < 4));
    // Without AO every surface counts as open; the image is brighter.
    let image = lit::compose(&surfaces, &options, |_| None);
    assert_eq!(image.len(), (w * h * 3) as usize);
}

#[cfg(feature = "gpu")]
mod gpu {
    use super::*;
    use dagtrace::gpu::{AdapterChoice, GpuContext, GpuOptions, GpuTracer};

    fn context() -> Option<GpuContext> {
        match GpuContext::new(AdapterChoice::Default) {
            Ok(c) => Some(c),
            Err(e) => {
                if std::env::var("VDAG_REQUIRE_GPU").is_ok_and(|v| v == "1") {
                    panic!("VDAG_REQUIRE_GPU=1 but no GPU adapter: {e}");
                }
                println!("skipped: no GPU adapter: {e}");
                None
            }
        }
    }

    /// The GPU's lit image against the CPU's: surfaces agree but for rays
    /// whose f32 set-up differs at ties (silhouettes, grazing shadow and
    /// AO rays), so almost every pixel is the same.
    #[test]
    fn gpu_lit_image_matches_the_cpu_image() {
        let Some(ctx) = context() else { return };
        let bytes = lit_scene();
        let dag = Dag::open(&bytes).expect("open");
        let tracer = Tracer::new(&dag).expect("tracer");
        let gpu = GpuTracer::with_context(&ctx, &dag, &GpuOptions::default()).expect("gpu");
        for (w, h, options, level) in [
            (
                96,
                64,
                LitOptions {
                    samples: 2,
                    ao_rays: 6,
                    ..LitOptions::default()
                },
                None,
            ),
            (
                40,
                30,
                LitOptions {
                    sun: [0.6, 0.5, -0.2],
                    ao_rays: 3,
                    ao_radius: Some(4.0),
                    samples: 1,
                },
                Some(6),
            ),
            (
                // Cells above the leaves: the shader's node lookups.
                32,
                24,
                LitOptions {
                    ao_rays: 2,
                    ..LitOptions::default()
                },
                Some(4),
            ),
        ] {
            let camera = Camera::automatic(&dag, f64::from(w) / f64::from(h));
            let frame = camera.frame().expect("frame");
            let cpu = lit::trace_surfaces(&tracer, &frame, w, h, level, &options).expect("cpu");
            let on_gpu = gpu
                .lit_surfaces(&camera, w, h, level, &options)
                .expect("gpu");
            assert_eq!(cpu.len(), on_gpu.len());
            let same_hit = cpu
                .iter()
                .zip(&on_gpu)
                .filter(|(a, b)| a.hit == b.hit)
                .count();
            // The CPU computes no attribute index without colours; the GPU
            // tracer here does.
            let same = cpu
                .iter()
                .zip(&on_gpu)
                .filter(|(a, b)| lit::Surface { index: None, ..**b } == **a)
                .count();
            let a = lit::compose(&cpu, &options, |_| None);
            let b = lit::compose(&on_gpu, &options, |_| None);
            // The banded image is the composed surfaces.
            let banded = gpu
                .render_lit(&camera, w, h, level, &options, |_| None)
                .expect("gpu image");
            assert_eq!(banded, b);
            let diffs: Vec<u8> = a
                .chunks(3)
                .zip(b.chunks(3))
                .map(|(p, q)| (0..3).map(|i| p[i].abs_diff(q[i])).max().unwrap_or(0))
                .collect();
            let off = diffs.iter().filter(|&&d| d > 2).count();
            let mean = diffs.iter().map(|&d| f64::from(d)).sum::<f64>() / diffs.len() as f64;
            println!(
                "{w}x{h} level {level:?}: surfaces equal {same}/{}, same hit {same_hit}; \
                 pixels off by more than 2/255: {off}/{}, mean difference {mean:.3}/255",
                cpu.len(),
                diffs.len()
            );
            assert!(
                same_hit * 100 >= cpu.len() * 99,
                "hits {same_hit}/{}",
                cpu.len()
            );
            assert!(
                same * 100 >= cpu.len() * 98,
                "surfaces {same}/{}",
                cpu.len()
            );
            assert!(off * 100 <= diffs.len(), "{off} pixels off");
            assert!(mean < 0.5, "mean difference {mean}");
        }
    }
}
