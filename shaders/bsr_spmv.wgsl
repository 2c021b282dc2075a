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
//   1  row_ptr  read      rows + 1 offsets into the blocks (block units).
//   3  blocks   texture   RGBA32F, TW texels per texture row; block k is texels
//                         3k, 3k+1, 3k+2 (texel t at (t % TW, t / TW)) holding
//                         its rows (m_q0, m_q1, m_q2, .) and, in the .w of its
//                         first texel, its block column as an f32 value (exact:
//                         columns stay below 2^24; a value, not bit pattern,
//                         so no driver's denormal flush can touch it).
//                         Both triangles are stored (the lower CSC is expanded
//                         on upload); rows/columns of fixed vertices are already
//                         the identity.
//   4  x        texture   RGBA32F, TW texels per row: column c, vertex j at
//                         texel t = c * rows + j holding (x_3j, x_3j+1, x_3j+2,
//                         .) (the search direction p in PCG, stored there by
//                         pcg.wgsl's direction_tex).
//   5  y        write     y = A x, same layout (Ap in PCG). Every entry of the
//                         first ncols columns is written.
//   6  partials write     partials[c * groups + g] = sum over the rows of
//                         workgroup g of x_c . y_c; reduced by a second pass
//                         (dot.wgsl or pcg.wgsl).
//
// One invocation per block row: it reads each block of its row once and applies
// it to all ncols columns (the matrix, the dominant memory traffic, is read once
// per iteration whatever the number of right-hand sides). The blocks are read
// from a texture: on llvmpipe a texel fetch is a vector gather, while a
// storage-buffer load with a per-invocation address is a loop over the lanes
// with a bounds check per component (1.7-2x slower SpMV at 50k block rows in a
// side-by-side test of the two layouts); and a texture is not bound by the
// storage-buffer binding limit. The gathered x is read from a texture too, for
// the same reason.

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
// Texels per texture row: a power of two set by the host from the device's
// max_texture_dimension_2d.
override TW: u32 = 4096u;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> row_ptr: array<u32>;
@group(0) @binding(3) var blocks: texture_2d<f32>;
@group(0) @binding(4) var xt: texture_2d<f32>;
@group(0) @binding(5) var<storage, read_write> y: array<f32>;
@group(0) @binding(6) var<storage, read_write> partials: array<f32>;

var<workgroup> red: array<f32, 1024>; // CMAX * WG

fn texel(t: u32) -> vec4<f32> {
    return textureLoad(blocks, vec2<u32>(t % TW, t / TW), 0);
}

fn xv(c: u32, j: u32) -> vec3<f32> {
    let t = c * P.rows + j;
    return textureLoad(xt, vec2<u32>(t % TW, t / TW), 0).xyz;
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
            let t0 = texel(3u * k);
            let j = u32(t0.w);
            let m0 = t0.xyz;
            let m1 = texel(3u * k + 1u).xyz;
            let m2 = texel(3u * k + 2u).xyz;
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
    // (two barriers instead of the seven of a tree: on llvmpipe every barrier
    // suspends and resumes each SIMD slice of the workgroup).
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
