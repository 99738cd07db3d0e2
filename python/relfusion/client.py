"""The synchronous client: ``Client(url, token)``."""

from __future__ import annotations

import os
import queue
import threading
import time
from pathlib import Path
from typing import Any, Callable, Dict, Iterable, Iterator, List, Optional, Tuple, Union

import httpx

from . import _protocol as p
from .errors import RelfusionError, error_from_response
from .images import Frame, encode
from .types import Camera, Pose, Results, parse_tum

Frames = Iterable[Tuple[float, Frame]]
"""(timestamp in seconds, frame) pairs: a uint8 numpy image or JPEG/PNG bytes."""


def _check(response: httpx.Response) -> httpx.Response:
    if response.status_code >= 400:
        raise error_from_response(response.status_code, response.read())
    return response


class Client:
    """A relfusiond service. Every call raises a :class:`RelfusionError` subclass for the
    service's error answers (``status``, ``code``, ``message``).

    >>> client = Client("http://127.0.0.1:8780", token="…")
    >>> for pose in client.stream(frames, camera):   # poses as they come
    ...     print(pose.frame_id, pose.t)
    >>> results = client.fetch(client.last_session)
    """

    def __init__(self, url: str, token: Optional[str] = None, timeout: float = 60.0) -> None:
        self._http = httpx.Client(
            base_url=p.base_url(url), headers=p.headers(token), timeout=timeout
        )
        self.last_session: Optional[str] = None

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ---- plain calls ----

    def _send(self, method: str, path: str, **kw: Any) -> httpx.Response:
        """The answer to a request; the service's errors and an unreachable service raise."""
        try:
            return _check(self._http.request(method, path, **kw))
        except httpx.TransportError as e:
            raise RelfusionError(0, "unreachable", str(e)) from e

    def _json(self, method: str, path: str, **kw: Any) -> Any:
        return self._send(method, path, **kw).json()

    def version(self) -> Dict[str, Any]:
        return self._json("GET", "v1/version")

    def create_session(
        self,
        camera: Optional[Camera] = None,
        *,
        model: Optional[str] = None,
        config: Optional[Dict[str, Any]] = None,
        policy: str = "drop_oldest",
        map_id: Optional[str] = None,
        map_mode: str = "localize",
        ros2: Optional[Dict[str, Any]] = None,
    ) -> Dict[str, Any]:
        """Opens a live session; returns its info (``["id"]``). ``policy="wait"`` processes
        every frame (the service stops reading while the queue is full); the default drops the
        oldest queued frame as a live camera should. ``map_id``: start in a saved map.
        ``ros2``: the session on ROS 2 (servers with ``[ros2]``), e.g. ``{"publish": True,
        "image_topic": "camera/image_raw", "camera_info_topic": "camera/camera_info"}``; with a
        CameraInfo topic the camera may be left out."""
        body = p.session_request(camera, model, config, policy, map_id, map_mode, ros2)
        created = self._json("POST", "v1/sessions", json=body)
        self.last_session = created["id"]
        return created["session"]

    def send_frame(self, session: str, timestamp: float, frame: Frame) -> int:
        """Sends one frame; returns the service's frame index."""
        data, content_type = encode(frame)
        answer = self._json(
            "POST",
            f"v1/sessions/{session}/frames",
            params={"timestamp": repr(float(timestamp))},
            content=data,
            headers={"Content-Type": content_type},
        )
        return int(answer["frame_index"])

    def finish(self, session: str) -> None:
        """End of stream: the session processes its queued frames and finishes its map."""
        self._json("POST", f"v1/sessions/{session}/finish")

    def session(self, session: str) -> Dict[str, Any]:
        return self._json("GET", f"v1/sessions/{session}")

    def sessions(self) -> List[Dict[str, Any]]:
        return self._json("GET", "v1/sessions")["sessions"]

    def delete(self, session: str) -> None:
        self._send("DELETE", f"v1/sessions/{session}")

    def events(
        self, session: str, on_open: Optional[Callable[[], None]] = None
    ) -> Iterator[Tuple[str, Any]]:
        """The session's events as they happen, ``(type, data)``, until it ends; ``on_open``
        is called once the service has accepted the subscription."""
        parser = p.EventParser()
        try:
            with self._http.stream(
                "GET", f"v1/sessions/{session}/events", timeout=httpx.Timeout(None, connect=30)
            ) as response:
                _check(response)
                if on_open is not None:
                    on_open()
                for line in response.iter_lines():
                    got = parser.feed(line)
                    if got is None:
                        continue
                    yield got
                    if p.is_last(got[0]):
                        return
        except httpx.TransportError as e:
            raise RelfusionError(0, "unreachable", str(e)) from e

    def wait_finished(self, session: str, timeout: float = 3600.0) -> Dict[str, Any]:
        """Waits for the session to end; its info. Raises if it failed."""
        deadline = time.monotonic() + timeout
        while True:
            info = self.session(session)
            if info["state"] == "finished":
                return info
            if info["state"] == "failed":
                raise RelfusionError(0, "session_failed", info.get("error") or "the session failed")
            if time.monotonic() > deadline:
                raise RelfusionError(0, "timeout", f"session {session} still {info['state']}")
            time.sleep(0.5)

    # ---- streaming ----

    def stream(
        self,
        frames: Frames,
        camera: Camera,
        *,
        model: Optional[str] = None,
        config: Optional[Dict[str, Any]] = None,
        policy: str = "wait",
        map_id: Optional[str] = None,
        map_mode: str = "localize",
    ) -> Iterator[Pose]:
        """Streams frames to a new session and yields each frame's pose as it comes, then the
        rest once the stream has ended and the session finished. The session's id is
        ``client.last_session``. Frames go as fast as the service takes them (``policy="wait"``);
        pace them yourself for a live camera and pass ``policy="drop_oldest"``."""
        info = self.create_session(
            camera, model=model, config=config, policy=policy, map_id=map_id, map_mode=map_mode
        )
        session = info["id"]
        events: "queue.Queue[Tuple[str, Any]]" = queue.Queue()
        connected = threading.Event()

        def listen() -> None:
            try:
                for event in self.events(session, on_open=connected.set):
                    events.put(event)
            except Exception as e:  # handed to the caller's thread
                events.put(("error", e))
            finally:
                connected.set()

        listener = threading.Thread(target=listen, name="relfusion-events", daemon=True)
        listener.start()
        # Subscribed before the first frame, so no pose is missed.
        connected.wait(timeout=30)

        def drain(block: bool) -> Iterator[Pose]:
            while True:
                try:
                    kind, data = events.get(block=block, timeout=600 if block else None)
                except queue.Empty:
                    if block:
                        raise RelfusionError(0, "timeout", "no event from the session for 600 s")
                    return
                if kind == "error":
                    raise data
                if kind == "pose":
                    yield Pose.from_event(data)
                elif kind == "failed":
                    raise RelfusionError(0, "session_failed", str(data.get("message", data)))
                elif kind == "finished":
                    return

        for timestamp, frame in frames:
            self.send_frame(session, timestamp, frame)
            yield from drain(block=False)
        self.finish(session)
        yield from drain(block=True)
        listener.join(timeout=10)

    def stream_folder(self, folder: Union[str, Path], **kw: Any) -> Iterator[Pose]:
        """:meth:`stream` of a TUM-layout sequence folder (``rgb.txt``, ``calibration.txt``)."""
        from .images import image_size

        frames = list(p.tum_frames(Path(folder)))
        if not frames:
            raise ValueError(f"{folder}: rgb.txt lists no frames")
        width, height = image_size(frames[0][1])
        camera = kw.pop("camera", None) or p.read_calibration(Path(folder), width, height)
        return self.stream(frames, camera, **kw)

    # ---- uploads and results ----

    def upload(
        self,
        folder: Union[str, Path],
        *,
        camera: Optional[Camera] = None,
        progress: Optional[p.Progress] = None,
    ) -> Dict[str, Any]:
        """Uploads a TUM-layout sequence (tar); returns the new session's info once the service
        has stored it durably. ``progress(sent, total)`` follows the bytes."""
        path, total = p.upload_archive(Path(folder), camera)
        try:
            created = self._json(
                "POST",
                "v1/uploads",
                params={"format": "tar"},
                content=p.file_chunks(path, total, progress),
                headers={"Content-Type": "application/x-tar", "Content-Length": str(total)},
                timeout=httpx.Timeout(None, connect=30),
            )
        finally:
            os.unlink(path)
        session = created.get("session", created)
        self.last_session = session["id"]
        return session

    def _bytes(self, session: str, name: str) -> bytes:
        return self._send("GET", f"v1/sessions/{session}/{name}").content

    def fetch(self, session: str) -> Results:
        """The session's results: trajectory and keyframes as numpy, the mesh (``.mesh`` is a
        ``trimesh.Trimesh``), the service's MCAP recording once it ended."""
        from .errors import NotFound

        results = Results(
            session=self.session(session),
            trajectory=parse_tum(self._bytes(session, "trajectory").decode()),
            keyframes=parse_tum(self._bytes(session, "keyframes").decode()),
        )
        for name in p.OPTIONAL_RESULTS:
            try:
                data = self._bytes(session, name)
            except NotFound as e:
                results.missing[name] = e.message
                continue
            if name == "mesh.ply":
                results.mesh_ply = data
            else:
                results.recording_mcap = data
        return results

    # ---- maps ----

    def save_map(self, session: str, name: Optional[str] = None) -> Dict[str, Any]:
        """Keeps a finished session's map; its info (``["id"]``)."""
        return self._json("POST", "v1/maps", json={"session": session, "name": name})

    def maps(self) -> List[Dict[str, Any]]:
        return self._json("GET", "v1/maps")["maps"]

    def delete_map(self, map_id: str) -> None:
        self._send("DELETE", f"v1/maps/{map_id}")
