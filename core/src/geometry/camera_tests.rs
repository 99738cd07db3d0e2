//! Tests of [`PinholeCamera`], [`Distortion`] and [`super::super::UndistortMap`].

use super::*;
use crate::geometry::UndistortMap;
use crate::geometry::testing::numeric_jacobian;
use crate::image::ImageF32;
use proptest::prelude::*;

fn fr1() -> PinholeCamera {
    PinholeCamera::tum_freiburg1()
}

#[test]
fn new_validates() {
    assert!(PinholeCamera::new(517.3, 516.5, 318.6, 255.3, 640, 480).is_ok());
    let cases: [(f64, f64, f64, f64, u32, u32, &str); 8] = [
        (0.0, 500.0, 320.0, 240.0, 640, 480, "fx"),
        (-1.0, 500.0, 320.0, 240.0, 640, 480, "fx"),
        (f64::NAN, 500.0, 320.0, 240.0, 640, 480, "fx"),
        (500.0, f64::INFINITY, 320.0, 240.0, 640, 480, "fy"),
        (500.0, 500.0, f64::NAN, 240.0, 640, 480, "cx"),
        (500.0, 500.0, 320.0, f64::NEG_INFINITY, 640, 480, "cy"),
        (500.0, 500.0, 320.0, 240.0, 0, 480, "size"),
        (500.0, 500.0, 320.0, 240.0, 640, 0, "size"),
    ];
    for (fx, fy, cx, cy, w, h, what) in cases {
        match PinholeCamera::new(fx, fy, cx, cy, w, h) {
            Err(Error::InvalidCamera(msg)) => assert!(msg.contains(what), "{msg} lacks {what}"),
            other => panic!("expected InvalidCamera({what}), got {other:?}"),
        }
    }
    let cam = PinholeCamera::new(500.0, 500.0, 320.0, 240.0, 640, 480).expect("valid camera");
    let bad = Distortion::new(0.1, f64::NAN, 0.0, 0.0, 0.0);
    assert!(matches!(
        cam.with_distortion(bad),
        Err(Error::InvalidCamera(_))
    ));
    let good = cam
        .with_distortion(Distortion::new(0.1, 0.0, 0.0, 0.0, 0.0))
        .expect("finite");
    assert!(good.distortion.is_some());
}

#[test]
fn serde_round_trip_validates() {
    let cam = fr1();
    let text = serde_json::to_string(&cam).expect("serialise");
    let back: PinholeCamera = serde_json::from_str(&text).expect("deserialise");
    assert_eq!(back, cam);
    let bad = r#"{"fx": -5.0, "fy": 1.0, "cx": 0.0, "cy": 0.0, "width": 4, "height": 4}"#;
    let err = serde_json::from_str::<PinholeCamera>(bad).expect_err("negative fx rejected");
    assert!(err.to_string().contains("fx"), "{err}");
    let no_dist = r#"{"fx": 5.0, "fy": 5.0, "cx": 2.0, "cy": 2.0, "width": 4, "height": 4}"#;
    let cam: PinholeCamera = serde_json::from_str(no_dist).expect("distortion optional");
    assert!(cam.distortion.is_none());
}

#[test]
fn k_matrix_and_inverse() {
    let cam = fr1();
    let prod = cam.k_matrix() * cam.k_inverse();
    assert!((prod - Matrix3::identity()).abs().max() < 1e-15);
    let p = Vector3::new(0.3, -0.2, 2.0);
    let h = cam.k_matrix() * p;
    assert!((cam.project(&p) - h.xy() / h.z).norm() < 1e-12);
}

proptest! {
    #[test]
    fn project_unproject_round_trip(u in 0.0..639.0f64, v in 0.0..479.0f64, d in 0.1..20.0f64) {
        let cam = fr1();
        let uv = Vector2::new(u, v);
        let p = cam.unproject(&uv, d);
        prop_assert!((p.z - d).abs() < 1e-12);
        prop_assert!((cam.project(&p) - uv).norm() < 1e-9);
    }

    #[test]
    fn project_jacobian_matches_numeric(x in -2.0..2.0f64, y in -2.0..2.0f64, z in 0.5..10.0f64) {
        let cam = fr1();
        let p = Vector3::new(x, y, z);
        let f = |d: &Vector3<f64>| cam.project(&(p + d));
        let num = numeric_jacobian::<3, 2>(&f);
        prop_assert!((cam.project_jacobian(&p) - num).abs().max() < 1e-5 * (1.0 + num.abs().max()));
    }

    #[test]
    fn distort_jacobian_matches_numeric(x in -0.7..0.7f64, y in -0.6..0.6f64) {
        let d = fr1().distortion.expect("fr1 has distortion");
        let p = Vector2::new(x, y);
        let f = |e: &Vector2<f64>| d.distort(&(p + e));
        let num = numeric_jacobian::<2, 2>(&f);
        prop_assert!((d.distort_jacobian(&p) - num).abs().max() < 1e-7);
    }

    #[test]
    fn scaled_relations(level in 0u32..5, x in -2.0..2.0f64, y in -2.0..2.0f64, z in 0.5..10.0f64) {
        let cam = fr1();
        let s = cam.scaled(level);
        let f = f64::from(1u32 << level);
        let p = Vector3::new(x, y, z);
        // A point projects to the level-L pixel whose block contains its level-0 pixel.
        let expected = (cam.project(&p) + Vector2::repeat(0.5)) / f - Vector2::repeat(0.5);
        prop_assert!((s.project(&p) - expected).norm() < 1e-9);
        prop_assert_eq!(s.width, 640 >> level);
        prop_assert_eq!(s.height, 480 >> level);
        // Halving twice equals halving to level 2 directly.
        let twice = cam.scaled(1).scaled(1);
        let direct = cam.scaled(2);
        prop_assert!((twice.cx - direct.cx).abs() < 1e-12 && (twice.fy - direct.fy).abs() < 1e-12);
        prop_assert_eq!(s.distortion, cam.distortion);
    }
}

#[test]
fn scaled_level_zero_is_identity_and_centres_map() {
    let cam = fr1();
    assert_eq!(cam.scaled(0), cam);
    // The centre of level-1 pixel 0 is the midpoint of level-0 pixels 0 and 1.
    let c = PinholeCamera::new(100.0, 100.0, 0.5, 0.5, 8, 8)
        .expect("valid")
        .scaled(1);
    assert!(c.cx.abs() < 1e-15 && c.cy.abs() < 1e-15);
    assert_eq!(cam.scaled(40).width, 1);
}

#[test]
fn is_in_image_bounds() {
    let cam = fr1();
    assert!(cam.is_in_image(&Vector2::new(0.0, 0.0)));
    assert!(cam.is_in_image(&Vector2::new(639.0, 479.0)));
    assert!(!cam.is_in_image(&Vector2::new(639.01, 10.0)));
    assert!(!cam.is_in_image(&Vector2::new(10.0, -0.01)));
    assert!(!cam.is_in_image(&Vector2::new(f64::NAN, 10.0)));
    assert!(!cam.is_in_image_with_border(&Vector2::new(2.0, 100.0), 3.0));
    assert!(cam.is_in_image_with_border(&Vector2::new(3.0, 100.0), 3.0));
}

#[test]
fn distort_undistort_round_trip_over_fr1_image() {
    let cam = fr1();
    let mut worst: f64 = 0.0;
    let mut worst_reverse: f64 = 0.0;
    for v in (0..480).step_by(2) {
        for u in (0..640).step_by(2) {
            let raw = Vector2::new(f64::from(u), f64::from(v));
            let ideal = cam.undistort_pixel(&raw);
            worst = worst.max((cam.distort_pixel(&ideal) - raw).norm());
            let back = cam.undistort_pixel(&cam.distort_pixel(&raw));
            worst_reverse = worst_reverse.max((back - raw).norm());
        }
    }
    println!(
        "fr1 distort∘undistort max error {worst:e} px, undistort∘distort {worst_reverse:e} px"
    );
    assert!(
        worst < 1e-3 && worst_reverse < 1e-3,
        "{worst} / {worst_reverse}"
    );
    // Distortion is strong enough that the test means something: corners move by > 10 px.
    assert!((cam.undistort_pixel(&Vector2::new(0.0, 0.0)) - Vector2::new(0.0, 0.0)).norm() > 10.0);
}

/// A smooth grid of straight lines in the ideal image: dark lines (Gaussian profile, σ = 2.5
/// px, wide enough that bilinear resampling barely blurs them) every 40 px on a bright
/// background.
fn grid(uv: &Vector2<f64>) -> f32 {
    let line = |c: f64| {
        let d = (c - 20.0).rem_euclid(40.0) - 20.0;
        (-d * d / (2.0 * 2.5 * 2.5)).exp()
    };
    (200.0 - 150.0 * line(uv.x).max(line(uv.y))) as f32
}

#[test]
fn undistort_map_recovers_straight_grid() {
    let cam = fr1();
    let (w, h) = (cam.width as usize, cam.height as usize);
    // Render what the lens sees: raw pixel → ideal pixel → pattern.
    let mut raw = ImageF32::filled(w, h, 0.0);
    let mut ideal = ImageF32::filled(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            let uv = Vector2::new(x as f64, y as f64);
            *raw.at_mut(x, y) = grid(&cam.undistort_pixel(&uv));
            *ideal.at_mut(x, y) = grid(&uv);
        }
    }
    let map = UndistortMap::new(&cam);
    assert_eq!(map.undistorted_camera(), cam.undistorted());
    let out = map.apply(&raw).expect("same size");
    let (mut sum, mut worst, mut n, mut sum_raw) = (0.0f64, 0.0f32, 0usize, 0.0f64);
    for y in 0..h {
        for x in 0..w {
            match map.source(x as u32, y as u32) {
                Some(_) => {
                    let e = (out.at(x, y) - ideal.at(x, y)).abs();
                    sum += f64::from(e);
                    sum_raw += f64::from((raw.at(x, y) - ideal.at(x, y)).abs());
                    worst = worst.max(e);
                    n += 1;
                }
                None => assert_eq!(out.at(x, y), 0.0, "outside pixels are 0"),
            }
        }
    }
    let (mean, mean_raw) = (sum / n as f64, sum_raw / n as f64);
    println!("undistort grid: mean |err| {mean:.3}, max {worst:.2} (raw vs ideal: {mean_raw:.2})");
    // Bilinear resampling blurs the line profile a little; the raw image is off by whole line
    // widths near the border.
    assert!(mean < 1.0, "mean error {mean}");
    assert!(worst < 20.0, "max error {worst}");
    assert!(
        mean_raw > 10.0 * mean,
        "raw {mean_raw} vs undistorted {mean}"
    );
    // Most of the output is covered (fr1's barrel-like distortion keeps corners inside).
    assert!(n as f64 > 0.9 * (w * h) as f64, "{n} valid pixels");
}

#[test]
fn undistort_map_straightens_border_line() {
    // The vertical grid line at ideal x = 40 (near the left border), sampled on rows midway
    // between horizontal lines: in the undistorted output its intensity-weighted column is the
    // same on every row; in the raw image it bends by pixels.
    let cam = fr1();
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut raw = ImageF32::filled(w, h, 0.0);
    for y in 0..h {
        for x in 0..w {
            *raw.at_mut(x, y) = grid(&cam.undistort_pixel(&Vector2::new(x as f64, y as f64)));
        }
    }
    let out = UndistortMap::new(&cam).apply(&raw).expect("same size");
    let centroid = |img: &ImageF32, y: usize, lo: usize, hi: usize| {
        let (mut s, mut sw) = (0.0f64, 0.0f64);
        for x in lo..hi {
            let wgt = f64::from(200.0 - img.at(x, y)).max(0.0);
            s += wgt * x as f64;
            sw += wgt;
        }
        s / sw
    };
    let spread = |v: &[f64]| {
        v.iter().cloned().fold(f64::MIN, f64::max) - v.iter().cloned().fold(f64::MAX, f64::min)
    };
    let rows: Vec<usize> = (20..h).step_by(40).collect();
    let cols: Vec<f64> = rows.iter().map(|&y| centroid(&out, y, 30, 51)).collect();
    let raw_cols: Vec<f64> = rows.iter().map(|&y| centroid(&raw, y, 12, 56)).collect();
    println!("undistorted line columns {cols:.3?}\nraw line columns {raw_cols:.3?}");
    assert!(spread(&cols) < 0.05, "undistorted line wanders: {cols:?}");
    assert!(
        cols.iter().all(|c| (c - 40.0).abs() < 0.05),
        "line not at x = 40: {cols:?}"
    );
    assert!(
        spread(&raw_cols) > 3.0,
        "raw line should bend: {raw_cols:?}"
    );
}

#[test]
fn undistort_map_identity_without_distortion_and_checks_size() {
    let cam = fr1().undistorted();
    let img = ImageF32::from_vec(640, 480, (0..640 * 480).map(|i| (i % 251) as f32).collect())
        .expect("size");
    let map = UndistortMap::new(&cam);
    assert_eq!(map.apply(&img).expect("same size"), img);
    let small = ImageF32::filled(320, 240, 1.0);
    assert!(matches!(map.apply(&small), Err(Error::Shape(_))));
    let rgb = ::image::RgbImage::from_fn(640, 480, |x, y| ::image::Rgb([x as u8, y as u8, 7]));
    assert_eq!(map.apply_rgb(&rgb).expect("same size"), rgb);
}

#[test]
fn apply_rgb_matches_gray() {
    let cam = fr1();
    let rgb = ::image::RgbImage::from_fn(640, 480, |x, y| {
        let v = ((x / 8 + y / 8) % 2 * 200 + 20) as u8;
        ::image::Rgb([v, v, v])
    });
    let map = UndistortMap::new(&cam);
    let out_rgb = map.apply_rgb(&rgb).expect("size");
    let out_gray = map.apply(&ImageF32::from_rgb8(&rgb)).expect("size");
    let g = ImageF32::from_rgb8(&out_rgb);
    let worst = g
        .data
        .iter()
        .zip(&out_gray.data)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    assert!(worst <= 1.0, "rgb vs gray undistortion differ by {worst}");
}

#[test]
fn apply_nearest_moves_depths_without_blending_them() {
    let cam = fr1();
    // Two depth planes in 8×8 blocks with holes: any blend would create a value in between.
    let depth = ImageF32::from_vec(
        640,
        480,
        (0..640 * 480)
            .map(|i| {
                let (x, y) = (i % 640, i / 640);
                if (x + y) % 13 == 0 {
                    0.0
                } else if (x / 8 + y / 8) % 2 == 0 {
                    1.0
                } else {
                    3.0
                }
            })
            .collect(),
    )
    .expect("size");
    let map = UndistortMap::new(&cam);
    let out = map.apply_nearest(&depth).expect("same size");
    let mut checked = 0;
    for y in 0..480u32 {
        for x in 0..640u32 {
            let v = out.at(x as usize, y as usize);
            assert!(
                v == 0.0 || v == 1.0 || v == 3.0,
                "blended depth {v} at ({x}, {y})"
            );
            if let Some(s) = map.source(x, y) {
                let (sx, sy) = ((s.x + 0.5).floor() as usize, (s.y + 0.5).floor() as usize);
                if sx < 640 && sy < 480 {
                    assert_eq!(v, depth.at(sx, sy), "({x}, {y}) from ({sx}, {sy})");
                    checked += 1;
                }
            }
        }
    }
    assert!(checked > 600 * 440, "only {checked} pixels had a source");
    let undistorted = cam.undistorted();
    assert_eq!(
        UndistortMap::new(&undistorted)
            .apply_nearest(&depth)
            .expect("same size"),
        depth
    );
    assert!(matches!(
        map.apply_nearest(&ImageF32::filled(320, 240, 1.0)),
        Err(Error::Shape(_))
    ));
}
