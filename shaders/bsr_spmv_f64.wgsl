// y = A x in f64 for the 3x3 block-CSR matrix of the mixed-precision PCG (f64
// vectors and scalars, f32 AMG V-cycle), for `ncols` columns at once, fused
// with the per-workgroup partial dot products x . y (p . Ap). Needs SHADER_F64.
//
// Driven by solver-gpu/src/bsr_spmv.rs (`new_f64`).
//
// Each matrix value v is held as two f32, hi = f32(v) and lo = f32(v - hi), read
// back as f64(hi) + f64(lo): a 48-bit significand (relative error <= 2^-48 per
// entry). The hi buffers are the f32 PCG's own block values (bsr_spmv.wgsl's
// layout, shared with its columns and chunks), so the f64 product adds one
// buffer of 36 bytes a block (lo): 76 bytes a block read, the least for f64
// values (72) and a u32 column. The mixed-precision solve's accuracy does not
// rest on the 48 bits: its residuals are recomputed in f64 with the exact matrix
// every round, on the GPU from the f64 lower blocks (refine_product.wgsl), or on
// the host where those are not on the GPU.
//
// As in bsr_spmv.wgsl the matrix is split by block rows into chunks that each
// fit one storage binding, one dispatch per chunk.
//
// The PCG workspace of the mixed solve is scalar (one row per unknown), so this
// kernel takes its parameters: P.groups (at least the chunks' workgroups)
// partial slots per column. The last chunk's dispatch reaches P.groups; its
// workgroups past its rows write zero partials, so the finishing reduction over
// P.groups partials per column (pcg.wgsl's finish_alpha) is unchanged.
//
// Bindings (group 0):
//   0  P        uniform   n = length of one column (3 x block rows), ncols
//                         (= NCOLS), groups = partial slots per column.
//   1  row_ptr  read      block rows + 1 offsets into the blocks (block units,
//                         of the whole matrix).
//   2  lo       read      f32, the low parts, value for value as `hi`.
//   3  hi       read      f32, 9 per block of the chunk, row-major.
//   4  x        read      f64, ncols columns of length n, column-major.
//   5  y        write     y = A x, same layout; every entry of the chunk's rows
//                         in the first ncols columns is written.
//   6  partials write     partials[c * groups + g] = sum over the rows of
//                         workgroup (slot) g of x_c . y_c (f64).
//   7  cols     read      u32 block column per block of the chunk.
//   8  C        uniform   this chunk (bsr_spmv.wgsl's `C`): block rows
//                         row0..row1, group0, block0. 2-D dispatch, local
//                         workgroup index wid.x + wid.y * nwg.x.

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
// Columns handled by this pipeline (1..=8), fixed when the pipeline is created.
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> row_ptr: array<u32>;
@group(0) @binding(2) var<storage, read> lo: array<f32>;
@group(0) @binding(3) var<storage, read> hi: array<f32>;
@group(0) @binding(4) var<storage, read> x: array<f64>;
@group(0) @binding(5) var<storage, read_write> y: array<f64>;
@group(0) @binding(6) var<storage, read_write> partials: array<f64>;
@group(0) @binding(7) var<storage, read> cols: array<u32>;
@group(0) @binding(8) var<uniform> C: Chunk;

var<workgroup> red: array<f64, 1024>; // 8 columns * WG

// Row q of the block at value offset o, in f64 (hi + lo).
fn block_row(o: u32) -> vec3<f64> {
    let h = vec3<f64>(f64(hi[o]), f64(hi[o + 1u]), f64(hi[o + 2u]));
    let l = vec3<f64>(f64(lo[o]), f64(lo[o + 1u]), f64(lo[o + 2u]));
    return h + l;
}

fn xv(c: u32, j: u32) -> vec3<f64> {
    let o = c * P.n + 3u * j;
    return vec3<f64>(x[o], x[o + 1u], x[o + 2u]);
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
    var acc: array<f64, 8>;
    if row < C.row1 {
        var yv: array<vec3<f64>, 8>;
        let k0 = row_ptr[row] - C.block0;
        let k1 = row_ptr[row + 1u] - C.block0;
        for (var k = k0; k < k1; k++) {
            let j = cols[k];
            let m0 = block_row(9u * k);
            let m1 = block_row(9u * k + 3u);
            let m2 = block_row(9u * k + 6u);
            for (var c = 0u; c < ncols; c++) {
                let v = xv(c, j);
                yv[c] += vec3<f64>(dot(m0, v), dot(m1, v), dot(m2, v));
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
    // The two-level sum of bsr_spmv.wgsl (two barriers).
    workgroupBarrier();
    if lid < 16u {
        for (var c = 0u; c < ncols; c++) {
            var s: f64 = 0.0;
            for (var q = 0u; q < WG; q += 16u) {
                s += red[c * WG + lid + q];
            }
            red[c * WG + lid] = s;
        }
    }
    workgroupBarrier();
    if lid == 0u {
        for (var c = 0u; c < ncols; c++) {
            var s: f64 = 0.0;
            for (var q = 0u; q < 16u; q++) {
                s += red[c * WG + q];
            }
            partials[c * P.groups + g] = s;
        }
    }
}
