"""Synthetic episodes for the quality-gate tests: a UR5e's recorded streams written as the recorder
writes them (EpisodeStore draft + McapLog + manifest stats and alignment report), with the defects
each gate must catch dialled in."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from pydantic import JsonValue

from telerig.ir import wire
from telerig.ir.mcap_log import McapLog
from telerig.ir.types import (
    CameraFrame,
    FloatArray,
    GripperCommand,
    JointCommand,
    JointState,
    Pose,
    RetargetResidual,
    Sample,
    Stamp,
    Wrench,
)
from telerig.record.align import CaptureTimes
from telerig.robots.models import arm_model
from telerig.store.episodes import EpisodeStore
from telerig.store.manifest_extra import EpisodeExtra, FingerprintRecord, RobotJointsRecord, SafetyEventRecord

START_NS = 1_800_000_000_000_000_000
RIG = "qa"
ROBOT = "arm0"
UR5E = arm_model("ur5e_robotiq85")
JOINTS = UR5E.joints
HOME = np.array(UR5E.home)
#: The UR5e MJCF's joint ranges [rad] (symmetric): the elbow's is +-pi, the others' +-2 pi.
UR5E_RANGE = {j: (3.14159 if j == "elbow_joint" else 6.28319) for j in JOINTS}
#: A UR5e configuration folded into itself: elbow fully bent, wrist 1 inside the upper arm.
FOLDED = np.array([0.0, -1.57, 3.1, 0.0, -1.57, 0.0])

Trajectory = Callable[[FloatArray], FloatArray]


def ramp(t: FloatArray, t0: float, t1: float) -> FloatArray:
    """0 before ``t0``, 1 after ``t1``, a cosine ramp between (zero speed at both ends)."""
    u = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    out: FloatArray = 0.5 - 0.5 * np.cos(np.pi * u)
    return out


def reach_and_back(t: FloatArray) -> FloatArray:
    """Home, still 0.6 s; shoulder pan +0.5 rad and elbow -0.3 rad over 1.2 s; pause 0.8 s; back
    in 1.0 s; still to the end (4 s episodes: 45 % still)."""
    delta = np.array([0.5, 0.0, -0.3, 0.2, 0.0, 0.3])
    s = ramp(t, 0.6, 1.8) - ramp(t, 2.6, 3.6)
    out: FloatArray = HOME + s[:, None] * delta
    return out


def still(t: FloatArray) -> FloatArray:
    """Home for the whole episode."""
    out: FloatArray = np.tile(HOME, (t.size, 1))
    return out


def fold_and_back(t: FloatArray) -> FloatArray:
    """Home to :data:`FOLDED` over 1 s from t=0.5 s, held 0.5 s, back by 3 s."""
    s = ramp(t, 0.5, 1.5) - ramp(t, 2.0, 3.0)
    out: FloatArray = HOME + s[:, None] * (FOLDED - HOME)
    return out


@dataclass
class Recording:
    """What a synthetic episode records (every time in seconds from the episode start).

    ``sent`` is the joint command sent; the measured state is ``sent`` delayed by ``lag_s`` plus
    ``offset`` [rad]; its velocities are the measured positions' derivative times ``speed_scale``.
    """

    seconds: float = 4.0
    rate_hz: float = 100.0
    sent: Trajectory = reach_and_back
    lag_s: float = 0.03
    #: Measured minus sent [rad], per joint; none when empty.
    offset: Sequence[float] = ()
    speed_scale: float = 1.0
    #: Joint-state samples left out in these windows (recording gaps).
    state_gaps: Sequence[tuple[float, float]] = ()
    #: IK residual flagged in this window.
    residual_flagged: tuple[float, float] | None = None
    #: Record the residual as the JSON object of episodes before issue 18 (else typed).
    residual_json: bool = False
    #: Residuals only in this window [s] (the operator's input stopped outside it); all ticks when None.
    residual_window: tuple[float, float] | None = None
    status: Sequence[tuple[float, str]] = ((0.0, "ok"),)
    safety_log: Sequence[SafetyEventRecord] = ()
    tick_faults: int = 0
    #: Wrist force [N] (S, 3) at the joint-state times; None: no F/T recorded.
    force: Callable[[FloatArray], FloatArray] | None = None
    #: Base / pelvis height [m] at the joint-state times, recorded as ``base_pose``; None: not recorded.
    base_z: Callable[[FloatArray], FloatArray] | None = None
    robot_type: str = "mujoco_arm"
    model: str = "ur5e_robotiq85"
    #: The recorded joints (``sent`` gives one column each).
    joints: tuple[str, ...] = JOINTS
    #: Write the driver's joints and limits into the manifest (as the runtime does since issue 13).
    robot_joints: bool = True
    standing_height_m: float | None = None
    camera_hz: float = 30.0
    #: Windows [s] without camera frames, as ``state_gaps``.
    frame_gaps: Sequence[tuple[float, float]] = ()
    extra: dict[str, object] = field(default_factory=dict)


def _stamp(source: str, seq: int, t_ns: int) -> Stamp:
    return Stamp(source, seq, t_ns, t_ns, t_ns)


def write_episode(root: Path, rec: Recording) -> Path:
    """Record ``rec`` into a committed episode under ``root``; its directory."""
    store = EpisodeStore(root)
    draft = store.begin(rig=RIG, task="reach", operator="tester", start_ns=START_NS)
    n = round(rec.seconds * rec.rate_hz)
    t = np.arange(n) / rec.rate_hz
    t_ns = START_NS + np.round(t * 1e9).astype(np.int64)
    q_sent = rec.sent(t)
    q_meas = rec.sent(t - rec.lag_s) + (np.asarray(rec.offset) if len(rec.offset) else 0.0)
    v_meas = np.gradient(q_meas, t, axis=0) * rec.speed_scale
    keep = np.ones(n, dtype=bool)
    for a, b in rec.state_gaps:
        keep &= ~((t >= a) & (t < b))
    topic = f"telerig/v1/{RIG}/{ROBOT}"
    entries: list[tuple[str, Sample]] = []
    for i in range(n):
        ns = int(t_ns[i])
        sent = JointCommand(_stamp(ROBOT, i, ns), rec.joints, q_sent[i])
        entries.append((f"{topic}/joint_command_sent", sent))
        entries.append((f"{topic}/gripper_command_sent", GripperCommand(_stamp(ROBOT, i, ns), 1.0)))
        if keep[i]:
            state = JointState(_stamp(ROBOT, i, ns + 1_000_000), rec.joints, q_meas[i], v_meas[i])
            entries.append((f"{topic}/joint_state", state))
    if rec.force is not None:
        f = rec.force(t)
        for i in range(n):
            wrench = Wrench(_stamp(ROBOT, i, int(t_ns[i])), f[i], np.zeros(3), f"{ROBOT}/ft_sensor")
            entries.append((f"{topic}/wrench", wrench))
    if rec.base_z is not None:
        z = rec.base_z(t)
        for i in range(n):
            pose = Pose(
                _stamp(ROBOT, i, int(t_ns[i])), np.array([0.0, 0.0, z[i]]), np.array([1.0, 0, 0, 0]), "world"
            )
            entries.append((f"{topic}/base_pose", pose))
    frames = np.arange(int(rec.seconds * rec.camera_hz)) / rec.camera_hz
    for a, b in rec.frame_gaps:
        frames = frames[(frames < a) | (frames >= b)]
    for k, ft in enumerate(frames):
        ns = START_NS + round(ft * 1e9) + 2_000_000
        entries.append(
            (f"telerig/v1/{RIG}/scene/frames", CameraFrame(_stamp("scene", k, ns), "scene", k, 64, 48))
        )
    entries.sort(key=lambda e: e[1].stamp.capture_ns)
    capture = CaptureTimes()
    with McapLog(draft.mcap_path) as log:
        for name, sample in entries:
            ns = sample.stamp.capture_ns
            log.write(name, wire.encode(sample), log_time_ns=ns + 500_000, publish_time_ns=ns)
            capture.add(name, ns)
        for i in range(n):
            ns = int(t_ns[i])
            flagged = bool(
                rec.residual_flagged is not None and rec.residual_flagged[0] <= t[i] < rec.residual_flagged[1]
            )
            error = 0.05 if flagged else 1e-5
            if (
                rec.residual_window is not None
                and not rec.residual_window[0] <= t[i] < rec.residual_window[1]
            ):
                continue
            if rec.residual_json:
                doc = {"capture_ns": ns, "flagged": flagged, "position_error_m": error}
                log.write_json(f"{topic}/residual", json.dumps(doc).encode(), log_time_ns=ns + 500_000)
            else:
                residual = RetargetResidual(_stamp(ROBOT, i, ns), flagged, ("position_error_m",), (error,))
                log.write(
                    f"{topic}/residual", wire.encode(residual), log_time_ns=ns + 500_000, publish_time_ns=ns
                )
                capture.add(f"{topic}/residual", ns)  # as the recorder does for every IR sample
        for at, word in rec.status:
            log.write_json(
                f"{topic}/status", json.dumps(word).encode(), log_time_ns=START_NS + round(at * 1e9)
            )
    end_ns = START_NS + round(rec.seconds * 1e9)
    extra = EpisodeExtra(
        fingerprint=FingerprintRecord(
            digest="0" * 16, components={f"robot {ROBOT}": f"{rec.robot_type} {rec.model}"}
        ),
        robots=[rec.model],
        robot_joints={ROBOT: _joints_record(rec)} if rec.robot_joints else {},
        streams=_stream_stats(capture, rec),
        safety_events={ROBOT: {}},
        safety_log=list(rec.safety_log),
        tick_faults={ROBOT: rec.tick_faults},
        alignment=capture.report(),
    ).to_json()
    extra.update(rec.extra)  # type: ignore[arg-type]
    manifest = draft.commit(extra, end_ns=end_ns)
    return store.root / "episodes" / manifest.id


def _joints_record(rec: Recording) -> RobotJointsRecord:
    return RobotJointsRecord(
        type=rec.robot_type,
        model=rec.model,
        joints=list(JOINTS),
        lower=[-UR5E_RANGE[j] for j in JOINTS],
        upper=[UR5E_RANGE[j] for j in JOINTS],
        velocity=list(UR5E.velocity),
        acceleration=list(UR5E.acceleration),
        gripper=True,
        standing_height_m=rec.standing_height_m,
    )


def _stream_stats(capture: CaptureTimes, rec: Recording) -> list[dict[str, JsonValue]]:
    out: list[dict[str, JsonValue]] = []
    for name, times in sorted(capture.times.items()):
        arr = np.sort(np.asarray(times, dtype=np.int64))
        span = (arr[-1] - arr[0]) / 1e9
        expected = rec.camera_hz if name.endswith("/frames") else rec.rate_hz
        out.append(
            {
                "name": name,
                "expected_hz": expected,
                "measured_hz": (arr.size - 1) / span if span > 0 else 0.0,
                "messages": int(arr.size),
                "drops": 0,
                "max_gap_ms": float(np.diff(arr).max() / 1e6) if arr.size > 1 else 0.0,
                "rejected": {},
            }
        )
    return out


class Synthetic:
    """What the tests use to write synthetic episodes (handed out by the ``synthetic`` fixture).

    ``make(**fields)`` writes an episode of :class:`Recording` fields and returns its directory.
    """

    home = HOME
    folded = FOLDED
    still = staticmethod(still)
    ramp = staticmethod(ramp)
    fold_and_back = staticmethod(fold_and_back)
    reach_and_back = staticmethod(reach_and_back)

    def __init__(self, root: Path) -> None:
        self._root = root

    def make(self, **fields: object) -> Path:
        return write_episode(self._root, Recording(**fields))  # type: ignore[arg-type]


@pytest.fixture
def synthetic(tmp_path: Path) -> Synthetic:
    """Writes synthetic episodes under the test's temp dir."""
    return Synthetic(tmp_path / "data")


@pytest.fixture(scope="module")
def clean_episode(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One clean synthetic episode (:func:`reach_and_back`, 30 ms tracking lag), written once per module."""
    return write_episode(tmp_path_factory.mktemp("clean"), Recording())
