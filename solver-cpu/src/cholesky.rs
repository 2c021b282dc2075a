//! Reference backend: sparse Cholesky `A = L L^T` with faer.
//!
//! Symbolic/numeric split: the ordering, elimination tree and supernodes are
//! computed once per sparsity pattern and reused for every new set of values;
//! the numeric factor's storage and the scratch memory are reused too, so a
//! refactorization allocates nothing.

use crate::{BlockSym3, SolveInfo, SolverError, SpdSolver, SymCsc};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::cholesky::{factorize_symbolic_cholesky, LltRef, SymbolicCholesky};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{get_global_parallelism, Conj, MatMut, Side};

/// faer sparse Cholesky with the symbolic factorization reused across matrices
/// of the same pattern.
#[derive(Default)]
pub struct CholeskySolver {
    pattern: Option<(Vec<usize>, Vec<usize>)>,
    symbolic: Option<SymbolicCholesky<usize>>,
    numeric: Vec<f64>,
    factored: bool,
    scratch: Option<MemBuffer>,
    n: usize,
    /// Scalar copy of the last block matrix (pattern kept while unchanged).
    block_scalar: Option<(Vec<usize>, Vec<usize>, SymCsc)>,
    /// How many symbolic analyses were made (for tests and benchmarks).
    pub symbolic_count: usize,
    /// How many numeric factorizations were made.
    pub numeric_count: usize,
}

impl CholeskySolver {
    pub fn new() -> Self {
        Self::default()
    }

    /// Stored entries of the factor L.
    pub fn factor_nnz(&self) -> usize {
        self.symbolic.as_ref().map_or(0, |s| s.len_val())
    }
}

impl SpdSolver for CholeskySolver {
    fn prepare(&mut self, a: &SymCsc) -> Result<(), SolverError> {
        let same = matches!(&self.pattern, Some((cp, ri)) if *cp == a.col_ptr && *ri == a.row_idx);
        let sym_ref = SymbolicSparseColMatRef::new_checked(a.n, a.n, &a.col_ptr, None, &a.row_idx);
        if !same || self.symbolic.is_none() {
            let sym = factorize_symbolic_cholesky(
                sym_ref,
                Side::Lower,
                Default::default(),
                Default::default(),
            )
            .map_err(|e| SolverError::Backend(format!("symbolic Cholesky: {e:?}")))?;
            self.numeric = Vec::new();
            self.numeric
                .try_reserve_exact(sym.len_val())
                .map_err(|_| SolverError::OutOfMemory)?;
            self.numeric.resize(sym.len_val(), 0.0);
            self.symbolic = Some(sym);
            self.pattern = Some((a.col_ptr.clone(), a.row_idx.clone()));
            self.scratch = None;
            self.symbolic_count += 1;
            log::debug!(
                "Cholesky symbolic analysis: n {}, nnz(A) {}, nnz(L) {}",
                a.n,
                a.row_idx.len(),
                self.numeric.len()
            );
        }
        let sym = self.symbolic.as_ref().unwrap();
        let par = get_global_parallelism();
        if self.scratch.is_none() {
            let req = sym.factorize_numeric_llt_scratch::<f64>(par, Default::default());
            let req = req.or(sym.solve_in_place_scratch::<f64>(8, par));
            self.scratch = Some(MemBuffer::try_new(req).map_err(|_| SolverError::OutOfMemory)?);
        }
        let mat = SparseColMatRef::new(sym_ref, &a.values);
        self.factored = false;
        sym.factorize_numeric_llt::<f64>(
            &mut self.numeric,
            mat,
            Side::Lower,
            Default::default(),
            par,
            MemStack::new(self.scratch.as_mut().unwrap()),
            Default::default(),
        )
        .map_err(|_| SolverError::NotPositiveDefinite)?;
        self.factored = true;
        self.n = a.n;
        self.numeric_count += 1;
        Ok(())
    }

    fn prepare_blocks(&mut self, a: &BlockSym3, fixed: &[bool]) -> Result<(), SolverError> {
        a.check_fixed(fixed)?;
        let same =
            matches!(&self.block_scalar, Some((cp, ri, _)) if *cp == a.col_ptr && *ri == a.row_idx);
        if !same {
            self.block_scalar = Some((a.col_ptr.clone(), a.row_idx.clone(), a.scalar_pattern()));
        }
        let mut scalar = std::mem::take(&mut self.block_scalar.as_mut().unwrap().2);
        a.fill_scalar(&mut scalar, fixed);
        let r = self.prepare(&scalar);
        self.block_scalar.as_mut().unwrap().2 = scalar;
        r
    }

    fn solve_in_place(&mut self, rhs: &mut [f64], ncols: usize) -> Result<SolveInfo, SolverError> {
        if !self.factored {
            return Err(SolverError::NotPrepared);
        }
        if rhs.len() != self.n * ncols {
            return Err(SolverError::DimensionMismatch(format!(
                "rhs has {} entries, expected {} x {}",
                rhs.len(),
                self.n,
                ncols
            )));
        }
        // The triangular solves are memory-bound: faer's own parallel split is
        // slower here than sequential solves of the columns split among threads.
        let sym = self.symbolic.as_ref().unwrap();
        let numeric = &self.numeric;
        let n = self.n;
        let threads = rayon::current_num_threads().max(1);
        let per = ncols.div_ceil(threads).max(1);
        let failed = std::sync::atomic::AtomicBool::new(false);
        rayon::scope(|scope| {
            for chunk in rhs.chunks_mut(n * per) {
                let failed = &failed;
                scope.spawn(move |_| {
                    let cols = chunk.len() / n;
                    let par = faer::Par::Seq;
                    let Ok(mut buf) =
                        MemBuffer::try_new(sym.solve_in_place_scratch::<f64>(cols, par))
                    else {
                        failed.store(true, std::sync::atomic::Ordering::Relaxed);
                        return;
                    };
                    let m = MatMut::from_column_major_slice_mut(chunk, n, cols);
                    LltRef::<'_, usize, f64>::new(sym, numeric).solve_in_place_with_conj(
                        Conj::No,
                        m,
                        par,
                        MemStack::new(&mut buf),
                    );
                });
            }
        });
        if failed.into_inner() {
            return Err(SolverError::OutOfMemory);
        }
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
