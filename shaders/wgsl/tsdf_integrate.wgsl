// TSDF integration / de-integration of one depth map into the voxel pool (paper §III-F; the
// weighted running average of Curless & Levoy, projective signed distance).
//
// One invocation per voxel of the listed blocks: block k of the list is (x, y, z, slot) and
// its voxel i (x + 8y + 64z inside the block) is invocation 512·k + i, so each invocation owns
// one pool entry (listed slots are distinct) and no atomics are needed. The dispatch is 2-D
// when the list needs more than the per-dimension workgroup limit: the flat workgroup index is
// workgroup_id.y · num_workgroups.x + workgroup_id.x, and invocations past the list return.
//
// The CPU twin (`relfusion_slam::fusion::integrate::integrate_cpu`) performs the same f32
// operations in the same order; keep the two in sync.
//
// Rust mirror: `relfusion_slam::fusion::gpu_volume::IntegrateUniform` (96 bytes, size-asserted).

struct IntegrateParams {
    // Rows of the 3×4 camera_from_world matrix (Sim(3) scale included).
    row0: vec4<f32>,
    row1: vec4<f32>,
    row2: vec4<f32>,
    // fx, fy, cx, cy of the depth map.
    intrinsics: vec4<f32>,
    width: u32,
    height: u32,
    block_count: u32,
    // World units per camera unit (the keyframe's Sim(3) scale).
    scale: f32,
    voxel_size: f32,
    truncation: f32,
    max_weight: f32,
    // > 0: integrate; otherwise de-integrate.
    sign: f32,
}

@group(0) @binding(0) var<uniform> params: IntegrateParams;
@group(0) @binding(1) var<storage, read> blocks: array<vec4<i32>>;
@group(0) @binding(2) var<storage, read> depth: array<f32>;
@group(0) @binding(3) var<storage, read> pixel_weight: array<f32>;
@group(0) @binding(4) var<storage, read> pixel_color: array<u32>;
@group(0) @binding(5) var<storage, read_write> tsdf: array<f32>;
@group(0) @binding(6) var<storage, read_write> weight: array<f32>;
@group(0) @binding(7) var<storage, read_write> color: array<u32>;

fn unpack(c: u32) -> vec3<f32> {
    return vec3<f32>(f32(c & 255u), f32((c >> 8u) & 255u), f32((c >> 16u) & 255u));
}

// Clamped to 0..255 and rounded half up (WGSL's round() would round halves to even).
fn pack(c: vec3<f32>) -> u32 {
    let r = vec3<u32>(floor(clamp(c, vec3<f32>(0.0), vec3<f32>(255.0)) + 0.5));
    return r.x | (r.y << 8u) | (r.z << 16u);
}

@compute @workgroup_size(64, 1, 1)
fn main(
    @builtin(workgroup_id) group: vec3<u32>,
    @builtin(num_workgroups) groups: vec3<u32>,
    @builtin(local_invocation_index) local: u32,
) {
    let flat = (group.y * groups.x + group.x) * 64u + local;
    let k = flat / 512u;
    if (k >= params.block_count) {
        return;
    }
    let i = flat % 512u;
    let block = blocks[k];
    let v = vec3<i32>(
        block.x * 8 + i32(i & 7u),
        block.y * 8 + i32((i >> 3u) & 7u),
        block.z * 8 + i32(i >> 6u),
    );
    let p = vec3<f32>(v) * params.voxel_size;
    let x = ((params.row0.x * p.x + params.row0.y * p.y) + params.row0.z * p.z) + params.row0.w;
    let y = ((params.row1.x * p.x + params.row1.y * p.y) + params.row1.z * p.z) + params.row1.w;
    let z = ((params.row2.x * p.x + params.row2.y * p.y) + params.row2.z * p.z) + params.row2.w;
    if (!(z > 0.0)) {
        return;
    }
    let u = params.intrinsics.x * (x / z) + params.intrinsics.z;
    let vv = params.intrinsics.y * (y / z) + params.intrinsics.w;
    // Nearest pixel, halves rounded up; NaN fails the test.
    let ur = floor(u + 0.5);
    let vr = floor(vv + 0.5);
    if (!(ur >= 0.0 && vr >= 0.0 && ur <= f32(params.width - 1u) && vr <= f32(params.height - 1u))) {
        return;
    }
    let pix = u32(vr) * params.width + u32(ur);
    let d = depth[pix];
    let w = pixel_weight[pix];
    if (!(d > 0.0 && w > 0.0)) {
        return;
    }
    let sdf = (d - z) * params.scale;
    if (sdf < -params.truncation) {
        return;
    }
    let t = min(1.0, sdf / params.truncation);

    let j = u32(block.w) * 512u + i;
    let w0 = weight[j];
    let t0 = tsdf[j];
    let c0 = unpack(color[j]);
    let c = unpack(pixel_color[pix]);
    if (params.sign > 0.0) {
        let w1 = w0 + w;
        tsdf[j] = (t0 * w0 + t * w) / w1;
        color[j] = pack((c0 * w0 + c * w) / w1);
        weight[j] = min(w1, params.max_weight);
    } else {
        let w1 = w0 - w;
        // EMPTY_WEIGHT of fusion/integrate.rs: rounding residues of a fully removed voxel.
        if (w1 <= 1e-3) {
            tsdf[j] = 0.0;
            weight[j] = 0.0;
            color[j] = 0u;
            return;
        }
        tsdf[j] = (t0 * w0 - t * w) / w1;
        color[j] = pack((c0 * w0 - c * w) / w1);
        weight[j] = w1;
    }
}
