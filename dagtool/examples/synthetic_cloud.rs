//! Writes a synthetic point cloud as a binary little-endian PLY, for the
//! out-of-core point benchmark (dagtool/BENCHMARKS.md):
//!
//! ```sh
//! cargo run --release -p dagtool --example synthetic_cloud -- /tmp/cloud.ply 100000000
//! dagtool convert /tmp/cloud.ply -o /tmp/cloud.vdag --depth 14 --memory-limit 2G
//! ```
//!
//! The points lie on a wavy sphere of radius about 1 (`x y z` as float32,
//! `red green blue` as uchar), drawn by a SplitMix64 generator from a fixed
//! seed, so that every run writes the same file.

use std::io::{BufWriter, Write};

fn main() -> std::io::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(path), Some(count)) = (args.get(1), args.get(2).and_then(|c| c.parse::<u64>().ok()))
    else {
        eprintln!("usage: synthetic_cloud OUT.ply POINTS");
        std::process::exit(2);
    };
    let mut out = BufWriter::with_capacity(1 << 22, std::fs::File::create(path)?);
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\nelement vertex {count}\n\
         property float x\nproperty float y\nproperty float z\n\
         property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )?;
    let mut state = 0x5EED_u64;
    let mut next = || {
        state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut record = [0u8; 15];
    for _ in 0..count {
        let (u, v) = (next(), next());
        let theta = std::f64::consts::TAU * u;
        let phi = (2.0 * v - 1.0).acos();
        let r = 1.0 + 0.05 * (5.0 * theta).sin() * (4.0 * phi).cos();
        let p = [
            r * phi.sin() * theta.cos(),
            r * phi.sin() * theta.sin(),
            r * phi.cos(),
        ];
        for (k, c) in p.iter().enumerate() {
            record[4 * k..4 * k + 4].copy_from_slice(&(*c as f32).to_le_bytes());
        }
        record[12..].copy_from_slice(&[(u * 255.0) as u8, (v * 255.0) as u8, 128]);
        out.write_all(&record)?;
    }
    out.flush()
}
