//! The preconditioner's set-up, at most once per system kind per run: the
//! supernodal Cholesky factor of `K` (made on the host, uploaded once), or
//! the squared-Laplacian or matrix AMG hierarchies.

use super::*;

/// A shape kind's factor made ahead on its way to the GPU, on a thread of
/// its own, or up already ([`GpuSolver::upload_factor_ahead`]), and its
/// precision.
pub(crate) struct FactorUpload {
    upload: Uploading,
    precision: precision::Precision,
}

enum Uploading {
    Beside(std::thread::JoinHandle<Result<supernodal::GpuFactor, GpuError>>),
    Done(Result<supernodal::GpuFactor, GpuError>),
}

impl GpuSolver {
    /// Build (or refresh) the AMG hierarchy of the prepared host matrix.
    pub(super) fn setup_amg(&mut self) -> Result<(), GpuError> {
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
    pub(super) fn finish_setup(&mut self, what: &str, hier: amg::Hierarchy, t: std::time::Instant) {
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
    pub(super) fn cholesky_steps(
        &self,
        precision: precision::Precision,
        r: &wgpu::Buffer,
        z: &wgpu::Buffer,
        bs: usize,
        cmax: usize,
    ) -> Result<Option<supernodal::SupernodalSteps>, GpuError> {
        self.cholesky_steps_with(precision, (r, z), bs, cmax, supernodal::MAX_TEAM)
    }

    /// [`GpuSolver::cholesky_steps`] with teams of at most `most` lanes
    /// per dot product (1: one lane each; a benchmark compares them).
    pub(crate) fn cholesky_steps_with(
        &self,
        precision: precision::Precision,
        (r, z): (&wgpu::Buffer, &wgpu::Buffer),
        bs: usize,
        cmax: usize,
        most: u32,
    ) -> Result<Option<supernodal::SupernodalSteps>, GpuError> {
        match (&self.chol, &self.chol_kernels) {
            (Some(f), Some(k)) if f.precision == precision => {
                Ok(Some(supernodal::SupernodalSteps::with_teams(
                    &self.ctx,
                    k,
                    f,
                    (r, z),
                    bs,
                    cmax,
                    matrix::binding_limit(&self.ctx),
                    most,
                )?))
            }
            _ => Ok(None),
        }
    }

    /// Most columns one PCG batch carries: [`CMAX`], fewer where the Cholesky
    /// preconditioner's updates for that many would not fit a storage binding.
    pub(super) fn batch_columns(&self) -> usize {
        match (&self.chol, self.host.as_ref()) {
            (Some(f), Some(h)) => f.max_columns(matrix::binding_limit(&self.ctx), h.bs),
            _ => CMAX,
        }
    }

    /// Whether the next matrix is preconditioned by a Cholesky factor: that
    /// of K for the shape systems (`prepare_shape_owned`), the matrix's own
    /// for the scale factors' constant Hessian (`prepare`, scalar).
    pub(super) fn cholesky_wanted(&self) -> bool {
        self.preconditioner == Preconditioner::Cholesky && !self.chol_unavailable[self.chol_group()]
    }

    /// Whether the current shape kind's Cholesky preconditioner is made:
    /// a new matrix of the kind keeps it, and no AMG is set up for it.
    pub(super) fn shape_factor_made(&self) -> bool {
        self.kind != SystemKind::ScaleFactors
            && self.cholesky_wanted()
            && self.chol.is_some()
            && self.chol_kind == Some(self.kind)
    }

    /// Which of [`Self::chol_unavailable`] the current kind reads: the shape
    /// systems share one (their factors are of the same size), the scale
    /// factors have their own.
    pub(super) fn chol_group(&self) -> usize {
        self.chol_group_of(self.kind)
    }

    /// The index of `kind` in [`Self::chol_unavailable`] and the like.
    pub(super) fn chol_group_of(&self, kind: SystemKind) -> usize {
        usize::from(kind == SystemKind::ScaleFactors)
    }

    /// Keep the Cholesky preconditioner of this kind (`current`: it was made
    /// for this pattern and kind), or set it up by factoring `k()` (of the
    /// lower CSC pattern `(col_ptr, row_idx)`; not made where a factor made
    /// ahead serves); where that
    /// fails (over the storage bindings, or not positive definite in the
    /// factor's precision) the kind's other preconditioner is used for the
    /// rest of the run.
    pub(super) fn cholesky_for_kind(
        &mut self,
        current: bool,
        pattern: (&[usize], &[usize]),
        k: impl FnOnce() -> SymCsc,
    ) {
        if !self.cholesky_wanted() {
            self.drop_cholesky();
            return;
        }
        if current && self.chol.is_some() && self.chol_kind == Some(self.kind) {
            return;
        }
        if let Err(e) = self.setup_cholesky(pattern, k) {
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

    pub(super) fn drop_cholesky(&mut self) {
        if self.chol.is_some() {
            self.chol = None;
            self.chol_kind = None;
            self.drop_preconditioner_steps();
        }
    }

    /// The precision of the Cholesky factor of `kind`: f64 where its PCG
    /// runs in f64 (mixed precision) from the start, since `K` is too
    /// ill-conditioned for an f32 factorization on large meshes (homer 1.2M:
    /// not positive definite in f32) and the f64 solves read the PCG's
    /// vectors in place; else f32, for the f32 PCG. The scale factors'
    /// factor (of their matrix itself, which starts them in mixed
    /// precision) is f64 too: their Newton steps run on the device with it
    /// as a direct solve ([`SpdSolver::power_sum_newton`]).
    pub(super) fn factor_precision(&self, kind: SystemKind) -> precision::Precision {
        let own_factor = kind == SystemKind::ScaleFactors;
        match self.ctx.shader_f64 && self.mixed_precision.starts_mixed_with(kind, own_factor) {
            true => precision::Precision::F64,
            false => precision::Precision::F32,
        }
    }

    /// Factor `k()` (of the pattern `(col_ptr, row_idx)`) on the host and
    /// upload the factor, or take this kind's factor made ahead and uploaded
    /// already: the preconditioner of this system kind for the rest of the
    /// run. For the shape systems `k` is the isotropic part K of the matrix
    /// (held rows identity); for the scale factors the Hessian of Eq. 3
    /// itself, which is constant, so that the PCG converges in an iteration
    /// or two a round. Any other preconditioner is released.
    pub(super) fn setup_cholesky(
        &mut self,
        (col_ptr, row_idx): (&[usize], &[usize]),
        k: impl FnOnce() -> SymCsc,
    ) -> Result<(), GpuError> {
        let t = std::time::Instant::now();
        self.setups += 1;
        self.drop_cholesky();
        let precision = self.factor_precision(self.kind);
        // This kind's factor submitted to the GPU ahead
        // (`factor_isotropic_on_device`), where it is of this pattern.
        let on_gpu_ahead = match self.gpu_factor_ahead.take() {
            Some((kind, made)) if kind == self.kind => self
                .chol_host
                .has_analysed(col_ptr, row_idx)
                .then_some(made),
            other => {
                self.gpu_factor_ahead = other;
                None
            }
        };
        let on_gpu_ahead = on_gpu_ahead.and_then(|made| {
            self.finish_factor_on_gpu(made, false)
                .inspect_err(|e| log::debug!("Cholesky factor on the GPU ahead: {e}"))
                .ok()
        });
        // This kind's factor, made ahead on another thread from another `K`
        // of the kind and uploaded already (`adopt_isotropic_factor`):
        // taken in place of this one's factorization where it fits.
        let ahead = match self.chol_ahead.take() {
            Some((kind, up)) if kind == self.kind => {
                let fits =
                    up.precision == precision && self.chol_host.has_analysed(col_ptr, row_idx);
                if !fits {
                    log::debug!(
                        "Cholesky factor made ahead ({kind:?} system) does not fit; factored here"
                    );
                }
                match fits {
                    true => self.join_factor_upload(kind, up),
                    false => None,
                }
            }
            other => {
                self.chol_ahead = other;
                None
            }
        };
        self.drop_preconditioner_steps();
        self.amg_host = None;
        self.amg_gpu = None;
        self.squared = None;
        self.amg_kind = None;
        let (g, made) = match (ahead, on_gpu_ahead) {
            (_, Some((g, text))) => {
                self.setups_ahead += 1;
                (g, format!("{text}, submitted ahead"))
            }
            (Some(g), None) => {
                self.setups_ahead += 1;
                (g, "made ahead".to_string())
            }
            (None, None) => {
                let k = k();
                let on_gpu = match self.factors_on_gpu(self.kind) {
                    true => self
                        .factor_on_gpu(&k)
                        .inspect_err(|e| {
                            log::debug!("Cholesky factor on the GPU: {e}; made on the host")
                        })
                        .ok(),
                    false => None,
                };
                match on_gpu {
                    Some(made) => made,
                    None => {
                        let t = std::time::Instant::now();
                        let f = self.factor_here(k, precision)?;
                        let factor_seconds = t.elapsed().as_secs_f64();
                        let (mut g, inverse_seconds) = self.upload_factor(f)?;
                        g.analysis = self.chol_host.analysis_id();
                        let made = format!(
                            "factor {factor_seconds:.3} s, its inverted form {inverse_seconds:.3} s"
                        );
                        (g, made)
                    }
                }
            }
        };
        log::debug!(
            "Cholesky preconditioner ({:?} system, {:?}): {} unknowns, {} supernodes, {} levels, \
             nnz(L) {} in {} buffers, {made}, setup {:.3} s",
            self.kind,
            precision,
            g.nv,
            g.supernodes(),
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

    /// The f64 factor of `k` made on the GPU from its values
    /// ([`crate::factorize`]), on the host's symbolic analysis of its pattern
    /// (made here unless made before), and how it was made.
    fn factor_on_gpu(&mut self, k: &SymCsc) -> Result<(supernodal::GpuFactor, String), GpuError> {
        let made = self.start_factor_on_gpu(self.kind, k, true, 1)?;
        self.finish_factor_on_gpu(made, true)
    }

    /// [`Self::factor_on_gpu`] of `kind`'s matrix up to its submission (in
    /// `slices`, [`GpuFactorization::submit_sliced`]): the host goes on at
    /// once (`timed`: its pass timed, for a factorization waited for next).
    /// Recorded here unless [`Self::record_factor_on_gpu`] recorded it for
    /// `kind` and this pattern before.
    ///
    /// [`GpuFactorization::submit_sliced`]: crate::factorize::GpuFactorization::submit_sliced
    pub(super) fn start_factor_on_gpu(
        &mut self,
        kind: SystemKind,
        k: &SymCsc,
        timed: bool,
        slices: usize,
    ) -> Result<GpuMade, GpuError> {
        let recorded = self.factor_recorded.take().filter(|made| {
            made.kind == kind
                && made.fac.nnz_k() == k.row_idx.len()
                && self.chol_host.has_analysed(&k.col_ptr, &k.row_idx)
                && (made.g.analysis.as_ref()).is_some_and(|a| a.is_of(&self.chol_host))
        });
        let mut made = match recorded {
            Some(made) => GpuMade {
                recorded_ahead: true,
                ..made
            },
            None => self.record_factor_on_gpu(kind, k)?,
        };
        self.factor_pipelines_ready();
        let t = std::time::Instant::now();
        made.fac
            .submit_sliced(&self.ctx, &k.values, timed, slices)?;
        made.host[2] = t.elapsed().as_secs_f64();
        made.submitted = std::time::Instant::now();
        Ok(made)
    }

    /// `kind`'s factorization of `k`'s pattern recorded (its factor's
    /// buffers made, `K`'s map, the plan and its bindings), not submitted.
    pub(super) fn record_factor_on_gpu(
        &mut self,
        kind: SystemKind,
        k: &SymCsc,
    ) -> Result<GpuMade, GpuError> {
        let t = std::time::Instant::now();
        self.host_factor_precision(precision::Precision::F64);
        let backend = |e: SolverError| GpuError::Backend(format!("Cholesky analysis: {e}"));
        if !self.chol_host.has_analysed(&k.col_ptr, &k.row_idx) {
            self.chol_host.analyse(k).map_err(backend)?;
        }
        // The scale-driven kind's recording, where this is of its analysis.
        let reuse = self.factor_recording.take().filter(|rec| {
            kind != SystemKind::ScaleFactors
                && (rec.skeleton.analysis.as_ref()).is_some_and(|a| a.is_of(&self.chol_host))
                && rec.fac.nnz_k() == k.row_idx.len()
        });
        let reused = reuse.is_some();
        let (analysed, mut g, fac) = match reuse {
            Some(rec) => {
                let analysed = t.elapsed().as_secs_f64();
                let g = rec.skeleton.twin(&self.ctx)?;
                let fac = rec.fac.for_factor(&self.ctx, &g)?;
                (analysed, g, fac)
            }
            None => {
                let f = self
                    .chol_host
                    .supernodal_structure()
                    .ok_or_else(|| GpuError::Backend("no supernodal structure".into()))?;
                let analysed = t.elapsed().as_secs_f64();
                let kernels = self.factor_kernels()?;
                let t = std::time::Instant::now();
                let recorded = supernodal::GpuFactor::allocate(
                    &self.ctx,
                    &f,
                    matrix::binding_limit(&self.ctx),
                )
                .and_then(|(g, place)| {
                    log::debug!(
                        "{kind:?} system's factor allocated on the GPU in {:.3} s",
                        t.elapsed().as_secs_f64()
                    );
                    let fac = crate::factorize::GpuFactorization::new(
                        &self.ctx, &kernels, &g, &place, &f, k,
                    )?;
                    Ok((g, fac))
                });
                // Over the device's limits for this pattern: not asked again.
                if let Err(GpuError::LimitExceeded { .. }) = recorded {
                    self.gpu_factor_refused[self.chol_group_of(kind)] = true;
                }
                let (g, fac) = recorded?;
                (analysed, g, fac)
            }
        };
        g.analysis = self.chol_host.analysis_id();
        let recorded = t.elapsed().as_secs_f64() - analysed;
        Ok(GpuMade {
            g,
            fac,
            kind,
            reused,
            host: [analysed, recorded, 0.0],
            submitted: std::time::Instant::now(),
            recorded_ahead: false,
        })
    }

    /// The factor of `made` once the GPU has made it (waited for), with the
    /// kernels that solve with it, and how it was made.
    pub(super) fn finish_factor_on_gpu(
        &mut self,
        made: GpuMade,
        timed: bool,
    ) -> Result<(supernodal::GpuFactor, String), GpuError> {
        let since = made.submitted.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        let (sliced, slices) = made.fac.slices_submitted();
        made.fac.finish(&self.ctx, timed)?;
        let waited = t.elapsed().as_secs_f64();
        let work = made.fac.work();
        // The scale-driven kind's recording serves the fine-tune's.
        self.factor_recording =
            match made.kind == SystemKind::ScaleDriven && made.g.analysis.is_some() {
                true => Some(FactorRecording {
                    fac: made.fac,
                    skeleton: made.g.handles(),
                }),
                false => None,
            };
        self.supernodal_kernels(precision::Precision::F64)?;
        let [analysed, recorded, submitted] = made.host;
        let how = match (made.reused, made.recorded_ahead) {
            (true, _) => "the scale-driven kind's recording bound in",
            (false, true) => "recorded ahead in",
            (false, false) => "recorded in",
        };
        let sliced = match slices > 1 {
            true => format!(" in {slices} slices, {sliced} ahead"),
            false => String::new(),
        };
        let text = format!(
            "factored on the GPU: analysis {analysed:.3} s, {how} {recorded:.3} s, \
             submitted{sliced} in {submitted:.3} s, waited for {waited:.3} s ({since:.3} s after \
             its first submission; {} dispatches, {} serial steps, {:.1} MB modelled)",
            work.dispatches,
            work.serial_steps,
            work.bytes as f64 / 1e6
        );
        Ok((made.g, text))
    }

    /// The GPU factorization's kernels, made once for the solver and its
    /// siblings.
    pub(super) fn factor_kernels(
        &mut self,
    ) -> Result<std::sync::Arc<crate::factorize::FactorKernels>, GpuError> {
        let mut shared = self
            .factor_kernels
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if shared.is_none() {
            *shared = Some(crate::factorize::FactorKernels::new(&self.ctx)?);
        }
        Ok(shared.clone().unwrap())
    }

    /// The host's solver in `precision`, its fill ordering kept.
    fn host_factor_precision(&mut self, precision: precision::Precision) {
        if self.chol_host.is_single_precision() != (precision == precision::Precision::F32) {
            let ordering = std::mem::take(&mut self.chol_host.ordering);
            self.chol_host = match precision {
                precision::Precision::F32 => solver_cpu::CholeskySolver::single_precision(),
                precision::Precision::F64 => solver_cpu::CholeskySolver::new(),
            };
            self.chol_host.supernodal = true;
            self.chol_host.ordering = ordering;
        }
    }

    /// `f` with its diagonal blocks inverted, uploaded, and the kernels of
    /// its precision made: the GPU's factor, and the inversion's seconds.
    fn upload_factor(
        &mut self,
        mut f: solver_cpu::SupernodalFactor,
    ) -> Result<(supernodal::GpuFactor, f64), GpuError> {
        let t = std::time::Instant::now();
        f.invert_diagonal_blocks();
        let inverse_seconds = t.elapsed().as_secs_f64();
        let g = supernodal::GpuFactor::upload(&self.ctx, &f, matrix::binding_limit(&self.ctx))?;
        self.ctx.check()?;
        self.supernodal_kernels(g.precision)?;
        Ok((g, inverse_seconds))
    }

    /// The Cholesky kernels of `precision`, made where those at hand are of
    /// the other.
    fn supernodal_kernels(&mut self, precision: precision::Precision) -> Result<(), GpuError> {
        if self
            .chol_kernels
            .as_ref()
            .is_none_or(|k| k.precision != precision)
        {
            self.chol_kernels = Some(supernodal::SupernodalKernels::new(&self.ctx, precision)?);
        }
        Ok(())
    }

    /// `factored`, a kind's factor of the host's analysed pattern made
    /// ahead (on a twin of that analysis, or on its own ordering), sent up to
    /// the GPU beside the active factor, for that kind's set-up to take
    /// ([`Self::join_factor_upload`]). Where uploads go beside the caller
    /// ([`super::BESIDE_UPLOADS_FROM_THREADS`]) it goes up on a thread of its
    /// own and the caller goes on at once (with the scale-driven kind's first
    /// matrix: its host assembly, and its ring pairs' slots; with the
    /// scale-driven iteration, for the fine-tune's), where it waited for the
    /// inversion of the diagonal blocks and the upload before (homer 1.2M on
    /// the H200's host: 0.54 and 0.45 s); else here. The host drops its copy
    /// once the copy is up.
    pub(super) fn upload_factor_ahead(
        &mut self,
        kind: SystemKind,
        mut factored: solver_cpu::CholeskySolver,
    ) -> Result<(), GpuError> {
        if !factored.is_factored_of_pattern_of(&self.chol_host) {
            return Err(GpuError::Backend(
                "not a factor of the pattern the solver has analysed".into(),
            ));
        }
        let precision = match factored.is_single_precision() {
            true => precision::Precision::F32,
            false => precision::Precision::F64,
        };
        self.check_supernodes(&factored, precision)?;
        let analysis = factored.analysis_id();
        let mut f = factored
            .take_supernodal_factor()
            .ok_or_else(|| GpuError::Backend("no supernodal factor".into()))?;
        drop(factored);
        // The factor on the device, where it is of the same analysis and
        // precision (the scale-driven kind's, for the fine-tune's): its
        // index sections are shared, not built on the host and sent again.
        let like = self
            .chol
            .as_ref()
            .filter(|g| {
                g.precision == precision
                    && match (&g.analysis, &analysis) {
                        (Some(a), Some(b)) => a.is(b),
                        _ => false,
                    }
            })
            .map(supernodal::GpuFactor::handles);
        let ctx = self.ctx.clone();
        let limit = matrix::binding_limit(&self.ctx);
        let beside = self.beside_uploads;
        let up = move || {
            let t = std::time::Instant::now();
            f.invert_diagonal_blocks();
            let inverse_seconds = t.elapsed().as_secs_f64();
            let shared = like.as_ref().and_then(|like| {
                supernodal::GpuFactor::upload_like(&ctx, like, &f, limit)
                    .inspect_err(|e| log::debug!("{e}: its index sections sent too"))
                    .ok()
            });
            let index = match shared.is_some() {
                true => ", its index sections shared",
                false => "",
            };
            let mut g = match shared {
                Some(g) => g,
                None => supernodal::GpuFactor::upload(&ctx, &f, limit)?,
            };
            g.analysis = analysis;
            log::debug!(
                "Cholesky factor made ahead ({kind:?} system, {precision:?}): inverted form \
                 {inverse_seconds:.3} s, uploaded in {:.3} s{}{index}",
                t.elapsed().as_secs_f64() - inverse_seconds,
                if beside { ", on its own thread" } else { "" }
            );
            Ok(g)
        };
        let upload = match beside {
            true => {
                let thread = self
                    .ctx
                    .spawn_beside(format!("{kind:?} factor upload"), up)
                    .map_err(|e| GpuError::Backend(format!("a thread for its upload: {e}")))?;
                Uploading::Beside(thread)
            }
            false => Uploading::Done(up()),
        };
        self.chol_ahead = Some((kind, FactorUpload { upload, precision }));
        Ok(())
    }

    /// The factor of `up` once on the GPU (waited for), with the kernels of
    /// its precision; `None` where its upload failed (the kind's set-up
    /// factors then).
    fn join_factor_upload(
        &mut self,
        kind: SystemKind,
        up: FactorUpload,
    ) -> Option<supernodal::GpuFactor> {
        let t = std::time::Instant::now();
        let uploaded = match up.upload {
            Uploading::Beside(thread) => joined(thread),
            Uploading::Done(uploaded) => uploaded,
        };
        let taken = uploaded.and_then(|g| {
            self.ctx.check()?;
            self.supernodal_kernels(g.precision)?;
            Ok(g)
        });
        match taken {
            Ok(g) => {
                log::debug!(
                    "Cholesky factor made ahead ({kind:?} system): waited {:.3} s for its upload",
                    t.elapsed().as_secs_f64()
                );
                Some(g)
            }
            Err(e) => {
                log::debug!("Cholesky factor made ahead ({kind:?} system) not uploaded: {e}");
                None
            }
        }
    }

    /// Refuses a factor (analysed by `solver`) whose largest supernode in
    /// `precision` would not fit one storage binding of the device.
    pub(super) fn check_supernodes(
        &self,
        solver: &solver_cpu::CholeskySolver,
        precision: precision::Precision,
    ) -> Result<(), GpuError> {
        let limit = matrix::binding_limit(&self.ctx);
        let supernode = solver.largest_supernode_nnz() as u64 * precision.bytes();
        if supernode > limit {
            return Err(GpuError::LimitExceeded {
                what: format!("the Cholesky factor's largest supernode ({supernode} bytes)"),
                limit_name: "max_storage_buffer_binding_size",
                needed: supernode,
                limit,
            });
        }
        Ok(())
    }

    /// The supernodal factor of `k` in `precision`, made here by the host's
    /// solver (its symbolic analysis kept for later kinds).
    fn factor_here(
        &mut self,
        k: SymCsc,
        precision: precision::Precision,
    ) -> Result<solver_cpu::SupernodalFactor, GpuError> {
        self.host_factor_precision(precision);
        let backend = |e: SolverError| GpuError::Backend(format!("Cholesky factor: {e}"));
        // The factor's sizes are known from the symbolic analysis: one that
        // would not fit the device's storage bindings is refused before the
        // numeric factorization. Its values, and the updates of its
        // triangular solves, are split over as many bindings as they need,
        // at supernode boundaries ([`supernodal::GpuFactor`],
        // [`supernodal::SupernodalSteps`]): the largest supernode must fit
        // one.
        self.chol_host.analyse(&k).map_err(backend)?;
        self.check_supernodes(&self.chol_host, precision)?;
        self.chol_host.prepare(&k).map_err(backend)?;
        drop(k);
        self.chol_host
            .take_supernodal_factor()
            .ok_or_else(|| GpuError::Backend("no supernodal factor".into()))
    }

    /// The shape model the squared-Laplacian preconditioner builds on, where
    /// it is asked for and fits the prepared block matrix.
    pub(super) fn squared_model(&self) -> Option<std::sync::Arc<ShapeOperatorModel>> {
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
    pub(super) fn setup_squared(
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
}

/// A factorization submitted to the GPU ([`GpuSolver::start_factor_on_gpu`]):
/// its factor, its recording (whose pivot flag is read when it is taken),
/// the host's seconds (analysis, recording, submission) and when it went.
pub(super) struct GpuMade {
    g: supernodal::GpuFactor,
    fac: crate::factorize::GpuFactorization,
    kind: SystemKind,
    /// Recorded for another factor of the kind's pattern (the scale-driven
    /// kind's), bound to this one.
    reused: bool,
    host: [f64; 3],
    submitted: std::time::Instant,
    /// Recorded before its submission was asked for
    /// (`prepare_factor_on_device`).
    recorded_ahead: bool,
}

impl GpuMade {
    /// Its next slice submitted, where one is left: which of how many.
    pub(super) fn submit_next(
        &self,
        ctx: &crate::device::Context,
    ) -> Result<Option<(usize, usize)>, GpuError> {
        Ok(self
            .fac
            .submit_next(ctx)?
            .then(|| self.fac.slices_submitted()))
    }
}

/// The scale-driven kind's factorization once finished, kept for the
/// fine-tune's (the same pattern and analysis): its index, map and plan
/// are not made or sent again ([`GpuFactorization::for_factor`]), only the
/// values' buffers and bind groups.
///
/// [`GpuFactorization::for_factor`]: crate::factorize::GpuFactorization::for_factor
pub(super) struct FactorRecording {
    fac: crate::factorize::GpuFactorization,
    /// The factor it was bound to (handles, with the host's analysis it is
    /// of), whose structure a twin takes.
    skeleton: supernodal::GpuFactor,
}
