//! Shading traced primary rays into an RGB image.

use rayon::prelude::*;

use crate::camera::CameraFrame;
use crate::walk::{TraceError, Tracer};
use dagfmt::ColorTable;
use dagfmt::batch::Hit;

/// How hit pixels are coloured.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shade {
    /// Colour by the entry face's normal, lit by a directional light.
    Normal,
    /// Grey level by distance: near is bright.
    Depth,
    /// The voxel's colour from the file's VOXEL_COLORS section, lit like
    /// [`Shade::Normal`]; a neutral grey when the file has no colours.
    Color,
}

/// Background colour of pixels whose ray hits nothing.
pub const BACKGROUND: [u8; 3] = [24, 26, 32];

/// Outward normal of an entry face (spec/VDAG.md numbering); face 0 (the ray
/// starts inside) has none.
pub fn face_normal(face: u8) -> Option<[f32; 3]> {
    Some(match face {
        1 => [-1.0, 0.0, 0.0],
        2 => [1.0, 0.0, 0.0],
        3 => [0.0, -1.0, 0.0],
        4 => [0.0, 1.0, 0.0],
        5 => [0.0, 0.0, -1.0],
        6 => [0.0, 0.0, 1.0],
        _ => return None,
    })
}

/// Renders a `width` x `height` image (RGB8, rows from the top) seen through
/// `camera`, tracing at `level` (`None` = full depth), on all cores.
pub fn render(
    tracer: &Tracer<'_>,
    camera: &CameraFrame,
    width: u32,
    height: u32,
    shade: Shade,
    level: Option<u8>,
) -> Result<Vec<u8>, TraceError> {
    // Rays in tiles, which the batch API traces as packets; hits back to rows.
    let (rays, pixels) = camera.rays_in_tiles(width, height, level);
    let colored = shade == Shade::Color && tracer.colors().is_some();
    let tracer = tracer.clone().with_index(colored);
    let tiled = tracer.trace_batch(&rays)?;
    let mut hits = vec![Hit::MISS; tiled.len()];
    for (hit, &pixel) in tiled.into_iter().zip(&pixels) {
        hits[pixel as usize] = hit;
    }
    Ok(shade_hits(&hits, shade, tracer.colors()))
}

/// Pixels shaded by one rayon task: a few rows, whose colour lookups share a
/// cursor.
const SHADE_CHUNK: usize = 4096;

/// Colours traced primary-ray hits (one per pixel, rows from the top) into
/// RGB8 pixels, on all cores. [`Shade::Color`] looks a voxel's stored colour
/// up by attribute index in `colors`, through a cursor per task that keeps
/// the last packed block's header (neighbouring pixels mostly fall in one
/// block, spec §12.6); hits without an index or colours get a neutral grey.
/// Shared by the CPU and GPU back ends so both produce the same image.
pub fn shade_hits(hits: &[Hit], shade: Shade, colors: Option<ColorTable<'_>>) -> Vec<u8> {
    shade_with(hits, shade, || {
        let mut cursor = colors.map(|table| table.cursor());
        move |_: usize, hit: &Hit| hit.index.and_then(|i| cursor.as_mut()?.get(i))
    })
}

/// [`shade_hits`] with each hit's colour given, `colors[k]` for `hits[k]`
/// (the GPU back end decodes them on the device: `GpuTracer::hit_colors`);
/// `None` (or a missing entry) gets the neutral grey. The same pixels as
/// [`shade_hits`] when the colours are the same.
pub fn shade_hits_colored(hits: &[Hit], shade: Shade, colors: &[Option<[u8; 4]>]) -> Vec<u8> {
    shade_with(hits, shade, || {
        |k: usize, _: &Hit| colors.get(k).copied().flatten()
    })
}

/// The shading of [`shade_hits`]: `lookup` makes, per task, the function
/// giving hit `k`'s stored colour.
fn shade_with<F, L>(hits: &[Hit], shade: Shade, lookup: L) -> Vec<u8>
where
    L: Fn() -> F + Sync,
    F: FnMut(usize, &Hit) -> Option<[u8; 4]>,
{
    let (near, far) = hits
        .iter()
        .filter(|h| h.hit && h.t.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(n, f), h| {
            (n.min(h.t), f.max(h.t))
        });
    let mut pixels = vec![0u8; hits.len() * 3];
    pixels
        .par_chunks_mut(SHADE_CHUNK * 3)
        .zip(hits.par_chunks(SHADE_CHUNK))
        .enumerate()
        .for_each(|(task, (out, hits))| {
            let mut color = lookup();
            for (j, (px, hit)) in out.chunks_exact_mut(3).zip(hits).enumerate() {
                let k = task * SHADE_CHUNK + j;
                px.copy_from_slice(&shade_hit(hit, shade, (near, far), || color(k, hit)));
            }
        });
    pixels
}

/// One pixel of [`shade_hits`]; `span` is the nearest and farthest finite
/// hit; `color` gives the hit voxel's stored colour (asked only for
/// [`Shade::Color`] hits).
fn shade_hit(
    hit: &Hit,
    shade: Shade,
    (near, far): (f32, f32),
    color: impl FnOnce() -> Option<[u8; 4]>,
) -> [u8; 3] {
    if !hit.hit {
        return BACKGROUND;
    }
    match shade {
        Shade::Depth => {
            let span = (far - near).max(f32::MIN_POSITIVE);
            let g = if hit.t.is_finite() {
                1.0 - 0.85 * (hit.t - near) / span
            } else {
                0.15
            };
            [to_u8(g); 3]
        }
        Shade::Normal => lit(normal_color(hit), hit),
        Shade::Color => {
            let base = color()
                .map(|c| [c[0], c[1], c[2]].map(|v| f32::from(v) / 255.0))
                .unwrap_or([0.75, 0.75, 0.72]);
            lit(base, hit)
        }
    }
}

/// Base colour from the face normal: each axis its own hue.
fn normal_color(hit: &Hit) -> [f32; 3] {
    match face_normal(hit.face) {
        Some(n) => n.map(|v| 0.55 + 0.4 * v),
        None => [0.8, 0.8, 0.8],
    }
}

/// Simple directional lighting with an ambient term.
fn lit(base: [f32; 3], hit: &Hit) -> [u8; 3] {
    let light = [0.48f32, 0.72, 0.5];
    let diffuse = face_normal(hit.face).map_or(0.6, |n| {
        (n[0] * light[0] + n[1] * light[1] + n[2] * light[2]).max(0.0)
    });
    let k = 0.35 + 0.65 * diffuse;
    base.map(|c| to_u8(c * k))
}

fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use dagfmt::builder::DagBuilder;
    use dagfmt::{AttributeKind, Dag};

    /// A ball at depth 6 with smoothly varying colours in runs (as textures
    /// give), raw or packed within `packed`.
    fn ball(packed: Option<u8>) -> Vec<u8> {
        let mut dag = DagBuilder::from_fn(6, AttributeKind::VoxelCount, |x, y, z| {
            let d = |c: u32| (f64::from(c) - 31.5).powi(2);
            d(x) + d(y) + d(z) < 900.0
        })
        .expect("ball builds");
        let colors: Vec<[u8; 4]> = (0..dag.voxel_count())
            .map(|i| {
                [
                    (i / 7 % 5 * 50) as u8,
                    (i / 300) as u8,
                    90 + (i % 2) as u8,
                    255,
                ]
            })
            .collect();
        match packed {
            None => dag.set_colors(colors).expect("colours attach"),
            Some(e) => {
                dag.set_packed_colors(&colors, e).expect("colours attach");
            }
        }
        dag.to_bytes()
    }

    fn picture(bytes: &[u8]) -> Vec<u8> {
        let dag = Dag::open(bytes).expect("opens");
        let tracer = Tracer::new(&dag).expect("traces");
        let frame = Camera::looking_at_box([0.0; 3], [1.0; 3], 1.0)
            .frame()
            .expect("camera");
        render(&tracer, &frame, 48, 48, Shade::Color, None).expect("renders")
    }

    #[test]
    fn packed_colours_render_like_raw_ones() {
        let raw = picture(&ball(None));
        assert_eq!(
            picture(&ball(Some(0))),
            raw,
            "lossless packing changed pixels"
        );
        let lossy = picture(&ball(Some(8)));
        // Lit colours scale the stored ones by at most 1, so a pixel moves by
        // at most E (plus rounding).
        let worst = raw.iter().zip(&lossy).map(|(a, b)| a.abs_diff(*b)).max();
        assert!(
            worst.is_some_and(|w| w <= 9),
            "worst channel difference {worst:?}"
        );
        // Not vacuous: the ball is in the picture, in more than one colour.
        let hit: std::collections::BTreeSet<_> =
            raw.chunks(3).filter(|p| *p != BACKGROUND).collect();
        assert!(hit.len() > 10, "{} distinct lit colours", hit.len());
    }
}
