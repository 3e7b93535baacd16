"""Run a device for the calibration window and calibrate from what it delivered."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping

from telerig.calibrate.neutral import CalibrationError, CalibrationSettings, Role, run_calibration
from telerig.calibrate.profile import CalibrationProfile
from telerig.devices.base import Device
from telerig.ir.types import Sample

__all__ = ["ProgressCallback", "calibrate_from_device"]

#: Called with ``(elapsed_s, total_s)`` while the window runs, and once with ``(total_s, total_s)``.
ProgressCallback = Callable[[float, float], None]


def calibrate_from_device(
    device: Device,
    duration_s: float = 30.0,
    *,
    operator: str = "operator",
    settings: CalibrationSettings | None = None,
    roles: Mapping[str, Role] | None = None,
    settle_s: float = 0.0,
    progress: ProgressCallback | None = None,
    tick_s: float = 0.1,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> CalibrationProfile:
    """Start ``device``, collect its samples for ``settle_s + duration_s``, stop it, calibrate.

    The device is stopped even when collection fails. Only the last ``duration_s`` of samples
    (by capture time) are used, so ``settle_s`` gives the operator time to get into the pose.

    Args:
        device: A device that streams both hands (and the head, for the arm length).
        duration_s: Calibration window [s] (> 0).
        operator: Operator name for the profile.
        settings: See :class:`CalibrationSettings`.
        roles: ``source_id`` → role of ``Pose`` streams (see :func:`run_calibration`).
        settle_s: Time before the window [s] (>= 0); its samples are collected but not used.
        progress: Called about every ``tick_s`` with ``(elapsed_s, total_s)``.
        tick_s: Progress period [s] (> 0).
        clock: Monotonic clock [s]; injectable for tests.
        sleep: Sleep function [s]; injectable for tests.

    Raises:
        CalibrationError: The hold could not be used (see :func:`run_calibration`).
    """
    for name, value, low in (("duration_s", duration_s, 0.0), ("tick_s", tick_s, 0.0)):
        if not (math.isfinite(value) and value > low):
            raise CalibrationError(f"{name} must be > 0 s, got {value}")
    if not (math.isfinite(settle_s) and settle_s >= 0.0):
        raise CalibrationError(f"settle_s must be >= 0 s, got {settle_s}")
    total = settle_s + duration_s
    collected: list[Sample] = []
    lock = threading.Lock()

    def sink(sample: Sample) -> None:
        with lock:
            collected.append(sample)

    start = clock()
    device.start(sink)
    try:
        while (elapsed := clock() - start) < total:
            if progress is not None:
                progress(elapsed, total)
            sleep(min(tick_s, total - elapsed))
    finally:
        device.stop()
    if progress is not None:
        progress(total, total)
    with lock:
        samples = list(collected)
    return run_calibration(samples, duration_s=duration_s, operator=operator, settings=settings, roles=roles)
