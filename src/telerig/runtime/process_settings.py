"""Process-wide settings for a process that runs control loops, applied only by entry points.

A library object must not change the interpreter or the C heap of whoever imports it, so
:class:`~telerig.runtime.rig.RigRuntime` leaves them alone; ``telerig run``/``demo``, the robot
host processes and the benchmarks apply them around the rig with :func:`control_process`.
"""

from __future__ import annotations

import contextlib
import gc
import os
import sys
from collections.abc import Iterator
from types import FrameType

from telerig.runtime.realtime import keep_heap, release_heap, set_realtime_priority

__all__ = ["DEFAULT_SWITCH_INTERVAL_S", "Terminated", "control_process", "raise_terminated", "settle_heap"]

#: Python's GIL switch interval while control loops run [s]. The default 5 ms lets a busy thread
#: (recorder, encoder feed) delay a woken control thread by up to 5 ms; 1 ms bounds that.
DEFAULT_SWITCH_INTERVAL_S = 0.001


@contextlib.contextmanager
def control_process(
    switch_interval_s: float | None = DEFAULT_SWITCH_INTERVAL_S,
    *,
    realtime_priority: int | None = None,
    freeze_after_start: bool = True,
) -> Iterator[None]:
    """Within the block: the GIL switch interval ``switch_interval_s`` [s] (None: unchanged) and a
    C heap that is never trimmed inside ``free()`` (:func:`~telerig.runtime.realtime.keep_heap`,
    which stays for the life of the process). The switch interval is restored on exit.

    ``freeze_after_start``: once a rig has started, :func:`settle_heap` freezes the objects start-up
    made (``gc.freeze``); they are unfrozen when the block ends. A process that opens many rigs in
    one block (a test session) passes False: frozen, each rig's objects would outlive it.

    ``realtime_priority`` (the rig's ``runtime.realtime_priority``, set when its robot processes run
    under ``SCHED_RR``) puts the station under ``SCHED_RR`` at the same priority for the block: the
    threads started inside it (the bus delivery threads, coordinator, the fleet's safety supervisor)
    inherit it; the recorder's writer thread and the other ``work`` threads leave it for
    :mod:`telerig.priority`'s ``work`` role.
    Below the robots' priority a full machine starved the station: on the fleet rig (2 cores) the
    robots applied 500 commands each in 6 s while the recorder kept 62 of them; at the same
    priority every applied command is recorded (the robots then apply about 55 % of their rate on
    that machine: it cannot do both).
    """
    global _freezing_blocks
    keep_heap()
    saved = sys.getswitchinterval()
    if switch_interval_s is not None:
        sys.setswitchinterval(switch_interval_s)
    realtime = realtime_priority is not None and set_realtime_priority(realtime_priority, "the station")
    _freezing_blocks += freeze_after_start
    try:
        yield
    finally:
        _freezing_blocks -= freeze_after_start
        if freeze_after_start and _freezing_blocks == 0:
            gc.unfreeze()  # what settle_heap froze is the collector's again (a benchmark's next rig)
        sys.setswitchinterval(saved)
        if realtime:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


#: How many control_process blocks with ``freeze_after_start`` this process is in.
_freezing_blocks = 0


def settle_heap() -> None:
    """Once a rig's nodes run (``RigRuntime.open``, a robot host's start), before any control tick:
    give the memory start-up left free back to the kernel
    (:func:`~telerig.runtime.realtime.release_heap`) and, inside :func:`control_process`, collect
    once and move every object start-up made into the collector's permanent generation
    (``gc.freeze``; unless it was entered with ``freeze_after_start=False``).

    Python's full collection walks every tracked object with the interpreter lock held, stopping
    every thread of the process: in the demo rig's process (160 000 objects, most of them imported
    modules, models and configs that live as long as the process) each took 85-112 ms, about every
    20 s, and every stream of the process paused with it. Frozen, they are never walked again: the
    same collections took 22 ms. Outside :func:`control_process` (a library caller) nothing is
    frozen: its objects must stay collectable after the rig closes.
    """
    release_heap()
    if _freezing_blocks > 0:
        gc.collect()
        gc.freeze()


class Terminated(KeyboardInterrupt):
    """A service manager's SIGTERM, raised in the main thread like Ctrl-C (robots hold, the episode
    is kept) but recorded as ``terminated (SIGTERM)``, not as the operator's Ctrl-C."""


def raise_terminated(signum: int, frame: FrameType | None) -> None:
    """A SIGTERM handler for entry points: ``signal.signal(signal.SIGTERM, raise_terminated)``."""
    raise Terminated
