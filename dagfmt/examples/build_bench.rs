//! Builder throughput: pushes the 4³ bricks of a spherical shell in Morton
//! order and reports bricks per second, the nodes and bytes of every level,
//! and the file size.
//!
//! ```text
//! cargo run --release -p dagfmt --example build_bench -- [DEPTH [THICKNESS]]
//! ```
//!
//! Default: depth 14 (16384³), a shell 2 voxels thick at radius 0.45·2^D.
//! The shell's bricks are generated in batches by an octree descent; only the
//! `push_brick` calls are timed as "push", then `finish` and `write_to` (into a
//! sink) separately.

use std::time::{Duration, Instant};

use dagfmt::layout::AttributeKind;
use dagfmt::{DagBuilder, morton};

/// CPU seconds used by this thread so far (Linux; `None` elsewhere). The
/// machine may be shared, so CPU time is reported next to wall time.
fn thread_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/thread-self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split(' ').collect();
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// Bricks generated before each timed batch of pushes.
const BATCH: usize = 1 << 20;

/// The shell: voxel centres whose squared distance to `centre` is within `[r2_in, r2_out]`.
struct Shell {
    centre: f64,
    r2_in: f64,
    r2_out: f64,
}

impl Shell {
    /// Squared distance range from the centre to the voxel centres of a cube.
    fn distance2_range(&self, lo: [u32; 3], size: u32) -> (f64, f64) {
        let (mut near, mut far) = (0.0, 0.0);
        for &l in &lo {
            let a = f64::from(l) + 0.5 - self.centre;
            let b = a + f64::from(size - 1);
            let n = if a > 0.0 {
                a
            } else if b < 0.0 {
                -b
            } else {
                0.0
            };
            near += n * n;
            far += (a * a).max(b * b);
        }
        (near, far)
    }

    fn brick_mask(&self, lo: [u32; 3], offsets: &[[u32; 3]; 64]) -> u64 {
        let mut mask = 0u64;
        for (bit, o) in offsets.iter().enumerate() {
            let d2: f64 = (0..3)
                .map(|i| (f64::from(lo[i] + o[i]) + 0.5 - self.centre).powi(2))
                .sum();
            if d2 >= self.r2_in && d2 <= self.r2_out {
                mask |= 1 << bit;
            }
        }
        mask
    }

    /// Calls `emit(brick, mask)` for every non-empty brick, in Morton order.
    fn for_each_brick(&self, depth: u8, mut emit: impl FnMut(u64, u64)) {
        let offsets: [[u32; 3]; 64] = std::array::from_fn(|b| morton::decode(b as u64));
        // (Morton prefix, level) in an explicit stack, children pushed in reverse.
        let mut stack = vec![(0u64, 0u8)];
        let brick_level = depth - 2;
        while let Some((prefix, level)) = stack.pop() {
            let size = 1u32 << (depth - level);
            let lo = morton::decode(prefix).map(|c| c * size);
            let (near, far) = self.distance2_range(lo, size);
            if near > self.r2_out || far < self.r2_in {
                continue;
            }
            if level == brick_level {
                let mask = self.brick_mask(lo, &offsets);
                if mask != 0 {
                    emit(prefix, mask);
                }
            } else {
                for child in (0..8).rev() {
                    stack.push((prefix << 3 | child, level + 1));
                }
            }
        }
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let depth: u8 = args
        .get(1)
        .map_or(14, |a| a.parse().expect("DEPTH is a number 2..=21"));
    let thickness: f64 = args
        .get(2)
        .map_or(2.0, |a| a.parse().expect("THICKNESS is a number"));
    let side = f64::from(1u32 << depth);
    let radius = 0.45 * side;
    let shell = Shell {
        centre: side / 2.0,
        r2_in: (radius - thickness / 2.0).powi(2),
        r2_out: (radius + thickness / 2.0).powi(2),
    };
    println!("sphere shell: depth {depth} ({side}^3), radius {radius}, thickness {thickness}");

    let mut builder = DagBuilder::new(depth, AttributeKind::VoxelCount).expect("valid depth");
    let mut batch: Vec<(u64, u64)> = Vec::with_capacity(BATCH);
    let mut push_time = Duration::ZERO;
    let mut push_cpu = 0.0f64;
    let mut bricks = 0u64;
    let mut peak_memory = 0usize;
    let start = Instant::now();
    let mut flush = |batch: &mut Vec<(u64, u64)>, builder: &mut DagBuilder| {
        let t = Instant::now();
        let cpu = thread_cpu_seconds();
        for &(brick, mask) in batch.iter() {
            builder
                .push_brick(brick, mask)
                .expect("bricks arrive in Morton order");
        }
        push_time += t.elapsed();
        if let (Some(a), Some(b)) = (cpu, thread_cpu_seconds()) {
            push_cpu += b - a;
        }
        bricks += batch.len() as u64;
        peak_memory = peak_memory.max(builder.memory_bytes());
        batch.clear();
    };
    shell.for_each_brick(depth, |brick, mask| {
        batch.push((brick, mask));
        if batch.len() == BATCH {
            flush(&mut batch, &mut builder);
        }
    });
    flush(&mut batch, &mut builder);
    let total = start.elapsed();
    let voxels = builder.voxel_count();

    let t = Instant::now();
    let built = builder.finish().expect("finish");
    let finish_time = t.elapsed();
    let t = Instant::now();
    built.write_to(&mut std::io::sink()).expect("write to sink");
    let write_time = t.elapsed();

    println!("{bricks} bricks, {voxels} voxels");
    println!(
        "push_brick: {:.3} s wall = {:.1} M bricks/s; {:.2} s CPU = {:.1} M bricks/s (generation + push {:.3} s)",
        push_time.as_secs_f64(),
        bricks as f64 / push_time.as_secs_f64() / 1e6,
        push_cpu,
        bricks as f64 / push_cpu / 1e6,
        total.as_secs_f64()
    );
    println!(
        "finish:     {:.3} s (layout + checksums)",
        finish_time.as_secs_f64()
    );
    println!(
        "write_to:   {:.3} s ({} bytes)",
        write_time.as_secs_f64(),
        built.file_size()
    );
    println!(
        "builder peak memory: {:.1} MiB",
        peak_memory as f64 / (1 << 20) as f64
    );
    println!(
        "{:>5} {:>12} {:>14} {:>5} {:>16} {:>9}",
        "level", "nodes", "bytes", "width", "tree nodes", "dedup"
    );
    for s in built.level_stats() {
        println!(
            "{:>5} {:>12} {:>14} {:>5} {:>16} {:>9.2}",
            s.level,
            s.node_count,
            s.bytes,
            s.pointer_width,
            s.tree_nodes,
            s.dedup_ratio()
        );
    }
}
