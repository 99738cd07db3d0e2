//! The depth filter on the real 7-Scenes redkitchen sequence (shared data, skipped when absent)
//! with its ground-truth poses; the sensor depth is the reference. 7-Scenes colour and depth
//! are not registered (a few pixels apart) and the poses are the depth camera's, so the
//! reference is only good to a few percent at texture edges.

use std::sync::Arc;
use std::time::Instant;

use super::test_scene::{median, relative_errors, share_above};
use super::{DepthFilter, MappingConfig};
use crate::dataset::TumSequence;
use crate::frame::Frame;
use crate::image::ImageF32;

fn redkitchen() -> Option<TumSequence> {
    crate::dataset::shared_sequence("7scenes_redkitchen_f0000-0299")
}

#[test]
fn mapping_real_redkitchen_converges_with_true_poses() {
    let Some(seq) = redkitchen() else { return };
    let frames: Vec<Arc<Frame>> = (0..=30)
        .map(|i| Arc::new(crate::dataset::shared_frame(&seq, i)))
        .collect();
    let pose = |i: usize| seq.frames[i].world_from_camera.expect("ground truth");
    let depth = seq.load_depth(0).expect("depth").expect("depth image");
    let gt_metric = ImageF32::from_vec(
        depth.width,
        depth.height,
        depth
            .data
            .iter()
            .map(|&z| if z > 0.1 { 1.0 / z } else { 0.0 })
            .collect(),
    )
    .expect("size");

    let mut f = DepthFilter::new(frames[0].clone(), MappingConfig::default()).expect("filter");
    f.init_random(5);
    // Express the true poses in the scale of the random map (mean inverse depth 1), as LSD's
    // tracking would.
    let (mut sum, mut n) = (0.0f64, 0usize);
    for (i, &g) in gt_metric.data.iter().enumerate() {
        if g > 0.0 && f.raw_estimate(i % f.width(), i / f.width()).is_some() {
            sum += f64::from(g);
            n += 1;
        }
    }
    let k = sum / n.max(1) as f64;
    let gt = ImageF32::from_vec(
        gt_metric.width,
        gt_metric.height,
        gt_metric.data.iter().map(|v| v / k as f32).collect(),
    )
    .expect("size");

    let (mut t_obs, mut t_reg, mut timed) = (0.0, 0.0, 0usize);
    for (i, frame) in frames.iter().enumerate().skip(1) {
        let mut rel = pose(0).inverse() * pose(i);
        rel.translation *= k;
        let t0 = Instant::now();
        f.observe(frame, &rel).expect("observe");
        let t1 = Instant::now();
        f.regularize();
        if i > 3 {
            t_obs += (t1 - t0).as_secs_f64();
            t_reg += t1.elapsed().as_secs_f64();
            timed += 1;
        }
    }
    let map = f.depth_map();
    let errs = relative_errors(&map, &gt);
    // Ratios estimate/reference of the confident (observed) hypotheses; the unobserved random
    // ones keep a large raw variance and are excluded.
    let ratios: Vec<f64> = map
        .pixels
        .iter()
        .zip(&gt.data)
        .filter_map(|(p, &g)| {
            let (d, v) = p.estimate()?;
            (g > 0.0 && v < 1e-3).then(|| f64::from(d / g))
        })
        .collect();
    // The colour camera's focal length is not calibrated (585 is the depth camera's), which
    // biases the scale of every estimate alike: compare after aligning the median ratio.
    let bias = median(ratios.clone());
    let aligned: Vec<f64> = ratios.iter().map(|q| (q / bias - 1.0).abs()).collect();
    let med = median(aligned.clone());
    eprintln!(
        "redkitchen 640x480: {} estimates, {} confident; scale ratio {bias:.3}, aligned median \
         rel err {med:.4}, >10%: {:.3}; observe {:.2} ms, regularize {:.2} ms",
        errs.len(),
        ratios.len(),
        share_above(&aligned, 0.1),
        t_obs / timed as f64 * 1e3,
        t_reg / timed as f64 * 1e3
    );
    assert!(ratios.len() > 20_000, "too few confident estimates");
    assert!((0.8..1.25).contains(&bias), "scale ratio {bias}");
    assert!(
        med < 0.05,
        "median relative error of confident estimates {med}"
    );
    assert!(share_above(&aligned, 0.1) < 0.25, "too many outliers");
}
