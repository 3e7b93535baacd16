"""A trained policy as an input device: robot state and camera frames in, joint targets out.

Why a device (a family of :mod:`telerig.devices`) and not a runtime node of its own: to the rest
of the rig a policy is a source of samples like an operator's controller. As a device it is bound
to a robot part by the rig's ``bindings`` (a joint passthrough retargeter and the gripper), its
samples pass the device node's validation, health counters, per-device pause and the broker's ACL
(``dev-<id>`` may publish only its own streams), the recorder records them as it records any
device, and the safety chain, the handover and the QA gates treat a rollout exactly as a
teleoperated episode. What a policy needs beyond an operator device is to read the bus: its device
node hands it the robot's measured state (:class:`~telerig.devices.base.ObservingDevice`) and the
cameras' observation frames (:class:`~telerig.devices.observing.FrameObservingDevice`).

Inference runs in its own process (:mod:`telerig.devices.policy.worker`; torch never enters the
control process) with a deadline per tick: an action that is not there in time is not sent, so to
the safety chain it is a missed sample (it holds, then its watchdog stops the robot), and the
device's loop never waits longer than the deadline.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Mapping

import numpy as np
import numpy.typing as npt

from telerig import priority
from telerig.bus.catalogue import GRIPPER_STATE, JOINT_STATE
from telerig.devices.base import SampleSink
from telerig.devices.policy.ensemble import TemporalEnsemble
from telerig.devices.policy.worker import DEFAULT_LOADER, InferenceProcess, PolicyInfo
from telerig.errors import DeviceError, WireError
from telerig.ir.observation import decode_observation
from telerig.ir.types import GripperCommand, JointCommand, JointState, Sample, Stamp, now_ns

__all__ = ["PolicyDevice", "PolicyStats"]

log = logging.getLogger(__name__)

#: The action entry that is the gripper's opening (0 closed, 1 open), as the exports name it.
GRIPPER = "gripper"


class PolicyStats(dict[str, int]):
    """Counters (the device node reports them in its health): ``actions`` sent, ``late`` (no action
    by the deadline: a missed sample), ``busy`` (ticks skipped while a late answer was still being
    computed), ``failed`` (the policy raised), ``no_state`` / ``no_frames`` (ticks before the
    observation was complete), ``bad_state`` / ``bad_frames`` (observed messages dropped),
    ``mean_infer_us``."""


class PolicyDevice:
    """A checkpoint rolled out at ``rate_hz``, reading ``robot``'s state and the cameras' frames.

    Args:
        device_id: The device's id in the rig (its samples' source: ``<id>/joints``).
        checkpoint: The checkpoint file.
        robot: The robot whose ``joint_state`` (and ``gripper_state``) the policy observes.
        cameras: Checkpoint camera key → rig camera id publishing ``observation`` frames.
        rate_hz: Actions per second; the checkpoint's fps when None [Hz].
        deadline_ms: How long a tick waits for its action [ms]; 80 % of a period when None.
        execute_actions: Actions of a chunk sent before asking again (1: infer every tick).
        temporal_ensemble: ACT's temporal ensembling with this weight decay per tick (e.g. 0.01):
            infer every tick and send the weighted mean of every live chunk's action for the tick
            (:class:`~telerig.devices.policy.ensemble.TemporalEnsemble`); None: chunks as they are.
        max_frame_age_ms: A frame older than this does not count as the camera's current view [ms].
        loader: ``module:function`` loading the checkpoint in the inference process.
        threads: torch threads of the inference process.
        start_timeout_s: How long loading may take [s].
    """

    def __init__(
        self,
        device_id: str,
        checkpoint: str,
        *,
        robot: str,
        cameras: Mapping[str, str] | None = None,
        rate_hz: float | None = None,
        deadline_ms: float | None = None,
        execute_actions: int = 1,
        temporal_ensemble: float | None = None,
        max_frame_age_ms: float = 500.0,
        loader: str = DEFAULT_LOADER,
        threads: int = 1,
        start_timeout_s: float = 120.0,
    ) -> None:
        if execute_actions < 1:
            raise DeviceError(f"policy {device_id}: execute_actions must be >= 1, got {execute_actions}")
        if temporal_ensemble is not None and execute_actions != 1:
            raise DeviceError(
                f"policy {device_id}: temporal_ensemble infers every tick; drop execute_actions "
                f"({execute_actions}) or the ensemble"
            )
        try:
            self._ensemble = None if temporal_ensemble is None else TemporalEnsemble(temporal_ensemble)
        except ValueError as exc:
            raise DeviceError(f"policy {device_id}: {exc}") from None
        self._id = device_id
        self.checkpoint = checkpoint
        self.robot = robot
        self._cameras = dict(cameras or {})
        self._rate_hz = rate_hz
        self._deadline_ms = deadline_ms
        self._execute = execute_actions
        self._max_frame_age_ns = int(max_frame_age_ms * 1e6)
        self._loader = loader
        self._threads = threads
        self._start_timeout_s = start_timeout_s
        self._lock = threading.Lock()
        self._joints: JointState | None = None
        self._gripper: GripperCommand | None = None
        self._frames: dict[str, tuple[int, npt.NDArray[np.uint8]]] = {}
        self._process: InferenceProcess | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._seq = 0
        self._last_ns = 0
        self.stats = PolicyStats.fromkeys(
            ("actions", "late", "busy", "failed", "no_state", "no_frames", "bad_state", "bad_frames"), 0
        )
        self.stats["mean_infer_us"] = 0
        self.info: PolicyInfo | None = None

    # -- Device ----------------------------------------------------------------------------------

    @property
    def id(self) -> str:
        return self._id

    @property
    def observes(self) -> tuple[tuple[str, str], ...]:
        """The robot's measured joints and gripper (:class:`~telerig.devices.base.ObservingDevice`)."""
        return ((self.robot, JOINT_STATE), (self.robot, GRIPPER_STATE))

    @property
    def observes_frames(self) -> tuple[str, ...]:
        return tuple(sorted(set(self._cameras.values())))

    def load(self) -> PolicyInfo:
        """Start the inference process and load the checkpoint (done by :meth:`start` if not yet).

        Raises:
            DeviceError: it could not be loaded, or it needs a camera the rig does not give it.
        """
        if self._process is None:
            self._process = InferenceProcess(
                self.checkpoint,
                loader=self._loader,
                threads=self._threads,
                start_timeout_s=self._start_timeout_s,
            )
            info = self.info = self._process.info
            for key in info.camera_keys:
                if key not in self._cameras:
                    # By default a checkpoint camera key names the rig camera (its last dotted part:
                    # ``observation.images.scene`` → ``scene``).
                    self._cameras[key] = key.rsplit(".", 1)[-1]
        assert self.info is not None
        return self.info

    def start(self, sink: SampleSink) -> None:
        """Act from now on (loads the policy first if :meth:`load` was not called).

        Raises:
            DeviceError: it cannot be loaded, or its inference process died (the rig must restart).
        """
        info = self.load()
        if self._thread is not None and self._thread.is_alive():
            return
        assert self._process is not None
        if not self._process.alive:
            raise DeviceError(
                f"policy {self._id}: its inference process ended (exit code "
                f"{self._process.exitcode}); restart the rig"
            )
        rate = self._rate_hz or info.fps
        for key in self.stats:  # counters per episode (the manifest records them)
            self.stats[key] = 0
        assert self._process is not None
        self._process.late = self._process.failed = 0
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._run, args=(sink, info, rate), name=f"policy-{self._id}", daemon=True
        )
        self._thread.start()

    def stop(self) -> None:
        """Stop acting (the inference process stays loaded for the next episode; :meth:`close` ends it)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        with self._lock:
            self._joints = self._gripper = None
            self._frames.clear()

    def close(self) -> None:
        """Stop and end the inference process. Idempotent."""
        self.stop()
        if self._process is not None:
            self._process.close()
            self._process = None

    # -- observations (bus thread) ------------------------------------------------------------

    def observe(self, sample: Sample) -> None:
        if isinstance(sample, JointState):
            if not (np.all(np.isfinite(sample.positions)) and len(sample.names) == len(sample.positions)):
                self.stats["bad_state"] += 1
                return
            with self._lock:
                self._joints = sample
        elif isinstance(sample, GripperCommand):
            if not np.isfinite(sample.opening):
                self.stats["bad_state"] += 1
                return
            with self._lock:
                self._gripper = sample
        else:
            self.stats["bad_state"] += 1

    def observe_frame(self, camera: str, payload: bytes) -> None:
        try:
            frame = decode_observation(payload)
        except WireError as exc:
            self.stats["bad_frames"] += 1
            if self.stats["bad_frames"] == 1:
                log.warning("%s: dropped an observation frame of %s: %s", self._id, camera, exc)
            return
        with self._lock:
            self._frames[camera] = (frame.capture_ns, frame.image)

    # -- the loop -----------------------------------------------------------------------------

    def _observation(
        self, info: PolicyInfo, now: int
    ) -> tuple[npt.NDArray[np.float64], dict[str, npt.NDArray[np.uint8]], int] | None:
        """State vector, frames by checkpoint key and the state's capture time; None (counted) when
        something is missing."""
        with self._lock:
            joints, gripper, frames = self._joints, self._gripper, dict(self._frames)
        if joints is None:
            self.stats["no_state"] += 1
            return None
        by_name = dict(zip(joints.names, joints.positions.tolist(), strict=True))
        prefix = f"{self.robot}."
        state = np.empty(len(info.state_names))
        for i, name in enumerate(info.state_names):
            key = name[len(prefix) :] if name.startswith(prefix) else name
            if key in by_name:
                state[i] = by_name[key]
            elif key == GRIPPER and gripper is not None:
                state[i] = gripper.opening
            else:
                self.stats["no_state"] += 1
                return None
        images: dict[str, npt.NDArray[np.uint8]] = {}
        for key in info.camera_keys:
            got = frames.get(self._cameras[key])
            if got is None or now - got[0] > self._max_frame_age_ns:
                self.stats["no_frames"] += 1
                return None
            images[key] = got[1]
        return state, images, joints.stamp.capture_ns

    def _run(self, sink: SampleSink, info: PolicyInfo, rate_hz: float) -> None:
        priority.enter("work")  # below the control loop
        process = self._process
        assert process is not None
        period = 1.0 / rate_hz
        deadline = period * 0.8 if self._deadline_ms is None else self._deadline_ms / 1e3
        ensemble = self._ensemble
        if ensemble is not None:
            ensemble.clear()  # nothing predicted before this start covers its ticks
        chunk: npt.NDArray[np.float64] | None = None
        used = 0
        next_t = time.monotonic()
        while not self._stop.is_set():
            next_t += period
            now = now_ns()
            if ensemble is not None or chunk is None or used >= min(self._execute, len(chunk)):
                chunk, used = None, 0
                try:
                    chunk = self._ask(process, info, now, deadline)
                except DeviceError as exc:  # the inference process died: no more actions
                    log.error("%s: %s; the policy stops acting", self._id, exc)
                    return
            if ensemble is not None:
                if chunk is not None:
                    ensemble.add(chunk)
                action = ensemble.next()
                if action is not None:
                    self._emit(sink, info, action, now)
            elif chunk is not None:
                self._emit(sink, info, chunk[used], now)
                used += 1
            remaining = next_t - time.monotonic()
            if remaining > 0:
                self._stop.wait(remaining)
            else:
                next_t = time.monotonic()  # behind: restart the grid rather than catch up

    def _ask(
        self, process: InferenceProcess, info: PolicyInfo, now: int, deadline: float
    ) -> npt.NDArray[np.float64] | None:
        """A chunk for the current observation, or None (incomplete observation, busy, late, bad).

        Raises:
            DeviceError: the inference process died.
        """
        observed = self._observation(info, now)
        if observed is None:
            return None
        state, images, _ = observed
        if process.busy:
            self.stats["busy"] += 1
            return None
        chunk = process.request(state, images, deadline)
        self.stats["late"], self.stats["failed"] = process.late, process.failed
        if process.infer_ns:
            self.stats["mean_infer_us"] = int(np.mean(process.infer_ns) / 1e3)
        if chunk is not None and (chunk.ndim != 2 or chunk.shape[1] != len(info.action_names)):
            log.error("%s: the policy returned actions of shape %s", self._id, chunk.shape)
            self.stats["failed"] += 1
            return None
        return chunk

    def _emit(self, sink: SampleSink, info: PolicyInfo, action: npt.NDArray[np.float64], now: int) -> None:
        # Stamped when it is sent (strictly increasing): the chain's freshness then measures the
        # action's delivery, and a late one never reaches it.
        capture = max(now, self._last_ns + 1)
        self._last_ns = capture
        self._seq += 1
        stamp = Stamp(f"{self._id}/joints", self._seq, capture, capture)
        sink(JointCommand(stamp, info.action_names, np.array(action, dtype=np.float64)))
        self.stats["actions"] += 1
