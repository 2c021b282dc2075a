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
//! `3 levels` dispatches, no host work and no atomics (the same result on
//! every run): per level of the supernodal elimination tree,
//! leaves first, pull `w_s = (P r)_s` less the descendants' updates, then one
//! step for `y_s = L_ss^-1 w_s` and the updates `B_s w_s` of the rows below
//! (both read `w_s` only); per level, root first, `x_s = L_ss^-T y_s - B_s^T
//! x_r` in one step, written to `z = P^T x` as well. Each kernel computes one
//! dot product per row (or slot) and scalar column of the level: the dense
//! separators at the top of the tree spread over the whole GPU instead of one
//! workgroup. Where a level has too few rows to fill a discrete GPU and long
//! rows (the separators: up to 2,000 terms at homer 1.2M), a team of lanes
//! shares each dot product ([`team`]), so that an application's chain of
//! dependent steps ([`KernelWork::serial_steps`]) is not the sum of the
//! separators' widths.
//!
//! The values are stored level by level and cut into buffers of at most one
//! storage binding at supernode boundaries ([`GpuFactor::upload`]); a level
//! whose supernodes span two buffers is dispatched as two segments. The
//! updates `B_s w_s` (one per slot below a diagonal block and scalar column,
//! kept in the slots' level order) are cut the same way
//! ([`SupernodalSteps::new`]; homer 1.2M's, 180 MB for one PCG column, over
//! lavapipe's 128 MiB binding): a segment is dispatched as one piece per
//! update buffer its slots fill, and a level's rows pull once from each
//! buffer that holds updates of theirs, in order (the same sums in the same
//! order as with one buffer).
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
    pub(crate) offsets: [u32; 8],
    /// The bound update buffer's slots, `[update0, update1)` in the level
    /// order of the slots.
    pub(crate) update0: u32,
    pub(crate) update1: u32,
    /// Whether `pull` starts from `r` (the first update buffer) or from `w`.
    pub(crate) first: u32,
    /// Lanes per dot product of `forward` and of `backward` ([`team`]).
    pub(crate) team_f: u32,
    pub(crate) team_b: u32,
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

    /// Its kernels (pull, forward, backward): a solve runs all three.
    pub fn kernels(&self) -> &[Kernel; 3] {
        &self.kernels
    }
}

/// `f`'s values in `precision`, uploaded chunk by chunk in `place`'s order
/// (each supernode's block as it is, a piece of one upload).
fn upload_values(
    ctx: &Context,
    staging: &mut crate::device::Staging,
    f: &SupernodalFactor,
    place: &Placement,
    chunk_len: &[usize],
    precision: Precision,
) -> Result<Vec<wgpu::Buffer>, GpuError> {
    let piece = |s: usize| -> &[u8] {
        let r = f.val_ptr[s] as usize..f.val_ptr[s + 1] as usize;
        match precision {
            Precision::F32 => bytemuck::cast_slice(&f.values[r]),
            Precision::F64 => bytemuck::cast_slice(&f.values64[r]),
        }
    };
    (0..chunk_len.len())
        .map(|k| {
            ctx.storage_from_pieces(
                staging,
                &format!("Cholesky values ({precision:?}, chunk {k})"),
                chunk_len[k] as u64 * precision.bytes(),
                place
                    .order
                    .iter()
                    .filter(|&&s| place.chunk[s] as usize == k)
                    .map(|&s| piece(s)),
            )
        })
        .collect()
}

/// A supernodal factor on the GPU, with its level schedule.
pub(crate) struct GpuFactor {
    pub(crate) idx: wgpu::Buffer,
    /// The values, in chunks of at most one storage binding each, split at
    /// supernode boundaries (a supernode's `vo` is its offset in its chunk).
    pub(crate) vals: Vec<wgpu::Buffer>,
    /// Offsets of the sections of `idx` (as in `SnParams::offsets`).
    pub(crate) offsets: [u32; 8],
    /// Slots of `rows` (one update per slot and column in `contrib`).
    pub(crate) slots: usize,
    /// Per level, leaves first, its segments (one dispatch per segment and
    /// kernel).
    pub(crate) levels: Vec<Vec<Segment>>,
    /// Each supernode's columns and slots below its diagonal block, the
    /// supernodes in level order ([`Segment::sn`]): where the updates may be
    /// cut.
    sizes: Vec<[u32; 2]>,
    /// Per supernode in level order, the most updates any of its rows pulls
    /// (the longest loop of its `pull`).
    pulls: Vec<u32>,
    /// Rows of `K`.
    pub nv: usize,
    /// Stored values of the factor.
    pub nnz: usize,
    /// Precision of its values (and of the vectors its solves run on).
    pub precision: Precision,
    /// Bytes of the factor's values and row indices (read twice an application).
    bytes: u64,
    /// The host's symbolic analysis it is of, where its maker knows it: a
    /// factor of the same one shares its index sections
    /// ([`GpuFactor::upload_like`]).
    pub(crate) analysis: Option<solver_cpu::AnalysisId>,
}

/// Where [`GpuFactor::upload`] put each supernode's values.
pub(crate) struct Placement {
    /// The supernodes in level order (leaves first).
    pub order: Vec<usize>,
    /// Each supernode's first value in its chunk.
    pub vo: Vec<u32>,
    /// Each supernode's chunk.
    pub chunk: Vec<u32>,
    /// Each chunk's first value, counting the values before it.
    pub starts: Vec<u64>,
}

impl Placement {
    /// `f`'s supernodes by `level`, leaves first (by index within a level),
    /// their values cut into chunks of at most `cap` at supernode
    /// boundaries; and each chunk's values. `Err(s)` where supernode `s`
    /// alone exceeds `cap`.
    pub fn new(
        f: &SupernodalFactor,
        level: &[u32],
        cap: usize,
    ) -> Result<(Placement, Vec<usize>), usize> {
        let ns = f.len();
        let mut order: Vec<usize> = (0..ns).collect();
        order.sort_by_key(|&s| (level[s], s));
        let size = |s: usize| (f.val_ptr[s + 1] - f.val_ptr[s]) as usize;
        let runs = pack(order.iter().map(|&s| size(s)), cap).map_err(|i| order[i])?;
        let mut chunk = vec![0u32; ns];
        let mut vo = vec![0u32; ns];
        let mut chunk_len = vec![0usize];
        for (&s, &k) in order.iter().zip(&runs) {
            let k = k as usize;
            if k == chunk_len.len() {
                chunk_len.push(0);
            }
            chunk[s] = k as u32;
            vo[s] = chunk_len[k] as u32;
            chunk_len[k] += size(s);
        }
        let starts = chunk_len
            .iter()
            .scan(0u64, |at, &len| {
                let start = *at;
                *at += len as u64;
                Some(start)
            })
            .collect();
        let place = Placement {
            order,
            vo,
            chunk,
            starts,
        };
        Ok((place, chunk_len))
    }

    /// Each supernode's first value counting every chunk's (`None` past
    /// 32 bits).
    pub fn global_vo(&self) -> Option<Vec<u32>> {
        self.vo
            .iter()
            .zip(&self.chunk)
            .map(|(&v, &c)| u32::try_from(self.starts[c as usize] + v as u64).ok())
            .collect()
    }
}

/// Supernodes of one level whose values are in one chunk, consecutive in the
/// level order: `[own, own + n_own)` their columns in the `cols` section,
/// `[below, below + n_below)` their slots in the slots' level order (the
/// `rows` section, and an update's position in `contrib`), and `[sn, sn +
/// n_sn)` the supernodes themselves in that order.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct Segment {
    own: u32,
    n_own: u32,
    below: u32,
    n_below: u32,
    /// The chunk of the values.
    pub(crate) chunk: u32,
    pub(crate) sn: u32,
    pub(crate) n_sn: u32,
}

impl GpuFactor {
    /// Supernodes of the factor.
    pub fn supernodes(&self) -> usize {
        self.sizes.len()
    }

    /// Upload `f` (its diagonal blocks inverted; indices in u32). The values
    /// are stored level by level, leaves first, and cut into chunks of at
    /// most `limit` bytes (one storage binding) at supernode boundaries, so
    /// that a level's supernodes share one chunk but where a cut falls: a
    /// factor larger than a binding (homer 4.3M's f64 factor, 3.5 GB, against
    /// the H100's 2 GiB) costs a few dispatches more, not the preconditioner.
    pub fn upload(ctx: &Context, f: &SupernodalFactor, limit: u64) -> Result<GpuFactor, GpuError> {
        if !f.inverted {
            return Err(GpuError::Backend(
                "supernodal factor: diagonal blocks not inverted".into(),
            ));
        }
        Ok(GpuFactor::build(ctx, f, limit, true)?.0)
    }

    /// The factor of `f`'s structure (its values, if any, ignored) in f64,
    /// its values zero, laid out as [`GpuFactor::upload`] lays them out, for
    /// a numeric factorization on the GPU ([`crate::factorize`]); and where
    /// each supernode's values start. Refused, before any buffer is made,
    /// where the values would take more than that factorization's
    /// [`crate::factorize::VALUE_BUFFERS`].
    pub fn allocate(
        ctx: &Context,
        f: &SupernodalFactor,
        limit: u64,
    ) -> Result<(GpuFactor, Placement), GpuError> {
        GpuFactor::build(ctx, f, limit, false)
    }

    fn build(
        ctx: &Context,
        f: &SupernodalFactor,
        limit: u64,
        fill: bool,
    ) -> Result<(GpuFactor, Placement), GpuError> {
        let ns = f.len();
        let bad = |what: &str| GpuError::Backend(format!("supernodal factor: {what}"));
        let level = f
            .levels()
            .ok_or_else(|| bad("supernodes out of topological order"))?;
        let n = f.perm.len();
        let nrows = f.rows.len();
        let total = 5 * ns + nrows + n + (n + 1) + nrows + 2 * n + nrows;
        if total > u32::MAX as usize {
            return Err(GpuError::LimitExceeded {
                what: "a Cholesky factor's index sections (32-bit offsets)".into(),
                limit_name: "u32::MAX",
                needed: total as u64,
                limit: u32::MAX as u64,
            });
        }
        let precision = match f.values64.is_empty() && fill {
            true => Precision::F32,
            false => Precision::F64,
        };
        let nvals = f.val_ptr.last().copied().unwrap_or(0) as usize;
        if fill && nvals != f.nnz() {
            return Err(bad("values and structure differ in length"));
        }
        let b = precision.bytes();
        let depth = level.iter().max().map_or(0, |&l| l as usize + 1);
        // Supernodes by level, leaves first, in chunks of at most `cap`
        // values.
        let cap = (limit / b).min(u32::MAX as u64) as usize;
        let size = |s: usize| (f.val_ptr[s + 1] - f.val_ptr[s]) as usize;
        let (place, chunk_len) =
            Placement::new(f, &level, cap).map_err(|s| GpuError::LimitExceeded {
                what: format!(
                    "one supernode of a Cholesky factor ({} x {} values)",
                    f.shape(s).0 + f.shape(s).1,
                    f.shape(s).0
                ),
                limit_name: "max_storage_buffer_binding_size",
                needed: size(s) as u64 * b,
                limit,
            })?;
        if !fill && chunk_len.len() > crate::factorize::VALUE_BUFFERS {
            return Err(GpuError::LimitExceeded {
                what: format!(
                    "a Cholesky factor factored on the GPU ({nvals} values in {} buffers)",
                    chunk_len.len()
                ),
                limit_name: "max_storage_buffer_binding_size",
                needed: nvals as u64 * b,
                limit,
            });
        }
        let Placement {
            order, vo, chunk, ..
        } = &place;
        // The columns and slots in that order, and each level's segments.
        let mut levels: Vec<Vec<Segment>> = vec![Vec::new(); depth];
        let mut cols = Vec::with_capacity(n);
        let mut owner = vec![0u32; n];
        // The slots in level order: each supernode's rows below its diagonal
        // block from `po[s]` on, and the supernode of each.
        let mut rows = Vec::with_capacity(nrows);
        let mut slot_owner = Vec::with_capacity(nrows);
        let mut po = vec![0u32; ns];
        let mut sizes = Vec::with_capacity(ns);
        for &s in order {
            let (m, q) = f.shape(s);
            let segments = &mut levels[level[s] as usize];
            match segments.last_mut() {
                Some(g) if g.chunk == chunk[s] => {
                    g.n_own += m as u32;
                    g.n_below += q as u32;
                    g.n_sn += 1;
                }
                _ => segments.push(Segment {
                    own: cols.len() as u32,
                    n_own: m as u32,
                    below: rows.len() as u32,
                    n_below: q as u32,
                    chunk: chunk[s],
                    sn: sizes.len() as u32,
                    n_sn: 1,
                }),
            }
            sizes.push([m as u32, q as u32]);
            for c in f.begin[s]..f.begin[s + 1] {
                cols.push(c);
                owner[c as usize] = s as u32;
            }
            po[s] = rows.len() as u32;
            rows.extend_from_slice(&f.rows[f.row_ptr[s] as usize..f.row_ptr[s + 1] as usize]);
            slot_owner.resize(rows.len(), s as u32);
        }
        // The index sections, in this order in one buffer: each supernode's
        // header, the slots' rows, the permutation, the slots of each row
        // (pointers, then positions), the columns, their owners and the
        // slots' owners. Each goes up as it is, a piece of one upload: no
        // concatenated copy (at homer 1.2M, about 220 MB beside the 985 MB of
        // values the caller holds).
        let header: Vec<u32> = vo
            .iter()
            .enumerate()
            .flat_map(|(s, &v)| {
                let (m, q) = f.shape(s);
                [f.begin[s], m as u32, q as u32, po[s], v]
            })
            .collect();
        // The slots holding each row, ascending (in the level order, where
        // their updates are kept): a counting sort by row.
        let mut tptr = vec![0u32; n + 1];
        for &r in &f.rows {
            tptr[r as usize + 1] += 1;
        }
        for i in 0..n {
            tptr[i + 1] += tptr[i];
        }
        let pulls = order
            .iter()
            .map(|&s| {
                (f.begin[s]..f.begin[s + 1])
                    .map(|c| tptr[c as usize + 1] - tptr[c as usize])
                    .max()
                    .unwrap_or(0)
            })
            .collect();
        let mut tpos = vec![0u32; nrows];
        let mut next = tptr.clone();
        for (p, &r) in rows.iter().enumerate() {
            tpos[next[r as usize] as usize] = p as u32;
            next[r as usize] += 1;
        }
        drop(next);
        let sections: [&[u32]; 8] = [
            &header,
            &rows,
            &f.perm,
            &tptr,
            &tpos,
            &cols,
            &owner,
            &slot_owner,
        ];
        let mut offsets = [0u32; 8];
        let mut at = 0usize;
        for (o, section) in offsets.iter_mut().zip(sections) {
            *o = at as u32;
            at += section.len();
        }
        debug_assert_eq!(at, total);
        // One staging buffer for every window of the index and the values.
        let mut staging = crate::device::Staging::default();
        let idx_buf = ctx.storage_from_pieces(
            &mut staging,
            "Cholesky index sections",
            4 * total as u64,
            sections.map(bytemuck::cast_slice::<u32, u8>),
        )?;
        // The host's copies are dropped before the values go up.
        drop((header, rows, tptr, tpos, cols, owner, slot_owner));
        let bytes = b * nvals as u64 + 8 * nrows as u64;
        let vals = match fill {
            true => upload_values(ctx, &mut staging, f, &place, &chunk_len, precision)?,
            false => (0..chunk_len.len())
                .map(|k| {
                    let label = format!("Cholesky values ({precision:?}, chunk {k})");
                    ctx.storage(&label, chunk_len[k] as u64 * b)
                })
                .collect::<Result<Vec<_>, _>>()?,
        };
        let g = GpuFactor {
            idx: idx_buf,
            vals,
            offsets,
            slots: nrows,
            levels,
            sizes,
            pulls,
            nv: n,
            nnz: nvals,
            precision,
            bytes,
            analysis: None,
        };
        Ok((g, place))
    }

    /// `f` (its diagonal blocks inverted) uploaded as [`GpuFactor::upload`]
    /// would, but for its values alone: laid out as `like`, a factor of the
    /// same symbolic analysis, precision and binding `limit`, whose index
    /// sections it shares (not built or sent again: about 220 MB at homer
    /// 1.2M). Refused where `f`'s structure does not lay out as `like`'s.
    pub fn upload_like(
        ctx: &Context,
        like: &GpuFactor,
        f: &SupernodalFactor,
        limit: u64,
    ) -> Result<GpuFactor, GpuError> {
        let bad = |what: &str| GpuError::Backend(format!("supernodal factor: {what}"));
        if !f.inverted {
            return Err(bad("diagonal blocks not inverted"));
        }
        let precision = match f.values64.is_empty() {
            true => Precision::F32,
            false => Precision::F64,
        };
        let nvals = f.val_ptr.last().copied().unwrap_or(0) as usize;
        if precision != like.precision
            || nvals != f.nnz()
            || nvals != like.nnz
            || f.len() != like.sizes.len()
            || f.perm.len() != like.nv
            || f.rows.len() != like.slots
        {
            return Err(bad("not of the structure of the factor it is laid out as"));
        }
        let level = f
            .levels()
            .ok_or_else(|| bad("supernodes out of topological order"))?;
        let cap = (limit / precision.bytes()).min(u32::MAX as u64) as usize;
        let (place, chunk_len) =
            Placement::new(f, &level, cap).map_err(|_| bad("a supernode over the binding"))?;
        let b = precision.bytes();
        if chunk_len.len() != like.vals.len()
            || chunk_len
                .iter()
                .zip(&like.vals)
                .any(|(&n, v)| (n as u64 * b).max(16).div_ceil(4) * 4 != v.size())
        {
            return Err(bad("values not cut as the factor's it is laid out as"));
        }
        let mut staging = crate::device::Staging::default();
        let vals = upload_values(ctx, &mut staging, f, &place, &chunk_len, precision)?;
        Ok(GpuFactor {
            vals,
            ..like.handles()
        })
    }

    /// This factor's handles (its buffers shared, not copied): a skeleton
    /// for [`GpuFactor::twin`] that outlives no buffer it names.
    pub fn handles(&self) -> GpuFactor {
        GpuFactor {
            idx: self.idx.clone(),
            vals: self.vals.clone(),
            offsets: self.offsets,
            slots: self.slots,
            levels: self.levels.clone(),
            sizes: self.sizes.clone(),
            pulls: self.pulls.clone(),
            nv: self.nv,
            nnz: self.nnz,
            precision: self.precision,
            bytes: self.bytes,
            analysis: self.analysis.clone(),
        }
    }

    /// A factor of the same structure on the same device, sharing this one's
    /// index sections (one buffer, not made or sent again), its values new
    /// (zero): for another factorization of the same pattern on the GPU
    /// ([`crate::factorize::GpuFactorization::for_factor`]).
    pub fn twin(&self, ctx: &Context) -> Result<GpuFactor, GpuError> {
        let vals = self
            .vals
            .iter()
            .enumerate()
            .map(|(k, b)| {
                let label = format!("Cholesky values ({:?}, chunk {k})", self.precision);
                ctx.storage(&label, b.size())
            })
            .collect::<Result<Vec<_>, _>>()?;
        Ok(GpuFactor {
            vals,
            ..self.handles()
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
    /// Per level, its pieces: the segments ([`GpuFactor::levels`]) cut
    /// where the updates change buffer.
    levels: Vec<Vec<Piece>>,
    bs: usize,
    w: wgpu::Buffer,
    /// Kept alive for the bind groups.
    #[allow(dead_code)]
    y: wgpu::Buffer,
    #[allow(dead_code)]
    contrib: Vec<wgpu::Buffer>,
    #[allow(dead_code)]
    params: Vec<wgpu::Buffer>,
    /// Factor bytes, and bytes of one PCG column.
    bytes: (u64, u64),
}

/// A segment's supernodes whose updates are in one buffer, with a bind
/// group for each update buffer its `pull` reads (the first of them
/// starting from `r`) and for the one its `forward` writes.
struct Piece {
    groups: Vec<wgpu::BindGroup>,
    /// Update buffers its rows' `pull` reads: `groups[..pulls]`.
    pulls: usize,
    /// The update buffer its `forward` writes: `groups[own]`.
    own: usize,
    /// Its own rows and slots (the dispatch sizes, per column).
    rows: [u32; 2],
    /// Lanes per dot product of `forward` and `backward` ([`team`]).
    teams: [u32; 2],
    /// Serial steps of its `pull` (each), `forward` and `backward`: the
    /// longest loop of one lane, with a team's additions.
    steps: [u32; 3],
}

/// Invocations that fill a discrete GPU's cores with work to hide memory
/// latency (an H100 holds 270k resident: 132 units of 2,048).
const FILL: u64 = 1 << 18;

/// Least terms a team's lane takes of a dot product.
const LANE_TERMS: u32 = 8;

/// Most lanes of a team (a power of two dividing the shader's workgroup).
pub(crate) const MAX_TEAM: u32 = 64;

/// Lanes that share each of a level's `items` dot products of up to `len`
/// terms (a power of two, 1 to `most`): as many as fit one wave of a large
/// GPU ([`FILL`]) beside the `items` (a level with rows enough to fill it
/// keeps one lane per dot product, which streams the factor best; more lanes
/// would wait for room, not shorten the chain), and no more than give each
/// lane [`LANE_TERMS`] terms. A function of the factor's shape alone, so a
/// factor's sums are the same on every adapter.
fn team(items: u64, len: u32, most: u32) -> u32 {
    let floor2 = |v: u64| 1u64 << (63 - v.max(1).leading_zeros());
    let by_room = floor2(FILL / items.max(1));
    let by_len = floor2((len / LANE_TERMS) as u64);
    by_room.min(by_len).min(most as u64) as u32
}

/// Serial steps of one lane of a team of `team` over `len` terms: its share
/// of the terms and the team's pairwise additions.
fn team_steps(len: u32, team: u32) -> u32 {
    len.div_ceil(team) + team.trailing_zeros()
}

/// Cut consecutive items of `sizes` into runs of at most `cap` (greedy: an
/// item starts a new run where it would not fit the current one): each
/// item's run. `Err(i)` where item `i` alone exceeds `cap`. The values of
/// a factor are cut so by supernode ([`GpuFactor::upload`]), and the updates
/// of its solves too ([`SupernodalSteps::new`]).
fn pack(sizes: impl IntoIterator<Item = usize>, cap: usize) -> Result<Vec<u32>, usize> {
    let (mut run, mut len) = (0u32, 0usize);
    let mut out = Vec::new();
    for (i, q) in sizes.into_iter().enumerate() {
        if q > cap {
            return Err(i);
        }
        if len + q > cap {
            run += 1;
            len = 0;
        }
        len += q;
        out.push(run);
    }
    Ok(out)
}

/// The pieces of one level's segments: each cut where its supernodes'
/// update buffer (`buffer`, per supernode in level order, from [`pack`])
/// changes; each as `(segment with its own rows and slots, update buffer)`.
fn cut_segments(segments: &[Segment], sizes: &[[u32; 2]], buffer: &[u32]) -> Vec<(Segment, usize)> {
    let mut pieces: Vec<(Segment, usize)> = Vec::new();
    for g in segments {
        let (mut own, mut below) = (g.own, g.below);
        let mut piece: Option<(Segment, usize)> = None;
        for s in g.sn..g.sn + g.n_sn {
            let [m, q] = sizes[s as usize];
            let k = buffer[s as usize] as usize;
            match &mut piece {
                Some((p, pk)) if *pk == k => {
                    p.n_own += m;
                    p.n_below += q;
                    p.n_sn += 1;
                }
                _ => {
                    pieces.extend(piece.take());
                    piece = Some((
                        Segment {
                            own,
                            n_own: m,
                            below,
                            n_below: q,
                            chunk: g.chunk,
                            sn: s,
                            n_sn: 1,
                        },
                        k,
                    ));
                }
            }
            own += m;
            below += q;
        }
        pieces.extend(piece);
    }
    pieces
}

impl SupernodalSteps {
    /// The steps for `r` and `z` (in the factor's precision, columns of
    /// `stride = nv * bs`, up to `cmax` of them). The updates are cut into
    /// buffers of at most `limit` bytes (one storage binding) at supernode
    /// boundaries, as the values are.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        ctx: &Context,
        kernels: &Arc<SupernodalKernels>,
        f: &GpuFactor,
        r: &wgpu::Buffer,
        z: &wgpu::Buffer,
        bs: usize,
        cmax: usize,
        limit: u64,
    ) -> Result<SupernodalSteps, GpuError> {
        Self::with_teams(ctx, kernels, f, (r, z), bs, cmax, limit, MAX_TEAM)
    }

    /// [`SupernodalSteps::new`] with teams of at most `most` lanes ([`team`]).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn with_teams(
        ctx: &Context,
        kernels: &Arc<SupernodalKernels>,
        f: &GpuFactor,
        (r, z): (&wgpu::Buffer, &wgpu::Buffer),
        bs: usize,
        cmax: usize,
        limit: u64,
        most: u32,
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
        let per_slot = (bs * cmax * b) as u64;
        let cap = (limit / per_slot).min(u32::MAX as u64) as usize;
        let buffer = pack(f.sizes.iter().map(|s| s[1] as usize), cap).map_err(|i| {
            GpuError::LimitExceeded {
                what: format!("the updates of one Cholesky supernode for {cmax} columns"),
                limit_name: "max_storage_buffer_binding_size",
                needed: f.sizes[i][1] as u64 * per_slot,
                limit,
            }
        })?;
        // The first slot of each buffer, and the slot count last.
        let buffers = buffer.last().map_or(1, |&k| k as usize + 1);
        let mut starts = vec![0usize; buffers + 1];
        for (&[_, q], &k) in f.sizes.iter().zip(&buffer) {
            starts[k as usize + 1] += q as usize;
        }
        for k in 0..buffers {
            starts[k + 1] += starts[k];
        }
        let contrib = (0..starts.len() - 1)
            .map(|k| {
                let slots = starts[k + 1] - starts[k];
                ctx.storage(
                    &format!("Cholesky updates {k} ({slots} x {})", bs * cmax),
                    slots as u64 * per_slot,
                )
            })
            .collect::<Result<Vec<_>, _>>()?;
        // An empty factor still records one (empty) piece.
        let levels = match f.levels.is_empty() {
            true => vec![vec![Segment::default()]],
            false => f.levels.clone(),
        };
        let mut params = Vec::new();
        let mut pieces = Vec::with_capacity(levels.len());
        for segments in &levels {
            // The level's rows are updated by the slots of the levels below.
            let first = segments.first().map_or(0, |g| g.below as usize);
            let pulls = starts[..starts.len() - 1]
                .iter()
                .filter(|&&a| a < first)
                .count()
                .max(1);
            // The level's teams, from the whole level (not its segments and
            // pieces, which the adapter's binding size cuts): every dot
            // product's sum is the same wherever the cuts fall. Forward:
            // own row k of supernode s sums k + 1 terms, a slot m;
            // backward: own row k, m - k + q.
            let sns = || {
                segments
                    .iter()
                    .flat_map(|g| g.sn as usize..(g.sn + g.n_sn) as usize)
            };
            let len_f = sns().map(|s| f.sizes[s][0]).max().unwrap_or(0);
            let len_b = sns()
                .map(|s| f.sizes[s][0] + f.sizes[s][1])
                .max()
                .unwrap_or(0);
            let (own_rows, slots) = segments.iter().fold((0u64, 0u64), |(a, b), g| {
                (a + g.n_own as u64, b + g.n_below as u64)
            });
            let teams = [
                team((own_rows + slots) * bs as u64, len_f, most),
                team(own_rows * bs as u64, len_b, most),
            ];
            let mut level = Vec::new();
            for (g, own) in cut_segments(segments, &f.sizes, &buffer) {
                let sns = g.sn as usize..(g.sn + g.n_sn) as usize;
                let len_p = f.pulls[sns.clone()].iter().copied().max().unwrap_or(0);
                let len_f = f.sizes[sns.clone()].iter().map(|s| s[0]).max().unwrap_or(0);
                let len_b = f.sizes[sns].iter().map(|s| s[0] + s[1]).max().unwrap_or(0);
                let mut bind = |k: usize| -> Result<wgpu::BindGroup, GpuError> {
                    let p = ctx.uniform_of(
                        "supernodal params",
                        &SnParams {
                            own: g.own,
                            n_own: g.n_own,
                            below: g.below,
                            n_below: g.n_below,
                            nv: f.nv as u32,
                            stride: stride as u32,
                            bs: bs as u32,
                            offsets: f.offsets,
                            update0: starts[k] as u32,
                            update1: starts[k + 1] as u32,
                            first: (k == 0) as u32,
                            team_f: teams[0],
                            team_b: teams[1],
                        },
                    )?;
                    let group = kernels.shader.bind(
                        ctx,
                        &[
                            (0, &p),
                            (1, &f.idx),
                            (2, &f.vals[g.chunk as usize]),
                            (3, &w),
                            (4, &y),
                            (5, r),
                            (6, z),
                            (7, &contrib[k]),
                        ],
                    )?;
                    params.push(p);
                    Ok(group)
                };
                let mut groups = (0..pulls).map(&mut bind).collect::<Result<Vec<_>, _>>()?;
                let own = match own < pulls {
                    true => own,
                    false => {
                        groups.push(bind(own)?);
                        pulls
                    }
                };
                level.push(Piece {
                    groups,
                    pulls,
                    own,
                    rows: [g.n_own, g.n_below],
                    teams,
                    steps: [
                        len_p,
                        team_steps(len_f, teams[0]),
                        team_steps(len_b, teams[1]),
                    ],
                });
            }
            pieces.push(level);
        }
        Ok(SupernodalSteps {
            kernels: kernels.clone(),
            levels: pieces,
            bs,
            w,
            y,
            contrib,
            params,
            bytes: (f.bytes, b as u64 * stride as u64),
        })
    }

    /// Buffers the updates are cut into.
    #[allow(dead_code)]
    pub fn update_buffers(&self) -> usize {
        self.contrib.len()
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
        let mut levels = Vec::with_capacity(self.levels.len());
        for level in &self.levels {
            let mut pieces = Vec::with_capacity(level.len());
            for Piece {
                rows: [own, below],
                teams: [team_f, team_b],
                ..
            } in level
            {
                let (own, below) = (*own as u64, *below as u64);
                pieces.push([
                    dims(own)?,
                    dims((own + below) * *team_f as u64)?,
                    dims(own * *team_b as u64)?,
                ]);
            }
            levels.push(pieces);
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
        let dispatches: usize = self.levels.iter().flatten().map(|p| p.pulls + 2).sum();
        KernelWork {
            dispatches: dispatches as u64,
            serial_steps: self.serial_steps(),
            ..sweep.times(2) + KernelWork::other(2 * col).times(2)
        }
    }

    /// The chain of dependent steps through one application: each
    /// dispatch's longest lane (a dot product's terms, or a team's share of
    /// them and its additions), the dispatches one after another.
    pub fn serial_steps(&self) -> u64 {
        let piece =
            |p: &Piece| p.pulls as u64 * p.steps[0] as u64 + (p.steps[1] + p.steps[2]) as u64;
        self.levels.iter().flatten().map(piece).sum()
    }

    /// Record one application into `pass`. A level's pieces are independent
    /// supernodes (in different chunks of the values or the updates); a
    /// piece's rows pull the updates of the levels below from each buffer
    /// that holds some, in the buffers' order.
    pub fn record(&self, pass: &mut wgpu::ComputePass, p: &Pipelines) {
        for (level, dims) in self.levels.iter().zip(&p.levels) {
            for (piece, d) in level.iter().zip(dims) {
                for bg in &piece.groups[..piece.pulls] {
                    dispatch(pass, &p.p[0], bg, d[0]);
                }
                dispatch(pass, &p.p[1], &piece.groups[piece.own], d[1]);
            }
        }
        for (level, dims) in self.levels.iter().zip(&p.levels).rev() {
            for (piece, d) in level.iter().zip(dims) {
                dispatch(pass, &p.p[2], &piece.groups[piece.own], d[2]);
            }
        }
    }
}

/// The pipelines of [`SupernodalSteps`] for one column count, and their
/// dispatch sizes.
pub(crate) struct Pipelines {
    p: [wgpu::ComputePipeline; 3],
    /// Per level and piece: the sizes of `pull` (its own rows), `forward`
    /// (its own rows and its slots, times its team) and `backward` (its
    /// own rows, times its team).
    levels: Vec<Vec<[(u32, u32); 3]>>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use solver_cpu::{CholeskySolver, FillOrdering, SpdSolver, SymCsc};

    /// A grid's Laplacian plus a shift, `nx x ny` unknowns.
    fn grid(nx: usize, ny: usize) -> SymCsc {
        let id = |i: usize, j: usize| i * ny + j;
        let mut pairs = Vec::new();
        for i in 0..nx {
            for j in 0..ny {
                pairs.push((id(i, j), id(i, j)));
                if i + 1 < nx {
                    pairs.push((id(i + 1, j), id(i, j)));
                }
                if j + 1 < ny {
                    pairs.push((id(i, j + 1), id(i, j)));
                }
            }
        }
        let mut a = SymCsc::from_pattern(nx * ny, pairs);
        for j in 0..a.n {
            for s in a.col_ptr[j]..a.col_ptr[j + 1] {
                let r = a.row_idx[s];
                a.values[s] = if r == j {
                    4.1 + (j % 7) as f64 * 0.1
                } else {
                    -1.0
                };
            }
        }
        a
    }

    /// The precisions the adapter runs the factor's solves in.
    fn precisions(ctx: &Context) -> Vec<Precision> {
        match ctx.shader_f64 {
            true => vec![Precision::F32, Precision::F64],
            false => vec![Precision::F32],
        }
    }

    /// The host's supernodal factor of `k` in `precision` (nested
    /// dissection), prepared.
    fn host_factor(k: &SymCsc, precision: Precision) -> CholeskySolver {
        let mut host = match precision {
            Precision::F32 => CholeskySolver::single_precision(),
            Precision::F64 => CholeskySolver::new(),
        };
        host.supernodal = true;
        host.set_fill_ordering(FillOrdering::NestedDissection);
        host.prepare(k).unwrap();
        host
    }

    /// Values read back in `precision`, as f64.
    fn decode(precision: Precision, z: &[u8]) -> Vec<f64> {
        match precision {
            Precision::F32 => bytemuck::cast_slice::<u8, f32>(z)
                .iter()
                .map(|&v| v as f64)
                .collect(),
            Precision::F64 => bytemuck::cast_slice::<u8, f64>(z).to_vec(),
        }
    }

    /// One application of `steps` to `r` (`ncols` columns) on the GPU.
    fn apply(
        ctx: &Context,
        steps: &SupernodalSteps,
        r: &wgpu::Buffer,
        z: &wgpu::Buffer,
        rhs: &[f64],
        ncols: usize,
        precision: Precision,
    ) -> Vec<u8> {
        ctx.write_buffer(r, 0, &precision.encode(rhs));
        ctx.write_buffer(z, 0, &precision.encode(&vec![f64::NAN; rhs.len()]));
        ctx.write_buffer(
            steps.work_vector(),
            0,
            &precision.encode(&vec![f64::NAN; rhs.len()]),
        );
        let pipelines = steps.pipelines(ctx, ncols).unwrap();
        let mut enc = ctx.encoder("supernodal test");
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            steps.record(&mut pass, &pipelines);
        }
        ctx.read::<u8>(
            z,
            rhs.len() * precision.bytes() as usize,
            &mut None,
            Some(enc),
        )
        .unwrap()
    }

    /// Updates cut over several buffers (a binding too small for one
    /// column's) solve as one buffer does, to the bit: the same sums in the
    /// same order, with a pull per buffer a level reads; and that solve is
    /// the factor's, per component of each column.
    #[test]
    fn updates_over_several_buffers_solve_as_one() {
        let Some(s) = crate::test_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let k = grid(70, 60);
        let n = k.n;
        let (bs, ncols) = (3, 2);
        for precision in precisions(ctx) {
            let mut host = host_factor(&k, precision);
            let rhs: Vec<f64> = (0..n * bs * ncols)
                .map(|i| ((i * 7919) % 1013) as f64 / 1013.0 - 0.5)
                .collect();
            let mut want = vec![0.0; rhs.len()];
            for c in 0..ncols {
                for q in 0..bs {
                    let mut col: Vec<f64> = (0..n).map(|i| rhs[c * n * bs + i * bs + q]).collect();
                    host.solve_in_place(&mut col, 1).unwrap();
                    for i in 0..n {
                        want[c * n * bs + i * bs + q] = col[i];
                    }
                }
            }
            let mut f = host.take_supernodal_factor().unwrap();
            f.invert_diagonal_blocks();
            let g = GpuFactor::upload(ctx, &f, crate::matrix::binding_limit(ctx)).unwrap();
            let kernels = SupernodalKernels::new(ctx, precision).unwrap();
            let b = precision.bytes();
            let r = ctx.storage("r", rhs.len() as u64 * b).unwrap();
            let z = ctx.storage("z", rhs.len() as u64 * b).unwrap();
            let per_slot = (bs * ncols) as u64 * b;
            let all = g.slots as u64 * per_slot;
            let one = SupernodalSteps::new(ctx, &kernels, &g, &r, &z, bs, ncols, all).unwrap();
            let limit = all / 5 / 4 * 4;
            let split = SupernodalSteps::new(ctx, &kernels, &g, &r, &z, bs, ncols, limit).unwrap();
            assert_eq!(one.update_buffers(), 1);
            assert!(split.update_buffers() >= 5, "{}", split.update_buffers());
            assert!(
                split.work(ncols).dispatches > one.work(ncols).dispatches,
                "{} {}",
                split.work(ncols).dispatches,
                one.work(ncols).dispatches
            );
            let z1 = apply(ctx, &one, &r, &z, &rhs, ncols, precision);
            let z2 = apply(ctx, &split, &r, &z, &rhs, ncols, precision);
            assert!(z1 == z2, "{precision:?}: split updates differ");
            let got = decode(precision, &z2);
            let err = got
                .iter()
                .zip(&want)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            let scale = want.iter().map(|v| v.abs()).fold(0.0, f64::max);
            let tol = match precision {
                Precision::F32 => 1e-5,
                Precision::F64 => 1e-12,
            };
            assert!(
                err <= tol * scale,
                "{precision:?}: {err:e} against {scale:e}"
            );
            // One supernode's updates over the binding are refused.
            assert!((0..f.len()).any(|s| f.shape(s).1 > 1));
            assert!(matches!(
                SupernodalSteps::new(ctx, &kernels, &g, &r, &z, bs, ncols, per_slot),
                Err(GpuError::LimitExceeded { .. })
            ));
        }
    }

    /// A second factor of the same analysis uploaded like the first (its
    /// index sections shared, over several value buffers too) holds the
    /// values a full upload of it holds, to the bit, and applies as it does;
    /// one of another structure is refused.
    #[test]
    fn a_factor_laid_out_like_another_is_its_full_upload() {
        let Some(s) = crate::test_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let k = grid(40, 30);
        let mut k2 = k.clone();
        for j in 0..k2.n {
            k2.values[k2.col_ptr[j]] += 0.5 + (j % 3) as f64;
        }
        for precision in precisions(ctx) {
            let mut first = host_factor(&k, precision);
            let mut second = first.numeric_twin(precision == Precision::F32).unwrap();
            second.prepare(&k2).unwrap();
            let mut f1 = first.take_supernodal_factor().unwrap();
            let mut f2 = second.take_supernodal_factor().unwrap();
            f1.invert_diagonal_blocks();
            f2.invert_diagonal_blocks();
            let b = precision.bytes();
            for limit in [crate::matrix::binding_limit(ctx), b * f1.nnz() as u64 / 3] {
                let g1 = GpuFactor::upload(ctx, &f1, limit).unwrap();
                let full = GpuFactor::upload(ctx, &f2, limit).unwrap();
                let like = GpuFactor::upload_like(ctx, &g1, &f2, limit).unwrap();
                assert_eq!(like.vals.len(), full.vals.len());
                assert!(limit > b * f1.nnz() as u64 || like.vals.len() > 1);
                assert!(like.idx == g1.idx, "{precision:?}: the index not shared");
                let read = |g: &GpuFactor| -> Vec<Vec<u8>> {
                    g.vals
                        .iter()
                        .map(|v| {
                            ctx.read::<u8>(v, v.size() as usize, &mut None, None)
                                .unwrap()
                        })
                        .collect()
                };
                assert!(read(&like) == read(&full), "{precision:?}: values differ");
                assert!(
                    read(&like) != read(&g1),
                    "{precision:?}: the first's values"
                );
            }
            // Another structure (another grid) is refused.
            let mut other = host_factor(&grid(30, 40), precision)
                .take_supernodal_factor()
                .unwrap();
            other.invert_diagonal_blocks();
            let g1 = GpuFactor::upload(ctx, &f1, crate::matrix::binding_limit(ctx)).unwrap();
            assert!(
                GpuFactor::upload_like(ctx, &g1, &other, crate::matrix::binding_limit(ctx))
                    .is_err()
            );
        }
    }

    /// Teams: one lane per dot product where a level's rows fill a wave of
    /// the GPU or are short, up to 64 where a few long rows would leave it
    /// idle.
    #[test]
    fn teams_are_sized_by_the_room_and_the_row() {
        assert_eq!(team(FILL, 2000, MAX_TEAM), 1);
        assert_eq!(team(4 * FILL, 2000, MAX_TEAM), 1);
        assert_eq!(team(1000, 2000, MAX_TEAM), 64);
        assert_eq!(team(1000, 2000, 8), 8);
        assert_eq!(team(1000, 40, MAX_TEAM), 4);
        assert_eq!(team(1000, 7, MAX_TEAM), 1);
        assert_eq!(team(FILL / 4, 2000, MAX_TEAM), 4);
        assert_eq!(team(0, 0, MAX_TEAM), 1);
        assert_eq!(team_steps(2000, 64), 32 + 6);
        assert_eq!(team_steps(2000, 1), 2000);
    }

    /// Dot products summed by teams of lanes give one lane's result up to
    /// rounding, and the chain of dependent steps through an application
    /// is several times shorter; a grid's top separators are what the teams
    /// take.
    #[test]
    fn teams_shorten_the_chain_and_keep_the_solve() {
        let Some(s) = crate::test_solver() else {
            return;
        };
        let ctx = &s.ctx;
        let k = grid(90, 80);
        let (bs, ncols) = (3, 1);
        for precision in precisions(ctx) {
            let mut f = host_factor(&k, precision).take_supernodal_factor().unwrap();
            f.invert_diagonal_blocks();
            let limit = crate::matrix::binding_limit(ctx);
            let g = GpuFactor::upload(ctx, &f, limit).unwrap();
            let kernels = SupernodalKernels::new(ctx, precision).unwrap();
            let b = precision.bytes();
            let len = k.n * bs * ncols;
            let r = ctx.storage("r", len as u64 * b).unwrap();
            let z = ctx.storage("z", len as u64 * b).unwrap();
            let build = |most| {
                SupernodalSteps::with_teams(ctx, &kernels, &g, (&r, &z), bs, ncols, limit, most)
                    .unwrap()
            };
            let (one, teams) = (build(1), build(MAX_TEAM));
            let most = teams
                .levels
                .iter()
                .flatten()
                .map(|p| p.teams[1])
                .max()
                .unwrap();
            assert!(most >= 8, "largest backward team {most}");
            assert!(one.levels.iter().flatten().all(|p| p.teams == [1, 1]));
            let (chain1, chain) = (one.serial_steps(), teams.serial_steps());
            assert!(2 * chain < chain1, "{chain} steps against {chain1}");
            let rhs: Vec<f64> = (0..len)
                .map(|i| ((i * 7919) % 1013) as f64 / 1013.0 - 0.5)
                .collect();
            let z1 = decode(precision, &apply(ctx, &one, &r, &z, &rhs, ncols, precision));
            let z2 = decode(
                precision,
                &apply(ctx, &teams, &r, &z, &rhs, ncols, precision),
            );
            assert!(z2.iter().all(|v| v.is_finite()));
            let err = z1
                .iter()
                .zip(&z2)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            let scale = z1.iter().map(|v| v.abs()).fold(0.0, f64::max);
            let tol = match precision {
                Precision::F32 => 1e-5,
                Precision::F64 => 1e-13,
            };
            assert!(
                err <= tol * scale,
                "{precision:?}: {err:e} against {scale:e}"
            );
            assert!(
                z1 != z2,
                "{precision:?}: the teams' sums are a lane's, to the bit"
            );
        }
    }

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
        let l = f.levels().unwrap();
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
