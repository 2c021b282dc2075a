//! Drives `shaders/supernodal.wgsl`: the shape systems' preconditioner
//! `z = (P^T L L^T P)^-1 r` for x, y and z of every PCG column
//! ([`crate::Preconditioner::Cholesky`]), with `L L^T = P K P^T` the
//! supernodal Cholesky factor of the matrix's isotropic part `K` (`K_ij =
//! tr(A_ij) / 3`, the held rows identity), as the CPU backend's block PCG
//! preconditions the same systems (`solver_cpu::pcg`).
//!
//! The factor is made on the host once per system kind per run (faer, nested
//! dissection from 50k vertices: a shallow elimination tree) and goes up once,
//! in f32. An application is `2 + 2 levels` dispatches, no host work and no
//! atomics (the same result on every run): gather
//! `w = P r`, the forward solve level by level of the supernodal elimination
//! tree (a level's supernodes are independent: one workgroup each), the
//! backward solve the other way, scatter `z = P^T w`.
//!
//! Bindings (group 0), as documented in the shader: 0 `P` uniform
//! ([`SnParams`], one per level), 1 `idx` (the index sections), 2 `vals`,
//! 3 `w` (read-write), 4 `r`, 5 `z` (read-write), 6 `contrib` (read-write).

use crate::device::{dispatch, Bind, Context, Kernel, KernelWork, Shader, FLAT_WG};
use crate::precision::Precision;
use crate::GpuError;
use solver_cpu::SupernodalFactor;
use std::sync::Arc;

pub(crate) const SOURCE: &str = include_str!("../../shaders/supernodal.wgsl");

const BINDINGS: [(u32, Bind); 7] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::ReadWrite),
    (4, Bind::Read),
    (5, Bind::ReadWrite),
    (6, Bind::ReadWrite),
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
    o_sn: u32,
    o_rows: u32,
    o_perm: u32,
    o_tptr: u32,
    o_tpos: u32,
    pad: [u32; 2],
}

/// The four entry points, in one precision.
pub(crate) struct SupernodalKernels {
    pub precision: Precision,
    shader: Shader,
    gather: Kernel,
    forward: Kernel,
    backward: Kernel,
    scatter: Kernel,
}

impl SupernodalKernels {
    pub fn new(ctx: &Context, precision: Precision) -> Result<Arc<Self>, GpuError> {
        let source = precision.source(SOURCE);
        let shader = Shader::new(ctx, "supernodal.wgsl", &source, &BINDINGS)?;
        Ok(Arc::new(SupernodalKernels {
            precision,
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
    idx: wgpu::Buffer,
    vals: wgpu::Buffer,
    /// Offsets of the sections of `idx`: supernode table, rows, permutation,
    /// row pointers and slots of the transposed row lists.
    offsets: [u32; 5],
    /// Slots of `rows` (one update per slot and column in `contrib`).
    slots: usize,
    /// `(first, count)` in `order` per level, leaves first.
    levels: Vec<(u32, u32)>,
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
        // One u32 buffer: order, supernode table, rows, perm, and the rows'
        // slots (a counting sort of `rows` by row).
        let n = f.perm.len();
        let nrows = f.rows.len();
        let total = ns + 5 * ns + nrows + n + (n + 1) + nrows;
        if total > u32::MAX as usize {
            return Err(GpuError::LimitExceeded {
                what: "a Cholesky factor's index sections (32-bit offsets)".into(),
                limit_name: "u32::MAX",
                needed: total as u64,
                limit: u32::MAX as u64,
            });
        }
        let mut idx = Vec::with_capacity(total);
        idx.extend_from_slice(&order);
        let o_sn = idx.len() as u32;
        for s in 0..ns {
            let (m, q) = f.shape(s);
            idx.extend_from_slice(&[
                f.begin[s],
                m as u32,
                q as u32,
                f.row_ptr[s],
                f.val_ptr[s] as u32,
            ]);
        }
        let o_rows = idx.len() as u32;
        idx.extend_from_slice(&f.rows);
        let o_perm = idx.len() as u32;
        idx.extend_from_slice(&f.perm);
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
        idx.resize(total, 0);
        let mut next = tptr;
        for (e, &r) in f.rows.iter().enumerate() {
            let at = next[r as usize] as usize;
            idx[o_tpos as usize + at] = e as u32;
            next[r as usize] += 1;
        }
        let precision = match f.values64.is_empty() {
            true => Precision::F32,
            false => Precision::F64,
        };
        let bytes = precision.bytes() * f.nnz() as u64 + 8 * nrows as u64;
        let vals = match precision {
            Precision::F32 => ctx.storage_init("Cholesky values (f32)", &f.values)?,
            Precision::F64 => ctx.storage_init("Cholesky values (f64)", &f.values64)?,
        };
        Ok(GpuFactor {
            idx: ctx.storage_init("Cholesky index sections", &idx)?,
            vals,
            precision,
            offsets: [o_sn, o_rows, o_perm, o_tptr, o_tpos],
            slots: nrows,
            levels,
            nv: f.perm.len(),
            nnz: f.nnz(),
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
    /// Kept alive for the bind groups.
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
        let w = ctx.storage(
            &format!("Cholesky work vector ({stride} x {cmax})"),
            (stride * cmax * b) as u64,
        )?;
        let contrib = ctx.storage(
            &format!("Cholesky updates ({} x {})", f.slots, bs * cmax),
            (f.slots * bs * cmax * b) as u64,
        )?;
        let [o_sn, o_rows, o_perm, o_tptr, o_tpos] = f.offsets;
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
                    o_sn,
                    o_rows,
                    o_perm,
                    o_tptr,
                    o_tpos,
                    pad: [0; 2],
                },
            )?;
            let bg = kernels.shader.bind(
                ctx,
                &[
                    (0, &p),
                    (1, &f.idx),
                    (2, &f.vals),
                    (3, &w),
                    (4, r),
                    (5, z),
                    (6, &contrib),
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
