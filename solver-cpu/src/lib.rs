//! Sparse symmetric positive definite systems and the solver interface every
//! backend implements.
//!
//! The deformation pipeline solves `H Y = [b | L^T]` many times with few distinct
//! matrices `H` (paper Eqs. 7, 8 and 16-18): `prepare` once per matrix (the
//! symbolic analysis is kept while the sparsity pattern stays the same), then
//! `solve_in_place` for any number of right-hand sides.

pub mod block;
pub mod cholesky;
pub mod iso_ring;
pub mod ordering;
pub mod pcg;
mod symbolic;
pub mod tree_factor;

pub use block::{row_groups_mut, BlockRows, BlockSym3};
pub use cholesky::{
    analyse_beside, analyse_beside_then, background_pool, nested_dissection_of_pattern,
    thread_priority, AnalysisId, CholeskySolver, FactorAhead, FactorPlan, FillOrdering, PatternKey,
    SupernodalFactor, PATTERN_KEY_RUN,
};
pub use iso_ring::{sym3_block, IsoRingSym3, SparseRows, NO_TRIPLET};
pub use ordering::{coordinate_nested_dissection, coordinate_nested_dissection_of_pairs};
pub use pcg::{BlockPcgParams, BlockPcgSolver};

/// Failure of a linear solve.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SolverError {
    #[error("matrix is not positive definite")]
    NotPositiveDefinite,
    #[error("no convergence after {iterations} iterations (relative residual {residual:.3e})")]
    NoConvergence { iterations: usize, residual: f64 },
    #[error("dimension mismatch: {0}")]
    DimensionMismatch(String),
    #[error("out of memory")]
    OutOfMemory,
    #[error("solve called before prepare")]
    NotPrepared,
    #[error("{0}")]
    Backend(String),
}

/// What a solve did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SolveInfo {
    /// Iterations of an iterative method (0 for a direct factorization).
    pub iterations: usize,
    /// Largest relative residual `||A x - b|| / ||b||` over the columns, when known.
    pub residual: f64,
}

/// Which of a run's linear systems a solver is prepared for. A backend whose
/// preconditioner is costly to set up (the GPU's AMG) builds it once per kind
/// and keeps it while later matrices of the same kind and pattern only change
/// values; a new kind sets one up anew.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum SystemKind {
    /// The face system of the scale factors (Eq. 3).
    ScaleFactors,
    /// The shape systems of the scale-driven iteration (Eq. 7), new values
    /// every outer iteration.
    #[default]
    ScaleDriven,
    /// The fine-tune Hessian (Eq. 8), one matrix for the whole fine-tune.
    FineTune,
}

/// Running totals of a solver's work since it was made (the report's
/// `solver` section). Differences of two readings give one phase's share.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct WorkCounters {
    /// Preconditioner set-ups: numeric factorizations (CPU), AMG hierarchy
    /// builds (GPU).
    pub preconditioner_setups: usize,
    /// Of those set-ups, the ones that took a factor made ahead on another
    /// thread ([`FactorAhead`], [`SpdSolver::adopt_isotropic_factor`]).
    pub setups_from_factors_ahead: usize,
    /// Solve calls.
    pub solves: usize,
    /// Iterations summed over solves (0 for direct solves).
    pub iterations: usize,
    /// Most iterations of any one solve.
    pub iterations_max: usize,
    /// Seconds the host waited for the device (0 without one).
    pub device_seconds: f64,
    /// Times the host waited for the device.
    pub device_waits: usize,
    /// Times a thread working beside the caller (a factor's upload) waited
    /// for the device: not in `device_waits`, they hold up no solve.
    pub device_waits_beside: usize,
    /// Host seconds spent handing work to the device's queue (0 without
    /// one); on a CPU emulation of a GPU they include its running of the
    /// work.
    pub submit_seconds: f64,
    /// Bytes written from the host to the device.
    pub bytes_to_device: u64,
    /// Bytes read back from the device.
    pub bytes_from_device: u64,
    /// Kernel dispatches submitted to the device.
    pub device_dispatches: u64,
    /// Bytes the device's kernels read and write, modelled from what they
    /// access as stored (`solver_gpu::KernelWork`).
    pub device_bytes: u64,
    /// The least bytes of the operator applications among those kernels
    /// (each matrix in its least storage, its vectors once).
    pub device_bytes_minimal: u64,
    /// The chain of dependent steps through those kernels: each dispatch's
    /// longest loop of one invocation, summed (`solver_gpu::KernelWork`;
    /// counted for the Cholesky solves).
    pub device_serial_steps: u64,
    /// Compute passes timed on the device with timestamp queries (0 where
    /// the adapter has none) and the device seconds they took.
    pub device_timed_passes: u64,
    pub device_timed_seconds: f64,
    /// Compute pipelines compiled for the device where they were first
    /// needed, and the host seconds that took (a driver compiles each, from
    /// its shader cache where it has one).
    pub device_compiles: u64,
    pub device_compile_seconds: f64,
    /// Of the same, those compiled ahead of their use on another thread
    /// ([`SpdSolver::warm_up`]) and that thread's seconds.
    pub device_compiles_ahead: u64,
    pub device_compile_ahead_seconds: f64,
}

impl WorkCounters {
    /// Record one solve of `iterations` iterations.
    pub fn solved(&mut self, iterations: usize) {
        self.solves += 1;
        self.iterations += iterations;
        self.iterations_max = self.iterations_max.max(iterations);
    }

    /// `self - earlier` for the running totals; `iterations_max` is the
    /// later reading's (a maximum has no difference).
    pub fn since(&self, earlier: &WorkCounters) -> WorkCounters {
        WorkCounters {
            preconditioner_setups: self.preconditioner_setups - earlier.preconditioner_setups,
            setups_from_factors_ahead: self.setups_from_factors_ahead
                - earlier.setups_from_factors_ahead,
            solves: self.solves - earlier.solves,
            iterations: self.iterations - earlier.iterations,
            iterations_max: self.iterations_max,
            device_seconds: self.device_seconds - earlier.device_seconds,
            device_waits: self.device_waits - earlier.device_waits,
            device_waits_beside: self.device_waits_beside - earlier.device_waits_beside,
            submit_seconds: self.submit_seconds - earlier.submit_seconds,
            bytes_to_device: self.bytes_to_device - earlier.bytes_to_device,
            bytes_from_device: self.bytes_from_device - earlier.bytes_from_device,
            device_dispatches: self.device_dispatches - earlier.device_dispatches,
            device_bytes: self.device_bytes - earlier.device_bytes,
            device_bytes_minimal: self.device_bytes_minimal - earlier.device_bytes_minimal,
            device_serial_steps: self.device_serial_steps - earlier.device_serial_steps,
            device_timed_passes: self.device_timed_passes - earlier.device_timed_passes,
            device_timed_seconds: self.device_timed_seconds - earlier.device_timed_seconds,
            device_compiles: self.device_compiles - earlier.device_compiles,
            device_compile_seconds: self.device_compile_seconds - earlier.device_compile_seconds,
            device_compiles_ahead: self.device_compiles_ahead - earlier.device_compiles_ahead,
            device_compile_ahead_seconds: self.device_compile_ahead_seconds
                - earlier.device_compile_ahead_seconds,
        }
    }
}

/// Symmetric sparse matrix, lower triangle stored in compressed sparse columns
/// (row indices sorted within each column, `row >= col`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SymCsc {
    pub n: usize,
    pub col_ptr: Vec<usize>,
    pub row_idx: Vec<usize>,
    pub values: Vec<f64>,
}

impl SymCsc {
    /// Build the pattern from (row, col) pairs (either triangle); values start at zero.
    /// Each column's rows are its entries' and its diagonal, ascending, each
    /// once: counted into place (no vector per column: at 4.3M faces, the
    /// scale factors' 4.3M columns), each column sorted on rayon's threads.
    pub fn from_pattern(n: usize, entries: impl IntoIterator<Item = (usize, usize)>) -> SymCsc {
        use rayon::prelude::*;
        let lower: Vec<(usize, usize)> = entries
            .into_iter()
            .map(|(r, c)| if r >= c { (r, c) } else { (c, r) })
            .collect();
        // Every column holds its diagonal.
        let mut start = vec![1usize; n + 1];
        start[n] = 0;
        for &(_, c) in &lower {
            start[c] += 1;
        }
        let mut at = 0;
        for s in start.iter_mut() {
            let count = *s;
            *s = at;
            at += count;
        }
        let mut rows = vec![0usize; at];
        let mut next: Vec<usize> = start[..n].to_vec();
        for (c, slot) in next.iter_mut().enumerate() {
            rows[*slot] = c;
            *slot += 1;
        }
        for &(r, c) in &lower {
            rows[next[c]] = r;
            next[c] += 1;
        }
        drop((lower, next));
        // Each column sorted and its repeats dropped, in place: its length.
        let mut columns: Vec<&mut [usize]> = Vec::with_capacity(n);
        let mut rest = &mut rows[..];
        for c in 0..n {
            let (column, tail) = std::mem::take(&mut rest).split_at_mut(start[c + 1] - start[c]);
            columns.push(column);
            rest = tail;
        }
        let lens: Vec<usize> = columns
            .into_par_iter()
            .with_min_len(1024)
            .map(|column| {
                column.sort_unstable();
                let mut kept = 0;
                for i in 0..column.len() {
                    if i == 0 || column[i] != column[kept - 1] {
                        column[kept] = column[i];
                        kept += 1;
                    }
                }
                kept
            })
            .collect();
        let mut col_ptr = Vec::with_capacity(n + 1);
        col_ptr.push(0);
        let mut row_idx = Vec::with_capacity(lens.iter().sum());
        for (c, &len) in lens.iter().enumerate() {
            row_idx.extend_from_slice(&rows[start[c]..start[c] + len]);
            col_ptr.push(row_idx.len());
        }
        let nnz = row_idx.len();
        SymCsc {
            n,
            col_ptr,
            row_idx,
            values: vec![0.0; nnz],
        }
    }

    /// The rows and columns of the held unknowns (`fixed`) made identity.
    pub fn set_held_identity(&mut self, fixed: &[bool]) {
        if !fixed.iter().any(|&f| f) {
            return;
        }
        for j in 0..self.n {
            for s in self.col_ptr[j]..self.col_ptr[j + 1] {
                let i = self.row_idx[s];
                if fixed[i] || fixed[j] {
                    self.values[s] = if i == j { 1.0 } else { 0.0 };
                }
            }
        }
    }

    /// Position of entry (r, c) (either triangle) in `values`, if stored.
    #[inline]
    pub fn slot(&self, r: usize, c: usize) -> Option<usize> {
        let (r, c) = if r >= c { (r, c) } else { (c, r) };
        let s = self.col_ptr[c];
        let e = self.col_ptr[c + 1];
        self.row_idx[s..e].binary_search(&r).ok().map(|k| s + k)
    }

    /// y = A x for the full symmetric matrix.
    pub fn mul_vec(&self, x: &[f64], y: &mut [f64]) {
        y.iter_mut().for_each(|v| *v = 0.0);
        for c in 0..self.n {
            for k in self.col_ptr[c]..self.col_ptr[c + 1] {
                let r = self.row_idx[k];
                let v = self.values[k];
                y[r] += v * x[c];
                if r != c {
                    y[c] += v * x[r];
                }
            }
        }
    }

    pub fn nnz(&self) -> usize {
        self.row_idx.len()
    }
}

/// What a preconditioner may know of a shape matrix beyond its values: its
/// isotropic part `K` is close to `S Mt^-1 S + c S`, with `S` the input's
/// cotangent Laplacian (E_m's Hessian is `S diag(m) S`, `m_i = k_m / (2 A_i)`,
/// so `Mt = diag(2 A_i / k_m)`) and E_f's Hessian `c S` at the reference
/// positions (`c = 2 k_f / A`, `A` the input's area). The GPU backend builds
/// its shape preconditioner from it (`solver_gpu`, `Preconditioner::SquaredLaplacian`).
#[derive(Debug, Clone, PartialEq)]
pub struct ShapeOperatorModel {
    /// `S`: rows `S_i x = diag_i x_i - sum_j w_ij x_j`, symmetric.
    pub laplacian: std::sync::Arc<SparseRows>,
    /// The diagonal of `Mt` (0 for vertices outside every face).
    pub mt: Vec<f64>,
    /// `c`.
    pub c: f64,
}

impl ShapeOperatorModel {
    /// `1 / Mt_i`, E_m's weight `m_i` of vertex `i` in `S diag(m) S` (0
    /// where `Mt_i` is 0: a vertex outside every face).
    pub fn square_weight(&self, i: usize) -> f64 {
        let mt = self.mt[i];
        if mt > 0.0 {
            1.0 / mt
        } else {
            0.0
        }
    }
}

/// One constraint on the unknowns `s` of a power-sum Newton problem
/// ([`SpdSolver::power_sum_newton`]): `C(s) = sum_e c_e s_{f_e}^p / T - 1`,
/// `coeffs` the pairs `(f_e, c_e)` (each unknown at most once), `degree` p,
/// `target` T. The scale factors' constraints (paper Eqs. 9, 11, 13) have
/// this form, with p = 1, 2, 3 for lengths, areas and volumes.
#[derive(Debug, Clone, Copy)]
pub struct PowerSum<'a> {
    pub coeffs: &'a [(u32, f64)],
    pub degree: i32,
    pub target: f64,
}

/// The stopping rules of [`SpdSolver::power_sum_newton`]: at most
/// `max_steps` steps; done when every `|C_j(s)| < residual`, or once a step
/// moves no unknown by `moved` or more; each step's length is cut so that
/// every unknown stays at or above `floor` (less a tenth of the way there).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NewtonRules {
    pub max_steps: usize,
    pub residual: f64,
    pub moved: f64,
    pub floor: f64,
}

/// What [`SpdSolver::power_sum_newton`] did: the steps taken and the largest
/// `|C_j(s)|` at the `s` it returns.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct NewtonInfo {
    pub steps: usize,
    pub max_residual: f64,
}

/// A solver for symmetric positive definite systems: `prepare` once per matrix,
/// then solve many right-hand sides. Implemented by the CPU Cholesky reference
/// backend and by the GPU preconditioned-conjugate-gradient backend.
pub trait SpdSolver: Send {
    /// Factor (or upload) a scalar matrix. The symbolic analysis is reused while
    /// the sparsity pattern is unchanged.
    fn prepare(&mut self, a: &SymCsc) -> Result<(), SolverError>;
    /// Factor (or upload) a 3x3-block matrix. Vertices with `fixed[v]` are held:
    /// their rows and columns become the identity (zero increment for a zero
    /// right-hand side there).
    fn prepare_blocks(&mut self, a: &BlockSym3, fixed: &[bool]) -> Result<(), SolverError>;
    /// As `prepare_blocks`, for a matrix the caller hands over. A solver that
    /// needs the matrix during its solves keeps it instead of copying it (read
    /// it with `blocks`, take it back with `take_blocks`); others hand it back.
    fn prepare_blocks_owned(
        &mut self,
        a: BlockSym3,
        fixed: &[bool],
    ) -> Result<Option<BlockSym3>, SolverError> {
        self.prepare_blocks(&a, fixed).map(|()| Some(a))
    }
    /// The matrix kept by `prepare_blocks_owned`, as it was handed over.
    fn blocks(&self) -> Option<&BlockSym3> {
        None
    }
    /// Takes back the matrix kept by `prepare_blocks_owned`.
    fn take_blocks(&mut self) -> Option<BlockSym3> {
        None
    }
    /// As `prepare_blocks_owned`, for a shape matrix in isotropic-plus-ring form.
    /// Solvers that work on that form keep it (read it with `shape_matrix`, take it
    /// back with `take_shape_matrix`); the others get its explicit blocks and hand
    /// it back.
    fn prepare_shape_owned(
        &mut self,
        a: IsoRingSym3,
        fixed: &[bool],
    ) -> Result<Option<IsoRingSym3>, SolverError> {
        self.prepare_blocks(&a.to_blocks(), fixed).map(|()| Some(a))
    }
    /// The pattern of the shape matrices to come, before the first of them:
    /// `a`'s pattern of `K`, its rings (and their slots where it names
    /// them) and the held vertices `fixed`; `a`'s values are not read. A
    /// solver may set up meanwhile what depends on them alone (the GPU
    /// backend: its device's buffers, on a thread of its own), for the
    /// first [`Self::prepare_shape_owned`] of that pattern to take up.
    /// Default: nothing.
    fn prepare_shape_pattern(&mut self, _a: &IsoRingSym3, _fixed: &[bool]) {}
    /// Whether the next shape matrix must carry its whole isotropic part in
    /// `K` (default: always). A backend whose preconditioner of the current
    /// system kind is made (from an earlier matrix's `K`) and never reads `K`
    /// again says no: the assembly may then put an isotropic term of ring
    /// form, `R_i^T (a_i I3) R_i`, into `C_i` instead (the same matrix,
    /// without scattering `a_i R_ip R_iq` into `K`'s slots).
    fn wants_isotropic_part(&self) -> bool {
        true
    }
    /// Whether the next shape matrix may leave E_m's Hessian out of `K` and
    /// name it instead ([`IsoRingSym3::laplacian_square`]: `S Mt^-1 S (x)
    /// I3` of a [`ShapeOperatorModel`]), for the solver to add it itself
    /// (default: never). A backend says yes where it keeps that constant
    /// term's values apart from the host (made once per model, added to
    /// every later matrix of it), and never while it wants `K`'s whole
    /// isotropic part ([`Self::wants_isotropic_part`]).
    fn adds_laplacian_square(&self) -> bool {
        false
    }
    /// The matrix kept by `prepare_shape_owned`.
    fn shape_matrix(&self) -> Option<&IsoRingSym3> {
        None
    }
    /// Takes back the matrix kept by `prepare_shape_owned`.
    fn take_shape_matrix(&mut self) -> Option<IsoRingSym3> {
        None
    }
    /// Solve `A X = B` in place; `rhs` holds `ncols` columns of length `n`, column-major.
    fn solve_in_place(&mut self, rhs: &mut [f64], ncols: usize) -> Result<SolveInfo, SolverError>;
    /// Solve `A X = B` with `x` holding an initial guess on entry (iterative
    /// backends warm-start from it; direct ones ignore it).
    fn solve_with_guess(
        &mut self,
        b: &[f64],
        x: &mut [f64],
        ncols: usize,
    ) -> Result<SolveInfo, SolverError> {
        x.copy_from_slice(b);
        self.solve_in_place(x, ncols)
    }
    /// Relative residual `||A x - b|| / ||b||` an iterative backend must reach
    /// (ignored by direct solvers).
    fn set_tolerance(&mut self, _relative_residual: f64) {}
    /// Positions of the vertices behind the block rows of the next block
    /// matrices (empty: none), for iterative backends whose preconditioner
    /// builds on them (the GPU's AMG: the affine motions as near-null space);
    /// ignored by the others.
    fn set_vertex_positions(&mut self, _positions: &[[f64; 3]]) {}
    /// Whether the next block matrix's preparation may read the positions
    /// of [`SpdSolver::set_vertex_positions`] (default: never), so that a
    /// caller makes them only then.
    fn wants_vertex_positions(&self) -> bool {
        false
    }
    /// Fill-reducing ordering of the next symbolic analysis, for backends that
    /// factor (of the scalar unknowns, or of the block rows of a block matrix);
    /// ignored by the others.
    fn set_fill_ordering(&mut self, _ordering: FillOrdering) {}
    /// Whether a large factor of this solver's is worth a METIS
    /// nested-dissection ordering (the default: the least fill, so the least
    /// bytes per solve), or only an ordering made in a fraction of its time
    /// for more fill (the nested dissection of the unknowns' positions,
    /// [`coordinate_nested_dissection`], where the caller has them): where
    /// the solves stream the factor at a GPU's bandwidth, METIS's seconds
    /// cost more than the fill.
    fn wants_nested_dissection(&self) -> bool {
        true
    }
    /// A solver of this backend for another system of the same run (the
    /// scale factors' beside the shape systems'), sharing what this one has
    /// opened: on a GPU its device, not a second one with its own driver
    /// memory. `None` (the default) where there is nothing to share.
    fn sibling(&self) -> Option<Result<Box<dyn SpdSolver>, SolverError>> {
        None
    }
    /// A Cholesky solver set up as this one's factor of the shape matrices'
    /// isotropic part `K` will be (fill ordering, precision), for that
    /// factor's symbolic analysis to run ahead, on another thread, while the
    /// scale factors are set up; `None` (the default) where this solver makes
    /// no such factor or has analysed one already. The solver comes back,
    /// analysed, through [`SpdSolver::adopt_isotropic_analysis`].
    fn isotropic_analyser(&self) -> Option<CholeskySolver> {
        None
    }
    /// Take over `analysed`, made by [`SpdSolver::isotropic_analyser`], that
    /// has analysed the pattern of `K`: the first shape matrix's
    /// factorization then skips its symbolic analysis. Ignored (the
    /// default) where it does not fit.
    fn adopt_isotropic_analysis(&mut self, _analysed: CholeskySolver) {}
    /// A Cholesky solver that shares this one's symbolic analysis of `K`
    /// and factors in the precision of `kind`'s factor: for that kind's
    /// numeric factorization to run ahead, on another thread
    /// ([`FactorAhead`]), from a `K` the caller assembles (held rows and
    /// columns identity, as [`IsoRingSym3::iso_held_identity`]); `None` (the
    /// default) where this solver makes no such factor for `kind` or has not
    /// analysed `K` yet. The factor comes back through
    /// [`SpdSolver::adopt_isotropic_factor`].
    fn isotropic_factorer(&self, _kind: SystemKind) -> Option<CholeskySolver> {
        None
    }
    /// How this solver would make `kind`'s factor of `K` ahead, before its
    /// symbolic analysis exists (for numeric factorizations started on the
    /// analysing thread as soon as the analysis is made): `None` (the
    /// default) where it makes no such factor for `kind`.
    fn isotropic_factor_plan(&self, _kind: SystemKind) -> Option<FactorPlan> {
        None
    }
    /// Take `factored`, made from [`SpdSolver::isotropic_factorer`]'s solver
    /// or on its own analysis of the same pattern
    /// ([`FactorAhead::spawn_analysing`] with [`SpdSolver::isotropic_factor_plan`]),
    /// as `kind`'s preconditioner: that kind's set-up then uploads or uses it
    /// instead of factoring its first matrix's `K` (a preconditioner: made
    /// from another matrix of the kind, it changes the iterations, not the
    /// solution's tolerance). Ignored (the default) where it does not fit.
    fn adopt_isotropic_factor(&mut self, _kind: SystemKind, _factored: CholeskySolver) {}
    /// Whether this solver makes `kind`'s factor of `K` (the scale
    /// factors': of their matrix) on its device from its values
    /// ([`SpdSolver::factor_isotropic_on_device`]); `false` (the default)
    /// where it makes it on the host or makes none.
    fn factors_isotropic_on_device(&self, _kind: SystemKind) -> bool {
        false
    }
    /// Starts `kind`'s factor of `k` (a `K` of the kind, or the scale
    /// factors' matrix, of the analysed pattern) on the device and returns
    /// at once, for that kind's set-up to take instead of factoring its
    /// first matrix (as [`SpdSolver::adopt_isotropic_factor`]'s): in
    /// `slices` submissions (1: at once), the first now, the next by
    /// [`SpdSolver::advance_factor_on_device`], the rest by the set-up.
    /// Ignored (the default) where it does not apply.
    fn factor_isotropic_on_device(&mut self, _kind: SystemKind, _k: &SymCsc, _slices: usize) {}
    /// Prepares [`SpdSolver::factor_isotropic_on_device`] of `kind` and
    /// `k`'s pattern now (on a GPU, the factorization's recording), so that
    /// that call only submits it: called where the host would otherwise
    /// wait. Ignored (the default) where it does not apply.
    fn prepare_factor_on_device(&mut self, _kind: SystemKind, _k: &SymCsc) {}
    /// The next slice of a factor [`SpdSolver::factor_isotropic_on_device`]
    /// submitted in slices (one for a set-up several solves away), where
    /// one is left: called where the device would otherwise idle while the
    /// host works. Whether a slice was submitted (`false`, the default:
    /// none was left, or none applies).
    fn advance_factor_on_device(&mut self) -> bool {
        false
    }
    /// Waits until the device has done the work given to it (by this
    /// solver and the solvers on its device): between the slices of a
    /// factor ([`SpdSolver::advance_factor_on_device`]) where another
    /// thread's work may come, so that it waits for one slice at most.
    /// Nothing (the default) where there is no device.
    fn wait_for_device(&mut self) {}
    /// The model of the next shape matrices (`None`: no model), for backends
    /// whose preconditioner builds on it; ignored by the others.
    fn set_shape_model(&mut self, _model: Option<std::sync::Arc<ShapeOperatorModel>>) {}
    /// The kind of system the next `prepare*` calls bring (default
    /// [`SystemKind::ScaleDriven`]); see [`SystemKind`].
    fn set_system_kind(&mut self, _kind: SystemKind) {}

    /// Starts making, on another thread, what solves of `kind` with these
    /// column counts will need and can be made before their matrices exist:
    /// a GPU's compute pipelines. A no-op for the host's solvers.
    fn warm_up(&mut self, _kind: SystemKind, _columns: &[usize]) {}
    /// Minimise `(s - 1)^T A (s - 1)`, `A` the prepared scalar matrix,
    /// subject to `C_j(s) = 0` for the `constraints`, by sequential linearly
    /// constrained Newton steps from `s = 1` (paper Sec. 4, Eqs. 15-18,
    /// with one multiplier per constraint), all on the solver's device:
    /// `s` receives the result. `None` (the default) where the solver does
    /// not run them itself (the caller then takes the steps through
    /// [`Self::solve_with_guess`]).
    fn power_sum_newton(
        &mut self,
        _constraints: &[PowerSum],
        _rules: &NewtonRules,
        _s: &mut [f64],
    ) -> Option<Result<NewtonInfo, SolverError>> {
        None
    }
    /// Running totals of the work done so far.
    fn counters(&self) -> WorkCounters;
    /// Short name for reports ("cpu", "gpu").
    fn name(&self) -> &str;
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The pattern counted into place is the one of a sorted vector per
    /// column: entries in both triangles, repeated, on the diagonal, and
    /// columns with none but their diagonal.
    #[test]
    fn the_pattern_is_each_columns_sorted_rows() {
        let n = 5000;
        let mut entries: Vec<(usize, usize)> = (0..40_000)
            .map(|i| ((i * 7919) % n, (i * 104_729 + i / 3) % n))
            .filter(|&(r, c)| r % 97 != 13 && c % 97 != 13)
            .collect();
        entries.extend([(3, 3), (7, 2), (2, 7), (7, 2)]);
        let mut cols: Vec<Vec<usize>> = vec![Vec::new(); n];
        for &(r, c) in &entries {
            let (r, c) = if r >= c { (r, c) } else { (c, r) };
            cols[c].push(r);
        }
        let (mut col_ptr, mut row_idx) = (vec![0], Vec::new());
        for (c, mut rows) in cols.into_iter().enumerate() {
            rows.push(c);
            rows.sort_unstable();
            rows.dedup();
            row_idx.extend(rows);
            col_ptr.push(row_idx.len());
        }
        let a = SymCsc::from_pattern(n, entries);
        assert_eq!(a.col_ptr, col_ptr);
        assert_eq!(a.row_idx, row_idx);
        assert_eq!(a.values, vec![0.0; row_idx.len()]);
        assert_eq!(
            a.col_ptr[14] - a.col_ptr[13],
            1,
            "column 13: its diagonal alone"
        );
        let empty = SymCsc::from_pattern(0, std::iter::empty());
        assert_eq!((empty.col_ptr, empty.row_idx), (vec![0], vec![]));
    }

    /// A random-ish SPD block matrix: Laplacian of a path plus a diagonal shift.
    /// [`spd`]'s scalar part (no held rows).
    fn spd_scalar(n: usize) -> SymCsc {
        let a = spd(n);
        let mut s = a.scalar_pattern();
        a.fill_scalar(&mut s, &vec![false; n]);
        s
    }

    fn spd(n: usize) -> BlockSym3 {
        let mut a = BlockSym3::from_pattern(n, (1..n).map(|i| (i, i - 1)));
        for i in 1..n {
            let w = 1.0 + (i as f64 * 0.37).sin().abs();
            a.add_scalar(i, i, w);
            a.add_scalar(i - 1, i - 1, w);
            a.add_scalar(i, i - 1, -w);
            let m = [0.1, 0.02 * i as f64, 0.0, 0.0, 0.3, 0.05, 0.01, 0.0, 0.2];
            a.add_block(i, i - 1, &m);
            a.add_block(i, i, &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
        }
        a.add_block(0, 0, &[2.0, 0.5, 0.0, 0.5, 2.0, 0.0, 0.0, 0.0, 2.0]);
        a
    }

    /// The supernodal layout handed to the GPU solves as the factor does:
    /// a grid Laplacian's simplicial and supernodal factors (AMD and nested
    /// dissection), and a single unknown.
    #[test]
    fn supernodal_factor_solves_as_the_factor() {
        let grid = |w: usize| {
            let n = w * w;
            let mut e = Vec::new();
            for i in 0..w {
                for j in 0..w {
                    let v = i * w + j;
                    e.push((v, v));
                    if j + 1 < w {
                        e.push((v + 1, v));
                    }
                    if i + 1 < w {
                        e.push((v + w, v));
                    }
                }
            }
            let mut a = SymCsc::from_pattern(n, e);
            for j in 0..n {
                for s in a.col_ptr[j]..a.col_ptr[j + 1] {
                    a.values[s] = if a.row_idx[s] == j {
                        4.1 + (j as f64).sin().abs()
                    } else {
                        -1.0
                    };
                }
            }
            a
        };
        let b_of = |n: usize| -> Vec<f64> { (0..n).map(|i| (i as f64 * 0.7).cos()).collect() };
        for (w, ordering, supernodal, single) in [
            (1, FillOrdering::Amd, false, true),
            (30, FillOrdering::Amd, false, true),
            (30, FillOrdering::NestedDissection, true, true),
            (30, FillOrdering::Amd, true, true),
            (30, FillOrdering::NestedDissection, true, false),
        ] {
            let a = grid(w);
            let mut solver = if single {
                CholeskySolver::single_precision()
            } else {
                CholeskySolver::new()
            };
            solver.supernodal = supernodal;
            solver.set_fill_ordering(ordering.clone());
            solver.prepare(&a).unwrap();
            let mut y = b_of(a.n);
            solver.solve_in_place(&mut y, 1).unwrap();
            let f = solver.take_supernodal_factor().unwrap();
            let slots = solver.factor_slots();
            assert_eq!(f.nnz(), solver.factor_nnz());
            assert_eq!(f.rows.len(), slots);
            assert_eq!(f.values64.is_empty(), single);
            assert_eq!(f.val_ptr.last().copied(), Some(f.nnz() as u64));
            let largest = f.val_ptr.windows(2).map(|w| w[1] - w[0]).max();
            assert_eq!(largest, Some(solver.largest_supernode_nnz() as u64));
            if supernodal {
                assert!(
                    (0..f.len()).any(|s| f.shape(s).0 > 1),
                    "{ordering:?}: no supernode"
                );
            }
            for s in 0..f.len() {
                let rows = &f.rows[f.row_ptr[s] as usize..f.row_ptr[s + 1] as usize];
                assert!(
                    rows.iter().all(|&r| r >= f.begin[s + 1]),
                    "{w} {ordering:?} {s}"
                );
            }
            let b = b_of(a.n);
            let x = f.solve(&b);
            // Taken out: the solver refactors into new storage.
            assert!(solver.solve_in_place(&mut b_of(a.n), 1).is_err());
            solver.prepare(&a).unwrap();
            let mut y2 = b_of(a.n);
            solver.solve_in_place(&mut y2, 1).unwrap();
            assert_eq!(y, y2);
            let scale = y.iter().fold(0f64, |m, v| m.max(v.abs()));
            for i in 0..a.n {
                assert!(
                    (x[i] - y[i]).abs() <= if single { 1e-5 } else { 1e-12 } * scale,
                    "{w} {ordering:?} {i}: {} {}",
                    x[i],
                    y[i]
                );
            }
            // With inverted diagonal blocks, the same solve.
            let mut fi = f.clone();
            fi.invert_diagonal_blocks();
            let xi = fi.solve(&b);
            for i in 0..a.n {
                assert!(
                    (xi[i] - x[i]).abs() <= if single { 1e-4 } else { 1e-10 } * scale,
                    "{w} {ordering:?} {i}: inverted blocks"
                );
            }
            // And it inverts A itself (to the f32 factor's accuracy).
            let mut ax = vec![0.0; a.n];
            a.mul_vec(&x, &mut ax);
            for i in 0..a.n {
                assert!((ax[i] - b[i]).abs() < 1e-4, "{w} {ordering:?} {i}");
            }
        }
    }

    /// The key tells apart patterns that differ in one entry, or in the
    /// order of two, and is the same for equal patterns.
    #[test]
    fn a_pattern_key_changes_with_any_entry() {
        let a = grid_laplacian(7, 1.0);
        let key = PatternKey::of(&a.col_ptr, &a.row_idx);
        assert_eq!(key, PatternKey::of(&a.col_ptr.clone(), &a.row_idx.clone()));
        for i in 0..a.row_idx.len() {
            let mut rows = a.row_idx.clone();
            rows[i] += 1;
            assert_ne!(key, PatternKey::of(&a.col_ptr, &rows), "row entry {i}");
            if i + 1 < rows.len() && a.row_idx[i] != a.row_idx[i + 1] {
                let mut swapped = a.row_idx.clone();
                swapped.swap(i, i + 1);
                assert_ne!(
                    key,
                    PatternKey::of(&a.col_ptr, &swapped),
                    "entries {i} and {}",
                    i + 1
                );
            }
        }
        for i in 1..a.col_ptr.len() - 1 {
            let mut cols = a.col_ptr.clone();
            cols[i] -= 1;
            assert_ne!(key, PatternKey::of(&cols, &a.row_idx), "column pointer {i}");
        }
    }

    /// Over several runs of the hash: the same key on one thread and on
    /// four, and another where one word changes in any run, or two words
    /// across a run's end trade places.
    #[test]
    fn a_pattern_key_of_several_runs_is_the_same_on_any_number_of_threads() {
        let col_ptr: Vec<usize> = (0..PATTERN_KEY_RUN + 10).map(|i| 3 * i).collect();
        let row_idx: Vec<usize> = (0..2 * PATTERN_KEY_RUN + 7)
            .map(|i| i / 3 + i % 3)
            .collect();
        let on = |threads: usize, rows: &[usize]| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| PatternKey::of(&col_ptr, rows))
        };
        let key = on(1, &row_idx);
        assert_eq!(key, on(4, &row_idx));
        for i in [
            0,
            PATTERN_KEY_RUN - 1,
            PATTERN_KEY_RUN,
            2 * PATTERN_KEY_RUN + 6,
        ] {
            let mut rows = row_idx.clone();
            rows[i] += 1;
            assert_ne!(key, on(4, &rows), "row entry {i}");
        }
        let mut swapped = row_idx.clone();
        swapped.swap(PATTERN_KEY_RUN - 1, PATTERN_KEY_RUN);
        assert_ne!(swapped, row_idx);
        assert_ne!(key, on(4, &swapped), "across a run's end");
        let mut cols = col_ptr.clone();
        cols[PATTERN_KEY_RUN + 5] += 1;
        assert_ne!(key, PatternKey::of(&cols, &row_idx), "a column pointer");
    }

    #[test]
    fn given_fill_ordering_is_used_once_then_released() {
        let n = 50;
        let a = spd(n);
        let fixed = vec![false; n];
        let x: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.3).sin() + 0.5).collect();
        let mut b = vec![0.0; 3 * n];
        a.mul_vec(&x, &mut b);
        let solve_with = |order: Vec<usize>| -> (usize, FillOrdering) {
            let mut solver = CholeskySolver::new();
            solver.set_fill_ordering(FillOrdering::Given(order.into()));
            solver.prepare_blocks(&a, &fixed).unwrap();
            let mut y = b.clone();
            solver.solve_in_place(&mut y, 1).unwrap();
            for i in 0..3 * n {
                assert!((y[i] - x[i]).abs() < 1e-9, "{i}");
            }
            (solver.factor_nnz(), solver.ordering.clone())
        };
        // A path of blocks: its own order fills nothing; eliminating every other
        // vertex first joins their neighbours.
        let (natural, after) = solve_with((0..n).collect());
        assert_eq!(after, FillOrdering::Auto, "the given ordering is released");
        let odd_first: Vec<usize> = (1..n).step_by(2).chain((0..n).step_by(2)).collect();
        let (odd, _) = solve_with(odd_first);
        assert!(
            odd > natural,
            "the given ordering was applied ({odd} vs {natural})"
        );
        // Not a permutation of the block rows: ignored, the solve still right.
        let (_, after) = solve_with(vec![0, 0, 1]);
        assert_eq!(after, FillOrdering::Auto);
    }

    #[test]
    fn cholesky_solves_and_reuses_symbolic() {
        let n = 50;
        let a = spd(n);
        let mut s = a.scalar_pattern();
        let fixed = vec![false; n];
        a.fill_scalar(&mut s, &fixed);
        let mut solver = CholeskySolver::new();
        solver.prepare(&s).unwrap();
        let x: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.7).cos()).collect();
        let mut b = vec![0.0; 3 * n];
        s.mul_vec(&x, &mut b);
        let mut b2 = vec![0.0; 3 * n];
        a.mul_vec(&x, &mut b2);
        for i in 0..3 * n {
            assert!(
                (b[i] - b2[i]).abs() < 1e-12,
                "block and scalar products differ"
            );
        }
        let mut rhs = b.clone();
        rhs.extend_from_slice(&b);
        solver.solve_in_place(&mut rhs, 2).unwrap();
        for i in 0..3 * n {
            assert!((rhs[i] - x[i]).abs() < 1e-9);
            assert!((rhs[3 * n + i] - x[i]).abs() < 1e-9);
        }
        // New values, same pattern: symbolic analysis reused.
        let mut s2 = s.clone();
        s2.values.iter_mut().for_each(|v| *v *= 2.0);
        solver.prepare(&s2).unwrap();
        assert_eq!(solver.symbolic_count, 1);
        assert_eq!(solver.numeric_count, 2);
    }

    /// The background pool's threads run nicer than the thread that asks
    /// (where the OS has per-thread priorities), and work installed in it
    /// runs on them.
    #[test]
    fn background_threads_are_nicer() {
        let pool = background_pool().expect("a background pool");
        let name = pool.install(|| std::thread::current().name().map(String::from));
        assert!(
            name.as_deref()
                .is_some_and(|n| n.starts_with("background-")),
            "{name:?}"
        );
        if let Some(caller) = thread_priority() {
            let background = pool.install(thread_priority).unwrap();
            assert!(
                background > caller || background == 19,
                "background {background}, caller {caller}"
            );
        }
    }

    /// A numeric twin factors on its solver's analysis (no analysis of its
    /// own, on another thread) what that solver would: the same solve to
    /// the bit. It is a factor of its pattern on that analysis only.
    #[test]
    fn a_numeric_twin_factors_on_the_shared_analysis() {
        let n = 50;
        let s = spd_scalar(n);
        let mut solver = CholeskySolver::new();
        assert!(solver.numeric_twin(false).is_none(), "nothing analysed");
        solver.analyse(&s).unwrap();
        let mut s2 = s.clone();
        s2.values.iter_mut().for_each(|v| *v *= 2.0);
        let twin = solver.numeric_twin(false).unwrap();
        let (twin, _) = FactorAhead::spawn(twin, s2.clone()).unwrap().join();
        let mut twin = twin.unwrap();
        // In the background pool: the same factor.
        let (background, _) =
            FactorAhead::spawn_in_background(solver.numeric_twin(false).unwrap(), s2.clone())
                .unwrap()
                .join();
        let mut background = background.unwrap();
        assert_eq!((twin.symbolic_count, twin.numeric_count), (0, 1));
        assert!(twin.is_factored_on(&solver));
        assert!(!twin.is_factored_on(&CholeskySolver::new()));
        assert!(!solver.is_factored_on(&solver), "analysed, not factored");
        let mut other = s.clone();
        other.row_idx.pop();
        other.values.pop();
        *other.col_ptr.last_mut().unwrap() -= 1;
        let analysed = |c: &CholeskySolver, a: &SymCsc| c.has_analysed(&a.col_ptr, &a.row_idx);
        assert!(analysed(&solver, &s2) && analysed(&twin, &s2));
        assert!(!analysed(&solver, &other), "another pattern");
        solver.prepare(&s2).unwrap();
        let b: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.3).sin()).collect();
        let (mut x, mut y) = (b.clone(), b.clone());
        let mut z = b.clone();
        solver.solve_in_place(&mut x, 1).unwrap();
        twin.solve_in_place(&mut y, 1).unwrap();
        background.solve_in_place(&mut z, 1).unwrap();
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&x), bits(&y));
        assert_eq!(bits(&x), bits(&z));
        assert_eq!(solver.symbolic_count, 1);
    }

    /// A factor made on its own analysis in another ordering
    /// ([`FactorAhead::spawn_analysing`]) is a factor of the pattern another
    /// solver analysed, though not on that analysis, and solves as that
    /// solver's own factor does (to rounding); a plan its largest supernode
    /// does not fit refuses it.
    #[test]
    fn a_factor_on_its_own_analysis_is_of_the_analysed_pattern() {
        let n = 50;
        let s = spd_scalar(n);
        let mut solver = CholeskySolver::new();
        solver.analyse(&s).unwrap();
        let reversed: std::sync::Arc<[usize]> = (0..s.n).rev().collect();
        let plan = |bytes| FactorPlan {
            single: false,
            largest_supernode_bytes: bytes,
            inverted: false,
        };
        let spawn = |bytes| {
            let ordering = FillOrdering::Given(reversed.clone());
            FactorAhead::spawn_analysing(plan(bytes), move || ordering, s.clone())
                .unwrap()
                .join()
                .0
        };
        let mut own = spawn(u64::MAX).unwrap();
        assert_eq!((own.symbolic_count, own.numeric_count), (1, 1));
        assert!(own.is_factored_of_pattern_of(&solver));
        assert!(!own.is_factored_on(&solver), "its own analysis");
        assert!(!solver.is_factored_of_pattern_of(&solver), "not factored");
        assert!(!own.is_factored_of_pattern_of(&CholeskySolver::new()));
        let mut other = s.clone();
        other.row_idx.pop();
        other.values.pop();
        *other.col_ptr.last_mut().unwrap() -= 1;
        let mut other_solver = CholeskySolver::new();
        other_solver.analyse(&other).unwrap();
        assert!(
            !own.is_factored_of_pattern_of(&other_solver),
            "another pattern"
        );
        assert!(
            matches!(spawn(8), Err(SolverError::Backend(_))),
            "too large a supernode"
        );
        solver.prepare(&s).unwrap();
        let b: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.3).sin()).collect();
        let (mut x, mut y) = (b.clone(), b.clone());
        solver.solve_in_place(&mut x, 1).unwrap();
        own.solve_in_place(&mut y, 1).unwrap();
        let scale = x.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (p, q) in x.iter().zip(&y) {
            assert!((p - q).abs() <= 1e-12 * scale, "{p} against {q}");
        }
    }

    /// A plan that asks for the inverted form has the factoring thread take
    /// the factor and invert its diagonal blocks: the solver made ahead is
    /// still a factor of its analysis, and gives the very factor a twin's,
    /// taken and inverted afterwards, is (to the bit), once.
    #[test]
    fn a_factor_made_ahead_inverted_is_the_factor_inverted_after() {
        let n = 60;
        let s = spd_scalar(n);
        let mut analysed = CholeskySolver::new();
        analysed.supernodal = true;
        analysed.analyse(&s).unwrap();
        let plan = |inverted| FactorPlan {
            single: false,
            largest_supernode_bytes: u64::MAX,
            inverted,
        };
        let made = |inverted| {
            let twin = plan(inverted).twin(&analysed).unwrap();
            FactorAhead::spawn(twin, s.clone())
                .unwrap()
                .join()
                .0
                .unwrap()
        };
        let mut ahead = made(true);
        assert!(ahead.is_factored_on(&analysed));
        let mut after = made(false);
        let mut want = after.take_supernodal_factor().unwrap();
        assert!(!want.inverted);
        want.invert_diagonal_blocks();
        let got = ahead.take_supernodal_factor().unwrap();
        assert!(got.inverted);
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&got.values64), bits(&want.values64));
        assert_eq!(got.rows, want.rows);
        assert!(!ahead.is_factored_on(&analysed), "taken");
        assert!(ahead.take_supernodal_factor().is_none(), "taken once");
    }

    /// A factor plan's twin is a numeric twin in its precision where the
    /// largest supernode fits its bound, and none where it does not or
    /// before an analysis; the factor's bytes follow the precision.
    #[test]
    fn a_factor_plan_twins_an_analysis_whose_supernodes_fit() {
        let n = 50;
        let s = spd_scalar(n);
        let mut solver = CholeskySolver::new();
        let plan = |single, bytes| FactorPlan {
            single,
            largest_supernode_bytes: bytes,
            inverted: false,
        };
        assert!(
            plan(false, u64::MAX).twin(&solver).is_none(),
            "nothing analysed"
        );
        solver.analyse(&s).unwrap();
        let largest = solver.largest_supernode_nnz() as u64;
        assert!(largest > 0);
        for single in [false, true] {
            let value = if single { 4 } else { 8 };
            let fits = plan(single, largest * value).twin(&solver).unwrap();
            assert_eq!(fits.is_single_precision(), single);
            assert!(!fits.is_factored_on(&solver), "not factored yet");
            assert!(plan(single, largest * value - 1).twin(&solver).is_none());
            assert_eq!(
                plan(single, 0).factor_bytes(&solver),
                solver.factor_nnz() as u64 * value
            );
        }
    }

    #[test]
    fn cholesky_rejects_indefinite() {
        let mut s = SymCsc::from_pattern(2, [(1, 0)]);
        let (a, b, c) = (
            s.slot(0, 0).unwrap(),
            s.slot(1, 0).unwrap(),
            s.slot(1, 1).unwrap(),
        );
        s.values[a] = 1.0;
        s.values[b] = 2.0;
        s.values[c] = 1.0;
        let mut solver = CholeskySolver::new();
        let r = solver.prepare(&s);
        assert_eq!(r, Err(SolverError::NotPositiveDefinite));
    }

    /// Vertex pairs of a w x w grid: right and down neighbours, and with
    /// `diagonal` the down-right one too.
    fn grid_pairs(w: usize, diagonal: bool) -> Vec<(usize, usize)> {
        let mut pairs = Vec::new();
        for y in 0..w {
            for x in 0..w {
                let v = y * w + x;
                if x + 1 < w {
                    pairs.push((v, v + 1));
                }
                if y + 1 < w {
                    pairs.push((v, v + w));
                    if diagonal && x + 1 < w {
                        pairs.push((v, v + w + 1));
                    }
                }
            }
        }
        pairs
    }

    /// A 2D grid graph (mesh-like, every vertex coupled to up to 8 neighbours)
    /// with anisotropic random 3x3 couplings: SPD, not a Kronecker product.
    fn grid_spd(w: usize) -> BlockSym3 {
        let n = w * w;
        let pairs = grid_pairs(w, true);
        let mut a = BlockSym3::from_pattern(n, pairs.clone());
        for (k, &(p, q)) in pairs.iter().enumerate() {
            let w = 1.0 + 0.5 * (k as f64 * 0.61).sin();
            a.add_scalar(p, p, w);
            a.add_scalar(q, q, w);
            a.add_scalar(p, q, -w);
            // Anisotropic PSD term d d^T on the pair (p, q): [[M, -M], [-M, M]].
            let d = [(k as f64).cos(), (k as f64 * 1.3).sin(), 0.4];
            let m: [f64; 9] = std::array::from_fn(|e| 0.8 * d[e / 3] * d[e % 3]);
            let neg: [f64; 9] = std::array::from_fn(|e| -m[e]);
            a.add_block(p, p, &m);
            a.add_block(q, q, &m);
            a.add_block(p, q, &neg);
        }
        a
    }

    #[test]
    fn block_pcg_matches_cholesky_with_held_vertices_and_columns() {
        let w = 20;
        let a = grid_spd(w);
        let n = a.n;
        // Hold two vertices (the matrix is singular without them: a Laplacian).
        let mut fixed = vec![false; n];
        fixed[0] = true;
        fixed[n - 1] = true;
        let mut direct = CholeskySolver::new();
        direct.prepare_blocks(&a, &fixed).unwrap();
        let mut pcg = BlockPcgSolver::new();
        pcg.prepare_blocks(&a, &fixed).unwrap();
        let ncols = 3;
        let mut b: Vec<f64> = (0..3 * n * ncols)
            .map(|i| (i as f64 * 0.37).sin() + 0.1)
            .collect();
        for c in 0..ncols {
            for v in [0, n - 1] {
                b[3 * n * c + 3 * v..3 * n * c + 3 * v + 3].fill(0.0);
            }
        }
        let mut xd = b.clone();
        direct.solve_in_place(&mut xd, ncols).unwrap();
        let mut xp = b.clone();
        let info = pcg.solve_in_place(&mut xp, ncols).unwrap();
        assert!(info.iterations > 1, "a real iteration ran");
        assert!(info.residual <= 1e-10);
        let scale = xd.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for i in 0..xd.len() {
            assert!(
                (xd[i] - xp[i]).abs() <= 1e-8 * scale,
                "entry {i}: direct {} pcg {}",
                xd[i],
                xp[i]
            );
        }
        // Held vertices stay at zero increment.
        assert_eq!(&xp[0..3], &[0.0, 0.0, 0.0]);
        // Warm start from the solution converges at once.
        let mut guess = xp.clone();
        let warm = pcg.solve_with_guess(&b, &mut guess, ncols).unwrap();
        assert!(warm.iterations < info.iterations);
        // Parallel product equals the sequential one.
        let x: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.11).cos()).collect();
        let (mut y1, mut y2) = (vec![0.0; 3 * n], vec![0.0; 3 * n]);
        a.mul_vec(&x, &mut y1);
        a.mul_vec_rows(&a.row_index(), &x, &mut y2);
        for i in 0..3 * n {
            assert!((y1[i] - y2[i]).abs() <= 1e-12 * (1.0 + y1[i].abs()));
        }
    }

    #[test]
    fn block_pcg_reports_no_convergence() {
        let a = grid_spd(12);
        let mut fixed = vec![false; a.n];
        fixed[0] = true;
        let mut pcg = BlockPcgSolver::with_params(BlockPcgParams {
            max_iterations: 1,
            ..BlockPcgParams::default()
        });
        pcg.prepare_blocks(&a, &fixed).unwrap();
        let mut b: Vec<f64> = (0..3 * a.n).map(|i| (i as f64).sin()).collect();
        b[0..3].fill(0.0);
        match pcg.solve_in_place(&mut b, 1) {
            Err(SolverError::NoConvergence { iterations, .. }) => assert_eq!(iterations, 1),
            other => panic!("expected NoConvergence, got {other:?}"),
        }
    }

    /// Scalar 5-point Laplacian of a w x w grid plus `shift` on the diagonal.
    fn grid_laplacian(w: usize, shift: f64) -> SymCsc {
        let n = w * w;
        let pairs = grid_pairs(w, false);
        let mut s = SymCsc::from_pattern(n, pairs.clone());
        for v in 0..n {
            let k = s.slot(v, v).unwrap();
            s.values[k] += shift * (1.0 + 0.5 * (v as f64 * 0.3).sin());
        }
        for &(p, q) in &pairs {
            let (kp, kq, kpq) = (
                s.slot(p, p).unwrap(),
                s.slot(q, q).unwrap(),
                s.slot(p, q).unwrap(),
            );
            s.values[kp] += 1.0;
            s.values[kq] += 1.0;
            s.values[kpq] -= 1.0;
        }
        s
    }

    /// METIS's random numbers are global state: orderings computed on
    /// several threads at once equal the one a call alone computes, because
    /// one call runs at a time (without that, they differed).
    #[test]
    fn nested_dissection_is_the_same_on_several_threads_at_once() {
        let a = grid_laplacian(160, 1e-3);
        let alone = crate::cholesky::nested_dissection(&a)
            .expect("METIS ordering")
            .0;
        let together: Vec<Vec<usize>> = std::thread::scope(|scope| {
            let runs: Vec<_> = (0..4)
                .map(|_| scope.spawn(|| crate::cholesky::nested_dissection(&a).unwrap().0))
                .collect();
            runs.into_iter().map(|r| r.join().unwrap()).collect()
        });
        for (i, order) in together.iter().enumerate() {
            assert!(*order == alone, "thread {i}: another ordering");
        }
    }

    #[test]
    fn nested_dissection_solves_like_amd_with_less_fill_on_a_grid() {
        let a = grid_laplacian(120, 1e-3);
        let (fwd, inv) = crate::cholesky::nested_dissection(&a).expect("METIS ordering");
        for (new, &old) in fwd.iter().enumerate() {
            assert_eq!(inv[old], new, "inverse permutation");
        }
        let b: Vec<f64> = (0..a.n).map(|i| (i as f64 * 0.7).sin()).collect();
        let mut solutions = Vec::new();
        let mut fill = Vec::new();
        for ordering in [FillOrdering::Amd, FillOrdering::NestedDissection] {
            let mut chol = CholeskySolver::new();
            chol.ordering = ordering;
            chol.prepare(&a).unwrap();
            let mut x = b.clone();
            chol.solve_in_place(&mut x, 1).unwrap();
            let mut ax = vec![0.0; a.n];
            a.mul_vec(&x, &mut ax);
            let res = ax
                .iter()
                .zip(&b)
                .map(|(p, q)| (p - q).powi(2))
                .sum::<f64>()
                .sqrt();
            assert!(res <= 1e-10 * b.iter().map(|v| v * v).sum::<f64>().sqrt());
            fill.push(chol.factor_nnz());
            solutions.push(x);
        }
        let scale = solutions[0].iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (p, q) in solutions[0].iter().zip(&solutions[1]) {
            assert!((p - q).abs() <= 1e-9 * scale);
        }
        assert!(
            fill[1] < fill[0],
            "nnz(L): AMD {} nested dissection {}",
            fill[0],
            fill[1]
        );
    }

    /// A factor made from an owned matrix (dropped before the factor's
    /// storage is made) is the factor made from a borrowed one, to the bit,
    /// and a twin's solves give the same solution.
    #[test]
    fn a_factor_of_an_owned_matrix_is_the_factor_of_a_borrowed_one() {
        let a = grid_laplacian(90, 1e-3);
        let mut borrowed = CholeskySolver::new();
        borrowed.supernodal = true;
        borrowed.prepare(&a).unwrap();
        let mut owned = borrowed.numeric_twin(false).unwrap();
        owned.prepare_owned(a.clone()).unwrap();
        assert!(owned.is_factored_on(&borrowed));
        let b: Vec<f64> = (0..a.n).map(|i| (i as f64 * 0.37).sin() + 0.1).collect();
        let (mut xb, mut xo) = (b.clone(), b.clone());
        borrowed.solve_in_place(&mut xb, 1).unwrap();
        owned.solve_in_place(&mut xo, 1).unwrap();
        assert!(xb.iter().zip(&xo).all(|(p, q)| p.to_bits() == q.to_bits()));
        let fb = borrowed.take_supernodal_factor().unwrap().values64;
        let fo = owned.take_supernodal_factor().unwrap().values64;
        assert!(!fb.is_empty() && fb.len() == fo.len());
        assert!(fb.iter().zip(&fo).all(|(p, q)| p.to_bits() == q.to_bits()));
        // A matrix that is not positive definite is reported as such.
        let mut bad = a.clone();
        for v in 0..bad.n {
            let k = bad.slot(v, v).unwrap();
            bad.values[k] -= 10.0;
        }
        let mut twin = borrowed.numeric_twin(false).unwrap();
        assert!(matches!(
            twin.prepare_owned(bad),
            Err(SolverError::NotPositiveDefinite)
        ));
    }

    #[test]
    fn single_precision_factor_preconditions_f64_pcg_to_full_accuracy() {
        let a = grid_laplacian(60, 0.05);
        let mut pcg = BlockPcgSolver::with_params(BlockPcgParams {
            single_precision_factor: true,
            ..BlockPcgParams::default()
        });
        pcg.prepare(&a).unwrap();
        let (bytes, nnz) = pcg.factor_size();
        assert!(
            nnz > a.n && bytes == 4 * nnz,
            "f32 factor: {bytes} bytes, {nnz} entries"
        );
        let mut direct = CholeskySolver::new();
        direct.prepare(&a).unwrap();
        let b: Vec<f64> = (0..2 * a.n)
            .map(|i| (i as f64 * 0.29).cos() + 0.2)
            .collect();
        let mut xd = b.clone();
        direct.solve_in_place(&mut xd, 2).unwrap();
        let mut xp = b.clone();
        let info = pcg.solve_in_place(&mut xp, 2).unwrap();
        assert!(info.iterations >= 1 && info.residual <= 1e-10, "{info:?}");
        let scale = xd.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (p, q) in xd.iter().zip(&xp) {
            assert!((p - q).abs() <= 1e-8 * scale, "direct {p} pcg {q}");
        }
    }

    #[test]
    fn block_pcg_keeps_an_owned_matrix_unchanged_and_honours_held_right_hand_sides() {
        let a = grid_spd(14);
        let n = a.n;
        let mut fixed = vec![false; n];
        fixed[3] = true;
        fixed[n - 5] = true;
        let mut direct = CholeskySolver::new();
        direct.prepare_blocks(&a, &fixed).unwrap();
        let mut pcg = BlockPcgSolver::new();
        let back = pcg.prepare_blocks_owned(a.clone(), &fixed).unwrap();
        assert!(back.is_none(), "the PCG solver keeps the matrix");
        assert_eq!(
            pcg.blocks().unwrap().blocks,
            a.blocks,
            "kept as handed over"
        );
        // Non-zero right-hand side at held dofs: identity rows, x_v = b_v.
        let b: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.53).sin() + 0.3).collect();
        let mut xd = b.clone();
        direct.solve_in_place(&mut xd, 1).unwrap();
        let mut xp = vec![0.0; 3 * n];
        pcg.solve_with_guess(&b, &mut xp, 1).unwrap();
        let scale = xd.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for i in 0..3 * n {
            assert!(
                (xd[i] - xp[i]).abs() <= 1e-8 * scale,
                "dof {i}: {} vs {}",
                xd[i],
                xp[i]
            );
        }
        assert_eq!(&xp[9..12], &b[9..12]);
        let taken = pcg.take_blocks().unwrap();
        assert_eq!(taken.blocks, a.blocks);
        assert!(pcg.blocks().is_none() || pcg.blocks().unwrap().n == 0);
    }
}
