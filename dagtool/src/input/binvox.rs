//! binvox (`.binvox`) occupancy grids. No maintained Rust crate reads them,
//! so this is a small hand-written parser (fuzzed by the `binvox` target).
//!
//! The header is text lines — `#binvox 1`, `dim D H W`, `translate x y z`,
//! `scale s`, `data` — followed by run-length pairs of bytes (value, count
//! 1..=255) covering the `D H W` voxels with y running fastest, then z, then
//! x. Voxel `(x, y, z)` spans the world cube with corner
//! `translate + (x, y, z) s / max(D, H, W)` and edge `s / max(D, H, W)`: the
//! grid's own cube (translate, scale) becomes the root cube.

use std::path::Path;

use super::{Format, Input, OpenOptions, VoxelGrid};
use crate::error::ConvertError;

/// The registry entry.
pub const FORMAT: Format = Format {
    name: "binvox",
    description: "binvox voxel grid",
    extensions: &["binvox"],
    magic: Some(|head| head.starts_with(b"#binvox")),
    open,
};

/// The largest side accepted: the DAG's deepest grid.
const MAX_SIDE: u64 = 1 << dagfmt::layout::MAX_DEPTH;

fn open(path: &Path, _options: &OpenOptions) -> Result<Input, ConvertError> {
    let bytes = super::read_file(path, "binvox file")?;
    load_bytes(&bytes, &path.display().to_string()).map(Input::Voxels)
}

/// Reads a binvox grid held in memory; `name` names it in messages.
pub fn load_bytes(bytes: &[u8], name: &str) -> Result<VoxelGrid, ConvertError> {
    let err = |m: String| ConvertError::Input(format!("{name}: {m}"));
    let mut rest = bytes;
    let next_line = |rest: &mut &[u8]| -> Option<String> {
        let end = rest.iter().position(|&b| b == b'\n')?;
        let line = String::from_utf8_lossy(&rest[..end]).trim().to_string();
        *rest = &rest[end + 1..];
        Some(line)
    };
    match next_line(&mut rest) {
        Some(l) if l.starts_with("#binvox") => {}
        _ => return Err(err("not a binvox file (no `#binvox` line)".into())),
    }
    let mut dims: Option<[u64; 3]> = None;
    let mut translate = [0.0f64; 3];
    let mut scale = 1.0f64;
    loop {
        let Some(line) = next_line(&mut rest) else {
            return Err(err("the binvox header ends before `data`".into()));
        };
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.first().copied() {
            Some("data") => break,
            Some("dim") => {
                let d: Vec<u64> = words[1..].iter().filter_map(|w| w.parse().ok()).collect();
                match d.as_slice() {
                    [a, b, c] if words.len() == 4 => dims = Some([*a, *b, *c]),
                    _ => return Err(err(format!("bad binvox line {line:?}"))),
                }
            }
            Some("translate") => {
                let t: Vec<f64> = words[1..].iter().filter_map(|w| w.parse().ok()).collect();
                match t.as_slice() {
                    [a, b, c] if words.len() == 4 => translate = [*a, *b, *c],
                    _ => return Err(err(format!("bad binvox line {line:?}"))),
                }
            }
            Some("scale") => match (words.len(), words.get(1).and_then(|w| w.parse().ok())) {
                (2, Some(s)) => scale = s,
                _ => return Err(err(format!("bad binvox line {line:?}"))),
            },
            None => {}
            Some(_) => return Err(err(format!("unknown binvox header line {line:?}"))),
        }
    }
    let Some(dims) = dims else {
        return Err(err("the binvox header has no `dim` line".into()));
    };
    // The file's dims are depth (x), height (z), width (y) as binvox writes
    // them; every binvox file in use is cubic, but the order is honoured.
    let [nx, nz, ny] = dims;
    if dims.contains(&0) || dims.iter().any(|&d| d > MAX_SIDE) {
        return Err(err(format!(
            "binvox dimensions {dims:?} are outside 1..={MAX_SIDE}"
        )));
    }
    if !(scale.is_finite() && scale > 0.0) || translate.iter().any(|c| !c.is_finite()) {
        return Err(err(format!(
            "binvox placement is not finite and positive (translate {translate:?}, scale {scale})"
        )));
    }
    let total = nx as u128 * ny as u128 * nz as u128;
    if !rest.len().is_multiple_of(2) {
        return Err(err("the binvox data has an odd number of bytes".into()));
    }
    let mut grid = VoxelGrid::default();
    let mut index: u128 = 0;
    for pair in rest.chunks_exact(2) {
        let (value, count) = (pair[0], u128::from(pair[1]));
        if value > 1 || count == 0 {
            return Err(err(format!(
                "bad binvox run (value {value}, count {count}) at voxel {index}"
            )));
        }
        if index + count > total {
            return Err(err(format!(
                "the binvox data covers more than the {total} voxels of the grid"
            )));
        }
        if value == 1 {
            for i in index..index + count {
                // y fastest, then z, then x.
                let y = (i % u128::from(ny)) as u32;
                let z = (i / u128::from(ny) % u128::from(nz)) as u32;
                let x = (i / (u128::from(ny) * u128::from(nz))) as u32;
                grid.voxels.push([x, y, z]);
            }
        }
        index += count;
    }
    if index != total {
        return Err(err(format!(
            "the binvox data covers {index} of the {total} voxels of the grid (truncated?)"
        )));
    }
    if grid.voxels.is_empty() {
        return Err(err("the binvox grid has no set voxel".into()));
    }
    let side = nx.max(ny).max(nz);
    grid.depth = ((64 - (side - 1).leading_zeros()) as u8).max(dagfmt::layout::MIN_DEPTH);
    grid.origin = translate;
    grid.voxel_size = scale / side as f64;
    grid.description = format!(
        "binvox {nx}x{ny}x{nz} grid, {} voxels set, translate {translate:?}, scale {scale}",
        grid.voxels.len()
    );
    Ok(grid)
}
