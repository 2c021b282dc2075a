//! Drives `shaders/pcg.wgsl`: the f32 preconditioned conjugate gradient loop,
//! every scalar kept on the GPU. One iteration is five dispatches in one compute
//! pass (no host round trip):
//!
//! 1. SpMV (`bsr_spmv.wgsl` or `csr_spmv.wgsl`): `Ap = A p`, partials of `p . Ap`;
//! 2. `finish_alpha` (1 workgroup): `alpha = rz / (p . Ap)` per column, breakdown check;
//! 3. `update`: `x += alpha p`, `r -= alpha Ap`, `z = M^-1 r` (block-Jacobi),
//!    partials of `r . z` and `r . r`;
//! 4. `finish_beta` (1 workgroup): `beta = rz' / rz`, convergence flag `rr <= thr`;
//! 5. `direction`: `p = z + beta p` (the SpMV reads `p` in place).
//!
//! A block matrix split into chunks (`crate::matrix::split_rows`, past the
//! storage binding limit) makes step 1 one dispatch per chunk.
//!
//! With the AMG preconditioner, step 3 is `update_amg` (no `z`, partials of
//! `r . r` only), then the recorded V-cycle ([`crate::amg_gpu`], reading `r`,
//! writing `z`), then `dot_rz` (partials of `r . z`).
//!
//! The host reads the 32-byte `ColState` of each column back after each batch
//! of iterations (one submission) and stops when every column is done (converged
//! or broken down) or the iteration budget is spent. Batch sizes adapt: the first
//! batch has as many iterations as the caller's last run of the same system
//! kind took (8 with no such run), later ones the predicted remaining count (from the
//! observed residual reduction rate since the last read-back, or since the start
//! for a refined round, whose right-hand side has norm 1; plus 2), between 2 and
//! `check_every` (the cap, 32 by default), so few iterations are wasted past
//! convergence: each is a full product and preconditioner application.
//!
//! Bindings of `pcg.wgsl` (group 0): 0 `P` uniform `Params`; 1 `cols`
//! (`ColState` per column); 2 `partials` (slot s, column c, workgroup g at
//! `(s ncols + c) groups + g`); 3 `minv` (inverted diagonal blocks); 4 `p`;
//! 5 `ap`; 6 `x`; 7 `r`; 8 `z` (vectors column-major, stride n). `update`
//! uses 0-8, `finish_alpha`/`finish_beta` 0-2, `direction` 0, 1, 4, 8; one
//! bind group through one explicit layout serves them all. Every pipeline is
//! specialised for the number of columns (`NCOLS` override, compiled on first use).

use crate::amg_gpu::{AmgKernels, SquaredSteps, VcycleWorkspace};
use crate::bsr_spmv::{BsrSpmv, SpmvDispatch};
use crate::convert::{Convert, ConvertParams};
use crate::csr_spmv::CsrSpmv;
use crate::device::{dispatch, Bind, Context, Kernel, KernelWork, Params, Shader, FLAT_WG, ROW_WG};
use crate::matrix::GpuMatrix;
use crate::precision::Precision;
use crate::{GpuError, CMAX};

pub(crate) const SOURCE: &str = include_str!("../../shaders/pcg.wgsl");

/// Per-column scalars, as `ColState` in `pcg.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ColState {
    pub rz: f32,
    pub pap: f32,
    pub alpha: f32,
    pub beta: f32,
    /// Squared norm of the recurrence residual.
    pub rr: f32,
    /// The column is done when `rr <= thr`.
    pub thr: f32,
    /// 0 running, 1 converged, 2 breakdown.
    pub done: u32,
    pub iters: u32,
}

/// `ColState` of the f64 kernels (`precision.rs`): the same fields, the
/// scalars in f64 (56 bytes, 8-aligned).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ColState64 {
    pub(crate) rz: f64,
    pub(crate) pap: f64,
    pub(crate) alpha: f64,
    pub(crate) beta: f64,
    pub(crate) rr: f64,
    pub(crate) thr: f64,
    pub(crate) done: u32,
    pub(crate) iters: u32,
}

impl Precision {
    /// Bytes of one `ColState` in this precision.
    fn col_state_bytes(self) -> usize {
        match self {
            Precision::F32 => std::mem::size_of::<ColState>(),
            Precision::F64 => std::mem::size_of::<ColState64>(),
        }
    }

    /// Fresh column states with the thresholds `thr`, as bytes.
    fn col_states(self, thr: &[f64]) -> Vec<u8> {
        match self {
            Precision::F32 => bytemuck::cast_slice(
                &thr.iter()
                    .map(|&t| ColState {
                        thr: t as f32,
                        ..Default::default()
                    })
                    .collect::<Vec<_>>(),
            )
            .to_vec(),
            Precision::F64 => bytemuck::cast_slice(
                &thr.iter()
                    .map(|&t| ColState64 {
                        thr: t,
                        ..Default::default()
                    })
                    .collect::<Vec<_>>(),
            )
            .to_vec(),
        }
    }

    /// Column states read back, the scalars as f32 (the host only tests them).
    fn read_col_states(self, bytes: &[u8]) -> Vec<ColState> {
        match self {
            Precision::F32 => bytemuck::pod_collect_to_vec(bytes),
            Precision::F64 => bytemuck::pod_collect_to_vec::<u8, ColState64>(bytes)
                .into_iter()
                .map(|c| ColState {
                    rz: c.rz as f32,
                    pap: c.pap as f32,
                    alpha: c.alpha as f32,
                    beta: c.beta as f32,
                    rr: c.rr as f32,
                    thr: c.thr as f32,
                    done: c.done,
                    iters: c.iters,
                })
                .collect(),
        }
    }
}

pub(crate) const DONE_BREAKDOWN: u32 = 2;

/// Iterations of the first batch of a run with nothing known about it.
pub(crate) const FIRST_BATCH: usize = 8;

/// Layout of `pcg.wgsl` (group 0), shared by its four entry points.
const BINDINGS: [(u32, Bind); 9] = [
    (0, Bind::Uniform),
    (1, Bind::ReadWrite),
    (2, Bind::ReadWrite),
    (3, Bind::Read),
    (4, Bind::ReadWrite),
    (5, Bind::Read),
    (6, Bind::ReadWrite),
    (7, Bind::ReadWrite),
    (8, Bind::ReadWrite),
];

pub(crate) struct Pcg {
    pub precision: Precision,
    shader: Shader,
    pub update: Kernel,
    pub finish_alpha: Kernel,
    pub finish_beta: Kernel,
    pub direction: Kernel,
    pub update_amg: Kernel,
    pub dot_rz: Kernel,
}

/// The SpMV kernel of the prepared matrix (block or scalar).
pub(crate) enum Spmv<'a> {
    Block(&'a BsrSpmv),
    Scalar(&'a CsrSpmv),
}

impl Spmv<'_> {
    pub fn kernel(&self) -> &Kernel {
        match self {
            Spmv::Block(k) => &k.kernel,
            Spmv::Scalar(k) => &k.kernel,
        }
    }

    #[allow(clippy::too_many_arguments)]
    pub fn bind(
        &self,
        ctx: &Context,
        params: &wgpu::Buffer,
        m: &GpuMatrix,
        x: &wgpu::Buffer,
        y: &wgpu::Buffer,
        partials: &wgpu::Buffer,
        groups: u64,
    ) -> Result<Vec<SpmvDispatch>, GpuError> {
        match self {
            Spmv::Block(k) => k.bind(ctx, params, m, x, y, partials, groups),
            Spmv::Scalar(k) => k.bind(ctx, params, m, x, y, partials, groups),
        }
    }
}

/// Vector buffers and bind groups for one prepared matrix and up to `cmax`
/// columns; reused by every solve until the pattern changes or more columns
/// are needed.
pub(crate) struct Workspace {
    pub precision: Precision,
    pub cmax: usize,
    pub rows: usize,
    pub bs: usize,
    pub groups: u32,
    pub params: wgpu::Buffer,
    pub cols: wgpu::Buffer,
    /// Only used through the bind groups.
    #[allow(dead_code)]
    pub partials: wgpu::Buffer,
    pub x: wgpu::Buffer,
    pub r: wgpu::Buffer,
    #[allow(dead_code)]
    pub z: wgpu::Buffer,
    pub p: wgpu::Buffer,
    pub ap: wgpu::Buffer,
    /// The product `Ap = A p`: one dispatch, or one per chunk of a block
    /// matrix.
    spmv: Vec<SpmvDispatch>,
    bg_pcg: wgpu::BindGroup,
    row_dims: (u32, u32),
    pub staging_cols: Option<wgpu::Buffer>,
    pub staging_x: Option<wgpu::Buffer>,
    /// The AMG V-cycle (z = M^-1 r) when the preconditioner is AMG, else the
    /// block Jacobi fused into `update`.
    pub amg: Option<VcycleWorkspace>,
    /// The squared-Laplacian preconditioner (in place of `amg`).
    pub squared: Option<SquaredSteps>,
    /// The Cholesky factor's triangular solves (in place of `amg`).
    pub chol: Option<crate::supernodal::SupernodalSteps>,
    /// Mixed precision (an f64 workspace with the f32 V-cycle): the copies the
    /// V-cycle reads and writes.
    pub narrow: Option<Narrow>,
    /// The bound matrix's [`GpuMatrix::stored`] bytes.
    stored: (u64, u64),
}

/// The f32 side of a mixed-precision workspace: the V-cycle runs from `r32` to
/// `z32`, which `convert.wgsl` copies from the f64 `r` and into the f64 `z`.
pub(crate) struct Narrow {
    pub r32: wgpu::Buffer,
    pub z32: wgpu::Buffer,
    #[allow(dead_code)]
    params: wgpu::Buffer,
    bg_r: wgpu::BindGroup,
    bg_z: wgpu::BindGroup,
    dims: (u32, u32),
}

impl Narrow {
    /// f32 copies of `ws.r` and `ws.z` (an f64 workspace) and their bind groups.
    pub fn new(ctx: &Context, conv: &Convert, ws: &Workspace) -> Result<Narrow, GpuError> {
        assert_eq!(ws.precision, Precision::F64);
        let (n, cmax) = (ws.n(), ws.cmax);
        let bytes = (n * cmax * 4) as u64;
        let what = |v: &str| format!("mixed-precision f32 copy of {v} ({n} x {cmax})");
        ctx.check_storage(&what("r"), bytes)?;
        let r32 = ctx.storage(&what("r"), bytes)?;
        let z32 = ctx.storage(&what("z"), bytes)?;
        let params = ctx.uniform_of(
            "convert params",
            &ConvertParams {
                n: n as u32,
                pad: [0; 3],
            },
        )?;
        Ok(Narrow {
            bg_r: conv.bind(ctx, &params, &ws.r, &r32)?,
            bg_z: conv.bind(ctx, &params, &ws.z, &z32)?,
            dims: ctx.dims("convert kernels", (n as u64).div_ceil(FLAT_WG as u64))?,
            r32,
            z32,
            params,
        })
    }
}

impl Workspace {
    /// Drops the preconditioner's steps (`amg`, `squared`, `chol` and the
    /// f32 copies they read), for a new preconditioner's; the vectors stay.
    pub fn drop_preconditioner_steps(&mut self) {
        (self.chol, self.squared, self.amg, self.narrow) = (None, None, None, None);
    }

    pub fn n(&self) -> usize {
        self.rows * self.bs
    }

    pub fn params(&self, ncols: usize) -> Params {
        Params {
            rows: self.rows as u32,
            ncols: ncols as u32,
            n: self.n() as u32,
            groups: self.groups,
            bs: self.bs as u32,
            pad: [0; 3],
        }
    }
}

/// What one PCG run did.
#[derive(Debug, Clone)]
pub(crate) struct PcgRun {
    /// Iterations dispatched (the largest per-column count is `max(cols.iters)`).
    pub dispatched: usize,
    pub cols: Vec<ColState>,
    /// `x` (bytes in the run's precision) where the last read-back brought it;
    /// in a refined run the refinement's `x'`.
    pub x: Option<Vec<u8>>,
    /// A refined run's sums after it ([`crate::refine`]) where the last
    /// read-back brought them.
    pub norms: Option<Vec<u8>>,
}

/// The refinement round around a PCG run ([`crate::refine`]): its start is
/// recorded before the run's first iterations, its end after each batch
/// that reads `x` back.
pub(crate) struct Refined<'a> {
    pub refinement: &'a crate::refine::Refinement,
    pub kernels: &'a crate::refine::RefineKernels,
    /// The solve's first round (the guess's residual is formed first).
    pub first: bool,
}

impl PcgRun {
    pub fn iterations(&self) -> usize {
        self.cols
            .iter()
            .map(|c| c.iters as usize)
            .max()
            .unwrap_or(0)
    }

    pub fn all_done(&self) -> bool {
        self.cols.iter().all(|c| c.done != 0)
    }

    pub fn breakdown(&self) -> bool {
        self.cols.iter().any(|c| c.done == DONE_BREAKDOWN)
    }
}

impl Pcg {
    pub fn new(ctx: &Context, precision: Precision) -> Result<Self, GpuError> {
        let label = match precision {
            Precision::F32 => "pcg.wgsl",
            Precision::F64 => "pcg.wgsl (f64)",
        };
        let shader = Shader::new(ctx, label, &precision.source(SOURCE), &BINDINGS)?;
        Ok(Pcg {
            precision,
            update: Kernel::new(&shader, "pcg_update", "update"),
            finish_alpha: Kernel::new(&shader, "pcg_finish_alpha", "finish_alpha"),
            finish_beta: Kernel::new(&shader, "pcg_finish_beta", "finish_beta"),
            direction: Kernel::new(&shader, "pcg_direction", "direction"),
            update_amg: Kernel::new(&shader, "pcg_update_amg", "update_amg"),
            dot_rz: Kernel::new(&shader, "pcg_dot_rz", "dot_rz"),
            shader,
        })
    }

    /// Allocate the vectors for `cmax` columns of the prepared matrix (`rows`
    /// block rows of size `bs`) and bind everything.
    #[allow(clippy::too_many_arguments)]
    pub fn workspace(
        &self,
        ctx: &Context,
        spmv: &Spmv,
        m: &GpuMatrix,
        rows: usize,
        bs: usize,
        cmax: usize,
    ) -> Result<Workspace, GpuError> {
        let cmax = cmax.clamp(1, CMAX);
        let n = rows * bs;
        // Partial slots: one per workgroup of rows, or the chunked product's.
        let groups = (rows as u64)
            .div_ceil(ROW_WG as u64)
            .max(m.partial_slots(rows));
        let row_dims = ctx.dims("row kernels", groups)?;
        ctx.dims(
            "element-wise kernels",
            ((n * cmax) as u64).div_ceil(FLAT_WG as u64),
        )?;
        let precision = self.precision;
        let fp = precision.bytes();
        let vec_bytes = (n * cmax) as u64 * fp;
        let what = |name: &str| format!("PCG vector {name} ({n} x {cmax} {precision:?})");
        for name in ["x", "r", "z", "p", "Ap"] {
            ctx.check_storage(&what(name), vec_bytes)?;
        }
        let params = ctx.uniform("pcg params", &Params::default())?;
        let cols = ctx.storage(
            "pcg column scalars",
            (cmax * precision.col_state_bytes()) as u64,
        )?;
        let partials = ctx.storage("pcg partial sums", 2 * cmax as u64 * groups * fp)?;
        let x = ctx.storage(&what("x"), vec_bytes)?;
        let r = ctx.storage(&what("r"), vec_bytes)?;
        let z = ctx.storage(&what("z"), vec_bytes)?;
        let p = ctx.storage(&what("p"), vec_bytes)?;
        let ap = ctx.storage(&what("Ap"), vec_bytes)?;
        let spmv = spmv.bind(ctx, &params, m, &p, &ap, &partials, groups)?;
        let bg_pcg = self.shader.bind(
            ctx,
            &[
                (0, &params),
                (1, &cols),
                (2, &partials),
                (3, &m.minv),
                (4, &p),
                (5, &ap),
                (6, &x),
                (7, &r),
                (8, &z),
            ],
        )?;
        Ok(Workspace {
            stored: m.stored,
            precision,
            cmax,
            rows,
            bs,
            groups: groups as u32,
            params,
            cols,
            partials,
            x,
            r,
            z,
            p,
            ap,
            spmv,
            bg_pcg,
            row_dims,
            staging_cols: None,
            staging_x: None,
            amg: None,
            squared: None,
            chol: None,
            narrow: None,
        })
    }

    /// Run PCG on `ncols` columns whose right-hand sides are already in `ws.r`
    /// (x starts at 0). `thr[c]` is the squared residual norm at which column c
    /// is done (rounded to the working precision). Stops when every column is done or after `max_iters` iterations;
    /// batches between read-backs hold at most `check_every` iterations, the
    /// first `first_batch` (`fixed_batches`: exactly `check_every`, for timing).
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &self,
        ctx: &Context,
        spmv: &Spmv,
        ws: &mut Workspace,
        ncols: usize,
        thr: &[f64],
        max_iters: usize,
        check_every: usize,
        first_batch: Option<usize>,
        fixed_batches: bool,
        amg: Option<&AmgKernels>,
        convert: Option<&Convert>,
        refine: Option<&Refined>,
    ) -> Result<PcgRun, GpuError> {
        assert!(ncols >= 1 && ncols <= ws.cmax && thr.len() == ncols);
        assert_eq!(ws.precision, self.precision);
        let n = ws.n();
        ctx.write_buffer(&ws.params, 0, bytemuck::bytes_of(&ws.params(ncols)));
        ctx.write_buffer(&ws.cols, 0, &self.precision.col_states(thr));
        let flat_dims = ctx.dims(
            "element-wise kernels",
            ((n * ncols) as u64).div_ceil(FLAT_WG as u64),
        )?;
        let used = (n * ncols) as u64 * self.precision.bytes();
        let k_spmv = spmv.kernel().pipeline(ctx, ncols)?;
        let k_alpha = self.finish_alpha.pipeline(ctx, ncols)?;
        // With AMG: update_amg, the V-cycle, dot_rz in place of update.
        let vcycle = match (&ws.amg, amg) {
            (Some(v), Some(k)) => Some((v, v.pipelines(ctx, k, ncols)?)),
            _ => None,
        };
        let squared = match (&ws.squared, amg) {
            (Some(q), Some(k)) => {
                let pipes = |v: &[VcycleWorkspace]| {
                    v.iter()
                        .map(|c| c.pipelines(ctx, k, ncols))
                        .collect::<Result<Vec<_>, _>>()
                };
                Some((
                    q,
                    pipes(&q.first)?,
                    k.scale.kernel.pipeline(ctx, ncols)?,
                    pipes(&q.second)?,
                ))
            }
            _ => None,
        };
        let chol = match &ws.chol {
            Some(c) => Some((c, c.pipelines(ctx, ncols)?)),
            None => None,
        };
        let k_update = if vcycle.is_some() || squared.is_some() || chol.is_some() {
            self.update_amg.pipeline(ctx, ncols)?
        } else {
            self.update.pipeline(ctx, ncols)?
        };
        let k_rz = self.dot_rz.pipeline(ctx, ncols)?;
        // Mixed precision: r -> f32 before the V-cycle, z -> f64 after it.
        let narrow = match (&ws.narrow, convert) {
            (Some(nw), Some(c)) => Some((
                nw,
                c.to_f32.pipeline(ctx, ncols)?,
                c.to_f64.pipeline(ctx, ncols)?,
            )),
            _ => None,
        };
        // Modelled work (KernelWork) of an iteration: the product A p (an
        // operator application: the matrix, p and Ap), the vector updates and
        // dot products (reads and writes of x, r, p, Ap, z; partials), the
        // preconditioner's kernels.
        let nv = (n * ncols) as u64 * self.precision.bytes();
        let partials = 2 * u64::from(ws.groups) * ncols as u64 * self.precision.bytes();
        // One dispatch per chunk: the matrix once, p and Ap once in all.
        let spmv_work = KernelWork {
            dispatches: ws.spmv.len() as u64,
            ..KernelWork::operator(ws.stored.0 + 2 * nv + partials, ws.stored.1 + 2 * nv)
        };
        let scalars = KernelWork::other(partials);
        let jacobi_update = vcycle.is_none() && squared.is_none() && chol.is_none();
        let update_work = match jacobi_update {
            // x, r, p, Ap read; x, r, z written; the inverted diagonal blocks.
            true => KernelWork::other(7 * nv + (ws.rows * ws.bs * ws.bs * 4) as u64 + partials),
            // x, r, p, Ap read; x, r written.
            false => KernelWork::other(6 * nv + partials),
        };
        let mut precondition_work = KernelWork::default();
        if !jacobi_update {
            if let Some((v, _)) = &vcycle {
                precondition_work = precondition_work + v.work(ncols);
            }
            if let Some((q, ..)) = &squared {
                precondition_work = precondition_work + q.work(ncols);
            }
            if let Some((c, _)) = &chol {
                precondition_work = precondition_work + c.work(ncols);
            }
            if narrow.is_some() {
                // r to f32 and z to f64: 12 bytes an entry each way.
                let e = (n * ncols) as u64;
                precondition_work = precondition_work + KernelWork::other(12 * e).times(2);
            }
            // dot_rz: r and z read.
            precondition_work = precondition_work + KernelWork::other(2 * nv + partials);
        }
        // direction: z and p read, p written.
        let direction_work = KernelWork::other(3 * nv);
        let iteration_work =
            spmv_work + scalars + update_work + precondition_work + scalars + direction_work;
        let precondition = |pass: &mut wgpu::ComputePass| {
            if !jacobi_update {
                if let Some((nw, to32, _)) = &narrow {
                    dispatch(pass, to32, &nw.bg_r, nw.dims);
                }
                if let Some((v, pipes)) = &vcycle {
                    v.record(pass, pipes);
                }
                if let Some((q, first, scale, second)) = &squared {
                    for (c, p) in q.first.iter().zip(first) {
                        c.record(pass, p);
                    }
                    q.scale.record(pass, scale);
                    for (c, p) in q.second.iter().zip(second) {
                        c.record(pass, p);
                    }
                }
                if let Some((c, pipes)) = &chol {
                    c.record(pass, pipes);
                }
                if let Some((nw, _, to64)) = &narrow {
                    dispatch(pass, to64, &nw.bg_z, nw.dims);
                }
                dispatch(pass, &k_rz, &ws.bg_pcg, ws.row_dims);
            }
        };
        let k_beta = self.finish_beta.pipeline(ctx, ncols)?;
        let (dir, dir_dims) = (&self.direction, flat_dims);
        let k_dir = dir.pipeline(ctx, ncols)?;
        let mut enc = ctx.encoder("pcg init");
        if let Some(rf) = refine {
            rf.refinement
                .record_start(ctx, rf.kernels, &k_spmv, &mut enc, ncols, rf.first)?;
        }
        for b in [&ws.x, &ws.p, &ws.ap] {
            enc.clear_buffer(b, 0, Some(used));
        }
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("pcg init"),
                timestamp_writes: None,
            });
            dispatch(&mut pass, &k_update, &ws.bg_pcg, ws.row_dims);
            precondition(&mut pass);
            dispatch(&mut pass, &k_beta, &ws.bg_pcg, (1, 1));
            dispatch(&mut pass, &k_dir, &ws.bg_pcg, dir_dims);
        }
        ctx.count_kernels(update_work + precondition_work + scalars + direction_work);
        let check_every = check_every.max(1);
        let mut dispatched = 0;
        let mut staging = ws.staging_cols.take();
        let mut next = if fixed_batches {
            check_every
        } else {
            first_batch.unwrap_or(FIRST_BATCH).clamp(1, check_every)
        };
        // A batch sized to finish the run (from a hint or a prediction) brings
        // x back with the column states: one host wait instead of two. A
        // refined run's every batch does (x' and the sums): its first, with
        // no hint, often ends the round.
        let mut with_x = !fixed_batches && (first_batch.is_some() || refine.is_some());
        let x_bytes = used;
        // A refined round's right-hand side is its residual over its norm
        // (refine.wgsl's `scale_r`), so its squared residual starts at 1: the
        // first batch's reduction from there predicts the second batch.
        let mut last: Option<(usize, Vec<ColState>)> = refine.map(|_| (0, unit_start(ncols)));
        let result = loop {
            let k = next.min(max_iters.saturating_sub(dispatched)).max(1);
            {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("pcg iterations"),
                    timestamp_writes: ctx.pass_timestamps(),
                });
                for _ in 0..k {
                    for (bg, dims) in &ws.spmv {
                        dispatch(&mut pass, &k_spmv, bg, *dims);
                    }
                    dispatch(&mut pass, &k_alpha, &ws.bg_pcg, (1, 1));
                    dispatch(&mut pass, &k_update, &ws.bg_pcg, ws.row_dims);
                    precondition(&mut pass);
                    dispatch(&mut pass, &k_beta, &ws.bg_pcg, (1, 1));
                    dispatch(&mut pass, &k_dir, &ws.bg_pcg, dir_dims);
                }
            }
            dispatched += k;
            ctx.count_kernels(iteration_work.times(k as u64));
            ctx.resolve_pass_time(&mut enc);
            let refined = refine.filter(|_| with_x);
            if let Some(rf) = refined {
                if let Err(e) = rf
                    .refinement
                    .record_end(ctx, rf.kernels, &k_spmv, &mut enc, ncols)
                {
                    break Err(e);
                }
            }
            let bytes = (ncols * self.precision.col_state_bytes()) as u64;
            // Column states, then x when asked for (a refined run's sums and
            // x'), then the pass's timestamps.
            let mut parts: Vec<(&wgpu::Buffer, u64)> = vec![(&ws.cols, bytes)];
            match refined {
                Some(rf) => {
                    parts.push((&rf.refinement.norms, crate::refine::norms_bytes(ncols)));
                    parts.push((&rf.refinement.xnew, x_bytes));
                }
                None if with_x => parts.push((&ws.x, x_bytes)),
                None => {}
            }
            parts.extend(ctx.pass_time_buffer());
            let mut read = match ctx.read_parts(&parts, &mut staging, Some(enc)) {
                Ok(b) => b,
                Err(e) => break Err(e),
            };
            if ctx.pass_time_buffer().is_some() {
                let times = read.pop().unwrap_or_default();
                ctx.count_pass_time(&times);
                ctx.recycle(times);
            }
            let mut read = read.into_iter();
            let states = read.next().unwrap_or_default();
            let cols = self.precision.read_col_states(&states);
            ctx.recycle(states);
            let norms = refined.and_then(|_| read.next());
            let run = PcgRun {
                dispatched,
                cols,
                x: read.next(),
                norms,
            };
            log::trace!(
                "PCG ({:?}) batch to {dispatched}: rr / thr per column {:?}",
                self.precision,
                run.cols
                    .iter()
                    .map(|c| (c.rr, c.thr, c.done))
                    .collect::<Vec<_>>()
            );
            if run.all_done() || run.breakdown() || dispatched >= max_iters {
                break Ok(run);
            }
            if !fixed_batches {
                next = predict(last.as_ref(), &run, check_every);
                with_x = true;
            }
            last = Some((dispatched, run.cols));
            enc = ctx.encoder("pcg iterations");
        };
        ws.staging_cols = staging;
        result
    }

    #[cfg(feature = "bench-kernels")]
    /// Seconds per dispatch of each kernel of an iteration (SpMV, finish_alpha,
    /// update, finish_beta, direction), each submitted `reps` times alone on the
    /// current workspace state (values are meaningless; for profiling).
    pub fn profile(
        &self,
        ctx: &Context,
        spmv: &Spmv,
        ws: &Workspace,
        ncols: usize,
        reps: usize,
    ) -> Result<Vec<(&'static str, f64)>, GpuError> {
        ctx.write_buffer(&ws.params, 0, bytemuck::bytes_of(&ws.params(ncols)));
        let flat_dims = ctx.dims(
            "element-wise kernels",
            ((ws.n() * ncols) as u64).div_ceil(FLAT_WG as u64),
        )?;
        let one = |bg, dims| vec![(bg, dims)];
        type Dispatches<'a> = Vec<(&'a wgpu::BindGroup, (u32, u32))>;
        let kernels: [(&Kernel, Dispatches); 5] = [
            (
                spmv.kernel(),
                ws.spmv.iter().map(|(bg, d)| (bg, *d)).collect(),
            ),
            (&self.finish_alpha, one(&ws.bg_pcg, (1, 1))),
            (&self.update, one(&ws.bg_pcg, ws.row_dims)),
            (&self.finish_beta, one(&ws.bg_pcg, (1, 1))),
            (&self.direction, one(&ws.bg_pcg, flat_dims)),
        ];
        let mut out = Vec::new();
        for (k, bgs) in kernels {
            let pipeline = k.pipeline(ctx, ncols)?;
            let mut enc = ctx.encoder("profile");
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                for &(bg, dims) in &bgs {
                    dispatch(&mut pass, &pipeline, bg, dims);
                }
            }
            ctx.submit_wait(enc)?;
            let t = std::time::Instant::now();
            let mut enc = ctx.encoder("profile");
            {
                let mut pass = enc.begin_compute_pass(&Default::default());
                for _ in 0..reps {
                    for &(bg, dims) in &bgs {
                        dispatch(&mut pass, &pipeline, bg, dims);
                    }
                }
            }
            ctx.submit_wait(enc)?;
            out.push((k.label, t.elapsed().as_secs_f64() / reps as f64));
        }
        Ok(out)
    }

    /// Read the first `ncols` columns of `x` (as f64 whatever the precision).
    /// The solution of `run`: from its last read-back where that brought
    /// it, else read now.
    pub fn read_x(
        &self,
        ctx: &Context,
        ws: &mut Workspace,
        ncols: usize,
        run: &mut PcgRun,
    ) -> Result<Vec<f64>, GpuError> {
        let mut x = vec![0.0; ws.n() * ncols];
        self.add_x(ctx, ws, run, &vec![1.0; ncols], &mut x)?;
        Ok(x)
    }

    /// `x_c += scale_c d_c` for the columns with a nonzero `scale`, `d` the
    /// solution of `run` (from its last read-back where that brought it, else
    /// read now): no f64 copy of `d` is made on the host.
    pub fn add_x(
        &self,
        ctx: &Context,
        ws: &mut Workspace,
        run: &mut PcgRun,
        scale: &[f64],
        x: &mut [f64],
    ) -> Result<(), GpuError> {
        let count = ws.n() * scale.len();
        let bytes = match run.x.take() {
            Some(b) => b,
            None => {
                let mut staging = ws.staging_x.take();
                let b = ctx.read::<u8>(
                    &ws.x,
                    count * ws.precision.bytes() as usize,
                    &mut staging,
                    None,
                );
                ws.staging_x = staging;
                b?
            }
        };
        add_columns(ws.precision, &bytes, scale, x);
        ctx.recycle(bytes);
        Ok(())
    }
}

/// `x_c += scale_c d_c` over the columns of `x` (length `n` each) with a
/// nonzero scale, `d` the bytes of as many columns in `precision`: read in
/// place where they are aligned for it, else value by value.
fn add_columns(precision: Precision, d: &[u8], scale: &[f64], x: &mut [f64]) {
    let n = x.len() / scale.len().max(1);
    for (c, &s) in scale.iter().enumerate() {
        if s == 0.0 {
            continue;
        }
        let xc = &mut x[c * n..(c + 1) * n];
        match precision {
            Precision::F64 => {
                let bytes = &d[8 * c * n..8 * (c + 1) * n];
                match bytemuck::try_cast_slice::<u8, f64>(bytes) {
                    Ok(dc) => xc.iter_mut().zip(dc).for_each(|(xi, di)| *xi += s * di),
                    Err(_) => xc
                        .iter_mut()
                        .zip(bytes.chunks_exact(8))
                        .for_each(|(xi, b)| *xi += s * f64::from_ne_bytes(b.try_into().unwrap())),
                }
            }
            Precision::F32 => {
                let bytes = &d[4 * c * n..4 * (c + 1) * n];
                xc.iter_mut()
                    .zip(bytes.chunks_exact(4))
                    .for_each(|(xi, b)| {
                        *xi += s * f64::from(f32::from_ne_bytes(b.try_into().unwrap()))
                    });
            }
        }
    }
}

/// Column states at the start of a run whose right-hand sides have norm 1
/// (a refined round's): the point [`predict`] measures the first batch's
/// reduction from.
fn unit_start(ncols: usize) -> Vec<ColState> {
    vec![
        ColState {
            rr: 1.0,
            ..ColState::default()
        };
        ncols
    ]
}

/// Iterations until every running column is predicted to be done, from the
/// residual reduction between the last two read-backs, or from the start
/// (`at` 0: [`unit_start`]) to the first (2..=cap). Without a previous point,
/// or where the first batch's reduction says nothing (a residual that grew),
/// [`FIRST_BATCH`].
fn predict(last: Option<&(usize, Vec<ColState>)>, run: &PcgRun, cap: usize) -> usize {
    let Some((at, prev)) = last else {
        return cap.min(FIRST_BATCH);
    };
    let unknown = match at {
        0 => cap.min(FIRST_BATCH),
        _ => cap,
    };
    let k = (run.dispatched - at) as f64;
    let mut need = 2.0f64;
    for (c, p) in run.cols.iter().zip(prev) {
        if c.done != 0 {
            continue;
        }
        let (r0, r1) = (p.rr as f64, c.rr as f64);
        let rate = (r1 / r0).powf(1.0 / k);
        let useful = rate > 0.0 && rate < 0.999 && c.thr > 0.0;
        if !useful {
            return unknown;
        }
        let left = (c.thr as f64 / r1).ln() / rate.ln();
        need = need.max(left.ceil() + 2.0);
    }
    (need as usize).clamp(2, cap)
}

#[cfg(test)]
mod tests {
    use super::{add_columns, predict, unit_start, ColState, PcgRun, Precision, FIRST_BATCH};

    /// The second batch of a refined round is predicted from the first
    /// batch's reduction of the unit start (homer 108k's second scale-driven
    /// solve: 3 iterations to 4.4e-9 against a threshold of 2.5e-17 leave 3,
    /// predicted as 3 + 2), not [`FIRST_BATCH`]; a first batch whose residual
    /// grew, or a run without a start point, gets `FIRST_BATCH`; later
    /// batches measure from the last read-back.
    #[test]
    fn the_second_batch_of_a_refined_round_is_predicted_from_its_start() {
        let state = |rr: f32, thr: f32, done: u32| ColState {
            rr,
            thr,
            done,
            ..ColState::default()
        };
        let run = |dispatched: usize, cols: Vec<ColState>| PcgRun {
            dispatched,
            cols,
            x: None,
            norms: None,
        };
        let start = (0, unit_start(1));
        let after3 = run(3, vec![state(4.4e-9, 2.5e-17, 0)]);
        assert_eq!(predict(Some(&start), &after3, 32), 5);
        assert_eq!(predict(None, &after3, 32), FIRST_BATCH);
        let grew = run(2, vec![state(1.5, 2.5e-17, 0)]);
        assert_eq!(predict(Some(&start), &grew, 32), FIRST_BATCH);
        // Later batches: from the last read-back (3 iterations, 1e-6 to 1e-9:
        // 1e-3 each, 8 more to 2.5e-17 and 2 to spare); a grown residual
        // there gets the cap.
        let at3 = (3, vec![state(1e-6, 2.5e-17, 0)]);
        let after6 = run(6, vec![state(1e-9, 2.5e-17, 0)]);
        assert_eq!(predict(Some(&at3), &after6, 32), 10);
        let grew6 = run(6, vec![state(2e-6, 2.5e-17, 0)]);
        assert_eq!(predict(Some(&at3), &grew6, 32), 32);
        // A column that is done (here broken down, its residual barely
        // reduced) is not waited for: the running one needs 1 more, and 2
        // to spare.
        let done = run(3, vec![state(0.5, 2.5e-17, 2), state(1e-16, 2.5e-17, 0)]);
        let start2 = (0, unit_start(2));
        assert_eq!(predict(Some(&start2), &done, 32), 3);
    }

    /// `x_c += s_c d_c` for the columns with a nonzero scale, from f64 bytes
    /// aligned or not (a read-back's `Vec<u8>` promises no alignment) and
    /// from f32 bytes.
    #[test]
    fn columns_are_added_from_bytes_in_either_precision_and_alignment() {
        let n = 5;
        let d: Vec<f64> = (0..2 * n).map(|i| 0.5 + i as f64).collect();
        let want = |x0: f64, scale: [f64; 2]| -> Vec<f64> {
            (0..2 * n).map(|i| x0 + scale[i / n] * d[i]).collect()
        };
        let bytes: Vec<u8> = bytemuck::cast_slice(&d).to_vec();
        let mut shifted = vec![0u8; bytes.len() + 1];
        shifted[1..].copy_from_slice(&bytes);
        for (what, b) in [("aligned", &bytes[..]), ("unaligned", &shifted[1..])] {
            let mut x = vec![1.0; 2 * n];
            add_columns(Precision::F64, b, &[2.0, 0.0], &mut x);
            assert_eq!(x, want(1.0, [2.0, 0.0]), "{what}");
        }
        let d32: Vec<f32> = d.iter().map(|&v| v as f32).collect();
        let mut x = vec![-1.0; 2 * n];
        add_columns(
            Precision::F32,
            bytemuck::cast_slice(&d32),
            &[1.0, -3.0],
            &mut x,
        );
        assert_eq!(x, want(-1.0, [1.0, -3.0]));
    }
}
