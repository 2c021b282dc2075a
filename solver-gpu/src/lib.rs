//! GPU backend: a preconditioned conjugate gradient in WGSL compute shaders on
//! wgpu (Vulkan), behind [`solver_cpu::SpdSolver`].
//!
//! # The math
//!
//! The precision follows the system kind ([`MixedPrecision::ByKind`], the
//! default, measured in `BENCHMARKS.md`, "GPU precision policy"): the shape
//! systems (Eqs. 7 and 8) run as the **mixed-precision PCG** below from their
//! first solve, the scale-factor system (Eq. 3) as **iterative refinement**
//! around an **f32 PCG**. For an SPD matrix `A` (3x3-block vertex systems, or
//! the scalar face system), refinement solves each right-hand side `b` as:
//!
//! ```text
//! x = x0 (0, or the caller's guess)                        host, f64
//! loop (at most max_rounds):
//!     r = b - A x                    f64 SpMV on the host (rayon)
//!     stop if ||r|| <= max(tol ||b||, eps ||A||_inf ||x||)
//!                                    (per column; tol = 1e-10 by default; the
//!                                    second term is the f64 rounding floor,
//!                                    which no f64 solver gets under)
//!     solve A d = r / ||r||          f32 PCG on the GPU, d0 = 0, to a relative
//!                                    residual eta = clamp(0.5 tol ||b|| / ||r||, 1e-5, 0.1)
//!     x += ||r|| d                   host, f64
//! ```
//!
//! The f64 residual makes the result as accurate as a direct f64 solve (to the
//! tolerance) although the GPU only computes in f32; each round gains about
//! `eta` as long as `cond(A) * 2^-24 << 1`. A warm start (`solve_with_guess`)
//! helps through the first residual: a good guess needs fewer or cheaper rounds.
//!
//! Where the rounds are limited by f32 rounding (two rounds in a row whose f64
//! residual gained less than `(1/eta)^(1/3)` where the f32 PCG reached its
//! tolerance `eta`), stagnate (three
//! without halving the residual), break down or run out, and the adapter has
//! `SHADER_F64`, the solve goes on in **mixed precision** ([`MixedPrecision`]),
//! as the shape systems do from the start: PCG with f64
//! vectors, scalars and SpMV (3x3 blocks as high and low f32 parts in two
//! storage buffers, `shaders/bsr_spmv_f64.wgsl`; a scalar matrix as f64 CSR),
//! preconditioned by the same f32 AMG V-cycle on f32 copies of `r` and `z`
//! (`shaders/convert.wgsl`). Its rounds are the loop above with every step
//! on the GPU (`refine`, `shaders/refine.wgsl`): `b` and the guess go up once
//! per solve, the f64 residual `b - A x` (with the exact matrix: the f64
//! CSR values, or a block matrix's f64 lower blocks through
//! `shaders/refine_product.wgsl`) and its norms are formed after each batch
//! that may end a round, in the same submission, and the host reads the norms
//! and `x` with the PCG's column states; it forms no residual. (A block
//! matrix whose f64 values are not on the GPU, written by the host, has its
//! residuals formed on the host.) On the shape systems the f32 PCG converges far
//! slower than this one with the same preconditioner (homer, 12k faces: 112
//! against 41 PCG iterations per scale-driven solve, 446 against 182 in the
//! fine-tune; at 108k faces the first f32 round broke down after ~480).
//!
//! New values of a prepared 3x3-block pattern go up as their lower triangle
//! in f64 (the host converts nothing) and `shaders/expand_blocks.wgsl` writes
//! both triangles, the held rows and the f32 high and low parts on the GPU
//! (where the adapter has `SHADER_F64`; else the host writes f32 values). A
//! shape matrix in isotropic-plus-ring form ([`solver_cpu::IsoRingSym3`],
//! `K (x) I3 + sum_i R_i^T C_i R_i`) goes up as less still, `K`'s values and
//! the `C_i`: `shaders/sum_shape_blocks.wgsl` sums its lower blocks on the GPU
//! (each block's ring pairs and weights found once per pattern and rings;
//! the f64 lower blocks in up to four storage bindings,
//! `expand_blocks::LowerParts`),
//! and the host keeps the matrix in that form, as the CPU backend does, for
//! its residuals (matrix-free) and diagonal blocks: no blocks on the host.
//! Once a kind's factor is made, the later matrices leave E_m's constant
//! Hessian `S Mt^-1 S` out of `K` and name it
//! ([`IsoRingSym3::laplacian_square`](solver_cpu::IsoRingSym3::laplacian_square)):
//! its values go up once per weight set and the sum adds them to `K`.
//!
//! The **shape systems** (the scale-driven ones, Eq. 7, and the fine-tune's,
//! Eq. 8) are preconditioned by default as the CPU backend's block PCG is,
//! by the **Cholesky factor of their isotropic part** `K_ij = tr(A_ij) / 3`
//! ([`Preconditioner::Cholesky`]), `M = P^T L L^T P (x) I3`:
//!
//! ```text
//! P K P^T = L L^T            host, faer, f64 where the PCG is f64, once per system kind
//! L_ss := L_ss^-1            host, each supernode's diagonal block
//! L_rs := L_rs L_ss^-1       host, the rows below it
//! z = P^T L^-T L^-1 P r      GPU, three dispatches per level of the elimination tree
//! ```
//!
//! (`supernodal`, `shaders/supernodal.wgsl`; the values, and the updates its
//! solves pass up the tree, split over several storage bindings at supernode
//! boundaries where they exceed one). With [`Factorization::Gpu`]
//! ([`GpuSolver::set_factorization`], `METRICDEFORM_GPU_FACTORIZATION=gpu`;
//! the default on a hardware adapter with f64 shaders, measured faster on
//! an H200 at every size, [`Factorization::on`]) the first three lines
//! run on the GPU instead, from `K`'s values on the host's symbolic analysis
//! (`factorize`, `shaders/supernodal_factor.wgsl`; its work counted from the
//! structure alone: [`factorization_work`]), where the factor is f64
//! and fits two storage bindings; the scale factors' factor (below) too. The
//! **scale-factor system** (Eq. 3, scalar, its Hessian constant for the run)
//! has its own factor, in f64 where the adapter has `SHADER_F64`: the scale
//! factors' **Newton steps run on the GPU** with it as a direct solve
//! ([`SpdSolver::power_sum_newton`](solver_cpu::SpdSolver::power_sum_newton),
//! `power_sum_newton`, `shaders/power_sum_newton.wgsl`: values, Jacobian
//! rows, `Y = A^-1 L^T`, the multipliers, the step and its length, a batch
//! of steps per submission and one host wait for it), and a solve through it
//! otherwise (more than [`CMAX`] constraints, per-kind multipliers) is an f64
//! PCG with an exact preconditioner, ending in one round of 1-2 iterations
//! (in f32, without `SHADER_F64`). A
//! factor whose largest supernode does not fit one storage binding, or an f32
//! one that breaks down, falls back: the scale factors to the AMG V-cycle
//! below, the shape systems to the
//! **squared Laplacian** ([`Preconditioner::SquaredLaplacian`]): their
//! isotropic part is close to `S Mt^-1 S + c S` (`S` the input's cotangent
//! Laplacian; E_m's bi-Laplacian and E_f's Laplacian,
//! [`solver_cpu::ShapeOperatorModel`], handed over by
//! [`SpdSolver::set_shape_model`](solver_cpu::SpdSolver::set_shape_model)), and
//!
//! ```text
//! z = B^-1 Mt B^-1 r,   B = S + eps Mt   (held rows identity)
//! P^-1 = S Mt^-1 S + 2 eps S + eps^2 Mt
//! ```
//!
//! each `B^-1` `v` V-cycles (Richardson from zero, a fixed symmetric
//! operator; `v` grows as the square root of `B`'s rows, 3 at 54k and 10 at
//! 600k: [`squared_laplacian_vcycles`]) of a scalar SA-AMG hierarchy of `B` (4 Jacobi sweeps each way)
//! applied to x, y and z at once (`B (x) I3`, by scalar CSR kernels on
//! interleaved 3-vectors: 8 bytes a stored entry), the rows
//! scaled by `Mt` in between (`shaders/scale_rows.wgsl`). `B` depends on the
//! input mesh and the weights only: it is set up once per run and never
//! refreshed, whatever the outer iteration's matrix values.
//!
//! Every other system (or every system, as asked) is preconditioned by one **smoothed-aggregation AMG
//! V-cycle** ([`Preconditioner::AffineAmg`]:
//! hierarchy built on the CPU in f64 by [`amg`] once per system kind
//! ([`SpdSolver::set_system_kind`](solver_cpu::SpdSolver::set_system_kind): scale factors, scale-driven shape,
//! fine-tune), applied by `shaders/amg.wgsl` through [`amg_gpu`]; a later
//! matrix of the same kind and pattern rewrites only the PCG's matrix values
//! and the finest smoother's diagonal and keeps the coarse levels, a fixed SPD
//! preconditioner (a solve that fails with it rebuilds it, once);
//! its near-null space is the vertices' affine motions where their positions
//! were given by [`SpdSolver::set_vertex_positions`](solver_cpu::SpdSolver::set_vertex_positions), else the translations),
//! or by block Jacobi `M = blockdiag(A)` ([`Preconditioner::BlockJacobi`]: 3x3
//! blocks inverted on the CPU in f64; plain Jacobi for the scalar system; also
//! the fallback when AMG coarsening stalls). [`GpuSolver::set_preconditioner`] or
//! `METRICDEFORM_GPU_PRECONDITIONER=cholesky|squared-laplacian|affine-amg|amg` chooses. The PCG keeps every scalar on the GPU:
//! `alpha = r.z / p.Ap` and `beta = r'.z' / r.z` are computed per column by a
//! one-workgroup kernel from per-workgroup partial sums; the host reads the
//! per-column state back only after batches of iterations (the first as long
//! as the last run of the same kind, later ones sized from the observed
//! convergence rate, at most 32; a batch sized to finish brings `x` back
//! with the state). Up to
//! [`CMAX`] right-hand sides run together, so the matrix is read once per
//! iteration for all of them. Breakdown (`p.Ap <= 0`, NaN) means the matrix is
//! not positive definite ([`SolverError::NotPositiveDefinite`](solver_cpu::SolverError::NotPositiveDefinite)); running out of
//! rounds or iterations gives [`SolverError::NoConvergence`](solver_cpu::SolverError::NoConvergence), never a hang.
//!
//! The matrix pattern is uploaded once per pattern; a new matrix with the same
//! pattern only rewrites the values. Vector buffers are sized for the largest
//! number of columns seen and reused.
//!
//! Every matrix and vector lives in storage buffers (no textures): a 3x3
//! block is its 9 f32 values and a u32 column (40 bytes, the least it can be
//! stored in), and the block SpMV reads the search direction `p` in place.
//! A block matrix whose values pass the adapter's
//! `max_storage_buffer_binding_size` is split by block rows into chunks that
//! each fit one binding (`matrix::split_rows`), one dispatch per chunk; only a
//! single block row over the limit is a [`GpuError::LimitExceeded`].

pub mod amg;
pub mod amg_gpu;
pub mod block_jacobi;
pub mod bsr_spmv;
mod convert;
pub mod csr_spmv;
mod device;
pub mod dot;
mod expand_blocks;
mod factorize;
pub mod kernels;
mod matrix;
pub mod pcg;
mod power_sum_newton;
pub mod precision;
mod refine;
mod scale_rows;
#[cfg(feature = "bench-kernels")]
pub mod stream;
mod supernodal;

pub use device::{AdapterSummary, KernelWork, OpenOptions};
pub use wgpu;
pub use wgpu::naga;

mod error;
mod preconditioner;
#[cfg(test)]
mod shader_layout_tests;
mod solver;

pub use error::GpuError;
pub use factorize::{factorization_work, Factorization};
pub use precision::MixedPrecision;
pub use preconditioner::{squared_laplacian_vcycles, Preconditioner, SQUARED_LAPLACIAN_SWEEPS};
pub use solver::{
    drop_opened_ahead, gpu_available, open, open_ahead, open_with, GpuSolver, SolveStats,
};

/// The default adapter's solver for a unit test, or `None` (the test passes
/// without running) where there is none; with `REQUIRE_GPU=1` (as in CI)
/// none fails the test.
#[cfg(test)]
pub(crate) fn test_solver() -> Option<GpuSolver> {
    match open() {
        Ok(s) => Some(s),
        Err(e) => {
            assert!(
                std::env::var("REQUIRE_GPU").map_or(true, |v| v != "1"),
                "REQUIRE_GPU=1 but no GPU adapter: {e}"
            );
            None
        }
    }
}

/// Most right-hand sides one PCG batch carries (more are solved in batches).
pub const CMAX: usize = 8;

/// Adapters wgpu sees (Vulkan), for `metricdeform adapters`.
pub fn list_adapters() -> Vec<AdapterSummary> {
    device::list_adapters()
}

/// The adapter [`open`] would pick (`WGPU_ADAPTER_NAME` substring, else wgpu's
/// high-performance default), without opening a device.
pub fn default_adapter() -> Result<AdapterSummary, GpuError> {
    device::default_adapter()
}

/// The choice the environment variable `var` names, matched without regard
/// to case, and with `_` read as `-`, against `names` (each name with the
/// value it stands for):
/// `None` where `var` is unset or empty, and where its value names nothing,
/// which is logged as a warning with the spellings taken and `instead`,
/// what is used in its place. The `METRICDEFORM_GPU_*` switches
/// ([`Preconditioner::from_env`], [`MixedPrecision::from_env`],
/// [`Factorization::from_env`], the factorization's kernels).
pub(crate) fn env_choice<T: Copy>(var: &str, names: &[(&str, T)], instead: &str) -> Option<T> {
    let value = std::env::var(var)
        .unwrap_or_default()
        .to_lowercase()
        .replace('_', "-");
    if value.is_empty() {
        return None;
    }
    let found = names
        .iter()
        .find(|(name, _)| *name == value)
        .map(|&(_, v)| v);
    if found.is_none() {
        let taken: Vec<&str> = names.iter().map(|(name, _)| *name).collect();
        log::warn!(
            "{var}={value} is none of {}; using {instead}",
            taken.join(", ")
        );
    }
    found
}

#[cfg(test)]
mod env_choice_tests {
    /// A variable of its own (no other test reads it): unset, a spelling in
    /// another case and with `_` for `-`, and a value that names nothing.
    #[test]
    fn env_choice_matches_without_case_and_gives_none_for_the_rest() {
        let var = "METRICDEFORM_TEST_ENV_CHOICE";
        let names = [("one", 1), ("two-ways", 2)];
        std::env::remove_var(var);
        assert_eq!(super::env_choice(var, &names, "none"), None);
        std::env::set_var(var, "");
        assert_eq!(super::env_choice(var, &names, "none"), None);
        std::env::set_var(var, "Two_Ways");
        assert_eq!(super::env_choice(var, &names, "none"), Some(2));
        std::env::set_var(var, "TWO-WAYS");
        assert_eq!(super::env_choice(var, &names, "none"), Some(2));
        std::env::set_var(var, "ONE");
        assert_eq!(super::env_choice(var, &names, "none"), Some(1));
        std::env::set_var(var, "three");
        assert_eq!(super::env_choice(var, &names, "none"), None);
        std::env::remove_var(var);
    }
}
