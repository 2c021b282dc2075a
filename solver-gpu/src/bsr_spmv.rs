//! Drives `shaders/bsr_spmv.wgsl`: `y = A x` for the full 3x3 block-CSR matrix
//! (f32) on up to [`crate::CMAX`] columns at once, with the per-workgroup partial
//! dot products `x . y` (the `p . Ap` of PCG) fused in.
//!
//! Bindings (group 0), as the shader's header describes:
//! - 0 `P` uniform [`Params`](crate::device::Params): rows = block rows, ncols,
//!   n = 3 rows, groups = ceil(rows / 128);
//! - 1 `row_ptr` (buffer) and 3 `blocks` (RGBA32F texture, three texels per
//!   block holding its 9 values and its column): the matrix ([`GpuMatrix`]);
//! - 4 `x` (RGBA32F texture: column c, vertex j at texel `c rows + j`, written
//!   by `pcg.wgsl`'s `direction_tex`), 5 `y` (written, column-major, stride n);
//! - 6 `partials` (written): `partials[c * groups + g]`.
//!
//! Dispatch: `groups` workgroups of 128 invocations, 2-D (see `Context::dims`).
//!
//! Also drives `shaders/bsr_spmv_f64.wgsl` ([`new_f64`]), the f64 product of
//! the mixed-precision solve: the same blocks as high (the f32 texture) and low
//! f32 parts, `x`, `y` and the partials in f64 buffers (bindings 2 `lo`, 3 `hi`,
//! 4 `x`; the rest as above).

use crate::device::{Bind, Context, Kernel, Shader};
use crate::matrix::{GpuMatrix, MatrixStorage};
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/bsr_spmv.wgsl");
pub(crate) const F64_SOURCE: &str = include_str!("../../shaders/bsr_spmv_f64.wgsl");

/// Layout of `bsr_spmv_f64.wgsl` (group 0).
const BLOCK_F64_BINDINGS: [(u32, Bind); 7] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Texture),
    (3, Bind::Texture),
    (4, Bind::Read),
    (5, Bind::ReadWrite),
    (6, Bind::ReadWrite),
];

/// Layout of `bsr_spmv.wgsl` (group 0).
const BLOCK_BINDINGS: [(u32, Bind); 6] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (3, Bind::Texture),
    (4, Bind::Texture),
    (5, Bind::ReadWrite),
    (6, Bind::ReadWrite),
];

/// Layout of `csr_spmv.wgsl` (group 0).
const SCALAR_BINDINGS: [(u32, Bind); 7] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::Read),
    (4, Bind::Read),
    (5, Bind::ReadWrite),
    (6, Bind::ReadWrite),
];

/// A compiled SpMV shader (block or scalar: bindings 0, 1, 5 and 6 are shared;
/// the scalar product reads the entries from two buffers (2, 3) and `x` from a
/// buffer (4), the block product both from textures (3, 4)).
pub(crate) struct SpmvKernel {
    shader: Shader,
    pub kernel: Kernel,
}

pub(crate) type BsrSpmv = SpmvKernel;

/// Compile `bsr_spmv.wgsl`, its texture width fixed from the device limits.
pub(crate) fn new(ctx: &Context) -> Result<BsrSpmv, GpuError> {
    let shader = Shader::new(ctx, "bsr_spmv.wgsl", SOURCE, &BLOCK_BINDINGS)?;
    let tw = ctx.texture_width() as f64;
    let kernel = Kernel::with_constants(&shader, "bsr_spmv", "main", &[("TW", tw)]);
    Ok(SpmvKernel { shader, kernel })
}

/// Compile `bsr_spmv_f64.wgsl` (needs `SHADER_F64`): the f64 block product of
/// the mixed-precision solve, on a [`MatrixStorage::SplitBlockTexture`] matrix
/// and a scalar PCG workspace (its parameters and dispatch; see the shader).
pub(crate) fn new_f64(ctx: &Context) -> Result<BsrSpmv, GpuError> {
    let shader = Shader::new(ctx, "bsr_spmv_f64.wgsl", F64_SOURCE, &BLOCK_F64_BINDINGS)?;
    let tw = ctx.texture_width() as f64;
    let kernel = Kernel::with_constants(&shader, "bsr_spmv_f64", "main", &[("TW", tw)]);
    Ok(SpmvKernel { shader, kernel })
}

impl SpmvKernel {
    /// A scalar (CSR) SpMV shader.
    pub(crate) fn load_scalar(
        ctx: &Context,
        file: &'static str,
        source: &str,
        label: &'static str,
    ) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, file, source, &SCALAR_BINDINGS)?;
        let kernel = Kernel::new(&shader, label, "main");
        Ok(SpmvKernel { shader, kernel })
    }

    /// `x` is read from the buffer by the scalar product, from the texture
    /// `x_tex` (same values, 4 f32 per vertex) by the block product.
    #[allow(clippy::too_many_arguments)]
    pub fn bind(
        &self,
        ctx: &Context,
        params: &wgpu::Buffer,
        m: &GpuMatrix,
        x: &wgpu::Buffer,
        x_tex: &wgpu::TextureView,
        y: &wgpu::Buffer,
        partials: &wgpu::Buffer,
    ) -> Result<wgpu::BindGroup, GpuError> {
        let shared = [(0, params), (1, &m.row_ptr), (5, y), (6, partials)];
        match &m.storage {
            MatrixStorage::Csr { col_idx, vals } => {
                let mut b = shared.to_vec();
                b.push((2, col_idx));
                b.push((3, vals));
                b.push((4, x));
                self.shader.bind(ctx, &b)
            }
            MatrixStorage::BlockTexture { view, .. } => {
                self.shader
                    .bind_with_views(ctx, &shared, &[(3, view), (4, x_tex)])
            }
            MatrixStorage::SplitBlockTexture { hi, lo_view, .. } => {
                let mut b = shared.to_vec();
                b.push((4, x));
                self.shader
                    .bind_with_views(ctx, &b, &[(2, lo_view), (3, hi)])
            }
        }
    }
}
