"""The fleet rig live: six simulated robot kinds at once, each driven by its own device, per-robot rates.

Runs ``src/telerig/config/rigs/fleet.yaml`` (UR5e and Panda from scripted VR controllers, the
gripper alone from a scripted trigger, the Inspire hand from a fake glove at 30 Hz, the G1 from a
BVH clip at 60 Hz, the TIAGo from a scripted SpaceMouse; embedded Mosquitto, one recorder) through
``RigRuntime`` for one recorded episode of ``--seconds`` and reports, per robot:

* command rate: applied commands per second (``joint_command_sent`` stamps, the driver's apply
  times, from the episode's MCAP) against the robot's control rate;
* missed ticks: the control loop applies a command per input sample and, without input, one per
  control period P. An interval g between consecutive applied commands longer than 1.5 P missed
  ``max(1, round(g / P) - 1)`` ticks (the ticks that should have fallen inside it);
* recorded part: where the recorded commands end against the episode, and the recorder's lag
  (received - applied). The station records what it has received when the episode closes; a
  recorder short of CPU falls seconds behind and the episode's tail is not in it (the sync gate
  fails such an episode). Missed ticks count the recorded part only, so the target is met only
  when the recording reaches the episode's end;
* state skips / gaps: the robot's recorded ``joint_state`` stamps (when the state read was true). A
  skip is an interval over 1.5 control periods (a tick found no new state, or missed); a gap one
  over 2 periods, the health monitor's rule and what the soak counts. Where the physics wakes next
  to the control loop's reads, read jitter makes skips (``physics_wake_hz`` in the rig file);
* skipped inputs: device samples superseded in the node's inbox before the loop got to them;
* input-to-actuation latency p50 / p99 (device capture → driver apply, ``ControlNode.latency``);
* retargeting residual flags (IK / hand-vector error over the retargeter's threshold), per
  retargeted command;
* real-time blackouts: moments a SCHED_FIFO probe above every thread of the rig woke late
  (``rt_blackout.py``: the kernel gave a CPU to ordinary tasks and stopped every real-time thread
  there), and how many of the missed ticks fell in one: the host's, not the rig's;
* CPU: the process (CPU time / wall, in cores), per thread role in the station and in every
  robot process (``robot host: control loop``, ``robot host: physics``, ``robot host: MQTT client
  loop``, ``station: recorder``, ``broker``, ...: the threads' OS names, as ``sched_trace.py``
  groups them), the machine's load average and its busy share from other processes (the host is
  shared).

With ``--browsers N`` the control center watches the rig while it runs: ``telerig serve --rig
fleet`` (its own process, TLS) with N headless Chromium pages on its dashboard (live WebSocket
feed, camera previews), and the report adds the server's and the browsers' CPU; run it with 0 and
with 3 to see what the dashboard costs the robots (missed ticks).

The station (this process: recorder, coordinator, the fleet's safety supervisor) runs at the robots'
``runtime.realtime_priority``, as ``telerig run`` runs it (``control_process``); below them it got
0.15 cores and recorded a quarter of each episode.

The rig keeps the idle CPUs polling (``runtime.idle_poll``: on this VM one ``SCHED_IDLE`` poller per
CPU); ``--no-idle-poll`` lets them halt, the A/B of what waking a halted CPU costs the ticks. The
pollers' CPU is reported apart from the rig's.

``--control-realtime P`` puts the control threads under SCHED_RR (``runtime.priorities``),
``--realtime-priority P`` each robot's whole process, physics included (``runtime.realtime_priority``):
the A/B of what real-time scheduling does for the missed ticks (both need root or CAP_SYS_NICE).

Usage: python benchmarks/fleet.py [--seconds 20] [--switch-interval-ms 1] [--browsers 3]
       [--control-realtime 10 | --realtime-priority 10] [--no-idle-poll]
       [--out benchmarks/results/fleet.json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import psutil
from rich.console import Console
from rich.table import Table

from telerig import priority
from telerig.cli.bus_options import operator_login
from telerig.cli.serve import wait_for_url
from telerig.config import load_rig
from telerig.ir.mcap_log import read_log
from telerig.ir.types import JointCommand
from telerig.qa.timing import END_SLACK_S
from telerig.record.health import GAP_FACTOR
from telerig.runtime import streams
from telerig.runtime.metrics import LatencyTracker
from telerig.runtime.process_settings import control_process
from telerig.runtime.rig import RigRuntime
from telerig.runtime.robot_host import LatencyNs, Stats

sys.path.insert(0, str(Path(__file__).parent))
from host_steal import StealMeter, steal_text, steal_warning
from rt_blackout import RtBlackoutProbe, blackout_text, rt_throttle_text
from sched_trace import process_kind, role
from telerig.thread_names import os_name

TARGET_MISSED_TICKS = 0


@dataclass
class ThreadCpu:
    """Per-thread CPU time [s] over a window, sampled so threads that end inside it are counted."""

    start: dict[int, float]
    latest: dict[int, float]
    names: dict[int, str]
    #: The child processes' threads: (pid, tid) → CPU time [s] at the start and latest, and the
    #: thread's role by its OS name (``robot host: control loop``, ...; telerig.thread_names).
    child_start: dict[tuple[int, int], float] = field(default_factory=dict)
    child_latest: dict[tuple[int, int], float] = field(default_factory=dict)
    child_roles: dict[tuple[int, int], str] = field(default_factory=dict)


class CpuSampler:
    """Samples this process's per-thread CPU times every ``period_s`` on a thread of its own."""

    def __init__(self, period_s: float = 0.25, *, pollers: tuple[int, ...] = ()) -> None:
        self._proc = psutil.Process()
        self._pollers = set(pollers)  # the idle pollers: counted apart from the rig's processes
        self._period_s = period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-cpu-sampler", daemon=True)
        self.cpu = ThreadCpu({}, {}, {})
        self.system: list[float] = []
        self._kinds: dict[int, str] = {}

    def _sample(self) -> None:
        names = {t.native_id: t.name for t in threading.enumerate() if t.native_id is not None}
        for t in self._proc.threads():
            self.cpu.latest[t.id] = t.user_time + t.system_time
            if t.id in names:
                self.cpu.names[t.id] = names[t.id]
        for child in self._proc.children(recursive=True):
            if child.pid in self._pollers:
                continue
            try:
                kind = self._kinds.get(child.pid) or self._kinds.setdefault(
                    child.pid, process_kind(" ".join(child.cmdline()))
                )
                threads = child.threads()
            except psutil.Error:
                continue
            for t in threads:
                key = (child.pid, t.id)
                self.cpu.child_latest[key] = t.user_time + t.system_time
                try:  # the name it has now: a robot host names its threads once they are up
                    comm = Path(f"/proc/{child.pid}/task/{t.id}/comm").read_text().strip()
                except OSError:
                    continue
                self.cpu.child_roles[key] = role(kind, comm)

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            self._sample()
            self.system.append(psutil.cpu_percent(interval=None))

    def __enter__(self) -> CpuSampler:
        psutil.cpu_percent(interval=None)
        self._t0 = time.monotonic()
        self._c0 = self._proc.cpu_times()
        self._sample()
        self.cpu.start = dict(self.cpu.latest)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()
        c1 = self._proc.cpu_times()
        self.wall_s = time.monotonic() - self._t0
        self.process_cores = (c1.user + c1.system - self._c0.user - self._c0.system) / self.wall_s
        used = {
            pid: (c.user + c.system - self._children0.get(pid, 0.0)) / self.wall_s
            for pid, c in self._children().items()
        }
        self.children_cores = {pid: c for pid, c in used.items() if pid not in self._pollers}
        self.poller_cores = sum(c for pid, c in used.items() if pid in self._pollers)

    def _children(self) -> dict[int, Any]:
        """CPU times of the child processes (robot hosts, the broker) by pid."""
        out = {}
        for child in self._proc.children(recursive=True):
            try:
                out[child.pid] = child.cpu_times()
            except psutil.NoSuchProcess:
                continue
        return out

    def mark_children(self) -> None:
        """Start counting the child processes' CPU from now (call once they exist)."""
        self._children0 = {pid: c.user + c.system for pid, c in self._children().items()}
        self._sample()
        self.cpu.child_start = dict(self.cpu.child_latest)

    def groups(self) -> dict[str, float]:
        """CPU use [cores] by thread role, as ``sched_trace.py`` names them: ``station: recorder``,
        ``robot host: control loop``, ``broker``, ... (this process's threads by their Python
        names, the child processes' by their OS names: telerig.thread_names)."""
        out: dict[str, float] = {}
        for tid, latest in self.cpu.latest.items():
            used = (latest - self.cpu.start.get(tid, 0.0)) / self.wall_s
            name = self.cpu.names.get(tid)
            group = "station: native threads" if name is None else role("station", os_name(name))
            out[group] = out.get(group, 0.0) + used
        for key, latest in self.cpu.child_latest.items():
            group = self.cpu.child_roles.get(key, "child processes: ended threads")
            used = (latest - self.cpu.child_start.get(key, 0.0)) / self.wall_s
            out[group] = out.get(group, 0.0) + used
        return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def _late(stamps_ns: np.ndarray, period_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The gaps between apply times [ns] longer than 1.5 control periods ``period_s`` [s]: where each
    starts [ns], how long it is [ns], and the ticks it missed (``max(1, round(gap / P) - 1)``)."""
    stamps = np.sort(stamps_ns)
    gaps = np.diff(stamps)
    late = np.flatnonzero(gaps > 1.5 * period_s * 1e9)
    missed = np.maximum(1, np.rint(gaps[late] / 1e9 / period_s).astype(int) - 1)
    return stamps[late], gaps[late], missed


def missed_ticks(stamps_ns: np.ndarray, period_s: float) -> tuple[int, float]:
    """Missed ticks in apply times [ns] at control period ``period_s`` [s], and the longest gap [ms]."""
    if stamps_ns.size < 2:
        return 0, float("nan")
    _, _, missed = _late(stamps_ns, period_s)
    return int(missed.sum()), float(np.diff(np.sort(stamps_ns)).max() / 1e6)


def missed_in(stamps_ns: np.ndarray, period_s: float, probe: RtBlackoutProbe) -> int:
    """Of the ticks missed in ``stamps_ns`` (see :func:`missed_ticks`), those in a gap that overlaps
    one of the probe's real-time blackouts: the kernel's, not the rig's."""
    starts, gaps, missed = _late(stamps_ns, period_s)
    return sum(
        int(n) for t, g, n in zip(starts, gaps, missed, strict=True) if probe.overlapping(int(t), int(t + g))
    )


def late_gaps(stamps_ns: np.ndarray, period_s: float, start_ns: int, most: int = 10) -> list[list[float]]:
    """The ``most`` longest gaps over 1.5 control periods: ``[when [s into the episode], gap [ms]]``,
    by time (where in the episode ticks go missing: start, stop, or all along)."""
    starts, gaps, _ = _late(stamps_ns, period_s)
    longest = sorted(np.argsort(gaps)[::-1][:most])
    return [[round((int(starts[i]) - start_ns) / 1e9, 3), round(int(gaps[i]) / 1e6, 1)] for i in longest]


def state_skips(stamps_ns: np.ndarray, period_s: float) -> tuple[int, int]:
    """Skips and gaps in a robot's recorded state times [ns] at control period ``period_s`` [s]: the
    intervals over 1.5 periods (:func:`_late`, the missed ticks' rule: a tick found no new state, or
    none came), and of those the ones over :data:`~telerig.record.health.GAP_FACTOR` periods (what
    the health monitor and the soak count)."""
    _, skips, _ = _late(stamps_ns, period_s)
    return int(skips.size), int((skips > GAP_FACTOR * period_s * 1e9).sum())


def _robot_stats(runtime: RigRuntime, rid: str) -> dict[str, Any]:
    """A robot's control counters, latency and physics timing, in this process or its robot host."""
    if rid in runtime.hosts:
        host = runtime.hosts[rid]
        st: dict[str, Any] = asdict(host.call(Stats()))
        latency = LatencyTracker()
        for value in host.call(LatencyNs()):
            latency.add(int(value))
        st["latency"] = latency.summary()
        return st
    node = runtime.controls[rid]
    physics = runtime.robots[rid]
    stats = physics.stats() if hasattr(physics, "stats") else None
    return {
        "inputs_skipped": node.stats.inputs_skipped,
        "applied": node.stats.applied,
        "ik_flagged": node.stats.ik_flagged,
        "safety_events": dict(node.stats.safety_events),
        "physics_realtime_factor": None if stats is None else stats.realtime_factor,
        "physics_overruns": None if stats is None else stats.overruns,
        "latency": node.latency.summary(),
    }


#: Opens N dashboards (one browser context each: its own login, cookie and WebSocket) and keeps them
#: open until stdin closes. argv: URL USER PASSWORD N.
_DASHBOARDS = """
import sys
from playwright.sync_api import sync_playwright
url, user, password, n = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
args = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run"]
with sync_playwright() as pw:
    browser = pw.chromium.launch(executable_path="/usr/bin/chromium", headless=True, args=args)
    for _ in range(n):
        page = browser.new_context(ignore_https_errors=True).new_page()
        page.goto(url + "/login")
        page.fill("input[name=user]", user)
        page.fill("input[name=password]", password)
        page.click("button[type=submit]")
        page.wait_for_selector("#feed[data-feed=live]", timeout=60_000)
        # the rig's own live data: a robot's status (the stream health comes once recording starts)
        page.wait_for_selector("#robots li:not([data-status=unknown])", timeout=60_000)
    print("ready", flush=True)
    sys.stdin.read()
    browser.close()
"""


class ControlCenter:
    """``telerig serve --rig fleet`` on the rig's data root with ``browsers`` headless Chromium pages
    on its dashboard (nothing when 0); :meth:`cores` is their CPU since :meth:`mark` [cores]."""

    PASSWORD = "fleet benchmark password"

    def __init__(self, root: Path, browsers: int) -> None:
        self.root, self.browsers = root, browsers
        self._stack = contextlib.ExitStack()
        self._procs: list[psutil.Process] = []
        self._mark: tuple[float, float] = (0.0, 0.0)

    def __enter__(self) -> ControlCenter:
        if self.browsers <= 0:
            return self
        from telerig.server.accounts import AccountStore

        with contextlib.closing(AccountStore.open(self.root)) as accounts:
            accounts.add_user("bench", "admin", self.PASSWORD)
        log = self._stack.enter_context((self.root / "serve.log").open("wb"))
        serve = subprocess.Popen(
            [sys.executable, "-m", "telerig.cli.main", "serve", "--rig", "fleet", "--data-root",
             str(self.root), "--port", "0"],
            stdout=log, stderr=subprocess.STDOUT,
        )  # fmt: skip
        self._stack.callback(serve.wait, 30)
        self._stack.callback(serve.terminate)
        url = wait_for_url(self.root / "serve.log", serve)
        # The browsers are driven from a process of their own, as they would be on other machines.
        pages = subprocess.Popen(
            [sys.executable, "-c", _DASHBOARDS, url, "bench", self.PASSWORD,
             str(self.browsers)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )  # fmt: skip
        self._stack.callback(pages.wait, 30)
        self._stack.callback(pages.stdin.close)  # type: ignore[union-attr]
        if (pages.stdout.readline() if pages.stdout else "").strip() != "ready":
            raise RuntimeError("the dashboards did not open")
        self._procs = [psutil.Process(serve.pid)] + [
            c for c in psutil.Process(pages.pid).children(recursive=True) if "chrom" in c.name()
        ]
        return self

    def __exit__(self, *exc: object) -> None:
        self._stack.close()

    def _cpu(self) -> tuple[float, float]:
        """CPU seconds of the server and of every Chromium process (browser, renderers, GPU, ...)."""
        used = [0.0]  # no server without browsers
        for i, p in enumerate(self._procs):
            try:
                t = p.cpu_times()
            except psutil.Error:  # a renderer that ended: its time is lost (small)
                continue
            if i == 0:
                used[0] = t.user + t.system
            else:
                used.append(t.user + t.system)
        return used[0], sum(used[1:])

    def mark(self) -> None:
        self._mark = self._cpu()
        self._t0 = time.monotonic()

    def cores(self) -> dict[str, float]:
        if not self._procs:
            return {"server_cores": 0.0, "browsers_cores": 0.0}
        server, browsers = self._cpu()
        wall = time.monotonic() - self._t0
        return {
            "server_cores": (server - self._mark[0]) / wall,
            "browsers_cores": (browsers - self._mark[1]) / wall,
        }


def run(
    seconds: float,
    switch_interval_s: float | None,
    isolation: Literal["threads", "processes"] | None = None,
    browsers: int = 0,
    control_realtime: int | None = None,
    realtime_priority: int | None = None,
    idle_poll: bool | None = None,
) -> dict[str, Any]:
    """One recorded episode of the fleet rig; per-robot and process statistics (and the control
    center's with ``browsers`` dashboards open on it)."""
    config = load_rig("fleet")
    if isolation is not None or realtime_priority is not None:
        isolation = isolation or config.runtime.isolation
        if realtime_priority is None and isolation == "processes":
            realtime_priority = config.runtime.realtime_priority
        # Validated: one process takes no robot priority (before, it kept the rig's 10 unchecked).
        config = config.with_isolation(isolation, realtime_priority)
    if control_realtime is not None:
        config = config.with_runtime(priorities={"control_realtime": control_realtime})
    if idle_poll is not None:
        config = config.with_runtime(idle_poll=idle_poll)
    rates = {r.id: r.control_rate() for r in config.robots}
    with (
        tempfile.TemporaryDirectory() as tmp,
        # As `telerig run` does: the station at its robots' SCHED_RR priority (below them a full
        # machine starves the recorder, see control_process).
        control_process(switch_interval_s, realtime_priority=config.runtime.realtime_priority),
        RigRuntime(config, data_root=Path(tmp)) as runtime,
        operator_login(runtime.broker.embedded, runtime.store.root, config),
        ControlCenter(Path(tmp), browsers) as web,
    ):
        load_before = os.getloadavg()
        idle_how = runtime.idle_poll.how
        with (
            CpuSampler(pollers=runtime.idle_poll.pollers) as cpu,
            StealMeter() as steal,
            RtBlackoutProbe() as probe,
        ):
            cpu.mark_children()
            web.mark()
            result = runtime.run_episode(seconds)
            web_cores = web.cores()
        load_after = os.getloadavg()
        ids = [*runtime.controls, *runtime.hosts]
        sent: dict[str, list[int]] = {rid: [] for rid in ids}
        state: dict[str, list[int]] = {rid: [] for rid in ids}
        lag: dict[str, list[int]] = {rid: [] for rid in ids}
        # Where the episode lies now: the gates may have moved it to failures/ (one rename).
        manifest = runtime.store.get(result.episode_id)
        start_ns, end_ns = manifest.start_ns, manifest.end_ns or manifest.start_ns
        for entry in read_log(runtime.store.episode_dir(result.episode_id) / "episode.mcap"):
            robot, _, stream = entry.topic.split("/", 3)[-1].partition("/")
            if stream == streams.JOINT_SENT and robot in sent and isinstance(entry.sample, JointCommand):
                sent[robot].append(entry.sample.stamp.capture_ns)
                lag[robot].append(entry.log_time_ns - entry.publish_time_ns)  # received - applied
            elif stream == streams.JOINT_STATE and robot in state:
                state[robot].append(entry.sample.stamp.capture_ns)
        robots = []
        for rid in ids:
            stamps = np.array(sent[rid], dtype=np.int64)
            period = 1.0 / rates[rid]
            missed, max_gap_ms = missed_ticks(stamps, period)
            span = (stamps.max() - stamps.min()) / 1e9 if stamps.size > 1 else 0.0
            lags_ms = np.array(lag[rid], dtype=np.float64) / 1e6
            skips, state_gaps = state_skips(np.array(state[rid], dtype=np.int64), period)
            st = _robot_stats(runtime, rid)
            robots.append(
                {
                    "robot": rid,
                    "type": next(r.type for r in config.robots if r.id == rid),
                    "expected_hz": rates[rid],
                    "command_hz": (stamps.size - 1) / span if span > 0 else 0.0,
                    "commands": int(stamps.size),
                    # Where the recorded commands end, against the episode: the station records what
                    # it has received when the episode closes; a recorder that fell behind its
                    # streams leaves their tail out, and missed ticks count the recorded part only.
                    "episode_s": (end_ns - start_ns) / 1e9,
                    "recorded_until_s": (int(stamps.max()) - start_ns) / 1e9 if stamps.size else 0.0,
                    "recorder_lag_p50_ms": float(np.median(lags_ms)) if lags_ms.size else float("nan"),
                    "recorder_lag_max_ms": float(lags_ms.max()) if lags_ms.size else float("nan"),
                    "missed_ticks": missed,
                    "missed_in_rt_blackouts": missed_in(stamps, period, probe),
                    "max_interval_ms": max_gap_ms,
                    "late_gaps": late_gaps(stamps, period, start_ns),
                    "states": len(state[rid]),
                    "state_skips": skips,
                    "state_gaps": state_gaps,
                    "inputs_skipped": st["inputs_skipped"],
                    "retargeted": st["applied"],
                    "residual_flagged": st["ik_flagged"],
                    "latency_p50_ms": st["latency"].p50_ms,
                    "latency_p99_ms": st["latency"].p99_ms,
                    "physics_realtime_factor": st["physics_realtime_factor"],
                    "physics_overruns": st["physics_overruns"],
                    "safety_events": st["safety_events"],
                }
            )
    busy = float(np.mean(cpu.system)) if cpu.system else float("nan")  # all cores [%]
    cores = os.cpu_count() or 1
    return {
        "seconds": seconds,
        # The episode's start and end, wall clock [ns]: to line a run up with a system trace.
        "episode_ns": [start_ns, end_ns],
        "switch_interval_ms": None if switch_interval_s is None else switch_interval_s * 1e3,
        "robots": robots,
        "isolation": config.runtime.isolation,
        # What the station process's threads of each role got (robot processes are not read here).
        "control_realtime": control_realtime,
        "realtime_priority": config.runtime.realtime_priority,
        "priorities": priority.applied(),
        "idle_poll": idle_how,
        "web": {"browsers": browsers, **web_cores},
        "process_cores": cpu.process_cores,
        "children_cores": sum(cpu.children_cores.values()),
        "threads_cores": cpu.groups(),
        "machine": {
            "cpus": cores,
            "load_avg_1min_before": load_before[0],
            "load_avg_1min_after": load_after[0],
            "busy_cores": busy / 100 * cores,
            # CPU time the hypervisor took from this VM during the episode (host_steal.py).
            "steal_fraction": steal.fraction,
            # The kernel's real-time share and the moments it stopped every real-time thread at once
            # ([s into the episode, ms]; rt_blackout.py): None where the probes did not watch to the end.
            "rt_throttle": rt_throttle_text(),
            "rt_blackouts": None
            if probe.not_measured
            else [
                [round((b.start_ns - start_ns) / 1e9, 3), round(b.ms, 1)]
                for b in probe.overlapping(start_ns, end_ns)
            ],
            "rt_blackouts_text": blackout_text(probe, start_ns, end_ns),
            # The idle pollers take the time nothing else wants (SCHED_IDLE): apart from the rest.
            "idle_poller_cores": cpu.poller_cores,
            "busy_cores_other_processes": max(
                0.0,
                busy / 100 * cores - cpu.process_cores - sum(cpu.children_cores.values()) - cpu.poller_cores,
            ),
        },
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="episode length [s]")
    parser.add_argument(
        "--switch-interval-ms",
        type=float,
        default=1.0,
        help="GIL switch interval while the rig runs; 0 = Python's default",
    )
    parser.add_argument(
        "--isolation",
        choices=("threads", "processes"),
        default=None,
        help="run the robots in the station's process or one process each (default: the rig's)",
    )
    parser.add_argument(
        "--browsers",
        type=int,
        default=0,
        help="headless Chromium dashboards of telerig serve watching the rig while it runs (default 0)",
    )
    parser.add_argument(
        "--control-realtime",
        type=int,
        default=None,
        metavar="PRIORITY",
        help="run the control threads under SCHED_RR at this priority (1..99; the rig's "
        "runtime.priorities.control_realtime; needs root or CAP_SYS_NICE)",
    )
    parser.add_argument(
        "--realtime-priority",
        type=int,
        default=None,
        metavar="PRIORITY",
        help="run each robot's whole process under SCHED_RR at this priority (1..99; the rig's "
        "runtime.realtime_priority, physics included; needs root or CAP_SYS_NICE)",
    )
    parser.add_argument(
        "--idle-poll",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="keep idle CPUs polling while the rig runs, or let them halt (default: the rig's "
        "runtime.idle_poll, on)",
    )
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/fleet.json"))
    args = parser.parse_args()
    for flag in ("control_realtime", "realtime_priority"):
        value = getattr(args, flag)
        if value is not None and not 1 <= value <= 99:
            parser.error(f"--{flag.replace('_', '-')} must be 1..99, got {value}")
    console = Console(width=140)
    switch = args.switch_interval_ms / 1e3 if args.switch_interval_ms > 0 else None
    console.print(f"running the fleet rig for {args.seconds:g} s ...")
    r = run(
        args.seconds,
        switch,
        args.isolation,
        args.browsers,
        args.control_realtime,
        args.realtime_priority,
        args.idle_poll,
    )
    table = Table(
        title=f"fleet rig: six sim robots at once, {os.cpu_count()} cores, {args.seconds:g} s, "
        f"isolation: {r['isolation']}"
    )
    columns = (
        "robot",
        "type",
        "cmd Hz / expected",
        "missed ticks",
        "max gap ms",
        "state skips / gaps",
        "recorded s / episode",
        "recorder lag p50 / max s",
        "inputs skipped",
        "latency p50 ms",
        "p99 ms",
        "flagged / retargeted",
        "physics RT factor",
    )
    for col in columns:
        table.add_column(col, justify="left" if col in ("robot", "type") else "right")
    for row in r["robots"]:
        rtf = row["physics_realtime_factor"]
        ratio = row["command_hz"] / row["expected_hz"]
        table.add_row(
            row["robot"],
            row["type"],
            f"{row['command_hz']:.1f} / {row['expected_hz']:g} ({ratio:.0%})",
            str(row["missed_ticks"]),
            f"{row['max_interval_ms']:.1f}",
            f"{row['state_skips']} / {row['state_gaps']}",
            f"{row['recorded_until_s']:.1f} / {row['episode_s']:.1f}",
            f"{row['recorder_lag_p50_ms'] / 1e3:.2f} / {row['recorder_lag_max_ms'] / 1e3:.2f}",
            str(row["inputs_skipped"]),
            f"{row['latency_p50_ms']:.2f}",
            f"{row['latency_p99_ms']:.2f}",
            f"{row['residual_flagged']} / {row['retargeted']}",
            "-" if rtf is None else f"{rtf:.3f}",
        )
    console.print(table)
    cpu = Table(title="CPU use [cores]")
    cpu.add_column("thread group")
    cpu.add_column("cores", justify="right")
    for group, used in r["threads_cores"].items():
        if used >= 0.005:
            cpu.add_row(group, f"{used:.3f}")
    cpu.add_row("[b]station process[/b]", f"[b]{r['process_cores']:.2f}[/b]")
    cpu.add_row("[b]child processes (robot hosts, broker)[/b]", f"[b]{r['children_cores']:.2f}[/b]")
    if r["web"]["browsers"]:
        cpu.add_row("telerig serve (control center)", f"{r['web']['server_cores']:.3f}")
        cpu.add_row(f"{r['web']['browsers']} Chromium dashboards", f"{r['web']['browsers_cores']:.3f}")
    m = r["machine"]
    cpu.add_row("machine busy (all processes)", f"{m['busy_cores']:.2f} of {m['cpus']}")
    cpu.add_row("other processes", f"{m['busy_cores_other_processes']:.2f}")
    cpu.add_row(f"idle CPUs: {r['idle_poll']}", f"{m['idle_poller_cores']:.2f}")
    console.print(cpu)
    console.print(
        f"load average (1 min) before {m['load_avg_1min_before']:.2f}, after {m['load_avg_1min_after']:.2f}; "
        f"steal {steal_text(m['steal_fraction'])}"
    )
    if warning := steal_warning([m["steal_fraction"]]):
        console.print(f"[yellow]{warning}[/]")
    console.print(m["rt_blackouts_text"])
    missed = sum(row["missed_ticks"] for row in r["robots"])
    kernel = sum(row["missed_in_rt_blackouts"] for row in r["robots"])
    if kernel:
        console.print(f"{kernel} of the {missed} missed ticks fell in a real-time blackout")
    short_s = max(row["episode_s"] - row["recorded_until_s"] for row in r["robots"])
    complete = short_s <= END_SLACK_S
    r["recording_complete"] = complete
    verdict = "met" if missed <= TARGET_MISSED_TICKS and complete else "MISSED"
    console.print(f"target: zero missed ticks at the control rates: {verdict} ({missed} missed in all)")
    if not complete:
        lag_s = max(row["recorder_lag_max_ms"] for row in r["robots"]) / 1e3
        console.print(
            f"[yellow]the recording ends up to {short_s:.1f} s before the episode: the station received "
            f"the robots' commands up to {lag_s:.1f} s late and closed the episode before their tail "
            "arrived; the missed ticks count the recorded part only[/]"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {
                "benchmark": "fleet",
                "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
                "argv": sys.argv[1:],
                "targets": {"missed_ticks": TARGET_MISSED_TICKS},
                "results": r,
            },
            indent=2,
        )
    )
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
