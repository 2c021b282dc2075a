// The read-bandwidth ceiling of the adapter: the least work a kernel can do per
// byte read. Each invocation sums a run of vec4<f32> storage-buffer elements and
// writes one partial, so its time is the floor of any kernel that must read
// those bytes the same way. The benchmark (`pcg_kernels`) compares it with the
// PCG iteration, whose matrix read alone is most of the bytes it must move.
//
// Driven by solver-gpu/src/stream.rs.
//
// Bindings (group 0):
//   0  P        uniform   elements = vec4 elements to read, groups = workgroups
//                         holding them (each reads WG * PER elements); 2-D
//                         dispatch, linear index wid.x + wid.y * nwg.x.
//   2  src      read      the values as vec4<f32> in a storage buffer (the
//                         storage the solver's matrices live in).
//   3  partials write     one sum per invocation (groups * WG), so that the
//                         reads cannot be optimised away.
//
// Invocation `lid` of workgroup g reads elements g * WG * PER + k * WG + lid,
// k < PER: neighbouring invocations read neighbouring elements (coalesced).

struct Params {
    elements: u32,
    groups: u32,
    pad0: u32,
    pad1: u32,
}

const WG: u32 = 128u;
const PER: u32 = 16u;
// Column count of the shared pipeline cache (unused: one pass reads once).
override NCOLS: u32 = 1u;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(2) var<storage, read> src: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> partials: array<f32>;

@compute @workgroup_size(128)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
) {
    let g = wid.x + wid.y * nwg.x;
    if g >= P.groups || NCOLS == 0u {
        return;
    }
    var s = vec4<f32>(0.0);
    for (var k = 0u; k < PER; k++) {
        let t = g * WG * PER + k * WG + lid;
        if t < P.elements {
            s += src[t];
        }
    }
    partials[g * WG + lid] = s.x + s.y + s.z + s.w;
}
