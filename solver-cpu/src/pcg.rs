//! Preconditioned conjugate gradient on 3x3-block SPD matrices, preconditioned by
//! the Cholesky factor of the matrix's isotropic part.
//!
//! For `A` with blocks `A_ij` (one per vertex pair, dof `3 v + r`), the scalar
//! matrix `K_ij = tr(A_ij) / 3` is the mean of the three coordinate sub-matrices
//! `A_xx, A_yy, A_zz`, each a principal sub-matrix of `A`, so `K` is SPD whenever
//! `A` is. The preconditioner is `M = K (x) I3`: applying `M^-1` is one solve with
//! the scalar factor of `K` and three right-hand sides (x, y, z). Terms of the
//! shape energy of the form `(c c^T) (x) I3` (the frame and curvature terms, paper
//! Eqs. 4-5) are reproduced exactly by `M`; only the anisotropic direction term
//! (Eq. 6) is approximated, so PCG needs few iterations while the factor of `K`
//! has one ninth of the entries of a factor of `A` and costs about 1/27 of it.
//!
//! Every column stops when `||b - A x|| <= tolerance ||b||` (recurrence residual).

use crate::cholesky::CholeskySolver;
use crate::{BlockRows, BlockSym3, SolveInfo, SolverError, SpdSolver, SymCsc};
use rayon::prelude::*;

/// Settings of [`BlockPcgSolver`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlockPcgParams {
    /// Relative residual every column must reach.
    pub tolerance: f64,
    /// Iteration cap; reaching it is [`SolverError::NoConvergence`].
    pub max_iterations: usize,
    /// A new matrix of the same pattern keeps the previous preconditioner factor
    /// unless the last solve needed more than this many iterations or the trace
    /// of `K` moved by more than `refactor_trace_change` (relative). 0 refactors
    /// every time.
    pub refactor_iterations: usize,
    pub refactor_trace_change: f64,
}

impl Default for BlockPcgParams {
    fn default() -> Self {
        BlockPcgParams {
            tolerance: 1e-10,
            max_iterations: 2000,
            refactor_iterations: 6,
            refactor_trace_change: 0.05,
        }
    }
}

/// Block-sparse PCG with the isotropic Cholesky preconditioner (see module docs).
/// Scalar matrices (`prepare`) are solved directly by the inner Cholesky solver.
#[derive(Default)]
pub struct BlockPcgSolver {
    pub params: BlockPcgParams,
    /// The prepared block matrix, with held vertices replaced by identity rows.
    a: BlockSym3,
    /// Strictly lower blocks by block row.
    rows: BlockRows,
    /// Isotropic part `K` (same pattern as the blocks).
    k: SymCsc,
    precond: CholeskySolver,
    /// True when the last `prepare` was a scalar matrix (direct solve).
    scalar_mode: bool,
    /// Trace of the `K` that was last factored (0: none factored).
    factored_trace: f64,
    /// Iterations of the last block solve (its slowest column).
    last_iterations: usize,
    /// PCG iterations summed over all solves (for tests and benchmarks).
    pub total_iterations: usize,
    pub solves: usize,
}

impl BlockPcgSolver {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn with_params(params: BlockPcgParams) -> Self {
        BlockPcgSolver {
            params,
            ..Self::default()
        }
    }

    /// Numeric factorizations of the preconditioner so far.
    pub fn factorizations(&self) -> usize {
        self.precond.numeric_count
    }

    /// `y = A x` for one column of length `3 n` (parallel over block rows).
    pub fn mul_vec(&self, x: &[f64], y: &mut [f64]) {
        self.a.mul_vec_rows(&self.rows, x, y);
    }

    /// `z = M^-1 r` for `ncols` columns of length `3 n`.
    fn precondition(
        &mut self,
        r: &[f64],
        z: &mut [f64],
        ncols: usize,
        buf: &mut Vec<f64>,
    ) -> Result<(), SolverError> {
        let n = self.a.n;
        buf.resize(3 * n * ncols, 0.0);
        for c in 0..ncols {
            let rc = &r[3 * n * c..3 * n * (c + 1)];
            for d in 0..3 {
                let dst = &mut buf[n * (3 * c + d)..n * (3 * c + d + 1)];
                for v in 0..n {
                    dst[v] = rc[3 * v + d];
                }
            }
        }
        self.precond.solve_in_place(buf, 3 * ncols)?;
        for c in 0..ncols {
            let zc = &mut z[3 * n * c..3 * n * (c + 1)];
            for d in 0..3 {
                let src = &buf[n * (3 * c + d)..n * (3 * c + d + 1)];
                for v in 0..n {
                    zc[3 * v + d] = src[v];
                }
            }
        }
        Ok(())
    }

    fn same_pattern(&self, a: &BlockSym3) -> bool {
        self.a.n == a.n && self.a.col_ptr == a.col_ptr && self.a.row_idx == a.row_idx
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.par_iter().zip(b).map(|(x, y)| x * y).sum()
}

impl SpdSolver for BlockPcgSolver {
    fn prepare(&mut self, a: &SymCsc) -> Result<(), SolverError> {
        self.scalar_mode = true;
        self.precond.prepare(a)
    }

    fn prepare_blocks(&mut self, a: &BlockSym3, fixed: &[bool]) -> Result<(), SolverError> {
        a.check_fixed(fixed)?;
        let n = a.n;
        let mut refactor = self.scalar_mode
            || self.factored_trace == 0.0
            || self.last_iterations > self.params.refactor_iterations;
        self.scalar_mode = false;
        if !self.same_pattern(a) {
            refactor = true;
            self.a = a.clone();
            self.rows = a.row_index();
            self.k = SymCsc {
                n,
                col_ptr: a.col_ptr.clone(),
                row_idx: a.row_idx.clone(),
                values: vec![0.0; a.row_idx.len()],
            };
        } else {
            self.a.blocks.copy_from_slice(&a.blocks);
        }
        // Held vertices: identity diagonal block, no coupling (as BlockSym3::fill_scalar).
        let col_ptr = &self.a.col_ptr;
        let row_idx = &self.a.row_idx;
        let blocks = &mut self.a.blocks;
        let kv = &mut self.k.values;
        for j in 0..n {
            for k in col_ptr[j]..col_ptr[j + 1] {
                let i = row_idx[k];
                if fixed[i] || fixed[j] {
                    blocks[k] = if i == j {
                        [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
                    } else {
                        [0.0; 9]
                    };
                }
                let b = &blocks[k];
                kv[k] = (b[0] + b[4] + b[8]) / 3.0;
            }
        }
        let trace: f64 = (0..n).map(|j| kv[col_ptr[j]]).sum();
        if (trace - self.factored_trace).abs() > self.params.refactor_trace_change * trace.abs() {
            refactor = true;
        }
        if refactor || self.params.refactor_iterations == 0 {
            self.factored_trace = 0.0;
            self.precond.prepare(&self.k)?;
            self.factored_trace = trace;
        }
        Ok(())
    }

    fn solve_in_place(&mut self, rhs: &mut [f64], ncols: usize) -> Result<SolveInfo, SolverError> {
        if self.scalar_mode {
            return self.precond.solve_in_place(rhs, ncols);
        }
        let b = rhs.to_vec();
        rhs.iter_mut().for_each(|v| *v = 0.0);
        self.solve_with_guess(&b, rhs, ncols)
    }

    fn solve_with_guess(
        &mut self,
        b: &[f64],
        x: &mut [f64],
        ncols: usize,
    ) -> Result<SolveInfo, SolverError> {
        if self.scalar_mode {
            x.copy_from_slice(b);
            return self.precond.solve_in_place(x, ncols);
        }
        let m = 3 * self.a.n;
        if m == 0 {
            return Err(SolverError::NotPrepared);
        }
        if b.len() != m * ncols || x.len() != m * ncols {
            return Err(SolverError::DimensionMismatch(format!(
                "right-hand side has {} entries, guess {}, expected {m} x {ncols}",
                b.len(),
                x.len()
            )));
        }
        self.solves += 1;
        let tol = self.params.tolerance;
        let mut r = vec![0.0; m * ncols];
        for c in 0..ncols {
            let (xc, rc) = (&x[m * c..m * (c + 1)], &mut r[m * c..m * (c + 1)]);
            self.mul_vec(xc, rc);
            for (ri, bi) in rc.iter_mut().zip(&b[m * c..m * (c + 1)]) {
                *ri = bi - *ri;
            }
        }
        let bnorm: Vec<f64> = (0..ncols)
            .map(|c| dot(&b[m * c..m * (c + 1)], &b[m * c..m * (c + 1)]).sqrt())
            .collect();
        let mut active: Vec<bool> = (0..ncols).map(|c| bnorm[c] > 0.0).collect();
        for c in 0..ncols {
            if !active[c] {
                x[m * c..m * (c + 1)].iter_mut().for_each(|v| *v = 0.0);
            }
        }
        let mut z = vec![0.0; m * ncols];
        let mut buf = Vec::new();
        self.precondition(&r, &mut z, ncols, &mut buf)?;
        let mut p = z.clone();
        let mut rz: Vec<f64> = (0..ncols)
            .map(|c| dot(&r[m * c..m * (c + 1)], &z[m * c..m * (c + 1)]))
            .collect();
        let mut q = vec![0.0; m * ncols];
        let mut worst;
        let mut it = 0;
        let t_start = std::time::Instant::now();
        let mut t_precond = std::time::Duration::ZERO;
        loop {
            worst = 0.0f64;
            for c in 0..ncols {
                if !active[c] {
                    continue;
                }
                let rc = &r[m * c..m * (c + 1)];
                let rel = dot(rc, rc).sqrt() / bnorm[c];
                if !rel.is_finite() {
                    return Err(SolverError::NotPositiveDefinite);
                }
                if rel <= tol {
                    active[c] = false;
                }
                worst = worst.max(rel);
            }
            if !active.iter().any(|&a| a) {
                break;
            }
            if it >= self.params.max_iterations {
                self.total_iterations += it;
                return Err(SolverError::NoConvergence {
                    iterations: it,
                    residual: worst,
                });
            }
            for c in 0..ncols {
                if !active[c] {
                    continue;
                }
                let s = m * c..m * (c + 1);
                self.mul_vec(&p[s.clone()], &mut q[s.clone()]);
                let pq = dot(&p[s.clone()], &q[s.clone()]);
                if pq.is_nan() || pq <= 0.0 {
                    return Err(SolverError::NotPositiveDefinite);
                }
                let alpha = rz[c] / pq;
                x[s.clone()]
                    .par_iter_mut()
                    .zip(&p[s.clone()])
                    .for_each(|(xi, pi)| *xi += alpha * pi);
                r[s.clone()]
                    .par_iter_mut()
                    .zip(&q[s.clone()])
                    .for_each(|(ri, qi)| *ri -= alpha * qi);
            }
            let tp = std::time::Instant::now();
            self.precondition(&r, &mut z, ncols, &mut buf)?;
            t_precond += tp.elapsed();
            for c in 0..ncols {
                if !active[c] {
                    continue;
                }
                let s = m * c..m * (c + 1);
                let rz_new = dot(&r[s.clone()], &z[s.clone()]);
                let beta = rz_new / rz[c];
                rz[c] = rz_new;
                p[s.clone()]
                    .par_iter_mut()
                    .zip(&z[s.clone()])
                    .for_each(|(pi, zi)| *pi = zi + beta * *pi);
            }
            it += 1;
        }
        self.total_iterations += it;
        self.last_iterations = it;
        log::debug!(
            "block PCG: {ncols} column(s), {it} iterations, residual {worst:.2e}, {:.3} s ({:.3} s preconditioning)",
            t_start.elapsed().as_secs_f64(),
            t_precond.as_secs_f64()
        );
        Ok(SolveInfo {
            iterations: it,
            residual: worst,
        })
    }

    fn set_tolerance(&mut self, relative_residual: f64) {
        self.params.tolerance = relative_residual;
    }

    fn name(&self) -> &str {
        "cpu"
    }
}
