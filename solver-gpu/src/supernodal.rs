//! Drives `shaders/supernodal.wgsl`: the shape systems' preconditioner
//! `z = (P^T L L^T P)^-1 r` for x, y and z of every PCG column
//! ([`crate::Preconditioner::Cholesky`]), with `L L^T = P K P^T` the
//! supernodal Cholesky factor of the matrix's isotropic part `K` (`K_ij =
//! tr(A_ij) / 3`, the held rows identity), as the CPU backend's block PCG
//! preconditions the same systems (`solver_cpu::pcg`).
//!
//! The factor is made on the host once per system kind per run (faer, nested
//! dissection from 50k vertices: a shallow elimination tree) and goes up once,
//! in f32. An application is `2 + 2 levels` dispatches, no host work: gather
//! `w = P r`, the forward solve level by level of the supernodal elimination
//! tree (a level's supernodes are independent: one workgroup each), the
//! backward solve the other way, scatter `z = P^T w`.
//!
//! Bindings (group 0), as documented in the shader: 0 `P` uniform
//! ([`SnParams`], one per level), 1 `order`, 2 `sn`, 3 `rows`, 4 `vals`,
//! 5 `perm`, 6 `w` (read-write), 7 `r`, 8 `z` (read-write).

use crate::device::{dispatch, Bind, Context, Kernel, KernelWork, Shader, FLAT_WG};
use crate::GpuError;
use solver_cpu::SupernodalFactor;
use std::sync::Arc;

pub(crate) const SOURCE: &str = include_str!("../../shaders/supernodal.wgsl");

const BINDINGS: [(u32, Bind); 9] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::Read),
    (4, Bind::Read),
    (5, Bind::Read),
    (6, Bind::ReadWrite),
    (7, Bind::Read),
    (8, Bind::ReadWrite),
];

/// Parameters, as `Params` in `supernodal.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
struct SnParams {
    first: u32,
    count: u32,
    nv: u32,
    stride: u32,
    bs: u32,
    pad: [u32; 3],
}

/// The four entry points.
pub(crate) struct SupernodalKernels {
    shader: Shader,
    gather: Kernel,
    forward: Kernel,
    backward: Kernel,
    scatter: Kernel,
}

impl SupernodalKernels {
    pub fn new(ctx: &Context) -> Result<Arc<Self>, GpuError> {
        let shader = Shader::new(ctx, "supernodal.wgsl", SOURCE, &BINDINGS)?;
        Ok(Arc::new(SupernodalKernels {
            gather: Kernel::new(&shader, "supernodal gather", "gather"),
            forward: Kernel::new(&shader, "supernodal forward", "forward"),
            backward: Kernel::new(&shader, "supernodal backward", "backward"),
            scatter: Kernel::new(&shader, "supernodal scatter", "scatter"),
            shader,
        }))
    }
}

/// A supernodal factor on the GPU, with its level schedule.
pub(crate) struct GpuFactor {
    order: wgpu::Buffer,
    sn: wgpu::Buffer,
    rows: wgpu::Buffer,
    vals: wgpu::Buffer,
    perm: wgpu::Buffer,
    /// `(first, count)` in `order` per level, leaves first.
    levels: Vec<(u32, u32)>,
    /// Rows of `K`.
    pub nv: usize,
    /// Stored values of the factor.
    pub nnz: usize,
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
    /// Upload `f` (values in f32, indices in u32).
    pub fn upload(ctx: &Context, f: &SupernodalFactor) -> Result<GpuFactor, GpuError> {
        let ns = f.len();
        let bad = |what: &str| GpuError::Backend(format!("supernodal factor: {what}"));
        let level = levels(f).ok_or_else(|| bad("supernodes out of topological order"))?;
        if f.values.len() > u32::MAX as usize {
            return Err(GpuError::LimitExceeded {
                what: "a Cholesky factor's values (32-bit offsets)".into(),
                limit_name: "u32::MAX",
                needed: f.values.len() as u64,
                limit: u32::MAX as u64,
            });
        }
        let depth = level.iter().max().map_or(0, |&l| l as usize + 1);
        let mut count = vec![0u32; depth];
        for &l in &level {
            count[l as usize] += 1;
        }
        let mut levels = Vec::with_capacity(depth);
        let mut first = 0u32;
        for &c in &count {
            levels.push((first, c));
            first += c;
        }
        let mut next: Vec<u32> = levels.iter().map(|l| l.0).collect();
        let mut order = vec![0u32; ns];
        for (s, &l) in level.iter().enumerate() {
            order[next[l as usize] as usize] = s as u32;
            next[l as usize] += 1;
        }
        let mut sn = Vec::with_capacity(5 * ns);
        for s in 0..ns {
            let (m, q) = f.shape(s);
            sn.extend_from_slice(&[
                f.begin[s],
                m as u32,
                q as u32,
                f.row_ptr[s],
                f.val_ptr[s] as u32,
            ]);
        }
        let bytes = 4 * (f.values.len() + f.rows.len()) as u64;
        Ok(GpuFactor {
            order: ctx.storage_init("Cholesky supernodes by level", &order)?,
            sn: ctx.storage_init("Cholesky supernodes", &sn)?,
            rows: ctx.storage_init("Cholesky rows", &f.rows)?,
            vals: ctx.storage_init("Cholesky values (f32)", &f.values)?,
            perm: ctx.storage_init("Cholesky permutation", &f.perm)?,
            levels,
            nv: f.perm.len(),
            nnz: f.values.len(),
            bytes,
        })
    }

    /// Levels of the elimination tree (dispatches per triangular solve).
    pub fn depth(&self) -> usize {
        self.levels.len()
    }
}

/// One recorded application `z = M^-1 r` for a workspace's `r` and `z`.
pub(crate) struct SupernodalSteps {
    kernels: Arc<SupernodalKernels>,
    /// One bind group per level (each with its own parameters).
    groups: Vec<(wgpu::BindGroup, (u32, u32))>,
    flat: (u32, u32),
    w: wgpu::Buffer,
    #[allow(dead_code)]
    params: Vec<wgpu::Buffer>,
    /// Factor bytes, and bytes of one PCG column.
    bytes: (u64, u64),
}

impl SupernodalSteps {
    /// The steps for `r` and `z` (f32, columns of `stride = nv * bs`, up to
    /// `cmax` of them).
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
        let w = ctx.storage(
            &format!("Cholesky work vector ({} x {cmax} f32)", stride),
            (stride * cmax * 4) as u64,
        )?;
        let mut params = Vec::with_capacity(f.levels.len().max(1));
        let mut groups = Vec::with_capacity(params.capacity());
        let levels: Vec<(u32, u32)> = if f.levels.is_empty() {
            vec![(0, 0)]
        } else {
            f.levels.clone()
        };
        for (first, count) in levels {
            let p = ctx.uniform_of(
                "supernodal params",
                &SnParams {
                    first,
                    count,
                    nv: f.nv as u32,
                    stride: stride as u32,
                    bs: bs as u32,
                    pad: [0; 3],
                },
            )?;
            let bg = kernels.shader.bind(
                ctx,
                &[
                    (0, &p),
                    (1, &f.order),
                    (2, &f.sn),
                    (3, &f.rows),
                    (4, &f.vals),
                    (5, &f.perm),
                    (6, &w),
                    (7, r),
                    (8, z),
                ],
            )?;
            groups.push((bg, ctx.dims("supernodal level", count as u64)?));
            params.push(p);
        }
        let flat = ctx.dims(
            "supernodal gather",
            ((stride * cmax) as u64).div_ceil(FLAT_WG as u64),
        )?;
        Ok(SupernodalSteps {
            kernels: kernels.clone(),
            groups,
            flat,
            w,
            params,
            bytes: (f.bytes, 4 * stride as u64),
        })
    }

    /// The work vector (tests poison it).
    #[allow(dead_code)]
    pub fn work_vector(&self) -> &wgpu::Buffer {
        &self.w
    }

    /// Pipelines for `ncols` PCG columns: gather, forward, backward, scatter.
    pub fn pipelines(
        &self,
        ctx: &Context,
        ncols: usize,
    ) -> Result<[wgpu::ComputePipeline; 4], GpuError> {
        let k = &self.kernels;
        Ok([
            k.gather.pipeline(ctx, ncols)?,
            k.forward.pipeline(ctx, ncols)?,
            k.backward.pipeline(ctx, ncols)?,
            k.scatter.pipeline(ctx, ncols)?,
        ])
    }

    /// Modelled work of one application for `ncols` columns: the factor read
    /// twice (an operator application each way), `w` read and written about
    /// twice per sweep, `r` read and `z` written once.
    pub fn work(&self, ncols: usize) -> KernelWork {
        let col = self.bytes.1 * ncols as u64;
        let sweep = KernelWork::operator(self.bytes.0 + 2 * col, self.bytes.0 + 2 * col);
        let levels = self.groups.len() as u64;
        KernelWork {
            dispatches: 2 + 2 * levels,
            ..sweep.times(2) + KernelWork::other(2 * col).times(2)
        }
    }

    /// Record one application into `pass`.
    pub fn record(&self, pass: &mut wgpu::ComputePass, p: &[wgpu::ComputePipeline; 4]) {
        let bg0 = &self.groups[0].0;
        dispatch(pass, &p[0], bg0, self.flat);
        for (bg, dims) in &self.groups {
            dispatch(pass, &p[1], bg, *dims);
        }
        for (bg, dims) in self.groups.iter().rev() {
            dispatch(pass, &p[2], bg, *dims);
        }
        dispatch(pass, &p[3], bg0, self.flat);
    }
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
        let f = c.supernodal_factor().unwrap();
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
