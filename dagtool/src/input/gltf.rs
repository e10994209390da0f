//! glTF 2.0: `.gltf` (JSON, buffers and images external or embedded as
//! `data:` URIs) and `.glb` (binary), with the `gltf` crate for the
//! document and its validation; the accessors are read here, with every
//! offset checked, so that no bytes can make the reader panic.
//!
//! - Geometry: every mesh instance of the default scene (all scenes when
//!   none is marked default), node transforms (matrices or translation,
//!   rotation, scale) composed down the hierarchy; triangles, strips and
//!   fans (points and lines are skipped); indices u8, u16, u32 or none;
//!   float, normalized and quantized (`KHR_mesh_quantization`) accessors;
//!   sparse accessors.
//! - Colours: `baseColorFactor` × `baseColorTexture` (its texture
//!   coordinate set, the sampler's wrap modes, `KHR_texture_transform`) ×
//!   `COLOR_0`.
//! - Extensions in `extensionsRequired` that change what is read (Draco,
//!   meshopt, KTX2, WebP, …) are refused with a one-line error naming them.

use std::borrow::Cow;
use std::path::Path;

use base64::Engine as _;
use gltf::accessor::{DataType, Dimensions};
use gltf::mesh::Mode;

use super::{Format, Input, OpenOptions};
use crate::error::ConvertError;
use crate::mesh::{DEFAULT_COLOR, Mesh, Texture, Wrap};

/// The binary form's registry entry.
pub const GLB: Format = Format {
    name: "glb",
    description: "binary glTF 2.0",
    extensions: &["glb"],
    magic: Some(|head| head.starts_with(b"glTF")),
    open,
};

/// The JSON form's registry entry (recognised by its extension).
pub const GLTF: Format = Format {
    name: "gltf",
    description: "glTF 2.0 (JSON)",
    extensions: &["gltf"],
    magic: None,
    open,
};

/// Extensions that may be required: they change nothing this reader
/// needs, or it implements them.
const SUPPORTED_REQUIRED: &[&str] = &[
    "KHR_mesh_quantization",
    "KHR_texture_transform",
    "KHR_materials_unlit",
    "KHR_materials_emissive_strength",
    "KHR_materials_ior",
    "KHR_materials_specular",
    "KHR_materials_transmission",
    "KHR_materials_volume",
    "KHR_materials_clearcoat",
    "KHR_materials_sheen",
    "KHR_materials_iridescence",
    "KHR_materials_anisotropy",
    "KHR_materials_dispersion",
    "KHR_materials_variants",
    "KHR_lights_punctual",
];

fn open(path: &Path, options: &OpenOptions) -> Result<Input, ConvertError> {
    let bytes = super::read_file(path, "glTF file")?;
    let dir = path.parent().unwrap_or(Path::new(""));
    let name = path.display().to_string();
    load_bytes(&bytes, &name, Some(dir), options.colors).map(|m| Input::Mesh(Box::new(m)))
}

/// A one-line error about `name`.
fn bad(name: &str, message: impl std::fmt::Display) -> ConvertError {
    let text = message.to_string();
    let first = text.lines().next().unwrap_or("").trim();
    ConvertError::Input(format!("{name}: {first}"))
}

/// Reads a glTF or GLB held in memory. External files (buffers, images) are
/// read relative to `dir`; with `None` (the fuzz harness) they are refused.
/// Textures are decoded only for `colors`.
pub fn load_bytes(
    bytes: &[u8],
    name: &str,
    dir: Option<&Path>,
    colors: bool,
) -> Result<Mesh, ConvertError> {
    let (json, blob): (Cow<'_, [u8]>, Option<Cow<'_, [u8]>>) = if bytes.starts_with(b"glTF") {
        // The gltf crate subtracts the header's size from the declared
        // length unchecked: a length below a header and one chunk header is
        // refused first.
        let declared = bytes
            .get(8..12)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize);
        match declared {
            Some(n) if (20..=bytes.len()).contains(&n) => {}
            _ => {
                return Err(bad(
                    name,
                    format!(
                        "cannot read GLB: declared length {declared:?} is not between 20 and the file's {} bytes",
                        bytes.len()
                    ),
                ));
            }
        }
        let glb = gltf::binary::Glb::from_slice(bytes)
            .map_err(|e| bad(name, format!("cannot read GLB: {e}")))?;
        (glb.json, glb.bin)
    } else {
        (Cow::Borrowed(bytes), None)
    };
    let mut root: gltf::json::Root = gltf::json::deserialize::from_slice(&json)
        .map_err(|e| bad(name, format!("cannot read glTF JSON: {e}")))?;
    let unsupported: Vec<&str> = root
        .extensions_required
        .iter()
        .map(String::as_str)
        .filter(|e| !SUPPORTED_REQUIRED.contains(e))
        .collect();
    if !unsupported.is_empty() {
        return Err(bad(
            name,
            format!(
                "the glTF file requires the unsupported extension{} {}",
                if unsupported.len() == 1 { "" } else { "s" },
                unsupported.join(", ")
            ),
        ));
    }
    // The gltf crate validates only the extensions it knows itself; the
    // check above replaces its own.
    root.extensions_required.clear();
    // Its validation reads each POSITION accessor before checking that it
    // exists (gltf-json 1.4 panics there), so that is checked first.
    // Image::source unwraps the MIME type of an image in a buffer view and
    // the URI of any other.
    for (i, image) in root.images.iter().enumerate() {
        let complete = if image.buffer_view.is_some() {
            image.mime_type.is_some()
        } else {
            image.uri.is_some()
        };
        if !complete {
            return Err(bad(
                name,
                format!(
                    "invalid glTF: image {i} has neither a URI nor a buffer view with a MIME type"
                ),
            ));
        }
    }
    for (m, mesh) in root.meshes.iter().enumerate() {
        for (p, primitive) in mesh.primitives.iter().enumerate() {
            for index in primitive.attributes.values() {
                if index.value() >= root.accessors.len() {
                    return Err(bad(
                        name,
                        format!(
                            "invalid glTF: mesh {m} primitive {p} uses accessor {} but there are only {}",
                            index.value(),
                            root.accessors.len()
                        ),
                    ));
                }
            }
        }
    }
    let document =
        gltf::Document::from_json(root).map_err(|e| bad(name, format!("invalid glTF: {e}")))?;
    let buffers = load_buffers(&document, blob.as_deref(), name, dir)?;
    let mut loader = Loader {
        name,
        buffers: &buffers,
        mesh: Mesh::default(),
        colors,
        any_vertex_colors: false,
        material_ids: vec![None; document.materials().len() + 1],
        textures: Vec::new(),
        dir,
    };
    let scenes: Vec<gltf::Scene<'_>> = match document.default_scene() {
        Some(s) => vec![s],
        None => document.scenes().collect(),
    };
    for scene in scenes {
        for node in scene.nodes() {
            loader.node(&node, IDENTITY, 0)?;
        }
    }
    let mut mesh = loader.mesh;
    if !loader.any_vertex_colors {
        mesh.vertex_colors.clear();
    }
    if mesh.triangle_texcoords.iter().all(|t| t[0] == u32::MAX) {
        mesh.triangle_texcoords.clear();
    }
    Ok(mesh)
}

/// Percent-decodes a relative URI into a path.
fn uri_path(uri: &str) -> String {
    percent_encoding::percent_decode_str(uri)
        .decode_utf8_lossy()
        .into_owned()
}

/// The bytes a `data:` URI holds, or `None` for other URIs.
fn data_uri(uri: &str, name: &str) -> Option<Result<Vec<u8>, ConvertError>> {
    let rest = uri.strip_prefix("data:")?;
    let Some((meta, data)) = rest.split_once(',') else {
        return Some(Err(bad(name, "a data URI has no comma")));
    };
    Some(if meta.ends_with(";base64") {
        base64::engine::general_purpose::STANDARD
            .decode(data)
            .map_err(|e| bad(name, format!("a data URI is not valid base64: {e}")))
    } else {
        Ok(percent_encoding::percent_decode_str(data).collect())
    })
}

/// Reads an external file named by a URI, relative to `dir`.
fn external(
    uri: &str,
    what: &str,
    name: &str,
    dir: Option<&Path>,
) -> Result<Vec<u8>, ConvertError> {
    if let Some(bytes) = data_uri(uri, name) {
        return bytes;
    }
    let Some(dir) = dir else {
        return Err(bad(name, format!("{what} {uri} is an external file")));
    };
    if uri.contains("://") {
        return Err(bad(name, format!("{what} {uri} is not a local file")));
    }
    let path = dir.join(uri_path(uri));
    match std::fs::metadata(&path) {
        Ok(m) if m.is_file() => {}
        Ok(_) => {
            return Err(bad(
                name,
                format!("{what} {} is not a regular file", path.display()),
            ));
        }
        Err(e) => {
            return Err(bad(
                name,
                format!("cannot read {what} {}: {e}", path.display()),
            ));
        }
    }
    std::fs::read(&path)
        .map_err(|e| bad(name, format!("cannot read {what} {}: {e}", path.display())))
}

fn load_buffers(
    document: &gltf::Document,
    blob: Option<&[u8]>,
    name: &str,
    dir: Option<&Path>,
) -> Result<Vec<Vec<u8>>, ConvertError> {
    document
        .buffers()
        .map(|buffer| {
            let data = match buffer.source() {
                gltf::buffer::Source::Bin => blob
                    .ok_or_else(|| {
                        bad(
                            name,
                            "the glTF buffer refers to a GLB binary chunk the file does not have",
                        )
                    })?
                    .to_vec(),
                gltf::buffer::Source::Uri(uri) => external(uri, "buffer", name, dir)?,
            };
            if data.len() < buffer.length() {
                return Err(bad(
                    name,
                    format!(
                        "buffer {} has {} bytes, fewer than its declared {}",
                        buffer.index(),
                        data.len(),
                        buffer.length()
                    ),
                ));
            }
            Ok(data)
        })
        .collect()
}

/// A column-major 4×4 matrix.
type Matrix = [[f64; 4]; 4];

const IDENTITY: Matrix = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

/// `a b` for column-major matrices.
fn mul(a: &Matrix, b: &Matrix) -> Matrix {
    let mut m = [[0.0; 4]; 4];
    for (c, col) in m.iter_mut().enumerate() {
        for (r, cell) in col.iter_mut().enumerate() {
            *cell = (0..4).map(|k| a[k][r] * b[c][k]).sum();
        }
    }
    m
}

fn transform_point(m: &Matrix, p: [f64; 3]) -> [f64; 3] {
    [0, 1, 2].map(|r| m[0][r] * p[0] + m[1][r] * p[1] + m[2][r] * p[2] + m[3][r])
}

/// A node's local transform in f64: the matrix as given, or T R S.
fn local_matrix(node: &gltf::Node<'_>) -> Matrix {
    match node.transform() {
        gltf::scene::Transform::Matrix { matrix } => matrix.map(|c| c.map(f64::from)),
        gltf::scene::Transform::Decomposed {
            translation,
            rotation,
            scale,
        } => {
            let [x, y, z, w] = rotation.map(f64::from);
            // Normalised, so that a slightly off quaternion stays a rotation.
            let n = (x * x + y * y + z * z + w * w).sqrt();
            let (x, y, z, w) = if n > 0.0 {
                (x / n, y / n, z / n, w / n)
            } else {
                (0.0, 0.0, 0.0, 1.0)
            };
            let r = [
                [
                    1.0 - 2.0 * (y * y + z * z),
                    2.0 * (x * y + z * w),
                    2.0 * (x * z - y * w),
                ],
                [
                    2.0 * (x * y - z * w),
                    1.0 - 2.0 * (x * x + z * z),
                    2.0 * (y * z + x * w),
                ],
                [
                    2.0 * (x * z + y * w),
                    2.0 * (y * z - x * w),
                    1.0 - 2.0 * (x * x + y * y),
                ],
            ];
            let s = scale.map(f64::from);
            let t = translation.map(f64::from);
            [
                [r[0][0] * s[0], r[0][1] * s[0], r[0][2] * s[0], 0.0],
                [r[1][0] * s[1], r[1][1] * s[1], r[1][2] * s[1], 0.0],
                [r[2][0] * s[2], r[2][1] * s[2], r[2][2] * s[2], 0.0],
                [t[0], t[1], t[2], 1.0],
            ]
        }
    }
}

/// The deepest node hierarchy walked (glTF forbids cycles; validation
/// checks indices, not cycles).
const MAX_NODE_DEPTH: usize = 256;

struct Loader<'a> {
    name: &'a str,
    buffers: &'a [Vec<u8>],
    mesh: Mesh,
    colors: bool,
    any_vertex_colors: bool,
    /// The mesh's material index of each glTF material (the last entry: the
    /// default material), once made.
    material_ids: Vec<Option<u32>>,
    /// Decoded textures by glTF texture index.
    textures: Vec<(usize, Texture)>,
    dir: Option<&'a Path>,
}

impl Loader<'_> {
    fn node(
        &mut self,
        node: &gltf::Node<'_>,
        parent: Matrix,
        level: usize,
    ) -> Result<(), ConvertError> {
        if level > MAX_NODE_DEPTH {
            return Err(bad(
                self.name,
                format!("the node hierarchy is deeper than {MAX_NODE_DEPTH} (or has a cycle)"),
            ));
        }
        let world = mul(&parent, &local_matrix(node));
        if let Some(mesh) = node.mesh() {
            for primitive in mesh.primitives() {
                self.primitive(&primitive, &world)?;
            }
        }
        for child in node.children() {
            self.node(&child, world, level + 1)?;
        }
        Ok(())
    }

    fn primitive(
        &mut self,
        primitive: &gltf::Primitive<'_>,
        world: &Matrix,
    ) -> Result<(), ConvertError> {
        let mode = primitive.mode();
        if matches!(
            mode,
            Mode::Points | Mode::Lines | Mode::LineLoop | Mode::LineStrip
        ) {
            return Ok(());
        }
        let Some(positions) = primitive.get(&gltf::Semantic::Positions) else {
            return Ok(());
        };
        let positions = read_accessor(&positions, self.buffers, self.name)?;
        let count = positions.len();
        let base = self.mesh.vertices.len();
        if base + count > u32::MAX as usize {
            return Err(bad(self.name, "more than 2^32 vertices"));
        }
        for p in &positions {
            let q = transform_point(world, [p[0], p[1], p[2]]);
            self.mesh.vertices.push(q);
        }
        let indices: Vec<u32> = match primitive.indices() {
            Some(a) => {
                if a.dimensions() != Dimensions::Scalar
                    || !matches!(a.data_type(), DataType::U8 | DataType::U16 | DataType::U32)
                {
                    return Err(bad(
                        self.name,
                        format!("index accessor {} is not of unsigned integers", a.index()),
                    ));
                }
                let values = read_accessor(&a, self.buffers, self.name)?;
                let mut out = Vec::with_capacity(values.len());
                for v in values {
                    let i = v[0] as u64;
                    if i >= count as u64 {
                        return Err(bad(
                            self.name,
                            format!(
                                "index {i} of accessor {} is out of range ({count} vertices)",
                                a.index()
                            ),
                        ));
                    }
                    out.push(i as u32);
                }
                out
            }
            None => (0..count as u32).collect(),
        };
        let triangles: Vec<[u32; 3]> = match mode {
            Mode::Triangles => indices
                .chunks_exact(3)
                .map(|t| [t[0], t[1], t[2]])
                .collect(),
            Mode::TriangleStrip => (2..indices.len())
                .map(|i| {
                    // Every other triangle is flipped to keep the winding.
                    if i % 2 == 0 {
                        [indices[i - 2], indices[i - 1], indices[i]]
                    } else {
                        [indices[i - 1], indices[i - 2], indices[i]]
                    }
                })
                .collect(),
            Mode::TriangleFan => (2..indices.len())
                .map(|i| [indices[0], indices[i - 1], indices[i]])
                .collect(),
            _ => Vec::new(),
        };
        let b = base as u32;
        // Colours: the material, its texture coordinates, COLOR_0.
        let material = if self.colors {
            self.material(&primitive.material())?
        } else {
            u32::MAX
        };
        let uv_set = primitive
            .material()
            .pbr_metallic_roughness()
            .base_color_texture()
            .map(|info| {
                let transform = info.texture_transform();
                let set = transform
                    .as_ref()
                    .and_then(|t| t.tex_coord())
                    .unwrap_or(info.tex_coord());
                (
                    set,
                    transform.map(|t| (t.offset(), t.rotation(), t.scale())),
                )
            });
        let uv_base = self.mesh.texcoords.len() as u32;
        let mut has_uv = false;
        if self.colors
            && let Some((set, transform)) = uv_set
            && let Some(accessor) = primitive.get(&gltf::Semantic::TexCoords(set))
        {
            let uvs = read_accessor(&accessor, self.buffers, self.name)?;
            if uvs.len() == count {
                has_uv = true;
                for uv in uvs {
                    let (mut u, mut v) = (uv[0], uv[1]);
                    if let Some((offset, rotation, scale)) = transform {
                        // KHR_texture_transform: T R S, with the rotation
                        // counter-clockwise in UV space (v down).
                        let (su, sv) = (u * f64::from(scale[0]), v * f64::from(scale[1]));
                        let (s, c) = f64::from(rotation).sin_cos();
                        u = c * su + s * sv + f64::from(offset[0]);
                        v = -s * su + c * sv + f64::from(offset[1]);
                    }
                    // glTF's v runs down the image; the mesh's runs up.
                    self.mesh.texcoords.push([u, 1.0 - v]);
                }
            }
        }
        let color_attr = if self.colors {
            primitive.get(&gltf::Semantic::Colors(0))
        } else {
            None
        };
        match color_attr {
            Some(accessor) => {
                let colors = read_accessor(&accessor, self.buffers, self.name)?;
                if colors.len() != count {
                    return Err(bad(
                        self.name,
                        format!(
                            "COLOR_0 accessor {} has {} values for {count} vertices",
                            accessor.index(),
                            colors.len()
                        ),
                    ));
                }
                self.pad_vertex_colors(base);
                self.any_vertex_colors = true;
                for c in colors {
                    let alpha = if accessor.dimensions() == Dimensions::Vec4 {
                        c[3]
                    } else {
                        1.0
                    };
                    self.mesh.vertex_colors.push(
                        [c[0], c[1], c[2], alpha]
                            .map(|x| (x.clamp(0.0, 1.0) * 255.0).round() as u8),
                    );
                }
            }
            None if self.any_vertex_colors => self.pad_vertex_colors(base + count),
            None => {}
        }
        for t in triangles {
            self.mesh.triangles.push(t.map(|i| i + b));
            self.mesh.triangle_material.push(material);
            if self.colors {
                self.mesh.triangle_texcoords.push(if has_uv {
                    t.map(|i| i + uv_base)
                } else {
                    [u32::MAX; 3]
                });
            }
        }
        Ok(())
    }

    /// Fills the vertex colours with white up to `len` vertices (vertices
    /// of primitives without `COLOR_0`).
    fn pad_vertex_colors(&mut self, len: usize) {
        let n = len.max(self.mesh.vertex_colors.len());
        self.mesh.vertex_colors.resize(n, DEFAULT_COLOR);
    }

    /// The mesh's material for a glTF material: its base colour factor and
    /// texture.
    fn material(&mut self, material: &gltf::Material<'_>) -> Result<u32, ConvertError> {
        let slot = material.index().unwrap_or(self.material_ids.len() - 1);
        if let Some(id) = self.material_ids.get(slot).copied().flatten() {
            return Ok(id);
        }
        let pbr = material.pbr_metallic_roughness();
        let factor = pbr
            .base_color_factor()
            .map(|c| (f64::from(c).clamp(0.0, 1.0) * 255.0).round() as u8);
        let texture = match pbr.base_color_texture() {
            Some(info) => Some(self.texture(&info.texture())?),
            None => None,
        };
        let id = self.mesh.colors.len() as u32;
        self.mesh.colors.push(factor);
        self.mesh.texture_files.push(None);
        self.mesh.textures.push(texture);
        self.mesh.material_names.push(
            material
                .index()
                .map_or("(default)".to_string(), |i| format!("{i}")),
        );
        if let Some(s) = self.material_ids.get_mut(slot) {
            *s = Some(id);
        }
        Ok(id)
    }

    /// A glTF texture decoded, with its sampler's wrap modes. Unlike an OBJ
    /// material's, a texture that cannot be read is an error: glTF names its
    /// files exactly, so a missing one is a broken file.
    fn texture(&mut self, texture: &gltf::Texture<'_>) -> Result<Texture, ConvertError> {
        if let Some((_, t)) = self.textures.iter().find(|(i, _)| *i == texture.index()) {
            return Ok(t.clone());
        }
        let wrap = |m: gltf::texture::WrappingMode| match m {
            gltf::texture::WrappingMode::ClampToEdge => Wrap::ClampToEdge,
            gltf::texture::WrappingMode::MirroredRepeat => Wrap::MirroredRepeat,
            gltf::texture::WrappingMode::Repeat => Wrap::Repeat,
        };
        let sampler = texture.sampler();
        let image = texture.source();
        let bytes = match image.source() {
            gltf::image::Source::View { view, .. } => {
                view_bytes(&view, self.buffers, self.name).map(<[u8]>::to_vec)
            }
            gltf::image::Source::Uri { uri, .. } => external(uri, "image", self.name, self.dir),
        };
        let decoded = Texture::decode(&bytes?).map_err(|e| {
            bad(
                self.name,
                format!(
                    "cannot decode image {} of texture {}: {e}",
                    image.index(),
                    texture.index()
                ),
            )
        })?;
        let result = decoded.with_wrap([wrap(sampler.wrap_s()), wrap(sampler.wrap_t())]);
        self.textures.push((texture.index(), result.clone()));
        Ok(result)
    }
}

/// The bytes of a buffer view, checked against its buffer.
fn view_bytes<'b>(
    view: &gltf::buffer::View<'_>,
    buffers: &'b [Vec<u8>],
    name: &str,
) -> Result<&'b [u8], ConvertError> {
    let buffer = buffers
        .get(view.buffer().index())
        .ok_or_else(|| bad(name, format!("buffer view {} has no buffer", view.index())))?;
    let start = view.offset();
    start
        .checked_add(view.length())
        .and_then(|end| buffer.get(start..end))
        .ok_or_else(|| {
            bad(
                name,
                format!("buffer view {} lies outside its buffer", view.index()),
            )
        })
}

/// One component of type `t` at `bytes[0..]`, as f64, normalized when asked
/// (glTF's rules: signed values are max(c / MAX, -1)).
fn component(bytes: &[u8], t: DataType, normalized: bool) -> f64 {
    match t {
        DataType::I8 => {
            let v = f64::from(bytes[0] as i8);
            if normalized { (v / 127.0).max(-1.0) } else { v }
        }
        DataType::U8 => {
            let v = f64::from(bytes[0]);
            if normalized { v / 255.0 } else { v }
        }
        DataType::I16 => {
            let v = f64::from(i16::from_le_bytes([bytes[0], bytes[1]]));
            if normalized {
                (v / 32767.0).max(-1.0)
            } else {
                v
            }
        }
        DataType::U16 => {
            let v = f64::from(u16::from_le_bytes([bytes[0], bytes[1]]));
            if normalized { v / 65535.0 } else { v }
        }
        DataType::U32 => {
            let v = f64::from(u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]));
            if normalized {
                v / f64::from(u32::MAX)
            } else {
                v
            }
        }
        DataType::F32 => f64::from(f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]])),
    }
}

/// Reads every element of an accessor (up to 4 components, as f64), with
/// its sparse substitutions; every byte range is checked.
fn read_accessor(
    accessor: &gltf::Accessor<'_>,
    buffers: &[Vec<u8>],
    name: &str,
) -> Result<Vec<[f64; 4]>, ConvertError> {
    let t = accessor.data_type();
    let n = accessor.dimensions().multiplicity();
    if n > 4 {
        return Err(bad(
            name,
            format!("accessor {} is a matrix", accessor.index()),
        ));
    }
    let size = t.size();
    let normalized = accessor.normalized();
    let count = accessor.count();
    let read = |bytes: &[u8], at: usize| -> [f64; 4] {
        let mut v = [0.0; 4];
        for (k, slot) in v.iter_mut().enumerate().take(n) {
            *slot = component(&bytes[at + k * size..], t, normalized);
        }
        v
    };
    let mut out = match accessor.view() {
        None => {
            if count > 1 << 24 {
                return Err(bad(
                    name,
                    format!("accessor {} has {count} elements", accessor.index()),
                ));
            }
            vec![[0.0; 4]; count]
        }
        Some(view) => {
            let bytes = view_bytes(&view, buffers, name)?;
            let element = n * size;
            let stride = view.stride().unwrap_or(element);
            let offset = accessor.offset();
            let fits = count == 0
                || (count - 1)
                    .checked_mul(stride)
                    .and_then(|x| x.checked_add(offset))
                    .and_then(|x| x.checked_add(element))
                    .is_some_and(|end| end <= bytes.len());
            if stride < element || !fits {
                return Err(bad(
                    name,
                    format!(
                        "accessor {} does not fit in buffer view {}",
                        accessor.index(),
                        view.index()
                    ),
                ));
            }
            (0..count)
                .map(|i| read(bytes, offset + i * stride))
                .collect()
        }
    };
    if let Some(sparse) = accessor.sparse() {
        let k = sparse.count();
        let idx = sparse.indices();
        let vals = sparse.values();
        let ibytes = view_bytes(&idx.view(), buffers, name)?;
        let vbytes = view_bytes(&vals.view(), buffers, name)?;
        let isize = match idx.index_type() {
            gltf::accessor::sparse::IndexType::U8 => 1,
            gltf::accessor::sparse::IndexType::U16 => 2,
            gltf::accessor::sparse::IndexType::U32 => 4,
        };
        let element = n * size;
        let ifits = k
            .checked_mul(isize)
            .and_then(|x| x.checked_add(idx.offset()))
            .is_some_and(|e| e <= ibytes.len());
        let vfits = k
            .checked_mul(element)
            .and_then(|x| x.checked_add(vals.offset()))
            .is_some_and(|e| e <= vbytes.len());
        if !ifits || !vfits {
            return Err(bad(
                name,
                format!(
                    "sparse accessor {} does not fit in its buffer views",
                    accessor.index()
                ),
            ));
        }
        for j in 0..k {
            let at = idx.offset() + j * isize;
            let i = match isize {
                1 => usize::from(ibytes[at]),
                2 => usize::from(u16::from_le_bytes([ibytes[at], ibytes[at + 1]])),
                _ => {
                    u32::from_le_bytes([ibytes[at], ibytes[at + 1], ibytes[at + 2], ibytes[at + 3]])
                        as usize
                }
            };
            let Some(slot) = out.get_mut(i) else {
                return Err(bad(
                    name,
                    format!(
                        "sparse accessor {} substitutes element {i} of {count}",
                        accessor.index()
                    ),
                ));
            };
            *slot = read(vbytes, vals.offset() + j * element);
        }
    }
    Ok(out)
}
