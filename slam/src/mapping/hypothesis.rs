//! Per-pixel state of the depth filter (LSD-SLAM `DepthMapPixelHypothesis`).

/// A Gaussian inverse-depth hypothesis with its regularised twin and bookkeeping.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Estimate {
    /// Raw filtered inverse depth (what observations are fused into).
    pub idepth: f32,
    /// Variance of `idepth`.
    pub var: f32,
    /// Regularised inverse depth (what is searched around and published).
    pub idepth_smoothed: f32,
    /// Variance of `idepth_smoothed`.
    pub var_smoothed: f32,
    /// How many successful observations support it (ICCV 2013 §2.3: outlier handling).
    pub validity: i32,
    /// Frames with a smaller id are not used for stereo on this pixel (LSD
    /// `nextStereoFrameMinID`): decorrelates repeated short-baseline observations.
    pub next_stereo_frame: u64,
}

impl Estimate {
    /// A new hypothesis; the smoothed values start equal to the raw ones (LSD leaves them
    /// unset until the next regularisation, which always follows creation).
    pub fn new(idepth: f32, var: f32, validity: i32) -> Self {
        Self {
            idepth,
            var,
            idepth_smoothed: idepth,
            var_smoothed: var,
            validity,
            next_stereo_frame: 0,
        }
    }
}

/// One keyframe pixel: an optional hypothesis and the blacklist counter, which survives the
/// hypothesis (a pixel where stereo keeps failing is eventually ignored).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct Pixel {
    /// Starts at 0, decremented on each failure; ignored when below `min_blacklist`.
    pub blacklist: i32,
    pub estimate: Option<Estimate>,
}

impl Pixel {
    /// Installs a new hypothesis; like LSD's constructor this clears the blacklist.
    pub fn set(&mut self, estimate: Estimate) {
        self.blacklist = 0;
        self.estimate = Some(estimate);
    }
}

/// LSD `UNZERO`: keeps an inverse depth away from exactly 0 (divisions follow).
#[inline]
pub(crate) fn unzero(v: f32) -> f32 {
    const EPS: f32 = 1e-10;
    if v < 0.0 { v.min(-EPS) } else { v.max(EPS) }
}
