//! LAS 1.0–1.4 point clouds (`.las`), plain or LAZ-compressed (`.laz`), in
//! point formats 0–10, read with the `las` crate in batches.
//!
//! Points are scaled and offset as the header says. Colours (formats 2, 3, 5,
//! 7, 8 and 10) are 16-bit per channel in LAS and become 8-bit as
//! `round(v / 257)` (65535 ↦ 255); formats without colours are white. The
//! header's bounding box places the cloud without a first pass over the
//! points; a point outside it (beyond one coordinate quantum) is an error.

use std::path::{Path, PathBuf};

use las::{PointData, PointDataBuilder, Reader};

use super::{CloudPoint, Format, Input, OpenOptions, PointSource};
use crate::error::ConvertError;
use crate::mesh::DEFAULT_COLOR;

/// The registry entry.
pub const FORMAT: Format = Format {
    name: "las",
    description: "LAS or LAZ point cloud",
    extensions: &["las", "laz"],
    magic: Some(|head| head.starts_with(b"LASF")),
    open,
};

fn open(path: &Path, _options: &OpenOptions) -> Result<Input, ConvertError> {
    Ok(Input::Points(Box::new(LasCloud::open(path)?)))
}

/// An 8-bit channel of a 16-bit LAS colour channel: `round(v / 257)`.
pub fn channel_8bit(v: u16) -> u8 {
    ((u32::from(v) + 128) / 257) as u8
}

fn las_error(name: &str, e: las::Error) -> ConvertError {
    let text = e.to_string();
    let first = text.lines().next().unwrap_or("").trim();
    ConvertError::Input(format!("{name}: cannot read LAS: {first}"))
}

/// A LAS or LAZ file read in batches.
pub struct LasCloud {
    path: PathBuf,
    name: String,
    reader: Reader,
    data: PointData,
    count: u64,
    read: u64,
    colors: bool,
    bounds: ([f64; 3], [f64; 3]),
    description: String,
}

/// Checks the raw header before the `las` reader sees it: the end of the
/// points must be representable (the reader computes it unchecked) and, in
/// an uncompressed file, within the file (a truncated file is refused
/// before any point is read).
fn check_header<R: std::io::Read + std::io::Seek>(
    mut head: R,
    len: u64,
    name: &str,
) -> Result<(), ConvertError> {
    let raw = las::raw::Header::read_from(&mut head).map_err(|e| las_error(name, e))?;
    // The reader's rule: the legacy count unless it is 0 in a LAS 1.4 file.
    let points = match raw.large_file {
        Some(lf) if raw.number_of_point_records == 0 => lf.number_of_point_records,
        _ => u64::from(raw.number_of_point_records),
    };
    let end = u64::from(raw.point_data_record_length)
        .checked_mul(points)
        .and_then(|b| b.checked_add(u64::from(raw.offset_to_point_data)));
    let compressed = raw.point_data_record_format & 0x80 != 0;
    if let Some(evlr) = raw.evlr {
        check_evlr(&mut head, evlr.start_of_first_evlr, len, name)?;
    }
    match end {
        None => Err(ConvertError::Input(format!(
            "{name}: the LAS header declares {} points of {} bytes, more than a file can hold",
            points, raw.point_data_record_length
        ))),
        Some(end) if !compressed && end > len => Err(ConvertError::Input(format!(
            "{name}: the LAS file has {len} bytes but its {points} points end at byte {end} (truncated?)"
        ))),
        Some(_) if compressed => {
            check_chunk_table(&mut head, raw.offset_to_point_data, len, name)?;
            check_chunk_entries(&mut head, &raw, len, name)
        }
        Some(_) => Ok(()),
    }
}

/// LAS 1.4: the extended record the `las` reader reads at
/// `start_of_first_evlr` must fit in the file, because the reader sizes its
/// buffer from the record's 64-bit length before reading it (a mutated length
/// asked for 52 TB).
fn check_evlr<R: std::io::Read + std::io::Seek>(
    mut file: R,
    start: u64,
    len: u64,
    name: &str,
) -> Result<(), ConvertError> {
    // reserved u16, user ID [u8; 16], record ID u16, then the u64 length.
    const LENGTH_AT: u64 = 20;
    const HEADER: u64 = 60;
    let mut word = [0u8; 8];
    let readable = start
        .checked_add(LENGTH_AT)
        .filter(|&at| at.checked_add(8).is_some_and(|end| end <= len))
        .is_some_and(|at| {
            file.seek(std::io::SeekFrom::Start(at)).is_ok() && file.read_exact(&mut word).is_ok()
        });
    if !readable {
        // The `las` reader reports the missing record itself.
        return Ok(());
    }
    let length = u64::from_le_bytes(word);
    if start
        .checked_add(HEADER)
        .and_then(|e| e.checked_add(length))
        .is_none_or(|end| end > len)
    {
        return Err(ConvertError::Input(format!(
            "{name}: the extended variable-length record at byte {start} declares {length} bytes, more than the file's {len} bytes hold"
        )));
    }
    Ok(())
}

/// LAZ: the chunk table's entries, which the `laz` decompressor trusts: it
/// sizes a buffer to the sum of the byte counts of the chunks it reads at
/// once (a sum past `isize::MAX` is a capacity-overflow panic inside the
/// crate), so the byte counts must add up to no more than the file holds and
/// variable-size chunks to no more points than the header declares.
fn check_chunk_entries<R: std::io::Read + std::io::Seek>(
    mut file: R,
    raw: &las::raw::Header,
    len: u64,
    name: &str,
) -> Result<(), ConvertError> {
    use std::io::SeekFrom;
    let bad = |what: String| ConvertError::Input(format!("{name}: {what}"));
    file.seek(SeekFrom::Start(u64::from(raw.header_size)))
        .map_err(|e| bad(format!("cannot read the LAS records: {e}")))?;
    let mut laszip = None;
    for _ in 0..raw.number_of_variable_length_records {
        let Ok(vlr) = las::raw::Vlr::read_from(&mut file, false) else {
            // The `las` reader reports a damaged record itself.
            return Ok(());
        };
        let user = vlr.user_id.split(|&b| b == 0).next().unwrap_or(&[]);
        if user == laz::LazVlr::USER_ID.as_bytes() && vlr.record_id == laz::LazVlr::RECORD_ID {
            laszip = Some(vlr);
            break;
        }
    }
    // Without its record the `las` reader refuses the file with its own error.
    let Some(record) = laszip else { return Ok(()) };
    let Ok(vlr) = laz::LazVlr::from_buffer(&record.data) else {
        return Ok(());
    };
    // The decompressor asserts that the points the `las` reader asks for
    // (records of the header's length) are whole records of its items.
    let items: u64 = vlr.items().iter().map(|item| u64::from(item.size())).sum();
    if items != u64::from(raw.point_data_record_length) {
        return Err(bad(format!(
            "the LAZ record's items make points of {items} bytes, but the header says {}",
            raw.point_data_record_length
        )));
    }
    file.seek(SeekFrom::Start(u64::from(raw.offset_to_point_data)))
        .map_err(|e| bad(format!("cannot read the LAZ chunk table: {e}")))?;
    let table = laz::laszip::ChunkTable::read_from(&mut file, &vlr)
        .map_err(|e| bad(format!("cannot read the LAZ chunk table: {e}")))?;
    let mut bytes = 0u64;
    let mut points = 0u64;
    for entry in table.as_ref() {
        bytes = bytes.saturating_add(entry.byte_count);
        points = points.saturating_add(entry.point_count);
    }
    if bytes > len {
        return Err(bad(format!(
            "the LAZ chunk table declares {bytes} bytes of chunks, more than the file's {len} bytes"
        )));
    }
    let declared = match raw.large_file {
        Some(lf) if raw.number_of_point_records == 0 => lf.number_of_point_records,
        _ => u64::from(raw.number_of_point_records),
    };
    if vlr.uses_variable_size_chunks() && points > declared {
        return Err(bad(format!(
            "the LAZ chunk table declares {points} points in its chunks, more than the header's {declared}"
        )));
    }
    Ok(())
}

/// LAZ: the chunk table's entry count, which the `laz` reader allocates
/// for before reading the entries, must fit in the file.
fn check_chunk_table<R: std::io::Read + std::io::Seek>(
    mut file: R,
    offset_to_point_data: u32,
    len: u64,
    name: &str,
) -> Result<(), ConvertError> {
    use std::io::SeekFrom;
    let mut word = [0u8; 8];
    let io = |e: std::io::Error| {
        ConvertError::Input(format!("{name}: cannot read the LAZ chunk table: {e}"))
    };
    file.seek(SeekFrom::Start(u64::from(offset_to_point_data)))
        .map_err(io)?;
    file.read_exact(&mut word).map_err(io)?;
    let table = i64::from_le_bytes(word);
    // -1: the table's offset is at the end of the file (written last).
    let table = if table == -1 {
        let end = len
            .checked_sub(8)
            .ok_or_else(|| io(std::io::ErrorKind::UnexpectedEof.into()))?;
        file.seek(SeekFrom::Start(end)).map_err(io)?;
        file.read_exact(&mut word).map_err(io)?;
        i64::from_le_bytes(word)
    } else {
        table
    };
    let Ok(table) = u64::try_from(table) else {
        return Err(ConvertError::Input(format!(
            "{name}: the LAZ chunk table offset {table} is negative"
        )));
    };
    if table.checked_add(8).is_none_or(|end| end > len) {
        return Err(ConvertError::Input(format!(
            "{name}: the LAZ chunk table at byte {table} lies beyond the file's {len} bytes (truncated?)"
        )));
    }
    file.seek(SeekFrom::Start(table)).map_err(io)?;
    file.read_exact(&mut word).map_err(io)?;
    let chunks = u64::from(u32::from_le_bytes([word[4], word[5], word[6], word[7]]));
    if chunks > len - table {
        return Err(ConvertError::Input(format!(
            "{name}: the LAZ chunk table declares {chunks} chunks, more than its {} bytes can hold",
            len - table
        )));
    }
    Ok(())
}

/// Reads a LAS or LAZ held in memory (for the fuzz harness), at most a
/// million points.
pub fn load_bytes(bytes: &[u8], name: &str) -> Result<Box<dyn PointSource>, ConvertError> {
    check_header(std::io::Cursor::new(bytes), bytes.len() as u64, name)?;
    let reader =
        Reader::new(std::io::Cursor::new(bytes.to_vec())).map_err(|e| las_error(name, e))?;
    let mut cloud = LasCloud::from_reader(reader, PathBuf::new(), name.to_string())?;
    if cloud.count > 1 << 20 {
        return Err(ConvertError::Input(format!(
            "{name}: too many points for the harness"
        )));
    }
    let mut points = Vec::new();
    while cloud.read(&mut points, 4096)? > 0 {}
    Ok(Box::new(super::MemoryCloud::new(
        points,
        cloud.colors,
        cloud.describe(),
    )))
}

impl LasCloud {
    /// Opens a LAS or LAZ file.
    pub fn open(path: &Path) -> Result<LasCloud, ConvertError> {
        let name = path.display().to_string();
        let file = std::fs::File::open(path)
            .map_err(|e| ConvertError::Input(format!("cannot read LAS file {name}: {e}")))?;
        let len = file.metadata().map(|m| m.len()).unwrap_or(u64::MAX);
        check_header(std::io::BufReader::new(file), len, &name)?;
        let reader = Reader::from_path(path).map_err(|e| las_error(&name, e))?;
        LasCloud::from_reader(reader, path.to_path_buf(), name)
    }

    fn from_reader(reader: Reader, path: PathBuf, name: String) -> Result<LasCloud, ConvertError> {
        let header = reader.header();
        let format = *header.point_format();
        let count = header.number_of_points();
        let b = header.bounds();
        let t = header.transforms();
        // One quantum of slack: the header's box is computed from the
        // quantized coordinates, which rounding may put a hair outside.
        let slack = [t.x.scale, t.y.scale, t.z.scale].map(f64::abs);
        let bounds = (
            [b.min.x - slack[0], b.min.y - slack[1], b.min.z - slack[2]],
            [b.max.x + slack[0], b.max.y + slack[1], b.max.z + slack[2]],
        );
        if !(0..3).all(|a| bounds.0[a].is_finite() && bounds.1[a].is_finite()) {
            return Err(ConvertError::Input(format!(
                "{name}: the LAS header's bounding box is not finite"
            )));
        }
        let description = format!(
            "LAS {}.{}{} point format {}, {count} points{}",
            header.version().major,
            header.version().minor,
            if format.is_compressed { " (LAZ)" } else { "" },
            format.to_u8().unwrap_or(0),
            if format.has_color {
                " with 16-bit colours"
            } else {
                ""
            }
        );
        let data = PointDataBuilder::new().for_header(header).build();
        Ok(LasCloud {
            path,
            name,
            colors: format.has_color,
            reader,
            data,
            count,
            read: 0,
            bounds,
            description,
        })
    }
}

impl std::fmt::Debug for LasCloud {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "LasCloud({}: {})", self.name, self.description)
    }
}

impl PointSource for LasCloud {
    fn describe(&self) -> String {
        self.description.clone()
    }

    fn count(&self) -> u64 {
        self.count
    }

    fn declared_bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        Some(self.bounds)
    }

    fn has_colors(&self) -> bool {
        self.colors
    }

    fn read(&mut self, out: &mut Vec<CloudPoint>, max: usize) -> Result<usize, ConvertError> {
        let want = (max as u64).min(self.count - self.read);
        if want == 0 {
            return Ok(0);
        }
        let n = self
            .reader
            .fill_points(want, &mut self.data)
            .map_err(|e| las_error(&self.name, e))?;
        if n < want {
            return Err(ConvertError::Input(format!(
                "{}: the LAS file ends after {} of its {} points",
                self.name,
                self.read + n,
                self.count
            )));
        }
        let start = out.len();
        out.extend(
            self.data
                .x()
                .zip(self.data.y())
                .zip(self.data.z())
                .map(|((x, y), z)| CloudPoint {
                    position: [x, y, z],
                    rgba: DEFAULT_COLOR,
                }),
        );
        if let Some(rgb) = self.data.rgb() {
            for (p, (r, g, b)) in out[start..].iter_mut().zip(rgb) {
                p.rgba = [channel_8bit(r), channel_8bit(g), channel_8bit(b), 255];
            }
        }
        let (lo, hi) = self.bounds;
        for (i, p) in out[start..].iter().enumerate() {
            let q = p.position;
            if !(0..3).all(|a| q[a] >= lo[a] && q[a] <= hi[a]) {
                super::check_finite(q, || {
                    format!("{}: point {}", self.name, self.read + i as u64 + 1)
                })?;
                return Err(ConvertError::Input(format!(
                    "{}: point {} at {q:?} lies outside the header's bounding box {:?} to {:?}",
                    self.name,
                    self.read + i as u64 + 1,
                    lo,
                    hi
                )));
            }
        }
        self.read += n;
        Ok(n as usize)
    }

    fn rewind(&mut self) -> Result<(), ConvertError> {
        *self = LasCloud::open(&self.path.clone())?;
        Ok(())
    }
}
