//! Drives `shaders/refine.wgsl`: the refinement rounds of the mixed-precision
//! solve on the GPU. Per column, with `x` on the GPU from the caller's guess:
//!
//! ```text
//! r = b - A x, ||r||, ||x||                       f64 SpMV and sums (GPU)
//! eps ||A||_inf                                   once per matrix (GPU;
//!                                                  a scalar matrix's: host)
//! loop:
//!     target = max(tol, eps ||A||_inf ||x|| / ||b||)
//!     stop if ||r|| / ||b|| <= target              host, from the sums
//!     solve A d = r / ||r|| to eta = clamp(0.5 target ||b|| / ||r||, 1e-13, 0.1)
//!                                                  f64 PCG (pcg.wgsl)
//!     x += ||r|| d; r = b - A x, ||r||, ||x||      GPU
//! ```
//!
//! The round's set-up (`start`: thresholds, `scale_r`: the right-hand side)
//! is recorded before the PCG's first iterations and the new residual after
//! each batch of iterations that may finish the round, in the same
//! submissions ([`crate::pcg::Pcg::run`]): the host reads the sums and `x`
//! with the PCG's column states, in the wait it had anyway. It sends `b`
//! (and a nonzero guess) once per solve and forms no residual.
//!
//! `A x` is the exact matrix's, in f64: a scalar matrix's by the PCG's own
//! product (f64 CSR), a block matrix's by `shaders/refine_product.wgsl` from
//! its f64 lower blocks through the block map of `expand_blocks.wgsl` (the
//! PCG's block product reads 48-bit high and low parts). It goes into the
//! PCG workspace's `Ap`, which the next PCG iteration recomputes before
//! reading. A block matrix's `||A||_inf` is found the same way, from the same
//! values (`refine_row_abs`, then `rounding_floor`), before its first round's
//! product: the host, which keeps a shape matrix in its own form, would walk
//! every value of `K` on one thread for a looser bound. Bindings: as each
//! shader's header lists them (one bind group of `refine.wgsl` serves all
//! its entry points).

use crate::bsr_spmv::SpmvDispatch;
use crate::device::{dispatch, Bind, Context, Kernel, KernelWork, Shader, FLAT_WG};
use crate::matrix::GpuMatrix;
use crate::pcg::{Spmv, Workspace};
use crate::precision::Precision;
use crate::{GpuError, CMAX};
use std::cell::Cell;

pub(crate) const SOURCE: &str = include_str!("../../shaders/refine.wgsl");
pub(crate) const PRODUCT_SOURCE: &str = include_str!("../../shaders/refine_product.wgsl");

/// Workgroup size of `refine.wgsl` (its `WG`).
const WG: u64 = 256;

/// Layout of `refine.wgsl` (group 0).
const BINDINGS: [(u32, Bind); 12] = [
    (0, Bind::Uniform),
    (1, Bind::ReadWrite),
    (2, Bind::Read),
    (3, Bind::Read),
    (4, Bind::Read),
    (5, Bind::Read),
    (6, Bind::ReadWrite),
    (7, Bind::ReadWrite),
    (8, Bind::ReadWrite),
    (9, Bind::ReadWrite),
    (10, Bind::ReadWrite),
    (11, Bind::ReadWrite),
];

/// Layout of `refine_product.wgsl` (group 0).
const PRODUCT_BINDINGS: [(u32, Bind); 11] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::Read),
    (4, Bind::Read),
    (5, Bind::ReadWrite),
    (6, Bind::Read),
    (7, Bind::Uniform),
    (8, Bind::Read),
    (9, Bind::Read),
    (10, Bind::Read),
];

/// Block rows per workgroup of `refine_product.wgsl` (its `WG`).
const PRODUCT_WG: u64 = 128;

/// The kernels of `refine.wgsl` and `refine_product.wgsl` (f64: need
/// `SHADER_F64`).
pub(crate) struct RefineKernels {
    shader: Shader,
    product_shader: Shader,
    product: Kernel,
    add: Kernel,
    residual: Kernel,
    finish: Kernel,
    start: Kernel,
    scale_r: Kernel,
    row_abs: Kernel,
    rounding_floor: Kernel,
}

impl RefineKernels {
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, "refine.wgsl", SOURCE, &BINDINGS)?;
        let product_shader = Shader::new(
            ctx,
            "refine_product.wgsl",
            PRODUCT_SOURCE,
            &PRODUCT_BINDINGS,
        )?;
        Ok(RefineKernels {
            product: Kernel::new(&product_shader, "refine_product", "refine_product"),
            row_abs: Kernel::new(&product_shader, "refine_row_abs", "refine_row_abs"),
            product_shader,
            add: Kernel::new(&shader, "refine_add", "add"),
            residual: Kernel::new(&shader, "refine_residual", "residual"),
            finish: Kernel::new(&shader, "refine_finish", "finish"),
            start: Kernel::new(&shader, "refine_start", "start"),
            scale_r: Kernel::new(&shader, "refine_scale_r", "scale_r"),
            rounding_floor: Kernel::new(&shader, "refine_rounding_floor", "rounding_floor"),
            shader,
        })
    }

    /// Every kernel a refined solve runs for its columns ([`crate::solver`]'s
    /// compilations ahead).
    pub fn kernels(&self) -> [&Kernel; 6] {
        [
            &self.product,
            &self.add,
            &self.residual,
            &self.finish,
            &self.start,
            &self.scale_r,
        ]
    }

    /// The kernels a block matrix's rounding floor runs, once per matrix
    /// and whatever the columns: their pipelines for one column.
    pub fn floor_kernels(&self) -> [&Kernel; 2] {
        [&self.row_abs, &self.rounding_floor]
    }
}

/// The refinement's vectors and bind groups for one f64 PCG workspace.
pub(crate) struct Refinement {
    n: usize,
    cmax: usize,
    /// Partial-sum workgroups per column.
    groups: u64,
    params: wgpu::Buffer,
    aim: wgpu::Buffer,
    b: wgpu::Buffer,
    x: wgpu::Buffer,
    pub xnew: wgpu::Buffer,
    pub norms: wgpu::Buffer,
    bg: wgpu::BindGroup,
    /// `A x'` into the workspace's `Ap` (one dispatch per chunk) by the
    /// PCG's own f64 product: exact for a scalar matrix (f64 CSR).
    spmv: Vec<SpmvDispatch>,
    /// For a block matrix, `A x'` with its exact f64 values
    /// (`refine_product.wgsl`), bound for the matrix values of `key`
    /// ([`Self::bind_exact`]); a block matrix without it is not refined here.
    exact: Option<(usize, Vec<SpmvDispatch>)>,
    /// The workspace's parameters (`n`, the columns) and `Ap`, for the exact
    /// product's bind groups.
    ws_params: wgpu::Buffer,
    ax: wgpu::Buffer,
    /// The block product's bytes per round: the row pointers, map and
    /// columns, and the lower blocks.
    exact_bytes: u64,
    /// The matrix's stored bytes ([`GpuMatrix::stored`]).
    stored: (u64, u64),
    /// The matrix values (the solver's count of matrices) whose rounding
    /// floor `eps ||A||_inf` `rounding_floor` left in `aim`: none where the
    /// host's is there.
    floor_of: Cell<Option<usize>>,
    /// The values whose floor the next first round finds before its
    /// residual (a solve of them loaded without the host's floor while
    /// `aim` held another).
    floor_due: Cell<Option<usize>>,
    /// Only used through the bind groups.
    #[allow(dead_code)]
    rest: [wgpu::Buffer; 3],
}

/// Where a solve's rounding floor `eps ||A||_inf` comes from
/// ([`Refinement::load`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Floor {
    /// The host's.
    Host(f64),
    /// Found on the GPU from the exact values of the solver's matrix
    /// number `values` (one per set of values uploaded).
    OnGpu(usize),
}

/// What the host reads after a round: per column `r'.r'`, `x'.x'` and the
/// round's scale (then, once, the rounding floor's `eps ||A||_inf`).
pub(crate) const NORMS_PER_COLUMN: usize = 3;

/// The bytes of the norms read after a round of `ncols` columns: theirs and
/// the rounding floor's.
pub(crate) fn norms_bytes(ncols: usize) -> u64 {
    ((NORMS_PER_COLUMN * ncols + 1) * 8) as u64
}

impl Refinement {
    /// Buffers for the workspace `ws` (f64) of the matrix `m`.
    pub fn new(
        ctx: &Context,
        k: &RefineKernels,
        spmv: &Spmv,
        m: &GpuMatrix,
        ws: &Workspace,
    ) -> Result<Refinement, GpuError> {
        assert_eq!(ws.precision, Precision::F64);
        let (n, cmax) = (ws.n(), ws.cmax);
        let vec_bytes = (n * cmax * 8) as u64;
        let what = |v: &str| format!("refinement vector {v} ({n} x {cmax} f64)");
        let groups = (n as u64).div_ceil(WG);
        let params = ctx.uniform("refine params", &ws.params(cmax))?;
        let aim = ctx.storage("refinement aims", ((CMAX + 2) * 8) as u64)?;
        let b = ctx.storage(&what("b"), vec_bytes)?;
        let x = ctx.storage(&what("x"), vec_bytes)?;
        let xnew = ctx.storage(&what("x'"), vec_bytes)?;
        let rtrue = ctx.storage(&what("r"), vec_bytes)?;
        let partials = ctx.storage("refinement partial sums", 2 * cmax as u64 * groups * 8)?;
        let norms = ctx.storage("refinement norms", norms_bytes(cmax))?;
        let bg = k.shader.bind(
            ctx,
            &[
                (0, &params),
                (1, &aim),
                (2, &b),
                (3, &ws.ap),
                (4, &x),
                (5, &ws.x),
                (6, &xnew),
                (7, &rtrue),
                (8, &partials),
                (9, &norms),
                (10, &ws.r),
                (11, &ws.cols),
            ],
        )?;
        // The product's own partial sums (p . Ap in the PCG), unread here.
        let spmv_partials = ctx.storage(
            "refinement spmv partial sums",
            2 * cmax as u64 * u64::from(ws.groups) * 8,
        )?;
        let spmv = spmv.bind(
            ctx,
            &ws.params,
            m,
            &xnew,
            &ws.ap,
            &spmv_partials,
            u64::from(ws.groups),
        )?;
        Ok(Refinement {
            exact: None,
            ws_params: ws.params.clone(),
            ax: ws.ap.clone(),
            exact_bytes: 0,
            n,
            cmax,
            groups,
            params,
            aim,
            b,
            x,
            xnew,
            norms,
            bg,
            spmv,
            stored: m.stored,
            rest: [rtrue, partials, spmv_partials],
            floor_of: Cell::new(None),
            floor_due: Cell::new(None),
        })
    }

    /// Whether a block matrix's exact product is bound for the values `key`.
    pub fn exact_for(&self, key: usize) -> bool {
        self.exact.as_ref().is_some_and(|(k, _)| *k == key)
    }

    /// Bind the exact product of the block matrix `m` (its chunks' columns
    /// and row pointers) with the f64 lower blocks and the block map of the
    /// expansion `e`, made for the values `key`.
    pub fn bind_exact(
        &mut self,
        ctx: &Context,
        k: &RefineKernels,
        m: &GpuMatrix,
        e: &crate::expand_blocks::Expansion,
        key: usize,
    ) -> Result<(), GpuError> {
        let (map, lower) = (&e.map, &e.lower);
        self.exact = None;
        let Some((chunks, _)) = m.block_parts() else {
            return Ok(());
        };
        let uniforms = m.chunk_uniforms();
        let mut steps = Vec::with_capacity(chunks.len());
        let mut blocks = 0u64;
        for (c, u) in chunks.iter().zip(uniforms) {
            let bg = k.product_shader.bind(
                ctx,
                &[
                    (0, &self.ws_params),
                    (1, &m.row_ptr),
                    (2, map),
                    (3, lower.part(0)),
                    (4, &self.xnew),
                    (5, &self.ax),
                    (6, &c.cols),
                    (7, u),
                    (8, lower.part(1)),
                    (9, lower.part(2)),
                    (10, lower.part(3)),
                ],
            )?;
            let groups = (c.rows.len() as u64).div_ceil(PRODUCT_WG);
            steps.push((bg, ctx.dims("refinement product", groups)?));
            blocks += c.blocks.len() as u64;
        }
        let rows = (self.n / 3) as u64;
        self.exact_bytes = 4 * (rows + 1) + 8 * blocks + 72 * lower.blocks as u64;
        self.exact = Some((key, steps));
        Ok(())
    }

    /// Write a solve's `ncols` right-hand sides `b`, the guess `x` (a zero
    /// guess is cleared on the GPU, not sent) and the aims: the norms of the
    /// columns of `b`, the relative residual `tol` and the rounding floor's
    /// `eps ||A||_inf`: the host's, or for a block matrix with its exact
    /// product bound, [`Floor::OnGpu`]: the first round finds it on the GPU
    /// from the exact values (`refine_row_abs`, `rounding_floor`) where
    /// `aim` does not hold theirs yet, the host walking none of them.
    #[allow(clippy::too_many_arguments)]
    pub fn load(
        &self,
        ctx: &Context,
        b: &[f64],
        x: &[f64],
        ncols: usize,
        bnorm: &[f64],
        tol: f64,
        floor: Floor,
    ) {
        assert!(ncols <= self.cmax && b.len() == self.n * ncols && x.len() == b.len());
        let n = self.n;
        let p = crate::device::Params {
            rows: n as u32,
            ncols: ncols as u32,
            n: n as u32,
            groups: self.groups as u32,
            bs: 1,
            pad: [0; 3],
        };
        ctx.write_buffer(&self.params, 0, bytemuck::bytes_of(&p));
        let mut aim = vec![0.0; CMAX + 2];
        aim[..ncols].copy_from_slice(bnorm);
        aim[CMAX] = tol;
        match floor {
            Floor::Host(v) => {
                aim[CMAX + 1] = v;
                self.floor_of.set(None);
                self.floor_due.set(None);
            }
            Floor::OnGpu(values) => {
                debug_assert!(self.exact.is_some());
                aim.pop();
                let held = self.floor_of.get() == Some(values);
                self.floor_due.set((!held).then_some(values));
            }
        }
        ctx.write_buffer(&self.aim, 0, bytemuck::cast_slice(&aim));
        ctx.write_buffer(&self.b, 0, bytemuck::cast_slice(b));
        if x.iter().any(|&v| v != 0.0) {
            ctx.write_buffer(&self.x, 0, bytemuck::cast_slice(x));
        } else {
            let mut enc = ctx.encoder("refinement: zero guess");
            enc.clear_buffer(&self.x, 0, Some((n * ncols * 8) as u64));
            ctx.submit(Some(enc));
        }
    }

    /// Record a round's start: on the first round `x' = x` and its residual
    /// and sums; on later ones `x = x'` (the last round's, whose residual
    /// and sums are current). Then each column's threshold and right-hand
    /// side (`start`, `scale_r`).
    pub fn record_start(
        &self,
        ctx: &Context,
        k: &RefineKernels,
        spmv: &wgpu::ComputePipeline,
        enc: &mut wgpu::CommandEncoder,
        ncols: usize,
        first: bool,
    ) -> Result<(), GpuError> {
        let bytes = (self.n * ncols * 8) as u64;
        if first {
            if let Some(values) = self.floor_due.get() {
                self.record_floor(ctx, k, enc, values)?;
            }
            enc.clear_buffer(&self.norms, 0, None);
            self.record_end(ctx, k, spmv, enc, ncols)?;
        } else {
            enc.copy_buffer_to_buffer(&self.xnew, 0, &self.x, 0, bytes);
        }
        let start = k.start.pipeline(ctx, ncols)?;
        let scale_r = k.scale_r.pipeline(ctx, ncols)?;
        let flat = self.flat_dims(ctx, ncols)?;
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("refinement: round start"),
            timestamp_writes: None,
        });
        dispatch(&mut pass, &start, &self.bg, (1, 1));
        dispatch(&mut pass, &scale_r, &self.bg, flat);
        let nv = bytes;
        ctx.count_kernels(KernelWork {
            dispatches: 2,
            ..KernelWork::other(2 * nv)
        });
        Ok(())
    }

    /// Record the rounding floor's `eps ||A||_inf` of the exact values (the
    /// solver's matrix number `values`) into `aim`: each block row's largest
    /// absolute row sum into `Ap` (free before the first round's product),
    /// then their maximum.
    fn record_floor(
        &self,
        ctx: &Context,
        k: &RefineKernels,
        enc: &mut wgpu::CommandEncoder,
        values: usize,
    ) -> Result<(), GpuError> {
        let Some((_, steps)) = &self.exact else {
            return Ok(());
        };
        let row_abs = k.row_abs.pipeline(ctx, 1)?;
        let floor = k.rounding_floor.pipeline(ctx, 1)?;
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("refinement: rounding floor"),
            timestamp_writes: None,
        });
        for (bg, dims) in steps {
            dispatch(&mut pass, &row_abs, bg, *dims);
        }
        dispatch(&mut pass, &floor, &self.bg, (1, 1));
        // The product's reads, a row's maximum written and read again.
        let rows = (self.n / 3) as u64;
        ctx.count_kernels(KernelWork {
            dispatches: steps.len() as u64 + 1,
            ..KernelWork::other(self.exact_bytes + 16 * rows)
        });
        self.floor_due.set(None);
        self.floor_of.set(Some(values));
        Ok(())
    }

    /// Record a round's end: `x' = x + scale d`, `A x'`, `r' = b - A x'`
    /// and the sums `r'.r'`, `x'.x'` per column.
    pub fn record_end(
        &self,
        ctx: &Context,
        k: &RefineKernels,
        spmv: &wgpu::ComputePipeline,
        enc: &mut wgpu::CommandEncoder,
        ncols: usize,
    ) -> Result<(), GpuError> {
        let add = k.add.pipeline(ctx, ncols)?;
        let product = match &self.exact {
            Some(_) => Some(k.product.pipeline(ctx, ncols)?),
            None => None,
        };
        let residual = k.residual.pipeline(ctx, ncols)?;
        let finish = k.finish.pipeline(ctx, ncols)?;
        let flat = self.flat_dims(ctx, ncols)?;
        let groups = ctx.dims("refinement residual", self.groups * ncols as u64)?;
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("refinement: round end"),
            timestamp_writes: None,
        });
        dispatch(&mut pass, &add, &self.bg, flat);
        let (steps, pipeline) = match (&self.exact, &product) {
            (Some((_, steps)), Some(p)) => (steps, p),
            _ => (&self.spmv, spmv),
        };
        for (bg, dims) in steps {
            dispatch(&mut pass, pipeline, bg, *dims);
        }
        dispatch(&mut pass, &residual, &self.bg, groups);
        dispatch(&mut pass, &finish, &self.bg, (1, 1));
        // add: x, d read, x' written; the product (an operator application);
        // residual: b, A x', x' read, r' written.
        let nv = (self.n * ncols * 8) as u64;
        let partials = 2 * ncols as u64 * self.groups * 8;
        let product_work = match &self.exact {
            Some((_, steps)) => KernelWork {
                dispatches: steps.len() as u64,
                ..KernelWork::operator(self.exact_bytes + 2 * nv, self.stored.1 + 2 * nv)
            },
            None => KernelWork {
                dispatches: self.spmv.len() as u64,
                ..KernelWork::operator(self.stored.0 + 2 * nv, self.stored.1 + 2 * nv)
            },
        };
        let work = KernelWork {
            dispatches: 3,
            ..KernelWork::other(3 * nv + 4 * nv + partials)
        } + product_work;
        ctx.count_kernels(work);
        Ok(())
    }

    fn flat_dims(&self, ctx: &Context, ncols: usize) -> Result<(u32, u32), GpuError> {
        ctx.dims(
            "refinement kernels",
            ((self.n * ncols) as u64).div_ceil(FLAT_WG as u64),
        )
    }
}

/// The sums read back after a round, per column: `(||r'||, ||x'||)`; and
/// the rounding floor's `eps ||A||_inf` the round ran with.
pub(crate) fn decode_norms(bytes: &[u8], ncols: usize) -> (Vec<(f64, f64)>, f64) {
    let v: Vec<f64> = bytemuck::pod_collect_to_vec(bytes);
    let sums = (0..ncols)
        .map(|c| {
            let at = NORMS_PER_COLUMN * c;
            (
                v.get(at).map_or(f64::NAN, |s| s.sqrt()),
                v.get(at + 1).map_or(f64::NAN, |s| s.sqrt()),
            )
        })
        .collect();
    let floor = v.get(NORMS_PER_COLUMN * ncols).copied().unwrap_or(f64::NAN);
    (sums, floor)
}

#[cfg(test)]
mod tests {
    use crate::precision::MixedPrecision;
    use solver_cpu::{SpdSolver, SymCsc};

    /// A path graph's Laplacian plus a small diagonal: SPD, with condition
    /// number in the hundreds of thousands at this size.
    fn path(n: usize) -> SymCsc {
        let mut a = SymCsc::from_pattern(n, (1..n).map(|i| (i - 1, i)));
        for i in 0..n {
            let d = a.slot(i, i).unwrap();
            a.values[d] += 1e-3 * (1.0 + (i % 7) as f64);
        }
        for i in 1..n {
            for (r, c, v) in [(i - 1, i - 1, 1.0), (i, i, 1.0), (i - 1, i, -1.0)] {
                let sl = a.slot(r, c).unwrap();
                a.values[sl] += v;
            }
        }
        a
    }

    fn relative_residual(a: &SymCsc, b: &[f64], x: &[f64]) -> f64 {
        let mut ax = vec![0.0; b.len()];
        a.mul_vec(x, &mut ax);
        let rr: f64 = b.iter().zip(&ax).map(|(u, v)| (u - v) * (u - v)).sum();
        let bb: f64 = b.iter().map(|u| u * u).sum();
        (rr / bb).sqrt()
    }

    /// A mixed-precision solve refines on the GPU: no residual formed on the
    /// host, `b` (and a nonzero guess) sent once, the result as accurate as
    /// asked; a zero column gives zero, and a guess that already solves its
    /// column is kept without PCG iterations.
    #[test]
    fn mixed_solves_refine_on_the_gpu() {
        let Some(mut s) = crate::test_solver() else {
            return;
        };
        if !s.ctx.shader_f64 {
            return;
        }
        s.set_mixed_precision(MixedPrecision::Always);
        let n = 3000;
        let a = path(n);
        s.prepare(&a).unwrap();
        s.set_tolerance(1e-10);
        let b: Vec<f64> = (0..3 * n)
            .map(|i| match i / n {
                0 => (0.01 * i as f64).sin(),
                1 => 0.0,
                _ => 1.0 + (i % 5) as f64,
            })
            .collect();
        // The first solve uploads the mixed-precision matrix; then, from a
        // zero guess, b alone goes up.
        let mut x = vec![0.0; 3 * n];
        s.solve_with_guess(&b, &mut x, 3).unwrap();
        x.fill(0.0);
        let before = s.ctx.traffic();
        let residuals = s.host_residuals;
        let info = s.solve_with_guess(&b, &mut x, 3).unwrap();
        let after = s.ctx.traffic();
        assert!(s.last_solve_mixed());
        assert_eq!(s.host_residuals, residuals, "no residual on the host");
        let vec_bytes = (3 * n * 8) as u64;
        let up = after.to_device - before.to_device;
        assert!(up >= vec_bytes && up < vec_bytes + 4096, "{up} bytes up");
        assert!(info.iterations > 0);
        for c in [0, 2] {
            let col = c * n..(c + 1) * n;
            let rel = relative_residual(&a, &b[col.clone()], &x[col]);
            assert!(rel <= 1e-10, "column {c}: {rel:e}");
        }
        assert!(x[n..2 * n].iter().all(|&v| v == 0.0), "b = 0 gives x = 0");
        // The solution as the guess: kept, with no PCG iteration; the guess
        // goes up beside b.
        let solved = x.clone();
        let before = s.ctx.traffic();
        let info = s.solve_with_guess(&b, &mut x, 3).unwrap();
        let up = s.ctx.traffic().to_device - before.to_device;
        assert_eq!(info.iterations, 0);
        assert_eq!(x, solved);
        assert!(
            up >= 2 * vec_bytes && up < 2 * vec_bytes + 4096,
            "{up} bytes up"
        );
        // A rough guess is refined from where it is.
        let mut x: Vec<f64> = solved.iter().map(|v| v * 1.01 + 1e-3).collect();
        s.solve_with_guess(&b, &mut x, 3).unwrap();
        for c in [0, 2] {
            let col = c * n..(c + 1) * n;
            let rel = relative_residual(&a, &b[col.clone()], &x[col]);
            assert!(rel <= 1e-10, "column {c} from a rough guess: {rel:e}");
        }
        assert_eq!(s.host_residuals, residuals);
        // A kind with no earlier run (no batch hint): the PCG's first batch
        // ends the round and brings x back, one wait for the solve.
        // (A better conditioned matrix of the pattern, which takes few
        // iterations.)
        s.set_system_kind(solver_cpu::SystemKind::FineTune);
        let mut easy = a.clone();
        for i in 0..n {
            let d = easy.slot(i, i).unwrap();
            easy.values[d] += 4.0;
        }
        s.prepare(&easy).unwrap();
        x.fill(0.0);
        let waits = s.ctx.traffic().waits;
        let info = s.solve_with_guess(&b, &mut x, 3).unwrap();
        assert!(info.iterations <= crate::pcg::FIRST_BATCH, "{info:?}");
        assert_eq!(s.ctx.traffic().waits - waits, 1);
    }
}
