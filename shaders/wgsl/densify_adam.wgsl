// One Adam iteration of the DeepRelativeFusion densification (Loo et al. 2021, eqs. 10–13).
//
// For each pixel n = (x, y): the analytic gradient dE/dD(n) of
//   E = grad_scale · Σ [wx·ex² + wy·ey²]                      (eq. 11, forward differences of
//     + semi_scale · Σ_{semi>0} ρ((D − semi)² / semi_var)       L = ln D minus the targets)
//     + grad_scale · Σ cnn_weight · (D − cnn)²                 (eq. 13; term 3)
// at the previous iterate (its own pixel and the 4-neighbourhood), then PyTorch's Adam step on
// its own moments, writing the next iterate. The host ping-pongs `state_in` / `state_out`
// between dispatches (one dispatch per iteration, all in one compute pass), so every pixel's
// gradient sees the same previous iterate, as autograd does.
//
// Layout: pixels are grouped in quads, 4 horizontally adjacent pixels held in the channels of
// one rgba32float texel, and one invocation updates a block of 2 × 2 quads (8 × 2 pixels).
// Every per-pixel map is one layer of a 2-D array texture of `row_quads × height` texels
// (`row_quads` even): texel (xq, y) holds pixels 4·xq .. 4·xq + 3 of row y. Padding pixels
// carry zero weights, no semi-dense depth and D = 1, so their gradient is 0 and Adam leaves
// them alone; the host also zeroes wx at the last column and wy at the last row (the energy
// has no difference there), so no real pixel sees a padding one.
// Why storage textures and blocks of quads: lavapipe (the CPU Vulkan driver of machines
// without a GPU) executes storage-buffer accesses lane by lane with a bounds check, while
// storage-image loads are vector gathers; and a block's quads and rows are each other's
// neighbours, so a pixel touches 4.25 texels per iteration instead of 10. On a real GPU these
// are plain 16-byte image accesses with 2-D locality.
//
// The state keeps ln D beside D: each pixel takes one `log` per iteration instead of five.
// CPU twin and exact definitions: relfusion_slam::dense::densify (same order of operations per
// pixel).

requires readonly_and_readwrite_storage_textures;

struct Params {
    width: u32,
    height: u32,
    // Texels per row (quads per padded row, even).
    row_quads: u32,
    // Bit 0: ρ(u) = (u² + ε²)^α (generalised Charbonnier), else ρ(u) = u.
    // Bit 1: some cnn_weight is non-zero (term 3 present; its layers are read only then).
    flags: u32,
    // Adam's step of this iteration t (from 1): lr / (1 − β1^t) and sqrt(1 − β2^t), computed
    // on the host.
    step_size: f32,
    bias2_sqrt: f32,
    beta1: f32,
    beta2: f32,
    adam_epsilon: f32,
    // λ / |Ω_i| and 1 / |Ω|.
    semi_scale: f32,
    grad_scale: f32,
    alpha: f32,
    epsilon: f32,
    min_idepth: f32,
}

@group(0) @binding(0) var<uniform> params: Params;
// Previous iterate, layers D, ln D, m, v (Adam's moments).
@group(0) @binding(1) var state_in: texture_storage_2d_array<rgba32float, read>;
// Next iterate, same layers.
@group(0) @binding(2) var state_out: texture_storage_2d_array<rgba32float, write>;
// The problem, layers wx, wy, tx, ty (gradient term), semi (0 = none), semi_var, cnn,
// cnn_weight (data terms).
@group(0) @binding(3) var terms: texture_storage_2d_array<rgba32float, read>;

const CHARBONNIER: u32 = 1u;
const CNN_DEPTH: u32 = 2u;

const D: i32 = 0;
const LN_D: i32 = 1;
const M: i32 = 2;
const V: i32 = 3;
const WX: i32 = 0;
const WY: i32 = 1;
const TX: i32 = 2;
const TY: i32 = 3;
const SEMI: i32 = 4;
const SEMI_VAR: i32 = 5;
const CNN: i32 = 6;
const CNN_WEIGHT: i32 = 7;

fn state(p: vec2<i32>, layer: i32) -> vec4<f32> {
    return textureLoad(state_in, p, layer);
}

fn term(p: vec2<i32>, layer: i32) -> vec4<f32> {
    return textureLoad(terms, p, layer);
}

// dE/dL of one quad up to the factor 2·grad_scale, per lane: each forward difference touching
// the pixel. `l_prev` / `wx_prev` / `tx_prev`: the pixel left of the quad (weight 0 at a row's
// start); `l_next`: right of it (the last lane of a row has wx = 0, so any finite value works).
fn grad_term(
    l: vec4<f32>, l_prev: f32, l_next: f32, l_up: vec4<f32>, l_down: vec4<f32>,
    wx: vec4<f32>, tx: vec4<f32>, wx_prev: f32, tx_prev: f32,
    wy: vec4<f32>, ty: vec4<f32>, wy_up: vec4<f32>, ty_up: vec4<f32>,
    has_up: bool, has_down: bool,
) -> vec4<f32> {
    let l_right = vec4<f32>(l.y, l.z, l.w, l_next);
    var dl = vec4<f32>(0.0) - wx * (l_right - l - tx);
    let l_left = vec4<f32>(l_prev, l.x, l.y, l.z);
    let wx_left = vec4<f32>(wx_prev, wx.x, wx.y, wx.z);
    let tx_left = vec4<f32>(tx_prev, tx.x, tx.y, tx.z);
    dl = dl + wx_left * (l - l_left - tx_left);
    if (has_down) {
        dl = dl - wy * (l_down - l - ty);
    }
    if (has_up) {
        dl = dl + wy_up * (l - l_up - ty_up);
    }
    return dl;
}

// The data terms, Adam and the stores of the quad at texel p given its gradient-term part dl.
fn finish(p: vec2<i32>, d: vec4<f32>, l: vec4<f32>, dl: vec4<f32>) {
    // dL/dD = 1/D.
    var g = 2.0 * params.grad_scale * dl / d;
    let semi = term(p, SEMI);
    let has_semi = (semi > vec4<f32>(0.0)) & vec4<bool>(params.semi_scale > 0.0);
    if (any(has_semi)) {
        // Lanes without semi-dense depth compute with variance 1 and are then discarded.
        let var_ = select(vec4<f32>(1.0), term(p, SEMI_VAR), has_semi);
        let r = d - semi;
        let u = r * r / var_;
        var drho = vec4<f32>(1.0);
        if ((params.flags & CHARBONNIER) != 0u) {
            let e2 = params.epsilon * params.epsilon;
            drho = 2.0 * params.alpha * u * pow(u * u + e2, vec4<f32>(params.alpha - 1.0));
        }
        g = g + select(vec4<f32>(0.0), params.semi_scale * drho * (2.0 * r / var_), has_semi);
    }
    if ((params.flags & CNN_DEPTH) != 0u) {
        g = g + 2.0 * params.grad_scale * term(p, CNN_WEIGHT) * (d - term(p, CNN));
    }
    // Adam in torch.optim.Adam's order (denom = sqrt(v) / sqrt(1 − β2^t) + ε,
    // D −= step_size · m / denom), then the projection onto D ≥ min_idepth.
    let m = params.beta1 * state(p, M) + (1.0 - params.beta1) * g;
    let v = params.beta2 * state(p, V) + (1.0 - params.beta2) * g * g;
    let denom = sqrt(v) / params.bias2_sqrt + params.adam_epsilon;
    let d_next = max(d - params.step_size * (m / denom), vec4<f32>(params.min_idepth));
    textureStore(state_out, p, D, d_next);
    // An unmoved pixel keeps its ln D bit for bit: the host's `ln` and the GPU's `log` may
    // differ in the last ulp, and such a difference would give a pixel whose gradient is
    // exactly zero (D = D'_CNN away from semi-dense pixels) a rounding-noise gradient, which
    // Adam's normalisation turns into a full-size step.
    textureStore(state_out, p, LN_D, select(log(d_next), l, d_next == d));
    textureStore(state_out, p, M, m);
    textureStore(state_out, p, V, v);
}

// One invocation per block of 2 × 2 quads (8 × 2 pixels): quads a, b of rows y and y + 1.
@compute @workgroup_size(64, 1, 1)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let rq = params.row_quads;
    let h = params.height;
    let bx_count = rq / 2u;
    if (id.x >= bx_count * ((h + 1u) / 2u)) {
        return;
    }
    let by = id.x / bx_count;
    let xq = 2u * (id.x - by * bx_count);
    let y = 2u * by;
    let has_row1 = y + 1u < h;
    let has_left = xq > 0u;
    let has_right = xq + 2u < rq;
    let pa = vec2<i32>(i32(xq), i32(y));
    let pb = pa + vec2<i32>(1, 0);
    let left = vec2<i32>(-1, 0);
    let up = vec2<i32>(0, -1);
    let down = vec2<i32>(0, 1);

    // Row y.
    let l0a = state(pa, LN_D);
    let l0b = state(pb, LN_D);
    let wx0a = term(pa, WX);
    let wx0b = term(pb, WX);
    let wy0a = term(pa, WY);
    let wy0b = term(pb, WY);
    let tx0a = term(pa, TX);
    let tx0b = term(pb, TX);
    let ty0a = term(pa, TY);
    let ty0b = term(pb, TY);
    var lp0 = l0a.x;
    var wxp0 = 0.0;
    var txp0 = 0.0;
    var ln0 = l0b.w;
    if (has_left) {
        lp0 = state(pa + left, LN_D).w;
        wxp0 = term(pa + left, WX).w;
        txp0 = term(pa + left, TX).w;
    }
    if (has_right) {
        ln0 = state(pb - left, LN_D).x;
    }
    // Above row y.
    let has_up = y > 0u;
    var lua = vec4<f32>(0.0);
    var lub = vec4<f32>(0.0);
    var wyua = vec4<f32>(0.0);
    var wyub = vec4<f32>(0.0);
    var tyua = vec4<f32>(0.0);
    var tyub = vec4<f32>(0.0);
    if (has_up) {
        lua = state(pa + up, LN_D);
        lub = state(pb + up, LN_D);
        wyua = term(pa + up, WY);
        wyub = term(pb + up, WY);
        tyua = term(pa + up, TY);
        tyub = term(pb + up, TY);
    }
    // Row y + 1 (when it exists: below row y, and its own quads).
    var l1a = vec4<f32>(0.0);
    var l1b = vec4<f32>(0.0);
    if (has_row1) {
        l1a = state(pa + down, LN_D);
        l1b = state(pb + down, LN_D);
    }

    let dl0a = grad_term(
        l0a, lp0, l0b.x, lua, l1a, wx0a, tx0a, wxp0, txp0, wy0a, ty0a, wyua, tyua, has_up, has_row1,
    );
    let dl0b = grad_term(
        l0b, l0a.w, ln0, lub, l1b, wx0b, tx0b, wx0a.w, tx0a.w, wy0b, ty0b, wyub, tyub, has_up,
        has_row1,
    );
    finish(pa, state(pa, D), l0a, dl0a);
    finish(pb, state(pb, D), l0b, dl0b);

    if (has_row1) {
        let ra = pa + down;
        let rb = pb + down;
        let wx1a = term(ra, WX);
        let wx1b = term(rb, WX);
        let wy1a = term(ra, WY);
        let wy1b = term(rb, WY);
        let tx1a = term(ra, TX);
        let tx1b = term(rb, TX);
        let ty1a = term(ra, TY);
        let ty1b = term(rb, TY);
        var lp1 = l1a.x;
        var wxp1 = 0.0;
        var txp1 = 0.0;
        var ln1 = l1b.w;
        if (has_left) {
            lp1 = state(ra + left, LN_D).w;
            wxp1 = term(ra + left, WX).w;
            txp1 = term(ra + left, TX).w;
        }
        if (has_right) {
            ln1 = state(rb - left, LN_D).x;
        }
        let has_down = y + 2u < h;
        var lda = vec4<f32>(0.0);
        var ldb = vec4<f32>(0.0);
        if (has_down) {
            lda = state(ra + down, LN_D);
            ldb = state(rb + down, LN_D);
        }
        let dl1a = grad_term(
            l1a, lp1, l1b.x, l0a, lda, wx1a, tx1a, wxp1, txp1, wy1a, ty1a, wy0a, ty0a, true,
            has_down,
        );
        let dl1b = grad_term(
            l1b, l1a.w, ln1, l0b, ldb, wx1b, tx1b, wx1a.w, tx1a.w, wy1b, ty1b, wy0b, ty0b, true,
            has_down,
        );
        finish(ra, state(ra, D), l1a, dl1a);
        finish(rb, state(rb, D), l1b, dl1b);
    }
}
