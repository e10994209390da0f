//! Packed colours on a real file's colour stream: size against raw 24-bit RGB,
//! measured error and PSNR, encode and decode speed, for several error bounds.
//!
//! `cargo run --release -p dagfmt --example color_bench -- FILE.vdag [E ...]`
//! (the file's colours, raw or packed; default bounds 0 and 8). With
//! `COLOR_BENCH_LAYOUTS=1` each bound is also encoded in every fixed layout
//! (format 1.1's 64-colour blocks, and 64, 128, 256 with split sub-blocks)
//! beside the encoder's own choice.
use dagfmt::Dag;
use dagfmt::packed_colors::{BlockLayout, PackedColors, check_section, encode, encode_with_layout};
use std::time::Instant;

fn main() {
    let mut args = std::env::args().skip(1);
    let Some(path) = args.next() else {
        eprintln!("usage: color_bench FILE.vdag [E ...]");
        std::process::exit(2);
    };
    let bounds: Vec<u8> = args
        .map(|a| a.parse().expect("error bound 0..=127"))
        .collect();
    let bounds = if bounds.is_empty() {
        vec![0, 8]
    } else {
        bounds
    };
    let map = dagfmt::mmap::MappedFile::open(std::path::Path::new(&path)).expect("open");
    let dag = Dag::open(map.bytes()).expect("a .vdag");
    let table = dag.color_table().expect("a file with colours");
    let colors: Vec<[u8; 4]> = table.iter().collect();
    let n = colors.len() as u64;
    println!("{path}: {n} colours");
    println!(
        "| E | layout | bytes | bits/voxel | % of raw RGB | max error | PSNR dB | encode MB/s | random Mcol/s | sequential Mcol/s |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let mut layouts = vec![None];
    if std::env::var_os("COLOR_BENCH_LAYOUTS").is_some() {
        layouts.push(Some(BlockLayout::V1_1));
        layouts.extend(BlockLayout::CHOICES.map(Some));
    }
    for (e, layout) in bounds
        .iter()
        .flat_map(|&e| layouts.iter().map(move |&l| (e, l)))
    {
        let t = Instant::now();
        let (bytes, summary) = match layout {
            None => encode(&colors, e),
            Some(l) => encode_with_layout(&colors, e, l),
        }
        .expect("bound ≤ 127");
        let enc = t.elapsed().as_secs_f64();
        assert!(
            check_section(&bytes, n).is_empty(),
            "the encoder wrote an invalid section"
        );
        let packed = PackedColors::new(&bytes, n).expect("valid");
        let t = Instant::now();
        let mut max = 0u8;
        for (src, dec) in colors.iter().zip(packed.iter()) {
            for c in 0..4 {
                max = max.max(src[c].abs_diff(dec[c]));
            }
        }
        let seq = t.elapsed().as_secs_f64();
        assert!(max <= e);
        assert_eq!(max, summary.trailer.max_error);
        // Random access in a scattered order.
        let t = Instant::now();
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        let mut sum = 0u64;
        let probes = n.min(4_000_000);
        for _ in 0..probes {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            sum += u64::from(packed.get(x % n).unwrap()[0]);
        }
        let rnd = t.elapsed().as_secs_f64();
        std::hint::black_box(sum);
        let bpv = bytes.len() as f64 * 8.0 / n as f64;
        let l = summary.trailer.layout;
        let name = format!(
            "{}{} {}{}",
            if layout.is_none() { "auto: " } else { "" },
            1 << l.shift,
            if l.split { "split" } else { "plain" },
            if l.is_v1_1() { " (1.1)" } else { "" }
        );
        println!(
            "| {e} | {name} | {} | {bpv:.3} | {:.2} % | {max} | {:.2} | {:.0} | {:.1} | {:.1} |",
            bytes.len(),
            bpv / 24.0 * 100.0,
            summary.trailer.psnr(n),
            n as f64 * 4.0 / enc / 1e6,
            probes as f64 / rnd / 1e6,
            n as f64 / seq / 1e6,
        );
    }
}
