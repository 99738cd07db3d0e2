// `/view/bench?triangles=N`: the renderer's frame rate with an N-triangle mesh split into
// blocks the way MeshUpdates deliver it (scripts/bench-viewer.sh reads `benchFps`).

import { MapScene } from "./scene.js";

/** Triangles per block: about what a fused 16³-voxel block of a room holds. */
const BLOCK_TRIANGLES = 2048;

export async function runBench(triangles, ui, viewer) {
  const scene = new MapScene(ui.canvas);
  viewer.scene = scene;
  ui.bindLayers(scene);
  const cells = Math.ceil(Math.sqrt(BLOCK_TRIANGLES / 2));
  const blocks = Math.ceil(triangles / (cells * cells * 2));
  const side = Math.ceil(Math.sqrt(blocks));
  for (let b = 0; b < blocks; b++) {
    const bx = b % side;
    const bz = Math.floor(b / side);
    const positions = new Float32Array((cells + 1) * (cells + 1) * 3);
    const colors = new Uint8Array(positions.length);
    const normals = new Float32Array(positions.length);
    for (let j = 0; j <= cells; j++) {
      for (let i = 0; i <= cells; i++) {
        const k = (j * (cells + 1) + i) * 3;
        const x = bx + i / cells;
        const z = bz + j / cells;
        positions[k] = x;
        positions[k + 1] = 0.2 * Math.sin(x * 2.1) * Math.cos(z * 1.7);
        positions[k + 2] = z;
        colors[k] = 80 + ((bx * 37) % 150);
        colors[k + 1] = 120 + ((bz * 53) % 120);
        colors[k + 2] = 160;
        normals[k + 1] = 1;
      }
    }
    const indices = new Uint32Array(cells * cells * 6);
    let n = 0;
    for (let j = 0; j < cells; j++) {
      for (let i = 0; i < cells; i++) {
        const a = j * (cells + 1) + i;
        indices.set([a, a + 1, a + cells + 1, a + 1, a + cells + 2, a + cells + 1], n);
        n += 6;
      }
    }
    scene.setBlock(`${bx},0,${bz}`, positions, colors, normals, indices);
  }
  scene.frameAll(true);
  scene.controls.autoRotate = true;
  scene.controls.autoRotateSpeed = 10;
  viewer.ready = true;
  const seconds = Number(new URLSearchParams(location.search).get("seconds") || 5);
  await new Promise((r) => setTimeout(r, 1000));
  const start = scene.frames;
  const t0 = performance.now();
  await new Promise((r) => setTimeout(r, seconds * 1000));
  viewer.benchFps = ((scene.frames - start) * 1000) / (performance.now() - t0);
  viewer.benchTriangles = scene.triangles;
  viewer.benchBlocks = scene.blocks.size;
  viewer.finished = true;
}
