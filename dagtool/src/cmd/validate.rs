//! `dagtool validate FILE...`: every rule of the format, every violation.

use std::io::Write;
use std::path::PathBuf;

use dagfmt::validate::{ValidateOptions, validate_with};

use super::{FileBytes, error_json};

/// The outcome of validating several files.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// Every file is valid.
    Valid,
    /// At least one file is invalid (and none could not be read).
    Invalid,
    /// At least one file could not be read.
    IoError,
}

impl Outcome {
    /// Exit status: 0 valid, 1 invalid, 2 I/O error.
    pub fn exit_code(self) -> i32 {
        match self {
            Outcome::Valid => 0,
            Outcome::Invalid => 1,
            Outcome::IoError => 2,
        }
    }
}

/// Validates `files`, writing the report to `out` (human text, or one JSON
/// document with `json`). Errors opening a file go to `err` as
/// `dagtool: error: ...` lines (and into the JSON document).
pub fn run(
    files: &[PathBuf],
    json: bool,
    out: &mut impl Write,
    err: &mut impl Write,
) -> std::io::Result<Outcome> {
    let mut outcome = Outcome::Valid;
    let mut reports = Vec::new();
    for path in files {
        let name = path.display().to_string();
        let bytes = match FileBytes::open(path) {
            Ok(b) => b,
            Err(e) => {
                writeln!(err, "dagtool: error: {e}")?;
                outcome = Outcome::IoError;
                reports.push(
                    serde_json::json!({ "file": name, "valid": false, "io_error": e.to_string() }),
                );
                continue;
            }
        };
        let report = validate_with(bytes.bytes(), &ValidateOptions::default());
        // A valid file that is a part (spec § 24) is checked against the
        // part rules too; they are one finding at most.
        let part = if report.is_valid() {
            dagfmt::Dag::open(bytes.bytes())
                .ok()
                .map(|dag| crate::region::check_part(&dag))
        } else {
            None
        };
        let part_error = match &part {
            Some(Err(e)) => Some(e.clone()),
            _ => None,
        };
        let placement = match part {
            Some(Ok(Some(p))) => Some(p),
            _ => None,
        };
        let valid = report.is_valid() && part_error.is_none();
        if !valid && outcome == Outcome::Valid {
            outcome = Outcome::Invalid;
        }
        if json {
            reports.push(serde_json::json!({
                "file": name,
                "packed": bytes.was_packed(),
                "bytes": bytes.bytes().len(),
                "valid": valid,
                "truncated": report.truncated,
                "part": placement.as_ref().map(|p| serde_json::json!({
                    "region_level": p.level,
                    "cells": [p.cells.start, p.cells.end],
                })),
                "errors": report
                    .errors
                    .iter()
                    .map(error_json)
                    .chain(part_error.iter().map(|e| serde_json::json!({
                        "code": e.code,
                        "name": e.name,
                        "offset": e.offset,
                        "level": null,
                        "node": null,
                        "message": e.message,
                    })))
                    .collect::<Vec<_>>(),
            }));
        } else if let Some(e) = &part_error {
            writeln!(out, "{name}: INVALID, 1 violation of the part rules")?;
            writeln!(out, "  {e}")?;
        } else if report.is_valid() {
            writeln!(
                out,
                "{name}: valid ({} bytes{}{})",
                bytes.bytes().len(),
                if bytes.was_packed() {
                    ", unpacked from zstd"
                } else {
                    ""
                },
                match &placement {
                    Some(p) => format!(
                        "; a part: cells {}..{} of level {}",
                        p.cells.start, p.cells.end, p.level
                    ),
                    None => String::new(),
                }
            )?;
        } else {
            writeln!(
                out,
                "{name}: INVALID, {}{} violation{}",
                report.errors.len(),
                if report.truncated { "+" } else { "" },
                if report.errors.len() == 1 { "" } else { "s" }
            )?;
            for e in &report.errors {
                writeln!(out, "  {e}")?;
            }
            if report.truncated {
                writeln!(out, "  (stopped after {} violations)", report.errors.len())?;
            }
        }
    }
    if json {
        let doc = serde_json::json!({
            "valid": outcome == Outcome::Valid,
            "files": reports,
        });
        writeln!(
            out,
            "{}",
            serde_json::to_string_pretty(&doc).expect("JSON values serialize")
        )?;
    }
    Ok(outcome)
}
