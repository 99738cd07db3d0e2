// The wire schema, read from the server itself: GET /v1/proto lists the .proto files in
// dependency order and each is parsed here, so the page always decodes what the server speaks.

import protobuf from "protobufjs";
import { getJson, getText } from "./api.js";

/** Loads the schema; resolves to the message types the viewer decodes. */
export async function loadWire() {
  const { files } = await getJson("/v1/proto");
  const root = new protobuf.Root();
  for (const file of files) {
    const source = await getText(`/v1/proto/${file}`);
    protobuf.parse(source, root, { keepCase: false });
  }
  root.resolveAll();
  return {
    ServerMessage: root.lookupType("relfusion.v1.ServerMessage"),
    MapSnapshot: root.lookupType("relfusion.v1.MapSnapshot"),
    TrackingState: root.lookupEnum("relfusion.v1.TrackingState"),
  };
}

/** A 64-bit field as a number (protobufjs gives a Long when long.js is bundled). */
export function num(value) {
  if (value === null || value === undefined) return 0;
  return typeof value === "number" ? value : Number(value.toString());
}

/** `bytes` of little-endian float32 as a Float32Array (copied: the field may be unaligned). */
export function float32s(bytes) {
  const copy = new Uint8Array(bytes.length);
  copy.set(bytes);
  return new Float32Array(copy.buffer, 0, Math.floor(bytes.length / 4));
}

/** A Sim3Pose as `{t, q, s}`. */
export function pose(p) {
  const t = p && p.translation ? p.translation : { x: 0, y: 0, z: 0 };
  const q = p && p.rotation ? p.rotation : { x: 0, y: 0, z: 0, w: 1 };
  const s = p && p.scale ? p.scale : 1;
  return { t: [t.x || 0, t.y || 0, t.z || 0], q: [q.x || 0, q.y || 0, q.z || 0, q.w || 0], s };
}
