//! Drives `shaders/amg.wgsl`: the SA-AMG V-cycle `z = M^-1 r` on the GPU (f32)
//! with the hierarchy built by [`crate::amg`] on the CPU.
//!
//! [`GpuHierarchy`] holds the uploaded levels (per level: `A_l`, `P_l`, `R_l` as
//! block-CSR with `bs` = 3 or 1, the inverted diagonal blocks; the dense inverse
//! of the coarsest matrix). A hierarchy with the same level patterns (aggregates
//! reused for a matrix of the same pattern) only rewrites the values.
//!
//! [`VcycleWorkspace`] holds the per-level vectors (`b_l`, `x_l`, `t_l`, sized for
//! `cmax` columns; level 0 uses the PCG's `r` and `z`) and the V-cycle recorded
//! once as a list of dispatches, each with its own parameters and bind group
//! (the sequence is in the shader's header). Every dispatch is one invocation per
//! (block) row, 2-D.
//!
//! Bindings of `amg.wgsl` (group 0): 0 `P` uniform [`AmgParams`]; 1 `row_ptr`
//! and 3 `blocks` (RGBA32F texture, `bs` texels per block, the layout of
//! [`crate::matrix::block_texel`]): the matrix of the step; 2 `dense_inv` (the
//! dense coarse inverse); 4 `x` (read); 5 `b` (read); 6 `y` (written); 7 `dinv`.

use crate::amg::{Bsr, Hierarchy};
use crate::device::{dispatch, Bind, Context, Kernel, Shader, ROW_WG};
use crate::matrix::{block_texel, check_texture_columns, GpuMatrix, MatrixStorage};
use crate::{GpuError, CMAX};

pub(crate) const SOURCE: &str = include_str!("../../shaders/amg.wgsl");

const BINDINGS: [(u32, Bind); 8] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::Texture),
    (4, Bind::Read),
    (5, Bind::Read),
    (6, Bind::ReadWrite),
    (7, Bind::Read),
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
    pub pad: [u32; 2],
}

pub(crate) struct AmgKernels {
    shader: Shader,
    spmv: [Kernel; 2],
    jacobi: [Kernel; 2],
    dense: Kernel,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Op {
    Spmv,
    Jacobi,
    Dense,
}

impl AmgKernels {
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, "amg.wgsl", SOURCE, &BINDINGS)?;
        let tw = ctx.texture_width() as f64;
        let k = |label, entry, bs: f64| {
            Kernel::with_constants(&shader, label, entry, &[("BS", bs), ("TW", tw)])
        };
        Ok(AmgKernels {
            spmv: [
                k("amg_spmv_bs3", "spmv", 3.0),
                k("amg_spmv_bs1", "spmv", 1.0),
            ],
            jacobi: [
                k("amg_jacobi_bs3", "jacobi", 3.0),
                k("amg_jacobi_bs1", "jacobi", 1.0),
            ],
            dense: k("amg_dense", "dense", 1.0),
            shader,
        })
    }

    fn kernel(&self, op: Op, bs: usize) -> &Kernel {
        let i = usize::from(bs != 3);
        match op {
            Op::Spmv => &self.spmv[i],
            Op::Jacobi => &self.jacobi[i],
            Op::Dense => &self.dense,
        }
    }
}

/// One block-CSR matrix on the GPU: row pointers in a buffer, blocks (f32) and
/// block columns in a texture.
struct GpuBsr {
    row_ptr: wgpu::Buffer,
    /// `None`: the PCG's own matrix ([`GpuMatrix`], same layout), whose values
    /// are written with it.
    texture: Option<wgpu::Texture>,
    view: wgpu::TextureView,
    rows: usize,
}

fn f32s(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&a| a as f32).collect()
}

impl GpuBsr {
    fn upload(ctx: &Context, what: &str, m: &Bsr) -> Result<GpuBsr, GpuError> {
        check_texture_columns(&format!("AMG {what}"), m.cols)?;
        let texels = m.bs * m.nnz_blocks();
        let texture = ctx.data_texture(
            &format!("AMG {what} ({} blocks of {} texels)", m.nnz_blocks(), m.bs),
            texels as u64,
            false,
        )?;
        let g = GpuBsr {
            row_ptr: ctx.storage_init(&format!("AMG {what} row pointers"), &m.row_ptr)?,
            view: texture.create_view(&Default::default()),
            texture: Some(texture),
            rows: m.rows,
        };
        g.write(ctx, m);
        Ok(g)
    }

    /// The PCG's block matrix as the finest `A` (no second copy on the GPU).
    fn shared(m: &GpuMatrix, rows: usize) -> Option<GpuBsr> {
        match &m.storage {
            MatrixStorage::BlockTexture { view, .. } => Some(GpuBsr {
                row_ptr: m.row_ptr.clone(),
                texture: None,
                view: view.clone(),
                rows,
            }),
            MatrixStorage::Csr { .. } => None,
        }
    }

    fn write(&self, ctx: &Context, m: &Bsr) {
        if let Some(t) = &self.texture {
            ctx.write_data_texture(t, m.bs * m.nnz_blocks(), |t, out| {
                block_texel(m.bs, &m.col_idx, &m.vals, t, out)
            });
        }
    }
}

struct GpuLevel {
    a: GpuBsr,
    p: GpuBsr,
    r: GpuBsr,
    /// `omega D^-1` (the smoother weight folded in).
    dinv: wgpu::Buffer,
}

fn scaled_dinv(lv: &crate::amg::Level) -> Vec<f32> {
    lv.dinv.iter().map(|&a| (lv.omega * a) as f32).collect()
}

/// The uploaded hierarchy.
pub(crate) struct GpuHierarchy {
    bs: usize,
    levels: Vec<GpuLevel>,
    coarse_inv: wgpu::Buffer,
    /// Unknowns per level, the coarsest last.
    sizes: Vec<usize>,
    sweeps: usize,
    dummy: wgpu::Buffer,
    #[allow(dead_code)]
    dummy_texture: wgpu::Texture,
    dummy_view: wgpu::TextureView,
}

/// Whether two hierarchies have the same level patterns (values-only upload).
pub(crate) fn same_patterns(a: &Hierarchy, b: &Hierarchy) -> bool {
    a.bs == b.bs
        && a.opts.sweeps == b.opts.sweeps
        && a.levels.len() == b.levels.len()
        && a.coarse.rows == b.coarse.rows
        && a.levels.iter().zip(&b.levels).all(|(x, y)| {
            x.a.same_pattern(&y.a) && x.p.same_pattern(&y.p) && x.r.same_pattern(&y.r)
        })
}

impl GpuHierarchy {
    /// Upload `h`. `fine`: the PCG's matrix on the GPU, the same as the finest
    /// `A`; a block matrix (texture) is used in place of a second copy.
    pub fn upload(
        ctx: &Context,
        h: &Hierarchy,
        fine: Option<&GpuMatrix>,
    ) -> Result<GpuHierarchy, GpuError> {
        let mut levels = Vec::with_capacity(h.levels.len());
        for (l, lv) in h.levels.iter().enumerate() {
            let shared = match fine {
                Some(m) if l == 0 && h.bs == 3 => GpuBsr::shared(m, lv.a.rows),
                _ => None,
            };
            let a = match shared {
                Some(a) => a,
                None => GpuBsr::upload(ctx, &format!("A_{l}"), &lv.a)?,
            };
            levels.push(GpuLevel {
                a,
                p: GpuBsr::upload(ctx, &format!("P_{l}"), &lv.p)?,
                r: GpuBsr::upload(ctx, &format!("R_{l}"), &lv.r)?,
                dinv: ctx.storage_init(&format!("AMG w D_{l}^-1"), &scaled_dinv(lv))?,
            });
        }
        let dummy_texture = ctx.data_texture("AMG unused texture binding", 1, false)?;
        Ok(GpuHierarchy {
            bs: h.bs,
            levels,
            coarse_inv: ctx.storage_init("AMG coarsest inverse", &f32s(&h.coarse_inv))?,
            sizes: h.sizes(),
            sweeps: h.opts.sweeps.max(1),
            dummy: ctx.storage("AMG unused binding", 16)?,
            dummy_view: dummy_texture.create_view(&Default::default()),
            dummy_texture,
        })
    }

    /// New values, same patterns (checked by [`same_patterns`]); a finest `A`
    /// shared with the PCG's matrix has been written with that.
    pub fn write_values(&self, ctx: &Context, h: &Hierarchy) {
        for (g, lv) in self.levels.iter().zip(&h.levels) {
            g.a.write(ctx, &lv.a);
            g.p.write(ctx, &lv.p);
            g.r.write(ctx, &lv.r);
            ctx.queue
                .write_buffer(&g.dinv, 0, bytemuck::cast_slice(&scaled_dinv(lv)));
        }
        ctx.queue.write_buffer(
            &self.coarse_inv,
            0,
            bytemuck::cast_slice(&f32s(&h.coarse_inv)),
        );
    }

    /// Levels (the coarsest included).
    pub fn depth(&self) -> usize {
        self.sizes.len()
    }
}

/// One recorded dispatch of the V-cycle.
struct Step {
    op: Op,
    bg: wgpu::BindGroup,
    dims: (u32, u32),
    /// Kept alive for the bind group.
    #[allow(dead_code)]
    params: wgpu::Buffer,
}

/// Per-level vectors and the recorded V-cycle for up to `cmax` columns.
pub(crate) struct VcycleWorkspace {
    bs: usize,
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
        let cmax = cmax.clamp(1, CMAX);
        let bs = h.bs;
        let nl = h.depth();
        let mut vectors = Vec::new();
        let mut vec = |what: String, n: usize| -> Result<usize, GpuError> {
            vectors.push(ctx.storage(&what, (n * cmax * 4) as u64)?);
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
            let groups = (rows as u64).div_ceil(ROW_WG as u64).max(1);
            let params = ctx.uniform_of(
                "AMG step params",
                &AmgParams {
                    rows: rows as u32,
                    n: n as u32,
                    nx: nx as u32,
                    groups: groups as u32,
                    mode,
                    omega,
                    pad: [0; 2],
                },
            )?;
            let d = &h.dummy;
            let bg = k.shader.bind_with_views(
                ctx,
                &[
                    (0, &params),
                    (1, m.map_or(d, |m| &m.row_ptr)),
                    (2, vals.unwrap_or(d)),
                    (4, x.unwrap_or(d)),
                    (5, b.unwrap_or(d)),
                    (6, y),
                    (7, dinv.unwrap_or(d)),
                ],
                &[(3, m.map_or(&h.dummy_view, |m| &m.view))],
            )?;
            steps.push(Step {
                op,
                bg,
                dims: ctx.dims("AMG kernels", groups)?,
                params,
            });
            Ok(())
        };
        // Down.
        for (l, lv) in h.levels.iter().enumerate() {
            let n = h.sizes[l];
            let rows = lv.a.rows;
            let (b, x, t) = (
                buf(slots[l].0, "b"),
                buf(slots[l].1, "x"),
                buf(slots[l].2, "t"),
            );
            let w = 1.0;
            step(
                Op::Jacobi,
                rows,
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
            for _ in 1..h.sweeps {
                step(
                    Op::Spmv,
                    rows,
                    n,
                    n,
                    1,
                    0.0,
                    Some(&lv.a),
                    None,
                    Some(x),
                    Some(b),
                    t,
                    None,
                )?;
                step(
                    Op::Jacobi,
                    rows,
                    n,
                    n,
                    1,
                    w,
                    None,
                    None,
                    None,
                    Some(t),
                    x,
                    Some(&lv.dinv),
                )?;
            }
            step(
                Op::Spmv,
                rows,
                n,
                n,
                1,
                0.0,
                Some(&lv.a),
                None,
                Some(x),
                Some(b),
                t,
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
                Some(t),
                None,
                bc,
                None,
            )?;
        }
        // Coarsest.
        let lc = nl - 1;
        let nc = h.sizes[lc];
        let (bc, xc) = (buf(slots[lc].0, "b"), buf(slots[lc].1, "x"));
        step(
            Op::Dense,
            nc,
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
        // Up.
        for (l, lv) in h.levels.iter().enumerate().rev() {
            let n = h.sizes[l];
            let rows = lv.a.rows;
            let (b, x, t) = (
                buf(slots[l].0, "b"),
                buf(slots[l].1, "x"),
                buf(slots[l].2, "t"),
            );
            let xc = buf(slots[l + 1].1, "x");
            let nc = h.sizes[l + 1];
            step(
                Op::Spmv,
                lv.p.rows,
                n,
                nc,
                2,
                0.0,
                Some(&lv.p),
                None,
                Some(xc),
                None,
                x,
                None,
            )?;
            let w = 1.0;
            for _ in 0..h.sweeps {
                step(
                    Op::Spmv,
                    rows,
                    n,
                    n,
                    1,
                    0.0,
                    Some(&lv.a),
                    None,
                    Some(x),
                    Some(b),
                    t,
                    None,
                )?;
                step(
                    Op::Jacobi,
                    rows,
                    n,
                    n,
                    1,
                    w,
                    None,
                    None,
                    None,
                    Some(t),
                    x,
                    Some(&lv.dinv),
                )?;
            }
        }
        Ok(VcycleWorkspace { bs, steps, vectors })
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
            .map(|s| k.kernel(s.op, self.bs).pipeline(ctx, ncols))
            .collect()
    }

    /// Record one V-cycle into `pass` (`pipelines` from [`Self::pipelines`]).
    pub fn record(&self, pass: &mut wgpu::ComputePass, pipelines: &[wgpu::ComputePipeline]) {
        for (s, p) in self.steps.iter().zip(pipelines) {
            dispatch(pass, p, &s.bg, s.dims);
        }
    }
}
