// `/view/{id}`: one session, live. The stream's WebSocket is opened first (the server
// subscribes it before answering), then the map snapshot is fetched and applied, then the
// updates that arrived meanwhile; a revision gap or a "you read too slowly" error re-fetches
// the snapshot. A finished session shows its mesh.glb and final trajectory.

import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { ApiError, getBytes, getJson, getText, parseTum, streamUrl } from "./api.js";
import { MapModel } from "./model.js";
import { MapScene } from "./scene.js";
import { loadWire, num } from "./wire.js";

const TERMINAL = new Set(["finished", "failed"]);
const RECONNECTS = 20;

export async function showSession(id, ui, viewer) {
  const scene = new MapScene(ui.canvas);
  const model = new MapModel(scene);
  viewer.scene = scene;
  viewer.model = model;
  ui.bindLayers(scene);
  const wire = await loadWire();
  const status = {
    tracking: "—",
    posesAt: [],
    info: null,
  };

  const pollInfo = async () => {
    try {
      status.info = await getJson(`/v1/sessions/${encodeURIComponent(id)}`);
    } catch (e) {
      if (e instanceof ApiError && (e.status === 404 || e.status === 410)) status.gone = e.message;
    }
    ui.showStatus(statusLines(status, model, scene));
  };
  await pollInfo();
  const poller = setInterval(pollInfo, 1000);

  if (status.gone) {
    ui.showStatus([["session", status.gone]]);
    clearInterval(poller);
    return;
  }
  if (TERMINAL.has(status.info.state)) {
    await showFinished(id, model, scene);
    viewer.finished = true;
    viewer.ready = true;
    return;
  }

  let attempts = 0;
  let resyncing = null;
  const resync = () => {
    resyncing ??= fetchSnapshot(id, wire)
      .then((s) => model.onSnapshot(s))
      .finally(() => {
        resyncing = null;
      });
    return resyncing;
  };

  const connect = () =>
    new Promise((resolve) => {
      const socket = new WebSocket(streamUrl(id));
      socket.binaryType = "arraybuffer";
      let buffered = [];
      const handle = (data) => {
        const message = wire.ServerMessage.decode(new Uint8Array(data));
        if (message.pose) {
          const state = wire.TrackingState.valuesById[message.pose.trackingState] || "";
          status.tracking = state.replace("TRACKING_STATE_", "").toLowerCase();
          status.posesAt.push(performance.now());
          model.onPose(message.pose, state === "TRACKING_STATE_LOST");
          viewer.posesReceived += 1;
        } else if (message.keyframe) {
          model.onKeyframe(message.keyframe);
        } else if (message.mesh) {
          if (!model.onMesh(message.mesh)) {
            viewer.resyncs += 1;
            resync();
          }
        } else if (message.error) {
          console.warn(`server: ${message.error.message}`);
          // RESOURCE_EXHAUSTED: this page read too slowly and updates were skipped.
          if (message.error.code === 3) {
            viewer.resyncs += 1;
            resync();
          }
        }
        scene.frameAll();
      };
      socket.onopen = async () => {
        try {
          await resync();
          attempts = 0;
        } catch (e) {
          console.warn(`snapshot: ${e.message}`);
        }
        for (const data of buffered) handle(data);
        buffered = null;
        viewer.ready = true;
      };
      socket.onmessage = (event) => {
        if (buffered) buffered.push(event.data);
        else handle(event.data);
      };
      socket.onclose = (event) => resolve(event);
    });

  for (;;) {
    const closed = await connect();
    const info = await getJson(`/v1/sessions/${encodeURIComponent(id)}`).catch(() => null);
    if ((info && TERMINAL.has(info.state)) || attempts >= RECONNECTS) {
      // Every update has been sent before the close: catch up if any went missing.
      if (info && num(info.mesh_revision) !== model.meshRevision) await resync();
      viewer.live = { trajectoryPoints: model.frames.length, meshTriangles: scene.triangles };
      await showFinalTrajectory(id, model);
      viewer.finished = true;
      status.closed = closed.reason || "closed";
      await pollInfo();
      clearInterval(poller);
      return;
    }
    attempts += 1;
    await new Promise((r) => setTimeout(r, Math.min(5000, 250 * 2 ** attempts)));
  }
}

async function fetchSnapshot(id, wire) {
  const bytes = await getBytes(`/v1/sessions/${encodeURIComponent(id)}/map`, "application/x-protobuf");
  return wire.MapSnapshot.decode(bytes);
}

async function showFinalTrajectory(id, model) {
  const path = `/v1/sessions/${encodeURIComponent(id)}`;
  const [trajectory, keyframes] = await Promise.all([
    getText(`${path}/trajectory`).then(parseTum),
    getText(`${path}/keyframes`).then(parseTum),
  ]);
  model.setFinal(trajectory, keyframes);
}

async function showFinished(id, model, scene) {
  await showFinalTrajectory(id, model);
  try {
    const glb = await getBytes(`/v1/sessions/${encodeURIComponent(id)}/mesh.glb`, "model/gltf-binary");
    const gltf = await new GLTFLoader().parseAsync(glb.buffer, "");
    scene.setGltfScene(gltf.scene);
  } catch (e) {
    // 404: the session has no mesh (dense layer off); anything else is worth a word.
    if (!(e instanceof ApiError && e.status === 404)) console.warn(`mesh.glb: ${e.message}`);
  }
  scene.frameAll(true);
}

function statusLines(status, model, scene) {
  const info = status.info || {};
  const now = performance.now();
  status.posesAt = status.posesAt.filter((t) => now - t < 2000);
  const fps = status.posesAt.length / 2;
  return [
    ["state", info.state || "—"],
    ["tracking", status.tracking],
    ["frames received", info.frames_received ?? "—"],
    ["frames processed", info.frames_processed ?? "—"],
    ["frames dropped", info.frames_dropped ?? "—"],
    ["keyframes", info.keyframes ?? "—"],
    ["processing fps", fps.toFixed(1)],
    ["trajectory points", model.frames.length],
    ["mesh", `${scene.triangles} triangles, ${scene.blocks.size} blocks`],
    ["render fps", scene.fps.toFixed(0)],
  ];
}
