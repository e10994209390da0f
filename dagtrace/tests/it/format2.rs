//! Format 2.0 (spec §23): the tracer over the 2.0 encoding of a DAG's voxels
//! (`dagfmt::v2::encode`, read through `Tracer::from_v2_levels`) gives exactly
//! the 1.0 tracer's answers (hit, t, cell, face, attribute index) in every
//! path: per ray, any-hit, the batch API with eight and sixteen lanes and
//! both ways of gathering, coherent runs (packets), and the occupancy window
//! of the lit renderer; both through the expanded levels (spec §23.12, what
//! `from_v2_levels` makes) and reading the levels in place
//! (`from_v2_levels_in_place`). Damaged levels, which do not expand, are
//! traced in place, with the in-place tracer's answers and errors.

use std::path::Path;

use dagfmt::batch::{Hit, Ray};
use dagfmt::v2::{Child, Encoded, decode_node, encode};
use dagfmt::{AttributeKind, Dag};
use dagtrace::{Gathers, Lanes, Tracer};

use crate::common::{Rng, build};
use crate::props::{ball_scene, random_ray, scene_voxels};

/// The references of `enc` that carry a reflection r ≠ 0, every record of
/// every node level decoded.
fn reflected_references(enc: &Encoded) -> usize {
    let mut reflected = 0;
    for level in enc.levels.iter().filter(|l| !l.is_leaf) {
        let mut at = 0u64;
        while at < level.bytes.len() as u64 {
            let node = decode_node(&level.bytes, at, level.widths).expect("encoded records decode");
            reflected += node
                .children
                .iter()
                .flatten()
                .filter(|c| matches!(c, Child::Shared { reflection, .. } if *reflection != 0))
                .count();
            at += u64::from(node.size);
        }
    }
    reflected
}

/// The tracers of the 2.0 levels of `enc`, with `dag`'s header and colours:
/// through the expanded levels, and reading the levels in place.
fn tracers_v2<'a>(dag: &Dag<'a>, enc: &'a Encoded) -> [Tracer<'a>; 2] {
    let expanded = Tracer::from_v2_levels(dag.header(), &enc.views(), dag.color_table())
        .expect("2.0 levels of a valid DAG make a tracer");
    assert!(expanded.is_expanded(), "the levels of a valid DAG expand");
    let in_place = Tracer::from_v2_levels_in_place(dag.header(), &enc.views(), dag.color_table())
        .expect("2.0 levels of a valid DAG make a tracer");
    assert!(!in_place.is_expanded());
    [expanded, in_place]
}

/// Checks every path of the 2.0 tracer of `dag`'s voxels against the 1.0
/// tracer's per-ray answers on `rays`; returns the number of hits.
fn check_same_answers(name: &str, dag: &Dag<'_>, rays: &[Ray]) -> usize {
    let enc = encode(dag).expect("valid DAG encodes");
    let mut hits = 0;
    for v2 in tracers_v2(dag, &enc) {
        let how = if v2.is_expanded() {
            "expanded"
        } else {
            "in place"
        };
        hits = check_tracer(&format!("{name}, {how}"), dag, &v2, rays);
    }
    hits
}

/// [`check_same_answers`] for one 2.0 tracer `v2` of `dag`'s voxels.
fn check_tracer(name: &str, dag: &Dag<'_>, v2: &Tracer<'_>, rays: &[Ray]) -> usize {
    let v1 = Tracer::new(dag).expect("tracer");
    // Per ray, errors included (conformance rays may ask for a level deeper
    // than the DAG); the batches take the rays that trace.
    for ray in rays {
        assert_eq!(
            v2.trace(ray),
            v1.trace(ray),
            "{name}: 2.0 and 1.0 answer {ray:?} differently"
        );
        assert_eq!(
            v2.occluded(ray),
            v1.occluded(ray),
            "{name}: any-hit differs for {ray:?}"
        );
    }
    let rays: Vec<Ray> = rays
        .iter()
        .filter(|r| v1.trace(r).is_ok())
        .copied()
        .collect();
    let rays = &rays[..];
    let expected: Vec<Hit> = rays
        .iter()
        .map(|r| v1.trace(r).expect("filtered"))
        .collect();
    // The batch API in every configuration of the lanes.
    for gathers in [Gathers::Instruction, Gathers::ScalarLoads] {
        for lanes in [Lanes::Eight, Lanes::Sixteen] {
            let batch = v2
                .clone()
                .with_gathers(gathers)
                .with_lanes(lanes)
                .trace_batch(rays)
                .expect("2.0 traces");
            assert!(
                batch == expected,
                "{name}: 2.0 batch ({gathers:?}, {lanes:?}) differs from 1.0"
            );
        }
    }
    let mut sequential = vec![Hit::MISS; rays.len()];
    v2.trace_sequential_into(rays, &mut sequential)
        .expect("2.0 traces");
    assert!(
        sequential == expected,
        "{name}: 2.0 sequential batch differs"
    );
    assert_eq!(
        v2.occluded_batch(rays).expect("2.0 traces"),
        v1.occluded_batch(rays).expect("1.0 traces"),
        "{name}: any-hit batch differs"
    );
    // The occupancy window around some hit cells, at their level.
    for hit in expected.iter().filter(|h| h.hit).step_by(7).take(40) {
        assert_eq!(
            v2.occupancy_around(hit.voxel, hit.level)
                .expect("2.0 reads"),
            v1.occupancy_around(hit.voxel, hit.level)
                .expect("1.0 reads"),
            "{name}: occupancy around {:?} at level {} differs",
            hit.voxel,
            hit.level
        );
    }
    expected.iter().filter(|h| h.hit).count()
}

/// Random scenes (scattered voxels, balls, noise, boxes) at depths 2 to 7,
/// with and without attributes, under random rays.
#[test]
fn random_dags_answer_alike_in_both_versions() {
    let mut reflected = 0;
    let mut hits = 0;
    for case in 0..48u64 {
        let mut rng = Rng(0x2_0000 + case);
        let depth = 2 + (case % 6) as u8;
        let voxels = scene_voxels(depth, (case / 6 % 4) as u8, &mut rng);
        let kind = if case % 5 == 4 {
            AttributeKind::None
        } else {
            AttributeKind::VoxelCount
        };
        let root_min = [0; 3].map(|_| rng.range(-10.0, 10.0));
        let root_size = rng.range(0.3, 30.0);
        let bytes = build(depth, kind, &voxels, root_min, root_size);
        let dag = Dag::open(&bytes).expect("built DAG opens");
        reflected += reflected_references(&encode(&dag).expect("encodes"));
        let rays: Vec<Ray> = (0..200)
            .map(|_| random_ray(depth, &voxels, root_min, root_size, &mut rng))
            .collect();
        hits += check_same_answers(&format!("case {case} (depth {depth})"), &dag, &rays);
    }
    // Not vacuous: mirrored subtrees are really traced, and rays hit.
    assert!(reflected >= 20, "only {reflected} reflected references");
    assert!(hits >= 48 * 20, "only {hits} hits");
}

/// Coherent rays (cameras aimed at hollow balls) at depths where 1.0 traces
/// them as packets: the 2.0 batch gives the 1.0 per-ray answers.
#[test]
fn coherent_rays_answer_alike_in_both_versions() {
    for (depth, seed) in [(9u8, 0x9a_u64), (10, 0x10b)] {
        let mut rng = Rng(seed);
        let (voxels, centres) = ball_scene(depth, &mut rng);
        let bytes = build(depth, AttributeKind::VoxelCount, &voxels, [0.0; 3], 1.0);
        let dag = Dag::open(&bytes).expect("built DAG opens");
        let enc = encode(&dag).expect("encodes");
        let reflected = reflected_references(&enc);
        assert!(reflected > 0, "depth {depth}: no reflected references");
        let n = f64::from(1u32 << depth);
        let mut rays = Vec::new();
        for camera in 0..12 {
            let origin: [f64; 3] = [0; 3].map(|_| rng.range(-n, 2.0 * n));
            let c = centres[camera % centres.len()];
            let axis = [0, 1, 2].map(|i| c[i] - origin[i]);
            // An 8×8 tile of rays in a narrow cone.
            for j in 0..8 {
                for i in 0..8 {
                    let (u, v) = (f64::from(i) - 3.5, f64::from(j) - 3.5);
                    let dir = [axis[0] + u * 0.3, axis[1] + v * 0.3, axis[2] + u * v * 0.01];
                    rays.push(Ray {
                        origin: origin.map(|o| (o / n) as f32),
                        dir: dir.map(|d| (d / n) as f32),
                        tmin: 0.0,
                        tmax: f32::INFINITY,
                        level: None,
                    });
                }
            }
        }
        let hits = check_same_answers(&format!("balls depth {depth}"), &dag, &rays);
        assert!(hits * 10 >= rays.len(), "only {hits} of {} hit", rays.len());
    }
}

/// Every trace case of the conformance suite (conformance/cases/trace): its
/// DAG in 2.0 answers its rays as in 1.0.
#[test]
fn conformance_scenes_answer_alike_in_both_versions() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../conformance/cases/trace");
    let mut cases = 0;
    let mut reflected = 0;
    let mut entries: Vec<_> = std::fs::read_dir(&dir)
        .expect("the conformance cases are in the repository")
        .map(|e| e.expect("directory entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "vdag"))
        .collect();
    entries.sort();
    for path in entries {
        let bytes = std::fs::read(&path).expect("case file reads");
        let rays = dagfmt::batch::parse_rays(
            &std::fs::read(path.with_extension("rays")).expect("the case's rays read"),
        )
        .expect("the case's rays parse");
        let dag = Dag::open(&bytes).expect("case DAG opens");
        reflected += reflected_references(&encode(&dag).expect("encodes"));
        check_same_answers(&path.display().to_string(), &dag, &rays);
        cases += 1;
    }
    assert!(cases >= 40, "only {cases} trace cases found in {dir:?}");
    assert!(reflected > 0, "no reflected references in the cases");
}

/// Damaged 2.0 levels (cut short, bytes flipped) never panic the tracer: it
/// answers or reports the DAG as malformed, exactly as the tracer reading
/// the levels in place does (per ray and in batches); bad widths are
/// refused.
#[test]
fn damaged_v2_levels_never_panic() {
    let mut rng = Rng(0xbad2);
    let depth = 6;
    let voxels = scene_voxels(depth, 1, &mut rng);
    let bytes = build(depth, AttributeKind::VoxelCount, &voxels, [0.0; 3], 1.0);
    let dag = Dag::open(&bytes).expect("built DAG opens");
    let enc = encode(&dag).expect("encodes");
    let rays: Vec<Ray> = (0..100)
        .map(|_| random_ray(depth, &voxels, [0.0; 3], 1.0, &mut rng))
        .collect();
    let (mut faults, mut expanded) = (0, 0);
    for round in 0..60 {
        let mut damaged = enc.clone();
        let level = round % damaged.levels.len();
        let section = &mut damaged.levels[level].bytes;
        if section.is_empty() {
            continue;
        }
        if round % 3 == 0 {
            let keep = rng.below(section.len() as u64) as usize;
            section.truncate(keep);
        } else {
            for _ in 0..4 {
                let at = rng.below(section.len() as u64) as usize;
                section[at] ^= 1 << rng.below(8);
            }
        }
        let views = damaged.views();
        let in_place = Tracer::from_v2_levels_in_place(dag.header(), &views, None);
        let Ok(tracer) = Tracer::from_v2_levels(dag.header(), &views, None) else {
            // Refused exactly as in place.
            assert_eq!(
                in_place.err(),
                Tracer::from_v2_levels(dag.header(), &views, None).err()
            );
            faults += 1;
            continue;
        };
        let in_place = in_place.expect("made where the expanded tracer is");
        // What expands answers as the levels read in place; what does not is
        // traced in place.
        expanded += usize::from(tracer.is_expanded());
        for ray in &rays {
            let answer = tracer.trace(ray);
            assert_eq!(answer, in_place.trace(ray), "round {round}: {ray:?}");
            faults += usize::from(answer.is_err());
            assert_eq!(tracer.occluded(ray), in_place.occluded(ray));
        }
        assert_eq!(tracer.trace_batch(&rays), in_place.trace_batch(&rays));
    }
    assert!(faults > 0, "no damage was ever noticed");
    assert!(expanded > 0, "no damaged level ever expanded");
    // Widths out of 1..=40, and levels that do not fit the depth, are refused.
    let mut bad = enc.clone();
    bad.levels[0].widths = [0, 3, 41];
    assert!(Tracer::from_v2_levels(dag.header(), &bad.views(), None).is_err());
    let views = enc.views();
    assert!(Tracer::from_v2_levels(dag.header(), &views[1..], None).is_err());
}

/// An empty volume: its 2.0 levels hold no records, and every ray misses as
/// in 1.0.
#[test]
fn empty_v2_dag_misses_everything() {
    let mut rng = Rng(0xe2);
    for depth in [2u8, 5] {
        let bytes = build(depth, AttributeKind::VoxelCount, &[], [0.0; 3], 1.0);
        let dag = Dag::open(&bytes).expect("built DAG opens");
        let rays: Vec<Ray> = (0..50)
            .map(|_| random_ray(depth, &[[0, 0, 0]], [0.0; 3], 1.0, &mut rng))
            .collect();
        assert_eq!(check_same_answers("empty", &dag, &rays), 0);
    }
}
