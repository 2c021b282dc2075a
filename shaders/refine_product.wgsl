// y = A x in f64 with the matrix's exact f64 values, for the residuals of the
// mixed-precision solve's refinement rounds (driven by solver-gpu/src/refine.rs;
// its `refine.wgsl` forms b - y). The PCG's own f64 product reads each value as
// two f32 parts (48 bits, bsr_spmv_f64.wgsl); the residual that decides when a
// solve is done must be of the matrix itself, as the host's was. So each block
// is read from the f64 lower triangle that `sum_shape_blocks.wgsl` or the host
// wrote and `expand_blocks.wgsl` expanded, through the same block map: 72 bytes
// a lower block and 4 a block of both triangles, once per round, not per
// iteration.
//
// As in bsr_spmv_f64.wgsl the blocks' columns come in chunks of block rows,
// one dispatch per chunk.
//
// `refine_row_abs`, with the same bindings and dispatches, writes per block
// row the largest of its three rows' absolute sums into `y[row]`: the rows'
// part of ||A||_inf for the rounding floor (`refine.wgsl`'s
// `rounding_floor` takes their maximum), once per matrix, where the host
// would walk every value (`HostMatrix::norm_inf`). In block-CSR order, each
// block's row of three values summed before it is added, as the host sums
// them (the same bits).
//
// Bindings (group 0):
//   0  P       uniform  n = length of one column (3 x block rows), ncols
//                       (= NCOLS).
//   1  row_ptr read     block rows + 1 offsets into the blocks (whole matrix).
//   2  map     read     u32 per block of both triangles (block-CSR order): its
//                       lower block as its part (bits 29-30) and offset there
//                       (bits 0-28), bit 31 set for the transpose; 0xFFFFFFFF
//                       a zero block, 0xFFFFFFFE the identity (held vertices).
//   3  lower0  read     f64, 9 per lower block, row-major: the first part of
//                       them (`LowerParts`; 8, 9, 10 the others, bound to
//                       part 0 where there are fewer).
//   4  x       read     f64, ncols columns of length n, column-major.
//   5  y       rw       y = A x, same layout; every entry of the chunk's rows
//                       in the first ncols columns is written
//                       (`refine_row_abs`: y[row] per block row of the
//                       chunk).
//   6  cols    read     u32 block column per block of the chunk.
//   7  C       uniform  this chunk: block rows row0..row1, its first block
//                       block0 (group0 unused here).
//   8  lower1  read     f64, the second part of the lower blocks.
//   9  lower2  read     f64, the third.
//   10 lower3  read     f64, the fourth.
// One invocation per block row of the chunk, WG per workgroup, 2-D dispatch
// (local workgroup index wid.x + wid.y * nwg.x).

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

struct Chunk {
    row0: u32,
    row1: u32,
    group0: u32,
    block0: u32,
}

const WG: u32 = 128u;
const ZERO: u32 = 0xFFFFFFFFu;
const IDENTITY: u32 = 0xFFFFFFFEu;
const TRANSPOSE: u32 = 0x80000000u;
const PART_SHIFT: u32 = 29u;
const OFFSET: u32 = 0x1FFFFFFFu;
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> row_ptr: array<u32>;
@group(0) @binding(2) var<storage, read> map: array<u32>;
@group(0) @binding(3) var<storage, read> lower0: array<f64>;
@group(0) @binding(4) var<storage, read> x: array<f64>;
@group(0) @binding(5) var<storage, read_write> y: array<f64>;
@group(0) @binding(6) var<storage, read> cols: array<u32>;
@group(0) @binding(7) var<uniform> C: Chunk;
@group(0) @binding(8) var<storage, read> lower1: array<f64>;
@group(0) @binding(9) var<storage, read> lower2: array<f64>;
@group(0) @binding(10) var<storage, read> lower3: array<f64>;

// The three values from `o` on of the lower blocks' part `part` (a row of a
// block).
fn lower_row(part: u32, o: u32) -> vec3<f64> {
    switch part {
        case 0u: {
            return vec3<f64>(lower0[o], lower0[o + 1u], lower0[o + 2u]);
        }
        case 1u: {
            return vec3<f64>(lower1[o], lower1[o + 1u], lower1[o + 2u]);
        }
        case 2u: {
            return vec3<f64>(lower2[o], lower2[o + 1u], lower2[o + 2u]);
        }
        default: {
            return vec3<f64>(lower3[o], lower3[o + 1u], lower3[o + 2u]);
        }
    }
}

struct Block {
    r0: vec3<f64>,
    r1: vec3<f64>,
    r2: vec3<f64>,
}

// The rows of the block of both triangles that `m` (its map entry, not ZERO)
// names: the identity, or a lower block as stored or transposed.
fn block(m: u32) -> Block {
    if m == IDENTITY {
        return Block(
            vec3<f64>(f64(1.0), f64(0.0), f64(0.0)),
            vec3<f64>(f64(0.0), f64(1.0), f64(0.0)),
            vec3<f64>(f64(0.0), f64(0.0), f64(1.0)),
        );
    }
    let o = 9u * (m & OFFSET);
    let part = (m >> PART_SHIFT) & 3u;
    let r0 = lower_row(part, o);
    let r1 = lower_row(part, o + 3u);
    let r2 = lower_row(part, o + 6u);
    if (m & TRANSPOSE) != 0u {
        return Block(
            vec3<f64>(r0.x, r1.x, r2.x),
            vec3<f64>(r0.y, r1.y, r2.y),
            vec3<f64>(r0.z, r1.z, r2.z),
        );
    }
    return Block(r0, r1, r2);
}

// |v.x| + |v.y| + |v.z|, left to right.
fn abs_sum(v: vec3<f64>) -> f64 {
    return abs(v.x) + abs(v.y) + abs(v.z);
}

fn xv(c: u32, j: u32) -> vec3<f64> {
    let o = c * P.n + 3u * j;
    return vec3<f64>(x[o], x[o + 1u], x[o + 2u]);
}

// The block row of invocation `lid` of workgroup `wid` (2-D dispatch) in
// this chunk.
fn chunk_row(wid: vec3<u32>, nwg: vec3<u32>, lid: u32) -> u32 {
    return C.row0 + (wid.x + wid.y * nwg.x) * WG + lid;
}

@compute @workgroup_size(128)
fn refine_product(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let row = chunk_row(wid, nwg, lid);
    if row >= C.row1 {
        return;
    }
    var yv: array<vec3<f64>, 8>;
    for (var c = 0u; c < NCOLS; c++) {
        yv[c] = vec3<f64>(f64(0.0), f64(0.0), f64(0.0));
    }
    for (var k = row_ptr[row]; k < row_ptr[row + 1u]; k++) {
        let m = map[k];
        if m == ZERO {
            continue;
        }
        let j = cols[k - C.block0];
        let b = block(m);
        for (var c = 0u; c < NCOLS; c++) {
            let v = xv(c, j);
            yv[c] += vec3<f64>(dot(b.r0, v), dot(b.r1, v), dot(b.r2, v));
        }
    }
    for (var c = 0u; c < NCOLS; c++) {
        let o = c * P.n + 3u * row;
        y[o] = yv[c].x;
        y[o + 1u] = yv[c].y;
        y[o + 2u] = yv[c].z;
    }
}

@compute @workgroup_size(128)
fn refine_row_abs(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let row = chunk_row(wid, nwg, lid);
    if row >= C.row1 {
        return;
    }
    var acc = vec3<f64>(f64(0.0), f64(0.0), f64(0.0));
    for (var k = row_ptr[row]; k < row_ptr[row + 1u]; k++) {
        let m = map[k];
        if m == ZERO {
            continue;
        }
        let b = block(m);
        acc += vec3<f64>(abs_sum(b.r0), abs_sum(b.r1), abs_sum(b.r2));
    }
    y[row] = max(max(acc.x, acc.y), acc.z);
}
