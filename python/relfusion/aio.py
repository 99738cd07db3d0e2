"""The asynchronous client: ``AsyncClient(url, token)``, the same calls as :class:`Client`
as coroutines, and ``stream`` as an async generator."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path
from typing import Any, AsyncIterator, Dict, Iterable, List, Optional, Tuple, Union

import httpx

from . import _protocol as p
from .errors import NotFound, RelfusionError, error_from_response
from .images import Frame, encode
from .types import Camera, Pose, Results, parse_tum


async def _check(response: httpx.Response) -> httpx.Response:
    if response.status_code >= 400:
        raise error_from_response(response.status_code, await response.aread())
    return response


class AsyncClient:
    """A relfusiond service, for asyncio code (``async with AsyncClient(url, token) as c``)."""

    def __init__(self, url: str, token: Optional[str] = None, timeout: float = 60.0) -> None:
        self._http = httpx.AsyncClient(
            base_url=p.base_url(url), headers=p.headers(token), timeout=timeout
        )
        self.last_session: Optional[str] = None

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.aclose()

    async def _send(self, method: str, path: str, **kw: Any) -> httpx.Response:
        """The answer to a request; the service's errors and an unreachable service raise."""
        try:
            return await _check(await self._http.request(method, path, **kw))
        except httpx.TransportError as e:
            raise RelfusionError(0, "unreachable", str(e)) from e

    async def _json(self, method: str, path: str, **kw: Any) -> Any:
        return (await self._send(method, path, **kw)).json()

    async def _bytes(self, session: str, name: str) -> bytes:
        return (await self._send("GET", f"v1/sessions/{session}/{name}")).content

    async def create_session(
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
        body = p.session_request(camera, model, config, policy, map_id, map_mode, ros2)
        created = await self._json("POST", "v1/sessions", json=body)
        self.last_session = created["id"]
        return created["session"]

    async def send_frame(self, session: str, timestamp: float, frame: Frame) -> int:
        data, content_type = encode(frame)
        answer = await self._json(
            "POST",
            f"v1/sessions/{session}/frames",
            params={"timestamp": repr(float(timestamp))},
            content=data,
            headers={"Content-Type": content_type},
        )
        return int(answer["frame_index"])

    async def finish(self, session: str) -> None:
        await self._json("POST", f"v1/sessions/{session}/finish")

    async def session(self, session: str) -> Dict[str, Any]:
        return await self._json("GET", f"v1/sessions/{session}")

    async def stream(
        self,
        frames: Iterable[Tuple[float, Frame]],
        camera: Camera,
        *,
        model: Optional[str] = None,
        config: Optional[Dict[str, Any]] = None,
        policy: str = "wait",
        map_id: Optional[str] = None,
        map_mode: str = "localize",
    ) -> AsyncIterator[Pose]:
        """As :meth:`Client.stream`: poses as they come, then the rest after the end."""
        info = await self.create_session(
            camera, model=model, config=config, policy=policy, map_id=map_id, map_mode=map_mode
        )
        session = info["id"]
        events: "asyncio.Queue[Tuple[str, Any]]" = asyncio.Queue()
        connected = asyncio.Event()

        async def listen() -> None:
            try:
                parser = p.EventParser()
                async with self._http.stream(
                    "GET",
                    f"v1/sessions/{session}/events",
                    timeout=httpx.Timeout(None, connect=30),
                ) as response:
                    await _check(response)
                    connected.set()
                    async for line in response.aiter_lines():
                        got = parser.feed(line)
                        if got is not None:
                            await events.put(got)
                            if p.is_last(got[0]):
                                return
            except Exception as e:
                await events.put(("error", e))
            finally:
                connected.set()

        listener = asyncio.ensure_future(listen())
        await asyncio.wait_for(connected.wait(), timeout=30)

        def handle(kind: str, data: Any) -> Optional[Pose]:
            if kind == "error":
                raise data
            if kind == "failed":
                raise RelfusionError(0, "session_failed", str(data.get("message", data)))
            return Pose.from_event(data) if kind == "pose" else None

        try:
            for timestamp, frame in frames:
                await self.send_frame(session, timestamp, frame)
                while not events.empty():
                    kind, data = events.get_nowait()
                    pose = handle(kind, data)
                    if pose is not None:
                        yield pose
            await self.finish(session)
            while True:
                kind, data = await asyncio.wait_for(events.get(), timeout=600)
                if kind == "finished":
                    break
                pose = handle(kind, data)
                if pose is not None:
                    yield pose
        finally:
            listener.cancel()

    async def upload(
        self,
        folder: Union[str, Path],
        *,
        camera: Optional[Camera] = None,
        progress: Optional[p.Progress] = None,
    ) -> Dict[str, Any]:
        path, total = p.upload_archive(Path(folder), camera)

        async def chunks() -> AsyncIterator[bytes]:
            for chunk in p.file_chunks(path, total, progress):
                yield chunk

        try:
            created = await self._json(
                "POST",
                "v1/uploads",
                params={"format": "tar"},
                content=chunks(),
                headers={"Content-Type": "application/x-tar", "Content-Length": str(total)},
                timeout=httpx.Timeout(None, connect=30),
            )
        finally:
            os.unlink(path)
        session = created.get("session", created)
        self.last_session = session["id"]
        return session

    async def fetch(self, session: str) -> Results:
        results = Results(
            session=await self.session(session),
            trajectory=parse_tum((await self._bytes(session, "trajectory")).decode()),
            keyframes=parse_tum((await self._bytes(session, "keyframes")).decode()),
        )
        for name in p.OPTIONAL_RESULTS:
            try:
                data = await self._bytes(session, name)
            except NotFound as e:
                results.missing[name] = e.message
                continue
            if name == "mesh.ply":
                results.mesh_ply = data
            else:
                results.recording_mcap = data
        return results

    async def save_map(self, session: str, name: Optional[str] = None) -> Dict[str, Any]:
        return await self._json("POST", "v1/maps", json={"session": session, "name": name})

    async def maps(self) -> List[Dict[str, Any]]:
        return (await self._json("GET", "v1/maps"))["maps"]
