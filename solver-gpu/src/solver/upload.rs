//! A prepared matrix's way to the GPU: its pattern once, then per matrix
//! its values, a shape matrix's blocks summed on the GPU from `K`, the rings'
//! `C_i` and the Laplacian square term (`expand_blocks`), else expanded from
//! the lower triangle the host sends.

use super::*;
use solver_cpu::SparseRows;

/// `h`'s f32 inverse diagonal blocks into `minv`
/// ([`block_jacobi::inverse_diagonal`]), a block that is not positive
/// definite as [`GpuError::NotPositiveDefinite`].
fn inverse_diagonal(h: &HostMatrix, minv: &mut Vec<f32>) -> Result<(), GpuError> {
    block_jacobi::inverse_diagonal(h, minv).map_err(|e| match e {
        SolverError::NotPositiveDefinite => GpuError::NotPositiveDefinite,
        other => GpuError::Backend(other.to_string()),
    })
}

impl GpuSolver {
    pub(crate) fn spmv(&self) -> Spmv<'_> {
        match self.host.as_ref().map(|h| h.bs) {
            Some(1) => Spmv::Scalar(&self.k.csr),
            _ => Spmv::Block(&self.k.bsr),
        }
    }

    /// Upload a prepared host matrix (pattern if new, else values only: a
    /// block matrix's as its lower triangle, see [`Self::expand_values`]);
    /// a new pattern's (not `same`) device part `ahead` where it was set
    /// up ahead of its values ([`Self::pattern_ready`]: of this one).
    pub(super) fn upload(
        &mut self,
        mut h: HostMatrix,
        same: bool,
        ahead: Option<PatternDevice>,
    ) -> Result<(), GpuError> {
        self.matrices += 1;
        let mut minv = std::mem::take(&mut self.minv_scratch);
        // The inverse diagonal blocks are read by the block-Jacobi and AMG
        // preconditioners only: new values of an uploaded pattern that the
        // kind's Cholesky factor preconditions leave them, on the host and
        // the GPU, until another preconditioner asks for them
        // ([`Self::refresh_inverse_diagonal`]).
        // Nor does a new pattern's first shape matrix (summed on the GPU)
        // where the kind's factor is made.
        let fresh_shape = !same && h.shape_form().is_some();
        let diagonal = !(self.chol.is_some() && (same && self.gpu.is_some() || fresh_shape));
        if diagonal {
            inverse_diagonal(&h, &mut minv)?;
        }
        self.diagonal_current = diagonal;
        let mut same_values_only = false;
        let expanded = same
            && self.gpu.is_some()
            && h.bs == 3
            && self.expand_values(&h, diagonal.then_some(&minv[..]))?;
        if expanded {
            h.release_map();
        }
        match (same, self.gpu.as_ref()) {
            (true, Some(_)) if expanded => same_values_only = true,
            (true, Some(gpu)) => {
                gpu.write_values(&self.ctx, &h, diagonal.then_some(&minv[..]));
                self.value_uploads += 1;
                same_values_only = true;
            }
            _ => {
                self.gpu = None;
                self.drop_workspaces();
                // A shape matrix kept in its form is summed on the GPU from
                // the start: its pattern goes up with no values.
                let shape = h.shape_form().is_some();
                let (gpu, mut split, sum) = match ahead {
                    Some(d) => {
                        if diagonal {
                            d.gpu.write_diagonal(&self.ctx, &h, &minv);
                        }
                        self.patterns_taken_ahead += 1;
                        (d.gpu, d.split, d.sum)
                    }
                    None => (
                        GpuMatrix::upload(&self.ctx, &h, diagonal.then_some(&minv[..]), !shape)?,
                        None,
                        None,
                    ),
                };
                self.gpu = Some(gpu);
                self.pattern_uploads += 1;
                // A kind whose solves start in mixed precision has its
                // mixed-precision matrix made now, before the expansion, so
                // that one expansion writes its low parts too: made at the
                // first solve, it set the expansion up a second time (the
                // map and the values sent up again).
                let early = shape && self.mixed_from_the_first_solve();
                let split_ahead = early && split.is_some();
                if early {
                    let stamp = (self.pattern_uploads, self.value_uploads);
                    self.host = Some(h);
                    let built = self.build_mixed(1, stamp, true, split.take());
                    h = self.host.take().unwrap();
                    built?;
                    if split_ahead && diagonal {
                        let m = &self.mixed.as_ref().unwrap().matrix;
                        m.write_diagonal(&self.ctx, &h, &[]);
                    }
                }
                if let Some(sum) = sum {
                    self.adopt_sum_ahead(sum, early, split_ahead);
                }
                if shape && self.expand_on_gpu(&h)? {
                    h.release_map();
                } else if shape {
                    self.gpu
                        .as_ref()
                        .unwrap()
                        .write_values(&self.ctx, &h, Some(&minv));
                    if let Some(m) = self.mixed.as_ref().filter(|_| early) {
                        m.matrix.write_values(&self.ctx, &h, Some(&[]));
                    }
                }
                self.mixed_sticky = false;
                self.hints.clear();
            }
        }
        // A kind preconditioned by its Cholesky factor reads no diagonal
        // blocks after its pattern's first inverse diagonal: not held
        // through its solves (43 MB at homer 1.2M faces).
        if self.chol.is_some() {
            h.release_diagonal();
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
        // Kept for the next matrix's inverse diagonal, unless a Cholesky
        // factor preconditions this kind: its next matrices make none (4
        // bytes a block row: 26 MB at homer 1.2M faces, held through the
        // run's peak, the fine-tune's factorization).
        if self.chol.is_none() {
            self.minv_scratch = minv;
        }
        self.ctx.check()
    }

    /// New values of the uploaded block pattern from their lower triangle:
    /// the f64 lower blocks go up (72 bytes a lower block), or a shape
    /// matrix's `K` values and `C_i` for `sum_shape_blocks.wgsl` to sum them,
    /// and `expand_blocks.wgsl` writes both triangles, held rows, f32 high
    /// parts and, once the mixed-precision matrix exists, its low parts; the
    /// host writes only the inverse diagonals (`minv`; none: left as they
    /// are). `false` (nothing done) where the adapter lacks `SHADER_F64`, or
    /// the lower values would not fit one storage binding: then the host
    /// writes the values.
    pub(super) fn expand_values(
        &mut self,
        h: &HostMatrix,
        minv: Option<&[f32]>,
    ) -> Result<bool, GpuError> {
        if !self.expand_on_gpu(h)? {
            return Ok(false);
        }
        let stamp = self.pattern_uploads;
        if let Some(minv) = minv {
            self.gpu
                .as_ref()
                .unwrap()
                .write_diagonal(&self.ctx, h, minv);
        }
        self.value_uploads += 1;
        if let Some(m) = self.mixed.as_mut().filter(|m| m.stamp.0 == stamp) {
            if minv.is_some() {
                m.matrix.write_diagonal(&self.ctx, h, &[]);
            }
            m.stamp = (stamp, self.value_uploads);
        }
        Ok(true)
    }

    /// The uploaded matrix's inverse diagonal blocks, made and written
    /// where [`Self::upload`] left them (a kind preconditioned by its
    /// Cholesky factor), before a preconditioner that reads them is set
    /// up.
    pub(super) fn refresh_inverse_diagonal(&mut self) -> Result<(), GpuError> {
        let (Some(h), Some(gpu)) = (self.host.as_ref(), self.gpu.as_ref()) else {
            return Ok(());
        };
        if self.diagonal_current {
            return Ok(());
        }
        let mut minv = std::mem::take(&mut self.minv_scratch);
        inverse_diagonal(h, &mut minv)?;
        gpu.write_diagonal(&self.ctx, h, &minv);
        let stamp = (self.pattern_uploads, self.value_uploads);
        if let Some(m) = self.mixed.as_ref().filter(|m| m.stamp == stamp) {
            m.matrix.write_diagonal(&self.ctx, h, &[]);
        }
        self.minv_scratch = minv;
        self.diagonal_current = true;
        self.ctx.check()
    }

    /// The blocks of both triangles of [`Self::expand_values`] (high parts,
    /// and low parts where the mixed-precision matrix of the pattern exists),
    /// without the inverse diagonals; `false` where it can not run.
    pub(super) fn expand_on_gpu(&mut self, h: &HostMatrix) -> Result<bool, GpuError> {
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
        let ahead = self.pairs_ahead.take();
        let mut took_ahead = false;
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
                    let pairs = ahead.and_then(|p| p.join(slots));
                    took_ahead = pairs.is_some();
                    let sum = expand_blocks::ShapeSum::new(k, &self.ctx, (a, slots), lower, pairs)?;
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
        self.pairs_taken_ahead += usize::from(took_ahead);
        Ok(true)
    }

    /// The host's parts of the Laplacian square term `a` names (`None`
    /// without one): made once per model, when its values are found and
    /// kept in `square_values` for the shape sum to take up.
    pub(super) fn square_parts(
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
        let ahead = self
            .square_ahead
            .take()
            .filter(|q| Arc::ptr_eq(&q.model, model) && std::ptr::eq(&*q.slots, slots));
        let values = match ahead.map(|q| q.values.join()) {
            Some(Ok(values)) if matrix::square_through_slots(model, a, slots) => {
                self.squares_taken_ahead += 1;
                log::debug!(
                    "{:?} system: the Laplacian square term's values summed ahead taken",
                    self.kind
                );
                values
            }
            _ => matrix::laplacian_square_values(a, slots)?.unwrap_or_default(),
        };
        let q = Arc::new(matrix::SquareParts::new(model.clone(), a, &values));
        self.square = Some(q.clone());
        self.square_values = Some(values);
        Ok(Some(q))
    }

    /// Where the next shape matrices will name the Laplacian square term of
    /// the current model ([`SpdSolver::set_shape_model`]) and `a` does not
    /// yet (its host summed the term into `K` while the kind's factor was
    /// being set up: this is the kind's first matrix), its values
    /// ([`matrix::square_values_through_slots`]) are summed on another thread
    /// from now on, for [`Self::square_parts`] to take at the next matrix:
    /// one serial pass over the rings' pairs, 0.39 s at homer 1.2M and 0.84
    /// s at 4.3M on an H200's host, which the main thread waited for at the
    /// second outer iteration. `a` is the shape form just set. The
    /// scale-driven kind's only: the fine-tune's steps keep their first
    /// matrix (homer 1.2M: one matrix), so its values would not be taken.
    pub(super) fn start_square_values(&mut self, a: Option<&IsoRingSym3>, slots: &Arc<RingSlots>) {
        let (Some(a), Some(model)) = (a, self.shape_model.as_ref()) else {
            return;
        };
        let started = |m: &Arc<ShapeOperatorModel>| Arc::ptr_eq(m, model);
        if self.kind != SystemKind::ScaleDriven
            || a.laplacian_square.is_some()
            || !self.shape_factor_made()
            || model.mt.iter().all(|&m| m == 0.0)
            || self.square.as_ref().is_some_and(|q| started(&q.model))
            || self
                .square_ahead
                .as_ref()
                .is_some_and(|q| started(&q.model))
            || !matrix::square_through_slots(model, a, slots)
        {
            return;
        }
        let (model, slots) = (model.clone(), slots.clone());
        let entries = a.iso.row_idx.len();
        let values = std::thread::Builder::new()
            .name("square-values".into())
            .spawn({
                let (model, slots) = (model.clone(), slots.clone());
                move || matrix::square_values_through_slots(&model, &slots, entries)
            });
        match values {
            Ok(values) => {
                log::debug!(
                    "{:?} system: the Laplacian square term's values summed ahead on another thread",
                    self.kind
                );
                self.square_ahead = Some(SquareAhead {
                    model,
                    slots,
                    values,
                })
            }
            Err(e) => log::debug!("no thread for the Laplacian square's values: {e}"),
        }
    }

    /// Whether a shape matrix `a` can have its blocks summed on the GPU
    /// ([`expand_blocks::ShapeSum`]): `SHADER_F64`, and every buffer within
    /// one storage binding.
    pub(super) fn shape_sum_possible(&self, a: &IsoRingSym3, slots: &RingSlots) -> bool {
        let limit = matrix::binding_limit(&self.ctx);
        self.ctx.shader_f64 && expand_blocks::ShapeSum::fits(a, slots, limit)
    }

    /// Starts gathering the ring pairs of `a`'s new `slots` by lower block,
    /// and sending them up, on a thread beside the caller, for the shape
    /// sum of `a`'s pattern ([`PairsAhead::join`]): the host part of
    /// the matrix (its diagonal blocks) and the kind's factor's upload go
    /// on meanwhile. Nothing where the GPU does not sum the blocks.
    pub(super) fn start_pairs_ahead(&mut self, a: &IsoRingSym3, slots: &Arc<RingSlots>) {
        self.pairs_ahead = None;
        if !self.beside_uploads || !self.shape_sum_possible(a, slots) {
            return;
        }
        let limit = matrix::binding_limit(&self.ctx);
        let blocks = a.iso.row_idx.len();
        let Some(layout) = expand_blocks::LowerParts::layout(blocks, limit) else {
            return;
        };
        let (ctx, rings, slots) = (self.ctx.clone(), a.rings.clone(), slots.clone());
        let ours = slots.clone();
        let thread = self.ctx.spawn_beside("shape sum's pairs".into(), move || {
            let t = std::time::Instant::now();
            let (parts, part_blocks) = layout;
            let up = expand_blocks::PairBuffers::upload(
                &ctx,
                (&rings, blocks, &ours),
                (part_blocks, parts),
            );
            log::debug!(
                "shape sum's ring pairs gathered by block and sent up on their own \
                 thread in {:.3} s",
                t.elapsed().as_secs_f64()
            );
            up
        });
        match thread {
            Ok(thread) => self.pairs_ahead = Some(PairsAhead { slots, thread }),
            Err(e) => log::debug!("no thread for the shape sum's pairs ({e}): made at the sum"),
        }
    }

    /// Starts setting up on a thread beside the caller what the shape
    /// matrices of `a`'s pattern, rings and held vertices `fixed` need
    /// before their first values: the ring pairs' slots, the host's block
    /// pattern and map, the block matrix (and the f64 low parts of the
    /// mixed-precision one) on the device, the expansion and the shape sum
    /// with its ring pairs ([`PatternAhead`]). The first matrix of the
    /// pattern takes them up ([`Self::pattern_ready`]) and makes no inverse
    /// diagonal where the kind's Cholesky factor preconditions it (nothing
    /// reads it: [`Self::refresh_inverse_diagonal`] makes it where a
    /// preconditioner will). On the main thread that was the first shape
    /// matrix's hand-over, between the first scale factors and the first
    /// shape solve: at homer 1.2M on the development machine (lavapipe, 2
    /// cores) 1.3 s on 2 of rayon's threads (the slots' check 0.22 s, the
    /// inverse diagonal 0.20, the expansion 0.20, the ring pairs 0.58) and
    /// 0.74 s on 4 (the pairs already beside it), against 0.17 s with the
    /// pattern set up ahead. Nothing where uploads do not go beside the
    /// caller ([`super::BESIDE_UPLOADS_FROM_THREADS`]) or the adapter has
    /// no `SHADER_F64`.
    pub(super) fn start_pattern_ahead(&mut self, a: &IsoRingSym3, fixed: &[bool]) {
        self.wait_for_pattern_ahead();
        let n = a.n();
        if !self.beside_uploads
            || !self.ctx.shader_f64
            || fixed.len() != n
            || a.rings.len() != n
            || a.iso.col_ptr.len() != n + 1
        {
            return;
        }
        let expand = match self.expand.as_ref() {
            Some(e) => e.clone(),
            None => match expand_blocks::ExpandBlocks::new(&self.ctx) {
                Ok(e) => self.expand.insert(e).clone(),
                Err(e) => {
                    log::debug!("no shape pattern set up ahead: {e}");
                    return;
                }
            },
        };
        // As `mixed_from_the_first_solve` will say once the kind's
        // preconditioner is made.
        let mixed = self.mixed_precision != MixedPrecision::Never && self.starts_mixed();
        let pattern = (a.iso.col_ptr.clone(), a.iso.row_idx.clone());
        let (ctx, rings, given) = (self.ctx.clone(), a.rings.clone(), a.ring_slots.clone());
        let held = fixed.to_vec();
        let thread = self
            .ctx
            .spawn_beside("shape pattern ahead".into(), move || {
                let t = std::time::Instant::now();
                let up = pattern_up(&ctx, &expand, pattern, (rings, given, held), mixed);
                log::debug!(
                    "shape pattern set up ahead on its own thread in {:.3} s",
                    t.elapsed().as_secs_f64()
                );
                up
            });
        match thread {
            Ok(thread) => {
                self.pattern_ahead = Some(PatternAhead {
                    rings: a.rings.clone(),
                    fixed: fixed.to_vec(),
                    thread,
                })
            }
            Err(e) => log::debug!("no thread for the shape pattern ahead: {e}"),
        }
    }

    /// The pattern set up ahead ([`Self::start_pattern_ahead`]) where it is
    /// `a`'s, with its rings and held vertices `fixed`, once its thread is
    /// done; `None` where not (or it failed: the matrix sets it up itself).
    pub(super) fn pattern_ready(&mut self, a: &IsoRingSym3, fixed: &[bool]) -> Option<PatternUp> {
        let ahead = self.pattern_ahead.take()?;
        if !Arc::ptr_eq(&ahead.rings, &a.rings) || ahead.fixed != fixed {
            // Ended, not left running on the device (see `Drop`).
            let _ = ahead.thread.join();
            return None;
        }
        let t = std::time::Instant::now();
        let up = match joined(ahead.thread) {
            Ok(up) => up,
            Err(e) => {
                log::debug!("shape pattern ahead: {e}; set up at its first matrix");
                return None;
            }
        };
        if !up.host.same_pattern(3, &a.iso.col_ptr, &a.iso.row_idx) {
            return None;
        }
        log::debug!(
            "shape pattern set up ahead: waited {:.3} s for its thread",
            t.elapsed().as_secs_f64()
        );
        Some(up)
    }

    /// Waits for a shape pattern's thread not taken up (its work dropped).
    pub(super) fn wait_for_pattern_ahead(&mut self) {
        if let Some(ahead) = self.pattern_ahead.take() {
            let _ = ahead.thread.join();
        }
    }

    /// The lower parts, expansion and shape sum set up ahead, taken up as
    /// the new pattern's (stamped with it). The expansion only where it
    /// writes the low parts of the mixed-precision matrix just as the one
    /// made now would (`early`: there is one; `split_ahead`: made with it);
    /// else [`Self::expand_on_gpu`] makes its own.
    fn adopt_sum_ahead(&mut self, sum: SumAhead, early: bool, split_ahead: bool) {
        let stamp = self.pattern_uploads;
        let SumAhead {
            lower,
            expansion,
            sum,
            split,
        } = sum;
        self.expand_lower = Some((stamp, lower));
        self.shape_sum = Some((stamp, sum));
        self.expansion = None;
        let writes_as_now = match split {
            true => split_ahead,
            false => !early,
        };
        if writes_as_now {
            let writes = early.then_some(self.mixed_builds);
            self.expansion = Some((expansion, stamp, writes, self.fixed.clone()));
            self.expansions += 1;
        }
    }

    /// Whether the prepared matrix has this lower pattern and block size.
    pub(super) fn same_pattern(&self, bs: usize, col_ptr: &[usize], row_idx: &[usize]) -> bool {
        self.host
            .as_ref()
            .is_some_and(|h| h.same_pattern(bs, col_ptr, row_idx))
    }

    /// The host matrix to fill: the prepared one when `same`, else a new
    /// pattern.
    pub(super) fn take_host(
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

/// The ring pairs of `slots` gathered by lower block and going up on a
/// thread of their own ([`GpuSolver::start_pairs_ahead`]).
pub(crate) struct PairsAhead {
    slots: Arc<RingSlots>,
    thread: std::thread::JoinHandle<Result<expand_blocks::PairBuffers, GpuError>>,
}

impl PairsAhead {
    /// The pairs, once up, where they are those of `slots`; `None` where
    /// not (or they failed: the shape sum sends them up itself).
    fn join(self, slots: &Arc<RingSlots>) -> Option<expand_blocks::PairBuffers> {
        if !Arc::ptr_eq(&self.slots, slots) {
            return None;
        }
        let t = std::time::Instant::now();
        match joined(self.thread) {
            Ok(p) => {
                log::debug!(
                    "shape sum's ring pairs: waited {:.3} s for their thread",
                    t.elapsed().as_secs_f64()
                );
                Some(p)
            }
            Err(e) => {
                log::debug!("shape sum's ring pairs ahead: {e}; sent up at the sum");
                None
            }
        }
    }
}

/// The Laplacian square term's values of `model` through `slots`, being
/// summed on their own thread ([`GpuSolver::start_square_values`]).
pub(crate) struct SquareAhead {
    pub model: Arc<ShapeOperatorModel>,
    pub slots: Arc<RingSlots>,
    pub values: std::thread::JoinHandle<Vec<f64>>,
}

/// A shape pattern being set up on a thread beside the caller
/// ([`GpuSolver::start_pattern_ahead`]) for these rings and held vertices.
pub(crate) struct PatternAhead {
    rings: Arc<SparseRows>,
    fixed: Vec<bool>,
    thread: std::thread::JoinHandle<Result<PatternUp, GpuError>>,
}

/// What a shape pattern's first matrix needs before its values: on the
/// host, the pattern's blocks (and map: see [`HostMatrix::map`]) and the
/// ring pairs' slots; on the device, [`PatternDevice`].
pub(crate) struct PatternUp {
    pub host: HostMatrix,
    pub slots: Arc<RingSlots>,
    pub device: PatternDevice,
}

/// The device's part of [`PatternUp`], taken up by [`GpuSolver::upload`].
pub(crate) struct PatternDevice {
    /// The f32 block matrix, its values and inverse diagonal unwritten.
    gpu: GpuMatrix,
    /// The mixed-precision matrix's f64 low parts and inverse diagonal
    /// over `gpu`, unwritten, where its solves start in mixed precision.
    split: Option<GpuMatrix>,
    /// Where the GPU sums the blocks.
    sum: Option<SumAhead>,
}

/// The lower parts, expansion (`split`: writing the low parts too) and
/// shape sum of a pattern set up ahead.
struct SumAhead {
    lower: expand_blocks::LowerParts,
    expansion: expand_blocks::Expansion,
    sum: expand_blocks::ShapeSum,
    split: bool,
}

/// [`PatternUp`] for the lower pattern `(col_ptr, row_idx)`, its `rings`
/// (their slots checked against `given` where given) and held vertices
/// `held`; the split f64 matrix where `mixed`.
fn pattern_up(
    ctx: &Context,
    expand: &expand_blocks::ExpandBlocks,
    (col_ptr, row_idx): (Vec<usize>, Vec<usize>),
    (rings, given, held): (Arc<SparseRows>, Option<Arc<[u32]>>, Vec<bool>),
    mixed: bool,
) -> Result<PatternUp, GpuError> {
    let host_error = |e: SolverError| GpuError::Backend(e.to_string());
    let n = held.len();
    let slots = RingSlots::new(&rings, &col_ptr, &row_idx, given.as_ref()).map_err(host_error)?;
    let slots = Arc::new(slots);
    let mut host = HostMatrix::pattern(n, 3, &col_ptr, &row_idx).map_err(host_error)?;
    host.set_fixed(&held);
    let nnz = row_idx.len();
    drop((col_ptr, row_idx));
    let gpu = GpuMatrix::upload(ctx, &host, None, false)?;
    let split = match mixed {
        true => Some(GpuMatrix::upload_split_f64(ctx, &host, &gpu, false, false)?),
        false => None,
    };
    let limit = matrix::binding_limit(ctx);
    let fits = expand_blocks::ShapeSum::fits_pattern((&rings, nnz, &slots), limit)
        && expand_blocks::LowerParts::layout(nnz, limit).is_some();
    let sum = match (fits, gpu.block_parts()) {
        (true, Some((chunks, None))) => {
            let lower = expand_blocks::LowerParts::new(ctx, nnz, limit)?;
            let lo = split
                .as_ref()
                .and_then(|m| m.block_parts())
                .and_then(|p| p.1);
            let expansion = expand.expansion(ctx, &lower, host.map(), chunks, lo)?;
            let sum = expand_blocks::ShapeSum::of_pattern(
                expand,
                ctx,
                (&rings, nnz, &slots),
                &lower,
                None,
            )?;
            Some(SumAhead {
                lower,
                expansion,
                sum,
                split: lo.is_some(),
            })
        }
        _ => None,
    };
    Ok(PatternUp {
        host,
        slots,
        device: PatternDevice { gpu, split, sum },
    })
}
