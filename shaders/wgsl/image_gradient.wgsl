// Image gradients of one pyramid level: central differences and their magnitude.
//
// LSD-SLAM's direct image alignment (Engel et al., ECCV 2014; `Frame::buildGradients` in its
// source) needs ∂I/∂x and ∂I/∂y at every pixel of every level for the Jacobian of the
// photometric residual, and |∇I| to select the semi-dense pixels with enough texture.
//
//   gx(x, y) = 0.5 · (I(x+1, y) − I(x−1, y))
//   gy(x, y) = 0.5 · (I(x, y+1) − I(x, y−1))
//   grad_mag = sqrt(gx² + gy²)
//
// Border rule: neighbour coordinates are clamped to the image (clamp-to-edge), so on the first
// and last column gx = 0.5 · one-sided difference (and likewise for rows); a 1-pixel-wide image
// has gx = 0. The CPU twin `relfusion_slam::image::pyramid::gradients_cpu` uses the same rule.
//
// `levels`, `gx`, `gy` and `grad_mag` share the per-level offsets: pixel (x, y) of a level is at
// `offset + y · width + x` in all four buffers.
//
// Rust mirror: `relfusion_slam::gpu::pyramid::GradientParams` (16 bytes); keep in sync.

struct GradientParams {
    offset: u32,
    width: u32,
    height: u32,
    _pad0: u32,
}

@group(0) @binding(0) var<uniform> params: GradientParams;
@group(0) @binding(1) var<storage, read> levels: array<f32>;
@group(0) @binding(2) var<storage, read_write> gx: array<f32>;
@group(0) @binding(3) var<storage, read_write> gy: array<f32>;
@group(0) @binding(4) var<storage, read_write> grad_mag: array<f32>;

@compute @workgroup_size(16, 16, 1)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let w = params.width;
    let h = params.height;
    if (id.x >= w || id.y >= h) {
        return;
    }
    let x = id.x;
    let y = id.y;
    // Clamp-to-edge neighbours (max(x, 1) − 1 avoids the u32 underflow of x − 1 at x = 0).
    let xl = max(x, 1u) - 1u;
    let xr = min(x + 1u, w - 1u);
    let yu = max(y, 1u) - 1u;
    let yd = min(y + 1u, h - 1u);
    let base = params.offset;
    let dx = 0.5 * (levels[base + y * w + xr] - levels[base + y * w + xl]);
    let dy = 0.5 * (levels[base + yd * w + x] - levels[base + yu * w + x]);
    let i = base + y * w + x;
    gx[i] = dx;
    gy[i] = dy;
    grad_mag[i] = sqrt(dx * dx + dy * dy);
}
