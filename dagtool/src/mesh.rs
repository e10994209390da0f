//! Triangle meshes, the common form of every mesh input (`crate::input`):
//! their colours, placing them in the root cube and snapping them to the
//! lattice the voxelizer works on.

use std::path::Path;

use crate::error::ConvertError;
use crate::geom::{Point, SUBVOXEL_BITS, Triangle};

/// Colour given to voxels whose triangle has no material (or no diffuse colour).
pub const DEFAULT_COLOR: [u8; 4] = [255, 255, 255, 255];

/// A triangle soup with per-triangle material colours.
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    /// Vertex positions (world space).
    pub vertices: Vec<[f64; 3]>,
    /// Vertex indices of each triangle.
    pub triangles: Vec<[u32; 3]>,
    /// Index into `colors` of each triangle's material, or `u32::MAX` for none.
    pub triangle_material: Vec<u32>,
    /// The diffuse colour (`Kd`) of each material, as RGBA8.
    pub colors: Vec<[u8; 4]>,
    /// The diffuse texture file (`map_Kd`, as written) of each material
    /// (indexed like `colors`).
    pub texture_files: Vec<Option<String>>,
    /// The decoded textures, once the input has read them (OBJ:
    /// [`crate::input::obj::load_textures`])
    /// (indexed like `colors`; `None` for a material without a readable one).
    pub textures: Vec<Option<Texture>>,
    /// Texture coordinates (`vt`) of the file.
    pub texcoords: Vec<[f64; 2]>,
    /// Indices into `texcoords` of each triangle's corners (`u32::MAX` for a
    /// triangle without them). Empty unless some material names a texture,
    /// so untextured meshes pay nothing.
    pub triangle_texcoords: Vec<[u32; 3]>,
    /// A problem with the materials that did not stop loading (e.g. a missing `.mtl`).
    pub material_warning: Option<String>,
    /// Textures that could not be read (their materials fall back to `Kd`).
    pub texture_warnings: Vec<String>,
    /// The name of each material (for messages).
    pub material_names: Vec<String>,
    /// Per-vertex colours (glTF `COLOR_0`, PLY `red green blue [alpha]`),
    /// indexed like `vertices`; empty when the mesh has none. A voxel's
    /// colour is then interpolated at the triangle's closest point and
    /// multiplied with the material's colour and texel.
    pub vertex_colors: Vec<[u8; 4]>,
}

/// How texture coordinates outside `[0, 1)` read the image (glTF sampler
/// wrap modes; OBJ textures repeat).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Wrap {
    /// The image repeats.
    #[default]
    Repeat,
    /// The image repeats, every other copy mirrored.
    MirroredRepeat,
    /// Coordinates are clamped to the edge texels.
    ClampToEdge,
}

impl Wrap {
    /// A coordinate mapped into `[0, 1]` (non-finite ones to 0).
    pub fn apply(self, c: f64) -> f64 {
        if !c.is_finite() {
            return 0.0;
        }
        match self {
            Wrap::Repeat => c - c.floor(),
            Wrap::MirroredRepeat => {
                let f = c.floor();
                let frac = c - f;
                if f.rem_euclid(2.0) == 0.0 {
                    frac
                } else {
                    1.0 - frac
                }
            }
            Wrap::ClampToEdge => c.clamp(0.0, 1.0),
        }
    }
}

/// A material's diffuse texture (`map_Kd`), decoded to RGBA8, with its
/// box-filtered mip levels, so that a voxel covering many texels takes their
/// average rather than whichever one its centre falls on.
#[derive(Clone, Debug)]
pub struct Texture {
    /// Level 0 is the image; each next one halves the sides (at least 1).
    levels: Vec<MipLevel>,
    /// How `u` and `v` outside `[0, 1)` read the image.
    wrap: [Wrap; 2],
}

/// One mip level: RGBA8 texels, rows from the top of the image.
#[derive(Clone, Debug)]
struct MipLevel {
    width: u32,
    height: u32,
    rgba: Vec<u8>,
}

impl MipLevel {
    /// The next level: sides halved (at least 1), each texel the rounded
    /// mean of the texels of this level it covers (two or three per axis).
    fn halved(&self) -> MipLevel {
        let (w, h) = (self.width as usize, self.height as usize);
        let (nw, nh) = ((w / 2).max(1), (h / 2).max(1));
        let mut rgba = vec![0u8; nw * nh * 4];
        for y in 0..nh {
            let rows = y * h / nh..(y + 1) * h / nh;
            for x in 0..nw {
                let cols = x * w / nw..(x + 1) * w / nw;
                let mut sum = [0u32; 4];
                for sy in rows.clone() {
                    for sx in cols.clone() {
                        let at = (sy * w + sx) * 4;
                        for (total, &byte) in sum.iter_mut().zip(&self.rgba[at..at + 4]) {
                            *total += u32::from(byte);
                        }
                    }
                }
                let n = (rows.len() * cols.len()) as u32;
                for c in 0..4 {
                    rgba[(y * nw + x) * 4 + c] = ((sum[c] + n / 2) / n) as u8;
                }
            }
        }
        MipLevel {
            width: nw as u32,
            height: nh as u32,
            rgba,
        }
    }
}

impl Texture {
    /// A texture of `width` x `height` texels from their RGBA8 bytes, rows
    /// from the top; `None` when the sizes do not match or it is empty.
    pub fn from_rgba(width: u32, height: u32, rgba: Vec<u8>) -> Option<Texture> {
        let texels = u64::from(width) * u64::from(height);
        if texels == 0 || rgba.len() as u64 != texels * 4 {
            return None;
        }
        let mut levels = vec![MipLevel {
            width,
            height,
            rgba,
        }];
        while let Some(last) = levels.last()
            && (last.width > 1 || last.height > 1)
        {
            let next = last.halved();
            levels.push(next);
        }
        Some(Texture {
            levels,
            wrap: [Wrap::Repeat; 2],
        })
    }

    /// The same texture with other wrap modes for `u` and `v`.
    pub fn with_wrap(mut self, wrap: [Wrap; 2]) -> Texture {
        self.wrap = wrap;
        self
    }

    /// Decodes an image held in memory (PNG, JPEG, TGA or BMP).
    pub fn decode(bytes: &[u8]) -> Result<Texture, String> {
        let image = image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| e.to_string())?
            .decode()
            .map_err(|e| e.to_string())?
            .into_rgba8();
        let (width, height) = image.dimensions();
        Texture::from_rgba(width, height, image.into_raw()).ok_or_else(|| "empty image".into())
    }

    /// Reads an image file (PNG, JPEG, TGA or BMP).
    pub fn load(path: &Path) -> Result<Texture, String> {
        // Only regular files: a FIFO or a device named by a material would
        // block or never end.
        match std::fs::metadata(path) {
            Ok(m) if m.is_file() => {}
            Ok(_) => return Err("not a regular file".into()),
            Err(e) => return Err(e.to_string()),
        }
        let image = image::ImageReader::open(path)
            .map_err(|e| e.to_string())?
            .with_guessed_format()
            .map_err(|e| e.to_string())?
            .decode()
            .map_err(|e| e.to_string())?
            .into_rgba8();
        let (width, height) = image.dimensions();
        Texture::from_rgba(width, height, image.into_raw()).ok_or_else(|| "empty image".into())
    }

    /// The texel at texture coordinates `uv` for a footprint `texels` wide in
    /// texels of the image: the nearest texel of the mip level whose texels
    /// are closest to the footprint in size (the image itself for footprints
    /// up to about one texel). Outside `[0, 1)` the coordinates wrap as the
    /// texture's [`Wrap`] modes say (repeating by default), and `v` runs up
    /// the image, as in OBJ.
    pub fn sample(&self, uv: [f64; 2], texels: f64) -> [u8; 4] {
        let level = if texels > 1.0 {
            // Rounded log2, in whole levels; NaN and infinities go to the ends.
            (texels.log2().round() as usize).min(self.levels.len() - 1)
        } else {
            0
        };
        let l = &self.levels[level];
        let (u, v) = (self.wrap[0].apply(uv[0]), self.wrap[1].apply(uv[1]));
        let x = ((u * f64::from(l.width)) as u32).min(l.width - 1);
        let y = (((1.0 - v) * f64::from(l.height)) as u32).min(l.height - 1);
        let at = (y as usize * l.width as usize + x as usize) * 4;
        [l.rgba[at], l.rgba[at + 1], l.rgba[at + 2], l.rgba[at + 3]]
    }

    /// The image's size in texels.
    fn size(&self) -> (u32, u32) {
        (self.levels[0].width, self.levels[0].height)
    }
}

/// `a - b`.
fn sub3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `a . b`.
fn dot3(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `a x b`.
fn cross3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// `|a|`.
fn length3(a: [f64; 3]) -> f64 {
    dot3(a, a).sqrt()
}

/// The items at three indices, or `None` when one is out of range.
fn gather<T: Copy>(items: &[T], indices: [u32; 3]) -> Option<[T; 3]> {
    Some([
        *items.get(indices[0] as usize)?,
        *items.get(indices[1] as usize)?,
        *items.get(indices[2] as usize)?,
    ])
}

/// Barycentric weights of the point of triangle `v` closest to `p` (Ericson,
/// *Real-Time Collision Detection*, 5.1.5); degenerate triangles give the
/// weights of one of their closest points.
fn closest_barycentric(p: [f64; 3], v: [[f64; 3]; 3]) -> [f64; 3] {
    let (sub, dot) = (sub3, dot3);
    let [a, b, c] = v;
    let (ab, ac) = (sub(b, a), sub(c, a));
    let ap = sub(p, a);
    let (d1, d2) = (dot(ab, ap), dot(ac, ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return [1.0, 0.0, 0.0];
    }
    let bp = sub(p, b);
    let (d3, d4) = (dot(ab, bp), dot(ac, bp));
    if d3 >= 0.0 && d4 <= d3 {
        return [0.0, 1.0, 0.0];
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let s = d1 / (d1 - d3);
        return [1.0 - s, s, 0.0];
    }
    let cp = sub(p, c);
    let (d5, d6) = (dot(ab, cp), dot(ac, cp));
    if d6 >= 0.0 && d5 <= d6 {
        return [0.0, 0.0, 1.0];
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let s = d2 / (d2 - d6);
        return [1.0 - s, 0.0, s];
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0 {
        let s = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return [0.0, 1.0 - s, s];
    }
    let inv = 1.0 / (va + vb + vc);
    let (s, t) = (vb * inv, vc * inv);
    if s.is_finite() && t.is_finite() {
        [1.0 - s - t, s, t]
    } else {
        [1.0, 0.0, 0.0]
    }
}

/// A texel tinted by a colour, channel by channel (`map_Kd` times `Kd`, the
/// texel's alpha times `d`).
fn modulate(texel: [u8; 4], tint: [u8; 4]) -> [u8; 4] {
    [0, 1, 2, 3].map(|i| ((u16::from(texel[i]) * u16::from(tint[i]) + 127) / 255) as u8)
}

impl Mesh {
    /// Builds a mesh from positions and triangles, without materials.
    pub fn from_triangles(vertices: Vec<[f64; 3]>, triangles: Vec<[u32; 3]>) -> Self {
        let n = triangles.len();
        Mesh {
            vertices,
            triangles,
            triangle_material: vec![u32::MAX; n],
            ..Default::default()
        }
    }

    /// The colour of triangle `t`'s material.
    pub fn triangle_color(&self, t: usize) -> [u8; 4] {
        let m = self.triangle_material[t];
        self.colors
            .get(m as usize)
            .copied()
            .unwrap_or(DEFAULT_COLOR)
    }

    /// Whether a triangle's colour varies over it: some triangle takes its
    /// colour from a texture, or the vertices have colours (so that
    /// [`Mesh::voxel_color`] needs the voxel's position).
    pub fn has_textures(&self) -> bool {
        !self.vertex_colors.is_empty()
            || (!self.triangle_texcoords.is_empty() && self.textures.iter().any(Option::is_some))
    }

    /// The colour of a voxel of edge `voxel` set by triangle `t`, whose centre
    /// is at `p` (world space): the material's texture at the texture
    /// coordinates of the triangle's point closest to `p`, averaged over the
    /// voxel's footprint (see [`Texture::sample`]: the footprint's width in
    /// texels is `voxel` times the triangle's texture-to-world scale, the
    /// square root of its area ratio), times `Kd`; the triangle's colour
    /// ([`Mesh::triangle_color`]) without a texture or texture coordinates.
    pub fn voxel_color(&self, t: usize, p: [f64; 3], voxel: f64) -> [u8; 4] {
        let mut tint = self.triangle_color(t);
        if let Some(c) = self.vertex_color(t, p) {
            tint = modulate(c, tint);
        }
        self.texel(t, p, voxel)
            .map_or(tint, |texel| modulate(texel, tint))
    }

    /// The vertex colour of triangle `t` interpolated at its point closest to
    /// `p`, or `None` when the mesh has no vertex colours.
    fn vertex_color(&self, t: usize, p: [f64; 3]) -> Option<[u8; 4]> {
        if self.vertex_colors.is_empty() {
            return None;
        }
        let tri = self.triangles[t];
        let c = gather(&self.vertex_colors, tri)?;
        let v = gather(&self.vertices, tri)?;
        let w = closest_barycentric(p, v);
        Some([0, 1, 2, 3].map(|k| {
            let x =
                w[0] * f64::from(c[0][k]) + w[1] * f64::from(c[1][k]) + w[2] * f64::from(c[2][k]);
            x.round().clamp(0.0, 255.0) as u8
        }))
    }

    /// The texel of [`Mesh::voxel_color`], or `None` when triangle `t` has no
    /// texture or no (valid) texture coordinates.
    fn texel(&self, t: usize, p: [f64; 3], voxel: f64) -> Option<[u8; 4]> {
        let m = self.triangle_material[t] as usize;
        let texture = self.textures.get(m)?.as_ref()?;
        let uv = gather(&self.texcoords, *self.triangle_texcoords.get(t)?)?;
        let v = gather(&self.vertices, self.triangles[t])?;
        let w = closest_barycentric(p, v);
        let at = [0, 1].map(|a| w[0] * uv[0][a] + w[1] * uv[1][a] + w[2] * uv[2][a]);
        // Twice the areas: in the world, and in texels.
        let world = length3(cross3(sub3(v[1], v[0]), sub3(v[2], v[0])));
        let (tw, th) = texture.size();
        let f = [1, 2].map(|k| {
            [
                (uv[k][0] - uv[0][0]) * f64::from(tw),
                (uv[k][1] - uv[0][1]) * f64::from(th),
            ]
        });
        let texel_area = (f[0][0] * f[1][1] - f[0][1] * f[1][0]).abs();
        // A degenerate triangle (or one without a texture area) reads the image.
        let texels = if world > 0.0 {
            voxel * (texel_area / world).sqrt()
        } else {
            0.0
        };
        Some(texture.sample(at, texels))
    }

    /// Checks that the mesh can be voxelized: it has triangles, every vertex
    /// is finite, every index is in range and not every triangle is degenerate.
    /// Returns the bounding box of the vertices used by triangles and the
    /// number of zero-area triangles.
    pub fn check(&self) -> Result<MeshCheck, ConvertError> {
        if self.triangles.is_empty() {
            return Err(ConvertError::Input("the mesh has no triangles".into()));
        }
        if let Some(i) = self
            .vertices
            .iter()
            .position(|v| !v.iter().all(|c| c.is_finite()))
        {
            return Err(ConvertError::Input(format!(
                "vertex {} has a non-finite coordinate {:?}",
                i + 1,
                self.vertices[i]
            )));
        }
        let mut min = [f64::INFINITY; 3];
        let mut max = [f64::NEG_INFINITY; 3];
        let mut degenerate = 0u64;
        for (t, tri) in self.triangles.iter().enumerate() {
            let mut v = [[0.0; 3]; 3];
            for (k, &i) in tri.iter().enumerate() {
                let Some(p) = self.vertices.get(i as usize) else {
                    return Err(ConvertError::Input(format!(
                        "triangle {} uses vertex {} but there are only {}",
                        t + 1,
                        i as u64 + 1,
                        self.vertices.len()
                    )));
                };
                v[k] = *p;
                for a in 0..3 {
                    min[a] = min[a].min(p[a]);
                    max[a] = max[a].max(p[a]);
                }
            }
            if cross3(sub3(v[1], v[0]), sub3(v[2], v[0])) == [0.0; 3] {
                degenerate += 1;
            }
        }
        if degenerate == self.triangles.len() as u64 {
            return Err(ConvertError::Input(format!(
                "all {} triangles of the mesh are degenerate (zero area)",
                self.triangles.len()
            )));
        }
        Ok(MeshCheck {
            min,
            max,
            degenerate,
        })
    }
}

/// What [`Mesh::check`] found.
#[derive(Clone, Copy, Debug)]
pub struct MeshCheck {
    /// Minimum corner of the bounding box of the used vertices.
    pub min: [f64; 3],
    /// Maximum corner of the bounding box of the used vertices.
    pub max: [f64; 3],
    /// Number of zero-area triangles.
    pub degenerate: u64,
}

/// How world space maps onto the voxel grid: the root cube and the depth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GridMapping {
    /// Depth D: 2^D voxels per axis.
    pub depth: u8,
    /// World-space minimum corner of the root cube.
    pub root_min: [f64; 3],
    /// World-space edge length of the root cube.
    pub root_size: f64,
}

impl GridMapping {
    /// The root cube for a mesh with bounding box `[min, max]`: centred on the
    /// box, with edge `max_extent * 2^D / (2^D - 1)`, so that along the
    /// longest axis the mesh spans `2^D - 1` voxels with half a voxel of
    /// padding on each side. The padding keeps every conservative voxel of the
    /// surface inside the volume (nothing is clipped at the border).
    pub fn fit(min: [f64; 3], max: [f64; 3], depth: u8) -> Result<Self, ConvertError> {
        let extent = (0..3).map(|a| max[a] - min[a]).fold(0.0, f64::max);
        if !(extent > 0.0 && extent.is_finite()) {
            return Err(ConvertError::Input(format!(
                "the mesh has no extent (bounding box {min:?} to {max:?})"
            )));
        }
        let res = (1u64 << depth) as f64;
        let root_size = extent * res / (res - 1.0);
        let root_min = [0, 1, 2].map(|a| 0.5 * (min[a] + max[a]) - 0.5 * root_size);
        if !root_size.is_finite() || root_min.iter().any(|c| !c.is_finite()) {
            return Err(ConvertError::Input(
                "the mesh's bounding box is too large".into(),
            ));
        }
        Ok(GridMapping {
            depth,
            root_min,
            root_size,
        })
    }

    /// Voxels per axis.
    pub fn resolution(&self) -> u64 {
        1 << self.depth
    }

    /// Snaps a world-space point to the lattice:
    /// `q = round((p - root_min) * (2^(D + 16) / root_size))`, each coordinate
    /// rounded to the nearest integer (ties away from zero) and clamped to
    /// `[0, 2^(D + 16)]`. One lattice unit is 1/65536 of a voxel.
    pub fn snap(&self, p: [f64; 3]) -> Point {
        let units = (1u64 << (u32::from(self.depth) + SUBVOXEL_BITS)) as f64;
        let scale = units / self.root_size;
        [0, 1, 2].map(|a| (((p[a] - self.root_min[a]) * scale).round()).clamp(0.0, units) as i64)
    }
}

/// A mesh snapped to the lattice, ready to voxelize.
#[derive(Clone, Debug)]
pub struct SnappedMesh {
    /// Snapped vertex positions.
    pub vertices: Vec<Point>,
    /// Vertex indices of each triangle.
    pub triangles: Vec<[u32; 3]>,
}

impl SnappedMesh {
    /// Snaps every vertex of `mesh` with `mapping`.
    pub fn new(mesh: &Mesh, mapping: &GridMapping) -> Self {
        SnappedMesh {
            vertices: mesh.vertices.iter().map(|&v| mapping.snap(v)).collect(),
            triangles: mesh.triangles.clone(),
        }
    }

    /// Triangle `t`'s vertices.
    #[inline]
    pub fn triangle(&self, t: u32) -> Triangle {
        self.triangles[t as usize].map(|i| self.vertices[i as usize])
    }

    /// Whether the surface is closed in the mod-2 sense: after welding
    /// vertices with equal snapped positions, every edge is used by an even
    /// number of triangles. Exactly then the parity of ray crossings is the
    /// same along every ray, so "inside" is well defined.
    pub fn is_closed(&self) -> bool {
        use std::collections::HashMap;
        let mut ids: HashMap<Point, u32> = HashMap::with_capacity(self.vertices.len());
        let canon: Vec<u32> = self
            .vertices
            .iter()
            .map(|p| {
                let next = ids.len() as u32;
                *ids.entry(*p).or_insert(next)
            })
            .collect();
        let mut odd: HashMap<(u32, u32), ()> = HashMap::with_capacity(self.triangles.len());
        for t in &self.triangles {
            let c = t.map(|i| canon[i as usize]);
            for j in 0..3 {
                let (a, b) = (c[j], c[(j + 1) % 3]);
                if a == b {
                    continue;
                }
                let key = (a.min(b), a.max(b));
                if odd.remove(&key).is_none() {
                    odd.insert(key, ());
                }
            }
        }
        odd.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn point(w: [f64; 3], v: [[f64; 3]; 3]) -> [f64; 3] {
        [0, 1, 2].map(|a| w[0] * v[0][a] + w[1] * v[1][a] + w[2] * v[2][a])
    }

    fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
        (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt()
    }

    proptest! {
        /// The closest point is a point of the triangle (weights >= 0 summing
        /// to 1) and no farther than the nearest of a fine grid of its points.
        #[test]
        fn closest_point_is_no_farther_than_any_sample(
            v in prop::array::uniform3(prop::array::uniform3(-4.0f64..4.0)),
            p in prop::array::uniform3(-6.0f64..6.0),
        ) {
            let w = closest_barycentric(p, v);
            prop_assert!(w.iter().all(|&x| (-1e-12..=1.0 + 1e-12).contains(&x)), "{w:?}");
            prop_assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-9);
            let got = distance(point(w, v), p);
            const N: usize = 60;
            for i in 0..=N {
                for j in 0..=N - i {
                    let s = [i, j, N - i - j].map(|k| k as f64 / N as f64);
                    prop_assert!(got <= distance(point(s, v), p) + 1e-9);
                }
            }
        }
    }

    #[test]
    fn texels_repeat_and_v_runs_up() {
        // 2 x 1 texels: left red, right green; 1 x 2: top red, bottom green.
        let red = [255, 0, 0, 255];
        let green = [0, 255, 0, 255];
        let wide = Texture::from_rgba(2, 1, [red, green].concat()).unwrap();
        assert_eq!(wide.sample([0.25, 0.5], 1.0), red);
        assert_eq!(wide.sample([0.75, 0.5], 0.0), green);
        assert_eq!(wide.sample([1.25, 7.5], 1.2), red);
        assert_eq!(wide.sample([-0.25, 0.5], f64::NAN), green);
        assert_eq!(wide.sample([f64::NAN, 0.5], 1.0), red);
        let tall = Texture::from_rgba(1, 2, [red, green].concat()).unwrap();
        assert_eq!(tall.sample([0.5, 0.75], 1.0), red);
        assert_eq!(tall.sample([0.5, 0.25], 1.0), green);
        // Footprints of two texels or more read the 1 x 1 level: the mean.
        for texels in [2.0, 3.0, 1e300, f64::INFINITY] {
            assert_eq!(wide.sample([0.25, 0.5], texels), [128, 128, 0, 255]);
        }
        assert!(Texture::from_rgba(2, 2, vec![0; 12]).is_none());
        assert!(Texture::from_rgba(0, 0, Vec::new()).is_none());
        assert_eq!(
            modulate([255, 128, 0, 255], [128, 255, 255, 128]),
            [128, 128, 0, 128]
        );
    }

    #[test]
    fn mip_levels_are_box_filtered() {
        // 4 x 2 texels with red 0, 30, ..., 210 (rows from the top).
        let rgba: Vec<u8> = (0..8u8).flat_map(|i| [i * 30, 7, 0, 255]).collect();
        let t = Texture::from_rgba(4, 2, rgba).unwrap();
        let sizes: Vec<_> = t.levels.iter().map(|l| (l.width, l.height)).collect();
        assert_eq!(sizes, [(4, 2), (2, 1), (1, 1)]);
        // Level 1: the rounded means of columns 0-1 and 2-3 of both rows.
        let reds: Vec<u8> = t.levels[1].rgba.chunks(4).map(|c| c[0]).collect();
        assert_eq!(reds, [75, 135]);
        assert_eq!(t.levels[2].rgba, [105, 7, 0, 255]);
        // Odd sides: 3 x 1 halves to one texel, the mean of the three.
        let odd = [[0u8; 4], [3; 4], [9; 4]].concat();
        let t = Texture::from_rgba(3, 1, odd).unwrap();
        assert_eq!(t.levels.len(), 2);
        assert_eq!(t.levels[1].rgba, [4, 4, 4, 4]);
        // The level is the rounded log2 of the footprint: a one-texel checker
        // reads as itself below sqrt 2 texels and as grey from there.
        let rgba: Vec<u8> = (0..16 * 16u32)
            .flat_map(|i| [((i + i / 16) % 2 * 255) as u8, 0, 0, 255])
            .collect();
        let t = Texture::from_rgba(16, 16, rgba).unwrap();
        assert_eq!(t.sample([0.01, 0.99], 1.4)[0], 0);
        assert_eq!(t.sample([0.07, 0.99], 1.4)[0], 255);
        assert_eq!(t.sample([0.01, 0.99], 1.5)[0], 128);
        assert_eq!(t.sample([0.5, 0.5], 100.0)[0], 128);
    }
}
