//! Tests of the epipolar line search on exactly known geometry.

use nalgebra::{Vector2, Vector3, Vector6};

use super::*;
use crate::frame::Frame;
use crate::geometry::{PinholeCamera, SE3, SO3};
use crate::image::ImageF32;
use crate::mapping::MappingConfig;

const DEPTH: f64 = 2.0;

fn camera() -> PinholeCamera {
    PinholeCamera::new(262.5, 262.5, 159.5, 119.5, 320, 240).expect("camera")
}

/// Smooth two-frequency texture on the plane z = DEPTH (8-bit units).
fn texture(x: f64, y: f64) -> f64 {
    128.0
        + 50.0 * (37.0 * x + 23.0 * y).sin()
        + 30.0 * (61.0 * x + 1.3).sin()
        + 25.0 * (47.0 * y + 0.4).sin()
}

/// The view of the textured plane from a camera whose centre is `c` (keyframe coordinates,
/// no rotation).
fn plane_view(cam: &PinholeCamera, c: Vector3<f64>, id: u64) -> Frame {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut img = ImageF32::filled(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            // Ray through the pixel hits z = DEPTH at depth DEPTH − c_z in this camera.
            let z = DEPTH - c.z;
            let px = (x as f64 - cam.cx) / cam.fx * z + c.x;
            let py = (y as f64 - cam.cy) / cam.fy * z + c.y;
            *img.at_mut(x, y) = texture(px, py) as f32;
        }
    }
    Frame::new(id, 0.0, *cam, &img, None).expect("frame")
}

fn pair<'a>(kf: &'a Frame, fr: &'a Frame, kf_from_fr: &SE3) -> StereoPair<'a> {
    let l0 = kf.level(0);
    StereoPair::new(
        &l0.image,
        &l0.gx,
        &l0.gy,
        &fr.level(0).image,
        Intrinsics::new(&kf.camera),
        kf_from_fr,
        0.25,
    )
}

/// Errors of full-range searches on a grid of pixels: disparity errors `|Δρ|·f·|b|` (pixels,
/// exact for a baseline parallel to the image plane), normalised errors `|Δρ|/σ`, and the
/// number of pixels searched.
fn search_errors(baseline: Vector3<f64>, cfg: &MappingConfig) -> (Vec<f64>, Vec<f64>, usize) {
    let cam = camera();
    let kf = plane_view(&cam, Vector3::zeros(), 0);
    let fr = plane_view(&cam, baseline, 1);
    let pose = SE3::new(SO3::identity(), baseline);
    let p = pair(&kf, &fr, &pose);
    let truth = (1.0 / DEPTH) as f32;
    let px_per_idepth = (cam.fx * baseline.norm()) as f32;
    let (mut disp, mut normalised, mut tried) = (Vec::new(), Vec::new(), 0);
    for y in (40..200).step_by(7) {
        for x in (60..260).step_by(5) {
            let Some(epl) = p.epipolar_direction(x, y, cfg) else {
                continue;
            };
            tried += 1;
            if let Ok(m) = p.search(x as f32, y as f32, epl, 0.0, 1.0, 20.0, cfg) {
                disp.push(f64::from((m.idepth - truth).abs() * px_per_idepth));
                normalised.push(f64::from((m.idepth - truth).abs() / m.var.sqrt()));
            }
        }
    }
    (disp, normalised, tried)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[test]
fn mapping_stereo_finds_true_disparity_with_subpixel_precision() {
    let cfg = MappingConfig::default();
    for baseline in [
        Vector3::new(0.1, 0.0, 0.0),
        Vector3::new(0.0, -0.08, 0.0),
        Vector3::new(0.06, 0.05, 0.0),
    ] {
        let (disp, normalised, tried) = search_errors(baseline, &cfg);
        assert!(tried > 100, "{tried} pixels with a usable epipolar line");
        let found = disp.len() as f64 / tried as f64;
        let med = median(disp.clone());
        let within3 =
            normalised.iter().filter(|&&e| e < 3.0).count() as f64 / normalised.len() as f64;
        eprintln!(
            "baseline {baseline:?}: found {found:.3}, median disparity error {med:.4} px, within 3σ {within3:.3}"
        );
        assert!(found > 0.9, "only {found} matched");
        assert!(med < 0.05, "median disparity error {med} px");
        assert!(disp.iter().filter(|&&e| e > 0.5).count() as f64 / (disp.len() as f64) < 0.02);
        assert!(
            within3 > 0.95,
            "the variance must cover the error: {within3}"
        );

        let coarse = MappingConfig {
            use_subpixel_stereo: false,
            ..cfg.clone()
        };
        let (disp_coarse, _, _) = search_errors(baseline, &coarse);
        let med_coarse = median(disp_coarse);
        assert!(
            med < 0.5 * med_coarse,
            "sub-pixel {med} vs integer steps {med_coarse}"
        );
    }
}

#[test]
fn mapping_stereo_forward_motion_rescales_samples() {
    // Moving towards the plane changes the scale between the images; the search must still
    // find the right inverse depth (LSD's rescale factor).
    // The disparity per unit inverse depth shrinks towards the epipole, so judge the errors
    // relative to the reported standard deviation.
    let cfg = MappingConfig::default();
    let (disp, normalised, tried) = search_errors(Vector3::new(0.03, 0.0, 0.12), &cfg);
    let within3 = normalised.iter().filter(|&&e| e < 3.0).count() as f64 / normalised.len() as f64;
    let med = median(normalised.clone());
    eprintln!(
        "forward: {} of {tried} matched, median |Δρ|/σ {med:.3}, within 3σ {within3:.3}",
        disp.len()
    );
    assert!(
        disp.len() as f64 > 0.7 * tried as f64,
        "{} of {tried}",
        disp.len()
    );
    assert!(within3 > 0.95, "within 3σ: {within3}");
    assert!(med < 1.0, "median normalised error {med}");
}

#[test]
fn mapping_stereo_idepth_derivative_matches_numeric() {
    let cam = camera();
    let img = ImageF32::filled(320, 240, 0.0);
    let xi = Vector6::new(0.12, -0.05, 0.03, 0.02, -0.04, 0.015);
    let kf_from_fr = SE3::exp(&xi);
    let p = StereoPair::new(
        &img,
        &img,
        &img,
        &img,
        Intrinsics::new(&cam),
        &kf_from_fr,
        0.25,
    );
    let fr_from_kf = kf_from_fr.inverse();
    for (u, v, idepth) in [(100.0, 80.0, 0.6), (250.0, 30.0, 1.7), (20.0, 200.0, 0.2)] {
        let ray = cam.unproject(&nalgebra::Vector2::new(u, v), 1.0);
        let q = fr_from_kf.act(&(ray / idepth));
        let m: Vector2<f32> = cam.project(&q).cast();
        let ray32: Vector3<f32> = ray.cast();
        for inc in [
            Vector2::new(0.95f32, 0.31),
            Vector2::new(-0.2, 0.98),
            Vector2::new(-0.7, -0.71),
        ] {
            let (rho, alpha) = p.idepth_from_match(&ray32, m, inc);
            assert!(
                (f64::from(rho) - idepth).abs() < 1e-3 * idepth,
                "triangulated {rho} vs {idepth}"
            );
            let h = 0.05f32;
            let (rp, _) = p.idepth_from_match(&ray32, m + inc * h, inc);
            let (rm, _) = p.idepth_from_match(&ray32, m - inc * h, inc);
            let numeric = (rp - rm) / (2.0 * h);
            assert!(
                (alpha - numeric).abs() < 1e-3 * alpha.abs().max(1e-3),
                "alpha {alpha} vs numeric {numeric} (inc {inc:?})"
            );
        }
    }
}

#[test]
fn mapping_stereo_geometric_variance_follows_eq5() {
    let cam = camera();
    // Ramp I = 2x + y: half-difference gradients (2, 1) everywhere inside.
    let data = (0..240)
        .flat_map(|y| (0..320).map(move |x| (2 * x + y) as f32))
        .collect();
    let img = ImageF32::from_vec(320, 240, data).expect("ramp");
    let f = Frame::new(0, 0.0, cam, &img, None).expect("frame");
    let l0 = f.level(0);
    let p = StereoPair::new(
        &l0.image,
        &l0.gx,
        &l0.gy,
        &l0.image,
        Intrinsics::new(&cam),
        &SE3::identity(),
        0.5,
    );
    let s2 = 0.25f32;
    let cases = [
        (Vector2::new(1.0f32, 0.0), s2 * 5.0 / 4.0),
        (Vector2::new(0.0, 1.0), s2 * 5.0),
        (Vector2::new(1.0, 1.0).normalize(), s2 * 10.0 / 9.0),
    ];
    for (epl, expected) in cases {
        let got = p.geometric_disparity_var(100.0, 100.0, epl);
        assert!(
            (got - expected).abs() < 1e-4 * expected,
            "{epl:?}: {got} vs {expected}"
        );
    }
}

#[test]
fn mapping_stereo_rejects_degenerate_epipolar_lines() {
    let cfg = MappingConfig::default();
    let cam = camera();
    let kf = plane_view(&cam, Vector3::zeros(), 0);
    // No baseline: every line is degenerate.
    let p = pair(&kf, &kf, &SE3::identity());
    assert!((10..300).all(|x| p.epipolar_direction(x, 120, &cfg).is_none()));
    // A texture constant along x seen with a horizontal baseline: gradient ⟂ line.
    let stripes = ImageF32::from_vec(
        320,
        240,
        (0..240)
            .flat_map(|y| (0..320).map(move |_| (y % 7 * 30) as f32))
            .collect(),
    )
    .expect("stripes");
    let sf = Frame::new(0, 0.0, cam, &stripes, None).expect("frame");
    let ps = pair(
        &sf,
        &sf,
        &SE3::new(SO3::identity(), Vector3::new(0.1, 0.0, 0.0)),
    );
    assert!((10..300).all(|x| ps.epipolar_direction(x, 120, &cfg).is_none()));
    // The same stripes with a vertical baseline are fine.
    let pv = pair(
        &sf,
        &sf,
        &SE3::new(SO3::identity(), Vector3::new(0.0, 0.1, 0.0)),
    );
    assert!((10..300).any(|x| pv.epipolar_direction(x, 120, &cfg).is_some()));
}
