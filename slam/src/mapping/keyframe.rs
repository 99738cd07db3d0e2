//! Keyframe selection (Engel et al., ECCV 2014 §3.3; LSD-SLAM `SlamSystem::trackFrame` and
//! `TrackableKeyFrameSearch::getRefFrameScore`).
//!
//! A new keyframe is taken when the camera has moved far relative to the scene depth, or when
//! the tracked frame uses few of the keyframe's points:
//! `score = |t·ρ̄|²·w_dist² + (1 − usage)²·w_usage²`, with `t` the translation of
//! `keyframe_from_frame` and `ρ̄` the keyframe's mean inverse depth (so the distance is
//! relative to the scene's scale, ECCV 2014 eq. 16).

use super::MappingConfig;
use crate::geometry::SE3;

/// The closeness score of a tracked frame relative to its keyframe. `mean_idepth` is the
/// keyframe's mean inverse depth (1 after scale normalisation), `point_usage` the fraction of
/// keyframe points tracking used in the frame (in [0, 1]).
pub fn keyframe_score(
    config: &MappingConfig,
    keyframe_from_frame: &SE3,
    mean_idepth: f64,
    point_usage: f32,
) -> f64 {
    let dist = keyframe_from_frame.translation * mean_idepth;
    let unused = 1.0 - f64::from(point_usage);
    dist.norm_squared() * config.kf_dist_weight.powi(2)
        + unused * unused * config.kf_usage_weight.powi(2)
}

/// The threshold the score must exceed with `num_keyframes` keyframes so far: it ramps from
/// 0.2 to 1 over the first `initialization_phase_count` keyframes and is relaxed by 0.7 during
/// that phase, so the map is initialised with more keyframes.
pub fn keyframe_threshold(config: &MappingConfig, num_keyframes: usize) -> f64 {
    let phase = config.initialization_phase_count.max(1);
    let ramp = (0.2 + num_keyframes as f64 * 0.8 / phase as f64).min(1.0);
    if num_keyframes < phase {
        ramp * 0.7
    } else {
        ramp
    }
}

/// Whether the tracked frame should become a new keyframe: the current keyframe must have been
/// mapped on more than `min_num_mapped` frames (so its depth had time to converge) and the
/// score must exceed [`keyframe_threshold`].
pub fn needs_new_keyframe(
    config: &MappingConfig,
    keyframe_from_frame: &SE3,
    mean_idepth: f64,
    point_usage: f32,
    num_keyframes: usize,
    num_mapped_on_keyframe: usize,
) -> bool {
    num_mapped_on_keyframe > config.min_num_mapped
        && keyframe_score(config, keyframe_from_frame, mean_idepth, point_usage)
            > keyframe_threshold(config, num_keyframes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::SO3;
    use nalgebra::Vector3;

    fn translated(x: f64) -> SE3 {
        SE3::new(
            SO3::exp(&Vector3::new(0.0, 0.1, 0.0)),
            Vector3::new(x, 0.0, 0.0),
        )
    }

    #[test]
    fn mapping_keyframe_score_follows_the_lsd_formula() {
        let cfg = MappingConfig::default();
        assert_eq!(keyframe_score(&cfg, &SE3::identity(), 1.0, 1.0), 0.0);
        // Scale invariance: moving twice as far in a scene twice as deep scores the same.
        let a = keyframe_score(&cfg, &translated(0.1), 1.0, 0.8);
        let b = keyframe_score(&cfg, &translated(0.2), 0.5, 0.8);
        assert!((a - b).abs() < 1e-12);
        let expected = 0.1f64.powi(2) * 7.5f64.powi(2) + 0.2f64.powi(2) * 7.5f64.powi(2);
        assert!((a - expected).abs() < 1e-6, "{a} vs {expected}");
        // Rotation alone does not count.
        let rot = SE3::new(SO3::exp(&Vector3::new(0.3, 0.0, 0.0)), Vector3::zeros());
        assert_eq!(keyframe_score(&cfg, &rot, 1.0, 1.0), 0.0);
    }

    #[test]
    fn mapping_keyframe_threshold_ramps_during_initialisation() {
        let cfg = MappingConfig::default();
        assert!((keyframe_threshold(&cfg, 0) - 0.14).abs() < 1e-12);
        assert!((keyframe_threshold(&cfg, 4) - 0.84 * 0.7).abs() < 1e-12);
        assert_eq!(keyframe_threshold(&cfg, 5), 1.0);
        assert_eq!(keyframe_threshold(&cfg, 50), 1.0);
    }

    #[test]
    fn mapping_keyframe_selection_triggers_after_enough_motion_only() {
        let cfg = MappingConfig::default();
        let n_kf = 10;
        // Full usage: threshold 1 ⇒ |t|·7.5 > 1 ⇔ |t| > 0.1333 at mean idepth 1.
        let mut first_trigger = None;
        for i in 0..100 {
            let x = i as f64 * 0.005;
            let fire = needs_new_keyframe(&cfg, &translated(x), 1.0, 1.0, n_kf, 20);
            if fire && first_trigger.is_none() {
                first_trigger = Some(x);
            }
            if first_trigger.is_some() {
                assert!(
                    fire,
                    "selection must stay on once the distance exceeds the threshold"
                );
            }
        }
        let x = first_trigger.expect("some motion triggers a keyframe");
        assert!((x - 0.135).abs() < 1e-9, "first trigger at {x}");
        // Lost overlap alone triggers; but not before the keyframe was mapped enough.
        assert!(needs_new_keyframe(
            &cfg,
            &SE3::identity(),
            1.0,
            0.8,
            n_kf,
            20
        ));
        assert!(!needs_new_keyframe(
            &cfg,
            &SE3::identity(),
            1.0,
            0.9,
            n_kf,
            20
        ));
        assert!(!needs_new_keyframe(
            &cfg,
            &translated(1.0),
            1.0,
            0.0,
            n_kf,
            cfg.min_num_mapped
        ));
        // LSD's own weights need more motion than the paper's.
        let lsd = MappingConfig {
            kf_dist_weight: 4.0,
            kf_usage_weight: 3.0,
            ..cfg.clone()
        };
        assert!(needs_new_keyframe(
            &cfg,
            &translated(0.2),
            1.0,
            1.0,
            n_kf,
            20
        ));
        assert!(!needs_new_keyframe(
            &lsd,
            &translated(0.2),
            1.0,
            1.0,
            n_kf,
            20
        ));
    }
}
