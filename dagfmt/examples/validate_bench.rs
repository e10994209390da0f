//! Validation throughput: builds (or loads) a large `.vdag` and reports how
//! many GB/s (10^9 bytes per second) [`dagfmt::validate::validate`] checks.
//!
//! ```text
//! cargo run --release -p dagfmt --example validate_bench -- [FILE]
//!     [--depth D] [--density N] [--runs R] [--save PATH]
//! ```
//!
//! With `FILE` the file is memory-mapped and validated. Otherwise a synthetic
//! DAG is built: at depth D (default 12), each 4³ brick is present with
//! probability 1/N (default 16) and holds a pseudo-random mask, a quarter of
//! them drawn from a palette of 4096 masks. Random masks defeat deduplication,
//! so the file grows with the number of bricks (depth 12, density 16: 67
//! million bricks, 50 million distinct leaves, a 1.17 GB file, built in one to
//! three minutes with about 3.7 GB of memory); the palette makes some leaves
//! shared, so about 15% of the pointers of the two largest levels jump back
//! to older nodes, as deduplicated pointers do in real scenes. `--save PATH` writes the built
//! file (refusing to overwrite an existing one).
//!
//! Prints the median of R runs (default 5) after one warm-up run, in wall
//! time and in CPU time. Checksums run on a second thread for large files
//! unless `--single-thread` is given.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use dagfmt::validate::{ValidateOptions, validate_with};
use dagfmt::{AttributeKind, DagBuilder};

struct Args {
    file: Option<PathBuf>,
    depth: u8,
    density: u64,
    runs: usize,
    save: Option<PathBuf>,
    single_thread: bool,
}

fn parse_args() -> Result<Args, String> {
    let mut args = Args {
        file: None,
        depth: 12,
        density: 16,
        runs: 5,
        save: None,
        single_thread: false,
    };
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        let mut value = |name: &str| it.next().ok_or_else(|| format!("{name} needs a value"));
        match a.as_str() {
            "--depth" => {
                args.depth = value("--depth")?
                    .parse()
                    .map_err(|e| format!("--depth: {e}"))?
            }
            "--density" => {
                args.density = value("--density")?
                    .parse()
                    .map_err(|e| format!("--density: {e}"))?;
                if args.density == 0 {
                    return Err("--density must be at least 1".into());
                }
            }
            "--runs" => {
                args.runs = value("--runs")?
                    .parse()
                    .map_err(|e| format!("--runs: {e}"))?
            }
            "--save" => args.save = Some(value("--save")?.into()),
            "--single-thread" => args.single_thread = true,
            "-h" | "--help" => {
                return Err("usage: validate_bench [FILE] [--depth D] [--density N] [--runs R] [--save PATH] [--single-thread]".into());
            }
            s if s.starts_with('-') => return Err(format!("unknown option {s}")),
            s => args.file = Some(s.into()),
        }
    }
    if args.runs == 0 {
        return Err("--runs must be at least 1".into());
    }
    Ok(args)
}

/// SplitMix64: a fast, well-mixed hash of a counter.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn build(depth: u8, density: u64) -> Result<Vec<u8>, String> {
    let start = Instant::now();
    let mut builder =
        DagBuilder::new(depth, AttributeKind::VoxelCount).map_err(|e| e.to_string())?;
    let palette: Vec<u64> = (0..4096u64).map(|i| mix(i ^ 0xABCD) | 1).collect();
    let bricks = 1u64 << (3 * (u32::from(depth) - 2));
    for brick in 0..bricks {
        let h = mix(brick);
        if !h.is_multiple_of(density) {
            continue;
        }
        let mask = if (h >> 20) & 3 == 0 {
            palette[((h >> 24) & 4095) as usize]
        } else {
            mix(h) | 1
        };
        builder.push_brick(brick, mask).map_err(|e| e.to_string())?;
    }
    let built = builder.finish().map_err(|e| e.to_string())?;
    let bytes = built.to_bytes();
    eprintln!(
        "built depth {depth}, {} voxels, {} bytes in {:.1} s",
        built.voxel_count(),
        bytes.len(),
        start.elapsed().as_secs_f64()
    );
    Ok(bytes)
}

fn run() -> Result<(), String> {
    let args = parse_args()?;
    let mapped;
    let built;
    let bytes: &[u8] = match &args.file {
        Some(path) => {
            mapped = dagfmt::mmap::MappedFile::open(path)
                .map_err(|e| format!("{}: {e}", path.display()))?;
            mapped.bytes()
        }
        None => {
            built = build(args.depth, args.density)?;
            if let Some(path) = &args.save {
                use std::io::Write;
                let mut f = std::fs::File::create_new(path)
                    .map_err(|e| format!("{}: {e}", path.display()))?;
                f.write_all(&built)
                    .map_err(|e| format!("{}: {e}", path.display()))?;
            }
            &built
        }
    };
    let options = ValidateOptions {
        threads: !args.single_thread,
        ..ValidateOptions::default()
    };
    let warm = validate_with(bytes, &options);
    if !warm.is_valid() {
        eprintln!(
            "note: the file is not valid ({} findings), first: {}",
            warm.errors.len(),
            warm.errors[0]
        );
    }
    let mut times = Vec::new();
    let mut cpu_times = Vec::new();
    for _ in 0..args.runs {
        let cpu = process_cpu_seconds();
        let t = Instant::now();
        let report = validate_with(bytes, &options);
        times.push(t.elapsed().as_secs_f64());
        if let (Some(before), Some(after)) = (cpu, process_cpu_seconds()) {
            cpu_times.push(after - before);
        }
        std::hint::black_box(report);
    }
    let gb = bytes.len() as f64 / 1e9;
    let wall = median(&mut times);
    println!(
        "validated {gb:.3} GB: median {wall:.3} s wall over {} runs (min {:.3}, max {:.3}) = {:.2} GB/s",
        times.len(),
        times[0],
        times[times.len() - 1],
        gb / wall
    );
    if cpu_times.len() == times.len() {
        // On a busy machine wall time includes waiting for a core; CPU time
        // (all threads) is what validation costs.
        let cpu = median(&mut cpu_times);
        println!(
            "  median CPU time {cpu:.3} s (all threads) = {:.2} GB per CPU-second",
            gb / cpu
        );
    }
    Ok(())
}

/// Sorts `v` and returns its median.
fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// User + system CPU time of this process so far (threads that have exited
/// included), from Linux's /proc (`None` elsewhere). Clock ticks of 10 ms.
fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the command name (which is in parentheses and may hold spaces).
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the line, 12 and 13 of `rest`.
    let ticks: u64 = fields.get(11)?.parse::<u64>().ok()? + fields.get(12)?.parse::<u64>().ok()?;
    Some(ticks as f64 / 100.0)
}

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("validate_bench: {e}");
            ExitCode::FAILURE
        }
    }
}
