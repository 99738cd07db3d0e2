// The page around the canvas: token box, layer switches, "follow camera", status panel.

import { setToken, token } from "./api.js";

function el(tag, attrs = {}, children = []) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "text") e.textContent = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c);
  return e;
}

/** The token box: applied on Enter or "use"; reloads the page so every request uses it. */
export function tokenBox() {
  const input = el("input", { type: "password", placeholder: "bearer token (if the server needs one)", id: "token" });
  input.value = token();
  const apply = () => {
    setToken(input.value.trim());
    const url = new URL(location.href);
    url.searchParams.delete("access_token");
    location.href = url.toString();
  };
  input.addEventListener("keydown", (e) => e.key === "Enter" && apply());
  return el("span", { class: "token" }, [input, el("button", { text: "use", onclick: apply })]);
}

export function buildViewUi(root, title) {
  const canvas = el("div", { class: "canvas", id: "canvas" });
  const statusTable = el("table", { class: "status", id: "status" });
  const layers = el("div", { class: "layers" });
  const panel = el("aside", { class: "panel" }, [
    el("h1", {}, [el("a", { href: "/", text: "relfusion" }), document.createTextNode(` · ${title}`)]),
    tokenBox(),
    statusTable,
    layers,
  ]);
  root.append(el("div", { class: "view" }, [panel, canvas]));

  const ui = {
    canvas,
    showStatus(lines) {
      statusTable.replaceChildren(
        ...lines.map(([k, v]) => el("tr", {}, [el("th", { text: k }), el("td", { text: String(v) })])),
      );
    },
    bindLayers(scene) {
      const state = { mesh: true, trajectory: true, keyframes: true, camera: true, points: false, grid: true };
      const box = (name, label) => {
        const input = el("input", { type: "checkbox", id: `layer-${name}` });
        input.checked = state[name];
        input.addEventListener("change", () => {
          state[name] = input.checked;
          scene.setLayers(state);
        });
        return el("label", {}, [input, document.createTextNode(` ${label}`)]);
      };
      const follow = el("input", { type: "checkbox", id: "follow" });
      follow.addEventListener("change", () => {
        scene.follow = follow.checked;
      });
      layers.replaceChildren(
        box("mesh", "mesh"),
        box("trajectory", "trajectory"),
        box("keyframes", "keyframes"),
        box("camera", "camera"),
        box("points", "keyframe points"),
        box("grid", "grid"),
        el("label", {}, [follow, document.createTextNode(" follow camera")]),
        el("button", { text: "fit view", onclick: () => scene.frameAll(true) }),
      );
      scene.setLayers(state);
    },
  };
  return ui;
}

export { el };
