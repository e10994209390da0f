//! The GPU tracer against two references: an f64 brute-force oracle of the
//! ray/hit semantics (spec/VDAG.md, with its tolerance) over the voxels of the
//! DAG, and the CPU tracer (`dagtrace::Tracer`), whose cells the GPU tracer
//! finds too but at exact ties (it uses the same set-up, traversal design and
//! f32 plane arithmetic, but not every path of the CPU's traversal).
//!
//! Without a wgpu adapter (not even a software one such as Mesa's lavapipe)
//! every test here prints that it is skipped, unless `VDAG_REQUIRE_GPU=1`,
//! which makes that a failure. (The shader's WGSL is validated without an
//! adapter by the unit tests in `dagtrace/src/gpu/tests.rs`.)
#![cfg(feature = "gpu")]

use std::sync::OnceLock;

use dagfmt::batch::{Hit, Ray};
use dagfmt::{AttributeKind, Dag, DagBuilder, morton};
use dagtrace::camera::Camera;
use dagtrace::gpu::{
    AdapterChoice, GpuContext, GpuError, GpuOptions, GpuTracer, StackMode, V2Layout,
};

// ---------------------------------------------------------------- adapter --

/// The shared context, or `None` (after saying so) when there is no adapter.
fn context() -> Option<&'static GpuContext> {
    static CONTEXT: OnceLock<Result<GpuContext, GpuError>> = OnceLock::new();
    match CONTEXT.get_or_init(|| GpuContext::new(AdapterChoice::Default)) {
        Ok(c) => Some(c),
        Err(e) => {
            if std::env::var("VDAG_REQUIRE_GPU").is_ok_and(|v| v == "1") {
                panic!("VDAG_REQUIRE_GPU=1 but no GPU adapter: {e}");
            }
            println!("skipped: no GPU adapter (set VDAG_REQUIRE_GPU=1 to make this an error): {e}");
            None
        }
    }
}

fn tracer(ctx: &GpuContext, dag: &Dag<'_>, options: GpuOptions) -> GpuTracer {
    GpuTracer::with_context(ctx, dag, &options).expect("GPU tracer")
}

// ------------------------------------------------------------ randomness --

/// SplitMix64: small, seedable, good enough for test inputs.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }

    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    fn chance(&mut self, p: f64) -> bool {
        self.unit() < p
    }
}

// ------------------------------------------------------------------ DAGs --

/// A DAG file in memory with the voxels it holds.
struct TestDag {
    bytes: Vec<u8>,
    depth: u8,
    root_min: [f64; 3],
    root_size: f64,
    /// Morton codes of the set voxels, sorted.
    codes: Vec<u64>,
}

impl TestDag {
    fn new(
        depth: u8,
        kind: AttributeKind,
        voxels: Vec<[u32; 3]>,
        root_min: [f64; 3],
        root_size: f64,
    ) -> TestDag {
        let mut built =
            DagBuilder::from_voxels(depth, kind, voxels.iter().copied()).expect("build");
        built.set_root_cube(root_min, root_size).expect("root cube");
        let mut codes: Vec<u64> = voxels
            .iter()
            .map(|v| morton::encode(v[0], v[1], v[2]))
            .collect();
        codes.sort_unstable();
        codes.dedup();
        TestDag {
            bytes: built.to_bytes(),
            depth,
            root_min,
            root_size,
            codes,
        }
    }

    fn dag(&self) -> Dag<'_> {
        Dag::open(&self.bytes).expect("open")
    }
}

/// Random clusters of voxels (blobs, slabs and single voxels) at `depth`.
fn random_voxels(rng: &mut Rng, depth: u8, clusters: usize) -> Vec<[u32; 3]> {
    let n = 1u32 << depth;
    let mut voxels = Vec::new();
    for _ in 0..clusters {
        let centre: [u32; 3] = std::array::from_fn(|_| rng.below(u64::from(n)) as u32);
        let radius = rng.below(u64::from((n / 4).clamp(1, 6))) as i64;
        let density = rng.range(0.3, 1.0);
        for dz in -radius..=radius {
            for dy in -radius..=radius {
                for dx in -radius..=radius {
                    let p = [
                        centre[0] as i64 + dx,
                        centre[1] as i64 + dy,
                        centre[2] as i64 + dz,
                    ];
                    if p.iter().all(|&c| (0..i64::from(n)).contains(&c)) && rng.chance(density) {
                        voxels.push(p.map(|c| c as u32));
                    }
                }
            }
        }
    }
    voxels
}

// ---------------------------------------------------------------- rays --

/// Random rays in grid terms mapped to world space: origins inside and
/// outside, on grid planes, directions with zero components, levels of detail,
/// odd intervals, and degenerate rays.
fn random_rays(rng: &mut Rng, t: &TestDag, count: usize) -> Vec<Ray> {
    let n = (1u64 << t.depth) as f64;
    let to_world = |g: [f64; 3]| -> [f32; 3] {
        std::array::from_fn(|i| (t.root_min[i] + g[i] * t.root_size / n) as f32)
    };
    let voxel = |rng: &mut Rng| -> [f64; 3] {
        let code = t.codes[rng.below(t.codes.len().max(1) as u64) as usize % t.codes.len().max(1)];
        let v = morton::decode(code);
        std::array::from_fn(|i| f64::from(v[i]) + rng.range(0.0, 1.0))
    };
    (0..count)
        .map(|k| {
            let mut origin: [f64; 3] = match rng.below(4) {
                0 => std::array::from_fn(|_| rng.range(-0.5 * n, 1.5 * n)),
                1 => std::array::from_fn(|_| rng.range(0.0, n)),
                2 => std::array::from_fn(|_| rng.below(n as u64 + 1) as f64),
                _ if !t.codes.is_empty() => voxel(rng),
                _ => std::array::from_fn(|_| rng.range(0.0, n)),
            };
            let target: [f64; 3] = if !t.codes.is_empty() && rng.chance(0.7) {
                voxel(rng)
            } else {
                std::array::from_fn(|_| rng.range(0.0, n))
            };
            let mut dir: [f64; 3] = std::array::from_fn(|i| target[i] - origin[i]);
            match rng.below(8) {
                0 => dir[rng.below(3) as usize] = 0.0,
                1 => {
                    let keep = rng.below(3) as usize;
                    for (i, d) in dir.iter_mut().enumerate() {
                        if i != keep {
                            *d = 0.0;
                        }
                    }
                }
                2 => dir = std::array::from_fn(|_| rng.range(-1.0, 1.0)),
                _ => {}
            }
            if k % 97 == 0 {
                dir = [0.0; 3];
            }
            if rng.chance(0.1) {
                // Start on a grid plane.
                let axis = rng.below(3) as usize;
                origin[axis] = origin[axis].round();
            }
            let (tmin, tmax) = match rng.below(6) {
                0 => (f32::NEG_INFINITY, f32::INFINITY),
                1 => (rng.range(-1.0, 0.5) as f32, rng.range(0.2, 2.0) as f32),
                2 => (0.5, 0.25),
                _ => (0.0, f32::INFINITY),
            };
            let level = if rng.chance(0.3) {
                Some(rng.below(u64::from(t.depth) + 1) as u8)
            } else {
                None
            };
            let mut ray = Ray {
                origin: to_world(origin),
                dir: to_world_dir(dir, t),
                tmin,
                tmax,
                level,
            };
            if k % 211 == 5 {
                ray.dir[1] = f32::NAN;
            }
            ray
        })
        .collect()
}

fn to_world_dir(d: [f64; 3], t: &TestDag) -> [f32; 3] {
    let n = (1u64 << t.depth) as f64;
    d.map(|v| (v * t.root_size / n) as f32)
}

// --------------------------------------------------------------- oracle --

/// Entry and exit parameters of the ray into the closed box `[lo, hi]`,
/// clipped to `[tmin, tmax]` (spec/VDAG.md § Ray/hit semantics).
fn interval(
    o: &[f64; 3],
    d: &[f64; 3],
    tmin: f64,
    tmax: f64,
    lo: [f64; 3],
    hi: [f64; 3],
) -> Option<(f64, f64)> {
    if (0..3).any(|i| lo[i] > hi[i]) {
        return None;
    }
    let (mut near, mut far) = (f64::NEG_INFINITY, f64::INFINITY);
    for i in 0..3 {
        if d[i] == 0.0 {
            if o[i] < lo[i] || o[i] > hi[i] {
                return None;
            }
        } else {
            let a = (lo[i] - o[i]) / d[i];
            let b = (hi[i] - o[i]) / d[i];
            near = near.max(a.min(b));
            far = far.min(a.max(b));
        }
    }
    let (e, x) = (tmin.max(near), tmax.min(far));
    (e <= x).then_some((e, x))
}

/// Checks `hit` for `ray` against the semantics, brute force over the cells.
fn oracle_check(t: &TestDag, ray: &Ray, hit: &Hit, indexed: bool) -> Result<(), String> {
    let depth = t.depth;
    let n = (1u64 << depth) as f64;
    let scale = n / t.root_size;
    let bad = ray
        .origin
        .iter()
        .chain(&ray.dir)
        .chain([&ray.tmin, &ray.tmax])
        .any(|v| v.is_nan())
        || ray.tmin > ray.tmax;
    if bad {
        return if hit.hit {
            Err("hit for a NaN or empty ray".into())
        } else {
            Ok(())
        };
    }
    let o: [f64; 3] = std::array::from_fn(|i| (f64::from(ray.origin[i]) - t.root_min[i]) * scale);
    let d: [f64; 3] = ray.dir.map(|v| f64::from(v) * scale);
    let (tmin, tmax) = (f64::from(ray.tmin), f64::from(ray.tmax));
    let level = ray.level.unwrap_or(depth);
    let eps = 2f64.powi(-12) + 2f64.powi(-21) * n.max(o.iter().fold(0f64, |m, v| m.max(v.abs())));
    let eps_t = eps / d.iter().map(|v| v * v).sum::<f64>().sqrt();
    let s = (1u64 << (depth - level)) as f64;
    let mut cells: Vec<[u32; 3]> = t
        .codes
        .iter()
        .map(|&c| morton::decode(c >> (3 * u32::from(depth - level))))
        .collect();
    cells.dedup();
    let box_of = |c: [u32; 3], delta: f64| -> ([f64; 3], [f64; 3]) {
        (
            c.map(|v| f64::from(v) * s - delta),
            c.map(|v| (f64::from(v) + 1.0) * s + delta),
        )
    };
    let t_minus = cells
        .iter()
        .filter_map(|&c| {
            let (lo, hi) = box_of(c, -eps);
            interval(&o, &d, tmin, tmax, lo, hi).map(|(e, _)| e)
        })
        .fold(f64::INFINITY, f64::min);
    if !hit.hit {
        return if t_minus == f64::INFINITY {
            Ok(())
        } else {
            Err(format!("miss, but a cell is entered at {t_minus}"))
        };
    }
    if hit.level != level {
        return Err(format!(
            "hit at level {} for a ray of level {level}",
            hit.level
        ));
    }
    let cell = hit.voxel;
    let code = morton::encode(cell[0], cell[1], cell[2]);
    if cell.iter().any(|&c| u64::from(c) >= 1u64 << level)
        || cells
            .binary_search_by_key(&code, |c| morton::encode(c[0], c[1], c[2]))
            .is_err()
    {
        return Err(format!("hit cell {cell:?} is not occupied"));
    }
    let (lo, hi) = box_of(cell, eps);
    let Some((e_plus, x_plus)) = interval(&o, &d, tmin, tmax, lo, hi) else {
        return Err(format!(
            "the ray does not meet hit cell {cell:?} even grown by eps"
        ));
    };
    let tt = f64::from(hit.t);
    // `a <= b` up to `eps_t`, which is infinite for a ray with no direction.
    let le = |a: f64, b: f64| eps_t == f64::INFINITY || a <= b + eps_t;
    if !le(e_plus, t_minus) {
        return Err(format!(
            "cell {cell:?} entered at {e_plus}, but another is entered at {t_minus}"
        ));
    }
    if !(le(e_plus, tt) && le(tt, x_plus.min(t_minus))) || tt.is_nan() {
        return Err(format!(
            "t = {tt} outside [{e_plus}, {}] +- {eps_t}",
            x_plus.min(t_minus)
        ));
    }
    // Faces: the entry face against the cell, grown or shrunk, ties included.
    let mut faces = Vec::new();
    for delta in [-eps, 0.0, eps] {
        let (lo, hi) = box_of(cell, delta);
        let starts: Vec<(f64, u8)> = (0..3)
            .filter(|&i| d[i] != 0.0)
            .map(|i| {
                (
                    ((lo[i] - o[i]) / d[i]).min((hi[i] - o[i]) / d[i]),
                    1 + 2 * i as u8 + u8::from(d[i] < 0.0),
                )
            })
            .collect();
        let near = starts.iter().map(|s| s.0).fold(f64::NEG_INFINITY, f64::max);
        if le(near, tmin) {
            faces.push(0);
        }
        if le(tmin, near) {
            faces.extend(starts.iter().filter(|s| le(near, s.0)).map(|s| s.1));
        }
    }
    if !faces.contains(&hit.face) {
        return Err(format!("face {} not among {faces:?}", hit.face));
    }
    let first = code << (3 * u32::from(depth - level));
    let expected = indexed.then(|| t.codes.partition_point(|&c| c < first) as u64);
    if hit.index != expected {
        return Err(format!("index {:?}, expected {expected:?}", hit.index));
    }
    Ok(())
}

// ------------------------------------------------------------ CPU tracer --

fn cpu_hits(dag: &Dag<'_>, rays: &[Ray]) -> Vec<Hit> {
    let tracer = dagtrace::Tracer::new(dag).expect("CPU tracer");
    rays.iter()
        .map(|r| {
            let ray = dagtrace::Ray {
                origin: r.origin,
                dir: r.dir,
                tmin: r.tmin,
                tmax: r.tmax,
                level: r.level,
            };
            let h = tracer.trace(&ray).expect("CPU trace");
            Hit {
                hit: h.hit,
                t: h.t,
                voxel: h.voxel,
                level: h.level,
                face: h.face,
                index: h.index,
            }
        })
        .collect()
}

fn same(a: &Hit, b: &Hit) -> bool {
    a.hit == b.hit
        && a.t.to_bits() == b.t.to_bits()
        && a.voxel == b.voxel
        && a.level == b.level
        && a.face == b.face
        && a.index == b.index
}

/// Whether two answers name the same cell (or are both misses). The CPU and
/// GPU tracers share the traversal's design and set-up, and compute `t` the
/// same way, but not every path of the traversal (and the GPU computes `t`
/// in f64 on the host for rare rays: no direction, far origins, rays that
/// start inside the cell), so at exact ties they may pick different cells,
/// and `t` may differ in the last bits; both are checked against the oracle.
fn same_cell(a: &Hit, b: &Hit) -> bool {
    a.hit == b.hit && (!a.hit || (a.voxel == b.voxel && a.level == b.level && a.index == b.index))
}

/// Asserts that the GPU and CPU answers name the same cells for all but 1% of the rays.
fn assert_agrees_with_cpu(rays: &[Ray], gpu: &[Hit], cpu: &[Hit], what: &str) {
    let differ: Vec<String> = rays
        .iter()
        .zip(gpu.iter().zip(cpu))
        .enumerate()
        .filter(|(_, (_, (g, c)))| !same_cell(g, c))
        .map(|(i, (r, (g, c)))| format!("ray {i} {r:?}: GPU {g:?}, CPU {c:?}"))
        .collect();
    assert!(
        differ.len() * 100 <= rays.len(),
        "{what}: GPU and CPU disagree on {} of {} rays:\n{}",
        differ.len(),
        rays.len(),
        differ[..differ.len().min(10)].join("\n")
    );
}

/// Traces `rays` on the GPU and checks every answer against the oracle, and
/// the answers together against the CPU tracer. Returns the GPU's hits.
fn check_against_references(
    ctx: &GpuContext,
    t: &TestDag,
    rays: &[Ray],
    options: GpuOptions,
    what: &str,
) -> Vec<Hit> {
    let dag = t.dag();
    let gpu = tracer(ctx, &dag, options);
    let hits = gpu.trace(rays).expect("GPU trace");
    let indexed = dag.header().attribute_kind == AttributeKind::VoxelCount;
    let failures: Vec<String> = rays
        .iter()
        .zip(&hits)
        .enumerate()
        .filter_map(|(i, (ray, g))| {
            oracle_check(t, ray, g, indexed)
                .err()
                .map(|e| format!("ray {i} {ray:?}: GPU {g:?}: {e}"))
        })
        .collect();
    assert!(
        failures.is_empty(),
        "{what}: {} of {} rays wrong:\n{}",
        failures.len(),
        rays.len(),
        failures[..failures.len().min(10)].join("\n")
    );
    let cpu = cpu_hits(&dag, rays);
    assert_agrees_with_cpu(rays, &hits, &cpu, what);
    // Both tracers set rays up with the same operations and compute `t` and
    // the face from the same plane parameters, so nearly every answer is the
    // CPU's to the bit (the rest: exact ties, and the rare rays whose answer
    // the host computes in f64).
    let identical = hits.iter().zip(&cpu).filter(|(g, c)| same(g, c)).count();
    assert!(
        identical * 100 >= rays.len() * 95,
        "{what}: only {identical} of {} GPU answers are the CPU's to the bit",
        rays.len()
    );
    let hit_count = hits.iter().filter(|h| h.hit).count();
    assert!(
        hit_count * 5 >= rays.len(),
        "{what}: only {hit_count} of {} rays hit; the test is too easy",
        rays.len()
    );
    hits
}

// ----------------------------------------------------------------- tests --

#[test]
fn gpu_matches_oracle_and_cpu_on_random_dags() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(1);
    for (case, depth) in [2u8, 3, 4, 5, 6, 7, 8].into_iter().enumerate() {
        let kind = if case % 3 == 2 {
            AttributeKind::None
        } else {
            AttributeKind::VoxelCount
        };
        let voxels = random_voxels(&mut rng, depth, 6);
        let root_min = [
            rng.range(-10.0, 10.0),
            rng.range(-10.0, 10.0),
            rng.range(-10.0, 10.0),
        ];
        let t = TestDag::new(depth, kind, voxels, root_min, rng.range(0.5, 40.0));
        let rays = random_rays(&mut rng, &t, 600);
        check_against_references(
            ctx,
            &t,
            &rays,
            GpuOptions::default(),
            &format!("depth {depth}"),
        );
    }
}

#[test]
fn short_stacks_give_the_full_stack_answers() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(2);
    let t = TestDag::new(
        8,
        AttributeKind::VoxelCount,
        random_voxels(&mut rng, 8, 12),
        [0.0; 3],
        1.0,
    );
    let rays = random_rays(&mut rng, &t, 1500);
    let full = check_against_references(ctx, &t, &rays, GpuOptions::default(), "full stack");
    let (_, full_stats) = tracer(ctx, &t.dag(), GpuOptions::default())
        .trace_with_stats(&rays)
        .expect("trace");
    for size in [1, 2, 4] {
        let options = GpuOptions {
            stack: StackMode::Short(size),
            ..GpuOptions::default()
        };
        let (short, stats) = tracer(ctx, &t.dag(), options)
            .trace_with_stats(&rays)
            .expect("trace");
        for (i, (a, b)) in full.iter().zip(&short).enumerate() {
            assert!(
                same(a, b),
                "short stack {size}, ray {i} {:?}: {b:?} != full {a:?}",
                rays[i]
            );
        }
        // The ring overflowed and the traversal restarted along its path.
        assert!(
            stats.iterations > full_stats.iterations,
            "stack of {size}: {stats:?} vs {full_stats:?}"
        );
    }
}

#[test]
fn dag_split_over_bindings_gives_the_same_answers() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(3);
    // 80 000 bricks with random masks: as many distinct leaves, so the level
    // above points at them with 3-byte pointers, and the file is large.
    let depth = 10;
    let mut bricks: Vec<u64> = (0..80_000)
        .map(|_| rng.below(1 << (3 * (depth - 2))))
        .collect();
    bricks.sort_unstable();
    bricks.dedup();
    let mut builder = DagBuilder::new(depth, AttributeKind::VoxelCount).expect("builder");
    let mut codes = Vec::new();
    for &brick in &bricks {
        let mask = rng.next() & rng.next() & rng.next() | 1 << rng.below(64);
        builder.push_brick(brick, mask).expect("brick");
        codes.extend(
            (0..64)
                .filter(|b| mask >> b & 1 == 1)
                .map(|b| brick << 6 | b),
        );
    }
    let mut built = builder.finish().expect("finish");
    built.set_root_cube([1.0, -2.0, 0.5], 3.0).expect("cube");
    let t = TestDag {
        bytes: built.to_bytes(),
        depth,
        root_min: [1.0, -2.0, 0.5],
        root_size: 3.0,
        codes,
    };
    let dag = t.dag();
    assert_eq!(
        dag.levels().iter().map(|l| l.pointer_width).max(),
        Some(3),
        "no 3-byte pointers"
    );
    assert!(
        t.bytes.len() > 1 << 20,
        "file of {} bytes is too small for the test",
        t.bytes.len()
    );
    let rays = random_rays(&mut rng, &t, 1500);
    let whole = tracer(ctx, &dag, GpuOptions::default());
    assert_eq!(whole.binding_count(), 1);
    let expected = whole.trace(&rays).expect("trace");
    assert!(expected.iter().filter(|h| h.hit).count() > 300);
    assert_agrees_with_cpu(&rays, &expected, &cpu_hits(&dag, &rays), "unsplit");
    for (cap, stack) in [
        (256u64 << 10, StackMode::Full),
        (512 << 10, StackMode::Short(4)),
    ] {
        let split = tracer(
            ctx,
            &dag,
            GpuOptions {
                max_binding_bytes: Some(cap),
                stack,
                ..GpuOptions::default()
            },
        );
        assert!(
            split.binding_count() > 4,
            "cap {cap}: {} binding(s)",
            split.binding_count()
        );
        assert_eq!(split.binding_bytes(), cap);
        let hits = split.trace(&rays).expect("trace");
        for (i, (a, b)) in expected.iter().zip(&hits).enumerate() {
            assert!(same(a, b), "cap {cap}, ray {i}: {b:?} != unsplit {a:?}");
        }
    }
    // More pages than the shader has bindings for.
    let too_many = GpuOptions {
        max_binding_bytes: Some(32 << 10),
        ..GpuOptions::default()
    };
    assert!(matches!(
        GpuTracer::with_context(ctx, &dag, &too_many),
        Err(GpuError::TooLarge(_))
    ));
    // Tiny pages: records and pointers straddle page boundaries everywhere.
    let small = TestDag::new(
        6,
        AttributeKind::VoxelCount,
        random_voxels(&mut rng, 6, 10),
        [0.0; 3],
        1.0,
    );
    let rays = random_rays(&mut rng, &small, 500);
    let pages = GpuOptions {
        max_binding_bytes: Some(small.bytes.len() as u64 / 8),
        ..GpuOptions::default()
    };
    assert!(tracer(ctx, &small.dag(), pages.clone()).binding_count() >= 8);
    check_against_references(ctx, &small, &rays, pages, "tiny pages");
}

#[test]
fn saturated_counts_give_dense_indices() {
    let Some(ctx) = context() else { return };
    // A solid 256^3 octant holds 2^24 voxels: its node's stored count is
    // saturated, so the indices of the voxels after it need the host's table.
    let mut builder = DagBuilder::new(9, AttributeKind::VoxelCount).expect("builder");
    for brick in 0..(1u64 << 18) {
        builder.push_brick(brick, u64::MAX).expect("brick");
    }
    let extra = [
        [300u32, 10, 20],
        [5, 400, 7],
        [511, 511, 511],
        [260, 300, 100],
    ];
    let mut codes: Vec<u64> = extra
        .iter()
        .map(|v| morton::encode(v[0], v[1], v[2]))
        .collect();
    codes.sort_unstable();
    for &c in &codes {
        builder.push_morton(c).expect("voxel");
    }
    let built = builder.finish().expect("finish");
    let bytes = built.to_bytes();
    let dag = Dag::open(&bytes).expect("open");
    let gpu = tracer(ctx, &dag, GpuOptions::default());
    let cpu = dagtrace::Tracer::new(&dag).expect("CPU tracer");
    let rays: Vec<Ray> = extra
        .iter()
        .flat_map(|v| {
            let c = v.map(|x| (f64::from(x) + 0.5) / 512.0);
            [
                Ray {
                    origin: [c[0] as f32, c[1] as f32, 1.5],
                    dir: [0.0, 0.0, -1.0],
                    tmin: 0.0,
                    tmax: f32::INFINITY,
                    level: None,
                },
                Ray {
                    origin: [c[0] as f32, c[1] as f32, c[2] as f32],
                    dir: [0.0; 3],
                    tmin: 0.0,
                    tmax: 0.0,
                    level: None,
                },
            ]
        })
        .collect();
    let hits = gpu.trace(&rays).expect("trace");
    for (ray, hit) in rays.iter().zip(&hits) {
        let r = dagtrace::Ray {
            origin: ray.origin,
            dir: ray.dir,
            tmin: ray.tmin,
            tmax: ray.tmax,
            level: ray.level,
        };
        let c = cpu.trace(&r).expect("CPU");
        let c = Hit {
            hit: c.hit,
            t: c.t,
            voxel: c.voxel,
            level: c.level,
            face: c.face,
            index: c.index,
        };
        assert!(same_cell(hit, &c), "{ray:?}: GPU {hit:?} != CPU {c:?}");
        assert!(hit.hit);
        let code = morton::encode(hit.voxel[0], hit.voxel[1], hit.voxel[2]);
        let solid_before = if hit.voxel.iter().all(|&x| x < 256) {
            code
        } else {
            1 << 24
        };
        let extra_before = codes.iter().filter(|&&c| c < code).count() as u64;
        assert_eq!(hit.index, Some(solid_before + extra_before), "{ray:?}");
    }
    // The 2.0 file of the same voxels gives the same indices: its saturated
    // records' counts are in the table under their expanded word index
    // (expanded) or the word of their first byte (in place).
    let v2 = dagfmt::v2file::upgrade(&dag).expect("upgrade");
    for v2_layout in LAYOUTS {
        let options = GpuOptions {
            v2_layout,
            ..GpuOptions::default()
        };
        let two = tracer_v2(ctx, &v2, options)
            .trace(&rays)
            .expect("2.0 trace");
        assert_same_hits(&rays, &hits, &two, &format!("saturated, {v2_layout:?}"));
    }
}

#[test]
fn depth_20_and_21_precision() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(4);
    for depth in [20u8, 21] {
        let n = 1u32 << depth;
        let mut voxels = vec![
            [0, 0, 0],
            [n - 1, n - 1, n - 1],
            [n / 2, n / 2 - 1, n / 2],
            [n / 2 - 1, n / 2, n / 2 - 1],
        ];
        for _ in 0..40 {
            let base: [u32; 3] = std::array::from_fn(|_| rng.below(u64::from(n - 8)) as u32);
            for _ in 0..6 {
                voxels.push(std::array::from_fn(|i| base[i] + rng.below(3) as u32));
            }
        }
        let t = TestDag::new(
            depth,
            AttributeKind::VoxelCount,
            voxels.clone(),
            [-1000.0, 20.0, 0.125],
            2048.0,
        );
        let mut rays = Vec::new();
        let scale = 2048.0 / f64::from(n);
        for _ in 0..800 {
            let v = voxels[rng.below(voxels.len() as u64) as usize];
            // Aim at a point of the voxel from far away, from outside the
            // cube or from inside it.
            let target: [f64; 3] = std::array::from_fn(|i| f64::from(v[i]) + rng.range(0.05, 0.95));
            let from: [f64; 3] = if rng.chance(0.5) {
                std::array::from_fn(|_| rng.range(-0.5, 1.5) * f64::from(n))
            } else {
                std::array::from_fn(|i| target[i] + rng.range(-300.0, 300.0))
            };
            let origin: [f32; 3] =
                std::array::from_fn(|i| (t.root_min[i] + from[i] * scale) as f32);
            let dir: [f32; 3] = std::array::from_fn(|i| ((target[i] - from[i]) * scale) as f32);
            rays.push(Ray {
                origin,
                dir,
                tmin: 0.0,
                tmax: f32::INFINITY,
                level: None,
            });
        }
        rays.extend(random_rays(&mut rng, &t, 400));
        check_against_references(
            ctx,
            &t,
            &rays,
            GpuOptions::default(),
            &format!("depth {depth}"),
        );
        check_against_references(
            ctx,
            &t,
            &rays,
            GpuOptions {
                stack: StackMode::Short(4),
                ..GpuOptions::default()
            },
            &format!("depth {depth}, short stack"),
        );
    }
}

#[test]
fn levels_of_detail() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(5);
    let t = TestDag::new(
        7,
        AttributeKind::VoxelCount,
        random_voxels(&mut rng, 7, 8),
        [2.0, 3.0, 4.0],
        16.0,
    );
    let mut rays = random_rays(&mut rng, &t, 700);
    for (k, ray) in rays.iter_mut().enumerate() {
        ray.level = Some((k % 8) as u8);
    }
    check_against_references(ctx, &t, &rays, GpuOptions::default(), "levels of detail");
    let dag = t.dag();
    let gpu = tracer(ctx, &dag, GpuOptions::default());
    let deep = Ray {
        level: Some(8),
        ..rays[0]
    };
    assert_eq!(
        gpu.trace(&[rays[1], deep]),
        Err(GpuError::LevelTooDeep {
            ray: 1,
            level: 8,
            depth: 7
        })
    );
}

#[test]
fn empty_and_tiny_volumes() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(6);
    let empty = TestDag::new(5, AttributeKind::VoxelCount, Vec::new(), [0.0; 3], 1.0);
    let rays = random_rays(&mut rng, &empty, 200);
    let hits = tracer(ctx, &empty.dag(), GpuOptions::default())
        .trace(&rays)
        .expect("trace");
    assert!(hits.iter().all(|h| *h == Hit::MISS));
    // Depth 2: the root is a single leaf.
    let voxels: Vec<[u32; 3]> = (0..64u32)
        .filter(|i| i % 3 != 0)
        .map(|i| [i & 3, (i >> 2) & 3, i >> 4])
        .collect();
    let t = TestDag::new(2, AttributeKind::VoxelCount, voxels, [0.0; 3], 4.0);
    let rays = random_rays(&mut rng, &t, 400);
    check_against_references(ctx, &t, &rays, GpuOptions::default(), "depth 2");
    assert_eq!(
        tracer(ctx, &t.dag(), GpuOptions::default())
            .trace(&[])
            .expect("trace"),
        Vec::new()
    );
}

#[test]
fn uploads_from_a_memory_mapped_file_in_several_dispatches() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(7);
    let t = TestDag::new(
        6,
        AttributeKind::VoxelCount,
        random_voxels(&mut rng, 6, 8),
        [0.0; 3],
        1.0,
    );
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("model.vdag");
    std::fs::write(&path, &t.bytes).expect("write");
    let file = dagfmt::mmap::MappedFile::open(&path).expect("map");
    let dag = Dag::open(file.bytes()).expect("open");
    let rays = random_rays(&mut rng, &t, 1000);
    let options = GpuOptions {
        rays_per_dispatch: 64 * 3 + 5,
        ..GpuOptions::default()
    };
    let gpu = tracer(ctx, &dag, options);
    let (hits, stats) = gpu.trace_with_stats(&rays).expect("trace");
    assert!(stats.gpu_rays > 0 && stats.max_iterations > 0);
    assert_agrees_with_cpu(&rays, &hits, &cpu_hits(&dag, &rays), "memory-mapped");
}

#[test]
fn bad_pointers_and_runaway_rays_are_errors() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(8);
    let t = TestDag::new(
        6,
        AttributeKind::VoxelCount,
        random_voxels(&mut rng, 6, 8),
        [0.0; 3],
        1.0,
    );
    let rays = random_rays(&mut rng, &t, 300);
    // Iteration limit.
    let limited = tracer(
        ctx,
        &t.dag(),
        GpuOptions {
            max_iterations: Some(2),
            ..GpuOptions::default()
        },
    );
    let Err(GpuError::IterationLimit { ray, limit: 2 }) = limited.trace(&rays) else {
        panic!("expected the iteration limit");
    };
    // The first ray over the limit is the one named: the rays before it pass.
    assert!(limited.trace(&rays[..ray]).is_ok());
    assert_eq!(
        limited.trace(&rays[ray..=ray]),
        Err(GpuError::IterationLimit { ray: 0, limit: 2 })
    );
    // Every pointer of the root made to point far outside level 1.
    let mut bytes = t.bytes.clone();
    let dag = Dag::open(&t.bytes).expect("open");
    let root = dag.levels()[0];
    let node = dag.node(0, 0).expect("root");
    let width = usize::from(root.pointer_width);
    let start = root.file_offset as usize + 4;
    for b in &mut bytes[start..start + width * node.child_count() as usize] {
        *b = 0xff;
    }
    let broken = Dag::open(&bytes).expect("open");
    let gpu = tracer(ctx, &broken, GpuOptions::default());
    let aimed: Vec<Ray> = rays
        .into_iter()
        .filter(|r| r.dir.iter().all(|d| d.is_finite()))
        .collect();
    let Err(GpuError::MalformedPointer { ray }) = gpu.trace(&aimed) else {
        panic!("expected a malformed pointer");
    };
    assert!(gpu.trace(&aimed[..ray]).is_ok());
    assert_eq!(
        gpu.trace(&aimed[ray..=ray]),
        Err(GpuError::MalformedPointer { ray: 0 })
    );
    // Options that cannot work.
    for options in [
        GpuOptions {
            stack: StackMode::Short(3),
            ..GpuOptions::default()
        },
        GpuOptions {
            rays_per_dispatch: 0,
            ..GpuOptions::default()
        },
        GpuOptions {
            max_binding_bytes: Some(8),
            ..GpuOptions::default()
        },
    ] {
        assert!(
            matches!(
                GpuTracer::with_context(ctx, &t.dag(), &options),
                Err(GpuError::InvalidOptions(_))
            ),
            "{options:?}"
        );
    }
}

#[test]
fn render_matches_cpu_camera_rays() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(9);
    // Ground, a ball and some blobs.
    let n = 128i32;
    let mut voxels = random_voxels(&mut rng, 7, 25);
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let (dx, dy, dz) = (x - n / 2, y - n / 3, z - n / 2);
                if y < n / 8 + (x / 16 + z / 16) % 3
                    || dx * dx + dy * dy + dz * dz <= (n / 5) * (n / 5)
                {
                    voxels.push([x as u32, y as u32, z as u32]);
                }
            }
        }
    }
    let t = TestDag::new(7, AttributeKind::VoxelCount, voxels, [-1.0, 0.0, 2.0], 5.0);
    let dag = t.dag();
    let (w, h) = (96u32, 64u32);
    let camera = Camera::looking_at_cube(t.root_min, t.root_size, f64::from(w) / f64::from(h));
    let out = tracer(ctx, &dag, GpuOptions::default())
        .render(&camera, w, h, None)
        .expect("render");
    assert_eq!(out.hits.len(), (w * h) as usize);
    assert_eq!(out.rgba.len(), (w * h * 4) as usize);
    // The CPU makes the same camera rays in f64: the answers agree except
    // where the f32 rays graze a cell edge.
    let frame = camera.frame().expect("frame");
    let rays: Vec<Ray> = frame
        .rays(w, h, None)
        .into_iter()
        .map(|r| Ray {
            origin: r.origin,
            dir: r.dir,
            tmin: r.tmin,
            tmax: r.tmax,
            level: r.level,
        })
        .collect();
    let cpu = cpu_hits(&dag, &rays);
    let agree = out
        .hits
        .iter()
        .zip(&cpu)
        .filter(|(g, c)| {
            g.hit == c.hit && g.voxel == c.voxel && g.face == c.face && g.index == c.index
        })
        .count();
    let hits = cpu.iter().filter(|c| c.hit).count();
    assert!(hits > (w * h / 10) as usize, "only {hits} pixels hit");
    assert!(
        agree * 100 >= cpu.len() * 98,
        "{agree} of {} pixels agree",
        cpu.len()
    );
    for (g, c) in out.hits.iter().zip(&cpu) {
        if g.hit && c.hit && g.voxel == c.voxel {
            assert!(
                (g.t - c.t).abs() <= 1e-3 * c.t.abs().max(1.0),
                "t {} vs {}",
                g.t,
                c.t
            );
        }
    }
    let cpu_rgb = dagtrace::render::render(
        &dagtrace::Tracer::new(&dag).expect("CPU"),
        &frame,
        w,
        h,
        dagtrace::render::Shade::Normal,
        None,
    )
    .expect("CPU render");
    let same_pixels = out
        .rgba
        .chunks(4)
        .zip(cpu_rgb.chunks(3))
        .filter(|(g, c)| &g[..3] == *c && g[3] == 255)
        .count();
    assert!(
        same_pixels * 100 >= cpu.len() * 98,
        "{same_pixels} of {} pixels equal",
        cpu.len()
    );
    let timed = tracer(ctx, &dag, GpuOptions::default())
        .time_render(&camera, w, h, 2)
        .expect("time");
    assert_eq!(timed.len(), 2);
}

#[test]
fn command_line_gpu_backend_gives_the_cpu_answers() {
    let Some(_) = context() else { return };
    let mut rng = Rng(77);
    let voxels = random_voxels(&mut rng, 6, 20);
    let t = TestDag::new(6, AttributeKind::VoxelCount, voxels, [0.5, -1.0, 3.0], 2.0);
    // The batch formats name levels 1..=21; level 0 (the root cell) is API-only.
    let rays: Vec<Ray> = random_rays(&mut rng, &t, 2000)
        .into_iter()
        .filter(|r| r.level != Some(0))
        .collect();
    let cpu = cpu_hits(&t.dag(), &rays);
    let dir = tempfile::tempdir().expect("temp dir");
    let vdag = dir.path().join("scene.vdag");
    std::fs::write(&vdag, &t.bytes).expect("write");
    // The same voxels in format 2.0: traced on the GPU too, with the same answers.
    let vdag2 = dir.path().join("scene2.vdag");
    std::fs::write(&vdag2, dagfmt::v2file::upgrade(&t.dag()).expect("upgrade")).expect("write");
    let rays_path = dir.path().join("rays.txt");
    let mut text = Vec::new();
    dagfmt::batch::write_rays_text(&mut text, &rays).expect("format rays");
    std::fs::write(&rays_path, text).expect("write rays");
    let run = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_dagtrace"))
            .args(args)
            .output()
            .expect("run dagtrace");
        assert!(
            out.status.success(),
            "dagtrace {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let path = |p: &std::path::Path| p.to_str().expect("UTF-8 path").to_string();
    let mut by_file: Vec<Vec<Hit>> = Vec::new();
    for (file, extra) in [&vdag, &vdag2].into_iter().flat_map(|f| {
        [
            (f, &["--backend", "gpu"][..]),
            (f, &["--backend", "gpu", "--short-stack", "2"]),
            (f, &["--backend", "auto"]),
        ]
    }) {
        let hits_path = dir.path().join("hits.txt");
        let mut args = vec![
            "trace".to_string(),
            path(file),
            "--rays".into(),
            path(&rays_path),
            "--out".into(),
            path(&hits_path),
            "--force".into(),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let stderr = run(&args);
        assert!(stderr.contains("tracing on the GPU"), "{stderr}");
        let gpu = dagfmt::batch::parse_hits(&std::fs::read(&hits_path).expect("hits"))
            .expect("parse hits");
        assert_eq!(gpu.len(), rays.len());
        assert_agrees_with_cpu(&rays, &gpu, &cpu, &format!("dagtrace trace {extra:?}"));
        for (ray, hit) in rays.iter().zip(&gpu) {
            oracle_check(&t, ray, hit, true)
                .unwrap_or_else(|e| panic!("{extra:?}: ray {ray:?}: {hit:?}: {e}"));
        }
        if let Some(first) = by_file.first() {
            assert_same_hits(&rays, first, &gpu, &format!("{} {extra:?}", file.display()));
        }
        by_file.push(gpu);
    }
    // `render --shade normal` and `--shade lit` of the 2.0 file on the GPU
    // (`auto` too): the 1.0 file's picture.
    for (shade, backend) in [("normal", "gpu"), ("lit", "gpu"), ("lit", "auto")] {
        let mut pictures = Vec::new();
        for file in [&vdag, &vdag2] {
            let png = dir.path().join(format!("{shade}.png"));
            let stderr = run(&[
                "render",
                &path(file),
                "-o",
                &path(&png),
                "--width",
                "64",
                "--height",
                "48",
                "--shade",
                shade,
                "--backend",
                backend,
                "--force",
            ]);
            assert!(
                stderr.contains("tracing on the GPU"),
                "{shade} {backend}: {stderr}"
            );
            pictures.push(std::fs::read(&png).expect("PNG"));
        }
        assert_eq!(
            pictures[0], pictures[1],
            "--shade {shade} --backend {backend}: 2.0 picture differs from 1.0"
        );
    }
    // `render` on both back ends: the same camera rays, so nearly the same pixels.
    let mut images = Vec::new();
    for backend in ["cpu", "gpu"] {
        let png = dir.path().join(format!("{backend}.png"));
        run(&[
            "render",
            &path(&vdag),
            "-o",
            &path(&png),
            "--width",
            "64",
            "--height",
            "48",
            "--backend",
            backend,
        ]);
        images.push(image::open(&png).expect("PNG").to_rgb8().into_raw());
    }
    let differ = images[0]
        .chunks_exact(3)
        .zip(images[1].chunks_exact(3))
        .filter(|(a, b)| a != b)
        .count();
    assert!(differ * 50 <= 64 * 48, "{differ} of 3072 pixels differ");
}

// ------------------------------------------------------------ format 2.0 --

/// The GPU tracer of the 2.0 file `v2` (spec §23), its node levels laid
/// out as `options.v2_layout` asks (checked: a valid file expands).
fn tracer_v2(ctx: &GpuContext, v2: &[u8], options: GpuOptions) -> GpuTracer {
    let dag = dagfmt::Dag2::open(v2).expect("a 2.0 file");
    let gpu = GpuTracer::with_context_v2(ctx, dag.header(), dag.levels(), None, &options)
        .expect("GPU tracer");
    assert_eq!(gpu.v2_layout(), Some(options.v2_layout));
    gpu
}

/// The layouts of a 2.0 DAG's node levels on the device: expanded (spec
/// §23.12, the default) and in place (§23.2).
const LAYOUTS: [V2Layout; 2] = [V2Layout::Expanded, V2Layout::InPlace];

/// Asserts that the 2.0 answers are the 1.0 answers to the bit.
fn assert_same_hits(rays: &[Ray], v1: &[Hit], v2: &[Hit], what: &str) {
    assert_eq!(v1.len(), v2.len(), "{what}");
    let differ: Vec<String> = rays
        .iter()
        .zip(v1.iter().zip(v2))
        .enumerate()
        .filter(|(_, (_, (a, b)))| !same(a, b))
        .map(|(i, (r, (a, b)))| format!("ray {i} {r:?}: 2.0 {b:?}, 1.0 {a:?}"))
        .collect();
    assert!(
        differ.is_empty(),
        "{what}: 2.0 and 1.0 answers differ on {} of {} rays:\n{}",
        differ.len(),
        rays.len(),
        differ[..differ.len().min(10)].join("\n")
    );
}

/// The stacks the 2.0 answers are checked with.
const STACKS: [StackMode; 3] = [StackMode::Full, StackMode::Short(2), StackMode::Short(1)];

/// Format 2.0 on the GPU (spec §23): every conformance trace case upgraded
/// with `dagfmt::v2file::upgrade` gives, on its own rays, the GPU's 1.0
/// answers to the bit (hit, t, cell, face, attribute index), with the full
/// and short stacks, expanded and in place. (The cases' exact ties, where the GPU and CPU tracers
/// may differ within the spec's tolerance, are the suite's to judge; the
/// random DAGs below check against the oracle and the CPU.)
#[test]
fn format_2_conformance_cases_give_the_1_0_answers() {
    let Some(ctx) = context() else { return };
    let cases = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../conformance/cases/trace");
    let mut files: Vec<std::path::PathBuf> = std::fs::read_dir(&cases)
        .expect("the conformance cases")
        .map(|e| e.expect("a directory entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "vdag"))
        .collect();
    files.sort();
    assert!(!files.is_empty(), "no .vdag in {}", cases.display());
    let mut traced = 0;
    for file in &files {
        let name = file.display().to_string();
        let bytes = std::fs::read(file).expect("a case file");
        let rays = dagfmt::batch::parse_rays(
            &std::fs::read(file.with_extension("rays")).expect("the case's rays"),
        )
        .expect("rays parse");
        let dag = Dag::open(&bytes).expect("a case opens");
        // (Rays deeper than the DAG are an error for the whole batch, the
        // same for both versions: the suite checks that.)
        let depth = dag.header().depth;
        let rays: Vec<Ray> = rays
            .into_iter()
            .filter(|r| r.level.is_none_or(|l| l <= depth))
            .collect();
        let v2 = dagfmt::v2file::upgrade(&dag).expect("upgrade");
        let v1_hits = tracer(ctx, &dag, GpuOptions::default())
            .trace(&rays)
            .expect("1.0 trace");
        for stack in STACKS {
            for v2_layout in LAYOUTS {
                let options = GpuOptions {
                    stack,
                    v2_layout,
                    ..GpuOptions::default()
                };
                let hits = tracer_v2(ctx, &v2, options)
                    .trace(&rays)
                    .expect("2.0 trace");
                let what = format!("{name} {stack:?} {v2_layout:?}");
                assert_same_hits(&rays, &v1_hits, &hits, &what);
            }
        }
        traced += rays.len();
    }
    println!("{} cases, {traced} rays: 2.0 = 1.0 on the GPU", files.len());
}

/// Format 2.0 on the GPU over random DAGs (with and without attributes,
/// depths 2 to 9, off-centre root cubes): the 2.0 file's answers are the
/// 1.0 file's to the bit, with the full and short stacks, and pass the
/// oracle; a render through a camera gives the same hits and picture.
#[test]
fn format_2_random_dags_give_the_1_0_answers() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(42);
    let mut hits_seen = 0;
    for (case, depth) in [2u8, 3, 4, 5, 6, 7, 8, 9].into_iter().enumerate() {
        let kind = if case % 3 == 2 {
            AttributeKind::None
        } else {
            AttributeKind::VoxelCount
        };
        let voxels = random_voxels(&mut rng, depth, 8);
        let root_min = [
            rng.range(-10.0, 10.0),
            rng.range(-10.0, 10.0),
            rng.range(-10.0, 10.0),
        ];
        let t = TestDag::new(depth, kind, voxels, root_min, rng.range(0.5, 40.0));
        let dag = t.dag();
        let v2 = dagfmt::v2file::upgrade(&dag).expect("upgrade");
        let rays = random_rays(&mut rng, &t, 800);
        let what = format!("depth {depth}");
        let v1_hits = check_against_references(ctx, &t, &rays, GpuOptions::default(), &what);
        check_2_0_layouts(ctx, &t, &v2, &rays, &v1_hits, &what);
        hits_seen += v1_hits.iter().filter(|h| h.hit).count();
    }
    assert!(hits_seen > 1000, "{hits_seen} hits only");
}

/// The 2.0 file `v2` of `t`'s voxels, expanded and in place, with the full
/// and short stacks, gives `v1_hits` (the GPU's 1.0 answers, checked
/// against the oracle and the CPU) on `rays` to the bit; from depth 5, a
/// render through a camera gives the 1.0 hits and picture.
fn check_2_0_layouts(
    ctx: &GpuContext,
    t: &TestDag,
    v2: &[u8],
    rays: &[Ray],
    v1_hits: &[Hit],
    what: &str,
) {
    for stack in STACKS {
        for v2_layout in LAYOUTS {
            let options = GpuOptions {
                stack,
                v2_layout,
                ..GpuOptions::default()
            };
            let hits = tracer_v2(ctx, v2, options).trace(rays).expect("2.0 trace");
            assert_same_hits(
                rays,
                v1_hits,
                &hits,
                &format!("{what} {stack:?} {v2_layout:?}"),
            );
        }
    }
    if t.depth >= 5 {
        let camera = Camera::looking_at_cube(t.root_min, t.root_size, 1.5);
        let one = tracer(ctx, &t.dag(), GpuOptions::default())
            .render(&camera, 48, 32, None)
            .expect("1.0 render");
        for v2_layout in LAYOUTS {
            let options = GpuOptions {
                v2_layout,
                ..GpuOptions::default()
            };
            let two = tracer_v2(ctx, v2, options)
                .render(&camera, 48, 32, None)
                .expect("2.0 render");
            assert_eq!(
                one, two,
                "{what} {v2_layout:?}: 2.0 render differs from 1.0"
            );
        }
    }
}

/// Random DAGs with mirrored content (each cluster also mirrored across one
/// to three axes of the volume), whose 2.0 files have reflected references
/// on several levels (checked on the expansion): expanded and in place,
/// full and short stacks, the 2.0 answers are the GPU's 1.0 answers to the
/// bit, which pass the oracle and agree with the CPU tracer.
#[test]
fn format_2_mirrored_random_dags_give_the_1_0_answers() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(4242);
    let mut reflected_levels = std::collections::HashSet::new();
    for (case, depth) in [3u8, 4, 5, 6, 7, 8].into_iter().enumerate() {
        let kind = if case % 3 == 2 {
            AttributeKind::None
        } else {
            AttributeKind::VoxelCount
        };
        let n = (1u32 << depth) - 1;
        let mut voxels = random_voxels(&mut rng, depth, 6);
        let mirrored: Vec<[u32; 3]> = voxels
            .iter()
            .map(|v| {
                let axes = 1 + (v[0] ^ v[1] ^ v[2]) % 7;
                std::array::from_fn(|i| if axes >> i & 1 == 1 { n - v[i] } else { v[i] })
            })
            .collect();
        voxels.extend(mirrored);
        let root_min = [
            rng.range(-5.0, 5.0),
            rng.range(-5.0, 5.0),
            rng.range(-5.0, 5.0),
        ];
        let t = TestDag::new(depth, kind, voxels, root_min, rng.range(0.5, 40.0));
        let v2 = dagfmt::v2file::upgrade(&t.dag()).expect("upgrade");
        let dag2 = dagfmt::Dag2::open(&v2).expect("a 2.0 file");
        let expanded = dagfmt::expand::expand_levels(dag2.levels()).expect("expands");
        for (l, level) in expanded.iter().enumerate() {
            let mut at = 0;
            while at < level.words.len() {
                let children = (level.words[at] & 0xff).count_ones() as usize;
                if level.words[at + 1..at + 1 + children]
                    .iter()
                    .any(|w| w & 7 != 0)
                {
                    reflected_levels.insert(l);
                }
                at += 1 + children;
            }
        }
        let rays = random_rays(&mut rng, &t, 800);
        let what = format!("mirrored, depth {depth}");
        let v1_hits = check_against_references(ctx, &t, &rays, GpuOptions::default(), &what);
        check_2_0_layouts(ctx, &t, &v2, &rays, &v1_hits, &what);
    }
    assert!(
        reflected_levels.len() >= 3,
        "reflected references on levels {reflected_levels:?} only"
    );
}

/// A 2.0 DAG whose levels do not expand (its last node level cut by a
/// byte, so its last record runs past the end) is traced in place, as
/// [`V2Layout::InPlace`] traces it: the same answers, or the same error.
#[test]
fn format_2_that_does_not_expand_is_traced_in_place() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(4343);
    let t = TestDag::new(
        6,
        AttributeKind::VoxelCount,
        random_voxels(&mut rng, 6, 6),
        [0.0; 3],
        1.0,
    );
    let dag = t.dag();
    let mut enc = dagfmt::v2::encode(&dag).expect("encode");
    let last = enc.levels.len() - 2;
    enc.levels[last].bytes.pop();
    let views = enc.views();
    assert!(dagfmt::expand::expand_levels(&views).is_err());
    let rays = random_rays(&mut rng, &t, 400);
    let traced = |v2_layout| {
        let options = GpuOptions {
            v2_layout,
            ..GpuOptions::default()
        };
        let gpu = GpuTracer::with_context_v2(ctx, dag.header(), &views, None, &options)
            .expect("GPU tracer");
        assert_eq!(gpu.v2_layout(), Some(V2Layout::InPlace), "{v2_layout:?}");
        assert_eq!(gpu.expansion_time(), None);
        gpu.trace(&rays)
    };
    assert_eq!(traced(V2Layout::Expanded), traced(V2Layout::InPlace));
}

/// The GPU's lit render of a 2.0 DAG (the lit passes compiled with the 2.0
/// variant of the traversal, their neighbourhood lookups through
/// `path_node`, reflected leaves included) gives the 1.0 DAG's surfaces to
/// the bit (hit, face, attribute index, shading normal, shadow, ambient
/// occlusion) and so its image: random DAGs and conformance scenes (whose
/// symmetric shapes make reflected references), expanded (full and short
/// stacks) and in place (full stack), at
/// full depth, at the cells of the leaf level's 4^3 bricks and above them.
#[test]
fn format_2_lit_render_gives_the_1_0_surfaces() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(44);
    let mut scenes: Vec<(String, Vec<u8>)> = Vec::new();
    for depth in [4u8, 6, 7] {
        let voxels = random_voxels(&mut rng, depth, 10);
        let t = TestDag::new(
            depth,
            AttributeKind::VoxelCount,
            voxels,
            [1.0, -2.0, 0.5],
            3.0,
        );
        scenes.push((format!("random depth {depth}"), t.bytes.clone()));
    }
    let cases = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../conformance/cases/trace");
    for name in [
        "mesh-sphere-d6",
        "mesh-torus-d6",
        "lod-blobs-d6",
        "checker2-d4",
    ] {
        let bytes = std::fs::read(cases.join(format!("{name}.vdag"))).expect("a case file");
        scenes.push((name.to_string(), bytes));
    }
    let options = dagtrace::lit::LitOptions {
        samples: 2,
        ao_rays: 4,
        ..dagtrace::lit::LitOptions::default()
    };
    let mut lit_surfaces = 0;
    for (name, bytes) in &scenes {
        let dag = Dag::open(bytes).expect("a scene opens");
        let depth = dag.header().depth;
        let v2 = dagfmt::v2file::upgrade(&dag).expect("upgrade");
        let camera = Camera::automatic(&dag, 4.0 / 3.0);
        let one = tracer(ctx, &dag, GpuOptions::default());
        for level in [None, Some(depth - 1), Some(depth - 2), Some(depth - 3)] {
            let level = level.filter(|&l| l >= 1);
            let expected = one
                .lit_surfaces(&camera, 40, 30, level, &options)
                .expect("1.0 lit surfaces");
            let image = one
                .render_lit(&camera, 40, 30, level, &options, |_| None)
                .expect("1.0 lit image");
            // Expanded with every stack; in place with the full one.
            let configurations = STACKS
                .iter()
                .map(|&stack| (stack, V2Layout::Expanded))
                .chain([(StackMode::Full, V2Layout::InPlace)]);
            for (stack, v2_layout) in configurations {
                let two = tracer_v2(
                    ctx,
                    &v2,
                    GpuOptions {
                        stack,
                        v2_layout,
                        ..GpuOptions::default()
                    },
                );
                let what = format!("{name}, level {level:?}, {stack:?}, {v2_layout:?}");
                let surfaces = two
                    .lit_surfaces(&camera, 40, 30, level, &options)
                    .expect("2.0 lit surfaces");
                let differ = expected.iter().zip(&surfaces).position(|(a, b)| a != b);
                assert!(
                    differ.is_none() && expected.len() == surfaces.len(),
                    "{what}: surface {differ:?} differs: 1.0 {:?}, 2.0 {:?}",
                    differ.map(|i| expected[i]),
                    differ.map(|i| surfaces[i])
                );
                let two_image = two
                    .render_lit(&camera, 40, 30, level, &options, |_| None)
                    .expect("2.0 lit image");
                assert!(two_image == image, "{what}: the 2.0 lit image differs");
            }
            lit_surfaces += expected.iter().filter(|s| s.hit && s.face != 0).count();
        }
    }
    assert!(lit_surfaces > 2000, "{lit_surfaces} lit surfaces only");
}

/// A 2.0 DAG's levels that do not match the depth are an error, not a
/// panic.
#[test]
fn format_2_refusals() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(43);
    let t = TestDag::new(
        5,
        AttributeKind::VoxelCount,
        random_voxels(&mut rng, 5, 4),
        [0.0; 3],
        1.0,
    );
    let v2 = dagfmt::v2file::upgrade(&t.dag()).expect("upgrade");
    let dag = dagfmt::Dag2::open(&v2).expect("a 2.0 file");
    let short = GpuTracer::with_context_v2(
        ctx,
        dag.header(),
        &dag.levels()[1..],
        None,
        &GpuOptions::default(),
    );
    assert!(
        matches!(short, Err(GpuError::InvalidOptions(_))),
        "{short:?}"
    );
}
