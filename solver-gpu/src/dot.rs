//! Drives `shaders/dot.wgsl`: dot products `a_c . b_c` of up to
//! [`crate::CMAX`] column pairs in two passes.
//!
//! Bindings (group 0), as the shader's header describes:
//! - 0 `P` uniform `Params`: n (column length), ncols,
//!   groups = ceil(n / 128);
//! - 1 `a`, 2 `b` (read, `partial` only): column-major, stride n;
//! - 3 `partials`: written by `partial` (`partials[c * groups + g]`), read by
//!   `finish`;
//! - 4 `out` (written by `finish`): one f32 per column.
//!
//! `partial` runs `groups` workgroups of 128 (2-D dispatch); `finish` one
//! workgroup of 256. The PCG loop reduces the same partials layout in its own
//! finishing kernels (`pcg.wgsl`), which also update alpha and beta.

use crate::device::{Bind, Context, Kernel, Shader};
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/dot.wgsl");

/// Layout of `dot.wgsl` (group 0).
const BINDINGS: [(u32, Bind); 5] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::ReadWrite),
    (4, Bind::ReadWrite),
];

pub(crate) struct Dot {
    shader: Shader,
    pub partial: Kernel,
    pub finish: Kernel,
}

impl Dot {
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, "dot.wgsl", SOURCE, &BINDINGS)?;
        Ok(Dot {
            partial: Kernel::new(&shader, "dot_partial", "partial"),
            finish: Kernel::new(&shader, "dot_finish", "finish"),
            shader,
        })
    }

    /// The bind group of both passes.
    pub fn bind(
        &self,
        ctx: &Context,
        params: &wgpu::Buffer,
        a: &wgpu::Buffer,
        b: &wgpu::Buffer,
        partials: &wgpu::Buffer,
        out: &wgpu::Buffer,
    ) -> Result<wgpu::BindGroup, GpuError> {
        self.shader
            .bind(ctx, &[(0, params), (1, a), (2, b), (3, partials), (4, out)])
    }
}
