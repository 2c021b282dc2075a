//! Drives `shaders/csr_spmv.wgsl`: `y = A x` for the full scalar CSR matrix of the
//! scale-factor system (f32), up to [`crate::CMAX`] columns at once, with the
//! per-workgroup partial dot products `x . y` fused in.
//!
//! Bindings (group 0), as the shader's header describes:
//! - 0 `P` uniform [`Params`](crate::device::Params): rows, ncols, n = rows,
//!   groups = ceil(rows / 128);
//! - 1 `row_ptr`, 2 `col_idx`, 3 `vals` (one f32 per entry): the matrix
//!   ([`GpuMatrix`] with block size 1);
//! - 4 `x` (read), 5 `y` (written), column-major, stride n;
//! - 6 `partials` (written): `partials[c * groups + g]`.
//!
//! Dispatch: `groups` workgroups of 128 invocations, 2-D (see `Context::dims`).

use crate::device::{Bind, Context, Kernel, Shader};
use crate::matrix::GpuMatrix;
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/csr_spmv.wgsl");

/// Layout of `csr_spmv.wgsl` (group 0).
const BINDINGS: [(u32, Bind); 7] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::Read),
    (4, Bind::Read),
    (5, Bind::ReadWrite),
    (6, Bind::ReadWrite),
];

pub(crate) struct CsrSpmv {
    shader: Shader,
    pub kernel: Kernel,
}

impl CsrSpmv {
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, "csr_spmv.wgsl", SOURCE, &BINDINGS)?;
        let kernel = Kernel::new(&shader, "csr_spmv", "main");
        Ok(CsrSpmv { shader, kernel })
    }

    pub fn bind(
        &self,
        ctx: &Context,
        params: &wgpu::Buffer,
        m: &GpuMatrix,
        x: &wgpu::Buffer,
        y: &wgpu::Buffer,
        partials: &wgpu::Buffer,
    ) -> Result<wgpu::BindGroup, GpuError> {
        self.shader.bind(
            ctx,
            &[
                (0, params),
                (1, &m.row_ptr),
                (2, &m.col_idx),
                (3, &m.vals),
                (4, x),
                (5, y),
                (6, partials),
            ],
        )
    }
}
