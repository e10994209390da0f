//! PLY (`.ply`), ASCII and binary in both byte orders, read with `ply-rs-bw`
//! element by element.
//!
//! A file with a non-empty `face` element is a mesh: its faces are polygons
//! (`vertex_indices` or `vertex_index`, any integer list type), triangulated
//! as fans. Without faces the `vertex` element is a point cloud, read in a
//! stream. Vertex positions are `x y z` (any scalar type); vertex colours are
//! `red green blue [alpha]` (also `r g b a` or `diffuse_red` …): unsigned
//! chars as they are, unsigned shorts scaled to 8 bits, floats and doubles
//! in `[0, 1]` scaled by 255. Other elements and properties are skipped.

use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

use ply_rs_bw::parser::{Parser, Reader};
use ply_rs_bw::ply::{
    BeginList, ElementDef, Encoding, Header, Property, PropertyAccess, PropertyAccessResult,
    PropertyType,
};

use super::{CloudPoint, Format, Input, OpenOptions, PointSource};
use crate::error::ConvertError;
use crate::mesh::{DEFAULT_COLOR, Mesh};

/// The registry entry.
pub const FORMAT: Format = Format {
    name: "ply",
    description: "PLY mesh or point cloud (ASCII or binary)",
    extensions: &["ply"],
    magic: Some(|head| head.starts_with(b"ply\n") || head.starts_with(b"ply\r\n")),
    open,
};

fn open(path: &Path, options: &OpenOptions) -> Result<Input, ConvertError> {
    let name = path.display().to_string();
    let file = File::open(path)
        .map_err(|e| ConvertError::Input(format!("cannot read PLY file {name}: {e}")))?;
    let mut reader = Reader::new(BufReader::with_capacity(1 << 20, file));
    let header = read_header(&mut reader, &name)?;
    if header
        .elements
        .get("face")
        .is_some_and(|face| face.count > 0)
    {
        return load_mesh(reader, &header, &name, options.colors).map(|m| Input::Mesh(Box::new(m)));
    }
    let cloud = PlyCloud::new(path.to_path_buf(), name, reader, header)?;
    Ok(Input::Points(Box::new(cloud)))
}

fn parse_error(name: &str, what: &str, e: impl std::fmt::Display) -> ConvertError {
    // ply-rs's messages span lines: only the first is kept.
    let text = e.to_string();
    let first = text.lines().next().unwrap_or("").trim();
    ConvertError::Input(format!("{name}: cannot read PLY {what}: {first}"))
}

fn read_header<R: BufRead>(reader: &mut Reader<R>, name: &str) -> Result<Header, ConvertError> {
    let header = Parser::<Skip>::new()
        .read_header(reader)
        .map_err(|e| parse_error(name, "header", e))?;
    let Some(vertex) = header.elements.get("vertex") else {
        return Err(ConvertError::Input(format!(
            "{name}: the PLY file has no vertex element"
        )));
    };
    for axis in ["x", "y", "z"] {
        match vertex.properties.get(axis).map(|p| &p.data_type) {
            Some(PropertyType::Scalar(_)) => {}
            _ => {
                return Err(ConvertError::Input(format!(
                    "{name}: the PLY vertex element has no scalar property {axis}"
                )));
            }
        }
    }
    Ok(header)
}

/// Whether the vertex element has colour properties.
fn has_colors(vertex: &ElementDef) -> bool {
    vertex
        .properties
        .keys()
        .any(|k| channel(k).is_some_and(|c| c < 3))
}

/// The channel (0 red … 3 alpha) a property names, if any.
fn channel(name: &str) -> Option<usize> {
    match name {
        "red" | "r" | "diffuse_red" => Some(0),
        "green" | "g" | "diffuse_green" => Some(1),
        "blue" | "b" | "diffuse_blue" => Some(2),
        "alpha" | "a" | "diffuse_alpha" => Some(3),
        _ => None,
    }
}

/// An element whose properties are all skipped.
struct Skip;

impl PropertyAccess for Skip {
    fn new() -> Self {
        Skip
    }
}

/// A vertex: position and colour.
struct Vertex {
    position: [f64; 3],
    rgba: [u8; 4],
}

impl Vertex {
    fn set(&mut self, name: &str, value: f64, unit: f64) -> PropertyAccessResult {
        match name {
            "x" => self.position[0] = value,
            "y" => self.position[1] = value,
            "z" => self.position[2] = value,
            _ => match channel(name) {
                Some(c) => {
                    let v = (value * 255.0 / unit).round();
                    // NaN becomes 0.
                    self.rgba[c] = if v >= 0.0 { v.min(255.0) as u8 } else { 0 };
                }
                None => return PropertyAccessResult::Ignored,
            },
        }
        PropertyAccessResult::Set
    }
}

impl PropertyAccess for Vertex {
    fn new() -> Self {
        Vertex {
            position: [0.0; 3],
            rgba: DEFAULT_COLOR,
        }
    }
    fn set_char(&mut self, name: &str, v: i8) -> PropertyAccessResult {
        self.set(name, f64::from(v), 127.0)
    }
    fn set_uchar(&mut self, name: &str, v: u8) -> PropertyAccessResult {
        self.set(name, f64::from(v), 255.0)
    }
    fn set_short(&mut self, name: &str, v: i16) -> PropertyAccessResult {
        self.set(name, f64::from(v), 32767.0)
    }
    fn set_ushort(&mut self, name: &str, v: u16) -> PropertyAccessResult {
        self.set(name, f64::from(v), 65535.0)
    }
    fn set_int(&mut self, name: &str, v: i32) -> PropertyAccessResult {
        self.set(name, f64::from(v), f64::from(i32::MAX))
    }
    fn set_uint(&mut self, name: &str, v: u32) -> PropertyAccessResult {
        self.set(name, f64::from(v), f64::from(u32::MAX))
    }
    fn set_float(&mut self, name: &str, v: f32) -> PropertyAccessResult {
        self.set(name, f64::from(v), 1.0)
    }
    fn set_double(&mut self, name: &str, v: f64) -> PropertyAccessResult {
        self.set(name, v, 1.0)
    }
}

/// A face: its vertex indices (negative ones become `u32::MAX`, out of range).
struct Face {
    indices: Vec<u32>,
    signed: Vec<i32>,
}

fn is_index_list(name: &str) -> bool {
    name == "vertex_indices" || name == "vertex_index"
}

impl PropertyAccess for Face {
    fn new() -> Self {
        Face {
            indices: Vec::new(),
            signed: Vec::new(),
        }
    }
    fn set_property(&mut self, name: &str, property: Property) -> PropertyAccessResult {
        if !is_index_list(name) {
            return PropertyAccessResult::Ignored;
        }
        let to_u32 = |v: i64| u32::try_from(v).unwrap_or(u32::MAX);
        self.indices = match property {
            Property::ListChar(l) => l.into_iter().map(|v| to_u32(v.into())).collect(),
            Property::ListUChar(l) => l.into_iter().map(u32::from).collect(),
            Property::ListShort(l) => l.into_iter().map(|v| to_u32(v.into())).collect(),
            Property::ListUShort(l) => l.into_iter().map(u32::from).collect(),
            Property::ListInt(l) => l.into_iter().map(|v| to_u32(v.into())).collect(),
            Property::ListUInt(l) => l,
            _ => return PropertyAccessResult::UnsupportedType,
        };
        PropertyAccessResult::Set
    }
    fn begin_list_uint(&mut self, name: &str, _len: usize) -> BeginList<'_, u32> {
        if is_index_list(name) {
            BeginList::Fill(&mut self.indices)
        } else {
            BeginList::UseSetter
        }
    }
    fn begin_list_int(&mut self, name: &str, _len: usize) -> BeginList<'_, i32> {
        if is_index_list(name) {
            BeginList::Fill(&mut self.signed)
        } else {
            BeginList::UseSetter
        }
    }
}

impl Face {
    /// The indices, whichever list type they came in.
    fn take(&mut self) -> Vec<u32> {
        if !self.signed.is_empty() {
            self.indices = self
                .signed
                .drain(..)
                .map(|v| u32::try_from(v).unwrap_or(u32::MAX))
                .collect();
        }
        std::mem::take(&mut self.indices)
    }
}

/// Reads one element of `def` from `reader` in the file's encoding.
fn read_element<E: PropertyAccess, R: BufRead>(
    parser: &Parser<E>,
    reader: &mut Reader<R>,
    def: &ElementDef,
    encoding: Encoding,
    line: &mut String,
) -> ply_rs_bw::parser::Result<E> {
    match encoding {
        Encoding::BinaryLittleEndian => parser.read_little_endian_element(reader.get_mut(), def),
        Encoding::BinaryBigEndian => parser.read_big_endian_element(reader.get_mut(), def),
        Encoding::Ascii => {
            line.clear();
            if reader.get_mut().read_line(line)? == 0 {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::UnexpectedEof,
                    "unexpected end of file",
                )
                .into());
            }
            parser.read_ascii_element(line, def)
        }
    }
}

/// Skips every element of `def`.
fn skip_element<R: BufRead>(
    reader: &mut Reader<R>,
    def: &ElementDef,
    encoding: Encoding,
    name: &str,
) -> Result<(), ConvertError> {
    let parser = Parser::<Skip>::new();
    let mut line = String::new();
    for _ in 0..def.count {
        read_element(&parser, reader, def, encoding, &mut line)
            .map_err(|e| parse_error(name, &format!("element {}", def.name), e))?;
    }
    Ok(())
}

fn load_mesh<R: BufRead>(
    mut reader: Reader<R>,
    header: &Header,
    name: &str,
    colors: bool,
) -> Result<Mesh, ConvertError> {
    let mut mesh = Mesh::default();
    let mut line = String::new();
    for (key, def) in &header.elements {
        match key.as_str() {
            "vertex" => {
                let vertex_colors = colors && has_colors(def);
                let parser = Parser::<Vertex>::new();
                mesh.vertices.reserve(def.count.min(1 << 20));
                for i in 0..def.count {
                    let v = read_element(&parser, &mut reader, def, header.encoding, &mut line)
                        .map_err(|e| parse_error(name, &format!("vertex {}", i + 1), e))?;
                    mesh.vertices.push(v.position);
                    if vertex_colors {
                        mesh.vertex_colors.push(v.rgba);
                    }
                }
            }
            "face" => {
                let parser = Parser::<Face>::new();
                mesh.triangles.reserve(def.count.min(1 << 20));
                for i in 0..def.count {
                    let mut f = read_element(&parser, &mut reader, def, header.encoding, &mut line)
                        .map_err(|e| parse_error(name, &format!("face {}", i + 1), e))?;
                    let indices = f.take();
                    // Polygons as fans; fewer than three corners are a point
                    // or a segment (zero-area triangles).
                    match indices.len() {
                        0 => {}
                        1 => mesh.triangles.push([indices[0]; 3]),
                        2 => mesh.triangles.push([indices[0], indices[1], indices[1]]),
                        n => {
                            for k in 1..n - 1 {
                                mesh.triangles
                                    .push([indices[0], indices[k], indices[k + 1]]);
                            }
                        }
                    }
                }
                // The rest of the file is not needed.
                break;
            }
            _ => skip_element(&mut reader, def, header.encoding, name)?,
        }
    }
    if mesh.vertices.len() > u32::MAX as usize {
        return Err(ConvertError::Input(format!(
            "{name}: more than 2^32 vertices"
        )));
    }
    mesh.triangle_material = vec![u32::MAX; mesh.triangles.len()];
    Ok(mesh)
}

/// A PLY point cloud: the vertex element, read in a stream.
struct PlyCloud {
    path: PathBuf,
    name: String,
    reader: Reader<BufReader<Box<dyn Read>>>,
    header: Header,
    /// Vertices read so far.
    read: usize,
    /// Whether the reader is at the first vertex.
    positioned: bool,
    line: String,
}

impl PlyCloud {
    fn new<R: BufRead + 'static>(
        path: PathBuf,
        name: String,
        reader: Reader<R>,
        header: Header,
    ) -> Result<PlyCloud, ConvertError> {
        let inner: Box<dyn Read> = Box::new(reader.into_inner());
        let mut cloud = PlyCloud {
            path,
            name,
            reader: Reader::new(BufReader::with_capacity(1 << 16, inner)),
            header,
            read: 0,
            positioned: false,
            line: String::new(),
        };
        cloud.position()?;
        Ok(cloud)
    }

    fn vertex(&self) -> &ElementDef {
        self.header
            .elements
            .get("vertex")
            .expect("checked when the header was read")
    }

    /// Skips the elements before the vertices.
    fn position(&mut self) -> Result<(), ConvertError> {
        if self.positioned {
            return Ok(());
        }
        let before: Vec<ElementDef> = self
            .header
            .elements
            .values()
            .take_while(|d| d.name != "vertex")
            .cloned()
            .collect();
        for def in &before {
            skip_element(&mut self.reader, def, self.header.encoding, &self.name)?;
        }
        self.positioned = true;
        Ok(())
    }
}

impl PointSource for PlyCloud {
    fn describe(&self) -> String {
        format!(
            "PLY point cloud ({}), {} points{}",
            self.header.encoding,
            self.vertex().count,
            if has_colors(self.vertex()) {
                " with colours"
            } else {
                ""
            }
        )
    }

    fn count(&self) -> u64 {
        self.vertex().count as u64
    }

    fn declared_bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        None
    }

    fn has_colors(&self) -> bool {
        has_colors(self.vertex())
    }

    fn read(&mut self, out: &mut Vec<CloudPoint>, max: usize) -> Result<usize, ConvertError> {
        let def = self.vertex().clone();
        let n = max.min(def.count - self.read);
        let parser = Parser::<Vertex>::new();
        for _ in 0..n {
            let v = read_element(
                &parser,
                &mut self.reader,
                &def,
                self.header.encoding,
                &mut self.line,
            )
            .map_err(|e| parse_error(&self.name, &format!("vertex {}", self.read + 1), e))?;
            self.read += 1;
            super::check_finite(v.position, || format!("point {}", self.read))?;
            out.push(CloudPoint {
                position: v.position,
                rgba: v.rgba,
            });
        }
        Ok(n)
    }

    fn rewind(&mut self) -> Result<(), ConvertError> {
        let file = File::open(&self.path)
            .map_err(|e| ConvertError::Input(format!("cannot read PLY file {}: {e}", self.name)))?;
        let mut reader = Reader::new(BufReader::with_capacity(1 << 20, file));
        let header = read_header(&mut reader, &self.name)?;
        *self = PlyCloud::new(self.path.clone(), self.name.clone(), reader, header)?;
        Ok(())
    }
}

/// Reads a PLY held in memory (for the fuzz harness): a mesh, or the points
/// of a cloud.
pub fn load_bytes(bytes: &[u8], name: &str) -> Result<Input, ConvertError> {
    let owned = bytes.to_vec();
    let mut reader = Reader::new(BufReader::new(std::io::Cursor::new(owned)));
    let header = read_header(&mut reader, name)?;
    if header
        .elements
        .get("face")
        .is_some_and(|face| face.count > 0)
    {
        return load_mesh(reader, &header, name, true).map(|m| Input::Mesh(Box::new(m)));
    }
    let mut cloud = PlyCloud::new(PathBuf::new(), name.to_string(), reader, header)?;
    let mut points = Vec::new();
    while cloud.read(&mut points, 4096)? > 0 {}
    let colors = cloud.has_colors();
    Ok(Input::Points(Box::new(super::MemoryCloud::new(
        points,
        colors,
        cloud.describe(),
    ))))
}
