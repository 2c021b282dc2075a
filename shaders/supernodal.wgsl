// Triangular solves with a supernodal Cholesky factor, the shape systems'
// preconditioner z = M^-1 r with M = P^T L L^T P (x) I_bs: the factor of the
// isotropic part K of the shape matrix (solver_cpu::SupernodalFactor, made on
// the host once per system kind) applied to x, y and z of every PCG column.
//
// Driven by solver-gpu/src/supernodal.rs. One application:
//   gather     w = P r                                   (flat, every entry)
//   forward    L y = w, one dispatch per level of the    (a workgroup per
//              supernodal elimination tree, leaves first   supernode)
//   backward   L^T x = y, one dispatch per level, root first
//   scatter    z = P^T x                                 (flat)
// Within a level no supernode depends on another, and no two write the same
// entry (no atomics). Forward, a supernode first pulls the updates its
// descendants left for its rows in `contrib` (lower levels, done), solves its
// diagonal block, then leaves one update per row below its block, L[m + r, :] y,
// in its own slots of `contrib`. Backward, it reads only its ancestors' rows,
// which are final, and its own.
//
// Supernode s (5 u32 at idx[o_sn + 5 s]): c0 its first column, m columns, q
// rows below its diagonal block (idx[o_rows + ro ..][..q], permuted
// numbering), its values the dense column-major (m + q) x m block at vals[vo]:
// L[i, k] of the supernode at vals[vo + k (m + q) + i].
//
// Bindings (group 0):
//   0  P        uniform  first, count: this level's supernodes (idx[first ..]);
//                        nv: rows of K (vertices); stride: length of one PCG
//                        column (nv * bs); bs: unknowns per vertex (3); the
//                        offsets of the index sections in `idx`.
//   1  idx      read     u32 sections: supernodes by level (at 0), per supernode
//                        c0, m, q, ro, vo (o_sn), the rows below each diagonal
//                        block (o_rows), perm[new] = old vertex (o_perm), and per
//                        row i the slots e of `rows` holding i:
//                        tpos[tptr[i] .. tptr[i + 1]] (o_tptr, o_tpos).
//   2  vals     read     the factor's values (f32; this shader is also
//                        compiled in f64, every f32 made f64, for the f64
//                        factor and the mixed-precision PCG's f64 vectors).
//   3  w        rw       work vector, nv x C (C = bs * NCOLS scalar columns;
//                        entry (i, c) at i * C + c: a row's columns adjacent).
//   4  r        read     PCG residual, NCOLS columns of stride `stride`.
//   5  z        rw       preconditioned residual, same layout.
//   6  contrib  rw       one update per slot e of `rows` and column: at e * C + c.
// Supernode kernels: one workgroup of WG per supernode of the level, 2-D
// dispatch (linear workgroup index wid.x + wid.y * nwg.x); flat kernels: one
// invocation per entry of w, 256 per workgroup.

struct Params {
    first: u32,
    count: u32,
    nv: u32,
    stride: u32,
    bs: u32,
    o_sn: u32,
    o_rows: u32,
    o_perm: u32,
    o_tptr: u32,
    o_tpos: u32,
    pad0: u32,
    pad1: u32,
}

const WG: u32 = 128u;
const FWG: u32 = 256u;
// Columns of a diagonal block solved per step by one invocation per scalar
// column (registers), between the parallel updates of the block's other rows.
const TILE: u32 = 32u;
// PCG columns (1..=8), fixed when the pipeline is created.
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> idx: array<u32>;
@group(0) @binding(2) var<storage, read> vals: array<f32>;
@group(0) @binding(3) var<storage, read_write> w: array<f32>;
@group(0) @binding(4) var<storage, read> r: array<f32>;
@group(0) @binding(5) var<storage, read_write> z: array<f32>;
@group(0) @binding(6) var<storage, read_write> contrib: array<f32>;

// The PCG entry of w's entry t: column pc of r / z, vertex perm[i], unknown k.
fn pcg_index(t: u32) -> u32 {
    let cc = P.bs * NCOLS;
    let i = t / cc;
    let c = t % cc;
    return (c / P.bs) * P.stride + idx[P.o_perm + i] * P.bs + c % P.bs;
}

@compute @workgroup_size(256)
fn gather(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = gid.x + gid.y * nwg.x * FWG;
    if t < P.nv * P.bs * NCOLS {
        w[t] = r[pcg_index(t)];
    }
}

@compute @workgroup_size(256)
fn scatter(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = gid.x + gid.y * nwg.x * FWG;
    if t < P.nv * P.bs * NCOLS {
        z[pcg_index(t)] = w[t];
    }
}

// L y = w for the supernodes of one level: the descendants' updates pulled in,
// the diagonal block solved by tiles (each tile by one invocation per scalar
// column, then the block's rows below it updated in parallel), then the
// updates of the rows below the block left in `contrib`.
@compute @workgroup_size(128)
fn forward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let g = wid.x + wid.y * nwg.x;
    if g >= P.count {
        return;
    }
    let s = idx[P.first + g];
    let c0 = idx[P.o_sn + 5u * s];
    let m = idx[P.o_sn + 5u * s + 1u];
    let q = idx[P.o_sn + 5u * s + 2u];
    let ro = idx[P.o_sn + 5u * s + 3u];
    let vo = idx[P.o_sn + 5u * s + 4u];
    let cc = P.bs * NCOLS;
    let nr = m + q;
    let own = m * cc;
    for (var t = lid; t < own; t += WG) {
        let row = c0 + t / cc;
        let c = t % cc;
        var acc = w[row * cc + c];
        let e1 = idx[P.o_tptr + row + 1u];
        for (var e = idx[P.o_tptr + row]; e < e1; e++) {
            acc -= contrib[idx[P.o_tpos + e] * cc + c];
        }
        w[row * cc + c] = acc;
    }
    storageBarrier();
    for (var a = 0u; a < m; a += TILE) {
        let b = min(a + TILE, m);
        if lid < cc {
            var x: array<f32, TILE>;
            for (var k = a; k < b; k++) {
                var t = w[(c0 + k) * cc + lid];
                for (var j = a; j < k; j++) {
                    t -= vals[vo + j * nr + k] * x[j - a];
                }
                let v = t / vals[vo + k * nr + k];
                x[k - a] = v;
                w[(c0 + k) * cc + lid] = v;
            }
        }
        storageBarrier();
        let cnt = (m - b) * cc;
        for (var t = lid; t < cnt; t += WG) {
            let i = b + t / cc;
            let c = t % cc;
            var acc = w[(c0 + i) * cc + c];
            for (var k = a; k < b; k++) {
                acc -= vals[vo + k * nr + i] * w[(c0 + k) * cc + c];
            }
            w[(c0 + i) * cc + c] = acc;
        }
        storageBarrier();
    }
    let below = q * cc;
    for (var t = lid; t < below; t += WG) {
        let rr = t / cc;
        let c = t % cc;
        var acc: f32 = 0.0;
        for (var k = 0u; k < m; k++) {
            acc += vals[vo + k * nr + m + rr] * w[(c0 + k) * cc + c];
        }
        contrib[(ro + rr) * cc + c] = acc;
    }
}

// L^T x = y for the supernodes of one level: first the rows below the block
// (ancestors, solved): w[k] -= L[m + r, k] x[rows[r]]; then the diagonal block
// by tiles from the last, each tile solved by one invocation per scalar column,
// then the block's rows before it updated in parallel.
@compute @workgroup_size(128)
fn backward(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let g = wid.x + wid.y * nwg.x;
    if g >= P.count {
        return;
    }
    let s = idx[P.first + g];
    let c0 = idx[P.o_sn + 5u * s];
    let m = idx[P.o_sn + 5u * s + 1u];
    let q = idx[P.o_sn + 5u * s + 2u];
    let ro = idx[P.o_sn + 5u * s + 3u];
    let vo = idx[P.o_sn + 5u * s + 4u];
    let cc = P.bs * NCOLS;
    let nr = m + q;
    let own = m * cc;
    for (var t = lid; t < own; t += WG) {
        let k = t / cc;
        let c = t % cc;
        var acc = w[(c0 + k) * cc + c];
        for (var rr = 0u; rr < q; rr++) {
            acc -= vals[vo + k * nr + m + rr] * w[idx[P.o_rows + ro + rr] * cc + c];
        }
        w[(c0 + k) * cc + c] = acc;
    }
    storageBarrier();
    var b = m;
    loop {
        if b == 0u {
            break;
        }
        let a = select(0u, b - TILE, b > TILE);
        if lid < cc {
            var x: array<f32, TILE>;
            for (var kk = b; kk > a; kk--) {
                let k = kk - 1u;
                var t = w[(c0 + k) * cc + lid];
                for (var j = k + 1u; j < b; j++) {
                    t -= vals[vo + k * nr + j] * x[j - a];
                }
                let v = t / vals[vo + k * nr + k];
                x[k - a] = v;
                w[(c0 + k) * cc + lid] = v;
            }
        }
        storageBarrier();
        let cnt = a * cc;
        for (var t = lid; t < cnt; t += WG) {
            let k = t / cc;
            let c = t % cc;
            var acc = w[(c0 + k) * cc + c];
            for (var i = a; i < b; i++) {
                acc -= vals[vo + k * nr + i] * w[(c0 + i) * cc + c];
            }
            w[(c0 + k) * cc + c] = acc;
        }
        storageBarrier();
        b = a;
    }
}
