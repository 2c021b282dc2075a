//! Drives `shaders/expand_blocks.wgsl`: a new symmetric 3x3 block matrix of a
//! prepared pattern goes up as its lower triangle in f64 (72 bytes per lower
//! block, no conversion on the host) and is expanded on the GPU into the
//! block product's chunks: both triangles, held rows and columns the
//! identity, f32 high parts and, where the mixed-precision product exists,
//! low parts (`hi + lo` = `v` to 2^-48).
//!
//! Bindings (group 0): 0 `C` uniform ([`ExpandParams`], one per chunk); 1
//! `lower` (read, f64); 2 `map` (read, u32 per block, [`HostMatrix::map`]); 3 `hi`
//! (read-write, the chunk's values); 4 `lo` (read-write, its low parts or a
//! placeholder). Dispatch: `ceil(blocks / 256)` workgroups per chunk, 2-D.
//! Needs `SHADER_F64`; without it the host writes the f32 values itself.

use crate::device::{dispatch, Bind, Context, Kernel, KernelWork, Shader, FLAT_WG};
use crate::matrix::Chunk;
#[cfg(doc)]
use crate::matrix::HostMatrix;
use crate::GpuError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/expand_blocks.wgsl");

const BINDINGS: [(u32, Bind); 5] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::ReadWrite),
    (4, Bind::ReadWrite),
];

/// `map` entries of [`HostMatrix::map`] (as in the shader).
pub(crate) const ZERO: u32 = u32::MAX;
pub(crate) const IDENTITY: u32 = u32::MAX - 1;
pub(crate) const TRANSPOSE: u32 = 1 << 31;

/// Parameters of one chunk, as `ExpandParams` in `expand_blocks.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
struct ExpandParams {
    block0: u32,
    blocks: u32,
    split: u32,
    pad: u32,
}

pub(crate) struct ExpandBlocks {
    shader: Shader,
    kernel: Kernel,
}

/// The recorded expansion into one matrix's chunks.
pub(crate) struct Expansion {
    /// The lower triangle's f64 values, written by the host per matrix.
    pub lower: wgpu::Buffer,
    steps: Vec<(wgpu::BindGroup, (u32, u32))>,
    work: KernelWork,
    /// Kept alive for the bind groups.
    #[allow(dead_code)]
    keep: Vec<wgpu::Buffer>,
}

impl ExpandBlocks {
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, "expand_blocks.wgsl", SOURCE, &BINDINGS)?;
        Ok(ExpandBlocks {
            kernel: Kernel::new(&shader, "expand_blocks", "expand_blocks"),
            shader,
        })
    }

    /// The expansion of `lower_blocks` lower blocks through `map` into
    /// `chunks` (their values) and, when given, `lo` (one buffer per chunk).
    pub fn expansion(
        &self,
        ctx: &Context,
        lower_blocks: usize,
        map: &[u32],
        chunks: &[Chunk],
        lo: Option<&[wgpu::Buffer]>,
    ) -> Result<Expansion, GpuError> {
        let lower = ctx.storage(
            &format!("lower-triangle f64 values ({lower_blocks} blocks)"),
            (72 * lower_blocks.max(1)) as u64,
        )?;
        let map_buf = ctx.storage_init("block map (full block to lower block)", map)?;
        let placeholder = ctx.storage("expansion placeholder", 4)?;
        let mut steps = Vec::with_capacity(chunks.len());
        let mut keep = vec![map_buf.clone(), placeholder.clone()];
        for (i, c) in chunks.iter().enumerate() {
            let blocks = c.blocks.len();
            let params = ctx.uniform_of(
                "expand_blocks params",
                &ExpandParams {
                    block0: c.blocks.start as u32,
                    blocks: blocks as u32,
                    split: u32::from(lo.is_some()),
                    pad: 0,
                },
            )?;
            let lo_buf = lo.map_or(&placeholder, |l| &l[i]);
            let bg = self.shader.bind(
                ctx,
                &[
                    (0, &params),
                    (1, &lower),
                    (2, &map_buf),
                    (3, &c.vals),
                    (4, lo_buf),
                ],
            )?;
            steps.push((
                bg,
                ctx.dims("expand_blocks", (blocks as u64).div_ceil(FLAT_WG as u64))?,
            ));
            keep.push(params);
        }
        // Each block's map entry and its source once, its parts written.
        let full = map.len() as u64;
        let parts = if lo.is_some() { 2 } else { 1 };
        let bytes = 4 * full + 72 * lower_blocks as u64 + 36 * parts * full;
        Ok(Expansion {
            lower,
            steps,
            work: KernelWork::other(bytes),
            keep,
        })
    }

    /// Write `lower` (f64, 9 per lower block) and expand it: one submission.
    pub fn run(&self, ctx: &Context, e: &Expansion, lower: &[[f64; 9]]) -> Result<(), GpuError> {
        ctx.write_buffer(&e.lower, 0, bytemuck::cast_slice(lower));
        let pipeline = self.kernel.pipeline(ctx, 1)?;
        let mut enc = ctx.encoder("expand_blocks");
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("expand_blocks"),
                timestamp_writes: None,
            });
            for (bg, dims) in &e.steps {
                dispatch(&mut pass, &pipeline, bg, *dims);
            }
        }
        ctx.count_kernels(e.work);
        ctx.queue.submit([enc.finish()]);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use crate::matrix::{high_part, low_part, HostMatrix};
    use crate::MixedPrecision;
    use solver_cpu::{BlockSym3, SpdSolver};

    /// A block matrix on a ring of `n` vertices (neighbours 1 and 2 apart),
    /// SPD diagonal blocks, values depending on `seed`.
    fn ring(n: usize, seed: f64) -> BlockSym3 {
        let pairs = (0..n).flat_map(|i| [(i, (i + 1) % n), (i, (i + 2) % n)]);
        let mut a = BlockSym3::from_pattern(n, pairs);
        for j in 0..n {
            for k in a.col_ptr[j]..a.col_ptr[j + 1] {
                let i = a.row_idx[k];
                let b = &mut a.blocks[k];
                for (q, v) in b.iter_mut().enumerate() {
                    // Values with bits below f32's, so the low parts matter.
                    *v = 0.01 * ((seed + (7 * k + q) as f64) * 0.731).sin() / 3.0;
                }
                if i == j {
                    for q in [0, 4, 8] {
                        b[q] += 4.0 + seed;
                    }
                    // Symmetric diagonal blocks.
                    for (r, c) in [(0, 1), (0, 2), (1, 2)] {
                        b[3 * c + r] = b[3 * r + c];
                    }
                }
            }
        }
        a
    }

    #[test]
    fn expanded_values_are_the_hosts_high_and_low_parts() {
        let Ok(mut s) = crate::open() else {
            assert!(
                std::env::var("REQUIRE_GPU").map_or(true, |v| v != "1"),
                "REQUIRE_GPU=1 but no GPU adapter"
            );
            return;
        };
        if !s.ctx.shader_f64 {
            return;
        }
        s.set_mixed_precision(MixedPrecision::Always);
        let n = 40;
        let mut fixed = vec![false; n];
        fixed[7] = true;
        let a = ring(n, 0.0);
        s.prepare_blocks(&a, &fixed).unwrap();
        // A solve builds the mixed-precision matrix (its low parts).
        let mut x = vec![1.0; 3 * n];
        s.solve_in_place(&mut x, 1).unwrap();
        assert!(s.last_solve_mixed());
        // New values of the pattern: expanded on the GPU (the first time
        // also uploads the block map), then again.
        s.prepare_blocks(&ring(n, 0.25), &fixed).unwrap();
        assert!(
            s.expansion.is_some(),
            "the values went through the expansion"
        );
        let b = ring(n, 0.5);
        let up0 = s.ctx.traffic().to_device;
        s.prepare_blocks(&b, &fixed).unwrap();
        let up = s.ctx.traffic().to_device - up0;
        // The lower f64 values and the inverse diagonals, nothing per block of
        // both triangles: 72 bytes a lower block, 36 + 24 a block row.
        assert_eq!(up, (72 * b.blocks.len() + 60 * n) as u64);
        let mut want = HostMatrix::pattern(n, 3, &b.col_ptr, &b.row_idx).unwrap();
        want.fill_blocks(&b, &fixed);
        let want_vals = want.full_values();
        let gpu = s.gpu.as_ref().unwrap();
        let (chunks, _) = gpu.block_parts().unwrap();
        let mixed = s.mixed.as_ref().unwrap();
        let (_, lo) = mixed.matrix.block_parts().unwrap();
        let lo = lo.unwrap();
        let mut staging = None;
        let mut checked = 0;
        for (c, lo_buf) in chunks.iter().zip(lo) {
            let count = 9 * c.blocks.len();
            let hi: Vec<f32> = s.ctx.read(&c.vals, count, &mut staging, None).unwrap();
            let lo: Vec<f32> = s.ctx.read(lo_buf, count, &mut staging, None).unwrap();
            let v = &want_vals[9 * c.blocks.start..9 * c.blocks.end];
            for ((&v, &h), &l) in v.iter().zip(&hi).zip(&lo) {
                // f32 conversions may round either way in WGSL: one ulp.
                let ulp = |x: f32| (x.abs() * f32::EPSILON).max(f32::MIN_POSITIVE) as f64;
                assert!(
                    (h as f64 - high_part(v) as f64).abs() <= ulp(h),
                    "{h} vs {v}"
                );
                let sum = h as f64 + l as f64;
                assert!(
                    (sum - v).abs() <= 2f64.powi(-46) * v.abs(),
                    "{h} + {l} vs {v}"
                );
                if v != 0.0 && h as f64 == high_part(v) as f64 {
                    assert!((l - low_part(v)).abs() <= l.abs() * f32::EPSILON);
                }
                checked += 1;
            }
        }
        assert_eq!(checked, want_vals.len());
        // The held vertex's row is the identity, its column zero elsewhere.
        let r = want.row_ptr[7] as usize..want.row_ptr[8] as usize;
        assert!(r.clone().all(|k| {
            let blk = &want_vals[9 * k..9 * k + 9];
            match want.col_idx[k] {
                7 => blk == [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                _ => blk.iter().all(|&v| v == 0.0),
            }
        }));
        // And the solve with the expanded matrix is the host's.
        let mut y = vec![1.0; 3 * n];
        s.solve_in_place(&mut y, 1).unwrap();
        let mut r = vec![0.0; 3 * n];
        want.residual(&vec![1.0; 3 * n], &y, &mut r, 1);
        let rel = r.iter().map(|v| v * v).sum::<f64>().sqrt() / (3.0 * n as f64).sqrt();
        assert!(rel < 1e-9, "relative residual {rel:e}");
    }
}
