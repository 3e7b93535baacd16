// Emulated navigator.xr for testing the telerig page without a headset (inject before the page loads).
// Scene, in the WebXR local-floor space (x right, y up, -z forward, metres), at time t [s] since the
// session started:
//   head             position (0, 1.6, -0.1 t)  (walks forward at 0.1 m/s), identity orientation
//   right controller position (0.25, 1.1, -0.4), identity grip (pointing forward, top up),
//                    trigger 0.75, squeeze 0.25, thumbstick (0.5, -1), buttons A (4) and trigger (0) pressed
//   left controller  position (-0.25, 1.0, -0.3), grip turned 90 deg left about +y,
//                    trigger 0, squeeze 1 (pressed), thumbstick (0, 0), button Y (5) pressed
//   left hand        flat, fingers forward, wrist (-0.2, 1.0, -0.3), joints 2 cm apart, radius 0.01
//   right hand       not present
// Frames come every 1000/72 ms (72 Hz) from setTimeout.
(() => {
  const JOINTS = [
    "wrist", "thumb-metacarpal", "thumb-phalanx-proximal", "thumb-phalanx-distal", "thumb-tip",
    ...["index-finger", "middle-finger", "ring-finger", "pinky-finger"].flatMap((f) =>
      ["metacarpal", "phalanx-proximal", "phalanx-intermediate", "phalanx-distal", "tip"].map((p) => `${f}-${p}`)),
  ];
  const S = Math.SQRT1_2;
  const pose = (x, y, z, q = [0, 0, 0, 1]) => ({
    transform: { position: { x, y, z, w: 1 }, orientation: { x: q[0], y: q[1], z: q[2], w: q[3] } },
  });
  const button = (value, pressed = value >= 0.5) => ({ value, pressed, touched: pressed });
  const gamepad = (values, pressed, axes) => ({
    mapping: "xr-standard", connected: true, axes,
    buttons: values.map((v, i) => button(v, pressed.includes(i))),
  });
  // Hand joint offsets: the wrist, then per finger its joints 2 cm apart along -z.
  const handOffsets = [[0, 0, 0]];
  for (let finger = 0; finger < 5; finger++) {
    for (let k = 0; k < (finger === 0 ? 4 : 5); k++) handOffsets.push([(finger - 2) * 0.02, 0, -(k + 1) * 0.02]);
  }
  class FakeHand extends Map {
    constructor() { super(JOINTS.map((name) => [name, { jointName: name }])); }
  }
  const sources = [
    { handedness: "right", targetRayMode: "tracked-pointer", gripSpace: { id: "grip-right" }, targetRaySpace: {},
      gamepad: gamepad([0.75, 0.25, 0, 0, 1, 0], [0, 4], [0, 0, 0.5, -1]), hand: null, profiles: [] },
    { handedness: "left", targetRayMode: "tracked-pointer", gripSpace: { id: "grip-left" }, targetRaySpace: {},
      gamepad: gamepad([0, 1, 0, 0, 0, 1], [1, 5], [0, 0, 0, 0]), hand: null, profiles: [] },
    { handedness: "left", targetRayMode: "tracked-pointer", gripSpace: { id: "grip-left-hand" }, targetRaySpace: {},
      gamepad: null, hand: new FakeHand(), profiles: [] },
  ];

  class FakeFrame {
    constructor(session, t) { this.session = session; this.t = t; }
    getViewerPose() { return { ...pose(0, 1.6, -0.1 * this.t), views: [] }; }
    getPose(space) {
      if (space.id === "grip-right") return pose(0.25, 1.1, -0.4);
      if (space.id === "grip-left") return pose(-0.25, 1.0, -0.3, [0, S, 0, S]);
      return null;
    }
    getJointPose(space) {
      const o = handOffsets[JOINTS.indexOf(space.jointName)];
      return { ...pose(-0.2 + o[0], 1.0 + o[1], -0.3 + o[2]), radius: 0.01 };
    }
  }

  class FakeSession extends EventTarget {
    constructor(mode) {
      super();
      this.mode = mode;
      this.inputSources = sources;
      this.renderState = { baseLayer: null };
      this.environmentBlendMode = mode === "immersive-ar" ? "alpha-blend" : "opaque";
      this.visibilityState = "visible";
      this.ended = false;
      this.start = performance.now();
      this.nextHandle = 1;
      this.timers = new Map();
    }
    async updateRenderState(state) { Object.assign(this.renderState, state); }
    async requestReferenceSpace(type) {
      if (type !== "local-floor" && type !== "local" && type !== "viewer") throw new DOMException("unsupported", "NotSupportedError");
      return { type };
    }
    requestAnimationFrame(callback) {
      const handle = this.nextHandle++;
      this.timers.set(handle, setTimeout(() => {
        this.timers.delete(handle);
        if (this.ended) return;
        const now = performance.now();
        callback(now, new FakeFrame(this, (now - this.start) / 1000));
      }, 1000 / 72));
      return handle;
    }
    cancelAnimationFrame(handle) { clearTimeout(this.timers.get(handle)); this.timers.delete(handle); }
    async end() {
      if (this.ended) return;
      this.ended = true;
      for (const t of this.timers.values()) clearTimeout(t);
      this.dispatchEvent(new Event("end"));
    }
  }

  window.XRWebGLLayer = class { constructor(session, context) { this.framebuffer = null; this.context = context; } };
  const xr = {
    async isSessionSupported(mode) { return mode === "immersive-vr" || mode === "immersive-ar"; },
    async requestSession(mode) { return new FakeSession(mode); },
  };
  Object.defineProperty(navigator, "xr", { value: xr, configurable: true });
  window.__fakeXR = true;
})();
