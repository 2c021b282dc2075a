// The scale factors' Newton steps on the GPU, in f64 (driven by
// solver-gpu/src/power_sum_newton.rs): paper Eq. 3 solved by sequential
// linearly constrained Newton steps (Sec. 4, Eqs. 15-18), one multiplier per
// constraint, with no host work between the steps.
//
// min (s - 1)^T A (s - 1)  s.t.  C_j(s) = sum_e c_e s_{f_e}^p_j / T_j - 1 = 0,
// A the scale factors' Hessian, whose Cholesky factor solves `Y = A^-1 L^T`
// (supernodal.wgsl, a direct solve between `rows` and `ycols`). Since the
// energy vanishes with its gradient at s = 1, `y = A^-1 (-grad E) = 1 - s`
// needs no solve. A step, each kernel one dispatch:
//   values, finish_values  C_j(s), max |C_j|; done when it is below the
//                          tolerance (or the step budget is spent);
//   rows                   the Jacobian rows L_j = p_j c_e s^(p_j - 1) / T_j;
//   (the factor's solve    Y = A^-1 L^T, for the rows that changed);
//   dots, multipliers      S = L Y, r = L y + C, lambda = pinv(S) r (Eq. 17),
//                          through a Jacobi eigen-decomposition of the
//                          symmetric S, eigenvalues |e| <= 1e-12 max |e|
//                          dropped as the host's SVD drops singular values;
//   direction, step_length dx = y - Y lambda (Eq. 18) and the step length
//                          alpha = min(1, 0.9 (s - floor) / -dx over dx < 0);
//   advance, finish_step   s += alpha dx; done when max |alpha dx| is below
//                          its tolerance.
// Every kernel but `init`, `values` and `finish_values`' sums returns at once
// once the state says done, so a batch recorded past convergence changes
// nothing; the host reads the state and `s` after each batch (one wait).
//
// Bindings (group 0):
//   0  P        uniform  n (unknowns), ge (workgroups over the longest
//                        constraint's entries), gn = ceil(n / WG).
//   1  offsets  read     u32, constraint j's entries at [offsets[j],
//                        offsets[j + 1]).
//   2  faces    read     u32, each entry's unknown f_e (once per constraint).
//   3  coef     read     f64, each entry's c_e.
//   4  targets  read     f64, per constraint: degree p_j, target T_j.
//   5  s        rw       f64, the unknowns (set to 1 by `init`).
//   6  rows     rw       f64, L_j at j n (the solve's right-hand sides).
//   7  ycols    read     f64, Y's column j at j n (the solve's solutions).
//   8  dx       rw       f64, the step.
//   9  partials rw       f64, per-workgroup sums, minima and maxima, slot q
//                        of workgroup g at q ge + g (`values`) or q gn + g.
//  10  state    rw       State: the done flag, steps, tolerances, the last
//                        values, max |C|, alpha, the largest move, lambda.
// NCOLS is k, the number of constraints (at most KMAX).

struct NewtonParams {
    n: u32,
    ge: u32,
    gn: u32,
    pad: u32,
}

// done: 0 running, 1 every |C_j| below tol_res, 2 a step moved less than
// tol_moved, 3 the step budget spent.
struct State {
    done: u32,
    steps: u32,
    max_steps: u32,
    pad: u32,
    tol_res: f64,
    tol_moved: f64,
    floor: f64,
    max_res: f64,
    alpha: f64,
    moved: f64,
    values: array<f64, 8>,
    lambda: array<f64, 8>,
}

const WG: u32 = 256u;
const KMAX: u32 = 8u;
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: NewtonParams;
@group(0) @binding(1) var<storage, read> offsets: array<u32>;
@group(0) @binding(2) var<storage, read> faces: array<u32>;
@group(0) @binding(3) var<storage, read> coef: array<f64>;
@group(0) @binding(4) var<storage, read> targets: array<f64>;
@group(0) @binding(5) var<storage, read_write> s: array<f64>;
@group(0) @binding(6) var<storage, read_write> rows: array<f64>;
@group(0) @binding(7) var<storage, read> ycols: array<f64>;
@group(0) @binding(8) var<storage, read_write> dx: array<f64>;
@group(0) @binding(9) var<storage, read_write> partials: array<f64>;
@group(0) @binding(10) var<storage, read_write> state: State;

var<workgroup> red: array<f64, 256>;
var<workgroup> flag: u32;
// S (k x k, row i at i (k + 1)) and L y (at i (k + 1) + k).
var<workgroup> sums: array<f64, 72>;

// Whether the iteration still runs (the same answer in every invocation of
// the workgroup, so that the barriers after it stay in uniform control flow).
fn running(lid: u32) -> bool {
    if lid == 0u {
        flag = state.done;
    }
    return workgroupUniformLoad(&flag) == 0u;
}

// The workgroup's sum, minimum or maximum of `v` (op 0, 1, 2), in every
// invocation (tree reduction; every invocation calls it).
fn reduce(lid: u32, v: f64, op: u32) -> f64 {
    red[lid] = v;
    workgroupBarrier();
    for (var h = WG / 2u; h > 0u; h >>= 1u) {
        if lid < h {
            let a = red[lid];
            let b = red[lid + h];
            if op == 0u {
                red[lid] = a + b;
            } else if op == 1u {
                red[lid] = min(a, b);
            } else {
                red[lid] = max(a, b);
            }
        }
        workgroupBarrier();
    }
    let out = red[0];
    workgroupBarrier();
    return out;
}

// The first gn partials folded from `init` by op 1 (minimum) or 2
// (maximum), in every invocation.
fn fold_partials(lid: u32, init: f64, op: u32) -> f64 {
    var m = init;
    for (var g = lid; g < P.gn; g += WG) {
        if op == 1u {
            m = min(m, partials[g]);
        } else {
            m = max(m, partials[g]);
        }
    }
    return reduce(lid, m, op);
}

// `x^p` as the host's products (p up to 3: ((x x) x)).
fn power(x: f64, p: u32) -> f64 {
    var r = x;
    if p == 0u {
        return f64(1.0);
    }
    for (var i = 1u; i < p; i++) {
        r *= x;
    }
    return r;
}

fn degree(j: u32) -> u32 {
    return u32(targets[2u * j]);
}

@compute @workgroup_size(256)
fn init(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let f = wid.x * WG + lid;
    if f < P.n {
        s[f] = f64(1.0);
    }
}

// Workgroup (g, j): constraint j's entries g WG.. of its sum (always run, so
// that the state's max |C| is that of the `s` the host reads).
@compute @workgroup_size(256)
fn values(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let j = wid.y;
    let e = offsets[j] + wid.x * WG + lid;
    var v = f64(0.0);
    if e < offsets[j + 1u] {
        v = coef[e] * power(s[faces[e]], degree(j));
    }
    let total = reduce(lid, v, 0u);
    if lid == 0u {
        partials[j * P.ge + wid.x] = total;
    }
}

@compute @workgroup_size(256)
fn finish_values(@builtin(local_invocation_index) lid: u32) {
    var worst = f64(0.0);
    for (var j = 0u; j < NCOLS; j++) {
        var v = f64(0.0);
        for (var g = lid; g < P.ge; g += WG) {
            v += partials[j * P.ge + g];
        }
        let c = reduce(lid, v, 0u) / targets[2u * j + 1u] - f64(1.0);
        worst = max(worst, abs(c));
        if lid == 0u {
            state.values[j] = c;
        }
    }
    if lid == 0u {
        state.max_res = worst;
        if state.done == 0u {
            if worst < state.tol_res {
                state.done = 1u;
            } else if state.steps >= state.max_steps {
                state.done = 3u;
            }
        }
    }
}

// Workgroup (g, j): L_j at constraint j's entries g WG.. (the rest of the
// row stays zero: the host clears `rows` before an estimation).
@compute @workgroup_size(256)
fn jacobian_rows(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    if !running(lid) {
        return;
    }
    let j = wid.y;
    let e = offsets[j] + wid.x * WG + lid;
    if e < offsets[j + 1u] {
        let p = degree(j);
        let f = faces[e];
        var g = f64(0.0);
        if p > 0u {
            g = f64(p) * coef[e] * power(s[f], p - 1u) / targets[2u * j + 1u];
        }
        rows[j * P.n + f] = g;
    }
}

// Workgroup (g, q), q = i (k + 1) + j: L_i . Y_j (j < k) or L_i . y (j = k)
// over the unknowns g WG..
@compute @workgroup_size(256)
fn dots(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    if !running(lid) {
        return;
    }
    let q = wid.y;
    let i = q / (NCOLS + 1u);
    let j = q % (NCOLS + 1u);
    let f = wid.x * WG + lid;
    var v = f64(0.0);
    if f < P.n {
        let a = rows[i * P.n + f];
        if j < NCOLS {
            v = a * ycols[j * P.n + f];
        } else {
            v = a * (f64(1.0) - s[f]);
        }
    }
    let total = reduce(lid, v, 0u);
    if lid == 0u {
        partials[q * P.gn + wid.x] = total;
    }
}

// One workgroup: S and r = L y + C from the partial sums, then lambda.
@compute @workgroup_size(256)
fn multipliers(@builtin(local_invocation_index) lid: u32) {
    if !running(lid) {
        return;
    }
    for (var q = 0u; q < NCOLS * (NCOLS + 1u); q++) {
        var v = f64(0.0);
        for (var g = lid; g < P.gn; g += WG) {
            v += partials[q * P.gn + g];
        }
        let total = reduce(lid, v, 0u);
        if lid == 0u {
            sums[q] = total;
        }
    }
    if lid == 0u {
        solve_multipliers();
    }
}

// lambda = pinv(S) r with S symmetrised, by cyclic Jacobi rotations
// (S = V diag(e) V^T; one invocation, k <= KMAX).
fn solve_multipliers() {
    let k = NCOLS;
    var a: array<f64, 64>;
    var v: array<f64, 64>;
    var r: array<f64, 8>;
    for (var i = 0u; i < k; i++) {
        r[i] = sums[i * (k + 1u) + k] + state.values[i];
        for (var j = 0u; j < k; j++) {
            a[i * KMAX + j] = f64(0.5) * (sums[i * (k + 1u) + j] + sums[j * (k + 1u) + i]);
            v[i * KMAX + j] = select(f64(0.0), f64(1.0), i == j);
        }
    }
    for (var sweep = 0u; sweep < 64u; sweep++) {
        var off = f64(0.0);
        var diag = f64(0.0);
        for (var i = 0u; i < k; i++) {
            diag += a[i * KMAX + i] * a[i * KMAX + i];
            for (var j = i + 1u; j < k; j++) {
                off += a[i * KMAX + j] * a[i * KMAX + j];
            }
        }
        if !(off > f64(1e-32) * diag) {
            break;
        }
        for (var p = 0u; p < k; p++) {
            for (var q = p + 1u; q < k; q++) {
                let apq = a[p * KMAX + q];
                if apq == f64(0.0) {
                    continue;
                }
                let theta = (a[q * KMAX + q] - a[p * KMAX + p]) / (f64(2.0) * apq);
                var t = f64(1.0) / (abs(theta) + sqrt(theta * theta + f64(1.0)));
                if theta < f64(0.0) {
                    t = -t;
                }
                let c = f64(1.0) / sqrt(t * t + f64(1.0));
                let sn = t * c;
                // A J, then J^T (A J); V J.
                for (var m = 0u; m < k; m++) {
                    let amp = a[m * KMAX + p];
                    let amq = a[m * KMAX + q];
                    a[m * KMAX + p] = c * amp - sn * amq;
                    a[m * KMAX + q] = sn * amp + c * amq;
                    let vmp = v[m * KMAX + p];
                    let vmq = v[m * KMAX + q];
                    v[m * KMAX + p] = c * vmp - sn * vmq;
                    v[m * KMAX + q] = sn * vmp + c * vmq;
                }
                for (var m = 0u; m < k; m++) {
                    let apm = a[p * KMAX + m];
                    let aqm = a[q * KMAX + m];
                    a[p * KMAX + m] = c * apm - sn * aqm;
                    a[q * KMAX + m] = sn * apm + c * aqm;
                }
            }
        }
    }
    var emax = f64(0.0);
    for (var i = 0u; i < k; i++) {
        emax = max(emax, abs(a[i * KMAX + i]));
    }
    var lambda: array<f64, 8>;
    for (var i = 0u; i < k; i++) {
        let e = a[i * KMAX + i];
        if abs(e) <= f64(1e-12) * emax || e == f64(0.0) {
            continue;
        }
        var vr = f64(0.0);
        for (var m = 0u; m < k; m++) {
            vr += v[m * KMAX + i] * r[m];
        }
        let w = vr / e;
        for (var m = 0u; m < k; m++) {
            lambda[m] += v[m * KMAX + i] * w;
        }
    }
    for (var i = 0u; i < k; i++) {
        state.lambda[i] = lambda[i];
    }
}

// dx = (1 - s) - sum_j lambda_j Y_j, and the workgroup's least step length
// keeping s at or above the floor.
@compute @workgroup_size(256)
fn direction(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    if !running(lid) {
        return;
    }
    let f = wid.x * WG + lid;
    var lim = f64(1.0);
    if f < P.n {
        let si = s[f];
        var d = f64(1.0) - si;
        for (var j = 0u; j < NCOLS; j++) {
            let l = state.lambda[j];
            if l != f64(0.0) {
                d -= l * ycols[j * P.n + f];
            }
        }
        dx[f] = d;
        if d < f64(0.0) {
            lim = f64(0.9) * max((si - state.floor) / -d, f64(0.0));
        }
    }
    let m = reduce(lid, lim, 1u);
    if lid == 0u {
        partials[wid.x] = m;
    }
}

@compute @workgroup_size(256)
fn step_length(@builtin(local_invocation_index) lid: u32) {
    if !running(lid) {
        return;
    }
    let alpha = fold_partials(lid, f64(1.0), 1u);
    if lid == 0u {
        state.alpha = alpha;
    }
}

@compute @workgroup_size(256)
fn advance(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    if !running(lid) {
        return;
    }
    let f = wid.x * WG + lid;
    var moved = f64(0.0);
    if f < P.n {
        let d = state.alpha * dx[f];
        s[f] += d;
        moved = abs(d);
    }
    let m = reduce(lid, moved, 2u);
    if lid == 0u {
        partials[wid.x] = m;
    }
}

@compute @workgroup_size(256)
fn finish_step(@builtin(local_invocation_index) lid: u32) {
    if !running(lid) {
        return;
    }
    let moved = fold_partials(lid, f64(0.0), 2u);
    if lid == 0u {
        state.moved = moved;
        state.steps += 1u;
        if moved < state.tol_moved {
            state.done = 2u;
        }
    }
}
