//! The photometric residual of a window point in one target keyframe and its first-estimate
//! Jacobians (DSO, TPAMI 2018, eqs. 4-5 and §2.2 "First Estimate Jacobians").
//!
//! A point is hosted in keyframe `h` at pixel `u`, with inverse depth `ρ` in `h`'s camera.
//! Pattern pixel `u + o` is predicted in target `t` at `π(T_tw·T_wh·(K⁻¹(u + o)/ρ))` (the
//! pattern shares the centre's depth: DSO's fronto-parallel assumption) and its residual is
//! `r = I_t(u') − b_t − e^{a_t − a_h}(I_h(u + o) − b_h)`.
//!
//! Residual and image gradient are evaluated at the current state; the geometric part of the
//! Jacobian (how the pixel moves with the two poses and the depth) at the keyframes'
//! *first estimates*. Every residual then sees the same linearisation point of a keyframe, so
//! the 7 directions that leave all residuals unchanged (a rigid motion and a scale of the whole
//! window) stay exactly unobservable in every Hessian and in the marginalisation prior built
//! from them; with Jacobians at the current state the prior would gain fake information along
//! them and the estimate would drift while looking certain. Poses are perturbed on the right,
//! `T ← T·exp(δ)`, tangent order (v, ω); a keyframe's eight parameters are `(v, ω, a, b)`.

use nalgebra::{Matrix3, SMatrix, Vector2, Vector3, Vector6};

use crate::geometry::{PinholeCamera, SE3, SO3};
use crate::image::pyramid::PyramidLevel;

/// Parameters per keyframe: pose (6) and affine brightness (2).
pub const FRAME_PARAMS: usize = 8;
/// A keyframe's parameter vector.
pub type Vector8 = SMatrix<f64, FRAME_PARAMS, 1>;
/// A block of the window's Hessian between two keyframes.
pub type Matrix8 = SMatrix<f64, FRAME_PARAMS, FRAME_PARAMS>;

/// DSO's residual pattern of eight pixels around the point (`staticPattern[8]`): spread
/// enough to be distinctive, small enough for one depth to hold.
pub const PATTERN: [(f64, f64); 8] = [
    (0.0, -2.0),
    (-1.0, -1.0),
    (1.0, -1.0),
    (-2.0, 0.0),
    (0.0, 0.0),
    (2.0, 0.0),
    (-1.0, 1.0),
    (0.0, 2.0),
];

/// Pose and affine brightness `(a, b)` of a keyframe.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameState {
    pub world_from_camera: SE3,
    pub affine: (f64, f64),
}

impl FrameState {
    /// The state moved by `delta`: pose `T·exp(δ)`, affine `(a + δa, b + δb)`.
    pub fn step(&self, delta: &Vector8) -> Self {
        let xi = delta.fixed_rows::<6>(0).into_owned();
        Self {
            world_from_camera: self.world_from_camera * SE3::exp(&xi),
            affine: (self.affine.0 + delta[6], self.affine.1 + delta[7]),
        }
    }

    /// Where this state is relative to `origin`, in the coordinates of [`Self::step`]
    /// (`origin.step(d) == self`).
    pub fn delta_from(&self, origin: &FrameState) -> Vector8 {
        let xi = (origin.world_from_camera.inverse() * self.world_from_camera).log();
        let mut d = Vector8::zeros();
        d.fixed_rows_mut::<6>(0).copy_from(&xi);
        d[6] = self.affine.0 - origin.affine.0;
        d[7] = self.affine.1 - origin.affine.1;
        d
    }
}

/// A keyframe as the residuals see it: its image at the window's level, that level's camera,
/// its current state and the state its Jacobians are evaluated at.
#[derive(Clone, Copy, Debug)]
pub struct FrameView<'a> {
    pub level: &'a PyramidLevel,
    /// The same level interleaved, for sampling.
    pub samples: &'a Interleaved,
    pub camera: PinholeCamera,
    pub state: FrameState,
    pub first_estimate: FrameState,
    /// The camera's motion from one image row to the next at this level (rolling shutter:
    /// row `v` is seen from `pose · exp(row_twist · (v − middle row))`); zero for a global
    /// shutter.
    pub row_twist: Vector6<f64>,
}

impl FrameView<'_> {
    /// The pose of row `v` relative to the frame's pose (the middle row's); `None` for a
    /// global shutter.
    fn row_offset(&self, v: f64) -> Option<SE3> {
        if self.row_twist == Vector6::zeros() {
            return None;
        }
        let middle = 0.5 * (self.level.height() as f64 - 1.0);
        Some(SE3::exp(&(self.row_twist * (v - middle))))
    }
}

/// Which state the geometric Jacobians are evaluated at.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Linearisation {
    /// The keyframes' first estimates (DSO; the gauge stays unobservable).
    FirstEstimate,
    /// The current state (plain Gauss–Newton; only to show what FEJ prevents).
    Current,
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

/// What the pattern pixels of every point of one host seen in one target share: the relative
/// poses at the current state and at the linearisation point, and the brightness transfer.
/// Computed once per point and target instead of once per pixel (it was a tenth of the
/// window's time).
#[derive(Clone, Copy, Debug)]
pub struct PairGeometry {
    target_from_host: SE3,
    lin_target_from_host: SE3,
    lin_rotation: Matrix3<f64>,
    transfer: f64,
}

impl PairGeometry {
    /// The geometry of the point at host pixel `uv` with inverse depth `idepth` in `target`.
    /// With a rolling shutter the host pose is that of the point's row, the target's that of
    /// the row where the point lands (found with the host row's pose); the Jacobians treat
    /// the rows' offsets as constants (they are a fraction of a degree).
    pub fn new(
        host: &FrameView<'_>,
        target: &FrameView<'_>,
        mode: Linearisation,
        uv: &Vector2<f64>,
        idepth: f64,
    ) -> Self {
        let relative =
            |h: &FrameState, t: &FrameState| t.world_from_camera.inverse() * h.world_from_camera;
        let mut target_from_host = relative(&host.state, &target.state);
        // Geometry at the linearisation point, the image gradient at the current prediction.
        let mut lin_target_from_host = match mode {
            Linearisation::FirstEstimate => relative(&host.first_estimate, &target.first_estimate),
            Linearisation::Current => target_from_host,
        };
        if let Some(d) = host.row_offset(uv.y) {
            target_from_host = target_from_host * d;
            lin_target_from_host = lin_target_from_host * d;
        }
        if target.row_twist != Vector6::zeros() {
            let x = target_from_host.act(&(host.camera.unproject(uv, 1.0) / idepth.max(1e-12)));
            if x.z > 1e-6
                && let Some(d) = target.row_offset(target.camera.project(&x).y)
            {
                let back = d.inverse();
                target_from_host = back * target_from_host;
                lin_target_from_host = back * lin_target_from_host;
            }
        }
        Self {
            target_from_host,
            lin_rotation: lin_target_from_host.rotation.matrix(),
            lin_target_from_host,
            transfer: (target.state.affine.0 - host.state.affine.0).exp(),
        }
    }
}

/// The residual of pattern pixel `k` of the point at `uv` (host pixel) with inverse depth
/// `idepth` and host intensity `host_intensity`, in `target`, with its derivatives with
/// respect to both keyframes' parameters and the inverse depth; `None` when the point falls
/// behind the target camera or outside its image.
pub fn linearise(
    uv: &Vector2<f64>,
    idepth: f64,
    host_intensity: f64,
    k: usize,
    host: &FrameView<'_>,
    target: &FrameView<'_>,
    mode: Linearisation,
) -> Option<Linearised> {
    let pair = PairGeometry::new(host, target, mode, uv, idepth);
    linearise_in(&pair, uv, idepth, host_intensity, k, host, target)
}

/// One pattern pixel's prediction in the target: what the residual and the Jacobians share.
struct Prediction {
    ray: Vector3<f64>,
    x_h: Vector3<f64>,
    residual: f64,
    gx: f64,
    gy: f64,
}

/// The residual of pattern pixel `k` and the target's gradient there; `None` when the point
/// falls behind the target camera or outside its image.
fn predict(
    pair: &PairGeometry,
    uv: &Vector2<f64>,
    idepth: f64,
    host_intensity: f64,
    k: usize,
    host: &FrameView<'_>,
    target: &FrameView<'_>,
) -> Option<Prediction> {
    // Also refuses NaN.
    if idepth.is_nan() || idepth <= 0.0 {
        return None;
    }
    let (ox, oy) = PATTERN[k];
    let ray = host
        .camera
        .unproject(&Vector2::new(uv.x + ox, uv.y + oy), 1.0);
    let x_h = ray / idepth;
    let x_t = pair.target_from_host.act(&x_h);
    if x_t.z < 1e-3 {
        return None;
    }
    let u = target.camera.project(&x_t);
    let lvl = target.level;
    let (w, h) = (lvl.width() as f64, lvl.height() as f64);
    if !(u.x >= 1.0 && u.y >= 1.0 && u.x <= w - 2.0 && u.y <= h - 2.0) {
        return None;
    }
    let (i_t, gx, gy) = target.samples.sample(u.x as f32, u.y as f32)?;
    let (_, b_h) = host.state.affine;
    let (_, b_t) = target.state.affine;
    let residual = i_t - b_t - pair.transfer * (host_intensity - b_h);
    Some(Prediction {
        ray,
        x_h,
        residual,
        gx,
        gy,
    })
}

/// The residual of pattern pixel `k` and the squared gradient there, without the Jacobians
/// (for energies: half the cost of [`linearise_in`]).
pub fn residual_in(
    pair: &PairGeometry,
    uv: &Vector2<f64>,
    idepth: f64,
    host_intensity: f64,
    k: usize,
    host: &FrameView<'_>,
    target: &FrameView<'_>,
) -> Option<(f64, f64)> {
    let p = predict(pair, uv, idepth, host_intensity, k, host, target)?;
    Some((p.residual, p.gx * p.gx + p.gy * p.gy))
}

/// [`linearise`] with the pair's shared values computed.
pub fn linearise_in(
    pair: &PairGeometry,
    uv: &Vector2<f64>,
    idepth: f64,
    host_intensity: f64,
    k: usize,
    host: &FrameView<'_>,
    target: &FrameView<'_>,
) -> Option<Linearised> {
    let Prediction {
        ray,
        x_h,
        residual,
        gx,
        gy,
    } = predict(pair, uv, idepth, host_intensity, k, host, target)?;
    let (_, b_h) = host.state.affine;
    let e = pair.transfer;
    let r_th = &pair.lin_rotation;
    let x_t_lin = pair.lin_target_from_host.act(&x_h);
    let du_dx = target.camera.project_jacobian(&x_t_lin);
    let g = (Vector2::new(gx, gy).transpose() * du_dx).transpose(); // ∂r/∂x_t
    // Host perturbation: x_t = R_th (x_h + v + ω × x_h) + t_th.
    let dv_h = r_th.transpose() * g;
    let dw_h = -SO3::hat(&x_h).transpose() * dv_h;
    // Target perturbation: x_t ← x_t − v − ω × x_t.
    let dv_t = -g;
    let dw_t = SO3::hat(&x_t_lin).transpose() * g;
    let d_idepth = g.dot(&(r_th * (-ray / (idepth * idepth))));

    let mut d_host = Vector8::zeros();
    d_host.fixed_rows_mut::<3>(0).copy_from(&dv_h);
    d_host.fixed_rows_mut::<3>(3).copy_from(&dw_h);
    d_host[6] = e * (host_intensity - b_h);
    d_host[7] = e;
    let mut d_target = Vector8::zeros();
    d_target.fixed_rows_mut::<3>(0).copy_from(&dv_t);
    d_target.fixed_rows_mut::<3>(3).copy_from(&dw_t);
    d_target[6] = -e * (host_intensity - b_h);
    d_target[7] = -1.0;
    Some(Linearised {
        residual,
        grad2: gx * gx + gy * gy,
        d_host,
        d_target,
        d_idepth,
    })
}

/// A level's intensity and gradients interleaved per pixel (DSO's `dI`), so that sampling a
/// point reads two cache lines instead of six: sampling was a fifth of the window's time.
#[derive(Clone, Debug)]
pub struct Interleaved {
    width: usize,
    height: usize,
    data: Vec<[f32; 3]>,
}

impl Interleaved {
    /// Bytes a pixel takes: its intensity and two gradients, `f32` each.
    pub const BYTES_PER_PIXEL: usize = std::mem::size_of::<[f32; 3]>();

    pub fn new(level: &PyramidLevel) -> Self {
        let data = (level.image.data.iter())
            .zip(&level.gx.data)
            .zip(&level.gy.data)
            .map(|((i, gx), gy)| [*i, *gx, *gy])
            .collect();
        Self {
            width: level.image.width,
            height: level.image.height,
            data,
        }
    }

    /// Intensity and gradients at `(x, y)`, bilinear (the arithmetic of
    /// [`ImageF32::bilinear`](crate::image::ImageF32::bilinear) on each of the three, written
    /// out here: a shared tap type for both made the window 20 % slower, measured).
    #[inline]
    fn sample(&self, x: f32, y: f32) -> Option<(f64, f64, f64)> {
        let (w, h) = (self.width, self.height);
        if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f32 && y <= (h - 1) as f32) {
            return None;
        }
        let x0 = (x.floor() as usize).min(w.saturating_sub(2));
        let y0 = (y.floor() as usize).min(h.saturating_sub(2));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let x1 = (x0 + 1).min(w - 1);
        let y1 = (y0 + 1).min(h - 1);
        let [a, b, c, d] = [
            self.data[y0 * w + x0],
            self.data[y0 * w + x1],
            self.data[y1 * w + x0],
            self.data[y1 * w + x1],
        ];
        let at = |j: usize| {
            let top = a[j] * (1.0 - fx) + b[j] * fx;
            let bottom = c[j] * (1.0 - fx) + d[j] * fx;
            f64::from(top * (1.0 - fy) + bottom * fy)
        };
        Some((at(0), at(1), at(2)))
    }
}
