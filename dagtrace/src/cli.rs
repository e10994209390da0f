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
