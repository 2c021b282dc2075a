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
// Within a level no supernode depends on another: forward, a supernode's
// rows only receive updates from its descendants (lower levels) and it
// pushes its own updates to its ancestors' rows (higher levels, with an
// atomic add: several supernodes of a level may share an ancestor row);
// backward, it reads only its ancestors' rows, which are final.
//
// Supernode s (5 u32 at sn[5 s]): c0 its first column, m columns, q rows
// below its diagonal block (rows[ro .. ro + q], permuted numbering), its
// values the dense column-major (m + q) x m block at vals[vo]: L[i, k] of
// the supernode at vals[vo + k (m + q) + i].
//
// Bindings (group 0):
//   0  P      uniform  first, count: this level's supernodes in `order`;
//                      nv: rows of K (vertices); stride: length of one PCG
//                      column (nv * bs); bs: unknowns per vertex (3).
//   1  order  read     supernodes sorted by level.
//   2  sn     read     per supernode c0, m, q, ro, vo.
//   3  rows   read     the rows below each supernode's diagonal block.
//   4  vals   read     the factor's values (f32).
//   5  perm   read     perm[new] = old vertex.
//   6  w      rw       work vector, nv x C (C = bs * NCOLS scalar columns;
//                      entry (i, c) at i * C + c: a row's columns adjacent),
//                      f32 bits in atomic u32 (the forward push adds atomically).
//   7  r      read     PCG residual, NCOLS columns of stride `stride`.
//   8  z      rw       preconditioned residual, same layout.
// Supernode kernels: one workgroup of WG per supernode of the level, 2-D
// dispatch (linear workgroup index wid.x + wid.y * nwg.x); flat kernels: one
// invocation per entry of w, 256 per workgroup.

struct Params {
    first: u32,
    count: u32,
    nv: u32,
    stride: u32,
    bs: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

const WG: u32 = 128u;
const FWG: u32 = 256u;
// Columns of a diagonal block solved per step by one invocation per scalar
// column (registers), between the parallel updates of the rows below.
const TILE: u32 = 32u;
// PCG columns (1..=8), fixed when the pipeline is created.
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> order: array<u32>;
@group(0) @binding(2) var<storage, read> sn: array<u32>;
@group(0) @binding(3) var<storage, read> rows: array<u32>;
@group(0) @binding(4) var<storage, read> vals: array<f32>;
@group(0) @binding(5) var<storage, read> perm: array<u32>;
@group(0) @binding(6) var<storage, read_write> w: array<atomic<u32>>;
@group(0) @binding(7) var<storage, read> r: array<f32>;
@group(0) @binding(8) var<storage, read_write> z: array<f32>;

fn wload(i: u32) -> f32 {
    return bitcast<f32>(atomicLoad(&w[i]));
}

fn wstore(i: u32, v: f32) {
    atomicStore(&w[i], bitcast<u32>(v));
}

fn wadd(i: u32, v: f32) {
    var old = atomicLoad(&w[i]);
    loop {
        let res = atomicCompareExchangeWeak(&w[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if res.exchanged {
            break;
        }
        old = res.old_value;
    }
}

// The PCG entry of w's entry t: column pc of r / z, vertex perm[i], unknown k.
fn pcg_index(t: u32) -> u32 {
    let cc = P.bs * NCOLS;
    let i = t / cc;
    let c = t % cc;
    return (c / P.bs) * P.stride + perm[i] * P.bs + c % P.bs;
}

@compute @workgroup_size(256)
fn gather(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = gid.x + gid.y * nwg.x * FWG;
    if t < P.nv * P.bs * NCOLS {
        wstore(t, r[pcg_index(t)]);
    }
}

@compute @workgroup_size(256)
fn scatter(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = gid.x + gid.y * nwg.x * FWG;
    if t < P.nv * P.bs * NCOLS {
        z[pcg_index(t)] = wload(t);
    }
}

// L y = w for the supernodes of one level: the diagonal block by tiles (each
// tile solved by one invocation per scalar column, then the block's rows below
// it updated in parallel), then the rows below the block pushed to the
// ancestors: w[rows[r]] -= L[m + r, :] y.
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
    let s = order[P.first + g];
    let c0 = sn[5u * s];
    let m = sn[5u * s + 1u];
    let q = sn[5u * s + 2u];
    let ro = sn[5u * s + 3u];
    let vo = sn[5u * s + 4u];
    let cc = P.bs * NCOLS;
    let nr = m + q;
    for (var a = 0u; a < m; a += TILE) {
        let b = min(a + TILE, m);
        if lid < cc {
            var x: array<f32, TILE>;
            for (var k = a; k < b; k++) {
                var t = wload((c0 + k) * cc + lid);
                for (var j = a; j < k; j++) {
                    t -= vals[vo + j * nr + k] * x[j - a];
                }
                let v = t / vals[vo + k * nr + k];
                x[k - a] = v;
                wstore((c0 + k) * cc + lid, v);
            }
        }
        storageBarrier();
        let cnt = (m - b) * cc;
        for (var t = lid; t < cnt; t += WG) {
            let i = b + t / cc;
            let c = t % cc;
            var acc = 0.0;
            for (var k = a; k < b; k++) {
                acc += vals[vo + k * nr + i] * wload((c0 + k) * cc + c);
            }
            let idx = (c0 + i) * cc + c;
            wstore(idx, wload(idx) - acc);
        }
        storageBarrier();
    }
    let cnt = q * cc;
    for (var t = lid; t < cnt; t += WG) {
        let rr = t / cc;
        let c = t % cc;
        var acc = 0.0;
        for (var k = 0u; k < m; k++) {
            acc += vals[vo + k * nr + m + rr] * wload((c0 + k) * cc + c);
        }
        wadd(rows[ro + rr] * cc + c, -acc);
    }
}

// L^T x = y for the supernodes of one level: first the rows below the block
// (ancestors, solved): w[k] -= L[m + r, k] x[rows[r]]; then the diagonal
// block by tiles from the last, each tile's columns first updated in parallel
// with the rows after it, then solved by one invocation per scalar column.
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
    let s = order[P.first + g];
    let c0 = sn[5u * s];
    let m = sn[5u * s + 1u];
    let q = sn[5u * s + 2u];
    let ro = sn[5u * s + 3u];
    let vo = sn[5u * s + 4u];
    let cc = P.bs * NCOLS;
    let nr = m + q;
    let cnt = m * cc;
    for (var t = lid; t < cnt; t += WG) {
        let k = t / cc;
        let c = t % cc;
        var acc = 0.0;
        for (var rr = 0u; rr < q; rr++) {
            acc += vals[vo + k * nr + m + rr] * wload(rows[ro + rr] * cc + c);
        }
        let idx = (c0 + k) * cc + c;
        wstore(idx, wload(idx) - acc);
    }
    storageBarrier();
    var b = m;
    loop {
        if b == 0u {
            break;
        }
        let a = select(0u, b - TILE, b > TILE);
        let cnt2 = (b - a) * cc;
        for (var t = lid; t < cnt2; t += WG) {
            let k = a + t / cc;
            let c = t % cc;
            var acc = 0.0;
            for (var i = b; i < m; i++) {
                acc += vals[vo + k * nr + i] * wload((c0 + i) * cc + c);
            }
            let idx = (c0 + k) * cc + c;
            wstore(idx, wload(idx) - acc);
        }
        storageBarrier();
        if lid < cc {
            var x: array<f32, TILE>;
            for (var kk = b; kk > a; kk--) {
                let k = kk - 1u;
                var t = wload((c0 + k) * cc + lid);
                for (var j = k + 1u; j < b; j++) {
                    t -= vals[vo + k * nr + j] * x[j - a];
                }
                let v = t / vals[vo + k * nr + k];
                x[k - a] = v;
                wstore((c0 + k) * cc + lid, v);
            }
        }
        storageBarrier();
        b = a;
    }
}
