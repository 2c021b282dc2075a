//! Errors of the GPU backend, and how they map onto the solver interface's
//! ([`SolverError`]).

use solver_cpu::SolverError;

/// Errors of the GPU backend.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GpuError {
    #[error("no GPU adapter: {0}")]
    NoAdapter(String),
    #[error("could not open the GPU device: {0}")]
    RequestDevice(String),
    #[error("GPU device lost: {0}")]
    DeviceLost(String),
    #[error("GPU out of memory: {0}")]
    OutOfMemory(String),
    #[error("{what} needs {needed}, over the device limit {limit_name} = {limit}")]
    LimitExceeded {
        what: String,
        limit_name: &'static str,
        needed: u64,
        limit: u64,
    },
    #[error(
        "PCG did not converge after {iterations} iterations (relative residual {residual:.3e})"
    )]
    NoConvergence { iterations: usize, residual: f64 },
    #[error("matrix is not positive definite (PCG breakdown)")]
    NotPositiveDefinite,
    #[error("GPU backend: {0}")]
    Backend(String),
}

impl From<GpuError> for SolverError {
    fn from(e: GpuError) -> SolverError {
        match e {
            GpuError::NoConvergence {
                iterations,
                residual,
            } => SolverError::NoConvergence {
                iterations,
                residual,
            },
            GpuError::OutOfMemory(_) => SolverError::OutOfMemory,
            GpuError::NotPositiveDefinite => SolverError::NotPositiveDefinite,
            other => SolverError::Backend(other.to_string()),
        }
    }
}
