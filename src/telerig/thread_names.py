"""Each thread's name, as the kernel shows it: so ``top -H``, ``perf`` and the scheduler's trace
tell a control loop from a physics loop, an MQTT client loop or a video encoder.

Python 3.11 names its threads for Python alone: the kernel knows every thread of a rig's process
as ``python``. :func:`name_current` gives the calling thread its Python name at the OS level (the
task's ``comm``, 15 bytes); :func:`name_all` does so for every Python thread of this process,
the main thread excepted (its name is the process's in ``ps`` and ``pgrep``). paho-mqtt's network
threads, ``paho-mqtt-client-<rig>-<role>-<id>``, become ``mqtt-<role>-<id>``, which fits.

Off Linux, or where ``/proc`` is not writable, nothing changes and nothing raises.
"""

from __future__ import annotations

import contextlib
import threading
import weakref
from pathlib import Path

__all__ = ["COMM_BYTES", "name_all", "name_current", "os_name"]

#: Longest name the kernel keeps for a task (TASK_COMM_LEN 16, with its terminating NUL).
COMM_BYTES = 15
_PAHO = "paho-mqtt-client-"
#: Each thread :func:`name_all` named → the name it gave (forgotten with the thread).
_named: weakref.WeakKeyDictionary[threading.Thread, str] = weakref.WeakKeyDictionary()
_lock = threading.Lock()


def os_name(name: str) -> str:
    """The kernel's form of Python thread name ``name``: at most :data:`COMM_BYTES` bytes of UTF-8,
    cut on a character boundary (what UTF-8 cannot encode becomes ``?``); paho's network threads
    as ``mqtt-`` and their client id without its first part (the rig's name)."""
    if name.startswith(_PAHO):
        client_id = name[len(_PAHO) :]
        name = "mqtt-" + client_id.split("-", 1)[-1]
    return name.encode(errors="replace")[:COMM_BYTES].decode(errors="ignore")


def name_current() -> bool:
    """Give the calling thread its Python name at the OS level; whether the kernel took it."""
    thread = threading.current_thread()
    if thread is threading.main_thread() or not _write(Path("/proc/thread-self/comm"), thread.name):
        return False
    with _lock:
        _named[thread] = thread.name
    return True


def name_all() -> int:
    """Give every Python thread of this process but the main one its name at the OS level; how many
    the kernel took. Cheap to call again: a thread already named under its name is skipped. Call
    it once a rig's threads are up, and after starting more (a thread started later may name
    itself with :func:`name_current`, as :func:`telerig.priority.enter` does)."""
    main = threading.main_thread()
    named = 0
    with _lock:
        for thread in threading.enumerate():
            tid = thread.native_id
            if thread is main or tid is None or _named.get(thread) == thread.name:
                continue
            if _write(Path(f"/proc/self/task/{tid}/comm"), thread.name):
                _named[thread] = thread.name
                named += 1
    return named


def _write(path: Path, name: str) -> bool:
    with contextlib.suppress(OSError):  # not Linux, /proc read-only, or the thread just ended
        path.write_bytes(os_name(name).encode())
        return True
    return False
