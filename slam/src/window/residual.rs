//! Photometric residuals of the window and their Jacobians (DSO, TPAMI 2018, eqs. 4-5 with a
//! 5-pixel pattern).
//!
//! A point is hosted in keyframe `h` at pixel `u` of the window's pyramid level, with inverse
//! depth `ρ` in world units. In target `t`, pattern pixel `u + o` is predicted at
//! `π(T_tw·T_wh·(K⁻¹(u + o)/ρ))` (the pattern shares the centre's depth, DSO's fronto-parallel
//! assumption) and its residual is
//! `r = I_t(u') − e^{a_t − a_h}(I_h(u + o) − b_h) − b_t`
//! with each keyframe's affine brightness `(a, b)`. Poses are perturbed on the right,
//! `T ← T·exp(δ)`, tangent order (v, ω), as everywhere in the crate; a keyframe's eight
//! parameters are `(v, ω, a, b)`.

use nalgebra::{Matrix2x3, SMatrix, Vector2, Vector3};

use crate::geometry::{PinholeCamera, SE3, SO3};
use crate::image::pyramid::PyramidLevel;
use crate::mapping::DepthMap;

/// Parameters per keyframe: pose (6) and affine brightness (2).
pub const KF_PARAMS: usize = 8;
/// A keyframe's parameter vector.
pub type Vector8 = SMatrix<f64, KF_PARAMS, 1>;

/// DSO's pattern reduced to five pixels (centre and the four diagonals two pixels out): the
/// residual of a point is less ambiguous than one pixel's, at a fifth of DSO's eight.
pub const PATTERN: [(f64, f64); 5] = [
    (0.0, 0.0),
    (-2.0, -2.0),
    (2.0, -2.0),
    (-2.0, 2.0),
    (2.0, 2.0),
];

/// One keyframe of the window as the residuals see it.
#[derive(Clone, Copy, Debug)]
pub struct View<'a> {
    pub level: &'a PyramidLevel,
    /// The camera of that pyramid level.
    pub camera: PinholeCamera,
    pub world_from_camera: SE3,
    /// Affine brightness `(a, b)`.
    pub affine: (f64, f64),
}

/// A point of the window.
#[derive(Clone, Debug, PartialEq)]
pub struct Point {
    /// Index of the host keyframe in the window.
    pub host: usize,
    /// Pixel at the window's level.
    pub uv: Vector2<f64>,
    /// Inverse depth in world units (`idepth_keyframe / scale_keyframe`).
    pub idepth: f64,
    /// The host's inverse depth in its own keyframe units (to recover its scale).
    pub idepth_keyframe: f64,
    /// Host intensities at the pattern pixels.
    pub intensity: [f64; PATTERN.len()],
}

/// The linearisation of one pattern pixel of a point in one target.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Linearised {
    pub residual: f64,
    /// Squared gradient of the target image at the prediction (for the residual's weight).
    pub grad2: f64,
    pub d_host: Vector8,
    pub d_target: Vector8,
    pub d_idepth: f64,
}

fn skew(v: &Vector3<f64>) -> nalgebra::Matrix3<f64> {
    SO3::hat(v)
}

/// Selects up to `count` points of `depth` (a full-resolution semi-dense map in keyframe
/// units) for `host`: the image is cut into square cells, and each cell gives its pixel of
/// strongest gradient that has an estimate (well spread, as DSO's point selection).
/// `scale` is the host's Sim(3) scale (keyframe units → world units).
pub fn select_points(
    host: usize,
    view: &View<'_>,
    depth: &DepthMap,
    level: usize,
    scale: f64,
    count: usize,
) -> Vec<Point> {
    let (w, h) = (view.level.width(), view.level.height());
    let factor = 1usize << level;
    let cell = (((w * h) as f64 / count.max(1) as f64).sqrt().floor() as usize).max(3);
    let margin = 4usize;
    let mut points = Vec::new();
    let mut cy = margin;
    while cy + margin < h {
        let mut cx = margin;
        while cx + margin < w {
            let mut best: Option<(f32, usize, usize, f64)> = None;
            for y in cy..(cy + cell).min(h - margin) {
                for x in cx..(cx + cell).min(w - margin) {
                    let g = view.level.grad_mag.at(x, y);
                    if best.is_some_and(|b| b.0 >= g) {
                        continue;
                    }
                    // The level pixel covers `factor²` full-resolution pixels: take an estimate
                    // from its top-left one (the pyramid's box filter centre is between them).
                    let (x0, y0) = (x * factor, y * factor);
                    if x0 >= depth.width || y0 >= depth.height {
                        continue;
                    }
                    if let Some((d, _)) = depth.at(x0, y0).estimate()
                        && d > 0.0
                        && d.is_finite()
                    {
                        best = Some((g, x, y, f64::from(d)));
                    }
                }
            }
            if let Some((_, x, y, d)) = best {
                let uv = Vector2::new(x as f64, y as f64);
                let mut intensity = [0.0; PATTERN.len()];
                for (k, (ox, oy)) in PATTERN.iter().enumerate() {
                    let (px, py) = (x as f64 + ox, y as f64 + oy);
                    intensity[k] = f64::from(view.level.image.at(px as usize, py as usize));
                }
                points.push(Point {
                    host,
                    uv,
                    idepth: d / scale,
                    idepth_keyframe: d,
                    intensity,
                });
            }
            cx += cell;
        }
        cy += cell;
    }
    points
}

/// The residual of pattern pixel `k` of `point` in `target` and its derivatives with respect
/// to the host's and the target's parameters and the inverse depth; `None` when the point falls
/// behind the target camera or outside its image.
pub fn linearise(
    point: &Point,
    k: usize,
    host: &View<'_>,
    target: &View<'_>,
) -> Option<Linearised> {
    let (ox, oy) = PATTERN[k];
    let cam_h = &host.camera;
    let ray = Vector3::new(
        (point.uv.x + ox - cam_h.cx) / cam_h.fx,
        (point.uv.y + oy - cam_h.cy) / cam_h.fy,
        1.0,
    );
    let rho = point.idepth;
    // Also refuses NaN.
    if rho.is_nan() || rho <= 0.0 {
        return None;
    }
    let x_h = ray / rho;
    let target_from_host = target.world_from_camera.inverse() * host.world_from_camera;
    let r_th = target_from_host.rotation.matrix();
    let x_t = target_from_host.act(&x_h);
    if x_t.z < 1e-3 {
        return None;
    }
    let cam = &target.camera;
    let u = cam.fx * x_t.x / x_t.z + cam.cx;
    let v = cam.fy * x_t.y / x_t.z + cam.cy;
    let lvl = target.level;
    let (w, h) = (lvl.width() as f64, lvl.height() as f64);
    if !(u >= 1.0 && v >= 1.0 && u <= w - 2.0 && v <= h - 2.0) {
        return None;
    }
    let (uf, vf) = (u as f32, v as f32);
    let i_t = f64::from(lvl.image.bilinear(uf, vf)?);
    let gx = f64::from(lvl.gx.bilinear(uf, vf)?);
    let gy = f64::from(lvl.gy.bilinear(uf, vf)?);
    let (a_h, b_h) = host.affine;
    let (a_t, b_t) = target.affine;
    let e = (a_t - a_h).exp();
    let i_h = point.intensity[k];
    let residual = i_t - e * (i_h - b_h) - b_t;

    let iz = 1.0 / x_t.z;
    let du_dx = Matrix2x3::new(
        cam.fx * iz,
        0.0,
        -cam.fx * x_t.x * iz * iz,
        0.0,
        cam.fy * iz,
        -cam.fy * x_t.y * iz * iz,
    );
    let g = Vector2::new(gx, gy).transpose() * du_dx; // dr/dx_t, 1×3
    let g = g.transpose();
    // Host perturbation: x_t = R_th (x_h + v + ω × x_h) + t_th.
    let dv_h = r_th.transpose() * g;
    let dw_h = -skew(&x_h).transpose() * dv_h;
    // Target perturbation: x_t ← x_t − v − ω × x_t.
    let dv_t = -g;
    let dw_t = skew(&x_t).transpose() * g;
    let d_idepth = g.dot(&(r_th * (-ray / (rho * rho))));

    let mut d_host = Vector8::zeros();
    d_host.fixed_rows_mut::<3>(0).copy_from(&dv_h);
    d_host.fixed_rows_mut::<3>(3).copy_from(&dw_h);
    d_host[6] = e * (i_h - b_h);
    d_host[7] = e;
    let mut d_target = Vector8::zeros();
    d_target.fixed_rows_mut::<3>(0).copy_from(&dv_t);
    d_target.fixed_rows_mut::<3>(3).copy_from(&dw_t);
    d_target[6] = -e * (i_h - b_h);
    d_target[7] = -1.0;
    Some(Linearised {
        residual,
        grad2: gx * gx + gy * gy,
        d_host,
        d_target,
        d_idepth,
    })
}

/// `view` moved by the parameter step `delta`: pose `T·exp(δ)`, affine `(a + δa, b + δb)`.
pub fn apply_step(view: &View<'_>, delta: &Vector8) -> (SE3, (f64, f64)) {
    let xi = delta.fixed_rows::<6>(0).into_owned();
    (
        view.world_from_camera * SE3::exp(&xi),
        (view.affine.0 + delta[6], view.affine.1 + delta[7]),
    )
}
