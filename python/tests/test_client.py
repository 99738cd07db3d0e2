"""The Python SDK against a real relfusiond: stream (sync and async), upload, fetch into numpy
and trimesh, maps, and the service's errors as exceptions."""

import asyncio
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import trimesh

import relfusion
from relfusion import _protocol


def frames_of(sequence: Path):
    return list(_protocol.tum_frames(sequence))


def camera_of(sequence: Path) -> relfusion.Camera:
    from relfusion.images import image_size

    w, h = image_size(frames_of(sequence)[0][1])
    return _protocol.read_calibration(sequence, w, h)


def tum_rows(sequence: Path, name: str) -> int:
    return sum(
        1
        for line in (sequence / name).read_text().splitlines()
        if line.strip() and not line.startswith("#")
    )


def test_stream_gives_every_pose_and_fetch_gives_numpy_and_trimesh(client, sequence):
    poses = list(client.stream_folder(sequence))
    frames = tum_rows(sequence, "rgb.txt")
    assert [p.frame_id for p in poses] == list(range(len(poses)))
    assert len(poses) == frames
    tracked = [p for p in poses if p.state != "lost"]
    assert len(tracked) > frames // 2
    assert all(p.t.shape == (3,) and abs(np.linalg.norm(p.q) - 1) < 1e-6 for p in tracked)
    assert np.allclose(poses[0].matrix()[:3, 3], poses[0].t)

    results = client.fetch(client.last_session)
    assert results.session["state"] == "finished"
    assert results.trajectory.shape == (len(tracked), 8)
    assert np.all(np.diff(results.trajectory[:, 0]) > 0)
    assert results.keyframes.shape[0] == results.session["keyframes"]
    mesh = results.mesh
    assert isinstance(mesh, trimesh.Trimesh)
    assert len(mesh.faces) == results.session["mesh_triangles"] > 100
    assert results.recording_mcap is not None and results.recording_mcap.startswith(b"\x89MCAP0\r\n")


def test_async_stream_of_numpy_frames(url, token, sequence):
    camera = camera_of(sequence)
    rng = np.random.default_rng(3)
    # Textured noise the tracker can follow: the same image drifting right by a pixel a frame.
    base = rng.integers(0, 256, size=(camera.height, camera.width + 40, 3), dtype=np.uint8)
    frames = [(i / 30.0, base[:, i : i + camera.width]) for i in range(12)]

    async def run():
        async with relfusion.AsyncClient(url, token) as client:
            poses = [p async for p in client.stream(frames, camera)]
            info = await client.session(client.last_session)
            return poses, info

    poses, info = asyncio.run(run())
    assert [p.frame_id for p in poses] == list(range(12))
    assert info["state"] == "finished" and info["frames_processed"] == 12


def test_upload_reports_progress_and_finishes(client, sequence):
    seen = []
    info = client.upload(sequence, progress=lambda sent, total: seen.append((sent, total)))
    assert info["kind"] == "upload"
    assert seen and seen[-1][0] == seen[-1][1] and all(a <= b for (a, _), (b, _) in zip(seen, seen[1:]))
    finished = client.wait_finished(info["id"], timeout=600)
    assert finished["frames_processed"] == tum_rows(sequence, "rgb.txt")
    results = client.fetch(info["id"])
    assert results.trajectory.shape[0] > 0


def test_maps_are_saved_listed_and_localised_in(client, sequence):
    list(client.stream_folder(sequence))
    saved = client.save_map(client.last_session, name="py-sdk")
    assert any(m["id"] == saved["id"] for m in client.maps())
    poses = list(client.stream_folder(sequence, map_id=saved["id"]))
    assert sum(p.state != "lost" for p in poses) > len(poses) // 2
    client.delete_map(saved["id"])
    assert all(m["id"] != saved["id"] for m in client.maps())


def test_errors_carry_the_service_code(client, url, sequence):
    with pytest.raises(relfusion.NotFound) as missing:
        client.session("no-such-session")
    assert missing.value.status == 404 and missing.value.code == "not_found"
    with pytest.raises(relfusion.BadRequest) as bad:
        client.create_session(relfusion.Camera(500, 500, 160, 120, 0, 240))
    assert bad.value.status == 400 and bad.value.code == "invalid_argument" and bad.value.message
    # This server has no [ros2]: a session on ROS 2 is refused with the reason.
    with pytest.raises(relfusion.BadRequest) as no_ros2:
        client.create_session(relfusion.Camera(500, 500, 160, 120, 320, 240), ros2={"publish": True})
    assert "ros2" in no_ros2.value.message
    with relfusion.Client(url, "not-a-token") as stranger:
        with pytest.raises(relfusion.Unauthorized):
            stranger.sessions()
    with relfusion.Client("http://127.0.0.1:1") as nobody:
        with pytest.raises(relfusion.RelfusionError) as unreachable:
            nobody.version()
    assert unreachable.value.status == 0


def test_png_encoding_round_trips():
    image = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    png = relfusion.png_bytes(image)
    assert png.startswith(b"\x89PNG")
    width, height = struct.unpack(">II", png[16:24])
    assert (width, height) == (5, 4)
    idat = png.index(b"IDAT")
    (length,) = struct.unpack(">I", png[idat - 4 : idat])
    raw = zlib.decompress(png[idat + 4 : idat + 4 + length])
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(4, 1 + 15)
    assert np.all(rows[:, 0] == 0) and np.array_equal(rows[:, 1:].reshape(4, 5, 3), image)
    with pytest.raises(TypeError):
        relfusion.png_bytes(image.astype(np.float32))
