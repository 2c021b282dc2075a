// The values of a symmetric 3x3 block matrix, uploaded once per new matrix as
// its lower triangle in f64, expanded on the GPU into the block product's
// storage: both triangles, rows and columns of held vertices the identity, as
// f32 high parts `hi = f32(v)` and, for the mixed-precision product, low parts
// `lo = f32(v - f64(hi))` (driven by solver-gpu/src/expand_blocks.rs). The
// host sends 72 bytes per lower block instead of 36 (f32) or 72 (f64) per
// block of both triangles, and converts nothing.
//
// Bindings (group 0):
//   0  C      uniform   this chunk of the block product's storage: its first
//                       block block0 and its block count; split = 1 when `lo`
//                       is written.
//   1  lower0 read      f64, 9 per lower-triangle block (row-major), in the
//                       order of the lower CSC input: the first part of
//                       them (`LowerParts`; 5, 6, 7 the others, bound to
//                       part 0 where there are fewer).
//   2  map    read      u32 per block of the whole matrix (both triangles,
//                       block-CSR order): the lower block it comes from, as
//                       its part (bits 29-30) and offset there (bits 0-28),
//                       bit 31 set when it is that block's transpose;
//                       0xFFFFFFFF a zero block, 0xFFFFFFFE the identity
//                       (the rows and columns of held vertices).
//   3  hi     rw        f32, 9 per block of the chunk (its `vals`), block k
//                       at k - block0.
//   4  lo     rw        f32, the same layout (the chunk's low parts); a
//                       placeholder when split = 0.
//   5  lower1 read      f64, the second part of the lower blocks.
//   6  lower2 read      f64, the third.
//   7  lower3 read      f64, the fourth.
// One invocation per block, 256 per workgroup, 2-D dispatch (linear index
// gid.x + gid.y * nwg.x * 256); invocations past the chunk's blocks return.

struct ExpandParams {
    block0: u32,
    blocks: u32,
    split: u32,
    pad: u32,
}

const FWG: u32 = 256u;
const ZERO: u32 = 0xFFFFFFFFu;
const IDENTITY: u32 = 0xFFFFFFFEu;
const TRANSPOSE: u32 = 0x80000000u;
const PART_SHIFT: u32 = 29u;
const OFFSET: u32 = 0x1FFFFFFFu;
// Set by the host for every kernel (columns); one matrix here, unused.
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> C: ExpandParams;
@group(0) @binding(1) var<storage, read> lower0: array<f64>;
@group(0) @binding(2) var<storage, read> map: array<u32>;
@group(0) @binding(3) var<storage, read_write> hi: array<f32>;
@group(0) @binding(4) var<storage, read_write> lo: array<f32>;
@group(0) @binding(5) var<storage, read> lower1: array<f64>;
@group(0) @binding(6) var<storage, read> lower2: array<f64>;
@group(0) @binding(7) var<storage, read> lower3: array<f64>;

// Value `at` of the lower blocks' part `part`.
fn lower(part: u32, at: u32) -> f64 {
    switch part {
        case 0u: {
            return lower0[at];
        }
        case 1u: {
            return lower1[at];
        }
        case 2u: {
            return lower2[at];
        }
        default: {
            return lower3[at];
        }
    }
}

@compute @workgroup_size(256)
fn expand_blocks(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * FWG;
    if i >= C.blocks || NCOLS == 0u {
        return;
    }
    let m = map[C.block0 + i];
    for (var q = 0u; q < 9u; q++) {
        var v = f64(0.0);
        if m == IDENTITY {
            if q % 4u == 0u {
                v = f64(1.0);
            }
        } else if m != ZERO {
            let src = m & OFFSET;
            let part = (m >> PART_SHIFT) & 3u;
            // Entry (r, c) of the transpose is entry (c, r) of the block.
            var at = q;
            if (m & TRANSPOSE) != 0u {
                at = 3u * (q % 3u) + q / 3u;
            }
            v = lower(part, 9u * src + at);
        }
        let h = f32(v);
        hi[9u * i + q] = h;
        if C.split != 0u {
            lo[9u * i + q] = f32(v - f64(h));
        }
    }
}
