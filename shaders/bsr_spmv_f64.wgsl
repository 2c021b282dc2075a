// y = A x in f64 for the 3x3 block-CSR matrix of the mixed-precision PCG (f64
// vectors and scalars, f32 AMG V-cycle), for `ncols` columns at once, fused
// with the per-workgroup partial dot products x . y (p . Ap). Needs SHADER_F64.
//
// Driven by solver-gpu/src/bsr_spmv.rs (`new_f64`).
//
// Each matrix value v is held as two f32, hi = f32(v) and lo = f32(v - hi), read
// back as f64(hi) + f64(lo): a 48-bit significand (relative error <= 2^-48 per
// entry). The hi texture is the f32 PCG's own block texture, so the f64 product
// adds one texture of the same size (lo) and no storage buffer: unlike a scalar
// f64 CSR copy (108 B per block in buffers) it is not bound by the storage
// binding limit (128 MiB on lavapipe), and it is read with texel gathers. The
// mixed-precision solve's accuracy does not rest on the 48 bits: its residuals
// are recomputed on the host in f64 with the exact matrix every round.
//
// The PCG workspace of the mixed solve is scalar (one row per unknown), so this
// kernel takes its parameters and dispatch: P.groups = ceil(n / WG) workgroups,
// of which the first ceil(n / 3 / WG) handle the n / 3 block rows (WG block rows
// each); the others write zero partials, so the finishing reduction over
// P.groups partials per column (pcg.wgsl's finish_alpha) is unchanged.
//
// Bindings (group 0):
//   0  P        uniform   n = length of one column (3 x block rows), ncols
//                         (= NCOLS), groups = ceil(n / WG); the dispatch is 2-D,
//                         linear workgroup index wid.x + wid.y * nwg.x.
//   1  row_ptr  read      block rows + 1 offsets into the blocks (block units).
//   2  lo       texture   RGBA32F, the low parts, texel for texel as `hi`
//                         (.w unused).
//   3  hi       texture   RGBA32F, TW texels per texture row: block k is texels
//                         3k, 3k+1, 3k+2 holding its rows' f32 values and, in
//                         the .w of its first texel, its block column as an f32
//                         value (bsr_spmv.wgsl's layout).
//   4  x        read      f64, ncols columns of length n, column-major.
//   5  y        write     y = A x, same layout; every entry of the first ncols
//                         columns is written.
//   6  partials write     partials[c * groups + g] = sum over the rows of
//                         workgroup g of x_c . y_c (f64).

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
// Columns handled by this pipeline (1..=8), fixed when the pipeline is created.
override NCOLS: u32 = 1u;
// Texels per texture row, as in bsr_spmv.wgsl.
override TW: u32 = 4096u;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> row_ptr: array<u32>;
@group(0) @binding(2) var lo: texture_2d<f32>;
@group(0) @binding(3) var hi: texture_2d<f32>;
@group(0) @binding(4) var<storage, read> x: array<f64>;
@group(0) @binding(5) var<storage, read_write> y: array<f64>;
@group(0) @binding(6) var<storage, read_write> partials: array<f64>;

var<workgroup> red: array<f64, 1024>; // 8 columns * WG

fn at(t: u32) -> vec2<u32> {
    return vec2<u32>(t % TW, t / TW);
}

// Row q of block k in f64 (hi + lo).
fn block_row(t: u32) -> vec3<f64> {
    let h = textureLoad(hi, at(t), 0);
    let l = textureLoad(lo, at(t), 0);
    return vec3<f64>(h.xyz) + vec3<f64>(l.xyz);
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
    let g = wid.x + wid.y * nwg.x;
    if g >= P.groups {
        return;
    }
    let ncols = NCOLS;
    let rows = P.n / 3u;
    if g * WG >= rows {
        // Past the block rows: this workgroup's share of x . y is zero.
        if lid == 0u {
            for (var c = 0u; c < ncols; c++) {
                partials[c * P.groups + g] = 0.0;
            }
        }
        return;
    }
    let row = g * WG + lid;
    var acc: array<f64, 8>;
    if row < rows {
        var yv: array<vec3<f64>, 8>;
        let k0 = row_ptr[row];
        let k1 = row_ptr[row + 1u];
        for (var k = k0; k < k1; k++) {
            let j = u32(textureLoad(hi, at(3u * k), 0).w);
            let m0 = block_row(3u * k);
            let m1 = block_row(3u * k + 1u);
            let m2 = block_row(3u * k + 2u);
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
