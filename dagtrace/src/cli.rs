//! What the suite's command-line tools (`dagtrace`, `dagtool`) share about
//! talking to people: usage errors as one line.

/// clap's rendering of a usage error as one line: its message, up to the
/// usage and tips, with the lines after the first (where clap lists missing
/// arguments) joined on, and without clap's own `error: ` prefix.
pub fn usage_error_line(error: &clap::Error) -> String {
    let text = error.to_string();
    let message: Vec<&str> = text
        .lines()
        .map(str::trim)
        .take_while(|l| !l.starts_with("Usage:") && !l.starts_with("tip:"))
        .filter(|l| !l.is_empty())
        .collect();
    let line = message.join(" ");
    match line.strip_prefix("error: ") {
        Some(rest) => rest.to_string(),
        None => line,
    }
}

/// The peak resident memory of this process in MiB (`VmHWM`), where the
/// system says (Linux).
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}
