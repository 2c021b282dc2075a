// f64 <-> f32 copies of PCG vectors, for the mixed-precision PCG: the iteration
// (vectors, SpMV, scalars) in f64, the AMG V-cycle (amg.wgsl) in f32. Needs the
// adapter feature SHADER_F64 (validated with naga's FLOAT64 capability).
//
// Driven by solver-gpu/src/convert.rs. Per iteration:
//   narrow   r32 = f32(r64)   before the V-cycle (which reads r32, writes z32)
//   widen    z64 = f64(z32)   after it
//
// Bindings (group 0):
//   0  P       uniform   n = length of one column (both vectors hold NCOLS
//                        columns, column-major, stride n).
//   1  wide    rw        the f64 vector (r or z of the f64 PCG).
//   2  narrow  rw        the f32 vector (the V-cycle's input or output).
// One invocation per row (all NCOLS columns), 256 per workgroup, 2-D dispatch
// (linear index gid.x + gid.y * nwg.x * 256); rows past `n` do nothing.

struct ConvertParams {
    n: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

const FWG: u32 = 256u;
// Columns (1..=8), fixed when the pipeline is created.
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: ConvertParams;
@group(0) @binding(1) var<storage, read_write> wide: array<f64>;
@group(0) @binding(2) var<storage, read_write> narrow: array<f32>;

fn entry(gid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return gid.x + gid.y * nwg.x * FWG;
}

@compute @workgroup_size(256)
fn to_f32(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = entry(gid, nwg);
    if i < P.n {
        for (var c = 0u; c < NCOLS; c++) {
            narrow[c * P.n + i] = f32(wide[c * P.n + i]);
        }
    }
}

@compute @workgroup_size(256)
fn to_f64(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = entry(gid, nwg);
    if i < P.n {
        for (var c = 0u; c < NCOLS; c++) {
            wide[c * P.n + i] = f64(narrow[c * P.n + i]);
        }
    }
}
