//! Pipelines compiled ahead of their use ([`SpdSolver::warm_up`]).
//!
//! A driver compiles each compute pipeline (one per kernel and column
//! count) when it is made, from its shader cache where it has one. A run
//! makes about 60 (homer 108k, two girths and the volume: 16 for the scale
//! factors' Newton steps, 17 for the first scale-driven solve, 15 for each
//! of the fine-tune's two column counts). Made on first use, they sit on the
//! run's path; here a kind's are made on a thread of their own from the
//! run's start, while the host sets up the systems. The kind's first solve
//! (or estimation, or shape matrix) waits for that thread to end, so that
//! every pipeline of the plan is made once, by that thread: each kind's plan
//! is what its first solve runs, but for the fine-tune's later column count.
//!
//! Only the default path is compiled ahead: the Cholesky preconditioner
//! with an f64 factor and the f64 PCG (an adapter with `SHADER_F64`). Other
//! paths compile on first use, as before.

use super::*;

impl GpuSolver {
    /// Starts compiling, on another thread, the pipelines that solves of
    /// `kind` with these column counts run; returns how many it will
    /// compile (0 where the kind's path is not the one compiled ahead).
    /// The kernels' families are made here (their shader modules), so that
    /// the solves use the very kernels whose pipelines the thread makes.
    pub(super) fn warm_up_kind(
        &mut self,
        kind: SystemKind,
        columns: &[usize],
    ) -> Result<usize, GpuError> {
        let precision = self.factor_precision(kind);
        if precision != precision::Precision::F64 || self.preconditioner != Preconditioner::Cholesky
        {
            return Ok(0);
        }
        let mut columns: Vec<usize> = columns.iter().map(|&c| c.clamp(1, CMAX)).collect();
        columns.sort_unstable();
        columns.dedup();
        if self
            .chol_kernels
            .as_ref()
            .is_none_or(|k| k.precision != precision)
        {
            self.chol_kernels = Some(supernodal::SupernodalKernels::new(&self.ctx, precision)?);
        }
        let chol = self.chol_kernels.clone().unwrap();
        let mut work: Vec<(device::Kernel, usize)> = Vec::new();
        let mut each = |kernels: &[&device::Kernel], cols: &[usize]| {
            for &c in cols {
                work.extend(kernels.iter().map(|&k| (k.clone(), c)));
            }
        };
        match kind {
            SystemKind::ScaleFactors => {
                if self.newton_kernels.is_none() {
                    self.newton_kernels = Some(power_sum_newton::NewtonKernels::new(&self.ctx)?);
                }
                let newton = self.newton_kernels.as_ref().unwrap();
                // The Newton steps' kernels with one column per constraint
                // (the most columns asked), the factor's solves with each
                // count asked (after the first step only the rows of degree
                // above 1 change, and only their columns are solved).
                let all = columns.last().copied().unwrap_or(1);
                each(&newton.kernels(), &[all]);
                each(&chol.kernels().each_ref(), &columns);
            }
            SystemKind::ScaleDriven | SystemKind::FineTune => {
                if kind == SystemKind::ScaleDriven {
                    // A kind's first matrix is expanded and summed on the GPU.
                    if self.expand.is_none() {
                        self.expand = Some(expand_blocks::ExpandBlocks::new(&self.ctx)?);
                    }
                    each(&self.expand.as_ref().unwrap().kernels(), &[1]);
                }
                each(&self.mixed_kernels()?.block_solve_kernels(), &columns);
                each(&self.mixed_kernels()?.block_floor_kernels(), &[1]);
                each(&chol.kernels().each_ref(), &columns);
            }
        }
        // The factorization's kernels, where the kind's factor is made on the
        // GPU (the scale factors' own; the scale-driven kind's, whose
        // pipelines the fine-tune's uses too): on a thread of their own, the
        // kind's first work on the device, which waits for them alone
        // (`factor_pipelines_ready`). Shared by the solvers of the device: a
        // second thread finds them made, or waits for the one making them.
        let factor_kind = kind != SystemKind::FineTune && self.factors_on_gpu(kind);
        let factor_work: Vec<(device::Kernel, usize)> = match factor_kind {
            true => (self.factor_kernels()?.kernels().iter())
                .map(|k| (k.clone(), 1))
                .collect(),
            false => Vec::new(),
        };
        let factor_count = factor_work.len();
        if factor_count > 0 {
            let ctx = self.ctx.clone();
            let thread = std::thread::Builder::new()
                .name(format!("factorization pipelines ahead ({kind:?})"))
                .spawn(move || {
                    for (k, c) in &factor_work {
                        if let Err(e) = k.compile_ahead(&ctx, *c) {
                            log::debug!("{e}, compiled ahead; left to its use");
                        }
                    }
                });
            match thread {
                Ok(h) => self.factor_warming.push(h),
                Err(e) => log::debug!("no thread to compile pipelines ahead: {e}"),
            }
        }
        let count = work.len() + factor_count;
        let ctx = self.ctx.clone();
        let name = format!("pipelines ahead ({kind:?})");
        let thread = std::thread::Builder::new().name(name).spawn(move || {
            let t = std::time::Instant::now();
            for (k, c) in &work {
                if let Err(e) = k.compile_ahead(&ctx, *c) {
                    // The use compiles it again and reports the error.
                    log::debug!("{e}, compiled ahead; left to its use");
                }
            }
            log::debug!(
                "{kind:?} system: {} pipelines compiled ahead on another thread in {:.3} s",
                work.len(),
                t.elapsed().as_secs_f64()
            );
        });
        match thread {
            Ok(h) => self.warming.push((kind, h)),
            Err(e) => log::debug!("no thread to compile pipelines ahead: {e}"),
        }
        Ok(count)
    }

    /// Waits until every compilation ahead has ended.
    pub fn wait_for_warm_up(&mut self) {
        for (_, h) in self.warming.drain(..) {
            let _ = h.join();
        }
        for h in self.factor_warming.drain(..) {
            let _ = h.join();
        }
    }

    /// Waits for the GPU factorization's pipelines compiled ahead: before
    /// a factorization is submitted.
    pub(super) fn factor_pipelines_ready(&mut self) {
        if self.factor_warming.is_empty() {
            return;
        }
        let t = std::time::Instant::now();
        for h in self.factor_warming.drain(..) {
            let _ = h.join();
        }
        log::debug!(
            "waited {:.3} s for the factorization's pipelines compiled ahead",
            t.elapsed().as_secs_f64()
        );
    }

    /// Waits for the compilations ahead of the current system kind: before
    /// its first pipeline runs.
    pub(super) fn kind_pipelines_ready(&mut self) {
        if self.warming.is_empty() {
            return;
        }
        let kind = self.kind;
        let (mine, others): (Vec<_>, Vec<_>) = std::mem::take(&mut self.warming)
            .into_iter()
            .partition(|(k, _)| *k == kind);
        self.warming = others;
        for (_, h) in mine {
            let t = std::time::Instant::now();
            let _ = h.join();
            log::debug!(
                "{kind:?} system: waited {:.3} s for its pipelines compiled ahead",
                t.elapsed().as_secs_f64()
            );
        }
    }
}

impl Drop for GpuSolver {
    /// The threads compiling for the solver's device, and the one setting
    /// a shape pattern up ahead, end before the solver does, so that the
    /// device is dropped where the solver is.
    fn drop(&mut self) {
        self.wait_for_warm_up();
        self.wait_for_pattern_ahead();
    }
}
