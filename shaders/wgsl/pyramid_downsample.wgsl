// Image pyramid: one 2×2 box-filter downsampling step, level L -> level L+1.
//
// LSD-SLAM (Engel et al., ECCV 2014; `Frame::buildImage` in its source) aligns images
// coarse-to-fine on a pyramid where each level halves the previous one by averaging 2×2
// blocks. The destination size is floor(w/2) × floor(h/2): for odd sizes the last source
// column/row is dropped, exactly like the CPU twin `relfusion_slam::image::pyramid::downsample_cpu`.
//
// All levels of a pyramid live in ONE storage buffer (`levels`), each at its own offset, so a
// whole pyramid is built with one bind group layout and one submission.
//
// Rust mirror: `relfusion_slam::gpu::pyramid::DownsampleParams` (32 bytes, checked by a size
// assert there); keep the two in sync.

struct DownsampleParams {
    src_offset: u32,
    src_width: u32,
    src_height: u32,
    dst_offset: u32,
    dst_width: u32,
    dst_height: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> params: DownsampleParams;
@group(0) @binding(1) var<storage, read_write> levels: array<f32>;

@compute @workgroup_size(16, 16, 1)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    if (id.x >= params.dst_width || id.y >= params.dst_height) {
        return;
    }
    let s = params.src_offset + 2u * id.y * params.src_width + 2u * id.x;
    // Same summation order as the CPU twin: (a + b) + (c + d), then × 0.25.
    let top = levels[s] + levels[s + 1u];
    let bottom = levels[s + params.src_width] + levels[s + params.src_width + 1u];
    levels[params.dst_offset + id.y * params.dst_width + id.x] = 0.25 * (top + bottom);
}
