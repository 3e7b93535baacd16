// telerig WebXR page: streams head, controllers and hands to the control center (telerig serve, behind
// its login) over a WebSocket; the server relays them to the rig's WebXR device.
// Wire format (binary, little-endian): see telerig/devices/webxr/protocol.py. Version 1.
// Desktop (no WebXR): keyboard (only while the page has focus) and the Gamepad API drive two
// virtual controllers, sent in the same frame format with mode 0.

const VERSION = 1;
const KIND_FRAME = 1, KIND_PONG = 2, KIND_PING = 3;
const MODE = { desktop: 0, "immersive-vr": 1, "immersive-ar": 2 };
const HEADER = 20, POSE = 28, CONTROLLER = 48, HAND = 25 * 8 * 4;
const JOINTS = [
  "wrist", "thumb-metacarpal", "thumb-phalanx-proximal", "thumb-phalanx-distal", "thumb-tip",
  ...["index-finger", "middle-finger", "ring-finger", "pinky-finger"].flatMap((f) =>
    ["metacarpal", "phalanx-proximal", "phalanx-intermediate", "phalanx-distal", "tip"].map((p) => `${f}-${p}`)),
];
const DESKTOP_HZ = 60;
const SPEED = 0.5;            // m/s, virtual controller translation
const TURN = Math.PI / 2;     // rad/s, virtual controller yaw
const DEADZONE = 0.15;
const MAX_BUFFERED = 64 * 1024; // bytes queued in the socket before frames are skipped

const $ = (id) => document.getElementById(id);
const state = {
  connected: false, sent: 0, skipped: 0, seq: 0, mode: "desktop", rate: 0, device: null, pings: 0, closeCode: null,
  xrSupported: { "immersive-vr": false, "immersive-ar": false }, lastError: null,
};
window.telerigXR = state; // read by tests and for debugging in the browser console

const clamp = (v, lo, hi) => (Number.isFinite(v) ? Math.min(hi, Math.max(lo, v)) : 0);

// ---------------------------------------------------------------- encoding
const buffer = new ArrayBuffer(HEADER + POSE + 2 * CONTROLLER + 2 * HAND);
const view = new DataView(buffer);

function writeHeader(seq, clientMs, mode, present) {
  view.setUint8(0, 0x54); view.setUint8(1, 0x58); // "TX"
  view.setUint8(2, VERSION); view.setUint8(3, KIND_FRAME);
  view.setUint32(4, seq >>> 0, true);
  view.setFloat64(8, clientMs, true);
  view.setUint8(16, MODE[mode]); view.setUint8(17, present); view.setUint16(18, 0, true);
}

function writePose(off, p, q) {
  view.setFloat32(off, p.x, true); view.setFloat32(off + 4, p.y, true); view.setFloat32(off + 8, p.z, true);
  view.setFloat32(off + 12, q.x, true); view.setFloat32(off + 16, q.y, true);
  view.setFloat32(off + 20, q.z, true); view.setFloat32(off + 24, q.w, true);
  return off + POSE;
}

function writeController(off, c) {
  off = writePose(off, c.position, c.orientation);
  view.setFloat32(off, clamp(c.trigger, 0, 1), true);
  view.setFloat32(off + 4, clamp(c.squeeze, 0, 1), true);
  view.setFloat32(off + 8, clamp(c.axes[0], -1, 1), true);
  view.setFloat32(off + 12, clamp(c.axes[1], -1, 1), true);
  view.setUint32(off + 16, c.buttons >>> 0, true);
  return off + 20;
}

// joints: 25 entries of {position, orientation, radius} or null (untracked).
function writeHand(off, joints) {
  for (const j of joints) {
    if (j) {
      off = writePose(off, j.position, j.orientation);
      view.setFloat32(off, clamp(j.radius ?? 0.01, 1e-4, 0.1), true);
    } else {
      off = writePose(off, { x: 0, y: 0, z: 0 }, { x: 0, y: 0, z: 0, w: 1 });
      view.setFloat32(off, 0, true);
    }
    off += 4;
  }
  return off;
}

// frame: {clientMs, mode, head, left, right, leftHand, rightHand}; missing parts are left out.
function encodeFrame(frame) {
  let present = 0, off = HEADER;
  if (frame.head) { present |= 1; off = writePose(off, frame.head.position, frame.head.orientation); }
  if (frame.left) { present |= 2; off = writeController(off, frame.left); }
  if (frame.right) { present |= 4; off = writeController(off, frame.right); }
  if (frame.leftHand) { present |= 8; off = writeHand(off, frame.leftHand); }
  if (frame.rightHand) { present |= 16; off = writeHand(off, frame.rightHand); }
  writeHeader(state.seq++, frame.clientMs, frame.mode, present);
  return buffer.slice(0, off);
}

// ---------------------------------------------------------------- connection
let ws = null;
let frames = 0;

// The page is the control center's (telerig serve): its WebSocket needs this login's cookie (sent
// by the browser), the server's own origin, and the login's CSRF token offered as a subprotocol.
const SUBPROTOCOL = "telerig-xr.v1";

async function connect() {
  setConn("connecting…", "");
  let me, device;
  try {
    const reply = await fetch("/api/me", { credentials: "same-origin" });
    if (reply.status === 401) { location.href = "/login"; return; }
    me = await reply.json();
    $("who").textContent = `${me.user} (${me.role})`;
    if (me.role === "viewer") { setConn("a viewer cannot drive a robot: log in as an operator", "bad"); return; }
    device = new URLSearchParams(location.search).get("device");
    if (!device) {
      const devices = await (await fetch("/api/xr", { credentials: "same-origin" })).json();
      if (!devices.length) { setConn("this rig has no WebXR device (or the server watches no rig)", "bad"); return; }
      device = devices[0].device;
    }
  } catch (err) {
    state.lastError = String(err);
    setConn("server unreachable, retrying…", "bad");
    setTimeout(connect, 2000);
    return;
  }
  state.device = device;
  $("device").textContent = device;
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  ws = new WebSocket(`${scheme}://${location.host}/api/xr/${encodeURIComponent(device)}`, [SUBPROTOCOL, `csrf.${me.csrf}`]);
  ws.binaryType = "arraybuffer";
  ws.onopen = () => { state.connected = true; setConn("connected", "ok"); };
  ws.onclose = (ev) => {
    state.connected = false;
    state.closeCode = ev.code;
    if (ev.code === 4000) { setConn("replaced by another page", "bad"); return; }
    if (ev.code === 4003) { setConn("another page is active, retrying…", "bad"); setTimeout(connect, 3000); return; }
    if (ev.code === 1013) { setConn(`${ev.reason || "the rig is not reachable"}…`, "bad"); setTimeout(connect, 3000); return; }
    if (ev.code === 1008) { setConn(`refused: ${ev.reason || "log in again"}`, "bad"); setTimeout(connect, 5000); return; }
    setConn("disconnected, retrying…", "bad");
    setTimeout(connect, 1000);
  };
  ws.onmessage = (ev) => {
    if (!(ev.data instanceof ArrayBuffer) || ev.data.byteLength !== 8) return;
    const m = new DataView(ev.data);
    if (m.getUint8(0) !== 0x54 || m.getUint8(1) !== 0x58 || m.getUint8(3) !== KIND_PING) return;
    const pong = new DataView(new ArrayBuffer(16));
    pong.setUint8(0, 0x54); pong.setUint8(1, 0x58); pong.setUint8(2, VERSION); pong.setUint8(3, KIND_PONG);
    pong.setUint32(4, m.getUint32(4, true), true);
    pong.setFloat64(8, performance.timeOrigin + performance.now(), true);
    ws.send(pong.buffer);
    state.pings++;
  };
}

function send(frame) {
  if (!ws || ws.readyState !== WebSocket.OPEN) return;
  if (ws.bufferedAmount > MAX_BUFFERED) { state.skipped++; return; } // never queue stale poses
  ws.send(encodeFrame(frame));
  state.sent++; frames++;
}

function setConn(text, cls) { $("conn").textContent = text; $("dot").className = `dot ${cls}`; }

setInterval(() => { state.rate = frames; frames = 0; }, 1000);
setInterval(() => {
  $("rate").textContent = String(state.rate); $("sent").textContent = String(state.sent);
  $("skipped").textContent = String(state.skipped); $("mode").textContent = state.mode;
}, 200);

// ---------------------------------------------------------------- desktop mode
const keys = new Set();
const virtual = {
  left: { position: [-0.2, 1.0, -0.3], yaw: 0 },
  right: { position: [0.2, 1.0, -0.3], yaw: 0 },
};
let activeHand = "right";
const CONTROL_KEYS = new Set(["KeyW", "KeyA", "KeyS", "KeyD", "KeyQ", "KeyE", "KeyR", "KeyF", "KeyG", "Space",
  "Digit1", "Digit2", "Digit3", "Digit4", "ArrowUp", "ArrowDown", "ArrowLeft", "ArrowRight"]);

// Listeners on this page only: keys are seen while the page has focus, never system-wide.
window.addEventListener("keydown", (ev) => {
  if (ev.code === "KeyH" && !ev.repeat) activeHand = activeHand === "right" ? "left" : "right";
  if (CONTROL_KEYS.has(ev.code)) { keys.add(ev.code); ev.preventDefault(); }
});
window.addEventListener("keyup", (ev) => keys.delete(ev.code));
window.addEventListener("blur", () => keys.clear());
document.addEventListener("visibilitychange", () => keys.clear());

function firstGamepad() {
  if (!navigator.getGamepads) return null;
  for (const gp of navigator.getGamepads()) if (gp && gp.connected) return gp;
  return null;
}

const dz = (v) => (Math.abs(v) < DEADZONE ? 0 : v);
const held = (code) => (keys.has(code) ? 1 : 0);

let lastTick = performance.now();
function desktopTick() {
  const now = performance.now();
  const dt = Math.min(0.1, (now - lastTick) / 1000);
  lastTick = now;
  if (xrSession) return;
  const gp = firstGamepad();
  const gb = (i) => (gp && gp.buttons[i] ? gp.buttons[i].value : 0);
  const ga = (i) => (gp && gp.axes.length > i ? dz(gp.axes[i]) : 0);
  if (gb(4) > 0.5) activeHand = "left";
  if (gb(5) > 0.5) activeHand = "right";
  // WebXR axes: x right, y up, -z forward.
  const vx = held("KeyD") - held("KeyA") + ga(0);
  const vz = held("KeyS") - held("KeyW") + ga(1);
  const vy = held("KeyR") - held("KeyF") - ga(3);
  const wy = held("KeyQ") - held("KeyE") - ga(2);
  const v = virtual[activeHand];
  v.position[0] = clamp(v.position[0] + SPEED * dt * clamp(vx, -1, 1), -5, 5);
  v.position[1] = clamp(v.position[1] + SPEED * dt * clamp(vy, -1, 1), 0, 2.5);
  v.position[2] = clamp(v.position[2] + SPEED * dt * clamp(vz, -1, 1), -5, 5);
  v.yaw += TURN * dt * clamp(wy, -1, 1);
  const trigger = Math.max(held("Space"), gb(7));
  const squeeze = Math.max(held("KeyG"), gb(6));
  const stick = [
    clamp(held("ArrowRight") - held("ArrowLeft") + (gp ? ga(0) : 0), -1, 1),
    clamp(held("ArrowDown") - held("ArrowUp") + (gp ? ga(1) : 0), -1, 1),
  ];
  const bits = (t, s, primary, secondary) =>
    (t >= 0.5 ? 1 : 0) | (s >= 0.5 ? 2 : 0) | (primary ? 16 : 0) | (secondary ? 32 : 0);
  const make = (hand, primary, secondary) => {
    const c = virtual[hand];
    const active = hand === activeHand;
    const t = active ? trigger : 0, s = active ? squeeze : 0;
    return {
      position: { x: c.position[0], y: c.position[1], z: c.position[2] },
      orientation: { x: 0, y: Math.sin(c.yaw / 2), z: 0, w: Math.cos(c.yaw / 2) },
      trigger: t, squeeze: s, axes: active ? stick : [0, 0], buttons: bits(t, s, primary, secondary),
    };
  };
  const right = make("right", held("Digit1") || gb(0) > 0.5, held("Digit2") || gb(1) > 0.5);
  const left = make("left", held("Digit3") || gb(2) > 0.5, held("Digit4") || gb(3) > 0.5);
  state.mode = "desktop";
  send({ clientMs: performance.timeOrigin + now, mode: "desktop", left, right });
  renderTable({ left, right });
}

function renderTable(ctrl) {
  const rows = ["left", "right"].map((hand) => {
    const c = ctrl[hand], v = virtual[hand];
    const names = [];
    if (c.buttons & 16) names.push(hand === "right" ? "A" : "X");
    if (c.buttons & 32) names.push(hand === "right" ? "B" : "Y");
    const p = v.position.map((x) => x.toFixed(2)).join(" ");
    return `<tr class="${hand === activeHand ? "active" : ""}"><td>${hand}${hand === activeHand ? " ◀" : ""}</td>` +
      `<td class="num">${p}</td><td class="num">${(v.yaw * 180 / Math.PI).toFixed(0)}</td>` +
      `<td class="num">${c.trigger.toFixed(2)}</td><td class="num">${c.squeeze.toFixed(2)}</td><td>${names.join(" ")}</td></tr>`;
  });
  $("controllers").innerHTML = rows.join("");
}

setInterval(desktopTick, 1000 / DESKTOP_HZ);

// ---------------------------------------------------------------- WebXR mode
let xrSession = null;
let refSpace = null;
let gl = null;

function readController(frame, source) {
  const pose = frame.getPose(source.gripSpace, refSpace);
  if (!pose) return null;
  const gp = source.gamepad;
  let buttons = 0;
  for (let i = 0; i < Math.min(gp.buttons.length, 32); i++) if (gp.buttons[i].pressed) buttons |= 1 << i;
  const axes = gp.axes.length >= 4 ? [gp.axes[2], gp.axes[3]] : [0, 0]; // xr-standard thumbstick
  return {
    position: pose.transform.position, orientation: pose.transform.orientation,
    trigger: gp.buttons[0] ? gp.buttons[0].value : 0, squeeze: gp.buttons[1] ? gp.buttons[1].value : 0,
    axes, buttons,
  };
}

function readHand(frame, hand) {
  const joints = JOINTS.map((name) => {
    const space = hand.get(name);
    const pose = space ? frame.getJointPose(space, refSpace) : null;
    return pose ? { position: pose.transform.position, orientation: pose.transform.orientation, radius: pose.radius } : null;
  });
  return joints[0] ? joints : null; // a hand without a tracked wrist is left out
}

function onXRFrame(time, frame) {
  const session = frame.session;
  session.requestAnimationFrame(onXRFrame);
  const out = { clientMs: performance.timeOrigin + time, mode: state.mode };
  const viewer = frame.getViewerPose(refSpace);
  if (viewer) out.head = { position: viewer.transform.position, orientation: viewer.transform.orientation };
  for (const source of session.inputSources) {
    const side = source.handedness;
    if (side !== "left" && side !== "right") continue;
    if (source.hand) {
      const joints = readHand(frame, source.hand);
      if (joints) out[`${side}Hand`] = joints;
    } else if (source.gripSpace && source.gamepad) {
      const c = readController(frame, source);
      if (c) out[side] = c;
    }
  }
  send(out);
  const layer = session.renderState.baseLayer;
  if (gl && layer) {
    gl.bindFramebuffer(gl.FRAMEBUFFER, layer.framebuffer);
    const ar = state.mode === "immersive-ar";
    gl.clearColor(0.08, 0.09, 0.1, ar ? 0 : 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
  }
}

async function enterXR(mode) {
  if (xrSession) { xrSession.end(); return; }
  try {
    const session = await navigator.xr.requestSession(mode, { optionalFeatures: ["local-floor", "hand-tracking"] });
    const canvas = $("gl");
    gl = canvas.getContext("webgl2", { xrCompatible: true }) || canvas.getContext("webgl", { xrCompatible: true });
    await session.updateRenderState({ baseLayer: new XRWebGLLayer(session, gl) });
    try {
      refSpace = await session.requestReferenceSpace("local-floor");
      note("Streaming from the headset (local-floor: origin on the floor).");
    } catch {
      refSpace = await session.requestReferenceSpace("local");
      note("local-floor is not supported here: heights are relative to the starting head position.", true);
    }
    xrSession = session;
    state.mode = mode;
    $("mode").textContent = mode;
    $(mode === "immersive-ar" ? "enter-ar" : "enter-vr").textContent = "Exit";
    session.addEventListener("end", () => {
      xrSession = null; refSpace = null; state.mode = "desktop";
      $("enter-vr").textContent = "Enter VR"; $("enter-ar").textContent = "Enter AR";
      note("XR session ended: back to desktop mode.");
    });
    session.requestAnimationFrame(onXRFrame);
  } catch (err) {
    state.lastError = String(err);
    note(`Could not start ${mode}: ${err}`, true);
  }
}

function note(text, warn = false) { $("note").textContent = text; $("note").className = warn ? "warn" : ""; }

async function detectXR() {
  if (!navigator.xr) {
    note(window.isSecureContext
      ? "WebXR is not available in this browser: desktop mode (keyboard and gamepad)."
      : "WebXR needs HTTPS (or http://localhost): desktop mode (keyboard and gamepad).", !window.isSecureContext);
    return;
  }
  for (const mode of ["immersive-vr", "immersive-ar"]) {
    try { state.xrSupported[mode] = await navigator.xr.isSessionSupported(mode); } catch { /* unsupported */ }
  }
  $("enter-vr").hidden = !state.xrSupported["immersive-vr"];
  $("enter-ar").hidden = !state.xrSupported["immersive-ar"];
  note(state.xrSupported["immersive-vr"] || state.xrSupported["immersive-ar"]
    ? "WebXR ready: press Enter VR / Enter AR in the headset. Until then, desktop mode."
    : "No immersive WebXR device: desktop mode (keyboard and gamepad).");
}

$("enter-vr").addEventListener("click", () => enterXR("immersive-vr"));
$("enter-ar").addEventListener("click", () => enterXR("immersive-ar"));
connect();
detectXR();
