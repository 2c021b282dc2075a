// The lower-triangle 3x3 blocks of a shape matrix in isotropic-plus-ring form,
// A = K (x) I3 + sum_i R_i^T C_i R_i, summed on the GPU from K's values and
// the 3x3 symmetric C_i (driven by solver-gpu/src/expand_blocks.rs; its
// `expand_blocks.wgsl` then writes both triangles from them). Per matrix the
// host sends 8 bytes per lower entry of K and 48 per ring instead of 72 per
// lower block. Each lower block s is
//   K_s I3 + sum over the ring pairs (p, q) of s, in ring order, of f C_i,
// with f = R_ip R_iq fixed for a run (the rings are the input's Laplacian):
// the order and arithmetic of the host's sum (`HostMatrix::fill_shape`).
// Where the rows are short enough (C.bits > 0) a pair comes packed in one
// u32, its ring i and the positions a, b of p and q in row i, and its
// weight is formed here, R_ia R_ib from the rows' weights: the host's
// product (`SparseRows::pairs`), 4 bytes a pair instead of 12.
// Where the matrices name a constant term (E_m's Hessian S Mt^-1 S, kept
// out of K: `IsoRingSym3::laplacian_square`), its value per lower entry,
// uploaded once per model, is added to K's first: K_s + square_s.
//
// The lower blocks may be cut into parts of one storage binding each
// (`LowerParts`): one dispatch per part, its blocks' ring pairs in buffers of
// their own.
//
// Bindings (group 0):
//   0  C      uniform   this part: its lower blocks block0 .. block0 + slots,
//                       their first ring pair pair0; square: see 7; bits:
//                       see 4 (0: the pairs are not packed).
//   1  iso    read      f64, K's value per lower entry (input CSC order).
//   2  ring_c read      f64, 6 per ring: C_i as (xx, yy, zz, xy, xz, yz).
//   3  start  read      u32, lower blocks + 1: block s's ring pairs are
//                       start[s] .. start[s + 1] (all parts' numbering).
//   4  ring   read      u32 per ring pair of the part (pair t at t - pair0):
//                       bits 0, the ring i it belongs to; else packed,
//                       (i << 2 bits) | (a << bits) | b.
//   5  f      read      f64: bits 0, per ring pair of the part, its weight
//                       R_ip R_iq; else every row's weights, the diagonal
//                       first (row i at row_start[i]), all parts alike.
//   6  lower  rw        f64, 9 per lower block of the part (row-major; block s
//                       at s - block0), written whole.
//   7  square read      f64, the constant term's value per lower entry
//                       (read only where C.square is 1).
//   8  row_start read   u32 per ring + 1: where row i's weights start in f
//                       (read only where C.bits > 0).
// One invocation per lower block of the part, 256 per workgroup, 2-D
// dispatch (linear index gid.x + gid.y * nwg.x * 256); invocations past the
// blocks return.

struct SumParams {
    slots: u32,
    // 1: add `square` to K's values; 0: no constant term.
    square: u32,
    block0: u32,
    pair0: u32,
    bits: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

const FWG: u32 = 256u;
// Set by the host for every kernel (columns); one matrix here, unused.
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> C: SumParams;
@group(0) @binding(1) var<storage, read> iso: array<f64>;
@group(0) @binding(2) var<storage, read> ring_c: array<f64>;
@group(0) @binding(3) var<storage, read> start: array<u32>;
@group(0) @binding(4) var<storage, read> ring: array<u32>;
@group(0) @binding(5) var<storage, read> f: array<f64>;
@group(0) @binding(6) var<storage, read_write> lower: array<f64>;
@group(0) @binding(7) var<storage, read> square: array<f64>;
@group(0) @binding(8) var<storage, read> row_start: array<u32>;

@compute @workgroup_size(256)
fn sum_shape_blocks(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let local = gid.x + gid.y * nwg.x * FWG;
    if local >= C.slots || NCOLS == 0u {
        return;
    }
    let s = C.block0 + local;
    var k = iso[s];
    if C.square != 0u {
        k = k + square[s];
    }
    // Row-major 3x3: xx xy xz / xy yy yz / xz yz zz.
    var m = array<f64, 9>(k, f64(0.0), f64(0.0), f64(0.0), k, f64(0.0), f64(0.0), f64(0.0), k);
    for (var t = start[s]; t < start[s + 1u]; t++) {
        var i = ring[t - C.pair0];
        var w: f64;
        if C.bits == 0u {
            w = f[t - C.pair0];
        } else {
            let mask = (1u << C.bits) - 1u;
            let r = row_start[i >> (2u * C.bits)];
            w = f[r + ((i >> C.bits) & mask)] * f[r + (i & mask)];
            i = i >> (2u * C.bits);
        }
        let c = 6u * i;
        m[0] += w * ring_c[c];
        m[1] += w * ring_c[c + 3u];
        m[2] += w * ring_c[c + 4u];
        m[3] += w * ring_c[c + 3u];
        m[4] += w * ring_c[c + 1u];
        m[5] += w * ring_c[c + 5u];
        m[6] += w * ring_c[c + 4u];
        m[7] += w * ring_c[c + 5u];
        m[8] += w * ring_c[c + 2u];
    }
    for (var q = 0u; q < 9u; q++) {
        lower[9u * local + q] = m[q];
    }
}
