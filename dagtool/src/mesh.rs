//! Triangle meshes: loading Wavefront OBJ files, placing them in the root cube
//! and snapping them to the lattice the voxelizer works on.

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
    /// A problem with the materials that did not stop loading (e.g. a missing `.mtl`).
    pub material_warning: Option<String>,
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

    /// The options every OBJ is loaded with: polygons triangulated as fans,
    /// one index per position.
    fn obj_options() -> tobj::LoadOptions {
        tobj::LoadOptions {
            triangulate: true,
            single_index: false,
            ..Default::default()
        }
    }

    /// Loads every model and group of a Wavefront OBJ file, triangulating
    /// polygons (as fans). Points and lines in the file become zero-area
    /// triangles (tobj's behaviour), which the voxelizer treats as points and
    /// segments.
    pub fn load_obj(path: &Path) -> Result<Mesh, ConvertError> {
        let name = path.display().to_string();
        let file = std::fs::File::open(path)
            .map_err(|e| ConvertError::Input(format!("cannot read OBJ file {name}: {e}")))?;
        let mut guarded = IndexGuard::new(std::io::BufReader::new(file));
        // What `tobj::load_obj` does, with the index guard in between:
        // material libraries are looked up next to the OBJ file.
        let loaded = tobj::load_obj_buf(&mut guarded, &Self::obj_options(), |mtl| {
            tobj::load_mtl(
                path.parent()
                    .map_or_else(|| mtl.to_owned(), |p| p.join(mtl)),
            )
        });
        guarded.check(&name)?;
        Self::from_tobj(loaded, &name)
    }

    /// Loads an OBJ held in memory, like [`Mesh::load_obj`] but without
    /// touching the file system: `mtllib` statements are not followed (the
    /// mesh gets a material warning and default colours). `name` names the
    /// input in messages.
    pub fn load_obj_bytes(bytes: &[u8], name: &str) -> Result<Mesh, ConvertError> {
        let mut guarded = IndexGuard::new(bytes);
        let loaded = tobj::load_obj_buf(&mut guarded, &Self::obj_options(), |_| {
            Err(tobj::LoadError::OpenFileFailed)
        });
        guarded.check(name)?;
        Self::from_tobj(loaded, name)
    }

    /// The mesh of what tobj loaded from `name`.
    fn from_tobj(loaded: tobj::LoadResult, name: &str) -> Result<Mesh, ConvertError> {
        let (models, materials) =
            loaded.map_err(|e| ConvertError::Input(format!("cannot read OBJ file {name}: {e}")))?;
        let mut mesh = Mesh::default();
        match materials {
            Ok(materials) => {
                mesh.colors = materials
                    .iter()
                    .map(|m| match m.diffuse {
                        Some(kd) => {
                            let c = kd.map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8);
                            let a = m
                                .dissolve
                                .map_or(255, |d| (d.clamp(0.0, 1.0) * 255.0).round() as u8);
                            [c[0], c[1], c[2], a]
                        }
                        None => DEFAULT_COLOR,
                    })
                    .collect();
            }
            Err(e) => {
                mesh.material_warning = Some(format!("materials not loaded ({e})"));
            }
        }
        for model in &models {
            let m = &model.mesh;
            let base = mesh.vertices.len();
            if base + m.positions.len() / 3 > u32::MAX as usize {
                return Err(ConvertError::Input(format!(
                    "{name}: more than 2^32 vertices"
                )));
            }
            mesh.vertices.extend(
                m.positions
                    .chunks_exact(3)
                    .map(|p| [f64::from(p[0]), f64::from(p[1]), f64::from(p[2])]),
            );
            let material = m
                .material_id
                .filter(|&id| id < mesh.colors.len())
                .map_or(u32::MAX, |id| id as u32);
            for t in m.indices.chunks_exact(3) {
                mesh.triangles
                    .push([t[0], t[1], t[2]].map(|i| i + base as u32));
                mesh.triangle_material.push(material);
            }
        }
        Ok(mesh)
    }

    /// The colour of triangle `t`'s material.
    pub fn triangle_color(&self, t: usize) -> [u8; 4] {
        let m = self.triangle_material[t];
        self.colors
            .get(m as usize)
            .copied()
            .unwrap_or(DEFAULT_COLOR)
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
            let e1 = [0, 1, 2].map(|a| v[1][a] - v[0][a]);
            let e2 = [0, 1, 2].map(|a| v[2][a] - v[0][a]);
            let n = [
                e1[1] * e2[2] - e1[2] * e2[1],
                e1[2] * e2[0] - e1[0] * e2[2],
                e1[0] * e2[1] - e1[1] * e2[0],
            ];
            if n == [0.0; 3] {
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

/// The largest positive vertex, texture or normal index accepted in a face.
/// Larger ones cannot address anything (a mesh holds fewer than 2^32
/// vertices) and would overflow tobj's index arithmetic.
const MAX_OBJ_INDEX: i64 = 1 << 32;

/// A reader between the OBJ text and tobj that refuses, with a message naming
/// the line, face indices tobj does not handle safely: indices of 0, above
/// [`MAX_OBJ_INDEX`], or relative (negative) indices reaching before the first
/// element of their kind. (tobj turns those into indices near 2^64 and
/// multiplies them unchecked, which panics in builds with overflow checks.)
/// Everything else is passed through unchanged; tobj reports its own errors.
struct IndexGuard<R> {
    inner: R,
    /// The current line, handed to tobj from `pos` on.
    line: Vec<u8>,
    pos: usize,
    /// Lines read so far.
    number: u64,
    /// Positions, texture coordinates and normals declared so far.
    declared: [i64; 3],
    /// The first refused line's message.
    error: Option<String>,
}

impl<R: std::io::BufRead> IndexGuard<R> {
    fn new(inner: R) -> Self {
        IndexGuard {
            inner,
            line: Vec::new(),
            pos: 0,
            number: 0,
            declared: [0; 3],
            error: None,
        }
    }

    /// The refused line's error, if a line was refused.
    fn check(&self, name: &str) -> Result<(), ConvertError> {
        match &self.error {
            Some(message) => Err(ConvertError::Input(format!("{name}: {message}"))),
            None => Ok(()),
        }
    }

    /// Checks one line; returns the reason it is refused.
    fn refuse(&mut self, line: &[u8]) -> Option<String> {
        // tobj refuses lines that are not UTF-8 itself.
        let text = std::str::from_utf8(line).ok()?;
        let mut words = text.split_whitespace();
        match words.next()? {
            "v" => self.declared[0] += 1,
            "vt" => self.declared[1] += 1,
            "vn" => self.declared[2] += 1,
            "f" | "l" | "p" => {
                const KINDS: [&str; 3] = ["vertex", "texture coordinate", "normal"];
                for word in words {
                    for (k, part) in word.split('/').take(3).enumerate() {
                        // tobj refuses what is not an integer itself.
                        let Ok(index) = part.parse::<i64>() else {
                            continue;
                        };
                        let declared = self.declared[k];
                        if index == 0 || index > MAX_OBJ_INDEX || index < -declared {
                            return Some(format!(
                                "line {}: {} index {index} is out of range ({declared} defined so far)",
                                self.number, KINDS[k]
                            ));
                        }
                    }
                }
            }
            _ => {}
        }
        None
    }
}

impl<R: std::io::BufRead> std::io::Read for IndexGuard<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        use std::io::BufRead;
        let available = self.fill_buf()?;
        let n = available.len().min(buf.len());
        buf[..n].copy_from_slice(&available[..n]);
        self.consume(n);
        Ok(n)
    }
}

impl<R: std::io::BufRead> std::io::BufRead for IndexGuard<R> {
    fn fill_buf(&mut self) -> std::io::Result<&[u8]> {
        if self.pos == self.line.len() && self.error.is_none() {
            let mut line = std::mem::take(&mut self.line);
            line.clear();
            self.pos = 0;
            if self.inner.read_until(b'\n', &mut line)? > 0 {
                self.number += 1;
                if let Some(message) = self.refuse(&line) {
                    self.error = Some(message);
                }
            }
            self.line = line;
        }
        if let Some(message) = &self.error {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                message.clone(),
            ));
        }
        Ok(&self.line[self.pos..])
    }

    fn consume(&mut self, amount: usize) {
        self.pos = (self.pos + amount).min(self.line.len());
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
