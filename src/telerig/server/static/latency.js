// The page's side of the latency stages it alone sees (issue 17): which joint state or camera
// preview it drew, and when, reported to the control center over /api/latency (logged-in session,
// same origin, the login's CSRF token as a subprotocol; see telerig.server.routes_latency).
//
//   import { connectLatency } from "/static/latency.js";
//   const latency = await connectLatency();           // reads /api/me for the CSRF token
//   ... after the frame that shows a robot's joint state stamped `stampNs` is drawn:
//   latency.rendered("arm0", stampNs);                // a decimal string (exact) or a number
//   ... after a camera preview (its X-Capture-Ns header) is on screen:
//   latency.displayed("scene", captureNs);
//
// Call them right after drawing (after renderer.render(), or in the next requestAnimationFrame for
// an <img>): the time taken is "drawn". Each stamp is reported once; reports wait while the socket
// is down (the latest per node is kept) and the socket reconnects every 2 s.

const PROTOCOL = "telerig-latency.v1";

function pageMs() {
  return performance.timeOrigin + performance.now(); // the page's clock [ms], answered in syncs
}

export async function connectLatency({ csrf = null, retryMs = 2000 } = {}) {
  if (csrf === null) {
    const me = await fetch("/api/me", { credentials: "same-origin" });
    if (!me.ok) throw new Error(`latency: not logged in (${me.status})`);
    csrf = (await me.json()).csrf;
  }
  const last = new Map(); // node -> last stamp reported
  const waiting = new Map(); // node -> report not sent yet (socket down)
  const stats = { sent: 0, syncs: 0, open: false };
  let ws = null;
  let closed = false;

  function send(report) {
    if (ws && ws.readyState === WebSocket.OPEN) {
      ws.send(JSON.stringify(report));
      stats.sent += 1;
      return true;
    }
    return false;
  }

  function open() {
    if (closed) return;
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    ws = new WebSocket(`${scheme}://${location.host}/api/latency`, [PROTOCOL, `csrf.${csrf}`]);
    ws.onopen = () => {
      stats.open = true;
      for (const report of waiting.values()) send(report);
      waiting.clear();
    };
    ws.onmessage = (event) => {
      let message;
      try { message = JSON.parse(event.data); } catch { return; }
      if (message && message.t === "sync" && Number.isInteger(message.id)) {
        send({ t: "sync", id: message.id, page_ms: pageMs() });
        stats.syncs += 1;
      }
    };
    ws.onclose = () => {
      stats.open = false;
      if (!closed) setTimeout(open, retryMs);
    };
  }

  function report(t, key, node, stamp) {
    if (stamp === null || stamp === undefined) return;
    const id = `${key}:${node}`;
    const value = typeof stamp === "bigint" ? stamp.toString() : stamp;
    if (last.get(id) === String(value)) return; // already reported
    last.set(id, String(value));
    const message = { t, [key]: node, stamp: value, page_ms: pageMs() };
    if (!send(message)) waiting.set(id, message);
  }

  open();
  return {
    rendered: (robot, stampNs) => report("rendered", "robot", robot, stampNs),
    displayed: (camera, captureNs) => report("displayed", "camera", camera, captureNs),
    stats,
    close() { closed = true; if (ws) ws.close(); },
  };
}
