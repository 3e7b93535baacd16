"use strict";
// The control center's dashboard: the whole rig at a glance from the live feed (WebSocket
// /api/live: a snapshot, then the sections that changed; polling GET /api/rig while the socket is
// down), session commands and the e-stop for operators, and the admin tables.
// Every text from the server goes through textContent (never innerHTML); requests go through
// api.js's api(), which sends the session's CSRF token.
let role = "viewer";
let userName = "";
let rig = null; // the last snapshot, deltas merged in
let socket = null;
let lastMessageMs = 0;
let pollTimer = null;
let reconnectMs = 500;
const FEED_STALE_MS = 2500; // the server resends every section each second
const PREVIEW_MS = 2000; // camera previews: one fetch per camera every 2 s
const OPERATOR_ROLES = new Set(["operator", "admin"]);

function el(tag, text, attrs = {}) {
  const node = document.createElement(tag);
  if (text !== undefined && text !== null) node.textContent = String(text);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  return node;
}

function row(table, cells) {
  const tr = document.createElement("tr");
  for (const value of cells) tr.appendChild(el("td", value));
  document.querySelector(`#${table} tbody`).appendChild(tr);
}

function dot(light) {
  return el("span", "", { class: "dot", "data-light": light, title: light, "aria-label": light });
}

function fmt(value, digits = 1, unit = "") {
  if (value === null || value === undefined || Number.isNaN(value)) return "–";
  return `${Number(value).toFixed(digits)}${unit}`;
}

function shortTopic(topic) {
  // telerig/v1/<rig>/<node>/<stream> -> <node>/<stream>
  const parts = topic.split("/");
  return parts.length > 3 ? parts.slice(3).join("/") : topic;
}

// Each keyed row keeps the time (ms since the epoch) its light last changed, so a test or an
// operator can tell how fresh a colour is (data-light-since).
function keyedRow(tbody, key, light, cells) {
  let tr = tbody.querySelector(`tr[data-key="${CSS.escape(key)}"]`);
  if (!tr) {
    tr = el("tr", null, { "data-key": key });
    tbody.appendChild(tr);
  }
  if (tr.dataset.light !== light) {
    tr.dataset.light = light;
    tr.dataset.lightSince = String(Date.now());
  }
  tr.replaceChildren(el("td"), ...cells.map((c) => (c instanceof Node ? c : el("td", c))));
  tr.firstChild.appendChild(dot(light));
  tr.dataset.seen = "1";
  return tr;
}

function sweep(tbody) {
  for (const tr of [...tbody.children]) {
    if (tr.dataset.seen !== "1") tr.remove();
    delete tr.dataset.seen;
  }
}

// --- rendering -------------------------------------------------------------------------------------

function render() {
  if (!rig) return;
  const link = document.getElementById("link");
  link.hidden = rig.connected;
  link.textContent = rig.connected ? "" : `Not connected to rig ${rig.rig}: ${rig.link_error || "no link"}`;
  document.getElementById("rig-name").textContent = rig.rig;
  document.getElementById("fault-policy").textContent = rig.fault_policy;
  renderSession(rig.session);
  renderRobots(rig.robots || []);
  renderStations(rig.stations || []);
  renderDevices(rig.devices || []);
  renderStreams(rig.streams || [], rig.active_alerts || []);
  renderAlerts(rig.active_alerts || [], rig.alerts || []);
  renderLatency(rig.latency_stages || []);
  renderCameras(rig.cameras || []);
}

function renderSession(s) {
  const state = s ? s.state : "unknown";
  const badge = document.getElementById("session-state");
  badge.textContent = s && s.discarded && state === "stopped" ? "stopped (discarded)" : state;
  badge.dataset.state = state;
  document.getElementById("session-episode").textContent = s && s.episode_id ? `episode ${s.episode_id}` : "";
  const parts = [];
  if (s && s.task) parts.push(`task: ${s.task}`);
  if (s && s.operator) parts.push(`operator: ${s.operator}`);
  if (s && s.reason) parts.push(`reason: ${s.reason}`);
  document.getElementById("session-task").textContent = parts.join(" · ");
  const allowed = {
    start: ["idle", "stopped", "unknown"],
    pause: ["recording"],
    resume: ["paused"],
    stop: ["recording", "paused", "armed"],
    discard: ["recording", "paused", "armed"],
    restart: ["recording", "paused", "armed"],
    end: ["recording", "paused", "armed", "stopped"],
    mark: ["recording", "paused", "stopped"],
  };
  for (const button of document.querySelectorAll("#session-buttons button")) {
    button.disabled = !rig.connected || !allowed[button.dataset.command].includes(state);
  }
}

function renderRobots(robots) {
  const list = document.getElementById("robots");
  for (const r of robots) {
    let li = list.querySelector(`li[data-key="${CSS.escape(r.id)}"]`);
    if (!li) {
      li = el("li", null, { "data-key": r.id, class: "card" });
      list.appendChild(li);
    }
    if (li.dataset.light !== r.light) {
      li.dataset.light = r.light;
      li.dataset.lightSince = String(Date.now());
    }
    li.dataset.status = r.status || "unknown";
    li.replaceChildren(
      dot(r.light),
      el("strong", r.id),
      el("span", r.status || "no status", { class: "status" }),
      el("span", r.status_age_s === null ? "" : `${fmt(r.status_age_s, 1)} s ago`, { class: "muted" }),
      latencyBadge(li, r.latency),
    );
    li.dataset.seen = "1";
  }
  sweep(list);
}

// Input-to-actuation latency of a robot's control loop (device capture -> command applied), p50 and
// p99 over its window against its budget; the light (and when it changed) is kept on the card.
function latencyBadge(li, lat) {
  const light = lat ? lat.light : "grey";
  if (li.dataset.latencyLight !== light) {
    li.dataset.latencyLight = light;
    li.dataset.latencyLightSince = String(Date.now());
  }
  const badge = el("span", null, { class: "latency", "data-light": light });
  if (!lat) {
    badge.append(dot("grey"), el("span", " latency: no report", { class: "muted" }));
    return badge;
  }
  badge.title =
    `device capture -> command applied over the last ${fmt(lat.window_s, 0)} s (${lat.commands} commands); ` +
    `-> measured state p50 ${fmt(lat.state_p50_ms, 1)} / p99 ${fmt(lat.state_p99_ms, 1)} ms; ` +
    `amber over the ${fmt(lat.budget_ms, 0)} ms budget, red over the ${fmt(lat.hold_ms, 0)} ms hold time`;
  const text = lat.p50_ms === null
    ? " latency: no input"
    : ` latency p50 ${fmt(lat.p50_ms, 1)} / p99 ${fmt(lat.p99_ms, 1)} ms (budget ${fmt(lat.budget_ms, 0)})`;
  badge.append(dot(light), el("span", text));
  return badge;
}

function renderStations(stations) {
  const tbody = document.querySelector("#stations tbody");
  for (const s of stations) {
    keyedRow(tbody, s.id, s.light, [
      s.id,
      s.last_seen_s === null ? "never" : `${fmt(s.last_seen_s, 1)} s ago`,
      s.clock_offset_ms === null ? "–" : `${fmt(s.clock_offset_ms, 2)} ms`,
    ]);
  }
  sweep(tbody);
}

function renderDevices(devices) {
  const tbody = document.querySelector("#devices tbody");
  // Per-device pause (seed 000): a paused device's robots hold while the rest of the rig goes on.
  const paused = new Set((rig.session && rig.session.paused_devices) || []);
  for (const d of devices) {
    const dropped = Object.entries(d.dropped || {})
      .filter(([, n]) => n > 0)
      .map(([why, n]) => `${why} ${n}`)
      .join(", ");
    const input = el("td", null, { class: "device-input" });
    input.appendChild(el("span", paused.has(d.id) ? "paused" : "live", { class: "device-state" }));
    if (d.calibration) {
      input.appendChild(el("span", ` · calibration ${d.calibration}`, { class: "calibration muted" }));
    }
    if (OPERATOR_ROLES.has(role)) {
      const action = paused.has(d.id) ? "resume" : "pause";
      input.appendChild(
        el("button", action === "pause" ? "Pause" : "Resume", {
          type: "button",
          class: "device-pause",
          "data-device": d.id,
          "data-action": action,
          title: action === "pause" ? `pause ${d.id}: its robots hold, the rest goes on` : `resume ${d.id}`,
        }),
      );
      input.appendChild(
        el("button", "Calibrate", {
          type: "button",
          class: "device-calibrate",
          "data-device": d.id,
          title: `calibrate an operator with ${d.id}: hold both hands straight forward, level and still`,
        }),
      );
    }
    const rate = d.rate_hz === null ? "–" : `${fmt(d.rate_hz, 0)} Hz`;
    const tr = keyedRow(tbody, d.id, d.light, [d.id, rate, dropped || "0", input]);
    tr.dataset.paused = paused.has(d.id) ? "1" : "0";
  }
  sweep(tbody);
}

function renderStreams(streams, active) {
  // A stall alert goes out at once; the recorder's health report only each second: a stream with
  // an active stall alert is red now.
  const stalled = new Set(active.filter((a) => a.code === "stream_stalled").map((a) => a.subject));
  const tbody = document.querySelector("#streams tbody");
  for (const s of streams) {
    const light = stalled.has(s.topic) ? "red" : s.light;
    const state = stalled.has(s.topic) ? "stalled" : s.state;
    const tr = keyedRow(tbody, s.topic, light, [
      el("td", shortTopic(s.topic), { title: s.topic }),
      `${fmt(s.measured_hz, 1)} / ${fmt(s.expected_hz, 0)} Hz`,
      String(s.drops),
      s.gaps ? `${s.gaps} (max ${fmt(s.max_gap_ms, 0)} ms)` : "0",
      s.latency_ms === null ? "–" : `${fmt(s.latency_ms, 1)} ms`,
      state,
    ]);
    tr.dataset.state = state;
  }
  sweep(tbody);
}

function alertItem(a) {
  const li = el("li", null, { class: `alert severity-${a.severity}`, "data-code": a.code });
  if (!a.active) li.classList.add("cleared");
  const when = new Date(a.t_ns / 1e6).toLocaleTimeString();
  const head = el("div", null, { class: "alert-head" });
  head.append(
    el("span", a.severity, { class: "severity" }),
    el("strong", a.code),
    el("span", a.subject ? shortTopic(a.subject) : a.source),
    el("span", a.active ? when : `${when} · cleared`, { class: "muted" }),
  );
  li.appendChild(head);
  if (a.reason) li.appendChild(el("p", a.reason));
  if (a.suggested_action) li.appendChild(el("p", `→ ${a.suggested_action}`, { class: "action" }));
  return li;
}

function renderAlerts(active, recent) {
  const list = document.getElementById("active-alerts");
  list.replaceChildren(...active.map(alertItem));
  if (!active.length) list.appendChild(el("li", "No active alerts", { class: "muted none" }));
  document.getElementById("alerts").replaceChildren(...recent.slice(0, 20).map(alertItem));
}

// --- latency per stage (issue 17): the control nodes' stages, the pages' rendered/displayed -----------

function renderLatency(entries) {
  const tbody = document.querySelector("#latency tbody");
  for (const entry of entries) {
    const rows = entry.end_to_end ? [...entry.stages, entry.end_to_end] : entry.stages;
    for (const s of rows) {
      const tr = keyedRow(tbody, `${entry.node}/${s.stage}`, s.light, [
        entry.node, s.stage.replace(/_/g, " "), fmt(s.p50_ms, 1, " ms"), fmt(s.p99_ms, 1, " ms"),
        fmt(s.budget_ms, 0, " ms"), String(s.count),
      ]);
      tr.dataset.node = entry.node;
      tr.dataset.stage = s.stage;
      if (s.stage === "end_to_end") tr.classList.add("total");
    }
  }
  sweep(tbody);
}

// The page's own stages: when it shows a camera preview, it tells the server which frame and when
// (/static/latency.js); loaded lazily so the dashboard works without it.
let latency = null;
async function latencyReporter() {
  if (latency === null) {
    latency = import("/static/latency.js").then((m) => m.connectLatency({ csrf })).catch(() => undefined);
  }
  return latency;
}

// --- camera previews (low rate, only while the page is visible) ------------------------------------

const previews = new Map(); // camera -> {img, url, busy}

function renderCameras(cameras) {
  const panel = document.getElementById("cameras-panel");
  panel.hidden = cameras.length === 0;
  const box = document.getElementById("cameras");
  for (const c of cameras) {
    if (!previews.has(c.id)) {
      const figure = el("figure", null, { "data-key": c.id });
      const img = el("img", null, { alt: `camera ${c.id}`, width: "320", height: "240" });
      const caption = el("figcaption");
      figure.append(img, caption);
      box.appendChild(figure);
      previews.set(c.id, { img, caption, url: null, busy: false });
    }
    const p = previews.get(c.id);
    p.caption.replaceChildren(dot(c.light), el("span", ` ${c.id} `),
      el("span", c.preview_age_s === null ? "no preview" : `${fmt(c.preview_age_s, 1)} s old`, { class: "muted" }));
  }
}

async function refreshPreviews() {
  if (document.hidden || !rig || !rig.connected) return;
  for (const [camera, p] of previews) {
    if (p.busy) continue;
    p.busy = true;
    try {
      const reply = await api(`/api/rig/cameras/${encodeURIComponent(camera)}/preview`);
      if (reply.ok && (reply.headers.get("content-type") || "").startsWith("image/jpeg")) {
        const url = URL.createObjectURL(await reply.blob());
        const captureNs = reply.headers.get("X-Capture-Ns");
        p.img.src = url;
        if (p.url) URL.revokeObjectURL(p.url);
        p.url = url;
        if (captureNs) {
          await p.img.decode().catch(() => undefined);
          // Drawn by the next frame after the decoded image is in the document.
          requestAnimationFrame(async () => (await latencyReporter())?.displayed(camera, captureNs));
        }
      }
    } catch (err) {
      // the next round tries again
    } finally {
      p.busy = false;
    }
  }
}

// --- the live feed ---------------------------------------------------------------------------------

function setFeed(state, text) {
  const feed = document.getElementById("feed");
  feed.dataset.feed = state;
  feed.textContent = text;
}

function onMessage(event) {
  lastMessageMs = Date.now();
  const message = JSON.parse(event.data);
  if (message.type === "snapshot") {
    const { type, ...snapshot } = message;
    rig = snapshot;
  } else if (message.type === "delta" && rig) {
    Object.assign(rig, message.changed);
    rig.t_ns = message.t_ns;
  }
  setFeed("live", "live");
  stopPolling();
  render();
}

function connect() {
  const scheme = window.location.protocol === "https:" ? "wss" : "ws";
  socket = new WebSocket(`${scheme}://${window.location.host}/api/live`);
  socket.addEventListener("open", () => {
    reconnectMs = 500;
  });
  socket.addEventListener("message", onMessage);
  socket.addEventListener("close", (event) => {
    socket = null;
    if (event.reason === "log in first" || event.reason === "logged out") {
      api("/api/me").catch(loggedOutIsNoError); // a 401 there goes to the login page
    }
    if (event.reason === "this server watches no rig") {
      setFeed("none", "no rig");
      const link = document.getElementById("link");
      link.hidden = false;
      link.textContent = "This server watches no rig: start it with `telerig serve --rig RIG`.";
      return;
    }
    startPolling(event.reason || "reconnecting");
    setTimeout(connect, reconnectMs);
    reconnectMs = Math.min(reconnectMs * 2, 5000);
  });
}

async function poll() {
  try {
    const reply = await api("/api/rig");
    if (reply.ok) {
      rig = await reply.json();
      render();
    } else {
      const body = await reply.json().catch(() => ({ detail: reply.statusText }));
      const link = document.getElementById("link");
      link.hidden = false;
      link.textContent = body.detail;
    }
  } catch (err) {
    setFeed("offline", "offline");
  }
}

function startPolling(why) {
  setFeed("polling", `polling (${why})`);
  if (pollTimer === null) {
    poll();
    pollTimer = setInterval(poll, 1000);
  }
}

function stopPolling() {
  if (pollTimer !== null) {
    clearInterval(pollTimer);
    pollTimer = null;
  }
}

function watchFeed() {
  // A socket that is open but silent (a proxy holding it, a stalled server) is as good as closed.
  if (socket && socket.readyState === WebSocket.OPEN && Date.now() - lastMessageMs > FEED_STALE_MS) {
    startPolling("live feed silent");
  }
}

// --- commands --------------------------------------------------------------------------------------

function showResult(text, ok) {
  const result = document.getElementById("command-result");
  result.textContent = text;
  result.dataset.ok = ok ? "1" : "0";
}

async function sessionCommand(command, outcome) {
  let body = { reason: "from the dashboard" };
  if (command === "start" || command === "restart") body = {};
  if (command === "mark") body = { outcome, reason: "from the dashboard" };
  const reply = await api(`/api/session/${command}`, { method: "POST", body: JSON.stringify(body) });
  const doc = await reply.json().catch(() => ({ detail: reply.statusText }));
  if (reply.ok) showResult(`${command}: session ${doc.session.state}`, true);
  else showResult(`${command} refused: ${doc.detail}`, false);
}

// A phrase of the voice command grammar, typed (POST /api/voice/say; the same grammar as speech).
async function voiceCommand() {
  const input = document.getElementById("voice-text");
  const reply = await api("/api/voice/say", { method: "POST", body: JSON.stringify({ text: input.value }) });
  const doc = await reply.json().catch(() => ({ detail: reply.statusText }));
  if (reply.ok) {
    showResult(`${doc.status}: ${doc.say}`, true);
    input.value = "";
  } else {
    showResult(`not sent: ${typeof doc.detail === "string" ? doc.detail : "not a command of the grammar"}`, false);
  }
}

async function deviceCommand(device, action) {
  const path = `/api/rig/devices/${encodeURIComponent(device)}/${action}`;
  const reply = await api(path, { method: "POST", body: JSON.stringify({ reason: "from the dashboard" }) });
  const doc = await reply.json().catch(() => ({ detail: reply.statusText }));
  if (!reply.ok) {
    showResult(`${action} ${device} refused: ${doc.detail}`, false);
    return;
  }
  const paused = doc.session.paused_devices || [];
  showResult(`${action} ${device}: paused devices ${paused.join(", ") || "none"}`, true);
  if (rig) {
    rig.session = doc.session;
    render();
  }
}

async function calibrate(device) {
  const operator = window.prompt(
    `Calibrate which operator with ${device}? They hold both hands straight forward, level and still ` +
      "for 30 s (3 s to get there first; a device driving robots in an episode must be paused).",
    userName,
  );
  if (!operator) return;
  const path = `/api/rig/devices/${encodeURIComponent(device)}/calibrate`;
  const reply = await api(path, { method: "POST", body: JSON.stringify({ operator }) });
  const doc = await reply.json().catch(() => ({ detail: reply.statusText }));
  if (!reply.ok) showResult(`calibrate ${device} refused: ${doc.detail}`, false);
  else {
    const text = doc.reply || "no answer from the device: is the rig running?";
    showResult(`calibrate ${device}: ${text}`, !!doc.reply && !doc.reply.startsWith("calibrate refused"));
  }
}

async function safetyCommand(what) {
  const reason = what === "estop" ? "e-stop button on the dashboard" : "reset from the dashboard";
  const reply = await api(`/api/${what}`, { method: "POST", body: JSON.stringify({ reason }) });
  const doc = await reply.json().catch(() => ({ detail: reply.statusText }));
  if (!reply.ok) {
    showResult(`${what} failed: ${doc.detail}`, false);
    return;
  }
  const confirmed = doc.robots.filter((r) => r.confirmed).map((r) => r.robot);
  const missing = doc.robots.filter((r) => !r.confirmed).map((r) => `${r.robot} (${r.status || "no status"})`);
  let text = `${what === "estop" ? "E-stop" : "Reset"}: confirmed by ${confirmed.join(", ") || "no robot"}`;
  if (missing.length) text += `; NOT confirmed: ${missing.join(", ")}`;
  showResult(text, doc.confirmed);
}

function wireControls() {
  const operator = OPERATOR_ROLES.has(role);
  for (const node of document.querySelectorAll(".operator-only")) node.hidden = !operator;
  if (!operator) return;
  for (const button of document.querySelectorAll("#session-buttons button")) {
    button.addEventListener("click", () => sessionCommand(button.dataset.command, button.dataset.outcome));
  }
  document.getElementById("estop").addEventListener("click", () => safetyCommand("estop"));
  document.getElementById("voice-form").addEventListener("submit", (event) => {
    event.preventDefault();
    voiceCommand();
  });
  document.querySelector("#devices tbody").addEventListener("click", (event) => {
    const button = event.target.closest("button.device-pause");
    if (button) deviceCommand(button.dataset.device, button.dataset.action);
    const calibrating = event.target.closest("button.device-calibrate");
    if (calibrating) calibrate(calibrating.dataset.device);
  });
  document.getElementById("reset").addEventListener("click", () => {
    if (window.confirm("Release the e-stop of every robot? They restart stopped and ramp up on fresh input.")) {
      safetyCommand("reset");
    }
  });
}

// --- admin -----------------------------------------------------------------------------------------

async function loadAdmin() {
  document.getElementById("admin").hidden = false;
  for (const u of await (await api("/api/users")).json()) {
    row("users", [u.name, u.role, u.disabled ? "disabled" : "active"]);
  }
  for (const e of await (await api("/api/audit?limit=50")).json()) {
    row("audit", [new Date(e.t_ns / 1e6).toLocaleString(), e.user || "-", e.action, e.target, e.client]);
  }
}

async function start() {
  const me = await (await api("/api/me")).json();
  csrf = me.csrf;
  role = me.role;
  userName = me.user;
  document.body.dataset.role = role;
  document.getElementById("who").textContent = `${me.user} (${me.role})`;
  document.getElementById("logout").addEventListener("click", async () => {
    await api("/api/logout", { method: "POST" });
    window.location.assign("/login");
  });
  wireControls();
  connect();
  setInterval(watchFeed, 500);
  setInterval(refreshPreviews, PREVIEW_MS);
  if (role === "admin") loadAdmin().catch(loggedOutIsNoError);
}

start().catch(loggedOutIsNoError);
