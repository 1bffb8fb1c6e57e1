//! Which instructions the traversals run on: the portable x86-64 baseline the crate is built
//! for, or the same code compiled again with AVX2 and the bit-manipulation extensions, chosen
//! at run time when the CPU has them.
//!
//! Why: the crate targets baseline x86-64 (SSE2) so that one binary runs anywhere, but the
//! traversal's node and hit tests are four-wide `Vec4` arithmetic and mask bit-twiddling, which
//! VEX encoding (three operands, no register copies), `lzcnt`/`tzcnt`, `popcnt` and BMI do in
//! fewer instructions. Measured alternating against the baseline build (`cargo bench --bench
//! trace`, 2026-11-27, three rounds on a VM with noisy neighbours): composited camera rays on
//! the 200k room 1.001-1.004 -> 1.109 M/s (+10 %), the learned scene's render 134-150 k ->
//! 149-160 k path samples/s (+3-8 %); visibility rays and stage 3's cached passes within their
//! run-to-run noise (±15 %).
//!
//! Same results: the same Rust source is compiled twice, and Rust never contracts a multiply and
//! an add into a fused one nor reorders float arithmetic, whatever the target features: the
//! wider encodings carry the same IEEE operations. `tests/trace.rs` checks both bit for bit on
//! random scenes (`the_avx2_traversals_match_the_baseline_bit_for_bit`), and the learned scene's
//! renders are byte-identical.
//!
//! How: [`super::Placed`]'s three traversal entry points (composite, visibility, the backward
//! pass's walk) each have a twin method with `#[target_feature]`, which the entry point calls
//! when its `Isa` is [`Isa::Avx2`]; everything below them is `#[inline(always)]` down to the hit
//! test, so it is compiled into the twin. Calling a function built with target features is
//! `unsafe` (the CPU must have them), which an [`Isa::Avx2`] guarantees by construction: only
//! [`Isa::best`] makes one, after `is_x86_feature_detected!`. The composite's per-hit work is a
//! trait method marked `#[inline(always)]` (`placed::Visit`), not a closure: as a closure it
//! stayed out of line in the twin, and composited camera rays gained +5 % rather than +10 %.
//! Written by hand rather than with the
//! `multiversion` crate: three one-line twins and a feature check need no dependency.

/// The instruction set a [`super::Placed`] scene's traversals run on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// The crate's build target (x86-64: SSE2), on any CPU.
    Baseline,
    /// AVX2, BMI1/2, LZCNT and POPCNT: only made when the CPU has them all.
    #[cfg(target_arch = "x86_64")]
    Avx2(Avx2Token),
}

/// Proof that the running CPU has what [`Isa::Avx2`] is compiled for: only [`Isa::best`] makes one.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Avx2Token(());

impl Isa {
    /// The best this CPU runs (detected once by the standard library, then a cached load).
    pub fn best() -> Isa {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2")
            && std::is_x86_feature_detected!("bmi1")
            && std::is_x86_feature_detected!("bmi2")
            && std::is_x86_feature_detected!("lzcnt")
            && std::is_x86_feature_detected!("popcnt")
        {
            return Isa::Avx2(Avx2Token(()));
        }
        Isa::Baseline
    }
}
