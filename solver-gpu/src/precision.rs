//! Kernel precision. The shaders are written in f32; where the adapter has
//! `SHADER_F64` the PCG shaders (`pcg.wgsl`, `csr_spmv.wgsl`) also compile in
//! f64 after a small text transform of the same source ([`f64_source`]):
//!
//! 1. the lines from `// f32-only begin` to `// f32-only end` are dropped (the
//!    texture paths: textures hold f32, so the f64 kernels read buffers);
//! 2. a line `// f64-only: CODE` becomes `CODE`;
//! 3. every `f32` becomes `f64`.
//!
//! The f64 kernels run the mixed-precision solve (f64 PCG, f32 V-cycle; its
//! block product is the hand-written `bsr_spmv_f64.wgsl`) and the precision
//! measurement (`kernels::scalar_pcg` and the `pcg_kernels` benchmark); the
//! solver's first choice is f32 kernels with residuals in f64 on the host
//! (iterative refinement), see `BENCHMARKS.md`.

use std::borrow::Cow;

/// Floating-point type of the GPU vectors, matrix values and PCG scalars.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Precision {
    F32,
    /// Needs the adapter feature `SHADER_F64`.
    F64,
}

impl Precision {
    /// Bytes of one value.
    pub fn bytes(self) -> u64 {
        match self {
            Precision::F32 => 4,
            Precision::F64 => 8,
        }
    }

    /// `v` rounded to this precision, as the bytes a buffer holds.
    pub(crate) fn encode(self, v: &[f64]) -> Vec<u8> {
        match self {
            Precision::F32 => {
                let w: Vec<f32> = v.iter().map(|&a| a as f32).collect();
                bytemuck::cast_slice(&w).to_vec()
            }
            Precision::F64 => bytemuck::cast_slice(v).to_vec(),
        }
    }

    /// The shader source in this precision.
    pub(crate) fn source(self, src: &'static str) -> Cow<'static, str> {
        match self {
            Precision::F32 => Cow::Borrowed(src),
            Precision::F64 => Cow::Owned(f64_source(src)),
        }
    }
}

/// The f64 variant of an f32 shader source (the transform of the module docs).
pub fn f64_source(src: &str) -> String {
    let mut out = String::with_capacity(src.len());
    let mut skipping = false;
    for line in src.lines() {
        let t = line.trim_start();
        if t.starts_with("// f32-only begin") {
            skipping = true;
            continue;
        }
        if t.starts_with("// f32-only end") {
            skipping = false;
            continue;
        }
        if skipping {
            continue;
        }
        let line = match t.strip_prefix("// f64-only: ") {
            Some(code) => code,
            None => line,
        };
        out.push_str(&line.replace("f32", "f64"));
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn f64_source_drops_f32_sections_and_uncomments_f64_lines() {
        let src = "var<storage> a: array<f32>;\n\
                   // f32-only begin\n\
                   var t: texture_2d<f32>;\n\
                   // f32-only end\n\
                   // f32-only begin\n\
                   const TINY: f32 = 1e-12;\n\
                   // f32-only end\n\
                   // f64-only: const TINY: f32 = 1e-24;\n\
                   fn g() -> f32 { return 0.0; }\n";
        let out = f64_source(src);
        assert_eq!(
            out,
            "var<storage> a: array<f64>;\n\
             const TINY: f64 = 1e-24;\n\
             fn g() -> f64 { return 0.0; }\n"
        );
    }
}
