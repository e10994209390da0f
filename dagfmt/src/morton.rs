//! Morton (Z-order) codes of voxel coordinates.
//!
//! The Morton code of a voxel at depth D is the concatenation of the child
//! indices along its path from the root, three bits per level, the root's
//! first: bit `3k` is bit `k` of x, bit `3k + 1` of y, bit `3k + 2` of z. Sorting
//! voxels by Morton code therefore visits them in the DAG's child order.

/// Spreads the low 21 bits of `v` so that bit `k` lands on bit `3k`.
#[inline]
pub fn spread3(v: u32) -> u64 {
    let mut x = u64::from(v) & 0x1f_ffff;
    x = (x | (x << 32)) & 0x001f_0000_0000_ffff;
    x = (x | (x << 16)) & 0x001f_0000_ff00_00ff;
    x = (x | (x << 8)) & 0x100f_00f0_0f00_f00f;
    x = (x | (x << 4)) & 0x10c3_0c30_c30c_30c3;
    x = (x | (x << 2)) & 0x1249_2492_4924_9249;
    x
}

/// Gathers bits `3k` of `x` into bit `k` of the result (inverse of [`spread3`]).
#[inline]
pub fn compact3(x: u64) -> u32 {
    let mut x = x & 0x1249_2492_4924_9249;
    x = (x | (x >> 2)) & 0x10c3_0c30_c30c_30c3;
    x = (x | (x >> 4)) & 0x100f_00f0_0f00_f00f;
    x = (x | (x >> 8)) & 0x001f_0000_ff00_00ff;
    x = (x | (x >> 16)) & 0x001f_0000_0000_ffff;
    x = (x | (x >> 32)) & 0x1f_ffff;
    x as u32
}

/// The Morton code of voxel `(x, y, z)`; each coordinate uses its low 21 bits.
#[inline]
pub fn encode(x: u32, y: u32, z: u32) -> u64 {
    spread3(x) | (spread3(y) << 1) | (spread3(z) << 2)
}

/// The coordinates of the voxel with Morton code `code`.
#[inline]
pub fn decode(code: u64) -> [u32; 3] {
    [compact3(code), compact3(code >> 1), compact3(code >> 2)]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_order() {
        for &(x, y, z) in &[
            (0, 0, 0),
            (1, 0, 0),
            (0, 1, 0),
            (0, 0, 1),
            (0x1f_ffff, 5, 0x10_0000),
        ] {
            assert_eq!(decode(encode(x, y, z)), [x, y, z]);
        }
        assert_eq!(encode(1, 0, 0), 1);
        assert_eq!(encode(0, 1, 0), 2);
        assert_eq!(encode(0, 0, 1), 4);
        assert_eq!(encode(2, 0, 0), 8);
        assert_eq!(encode(0x1f_ffff, 0x1f_ffff, 0x1f_ffff), (1u64 << 63) - 1);
    }
}
