"""Process set-up for control loops that must not stall: scheduling policy and the C heap.

Three things delay a Python control thread on Linux that no tuning inside the loop fixes:

* **Scheduling.** Under the default policy a woken control thread queues behind ordinary
  processes on a busy host. :func:`set_realtime_priority` puts the process (and the threads it
  starts afterwards) under ``SCHED_RR``.
* **Someone trimming the heap mid-tick.** protobuf's upb runtime calls glibc's ``malloc_trim(0)``
  after every 10 000th message it frees, from whichever thread frees it and with the GIL held.
  ``malloc_trim`` hands every free page of every thread's heap back to the kernel, one
  ``madvise(MADV_DONTNEED)`` at a time. The first such call in a process also releases
  everything start-up left free (model compilation, imports): measured with perf probes on
  ``malloc_trim`` in the fleet rig, 9-14 ms of kernel time in each robot process about 2.5 s into
  the first episode, and each was one of the fleet benchmark's missed ticks; the later calls
  take 0.1-0.6 ms. :func:`release_heap` makes the first, expensive trim happen at start-up,
  before the episode.
* **glibc trimming on its own.** ``free()`` returns the top of a heap to the kernel the same way
  once more than the trim threshold (128 KiB, raised dynamically) is free there.
  :func:`keep_heap` stops that and serves blocks up to 32 MiB from the heap instead of a fresh
  ``mmap`` per allocation (the usual ``mallopt`` advice for real-time processes).

Measured with the fleet benchmark (six robot processes, ~10 000 ticks per 20 s run): before,
0-2 missed ticks per run (0 in 1 of 4 runs); with :func:`release_heap` alone 1, 0, 0; with both,
0 in 11 of 14 runs and 1 in two (one more run, started while the kernel was still reclaiming a
full test run's page cache, missed 30).
"""

from __future__ import annotations

import ctypes
import logging
import os
import sys
from collections.abc import Callable
from functools import cache

__all__ = ["keep_heap", "release_heap", "set_realtime_priority"]

log = logging.getLogger(__name__)

# glibc <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
# The largest fixed mmap threshold glibc accepts (HEAP_MAX_SIZE / 2 on 64-bit).
_MMAP_THRESHOLD = 32 * 1024 * 1024
# Trim only when this much is free at the top of a heap: in practice never.
_TRIM_THRESHOLD = 1 << 30


@cache
def _libc() -> ctypes.CDLL | None:
    if sys.platform != "linux":
        return None
    return ctypes.CDLL(None, use_errno=True)


def _glibc(name: str) -> Callable[..., int] | None:
    """The named C library function where the C library is glibc (musl and others lack these)."""
    libc = _libc()
    function: Callable[..., int] | None = getattr(libc, name, None) if libc is not None else None
    return function


def keep_heap() -> bool:
    """Make glibc keep freed heap memory instead of returning it to the kernel inside ``free()``.

    Call once, early, in a process that runs control loops. Returns ``False`` (and changes
    nothing) where the C library is not glibc.
    """
    mallopt = _glibc("mallopt")
    if mallopt is None:
        return False
    # Setting either parameter also turns glibc's dynamic thresholds off.
    ok = mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD) == 1
    return mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD) == 1 and ok


def release_heap() -> bool:
    """Give the memory start-up left free back to the kernel now (glibc ``malloc_trim``).

    Call once everything is built and before the control loops drive a robot: a later
    ``malloc_trim`` (see the module docs) then has little to release. Returns ``False`` where
    the C library is not glibc.
    """
    malloc_trim = _glibc("malloc_trim")
    if malloc_trim is None:
        return False
    malloc_trim(0)
    return True


def set_realtime_priority(priority: int, what: str, *, pid: int = 0) -> bool:
    """Put process ``pid`` (0: this one, and the threads it starts from now on) under ``SCHED_RR``
    at ``priority``.

    Without the right to (root, CAP_SYS_NICE or an ``rtprio`` limit) logs one warning naming the
    fix and returns ``False``; the process keeps its normal priority. ``what`` names the process.
    """
    try:
        os.sched_setscheduler(pid, os.SCHED_RR, os.sched_param(priority))
    except (PermissionError, AttributeError, OSError) as exc:
        log.warning(
            "%s runs at normal priority: real-time priority %d was refused (%s); grant CAP_SYS_NICE "
            "or an rtprio limit in /etc/security/limits.conf",
            what,
            priority,
            exc,
        )
        return False
    return True
