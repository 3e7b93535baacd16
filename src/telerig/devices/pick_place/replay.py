"""Replay of a recorded operator stream re-targeted to a new cube pose.

A demonstration recorded on the pick-and-place task holds the operator's controller stream and
the cube's pose (``<robot>/object_pose``). Replayed into an episode whose cube lies elsewhere, the
hand's path is bent toward the new cube: the cube's displacement (in the operator frame) and yaw
change are blended in with a minimum-jerk weight from the start to the grasp (the trigger's first
rise past 0.5), held through the grasp, and blended out by the release (its fall below 0.5), so
the hand still starts at home and puts the cube where the recording put it. Timing is the
recording's; the trigger, grip and buttons are replayed as they were.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from pathlib import Path

import numpy as np

from telerig.devices.base import SampleSink
from telerig.devices.pick_place.operator import OBJECT_POSE, OperatorFrame, grasp_yaw, quat_yaw
from telerig.devices.worker import DeviceWorker, PlaybackClock
from telerig.errors import DeviceError, RecordingError, WireError
from telerig.ir.frames import quat_multiply, quat_normalize
from telerig.ir.mcap_log import read_log
from telerig.ir.types import ControllerState, FloatArray, Pose, Sample, now_ns

__all__ = ["RetargetedReplay", "retarget_stream"]

_log = logging.getLogger(__name__)
_SETTLE_S = 0.1
_SETTLE_M = 0.001


def _min_jerk(u: float) -> float:
    u = 0.0 if u < 0.0 else 1.0 if u > 1.0 else u
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


def _yaw_quat(yaw: float) -> FloatArray:
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def _weights(times: FloatArray, trigger: FloatArray) -> FloatArray:
    """Blend weight per sample: 0 → 1 until the grasp, 1 → 0 from the grasp to the release."""
    closed = np.flatnonzero(trigger > 0.5)
    if closed.size == 0:
        raise DeviceError("the recorded stream never closes the gripper (trigger > 0.5): not a pick")
    g = int(closed[0])
    opened = np.flatnonzero(trigger[g:] <= 0.5)
    r = g + int(opened[0]) if opened.size else len(times) - 1
    t0, tg, tr = times[0], times[g], times[r]
    w = np.empty(len(times))
    for i, t in enumerate(times):
        if t <= tg:
            w[i] = _min_jerk((t - t0) / max(tg - t0, 1e-9))
        else:
            w[i] = 1.0 - _min_jerk((t - tg) / max(tr - tg, 1e-9))
    return w


def retarget_stream(
    samples: tuple[ControllerState, ...],
    frame: OperatorFrame,
    old_cube: Pose,
    new_cube: Pose,
) -> tuple[ControllerState, ...]:
    """The recorded controller samples bent from ``old_cube`` to ``new_cube`` (both world frame).

    Raises:
        DeviceError: the stream is empty or never closes the gripper.
    """
    if not samples:
        raise DeviceError("no controller samples to re-target")
    times = np.array([s.stamp.capture_ns for s in samples], dtype=np.float64) / 1e9
    trigger = np.array([s.trigger for s in samples])
    weights = _weights(times, trigger)
    shift = frame.to_operator(new_cube.position) - frame.to_operator(old_cube.position)
    turn = grasp_yaw(quat_yaw(new_cube.orientation)) - grasp_yaw(quat_yaw(old_cube.orientation))
    # The rotation about the operator's vertical that turns the gripper by `turn` in the world.
    out = []
    for sample, w in zip(samples, weights, strict=True):
        q = quat_normalize(
            quat_multiply(frame.orientation(w * turn), quat_multiply(_conj_down(frame), sample.orientation))
        )
        out.append(dataclasses.replace(sample, position=sample.position + w * shift, orientation=q))
    return tuple(out)


def _conj_down(frame: OperatorFrame) -> FloatArray:
    """The inverse of :meth:`OperatorFrame.orientation` at yaw 0 (pointing down)."""
    q = frame.orientation(0.0)
    return np.array([q[0], -q[1], -q[2], -q[3]])


class RetargetedReplay:
    """Replays a recorded operator stream bent toward the cube observed in this episode.

    Args:
        path: The demonstration's ``episode.mcap``.
        topic: The controller stream's topic in it (``telerig/v1/<rig>/<device>/<part>``).
        robot: The task robot whose ``object_pose`` both the recording and this episode have.
        frame: The operator frame (the binding's alignment and the robot base).
        id: Device id (the topics it publishes on).
        cube: The cube object's name.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        topic: str,
        robot: str,
        frame: OperatorFrame,
        id: str = "replay",
        cube: str = "cube",
    ) -> None:
        self._path = Path(path)
        if not self._path.is_file():
            raise DeviceError(f"replay '{id}': recording {self._path} does not exist")
        self._topic = topic
        self.robot = robot
        self.frame = frame
        self._id = id
        self._cube = f"{robot}/{cube}"
        self._recorded: tuple[tuple[ControllerState, ...], Pose] | None = None
        self._worker = DeviceWorker(
            id, kind="re-targeted replay", thread_name=f"telerig-rreplay-{id}", log=_log
        )
        self._lock = threading.Lock()
        self._latest: Pose | None = None
        self._since: float | None = None
        self._watch_from = math.inf
        #: Observed samples ignored (not the cube's finite world-frame pose).
        self.ignored = 0

    @property
    def id(self) -> str:
        return self._id

    @property
    def observes(self) -> tuple[tuple[str, str], ...]:
        return ((self.robot, OBJECT_POSE),)

    def observe(self, sample: Sample) -> None:
        if not (
            isinstance(sample, Pose)
            and sample.stamp.source_id == self._cube
            and sample.frame_id == "world"
            and np.all(np.isfinite(sample.position))
            and np.all(np.isfinite(sample.orientation))
        ):
            self.ignored += 1
            return
        now = time.monotonic()
        with self._lock:
            if now < self._watch_from:
                return
            previous = self._latest
            self._latest = sample
            if previous is None or float(np.abs(previous.position - sample.position).max()) > _SETTLE_M:
                self._since = now

    def recorded(self) -> tuple[tuple[ControllerState, ...], Pose]:
        """The recorded controller samples and the cube's first recorded pose.

        Raises:
            DeviceError: unreadable file, no controller samples on the topic, or no cube pose.
        """
        if self._recorded is not None:
            return self._recorded
        cube_topic = f"{self._topic.rsplit('/', 2)[0]}/{self.robot}/{OBJECT_POSE}"
        states: list[ControllerState] = []
        cube: Pose | None = None
        try:
            for entry in read_log(self._path, topics=[self._topic, cube_topic]):
                sample = entry.sample
                if entry.topic == self._topic and isinstance(sample, ControllerState):
                    states.append(sample)
                elif cube is None and isinstance(sample, Pose) and sample.stamp.source_id == self._cube:
                    cube = sample
        except (RecordingError, WireError) as exc:
            raise DeviceError(f"replay '{self._id}': {exc}") from None
        if not states:
            raise DeviceError(f"replay '{self._id}': no controller samples on {self._topic} in {self._path}")
        if cube is None:
            raise DeviceError(
                f"replay '{self._id}': {self._path} has no {self._cube} pose on {cube_topic}; "
                "record the demonstration with a task rig (type mujoco_pick_place)"
            )
        states.sort(key=lambda s: s.stamp.capture_ns)
        self._recorded = (tuple(states), cube)
        return self._recorded

    def start(self, sink: SampleSink) -> None:
        recorded = self.recorded()
        with self._lock:
            self._latest, self._since = None, None
            self._watch_from = time.monotonic()
        self._worker.start(self._run, recorded, sink)

    def stop(self) -> None:
        self._worker.stop()
        with self._lock:
            self._watch_from = math.inf

    def _run(
        self, recorded: tuple[tuple[ControllerState, ...], Pose], sink: SampleSink, stop: threading.Event
    ) -> None:
        states, old_cube = recorded
        first = states[0]
        seq = 0

        def deliver(sample: ControllerState, capture_ns: int | None = None) -> None:
            nonlocal seq
            # Restamped as this device's own stream: increasing seq, its clock, captured now (or,
            # replayed, when the sample fell due).
            stamp = dataclasses.replace(
                sample.stamp,
                seq=seq,
                device_ns=time.monotonic_ns(),
                capture_ns=now_ns() if capture_ns is None else capture_ns,
                arrival_ns=0,
            )
            self._worker.deliver(sink, dataclasses.replace(sample, stamp=stamp))
            seq += 1

        # Hold the recording's first sample (the hand at home) until the cube is seen at rest.
        period = 0.01
        while True:
            with self._lock:
                cube, since = self._latest, self._since
            if cube is not None and since is not None and time.monotonic() - since >= _SETTLE_S:
                break
            deliver(first)
            if stop.wait(period):
                return
        bent = retarget_stream(states, self.frame, old_cube, cube)
        first_ns = bent[0].stamp.capture_ns
        clock = PlaybackClock()
        for sample in bent:
            due_ns = clock.wait((sample.stamp.capture_ns - first_ns) / 1e9, stop)
            if due_ns is None:
                return
            deliver(sample, due_ns)
        last = bent[-1]
        while not stop.wait(period):  # rest where the recording ended until the episode ends
            deliver(last)
