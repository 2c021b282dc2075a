// Triangular solves with a supernodal Cholesky factor, the shape systems'
// preconditioner z = M^-1 r with M = P^T L L^T P (x) I_bs: the factor of the
// isotropic part K of the shape matrix (solver_cpu::SupernodalFactor, made on
// the host once per system kind, its diagonal blocks L_ss inverted there)
// applied to x, y and z of every PCG column.
//
// Driven by solver-gpu/src/supernodal.rs. One application, with the levels of
// the supernodal elimination tree (a level's supernodes are independent):
//   per level, leaves first:
//     pull     (own rows)       w_s = (P r)_s - the updates the descendants
//                               left in `contrib` for the rows of s (once
//                               per update buffer holding some)
//     forward  (own rows, then  y_s = L_ss^-1 w_s, and contrib[slot of row r]
//               rows below)     = B_rs w_s with B = L_rs L_ss^-1 (= L_rs y_s)
//   per level, root first:
//     backward (own rows)       w_s = x_s = L_ss^-T y_s - B_rs^T x_r (x of the
//                               ancestors, final, kept in w); z = P^T x
// Three dispatches a level (where the updates fit one binding) and nothing
// else: the factor holds B in place of
// L_rs (SupernodalFactor::invert_diagonal_blocks), so the diagonal and below
// products of a sweep read the same vector and share a dispatch, and the
// permutations are folded into the first and last step of each row.
// Every kernel is one dot product per (row, scalar column) of its list: no
// atomics, no two dot products write one entry. `pull`'s are one invocation
// each (a row pulls at most about a hundred updates, and over several update
// buffers its sum is taken buffer by buffer: with a team it would depend on
// where the adapter's binding size cuts them). `forward`'s and `backward`'s are each summed by a team of `team_f`
// or `team_b` lanes (a power of two up to 64, per segment; 1: one
// invocation, no barrier): lane j takes the terms j, j + team, ... of the
// row, and the team's lanes add theirs up in workgroup memory in a fixed
// tree (the same result on every run). The dense separators at the top of
// the tree have few rows of up to a few thousand terms: one invocation each
// would walk them one after the other, thousands of dependent steps that a
// discrete GPU's bandwidth does not shorten; a team walks them in `len /
// team + log2 team` steps. Where a level has rows enough to fill the GPU,
// its team is 1 (SupernodalSteps::new picks them).
//
// Supernode s (5 u32 at idx[o_sn + 5 s]): c0 its first column, m columns, q
// rows below its diagonal block (idx[o_rows + ro ..][..q], permuted
// numbering; the slots ro .. ro + q in the slots' level order), its values the dense column-major (m + q) x m block at vals[vo]:
// entry (i, k) at vals[vo + k (m + q) + i]; the first m rows hold L_ss^-1,
// the q below B = L_rs L_ss^-1.
//
// Bindings (group 0):
//   0  P        uniform  own, n_own: this level segment's own rows (columns) at
//                        idx[o_cols + own ..]; below, n_below: its slots, from
//                        slot `below` on (level order); nv: rows of K; stride: length
//                        of one PCG column (nv * bs); bs: unknowns per vertex;
//                        the offsets of the sections of `idx`; update0,
//                        update1: the slots (level order) whose updates the
//                        bound `contrib` holds; first: pull starts from r
//                        (else from w, after an earlier buffer's pull);
//                        team_f, team_b: lanes per dot product of forward
//                        and backward.
//   1  idx      read     u32 sections: per supernode c0, m, q, ro, vo (o_sn);
//                        the rows below the diagonal blocks, one per slot, the
//                        slots in level order: the supernodes by level, leaves
//                        first (o_rows); perm[new] = old vertex (o_perm); per
//                        row i the slots holding i, ascending, tpos[tptr[i] ..
//                        tptr[i + 1]] (o_tptr, o_tpos); the columns by level
//                        (o_cols) and each column's supernode (o_owner); each
//                        slot's supernode (o_slot_owner).
//   2  vals     read     the values of this dispatch's supernodes: one of the
//                        buffers the factor's values are cut into at supernode
//                        boundaries (vo is an offset in it). (f32; this shader is also
//                        compiled in f64, every f32 made f64, for the f64
//                        factor and the mixed-precision PCG's f64 vectors).
//   3  w        rw       work vector, nv x C (C = bs * NCOLS scalar columns;
//                        entry (i, c) at i * C + c: a row's columns adjacent).
//   4  y        rw       second work vector, same layout.
//   5  r        read     PCG residual, NCOLS columns of stride `stride`.
//   6  z        rw       preconditioned residual, same layout.
//   7  contrib  rw       one update per slot and column, the slots in level
//                        order: slot p's at (p - update0) * C + c. The updates
//                        are cut into buffers of at most one binding at
//                        supernode boundaries, one bound per dispatch.
// 256 invocations per workgroup, 2-D dispatch (linear index gid.x + gid.y *
// nwg.x * 256; dot product linear / team, lane linear % team, so a team is
// inside one workgroup); invocations past the list add nothing and write
// nothing, but reach the team's barriers.

struct Params {
    own: u32,
    n_own: u32,
    below: u32,
    n_below: u32,
    nv: u32,
    stride: u32,
    bs: u32,
    o_sn: u32,
    o_rows: u32,
    o_perm: u32,
    o_tptr: u32,
    o_tpos: u32,
    o_cols: u32,
    o_owner: u32,
    o_slot_owner: u32,
    update0: u32,
    update1: u32,
    first: u32,
    team_f: u32,
    team_b: u32,
}

const FWG: u32 = 256u;
// PCG columns (1..=8), fixed when the pipeline is created.
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> idx: array<u32>;
@group(0) @binding(2) var<storage, read> vals: array<f32>;
@group(0) @binding(3) var<storage, read_write> w: array<f32>;
@group(0) @binding(4) var<storage, read_write> y: array<f32>;
@group(0) @binding(5) var<storage, read> r: array<f32>;
@group(0) @binding(6) var<storage, read_write> z: array<f32>;
@group(0) @binding(7) var<storage, read_write> contrib: array<f32>;

// A supernode's table entry.
struct Super {
    c0: u32,
    m: u32,
    q: u32,
    ro: u32,
    vo: u32,
}

fn supernode(s: u32) -> Super {
    let a = P.o_sn + 5u * s;
    return Super(idx[a], idx[a + 1u], idx[a + 2u], idx[a + 3u], idx[a + 4u]);
}

// Invocation t of a level's own rows: row (permuted column) `row` of
// supernode `s`, local index `k = row - c0`, scalar column `c` of `cc`.
struct OwnRow {
    row: u32,
    k: u32,
    c: u32,
    cc: u32,
    s: Super,
}

fn own_row(t: u32) -> OwnRow {
    let cc = P.bs * NCOLS;
    let row = idx[P.o_cols + P.own + t / cc];
    let s = supernode(idx[P.o_owner + row]);
    return OwnRow(row, row - s.c0, t % cc, cc, s);
}

fn linear(gid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return gid.x + gid.y * nwg.x * FWG;
}

// A team's partial sums (one per invocation of the workgroup).
var<workgroup> part: array<f32, FWG>;

// The sum of `acc` over the `team` lanes holding invocation `lid` (team a
// power of two dividing FWG, the same for the whole dispatch), at the team's
// first lane: halves added pairwise in workgroup memory, in a fixed order.
// Reached by every invocation of the workgroup (its barriers).
fn team_sum(lid: u32, acc: f32, team: u32) -> f32 {
    if team == 1u {
        return acc;
    }
    part[lid] = acc;
    workgroupBarrier();
    for (var h = team / 2u; h > 0u; h = h / 2u) {
        if lid % team < h {
            part[lid] += part[lid + h];
        }
        workgroupBarrier();
    }
    return part[lid];
}

// The PCG entry of w's entry t: column pc of r / z, vertex perm[i], unknown k.
fn pcg_index(t: u32) -> u32 {
    let cc = P.bs * NCOLS;
    let i = t / cc;
    let c = t % cc;
    return (c / P.bs) * P.stride + idx[P.o_perm + i] * P.bs + c % P.bs;
}

// w_i = (P r)_i - the descendants' updates of row i (the gather of r fused:
// nothing reads w_i before its pull), those in the bound update buffer; the
// buffers in order, the first from r, the later ones from w (the same sums
// in the same order as with one buffer).
@compute @workgroup_size(256)
fn pull(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let cc = P.bs * NCOLS;
    let t = linear(gid, nwg);
    if t >= P.n_own * cc {
        return;
    }
    let row = idx[P.o_cols + P.own + t / cc];
    let c = t % cc;
    var acc: f32;
    if P.first != 0u {
        acc = r[pcg_index(row * cc + c)];
    } else {
        acc = w[row * cc + c];
    }
    let e1 = idx[P.o_tptr + row + 1u];
    for (var e = idx[P.o_tptr + row]; e < e1; e++) {
        let p = idx[P.o_tpos + e];
        if p >= P.update1 {
            break;
        }
        if p >= P.update0 {
            acc -= contrib[(p - P.update0) * cc + c];
        }
    }
    w[row * cc + c] = acc;
}

// Forward step of a level segment, after its pull: own row i of supernode s,
// y_i = sum_{k <= i} L_ss^-1[i, k] w_k; then, past the own rows, slot p = ro + r
// (level order) of supernode s, contrib[p] = sum_k B[r, k] w_k
// (B = L_rs L_ss^-1, stored in place of L_rs). Both read w_s only, so they
// share one dispatch. A team of team_f lanes per dot product.
@compute @workgroup_size(256)
fn forward(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let cc = P.bs * NCOLS;
    let team = P.team_f;
    let lane = lid % team;
    let t = linear(gid, nwg) / team;
    var acc: f32 = 0.0;
    // Where the sum goes: 1 y, 2 contrib, 0 nowhere (past the list).
    var to = 0u;
    var at_out = 0u;
    if t < P.n_own * cc {
        let o = own_row(t);
        let nr = o.s.m + o.s.q;
        for (var k = lane; k <= o.k; k += team) {
            acc += vals[o.s.vo + k * nr + o.k] * w[(o.s.c0 + k) * cc + o.c];
        }
        to = 1u;
        at_out = o.row * cc + o.c;
    } else if t - P.n_own * cc < P.n_below * cc {
        let u = t - P.n_own * cc;
        let p = P.below + u / cc;
        let c = u % cc;
        let s = supernode(idx[P.o_slot_owner + p]);
        let at = s.vo + s.m + (p - s.ro);
        let nr = s.m + s.q;
        for (var k = lane; k < s.m; k += team) {
            acc += vals[at + k * nr] * w[(s.c0 + k) * cc + c];
        }
        to = 2u;
        at_out = (p - P.update0) * cc + c;
    }
    let sum = team_sum(lid, acc, team);
    if lane != 0u {
        return;
    }
    if to == 1u {
        y[at_out] = sum;
    } else if to == 2u {
        contrib[at_out] = sum;
    }
}

// Backward step: x_k = sum_{i >= k} L_ss^-1[i, k] y_i - sum_r B[r, k] x_{rows[r]}
// for row k of supernode s, into w (the ancestors' x, final, are in w; this
// level's forward y in y) and, scattered, into z (z = P^T x). A team of
// team_b lanes per dot product.
@compute @workgroup_size(256)
fn backward(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let cc = P.bs * NCOLS;
    let team = P.team_b;
    let lane = lid % team;
    let t = linear(gid, nwg) / team;
    let inside = t < P.n_own * cc;
    var acc: f32 = 0.0;
    var at_out = 0u;
    if inside {
        let o = own_row(t);
        let at = o.s.vo + o.k * (o.s.m + o.s.q);
        for (var i = o.k + lane; i < o.s.m; i += team) {
            acc += vals[at + i] * y[(o.s.c0 + i) * cc + o.c];
        }
        for (var rr = lane; rr < o.s.q; rr += team) {
            acc -= vals[at + o.s.m + rr] * w[idx[P.o_rows + o.s.ro + rr] * cc + o.c];
        }
        at_out = o.row * cc + o.c;
    }
    let sum = team_sum(lid, acc, team);
    if lane != 0u || !inside {
        return;
    }
    w[at_out] = sum;
    z[pcg_index(at_out)] = sum;
}
