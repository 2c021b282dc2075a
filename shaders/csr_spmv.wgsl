// y = A x for a full symmetric scalar CSR matrix, f32, for `ncols` columns at
// once, fused with the per-workgroup partial dot products x . y (p . Ap).
// Used for the face-adjacency scale-factor system (about 4 off-diagonals a row).
//
// Driven by solver-gpu/src/csr_spmv.rs.
//
// Bindings (group 0):
//   0  P        uniform   rows, ncols (= NCOLS), n = rows (length of one column),
//                         groups = ceil(rows / WG); 2-D dispatch, linear
//                         workgroup index wid.x + wid.y * nwg.x, workgroups past
//                         `groups` return at once.
//   1  row_ptr  read      rows + 1 offsets into col_idx / vals.
//   2  col_idx  read      column of each stored entry.
//   3  vals     read      f32 value of each entry (both triangles stored).
//   4  x        read      ncols columns of length n, column-major.
//   5  y        write     y = A x, same layout.
//   6  partials write     partials[c * groups + g] = sum over the rows of
//                         workgroup g of x_c[i] * y_c[i].
//
// One invocation per row; each matrix entry is read once for all columns.

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
        var yv: array<f32, 8>;
        let k0 = row_ptr[row];
        let k1 = row_ptr[row + 1u];
        for (var k = k0; k < k1; k++) {
            let j = col_idx[k];
            let a = vals[k];
            for (var c = 0u; c < ncols; c++) {
                yv[c] += a * x[c * P.n + j];
            }
        }
        for (var c = 0u; c < ncols; c++) {
            let o = c * P.n + row;
            y[o] = yv[c];
            acc[c] = yv[c] * x[o];
        }
    }
    for (var c = 0u; c < ncols; c++) {
        red[c * WG + lid] = acc[c];
    }
    // Two-level sum (two barriers; see bsr_spmv.wgsl).
    workgroupBarrier();
    if lid < 16u {
        for (var c = 0u; c < ncols; c++) {
            var s: f32 = 0.0;
            for (var q = 0u; q < WG; q += 16u) {
                s += red[c * WG + lid + q];
            }
            red[c * WG + lid] = s;
        }
    }
    workgroupBarrier();
    if lid == 0u {
        for (var c = 0u; c < ncols; c++) {
            var s: f32 = 0.0;
            for (var q = 0u; q < 16u; q++) {
                s += red[c * WG + q];
            }
            partials[c * P.groups + g] = s;
        }
    }
}
