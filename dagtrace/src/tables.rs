//! Lookup tables of the traversal, built at compile time.
//!
//! Child indices follow the format: `c = x | y << 1 | z << 2`, a set bit
//! meaning the upper half. The tracer works in a *mirrored* frame where every
//! direction component is non-negative: axis `i` is flipped when bit `i` of the
//! ray's direction octant `neg` is set, so a child `c` of the file is child
//! `c ^ neg` of the mirrored frame. In the mirrored frame the ray only ever moves
//! from a lower half to an upper half, which is what makes these tables small.

/// `CHAIN[neg][key]`: the children (as a mask of *file* child indices) that the
/// ray passes through inside a node.
///
/// `key = c0 | crossing << 3 | order << 6`, all in the mirrored frame:
/// - `c0` (3 bits): the child holding the ray where it enters the node (bit `i`
///   set when the ray is already past the mid-plane of axis `i`);
/// - `crossing` (3 bits): the axes whose mid-plane the ray crosses after
///   inside the node's `[t_enter, t_exit]`;
/// - `order` (3 bits): `t_x < t_y`, `t_x < t_z`, `t_y < t_z` for the mid-plane
///   crossing times.
///
/// The ray visits `c0`, then adds one crossing axis at a time in time order,
/// so the children it passes through form a chain of at most four.
pub static CHAIN: [[u8; 512]; 8] = build_chain();

/// `FIRST[neg][mask]`: the child (file index) of `mask` that comes first in
/// front-to-back order for a ray of direction octant `neg`, i.e. the one with
/// the fewest mirrored upper-half bits. Any set of children that lies on one
/// ray's chain has a unique such child. `FIRST[_][0]` is 0 and never used.
pub static FIRST: [[u8; 256]; 8] = build_first();

/// [`CHAIN`] as one flat byte table (`[neg * 512 + key]`) with 4 bytes of
/// padding, so that the vector traversal can gather any entry with a 32-bit
/// load that stays inside the table.
pub static CHAIN_PADDED: [u8; 8 * 512 + 4] = flatten_padded(&build_chain());

/// [`FIRST`] as one flat byte table (`[neg * 256 + mask]`), padded like
/// [`CHAIN_PADDED`].
pub static FIRST_PADDED: [u8; 8 * 256 + 4] = flatten_padded(&build_first());

const fn flatten_padded<const ROW: usize, const N: usize>(rows: &[[u8; ROW]; 8]) -> [u8; N] {
    let mut t = [0u8; N];
    let mut i = 0;
    while i < 8 * ROW {
        t[i] = rows[i / ROW][i % ROW];
        i += 1;
    }
    t
}

/// Number of set bits of a byte: the rank of a child pointer. A table because
/// the default x86-64 target has no `popcnt` instruction.
pub static POPCOUNT8: [u8; 256] = build_popcount();

/// `CHILD_BITS[c]`: per axis, 1 when child `c` is the upper half.
pub static CHILD_BITS: [[u32; 3]; 8] = build_child_bits();

const fn build_popcount() -> [u8; 256] {
    let mut t = [0u8; 256];
    let mut i = 0;
    while i < 256 {
        t[i] = (i as u8).count_ones() as u8;
        i += 1;
    }
    t
}

const fn build_child_bits() -> [[u32; 3]; 8] {
    let mut t = [[0u32; 3]; 8];
    let mut c = 0;
    while c < 8 {
        t[c] = [(c & 1) as u32, ((c >> 1) & 1) as u32, ((c >> 2) & 1) as u32];
        c += 1;
    }
    t
}

/// Whether crossing of axis `j` comes before crossing of axis `i` (`i != j`)
/// according to the three comparison bits; exactly one of `before(i, j)` and
/// `before(j, i)` holds, ties going to the higher axis.
const fn before(order: usize, j: usize, i: usize) -> bool {
    // Bit of the pair (a, b) with a < b says t_a < t_b.
    let (a, b, swapped) = if j < i { (j, i, false) } else { (i, j, true) };
    let bit = match (a, b) {
        (0, 1) => 0,
        (0, 2) => 1,
        _ => 2,
    };
    let a_first = order >> bit & 1 == 1;
    if swapped { !a_first } else { a_first }
}

const fn build_chain() -> [[u8; 512]; 8] {
    let mut t = [[0u8; 512]; 8];
    let mut neg = 0;
    while neg < 8 {
        let mut key = 0;
        while key < 512 {
            let c0 = key & 7;
            let crossing = (key >> 3) & 7 & !c0;
            let order = key >> 6;
            // Rank of each crossing axis among the crossing axes.
            let mut rank = [0usize; 3];
            let mut i = 0;
            while i < 3 {
                let mut j = 0;
                while j < 3 {
                    if i != j
                        && crossing >> i & 1 == 1
                        && crossing >> j & 1 == 1
                        && before(order, j, i)
                    {
                        rank[i] += 1;
                    }
                    j += 1;
                }
                i += 1;
            }
            // Walk the chain: step k adds the axes of rank < k. With a
            // consistent order the ranks are 0, 1, 2; an inconsistent one
            // (impossible for real comparisons) still gives a chain.
            let mut mask = 0u32;
            let mut k = 0;
            while k <= 3 {
                let mut c = c0;
                let mut i = 0;
                while i < 3 {
                    if crossing >> i & 1 == 1 && rank[i] < k {
                        c |= 1 << i;
                    }
                    i += 1;
                }
                mask |= 1 << (c ^ neg);
                k += 1;
            }
            t[neg][key] = mask as u8;
            key += 1;
        }
        neg += 1;
    }
    t
}

const fn build_first() -> [[u8; 256]; 8] {
    let mut t = [[0u8; 256]; 8];
    let mut neg = 0;
    while neg < 8 {
        let mut mask = 1;
        while mask < 256 {
            let mut best = 0;
            let mut best_key = u32::MAX;
            let mut c = 0;
            while c < 8 {
                if mask >> c & 1 == 1 {
                    let key = ((c ^ neg) as u32).count_ones();
                    if key < best_key {
                        best_key = key;
                        best = c;
                    }
                }
                c += 1;
            }
            t[neg][mask] = best as u8;
            mask += 1;
        }
        neg += 1;
    }
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chain_of_a_ray_without_crossings_is_its_entry_child() {
        for (neg, table) in CHAIN.iter().enumerate() {
            for (c0, &mask) in table.iter().enumerate().take(8) {
                assert_eq!(mask, 1 << (c0 ^ neg));
            }
        }
    }

    #[test]
    fn chain_follows_crossing_order() {
        // Mirrored frame, neg = 0: enter child 0, cross z first, then x, then y.
        // order bits: t_x < t_y (1), t_x < t_z (0), t_y < t_z (0).
        let key = 0b111 << 3 | 0b001 << 6;
        let expected = 1 << 0 | 1 << 4 | 1 << 5 | 1 << 7;
        assert_eq!(CHAIN[0][key], expected);
        // Same ray mirrored in x: file children are mirrored indices ^ 1.
        assert_eq!(CHAIN[1][key], 1 << 1 | 1 << 5 | 1 << 4 | 1 << 6);
    }

    #[test]
    fn first_is_front_to_back() {
        assert_eq!(FIRST[0][0b1001_0110], 1);
        assert_eq!(FIRST[7][0b1000_0001], 7);
        assert_eq!(FIRST[1][0b0000_0011], 1);
        for neg in 0..8 {
            for mask in 0..256 {
                assert_eq!(FIRST_PADDED[neg * 256 + mask], FIRST[neg][mask]);
            }
            for key in 0..512 {
                assert_eq!(CHAIN_PADDED[neg * 512 + key], CHAIN[neg][key]);
            }
        }
        for (m, &count) in POPCOUNT8.iter().enumerate() {
            assert_eq!(u32::from(count), m.count_ones());
        }
    }
}
