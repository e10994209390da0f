//! Out-of-core DAG building: memory bounded by a budget, not by the number of
//! distinct nodes, with exact global deduplication.
//!
//! # Runs
//!
//! Bricks arrive in Morton order ([`DagSink::push_brick`]) and go into an
//! ordinary in-memory [`DagBuilder`] that records the roots of its subtrees
//! at a *split level* P (the level of the converter's 128³ chunks). At every
//! boundary between two level-P cells the sink compares the builder's memory
//! with the run budget; when it is over, the builder's distinct nodes of
//! levels P ..= D − 2 (with their builder-local ids) and its list of
//! (level-P Morton code, local id, voxel count) roots are appended to
//! temporary files, and a new builder starts on the next cell: a *run* is a
//! Morton range of complete level-P subtrees. If nothing was ever spilled,
//! the one builder finishes in memory as before.
//!
//! # Merge
//!
//! The runs are then merged bottom-up, one level at a time, starting at the
//! leaves. For level L, every run's nodes are read with their children
//! rewritten to *final* pointers (the run's map "local id at L + 1 → final
//! pointer", an array the size of the run's level, produced by the merge of
//! L + 1) and hash-partitioned into K buckets sized to the memory budget
//! (step 1). Each bucket is deduplicated in memory; identical records of
//! different runs meet in the same bucket, so deduplication is exact. Each
//! distinct record keeps the (run, local id) of its first occurrence (step
//! 2). A K-way merge on that key lays the level out (step 3): runs are
//! consecutive Morton ranges and local ids are first-seen order within a
//! run, so the key order is exactly the first-seen order of a single
//! in-memory build, and the level's records get the same offsets and bytes as
//! there. The encoded section goes to a temporary file, with its CRC-32C.
//! Finally the per-run maps "local id at L → final pointer" are written for
//! the level above (step 4). After level P, an [`UpperBuilder`] builds levels
//! 0 .. P from the roots. The file is then the in-memory build's file, byte
//! for byte, whatever the budget, the runs and the buckets.
//!
//! Every temporary file is unnamed ([`tempfile::tempfile_in`]: `O_TMPFILE`
//! on Linux), so nothing is left behind on success, on error, or when the
//! process is killed. Temporary data is in native-endian 32-bit words: it
//! never leaves the process.
//!
//! # Memory
//!
//! A run holds at most its budget (the builder's [`DagBuilder::memory_bytes`]
//! plus the next hash-table growth). The merge holds, at any time, one
//! bucket (its records, a hash table sized for them, one offset per distinct
//! record), or one run's map plus K block buffers, or K read buffers; K is
//! chosen so that a bucket fits the merge budget. The levels above P, built
//! in memory, hold at most one node per occupied cell above level P: fewer
//! than the occupied level-P cells (the chunks), which the triangle bins
//! already hold.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use dagfmt::assemble::SectionInfo;
use dagfmt::builder::{
    BuildError, BuiltDag, DagBuilder, Subtrees, UpperBuilder, UpperLevels, fmix64,
};
use dagfmt::layout::{self, AttributeKind, MAX_LEAF_COUNT, MAX_NODE_LEVEL_BYTES};
use dagfmt::packed_colors::{PackedColorEncoder, PackedSummary};
use dagfmt::stats::LevelStats;
use hashbrown::HashTable;
use rayon::prelude::*;

use crate::dedup::ShardedTable;

use crate::error::ConvertError;

/// The smallest run budget the converter accepts: a few chunks' worth of
/// nodes, so that runs are not absurdly short.
pub const MIN_RUN_BUDGET: u64 = 8 << 20;

/// The smallest merge budget: a bucket of a few hundred thousand records.
pub const MIN_MERGE_BUDGET: u64 = 8 << 20;

/// Most buckets per level. Beyond this the block buffers of the partition
/// would dominate; a budget this small is refused before (`MIN_MERGE_BUDGET`).
const MAX_BUCKETS: usize = 4096;

fn build_error(e: BuildError) -> ConvertError {
    ConvertError::Limit(format!("cannot build the DAG: {e}"))
}

// ---------------------------------------------------------------------------
// Temporary files.

/// The directory temporary files go to, and the bytes written to them.
#[derive(Clone, Debug)]
pub struct Scratch {
    dir: PathBuf,
    usage: Arc<Usage>,
}

/// Bytes written to temporary files: in all, held now, and held at most.
#[derive(Debug, Default)]
struct Usage {
    written: AtomicU64,
    held: AtomicU64,
    peak: AtomicU64,
}

impl Scratch {
    /// Checks, before any work is done, that unnamed temporary files can be
    /// made in `dir`.
    pub fn new(dir: &Path) -> Result<Scratch, ConvertError> {
        match std::fs::metadata(dir) {
            Err(e) if e.kind() == io::ErrorKind::NotFound => {
                return Err(ConvertError::Io(format!(
                    "temporary directory {} does not exist",
                    dir.display()
                )));
            }
            Err(e) => {
                return Err(ConvertError::io(
                    format!("cannot use temporary directory {}", dir.display()),
                    e,
                ));
            }
            Ok(m) if !m.is_dir() => {
                return Err(ConvertError::Io(format!(
                    "temporary directory {} is not a directory",
                    dir.display()
                )));
            }
            Ok(_) => {}
        }
        let scratch = Scratch {
            dir: dir.to_path_buf(),
            usage: Arc::new(Usage::default()),
        };
        // Makes (and at once forgets) one unnamed file, so that an unwritable
        // directory is an error now rather than after the voxelization.
        scratch.file().map_err(|e| {
            ConvertError::io(
                format!("cannot create temporary files in {}", dir.display()),
                e,
            )
        })?;
        Ok(scratch)
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Bytes written to temporary files so far.
    pub fn bytes_written(&self) -> u64 {
        self.usage.written.load(Ordering::Relaxed)
    }

    /// The most bytes the temporary files held at once (the disk space they
    /// needed).
    pub fn peak_bytes(&self) -> u64 {
        self.usage.peak.load(Ordering::Relaxed)
    }

    /// A new unnamed temporary file: it has no name, so it disappears with
    /// the process whatever happens.
    fn file(&self) -> io::Result<File> {
        tempfile::tempfile_in(&self.dir)
    }

    /// The one-line error for a failed temporary-file operation.
    pub fn error(&self, e: io::Error) -> ConvertError {
        ConvertError::io(
            format!("cannot write temporary files in {}", self.dir.display()),
            e,
        )
    }

    /// A new unnamed temporary file to write and then read back (counted
    /// like the others).
    pub fn counted_file(&self) -> io::Result<CountedFile> {
        Ok(CountedFile(self.writer()?))
    }

    fn writer(&self) -> io::Result<TempFile> {
        Ok(TempFile {
            file: self.file()?,
            bytes: 0,
            usage: Arc::clone(&self.usage),
        })
    }
}

/// An unnamed temporary file that counts what is written to it; its bytes
/// stop counting as held when it is dropped (and the system frees them).
#[derive(Debug)]
struct TempFile {
    file: File,
    bytes: u64,
    usage: Arc<Usage>,
}

impl Write for TempFile {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.file.write(buf)?;
        let u = &self.usage;
        self.bytes += n as u64;
        u.written.fetch_add(n as u64, Ordering::Relaxed);
        let held = u.held.fetch_add(n as u64, Ordering::Relaxed) + n as u64;
        u.peak.fetch_max(held, Ordering::Relaxed);
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.file.flush()
    }
}

impl Drop for TempFile {
    fn drop(&mut self) {
        self.usage.held.fetch_sub(self.bytes, Ordering::Relaxed);
    }
}

/// An unnamed temporary file from [`Scratch::counted_file`]: written
/// through `Write`, then read back from its start with [`CountedFile::reader`].
#[derive(Debug)]
pub struct CountedFile(TempFile);

impl Write for CountedFile {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.0.write(buf)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.0.flush()
    }
}

impl CountedFile {
    /// The file, positioned at its start, for reading.
    pub fn reader(&mut self) -> io::Result<&File> {
        use std::io::Seek;
        self.0.file.seek(io::SeekFrom::Start(0))?;
        Ok(&self.0.file)
    }
}

fn read_exact_at(file: &File, buf: &mut [u8], offset: u64) -> io::Result<()> {
    #[cfg(unix)]
    {
        std::os::unix::fs::FileExt::read_exact_at(file, buf, offset)
    }
    #[cfg(windows)]
    {
        let (mut buf, mut offset) = (buf, offset);
        while !buf.is_empty() {
            match std::os::windows::fs::FileExt::seek_read(file, buf, offset) {
                Ok(0) => return Err(io::ErrorKind::UnexpectedEof.into()),
                Ok(n) => {
                    buf = &mut buf[n..];
                    offset += n as u64;
                }
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }
}

fn corrupt(what: &str) -> io::Error {
    io::Error::new(
        io::ErrorKind::InvalidData,
        format!("temporary data read back inconsistent ({what})"),
    )
}

/// A sequential writer of 32-bit words to a temporary file.
#[derive(Debug)]
struct WordFile {
    out: TempFile,
    buf: Vec<u32>,
    cap: usize,
    words: u64,
}

impl WordFile {
    fn new(scratch: &Scratch, cap: usize) -> io::Result<Self> {
        Ok(WordFile {
            out: scratch.writer()?,
            buf: Vec::new(),
            cap,
            words: 0,
        })
    }

    #[inline]
    fn push(&mut self, word: u32) -> io::Result<()> {
        if self.buf.len() == self.cap {
            self.flush()?;
        }
        self.buf.push(word);
        self.words += 1;
        Ok(())
    }

    fn extend(&mut self, words: &[u32]) -> io::Result<()> {
        for &w in words {
            self.push(w)?;
        }
        Ok(())
    }

    fn flush(&mut self) -> io::Result<()> {
        self.out.write_all(bytemuck::cast_slice(&self.buf))?;
        self.buf.clear();
        Ok(())
    }

    fn finish(mut self) -> io::Result<WordData> {
        self.flush()?;
        Ok(WordData {
            file: self.out,
            words: self.words,
        })
    }
}

/// Words written by a [`WordFile`].
#[derive(Debug)]
struct WordData {
    file: TempFile,
    words: u64,
}

impl WordData {
    fn reader(&self, cap: usize) -> WordReader<'_> {
        WordReader {
            source: Source::Plain(&self.file.file),
            pos: 0,
            end: self.words,
            buf: Vec::new(),
            at: 0,
            cap,
        }
    }
}

/// `K` streams of words in one temporary file, each written in blocks of a
/// fixed size (so a position in a stream maps to a block by division). Only
/// the last block of a stream may be short.
#[derive(Debug)]
struct StreamWriter {
    out: TempFile,
    block: usize,
    bufs: Vec<Vec<u32>>,
    blocks: Vec<Vec<u64>>,
    lens: Vec<u64>,
    end: u64,
}

impl StreamWriter {
    fn new(scratch: &Scratch, streams: usize, block: usize) -> io::Result<Self> {
        Ok(StreamWriter {
            out: scratch.writer()?,
            block,
            bufs: (0..streams).map(|_| Vec::new()).collect(),
            blocks: vec![Vec::new(); streams],
            lens: vec![0; streams],
            end: 0,
        })
    }

    #[inline]
    fn push(&mut self, stream: usize, words: &[u32]) -> io::Result<()> {
        for &w in words {
            if self.bufs[stream].len() == self.block {
                self.flush_block(stream)?;
            }
            let buf = &mut self.bufs[stream];
            if buf.capacity() == 0 {
                buf.reserve_exact(self.block);
            }
            buf.push(w);
        }
        self.lens[stream] += words.len() as u64;
        Ok(())
    }

    fn flush_block(&mut self, stream: usize) -> io::Result<()> {
        let buf = &mut self.bufs[stream];
        if buf.is_empty() {
            return Ok(());
        }
        self.out.write_all(bytemuck::cast_slice(buf))?;
        self.blocks[stream].push(self.end);
        self.end += buf.len() as u64;
        buf.clear();
        Ok(())
    }

    /// Ends `stream`: writes its last block and frees its buffer.
    fn close(&mut self, stream: usize) -> io::Result<()> {
        self.flush_block(stream)?;
        self.bufs[stream] = Vec::new();
        Ok(())
    }

    fn finish(mut self) -> io::Result<Streams> {
        for s in 0..self.bufs.len() {
            self.close(s)?;
        }
        Ok(Streams {
            file: self.out,
            block: self.block as u64,
            blocks: self.blocks,
            lens: self.lens,
        })
    }
}

/// The streams of a [`StreamWriter`], for reading.
#[derive(Debug)]
struct Streams {
    file: TempFile,
    block: u64,
    blocks: Vec<Vec<u64>>,
    lens: Vec<u64>,
}

impl Streams {
    fn len(&self, stream: usize) -> u64 {
        self.lens[stream]
    }

    /// Reads `out.len()` words of `stream` from word `start`.
    fn read(&self, stream: usize, start: u64, out: &mut [u32]) -> io::Result<()> {
        if start + out.len() as u64 > self.lens[stream] {
            return Err(corrupt("a read past the end of a stream"));
        }
        let mut done = 0usize;
        while done < out.len() {
            let p = start + done as u64;
            let (i, within) = ((p / self.block) as usize, p % self.block);
            let take = ((self.block - within) as usize).min(out.len() - done);
            let at = self.blocks[stream][i] + within;
            read_exact_at(
                &self.file.file,
                bytemuck::cast_slice_mut(&mut out[done..done + take]),
                at * 4,
            )?;
            done += take;
        }
        Ok(())
    }

    fn read_all(&self, stream: usize) -> io::Result<Vec<u32>> {
        let mut out = vec![0u32; self.lens[stream] as usize];
        self.read(stream, 0, &mut out)?;
        Ok(out)
    }

    fn reader(&self, stream: usize, cap: usize) -> WordReader<'_> {
        WordReader {
            source: Source::Stream(self, stream),
            pos: 0,
            end: self.lens[stream],
            buf: Vec::new(),
            at: 0,
            cap,
        }
    }
}

#[derive(Debug)]
enum Source<'a> {
    Plain(&'a File),
    Stream(&'a Streams, usize),
}

/// A buffered sequential reader of words (positioned reads, so that several
/// readers can share one file).
#[derive(Debug)]
struct WordReader<'a> {
    source: Source<'a>,
    pos: u64,
    end: u64,
    buf: Vec<u32>,
    at: usize,
    cap: usize,
}

impl WordReader<'_> {
    fn remaining(&self) -> u64 {
        self.end - self.pos + (self.buf.len() - self.at) as u64
    }

    #[inline]
    fn next(&mut self) -> io::Result<u32> {
        if self.at == self.buf.len() {
            self.refill()?;
        }
        let w = self.buf[self.at];
        self.at += 1;
        Ok(w)
    }

    fn refill(&mut self) -> io::Result<()> {
        let n = (self.end - self.pos).min(self.cap as u64) as usize;
        if n == 0 {
            return Err(corrupt("a temporary file ends early"));
        }
        self.buf.resize(n, 0);
        match self.source {
            Source::Plain(file) => {
                read_exact_at(file, bytemuck::cast_slice_mut(&mut self.buf), self.pos * 4)?
            }
            Source::Stream(streams, s) => streams.read(s, self.pos, &mut self.buf)?,
        }
        self.pos += n as u64;
        self.at = 0;
        Ok(())
    }
}

/// Hands the first `length` bytes of `file` to `sink`.
fn emit_file(
    file: &File,
    length: u64,
    sink: &mut dyn FnMut(&[u8]) -> io::Result<()>,
) -> io::Result<()> {
    let mut buf = vec![0u8; 1 << 20];
    let mut at = 0u64;
    while at < length {
        let n = (length - at).min(buf.len() as u64) as usize;
        read_exact_at(file, &mut buf[..n], at)?;
        sink(&buf[..n])?;
        at += n as u64;
    }
    Ok(())
}

/// The bytes of one section, written to a temporary file with their CRC-32C.
#[derive(Debug)]
struct SectionFile {
    file: TempFile,
    info: SectionInfo,
}

impl SectionFile {
    /// Hands the section's bytes to `sink`.
    fn emit(&self, sink: &mut dyn FnMut(&[u8]) -> io::Result<()>) -> io::Result<()> {
        emit_file(&self.file.file, self.info.length, sink)
    }
}

#[derive(Debug)]
struct SectionWriter {
    out: BufWriter<TempFile>,
    length: u64,
    crc: u32,
}

impl SectionWriter {
    fn new(scratch: &Scratch) -> io::Result<Self> {
        Ok(SectionWriter {
            out: BufWriter::with_capacity(1 << 20, scratch.writer()?),
            length: 0,
            crc: 0,
        })
    }

    fn write(&mut self, bytes: &[u8]) -> io::Result<()> {
        self.crc = crc32c::crc32c_append(self.crc, bytes);
        self.length += bytes.len() as u64;
        self.out.write_all(bytes)
    }

    fn finish(self) -> io::Result<(TempFile, u64, u32)> {
        let file = self.out.into_inner().map_err(|e| e.into_error())?;
        Ok((file, self.length, self.crc))
    }
}

// ---------------------------------------------------------------------------
// Colours.

/// The per-voxel colours, in dense index (Morton) order: kept in memory up to
/// a cap, then streamed to an unnamed temporary file. With an error bound the
/// colours are packed (spec §12.6) on the way in, block by block, so only the
/// packed bytes are kept or spilled, and the directory (1/32 byte per colour)
/// stays in memory until [`ColourSink::finish`].
#[derive(Debug)]
pub struct ColourSink {
    scratch: Scratch,
    cap: usize,
    mem: Vec<u8>,
    file: Option<BufWriter<TempFile>>,
    /// Colours written.
    count: u64,
    /// Bytes stored (raw or packed).
    length: u64,
    crc: u32,
    packer: Option<(PackedColorEncoder, Vec<u8>)>,
}

impl ColourSink {
    /// Colours kept in memory up to `cap` bytes, beyond that in a file in
    /// `scratch`; packed within `error_bound` (≤ 127) when there is one.
    pub fn new(scratch: &Scratch, cap: u64, error_bound: Option<u8>) -> Self {
        ColourSink {
            scratch: scratch.clone(),
            cap: cap as usize,
            mem: Vec::new(),
            file: None,
            count: 0,
            length: 0,
            crc: 0,
            packer: error_bound.map(|e| {
                (
                    PackedColorEncoder::new(e).expect("the error bound was checked"),
                    Vec::new(),
                )
            }),
        }
    }

    /// Appends colours (RGBA8, 4 bytes each).
    pub fn write(&mut self, rgba: &[u8]) -> Result<(), ConvertError> {
        debug_assert_eq!(rgba.len() % 4, 0);
        self.count += rgba.len() as u64 / 4;
        match self.packer.take() {
            None => self.store(rgba),
            Some((mut encoder, mut buf)) => {
                encoder.push_bytes(rgba, &mut buf);
                let stored = self.store(&buf);
                buf.clear();
                self.packer = Some((encoder, buf));
                stored
            }
        }
    }

    /// Keeps section bytes.
    fn store(&mut self, bytes: &[u8]) -> Result<(), ConvertError> {
        self.crc = crc32c::crc32c_append(self.crc, bytes);
        self.length += bytes.len() as u64;
        if self.file.is_none() && self.mem.len() + bytes.len() <= self.cap {
            self.mem.extend_from_slice(bytes);
            return Ok(());
        }
        self.spill().map_err(|e| self.scratch.error(e))?;
        let file = self.file.as_mut().expect("spilled");
        file.write_all(bytes).map_err(|e| self.scratch.error(e))
    }

    fn spill(&mut self) -> io::Result<()> {
        if self.file.is_none() {
            let mut file = BufWriter::with_capacity(1 << 20, self.scratch.writer()?);
            file.write_all(&self.mem)?;
            self.mem = Vec::new();
            self.file = Some(file);
        }
        Ok(())
    }

    /// The colours, ready to be copied into the file.
    pub fn finish(mut self) -> Result<Colours, ConvertError> {
        let mut packed = None;
        if let Some((encoder, mut buf)) = self.packer.take() {
            let summary = encoder.finish(&mut buf);
            self.store(&buf)?;
            packed = Some(summary);
        }
        let data = match self.file {
            None => ColourData::Memory(self.mem),
            Some(file) => {
                let file = file
                    .into_inner()
                    .map_err(|e| self.scratch.error(e.into_error()))?;
                ColourData::File(file)
            }
        };
        Ok(Colours {
            data,
            count: self.count,
            length: self.length,
            crc: self.crc,
            packed,
        })
    }
}

#[derive(Debug)]
enum ColourData {
    Memory(Vec<u8>),
    File(TempFile),
}

/// Colours gathered by a [`ColourSink`].
#[derive(Debug)]
pub struct Colours {
    data: ColourData,
    count: u64,
    length: u64,
    crc: u32,
    packed: Option<PackedSummary>,
}

impl Colours {
    /// The colour section's entry.
    pub fn section(&self) -> SectionInfo {
        match self.packed {
            None => SectionInfo::voxel_colors(self.count, self.crc),
            Some(p) => {
                SectionInfo::packed_colors(self.count, self.length, self.crc, p.trailer.layout)
            }
        }
    }

    /// What packing measured, if the colours are packed.
    pub fn packed(&self) -> Option<PackedSummary> {
        self.packed
    }

    /// Whether they went through a temporary file.
    pub fn spilled(&self) -> bool {
        matches!(self.data, ColourData::File(_))
    }

    /// Hands the colour bytes to `sink`.
    pub fn emit(&self, sink: &mut dyn FnMut(&[u8]) -> io::Result<()>) -> io::Result<()> {
        match &self.data {
            ColourData::Memory(bytes) => {
                for chunk in bytes.chunks(1 << 20) {
                    sink(chunk)?;
                }
                Ok(())
            }
            ColourData::File(file) => emit_file(&file.file, self.length, sink),
        }
    }
}

// ---------------------------------------------------------------------------
// Occupied cells (the nodes of a tree without deduplication).

/// Counts the occupied cells of every level from the bricks, in O(1) per
/// brick: the levels whose cell changes between two consecutive bricks are
/// those below the highest differing bit of their codes.
#[derive(Clone, Debug)]
pub struct CellCounter {
    leaf: usize,
    /// `first[l]`: bricks whose first new cell is at level `l`.
    first: Vec<u64>,
    previous: Option<u64>,
}

impl CellCounter {
    /// A counter for a depth-`depth` volume.
    pub fn new(depth: u8) -> Self {
        let leaf = usize::from(depth) - 2;
        CellCounter {
            leaf,
            first: vec![0; leaf + 1],
            previous: None,
        }
    }

    /// Counts a non-empty brick; bricks must come in increasing order.
    #[inline]
    pub fn add(&mut self, brick: u64) {
        let level = match self.previous {
            None => 0,
            Some(p) => {
                let high = 63 - (p ^ brick).leading_zeros() as usize;
                self.leaf - (high / 3).min(self.leaf)
            }
        };
        self.first[level] += 1;
        self.previous = Some(brick);
    }

    /// Occupied cells per level, root first, leaf level last.
    pub fn cells(&self) -> Vec<u128> {
        let mut sum = 0u128;
        self.first
            .iter()
            .map(|&n| {
                sum += u128::from(n);
                sum
            })
            .collect()
    }
}

// ---------------------------------------------------------------------------
// The sink: runs.

/// How a [`DagSink`] splits its work.
#[derive(Clone, Debug)]
pub struct SpillSettings {
    /// The split level P: runs are Morton ranges of complete level-P
    /// subtrees. 0: never spill.
    pub split_level: u8,
    /// Bytes the in-memory builder may hold before its run is spilled.
    pub run_budget: u64,
    /// Testing: end a run after this many level-P cells, whatever the
    /// memory, and merge even a single run.
    pub cells_per_run: Option<u64>,
    /// Testing: the number of buckets of every level's merge.
    pub buckets: Option<u32>,
}

/// What spilling did, for the summary.
#[derive(Clone, Debug, Default)]
pub struct SpillReport {
    /// Runs written to temporary files (0: the DAG was built in memory).
    pub runs: u64,
    /// Most buckets of a level's merge.
    pub max_buckets: u64,
    /// Seconds spent merging the runs.
    pub merge_seconds: f64,
}

/// Takes bricks in Morton order and builds the DAG in memory or, when it
/// outgrows the run budget, in runs spilled to temporary files.
#[derive(Debug)]
pub struct DagSink {
    depth: u8,
    attributes: AttributeKind,
    settings: SpillSettings,
    scratch: Scratch,
    builder: DagBuilder,
    /// Shift from a brick code to its level-P cell code.
    shift: u32,
    cell: Option<u64>,
    cells_in_run: u64,
    runs: Option<RunFiles>,
    counter: CellCounter,
}

impl DagSink {
    /// A sink for a depth-`depth` volume whose temporary files go to `scratch`.
    pub fn new(
        depth: u8,
        attributes: AttributeKind,
        settings: SpillSettings,
        scratch: &Scratch,
    ) -> Result<Self, ConvertError> {
        let leaf = depth.saturating_sub(2);
        if settings.split_level > leaf {
            return Err(ConvertError::Usage(format!(
                "split level {} is outside 0..={leaf} for depth {depth}",
                settings.split_level
            )));
        }
        let mut sink = DagSink {
            depth,
            attributes,
            shift: 3 * u32::from(leaf - settings.split_level),
            settings,
            scratch: scratch.clone(),
            builder: DagBuilder::new(depth, attributes).map_err(build_error)?,
            cell: None,
            cells_in_run: 0,
            runs: None,
            counter: CellCounter::new(depth),
        };
        sink.builder = sink.new_builder()?;
        Ok(sink)
    }

    fn new_builder(&self) -> Result<DagBuilder, ConvertError> {
        let mut b = DagBuilder::new(self.depth, self.attributes).map_err(build_error)?;
        if self.settings.split_level > 0 {
            b.record_subtrees(self.settings.split_level)
                .map_err(build_error)?;
        }
        Ok(b)
    }

    /// Runs spilled so far.
    pub fn runs(&self) -> u64 {
        self.runs.as_ref().map_or(0, |r| r.runs.len() as u64)
    }

    /// Adds brick `brick` with voxels `mask` (bricks strictly increasing).
    #[inline]
    pub fn push_brick(&mut self, brick: u64, mask: u64) -> Result<(), ConvertError> {
        if mask == 0 {
            return Ok(());
        }
        let cell = brick >> self.shift;
        if self.cell != Some(cell) {
            if self.cell.is_some() {
                self.cells_in_run += 1;
                if self.run_is_full() {
                    self.spill_run()?;
                }
            }
            self.cell = Some(cell);
        }
        self.builder.push_brick(brick, mask).map_err(build_error)?;
        self.counter.add(brick);
        Ok(())
    }

    /// Whether the run ends at this cell boundary.
    fn run_is_full(&self) -> bool {
        if self.settings.split_level == 0 {
            return false;
        }
        match self.settings.cells_per_run {
            Some(n) => self.cells_in_run >= n,
            None => {
                (self.builder.memory_bytes() + self.builder.growth_bytes()) as u64
                    > self.settings.run_budget
            }
        }
    }

    fn spill_run(&mut self) -> Result<(), ConvertError> {
        let fresh = self.new_builder()?;
        let full = std::mem::replace(&mut self.builder, fresh);
        let subtrees = full.finish_subtrees().map_err(build_error)?;
        if self.runs.is_none() {
            let files = RunFiles::new(&self.scratch, self.depth, self.settings.split_level)
                .map_err(|e| self.scratch.error(e))?;
            self.runs = Some(files);
        }
        let runs = self.runs.as_mut().expect("just made");
        runs.append(&subtrees).map_err(|e| self.scratch.error(e))?;
        self.cells_in_run = 0;
        Ok(())
    }

    /// Completes the DAG: in memory when nothing was spilled, else by
    /// merging the runs within `merge_budget` bytes (sized by the caller
    /// once the voxelization's memory is free), telling `progress` which
    /// level it merges (for a progress display).
    pub fn finish(
        mut self,
        merge_budget: impl FnOnce() -> u64,
        progress: &dyn Fn(&str),
    ) -> Result<FinishedDag, ConvertError> {
        let cells = self.counter.cells();
        // A forced spill (testing) goes through the merge even with one run.
        let forced = self.settings.cells_per_run.is_some()
            && self.settings.split_level > 0
            && self.cell.is_some();
        if self.runs.is_none() && !forced {
            let built = self.builder.finish().map_err(build_error)?;
            return Ok(FinishedDag {
                inner: Inner::InCore(built),
                cells,
                report: SpillReport::default(),
            });
        }
        let t = std::time::Instant::now();
        self.spill_run()?;
        let DagSink {
            builder,
            runs,
            scratch,
            settings,
            depth,
            attributes,
            ..
        } = self;
        drop(builder);
        let (runs, levels) = runs
            .expect("spilled")
            .finish()
            .map_err(|e| scratch.error(e))?;
        let budget = merge_budget().max(MIN_MERGE_BUDGET);
        let merger = Merger {
            scratch: &scratch,
            depth,
            attributes,
            split: settings.split_level,
            budget,
            forced_buckets: settings.buckets,
            runs: &runs,
        };
        let (external, max_buckets) = merger.run(levels, progress)?;
        Ok(FinishedDag {
            inner: Inner::External(external),
            cells,
            report: SpillReport {
                runs: runs.runs.len() as u64,
                max_buckets,
                merge_seconds: t.elapsed().as_secs_f64(),
            },
        })
    }
}

/// The temporary files of the runs being spilled.
#[derive(Debug)]
struct RunFiles {
    split: u8,
    leaf: u8,
    /// Levels `split ..= leaf`: records (header, children) or leaves (two words).
    levels: Vec<WordFile>,
    /// Per root: code (two words), local id, count (two words).
    roots: WordFile,
    runs: Vec<RunInfo>,
}

#[derive(Clone, Debug)]
struct RunInfo {
    /// Distinct nodes per level `split ..= leaf`.
    nodes: Vec<u64>,
    roots: u64,
}

const WRITE_WORDS: usize = 1 << 16;

impl RunFiles {
    fn new(scratch: &Scratch, depth: u8, split: u8) -> io::Result<Self> {
        let leaf = depth - 2;
        Ok(RunFiles {
            split,
            leaf,
            levels: (split..=leaf)
                .map(|_| WordFile::new(scratch, WRITE_WORDS))
                .collect::<io::Result<_>>()?,
            roots: WordFile::new(scratch, WRITE_WORDS)?,
            runs: Vec::new(),
        })
    }

    fn append(&mut self, run: &Subtrees) -> io::Result<()> {
        let mut nodes = Vec::with_capacity(self.levels.len());
        for level in self.split..self.leaf {
            let out = &mut self.levels[usize::from(level - self.split)];
            let n = run.node_count(level);
            for id in 0..n as u32 {
                let (header, children) = run.node(level, id);
                out.push(header)?;
                out.extend(children)?;
            }
            nodes.push(n as u64);
        }
        let out = self.levels.last_mut().expect("the leaf level");
        for &mask in run.leaves() {
            out.push(mask as u32)?;
            out.push((mask >> 32) as u32)?;
        }
        nodes.push(run.leaves().len() as u64);
        for root in run.roots() {
            self.roots.extend(&[
                root.code as u32,
                (root.code >> 32) as u32,
                root.id,
                root.count as u32,
                (root.count >> 32) as u32,
            ])?;
        }
        self.runs.push(RunInfo {
            nodes,
            roots: run.roots().len() as u64,
        });
        Ok(())
    }

    /// The runs, and their records of each level `split ..= leaf`, which
    /// the merge consumes (and frees) one level at a time.
    fn finish(self) -> io::Result<(SpilledRuns, Vec<WordData>)> {
        let levels = self
            .levels
            .into_iter()
            .map(WordFile::finish)
            .collect::<io::Result<_>>()?;
        let runs = SpilledRuns {
            split: self.split,
            leaf: self.leaf,
            roots: self.roots.finish()?,
            runs: self.runs,
        };
        Ok((runs, levels))
    }
}

/// Joins DAGs given as runs from outside the converter (the parts of a
/// region build, [`crate::merge`]) with the same level merge as a spilled
/// conversion: each run is a Morton range of complete level-`split`
/// subtrees, given as its distinct records of levels `split ..= D − 2` with
/// run-local ids (first-seen order) and its roots; runs come in increasing
/// Morton order. The result is the file one in-memory build of all the runs'
/// voxels makes, byte for byte.
#[derive(Debug)]
pub struct RunMerge {
    depth: u8,
    attributes: AttributeKind,
    scratch: Scratch,
    files: RunFiles,
    /// Records per level `split ..= leaf` of the run being given.
    nodes: Vec<u64>,
    roots: u64,
    last_code: Option<u64>,
    forced_buckets: Option<u32>,
}

impl RunMerge {
    /// A merge of depth-`depth` runs split at level `split` (1 ..= D − 2),
    /// with temporary files in `scratch`; `buckets` forces the number of
    /// buckets of every level (testing).
    pub fn new(
        depth: u8,
        attributes: AttributeKind,
        split: u8,
        scratch: &Scratch,
        buckets: Option<u32>,
    ) -> Result<Self, ConvertError> {
        if depth < 3 || !(1..=depth - 2).contains(&split) {
            return Err(ConvertError::Usage(format!(
                "split level {split} is outside 1..={} for depth {depth}",
                depth.saturating_sub(2)
            )));
        }
        let files = RunFiles::new(scratch, depth, split).map_err(|e| scratch.error(e))?;
        Ok(RunMerge {
            depth,
            attributes,
            scratch: scratch.clone(),
            nodes: vec![0; usize::from(depth - 2 - split) + 1],
            files,
            roots: 0,
            last_code: None,
            forced_buckets: buckets,
        })
    }

    /// The split level.
    pub fn split_level(&self) -> u8 {
        self.files.split
    }

    /// Adds the next record of interior `level` (`split ..= D − 3`) of the
    /// current run: its header word and its children's run-local ids.
    pub fn push_node(
        &mut self,
        level: u8,
        header: u32,
        children: &[u32],
    ) -> Result<(), ConvertError> {
        let (split, leaf) = (self.files.split, self.files.leaf);
        if !(split..leaf).contains(&level)
            || (header & 0xFF).count_ones() as usize != children.len()
        {
            return Err(ConvertError::Input(format!(
                "a record of level {level} with header {header:#x} and {} children does not fit levels {split}..{leaf}",
                children.len()
            )));
        }
        let i = usize::from(level - split);
        let out = &mut self.files.levels[i];
        out.push(header)
            .and_then(|()| out.extend(children))
            .map_err(|e| self.scratch.error(e))?;
        self.nodes[i] += 1;
        Ok(())
    }

    /// Adds the next leaf mask of the current run.
    pub fn push_leaf(&mut self, mask: u64) -> Result<(), ConvertError> {
        let out = self.files.levels.last_mut().expect("the leaf level");
        out.push(mask as u32)
            .and_then(|()| out.push((mask >> 32) as u32))
            .map_err(|e| self.scratch.error(e))?;
        *self.nodes.last_mut().expect("the leaf level") += 1;
        Ok(())
    }

    /// Adds a root of the current run: the Morton code of its level-`split`
    /// cell (strictly increasing over all runs), its run-local id and its
    /// voxel count.
    pub fn push_root(&mut self, code: u64, id: u32, count: u64) -> Result<(), ConvertError> {
        if self.last_code.is_some_and(|c| c >= code) || u64::from(id) >= self.nodes[0] {
            return Err(ConvertError::Input(format!(
                "subtree {code} (id {id}) is out of Morton order or refers to no record"
            )));
        }
        self.last_code = Some(code);
        self.files
            .roots
            .extend(&[
                code as u32,
                (code >> 32) as u32,
                id,
                count as u32,
                (count >> 32) as u32,
            ])
            .map_err(|e| self.scratch.error(e))?;
        self.roots += 1;
        Ok(())
    }

    /// Ends the current run (nothing happens for a run without roots, which
    /// must then have no records either).
    pub fn end_run(&mut self) -> Result<(), ConvertError> {
        if self.roots == 0 {
            if self.nodes.iter().any(|&n| n > 0) {
                return Err(ConvertError::Input(
                    "a run has records but no subtree roots".into(),
                ));
            }
            return Ok(());
        }
        self.files.runs.push(RunInfo {
            nodes: std::mem::replace(&mut self.nodes, vec![0; self.files.levels.len()]),
            roots: std::mem::take(&mut self.roots),
        });
        Ok(())
    }

    /// Runs given so far.
    pub fn runs(&self) -> usize {
        self.files.runs.len()
    }

    /// Merges the runs within `budget` bytes.
    pub fn finish(
        mut self,
        budget: u64,
        progress: &dyn Fn(&str),
    ) -> Result<FinishedDag, ConvertError> {
        self.end_run()?;
        let t = std::time::Instant::now();
        if self.files.runs.is_empty() {
            return FinishedDag::empty_volume(self.depth, self.attributes);
        }
        let RunMerge {
            depth,
            attributes,
            scratch,
            files,
            forced_buckets,
            ..
        } = self;
        let split = files.split;
        let (runs, levels) = files.finish().map_err(|e| scratch.error(e))?;
        let merger = Merger {
            scratch: &scratch,
            depth,
            attributes,
            split,
            budget: budget.max(MIN_MERGE_BUDGET),
            forced_buckets,
            runs: &runs,
        };
        let (external, max_buckets) = merger.run(levels, progress)?;
        Ok(FinishedDag {
            inner: Inner::External(external),
            cells: Vec::new(),
            report: SpillReport {
                runs: runs.runs.len() as u64,
                max_buckets,
                merge_seconds: t.elapsed().as_secs_f64(),
            },
        })
    }
}

#[derive(Debug)]
struct SpilledRuns {
    split: u8,
    leaf: u8,
    roots: WordData,
    runs: Vec<RunInfo>,
}

impl SpilledRuns {
    fn nodes(&self, run: usize, level: u8) -> u64 {
        self.runs[run].nodes[usize::from(level - self.split)]
    }
}

// ---------------------------------------------------------------------------
// The merge.

#[inline]
fn hash_words(words: &[u32]) -> u64 {
    const K: u64 = 0x9e37_79b9_7f4a_7c15;
    let mut h = words.len() as u64;
    for pair in words.chunks(2) {
        let w = u64::from(pair[0]) | pair.get(1).map_or(0, |&x| u64::from(x) << 32);
        h = (h ^ w).wrapping_mul(K).rotate_left(31);
    }
    fmix64(h)
}

/// The bucket of a record: from the top bits of its hash, so that the hash
/// table inside a bucket (which takes bits from both ends of
/// [`table_hash`]) is not skewed.
#[inline]
fn bucket_of(hash: u64, buckets: usize) -> usize {
    ((u128::from(hash) * buckets as u128) >> 64) as usize
}

#[inline]
fn table_hash(hash: u64) -> u64 {
    fmix64(hash ^ 0x2545_f491_4f6c_dd1d)
}

/// Words of a record's content, from its first word.
#[inline]
fn content_len(leaf: bool, first: u32) -> usize {
    if leaf {
        2
    } else {
        1 + (first & 0xFF).count_ones() as usize
    }
}

/// The merge of one level: per-run maps "local id → final pointer", stored
/// as `(local, final)` pairs, one stream per bucket, each in run order.
#[derive(Debug)]
struct Finals {
    pairs: Streams,
    runs: usize,
    /// `starts[b * (runs + 1) + r]`: the first record of run `r` in bucket `b`.
    starts: Vec<u64>,
}

impl Finals {
    fn buckets(&self) -> usize {
        self.starts.len() / (self.runs + 1)
    }

    /// The map of run `run`, which has `n` nodes at this level.
    fn map(&self, run: usize, n: u64) -> io::Result<Vec<u32>> {
        let mut map = vec![u32::MAX; n as usize];
        let mut assigned = 0u64;
        let mut buf = Vec::new();
        for b in 0..self.buckets() {
            let s = &self.starts[b * (self.runs + 1)..];
            let (mut at, end) = (s[run], s[run + 1]);
            while at < end {
                let take = (end - at).min(1 << 15);
                buf.resize(2 * take as usize, 0);
                self.pairs.read(b, 2 * at, &mut buf)?;
                for pair in buf.chunks_exact(2) {
                    let slot = map
                        .get_mut(pair[0] as usize)
                        .ok_or_else(|| corrupt("a local id out of range"))?;
                    if *slot != u32::MAX {
                        return Err(corrupt("a node mapped twice"));
                    }
                    *slot = pair[1];
                }
                assigned += take;
                at += take;
            }
        }
        if assigned != n {
            return Err(corrupt("a node without a final position"));
        }
        Ok(map)
    }
}

/// A merged level: its section, and the units pointers into it count.
#[derive(Debug)]
struct MergedLevel {
    section: SectionFile,
    units: u64,
    finals: Finals,
    buckets: usize,
}

struct Merger<'a> {
    scratch: &'a Scratch,
    depth: u8,
    attributes: AttributeKind,
    split: u8,
    budget: u64,
    forced_buckets: Option<u32>,
    runs: &'a SpilledRuns,
}

impl Merger<'_> {
    fn io(&self, e: io::Error) -> ConvertError {
        self.scratch.error(e)
    }

    /// Merges every level from the leaves up to the split level (`levels`
    /// holds the runs' records of each, split level first), then builds the
    /// levels above.
    fn run(
        &self,
        mut levels: Vec<WordData>,
        progress: &dyn Fn(&str),
    ) -> Result<(ExternalDag, u64), ConvertError> {
        let leaf = self.runs.leaf;
        let mut lower: Vec<SectionFile> = Vec::new();
        let mut below: Option<MergedLevel> = None;
        let mut max_buckets = 0;
        for level in (self.split..=leaf).rev() {
            progress(&format!(
                "merging the spilled runs: level {level} ({} of {})",
                leaf - level + 1,
                leaf - self.split + 1
            ));
            let data = levels.pop().expect("one record file per level");
            let merged = self.merge_level(level, data, below.as_ref())?;
            max_buckets = max_buckets.max(merged.buckets as u64);
            if let Some(b) = below.take() {
                lower.push(b.section);
            }
            below = Some(merged);
        }
        let top = below.expect("at least the leaf level");
        progress("merging the spilled runs: the levels above the split");
        let upper = self.upper_levels(&top)?;
        lower.push(top.section);
        lower.reverse();
        Ok((
            ExternalDag {
                upper,
                lower,
                split: self.split,
            },
            max_buckets,
        ))
    }

    fn upper_levels(&self, split: &MergedLevel) -> Result<UpperLevels, ConvertError> {
        let mut upper =
            UpperBuilder::new(self.depth, self.attributes, self.split).map_err(build_error)?;
        let mut roots = self.runs.roots.reader(WRITE_WORDS);
        for run in 0..self.runs.runs.len() {
            let map = split
                .finals
                .map(run, self.runs.nodes(run, self.split))
                .map_err(|e| self.io(e))?;
            for _ in 0..self.runs.runs[run].roots {
                let mut w = [0u32; 5];
                for x in &mut w {
                    *x = roots.next().map_err(|e| self.io(e))?;
                }
                let code = u64::from(w[0]) | u64::from(w[1]) << 32;
                let pointer = *map
                    .get(w[2] as usize)
                    .ok_or_else(|| self.io(corrupt("a root out of range")))?;
                let count = u64::from(w[3]) | u64::from(w[4]) << 32;
                upper
                    .push_subtree(code, pointer, count)
                    .map_err(build_error)?;
            }
        }
        upper.finish(split.units).map_err(build_error)
    }

    /// Buckets for a level of `records` records in `words` content words, and
    /// the block size (words) of the bucket streams.
    fn buckets(&self, records: u64, words: u64) -> (usize, usize) {
        // A bucket in memory: its records with their local ids, a hash table
        // of 4-byte entries sized for all of them (at most 2.3 slots of 5
        // bytes each), and a 4-byte offset per distinct record.
        let bytes = 4 * (words + records) + 16 * records;
        let k = match self.forced_buckets {
            Some(k) => k.max(1) as usize,
            None => {
                let usable = self.budget / 4 * 3;
                (bytes.div_ceil(usable.max(1)) as usize).clamp(1, MAX_BUCKETS)
            }
        };
        // The partition keeps one block per bucket in memory: an eighth of
        // the budget for all of them.
        let block = ((self.budget / 8) as usize / k / 4).clamp(256, 1 << 16);
        (k, block)
    }

    /// Merges `level`, whose records are `data` (freed once read), given the
    /// merge of the level below (none for the leaf level).
    fn merge_level(
        &self,
        level: u8,
        data: WordData,
        below: Option<&MergedLevel>,
    ) -> Result<MergedLevel, ConvertError> {
        let io = |e| self.io(e);
        let runs = self.runs;
        let leaf = level == runs.leaf;
        let r_count = runs.runs.len();
        let records: u64 = (0..r_count).map(|r| runs.nodes(r, level)).sum();
        let (k, block) = self.buckets(records, data.words);
        // The pointer width of this level is set by the units of the level below.
        let width = match below {
            Some(b) => layout::minimal_pointer_width(b.units).ok_or_else(|| {
                build_error(BuildError::TooLarge {
                    what: format!(
                        "level {} has {} units, more than 4-byte pointers address",
                        level + 1,
                        b.units
                    ),
                })
            })?,
            None => 0,
        };

        // Step 1: every run's records, children rewritten to final pointers,
        // into K buckets by hash.
        let mut counts = vec![0u64; k * (r_count + 1)];
        let mut buckets = StreamWriter::new(self.scratch, k, block).map_err(io)?;
        let mut reader = data.reader(WRITE_WORDS);
        let mut rec = [0u32; 10];
        for run in 0..r_count {
            let map = match below {
                Some(b) => b.finals.map(run, runs.nodes(run, level + 1)).map_err(io)?,
                None => Vec::new(),
            };
            for local in 0..runs.nodes(run, level) {
                rec[0] = reader.next().map_err(io)?;
                let len = content_len(leaf, rec[0]);
                for slot in &mut rec[1..len] {
                    let w = reader.next().map_err(io)?;
                    *slot = if leaf {
                        w
                    } else {
                        *map.get(w as usize)
                            .ok_or_else(|| io(corrupt("a child out of range")))?
                    };
                }
                let b = bucket_of(hash_words(&rec[..len]), k);
                rec[len] = local as u32;
                buckets.push(b, &rec[..=len]).map_err(io)?;
                counts[b * (r_count + 1) + run] += 1;
            }
        }
        drop(reader);
        // The runs' records of this level are in the buckets now.
        drop(data);
        let buckets = buckets.finish().map_err(io)?;

        // Step 2: deduplicate each bucket; each distinct record keeps the
        // (run, local id) of its first occurrence.
        let mut distinct = StreamWriter::new(self.scratch, k, block).map_err(io)?;
        let mut assign = StreamWriter::new(self.scratch, k, block).map_err(io)?;
        let mut distinct_counts = vec![0usize; k];
        for b in 0..k {
            let words = buckets.read_all(b).map_err(io)?;
            let row = &counts[b * (r_count + 1)..(b + 1) * (r_count + 1) - 1];
            let total: u64 = row.iter().sum();
            let mut table: HashTable<u32> = HashTable::with_capacity(total as usize);
            let mut firsts: Vec<u32> = Vec::new();
            let content = |at: u32| {
                let at = at as usize;
                &words[at..at + content_len(leaf, words[at])]
            };
            let mut at = 0usize;
            for (run, &n) in row.iter().enumerate() {
                for _ in 0..n {
                    let len = content_len(leaf, words[at]);
                    let this = &words[at..at + len];
                    let local = words[at + len];
                    let h = table_hash(hash_words(this));
                    let entry = table.entry(
                        h,
                        |&j| content(firsts[j as usize]) == this,
                        |&j| table_hash(hash_words(content(firsts[j as usize]))),
                    );
                    let j = match entry {
                        hashbrown::hash_table::Entry::Occupied(e) => *e.get(),
                        hashbrown::hash_table::Entry::Vacant(e) => {
                            let j = firsts.len() as u32;
                            e.insert(j);
                            firsts.push(at as u32);
                            distinct.push(b, &[run as u32, local]).map_err(io)?;
                            distinct.push(b, this).map_err(io)?;
                            j
                        }
                    };
                    assign.push(b, &[local, j]).map_err(io)?;
                    at += len + 1;
                }
            }
            distinct.close(b).map_err(io)?;
            assign.close(b).map_err(io)?;
            distinct_counts[b] = firsts.len();
        }
        drop(buckets);
        let distinct = distinct.finish().map_err(io)?;
        let assign = assign.finish().map_err(io)?;

        // Step 3: lay the level out in first-occurrence order (a K-way merge
        // on (run, local id)), which is the order of an in-memory build.
        let mut section = SectionWriter::new(self.scratch).map_err(io)?;
        let mut finals = StreamWriter::new(self.scratch, k, block).map_err(io)?;
        let read_cap = ((self.budget / 4) as usize / k / 4).clamp(256, 1 << 16);
        let mut cursors: Vec<WordReader<'_>> =
            (0..k).map(|b| distinct.reader(b, read_cap)).collect();
        let mut heap = BinaryHeap::with_capacity(k);
        let next_key = |c: &mut WordReader<'_>| -> io::Result<Option<u64>> {
            if c.remaining() == 0 {
                return Ok(None);
            }
            let run = c.next()?;
            let local = c.next()?;
            Ok(Some(u64::from(run) << 32 | u64::from(local)))
        };
        for (b, c) in cursors.iter_mut().enumerate() {
            if let Some(key) = next_key(c).map_err(io)? {
                heap.push(Reverse((key, b)));
            }
        }
        let mut units = 0u64;
        let mut items = 0u64;
        let mut out = Vec::with_capacity(1 << 16);
        let mut rec = [0u32; 9];
        while let Some(Reverse((_, b))) = heap.pop() {
            let c = &mut cursors[b];
            rec[0] = c.next().map_err(io)?;
            let len = content_len(leaf, rec[0]);
            for slot in &mut rec[1..len] {
                *slot = c.next().map_err(io)?;
            }
            let position = u32::try_from(units).map_err(|_| {
                build_error(BuildError::TooLarge {
                    what: format!("level {level} has more than 2^32 units"),
                })
            })?;
            if leaf {
                let mask = u64::from(rec[0]) | u64::from(rec[1]) << 32;
                out.extend_from_slice(&mask.to_le_bytes());
                units += 1;
            } else {
                let mask = rec[0] as u8;
                layout::encode_node_record(
                    mask,
                    rec[0] >> layout::CHILD_MASK_BITS,
                    &rec[1..len],
                    width,
                    &mut out,
                );
                units += layout::node_record_size(mask.count_ones(), width) / 4;
            }
            items += 1;
            finals.push(b, &[position]).map_err(io)?;
            if out.len() >= 1 << 16 {
                section.write(&out).map_err(io)?;
                out.clear();
            }
            if let Some(key) = next_key(c).map_err(io)? {
                heap.push(Reverse((key, b)));
            }
        }
        section.write(&out).map_err(io)?;
        drop(cursors);
        drop(distinct);
        if leaf && units > MAX_LEAF_COUNT {
            return Err(build_error(BuildError::TooLarge {
                what: format!("{units} leaves exceed the limit of {MAX_LEAF_COUNT}"),
            }));
        }
        if !leaf && units * 4 > MAX_NODE_LEVEL_BYTES {
            return Err(build_error(BuildError::TooLarge {
                what: format!("level {level} exceeds {MAX_NODE_LEVEL_BYTES} bytes"),
            }));
        }
        let finals = finals.finish().map_err(io)?;
        let (file, length, crc) = section.finish().map_err(io)?;
        let info = if leaf {
            SectionInfo::leaf_level(level, items, crc)
        } else {
            SectionInfo::node_level(level, width, length, items, crc)
        };
        debug_assert_eq!(info.length, length);

        // Step 4: the per-run maps "local id → final position", per bucket
        // in run order.
        let mut pairs = StreamWriter::new(self.scratch, k, block).map_err(io)?;
        for (b, &expected) in distinct_counts.iter().enumerate() {
            let positions = finals.read_all(b).map_err(io)?;
            if positions.len() != expected {
                return Err(io(corrupt("a bucket's positions")));
            }
            let mut a = assign.reader(b, read_cap);
            for _ in 0..assign.len(b) / 2 {
                let local = a.next().map_err(io)?;
                let j = a.next().map_err(io)?;
                let position = *positions
                    .get(j as usize)
                    .ok_or_else(|| io(corrupt("a distinct index out of range")))?;
                pairs.push(b, &[local, position]).map_err(io)?;
            }
            pairs.close(b).map_err(io)?;
        }
        // Record counts per (bucket, run) become the start of each run's
        // segment in its bucket's stream.
        for row in counts.chunks_exact_mut(r_count + 1) {
            let mut sum = 0;
            for c in row.iter_mut() {
                let n = *c;
                *c = sum;
                sum += n;
            }
        }
        Ok(MergedLevel {
            section: SectionFile { file, info },
            units,
            finals: Finals {
                pairs: pairs.finish().map_err(io)?,
                runs: r_count,
                starts: counts,
            },
            buckets: k,
        })
    }
}

// ---------------------------------------------------------------------------
// The merge in memory.

/// Joins runs like [`RunMerge`], but in memory, without temporary files: the
/// distinct records of each level in a hash-sharded table
/// ([`crate::dedup::ShardedTable`], looked up on every core), filled run after
/// run. Each run gives its records bottom-up, one level at a time (its leaves
/// to [`MemoryMerge::leaves`], then each level up to the split level to
/// [`MemoryMerge::nodes`], children as the indices returned for the level
/// below), then its roots. A record gets the next index of its level the
/// first time it is seen, so the indices are the first-seen order of the
/// runs in order, each in its own order: the order of one in-memory build of
/// all their voxels (as in the out-of-core merge), and the file is that
/// build's, byte for byte, however many threads ran.
///
/// It holds every distinct record of the levels `split ..= D − 2` as words
/// (header, then child indices), each record's offset, and a table slot per
/// record (its index and offset, so that a lookup reads the table and then
/// the record: no third access); [`MemoryMerge::estimate`] bounds that from
/// the runs' sizes, so a caller can choose it when it fits its memory and
/// [`RunMerge`] otherwise.
pub struct MemoryMerge {
    depth: u8,
    attributes: AttributeKind,
    split: u8,
    leaves: Vec<u64>,
    leaf_table: ShardedTable,
    /// Levels `split .. D − 2`, index `level − split`.
    nodes: Vec<NodeLevel>,
    /// Per root: Morton code of its level-`split` cell, index, voxel count.
    roots: Vec<(u64, u32, u64)>,
}

impl std::fmt::Debug for MemoryMerge {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MemoryMerge")
            .field("depth", &self.depth)
            .field("split", &self.split)
            .field("leaves", &self.leaves.len())
            .field("roots", &self.roots.len())
            .finish_non_exhaustive()
    }
}

/// The distinct records of one interior level, in first-seen order.
#[derive(Default)]
struct NodeLevel {
    /// Each record's header word, then its children's indices in the level
    /// below.
    words: Vec<u32>,
    /// Each record's offset in `words`.
    starts: Vec<u32>,
    /// Keys: offsets in `words` (of the batch's words while pending).
    table: ShardedTable,
}

/// Records of one interior level of one run, in the run's order: each
/// record's header word, then its children's indices in the merged level
/// below ([`MemoryMerge::nodes`]).
#[derive(Debug, Default)]
pub struct NodeBatch {
    /// The records' words.
    pub words: Vec<u32>,
    /// Each record's offset in `words`.
    pub starts: Vec<u32>,
}

impl NodeBatch {
    /// Appends `other`'s records.
    pub fn append(&mut self, other: &NodeBatch) {
        let at = self.words.len() as u32;
        self.words.extend_from_slice(&other.words);
        self.starts.extend(other.starts.iter().map(|&s| s + at));
    }
}

/// Bytes per expected record of the levels' words (beside their content).
const START_BYTES_PER_RECORD: u64 = 4;

impl MemoryMerge {
    /// A merge of depth-`depth` runs split at level `split` (1 ..= D − 2).
    pub fn new(depth: u8, attributes: AttributeKind, split: u8) -> Result<Self, ConvertError> {
        if depth < 3 || !(1..=depth - 2).contains(&split) {
            return Err(ConvertError::Usage(format!(
                "split level {split} is outside 1..={} for depth {depth}",
                depth.saturating_sub(2)
            )));
        }
        Ok(MemoryMerge {
            depth,
            attributes,
            split,
            leaves: Vec::new(),
            leaf_table: ShardedTable::new(),
            nodes: (split..depth - 2).map(|_| NodeLevel::default()).collect(),
            roots: Vec::new(),
        })
    }

    /// An upper bound of the bytes the merge holds for runs whose level
    /// `level` has `records` records with `words` words of content (header
    /// and children) in all, per level.
    pub fn estimate(levels: impl IntoIterator<Item = (u64, u64)>) -> u64 {
        levels
            .into_iter()
            .map(|(records, words)| {
                4 * words + (START_BYTES_PER_RECORD + crate::dedup::BYTES_PER_ENTRY) * records
            })
            .sum()
    }

    /// An upper bound of the bytes a batch of `records` records with `words`
    /// words of content takes while it is decoded and merged (its words and
    /// offsets, twice while its decoded pieces are joined, each record's
    /// offset in the run, and the tables' working arrays).
    pub fn batch_estimate(records: u64, words: u64) -> u64 {
        8 * words + (12 + crate::dedup::BATCH_BYTES_PER_RECORD) * records
    }

    /// Makes room for `records` more records of `level` with `words` words
    /// of content (upper bounds: the runs' records before deduplication), so
    /// that the tables do not grow (and briefly hold twice their size, and
    /// rehash) while the runs are given.
    pub fn reserve(&mut self, level: u8, records: u64, words: u64) {
        if level == self.depth - 2 {
            self.leaves.reserve(records as usize);
            self.leaf_table.reserve(records, leaf_hash);
        } else if let Some(n) = level
            .checked_sub(self.split)
            .and_then(|i| self.nodes.get_mut(usize::from(i)))
        {
            n.words.reserve(words as usize);
            n.starts.reserve(records as usize);
            let NodeLevel { words, table, .. } = n;
            table.reserve(records, |at| node_hash(words, at as u32));
        }
    }

    /// The indices of the leaf masks `masks`, in order: the next ones for
    /// those not seen before.
    pub fn leaves(&mut self, masks: &[u64]) -> Result<Vec<u32>, ConvertError> {
        let hashes: Vec<u64> = masks.par_iter().map(|&m| leaf_hash(m)).collect();
        let base = self.leaves.len() as u64;
        let found = self.leaf_table.find_or_insert(
            base,
            &hashes,
            |i| masks[i],
            |i, _, key| key == masks[i],
            leaf_hash,
        );
        let leaves = &mut self.leaves;
        let ids = crate::dedup::number_first_seen(&found, base, |i| {
            let id = u32::try_from(leaves.len())
                .ok()
                .filter(|&id| u64::from(id) < MAX_LEAF_COUNT)
                .ok_or_else(|| {
                    build_error(BuildError::TooLarge {
                        what: format!("more than {MAX_LEAF_COUNT} leaves"),
                    })
                })?;
            leaves.push(masks[i]);
            Ok(id)
        })?;
        self.leaf_table.settle(base, &ids, |_, mask| mask);
        Ok(ids)
    }

    /// The indices of the records of `batch` of interior `level` (`split ..
    /// D − 2`), in order: the next ones for those not seen before. Every
    /// record's children must be indices of the level below, as many as its
    /// header's child mask has bits.
    pub fn nodes(&mut self, level: u8, batch: &NodeBatch) -> Result<Vec<u32>, ConvertError> {
        let leaf = self.depth - 2;
        let below = if level + 1 == leaf {
            self.leaves.len()
        } else {
            level
                .checked_sub(self.split)
                .and_then(|i| self.nodes.get(usize::from(i) + 1))
                .map_or(0, |n| n.starts.len())
        };
        let words_end = batch.words.len();
        let misfit = (self.split..leaf).contains(&level).then(|| {
            batch.starts.par_iter().enumerate().find_any(|&(i, &s)| {
                let s = s as usize;
                let end = batch.starts.get(i + 1).map_or(words_end, |&e| e as usize);
                let fits = s < end
                    && end <= words_end
                    && (batch.words[s] & 0xFF).count_ones() as usize == end - s - 1
                    && batch.words[s + 1..end]
                        .iter()
                        .all(|&c| (c as usize) < below);
                !fits
            })
        });
        let bad = match misfit {
            None => Some(None),
            Some(Some((i, _))) => Some(Some(i)),
            Some(None) => None,
        };
        if let Some(i) = bad {
            let record = i.map_or(String::new(), |i| {
                let s = batch.starts[i] as usize;
                let e = batch.starts.get(i + 1).map_or(words_end, |&e| e as usize);
                format!(" {:?}", &batch.words[s..e.max(s).min(words_end)])
            });
            return Err(ConvertError::Input(format!(
                "a record{record} of level {level} does not fit levels {}..{leaf} ({below} records below)",
                self.split
            )));
        }
        let n = &mut self.nodes[usize::from(level - self.split)];
        let NodeLevel {
            words,
            starts,
            table,
        } = n;
        let hashes: Vec<u64> = batch
            .starts
            .par_iter()
            .map(|&s| node_hash(&batch.words, s))
            .collect();
        let base = starts.len() as u64;
        let found = {
            let words = &*words;
            table.find_or_insert(
                base,
                &hashes,
                |i| u64::from(batch.starts[i]),
                |i, value, key| {
                    let record = node_content(&batch.words, batch.starts[i]);
                    let held = if value < base {
                        node_content(words, key as u32)
                    } else {
                        node_content(&batch.words, key as u32)
                    };
                    record == held
                },
                |at| node_hash(words, at as u32),
            )
        };
        let too_large = || {
            build_error(BuildError::TooLarge {
                what: format!("level {level} has more than 2^32 words of records"),
            })
        };
        let ids = crate::dedup::number_first_seen(&found, base, |i| {
            let id = u32::try_from(starts.len()).map_err(|_| too_large())?;
            let record = node_content(&batch.words, batch.starts[i]);
            let at = u32::try_from(words.len()).map_err(|_| too_large())?;
            u32::try_from(words.len() + record.len()).map_err(|_| too_large())?;
            words.extend_from_slice(record);
            starts.push(at);
            Ok(id)
        })?;
        let starts = &*starts;
        table.settle(base, &ids, |id, _| u64::from(starts[id as usize]));
        Ok(ids)
    }

    /// Adds a root: the Morton code of its level-`split` cell (strictly
    /// increasing over all runs), the index of its record (or leaf) and its
    /// voxel count.
    pub fn push_root(&mut self, code: u64, index: u32, count: u64) -> Result<(), ConvertError> {
        let records = match self.nodes.first() {
            Some(n) => n.starts.len(),
            None => self.leaves.len(),
        };
        if self.roots.last().is_some_and(|r| r.0 >= code) || index as usize >= records {
            return Err(ConvertError::Input(format!(
                "subtree {code} (index {index}) is out of Morton order or refers to no record"
            )));
        }
        self.roots.push((code, index, count));
        Ok(())
    }

    /// Lays the levels out: pointer widths and offsets from the leaves up,
    /// then the levels above the split from the roots.
    pub fn finish(self) -> Result<FinishedDag, ConvertError> {
        let t = std::time::Instant::now();
        if self.roots.is_empty() {
            return FinishedDag::empty_volume(self.depth, self.attributes);
        }
        let MemoryMerge {
            depth,
            attributes,
            split,
            leaves,
            leaf_table,
            nodes,
            roots,
        } = self;
        drop(leaf_table);
        let leaf = depth - 2;
        let leaf_crc = leaves.chunks(1 << 13).fold(0, |crc, chunk| {
            let bytes: Vec<u8> = chunk.iter().flat_map(|m| m.to_le_bytes()).collect();
            crc32c::crc32c_append(crc, &bytes)
        });
        let leaf_info = SectionInfo::leaf_level(leaf, leaves.len() as u64, leaf_crc);
        let mut below_units = leaves.len() as u64;
        let mut levels: Vec<MemoryLevel> = vec![MemoryLevel::Leaves {
            masks: leaves,
            info: leaf_info,
        }];
        for (i, n) in nodes.into_iter().enumerate().rev() {
            let level = split + i as u8;
            let NodeLevel {
                words,
                starts,
                table,
            } = n;
            drop(table);
            let records = starts.len();
            drop(starts);
            let width = layout::minimal_pointer_width(below_units).ok_or_else(|| {
                build_error(BuildError::TooLarge {
                    what: format!(
                        "level {} has {below_units} units, more than 4-byte pointers address",
                        level + 1
                    ),
                })
            })?;
            // Each record's offset in units (words): its start, once the
            // sizes of the records before it at this width are known.
            let mut units = vec![0u32; records];
            let mut at = 0u64;
            let mut w = 0usize;
            for u in &mut units {
                let children = (words[w] & 0xFF).count_ones();
                *u = u32::try_from(at).map_err(|_| {
                    build_error(BuildError::TooLarge {
                        what: format!("level {level} has more than 2^32 units"),
                    })
                })?;
                at += layout::node_record_size(children, width) / 4;
                w += 1 + children as usize;
            }
            if at * 4 > MAX_NODE_LEVEL_BYTES {
                return Err(build_error(BuildError::TooLarge {
                    what: format!("level {level} exceeds {MAX_NODE_LEVEL_BYTES} bytes"),
                }));
            }
            let count = units.len() as u64;
            let mut this = MemoryLevel::Nodes {
                words,
                units,
                width,
                info: SectionInfo::node_level(level, width, at * 4, count, 0),
            };
            let below = levels.last().expect("the level below");
            let mut crc = 0;
            this.emit(below, &mut |bytes| {
                crc = crc32c::crc32c_append(crc, bytes);
                Ok(())
            })
            .expect("a sink that cannot fail");
            if let MemoryLevel::Nodes { info, .. } = &mut this {
                info.crc = crc;
            }
            below_units = at;
            levels.push(this);
        }
        levels.reverse();
        let mut upper = UpperBuilder::new(depth, attributes, split).map_err(build_error)?;
        for &(code, index, count) in &roots {
            upper
                .push_subtree(code, levels[0].unit(index), count)
                .map_err(build_error)?;
        }
        let upper = upper.finish(below_units).map_err(build_error)?;
        Ok(FinishedDag {
            inner: Inner::Memory(MemoryDag {
                upper,
                levels,
                split,
            }),
            cells: Vec::new(),
            report: SpillReport {
                runs: 0,
                max_buckets: 0,
                merge_seconds: t.elapsed().as_secs_f64(),
            },
        })
    }
}

#[inline]
fn leaf_hash(mask: u64) -> u64 {
    table_hash(mask ^ 0x9e37_79b9_7f4a_7c15)
}

#[inline]
fn node_content(words: &[u32], start: u32) -> &[u32] {
    let at = start as usize;
    &words[at..at + 1 + (words[at] & 0xFF).count_ones() as usize]
}

#[inline]
fn node_hash(words: &[u32], start: u32) -> u64 {
    table_hash(hash_words(node_content(words, start)))
}

/// A level merged in memory, ready to be encoded.
#[derive(Debug)]
enum MemoryLevel {
    Leaves {
        masks: Vec<u64>,
        info: SectionInfo,
    },
    Nodes {
        /// Header, then child indices, per record.
        words: Vec<u32>,
        /// Each record's offset in the level, in words.
        units: Vec<u32>,
        width: u8,
        info: SectionInfo,
    },
}

impl MemoryLevel {
    /// The pointer to the record or leaf of index `index`.
    #[inline]
    fn unit(&self, index: u32) -> u32 {
        match self {
            MemoryLevel::Leaves { .. } => index,
            MemoryLevel::Nodes { units, .. } => units[index as usize],
        }
    }

    fn info(&self) -> SectionInfo {
        match self {
            MemoryLevel::Leaves { info, .. } | MemoryLevel::Nodes { info, .. } => *info,
        }
    }

    /// Encodes the level in chunks; `below` is the level below (its
    /// pointers), unused for the leaves.
    fn emit(
        &self,
        below: &MemoryLevel,
        sink: &mut dyn FnMut(&[u8]) -> io::Result<()>,
    ) -> io::Result<()> {
        const CHUNK: usize = 1 << 16;
        let mut out: Vec<u8> = Vec::with_capacity(CHUNK + 64);
        match self {
            MemoryLevel::Leaves { masks, .. } => {
                for chunk in masks.chunks(CHUNK / 8) {
                    out.clear();
                    for m in chunk {
                        out.extend_from_slice(&m.to_le_bytes());
                    }
                    sink(&out)?;
                }
            }
            MemoryLevel::Nodes { words, width, .. } => {
                let mut pointers = [0u32; 8];
                let mut at = 0usize;
                while at < words.len() {
                    let header = words[at];
                    let c = (header & 0xFF).count_ones() as usize;
                    for (p, &child) in pointers.iter_mut().zip(&words[at + 1..at + 1 + c]) {
                        *p = below.unit(child);
                    }
                    layout::encode_node_record(
                        header as u8,
                        header >> layout::CHILD_MASK_BITS,
                        &pointers[..c],
                        *width,
                        &mut out,
                    );
                    at += 1 + c;
                    if out.len() >= CHUNK {
                        sink(&out)?;
                        out.clear();
                    }
                }
                sink(&out)?;
            }
        }
        Ok(())
    }
}

/// Levels merged in memory: the upper levels, and levels `split ..= leaf`
/// as distinct records, encoded as they are written.
#[derive(Debug)]
pub struct MemoryDag {
    upper: UpperLevels,
    /// Levels `split ..= leaf`.
    levels: Vec<MemoryLevel>,
    split: u8,
}

// ---------------------------------------------------------------------------
// The result.

/// Levels built out of core: the upper levels in memory, the others in
/// temporary files.
#[derive(Debug)]
pub struct ExternalDag {
    upper: UpperLevels,
    /// Levels `split ..= leaf`.
    lower: Vec<SectionFile>,
    split: u8,
}

#[derive(Debug)]
enum Inner {
    InCore(BuiltDag),
    External(ExternalDag),
    Memory(MemoryDag),
}

/// A finished DAG, in memory or in temporary files, ready to be written.
#[derive(Debug)]
pub struct FinishedDag {
    inner: Inner,
    /// Occupied cells per level.
    cells: Vec<u128>,
    report: SpillReport,
}

impl FinishedDag {
    /// The empty volume (no voxels), as an in-memory build makes it: what a
    /// merge of no runs or no parts' roots finishes with.
    fn empty_volume(depth: u8, attributes: AttributeKind) -> Result<FinishedDag, ConvertError> {
        let built = DagBuilder::new(depth, attributes)
            .and_then(DagBuilder::finish)
            .map_err(build_error)?;
        Ok(FinishedDag {
            inner: Inner::InCore(built),
            cells: Vec::new(),
            report: SpillReport::default(),
        })
    }

    /// Set voxels.
    pub fn voxel_count(&self) -> u64 {
        match &self.inner {
            Inner::InCore(b) => b.voxel_count(),
            Inner::External(e) => e.upper.voxel_count(),
            Inner::Memory(m) => m.upper.voxel_count(),
        }
    }

    /// What spilling did.
    pub fn report(&self) -> &SpillReport {
        &self.report
    }

    /// The level sections, root first.
    pub fn level_sections(&self) -> Vec<SectionInfo> {
        match &self.inner {
            Inner::InCore(b) => b.layout().sections().to_vec(),
            Inner::External(e) => {
                let mut s = e.upper.sections();
                s.extend(e.lower.iter().map(|f| f.info));
                s
            }
            Inner::Memory(m) => {
                let mut s = m.upper.sections();
                s.extend(m.levels.iter().map(MemoryLevel::info));
                s
            }
        }
    }

    /// Hands the bytes of level section `index` to `sink`.
    pub fn emit_level(
        &self,
        index: usize,
        sink: &mut dyn FnMut(&[u8]) -> io::Result<()>,
    ) -> io::Result<()> {
        match &self.inner {
            Inner::InCore(b) => b.emit_section(index, sink),
            Inner::External(e) => match index.checked_sub(usize::from(e.split)) {
                None => e.upper.emit_section(index, sink),
                Some(i) => e.lower[i].emit(sink),
            },
            Inner::Memory(m) => match index.checked_sub(usize::from(m.split)) {
                None => m.upper.emit_section(index, sink),
                Some(i) => {
                    let level = &m.levels[i];
                    level.emit(m.levels.get(i + 1).unwrap_or(level), sink)
                }
            },
        }
    }

    /// Per-level statistics.
    pub fn level_stats(&self) -> Vec<LevelStats> {
        self.level_sections()
            .iter()
            .zip(&self.cells)
            .map(|(s, &cells)| LevelStats {
                level: s.level,
                node_count: s.item_count,
                bytes: s.length,
                pointer_width: s.pointer_width,
                tree_nodes: cells,
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cell_counter_counts_tree_nodes() {
        let mut state = 7u64;
        for depth in [2u8, 3, 5, 7] {
            let mut voxels = Vec::new();
            let side = 1u64 << depth;
            for _ in 0..200 {
                state = state.wrapping_mul(6364136223846793005).wrapping_add(1);
                let r = state >> 11;
                voxels.push([
                    (r % side) as u32,
                    ((r >> 16) % side) as u32,
                    ((r >> 32) % side) as u32,
                ]);
            }
            let built =
                DagBuilder::from_voxels(depth, AttributeKind::VoxelCount, voxels.clone()).unwrap();
            let mut bricks: Vec<u64> = voxels
                .iter()
                .map(|v| dagfmt::morton::encode(v[0], v[1], v[2]) >> 6)
                .collect();
            bricks.sort_unstable();
            bricks.dedup();
            let mut counter = CellCounter::new(depth);
            for b in bricks {
                counter.add(b);
            }
            let expected: Vec<u128> = built.level_stats().iter().map(|s| s.tree_nodes).collect();
            assert_eq!(counter.cells(), expected, "depth {depth}");
        }
    }
}
