//! Kernel precision. The shaders are written in f32; where the adapter has
//! `SHADER_F64` the PCG shaders (`pcg.wgsl`, `csr_spmv.wgsl`) also compile in
//! f64 after a small text transform of the same source ([`f64_source`]):
//!
//! 1. the lines from `// f32-only begin` to `// f32-only end` are dropped
//!    (constants that only hold in f32, such as `TINY`);
//! 2. a line `// f64-only: CODE` becomes `CODE`;
//! 3. every `f32` becomes `f64`.
//!
//! The f64 kernels run the mixed-precision solve (f64 PCG, f32 V-cycle; its
//! block product is the hand-written `bsr_spmv_f64.wgsl`) and the precision
//! measurement (`kernels::scalar_pcg` and the `pcg_kernels` benchmark); the
//! solver's first choice is f32 kernels with residuals in f64 on the host
//! (iterative refinement), see `BENCHMARKS.md`.

use solver_cpu::SystemKind;
use std::borrow::Cow;

/// Floating-point type of the GPU vectors, matrix values and PCG scalars.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Precision {
    F32,
    /// Needs the adapter feature `SHADER_F64`.
    F64,
}

impl Precision {
    /// Bytes of one value.
    pub fn bytes(self) -> u64 {
        match self {
            Precision::F32 => 4,
            Precision::F64 => 8,
        }
    }

    /// `v` rounded to this precision, as the bytes a buffer holds.
    pub(crate) fn encode(self, v: &[f64]) -> Vec<u8> {
        match self {
            Precision::F32 => {
                let w: Vec<f32> = v.iter().map(|&a| a as f32).collect();
                bytemuck::cast_slice(&w).to_vec()
            }
            Precision::F64 => bytemuck::cast_slice(v).to_vec(),
        }
    }

    /// The shader source in this precision.
    pub(crate) fn source(self, src: &'static str) -> Cow<'static, str> {
        match self {
            Precision::F32 => Cow::Borrowed(src),
            Precision::F64 => Cow::Owned(f64_source(src)),
        }
    }
}

/// The f64 variant of an f32 shader source (the transform of the module docs).
pub fn f64_source(src: &str) -> String {
    let mut out = String::with_capacity(src.len());
    let mut skipping = false;
    for line in src.lines() {
        let t = line.trim_start();
        if t.starts_with("// f32-only begin") {
            skipping = true;
            continue;
        }
        if t.starts_with("// f32-only end") {
            skipping = false;
            continue;
        }
        if skipping {
            continue;
        }
        let line = match t.strip_prefix("// f64-only: ") {
            Some(code) => code,
            None => line,
        };
        out.push_str(&line.replace("f32", "f64"));
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn f64_source_drops_f32_sections_and_uncomments_f64_lines() {
        let src = "var<storage> a: array<f32>;\n\
                   // f32-only begin\n\
                   const HALF: f32 = 0.5;\n\
                   // f32-only end\n\
                   // f32-only begin\n\
                   const TINY: f32 = 1e-12;\n\
                   // f32-only end\n\
                   // f64-only: const TINY: f32 = 1e-24;\n\
                   fn g() -> f32 { return 0.0; }\n";
        let out = f64_source(src);
        assert_eq!(
            out,
            "var<storage> a: array<f64>;\n\
             const TINY: f64 = 1e-24;\n\
             fn g() -> f64 { return 0.0; }\n"
        );
    }
}

/// When the solver runs the PCG iteration in f64 with the f32 AMG V-cycle as
/// its preconditioner (needs `SHADER_F64` and the AMG preconditioner).
///
/// The default, [`MixedPrecision::ByKind`], is measured (BENCHMARKS.md, "GPU
/// precision policy"): on the shape systems the f32 PCG converges far slower
/// than the f64 one with the same f32 preconditioner (its recurrence loses
/// conjugacy, and each refinement round restarts it), so those start in mixed
/// precision; the scale-factor systems converged in f32 in one or two rounds
/// of 8-18 iterations with the AMG V-cycle and keep the f32 kernels there,
/// which move fewer bytes. Preconditioned by their own Cholesky factor, the
/// default, they too start in mixed precision, and that factor is made in
/// f64: an iteration or two (one host wait) ends a solve where f32
/// refinement needs two rounds, and the scale factors' Newton steps run on
/// the device with it as a direct solve
/// ([`solver_cpu::SpdSolver::power_sum_newton`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MixedPrecision {
    /// After f32 refinement stagnates (the system is too ill-conditioned for
    /// f32: `cond(A) 2^-24` near 1), where the adapter has `SHADER_F64`; then
    /// every later solve of the same matrix pattern starts in mixed precision.
    Fallback,
    /// The shape systems ([`SystemKind::ScaleDriven`], [`SystemKind::FineTune`])
    /// in mixed precision from their first solve; the scale-factor systems
    /// too where their Cholesky factor preconditions them, else as
    /// [`MixedPrecision::Fallback`].
    #[default]
    ByKind,
    /// Every solve (where the adapter has `SHADER_F64`).
    Always,
    /// Never: stagnation is `NoConvergence`.
    Never,
}

impl MixedPrecision {
    /// Whether a solve of `kind` starts in mixed precision (before any
    /// fallback).
    pub fn starts_mixed(self, kind: SystemKind) -> bool {
        match self {
            MixedPrecision::Always => true,
            MixedPrecision::ByKind => kind != SystemKind::ScaleFactors,
            MixedPrecision::Fallback | MixedPrecision::Never => false,
        }
    }

    /// Whether a solve of `kind` starts in mixed precision when its
    /// preconditioner is (`own_factor`) or is not the Cholesky factor of its
    /// matrix itself: with that exact preconditioner each f64 iteration gains
    /// about seven digits, so under [`MixedPrecision::ByKind`] one mixed round
    /// of an iteration or two ends the solve where f32 refinement needs two
    /// rounds (two waits).
    pub fn starts_mixed_with(self, kind: SystemKind, own_factor: bool) -> bool {
        self.starts_mixed(kind) || (own_factor && self == MixedPrecision::ByKind)
    }
}

impl MixedPrecision {
    /// From `METRICDEFORM_GPU_PRECISION` (`fallback`, `by-kind`, or `mixed` for
    /// [`MixedPrecision::Always`]), else the default. [`MixedPrecision::Never`]
    /// is not offered there: the f32 PCG alone breaks down on the shape
    /// systems of 100k-face meshes (BENCHMARKS.md), so it stays an API
    /// choice for tests.
    pub fn from_env() -> MixedPrecision {
        crate::env_choice(
            "METRICDEFORM_GPU_PRECISION",
            &[
                ("fallback", MixedPrecision::Fallback),
                ("by-kind", MixedPrecision::ByKind),
                ("mixed", MixedPrecision::Always),
                ("always", MixedPrecision::Always),
            ],
            &format!("{:?}", MixedPrecision::default()),
        )
        .unwrap_or_default()
    }
}

/// Tells when f32 refinement rounds are limited by f32 rounding. A round whose
/// inner PCG reached its tolerance `eta` (a gain of `1/eta` in its f32
/// recurrence) while the true f64 residual gained less than `(1/eta)^(1/3)`
/// was limited by f32: the f64 iteration of the mixed-precision solve would
/// gain about `1/eta` in as many iterations, at 1.6-2.2x the cost of an f32
/// one on lavapipe. Two such rounds in a row are needed (a first round alone
/// can be weak and the next ones fine: a 128x128 biharmonic system's rounds
/// gain 13x, then 1660x and 2000x against 1e5 asked). Spot x16's shape system:
/// 7 f32 rounds of ~190 iterations gaining ~27x each against 1e5 asked, 1354
/// iterations in all, against 527 in mixed precision (lavapipe, 2026-11-22;
/// BENCHMARKS.md's git history).
#[derive(Default)]
pub(crate) struct RoundWatch {
    /// The last round's relative residual and inner tolerance per column
    /// (`eta = 1`: the column was done).
    last: Option<(Vec<f64>, Vec<f64>)>,
    /// Limited rounds in a row.
    limited: usize,
}

impl RoundWatch {
    /// With the relative residuals `rel` after the last round: whether the
    /// rounds are limited by f32 rounding.
    pub(crate) fn f32_limited(&mut self, rel: &[f64]) -> bool {
        let limited = self.last.as_ref().is_some_and(|(prev, eta)| {
            (0..rel.len()).any(|c| eta[c] < 1.0 && rel[c] > prev[c] * eta[c].cbrt())
        });
        self.limited = if limited { self.limited + 1 } else { 0 };
        self.limited >= 2
    }

    /// A round starts from the relative residuals `rel`, asking each column
    /// for a relative tolerance `eta` (1 for columns already done).
    pub(crate) fn launched(&mut self, rel: &[f64], eta: Vec<f64>) {
        self.last = Some((rel.to_vec(), eta));
    }
}

#[cfg(test)]
mod round_watch_tests {
    use super::RoundWatch;

    /// Feeds rounds of (residual after, eta asked) for one column from a
    /// residual of 1; returns the verdict after each round.
    fn verdicts(rounds: &[(f64, f64)]) -> Vec<bool> {
        let mut w = RoundWatch::default();
        let mut rel = 1.0;
        assert!(!w.f32_limited(&[rel]), "no round yet");
        rounds
            .iter()
            .map(|&(after, eta)| {
                w.launched(&[rel], vec![eta]);
                rel = after;
                w.f32_limited(&[rel])
            })
            .collect()
    }

    #[test]
    fn two_weak_rounds_in_a_row_mean_f32_rounding() {
        // Spot x16's shape system: ~27x a round against 1e5 asked (cube root 46).
        assert_eq!(
            verdicts(&[(1.0 / 27.0, 1e-5), (1.0 / 27.0 / 27.0, 1e-5)]),
            [false, true]
        );
        // The 128x128 biharmonic: a weak first round, then healthy ones.
        assert_eq!(
            verdicts(&[(7.5e-2, 1e-5), (4.5e-5, 1e-5), (2.3e-8, 1e-5)]),
            [false, false, false]
        );
        // Near the end eta is larger (0.1, cube root 0.46): gaining 3x passes,
        // 1.5x twice does not.
        assert_eq!(
            verdicts(&[(1.0 / 3.0, 0.1), (1.0 / 9.0, 0.1)]),
            [false, false]
        );
        assert_eq!(
            verdicts(&[(1.0 / 1.5, 0.1), (1.0 / 2.25, 0.1)]),
            [false, true]
        );
    }

    #[test]
    fn columns_already_done_do_not_count() {
        let mut w = RoundWatch::default();
        // Column 1 is done (eta 1) and its residual does not move; column 0
        // gains 1e4 against 1e5 asked.
        w.launched(&[1.0, 1e-11], vec![1e-5, 1.0]);
        assert!(!w.f32_limited(&[1e-4, 1e-11]));
        w.launched(&[1e-4, 1e-11], vec![1e-5, 1.0]);
        assert!(!w.f32_limited(&[1e-8, 1e-11]));
        // Column 0 weak twice: limited.
        w.launched(&[1e-8, 1e-11], vec![1e-2, 1.0]);
        assert!(!w.f32_limited(&[0.5e-8, 1e-11]));
        w.launched(&[0.5e-8, 1e-11], vec![1e-2, 1.0]);
        assert!(w.f32_limited(&[0.25e-8, 1e-11]));
    }
}
