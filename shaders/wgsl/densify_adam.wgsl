// One Adam iteration of the DeepRelativeFusion densification (Loo et al. 2021, eqs. 10–13).
//
// For each pixel n = (x, y): the analytic gradient dE/dD(n) of
//   E = grad_scale · Σ [wx·ex² + wy·ey²]                      (eq. 11, forward differences of
//     + semi_scale · Σ_{semi>0} ρ((D − semi)² / semi_var)       L = ln D minus the targets)
//     + grad_scale · Σ cnn_weight · (D − cnn)²                 (eq. 13; term 3)
// at the previous iterate (its own pixel and the 4-neighbourhood), then PyTorch's Adam step on
// its own moments, writing the next iterate. The host ping-pongs `iter_in` / `iter_out`
// between dispatches (one dispatch per iteration, all in one compute pass), so every pixel's
// gradient sees the same previous iterate, as autograd does.
//
// Layout: pixels are grouped in quads, 4 horizontally adjacent pixels held as vec4 lanes, and
// one invocation updates a block of 2 × 2 quads (8 × 2 pixels). Rows are padded to
// `row_quads` quads (even); every per-pixel map is a plane of `n_quads = row_quads · height`
// vec4s, and a buffer holds several planes back to back (plane k of buffer b starts at
// b[k · n_quads]). Padding pixels carry zero weights, no semi-dense depth and D = 1, so their
// gradient is 0 and Adam leaves them alone; the host also zeroes wx at the last column and wy
// at the last row (the energy has no difference there), so no real pixel sees a padding one.
// Why blocks of quads: lavapipe (the CPU Vulkan driver of machines without a GPU) executes each
// storage load or store instruction lane by lane, with a bounds check per lane, so its cost
// follows the number of such instructions, whatever their width: one invocation per pixel
// needed 12 per pixel, this layout 4.25 (vec4 accesses; the block's quads and rows are each
// other's neighbours). On a real GPU they are coalesced 16-byte accesses.
//
// Iterates are stored as planes (D, ln D): each pixel takes one `log` per iteration instead of
// five. CPU twin and exact definitions: relfusion_slam::dense::densify (same order of
// operations per pixel).

struct Params {
    width: u32,
    height: u32,
    // Quads per (padded) row, and row_quads · height.
    row_quads: u32,
    n_quads: u32,
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
    // Bit 0: ρ(u) = (u² + ε²)^α (generalised Charbonnier), else ρ(u) = u.
    // Bit 1: some cnn_weight is non-zero (term 3 present; its maps are read only then).
    flags: u32,
    _pad0: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
// Previous iterate: planes D, ln D.
@group(0) @binding(1) var<storage, read> iter_in: array<vec4<f32>>;
// Next iterate: planes D, ln D.
@group(0) @binding(2) var<storage, read_write> iter_out: array<vec4<f32>>;
// Adam moments: planes m, v.
@group(0) @binding(3) var<storage, read_write> moments: array<vec4<f32>>;
// Gradient term: planes wx, wy, tx, ty (weights and target log-gradients).
@group(0) @binding(4) var<storage, read> grad_terms: array<vec4<f32>>;
// Data terms: planes semi (0 = none), semi_var, cnn, cnn_weight.
@group(0) @binding(5) var<storage, read> data_terms: array<vec4<f32>>;

const CHARBONNIER: u32 = 1u;
const CNN_DEPTH: u32 = 2u;

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

// The data terms, Adam and the stores of quad q given its gradient-term part dl.
fn finish(q: u32, d: vec4<f32>, l: vec4<f32>, dl: vec4<f32>) {
    let nq = params.n_quads;
    // dL/dD = 1/D.
    var g = 2.0 * params.grad_scale * dl / d;
    let semi = data_terms[q];
    let has_semi = (semi > vec4<f32>(0.0)) & vec4<bool>(params.semi_scale > 0.0);
    if (any(has_semi)) {
        // Lanes without semi-dense depth compute with variance 1 and are then discarded.
        let var_ = select(vec4<f32>(1.0), data_terms[nq + q], has_semi);
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
        let cnn = data_terms[2u * nq + q];
        let cnn_weight = data_terms[3u * nq + q];
        g = g + 2.0 * params.grad_scale * cnn_weight * (d - cnn);
    }
    // Adam in torch.optim.Adam's order (denom = sqrt(v) / sqrt(1 − β2^t) + ε,
    // D −= step_size · m / denom), then the projection onto D ≥ min_idepth.
    let m = params.beta1 * moments[q] + (1.0 - params.beta1) * g;
    let v = params.beta2 * moments[nq + q] + (1.0 - params.beta2) * g * g;
    moments[q] = m;
    moments[nq + q] = v;
    let denom = sqrt(v) / params.bias2_sqrt + params.adam_epsilon;
    let d_next = max(d - params.step_size * (m / denom), vec4<f32>(params.min_idepth));
    iter_out[q] = d_next;
    // An unmoved pixel keeps its ln D bit for bit: the host's `ln` and the GPU's `log` may
    // differ in the last ulp, and such a difference would give a pixel whose gradient is
    // exactly zero (D = D'_CNN away from semi-dense pixels) a rounding-noise gradient, which
    // Adam's normalisation turns into a full-size step.
    iter_out[nq + q] = select(log(d_next), l, d_next == d);
}

// One invocation per block of 2 × 2 quads (8 × 2 pixels): quads a, b of rows y and y + 1.
@compute @workgroup_size(64, 1, 1)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let nq = params.n_quads;
    let rq = params.row_quads;
    let h = params.height;
    let bx_count = rq / 2u;
    if (id.x >= bx_count * ((h + 1u) / 2u)) {
        return;
    }
    let by = id.x / bx_count;
    let xq = 2u * (id.x - by * bx_count);
    let y = 2u * by;
    let qa = y * rq + xq;
    let qb = qa + 1u;
    let has_row1 = y + 1u < h;
    let has_left = xq > 0u;
    let has_right = xq + 2u < rq;

    // Row y.
    let l0a = iter_in[nq + qa];
    let l0b = iter_in[nq + qb];
    let wx0a = grad_terms[qa];
    let wx0b = grad_terms[qb];
    let wy0a = grad_terms[nq + qa];
    let wy0b = grad_terms[nq + qb];
    let tx0a = grad_terms[2u * nq + qa];
    let tx0b = grad_terms[2u * nq + qb];
    let ty0a = grad_terms[3u * nq + qa];
    let ty0b = grad_terms[3u * nq + qb];
    var lp0 = l0a.x;
    var wxp0 = 0.0;
    var txp0 = 0.0;
    var ln0 = l0b.w;
    if (has_left) {
        lp0 = iter_in[nq + qa - 1u].w;
        wxp0 = grad_terms[qa - 1u].w;
        txp0 = grad_terms[2u * nq + qa - 1u].w;
    }
    if (has_right) {
        ln0 = iter_in[nq + qb + 1u].x;
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
        lua = iter_in[nq + qa - rq];
        lub = iter_in[nq + qb - rq];
        wyua = grad_terms[nq + qa - rq];
        wyub = grad_terms[nq + qb - rq];
        tyua = grad_terms[3u * nq + qa - rq];
        tyub = grad_terms[3u * nq + qb - rq];
    }
    // Row y + 1 (when it exists: below row y, and its own quads).
    var l1a = vec4<f32>(0.0);
    var l1b = vec4<f32>(0.0);
    if (has_row1) {
        l1a = iter_in[nq + qa + rq];
        l1b = iter_in[nq + qb + rq];
    }

    let dl0a = grad_term(
        l0a, lp0, l0b.x, lua, l1a, wx0a, tx0a, wxp0, txp0, wy0a, ty0a, wyua, tyua, has_up, has_row1,
    );
    let dl0b = grad_term(
        l0b, l0a.w, ln0, lub, l1b, wx0b, tx0b, wx0a.w, tx0a.w, wy0b, ty0b, wyub, tyub, has_up,
        has_row1,
    );
    finish(qa, iter_in[qa], l0a, dl0a);
    finish(qb, iter_in[qb], l0b, dl0b);

    if (has_row1) {
        let ra = qa + rq;
        let rb = qb + rq;
        let wx1a = grad_terms[ra];
        let wx1b = grad_terms[rb];
        let wy1a = grad_terms[nq + ra];
        let wy1b = grad_terms[nq + rb];
        let tx1a = grad_terms[2u * nq + ra];
        let tx1b = grad_terms[2u * nq + rb];
        let ty1a = grad_terms[3u * nq + ra];
        let ty1b = grad_terms[3u * nq + rb];
        var lp1 = l1a.x;
        var wxp1 = 0.0;
        var txp1 = 0.0;
        var ln1 = l1b.w;
        if (has_left) {
            lp1 = iter_in[nq + ra - 1u].w;
            wxp1 = grad_terms[ra - 1u].w;
            txp1 = grad_terms[2u * nq + ra - 1u].w;
        }
        if (has_right) {
            ln1 = iter_in[nq + rb + 1u].x;
        }
        let has_down = y + 2u < h;
        var lda = vec4<f32>(0.0);
        var ldb = vec4<f32>(0.0);
        if (has_down) {
            lda = iter_in[nq + ra + rq];
            ldb = iter_in[nq + rb + rq];
        }
        let dl1a = grad_term(
            l1a, lp1, l1b.x, l0a, lda, wx1a, tx1a, wxp1, txp1, wy1a, ty1a, wy0a, ty0a, true,
            has_down,
        );
        let dl1b = grad_term(
            l1b, l1a.w, ln1, l0b, ldb, wx1b, tx1b, wx1a.w, tx1a.w, wy1b, ty1b, wy0b, ty0b, true,
            has_down,
        );
        finish(ra, iter_in[ra], l1a, dl1a);
        finish(rb, iter_in[rb], l1b, dl1b);
    }
}
