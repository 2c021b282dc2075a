//! Reference backend: sparse Cholesky `A = L L^T` with faer.
//!
//! Symbolic/numeric split: the elimination tree, ordering and supernodes are
//! computed once per sparsity pattern (`SymbolicLlt`) and reused for every new set
//! of values (`Llt::try_new_with_symbolic`).

use crate::{SolveInfo, SolverError, SpdSolver, SymCsc};
use faer::linalg::solvers::SolveCore;
use faer::sparse::linalg::solvers::{Llt, SymbolicLlt};
use faer::sparse::linalg::LltError;
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Conj, MatMut, Side};

/// faer sparse Cholesky with the symbolic factorization reused across matrices
/// of the same pattern.
#[derive(Default)]
pub struct CholeskySolver {
    pattern: Option<(Vec<usize>, Vec<usize>)>,
    symbolic: Option<SymbolicLlt<usize>>,
    numeric: Option<Llt<usize, f64>>,
    n: usize,
    /// How many symbolic analyses were made (for tests and benchmarks).
    pub symbolic_count: usize,
    /// How many numeric factorizations were made.
    pub numeric_count: usize,
}

impl CholeskySolver {
    pub fn new() -> Self {
        Self::default()
    }
}

impl SpdSolver for CholeskySolver {
    fn prepare(&mut self, a: &SymCsc) -> Result<(), SolverError> {
        let same = matches!(&self.pattern, Some((cp, ri)) if *cp == a.col_ptr && *ri == a.row_idx);
        // SAFETY-free: the pattern is validated by faer's checked constructor.
        let sym_ref = SymbolicSparseColMatRef::new_checked(a.n, a.n, &a.col_ptr, None, &a.row_idx);
        if !same || self.symbolic.is_none() {
            let sym = SymbolicLlt::try_new(sym_ref, Side::Lower)
                .map_err(|e| SolverError::Backend(format!("symbolic Cholesky: {e:?}")))?;
            self.symbolic = Some(sym);
            self.pattern = Some((a.col_ptr.clone(), a.row_idx.clone()));
            self.symbolic_count += 1;
        }
        let mat = SparseColMatRef::new(sym_ref, &a.values);
        let llt = Llt::try_new_with_symbolic(self.symbolic.clone().unwrap(), mat, Side::Lower)
            .map_err(|e| match e {
                LltError::Numeric(_) => SolverError::NotPositiveDefinite,
                LltError::Generic(g) => SolverError::Backend(format!("{g:?}")),
            })?;
        self.numeric = Some(llt);
        self.n = a.n;
        self.numeric_count += 1;
        Ok(())
    }

    fn solve_in_place(&mut self, rhs: &mut [f64], ncols: usize) -> Result<SolveInfo, SolverError> {
        let llt = self.numeric.as_ref().ok_or(SolverError::NotPrepared)?;
        if rhs.len() != self.n * ncols {
            return Err(SolverError::DimensionMismatch(format!(
                "rhs has {} entries, expected {} x {}",
                rhs.len(),
                self.n,
                ncols
            )));
        }
        let m = MatMut::from_column_major_slice_mut(rhs, self.n, ncols);
        llt.solve_in_place_with_conj(Conj::No, m);
        if rhs.iter().any(|v| !v.is_finite()) {
            return Err(SolverError::NotPositiveDefinite);
        }
        Ok(SolveInfo {
            iterations: 0,
            residual: 0.0,
        })
    }

    fn name(&self) -> &str {
        "cpu"
    }
}
