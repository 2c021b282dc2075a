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
//! The factor of `K` is stored in f32 by default (`single_precision_factor`):
//! half the memory and half the traffic per application, at the price of an
//! iteration or two; an f32 factorization that breaks down falls back to f64.
//! Scalar matrices (`prepare`) are solved directly by an f64 factor, or, with the
//! f32 factor, by the same PCG preconditioned with it.
//!
//! Held vertices (`fixed`) are identity rows with no coupling: `x_v = b_v`, and
//! the other rows see `x_v = 0`. The matrix itself is kept as handed over (the
//! masking happens in the products), so `prepare_blocks_owned` needs no copy.
//!
//! Every column stops when `||b - A x|| <= tolerance ||b||` (recurrence residual).

use crate::cholesky::{CholeskySolver, FillOrdering, PatternKey};
use crate::{
    BlockRows, BlockSym3, IsoRingSym3, SolveInfo, SolverError, SpdSolver, SymCsc, WorkCounters,
};
use rayon::prelude::*;

/// Settings of [`BlockPcgSolver`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlockPcgParams {
    /// Relative residual every column must reach.
    pub tolerance: f64,
    /// Iteration cap; reaching it is [`SolverError::NoConvergence`].
    pub max_iterations: usize,
    /// A new matrix of the same pattern keeps the previous preconditioner factor
    /// unless the iterations the last solve needed beyond those of the first
    /// solve after the factorization have cost more than a factorization, the
    /// last solve needed more than this many iterations, or the trace of `K`
    /// moved by more than `refactor_trace_change` (relative). 0 refactors every
    /// time.
    pub refactor_iterations: usize,
    pub refactor_trace_change: f64,
    /// Store the preconditioner factor in f32 (see module docs).
    pub single_precision_factor: bool,
}

impl Default for BlockPcgParams {
    fn default() -> Self {
        BlockPcgParams {
            tolerance: 1e-10,
            max_iterations: 2000,
            refactor_iterations: 12,
            refactor_trace_change: 0.05,
            single_precision_factor: false,
        }
    }
}

/// What the last `prepare` handed over.
#[derive(Default, Clone, Copy, PartialEq, Eq)]
enum Mode {
    #[default]
    None,
    Blocks,
    /// Shape matrix in isotropic-plus-ring form: its `K` is the preconditioner's
    /// matrix, factored in place (held rows masked for the factorization only).
    Iso,
    /// Scalar matrix solved directly by the (f64) factor.
    ScalarDirect,
    /// Scalar matrix solved by PCG with the (f32) factor.
    ScalarPcg,
}

/// Block-sparse PCG with the isotropic Cholesky preconditioner (see module docs).
#[derive(Default)]
pub struct BlockPcgSolver {
    pub params: BlockPcgParams,
    /// The prepared block matrix, as handed over.
    a: BlockSym3,
    /// Held vertices of the prepared block matrix.
    fixed: Vec<bool>,
    /// The prepared isotropic-plus-ring matrix, as handed over.
    iso: IsoRingSym3,
    /// Pattern of the last isotropic-plus-ring matrix (`rows` belongs to it).
    iso_key: Option<PatternKey>,
    /// Strictly lower blocks (or entries of `K`) by block row.
    rows: BlockRows,
    /// Isotropic part `K` (same pattern as the blocks), held rows identity.
    k: SymCsc,
    /// The prepared scalar matrix (scalar PCG mode).
    scalar: SymCsc,
    precond: CholeskySolver,
    mode: Mode,
    /// Trace of the `K` that was last factored (0: none factored).
    factored_trace: f64,
    /// Iterations of the last block solve (its slowest column).
    last_iterations: usize,
    /// Iterations of the first block solve after the last factorization.
    base_iterations: Option<usize>,
    /// Floating-point operations of the last factorization, and of one PCG
    /// iteration with it (the two triangular solves, 4 per factor entry, and
    /// about as much again for the operator): counted, not timed, so that the
    /// refactoring decisions, and the result, are the same on every run.
    factor_flops: f64,
    iteration_flops: f64,
    /// PCG iterations summed over all solves (for tests and benchmarks).
    pub total_iterations: usize,
    pub solves: usize,
    /// Solves and iterations for [`SpdSolver::counters`].
    work: WorkCounters,
}

impl BlockPcgSolver {
    pub fn new() -> Self {
        Self::with_params(BlockPcgParams::default())
    }

    pub fn with_params(params: BlockPcgParams) -> Self {
        BlockPcgSolver {
            params,
            precond: Self::factor_for(params.single_precision_factor),
            ..Self::default()
        }
    }

    fn factor_for(single: bool) -> CholeskySolver {
        if single {
            CholeskySolver::single_precision()
        } else {
            CholeskySolver::new()
        }
    }

    /// Symbolic analyses of the preconditioner's factor so far (made by this
    /// solver, or ahead and adopted).
    pub fn analyses(&self) -> usize {
        self.precond.symbolic_count
    }

    /// Numeric factorizations of the preconditioner so far.
    pub fn factorizations(&self) -> usize {
        self.precond.numeric_count
    }

    /// Bytes held by the preconditioner's numeric factor, and its entries.
    pub fn factor_size(&self) -> (usize, usize) {
        (self.precond.factor_bytes(), self.precond.factor_nnz())
    }

    /// `y = A x` for one column of length `3 n` (parallel over block rows), held
    /// rows identity and held columns ignored.
    pub fn mul_vec(&self, x: &[f64], y: &mut [f64]) {
        if self.fixed.iter().any(|&f| f) {
            let mut xm = x.to_vec();
            self.mask(&mut xm);
            self.product(&xm, y);
            for (v, &f) in self.fixed.iter().enumerate() {
                if f {
                    y[3 * v..3 * v + 3].copy_from_slice(&x[3 * v..3 * v + 3]);
                }
            }
        } else {
            self.product(x, y);
        }
    }

    /// Zero the held dofs of one column.
    fn mask(&self, x: &mut [f64]) {
        for (v, &f) in self.fixed.iter().enumerate() {
            if f {
                x[3 * v..3 * v + 3].fill(0.0);
            }
        }
    }

    /// Product inside the iteration: the direction is zero at held dofs, so the
    /// product only needs its held rows cleared.
    fn mul_direction(&self, p: &[f64], q: &mut [f64]) {
        match self.mode {
            Mode::Blocks | Mode::Iso => {
                self.product(p, q);
                self.mask(q);
            }
            _ => self.scalar.mul_vec(p, q),
        }
    }

    /// `z = M^-1 r` for `ncols` columns.
    fn precondition(
        &mut self,
        r: &[f64],
        z: &mut [f64],
        ncols: usize,
        buf: &mut Vec<f64>,
    ) -> Result<(), SolverError> {
        if self.mode == Mode::ScalarPcg {
            z.copy_from_slice(r);
            self.precond.solve_in_place(z, ncols)?;
            return Ok(());
        }
        let n = self.block_rows();
        // Column by column through `z`: r's x, y, z parts gathered into z's
        // column, solved in place as three scalar columns, then interleaved back
        // through `buf` (one column of scratch, not ncols).
        buf.resize(3 * n, 0.0);
        for c in 0..ncols {
            let rc = &r[3 * n * c..3 * n * (c + 1)];
            let zc = &mut z[3 * n * c..3 * n * (c + 1)];
            for d in 0..3 {
                let dst = &mut zc[n * d..n * (d + 1)];
                for v in 0..n {
                    dst[v] = rc[3 * v + d];
                }
            }
        }
        self.precond.solve_in_place(z, 3 * ncols)?;
        for c in 0..ncols {
            let zc = &mut z[3 * n * c..3 * n * (c + 1)];
            buf.copy_from_slice(zc);
            for d in 0..3 {
                let src = &buf[n * d..n * (d + 1)];
                for v in 0..n {
                    zc[3 * v + d] = src[v];
                }
            }
        }
        Ok(())
    }

    fn same_pattern(&self, a: &BlockSym3) -> bool {
        self.k.n == a.n && self.k.col_ptr == a.col_ptr && self.k.row_idx == a.row_idx
    }

    /// Factor `m` into the preconditioner; an f32 factorization that breaks down
    /// is retried in f64 (kept for the rest of the run).
    fn factor(&mut self, m: &SymCsc) -> Result<(), SolverError> {
        match self.precond.prepare(m) {
            Err(SolverError::NotPositiveDefinite) if self.precond.is_single_precision() => {
                log::info!("f32 preconditioner factor broke down; refactoring in f64");
                self.params.single_precision_factor = false;
                let ordering = self.precond.ordering.clone();
                self.precond = CholeskySolver::new();
                self.precond.ordering = ordering;
                self.precond.prepare(m)
            }
            r => r,
        }
    }

    /// Whether a new matrix (of mode `mode`) must be factored regardless of its
    /// trace: see [`BlockPcgParams::refactor_iterations`].
    fn refactor_due(&self, mode: Mode) -> bool {
        let extra =
            self.last_iterations - self.base_iterations.unwrap_or(0).min(self.last_iterations);
        self.mode != mode
            || self.factored_trace == 0.0
            || self.last_iterations > self.params.refactor_iterations
            || extra as f64 * self.iteration_flops > self.factor_flops
    }

    /// Factor the preconditioner if `refactor`, or if `trace` moved too far
    /// from the factored one.
    fn factor_if_due(&mut self, m: &SymCsc, trace: f64, refactor: bool) -> Result<(), SolverError> {
        let moved =
            (trace - self.factored_trace).abs() > self.params.refactor_trace_change * trace.abs();
        if refactor || moved || self.params.refactor_iterations == 0 {
            self.factored_trace = 0.0;
            self.factor(m)?;
            self.factor_flops = self.precond.factor_flops();
            self.iteration_flops = 8.0 * self.precond.factor_nnz() as f64;
            self.factored_trace = trace;
            self.base_iterations = None;
        }
        Ok(())
    }

    /// Store `a` (isotropic-plus-ring form); factor its `K` when due, with the
    /// held rows and columns made identity for the factorization only.
    fn take_iso(&mut self, a: IsoRingSym3, fixed: &[bool]) -> Result<(), SolverError> {
        let n = a.n();
        if fixed.len() != n {
            return Err(SolverError::DimensionMismatch(format!(
                "{} fixed flags for {n} block rows",
                fixed.len()
            )));
        }
        let mut refactor = self.refactor_due(Mode::Iso);
        self.mode = Mode::Iso;
        let key = PatternKey::of(&a.iso.col_ptr, &a.iso.row_idx);
        if self.iso_key != Some(key) {
            refactor = true;
            self.rows = a.row_index();
            self.iso_key = Some(key);
            self.a = BlockSym3::default();
            self.k = SymCsc::default();
        }
        self.iso = a;
        self.fixed.clear();
        self.fixed.extend_from_slice(fixed);
        let mut k = std::mem::take(&mut self.iso.iso);
        let mut saved = Vec::new();
        for (v, _) in fixed.iter().enumerate().filter(|(_, &f)| f) {
            for s in k.col_ptr[v]..k.col_ptr[v + 1] {
                saved.push((s, k.values[s]));
                k.values[s] = if k.row_idx[s] == v { 1.0 } else { 0.0 };
            }
            for &(s, _) in &self.rows.entries[self.rows.row_ptr[v]..self.rows.row_ptr[v + 1]] {
                saved.push((s as usize, k.values[s as usize]));
                k.values[s as usize] = 0.0;
            }
        }
        let trace: f64 = (0..n).map(|j| k.values[k.col_ptr[j]]).sum();
        let r = self.factor_if_due(&k, trace, refactor);
        // Last saved first: an entry saved twice gets its original value back.
        for (s, v) in saved.into_iter().rev() {
            k.values[s] = v;
        }
        self.iso.iso = k;
        r
    }

    /// Block rows of the prepared block or isotropic-plus-ring matrix.
    fn block_rows(&self) -> usize {
        match self.mode {
            Mode::Iso => self.iso.n(),
            _ => self.a.n,
        }
    }

    /// `y = A x` for the prepared block or isotropic-plus-ring matrix (unmasked).
    fn product(&self, x: &[f64], y: &mut [f64]) {
        match self.mode {
            Mode::Iso => self.iso.mul_vec_rows(&self.rows, x, y),
            _ => self.a.mul_vec_rows(&self.rows, x, y),
        }
    }

    /// Store `a` and its isotropic part; factor it when due.
    fn take_matrix(&mut self, a: BlockSym3, fixed: &[bool]) -> Result<(), SolverError> {
        a.check_fixed(fixed)?;
        let n = a.n;
        let mut refactor = self.refactor_due(Mode::Blocks);
        self.mode = Mode::Blocks;
        self.iso_key = None;
        self.iso = IsoRingSym3::default();
        if !self.same_pattern(&a) {
            refactor = true;
            self.rows = a.row_index();
            self.k = SymCsc {
                n,
                col_ptr: a.col_ptr.clone(),
                row_idx: a.row_idx.clone(),
                values: vec![0.0; a.row_idx.len()],
            };
        }
        self.a = a;
        self.fixed.clear();
        self.fixed.extend_from_slice(fixed);
        // Held vertices: identity diagonal, no coupling (as BlockSym3::fill_scalar).
        let (col_ptr, row_idx, blocks) = (&self.a.col_ptr, &self.a.row_idx, &self.a.blocks);
        let kv = &mut self.k.values;
        for j in 0..n {
            for k in col_ptr[j]..col_ptr[j + 1] {
                let i = row_idx[k];
                kv[k] = if fixed[i] || fixed[j] {
                    if i == j {
                        1.0
                    } else {
                        0.0
                    }
                } else {
                    let b = &blocks[k];
                    (b[0] + b[4] + b[8]) / 3.0
                };
            }
        }
        let trace: f64 = (0..n).map(|j| kv[col_ptr[j]]).sum();
        let k = std::mem::take(&mut self.k);
        let r = self.factor_if_due(&k, trace, refactor);
        self.k = k;
        r
    }
}

/// Elements per block of [`dot`].
const DOT_BLOCK: usize = 1 << 14;

/// `a . b`, the same to the last bit on every run: fixed blocks summed in
/// parallel, their sums added in order (rayon's own `sum` adds in the order
/// its work stealing happens to split, which varies from run to run).
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let partial: Vec<f64> = a
        .par_chunks(DOT_BLOCK)
        .zip(b.par_chunks(DOT_BLOCK))
        .map(|(x, y)| x.iter().zip(y).map(|(x, y)| x * y).sum::<f64>())
        .collect();
    partial.iter().sum()
}

impl SpdSolver for BlockPcgSolver {
    fn set_fill_ordering(&mut self, ordering: FillOrdering) {
        self.precond.set_fill_ordering(ordering);
    }

    fn isotropic_analyser(&self) -> Option<CholeskySolver> {
        self.precond
            .unanalysed_like(self.precond.is_single_precision())
    }

    fn adopt_isotropic_analysis(&mut self, analysed: CholeskySolver) {
        if self.precond.may_adopt(&analysed)
            && analysed.is_single_precision() == self.precond.is_single_precision()
        {
            self.precond = analysed;
        }
    }

    fn prepare(&mut self, a: &SymCsc) -> Result<(), SolverError> {
        self.factored_trace = 0.0;
        self.factor(a)?;
        if self.precond.is_single_precision() {
            self.mode = Mode::ScalarPcg;
            self.scalar = a.clone();
        } else {
            self.mode = Mode::ScalarDirect;
            self.scalar = SymCsc::default();
        }
        Ok(())
    }

    fn prepare_blocks(&mut self, a: &BlockSym3, fixed: &[bool]) -> Result<(), SolverError> {
        self.take_matrix(a.clone(), fixed)
    }

    fn prepare_blocks_owned(
        &mut self,
        a: BlockSym3,
        fixed: &[bool],
    ) -> Result<Option<BlockSym3>, SolverError> {
        self.take_matrix(a, fixed).map(|()| None)
    }

    fn blocks(&self) -> Option<&BlockSym3> {
        (self.mode == Mode::Blocks).then_some(&self.a)
    }

    fn take_blocks(&mut self) -> Option<BlockSym3> {
        (self.mode == Mode::Blocks && self.a.n > 0).then(|| std::mem::take(&mut self.a))
    }

    fn prepare_shape_owned(
        &mut self,
        a: IsoRingSym3,
        fixed: &[bool],
    ) -> Result<Option<IsoRingSym3>, SolverError> {
        self.take_iso(a, fixed).map(|()| None)
    }

    fn shape_matrix(&self) -> Option<&IsoRingSym3> {
        (self.mode == Mode::Iso).then_some(&self.iso)
    }

    fn take_shape_matrix(&mut self) -> Option<IsoRingSym3> {
        (self.mode == Mode::Iso && self.iso.n() > 0).then(|| std::mem::take(&mut self.iso))
    }

    fn solve_in_place(&mut self, rhs: &mut [f64], ncols: usize) -> Result<SolveInfo, SolverError> {
        if self.mode == Mode::ScalarDirect {
            self.work.solved(0);
            return self.precond.solve_in_place(rhs, ncols);
        }
        // Zero initial guess: the residual is the right-hand side itself, so it
        // is formed without keeping a copy of b (one column of 3n values less).
        self.run(None, rhs, ncols)
    }

    fn solve_with_guess(
        &mut self,
        b: &[f64],
        x: &mut [f64],
        ncols: usize,
    ) -> Result<SolveInfo, SolverError> {
        self.run(Some(b), x, ncols)
    }

    fn set_tolerance(&mut self, relative_residual: f64) {
        self.params.tolerance = relative_residual;
    }

    fn counters(&self) -> WorkCounters {
        WorkCounters {
            preconditioner_setups: self.precond.numeric_count,
            ..self.work
        }
    }

    fn name(&self) -> &str {
        "cpu"
    }
}

impl BlockPcgSolver {
    /// PCG from the guess in `x` for right-hand sides `b`; with `b = None`, `x`
    /// holds the right-hand sides on entry and the guess is zero.
    fn run(
        &mut self,
        b: Option<&[f64]>,
        x: &mut [f64],
        ncols: usize,
    ) -> Result<SolveInfo, SolverError> {
        let m = match self.mode {
            Mode::None => return Err(SolverError::NotPrepared),
            Mode::ScalarDirect => {
                if let Some(b) = b {
                    x.copy_from_slice(b);
                }
                return self.precond.solve_in_place(x, ncols);
            }
            Mode::ScalarPcg => self.scalar.n,
            Mode::Blocks | Mode::Iso => 3 * self.block_rows(),
        };
        if m == 0 {
            return Err(SolverError::NotPrepared);
        }
        let blen = b.map_or(x.len(), |b| b.len());
        if blen != m * ncols || x.len() != m * ncols {
            return Err(SolverError::DimensionMismatch(format!(
                "right-hand side has {blen} entries, guess {}, expected {m} x {ncols}",
                x.len()
            )));
        }
        self.solves += 1;
        let tol = self.params.tolerance;
        let blocks = matches!(self.mode, Mode::Blocks | Mode::Iso);
        let (mut r, bnorm) = match b {
            Some(b) => {
                let mut r = vec![0.0; m * ncols];
                for c in 0..ncols {
                    let s = m * c..m * (c + 1);
                    if blocks {
                        // Held dofs take their right-hand side; the rest see them as zero.
                        let (xc, bc) = (&mut x[s.clone()], &b[s.clone()]);
                        for (v, &f) in self.fixed.iter().enumerate() {
                            if f {
                                xc[3 * v..3 * v + 3].copy_from_slice(&bc[3 * v..3 * v + 3]);
                            }
                        }
                        self.mul_vec(xc, &mut r[s.clone()]);
                    } else {
                        self.scalar.mul_vec(&x[s.clone()], &mut r[s.clone()]);
                    }
                    for (ri, bi) in r[s.clone()].iter_mut().zip(&b[s]) {
                        *ri = bi - *ri;
                    }
                }
                let bnorm: Vec<f64> = (0..ncols)
                    .map(|c| dot(&b[m * c..m * (c + 1)], &b[m * c..m * (c + 1)]).sqrt())
                    .collect();
                (r, bnorm)
            }
            None => {
                // x = 0 but held dofs, which keep their right-hand side: r = b
                // with the held rows zero.
                let bnorm: Vec<f64> = (0..ncols)
                    .map(|c| dot(&x[m * c..m * (c + 1)], &x[m * c..m * (c + 1)]).sqrt())
                    .collect();
                let mut r = x.to_vec();
                for c in 0..ncols {
                    let (xc, rc) = (&mut x[m * c..m * (c + 1)], &mut r[m * c..m * (c + 1)]);
                    if blocks {
                        for (v, &f) in self.fixed.iter().enumerate() {
                            let d = 3 * v..3 * v + 3;
                            if f {
                                rc[d].fill(0.0);
                            } else {
                                xc[d].fill(0.0);
                            }
                        }
                    } else {
                        xc.fill(0.0);
                    }
                }
                (r, bnorm)
            }
        };
        let mut active: Vec<bool> = (0..ncols).map(|c| bnorm[c] > 0.0).collect();
        for c in 0..ncols {
            if !active[c] {
                x[m * c..m * (c + 1)].iter_mut().for_each(|v| *v = 0.0);
            }
        }
        // `z` (M^-1 r) and `q` (A p) share one buffer: q is used up by the x and
        // r updates before the next z is written, and z by p's update before
        // the next q.
        let mut zq = vec![0.0; m * ncols];
        let mut buf = Vec::new();
        self.precondition(&r, &mut zq, ncols, &mut buf)?;
        let mut p = zq.clone();
        let mut rz: Vec<f64> = (0..ncols)
            .map(|c| dot(&r[m * c..m * (c + 1)], &zq[m * c..m * (c + 1)]))
            .collect();
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
                let q = &mut zq[s.clone()];
                self.mul_direction(&p[s.clone()], q);
                let pq = dot(&p[s.clone()], q);
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
                    .zip(&zq[s.clone()])
                    .for_each(|(ri, qi)| *ri -= alpha * qi);
            }
            let tp = std::time::Instant::now();
            self.precondition(&r, &mut zq, ncols, &mut buf)?;
            t_precond += tp.elapsed();
            for c in 0..ncols {
                if !active[c] {
                    continue;
                }
                let s = m * c..m * (c + 1);
                let rz_new = dot(&r[s.clone()], &zq[s.clone()]);
                let beta = rz_new / rz[c];
                rz[c] = rz_new;
                p[s.clone()]
                    .par_iter_mut()
                    .zip(&zq[s.clone()])
                    .for_each(|(pi, zi)| *pi = zi + beta * *pi);
            }
            it += 1;
        }
        self.total_iterations += it;
        self.work.solved(it);
        if blocks {
            self.last_iterations = it;
            self.base_iterations.get_or_insert(it);
        }
        log::debug!(
            "{} PCG: {ncols} column(s), {it} iterations, residual {worst:.2e}, {:.3} s ({:.3} s preconditioning)",
            if blocks { "block" } else { "scalar" },
            t_start.elapsed().as_secs_f64(),
            t_precond.as_secs_f64()
        );
        Ok(SolveInfo {
            iterations: it,
            residual: worst,
        })
    }
}
