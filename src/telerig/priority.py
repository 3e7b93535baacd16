"""CPU priority by role: nothing that is not control (rendering, encoding, previews, health,
uploads, the recorder) may delay a control tick.

Linux schedules threads, not processes: each thread has its own policy and niceness, and a
thread (or process) starts with its creator's. So each worker sets its own priority once, first
thing, with :func:`enter` and its role; threads it starts later (libx264's, llvmpipe's) inherit
it. The roles:

* ``control``: the control loops. Raised (negative niceness) where the host allows it
  (root or CAP_SYS_NICE); elsewhere they keep the default and one warning says so.
* ``work``: threads of the station's process that are not control (video encoding, previews,
  health, uploads, the recorder's writer): nicer than control, under ``SCHED_BATCH`` (never
  preempts a running thread on wake-up). Not ``SCHED_IDLE``: these threads share Python's GIL
  with the control thread, and one starved while it holds the GIL would stall control with it.
* ``render``: processes of their own that share no lock with control (a simulated camera's
  renderer, every thread of it): ``SCHED_BATCH`` at niceness 10 by default. ``SCHED_IDLE`` (or
  niceness 19) is there to choose, but measured on a loaded 2-core host (benchmarks/priorities.py)
  it starved the camera: 4-5 instead of 7 frames/s, single frames over 5 s, and no better control
  latency for it.

Which settings apply is process-wide: :func:`configure`, which
:class:`~telerig.runtime.nodes.StationNodes` calls with the rig's ``runtime.priorities``;
:func:`applied` reports what each role got, for the episode's manifest. Off Linux, :func:`enter`
changes nothing.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

from telerig import thread_names

__all__ = [
    "RENDER_ENV",
    "enter_render_from_env",
    "note",
    "render_env",
    "Policy",
    "Priorities",
    "Role",
    "applied",
    "configure",
    "current",
    "describe",
    "enter",
    "settings",
]

log = logging.getLogger(__name__)

Role = Literal["control", "work", "render"]
#: ``other`` is Linux's default time-sharing policy (SCHED_OTHER); ``batch`` is SCHED_BATCH
#: (never preempts on wake-up); ``idle`` is SCHED_IDLE (runs only when nothing else wants the CPU).
Policy = Literal["other", "batch", "idle"]

#: Environment variable through which a render process learns its settings: ``POLICY:NICE``.
RENDER_ENV = "TELERIG_RENDER_PRIORITY"

_POLICIES: dict[str, str] = {"other": "SCHED_OTHER", "batch": "SCHED_BATCH", "idle": "SCHED_IDLE"}
_NAMES = {getattr(os, v): k for k, v in _POLICIES.items() if hasattr(os, v)}


@dataclass(frozen=True, slots=True)
class Priorities:
    """Scheduling of each role (see the module docs).

    Attributes:
        enabled: Apply anything at all; off leaves every thread as it was created.
        control_nice: Niceness of the control threads (-20..0): below 0 needs root or
            CAP_SYS_NICE; refused, they stay at the station's niceness.
        control_realtime: When set, the control threads run under ``SCHED_RR`` at this priority
            (1..99) instead, above every ordinary thread of the host (same rights needed;
            refused, ``control_nice`` applies).
        work_nice: Niceness of the station's other threads (0..19); a thread already nicer
            (a station started under ``nice``) stays as it is, as do render processes.
        work_policy: Their policy (``other`` or ``batch``).
        render_nice: Niceness of render processes (0..19).
        render_policy: Their policy.
    """

    enabled: bool = True
    control_nice: int = -10
    control_realtime: int | None = None
    work_nice: int = 10
    work_policy: Literal["other", "batch"] = "batch"
    render_nice: int = 10
    render_policy: Policy = "batch"

    def of(self, role: Role) -> tuple[Policy, int]:
        """The ``(policy, niceness)`` ``role`` gets."""
        if role == "control":
            return "other", self.control_nice
        if role == "work":
            return self.work_policy, self.work_nice
        return self.render_policy, self.render_nice


_lock = threading.Lock()
_settings = Priorities()
_applied: dict[str, str] = {}
_warned: set[str] = set()


def configure(priorities: Priorities) -> None:
    """Use ``priorities`` for every later :func:`enter` of this process (and its render processes)."""
    global _settings
    with _lock:
        _settings = priorities
        _applied.clear()


def render_env() -> str:
    """The value of :data:`RENDER_ENV` for a render process started now."""
    s = _settings
    return f"{s.render_policy}:{s.render_nice}" if s.enabled else "off"


def settings() -> Priorities:
    """The settings :func:`enter` applies now."""
    return _settings


def applied() -> dict[str, str]:
    """Role -> what the last thread of that role got (e.g. ``{"control": "SCHED_OTHER nice -10"}``);
    a refused change reads ``"SCHED_OTHER nice 0 (refused: nice -10: Permission denied)"``."""
    with _lock:
        return dict(_applied)


def describe(tid: int = 0) -> str:
    """The policy and niceness of thread ``tid`` (0: the calling one), e.g. ``SCHED_IDLE nice 19``."""
    tid = tid or threading.get_native_id()
    number = os.sched_getscheduler(tid)
    if _is_realtime(tid):
        kind = "SCHED_RR" if number == os.SCHED_RR else "SCHED_FIFO"
        return f"{kind} priority {os.sched_getparam(tid).sched_priority}"
    policy = _NAMES.get(number, str(number))
    return f"{_POLICIES.get(policy, policy)} nice {os.getpriority(os.PRIO_PROCESS, tid)}"


def current() -> tuple[str, int]:
    """The calling thread's ``(policy, niceness)``, policy as in :data:`Policy` (or the kernel's number)."""
    tid = threading.get_native_id()
    number = os.sched_getscheduler(tid)
    return _NAMES.get(number, str(number)), os.getpriority(os.PRIO_PROCESS, tid)


def enter(role: Role, priorities: Priorities | None = None, *, tid: int = 0) -> str:
    """Give the calling thread (or thread ``tid`` of this process) the scheduling of ``role`` (from
    ``priorities``, else the process's settings); threads and processes it starts afterwards
    inherit it. The calling thread also gets its Python name at the OS level
    (:func:`telerig.thread_names.name_current`). Never raises.

    A change the host refuses (raising priority without CAP_SYS_NICE, a container's seccomp
    filter) leaves the thread as it is and logs one warning per role. Returns what the thread has
    now, as :func:`describe` writes it (``"unchanged"`` when disabled or not on Linux).
    """
    if not tid:
        thread_names.name_current()  # so the kernel's tools tell the role's threads apart
    chosen = priorities if priorities is not None else _settings
    if not chosen.enabled or not hasattr(os, "sched_setscheduler"):
        return "unchanged"
    policy, nice = chosen.of(role)
    tid = tid or threading.get_native_id()
    refused: list[str] = []
    if role == "control" and chosen.control_realtime is not None:
        try:
            os.sched_setscheduler(tid, os.SCHED_RR, os.sched_param(chosen.control_realtime))
            return note(role, describe(tid), [])
        except OSError as exc:
            refused.append(f"SCHED_RR {chosen.control_realtime}: {exc.strerror}")
    try:
        # A thread under a real-time policy (the station's SCHED_RR) is left there: only the
        # lower roles leave it, and only control raises its niceness, which SCHED_RR ignores.
        number = getattr(os, _POLICIES[policy])
        if os.sched_getscheduler(tid) != number and not (role == "control" and _is_realtime(tid)):
            os.sched_setscheduler(tid, number, os.sched_param(0))
    except (OSError, AttributeError) as exc:
        refused.append(f"{_POLICIES[policy]}: {exc.strerror if isinstance(exc, OSError) else exc}")
    try:
        now_nice = os.getpriority(os.PRIO_PROCESS, tid)
        # The lower roles only ever go down: a station started under ``nice`` keeps them below it.
        if now_nice != nice and (role == "control" or nice > now_nice):
            os.setpriority(os.PRIO_PROCESS, tid, nice)
    except OSError as exc:
        refused.append(f"nice {nice}: {exc.strerror}")
    try:
        now = describe(tid)
    except OSError:  # the thread ended meanwhile
        now = "unknown"
    return note(role, now, refused)


def note(role: Role, now: str, refused: Sequence[str] = ()) -> str:
    """Record what ``role`` got (and warn once per role about a refusal); the text recorded.

    For what another process reports (a render process's :func:`enter_render_from_env`)."""
    text = now if not refused else f"{now} (refused: {'; '.join(refused)})"
    with _lock:
        _applied[role] = text
        first = refused and role not in _warned
        if first:
            _warned.add(role)
    if first:
        fix = " (raising priority needs root or CAP_SYS_NICE)" if role == "control" else ""
        log.warning("%s threads run at %s%s", role, text, fix)
    return text


def enter_render_from_env() -> str:
    """Give every thread of this process (a render process: its own, numpy's, the GL driver's)
    the ``render`` role's scheduling, as the parent passed it in :data:`RENDER_ENV` (its
    :func:`configure`); what the calling thread has now.

    Call it once the renderer exists: a render process lowered from its start needed over 30 s
    to import MuJoCo and create its GL context on a loaded 2-core host."""
    value = os.environ.get(RENDER_ENV, "")
    if value == "off":
        return "unchanged"
    policy, _, nice = value.partition(":")
    base = Priorities()
    if policy in _POLICIES and nice.isdigit():
        base = Priorities(render_policy=policy, render_nice=int(nice))  # type: ignore[arg-type]
    me = threading.get_native_id()
    with contextlib.suppress(OSError):
        for tid in (int(t) for t in os.listdir("/proc/self/task")):
            if tid != me:
                enter("render", base, tid=tid)
    return enter("render", base)


def _is_realtime(tid: int) -> bool:
    return os.sched_getscheduler(tid) in (getattr(os, "SCHED_RR", -1), getattr(os, "SCHED_FIFO", -1))
