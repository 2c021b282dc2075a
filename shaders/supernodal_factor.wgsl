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
//     or update_tiled (a workgroup  the same sums, where they are long: a
//                  per 32 x 32      descendant's rows of the tile read into
//                  tile)            workgroup memory once a tile
//     per block column kb = 0, W, 2W, ... of the level's widest supernode,
//     over the supernodes wider than kb (the dispatch's tasks):
//       diag      (a workgroup     the block's w x w diagonal tile (w <= W)
//                  per supernode)  factored in workgroup memory, and its
//                                  inverse X_bb = L_bb^-1 made beside it
//                                  (into the scratch xs)
//       below     (a lane per      l_i = a_i X_bb^T: the block's rows under
//                  entry under     the tile, own rows and the rows below
//                  the tile)
//       trailing  (a workgroup     A_ij -= L_i,block . L_j,block for the
//                  per 32 x 32     columns j right of the block, i >= j
//                  tile)
//   the inversion, X = L_ss^-1 in xs (its diagonal tiles are diag's X_bb):
//   inv_offdiag    (per tile row   X's tiles left of the diagonal, a
//                   I, its tasks)  workgroup a tile
//   inv_below      (per tile       B = L_rs X, in place, a tile column at a
//                   column J)      time, a workgroup per 32 rows
//   inv_copy       (every column)  X over L_ss
// No host work between the dispatches and no atomics on values: the same
// factor on every run. Each value's update is one dot product, summed in a
// fixed order; the dense separators at the top of the tree spread over the
// whole GPU (trailing), not one workgroup.
//
// The long sums (update_tiled, trailing, inv_offdiag, inv_below) run in
// tiles: a workgroup makes a 32 x 32 tile of sums, reading the tile's rows
// and columns, KC terms at a time, into workgroup memory (tile) and each
// lane adding its four entries' products from there (panel_products). Each
// value is read from device memory once a tile, not once an entry: on a
// discrete GPU these sums' time is the bytes they read (BENCHMARKS.md, "GPU
// numeric factorization").
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
//                     first column; lpr: lanes a row in `below`; o_dptr,
//                     o_dlist: update_tiled's lists in fidx.
//   1  idx   read     GpuFactor's u32 sections (as in supernodal.wgsl): per
//                     supernode c0, m, q, ro, vo (o_sn); the slots' rows
//                     (o_rows); per row the slots holding it (o_tptr,
//                     o_tpos); each column's supernode (o_owner); each
//                     slot's supernode (o_slot_owner).
//   2  fidx  read     the factorization's own u32 sections: the supernodes in
//                     level order (o_order); the place in vals of each of
//                     K's stored entries (o_map); per block column, its
//                     tasks, three u32 each (o_task): the supernode, and the
//                     workgroups of `below` (of `inv_below` in its tasks;
//                     update_tiled's: its tiles) and the trailing tiles of
//                     the tasks before it (update_tiled's: its first list);
//                     each supernode's inverse diagonal block in xs (o_xo);
//                     each supernode's first value, a global index (o_gvo);
//                     update_tiled's lists: per tile column of a tiled
//                     supernode, where its descendants start (o_dptr, one
//                     more at the end), and per descendant its supernode
//                     and its first slot at or past the tile column,
//                     relative to its rows (o_dlist, two u32 each).
//   3  vals  rw       the factor's values (f64) below c1 (a factor over two
//                     bindings is factored on the host).
//   4  kv    read     K's stored values (f64), in the order of the map.
//   5  flag  rw       [0]: the least column whose pivot was not positive
//                     (u32::MAX, as the host sets it: none).
//   6  xs    rw       scratch: each supernode's L_ss^-1, m x m column-major.
//   7  vals1 rw       the factor's values from c1 on (a 16-byte stand-in
//                     where they fit one buffer).
// 256 invocations per workgroup; diag a workgroup per task, below,
// trailing, update_tiled, inv_offdiag and inv_below workgroups by their
// tasks' counts (wid.x + wid.y * nwg.x), the others 2-D (linear index gid.x
// + gid.y * nwg.x * 256).

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
    o_dptr: u32,
    o_dlist: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
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

// The update of the levels with long sums, in tiles: a workgroup per 32 x 32
// tile of a supernode's block on or below its diagonal (tile row I >= tile
// column J; a task is a supernode, fidx: its tiles' first workgroup and its
// first list), and per descendant d of the tile's columns (fidx's list for
// the supernode's tile column J, in level order, with d's first slot at or
// past the tile's first column), the same sum as `update`'s: lanes find the
// tile's rows and columns among d's rows (binary searches), then d's
// columns of those rows are read into workgroup memory KC at a time, and
// each lane adds their products to its four entries. Each of d's values
// is read once a tile, not once an entry; a descendant with none of the
// tile's rows is skipped.
@compute @workgroup_size(256)
fn update_tiled(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let g = wid.x + wid.y * nwg.x;
    if g >= P.nval {
        return;
    }
    let task = P.o_task + 3u * (P.task0 + task_of(g, 1u));
    let s = supernode(fidx[task]);
    let nr = s.m + s.q;
    let it = lower_tile(g - fidx[task + 1u], nr, s.m);
    let i0 = W * it.x;
    let j0 = W * it.y;
    // The global rows of the tile's rows and columns (NONE past the block).
    if lid < 2u * W {
        var li = i0 + lid;
        if lid >= W {
            li = j0 + lid - W;
        }
        var gr = NONE;
        if li < nr && (lid < W || li < s.m) {
            if li < s.m {
                gr = s.c0 + li;
            } else {
                gr = idx[P.o_rows + s.ro + li - s.m];
            }
        }
        grow[lid] = gr;
    }
    if lid == 0u {
        atomicStore(&hits, 0u);
    }
    var acc = vec4<f64>(0.0);
    let list = fidx[task + 2u] + it.y;
    let e1 = fidx[P.o_dptr + list + 1u];
    for (var e = fidx[P.o_dptr + list]; e < e1; e++) {
        let d = supernode(fidx[P.o_dlist + 2u * e]);
        let a0 = d.ro + fidx[P.o_dlist + 2u * e + 1u];
        let a1 = d.ro + d.q;
        // grow is written (the first time); the last descendant's slots
        // are read.
        workgroupBarrier();
        if lid < 2u * W {
            let want = grow[lid];
            // The tile's columns are among d's next W rows.
            var hi = a1;
            if lid >= W {
                hi = min(a1, a0 + W);
            }
            var lo = a0;
            var h = hi;
            while lo < h {
                let mid = (lo + h) / 2u;
                if idx[P.o_rows + mid] < want {
                    lo = mid + 1u;
                } else {
                    h = mid;
                }
            }
            var sl = NONE;
            if want != NONE && lo < hi && idx[P.o_rows + lo] == want {
                sl = lo - d.ro;
                if lid < W {
                    atomicOr(&hits, 1u);
                }
            }
            slot[lid] = sl;
        }
        workgroupBarrier();
        if lid == 0u {
            hit = atomicLoad(&hits);
            atomicStore(&hits, 0u);
        }
        if workgroupUniformLoad(&hit) == 0u {
            continue;
        }
        let nd = d.m + d.q;
        for (var k0 = 0u; k0 < d.m; k0 += KC) {
            load_panels(lid, d.vo + d.m, nd, k0, min(KC, d.m - k0));
            workgroupBarrier();
            acc = panel_products(acc, lid, min(KC, d.m - k0));
            workgroupBarrier();
        }
    }
    store_tile(lid, acc, s, i0, j0);
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
// Lanes sharing one sum in inv_offdiag_parts: a workgroup's 256 lanes are
// W x PARTS.
const PARTS: u32 = 8u;
var<workgroup> shape: array<u32, 5>;
var<workgroup> tile: array<f64, 1024>;
var<workgroup> sums: array<f64, 256>;
// The tiled kernels: a tile's panels are KC terms of its W rows and of its W
// columns (in tile: the rows' at k W + r, the columns' from HALF). slot
// (update_tiled, trailing): each of those rows' place (NONE: none);
// update_tiled's grow: the tile's rows' and columns' global rows, and hits:
// whether a descendant holds any of its rows.
const KC: u32 = 16u;
const HALF: u32 = 512u; // W * KC
const NONE: u32 = 0xffffffffu;
var<workgroup> slot: array<u32, 64>;
var<workgroup> grow: array<u32, 64>;
var<workgroup> hits: atomic<u32>;
var<workgroup> hit: u32;

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

// Entries (i, j) of a supernode right of its block (j from kb + bw, i >= j):
// A_ij -= sum over the block's columns k of L_ik L_jk. A workgroup per 32 x
// 32 tile of that region on or below its diagonal (tile row I >= tile
// column J, from kb + bw; fidx: the tiles of the tasks before it): the
// block's columns of the tile's rows and of its columns are read into
// workgroup memory, KC at a time (`load_panels`), and each lane sums its
// four entries from there (`panel_products`): the block is read once a
// tile, not once an entry.
@compute @workgroup_size(256)
fn trailing(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let g = wid.x + wid.y * nwg.x;
    if g >= P.nval {
        return;
    }
    let item = trailing_item(g);
    let s = item.s;
    let nr = item.nr;
    let j0 = item.j0;
    let it = lower_tile(item.local, nr - j0, s.m - j0);
    let i0 = j0 + W * it.x;
    let jc0 = j0 + W * it.y;
    if lid < 2u * W {
        var row = jc0 + lid - W;
        if lid < W {
            row = i0 + lid;
        }
        var sl = NONE;
        if row < nr {
            sl = row;
        }
        slot[lid] = sl;
    }
    let col = s.vo + P.kb * nr;
    var acc = vec4<f64>(0.0);
    for (var k0 = 0u; k0 < item.bw; k0 += KC) {
        workgroupBarrier();
        load_panels(lid, col, nr, k0, min(KC, item.bw - k0));
        workgroupBarrier();
        acc = panel_products(acc, lid, min(KC, item.bw - k0));
    }
    store_tile(lid, acc, s, i0, jc0);
}

struct TrailingItem {
    s: Super,
    nr: u32,
    bw: u32,
    j0: u32,
    local: u32,
}

// Item e of a trailing dispatch (a tile, or an entry): its task's
// supernode, its rows, its block's width, the first column right of the
// block, and e's place among the task's items.
fn trailing_item(e: u32) -> TrailingItem {
    let t = task_of(e, 2u);
    let s = supernode(task_supernode(t));
    let bw = block_width(s.m);
    let local = e - fidx[P.o_task + 3u * (P.task0 + t) + 2u];
    return TrailingItem(s, s.m + s.q, bw, P.kb + bw, local);
}

// Tile `local` (in column-major order over the tiles on or below the
// diagonal) of a region of `rows` x `cols` entries (rows >= cols): its tile
// row I and column J, as (I, J). Tile column J holds the tile rows J .. tr.
fn lower_tile(local: u32, rows: u32, cols: u32) -> vec2<u32> {
    let tr = (rows + W - 1u) / W;
    let tc = (cols + W - 1u) / W;
    var lo = 0u;
    var hi = tc;
    while hi - lo > 1u {
        let mid = (lo + hi) / 2u;
        if mid * tr - mid * (mid - 1u) / 2u <= local {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    return vec2<u32>(lo + local - (lo * tr - lo * (lo - 1u) / 2u), lo);
}

// Columns k0 .. k0 + kc of the panels of a tile: the rows slot[0 .. W] (the
// tile's rows) into tile[k W + r], the rows slot[W .. 2W] (its columns) into
// tile[HALF + k W + c]; entry (row, k) of a slot's row at base + k nd + row
// (0 where the slot is NONE, and past kc).
fn load_panels(lid: u32, base: u32, nd: u32, k0: u32, kc: u32) {
    for (var x = lid; x < 2u * HALF; x += FWG) {
        let rr = x % W;
        let k = x / W % KC;
        var sl = slot[rr];
        if x >= HALF {
            sl = slot[W + rr];
        }
        var v = f64(0.0);
        if k < kc && sl != NONE {
            v = ld(base + (k0 + k) * nd + sl);
        }
        tile[x] = v;
    }
}

// Lane (r, c) of a tile (r = lid % W, c = lid / W): the panels' products for
// its entries (r, c), (r, c + 8), (r, c + 16), (r, c + 24), added to acc in
// the order of k.
fn panel_products(acc: vec4<f64>, lid: u32, kc: u32) -> vec4<f64> {
    let r = lid % W;
    let c = HALF + lid / W;
    var a = acc;
    for (var k = 0u; k < kc; k++) {
        let b = vec4<f64>(tile[c + k * W], tile[c + k * W + 8u], tile[c + k * W + 16u], tile[c + k * W + 24u]);
        a += tile[k * W + r] * b;
    }
    return a;
}

// A_ij -= acc for the lane's entries of the tile with rows from i0 and
// columns from j0 (local to supernode s), those of the block on or below
// its diagonal.
fn store_tile(lid: u32, acc: vec4<f64>, s: Super, i0: u32, j0: u32) {
    let nr = s.m + s.q;
    let i = i0 + lid % W;
    for (var u = 0u; u < 4u; u++) {
        let j = j0 + lid / W + 8u * u;
        if i < nr && j < s.m && i >= j {
            let v = s.vo + j * nr + i;
            st(v, ld(v) - acc[u]);
        }
    }
}

// The inversion, in tiles of W: X = L_ss^-1 into the scratch xs (supernode
// s's m x m block at xs[xo(s)], column-major, its upper triangle zero), then
// B = L_rs X in place, then X over L_ss. L stays in vals until B is made.


// Step I (kb = W I) of X's tiles left of the diagonal: X_IJ = -X_II (sum over
// K from J to I - 1 of L_IK X_KJ) for every J < I of every task (a supernode
// wider than kb). A workgroup per task and tile column J < I: the sum R as
// in `inv_below` (the tile's rows of L and X's columns, from W J to kb, read
// into workgroup memory KC at a time, four entries a lane), then R into
// workgroup memory and lane (t, c) makes X_IJ's entries (t, c + 8 u) as row
// t of X_II against R's columns.
@compute @workgroup_size(256)
fn inv_offdiag(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let g = wid.x + wid.y * nwg.x;
    let tiles = P.kb / W;
    if g >= P.n_task * tiles {
        return;
    }
    let sn = task_supernode(g / tiles);
    let s = supernode(sn);
    let m = s.m;
    let nr = s.m + s.q;
    let xo = fidx[P.o_xo + sn];
    let w = min(W, m - P.kb);
    let j0 = W * (g % tiles);
    var acc = vec4<f64>(0.0);
    for (var k0 = j0; k0 < P.kb; k0 += KC) {
        let kc = min(KC, P.kb - k0);
        workgroupBarrier();
        load_inverse_panels(lid, s.vo + P.kb, w, nr, xo + j0 * m, W, m, k0, kc);
        workgroupBarrier();
        acc = panel_products(acc, lid, kc);
    }
    workgroupBarrier();
    let t = lid % W;
    let c = lid / W;
    for (var u = 0u; u < 4u; u++) {
        tile[(c + 8u * u) * W + t] = acc[u];
    }
    workgroupBarrier();
    if t < w {
        let d = xo + P.kb * m + P.kb;
        var x = vec4<f64>(0.0);
        for (var u = 0u; u <= t; u++) {
            let r = vec4<f64>(tile[c * W + u], tile[(c + 8u) * W + u], tile[(c + 16u) * W + u], tile[(c + 24u) * W + u]);
            x += xs[d + u * m + t] * r;
        }
        for (var u = 0u; u < 4u; u++) {
            xs[xo + (j0 + c + 8u * u) * m + P.kb + t] = -x[u];
        }
    }
}

// Terms k0 .. k0 + kc of the inversion's panels: rows r < rows of L (entry
// (r, k) at lv + k nr + r) into tile[k W + r], columns c < cols of X (entry
// (k, c) at xs[xv + c m + k]) into tile[HALF + k W + c]; 0 elsewhere.
fn load_inverse_panels(lid: u32, lv: u32, rows: u32, nr: u32, xv: u32, cols: u32, m: u32, k0: u32, kc: u32) {
    for (var x = lid; x < 2u * HALF; x += FWG) {
        let rr = x % W;
        let k = x / W % KC;
        var v = f64(0.0);
        if k < kc && x < HALF && rr < rows {
            v = ld(lv + (k0 + k) * nr + rr);
        } else if k < kc && x >= HALF && rr < cols {
            v = xs[xv + rr * m + k0 + k];
        }
        tile[x] = v;
    }
}

// Step J (kb = W J) of B = L_rs X, columns kb .. kb + w of every row below
// the diagonal blocks of the tasks (supernodes wider than kb with rows
// below): B_rj = sum over k >= j of L_rk X_kj (X's upper triangle is zero
// in xs). A workgroup per W rows of a task (fidx: the workgroups before
// it): the rows' L and X's columns, from kb on, read into workgroup memory
// KC at a time, four entries a lane; written once the workgroup has read
// all of its rows' L (columns from kb on, still L).
@compute @workgroup_size(256)
fn inv_below(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let g = wid.x + wid.y * nwg.x;
    if g >= P.nval {
        return;
    }
    let task = task_of(g, 1u);
    let sn = task_supernode(task);
    let s = supernode(sn);
    let r0 = (g - fidx[P.o_task + 3u * (P.task0 + task) + 1u]) * W;
    let nr = s.m + s.q;
    let xo = fidx[P.o_xo + sn];
    let w = min(W, s.m - P.kb);
    let row0 = s.vo + s.m + r0;
    var acc = vec4<f64>(0.0);
    for (var k0 = P.kb; k0 < s.m; k0 += KC) {
        let kc = min(KC, s.m - k0);
        workgroupBarrier();
        load_inverse_panels(lid, row0, min(W, s.q - r0), nr, xo + P.kb * s.m, w, s.m, k0, kc);
        workgroupBarrier();
        acc = panel_products(acc, lid, kc);
    }
    let r = lid % W;
    for (var u = 0u; u < 4u; u++) {
        let j = lid / W + 8u * u;
        if r0 + r < s.q && j < w {
            st(row0 + (P.kb + j) * nr + r, acc[u]);
        }
    }
}

// `trailing` a lane an entry (where its dispatch is small: a chain of bw
// steps, not a tile's): entry (i, j) right of the block (j from kb + bw, i >= j):
// A_ij -= sum over the block's columns k of L_ik L_jk. Items run over the
// rectangle (rows from kb + bw) x (columns from kb + bw); those above the
// diagonal do nothing.
@compute @workgroup_size(256)
fn trailing_entries(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let e = linear(gid, nwg);
    if e >= P.nval {
        return;
    }
    let item = trailing_item(e);
    let nr = item.nr;
    let i = item.j0 + item.local % (nr - item.j0);
    let j = item.j0 + item.local / (nr - item.j0);
    if i < j {
        return;
    }
    let col = item.s.vo + P.kb * nr;
    var acc = f64(0.0);
    for (var k = 0u; k < item.bw; k++) {
        acc += ld(col + k * nr + i) * ld(col + k * nr + j);
    }
    st(item.s.vo + j * nr + i, ld(item.s.vo + j * nr + i) - acc);
}

// `inv_offdiag` with shared sums (where its dispatch is small: a chain of
// kb / PARTS steps, not kb): step I (kb = W I) of X's tiles left of the diagonal: X_IJ = -X_II (sum over
// K from J to I - 1 of L_IK X_KJ) for every J < I of every task (a supernode
// wider than kb). A workgroup per task and column j < kb, its lanes (t, p):
// part p of the sum of row kb + t of L against column j of X (every PARTS-th
// term from j + p), the parts then summed in workgroup memory, then row t of
// X_II against the w sums.
@compute @workgroup_size(256)
fn inv_offdiag_parts(@builtin(local_invocation_index) lid: u32, @builtin(workgroup_id) wid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
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
