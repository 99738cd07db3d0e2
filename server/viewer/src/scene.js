// The 3D scene: the fused mesh (one GPU buffer per block, patched from MeshUpdate deltas), the
// trajectory (every tracked frame, re-anchored when the pose graph moves its keyframe),
// keyframe markers, the current camera's frustum and, as an option, keyframe depth points.

import * as THREE from "three";
import { OrbitControls } from "three/examples/jsm/controls/OrbitControls.js";

/** world_from_camera {t, q, s} as a 4x4 similarity matrix: p_world = s R p + t. */
export function poseMatrix(p) {
  return new THREE.Matrix4().compose(
    new THREE.Vector3(p.t[0], p.t[1], p.t[2]),
    new THREE.Quaternion(p.q[0], p.q[1], p.q[2], p.q[3]).normalize(),
    new THREE.Vector3(p.s, p.s, p.s),
  );
}

const BACKGROUND = 0x15181d;

/** Whether WebGL runs on a CPU rasteriser (SwiftShader, llvmpipe): no GPU in this browser. */
function softwareRenderer() {
  try {
    const gl = document.createElement("canvas").getContext("webgl2");
    const info = gl && gl.getExtension("WEBGL_debug_renderer_info");
    const name = info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : "";
    gl?.getExtension("WEBGL_lose_context")?.loseContext();
    return /swiftshader|llvmpipe|software/i.test(name);
  } catch (_) {
    return false;
  }
}

/** A growable line of points (trajectory) or point set (keyframe markers). */
class GrowingPoints {
  constructor(make, color) {
    this.capacity = 1024;
    this.count = 0;
    this.positions = new Float32Array(this.capacity * 3);
    this.geometry = new THREE.BufferGeometry();
    this.attribute = new THREE.BufferAttribute(this.positions, 3);
    this.geometry.setAttribute("position", this.attribute);
    this.geometry.setDrawRange(0, 0);
    this.object = make(this.geometry, color);
    this.object.frustumCulled = false;
  }

  /** Sets point `i` (appending when `i == count`). */
  set(i, v) {
    if (i >= this.capacity) {
      this.capacity = Math.max(this.capacity * 2, i + 1);
      const grown = new Float32Array(this.capacity * 3);
      grown.set(this.positions);
      this.positions = grown;
      this.attribute = new THREE.BufferAttribute(this.positions, 3);
      this.geometry.setAttribute("position", this.attribute);
    }
    this.positions[i * 3] = v.x;
    this.positions[i * 3 + 1] = v.y;
    this.positions[i * 3 + 2] = v.z;
    this.count = Math.max(this.count, i + 1);
    this.geometry.setDrawRange(0, this.count);
    this.attribute.needsUpdate = true;
    this.geometry.boundingBox = null; // recomputed when the view is fitted
    if (i === 0) this.origin = v.clone();
    else if (this.origin) this.extent = Math.max(this.extent || 0, v.distanceTo(this.origin));
  }

  clear() {
    this.count = 0;
    this.origin = null;
    this.extent = 0;
    this.geometry.setDrawRange(0, 0);
  }
}

/** Lines of a camera frustum (apex at the origin, image plane at z = 1) for an aspect ratio. */
function frustumGeometry(aspect) {
  const w = 0.5 * aspect;
  const h = 0.5;
  const c = [[-w, -h], [w, -h], [w, h], [-w, h]];
  const v = [];
  for (let i = 0; i < 4; i++) {
    const [x0, y0] = c[i];
    const [x1, y1] = c[(i + 1) % 4];
    v.push(0, 0, 0, x0, y0, 1, x0, y0, 1, x1, y1, 1);
  }
  const g = new THREE.BufferGeometry();
  g.setAttribute("position", new THREE.Float32BufferAttribute(v, 3));
  return g;
}

export class MapScene {
  constructor(container) {
    this.container = container;
    this.software = softwareRenderer();
    // Multisampling triples the cost of a frame on a software renderer (200k triangles in
    // headless Chromium: 1.8 → 4.4 fps): keep it for real GPUs only.
    this.renderer = new THREE.WebGLRenderer({ antialias: !this.software, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.renderer.setClearColor(BACKGROUND);
    container.appendChild(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(60, 1, 0.01, 1000);
    this.camera.position.set(0, 1.5, -2.5);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.enableDamping = true;
    this.dirty = true;

    // The map's world frame is the first camera's (x right, y down, z forward): turn it so
    // that "down" in the images is down on screen.
    this.world = new THREE.Group();
    this.world.rotation.x = Math.PI;
    this.scene.add(this.world);
    this.grid = new THREE.GridHelper(10, 20, 0x3a4048, 0x262a30);
    this.grid.position.y = -1;
    this.scene.add(this.grid);

    this.meshMaterial = new THREE.MeshBasicMaterial({ vertexColors: true, side: THREE.DoubleSide });
    this.meshGroup = new THREE.Group();
    this.world.add(this.meshGroup);
    /** key "x,y,z" → THREE.Mesh */
    this.blocks = new Map();
    this.triangles = 0;

    this.trajectory = new GrowingPoints(
      (g, color) => new THREE.Line(g, new THREE.LineBasicMaterial({ color })),
      0x4fc3f7,
    );
    this.world.add(this.trajectory.object);
    this.keyframeMarkers = new GrowingPoints(
      (g, color) => new THREE.Points(g, new THREE.PointsMaterial({ color, size: 6, sizeAttenuation: false })),
      0xffa726,
    );
    this.world.add(this.keyframeMarkers.object);

    this.frustum = new THREE.LineSegments(
      frustumGeometry(4 / 3),
      new THREE.LineBasicMaterial({ color: 0xff5252 }),
    );
    this.frustum.matrixAutoUpdate = false;
    this.frustum.visible = false;
    this.world.add(this.frustum);
    this.hasCamera = false;
    this.showCamera = true;

    this.pointsGroup = new THREE.Group();
    this.pointsGroup.visible = false;
    this.world.add(this.pointsGroup);
    /** keyframe id → THREE.Points in the keyframe's frame */
    this.keyframePoints = new Map();

    this.follow = false;
    this.frames = 0;
    this.fps = 0;
    this.fpsWindowStart = performance.now();
    this.fpsWindowFrames = 0;
    this.framedOnce = false;

    const resize = () => {
      const w = container.clientWidth || 640;
      const h = container.clientHeight || 480;
      this.renderer.setSize(w, h, false);
      this.camera.aspect = w / h;
      this.camera.updateProjectionMatrix();
      this.dirty = true;
    };
    new ResizeObserver(resize).observe(container);
    resize();
    const loop = () => {
      this.render();
      requestAnimationFrame(loop);
    };
    requestAnimationFrame(loop);
  }

  /** Draws a frame when something changed or the view moves: an idle map costs no CPU (a
   * software-rendered browser shares the machine with the SLAM pipeline). */
  render() {
    const moving = this.controls.update();
    if (!moving && !this.dirty) return;
    this.dirty = false;
    if (this.follow && this.frustum.visible) {
      const eye = new THREE.Vector3().setFromMatrixPosition(this.frustum.matrixWorld);
      const offset = this.camera.position.clone().sub(this.controls.target);
      this.controls.target.copy(eye);
      this.camera.position.copy(eye).add(offset);
    }
    this.renderer.render(this.scene, this.camera);
    this.frames += 1;
    this.fpsWindowFrames += 1;
    const now = performance.now();
    if (now - this.fpsWindowStart >= 1000) {
      this.fps = (this.fpsWindowFrames * 1000) / (now - this.fpsWindowStart);
      this.fpsWindowStart = now;
      this.fpsWindowFrames = 0;
    }
  }

  // ---- mesh ----

  /** Replaces or adds one MeshBlock (positions, colours, normals as typed arrays). */
  setBlock(key, positions, colors, normals, indices) {
    this.dirty = true;
    this.removeBlock(key);
    if (indices.length === 0) return;
    const g = new THREE.BufferGeometry();
    g.setAttribute("position", new THREE.BufferAttribute(positions, 3));
    if (colors.length === positions.length) {
      g.setAttribute("color", new THREE.BufferAttribute(colors, 3, true));
    }
    if (normals.length === positions.length) g.setAttribute("normal", new THREE.BufferAttribute(normals, 3));
    g.setIndex(new THREE.BufferAttribute(indices, 1));
    g.computeBoundingSphere();
    const mesh = new THREE.Mesh(g, this.meshMaterial);
    this.meshGroup.add(mesh);
    this.blocks.set(key, mesh);
    this.triangles += indices.length / 3;
  }

  removeBlock(key) {
    this.dirty = true;
    const old = this.blocks.get(key);
    if (!old) return;
    this.triangles -= old.geometry.index.count / 3;
    this.meshGroup.remove(old);
    old.geometry.dispose();
    this.blocks.delete(key);
  }

  clearMesh() {
    this.dirty = true;
    for (const key of [...this.blocks.keys()]) this.removeBlock(key);
    if (this.gltf) {
      this.meshGroup.remove(this.gltf);
      this.gltf.traverse((o) => o.isMesh && o.geometry.dispose());
      this.gltf = null;
      this.triangles = 0;
    }
  }

  /** Shows a finished session's mesh.glb in place of the blocks. */
  setGltfScene(gltfScene) {
    this.dirty = true;
    this.clearMesh();
    let triangles = 0;
    gltfScene.traverse((o) => {
      if (o.isMesh) {
        o.material = new THREE.MeshBasicMaterial({
          vertexColors: !!o.geometry.getAttribute("color"),
          side: THREE.DoubleSide,
        });
        const g = o.geometry;
        triangles += (g.index ? g.index.count : g.getAttribute("position").count) / 3;
      }
    });
    this.meshGroup.add(gltfScene);
    this.gltf = gltfScene;
    this.triangles = triangles;
  }

  // ---- trajectory, keyframes, frustum ----

  setTrajectoryPoint(i, position) {
    this.dirty = true;
    this.trajectory.set(i, position);
  }

  setKeyframeMarker(i, position) {
    this.dirty = true;
    this.keyframeMarkers.set(i, position);
  }

  clearTrajectory() {
    this.dirty = true;
    this.trajectory.clear();
    this.keyframeMarkers.clear();
  }

  /** Places the current camera's frustum; its size follows the trajectory's extent. */
  setCurrentCamera(matrix, aspect) {
    this.dirty = true;
    if (aspect && Math.abs(aspect - (this.frustumAspect || 4 / 3)) > 1e-3) {
      this.frustum.geometry.dispose();
      this.frustum.geometry = frustumGeometry(aspect);
      this.frustumAspect = aspect;
    }
    const size = Math.max(0.05, Math.min(0.5, (this.trajectory.extent || 1) * 0.08));
    this.frustum.matrix.copy(matrix).multiply(new THREE.Matrix4().makeScale(size, size, size));
    this.frustum.matrixWorldNeedsUpdate = true;
    this.hasCamera = true;
    this.frustum.visible = this.showCamera;
  }

  /** Dense depth points of a keyframe, in its own frame (they move with the keyframe). */
  setKeyframePoints(id, points, matrix) {
    this.dirty = true;
    const old = this.keyframePoints.get(id);
    if (old) {
      this.pointsGroup.remove(old);
      old.geometry.dispose();
    }
    const g = new THREE.BufferGeometry();
    g.setAttribute("position", new THREE.BufferAttribute(points, 3));
    const p = new THREE.Points(g, new THREE.PointsMaterial({ color: 0xb0bec5, size: 2, sizeAttenuation: false }));
    p.matrixAutoUpdate = false;
    p.matrix.copy(matrix);
    this.pointsGroup.add(p);
    this.keyframePoints.set(id, p);
  }

  moveKeyframePoints(id, matrix) {
    this.dirty = true;
    const p = this.keyframePoints.get(id);
    if (p) {
      p.matrix.copy(matrix);
      p.matrixWorldNeedsUpdate = true;
    }
  }

  /** Points the view at what is shown (once, when the map first has extent; again on
   * "fit view"), from behind and above the first camera. */
  frameAll(force = false) {
    this.dirty = true;
    if (this.framedOnce && !force) return;
    const box = new THREE.Box3();
    this.world.updateMatrixWorld(true);
    for (const layer of [this.meshGroup, this.trajectory.object, this.keyframeMarkers.object, this.pointsGroup]) {
      if (layer.visible) box.union(new THREE.Box3().setFromObject(layer));
    }
    if (box.isEmpty()) return;
    const sphere = box.getBoundingSphere(new THREE.Sphere());
    if (!(sphere.radius > 0) || !Number.isFinite(sphere.radius)) return;
    this.framedOnce = true;
    this.controls.target.copy(sphere.center);
    const distance = (0.9 * sphere.radius) / Math.tan((this.camera.fov * Math.PI) / 360);
    const behind = new THREE.Vector3(0, 0.45, 1).normalize().multiplyScalar(distance);
    this.camera.position.copy(sphere.center).add(behind);
    // The grid lies under the map, sized to it.
    this.grid.position.set(sphere.center.x, box.min.y, sphere.center.z);
    this.grid.scale.setScalar(Math.max(1e-3, (4 * sphere.radius) / 10));
    this.camera.near = Math.max(0.001, distance / 1000);
    this.camera.far = distance * 100;
    this.camera.updateProjectionMatrix();
  }

  /** Which layers draw (the test's mesh-only screenshot; the page's check boxes). */
  setLayers({ mesh = true, trajectory = true, keyframes = true, camera = true, points = false, grid = true }) {
    this.dirty = true;
    this.meshGroup.visible = mesh;
    this.trajectory.object.visible = trajectory;
    this.keyframeMarkers.object.visible = keyframes;
    this.showCamera = camera;
    this.frustum.visible = camera && this.hasCamera;
    this.pointsGroup.visible = points;
    this.grid.visible = grid;
  }
}

export { THREE };
