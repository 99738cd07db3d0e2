//! A keyframe's map-to-metre scale observed through a metric depth prior (issue 39).
//!
//! A keyframe's inverse depths live in its own gauge: `ρ_kf = s·ρ_world`, where `s` is the
//! scale of its `world_from_keyframe` similarity. When the world is in metres, `ρ_world` is the
//! metric inverse depth a metric network (FastDepth, Depth Anything metric, UniDepth) predicts,
//! so every semi-dense pixel votes `ln s = ln ρ_kf − ln ρ_prior`. The median of the votes is
//! robust to the semi-dense map's outliers and to the network's local failures; the spread of
//! the votes (MAD) says how far one keyframe's estimate can be trusted. The spread is *not*
//! divided by √n: a network's scale error is shared by the whole image (CNN-SLAM's
//! observation), so thousands of pixels do not make one image's scale thousands of times
//! surer. The pose graph takes the observation as a weak unary factor on the keyframe's scale
//! ([`crate::graph::ScalePrior`]).

use serde::Serialize;

use crate::image::ImageF32;

/// One keyframe's observed scale: `ln s` with the spread of the per-pixel votes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ScaleObservation {
    /// Median of `ln ρ_kf − ln ρ_prior` over the pixels where both are positive.
    pub log_scale: f64,
    /// 1.4826 × the median absolute deviation of the votes: a robust standard deviation of
    /// one pixel's vote.
    pub log_spread: f64,
    /// Pixels that voted.
    pub pixels: usize,
}

impl ScaleObservation {
    /// The scale `s` itself.
    pub fn scale(&self) -> f64 {
        self.log_scale.exp()
    }
}

/// The scale that maps `prior` (metric inverse depth) onto `keyframe` (inverse depth in the
/// keyframe's gauge), from every pixel where both are positive and finite; `None` when no pixel
/// votes or the two maps differ in size.
pub fn observe(keyframe: &ImageF32, prior: &ImageF32) -> Option<ScaleObservation> {
    if (keyframe.width, keyframe.height) != (prior.width, prior.height) {
        return None;
    }
    let mut votes: Vec<f64> = keyframe
        .data
        .iter()
        .zip(&prior.data)
        .filter(|(k, p)| k.is_finite() && p.is_finite() && **k > 0.0 && **p > 0.0)
        .map(|(&k, &p)| f64::from(k).ln() - f64::from(p).ln())
        .collect();
    let log_scale = median(&mut votes)?;
    let mut deviations: Vec<f64> = votes.iter().map(|v| (v - log_scale).abs()).collect();
    let mad = median(&mut deviations)?;
    Some(ScaleObservation {
        log_scale,
        log_spread: 1.4826 * mad,
        pixels: votes.len(),
    })
}

/// The median (the mean of the two middle values for an even count); reorders `values`.
pub(crate) fn median(values: &mut [f64]) -> Option<f64> {
    let n = values.len();
    if n == 0 {
        return None;
    }
    let (_, &mut upper, _) = values.select_nth_unstable_by(n / 2, f64::total_cmp);
    if n % 2 == 1 {
        return Some(upper);
    }
    let lower = values[..n / 2].iter().copied().fold(f64::MIN, f64::max);
    Some(0.5 * (lower + upper))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(data: Vec<f32>) -> ImageF32 {
        let w = data.len();
        ImageF32::from_vec(w, 1, data).expect("size")
    }

    #[test]
    fn metric_scale_is_the_median_ratio_and_ignores_outliers_and_holes() {
        // ρ_kf = 2.5·ρ_prior on most pixels, a few wild outliers, holes on either side.
        let prior: Vec<f32> = (0..200).map(|i| 0.2 + 0.01 * i as f32).collect();
        let mut kf: Vec<f32> = prior.iter().map(|p| 2.5 * p).collect();
        for i in (0..200).step_by(10) {
            kf[i] *= 40.0;
        }
        kf[3] = 0.0;
        let mut prior_img = prior.clone();
        prior_img[5] = f32::NAN;
        let obs = observe(&image(kf), &image(prior_img)).expect("votes");
        assert_eq!(obs.pixels, 198);
        assert!((obs.scale() - 2.5).abs() < 1e-4, "{obs:?}");
        assert!(
            obs.log_spread < 1e-4,
            "exact ratios have no spread: {obs:?}"
        );
    }

    #[test]
    fn metric_scale_spread_follows_the_vote_noise() {
        // Votes ln 2 ± 0.2 alternately: the MAD is 0.2, the robust σ 0.2·1.4826.
        let prior = vec![1.0f32; 100];
        let kf: Vec<f32> = (0..100)
            .map(|i| (2.0f64.ln() + if i % 2 == 0 { 0.2 } else { -0.2 }).exp() as f32)
            .collect();
        let obs = observe(&image(kf), &image(prior)).expect("votes");
        assert!((obs.log_scale - 2.0f64.ln()).abs() < 1e-6, "{obs:?}");
        assert!((obs.log_spread - 0.2 * 1.4826).abs() < 1e-5, "{obs:?}");
    }

    #[test]
    fn metric_scale_needs_votes_and_equal_sizes() {
        assert!(observe(&image(vec![0.0; 4]), &image(vec![1.0; 4])).is_none());
        assert!(observe(&image(vec![1.0; 4]), &image(vec![1.0; 5])).is_none());
    }
}
