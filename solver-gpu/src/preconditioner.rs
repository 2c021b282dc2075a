//! Which preconditioner the PCG runs, per system kind (see the crate docs for
//! the math of each).

/// Jacobi sweeps before and after the coarse correction in the V-cycles of
/// the squared-Laplacian preconditioner: twice the default's, which halves
/// the PCG iterations on spot x16 (105 to 41, `benches/shape_preconditioner.rs`)
/// for V-cycles of a scalar Laplacian, cheap beside the shape matrix's product.
pub const SQUARED_LAPLACIAN_SWEEPS: usize = 4;

/// V-cycles per `B^-1` of the squared-Laplacian preconditioner (Richardson
/// from zero: symmetric, a fixed linear operator) for a `B` of `n` rows:
/// `ceil(3 sqrt(n / 54,000))`, at least 2, at most 24.
///
/// The preconditioner is only as good as `B^-1` squared: with exact solves the
/// PCG needs 19-30 iterations at any size, but one V-cycle's contraction on
/// `B` worsens with the mesh (its B-norm ratio after 12 cycles: 0.47 on spot
/// x4, 0.56 on spot x16, 0.75 on homer's 108k faces; `cargo bench --bench
/// shape_preconditioner -- --homer --gpu-form-only --rho`), and the count with
/// it. Homer 108k (54k rows of `B`), f64: 252 / 110 / 69 / 51 / 39 PCG
/// iterations with 1 / 2 / 3 / 4 / 6 V-cycles; with an iteration costing
/// `0.5 + 1.4 v` ms (the H100's fit at 1.2M, below, scaled) the least work is
/// at 3-4.
/// Homer 1.2M (600k rows), the first scale-driven solve on an NVIDIA H100:
/// 2366 / 875 / 296 / 168 iterations with 2 / 4 / 8 / 12 V-cycles, 7.8 / 5.2 /
/// 3.6 / 2.9 s of GPU time. Hence V-cycles growing as the square root of the
/// rows (3 at 54k, 10 at 600k, 19 at 2.2M).
pub fn squared_laplacian_vcycles(n: usize) -> usize {
    ((3.0 * (n as f64 / 54_000.0).sqrt()).ceil() as usize).clamp(2, 24)
}

/// The preconditioner of the f32 PCG.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Preconditioner {
    /// `M = blockdiag(A)` (3x3 blocks, or plain Jacobi for the scalar system).
    BlockJacobi,
    /// One smoothed-aggregation AMG V-cycle ([`crate::amg`], [`crate::amg_gpu`]), the
    /// translations as near-null space.
    Amg,
    /// The same V-cycle on a hierarchy whose near-null space is the 12 affine
    /// motions of the vertices ([`crate::amg::Hierarchy::build_affine`]), for block
    /// matrices whose vertex positions were given
    /// ([`solver_cpu::SpdSolver::set_vertex_positions`]); otherwise as `Amg`.
    AffineAmg,
    /// For the shape systems (scale-driven and fine-tune) with a model
    /// ([`solver_cpu::SpdSolver::set_shape_model`]): `z = B^-1 Mt B^-1 r`, each `B^-1`
    /// [`squared_laplacian_vcycles`] V-cycles of the screened Laplacian `B = S + eps Mt`
    /// ([`crate::amg::squared_laplacian`]) applied to x, y and z at once. `B` depends
    /// on the input mesh and the weights only: built once per run, never
    /// refreshed. The fine-tune's (weights 1/100/100) too: on an NVIDIA H100,
    /// homer 1.2M, 1255 PCG iterations in its two solves against 2305 with
    /// `AffineAmg`, 9 s of host time against 42 s, a host peak of 3380 MiB
    /// for the whole run against 14148 MiB (the affine hierarchy's 12x12
    /// blocks), but 63.8 s for the phase against 57.6 s (each iteration applies
    /// 2 x 11 V-cycles to its 4 right-hand sides); 108k: at most 300
    /// iterations against 541, 3.1 s against 6.9 s. Every other system (the
    /// scale factors') as `AffineAmg`.
    SquaredLaplacian,
    /// For the shape systems prepared in isotropic-plus-ring form
    /// ([`solver_cpu::SpdSolver::prepare_shape_owned`]): the supernodal Cholesky
    /// factor of their isotropic part `K` (held rows identity), made on the host
    /// once per system kind per run and applied on the GPU by level-scheduled
    /// triangular solves (`supernodal.rs`, `shaders/supernodal.wgsl`), the CPU backend's
    /// preconditioner. For the scale factors' scalar system
    /// ([`solver_cpu::SystemKind::ScaleFactors`], prepared by
    /// [`solver_cpu::SpdSolver::prepare`]): that matrix's own factor, in f32
    /// (exact but for rounding: one f64 round of 1-2 iterations). A factor's
    /// values may span several storage bindings; where its largest supernode
    /// does not fit one, or it cannot be made, the shape systems fall back to
    /// `SquaredLaplacian` and the scale factors to `AffineAmg` (a scalar AMG).
    #[default]
    Cholesky,
}

impl Preconditioner {
    /// From `METRICDEFORM_GPU_PRECONDITIONER` (`cholesky`, `squared-laplacian`,
    /// `affine-amg` or `amg`), else
    /// the default. Block Jacobi is not offered there: it needs tens of
    /// thousands of iterations on the shape systems of 100k-face meshes
    /// (50,000 without converging on an H100), so it stays an API choice for
    /// tests and a fallback where AMG coarsening fails.
    pub fn from_env() -> Preconditioner {
        crate::env_choice(
            "METRICDEFORM_GPU_PRECONDITIONER",
            &[
                ("cholesky", Preconditioner::Cholesky),
                ("amg", Preconditioner::Amg),
                ("affine-amg", Preconditioner::AffineAmg),
                ("squared-laplacian", Preconditioner::SquaredLaplacian),
            ],
            "cholesky",
        )
        .unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::squared_laplacian_vcycles;

    /// More V-cycles as `B` grows, from 2 up to 24: 3 at homer's 108k faces
    /// (54k rows), 10 at its 1.2M (600k rows).
    #[test]
    fn vcycles_grow_with_the_rows() {
        assert_eq!(squared_laplacian_vcycles(0), 2);
        assert_eq!(squared_laplacian_vcycles(5_000), 2);
        assert_eq!(squared_laplacian_vcycles(54_000), 3);
        assert_eq!(squared_laplacian_vcycles(600_000), 10);
        assert_eq!(squared_laplacian_vcycles(usize::MAX), 24);
        let v: Vec<usize> = (0..60)
            .map(|k| squared_laplacian_vcycles(k * 50_000))
            .collect();
        assert!(v.windows(2).all(|w| w[0] <= w[1]), "{v:?}");
    }
}
