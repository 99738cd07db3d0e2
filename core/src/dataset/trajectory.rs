//! TUM trajectory files: one `timestamp tx ty tz qx qy qz qw` line per pose.
//!
//! This is the exchange format of the TUM RGB-D benchmark tools and of evo (`evo_ape tum ...`):
//! `world_from_camera` poses (camera-to-world), translation in metres, Hamilton unit quaternion
//! with the real part last. Lines starting with `#` are comments; fields may be separated by
//! spaces, tabs or commas (the benchmark's `associate.py` accepts all three).
//!
//! Written files keep every `f64` at full precision (Rust's shortest round-trip formatting), so
//! that a trajectory read back is bit-identical and evaluations of written estimates do not
//! depend on a print format.

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::geometry::{SE3, Sim3};
use crate::{Error, Result};

/// One pose of a trajectory with its timestamp (seconds).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StampedPose {
    pub timestamp: f64,
    pub world_from_camera: SE3,
}

/// One pose of a monocular trajectory that still carries its Sim(3) scale (e.g. a keyframe
/// pose of the scale-drifting pose graph). TUM files cannot store the scale: [`Self::to_se3`]
/// keeps rotation and translation, which is what trajectory evaluation needs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StampedSim3 {
    pub timestamp: f64,
    pub world_from_camera: Sim3,
}

impl StampedSim3 {
    /// The rigid part (rotation, translation) of the pose; the scale only acts on points
    /// expressed in the camera frame and does not move the camera centre.
    pub fn to_se3(&self) -> StampedPose {
        StampedPose {
            timestamp: self.timestamp,
            world_from_camera: SE3::new(
                self.world_from_camera.rotation,
                self.world_from_camera.translation,
            ),
        }
    }
}

/// The rigid part of every `(timestamp, world_from_camera)` pose of the pipeline (see
/// [`StampedSim3::to_se3`]): what TUM files and trajectory evaluation take.
pub fn stamped_se3(poses: &[(f64, Sim3)]) -> Vec<StampedPose> {
    poses
        .iter()
        .map(|&(timestamp, world_from_camera)| {
            StampedSim3 {
                timestamp,
                world_from_camera,
            }
            .to_se3()
        })
        .collect()
}

/// Reads a TUM trajectory file. Poses keep file order (evaluation does not need sorted stamps).
/// Errors name the file and the 1-based line.
pub fn read_tum_trajectory(path: &Path) -> Result<Vec<StampedPose>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_tum_trajectory(&text, &path.display().to_string())
}

/// Parses the text of a TUM trajectory file; `source` names it in error messages.
pub fn parse_tum_trajectory(text: &str, source: &str) -> Result<Vec<StampedPose>> {
    parse_tum_trajectory_bounded(text, source, usize::MAX)
}

/// [`parse_tum_trajectory`] of at most `max_poses` poses (refused at the first line beyond,
/// before it is stored: an untrusted file's cost stays bounded).
pub fn parse_tum_trajectory_bounded(
    text: &str,
    source: &str,
    max_poses: usize,
) -> Result<Vec<StampedPose>> {
    let mut poses = Vec::new();
    for (index, raw) in text.lines().enumerate() {
        let lineno = index + 1;
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |why: String| Error::Dataset(format!("{source}:{lineno}: {why}"));
        if poses.len() == max_poses {
            return Err(bad(format!("more than {max_poses} poses")));
        }
        let fields: Vec<&str> = line
            .split(|c: char| c == ',' || c.is_whitespace())
            .filter(|f| !f.is_empty())
            .collect();
        if fields.len() != 8 {
            return Err(bad(format!(
                "expected 8 fields `timestamp tx ty tz qx qy qz qw`, got {}",
                fields.len()
            )));
        }
        let mut v = [0.0_f64; 8];
        for (slot, field) in v.iter_mut().zip(&fields) {
            *slot = field
                .parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or_else(|| bad(format!("`{field}` is not a finite number")))?;
        }
        let q = Quaternion::new(v[7], v[4], v[5], v[6]);
        // Files are written with ~4–9 decimals, so quaternions are only approximately unit;
        // a norm far from 1 means a column mix-up (e.g. w first), which we refuse.
        let norm = q.norm();
        if !(0.9..=1.1).contains(&norm) {
            return Err(bad(format!(
                "quaternion (qx qy qz qw) = ({} {} {} {}) has norm {norm:.4}, expected 1",
                v[4], v[5], v[6], v[7]
            )));
        }
        poses.push(StampedPose {
            timestamp: v[0],
            world_from_camera: SE3::from_quaternion_translation(
                UnitQuaternion::from_quaternion(q),
                Vector3::new(v[1], v[2], v[3]),
            ),
        });
    }
    Ok(poses)
}

/// Writes a TUM trajectory file at full precision, preceded by a `#` comment naming the
/// columns.
pub fn write_tum_trajectory(path: &Path, poses: &[StampedPose]) -> Result<()> {
    std::fs::write(path, format_tum_trajectory(poses)).map_err(|e| Error::io(path, e))
}

/// The text [`write_tum_trajectory`] writes.
pub fn format_tum_trajectory(poses: &[StampedPose]) -> String {
    let mut out = String::from("# timestamp tx ty tz qx qy qz qw\n");
    for pose in poses {
        let q = pose.world_from_camera.rotation.quaternion();
        let p = pose.world_from_camera.translation;
        // `{}` on f64 prints the shortest string that parses back to the same value.
        let _ = writeln!(
            out,
            "{} {} {} {} {} {} {} {}",
            pose.timestamp, p.x, p.y, p.z, q.i, q.j, q.k, q.w
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::SO3;
    use nalgebra::Vector3;

    fn sample() -> Vec<StampedPose> {
        (0..20)
            .map(|i| {
                let f = f64::from(i);
                StampedPose {
                    timestamp: 1305031228.5331 + 0.0333 * f,
                    world_from_camera: SE3::new(
                        SO3::exp(&Vector3::new(0.1 * f, -0.37, 0.05 * f.sin())),
                        Vector3::new(1.0 / 3.0 + f, -2.0_f64.sqrt() * f, 1e-7 * f),
                    ),
                }
            })
            .collect()
    }

    #[test]
    fn trajectory_round_trip_is_bit_exact() {
        let poses = sample();
        let dir = std::env::temp_dir().join(format!("relfusion_traj_{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let path = dir.join("t.txt");
        write_tum_trajectory(&path, &poses).expect("write");
        let back = read_tum_trajectory(&path).expect("read");
        std::fs::remove_dir_all(&dir).ok();
        assert_eq!(back.len(), poses.len());
        for (a, b) in poses.iter().zip(&back) {
            assert_eq!(a.timestamp.to_bits(), b.timestamp.to_bits());
            assert_eq!(
                a.world_from_camera.translation,
                b.world_from_camera.translation
            );
            let (qa, qb) = (
                a.world_from_camera.rotation.quaternion(),
                b.world_from_camera.rotation.quaternion(),
            );
            // Normalising an already unit quaternion may move the last bit.
            assert!(qa.angle_to(&qb) < 1e-15, "{qa:?} vs {qb:?}");
        }
    }

    #[test]
    fn trajectory_parses_comments_commas_and_tabs() {
        let text = "# header\n\n1.5 1 2 3 0 0 0 1\n  # indented comment\n2.5,1,2,3,0,0,0.7071067811865476,0.7071067811865476\n3.5\t0\t0\t0\t0\t0\t0\t-1\n";
        let poses = parse_tum_trajectory(text, "mem").expect("parse");
        assert_eq!(poses.len(), 3);
        assert_eq!(poses[0].timestamp, 1.5);
        assert_eq!(
            poses[0].world_from_camera.translation,
            Vector3::new(1.0, 2.0, 3.0)
        );
        let angle = poses[1].world_from_camera.rotation.log().norm();
        assert!(
            (angle - std::f64::consts::FRAC_PI_2).abs() < 1e-12,
            "{angle}"
        );
        assert!(poses[2].world_from_camera.rotation.log().norm() < 1e-12);
    }

    #[test]
    fn trajectory_errors_name_the_line() {
        let cases = [
            ("# c\n1 2 3 4 0 0 0 1\n1 2 3 4 0 0 1\n", "mem:3:", "got 7"),
            ("1 2 3 4 0 0 0 1 9\n", "mem:1:", "got 9"),
            ("\n\n1 2 x 4 0 0 0 1\n", "mem:3:", "`x`"),
            ("1 2 3 nan 0 0 0 1\n", "mem:1:", "`nan`"),
            ("1 0 0 0 1 0 0 1\n", "mem:1:", "norm"),
        ];
        for (text, place, why) in cases {
            let err = parse_tum_trajectory(text, "mem")
                .expect_err(text)
                .to_string();
            assert!(err.contains(place) && err.contains(why), "{text:?}: {err}");
        }
    }

    #[test]
    fn trajectory_reports_missing_file() {
        let err = read_tum_trajectory(Path::new("/nonexistent/relfusion/gt.txt"))
            .expect_err("missing file");
        assert!(
            err.to_string().contains("/nonexistent/relfusion/gt.txt"),
            "{err}"
        );
    }

    #[test]
    fn trajectory_sim3_keeps_the_camera_centre() {
        let p = StampedSim3 {
            timestamp: 2.0,
            world_from_camera: Sim3 {
                rotation: SO3::exp(&Vector3::new(0.3, 0.0, 0.1)),
                translation: Vector3::new(1.0, 2.0, 3.0),
                scale: 4.0,
            },
        };
        let se3 = p.to_se3();
        assert_eq!(se3.timestamp, 2.0);
        assert_eq!(
            se3.world_from_camera.translation,
            Vector3::new(1.0, 2.0, 3.0)
        );
    }
}
