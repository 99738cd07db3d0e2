// relfusion's viewer, served by relfusiond: `/` lists the sessions, `/view/{id}` shows one
// live. `window.relfusionViewer` holds the page's state for people and for tests.

import { runBench } from "./bench.js";
import { showList } from "./list.js";
import { buildViewUi } from "./ui.js";
import { showSession } from "./view.js";

const viewer = {
  ready: false,
  finished: false,
  posesReceived: 0,
  resyncs: 0,
  errors: [],
  live: null,
  /** The counts a test compares with the service's own files. */
  counts() {
    return {
      trajectoryPoints: this.model ? this.model.frames.length : 0,
      keyframes: this.model ? this.model.keyframeCount : 0,
      meshTriangles: this.scene ? this.scene.triangles : 0,
      meshBlocks: this.scene ? this.scene.blocks.size : 0,
      meshRevision: this.model ? this.model.meshRevision : 0,
    };
  },
  setLayers(layers) {
    this.scene.setLayers(layers);
  },
};
window.relfusionViewer = viewer;

// Errors of the page are kept for the status and for tests (no console error is expected).
window.addEventListener("error", (e) => viewer.errors.push(e.message || `failed to load ${e.target && (e.target.src || e.target.href)}`), true);
window.addEventListener("unhandledrejection", (e) => viewer.errors.push(String(e.reason && e.reason.message ? e.reason.message : e.reason)));
const consoleError = console.error.bind(console);
console.error = (...args) => {
  viewer.errors.push(args.map(String).join(" "));
  consoleError(...args);
};

const root = document.getElementById("app");
const match = location.pathname.match(/^\/view\/([^/]+)$/);
if (!match) {
  showList(root);
} else {
  const id = decodeURIComponent(match[1]);
  const ui = buildViewUi(root, id);
  const triangles = Number(new URLSearchParams(location.search).get("triangles") || 0);
  const run = id === "bench" && triangles > 0 ? runBench(triangles, ui, viewer) : showSession(id, ui, viewer);
  run.catch((e) => {
    console.error(e);
    ui.showStatus([["error", e.message]]);
  });
}
