// The service's HTTP API as the pages use it: the bearer token (entered once, kept in
// localStorage; `?access_token=` in a link offers one) and JSON / binary fetches that carry it.

const TOKEN_KEY = "relfusion.token";

/**
 * Takes `?access_token=` from the address once: it is removed from the address bar (and so
 * from history and from what the page could leak), kept when the browser has no token yet,
 * and replaces a different stored token only when the user agrees (a link must not sign a
 * victim in as someone else).
 */
function takeTokenFromLink() {
  const params = new URLSearchParams(location.search);
  const fromLink = params.get("access_token");
  if (fromLink === null) return;
  params.delete("access_token");
  const rest = params.toString();
  history.replaceState(history.state, "", location.pathname + (rest ? `?${rest}` : "") + location.hash);
  const stored = localStorage.getItem(TOKEN_KEY);
  if (!fromLink || stored === fromLink) return;
  if (
    !stored ||
    window.confirm("This link carries another token than the one this browser uses. Sign in with the link's token?")
  ) {
    localStorage.setItem(TOKEN_KEY, fromLink);
  }
}

takeTokenFromLink();

/** The token this browser uses (entered in the page, or taken from a link). */
export function token() {
  return localStorage.getItem(TOKEN_KEY) || "";
}

export function setToken(value) {
  if (value) localStorage.setItem(TOKEN_KEY, value);
  else localStorage.removeItem(TOKEN_KEY);
}

/** An API error with the service's message (`{"error": {"code", "message"}}`). */
export class ApiError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

async function request(path, accept) {
  const headers = { Accept: accept };
  const t = token();
  if (t) headers.Authorization = `Bearer ${t}`;
  const response = await fetch(path, { headers });
  if (!response.ok) {
    let message = `${response.status} ${response.statusText}`;
    try {
      const body = await response.json();
      if (body && body.error && body.error.message) message = body.error.message;
    } catch (_) {
      // Not the JSON error shape: keep the status line.
    }
    throw new ApiError(response.status, message);
  }
  return response;
}

export async function getJson(path) {
  return (await request(path, "application/json")).json();
}

export async function getText(path) {
  return (await request(path, "text/plain")).text();
}

export async function getBytes(path, accept = "application/octet-stream") {
  return new Uint8Array(await (await request(path, accept)).arrayBuffer());
}

/** The WebSocket URL of a session's stream (browsers cannot set headers on it). */
export function streamUrl(id) {
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  const t = token();
  const query = t ? `?access_token=${encodeURIComponent(t)}` : "";
  return `${scheme}//${location.host}/v1/sessions/${encodeURIComponent(id)}/stream${query}`;
}

/** Parses a TUM trajectory file: `timestamp tx ty tz qx qy qz qw` per line. */
export function parseTum(text) {
  const poses = [];
  for (const line of text.split("\n")) {
    const trimmed = line.trim();
    if (!trimmed || trimmed.startsWith("#")) continue;
    const v = trimmed.split(/\s+/).map(Number);
    if (v.length < 8 || v.some((x) => !Number.isFinite(x))) continue;
    poses.push({ timestamp: v[0], t: [v[1], v[2], v[3]], q: [v[4], v[5], v[6], v[7]], s: 1 });
  }
  return poses;
}
