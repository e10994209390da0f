// The GPU traversal of a .vdag sparse voxel DAG.
//
// Preceded by a preamble generated from dagtrace/src/gpu/layout.rs (shared
// structs, constants, bindings and `load_word`).
//
// The traversal is the CPU tracer's (dagtrace/src/walk.rs), with the same
// plane arithmetic and tie rules, so that both find the same cell:
// - the ray is in grid space, mirrored so that every direction component is
//   non-negative (bit i of `octant` set when axis i is mirrored); cell
//   coordinates (`idx`) are mirrored too, child index bits are the file's
//   XOR the octant;
// - at a node, the entry/exit parameters and the three mid-plane crossings
//   come from exact plane positions, t = (p - o) * inv_dir; the children the
//   ray passes through form a chain (entry child, then one axis flipped per
//   mid-plane crossing, in crossing order), computed by `chain` (the CPU looks
//   the same chain up in a table), ANDed with the (mirrored) child mask, and
//   visited in increasing mirrored index, which is chain order;
// - the child pointer is found by rank (popcount of the lower mask bits);
// - the last two levels (the 4^3 brick of a leaf) come from the 64-bit mask.
//
// Format 2.0 (spec §23; FORMAT_V2, a separate shader: the 1.0 shader has
// these branches compiled out): each frame carries the accumulated
// reflection R (§23.4). Its node levels are read in one of two forms:
// - expanded (the default; spec §23.12, dagfmt::expand): 1.0-like records
//   of aligned words, a child one word `index << 3 | r` at rank + 1 after
//   the header (`child_entry`), so a node is addressed and read as in 1.0
//   with 4-byte pointers;
// - in place (V2_IN_PLACE: files that do not expand, or when asked): a
//   node's address is its byte offset in its level, its references are
//   decoded by the functions below (the counterpart of dagfmt::v2::Coding). A node reached with R is traced as a 1.0 node by a ray whose
// octant is `neg ^ R` (the CPU's walk.rs does the same): physical slot of
// mirrored child j is `j ^ neg ^ R`, and a leaf's sub-brick and voxel bits
// are both indexed with `neg ^ R`; a child's R is its parent's XOR the
// reference's reflection. The dense index sums the siblings at physical
// slots p with (p ^ R) < c and counts the bits of the reflected leaf mask.
//
// Stack: one entry (node word address (2.0 in place: byte offset), child
// mask | remaining chain << 8 | R << 16) per interior level; 2.0 in place
// keeps the node's codes in a second array. With SHORT_STACK the stack is a ring of STACK_SIZE entries;
// when the traversal pops to a level whose entry was overwritten, it restarts
// from the root and replays the path to that level (the path is the current
// cell's coordinate bits): every node on the way is evaluated with the same
// arithmetic as before, so the recomputed remaining-children masks (minus the
// children already done) are exactly what the full stack held, and both
// variants return identical answers.

struct Prepared {
    o: vec3<f32>,
    inv: vec3<f32>,
    tmin: f32,
    tmax: f32,
    neg: u32,
    level: u32,
}

struct Found {
    hit: bool,
    // Mirrored cell coordinates at `level`.
    cell: vec3<u32>,
    level: u32,
    status: u32,
    iterations: u32,
}

fn max3(v: vec3<f32>) -> f32 {
    return max(v.x, max(v.y, v.z));
}

fn min3(v: vec3<f32>) -> f32 {
    return min(v.x, min(v.y, v.z));
}

// The per-axis bits of child index j (1 = upper half).
fn axis_bits(j: u32) -> vec3<u32> {
    return vec3<u32>(j & 1u, (j >> 1u) & 1u, (j >> 2u) & 1u);
}

// Child mask in the mirrored frame: bit j = bit (j ^ neg) of m.
fn mirror_mask(m: u32, neg: u32) -> u32 {
    var r = m;
    r = select(r, ((r & 0x55u) << 1u) | ((r >> 1u) & 0x55u), (neg & 1u) != 0u);
    r = select(r, ((r & 0x33u) << 2u) | ((r >> 2u) & 0x33u), (neg & 2u) != 0u);
    r = select(r, ((r & 0x0fu) << 4u) | ((r >> 4u) & 0x0fu), (neg & 4u) != 0u);
    return r;
}

// The children (mirrored-frame mask) a ray passes through inside a node it
// enters at `te` and leaves at `tx`, crossing the mid-planes at `tm`. Same
// semantics as the CPU tracer's CHAIN table: an axis whose crossing is at or
// before the entry starts in the upper half (a point on a boundary belongs to
// the cell the ray moves into); an axis is crossed when te < tm <= tx (a
// crossing exactly at the exit still touches the next, closed, child);
// crossings are ordered by time, ties going to the higher axis.
fn chain(te: f32, tx: f32, tm: vec3<f32>) -> u32 {
    let first = tm <= vec3<f32>(te);
    let crossing = (tm > vec3<f32>(te)) & (tm <= vec3<f32>(tx));
    let c0 = select(0u, 1u, first.x) | select(0u, 2u, first.y) | select(0u, 4u, first.z);
    // The crossing axes that come before each axis.
    let before_x = select(0u, 2u, crossing.y && tm.y <= tm.x) | select(0u, 4u, crossing.z && tm.z <= tm.x);
    let before_y = select(0u, 1u, crossing.x && tm.x < tm.y) | select(0u, 4u, crossing.z && tm.z <= tm.y);
    let before_z = select(0u, 1u, crossing.x && tm.x < tm.z) | select(0u, 2u, crossing.y && tm.y < tm.z);
    var m = 1u << c0;
    m |= select(0u, 1u << (c0 | before_x | 1u), crossing.x);
    m |= select(0u, 1u << (c0 | before_y | 2u), crossing.y);
    m |= select(0u, 1u << (c0 | before_z | 4u), crossing.z);
    return m;
}

// Bit k set when byte k of w is non-zero (k in 0..4).
fn byte_flags(w: u32) -> u32 {
    var t = w | (w >> 4u);
    t |= t >> 2u;
    t |= t >> 1u;
    return (t & 1u) | ((t >> 7u) & 2u) | ((t >> 14u) & 4u) | ((t >> 21u) & 8u);
}

// Pointer number `rank` of the node record at word address `node`, of `width`
// bytes (1 to 4), little-endian; a 3-byte pointer may straddle two words.
fn fetch_pointer(node: u32, rank: u32, width: u32) -> u32 {
    let bit = rank * width * 8u;
    let a = node + 1u + (bit >> 5u);
    let shift = bit & 31u;
    var v = load_word(a) >> shift;
    if (shift + width * 8u > 32u) {
        v |= load_word(a + 1u) << (32u - shift);
    }
    if (width < 4u) {
        v &= (1u << (width * 8u)) - 1u;
    }
    return v;
}

// Node and leaf decoding, the counterpart of the CPU tracer's
// dagtrace/src/node.rs (the test gpu::decode_check runs these functions on
// the device and compares them with it).

// Word address of record `pointer` of level `level`: a node's header word,
// or a leaf mask's low word.
fn record_address(level: u32, pointer: u32) -> u32 {
    return params.levels[level].x + select(pointer, 2u * pointer, level == params.leaf_level);
}

// The child mask of the node at word address `a`.
fn node_mask(a: u32) -> u32 {
    return load_word(a) & 0xffu;
}

// The 24 attribute bits of the node at word address `a`.
fn node_attribute(a: u32) -> u32 {
    return load_word(a) >> CHILD_MASK_BITS;
}

// The reference (pointer into level `level + 1`) of the child at slot `c`
// (set in `mask`) of the node of level `level` at word address `a`, whose
// child mask is `mask`.
fn child_reference(a: u32, level: u32, mask: u32, c: u32) -> u32 {
    return fetch_pointer(a, countOneBits(mask & ((1u << c) - 1u)), params.levels[level].y);
}

// The child at slot `c` (set in `mask`) of the node of level `level` at word
// address `a`: (pointer into level `level + 1`, reflection). 1.0: the
// reference, reflection 0; 2.0 expanded (spec §23.12): the word at rank + 1,
// `index << 3 | r`, one aligned load whatever the width of the file's
// references.
fn child_entry(a: u32, level: u32, mask: u32, c: u32) -> vec2<u32> {
    if (FORMAT_V2) {
        let w = load_word(a + 1u + countOneBits(mask & ((1u << c) - 1u)));
        return vec2<u32>(w >> 3u, w & 7u);
    }
    return vec2<u32>(child_reference(a, level, mask, c), 0u);
}

// The leaf mask at word address `a` (low word, high word).
fn leaf_mask(a: u32) -> vec2<u32> {
    return vec2<u32>(load_word(a), load_word(a + 1u));
}

// ---- Format 2.0 records (spec §23.2, §23.3) ----

// Bits 0, 2, 4, ... of a code word: the low bit of each 2-bit code.
const LOW_CODE_BITS: u32 = 0x55555u;

// A 2.0 record's header word and its m 2-bit codes (code i in bits 2i, 2i+1).
// `w1`, `w2`: the record's second and third aligned words (from the word
// holding its first byte), where its first references usually are.
struct Codes2 {
    header: u32,
    codes: u32,
    count: u32,
    w1: u32,
    w2: u32,
}

// The 32 bits at bit `s` (0..32) of the 64-bit little-endian (w0, w1).
fn funnel(w0: u32, w1: u32, s: u32) -> u32 {
    return select((w0 >> s) | (w1 << (32u - s)), w0, s == 0u);
}

// The header and codes of the record at byte `off` of 2.0 level `level`: at
// most 3 aligned loads (spec §23.8). As dagfmt::v2::Coding::codes.
fn codes2(level: u32, off: u32) -> Codes2 {
    let a = params.levels[level].x + (off >> 2u);
    let s = (off & 3u) * 8u;
    let w0 = load_word(a);
    let w1 = load_word(a + 1u);
    let w2 = load_word(a + 2u);
    var c: Codes2;
    c.header = funnel(w0, w1, s);
    c.w1 = w1;
    c.w2 = w2;
    let k = countOneBits(c.header & 0xffu);
    // The k codes and the base code, if any: at most 18 bits from byte off + 4.
    let raw = funnel(w1, w2, s);
    let k_codes = raw & ((1u << (2u * k)) - 1u);
    let n_shared = countOneBits((k_codes | (k_codes >> 1u)) & LOW_CODE_BITS);
    let count = k + select(0u, 1u, n_shared < k);
    var codes = raw & ((1u << (2u * count)) - 1u);
    if (count > k && (codes >> (2u * k)) == 0u) {
        // A base code of 0 is invalid; it reads as 1, as on the CPU.
        codes |= 1u << (2u * k);
    }
    c.codes = codes;
    c.count = count;
    return c;
}

// Width in bits of the references of `code` (1..=3) of a level whose widths
// word is `widths` (w1 | w2 << 8 | w3 << 16).
fn code_width(widths: u32, code: u32) -> u32 {
    return (widths >> (8u * (code - 1u))) & 0xffu;
}

// Bits of the references of the codes in `codes` (a prefix of a code word):
// n1·w1 + n2·w2 + n3·w3, three masked popcounts.
fn reference_bits2(widths: u32, codes: u32) -> u32 {
    let low = codes & LOW_CODE_BITS;
    let high = (codes >> 1u) & LOW_CODE_BITS;
    return countOneBits(low & ~high) * (widths & 0xffu)
        + countOneBits(high & ~low) * ((widths >> 8u) & 0xffu)
        + countOneBits(low & high) * ((widths >> 16u) & 0xffu);
}

// Bytes of the record at byte `off` of 2.0 level `level`.
fn record_size2(level: u32, off: u32) -> u32 {
    let c = codes2(level, off);
    return 4u + (2u * c.count + reference_bits2(params.levels[level].y, c.codes) + 7u) / 8u;
}

// The `width`-bit value (1 to 40 bits) at bit `bit` of the record at byte
// `off` of level `level`, least significant bit first: (bits 0..32, bits
// 32..40). 1 to 3 aligned loads.
fn value2(level: u32, off: u32, bit: u32, width: u32) -> vec2<u32> {
    let byte = off + (bit >> 3u);
    let a = params.levels[level].x + (byte >> 2u);
    let s = ((byte & 3u) << 3u) | (bit & 7u);
    let w0 = load_word(a);
    var w1 = 0u;
    var w2 = 0u;
    if (s + width > 32u) {
        w1 = load_word(a + 1u);
        if (s + width > 64u) {
            w2 = load_word(a + 2u);
        }
    }
    var lo = funnel(w0, w1, s);
    var hi = funnel(w1, w2, s);
    if (width < 32u) {
        lo &= (1u << width) - 1u;
        hi = 0u;
    } else {
        hi &= (1u << (width - 32u)) - 1u;
    }
    return vec2<u32>(lo, hi);
}

// `value2` of the record whose `Codes2` is `c`: from the words `codes2`
// read (no load) when the value lies in them, else `value2`.
fn value2_from(level: u32, off: u32, c: Codes2, bit: u32, width: u32) -> vec2<u32> {
    // Bit position from the start of the record's first word (at least 32).
    let at = ((off & 3u) << 3u) + bit;
    if (at + width > 96u) {
        return value2(level, off, bit, width);
    }
    let sh = at - 32u;
    var lo = select(funnel(c.w1, c.w2, sh), c.w2 >> (sh - 32u), sh >= 32u);
    var hi = 0u;
    if (width < 32u) {
        lo &= (1u << width) - 1u;
    } else {
        hi = funnel(c.w2, 0u, sh) & ((1u << (width - 32u)) - 1u);
    }
    return vec2<u32>(lo, hi);
}

// The child at physical slot `slot` (set in the child mask) of the record at
// byte `off` of 2.0 level `level`, whose header and codes are `c`: (address
// in level + 1, reflection). A shared child's reference is at bit 2m +
// n1·w1 + n2·w2 + n3·w3 of the stream; a sequential child is `base + j` in
// the leaf level, else the j-th record after `base` (`next_records`). Both
// kinds read one reference (the child's, or the base reference after the k
// children's), by the same arithmetic, so that lanes taking either agree
// on the load. An address beyond 32 bits reads as 0xffffffff (out of range).
fn child2(level: u32, off: u32, c: Codes2, slot: u32) -> vec2<u32> {
    let widths = params.levels[level].y;
    let mask = c.header & 0xffu;
    let k = countOneBits(mask);
    let rank = countOneBits(mask & ((1u << slot) - 1u));
    let code = (c.codes >> (2u * rank)) & 3u;
    let is_shared = code != 0u;
    let upto = select(k, rank, is_shared);
    let reference_code = select((c.codes >> (2u * k)) & 3u, code, is_shared);
    let before = c.codes & ((1u << (2u * upto)) - 1u);
    let v = value2_from(level, off, c, 32u + 2u * c.count + reference_bits2(widths, before), code_width(widths, reference_code));
    if (is_shared) {
        let dest = select(0xffffffffu, (v.x >> 3u) | (v.y << 29u), v.y < 8u);
        return vec2<u32>(dest, v.x & 7u);
    }
    let base = select(0xffffffffu, v.x, v.y == 0u);
    let earlier = c.codes & ((1u << (2u * rank)) - 1u);
    let j = rank - countOneBits((earlier | (earlier >> 1u)) & LOW_CODE_BITS);
    let child_level = level + 1u;
    if (child_level == params.leaf_level) {
        return vec2<u32>(select(0xffffffffu, base + j, base <= 0xffffffffu - j), 0u);
    }
    return vec2<u32>(next_records(child_level, base, j), 0u);
}

// A record's `Codes2` for the traversal's stack: codes and their count in
// one word (codes: at most 18 bits), and the words `w1`, `w2`.
fn pack_codes2(c: Codes2) -> vec3<u32> {
    return vec3<u32>(c.codes | (c.count << 20u), c.w1, c.w2);
}

// The `Codes2` of a record from its child mask and `pack_codes2`.
fn unpack_codes2(mask: u32, packed: vec3<u32>) -> Codes2 {
    var c: Codes2;
    c.header = mask;
    c.codes = packed.x & 0xfffffu;
    c.count = packed.x >> 20u;
    c.w1 = packed.y;
    c.w2 = packed.z;
    return c;
}

// The byte offset of the record `n` records after the one at byte `at` of
// 2.0 level `level`: the n-th set bit after bit `at` of the level's
// record-start bit vector (uploaded with it, `upload::record_starts`),
// usually one load; 0xffffffff past the level. (`at + size(at) + ...`, the
// sizes read from each record's header and codes, `record_size2`, gives
// the same in a valid level.)
fn next_records(level: u32, at: u32, count: u32) -> u32 {
    if (count == 0u) {
        return at;
    }
    let starts = params.levels[level].w;
    let words = (params.levels[level].z + 31u) / 32u;
    var n = count;
    var w = at >> 5u;
    if (w >= words) {
        return 0xffffffffu;
    }
    var m = load_word(starts + w) & ~((2u << (at & 31u)) - 1u);
    loop {
        let c = countOneBits(m);
        if (c >= n) {
            for (var t = 1u; t < n; t += 1u) {
                m &= m - 1u;
            }
            return w * 32u + countTrailingZeros(m);
        }
        n -= c;
        w += 1u;
        if (w >= words) {
            return 0xffffffffu;
        }
        m = load_word(starts + w);
    }
    return 0xffffffffu;
}

// The leaf mask `bits` (low, high word) of a leaf reached with accumulated
// reflection `r`, as its logical brick: bit b is stored bit b ^ (r | r << 3)
// (spec §23.4): flipping index bit i swaps the halves of every group of
// 2^(i+1) bits, six masked swaps at most.
fn reflect_leaf(bits: vec2<u32>, r: u32) -> vec2<u32> {
    var m = bits;
    let rr = r | (r << 3u);
    if ((rr & 1u) != 0u) {
        m = ((m & vec2<u32>(0x55555555u)) << vec2<u32>(1u)) | ((m >> vec2<u32>(1u)) & vec2<u32>(0x55555555u));
    }
    if ((rr & 2u) != 0u) {
        m = ((m & vec2<u32>(0x33333333u)) << vec2<u32>(2u)) | ((m >> vec2<u32>(2u)) & vec2<u32>(0x33333333u));
    }
    if ((rr & 4u) != 0u) {
        m = ((m & vec2<u32>(0x0f0f0f0fu)) << vec2<u32>(4u)) | ((m >> vec2<u32>(4u)) & vec2<u32>(0x0f0f0f0fu));
    }
    if ((rr & 8u) != 0u) {
        m = ((m & vec2<u32>(0x00ff00ffu)) << vec2<u32>(8u)) | ((m >> vec2<u32>(8u)) & vec2<u32>(0x00ff00ffu));
    }
    if ((rr & 16u) != 0u) {
        m = (m << vec2<u32>(16u)) | (m >> vec2<u32>(16u));
    }
    if ((rr & 32u) != 0u) {
        m = m.yx;
    }
    return m;
}

// What `path_node` found.
const PATH_FOUND: u32 = 0u;
const PATH_EMPTY: u32 = 1u;
const PATH_MALFORMED: u32 = 2u;

// The node (or leaf) of level `to` on the path of cell `cell` (file frame)
// of level `level`, `to` at most min(level, leaf_level), reached as
// `traverse` reaches it (the lit passes' neighbourhood lookups): `.x` its
// reference in level `to` (1.0 and 2.0 expanded: word offset of the node,
// or leaf index; 2.0 in place: byte offset of the record, or leaf index),
// `.y` its accumulated reflection (0 in 1.0), `.z` PATH_FOUND, PATH_EMPTY when a node on the way
// lacks the child, PATH_MALFORMED when a reference leaves its level.
fn path_node(cell: vec3<u32>, level: u32, to: u32) -> vec3<u32> {
    var pointer = 0u;
    var r = 0u;
    for (var l = 0u; l < to; l += 1u) {
        let c = path_child(cell, level - 1u - l);
        var next = 0u;
        if (V2_IN_PLACE) {
            let codes = codes2(l, pointer);
            let slot = c ^ r;
            if ((codes.header & (1u << slot)) == 0u) {
                return vec3<u32>(0u, 0u, PATH_EMPTY);
            }
            let ch = child2(l, pointer, codes, slot);
            next = ch.x;
            r ^= ch.y;
        } else {
            let a = params.levels[l].x + pointer;
            let mask = node_mask(a);
            let slot = c ^ r;
            if ((mask & (1u << slot)) == 0u) {
                return vec3<u32>(0u, 0u, PATH_EMPTY);
            }
            let ch = child_entry(a, l, mask, slot);
            next = ch.x;
            r ^= ch.y;
        }
        if (next >= params.levels[l + 1u].z) {
            return vec3<u32>(0u, 0u, PATH_MALFORMED);
        }
        pointer = next;
    }
    return vec3<u32>(pointer, r, PATH_FOUND);
}

struct BrickHit {
    hit: bool,
    cell: vec3<u32>,
}

// The first set sub-brick (level D-1) or voxel (level D) of the 4^3 brick at
// word address `leaf`, at mirrored brick coordinates `idx`, the stored mask
// seen by a ray of octant `neg` (`p.neg`, XOR the leaf's reflection in 2.0).
fn brick(p: Prepared, leaf: u32, idx: vec3<u32>, neg: u32) -> BrickHit {
    var r: BrickHit;
    r.hit = false;
    let bits = leaf_mask(leaf);
    let w0 = bits.x;
    let w1 = bits.y;
    let lo = vec3<f32>(idx) * 4.0;
    let t0 = (lo - p.o) * p.inv;
    let t1 = (lo + vec3<f32>(1.0) - p.o) * p.inv;
    let t2 = (lo + vec3<f32>(2.0) - p.o) * p.inv;
    let t3 = (lo + vec3<f32>(3.0) - p.o) * p.inv;
    let t4 = (lo + vec3<f32>(4.0) - p.o) * p.inv;
    let te = max(max3(t0), p.tmin);
    let tx = min(min3(t4), p.tmax);
    if (te > tx) {
        return r;
    }
    let subs = byte_flags(w0) | (byte_flags(w1) << 4u);
    var remaining = chain(te, tx, t2) & mirror_mask(subs, neg);
    loop {
        if (remaining == 0u) {
            break;
        }
        let m = countTrailingZeros(remaining);
        remaining &= remaining - 1u;
        let sub = m ^ neg;
        let up = axis_bits(m);
        let sub_idx = idx * 2u + up;
        if (p.level < params.depth) {
            r.hit = true;
            r.cell = sub_idx;
            return r;
        }
        let upper = up != vec3<u32>(0u);
        let s_lo = select(t0, t2, upper);
        let s_mid = select(t1, t3, upper);
        let s_hi = select(t2, t4, upper);
        let se = max(max3(s_lo), p.tmin);
        let sx = min(min3(s_hi), p.tmax);
        if (se > sx) {
            continue;
        }
        let word = select(w0, w1, sub >= 4u);
        let voxels = (word >> (8u * (sub & 3u))) & 0xffu;
        let chain_voxels = chain(se, sx, s_mid) & mirror_mask(voxels, neg);
        if (chain_voxels != 0u) {
            r.hit = true;
            r.cell = sub_idx * 2u + axis_bits(countTrailingZeros(chain_voxels));
            return r;
        }
    }
    return r;
}

// Bits of the path of mirrored cell `path` at coordinate bit `shift`, as a child index.
fn path_child(path: vec3<u32>, shift: u32) -> u32 {
    let b = (path >> vec3<u32>(shift)) & vec3<u32>(1u);
    return b.x | (b.y << 1u) | (b.z << 2u);
}

// The front-to-back traversal: the first occupied cell at level p.level.
fn traverse(p: Prepared) -> Found {
    var f: Found;
    f.hit = false;
    f.status = 0u;
    f.iterations = 0u;
    let depth = params.depth;
    let leaf_level = params.leaf_level;
    if (leaf_level == 0u) {
        let b = brick(p, params.levels[0].x, vec3<u32>(0u), p.neg);
        f.hit = b.hit;
        f.cell = b.cell;
        f.level = p.level;
        f.iterations = 1u;
        return f;
    }
    var stack: array<vec2<u32>, STACK_SIZE>;
    // 2.0 in place: the codes of each frame's node, `pack_codes2` (unused,
    // and compiled out, in 1.0 and 2.0 expanded).
    var codes_stack: array<vec3<u32>, STACK_SIZE>;
    var level = 0u;
    var idx = vec3<u32>(0u);
    // The node to enter: word address (2.0 in place: byte offset in its level).
    var addr = select(params.levels[0].x, 0u, V2_IN_PLACE);
    // 2.0: accumulated reflection of the current frame (0 in 1.0).
    var refl = 0u;
    var enter = true;
    // Short stack: the level whose entry is being rebuilt, the cell whose
    // path is replayed, and the lowest level whose entry is still valid.
    var replay_to = NO_REPLAY;
    var path = vec3<u32>(0u);
    var bottom = 0u;
    var iterations = 0u;
    loop {
        iterations += 1u;
        if (iterations > params.max_iterations) {
            f.status = INFO_EXHAUSTED;
            break;
        }
        var node = 0u;
        var mask = 0u;
        var remaining = 0u;
        var forced = false;
        var j = 0u;
        if (enter) {
            enter = false;
            node = addr;
            if (V2_IN_PLACE) {
                let c = codes2(level, addr);
                codes_stack[level & STACK_MASK] = pack_codes2(c);
                mask = c.header & 0xffu;
            } else {
                mask = node_mask(addr);
            }
            let size = f32(1u << (depth - level));
            let lo = vec3<f32>(idx) * size;
            let t_lo = (lo - p.o) * p.inv;
            let t_mid = (lo + vec3<f32>(size * 0.5) - p.o) * p.inv;
            let t_hi = (lo + vec3<f32>(size) - p.o) * p.inv;
            let te = max(max3(t_lo), p.tmin);
            let tx = min(min3(t_hi), p.tmax);
            if (te <= tx) {
                remaining = chain(te, tx, t_mid) & mirror_mask(mask, p.neg ^ refl);
            }
            if (SHORT_STACK) {
                if (level >= bottom + STACK_SIZE) {
                    bottom = level + 1u - STACK_SIZE;
                }
                if (replay_to != NO_REPLAY) {
                    // Children up to the one on the path are done (or, above
                    // the target level, being descended into).
                    j = path_child(path, replay_to - level);
                    remaining &= ~((2u << j) - 1u);
                    if (level == replay_to) {
                        replay_to = NO_REPLAY;
                    } else {
                        forced = true;
                    }
                }
            }
            stack[level & STACK_MASK] = vec2<u32>(node, mask | (remaining << 8u) | (refl << 16u));
        } else {
            let e = stack[level & STACK_MASK];
            node = e.x;
            mask = e.y & 0xffu;
            remaining = e.y >> 8u;
            if (FORMAT_V2) {
                remaining &= 0xffu;
                refl = e.y >> 16u;
            }
        }
        if (!forced) {
            if (remaining == 0u) {
                if (level == 0u) {
                    break;
                }
                if (SHORT_STACK && level - 1u < bottom) {
                    replay_to = level - 1u;
                    path = idx;
                    level = 0u;
                    idx = vec3<u32>(0u);
                    addr = select(params.levels[0].x, 0u, V2_IN_PLACE);
                    refl = 0u;
                    bottom = 0u;
                    enter = true;
                    continue;
                }
                level -= 1u;
                idx = idx >> vec3<u32>(1u);
                continue;
            }
            j = countTrailingZeros(remaining);
            remaining &= remaining - 1u;
            stack[level & STACK_MASK].y = mask | (remaining << 8u) | (refl << 16u);
        }
        let child_idx = idx * 2u + axis_bits(j);
        let child_level = level + 1u;
        if (child_level == p.level) {
            f.hit = true;
            f.cell = child_idx;
            f.level = child_level;
            break;
        }
        let child_info = params.levels[child_level];
        var pointer = 0u;
        var child_refl = 0u;
        if (V2_IN_PLACE) {
            let codes = unpack_codes2(mask, codes_stack[level & STACK_MASK]);
            let ch = child2(level, node, codes, j ^ p.neg ^ refl);
            pointer = ch.x;
            child_refl = refl ^ ch.y;
        } else {
            // 1.0, and 2.0 expanded (refl is 0 in 1.0).
            let ch = child_entry(node, level, mask, j ^ p.neg ^ refl);
            pointer = ch.x;
            child_refl = refl ^ ch.y;
        }
        if (pointer >= child_info.z) {
            f.status = INFO_MALFORMED;
            break;
        }
        if (child_level == leaf_level) {
            let b = brick(p, child_info.x + 2u * pointer, child_idx, p.neg ^ child_refl);
            if (b.hit) {
                f.hit = true;
                f.cell = b.cell;
                f.level = p.level;
                break;
            }
            continue;
        }
        level = child_level;
        idx = child_idx;
        addr = select(child_info.x + pointer, pointer, V2_IN_PLACE);
        refl = child_refl;
        enter = true;
    }
    f.iterations = iterations;
    return f;
}

// 64-bit addition on (low, high) pairs.
fn add64(a: vec2<u32>, b: vec2<u32>) -> vec2<u32> {
    let lo = a.x + b.x;
    return vec2<u32>(lo, a.y + b.y + select(0u, 1u, lo < a.x));
}

// Voxel count of a saturated node (word address `a`) from the host's table.
fn saturated_count(a: u32) -> vec2<u32> {
    var lo = 0u;
    var hi = params.sat_count;
    loop {
        if (lo >= hi) {
            break;
        }
        let mid = (lo + hi) / 2u;
        if (load_word(params.sat_base + 3u * mid) < a) {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    let at = params.sat_base + 3u * lo;
    if (lo < params.sat_count && load_word(at) == a) {
        return vec2<u32>(load_word(at + 1u), load_word(at + 2u));
    }
    return vec2<u32>(0u);
}

// Voxel count of the child at `pointer` of level `level`.
fn subtree_count(level: u32, pointer: u32) -> vec2<u32> {
    let info = params.levels[level];
    if (level == params.leaf_level) {
        let bits = leaf_mask(info.x + 2u * pointer);
        return vec2<u32>(countOneBits(bits.x) + countOneBits(bits.y), 0u);
    }
    let a = info.x + pointer;
    let count = node_attribute(a);
    if (count == COUNT_SATURATED) {
        return saturated_count(a);
    }
    return vec2<u32>(count, 0u);
}

// Child index (file frame) of the path of `cell` taken at coordinate bit `shift`.
fn child_at(cell: vec3<u32>, shift: u32) -> u32 {
    return path_child(cell, shift);
}

// Voxel count of the child at byte offset (leaf index) `dest` of 2.0 level
// `level`; a saturated record's count is in the host's table under the word
// of its first byte (records are at least 5 bytes: one starts per word).
fn subtree_count2(level: u32, dest: u32) -> vec2<u32> {
    let info = params.levels[level];
    if (level == params.leaf_level) {
        let bits = leaf_mask(info.x + 2u * dest);
        return vec2<u32>(countOneBits(bits.x) + countOneBits(bits.y), 0u);
    }
    let count = codes2(level, dest).header >> CHILD_MASK_BITS;
    if (count == COUNT_SATURATED) {
        return saturated_count(info.x + (dest >> 2u));
    }
    return vec2<u32>(count, 0u);
}

// `dense_index` of a 2.0 DAG read in place (spec §23.5): with the accumulated reflection
// R, logical child c is at physical slot c ^ R, the earlier siblings are the
// set slots p with (p ^ R) < c, and the leaf's bits are counted in its mask
// reflected by R.
fn dense_index2(cell: vec3<u32>, level: u32) -> vec2<u32> {
    var index = vec2<u32>(0u);
    var off = 0u;
    var r = 0u;
    let leaf_level = params.leaf_level;
    let interior = min(level, leaf_level);
    for (var l = 0u; l < interior; l += 1u) {
        let codes = codes2(l, off);
        let mask = codes.header & 0xffu;
        let c = child_at(cell, level - 1u - l);
        for (var s = 0u; s < 8u; s += 1u) {
            if ((mask & (1u << s)) != 0u && (s ^ r) < c) {
                index = add64(index, subtree_count2(l + 1u, child2(l, off, codes, s).x));
            }
        }
        let ch = child2(l, off, codes, c ^ r);
        off = ch.x;
        r ^= ch.y;
    }
    if (level > leaf_level) {
        let bits = reflect_leaf(leaf_mask(params.levels[leaf_level].x + 2u * off), r);
        index = add64(index, vec2<u32>(leaf_rank(bits, cell, level), 0u));
    }
    return index;
}

// Set bits of the (logical) leaf mask `bits` before the first voxel of cell
// `cell` of level `level` (D - 1 or D).
fn leaf_rank(bits: vec2<u32>, cell: vec3<u32>, level: u32) -> u32 {
    var below: u32;
    if (level == params.depth) {
        let hi = child_at(cell & vec3<u32>(2u), 1u);
        let lo = child_at(cell & vec3<u32>(1u), 0u);
        below = hi * 8u + lo;
    } else {
        below = 8u * child_at(cell, 0u);
    }
    if (below < 32u) {
        return countOneBits(bits.x & ((1u << below) - 1u));
    }
    return countOneBits(bits.x) + countOneBits(bits.y & ((1u << (below - 32u)) - 1u));
}

// The dense index of the first voxel of cell `cell` (file frame) of level
// `level`: the counts of the earlier siblings on every level of its path plus
// the set bits before it in its leaf. 2.0 expanded (spec §23.5): with the
// accumulated reflection R, logical child c is at physical slot c ^ R, the
// earlier siblings are the set slots p with (p ^ R) < c, and the leaf's
// bits are counted in its mask reflected by R (R is 0 in 1.0).
fn dense_index(cell: vec3<u32>, level: u32) -> vec2<u32> {
    if (V2_IN_PLACE) {
        return dense_index2(cell, level);
    }
    var index = vec2<u32>(0u);
    var addr = params.levels[0].x;
    var r = 0u;
    let leaf_level = params.leaf_level;
    let interior = min(level, leaf_level);
    for (var l = 0u; l < interior; l += 1u) {
        let mask = node_mask(addr);
        let c = child_at(cell, level - 1u - l);
        // 1.0: the slots below c; 2.0: any slot may hold a logical sibling before it.
        let slots = select(c, 8u, FORMAT_V2);
        for (var s = 0u; s < slots; s += 1u) {
            if ((mask & (1u << s)) != 0u && (s ^ r) < c) {
                index = add64(index, subtree_count(l + 1u, child_entry(addr, l, mask, s).x));
            }
        }
        let ch = child_entry(addr, l, mask, c ^ r);
        r ^= ch.y;
        let child = params.levels[l + 1u];
        addr = child.x + select(ch.x, 2u * ch.x, l + 1u == leaf_level);
    }
    if (level > leaf_level) {
        var bits = leaf_mask(addr);
        if (FORMAT_V2) {
            bits = reflect_leaf(bits, r);
        }
        index = add64(index, vec2<u32>(leaf_rank(bits, cell, level), 0u));
    }
    return index;
}

// File-frame coordinates of a mirrored cell of `level`.
fn unmirror(cell: vec3<u32>, level: u32, neg: u32) -> vec3<u32> {
    let last = vec3<u32>((1u << level) - 1u);
    return select(cell, last - cell, axis_bits(neg) != vec3<u32>(0u));
}

fn miss_record() -> GpuHit {
    var h: GpuHit;
    h.cell = vec4<u32>(0u);
    h.t = 0.0;
    h.index_lo = 0u;
    h.index_hi = 0u;
    h.iterations = 0u;
    return h;
}

// The record of a traversal's outcome (t and face left for the caller).
fn hit_record(f: Found, neg: u32) -> GpuHit {
    var h = miss_record();
    h.iterations = f.iterations;
    if (f.hit) {
        let cell = unmirror(f.cell, f.level, neg);
        var info = INFO_HIT | (f.level << INFO_LEVEL_SHIFT);
        if ((params.options & OPTION_INDEX) != 0u) {
            let index = dense_index(cell, f.level);
            h.index_lo = index.x;
            h.index_hi = index.y;
        }
        h.cell = vec4<u32>(cell, info);
    } else {
        h.cell.w = f.status;
    }
    return h;
}

// The batch entry point, `trace_batch`, is in batch.wgsl (appended after this file).

// Entry parameter (in the prepared ray's units) and face of cell `cell`
// (mirrored) of `level`, in f32.
fn entry_face(p: Prepared, cell: vec3<u32>, level: u32) -> vec2<f32> {
    let size = f32(1u << (params.depth - level));
    let t_lo = (vec3<f32>(cell) * size - p.o) * p.inv;
    let near = max3(t_lo);
    var axis = 0u;
    if (t_lo.y > t_lo[axis]) {
        axis = 1u;
    }
    if (t_lo.z > t_lo[axis]) {
        axis = 2u;
    }
    var face = FACE_INSIDE;
    if (near >= p.tmin) {
        face = 1u + 2u * axis + ((p.neg >> axis) & 1u);
    }
    return vec2<f32>(max(near, p.tmin), f32(face));
}

// Shading of the CPU renderer's `Shade::Normal`.
fn shade(face: u32) -> u32 {
    var n = vec3<f32>(0.0);
    var base = vec3<f32>(0.8);
    var diffuse = 0.6;
    if (face != FACE_INSIDE) {
        let axis = (face - 1u) / 2u;
        let sign = select(-1.0, 1.0, (face & 1u) == 0u);
        n[axis] = sign;
        base = vec3<f32>(0.55) + 0.4 * n;
        diffuse = max(dot(n, vec3<f32>(0.48, 0.72, 0.5)), 0.0);
    }
    let k = 0.35 + 0.65 * diffuse;
    let rgb = vec3<u32>(clamp(base * k, vec3<f32>(0.0), vec3<f32>(1.0)) * 255.0 + 0.5);
    return rgb.x | (rgb.y << 8u) | (rgb.z << 16u) | (255u << 24u);
}

const BACKGROUND: u32 = 24u | (26u << 8u) | (32u << 16u) | (255u << 24u);

@compute @workgroup_size(RENDER_TILE, RENDER_TILE)
fn render_primary(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= params.width || gid.y >= params.height) {
        return;
    }
    let pixel = gid.y * params.width + gid.x;
    let u = ((f32(gid.x) + 0.5) / f32(params.width) * 2.0 - 1.0);
    let v = (1.0 - (f32(gid.y) + 0.5) / f32(params.height) * 2.0);
    let d = normalize(params.cam_forward.xyz + u * params.cam_right.xyz + v * params.cam_up.xyz);
    let res = f32(1u << params.depth);
    let negative = d < vec3<f32>(0.0);
    let neg = select(0u, 1u, negative.x) | select(0u, 2u, negative.y) | select(0u, 4u, negative.z);
    var p: Prepared;
    p.o = select(params.cam_origin.xyz, vec3<f32>(res) - params.cam_origin.xyz, negative);
    let a = abs(d);
    let tiny = a < vec3<f32>(max3(a) * (1.0 / TINY_DIRECTION_INVERSE));
    p.inv = select(vec3<f32>(1.0) / max(a, vec3<f32>(1.0e-30)), vec3<f32>(TINY_DIRECTION_INVERSE), tiny);
    p.neg = neg;
    p.level = params.render_level;
    let enter = max(max3((vec3<f32>(0.0) - p.o) * p.inv), 0.0);
    let exit = min(min3((vec3<f32>(res) - p.o) * p.inv), RENDER_FAR);
    p.tmin = enter;
    p.tmax = exit;
    var h = miss_record();
    var color = BACKGROUND;
    if (params.empty == 0u && enter <= exit) {
        let f = traverse(p);
        h = hit_record(f, neg);
        if (f.hit) {
            // The camera ray starts at t = 0, not at the cube.
            p.tmin = 0.0;
            let tf = entry_face(p, f.cell, f.level);
            let face = u32(tf.y);
            h.t = tf.x * params.cam_origin.w;
            h.cell.w |= face << INFO_FACE_SHIFT;
            color = shade(face);
        }
    }
    if ((params.options & OPTION_WRITE_HITS) != 0u) {
        hits[pixel] = h;
    }
    if ((params.options & OPTION_WRITE_IMAGE) != 0u) {
        image[pixel] = color;
    }
}
