"""What the sync and async clients share: URLs, the session request, the event-stream parser,
the upload archive. Nothing here does I/O on the network."""

from __future__ import annotations

import io
import json
import os
import tarfile
import tempfile
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple

from .types import Camera

Progress = Callable[[int, int], None]
"""Called with (bytes sent, bytes in all) while an upload goes out."""

UPLOAD_CHUNK = 1 << 20

# Results a session may not have yet: no mesh before the fusion has run, no recording before
# it ends.
OPTIONAL_RESULTS = ("mesh.ply", "recording.mcap")


def base_url(url: str) -> str:
    if not url.startswith(("http://", "https://")):
        raise ValueError(f"the service URL must start with http:// or https://, got {url!r}")
    return url.rstrip("/") + "/"


def headers(token: Optional[str]) -> Dict[str, str]:
    return {"Authorization": f"Bearer {token}"} if token else {}


def session_request(
    camera: Optional[Camera],
    model: Optional[str],
    config: Optional[Dict[str, Any]],
    policy: str,
    map_id: Optional[str],
    map_mode: str,
    ros2: Optional[Dict[str, Any]] = None,
) -> Dict[str, Any]:
    if policy not in ("drop_oldest", "wait"):
        raise ValueError(f"policy must be 'drop_oldest' or 'wait', got {policy!r}")
    if map_mode not in ("localize", "extend"):
        raise ValueError(f"map_mode must be 'localize' or 'extend', got {map_mode!r}")
    if camera is None and not (ros2 or {}).get("camera_info_topic"):
        raise ValueError("a camera is required unless ros2['camera_info_topic'] gives it")
    body: Dict[str, Any] = {"policy": policy}
    if camera is not None:
        body["camera"] = camera.to_json()
    if ros2 is not None:
        body["ros2"] = ros2
    if model is not None:
        body["model"] = model
    if config is not None:
        body["config"] = config
    if map_id is not None:
        body["map"] = {"id": map_id, "mode": map_mode}
    return body


class EventParser:
    """Server-sent events, line by line: yields ``(event, data)`` with the JSON data parsed."""

    def __init__(self) -> None:
        self._event = "message"
        self._data: List[str] = []

    def feed(self, line: str) -> Optional[Tuple[str, Any]]:
        line = line.rstrip("\r\n")
        if line == "":
            if not self._data:
                return None
            event, data = self._event, "\n".join(self._data)
            self._event, self._data = "message", []
            try:
                return event, json.loads(data)
            except ValueError:
                return event, data
        if line.startswith(":"):
            return None
        name, _, value = line.partition(":")
        value = value[1:] if value.startswith(" ") else value
        if name == "event":
            self._event = value
        elif name == "data":
            self._data.append(value)
        return None


def is_last(event: str) -> bool:
    return event in ("finished", "failed")


def _rgb_files(folder: Path) -> List[str]:
    """The images `rgb.txt` lists, relative to the folder."""
    listed: List[str] = []
    text = (folder / "rgb.txt").read_text()
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < 2:
            raise ValueError(f"{folder / 'rgb.txt'}: not 'timestamp path': {line!r}")
        listed.append(parts[1])
    return listed


def upload_archive(folder: Path, camera: Optional[Camera]) -> Tuple[str, int]:
    """A tar of the TUM-layout sequence in `folder` in a temporary file (its path and size):
    ``rgb.txt``, the images it lists, ``groundtruth.txt`` and ``calibration.txt`` when present
    (written from `camera` when given). The caller removes the file."""
    folder = Path(folder)
    if not (folder / "rgb.txt").is_file():
        raise ValueError(f"{folder} is not a TUM-layout sequence (no rgb.txt)")
    root = folder.resolve().name or "sequence"
    names = ["rgb.txt"] + _rgb_files(folder)
    for optional in ("groundtruth.txt", "calibration.txt"):
        if (folder / optional).is_file() and not (camera and optional == "calibration.txt"):
            names.append(optional)
    fd, path = tempfile.mkstemp(prefix="relfusion-upload-", suffix=".tar")
    os.close(fd)
    with tarfile.open(path, "w", format=tarfile.GNU_FORMAT) as tar:
        for name in names:
            source = (folder / name).resolve()
            if folder.resolve() not in source.parents:
                raise ValueError(f"{name} is outside {folder}")
            tar.add(str(source), arcname=f"{root}/{name}", recursive=False)
        if camera is not None:
            line = f"{camera.fx!r} {camera.fy!r} {camera.cx!r} {camera.cy!r}"
            if camera.distortion is not None:
                line += " " + " ".join(repr(float(d)) for d in camera.distortion)
            data = f"# fx fy cx cy [k1 k2 p1 p2 k3] (written by the relfusion Python SDK)\n{line}\n".encode()
            info = tarfile.TarInfo(f"{root}/calibration.txt")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return path, os.path.getsize(path)


def file_chunks(path: str, total: int, progress: Optional[Progress]) -> Iterator[bytes]:
    sent = 0
    with open(path, "rb") as f:
        while True:
            chunk = f.read(UPLOAD_CHUNK)
            if not chunk:
                break
            sent += len(chunk)
            if progress is not None:
                progress(sent, total)
            yield chunk


def tum_frames(folder: Path) -> Iterator[Tuple[float, bytes]]:
    """The frames of a TUM-layout sequence as (timestamp, encoded image), in order."""
    folder = Path(folder)
    for line in (folder / "rgb.txt").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        stamp, name = line.split()[:2]
        yield float(stamp), (folder / name).read_bytes()


def read_calibration(folder: Path, width: int, height: int) -> Camera:
    """The camera of a sequence's ``calibration.txt`` (``fx fy cx cy [k1 k2 p1 p2 k3]``)."""
    path = Path(folder) / "calibration.txt"
    if not path.is_file():
        raise ValueError(f"{folder} has no calibration.txt: pass camera=relfusion.Camera(...)")
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            v = [float(x) for x in line.split()]
            return Camera(v[0], v[1], v[2], v[3], width, height, v[4:9] if len(v) >= 9 else None)
    raise ValueError(f"{folder}/calibration.txt has no intrinsics")
