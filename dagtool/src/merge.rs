//! `dagtool merge`: joins parts (spec § 24) into a larger part or, when they
//! cover the whole root cube, into the file one `dagtool convert` of the
//! whole input writes, byte for byte.
//!
//! Every part is validated first (the format's rules, then the part rules
//! E090–E094); the parts must agree on depth, root cube, attributes, region
//! level and colours (E095), must not overlap (E096) and must cover one
//! contiguous Morton range of cells (E097). Each part is then one *run* of
//! the level merge: a part is the canonical DAG of a Morton range of
//! complete subtrees, its records in first-seen order, which is what a
//! spilled run of one conversion holds. When the parts' records fit the
//! memory limit they are deduplicated in one hash table per level, part
//! after part, each part's level looked up on every core in tables sharded
//! by hash ([`crate::external::MemoryMerge`]); otherwise by the
//! out-of-core level merge ([`crate::external::RunMerge`]), which works
//! within any budget through temporary files. Both deduplicate exactly and
//! give the same bytes, and the result does not depend on how the parts were
//! grouped: merging is associative, and parts of parts are parts.
//!
//! The parts are validated in parallel (one thread per core), and each
//! part's file is mapped only while it is validated and while it is read
//! into the merge, so the merge's resident memory is its tables, not the
//! parts.

use std::ops::Range;
use std::path::{Path, PathBuf};
use std::time::Instant;

use dagfmt::assemble::FileHeader;
use dagfmt::mmap::MappedFile;
use dagfmt::reader::{LevelSection, NodeRef};
use dagfmt::validate::{ValidateOptions, validate_with};
use dagfmt::{AnyDag, Dag, FormatError};

use crate::error::ConvertError;
use rayon::prelude::*;

use crate::external::{ColourSink, MIN_MERGE_BUDGET, MemoryMerge, NodeBatch, RunMerge, Scratch};
use crate::output::check_output;
use crate::region::{ColourMode, Placement, Region, check_part, rules};
use crate::sysinfo::{MemoryMeter, total_memory};

/// Options of `dagtool merge`.
#[derive(Clone, Debug)]
pub struct MergeOptions {
    /// Memory limit in bytes (`None`: 3/4 of physical memory).
    pub memory_limit: Option<u64>,
    /// Replace an existing output file.
    pub force: bool,
    /// Directory of the temporary files (`None`: the output's directory).
    pub tmp_dir: Option<PathBuf>,
    /// Testing: the number of buckets of every level's merge (forces the
    /// out-of-core merge).
    pub buckets: Option<u32>,
    /// The major format version of the whole-volume file: 2 (the default,
    /// as `dagtool convert`'s) or 1. A merge that does not cover the whole
    /// root cube writes a part, which is always format 1 (spec §24.3).
    pub format_version: u16,
}

impl Default for MergeOptions {
    fn default() -> Self {
        MergeOptions {
            memory_limit: None,
            force: false,
            tmp_dir: None,
            buckets: None,
            format_version: 2,
        }
    }
}

/// What a merge did.
#[derive(Clone, Debug)]
pub struct MergeSummary {
    /// Parts read.
    pub parts: usize,
    /// The region level K of the parts.
    pub region_level: u8,
    /// The Morton range of level-K cells the output covers.
    pub cells: Range<u64>,
    /// Whether the output covers the whole root cube, and is therefore an
    /// ordinary `.vdag` (no placement) rather than a part.
    pub complete: bool,
    /// The major format version written: the one asked for the whole
    /// volume, 1 for a part.
    pub format_version: u16,
    /// Depth D.
    pub depth: u8,
    /// Set voxels.
    pub voxels: u64,
    /// Distinct nodes per level, root first.
    pub level_nodes: Vec<u64>,
    /// Bytes of the output file.
    pub file_bytes: u64,
    /// Bytes read from the parts.
    pub input_bytes: u64,
    /// Buckets of the largest level's merge.
    pub max_buckets: u64,
    /// Bytes written to temporary files.
    pub temp_bytes: u64,
    /// Whether the levels were merged in memory (else out of core).
    pub in_memory: bool,
    /// Seconds spent validating the parts.
    pub validate_seconds: f64,
    /// Seconds spent reading the parts into the merge and merging their
    /// levels (after validating).
    pub merge_seconds: f64,
    /// Seconds spent writing the output (encoding it, in 2.0).
    pub write_seconds: f64,
    /// Total seconds.
    pub total_seconds: f64,
}

impl MergeSummary {
    /// The summary as text for people.
    pub fn render(&self, output: &Path) -> String {
        format!(
            "merged:   {} part{} of level {} (cells {}..{} of {}), depth {}\n\
             voxels:   {}\n\
             nodes:    {:?} per level\n\
             output:   {} ({} bytes, {}, format {}.0)\n\
             time:     {:.2} s ({:.2} s validating {} bytes of parts, {:.2} s merging, {:.2} s writing; {}, {} temporary bytes, up to {} buckets per level)\n",
            self.parts,
            if self.parts == 1 { "" } else { "s" },
            self.region_level,
            self.cells.start,
            self.cells.end,
            1u64 << (3 * u32::from(self.region_level)),
            self.depth,
            self.voxels,
            self.level_nodes,
            output.display(),
            self.file_bytes,
            if self.complete {
                "the whole volume"
            } else {
                "a part"
            },
            self.format_version,
            self.total_seconds,
            self.validate_seconds,
            self.input_bytes,
            self.merge_seconds,
            self.write_seconds,
            if self.in_memory {
                "in memory"
            } else {
                "out of core"
            },
            self.temp_bytes,
            self.max_buckets,
        )
    }
}

/// A part checked: its placement, and what the merge needs to size itself.
/// Its file is mapped again when it is read into the merge.
struct Part {
    path: PathBuf,
    placement: Placement,
    header: dagfmt::reader::Header,
    bytes: u64,
    /// Per level, root first: records, and an upper bound of the words of
    /// their content (header and children).
    levels: Vec<(u64, u64)>,
}

impl Part {
    /// Maps the part again to read it; refuses a file that changed since it
    /// was validated.
    fn map(&self) -> Result<MappedFile, ConvertError> {
        let file = MappedFile::open(&self.path).map_err(|e| {
            ConvertError::io(format!("cannot read part {}", self.path.display()), e)
        })?;
        if file.bytes().len() as u64 != self.bytes {
            return Err(ConvertError::Input(format!(
                "part {} changed while it was merged",
                self.path.display()
            )));
        }
        Ok(file)
    }
}

fn part_error(
    path: &Path,
    code: &str,
    name: &str,
    message: impl std::fmt::Display,
) -> ConvertError {
    ConvertError::Input(format!("{code} {name}: {}: {message}", path.display()))
}

/// Opens, validates and checks one part.
fn open_part(path: &Path) -> Result<Part, ConvertError> {
    let file = MappedFile::open(path)
        .map_err(|e| ConvertError::io(format!("cannot read part {}", path.display()), e))?;
    let report = validate_with(
        file.bytes(),
        &ValidateOptions {
            max_errors: 1,
            ..Default::default()
        },
    );
    if let Some(e) = report.errors.first() {
        return Err(part_error(
            path,
            e.code.code(),
            e.code.name(),
            format!("invalid at byte {:#x}: {}", e.offset, e.message),
        ));
    }
    // Parts are format 1 (spec §24.1): a valid 2.0 file is an ordinary file.
    if let Ok(AnyDag::V2(_)) = AnyDag::open(file.bytes()) {
        let (code, name) = rules::NOT_A_PART;
        return Err(part_error(
            path,
            code,
            name,
            "a format 2.0 file is not a part (parts are format 1; make them with convert --region)",
        ));
    }
    let dag = Dag::open(file.bytes()).map_err(|e| format_error(path, &e))?;
    let placement = match check_part(&dag) {
        Ok(Some(p)) => p,
        Ok(None) => {
            let (code, name) = rules::NOT_A_PART;
            return Err(part_error(
                path,
                code,
                name,
                "a .vdag without a PART_PLACEMENT section is not a part (make parts with convert --region)",
            ));
        }
        Err(e) => {
            return Err(part_error(
                path,
                e.code,
                e.name,
                format!("at byte {:#x}: {}", e.offset, e.message),
            ));
        }
    };
    let levels = dag
        .levels()
        .iter()
        .map(|s| {
            let words = if s.is_leaf {
                2 * s.node_count
            } else {
                // Each child takes at least `pointer_width` bytes.
                let pointer_bytes = (s.bytes.len() as u64).saturating_sub(4 * s.node_count);
                s.node_count + pointer_bytes / u64::from(s.pointer_width.max(1))
            };
            (s.node_count, words)
        })
        .collect();
    let header = dag.header().clone();
    Ok(Part {
        path: path.to_path_buf(),
        placement,
        header,
        bytes: file.bytes().len() as u64,
        levels,
    })
}

/// Opens and checks every part, on every core; the first failure in the
/// order of `parts`.
fn open_parts(parts: &[PathBuf]) -> Result<Vec<Part>, ConvertError> {
    let threads = std::thread::available_parallelism()
        .map_or(1, usize::from)
        .min(parts.len());
    if threads <= 1 {
        return parts.iter().map(|p| open_part(p)).collect();
    }
    let next = std::sync::atomic::AtomicUsize::new(0);
    let mut results: Vec<Option<Result<Part, ConvertError>>> = Vec::new();
    results.resize_with(parts.len(), || None);
    let done = std::sync::Mutex::new(results);
    std::thread::scope(|s| {
        for _ in 0..threads {
            s.spawn(|| {
                loop {
                    let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    let Some(path) = parts.get(i) else { break };
                    let r = open_part(path);
                    done.lock().expect("no thread panics holding it")[i] = Some(r);
                }
            });
        }
    });
    done.into_inner()
        .expect("no thread panics holding it")
        .into_iter()
        .map(|r| r.expect("every part was opened"))
        .collect()
}

fn format_error(path: &Path, e: &FormatError) -> ConvertError {
    part_error(
        path,
        e.code.code(),
        e.code.name(),
        format!("at byte {:#x}: {}", e.offset, e.message),
    )
}

/// Merges `parts` into `output`: a part covering their cells or, when they
/// cover the whole root cube, the ordinary `.vdag` of the whole volume
/// (byte-identical to one conversion of the whole input). Nothing is
/// written unless it succeeds.
pub fn merge(
    parts: &[PathBuf],
    output: &Path,
    opts: &MergeOptions,
) -> Result<MergeSummary, ConvertError> {
    let start = Instant::now();
    // The memory limit is on what the merge adds to the process.
    let meter = MemoryMeter::start();
    if parts.is_empty() {
        return Err(ConvertError::Usage("merge needs at least one part".into()));
    }
    if !(1..=2).contains(&opts.format_version) {
        return Err(ConvertError::Usage(format!(
            "--format-version {}: the format versions are 1 and 2",
            opts.format_version
        )));
    }
    check_output(output, opts.force)?;
    let out_dir = dagfmt::output::output_dir(output);
    let tmp_dir = opts.tmp_dir.clone().unwrap_or_else(|| out_dir.clone());
    let scratch = Scratch::new(&tmp_dir)?;
    let limit = opts
        .memory_limit
        .unwrap_or_else(|| total_memory().map_or(8 << 30, |m| m / 4 * 3));

    let mut opened = open_parts(parts)?;
    let validate_seconds = start.elapsed().as_secs_f64();
    opened.sort_by_key(|p| p.placement.cells.start);

    // One volume: the same depth, root cube, attributes, level and colours.
    let header = opened[0].header.clone();
    let placement0 = opened[0].placement.clone();
    for p in &opened[1..] {
        let h = &p.header;
        let differ = if h.depth != header.depth {
            Some(format!("depth {} against {}", h.depth, header.depth))
        } else if h.root_min.map(f64::to_bits) != header.root_min.map(f64::to_bits)
            || h.root_size.to_bits() != header.root_size.to_bits()
        {
            Some(format!(
                "root cube {:?} size {} against {:?} size {}",
                h.root_min, h.root_size, header.root_min, header.root_size
            ))
        } else if h.attribute_kind != header.attribute_kind {
            Some(format!(
                "attribute kind {} against {}",
                h.attribute_kind.to_raw(),
                header.attribute_kind.to_raw()
            ))
        } else if p.placement.level != placement0.level {
            Some(format!(
                "region level {} against {}",
                p.placement.level, placement0.level
            ))
        } else if p.placement.colours != placement0.colours {
            Some(format!(
                "{} against {}",
                p.placement.colours, placement0.colours
            ))
        } else {
            None
        };
        if let Some(d) = differ {
            let (code, name) = rules::MISMATCH;
            return Err(ConvertError::Input(format!(
                "{code} {name}: {} and {} are not parts of one volume: {d}",
                p.path.display(),
                opened[0].path.display()
            )));
        }
    }
    for w in opened.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        let (ra, rb) = (&a.placement.cells, &b.placement.cells);
        if rb.start < ra.end {
            let (code, name) = rules::OVERLAP;
            return Err(ConvertError::Input(format!(
                "{code} {name}: {} (cells {}..{}) and {} (cells {}..{}) both cover cell {} ({})",
                a.path.display(),
                ra.start,
                ra.end,
                b.path.display(),
                rb.start,
                rb.end,
                rb.start,
                Region::from_index(a.placement.level, rb.start)
            )));
        }
        if rb.start > ra.end {
            let (code, name) = rules::GAP;
            return Err(ConvertError::Input(format!(
                "{code} {name}: no part covers cells {}..{} between {} and {}: merge parts of one contiguous Morton range",
                ra.end,
                rb.start,
                a.path.display(),
                b.path.display()
            )));
        }
    }
    let level = placement0.level;
    let cells = opened[0].placement.cells.start..opened.last().expect("a part").placement.cells.end;
    let placement = Placement {
        level,
        cells,
        colours: placement0.colours,
    };
    let complete = placement.is_whole();
    let depth = header.depth;

    // Each part is one run, split at the region level (at least 1).
    let split = level.max(1);
    let colour_cap = (limit / 16).clamp(1 << 20, 256 << 20);
    // In memory when the parts' records, before deduplication, fit what is
    // left of the limit (beside the colours, the largest part's maps from its
    // pointers to the merged records, and its largest level decoded as a
    // batch).
    let lower = usize::from(split)..usize::from(depth) - 1;
    let largest_batch = opened
        .iter()
        .flat_map(|p| p.levels.get(lower.clone()).unwrap_or(&[]))
        .map(|&(records, words)| MemoryMerge::batch_estimate(records, words))
        .max()
        .unwrap_or(0);
    let needed = MemoryMerge::estimate(lower.clone().map(|l| level_totals(&opened, l)))
        + opened.iter().map(|p| p.bytes).max().unwrap_or(0)
        + largest_batch;
    let available = limit
        .saturating_sub(meter.resident().unwrap_or(0) + colour_cap + crate::convert::margin(limit));
    let in_memory = opts.buckets.is_none() && needed <= available;
    let mut levels = if in_memory {
        let mut m = MemoryMerge::new(depth, header.attribute_kind, split)?;
        for l in lower {
            let (records, words) = level_totals(&opened, l);
            m.reserve(l as u8, records, words);
        }
        Levels::Memory(m)
    } else {
        Levels::Runs(RunMerge::new(
            depth,
            header.attribute_kind,
            split,
            &scratch,
            opts.buckets,
        )?)
    };
    let packing = match (complete, placement.colours) {
        (true, ColourMode::Packed(e)) => Some(e),
        _ => None,
    };
    let mut colours = (placement.colours != ColourMode::None)
        .then(|| ColourSink::new(&scratch, colour_cap, packing));
    let mut input_bytes = 0u64;
    for p in &opened {
        let file = p.map()?;
        input_bytes += file.bytes().len() as u64;
        let dag = Dag::open(file.bytes()).map_err(|e| format_error(&p.path, &e))?;
        match &mut levels {
            Levels::Runs(runs) => add_run(&dag, split, runs),
            Levels::Memory(m) => add_part(&dag, split, m),
        }
        .map_err(|e| match e {
            RunError::Format(e) => format_error(&p.path, &e),
            RunError::Convert(e) => e,
        })?;
        if let Some(c) = &mut colours {
            for chunk in dag.colors().unwrap_or(&[]).chunks(1 << 20) {
                c.write(chunk)?;
            }
        }
    }
    drop(opened);
    let budget = limit
        .saturating_sub(meter.resident().unwrap_or(0) + crate::convert::margin(limit))
        .max(MIN_MERGE_BUDGET);
    let colours = colours.map(ColourSink::finish).transpose()?;
    let dag = match levels {
        Levels::Runs(runs) => runs.finish(budget, &|_| {})?,
        Levels::Memory(m) => m.finish()?,
    };
    let merge_seconds = start.elapsed().as_secs_f64() - validate_seconds;
    let file_header = FileHeader {
        depth,
        attributes: header.attribute_kind,
        root_min: header.root_min,
        root_size: header.root_size,
        voxel_count: dag.voxel_count(),
    };
    // The whole volume in 2.0 is its 1.0 file upgraded, as `convert`
    // writes it (so the bytes are the same); a part is always 1.0.
    let format_version = if complete { opts.format_version } else { 1 };
    let file_bytes = if format_version == 1 {
        crate::convert::write_dag(
            output,
            opts.force,
            &dag,
            colours.as_ref(),
            file_header,
            (!complete).then_some(&placement),
        )?
    } else {
        let temp = tempfile::Builder::new()
            .prefix(".vdag-1.0-")
            .suffix(".tmp")
            .tempfile_in(&out_dir)
            .map_err(|e| {
                ConvertError::io(format!("cannot create a file in {}", out_dir.display()), e)
            })?;
        crate::convert::write_dag(temp.path(), true, &dag, colours.as_ref(), file_header, None)?;
        // The merged levels are in the 1.0 file now: the encoder gets what
        // is left of the limit without them.
        let finished = (
            dag.voxel_count(),
            dag.level_sections().iter().map(|s| s.item_count).collect(),
            dag.report().max_buckets,
        );
        drop(dag);
        let upgraded = crate::cmd::upgrade::upgrade_within(
            temp.path(),
            output,
            opts.force,
            limit,
            &meter,
            &tmp_dir,
        )?;
        return Ok(MergeSummary {
            parts: parts.len(),
            region_level: level,
            cells: placement.cells.clone(),
            complete,
            format_version,
            depth,
            voxels: finished.0,
            level_nodes: finished.1,
            file_bytes: upgraded.output_bytes,
            input_bytes,
            max_buckets: finished.2,
            temp_bytes: scratch.bytes_written(),
            in_memory,
            validate_seconds,
            merge_seconds,
            write_seconds: start.elapsed().as_secs_f64() - validate_seconds - merge_seconds,
            total_seconds: start.elapsed().as_secs_f64(),
        });
    };
    Ok(MergeSummary {
        parts: parts.len(),
        region_level: level,
        cells: placement.cells.clone(),
        complete,
        format_version,
        depth,
        voxels: dag.voxel_count(),
        level_nodes: dag.level_sections().iter().map(|s| s.item_count).collect(),
        file_bytes,
        input_bytes,
        max_buckets: dag.report().max_buckets,
        temp_bytes: scratch.bytes_written(),
        in_memory,
        validate_seconds,
        merge_seconds,
        write_seconds: start.elapsed().as_secs_f64() - validate_seconds - merge_seconds,
        total_seconds: start.elapsed().as_secs_f64(),
    })
}

/// The parts' records of level `level`, and the bound of their words.
fn level_totals(parts: &[Part], level: usize) -> (u64, u64) {
    parts.iter().fold((0, 0), |(r, w), p| {
        let (pr, pw) = p.levels.get(level).copied().unwrap_or((0, 0));
        (r + pr, w + pw)
    })
}

/// The merge of the levels: in memory, or out of core.
enum Levels {
    Memory(MemoryMerge),
    Runs(RunMerge),
}

enum RunError {
    Format(FormatError),
    Convert(ConvertError),
}

impl From<FormatError> for RunError {
    fn from(e: FormatError) -> Self {
        RunError::Format(e)
    }
}

impl From<ConvertError> for RunError {
    fn from(e: ConvertError) -> Self {
        RunError::Convert(e)
    }
}

/// The word offsets of the records of an interior level, in order: a
/// record's index is its offset's rank.
fn record_starts(dag: &Dag<'_>, section: &LevelSection<'_>) -> Result<Vec<u32>, FormatError> {
    let mut starts = Vec::with_capacity(section.node_count as usize);
    let mut word = 0u64;
    for _ in 0..section.node_count {
        starts.push(word as u32);
        word += dag.node(section.level, word as u32)?.record_size() / 4;
    }
    Ok(starts)
}

/// Gives the part's levels `split ..= D − 2` and its level-`split` subtrees
/// to `runs` as one run: record indices are the run-local ids.
fn add_run(dag: &Dag<'_>, split: u8, runs: &mut RunMerge) -> Result<(), RunError> {
    if dag.is_empty() {
        return Ok(());
    }
    let leaf = dag.leaf_level();
    let levels = dag.levels();
    // The index of a child pointer of level `l`: its rank among the record
    // starts of level l + 1, or the leaf index itself.
    let index_of = |starts: &[u32], pointer: u32| -> Result<u32, RunError> {
        starts
            .binary_search(&pointer)
            .map(|i| i as u32)
            .map_err(|_| {
                RunError::Convert(ConvertError::Input(format!(
                    "a pointer ({pointer}) does not start a record"
                )))
            })
    };
    let mut below: Vec<u32> = Vec::new();
    let mut children = Vec::with_capacity(8);
    // Levels are given bottom-up so that each needs only the starts of the
    // level below.
    for level in (split..leaf).rev() {
        let section = &levels[usize::from(level)];
        let starts = record_starts(dag, section)?;
        let mut word = 0u32;
        for _ in 0..section.node_count {
            let node = dag.node(level, word)?;
            children.clear();
            for r in 0..node.child_count() {
                let p = node.pointer_at(r);
                children.push(if level + 1 == leaf {
                    p
                } else {
                    index_of(&below, p)?
                });
            }
            runs.push_node(level, node.header, &children)?;
            word += (node.record_size() / 4) as u32;
        }
        below = starts;
    }
    for i in 0..levels[usize::from(leaf)].node_count {
        runs.push_leaf(dag.leaf(i as u32)?.0)?;
    }
    let mut failed: Option<RunError> = None;
    crate::region::visit_cells(dag, split, &mut |code, pointer| {
        if failed.is_some() {
            return;
        }
        let result = (|| -> Result<(), RunError> {
            let id = if split == leaf {
                pointer
            } else {
                index_of(&below, pointer)?
            };
            let count = dag.subtree_voxel_count(NodeRef {
                level: split,
                pointer,
            })?;
            runs.push_root(code, id, count)?;
            Ok(())
        })();
        if let Err(e) = result {
            failed = Some(e);
        }
    })?;
    if let Some(e) = failed {
        return Err(e);
    }
    runs.end_run()?;
    Ok(())
}

/// Gives the part's levels `split ..= D − 2` and its level-`split` subtrees
/// to the in-memory merge, bottom-up, a level at a time: each record's
/// children become the merged indices of the records they point to, through
/// a map from the part's pointers (word offsets, or leaf indices) to those
/// indices. The records are decoded on every core, and each level is
/// deduplicated on every core ([`MemoryMerge::nodes`]).
fn add_part(dag: &Dag<'_>, split: u8, merge: &mut MemoryMerge) -> Result<(), RunError> {
    if dag.is_empty() {
        return Ok(());
    }
    let leaf = dag.leaf_level();
    let levels = dag.levels();
    let not_a_record = |pointer: u32| {
        RunError::Convert(ConvertError::Input(format!(
            "a pointer ({pointer}) does not start a record"
        )))
    };
    let masks: Vec<u64> = (0..levels[usize::from(leaf)].node_count as u32)
        .into_par_iter()
        .map(|i| dag.leaf(i).map(|l| l.0))
        .collect::<Result<_, _>>()?;
    // `below[pointer]`: the merged index of the record at `pointer` of the
    // level below (u32::MAX: no record starts there).
    let mut below: Vec<u32> = merge.leaves(&masks)?;
    drop(masks);
    /// Records decoded per task.
    const CHUNK: usize = 1 << 14;
    for level in (split..leaf).rev() {
        let section = &levels[usize::from(level)];
        // Where each record starts (the records are of different sizes, so
        // this one pass is serial: it reads the headers only).
        let mut offsets = Vec::with_capacity(section.node_count as usize);
        let mut word = 0u32;
        for _ in 0..section.node_count {
            offsets.push(word);
            word += (dag.node(level, word)?.record_size() / 4) as u32;
        }
        let chunks = offsets
            .par_chunks(CHUNK)
            .map(|chunk| -> Result<NodeBatch, RunError> {
                let mut batch = NodeBatch {
                    words: Vec::with_capacity(chunk.len() * 5),
                    starts: Vec::with_capacity(chunk.len()),
                };
                for &word in chunk {
                    let node = dag.node(level, word)?;
                    batch.starts.push(batch.words.len() as u32);
                    batch.words.push(node.header);
                    for rank in 0..node.child_count() {
                        let p = node.pointer_at(rank);
                        batch.words.push(
                            below
                                .get(p as usize)
                                .copied()
                                .filter(|&i| i != u32::MAX)
                                .ok_or_else(|| not_a_record(p))?,
                        );
                    }
                }
                Ok(batch)
            })
            .collect::<Result<Vec<_>, _>>()?;
        let mut batch = NodeBatch {
            words: Vec::with_capacity(chunks.iter().map(|c| c.words.len()).sum()),
            starts: Vec::with_capacity(offsets.len()),
        };
        for c in &chunks {
            batch.append(c);
        }
        drop(chunks);
        let ids = merge.nodes(level, &batch)?;
        drop(batch);
        let mut map = vec![u32::MAX; section.units() as usize];
        for (&word, id) in offsets.iter().zip(ids) {
            map[word as usize] = id;
        }
        below = map;
    }
    let mut failed: Option<RunError> = None;
    crate::region::visit_cells(dag, split, &mut |code, pointer| {
        if failed.is_some() {
            return;
        }
        let result = (|| -> Result<(), RunError> {
            let index = below
                .get(pointer as usize)
                .copied()
                .filter(|&i| i != u32::MAX)
                .ok_or_else(|| not_a_record(pointer))?;
            let count = dag.subtree_voxel_count(NodeRef {
                level: split,
                pointer,
            })?;
            merge.push_root(code, index, count)?;
            Ok(())
        })();
        if let Err(e) = result {
            failed = Some(e);
        }
    })?;
    failed.map_or(Ok(()), Err)
}
