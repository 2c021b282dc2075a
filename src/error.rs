//! Error type of the library and its mapping onto the contract's exit codes.

use std::path::PathBuf;

/// Everything that can go wrong in a run. `exit_code` maps onto the contract:
/// 2 for bad input or usage, 1 for internal failures.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Bad input: the message names the file, constraint or element and what is wrong.
    #[error("{0}")]
    BadInput(String),
    /// A file could not be read or written.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A linear solve failed (not positive definite, no convergence, ...).
    #[error("linear solver: {0}")]
    Solver(#[from] solver_cpu::SolverError),
    /// The caller asked the run to stop (Ctrl-C).
    #[error("interrupted")]
    Interrupted,
    /// Anything else that is our fault, not the user's.
    #[error("internal error: {0}")]
    Internal(String),
}

impl Error {
    /// Contract exit code: 2 bad input / usage, 1 internal failure, 130 interrupted.
    pub fn exit_code(&self) -> i32 {
        match self {
            Error::BadInput(_) => 2,
            Error::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => 2,
            Error::Io { .. } => 2,
            Error::Solver(_) | Error::Internal(_) => 1,
            Error::Interrupted => 130,
        }
    }

    /// Shorthand for a bad-input error.
    pub fn bad(msg: impl Into<String>) -> Self {
        Error::BadInput(msg.into())
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;
