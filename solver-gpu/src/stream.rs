//! Drives `shaders/stream.wgsl`: the adapter's read-bandwidth ceiling, the
//! time of the least work a kernel can do per byte read (sum a run of
//! RGBA32F texels, or of `vec4<f32>` storage elements, one partial written per
//! invocation; one entry point, the source chosen by the pipeline constant
//! `FROM_TEXTURE`). A kernel that must read `B` bytes the same way takes at least
//! `B / ceiling`; the `pcg_kernels` benchmark sets the PCG iteration beside it.
//!
//! Bindings (group 0), as the shader's header describes:
//! - 0 `P` uniform: texels, groups (each workgroup reads 128 x 16 elements);
//! - 1 `src` (RGBA32F texture, the block matrix's layout), 2 `src_buf` (the
//!   same values in a storage buffer);
//! - 3 `partials` (written, one per invocation).
//!
//! Dispatch: `groups` workgroups of 128 invocations, 2-D (see `Context::dims`).

use crate::device::{dispatch, Bind, Context, Kernel, Shader};
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/stream.wgsl");

const BINDINGS: [(u32, Bind); 4] = [
    (0, Bind::Uniform),
    (1, Bind::Texture),
    (2, Bind::Read),
    (3, Bind::ReadWrite),
];

/// Elements one workgroup reads (`WG * PER` in the shader).
const PER_GROUP: u64 = 128 * 16;

/// Seconds per pass over `bytes` bytes, read from a texture and from a
/// storage buffer (`None` where the bytes pass the storage binding limit).
#[derive(Debug, Clone, Copy)]
pub struct ReadCeiling {
    pub bytes: u64,
    pub texture_seconds: f64,
    pub buffer_seconds: Option<f64>,
}

impl ReadCeiling {
    /// Bytes per second through a texture.
    pub fn texture_bandwidth(&self) -> f64 {
        self.bytes as f64 / self.texture_seconds
    }

    /// Bytes per second through a storage buffer.
    pub fn buffer_bandwidth(&self) -> Option<f64> {
        self.buffer_seconds.map(|s| self.bytes as f64 / s)
    }
}

/// Time `reps` passes (after one warm-up pass) of each entry point over
/// `texels` RGBA32F values (16 bytes each); the storage-buffer pass only where
/// they fit the binding limit (the texture is not bound by it).
pub(crate) fn measure(ctx: &Context, texels: u64, reps: usize) -> Result<ReadCeiling, GpuError> {
    let shader = Shader::new(ctx, "stream.wgsl", SOURCE, &BINDINGS)?;
    let tw = ctx.texture_width() as f64;
    let kernels = [
        Kernel::with_constants(
            &shader,
            "texture_sum",
            "main",
            &[("TW", tw), ("FROM_TEXTURE", 1.0)],
        ),
        Kernel::with_constants(
            &shader,
            "buffer_sum",
            "main",
            &[("TW", tw), ("FROM_TEXTURE", 0.0)],
        ),
    ];
    let value = |i: u64| (i % 1000) as f32 * 1e-3;
    let texture = ctx.data_texture("stream source", texels, false)?;
    ctx.write_data_texture(&texture, texels as usize, |t, out| {
        for (q, o) in out.iter_mut().enumerate() {
            *o = value(4 * t as u64 + q as u64);
        }
    });
    let view = texture.create_view(&Default::default());
    let fits = ctx.check_storage("stream source", texels * 16).is_ok();
    let values: Vec<f32> = if fits {
        (0..4 * texels).map(value).collect()
    } else {
        vec![0.0; 4] // a placeholder binding; its pass is skipped
    };
    let buffer = ctx.storage_init("stream source (storage buffer)", &values)?;
    drop(values);
    let want: f64 = (0..4 * texels).map(|i| value(i) as f64).sum();
    let groups = texels.div_ceil(PER_GROUP);
    let partials = ctx.storage("stream partials", groups * 128 * 4)?;
    let params = ctx.uniform_of("stream params", &[texels as u32, groups as u32, 0, 0])?;
    let bg = shader.bind_with_views(
        ctx,
        &[(0, &params), (2, &buffer), (3, &partials)],
        &[(1, &view)],
    )?;
    let dims = ctx.dims("stream", groups)?;
    let mut seconds = [0.0; 2];
    let passes = if fits { 2 } else { 1 };
    for (k, s) in kernels.iter().zip(seconds.iter_mut()).take(passes) {
        let pipeline = k.pipeline(ctx, 1)?;
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
                *s = t.elapsed().as_secs_f64() / passes as f64;
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
                k.label
            )));
        }
    }
    Ok(ReadCeiling {
        bytes: texels * 16,
        texture_seconds: seconds[0],
        buffer_seconds: fits.then_some(seconds[1]),
    })
}
