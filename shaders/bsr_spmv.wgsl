// y = A x for a full symmetric 3x3 block-CSR matrix, f32, for `ncols` columns at
// once, fused with the per-workgroup partial dot products p . Ap (x . y).
//
// Driven by solver-gpu/src/bsr_spmv.rs.
//
// Bindings (group 0):
//   0  P        uniform   rows = block rows, ncols (= NCOLS), n = 3 * rows (length
//                         of one column), groups = number of workgroups that hold
//                         rows (ceil(rows / WG)); the dispatch is 2-D, so the
//                         linear workgroup index is wid.x + wid.y * nwg.x and
//                         workgroups past `groups` return at once.
//   1  row_ptr  read      rows + 1 offsets into col_idx / vals (block units).
//   2  col_idx  read      block column of each stored block.
//   3  vals     read      9 f32 per block, row-major. Both triangles are stored
//                         (the lower CSC is expanded on upload); rows/columns of
//                         fixed vertices are already the identity.
//   4  x        read      ncols columns of length n, column-major (the search
//                         direction p in PCG).
//   5  y        write     y = A x, same layout (Ap in PCG). Every entry of the
//                         first ncols columns is written.
//   6  partials write     partials[c * groups + g] = sum over the rows of
//                         workgroup g of x_c . y_c; reduced by a second pass
//                         (dot.wgsl or pcg.wgsl).
//
// One invocation per block row: it reads each block of its row once and applies
// it to all ncols columns (the matrix, the dominant memory traffic, is read once
// per iteration whatever the number of right-hand sides).

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
@group(0) @binding(1) var<storage, read> row_ptr: array<u32>;
@group(0) @binding(2) var<storage, read> col_idx: array<u32>;
@group(0) @binding(3) var<storage, read> vals: array<f32>;
@group(0) @binding(4) var<storage, read> x: array<f32>;
@group(0) @binding(5) var<storage, read_write> y: array<f32>;
@group(0) @binding(6) var<storage, read_write> partials: array<f32>;

var<workgroup> red: array<f32, 1024>; // CMAX * WG

fn xv(c: u32, j: u32) -> vec3<f32> {
    let o = c * P.n + 3u * j;
    return vec3<f32>(x[o], x[o + 1u], x[o + 2u]);
}

@compute @workgroup_size(128)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let g = wid.x + wid.y * nwg.x;
    if g >= P.groups {
        return;
    }
    let ncols = NCOLS;
    let row = g * WG + lid;
    var acc: array<f32, 8>;
    if row < P.rows {
        var yv: array<vec3<f32>, 8>;
        let k0 = row_ptr[row];
        let k1 = row_ptr[row + 1u];
        for (var k = k0; k < k1; k++) {
            let j = col_idx[k];
            let b = 9u * k;
            let m0 = vec3<f32>(vals[b], vals[b + 1u], vals[b + 2u]);
            let m1 = vec3<f32>(vals[b + 3u], vals[b + 4u], vals[b + 5u]);
            let m2 = vec3<f32>(vals[b + 6u], vals[b + 7u], vals[b + 8u]);
            for (var c = 0u; c < ncols; c++) {
                let v = xv(c, j);
                yv[c] += vec3<f32>(dot(m0, v), dot(m1, v), dot(m2, v));
            }
        }
        for (var c = 0u; c < ncols; c++) {
            let o = c * P.n + 3u * row;
            let r = yv[c];
            y[o] = r.x;
            y[o + 1u] = r.y;
            y[o + 2u] = r.z;
            acc[c] = dot(r, xv(c, row));
        }
    }
    for (var c = 0u; c < ncols; c++) {
        red[c * WG + lid] = acc[c];
    }
    workgroupBarrier();
    for (var s = WG / 2u; s > 0u; s >>= 1u) {
        if lid < s {
            for (var c = 0u; c < ncols; c++) {
                red[c * WG + lid] += red[c * WG + lid + s];
            }
        }
        workgroupBarrier();
    }
    if lid == 0u {
        for (var c = 0u; c < ncols; c++) {
            partials[c * P.groups + g] = red[c * WG];
        }
    }
}
