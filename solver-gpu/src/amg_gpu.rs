//! Drives `shaders/amg.wgsl`: the SA-AMG V-cycle `z = M^-1 r` on the GPU (f32)
//! with the hierarchy built by [`crate::amg`] on the CPU.
//!
//! `GpuHierarchy` holds the uploaded levels (per level: `A_l`, `P_l`, `R_l` as
//! block-CSR with `bs` = 3 or 1, the inverted diagonal blocks; the dense inverse
//! of the coarsest matrix). A hierarchy with the same level patterns (aggregates
//! reused for a matrix of the same pattern) only rewrites the values. A scalar
//! hierarchy can also be uploaded to act on 3-vectors
//! (`GpuHierarchy::upload_on_3_vectors`: `A (x) I3` without storing the
//! blocks `v I3`), its matrices as CSR in storage buffers.
//!
//! `VcycleWorkspace` holds the per-level vectors (`b_l`, `x_l`, `t_l`, sized for
//! `cmax` columns; level 0 uses the PCG's `r` and `z`) and the V-cycle recorded
//! once as a list of dispatches, each with its own parameters and bind group
//! (the sequence is in the shader's header). Every dispatch is one invocation per
//! (block) row, 2-D.
//!
//! Bindings of `amg.wgsl` (group 0): 0 `P` uniform `AmgParams`; 1 `row_ptr`,
//! 2 `vals` (f32, the values of the step's matrix block after block, each
//! row-major; or the dense coarse inverse) and 8 `block_cols` (u32 per block):
//! the matrix of the step; 4 `x` (read); 5 `b` (read); 6 `y` (written);
//! 7 `dinv`. Every matrix lives in storage buffers split by block rows into
//! chunks that each fit one binding (`crate::matrix::split_rows`); a step
//! on a chunked matrix is one dispatch per chunk.

use crate::amg::{Bsr, Hierarchy, AFFINE_MODES};
use crate::device::{dispatch, Bind, Context, Kernel, KernelWork, Shader, ROW_WG};
use crate::matrix::{
    high_part, upload_chunks, write_chunk_values, Chunk, GpuMatrix, MatrixStorage, Values,
};
use crate::{GpuError, CMAX};

pub(crate) const SOURCE: &str = include_str!("../../shaders/amg.wgsl");

const BINDINGS: [(u32, Bind); 8] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (4, Bind::Read),
    (5, Bind::Read),
    (6, Bind::ReadWrite),
    (7, Bind::Read),
    (8, Bind::Read),
];

/// Parameters of one dispatch, as `AmgParams` in `amg.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct AmgParams {
    pub rows: u32,
    pub n: u32,
    pub nx: u32,
    pub groups: u32,
    pub mode: u32,
    pub omega: f32,
    /// First output row of the dispatch (a chunk's), and the chunk's first
    /// block.
    pub row0: u32,
    pub block0: u32,
}

pub(crate) struct AmgKernels {
    shader: Shader,
    /// Block layouts `bs` = 3, 1.
    spmv: [Kernel; 2],
    /// Diagonal blocks of 3, 1 and [`AFFINE_MODES`].
    jacobi: [Kernel; 3],
    /// `spmv_wide` for the block shapes of an affine hierarchy.
    wide: Vec<((usize, usize), Kernel)>,
    dense: Kernel,
    /// `spmv3`, `jacobi` and `dense` with `KRON` = 3: a scalar hierarchy on
    /// 3-vectors.
    on3: [Kernel; 3],
    /// The row scaling between the two `B^-1` of the squared-Laplacian
    /// preconditioner.
    pub scale: crate::scale_rows::ScaleRows,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Op {
    Spmv,
    SpmvWide,
    Jacobi,
    Dense,
    Spmv3,
    Jacobi3,
    Dense3,
}

impl AmgKernels {
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, "amg.wgsl", SOURCE, &BINDINGS)?;
        const K: usize = AFFINE_MODES;
        let k =
            |label, entry, bs: f64| Kernel::with_constants(&shader, label, entry, &[("BS", bs)]);
        Ok(AmgKernels {
            spmv: [
                k("amg_spmv_bs3", "spmv", 3.0),
                k("amg_spmv_bs1", "spmv", 1.0),
            ],
            jacobi: [
                k("amg_jacobi_bs3", "jacobi", 3.0),
                k("amg_jacobi_bs1", "jacobi", 1.0),
                k("amg_jacobi_bs12", "jacobi", AFFINE_MODES as f64),
            ],
            dense: k("amg_dense", "dense", 1.0),
            on3: [
                Kernel::new(&shader, "amg_spmv3", "spmv3"),
                Kernel::with_constants(
                    &shader,
                    "amg_jacobi_on3",
                    "jacobi",
                    &[("BS", 1.0), ("KRON", 3.0)],
                ),
                Kernel::with_constants(&shader, "amg_dense_on3", "dense", &[("KRON", 3.0)]),
            ],
            wide: [
                ((3, K), "amg_spmv_wide_3x12"),
                ((K, 3), "amg_spmv_wide_12x3"),
                ((K, K), "amg_spmv_wide_12x12"),
            ]
            .into_iter()
            .map(|((br, bc), label)| {
                let c = [("BR", br as f64), ("BC", bc as f64)];
                (
                    (br, bc),
                    Kernel::with_constants(&shader, label, "spmv_wide", &c),
                )
            })
            .collect(),
            scale: crate::scale_rows::ScaleRows::new(ctx)?,
            shader,
        })
    }

    /// The kernel of `op` for blocks of `shape` (the matrix's layout for the
    /// products, the diagonal blocks for `Jacobi`).
    fn kernel(&self, op: Op, shape: (usize, usize)) -> &Kernel {
        match (op, shape.0) {
            (Op::Spmv, 3) => &self.spmv[0],
            (Op::Spmv, _) => &self.spmv[1],
            (Op::SpmvWide, _) => {
                let w = self.wide.iter().find(|(s, _)| *s == shape);
                &w.expect("a wide-block kernel for every shape of an affine hierarchy")
                    .1
            }
            (Op::Jacobi, 3) => &self.jacobi[0],
            (Op::Jacobi, 1) => &self.jacobi[1],
            (Op::Jacobi, _) => &self.jacobi[2],
            (Op::Dense, _) => &self.dense,
            (Op::Spmv3, _) => &self.on3[0],
            (Op::Jacobi3, _) => &self.on3[1],
            (Op::Dense3, _) => &self.on3[2],
        }
    }
}

/// How a [`GpuBsr`] is stored, and which kernel reads it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Layout {
    /// `bs` x `bs` blocks (`bs` = 3 or 1), `bs * bs` f32 values and a u32
    /// column per block: `spmv`.
    Blocks(usize),
    /// `br` x `bc` blocks, `br * bc` f32 values and a u32 column per block:
    /// `spmv_wide`, one invocation per scalar row (the affine hierarchy's
    /// `P`, `R` and coarse `A`).
    Wide(usize, usize),
    /// A scalar matrix as CSR (a value and a column per entry), applied to
    /// interleaved 3-vectors: `spmv3`, one invocation per scalar row.
    Scalar3,
}

impl Layout {
    /// f32 values per stored block.
    fn per_block(self) -> usize {
        match self {
            Layout::Blocks(bs) => bs * bs,
            Layout::Wide(br, bc) => br * bc,
            Layout::Scalar3 => 1,
        }
    }

    /// Rows of its kernel's dispatch per block row.
    fn row_scale(self) -> usize {
        match self {
            Layout::Wide(br, _) => br,
            _ => 1,
        }
    }
}

/// One block-CSR matrix on the GPU: row pointers in a buffer, the blocks
/// (values and columns) in chunks of block rows that each fit one storage
/// binding.
struct GpuBsr {
    layout: Layout,
    row_ptr: wgpu::Buffer,
    chunks: Vec<Chunk>,
    /// The PCG's own matrix ([`GpuMatrix`], same layout), whose values are
    /// written with it.
    shared: bool,
    /// Bytes a product reads of it, as stored and in its least storage
    /// ([`KernelWork`]).
    stored: (u64, u64),
    /// Rows of its kernel's dispatch: block rows, scalar rows if wide.
    rows: usize,
}

fn f32s(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&a| a as f32).collect()
}

impl GpuBsr {
    /// Upload `m` in `layout` (`Blocks(m.bs)`, `Scalar3` for a scalar `m`,
    /// or `Wide` with shapes that divide `m`'s scalar rows and columns).
    fn upload(ctx: &Context, what: &str, m: &Bsr, layout: Layout) -> Result<GpuBsr, GpuError> {
        let what = format!("AMG {what} ({layout:?})");
        let wide = match layout {
            Layout::Wide(br, bc) => Some(m.regroup(br, bc)),
            Layout::Blocks(bs) => {
                debug_assert_eq!(bs, m.bs);
                None
            }
            Layout::Scalar3 => {
                debug_assert_eq!(m.bs, 1);
                None
            }
        };
        let (row_ptr, col_idx, vals, rows) = match &wide {
            Some(w) => (&w.row_ptr, &w.col_idx, &w.vals, w.rows),
            None => (&m.row_ptr, &m.col_idx, &m.vals, m.rows),
        };
        let per_block = layout.per_block();
        let chunks = upload_chunks(ctx, &what, row_ptr, col_idx, per_block, Values::Flat(vals))?;
        // Values and a u32 column per block, and the row pointers: the least.
        let least = (col_idx.len() * (4 * per_block + 4) + 4 * (rows + 1)) as u64;
        Ok(GpuBsr {
            layout,
            row_ptr: ctx.storage_init(&format!("{what} row pointers"), row_ptr)?,
            chunks,
            shared: false,
            stored: (least, least),
            rows: rows * layout.row_scale(),
        })
    }

    /// The PCG's block matrix as the finest `A` (no second copy on the GPU).
    fn shared(m: &GpuMatrix, rows: usize) -> Option<GpuBsr> {
        match &m.storage {
            MatrixStorage::Blocks { chunks, .. } => Some(GpuBsr {
                layout: Layout::Blocks(3),
                row_ptr: m.row_ptr.clone(),
                chunks: chunks.clone(),
                shared: true,
                stored: m.stored,
                rows,
            }),
            MatrixStorage::Csr { .. } | MatrixStorage::SplitBlocks { .. } => None,
        }
    }

    fn write(&self, ctx: &Context, m: &Bsr) {
        if self.shared {
            return;
        }
        let per_block = self.layout.per_block();
        match self.layout {
            Layout::Wide(br, bc) => {
                let w = m.regroup(br, bc);
                write_chunk_values(
                    ctx,
                    &self.chunks,
                    per_block,
                    Values::Flat(&w.vals),
                    high_part,
                );
            }
            _ => write_chunk_values(
                ctx,
                &self.chunks,
                per_block,
                Values::Flat(&m.vals),
                high_part,
            ),
        }
    }
}

struct GpuLevel {
    a: GpuBsr,
    p: GpuBsr,
    r: GpuBsr,
    /// `omega D^-1` (the smoother weight folded in).
    dinv: wgpu::Buffer,
    /// Size of the diagonal blocks of `dinv`.
    dinv_bs: usize,
}

fn scaled_dinv(lv: &crate::amg::Level) -> Vec<f32> {
    lv.dinv.iter().map(|&a| (lv.omega * a) as f32).collect()
}

/// The uploaded hierarchy.
pub(crate) struct GpuHierarchy {
    levels: Vec<GpuLevel>,
    coarse_inv: wgpu::Buffer,
    /// Unknowns per level, the coarsest last (3 per scalar row on 3-vectors).
    sizes: Vec<usize>,
    /// A scalar hierarchy on 3-vectors ([`Self::upload_on_3_vectors`]).
    on3: bool,
    sweeps: usize,
    dummy: wgpu::Buffer,
}

/// Whether two hierarchies have the same level patterns (values-only upload).
pub(crate) fn same_patterns(a: &Hierarchy, b: &Hierarchy) -> bool {
    a.bs == b.bs
        && a.affine == b.affine
        && a.opts.sweeps == b.opts.sweeps
        && a.levels.len() == b.levels.len()
        && a.coarse.rows == b.coarse.rows
        && a.levels.iter().zip(&b.levels).all(|(x, y)| {
            x.a.same_pattern(&y.a) && x.p.same_pattern(&y.p) && x.r.same_pattern(&y.r)
        })
}

impl GpuHierarchy {
    /// Upload `h`. `fine`: the PCG's matrix on the GPU, the same as the finest
    /// `A`; a block matrix is used in place of a second copy.
    pub fn upload(
        ctx: &Context,
        h: &Hierarchy,
        fine: Option<&GpuMatrix>,
    ) -> Result<GpuHierarchy, GpuError> {
        Self::upload_as(ctx, h, fine, false)
    }

    /// Upload the scalar (not affine) hierarchy `h` to act on interleaved
    /// 3-vectors: the V-cycle of `A (x) I3` (x, y and z of each row through
    /// the same cycle), each matrix as scalar CSR in storage buffers.
    pub fn upload_on_3_vectors(ctx: &Context, h: &Hierarchy) -> Result<GpuHierarchy, GpuError> {
        if h.bs != 1 || h.affine {
            return Err(GpuError::Backend(
                "a hierarchy on 3-vectors is built from a scalar matrix".into(),
            ));
        }
        Self::upload_as(ctx, h, None, true)
    }

    fn upload_as(
        ctx: &Context,
        h: &Hierarchy,
        fine: Option<&GpuMatrix>,
        on3: bool,
    ) -> Result<GpuHierarchy, GpuError> {
        let mut levels = Vec::with_capacity(h.levels.len());
        // An affine hierarchy: P, R and every A past the finest are wide.
        const K: usize = AFFINE_MODES;
        for (l, lv) in h.levels.iter().enumerate() {
            let shared = match fine {
                Some(m) if l == 0 && h.bs == 3 => GpuBsr::shared(m, lv.a.rows),
                _ => None,
            };
            let bs = lv.a.bs;
            let (al, pl, rl) = match h.affine {
                _ if on3 => (Layout::Scalar3, Layout::Scalar3, Layout::Scalar3),
                true if bs > 3 => (
                    Layout::Wide(bs, bs),
                    Layout::Wide(bs, K),
                    Layout::Wide(K, bs),
                ),
                true => (Layout::Blocks(bs), Layout::Wide(bs, K), Layout::Wide(K, bs)),
                false => (Layout::Blocks(bs), Layout::Blocks(bs), Layout::Blocks(bs)),
            };
            let a = match shared {
                Some(a) => a,
                None => GpuBsr::upload(ctx, &format!("A_{l}"), &lv.a, al)?,
            };
            levels.push(GpuLevel {
                a,
                p: GpuBsr::upload(ctx, &format!("P_{l}"), &lv.p, pl)?,
                r: GpuBsr::upload(ctx, &format!("R_{l}"), &lv.r, rl)?,
                dinv: ctx.storage_init(&format!("AMG w D_{l}^-1"), &scaled_dinv(lv))?,
                // On 3-vectors one diagonal value serves a row's 3 unknowns.
                dinv_bs: if on3 { 3 } else { bs },
            });
        }
        Ok(GpuHierarchy {
            levels,
            coarse_inv: ctx.storage_init("AMG coarsest inverse", &f32s(&h.coarse_inv))?,
            sizes: h
                .sizes()
                .iter()
                .map(|&n| if on3 { 3 * n } else { n })
                .collect(),
            on3,
            sweeps: h.opts.sweeps.max(1),
            dummy: ctx.storage("AMG unused binding", 16)?,
        })
    }

    /// New values, same patterns (checked by [`same_patterns`]); a finest `A`
    /// shared with the PCG's matrix has been written with that.
    pub fn write_values(&self, ctx: &Context, h: &Hierarchy) {
        for (g, lv) in self.levels.iter().zip(&h.levels) {
            g.a.write(ctx, &lv.a);
            g.p.write(ctx, &lv.p);
            g.r.write(ctx, &lv.r);
            ctx.write_buffer(&g.dinv, 0, bytemuck::cast_slice(&scaled_dinv(lv)));
        }
        ctx.write_buffer(
            &self.coarse_inv,
            0,
            bytemuck::cast_slice(&f32s(&h.coarse_inv)),
        );
    }

    /// The finest smoother's `omega D^-1` from new values of the PCG's matrix,
    /// whose inverted diagonal blocks are `minv`; the coarse levels keep the
    /// values they were built from (a fixed, still symmetric positive definite
    /// preconditioner for the new matrix). `omega`: the finest level's weight.
    pub fn write_fine_diagonal(&self, ctx: &Context, minv: &[f32], omega: f64) {
        if let Some(g) = self.levels.first() {
            let scaled: Vec<f32> = minv.iter().map(|&a| (omega * a as f64) as f32).collect();
            ctx.write_buffer(&g.dinv, 0, bytemuck::cast_slice(&scaled));
        }
    }

    /// Levels (the coarsest included).
    pub fn depth(&self) -> usize {
        self.sizes.len()
    }
}

/// One recorded dispatch of the V-cycle.
struct Step {
    op: Op,
    /// Block shape of the kernel ([`AmgKernels::kernel`]).
    shape: (usize, usize),
    bg: wgpu::BindGroup,
    dims: (u32, u32),
    /// Kept alive for the bind group.
    #[allow(dead_code)]
    params: wgpu::Buffer,
    /// Modelled bytes ([`KernelWork`]): of the matrix or diagonal, as stored
    /// and least; of the vectors, per column (f32).
    fixed: (u64, u64),
    per_column: u64,
}

/// Per-level vectors and the recorded V-cycle for up to `cmax` columns.
pub(crate) struct VcycleWorkspace {
    steps: Vec<Step>,
    /// Level vectors (kept alive for the bind groups; poisoned by tests).
    pub vectors: Vec<wgpu::Buffer>,
}

impl VcycleWorkspace {
    /// Record the V-cycle from `b0` (the PCG's `r`) into `x0` (its `z`).
    pub fn new(
        ctx: &Context,
        k: &AmgKernels,
        h: &GpuHierarchy,
        b0: &wgpu::Buffer,
        x0: &wgpu::Buffer,
        cmax: usize,
    ) -> Result<VcycleWorkspace, GpuError> {
        Self::record_cycle(ctx, k, h, b0, x0, cmax, false, None)
    }

    /// Record one more V-cycle on `A x0 = b0` from the `x0` that `before`
    /// (a V-cycle of the same hierarchy, run just before) left: a Richardson
    /// step `x0 += M^-1 (b0 - A x0)`. It shares `before`'s level vectors.
    pub fn continued(
        ctx: &Context,
        k: &AmgKernels,
        h: &GpuHierarchy,
        b0: &wgpu::Buffer,
        x0: &wgpu::Buffer,
        cmax: usize,
        before: &VcycleWorkspace,
    ) -> Result<VcycleWorkspace, GpuError> {
        Self::record_cycle(ctx, k, h, b0, x0, cmax, true, Some(before))
    }

    /// As [`Self::new`], on the level vectors of `other` (a V-cycle of the
    /// same hierarchy that never runs at the same time).
    pub fn sharing(
        ctx: &Context,
        k: &AmgKernels,
        h: &GpuHierarchy,
        b0: &wgpu::Buffer,
        x0: &wgpu::Buffer,
        cmax: usize,
        other: &VcycleWorkspace,
    ) -> Result<VcycleWorkspace, GpuError> {
        Self::record_cycle(ctx, k, h, b0, x0, cmax, false, Some(other))
    }

    /// Record one V-cycle from zero, or (`warm`) from the `x0` there is.
    #[allow(clippy::too_many_arguments)]
    fn record_cycle(
        ctx: &Context,
        k: &AmgKernels,
        h: &GpuHierarchy,
        b0: &wgpu::Buffer,
        x0: &wgpu::Buffer,
        cmax: usize,
        warm: bool,
        share: Option<&VcycleWorkspace>,
    ) -> Result<VcycleWorkspace, GpuError> {
        let cmax = cmax.clamp(1, CMAX);
        let nl = h.depth();
        let mut shared = share.map(|b| b.vectors.clone().into_iter());
        let mut vectors = Vec::new();
        let mut vec = |what: String, n: usize| -> Result<usize, GpuError> {
            let v = match shared.as_mut().and_then(|s| s.next()) {
                Some(v) => v,
                None => ctx.storage(&what, (n * cmax * 4) as u64)?,
            };
            vectors.push(v);
            Ok(vectors.len() - 1)
        };
        // Buffer slots per level: (b, x, t); level 0's b and x are the PCG's.
        let mut slots: Vec<(Option<usize>, Option<usize>, Option<usize>)> = Vec::new();
        for (l, &n) in h.sizes.iter().enumerate() {
            let what = |v: &str| format!("AMG level {l} vector {v} ({n} x {cmax} f32)");
            let b = if l == 0 {
                None
            } else {
                Some(vec(what("b"), n)?)
            };
            let x = if l == 0 {
                None
            } else {
                Some(vec(what("x"), n)?)
            };
            let t = if l + 1 < nl {
                Some(vec(what("t"), n)?)
            } else {
                None
            };
            slots.push((b, x, t));
        }
        let buf = |s: Option<usize>, level0: &'static str| -> &wgpu::Buffer {
            match s {
                Some(i) => &vectors[i],
                None if level0 == "b" => b0,
                None => x0,
            }
        };
        let mut steps = Vec::new();
        let mut step = |op: Op,
                        rows: usize,
                        n: usize,
                        nx: usize,
                        mode: u32,
                        omega: f32,
                        m: Option<&GpuBsr>,
                        vals: Option<&wgpu::Buffer>,
                        x: Option<&wgpu::Buffer>,
                        b: Option<&wgpu::Buffer>,
                        y: &wgpu::Buffer,
                        dinv: Option<&wgpu::Buffer>|
         -> Result<(), GpuError> {
            // Modelled bytes: the matrix (or diagonal, or dense inverse) once,
            // x, b, y once each per column as the mode reads and writes them
            // (all on the first dispatch of a chunked matrix).
            let fixed = match (m, dinv, vals) {
                (Some(m), Some(d), _) => (m.stored.0 + d.size(), m.stored.1 + d.size()),
                (Some(m), _, _) => m.stored,
                (None, Some(d), _) => (d.size(), d.size()),
                (None, None, Some(v)) => (v.size(), v.size()),
                _ => (0, 0),
            };
            let reads_y = (op == Op::Jacobi && mode == 1) || (op != Op::Jacobi && mode == 2);
            let reads_b = op != Op::Jacobi && (mode == 1 || mode == 3);
            let x_len = if op == Op::Jacobi { n } else { nx };
            let per_column =
                4 * (x_len + n + n * usize::from(reads_y) + n * usize::from(reads_b)) as u64;
            let (op, shape) = match (op, m.map(|m| m.layout)) {
                (Op::Spmv, Some(Layout::Scalar3)) => (Op::Spmv3, (1, 1)),
                (Op::Jacobi, _) if h.on3 => (Op::Jacobi3, (1, 1)),
                (Op::Dense, _) if h.on3 => (Op::Dense3, (1, 1)),
                (Op::Spmv, Some(Layout::Wide(br, bc))) => (Op::SpmvWide, (br, bc)),
                (Op::Spmv, Some(Layout::Blocks(bs))) => (op, (bs, bs)),
                (Op::Jacobi, _) => (op, (n / rows, n / rows)),
                _ => (op, (1, 1)),
            };
            // One dispatch per chunk of the matrix: (rows, first block, values,
            // columns); one over `rows` for a step without a matrix.
            let d = &h.dummy;
            let parts: Vec<(std::ops::Range<usize>, usize, &wgpu::Buffer, &wgpu::Buffer)> = match m
            {
                Some(m) => {
                    let sc = m.layout.row_scale();
                    m.chunks
                        .iter()
                        .map(|c| {
                            let r = c.rows.start * sc..c.rows.end * sc;
                            (r, c.blocks.start, &c.vals, &c.cols)
                        })
                        .collect()
                }
                None => vec![(0..rows, 0, vals.unwrap_or(d), d)],
            };
            for (i, (r, block0, vals, cols)) in parts.into_iter().enumerate() {
                let groups = (r.len() as u64).div_ceil(ROW_WG as u64).max(1);
                let params = ctx.uniform_of(
                    "AMG step params",
                    &AmgParams {
                        rows: r.end as u32,
                        n: n as u32,
                        nx: nx as u32,
                        groups: groups as u32,
                        mode,
                        omega,
                        row0: r.start as u32,
                        block0: block0 as u32,
                    },
                )?;
                let bg = k.shader.bind(
                    ctx,
                    &[
                        (0, &params),
                        (1, m.map_or(d, |m| &m.row_ptr)),
                        (2, vals),
                        (4, x.unwrap_or(d)),
                        (5, b.unwrap_or(d)),
                        (6, y),
                        (7, dinv.unwrap_or(d)),
                        (8, cols),
                    ],
                )?;
                let first = i == 0;
                steps.push(Step {
                    op,
                    shape,
                    bg,
                    fixed: if first { fixed } else { (0, 0) },
                    per_column: if first { per_column } else { 0 },
                    dims: ctx.dims("AMG kernels", groups)?,
                    params,
                });
            }
            Ok(())
        };
        // A level's smoothing sweep: fused (`spmv` mode 3, `u = v + w D^-1 (b -
        // A v)` into the other buffer) where the level's `A` is not wide,
        // else `spmv` mode 1 into the other buffer then `jacobi` mode 1 in
        // place. `v`: which of `bufs` holds the iterate; gives where it is now.
        let w = 1.0;
        macro_rules! sweep {
            ($lv:expr, $n:expr, $b:expr, $v:expr, $bufs:expr, $fused:expr) => {{
                let (lv, n, v, bufs): (&GpuLevel, usize, usize, [&wgpu::Buffer; 2]) =
                    ($lv, $n, $v, $bufs);
                let (cur, other) = (bufs[v], bufs[1 - v]);
                if $fused {
                    step(
                        Op::Spmv,
                        lv.a.rows,
                        n,
                        n,
                        3,
                        w,
                        Some(&lv.a),
                        None,
                        Some(cur),
                        Some($b),
                        other,
                        Some(&lv.dinv),
                    )?;
                    1 - v
                } else {
                    step(
                        Op::Spmv,
                        lv.a.rows,
                        n,
                        n,
                        1,
                        0.0,
                        Some(&lv.a),
                        None,
                        Some(cur),
                        Some($b),
                        other,
                        None,
                    )?;
                    step(
                        Op::Jacobi,
                        n / lv.dinv_bs,
                        n,
                        n,
                        1,
                        w,
                        None,
                        None,
                        None,
                        Some(other),
                        cur,
                        Some(&lv.dinv),
                    )?;
                    v
                }
            }};
        }
        let fusable = |lv: &GpuLevel| !matches!(lv.a.layout, Layout::Wide(..));
        // Per level, which of (x, t) holds the iterate after its down leg
        // (then after its up leg): 0 = x, 1 = t.
        let mut at = vec![0usize; nl];
        // Down.
        for (l, lv) in h.levels.iter().enumerate() {
            let n = h.sizes[l];
            let (b, x, t) = (
                buf(slots[l].0, "b"),
                buf(slots[l].1, "x"),
                buf(slots[l].2, "t"),
            );
            let bufs = [x, t];
            let fused = fusable(lv);
            let mut v = 0;
            if warm && l == 0 {
                // From the x0 left by the cycle before.
                v = sweep!(lv, n, b, v, bufs, fused);
            } else {
                step(
                    Op::Jacobi,
                    n / lv.dinv_bs,
                    n,
                    n,
                    0,
                    w,
                    None,
                    None,
                    None,
                    Some(b),
                    x,
                    Some(&lv.dinv),
                )?;
            }
            for _ in 1..h.sweeps {
                v = sweep!(lv, n, b, v, bufs, fused);
            }
            // The residual into the buffer not holding the iterate, restricted.
            step(
                Op::Spmv,
                lv.a.rows,
                n,
                n,
                1,
                0.0,
                Some(&lv.a),
                None,
                Some(bufs[v]),
                Some(b),
                bufs[1 - v],
                None,
            )?;
            let nc = h.sizes[l + 1];
            let bc = buf(slots[l + 1].0, "b");
            step(
                Op::Spmv,
                lv.r.rows,
                nc,
                n,
                0,
                0.0,
                Some(&lv.r),
                None,
                Some(bufs[1 - v]),
                None,
                bc,
                None,
            )?;
            at[l] = v;
        }
        // Coarsest.
        let lc = nl - 1;
        let nc = h.sizes[lc];
        let (bc, xc) = (buf(slots[lc].0, "b"), buf(slots[lc].1, "x"));
        step(
            Op::Dense,
            if h.on3 { nc / 3 } else { nc },
            nc,
            nc,
            0,
            0.0,
            None,
            Some(&h.coarse_inv),
            Some(bc),
            None,
            xc,
            None,
        )?;
        at[lc] = 0;
        // Up.
        for (l, lv) in h.levels.iter().enumerate().rev() {
            let n = h.sizes[l];
            let (b, x, t) = (
                buf(slots[l].0, "b"),
                buf(slots[l].1, "x"),
                buf(slots[l].2, "t"),
            );
            let bufs = [x, t];
            let coarse = match at[l + 1] {
                0 => buf(slots[l + 1].1, "x"),
                _ => buf(slots[l + 1].2, "t"),
            };
            let mut v = at[l];
            step(
                Op::Spmv,
                lv.p.rows,
                n,
                h.sizes[l + 1],
                2,
                0.0,
                Some(&lv.p),
                None,
                Some(coarse),
                None,
                bufs[v],
                None,
            )?;
            let fused = fusable(lv);
            // The finest level ends in x (the PCG's z): fused sweeps alternate
            // the buffers, so where their count would end in t the first
            // sweep is unfused, in place.
            let flips = fused && l == 0 && (v + h.sweeps) % 2 == 1;
            for k in 0..h.sweeps {
                v = sweep!(lv, n, b, v, bufs, fused && !(flips && k == 0));
            }
            debug_assert!(l > 0 || v == 0, "the finest level's iterate ends in x");
            at[l] = v;
        }
        Ok(VcycleWorkspace { steps, vectors })
    }

    /// The modelled work of one V-cycle for `ncols` columns ([`KernelWork`]).
    pub fn work(&self, ncols: usize) -> KernelWork {
        self.steps
            .iter()
            .map(|s| {
                let v = s.per_column * ncols as u64;
                KernelWork::operator(s.fixed.0 + v, s.fixed.1 + v)
            })
            .sum()
    }

    /// The pipelines of the recorded steps for `ncols` columns.
    pub fn pipelines(
        &self,
        ctx: &Context,
        k: &AmgKernels,
        ncols: usize,
    ) -> Result<Vec<wgpu::ComputePipeline>, GpuError> {
        self.steps
            .iter()
            .map(|s| k.kernel(s.op, s.shape).pipeline(ctx, ncols))
            .collect()
    }

    /// Record one V-cycle into `pass` (`pipelines` from [`Self::pipelines`]).
    pub fn record(&self, pass: &mut wgpu::ComputePass, pipelines: &[wgpu::ComputePipeline]) {
        for (s, p) in self.steps.iter().zip(pipelines) {
            dispatch(pass, p, &s.bg, s.dims);
        }
    }
}

/// The squared-Laplacian preconditioner `z = B^-1 Mt B^-1 r` as recorded
/// steps: the first V-cycle of `B` writes `t`, `t` is scaled by `Mt` in
/// place, the second V-cycle reads `t` and writes `z`.
pub(crate) struct SquaredSteps {
    /// The middle vector `t`.
    pub t: wgpu::Buffer,
    /// `vcycles` V-cycles on `B t = r` (the later ones continue the first).
    pub first: Vec<VcycleWorkspace>,
    pub scale: crate::scale_rows::ScaleStep,
    /// `vcycles` V-cycles on `B z = t`.
    pub second: Vec<VcycleWorkspace>,
}

impl SquaredSteps {
    /// Modelled work of one application for `ncols` columns.
    pub fn work(&self, ncols: usize) -> KernelWork {
        let cycles: KernelWork = self
            .first
            .iter()
            .chain(&self.second)
            .map(|c| c.work(ncols))
            .sum();
        cycles + self.scale.work(ncols)
    }

    /// Record for the PCG's `r` and `z` (f32, `n x cmax`); `mt`: one f32 per
    /// vertex (`h`: the hierarchy of `B` on 3-vectors); each `B^-1`
    /// [`crate::squared_laplacian_vcycles`] V-cycles for `B`'s rows.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        ctx: &Context,
        k: &AmgKernels,
        h: &GpuHierarchy,
        mt: &wgpu::Buffer,
        r: &wgpu::Buffer,
        z: &wgpu::Buffer,
        cmax: usize,
    ) -> Result<SquaredSteps, GpuError> {
        let n = h.sizes[0];
        let vcycles = crate::squared_laplacian_vcycles(if h.on3 { n / 3 } else { n });
        let bs = h.levels.first().map_or(1, |l| l.dinv_bs);
        let t = ctx.storage(
            &format!("squared-Laplacian middle vector ({n} x {cmax} f32)"),
            (n * cmax.clamp(1, CMAX) * 4) as u64,
        )?;
        // One set of level vectors for every cycle: they run one after another.
        let mut first = vec![VcycleWorkspace::new(ctx, k, h, r, &t, cmax)?];
        let mut second = vec![VcycleWorkspace::sharing(ctx, k, h, &t, z, cmax, &first[0])?];
        for _ in 1..vcycles.max(1) {
            first.push(VcycleWorkspace::continued(
                ctx, k, h, r, &t, cmax, &second[0],
            )?);
            second.push(VcycleWorkspace::continued(
                ctx, k, h, &t, z, cmax, &second[0],
            )?);
        }
        let scale = k.scale.step(ctx, mt, &t, n, bs)?;
        Ok(SquaredSteps {
            t,
            first,
            scale,
            second,
        })
    }
}
