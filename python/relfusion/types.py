"""The values the SDK hands out: the camera, a pose, a session's results."""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence

import numpy as np


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels at the frames' resolution; optional radial-tangential
    distortion ``(k1, k2, p1, p2, k3)``."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: Optional[Sequence[float]] = None

    def to_json(self) -> Dict[str, Any]:
        out: Dict[str, Any] = {
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "width": self.width,
            "height": self.height,
        }
        if self.distortion is not None:
            out["distortion"] = list(self.distortion)
        return out


@dataclass(frozen=True)
class Pose:
    """A frame's camera-to-world pose: ``p_world = s · R(q) · p + t``, ``q`` = (x, y, z, w).
    ``state`` is ``"tracking"``, ``"relocalised"`` or ``"lost"`` (lost frames keep the last
    pose)."""

    frame_id: int
    timestamp: float
    t: np.ndarray
    q: np.ndarray
    s: float
    state: str
    keyframe_id: int
    is_keyframe: bool

    @staticmethod
    def from_event(event: Dict[str, Any]) -> "Pose":
        pose = event["pose"]
        return Pose(
            frame_id=int(event["frame_id"]),
            timestamp=float(event["timestamp"]),
            t=np.asarray(pose["t"], dtype=np.float64),
            q=np.asarray(pose["q"], dtype=np.float64),
            s=float(pose["s"]),
            state=str(event["state"]),
            keyframe_id=int(event.get("keyframe_id", 0)),
            is_keyframe=bool(event.get("is_keyframe", False)),
        )

    def matrix(self) -> np.ndarray:
        """The 4×4 similarity."""
        x, y, z, w = self.q
        r = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
        m = np.eye(4)
        m[:3, :3] = self.s * r
        m[:3, 3] = self.t
        return m


def parse_tum(text: str) -> np.ndarray:
    """TUM trajectory lines as an N×8 array: ``timestamp tx ty tz qx qy qz qw``."""
    rows: List[List[float]] = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        values = [float(v) for v in line.split()]
        if len(values) != 8:
            raise ValueError(f"not a TUM trajectory line: {line!r}")
        rows.append(values)
    return np.asarray(rows, dtype=np.float64).reshape(-1, 8)


@dataclass
class Results:
    """A session's results. ``trajectory`` and ``keyframes`` are N×8 arrays
    (``timestamp tx ty tz qx qy qz qw``); ``mesh_ply`` the fused surface (``None`` before any);
    ``recording_mcap`` the service's MCAP recording (``None`` while the session runs)."""

    session: Dict[str, Any]
    trajectory: np.ndarray
    keyframes: np.ndarray
    mesh_ply: Optional[bytes] = None
    recording_mcap: Optional[bytes] = None
    missing: Dict[str, str] = field(default_factory=dict)

    @property
    def mesh(self) -> Any:
        """The fused mesh as a ``trimesh.Trimesh`` (needs ``pip install relfusion[mesh]``)."""
        if self.mesh_ply is None:
            return None
        import trimesh

        return trimesh.load(io.BytesIO(self.mesh_ply), file_type="ply", process=False)
