//! Block-Jacobi preconditioner `M = blockdiag(A)`: the diagonal blocks are
//! inverted here on the CPU in f64 at prepare time (a non-positive-definite
//! block means the matrix is not SPD) and uploaded as f32; `shaders/block_jacobi.wgsl`
//! applies `z = M^-1 r`. For the scalar system the blocks are 1x1 (plain Jacobi).
//! The PCG loop applies the same inverse inside its fused update kernel.
//!
//! Bindings (group 0), as the shader's header describes:
//! - 0 `P` uniform `Params`: rows, bs (1 or 3),
//!   n = rows bs, ncols;
//! - 1 `minv` (read): rows * bs * bs f32;
//! - 2 `r` (read), 3 `z` (written): column-major, stride n.
//!
//! Dispatch: ceil(rows / 128) workgroups of 128, 2-D.

use crate::device::{Bind, Context, Kernel, Shader};
use crate::matrix::HostMatrix;
use crate::GpuError;
use rayon::prelude::*;
use solver_cpu::SolverError;

pub(crate) const SOURCE: &str = include_str!("../../shaders/block_jacobi.wgsl");

/// Layout of `block_jacobi.wgsl` (group 0).
const BINDINGS: [(u32, Bind); 4] = [
    (0, Bind::Uniform),
    (1, Bind::Read),
    (2, Bind::Read),
    (3, Bind::ReadWrite),
];

pub(crate) struct BlockJacobi {
    shader: Shader,
    pub kernel: Kernel,
}

impl BlockJacobi {
    pub fn new(ctx: &Context) -> Result<Self, GpuError> {
        let shader = Shader::new(ctx, "block_jacobi.wgsl", SOURCE, &BINDINGS)?;
        let kernel = Kernel::new(&shader, "block_jacobi", "main");
        Ok(BlockJacobi { shader, kernel })
    }

    pub fn bind(
        &self,
        ctx: &Context,
        params: &wgpu::Buffer,
        minv: &wgpu::Buffer,
        r: &wgpu::Buffer,
        z: &wgpu::Buffer,
    ) -> Result<wgpu::BindGroup, GpuError> {
        self.shader
            .bind(ctx, &[(0, params), (1, minv), (2, r), (3, z)])
    }
}

/// Inverses of the diagonal blocks (f64, checked positive definite), as f32,
/// into `out` (its contents replaced; the solver keeps it from one matrix
/// to the next: 36 bytes a block row, which a fresh vector would fault in
/// page by page, 21 MB at 1.2M faces).
pub(crate) fn inverse_diagonal(h: &HostMatrix, out: &mut Vec<f32>) -> Result<(), SolverError> {
    let bs = h.bs;
    let bb = bs * bs;
    out.clear();
    out.resize(h.rows * bb, 0.0);
    h.make_diagonal();
    let ok = out.par_chunks_mut(bb).enumerate().all(|(row, dst)| {
        let block = h.diag_block(row);
        let d = &block[..bb];
        let inv = if bs == 1 {
            (d[0] > 0.0 && d[0].is_finite()).then(|| {
                let mut one = [0.0; 9];
                one[0] = 1.0 / d[0];
                one
            })
        } else {
            invert_spd3(d)
        };
        match inv {
            Some(inv) if inv[..bb].iter().all(|v| (*v as f32).is_finite()) => {
                for (o, v) in dst.iter_mut().zip(&inv[..bb]) {
                    *o = *v as f32;
                }
                true
            }
            _ => false,
        }
    });
    if ok {
        Ok(())
    } else {
        Err(SolverError::NotPositiveDefinite)
    }
}

/// Inverse of a symmetric positive definite 3x3 matrix (row-major; the
/// symmetric part is used), or `None` if a leading minor is not positive.
pub fn invert_spd3(m: &[f64]) -> Option<[f64; 9]> {
    let (a, b, c) = (m[0], 0.5 * (m[1] + m[3]), 0.5 * (m[2] + m[6]));
    let (d, e) = (m[4], 0.5 * (m[5] + m[7]));
    let f = m[8];
    let m2 = a * d - b * b;
    let c00 = d * f - e * e;
    let c01 = c * e - b * f;
    let c02 = b * e - c * d;
    let det = a * c00 + b * c01 + c * c02;
    if !(a > 0.0 && m2 > 0.0 && det > 0.0 && det.is_finite()) {
        return None;
    }
    let c11 = a * f - c * c;
    let c12 = b * c - a * e;
    let inv = 1.0 / det;
    Some([
        c00 * inv,
        c01 * inv,
        c02 * inv,
        c01 * inv,
        c11 * inv,
        c12 * inv,
        c02 * inv,
        c12 * inv,
        m2 * inv,
    ])
}

#[cfg(test)]
mod tests {
    #[test]
    fn invert_spd3_is_inverse() {
        let m = [4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 2.0];
        let inv = super::invert_spd3(&m).unwrap();
        for r in 0..3 {
            for c in 0..3 {
                let s: f64 = (0..3).map(|k| m[3 * r + k] * inv[3 * k + c]).sum();
                assert!((s - if r == c { 1.0 } else { 0.0 }).abs() < 1e-14);
            }
        }
        assert!(super::invert_spd3(&[1.0, 2.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0, 1.0]).is_none());
    }
}
