//! The dense points last given for each keyframe, kept so that a keyframe the pose graph
//! rescales can be sent again (a point cloud hangs in its keyframe's frame, and a frame
//! transform carries no scale).
//!
//! Held in memory they were the largest part of a long session's growth: up to
//! [`POINTS_PER_KEYFRAME`](crate::session_log::POINTS_PER_KEYFRAME) points, 60-110 kB a
//! keyframe, for every keyframe of the session (heaptrack on `relfusion bench long`; issue 37).
//! So they go to an anonymous temporary file (unlinked at creation: nothing is left behind,
//! whatever ends the process) and memory keeps where each keyframe's points are, a few bytes.
//! A rescale reads them back, bit-identical. Without a temporary file the points stay in
//! memory, as before.
//!
//! [`KeyframeViews`] is what the logs keep of each keyframe (`foxglove_log`, `ros2::log`): its
//! newest pose, the scale its points were last sent at, and the points here.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};

use crate::session_log::{LogError, Pose, RESCALE_TOLERANCE};

/// Where one keyframe's newest points lie in the file.
#[derive(Clone, Copy, Debug)]
struct Slot {
    offset: u64,
    points: u32,
}

#[derive(Debug)]
enum Backing {
    /// `end` is where the next points are written.
    File {
        file: File,
        end: u64,
    },
    Memory(BTreeMap<u64, Vec<[f32; 3]>>),
}

/// Every keyframe's newest points, by keyframe id.
#[derive(Debug)]
pub struct KeyframeClouds {
    backing: Backing,
    slots: BTreeMap<u64, Slot>,
}

impl Default for KeyframeClouds {
    fn default() -> Self {
        Self::new()
    }
}

fn io_error(e: std::io::Error) -> LogError {
    LogError::Write {
        what: "keyframe points",
        message: e.to_string(),
    }
}

impl KeyframeClouds {
    /// In a temporary file, or in memory when none can be made (logged).
    pub fn new() -> Self {
        match tempfile::tempfile() {
            Ok(file) => Self::in_file(file),
            Err(e) => {
                tracing::warn!("keyframe points kept in memory (no temporary file: {e})");
                Self::in_memory()
            }
        }
    }

    /// In memory.
    pub fn in_memory() -> Self {
        Self {
            backing: Backing::Memory(BTreeMap::new()),
            slots: BTreeMap::new(),
        }
    }

    /// In `file` (read and written from its start).
    pub fn in_file(file: File) -> Self {
        Self {
            backing: Backing::File { file, end: 0 },
            slots: BTreeMap::new(),
        }
    }

    /// Replaces keyframe `id`'s points. A keyframe's older points are not reclaimed in the
    /// file: it grows with the depth maps given, as the log itself does.
    pub fn put(&mut self, id: u64, points: Vec<[f32; 3]>) -> Result<(), LogError> {
        match &mut self.backing {
            Backing::Memory(map) => {
                self.slots.insert(
                    id,
                    Slot {
                        offset: 0,
                        points: points.len() as u32,
                    },
                );
                map.insert(id, points);
            }
            Backing::File { file, end } => {
                let bytes: Vec<u8> = points
                    .iter()
                    .flat_map(|p| p.iter().flat_map(|v| v.to_le_bytes()))
                    .collect();
                file.seek(SeekFrom::Start(*end)).map_err(io_error)?;
                file.write_all(&bytes).map_err(io_error)?;
                self.slots.insert(
                    id,
                    Slot {
                        offset: *end,
                        points: points.len() as u32,
                    },
                );
                *end += bytes.len() as u64;
            }
        }
        Ok(())
    }

    /// Keyframe `id`'s newest points; empty when none were given.
    pub fn get(&mut self, id: u64) -> Result<Vec<[f32; 3]>, LogError> {
        let Some(slot) = self.slots.get(&id).copied() else {
            return Ok(Vec::new());
        };
        match &mut self.backing {
            Backing::Memory(map) => Ok(map.get(&id).cloned().unwrap_or_default()),
            Backing::File { file, .. } => {
                let mut bytes = vec![0u8; slot.points as usize * 12];
                file.seek(SeekFrom::Start(slot.offset)).map_err(io_error)?;
                file.read_exact(&mut bytes).map_err(io_error)?;
                Ok(bytes
                    .chunks_exact(12)
                    .map(|c| {
                        let v = |i: usize| f32::from_le_bytes([c[i], c[i + 1], c[i + 2], c[i + 3]]);
                        [v(0), v(4), v(8)]
                    })
                    .collect())
            }
        }
    }

    /// Whether keyframe `id` has points.
    pub fn has_points(&self, id: u64) -> bool {
        self.slots.get(&id).is_some_and(|s| s.points > 0)
    }
}

/// A keyframe's newest pose and the scale its points were last sent at.
#[derive(Clone, Copy, Debug)]
struct View {
    pose: Pose,
    sent_scale: f64,
}

/// What a log keeps of each keyframe: its newest pose (for the path) and its newest points,
/// to send them again, scaled, when the pose graph rescales it (a point cloud hangs in its
/// keyframe's frame, and a frame transform carries no scale).
#[derive(Debug, Default)]
pub struct KeyframeViews {
    views: BTreeMap<u64, View>,
    clouds: KeyframeClouds,
}

impl KeyframeViews {
    pub fn new() -> Self {
        Self::default()
    }

    /// Records keyframe `id`'s newest pose; true when its points were sent at a scale that
    /// this pose's differs from by more than [`RESCALE_TOLERANCE`] (send them again). A new
    /// keyframe's points have not been sent: false.
    pub fn set_pose(&mut self, id: u64, pose: &Pose) -> bool {
        let view = self.views.entry(id).or_insert(View {
            pose: *pose,
            sent_scale: pose.s,
        });
        view.pose = *pose;
        (pose.s / view.sent_scale - 1.0).abs() > RESCALE_TOLERANCE
    }

    /// Replaces keyframe `id`'s points (in its frame, unscaled). Points before the keyframe's
    /// pose (never from our callers) hang at the origin.
    pub fn set_points(&mut self, id: u64, points: Vec<[f32; 3]>) -> Result<(), LogError> {
        self.views.entry(id).or_insert(View {
            pose: Pose::IDENTITY,
            sent_scale: 1.0,
        });
        self.clouds.put(id, points)
    }

    /// Keyframe `id`'s points scaled by its newest pose's scale, to be sent now (they count
    /// as sent at that scale); `None` when it has none.
    pub fn points_to_send(&mut self, id: u64) -> Result<Option<Vec<[f32; 3]>>, LogError> {
        if !self.clouds.has_points(id) {
            return Ok(None);
        }
        let Some(view) = self.views.get_mut(&id) else {
            return Ok(None);
        };
        view.sent_scale = view.pose.s;
        let s = view.pose.s as f32;
        let mut points = self.clouds.get(id)?;
        for p in &mut points {
            *p = p.map(|v| v * s);
        }
        Ok(Some(points))
    }

    /// Every keyframe's newest pose, by id.
    pub fn poses(&self) -> impl Iterator<Item = &Pose> {
        self.views.values().map(|v| &v.pose)
    }

    /// How many keyframes.
    pub fn len(&self) -> usize {
        self.views.len()
    }

    pub fn is_empty(&self) -> bool {
        self.views.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(seed: u32, n: usize) -> Vec<[f32; 3]> {
        (0..n)
            .map(|i| {
                let x = (i as u32).wrapping_mul(2654435761).wrapping_add(seed) as f32;
                [x * 1e-9, -x * 3e-10, 1.0 + (i as f32) * 0.25]
            })
            .collect()
    }

    #[test]
    fn points_read_back_from_the_file_are_the_points_given() {
        let file = tempfile::tempfile().expect("temporary file");
        let mut clouds = KeyframeClouds::in_file(file);
        let mut memory = KeyframeClouds::in_memory();
        assert!(!clouds.has_points(3));
        assert!(clouds.get(3).expect("get").is_empty());
        for (id, n) in [(3u64, 5000usize), (7, 12), (3, 40), (9, 0)] {
            clouds.put(id, cloud(id as u32 + n as u32, n)).expect("put");
            memory.put(id, cloud(id as u32 + n as u32, n)).expect("put");
        }
        // The newest points of a keyframe given twice; an empty cloud has no points.
        assert_eq!(clouds.get(3).expect("get"), cloud(43, 40));
        assert_eq!(clouds.get(7).expect("get"), cloud(19, 12));
        assert!(!clouds.has_points(9) && clouds.has_points(7));
        for id in [3, 7, 9, 11] {
            assert_eq!(clouds.get(id).expect("get"), memory.get(id).expect("get"));
        }
    }

    #[test]
    fn a_rescaled_keyframe_sends_its_points_again_at_its_new_scale() {
        let mut views = KeyframeViews::new();
        let mut pose = Pose::IDENTITY;
        pose.s = 2.0;
        assert!(!views.set_pose(4, &pose), "a new keyframe is not a rescale");
        assert!(views.points_to_send(4).expect("send").is_none());
        views.set_points(4, cloud(1, 30)).expect("points");
        let sent = views.points_to_send(4).expect("send").expect("points");
        assert_eq!(sent[7], cloud(1, 30)[7].map(|v| v * 2.0));
        pose.s = 2.01;
        assert!(!views.set_pose(4, &pose), "within the tolerance");
        pose.s = 3.0;
        assert!(views.set_pose(4, &pose));
        let again = views.points_to_send(4).expect("send").expect("points");
        assert_eq!(again[7], cloud(1, 30)[7].map(|v| v * 3.0));
        assert!(!views.set_pose(4, &pose), "sent at this scale");
        // Points before a pose hang at the origin, unscaled.
        views.set_points(9, cloud(2, 3)).expect("points");
        assert_eq!(views.points_to_send(9).expect("send"), Some(cloud(2, 3)));
        assert_eq!(views.len(), 2);
        assert_eq!(views.poses().count(), 2);
    }
}
