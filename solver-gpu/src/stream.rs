//! Drives `shaders/stream.wgsl`: the adapter's read-bandwidth ceiling, the
//! time of the least work a kernel can do per byte read (sum a run of
//! `vec4<f32>` storage-buffer elements, neighbouring invocations reading
//! neighbouring elements, one partial written per invocation). A kernel that
//! must read `B` bytes the same way takes at least `B / ceiling`; the
//! `pcg_kernels` benchmark sets the PCG iteration beside it.
//!
//! Bindings (group 0), as the shader's header describes:
//! - 0 `P` uniform: elements, groups (each workgroup reads 128 x 16 elements);
//! - 2 `src` (the values, `vec4<f32>`, in a storage buffer);
//! - 3 `partials` (written, one per invocation).
//!
//! Dispatch: `groups` workgroups of 128 invocations, 2-D (see `Context::dims`).

use crate::device::{dispatch, Bind, Context, Kernel, Shader};
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/stream.wgsl");

const BINDINGS: [(u32, Bind); 3] = [(0, Bind::Uniform), (2, Bind::Read), (3, Bind::ReadWrite)];

/// Elements one workgroup reads (`WG * PER` in the shader).
const PER_GROUP: u64 = 128 * 16;

/// Seconds per pass over `bytes` bytes read from a storage buffer.
#[derive(Debug, Clone, Copy)]
pub struct ReadCeiling {
    pub bytes: u64,
    pub seconds: f64,
}

impl ReadCeiling {
    /// Bytes per second through a storage buffer.
    pub fn bandwidth(&self) -> f64 {
        self.bytes as f64 / self.seconds
    }
}

/// Time `reps` passes (after one warm-up pass) over `elements` `vec4<f32>`
/// values (16 bytes each), at most as many as one storage binding holds
/// (the ceiling is a rate: a larger request is measured over the largest
/// binding).
pub(crate) fn measure(ctx: &Context, elements: u64, reps: usize) -> Result<ReadCeiling, GpuError> {
    let shader = Shader::new(ctx, "stream.wgsl", SOURCE, &BINDINGS)?;
    let kernel = Kernel::new(&shader, "buffer_sum", "main");
    let elements = elements.min(crate::matrix::binding_limit(ctx) / 16).max(1);
    let value = |i: u64| (i % 1000) as f32 * 1e-3;
    let values: Vec<f32> = (0..4 * elements).map(value).collect();
    let buffer = ctx.storage_init("stream source (storage buffer)", &values)?;
    drop(values);
    let want: f64 = (0..4 * elements).map(|i| value(i) as f64).sum();
    let groups = elements.div_ceil(PER_GROUP);
    let partials = ctx.storage("stream partials", groups * 128 * 4)?;
    let params = ctx.uniform_of("stream params", &[elements as u32, groups as u32, 0, 0])?;
    let bg = shader.bind(ctx, &[(0, &params), (2, &buffer), (3, &partials)])?;
    let dims = ctx.dims("stream", groups)?;
    let pipeline = kernel.pipeline(ctx, 1)?;
    let mut seconds = 0.0;
    for (passes, timed) in [(1, false), (reps.max(1), true)] {
        let mut enc = ctx.encoder("stream");
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            for _ in 0..passes {
                dispatch(&mut pass, &pipeline, &bg, dims);
            }
        }
        let t = std::time::Instant::now();
        ctx.submit_wait(enc)?;
        if timed {
            seconds = t.elapsed().as_secs_f64() / passes as f64;
        }
    }
    // The pass read every value: its partials add up to their sum.
    let got: f64 = ctx
        .read::<f32>(&partials, (groups * 128) as usize, &mut None, None)?
        .iter()
        .map(|&v| v as f64)
        .sum();
    if (got - want).abs() > 1e-4 * want.abs().max(1.0) {
        return Err(GpuError::Backend(format!(
            "{}: the partials add up to {got}, not {want}",
            kernel.label
        )));
    }
    Ok(ReadCeiling {
        bytes: elements * 16,
        seconds,
    })
}
