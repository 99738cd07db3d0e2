// Two-view forward warp of an inverse-depth map (DeepRelativeFusion, Loo et al. IROS 2021,
// §III-E eq. 14): every source pixel x with inverse depth d > 0 is back-projected,
// transformed by the Sim(3) dst_from_src and projected into the other view:
//
//     x̂ = K · S · (K⁻¹ ẋ / d),    D̂(round(x̂)) = 1 / [x̂]₃ .
//
// One invocation per SOURCE pixel (a scatter), so several source pixels may land on one target
// pixel; the nearest surface wins, i.e. the largest inverse depth. Positive IEEE floats order
// like their bit patterns read as unsigned integers, so `atomicMax` on `bitcast<u32>(d̂)` is an
// order-independent z-test, and the result buffer, cleared to 0u, reads back directly as f32
// (0u is 0.0 = "nothing landed").
//
// Division-light arithmetic: with ñ = (xn, yn, 1) = K⁻¹ẋ the transformed point is
// S·(ñ/d) = (sR·ñ + t·d)/d =: q/d, so z' = q.z/d, the pixel is (fx·q.x/q.z + cx, fy·q.y/q.z + cy)
// and d̂ = d/q.z: one reciprocal per pixel. The CPU twin
// (`relfusion_slam::dense::two_view::warp_inverse_depth_cpu`) performs the same f32 operations
// in the same order; keep the two in sync.
//
// Rust mirror: `relfusion_slam::dense::gpu_warp::WarpParams` (96 bytes, size-asserted there).

struct WarpParams {
    // Rows of the 3×4 matrix [sR | t] of dst_from_src.
    row0: vec4<f32>,
    row1: vec4<f32>,
    row2: vec4<f32>,
    // fx, fy, cx, cy of the (shared) pinhole camera.
    intrinsics: vec4<f32>,
    // 1/fx, 1/fy, min_depth (a warped point must have z' > min_depth), unused.
    inverse: vec4<f32>,
    width: u32,
    height: u32,
    // 1: skip source pixels where exclude > 0.
    has_exclude: u32,
    _pad: u32,
}

@group(0) @binding(0) var<uniform> params: WarpParams;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read> exclude: array<f32>;
@group(0) @binding(3) var<storage, read_write> dst: array<atomic<u32>>;

// Largest finite f32: infinities (and NaN, which fails every comparison) are skipped.
const MAX_F32: f32 = 3.40282347e38;

@compute @workgroup_size(16, 16, 1)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    if (id.x >= params.width || id.y >= params.height) {
        return;
    }
    let i = id.y * params.width + id.x;
    let d = src[i];
    if (!(d > 0.0 && d <= MAX_F32)) {
        return;
    }
    if (params.has_exclude != 0u && exclude[i] > 0.0) {
        return;
    }
    let xn = (f32(id.x) - params.intrinsics.z) * params.inverse.x;
    let yn = (f32(id.y) - params.intrinsics.w) * params.inverse.y;
    let qx = ((params.row0.x * xn + params.row0.y * yn) + params.row0.z) + params.row0.w * d;
    let qy = ((params.row1.x * xn + params.row1.y * yn) + params.row1.z) + params.row1.w * d;
    let qz = ((params.row2.x * xn + params.row2.y * yn) + params.row2.z) + params.row2.w * d;
    // z' = qz / d > min_depth, without dividing (d > 0); also rejects points behind the camera.
    if (!(qz > params.inverse.z * d)) {
        return;
    }
    let inv = 1.0 / qz;
    let u = params.intrinsics.x * (qx * inv) + params.intrinsics.z;
    let v = params.intrinsics.y * (qy * inv) + params.intrinsics.w;
    // Nearest pixel, halves rounded up (WGSL's round() would round them to even).
    let ur = floor(u + 0.5);
    let vr = floor(v + 0.5);
    if (!(ur >= 0.0 && vr >= 0.0 && ur <= f32(params.width - 1u) && vr <= f32(params.height - 1u))) {
        return;
    }
    let warped = d * inv;
    if (!(warped > 0.0 && warped <= MAX_F32)) {
        return;
    }
    let j = u32(vr) * params.width + u32(ur);
    atomicMax(&dst[j], bitcast<u32>(warped));
}
