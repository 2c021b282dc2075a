// Row scaling v = diag(m) v between the two V-cycles of the squared-Laplacian
// preconditioner z = B^-1 Mt B^-1 r (driven by solver-gpu/src/scale_rows.rs).
//
// Bindings (group 0):
//   0  P   uniform   n = length of one column, bs = unknowns per block row
//                    (3: x, y, z of a vertex share its m).
//   1  m   read      one f32 per block row (Mt's diagonal).
//   2  v   rw        NCOLS columns, column-major, stride n; scaled in place.
// One invocation per row (all NCOLS columns), 256 per workgroup, 2-D dispatch
// (linear index gid.x + gid.y * nwg.x * 256); rows past `n` do nothing.

struct ScaleParams {
    n: u32,
    bs: u32,
    pad0: u32,
    pad1: u32,
}

const FWG: u32 = 256u;
// Columns (1..=8), fixed when the pipeline is created.
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: ScaleParams;
@group(0) @binding(1) var<storage, read> m: array<f32>;
@group(0) @binding(2) var<storage, read_write> v: array<f32>;

@compute @workgroup_size(256)
fn scale_rows(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * FWG;
    if i < P.n {
        let s = m[i / P.bs];
        for (var c = 0u; c < NCOLS; c++) {
            v[c * P.n + i] = s * v[c * P.n + i];
        }
    }
}
