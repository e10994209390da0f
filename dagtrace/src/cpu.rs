//! What the processor can run: the features the vector lanes need
//! ([`available`], [`wide_available`]) and whether its gather instructions
//! are slow ([`slow_gathers`]), each looked up once. Used by the tracer's
//! set-up ([`crate::Gathers`], [`crate::Lanes`]) and by every path that
//! chooses vector code.

use std::arch::x86_64::__cpuid;

/// Whether this processor runs the vector traversal: AVX2, and the
/// instructions every processor with AVX2 also has that the batch path is
/// compiled with (`#[target_feature]`: BMI1/2, POPCNT, LZCNT, FMA; no fused
/// arithmetic is written, so FMA only allows the encoding). Looked up once.
#[inline(always)]
pub(crate) fn available() -> bool {
    // 0: not known yet, 1: no, 2: yes. One load on the hot paths that ask
    // (inlined: a call there would make the caller save its vector
    // registers around it).
    match AVAILABLE.load(std::sync::atomic::Ordering::Relaxed) {
        0 => detect(),
        v => v == 2,
    }
}

/// [`available`]'s answer, once known.
static AVAILABLE: std::sync::atomic::AtomicU8 = std::sync::atomic::AtomicU8::new(0);

/// Looks the features of [`available`] up and records the answer.
#[cold]
#[inline(never)]
fn detect() -> bool {
    let yes = std::is_x86_feature_detected!("avx2")
        && std::is_x86_feature_detected!("bmi1")
        && std::is_x86_feature_detected!("bmi2")
        && std::is_x86_feature_detected!("popcnt")
        && std::is_x86_feature_detected!("lzcnt")
        && std::is_x86_feature_detected!("fma");
    AVAILABLE.store(1 + u8::from(yes), std::sync::atomic::Ordering::Relaxed);
    yes
}

/// Whether this processor runs the sixteen-lane traversal: [`available`],
/// and AVX-512 with the subsets [`step_wide`] is compiled with (F, BW, VL,
/// DQ, CD: every processor with AVX-512 since Intel's Skylake-SP and AMD's
/// Zen 4). Looked up once.
#[inline]
pub(crate) fn wide_available() -> bool {
    static WIDE_AVAILABLE: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *WIDE_AVAILABLE.get_or_init(|| {
        available()
            && std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512bw")
            && std::is_x86_feature_detected!("avx512vl")
            && std::is_x86_feature_detected!("avx512dq")
            && std::is_x86_feature_detected!("avx512cd")
    })
}

/// Whether this processor's gather instructions are slow enough that the
/// vector lanes read faster with scalar loads ([`crate::Gathers::Auto`]):
/// AMD's families 17h (Zen, Zen+ and Zen 2) and 19h (Zen 3 and Zen 4), and
/// Hygon's family 18h (built on Zen). Family 17h's `vpgatherdd` of eight
/// 32-bit words is microcoded: on a Zen 1 EPYC it took 20–30 cycles a gather
/// where eight loads put together took 6–10 (microbenchmark). Family 19h
/// gathers faster, but the loads still won there: 0.955 of the time of d12
/// random rays on a Zen 4 EPYC (101 alternating rounds), 0.983 on a Zen 3.
/// Intel's cores keep the instruction (scalar loads took 1.05–1.07 of its
/// time on a Xeon), and so do processors not measured (AMD's family 1Ah,
/// Zen 5, among them). The measurements: dagtrace/BENCHMARKS.md.
pub(crate) fn slow_gathers() -> bool {
    // (`cpuid` exists on every x86-64 processor; leaves 0 and 1 always do.)
    let (vendor, signature) = (__cpuid(0), __cpuid(1));
    let mut name = [0u8; 12];
    name[..4].copy_from_slice(&vendor.ebx.to_le_bytes());
    name[4..8].copy_from_slice(&vendor.edx.to_le_bytes());
    name[8..].copy_from_slice(&vendor.ecx.to_le_bytes());
    slow_gathers_on(&name, signature.eax)
}

/// [`slow_gathers`] for the processor with vendor string `vendor` (cpuid
/// leaf 0) and signature `eax` (leaf 1).
fn slow_gathers_on(vendor: &[u8; 12], eax: u32) -> bool {
    let base_family = (eax >> 8) & 0xf;
    let family = if base_family == 0xf {
        base_family + ((eax >> 20) & 0xff)
    } else {
        base_family
    };
    matches!(
        (vendor, family),
        (b"AuthenticAMD", 0x17 | 0x19) | (b"HygonGenuine", 0x18)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The processors whose gathers the lanes replace by scalar loads, by
    /// their cpuid signatures (leaf 1, eax).
    #[test]
    fn slow_gathers_are_amd_families_17h_and_19h_and_hygon() {
        let (amd, intel, hygon) = (b"AuthenticAMD", b"GenuineIntel", b"HygonGenuine");
        for (vendor, eax, slow, what) in [
            (amd, 0x0080_0f12, true, "EPYC 7001, Zen"),
            (amd, 0x0080_0f82, true, "Ryzen 2000, Zen+"),
            (amd, 0x0083_0f10, true, "EPYC 7002, Zen 2"),
            (amd, 0x00a0_0f11, true, "EPYC 7003, Zen 3"),
            (amd, 0x00a1_0f11, true, "EPYC 9004, Zen 4"),
            (amd, 0x00b0_0f20, false, "Zen 5"),
            (amd, 0x0060_0f20, false, "family 15h, Bulldozer line"),
            (hygon, 0x0090_0f11, true, "Hygon Dhyana"),
            (intel, 0x0005_0654, false, "Xeon, Skylake-SP"),
            (intel, 0x0006_06a6, false, "Xeon, Ice Lake-SP"),
        ] {
            assert_eq!(slow_gathers_on(vendor, eax), slow, "{what}");
        }
    }
}
