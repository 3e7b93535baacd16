"""Operator calibration launched over the bus, run by the device node where the device runs.

An operator (``telerig serve``'s dashboard, or any ``cli``/``web`` login: the bus ACL lets only
those and the stations publish on a device's command topic) sends
``{"calibrate": {"operator": "ana", "duration_s": 30, "settle_s": 3}}`` on
``telerig/v1/<rig>/<device>/command``. The device node answers at once with a ``command_reply``
event, then reports on ``<device>/events``: ``calibration_progress`` about once a second,
``calibration_done`` (arm length, scale, rotation and where the profile went) or
``calibration_failed`` (the one-line reason and what to do). It is the routine ``telerig
calibrate`` runs (:func:`~telerig.calibrate.calibrate_from_device` and
:func:`~telerig.calibrate.run_calibration`), with the device where it already runs:

* between episodes (the node is not running) the device is started for the window on its own and
  its samples go to the calibration only, never on the bus; an episode starting meanwhile cancels
  the calibration (the episode wins);
* during an episode the node's validated samples are copied for the window, but only while the
  device is paused (``pause_device``: its robots hold), so the calibration pose never drives a
  robot; otherwise the request is refused with that fix.

The profile is saved under the station's data root (``<root>/operators/<operator>.json``, as
``telerig calibrate --data-root`` does). A command that is not JSON, too large or not a valid
request is counted in :attr:`DeviceCalibration.rejected` and answered with one line saying why.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from telerig.bus.base import Bus, Message
from telerig.bus.catalogue import COMMAND, COORDINATOR, SESSION
from telerig.bus.topics import Topic
from telerig.calibrate import calibrate_from_device, run_calibration, save_profile
from telerig.calibrate.profile import CalibrationProfile
from telerig.devices.base import Device, DeviceAlert
from telerig.errors import CalibrationError, TelerigError
from telerig.ir.types import Sample, now_ns
from telerig.runtime.session import SessionStatus
from telerig.safety.commands import MAX_PAYLOAD_BYTES, parse_payload

__all__ = ["CalibrateRequest", "DeviceCalibration"]

log = logging.getLogger(__name__)

_NAME = r"^[A-Za-z0-9_.\-]+$"
#: Most samples copied from a running node for one calibration (120 s of 4 streams at 200 Hz).
MAX_SAMPLES = 100_000
#: What the operator is told to do while the window runs.
HOLD = "hold both hands straight forward, level and still"


class CalibrateRequest(BaseModel):
    """The ``calibrate`` object of a device command.

    Attributes:
        operator: Whose profile this is (its file name under ``operators/``).
        duration_s: The calibration window [s]: the hold that is measured.
        settle_s: Time before the window to get into the pose [s]; its samples are not used.
    """

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    operator: str = Field(pattern=_NAME, max_length=64)
    duration_s: float = Field(default=30.0, gt=0, le=120)
    settle_s: float = Field(default=3.0, ge=0, le=30)


class _Command(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    calibrate: CalibrateRequest


class DeviceCalibration:
    """The calibration side of one device node (see the module docs).

    Args:
        rig: Rig name.
        device: The node's device.
        bus: The node's bus client.
        alert: Publishes one of the device's events (the node's ``<device>/events``).
        running: Whether the node streams the device now (an episode runs).
        profile_root: Where profiles are saved (``<root>/operators/``); ``None``: not saved, the
            result event says so.
    """

    def __init__(
        self,
        rig: str,
        device: Device,
        bus: Bus,
        alert: Callable[[DeviceAlert], None],
        running: Callable[[], bool],
        *,
        profile_root: Path | None = None,
    ) -> None:
        self._device = device
        self._alert = alert
        self._running = running
        self.profile_root = profile_root
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._cancel = threading.Event()
        self._own = False  # the calibration started the device itself
        self._paused = False
        #: Samples copied from the running node for the calibration in progress, or ``None``.
        self.tap: list[Sample] | None = None
        #: Calibration commands refused as malformed or invalid.
        self.rejected = 0
        #: The last result: the profile, or the failure's one line.
        self.last: CalibrationProfile | str | None = None
        bus.subscribe(str(Topic(rig, device.id, COMMAND)), self._on_command, qos=1)
        bus.subscribe(str(Topic(rig, COORDINATOR, SESSION)), self._on_session, qos=1)

    @property
    def busy(self) -> bool:
        """Whether a calibration runs now."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    def cancel_own(self, timeout_s: float = 5.0) -> None:
        """Cancel a calibration that started the device itself (the node is about to start it)."""
        thread = self._thread
        if self._own and thread is not None and thread.is_alive():
            self._cancel.set()
            thread.join(timeout_s)

    def join(self, timeout_s: float | None = None) -> None:
        """Wait for the calibration in progress, if any."""
        thread = self._thread
        if thread is not None:
            thread.join(timeout_s)

    def _on_session(self, message: Message) -> None:
        status = parse_payload(SessionStatus, message)
        if not isinstance(status, str):
            self._paused = self._device.id in status.paused_devices

    def _on_command(self, message: Message) -> None:
        # Bus thread: validate, answer and start the calibration's own thread; never block.
        if len(message.payload) > MAX_PAYLOAD_BYTES:
            self._refuse(f"a command of {len(message.payload)} bytes, over {MAX_PAYLOAD_BYTES}")
            return
        try:
            doc = json.loads(message.payload)
        except (ValueError, RecursionError):
            doc = None
        if not isinstance(doc, dict):
            self._refuse("the command is not a JSON object")
            return
        if "calibrate" not in doc:
            return  # another command of the device (e.g. a WebXR takeover answer)
        try:
            request = _Command.model_validate_json(message.payload).calibrate
        except ValidationError as exc:
            error = exc.errors()[0]
            where = ".".join(str(p) for p in error["loc"]) or "calibrate"
            self._refuse(f"{where}: {error['msg']}")
            return
        self._start(request)

    def _refuse(self, why: str) -> None:
        self.rejected += 1
        log.warning("%s: refused a calibration command: %s", self._device.id, why)
        self._reply(f"calibrate refused: {why}")

    def _start(self, request: CalibrateRequest) -> None:
        device = self._device.id
        with self._lock:
            if self.busy:
                self._reply(f"calibrate refused: {device} is already calibrating; wait for its result")
                return
            running = self._running()
            if running and not self._paused:
                self._reply(
                    f"calibrate refused: {device} drives its robots in the running episode; pause "
                    f"the device first (its robots hold), then calibrate"
                )
                return
            self._own = not running
            self._cancel.clear()
            total = request.settle_s + request.duration_s
            self._reply(  # before the thread's first progress event
                f"calibrating operator {request.operator} with {device}: {HOLD} for "
                f"{request.duration_s:g} s (after {request.settle_s:g} s to get there; {total:g} s in all)"
            )
            self._thread = threading.Thread(
                target=self._run, args=(request,), name=f"calibrate-{device}", daemon=True
            )
            self._thread.start()

    def _run(self, request: CalibrateRequest) -> None:
        device = self._device.id
        try:
            profile = self._own_window(request) if self._own else self._tap_window(request)
            path = None if self.profile_root is None else save_profile(profile, data_root=self.profile_root)
        except (CalibrationError, TelerigError, OSError) as exc:
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            self.last = why
            self._event(
                "calibration_failed",
                f"operator {request.operator}: {why}",
                f"{HOLD}, then calibrate again",
                "warning",
            )
            return
        except Exception as exc:
            self.last = f"{type(exc).__name__}: {exc}"
            log.exception("%s: calibration failed", device)
            self._event(
                "calibration_failed",
                f"operator {request.operator}: {self.last}",
                "see the station's log",
                "error",
            )
            return
        finally:
            self.tap = None
        self.last = profile
        where = f"saved to {path}" if path is not None else "not saved (this device node has no data root)"
        self._event(
            "calibration_done",
            f"operator {request.operator}: arm length {profile.arm_length_m:.2f} m "
            f"({profile.arm_length_source}), "
            f"scale {profile.scale:.2f}, rotation {tuple(round(c, 3) for c in profile.rotation)}; {where}",
            "",
            "info",
        )

    def _own_window(self, request: CalibrateRequest) -> CalibrationProfile:
        """Between episodes: start the device for the window; its samples never reach the bus."""
        cancel = self._cancel

        def sleep(seconds: float) -> None:
            if cancel.wait(seconds):
                raise CalibrationError(
                    "cancelled: an episode started on this device; calibrate again after it"
                )

        return calibrate_from_device(
            self._device,
            request.duration_s,
            operator=request.operator,
            settle_s=request.settle_s,
            progress=self._progress(request),
            sleep=sleep,
        )

    def _tap_window(self, request: CalibrateRequest) -> CalibrationProfile:
        """During an episode (device paused): copy the node's validated samples for the window."""
        samples: list[Sample] = []
        self.tap = samples
        total = request.settle_s + request.duration_s
        progress = self._progress(request)
        start = time.monotonic()
        while (elapsed := time.monotonic() - start) < total:
            progress(elapsed, total)
            if self._cancel.wait(min(0.1, total - elapsed)):
                raise CalibrationError("cancelled")
        progress(total, total)
        self.tap = None
        return run_calibration(list(samples), duration_s=request.duration_s, operator=request.operator)

    def _progress(self, request: CalibrateRequest) -> Callable[[float, float], None]:
        last = [-1.0]

        def report(elapsed: float, total: float) -> None:
            if elapsed - last[0] >= 1.0 or elapsed >= total:
                last[0] = elapsed
                phase = "getting into the pose" if elapsed < request.settle_s else "measuring"
                self._event(
                    "calibration_progress",
                    f"operator {request.operator}: {elapsed:.0f} of {total:.0f} s ({phase})",
                    HOLD,
                    "info",
                )

        return report

    def _event(
        self, code: str, reason: str, action: str, severity: Literal["info", "warning", "error"]
    ) -> None:
        self._alert(DeviceAlert(code, self._device.id, reason, action, severity, now_ns()))

    def _reply(self, text: str) -> None:
        self._event("command_reply", text, "", "info")
