//! Drives `shaders/bsr_spmv.wgsl`: `y = A x` for the full 3x3 block-CSR matrix
//! (f32) on up to [`crate::CMAX`] columns at once, with the per-workgroup partial
//! dot products `x . y` (the `p . Ap` of PCG) fused in.
//!
//! Bindings (group 0), as the shader's header describes:
//! - 0 `P` uniform [`Params`](crate::device::Params): rows = block rows, ncols,
//!   n = 3 rows, groups = ceil(rows / 128);
//! - 1 `row_ptr`, 2 `col_idx`, 3 `vals` (9 f32 per block): the matrix
//!   ([`GpuMatrix`]);
//! - 4 `x` (read), 5 `y` (written), column-major, stride n;
//! - 6 `partials` (written): `partials[c * groups + g]`.
//!
//! Dispatch: `groups` workgroups of 128 invocations, 2-D (see `Context::dims`).

use crate::device::{Context, Kernel};
use crate::matrix::GpuMatrix;
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/bsr_spmv.wgsl");

pub(crate) struct BsrSpmv(pub Kernel);

impl BsrSpmv {
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let m = ctx.shader("bsr_spmv.wgsl", SOURCE)?;
        Ok(BsrSpmv(Kernel::new(ctx, "bsr_spmv", &m, "main")?))
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
