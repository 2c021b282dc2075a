//! Drives `shaders/dot.wgsl`: dot products `a_c . b_c` of up to
//! [`crate::CMAX`] column pairs in two passes.
//!
//! Bindings (group 0), as the shader's header describes:
//! - 0 `P` uniform [`Params`](crate::device::Params): n (column length), ncols,
//!   groups = ceil(n / 128);
//! - 1 `a`, 2 `b` (read, `partial` only): column-major, stride n;
//! - 3 `partials`: written by `partial` (`partials[c * groups + g]`), read by
//!   `finish`;
//! - 4 `out` (written by `finish`): one f32 per column.
//!
//! `partial` runs `groups` workgroups of 128 (2-D dispatch); `finish` one
//! workgroup of 256. The PCG loop reduces the same partials layout in its own
//! finishing kernels (`pcg.wgsl`), which also update alpha and beta.

use crate::device::{Context, Kernel};
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/dot.wgsl");

pub(crate) struct Dot {
    pub partial: Kernel,
    pub finish: Kernel,
}

impl Dot {
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let m = ctx.shader("dot.wgsl", SOURCE)?;
        Ok(Dot {
            partial: Kernel::new(ctx, "dot_partial", &m, "partial")?,
            finish: Kernel::new(ctx, "dot_finish", &m, "finish")?,
        })
    }

    /// Bind groups of the two passes.
    pub fn bind(
        &self,
        ctx: &Context,
        params: &wgpu::Buffer,
        a: &wgpu::Buffer,
        b: &wgpu::Buffer,
        partials: &wgpu::Buffer,
        out: &wgpu::Buffer,
    ) -> Result<(wgpu::BindGroup, wgpu::BindGroup), GpuError> {
        Ok((
            self.partial
                .bind(ctx, &[(0, params), (1, a), (2, b), (3, partials)])?,
            self.finish
                .bind(ctx, &[(0, params), (3, partials), (4, out)])?,
        ))
    }
}
