//! The refinement rounds of the mixed-precision solve: each round an f32
//! (or f64-iterate, f32-preconditioner) PCG on the scaled residual, then
//! `x += scale d`, with the residuals, their norms and each column's target
//! formed on the GPU where the exact matrix is there (`refine.wgsl`,
//! `refine_product.wgsl`), else on the host; and the per-kind hints of a
//! round's first batch.

use super::*;

/// One refinement round on the GPU: the scaled residuals `r` (bytes in the
/// workspace's precision) in, PCG to the squared thresholds `thr`, then
/// `x_c += scale_c d_c` for the columns with a nonzero `scale` (their residual
/// norm). Returns the iterations, and whether the PCG broke down (then `x`
/// is left as it was).
pub(super) struct Round<'a> {
    pub(super) ctx: &'a Context,
    pub(super) pcg: &'a pcg::Pcg,
    pub(super) spmv: &'a Spmv<'a>,
    pub(super) amg: &'a amg_gpu::AmgKernels,
    pub(super) convert: Option<&'a convert::Convert>,
    pub(super) budget: usize,
    pub(super) check_every: usize,
    /// Iterations of the first batch ([`BatchHints`]; `None`: nothing known).
    pub(super) first_batch: Option<usize>,
}

impl Round<'_> {
    pub(super) fn run(
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
pub(super) struct BatchHints(std::collections::HashMap<(SystemKind, bool, usize), usize>);

impl BatchHints {
    pub(super) fn key(kind: SystemKind, mixed: bool, round: usize) -> (SystemKind, bool, usize) {
        (kind, mixed, round.min(3))
    }

    /// Iterations of the first batch of round `round`, if a run like it was seen.
    pub(super) fn first_batch(&self, kind: SystemKind, mixed: bool, round: usize) -> Option<usize> {
        self.0
            .get(&Self::key(kind, mixed, round))
            .map(|&it| it.max(2))
    }

    pub(super) fn record(
        &mut self,
        kind: SystemKind,
        mixed: bool,
        round: usize,
        iterations: usize,
    ) {
        self.0.insert(Self::key(kind, mixed, round), iterations);
    }

    pub(super) fn clear(&mut self) {
        self.0.clear();
    }
}

/// The f64 kernels of the mixed-precision solve.
pub(super) struct MixedKernels {
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
    fn new(ctx: &device::Context) -> Result<Self, GpuError> {
        Ok(MixedKernels {
            pcg: pcg::Pcg::new(ctx, precision::Precision::F64)?,
            csr: csr_spmv::new_in(ctx, precision::Precision::F64)?,
            bsr: bsr_spmv::new_f64(ctx)?,
            convert: convert::Convert::new(ctx)?,
            refine: refine::RefineKernels::new(ctx)?,
        })
    }

    /// The kernels of an f64 solve of a block matrix with an f64 Cholesky
    /// preconditioner, beside the factor's own: the product, the PCG steps,
    /// the refinement.
    pub(super) fn block_solve_kernels(&self) -> Vec<&device::Kernel> {
        let p = &self.pcg;
        let mut k = vec![
            &self.bsr.kernel,
            &p.finish_alpha,
            &p.finish_beta,
            &p.direction,
            &p.update_amg,
            &p.dot_rz,
        ];
        k.extend(self.refine.kernels());
        k
    }

    /// The kernels of a block matrix's rounding floor, once per matrix
    /// (their pipelines for one column).
    pub(super) fn block_floor_kernels(&self) -> [&device::Kernel; 2] {
        self.refine.floor_kernels()
    }

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
    pub(super) stamp: (usize, usize),
    /// Read through the workspace's bind groups only.
    pub(crate) matrix: GpuMatrix,
    pub(crate) ws: Workspace,
    /// The refinement's vectors ([`crate::refine`]).
    pub(crate) refine: refine::Refinement,
    /// Whether `ws`'s preconditioner steps are of the solver's current
    /// preconditioner: a new one (a kind's factor) leaves the matrix, its
    /// expansion and the vectors as they are, and only the steps are made
    /// again ([`GpuSolver::drop_preconditioner_steps`]).
    pub(super) steps_current: bool,
}

impl GpuSolver {
    /// Whether the mixed-precision solve can run (f64 kernels and AMG).
    pub(super) fn mixed_available(&self) -> bool {
        self.ctx.shader_f64
            && (self.amg_gpu.is_some() || self.chol.is_some())
            && self.mixed_precision != MixedPrecision::Never
    }

    /// The mixed-precision matrix and workspace for at least `ncols` columns.
    /// A matrix of the uploaded pattern is kept: more columns make new
    /// vectors over it, and a new preconditioner new steps; neither sets up
    /// its expansion again (the map and the values sent up once more).
    pub(crate) fn mixed_workspace(&mut self, ncols: usize) -> Result<(), GpuError> {
        let stamp = (self.pattern_uploads, self.value_uploads);
        let want = ncols.min(CMAX);
        let block = self.host.as_ref().is_some_and(|h| h.bs == 3);
        if let Some(m) = self.mixed.as_mut() {
            if m.stamp.0 == stamp.0 && (block || m.stamp.1 == stamp.1) {
                if m.stamp.1 != stamp.1 {
                    // Same pattern, new values: rewrite them in place (the
                    // high parts are the f32 matrix's, already written).
                    let h = self.host.as_ref().unwrap();
                    m.matrix.write_values(&self.ctx, h, Some(&[]));
                    m.stamp = stamp;
                }
                if m.ws.cmax < want {
                    let mut m = self.mixed.take().unwrap();
                    let (ws, refine) = self.mixed_vectors(&m.matrix, want)?;
                    (m.ws, m.refine, m.steps_current) = (ws, refine, true);
                    self.mixed = Some(m);
                } else if !m.steps_current {
                    let mut m = self.mixed.take().unwrap();
                    self.mixed_steps(&mut m.ws)?;
                    m.steps_current = true;
                    self.mixed = Some(m);
                }
                return Ok(());
            }
        }
        self.mixed = None;
        // A shape matrix whose blocks the GPU sums has no blocks on the host:
        // the new matrix's low parts are summed and expanded there too.
        let on_gpu = self.host.as_ref().is_some_and(|h| h.shape_form().is_some());
        self.build_mixed(want, stamp, on_gpu, None)?;
        if on_gpu {
            let mut h = self.host.take().unwrap();
            let done = self.expand_on_gpu(&h);
            if matches!(done, Ok(true)) {
                h.release_map();
            }
            if matches!(done, Ok(false)) {
                self.mixed
                    .as_ref()
                    .unwrap()
                    .matrix
                    .write_values(&self.ctx, &h, Some(&[]));
            }
            self.host = Some(h);
            done?;
        }
        Ok(())
    }

    /// The f64 kernels of the mixed-precision solve, made on first use.
    pub(super) fn mixed_kernels(&mut self) -> Result<&MixedKernels, GpuError> {
        if self.mixed_kernels.is_none() {
            self.mixed_kernels = Some(MixedKernels::new(&self.ctx)?);
        }
        Ok(self.mixed_kernels.as_ref().unwrap())
    }

    /// [`Self::mixed_workspace`]'s new matrix and workspace, its low parts
    /// written from the host unless `unwritten`; the matrix `made` where
    /// it was made ahead of its values (the split f64 matrix of the
    /// uploaded pattern, [`Self::start_pattern_ahead`]).
    pub(super) fn build_mixed(
        &mut self,
        want: usize,
        stamp: (usize, usize),
        unwritten: bool,
        made: Option<GpuMatrix>,
    ) -> Result<(), GpuError> {
        self.mixed_kernels()?;
        let h = self.host.as_ref().unwrap();
        let matrix = match (made, h.bs) {
            (Some(m), _) => m,
            (None, 1) => GpuMatrix::upload_scalar(&self.ctx, h, precision::Precision::F64)?,
            (None, _) => GpuMatrix::upload_split_f64(
                &self.ctx,
                h,
                self.gpu.as_ref().unwrap(),
                !unwritten,
                self.diagonal_current,
            )?,
        };
        let (ws, refine) = self.mixed_vectors(&matrix, want)?;
        self.mixed = Some(MixedData {
            stamp,
            matrix,
            ws,
            refine,
            steps_current: true,
        });
        self.mixed_builds += 1;
        Ok(())
    }

    /// The workspace of `want` columns over the mixed-precision `matrix`,
    /// with the current preconditioner's steps, and the refinement's vectors.
    fn mixed_vectors(
        &self,
        matrix: &GpuMatrix,
        want: usize,
    ) -> Result<(Workspace, refine::Refinement), GpuError> {
        let k = self.mixed_kernels.as_ref().unwrap();
        let h = self.host.as_ref().unwrap();
        let spmv = k.spmv(h.bs);
        let mut ws = k.pcg.workspace(&self.ctx, &spmv, matrix, h.n(), 1, want)?;
        let refine = refine::Refinement::new(&self.ctx, &k.refine, &spmv, matrix, &ws)?;
        self.mixed_steps(&mut ws)?;
        Ok((ws, refine))
    }

    /// `ws`'s steps of the current preconditioner: an f64 factor's solves
    /// on the f64 vectors in place, else the f32 factor, squared Laplacian
    /// or V-cycle on f32 copies of them.
    fn mixed_steps(&self, ws: &mut Workspace) -> Result<(), GpuError> {
        let k = self.mixed_kernels.as_ref().unwrap();
        let bs = self.host.as_ref().unwrap().bs;
        ws.drop_preconditioner_steps();
        ws.chol = self.cholesky_steps(precision::Precision::F64, &ws.r, &ws.z, bs, ws.cmax)?;
        if ws.chol.is_some() {
            return Ok(());
        }
        let narrow = pcg::Narrow::new(&self.ctx, &k.convert, ws)?;
        let f32_chol = self.cholesky_steps(
            precision::Precision::F32,
            &narrow.r32,
            &narrow.z32,
            bs,
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
        Ok(())
    }

    /// Solve up to CMAX columns in mixed precision from the start `x`: rounds
    /// of f64 PCG on the f64 residual (preconditioned by the Cholesky factor
    /// in its precision, else by the f32 V-cycle), refined on the GPU
    /// ([`crate::refine`]). `bnorm`: the columns' `||b||`; `total`: PCG
    /// iterations already spent on these columns.
    pub(super) fn solve_batch_mixed(
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
        // A block matrix's floor is found on the GPU from its exact values
        // (the exact product is bound: `refine_on_gpu`); a scalar one's
        // `||A||_inf` is the host's, one parallel pass over its values.
        let h = self.host.as_ref().unwrap();
        let floor = match h.bs {
            1 => refine::Floor::Host(f64::EPSILON * h.norm_inf()),
            _ => refine::Floor::OnGpu(self.matrices),
        };
        let x = &mut x[..n * ncols];
        let mixed = self.mixed.as_ref().unwrap();
        mixed
            .refine
            .load(&self.ctx, b, x, ncols, bnorm, self.tol, floor);
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
                    let mut got = self.ctx.read_parts(
                        &[
                            (&mixed.refine.norms, refine::norms_bytes(ncols)),
                            (&mixed.refine.xnew, (n * ncols * 8) as u64),
                        ],
                        &mut None,
                        Some(enc),
                    )?;
                    let v = got.pop().unwrap_or_default();
                    (got.pop().unwrap_or_default(), v)
                }
            };
            // The floor the round ran with: the host's, or the GPU's of the
            // exact values.
            let (sums, eps_anorm) = refine::decode_norms(&norms, ncols);
            self.ctx.recycle(norms);
            let mut worst = 0.0f64;
            let mut done = true;
            for (c, &(rn, xn)) in sums.iter().enumerate() {
                if bnorm[c] == 0.0 {
                    continue;
                }
                let rel = rn / bnorm[c];
                let target = self.residual_target(eps_anorm, xn, bnorm[c]);
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
    pub(super) fn mixed_round_progressed(
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
    pub(super) fn round_eta(&self, rel: f64) -> f64 {
        (0.5 * self.tol / rel).clamp(1e-13, 0.1)
    }

    /// The relative residual a column must reach: the tolerance, or the f64
    /// rounding floor `eps ||A|| ||x|| / ||b||` where that is larger (a smooth
    /// right-hand side of a stiff system has a large solution, and no f64
    /// solver, Cholesky included, gets its relative residual below that
    /// floor). `eps_anorm`: `eps ||A||_inf` (`HostMatrix::norm_inf`, or the
    /// GPU's of the exact values). The GPU's refinement applies the same
    /// rule (`refine.wgsl`'s `start`).
    pub(super) fn residual_target(&self, eps_anorm: f64, xnorm: f64, bnorm: f64) -> f64 {
        self.tol.max(eps_anorm * xnorm / bnorm)
    }

    /// Per column: the f64 residual `r = b - A x` of the host's matrix (in
    /// `r`), its norm, the relative residual `||r|| / ||b||` (`bnorm`: the
    /// columns' `||b||`) and its [`Self::residual_target`]. Also the largest
    /// relative residual. The one place a residual is formed on the host:
    /// counted in `host_residuals`.
    pub(super) fn host_residuals_of(
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
                    target[c] = self.residual_target(
                        f64::EPSILON * anorm,
                        norm(&x[c * n..(c + 1) * n]),
                        bn,
                    );
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
    pub(super) fn mixed_rounds_host(
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
    pub(super) fn refine_on_gpu(&mut self) -> Result<bool, GpuError> {
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
}

/// A column's [`GpuSolver::residual_target`] holds once it has run a round
/// (`ran`): before, its true residual must reach the tolerance `tol` itself.
/// The rounding floor says the true residual can not show the error falling
/// further, not that the error is small: a warm start of homer 1.2M's
/// fine-tune at a relative residual of 1e-2 was taken as solved under a
/// floor of 0.54 (`refine.wgsl`'s `start` applies the same rule).
pub(super) fn floor_after_a_round(target: &mut [f64], ran: &[bool], tol: f64) {
    for (t, &r) in target.iter_mut().zip(ran) {
        if !r {
            *t = t.min(tol);
        }
    }
}
