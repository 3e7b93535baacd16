// The operator scene: the rig's robots from their models, live joint states and the operator's aids,
// in one three.js view. The server sends the geometry once and the state at a bounded rate
// (/api/scene); this page renders at the display rate and never talks to the control loop.
// Robot frames are z-up metres; the whole rig hangs under `world`, turned to three's y-up, so a
// WebXR session (head pose drives the camera) sees the robots upright in front of the operator.
import * as THREE from "three";
import { OrbitControls } from "/scene/OrbitControls.js";

const $ = (id) => document.getElementById(id);
const renderer = new THREE.WebGLRenderer({ canvas: $("view"), antialias: true });
renderer.xr.enabled = true;
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x1d232a);
scene.add(new THREE.HemisphereLight(0xffffff, 0x404850, 2.2));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
sun.position.set(2, 4, 3);
scene.add(sun);
const world = new THREE.Group(); // z-up robot frames -> three's y-up, x forward -> -z (away from you)
world.rotation.set(-Math.PI / 2, 0, Math.PI / 2, "XYZ");
scene.add(world);
const grid = new THREE.GridHelper(6, 24, 0x5a6570, 0x333b44);
grid.rotation.x = Math.PI / 2; // into the robots' xy plane
world.add(grid);

const camera = new THREE.PerspectiveCamera(50, 1, 0.02, 60);
const controls = new OrbitControls(camera, renderer.domElement);
controls.enabled = false;
const stats = { frames: 0, states: 0, previews: 0, settled: false, scene: null, latency: null }; // read by the tests
let dirty = true; // render when something changed (a state, the camera, a preview, the size), or in XR
window.sceneStats = stats;

// --- robots ------------------------------------------------------------------------------------

const robots = new Map(); // id -> { root, bodies, parts, markers, panel }
const v3 = (a, i = 0) => new THREE.Vector3(a[i], a[i + 1], a[i + 2]);
const q4 = (a, i = 0) => new THREE.Quaternion(a[i + 1], a[i + 2], a[i + 3], a[i]); // wire: w x y z

function decode(b64, Type) {
  const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  return new Type(bytes.buffer);
}

function geometryOf(geom, meshes) {
  const [a, b, c] = geom.size;
  switch (geom.type) {
    case "box": return new THREE.BoxGeometry(2 * a, 2 * b, 2 * c);
    case "sphere": return new THREE.SphereGeometry(a, 16, 12);
    case "ellipsoid": return new THREE.SphereGeometry(1, 16, 12).scale(a, b, c);
    case "capsule": return new THREE.CapsuleGeometry(a, 2 * b, 4, 12).rotateX(Math.PI / 2);
    case "cylinder": return new THREE.CylinderGeometry(a, a, 2 * b, 16).rotateX(Math.PI / 2);
    case "mesh": return meshes[geom.mesh];
    default: return null;
  }
}

function marker(colour, radius, wire = false) {
  const material = new THREE.MeshBasicMaterial({ color: colour, wireframe: wire, transparent: true, opacity: 0.9 });
  const mesh = new THREE.Mesh(new THREE.SphereGeometry(radius, 16, 12), material);
  mesh.visible = false;
  return mesh;
}

function buildRobot(doc) {
  const root = new THREE.Group();
  root.position.fromArray(doc.origin);
  world.add(root);
  const panel = document.createElement("article");
  panel.className = "robot";
  panel.dataset.robot = doc.id;
  panel.innerHTML = `<h2></h2><p class="aids"></p><p class="reach"></p><p class="plan" hidden></p>`;
  panel.querySelector("h2").textContent = `${doc.id} (${doc.model || doc.type}) `;
  $("robots").append(panel);
  const entry = { doc, root, bodies: [], parts: [], panel, markers: {} };
  robots.set(doc.id, entry);
  if (doc.error) {
    panel.querySelector(".aids").textContent = doc.error;
    panel.querySelector(".aids").className = "warn";
    return;
  }
  const meshes = doc.meshes.map((m) => {
    const g = new THREE.BufferGeometry();
    g.setAttribute("position", new THREE.BufferAttribute(decode(m.vertices, Float32Array), 3));
    g.setIndex(new THREE.BufferAttribute(decode(m.faces, Uint32Array), 1)); // int32 >= 0 on the wire
    g.computeVertexNormals();
    return g;
  });
  entry.bodies = doc.bodies.map(() => {
    const body = new THREE.Group();
    root.add(body);
    return body;
  });
  for (const geom of doc.geoms) {
    const shape = geometryOf(geom, meshes);
    if (!shape) continue;
    const [r, g, b, alpha] = geom.rgba;
    const material = new THREE.MeshStandardMaterial({
      color: new THREE.Color(r, g, b), roughness: 0.6, metalness: 0.1, transparent: alpha < 1, opacity: alpha,
    });
    const part = new THREE.Mesh(shape, material);
    part.position.fromArray(geom.pos);
    part.quaternion.copy(q4(geom.quat));
    entry.bodies[geom.body].add(part);
    entry.parts.push(part);
  }
  const m = entry.markers;
  m.ee = marker(0xffd54f, 0.012);
  m.target = marker(0x4dd0e1, 0.03, true);
  m.hand = new THREE.AxesHelper(0.08);
  m.hand.add(marker(0xe040fb, 0.02));
  m.hand.children[0].visible = true;
  m.hand.visible = false;
  m.link = new THREE.Line(new THREE.BufferGeometry().setFromPoints([v3([0, 0, 0]), v3([0, 0, 0])]),
    new THREE.LineDashedMaterial({ color: 0xe040fb, dashSize: 0.02, gapSize: 0.015 }));
  m.link.visible = false;
  // Reach: a ring on the floor at the farthest the grasp point gets; it lights up on an unreachable target.
  const r = doc.reach_m || 0.01;
  m.reach = new THREE.Mesh(new THREE.RingGeometry(r - 0.01, r, 96),
    new THREE.MeshBasicMaterial({ color: 0x90a4ae, transparent: true, opacity: 0.3, side: THREE.DoubleSide }));
  m.reach.visible = doc.reach_m > 0;
  m.fixture = new THREE.Group();
  m.plan = new THREE.Group();
  m.aim = aimMarker();
  for (const obj of Object.values(m)) root.add(obj);
  applyState(entry, {}); // home pose until the first state
}

// The plan marker (issue 17): where "plan here" will plan the reach to, from the operator's marker
// device mapped into the robot's world; an orange cross in a wire ball, labelled "target".
const AIM = 0xff9800;

function aimMarker() {
  const group = new THREE.Group();
  const half = 0.08;
  const cross = [[half, 0, 0], [-half, 0, 0], [0, half, 0], [0, -half, 0], [0, 0, half], [0, 0, -half]];
  group.add(new THREE.LineSegments(new THREE.BufferGeometry().setFromPoints(cross.map((p) => v3(p))),
    new THREE.LineBasicMaterial({ color: AIM })));
  group.add(new THREE.Mesh(new THREE.SphereGeometry(0.03, 16, 12), new THREE.MeshBasicMaterial({ color: AIM })));
  const canvas = document.createElement("canvas");
  canvas.width = 256;
  canvas.height = 64;
  const ctx = canvas.getContext("2d");
  ctx.fillStyle = "#ff9800";
  ctx.font = "bold 48px sans-serif";
  ctx.textAlign = "center";
  ctx.fillText("target", 128, 50);
  const texture = new THREE.CanvasTexture(canvas);
  texture.colorSpace = THREE.SRGBColorSpace;
  const label = new THREE.Sprite(new THREE.SpriteMaterial({ map: texture, depthTest: false }));
  label.scale.set(0.3, 0.075, 1);
  label.position.set(0, -0.12, 0.05); // beside the cross, readable from above and from behind
  group.add(label);
  group.visible = false;
  return group;
}

// A staged or executing reach plan (issue 17): the base's path on the floor, the grasp point's path
// and the target, in the robot's world frame (its base joints are part of its state).
const PLAN_SHOWN = new Set(["staged", "executing"]);

function drawPlan(group, plan) {
  const shown = Boolean(plan && plan.id && PLAN_SHOWN.has(plan.status));
  const key = shown ? `${plan.id}:${plan.status}` : "";
  if (group.userData.key === key) return;
  group.userData.key = key;
  group.clear();
  group.visible = shown;
  if (!shown) return;
  const colour = plan.status === "executing" ? 0x66bb6a : 0x29b6f6;
  const line = (points, dashed) => {
    const geometry = new THREE.BufferGeometry().setFromPoints(points);
    const material = dashed ? new THREE.LineDashedMaterial({ color: colour, dashSize: 0.04, gapSize: 0.02 })
      : new THREE.LineBasicMaterial({ color: colour });
    const obj = new THREE.Line(geometry, material);
    if (dashed) obj.computeLineDistances();
    return obj;
  };
  const base = (plan.base_path || []).map((p) => new THREE.Vector3(p[0], p[1], 0.01));
  if (base.length > 1) group.add(line(base, true));
  const ee = (plan.ee_path || []).map((p) => v3(p));
  if (ee.length > 1) group.add(line(ee, false));
  if (plan.target) {
    const goal = marker(colour, 0.04, true);
    goal.visible = true;
    goal.position.copy(v3(plan.target));
    group.add(goal);
  }
  group.userData.points = ee.length + base.length;
}

function showPlan(entry, plan) {
  const line = entry.panel.querySelector(".plan");
  const text = !plan || plan.status === "none" ? ""
    : plan.status === "staged" ? "plan staged — say 'robot please execute'"
      : `plan ${plan.status}${plan.reason ? `: ${plan.reason}` : ""}`;
  line.hidden = !text;
  line.textContent = text;
  line.dataset.status = plan ? plan.status : "none";
}

// A virtual fixture drawn where it acts: the allowed axis as a line, the allowed plane as a sheet,
// a kept orientation as a ring, all through the end effector.
function drawFixture(group, fixture) {
  const key = fixture ? JSON.stringify([fixture.name, fixture.kind, fixture.axis, fixture.keep_orientation]) : "";
  if (group.userData.key === key) return;
  group.userData.key = key;
  group.clear();
  group.userData.kind = fixture && fixture.kind !== "free" ? fixture.kind : null;
  if (!group.userData.kind) return;
  const colour = 0xffa726;
  const axis = new THREE.Vector3().fromArray(fixture.axis || [0, 0, 1]);
  const along = new THREE.Quaternion().setFromUnitVectors(new THREE.Vector3(0, 0, 1),
    axis.lengthSq() > 0 ? axis.normalize() : new THREE.Vector3(0, 0, 1));
  const ring = () => new THREE.Mesh(new THREE.TorusGeometry(0.07, 0.005, 8, 32),
    new THREE.MeshBasicMaterial({ color: colour }));
  let shape;
  if (fixture.kind === "axis") {
    shape = new THREE.Mesh(new THREE.CylinderGeometry(0.004, 0.004, 0.8, 8).rotateX(Math.PI / 2),
      new THREE.MeshBasicMaterial({ color: colour }));
  } else if (fixture.kind === "plane") {
    shape = new THREE.Mesh(new THREE.PlaneGeometry(0.5, 0.5),
      new THREE.MeshBasicMaterial({ color: colour, transparent: true, opacity: 0.35, side: THREE.DoubleSide }));
  } else {
    shape = ring();
  }
  shape.quaternion.copy(along);
  group.add(shape);
  if (fixture.keep_orientation && fixture.kind !== "orientation") group.add(ring()); // also holds the rotation
}

const STATUS_TINT = { estopped: 0x7f0000, stopped: 0x7f0000, holding: 0x4a3000, limited: 0x332200 };

function applyState(entry, state) {
  const { doc, bodies, markers: m } = entry;
  const poses = state.poses || [];
  for (let i = 0; i < bodies.length && 7 * i + 6 < poses.length; i++) {
    bodies[i].position.copy(v3(poses, 7 * i));
    bodies[i].quaternion.copy(q4(poses, 7 * i + 3));
  }
  if (state.base) {
    entry.root.position.fromArray(doc.origin).add(v3(state.base));
    entry.root.quaternion.copy(q4(state.base, 3));
  }
  const place = (obj, p) => { obj.visible = Boolean(p); if (p) obj.position.copy(v3(p)); };
  place(m.ee, state.ee);
  place(m.target, state.target);
  const flagged = Boolean(state.residual && state.residual.flagged);
  m.target.material.color.set(flagged ? 0xff5252 : 0x4dd0e1);
  m.reach.material.opacity = flagged ? 0.9 : 0.3;
  m.reach.material.color.set(flagged ? 0xff5252 : 0x90a4ae);
  const hand = state.hand && state.hand.pose;
  place(m.hand, hand);
  if (hand) m.hand.quaternion.copy(q4(hand, 3));
  m.link.visible = Boolean(hand && state.ee);
  let distance = null;
  if (m.link.visible) {
    m.link.geometry.setFromPoints([v3(hand), v3(state.ee)]);
    m.link.computeLineDistances();
    distance = v3(hand).distanceTo(v3(state.ee));
  }
  const aim = state.plan_marker && state.plan_marker.pose;
  place(m.aim, aim);
  drawPlan(m.plan, state.plan);
  showPlan(entry, state.plan);
  drawFixture(m.fixture, state.fixture);
  place(m.fixture, m.fixture.userData.kind ? state.ee : null);
  const tint = STATUS_TINT[state.status] || 0x000000;
  for (const part of entry.parts) part.material.emissive.setHex(tint);
  showAids(entry, state, distance, flagged);
  dirty = true;
}

function showAids(entry, state, distance, flagged) {
  const head = entry.panel.querySelector("h2");
  let badge = head.querySelector(".status");
  if (!badge) head.append((badge = document.createElement("span")));
  badge.className = "status";
  badge.dataset.status = state.status || "unknown";
  badge.textContent = state.status || "no status";
  const aids = [];
  if (state.scale) {
    const { scale, min, max } = state.scale;
    const at = (Math.log(scale) - Math.log(min)) / (Math.log(max) - Math.log(min) || 1);
    aids.push(`scale ×${Number(scale).toPrecision(3)} <span class="bar" data-at="${Math.round(100 * at)}"><i></i></span>`);
  }
  if (state.fixture) aids.push(`fixture <b class="fixture">${escape(state.fixture.name)}</b> (${escape(state.fixture.kind)})`);
  if (state.wbc) aids.push(`mode ${escape(state.wbc.mode)}`);
  if (distance !== null) aids.push(`hand ↔ EE <b class="distance">${(1000 * distance).toFixed(0)} mm</b>`);
  const aim = state.plan_marker && state.plan_marker.pose;
  if (aim) aids.push(`plan target <b class="plan-marker">${aim.slice(0, 3).map((v) => v.toFixed(2)).join(", ")} m</b>`);
  entry.panel.querySelector(".aids").innerHTML = aids.join(" · ") || "no aids";
  const bar = entry.panel.querySelector(".bar"); // widths through the CSSOM: the CSP allows no inline style
  if (bar) bar.firstChild.style.width = `${bar.dataset.at}%`;
  const reach = entry.panel.querySelector(".reach");
  const error = state.residual && state.residual.position_error_m;
  reach.className = flagged ? "reach warn" : "reach";
  reach.textContent = flagged ? `target out of reach${error ? ` by ${(1000 * error).toFixed(0)} mm` : ""}`
    : state.target ? "target reachable" : "";
}

function escape(text) {
  const span = document.createElement("span");
  span.textContent = String(text ?? "");
  return span.innerHTML;
}

// --- camera previews: a panel per camera beside the robots, facing the viewer, ~2 refreshes a second

const previews = [];

function addCamera(id, index) {
  const texture = new THREE.Texture();
  texture.colorSpace = THREE.SRGBColorSpace;
  texture.flipY = false; // the bitmap is flipped when decoded
  const panel = new THREE.Mesh(new THREE.PlaneGeometry(0.48, 0.36),
    new THREE.MeshBasicMaterial({ color: 0x3a4450, side: THREE.DoubleSide })); // grey until a preview
  panel.position.set(0.45, 0.75 + 0.55 * index, 0.75); // to the robot's left, above the table
  world.add(panel);
  previews.push(panel);
  const refresh = async () => {
    try {
      const reply = await fetch(`/api/rig/cameras/${encodeURIComponent(id)}/preview`);
      if (reply.ok) {
        texture.image = await createImageBitmap(await reply.blob(), { imageOrientation: "flipY" });
        texture.needsUpdate = true;
        if (!panel.material.map) Object.assign(panel.material, { map: texture, needsUpdate: true });
        panel.material.color.set(0xffffff);
        stats.previews += 1;
        const captureNs = reply.headers.get("X-Capture-Ns"); // a stamped preview: the video_display stage
        if (captureNs) shown.set(id, captureNs);
        dirty = true;
      }
    } catch { /* next time */ }
    setTimeout(refresh, 500);
  };
  refresh();
}

function facePreviews() {
  const toWorld = world.quaternion.clone().invert();
  for (const panel of previews) panel.quaternion.copy(toWorld).multiply(camera.quaternion);
}

// --- voice and text commands (telerig.voice): a perspective command picks the view once (a view
// chosen by hand afterwards stays); the last command's words and reply show in the HUD.

let voiceViewSeq = null;

function applyVoice(voice) {
  if (!voice) return;
  if (voice.view && voice.view_seq !== voiceViewSeq) {
    $("mode").value = voice.view;
    voiceViewSeq = voice.view_seq;
    dirty = true;
  }
  const said = voice.feedback;
  $("voice").hidden = !said;
  if (said) {
    $("voice").dataset.status = said.status || "";
    $("voice").textContent = `"${said.heard || ""}": ${said.say || said.status || ""}`;
  }
}

// --- viewpoint ---------------------------------------------------------------------------------

const goal = { eye: new THREE.Vector3(), at: new THREE.Vector3() };

function autoMode(entry) {
  if (!entry) return "free";
  return entry.doc.mobile && (!entry.state?.wbc || entry.state.wbc.mode !== "ee") ? "navigation" : "manipulation";
}

// Camera goals in a robot's frame (z up, x forward): where the eye is and what it looks at.
function viewGoal(mode, entry) {
  const ee = entry.markers.ee && entry.markers.ee.visible ? entry.markers.ee.position.clone() : new THREE.Vector3(0.4, 0, 0.3);
  const views = {
    navigation: [new THREE.Vector3(0.3, 0, 1.5 + 1.5 * (entry.doc.reach_m || 1)), new THREE.Vector3(0.3, 0, 0)],
    // Behind, above and beside the shoulder (higher and farther for a mobile manipulator's body).
    manipulation: [entry.doc.mobile ? new THREE.Vector3(-1.1, 0.7, 1.9) : new THREE.Vector3(-0.45, 0.55, 1.25), ee],
    ee: [ee.clone().add(new THREE.Vector3(-0.45, 0.05, 0.3)), ee],
    "ee-inverted": [ee.clone().add(new THREE.Vector3(0.55, -0.05, 0.3)), ee],
  };
  const [eye, at] = views[mode];
  return [entry.root.localToWorld(eye.clone()), entry.root.localToWorld(at.clone())];
}

function steer(dt) {
  const chosen = $("mode").value;
  const first = robots.values().next().value;
  const mode = chosen === "auto" ? autoMode(first) : chosen;
  controls.enabled = mode === "free";
  if (controls.enabled || !first || first.doc.error) { stats.settled = true; dirty ||= controls.update(); return; }
  world.updateMatrixWorld(true);
  const [eye, at] = viewGoal(mode, first);
  goal.eye.copy(eye);
  goal.at.copy(at);
  const k = 1 - Math.exp(-dt / 0.12); // smooth moves between perspectives, settled within ~1 s
  camera.position.lerp(goal.eye, k);
  controls.target.lerp(goal.at, k);
  // Top-down: robot forward is up on the screen.
  camera.up.copy(mode === "navigation" ? world.localToWorld(new THREE.Vector3(1, 0, 0)).sub(world.position).normalize() : new THREE.Vector3(0, 1, 0));
  camera.lookAt(controls.target);
  const settled = camera.position.distanceTo(goal.eye) < 1e-3 && controls.target.distanceTo(goal.at) < 1e-3;
  dirty ||= !settled || !stats.settled;
  stats.settled = settled;
}

// --- latency (issue 17): after drawing a robot's new joint state or a camera's new preview, tell the
// server which and when (the dashboard's /static/latency.js) ---

let latency = null; // the /static/latency.js reporter (the dashboard's), loaded once; the page works without it
const drawn = new Map(); // robot id -> state_ns applied since the last frame drawn
const shown = new Map(); // camera id -> X-Capture-Ns of the preview put on its panel since then

function reportDrawn() {
  if (drawn.size === 0 && shown.size === 0) return;
  const states = [...drawn], frames = [...shown];
  drawn.clear();
  shown.clear();
  latency?.then((reporter) => {
    for (const [id, ns] of states) reporter?.rendered(id, ns);
    for (const [id, ns] of frames) reporter?.displayed(id, ns); // repeats of one preview: reported once
  });
}

// --- link --------------------------------------------------------------------------------------

async function connect() {
  const me = await fetch("/api/me");
  if (me.status === 401) { location.href = "/login"; return; }
  const { csrf } = await me.json();
  if (!latency) {
    latency = import("/static/latency.js").then((m) => m.connectLatency({ csrf })).catch(() => undefined);
    latency.then((reporter) => { stats.latency = reporter?.stats ?? null; }); // sent, syncs: read by the tests
  }
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/api/scene`,
    ["telerig-scene.v1", `csrf.${csrf}`]);
  ws.onmessage = (event) => {
    const message = JSON.parse(event.data);
    if (message.type === "scene") {
      for (const entry of robots.values()) { entry.root.removeFromParent(); entry.panel.remove(); }
      robots.clear();
      message.robots.forEach(buildRobot);
      if (!stats.scene) message.cameras.forEach(addCamera);
      stats.scene = message;
      $("link").dataset.link = "live";
      $("link").textContent = `${message.rig}: live`;
    } else if (message.type === "state") {
      for (const [id, state] of Object.entries(message.robots)) {
        const entry = robots.get(id);
        if (!entry || entry.doc.error) continue;
        if (state.state_ns && state.state_ns !== entry.state?.state_ns) drawn.set(id, state.state_ns);
        entry.state = state;
        applyState(entry, state);
      }
      applyVoice(message.voice);
      stats.states += 1;
      $("link").dataset.link = message.connected ? "live" : "offline";
      $("link").textContent = `${stats.scene.rig}: ${message.connected ? "live" : "rig not reachable"}`;
    }
  };
  ws.onclose = (event) => {
    $("link").dataset.link = "offline";
    $("link").textContent = `offline (${event.reason || event.code}); retrying`;
    setTimeout(connect, 2000);
  };
}

async function offerXR() {
  if (!navigator.xr || !(await navigator.xr.isSessionSupported("immersive-vr").catch(() => false))) return;
  const button = $("xr");
  button.hidden = false;
  button.onclick = async () => {
    const session = await navigator.xr.requestSession("immersive-vr", { optionalFeatures: ["local-floor"] });
    renderer.xr.setReferenceSpaceType("local-floor");
    world.position.set(0, 0.75, -0.6); // the robots on a table-height plane in front of the operator
    await renderer.xr.setSession(session); // from here the head pose drives the camera
    session.addEventListener("end", () => world.position.set(0, 0, 0));
  };
}

let last = performance.now();
renderer.setAnimationLoop((now) => {
  const width = window.innerWidth, height = window.innerHeight;
  if (renderer.domElement.width !== width || renderer.domElement.height !== height) {
    renderer.setSize(width, height, false);
    camera.aspect = width / height;
    camera.updateProjectionMatrix();
    dirty = true;
  }
  if (!renderer.xr.isPresenting) steer(Math.min(0.1, (now - last) / 1000));
  last = now;
  if (!dirty && !renderer.xr.isPresenting) return; // nothing new to draw: leave the CPU/GPU idle
  dirty = false;
  facePreviews();
  renderer.render(scene, camera);
  stats.frames += 1;
  reportDrawn(); // the states applied before this frame are on screen now
});
camera.position.set(2, 1.5, 2);
connect();
offerXR();
