//! The WGSL colour decoder against dagfmt's (`dagfmt::packed_colors`): the
//! colour pass (`colors.wgsl`) decodes every colour of PACKED_COLORS
//! sections made by dagfmt's encoder — lossless and lossy, block shifts 6, 7
//! and 8, with and without split sub-blocks, from random and structured
//! colour streams, so that palette, direct, alpha, uniform and split
//! sub-blocks all occur — and must give what `PackedColors::get` gives, bit
//! for bit; raw VOXEL_COLORS sections too. Each section is also spread over
//! several storage bindings, so that the page choice of `color_word` is
//! checked, and indices past the end must find no colour.
//!
//! Without an adapter the test prints that it was skipped (a failure with
//! `VDAG_REQUIRE_GPU=1`), like the other device checks.

use dagfmt::ColorTable;
use dagfmt::packed_colors::{BlockLayout, PackedColors, encode_with_layout};
use wgpu::util::DeviceExt as _;

use super::colors::{GpuColors, RecordShape, unpack};
use super::{AdapterChoice, GpuContext, GpuError};
use crate::testing::Rng;

/// The shared context, or `None` (after saying so) when there is no adapter.
fn context() -> Option<GpuContext> {
    match GpuContext::new(AdapterChoice::Default) {
        Ok(c) => Some(c),
        Err(e) => {
            if std::env::var("VDAG_REQUIRE_GPU").is_ok_and(|v| v == "1") {
                panic!("VDAG_REQUIRE_GPU=1 but no GPU adapter: {e}");
            }
            println!("skipped: no GPU adapter (set VDAG_REQUIRE_GPU=1 to make this an error): {e}");
            None
        }
    }
}

fn random(rng: &mut Rng) -> [u8; 4] {
    [0; 4].map(|_| rng.next() as u8)
}

/// Colour streams of `n` colours: what textures, point clouds and
/// translucent data give.
fn streams(n: usize, rng: &mut Rng) -> Vec<(&'static str, Vec<[u8; 4]>)> {
    let noise: Vec<[u8; 4]> = (0..n)
        .map(|_| {
            let c = random(rng);
            [c[0], c[1], c[2], 255]
        })
        .collect();
    let translucent: Vec<[u8; 4]> = (0..n).map(|_| random(rng)).collect();
    // Runs of a few colours (a magnified texture along the Morton order),
    // some translucent, with stretches of noise between.
    let mut runs = Vec::with_capacity(n);
    let mut palette: Vec<[u8; 4]> = (0..3).map(|_| random(rng)).collect();
    while runs.len() < n {
        let r = rng.next();
        let len = 1 + (r % 23) as usize;
        match r >> 60 {
            0 => palette = (0..1 + (r >> 8) % 5).map(|_| random(rng)).collect(),
            1 => runs.extend((0..len).map(|_| random(rng))),
            2..=4 => runs.extend(std::iter::repeat_n(palette[0], len * 8)),
            _ => {
                let c = palette[(r >> 20) as usize % palette.len()];
                let a = if r >> 40 & 7 == 0 {
                    (r >> 48) as u8
                } else {
                    255
                };
                runs.extend(std::iter::repeat_n([c[0], c[1], c[2], a], len));
            }
        }
    }
    runs.truncate(n);
    // Smooth gradients: wide palettes of close colours.
    let gradient: Vec<[u8; 4]> = (0..n)
        .map(|i| {
            let t = (i / 3) as u32;
            [
                (t % 251) as u8,
                (t / 7 % 256) as u8,
                (t * 3 % 256) as u8,
                255,
            ]
        })
        .collect();
    vec![
        ("noise", noise),
        ("translucent noise", translucent),
        ("runs", runs),
        ("gradient", gradient),
    ]
}

/// What kinds of blocks and sub-blocks a section holds (read from the
/// spec's layout, §12.6), to show that the check is not vacuous.
#[derive(Debug, Default)]
struct Kinds {
    direct: usize,
    palette1: usize,
    palette: usize,
    alpha: usize,
    split: usize,
}

fn kinds(p: &PackedColors<'_>) -> Kinds {
    let s = p.bytes();
    let layout = p.trailer().layout;
    let directory = p.directory_offset();
    let bits = |at: usize, pos: usize, n: usize| -> u64 {
        (0..n).fold(0, |v, i| {
            let b = at * 8 + pos + i;
            v | u64::from(s[b / 8] >> (b % 8) & 1) << i
        })
    };
    let mut out = Kinds::default();
    let o = layout.offset_bits() as usize;
    for b in 0..p.block_count() as usize {
        let entry = directory + b / 16 * 32;
        let j = b % 16;
        let mut start = bits(entry, 0, 40) as usize;
        if j > 0 {
            start += bits(entry, 40 + o * (j - 1), o) as usize;
        }
        let h = s[start];
        let k = (h & 63) + 1;
        let alpha = h & 0x40 != 0;
        out.alpha += usize::from(alpha);
        if h & 0x80 != 0 {
            out.direct += 1;
        } else if k == 1 {
            out.palette1 += 1;
        } else {
            out.palette += 1;
            if layout.split {
                let n = (p.len() as usize - b * (1 << layout.shift)).min(1 << layout.shift);
                let subs = n.div_ceil(8);
                let mask_at = start + 3 + 3 + usize::from(alpha);
                let mask_bytes = 1 << (layout.shift - 6);
                let uniform = bits(mask_at, 0, 8 * mask_bytes) as u32;
                let flags = subs - (uniform & ((1u64 << subs) - 1) as u32).count_ones() as usize;
                out.split += bits(mask_at + mask_bytes, 0, flags).count_ones() as usize;
            }
        }
    }
    out
}

/// Decodes every index of `0 .. len + 40` (past the end too) on the device
/// from `table`, on one binding and, when the device has the bindings, on
/// several; returns the colours of each run.
fn device_colors(
    ctx: &GpuContext,
    table: ColorTable<'_>,
    len: u64,
    section_bytes: u64,
) -> Vec<(u32, Vec<Option<[u8; 4]>>)> {
    let indices: Vec<u32> = (0..len + 40)
        .flat_map(|i| [i as u32, (i >> 32) as u32])
        .chain([7, 1]) // an index of 2^32 + 7: past the end
        .collect();
    let count = (indices.len() / 2) as u32;
    let records = ctx
        .inner
        .device
        .create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("vdag colour check indices"),
            contents: bytemuck::cast_slice(&indices),
            usage: wgpu::BufferUsages::STORAGE,
        });
    let shape = RecordShape {
        stride: 2,
        info_word: 0,
        index_word: 0,
        info_mask: 0,
    };
    let mut out = Vec::new();
    for cap in [u64::MAX, (section_bytes / 2).max(64)] {
        let colors = match GpuColors::new(ctx, table, cap.min(ctx.max_binding_bytes())) {
            Ok(c) => c,
            // More pages than the device binds: the single binding is checked.
            Err(GpuError::TooLarge(_)) if cap != u64::MAX => continue,
            Err(e) => panic!("{e}"),
        };
        let words = colors
            .decode(ctx, &records, count, shape)
            .expect("the colour pass runs");
        out.push((colors.config.pages, unpack(&words)));
    }
    out
}

fn compare(name: &str, got: &[(u32, Vec<Option<[u8; 4]>>)], expected: &[Option<[u8; 4]>]) {
    for (pages, colors) in got {
        assert_eq!(colors.len(), expected.len(), "{name}");
        for (i, (g, e)) in colors.iter().zip(expected).enumerate() {
            assert_eq!(g, e, "{name} ({pages} bindings): colour {i}");
        }
    }
}

#[test]
fn wgsl_decodes_packed_colours_as_dagfmt_does() {
    let Some(ctx) = context() else { return };
    let mut rng = Rng(0xc0105);
    let mut total = Kinds::default();
    let mut decoded = 0usize;
    let mut paged = false;
    // Lengths that end inside a block, a sub-block and a group of blocks.
    for (n, e) in [(9_000usize, 0u8), (5_003, 8), (3_333, 1), (777, 127)] {
        for (stream, colors) in streams(n, &mut rng) {
            for layout in [
                BlockLayout::V1_1,
                BlockLayout::CHOICES[0],
                BlockLayout::CHOICES[1],
                BlockLayout::CHOICES[2],
            ] {
                let (bytes, summary) = encode_with_layout(&colors, e, layout).expect("encodes");
                assert_eq!(summary.trailer.layout, layout);
                let packed = PackedColors::new(&bytes, n as u64).expect("opens");
                let k = kinds(&packed);
                total.direct += k.direct;
                total.palette1 += k.palette1;
                total.palette += k.palette;
                total.alpha += k.alpha;
                total.split += k.split;
                let expected: Vec<Option<[u8; 4]>> = (0..n as u64 + 40)
                    .map(|i| packed.get(i))
                    .chain([None])
                    .collect();
                let got = device_colors(
                    &ctx,
                    ColorTable::Packed(packed),
                    n as u64,
                    bytes.len() as u64,
                );
                paged |= got.iter().any(|(pages, _)| *pages > 1);
                let name = format!("{stream}, {n} colours, E = {e}, {layout:?}");
                compare(&name, &got, &expected);
                decoded += n * got.len();
            }
        }
    }
    // Raw colours take the same path.
    let raw: Vec<u8> = streams(4_097, &mut rng)
        .into_iter()
        .flat_map(|(_, c)| c)
        .flatten()
        .collect();
    let table = ColorTable::Raw(&raw);
    let expected: Vec<Option<[u8; 4]>> = (0..table.len() + 40)
        .map(|i| table.get(i))
        .chain([None])
        .collect();
    let got = device_colors(&ctx, table, table.len(), raw.len() as u64);
    compare("raw", &got, &expected);
    println!("{decoded} colours decoded alike; blocks {total:?}; several bindings: {paged}");
    assert!(
        total.direct > 0
            && total.palette1 > 0
            && total.palette > 0
            && total.alpha > 0
            && total.split > 0,
        "not every kind of block was checked: {total:?}"
    );
    assert!(paged, "no section was spread over several bindings");
}
