//! Wavefront OBJ (`.obj`, with `.mtl` materials and `map_Kd` textures),
//! read with tobj behind a guard for the face indices tobj does not handle
//! safely.

use std::path::Path;

use super::{Format, Input, OpenOptions};
use crate::error::ConvertError;
use crate::mesh::{DEFAULT_COLOR, Mesh, Texture};

/// The registry entry. OBJ has no signature: it is recognised by its
/// extension only.
pub const FORMAT: Format = Format {
    name: "obj",
    description: "Wavefront OBJ mesh",
    extensions: &["obj"],
    magic: None,
    open,
};

fn open(path: &Path, options: &OpenOptions) -> Result<Input, ConvertError> {
    let mut mesh = load(path)?;
    if options.colors {
        load_textures(&mut mesh, path.parent().unwrap_or(Path::new("")));
    }
    Ok(Input::Mesh(Box::new(mesh)))
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
pub fn load(path: &Path) -> Result<Mesh, ConvertError> {
    let name = path.display().to_string();
    let file = std::fs::File::open(path)
        .map_err(|e| ConvertError::Input(format!("cannot read OBJ file {name}: {e}")))?;
    let mut guarded = IndexGuard::new(std::io::BufReader::new(file));
    // What `tobj::load_obj` does, with the index guard in between:
    // material libraries are looked up next to the OBJ file.
    let loaded = tobj::load_obj_buf(&mut guarded, &obj_options(), |mtl| {
        tobj::load_mtl(
            path.parent()
                .map_or_else(|| mtl.to_owned(), |p| p.join(mtl)),
        )
    });
    guarded.check(&name)?;
    from_tobj(loaded, &name)
}

/// Loads an OBJ held in memory, like [`load`] but without
/// touching the file system: `mtllib` statements are not followed (the
/// mesh gets a material warning and default colours). `name` names the
/// input in messages.
pub fn load_bytes(bytes: &[u8], name: &str) -> Result<Mesh, ConvertError> {
    let mut guarded = IndexGuard::new(bytes);
    let loaded = tobj::load_obj_buf(&mut guarded, &obj_options(), |_| {
        Err(tobj::LoadError::OpenFileFailed)
    });
    guarded.check(name)?;
    from_tobj(loaded, name)
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
            mesh.texture_files = materials
                .iter()
                .map(|m| m.diffuse_texture.clone())
                .collect();
            mesh.material_names = materials.iter().map(|m| m.name.clone()).collect();
        }
        Err(e) => {
            mesh.material_warning = Some(format!("materials not loaded ({e})"));
        }
    }
    let textured = mesh.texture_files.iter().any(Option::is_some);
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
        if textured {
            // tobj keeps one texture index per position index when the
            // faces have them (and none otherwise).
            let uv_base = mesh.texcoords.len() as u32;
            mesh.texcoords.extend(
                m.texcoords
                    .chunks_exact(2)
                    .map(|c| [f64::from(c[0]), f64::from(c[1])]),
            );
            let count = m.indices.len() / 3;
            if m.texcoord_indices.len() == m.indices.len() {
                mesh.triangle_texcoords.extend(
                    m.texcoord_indices
                        .chunks_exact(3)
                        .map(|t| [t[0], t[1], t[2]].map(|i| i.saturating_add(uv_base))),
                );
            } else {
                mesh.triangle_texcoords
                    .extend(std::iter::repeat_n([u32::MAX; 3], count));
            }
        }
    }
    Ok(mesh)
}

/// Decodes the materials' textures, their file names taken relative to
/// `dir` (the OBJ's folder); one that cannot be read adds a warning and
/// leaves its material with `Kd`. Only `--colors` needs them.
pub fn load_textures(mesh: &mut Mesh, dir: &Path) {
    let mut warnings = Vec::new();
    mesh.textures = mesh
        .texture_files
        .iter()
        .enumerate()
        .map(|(m, file)| {
            let path = texture_path(dir, file.as_deref()?);
            Texture::load(&path)
                .map_err(|e| {
                    let material = mesh.material_names.get(m).map_or("?", String::as_str);
                    warnings.push(format!(
                        "texture {} of material {material} not loaded ({e})",
                        path.display()
                    ));
                })
                .ok()
        })
        .collect();
    mesh.texture_warnings = warnings;
}

/// Where a material's `map_Kd` file is, relative to the OBJ's directory: the
/// name as written, else its last word (the name follows any options such as
/// `-s 1 1 1`), with `\\` read as `/` (files exported on Windows).
fn texture_path(dir: &Path, name: &str) -> std::path::PathBuf {
    let last = name.split_whitespace().last().unwrap_or(name);
    let candidates = [
        name,
        last,
        &name.replace('\\', "/"),
        &last.replace('\\', "/"),
    ]
    .map(|n| dir.join(n));
    candidates
        .iter()
        .find(|c| c.is_file())
        .unwrap_or(&candidates[0])
        .clone()
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
