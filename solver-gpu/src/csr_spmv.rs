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

use crate::device::{Context, Kernel};
use crate::matrix::GpuMatrix;
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/csr_spmv.wgsl");

pub(crate) struct CsrSpmv(pub Kernel);

impl CsrSpmv {
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let m = ctx.shader("csr_spmv.wgsl", SOURCE)?;
        Ok(CsrSpmv(Kernel::new(ctx, "csr_spmv", &m, "main")?))
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
        self.0.bind(
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
