//! The judge (`conformance::judge`, `conformance judge`): it must accept
//! exactly what the committed expectations accept, accept every answer of
//! dagtrace's tracers on the built-in cases and on random files of depths 3
//! to 16, and reject wrong answers naming the condition they break.

use std::path::Path;
use std::process::Command;

use conformance::expect;
use conformance::judge::{Judge, Reason};
use conformance::oracle::{Expectation, Oracle, OracleRay};
use conformance::rng::Rng;
use conformance::suite;
use dagfmt::batch::{self, Hit, Ray};
use dagfmt::{AttributeKind, Dag, DagBuilder};

fn conformance_exe() -> &'static str {
    env!("CARGO_BIN_EXE_conformance")
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()))
}

/// Whether the case's batch must be rejected as a whole.
fn rejects_batch(case: &suite::TraceCaseFiles) -> bool {
    let text = String::from_utf8(read(&case.expect)).expect("UTF-8");
    expect::parse_case(&text).expect("expectations") == expect::CaseExpectation::RejectBatch
}

/// Answers derived from an expectation: every listed cell at the ends of its
/// window and just outside them, with every face and a wrong index, and a
/// miss. The judge must agree with the expectation on each.
fn probes(e: &conformance::oracle::Expectation) -> Vec<Hit> {
    let mut out = vec![Hit::MISS];
    for c in &e.cells {
        let base = Hit {
            hit: true,
            t: c.t_lo,
            voxel: c.cell,
            level: e.level,
            face: c.faces.trailing_zeros().min(6) as u8,
            index: c.index,
        };
        for t in [c.t_lo, c.t_hi, c.t_lo.next_down(), c.t_hi.next_up()] {
            out.push(Hit { t, ..base });
        }
        for face in 0..=6 {
            out.push(Hit { face, ..base });
        }
        out.push(Hit {
            index: c.index.map(|i| i + 1),
            ..base
        });
        out.push(Hit {
            level: e.level.saturating_sub(1).max(1),
            ..base
        });
        // Neighbours: often empty or not first.
        for axis in 0..3 {
            let mut cell = c.cell;
            cell[axis] ^= 1;
            out.push(Hit {
                voxel: cell,
                ..base
            });
        }
    }
    out
}

#[test]
fn judge_agrees_with_the_committed_expectations() {
    let cases = suite::trace_cases(&suite::default_cases_dir(), None).expect("cases");
    let mut compared = 0usize;
    for case in &cases {
        let file = read(&case.dag);
        let dag = Dag::open(&file).expect("opens");
        let judge = Judge::new(&dag).expect("valid");
        let rays = batch::parse_rays(&read(&case.rays)).expect("rays");
        let text = String::from_utf8(read(&case.expect)).expect("UTF-8");
        let expect::CaseExpectation::Answers(expectations) =
            expect::parse_case(&text).expect("expectations")
        else {
            // A batch to reject as a whole: the judge refuses it up front.
            assert!(judge.check_levels(&rays).is_err(), "{}", case.name);
            continue;
        };
        let mut all_rays = Vec::new();
        let mut all_answers = Vec::new();
        let mut verdicts = Vec::new();
        for (ray, e) in rays.iter().zip(&expectations) {
            for answer in probes(e) {
                verdicts.push(expect::judge(e, &answer).is_ok());
                all_rays.push(*ray);
                all_answers.push(answer);
            }
        }
        let judged = judge.judge_batch(&all_rays, &all_answers);
        for (i, (verdict, judged)) in verdicts.iter().zip(&judged).enumerate() {
            assert_eq!(
                *verdict,
                judged.is_none(),
                "{}: ray {} answer {}: expectation says {}, judge says {:?}",
                case.name,
                bless_ray(&all_rays[i]),
                expect::format_answer(&all_answers[i]),
                if *verdict { "accept" } else { "reject" },
                judged.as_ref().map(|r| r.to_string())
            );
        }
        compared += verdicts.len();
    }
    assert!(compared > 50_000, "only {compared} answers compared");
}

fn bless_ray(ray: &Ray) -> String {
    conformance::bless::format_ray(ray)
}

#[test]
fn judge_accepts_the_cpu_tracer_on_every_case() {
    for case in suite::trace_cases(&suite::default_cases_dir(), None).expect("cases") {
        if rejects_batch(&case) {
            continue;
        }
        let file = read(&case.dag);
        let dag = Dag::open(&file).expect("opens");
        let judge = Judge::new(&dag).expect("valid");
        let rays = batch::parse_rays(&read(&case.rays)).expect("rays");
        let hits = dagtrace::Tracer::new(&dag)
            .expect("tracer")
            .trace_batch(&rays)
            .expect("traces");
        let rejected: Vec<String> = judge
            .judge_batch(&rays, &hits)
            .iter()
            .enumerate()
            .filter_map(|(i, r)| r.as_ref().map(|r| format!("ray {i}: {r}")))
            .collect();
        assert!(
            rejected.is_empty(),
            "{}: {}",
            case.name,
            rejected.join("\n")
        );
    }
}

/// The GPU tracer, full and short stack, on every case. Without an adapter
/// this says it was skipped, unless `VDAG_REQUIRE_GPU=1` makes it a failure.
#[test]
fn judge_accepts_the_gpu_tracer_on_every_case() {
    for short_stack in [None, Some(2)] {
        let options = dagtrace::gpu::GpuOptions {
            stack: match short_stack {
                Some(n) => dagtrace::gpu::StackMode::Short(n),
                None => dagtrace::gpu::StackMode::Full,
            },
            ..Default::default()
        };
        let context = match dagtrace::gpu::GpuContext::new(options.adapter) {
            Ok(c) => c,
            Err(e) => {
                if std::env::var("VDAG_REQUIRE_GPU").is_ok_and(|v| v == "1") {
                    panic!("VDAG_REQUIRE_GPU=1 but {e}");
                }
                println!("skipped: no GPU adapter: {e}");
                return;
            }
        };
        let mut files = Vec::new();
        for case in suite::trace_cases(&suite::default_cases_dir(), None).expect("cases") {
            if rejects_batch(&case) {
                continue;
            }
            let rays = batch::parse_rays(&read(&case.rays)).expect("rays");
            files.push((case.name, read(&case.dag), rays));
        }
        for depth in [3u8, 9, 16] {
            let (file, rays) = random_scene(&mut Rng::new(u64::from(depth) * 77), depth);
            files.push((format!("random-d{depth}"), file, rays));
        }
        for (name, file, rays) in files {
            let dag = Dag::open(&file).expect("opens");
            let judge = Judge::new(&dag).expect("valid");
            let tracer = dagtrace::gpu::GpuTracer::with_context(&context, &dag, &options)
                .expect("GPU tracer");
            let hits = tracer.trace(&rays).expect("traces");
            let rejected: Vec<String> = judge
                .judge_batch(&rays, &hits)
                .iter()
                .enumerate()
                .filter_map(|(i, r)| r.as_ref().map(|r| format!("ray {i}: {r}")))
                .collect();
            assert!(
                rejected.is_empty(),
                "{name} (short stack {short_stack:?}): {}",
                rejected.join("\n")
            );
        }
    }
}

/// A random file of `depth` (clusters of voxels, a solid box, scattered
/// voxels) and rays: aimed at voxels from outside, from inside, along lattice
/// lines (ties), random segments, points, coarser levels.
fn random_scene(rng: &mut Rng, depth: u8) -> (Vec<u8>, Vec<Ray>) {
    let n = 1u32 << depth;
    let mut voxels = Vec::new();
    // A solid box of up to 6³ voxels.
    let side = 2 + rng.below(5) as u32;
    let corner = [0; 3].map(|_| rng.below(u64::from(n - side.min(n))) as u32);
    for z in 0..side.min(n) {
        for y in 0..side.min(n) {
            for x in 0..side.min(n) {
                voxels.push([corner[0] + x, corner[1] + y, corner[2] + z]);
            }
        }
    }
    // Clusters and scattered voxels.
    for _ in 0..(4 + rng.below(8)) {
        let centre = [0; 3].map(|_| rng.below(u64::from(n)) as u32);
        for _ in 0..rng.below(40) {
            let v = centre.map(|c| {
                let off = rng.below(7) as i64 - 3;
                (i64::from(c) + off).clamp(0, i64::from(n) - 1) as u32
            });
            voxels.push(v);
        }
    }
    let kind = if rng.chance(0.2) {
        AttributeKind::None
    } else {
        AttributeKind::VoxelCount
    };
    let root_size = [1.0f64, 2.0, 7.5, 1000.0][rng.below(4) as usize];
    let root_min = [0; 3].map(|_| rng.range(-10.0, 10.0).round());
    let mut built = DagBuilder::from_voxels(depth, kind, voxels.iter().copied()).expect("builds");
    built.set_root_cube(root_min, root_size).expect("root cube");
    let file = built.to_bytes();
    let to_world = |g: [f64; 3]| -> [f32; 3] {
        [0, 1, 2].map(|i| (root_min[i] + g[i] * root_size / f64::from(n)) as f32)
    };
    let scale = root_size / f64::from(n);
    let mut rays = Vec::new();
    for _ in 0..300 {
        let target = voxels[rng.below(voxels.len() as u64) as usize];
        let centre = target.map(|c| f64::from(c) + 0.5);
        let kind = rng.below(6);
        let (o, d): ([f64; 3], [f64; 3]) = match kind {
            // From outside, aimed at a voxel centre.
            0 => {
                let dir = rng.direction();
                let far = f64::from(n) * 1.5;
                ([0, 1, 2].map(|i| centre[i] - dir[i] * far), dir)
            }
            // Lattice-aligned: origin on voxel corners or face centres, axis or
            // small integer directions (ties along faces and edges).
            1 => {
                let o = target.map(|c| f64::from(c) + (rng.below(3) as f64) * 0.5);
                let mut d = [0; 3].map(|_| rng.below(3) as f64 - 1.0);
                if d == [0.0; 3] {
                    d[rng.below(3) as usize] = 1.0;
                }
                let back = 3.0 + rng.below(5) as f64;
                ([0, 1, 2].map(|i| o[i] - d[i] * back), d)
            }
            // From inside the volume, random direction.
            2 => (
                [0; 3].map(|_| rng.range(0.0, f64::from(n))),
                rng.direction(),
            ),
            // Near a voxel, random direction.
            3 => (
                [0, 1, 2].map(|i| centre[i] + rng.range(-2.0, 2.0)),
                rng.direction(),
            ),
            // Grazing: along a face of the target voxel.
            4 => {
                let axis = rng.below(3) as usize;
                let mut o = centre;
                o[(axis + 1) % 3] = f64::from(target[(axis + 1) % 3]);
                o[axis] = -2.0;
                let mut d = [0.0; 3];
                d[axis] = 1.0;
                (o, d)
            }
            // A point query.
            _ => (
                [0, 1, 2].map(|i| centre[i] + rng.range(-0.7, 0.7)),
                [0.0; 3],
            ),
        };
        let length = [1.0, 0.25, 37.0][rng.below(3) as usize];
        let mut ray = Ray::new(to_world(o), d.map(|v| (v * scale * length) as f32));
        if rng.chance(0.2) {
            ray.tmin = rng.range(-5.0, 5.0) as f32;
            ray.tmax = ray.tmin + rng.range(0.0, 3.0 * f64::from(n) / length) as f32;
        }
        if rng.chance(0.3) {
            ray.level = Some(1 + rng.below(u64::from(depth)) as u8);
        }
        rays.push(ray);
    }
    (file, rays)
}

/// Property test: on random files of every depth from 3 to 16, the judge
/// accepts every answer of the CPU tracer, and agrees with the brute-force
/// oracle on those answers and on probes around the oracle's expectations.
#[test]
fn judge_accepts_the_cpu_tracer_and_agrees_with_the_oracle_on_random_files() {
    for depth in 3u8..=16 {
        for seed in 0..2u64 {
            let mut rng = Rng::new(seed * 1000 + u64::from(depth));
            let (file, rays) = random_scene(&mut rng, depth);
            let dag = Dag::open(&file).expect("opens");
            let judge = Judge::new(&dag).expect("valid");
            let hits = dagtrace::Tracer::new(&dag)
                .expect("tracer")
                .trace_batch(&rays)
                .expect("traces");
            let mut oracle = Oracle::new(&dag);
            for (i, (ray, hit)) in rays.iter().zip(&hits).enumerate() {
                if let Err(r) = judge.judge(ray, hit) {
                    panic!(
                        "depth {depth} seed {seed} ray {i}: {}: tracer's answer {} rejected: {r}",
                        bless_ray(ray),
                        expect::format_answer(hit)
                    );
                }
                let e = oracle
                    .expect(
                        &dag,
                        &OracleRay {
                            origin: ray.origin,
                            dir: ray.dir,
                            tmin: ray.tmin,
                            tmax: ray.tmax,
                            level: ray.level.unwrap_or(depth),
                        },
                    )
                    .expect("oracle");
                let mut answers = probes(&e);
                answers.push(*hit);
                for answer in answers {
                    let by_oracle = expect::judge(&e, &answer).is_ok();
                    let by_judge = judge.judge(ray, &answer);
                    assert_eq!(
                        by_oracle,
                        by_judge.is_ok(),
                        "depth {depth} seed {seed} ray {i}: {}: answer {}: oracle {}, judge {by_judge:?}",
                        bless_ray(ray),
                        expect::format_answer(&answer),
                        expect::format_expectation(&e)
                    );
                }
            }
        }
    }
}

/// A depth-5 volume whose lower half (z < 16) is solid, in a root cube
/// [0, 32]³ (grid = world).
fn half_solid() -> Vec<u8> {
    let mut voxels = Vec::new();
    for z in 0..16 {
        for y in 0..32 {
            for x in 0..32 {
                voxels.push([x, y, z]);
            }
        }
    }
    let mut built = DagBuilder::from_voxels(5, AttributeKind::VoxelCount, voxels).expect("builds");
    built.set_root_cube([0.0; 3], 32.0).expect("root cube");
    built.to_bytes()
}

#[test]
fn wrong_answers_are_rejected_with_the_condition_they_break() {
    let file = half_solid();
    let dag = Dag::open(&file).expect("opens");
    let judge = Judge::new(&dag).expect("valid");
    // Straight down onto the top face z = 16 at (4.5, 7.5): enters voxel
    // (4, 7, 15) at t = 4 through its +Z face (code 6).
    let ray = Ray::new([4.5, 7.5, 20.0], [0.0, 0.0, -1.0]);
    let index = |v: [u32; 3]| {
        dag.voxel_index(v[0], v[1], v[2])
            .expect("reads")
            .expect("set")
    };
    let good = Hit {
        hit: true,
        t: 4.0,
        voxel: [4, 7, 15],
        level: 5,
        face: 6,
        index: Some(index([4, 7, 15])),
    };
    assert_eq!(judge.judge(&ray, &good), Ok(()));
    let reason = |answer: Hit| judge.judge(&ray, &answer).expect_err("rejected").reason;
    // A miss through the solid interior.
    assert_eq!(reason(Hit::MISS), Reason::MissNotAccepted);
    // A hit on an empty cell.
    assert_eq!(
        reason(Hit {
            voxel: [4, 7, 16],
            ..good
        }),
        Reason::EmptyCell
    );
    // The wrong cell: occupied, but deeper along the ray.
    assert!(matches!(
        reason(Hit {
            voxel: [4, 7, 10],
            t: 9.0,
            index: Some(index([4, 7, 10])),
            ..good
        }),
        Reason::NotFirst { .. }
    ));
    // A cell the ray does not come near.
    assert_eq!(
        reason(Hit {
            voxel: [20, 7, 15],
            index: Some(index([20, 7, 15])),
            ..good
        }),
        Reason::MissesGrownCell
    );
    // t outside the accepted range, both sides.
    for t in [3.99, 4.01] {
        assert_eq!(reason(Hit { t, ..good }), Reason::TOutOfRange);
    }
    assert!(
        matches!(reason(Hit { face: 5, ..good }), Reason::Face { accepted } if accepted == 1 << 6)
    );
    assert!(matches!(
        reason(Hit {
            index: Some(0),
            ..good
        }),
        Reason::Index { .. }
    ));
    assert!(matches!(
        reason(Hit { level: 4, ..good }),
        Reason::WrongLevel { reported: 4 }
    ));
    assert_eq!(
        reason(Hit {
            voxel: [40, 7, 15],
            ..good
        }),
        Reason::CellOutsideVolume
    );
    // Invalid rays accept only a miss.
    let nan = Ray::new([f32::NAN, 7.5, 20.0], [0.0, 0.0, -1.0]);
    assert_eq!(judge.judge(&nan, &Hit::MISS), Ok(()));
    assert_eq!(
        judge.judge(&nan, &good).expect_err("rejected").reason,
        Reason::InvalidRayMustMiss
    );
    // A level deeper than the file.
    let deep = Ray {
        level: Some(6),
        ..ray
    };
    assert!(matches!(
        judge.judge(&deep, &good).expect_err("rejected").reason,
        Reason::LevelTooDeep { level: 6, depth: 5 }
    ));
    assert!(judge.check_levels(&[ray, deep]).is_err());
    // The report names T⁻ and the accepted range.
    let text = judge
        .judge(&ray, &Hit { t: 4.5, ..good })
        .expect_err("rejected")
        .to_string();
    assert!(
        text.starts_with("condition 4: t 4.5 is outside the accepted range; T⁻ = 4.0")
            && text.contains("accepted t for cell (4, 7, 15): [3.99"),
        "{text}"
    );
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> String {
    let path = dir.join(name);
    std::fs::write(&path, bytes).expect("write");
    path.to_str().expect("UTF-8").to_string()
}

#[test]
fn the_judge_command_lists_rejections_and_sets_its_status() {
    let temp = tempfile::tempdir().expect("temp dir");
    let file = write(temp.path(), "half.vdag", &half_solid());
    let rays = vec![
        Ray::new([4.5, 7.5, 20.0], [0.0, 0.0, -1.0]),
        Ray::new([4.5, 7.5, 20.0], [0.0, 0.0, 1.0]),
    ];
    let mut text = Vec::new();
    batch::write_rays_text(&mut text, &rays).expect("write");
    let rays_path = write(temp.path(), "rays", &text);
    let dag_bytes = half_solid();
    let dag = Dag::open(&dag_bytes).expect("opens");
    let good = dagtrace::Tracer::new(&dag)
        .expect("tracer")
        .trace_batch(&rays)
        .expect("traces");
    // Binary answers, all accepted.
    let mut binary = Vec::new();
    batch::write_hits_binary(&mut binary, &good).expect("write");
    let hits = write(temp.path(), "good.hits", &binary);
    let output = Command::new(conformance_exe())
        .args(["judge", &file, "--rays", &rays_path, "--hits", &hits])
        .output()
        .expect("runs");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert_eq!(output.status.code(), Some(0), "{stdout}");
    assert_eq!(stdout.trim(), "2 rays judged: 2 accepted, 0 rejected");
    // The 2.0 file of the same voxels (the tools' default) is judged alike.
    let upgraded = dagfmt::v2file::upgrade(&dag).expect("2.0");
    let file2 = write(temp.path(), "half2.vdag", &upgraded);
    for answers in [
        &hits,
        &write(temp.path(), "miss.hits", b"vdag-hits 1\nmiss\nmiss\n"),
    ] {
        let judged = |f: &str| {
            Command::new(conformance_exe())
                .args(["judge", f, "--rays", &rays_path, "--hits", answers])
                .output()
                .expect("runs")
        };
        let (one, two) = (judged(&file), judged(&file2));
        assert_eq!(two.status.code(), one.status.code());
        assert_eq!(
            String::from_utf8_lossy(&two.stdout),
            String::from_utf8_lossy(&one.stdout)
        );
    }
    // Text answers: the first is a miss through the solid half.
    let bad = write(temp.path(), "bad.hits", b"vdag-hits 1\nmiss\nmiss\n");
    let output = Command::new(conformance_exe())
        .args(["judge", &file, "--rays", &rays_path, "--hits", &bad])
        .output()
        .expect("runs");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert_eq!(output.status.code(), Some(1), "{stdout}");
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(lines.len(), 2, "{stdout}");
    assert!(
        lines[0]
            .starts_with("ray 0: 4.5 7.5 20 0 0 -1 0 inf | answer: miss | a miss is not accepted")
            && lines[0].contains("T⁻ = 4.0"),
        "{stdout}"
    );
    assert_eq!(lines[1], "2 rays judged: 1 accepted, 1 rejected");
    // --exec: a tracer command that copies the good answers.
    let output = Command::new(conformance_exe())
        .args([
            "judge",
            &file,
            "--rays",
            &rays_path,
            "--exec",
            &format!("cp '{hits}' {{hits}}"),
        ])
        .output()
        .expect("runs");
    assert_eq!(
        output.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&output.stdout)
    );
    // Too few answers, a level deeper than the file, an invalid file: status 2.
    let short = write(temp.path(), "short.hits", b"vdag-hits 1\nmiss\n");
    let deep = write(
        temp.path(),
        "deep.rays",
        b"vdag-rays 1\n4.5 7.5 20 0 0 -1 0 inf 6\n",
    );
    let mut broken = half_solid();
    broken[200] ^= 1;
    let broken = write(temp.path(), "broken.vdag", &broken);
    for (args, message) in [
        ([&file, &rays_path, &short], "1 answers for 2 rays"),
        (
            [&file, &deep, &short],
            "level 6 is deeper than the file's depth 5",
        ),
        ([&broken, &rays_path, &hits], "not valid"),
    ] {
        let output = Command::new(conformance_exe())
            .args(["judge", args[0], "--rays", args[1], "--hits", args[2]])
            .output()
            .expect("runs");
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert_eq!(output.status.code(), Some(2), "{stderr}");
        assert!(
            stderr.contains(message) && stderr.lines().count() == 1,
            "{stderr}"
        );
    }
}

/// Origins far away, up to `f32::MAX`: where `eps_g` spans the whole volume
/// the judge must answer at once (nothing can be robustly inside, and the
/// planes it examines are bounded by the volume), and it must still agree
/// with the oracle and accept the tracer. (Origins whose `eps_g` spans many
/// cells but less than the volume, about 10^7 to 10^8 voxels away here, are
/// slow for both: each robustness test then looks at (2 eps_g)^3 cells.)
#[test]
fn far_origins_are_judged_and_agree_with_the_oracle() {
    let file = half_solid();
    let dag = Dag::open(&file).expect("opens");
    let judge = Judge::new(&dag).expect("valid");
    let mut rays = Vec::new();
    for far in [1e4f32, 1e5, 1e9, 1e30, f32::MAX] {
        rays.push(Ray::new([4.5, 7.5, far], [0.0, 0.0, -1.0]));
        rays.push(Ray::new([far, 7.5, 8.0], [-1.0, 0.0, 0.0]));
        rays.push(Ray::new([-far, -far, 20.0], [1.0, 1.0, -0.1]));
    }
    let hits = dagtrace::Tracer::new(&dag)
        .expect("tracer")
        .trace_batch(&rays)
        .expect("traces");
    let mut oracle = Oracle::new(&dag);
    let started = std::time::Instant::now();
    for (ray, hit) in rays.iter().zip(&hits) {
        let e = oracle
            .expect(
                &dag,
                &OracleRay {
                    origin: ray.origin,
                    dir: ray.dir,
                    tmin: ray.tmin,
                    tmax: ray.tmax,
                    level: 5,
                },
            )
            .expect("oracle");
        // Where eps_g spans the volume every cell is acceptable: probe a few.
        let mut answers = probes(&Expectation {
            cells: e.cells.iter().take(3).cloned().collect(),
            ..e.clone()
        });
        answers.push(*hit);
        for answer in answers {
            assert_eq!(
                expect::judge(&e, &answer).is_ok(),
                judge.judge(ray, &answer).is_ok(),
                "{}: answer {}",
                bless_ray(ray),
                expect::format_answer(&answer)
            );
        }
    }
    assert!(
        started.elapsed().as_secs() < 30,
        "far origins took {:?}",
        started.elapsed()
    );
}
