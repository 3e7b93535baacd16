"""Process-wide settings for a process that runs control loops, applied only by entry points.

A library object must not change the interpreter or the C heap of whoever imports it, so
:class:`~telerig.runtime.rig.RigRuntime` leaves them alone; ``telerig run``/``demo``, the robot
host processes and the benchmarks apply them around the rig with :func:`control_process`.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from types import FrameType

from telerig.runtime.realtime import keep_heap, set_realtime_priority

__all__ = ["DEFAULT_SWITCH_INTERVAL_S", "Terminated", "control_process", "raise_terminated"]

#: Python's GIL switch interval while control loops run [s]. The default 5 ms lets a busy thread
#: (recorder, encoder feed) delay a woken control thread by up to 5 ms; 1 ms bounds that.
DEFAULT_SWITCH_INTERVAL_S = 0.001


@contextlib.contextmanager
def control_process(
    switch_interval_s: float | None = DEFAULT_SWITCH_INTERVAL_S, *, realtime_priority: int | None = None
) -> Iterator[None]:
    """Within the block: the GIL switch interval ``switch_interval_s`` [s] (None: unchanged) and a
    C heap that is never trimmed inside ``free()`` (:func:`~telerig.runtime.realtime.keep_heap`,
    which stays for the life of the process). The switch interval is restored on exit.

    ``realtime_priority`` (the rig's ``runtime.realtime_priority``, set when its robot processes run
    under ``SCHED_RR``) puts the station under ``SCHED_RR`` at the same priority for the block: the
    threads started inside it (recorder, coordinator, the fleet's safety supervisor) inherit it.
    Below the robots' priority a full machine starved the station: on the fleet rig (2 cores) the
    robots applied 500 commands each in 6 s while the recorder kept 62 of them; at the same
    priority every applied command is recorded (the robots then apply about 55 % of their rate on
    that machine: it cannot do both).
    """
    keep_heap()
    saved = sys.getswitchinterval()
    if switch_interval_s is not None:
        sys.setswitchinterval(switch_interval_s)
    realtime = realtime_priority is not None and set_realtime_priority(realtime_priority, "the station")
    try:
        yield
    finally:
        sys.setswitchinterval(saved)
        if realtime:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


class Terminated(KeyboardInterrupt):
    """A service manager's SIGTERM, raised in the main thread like Ctrl-C (robots hold, the episode
    is kept) but recorded as ``terminated (SIGTERM)``, not as the operator's Ctrl-C."""


def raise_terminated(signum: int, frame: FrameType | None) -> None:
    """A SIGTERM handler for entry points: ``signal.signal(signal.SIGTERM, raise_terminated)``."""
    raise Terminated
