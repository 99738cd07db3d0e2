"""Reads what relfusion gives Foxglove users, with their own tools, and prints a JSON summary.

    foxglove_check.py mcap FILE.mcap
        Reads the file with the `mcap` package and its protobuf decoder (the schemas embedded in
        the file): per topic the schema and the message count, and what the messages add up to
        (keyframe frames in /tf, the mesh after every SceneUpdate, points per cloud).

    foxglove_check.py ws URL [SECONDS [SUBPROTOCOLS]]
        Connects as a Foxglove viewer does, offering SUBPROTOCOLS (comma-separated; default
        foxglove.websocket.v1, the protocol's published name, which Lichtblick and older
        Foxglove apps offer alone; the current app also offers foxglove.sdk.v1), reads the
        advertised channels, subscribes to all of them, and decodes messages with the
        advertised protobuf schemas until every channel gave one (or SECONDS pass).

The Rust tests (tests/tests/recordings.rs) compare the summaries with the session's own files.
"""

import asyncio
import base64
import json
import struct
import sys
import time
from collections import Counter


def mesh_state(updates):
    """Entity id -> triangles after applying every SceneUpdate in order."""
    blocks = {}
    for update in updates:
        for deletion in update.deletions:
            if deletion.type == 0:  # MATCHING_ID
                blocks.pop(deletion.id, None)
            else:
                blocks.clear()
        for entity in update.entities:
            blocks[entity.id] = sum(len(t.indices) // 3 for t in entity.triangles)
    return blocks


def read_mcap(path):
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    counts = Counter()
    schemas = {}
    encodings = {}
    keyframe_frames = set()
    camera_transforms = 0
    mesh_updates = []
    cloud_points = []
    last_time = {}
    times_ordered = True
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            topic = channel.topic
            counts[topic] += 1
            schemas[topic] = schema.name
            encodings[topic] = channel.message_encoding
            if message.log_time < last_time.get(topic, 0):
                times_ordered = False
            last_time[topic] = message.log_time
            if topic == "/tf":
                for t in decoded.transforms:
                    if t.child_frame_id.startswith("keyframe_"):
                        keyframe_frames.add(t.child_frame_id)
                    elif t.child_frame_id == "camera":
                        camera_transforms += 1
            elif topic == "/mesh":
                mesh_updates.append(decoded)
            elif topic == "/keyframes/points":
                cloud_points.append(len(decoded.data) // max(decoded.point_stride, 1))
            elif topic == "/camera/image":
                assert decoded.format in ("png", "jpeg"), decoded.format
            elif topic == "/trajectory":
                assert decoded.frame_id == "world"
    blocks = mesh_state(mesh_updates)
    return {
        "mesh_entities_total": sum(len(u.entities) for u in mesh_updates),
        "mesh_deletions_total": sum(len(u.deletions) for u in mesh_updates),
        "counts": dict(counts),
        "schemas": schemas,
        "encodings": encodings,
        "indexed_channels": len(summary.channels) if summary else 0,
        "times_ordered_per_topic": times_ordered,
        "keyframe_frames": len(keyframe_frames),
        "camera_transforms": camera_transforms,
        "mesh_blocks": len(blocks),
        "mesh_triangles": sum(blocks.values()),
        "clouds": len(cloud_points),
        "cloud_points_max": max(cloud_points, default=0),
    }


def message_class(schema_name, schema_b64):
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64))
    pool = descriptor_pool.DescriptorPool()
    pending = list(fds.file)
    # Add files once their dependencies are in (the set's order is not promised).
    while pending:
        added = False
        for fd in list(pending):
            try:
                pool.Add(fd)
                pending.remove(fd)
                added = True
            except Exception:
                pass
        if not added:
            raise RuntimeError(f"cannot load the schema of {schema_name}")
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))


async def read_ws(url, seconds, subprotocols):
    import websockets

    got = {}
    async with websockets.connect(
        url,
        subprotocols=subprotocols,
        max_size=None,
        open_timeout=10,
    ) as ws:
        subprotocol = ws.subprotocol
        server_info = None
        channels = {}
        deadline = time.monotonic() + seconds
        subscribed = {}
        while time.monotonic() < deadline:
            try:
                raw = await asyncio.wait_for(ws.recv(), timeout=max(0.1, deadline - time.monotonic()))
            except (asyncio.TimeoutError, websockets.ConnectionClosed):
                break
            if isinstance(raw, str):
                op = json.loads(raw)
                if op["op"] == "serverInfo":
                    server_info = op
                elif op["op"] == "advertise":
                    subs = []
                    for ch in op["channels"]:
                        assert ch["encoding"] == "protobuf", ch
                        sub_id = len(subscribed) + 1
                        channels[ch["id"]] = ch
                        subscribed[sub_id] = (ch, message_class(ch["schemaName"], ch["schema"]))
                        subs.append({"id": sub_id, "channelId": ch["id"]})
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                continue
            if raw[0] != 1:  # message data
                continue
            sub_id, log_time = struct.unpack_from("<IQ", raw, 1)
            ch, cls = subscribed[sub_id]
            msg = cls.FromString(raw[13:])
            if ch["topic"] not in got:
                got[ch["topic"]] = {
                    "schema": ch["schemaName"],
                    "log_time": log_time,
                    "bytes": len(raw) - 13,
                    "fields": sorted(f.name for f, _ in msg.ListFields()),
                }
            if len(got) == len(channels) and channels:
                break
    return {
        "subprotocol": subprotocol,
        "server_name": (server_info or {}).get("name"),
        "advertised": sorted(ch["topic"] for ch in channels.values()),
        "received": got,
    }


def main():
    if len(sys.argv) >= 3 and sys.argv[1] == "mcap":
        print(json.dumps(read_mcap(sys.argv[2])))
    elif len(sys.argv) >= 3 and sys.argv[1] == "ws":
        seconds = float(sys.argv[3]) if len(sys.argv) > 3 else 60.0
        offered = (sys.argv[4] if len(sys.argv) > 4 else "foxglove.websocket.v1").split(",")
        print(json.dumps(asyncio.run(read_ws(sys.argv[2], seconds, offered))))
    else:
        sys.exit(__doc__)


if __name__ == "__main__":
    main()
