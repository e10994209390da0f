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

    /// Loads every model and group of a Wavefront OBJ file, triangulating
    /// polygons (as fans). Points and lines in the file become zero-area
    /// triangles (tobj's behaviour), which the voxelizer treats as points and
    /// segments.
    pub fn load_obj(path: &Path) -> Result<Mesh, ConvertError> {
        let options = tobj::LoadOptions {
            triangulate: true,
            single_index: false,
            ..Default::default()
        };
        let (models, materials) = tobj::load_obj(path, &options).map_err(|e| {
            ConvertError::Input(format!("cannot read OBJ file {}: {e}", path.display()))
        })?;
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
                    "{}: more than 2^32 vertices",
                    path.display()
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
