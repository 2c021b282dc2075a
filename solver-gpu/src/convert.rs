//! Drives `shaders/convert.wgsl`: f64 <-> f32 copies of PCG vectors for the
//! mixed-precision PCG (f64 iteration, f32 AMG V-cycle; needs `SHADER_F64`).
//!
//! Bindings (group 0): 0 `P` uniform (`n`, the column length); 1 `wide` (f64);
//! 2 `narrow` (f32), both `NCOLS` columns of stride `n`. `to_f32` writes
//! `narrow = f32(wide)`, `to_f64` `wide = f64(narrow)`. Dispatch: `ceil(n / 256)`
//! workgroups, 2-D.

use crate::device::{Bind, Context, Kernel, Shader};
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/convert.wgsl");

const BINDINGS: [(u32, Bind); 3] = [
    (0, Bind::Uniform),
    (1, Bind::ReadWrite),
    (2, Bind::ReadWrite),
];

/// Parameters, as `ConvertParams` in `convert.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ConvertParams {
    pub n: u32,
    pub pad: [u32; 3],
}

pub(crate) struct Convert {
    shader: Shader,
    pub to_f32: Kernel,
    pub to_f64: Kernel,
}

impl Convert {
    /// Compile `convert.wgsl` (the device must have `SHADER_F64`).
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, "convert.wgsl", SOURCE, &BINDINGS)?;
        Ok(Convert {
            to_f32: Kernel::new(&shader, "convert_to_f32", "to_f32"),
            to_f64: Kernel::new(&shader, "convert_to_f64", "to_f64"),
            shader,
        })
    }

    /// The bind group pairing an f64 and an f32 vector.
    pub fn bind(
        &self,
        ctx: &Context,
        params: &wgpu::Buffer,
        wide: &wgpu::Buffer,
        narrow: &wgpu::Buffer,
    ) -> Result<wgpu::BindGroup, GpuError> {
        self.shader
            .bind(ctx, &[(0, params), (1, wide), (2, narrow)])
    }
}
