// Preconditioned conjugate gradient, everything but the SpMV (bsr_spmv.wgsl /
// csr_spmv.wgsl). All scalars stay on the GPU in `cols`; the host reads them back
// only every few iterations to test convergence.
//
// Driven by solver-gpu/src/pcg.rs. One iteration, per column c (all columns of a
// batch advance together, a converged column is frozen with alpha = beta = 0):
//   spmv         Ap = A p, partials slot 0 = p . Ap                 (SpMV shader)
//   finish_alpha pap = sum of partials; alpha = rz / pap            (1 workgroup)
//   update       x += alpha p; r -= alpha Ap; z = M^-1 r (block-Jacobi);
//                partials slot 0 = r . z, slot 1 = r . r            (one pass)
//   finish_beta  rz' = sum slot 0, rr = sum slot 1; beta = rz' / rz; rz = rz';
//                done when rr <= thr                                (1 workgroup)
//   direction    p = z + beta p (the SpMV reads p in place)
// With the AMG preconditioner, `update` is replaced by `update_amg` (no z, no
// r . z), the V-cycle (amg.wgsl) writes z = M^-1 r, and `dot_rz` adds r . z.
// Start: x = p = Ap = 0, r = b, alpha = rz = 0; then update, finish_beta and
// direction give z = M^-1 b, p = z, rz = b . z.
//
// Bindings (group 0), each entry point uses a subset:
//   0  P        uniform  rows = block rows, bs = block size (1 or 3), n = rows * bs
//                        (length of one column), ncols (= NCOLS), groups =
//                        workgroups of `update` and partial slots per column:
//                        ceil(rows / WG), or more where the SpMV of a chunked
//                        block matrix writes more (one set per chunk; `update`'s
//                        workgroups past the rows write zero partials).
//                        2-D dispatch: linear workgroup index wid.x + wid.y * nwg.x.
//   1  cols     rw       one ColState per column (see below).
//   2  partials rw       slot s, column c, workgroup g at (s * ncols + c) * groups + g.
//   3  minv     read     rows * bs * bs f32, inverted diagonal blocks (row-major).
//   4  p        rw       search directions, ncols columns of length n, column-major.
//   5  ap       read     A p, same layout.
//   6  x        rw       solution (starts at 0).
//   7  r        rw       residual (starts at b).
//   8  z        rw       preconditioned residual.
//   update uses 0-8; finish_alpha, finish_beta 0-2; direction 0, 1, 4, 8.
//   The host binds all nine through one explicit layout shared by every
//   entry point.

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

// Per-column scalars. `thr` (squared residual norm at which the column is done)
// is set by the host; done: 0 running, 1 converged, 2 breakdown (p . Ap <= 0,
// r . z <= 0 or NaN while the residual is not small: matrix not SPD).
struct ColState {
    rz: f32,
    pap: f32,
    alpha: f32,
    beta: f32,
    rr: f32,
    thr: f32,
    done: u32,
    iters: u32,
}

const WG: u32 = 128u;
const FWG: u32 = 256u;
const CMAX: u32 = 8u;
// Columns handled by this pipeline (1..=CMAX), fixed when the pipeline is
// created: the column loops unroll and the per-column accumulators stay in
// registers. P.ncols must equal it.
override NCOLS: u32 = 1u;
// Squared residual norm (columns are scaled to unit norm on upload) below which
// a breakdown is taken for stagnation at the working precision, not
// indefiniteness. (The f64 variant, made by solver-gpu/src/precision.rs, drops
// the f32-only sections and uncomments the f64-only lines.)
// f32-only begin
const TINY: f32 = 1e-12;
// f32-only end
// f64-only: const TINY: f32 = 1e-26;
const HUGE: f32 = 1e37;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read_write> cols: array<ColState>;
@group(0) @binding(2) var<storage, read_write> partials: array<f32>;
@group(0) @binding(3) var<storage, read> minv: array<f32>;
@group(0) @binding(4) var<storage, read_write> p: array<f32>;
@group(0) @binding(5) var<storage, read> ap: array<f32>;
@group(0) @binding(6) var<storage, read_write> x: array<f32>;
@group(0) @binding(7) var<storage, read_write> r: array<f32>;
@group(0) @binding(8) var<storage, read_write> z: array<f32>;

var<workgroup> red: array<f32, 2048>; // 2 * CMAX * WG
var<workgroup> fred: array<f32, 512>; // 2 * FWG

// Workgroup sums of `red` in two levels, between barriers the caller places:
// fold16 (invocations 0..16) leaves red[base + i] = sum over q of
// red[base + i + 16 q]; sum16 then adds those 16. Two barriers instead of the
// seven of a tree.
fn fold16(lid: u32, base: u32) {
    var s: f32 = 0.0;
    for (var q = 0u; q < WG; q += 16u) {
        s += red[base + lid + q];
    }
    red[base + lid] = s;
}

fn sum16(base: u32) -> f32 {
    var s: f32 = 0.0;
    for (var q = 0u; q < 16u; q++) {
        s += red[base + q];
    }
    return s;
}

@compute @workgroup_size(128)
fn update(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let g = wid.x + wid.y * nwg.x;
    if g >= P.groups {
        return;
    }
    let ncols = NCOLS;
    let bs = min(P.bs, 3u);
    let row = g * WG + lid;
    var rz: array<f32, 8>;
    var rr: array<f32, 8>;
    if row < P.rows {
        var m: array<f32, 9>;
        for (var q = 0u; q < bs * bs; q++) {
            m[q] = minv[row * bs * bs + q];
        }
        for (var c = 0u; c < ncols; c++) {
            let alpha = cols[c].alpha;
            let o = c * P.n + row * bs;
            var rv: array<f32, 3>;
            for (var q = 0u; q < bs; q++) {
                let i = o + q;
                x[i] += alpha * p[i];
                let rn = r[i] - alpha * ap[i];
                r[i] = rn;
                rv[q] = rn;
                rr[c] += rn * rn;
            }
            for (var q = 0u; q < bs; q++) {
                var s: f32 = 0.0;
                for (var t = 0u; t < bs; t++) {
                    s += m[q * bs + t] * rv[t];
                }
                z[o + q] = s;
                rz[c] += rv[q] * s;
            }
        }
    }
    for (var c = 0u; c < ncols; c++) {
        red[c * WG + lid] = rz[c];
        red[(CMAX + c) * WG + lid] = rr[c];
    }
    workgroupBarrier();
    if lid < 16u {
        for (var c = 0u; c < ncols; c++) {
            fold16(lid, c * WG);
            fold16(lid, (CMAX + c) * WG);
        }
    }
    workgroupBarrier();
    if lid == 0u {
        for (var c = 0u; c < ncols; c++) {
            partials[c * P.groups + g] = sum16(c * WG);
            partials[(ncols + c) * P.groups + g] = sum16((CMAX + c) * WG);
        }
    }
}

// `update` without the preconditioner, for the AMG V-cycle (amg.wgsl), which
// runs between this kernel and `dot_rz`: x += alpha p, r -= alpha Ap, partials
// slot 1 = r . r (slot 0 is left to dot_rz).
@compute @workgroup_size(128)
fn update_amg(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let g = wid.x + wid.y * nwg.x;
    if g >= P.groups {
        return;
    }
    let ncols = NCOLS;
    let bs = min(P.bs, 3u);
    let row = g * WG + lid;
    var rr: array<f32, 8>;
    if row < P.rows {
        for (var c = 0u; c < ncols; c++) {
            let alpha = cols[c].alpha;
            let o = c * P.n + row * bs;
            for (var q = 0u; q < bs; q++) {
                let i = o + q;
                x[i] += alpha * p[i];
                let rn = r[i] - alpha * ap[i];
                r[i] = rn;
                rr[c] += rn * rn;
            }
        }
    }
    for (var c = 0u; c < ncols; c++) {
        red[(CMAX + c) * WG + lid] = rr[c];
    }
    workgroupBarrier();
    if lid < 16u {
        for (var c = 0u; c < ncols; c++) {
            fold16(lid, (CMAX + c) * WG);
        }
    }
    workgroupBarrier();
    if lid == 0u {
        for (var c = 0u; c < ncols; c++) {
            partials[(ncols + c) * P.groups + g] = sum16((CMAX + c) * WG);
        }
    }
}

// Partials slot 0 = r . z after the AMG V-cycle has written z (pairs with
// update_amg).
@compute @workgroup_size(128)
fn dot_rz(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let g = wid.x + wid.y * nwg.x;
    if g >= P.groups {
        return;
    }
    let ncols = NCOLS;
    let bs = min(P.bs, 3u);
    let row = g * WG + lid;
    var rz: array<f32, 8>;
    if row < P.rows {
        for (var c = 0u; c < ncols; c++) {
            let o = c * P.n + row * bs;
            for (var q = 0u; q < bs; q++) {
                rz[c] += r[o + q] * z[o + q];
            }
        }
    }
    for (var c = 0u; c < ncols; c++) {
        red[c * WG + lid] = rz[c];
    }
    workgroupBarrier();
    if lid < 16u {
        for (var c = 0u; c < ncols; c++) {
            fold16(lid, c * WG);
        }
    }
    workgroupBarrier();
    if lid == 0u {
        for (var c = 0u; c < ncols; c++) {
            partials[c * P.groups + g] = sum16(c * WG);
        }
    }
}

// Sums slot `slot` of column c's partials into fred[0] (all invocations call it).
fn reduce_slot(lid: u32, ncols: u32, slot: u32, c: u32, half: u32) {
    var s: f32 = 0.0;
    let base = (slot * ncols + c) * P.groups;
    for (var i = lid; i < P.groups; i += FWG) {
        s += partials[base + i];
    }
    fred[half * FWG + lid] = s;
}

fn tree(lid: u32) {
    workgroupBarrier();
    for (var h = FWG / 2u; h > 0u; h >>= 1u) {
        if lid < h {
            fred[lid] += fred[lid + h];
            fred[FWG + lid] += fred[FWG + lid + h];
        }
        workgroupBarrier();
    }
}

@compute @workgroup_size(256)
fn finish_alpha(@builtin(local_invocation_index) lid: u32) {
    let ncols = NCOLS;
    for (var c = 0u; c < ncols; c++) {
        reduce_slot(lid, ncols, 0u, c, 0u);
        fred[FWG + lid] = 0.0;
        tree(lid);
        if lid == 0u {
            var st = cols[c];
            let pap = fred[0];
            st.pap = pap;
            if st.done == 0u {
                if pap > 0.0 && pap < HUGE && st.rz > 0.0 && st.rz < HUGE {
                    st.alpha = st.rz / pap;
                    st.iters += 1u;
                } else {
                    st.alpha = 0.0;
                    if st.rr <= TINY {
                        st.done = 1u;
                    } else {
                        st.done = 2u;
                    }
                }
            } else {
                st.alpha = 0.0;
            }
            cols[c] = st;
        }
        workgroupBarrier();
    }
}

@compute @workgroup_size(256)
fn finish_beta(@builtin(local_invocation_index) lid: u32) {
    let ncols = NCOLS;
    for (var c = 0u; c < ncols; c++) {
        reduce_slot(lid, ncols, 0u, c, 0u);
        reduce_slot(lid, ncols, 1u, c, 1u);
        tree(lid);
        if lid == 0u {
            var st = cols[c];
            let rz = fred[0];
            let rr = fred[FWG];
            if st.done == 0u {
                if !(rr < HUGE) || !(rz >= 0.0) {
                    st.done = 2u;
                    st.beta = 0.0;
                } else {
                    if st.rz > 0.0 {
                        st.beta = rz / st.rz;
                    } else {
                        st.beta = 0.0;
                    }
                    st.rz = rz;
                    st.rr = rr;
                    if rr <= st.thr {
                        st.done = 1u;
                    }
                }
            } else {
                st.beta = 0.0;
            }
            cols[c] = st;
        }
        workgroupBarrier();
    }
}

@compute @workgroup_size(256)
fn direction(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let i = gid.x + gid.y * nwg.x * FWG;
    let ncols = NCOLS;
    if i >= P.n * ncols {
        return;
    }
    let c = i / P.n;
    p[i] = z[i] + cols[c].beta * p[i];
}
