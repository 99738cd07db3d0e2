//! Parameters of the semi-dense depth filter and of keyframe selection.
//!
//! Defaults are LSD-SLAM's (`util/settings.h`, `util/settings.cpp` of tum-vision/lsd_slam)
//! except the keyframe-selection weights, which DeepRelativeFusion (Loo et al., IROS 2021,
//! §IV "Implementation") raises to 7.5. Intensities are in 8-bit units (0..255) and inverse
//! depths in the keyframe's own (normalised) scale, as everywhere in the crate.

use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// Configuration of [`super::DepthFilter`] and of [`super::keyframe_score`] /
/// [`super::needs_new_keyframe`]. A config file only lists the fields it changes. Its user
/// settings are listed in [`crate::pipeline::user_config`]; the rest is expert level
/// (LSD-SLAM's constants).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MappingConfig {
    // ---- pixel selection -------------------------------------------------------------
    /// Minimal gradient (max of |∇I| over the 3×3 neighbourhood, 8-bit units) for a pixel to
    /// get or keep a hypothesis: LSD `minUseGrad` = 5 (`MIN_ABS_GRAD_CREATE`/`_DECREASE`). The
    /// paper sets 1 on low-texture sequences (ICL office0/living1, TUM seq2) to densify.
    pub min_use_grad: f32,
    /// Image noise variance σ_I² used by the photometric disparity error (ICCV 2013 eq. 6):
    /// LSD `cameraPixelNoise2` = 4².
    pub camera_pixel_noise2: f32,
    /// Geometric (pose/calibration) error of the epipolar line position, pixels: σ_l in ICCV
    /// 2013 eq. 5. LSD uses `0.25·(1 + tracking residual)`; this is the 0.25 base, the
    /// residual is passed to [`super::DepthFilter::observe_with_residual`].
    pub epipolar_line_noise: f32,

    // ---- stereo (epipolar line search) ------------------------------------------------
    /// Minimal squared image gradient along the epipolar line (full central differences):
    /// LSD `MIN_EPL_GRAD_SQUARED` = 2². Below it the search is ill-conditioned (eq. 6).
    pub min_epl_grad_squared: f32,
    /// Minimal squared length of the (unnormalised) epipolar direction: LSD
    /// `MIN_EPL_LENGTH_SQUARED` = 1. Tiny baselines give a degenerate line and are skipped.
    pub min_epl_length_squared: f32,
    /// Minimal squared cosine between gradient and epipolar line: LSD `MIN_EPL_ANGLE_SQUARED`
    /// = 0.3². Gradients orthogonal to the line make the geometric error explode (eq. 5).
    pub min_epl_angle_squared: f32,
    /// Maximal SSD of the 5 epipolar samples for a match: LSD `MAX_ERROR_STEREO` = 1300
    /// (4× this before sub-pixel refinement, plus `20·|∇I along line|` after it).
    pub max_error_stereo: f32,
    /// Second-best minimum must be this many times worse than the best (unless adjacent),
    /// otherwise the match is ambiguous: LSD `MIN_DISTANCE_ERROR_STEREO` = 1.5.
    pub min_distance_error_stereo: f32,
    /// Spacing of the 5 SSD samples and of the search steps along the line, pixels: LSD
    /// `GRADIENT_SAMPLE_DIST` = 1.
    pub gradient_sample_dist: f32,
    /// Search interval of an existing hypothesis, in standard deviations: LSD
    /// `STEREO_EPL_VAR_FAC` = 2 (ICCV 2013 §2.1.3: "d ± 2σ").
    pub stereo_epl_var_fac: f32,
    /// Minimal depth searched when creating a hypothesis (idepth range [0, 1/min_depth]):
    /// LSD `MIN_DEPTH` = 0.05.
    pub min_depth: f32,
    /// Longest searched epipolar segment, pixels: LSD `MAX_EPL_LENGTH_CROP` = 30.
    pub max_epl_length_crop: f32,
    /// Shorter segments are padded to this length, pixels: LSD `MIN_EPL_LENGTH_CROP` = 3.
    pub min_epl_length_crop: f32,
    /// Samples must stay this far from the image border, pixels: LSD
    /// `SAMPLE_POINT_TO_BORDER` = 7.
    pub sample_point_to_border: f32,
    /// Sub-pixel refinement of the SSD minimum (LSD `useSubpixelStereo` = true).
    pub use_subpixel_stereo: bool,
    /// Keep matches with negative inverse depth (beyond infinity through noise): LSD
    /// `allowNegativeIdepths` = true. Such estimates are never published.
    pub allow_negative_idepths: bool,
    /// Frames skipped by a hypothesis after an update from a short (< `min_epl_length_crop`)
    /// epipolar segment, tripled below half that length: LSD's `nextStereoFrameMinID` logic
    /// (inc ≥ 3). Consecutive small-baseline observations are strongly correlated; fusing
    /// them all would make the variance over-confident.
    pub short_epl_skip_frames: u64,

    // ---- validity counters and blacklisting --------------------------------------------
    /// Added to the validity counter on a successful update: LSD `VALIDITY_COUNTER_INC` = 5.
    pub validity_counter_inc: i32,
    /// Subtracted on a failed (ambiguous) search: LSD `VALIDITY_COUNTER_DEC` = 5.
    pub validity_counter_dec: i32,
    /// Validity of a hypothesis created by stereo: LSD `VALIDITY_COUNTER_INITIAL_OBSERVE` = 5.
    pub validity_counter_initial_observe: i32,
    /// Validity of a hypothesis created by [`super::DepthFilter::init_random`] or
    /// [`super::DepthFilter::init_from_depth`]: 20 in LSD's `initializeRandomly` /
    /// `initializeFromGTDepth`.
    pub validity_counter_init: i32,
    /// Fixed part of the validity cap: LSD `VALIDITY_COUNTER_MAX` = 5.
    pub validity_counter_max: f32,
    /// Gradient-dependent part of the cap, `max + |∇I|/255·this`: LSD
    /// `VALIDITY_COUNTER_MAX_VARIABLE` = 250.
    pub validity_counter_max_variable: f32,
    /// Summed 5×5 validity above which a hole is filled: LSD `VAL_SUM_MIN_FOR_CREATE` = 30.
    pub val_sum_min_for_create: i32,
    /// Summed 5×5 validity of agreeing neighbours below which a hypothesis is removed by
    /// regularisation: LSD `VAL_SUM_MIN_FOR_KEEP` = 24.
    pub val_sum_min_for_keep: i32,
    /// Summed 5×5 validity above which even a blacklisted hole is filled: LSD
    /// `VAL_SUM_MIN_FOR_UNBLACKLIST` = 100.
    pub val_sum_min_for_unblacklist: i32,
    /// A pixel whose blacklist counter (0, decremented on each failure) drops below this is
    /// ignored: LSD `MIN_BLACKLIST` = −1.
    pub min_blacklist: i32,

    // ---- variances -----------------------------------------------------------------------
    /// Variance inflation before each EKF update (prediction uncertainty): LSD
    /// `SUCC_VAR_INC_FAC` = 1.01.
    pub succ_var_inc_fac: f32,
    /// Variance inflation after a failed or inconsistent observation: LSD `FAIL_VAR_INC_FAC`
    /// = 1.1.
    pub fail_var_inc_fac: f32,
    /// Hypotheses whose variance exceeds this are removed (and new stereo results above it are
    /// not created): LSD `MAX_VAR` = 0.5².
    pub max_var: f32,
    /// Initial variance of [`super::DepthFilter::init_random`] and of filled holes: LSD
    /// `VAR_RANDOM_INIT_INITIAL` = 0.5·MAX_VAR.
    pub var_random_init_initial: f32,
    /// Initial variance of a ground-truth initialisation: LSD `VAR_GT_INIT_INITIAL` = 0.01².
    /// (Callers of [`super::DepthFilter::init_from_depth`] pass their own variance; this is
    /// the value to use for exact depth.)
    pub var_gt_init_initial: f32,
    /// Additive prediction variance σ_p² of keyframe propagation (ICCV 2013 eq. 8), in the
    /// old keyframe's normalised scale (mean inverse depth 1). Default 0.05 (σ ≈ 0.22 of the
    /// mean inverse depth). LSD's code adds none: a propagated estimate then hardly moves in
    /// the new keyframe, inherits the pose error it was propagated with, and the map's scale
    /// drifts; with σ_p² the new keyframe's own stereo re-estimates it (docs/tuning.md,
    /// "Propagation variance").
    pub propagation_var_inc: f32,

    // ---- regularisation and merging ----------------------------------------------------
    /// Assumed inverse-depth variance between neighbouring pixels per squared pixel distance:
    /// LSD `REG_DIST_VAR` = 0.075²·depthSmoothingFactor² (factor 1). Smaller = smoother.
    pub reg_dist_var: f32,
    /// Neighbours agree when `fac·Δ² ≤ σ₁² + σ₂²` (a 1σ test of the sum): LSD
    /// `DIFF_FAC_SMOOTHING` = 1.
    pub diff_fac_smoothing: f32,
    /// Same test between prior and observation (else the observation is inconsistent): LSD
    /// `DIFF_FAC_OBSERVE` = 1.
    pub diff_fac_observe: f32,
    /// Same test between hypotheses propagated onto the same pixel (else the farther one is
    /// occluded): LSD `DIFF_FAC_PROP_MERGE` = 1.
    pub diff_fac_prop_merge: f32,
    /// Propagation drops a hypothesis whose colour changes by more than
    /// `sqrt(max_diff_constant + max_diff_grad_mult·|∇I|²)`: LSD `MAX_DIFF_CONSTANT` = 40².
    pub max_diff_constant: f32,
    /// See `max_diff_constant`: LSD `MAX_DIFF_GRAD_MULT` = 0.5².
    pub max_diff_grad_mult: f32,

    // ---- keyframe selection (LSD SlamSystem::trackFrame) ------------------------------
    /// Weight of the scale-normalised distance in the keyframe score. LSD `KFDistWeight` = 4;
    /// DeepRelativeFusion uses 7.5 (denser keyframes for the dense layer).
    pub kf_dist_weight: f64,
    /// Weight of `1 − point usage` in the keyframe score. LSD `KFUsageWeight` = 3;
    /// DeepRelativeFusion uses 7.5.
    pub kf_usage_weight: f64,
    /// Keyframes during which the selection threshold ramps up from 0.2 to 1 (and is
    /// relaxed by 0.7): LSD `INITIALIZATION_PHASE_COUNT` = 5.
    pub initialization_phase_count: usize,
    /// A keyframe must have been mapped on more than this many frames before it can be
    /// replaced: LSD `MIN_NUM_MAPPED` = 5.
    pub min_num_mapped: usize,

    // ---- execution ---------------------------------------------------------------------
    /// Worker threads for observe/regularise (row bands); 0 = all available cores. Default 2
    /// (LSD's `MAPPING_THREADS` is 4; the reference machine has 2 cores).
    pub threads: usize,
}

impl Default for MappingConfig {
    fn default() -> Self {
        let max_var = 0.5 * 0.5;
        Self {
            min_use_grad: 5.0,
            camera_pixel_noise2: 4.0 * 4.0,
            epipolar_line_noise: 0.25,
            min_epl_grad_squared: 2.0 * 2.0,
            min_epl_length_squared: 1.0,
            min_epl_angle_squared: 0.3 * 0.3,
            max_error_stereo: 1300.0,
            min_distance_error_stereo: 1.5,
            gradient_sample_dist: 1.0,
            stereo_epl_var_fac: 2.0,
            min_depth: 0.05,
            max_epl_length_crop: 30.0,
            min_epl_length_crop: 3.0,
            sample_point_to_border: 7.0,
            use_subpixel_stereo: true,
            allow_negative_idepths: true,
            short_epl_skip_frames: 3,
            validity_counter_inc: 5,
            validity_counter_dec: 5,
            validity_counter_initial_observe: 5,
            validity_counter_init: 20,
            validity_counter_max: 5.0,
            validity_counter_max_variable: 250.0,
            val_sum_min_for_create: 30,
            val_sum_min_for_keep: 24,
            val_sum_min_for_unblacklist: 100,
            min_blacklist: -1,
            succ_var_inc_fac: 1.01,
            fail_var_inc_fac: 1.1,
            max_var,
            var_random_init_initial: 0.5 * max_var,
            var_gt_init_initial: 0.01 * 0.01,
            propagation_var_inc: 0.05,
            reg_dist_var: 0.075 * 0.075,
            diff_fac_smoothing: 1.0,
            diff_fac_observe: 1.0,
            diff_fac_prop_merge: 1.0,
            max_diff_constant: 40.0 * 40.0,
            max_diff_grad_mult: 0.5 * 0.5,
            kf_dist_weight: 7.5,
            kf_usage_weight: 7.5,
            initialization_phase_count: 5,
            min_num_mapped: 5,
            threads: 2,
        }
    }
}

impl MappingConfig {
    /// Rejects values that would make the filter meaningless (non-positive variances,
    /// sample spacing or crop lengths, inverted crop range).
    pub fn validate(&self) -> Result<()> {
        let positive = [
            ("camera_pixel_noise2", self.camera_pixel_noise2),
            ("gradient_sample_dist", self.gradient_sample_dist),
            ("min_depth", self.min_depth),
            ("max_epl_length_crop", self.max_epl_length_crop),
            ("min_epl_length_crop", self.min_epl_length_crop),
            ("max_var", self.max_var),
            ("var_random_init_initial", self.var_random_init_initial),
            ("var_gt_init_initial", self.var_gt_init_initial),
            ("reg_dist_var", self.reg_dist_var),
            ("succ_var_inc_fac", self.succ_var_inc_fac),
            ("fail_var_inc_fac", self.fail_var_inc_fac),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::Config(format!(
                    "mapping: {name} must be positive, got {v}"
                )));
            }
        }
        if self.min_epl_length_crop > self.max_epl_length_crop {
            return Err(Error::Config(
                "mapping: min_epl_length_crop exceeds max_epl_length_crop".into(),
            ));
        }
        if !(self.kf_dist_weight.is_finite() && self.kf_usage_weight.is_finite()) {
            return Err(Error::Config(
                "mapping: keyframe weights must be finite".into(),
            ));
        }
        if self.initialization_phase_count == 0 {
            return Err(Error::Config(
                "mapping: initialization_phase_count must be ≥ 1".into(),
            ));
        }
        Ok(())
    }

    /// Number of worker threads actually used (`threads`, or all cores when 0).
    pub(crate) fn worker_threads(&self) -> usize {
        if self.threads > 0 {
            self.threads
        } else {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        }
    }
}
