//! Smooth 6-DoF camera trajectories (sums of sinusoids) inside the room's free region.
//!
//! Every preset is a function of time (seconds), not of the frame index, so a shorter
//! sequence is the beginning of the longer one and per-frame motion does not depend on the
//! frame count. Periods are tied to [`PERIOD_S`] = 10 s, the default 300 frames at 30 Hz. The
//! seed only shifts the phases, so the motion's size is the same for every seed.
//!
//! | preset | translation | rotation (about the base view along +x) |
//! |---|---|---|
//! | `orbit` (default) | ellipse 0.7 × 1.0 m + ±0.12 m height: ≈ 2.7 m per 10 s | yaw ±20°, pitch ±10°, roll ±6° |
//! | `forward` | 1.5 m towards the far wall and back (cosine), ±0.1 m sway | yaw ±6°, pitch ±4°, roll ±3° |
//! | `rotation` | ±1 cm jitter | yaw ±25°, pitch ±15°, roll ±10° |
//! | `shake` | ±1.5 cm at 1.3 Hz + ±0.5 cm at 3.7 Hz per axis | ±2.5° at 0.9 Hz + ±1° at 2.3 Hz per axis |
//! | `handheld` | a wander over the free region, incommensurate periods 7-31 s (no return to the start): ≈ 0.2 m/s | yaw ±45°, pitch ±12°, roll ±6°, plus hand tremor |
//! | `loop` | a closed loop of 1.1 × 0.9 m in 30 s (900 frames), back over the start after it | yaw ±40°, pitch ±10°, roll ±5° (periodic), plus hand tremor |
//!
//! `handheld` and `loop` are the long presets (1000+ frames, issue 22): the hand tremor
//! (±4 mm, ±0.6° at 1.7-4.3 Hz) is not periodic, so a revisit is never an exact repeat.

use std::f64::consts::{PI, TAU};
use std::fmt;
use std::str::FromStr;

use nalgebra::{Matrix3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::geometry::{SE3, SO3};
use crate::{Error, Result};

/// Period of the main motion components, seconds (300 frames at 30 Hz).
pub const PERIOD_S: f64 = 10.0;

/// Motion preset of a synthetic sequence (see the module table).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Motion {
    /// Translation around an ellipse with moderate rotation: parallax for monocular SLAM.
    #[default]
    Orbit,
    /// Dolly towards the far wall and back: depth changes, little rotation.
    Forward,
    /// Almost pure rotation: the hard case for monocular depth estimation (no parallax).
    Rotation,
    /// Hand-held jitter: small fast translation and rotation.
    Shake,
    /// A long hand-held walk-around that never returns to its start.
    Handheld,
    /// A long hand-held loop that comes back over its start every 30 s.
    Loop,
}

impl Motion {
    /// All presets, for tests and help texts.
    pub const ALL: [Motion; 6] = [
        Motion::Orbit,
        Motion::Forward,
        Motion::Rotation,
        Motion::Shake,
        Motion::Handheld,
        Motion::Loop,
    ];

    /// The lowercase name used on the command line and in configs.
    pub fn name(self) -> &'static str {
        match self {
            Motion::Orbit => "orbit",
            Motion::Forward => "forward",
            Motion::Rotation => "rotation",
            Motion::Shake => "shake",
            Motion::Handheld => "handheld",
            Motion::Loop => "loop",
        }
    }
}

impl fmt::Display for Motion {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Motion {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        Motion::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .ok_or_else(|| {
                Error::Config(format!(
                    "unknown motion `{s}` (orbit, forward, rotation, shake, handheld, loop)"
                ))
            })
    }
}

/// Seed-dependent phases of a trajectory's sinusoids.
#[derive(Clone, Debug)]
pub struct Trajectory {
    motion: Motion,
    phase: [f64; 20],
}

/// Camera axes (columns: right, down, forward) of the base view: looking along world +x with
/// world z up.
fn base_rotation() -> Matrix3<f64> {
    Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0)
}

impl Trajectory {
    /// The trajectory of `motion` for `seed` (phases drawn from their own ChaCha stream, so
    /// they do not change when the scene generator draws more numbers).
    pub fn new(motion: Motion, seed: u64) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(2);
        let mut phase = [0.0; 20];
        for p in &mut phase {
            *p = rng.random_range(0.0..TAU);
        }
        Self { motion, phase }
    }

    /// Camera-to-world pose at time `t` seconds.
    pub fn world_from_camera(&self, t: f64) -> SE3 {
        let w = TAU / PERIOD_S;
        let ph = &self.phase;
        let s = |amp: f64, freq: f64, k: usize| amp * (freq * t + ph[k]).sin();
        let deg = PI / 180.0;
        let (position, ypr) = match self.motion {
            Motion::Orbit => (
                Vector3::new(
                    -0.25 + 0.35 * (w * t + ph[0]).cos(),
                    0.5 * (w * t + ph[0]).sin(),
                    1.3 + s(0.12, 2.0 * w, 1),
                ),
                [s(20.0, w, 2), s(10.0, 1.5 * w, 3), s(6.0, 2.0 * w, 4)],
            ),
            Motion::Forward => (
                Vector3::new(
                    -0.25 - 0.75 * (PI * t / PERIOD_S).cos(),
                    s(0.1, w, 1),
                    1.25 + s(0.05, 2.0 * w, 2),
                ),
                [s(6.0, w, 3), s(4.0, 1.5 * w, 4), s(3.0, 2.0 * w, 5)],
            ),
            Motion::Rotation => (
                Vector3::new(
                    -0.3 + s(0.01, 2.0 * w, 0),
                    s(0.01, 3.0 * w, 1),
                    1.3 + s(0.01, 2.5 * w, 2),
                ),
                [s(25.0, w, 3), s(15.0, 1.3 * w, 4), s(10.0, 1.7 * w, 5)],
            ),
            Motion::Shake => {
                let jitter = |k: usize| s(0.015, TAU * 1.3, k) + s(0.005, TAU * 3.7, k + 3);
                let turn = |k: usize| s(2.5, TAU * 0.9, k) + s(1.0, TAU * 2.3, k + 3);
                (
                    Vector3::new(-0.3 + jitter(0), jitter(1), 1.3 + jitter(2)),
                    [turn(6), turn(7), turn(8)],
                )
            }
            Motion::Handheld => {
                let f = |period: f64| TAU / period;
                (
                    Vector3::new(
                        -0.25 + s(0.4, f(31.0), 0) + s(0.18, f(13.0), 1),
                        s(0.32, f(23.0), 2) + s(0.14, f(11.0), 3),
                        1.3 + s(0.12, f(19.0), 4) + s(0.05, f(7.0), 5),
                    ),
                    [
                        s(35.0, f(29.0), 6) + s(10.0, f(9.0), 7),
                        s(12.0, f(17.0), 8),
                        s(6.0, f(13.0), 9),
                    ],
                )
            }
            Motion::Loop => {
                let w = TAU / 30.0;
                (
                    Vector3::new(
                        -0.25 + 0.55 * (w * t + ph[0]).cos(),
                        0.45 * (w * t + ph[0]).sin(),
                        1.3 + s(0.1, 2.0 * w, 1),
                    ),
                    [
                        s(30.0, w, 2) + s(10.0, 3.0 * w, 3),
                        s(10.0, 2.0 * w, 4),
                        s(5.0, 3.0 * w, 5),
                    ],
                )
            }
        };
        let (position, ypr) = match self.motion {
            Motion::Handheld | Motion::Loop => {
                // Hand tremor: fast, small, not periodic with the path.
                let tremor_t = |k: usize| s(0.003, TAU * 1.7, k) + s(0.001, TAU * 4.3, k + 3);
                let tremor_r = |k: usize| s(0.45, TAU * 2.1, k) + s(0.15, TAU * 3.9, k + 3);
                (
                    position + Vector3::new(tremor_t(10), tremor_t(11), tremor_t(12)),
                    [
                        ypr[0] + tremor_r(13),
                        ypr[1] + tremor_r(14),
                        ypr[2] + tremor_r(15),
                    ],
                )
            }
            _ => (position, ypr),
        };
        let [yaw, pitch, roll] = ypr.map(|a| a * deg);
        // Yaw about world z, pitch about world y (tilts the view up/down), roll about the
        // optical axis: R = Rz(yaw)·Ry(pitch)·R_base·Rz_cam(roll).
        let rotation = SO3::exp(&Vector3::new(0.0, 0.0, yaw))
            * SO3::exp(&Vector3::new(0.0, pitch, 0.0))
            * SO3::from_matrix(&base_rotation())
            * SO3::exp(&Vector3::new(0.0, 0.0, roll));
        SE3::new(rotation, position)
    }

    /// Poses of `frames` frames at `fps`.
    pub fn poses(&self, frames: usize, fps: f64) -> Vec<SE3> {
        (0..frames)
            .map(|i| self.world_from_camera(i as f64 / fps))
            .collect()
    }
}

/// Total camera-centre path length, metres.
pub fn path_length(poses: &[SE3]) -> f64 {
    poses
        .windows(2)
        .map(|w| (w[1].translation - w[0].translation).norm())
        .fold(0.0, |a, b| a + b)
}

/// Largest rotation angle of any pose relative to the first, degrees.
pub fn max_rotation_deg(poses: &[SE3]) -> f64 {
    let Some(first) = poses.first() else {
        return 0.0;
    };
    let inv = first.rotation.inverse();
    poses
        .iter()
        .map(|p| (inv * p.rotation).log().norm().to_degrees())
        .fold(0.0, f64::max)
}
