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

use crate::device::{Bind, Context, Kernel, Shader};
use crate::matrix::GpuMatrix;
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/bsr_spmv.wgsl");

/// Layout of `bsr_spmv.wgsl` and `csr_spmv.wgsl` (group 0): the same bindings.
const BINDINGS: [(u32, Bind); 7] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::Read),
    (4, Bind::Read),
    (5, Bind::ReadWrite),
    (6, Bind::ReadWrite),
];

/// A compiled SpMV shader (block or scalar: both share the bindings above).
pub(crate) struct SpmvKernel {
    shader: Shader,
    pub kernel: Kernel,
}

pub(crate) type BsrSpmv = SpmvKernel;

/// Compile `bsr_spmv.wgsl`.
pub(crate) fn new(ctx: &Context) -> Result<BsrSpmv, GpuError> {
    SpmvKernel::load(ctx, "bsr_spmv.wgsl", SOURCE, "bsr_spmv")
}

impl SpmvKernel {
    pub(crate) fn load(
        ctx: &Context,
        file: &'static str,
        source: &'static str,
        label: &'static str,
    ) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, file, source, &BINDINGS)?;
        let kernel = Kernel::new(&shader, label, "main");
        Ok(SpmvKernel { shader, kernel })
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
