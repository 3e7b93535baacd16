"""Benchmark: how late a thread starts when it wakes onto an idle CPU, with the CPUs halting or polling.

Two probes, each in processes of their own under SCHED_RR where the host allows it (as the robot
processes run), the machine otherwise idle:

* **timer**: a 100 Hz loop sleeping to absolute deadlines (a control loop's tick); lateness is
  the time from the deadline to the moment the loop runs again;
* **ping-pong**: two processes pinned to different CPUs pass a byte back and forth over pipes,
  with 5 ms of sleep between rounds so the CPUs go idle; the round trip is two cross-CPU
  wake-ups (a message arriving from the broker, a physics step waking the control thread).

Arms, same run, interleaved in blocks of ``--block`` seconds: the CPUs allowed to halt (as they
do by default) and kept polling (``runtime.idle_poll``: :class:`telerig.runtime.idle_poll.IdlePoll`,
on a VM without a cpuidle driver one ``SCHED_IDLE`` poller per CPU). The ratio is polling's p99
over halting's, per probe.

Usage: python benchmarks/idle_wake.py [--blocks 6] [--block 5] [--out benchmarks/results/idle_wake.json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing as mp
import os
import time
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from telerig.runtime.idle_poll import IdlePoll

PERIOD_S = 0.01
PAUSE_S = 0.005


def _realtime() -> None:
    with contextlib.suppress(PermissionError):  # else at normal priority, as without root
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(10))


def _timer(seconds: float, out: Connection) -> None:
    _realtime()
    late: list[float] = []
    deadline = time.monotonic() + PERIOD_S
    end = deadline + seconds
    while deadline < end:
        time.sleep(max(0.0, deadline - time.monotonic()))
        late.append(time.monotonic() - deadline)
        deadline += PERIOD_S
    out.send(late)


def _echo(cpu: int, inbox: Connection, outbox: Connection) -> None:
    _realtime()
    os.sched_setaffinity(0, {cpu})
    while (msg := inbox.recv_bytes()) != b"stop":
        outbox.send_bytes(msg)


def _ping(cpu: int, seconds: float, inbox: Connection, outbox: Connection, out: Connection) -> None:
    _realtime()
    os.sched_setaffinity(0, {cpu})
    rtt: list[float] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        time.sleep(PAUSE_S)
        t0 = time.perf_counter()
        outbox.send_bytes(b"x")
        inbox.recv_bytes()
        rtt.append(time.perf_counter() - t0)
    outbox.send_bytes(b"stop")
    out.send(rtt)


def block(seconds: float) -> tuple[list[float], list[float]]:
    """One block of both probes at once: (timer lateness [s], ping-pong round trips [s])."""
    cpus = sorted(os.sched_getaffinity(0))
    a, b = cpus[0], cpus[-1]
    to_echo_r, to_echo_w = mp.Pipe(duplex=False)
    to_ping_r, to_ping_w = mp.Pipe(duplex=False)
    timer_r, timer_w = mp.Pipe(duplex=False)
    ping_r, ping_w = mp.Pipe(duplex=False)
    procs = [
        mp.Process(target=_timer, args=(seconds, timer_w)),
        mp.Process(target=_echo, args=(b, to_echo_r, to_ping_w)),
        mp.Process(target=_ping, args=(a, seconds, to_ping_r, to_echo_w, ping_w)),
    ]
    for p in procs:
        p.start()
    late, rtt = timer_r.recv(), ping_r.recv()
    for p in procs:
        p.join()
    return late, rtt


def stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values) * 1e3
    return {
        "n": int(a.size),
        "p50_ms": float(np.median(a)),
        "p99_ms": float(np.percentile(a, 99)),
        "max_ms": float(a.max()),
        "over_5ms": int(np.sum(a > 5.0)),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--blocks", type=int, default=6, help="blocks in all, alternating halt / poll")
    parser.add_argument("--block", type=float, default=5.0, help="seconds per block")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/idle_wake.json"))
    args = parser.parse_args()
    console = Console(width=120)
    samples: dict[str, dict[str, list[float]]] = {
        arm: {"timer": [], "ping-pong": []} for arm in ("halt", "poll")
    }
    how = ""
    for k in range(args.blocks):
        arm = "halt" if k % 2 == 0 else "poll"
        console.print(f"block {k + 1}/{args.blocks}: CPUs {arm} ({args.block:g} s) ...")
        poll = IdlePoll()
        with poll if arm == "poll" else contextlib.nullcontext():
            how = poll.how if arm == "poll" else how
            late, rtt = block(args.block)
        samples[arm]["timer"] += late
        samples[arm]["ping-pong"] += rtt
    results = {arm: {probe: stats(v) for probe, v in probes.items()} for arm, probes in samples.items()}
    table = Table(title=f"wake-up delay onto idle CPUs, {os.cpu_count()} cores (polling: {how})")
    for col in ("probe", "CPUs", "samples", "p50 ms", "p99 ms", "max ms", "> 5 ms"):
        table.add_column(col, justify="left" if col in ("probe", "CPUs") else "right")
    for probe in ("timer", "ping-pong"):
        for arm in ("halt", "poll"):
            r = results[arm][probe]
            table.add_row(
                f"{probe} ({'deadline lateness' if probe == 'timer' else 'round trip'})",
                arm,
                str(r["n"]),
                f"{r['p50_ms']:.3f}",
                f"{r['p99_ms']:.3f}",
                f"{r['max_ms']:.1f}",
                str(r["over_5ms"]),
            )
    console.print(table)
    ratios = {
        probe: results["poll"][probe]["p99_ms"] / results["halt"][probe]["p99_ms"]
        for probe in ("timer", "ping-pong")
    }
    console.print(
        "p99 polling / halting: " + ", ".join(f"{probe} {ratio:.2f}x" for probe, ratio in ratios.items())
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {"benchmark": "idle_wake", "polling": how, "results": results, "p99_ratio_poll_to_halt": ratios},
            indent=2,
        )
    )
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
