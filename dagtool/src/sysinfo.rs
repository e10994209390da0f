//! Process memory figures from `/proc/self/status` (Linux; `None` elsewhere).

/// Reads a `kB` field such as `VmHWM` from `/proc/self/status`, in bytes.
fn status_field(name: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    status.lines().find_map(|line| {
        let rest = line.strip_prefix(name)?.strip_prefix(':')?;
        let kb: u64 = rest.trim().strip_suffix("kB")?.trim().parse().ok()?;
        Some(kb * 1024)
    })
}

/// Peak resident set size of this process (`VmHWM`), in bytes.
pub fn peak_rss() -> Option<u64> {
    status_field("VmHWM")
}

/// Current resident set size (`VmRSS`), in bytes.
pub fn current_rss() -> Option<u64> {
    status_field("VmRSS")
}

/// Resets the process's peak resident set size (`VmHWM`) to its current
/// resident size (`echo 5 > /proc/self/clear_refs`, Linux 4.0 and later);
/// false where that file cannot be written.
fn reset_peak_rss() -> bool {
    std::fs::OpenOptions::new()
        .write(true)
        .open("/proc/self/clear_refs")
        .and_then(|mut f| std::io::Write::write_all(&mut f, b"5"))
        .is_ok()
}

/// The memory of one conversion (or merge, or upgrade) in a process that
/// may hold other things: its resident memory above what was resident when
/// it started, so that a memory limit applies to the conversion itself, not
/// to what a long-lived process (Python, a Dask worker) held before or
/// peaked at earlier.
///
/// [`MemoryMeter::start`] resets the process's peak (`VmHWM`) to the
/// current resident size, so that the peak it reads later is the
/// conversion's; where the reset is refused it falls back on the resident
/// size (see [`MemoryMeter::peak`]). The reset is process-wide: a peak that
/// something else in the process was tracking is lost, and conversions run
/// at the same time in one process count each other's memory.
#[derive(Clone, Copy, Debug)]
pub struct MemoryMeter {
    /// Resident bytes when the conversion started.
    start_rss: u64,
    /// The process's peak when the conversion started (after the reset).
    start_peak: u64,
    /// Whether the peak was reset to `start_rss`.
    peak_reset: bool,
}

impl MemoryMeter {
    /// Starts measuring: takes the resident size and resets the peak.
    pub fn start() -> MemoryMeter {
        let peak_reset = reset_peak_rss();
        let start_rss = current_rss().unwrap_or(0);
        MemoryMeter {
            start_rss,
            start_peak: peak_rss().unwrap_or(0),
            peak_reset,
        }
    }

    /// A meter that counts the whole process (nothing resident at its
    /// start): what a conversion measured before meters existed.
    pub fn whole_process() -> MemoryMeter {
        MemoryMeter {
            start_rss: 0,
            start_peak: 0,
            peak_reset: true,
        }
    }

    /// Bytes that were resident when the conversion started (not counted).
    pub fn start_rss(&self) -> u64 {
        self.start_rss
    }

    /// The conversion's resident bytes now: the process's above its start.
    pub fn resident(&self) -> Option<u64> {
        Some(current_rss()?.saturating_sub(self.start_rss))
    }

    /// The conversion's peak resident bytes so far: the process's peak
    /// above the resident size at the start. Where the peak could not be
    /// reset and the process had peaked higher before the conversion (so
    /// that its peak says nothing of the conversion), the conversion's
    /// resident bytes now: the best figure there is, a lower bound.
    pub fn peak(&self) -> Option<u64> {
        let peak = peak_rss()?;
        if self.peak_reset || peak > self.start_peak {
            Some(peak.saturating_sub(self.start_rss))
        } else {
            self.resident()
        }
    }
}

/// Physical memory of the machine (`MemTotal` of `/proc/meminfo`), in bytes.
pub fn total_memory() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    info.lines().find_map(|line| {
        let rest = line.strip_prefix("MemTotal:")?;
        let kb: u64 = rest.trim().strip_suffix("kB")?.trim().parse().ok()?;
        Some(kb * 1024)
    })
}

/// Parses a byte size such as `4G`, `512M`, `1.5GiB` or `1000000`
/// (K, M, G, T are powers of 1024; an optional `B` or `iB` suffix is accepted).
pub fn parse_size(text: &str) -> Option<u64> {
    let t = text.trim();
    let t = t
        .strip_suffix("iB")
        .or_else(|| t.strip_suffix("B"))
        .unwrap_or(t);
    let (number, unit) = match t.char_indices().find(|(_, c)| c.is_ascii_alphabetic()) {
        Some((i, _)) => (&t[..i], &t[i..]),
        None => (t, ""),
    };
    let factor: u64 = match unit.to_ascii_uppercase().as_str() {
        "" => 1,
        "K" => 1 << 10,
        "M" => 1 << 20,
        "G" => 1 << 30,
        "T" => 1 << 40,
        _ => return None,
    };
    let value: f64 = number.trim().parse().ok()?;
    if !(value.is_finite() && value > 0.0) {
        return None;
    }
    let bytes = value * factor as f64;
    (bytes < 1.8e19).then_some(bytes as u64)
}

/// Formats a byte count for people (binary units).
pub fn human_bytes(bytes: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = bytes as f64;
    let mut unit = 0;
    while v >= 1024.0 && unit < UNITS.len() - 1 {
        v /= 1024.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{bytes} B")
    } else {
        format!("{v:.2} {}", UNITS[unit])
    }
}

/// CPU time (user + system, seconds) from a `/proc/.../stat` file.
fn stat_cpu_seconds(path: &str) -> Option<f64> {
    let stat = std::fs::read_to_string(path).ok()?;
    // Fields after the command name (which may contain spaces) start after ')'.
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the whole line (11 and 12 here).
    let ticks: u64 = fields.get(11)?.parse::<u64>().ok()? + fields.get(12)?.parse::<u64>().ok()?;
    // The kernel reports USER_HZ ticks, 100 per second on Linux.
    Some(ticks as f64 / 100.0)
}

/// CPU time of the whole process so far (all threads), in seconds.
pub fn process_cpu_seconds() -> Option<f64> {
    stat_cpu_seconds("/proc/self/stat")
}

/// CPU time of the calling thread so far, in seconds.
pub fn thread_cpu_seconds() -> Option<f64> {
    stat_cpu_seconds("/proc/thread-self/stat")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes() {
        assert_eq!(parse_size("4G"), Some(4 << 30));
        assert_eq!(parse_size("512MiB"), Some(512 << 20));
        assert_eq!(parse_size("1.5g"), Some(3 << 29));
        assert_eq!(parse_size("1000"), Some(1000));
        assert_eq!(parse_size("0"), None);
        assert_eq!(parse_size("12X"), None);
        assert_eq!(parse_size("-1G"), None);
    }
}
