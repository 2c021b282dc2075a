// The numeric Cholesky factorization P K P^T = L L^T on the GPU, supernode by
// supernode on the host's symbolic structure, into the inverted form the
// triangular solves of supernodal.wgsl read: L_ss^-1 in each diagonal block,
// B = L_rs L_ss^-1 in the rows below it. f64 throughout (needs SHADER_F64).
//
// Driven by solver-gpu/src/factorize.rs. The values live where
// supernodal.wgsl reads them (GpuFactor: level by level, leaves first, in
// one or two buffers cut at a supernode boundary; here a global index, the
// second buffer's from c1 on: supernode s's dense column-major (m + q) x m
// block at value gvo(s), entry (i, k) at gvo + k (m + q) + i, the first m
// rows its diagonal block, the q below its rows rows[ro ..][..q]). One
// factorization:
//   scatter   (K's stored entries)  the buffer cleared, then every entry of
//                                   K's lower triangle to its place in L
//   per level, leaves first:
//     update  (the level's values)  A_ij -= sum over the descendants d that
//                                   hold both rows i and j below their
//                                   diagonal blocks of L_d[i, :] . L_d[j, :]
//                                   (left-looking: every descendant is on a
//                                   lower level, final)
//     per block column kb = 0, W, 2W, ... of the level's widest supernode,
//     over the supernodes wider than kb (the dispatch's tasks):
//       diag      (a workgroup     the block's w x w diagonal tile (w <= W)
//                  per supernode)  factored in workgroup memory, and its
//                                  inverse X_bb = L_bb^-1 made beside it
//                                  (into the scratch xs)
//       below     (a lane per      l_i = a_i X_bb^T: the block's rows under
//                  entry under     the tile, own rows and the rows below
//                  the tile)
//       trailing  (each entry      A_ij -= L_i,block . L_j,block for the
//                  right of the    columns j right of the block, i >= j
//                  block)
//   the inversion, X = L_ss^-1 in xs (its diagonal tiles are diag's X_bb):
//   inv_offdiag    (per tile row   X's tiles left of the diagonal
//                   I, its tasks)
//   inv_below      (per tile       B = L_rs X, in place, a tile column at a
//                   column J)      time
//   inv_copy       (every column)  X over L_ss
// No host work between the dispatches and no atomics on values: the same
// factor on every run. Each value's update is one dot product, summed in a
// fixed order; the dense separators at the top of the tree spread over the
// whole GPU (trailing), not one workgroup.
//
// An update merges two lists of slots (the slots holding row i, and those
// holding row j: tpos[tptr[i] .. tptr[i + 1]], ascending in the slots' level
// order, at most one slot per supernode); a supernode in both is a
// descendant holding both rows.
//
// Bindings (group 0):
//   0  P     uniform  sn0, n_sn: an update's supernodes in level order
//                     (order[sn0 ..]); v0, nval: their values (below and
//                     trailing: their items); n: columns; nnz_k: K's stored
//                     entries; slots; the offsets of the sections of idx and
//                     fidx; task0, n_task: a block column's tasks; kb: its
//                     first column; lpr: lanes a row in `below`; parts:
//                     lanes a sum in inv_below.
//   1  idx   read     GpuFactor's u32 sections (as in supernodal.wgsl): per
//                     supernode c0, m, q, ro, vo (o_sn); the slots' rows
//                     (o_rows); per row the slots holding it (o_tptr,
//                     o_tpos); each column's supernode (o_owner); each
//                     slot's supernode (o_slot_owner).
//   2  fidx  read     the factorization's own u32 sections: the supernodes in
//                     level order (o_order); the place in vals of each of
//                     K's stored entries (o_map); per block column, its
//                     tasks, three u32 each (o_task): the supernode, and the
//                     workgroups of `below` (of `inv_below` in its tasks)
//                     and the trailing entries of the tasks before it;
//                     each supernode's inverse diagonal block in xs (o_xo);
//                     each supernode's first value, a global index (o_gvo).
//   3  vals  rw       the factor's values (f64) below c1 (a factor over two
//                     bindings is factored on the host).
//   4  kv    read     K's stored values (f64), in the order of the map.
//   5  flag  rw       [0]: the least column whose pivot was not positive
//                     (u32::MAX, as the host sets it: none).
//   6  xs    rw       scratch: each supernode's L_ss^-1, m x m column-major.
//   7  vals1 rw       the factor's values from c1 on (a 16-byte stand-in
//                     where they fit one buffer).
// 256 invocations per workgroup; diag a workgroup per task, below,
// inv_offdiag and inv_below workgroups by their tasks' counts (wid.x + wid.y
// * nwg.x), the others 2-D (linear index gid.x + gid.y * nwg.x * 256).

struct FParams {
    sn0: u32,
    n_sn: u32,
    v0: u32,
    nval: u32,
    n: u32,
    nnz_k: u32,
    slots: u32,
    o_sn: u32,
    o_rows: u32,
    o_tptr: u32,
    o_tpos: u32,
    o_owner: u32,
    o_slot_owner: u32,
    o_order: u32,
    o_map: u32,
    o_task: u32,
    task0: u32,
    n_task: u32,
    kb: u32,
    o_xo: u32,
    o_gvo: u32,
    c1: u32,
    lpr: u32,
    parts: u32,
}

const FWG: u32 = 256u;
// Unused; every kernel of the crate is specialised by it.
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: FParams;
@group(0) @binding(1) var<storage, read> idx: array<u32>;
@group(0) @binding(2) var<storage, read> fidx: array<u32>;
@group(0) @binding(3) var<storage, read_write> vals: array<f64>;
@group(0) @binding(4) var<storage, read> kv: array<f64>;
@group(0) @binding(5) var<storage, read_write> flag: array<atomic<u32>>;
@group(0) @binding(6) var<storage, read_write> xs: array<f64>;
@group(0) @binding(7) var<storage, read_write> vals1: array<f64>;

// Value i of the factor (a global index): in vals below c1, else in vals1.
fn ld(i: u32) -> f64 {
    if i < P.c1 {
        return vals[i];
    }
    return vals1[i - P.c1];
}

fn st(i: u32, v: f64) {
    if i < P.c1 {
        vals[i] = v;
    } else {
        vals1[i - P.c1] = v;
    }
}

struct Super {
    c0: u32,
    m: u32,
    q: u32,
    ro: u32,
    vo: u32,
}

// Supernode s's header, its values' offset global (fidx), not its chunk's.
fn supernode(s: u32) -> Super {
    let a = P.o_sn + 5u * s;
    return Super(idx[a], idx[a + 1u], idx[a + 2u], idx[a + 3u], fidx[P.o_gvo + s]);
}

fn linear(gid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return gid.x + gid.y * nwg.x * FWG;
}

// A pivot that is not positive: the least failing column is kept.
fn not_positive(col: u32) {
    atomicMin(&flag[0], col);
}

@compute @workgroup_size(256)
fn scatter(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = linear(gid, nwg);
    if t >= P.nnz_k {
        return;
    }
    st(fidx[P.o_map + t], kv[t]);
}

// The supernode (in level order, within [sn0, sn0 + n_sn)) whose block holds
// value v: the last one whose block starts at or before v.
fn holder(v: u32) -> u32 {
    var lo = P.sn0;
    var hi = P.sn0 + P.n_sn;
    while hi - lo > 1u {
        let mid = (lo + hi) / 2u;
        if supernode(fidx[P.o_order + mid]).vo <= v {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return fidx[P.o_order + lo];
}

@compute @workgroup_size(256)
fn update(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = linear(gid, nwg);
    if t >= P.nval {
        return;
    }
    let v = P.v0 + t;
    let s = supernode(holder(v));
    let nr = s.m + s.q;
    let j = (v - s.vo) / nr;
    let i = (v - s.vo) % nr;
    if i < j {
        return;
    }
    let c = s.c0 + j;
    var g = s.c0 + i;
    if i >= s.m {
        g = idx[P.o_rows + s.ro + i - s.m];
    }
    var a = idx[P.o_tptr + c];
    let a1 = idx[P.o_tptr + c + 1u];
    var b = idx[P.o_tptr + g];
    let b1 = idx[P.o_tptr + g + 1u];
    var acc = f64(0.0);
    while a < a1 && b < b1 {
        let pa = idx[P.o_tpos + a];
        let pb = idx[P.o_tpos + b];
        let da = idx[P.o_slot_owner + pa];
        if da == idx[P.o_slot_owner + pb] {
            let d = supernode(da);
            let nd = d.m + d.q;
            let ra = d.vo + d.m + pa - d.ro;
            let rb = d.vo + d.m + pb - d.ro;
            for (var k = 0u; k < d.m; k++) {
                acc += ld(ra + k * nd) * ld(rb + k * nd);
            }
            a++;
            b++;
        } else if pa < pb {
            a++;
        } else {
            b++;
        }
    }
    st(v, ld(v) - acc);
}

// The supernode of task `t` of this dispatch (fidx[o_task + 3 (task0 + t)]:
// the supernode, then the rows below and the entries of the trailing update
// of the tasks before it in this dispatch).
fn task_supernode(t: u32) -> u32 {
    return fidx[P.o_task + 3u * (P.task0 + t)];
}

// The task of this dispatch holding item `e` of list `which` (1: rows
// below, 2: trailing entries): the last one whose items start at or before e.
fn task_of(e: u32, which: u32) -> u32 {
    var lo = 0u;
    var hi = P.n_task;
    while hi - lo > 1u {
        let mid = (lo + hi) / 2u;
        if fidx[P.o_task + 3u * (P.task0 + mid) + which] <= e {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return lo;
}

// Columns of this dispatch's block of a supernode with m columns: from kb,
// at most W.
fn block_width(m: u32) -> u32 {
    if m <= P.kb {
        return 0u;
    }
    return min(W, m - P.kb);
}

const W: u32 = 32u;
// Lanes sharing one sum in inv_offdiag (and in inv_below's wide steps): a
// workgroup's 256 lanes are W x PARTS.
const PARTS: u32 = 8u;
var<workgroup> shape: array<u32, 5>;
var<workgroup> tile: array<f64, 1024>;
var<workgroup> sums: array<f64, 256>;

// The dense Cholesky of the block's W x W diagonal tile, in workgroup memory,
// and the inverse of its factor, X = L_bb^-1 (lower triangular), beside it,
// one barrier a column. The tile's lower triangle (entry (r, c) at
// tile[c bw + r], r >= c) holds A's entries as they are updated, column k
// left unscaled: at step k, with p = a_kk, a_rc -= a_rk a_ck / p right of k
// (l_rk l_ck, l_ik = a_ik / sqrt(p)). Its upper triangle, transposed (entry
// (r, c), r > c, at tile[r bw + c]), holds the sums s_rc of L X = I's
// forward substitution, x_rc = s_rc / sqrt(a_rr) once row r is reached:
// step k takes s_ij -= l_ik x_kj = a_ik s_kj / p off the rows i > k of X
// (the same product, s_kj in column k of the tile), and s_ik -= a_ik / p
// (x_kk = 1 / sqrt(p)). At the end the columns of L and the rows of X are
// scaled by their pivots' roots as they are stored: L in the factor, X in
// the scratch (xs, where the inversion reads the diagonal tiles of
// L_ss^-1), for `below` and the inversion. A pivot that is not positive is
// flagged and taken as 1.
@compute @workgroup_size(256)
fn diag(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = wid.x + wid.y * nwg.x;
    if lid == 0u {
        var s = Super(0u, 0u, 0u, 0u, 0u);
        var xo = 0u;
        if t < P.n_task {
            let sn = task_supernode(t);
            s = supernode(sn);
            xo = fidx[P.o_xo + sn];
        }
        shape[0] = s.m;
        shape[1] = s.m + s.q;
        shape[2] = s.vo;
        shape[3] = s.c0;
        shape[4] = xo;
    }
    // Uniform across the workgroup (the loop below holds barriers).
    let m = workgroupUniformLoad(&shape[0]);
    let nr = workgroupUniformLoad(&shape[1]);
    let vo = workgroupUniformLoad(&shape[2]);
    let c0 = workgroupUniformLoad(&shape[3]);
    let xo = workgroupUniformLoad(&shape[4]);
    let bw = block_width(m);
    let at = vo + P.kb * nr + P.kb;
    for (var e = lid; e < bw * bw; e += FWG) {
        let r = e % bw;
        let c = e / bw;
        if r >= c {
            tile[e] = ld(at + c * nr + r);
        } else {
            tile[e] = f64(0.0);
        }
    }
    workgroupBarrier();
    for (var k = 0u; k < bw; k++) {
        let a = tile[k * bw + k];
        if !(a > f64(0.0)) && lid == 0u {
            not_positive(c0 + P.kb + k);
        }
        let inv = f64(1.0) / pivot(k, bw);
        // The columns right of k.
        for (var e = (k + 1u) * bw + lid; e < bw * bw; e += FWG) {
            let r = e % bw;
            let c = e / bw;
            if r >= c || r < k {
                tile[e] -= tile[k * bw + r] * tile[k * bw + c] * inv;
            } else if r == k {
                tile[e] -= tile[k * bw + c] * inv;
            }
        }
        workgroupBarrier();
    }
    let xat = xo + P.kb * m + P.kb;
    for (var e = lid; e < bw * bw; e += FWG) {
        let r = e % bw;
        let c = e / bw;
        if r >= c {
            let dc = sqrt(pivot(c, bw));
            st(at + c * nr + r, select(tile[e] / dc, dc, r == c));
            let x = select(tile[r * bw + c] / sqrt(pivot(r, bw)), f64(1.0) / dc, r == c);
            xs[xat + c * m + r] = x;
        }
    }
}

// Pivot k of `diag`'s tile (of width bw), 1 where it is not positive.
fn pivot(k: u32, bw: u32) -> f64 {
    let a = tile[k * bw + k];
    return select(f64(1.0), a, a > f64(0.0));
}

// Rows of a supernode's block below its diagonal tile (own rows past the
// tile, then the rows below the diagonal block): l_i solves l_i L_bb^T = a_i,
// that is l_i = a_i X^T with X = L_bb^-1 (made by `diag`, in xs): l_ij = sum
// over k <= j of a_ik X_jk, in place. A workgroup per 256 / lpr rows of a
// task (fidx: the workgroups before it), P.lpr lanes a row (a power of
// two, at least the dispatch's widest block): lane (j, row) makes l_ij from
// the row's a and X's tile, both read into workgroup memory first, and
// writes it once the workgroup has read them.
@compute @workgroup_size(256)
fn below(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let g = wid.x + wid.y * nwg.x;
    let lpr = P.lpr;
    let j = lid % lpr;
    let rr = lid / lpr;
    var bw = 0u;
    var m = 0u;
    var xat = 0u;
    var at = 0u;
    var live = false;
    var a = f64(0.0);
    if g < P.nval {
        let task = task_of(g, 1u);
        let sn = task_supernode(task);
        let s = supernode(sn);
        bw = block_width(s.m);
        m = s.m;
        xat = fidx[P.o_xo + sn] + P.kb * s.m + P.kb;
        let nr = s.m + s.q;
        let r = (g - fidx[P.o_task + 3u * (P.task0 + task) + 1u]) * (FWG / lpr) + rr;
        let i = P.kb + bw + r;
        if i < nr && j < bw {
            at = s.vo + (P.kb + j) * nr + i;
            a = ld(at);
            live = true;
        }
    }
    for (var e = lid; e < bw * bw; e += FWG) {
        tile[e] = xs[xat + (e / bw) * m + e % bw];
    }
    sums[lid] = a;
    workgroupBarrier();
    if live {
        var acc = f64(0.0);
        for (var k = 0u; k <= j; k++) {
            acc += sums[rr * lpr + k] * tile[k * bw + j];
        }
        st(at, acc);
    }
}

// Entry (i, j) of a supernode right of its block (j from kb + bw, i >= j):
// A_ij -= sum over the block's columns k of L_ik L_jk. Items run over the
// rectangle (rows from kb + bw) x (columns from kb + bw); those above the
// diagonal do nothing.
@compute @workgroup_size(256)
fn trailing(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let e = linear(gid, nwg);
    if e >= P.nval {
        return;
    }
    let t = task_of(e, 2u);
    let s = supernode(task_supernode(t));
    let nr = s.m + s.q;
    let bw = block_width(s.m);
    let j0 = P.kb + bw;
    let local = e - fidx[P.o_task + 3u * (P.task0 + t) + 2u];
    let i = j0 + local % (nr - j0);
    let j = j0 + local / (nr - j0);
    if i < j {
        return;
    }
    let col = s.vo + P.kb * nr;
    var acc = f64(0.0);
    for (var k = 0u; k < bw; k++) {
        acc += ld(col + k * nr + i) * ld(col + k * nr + j);
    }
    st(s.vo + j * nr + i, ld(s.vo + j * nr + i) - acc);
}

// The inversion, in tiles of W: X = L_ss^-1 into the scratch xs (supernode
// s's m x m block at xs[xo(s)], column-major, its upper triangle zero), then
// B = L_rs X in place, then X over L_ss. L stays in vals until B is made.


// Step I (kb = W I) of X's tiles left of the diagonal: X_IJ = -X_II (sum over
// K from J to I - 1 of L_IK X_KJ) for every J < I of every task (a supernode
// wider than kb). A workgroup per task and column j < kb, its lanes (t, p):
// part p of the sum of row kb + t of L against column j of X (every PARTS-th
// term from j + p), the parts then summed in workgroup memory, then row t of
// X_II against the w sums.
@compute @workgroup_size(256)
fn inv_offdiag(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let g = wid.x + wid.y * nwg.x;
    let t = lid % W;
    let p = lid / W;
    var w = 0u;
    var m = 0u;
    var nr = 0u;
    var vo = 0u;
    var xo = 0u;
    var j = 0u;
    if g < P.n_task * P.kb {
        let sn = task_supernode(g / P.kb);
        let s = supernode(sn);
        m = s.m;
        nr = s.m + s.q;
        vo = s.vo;
        xo = fidx[P.o_xo + sn];
        w = min(W, m - P.kb);
        j = g % P.kb;
    }
    var acc = f64(0.0);
    if t < w {
        let i = P.kb + t;
        for (var k = j + p; k < P.kb; k += PARTS) {
            acc += ld(vo + k * nr + i) * xs[xo + j * m + k];
        }
    }
    sums[lid] = acc;
    workgroupBarrier();
    if p == 0u && t < w {
        var part = f64(0.0);
        for (var q = 0u; q < PARTS; q++) {
            part += sums[q * W + t];
        }
        tile[t] = part;
    }
    workgroupBarrier();
    if p == 0u && t < w {
        let d = xo + P.kb * m + P.kb;
        var x = f64(0.0);
        for (var u = 0u; u <= t; u++) {
            x += xs[d + u * m + t] * tile[u];
        }
        xs[xo + j * m + P.kb + t] = -x;
    }
}

// Step J (kb = W J) of B = L_rs X, columns kb .. kb + w of every row below
// the diagonal blocks of the tasks (supernodes wider than kb): B_rj = sum
// over k >= j of L_rk X_kj. A workgroup per PARTS / P.parts rows of a task
// (fidx: the workgroups before it), lane (t, row, p): part p of P.parts of
// the sum for column kb + t (every P.parts-th term from it), the parts
// summed in workgroup memory and written once the workgroup has read its
// rows' L (columns from kb on, still L). One part a sum for the narrow
// supernodes of step 0, P.parts = PARTS for the wide ones.
@compute @workgroup_size(256)
fn inv_below(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let g = wid.x + wid.y * nwg.x;
    let parts = P.parts;
    let t = lid % W;
    let rr = lid / W / parts;
    let p = lid / W % parts;
    var acc = f64(0.0);
    var at = 0u;
    var live = false;
    if g < P.nval {
        let task = task_of(g, 1u);
        let sn = task_supernode(task);
        let s = supernode(sn);
        let r = (g - fidx[P.o_task + 3u * (P.task0 + task) + 1u]) * (PARTS / parts) + rr;
        let w = min(W, s.m - P.kb);
        let nr = s.m + s.q;
        let xo = fidx[P.o_xo + sn];
        if r < s.q && t < w {
            let j = P.kb + t;
            let row = s.vo + s.m + r;
            for (var k = j + p; k < s.m; k += parts) {
                acc += ld(row + k * nr) * xs[xo + j * s.m + k];
            }
            at = row + j * nr;
            live = p == 0u;
        }
    }
    sums[lid] = acc;
    workgroupBarrier();
    if live {
        var b = f64(0.0);
        for (var q = 0u; q < parts; q++) {
            b += sums[lid + q * W];
        }
        st(at, b);
    }
}

// X over L_ss: column c's entries of its diagonal block from xs (its upper
// triangle zero there).
@compute @workgroup_size(256)
fn inv_copy(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let c = linear(gid, nwg);
    if c >= P.n {
        return;
    }
    let sn = idx[P.o_owner + c];
    let s = supernode(sn);
    let nr = s.m + s.q;
    let j = c - s.c0;
    let xo = fidx[P.o_xo + sn];
    for (var i = 0u; i < s.m; i++) {
        st(s.vo + j * nr + i, xs[xo + j * s.m + i]);
    }
}
