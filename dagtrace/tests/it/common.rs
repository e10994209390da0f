//! Shared helpers: building small DAGs and a deterministic random source.

use dagfmt::AttributeKind;
use dagfmt::builder::DagBuilder;

/// The bytes of a `.vdag` holding `voxels`, with the given root cube.
pub fn build(
    depth: u8,
    kind: AttributeKind,
    voxels: &[[u32; 3]],
    root_min: [f64; 3],
    root_size: f64,
) -> Vec<u8> {
    let mut built = DagBuilder::from_voxels(depth, kind, voxels.iter().copied())
        .expect("test voxels are valid");
    built
        .set_root_cube(root_min, root_size)
        .expect("test root cube is valid");
    built.to_bytes()
}

/// splitmix64: a small deterministic generator for test data.
#[derive(Clone, Debug)]
pub struct Rng(pub u64);

impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    /// Uniform integer in [0, n).
    pub fn below(&mut self, n: u64) -> u64 {
        self.next_u64() % n.max(1)
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f64) -> bool {
        self.unit() < p
    }
}
