// The colour pass: the colour of each record's voxel, looked up by its
// attribute index (the dense voxel index, spec §12.3) in the file's colour
// section, which the GPU holds as it is in the file: VOXEL_COLORS (§12.5)
// read as one word per colour, PACKED_COLORS (§12.6) decoded here from its
// compressed bytes. `dagfmt::packed_colors` is the reference; the device
// check (`color_check.rs`) compares the two bit for bit.
//
// The section starts at a multiple of 8 in the file (§6), so its byte `b` is
// byte `b & 3` of word `b >> 2`. Blocks and directory entries start at any
// byte: every field is read as a bit run from a byte address, from at most
// two words.

// `n` <= 32 bits, least significant first, from bit `bit` after byte `byte`
// of the section.
fn color_bits(byte: u32, bit: u32, n: u32) -> u32 {
    if (n == 0u) {
        return 0u;
    }
    let b = byte + (bit >> 3u);
    let shift = ((b & 3u) << 3u) + (bit & 7u);
    let w = b >> 2u;
    var v = color_word(w) >> shift;
    if (shift != 0u && shift + n > 32u) {
        v = v | (color_word(w + 1u) << (32u - shift));
    }
    if (n < 32u) {
        v = v & ((1u << n) - 1u);
    }
    return v;
}

fn color_byte(at: u32) -> u32 {
    return color_bits(at, 0u, 8u);
}

// A packed block's header (dagfmt's `BlockHeader`).
struct ColorBlock {
    // Palette size, or 0 for a direct block.
    palette: u32,
    channels: u32,
    widths: vec4<u32>,
    base: vec4<u32>,
    uniform_mask: u32,
    split_flags: u32,
    // Bits of the stream before the entries (the split flags).
    lead: u32,
    // Byte offset of the bit stream.
    bits: u32,
}

// Byte offset in the section of block `b`, from the directory.
fn block_start(b: u32) -> u32 {
    let entry = cparams.directory + (b >> 4u) * 32u;
    // Bits 32..40 of the base offset are zero: the host refuses sections of
    // 4 GiB or more.
    let base = color_bits(entry, 0u, 32u);
    let j = b & 15u;
    if (j == 0u) {
        return base;
    }
    let o = cparams.offset_bits;
    return base + color_bits(entry, 40u + o * (j - 1u), o);
}

fn index_width(k: u32) -> u32 {
    if (k <= 1u) {
        return 0u;
    }
    return 32u - countLeadingZeros(k - 1u);
}

// Split flags of a palette block of `n` colours: one per sub-block that is
// not uniform.
fn split_flag_count(n: u32, uniform_mask: u32) -> u32 {
    let subs = (n + 7u) >> 3u;
    var valid = 0xffffffffu;
    if (subs < 32u) {
        valid = (1u << subs) - 1u;
    }
    return subs - countOneBits(uniform_mask & valid);
}

// The header of block `b`, of `n` colours.
fn block_header(b: u32, n: u32) -> ColorBlock {
    var h: ColorBlock;
    let start = block_start(b);
    let h0 = color_byte(start);
    let direct = (h0 & 0x80u) != 0u;
    let alpha = (h0 & 0x40u) != 0u;
    let k = (h0 & 0x3fu) + 1u;
    var at = start + 1u;
    h.widths = vec4<u32>(0u);
    if (direct || k > 1u) {
        let w = color_bits(at, 0u, 16u);
        h.widths = min(vec4<u32>(w & 15u, (w >> 4u) & 15u, (w >> 8u) & 15u, (w >> 12u) & 15u), vec4<u32>(8u));
        if (!alpha) {
            h.widths.w = 0u;
        }
        at = at + 2u;
    }
    h.channels = select(3u, 4u, alpha);
    let base = color_bits(at, 0u, 8u * h.channels);
    h.base = vec4<u32>(base & 255u, (base >> 8u) & 255u, (base >> 16u) & 255u, base >> 24u);
    at = at + h.channels;
    h.uniform_mask = 0u;
    h.split_flags = 0u;
    h.lead = 0u;
    if (!direct && k > 1u) {
        // 2^S / 64 bytes of the uniform mask.
        let mask_bytes = 1u << (cparams.block_shift - 6u);
        h.uniform_mask = color_bits(at, 0u, 8u * mask_bytes);
        at = at + mask_bytes;
        if (cparams.split != 0u) {
            h.lead = split_flag_count(n, h.uniform_mask);
            h.split_flags = color_bits(at, 0u, h.lead);
        }
    }
    h.palette = select(k, 0u, direct);
    h.bits = at;
    return h;
}

// Colour `local` of a block with header `h`, as RGBA8 (R in the low byte).
fn block_color(h: ColorBlock, local: u32) -> u32 {
    let eb = h.widths.x + h.widths.y + h.widths.z + h.widths.w;
    var entry = local;
    if (h.palette == 1u) {
        entry = 0u;
    } else if (h.palette > 1u) {
        let w = index_width(h.palette);
        let t = local >> 3u;
        let uniforms = countOneBits(h.uniform_mask & ((1u << t) - 1u));
        // Sub-block t's split flag is the one after those of the sub-blocks
        // before it that are not uniform.
        let rank = t - uniforms;
        let splits = countOneBits(h.split_flags & ((1u << rank) - 1u));
        let full = rank - splits;
        let pos = h.lead + h.palette * eb + uniforms * w + splits * (2u * w + 3u) + full * 8u * w;
        let at = local & 7u;
        var slot = at;
        if (((h.uniform_mask >> t) & 1u) == 1u) {
            slot = 0u;
        } else if (((h.split_flags >> rank) & 1u) == 1u) {
            let p = color_bits(h.bits, pos + 2u * w, 3u);
            slot = select(0u, 1u, at >= p);
        }
        entry = color_bits(h.bits, pos + slot * w, w);
    }
    let e = cparams.error_bound;
    let step = 2u * e + 1u;
    var pos = h.lead + entry * eb;
    var rgba = 0xff000000u;
    for (var c = 0u; c < h.channels; c = c + 1u) {
        let q = color_bits(h.bits, pos, h.widths[c]);
        pos = pos + h.widths[c];
        let v = min(255u, h.base[c] + q * step + e);
        rgba = (rgba & ~(255u << (8u * c))) | (v << (8u * c));
    }
    return rgba;
}

// The colour of the voxel with dense index `index` (high word `index_hi`):
// x = RGBA8, y = 1 when the section has one.
fn voxel_color(index: u32, index_hi: u32) -> vec2<u32> {
    if (index_hi != 0u || index >= cparams.colors) {
        return vec2<u32>(0u, 0u);
    }
    if (!COLORS_PACKED) {
        return vec2<u32>(color_word(index), 1u);
    }
    let s = cparams.block_shift;
    let b = index >> s;
    let size = 1u << s;
    let n = min(cparams.colors - b * size, size);
    let h = block_header(b, n);
    return vec2<u32>(block_color(h, index & (size - 1u)), 1u);
}

@compute @workgroup_size(COLOR_WORKGROUP_SIZE)
fn record_colors(
    @builtin(global_invocation_id) gid: vec3<u32>,
) {
    let i = gid.x + gid.y * (COLOR_DISPATCH_ROW * COLOR_WORKGROUP_SIZE);
    if (i >= cparams.count) {
        return;
    }
    let r = i * cparams.stride;
    var found = vec2<u32>(0u, 0u);
    let info = records[r + cparams.info_word];
    if ((info & cparams.info_mask) == cparams.info_mask) {
        found = voxel_color(records[r + cparams.index_word], records[r + cparams.index_word + 1u]);
    }
    colors_out[2u * i] = found.x;
    colors_out[2u * i + 1u] = found.y;
}
