//! GPU backend (wgpu compute shaders, WGSL preconditioned conjugate gradient).
//!
//! Not implemented yet: this crate only reports that the backend is unavailable,
//! so that `--backend gpu` fails with a clear message (exit 2) instead of falling
//! back silently. The GPU issue fills it in behind `solver_cpu::SpdSolver`.

/// Why the GPU backend cannot be used.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{0}")]
pub struct Unavailable(pub String);

/// Returns the GPU solver, or why there is none.
pub fn open() -> Result<std::convert::Infallible, Unavailable> {
    Err(Unavailable(
        "the GPU backend is not implemented in this version of metricdeform; use --backend cpu"
            .into(),
    ))
}
