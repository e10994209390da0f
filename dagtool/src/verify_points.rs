//! `dagtool verify CLOUD FILE.vdag`: checks a point cloud's conversion
//! exactly, voxel by voxel, from the header's root cube alone:
//!
//! 1. every point of the cloud (inside the root cube) lies in a set voxel:
//!    some set voxel's closed cube contains it;
//! 2. every set voxel holds a point (its closed cube contains one) or, with
//!    `--point-radius R`, lies within distance R of one.
//!
//! The set voxels are listed once (Morton order) and searched; the points
//! are read in a stream for check 1 and kept, sorted by voxel, for check 2,
//! which then walks every set voxel.

use std::path::PathBuf;
use std::time::Instant;

use dagfmt::AnyDag;

use crate::cmd::FileBytes;
use crate::error::ConvertError;
use crate::input::PointSource;

/// What was found.
#[derive(Clone, Debug, Default)]
pub struct PointReport {
    /// The cloud.
    pub cloud: PathBuf,
    /// The `.vdag` file.
    pub dag: PathBuf,
    /// The splat radius checked against.
    pub radius: f64,
    /// Points read.
    pub points: u64,
    /// Points outside the root cube (not checked; `--bounds` skips them).
    pub outside: u64,
    /// Points in no set voxel (check 1).
    pub uncovered_points: u64,
    /// The first such point.
    pub first_uncovered: Option<[f64; 3]>,
    /// Set voxels.
    pub voxels: u64,
    /// Set voxels with no point in or within the radius (check 2).
    pub empty_voxels: u64,
    /// The first such voxel.
    pub first_empty: Option<[u32; 3]>,
    /// Seconds taken.
    pub seconds: f64,
}

impl PointReport {
    /// Whether both checks hold.
    pub fn passed(&self) -> bool {
        self.uncovered_points == 0 && self.empty_voxels == 0
    }

    /// The report for people.
    pub fn render(&self) -> String {
        let mark = |ok: bool| if ok { "PASS" } else { "FAIL" };
        format!(
            "cloud:  {} ({} points, {} outside the root cube, not checked)\n\
             dag:    {} ({} voxels)\n\
             [{}] every point lies in a set voxel: {} do not{}\n\
             [{}] every set voxel holds a point or lies within {} of one: {} do not{}\n\
             time:   {:.2} s\n\
             result: {}",
            self.cloud.display(),
            self.points,
            self.outside,
            self.dag.display(),
            self.voxels,
            mark(self.uncovered_points == 0),
            self.uncovered_points,
            self.first_uncovered
                .map_or(String::new(), |p| format!(" (first: {p:?})")),
            mark(self.empty_voxels == 0),
            self.radius,
            self.empty_voxels,
            self.first_empty
                .map_or(String::new(), |v| format!(" (first: voxel {v:?})")),
            self.seconds,
            if self.passed() { "PASS" } else { "FAIL" }
        )
    }

    /// The report as JSON.
    pub fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "cloud": self.cloud.display().to_string(),
            "dag": self.dag.display().to_string(),
            "radius": self.radius,
            "points": self.points,
            "outside_root_cube": self.outside,
            "uncovered_points": self.uncovered_points,
            "first_uncovered": self.first_uncovered,
            "voxels": self.voxels,
            "empty_voxels": self.empty_voxels,
            "first_empty": self.first_empty,
            "seconds": self.seconds,
            "passed": self.passed(),
        })
    }
}

/// The voxel range `[lo, hi]` along one axis whose closed cells hold grid
/// coordinate `c` (two cells when `c` is on a face), clipped to `0..n`.
fn cells(c: f64, n: u32) -> (u32, u32) {
    let f = c.floor();
    let hi = (f as i64).clamp(0, i64::from(n) - 1) as u32;
    let lo = if c == f {
        (f as i64 - 1).clamp(0, i64::from(n) - 1) as u32
    } else {
        hi
    };
    (lo, hi)
}

/// Checks `dag` against the points of `cloud`.
pub fn verify_points(
    cloud_path: &std::path::Path,
    mut cloud: Box<dyn PointSource>,
    dag_path: &std::path::Path,
    radius: f64,
) -> Result<PointReport, ConvertError> {
    if !(radius >= 0.0 && radius.is_finite()) {
        return Err(ConvertError::Usage(format!(
            "--point-radius {radius} is not a finite number >= 0"
        )));
    }
    let start = Instant::now();
    let bytes = FileBytes::open(dag_path)?;
    let dag = AnyDag::open(bytes.bytes())
        .map_err(|e| ConvertError::Input(format!("{}: {e}", dag_path.display())))?;
    let header = dag.header();
    let n = 1u32 << header.depth;
    let scale = f64::from(n) / header.root_size;
    let root_min = header.root_min;
    let dag_error =
        |e: dagfmt::FormatError| ConvertError::Input(format!("{}: {e}", dag_path.display()));
    // The set voxels, in Morton order (the order the DAG lists them in),
    // of either format version.
    let set_codes = dag.voxel_codes().map_err(dag_error)?;
    let is_set = |v: [u32; 3]| {
        set_codes
            .binary_search(&dagfmt::morton::encode(v[0], v[1], v[2]))
            .is_ok()
    };
    let mut report = PointReport {
        cloud: cloud_path.to_path_buf(),
        dag: dag_path.to_path_buf(),
        radius,
        voxels: set_codes.len() as u64,
        ..Default::default()
    };
    // Points by the Morton code of the voxel holding them (grid coordinates).
    let mut homes: Vec<(u64, [f64; 3])> = Vec::new();
    let mut batch = Vec::new();
    loop {
        batch.clear();
        if cloud.read(&mut batch, 1 << 16)? == 0 {
            break;
        }
        for p in &batch {
            report.points += 1;
            let g = [0, 1, 2].map(|a| (p.position[a] - root_min[a]) * scale);
            if !g.iter().all(|&c| (0.0..=f64::from(n)).contains(&c)) {
                report.outside += 1;
                continue;
            }
            let r = [0, 1, 2].map(|a| cells(g[a], n));
            let mut covered = false;
            'search: for x in r[0].0..=r[0].1 {
                for y in r[1].0..=r[1].1 {
                    for z in r[2].0..=r[2].1 {
                        if is_set([x, y, z]) {
                            covered = true;
                            break 'search;
                        }
                    }
                }
            }
            if !covered {
                report.uncovered_points += 1;
                report.first_uncovered.get_or_insert(p.position);
            }
            homes.push((dagfmt::morton::encode(r[0].1, r[1].1, r[2].1), g));
        }
    }
    homes.sort_unstable_by_key(|h| h.0);
    // Check 2: a voxel holds a point when its closed cube contains one, so
    // the points of the voxel and of its neighbours within the radius (plus
    // one, for points on faces) are searched.
    let r = radius * scale;
    let reach = r.ceil() as i64 + 1;
    for &code in &set_codes {
        let v = dagfmt::morton::decode(code);
        let mut near = false;
        'near: for dx in -reach..=reach {
            for dy in -reach..=reach {
                for dz in -reach..=reach {
                    let b = [
                        i64::from(v[0]) + dx,
                        i64::from(v[1]) + dy,
                        i64::from(v[2]) + dz,
                    ];
                    if b.iter().any(|&c| c < 0 || c >= i64::from(n)) {
                        continue;
                    }
                    let key = dagfmt::morton::encode(b[0] as u32, b[1] as u32, b[2] as u32);
                    let from = homes.partition_point(|h| h.0 < key);
                    for (_, g) in homes[from..].iter().take_while(|h| h.0 == key) {
                        let d2: f64 = (0..3)
                            .map(|a| crate::cloud::axis_distance(g[a], v[a]).powi(2))
                            .sum();
                        if d2 <= r * r {
                            near = true;
                            break 'near;
                        }
                    }
                }
            }
        }
        if !near {
            report.empty_voxels += 1;
            report.first_empty.get_or_insert(v);
        }
    }
    report.seconds = start.elapsed().as_secs_f64();
    Ok(report)
}
