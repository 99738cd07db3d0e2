//! Localisation in a saved map without changing it (RTAB-Map's localisation mode, ORB-SLAM's
//! "localization only"): every frame gets a pose in the map's frame, or is reported not
//! localised.
//!
//! - **Tracking in the map.** Once localised, a frame is tracked (LSD-SLAM's SE(3) direct
//!   alignment, constant-velocity guess) against the map keyframe nearest to the last pose —
//!   nearest in units of that keyframe's scene depth and viewing angle — falling back to the
//!   keyframe of the last frame. The map's keyframes are never modified.
//! - **Place recognition.** A frame with no usable last pose is compared with every keyframe by
//!   its appearance descriptor ([`Thumbnail`]); the best [`LocalizeConfig::candidates`] are
//!   aligned from the identity and the good alignment with the highest point usage × good
//!   ratio is kept. LSD-SLAM's relocaliser also asks that score to exceed 0.7; correct
//!   relocalisations in another recording score 0.55-0.65, so the second keyframe's
//!   confirmation below takes that test's place (docs/tuning.md, "Localisation in a saved map").
//! - **Verification.** A relocalised pose must be confirmed by a second map keyframe: the
//!   frame, aligned to the nearest other keyframe from that pose, must land at the same place
//!   (within [`LocalizeConfig::verify_distance`] of the scene depth and
//!   [`LocalizeConfig::verify_angle_deg`]). A single alignment can fall into a wrong minimum
//!   on a similar-looking view; two keyframes from different viewpoints rarely agree on it, so
//!   frames outside the map are reported as not localised rather than given a wrong pose.

use super::{MapKeyframe, SavedMap};
use crate::frame::Frame;
use crate::geometry::{PinholeCamera, SE3, Sim3, UndistortMap};
use crate::graph::resident::Resident;
use crate::graph::{KeyframeId, Thumbnail};
use crate::tracking::{SE3Tracker, TrackingConfig, TrackingReference, TrackingResult};
use crate::{Error, Result};

/// Tracking references a [`Localizer`] keeps beyond its place-recognition candidates: the
/// keyframes tracking and verification use next to them.
const RESIDENT_BEYOND_CANDIDATES: usize = 4;

/// A map keyframe's tracking reference, from its compact image and depth.
fn reference_of(kf: &MapKeyframe) -> Result<TrackingReference> {
    TrackingReference::new(&kf.image.rebuild()?, &kf.depth.expand())
}

/// Settings of [`Localizer`].
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LocalizeConfig {
    /// Keyframes aligned per place-recognition attempt, best appearance scores first. Default 4:
    /// LSD-SLAM's relocaliser tries a handful of keyframes per frame.
    pub candidates: usize,
    /// A relocalised pose is confirmed when the second keyframe puts the camera within this
    /// distance, in units of the scene's mean depth. Default 0.05: a twentieth of the depth,
    /// well inside the basin of a correct alignment, far below the jump of a wrong minimum.
    pub verify_distance: f64,
    /// … and within this rotation (degrees). Default 3.
    pub verify_angle_deg: f64,
    /// Keyframes farther than this (scene depths, plus one per radian of viewing angle) from
    /// the relocalised pose are not used to confirm it. Default 1.
    pub verify_reach: f64,
    /// A frame farther than this from the keyframe it was aligned to ([`Localization::reach`]:
    /// distance in scene depths and the share of the keyframe's points it does not see, LSD-SLAM's
    /// keyframe distance) is outside the map: its pose would be an extrapolation whose error
    /// grows with the reach, so it is reported not localised. Default 0.45: about twice the
    /// reach within which LSD-SLAM keeps a keyframe ((1/7.5)·√2, docs/tuning.md "Localisation").
    pub max_reach: f64,
    /// A relocalised pose has no history to support it, so it must lie well inside the map:
    /// reach at most this (hysteresis below `max_reach`). Default 0.3.
    pub relocalize_reach: f64,
}

impl Default for LocalizeConfig {
    fn default() -> Self {
        Self {
            candidates: 4,
            verify_distance: 0.05,
            verify_angle_deg: 3.0,
            verify_reach: 1.0,
            max_reach: 0.45,
            relocalize_reach: 0.3,
        }
    }
}

impl LocalizeConfig {
    /// Rejects values that make no sense.
    pub fn validate(&self) -> Result<()> {
        let ok = self.candidates >= 1
            && self.verify_distance > 0.0
            && self.verify_angle_deg > 0.0
            && self.verify_reach > 0.0
            && self.max_reach > 0.0
            && self.relocalize_reach > 0.0
            && [
                self.verify_distance,
                self.verify_angle_deg,
                self.verify_reach,
                self.max_reach,
                self.relocalize_reach,
            ]
            .iter()
            .all(|v| v.is_finite());
        if ok {
            Ok(())
        } else {
            Err(Error::Config(format!("invalid localize config {self:?}")))
        }
    }
}

/// How a frame was placed in the map.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LocalizationState {
    /// Tracked from the last localised frame.
    Tracked,
    /// Found by place recognition and confirmed by a second keyframe.
    Relocalized,
    /// No trustworthy pose: outside the map, or not recognised.
    NotLocalized,
}

/// The outcome for one frame.
#[derive(Clone, Copy, Debug)]
pub struct Localization {
    pub timestamp: f64,
    pub state: LocalizationState,
    /// The camera's pose in the map's frame (`None` when not localised).
    pub world_from_camera: Option<Sim3>,
    /// The keyframe it was aligned to.
    pub keyframe: Option<KeyframeId>,
    /// Point usage × good ratio of that alignment (LSD-SLAM's relocalisation score).
    pub score: f32,
    /// How far the frame is from that keyframe ([`LocalizeConfig::max_reach`]); infinite
    /// when no alignment succeeded.
    pub reach: f64,
}

/// A map keyframe ready for alignment (its tracking reference in [`Localizer::references`]).
struct Anchor {
    keyframe: MapKeyframe,
    /// Mean inverse depth of its semi-dense map (distances in units of the scene depth).
    mean_idepth: f64,
}

/// The last localised frame.
#[derive(Clone, Copy)]
struct LastPose {
    keyframe: KeyframeId,
    frame_from_keyframe: SE3,
    /// `this_from_previous` between the last two localised frames, when both used `keyframe`.
    velocity: Option<SE3>,
}

/// Localises frames of the map's camera in a loaded map, one at a time.
pub struct Localizer {
    config: LocalizeConfig,
    camera: PinholeCamera,
    undistort: Option<UndistortMap>,
    anchors: Vec<Anchor>,
    /// The most recently used keyframes' tracking references (issue 37: a map of hundreds of
    /// keyframes holds its images and depth compact); others are rebuilt when aligned to.
    references: Resident<TrackingReference>,
    /// Points the map's keyframes offer tracking at full resolution, in all.
    tracking_points: usize,
    tracker: SE3Tracker,
    last: Option<LastPose>,
    next_frame_id: u64,
}

impl std::fmt::Debug for Localizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Localizer")
            .field("keyframes", &self.anchors.len())
            .field("config", &self.config)
            .finish()
    }
}

impl Localizer {
    /// A localiser over `map` (which must have at least one keyframe); `tracking`'s thresholds
    /// decide what a good alignment is.
    pub fn new(map: &SavedMap, tracking: TrackingConfig, config: LocalizeConfig) -> Result<Self> {
        config.validate()?;
        // Every reference is built once (it checks the keyframe and counts its points); the
        // last ones built stay resident.
        let mut references = Resident::new(config.candidates + RESIDENT_BEYOND_CANDIDATES);
        let mut tracking_points = 0;
        let anchors = map
            .keyframes
            .iter()
            .map(|kf| {
                let reference = references.insert_as(kf.id, reference_of(kf)?);
                tracking_points += reference.num_points(0);
                Ok(Anchor {
                    mean_idepth: kf.depth.mean_idepth().unwrap_or(1.0),
                    keyframe: kf.clone(),
                })
            })
            .collect::<Result<Vec<_>>>()?;
        if anchors.is_empty() {
            return Err(Error::Map("the map has no keyframes".into()));
        }
        let undistort = map
            .camera
            .distortion
            .is_some()
            .then(|| UndistortMap::new(&map.camera));
        Ok(Self {
            tracker: SE3Tracker::new(tracking)?,
            config,
            camera: map.camera,
            undistort,
            anchors,
            references,
            tracking_points,
            last: None,
            // Frame ids above the keyframes' so that none is mistaken for a keyframe.
            next_frame_id: 1 << 32,
        })
    }

    /// Points the map's keyframes offer tracking at full resolution, in all.
    pub fn tracking_points(&self) -> usize {
        self.tracking_points
    }

    /// Localises one frame (distorted as the camera delivers it).
    pub fn localize(&mut self, timestamp: f64, rgb: ::image::RgbImage) -> Result<Localization> {
        let frame = self.make_frame(timestamp, rgb)?;
        if let Some(last) = self.last {
            if let Some((kf, result)) = self.track_from(&frame, last) {
                self.remember(kf, &result);
                return Ok(self.outcome(timestamp, LocalizationState::Tracked, kf, &result));
            }
            self.last = None;
        }
        match self.relocalise(&frame) {
            Some((kf, result)) => {
                self.remember(kf, &result);
                Ok(self.outcome(timestamp, LocalizationState::Relocalized, kf, &result))
            }
            None => Ok(Localization {
                timestamp,
                state: LocalizationState::NotLocalized,
                world_from_camera: None,
                keyframe: None,
                score: 0.0,
                reach: f64::INFINITY,
            }),
        }
    }

    /// Keeps the alignment as the next frame's starting point — also beyond
    /// [`LocalizeConfig::max_reach`], so that tracking picks the camera up again as soon as it
    /// comes back into the map.
    fn remember(&mut self, kf: KeyframeId, result: &TrackingResult) {
        let velocity = self
            .last
            .filter(|l| l.keyframe == kf)
            .map(|l| result.frame_from_keyframe * l.frame_from_keyframe.inverse());
        self.last = Some(LastPose {
            keyframe: kf,
            frame_from_keyframe: result.frame_from_keyframe,
            velocity,
        });
    }

    /// The report of an alignment: a pose only within the map's reach (beyond it the pose
    /// would be an extrapolation whose error grows with the reach).
    fn outcome(
        &self,
        timestamp: f64,
        state: LocalizationState,
        kf: KeyframeId,
        result: &TrackingResult,
    ) -> Localization {
        let reach = self.reach(kf, result);
        let inside = reach <= self.config.max_reach;
        Localization {
            timestamp,
            state: if inside {
                state
            } else {
                LocalizationState::NotLocalized
            },
            world_from_camera: inside.then(|| self.world_pose(kf, &result.frame_from_keyframe)),
            keyframe: Some(kf),
            score: result.point_usage * result.good_ratio,
            reach,
        }
    }

    fn make_frame(&mut self, timestamp: f64, rgb: ::image::RgbImage) -> Result<Frame> {
        let id = self.next_frame_id;
        self.next_frame_id += 1;
        Frame::from_camera_rgb(id, timestamp, &self.camera, self.undistort.as_ref(), rgb)
    }

    /// LSD-SLAM's keyframe distance (ECCV 2014 eq. 16) without its weights:
    /// `sqrt(d² + (1 − u)²)`, `d` the distance to keyframe `kf` in units of its scene depth, `u`
    /// the share of the keyframe's points the frame sees.
    fn reach(&self, kf: KeyframeId, result: &TrackingResult) -> f64 {
        let d =
            result.frame_from_keyframe.inverse().translation.norm() * self.anchors[kf].mean_idepth;
        let unused = 1.0 - f64::from(result.point_usage);
        (d * d + unused * unused).sqrt()
    }

    /// The camera's map pose from an alignment to keyframe `kf`.
    fn world_pose(&self, kf: KeyframeId, frame_from_keyframe: &SE3) -> Sim3 {
        self.anchors[kf].keyframe.world_from_keyframe
            * Sim3::from_se3(&frame_from_keyframe.inverse(), 1.0)
    }

    /// The frame's pose relative to keyframe `kf` (in its units) for a map pose.
    fn relative_to(&self, kf: KeyframeId, world_from_camera: &Sim3) -> SE3 {
        let kf_from_camera =
            self.anchors[kf].keyframe.world_from_keyframe.inverse() * *world_from_camera;
        SE3::new(kf_from_camera.rotation, kf_from_camera.translation).inverse()
    }

    /// Distance of keyframe `kf` from a map pose: camera distance in units of the keyframe's
    /// scene depth plus the angle between the optical axes in radians.
    fn distance(&self, kf: KeyframeId, world_from_camera: &Sim3) -> f64 {
        let anchor = &self.anchors[kf];
        let kf_from_camera = anchor.keyframe.world_from_keyframe.inverse() * *world_from_camera;
        let axis = kf_from_camera.rotation.matrix().column(2).into_owned();
        kf_from_camera.translation.norm() * anchor.mean_idepth + axis.z.clamp(-1.0, 1.0).acos()
    }

    /// The keyframe nearest to a map pose, other than `except`.
    fn nearest(
        &self,
        world_from_camera: &Sim3,
        except: Option<KeyframeId>,
    ) -> Option<(KeyframeId, f64)> {
        (0..self.anchors.len())
            .filter(|&k| Some(k) != except)
            .map(|k| (k, self.distance(k, world_from_camera)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
    }

    /// Tracks against keyframe `kf` from `guess`, constant-velocity guess first when given.
    fn track(
        &mut self,
        kf: KeyframeId,
        frame: &Frame,
        guess: &SE3,
        velocity: Option<SE3>,
    ) -> Option<TrackingResult> {
        let keyframe = &self.anchors[kf].keyframe;
        let reference = match self.references.get_or_build(kf, || reference_of(keyframe)) {
            Ok(reference) => reference,
            Err(e) => {
                tracing::warn!(keyframe = kf, "map keyframe not rebuilt: {e}");
                return None;
            }
        };
        if let Some(v) = velocity {
            let result = self.tracker.track(&reference, frame, &(v * *guess));
            if result.good {
                return Some(result);
            }
        }
        let result = self.tracker.track(&reference, frame, guess);
        result.good.then_some(result)
    }

    /// Tracking from the last localised frame: against the keyframe nearest to its pose, then
    /// against the keyframe it was aligned to.
    fn track_from(
        &mut self,
        frame: &Frame,
        last: LastPose,
    ) -> Option<(KeyframeId, TrackingResult)> {
        let last_world = self.world_pose(last.keyframe, &last.frame_from_keyframe);
        let nearest = self.nearest(&last_world, None).map(|(k, _)| k);
        if let Some(k) = nearest.filter(|&k| k != last.keyframe) {
            let guess = self.relative_to(k, &last_world);
            if let Some(result) = self.track(k, frame, &guess, None) {
                return Some((k, result));
            }
        }
        self.track(
            last.keyframe,
            frame,
            &last.frame_from_keyframe,
            last.velocity,
        )
        .map(|r| (last.keyframe, r))
    }

    /// Place recognition, alignment and verification by a second keyframe: the map keyframe
    /// and the frame's alignment to it (also how an extended map finds its camera,
    /// `pipeline::extend`).
    pub(crate) fn relocalise(&mut self, frame: &Frame) -> Option<(KeyframeId, TrackingResult)> {
        let thumbnail = Thumbnail::new(frame);
        let mut ranked: Vec<(KeyframeId, f64)> = self
            .anchors
            .iter()
            .enumerate()
            .map(|(k, a)| (k, a.keyframe.thumbnail.score(&thumbnail)))
            .collect();
        ranked.sort_by(|a, b| b.1.total_cmp(&a.1));
        let mut best: Option<(KeyframeId, TrackingResult, f32)> = None;
        for &(k, _) in ranked.iter().take(self.config.candidates) {
            let Some(result) = self.track(k, frame, &SE3::identity(), None) else {
                continue;
            };
            let score = result.point_usage * result.good_ratio;
            if best.as_ref().is_none_or(|b| score > b.2) {
                best = Some((k, result, score));
            }
        }
        let (k, result, _) = best?;
        (self.reach(k, &result) <= self.config.relocalize_reach && self.verified(frame, k, &result))
            .then_some((k, result))
    }

    /// Whether the nearest other keyframe confirms the pose found against `kf`.
    fn verified(&mut self, frame: &Frame, kf: KeyframeId, result: &TrackingResult) -> bool {
        let world = self.world_pose(kf, &result.frame_from_keyframe);
        let Some((other, distance)) = self.nearest(&world, Some(kf)) else {
            return false;
        };
        if distance > self.config.verify_reach {
            return false;
        }
        let guess = self.relative_to(other, &world);
        let Some(check) = self.track(other, frame, &guess, None) else {
            return false;
        };
        let confirmed = self.world_pose(other, &check.frame_from_keyframe);
        let delta = world.inverse() * confirmed;
        // `world`'s scale is keyframe kf's, so delta's translation is in kf's units.
        let moved = delta.translation.norm() * self.anchors[kf].mean_idepth;
        moved < self.config.verify_distance
            && delta.rotation.angle().to_degrees() < self.config.verify_angle_deg
    }
}
