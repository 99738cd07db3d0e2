// `/`: the caller's sessions, each linked to its viewer.

import { ApiError, getJson } from "./api.js";
import { el, tokenBox } from "./ui.js";

export async function showList(root) {
  const table = el("table", { class: "sessions", id: "sessions" });
  const message = el("p", { class: "message" });
  root.append(
    el("main", { class: "list" }, [
      el("h1", { text: "relfusion sessions" }),
      tokenBox(),
      message,
      table,
      el("p", {}, [el("a", { href: "/docs", text: "API docs" })]),
    ]),
  );
  const refresh = async () => {
    try {
      const { sessions } = await getJson("/v1/sessions");
      message.textContent = sessions.length ? "" : "No sessions yet.";
      table.replaceChildren(
        el("tr", {}, ["session", "kind", "state", "frames", "keyframes", "triangles"].map((t) => el("th", { text: t }))),
        ...sessions
          .sort((a, b) => b.created_unix - a.created_unix)
          .map((s) =>
            el("tr", {}, [
              el("td", {}, [el("a", { href: `/view/${encodeURIComponent(s.id)}`, text: s.id })]),
              el("td", { text: s.kind }),
              el("td", { text: s.state }),
              el("td", { text: String(s.frames_processed) }),
              el("td", { text: String(s.keyframes) }),
              el("td", { text: String(s.mesh_triangles) }),
            ]),
          ),
      );
    } catch (e) {
      message.textContent = e instanceof ApiError && e.status === 401 ? `${e.message}: enter a token above` : e.message;
    }
  };
  await refresh();
  setInterval(refresh, 2000);
}
