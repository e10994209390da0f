//! STL (`.stl`), ASCII and binary, read with `stl_io`.
//!
//! A file is binary when its size is exactly `84 + 50 N` bytes for the `N`
//! its header declares, whatever its first bytes (some writers start binary
//! headers with `solid`); otherwise it must be ASCII (`solid name` …). STL
//! has no colours: `--colors` makes every voxel white.

use std::path::Path;

use super::{Format, Input, OpenOptions};
use crate::error::ConvertError;
use crate::mesh::Mesh;

/// The registry entry.
pub const FORMAT: Format = Format {
    name: "stl",
    description: "STL mesh (ASCII or binary)",
    extensions: &["stl"],
    magic: Some(is_ascii_stl),
    open,
};

/// ASCII STL starts with `solid` and a space. (Binary STL has no signature:
/// it is recognised by its extension.)
fn is_ascii_stl(head: &[u8]) -> bool {
    head.starts_with(b"solid ") && head.windows(5).any(|w| w == b"facet" || w == b"endso")
}

fn open(path: &Path, _options: &OpenOptions) -> Result<Input, ConvertError> {
    let bytes = super::read_file(path, "STL file")?;
    load_bytes(bytes, &path.display().to_string()).map(|m| Input::Mesh(Box::new(m)))
}

/// Whether `bytes` are a binary STL by their size.
fn is_binary(bytes: &[u8]) -> bool {
    bytes.len() >= 84
        && u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as u64 * 50 + 84
            == bytes.len() as u64
}

/// Reads an STL held in memory; `name` names it in messages.
pub fn load_bytes(mut bytes: Vec<u8>, name: &str) -> Result<Mesh, ConvertError> {
    let binary = is_binary(&bytes);
    if binary {
        // stl_io takes any file starting with "solid " for ASCII; the header
        // of a binary file means nothing, so it is blanked.
        bytes[0] = b' ';
    } else if !bytes.starts_with(b"solid") {
        let declared = if bytes.len() >= 84 {
            format!(
                "declares {} triangles ({} bytes) but has {} bytes",
                u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]),
                u64::from(u32::from_le_bytes([
                    bytes[80], bytes[81], bytes[82], bytes[83]
                ])) * 50
                    + 84,
                bytes.len()
            )
        } else {
            format!("has only {} bytes", bytes.len())
        };
        return Err(ConvertError::Input(format!(
            "{name}: not an STL file: not ASCII (no `solid`) and as binary STL it {declared}"
        )));
    }
    let mut cursor = std::io::Cursor::new(bytes);
    let reader = stl_io::create_stl_reader(&mut cursor)
        .map_err(|e| ConvertError::Input(format!("{name}: cannot read STL: {e}")))?;
    let mut mesh = Mesh::default();
    for (i, triangle) in reader.enumerate() {
        let triangle = triangle.map_err(|e| {
            ConvertError::Input(format!("{name}: cannot read STL triangle {}: {e}", i + 1))
        })?;
        let base = mesh.vertices.len();
        if base + 3 > u32::MAX as usize {
            return Err(ConvertError::Input(format!(
                "{name}: more than 2^32 vertices"
            )));
        }
        for v in triangle.vertices {
            mesh.vertices.push([0, 1, 2].map(|a| f64::from(v.0[a])));
        }
        let b = base as u32;
        mesh.triangles.push([b, b + 1, b + 2]);
    }
    mesh.triangle_material = vec![u32::MAX; mesh.triangles.len()];
    Ok(mesh)
}
