//! Which preconditioner the PCG runs, per system kind (see the crate docs for
//! the math of each).

/// Jacobi sweeps before and after the coarse correction in the V-cycles of
/// the squared-Laplacian preconditioner: twice the default's, which halves
/// the PCG iterations on spot x16 (105 to 41, `benches/shape_preconditioner.rs`)
/// for V-cycles of a scalar Laplacian, cheap beside the shape matrix's product.
pub const SQUARED_LAPLACIAN_SWEEPS: usize = 4;

/// V-cycles per `B^-1` of the squared-Laplacian preconditioner (Richardson
/// from zero: symmetric, a fixed linear operator). The preconditioner is only
/// as good as `B^-1` squared: with exact solves PCG needs 19-30 iterations at
/// any size, with one V-cycle 39 / 59 / 125 on spot x4 / x16 / x64 and 252 on
/// homer's 108k faces, with two 32 / 38 on spot x4 / x16 and 110 on homer
/// (f64, `benches/shape_preconditioner.rs`).
pub const SQUARED_LAPLACIAN_VCYCLES: usize = 2;

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
    /// For the scale-driven shape systems with a model
    /// ([`solver_cpu::SpdSolver::set_shape_model`]): `z = B^-1 Mt B^-1 r`, each `B^-1`
    /// [`SQUARED_LAPLACIAN_VCYCLES`] V-cycles of the screened Laplacian `B = S + eps Mt`
    /// ([`crate::amg::squared_laplacian`]) applied to x, y and z at once. `B` depends
    /// on the input mesh and the weights only: built once per run, never
    /// refreshed. Every other system (the fine-tune's, whose E_l is as heavy
    /// as E_m and which is nearly blind to local affine motions: 211
    /// iterations against 218 with `AffineAmg` on spot) as `AffineAmg`.
    #[default]
    SquaredLaplacian,
}

impl Preconditioner {
    /// From `METRICDEFORM_GPU_PRECONDITIONER` (`squared-laplacian`,
    /// `affine-amg` or `amg`), else
    /// the default. Block Jacobi is not offered there: it needs tens of
    /// thousands of iterations on the shape systems of 100k-face meshes
    /// (50,000 without converging on an H100), so it stays an API choice for
    /// tests and a fallback where AMG coarsening fails.
    pub fn from_env() -> Preconditioner {
        let v = std::env::var("METRICDEFORM_GPU_PRECONDITIONER").unwrap_or_default();
        match v.to_lowercase().as_str() {
            "amg" => Preconditioner::Amg,
            "affine-amg" | "affine_amg" => Preconditioner::AffineAmg,
            "" | "squared-laplacian" | "squared_laplacian" => Preconditioner::SquaredLaplacian,
            other => {
                log::warn!(
                    "METRICDEFORM_GPU_PRECONDITIONER={other} is not a preconditioner \
                     (amg, affine-amg or squared-laplacian); using squared-laplacian"
                );
                Preconditioner::SquaredLaplacian
            }
        }
    }
}
