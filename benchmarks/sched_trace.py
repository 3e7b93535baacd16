"""Benchmark: the kernel scheduler's view of a live rig: CPU and wake-to-run latency per thread role.

Runs one recorded episode of a shipped rig (``fleet`` by default) through ``RigRuntime``, as
``telerig run`` does (``control_process`` at the rig's ``runtime.realtime_priority``), with the
kernel's ``sched_switch`` and ``sched_wakeup`` events on in a ring buffer of ``--buffer-mb`` per
CPU, and reads the trace once the episode ends (streaming it to disk while the rig ran wrecked the
rig: 5 MB/s of text, 53-200 gaps an episode). Per thread role it reports:

* CPU [cores]: the thread's time on a CPU between its switch-in and switch-out, over the episode;
* wake-ups per second, and wake-to-run latency (woken, to first on a CPU) p50 / p99 / p99.9 / max
  and how many waited 1 ms or more: the time a woken control loop, MQTT client loop or physics
  loop sat in a run queue;
* run-queue waits after a preemption (switched out still runnable, to back on a CPU): p99 / max.

A role is the thread's process (the station, a robot host, a render process, the broker, the idle
pollers) and its name, which telerig gives every thread at the OS level
(:mod:`telerig.thread_names`: ``control-<robot>``, ``<robot>-physics``, ``mqtt-<role>-<id>``,
``encoder-<file>``, ...). For the longest waits of the control loops, and of every real-time
thread, it lists what ran on that CPU meanwhile and how much of it was ordinary tasks (the mark
of RT throttling or the fair server, which run those above every real-time thread). A CDF plot
per role goes beside the JSON.

The trace needs root and tracefs (``/sys/kernel/tracing``); elsewhere the benchmark says so in one
line and exits 2. It puts the tracing state back as it found it (events, buffer size, clock).

Usage: python benchmarks/sched_trace.py [--rig fleet] [--seconds 20] [--buffer-mb 64]
       [--out benchmarks/results/sched_trace.json] [--plot benchmarks/results/sched_trace.png]
       [--keep-trace trace.txt]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import tempfile
import threading
from collections import defaultdict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

from rich.console import Console
from rich.table import Table

from telerig.errors import TelerigError

#: Where tracefs is mounted, newest place first.
TRACEFS = (Path("/sys/kernel/tracing"), Path("/sys/kernel/debug/tracing"))
EVENTS = ("sched/sched_switch", "sched/sched_wakeup")
#: A wait this long or longer is counted apart [ms].
LONG_WAIT_MS = 1.0

# ``task-pid [cpu] flags timestamp: event: fields`` (the flags column only with options/irq-info).
_LINE = re.compile(r"\[(\d+)\]\s+(?:\S+\s+)?(\d+\.\d+):\s+(sched_switch|sched_wakeup):\s(.*)$")
_SWITCH = re.compile(
    r"prev_comm=(.*) prev_pid=(\d+) prev_prio=(-?\d+) prev_state=(\S+) ==> "
    r"next_comm=(.*) next_pid=(\d+) next_prio=(-?\d+)$"
)
_WAKEUP = re.compile(r"comm=(.*) pid=(\d+) prio=(-?\d+)(?: success=\d+)? target_cpu=(\d+)$")
_LOST = re.compile(r"LOST (\d+) EVENTS")


class TraceUnavailableError(RuntimeError):
    """The scheduler trace cannot be taken here (no tracefs, or no right to write it)."""


class Tracefs:
    """The kernel's scheduler events in a ring buffer, for the block; the tracing state as it was after.

    Entering checks the mount and the right to write it (raises :class:`TraceUnavailableError` with
    the fix), saves what it changes, then sets the clock to ``mono``, the buffer to ``buffer_kb``
    per CPU and the two events on, with tracing off; :meth:`on` and :meth:`off` bracket what to
    trace; :meth:`lines` reads the buffer. Leaving restores everything and empties the buffer.
    """

    def __init__(self, buffer_kb: int, root: Path | None = None) -> None:
        self.buffer_kb = buffer_kb
        self.root = (
            root if root is not None else next((p for p in TRACEFS if (p / "trace").exists()), TRACEFS[0])
        )
        self._saved: dict[str, str] = {}

    def __enter__(self) -> Tracefs:
        files = [
            "tracing_on",
            "buffer_size_kb",
            "trace_clock",
            "trace",
            *(f"events/{e}/enable" for e in EVENTS),
        ]
        missing = [f for f in files if not (self.root / f).exists()]
        if missing:
            raise TraceUnavailableError(
                f"no tracefs at {self.root} ({missing[0]} missing): mount it "
                "(mount -t tracefs nodev /sys/kernel/tracing) on a kernel with sched events"
            )
        if not all(os.access(self.root / f, os.W_OK) for f in files):
            raise TraceUnavailableError(f"{self.root} is not writable: run the benchmark as root (sudo)")
        for name in ("tracing_on", "buffer_size_kb", *(f"events/{e}/enable" for e in EVENTS)):
            self._saved[name] = self._read(name).strip()
        clock = self._read("trace_clock")
        self._saved["trace_clock"] = (
            clock[clock.index("[") + 1 : clock.index("]")] if "[" in clock else "local"
        )
        try:
            self._write("tracing_on", "0")
            self._write("trace_clock", "mono")
            self._write("buffer_size_kb", str(self.buffer_kb))
            self._write("trace", "")
            for event in EVENTS:
                self._write(f"events/{event}/enable", "1")
        except OSError:
            self._restore()
            raise
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._restore()

    def on(self) -> None:
        self._write("tracing_on", "1")

    def off(self) -> None:
        self._write("tracing_on", "0")

    def lines(self) -> Iterator[str]:
        """The buffer as text, oldest event first (CPUs merged by time)."""
        with (self.root / "trace").open(errors="replace") as text:
            yield from text

    def _restore(self) -> None:
        self._write("tracing_on", "0")
        for event in EVENTS:
            self._write(f"events/{event}/enable", self._saved.get(f"events/{event}/enable", "0"))
        self._write("trace", "")
        for name in ("trace_clock", "buffer_size_kb", "tracing_on"):
            if name in self._saved:
                self._write(name, self._saved[name])

    def _read(self, name: str) -> str:
        return (self.root / name).read_text()

    def _write(self, name: str, value: str) -> None:
        (self.root / name).write_text(value)


@dataclass
class ThreadTrace:
    """What the trace saw of one thread (a task: pid in the kernel's sense)."""

    tid: int
    comm: str = ""
    prio: int = 120
    on_cpu_s: float = 0.0
    #: Woken to first on a CPU [ms], one per wake-up.
    wake_ms: list[float] = field(default_factory=list)
    #: Switched out runnable (preempted) to back on a CPU [ms].
    preempted_ms: list[float] = field(default_factory=list)


@dataclass
class Trace:
    """The parsed trace: per thread, the waits worth a look, and what ran on each CPU."""

    threads: dict[int, ThreadTrace]
    #: Waits >= LONG_WAIT_MS: (waited [ms], tid, the CPU it was woken onto or preempted on, from
    #: [s], ran [s], ``woken`` or ``preempted``).
    long_waits: list[tuple[float, int, int, float, float, str]]
    #: Per CPU: (start [s], end [s], tid) of each stretch a task ran (idle, tid 0, included).
    runs: dict[int, list[tuple[float, float, int]]]
    events: int
    malformed: int
    lost: int
    span_s: float


def parse(lines: Iterable[str]) -> Trace:
    """Read ``sched_switch``/``sched_wakeup`` lines of the kernel's text trace (others are skipped;
    an event line that does not parse is counted in ``malformed``, a ``LOST n EVENTS`` mark in
    ``lost``)."""
    threads: dict[int, ThreadTrace] = {}
    # Per CPU: the task on it, since when. CPUs' clocks differ by microseconds, so a task that moves
    # may show its switch-in on the new CPU just before its switch-out on the old one.
    running: dict[int, tuple[int, float]] = {}
    woken: dict[int, tuple[float, int]] = {}
    preempted: dict[int, tuple[float, int]] = {}
    long_waits: list[tuple[float, int, int, float, float, str]] = []
    runs: dict[int, list[tuple[float, float, int]]] = defaultdict(list)
    events = malformed = lost = 0
    first = last = None

    def on_a_cpu(tid: int) -> bool:
        return any(task == tid for task, _ in running.values())

    def thread(tid: int, comm: str, prio: int) -> ThreadTrace:
        t = threads.get(tid)
        if t is None:
            t = threads[tid] = ThreadTrace(tid)
        t.comm, t.prio = comm, prio
        return t

    for line in lines:
        if line.startswith("#"):
            continue
        mark = _LOST.search(line)
        if mark is not None and "sched_" not in line:
            lost += int(mark.group(1))
            continue
        match = _LINE.search(line.rstrip("\n"))
        if match is None:
            malformed += bool(line.strip())
            continue
        cpu, ts, kind, body = int(match.group(1)), float(match.group(2)), match.group(3), match.group(4)
        if kind == "sched_wakeup":
            fields = _WAKEUP.match(body)
            if fields is None:
                malformed += 1
                continue
            tid = int(fields.group(2))
            if tid:
                thread(tid, fields.group(1), int(fields.group(3)))
                # A task woken while still on a CPU (it had not yet switched out) or while runnable
                # in a queue (preempted: its wait counts from then) waits for nothing new.
                if not on_a_cpu(tid) and tid not in preempted:
                    woken.setdefault(tid, (ts, int(fields.group(4))))
        else:
            fields = _SWITCH.match(body)
            if fields is None:
                malformed += 1
                continue
            prev, nxt = int(fields.group(2)), int(fields.group(6))
            woken.pop(prev, None)  # it ran: a wake-up noted before is spent
            was = running.pop(cpu, None)
            if was is not None and was[0] == prev:
                runs[cpu].append((was[1], ts, prev))
                if prev:
                    thread(prev, fields.group(1), int(fields.group(3))).on_cpu_s += ts - was[1]
            if prev and fields.group(4).startswith("R") and not on_a_cpu(prev):
                preempted[prev] = (ts, cpu)  # runnable, in a queue
            else:
                preempted.pop(prev, None)  # asleep, or already on another CPU
            running[cpu] = (nxt, ts)
            if nxt:
                t = thread(nxt, fields.group(5), int(fields.group(7)))
                wake = woken.pop(nxt, None)
                if wake is not None:
                    ms = (ts - wake[0]) * 1e3
                    t.wake_ms.append(ms)
                    if ms >= LONG_WAIT_MS:
                        long_waits.append((ms, nxt, wake[1], wake[0], ts, "woken"))
                elif nxt in preempted:
                    since, where = preempted.pop(nxt)
                    ms = (ts - since) * 1e3
                    t.preempted_ms.append(ms)
                    if ms >= LONG_WAIT_MS:
                        long_waits.append((ms, nxt, where, since, ts, "preempted"))
        events += 1
        first = ts if first is None else first
        last = ts
    span = (last - first) if first is not None and last is not None else 0.0
    return Trace(threads, long_waits, dict(runs), events, malformed, lost, span)


# --- who is who -----------------------------------------------------------------------------------

#: (process kind, the test on its command line), first match wins.
_PROCESS_KINDS = (
    ("robot host", "telerig.runtime.robot_host"),
    ("render", "_render_worker"),
    ("QA worker", "telerig.runtime.qa_worker"),
    ("idle poller", "SCHED_IDLE"),
    ("blackout probe", "SCHED_FIFO"),  # rt_blackout.py's, which fleet.py runs
    ("broker", "mosquitto"),
)
#: (thread role, the test on its OS name), first match wins.
_THREAD_ROLES = (
    ("control loop", re.compile(r"^control-")),
    ("physics", re.compile(r"-phys")),
    ("MQTT client loop", re.compile(r"^mqtt-")),
    ("video encode", re.compile(r"^encoder-")),  # libx264's threads inherit the name
    ("preview", re.compile(r"^preview-")),
    ("camera", re.compile(r"^camera-")),
    ("health", re.compile(r"^health-")),
    ("recorder", re.compile(r"^recorder|^mcap-")),
    ("device", re.compile(r"^telerig-")),
)


def process_kind(cmdline: str) -> str:
    """The kind of a rig's process (not the station's) from its command line (``soak.py`` reads
    its processes by the same names)."""
    return next((name for name, test in _PROCESS_KINDS if test in cmdline), "other process")


def process_kinds(station_pid: int) -> dict[int, tuple[int, str]]:
    """Every live thread's tid → (its process's pid, the kind of process), read from /proc."""
    out: dict[int, tuple[int, str]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        pid = int(entry.name)
        try:
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            tids = [int(t.name) for t in (entry / "task").iterdir()]
        except OSError:
            continue
        kind = "station" if pid == station_pid else process_kind(cmdline)
        for tid in tids:
            out[tid] = (pid, kind)
    return out


def role(kind: str, comm: str) -> str:
    """The role of a thread named ``comm`` (its OS name) in a process of ``kind`` (``ended``: a
    thread gone before any look at /proc; its name alone tells its role)."""
    if kind not in ("station", "robot host", "ended"):
        return kind  # a process of one job: its threads share its role
    for name, test in _THREAD_ROLES:
        if test.search(comm):
            return f"{kind}: {name}"
    return f"{kind}: main and other threads"


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def summarize(trace: Trace, who: dict[int, tuple[int, str]], seconds: float) -> dict[str, Any]:
    """Per role and per thread: CPU, wake-ups, wake-to-run and preempted waits; the longest waits
    of the real-time threads, and of the control loops among them, with what ran on their CPU
    meanwhile (and how much of that was ordinary tasks: the kernel's RT throttling and fair server
    run those above every real-time thread)."""
    span = trace.span_s or seconds
    roles: dict[str, list[ThreadTrace]] = defaultdict(list)
    role_of: dict[int, str] = {}
    for tid, t in trace.threads.items():
        role_of[tid] = role(who[tid][1] if tid in who else "ended", t.comm)
        roles[role_of[tid]].append(t)

    def stats(ts: list[ThreadTrace]) -> dict[str, Any]:
        wake = [w for t in ts for w in t.wake_ms]
        pre = [w for t in ts for w in t.preempted_ms]
        return {
            "threads": len(ts),
            "cpu_cores": sum(t.on_cpu_s for t in ts) / span,
            "wakeups_per_s": len(wake) / span,
            "wake_p50_ms": _pct(wake, 50),
            "wake_p99_ms": _pct(wake, 99),
            "wake_p999_ms": _pct(wake, 99.9),
            "wake_max_ms": max(wake) if wake else None,
            "waits_over_1ms": sum(w >= LONG_WAIT_MS for w in wake),
            "preempted": len(pre),
            "preempted_p99_ms": _pct(pre, 99),
            "preempted_max_ms": max(pre) if pre else None,
            "prios": sorted({t.prio for t in ts}),
        }

    by_role = {name: stats(ts) for name, ts in roles.items()}
    per_thread = [
        {"tid": t.tid, "comm": t.comm, "role": role_of[t.tid], "prio": t.prio, **stats([t])}
        for t in trace.threads.values()
        if t.on_cpu_s > 0.001 * span or len(t.wake_ms) > 10
    ]

    def described(wait: tuple[float, int, int, float, float, str]) -> dict[str, Any]:
        ms, tid, cpu, since, ran, kind = wait
        meanwhile: dict[str, float] = defaultdict(float)
        ordinary = 0.0  # time ordinary (not real-time) tasks had that CPU while this one waited
        for start, end, other in trace.runs.get(cpu, []):
            overlap = min(end, ran) - max(start, since)
            if overlap <= 0:
                continue
            other_t = trace.threads.get(other)
            meanwhile["idle" if other == 0 else (other_t.comm if other_t else str(other))] += overlap * 1e3
            if other and other_t is not None and other_t.prio >= 100:
                ordinary += overlap * 1e3
        return {
            "thread": trace.threads[tid].comm,
            "role": role_of[tid],
            "kind": kind,
            "waited_ms": ms,
            "cpu": cpu,
            "ordinary_tasks_ms": ordinary,
            "meanwhile_ms": dict(sorted(meanwhile.items(), key=lambda kv: -kv[1])[:5]),
        }

    realtime = sorted((w for w in trace.long_waits if trace.threads[w[1]].prio < 100), reverse=True)
    control = [w for w in realtime if role_of[w[1]].endswith("control loop")]
    return {
        "roles": dict(sorted(by_role.items(), key=lambda kv: -kv[1]["cpu_cores"])),
        "threads": sorted(per_thread, key=lambda t: -t["cpu_cores"]),
        "worst_control_waits": [described(w) for w in control[:5]],
        "worst_realtime_waits": [described(w) for w in realtime[:10]],
        "events": trace.events,
        "malformed": trace.malformed,
        "lost_events": trace.lost,
        "span_s": span,
        "wake_ms_by_role": {name: [w for t in ts for w in t.wake_ms] for name, ts in roles.items()},
    }


# --- the run --------------------------------------------------------------------------------------


def run(
    rig: str, seconds: float, buffer_kb: int, keep: Path | None = None
) -> tuple[dict[str, Any], dict[str, Any]]:
    """One episode of ``rig`` under the trace; the summary and the episode's figures. ``keep``:
    where to write the raw trace as well (text, tens of MB)."""
    from telerig.config import load_rig
    from telerig.runtime.process_settings import control_process
    from telerig.runtime.rig import RigRuntime

    config = load_rig(rig)
    with (
        Tracefs(buffer_kb) as tracefs,
        tempfile.TemporaryDirectory() as tmp,
        control_process(realtime_priority=config.runtime.realtime_priority),
        RigRuntime(config, data_root=Path(tmp)) as runtime,
    ):
        # Who is who, looked up before, during (the episode's own threads: the recorder's writer,
        # the encoders) and after the episode.
        who = process_kinds(os.getpid())
        looks = [threading.Timer(seconds / 2, lambda: who.update(process_kinds(os.getpid())))]
        tracefs.on()
        try:
            looks[0].start()
            result = runtime.run_episode(seconds)
        finally:
            tracefs.off()
            looks[0].cancel()
        who.update(process_kinds(os.getpid()))
        if keep is not None:
            keep.parent.mkdir(parents=True, exist_ok=True)
            with keep.open("w") as raw:
                raw.writelines(tracefs.lines())
        trace = parse(tracefs.lines())
    episode = {
        "episode_id": result.episode_id,
        "latency_p50_ms": result.latency.p50_ms,
        "latency_p99_ms": result.latency.p99_ms,
    }
    return summarize(trace, who, seconds), episode


def _ms(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _plot(summary: dict[str, Any], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 5.5))
    shown = [
        (name, waits)
        for name, waits in sorted(summary["wake_ms_by_role"].items())
        if len(waits) >= 50 and name not in ("other process", "idle poller")
    ]
    colors = plt.get_cmap("tab20")(np.linspace(0.0, 1.0, max(len(shown), 1), endpoint=False))
    for k, (name, waits) in enumerate(shown):
        values = np.sort(np.maximum(np.asarray(waits), 1e-3))
        style = "-" if "control" in name or k % 2 == 0 else "--"
        ax.plot(
            values, 1.0 - np.arange(values.size) / values.size, style, color=colors[k], label=name, lw=1.3
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("woken → on a CPU [ms]")
    ax.set_ylabel("fraction of wake-ups that waited longer")
    ax.axvline(LONG_WAIT_MS, color="grey", linestyle=":", linewidth=1)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    if shown:
        ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rig", default="fleet", help="a shipped rig's name (default: fleet)")
    parser.add_argument("--seconds", type=float, default=20.0, help="the episode's length [s]")
    parser.add_argument("--buffer-mb", type=int, default=64, help="trace ring buffer per CPU [MB]")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/sched_trace.json"))
    parser.add_argument("--plot", type=Path, default=Path("benchmarks/results/sched_trace.png"))
    parser.add_argument("--keep-trace", type=Path, default=None, help="also write the raw trace here")
    args = parser.parse_args()
    if args.seconds <= 0 or not 1 <= args.buffer_mb <= 4096:
        parser.error("--seconds must be > 0 and --buffer-mb 1..4096")
    console = Console(width=160)
    try:
        with console.status(f"{args.rig}: one {args.seconds:g} s episode under the scheduler trace"):
            summary, episode = run(args.rig, args.seconds, args.buffer_mb * 1024, args.keep_trace)
    except TraceUnavailableError as exc:
        console.print(f"[red]cannot trace the scheduler[/]: {exc}")
        return 2
    except TelerigError as exc:  # an unknown rig, a rig that does not start
        console.print(f"[red]{args.rig}[/]: {exc}")
        return 2
    table = Table(
        title=f"{args.rig}: CPU and wake-to-run latency per thread role ({summary['span_s']:.1f} s traced)"
    )
    for col in (
        "role",
        "threads",
        "prio",
        "CPU cores",
        "wake-ups/s",
        "p50 ms",
        "p99 ms",
        "p99.9 ms",
        "max ms",
        f">= {LONG_WAIT_MS:g} ms",
        "preempted p99 / max ms",
    ):
        table.add_column(col, justify="left" if col == "role" else "right")
    for name, r in summary["roles"].items():
        table.add_row(
            name,
            str(r["threads"]),
            ",".join(str(p) for p in r["prios"][:3]) + ("…" if len(r["prios"]) > 3 else ""),
            f"{r['cpu_cores']:.3f}",
            f"{r['wakeups_per_s']:.0f}",
            _ms(r["wake_p50_ms"], 3),
            _ms(r["wake_p99_ms"]),
            _ms(r["wake_p999_ms"]),
            _ms(r["wake_max_ms"]),
            str(r["waits_over_1ms"]),
            f"{_ms(r['preempted_p99_ms'])} / {_ms(r['preempted_max_ms'])}",
        )
    console.print(table)
    console.print(
        "prio: the kernel's (99 - P for SCHED_RR/FIFO priority P, 120 + niceness otherwise); "
        f"events {summary['events']}, malformed {summary['malformed']}, lost {summary['lost_events']}"
        + ("  [red](buffer too small: raise --buffer-mb)[/]" if summary["lost_events"] else "")
    )
    console.print(
        f"episode {episode['episode_id']}: input-to-actuation p50 {_ms(episode['latency_p50_ms'])} / "
        f"p99 {_ms(episode['latency_p99_ms'])} ms"
    )
    for title, key in (
        ("the control loops' longest waits", "worst_control_waits"),
        ("the real-time threads' longest waits", "worst_realtime_waits"),
    ):
        if summary[key]:
            console.print(f"{title}, and what ran on that CPU meanwhile [ms]:")
        for w in summary[key]:
            ran = ", ".join(f"{k} {v:.2f}" for k, v in w["meanwhile_ms"].items())
            console.print(
                f"  {w['thread']} ({w['role']}) {w['kind']}, waited {w['waited_ms']:.2f} on CPU {w['cpu']}"
                f" (ordinary tasks {w['ordinary_tasks_ms']:.2f}): {ran}"
            )
    _plot(summary, args.plot, f"{args.rig}: wake-to-run latency by thread role")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    data = {k: v for k, v in summary.items() if k != "wake_ms_by_role"}
    args.out.write_text(
        json.dumps(
            {
                "benchmark": "sched_trace",
                "host": {
                    "cpus": os.cpu_count(),
                    "python": platform.python_version(),
                    "kernel": platform.release(),
                    # Its build: PREEMPT_DYNAMIC, PREEMPT_RT, ... (how far kernel code yields to a thread).
                    "kernel_version": platform.version(),
                },
                "rig": args.rig,
                "seconds": args.seconds,
                "long_wait_ms": LONG_WAIT_MS,
                "episode": episode,
                **data,
            },
            indent=2,
        )
    )
    console.print(f"wrote {args.out} and {args.plot}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
