//! Drives `shaders/bsr_spmv.wgsl`: `y = A x` for the full 3x3 block-CSR matrix
//! (f32) on up to [`crate::CMAX`] columns at once, with the per-workgroup partial
//! dot products `x . y` (the `p . Ap` of PCG) fused in.
//!
//! Bindings (group 0), as the shader's header describes:
//! - 0 `P` uniform `Params`: n = 3 rows, ncols,
//!   groups = partial slots per column;
//! - 1 `row_ptr` (global), 3 `vals` (9 f32 per block) and 7 `cols` (u32 per
//!   block): the matrix (`GpuMatrix`), 2 `C` its chunk
//!   (`ChunkParams`);
//! - 4 `x` (read in place: the PCG's `p`), 5 `y` (written, column-major,
//!   stride n);
//! - 6 `partials` (written): `partials[c * groups + g]`.
//!
//! Dispatch: per chunk of the matrix (block rows whose values fit one
//! storage binding, `crate::matrix::split_rows`) its workgroups of 128
//! invocations, 2-D (see `Context::dims`); one chunk unless the matrix
//! passes `max_storage_buffer_binding_size`.
//!
//! Also drives `shaders/bsr_spmv_f64.wgsl` (`new_f64`), the f64 product of
//! the mixed-precision solve: the same blocks as high (the f32 values) and low
//! f32 parts, `x`, `y` and the partials in f64 buffers (bindings 2 `lo`, 3 `hi`,
//! 8 `C`; the rest as above).

use crate::device::{Bind, Context, Kernel, Shader};
use crate::matrix::{chunk_groups, GpuMatrix, MatrixStorage};
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/bsr_spmv.wgsl");
pub(crate) const F64_SOURCE: &str = include_str!("../../shaders/bsr_spmv_f64.wgsl");

/// Layout of `bsr_spmv_f64.wgsl` (group 0).
const BLOCK_F64_BINDINGS: [(u32, Bind); 9] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::Read),
    (4, Bind::Read),
    (5, Bind::ReadWrite),
    (6, Bind::ReadWrite),
    (7, Bind::Read),
    (8, Bind::Uniform),
];

/// Layout of `bsr_spmv.wgsl` (group 0).
const BLOCK_BINDINGS: [(u32, Bind); 8] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Uniform),
    (3, Bind::Read),
    (4, Bind::Read),
    (5, Bind::ReadWrite),
    (6, Bind::ReadWrite),
    (7, Bind::Read),
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

/// A compiled SpMV shader (block or scalar: bindings 0, 1, 4, 5 and 6 are
/// shared; the scalar product reads the entries from two buffers (2, 3), the
/// block product from its chunk's `vals` (3) and `cols` (7)).
pub(crate) struct SpmvKernel {
    shader: Shader,
    pub kernel: Kernel,
}

pub(crate) type BsrSpmv = SpmvKernel;

/// One dispatch of a product: its bind group and 2-D workgroup counts.
pub(crate) type SpmvDispatch = (wgpu::BindGroup, (u32, u32));

/// Compile `bsr_spmv.wgsl`.
pub(crate) fn new(ctx: &Context) -> Result<BsrSpmv, GpuError> {
    let shader = Shader::new(ctx, "bsr_spmv.wgsl", SOURCE, &BLOCK_BINDINGS)?;
    let kernel = Kernel::new(&shader, "bsr_spmv", "main");
    Ok(SpmvKernel { shader, kernel })
}

/// Compile `bsr_spmv_f64.wgsl` (needs `SHADER_F64`): the f64 block product of
/// the mixed-precision solve, on a [`MatrixStorage::SplitBlocks`] matrix and
/// a scalar PCG workspace (its parameters; see the shader).
pub(crate) fn new_f64(ctx: &Context) -> Result<BsrSpmv, GpuError> {
    let shader = Shader::new(ctx, "bsr_spmv_f64.wgsl", F64_SOURCE, &BLOCK_F64_BINDINGS)?;
    let kernel = Kernel::new(&shader, "bsr_spmv_f64", "main");
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

    /// The dispatches of `y = A x` with `groups` partial slots per column
    /// (at least [`GpuMatrix::partial_slots`]): one for a scalar matrix, one
    /// per chunk for a block matrix, the last reaching `groups`.
    #[allow(clippy::too_many_arguments)]
    pub fn bind(
        &self,
        ctx: &Context,
        params: &wgpu::Buffer,
        m: &GpuMatrix,
        x: &wgpu::Buffer,
        y: &wgpu::Buffer,
        partials: &wgpu::Buffer,
        groups: u64,
    ) -> Result<Vec<SpmvDispatch>, GpuError> {
        let shared = [(0, params), (1, &m.row_ptr), (4, x), (5, y), (6, partials)];
        let (chunks, uniforms, lo) = match &m.storage {
            MatrixStorage::Csr { col_idx, vals } => {
                let mut b = shared.to_vec();
                b.push((2, col_idx));
                b.push((3, vals));
                let bg = self.shader.bind(ctx, &b)?;
                return Ok(vec![(bg, ctx.dims("scalar spmv", groups)?)]);
            }
            MatrixStorage::Blocks { chunks, uniforms } => (chunks, uniforms, None),
            MatrixStorage::SplitBlocks { hi, lo, uniforms } => (hi, uniforms, Some(lo)),
        };
        let counts = chunk_groups(chunks);
        let mut group0 = 0u64;
        let mut out = Vec::with_capacity(chunks.len());
        for (i, (c, u)) in chunks.iter().zip(uniforms).enumerate() {
            let mut b = shared.to_vec();
            match lo {
                None => b.extend([(2, u), (3, &c.vals), (7, &c.cols)]),
                Some(lo) => b.extend([(2, &lo[i]), (3, &c.vals), (7, &c.cols), (8, u)]),
            }
            let mine = if i + 1 == chunks.len() {
                groups.saturating_sub(group0).max(1)
            } else {
                counts[i] as u64
            };
            group0 += counts[i] as u64;
            out.push((self.shader.bind(ctx, &b)?, ctx.dims("block spmv", mine)?));
        }
        Ok(out)
    }
}
