// Block-Jacobi preconditioner z = M^-1 r, M = block diagonal of A. The inverses
// of the diagonal blocks (3x3 for the vertex systems, 1x1 = plain Jacobi for the
// scalar system) are computed on the CPU in f64 at prepare time and uploaded as
// f32. The PCG loop applies M^-1 inside its fused update kernel (pcg.wgsl); this
// standalone kernel is the same operation on its own.
//
// Driven by solver-gpu/src/block_jacobi.rs.
//
// Bindings (group 0):
//   0  P     uniform   rows = block rows, bs = block size (1 or 3), n = rows * bs,
//                      ncols (= NCOLS), groups = ceil(rows / WG); 2-D dispatch,
//                      linear workgroup index wid.x + wid.y * nwg.x, rows past
//                      `rows` do nothing.
//   1  minv  read      rows * bs * bs f32, each inverse block row-major.
//   2  r     read      ncols columns of length n, column-major.
//   3  z     write     z = M^-1 r, same layout.

struct Params {
    rows: u32,
    ncols: u32,
    n: u32,
    groups: u32,
    bs: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

const WG: u32 = 128u;
const CMAX: u32 = 8u;
// Columns handled by this pipeline (1..=CMAX), fixed when the pipeline is
// created: the column loops unroll and the per-column accumulators stay in
// registers. P.ncols must equal it.
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> minv: array<f32>;
@group(0) @binding(2) var<storage, read> r: array<f32>;
@group(0) @binding(3) var<storage, read_write> z: array<f32>;

@compute @workgroup_size(128)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let row = (wid.x + wid.y * nwg.x) * WG + lid;
    if row >= P.rows {
        return;
    }
    let bs = min(P.bs, 3u);
    let ncols = NCOLS;
    var m: array<f32, 9>;
    for (var q = 0u; q < bs * bs; q++) {
        m[q] = minv[row * bs * bs + q];
    }
    for (var c = 0u; c < ncols; c++) {
        let o = c * P.n + row * bs;
        var rv: array<f32, 3>;
        for (var q = 0u; q < bs; q++) {
            rv[q] = r[o + q];
        }
        for (var q = 0u; q < bs; q++) {
            var s = 0.0;
            for (var t = 0u; t < bs; t++) {
                s += m[q * bs + t] * rv[t];
            }
            z[o + q] = s;
        }
    }
}
