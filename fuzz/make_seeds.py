#!/usr/bin/env python3
"""Writes the committed seed corpora (small valid inputs for each target). Needs only the
standard library and `cjpeg` (libjpeg-turbo-progs) for the JPEG seed. Run from fuzz/."""
import io, os, struct, subprocess, tarfile, zipfile, zlib

def png(w, h, color_type=2, depth=8):
    channels = {0: 1, 2: 3, 6: 4}[color_type]
    raw = b"".join(b"\0" + bytes((x * 7 + y * 13) % 256 for x in range(w * channels)) for y in range(h))
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", w, h, depth, color_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")

def ppm(w, h):
    return b"P6 %d %d 255\n" % (w, h) + bytes((i * 31) % 256 for i in range(w * h * 3))

def write(path, data):
    with open(path, "wb") as f:
        f.write(data)

# frame_decode: two size bytes (16 + b), then the image.
for w, h, name in [(16, 16, "png16"), (20, 18, "png20x18")]:
    write(f"corpus/frame_decode/{name}", bytes([w - 16, h - 16]) + png(w, h))
write("corpus/frame_decode/png_gray", bytes([0, 0]) + png(16, 16, color_type=0))
jpeg = subprocess.run(["cjpeg", "-quality", "80"], input=ppm(16, 16), capture_output=True, check=True).stdout
write("corpus/frame_decode/jpeg16", bytes([0, 0]) + jpeg)

# proto_messages: hand-encoded protobuf (field tags per proto/relfusion/v1/*.proto).
def varint(n):
    out = b""
    while True:
        b = n & 0x7F
        n >>= 7
        out += bytes([b | (0x80 if n else 0)])
        if not n:
            return out
def field(num, wire, payload):
    tag = varint((num << 3) | wire)
    return tag + (varint(len(payload)) + payload if wire == 2 else payload)
frame = field(1, 0, varint(7)) + field(2, 1, struct.pack("<d", 1.5)) + field(3, 2, png(16, 16))
write("corpus/proto_messages/frame", frame)
write("corpus/proto_messages/client_frame", field(1, 2, frame))
camera = b"".join(field(i, 1, struct.pack("<d", v)) for i, v in [(1, 300.0), (2, 300.0), (3, 160.0), (4, 120.0)]) + field(5, 0, varint(320)) + field(6, 0, varint(240))
write("corpus/proto_messages/session_config", field(1, 2, camera) + field(2, 2, b'{"pipeline":{"deterministic":true}}'))
write("corpus/proto_messages/empty", b"")

# archive_extract: selector byte (even = tar, odd = zip), then the archive.
def tar_bytes(entries):
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.USTAR_FORMAT) as t:
        for name, data in entries:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            t.addfile(info, io.BytesIO(data))
    return buf.getvalue()
def zip_bytes(entries):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in entries:
            z.writestr(name, data)
    return buf.getvalue()
dataset = [("seq/rgb.txt", b"0.0 rgb/0.png\n"), ("seq/calibration.txt", b"20 20 8 8\n"), ("seq/rgb/0.png", png(16, 16))]
write("corpus/archive_extract/tar", b"\0" + tar_bytes(dataset))
write("corpus/archive_extract/zip", b"\1" + zip_bytes(dataset))
write("corpus/archive_extract/tar_dir", b"\0" + tar_bytes([("a/b/c.txt", b"x")]))

# tum_text: each file kind.
write("corpus/tum_text/rgb", b"# color images\n0.000000 rgb/0.png\n0.033333 rgb/1.png\n")
write("corpus/tum_text/calibration", b"# fx fy cx cy k1 k2 p1 p2 k3\n517.3 516.5 318.6 255.3 0.2624 -0.9531 -0.0054 0.0026 1.1633\n")
# tum_list: an rgb.txt, a NUL, a depth.txt (interleaved 30 Hz streams; repeated stamps).
write("corpus/tum_list/interleaved", b"0.000 rgb/0.png\n0.033 rgb/1.png\n0.066 rgb/2.png\n\x00"
      b"0.004 depth/0.png\n0.037 depth/1.png\n0.070 depth/2.png\n")
write("corpus/tum_list/repeated", b"0 rgb/0.png\n0 rgb/0.png\n0 rgb/0.png\n\x000 rgb/0.png\n0 rgb/0.png\n")
write("corpus/tum_text/groundtruth", b"# t tx ty tz qx qy qz qw\n1.0 0.1 0.2 0.3 0 0 0 1\n1.01,0.1,0.2,0.3,0,0,0.7071068,0.7071068\n")

# ros2_messages: a type byte (0 Image, 1 CompressedImage, 2 CameraInfo), then plain CDR
# (little-endian, encapsulation 00 01 00 00; fields aligned to their size after the header).
class Cdr:
    def __init__(self):
        self.b = bytearray(b"\x00\x01\x00\x00")
    def align(self, n):
        while (len(self.b) - 4) % n:
            self.b.append(0)
    def u8(self, v):
        self.b.append(v)
    def u32(self, v):
        self.align(4); self.b += struct.pack("<I", v)
    def i32(self, v):
        self.align(4); self.b += struct.pack("<i", v)
    def f64(self, v):
        self.align(8); self.b += struct.pack("<d", v)
    def string(self, s):
        self.u32(len(s) + 1); self.b += s.encode() + b"\0"
    def raw(self, data):
        self.u32(len(data)); self.b += data
    def header(self):
        self.i32(1); self.u32(500); self.string("camera")
image = Cdr(); image.header(); image.u32(2); image.u32(4); image.string("rgb8"); image.u8(0)
image.u32(12); image.raw(bytes(range(24)))
write("corpus/ros2_messages/image_rgb8", b"\0" + bytes(image.b))
compressed = Cdr(); compressed.header(); compressed.string("png"); compressed.raw(png(16, 16))
write("corpus/ros2_messages/compressed_png", b"\1" + bytes(compressed.b))
info = Cdr(); info.header(); info.u32(480); info.u32(640); info.string("plumb_bob"); info.u32(5)
for v in [0.1, -0.2, 0.0, 0.0, 0.05] + [500, 0, 320, 0, 500, 240, 0, 0, 1] + [1, 0, 0, 0, 1, 0, 0, 0, 1] + [500, 0, 320, 0, 0, 500, 240, 0, 0, 0, 1, 0]:
    info.f64(v)
for _ in range(6):
    info.u32(0)
info.u8(0)
write("corpus/ros2_messages/camera_info", b"\2" + bytes(info.b))
