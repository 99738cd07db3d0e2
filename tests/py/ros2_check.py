"""A ROS 2 robot on rmw_zenoh, played with third-party parts: `eclipse-zenoh` for the network
and `pycdr2` (Cyclone DDS's CDR codec) with the ROS 2 message definitions written out below.
Keys, attachments and liveliness tokens follow rmw_zenoh's design document; nothing here is
relfusion's code.

    ros2_check.py listen ENDPOINT DOMAIN NAMESPACE
        Subscribes to the session's topics under NAMESPACE, prints "ready", and collects
        until stdin closes; then prints a JSON summary: per topic the messages decoded, the
        poses, the last path, the attachments' sequence numbers and GIDs, the clouds' and
        markers' sizes, and the liveliness tokens found (parsed as `ros2 node list` and
        `ros2 topic list` would).
    ros2_check.py bag FILE.mcap
        A ROS 2 bag (`--mcap-ros2`) read with `mcap` and `mcap-ros2-support` (the decoder
        rosbags of ROS 2 are read with): every message decoded from its `ros2msg` schema;
        prints the counts per topic, the schemas, and a few decoded fields.
    ros2_check.py camera ENDPOINT DOMAIN NAMESPACE FRAMES.json
        A camera: publishes `camera_info` every 100 ms from the start, and, once a subscription
        of `image_raw` appears in the graph (its liveliness token), every frame of FRAMES.json
        (raw RGB files and their times) as `sensor_msgs/Image`; prints a JSON summary.
"""

import json
import struct
import sys
import threading
import time
from dataclasses import dataclass, field

import zenoh
from pycdr2 import IdlStruct
from pycdr2.types import array, float32, float64, int32, sequence, uint8, uint32

# --- the message definitions (ROS 2 Jazzy/Kilted) ---------------------------------------


def dds(name):
    package, kind, short = name.split("/")
    return f"{package}::{kind}::dds_::{short}_"


@dataclass
class Time(IdlStruct, typename=dds("builtin_interfaces/msg/Time")):
    sec: int32
    nanosec: uint32


@dataclass
class Duration(IdlStruct, typename=dds("builtin_interfaces/msg/Duration")):
    sec: int32
    nanosec: uint32


@dataclass
class Header(IdlStruct, typename=dds("std_msgs/msg/Header")):
    stamp: Time
    frame_id: str


@dataclass
class Point(IdlStruct, typename=dds("geometry_msgs/msg/Point")):
    x: float64
    y: float64
    z: float64


@dataclass
class Vector3(IdlStruct, typename=dds("geometry_msgs/msg/Vector3")):
    x: float64
    y: float64
    z: float64


@dataclass
class Quaternion(IdlStruct, typename=dds("geometry_msgs/msg/Quaternion")):
    x: float64
    y: float64
    z: float64
    w: float64


@dataclass
class Pose(IdlStruct, typename=dds("geometry_msgs/msg/Pose")):
    position: Point
    orientation: Quaternion


@dataclass
class PoseStamped(IdlStruct, typename=dds("geometry_msgs/msg/PoseStamped")):
    header: Header
    pose: Pose


@dataclass
class Path(IdlStruct, typename=dds("nav_msgs/msg/Path")):
    header: Header
    poses: sequence[PoseStamped]


@dataclass
class Transform(IdlStruct, typename=dds("geometry_msgs/msg/Transform")):
    translation: Vector3
    rotation: Quaternion


@dataclass
class TransformStamped(IdlStruct, typename=dds("geometry_msgs/msg/TransformStamped")):
    header: Header
    child_frame_id: str
    transform: Transform


@dataclass
class TFMessage(IdlStruct, typename=dds("tf2_msgs/msg/TFMessage")):
    transforms: sequence[TransformStamped]


@dataclass
class PointField(IdlStruct, typename=dds("sensor_msgs/msg/PointField")):
    name: str
    offset: uint32
    datatype: uint8
    count: uint32


@dataclass
class PointCloud2(IdlStruct, typename=dds("sensor_msgs/msg/PointCloud2")):
    header: Header
    height: uint32
    width: uint32
    fields: sequence[PointField]
    is_bigendian: bool
    point_step: uint32
    row_step: uint32
    data: sequence[uint8]
    is_dense: bool


@dataclass
class ColorRGBA(IdlStruct, typename=dds("std_msgs/msg/ColorRGBA")):
    r: float32
    g: float32
    b: float32
    a: float32


@dataclass
class CompressedImage(IdlStruct, typename=dds("sensor_msgs/msg/CompressedImage")):
    header: Header
    format: str
    data: sequence[uint8]


@dataclass
class UVCoordinate(IdlStruct, typename=dds("visualization_msgs/msg/UVCoordinate")):
    u: float32
    v: float32


@dataclass
class MeshFile(IdlStruct, typename=dds("visualization_msgs/msg/MeshFile")):
    filename: str
    data: sequence[uint8]


@dataclass
class Marker(IdlStruct, typename=dds("visualization_msgs/msg/Marker")):
    header: Header
    ns: str
    id: int32
    type: int32
    action: int32
    pose: Pose
    scale: Vector3
    color: ColorRGBA
    lifetime: Duration
    frame_locked: bool
    points: sequence[Point]
    colors: sequence[ColorRGBA]
    texture_resource: str
    texture: CompressedImage
    uv_coordinates: sequence[UVCoordinate]
    text: str
    mesh_resource: str
    mesh_file: MeshFile
    mesh_use_embedded_materials: bool


@dataclass
class MarkerArray(IdlStruct, typename=dds("visualization_msgs/msg/MarkerArray")):
    markers: sequence[Marker]


@dataclass
class Image(IdlStruct, typename=dds("sensor_msgs/msg/Image")):
    header: Header
    height: uint32
    width: uint32
    encoding: str
    is_bigendian: uint8
    step: uint32
    data: sequence[uint8]


@dataclass
class RegionOfInterest(IdlStruct, typename=dds("sensor_msgs/msg/RegionOfInterest")):
    x_offset: uint32
    y_offset: uint32
    height: uint32
    width: uint32
    do_rectify: bool


@dataclass
class CameraInfo(IdlStruct, typename=dds("sensor_msgs/msg/CameraInfo")):
    header: Header
    height: uint32
    width: uint32
    distortion_model: str
    d: sequence[float64]
    k: array[float64, 9]
    r: array[float64, 9]
    p: array[float64, 12]
    binning_x: uint32
    binning_y: uint32
    roi: RegionOfInterest


# The RIHS01 hashes REP-2011 publishes for these types (Kilted's generated description files;
# unchanged since Jazzy): a key with another hash is another definition.
HASHES = {
    "geometry_msgs/msg/PoseStamped": "10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
    "nav_msgs/msg/Path": "1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b",
    "tf2_msgs/msg/TFMessage": "e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    "sensor_msgs/msg/PointCloud2": "9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5",
    "sensor_msgs/msg/Image": "d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/CameraInfo": "b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275",
}

TOPICS = {
    "pose": ("geometry_msgs/msg/PoseStamped", PoseStamped),
    "tf": ("tf2_msgs/msg/TFMessage", TFMessage),
    "path": ("nav_msgs/msg/Path", Path),
    "points": ("sensor_msgs/msg/PointCloud2", PointCloud2),
    "mesh": ("visualization_msgs/msg/MarkerArray", MarkerArray),
}


def key(domain, topic, type_name):
    """rmw_zenoh's key of a topic; the MarkerArray hash is matched by a wildcard."""
    digest = HASHES.get(type_name)
    return f"{domain}/{topic.strip('/')}/{dds(type_name)}/" + (f"RIHS01_{digest}" if digest else "*")


def session(endpoint):
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


def attachment(sample):
    """(sequence number, source time ns, GID hex) of rmw_zenoh's 33-byte attachment."""
    raw = sample.attachment.to_bytes() if sample.attachment is not None else b""
    if len(raw) != 33 or raw[16] != 16:
        raise ValueError(f"attachment of {len(raw)} bytes: {raw.hex()}")
    seq, stamp = struct.unpack_from("<qq", raw)
    return seq, stamp, raw[17:].hex()


def parse_token(key_expr):
    """A liveliness token as rmw_zenoh's graph cache reads it."""
    parts = str(key_expr).split("/")
    unmangle = lambda s: "/" if s == "%" else s.replace("%", "/")
    entity = {
        "key": str(key_expr),
        "domain": int(parts[1]),
        "zid": parts[2],
        "node_id": int(parts[3]),
        "id": int(parts[4]),
        "kind": parts[5],
        "enclave": unmangle(parts[6]),
        "namespace": unmangle(parts[7]),
        "node": parts[8],
    }
    if entity["kind"] in ("MP", "MS", "SS", "SC"):
        entity.update(
            topic=unmangle(parts[9]),
            type=parts[10],
            hash=parts[11],
            qos=parts[12],
        )
    return entity


def stamp_ns(header):
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def listen(endpoint, domain, namespace):
    z = session(endpoint)
    lock = threading.Lock()
    got = {name: {"count": 0, "sequences": [], "gids": set(), "errors": []} for name in TOPICS}
    poses, last_path, clouds, markers, tf_children = [], [], [], {"add": 0, "delete": 0, "vertices": 0}, set()

    def handler(name, cls):
        def on_sample(sample):
            with lock:
                entry = got[name]
                try:
                    seq, _, gid = attachment(sample)
                    msg = cls.deserialize(sample.payload.to_bytes())
                except Exception as e:  # noqa: BLE001 - every failure is reported
                    entry["errors"].append(repr(e))
                    return
                entry["count"] += 1
                entry["sequences"].append(seq)
                entry["gids"].add(gid)
                if name == "pose":
                    p = msg.pose
                    poses.append([stamp_ns(msg.header), p.position.x, p.position.y, p.position.z,
                                  p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w,
                                  msg.header.frame_id])
                elif name == "path":
                    last_path[:] = [[ps.pose.position.x, ps.pose.position.y, ps.pose.position.z]
                                    for ps in msg.poses]
                elif name == "tf":
                    for t in msg.transforms:
                        tf_children.add(f"{t.header.frame_id}->{t.child_frame_id}")
                elif name == "points":
                    ok = (msg.point_step == 12 and [f.name for f in msg.fields] == ["x", "y", "z"]
                          and len(msg.data) == msg.width * 12)
                    clouds.append({"points": msg.width, "well_formed": ok, "frame": msg.header.frame_id})
                elif name == "mesh":
                    for m in msg.markers:
                        if m.action == 0 and m.type == 11:
                            markers["add"] += 1
                            markers["vertices"] += len(m.points)
                            assert len(m.points) % 3 == 0 and len(m.colors) == len(m.points)
                        elif m.action == 2:
                            markers["delete"] += 1
        return on_sample

    subscribers = [
        z.declare_subscriber(key(domain, f"{namespace}/{name}", type_name), handler(name, cls))
        for name, (type_name, cls) in TOPICS.items()
    ]
    tokens = {}

    def on_token(sample):
        with lock:
            if sample.kind == zenoh.SampleKind.PUT:
                tokens[str(sample.key_expr)] = True

    # What rmw_zenoh does at start: a liveliness subscription with history on its domain.
    live = z.liveliness().declare_subscriber(f"@ros2_lv/{domain}/**", on_token, history=True)
    print("ready", flush=True)
    sys.stdin.read()
    time.sleep(0.5)
    # And what a late `ros2 node list` does: ask for the tokens alive now.
    alive = [str(reply.ok.key_expr) for reply in z.liveliness().get(f"@ros2_lv/{domain}/**", timeout=5) if reply.ok]
    with lock:
        summary = {
            "topics": {name: {"count": e["count"], "errors": e["errors"][:5],
                              "sequences_ok": e["sequences"] == list(range(1, len(e["sequences"]) + 1)),
                              # Where they first break, to tell a missed message from a reordered one.
                              "sequences_break": next(([i, s] for i, s in enumerate(e["sequences"], 1) if s != i), None),
                              "gids": sorted(e["gids"])}
                       for name, e in got.items()},
            "poses": poses,
            "last_path": last_path,
            "clouds": clouds,
            "markers": markers,
            "tf": sorted(tf_children),
            "tokens_seen": [parse_token(k) for k in sorted(tokens)],
            "tokens_alive": [parse_token(k) for k in sorted(alive)],
        }
    for s in subscribers:
        s.undeclare()
    live.undeclare()
    z.close()
    print(json.dumps(summary))


def camera(endpoint, domain, namespace, frames_file):
    spec = json.load(open(frames_file))
    z = session(endpoint)
    width, height = spec["width"], spec["height"]
    fx, fy, cx, cy = spec["intrinsics"]
    image_topic = f"{namespace}/camera/image_raw"
    info_key = key(domain, f"{namespace}/camera/camera_info", "sensor_msgs/msg/CameraInfo")
    image_key = key(domain, image_topic, "sensor_msgs/msg/Image")
    zid = str(z.info.zid())
    # Our own node and publishers in the graph, as a camera driver on rmw_zenoh has them.
    mangled = namespace.replace("/", "%")
    qos = "::,10:,:,:,,"
    tokens = [z.liveliness().declare_token(f"@ros2_lv/{domain}/{zid}/0/0/NN/%/{mangled}/camera")]
    publishers = {}
    for eid, (topic, type_name) in enumerate(
            [(f"{namespace}/camera/camera_info", "sensor_msgs/msg/CameraInfo"),
             (image_topic, "sensor_msgs/msg/Image")], start=1):
        token = (f"@ros2_lv/{domain}/{zid}/0/{eid}/MP/%/{mangled}/camera/{topic.replace('/', '%')}/"
                 f"{dds(type_name)}/RIHS01_{HASHES[type_name]}/{qos}")
        tokens.append(z.liveliness().declare_token(token))
        gid = bytes(16)  # rmw_zenoh's is a hash of the token; any 16 bytes are a valid GID here
        publishers[topic] = [z.declare_publisher(key(domain, topic, type_name),
                                                 congestion_control=zenoh.CongestionControl.BLOCK), gid, 0]

    def put(topic, payload):
        entry = publishers[topic]
        entry[2] += 1
        att = struct.pack("<qq", entry[2], time.time_ns()) + bytes([16]) + entry[1]
        entry[0].put(payload, attachment=att)

    def header(t):
        return Header(stamp=Time(sec=int(t), nanosec=int(round((t - int(t)) * 1e9)) % 1_000_000_000), frame_id="camera")

    stop = threading.Event()

    def info_loop():
        info = CameraInfo(
            header=header(0.0), height=height, width=width, distortion_model="plumb_bob",
            d=[0.0] * 5, k=[fx, 0, cx, 0, fy, cy, 0, 0, 1], r=[1, 0, 0, 0, 1, 0, 0, 0, 1],
            p=[fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], binning_x=0, binning_y=0,
            roi=RegionOfInterest(0, 0, 0, 0, False))
        while not stop.is_set():
            put(f"{namespace}/camera/camera_info", info.serialize())
            stop.wait(0.1)

    threading.Thread(target=info_loop, daemon=True).start()
    # Wait until a subscription of the image topic is in the graph.
    deadline = time.time() + 60
    subscriber = None
    while time.time() < deadline and subscriber is None:
        for reply in z.liveliness().get(f"@ros2_lv/{domain}/**", timeout=2):
            if reply.ok:
                t = parse_token(reply.ok.key_expr)
                if t["kind"] == "MS" and t.get("topic") == image_topic:
                    subscriber = t
        if subscriber is None:
            time.sleep(0.2)
    sent = 0
    if subscriber is not None:
        for frame in spec["frames"]:
            rgb = open(frame["rgb"], "rb").read()
            msg = Image(header=header(frame["timestamp"]), height=height, width=width,
                        encoding="rgb8", is_bigendian=0, step=width * 3, data=rgb)
            put(image_topic, msg.serialize())
            sent += 1
    stop.set()
    time.sleep(0.3)
    for t in tokens:
        t.undeclare()
    z.close()
    print(json.dumps({"subscriber": subscriber, "frames_sent": sent}))


def bag(path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    counts, schemas, first = {}, {}, {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            schemas[channel.topic] = [schema.name, schema.encoding, channel.message_encoding]
            if channel.topic not in first:
                if channel.topic == "/camera/camera_info":
                    first[channel.topic] = {"width": decoded.width, "k": list(decoded.k)}
                elif channel.topic == "/camera/image/compressed":
                    first[channel.topic] = {"format": decoded.format, "bytes": len(decoded.data)}
                elif channel.topic == "/relfusion/pose":
                    first[channel.topic] = {"frame_id": decoded.header.frame_id}
    print(json.dumps({"counts": counts, "schemas": schemas, "first": first}))


if __name__ == "__main__":
    if sys.argv[1] == "bag":
        bag(sys.argv[2])
        sys.exit(0)
    mode, endpoint, domain, namespace = sys.argv[1:5]
    if mode == "listen":
        listen(endpoint, int(domain), namespace)
    elif mode == "camera":
        camera(endpoint, int(domain), namespace, sys.argv[5])
    else:
        sys.exit(f"unknown mode {mode}")
