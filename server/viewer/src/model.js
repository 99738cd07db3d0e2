// The viewer's copy of a session's map, assembled from a MapSnapshot and the stream's updates
// with no gap and no duplicate: trajectory entries keyed by timestamp and kept in time order,
// keyframes by id (or, from a snapshot, by timestamp), mesh blocks by index at a revision.

import { poseMatrix, THREE } from "./scene.js";
import { float32s, num, pose } from "./wire.js";

/** Most dense points drawn per keyframe: a step over the depth map keeps within it. */
const POINTS_PER_KEYFRAME = 20000;

export class MapModel {
  constructor(scene) {
    this.scene = scene;
    /** [{i, timestamp, position: Vector3, keyframe, rel: Matrix4|null}] in time order (i: index) */
    this.frames = [];
    this.frameIndex = new Map();
    this.keyframesById = new Map();
    this.keyframesByTs = new Map();
    this.keyframeCount = 0;
    this.meshRevision = 0;
    this.aspect = null;
  }

  // ---- trajectory ----

  /** Adds or moves the frame at `timestamp`; returns its entry. */
  putFrame(timestamp, position) {
    let entry = this.frameIndex.get(timestamp);
    if (entry) {
      entry.position.copy(position);
      this.scene.setTrajectoryPoint(entry.i, position);
      return entry;
    }
    entry = { timestamp, position: position.clone(), keyframe: null, rel: null };
    this.frameIndex.set(timestamp, entry);
    let i = this.frames.length;
    while (i > 0 && this.frames[i - 1].timestamp > timestamp) i -= 1;
    this.frames.splice(i, 0, entry);
    // Out-of-order inserts (a resync) rewrite the line from there on.
    for (let j = i; j < this.frames.length; j++) {
      this.frames[j].i = j;
      this.scene.setTrajectoryPoint(j, this.frames[j].position);
    }
    return entry;
  }

  onPose(update, lost) {
    const matrix = poseMatrix(pose(update.worldFromCamera));
    this.scene.setCurrentCamera(matrix, this.aspect);
    if (lost) return;
    const position = new THREE.Vector3().setFromMatrixPosition(matrix);
    const entry = this.putFrame(update.timestamp, position);
    const keyframe = this.keyframesById.get(num(update.keyframeId));
    if (keyframe && !update.isKeyframe) {
      entry.keyframe = keyframe;
      entry.rel = keyframe.matrix.clone().invert().multiply(matrix);
      keyframe.frames.add(entry);
    }
  }

  // ---- keyframes ----

  keyframeEntry(id, timestamp) {
    let entry = id !== null ? this.keyframesById.get(id) : undefined;
    if (!entry) entry = this.keyframesByTs.get(timestamp);
    if (!entry) {
      entry = { id, timestamp, index: this.keyframeCount++, matrix: new THREE.Matrix4(), frames: new Set() };
      this.keyframesByTs.set(timestamp, entry);
    }
    if (id !== null && entry.id === null) entry.id = id;
    if (id !== null) this.keyframesById.set(id, entry);
    return entry;
  }

  /** A keyframe was made or moved: move its marker, the frames tracked on it, its points. */
  setKeyframePose(id, timestamp, matrix) {
    const entry = this.keyframeEntry(id, timestamp);
    entry.matrix.copy(matrix);
    this.scene.setKeyframeMarker(entry.index, new THREE.Vector3().setFromMatrixPosition(matrix));
    for (const frame of entry.frames) {
      const moved = matrix.clone().multiply(frame.rel);
      this.putFrame(frame.timestamp, new THREE.Vector3().setFromMatrixPosition(moved));
    }
    this.scene.moveKeyframePoints(entry.index, matrix);
    return entry;
  }

  onKeyframe(update) {
    const matrix = poseMatrix(pose(update.worldFromCamera));
    const entry = this.setKeyframePose(num(update.keyframeId), update.timestamp, matrix);
    if (update.depth) this.setDepth(entry, update.depth);
  }

  /** Back-projects a keyframe's dense inverse depth into points in the keyframe's frame. */
  setDepth(entry, depth) {
    const w = depth.width;
    const h = depth.height;
    const c = depth.camera;
    if (!c || !w || !h || !(c.fx > 0) || !(c.fy > 0)) return;
    this.aspect = w / h;
    const inv = float32s(depth.inverseDepth);
    if (inv.length !== w * h) return;
    const step = Math.max(1, Math.ceil(Math.sqrt((w * h) / POINTS_PER_KEYFRAME)));
    const out = [];
    for (let y = 0; y < h; y += step) {
      for (let x = 0; x < w; x += step) {
        const d = inv[y * w + x];
        if (!(d > 0) || !Number.isFinite(d)) continue;
        out.push((x - c.cx) / c.fx / d, (y - c.cy) / c.fy / d, 1 / d);
      }
    }
    this.scene.setKeyframePoints(entry.index, new Float32Array(out), entry.matrix);
  }

  // ---- mesh ----

  /** Applies a MeshUpdate; false when it does not follow the current revision (a gap). */
  onMesh(update) {
    const revision = num(update.revision);
    if (revision <= this.meshRevision) return true; // already in the snapshot
    if (revision !== this.meshRevision + 1) return false;
    this.applyBlocks(update.changedBlocks, update.removedBlocks);
    this.meshRevision = revision;
    return true;
  }

  applyBlocks(changed, removed) {
    for (const b of removed || []) this.scene.removeBlock(blockKey(b));
    for (const b of changed || []) {
      const indices = Uint32Array.from(b.indices || []);
      const colors = new Uint8Array(b.colors ? b.colors.length : 0);
      if (b.colors) colors.set(b.colors);
      this.scene.setBlock(blockKey(b.index), float32s(b.vertices), colors, float32s(b.normals), indices);
    }
  }

  // ---- snapshots and final results ----

  /** Takes in a MapSnapshot: the whole map at its mesh revision. */
  onSnapshot(snapshot) {
    for (const p of snapshot.trajectory) {
      const m = poseMatrix(pose(p.worldFromCamera));
      this.putFrame(p.timestamp, new THREE.Vector3().setFromMatrixPosition(m));
    }
    for (const k of snapshot.keyframes) {
      if (!this.keyframesByTs.has(k.timestamp)) {
        this.setKeyframePose(null, k.timestamp, poseMatrix(pose(k.worldFromCamera)));
      }
    }
    const revision = num(snapshot.meshRevision);
    if (revision >= this.meshRevision) {
      this.scene.clearMesh();
      this.applyBlocks(snapshot.meshBlocks, []);
      this.meshRevision = revision;
    }
  }

  /** Replaces the trajectory and keyframes with final ones ([{timestamp, t, q, s}]). */
  setFinal(trajectory, keyframes) {
    this.frames = [];
    this.frameIndex.clear();
    this.keyframesById.clear();
    this.keyframesByTs.clear();
    this.keyframeCount = 0;
    this.scene.clearTrajectory();
    for (const p of trajectory) {
      const m = poseMatrix(p);
      this.putFrame(p.timestamp, new THREE.Vector3().setFromMatrixPosition(m));
    }
    for (const k of keyframes) this.setKeyframePose(null, k.timestamp, poseMatrix(k));
    if (trajectory.length > 0) this.scene.setCurrentCamera(poseMatrix(trajectory[trajectory.length - 1]), this.aspect);
  }
}

function blockKey(b) {
  return `${b ? b.x || 0 : 0},${b ? b.y || 0 : 0},${b ? b.z || 0 : 0}`;
}
