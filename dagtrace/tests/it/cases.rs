//! Hand-made cases with known answers, and the behaviour on malformed files.

use dagfmt::batch::{Hit, Ray};
use dagfmt::builder::DagBuilder;
use dagfmt::{AttributeKind, Dag, ErrorCode};
use dagtrace::{TraceError, Tracer};

use crate::common::{Rng, build};
use crate::oracle::Reference;

fn ray(origin: [f32; 3], dir: [f32; 3]) -> Ray {
    Ray {
        origin,
        dir,
        tmin: 0.0,
        tmax: f32::INFINITY,
        level: None,
    }
}

/// One voxel at (1, 2, 3) of a depth-3 grid whose root cube is [0, 8)^3.
fn one_voxel() -> Vec<u8> {
    build(3, AttributeKind::VoxelCount, &[[1, 2, 3]], [0.0; 3], 8.0)
}

#[test]
fn each_face_is_entered_from_its_side() {
    let bytes = one_voxel();
    let dag = Dag::open(&bytes).unwrap();
    let tracer = Tracer::new(&dag).unwrap();
    let center = [1.5f32, 2.5, 3.5];
    for (axis, sign, face) in [
        (0, 1.0, 1u8),
        (0, -1.0, 2),
        (1, 1.0, 3),
        (1, -1.0, 4),
        (2, 1.0, 5),
        (2, -1.0, 6),
    ] {
        let mut origin = center;
        origin[axis] -= sign * 10.0;
        let mut dir = [0.0; 3];
        dir[axis] = sign * 2.0;
        let hit = tracer.trace(&ray(origin, dir)).unwrap();
        assert!(hit.hit, "face {face}");
        assert_eq!(hit.voxel, [1, 2, 3]);
        assert_eq!(hit.face, face);
        assert_eq!(hit.level, 3);
        assert_eq!(hit.t, 4.75, "entry at distance 9.5 with speed 2");
        assert_eq!(hit.index, Some(0));
    }
}

#[test]
fn origin_inside_an_occupied_voxel() {
    let bytes = one_voxel();
    let dag = Dag::open(&bytes).unwrap();
    let tracer = Tracer::new(&dag).unwrap();
    let mut r = ray([1.25, 2.5, 3.75], [0.3, -1.0, 0.2]);
    r.tmin = 0.125;
    let hit = tracer.trace(&r).unwrap();
    assert_eq!(
        (hit.hit, hit.t, hit.face, hit.voxel),
        (true, 0.125, 0, [1, 2, 3])
    );
    // With tmin = -inf the entry is where the line enters the cell: y = 3 at t = -0.5.
    r.tmin = f32::NEG_INFINITY;
    let hit = tracer.trace(&r).unwrap();
    assert_eq!((hit.hit, hit.t, hit.face), (true, -0.5, 4));
    // A zero direction is a point query.
    let hit = tracer.trace(&ray([1.25, 2.5, 3.75], [0.0; 3])).unwrap();
    assert_eq!(
        (hit.hit, hit.t, hit.face, hit.voxel),
        (true, 0.0, 0, [1, 2, 3])
    );
    assert!(!tracer.trace(&ray([0.5, 2.5, 3.75], [0.0; 3])).unwrap().hit);
}

#[test]
fn invalid_rays_miss() {
    let bytes = one_voxel();
    let dag = Dag::open(&bytes).unwrap();
    let tracer = Tracer::new(&dag).unwrap();
    let good = ray([-5.0, 2.5, 3.5], [1.0, 0.0, 0.0]);
    assert!(tracer.trace(&good).unwrap().hit);
    for bad in [
        Ray {
            origin: [f32::NAN, 2.5, 3.5],
            ..good
        },
        Ray {
            dir: [1.0, f32::NAN, 0.0],
            ..good
        },
        Ray {
            tmin: f32::NAN,
            ..good
        },
        Ray {
            tmin: 2.0,
            tmax: 1.0,
            ..good
        },
        Ray { tmax: 5.5, ..good },
        Ray { tmin: 7.5, ..good },
    ] {
        assert_eq!(tracer.trace(&bad).unwrap(), Hit::MISS, "{bad:?}");
        assert!(!tracer.occluded(&bad).unwrap());
    }
    // Exact boundary points belong to the cell the ray moves into (both
    // answers are within the tolerance; this is the documented tie rule):
    // tmax exactly at the entry touches the cell, tmin exactly at its exit does not.
    assert_eq!(tracer.trace(&Ray { tmax: 6.0, ..good }).unwrap().t, 6.0);
    assert!(!tracer.trace(&Ray { tmin: 7.0, ..good }).unwrap().hit);
    assert_eq!(
        tracer.trace(&Ray {
            level: Some(4),
            ..good
        }),
        Err(TraceError::LevelTooDeep { level: 4, depth: 3 })
    );
}

#[test]
fn empty_volume_misses_everything() {
    let bytes = build(5, AttributeKind::VoxelCount, &[], [0.0; 3], 1.0);
    let dag = Dag::open(&bytes).unwrap();
    let tracer = Tracer::new(&dag).unwrap();
    assert!(
        !tracer
            .trace(&ray([0.5, 0.5, -1.0], [0.0, 0.0, 1.0]))
            .unwrap()
            .hit
    );
    assert!(!tracer.trace(&ray([0.5, 0.5, 0.5], [0.0; 3])).unwrap().hit);
}

#[test]
fn level_of_detail_reports_coarse_cells() {
    // Voxels (5, 6, 7) and (4, 6, 7) at depth 4; ray along +x at y = 6.5, z = 7.5.
    let bytes = build(
        4,
        AttributeKind::VoxelCount,
        &[[5, 6, 7], [4, 6, 7], [0, 0, 0]],
        [0.0; 3],
        16.0,
    );
    let dag = Dag::open(&bytes).unwrap();
    let tracer = Tracer::new(&dag).unwrap();
    let base = ray([-1.0, 6.5, 7.5], [1.0, 0.0, 0.0]);
    for level in 0..=4u8 {
        let hit = tracer
            .trace(&Ray {
                level: Some(level),
                ..base
            })
            .unwrap();
        let shift = 4 - level;
        assert!(hit.hit);
        assert_eq!(hit.level, level);
        assert_eq!(
            hit.voxel,
            [4 >> shift, 6 >> shift, 7 >> shift],
            "level {level}"
        );
        let size = f32::from(1u8 << shift);
        assert_eq!(hit.t, ((4 >> shift) as f32) * size + 1.0, "level {level}");
        // The index of the first voxel of the cell in Morton order.
        let first = dag
            .voxels()
            .position(|v| v.unwrap().map(|c| c >> shift) == hit.voxel)
            .unwrap();
        assert_eq!(hit.index, Some(first as u64), "level {level}");
    }
}

#[test]
fn attribute_kind_zero_has_no_index() {
    let bytes = build(3, AttributeKind::None, &[[1, 2, 3]], [0.0; 3], 8.0);
    let dag = Dag::open(&bytes).unwrap();
    let tracer = Tracer::new(&dag).unwrap();
    let hit = tracer
        .trace(&ray([-5.0, 2.5, 3.5], [1.0, 0.0, 0.0]))
        .unwrap();
    assert!(hit.hit);
    assert_eq!(hit.index, None);
}

/// A thread remembers the sums behind its last attribute index so that the
/// next hit nearby reuses the levels both paths share. Two tracers over
/// different scenes of the same depth (and a clone of one), alternating on one
/// thread ray by ray and batch by batch, with levels of detail mixed in:
/// every index must still be the one of its own scene and level.
#[test]
fn indices_stay_right_when_tracers_and_levels_alternate() {
    let depth = 9;
    let n = 1u32 << depth;
    let shell = |centre: [f64; 3], radius: f64| {
        let mut voxels = Vec::new();
        let (lo, hi) = (
            (centre[0] - radius - 2.0) as u32,
            (centre[0] + radius + 2.0) as u32,
        );
        for z in lo..hi.min(n) {
            for y in lo..hi.min(n) {
                for x in lo..hi.min(n) {
                    let d2: f64 = [x, y, z]
                        .iter()
                        .zip(&centre)
                        .map(|(&p, &c)| (f64::from(p) + 0.5 - c).powi(2))
                        .sum();
                    if d2 <= radius * radius && d2 >= (radius - 1.5) * (radius - 1.5) {
                        voxels.push([x, y, z]);
                    }
                }
            }
        }
        voxels
    };
    let a = build(
        depth,
        AttributeKind::VoxelCount,
        &shell([256.0; 3], 120.0),
        [0.0; 3],
        512.0,
    );
    let mut b_voxels = shell([250.0; 3], 100.0);
    b_voxels.extend(shell([250.0; 3], 60.0));
    let b = build(depth, AttributeKind::VoxelCount, &b_voxels, [0.0; 3], 512.0);
    let (dag_a, dag_b) = (Dag::open(&a).unwrap(), Dag::open(&b).unwrap());
    let (ref_a, ref_b) = (Reference::new(&dag_a), Reference::new(&dag_b));
    let tracer_a = Tracer::new(&dag_a).unwrap();
    let tracer_b = Tracer::new(&dag_b).unwrap();
    let clone_a = tracer_a.clone();
    // Coherent 16x16 bundles (batches trace them as packets) from points
    // around the scenes, at full depth and at two coarser levels.
    let mut rng = Rng(41);
    let mut bundles = Vec::new();
    for k in 0..12 {
        let origin = [0; 3].map(|_| rng.range(-300.0, 812.0) as f32);
        let target = [0; 3].map(|_| rng.range(180.0, 330.0) as f32);
        let level = [None, Some(depth - 1), Some(depth - 3)][k % 3];
        let bundle: Vec<Ray> = (0..256)
            .map(|i| {
                let (u, v) = ((i % 16) as f32 - 7.5, (i / 16) as f32 - 7.5);
                let t = [
                    target[0] + u * 1.3,
                    target[1] + v * 1.3,
                    target[2] + (u - v) * 0.4,
                ];
                Ray {
                    level,
                    ..ray(origin, [0, 1, 2].map(|a| t[a] - origin[a]))
                }
            })
            .collect();
        bundles.push(bundle);
    }
    let check = |reference: &Reference, ray: &Ray, hit: &Hit, what: &str| {
        if hit.hit {
            let level = ray.level.unwrap_or(depth);
            let expected = reference.index_of(hit.voxel, level);
            assert_eq!(hit.index, Some(expected), "{what}: {ray:?} -> {hit:?}");
        }
        usize::from(hit.hit)
    };
    let mut hits = 0;
    for bundle in &bundles {
        let mut batch = vec![Hit::MISS; bundle.len()];
        for (tracer, reference, what) in [
            (&tracer_a, &ref_a, "a"),
            (&tracer_b, &ref_b, "b"),
            (&clone_a, &ref_a, "clone of a"),
        ] {
            tracer.trace_sequential_into(bundle, &mut batch).unwrap();
            for (ray, hit) in bundle.iter().zip(&batch) {
                hits += check(reference, ray, hit, what);
            }
        }
        for ray in bundle {
            hits += check(&ref_a, ray, &tracer_a.trace(ray).unwrap(), "a, one ray");
            hits += check(&ref_b, ray, &tracer_b.trace(ray).unwrap(), "b, one ray");
        }
    }
    assert!(hits > 5000, "{hits} hits");
    // Cells of two levels with the same coordinates, one after the other:
    // voxel (0, 5, 5) and the level-6 cell (0, 5, 5) of a solid corner cube.
    let corner: Vec<[u32; 3]> = (0..64u32 * 64 * 64)
        .map(|i| [i % 64, i / 64 % 64, i / 4096])
        .collect();
    let c = build(depth, AttributeKind::VoxelCount, &corner, [0.0; 3], 512.0);
    let dag_c = Dag::open(&c).unwrap();
    let (ref_c, tracer_c) = (Reference::new(&dag_c), Tracer::new(&dag_c).unwrap());
    let fine = ray([-10.0, 5.5, 5.5], [1.0, 0.0, 0.0]);
    let coarse = Ray {
        level: Some(6),
        ..ray([-10.0, 44.0, 44.0], [1.0, 0.0, 0.0])
    };
    for ray in [fine, coarse, fine] {
        let hit = tracer_c.trace(&ray).unwrap();
        assert_eq!(hit.voxel, [0, 5, 5]);
        check(&ref_c, &ray, &hit, "c");
    }
}

#[test]
fn indices_agree_with_the_reader() {
    let mut rng = Rng(7);
    let depth = 7;
    let voxels: Vec<[u32; 3]> = (0..3000)
        .map(|_| [0; 3].map(|_| rng.below(128) as u32))
        .collect();
    let bytes = build(depth, AttributeKind::VoxelCount, &voxels, [0.0; 3], 128.0);
    let dag = Dag::open(&bytes).unwrap();
    let tracer = Tracer::new(&dag).unwrap();
    let mut checked = 0;
    for _ in 0..2000 {
        let o = [0; 3].map(|_| rng.range(-50.0, 178.0) as f32);
        let v = voxels[rng.below(voxels.len() as u64) as usize];
        let dir = [0, 1, 2].map(|i| v[i] as f32 + 0.5 - o[i]);
        let hit = tracer.trace(&ray(o, dir)).unwrap();
        if hit.hit {
            let [x, y, z] = hit.voxel;
            assert_eq!(hit.index, dag.voxel_index(x, y, z).unwrap());
            checked += 1;
        }
    }
    assert!(checked > 1500);
}

/// Nodes holding 2^24 voxels or more store a saturated count; the tracer sums
/// their children. Depth 9 with the two lowest root octants full: both level-1
/// nodes hold 256^3 = 2^24 voxels (saturated), and a hit in octant 1 has index
/// 2^24 + its rank inside the octant (its Morton code there).
#[test]
fn saturated_counts_are_summed() {
    let mut builder = DagBuilder::new(9, AttributeKind::VoxelCount).unwrap();
    for brick in 0..(2u64 << 18) {
        builder.push_brick(brick, u64::MAX).unwrap();
    }
    let bytes = builder.finish().unwrap().to_bytes();
    let dag = Dag::open(&bytes).unwrap();
    let root = dag.node(0, 0).unwrap();
    assert_eq!(root.attribute(), dagfmt::layout::COUNT_SATURATED);
    let tracer = Tracer::new(&dag).unwrap();
    let mut rng = Rng(11);
    for _ in 0..200 {
        // Grid = world here (root cube [0, 1) scaled by 512): aim from -x.
        let target = [
            rng.range(0.0, 512.0),
            rng.range(0.0, 256.0),
            rng.range(0.0, 256.0),
        ];
        let r = Ray {
            origin: [-0.5, (target[1] / 512.0) as f32, (target[2] / 512.0) as f32],
            dir: [1.0, 0.0, 0.0],
            ..ray([0.0; 3], [1.0, 0.0, 0.0])
        };
        let hit = tracer.trace(&r).unwrap();
        assert!(hit.hit);
        let [x, y, z] = hit.voxel;
        assert_eq!(x, 0);
        assert_eq!(hit.index, Some(dagfmt::morton::encode(x, y, z)));
        // From +x the first voxel is in octant 1 (x >= 256).
        let back = tracer
            .trace(&Ray {
                origin: [1.5, r.origin[1], r.origin[2]],
                dir: [-1.0, 0.0, 0.0],
                ..r
            })
            .unwrap();
        let [x, y, z] = back.voxel;
        assert_eq!(x, 511);
        assert_eq!(back.index, Some(dagfmt::morton::encode(x, y, z)));
        assert!(back.index.unwrap() >= 1 << 24);
    }
}

/// Depth 20 and 21: cells are 2^-20 of the cube; precision of the f32
/// traversal must still place hits within the tolerance.
#[test]
fn deep_dags_trace_within_tolerance() {
    for depth in [16u8, 20, 21] {
        let n = 1u64 << depth;
        let mut rng = Rng(u64::from(depth));
        let voxels: Vec<[u32; 3]> = (0..40)
            .map(|_| [0; 3].map(|_| rng.below(n) as u32))
            .chain([[0, 0, 0], [(n - 1) as u32; 3], [(n / 2) as u32; 3]])
            .collect();
        let bytes = build(
            depth,
            AttributeKind::VoxelCount,
            &voxels,
            [-3.0, 1.0, 2.0],
            10.0,
        );
        let dag = Dag::open(&bytes).unwrap();
        let reference = Reference::new(&dag);
        let tracer = Tracer::new(&dag).unwrap();
        let mut hits = 0;
        for _ in 0..400 {
            let v = voxels[rng.below(voxels.len() as u64) as usize];
            let target = v.map(|c| f64::from(c) + rng.range(0.2, 0.8));
            let o = [0; 3].map(|_| rng.range(-0.5, 1.5) * n as f64);
            let to_world = |g: f64, i: usize| [-3.0, 1.0, 2.0][i] + g * 10.0 / n as f64;
            let origin = [0, 1, 2].map(|i| to_world(o[i], i) as f32);
            let target_w = [0, 1, 2].map(|i| to_world(target[i], i));
            let dir = [0, 1, 2].map(|i| (target_w[i] - f64::from(origin[i])) as f32);
            let r = ray(origin, dir);
            let hit = tracer.trace(&r).unwrap();
            reference
                .check(&r, &hit)
                .unwrap_or_else(|e| panic!("depth {depth}: {r:?} {hit:?}: {e}"));
            hits += usize::from(hit.hit);
        }
        assert!(hits > 300, "depth {depth}: only {hits} hits");
    }
}

#[test]
fn far_origins_and_tiny_direction_components() {
    let bytes = build(
        6,
        AttributeKind::VoxelCount,
        &[[10, 20, 30], [40, 41, 42]],
        [0.0; 3],
        64.0,
    );
    let dag = Dag::open(&bytes).unwrap();
    let tracer = Tracer::new(&dag).unwrap();
    // A million cube sizes away along -z.
    let hit = tracer
        .trace(&ray([10.5, 20.5, -64.0e6], [0.0, 0.0, 1.0]))
        .unwrap();
    assert!(hit.hit);
    assert_eq!(hit.voxel, [10, 20, 30]);
    assert_eq!(hit.face, 5);
    assert!((f64::from(hit.t) - (64.0e6 + 30.0)).abs() < 8.0);
    // Direction components far below the others behave like zero.
    for tiny in [1e-30f32, -1e-30, 1e-45, 1e-12] {
        let hit = tracer
            .trace(&ray([10.5, 20.5, -5.0], [tiny, tiny, 1.0]))
            .unwrap();
        assert_eq!(
            (hit.hit, hit.voxel, hit.face),
            (true, [10, 20, 30], 5),
            "tiny {tiny}"
        );
        assert_eq!(hit.t, 35.0);
    }
}

/// Corrupting the level sections must never panic or hang: the tracer either
/// answers or reports the malformed pointer.
#[test]
fn malformed_dags_never_panic() {
    let mut rng = Rng(99);
    let voxels: Vec<[u32; 3]> = (0..500)
        .map(|_| [0; 3].map(|_| rng.below(64) as u32))
        .collect();
    let bytes = build(6, AttributeKind::VoxelCount, &voxels, [0.0; 3], 64.0);
    let dag = Dag::open(&bytes).unwrap();
    let first = dag.levels()[0].file_offset as usize;
    let mut errors = 0;
    for case in 0..300 {
        let mut corrupt = bytes.clone();
        for _ in 0..1 + case % 8 {
            let at = first + rng.below((corrupt.len() - first) as u64) as usize;
            corrupt[at] = rng.next_u64() as u8;
        }
        let Ok(dag) = Dag::open(&corrupt) else {
            continue;
        };
        let Ok(tracer) = Tracer::new(&dag) else {
            errors += 1;
            continue;
        };
        for _ in 0..50 {
            let o = [0; 3].map(|_| rng.range(-20.0, 84.0) as f32);
            let d = [0; 3].map(|_| rng.range(-1.0, 1.0) as f32);
            match tracer.trace(&ray(o, d)) {
                Ok(_) => {}
                Err(TraceError::Malformed(e)) => {
                    assert!(
                        matches!(
                            e.code,
                            ErrorCode::PointerOutOfRange | ErrorCode::TruncatedNode
                        ),
                        "{e}"
                    );
                    errors += 1;
                }
                Err(e) => panic!("unexpected error {e}"),
            }
        }
    }
    assert!(
        errors > 0,
        "some corruption must lead a pointer out of range"
    );
}

#[test]
fn pointer_out_of_range_is_reported() {
    // Depth 4: level 0 (root), level 1 (nodes), level 2 (leaves). Point the
    // root's only pointer past the end of level 1.
    let bytes = build(4, AttributeKind::None, &[[0, 0, 0]], [0.0; 3], 16.0);
    let dag = Dag::open(&bytes).unwrap();
    let root_at = dag.levels()[0].file_offset as usize;
    let mut corrupt = bytes.clone();
    corrupt[root_at + 4] = 0xff;
    let dag = Dag::open(&corrupt).unwrap();
    let tracer = Tracer::new(&dag).unwrap();
    match tracer.trace(&ray([0.5, 0.5, -3.0], [0.0, 0.0, 1.0])) {
        Err(TraceError::Malformed(e)) => {
            assert_eq!(e.code, ErrorCode::PointerOutOfRange);
            assert_eq!(e.level, Some(1));
        }
        other => panic!("expected a malformed-DAG error, got {other:?}"),
    }
}
