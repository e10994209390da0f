//! Wall time of the batch API ([`Tracer::trace_batch`], all cores, attribute
//! index on) on the rays of a binary ray batch: the Rust side of the Python
//! package's trace benchmark (python/bench/trace_bench.py), which runs this
//! example and `vdag.Dag.trace` on the same file and rays, alternately.
//!
//! ```text
//! cargo run --release -p dagtrace --example batch_time -- FILE.vdag RAYS.vray RUNS
//! ```
//!
//! Prints one line per timed run, `seconds`, after one untimed run (the
//! DAG and the pages of the rays in memory, the thread pool started).

use std::time::Instant;

use dagfmt::AnyDag;
use dagfmt::mmap::MappedFile;
use dagtrace::Tracer;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [file, rays, runs] = args.as_slice() else {
        return Err("usage: batch_time FILE.vdag RAYS.vray RUNS".into());
    };
    let runs: usize = runs.parse()?;
    let map = MappedFile::open(file.as_ref())?;
    // Either version (a 2.0 file traced through its expanded levels).
    let dag = AnyDag::open(map.bytes())?;
    let rays = dagfmt::batch::parse_rays(&std::fs::read(rays)?)?;
    let tracer = Tracer::from_any(&dag)?;
    let mut hits = tracer.trace_batch(&rays)?;
    for _ in 0..runs {
        drop(hits);
        let start = Instant::now();
        hits = tracer.trace_batch(&rays)?;
        println!("{:.6}", start.elapsed().as_secs_f64());
    }
    eprintln!(
        "{} rays, {} hits",
        rays.len(),
        hits.iter().filter(|h| h.hit).count()
    );
    Ok(())
}
