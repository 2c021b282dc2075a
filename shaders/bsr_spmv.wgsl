// y = A x for a full symmetric 3x3 block-CSR matrix, f32, for `ncols` columns at
// once, fused with the per-workgroup partial dot products p . Ap (x . y).
//
// Driven by solver-gpu/src/bsr_spmv.rs.
//
// The matrix is split by block rows into chunks whose values each fit one
// storage binding (one chunk unless the matrix passes the adapter's
// max_storage_buffer_binding_size); one dispatch per chunk, each with its own
// bind group (its `vals`, `cols` and `C`), the rest shared.
//
// Bindings (group 0):
//   0  P        uniform   n = 3 x block rows (length and stride of one column),
//                         ncols (= NCOLS), groups = partial-sum slots per
//                         column (the stride of `partials`).
//   1  row_ptr  read      block rows + 1 offsets into the blocks (block units,
//                         of the whole matrix).
//   2  C        uniform   this chunk: block rows row0..row1, group0 = the
//                         partial slot of its first workgroup, block0 = its
//                         first block (block k is at k - block0 in 3 and 7).
//                         The dispatch is 2-D: local workgroup index
//                         wid.x + wid.y * nwg.x, slot group0 + that index;
//                         workgroups past P.groups return at once, those past
//                         row1 write zero partials.
//   3  vals     read      9 f32 per block of the chunk, row-major (36 bytes).
//                         Both triangles are stored (the lower CSC is expanded
//                         on upload); rows/columns of fixed vertices are
//                         already the identity.
//   4  x        read      f32, ncols columns of length n, column-major (the
//                         search direction p in PCG, read in place).
//   5  y        write     y = A x, same layout (Ap in PCG). Every entry of the
//                         chunk's rows in the first ncols columns is written.
//   6  partials write     partials[c * groups + g] = sum over the rows of
//                         workgroup (slot) g of x_c . y_c; reduced by a second
//                         pass (dot.wgsl or pcg.wgsl).
//   7  cols     read      u32 block column per block of the chunk.
//
// One invocation per block row: it reads each block of its row once (40
// bytes: 9 values and a column, the least a block can be stored in) and
// applies it to all ncols columns, so the matrix, the dominant memory
// traffic, is read once per product whatever the number of right-hand sides.

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

struct Chunk {
    row0: u32,
    row1: u32,
    group0: u32,
    block0: u32,
}

const WG: u32 = 128u;
const CMAX: u32 = 8u;
// Columns handled by this pipeline (1..=CMAX), fixed when the pipeline is
// created: the column loops unroll and the per-column accumulators stay in
// registers. P.ncols must equal it.
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> row_ptr: array<u32>;
@group(0) @binding(2) var<uniform> C: Chunk;
@group(0) @binding(3) var<storage, read> vals: array<f32>;
@group(0) @binding(4) var<storage, read> x: array<f32>;
@group(0) @binding(5) var<storage, read_write> y: array<f32>;
@group(0) @binding(6) var<storage, read_write> partials: array<f32>;
@group(0) @binding(7) var<storage, read> cols: array<u32>;

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
    let gl = wid.x + wid.y * nwg.x;
    let g = C.group0 + gl;
    if g >= P.groups {
        return;
    }
    let ncols = NCOLS;
    let row = C.row0 + gl * WG + lid;
    var acc: array<f32, 8>;
    if row < C.row1 {
        var yv: array<vec3<f32>, 8>;
        let k0 = row_ptr[row] - C.block0;
        let k1 = row_ptr[row + 1u] - C.block0;
        for (var k = k0; k < k1; k++) {
            let j = cols[k];
            let o = 9u * k;
            let m0 = vec3<f32>(vals[o], vals[o + 1u], vals[o + 2u]);
            let m1 = vec3<f32>(vals[o + 3u], vals[o + 4u], vals[o + 5u]);
            let m2 = vec3<f32>(vals[o + 6u], vals[o + 7u], vals[o + 8u]);
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
    // Two-level sum: 16 invocations add 8 values each, then one adds the 16
    // (two barriers instead of the seven of a tree).
    workgroupBarrier();
    if lid < 16u {
        for (var c = 0u; c < ncols; c++) {
            var s = 0.0;
            for (var q = 0u; q < WG; q += 16u) {
                s += red[c * WG + lid + q];
            }
            red[c * WG + lid] = s;
        }
    }
    workgroupBarrier();
    if lid == 0u {
        for (var c = 0u; c < ncols; c++) {
            var s = 0.0;
            for (var q = 0u; q < 16u; q++) {
                s += red[c * WG + q];
            }
            partials[c * P.groups + g] = s;
        }
    }
}
