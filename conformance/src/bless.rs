//! Generating the committed case files (`conformance bless`).
//!
//! Everything is computed in memory into a sorted map of relative paths to
//! bytes, so the output is the same on every run and platform: fixed seeds,
//! no hash-map iteration, floats printed in Rust's shortest round-trip form.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use dagfmt::batch::{self, Ray, format_f32};
use dagfmt::{AttributeKind, Dag};

use crate::expect;
use crate::malformed::{self, ValidateCase};
use crate::oracle::{LevelCells, Oracle, OracleRay};
use crate::scenes::{self, TraceCase};

/// Directory (under the cases root) of the tracer cases.
pub const TRACE_DIR: &str = "trace";
/// Directory (under the cases root) of the validator cases.
pub const VALIDATE_DIR: &str = "validate";
/// The list of validator cases and their expected outcome.
pub const VALIDATE_INDEX: &str = "expected.txt";

/// Formats a ray as a line of the text ray format.
pub fn format_ray(ray: &Ray) -> String {
    let mut line = [
        ray.origin[0],
        ray.origin[1],
        ray.origin[2],
        ray.dir[0],
        ray.dir[1],
        ray.dir[2],
        ray.tmin,
        ray.tmax,
    ]
    .map(format_f32)
    .join(" ");
    if let Some(level) = ray.level {
        write!(line, " {level}").expect("writing to a String");
    }
    line
}

/// The oracle's form of a batch ray in a depth-`depth` file.
pub fn oracle_ray(ray: &Ray, depth: u8) -> OracleRay {
    OracleRay {
        origin: ray.origin,
        dir: ray.dir,
        tmin: ray.tmin,
        tmax: ray.tmax,
        level: ray.level.unwrap_or(depth),
    }
}

fn describe_file(dag: &Dag<'_>) -> String {
    let h = dag.header();
    let kind = match h.attribute_kind {
        AttributeKind::None => 0,
        AttributeKind::VoxelCount => 1,
    };
    format!(
        "depth {}, attribute kind {kind}, {} voxels, root cube min [{}, {}, {}] size {}",
        h.depth, h.voxel_count, h.root_min[0], h.root_min[1], h.root_min[2], h.root_size
    )
}

/// Checks that the file holds the intended voxels and that the oracle's
/// decoding agrees with the reader's voxel iterator at `level`.
fn cross_check(
    case: &TraceCase,
    dag: &Dag<'_>,
    oracle: &mut Oracle,
    decoded: &[[u32; 3]],
    level: u8,
) -> Result<(), String> {
    let depth = dag.header().depth;
    let cells = oracle
        .cells(dag, level)
        .map_err(|e| format!("{}: {e}", case.name))?;
    if case.voxels.is_some() {
        let from_voxels = LevelCells::from_morton_voxels(depth, level, decoded);
        if from_voxels.codes != cells.codes || from_voxels.first_index != cells.first_index {
            return Err(format!(
                "{}: the oracle's walk and Dag::voxels disagree at level {level}",
                case.name
            ));
        }
    } else {
        // Only the full volume is too large to list: its cells are all
        // present and the first voxel of a cell is its Morton code shifted.
        let shift = 3 * u32::from(depth - level);
        let full = cells.codes.len() as u64 == 1 << (3 * u32::from(level))
            && cells
                .codes
                .iter()
                .zip(&cells.first_index)
                .all(|(&c, &i)| i == c << shift);
        if !full {
            return Err(format!(
                "{}: the unlisted volume is not full at level {level}",
                case.name
            ));
        }
    }
    Ok(())
}

/// The three files of one tracer case: `.vdag`, `.rays`, `.expect`.
pub fn trace_case_files(case: &TraceCase) -> Result<[(String, Vec<u8>); 3], String> {
    let dag = Dag::open(&case.file)
        .map_err(|e| format!("{}: the generated file does not open: {e}", case.name))?;
    let depth = dag.header().depth;
    let decoded: Vec<[u32; 3]> = match &case.voxels {
        Some(intended) => {
            let decoded = dag
                .voxels()
                .collect::<Result<Vec<_>, _>>()
                .map_err(|e| format!("{}: {e}", case.name))?;
            if &decoded != intended {
                return Err(format!(
                    "{}: the file does not hold the intended voxels",
                    case.name
                ));
            }
            decoded
        }
        None => Vec::new(),
    };
    let mut oracle = Oracle::new(&dag);
    let mut checked = Vec::new();
    let count: usize = case.groups.iter().map(|g| g.rays.len()).sum();
    let mut rays = format!(
        "vdag-rays 1\n# {}: {}\n# {}, {count} rays\n",
        case.name,
        case.description,
        describe_file(&dag)
    );
    let mut expected = format!(
        "{}\n# {}: {}\n# {}, {count} rays\n# one line per ray: miss | hit LEVEL CELL... | either LEVEL CELL...; CELL = X,Y,Z:T_LO,T_HI:FACES:INDEX\n",
        expect::EXPECT_HEADER,
        case.name,
        case.description,
        describe_file(&dag)
    );
    for group in &case.groups {
        writeln!(rays, "# {}", group.comment).expect("String");
        writeln!(expected, "# {}", group.comment).expect("String");
        if !group.literals.is_empty() && group.literals.len() != group.rays.len() {
            return Err(format!("{}: literals and rays differ in number", case.name));
        }
        for (i, ray) in group.rays.iter().enumerate() {
            let line = match group.literals.get(i) {
                Some(literal) => {
                    let parsed = batch::parse_rays(format!("vdag-rays 1\n{literal}\n").as_bytes())
                        .map_err(|e| format!("{}: literal `{literal}`: {e}", case.name))?;
                    if parsed[..] != [*ray] {
                        return Err(format!(
                            "{}: literal `{literal}` reads as {parsed:?}, not {ray:?}",
                            case.name
                        ));
                    }
                    literal.clone()
                }
                None => format_ray(ray),
            };
            rays.push_str(&line);
            rays.push('\n');
            if case.reject_batch {
                continue;
            }
            let oray = oracle_ray(ray, depth);
            if !checked.contains(&oray.level) {
                checked.push(oray.level);
                cross_check(case, &dag, &mut oracle, &decoded, oray.level)?;
            }
            let e = oracle
                .expect(&dag, &oray)
                .map_err(|e| format!("{}: ray {ray:?}: {e}", case.name))?;
            expected.push_str(&expect::format_expectation(&e));
            expected.push('\n');
        }
    }
    if case.reject_batch {
        if !case
            .groups
            .iter()
            .flat_map(|g| &g.rays)
            .any(|r| r.level.is_some_and(|l| l > depth))
        {
            return Err(format!("{}: no ray to reject the batch for", case.name));
        }
        expected.push_str(expect::REJECT_BATCH);
        expected.push('\n');
    }
    Ok([
        (format!("{TRACE_DIR}/{}.vdag", case.name), case.file.clone()),
        (format!("{TRACE_DIR}/{}.rays", case.name), rays.into_bytes()),
        (
            format!("{TRACE_DIR}/{}.expect", case.name),
            expected.into_bytes(),
        ),
    ])
}

/// The index line of a validator case: `FILE valid`, or `FILE CODE@OFFSET`
/// followed by the other codes the defect breaks too. The offset and the
/// other codes are those the reference validator reports; a case whose
/// expected code it does not report is an error of the generator.
fn index_line(case: &ValidateCase) -> Result<String, String> {
    let findings = dagfmt::validate::validate(&case.file);
    let outcome = match case.expected {
        None if findings.is_empty() => "valid".to_string(),
        None => {
            return Err(format!(
                "{}: the valid case is rejected: {}",
                case.name, findings[0]
            ));
        }
        Some(code) => {
            let first = findings.iter().find(|f| f.code == code).ok_or_else(|| {
                format!(
                    "{}: the reference validator does not report {code}",
                    case.name
                )
            })?;
            let mut also: Vec<&str> = findings
                .iter()
                .filter(|f| f.code != code)
                .map(|f| f.code.code())
                .collect();
            also.sort_unstable();
            also.dedup();
            let mut outcome = format!("{}@{:#x}", code.code(), first.offset);
            for other in also {
                outcome.push(' ');
                outcome.push_str(other);
            }
            outcome
        }
    };
    Ok(format!(
        "{}.vdag {outcome} # {}",
        case.name, case.description
    ))
}

/// Every case file, by path relative to the cases root.
pub fn generate() -> Result<BTreeMap<String, Vec<u8>>, String> {
    let mut files = BTreeMap::new();
    for case in scenes::trace_cases() {
        for (path, bytes) in trace_case_files(&case)? {
            if files.insert(path.clone(), bytes).is_some() {
                return Err(format!("two cases write {path}"));
            }
        }
    }
    let mut index = String::from(
        "# Validator cases: FILE valid | FILE CODE@OFFSET [ALSO...]. A conforming validator accepts\n\
         # the valid files and rejects each other file reporting CODE (the rule the file breaks) at\n\
         # byte OFFSET (spec/VDAG.md § 17.4); it may also report the ALSO codes, which the same\n\
         # defect breaks, and no others (strict mode, spec/CONFORMANCE.md § 6).\n",
    );
    for (code, why) in malformed::UNTESTABLE {
        writeln!(
            index,
            "# {} ({}) has no case: it {why}.",
            code.code(),
            code.name()
        )
        .expect("String");
    }
    for case in malformed::validate_cases() {
        index.push_str(&index_line(&case)?);
        index.push('\n');
        let path = format!("{VALIDATE_DIR}/{}.vdag", case.name);
        if files.insert(path.clone(), case.file).is_some() {
            return Err(format!("two cases write {path}"));
        }
    }
    files.insert(
        format!("{VALIDATE_DIR}/{VALIDATE_INDEX}"),
        index.into_bytes(),
    );
    Ok(files)
}

/// Whether `path` (relative) is a file bless owns: stale ones are removed.
fn owned(relative: &Path) -> bool {
    let ext = relative.extension().and_then(|e| e.to_str()).unwrap_or("");
    let dir = relative.parent().and_then(|p| p.to_str()).unwrap_or("");
    (dir == TRACE_DIR && matches!(ext, "vdag" | "rays" | "expect"))
        || (dir == VALIDATE_DIR
            && (ext == "vdag" || relative.file_name().is_some_and(|n| n == VALIDATE_INDEX)))
}

/// Writes the case files under `root`, removing case files that are no
/// longer generated. Returns the number of files written.
pub fn write(root: &Path, files: &BTreeMap<String, Vec<u8>>) -> std::io::Result<usize> {
    for dir in [TRACE_DIR, VALIDATE_DIR] {
        let path = root.join(dir);
        std::fs::create_dir_all(&path)?;
        for entry in std::fs::read_dir(&path)? {
            let name = entry?.file_name();
            let relative = Path::new(dir).join(&name);
            let key = format!("{dir}/{}", name.to_string_lossy());
            if owned(&relative) && !files.contains_key(&key) {
                std::fs::remove_file(root.join(&relative))?;
            }
        }
    }
    for (path, bytes) in files {
        let target = root.join(path);
        if std::fs::read(&target).ok().as_deref() != Some(bytes.as_slice()) {
            std::fs::write(&target, bytes)?;
        }
    }
    Ok(files.len())
}
