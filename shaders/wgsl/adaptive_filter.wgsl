// Semi-dense structure adaptive filter of DeepRelativeFusion (Loo et al., IROS 2021, §III-C,
// eqs. 4–8): one invocation per valid keyframe pixel x, a (2r+1)² window N around it.
//
//   w(x, n)  = w_s · w_d · w_c · w_u                                  (eqs. 4–6)
//            = exp(−[ (I(x)−I(n))²/(2σs²) + ‖x−n‖²/(2σd²)
//                     + (D(x)/D(n) − P(x)/P(n))²/(2σc²) + σu·V(n)/D(n)⁴ ])
//   W'(x)    = Σ_n w(x, n)                                            (eq. 8, right)
//   D'(x)    = Σ_n w(x, n) · D(n) / W'(x)                             (eq. 7)
//   V'(x)    = (|N| / n_valid) · Σ_n w_v(x, n) · (D'(x) − D(n))² / Σ_n w_v(x, n)   (eq. 8)
//
// with w_v = w_s · w_d · w_u (w without w_c), or w_v = w when `consistency_in_variance` is set
// (the literal reading). Without w_c in w_v a gross outlier, whose ratio every neighbour's
// disagrees with, cannot hide behind its own weight; see `relfusion_slam::dense::filter`.
//
// The four factors are multiplied as one exp of the summed exponents: the same value, one exp
// instead of four (plus one for w_v), and no factor underflows on its own before the product
// would.
// The w_c term is 0 (w_c = 1) without a prior or where P(x) or P(n) is not > 0.
//
// Inputs are sanitised on the host (`relfusion_slam::dense::filter`): an invalid pixel has
// D = V = 0 and a valid one D > 0 and V > 0, so "valid" here is D > 0 (WGSL may assume floats
// are finite, so the finiteness tests stay on the CPU), and P ≤ 0 means "no prior there".
//
// Output (0 elsewhere: the host clears both outputs): the centre must be valid (w_c needs D(x)),
// the window must hold at least two valid pixels (an isolated pixel has no local variance: it
// is the spurious kind the filter removes), and W' ≥ 1e-30. Neighbours outside the image are
// skipped; |N| stays (2r+1)².
//
// V' is accumulated in a second pass over the window's valid pixels once D'(x) is known, from
// their variance weights and depths kept in private arrays (1.5× faster on lavapipe than
// recomputing them), not as Σ w·D² − W'·D'², which cancels catastrophically for small
// variances, nor with a one-pass (West) update, whose error grows like ε·|D|·|D' − D(n)| where
// the weights span orders of magnitude: in the two-pass sum an error in D' enters only
// quadratically when w_v = w (Σ w·(D' − D(n)) = 0).
//
// One invocation per valid pixel (`pixels`, listed on the host): a semi-dense map covers a
// fraction of the image, and an invocation on an invalid pixel would hold its SIMD lanes for
// the whole window loop anyway (on lavapipe this halved the time).
//
// The CPU twin `relfusion_slam::dense::filter::adaptive_filter_cpu` performs the same f32
// operations in the same order. Rust mirror of the uniform:
// `relfusion_slam::dense::gpu_filter::AdaptiveFilterParams` (48 bytes); keep in sync.

struct AdaptiveFilterParams {
    width: u32,
    height: u32,
    radius: u32,
    // 1 when `prior` holds P (width × height floats), 0 when it is a 1-float placeholder.
    has_prior: u32,
    sigma_s: f32,
    sigma_d: f32,
    sigma_c: f32,
    sigma_u: f32,
    // 1: the variance weights include w_c (w_v = w); 0: w_v = w_s · w_d · w_u.
    consistency_in_variance: u32,
    // Number of entries of `pixels`.
    count: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: AdaptiveFilterParams;
@group(0) @binding(1) var<storage, read> intensity: array<f32>;
@group(0) @binding(2) var<storage, read> idepth: array<f32>;
@group(0) @binding(3) var<storage, read> variance: array<f32>;
@group(0) @binding(4) var<storage, read> prior: array<f32>;
@group(0) @binding(5) var<storage, read_write> out_idepth: array<f32>;
@group(0) @binding(6) var<storage, read_write> out_variance: array<f32>;
// The valid pixels (row-major indices), one invocation each.
@group(0) @binding(7) var<storage, read> pixels: array<u32>;

// Below this weight sum D' is not trusted (the centre's own w_u has underflowed).
const MIN_WEIGHT_SUM: f32 = 1e-30;

// Largest window, (2·7 + 1)²: the host bounds the radius by 7 (`filter::MAX_RADIUS`).
const MAX_WINDOW: u32 = 225u;

// Exponent coefficients 1/(2σ²), computed as on the CPU.
struct Coefficients {
    ks: f32,
    kd: f32,
    kc: f32,
}

// −ln w_s − ln w_d − ln w_u (x) and −ln w_c (y) for a valid neighbour n at offset (dx, dy).
fn exponents(k: Coefficients, ic: f32, dc: f32, pc: f32, n: u32, dx: i32, dy: i32) -> vec2<f32> {
    let di = ic - intensity[n];
    let r2 = f32(dx * dx + dy * dy);
    let dn = idepth[n];
    var c = 0.0;
    if (params.has_prior != 0u) {
        let pn = prior[n];
        if (pc > 0.0 && pn > 0.0) {
            c = dc / dn - pc / pn;
        }
    }
    let dn2 = dn * dn;
    let e_v = k.ks * di * di + k.kd * r2 + params.sigma_u * variance[n] / (dn2 * dn2);
    return vec2<f32>(e_v, k.kc * c * c);
}

@compute @workgroup_size(64, 1, 1)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    if (id.x >= params.count) {
        return;
    }
    let w = params.width;
    let h = params.height;
    let i = pixels[id.x];
    let dc = idepth[i];
    let k = Coefficients(
        1.0 / (2.0 * params.sigma_s * params.sigma_s),
        1.0 / (2.0 * params.sigma_d * params.sigma_d),
        1.0 / (2.0 * params.sigma_c * params.sigma_c),
    );
    let ic = intensity[i];
    var pc = 0.0;
    if (params.has_prior != 0u) {
        pc = prior[i];
    }
    let r = i32(params.radius);
    let cx = i32(i % w);
    let cy = i32(i / w);
    let wi = i32(w);
    let hi = i32(h);

    // The window clipped to the image (neighbours outside are skipped).
    let x0 = max(cx - r, 0);
    let x1 = min(cx + r, wi - 1);
    let y0 = max(cy - r, 0);
    let y1 = min(cy + r, hi - 1);

    // Pass 1: W', Σ w·D (eq. 7), the number of valid pixels in the window, and the variance
    // weight and depth of each of them for pass 2.
    var cache_w: array<f32, MAX_WINDOW>;
    var cache_d: array<f32, MAX_WINDOW>;
    let literal = params.consistency_in_variance != 0u;
    var wsum = 0.0;
    var wdsum = 0.0;
    var n_valid = 0u;
    for (var y = y0; y <= y1; y++) {
        for (var x = x0; x <= x1; x++) {
            let n = u32(y * wi + x);
            let dn = idepth[n];
            if (dn > 0.0) {
                let e = exponents(k, ic, dc, pc, n, x - cx, y - cy);
                let wn = exp(-(e.x + e.y));
                wsum += wn;
                wdsum += wn * dn;
                // w_v = w in the literal reading (and e_v + 0 = e_v exactly otherwise).
                cache_w[n_valid] = exp(-(e.x + select(0.0, e.y, literal)));
                cache_d[n_valid] = dn;
                n_valid += 1u;
            }
        }
    }
    if (n_valid < 2u || !(wsum >= MIN_WEIGHT_SUM)) {
        // The outputs were cleared to 0 on the host.
        return;
    }
    let d_filtered = wdsum / wsum;

    // Pass 2: the w_v-weighted squared deviations from D'(x) (eq. 8); W_v ≥ W' (w_c ≤ 1).
    var acc = 0.0;
    var wvsum = 0.0;
    for (var j = 0u; j < n_valid; j++) {
        let dev = d_filtered - cache_d[j];
        acc += cache_w[j] * dev * dev;
        wvsum += cache_w[j];
    }
    let side = f32(2 * r + 1);
    let scale = side * side / f32(n_valid);
    out_idepth[i] = d_filtered;
    out_variance[i] = scale * (acc / wvsum);
}
