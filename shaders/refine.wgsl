// Iterative refinement of the mixed-precision solve on the GPU, in f64
// (driven by solver-gpu/src/refine.rs): the true residual r = b - A x and the
// norms that decide each round, computed where x and A are, so the host sends
// b (and a starting x) once per solve and reads the norms with the PCG's column
// states; it forms no residual and adds no correction itself.
//
// A round: `start` turns the last residual's norms into the PCG's right-hand
// side r / ||r|| and threshold, per column (`scale_r` writes it); the PCG
// (pcg.wgsl) solves A d = r / ||r||; `add` forms x' = x + ||r|| d, the exact
// f64 product writes A x' into `ax` (a scalar matrix's f64 CSR SpMV, a block
// matrix's refine_product.wgsl), `residual` forms
// r' = b - A x' with the partial sums of r'.r' and x'.x', `finish` sums them.
// With `scale` zero (the first round, before any PCG), `add` copies x.
//
// Bindings (group 0):
//   0  P       uniform  rows, ncols (= NCOLS), n = length of a column,
//                       groups = ceil(n / WG) (the partial sums' workgroups).
//   1  aim     rw       f64: aim[c] = ||b_c|| (c < ncols), aim[CMAX] = the
//                       relative residual asked for (tol), aim[CMAX + 1] =
//                       eps ||A||_inf (the f64 rounding floor's factor):
//                       the host's, or `rounding_floor`'s (its one writer
//                       here).
//   2  b       read     f64, the right-hand sides, column-major, stride n.
//   3  ax      read     f64, A x' (the SpMV's output, the PCG's `Ap` buffer);
//                       for `rounding_floor`, the block rows' largest
//                       absolute row sums (`refine_product.wgsl`'s
//                       `refine_row_abs`).
//   4  x       read     f64, the solution so far.
//   5  d       read     f64, the PCG's solution of the round (its `x` buffer).
//   6  xnew    rw       f64, x' = x + scale d (`add`), read by `residual`.
//   7  rtrue   rw       f64, r' = b - A x' (`residual`), read by `scale_r`.
//   8  partials rw      f64, (s ncols + c) groups + g: s = 0 r'.r', 1 x'.x'.
//   9  norms   rw       f64, 3 per column: r'.r', x'.x' (`finish`), and the
//                       round's scale ||r|| (0 or -1: column done; see
//                       `start`); then, at 3 NCOLS, aim[CMAX + 1] (`finish`
//                       copies it: the host reads the floor with the sums).
//  10  rp      rw       f64, the PCG's right-hand side r / ||r|| (`scale_r`).
//  11  cols    rw       the PCG's column states (ColState of pcg.wgsl, f64):
//                       `start` writes each column's threshold.
// `add`, `residual` and `scale_r`: one invocation per entry of the columns,
// 2-D dispatch (linear index gid.x + gid.y * nwg.x * WG), past the end return;
// `residual` reduces per workgroup of one column (workgroup g of column c is
// c groups + g); `finish`, `start` and `rounding_floor`: one workgroup.

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

struct ColState {
    rz: f64,
    pap: f64,
    alpha: f64,
    beta: f64,
    rr: f64,
    thr: f64,
    done: u32,
    iters: u32,
}

const WG: u32 = 256u;
const CMAX: u32 = 8u;
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read_write> aim: array<f64>;
@group(0) @binding(2) var<storage, read> b: array<f64>;
@group(0) @binding(3) var<storage, read> ax: array<f64>;
@group(0) @binding(4) var<storage, read> x: array<f64>;
@group(0) @binding(5) var<storage, read> d: array<f64>;
@group(0) @binding(6) var<storage, read_write> xnew: array<f64>;
@group(0) @binding(7) var<storage, read_write> rtrue: array<f64>;
@group(0) @binding(8) var<storage, read_write> partials: array<f64>;
@group(0) @binding(9) var<storage, read_write> norms: array<f64>;
@group(0) @binding(10) var<storage, read_write> rp: array<f64>;
@group(0) @binding(11) var<storage, read_write> cols: array<ColState>;

var<workgroup> red: array<f64, 512>; // 2 WG

// The workgroup's sums of `rr` and `xx` into red[0] and red[WG] (tree
// reduction; every invocation of the workgroup calls it).
fn sum_pairs(lid: u32, rr: f64, xx: f64) {
    red[lid] = rr;
    red[WG + lid] = xx;
    workgroupBarrier();
    for (var h = WG / 2u; h > 0u; h >>= 1u) {
        if lid < h {
            red[lid] += red[lid + h];
            red[WG + lid] += red[WG + lid + h];
        }
        workgroupBarrier();
    }
}

@compute @workgroup_size(256)
fn add(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * WG;
    if i >= P.n * NCOLS {
        return;
    }
    let s = norms[3u * (i / P.n) + 2u];
    if s > f64(0.0) {
        xnew[i] = x[i] + s * d[i];
    } else {
        xnew[i] = x[i];
    }
}

@compute @workgroup_size(256)
fn residual(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let w = wid.x + wid.y * nwg.x;
    if w >= P.groups * NCOLS {
        return;
    }
    let c = w / P.groups;
    let g = w % P.groups;
    let k = g * WG + lid;
    var rr = f64(0.0);
    var xx = f64(0.0);
    if k < P.n {
        let i = c * P.n + k;
        let r = b[i] - ax[i];
        rtrue[i] = r;
        rr = r * r;
        xx = xnew[i] * xnew[i];
    }
    sum_pairs(lid, rr, xx);
    if lid == 0u {
        partials[c * P.groups + g] = red[0];
        partials[(NCOLS + c) * P.groups + g] = red[WG];
    }
}

@compute @workgroup_size(256)
fn finish(@builtin(local_invocation_index) lid: u32) {
    for (var c = 0u; c < NCOLS; c++) {
        var rr = f64(0.0);
        var xx = f64(0.0);
        for (var g = lid; g < P.groups; g += WG) {
            rr += partials[c * P.groups + g];
            xx += partials[(NCOLS + c) * P.groups + g];
        }
        sum_pairs(lid, rr, xx);
        if lid == 0u {
            norms[3u * c] = red[0];
            norms[3u * c + 1u] = red[WG];
        }
        workgroupBarrier();
    }
    if lid == 0u {
        norms[3u * NCOLS] = aim[CMAX + 1u];
    }
}

// The rounding floor's factor eps ||A||_inf into aim[CMAX + 1], from the
// block rows' largest absolute row sums in ax[0 .. n / 3]
// (`refine_row_abs`): once per matrix, before its first round's residual.
// A maximum, so the same whatever the order. eps = 2^-52.
@compute @workgroup_size(256)
fn rounding_floor(@builtin(local_invocation_index) lid: u32) {
    var m = f64(0.0);
    for (var i = lid; i < P.n / 3u; i += WG) {
        m = max(m, ax[i]);
    }
    red[lid] = m;
    workgroupBarrier();
    for (var h = WG / 2u; h > 0u; h >>= 1u) {
        if lid < h {
            red[lid] = max(red[lid], red[lid + h]);
        }
        workgroupBarrier();
    }
    if lid == 0u {
        aim[CMAX + 1u] = red[0] / f64(4503599627370496.0);
    }
}

// Per column, as the host's `residuals` and round set-up do: the target is
// the tolerance, or, once the column has run a round, the rounding floor
// eps ||A|| ||x|| / ||b|| where that is larger; a column above it runs with
// the right-hand side r / ||r|| to the squared threshold eta^2, eta = 0.5
// tol / rel clamped to [1e-13, 0.1]: the PCG's own recurrence reduces the
// error below what the floor lets the true residual show
// (GpuSolver::round_eta). The column's scale (norms[3 c + 2]) is the
// round's ||r|| while it runs, 0 before it has run one (and while done
// without one), -1 once done after one.
@compute @workgroup_size(1)
fn start() {
    for (var c = 0u; c < NCOLS; c++) {
        let bn = aim[c];
        let ran = norms[3u * c + 2u] != f64(0.0);
        var scale = f64(0.0);
        var thr = f64(0.0);
        if bn > f64(0.0) {
            let rn = sqrt(norms[3u * c]);
            let rel = rn / bn;
            var aimed = aim[CMAX];
            if ran {
                aimed = max(aimed, aim[CMAX + 1u] * sqrt(norms[3u * c + 1u]) / bn);
            }
            if rel > aimed {
                scale = rn;
                let eta = clamp(f64(0.5) * aim[CMAX] / rel, f64(1e-13), f64(0.1));
                thr = eta * eta;
            } else if ran {
                scale = f64(-1.0);
            }
        }
        norms[3u * c + 2u] = scale;
        cols[c].thr = thr;
    }
}

@compute @workgroup_size(256)
fn scale_r(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * WG;
    if i >= P.n * NCOLS {
        return;
    }
    let s = norms[3u * (i / P.n) + 2u];
    if s > f64(0.0) {
        rp[i] = rtrue[i] / s;
    } else {
        rp[i] = f64(0.0);
    }
}
