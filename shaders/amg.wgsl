// Smoothed-aggregation AMG V-cycle, the PCG preconditioner z = M^-1 r: the
// per-level kernels. The hierarchy (A_l, P_l, R_l = P_l^T, inverted diagonal
// blocks, the dense inverse of the coarsest matrix) is built on the CPU in f64
// (solver-gpu/src/amg.rs) and uploaded as f32.
//
// Driven by solver-gpu/src/amg_gpu.rs, which records one V-cycle as a fixed
// sequence of dispatches, each with its own bind group and parameters:
//   jacobi  mode 0        x_l = w D_l^-1 b_l                    (first pre-sweep)
//   spmv    mode 3        u = v + w D_l^-1 (b_l - A_l v)        (further sweeps,
//                         fused: v and u are x_l and t_l in turn)
//   spmv    mode 1        s = b_l - A_l v                       (residual; s the
//                         one of x_l, t_l not holding the iterate v)
//   spmv    mode 0        b_l+1 = R_l s                         (restriction)
//   dense                 x_L = C^-1 b_L                        (coarsest level)
//   spmv    mode 2        v += P_l x_l+1                        (prolongation)
//   spmv    mode 1, then jacobi mode 1 (t_l = b_l - A_l x_l; x_l += w D_l^-1 t_l):
//                         an unfused sweep in place, where the iterate must
//                         end in x_l (the finest level's z) and the fused
//                         sweeps would leave it in t_l.
// (`spmv_wide` in place of `spmv` for the wide-block matrices of an affine
// hierarchy, one invocation per scalar row: modes 0-2 only, so its levels
// sweep unfused, spmv mode 1 then jacobi mode 1.)
//
// A matrix whose values pass one storage binding (max_storage_buffer_binding_size)
// is split by block rows into chunks (solver-gpu/src/matrix.rs, split_rows):
// each product step is then one dispatch per chunk, each with its own
// parameters (`row0`, `block0`) and bind group (its `vals` and `block_cols`).
//
// Bindings (group 0), shared by every entry point:
//   0  P        uniform   rows = end of this dispatch's output rows (block
//                         rows; scalar rows for `spmv_wide` and `dense`), row0
//                         = its first row (0 unless the matrix is chunked), n
//                         = column stride of y and b, nx = column stride of x,
//                         groups = ceil((rows - row0) / WG) (2-D dispatch,
//                         linear workgroup index wid.x + wid.y * nwg.x, rows
//                         past `rows` do nothing), mode (see above), omega =
//                         Jacobi weight, block0 = the chunk's first block
//                         (block k of the matrix is at k - block0 in 2 and 8).
//   1  row_ptr  read      block rows + 1 offsets (block units, of the whole
//                         matrix).
//   2  vals     read      f32: the values of the step's matrix (A_l, P_l or
//                         R_l; rectangular for P and R), its chunk's blocks
//                         one after another, each row-major: BS x BS values a
//                         block (`spmv`), BR x BC (`spmv_wide`), one a stored
//                         entry (`spmv3`); or the row-major rows x rows
//                         inverse of the coarsest matrix (`dense`).
//   4  x        read      NCOLS input columns, column-major, stride nx.
//   5  b        read      right-hand side (spmv mode 1) or residual (jacobi),
//                         stride n.
//   6  y        rw        output, stride n (read too by the accumulating modes).
//                         Mode 3 writes y = x + w D^-1 (b - A x): y and x are
//                         different buffers (every row reads the old x).
//   7  dinv     read      omega times the inverted diagonal blocks, BS * BS f32
//                         per block row (`jacobi`, and `spmv` / `spmv3` in
//                         mode 3).
//   8  block_cols read    u32 block column per block of the chunk (`spmv`,
//                         `spmv_wide`), or per entry of a scalar CSR matrix
//                         (`spmv3`).
// Unused bindings hold a small placeholder buffer. A block costs its values
// and one u32 column (40 bytes for 3x3), the least it can be stored in.
//
// A scalar hierarchy applied to 3-vectors (the squared-Laplacian
// preconditioner's `B (x) I3`: x, y and z of a vertex interleaved, the PCG's
// layout) runs `spmv3` in place of `spmv`, and `jacobi` and `dense` with
// KRON = 3, same modes: each scalar entry acts on the three components, so
// a stored entry costs 8 bytes (value and column) where its `v I3` block
// would cost 40.

struct AmgParams {
    rows: u32,
    n: u32,
    nx: u32,
    groups: u32,
    mode: u32,
    omega: f32,
    row0: u32,
    block0: u32,
}

const WG: u32 = 128u;
// Columns handled by this pipeline (1..=8) and the block size (`spmv`: 3 or 1,
// the matrix's blocks; `jacobi`: 1, 3 or 12, its diagonal blocks),
// fixed when the pipeline is created: the loops unroll.
override NCOLS: u32 = 1u;
override BS: u32 = 3u;
// Components each scalar row acts on (`jacobi`, `dense`): 1, or 3 for a
// scalar hierarchy on interleaved 3-vectors (x, y, z of a vertex).
override KRON: u32 = 1u;

@group(0) @binding(0) var<uniform> P: AmgParams;
@group(0) @binding(1) var<storage, read> row_ptr: array<u32>;
@group(0) @binding(2) var<storage, read> vals: array<f32>;
@group(0) @binding(4) var<storage, read> x: array<f32>;
@group(0) @binding(5) var<storage, read> b: array<f32>;
@group(0) @binding(6) var<storage, read_write> y: array<f32>;
@group(0) @binding(7) var<storage, read> dinv: array<f32>;
@group(0) @binding(8) var<storage, read> block_cols: array<u32>;

// Block shape of `spmv_wide` (BR x BC <= 12 x 12): 3 x 12 for the finest P of an
// affine hierarchy, 12 x 3 for its R, 12 x 12 past the finest level.
override BR: u32 = 12u;
override BC: u32 = 12u;

fn row_of(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    let g = wid.x + wid.y * nwg.x;
    if g >= P.groups {
        return 0xffffffffu;
    }
    return P.row0 + g * WG + lid;
}

// Output `v` (a row of A x) at `i` by mode: y = A x (0), y = b - A x (1),
// y += A x (2).
fn store(i: u32, v: f32) {
    if P.mode == 0u {
        y[i] = v;
    } else if P.mode == 1u {
        y[i] = b[i] - v;
    } else {
        y[i] += v;
    }
}

// y = A x (mode 0), y = b - A x (mode 1), y += A x (mode 2), y = x + w D^-1
// (b - A x) (mode 3, the fused damped-Jacobi sweep; x of stride P.nx = P.n).
@compute @workgroup_size(128)
fn spmv(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let row = row_of(wid, nwg, lid);
    if row >= P.rows {
        return;
    }
    let bs = min(BS, 3u);
    var acc: array<f32, 24>; // NCOLS * BS <= 8 * 3
    let k0 = row_ptr[row] - P.block0;
    let k1 = row_ptr[row + 1u] - P.block0;
    for (var k = k0; k < k1; k++) {
        var m: array<f32, 9>;
        let j = block_cols[k];
        for (var e = 0u; e < bs * bs; e++) {
            m[e] = vals[bs * bs * k + e];
        }
        for (var c = 0u; c < NCOLS; c++) {
            let o = c * P.nx + j * bs;
            var xv: array<f32, 3>;
            for (var t = 0u; t < bs; t++) {
                xv[t] = x[o + t];
            }
            for (var q = 0u; q < bs; q++) {
                var s = 0.0;
                for (var t = 0u; t < bs; t++) {
                    s += m[q * bs + t] * xv[t];
                }
                acc[c * bs + q] += s;
            }
        }
    }
    if P.mode == 3u {
        let d0 = row * bs * bs;
        for (var c = 0u; c < NCOLS; c++) {
            let o = c * P.n + row * bs;
            var res: array<f32, 3>;
            for (var t = 0u; t < bs; t++) {
                res[t] = b[o + t] - acc[c * bs + t];
            }
            for (var q = 0u; q < bs; q++) {
                var s = 0.0;
                for (var t = 0u; t < bs; t++) {
                    s += dinv[d0 + q * bs + t] * res[t];
                }
                y[o + q] = x[c * P.nx + row * bs + q] + P.omega * s;
            }
        }
        return;
    }
    for (var c = 0u; c < NCOLS; c++) {
        for (var q = 0u; q < bs; q++) {
            store(c * P.n + row * bs + q, acc[c * bs + q]);
        }
    }
}

// As `spmv`, for BR x BC blocks (BR x BC values a block, row-major), one
// invocation per scalar row (`P.row0`, `P.rows` in scalar rows: block rows x
// BR).
@compute @workgroup_size(128)
fn spmv_wide(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let r = row_of(wid, nwg, lid);
    if r >= P.rows {
        return;
    }
    let br = min(BR, 12u);
    let bc = min(BC, 12u);
    let row = r / br;
    let q = r % br;
    var acc: array<f32, 8>;
    let k0 = row_ptr[row] - P.block0;
    let k1 = row_ptr[row + 1u] - P.block0;
    for (var k = k0; k < k1; k++) {
        let j = block_cols[k];
        let o = (k * br + q) * bc;
        for (var s = 0u; s < bc; s++) {
            let v = vals[o + s];
            for (var c = 0u; c < NCOLS; c++) {
                acc[c] += v * x[c * P.nx + j * bc + s];
            }
        }
    }
    for (var c = 0u; c < NCOLS; c++) {
        store(c * P.n + r, acc[c]);
    }
}

// y = omega D^-1 b (mode 0), y += omega D^-1 b (mode 1); one invocation per
// diagonal block (BS <= 12: 3 at the finest level, 12 on the coarse levels of
// the affine hierarchy; 1 with KRON = 3 on 3-vectors, one value per vertex).
@compute @workgroup_size(128)
fn jacobi(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let row = row_of(wid, nwg, lid);
    if row >= P.rows {
        return;
    }
    let bs = min(BS, 12u);
    let d0 = row * bs * bs;
    for (var c = 0u; c < NCOLS; c++) {
        for (var k = 0u; k < KRON; k++) {
            let o = c * P.n + row * bs * KRON + k;
            var rv: array<f32, 12>;
            for (var t = 0u; t < bs; t++) {
                rv[t] = b[o + t * KRON];
            }
            for (var q = 0u; q < bs; q++) {
                var s = 0.0;
                for (var t = 0u; t < bs; t++) {
                    s += dinv[d0 + q * bs + t] * rv[t];
                }
                s *= P.omega;
                if P.mode == 0u {
                    y[o + q * KRON] = s;
                } else {
                    y[o + q * KRON] += s;
                }
            }
        }
    }
}

// y = C^-1 x on the coarsest level: one invocation per (scalar) row of the dense
// rows x rows inverse, applied to KRON components per row.
@compute @workgroup_size(128)
fn dense(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let row = row_of(wid, nwg, lid);
    if row >= P.rows {
        return;
    }
    let nr = P.rows;
    var acc: array<f32, 24>; // NCOLS * KRON <= 8 * 3
    for (var j = 0u; j < nr; j++) {
        let a = vals[row * nr + j];
        for (var c = 0u; c < NCOLS; c++) {
            for (var k = 0u; k < KRON; k++) {
                acc[c * KRON + k] += a * x[c * P.nx + j * KRON + k];
            }
        }
    }
    for (var c = 0u; c < NCOLS; c++) {
        for (var k = 0u; k < KRON; k++) {
            y[c * P.n + row * KRON + k] = acc[c * KRON + k];
        }
    }
}

// y = A x (mode 0), y = b - A x (mode 1), y += A x (mode 2), y = x + w D^-1
// (b - A x) (mode 3) for a scalar CSR matrix (values `vals`, columns
// `block_cols`) on interleaved 3-vectors: one invocation per scalar row,
// writing its three components per column.
@compute @workgroup_size(128)
fn spmv3(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let row = row_of(wid, nwg, lid);
    if row >= P.rows {
        return;
    }
    var acc: array<vec3<f32>, 8>;
    let k0 = row_ptr[row] - P.block0;
    let k1 = row_ptr[row + 1u] - P.block0;
    for (var k = k0; k < k1; k++) {
        let a = vals[k];
        let j = 3u * block_cols[k];
        for (var c = 0u; c < NCOLS; c++) {
            let o = c * P.nx + j;
            acc[c] += a * vec3<f32>(x[o], x[o + 1u], x[o + 2u]);
        }
    }
    if P.mode == 3u {
        let d = P.omega * dinv[row];
        for (var c = 0u; c < NCOLS; c++) {
            let o = c * P.n + 3u * row;
            let ox = c * P.nx + 3u * row;
            let v = vec3<f32>(x[ox], x[ox + 1u], x[ox + 2u]);
            let r = vec3<f32>(b[o], b[o + 1u], b[o + 2u]) - acc[c];
            let u = v + d * r;
            y[o] = u.x;
            y[o + 1u] = u.y;
            y[o + 2u] = u.z;
        }
        return;
    }
    for (var c = 0u; c < NCOLS; c++) {
        let o = c * P.n + 3u * row;
        store(o, acc[c].x);
        store(o + 1u, acc[c].y);
        store(o + 2u, acc[c].z);
    }
}
