//! Drives `shaders/csr_spmv.wgsl`: `y = A x` for the full scalar CSR matrix of the
//! scale-factor system (f32), up to [`crate::CMAX`] columns at once, with the
//! per-workgroup partial dot products `x . y` fused in.
//!
//! Bindings (group 0), as the shader's header describes:
//! - 0 `P` uniform `Params`: rows, ncols, n = rows,
//!   groups = ceil(rows / 128);
//! - 1 `row_ptr`, 2 `col_idx`, 3 `vals` (one f32 per entry): the matrix
//!   (`GpuMatrix` with block size 1);
//! - 4 `x` (read), 5 `y` (written), column-major, stride n;
//! - 6 `partials` (written): `partials[c * groups + g]`.
//!
//! Dispatch: `groups` workgroups of 128 invocations, 2-D (see `Context::dims`).

use crate::bsr_spmv::SpmvKernel;
use crate::device::Context;
use crate::precision::Precision;
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/csr_spmv.wgsl");

/// Same driver as the block product ([`SpmvKernel`]); the matrix in buffers.
pub(crate) type CsrSpmv = SpmvKernel;

/// Compile `csr_spmv.wgsl`.
pub(crate) fn new(ctx: &Context) -> Result<CsrSpmv, GpuError> {
    new_in(ctx, Precision::F32)
}

/// Compile `csr_spmv.wgsl` in `precision` (f64: see [`crate::precision`]).
pub(crate) fn new_in(ctx: &Context, precision: Precision) -> Result<CsrSpmv, GpuError> {
    let (file, label) = match precision {
        Precision::F32 => ("csr_spmv.wgsl", "csr_spmv"),
        Precision::F64 => ("csr_spmv.wgsl (f64)", "csr_spmv_f64"),
    };
    SpmvKernel::load_scalar(ctx, file, &precision.source(SOURCE), label)
}
