// Dot products a_c . b_c of ncols column pairs, two passes:
//   `partial`: one invocation per vector index, per-workgroup tree reduction,
//              partials[c * groups + g];
//   `finish`:  a single workgroup of FWG invocations sums the `groups` partials
//              of each column into out[c].
//
// Driven by solver-gpu/src/dot.rs. (The PCG loop has its own finishing kernels in
// pcg.wgsl, which reduce the same partials layout and then update alpha/beta.)
//
// Bindings (group 0):
//   0  P        uniform   rows = n = length of one column, ncols (= NCOLS),
//                         groups = ceil(n / WG); 2-D dispatch of `partial`,
//                         linear workgroup index wid.x + wid.y * nwg.x,
//                         workgroups past `groups` return at once.
//   1  a        read      ncols columns of length n, column-major   (partial)
//   2  b        read      same layout                               (partial)
//   3  partials rw        ncols * groups f32: written by `partial`, read by `finish`
//   4  out      write     ncols f32                                 (finish)

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
const FWG: u32 = 256u;
const CMAX: u32 = 8u;
// Columns handled by this pipeline (1..=CMAX), fixed when the pipeline is
// created: the column loops unroll and the per-column accumulators stay in
// registers. P.ncols must equal it.
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read_write> partials: array<f32>;
@group(0) @binding(4) var<storage, read_write> out: array<f32>;

var<workgroup> red: array<f32, 1024>; // CMAX * WG
var<workgroup> fred: array<f32, 256>; // FWG

@compute @workgroup_size(128)
fn partial(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let g = wid.x + wid.y * nwg.x;
    if g >= P.groups {
        return;
    }
    let ncols = NCOLS;
    let i = g * WG + lid;
    for (var c = 0u; c < ncols; c++) {
        var v = 0.0;
        if i < P.n {
            v = a[c * P.n + i] * b[c * P.n + i];
        }
        red[c * WG + lid] = v;
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

@compute @workgroup_size(256)
fn finish(@builtin(local_invocation_index) lid: u32) {
    let ncols = NCOLS;
    for (var c = 0u; c < ncols; c++) {
        var s = 0.0;
        for (var i = lid; i < P.groups; i += FWG) {
            s += partials[c * P.groups + i];
        }
        fred[lid] = s;
        workgroupBarrier();
        for (var h = FWG / 2u; h > 0u; h >>= 1u) {
            if lid < h {
                fred[lid] += fred[lid + h];
            }
            workgroupBarrier();
        }
        if lid == 0u {
            out[c] = fred[0];
        }
        workgroupBarrier();
    }
}
