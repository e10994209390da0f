//! `MemoryMeter`: a conversion's memory is what the process holds above its
//! start, whatever the process peaked at before. Alone in its test binary
//! (no other test allocates while the peaks are read).

use dagtool::sysinfo::{MemoryMeter, current_rss, peak_rss};

#[test]
fn a_meter_counts_what_was_allocated_after_its_start() {
    let Some(rss) = current_rss() else {
        return; // no /proc here: nothing to measure
    };
    // Raise the process's peak 64 MiB above what it holds, then free it.
    let before = vec![1u8; 64 << 20];
    std::hint::black_box(&before);
    drop(before);
    let earlier_peak = peak_rss().expect("read with the resident size");
    assert!(
        earlier_peak >= rss + (48 << 20),
        "peak {earlier_peak} after 64 MiB held over {rss}"
    );
    let meter = MemoryMeter::start();
    let peak = meter.peak().expect("read before");
    // Where the peak can be reset (Linux) the earlier 64 MiB are not
    // counted; elsewhere the resident size now stands in for it.
    assert!(peak < 32 << 20, "peak {peak} counts the earlier 64 MiB");
    assert!(meter.start_rss() + peak <= peak_rss().expect("read before").max(earlier_peak));
    let during = vec![1u8; 16 << 20];
    std::hint::black_box(&during);
    let peak = meter.peak().expect("read before");
    assert!(peak >= 16 << 20, "peak {peak} misses the 16 MiB held");
    assert!(peak < 48 << 20, "peak {peak} counts the earlier 64 MiB");
    assert!(meter.resident().expect("read before") >= 16 << 20);
    // The whole process's meter counts from nothing: the resident size at
    // the start as well (its peak, reset by `start`, since then).
    let whole = MemoryMeter::whole_process().peak().expect("read before");
    assert!(whole >= meter.start_rss() + (16 << 20), "{whole}");
    drop(during);
}
