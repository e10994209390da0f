//! The expectation format (`.expect` files) and the judge of answers.
//!
//! ```text
//! vdag-expect 1
//! # one line per ray, in the order of the rays file:
//! miss
//! hit LEVEL CELL [CELL ...]
//! either LEVEL CELL [CELL ...]
//! # CELL = X,Y,Z:T_LO,T_HI:FACES:INDEX
//! ```
//!
//! A file whose only line after the header is `reject-batch` expects the
//! tracer to reject the whole batch (a ray's level is deeper than the file).
//!
//! `miss`: only a miss is accepted. `hit`: only a hit on one of the listed
//! cells. `either`: a miss or a hit on one of the listed cells. A hit on a
//! listed cell must report that cell's coordinates, the line's `LEVEL`, a `t`
//! with `T_LO <= t <= T_HI` (compared in f64; the tolerance is already
//! included), an entry face among the digits of `FACES` and exactly `INDEX`
//! (`-`: no index). `#` starts a comment; blank lines are ignored.

use std::fmt::Write as _;

use dagfmt::batch::{Hit, format_f32};

use crate::oracle::{AcceptableCell, Expectation, Verdict};

/// First line of an expectation file.
pub const EXPECT_HEADER: &str = "vdag-expect 1";

/// The one line of an expectation file whose batch must be rejected as a
/// whole (a ray asks for a level deeper than the file, spec/VDAG.md § 20.2).
pub const REJECT_BATCH: &str = "reject-batch";

/// What a case expects of a tracer.
#[derive(Clone, Debug, PartialEq)]
pub enum CaseExpectation {
    /// One expectation per ray.
    Answers(Vec<Expectation>),
    /// The tracer must reject the whole batch: fail, and write no answers.
    RejectBatch,
}

/// Parses an expectation file that may say `reject-batch`.
pub fn parse_case(text: &str) -> Result<CaseExpectation, String> {
    let mut content = text
        .lines()
        .map(|l| l.split('#').next().unwrap_or("").trim())
        .filter(|l| !l.is_empty());
    if content.next() == Some(EXPECT_HEADER) && content.next() == Some(REJECT_BATCH) {
        return match content.next() {
            None => Ok(CaseExpectation::RejectBatch),
            Some(l) => Err(format!("`{l}` follows `{REJECT_BATCH}`")),
        };
    }
    parse_file(text).map(CaseExpectation::Answers)
}

fn format_faces(faces: u8) -> String {
    (0..7u8)
        .filter(|f| faces & (1 << f) != 0)
        .map(|f| char::from(b'0' + f))
        .collect()
}

/// Formats one expectation as its line (no newline).
pub fn format_expectation(e: &Expectation) -> String {
    let mut line = String::from(e.verdict.keyword());
    if e.verdict == Verdict::Miss {
        return line;
    }
    write!(line, " {}", e.level).expect("writing to a String");
    for c in &e.cells {
        let index = c.index.map_or_else(|| "-".to_string(), |i| i.to_string());
        write!(
            line,
            " {},{},{}:{},{}:{}:{}",
            c.cell[0],
            c.cell[1],
            c.cell[2],
            format_f32(c.t_lo),
            format_f32(c.t_hi),
            format_faces(c.faces),
            index
        )
        .expect("writing to a String");
    }
    line
}

/// Formats a whole expectation file; `comments` go after the header line.
pub fn format_file(comments: &[String], expectations: &[Expectation]) -> String {
    let mut out = format!("{EXPECT_HEADER}\n");
    for c in comments {
        out.push_str("# ");
        out.push_str(c);
        out.push('\n');
    }
    for e in expectations {
        out.push_str(&format_expectation(e));
        out.push('\n');
    }
    out
}

fn parse_cell(field: &str) -> Result<AcceptableCell, String> {
    let parts: Vec<&str> = field.split(':').collect();
    let [coords, ts, faces, index] = parts[..] else {
        return Err(format!("cell `{field}` is not X,Y,Z:T_LO,T_HI:FACES:INDEX"));
    };
    let coords: Vec<u32> = coords
        .split(',')
        .map(str::parse)
        .collect::<Result<_, _>>()
        .map_err(|_| format!("bad coordinates in `{field}`"))?;
    let ts: Vec<f32> = ts
        .split(',')
        .map(str::parse)
        .collect::<Result<_, _>>()
        .map_err(|_| format!("bad t interval in `{field}`"))?;
    let (&[x, y, z], &[t_lo, t_hi]) = (&coords[..], &ts[..]) else {
        return Err(format!("cell `{field}` needs 3 coordinates and 2 bounds"));
    };
    let mut face_bits = 0u8;
    for ch in faces.chars() {
        match ch.to_digit(10) {
            Some(f) if f <= 6 => face_bits |= 1 << f,
            _ => return Err(format!("bad face `{ch}` in `{field}`")),
        }
    }
    let index = match index {
        "-" => None,
        i => Some(
            i.parse::<u64>()
                .map_err(|_| format!("bad index in `{field}`"))?,
        ),
    };
    Ok(AcceptableCell {
        cell: [x, y, z],
        t_lo,
        t_hi,
        faces: face_bits,
        index,
    })
}

/// Parses an expectation file.
pub fn parse_file(text: &str) -> Result<Vec<Expectation>, String> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.split('#').next().unwrap_or("").trim()))
        .filter(|(_, l)| !l.is_empty());
    match lines.next() {
        Some((_, l)) if l == EXPECT_HEADER => {}
        _ => return Err(format!("line 1: missing the `{EXPECT_HEADER}` header")),
    }
    let mut out = Vec::new();
    for (number, line) in lines {
        let fields: Vec<&str> = line.split_ascii_whitespace().collect();
        let verdict = match fields[0] {
            "miss" => Verdict::Miss,
            "hit" => Verdict::Hit,
            "either" => Verdict::Either,
            other => return Err(format!("line {number}: unknown verdict `{other}`")),
        };
        if verdict == Verdict::Miss {
            if fields.len() != 1 {
                return Err(format!("line {number}: `miss` takes no fields"));
            }
            out.push(Expectation::miss(0));
            continue;
        }
        let level = fields
            .get(1)
            .and_then(|l| l.parse::<u8>().ok())
            .ok_or_else(|| format!("line {number}: missing or bad level"))?;
        let cells = fields[2..]
            .iter()
            .map(|f| parse_cell(f))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| format!("line {number}: {e}"))?;
        if cells.is_empty() {
            return Err(format!(
                "line {number}: `{}` needs at least one cell",
                fields[0]
            ));
        }
        out.push(Expectation {
            verdict,
            level,
            cells,
        });
    }
    Ok(out)
}

/// Formats an answer like a line of the text hit format.
pub fn format_answer(hit: &Hit) -> String {
    if !hit.hit {
        return "miss".into();
    }
    let index = hit.index.map_or_else(|| "-".to_string(), |i| i.to_string());
    format!(
        "hit {} {} {} {} {} {} {}",
        format_f32(hit.t),
        hit.voxel[0],
        hit.voxel[1],
        hit.voxel[2],
        hit.level,
        hit.face,
        index
    )
}

/// Judges one answer: `Ok` when accepted, else why not.
pub fn judge(expected: &Expectation, answer: &Hit) -> Result<(), String> {
    if !answer.hit {
        return match expected.verdict {
            Verdict::Hit => Err("a hit is required".into()),
            Verdict::Miss | Verdict::Either => Ok(()),
        };
    }
    if expected.verdict == Verdict::Miss {
        return Err("a miss is required".into());
    }
    let Some(cell) = expected.cells.iter().find(|c| c.cell == answer.voxel) else {
        return Err(format!("cell {:?} is not an acceptable cell", answer.voxel));
    };
    if answer.level != expected.level {
        return Err(format!(
            "level {} reported, the ray traces level {}",
            answer.level, expected.level
        ));
    }
    let t = answer.t;
    if !(cell.t_lo <= t && t <= cell.t_hi) {
        return Err(format!(
            "t {} is outside [{}, {}]",
            format_f32(t),
            format_f32(cell.t_lo),
            format_f32(cell.t_hi)
        ));
    }
    if answer.face > 6 || cell.faces & (1 << answer.face) == 0 {
        return Err(format!(
            "face {} is not one of {}",
            answer.face,
            format_faces(cell.faces)
        ));
    }
    if answer.index != cell.index {
        let show = |i: Option<u64>| i.map_or_else(|| "-".to_string(), |i| i.to_string());
        return Err(format!(
            "index {} reported, expected {}",
            show(answer.index),
            show(cell.index)
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn format_round_trips() {
        let e = vec![
            Expectation::miss(0),
            Expectation {
                verdict: Verdict::Either,
                level: 3,
                cells: vec![
                    AcceptableCell {
                        cell: [1, 2, 3],
                        t_lo: 0.1,
                        t_hi: 1e-7,
                        faces: 0b101,
                        index: Some(17),
                    },
                    AcceptableCell {
                        cell: [0, 0, 7],
                        t_lo: -1.5,
                        t_hi: f32::INFINITY,
                        faces: 1,
                        index: None,
                    },
                ],
            },
        ];
        let text = format_file(&["a comment".into()], &e);
        assert_eq!(
            text,
            "vdag-expect 1\n# a comment\nmiss\neither 3 1,2,3:0.1,1e-7:02:17 0,0,7:-1.5,inf:0:-\n"
        );
        assert_eq!(parse_file(&text).unwrap(), e);
    }

    #[test]
    fn judge_checks_every_field() {
        let e = Expectation {
            verdict: Verdict::Hit,
            level: 3,
            cells: vec![AcceptableCell {
                cell: [1, 2, 3],
                t_lo: 1.0,
                t_hi: 2.0,
                faces: 0b110,
                index: Some(4),
            }],
        };
        let good = Hit {
            hit: true,
            t: 1.5,
            voxel: [1, 2, 3],
            level: 3,
            face: 2,
            index: Some(4),
        };
        assert_eq!(judge(&e, &good), Ok(()));
        assert!(judge(&e, &Hit::MISS).is_err());
        assert!(judge(&e, &Hit { t: 2.5, ..good }).is_err());
        assert!(
            judge(
                &e,
                &Hit {
                    t: f32::NAN,
                    ..good
                }
            )
            .is_err()
        );
        assert!(judge(&e, &Hit { face: 0, ..good }).is_err());
        assert!(judge(&e, &Hit { level: 2, ..good }).is_err());
        assert!(
            judge(
                &e,
                &Hit {
                    index: None,
                    ..good
                }
            )
            .is_err()
        );
        assert!(
            judge(
                &e,
                &Hit {
                    voxel: [1, 2, 4],
                    ..good
                }
            )
            .is_err()
        );
        assert_eq!(judge(&Expectation::miss(3), &Hit::MISS), Ok(()));
    }
}
