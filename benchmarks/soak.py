"""Endurance: a rig recording back-to-back episodes for minutes to an hour, watched for leaks and gaps.

Runs the rig (``demo``: one UR5e with the 640x480@30 scene camera; ``fleet``: six robots; both
with each robot in a process of its own, or all in the station's with ``--isolation threads``)
through ``RigRuntime.run_episode`` as ``telerig run`` does (same process settings, embedded
Mosquitto, recorder, index, QA gates), episode after episode until ``--minutes`` of recording have
passed. Beside it a sampler thread reads, every ``--sample-s`` seconds, each process
of the station (the station itself and its children: robot hosts, render workers, the broker, the
QA worker; grouped by role, since render workers are per camera and may be respawned) with psutil:
resident memory [MiB], open file descriptors and threads; and the data root's size and the index
database's size on disk. After each episode it reads the episode's manifest: status, input-to-
actuation latency p50/p99 [ms], stream drops and gaps (health monitor), camera frames dropped,
missing streams, malformed messages; and the index's row count.

At the end, for each metric, the least-squares slope [per minute] over the samples after warm-up
(the later of: the first 20 % of the run, the end of the second episode): memory, descriptors and
threads must not grow once the rig is warm. Verdict (exit 1 when it fails, with the reasons):

* RSS of any role (or of all processes together) grows by more than 1 MiB/min after warm-up;
* descriptors or threads grow: the fitted line over the samples taken between episodes (the rig
  idle, so a per-episode file or thread cannot blur it) rises by 1 or more over the post-warm-up
  span, for any role or in total; or the number of processes of a role grows the same way;
* any stream drop, gap or stall (health monitor), any camera frame dropped, any missing stream,
  malformed message or control tick fault;
* any episode whose status is not ``complete``; the index's rows differ from the episodes recorded;
* the quality gates fall behind (``qa.after_commit``): after warm-up, an episode ends with more than
  :data:`QA_MAX_WAITING` episodes waiting for their verdict (the one just committed included), or
  some episode still has none :data:`QA_DRAIN_S` after the last one ended. The first full hour
  (2026-11-27, the gates stopped while each episode recorded) had no verdict at all after 128
  episodes: a station recording back to back gave its gates 0.5 s between episodes;
* any thin episode: one that recorded fewer than :data:`THIN_SHARE` of the run's median messages per
  second. On 2026-11-26 five episodes taken while the hypervisor stole 42-66 % of the CPU recorded
  119-3 526 messages each against ~13 000 and still said ``complete``: the manifest's status says the
  recording was closed properly, not that it holds what the rig sent.

Each episode's line and record also carry its start/stop overhead (``overhead_s``: the wall time of
``run_episode`` beyond the recording itself: opening the MCAP, starting and joining the recorder,
the gates' hand-off), reported with its drift, not judged. One of those five took 128 s of wall time
for a 26 s recording.

Beside the rig, one ``SCHED_FIFO`` probe per CPU above every thread of it (``rt_blackout.py``)
notes each moment the kernel stopped every real-time thread on a CPU. Each episode's record carries
the blackouts inside it (``rt_blackouts``: [s into the episode, ms]) and the report says how many of
the episodes with gaps had one: a gap in such an episode may be the host's, not the rig's. It is
reported, not excused: a gap fails the verdict either way. Each record also carries the station's
garbage collections of 2 ms or more inside the episode (``gc_pauses``: [s, generation, ms, thread];
``gc_pauses.py``), which stop every thread of the station's process while they run.

Latency drift (p99 per episode against time) and data root / index growth [MB/min, kB/episode] are
reported, not judged: a dataset grows by design.

A one-hour run wants a quiet host (nothing else competing for the 2 cores): the gap and latency
figures are the machine's as much as the rig's on a shared one.

Usage: python benchmarks/soak.py [--rig demo|fleet] [--minutes 60] [--episode-s 15]
       [--sample-s 2] [--isolation threads|processes] [--idle-poll | --no-idle-poll] [--gates idle|pause|off]
       [--out benchmarks/results/soak_demo.json] [--plot benchmarks/results/soak_demo.png]
For the endurance note: ``--rig demo --minutes 60`` and ``--rig fleet --minutes 20``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import platform
import sys
import tempfile
import threading
import time
from collections.abc import Iterable
from concurrent.futures import wait
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

import numpy as np
import psutil
from rich.console import Console
from rich.table import Table

from telerig import priority
from telerig.config import load_rig
from telerig.errors import TelerigError
from telerig.runtime.process_settings import control_process
from telerig.runtime.rig import RigRuntime
from telerig.store.episodes import EpisodeManifest
from telerig.store.index import DEFAULT_FILENAME
from telerig.store.manifest_extra import EpisodeExtra

sys.path.insert(0, str(Path(__file__).parent))
from gc_pauses import GcPauses
from host_steal import StealMeter, steal_text, steal_warning
from rt_blackout import RtBlackoutProbe, blackout_text
from sched_trace import process_kind

#: RSS growth after warm-up that fails the verdict [MiB/min] (per role and in total).
RSS_SLOPE_LIMIT_MIB_PER_MIN = 1.0
#: Fitted growth over the post-warm-up span of descriptors, threads or processes that fails it.
COUNT_GROWTH_LIMIT = 1.0
#: Warm-up: this share of the run, or the first WARMUP_EPISODES episodes, whichever ends later.
WARMUP_SHARE = 0.2
WARMUP_EPISODES = 2
#: An episode recording fewer messages per second than this share of the run's median is thin.
THIN_SHARE = 0.5
#: Episodes that may wait for their verdict at an episode's end: the one just committed and the
#: one before it, still being checked.
QA_MAX_WAITING = 2
#: How long the verdicts still missing after the last episode may take to come [s].
QA_DRAIN_S = 120.0
#: A probe's wake-up this late is a real-time blackout [ms]. Half a 100 Hz period: a robot's state
#: read that much late already reads the next physics wake's state (the wakes keep half a period
#: from the reads), and its stream skips one.
BLACKOUT_MS = 4.0

MIB = 1024 * 1024


def role(proc: psutil.Process, station_pid: int) -> str:
    """What a process of the station is, from its command line (children are fresh interpreters):
    ``sched_trace.process_kind``'s names (``robot host``, ``render``, ``QA worker``, ``broker``,
    ...), ``other:<name>`` for a process of none of them."""
    if proc.pid == station_pid:
        return "station"
    try:
        cmd = " ".join(proc.cmdline())
        name = proc.name()
    except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
        return "gone"
    kind = process_kind(f"{name} {cmd}")
    return f"other:{name}" if kind == "other process" else kind


@dataclass
class Sample:
    """One reading of the station [s since the first episode's start, MiB, counts, bytes]."""

    t_s: float
    between_episodes: bool
    rss_mib: dict[str, float]
    fds: dict[str, int]
    threads: dict[str, int]
    processes: dict[str, int]
    data_root_bytes: int
    index_bytes: int


def tree_bytes(root: Path) -> int:
    """Total size of the regular files under ``root`` [bytes] (files vanishing meanwhile are skipped)."""
    total = 0
    for dirpath, _, files in os.walk(root):
        for f in files:
            with contextlib.suppress(OSError):  # a file moved or removed meanwhile
                total += os.lstat(os.path.join(dirpath, f)).st_size
    return total


def index_bytes(root: Path) -> int:
    """The SQLite index with its write-ahead log and shared memory [bytes]."""
    total = 0
    for suffix in ("", "-wal", "-shm"):
        path = root / (DEFAULT_FILENAME + suffix)
        if path.exists():
            total += path.stat().st_size
    return total


def read_processes(
    station: psutil.Process,
) -> tuple[dict[str, float], dict[str, int], dict[str, int], dict[str, int]]:
    """RSS [MiB], open descriptors, threads and process count per role, over the station's tree."""
    rss: dict[str, float] = {}
    fds: dict[str, int] = {}
    threads: dict[str, int] = {}
    count: dict[str, int] = {}
    for proc in [station, *station.children(recursive=True)]:
        try:
            with proc.oneshot():
                label = role(proc, station.pid)
                r, f, n = proc.memory_info().rss / MIB, proc.num_fds(), proc.num_threads()
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            continue  # a worker that ended between listing and reading
        rss[label] = rss.get(label, 0.0) + r
        fds[label] = fds.get(label, 0) + f
        threads[label] = threads.get(label, 0) + n
        count[label] = count.get(label, 0) + 1
    return rss, fds, threads, count


@dataclass
class Sampler:
    """Reads the station every ``period_s`` on its own thread (and on demand between episodes)."""

    root: Path
    period_s: float
    t0: float = field(default_factory=time.monotonic)
    samples: list[Sample] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _station: psutil.Process = field(default_factory=psutil.Process)
    _thread: threading.Thread | None = None

    def take(self, *, between_episodes: bool = False) -> Sample:
        rss, fds, threads, count = read_processes(self._station)
        sample = Sample(
            round(time.monotonic() - self.t0, 3),
            between_episodes,
            rss,
            fds,
            threads,
            count,
            tree_bytes(self.root),
            index_bytes(self.root),
        )
        with self._lock:
            self.samples.append(sample)
        return sample

    def start(self) -> None:
        self.t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="soak-sampler", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def _run(self) -> None:
        # Below the control loops, like any observer: started from the station's thread, it would
        # otherwise read every process and walk the data root at the robots' SCHED_RR priority.
        priority.enter("work")
        while not self._stop.wait(self.period_s):
            self.take()


def _total(rows: Iterable[Any], key: str) -> int:
    """Sum of the integer field ``key`` over JSON objects (rows that are not objects count 0)."""
    return sum(int(r.get(key) or 0) for r in rows if isinstance(r, dict))


def _by_stream(health_streams: dict[str, Any], key: str) -> dict[str, int]:
    """Topic -> the integer field ``key`` of its health row, for the streams where it is not 0."""
    counts = {name: int(row.get(key) or 0) for name, row in health_streams.items() if isinstance(row, dict)}
    return {name: n for name, n in sorted(counts.items()) if n}


def episode_record(runtime: RigRuntime, result: Any, t_start: float, t_end: float) -> dict[str, Any]:
    """What one episode's manifest says about latency, drops and gaps, with its status."""
    try:  # where it lies now (the gates may move it to failures/): cheap, unlike store.get's listing
        manifest = EpisodeManifest.model_validate_json((result.path / "manifest.json").read_bytes())
    except FileNotFoundError:  # moved between locating and reading
        manifest = runtime.store.get(result.episode_id, include_unfinished=True)
    extra = EpisodeExtra.of(manifest)
    latency = extra.latency_ms or {}
    health = extra.health if isinstance(extra.health, dict) else {}
    health_streams = health.get("streams")
    if not isinstance(health_streams, dict):
        health_streams = {}
    stream_drops = _total(extra.streams, "drops")
    gaps = _total(health_streams.values(), "gaps")
    health_drops = _total(health_streams.values(), "drops")
    stalls = _total(health_streams.values(), "stalls")
    messages = _total(extra.streams, "messages")
    index = runtime.index
    duration_s = float(result.duration_s)
    return {
        "episode_id": result.episode_id,
        "status": manifest.status,
        "start_s": round(t_start, 3),
        "end_s": round(t_end, 3),
        "duration_s": duration_s,
        # Wall time beyond the recording: opening, starting, stopping and handing the episode over.
        "overhead_s": round(t_end - t_start - duration_s, 3),
        "latency_count": latency.get("count"),
        "latency_p50_ms": latency.get("p50_ms"),
        "latency_p99_ms": latency.get("p99_ms"),
        "latency_max_ms": latency.get("max_ms"),
        "messages": messages,
        "message_rate_hz": round(messages / duration_s, 1) if duration_s > 0 else 0.0,
        "stream_drops": max(stream_drops, health_drops),
        "gaps": gaps,
        "stalls": stalls,
        # Where they were: topic -> count, the streams with any (a failing verdict names them).
        "gaps_by_stream": _by_stream(health_streams, "gaps"),
        "drops_by_stream": _by_stream(health_streams, "drops"),
        "camera_frames": sum(c.frames for c in extra.cameras.values()),
        "camera_dropped": sum(c.dropped for c in extra.cameras.values()),
        "missing_streams": sorted(extra.missing_streams),
        "malformed": sum(extra.malformed_messages.values()),
        "tick_faults": sum(extra.tick_faults.values()),
        "index_rows": index.count_episodes() if index is not None else None,
        "qa_waiting": qa_waiting(runtime),
    }


def stream_totals(episodes: Iterable[dict[str, Any]], key: str) -> list[tuple[str, int]]:
    """Topic -> the sum of ``key`` (``gaps_by_stream`` or ``drops_by_stream``) over the episodes,
    largest first."""
    totals: dict[str, int] = {}
    for e in episodes:
        for topic, n in (e.get(key) or {}).items():
            totals[topic] = totals.get(topic, 0) + int(n)
    return sorted(totals.items(), key=lambda kv: (-kv[1], kv[0]))


def note_blackouts(episodes: list[dict[str, Any]], probe: RtBlackoutProbe) -> str:
    """Set each episode's ``rt_blackouts`` ([s into the episode, ms] for each of the probe's blackouts
    inside it; None where the probes did not watch to the end) and return the report's line on them."""
    windows = [e["wall_ns"] for e in episodes if e.get("wall_ns")]
    for e in episodes:
        if probe.not_measured is not None or not e.get("wall_ns"):
            e["rt_blackouts"] = None
            continue
        start_ns, end_ns = e["wall_ns"]
        e["rt_blackouts"] = [
            [round((b.start_ns - start_ns) / 1e9, 3), round(b.ms, 1)]
            for b in probe.overlapping(start_ns, end_ns)
        ]
    if not windows:
        return "real-time blackouts: no episode recorded"
    line = blackout_text(probe, windows[0][0], windows[-1][1])
    with_gaps = [e for e in episodes if e["gaps"]]
    if probe.not_measured is None and with_gaps:
        hit = [e for e in with_gaps if e["rt_blackouts"]]
        line += (
            f"\n{len(hit)} of the {len(with_gaps)} episodes with gaps had a real-time blackout "
            f"({sum(e['gaps'] for e in hit)} of the {sum(e['gaps'] for e in with_gaps)} gaps)"
        )
    return line


def note_collections(episodes: list[dict[str, Any]], collections: GcPauses) -> str:
    """Set each episode's ``gc_pauses`` ([s into the episode, generation, ms, thread] for each of the
    station's garbage collections inside it of ``GcPauses``' threshold or more) and return the
    report's line on them. In a rig whose robots run in processes of their own a station's
    collection stops its recorder, not a robot's tick, and leaves no gap in the capture times; with
    ``--isolation threads`` it stops every robot."""
    for e in episodes:
        if not e.get("wall_ns"):
            e["gc_pauses"] = []
            continue
        start_ns, end_ns = e["wall_ns"]
        e["gc_pauses"] = [
            [round((p.start_ns - start_ns) / 1e9, 3), p.generation, round(p.ms, 1), p.thread]
            for p in collections.overlapping(start_ns, end_ns)
        ]
    counts = ", ".join(f"gen {g}: {n}" for g, n in sorted(collections.counts.items()))
    seen = collections.pauses
    line = f"the station's garbage collections ({counts}): {len(seen)} of 2 ms or more"
    if seen:
        full = [p.ms for p in seen if p.generation == 2]
        longest = max(seen, key=lambda p: p.ms)
        line += f", longest {longest.ms:.0f} ms (gen {longest.generation}, thread {longest.thread})" + (
            f"; full ones: {len(full)}, median {float(np.median(full)):.0f} ms" if full else ""
        )
    # No "episodes with gaps that had one" here, as for the blackouts: every fleet episode has full
    # collections of 10-50 ms (two as it ends), so only a gap's own time can tell (the JSON has both).
    return line


def qa_waiting(runtime: RigRuntime) -> int:
    """Episodes submitted to the quality gates with no verdict yet."""
    return sum(not f.done() for f in list(runtime.storage.qa_checks.values()))


def drain_qa(runtime: RigRuntime, timeout_s: float) -> dict[str, Any]:
    """Wait up to ``timeout_s`` for the verdicts still missing; how many came and how long it took."""
    checks = list(runtime.storage.qa_checks.values())
    waiting = sum(not f.done() for f in checks)
    t0 = time.monotonic()
    wait(checks, timeout=timeout_s)
    return {
        "submitted": len(checks),
        "waiting_at_end": waiting,
        "drain_s": round(time.monotonic() - t0, 3),
        "unchecked_after_drain": sum(not f.done() for f in checks),
        "failed": sum(f.done() and (f.cancelled() or f.exception() is not None) for f in checks),
    }


def failed_episode(status: str, t_start: float, t_end: float) -> dict[str, Any]:
    """The record of an episode that raised instead of ending: no manifest to read."""
    return {
        "episode_id": "-",
        "status": status,
        "start_s": round(t_start, 3),
        "end_s": round(t_end, 3),
        "duration_s": 0.0,
        "overhead_s": round(t_end - t_start, 3),
        "latency_count": None,
        "latency_p50_ms": None,
        "latency_p99_ms": None,
        "latency_max_ms": None,
        "messages": 0,
        "message_rate_hz": 0.0,
        "stream_drops": 0,
        "gaps": 0,
        "stalls": 0,
        "gaps_by_stream": {},
        "drops_by_stream": {},
        "camera_frames": 0,
        "camera_dropped": 0,
        "missing_streams": [],
        "malformed": 0,
        "tick_faults": 0,
        "index_rows": None,
        "qa_waiting": 0,
    }


def slope_per_min(t_s: np.ndarray, y: np.ndarray) -> float | None:
    """Least-squares slope of ``y`` against time [per minute]; None with fewer than 2 points or no span."""
    if t_s.size < 2 or float(np.ptp(t_s)) <= 0:
        return None
    return float(np.polyfit(t_s / 60.0, y, 1)[0])


def _in_blackouts(episode: dict[str, Any]) -> str:
    """`` (in an episode with N real-time blackouts, longest M ms)`` where the probe saw any, else ``""``."""
    seen = episode.get("rt_blackouts") or []
    if not seen:
        return ""
    return (
        f" (in an episode with {len(seen)} real-time blackouts, longest {max(ms for _, ms in seen):.0f} ms)"
    )


def thin_episodes(episodes: list[dict[str, Any]]) -> list[str]:
    """A failure line for each recorded episode below :data:`THIN_SHARE` of the run's median
    message rate (episodes that raised are failures of their own and set no median)."""
    rates = [e["message_rate_hz"] for e in episodes if e["episode_id"] != "-" and e["duration_s"] > 0]
    if not rates:
        return []
    median = float(np.median(rates))
    return [
        f"episode {e['episode_id']}: thin, {e['messages']} messages ({e['message_rate_hz']:.0f}/s, "
        f"under {THIN_SHARE:.0%} of the run's median {median:.0f}/s)"
        for e in episodes
        if e["episode_id"] != "-" and e["duration_s"] > 0 and e["message_rate_hz"] < THIN_SHARE * median
    ]


def analyse(
    samples: list[Sample],
    episodes: list[dict[str, Any]],
    warmup_end_s: float,
    qa: dict[str, Any] | None = None,
    index_closed_bytes: int | None = None,
) -> dict[str, Any]:
    """Slopes per metric after warm-up and the verdict's failures (``qa``: :func:`drain_qa`'s record;
    ``index_closed_bytes``: the index once the rig closed it, its write-ahead log folded in)."""
    failures: list[str] = []
    behind = [e for e in episodes if e["start_s"] >= warmup_end_s and e["qa_waiting"] > QA_MAX_WAITING]
    if behind:
        failures.append(
            f"the quality gates fell behind: {len(behind)} episodes after warm-up ended with more than "
            f"{QA_MAX_WAITING} waiting for a verdict (up to {max(e['qa_waiting'] for e in behind)})"
        )
    if qa is not None and qa["unchecked_after_drain"]:
        failures.append(
            f"{qa['unchecked_after_drain']} of {qa['submitted']} episodes had no verdict {QA_DRAIN_S:g} s "
            "after the last one ended"
        )
    roles = sorted({r for s in samples for r in s.rss_mib})
    after = [s for s in samples if s.t_s >= warmup_end_s]
    between = [s for s in after if s.between_episodes]
    span_min = (after[-1].t_s - after[0].t_s) / 60.0 if len(after) > 1 else 0.0
    between_span_min = (between[-1].t_s - between[0].t_s) / 60.0 if len(between) > 1 else 0.0
    metrics: dict[str, dict[str, Any]] = {}

    def series(rows: list[Sample], get: Any) -> tuple[np.ndarray, np.ndarray]:
        return np.array([s.t_s for s in rows]), np.array([float(get(s)) for s in rows])

    for name in [*roles, "total"]:

        def pick(d: dict[str, Any], name: str = name) -> float:
            return float(sum(d.values())) if name == "total" else float(d.get(name, 0))

        rss = slope_per_min(*series(after, lambda s: pick(s.rss_mib)))
        entry: dict[str, Any] = {"rss_mib_per_min": rss}
        if rss is not None and rss > RSS_SLOPE_LIMIT_MIB_PER_MIN:
            failures.append(
                f"{name}: RSS grows {rss:.2f} MiB/min after warm-up (limit {RSS_SLOPE_LIMIT_MIB_PER_MIN})"
            )
        for key, attr in (("fds", "fds"), ("threads", "threads"), ("processes", "processes")):
            entry[f"{key}_per_min"] = slope_per_min(*series(after, lambda s, a=attr: pick(getattr(s, a))))
            idle = slope_per_min(*series(between, lambda s, a=attr: pick(getattr(s, a))))
            entry[f"{key}_between_episodes_per_min"] = idle
            if idle is not None and idle * between_span_min >= COUNT_GROWTH_LIMIT:
                failures.append(
                    f"{name}: {key} grow {idle:.2f}/min between episodes after warm-up "
                    f"(+{idle * between_span_min:.1f} over {between_span_min:.1f} min)"
                )
        last = samples[-1] if samples else None
        entry["last"] = (
            None
            if last is None
            else {
                "rss_mib": round(pick(last.rss_mib), 1),
                "fds": pick(last.fds),
                "threads": pick(last.threads),
                "processes": pick(last.processes),
            }
        )
        metrics[name] = entry

    storage: dict[str, Any] = {
        "data_root_mb_per_min": None,
        "index_kb_per_min": None,
        "data_root_bytes": samples[-1].data_root_bytes if samples else 0,
        "index_bytes": samples[-1].index_bytes if samples else 0,
        "index_closed_bytes": index_closed_bytes,
    }
    d = slope_per_min(*series(after, lambda s: s.data_root_bytes / 1e6))
    i = slope_per_min(*series(after, lambda s: s.index_bytes / 1e3))
    storage["data_root_mb_per_min"], storage["index_kb_per_min"] = d, i
    if episodes:
        storage["data_root_kb_per_episode"] = storage["data_root_bytes"] / 1e3 / len(episodes)
        # While open, the index carries its write-ahead log: it grows to ~4 MB (SQLite's checkpoint
        # at 1000 pages) and is then reused, so per episode only the closed file says what a row costs.
        index = index_closed_bytes if index_closed_bytes is not None else storage["index_bytes"]
        storage["index_kb_per_episode"] = index / 1e3 / len(episodes)

    warm = [e for e in episodes if e["start_s"] >= warmup_end_s and e["latency_p99_ms"] is not None]
    latency_drift = (
        slope_per_min(np.array([e["start_s"] for e in warm]), np.array([e["latency_p99_ms"] for e in warm]))
        if warm
        else None
    )
    overheads = [e["overhead_s"] for e in warm]
    overhead = {
        "p50_s": float(np.median(overheads)) if overheads else None,
        "max_s": max(overheads, default=None),
        "drift_s_per_min": (
            slope_per_min(np.array([e["start_s"] for e in warm]), np.array(overheads)) if warm else None
        ),
    }
    failures += thin_episodes(episodes)
    for e in episodes:
        if e["status"] != "complete":
            failures.append(f"episode {e['episode_id']}: status {e['status']}")
        for key in ("stream_drops", "gaps", "stalls", "camera_dropped", "malformed", "tick_faults"):
            if e[key]:
                failures.append(f"episode {e['episode_id']}: {key} {e[key]}{_in_blackouts(e)}")
        if e["missing_streams"]:
            failures.append(f"episode {e['episode_id']}: missing streams {', '.join(e['missing_streams'])}")
    rows = [e["index_rows"] for e in episodes if e["index_rows"] is not None]
    recorded = sum(e["index_rows"] is not None for e in episodes)
    if rows and rows[-1] != recorded:
        failures.append(f"index has {rows[-1]} rows for {recorded} episodes recorded")
    if len(episodes) <= WARMUP_EPISODES or len(between) < 3:
        failures.append(
            f"too short to judge growth: {len(episodes)} episodes, {len(between)} idle samples after warm-up "
            f"(needs > {WARMUP_EPISODES} episodes and 3 samples)"
        )
    return {
        "warmup_end_s": round(warmup_end_s, 3),
        "post_warmup_min": round(span_min, 3),
        "processes": metrics,
        "storage": storage,
        "latency_p99_drift_ms_per_min": latency_drift,
        "overhead": overhead,
        "failures": failures,
    }


def plot(
    path: Path, samples: list[Sample], episodes: list[dict[str, Any]], warmup_end_s: float, title: str
) -> None:
    """RSS, descriptors and threads per role, latency per episode and storage, against minutes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([s.t_s for s in samples]) / 60.0
    roles = sorted({r for s in samples for r in s.rss_mib})
    fig, axes = plt.subplots(2, 3, figsize=(15, 7.5), constrained_layout=True)
    for ax, attr, label in (
        (axes[0, 0], "rss_mib", "RSS [MiB]"),
        (axes[0, 1], "fds", "open descriptors"),
        (axes[0, 2], "threads", "threads"),
    ):
        for r in roles:
            ax.plot(t, [getattr(s, attr).get(r, 0) for s in samples], label=r, lw=1)
        ax.set_ylabel(label)
        ax.axvline(warmup_end_s / 60.0, color="grey", ls=":", lw=1)
    axes[0, 0].legend(fontsize=7)
    ax = axes[1, 0]
    et = np.array([e["start_s"] for e in episodes]) / 60.0
    ax.plot(et, [e["latency_p50_ms"] or np.nan for e in episodes], "o-", ms=3, label="p50")
    ax.plot(et, [e["latency_p99_ms"] or np.nan for e in episodes], "o-", ms=3, label="p99")
    ax.set_ylabel("latency per episode [ms]")
    ax.legend(fontsize=7)
    ax = axes[1, 1]
    ax.bar(et, [e["gaps"] + e["stream_drops"] + e["camera_dropped"] for e in episodes], width=0.05)
    ax.set_ylabel("gaps + drops per episode")
    rate = ax.twinx()  # a thin episode (the host starved the rig) shows as a dip
    rate.plot(et, [e["message_rate_hz"] for e in episodes], "o-", ms=3, color="tab:green")
    rate.set_ylabel("messages/s recorded", color="tab:green")
    ax = axes[1, 2]
    ax.plot(t, [s.data_root_bytes / 1e6 for s in samples], label="data root [MB]")
    ax.plot(t, [s.index_bytes / 1e3 for s in samples], label="index [kB]")
    ax.legend(fontsize=7)
    for a in axes.flat:
        a.set_xlabel("minutes")
    fig.suptitle(title)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _fmt(v: float | None, digits: int = 2) -> str:
    return "-" if v is None else f"{v:+.{digits}f}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rig", choices=("demo", "fleet"), default="demo")
    parser.add_argument("--minutes", type=float, default=60.0, help="recording time in all [min]")
    parser.add_argument("--episode-s", type=float, default=15.0, help="seconds per episode")
    parser.add_argument("--sample-s", type=float, default=2.0, help="sampling period [s]")
    parser.add_argument(
        "--out", type=Path, default=None, help="JSON (default benchmarks/results/soak_<rig>.json)"
    )
    parser.add_argument("--plot", type=Path, default=None, help="PNG of the time series")
    parser.add_argument(
        "--data-root", type=Path, default=None, help="keep the episodes here (default: a temp dir)"
    )
    parser.add_argument(
        "--isolation",
        choices=("threads", "processes"),
        default=None,
        help="run the robots in the station's process or one process each (default: the rig's)",
    )
    parser.add_argument(
        "--idle-poll",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="keep idle CPUs polling while the rig runs, or let them halt (default: the rig's "
        "runtime.idle_poll)",
    )
    parser.add_argument(
        "--gates",
        choices=("idle", "pause", "off"),
        default=None,
        help="the quality gates while an episode records: under SCHED_IDLE, stopped, or not run after "
        "each commit at all (default: the rig's qa.while_recording; to tell the gates' share of a "
        "finding from the rig's)",
    )
    parser.add_argument(
        "--show-alerts",
        action="store_true",
        help="log each stream stall as it happens (default: counted per episode, in the JSON)",
    )
    args = parser.parse_args()
    if args.minutes <= 0 or args.episode_s <= 0 or args.sample_s <= 0:
        parser.error("--minutes, --episode-s and --sample-s must be > 0")
    if args.data_root is not None and args.data_root.exists() and any(args.data_root.iterdir()):
        parser.error(
            f"--data-root {args.data_root} is not empty: the soak measures a data root's growth from nothing"
        )
    if not args.show_alerts:
        logging.getLogger("telerig.record.health").setLevel(logging.ERROR)
    out = args.out or Path(f"benchmarks/results/soak_{args.rig}.json")
    console = Console(width=140)
    config = load_rig(args.rig)
    if args.isolation == "threads":
        config = config.with_isolation("threads")
    elif args.isolation == "processes":
        config = config.with_isolation("processes", config.runtime.realtime_priority)
    if args.idle_poll is not None:
        config = config.with_runtime(idle_poll=args.idle_poll)
    if args.gates == "off":
        config = config.model_copy(update={"qa": config.qa.model_copy(update={"after_commit": False})})
    elif args.gates is not None:
        config = config.model_copy(
            update={"qa": config.qa.model_copy(update={"while_recording": args.gates})}
        )
    budget_s = args.minutes * 60.0
    episodes: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="telerig-soak-") as tmp:
        root = (args.data_root or Path(tmp)).resolve()
        console.print(
            f"soak: rig {args.rig}, {args.minutes:g} min of {args.episode_s:g} s episodes → {root} "
            f"(sampling every {args.sample_s:g} s)"
        )
        sampler = Sampler(root, args.sample_s)
        started = time.monotonic()
        with (
            RtBlackoutProbe(threshold_ms=BLACKOUT_MS) as probe,
            GcPauses() as collections,
            control_process(realtime_priority=config.runtime.realtime_priority),
            RigRuntime(config, data_root=root) as runtime,
        ):
            console.print(f"rig open in {time.monotonic() - started:.1f} s")
            sampler.start()
            sampler.take(between_episodes=True)
            # Whole episodes only: the next one starts while at least half of it fits in the budget.
            while not episodes or time.monotonic() - sampler.t0 + args.episode_s / 2 < budget_s:
                t_start = time.monotonic() - sampler.t0
                wall_start_ns = time.time_ns()
                steal = StealMeter().start()
                try:
                    result = runtime.run_episode(args.episode_s)
                except TelerigError as exc:  # the episode is lost, the soak goes on (and fails)
                    record = failed_episode(f"error: {exc}", t_start, time.monotonic() - sampler.t0)
                except KeyboardInterrupt:  # Ctrl-C: report what was measured so far
                    episodes.append(failed_episode("interrupted", t_start, time.monotonic() - sampler.t0))
                    console.print("interrupted: reporting the episodes so far")
                    break
                else:
                    record = episode_record(runtime, result, t_start, time.monotonic() - sampler.t0)
                t_end = record["end_s"]
                record["wall_ns"] = [wall_start_ns, time.time_ns()]
                # CPU time the hypervisor took from this VM during the episode (host_steal.py).
                record["steal_fraction"] = steal.stop()
                episodes.append(record)
                sample = sampler.take(between_episodes=True)
                console.print(
                    f"[{t_end / 60:5.1f}/{args.minutes:g} min] episode {len(episodes)} {record['status']}: "
                    f"{record['messages']} messages, overhead {record['overhead_s']:.1f} s, "
                    f"p50 {record['latency_p50_ms'] or float('nan'):.2f} / p99 "
                    f"{record['latency_p99_ms'] or float('nan'):.2f} ms, "
                    f"gaps {record['gaps']}, stalls {record['stalls']}, steal {steal_text(steal.fraction)}, "
                    f"waiting for the gates {record['qa_waiting']}, "
                    f"drops {record['stream_drops']}+{record['camera_dropped']} frames; "
                    f"RSS {sum(sample.rss_mib.values()):.0f} MiB, fds {sum(sample.fds.values())}, "
                    f"threads {sum(sample.threads.values())}",
                    highlight=False,
                )
            sampler.stop()
            qa = drain_qa(runtime, QA_DRAIN_S)
            console.print(
                f"quality gates: {qa['waiting_at_end']} of {qa['submitted']} episodes waited for a verdict "
                f"at the end; {qa['unchecked_after_drain']} still did {qa['drain_s']:.0f} s later",
                highlight=False,
            )
        index_closed = index_bytes(root)  # the rig closed the index: its write-ahead log is folded in
    blackouts_line = note_blackouts(episodes, probe)
    collections_line = note_collections(episodes, collections)
    wall_s = sampler.samples[-1].t_s if sampler.samples else 0.0
    warmup_end_s = max(
        WARMUP_SHARE * wall_s, episodes[min(WARMUP_EPISODES, len(episodes)) - 1]["end_s"] if episodes else 0.0
    )
    report = analyse(sampler.samples, episodes, warmup_end_s, qa, index_closed)

    table = Table(
        title=f"soak of the {args.rig} rig: slopes after warm-up ({report['warmup_end_s'] / 60:.1f} min)"
    )
    for col in (
        "process",
        "procs",
        "RSS MiB",
        "RSS MiB/min",
        "fds",
        "fds/min idle",
        "threads",
        "threads/min idle",
    ):
        table.add_column(col, justify="left" if col == "process" else "right")
    for name, m in report["processes"].items():
        last = m["last"] or {}
        table.add_row(
            name,
            f"{last.get('processes', 0):g}",
            f"{last.get('rss_mib', 0):.0f}",
            _fmt(m["rss_mib_per_min"]),
            f"{last.get('fds', 0):g}",
            _fmt(m["fds_between_episodes_per_min"]),
            f"{last.get('threads', 0):g}",
            _fmt(m["threads_between_episodes_per_min"]),
        )
    console.print(table)
    p99 = [e["latency_p99_ms"] for e in episodes if e["latency_p99_ms"] is not None]
    st = report["storage"]
    oh = report["overhead"]
    console.print(
        f"{len(episodes)} episodes, {sum(e['messages'] for e in episodes)} messages, "
        f"gaps {sum(e['gaps'] for e in episodes)}, drops {sum(e['stream_drops'] for e in episodes)}, "
        f"camera frames dropped {sum(e['camera_dropped'] for e in episodes)}; latency p99 per episode "
        + (
            f"{min(p99):.2f}-{max(p99):.2f} ms, "
            f"drift {_fmt(report['latency_p99_drift_ms_per_min'], 3)} ms/min"
            if p99
            else "-"
        )
        + (
            f"; start/stop overhead p50 {oh['p50_s']:.2f} s, max {oh['max_s']:.2f} s, "
            f"drift {_fmt(oh['drift_s_per_min'], 3)} s/min"
            if oh["p50_s"] is not None
            else ""
        )
        + f"; data root {st['data_root_bytes'] / 1e6:.1f} MB ({_fmt(st['data_root_mb_per_min'])} MB/min), "
        f"index {st['index_bytes'] / 1e3:.0f} kB open ({_fmt(st['index_kb_per_min'])} kB/min), "
        f"{st['index_closed_bytes'] / 1e3:.0f} kB closed "
        f"({st.get('index_kb_per_episode', 0):.1f} kB per episode), "
        f"{max((e['index_rows'] or 0 for e in episodes), default=0)} rows",
        highlight=False,
    )
    for key, what in (("gaps_by_stream", "gaps"), ("drops_by_stream", "drops")):
        if worst := stream_totals(episodes, key)[:5]:
            console.print(f"most {what}: " + ", ".join(f"{topic} {n}" for topic, n in worst), highlight=False)
    console.print(blackouts_line, highlight=False)
    console.print(collections_line, highlight=False)
    if warning := steal_warning([e.get("steal_fraction") for e in episodes]):
        stolen = sum(1 for e in episodes if (e.get("steal_fraction") or 0.0) > 0.05)
        console.print(f"[yellow]{stolen} of {len(episodes)} episodes: {warning}[/]")
    passed = not report["failures"]
    console.print(
        f"limits: RSS <= {RSS_SLOPE_LIMIT_MIB_PER_MIN} MiB/min per role and in total; descriptors, threads, "
        f"processes: fitted growth between episodes < {COUNT_GROWTH_LIMIT:g}; "
        f"0 gaps, 0 drops, every episode complete and none thin (< {THIN_SHARE:.0%} of the median "
        f"message rate); at most {QA_MAX_WAITING} episodes waiting for the gates, none "
        f"{QA_DRAIN_S:g} s after the end"
    )
    console.print("[bold green]verdict: PASS[/]" if passed else "[bold red]verdict: FAIL[/]")
    for reason in report["failures"][:30]:
        console.print(f"  - {reason}", highlight=False)
    if len(report["failures"]) > 30:
        console.print(f"  ... and {len(report['failures']) - 30} more (in the JSON)")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps(
            {
                "benchmark": "soak",
                "rig": args.rig,
                "runtime": config.runtime.model_dump(
                    mode="json", include={"isolation", "realtime_priority", "idle_poll"}
                ),
                "gates": config.qa.while_recording if config.qa.after_commit else "off",
                "machine": {
                    "cpus": os.cpu_count(),
                    "python": platform.python_version(),
                    "load_avg": os.getloadavg(),
                    "nice": os.nice(0),
                },
                "minutes": args.minutes,
                "episode_s": args.episode_s,
                "sample_s": args.sample_s,
                "wall_s": wall_s,
                "limits": {
                    "rss_mib_per_min": RSS_SLOPE_LIMIT_MIB_PER_MIN,
                    "count_growth": COUNT_GROWTH_LIMIT,
                    "warmup_share": WARMUP_SHARE,
                    "warmup_episodes": WARMUP_EPISODES,
                    "thin_share": THIN_SHARE,
                    "qa_max_waiting": QA_MAX_WAITING,
                    "qa_drain_s": QA_DRAIN_S,
                },
                "verdict": "pass" if passed else "fail",
                "qa": qa,
                **report,
                "episodes": episodes,
                "samples": [asdict(s) for s in sampler.samples],
            },
            indent=1,
        )
    )
    console.print(f"wrote {out}")
    if args.plot is not None:
        plot(
            args.plot,
            sampler.samples,
            episodes,
            warmup_end_s,
            f"soak of the {args.rig} rig ({len(episodes)} episodes)",
        )
        console.print(f"wrote {args.plot}")
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
