//! How fast `conformance judge` judges: rays judged per second on a file, for
//! camera rays and for random rays, with the time dagtrace's CPU tracer takes
//! to answer the same rays in the same run (the peer), and the ratio.
//!
//! ```text
//! cargo run --release -p conformance --example judge_bench -- FILE.vdag [--rays N] [--runs R]
//! ```
//!
//! The answers judged are the CPU tracer's, so every one must be accepted; the
//! benchmark fails if one is not. Times are medians of R runs (default 5) of
//! the whole batch, on all cores. Validation of the file, which
//! `Judge::new` does once, is timed separately.

use std::time::Instant;

use conformance::judge::Judge;
use dagfmt::Dag;
use dagfmt::batch::Ray;

/// A fixed random stream (SplitMix64), so every run judges the same rays.
struct Stream(u64);

impl Stream {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    fn direction(&mut self) -> [f64; 3] {
        loop {
            let v = [0; 3].map(|_| self.next() * 2.0 - 1.0);
            let n = v.iter().map(|c| c * c).sum::<f64>().sqrt();
            if n > 0.1 && n <= 1.0 {
                return v.map(|c| c / n);
            }
        }
    }
}

/// A pinhole camera outside the root cube looking at its centre: `count`
/// primary rays in a square image.
fn camera_rays(min: [f64; 3], size: f64, count: usize) -> Vec<Ray> {
    let side = (count as f64).sqrt().ceil() as usize;
    let centre = min.map(|m| m + size / 2.0);
    let eye = [
        centre[0] + 1.1 * size,
        centre[1] + 0.7 * size,
        centre[2] + 1.3 * size,
    ];
    let forward = normalize([0, 1, 2].map(|i| centre[i] - eye[i]));
    let right = normalize(cross(forward, [0.0, 1.0, 0.0]));
    let up = cross(right, forward);
    let half = 0.35;
    let mut rays = Vec::with_capacity(side * side);
    for j in 0..side {
        for i in 0..side {
            let u = ((i as f64 + 0.5) / side as f64 * 2.0 - 1.0) * half;
            let v = ((j as f64 + 0.5) / side as f64 * 2.0 - 1.0) * half;
            let d = [0, 1, 2].map(|a| forward[a] + u * right[a] + v * up[a]);
            rays.push(Ray::new(eye.map(|c| c as f32), d.map(|c| c as f32)));
        }
    }
    rays.truncate(count);
    rays
}

/// Random origins inside the root cube, random directions.
fn random_rays(min: [f64; 3], size: f64, count: usize) -> Vec<Ray> {
    let mut s = Stream(12345);
    (0..count)
        .map(|_| {
            let o = min.map(|m| m + s.next() * size);
            Ray::new(o.map(|c| c as f32), s.direction().map(|c| c as f32))
        })
        .collect()
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalize(v: [f64; 3]) -> [f64; 3] {
    let n = v.iter().map(|c| c * c).sum::<f64>().sqrt();
    v.map(|c| c / n)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), String> {
    let mut args = std::env::args().skip(1);
    let mut file = None;
    let mut count = 1_000_000usize;
    let mut runs = 5usize;
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--rays" => {
                count = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .ok_or("--rays needs a count")?
            }
            "--runs" => {
                runs = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .filter(|&r| r > 0)
                    .ok_or("--runs needs a positive count")?
            }
            path => file = Some(path.to_string()),
        }
    }
    let file = file.ok_or("usage: judge_bench FILE.vdag [--rays N] [--runs R]")?;
    let bytes = std::fs::read(&file).map_err(|e| format!("{file}: {e}"))?;
    let dag = Dag::open(&bytes).map_err(|e| format!("{file}: {e}"))?;
    let header = dag.header().clone();
    let t = Instant::now();
    let judge = Judge::new(&dag).map_err(|e| format!("{file}: {e}"))?;
    let validate = t.elapsed().as_secs_f64();
    let tracer = dagtrace::Tracer::new(&dag).map_err(|e| format!("{file}: {e}"))?;
    println!(
        "{file}: depth {}, {} voxels, {} bytes; validation (Judge::new) {validate:.2} s; {} threads",
        header.depth,
        header.voxel_count,
        bytes.len(),
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    for (name, rays) in [
        (
            "camera",
            camera_rays(header.root_min, header.root_size, count),
        ),
        (
            "random",
            random_rays(header.root_min, header.root_size, count),
        ),
    ] {
        let mut trace_times = Vec::new();
        let mut judge_times = Vec::new();
        let mut hits = Vec::new();
        for _ in 0..runs {
            let t = Instant::now();
            hits = tracer.trace_batch(&rays).map_err(|e| e.to_string())?;
            trace_times.push(t.elapsed().as_secs_f64());
            let t = Instant::now();
            let verdicts = judge.judge_batch(&rays, &hits);
            judge_times.push(t.elapsed().as_secs_f64());
            if let Some((i, r)) = verdicts
                .iter()
                .enumerate()
                .find_map(|(i, v)| v.as_ref().map(|r| (i, r)))
            {
                return Err(format!("ray {i}: the tracer's answer is rejected: {r}"));
            }
        }
        let hit_share = hits.iter().filter(|h| h.hit).count() as f64 / rays.len() as f64;
        let (trace, judged) = (median(trace_times), median(judge_times));
        println!(
            "{name}: {} rays ({:.0}% hit): judge {:.3} s = {:.0} rays/s; tracer {:.3} s = {:.0} rays/s; judge/tracer time {:.1}x",
            rays.len(),
            100.0 * hit_share,
            judged,
            rays.len() as f64 / judged,
            trace,
            rays.len() as f64 / trace,
            judged / trace
        );
    }
    Ok(())
}
