// Marching cubes over voxel blocks: one invocation per cell of each meshing job.
//
// CPU reference and definition of the output: `relfusion_slam::fusion::marching`; the runner
// is `relfusion_slam::fusion::gpu_marching` (Rust mirrors of the structs below, size-asserted
// there). Cell (x, y, z) of a job's block has its corners at block-local voxels
// (x + dx, y + dy, z + dz); a coordinate of 8 lies in one of the seven upper neighbours, whose
// slots the job carries (-1 = missing). A cell emits nothing when a corner is in a missing
// neighbour or has weight <= min_weight.
//
// The case table is generated on the CPU (`fusion::mc_table`) and uploaded as `table`:
// `case_stride` words per case, the triangle count then three edge ids per triangle. Edge e
// runs along axis e / 4 from the corner whose index is e % 4 with a zero bit inserted at
// position `axis` (same formula as `mc_table::edge_corners`).
//
// Output: triangles are appended through the atomic `counter`, in whatever order invocations
// run; the runner sorts them by (job, cell, triangle in case). The counter counts every
// triangle, also those past `capacity` that were not written, so the runner knows the exact
// size for a re-run.
//
// Vertex arithmetic (same f32 operations in the same order as the CPU's `edge_vertex`): on
// the edge from its lower endpoint a to its upper endpoint b, s = ta / (ta - tb),
// p = pa + s (pb - pa) with pa = f32(voxel_a) * voxel_size, colour lerp rounded half away
// from zero.

struct MarchParams {
    voxel_size: f32,
    min_weight: f32,
    job_count: u32,
    // Triangles `tris` can hold.
    capacity: u32,
    // u32 words per case in `table`.
    case_stride: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

struct Job {
    // Block index (w unused).
    block: vec4<i32>,
    // slots[0] = the block's slot, slots[n] = upper neighbour n (offset (n & 1, n >> 1 & 1,
    // n >> 2 & 1)), -1 = missing.
    slots: array<i32, 8>,
}

struct Triangle {
    job: u32,
    // cell | triangle-in-case << 9 | edge0 << 12 | edge1 << 16 | edge2 << 20
    code: u32,
    // x, y, z of vertex 0, 1, 2.
    positions: array<f32, 9>,
    // r | g << 8 | b << 16 of vertex 0, 1, 2.
    colors: array<u32, 3>,
}

@group(0) @binding(0) var<uniform> params: MarchParams;
@group(0) @binding(1) var<storage, read> table: array<u32>;
@group(0) @binding(2) var<storage, read> jobs: array<Job>;
@group(0) @binding(3) var<storage, read> tsdf: array<f32>;
@group(0) @binding(4) var<storage, read> weight: array<f32>;
@group(0) @binding(5) var<storage, read> color: array<u32>;
@group(0) @binding(6) var<storage, read_write> counter: atomic<u32>;
@group(0) @binding(7) var<storage, read_write> tris: array<Triangle>;

fn corner_offset(c: u32) -> vec3<i32> {
    return vec3<i32>(i32(c & 1u), i32((c >> 1u) & 1u), i32((c >> 2u) & 1u));
}

fn unpack_rgb(c: u32) -> vec3<f32> {
    return vec3<f32>(f32(c & 255u), f32((c >> 8u) & 255u), f32((c >> 16u) & 255u));
}

// Rust's f32::round (half away from zero) for x >= -0.5; WGSL's round() breaks ties to even.
fn round_half_up(x: vec3<f32>) -> vec3<f32> {
    return select(round(x), ceil(x), fract(x) == vec3<f32>(0.5));
}

// Dispatch: (8, rows, layers) workgroups of 64; workgroup (gx, gy, gz) handles cells
// 64 gx .. 64 gx + 63 of job gy + gz * rows.
@compute @workgroup_size(64, 1, 1)
fn main(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
) {
    let j = group.y + group.z * groups.y;
    if (j >= params.job_count) {
        return;
    }
    let cell = group.x * 64u + lane;
    let c = vec3<i32>(i32(cell & 7u), i32((cell >> 3u) & 7u), i32(cell >> 6u));

    var t: array<f32, 8>;
    var rgb: array<u32, 8>;
    var case_index = 0u;
    for (var i = 0u; i < 8u; i += 1u) {
        let q = c + corner_offset(i);
        let n = u32(q.x >> 3u) | (u32(q.y >> 3u) << 1u) | (u32(q.z >> 3u) << 2u);
        let slot = jobs[j].slots[n];
        if (slot < 0) {
            return;
        }
        let idx = u32(slot) * 512u + u32(q.x & 7) + 8u * u32(q.y & 7) + 64u * u32(q.z & 7);
        // Written so that a NaN weight counts as unobserved (like the CPU).
        if (!(weight[idx] > params.min_weight)) {
            return;
        }
        t[i] = tsdf[idx];
        rgb[i] = color[idx];
        if (t[i] < 0.0) {
            case_index |= 1u << i;
        }
    }

    let row = case_index * params.case_stride;
    let count = table[row];
    if (count == 0u) {
        return;
    }
    let first = atomicAdd(&counter, count);
    let cell_voxel = jobs[j].block.xyz * 8 + c;
    for (var k = 0u; k < count; k += 1u) {
        let out = first + k;
        if (out >= params.capacity) {
            // Counted but not written: the runner re-runs with the counter's total.
            return;
        }
        var tri: Triangle;
        tri.job = j;
        var code = cell | (k << 9u);
        for (var v = 0u; v < 3u; v += 1u) {
            let e = table[row + 1u + 3u * k + v];
            code |= e << (12u + 4u * v);
            let axis = e / 4u;
            let below = (1u << axis) - 1u;
            let lo = ((e % 4u) & below) | (((e % 4u) & ~below) << 1u);
            let hi = lo | (1u << axis);
            let ta = t[lo];
            let tb = t[hi];
            let s = ta / (ta - tb);
            let va = cell_voxel + corner_offset(lo);
            let vb = cell_voxel + corner_offset(hi);
            let pa = vec3<f32>(va) * params.voxel_size;
            let pb = vec3<f32>(vb) * params.voxel_size;
            let p = pa + s * (pb - pa);
            tri.positions[3u * v] = p.x;
            tri.positions[3u * v + 1u] = p.y;
            tri.positions[3u * v + 2u] = p.z;
            let ca = unpack_rgb(rgb[lo]);
            let cb = unpack_rgb(rgb[hi]);
            let col = vec3<u32>(clamp(round_half_up(ca + s * (cb - ca)), vec3<f32>(0.0), vec3<f32>(255.0)));
            tri.colors[v] = col.x | (col.y << 8u) | (col.z << 16u);
        }
        tri.code = code;
        tris[out] = tri;
    }
}
