"""Test and demo peers for mocap: a fake Motive NatNet server, a typical frame and a synthetic BVH clip."""

from __future__ import annotations

import contextlib
import math
import selectors
import socket
import threading
import time
from collections import Counter
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np

from telerig.devices.mocap._axes import matrix_to_quat
from telerig.devices.mocap.bvh import BvhClip, parse_bvh
from telerig.devices.mocap.protocol import (
    NAT_CONNECT,
    NAT_KEEPALIVE,
    NAT_REQUEST_MODELDEF,
    LabeledMarker,
    MarkerSetData,
    MarkerSetDescription,
    MocapFrame,
    ModelDefinitions,
    NatNetVersion,
    RigidBodyData,
    RigidBodyDescription,
    ServerInfo,
    SkeletonData,
    SkeletonDescription,
    encode_frame,
    encode_model_definitions,
    encode_server_info,
    split_packet,
)
from telerig.errors import WireError

__all__ = [
    "RIGID_BODY_NAMES",
    "SKELETON_NAME",
    "FakeNatNetServer",
    "reaching_bvh",
    "sample_bvh_path",
    "typical_payload",
]

#: Rigid bodies the fake server streams (ids 1..5), Motive world Y up, metres.
RIGID_BODY_NAMES: tuple[str, ...] = ("right_wrist", "left_wrist", "head", "tool", "table")
SKELETON_NAME = "operator"
_SKELETON_ID = 1
_CLOCK_HZ = 10_000_000  # Windows QueryPerformanceCounter frequency on most hosts

# Synthetic skeleton, CMU-style names: (name, parent, offset [cm], Y up, facing +Z, +X = performer's left).
_BONES: tuple[tuple[str, str | None, tuple[float, float, float]], ...] = (
    ("Hips", None, (0.0, 0.0, 0.0)),
    ("LeftUpLeg", "Hips", (9.0, -5.0, 0.0)),
    ("LeftLeg", "LeftUpLeg", (0.0, -42.0, 0.0)),
    ("LeftFoot", "LeftLeg", (0.0, -40.0, 0.0)),
    ("LeftToeBase", "LeftFoot", (0.0, -5.0, 12.0)),
    ("RightUpLeg", "Hips", (-9.0, -5.0, 0.0)),
    ("RightLeg", "RightUpLeg", (0.0, -42.0, 0.0)),
    ("RightFoot", "RightLeg", (0.0, -40.0, 0.0)),
    ("RightToeBase", "RightFoot", (0.0, -5.0, 12.0)),
    ("Spine", "Hips", (0.0, 10.0, 0.0)),
    ("Spine1", "Spine", (0.0, 15.0, 0.0)),
    ("Neck", "Spine1", (0.0, 20.0, 0.0)),
    ("Head", "Neck", (0.0, 10.0, 0.0)),
    ("LeftShoulder", "Spine1", (3.0, 17.0, 0.0)),
    ("LeftArm", "LeftShoulder", (15.0, 0.0, 0.0)),
    ("LeftForeArm", "LeftArm", (28.0, 0.0, 0.0)),
    ("LeftHand", "LeftForeArm", (25.0, 0.0, 0.0)),
    ("RightShoulder", "Spine1", (-3.0, 17.0, 0.0)),
    ("RightArm", "RightShoulder", (-15.0, 0.0, 0.0)),
    ("RightForeArm", "RightArm", (-28.0, 0.0, 0.0)),
    ("RightHand", "RightForeArm", (-25.0, 0.0, 0.0)),
)
_END_SITES = {
    "LeftToeBase": (0.0, 0.0, 5.0),
    "RightToeBase": (0.0, 0.0, 5.0),
    "Head": (0.0, 15.0, 0.0),
    "LeftHand": (18.0, 0.0, 0.0),
    "RightHand": (-18.0, 0.0, 0.0),
}
_HIP_HEIGHT_CM = 92.0


def _min_jerk(u: float) -> float:
    u = min(1.0, max(0.0, u))
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


def _reach(t: float, duration_s: float) -> float:
    """Reach progress in [0, 1]: hold, reach out (40%), hold, return (27%), hold."""
    u = t / duration_s
    if u < 0.5:
        return _min_jerk((u - 0.1) / 0.4)
    return 1.0 - _min_jerk((u - 0.67) / 0.27)


def _channels(t: float, duration_s: float) -> dict[str, tuple[float, ...]]:
    """Channel values at time t: root (x, y, z [cm], Z, X, Y [deg]); joints (Z, X, Y [deg])."""
    r = _reach(t, duration_s)
    elbow = 10.0 + 45.0 * math.sin(math.pi * r) - 5.0 * r
    sway = 1.5 * math.sin(2.0 * math.pi * t / duration_s)
    out: dict[str, tuple[float, ...]] = {name: (0.0, 0.0, 0.0) for name, _, _ in _BONES}
    out["Hips"] = (sway, _HIP_HEIGHT_CM, 0.0, 0.0, 0.0, 0.0)
    out["Spine"] = (0.0, 8.0 * r, 0.0)
    out["Neck"] = (0.0, -4.0 * r, 0.0)
    out["LeftArm"] = (-80.0, 0.0, 0.0)
    out["LeftForeArm"] = (0.0, 0.0, -10.0)
    out["RightArm"] = (80.0 * (1.0 - r), 0.0, 85.0 * r)
    out["RightForeArm"] = (0.0, 0.0, elbow)
    out["RightHand"] = (0.0, -10.0 * r, 0.0)
    return out


def _fmt(v: float) -> str:
    text = f"{v:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def reaching_bvh(frame_rate_hz: float = 60.0, duration_s: float = 3.0) -> str:
    """BVH text of a person reaching forward with the right arm and back (centimetres, Y up).

    CMU-style joint names (Hips, LeftUpLeg, ..., Spine, Spine1, Neck, Head, RightShoulder,
    RightArm, RightForeArm, RightHand); root channels ``Xposition Yposition Zposition Zrotation
    Xrotation Yrotation``, joints ``Zrotation Xrotation Yrotation``; minimum-jerk timing.
    """
    children: dict[str | None, list[int]] = {}
    for i, (_, parent, _) in enumerate(_BONES):
        children.setdefault(parent, []).append(i)
    lines = ["HIERARCHY"]

    def emit(i: int, depth: int) -> None:
        name, parent, offset = _BONES[i]
        pad = "  " * depth
        lines.append(f"{pad}{'ROOT' if parent is None else 'JOINT'} {name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {' '.join(_fmt(v) for v in offset)}")
        if parent is None:
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation")
        else:
            lines.append(f"{pad}  CHANNELS 3 Zrotation Xrotation Yrotation")
        for c in children.get(name, []):
            emit(c, depth + 1)
        if name in _END_SITES:
            lines.extend(
                [
                    f"{pad}  End Site",
                    f"{pad}  {{",
                    f"{pad}    OFFSET {' '.join(map(_fmt, _END_SITES[name]))}",
                ]
            )
            lines.append(f"{pad}  }}")
        lines.append(f"{pad}}}")

    emit(0, 0)
    frames = round(frame_rate_hz * duration_s)
    lines += ["MOTION", f"Frames: {frames}", f"Frame Time: {1.0 / frame_rate_hz:.7f}"]
    order = [name for name, _, _ in _BONES]
    # File order is depth-first, which is the order emit() wrote the joints in.
    written = [ln.split()[1] for ln in lines if ln.strip().startswith(("ROOT", "JOINT"))]
    assert sorted(written) == sorted(order)
    for k in range(frames):
        ch = _channels(k / frame_rate_hz, duration_s)
        lines.append(" ".join(_fmt(v) for name in written for v in ch[name]))
    return "\n".join(lines) + "\n"


def sample_bvh_path() -> Path:
    """The shipped clip ``data/reach.bvh``: :func:`reaching_bvh` at 60 Hz for 3 s."""
    return Path(str(resources.files("telerig.devices.mocap") / "data" / "reach.bvh"))


@cache
def _skeleton_motion(rate_hz: float) -> tuple[BvhClip, np.ndarray, np.ndarray]:
    clip = parse_bvh(reaching_bvh(rate_hz, 3.0))
    pos, rot = clip.forward_kinematics()
    keep = [j for j, jt in enumerate(clip.joints) if not jt.end_site]
    q = matrix_to_quat(rot[:, keep])  # w, x, y, z
    return clip, pos[:, keep] * 0.01, q


def _skeleton_definition(clip: BvhClip) -> SkeletonDescription:
    joints = [j for j in clip.joints if not j.end_site]
    index = {j.name: i for i, j in enumerate(joints)}
    bones = []
    for i, j in enumerate(joints):
        parent = clip.joints[j.parent].name if j.parent >= 0 else None
        parent_id = index[parent] + 1 if parent is not None else 0
        offset = tuple(0.01 * v for v in j.offset)
        bones.append(RigidBodyDescription(j.name, i + 1, parent_id, offset))  # type: ignore[arg-type]
    return SkeletonDescription(SKELETON_NAME, _SKELETON_ID, tuple(bones))


class FakeNatNetServer:
    """A local Motive stand-in on 127.0.0.1 that speaks NatNet over UDP.

    Answers NAT_CONNECT with NAT_SERVERINFO (version, 10 MHz clock) and NAT_REQUEST_MODELDEF
    with NAT_MODELDEF (five rigid bodies, one 21-bone skeleton); streams NAT_FRAMEOFDATA at
    ``rate_hz`` to ``data_target`` or, when None, to every client that connected (Motive's
    unicast). Rigid bodies move on smooth circles; the skeleton plays :func:`reaching_bvh`;
    with ``invalid_every=N`` every N-th frame marks the first rigid body untracked, and with
    ``lose_every=N`` every N-th frame is never sent (a lossy network: its frame number is skipped).
    """

    def __init__(
        self,
        *,
        version: str = "4.1",
        rate_hz: float = 120.0,
        host: str = "127.0.0.1",
        command_port: int = 0,
        data_target: tuple[str, int] | None = None,
        invalid_every: int = 0,
        lose_every: int = 0,
    ) -> None:
        self.version = NatNetVersion.parse(version)
        self.rate_hz = rate_hz
        self._host = host
        self._command_port = command_port
        self.data_target = data_target
        self.invalid_every = invalid_every
        self.lose_every = lose_every
        clip, self._bone_pos, self._bone_rot = _skeleton_motion(rate_hz)
        self.models = ModelDefinitions(
            rigid_bodies=tuple(RigidBodyDescription(n, i + 1) for i, n in enumerate(RIGID_BODY_NAMES)),
            skeletons=(_skeleton_definition(clip),),
            marker_sets=(MarkerSetDescription("all", ("m1", "m2")),),
        )
        self.requests: Counter[int] = Counter()
        self.clients: set[tuple[str, int]] = set()
        self.frames_sent = 0
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()

    @property
    def address(self) -> tuple[str, int]:
        """Command channel (host, port); valid after :meth:`start`."""
        if self._sock is None:
            raise RuntimeError("FakeNatNetServer is not started")
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    def server_info(self) -> ServerInfo:
        """The NAT_SERVERINFO this server sends."""
        return ServerInfo(
            "Motive", (3, 1, 0, 0), (self.version.major, self.version.minor, 0, 0), _CLOCK_HZ, 0, False, ""
        )

    def frame_at(self, k: int) -> MocapFrame:
        """Frame k (pure): rigid bodies, skeleton, markers and timestamps at t = k / rate_hz."""
        t = k / self.rate_hz
        bodies = []
        for i in range(len(RIGID_BODY_NAMES)):
            a = 2.0 * math.pi * 0.25 * t + i
            pos = (0.3 * i - 0.6 + 0.1 * math.cos(a), 1.0 + 0.05 * math.sin(2 * a), 0.4 + 0.1 * math.sin(a))
            half = 0.5 * a
            quat = (0.0, math.sin(half), 0.0, math.cos(half))  # about Motive's Y (up), scalar last
            params = 0 if (self.invalid_every and k % self.invalid_every == 0 and i == 0) else 1
            bodies.append(RigidBodyData(i + 1, pos, quat, 0.0004, params))
        f = k % self._bone_pos.shape[0]
        bones = tuple(
            RigidBodyData(
                (_SKELETON_ID << 16) | (j + 1),
                tuple(self._bone_pos[f, j]),
                (*self._bone_rot[f, j, 1:], self._bone_rot[f, j, 0]),
                0.0005,
                1,
            )
            for j in range(self._bone_pos.shape[1])
        )
        ticks = round(t * _CLOCK_HZ) + _CLOCK_HZ  # the server clock started a second earlier
        return MocapFrame(
            frame_number=k,
            marker_sets=(MarkerSetData("all", ((0.0, 1.0, 0.0), (0.1, 1.0, 0.0))),),
            unlabeled_markers=((0.5, 0.02, 0.5),),
            rigid_bodies=tuple(bodies),
            skeletons=(SkeletonData(_SKELETON_ID, bones),),
            labeled_markers=(LabeledMarker((1 << 16) | 1, (0.0, 1.0, 0.0)),),
            timestamp=t,
            stamp_camera_mid_exposure=ticks,
            stamp_data_received=ticks + 20_000,
            stamp_transmit=ticks + 40_000,
            params=0,
        )

    def start(self) -> FakeNatNetServer:
        """Bind the command socket and start answering and streaming. Returns self."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind((self._host, self._command_port))
        self._sock = sock
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, args=(sock, self._stop), name="fake-natnet", daemon=True
        )
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop and close. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> FakeNatNetServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def send_raw(self, packet: bytes) -> None:
        """Send arbitrary bytes to every frame destination (for bad-input tests)."""
        if self._sock is not None:
            for target in self._targets():
                self._sock.sendto(packet, target)

    def _targets(self) -> list[tuple[str, int]]:
        with self._lock:
            return [self.data_target] if self.data_target is not None else sorted(self.clients)

    def _run(self, sock: socket.socket, stop: threading.Event) -> None:
        sel = selectors.DefaultSelector()
        sel.register(sock, selectors.EVENT_READ)
        period = 1.0 / self.rate_hz
        t0 = time.perf_counter()
        k = 0
        try:
            while not stop.is_set():
                timeout = max(0.0, t0 + k * period - time.perf_counter())
                if sel.select(timeout=timeout):
                    try:
                        packet, addr = sock.recvfrom(65536)
                        self._answer(sock, packet, (str(addr[0]), int(addr[1])))
                    except (OSError, WireError):
                        pass
                    continue
                targets = self._targets()
                if targets and not (self.lose_every and k % self.lose_every == 0):
                    data = encode_frame(self.frame_at(k), self.version)
                    for target in targets:
                        with contextlib.suppress(OSError):
                            sock.sendto(data, target)
                    self.frames_sent += 1
                k += 1
        finally:
            sel.close()

    def _answer(self, sock: socket.socket, packet: bytes, addr: tuple[str, int]) -> None:
        message_id, _ = split_packet(packet)
        with self._lock:
            self.requests[message_id] += 1
            if message_id in (NAT_CONNECT, NAT_KEEPALIVE):
                self.clients.add(addr)
        if message_id == NAT_CONNECT:
            sock.sendto(encode_server_info(self.server_info()), addr)
        elif message_id == NAT_REQUEST_MODELDEF:
            sock.sendto(encode_model_definitions(self.models, self.version), addr)


def typical_payload() -> bytes:
    """One NatNet 4.1 NAT_FRAMEOFDATA datagram: 5 rigid bodies and a 21-bone skeleton."""
    return encode_frame(FakeNatNetServer().frame_at(42), NatNetVersion(4, 1))
