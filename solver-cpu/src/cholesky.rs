//! Reference backend: sparse Cholesky `A = L L^T` with faer.
//!
//! Symbolic/numeric split: the ordering, elimination tree and supernodes are
//! computed once per sparsity pattern (recognised by a fingerprint, not a copy)
//! and reused for every new set of values; the numeric factor's storage is
//! reused too. The factorization's scratch is allocated per factorization and
//! freed after it, so it is not resident beside the factor.
//!
//! [`CholeskySolver::single_precision`] stores the numeric factor in f32 (half the
//! memory and half the memory traffic of a solve). Such a factor is a
//! preconditioner, not a solver: its solves carry f32 rounding amplified by the
//! condition number, so it is used inside the f64 PCG of [`crate::BlockPcgSolver`].

use crate::symbolic::{analyse_pattern, SymbolicFactor};
use crate::tree_factor::{factor_numeric_tree, factor_permuted, permute_lower};
use crate::{BlockSym3, SolveInfo, SolverError, SpdSolver, SymCsc, WorkCounters};
use faer::get_global_parallelism;
use faer::sparse::linalg::cholesky::{SymbolicCholeskyRaw, SymmetricOrdering};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use rayon::prelude::*;
use std::sync::Arc;

/// Fill-reducing ordering of the symbolic analysis.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum FillOrdering {
    /// Nested dissection from [`NESTED_DISSECTION_FROM`] unknowns on, AMD below.
    #[default]
    Auto,
    /// faer's approximate minimum degree.
    Amd,
    /// METIS nested dissection (`METIS_NodeND`).
    NestedDissection,
    /// A permutation computed beforehand (`forward[new] = old`), e.g. by
    /// [`nested_dissection_of_pattern`] on another thread; for a 3x3-block matrix,
    /// a permutation of its block rows. One that is not a permutation of the
    /// matrix's size is ignored (with a warning) for `Auto`. It is used by the
    /// next symbolic analysis only, then released (the solver reverts to `Auto`).
    Given(std::sync::Arc<[usize]>),
}

/// Size from which [`FillOrdering::Auto`] uses nested dissection: on mesh-like
/// graphs its factors grow as `n log n` where minimum degree's grow faster.
pub const NESTED_DISSECTION_FROM: usize = 50_000;

/// Runs `beside()` on this thread while `analyser` (an unanalysed solver,
/// e.g. [`SpdSolver::isotropic_analyser`]'s) makes the symbolic analysis of
/// `k`'s pattern on another; returns what `beside` returned, the analysed
/// solver (for [`SpdSolver::adopt_isotropic_analysis`]; `Err` where the
/// analysis failed or panicked) and the analysis's seconds.
pub fn analyse_beside<R>(
    analyser: CholeskySolver,
    k: &SymCsc,
    beside: impl FnOnce() -> R,
) -> (R, Result<CholeskySolver, SolverError>, f64) {
    let (made, analysed, seconds) = analyse_beside_then(analyser, k, |_| (), beside);
    (made, analysed.map(|(a, ())| a), seconds)
}

/// As [`analyse_beside`], and once the analysis is made, `then(&analysed)`
/// runs on the analysing thread too (e.g. starts numeric factorizations on
/// it, [`FactorPlan`]) while `beside()` may still run; its value comes back
/// with the analysed solver. The seconds are the analysis's alone.
pub fn analyse_beside_then<R, T: Send>(
    mut analyser: CholeskySolver,
    k: &SymCsc,
    then: impl FnOnce(&CholeskySolver) -> T + Send,
    beside: impl FnOnce() -> R,
) -> (R, Result<(CholeskySolver, T), SolverError>, f64) {
    std::thread::scope(|scope| {
        let ahead = scope.spawn(move || {
            let t = std::time::Instant::now();
            let done = analyser.analyse(k);
            let seconds = t.elapsed().as_secs_f64();
            (done.map(|()| (then(&analyser), analyser)), seconds)
        });
        let made = beside();
        let (analysed, seconds) = ahead.join().unwrap_or_else(|_| {
            (
                Err(SolverError::Backend(
                    "the symbolic analysis panicked".into(),
                )),
                0.0,
            )
        });
        (made, analysed.map(|(t, a)| (a, t)), seconds)
    })
}

/// How a solver makes a shape kind's factor of `K` ahead
/// ([`SpdSolver::isotropic_factor_plan`]), known before the analysis: its
/// precision, and the most bytes one supernode may take (the device's
/// storage binding, where the factor goes to a GPU).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FactorPlan {
    /// The factor in f32.
    pub single: bool,
    /// The most bytes of the largest supernode's values.
    pub largest_supernode_bytes: u64,
    /// The factor taken in supernodal form with its diagonal blocks
    /// inverted, on the thread that makes it
    /// ([`CholeskySolver::invert_taken`]): a GPU's form, off the thread that
    /// takes the factor.
    pub inverted: bool,
}

impl FactorPlan {
    /// A numeric twin of `analysed` ([`CholeskySolver::numeric_twin`]) in
    /// this plan's precision; `None` before an analysis or where the
    /// largest supernode would not fit.
    pub fn twin(&self, analysed: &CholeskySolver) -> Option<CholeskySolver> {
        (analysed.largest_supernode_nnz() as u64 * self.value_bytes()
            <= self.largest_supernode_bytes)
            .then(|| analysed.numeric_twin(self.single))
            .flatten()
            .map(|mut twin| {
                twin.invert_when_factored = self.inverted;
                twin
            })
    }

    /// A supernodal solver in this plan's precision that has analysed
    /// nothing and orders by `ordering`: for a factor made on its own
    /// symbolic analysis ([`FactorAhead::spawn_analysing`]).
    pub fn unanalysed(&self, ordering: FillOrdering) -> CholeskySolver {
        CholeskySolver {
            ordering,
            single: self.single,
            supernodal: true,
            invert_when_factored: self.inverted,
            ..CholeskySolver::default()
        }
    }

    /// Bytes of the factor's values on `analysed`'s analysis.
    pub fn factor_bytes(&self, analysed: &CholeskySolver) -> u64 {
        analysed.factor_nnz() as u64 * self.value_bytes()
    }

    fn value_bytes(&self) -> u64 {
        if self.single {
            4
        } else {
            8
        }
    }
}

/// A numeric factorization made on another thread while the caller goes on:
/// a numeric twin ([`CholeskySolver::numeric_twin`]) factors a matrix of its
/// analysed pattern. The caller takes the factored solver with
/// [`FactorAhead::join`]; dropped unjoined, the thread finishes on its own.
pub struct FactorAhead(std::thread::JoinHandle<(Result<CholeskySolver, SolverError>, f64)>);

impl FactorAhead {
    /// Starts factoring `k` with `twin`.
    pub fn spawn(twin: CholeskySolver, k: SymCsc) -> Result<FactorAhead, SolverError> {
        FactorAhead::spawn_on(twin, k, None)
    }

    /// [`Self::spawn`] for a factor that no phase waits for yet (the
    /// fine-tune's, made while the scale-driven iteration runs): its
    /// parallel work runs on [`background_pool`]'s threads, at a lower
    /// scheduling priority, instead of rayon's global pool, where the
    /// running phase's own parallel work (the shape terms' sums) queued
    /// behind it. On an H200's 16-core host the outer iterations that the
    /// fine-tune's factorization overlapped summed their shape terms in
    /// 0.19-0.38 s against 0.115 s at homer 1.2M, and in 0.96-1.13 s
    /// against 0.41 s at 4.3M. The same factor either way.
    pub fn spawn_in_background(
        twin: CholeskySolver,
        k: SymCsc,
    ) -> Result<FactorAhead, SolverError> {
        FactorAhead::spawn_on(twin, k, background_pool())
    }

    fn spawn_on(
        mut twin: CholeskySolver,
        k: SymCsc,
        pool: Option<&'static rayon::ThreadPool>,
    ) -> Result<FactorAhead, SolverError> {
        std::thread::Builder::new()
            .name("factor-ahead".into())
            .spawn(move || {
                let t = std::time::Instant::now();
                let factor = move || {
                    twin.prepare_owned(k).map(|()| {
                        twin.invert_taken_if_wanted();
                        twin
                    })
                };
                let done = match pool {
                    Some(pool) => pool.install(factor),
                    None => factor(),
                };
                (done, t.elapsed().as_secs_f64())
            })
            .map(FactorAhead)
            .map_err(|e| SolverError::Backend(format!("no thread for the factorization: {e}")))
    }

    /// Starts, on another thread, the symbolic analysis of `k` in `plan`'s
    /// precision with the fill ordering `ordering()` returns (which may
    /// wait for it, e.g. for METIS on a third thread), then its numeric
    /// factorization: a factor of `k`'s pattern on its own analysis, not a
    /// numeric twin's. It fails where the largest supernode would not fit
    /// `plan`.
    pub fn spawn_analysing(
        plan: FactorPlan,
        ordering: impl FnOnce() -> FillOrdering + Send + 'static,
        k: SymCsc,
    ) -> Result<FactorAhead, SolverError> {
        std::thread::Builder::new()
            .name("factor-ahead".into())
            .spawn(move || {
                let t = std::time::Instant::now();
                let mut c = plan.unanalysed(ordering());
                let done = c.analyse(&k).and_then(|()| {
                    let bytes = c.largest_supernode_nnz() as u64 * plan.value_bytes();
                    if bytes > plan.largest_supernode_bytes {
                        return Err(SolverError::Backend(format!(
                            "the factor's largest supernode ({bytes} bytes) exceeds the plan's \
                             {} bytes",
                            plan.largest_supernode_bytes
                        )));
                    }
                    c.prepare_owned(k).map(|()| {
                        c.invert_taken_if_wanted();
                        c
                    })
                });
                (done, t.elapsed().as_secs_f64())
            })
            .map(FactorAhead)
            .map_err(|e| SolverError::Backend(format!("no thread for the factorization: {e}")))
    }

    /// Whether the factorization has ended (joining does not wait then).
    pub fn is_finished(&self) -> bool {
        self.0.is_finished()
    }

    /// Waits for the factorization: the factored solver (`Err` where it
    /// failed or panicked) and its seconds.
    pub fn join(self) -> (Result<CholeskySolver, SolverError>, f64) {
        self.0.join().unwrap_or_else(|_| {
            (
                Err(SolverError::Backend(
                    "the factorization made ahead panicked".into(),
                )),
                0.0,
            )
        })
    }
}

/// rayon's threads for work that no phase waits for yet
/// ([`FactorAhead::spawn_in_background`]): as many as the global pool's
/// (at its first use), each 10 steps nicer than the thread that made the
/// pool (at most 19) where the OS gives threads their own priority (Linux),
/// so that the running phase's threads take the cores first. Made on first
/// use and kept; `None` where no pool could be built (the work then runs on
/// the global pool).
pub fn background_pool() -> Option<&'static rayon::ThreadPool> {
    static POOL: std::sync::OnceLock<Option<rayon::ThreadPool>> = std::sync::OnceLock::new();
    POOL.get_or_init(|| {
        let nicer = thread_priority().map(|p| (p + 10).min(19));
        rayon::ThreadPoolBuilder::new()
            .num_threads(rayon::current_num_threads())
            .thread_name(|i| format!("background-{i}"))
            .start_handler(move |_| {
                if let Some(p) = nicer {
                    set_thread_priority(p);
                }
            })
            .build()
            .inspect_err(|e| log::debug!("no background thread pool: {e}"))
            .ok()
    })
    .as_ref()
}

/// The calling thread's nice value (Linux; `None` elsewhere).
pub fn thread_priority() -> Option<i32> {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: plain system calls on the calling thread's id. errno is
        // cleared first: -1 is a valid nice value.
        unsafe {
            let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
            *libc::__errno_location() = 0;
            let p = libc::getpriority(libc::PRIO_PROCESS, tid);
            (*libc::__errno_location() == 0).then_some(p)
        }
    }
    #[cfg(not(target_os = "linux"))]
    None
}

/// Sets the calling thread's nice value (Linux; nothing elsewhere, or where
/// the OS refuses).
fn set_thread_priority(nice: i32) {
    #[cfg(target_os = "linux")]
    // SAFETY: plain system calls on the calling thread's id.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        if libc::setpriority(libc::PRIO_PROCESS, tid, nice) != 0 {
            log::debug!("background thread's priority left as it was");
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = nice;
}

/// METIS nested-dissection permutation of the graph of `a` (diagonal ignored):
/// `(forward, inverse)` with `forward[new] = old`; `None` if METIS fails.
pub fn nested_dissection(a: &SymCsc) -> Option<(Vec<usize>, Vec<usize>)> {
    nested_dissection_of_pattern(a.n, &a.col_ptr, &a.row_idx)
}

/// Held while METIS runs. METIS draws random numbers from GKlib's generator,
/// whose state is one global: two calls at once race on it (a data race in
/// C), and their orderings then differ from run to run (homer 108k's shape
/// pattern, 2026-11-26: two calls on two threads gave orderings unlike the
/// one every sequential call gives, in 4 of 4 trials). One call at a time
/// gives the same ordering on every run.
static METIS: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// As [`nested_dissection`], for the lower-triangular pattern `(col_ptr, row_idx)`
/// of an `n x n` symmetric matrix (scalar or block). One call runs at a time
/// in the process (METIS's random numbers are global state).
pub fn nested_dissection_of_pattern(
    n: usize,
    col_ptr: &[usize],
    row_idx: &[usize],
) -> Option<(Vec<usize>, Vec<usize>)> {
    if n == 0 {
        return None;
    }
    let graph = crate::ordering::Adjacency::of_lower(n, col_ptr, row_idx)?;
    let mut xadj: Vec<i32> = graph.xadj.iter().map(|&x| x as i32).collect();
    let mut adjncy: Vec<i32> = graph.adj.into_iter().map(|v| v as i32).collect();
    let mut nvtxs = n as i32;
    let mut options = [0i32; metis_sys::METIS_NOPTIONS as usize];
    let mut perm = vec![0i32; n];
    let mut iperm = vec![0i32; n];
    // SAFETY: every array has the length METIS_NodeND documents (xadj n + 1,
    // adjncy xadj[n], options METIS_NOPTIONS, perm and iperm n), all live for
    // the call; a null vwgt means unit weights.
    let _one_at_a_time = METIS.lock().unwrap_or_else(|e| e.into_inner());
    let status = unsafe {
        metis_sys::METIS_SetDefaultOptions(options.as_mut_ptr());
        metis_sys::METIS_NodeND(
            &mut nvtxs,
            xadj.as_mut_ptr(),
            adjncy.as_mut_ptr(),
            std::ptr::null_mut(),
            options.as_mut_ptr(),
            perm.as_mut_ptr(),
            iperm.as_mut_ptr(),
        )
    };
    if status != metis_sys::rstatus_et_METIS_OK {
        return None;
    }
    // METIS: row i of the permuted matrix is row perm[i] of the original.
    let forward: Vec<usize> = perm.iter().map(|&p| p as usize).collect();
    let inverse: Vec<usize> = iperm.iter().map(|&p| p as usize).collect();
    Some((forward, inverse))
}

/// Fingerprint of a sparsity pattern: its sizes and a 64-bit hash of its
/// indices. Kept instead of a copy of the pattern (tens of MiB at a million
/// faces) to decide whether the symbolic analysis can be reused; two different
/// patterns of equal sizes collide with probability about 2^-64.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PatternKey {
    n: usize,
    nnz: usize,
    hash: u64,
}

impl PatternKey {
    /// FNV-1a over the 64-bit words of each run of [`PATTERN_KEY_RUN`] of
    /// `col_ptr`, then of `row_idx`, on rayon's threads; the runs' hashes,
    /// each through an avalanche (splitmix64), are combined by FNV-1a in
    /// order, and the result goes through the avalanche again. The same key
    /// on any number of threads. One chain over every word took 6 ms at
    /// homer 1.2M's shape pattern on the development machine, for every
    /// shape matrix of the GPU path (its pattern check).
    pub fn of(col_ptr: &[usize], row_idx: &[usize]) -> PatternKey {
        const OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
        const PRIME: u64 = 0x0100_0000_01b3;
        let fnv = |h: u64, v: u64| (h ^ v).wrapping_mul(PRIME);
        let runs: Vec<u64> = col_ptr
            .par_chunks(PATTERN_KEY_RUN)
            .chain(row_idx.par_chunks(PATTERN_KEY_RUN))
            .map(|run| avalanche(run.iter().fold(OFFSET, |h, &v| fnv(h, v as u64))))
            .collect();
        PatternKey {
            n: col_ptr.len(),
            nnz: row_idx.len(),
            hash: avalanche(runs.into_iter().fold(OFFSET, fnv)),
        }
    }
}

/// Words per run of [`PatternKey::of`]'s hash (each run one task).
pub const PATTERN_KEY_RUN: usize = 1 << 16;

/// splitmix64's finaliser: every bit of `h` reaches every bit of the result.
fn avalanche(mut h: u64) -> u64 {
    h ^= h >> 30;
    h = h.wrapping_mul(0xbf58_476d_1ce4_e5b9);
    h ^= h >> 27;
    h = h.wrapping_mul(0x94d0_49bb_1331_11eb);
    h ^ (h >> 31)
}

/// The inverse of `forward` when it is a permutation of `0..n`.
fn inverse_permutation(forward: &[usize], n: usize) -> Option<Vec<usize>> {
    if forward.len() != n {
        return None;
    }
    let mut inverse = vec![usize::MAX; n];
    for (new, &old) in forward.iter().enumerate() {
        if old >= n || inverse[old] != usize::MAX {
            return None;
        }
        inverse[old] = new;
    }
    Some(inverse)
}

/// A solver's symbolic analysis ([`CholeskySolver::analysis_id`]), held:
/// the same analysis (shared by a solver and its numeric twins) or not,
/// whatever the patterns and orderings compared would say.
#[derive(Clone, Debug)]
pub struct AnalysisId(Arc<SymbolicFactor>);

impl AnalysisId {
    /// Whether `other` is this very analysis.
    pub fn is(&self, other: &AnalysisId) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }

    /// Whether `solver` holds this very analysis.
    pub fn is_of(&self, solver: &CholeskySolver) -> bool {
        solver
            .symbolic
            .as_ref()
            .is_some_and(|s| Arc::ptr_eq(s, &self.0))
    }
}

/// faer sparse Cholesky with the symbolic factorization reused across matrices
/// of the same pattern.
#[derive(Default)]
pub struct CholeskySolver {
    /// Ordering used by the next symbolic analysis.
    pub ordering: FillOrdering,
    /// Fingerprint of the analysed pattern (see [`PatternKey`]).
    pattern: Option<PatternKey>,
    /// Shared with the solver's numeric twins ([`CholeskySolver::numeric_twin`]).
    symbolic: Option<Arc<SymbolicFactor>>,
    numeric: Vec<f64>,
    /// The factor in f32 when `single` (then `numeric` stays empty).
    numeric32: Vec<f32>,
    /// Factor and solve in f32 (see module docs).
    single: bool,
    /// Always a supernodal factor (faer picks a simplicial one for sparse
    /// factors): for [`CholeskySolver::take_supernodal_factor`]'s users, whose
    /// solves run a supernode per step.
    pub supernodal: bool,
    /// Factor a supernodal factor's supernodes one after the other, on faer's
    /// loop, instead of its elimination tree's independent subtrees at once
    /// ([`crate::tree_factor`]; the default). For comparison.
    pub sequential_supernodes: bool,
    /// Solve buffer in f32 (single precision only).
    buf32: Vec<f32>,
    factored: bool,
    n: usize,
    /// Scalar copy of the last block matrix (pattern kept while unchanged).
    block_scalar: Option<(PatternKey, SymCsc)>,
    /// How many symbolic analyses were made (for tests and benchmarks).
    pub symbolic_count: usize,
    /// How many numeric factorizations were made.
    pub numeric_count: usize,
    /// Seconds of the last numeric factorization.
    pub numeric_seconds: f64,
    /// Solve calls.
    solves: usize,
    /// Take the factor and invert its diagonal blocks where it is made
    /// ahead ([`FactorPlan::inverted`]).
    invert_when_factored: bool,
    /// The factor so taken and inverted, for [`CholeskySolver::take_supernodal_factor`].
    taken_inverted: Option<SupernodalFactor>,
}

impl CholeskySolver {
    pub fn new() -> Self {
        Self::default()
    }

    /// A solver whose numeric factor is f32 (a preconditioner; see module docs).
    pub fn single_precision() -> Self {
        CholeskySolver {
            single: true,
            ..Self::default()
        }
    }

    /// Whether the numeric factor is f32.
    pub fn is_single_precision(&self) -> bool {
        self.single
    }

    /// A solver that has analysed nothing, with this one's fill ordering and
    /// supernodal choice, its factor in f32 when `single`; `None` once this
    /// one has analysed a pattern (its given ordering has served then). For
    /// a symbolic analysis made ahead on another thread
    /// ([`SpdSolver::isotropic_analyser`]).
    pub fn unanalysed_like(&self, single: bool) -> Option<CholeskySolver> {
        self.symbolic.is_none().then(|| CholeskySolver {
            ordering: self.ordering.clone(),
            single,
            supernodal: self.supernodal,
            sequential_supernodes: self.sequential_supernodes,
            ..Self::default()
        })
    }

    /// Whether `analysed` may take this solver's place: it has analysed a
    /// pattern and this one has not.
    pub fn may_adopt(&self, analysed: &CholeskySolver) -> bool {
        self.symbolic.is_none() && analysed.symbolic.is_some()
    }

    /// A solver that shares this one's symbolic analysis (its pattern,
    /// ordering and supernodes; nothing is copied) and has factored nothing,
    /// its factor in f32 when `single`; `None` before an analysis. For a
    /// numeric factorization made ahead on another thread
    /// ([`SpdSolver::isotropic_factorer`], [`FactorAhead`]).
    pub fn numeric_twin(&self, single: bool) -> Option<CholeskySolver> {
        self.symbolic.as_ref().map(|s| CholeskySolver {
            pattern: self.pattern,
            symbolic: Some(s.clone()),
            single,
            supernodal: self.supernodal,
            ..Self::default()
        })
    }

    /// Whether this solver holds a numeric factor made on `other`'s symbolic
    /// analysis (the same one, shared: see [`CholeskySolver::numeric_twin`]).
    pub fn is_factored_on(&self, other: &CholeskySolver) -> bool {
        self.factored
            && matches!((&self.symbolic, &other.symbolic), (Some(s), Some(o)) if Arc::ptr_eq(s, o))
    }

    /// Whether this solver holds a numeric factor of the pattern `other`
    /// has analysed, on any analysis of it (its own ordering, e.g.
    /// [`FactorAhead::spawn_analysing`]'s, or `other`'s shared).
    pub fn is_factored_of_pattern_of(&self, other: &CholeskySolver) -> bool {
        self.factored
            && other.symbolic.is_some()
            && self.pattern.is_some()
            && self.pattern == other.pattern
    }

    /// This solver's symbolic analysis, as a handle compared by identity
    /// ([`AnalysisId::is_of`]); `None` before the analysis.
    pub fn analysis_id(&self) -> Option<AnalysisId> {
        self.symbolic.clone().map(AnalysisId)
    }

    /// Whether this solver's symbolic analysis is of the pattern
    /// `(col_ptr, row_idx)` (lower CSC, as [`SymCsc`]'s).
    pub fn has_analysed(&self, col_ptr: &[usize], row_idx: &[usize]) -> bool {
        self.symbolic.is_some() && self.pattern == Some(PatternKey::of(col_ptr, row_idx))
    }

    /// Stored entries of the factor L.
    pub fn factor_nnz(&self) -> usize {
        self.symbolic.as_ref().map_or(0, |s| s.len_val())
    }

    /// Rows below the diagonal blocks, over all supernodes (a simplicial
    /// factor: its entries below the diagonal); 0 before the symbolic analysis.
    pub fn factor_slots(&self) -> usize {
        match self.symbolic.as_ref().map(|s| s.raw()) {
            None => 0,
            Some(SymbolicCholeskyRaw::Simplicial(s)) => s.row_idx().len().saturating_sub(s.nrows()),
            Some(SymbolicCholeskyRaw::Supernodal(s)) => (0..s.n_supernodes())
                .map(|k| s.supernode(k).pattern().len())
                .sum(),
        }
    }

    /// Stored values of the largest supernode (its `(m + q) x m` block: the
    /// diagonal block and the rows below it; a simplicial factor's largest
    /// column); 0 before the symbolic analysis. Where a factor is split over
    /// several buffers at supernode boundaries, the smallest piece possible.
    pub fn largest_supernode_nnz(&self) -> usize {
        let ptr = match self.symbolic.as_ref().map(|s| s.raw()) {
            None => return 0,
            Some(SymbolicCholeskyRaw::Simplicial(s)) => s.col_ptr(),
            Some(SymbolicCholeskyRaw::Supernodal(s)) => s.col_ptr_for_val(),
        };
        ptr.windows(2)
            .map(|w| (w[1] - w[0]) as usize)
            .max()
            .unwrap_or(0)
    }

    /// Floating-point operations of one numeric factorization, `sum_j c_j^2`
    /// over the factor's column counts `c_j` (0 before the symbolic analysis):
    /// a cost measure that is the same on every run, unlike a timing.
    pub fn factor_flops(&self) -> f64 {
        let Some(sym) = &self.symbolic else {
            return 0.0;
        };
        match sym.raw() {
            SymbolicCholeskyRaw::Simplicial(s) => s
                .col_ptr()
                .windows(2)
                .map(|w| ((w[1] - w[0]) as f64).powi(2))
                .sum(),
            SymbolicCholeskyRaw::Supernodal(s) => {
                let rows = s.col_ptr_for_row_idx();
                (0..s.n_supernodes())
                    .map(|k| {
                        let w = (s.supernode_end()[k] - s.supernode_begin()[k]) as f64;
                        let h = (rows[k + 1] - rows[k]) as f64;
                        // Column i of the supernode: w - i in its diagonal block, h below.
                        (0..w as usize)
                            .map(|i| (w - i as f64 + h).powi(2))
                            .sum::<f64>()
                    })
                    .sum()
            }
        }
    }

    /// Bytes held by the numeric factor.
    pub fn factor_bytes(&self) -> usize {
        self.numeric.len() * 8 + self.numeric32.len() * 4
    }
}

/// A numeric factor `P A P^T = L L^T` laid out by supernodes, in the precision
/// it was computed in, for triangular solves elsewhere (the GPU backend's
/// preconditioner).
///
/// Supernode `s` owns the columns `begin[s]..begin[s + 1]` (`m` of them) and the
/// rows below its diagonal block `rows[row_ptr[s]..row_ptr[s + 1]]` (`q`, in
/// the permuted numbering, ascending); its values are the dense column-major
/// `(m + q) x m` block at `values[val_ptr[s]..]`: the lower triangle of the
/// diagonal block in its first `m` rows, then the `q` rows below. Supernodes
/// come in topological order: every row below a supernode's diagonal block
/// belongs to a later supernode.
#[derive(Debug, Clone, Default)]
pub struct SupernodalFactor {
    /// `perm[new] = old`.
    pub perm: Vec<u32>,
    pub begin: Vec<u32>,
    pub row_ptr: Vec<u32>,
    pub rows: Vec<u32>,
    pub val_ptr: Vec<u64>,
    /// The values of an f32 factor (then `values64` is empty)...
    pub values: Vec<f32>,
    /// ... or of an f64 factor (then `values` is empty).
    pub values64: Vec<f64>,
    /// The diagonal blocks hold their inverses and the rows below them
    /// `L_rs L_ss^-1` ([`SupernodalFactor::invert_diagonal_blocks`]).
    pub inverted: bool,
}

impl SupernodalFactor {
    /// Supernodes.
    pub fn len(&self) -> usize {
        self.begin.len().saturating_sub(1)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Stored values.
    pub fn nnz(&self) -> usize {
        self.values.len() + self.values64.len()
    }

    /// Value `k` in f64.
    pub fn value(&self, k: usize) -> f64 {
        if self.values64.is_empty() {
            self.values[k] as f64
        } else {
            self.values64[k]
        }
    }

    /// Levels of the supernodal elimination tree: a supernode's parent owns
    /// its first row below the diagonal block; leaves are level 0, a parent
    /// one above its highest child (a GPU solves a level's supernodes at
    /// once). `None` where the factor is not in topological order.
    pub fn levels(&self) -> Option<Vec<u32>> {
        let ns = self.len();
        let n = self.perm.len();
        let mut owner = vec![0u32; n];
        for s in 0..ns {
            for c in self.begin[s]..self.begin[s + 1] {
                *owner.get_mut(c as usize)? = s as u32;
            }
        }
        let mut level = vec![0u32; ns];
        for s in 0..ns {
            let (a, b) = (self.row_ptr[s] as usize, self.row_ptr[s + 1] as usize);
            if a < b {
                let p = *owner.get(*self.rows.get(a)? as usize)? as usize;
                if p <= s {
                    return None;
                }
                level[p] = level[p].max(level[s] + 1);
            }
        }
        Some(level)
    }

    /// `(columns, rows below the diagonal block)` of supernode `s`.
    pub fn shape(&self, s: usize) -> (usize, usize) {
        (
            (self.begin[s + 1] - self.begin[s]) as usize,
            (self.row_ptr[s + 1] - self.row_ptr[s]) as usize,
        )
    }

    /// `P b`.
    fn permuted(&self, b: &[f64]) -> Vec<f64> {
        self.perm.iter().map(|&p| b[p as usize]).collect()
    }

    /// `P^T w`.
    fn unpermuted(&self, w: &[f64]) -> Vec<f64> {
        let mut x = vec![0.0; w.len()];
        for (i, &p) in self.perm.iter().enumerate() {
            x[p as usize] = w[i];
        }
        x
    }

    /// Supernode `s`: first column, columns, value offset, rows of its
    /// block, and the rows below its diagonal block.
    fn block(&self, s: usize) -> (usize, usize, usize, usize, &[u32]) {
        let (m, q) = self.shape(s);
        let rows = &self.rows[self.row_ptr[s] as usize..self.row_ptr[s + 1] as usize];
        (
            self.begin[s] as usize,
            m,
            self.val_ptr[s] as usize,
            m + q,
            rows,
        )
    }

    /// Replace each supernode's diagonal block `L_ss` by its inverse (lower
    /// triangular too, in place), and the rows below it `L_rs` by `B_s =
    /// L_rs L_ss^-1`: a solve then applies `L_ss^-1` as a product, parallel
    /// in all its rows, instead of a column-by-column substitution, and both
    /// products of a supernode's sweep read the same vector, so each sweep is
    /// one step per supernode (forward `y_s = L_ss^-1 w_s` and the updates
    /// `B_s w_s`; backward `x_s = L_ss^-T y_s - B_s^T x_r`). Done in parallel
    /// (faer, in the factor's precision).
    pub fn invert_diagonal_blocks(&mut self) {
        if self.inverted {
            return;
        }
        fn blocks<'a, T>(
            f: &SupernodalFactor,
            mut v: &'a mut [T],
        ) -> Vec<(usize, usize, &'a mut [T])> {
            let mut out = Vec::with_capacity(f.len());
            let mut at = 0;
            for s in 0..f.len() {
                let (m, q) = f.shape(s);
                let (a, b) = (f.val_ptr[s] as usize, f.val_ptr[s + 1] as usize);
                let rest = std::mem::take(&mut v);
                let (_, rest) = rest.split_at_mut(a - at);
                let (block, rest) = rest.split_at_mut(b - a);
                v = rest;
                at = b;
                out.push((m, m + q, block));
            }
            out
        }
        fn invert<T: faer::traits::ComplexField + Copy + Send>(
            items: Vec<(usize, usize, &mut [T])>,
        ) {
            use faer::linalg::matmul::triangular::{matmul, BlockStructure};
            use faer::prelude::{Reborrow, ReborrowMut};
            items.into_par_iter().for_each(|(m, nr, block)| {
                let par = if m >= 256 {
                    get_global_parallelism()
                } else {
                    faer::Par::Seq
                };
                let all = faer::MatMut::from_column_major_slice_with_stride_mut(block, nr, m, nr);
                let (mut diag, mut below) = all.split_at_row_mut(m);
                let src = diag.rb().to_owned();
                faer::linalg::triangular_inverse::invert_lower_triangular(
                    diag.rb_mut(),
                    src.as_ref(),
                    par,
                );
                if nr > m {
                    let l = below.rb().to_owned();
                    matmul(
                        below.rb_mut(),
                        BlockStructure::Rectangular,
                        faer::Accum::Replace,
                        l.as_ref(),
                        BlockStructure::Rectangular,
                        diag.rb(),
                        BlockStructure::TriangularLower,
                        T::one_impl(),
                        par,
                    );
                }
            });
        }
        let mut values = std::mem::take(&mut self.values);
        let mut values64 = std::mem::take(&mut self.values64);
        if !values.is_empty() {
            invert(blocks(self, &mut values));
        }
        if !values64.is_empty() {
            invert(blocks(self, &mut values64));
        }
        self.values = values;
        self.values64 = values64;
        self.inverted = true;
    }

    /// `x = P^T L^-T L^-1 P b` (the original numbering) for one column, in
    /// f64 (a reference for tests).
    pub fn solve(&self, b: &[f64]) -> Vec<f64> {
        if self.inverted {
            return self.solve_inverted(b);
        }
        let mut w = self.permuted(b);
        for s in 0..self.len() {
            let (c0, m, v, nr, rows) = self.block(s);
            for k in 0..m {
                w[c0 + k] /= self.value(v + k * nr + k);
                let x = w[c0 + k];
                for i in k + 1..m {
                    w[c0 + i] -= self.value(v + k * nr + i) * x;
                }
                for (r, &row) in rows.iter().enumerate() {
                    w[row as usize] -= self.value(v + k * nr + m + r) * x;
                }
            }
        }
        for s in (0..self.len()).rev() {
            let (c0, m, v, nr, rows) = self.block(s);
            for k in (0..m).rev() {
                let mut t = w[c0 + k];
                for i in k + 1..m {
                    t -= self.value(v + k * nr + i) * w[c0 + i];
                }
                for (r, &row) in rows.iter().enumerate() {
                    t -= self.value(v + k * nr + m + r) * w[row as usize];
                }
                w[c0 + k] = t / self.value(v + k * nr + k);
            }
        }
        self.unpermuted(&w)
    }
}

impl SupernodalFactor {
    /// [`SupernodalFactor::solve`] in the inverted form, as the GPU runs it:
    /// forward `y_s = L_ss^-1 w_s` and `w_r -= B_s w_s` (`w_s` after its
    /// descendants' updates), backward `x_s = L_ss^-T y_s - B_s^T x_r`.
    fn solve_inverted(&self, b: &[f64]) -> Vec<f64> {
        let mut w = self.permuted(b);
        for s in 0..self.len() {
            let (c0, m, v, nr, rows) = self.block(s);
            let ws = w[c0..c0 + m].to_vec();
            for (i, wi) in w[c0..c0 + m].iter_mut().enumerate() {
                *wi = (0..=i).map(|k| self.value(v + k * nr + i) * ws[k]).sum();
            }
            for (r, &row) in rows.iter().enumerate() {
                let d: f64 = (0..m).map(|k| self.value(v + k * nr + m + r) * ws[k]).sum();
                w[row as usize] -= d;
            }
        }
        for s in (0..self.len()).rev() {
            let (c0, m, v, nr, rows) = self.block(s);
            let x: Vec<f64> = (0..m)
                .map(|k| {
                    let diag: f64 = (k..m).map(|i| self.value(v + k * nr + i) * w[c0 + i]).sum();
                    let below: f64 = rows
                        .iter()
                        .enumerate()
                        .map(|(r, &row)| self.value(v + k * nr + m + r) * w[row as usize])
                        .sum();
                    diag - below
                })
                .collect();
            w[c0..c0 + m].copy_from_slice(&x);
        }
        self.unpermuted(&w)
    }
}

impl CholeskySolver {
    /// The numeric factor by supernodes (a simplicial factor as one-column
    /// supernodes), its values moved out (no copy: the solver is unfactored
    /// after it, its symbolic analysis kept); `None` before a factorization.
    pub fn take_supernodal_factor(&mut self) -> Option<SupernodalFactor> {
        if let Some(f) = self.taken_inverted.take() {
            self.factored = false;
            return Some(f);
        }
        if !self.factored {
            return None;
        }
        let mut f = self.supernodal_structure()?;
        f.values = std::mem::take(&mut self.numeric32);
        f.values64 = std::mem::take(&mut self.numeric);
        self.factored = false;
        Some(f)
    }

    /// The factor's structure by supernodes, as
    /// [`CholeskySolver::take_supernodal_factor`] lays it out, without
    /// values (for a numeric factorization elsewhere: the GPU's); `None`
    /// before the symbolic analysis.
    pub fn supernodal_structure(&self) -> Option<SupernodalFactor> {
        let sym = self.symbolic.as_ref()?;
        // The analysed pattern's order (`self.n` is the last factored one's).
        let perm = sym.forward().to_vec();
        let n = perm.len();
        let mut f = SupernodalFactor {
            perm,
            ..Default::default()
        };
        match sym.raw() {
            SymbolicCholeskyRaw::Simplicial(s) => {
                let (cp, ri) = (s.col_ptr(), s.row_idx());
                f.begin = (0..=n as u32).collect();
                f.row_ptr.push(0);
                f.val_ptr.push(0);
                for j in 0..n {
                    let (a, b) = (cp[j] as usize, cp[j + 1] as usize);
                    if b <= a || ri[a] as usize != j {
                        return None;
                    }
                    f.rows.extend_from_slice(&ri[a + 1..b]);
                    f.row_ptr.push(f.rows.len() as u32);
                    f.val_ptr.push(b as u64);
                }
                // Column-major columns, diagonal first: already the layout.
            }
            SymbolicCholeskyRaw::Supernodal(s) => {
                let ns = s.n_supernodes();
                let vp = s.col_ptr_for_val();
                f.begin = s.supernode_begin().to_vec();
                f.begin.push(n as u32);
                f.row_ptr.push(0);
                f.val_ptr.push(0);
                for k in 0..ns {
                    let pattern = s.supernode(k).pattern();
                    let m = (f.begin[k + 1] - f.begin[k]) as usize;
                    if (vp[k + 1] - vp[k]) as usize != m * (m + pattern.len()) {
                        return None;
                    }
                    f.rows.extend_from_slice(pattern);
                    f.row_ptr.push(f.rows.len() as u32);
                    f.val_ptr.push(vp[k + 1] as u64);
                }
            }
        }
        Some(f)
    }

    /// Takes the factor in supernodal form and inverts its diagonal blocks
    /// ([`SupernodalFactor::invert_diagonal_blocks`]) here, on the calling
    /// thread; [`CholeskySolver::take_supernodal_factor`] then returns it.
    /// The solver still counts as factored (of its pattern, on its
    /// analysis) until then, but its own solves have no factor to read: for
    /// a factor made ahead on another thread for a GPU, which applies the
    /// inverted form and would otherwise invert it on the thread that
    /// uploads it (0.3-0.6 s at homer 1.2M on the development machine).
    pub fn invert_taken(&mut self) {
        if let Some(mut f) = self.take_supernodal_factor() {
            f.invert_diagonal_blocks();
            self.taken_inverted = Some(f);
            self.factored = true;
        }
    }

    /// [`CholeskySolver::invert_taken`] where the plan asked for it.
    fn invert_taken_if_wanted(&mut self) {
        if self.invert_when_factored {
            self.invert_taken();
        }
    }
}

/// The pattern of `a` with u32 indices, or an error naming the limit.
fn pattern_u32(a: &SymCsc) -> Result<(Vec<u32>, Vec<u32>), SolverError> {
    if a.row_idx.len() > u32::MAX as usize || a.n > u32::MAX as usize {
        return Err(SolverError::Backend(format!(
            "matrix of {} unknowns and {} stored entries exceeds the Cholesky's 32-bit indices",
            a.n,
            a.row_idx.len()
        )));
    }
    Ok((
        a.col_ptr.iter().map(|&v| v as u32).collect(),
        a.row_idx.iter().map(|&v| v as u32).collect(),
    ))
}

/// Numeric LL^T factorization of the lower triangle `(pattern, values)` into
/// `out` by faer, one supernode or column after the other: false when the
/// matrix is not positive definite (in precision `T`).
fn factor_numeric<T: faer::traits::RealField + Copy>(
    sym: &SymbolicFactor,
    out: &mut [T],
    pattern: SymbolicSparseColMatRef<'_, u32>,
    values: &[T],
    par: faer::Par,
) -> Result<bool, SolverError> {
    sym.factorize_numeric_llt(out, SparseColMatRef::new(pattern, values), par)
        .ok_or(SolverError::OutOfMemory)
}

/// Sequential triangular solves `L L^T X = B` in place for the columns of `chunk`.
fn solve_columns<T: faer::traits::RealField + Copy>(
    sym: &SymbolicFactor,
    numeric: &[T],
    chunk: &mut [T],
) -> bool {
    sym.solve_in_place(numeric, chunk, faer::Par::Seq)
}

/// Solves the columns of `rhs` with the columns split among rayon threads, each
/// solve sequential: the triangular solves are memory-bound, and faer's own
/// parallel split is slower here. False when scratch memory was not available.
fn solve_split<T: faer::traits::RealField + Copy + Send + Sync>(
    sym: &SymbolicFactor,
    numeric: &[T],
    rhs: &mut [T],
    n: usize,
    ncols: usize,
) -> bool {
    let threads = rayon::current_num_threads().max(1);
    let per = ncols.div_ceil(threads).max(1);
    let failed = std::sync::atomic::AtomicBool::new(false);
    rayon::scope(|scope| {
        for chunk in rhs.chunks_mut(n * per) {
            let failed = &failed;
            scope.spawn(move |_| {
                if !solve_columns(sym, numeric, chunk) {
                    failed.store(true, std::sync::atomic::Ordering::Relaxed);
                }
            });
        }
    });
    !failed.into_inner()
}

impl CholeskySolver {
    /// The symbolic analysis of `a`'s pattern (ordering, elimination tree,
    /// supernodes) where it is new: the factor's size is known from here on
    /// ([`CholeskySolver::factor_nnz`]) before any numeric factorization.
    pub fn analyse(&mut self, a: &SymCsc) -> Result<(), SolverError> {
        let key = PatternKey::of(&a.col_ptr, &a.row_idx);
        let same = self.pattern == Some(key);
        // faer works on u32 indices here: its symbolic factor (supernode row
        // patterns, permutation, update lists) then takes half the memory; the
        // u32 copy of the pattern lives for this call only.
        let (col_ptr32, row_idx32) = pattern_u32(a)?;
        let sym_ref = SymbolicSparseColMatRef::new_checked(a.n, a.n, &col_ptr32, None, &row_idx32);
        if !same || self.symbolic.is_none() {
            let t0 = std::time::Instant::now();
            let given = match &self.ordering {
                FillOrdering::Given(fwd) => {
                    // A block-row ordering of a 3x3-block matrix's scalar form.
                    let fwd: Vec<usize> = if fwd.len() * 3 == a.n {
                        fwd.iter()
                            .flat_map(|&v| [3 * v, 3 * v + 1, 3 * v + 2])
                            .collect()
                    } else {
                        fwd.to_vec()
                    };
                    let inv = inverse_permutation(&fwd, a.n);
                    if inv.is_none() {
                        log::warn!(
                            "given fill ordering is not a permutation of {} unknowns; ignored",
                            a.n
                        );
                    }
                    inv.map(|inv| (fwd, inv))
                }
                _ => None,
            };
            let nd = match &self.ordering {
                FillOrdering::Amd => false,
                FillOrdering::NestedDissection => true,
                FillOrdering::Auto | FillOrdering::Given(_) => a.n >= NESTED_DISSECTION_FROM,
            };
            let perm = if given.is_some() {
                given
            } else if nd {
                nested_dissection(a)
            } else {
                None
            };
            let ordering_seconds = t0.elapsed().as_secs_f64();
            let perm32: Option<(Vec<u32>, Vec<u32>)> = perm.map(|(fwd, inv)| {
                (
                    fwd.iter().map(|&v| v as u32).collect(),
                    inv.iter().map(|&v| v as u32).collect(),
                )
            });
            let ordering = match &perm32 {
                Some((fwd, inv)) => {
                    SymmetricOrdering::Custom(faer::perm::PermRef::new_checked(fwd, inv, a.n))
                }
                None => SymmetricOrdering::Amd,
            };
            let symbolic_params = faer::sparse::linalg::cholesky::CholeskySymbolicParams {
                supernodal_flop_ratio_threshold: if self.supernodal {
                    faer::sparse::linalg::SupernodalThreshold::FORCE_SUPERNODAL
                } else {
                    faer::sparse::linalg::SupernodalThreshold::AUTO
                },
                ..Default::default()
            };
            let (sym, parts) =
                analyse_pattern(sym_ref, ordering, symbolic_params).map_err(|e| {
                    SolverError::Backend(format!(
                        "symbolic Cholesky of {} unknowns: {e:?} (the factor's entries must be \
                             indexable by 32-bit integers)",
                        a.n
                    ))
                })?;
            // The values' storage is made by the numeric factorization
            // (`prepare`), where one is made: a numeric twin may make it
            // instead ([`CholeskySolver::numeric_twin`]).
            self.numeric = Vec::new();
            self.numeric32 = Vec::new();
            let nnz_l = sym.len_val();
            let structure = match sym.raw() {
                SymbolicCholeskyRaw::Supernodal(_) => "supernodes",
                SymbolicCholeskyRaw::Simplicial(_) => "simplicial structure",
            };
            self.symbolic = Some(Arc::new(sym));
            self.pattern = Some(key);
            self.symbolic_count += 1;
            log::debug!(
                "Cholesky symbolic analysis: n {}, nnz(A) {}, nnz(L) {} ({}, {}), {:.3} s (ordering {:.3} s, \
                 elimination tree and column counts {:.3} s, {} {:.3} s)",
                a.n,
                a.row_idx.len(),
                nnz_l,
                if self.single { "f32" } else { "f64" },
                match (&self.ordering, &perm32) {
                    (_, None) => "AMD",
                    (FillOrdering::Given(_), Some(_)) => "given",
                    (_, Some(_)) => "nested dissection",
                },
                t0.elapsed().as_secs_f64(),
                ordering_seconds,
                parts.tree_and_counts,
                structure,
                parts.structure
            );
            // A given ordering has served (the symbolic factor keeps its own copy
            // of the permutation): release it, 8 bytes per unknown; a later
            // pattern gets the `Auto` choice.
            if matches!(self.ordering, FillOrdering::Given(_)) {
                self.ordering = FillOrdering::Auto;
            }
        }
        Ok(())
    }
}

impl CholeskySolver {
    /// The numeric factor's storage, where `take_supernodal_factor` moved
    /// it out (or a new analysis resized it).
    fn numeric_storage(&mut self) -> Result<(), SolverError> {
        let len = self.symbolic.as_ref().map_or(0, |s| s.len_val());
        let storage = if self.single {
            self.numeric32.len()
        } else {
            self.numeric.len()
        };
        if storage != len {
            self.numeric = Vec::new();
            self.numeric32 = Vec::new();
            if self.single {
                self.numeric32
                    .try_reserve_exact(len)
                    .map_err(|_| SolverError::OutOfMemory)?;
                self.numeric32.resize(len, 0.0);
            } else {
                self.numeric
                    .try_reserve_exact(len)
                    .map_err(|_| SolverError::OutOfMemory)?;
                self.numeric.resize(len, 0.0);
            }
        }
        Ok(())
    }

    /// A numeric factorization of an `n`-unknown matrix, begun at `t`, ended.
    fn numeric_done(
        &mut self,
        factored: bool,
        n: usize,
        t: std::time::Instant,
    ) -> Result<(), SolverError> {
        if !factored {
            return Err(SolverError::NotPositiveDefinite);
        }
        self.numeric_seconds = t.elapsed().as_secs_f64();
        self.factored = true;
        self.n = n;
        self.numeric_count += 1;
        Ok(())
    }

    /// [`SpdSolver::prepare`] taking `a`: where the factor is made on the
    /// elimination tree ([`crate::tree_factor`], f64), `a` and its index
    /// copies are dropped once its permuted lower triangle is made, before
    /// the factor's storage is (homer 1.2M's `K`: about 125 MB less beside
    /// its 1.1 GiB factor). Else as `prepare(&a)`.
    pub fn prepare_owned(&mut self, a: SymCsc) -> Result<(), SolverError> {
        self.analyse(&a)?;
        let sym = self.symbolic.clone().unwrap();
        if self.single
            || self.sequential_supernodes
            || !matches!(sym.raw(), SymbolicCholeskyRaw::Supernodal(_))
        {
            return self.prepare(&a);
        }
        let n = a.n;
        let permuted = {
            let (col_ptr32, row_idx32) = pattern_u32(&a)?;
            let sym_ref = SymbolicSparseColMatRef::new_checked(n, n, &col_ptr32, None, &row_idx32);
            permute_lower(&sym, sym_ref, &a.values)
        };
        drop(a);
        self.numeric_storage()?;
        self.factored = false;
        let t = std::time::Instant::now();
        let factored =
            factor_permuted(&sym, &mut self.numeric, &permuted, get_global_parallelism())
                .unwrap_or(false);
        drop(permuted);
        self.numeric_done(factored, n, t)
    }
}

impl SpdSolver for CholeskySolver {
    fn set_fill_ordering(&mut self, ordering: FillOrdering) {
        if ordering != self.ordering {
            self.ordering = ordering;
            self.symbolic = None;
        }
    }

    fn prepare(&mut self, a: &SymCsc) -> Result<(), SolverError> {
        self.analyse(a)?;
        let (col_ptr32, row_idx32) = pattern_u32(a)?;
        let sym_ref = SymbolicSparseColMatRef::new_checked(a.n, a.n, &col_ptr32, None, &row_idx32);
        self.numeric_storage()?;
        let sym = self.symbolic.as_ref().unwrap();
        let par = get_global_parallelism();
        self.factored = false;
        let t_numeric = std::time::Instant::now();
        // A supernodal factor's independent subtrees on rayon's threads
        // ([`crate::tree_factor`]); a simplicial one by faer.
        let values32: Vec<f32> = if self.single {
            a.values.iter().map(|&v| v as f32).collect()
        } else {
            Vec::new()
        };
        let tree = if self.sequential_supernodes {
            None
        } else if self.single {
            factor_numeric_tree(sym, &mut self.numeric32, sym_ref, &values32, par)
        } else {
            factor_numeric_tree(sym, &mut self.numeric, sym_ref, &a.values, par)
        };
        let factored = match tree {
            Some(factored) => factored,
            // Its scratch is for this factorization only: at a million
            // faces it is tens of MiB that would otherwise stay resident
            // beside the factor.
            None if self.single => {
                factor_numeric(sym, &mut self.numeric32, sym_ref, &values32, par)?
            }
            None => factor_numeric(sym, &mut self.numeric, sym_ref, &a.values, par)?,
        };
        drop(values32);
        self.numeric_done(factored, a.n, t_numeric)
    }

    fn prepare_blocks(&mut self, a: &BlockSym3, fixed: &[bool]) -> Result<(), SolverError> {
        a.check_fixed(fixed)?;
        let key = PatternKey::of(&a.col_ptr, &a.row_idx);
        if !matches!(&self.block_scalar, Some((k, _)) if *k == key) {
            self.block_scalar = Some((key, a.scalar_pattern()));
        }
        let mut scalar = std::mem::take(&mut self.block_scalar.as_mut().unwrap().1);
        a.fill_scalar(&mut scalar, fixed);
        let r = self.prepare(&scalar);
        self.block_scalar.as_mut().unwrap().1 = scalar;
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
        let sym = self.symbolic.as_ref().unwrap();
        let n = self.n;
        self.solves += 1;
        let solved = if self.single {
            self.buf32.clear();
            self.buf32.extend(rhs.iter().map(|&v| v as f32));
            let ok = solve_split(sym, &self.numeric32, &mut self.buf32, n, ncols);
            for (o, &v) in rhs.iter_mut().zip(&self.buf32) {
                *o = v as f64;
            }
            ok
        } else {
            solve_split(sym, &self.numeric, rhs, n, ncols)
        };
        if !solved {
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

    fn counters(&self) -> WorkCounters {
        WorkCounters {
            preconditioner_setups: self.numeric_count,
            solves: self.solves,
            ..WorkCounters::default()
        }
    }

    fn name(&self) -> &str {
        "cpu"
    }
}
