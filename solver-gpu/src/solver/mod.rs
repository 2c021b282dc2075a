//! The solver behind [`solver_cpu::SpdSolver`]: opens the device, and per
//! solve runs the refinement rounds of the crate docs. Its parts:
//! [`upload`] (each matrix: pattern once, values per matrix), [`setup`]
//! (the preconditioner, once per system kind) and [`mixed`] (the
//! mixed-precision rounds, residuals formed on the GPU where it can).

use device::Context;
use matrix::{GpuMatrix, HostMatrix, RingSlots};
use pcg::{Spmv, Workspace};
use solver_cpu::{
    BlockSym3, IsoRingSym3, ShapeOperatorModel, SolveInfo, SolverError, SpdSolver, SymCsc,
    SystemKind, WorkCounters,
};
use std::sync::{Arc, Mutex};

use crate::precision::{MixedPrecision, RoundWatch};
use crate::{
    amg, amg_gpu, block_jacobi, bsr_spmv, convert, csr_spmv, default_adapter, device, dot,
    expand_blocks, matrix, pcg, power_sum_newton, precision, refine, supernodal, AdapterSummary,
    OpenOptions,
};
use crate::{GpuError, Preconditioner, CMAX, SQUARED_LAPLACIAN_SWEEPS};

mod mixed;
mod newton;
mod setup;
mod upload;
mod warm;

/// From this many of rayon's threads on, uploads go up on threads of their
/// own, beside the caller: a factor made ahead
/// ([`GpuSolver::upload_factor_ahead`]), the shape sum's ring pairs
/// ([`GpuSolver::start_pairs_ahead`]) and the shape matrices' pattern
/// ([`GpuSolver::start_pattern_ahead`]). Below, on the caller's thread. On the
/// development machine's 2 cores at homer 1.2M, lavapipe, those threads
/// shared the cores with the main thread's own passes and with lavapipe's
/// copies:
/// - the scale-driven factor's upload took 0.7-0.95 s in three runs and
///   1.9-3.9 s in four (0.60 and 2.96 s in two runs on the main thread:
///   lavapipe's copies vary that much);
/// - the first matrix's diagonal blocks took 0.53-0.76 s against 0.2-0.33 s;
/// - the main thread took 1.6-4.2 s from the first scale factors to the
///   first solve, against 2.4 s before.
pub(crate) const BESIDE_UPLOADS_FROM_THREADS: usize = 4;

/// `thread`'s value, its panic carried on to the caller.
fn joined<T>(thread: std::thread::JoinHandle<T>) -> T {
    match thread.join() {
        Ok(value) => value,
        Err(panic) => std::panic::resume_unwind(panic),
    }
}

use mixed::{floor_after_a_round, BatchHints, MixedData, MixedKernels, Round};
use upload::SquareAhead;

/// Whether some adapter is available.
pub fn gpu_available() -> bool {
    default_adapter().is_ok()
}

/// The device [`open`] opens, being opened on its own thread
/// ([`open_ahead`]).
type OpeningAhead = std::thread::JoinHandle<Result<Context, GpuError>>;
static OPENING_AHEAD: Mutex<Option<OpeningAhead>> = Mutex::new(None);

/// Starts opening the device that [`open`] opens, on its own thread, while
/// the caller goes on (reading its mesh): the next [`open`] takes it. The
/// adapter and device took 0.16-0.18 s on the H200, before any of a run's
/// set-up that needs the GPU. Where it is not taken, [`drop_opened_ahead`]
/// ends it.
pub fn open_ahead() {
    let mut slot = OPENING_AHEAD.lock().unwrap_or_else(|e| e.into_inner());
    if slot.is_none() {
        *slot = std::thread::Builder::new()
            .name("GPU device opened ahead".into())
            .spawn(|| Context::open(&OpenOptions::default()))
            .ok();
    }
}

/// Waits for a device [`open_ahead`] started and not taken, and closes it
/// (before the process ends: not in the middle of the driver's set-up).
pub fn drop_opened_ahead() {
    let ahead = OPENING_AHEAD
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .take();
    if let Some(thread) = ahead {
        drop(joined(thread));
    }
}

/// Open the GPU solver on the adapter named by `WGPU_ADAPTER_NAME`
/// (case-insensitive substring) or wgpu's default high-performance adapter, with
/// the adapter's own limits; the one [`open_ahead`] started, where it did.
pub fn open() -> Result<GpuSolver, GpuError> {
    let t = std::time::Instant::now();
    let ahead = OPENING_AHEAD
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .take();
    match ahead {
        Some(thread) => on_context(joined(thread)?, t),
        None => open_with(OpenOptions::default()),
    }
}

/// [`open`] with options (adapter name, lowered limits).
pub fn open_with(opts: OpenOptions) -> Result<GpuSolver, GpuError> {
    let t = std::time::Instant::now();
    let ctx = Context::open(&opts)?;
    on_context(ctx, t)
}

impl GpuSolver {
    /// Another solver on this one's device (its own context on the same
    /// device and queue, with its own counts), with this one's tolerance:
    /// for a second system of the run.
    pub fn sibling_solver(&self) -> Result<GpuSolver, GpuError> {
        let mut s = on_context(self.ctx.sibling(), std::time::Instant::now())?;
        s.tol = self.tol;
        s.factor_kernels = self.factor_kernels.clone();
        Ok(s)
    }
}

/// A solver on `ctx`, opened from `t`: its kernels' shader modules made.
fn on_context(ctx: Context, t: std::time::Instant) -> Result<GpuSolver, GpuError> {
    let device_seconds = t.elapsed().as_secs_f64();
    let kernels = Kernels {
        bsr: bsr_spmv::new(&ctx)?,
        csr: csr_spmv::new(&ctx)?,
        dot: dot::Dot::new(&ctx)?,
        jacobi: block_jacobi::BlockJacobi::new(&ctx)?,
        pcg: pcg::Pcg::new(&ctx, precision::Precision::F32)?,
        amg: amg_gpu::AmgKernels::new(&ctx)?,
    };
    ctx.check()?;
    log::debug!(
        "GPU solver opened in {:.3} s: adapter and device {device_seconds:.3} s, the kernels' \
         shader modules {:.3} s",
        t.elapsed().as_secs_f64(),
        t.elapsed().as_secs_f64() - device_seconds
    );
    let factorization = crate::Factorization::asked().unwrap_or_else(|| {
        crate::Factorization::on_parts(
            ctx.info.device_type == wgpu::DeviceType::Cpu,
            ctx.shader_f64,
        )
    });
    Ok(GpuSolver {
        ctx: Arc::new(ctx),
        k: kernels,
        host: None,
        gpu: None,
        ws: None,
        tol: 1e-10,
        inner_min: 1e-5,
        max_iterations: 50_000,
        max_rounds: 20,
        check_every: 32,
        stats: SolveStats::default(),
        pattern_uploads: 0,
        value_uploads: 0,
        preconditioner: Preconditioner::from_env(),
        amg_opts: amg::AmgOptions::default(),
        amg_host: None,
        amg_gpu: None,
        amg_fine_upload: 0,
        amg_setup_seconds: 0.0,
        positions: None,
        mixed_precision: MixedPrecision::from_env(),
        mixed_kernels: None,
        mixed: None,
        mixed_sticky: false,
        kind: SystemKind::default(),
        amg_kind: None,
        setups: 0,
        setups_ahead: 0,
        work: WorkCounters::default(),
        amg_kept: false,
        hints: BatchHints::default(),
        shape_model: None,
        fixed: Vec::new(),
        squared: None,
        ring_slots: None,
        expand_lower: None,
        shape_sum: None,
        square: None,
        square_values: None,
        square_ahead: None,
        squares_taken_ahead: 0,
        pairs_ahead: None,
        pairs_taken_ahead: 0,
        pattern_ahead: None,
        patterns_taken_ahead: 0,
        beside_uploads: rayon::current_num_threads() >= BESIDE_UPLOADS_FROM_THREADS,
        minv_scratch: Vec::new(),
        diagonal_current: false,
        expand: None,
        expansion: None,
        mixed_builds: 0,
        host_residuals: 0,
        host_residual: Vec::new(),
        matrices: 0,
        lower_of: None,
        expansions: 0,
        chol: None,
        chol_kind: None,
        chol_kernels: None,
        factorization,
        factor_kernels: Default::default(),
        gpu_factor_ahead: None,
        chol_host: {
            let mut c = solver_cpu::CholeskySolver::single_precision();
            c.supernodal = true;
            c
        },
        chol_unavailable: [false; 2],
        gpu_factor_refused: [false; 2],
        factor_recording: None,
        factor_recorded: None,
        chol_ahead: None,
        newton_kernels: None,
        warming: Vec::new(),
        factor_warming: Vec::new(),
        newton: None,
    })
}

pub(crate) struct Kernels {
    pub bsr: bsr_spmv::BsrSpmv,
    pub csr: csr_spmv::CsrSpmv,
    pub dot: dot::Dot,
    pub jacobi: block_jacobi::BlockJacobi,
    pub pcg: pcg::Pcg,
    pub amg: amg_gpu::AmgKernels,
}

/// Counters of the last solve.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SolveStats {
    /// Refinement rounds (f64 residual evaluations that launched a GPU solve).
    pub rounds: usize,
    /// PCG iterations summed over rounds (largest column of each batch).
    pub iterations: usize,
    /// Largest final relative residual (f64).
    pub residual: f64,
    /// Whether the solve switched to mixed precision (f64 PCG, f32 V-cycle).
    pub mixed: bool,
    /// Rounds of f32 refinement (the rest of `rounds` ran in mixed precision).
    pub f32_rounds: usize,
}

/// The GPU PCG solver.
pub struct GpuSolver {
    pub(crate) ctx: Arc<Context>,
    pub(crate) k: Kernels,
    pub(crate) host: Option<HostMatrix>,
    pub(crate) gpu: Option<GpuMatrix>,
    pub(crate) ws: Option<Workspace>,
    tol: f64,
    inner_min: f64,
    max_iterations: usize,
    max_rounds: usize,
    pub(crate) check_every: usize,
    stats: SolveStats,
    /// How many times a matrix pattern was uploaded (tests, benchmarks).
    pub pattern_uploads: usize,
    /// How many times only the values were rewritten.
    pub value_uploads: usize,
    preconditioner: Preconditioner,
    amg_opts: amg::AmgOptions,
    /// The AMG hierarchy of the prepared matrix (`None`: block Jacobi in use).
    amg_host: Option<amg::Hierarchy>,
    pub(crate) amg_gpu: Option<amg_gpu::GpuHierarchy>,
    /// `pattern_uploads` when `amg_gpu` was uploaded (its finest `A` is the
    /// matrix of that upload).
    amg_fine_upload: usize,
    amg_setup_seconds: f64,
    /// Vertex positions of the block rows (the affine near-null space).
    positions: Option<Vec<[f64; 3]>>,
    mixed_precision: MixedPrecision,
    /// The f64 kernels of the mixed-precision solve (compiled on first use).
    mixed_kernels: Option<MixedKernels>,
    /// Its matrix and workspace, for the stamp's matrix.
    pub(crate) mixed: Option<MixedData>,
    /// A solve of the current pattern fell back to mixed precision: the next
    /// ones start there (reset by a new pattern).
    mixed_sticky: bool,
    /// The kind of system being prepared ([`SpdSolver::set_system_kind`]).
    kind: SystemKind,
    /// The kind the AMG hierarchy was built for: a new matrix of that kind and
    /// pattern keeps it (only the finest smoother's diagonal is rewritten).
    amg_kind: Option<SystemKind>,
    /// Preconditioner set-ups (AMG hierarchy builds, block-Jacobi
    /// inverses when AMG is off or failed).
    pub(crate) setups: usize,
    /// Of `setups`, those that took a factor made ahead (`chol_ahead`).
    setups_ahead: usize,
    /// Solves and iterations.
    work: WorkCounters,
    /// The hierarchy was kept for new values ([`Self::upload`]): a solve
    /// that fails with it rebuilds it and tries once more.
    amg_kept: bool,
    /// First batch sizes from the last runs of each kind.
    hints: BatchHints,
    /// The model of the next shape matrices ([`SpdSolver::set_shape_model`]).
    shape_model: Option<std::sync::Arc<ShapeOperatorModel>>,
    /// Held block rows of the prepared block matrix.
    fixed: Vec<bool>,
    /// The squared-Laplacian preconditioner in use (its hierarchy is
    /// `amg_host` / `amg_gpu`): the model it was built from and `Mt` per
    /// block row on the GPU.
    pub(crate) squared: Option<(std::sync::Arc<ShapeOperatorModel>, wgpu::Buffer)>,
    /// The ring pairs' slots of the shape matrices' pattern
    /// ([`SpdSolver::prepare_shape_owned`]).
    ring_slots: Option<Arc<RingSlots>>,
    /// The f64 lower blocks of the uploaded block pattern (its stamp), which
    /// the expansions read and the shape sum writes.
    expand_lower: Option<(usize, expand_blocks::LowerParts)>,
    /// The shape sum of the uploaded pattern (its stamp) and rings.
    pub(crate) shape_sum: Option<(usize, expand_blocks::ShapeSum)>,
    /// The host's parts of the Laplacian square term the shape matrices
    /// name ([`IsoRingSym3::laplacian_square`]; made once per model), and
    /// its values until the shape sum takes them up.
    square: Option<Arc<matrix::SquareParts>>,
    square_values: Option<Vec<f64>>,
    /// That term's values being summed on another thread, for the model and
    /// ring slots named ([`Self::start_square_values`]).
    pub(crate) square_ahead: Option<SquareAhead>,
    /// Such values taken by [`Self::square_parts`] (for the tests).
    pub(crate) squares_taken_ahead: usize,
    /// The shape sum's ring pairs going up on their own thread
    /// ([`Self::start_pairs_ahead`]), and how many such the sums took.
    pairs_ahead: Option<upload::PairsAhead>,
    pub(crate) pairs_taken_ahead: usize,
    /// The shape matrices' pattern being set up on its own thread
    /// ([`Self::start_pattern_ahead`]), and how many patterns were taken
    /// up so.
    pattern_ahead: Option<upload::PatternAhead>,
    pub(crate) patterns_taken_ahead: usize,
    /// Whether uploads go up on threads beside the caller: from
    /// [`BESIDE_UPLOADS_FROM_THREADS`] of rayon's threads (the tests set it
    /// either way).
    pub(crate) beside_uploads: bool,
    /// The f32 inverse diagonal blocks of the last matrix uploaded, kept
    /// for the next one's (`block_jacobi::inverse_diagonal`); not kept where
    /// a Cholesky factor preconditions the kind ([`Self::upload`]).
    pub(crate) minv_scratch: Vec<f32>,
    /// Whether the GPU's inverse diagonal blocks (and the host's in
    /// `minv_scratch`) are the uploaded matrix's: not where the kind's
    /// Cholesky factor preconditions it ([`Self::upload`]).
    diagonal_current: bool,
    /// New values of a prepared block pattern go up as their lower triangle
    /// in f64 and are expanded on the GPU (needs `SHADER_F64`): the kernel,
    /// and the recorded expansion with what it was recorded for
    /// (`pattern_uploads`, whether it writes the mixed matrix's low parts,
    /// the held rows).
    expand: Option<expand_blocks::ExpandBlocks>,
    pub(crate) expansion: Option<(expand_blocks::Expansion, usize, Option<usize>, Vec<bool>)>,
    /// Mixed-precision matrices built (each has its own low-part buffers).
    pub(crate) mixed_builds: usize,
    /// Residuals `b - A x` formed on the host (the f32 refinement's; the
    /// mixed-precision solve forms them on the GPU).
    pub(crate) host_residuals: usize,
    /// The residuals of the mixed-precision rounds formed on the host
    /// ([`Self::mixed_rounds_host`]), kept between solves.
    host_residual: Vec<f64>,
    /// Matrices uploaded ([`Self::upload`] calls), and the one whose f64
    /// lower blocks the GPU holds (summed or expanded there).
    matrices: usize,
    lower_of: Option<usize>,
    /// Expansions made (each with its own block map).
    pub(crate) expansions: usize,
    /// The Cholesky preconditioner's factor on the GPU
    /// ([`Preconditioner::Cholesky`]), the kind it was made for, its kernels,
    /// and the host factorization (its symbolic analysis serves every kind of
    /// the same pattern).
    pub(crate) chol: Option<supernodal::GpuFactor>,
    chol_kind: Option<SystemKind>,
    chol_kernels: Option<std::sync::Arc<supernodal::SupernodalKernels>>,
    /// Where the factors are made, and the GPU factorization's kernels once
    /// made: shared with the solvers' siblings on the device, so that each
    /// pipeline is compiled once a run.
    factorization: crate::Factorization,
    factor_kernels: Arc<Mutex<Option<Arc<crate::factorize::FactorKernels>>>>,
    /// A kind's factor submitted to the GPU ahead of its set-up.
    gpu_factor_ahead: Option<(SystemKind, setup::GpuMade)>,
    /// A kind's factorization on the GPU recorded ahead of its submission
    /// (`prepare_factor_on_device`).
    factor_recorded: Option<setup::GpuMade>,
    /// The scale-driven kind's factorization on the GPU, kept for the
    /// fine-tune's.
    factor_recording: Option<setup::FactorRecording>,
    pub(crate) chol_host: solver_cpu::CholeskySolver,
    /// The factor could not be made or kept on this device, for the shape
    /// systems (index 0) or the scale factors (index 1): the squared Laplacian or AMG
    /// serves instead for the rest of the run.
    chol_unavailable: [bool; 2],
    /// The GPU refused to make the factor (over its value buffers, or a CPU
    /// adapter's loop limit), for the shape systems (index 0) or the scale
    /// factors (index 1): the host makes it for the rest of the run.
    pub(crate) gpu_factor_refused: [bool; 2],
    /// A shape kind's factor of `K` made ahead on another thread and
    /// uploaded on its own ([`SpdSolver::adopt_isotropic_factor`]), for that
    /// kind's set-up.
    chol_ahead: Option<(SystemKind, setup::FactorUpload)>,
    /// The scale factors' Newton steps on the device
    /// ([`SpdSolver::power_sum_newton`]): the kernels (compiled on first
    /// use) and the buffers of the last problem size.
    /// Threads compiling pipelines ahead ([`SpdSolver::warm_up`]), by kind.
    warming: Vec<(SystemKind, std::thread::JoinHandle<()>)>,
    /// The threads compiling the GPU factorization's pipelines ahead, apart
    /// from the rest of their kind's: a factorization waits for these alone.
    factor_warming: Vec<std::thread::JoinHandle<()>>,
    newton_kernels: Option<power_sum_newton::NewtonKernels>,
    newton: Option<power_sum_newton::NewtonData>,
}

impl GpuSolver {
    /// Name of the adapter in use.
    pub fn adapter_name(&self) -> &str {
        &self.ctx.info.name
    }

    /// The adapter in use.
    pub fn adapter(&self) -> AdapterSummary {
        AdapterSummary::of(&self.ctx.info, self.ctx.device.features())
    }

    /// The limits the device was opened with.
    pub fn limits(&self) -> &wgpu::Limits {
        &self.ctx.limits
    }

    /// Cap on the PCG iterations of one solve (all rounds together).
    pub fn set_max_iterations(&mut self, n: usize) {
        self.max_iterations = n.max(1);
    }

    /// Cap on the refinement rounds of one solve.
    pub fn set_max_rounds(&mut self, n: usize) {
        self.max_rounds = n.max(1);
    }

    /// Most iterations between two read-backs of the residuals (default 32).
    pub fn set_check_every(&mut self, n: usize) {
        self.check_every = n.max(1);
    }

    /// Relative residual the f32 inner solve must reach at least (default 1e-5).
    pub fn set_inner_tolerance(&mut self, eta: f64) {
        self.inner_min = eta.clamp(1e-7, 0.5);
    }

    /// Counters of the last solve.
    pub fn last_stats(&self) -> SolveStats {
        self.stats
    }

    /// Choose the preconditioner (default [`Preconditioner::Cholesky`],
    /// or `METRICDEFORM_GPU_PRECONDITIONER`); a prepared matrix gets
    /// the new one at once.
    pub fn set_preconditioner(&mut self, p: Preconditioner) -> Result<(), GpuError> {
        if p == self.preconditioner {
            return Ok(());
        }
        self.preconditioner = p;
        self.drop_workspaces();
        self.amg_host = None;
        self.amg_gpu = None;
        self.chol = None;
        self.chol_kind = None;
        if self.host.is_some() {
            self.refresh_inverse_diagonal()?;
            self.setup_amg()?;
        }
        Ok(())
    }

    /// Where the Cholesky factors (the shape systems' of `K`, the scale
    /// factors' of their matrix) are made (default
    /// [`crate::Factorization::on`] the adapter, or
    /// `METRICDEFORM_GPU_FACTORIZATION`);
    /// from the next set-up of a kind on.
    pub fn set_factorization(&mut self, f: crate::Factorization) {
        self.factorization = f;
    }

    /// Where the next set-up of a kind makes its Cholesky factor
    /// ([`GpuSolver::set_factorization`]).
    pub fn factorization(&self) -> crate::Factorization {
        self.factorization
    }

    /// Whether `kind`'s factor is made on the GPU: asked for, its factor in
    /// f64 (the factorization's kernels are f64), and not refused before.
    pub(crate) fn factors_on_gpu(&self, kind: SystemKind) -> bool {
        self.factorization == crate::Factorization::Gpu
            && !self.gpu_factor_refused[self.chol_group_of(kind)]
            && self.ctx.shader_f64
            && self.factor_precision(kind) == precision::Precision::F64
    }

    /// When to switch to the mixed-precision solve (default: as a fallback).
    pub fn set_mixed_precision(&mut self, m: MixedPrecision) {
        self.mixed_precision = m;
    }

    /// Whether the last solve ran (partly) in mixed precision.
    pub fn last_solve_mixed(&self) -> bool {
        self.stats.mixed
    }

    /// Every workspace, the mixed-precision matrix's too: a new pattern.
    fn drop_workspaces(&mut self) {
        self.ws = None;
        self.mixed = None;
    }

    /// The workspaces' preconditioner steps, for a new preconditioner (a
    /// kind's factor, a hierarchy): the f32 workspace is dropped, and the
    /// mixed-precision one keeps its matrix (with its expansion) and
    /// vectors, its steps made again at its next solve.
    fn drop_preconditioner_steps(&mut self) {
        self.ws = None;
        if let Some(m) = self.mixed.as_mut() {
            m.ws.drop_preconditioner_steps();
            m.steps_current = false;
        }
    }
}

impl GpuSolver {
    /// The preconditioner asked for.
    pub fn preconditioner(&self) -> Preconditioner {
        self.preconditioner
    }

    /// The preconditioner of the prepared matrix: block Jacobi when AMG was not
    /// asked for or its setup failed (coarsening stalled); `Amg` when the
    /// affine hierarchy had no positions or failed.
    pub fn active_preconditioner(&self) -> Preconditioner {
        match (&self.amg_gpu, &self.amg_host) {
            _ if self.chol.is_some() => Preconditioner::Cholesky,
            (Some(_), _) if self.squared.is_some() => Preconditioner::SquaredLaplacian,
            (Some(_), Some(h)) if h.affine => Preconditioner::AffineAmg,
            (Some(_), _) => Preconditioner::Amg,
            _ => Preconditioner::BlockJacobi,
        }
    }

    /// Tuning of the AMG hierarchy (applies from the next prepare).
    pub fn set_amg_options(&mut self, o: amg::AmgOptions) {
        self.amg_opts = o;
    }

    /// The AMG hierarchy of the prepared matrix, if AMG is in use.
    pub fn amg_hierarchy(&self) -> Option<&amg::Hierarchy> {
        self.amg_host.as_ref()
    }

    /// Seconds the last AMG setup took on the CPU (hierarchy and upload).
    pub fn amg_setup_seconds(&self) -> f64 {
        self.amg_setup_seconds
    }

    /// The workspace for at least `ncols` columns.
    pub(crate) fn workspace(&mut self, ncols: usize) -> Result<(), GpuError> {
        let want = ncols.min(CMAX);
        if self.ws.as_ref().is_some_and(|w| w.cmax >= want) {
            return Ok(());
        }
        self.drop_workspaces();
        let h = self.host.as_ref().unwrap();
        let ws = self.k.pcg.workspace(
            &self.ctx,
            &self.spmv(),
            self.gpu.as_ref().unwrap(),
            h.rows,
            h.bs,
            want,
        )?;
        let mut ws = ws;
        ws.chol = self.cholesky_steps(precision::Precision::F32, &ws.r, &ws.z, h.bs, ws.cmax)?;
        let amg = self.amg_gpu.as_ref().filter(|_| ws.chol.is_none());
        if let (Some(g), Some((_, mt))) = (amg, &self.squared) {
            ws.squared = Some(amg_gpu::SquaredSteps::new(
                &self.ctx,
                &self.k.amg,
                g,
                mt,
                &ws.r,
                &ws.z,
                ws.cmax,
            )?);
        } else if let Some(g) = amg {
            ws.amg = Some(amg_gpu::VcycleWorkspace::new(
                &self.ctx,
                &self.k.amg,
                g,
                &ws.r,
                &ws.z,
                ws.cmax,
            )?);
        }
        self.ws = Some(ws);
        Ok(())
    }

    /// Whether this kind's solves start in mixed precision, by the policy.
    fn starts_mixed(&self) -> bool {
        // The scale factors' factor is of their matrix itself.
        let own_factor = self.kind == SystemKind::ScaleFactors && self.chol.is_some();
        self.mixed_precision
            .starts_mixed_with(self.kind, own_factor)
    }

    /// Whether the next solve of this kind runs in mixed precision from its
    /// start: the policy asks it and the solver can.
    pub(super) fn mixed_from_the_first_solve(&self) -> bool {
        self.starts_mixed() && self.mixed_available()
    }

    /// Solve up to CMAX columns: `x` holds the start on entry.
    fn solve_batch(&mut self, b: &[f64], x: &mut [f64], ncols: usize) -> Result<(), GpuError> {
        let n = self.host.as_ref().unwrap().n();
        let bnorm = column_norms(b, n, ncols);
        for c in 0..ncols {
            if bnorm[c] == 0.0 {
                x[c * n..(c + 1) * n].fill(0.0);
            }
        }
        let start_mixed = self.starts_mixed() || self.mixed_sticky;
        if start_mixed && self.mixed_available() {
            return self.solve_batch_mixed(b, &bnorm, x, ncols, 0);
        }
        self.workspace(ncols)?;
        let mut r = vec![0.0; n * ncols];
        let mut r32 = vec![0f32; n * ncols];
        let mut total = 0usize;
        let mut worse = 0;
        let mut prev = f64::INFINITY;
        let mut watch = RoundWatch::default();
        let anorm = self.host.as_ref().unwrap().norm_inf();
        let mut ran = vec![false; ncols];
        for round in 0.. {
            let (rnorm, rel, worst, mut target) =
                self.host_residuals_of(anorm, b, &bnorm, x, &mut r, ncols);
            floor_after_a_round(&mut target, &ran, self.tol);
            self.stats.residual = self.stats.residual.max(worst);
            log::trace!(
                "f32 round {round}: relative residual {worst:.2e} after {total} iterations"
            );
            if rel.iter().any(|v| !v.is_finite()) {
                return Err(GpuError::NotPositiveDefinite);
            }
            if (0..ncols).all(|c| rel[c] <= target[c]) {
                self.stats.residual = worst;
                return Ok(());
            }
            // Not improving for three rounds: the f32 solve cannot help (cond(A) too large).
            if worst > 0.5 * prev {
                worse += 1;
            } else {
                worse = 0;
            }
            prev = prev.min(worst);
            let f32_limited = watch.f32_limited(&rel);
            if round >= self.max_rounds
                || total >= self.max_iterations
                || worse >= 3
                || (f32_limited && self.mixed_available())
            {
                if self.mixed_available() && total < self.max_iterations {
                    log::info!(
                        "f32 refinement {} at a relative residual of {worst:.2e} after {total} iterations",
                        if f32_limited { "limited by f32 rounding" } else { "stagnated" }
                    );
                    // Later solves of this pattern start in mixed precision:
                    // the neighbouring systems are as hard.
                    self.mixed_sticky = true;
                    return self.solve_batch_mixed(b, &bnorm, x, ncols, total);
                }
                self.stats.residual = worst;
                return Err(GpuError::NoConvergence {
                    iterations: total,
                    residual: worst,
                });
            }
            let mut thr = vec![0f64; ncols];
            let mut etas = vec![1.0; ncols];
            for c in 0..ncols {
                let active = rel[c] > target[c];
                ran[c] |= active;
                let scale = if active { 1.0 / rnorm[c] } else { 0.0 };
                for (o, v) in r32[c * n..(c + 1) * n]
                    .iter_mut()
                    .zip(&r[c * n..(c + 1) * n])
                {
                    *o = (v * scale) as f32;
                }
                let eta = if active {
                    (0.5 * target[c] / rel[c]).clamp(self.inner_min, 0.1)
                } else {
                    1.0
                };
                thr[c] = eta * eta;
                etas[c] = eta;
            }
            watch.launched(&rel, etas);
            let spmv = match self.host.as_ref().unwrap().bs {
                1 => Spmv::Scalar(&self.k.csr),
                _ => Spmv::Block(&self.k.bsr),
            };
            let round_no = round;
            let round = Round {
                ctx: &self.ctx,
                pcg: &self.k.pcg,
                spmv: &spmv,
                amg: &self.k.amg,
                convert: None,
                budget: self.max_iterations - total,
                check_every: self.check_every,
                first_batch: self.hints.first_batch(self.kind, false, round_no),
            };
            let ws = self.ws.as_mut().unwrap();
            let active: Vec<f64> = (0..ncols)
                .map(|c| if rel[c] > target[c] { rnorm[c] } else { 0.0 })
                .collect();
            let (iterations, broke_down) =
                round.run(ws, bytemuck::cast_slice(&r32), &thr, &active, x)?;
            self.stats.rounds += 1;
            self.stats.f32_rounds += 1;
            // The iterations of a round that broke down count too: they were run.
            total += iterations;
            self.stats.iterations = total;
            if broke_down {
                // An f32 breakdown on a matrix whose diagonal blocks passed the
                // SPD check can be rounding (p.Ap or r.z <= 0 in f32 on a very
                // ill-conditioned system): the f64 iteration decides.
                if !self.mixed_available() {
                    return Err(GpuError::NotPositiveDefinite);
                }
                log::info!("f32 PCG broke down after {total} iterations");
                self.mixed_sticky = true;
                return self.solve_batch_mixed(b, &bnorm, x, ncols, total);
            }
            self.hints.record(self.kind, false, round_no, iterations);
        }
        unreachable!()
    }

    fn solve(&mut self, b: &[f64], x: &mut [f64], ncols: usize) -> Result<SolveInfo, SolverError> {
        let Some(h) = self.host.as_ref().filter(|h| h.is_filled()) else {
            return Err(SolverError::NotPrepared);
        };
        let n = h.n();
        if b.len() != n * ncols || x.len() != n * ncols {
            return Err(SolverError::DimensionMismatch(format!(
                "right-hand sides have {} entries, guesses {}, expected {} x {}",
                b.len(),
                x.len(),
                n,
                ncols
            )));
        }
        self.stats = SolveStats::default();
        let t = std::time::Instant::now();
        let mut worst = 0.0f64;
        let mut iterations = 0;
        let start = self.amg_kept.then(|| x.to_vec());
        let mut outcome = self.solve_columns(b, x, ncols, n, &mut worst, &mut iterations);
        if let (Err(e), Some(start)) = (&outcome, start) {
            // The kept hierarchy (built for an earlier matrix of this kind)
            // did not carry this one: build it for this matrix, once.
            log::info!("GPU solve with the kept preconditioner failed ({e}); rebuilding it");
            self.setup_amg().map_err(SolverError::from)?;
            x.copy_from_slice(&start);
            worst = 0.0;
            outcome = self.solve_columns(b, x, ncols, n, &mut worst, &mut iterations);
        }
        self.work.solved(iterations);
        outcome?;
        log::debug!(
            "GPU solve: {n} unknowns x {ncols}, {iterations} iterations, {} rounds ({} f32), \
             residual {worst:.1e}, {:.3} s",
            self.stats.rounds,
            self.stats.f32_rounds,
            t.elapsed().as_secs_f64()
        );
        Ok(SolveInfo {
            iterations,
            residual: worst,
        })
    }

    /// The batches of [`Self::solve`].
    fn solve_columns(
        &mut self,
        b: &[f64],
        x: &mut [f64],
        ncols: usize,
        n: usize,
        worst: &mut f64,
        iterations: &mut usize,
    ) -> Result<(), SolverError> {
        let batch = self.batch_columns();
        for c0 in (0..ncols).step_by(batch) {
            let m = batch.min(ncols - c0);
            let rng = c0 * n..(c0 + m) * n;
            let before = self.stats;
            self.stats = SolveStats::default();
            let res = self.solve_batch(&b[rng.clone()], &mut x[rng], m);
            *iterations += self.stats.iterations;
            *worst = worst.max(self.stats.residual);
            self.stats = SolveStats {
                rounds: before.rounds + self.stats.rounds,
                iterations: *iterations,
                residual: *worst,
                mixed: before.mixed || self.stats.mixed,
                f32_rounds: before.f32_rounds + self.stats.f32_rounds,
            };
            res.map_err(|e| match e {
                GpuError::NoConvergence { residual, .. } => SolverError::NoConvergence {
                    iterations: *iterations,
                    residual,
                },
                other => other.into(),
            })?;
        }
        Ok(())
    }
}

/// `||v||_2` through faer (SIMD partial sums; an in-order sum cannot
/// vectorise).
fn norm(v: &[f64]) -> f64 {
    faer::ColRef::from_slice(v).norm_l2()
}

/// [`norm`] of each of the `ncols` columns of length `n` in `v`.
fn column_norms(v: &[f64], n: usize, ncols: usize) -> Vec<f64> {
    (0..ncols).map(|c| norm(&v[c * n..(c + 1) * n])).collect()
}

impl SpdSolver for GpuSolver {
    fn prepare(&mut self, a: &SymCsc) -> Result<(), SolverError> {
        if a.values.len() != a.row_idx.len() {
            return Err(SolverError::DimensionMismatch(format!(
                "{} values for {} entries",
                a.values.len(),
                a.row_idx.len()
            )));
        }
        let same = self.same_pattern(1, &a.col_ptr, &a.row_idx);
        match self.kind {
            SystemKind::ScaleFactors => {
                self.cholesky_for_kind(same, (&a.col_ptr, &a.row_idx), || a.clone())
            }
            _ => self.drop_cholesky(),
        }
        let mut h = self.take_host(same, a.n, 1, &a.col_ptr, &a.row_idx)?;
        h.fill_scalar(a);
        self.upload(h, same, None).map_err(Into::into)
    }

    fn prepare_blocks(&mut self, a: &BlockSym3, fixed: &[bool]) -> Result<(), SolverError> {
        if fixed.len() != a.n || a.blocks.len() != a.row_idx.len() {
            return Err(SolverError::DimensionMismatch(format!(
                "{} fixed flags and {} blocks for {} block rows and {} pattern entries",
                fixed.len(),
                a.blocks.len(),
                a.n,
                a.row_idx.len()
            )));
        }
        self.drop_cholesky();
        let same = self.same_pattern(3, &a.col_ptr, &a.row_idx);
        let mut h = self.take_host(same, a.n, 3, &a.col_ptr, &a.row_idx)?;
        h.fill_blocks(a, fixed);
        self.fixed.clear();
        self.fixed.extend_from_slice(fixed);
        self.upload(h, same, None).map_err(Into::into)
    }

    /// No [`BlockSym3`] is built, and the ring pairs' slots are found once
    /// per pattern, not per matrix. Where the adapter can sum the blocks
    /// (`HostMatrix::set_shape`, `sum_shape_blocks.wgsl`) the solver keeps
    /// `a` (read it with `shape_matrix`, take it back with
    /// `take_shape_matrix`); else the host sums them
    /// (`HostMatrix::fill_shape`) and hands `a` back.
    fn prepare_shape_owned(
        &mut self,
        a: IsoRingSym3,
        fixed: &[bool],
    ) -> Result<Option<IsoRingSym3>, SolverError> {
        // A kind's first shape matrix is expanded on the GPU.
        self.kind_pipelines_ready();
        let n = a.n();
        if fixed.len() != n
            || a.iso.values.len() != a.iso.row_idx.len()
            || a.ring_c.len() != a.rings.len()
            || a.rings.len() != n
        {
            return Err(SolverError::DimensionMismatch(format!(
                "{} fixed flags, {} values for {} pattern entries, {} ring matrices \
                 for {} rings, for {n} block rows",
                fixed.len(),
                a.iso.values.len(),
                a.iso.row_idx.len(),
                a.ring_c.len(),
                a.rings.len(),
            )));
        }
        let (col_ptr, row_idx) = (&a.iso.col_ptr, &a.iso.row_idx);
        let same = self.same_pattern(3, col_ptr, row_idx);
        // A new pattern's parts set up ahead, where they are this one's.
        let ready = match same {
            true => None,
            false => self.pattern_ready(&a, fixed),
        };
        if let Some(up) = ready.as_ref() {
            self.pairs_ahead = None;
            self.ring_slots = Some(up.slots.clone());
        }
        let slots_current =
            ready.is_some() || same && self.ring_slots.as_ref().is_some_and(|r| r.of(&a.rings));
        if !slots_current {
            let t = std::time::Instant::now();
            let given = a.ring_slots.as_ref();
            let slots = Arc::new(RingSlots::new(&a.rings, col_ptr, row_idx, given)?);
            log::debug!(
                "ring pairs' slots {} in {:.3} s",
                match given.is_some_and(|g| slots.shares(g)) {
                    true => "taken from the matrix, checked,",
                    false => "found",
                },
                t.elapsed().as_secs_f64()
            );
            self.start_pairs_ahead(&a, &slots);
            self.ring_slots = Some(slots);
        }
        let t = std::time::Instant::now();
        let (mut h, ahead) = match ready {
            Some(up) => {
                self.host = None;
                (up.host, Some(up.device))
            }
            None => (self.take_host(same, n, 3, col_ptr, row_idx)?, None),
        };
        let slots = self.ring_slots.clone().unwrap();
        // A shape matrix is summed on the GPU where it can be (the first of a
        // pattern too): the host keeps it in its own form, not its blocks.
        let on_gpu = self.shape_sum_possible(&a, &slots);
        let kept = if on_gpu {
            let square = self.square_parts(&a, &slots)?;
            h.set_shape(a, slots, fixed, square);
            None
        } else {
            h.fill_shape(&a, &slots, fixed)?;
            Some(a)
        };
        let filled = t.elapsed().as_secs_f64();
        // The kind's preconditioner, after the host's part of the matrix:
        // a factor made ahead goes up on its own thread meanwhile
        // ([`Self::upload_factor_ahead`]).
        let a = kept.as_ref().or(h.shape_form()).unwrap();
        match self.kind {
            SystemKind::ScaleDriven | SystemKind::FineTune => {
                self.cholesky_for_kind(same, (&a.iso.col_ptr, &a.iso.row_idx), || {
                    a.iso_held_identity(fixed)
                })
            }
            SystemKind::ScaleFactors => self.drop_cholesky(),
        }
        self.fixed.clear();
        self.fixed.extend_from_slice(fixed);
        if let (true, Some(slots)) = (on_gpu, self.ring_slots.clone()) {
            self.start_square_values(h.shape_form(), &slots);
        }
        let t = std::time::Instant::now();
        let uploaded = self.upload(h, same, ahead);
        // Taken up by the shape sum, or not needed.
        self.square_values = None;
        uploaded?;
        log::debug!(
            "shape matrix: {} on the host in {filled:.3} s, uploaded in {:.3} s; \
             the solver's host copy {:.1} MB (beyond the matrix's own form)",
            if on_gpu { "its form kept" } else { "blocks" },
            t.elapsed().as_secs_f64(),
            self.host.as_ref().map_or(0, |h| h.host_bytes()) as f64 / 1e6
        );
        Ok(kept)
    }

    /// No once the Cholesky preconditioner of this shape kind is made: it is
    /// never made again for the kind, and nothing else reads `K` apart (the
    /// products, the diagonal blocks and the norm bound take any split of the
    /// matrix between `K` and the `C_i`).
    fn wants_isotropic_part(&self) -> bool {
        !self.shape_factor_made()
    }

    /// Yes where `K` is not read apart and the GPU sums the shape blocks
    /// (`sum_shape_blocks.wgsl` adds the term's values, uploaded once per
    /// model): E_m's constant Hessian is then not assembled on the host
    /// again for every matrix.
    fn adds_laplacian_square(&self) -> bool {
        !self.wants_isotropic_part() && self.shape_sum.is_some()
    }

    fn shape_matrix(&self) -> Option<&IsoRingSym3> {
        self.host.as_ref().and_then(|h| h.shape_form())
    }

    fn take_shape_matrix(&mut self) -> Option<IsoRingSym3> {
        self.host.as_mut().and_then(|h| h.take_shape())
    }

    fn solve_in_place(&mut self, rhs: &mut [f64], ncols: usize) -> Result<SolveInfo, SolverError> {
        self.kind_pipelines_ready();
        let b = rhs.to_vec();
        rhs.fill(0.0);
        self.solve(&b, rhs, ncols)
    }

    fn solve_with_guess(
        &mut self,
        b: &[f64],
        x: &mut [f64],
        ncols: usize,
    ) -> Result<SolveInfo, SolverError> {
        self.kind_pipelines_ready();
        self.solve(b, x, ncols)
    }

    fn set_tolerance(&mut self, relative_residual: f64) {
        self.tol = relative_residual.max(1e-15);
    }

    fn set_vertex_positions(&mut self, positions: &[[f64; 3]]) {
        self.positions = (!positions.is_empty()).then(|| positions.to_vec());
    }

    /// Only an AMG set-up reads them: not once the kind's Cholesky
    /// preconditioner is made, which a new matrix of the kind keeps.
    fn wants_vertex_positions(&self) -> bool {
        !self.shape_factor_made()
    }

    /// No: the factor is made once per system kind and streamed at the
    /// GPU's bandwidth, where METIS's seconds on one host thread are the
    /// set-up that bounds the speed-up (homer 1.2M: 4.5 s). The pipeline
    /// orders its large factors by the nested dissection of the vertices'
    /// positions instead (`solver_cpu::coordinate_nested_dissection`, on
    /// every thread: 0.57 s on two, for 21 % more factor values than
    /// METIS's and 16 % fewer than minimum degree's).
    fn wants_nested_dissection(&self) -> bool {
        false
    }

    fn sibling(&self) -> Option<Result<Box<dyn SpdSolver>, SolverError>> {
        let made = self.sibling_solver();
        Some(
            made.map(|s| Box::new(s) as Box<dyn SpdSolver>)
                .map_err(SolverError::from),
        )
    }

    fn set_system_kind(&mut self, kind: SystemKind) {
        self.kind = kind;
    }

    fn prepare_shape_pattern(&mut self, a: &IsoRingSym3, fixed: &[bool]) {
        self.start_pattern_ahead(a, fixed);
    }

    fn set_shape_model(&mut self, model: Option<std::sync::Arc<ShapeOperatorModel>>) {
        self.shape_model = model;
    }

    /// The first shape kind's factor of `K`: the Cholesky preconditioner in
    /// its precision (f64 where the shape PCG starts in f64), with the
    /// ordering given.
    fn isotropic_analyser(&self) -> Option<solver_cpu::CholeskySolver> {
        (self.preconditioner == Preconditioner::Cholesky && !self.chol_unavailable[0])
            .then(|| {
                let single =
                    self.factor_precision(SystemKind::ScaleDriven) == precision::Precision::F32;
                self.chol_host.unanalysed_like(single)
            })
            .flatten()
    }

    fn adopt_isotropic_analysis(&mut self, analysed: solver_cpu::CholeskySolver) {
        if self.chol_host.may_adopt(&analysed) {
            self.chol_host = analysed;
        }
    }

    /// A shape kind's factor of `K` in that kind's precision, on the
    /// symbolic analysis made for the shape systems already; none where that
    /// factor's largest supernode would not fit a storage binding (the
    /// kind's set-up then falls back without a factorization).
    fn isotropic_factorer(&self, kind: SystemKind) -> Option<solver_cpu::CholeskySolver> {
        self.isotropic_factor_plan(kind)?.twin(&self.chol_host)
    }

    /// In `kind`'s precision, each supernode within one storage binding
    /// (as `GpuSolver::check_supernodes` asks).
    fn isotropic_factor_plan(&self, kind: SystemKind) -> Option<solver_cpu::FactorPlan> {
        (kind != SystemKind::ScaleFactors
            && self.preconditioner == Preconditioner::Cholesky
            && !self.chol_unavailable[0]
            && !self.factors_on_gpu(kind))
        .then(|| solver_cpu::FactorPlan {
            single: self.factor_precision(kind) == precision::Precision::F32,
            largest_supernode_bytes: matrix::binding_limit(&self.ctx),
            // Its solves apply the inverted form: made on the factoring thread.
            inverted: true,
        })
    }

    /// Uploaded now (its diagonal blocks inverted), beside the active
    /// factor, and kept for `kind`'s Cholesky set-up, which takes it where it
    /// is of that `K`'s pattern and the kind's precision
    /// (`GpuSolver::setup_cholesky`). One that is not a factor of this
    /// solver's analysed pattern (on any ordering: the GPU factor carries
    /// its own permutation and supernodes), or does not fit the device, is
    /// dropped: the
    /// kind's set-up factors again.
    /// A shape kind's factor of `K`, or the scale factors' of their matrix
    /// (made on the host while the device was opened).
    fn adopt_isotropic_factor(&mut self, kind: SystemKind, factored: solver_cpu::CholeskySolver) {
        if let Err(e) = self.upload_factor_ahead(kind, factored) {
            log::debug!("Cholesky factor made ahead ({kind:?} system) not taken: {e}");
        }
    }

    fn factors_isotropic_on_device(&self, kind: SystemKind) -> bool {
        self.preconditioner == Preconditioner::Cholesky
            && !self.chol_unavailable[self.chol_group_of(kind)]
            && self.factors_on_gpu(kind)
    }

    /// Submitted now (the host goes on), kept for `kind`'s Cholesky set-up,
    /// which waits for it and takes it where it is of that `K`'s pattern.
    /// One already kept for another kind is dropped (its set-up factors).
    fn factor_isotropic_on_device(&mut self, kind: SystemKind, k: &SymCsc, slices: usize) {
        if !self.factors_isotropic_on_device(kind) {
            return;
        }
        let slices = slices.max(1);
        match self.start_factor_on_gpu(kind, k, false, slices) {
            Ok(made) => {
                log::debug!(
                    "{kind:?} system's factor submitted to the GPU ahead{}",
                    match slices {
                        1 => String::new(),
                        n => format!(", slice 1 of {n}"),
                    }
                );
                self.gpu_factor_ahead = Some((kind, made));
            }
            Err(e) => log::debug!("{kind:?} system's factor on the GPU ahead: {e}"),
        }
    }

    /// Recorded now, submitted by `factor_isotropic_on_device` of the same
    /// kind and pattern.
    fn prepare_factor_on_device(&mut self, kind: SystemKind, k: &SymCsc) {
        if !self.factors_isotropic_on_device(kind) {
            return;
        }
        match self.record_factor_on_gpu(kind, k) {
            Ok(made) => {
                log::debug!("{kind:?} system's factorization on the GPU recorded ahead");
                self.factor_recorded = Some(made);
            }
            Err(e) => log::debug!("{kind:?} system's factor on the GPU ahead: {e}"),
        }
    }

    /// The next slice of the factor kept ahead, where one is left.
    fn advance_factor_on_device(&mut self) -> bool {
        let Some((kind, made)) = &self.gpu_factor_ahead else {
            return false;
        };
        match made.submit_next(&self.ctx) {
            Ok(Some((i, n))) => {
                log::debug!(
                    "{kind:?} system's factor: slice {i} of {n} submitted to the GPU ahead"
                );
                true
            }
            Ok(None) => false,
            // Its set-up waits for it and finds the device's error.
            Err(e) => {
                log::debug!("{kind:?} system's factor on the GPU ahead: {e}");
                false
            }
        }
    }

    /// The queue drained (a counted wait). A device's error is left to the
    /// set-up that waits for its factor, which reports it.
    fn wait_for_device(&mut self) {
        if let Err(e) = self.ctx.wait() {
            log::debug!("waiting for the device between a factor's slices: {e}");
        }
    }

    /// For the Cholesky preconditioner's next symbolic analysis (the
    /// pipeline computes the vertices' nested dissection beside other work).
    fn set_fill_ordering(&mut self, ordering: solver_cpu::FillOrdering) {
        self.chol_host.set_fill_ordering(ordering);
    }

    /// On the device where its f64 kernels and the scale factors' own f64
    /// factor are there (`GpuSolver::newton_on_device`).
    fn power_sum_newton(
        &mut self,
        constraints: &[solver_cpu::PowerSum],
        rules: &solver_cpu::NewtonRules,
        s: &mut [f64],
    ) -> Option<Result<solver_cpu::NewtonInfo, SolverError>> {
        self.kind_pipelines_ready();
        self.newton_on_device(constraints, rules, s)
            .map(|r| r.map_err(Into::into))
    }

    fn warm_up(&mut self, kind: SystemKind, columns: &[usize]) {
        match self.warm_up_kind(kind, columns) {
            Ok(n) if n > 0 => log::debug!("{kind:?} system: {n} pipelines to compile ahead"),
            Ok(_) => {}
            Err(e) => log::debug!("{kind:?} system's pipelines ahead: {e}; left to their use"),
        }
    }

    fn counters(&self) -> WorkCounters {
        let t = self.ctx.traffic();
        WorkCounters {
            preconditioner_setups: self.setups,
            setups_from_factors_ahead: self.setups_ahead,
            device_seconds: t.wait_seconds,
            device_waits: t.waits as usize,
            device_waits_beside: t.beside_waits as usize,
            submit_seconds: t.submit_seconds,
            bytes_to_device: t.to_device,
            bytes_from_device: t.from_device,
            device_dispatches: t.kernels.dispatches,
            device_bytes: t.kernels.bytes,
            device_bytes_minimal: t.kernels.minimal,
            device_serial_steps: t.kernels.serial_steps,
            device_timed_passes: t.timed_passes,
            device_timed_seconds: t.timed_seconds,
            device_compiles: t.compiles,
            device_compile_seconds: t.compile_seconds,
            device_compiles_ahead: t.compiles_ahead,
            device_compile_ahead_seconds: t.compile_ahead_seconds,
            ..self.work
        }
    }

    fn name(&self) -> &str {
        "gpu"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A device [`open_ahead`] started is the one the next [`open`] takes
    /// (no thread is left opening one); one not taken is ended by
    /// [`drop_opened_ahead`].
    #[test]
    fn a_device_opened_ahead_is_taken_by_open() {
        if crate::test_solver().is_none() {
            return;
        }
        let waiting = || OPENING_AHEAD.lock().unwrap().is_some();
        // (Another test's `open` may take it first: it is taken either way.)
        open_ahead();
        let s = open().expect("the device opened ahead");
        assert!(!waiting());
        assert!(s.ctx.info.name == crate::default_adapter().unwrap().name);
        open_ahead();
        drop_opened_ahead();
        assert!(!waiting());
    }
}
