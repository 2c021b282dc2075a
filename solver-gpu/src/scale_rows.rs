//! Drives `shaders/scale_rows.wgsl`: `v = diag(m) v` per block row, in place,
//! the middle step of the squared-Laplacian preconditioner
//! `z = B^-1 Mt B^-1 r` ([`crate::Preconditioner::SquaredLaplacian`]).
//!
//! Bindings (group 0): 0 `P` uniform ([`ScaleParams`]: `n`, the column length,
//! and `bs`, unknowns per block row); 1 `m` (read, one f32 per block row);
//! 2 `v` (read-write, `NCOLS` columns of stride `n`). Dispatch: `ceil(n / 256)`
//! workgroups, 2-D.

use crate::device::{dispatch, Bind, Context, Kernel, KernelWork, Shader, FLAT_WG};
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/scale_rows.wgsl");

const BINDINGS: [(u32, Bind); 3] = [(0, Bind::Uniform), (1, Bind::Read), (2, Bind::ReadWrite)];

/// Parameters, as `ScaleParams` in `scale_rows.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ScaleParams {
    pub(crate) n: u32,
    pub(crate) bs: u32,
    pub(crate) pad: [u32; 2],
}

pub(crate) struct ScaleRows {
    shader: Shader,
    pub kernel: Kernel,
}

/// One recorded scaling of a vector buffer.
pub(crate) struct ScaleStep {
    bg: wgpu::BindGroup,
    /// Bytes of `m`, and of one column of `v`.
    bytes: (u64, u64),
    dims: (u32, u32),
    /// Kept alive for the bind group.
    #[allow(dead_code)]
    params: wgpu::Buffer,
}

impl ScaleRows {
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, "scale_rows.wgsl", SOURCE, &BINDINGS)?;
        Ok(ScaleRows {
            kernel: Kernel::new(&shader, "scale_rows", "scale_rows"),
            shader,
        })
    }

    /// The step scaling the columns of `v` (length `n` each, block rows of
    /// `bs`) by `m`.
    pub fn step(
        &self,
        ctx: &Context,
        m: &wgpu::Buffer,
        v: &wgpu::Buffer,
        n: usize,
        bs: usize,
    ) -> Result<ScaleStep, GpuError> {
        let params = ctx.uniform_of(
            "scale_rows params",
            &ScaleParams {
                n: n as u32,
                bs: bs as u32,
                pad: [0; 2],
            },
        )?;
        Ok(ScaleStep {
            bg: self.shader.bind(ctx, &[(0, &params), (1, m), (2, v)])?,
            bytes: (m.size(), 4 * n as u64),
            dims: ctx.dims("scale_rows", (n as u64).div_ceil(FLAT_WG as u64))?,
            params,
        })
    }
}

impl ScaleStep {
    /// Modelled work for `ncols` columns: `m` once, `v` read and written.
    pub fn work(&self, ncols: usize) -> KernelWork {
        let b = self.bytes.0 + 2 * self.bytes.1 * ncols as u64;
        KernelWork::operator(b, b)
    }

    pub fn record(&self, pass: &mut wgpu::ComputePass, pipeline: &wgpu::ComputePipeline) {
        dispatch(pass, pipeline, &self.bg, self.dims);
    }
}
