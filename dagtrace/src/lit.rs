//! Lit rendering: a directional light with hard shadows, ambient occlusion,
//! shading normals estimated from the voxels around each hit, the file's
//! colours, and several samples per pixel.
//!
//! A render is three sets of rays, traced by the batch API:
//! 1. primary rays, `samples` per pixel (jittered inside the pixel);
//! 2. for every primary hit, one shadow ray towards the sun;
//! 3. and [`LitOptions::ao_rays`] ambient-occlusion rays in the hemisphere
//!    around the shading normal, of length [`LitOptions::ao_radius`].
//!
//! Each hit becomes a [`Surface`]; [`compose`] shades surfaces into pixels.
//! The GPU renderer (`dagtrace::gpu`, feature `gpu`) computes the same
//! surfaces with the same functions of this module ported to WGSL (integer
//! hashes, the same normal kernel), never sending rays back to the host, and
//! shares [`compose`], so that both back ends make the same image up to the
//! rare rays whose f32 set-up differs at exact ties.
//!
//! The shading normal of a hit cell is the sum of the offsets `d` to the
//! empty cells of its neighbourhood, `|d|² <= 6` (80 cells of a 5³ window:
//! [`crate::Tracer::occupancy_around`]): over a flat surface of any
//! orientation the occupied half cancels out and the sum points away from
//! it. The sums are integers, so both back ends find exactly the same
//! normal. A hit whose sum is zero or points behind the entry face (thin
//! sheets, single voxels) takes the entry face's normal.
//!
//! Secondary rays start [`START_OFFSET`] cells along the shading normal
//! from the point where the primary ray enters the hit cell: far enough
//! above a voxelized flat surface (whose steps lie within a cell of the
//! true surface) that the rays do not hit the steps of the surface they
//! leave, which would show as bands ("shadow acne").

use crate::camera::{CameraFrame, TILE};
use crate::render::BACKGROUND;
use crate::walk::{TraceError, Tracer};
use dagfmt::batch::{Hit, Ray};
use rayon::prelude::*;

/// How far from the hit cell's entry point secondary rays start, along the
/// shading normal, in cells of the traced level.
pub const START_OFFSET: f32 = 1.5;

/// Default direction towards the sun (world space; normalised when used):
/// high, from the left of the automatic camera ([`crate::camera::Camera::automatic`]).
pub const DEFAULT_SUN: [f64; 3] = [-0.35, 1.0, 0.45];

/// Default number of ambient-occlusion rays per sample.
pub const DEFAULT_AO_RAYS: u32 = 8;

/// The default ambient-occlusion radius is the grid's edge divided by this
/// (at least one cell): 128 voxels at depth 12, 32 at depth 10.
pub const DEFAULT_AO_RADIUS_DIVISOR: u32 = 32;

/// Most samples per pixel.
pub const MAX_SAMPLES: u32 = 64;

/// Most ambient-occlusion rays per sample.
pub const MAX_AO_RAYS: u32 = 64;

/// Albedo of voxels without a stored colour.
pub const DEFAULT_ALBEDO: [f32; 3] = [0.78, 0.76, 0.72];

/// Bit `(dx + 2) + 5 (dy + 2) + 25 (dz + 2)` of the kernel: the offsets of
/// the normal estimate, `0 < |d|² <= 6`.
pub fn kernel_contains(dx: i32, dy: i32, dz: i32) -> bool {
    let r2 = dx * dx + dy * dy + dz * dz;
    r2 > 0 && r2 <= 6
}

/// The settings of a lit render.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LitOptions {
    /// Direction towards the sun, world space (any length but zero).
    pub sun: [f64; 3],
    /// Ambient-occlusion rays per sample (0: no ambient occlusion).
    pub ao_rays: u32,
    /// Length of ambient-occlusion rays in cells of the traced level (the
    /// voxels at full depth); `None`: the grid's edge /
    /// [`DEFAULT_AO_RADIUS_DIVISOR`].
    pub ao_radius: Option<f64>,
    /// Primary rays per pixel (1: through its centre; more: spread over the
    /// pixel and averaged, for anti-aliasing).
    pub samples: u32,
}

impl Default for LitOptions {
    fn default() -> Self {
        LitOptions {
            sun: DEFAULT_SUN,
            ao_rays: DEFAULT_AO_RAYS,
            ao_radius: None,
            samples: 1,
        }
    }
}

/// Why lit options cannot work.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum LitError {
    /// The sun direction is zero or not finite.
    #[error("the sun direction must be a non-zero finite vector")]
    BadSun,
    /// Samples outside 1..=MAX_SAMPLES.
    #[error("{0} samples per pixel: must be 1 to {MAX_SAMPLES}")]
    BadSamples(u32),
    /// Too many AO rays.
    #[error("{0} ambient-occlusion rays: must be 0 to {MAX_AO_RAYS}")]
    BadAoRays(u32),
    /// The AO radius is not a positive finite number.
    #[error("ambient-occlusion radius {0}: must be a positive finite number of voxels")]
    BadAoRadius(f64),
}

impl LitOptions {
    /// Checks the options.
    pub fn check(&self) -> Result<(), LitError> {
        let len2: f64 = self.sun.iter().map(|v| v * v).sum();
        if !(len2.is_finite() && len2 > 0.0) {
            return Err(LitError::BadSun);
        }
        if !(1..=MAX_SAMPLES).contains(&self.samples) {
            return Err(LitError::BadSamples(self.samples));
        }
        if self.ao_rays > MAX_AO_RAYS {
            return Err(LitError::BadAoRays(self.ao_rays));
        }
        if let Some(r) = self.ao_radius
            && !(r.is_finite() && r > 0.0)
        {
            return Err(LitError::BadAoRadius(r));
        }
        Ok(())
    }

    /// The unit direction towards the sun, in f32.
    pub fn sun_unit(&self) -> [f32; 3] {
        let len = self.sun.iter().map(|v| v * v).sum::<f64>().sqrt();
        self.sun.map(|v| (v / len) as f32)
    }

    /// Ambient-occlusion radius in cells of `level`.
    pub fn ao_radius_cells(&self, level: u8) -> f64 {
        self.ao_radius.unwrap_or_else(|| {
            (f64::from(1u32 << level) / f64::from(DEFAULT_AO_RADIUS_DIVISOR)).max(1.0)
        })
    }
}

/// What one primary ray found, ready to shade.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Surface {
    /// Whether the primary ray hit.
    pub hit: bool,
    /// Entry face of the hit cell (0: the ray started inside it; such
    /// surfaces get no secondary rays and a flat shade).
    pub face: u8,
    /// Attribute index of the hit (for the colour), when computed.
    pub index: Option<u64>,
    /// Unit shading normal.
    pub normal: [f32; 3],
    /// Whether the shadow ray reached the sun.
    pub sun_visible: bool,
    /// Ambient-occlusion rays that met nothing.
    pub ao_open: u32,
}

impl Surface {
    /// A primary ray that met nothing.
    pub const MISS: Surface = Surface {
        hit: false,
        face: 0,
        index: None,
        normal: [0.0; 3],
        sun_visible: false,
        ao_open: 0,
    };
}

/// A 32-bit integer hash (Chris Wellons' `lowbias32`), the same in WGSL.
pub fn hash32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

/// A number in `[0, 1)` from the top 24 bits of `h` (exact in f32).
pub fn unit_from_hash(h: u32) -> f32 {
    (h >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// `x - floor(x)`.
fn fract(x: f32) -> f32 {
    x - x.floor()
}

/// Position inside the pixel (x right, y down, in `[0, 1)`) of sample
/// `sample` of `samples`: the centre for one sample, else the R2
/// low-discrepancy sequence.
pub fn sample_offset(sample: u32, samples: u32) -> [f32; 2] {
    if samples <= 1 {
        return [0.5, 0.5];
    }
    let s = sample as f32;
    [fract(0.5 + s * 0.754_877_7), fract(0.5 + s * 0.569_840_3)]
}

/// The seed of the ambient-occlusion directions of surface number `surface`
/// (`pixel * samples + sample`).
pub fn surface_seed(surface: u32) -> u32 {
    hash32(surface.wrapping_mul(0x9e37_79b9) ^ 0x632b_e5ab)
}

/// The shading normal from the occupancy of the 5³ window around the hit
/// cell ([`crate::Tracer::occupancy_around`]'s bit order), falling back to
/// the entry face's normal (see the module documentation).
pub fn normal_from_occupancy(occupancy: u128, face: u8) -> [f32; 3] {
    let mut sum = [0i32; 3];
    for dz in -2..=2i32 {
        for dy in -2..=2i32 {
            for dx in -2..=2i32 {
                let bit = (dx + 2) + 5 * (dy + 2) + 25 * (dz + 2);
                if kernel_contains(dx, dy, dz) && occupancy >> bit & 1 == 0 {
                    sum[0] += dx;
                    sum[1] += dy;
                    sum[2] += dz;
                }
            }
        }
    }
    normal_from_sum(sum, face)
}

/// [`normal_from_occupancy`] from the integer sum of the empty offsets.
pub fn normal_from_sum(sum: [i32; 3], face: u8) -> [f32; 3] {
    let f = crate::render::face_normal(face).unwrap_or([0.0; 3]);
    let v = sum.map(|c| c as f32);
    let along_face = v[0] * f[0] + v[1] * f[1] + v[2] * f[2];
    if along_face <= 0.0 {
        return f;
    }
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    v.map(|c| c / len)
}

/// Direction `k` of `count` ambient-occlusion rays around unit `normal`:
/// cosine-weighted, stratified in the polar angle and spread by the golden
/// ratio in azimuth, rotated per surface by `seed`.
pub fn ao_direction(normal: [f32; 3], seed: u32, k: u32, count: u32) -> [f32; 3] {
    let r1 = unit_from_hash(seed);
    let r2 = unit_from_hash(hash32(seed));
    let u1 = (k as f32 + r1) / count as f32;
    let u2 = fract(r2 + k as f32 * 0.618_034);
    let r = u1.sqrt();
    let phi = std::f32::consts::TAU * u2;
    let (x, y) = (r * phi.cos(), r * phi.sin());
    let z = (1.0 - u1).max(0.0).sqrt();
    let (t, b) = basis(normal);
    [0, 1, 2].map(|i| x * t[i] + y * b[i] + z * normal[i])
}

/// Two unit vectors that make an orthonormal basis with unit `n` (Duff et
/// al. 2017, "Building an orthonormal basis, revisited").
fn basis(n: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    let sign = if n[2] >= 0.0 { 1.0f32 } else { -1.0 };
    let a = -1.0 / (sign + n[2]);
    let b = n[0] * n[1] * a;
    (
        [1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]],
        [b, sign + n[1] * n[1] * a, -n[1]],
    )
}

/// The colour (linear RGB) of one surface seen under the sun `sun` (unit)
/// with `ao_rays` ambient-occlusion rays per surface; `albedo` from the
/// file's colours or [`DEFAULT_ALBEDO`].
pub fn shade(surface: &Surface, albedo: [f32; 3], sun: [f32; 3], ao_rays: u32) -> [f32; 3] {
    if surface.face == 0 {
        return albedo.map(|c| c * 0.3);
    }
    let n = surface.normal;
    let open = if ao_rays == 0 {
        1.0
    } else {
        surface.ao_open as f32 / ao_rays as f32
    };
    let cos = (n[0] * sun[0] + n[1] * sun[1] + n[2] * sun[2]).max(0.0);
    let direct = if surface.sun_visible { 0.75 * cos } else { 0.0 };
    // Sky light, a little brighter from above.
    let sky = 0.3 * open * (0.8 + 0.2 * n[1]);
    albedo.map(|c| c * (direct + sky))
}

/// Shades surfaces (`samples` per pixel, pixel after pixel, rows from the
/// top) into RGB8 pixels, averaging each pixel's samples (misses are the
/// background). `color` looks up a voxel's stored colour by attribute index.
/// Shared by the CPU and GPU back ends.
pub fn compose(
    surfaces: &[Surface],
    options: &LitOptions,
    color: impl Fn(u64) -> Option<[u8; 4]> + Sync,
) -> Vec<u8> {
    compose_with(surfaces, options, |_, s| s.index.and_then(&color))
}

/// [`compose`] with each surface's colour given by `color(k, surface)`, `k`
/// the surface's position in `surfaces` (the GPU back end decodes the
/// colours on the device, one per surface).
pub fn compose_with(
    surfaces: &[Surface],
    options: &LitOptions,
    color: impl Fn(usize, &Surface) -> Option<[u8; 4]> + Sync,
) -> Vec<u8> {
    let samples = options.samples.max(1) as usize;
    let sun = options.sun_unit();
    let background = BACKGROUND.map(|c| srgb_to_linear(f32::from(c) / 255.0));
    surfaces
        .par_chunks(samples)
        .enumerate()
        .flat_map_iter(|(p, pixel)| {
            if pixel.iter().all(|s| !s.hit) {
                return BACKGROUND;
            }
            let mut sum = [0f32; 3];
            for (j, s) in pixel.iter().enumerate() {
                let rgb = if s.hit {
                    let albedo = color(p * samples + j, s)
                        .map(|c| [c[0], c[1], c[2]].map(|v| srgb_to_linear(f32::from(v) / 255.0)))
                        .unwrap_or(DEFAULT_ALBEDO);
                    shade(s, albedo, sun, options.ao_rays)
                } else {
                    background
                };
                for i in 0..3 {
                    sum[i] += rgb[i];
                }
            }
            sum.map(|c| linear_to_srgb8(c / pixel.len() as f32))
        })
        .collect()
}

fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

fn linear_to_srgb8(c: f32) -> u8 {
    let c = c.clamp(0.0, 1.0);
    let s = if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5) as u8
}

/// The point (grid units) where secondary rays of a hit start: the entry
/// point of the primary ray (grid origin `origin`, direction `dir`, entry
/// parameter `t`) into cell `cell` of `level`, exactly on the entry face,
/// moved [`START_OFFSET`] cells along `normal`.
pub fn start_point(
    origin: [f64; 3],
    dir: [f64; 3],
    t: f64,
    cell: [u32; 3],
    cell_size: f64,
    face: u8,
    normal: [f32; 3],
) -> [f64; 3] {
    let mut p: [f64; 3] = std::array::from_fn(|i| {
        let lo = f64::from(cell[i]) * cell_size;
        (origin[i] + t * dir[i]).clamp(lo, lo + cell_size)
    });
    if let 1..=6 = face {
        let axis = usize::from((face - 1) / 2);
        let upper = face.is_multiple_of(2);
        p[axis] = (f64::from(cell[axis]) + if upper { 1.0 } else { 0.0 }) * cell_size;
    }
    std::array::from_fn(|i| p[i] + f64::from(normal[i]) * f64::from(START_OFFSET) * cell_size)
}

/// Rays (primary and secondary) a chunk of the CPU render traces together, at
/// most (but a whole tile at least), so that memory stays bounded whatever
/// the image size, samples and AO rays.
const CHUNK_RAYS: usize = 1 << 20;

/// Renders a lit `width` x `height` image (RGB8, rows from the top) seen
/// through `camera`, tracing at `level` (`None` = full depth), on all cores,
/// in chunks of tiles (bounded memory). Check the options first
/// ([`LitOptions::check`]): samples and AO rays beyond their maxima are
/// clamped here.
pub fn render_lit(
    tracer: &Tracer<'_>,
    camera: &CameraFrame,
    width: u32,
    height: u32,
    level: Option<u8>,
    options: &LitOptions,
) -> Result<Vec<u8>, TraceError> {
    let mut image = vec![0u8; width as usize * height as usize * 3];
    for_each_chunk(
        tracer,
        camera,
        (width, height, CHUNK_RAYS),
        level,
        options,
        |pixels, surfaces| {
            let rgb = compose(surfaces, options, |i| tracer.color(i));
            for (&pixel, rgb) in pixels.iter().zip(rgb.chunks_exact(3)) {
                let at = pixel as usize * 3;
                image[at..at + 3].copy_from_slice(rgb);
            }
        },
    )?;
    Ok(image)
}

/// The surfaces of a lit render ([`render_lit`] before [`compose`]):
/// `samples` per pixel, pixel after pixel, rows from the top. (The whole
/// image's surfaces at once: for tests and small images.)
pub fn trace_surfaces(
    tracer: &Tracer<'_>,
    camera: &CameraFrame,
    width: u32,
    height: u32,
    level: Option<u8>,
    options: &LitOptions,
) -> Result<Vec<Surface>, TraceError> {
    let samples = options.samples.clamp(1, MAX_SAMPLES) as usize;
    let mut out = vec![Surface::MISS; width as usize * height as usize * samples];
    for_each_chunk(
        tracer,
        camera,
        (width, height, CHUNK_RAYS),
        level,
        options,
        |pixels, surfaces| {
            for (&pixel, group) in pixels.iter().zip(surfaces.chunks_exact(samples)) {
                let at = pixel as usize * samples;
                out[at..at + samples].copy_from_slice(group);
            }
        },
    )?;
    Ok(out)
}

/// Traces the `width` x `height` image in chunks of whole tiles of at most
/// `chunk_rays` rays (but one tile) and hands each chunk's pixels (pixel
/// numbers `y * width + x`) with their surfaces (`samples` per pixel, in the
/// same order) to `each`.
fn for_each_chunk(
    tracer: &Tracer<'_>,
    camera: &CameraFrame,
    (width, height, chunk_rays): (u32, u32, usize),
    level: Option<u8>,
    options: &LitOptions,
    mut each: impl FnMut(&[u32], &[Surface]),
) -> Result<(), TraceError> {
    let options = LitOptions {
        samples: options.samples.clamp(1, MAX_SAMPLES),
        ao_rays: options.ao_rays.min(MAX_AO_RAYS),
        ..*options
    };
    let samples = options.samples;
    let per_tile = (TILE * TILE) as usize * samples as usize * (2 + options.ao_rays as usize);
    let tiles_per_chunk = (chunk_rays / per_tile).max(1);
    let tiles: Vec<(u32, u32)> = (0..height)
        .step_by(TILE as usize)
        .flat_map(|ty| (0..width).step_by(TILE as usize).map(move |tx| (tx, ty)))
        .collect();
    for chunk in tiles.chunks(tiles_per_chunk) {
        let mut rays = Vec::new();
        let mut seeds = Vec::new();
        let mut slots = Vec::new();
        let mut pixels = Vec::new();
        for &(tx, ty) in chunk {
            let base = pixels.len() as u32;
            let first = pixels.len();
            pixels.extend((0..TILE * TILE).filter_map(|z| {
                let x = tx + crate::camera::morton_even_bits(z);
                let y = ty + crate::camera::morton_even_bits(z >> 1);
                (x < width && y < height).then_some(y * width + x)
            }));
            for s in 0..samples {
                let [ox, oy] = sample_offset(s, samples);
                for (j, &pixel) in pixels[first..].iter().enumerate() {
                    let (x, y) = (pixel % width, pixel / width);
                    rays.push(camera.ray_through(
                        f64::from(x) + f64::from(ox),
                        f64::from(y) + f64::from(oy),
                        width,
                        height,
                        level,
                    ));
                    seeds.push((u64::from(pixel) * u64::from(samples) + u64::from(s)) as u32);
                    slots.push((base + j as u32) * samples + s);
                }
            }
        }
        let traced = SecondaryRays::new(tracer, &rays, &seeds, level, &options)?.finish(tracer)?;
        let mut surfaces = vec![Surface::MISS; pixels.len() * samples as usize];
        for (slot, surface) in slots.into_iter().zip(traced) {
            surfaces[slot as usize] = surface;
        }
        each(&pixels, &surfaces);
    }
    Ok(())
}

/// The primary rays of rows `rows` (a multiple of [`TILE`] from the top),
/// tile by tile, each tile's pixels in Z order once per sample, with the
/// surface number (`pixel * samples + sample`, modulo 2³², the seed of its
/// AO rays) of each: the order [`render_lit`] traces them in.
pub fn primary_rays(
    camera: &CameraFrame,
    width: u32,
    height: u32,
    rows: std::ops::Range<u32>,
    samples: u32,
    level: Option<u8>,
) -> (Vec<Ray>, Vec<u32>) {
    let mut rays = Vec::new();
    let mut owners = Vec::new();
    for ty in rows.clone().step_by(TILE as usize) {
        for tx in (0..width).step_by(TILE as usize) {
            for s in 0..samples {
                let [ox, oy] = sample_offset(s, samples);
                for z in 0..TILE * TILE {
                    let (x, y) = (
                        tx + crate::camera::morton_even_bits(z),
                        ty + crate::camera::morton_even_bits(z >> 1),
                    );
                    if x < width && y < rows.end.min(height) {
                        rays.push(camera.ray_through(
                            f64::from(x) + f64::from(ox),
                            f64::from(y) + f64::from(oy),
                            width,
                            height,
                            level,
                        ));
                        let pixel = u64::from(y) * u64::from(width) + u64::from(x);
                        owners.push((pixel * u64::from(samples) + u64::from(s)) as u32);
                    }
                }
            }
        }
    }
    (rays, owners)
}

/// Primary hits of a chunk and their secondary rays.
struct SecondaryRays {
    /// Per primary ray: its surface (without its visibility).
    surfaces: Vec<Surface>,
    /// The primary rays that have secondary rays: `1 + ao_rays` each, the
    /// shadow ray first.
    traced: Vec<u32>,
    rays: Vec<Ray>,
    ao_rays: u32,
}

impl SecondaryRays {
    /// Traces the primary rays and makes the secondary rays of their hits.
    fn new(
        tracer: &Tracer<'_>,
        rays: &[Ray],
        owners: &[u32],
        level: Option<u8>,
        options: &LitOptions,
    ) -> Result<Self, TraceError> {
        let indexed = tracer.colors().is_some();
        let hits = tracer.clone().with_index(indexed).trace_batch(rays)?;
        Self::from_hits(tracer, rays, &hits, owners, level, options)
    }

    /// The surfaces of primary rays `rays` with hits `hits` and their
    /// secondary rays.
    fn from_hits(
        tracer: &Tracer<'_>,
        rays: &[Ray],
        hits: &[Hit],
        owners: &[u32],
        level: Option<u8>,
        options: &LitOptions,
    ) -> Result<Self, TraceError> {
        let traced_level = level.unwrap_or(tracer.depth());
        let cell_size = f64::from(1u32 << (tracer.depth() - traced_level));
        let sun = options.sun_unit();
        let ao_rays = options.ao_rays;
        let ao_length = (options.ao_radius_cells(traced_level) * cell_size) as f32;
        let made: Vec<Result<(Surface, Vec<Ray>), TraceError>> = hits
            .par_iter()
            .zip(rays)
            .zip(owners)
            .map(|((hit, ray), &owner)| {
                let mut secondary = Vec::new();
                let surface = surface_of(
                    tracer,
                    hit,
                    ray,
                    traced_level,
                    cell_size,
                    |start, normal| {
                        let make =
                            |dir: [f32; 3], length: f32| tracer.grid_ray(start, dir, length, level);
                        secondary.push(make(sun, f32::INFINITY));
                        let seed = surface_seed(owner);
                        for k in 0..ao_rays {
                            secondary.push(make(ao_direction(normal, seed, k, ao_rays), ao_length));
                        }
                    },
                )?;
                Ok((surface, secondary))
            })
            .collect();
        let mut surfaces = Vec::with_capacity(made.len());
        let mut traced = Vec::new();
        let mut secondary = Vec::new();
        for (i, m) in made.into_iter().enumerate() {
            let (surface, rays) = m?;
            if !rays.is_empty() {
                traced.push(i as u32);
                secondary.extend(rays);
            }
            surfaces.push(surface);
        }
        Ok(SecondaryRays {
            surfaces,
            traced,
            rays: secondary,
            ao_rays,
        })
    }

    /// Traces the secondary rays: the surfaces, one per primary ray.
    fn finish(mut self, tracer: &Tracer<'_>) -> Result<Vec<Surface>, TraceError> {
        let hits = tracer.clone().with_index(false).trace_batch(&self.rays)?;
        let per_hit = 1 + self.ao_rays as usize;
        for (&i, hits) in self.traced.iter().zip(hits.chunks_exact(per_hit)) {
            let surface = &mut self.surfaces[i as usize];
            surface.sun_visible = !hits[0].hit;
            surface.ao_open = hits[1..].iter().filter(|h| !h.hit).count() as u32;
        }
        Ok(self.surfaces)
    }
}

/// The shadow rays (one per hit that gets secondary rays) and the
/// ambient-occlusion rays (`options.ao_rays` per such hit) that a lit render
/// traces for the primary rays `rays` (surface numbers `owners`, as
/// [`primary_rays`] makes them) with hits `hits`: the secondary-ray workload,
/// for benchmarks.
pub fn secondary_rays(
    tracer: &Tracer<'_>,
    rays: &[Ray],
    hits: &[Hit],
    owners: &[u32],
    level: Option<u8>,
    options: &LitOptions,
) -> Result<(Vec<Ray>, Vec<Ray>), TraceError> {
    let set = SecondaryRays::from_hits(tracer, rays, hits, owners, level, options)?;
    let per_hit = 1 + options.ao_rays as usize;
    let mut shadow = Vec::with_capacity(set.traced.len());
    let mut ao = Vec::with_capacity(set.rays.len() - set.traced.len());
    for group in set.rays.chunks_exact(per_hit) {
        shadow.push(group[0]);
        ao.extend_from_slice(&group[1..]);
    }
    Ok((shadow, ao))
}

/// The surface of primary hit `hit` of `ray` (visibility not yet known);
/// calls `secondary` with the start point (grid units) and normal of the
/// secondary rays when the hit gets them.
fn surface_of(
    tracer: &Tracer<'_>,
    hit: &Hit,
    ray: &Ray,
    level: u8,
    cell_size: f64,
    secondary: impl FnOnce([f64; 3], [f32; 3]),
) -> Result<Surface, TraceError> {
    if !hit.hit {
        return Ok(Surface::MISS);
    }
    let mut surface = Surface {
        hit: true,
        face: hit.face,
        index: hit.index,
        normal: [0.0; 3],
        sun_visible: false,
        ao_open: 0,
    };
    if hit.face == 0 {
        return Ok(surface);
    }
    let occupancy = tracer.occupancy_around(hit.voxel, level)?;
    let normal = normal_from_occupancy(occupancy, hit.face);
    surface.normal = normal;
    let origin = tracer.world_to_grid(ray.origin.map(f64::from));
    let scale = tracer.grid_scale;
    let dir = ray.dir.map(|d| f64::from(d) * scale);
    let start = start_point(
        origin,
        dir,
        f64::from(hit.t),
        hit.voxel,
        cell_size,
        hit.face,
        normal,
    );
    secondary(start, normal);
    Ok(surface)
}

impl Tracer<'_> {
    /// A world-space ray from grid point `start` in the unit direction `dir`
    /// over `[0, length]` grid units, at `level`.
    pub fn grid_ray(&self, start: [f64; 3], dir: [f32; 3], length: f32, level: Option<u8>) -> Ray {
        let origin: [f32; 3] =
            std::array::from_fn(|i| (self.root_min[i] + start[i] / self.grid_scale) as f32);
        Ray {
            origin,
            dir,
            tmin: 0.0,
            tmax: (f64::from(length) / self.grid_scale) as f32,
            level,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Camera;
    use dagfmt::{AttributeKind, Dag, DagBuilder};

    /// How the image is cut into chunks changes nothing: every surface's
    /// rays and seeds depend only on its pixel and sample.
    #[test]
    fn chunks_of_any_size_give_the_same_surfaces() {
        let voxels = (0..32u32).flat_map(|x| {
            (0..32u32).flat_map(move |z| {
                let h = 8 + (x * 7 + z * 3) % 9;
                (0..h).map(move |y| [x, y, z])
            })
        });
        let mut built =
            DagBuilder::from_voxels(5, AttributeKind::VoxelCount, voxels).expect("build");
        built.set_root_cube([0.0; 3], 1.0).expect("cube");
        let bytes = built.to_bytes();
        let dag = Dag::open(&bytes).expect("open");
        let tracer = Tracer::new(&dag).expect("tracer");
        // Partial tiles at the right and bottom edges.
        let (w, h) = (21, 13);
        let frame = Camera::automatic(&dag, f64::from(w) / f64::from(h))
            .frame()
            .expect("frame");
        let options = LitOptions {
            samples: 3,
            ao_rays: 4,
            ..LitOptions::default()
        };
        let mut images = Vec::new();
        for chunk_rays in [1, 5000, CHUNK_RAYS] {
            let mut out = vec![Surface::MISS; (w * h * 3) as usize];
            let mut chunks = 0;
            for_each_chunk(
                &tracer,
                &frame,
                (w, h, chunk_rays),
                None,
                &options,
                |pixels, surfaces| {
                    chunks += 1;
                    for (&pixel, group) in pixels.iter().zip(surfaces.chunks_exact(3)) {
                        out[pixel as usize * 3..][..3].copy_from_slice(group);
                    }
                },
            )
            .expect("trace");
            assert!(chunks >= 1);
            images.push(out);
        }
        assert!(images[0].iter().filter(|s| s.hit).count() > 100);
        assert_eq!(images[0], images[1]);
        assert_eq!(images[0], images[2]);
        let rgb = render_lit(&tracer, &frame, w, h, None, &options).expect("render");
        assert_eq!(rgb, compose(&images[0], &options, |_| None));
    }
}
