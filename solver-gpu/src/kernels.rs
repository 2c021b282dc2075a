//! Single kernels on the prepared matrix, for the tests and the benchmark
//! (not needed to use the solver). Every output buffer is poisoned with NaN
//! before the kernel runs, so a kernel that writes nothing is caught.

use crate::csr_spmv;
use crate::device::{dispatch, Params, ROW_WG};
use crate::matrix::GpuMatrix;
use crate::pcg::{Pcg, PcgRun, Spmv};
pub use crate::precision::Precision;
use crate::{GpuError, GpuSolver, CMAX};

/// The prepared matrix as the GPU sees it: full (both triangles) block-CSR,
/// `bs` = 3 or 1, f64 values (`bs * bs` per block, row-major).
pub struct FullMatrix<'a> {
    pub bs: usize,
    pub rows: usize,
    pub row_ptr: &'a [u32],
    pub col_idx: &'a [u32],
    pub vals: Vec<f64>,
}

/// The prepared matrix, if any.
pub fn full_matrix(s: &GpuSolver) -> Option<FullMatrix<'_>> {
    s.host.as_ref().map(|h| FullMatrix {
        bs: h.bs,
        rows: h.rows,
        row_ptr: &h.row_ptr,
        col_idx: &h.col_idx,
        vals: h.full_values(),
    })
}

fn check_cols(s: &GpuSolver, len: usize, ncols: usize) -> Result<(usize, usize, usize), GpuError> {
    let h = s
        .host
        .as_ref()
        .ok_or_else(|| GpuError::Backend("no matrix prepared".into()))?;
    if ncols == 0 || ncols > CMAX || len != h.n() * ncols {
        return Err(GpuError::Backend(format!(
            "{len} entries for {ncols} columns of length {} (1..={CMAX} columns)",
            h.n()
        )));
    }
    Ok((h.rows, h.bs, h.n()))
}

fn poisoned(s: &GpuSolver, what: &str, len: usize) -> Result<wgpu::Buffer, GpuError> {
    s.ctx.storage_init(what, &vec![f32::NAN; len.max(1)])
}

/// `y = A x` with the SpMV kernel of the prepared matrix (block or scalar);
/// returns `y` and the per-column `x . y` reduced from the kernel's partials.
pub fn spmv(s: &GpuSolver, x: &[f32], ncols: usize) -> Result<(Vec<f32>, Vec<f64>), GpuError> {
    let (rows, bs, n) = check_cols(s, x.len(), ncols)?;
    let ctx = &s.ctx;
    let m = s.gpu.as_ref().unwrap();
    let groups = (rows as u64)
        .div_ceil(ROW_WG as u64)
        .max(m.partial_slots(rows));
    let params = ctx.uniform(
        "spmv params",
        &Params {
            rows: rows as u32,
            ncols: ncols as u32,
            n: n as u32,
            groups: groups as u32,
            bs: bs as u32,
            pad: [0; 3],
        },
    )?;
    let xb = ctx.storage_init("x", x)?;
    let y = poisoned(s, "y", x.len())?;
    let partials = poisoned(s, "partials", ncols * groups as usize)?;
    let spmv = s.spmv();
    let dispatches = spmv.bind(ctx, &params, m, &xb, &y, &partials, groups)?;
    let pipeline = spmv.kernel().pipeline(ctx, ncols)?;
    let mut enc = ctx.encoder("spmv");
    {
        let mut pass = enc.begin_compute_pass(&Default::default());
        for (bg, dims) in &dispatches {
            dispatch(&mut pass, &pipeline, bg, *dims);
        }
    }
    ctx.submit_wait(enc)?;
    let yv: Vec<f32> = ctx.read(&y, x.len(), &mut None, None)?;
    let pv: Vec<f32> = ctx.read(&partials, ncols * groups as usize, &mut None, None)?;
    let dots = pv
        .chunks(groups as usize)
        .map(|c| c.iter().map(|&v| v as f64).sum())
        .collect();
    Ok((yv, dots))
}

/// Chunks the prepared matrix is stored in on the GPU (block rows whose
/// values fit one storage binding; one for a scalar matrix), with the block
/// rows of each.
pub fn matrix_chunks(s: &GpuSolver) -> Vec<std::ops::Range<usize>> {
    use crate::matrix::MatrixStorage;
    match s.gpu.as_ref().map(|m| &m.storage) {
        Some(MatrixStorage::Blocks { chunks, .. })
        | Some(MatrixStorage::SplitBlocks { hi: chunks, .. }) => {
            chunks.iter().map(|c| c.rows.clone()).collect()
        }
        Some(MatrixStorage::Csr { .. }) => s
            .host
            .as_ref()
            .map(|h| std::iter::once(0..h.rows).collect())
            .unwrap_or_default(),
        None => Vec::new(),
    }
}

/// `a_c . b_c` for `ncols` columns of length `len / ncols` (two-pass reduction).
pub fn dot(s: &GpuSolver, a: &[f32], b: &[f32], ncols: usize) -> Result<Vec<f32>, GpuError> {
    if ncols == 0 || ncols > CMAX || a.len() != b.len() || !a.len().is_multiple_of(ncols) {
        return Err(GpuError::Backend("dot: bad lengths".into()));
    }
    let ctx = &s.ctx;
    let n = a.len() / ncols;
    let groups = (n as u64).div_ceil(ROW_WG as u64).max(1);
    let params = ctx.uniform(
        "dot params",
        &Params {
            rows: n as u32,
            ncols: ncols as u32,
            n: n as u32,
            groups: groups as u32,
            bs: 1,
            pad: [0; 3],
        },
    )?;
    let ab = ctx.storage_init("a", a)?;
    let bb = ctx.storage_init("b", b)?;
    let partials = poisoned(s, "partials", ncols * groups as usize)?;
    let out = poisoned(s, "out", ncols)?;
    let bg = s.k.dot.bind(ctx, &params, &ab, &bb, &partials, &out)?;
    let dims = ctx.dims("dot", groups)?;
    let (k1, k2) = (
        s.k.dot.partial.pipeline(ctx, ncols)?,
        s.k.dot.finish.pipeline(ctx, ncols)?,
    );
    let mut enc = ctx.encoder("dot");
    {
        let mut pass = enc.begin_compute_pass(&Default::default());
        dispatch(&mut pass, &k1, &bg, dims);
        dispatch(&mut pass, &k2, &bg, (1, 1));
    }
    ctx.read(&out, ncols, &mut None, Some(enc))
}

/// `z = M^-1 r` with the block-Jacobi kernel and the prepared matrix's inverse
/// diagonal blocks.
pub fn block_jacobi(s: &GpuSolver, r: &[f32], ncols: usize) -> Result<Vec<f32>, GpuError> {
    let (rows, bs, n) = check_cols(s, r.len(), ncols)?;
    let ctx = &s.ctx;
    let groups = (rows as u64).div_ceil(ROW_WG as u64).max(1);
    let params = ctx.uniform(
        "jacobi params",
        &Params {
            rows: rows as u32,
            ncols: ncols as u32,
            n: n as u32,
            groups: groups as u32,
            bs: bs as u32,
            pad: [0; 3],
        },
    )?;
    let rb = ctx.storage_init("r", r)?;
    let z = poisoned(s, "z", r.len())?;
    let bg =
        s.k.jacobi
            .bind(ctx, &params, &s.gpu.as_ref().unwrap().minv, &rb, &z)?;
    let dims = ctx.dims("block_jacobi", groups)?;
    let pipeline = s.k.jacobi.kernel.pipeline(ctx, ncols)?;
    let mut enc = ctx.encoder("block_jacobi");
    {
        let mut pass = enc.begin_compute_pass(&Default::default());
        dispatch(&mut pass, &pipeline, &bg, dims);
    }
    ctx.read(&z, r.len(), &mut None, Some(enc))
}

/// `z = M^-1 r`: one AMG V-cycle on the GPU with the prepared matrix's
/// hierarchy (AMG must be the active preconditioner). `z` and every level vector
/// are poisoned with NaN first.
pub fn amg_vcycle(s: &mut GpuSolver, r: &[f32], ncols: usize) -> Result<Vec<f32>, GpuError> {
    check_cols(s, r.len(), ncols)?;
    if s.amg_gpu.is_none() {
        return Err(GpuError::Backend(
            "AMG is not the active preconditioner".into(),
        ));
    }
    s.workspace(ncols)?;
    let ctx = &s.ctx;
    let ws = s.ws.as_ref().unwrap();
    let v = ws.amg.as_ref().unwrap();
    ctx.write_buffer(&ws.r, 0, bytemuck::cast_slice(r));
    for b in v.vectors.iter().chain([&ws.z]) {
        let nan = vec![f32::NAN; (b.size() / 4) as usize];
        ctx.write_buffer(b, 0, bytemuck::cast_slice(&nan));
    }
    let pipelines = v.pipelines(ctx, &s.k.amg, ncols)?;
    let mut enc = ctx.encoder("amg vcycle");
    {
        let mut pass = enc.begin_compute_pass(&Default::default());
        v.record(&mut pass, &pipelines);
    }
    ctx.read(&ws.z, r.len(), &mut None, Some(enc))
}

/// `z = B^-1 Mt B^-1 r`: the squared-Laplacian preconditioner on the GPU as
/// the PCG applies it (it must be the active preconditioner: a scale-driven
/// block matrix with a shape model). `z`, the middle vector and every level
/// vector are poisoned with NaN first.
pub fn squared_laplacian(s: &mut GpuSolver, r: &[f32], ncols: usize) -> Result<Vec<f32>, GpuError> {
    check_cols(s, r.len(), ncols)?;
    if s.squared.is_none() || s.amg_gpu.is_none() {
        return Err(GpuError::Backend(
            "the squared-Laplacian preconditioner is not active".into(),
        ));
    }
    s.workspace(ncols)?;
    let ctx = &s.ctx;
    let ws = s.ws.as_ref().unwrap();
    let q = ws.squared.as_ref().unwrap();
    ctx.write_buffer(&ws.r, 0, bytemuck::cast_slice(r));
    let cycles = q.first.iter().chain(&q.second);
    for b in cycles.flat_map(|c| &c.vectors).chain([&q.t, &ws.z]) {
        let nan = vec![f32::NAN; (b.size() / 4) as usize];
        ctx.write_buffer(b, 0, bytemuck::cast_slice(&nan));
    }
    let k = &s.k.amg;
    let pipes = |v: &[crate::amg_gpu::VcycleWorkspace]| {
        v.iter()
            .map(|c| c.pipelines(ctx, k, ncols))
            .collect::<Result<Vec<_>, _>>()
    };
    let (first, second) = (pipes(&q.first)?, pipes(&q.second)?);
    let scale = k.scale.kernel.pipeline(ctx, ncols)?;
    let mut enc = ctx.encoder("squared-Laplacian preconditioner");
    {
        let mut pass = enc.begin_compute_pass(&Default::default());
        for (c, p) in q.first.iter().zip(&first) {
            c.record(&mut pass, p);
        }
        q.scale.record(&mut pass, &scale);
        for (c, p) in q.second.iter().zip(&second) {
            c.record(&mut pass, p);
        }
    }
    ctx.read(&ws.z, r.len(), &mut None, Some(enc))
}

/// `z = (P^T L L^T P)^-1 r` for x, y and z of each column: the Cholesky
/// preconditioner's triangular solves on the GPU as the PCG applies them (it
/// must be the active preconditioner: a shape matrix prepared by
/// `prepare_shape_owned`). The work vector and `z` are poisoned with NaN first.
pub fn cholesky(s: &mut GpuSolver, r: &[f32], ncols: usize) -> Result<Vec<f32>, GpuError> {
    check_cols(s, r.len(), ncols)?;
    let precision = cholesky_workspace(s, ncols)?;
    let ws = cholesky_ws(s, precision);
    let f64 = precision == Precision::F64;
    let ctx = &s.ctx;
    let c = ws.chol.as_ref().unwrap();
    let input: Vec<f64> = r.iter().map(|&v| v as f64).collect();
    ctx.write_buffer(&ws.r, 0, &precision.encode(&input));
    for b in [c.work_vector(), &ws.z] {
        let nan = vec![f32::NAN; (b.size() / 4) as usize];
        ctx.write_buffer(b, 0, bytemuck::cast_slice(&nan));
    }
    let pipelines = c.pipelines(ctx, ncols)?;
    let mut enc = ctx.encoder("Cholesky preconditioner");
    {
        let mut pass = enc.begin_compute_pass(&Default::default());
        c.record(&mut pass, &pipelines);
    }
    match f64 {
        true => {
            let z: Vec<f64> = ctx.read(&ws.z, r.len(), &mut None, Some(enc))?;
            Ok(z.iter().map(|&v| v as f32).collect())
        }
        false => ctx.read(&ws.z, r.len(), &mut None, Some(enc)),
    }
}

/// The active Cholesky preconditioner's precision, with the workspace its
/// solves run on made for `ncols` columns ([`cholesky_ws`]).
fn cholesky_workspace(s: &mut GpuSolver, ncols: usize) -> Result<Precision, GpuError> {
    let Some(precision) = s.chol.as_ref().map(|f| f.precision) else {
        return Err(GpuError::Backend(
            "the Cholesky preconditioner is not active".into(),
        ));
    };
    match precision {
        Precision::F64 => s.mixed_workspace(ncols)?,
        Precision::F32 => s.workspace(ncols)?,
    };
    Ok(precision)
}

/// The workspace a factor of `precision` solves on: an f64 factor runs on
/// the mixed-precision PCG's f64 vectors (made by [`cholesky_workspace`]).
fn cholesky_ws(s: &GpuSolver, precision: Precision) -> &crate::pcg::Workspace {
    match precision {
        Precision::F64 => &s.mixed.as_ref().unwrap().ws,
        Precision::F32 => s.ws.as_ref().unwrap(),
    }
}

/// Whether the Laplacian square term's values are being summed ahead on
/// another thread (`GpuSolver::start_square_values`), and how many such
/// sums the shape matrices took.
pub fn square_values_ahead(s: &GpuSolver) -> (bool, usize) {
    (s.square_ahead.is_some(), s.squares_taken_ahead)
}

/// Whether the active Cholesky preconditioner's factor is f64.
pub fn cholesky_is_f64(s: &GpuSolver) -> Option<bool> {
    s.chol
        .as_ref()
        .map(|f| f.precision == crate::precision::Precision::F64)
}

/// Symbolic analyses the host's Cholesky factor of the shape systems has
/// made, its own or made ahead and adopted
/// ([`solver_cpu::SpdSolver::adopt_isotropic_analysis`]).
pub fn cholesky_analyses(s: &GpuSolver) -> usize {
    s.chol_host.symbolic_count
}

/// Numeric factorizations the host's Cholesky factor of the shape systems
/// has made itself (not those made ahead and adopted,
/// [`solver_cpu::SpdSolver::adopt_isotropic_factor`]).
pub fn cholesky_factorizations(s: &GpuSolver) -> usize {
    s.chol_host.numeric_count
}

/// Whether uploads go up on threads beside the caller (by default from 4
/// of rayon's threads on; a test sets it either way).
pub fn set_beside_uploads(s: &mut GpuSolver, on: bool) {
    s.beside_uploads = on;
}

/// Queue submissions the solver made on its caller's thread, and on
/// threads beside it (a factor made ahead, uploaded on its own thread,
/// [`solver_cpu::SpdSolver::adopt_isotropic_factor`]).
pub fn submissions(s: &GpuSolver) -> (u64, u64) {
    let t = s.ctx.traffic();
    (t.submits, t.beside_submits)
}

/// Bytes the solver sent to the device from threads beside its caller's.
pub fn beside_bytes(s: &GpuSolver) -> u64 {
    s.ctx.traffic().beside_to_device
}

/// Bytes of the active Cholesky preconditioner's value buffers; `None`
/// when it is not active.
pub fn cholesky_value_bytes(s: &GpuSolver) -> Option<u64> {
    s.chol
        .as_ref()
        .map(|f| f.vals.iter().map(|b| b.size()).sum())
}

/// Storage buffers the active Cholesky preconditioner's values are split
/// into (one where they fit a binding); `None` when it is not active.
pub fn cholesky_chunks(s: &GpuSolver) -> Option<usize> {
    s.chol.as_ref().map(|f| f.chunks())
}

/// Levels of the active Cholesky preconditioner's elimination tree (dispatches
/// per triangular solve), and its stored values; `None` when it is not active.
pub fn cholesky_shape(s: &GpuSolver) -> Option<(usize, usize)> {
    s.chol.as_ref().map(|f| (f.depth(), f.nnz))
}

/// Result of one f32 PCG run ([`pcg`]).
#[derive(Debug, Clone)]
pub struct PcgOutput {
    /// Solution, column-major (f32 kernels: their f32 values).
    pub x: Vec<f64>,
    /// Iterations per column.
    pub iterations: Vec<u32>,
    /// Final recurrence residual `||r|| / ||b||` per column.
    pub residual: Vec<f32>,
    /// Per column: 0 running (iteration cap), 1 converged, 2 breakdown.
    pub status: Vec<u32>,
    /// Iterations dispatched (a multiple of the check interval).
    pub dispatched: usize,
}

/// One plain f32 PCG solve on the GPU (no refinement), from x = 0, until
/// `||r|| <= rel_tol ||b||` per column or `max_iters`; `rel_tol = 0` runs exactly
/// `max_iters` iterations (in batches of the check interval, 32), for timing.
pub fn pcg(
    s: &mut GpuSolver,
    b: &[f32],
    ncols: usize,
    rel_tol: f32,
    max_iters: usize,
) -> Result<PcgOutput, GpuError> {
    check_cols(s, b.len(), ncols)?;
    s.workspace(ncols)?;
    let n = b.len() / ncols;
    let bb: Vec<f64> = (0..ncols)
        .map(|c| {
            b[c * n..(c + 1) * n]
                .iter()
                .map(|&v| (v as f64) * (v as f64))
                .sum()
        })
        .collect();
    let thr: Vec<f64> = bb.iter().map(|&v| v * (rel_tol as f64).powi(2)).collect();
    let ws = s.ws.as_mut().unwrap();
    s.ctx.write_buffer(&ws.r, 0, bytemuck::cast_slice(b));
    let spmv = match s.host.as_ref().unwrap().bs {
        1 => Spmv::Scalar(&s.k.csr),
        _ => Spmv::Block(&s.k.bsr),
    };
    let mut run = s.k.pcg.run(
        &s.ctx,
        &spmv,
        ws,
        ncols,
        &thr,
        max_iters,
        s.check_every,
        None,
        rel_tol == 0.0,
        Some(&s.k.amg),
        None,
        None,
    )?;
    let x = s.k.pcg.read_x(&s.ctx, ws, ncols, &mut run)?;
    Ok(PcgOutput::new(x, &run, &bb))
}

impl PcgOutput {
    fn new(x: Vec<f64>, run: &PcgRun, bb: &[f64]) -> PcgOutput {
        PcgOutput {
            x,
            iterations: run.cols.iter().map(|c| c.iters).collect(),
            residual: run
                .cols
                .iter()
                .zip(bb)
                .map(|(c, &b2)| ((c.rr as f64) / b2.max(f64::MIN_POSITIVE)).sqrt() as f32)
                .collect(),
            status: run.cols.iter().map(|c| c.done).collect(),
            dispatched: run.dispatched,
        }
    }
}

/// One plain PCG solve, as [`pcg`], on the scalar expansion of the prepared
/// matrix (CSR, every 3x3 block as 9 entries; scalar Jacobi) in `precision`:
/// the same kernels (`csr_spmv.wgsl`, `pcg.wgsl`) in f32 or, where the adapter
/// has `SHADER_F64`, in f64 (see [`crate::precision`]). For the precision
/// comparison of the benchmark: everything but the floating-point type is the
/// same between the two runs.
pub fn scalar_pcg(
    s: &mut GpuSolver,
    precision: Precision,
    b: &[f64],
    ncols: usize,
    rel_tol: f64,
    max_iters: usize,
) -> Result<PcgOutput, GpuError> {
    check_cols(s, b.len(), ncols)?;
    let ctx = &s.ctx;
    if precision == Precision::F64 && !ctx.shader_f64 {
        return Err(GpuError::Backend(format!(
            "f64 kernels need the adapter feature SHADER_F64, which {} lacks",
            ctx.info.name
        )));
    }
    let h = s.host.as_ref().unwrap();
    let n = h.n();
    let m = GpuMatrix::upload_scalar(ctx, h, precision)?;
    let pcg = Pcg::new(ctx, precision)?;
    let csr = csr_spmv::new_in(ctx, precision)?;
    let spmv = Spmv::Scalar(&csr);
    let mut ws = pcg.workspace(ctx, &spmv, &m, n, 1, ncols)?;
    let bb: Vec<f64> = b.chunks(n).map(|c| c.iter().map(|v| v * v).sum()).collect();
    let thr: Vec<f64> = bb.iter().map(|&v| v * rel_tol * rel_tol).collect();
    ctx.write_buffer(&ws.r, 0, &precision.encode(b));
    let mut run = pcg.run(
        ctx,
        &spmv,
        &mut ws,
        ncols,
        &thr,
        max_iters,
        s.check_every,
        None,
        rel_tol == 0.0,
        None,
        None,
        None,
    )?;
    let x = pcg.read_x(ctx, &mut ws, ncols, &mut run)?;
    ctx.check()?;
    Ok(PcgOutput::new(x, &run, &bb))
}

#[cfg(feature = "bench-kernels")]
/// Seconds per dispatch of each kernel of one PCG iteration on the prepared
/// matrix with `ncols` columns: `[(label, seconds)]` for the SpMV,
/// `finish_alpha`, `update`, `finish_beta` and `direction`.
pub fn profile_iteration(
    s: &mut GpuSolver,
    ncols: usize,
    reps: usize,
) -> Result<Vec<(&'static str, f64)>, GpuError> {
    if s.host.is_none() || ncols == 0 || ncols > CMAX {
        return Err(GpuError::Backend(
            "profile: no matrix or bad column count".into(),
        ));
    }
    s.workspace(ncols)?;
    let spmv = s.spmv();
    s.k.pcg
        .profile(&s.ctx, &spmv, s.ws.as_ref().unwrap(), ncols, reps.max(1))
}

#[cfg(feature = "bench-kernels")]
/// What one application of the Cholesky preconditioner costs ([`time_cholesky`]).
#[derive(Debug, Clone)]
pub struct CholeskyTiming {
    /// The chain of dependent steps through one application
    /// ([`crate::KernelWork::serial_steps`]).
    pub serial_steps: u64,
    /// Dispatches of one application.
    pub dispatches: u64,
    /// Device seconds per application, from timestamp queries around the
    /// pass (`None` without `TIMESTAMP_QUERY`).
    pub device_seconds: Option<f64>,
    /// Wall seconds per application, from the submission to the read-back.
    pub wall_seconds: f64,
    /// `z` of the last application, column-major.
    pub z: Vec<f64>,
}

#[cfg(feature = "bench-kernels")]
/// Times `reps` applications `z = (P^T L L^T P)^-1 r` of the active
/// Cholesky preconditioner (as [`cholesky`]: a shape matrix prepared by
/// `prepare_shape_owned`), recorded in one timed pass after one untimed
/// application, with teams of at most `most` lanes per dot product (1: one
/// lane each, the layout before teams): the latency a discrete GPU pays for
/// the chain of dependent steps against its bandwidth.
pub fn time_cholesky(
    s: &mut GpuSolver,
    r: &[f64],
    ncols: usize,
    reps: usize,
    most: u32,
) -> Result<CholeskyTiming, GpuError> {
    check_cols(s, r.len(), ncols)?;
    let precision = cholesky_workspace(s, ncols)?;
    let ws = cholesky_ws(s, precision);
    let f64 = precision == Precision::F64;
    let steps = s
        .cholesky_steps_with(precision, (&ws.r, &ws.z), 3, ncols, most)?
        .ok_or_else(|| GpuError::Backend("no Cholesky steps".into()))?;
    let ctx = &s.ctx;
    ctx.write_buffer(&ws.r, 0, &precision.encode(r));
    let pipelines = steps.pipelines(ctx, ncols)?;
    let bytes = r.len() as u64 * precision.bytes();
    let run = |reps: usize, timed: bool| -> Result<Vec<Vec<u8>>, GpuError> {
        let mut enc = ctx.encoder("Cholesky timing");
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("Cholesky applications"),
                timestamp_writes: if timed { ctx.pass_timestamps() } else { None },
            });
            for _ in 0..reps {
                steps.record(&mut pass, &pipelines);
            }
        }
        let mut parts = vec![(&ws.z, bytes)];
        if timed {
            ctx.resolve_pass_time(&mut enc);
            parts.extend(ctx.pass_time_buffer());
        }
        ctx.read_parts(&parts, &mut None, Some(enc))
    };
    run(1, false)?;
    let reps = reps.max(1);
    let before = ctx.traffic().timed_seconds;
    let t0 = std::time::Instant::now();
    let mut read = run(reps, true)?;
    let wall_seconds = t0.elapsed().as_secs_f64() / reps as f64;
    let device_seconds = match ctx.pass_time_buffer() {
        Some(_) => {
            let times = read.pop().unwrap_or_default();
            ctx.count_pass_time(&times);
            Some((ctx.traffic().timed_seconds - before) / reps as f64)
        }
        None => None,
    };
    let z = read.into_iter().next().unwrap_or_default();
    let z = match f64 {
        true => bytemuck::pod_collect_to_vec::<u8, f64>(&z),
        false => bytemuck::pod_collect_to_vec::<u8, f32>(&z)
            .into_iter()
            .map(f64::from)
            .collect(),
    };
    let work = steps.work(ncols);
    Ok(CholeskyTiming {
        serial_steps: work.serial_steps,
        dispatches: work.dispatches,
        device_seconds,
        wall_seconds,
        z,
    })
}

#[cfg(feature = "bench-kernels")]
/// The adapter's read-bandwidth ceiling over `bytes` bytes (rounded up to
/// 16-byte elements, at most one storage binding) read from a storage
/// buffer, `reps` timed passes (see [`crate::stream`]).
pub fn read_ceiling(
    s: &GpuSolver,
    bytes: u64,
    reps: usize,
) -> Result<crate::stream::ReadCeiling, GpuError> {
    crate::stream::measure(&s.ctx, bytes.div_ceil(16).max(1), reps)
}
