//! The solver behind [`solver_cpu::SpdSolver`]: opens the device, uploads
//! each matrix (pattern once, values per matrix), sets up the preconditioner
//! once per system kind and runs the refinement rounds of the crate docs
//! (f32 PCG, f64 residuals on the host; mixed precision where f32 stalls).

use device::Context;
use matrix::{GpuMatrix, HostMatrix, RingSlots};
use pcg::{Spmv, Workspace};
use solver_cpu::{
    BlockSym3, IsoRingSym3, ShapeOperatorModel, SolveInfo, SolverError, SpdSolver, SymCsc,
    SystemKind, WorkCounters,
};
use std::sync::Arc;

use crate::precision::{MixedPrecision, RoundWatch};
use crate::{
    amg, amg_gpu, block_jacobi, bsr_spmv, convert, csr_spmv, default_adapter, device, dot,
    expand_blocks, matrix, pcg, precision, refine, supernodal, AdapterSummary, OpenOptions,
};
use crate::{GpuError, Preconditioner, CMAX, SQUARED_LAPLACIAN_SWEEPS};

/// One refinement round on the GPU: the scaled residuals `r` (bytes in the
/// workspace's precision) in, PCG to the squared thresholds `thr`, then
/// `x_c += scale_c d_c` for the columns with a nonzero `scale` (their residual
/// norm). Returns the iterations, and whether the PCG broke down (then `x`
/// is left as it was).
struct Round<'a> {
    pub(crate) ctx: &'a Context,
    pcg: &'a pcg::Pcg,
    spmv: &'a Spmv<'a>,
    amg: &'a amg_gpu::AmgKernels,
    convert: Option<&'a convert::Convert>,
    budget: usize,
    pub(crate) check_every: usize,
    /// Iterations of the first batch ([`BatchHints`]; `None`: nothing known).
    first_batch: Option<usize>,
}

impl Round<'_> {
    fn run(
        &self,
        ws: &mut Workspace,
        r: &[u8],
        thr: &[f64],
        scale: &[f64],
        x: &mut [f64],
    ) -> Result<(usize, bool), GpuError> {
        let (n, ncols) = (ws.n(), thr.len());
        self.ctx.write_buffer(&ws.r, 0, r);
        let mut run = self.pcg.run(
            self.ctx,
            self.spmv,
            ws,
            ncols,
            thr,
            self.budget,
            self.check_every,
            self.first_batch,
            false,
            Some(self.amg),
            self.convert,
            None,
        )?;
        if run.breakdown() {
            return Ok((run.iterations(), true));
        }
        self.pcg
            .add_x(self.ctx, ws, &mut run, scale, &mut x[..n * ncols])?;
        Ok((run.iterations(), false))
    }
}

/// Iterations the last PCG runs of each kind took, to size the first batch of
/// the next one: a run of a kept preconditioner on a matrix of the same kind
/// takes about as many iterations as the last, so its first read-back comes
/// after that many instead of after [`pcg::FIRST_BATCH`]: a host round trip
/// costs a discrete GPU far more than an iteration or two past convergence.
/// A batch sized to finish also brings `x` back with the column states
/// ([`pcg::Pcg::run`]), so a round that goes as predicted waits once (spot's
/// pipeline row on lavapipe, affine AMG, 2026-11-23: 322 host waits down to
/// 180 for the same 1992 PCG iterations).
/// Keyed by system kind, precision and refinement round (rounds past the
/// third share one entry).
#[derive(Debug, Default)]
struct BatchHints(std::collections::HashMap<(SystemKind, bool, usize), usize>);

impl BatchHints {
    fn key(kind: SystemKind, mixed: bool, round: usize) -> (SystemKind, bool, usize) {
        (kind, mixed, round.min(3))
    }

    /// Iterations of the first batch of round `round`, if a run like it was seen.
    fn first_batch(&self, kind: SystemKind, mixed: bool, round: usize) -> Option<usize> {
        self.0
            .get(&Self::key(kind, mixed, round))
            .map(|&it| it.max(2))
    }

    fn record(&mut self, kind: SystemKind, mixed: bool, round: usize, iterations: usize) {
        self.0.insert(Self::key(kind, mixed, round), iterations);
    }

    fn clear(&mut self) {
        self.0.clear();
    }
}

/// Whether some adapter is available.
pub fn gpu_available() -> bool {
    default_adapter().is_ok()
}

/// Open the GPU solver on the adapter named by `WGPU_ADAPTER_NAME`
/// (case-insensitive substring) or wgpu's default high-performance adapter, with
/// the adapter's own limits.
pub fn open() -> Result<GpuSolver, GpuError> {
    open_with(OpenOptions::default())
}

/// [`open`] with options (adapter name, lowered limits).
pub fn open_with(opts: OpenOptions) -> Result<GpuSolver, GpuError> {
    let ctx = Context::open(&opts)?;
    let kernels = Kernels {
        bsr: bsr_spmv::new(&ctx)?,
        csr: csr_spmv::new(&ctx)?,
        dot: dot::Dot::new(&ctx)?,
        jacobi: block_jacobi::BlockJacobi::new(&ctx)?,
        pcg: pcg::Pcg::new(&ctx, precision::Precision::F32)?,
        amg: amg_gpu::AmgKernels::new(&ctx)?,
    };
    ctx.check()?;
    Ok(GpuSolver {
        ctx,
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
        chol_host: {
            let mut c = solver_cpu::CholeskySolver::single_precision();
            c.supernodal = true;
            c
        },
        chol_unavailable: [false; 2],
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
    pub(crate) ctx: Context,
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
    setups: usize,
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
    /// New values of a prepared block pattern go up as their lower triangle
    /// in f64 and are expanded on the GPU (needs `SHADER_F64`): the kernel,
    /// and the recorded expansion with what it was recorded for
    /// (`pattern_uploads`, whether it writes the mixed matrix's low parts,
    /// the held rows).
    expand: Option<expand_blocks::ExpandBlocks>,
    pub(crate) expansion: Option<(expand_blocks::Expansion, usize, Option<usize>, Vec<bool>)>,
    /// Mixed-precision matrices built (each has its own low-part buffers).
    mixed_builds: usize,
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
    expansions: usize,
    /// The Cholesky preconditioner's factor on the GPU
    /// ([`Preconditioner::Cholesky`]), the kind it was made for, its kernels,
    /// and the host factorization (its symbolic analysis serves every kind of
    /// the same pattern).
    pub(crate) chol: Option<supernodal::GpuFactor>,
    chol_kind: Option<SystemKind>,
    chol_kernels: Option<std::sync::Arc<supernodal::SupernodalKernels>>,
    chol_host: solver_cpu::CholeskySolver,
    /// The factor could not be made or kept on this device, for the shape
    /// systems ([0]) or the scale factors ([1]): the squared Laplacian or AMG
    /// serves instead for the rest of the run.
    chol_unavailable: [bool; 2],
}

/// The f64 kernels of the mixed-precision solve.
struct MixedKernels {
    pcg: pcg::Pcg,
    /// Scalar matrices (the face system).
    csr: csr_spmv::CsrSpmv,
    /// 3x3 block matrices: high and low f32 parts in storage buffers.
    bsr: bsr_spmv::BsrSpmv,
    convert: convert::Convert,
    /// The refinement rounds on the GPU.
    refine: refine::RefineKernels,
}

impl MixedKernels {
    /// The f64 product for a matrix of block size `bs`.
    pub(crate) fn spmv(&self, bs: usize) -> Spmv<'_> {
        match bs {
            1 => Spmv::Scalar(&self.csr),
            _ => Spmv::Block(&self.bsr),
        }
    }
}

/// The mixed-precision solve's data: the matrix in f64 (3x3 blocks as high and
/// low f32 parts in storage buffers, the high part shared with the f32 matrix; a
/// scalar matrix as f64 CSR) and a scalar workspace whose V-cycle runs on f32
/// copies of r and z.
pub(crate) struct MixedData {
    /// `(pattern_uploads, value_uploads)` of the matrix it was built from.
    stamp: (usize, usize),
    /// Read through the workspace's bind groups only.
    pub(crate) matrix: GpuMatrix,
    pub(crate) ws: Workspace,
    /// The refinement's vectors ([`crate::refine`]).
    refine: refine::Refinement,
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
            self.setup_amg()?;
        }
        Ok(())
    }

    /// When to switch to the mixed-precision solve (default: as a fallback).
    pub fn set_mixed_precision(&mut self, m: MixedPrecision) {
        self.mixed_precision = m;
    }

    /// Whether the last solve ran (partly) in mixed precision.
    pub fn last_solve_mixed(&self) -> bool {
        self.stats.mixed
    }

    fn drop_workspaces(&mut self) {
        self.ws = None;
        self.mixed = None;
    }

    /// Whether the mixed-precision solve can run (f64 kernels and AMG).
    fn mixed_available(&self) -> bool {
        self.ctx.shader_f64
            && (self.amg_gpu.is_some() || self.chol.is_some())
            && self.mixed_precision != MixedPrecision::Never
    }

    /// The mixed-precision matrix and workspace for at least `ncols` columns.
    pub(crate) fn mixed_workspace(&mut self, ncols: usize) -> Result<(), GpuError> {
        let stamp = (self.pattern_uploads, self.value_uploads);
        let want = ncols.min(CMAX);
        let block = self.host.as_ref().is_some_and(|h| h.bs == 3);
        if let Some(m) = self.mixed.as_mut() {
            if m.stamp.0 == stamp.0 && m.ws.cmax >= want && (block || m.stamp.1 == stamp.1) {
                if m.stamp.1 != stamp.1 {
                    // Same pattern, new values: rewrite them in place (the
                    // high parts are the f32 matrix's, already written).
                    let h = self.host.as_ref().unwrap();
                    m.matrix.write_values(&self.ctx, h, &[]);
                    m.stamp = stamp;
                }
                return Ok(());
            }
        }
        self.mixed = None;
        // A shape matrix whose blocks the GPU sums has no blocks on the host:
        // the new matrix's low parts are summed and expanded there too.
        let on_gpu = self.host.as_ref().is_some_and(|h| h.shape_form().is_some());
        self.build_mixed(want, stamp, on_gpu)?;
        if on_gpu {
            let h = self.host.take().unwrap();
            let done = self.expand_on_gpu(&h);
            if matches!(done, Ok(false)) {
                self.mixed
                    .as_ref()
                    .unwrap()
                    .matrix
                    .write_values(&self.ctx, &h, &[]);
            }
            self.host = Some(h);
            done?;
        }
        Ok(())
    }

    /// [`Self::mixed_workspace`]'s new matrix and workspace, its low parts
    /// written from the host unless `unwritten`.
    fn build_mixed(
        &mut self,
        want: usize,
        stamp: (usize, usize),
        unwritten: bool,
    ) -> Result<(), GpuError> {
        if self.mixed_kernels.is_none() {
            self.mixed_kernels = Some(MixedKernels {
                pcg: pcg::Pcg::new(&self.ctx, precision::Precision::F64)?,
                csr: csr_spmv::new_in(&self.ctx, precision::Precision::F64)?,
                bsr: bsr_spmv::new_f64(&self.ctx)?,
                convert: convert::Convert::new(&self.ctx)?,
                refine: refine::RefineKernels::new(&self.ctx)?,
            });
        }
        let k = self.mixed_kernels.as_ref().unwrap();
        let h = self.host.as_ref().unwrap();
        let matrix = match h.bs {
            1 => GpuMatrix::upload_scalar(&self.ctx, h, precision::Precision::F64)?,
            _ => GpuMatrix::upload_split_f64(&self.ctx, h, self.gpu.as_ref().unwrap(), !unwritten)?,
        };
        let spmv = k.spmv(h.bs);
        let mut ws = k.pcg.workspace(&self.ctx, &spmv, &matrix, h.n(), 1, want)?;
        let refine = refine::Refinement::new(&self.ctx, &k.refine, &spmv, &matrix, &ws)?;
        // An f64 factor's solves read and write the f64 vectors in place.
        ws.chol = self.cholesky_steps(precision::Precision::F64, &ws.r, &ws.z, h.bs, ws.cmax)?;
        if ws.chol.is_some() {
            self.mixed = Some(MixedData {
                stamp,
                matrix,
                ws,
                refine,
            });
            self.mixed_builds += 1;
            return Ok(());
        }
        let narrow = pcg::Narrow::new(&self.ctx, &k.convert, &ws)?;
        let f32_chol = self.cholesky_steps(
            precision::Precision::F32,
            &narrow.r32,
            &narrow.z32,
            h.bs,
            ws.cmax,
        )?;
        match (f32_chol, &self.squared) {
            (Some(steps), _) => ws.chol = Some(steps),
            (None, Some((_, mt))) => {
                let g = self.amg_gpu.as_ref().unwrap();
                ws.squared = Some(amg_gpu::SquaredSteps::new(
                    &self.ctx,
                    &self.k.amg,
                    g,
                    mt,
                    &narrow.r32,
                    &narrow.z32,
                    ws.cmax,
                )?)
            }
            (None, None) => {
                let g = self.amg_gpu.as_ref().unwrap();
                ws.amg = Some(amg_gpu::VcycleWorkspace::new(
                    &self.ctx,
                    &self.k.amg,
                    g,
                    &narrow.r32,
                    &narrow.z32,
                    ws.cmax,
                )?)
            }
        }
        ws.narrow = Some(narrow);
        self.mixed = Some(MixedData {
            stamp,
            matrix,
            ws,
            refine,
        });
        self.mixed_builds += 1;
        Ok(())
    }

    /// Solve up to CMAX columns in mixed precision from the start `x`: rounds
    /// of f64 PCG on the f64 residual (preconditioned by the Cholesky factor
    /// in its precision, else by the f32 V-cycle), refined on the GPU
    /// ([`crate::refine`]). `bnorm`: the columns' `||b||`; `total`: PCG
    /// iterations already spent on these columns.
    fn solve_batch_mixed(
        &mut self,
        b: &[f64],
        bnorm: &[f64],
        x: &mut [f64],
        ncols: usize,
        mut total: usize,
    ) -> Result<(), GpuError> {
        log::info!(
            "GPU solve: PCG in f64, preconditioner {:?}{}",
            self.active_preconditioner(),
            match self.chol.as_ref().map(|f| f.precision) {
                Some(precision::Precision::F64) => " (f64 factor)",
                Some(precision::Precision::F32) => " (f32 factor)",
                None => " (f32 V-cycle)",
            }
        );
        self.stats.mixed = true;
        self.mixed_workspace(ncols)?;
        let n = self.host.as_ref().unwrap().n();
        if !self.refine_on_gpu()? {
            // The residuals' host vector is kept between solves (no fresh
            // allocation, zeroed page by page, each time).
            let mut r = std::mem::take(&mut self.host_residual);
            r.resize(n * ncols, 0.0);
            let done = self.mixed_rounds_host(b, bnorm, x, ncols, total, &mut r);
            self.host_residual = r;
            return done;
        }
        let anorm = self.host.as_ref().unwrap().norm_inf();
        let x = &mut x[..n * ncols];
        let mixed = self.mixed.as_ref().unwrap();
        mixed.refine.load(
            &self.ctx,
            b,
            x,
            ncols,
            bnorm,
            self.tol,
            f64::EPSILON * anorm,
        );
        let mut prev = f64::INFINITY;
        for round_no in 0.. {
            let k = self.mixed_kernels.as_ref().unwrap();
            let mixed = self.mixed.as_mut().unwrap();
            let spmv = k.spmv(self.host.as_ref().unwrap().bs);
            let refined = pcg::Refined {
                refinement: &mixed.refine,
                kernels: &k.refine,
                first: round_no == 0,
            };
            // The thresholds are the GPU's (`refine.wgsl`'s `start`).
            let thr = vec![0.0; ncols];
            let mut run = k.pcg.run(
                &self.ctx,
                &spmv,
                &mut mixed.ws,
                ncols,
                &thr,
                self.max_iterations - total,
                self.check_every,
                self.hints.first_batch(self.kind, true, round_no),
                false,
                Some(&self.k.amg),
                Some(&k.convert),
                Some(&refined),
            )?;
            let it = run.iterations();
            total += it;
            self.stats.rounds += 1;
            self.stats.iterations = total;
            if run.breakdown() {
                return Err(GpuError::NotPositiveDefinite);
            }
            self.hints.record(self.kind, true, round_no, it);
            // The round's end where the last batch did not bring it.
            let (norms, xbytes) = match (run.norms.take(), run.x.take()) {
                (Some(s), Some(v)) => (s, v),
                _ => {
                    let mut enc = self.ctx.encoder("refinement: round end");
                    let pipe = spmv.kernel().pipeline(&self.ctx, ncols)?;
                    mixed
                        .refine
                        .record_end(&self.ctx, &k.refine, &pipe, &mut enc, ncols)?;
                    let sums = (refine::NORMS_PER_COLUMN * ncols * 8) as u64;
                    let mut got = self.ctx.read_parts(
                        &[
                            (&mixed.refine.norms, sums),
                            (&mixed.refine.xnew, (n * ncols * 8) as u64),
                        ],
                        &mut None,
                        Some(enc),
                    )?;
                    let v = got.pop().unwrap_or_default();
                    (got.pop().unwrap_or_default(), v)
                }
            };
            let sums = refine::decode_norms(&norms, ncols);
            self.ctx.recycle(norms);
            let mut worst = 0.0f64;
            let mut done = true;
            for (c, &(rn, xn)) in sums.iter().enumerate() {
                if bnorm[c] == 0.0 {
                    continue;
                }
                let rel = rn / bnorm[c];
                let target = self.residual_target(anorm, xn, bnorm[c]);
                worst = worst.max(rel);
                // NaN compares false: not done.
                done &= rel <= target;
            }
            self.stats.residual = worst;
            log::trace!(
                "mixed round {round_no}: relative residual {worst:.2e} after {total} iterations"
            );
            if done {
                // Straight from the read-back bytes into `x` (no f64 vector
                // in between: a fresh one per solve, page-faulted in).
                let dst: &mut [u8] = bytemuck::cast_slice_mut(x);
                let Some(src) = xbytes.get(..dst.len()) else {
                    return Err(GpuError::Backend(format!(
                        "refinement read back {} values for {}",
                        xbytes.len() / 8,
                        x.len()
                    )));
                };
                dst.copy_from_slice(src);
                self.ctx.recycle(xbytes);
                return Ok(());
            }
            self.ctx.recycle(xbytes);
            self.mixed_round_progressed(worst, prev, round_no, total)?;
            prev = worst;
        }
        unreachable!()
    }

    /// After mixed-precision round `round_no` left the largest relative
    /// residual `worst` (`prev` before it) with `total` iterations spent and
    /// not every column done: an error where the solve should stop. f64
    /// rounds each gain many digits: two that do not halve the residual mean
    /// the iteration itself stagnates.
    fn mixed_round_progressed(
        &self,
        worst: f64,
        prev: f64,
        round_no: usize,
        total: usize,
    ) -> Result<(), GpuError> {
        if !worst.is_finite() || round_no >= 4 || worst > 0.5 * prev || total >= self.max_iterations
        {
            return Err(GpuError::NoConvergence {
                iterations: total,
                residual: worst,
            });
        }
        Ok(())
    }

    /// How far a mixed-precision round's f64 PCG reduces its right-hand side
    /// `r / ||r||` for a column at relative residual `rel`: to half the
    /// tolerance, not to the [`Self::residual_target`] that ends the solve.
    /// Where the rounding floor raises that target (a stiff system: homer
    /// 1.2M's fine-tune matrix has row sums of 5e9 to 1.6e14 against `||b||`
    /// of a few units), the true residual can not show the error falling
    /// further, but the PCG's own recurrence still does: stopping it at the
    /// floor left the fine-tune's solution 4e-3 % of the bbox diagonal from
    /// the Cholesky one, where the CPU's PCG at the same tolerance is within
    /// 3e-5 %. `refine.wgsl`'s `start` applies the same rule.
    fn round_eta(&self, rel: f64) -> f64 {
        (0.5 * self.tol / rel).clamp(1e-13, 0.1)
    }

    /// The relative residual a column must reach: the tolerance, or the f64
    /// rounding floor `eps ||A|| ||x|| / ||b||` where that is larger (a smooth
    /// right-hand side of a stiff system has a large solution, and no f64
    /// solver, Cholesky included, gets its relative residual below that
    /// floor). `anorm`: `||A||_inf` (`HostMatrix::norm_inf`). The GPU's
    /// refinement applies the same rule (`refine.wgsl`'s `start`).
    fn residual_target(&self, anorm: f64, xnorm: f64, bnorm: f64) -> f64 {
        self.tol.max(f64::EPSILON * anorm * xnorm / bnorm)
    }

    /// Per column: the f64 residual `r = b - A x` of the host's matrix (in
    /// `r`), its norm, the relative residual `||r|| / ||b||` (`bnorm`: the
    /// columns' `||b||`) and its [`Self::residual_target`]. Also the largest
    /// relative residual. The one place a residual is formed on the host:
    /// counted in `host_residuals`.
    fn host_residuals_of(
        &mut self,
        anorm: f64,
        b: &[f64],
        bnorm: &[f64],
        x: &[f64],
        r: &mut [f64],
        ncols: usize,
    ) -> (Vec<f64>, Vec<f64>, f64, Vec<f64>) {
        self.host_residuals += 1;
        let h = self.host.as_ref().unwrap();
        let n = h.n();
        h.residual(b, x, r, ncols);
        let rnorm = column_norms(r, n, ncols);
        let mut target = vec![self.tol; ncols];
        let rel: Vec<f64> = (0..ncols)
            .map(|c| {
                let bn = bnorm[c];
                if bn == 0.0 {
                    0.0
                } else {
                    target[c] = self.residual_target(anorm, norm(&x[c * n..(c + 1) * n]), bn);
                    rnorm[c] / bn
                }
            })
            .collect();
        let worst = rel.iter().cloned().fold(0.0, f64::max);
        (rnorm, rel, worst, target)
    }

    /// The rounds of [`Self::solve_batch_mixed`] with the residuals formed
    /// on the host (`r` their vector): for a block matrix whose exact f64
    /// values are not on the GPU (the host wrote them).
    fn mixed_rounds_host(
        &mut self,
        b: &[f64],
        bnorm: &[f64],
        x: &mut [f64],
        ncols: usize,
        mut total: usize,
        r: &mut [f64],
    ) -> Result<(), GpuError> {
        let n = self.host.as_ref().unwrap().n();
        let mut prev = f64::INFINITY;
        let anorm = self.host.as_ref().unwrap().norm_inf();
        let mut ran = vec![false; ncols];
        for round_no in 0.. {
            let (rnorm, rel, worst, mut target) =
                self.host_residuals_of(anorm, b, bnorm, x, r, ncols);
            floor_after_a_round(&mut target, &ran, self.tol);
            self.stats.residual = worst;
            log::trace!(
                "mixed round {round_no}: relative residual {worst:.2e} after {total} iterations"
            );
            if (0..ncols).all(|c| rel[c] <= target[c]) {
                return Ok(());
            }
            self.mixed_round_progressed(worst, prev, round_no, total)?;
            prev = worst;
            let mut thr = vec![0f64; ncols];
            for c in 0..ncols {
                let cols = c * n..(c + 1) * n;
                if rel[c] > target[c] {
                    r[cols].iter_mut().for_each(|v| *v /= rnorm[c]);
                    thr[c] = self.round_eta(rel[c]).powi(2);
                    ran[c] = true;
                } else {
                    r[cols].fill(0.0);
                }
            }
            let k = self.mixed_kernels.as_ref().unwrap();
            let round = Round {
                ctx: &self.ctx,
                pcg: &k.pcg,
                spmv: &k.spmv(self.host.as_ref().unwrap().bs),
                amg: &self.k.amg,
                convert: Some(&k.convert),
                budget: self.max_iterations - total,
                check_every: self.check_every,
                first_batch: self.hints.first_batch(self.kind, true, round_no),
            };
            let ws = &mut self.mixed.as_mut().unwrap().ws;
            let active: Vec<f64> = (0..ncols)
                .map(|c| if rel[c] > target[c] { rnorm[c] } else { 0.0 })
                .collect();
            let (it, broke_down) = round.run(ws, bytemuck::cast_slice(r), &thr, &active, x)?;
            total += it;
            self.stats.rounds += 1;
            self.stats.iterations = total;
            if broke_down {
                return Err(GpuError::NotPositiveDefinite);
            }
            self.hints.record(self.kind, true, round_no, it);
        }
        unreachable!()
    }

    /// Whether the mixed-precision rounds can form their residuals on the GPU
    /// with the exact matrix: a scalar matrix (f64 CSR) always; a block
    /// matrix where its f64 lower blocks are on the GPU for these values
    /// (summed or expanded there), its exact product bound to them.
    fn refine_on_gpu(&mut self) -> Result<bool, GpuError> {
        let h = self.host.as_ref().unwrap();
        if h.bs == 1 {
            return Ok(true);
        }
        let Some((e, ..)) = self
            .expansion
            .as_ref()
            .filter(|_| self.lower_of == Some(self.matrices))
        else {
            return Ok(false);
        };
        let mixed = self.mixed.as_mut().unwrap();
        if !mixed.refine.exact_for(self.expansions) {
            let k = self.mixed_kernels.as_ref().unwrap();
            mixed
                .refine
                .bind_exact(&self.ctx, &k.refine, &mixed.matrix, e, self.expansions)?;
        }
        Ok(mixed.refine.exact_for(self.expansions))
    }

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

    /// Build (or refresh) the AMG hierarchy of the prepared host matrix.
    fn setup_amg(&mut self) -> Result<(), GpuError> {
        self.setups += 1;
        self.amg_kept = false;
        self.amg_kind = Some(self.kind);
        self.squared = None;
        if self.preconditioner == Preconditioner::BlockJacobi {
            self.amg_host = None;
            self.amg_gpu = None;
            return Ok(());
        }
        let t = std::time::Instant::now();
        if let Some(model) = self.squared_model() {
            return self.setup_squared(model, t);
        }
        let h = self.host.as_ref().unwrap();
        let fine_of = |h: &HostMatrix| amg::Bsr {
            bs: h.bs,
            rows: h.rows,
            cols: h.rows,
            row_ptr: h.row_ptr.clone(),
            col_idx: h.col_idx.clone(),
            vals: h.full_values(),
        };
        let prev = self.amg_host.take();
        let positions = match (&self.positions, self.preconditioner) {
            (
                Some(x),
                Preconditioner::AffineAmg
                | Preconditioner::SquaredLaplacian
                | Preconditioner::Cholesky,
            ) if h.bs == 3 && x.len() == h.rows => Some(x),
            _ => None,
        };
        let built = match positions {
            Some(x) => amg::Hierarchy::build_affine(fine_of(h), &self.amg_opts, x, prev.as_ref())
                .or_else(|e| {
                    log::warn!("affine AMG setup failed ({e}); translations only");
                    amg::Hierarchy::build(fine_of(h), &self.amg_opts, prev.as_ref())
                }),
            None => amg::Hierarchy::build(fine_of(h), &self.amg_opts, prev.as_ref()),
        };
        let hier = match built {
            Ok(hier) => hier,
            Err(e) => {
                log::warn!("AMG setup failed ({e}); block Jacobi instead");
                self.amg_gpu = None;
                self.drop_workspaces();
                return Ok(());
            }
        };
        // The finest A on the GPU is the PCG's matrix itself (its buffers):
        // a new upload of that matrix means a new hierarchy upload too.
        let fine_current = self.amg_fine_upload == self.pattern_uploads;
        match (&self.amg_gpu, &prev) {
            (Some(g), Some(p)) if fine_current && amg_gpu::same_patterns(p, &hier) => {
                g.write_values(&self.ctx, &hier);
            }
            _ => {
                self.drop_workspaces();
                self.amg_gpu = None;
                self.amg_gpu = Some(amg_gpu::GpuHierarchy::upload(
                    &self.ctx,
                    &hier,
                    self.gpu.as_ref(),
                )?);
                self.amg_fine_upload = self.pattern_uploads;
            }
        }
        self.finish_setup("AMG", hier, t);
        Ok(())
    }

    /// Keep the host hierarchy `hier` of a finished set-up begun at `t`, and
    /// log it.
    fn finish_setup(&mut self, what: &str, hier: amg::Hierarchy, t: std::time::Instant) {
        log::debug!(
            "{what} ({:?} system): levels {:?}, operator complexity {:.2}, setup {:.3} s",
            self.kind,
            hier.sizes(),
            hier.operator_complexity(),
            t.elapsed().as_secs_f64()
        );
        self.amg_host = Some(hier);
        self.amg_setup_seconds = t.elapsed().as_secs_f64();
    }

    /// The Cholesky preconditioner's steps for the vectors `r` and `z` of a
    /// workspace of `precision`, where its factor is of that precision.
    fn cholesky_steps(
        &self,
        precision: precision::Precision,
        r: &wgpu::Buffer,
        z: &wgpu::Buffer,
        bs: usize,
        cmax: usize,
    ) -> Result<Option<supernodal::SupernodalSteps>, GpuError> {
        match (&self.chol, &self.chol_kernels) {
            (Some(f), Some(k)) if f.precision == precision => {
                Ok(Some(supernodal::SupernodalSteps::new(
                    &self.ctx,
                    k,
                    f,
                    r,
                    z,
                    bs,
                    cmax,
                    matrix::binding_limit(&self.ctx),
                )?))
            }
            _ => Ok(None),
        }
    }

    /// Most columns one PCG batch carries: [`CMAX`], fewer where the Cholesky
    /// preconditioner's updates for that many would not fit a storage binding.
    fn batch_columns(&self) -> usize {
        match (&self.chol, self.host.as_ref()) {
            (Some(f), Some(h)) => f.max_columns(matrix::binding_limit(&self.ctx), h.bs),
            _ => CMAX,
        }
    }

    /// Whether the next matrix is preconditioned by a Cholesky factor: that
    /// of K for the shape systems (`prepare_shape_owned`), the matrix's own
    /// for the scale factors' constant Hessian (`prepare`, scalar).
    fn cholesky_wanted(&self) -> bool {
        self.preconditioner == Preconditioner::Cholesky && !self.chol_unavailable[self.chol_group()]
    }

    /// Which of [`Self::chol_unavailable`] the current kind reads: the shape
    /// systems share one (their factors are of the same size), the scale
    /// factors have their own.
    fn chol_group(&self) -> usize {
        usize::from(self.kind == SystemKind::ScaleFactors)
    }

    /// Keep the Cholesky preconditioner of this kind (`current`: it was made
    /// for this pattern and kind), or set it up by factoring `k()`; where that
    /// fails (over the storage bindings, or not positive definite in the
    /// factor's precision) the kind's other preconditioner is used for the
    /// rest of the run.
    fn cholesky_for_kind(&mut self, current: bool, k: impl FnOnce() -> SymCsc) {
        if !self.cholesky_wanted() {
            self.drop_cholesky();
            return;
        }
        if current && self.chol.is_some() && self.chol_kind == Some(self.kind) {
            return;
        }
        if let Err(e) = self.setup_cholesky(k()) {
            log::warn!(
                "Cholesky preconditioner ({:?} system) unavailable ({e}); {} instead",
                self.kind,
                match self.kind {
                    SystemKind::ScaleFactors => "AMG",
                    _ => "the squared Laplacian",
                }
            );
            self.drop_cholesky();
            self.chol_unavailable[self.chol_group()] = true;
        }
    }

    fn drop_cholesky(&mut self) {
        if self.chol.is_some() {
            self.chol = None;
            self.chol_kind = None;
            self.drop_workspaces();
        }
    }

    /// Factor `k` on the host and upload the factor: the preconditioner of
    /// this system kind for the rest of the run. For the shape systems `k` is
    /// the isotropic part K of the matrix (held rows identity); for the scale
    /// factors the Hessian of Eq. 3 itself, which is constant, so that the
    /// PCG converges in an iteration or two a round. Any other preconditioner
    /// is released.
    fn setup_cholesky(&mut self, k: SymCsc) -> Result<(), GpuError> {
        let t = std::time::Instant::now();
        self.setups += 1;
        self.drop_cholesky();
        // In f64 where the PCG runs in f64 (mixed precision) from the start:
        // K is too ill-conditioned for an f32 factorization on large meshes
        // (homer 1.2M: not positive definite in f32), and the f64 solves read
        // the PCG's vectors in place. Else f32, for the f32 PCG.
        let precision = match self.ctx.shader_f64 && self.mixed_precision.starts_mixed(self.kind) {
            true => precision::Precision::F64,
            false => precision::Precision::F32,
        };
        if self.chol_host.is_single_precision() != (precision == precision::Precision::F32) {
            let ordering = std::mem::take(&mut self.chol_host.ordering);
            self.chol_host = match precision {
                precision::Precision::F32 => solver_cpu::CholeskySolver::single_precision(),
                precision::Precision::F64 => solver_cpu::CholeskySolver::new(),
            };
            self.chol_host.supernodal = true;
            self.chol_host.ordering = ordering;
        }
        let backend = |e: SolverError| GpuError::Backend(format!("Cholesky factor: {e}"));
        // The factor's sizes are known from the symbolic analysis: one that
        // would not fit the device's storage bindings is refused before the
        // numeric factorization. Its values, and the updates of its
        // triangular solves, are split over as many bindings as they need,
        // at supernode boundaries ([`supernodal::GpuFactor`],
        // [`supernodal::SupernodalSteps`]): the largest supernode must fit
        // one.
        self.chol_host.analyse(&k).map_err(backend)?;
        let b = precision.bytes();
        let limit = matrix::binding_limit(&self.ctx);
        let supernode = self.chol_host.largest_supernode_nnz() as u64 * b;
        if supernode > limit {
            return Err(GpuError::LimitExceeded {
                what: format!("the Cholesky factor's largest supernode ({supernode} bytes)"),
                limit_name: "max_storage_buffer_binding_size",
                needed: supernode,
                limit,
            });
        }
        self.chol_host.prepare(&k).map_err(backend)?;
        drop(k);
        let mut f = self
            .chol_host
            .take_supernodal_factor()
            .ok_or_else(|| GpuError::Backend("no supernodal factor".into()))?;
        let t_inverse = std::time::Instant::now();
        f.invert_diagonal_blocks();
        let inverse_seconds = t_inverse.elapsed().as_secs_f64();
        let factor_seconds = t.elapsed().as_secs_f64();
        if self
            .chol_kernels
            .as_ref()
            .is_none_or(|k| k.precision != precision)
        {
            self.chol_kernels = Some(supernodal::SupernodalKernels::new(&self.ctx, precision)?);
        }
        self.drop_workspaces();
        self.amg_host = None;
        self.amg_gpu = None;
        self.squared = None;
        self.amg_kind = None;
        let g = supernodal::GpuFactor::upload(&self.ctx, &f, limit)?;
        self.ctx.check()?;
        log::debug!(
            "Cholesky preconditioner ({:?} system, {:?}): {} unknowns, {} supernodes, {} levels, \
             nnz(L) {} in {} buffers, factor {factor_seconds:.3} s (of it the inverted form \
             {inverse_seconds:.3} s), setup {:.3} s",
            self.kind,
            precision,
            g.nv,
            f.len(),
            g.depth(),
            g.nnz,
            g.chunks(),
            t.elapsed().as_secs_f64()
        );
        self.chol = Some(g);
        self.chol_kind = Some(self.kind);
        self.amg_setup_seconds = t.elapsed().as_secs_f64();
        Ok(())
    }

    /// The shape model the squared-Laplacian preconditioner builds on, where
    /// it is asked for and fits the prepared block matrix.
    fn squared_model(&self) -> Option<std::sync::Arc<ShapeOperatorModel>> {
        let h = self.host.as_ref()?;
        let m = self.shape_model.as_ref()?;
        (matches!(
            self.preconditioner,
            Preconditioner::SquaredLaplacian | Preconditioner::Cholesky
        ) && matches!(self.kind, SystemKind::ScaleDriven | SystemKind::FineTune)
            && h.bs == 3
            && m.laplacian.len() == h.rows
            && m.mt.len() == h.rows
            && self.fixed.len() == h.rows)
            .then(|| m.clone())
    }

    /// Build and upload the squared-Laplacian preconditioner of `model`.
    fn setup_squared(
        &mut self,
        model: std::sync::Arc<ShapeOperatorModel>,
        t: std::time::Instant,
    ) -> Result<(), GpuError> {
        let (b, mt) = amg::squared_laplacian(&model, &self.fixed, amg::SQUARED_LAPLACIAN_TAU);
        let opts = amg::AmgOptions {
            sweeps: self.amg_opts.sweeps.max(SQUARED_LAPLACIAN_SWEEPS),
            ..self.amg_opts
        };
        let hier = match amg::Hierarchy::build(b, &opts, None) {
            Ok(h) => h,
            Err(e) => {
                log::warn!("squared-Laplacian AMG setup failed ({e}); block Jacobi instead");
                self.amg_host = None;
                self.amg_gpu = None;
                self.drop_workspaces();
                return Ok(());
            }
        };
        self.drop_workspaces();
        self.amg_gpu = None;
        self.amg_gpu = Some(amg_gpu::GpuHierarchy::upload_on_3_vectors(
            &self.ctx, &hier,
        )?);
        let mt32: Vec<f32> = mt.iter().map(|&v| v as f32).collect();
        let buf = self.ctx.storage_init("squared-Laplacian Mt", &mt32)?;
        self.squared = Some((model, buf));
        self.finish_setup("squared-Laplacian AMG", hier, t);
        Ok(())
    }

    pub(crate) fn spmv(&self) -> Spmv<'_> {
        match self.host.as_ref().map(|h| h.bs) {
            Some(1) => Spmv::Scalar(&self.k.csr),
            _ => Spmv::Block(&self.k.bsr),
        }
    }

    /// Upload a prepared host matrix (pattern if new, else values only: a
    /// block matrix's as its lower triangle, see [`Self::expand_values`]).
    fn upload(&mut self, h: HostMatrix, same: bool) -> Result<(), GpuError> {
        self.matrices += 1;
        let minv = block_jacobi::inverse_diagonal(&h).map_err(|e| match e {
            SolverError::NotPositiveDefinite => GpuError::NotPositiveDefinite,
            other => GpuError::Backend(other.to_string()),
        })?;
        let mut same_values_only = false;
        let expanded = same && self.gpu.is_some() && h.bs == 3 && self.expand_values(&h, &minv)?;
        match (same, self.gpu.as_ref()) {
            (true, Some(_)) if expanded => same_values_only = true,
            (true, Some(gpu)) => {
                gpu.write_values(&self.ctx, &h, &minv);
                self.value_uploads += 1;
                same_values_only = true;
            }
            _ => {
                self.gpu = None;
                self.drop_workspaces();
                // A shape matrix kept in its form is summed on the GPU from
                // the start: its pattern goes up with no values.
                let shape = h.shape_form().is_some();
                self.gpu = Some(GpuMatrix::upload(&self.ctx, &h, &minv, !shape)?);
                self.pattern_uploads += 1;
                if shape && !self.expand_on_gpu(&h)? {
                    self.gpu
                        .as_ref()
                        .unwrap()
                        .write_values(&self.ctx, &h, &minv);
                }
                self.mixed_sticky = false;
                self.hints.clear();
            }
        }
        self.host = Some(h);
        // One preconditioner set-up per system kind: a new matrix of the kind
        // the hierarchy was built for, same pattern, keeps it. Its finest
        // level is the PCG's matrix itself (just rewritten); the finest
        // smoother's diagonal is refreshed, the coarse levels are kept. The
        // scale-driven matrices differ by the scale factors only, which
        // leaves the iteration counts as they were (BENCHMARKS.md).
        let keep = same_values_only
            && self.amg_kind == Some(self.kind)
            && (self.amg_gpu.is_some() || self.preconditioner == Preconditioner::BlockJacobi);
        // The squared-Laplacian preconditioner does not depend on the
        // matrix values at all: kept while its model is.
        let squared_kept = self.squared.as_ref().is_some_and(|(m, _)| {
            self.squared_model()
                .is_some_and(|now| std::sync::Arc::ptr_eq(m, &now))
        });
        match (&self.amg_gpu, &self.amg_host) {
            // Made for this kind in `prepare_shape_owned`, kept for its run.
            _ if self.chol.is_some() => self.amg_kept = false,
            _ if self.squared.is_some() => {
                if keep && squared_kept {
                    self.amg_kept = true;
                } else {
                    self.setup_amg()?;
                }
            }
            (Some(g), Some(hier)) if keep => {
                let omega = hier.levels.first().map_or(1.0, |l| l.omega);
                g.write_fine_diagonal(&self.ctx, &minv, omega);
                self.amg_kept = true;
            }
            _ if keep => {}
            _ => self.setup_amg()?,
        }
        self.ctx.check()
    }

    /// New values of the uploaded block pattern from their lower triangle:
    /// the f64 lower blocks go up (72 bytes a lower block), or a shape
    /// matrix's `K` values and `C_i` for `sum_shape_blocks.wgsl` to sum them,
    /// and `expand_blocks.wgsl` writes both triangles, held rows, f32 high
    /// parts and, once the mixed-precision matrix exists, its low parts; the
    /// host writes only the inverse diagonals. `false` (nothing done) where the
    /// adapter lacks `SHADER_F64`, or the lower values would not fit one
    /// storage binding: then the host writes the values.
    fn expand_values(&mut self, h: &HostMatrix, minv: &[f32]) -> Result<bool, GpuError> {
        if !self.expand_on_gpu(h)? {
            return Ok(false);
        }
        let stamp = self.pattern_uploads;
        self.gpu
            .as_ref()
            .unwrap()
            .write_diagonal(&self.ctx, h, minv);
        self.value_uploads += 1;
        if let Some(m) = self.mixed.as_mut().filter(|m| m.stamp.0 == stamp) {
            m.matrix.write_diagonal(&self.ctx, h, &[]);
            m.stamp = (stamp, self.value_uploads);
        }
        Ok(true)
    }

    /// The blocks of both triangles of [`Self::expand_values`] (high parts,
    /// and low parts where the mixed-precision matrix of the pattern exists),
    /// without the inverse diagonals; `false` where it can not run.
    fn expand_on_gpu(&mut self, h: &HostMatrix) -> Result<bool, GpuError> {
        let lower_len = h.lower_len();
        let limit = matrix::binding_limit(&self.ctx);
        if !self.ctx.shader_f64
            || h.bs != 3
            || expand_blocks::LowerParts::layout(lower_len, limit).is_none()
        {
            return Ok(false);
        }
        let stamp = self.pattern_uploads;
        let mixed = self.mixed.as_ref().filter(|m| m.stamp.0 == stamp);
        // Which mixed matrix's low parts it writes (each build has its own).
        let split = mixed.map(|_| self.mixed_builds);
        let current = self.expansion.as_ref().is_some_and(|(_, p, s, f)| {
            *p == stamp && *s == split && f.as_slice() == self.fixed.as_slice()
        });
        if !current {
            self.expansion = None;
            if self.expand.is_none() {
                self.expand = Some(expand_blocks::ExpandBlocks::new(&self.ctx)?);
            }
            let gpu = self.gpu.as_ref().unwrap();
            let Some((chunks, None)) = gpu.block_parts() else {
                return Ok(false);
            };
            let lo = mixed.and_then(|m| m.matrix.block_parts()).and_then(|p| p.1);
            if self.expand_lower.as_ref().is_none_or(|(p, _)| *p != stamp) {
                self.expand_lower = None;
                let parts = expand_blocks::LowerParts::new(&self.ctx, lower_len, limit)?;
                self.expand_lower = Some((stamp, parts));
            }
            let e = self.expand.as_ref().unwrap().expansion(
                &self.ctx,
                &self.expand_lower.as_ref().unwrap().1,
                h.map(),
                chunks,
                lo,
            )?;
            self.expansion = Some((e, stamp, split, self.fixed.clone()));
            self.expansions += 1;
        }
        let k = self.expand.as_ref().unwrap();
        match (h.shape_form(), self.ring_slots.as_ref()) {
            (Some(a), Some(slots)) => {
                let current = self
                    .shape_sum
                    .as_ref()
                    .is_some_and(|(p, sum)| *p == stamp && sum.of(&a.rings));
                if !current {
                    self.shape_sum = None;
                    let lower = &self.expand_lower.as_ref().unwrap().1;
                    let sum = expand_blocks::ShapeSum::new(k, &self.ctx, a, slots, lower)?;
                    self.shape_sum = Some((stamp, sum));
                }
                let sum = &mut self.shape_sum.as_mut().unwrap().1;
                if !sum.adds(a.laplacian_square.as_ref()) {
                    // A new model's term (or none): its values go up once.
                    let values = match self.square_values.take() {
                        Some(v) => Some(v),
                        None => matrix::laplacian_square_values(a, slots)
                            .map_err(|e| GpuError::Backend(e.to_string()))?,
                    };
                    sum.set_square(&self.ctx, a.laplacian_square.clone(), values.as_deref())?;
                }
                let (e, ..) = self.expansion.as_ref().unwrap();
                k.run_shape(&self.ctx, e, sum, a)?;
            }
            _ => {
                let (e, ..) = self.expansion.as_ref().unwrap();
                k.run(&self.ctx, e, h.lower_blocks())?;
            }
        }
        self.lower_of = Some(self.matrices);
        Ok(true)
    }

    /// The host's parts of the Laplacian square term `a` names (`None`
    /// without one): made once per model, when its values are found and
    /// kept in `square_values` for the shape sum to take up.
    fn square_parts(
        &mut self,
        a: &IsoRingSym3,
        slots: &RingSlots,
    ) -> Result<Option<Arc<matrix::SquareParts>>, SolverError> {
        let Some(model) = &a.laplacian_square else {
            return Ok(None);
        };
        if let Some(q) = self.square.as_ref().filter(|q| q.of(model)) {
            return Ok(Some(q.clone()));
        }
        self.square = None;
        let values = matrix::laplacian_square_values(a, slots)?.unwrap_or_default();
        let q = Arc::new(matrix::SquareParts::new(model.clone(), a, &values));
        self.square = Some(q.clone());
        self.square_values = Some(values);
        Ok(Some(q))
    }

    /// Whether a shape matrix `a` can have its blocks summed on the GPU
    /// ([`expand_blocks::ShapeSum`]): `SHADER_F64`, and every buffer within
    /// one storage binding.
    fn shape_sum_possible(&self, a: &IsoRingSym3, slots: &RingSlots) -> bool {
        let limit = matrix::binding_limit(&self.ctx);
        self.ctx.shader_f64 && expand_blocks::ShapeSum::fits(a, slots, limit)
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

    /// Solve up to CMAX columns: `x` holds the start on entry.
    fn solve_batch(&mut self, b: &[f64], x: &mut [f64], ncols: usize) -> Result<(), GpuError> {
        let n = self.host.as_ref().unwrap().n();
        let bnorm = column_norms(b, n, ncols);
        for c in 0..ncols {
            if bnorm[c] == 0.0 {
                x[c * n..(c + 1) * n].fill(0.0);
            }
        }
        // The scale factors' factor is of their matrix itself.
        let own_factor = self.kind == SystemKind::ScaleFactors && self.chol.is_some();
        let start_mixed = self
            .mixed_precision
            .starts_mixed_with(self.kind, own_factor)
            || self.mixed_sticky;
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

impl GpuSolver {
    /// Whether the prepared matrix has this lower pattern and block size.
    fn same_pattern(&self, bs: usize, col_ptr: &[usize], row_idx: &[usize]) -> bool {
        self.host
            .as_ref()
            .is_some_and(|h| h.same_pattern(bs, col_ptr, row_idx))
    }

    /// The host matrix to fill: the prepared one when `same`, else a new
    /// pattern.
    fn take_host(
        &mut self,
        same: bool,
        n: usize,
        bs: usize,
        col_ptr: &[usize],
        row_idx: &[usize],
    ) -> Result<HostMatrix, SolverError> {
        match (same, self.host.take()) {
            (true, Some(h)) => Ok(h),
            _ => HostMatrix::pattern(n, bs, col_ptr, row_idx),
        }
    }
}

/// `||v||_2` through faer (SIMD partial sums; an in-order sum cannot
/// vectorise).
fn norm(v: &[f64]) -> f64 {
    faer::ColRef::from_slice(v).norm_l2()
}

/// A column's [`GpuSolver::residual_target`] holds once it has run a round
/// (`ran`): before, its true residual must reach the tolerance `tol` itself.
/// The rounding floor says the true residual can not show the error falling
/// further, not that the error is small: a warm start of homer 1.2M's
/// fine-tune at a relative residual of 1e-2 was taken as solved under a
/// floor of 0.54 (`refine.wgsl`'s `start` applies the same rule).
fn floor_after_a_round(target: &mut [f64], ran: &[bool], tol: f64) {
    for (t, &r) in target.iter_mut().zip(ran) {
        if !r {
            *t = t.min(tol);
        }
    }
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
            SystemKind::ScaleFactors => self.cholesky_for_kind(same, || a.clone()),
            _ => self.drop_cholesky(),
        }
        let mut h = self.take_host(same, a.n, 1, &a.col_ptr, &a.row_idx)?;
        h.fill_scalar(a);
        self.upload(h, same).map_err(Into::into)
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
        self.upload(h, same).map_err(Into::into)
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
        if !(same && self.ring_slots.as_ref().is_some_and(|r| r.of(&a.rings))) {
            self.ring_slots = Some(Arc::new(RingSlots::new(&a.rings, col_ptr, row_idx)?));
        }
        match self.kind {
            SystemKind::ScaleDriven | SystemKind::FineTune => {
                self.cholesky_for_kind(same, || a.iso_held_identity(fixed))
            }
            SystemKind::ScaleFactors => self.drop_cholesky(),
        }
        let t = std::time::Instant::now();
        let mut h = self.take_host(same, n, 3, col_ptr, row_idx)?;
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
        self.fixed.clear();
        self.fixed.extend_from_slice(fixed);
        let filled = t.elapsed().as_secs_f64();
        let uploaded = self.upload(h, same);
        // Taken up by the shape sum, or not needed.
        self.square_values = None;
        uploaded?;
        log::debug!(
            "shape matrix: {} on the host in {filled:.3} s, uploaded in {:.3} s; \
             the solver's host copy {:.1} MB (beyond the matrix's own form)",
            if on_gpu { "diagonal blocks" } else { "blocks" },
            t.elapsed().as_secs_f64() - filled,
            self.host.as_ref().map_or(0, |h| h.host_bytes()) as f64 / 1e6
        );
        Ok(kept)
    }

    /// No once the Cholesky preconditioner of this shape kind is made: it is
    /// never made again for the kind, and nothing else reads `K` apart (the
    /// products, the diagonal blocks and the norm bound take any split of the
    /// matrix between `K` and the `C_i`).
    fn wants_isotropic_part(&self) -> bool {
        let made = self.kind != SystemKind::ScaleFactors
            && self.cholesky_wanted()
            && self.chol.is_some()
            && self.chol_kind == Some(self.kind);
        !made
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
        self.solve(b, x, ncols)
    }

    fn set_tolerance(&mut self, relative_residual: f64) {
        self.tol = relative_residual.max(1e-15);
    }

    fn set_vertex_positions(&mut self, positions: &[[f64; 3]]) {
        self.positions = (!positions.is_empty()).then(|| positions.to_vec());
    }

    fn set_system_kind(&mut self, kind: SystemKind) {
        self.kind = kind;
    }

    fn set_shape_model(&mut self, model: Option<std::sync::Arc<ShapeOperatorModel>>) {
        self.shape_model = model;
    }

    /// For the Cholesky preconditioner's next symbolic analysis (the
    /// pipeline computes the vertices' nested dissection beside other work).
    fn set_fill_ordering(&mut self, ordering: solver_cpu::FillOrdering) {
        self.chol_host.set_fill_ordering(ordering);
    }

    fn counters(&self) -> WorkCounters {
        let t = self.ctx.traffic();
        WorkCounters {
            preconditioner_setups: self.setups,
            device_seconds: t.wait_seconds,
            device_waits: t.waits as usize,
            bytes_to_device: t.to_device,
            bytes_from_device: t.from_device,
            device_dispatches: t.kernels.dispatches,
            device_bytes: t.kernels.bytes,
            device_bytes_minimal: t.kernels.minimal,
            device_timed_passes: t.timed_passes,
            device_timed_seconds: t.timed_seconds,
            ..self.work
        }
    }

    fn name(&self) -> &str {
        "gpu"
    }
}
