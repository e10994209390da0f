//! MagicaVoxel `.vox`, read with `dot_vox`: every model, placed by the scene
//! graph (nTRN translations and rotations, composed down through nGRP
//! groups to the nSHP shapes; the first frame of each transform), with the
//! palette's colours. Files without a scene graph place every model at the
//! origin.
//!
//! A model voxel `v` of a model of size `s` under the composed rotation `R`
//! and translation `t` becomes the cell `floor(R (v + 1/2 - floor(s/2)) + t)`
//! (MagicaVoxel turns models about their centre voxel). One `.vox` voxel is
//! one output voxel: world units are `.vox` voxels, and the grid's corner is
//! the scene's lowest cell.

use std::path::Path;

use dot_vox::{DotVoxData, SceneNode};

use super::{Format, Input, OpenOptions, VoxelGrid};
use crate::error::ConvertError;

/// The registry entry.
pub const FORMAT: Format = Format {
    name: "vox",
    description: "MagicaVoxel .vox",
    extensions: &["vox"],
    magic: Some(|head| head.starts_with(b"VOX ")),
    open,
};

fn open(path: &Path, _options: &OpenOptions) -> Result<Input, ConvertError> {
    let bytes = super::read_file(path, "VOX file")?;
    load_bytes(&bytes, &path.display().to_string()).map(Input::Voxels)
}

/// A rotation as a signed permutation matrix (rows).
type Matrix = [[i64; 3]; 3];

const IDENTITY: Matrix = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];

/// The rotation a frame's `_r` byte encodes (bits 0–1: the column of row 0's
/// non-zero entry, bits 2–3: row 1's; row 2 takes the one left; bits 4–6:
/// the rows' signs), or `None` when the byte is not a rotation.
fn rotation(byte: u8) -> Option<Matrix> {
    let c0 = usize::from(byte & 3);
    let c1 = usize::from((byte >> 2) & 3);
    if c0 == 3 || c1 == 3 || c0 == c1 {
        return None;
    }
    let c2 = 3 - c0 - c1;
    let mut m = [[0i64; 3]; 3];
    for (row, col) in [c0, c1, c2].into_iter().enumerate() {
        m[row][col] = if byte >> (4 + row) & 1 == 1 { -1 } else { 1 };
    }
    Some(m)
}

fn mul(a: &Matrix, b: &Matrix) -> Matrix {
    let mut m = [[0i64; 3]; 3];
    for (i, row) in m.iter_mut().enumerate() {
        for (j, cell) in row.iter_mut().enumerate() {
            *cell = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    m
}

fn apply(m: &Matrix, v: [i64; 3]) -> [i64; 3] {
    [0, 1, 2].map(|i| (0..3).map(|k| m[i][k] * v[k]).sum())
}

/// A rigid placement: `p ↦ R p + t`.
#[derive(Clone, Copy)]
struct Placement {
    rotation: Matrix,
    translation: [i64; 3],
}

impl Placement {
    fn then(&self, inner: &Placement) -> Placement {
        let t = apply(&self.rotation, inner.translation);
        Placement {
            rotation: mul(&self.rotation, &inner.rotation),
            translation: [0, 1, 2].map(|a| t[a] + self.translation[a]),
        }
    }
}

/// Reads a `.vox` held in memory; `name` names it in messages.
pub fn load_bytes(bytes: &[u8], name: &str) -> Result<VoxelGrid, ConvertError> {
    let data = dot_vox::load_bytes(bytes)
        .map_err(|e| ConvertError::Input(format!("{name}: cannot read VOX: {e}")))?;
    let mut instances = Vec::new();
    if data.scenes.is_empty() {
        for model in 0..data.models.len() {
            instances.push((
                model,
                Placement {
                    rotation: IDENTITY,
                    translation: [0; 3],
                },
            ));
        }
    } else {
        let root = Placement {
            rotation: IDENTITY,
            translation: [0; 3],
        };
        walk(&data, 0, root, 0, &mut instances, name)?;
    }
    let mut grid = VoxelGrid::default();
    let mut lo = [i64::MAX; 3];
    let mut hi = [i64::MIN; 3];
    let mut cells = Vec::new();
    for &(m, place) in &instances {
        let Some(model) = data.models.get(m) else {
            return Err(ConvertError::Input(format!(
                "{name}: a shape uses model {m} but there are only {}",
                data.models.len()
            )));
        };
        let size = [model.size.x, model.size.y, model.size.z].map(i64::from);
        for v in &model.voxels {
            // Twice the voxel centre relative to the pivot, so that the
            // arithmetic stays in integers: 2 (v + 1/2 - floor(s/2)).
            let c2 = [v.x, v.y, v.z]
                .iter()
                .zip(size)
                .map(|(&c, s)| 2 * i64::from(c) + 1 - 2 * (s / 2))
                .collect::<Vec<_>>();
            let r = apply(&place.rotation, [c2[0], c2[1], c2[2]]);
            let cell = [0, 1, 2].map(|a| (r[a] + 2 * place.translation[a]).div_euclid(2));
            for a in 0..3 {
                lo[a] = lo[a].min(cell[a]);
                hi[a] = hi[a].max(cell[a]);
            }
            cells.push(cell);
            let c = data
                .palette
                .get(usize::from(v.i))
                .map_or([255; 4], |c| [c.r, c.g, c.b, c.a]);
            grid.colors.push(c);
        }
    }
    if cells.is_empty() {
        return Err(ConvertError::Input(format!(
            "{name}: the VOX scene has no voxels"
        )));
    }
    let extent = (0..3).map(|a| hi[a] - lo[a] + 1).max().unwrap_or(1);
    let depth = (64 - (extent as u64 - 1).leading_zeros()) as u8;
    grid.depth = depth.max(dagfmt::layout::MIN_DEPTH);
    if grid.depth > dagfmt::layout::MAX_DEPTH {
        return Err(ConvertError::Input(format!(
            "{name}: the VOX scene spans {extent} voxels, more than 2^{}",
            dagfmt::layout::MAX_DEPTH
        )));
    }
    grid.voxels = cells
        .iter()
        .map(|c| [0, 1, 2].map(|a| (c[a] - lo[a]) as u32))
        .collect();
    grid.origin = lo.map(|c| c as f64);
    grid.voxel_size = 1.0;
    grid.description = format!(
        "MagicaVoxel .vox version {}, {} models, {} instances, {} voxels",
        data.version,
        data.models.len(),
        instances.len(),
        grid.voxels.len()
    );
    Ok(grid)
}

/// The deepest scene graph walked; deeper ones (or cycles) are refused.
const MAX_SCENE_DEPTH: usize = 64;

fn walk(
    data: &DotVoxData,
    node: usize,
    place: Placement,
    level: usize,
    out: &mut Vec<(usize, Placement)>,
    name: &str,
) -> Result<(), ConvertError> {
    if level > MAX_SCENE_DEPTH {
        return Err(ConvertError::Input(format!(
            "{name}: the VOX scene graph is deeper than {MAX_SCENE_DEPTH} nodes (or has a cycle)"
        )));
    }
    let Some(n) = data.scenes.get(node) else {
        return Err(ConvertError::Input(format!(
            "{name}: the VOX scene graph refers to node {node} but there are only {}",
            data.scenes.len()
        )));
    };
    match n {
        SceneNode::Transform { frames, child, .. } => {
            let mut local = Placement {
                rotation: IDENTITY,
                translation: [0; 3],
            };
            if let Some(frame) = frames.first() {
                if let Some(r) = frame.attributes.get("_r") {
                    local.rotation =
                        r.trim()
                            .parse::<u8>()
                            .ok()
                            .and_then(rotation)
                            .ok_or_else(|| {
                                ConvertError::Input(format!(
                                    "{name}: node {node} has an invalid rotation {r:?}"
                                ))
                            })?;
                }
                if let Some(t) = frame.attributes.get("_t") {
                    let parts: Vec<Option<i64>> = t
                        .split_whitespace()
                        .map(|w| w.parse::<i32>().ok().map(i64::from))
                        .collect();
                    match parts.as_slice() {
                        [Some(x), Some(y), Some(z)] => local.translation = [*x, *y, *z],
                        _ => {
                            return Err(ConvertError::Input(format!(
                                "{name}: node {node} has an invalid translation {t:?}"
                            )));
                        }
                    }
                }
            }
            walk(
                data,
                *child as usize,
                place.then(&local),
                level + 1,
                out,
                name,
            )
        }
        SceneNode::Group { children, .. } => {
            for &c in children {
                walk(data, c as usize, place, level + 1, out, name)?;
            }
            Ok(())
        }
        SceneNode::Shape { models, .. } => {
            for m in models {
                out.push((m.model_id as usize, place));
            }
            Ok(())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotations_are_signed_permutations() {
        assert_eq!(rotation(4), Some(IDENTITY));
        // Row 0 takes column 1, row 1 column 0, row 2 column 2, row 0 negated.
        assert_eq!(rotation(0b1_0001), Some([[0, -1, 0], [1, 0, 0], [0, 0, 1]]));
        assert_eq!(rotation(0), None);
        assert_eq!(rotation(3), None);
        let mut valid = 0;
        for b in 0..=127u8 {
            if let Some(m) = rotation(b) {
                valid += 1;
                // Orthogonal: M Mᵀ = I.
                let t = [0, 1, 2].map(|i| [0, 1, 2].map(|j| m[j][i]));
                assert_eq!(mul(&m, &t), IDENTITY);
            }
        }
        assert_eq!(valid, 48);
    }
}
