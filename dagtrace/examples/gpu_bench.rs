//! GPU versus CPU ray throughput on a `.vdag` file.
//!
//! ```text
//! cargo run --release -p dagtrace --example gpu_bench -- FILE.vdag [--runs N] [--random N] [--size WxH] [--cpu-runs N] [--chunk N]
//! ```
//!
//! Prints the adapter, the time to the first traced ray (open + device +
//! upload + shader + one ray), then rays per second (median of the runs) for
//! primary rays of a WxH image (default 1920x1080: made and traced on the GPU,
//! an RGBA image written) and for random rays (set up on the host, streamed
//! through the GPU in chunks, read back; the host part of the call, its
//! set-up and answers, in ms and per 10^6 rays, as wall time and as the CPU
//! time of the threads that run it, which the load of other processes does
//! not inflate; the whole call's time over the dispatch time), with the full
//! and the short stack, and the same rays
//! on the CPU tracer (all cores). `--chunk N` sets the rays per chunk of the
//! batch path (with the whole batch in one chunk nothing overlaps, and the
//! host part is the host's work alone, the GPU idle meanwhile).
//!
//! ```text
//! gpu_bench FILE.vdag --compare-v2 FILE2.vdag [--runs N] [--random N] [--size WxH]
//! ```
//!
//! compares the GPU trace rates of a format 1.0 file and the 2.0 file of the
//! same voxels (`dagtool convert --format-version 2`, or `dagtool upgrade`),
//! the latter uploaded expanded (spec §23.12, the default) and in place:
//! the same random rays (batch path, no attribute index) and primary rays,
//! full and short (4) stacks, run by run interleaved (1.0, then 2.0
//! expanded, then 2.0 in place, per run); prints each tracer's set-up time,
//! the expansion's time and the bytes uploaded, the medians and the median
//! of the per-run ratios 2.0 / 1.0 of the rates, and checks first that all
//! give the same answers.

#[cfg(feature = "gpu")]
fn main() {
    if let Err(e) = bench::run() {
        eprintln!("gpu_bench: {e}");
        std::process::exit(1);
    }
}

#[cfg(not(feature = "gpu"))]
fn main() {
    eprintln!("gpu_bench: dagtrace was built without the `gpu` feature");
    std::process::exit(1);
}

#[cfg(feature = "gpu")]
mod bench {
    use std::time::{Duration, Instant};

    use dagfmt::Dag;
    use dagfmt::batch::Ray;
    use dagfmt::mmap::MappedFile;
    use dagtrace::Tracer;
    use dagtrace::camera::Camera;
    use dagtrace::gpu::{AdapterChoice, GpuContext, GpuOptions, GpuTracer, StackMode, V2Layout};

    struct Args {
        path: String,
        runs: usize,
        cpu_runs: usize,
        random: usize,
        width: u32,
        height: u32,
        /// Rays per chunk of the batch path (`GpuOptions::rays_per_dispatch`).
        chunk: u32,
        /// `--compare-v2`: the 2.0 file of the same voxels.
        compare_v2: Option<String>,
    }

    fn parse_args() -> Result<Args, String> {
        let mut args = Args {
            path: String::new(),
            runs: 7,
            cpu_runs: 3,
            random: 1 << 20,
            width: 1920,
            height: 1080,
            chunk: GpuOptions::default().rays_per_dispatch,
            compare_v2: None,
        };
        let mut it = std::env::args().skip(1);
        let number = |v: Option<String>, what: &str| -> Result<usize, String> {
            v.ok_or(format!("{what} needs a value"))?
                .parse()
                .map_err(|e| format!("{what}: {e}"))
        };
        while let Some(a) = it.next() {
            match a.as_str() {
                "--runs" => args.runs = number(it.next(), "--runs")?.max(1),
                "--cpu-runs" => args.cpu_runs = number(it.next(), "--cpu-runs")?,
                "--random" => args.random = number(it.next(), "--random")?,
                "--chunk" => args.chunk = number(it.next(), "--chunk")?.clamp(1, 1 << 22) as u32,
                "--compare-v2" => {
                    args.compare_v2 = Some(it.next().ok_or("--compare-v2 needs a 2.0 file")?)
                }
                "--size" => {
                    let v = it.next().ok_or("--size needs WxH")?;
                    let (w, h) = v.split_once('x').ok_or("--size needs WxH")?;
                    args.width = w.parse().map_err(|e| format!("--size: {e}"))?;
                    args.height = h.parse().map_err(|e| format!("--size: {e}"))?;
                }
                _ if a.starts_with('-') => return Err(format!("unknown option {a}")),
                _ if args.path.is_empty() => args.path = a,
                _ => return Err(format!("unexpected argument {a}")),
            }
        }
        if args.path.is_empty() {
            return Err(
                "usage: gpu_bench FILE.vdag [--runs N] [--random N] [--size WxH] [--cpu-runs N] [--chunk N]"
                    .into(),
            );
        }
        Ok(args)
    }

    /// CPU time of the calling thread.
    fn thread_cpu_time() -> Duration {
        let mut t = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: `t` is a valid timespec for the call to write.
        let r = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) };
        assert_eq!(r, 0, "clock_gettime(CLOCK_THREAD_CPUTIME_ID)");
        Duration::new(t.tv_sec as u64, t.tv_nsec as u32)
    }

    /// CPU time of rayon's global pool so far, on which the batch path's
    /// host work (set-up and answers) runs and nothing else while it is
    /// measured (the driver's threads are not rayon's).
    fn pool_cpu_time() -> Duration {
        rayon::broadcast(|_| thread_cpu_time()).into_iter().sum()
    }

    fn median(mut v: Vec<Duration>) -> Duration {
        v.sort();
        v[v.len() / 2]
    }

    fn rate(rays: usize, d: Duration) -> String {
        let r = rays as f64 / d.as_secs_f64();
        if r >= 1e9 {
            format!("{:8.3} Grays/s", r / 1e9)
        } else {
            format!("{:8.2} Mrays/s", r / 1e6)
        }
    }

    /// SplitMix64.
    fn next(state: &mut u64) -> f64 {
        *state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = *state;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Rays from random points around the cube to random points inside it.
    fn random_rays(dag: &Dag<'_>, count: usize) -> Vec<Ray> {
        let h = dag.header();
        let mut s = 42u64;
        (0..count)
            .map(|_| {
                let from: [f64; 3] = std::array::from_fn(|i| {
                    h.root_min[i] + h.root_size * (next(&mut s) * 2.0 - 0.5)
                });
                let to: [f64; 3] =
                    std::array::from_fn(|i| h.root_min[i] + h.root_size * next(&mut s));
                Ray::new(
                    from.map(|v| v as f32),
                    std::array::from_fn(|i| (to[i] - from[i]) as f32),
                )
            })
            .collect()
    }

    /// `--compare-v2`: the GPU trace rates of the 1.0 file and the 2.0 file
    /// of the same voxels, the latter expanded and in place, interleaved run
    /// by run.
    fn compare_v2(args: &Args, path2: &str) -> Result<(), String> {
        let file1 =
            MappedFile::open(args.path.as_ref()).map_err(|e| format!("{}: {e}", args.path))?;
        let dag1 = Dag::open(file1.bytes()).map_err(|e| format!("{}: {e}", args.path))?;
        let file2 = MappedFile::open(path2.as_ref()).map_err(|e| format!("{path2}: {e}"))?;
        let dag2 = dagfmt::Dag2::open(file2.bytes()).map_err(|e| format!("{path2}: {e}"))?;
        let context = GpuContext::new(AdapterChoice::Default).map_err(|e| e.to_string())?;
        println!(
            "1.0: {} ({} bytes), 2.0: {path2} ({} bytes), depth {}",
            args.path,
            dag1.bytes().len(),
            dag2.bytes().len(),
            dag1.depth()
        );
        println!("adapter: {}", context.adapter_name());
        let rays = random_rays(&dag1, args.random);
        let (w, h) = (args.width, args.height);
        let pixels = (w * h) as usize;
        let header = dag1.header();
        let camera = Camera::looking_at_cube(
            header.root_min,
            header.root_size,
            f64::from(w) / f64::from(h),
        );
        let layouts = [
            ("2.0 expanded", V2Layout::Expanded),
            ("2.0 in place", V2Layout::InPlace),
        ];
        for (stack_name, stack) in [
            ("full stack", StackMode::Full),
            ("short stack (4)", StackMode::Short(4)),
        ] {
            let options = GpuOptions {
                stack,
                compute_index: false,
                rays_per_dispatch: args.chunk,
                ..GpuOptions::default()
            };
            let t0 = Instant::now();
            let one =
                GpuTracer::with_context(&context, &dag1, &options).map_err(|e| e.to_string())?;
            println!(
                "{stack_name}: 1.0 tracer made in {:.1} ms, {} bytes uploaded",
                t0.elapsed().as_secs_f64() * 1e3,
                one.uploaded_bytes()
            );
            let mut twos = Vec::new();
            for (name, v2_layout) in layouts {
                let t0 = Instant::now();
                let two = GpuTracer::with_context_v2(
                    &context,
                    dag2.header(),
                    dag2.levels(),
                    None,
                    &GpuOptions {
                        v2_layout,
                        ..options.clone()
                    },
                )
                .map_err(|e| e.to_string())?;
                if two.v2_layout() != Some(v2_layout) {
                    return Err(format!("{name}: the 2.0 levels did not expand"));
                }
                println!(
                    "{stack_name}: {name} tracer made in {:.1} ms (expansion {}), {} bytes uploaded",
                    t0.elapsed().as_secs_f64() * 1e3,
                    two.expansion_time().map_or("none".to_string(), |t| format!(
                        "{:.1} ms",
                        t.as_secs_f64() * 1e3
                    )),
                    two.uploaded_bytes()
                );
                twos.push((name, two));
            }
            // Warm-up (buffers, pipelines) and the answers, which must agree.
            let mut hits1 = vec![dagfmt::batch::Hit::MISS; rays.len()];
            let mut hits2 = hits1.clone();
            one.trace_into_with_stats(&rays, &mut hits1)
                .map_err(|e| e.to_string())?;
            one.time_render(&camera, w, h, 1)
                .map_err(|e| e.to_string())?;
            for (name, two) in &twos {
                two.trace_into_with_stats(&rays, &mut hits2)
                    .map_err(|e| e.to_string())?;
                if hits1 != hits2 {
                    let n = hits1.iter().zip(&hits2).filter(|(a, b)| a != b).count();
                    return Err(format!(
                        "{stack_name}: {name} answers differ from 1.0 on {n} rays"
                    ));
                }
                two.time_render(&camera, w, h, 1)
                    .map_err(|e| e.to_string())?;
            }
            // Per run: 1.0, then each 2.0 layout; random rays, then camera rays.
            let (mut r1, mut c1) = (Vec::new(), Vec::new());
            let mut r2 = vec![Vec::new(); twos.len()];
            let mut rr = vec![Vec::new(); twos.len()];
            let mut c2 = vec![Vec::new(); twos.len()];
            let mut cr = vec![Vec::new(); twos.len()];
            for _ in 0..args.runs {
                let a = one
                    .trace_into_with_stats(&rays, &mut hits1)
                    .map_err(|e| e.to_string())?
                    .gpu_time;
                r1.push(a);
                for (i, (_, two)) in twos.iter().enumerate() {
                    let b = two
                        .trace_into_with_stats(&rays, &mut hits2)
                        .map_err(|e| e.to_string())?
                        .gpu_time;
                    rr[i].push(a.as_secs_f64() / b.as_secs_f64());
                    r2[i].push(b);
                }
                let a = one
                    .time_render(&camera, w, h, 1)
                    .map_err(|e| e.to_string())?[0];
                c1.push(a);
                for (i, (_, two)) in twos.iter().enumerate() {
                    let b = two
                        .time_render(&camera, w, h, 1)
                        .map_err(|e| e.to_string())?[0];
                    cr[i].push(a.as_secs_f64() / b.as_secs_f64());
                    c2[i].push(b);
                }
            }
            let median_f = |mut v: Vec<f64>| {
                v.sort_by(f64::total_cmp);
                v[v.len() / 2]
            };
            let spread = |v: &[f64]| {
                (
                    v.iter().copied().fold(f64::INFINITY, f64::min),
                    v.iter().copied().fold(0.0, f64::max),
                )
            };
            println!("{stack_name}, median of {} interleaved runs:", args.runs);
            println!(
                "  random rays ({}): 1.0 {}",
                rays.len(),
                rate(rays.len(), median(r1))
            );
            for (i, (name, _)) in twos.iter().enumerate() {
                let (lo, hi) = spread(&rr[i]);
                println!(
                    "    {name} {}; rate / 1.0 {:.3} (per-run ratios {lo:.3} to {hi:.3})",
                    rate(rays.len(), median(r2[i].clone())),
                    median_f(rr[i].clone()),
                );
            }
            println!("  camera rays ({w}x{h}): 1.0 {}", rate(pixels, median(c1)));
            for (i, (name, _)) in twos.iter().enumerate() {
                let (lo, hi) = spread(&cr[i]);
                println!(
                    "    {name} {}; rate / 1.0 {:.3} (per-run ratios {lo:.3} to {hi:.3})",
                    rate(pixels, median(c2[i].clone())),
                    median_f(cr[i].clone()),
                );
            }
        }
        Ok(())
    }

    pub fn run() -> Result<(), String> {
        let args = parse_args()?;
        if let Some(path2) = &args.compare_v2 {
            return compare_v2(&args, path2);
        }
        let started = Instant::now();
        let file =
            MappedFile::open(args.path.as_ref()).map_err(|e| format!("{}: {e}", args.path))?;
        let dag = Dag::open(file.bytes()).map_err(|e| format!("{}: {e}", args.path))?;
        let opened = started.elapsed();
        let context = GpuContext::new(AdapterChoice::Default).map_err(|e| e.to_string())?;
        let device_ready = started.elapsed();
        let full = GpuTracer::with_context(&context, &dag, &GpuOptions::default())
            .map_err(|e| e.to_string())?;
        let uploaded = started.elapsed();
        let first = random_rays(&dag, 1);
        full.trace(&first).map_err(|e| e.to_string())?;
        let first_ray = started.elapsed();
        println!(
            "file: {} ({} bytes, depth {})",
            args.path,
            dag.bytes().len(),
            dag.depth()
        );
        println!("adapter: {}", context.adapter_name());
        println!(
            "time to first ray: {:.1} ms (open {:.1} ms, device {:.1} ms, upload + shader {:.1} ms, first trace {:.1} ms); {} bytes in {} binding(s)",
            first_ray.as_secs_f64() * 1e3,
            opened.as_secs_f64() * 1e3,
            (device_ready - opened).as_secs_f64() * 1e3,
            (uploaded - device_ready).as_secs_f64() * 1e3,
            (first_ray - uploaded).as_secs_f64() * 1e3,
            full.uploaded_bytes(),
            full.binding_count(),
        );
        let short = GpuTracer::with_context(
            &context,
            &dag,
            &GpuOptions {
                stack: StackMode::Short(4),
                ..GpuOptions::default()
            },
        )
        .map_err(|e| e.to_string())?;
        let (w, h) = (args.width, args.height);
        let pixels = (w * h) as usize;
        let header = dag.header();
        let camera = Camera::looking_at_cube(
            header.root_min,
            header.root_size,
            f64::from(w) / f64::from(h),
        );
        println!("primary rays, {w}x{h}, median of {} runs:", args.runs);
        for (name, tracer) in [("GPU full stack ", &full), ("GPU short stack", &short)] {
            // One warm-up run, then the timed ones.
            let times = tracer
                .time_render(&camera, w, h, args.runs + 1)
                .map_err(|e| e.to_string())?;
            let m = median(times[1..].to_vec());
            println!(
                "  {name}: {} ({:.2} ms)",
                rate(pixels, m),
                m.as_secs_f64() * 1e3
            );
        }
        let cpu = Tracer::new(&dag)
            .map_err(|e| e.to_string())?
            .with_index(false);
        let frame = camera.frame().map_err(|e| e.to_string())?;
        if args.cpu_runs > 0 {
            let rays = frame.rays(w, h, None);
            let times: Vec<Duration> = (0..args.cpu_runs)
                .map(|_| {
                    let t0 = Instant::now();
                    cpu.trace_batch(&rays)
                        .map(|_| t0.elapsed())
                        .map_err(|e| e.to_string())
                })
                .collect::<Result<_, _>>()?;
            let m = median(times);
            println!(
                "  CPU ({} threads): {} ({:.2} ms)",
                rayon::current_num_threads(),
                rate(pixels, m),
                m.as_secs_f64() * 1e3
            );
        }
        if args.random > 0 {
            let rays = random_rays(&dag, args.random);
            println!(
                "random rays, {} rays, median of {} runs (GPU: from the first chunk's submission to the last one's completion, with ray upload and hit read-back / the whole call; host part: the set-up and answers, on all cores, not overlapped waits):",
                rays.len(),
                args.runs
            );
            let no_index = GpuOptions {
                compute_index: false,
                rays_per_dispatch: args.chunk,
                ..GpuOptions::default()
            };
            let tracers = [
                (
                    "GPU full stack ",
                    GpuTracer::with_context(&context, &dag, &no_index)
                        .map_err(|e| e.to_string())?,
                ),
                (
                    "GPU short stack",
                    GpuTracer::with_context(
                        &context,
                        &dag,
                        &GpuOptions {
                            stack: StackMode::Short(4),
                            ..no_index
                        },
                    )
                    .map_err(|e| e.to_string())?,
                ),
            ];
            // The answers go into one reused vector, as a caller tracing
            // batch after batch would (`trace_into_with_stats`).
            let mut hits = vec![dagfmt::batch::Hit::MISS; rays.len()];
            let per_million = 1e6 / rays.len() as f64;
            for (name, tracer) in &tracers {
                let mut gpu = Vec::new();
                let mut total = Vec::new();
                let mut host = Vec::new();
                let mut ratio = Vec::new();
                let mut host_cpu = Vec::new();
                let mut iterations = 0.0;
                // One untimed call first: it makes the tracer's chunk buffers.
                tracer
                    .trace_into_with_stats(&rays, &mut hits)
                    .map_err(|e| e.to_string())?;
                for _ in 0..args.runs {
                    let cpu_before = pool_cpu_time();
                    let stats = tracer
                        .trace_into_with_stats(&rays, &mut hits)
                        .map_err(|e| e.to_string())?;
                    host_cpu.push(pool_cpu_time().saturating_sub(cpu_before));
                    gpu.push(stats.gpu_time);
                    total.push(stats.total_time);
                    host.push(stats.host_time);
                    ratio.push(Duration::from_secs_f64(
                        stats.total_time.as_secs_f64() / stats.gpu_time.as_secs_f64().max(1e-9),
                    ));
                    iterations = stats.iterations as f64 / stats.gpu_rays.max(1) as f64;
                }
                println!(
                    "  {name}: {} / {} (host part {:.1} ms, {:.2} ms per 10^6 rays, {:.2} ms of CPU per 10^6 rays; whole call {:.3}x the dispatch time; {:.1} loop iterations per traced ray)",
                    rate(rays.len(), median(gpu)),
                    rate(rays.len(), median(total)),
                    median(host.clone()).as_secs_f64() * 1e3,
                    median(host).as_secs_f64() * 1e3 * per_million,
                    median(host_cpu).as_secs_f64() * 1e3 * per_million,
                    median(ratio).as_secs_f64(),
                    iterations
                );
            }
            if args.cpu_runs > 0 {
                let cpu_rays: Vec<dagtrace::Ray> = rays
                    .iter()
                    .map(|r| dagtrace::Ray {
                        origin: r.origin,
                        dir: r.dir,
                        tmin: r.tmin,
                        tmax: r.tmax,
                        level: r.level,
                    })
                    .collect();
                let times: Vec<Duration> = (0..args.cpu_runs)
                    .map(|_| {
                        let t0 = Instant::now();
                        cpu.trace_batch(&cpu_rays)
                            .map(|_| t0.elapsed())
                            .map_err(|e| e.to_string())
                    })
                    .collect::<Result<_, _>>()?;
                println!(
                    "  CPU ({} threads): {}",
                    rayon::current_num_threads(),
                    rate(rays.len(), median(times))
                );
            }
        }
        Ok(())
    }
}
