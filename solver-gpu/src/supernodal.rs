//! Drives `shaders/supernodal.wgsl`: the shape systems' preconditioner
//! `z = (P^T L L^T P)^-1 r` for x, y and z of every PCG column
//! ([`crate::Preconditioner::Cholesky`]), with `L L^T = P K P^T` the
//! supernodal Cholesky factor of the matrix's isotropic part `K` (`K_ij =
//! tr(A_ij) / 3`, the held rows identity), as the CPU backend's block PCG
//! preconditions the same systems (`solver_cpu::pcg`); and, with `bs = 1`, the
//! scale factors' (the factor of their constant Hessian itself).
//!
//! The factor is made on the host once per system kind per run (faer, nested
//! dissection: a shallow elimination tree), put there in the inverted form
//! ([`SupernodalFactor::invert_diagonal_blocks`]: `L_ss^-1`, and `B_s = L_rs
//! L_ss^-1` in place of the rows below), and goes up once. An application is
//! `3 levels` dispatches, no host work, no atomics and no barriers (the
//! same result on every run): per level of the supernodal elimination tree,
//! leaves first, pull `w_s = (P r)_s` less the descendants' updates, then one
//! step for `y_s = L_ss^-1 w_s` and the updates `B_s w_s` of the rows below
//! (both read `w_s` only); per level, root first, `x_s = L_ss^-T y_s - B_s^T
//! x_r` in one step, written to `z = P^T x` as well. Each kernel runs one invocation per
//! row (or slot) and scalar column of the level, a dot product each: the dense
//! separators at the top of the tree spread over the whole GPU instead of one
//! workgroup.
//!
//! The values are stored level by level and cut into buffers of at most one
//! storage binding at supernode boundaries ([`GpuFactor::upload`]); a level
//! whose supernodes span two buffers is dispatched as two segments.
//!
//! Bindings (group 0), as documented in the shader: 0 `P` uniform
//! ([`SnParams`], one per segment of a level), 1 `idx` (the index sections), 2 `vals` (the segment's buffer),
//! 3 `w`, 4 `y`, 5 `r`, 6 `z`, 7 `contrib` (3, 4, 6, 7 read-write).

use crate::device::{dispatch, Bind, Context, Kernel, KernelWork, Shader, FLAT_WG};
use crate::precision::Precision;
use crate::GpuError;
use solver_cpu::SupernodalFactor;
use std::sync::Arc;

pub(crate) const SOURCE: &str = include_str!("../../shaders/supernodal.wgsl");

const BINDINGS: [(u32, Bind); 8] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::ReadWrite),
    (4, Bind::ReadWrite),
    (5, Bind::Read),
    (6, Bind::ReadWrite),
    (7, Bind::ReadWrite),
];

/// Parameters, as `Params` in `supernodal.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct SnParams {
    pub(crate) own: u32,
    pub(crate) n_own: u32,
    pub(crate) below: u32,
    pub(crate) n_below: u32,
    pub(crate) nv: u32,
    pub(crate) stride: u32,
    pub(crate) bs: u32,
    pub(crate) offsets: [u32; 9],
}

/// The entry points, in one precision.
pub(crate) struct SupernodalKernels {
    pub precision: Precision,
    shader: Shader,
    /// pull, forward, backward.
    kernels: [Kernel; 3],
}

impl SupernodalKernels {
    pub fn new(ctx: &Context, precision: Precision) -> Result<Arc<Self>, GpuError> {
        let source = precision.source(SOURCE);
        let shader = Shader::new(ctx, "supernodal.wgsl", &source, &BINDINGS)?;
        let k = |label, entry| Kernel::new(&shader, label, entry);
        let kernels = [
            k("supernodal pull", "pull"),
            k("supernodal forward", "forward"),
            k("supernodal backward", "backward"),
        ];
        Ok(Arc::new(SupernodalKernels {
            precision,
            shader,
            kernels,
        }))
    }
}

/// A supernodal factor on the GPU, with its level schedule.
pub(crate) struct GpuFactor {
    idx: wgpu::Buffer,
    /// The values, in chunks of at most one storage binding each, split at
    /// supernode boundaries (a supernode's `vo` is its offset in its chunk).
    vals: Vec<wgpu::Buffer>,
    /// Offsets of the sections of `idx` (as in `SnParams::offsets`).
    offsets: [u32; 9],
    /// Slots of `rows` (one update per slot and column in `contrib`).
    slots: usize,
    /// Per level, leaves first, its segments: `[first, count]` of their
    /// columns and of their slots in those sections, and the chunk of
    /// `vals` their values are in (one dispatch per segment and kernel).
    levels: Vec<Vec<[u32; 5]>>,
    /// Rows of `K`.
    pub nv: usize,
    /// Stored values of the factor.
    pub nnz: usize,
    /// Precision of its values (and of the vectors its solves run on).
    pub precision: Precision,
    /// Bytes of the factor's values and row indices (read twice an application).
    bytes: u64,
}

/// Levels of the supernodal elimination tree: a supernode's parent owns its
/// first row below the diagonal block; leaves are level 0, a parent one above
/// its highest child. `None` where the factor is not in topological order.
fn levels(f: &SupernodalFactor) -> Option<Vec<u32>> {
    let ns = f.len();
    let n = f.perm.len();
    let mut owner = vec![0u32; n];
    for s in 0..ns {
        for c in f.begin[s]..f.begin[s + 1] {
            *owner.get_mut(c as usize)? = s as u32;
        }
    }
    let mut level = vec![0u32; ns];
    for s in 0..ns {
        let (a, b) = (f.row_ptr[s] as usize, f.row_ptr[s + 1] as usize);
        if a < b {
            let p = *owner.get(*f.rows.get(a)? as usize)? as usize;
            if p <= s {
                return None;
            }
            level[p] = level[p].max(level[s] + 1);
        }
    }
    Some(level)
}

impl GpuFactor {
    /// Upload `f` (its diagonal blocks inverted; indices in u32). The values
    /// are stored level by level, leaves first, and cut into chunks of at
    /// most `limit` bytes (one storage binding) at supernode boundaries, so
    /// that a level's supernodes share one chunk but where a cut falls: a
    /// factor larger than a binding (homer 4.3M's f64 factor, 3.5 GB, against
    /// the H100's 2 GiB) costs a few dispatches more, not the preconditioner.
    pub fn upload(ctx: &Context, f: &SupernodalFactor, limit: u64) -> Result<GpuFactor, GpuError> {
        let ns = f.len();
        let bad = |what: &str| GpuError::Backend(format!("supernodal factor: {what}"));
        if !f.inverted {
            return Err(bad("diagonal blocks not inverted"));
        }
        let level = levels(f).ok_or_else(|| bad("supernodes out of topological order"))?;
        let n = f.perm.len();
        let nrows = f.rows.len();
        let total = 5 * ns + nrows + n + (n + 1) + nrows + 2 * n + 2 * nrows;
        if total > u32::MAX as usize {
            return Err(GpuError::LimitExceeded {
                what: "a Cholesky factor's index sections (32-bit offsets)".into(),
                limit_name: "u32::MAX",
                needed: total as u64,
                limit: u32::MAX as u64,
            });
        }
        let precision = match f.values64.is_empty() {
            true => Precision::F32,
            false => Precision::F64,
        };
        let b = precision.bytes();
        let depth = level.iter().max().map_or(0, |&l| l as usize + 1);
        // Supernodes by level, leaves first (by index within a level).
        let mut order: Vec<usize> = (0..ns).collect();
        order.sort_by_key(|&s| (level[s], s));
        // Chunks of at most `cap` values, in that order.
        let cap = (limit / b).min(u32::MAX as u64) as usize;
        let size = |s: usize| (f.val_ptr[s + 1] - f.val_ptr[s]) as usize;
        let mut chunk = vec![0u32; ns];
        let mut vo = vec![0u32; ns];
        let mut chunk_len = vec![0usize];
        for &s in &order {
            if size(s) > cap {
                return Err(GpuError::LimitExceeded {
                    what: format!(
                        "one supernode of a Cholesky factor ({} x {} values)",
                        f.shape(s).0 + f.shape(s).1,
                        f.shape(s).0
                    ),
                    limit_name: "max_storage_buffer_binding_size",
                    needed: size(s) as u64 * b,
                    limit,
                });
            }
            if chunk_len[chunk_len.len() - 1] + size(s) > cap {
                chunk_len.push(0);
            }
            let k = chunk_len.len() - 1;
            chunk[s] = k as u32;
            vo[s] = chunk_len[k] as u32;
            chunk_len[k] += size(s);
        }
        // The columns and slots in that order, and each level's segments.
        let mut levels: Vec<Vec<[u32; 5]>> = vec![Vec::new(); depth];
        let mut cols = Vec::with_capacity(n);
        let mut owner = vec![0u32; n];
        let mut slots = Vec::with_capacity(nrows);
        let mut slot_owner = vec![0u32; nrows];
        for &s in &order {
            let (m, q) = f.shape(s);
            let segments = &mut levels[level[s] as usize];
            match segments.last_mut() {
                Some(g) if g[4] == chunk[s] => {
                    g[1] += m as u32;
                    g[3] += q as u32;
                }
                _ => segments.push([
                    cols.len() as u32,
                    m as u32,
                    slots.len() as u32,
                    q as u32,
                    chunk[s],
                ]),
            }
            for c in f.begin[s]..f.begin[s + 1] {
                cols.push(c);
                owner[c as usize] = s as u32;
            }
            for e in f.row_ptr[s]..f.row_ptr[s + 1] {
                slots.push(e);
                slot_owner[e as usize] = s as u32;
            }
        }
        let mut idx: Vec<u32> = Vec::with_capacity(total);
        let o_sn = idx.len() as u32;
        for (s, &v) in vo.iter().enumerate() {
            let (m, q) = f.shape(s);
            idx.extend_from_slice(&[f.begin[s], m as u32, q as u32, f.row_ptr[s], v]);
        }
        let o_rows = idx.len() as u32;
        idx.extend_from_slice(&f.rows);
        let o_perm = idx.len() as u32;
        idx.extend_from_slice(&f.perm);
        // The slots holding each row: a counting sort of `rows` by row.
        let o_tptr = idx.len() as u32;
        let mut tptr = vec![0u32; n + 1];
        for &r in &f.rows {
            tptr[r as usize + 1] += 1;
        }
        for i in 0..n {
            tptr[i + 1] += tptr[i];
        }
        idx.extend_from_slice(&tptr);
        let o_tpos = idx.len() as u32;
        let mut tpos = vec![0u32; nrows];
        let mut next = tptr;
        for (e, &r) in f.rows.iter().enumerate() {
            tpos[next[r as usize] as usize] = e as u32;
            next[r as usize] += 1;
        }
        idx.extend_from_slice(&tpos);
        let o_cols = idx.len() as u32;
        idx.extend_from_slice(&cols);
        let o_owner = idx.len() as u32;
        idx.extend_from_slice(&owner);
        let o_slots = idx.len() as u32;
        idx.extend_from_slice(&slots);
        let o_slot_owner = idx.len() as u32;
        idx.extend_from_slice(&slot_owner);
        let bytes = b * f.nnz() as u64 + 8 * nrows as u64;
        let piece = |s: usize| -> &[u8] {
            let r = f.val_ptr[s] as usize..f.val_ptr[s + 1] as usize;
            match precision {
                Precision::F32 => bytemuck::cast_slice(&f.values[r]),
                Precision::F64 => bytemuck::cast_slice(&f.values64[r]),
            }
        };
        let vals = (0..chunk_len.len())
            .map(|k| {
                ctx.storage_from_pieces(
                    &format!("Cholesky values ({precision:?}, chunk {k})"),
                    chunk_len[k] as u64 * b,
                    order
                        .iter()
                        .filter(|&&s| chunk[s] as usize == k)
                        .map(|&s| piece(s)),
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(GpuFactor {
            idx: ctx.storage_init("Cholesky index sections", &idx)?,
            vals,
            offsets: [
                o_sn,
                o_rows,
                o_perm,
                o_tptr,
                o_tpos,
                o_cols,
                o_owner,
                o_slots,
                o_slot_owner,
            ],
            slots: nrows,
            levels,
            nv: n,
            nnz: f.nnz(),
            precision,
            bytes,
        })
    }

    /// Most PCG columns (up to [`crate::CMAX`], at least 1) whose work vectors
    /// and updates fit `limit` bytes a binding, for block rows of `bs`.
    pub fn max_columns(&self, limit: u64, bs: usize) -> usize {
        let b = self.precision.bytes();
        let per = (self.slots.max(self.nv) * bs) as u64 * b;
        ((limit / per.max(1)) as usize).clamp(1, crate::CMAX)
    }

    /// Levels of the elimination tree.
    pub fn depth(&self) -> usize {
        self.levels.len()
    }

    /// Buffers the values are split into.
    pub fn chunks(&self) -> usize {
        self.vals.len()
    }
}

/// One recorded application `z = M^-1 r` for a workspace's `r` and `z`.
pub(crate) struct SupernodalSteps {
    kernels: Arc<SupernodalKernels>,
    /// Per level, per segment ([`GpuFactor::levels`]): its bind group and
    /// its own rows and slots (the dispatch sizes, per column).
    groups: Vec<Vec<(wgpu::BindGroup, [u32; 2])>>,
    bs: usize,
    w: wgpu::Buffer,
    /// Kept alive for the bind groups.
    #[allow(dead_code)]
    y: wgpu::Buffer,
    #[allow(dead_code)]
    contrib: wgpu::Buffer,
    #[allow(dead_code)]
    params: Vec<wgpu::Buffer>,
    /// Factor bytes, and bytes of one PCG column.
    bytes: (u64, u64),
}

impl SupernodalSteps {
    /// The steps for `r` and `z` (in the factor's precision, columns of
    /// `stride = nv * bs`, up to `cmax` of them).
    pub fn new(
        ctx: &Context,
        kernels: &Arc<SupernodalKernels>,
        f: &GpuFactor,
        r: &wgpu::Buffer,
        z: &wgpu::Buffer,
        bs: usize,
        cmax: usize,
    ) -> Result<SupernodalSteps, GpuError> {
        let stride = f.nv * bs;
        let b = f.precision.bytes() as usize;
        if kernels.precision != f.precision {
            return Err(GpuError::Backend(
                "Cholesky kernels and factor of different precisions".into(),
            ));
        }
        let vector = |what: &str| {
            ctx.storage(
                &format!("Cholesky {what} ({stride} x {cmax})"),
                (stride * cmax * b) as u64,
            )
        };
        let (w, y) = (vector("work vector w")?, vector("work vector y")?);
        let contrib = ctx.storage(
            &format!("Cholesky updates ({} x {})", f.slots, bs * cmax),
            (f.slots * bs * cmax * b) as u64,
        )?;
        // An empty factor still records one (empty) segment.
        let levels = match f.levels.is_empty() {
            true => vec![vec![[0; 5]]],
            false => f.levels.clone(),
        };
        let mut params = Vec::new();
        let mut groups = Vec::with_capacity(levels.len());
        for segments in &levels {
            let mut level = Vec::with_capacity(segments.len());
            for &[own, n_own, below, n_below, chunk] in segments {
                let p = ctx.uniform_of(
                    "supernodal params",
                    &SnParams {
                        own,
                        n_own,
                        below,
                        n_below,
                        nv: f.nv as u32,
                        stride: stride as u32,
                        bs: bs as u32,
                        offsets: f.offsets,
                    },
                )?;
                let bg = kernels.shader.bind(
                    ctx,
                    &[
                        (0, &p),
                        (1, &f.idx),
                        (2, &f.vals[chunk as usize]),
                        (3, &w),
                        (4, &y),
                        (5, r),
                        (6, z),
                        (7, &contrib),
                    ],
                )?;
                level.push((bg, [n_own, n_below]));
                params.push(p);
            }
            groups.push(level);
        }
        Ok(SupernodalSteps {
            kernels: kernels.clone(),
            groups,
            bs,
            w,
            y,
            contrib,
            params,
            bytes: (f.bytes, b as u64 * stride as u64),
        })
    }

    /// The work vector (tests poison it).
    #[allow(dead_code)]
    pub fn work_vector(&self) -> &wgpu::Buffer {
        &self.w
    }

    /// Pipelines for `ncols` PCG columns, with the dispatch sizes of each
    /// segment.
    pub fn pipelines(&self, ctx: &Context, ncols: usize) -> Result<Pipelines, GpuError> {
        let k = &self.kernels.kernels;
        let cc = (self.bs * ncols) as u64;
        let dims =
            |items: u64| ctx.dims("supernodal kernel", (items * cc).div_ceil(FLAT_WG as u64));
        let mut levels = Vec::with_capacity(self.groups.len());
        for level in &self.groups {
            let mut segments = Vec::with_capacity(level.len());
            for (_, [own, below]) in level {
                segments.push([dims(*own as u64)?, dims(*own as u64 + *below as u64)?]);
            }
            levels.push(segments);
        }
        Ok(Pipelines {
            p: [
                k[0].pipeline(ctx, ncols)?,
                k[1].pipeline(ctx, ncols)?,
                k[2].pipeline(ctx, ncols)?,
            ],
            levels,
        })
    }

    /// Modelled work of one application for `ncols` columns: the factor read
    /// twice (an operator application each way), the vectors about twice per
    /// sweep, `r` read and `z` written once.
    pub fn work(&self, ncols: usize) -> KernelWork {
        let col = self.bytes.1 * ncols as u64;
        let sweep = KernelWork::operator(self.bytes.0 + 4 * col, self.bytes.0 + 2 * col);
        let segments: usize = self.groups.iter().map(Vec::len).sum();
        KernelWork {
            dispatches: 3 * segments as u64,
            ..sweep.times(2) + KernelWork::other(2 * col).times(2)
        }
    }

    /// Record one application into `pass`. A level's segments are
    /// independent supernodes (in different chunks of the values).
    pub fn record(&self, pass: &mut wgpu::ComputePass, p: &Pipelines) {
        for (level, dims) in self.groups.iter().zip(&p.levels) {
            for ((bg, _), d) in level.iter().zip(dims) {
                dispatch(pass, &p.p[0], bg, d[0]);
                dispatch(pass, &p.p[1], bg, d[1]);
            }
        }
        for (level, dims) in self.groups.iter().zip(&p.levels).rev() {
            for ((bg, _), d) in level.iter().zip(dims) {
                dispatch(pass, &p.p[2], bg, d[0]);
            }
        }
    }
}

/// The pipelines of [`SupernodalSteps`] for one column count, and their
/// dispatch sizes.
pub(crate) struct Pipelines {
    p: [wgpu::ComputePipeline; 3],
    /// Per level and segment: the sizes of `pull` and `backward` (its own
    /// rows), and of `forward` (its own rows and its slots).
    levels: Vec<Vec<[(u32, u32); 2]>>,
}

#[cfg(test)]
mod tests {
    use super::levels;
    use solver_cpu::{CholeskySolver, FillOrdering, SpdSolver, SymCsc};

    /// A path's factor is a chain: one level per supernode; a grid's
    /// nested-dissection factor is far shallower than its unknowns.
    #[test]
    fn levels_follow_the_elimination_tree() {
        let n = 400;
        let mut a = SymCsc::from_pattern(
            n,
            (0..n)
                .flat_map(|i| [(i, i), (i + 1, i)])
                .filter(|&(r, _)| r < n),
        );
        for j in 0..n {
            for s in a.col_ptr[j]..a.col_ptr[j + 1] {
                a.values[s] = if a.row_idx[s] == j { 2.5 } else { -1.0 };
            }
        }
        let mut c = CholeskySolver::single_precision();
        c.set_fill_ordering(FillOrdering::NestedDissection);
        c.prepare(&a).unwrap();
        let f = c.take_supernodal_factor().unwrap();
        let l = levels(&f).unwrap();
        let depth = *l.iter().max().unwrap() as usize + 1;
        // Nested dissection of a path: about log2(n) levels of separators.
        assert!(depth < 40, "depth {depth} of {} supernodes", f.len());
        for s in 0..f.len() {
            for &r in &f.rows[f.row_ptr[s] as usize..f.row_ptr[s + 1] as usize] {
                let p = (0..f.len())
                    .find(|&t| f.begin[t] <= r && r < f.begin[t + 1])
                    .unwrap();
                assert!(
                    l[p] > l[s],
                    "supernode {s} updates {p} on a level not above it"
                );
            }
        }
    }
}
