"""Clock sync offset error and synchronized-start skew of two station processes, over N runs.

Each run: a fresh Mosquitto, a coordinator in this process, two ``python -m telerig.runtime.session station``
processes (clock offsets 0 and +250 ms), arm with a 1 s lead; the host clock is the truth.

Usage: python benchmarks/session_sync.py [--runs 20] [--out benchmarks/results/session_sync.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import queue
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus
from telerig.runtime.session import Coordinator

STATIONS = {"s1": 0.0, "s2": 250.0}


def _station(url: str, sid: str, ms: float) -> tuple[subprocess.Popen[str], queue.Queue[dict[str, Any]]]:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "telerig.runtime.session",
            "station",
            "--url",
            url,
            "--id",
            sid,
            "--fake-offset-ms",
            str(ms),
            "--timeout-s",
            "20",
            "--settle-s",
            "1.0",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    events: queue.Queue[dict[str, Any]] = queue.Queue()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            events.put(json.loads(line))

    threading.Thread(target=read, daemon=True).start()
    return proc, events


def _get(events: queue.Queue[dict[str, Any]], name: str) -> dict[str, Any]:
    e = events.get(timeout=20)
    assert e["event"] == name, e
    return e


def run(lead_s: float) -> list[dict[str, float]]:
    rows = []
    with MosquittoBroker() as broker:
        procs = {sid: _station(broker.url, sid, ms) for sid, ms in STATIONS.items()}
        try:
            with (
                MqttBus(broker.url, client_id="coordinator") as bus,
                Coordinator(bus, "demo", lead_s=lead_s) as c,
            ):
                for _, ev in procs.values():
                    _get(ev, "synced")
                status = c.arm()
                started = {sid: _get(ev, "started") for sid, (_, ev) in procs.items()}
            for sid, e in started.items():
                truth = -round(STATIONS[sid] * 1e6)
                rows.append(
                    {
                        "station": sid,
                        "offset_error_us": (e["clock"]["offset_ns"] - truth) / 1e3,
                        "uncertainty_us": e["clock"]["uncertainty_ns"] / 1e3,
                        "delay_us": e["clock"]["delay_ns"] / 1e3,
                        "start_skew_us": (e["true_start_ns"] - status.start_at_ns) / 1e3,
                        "estimated_late_us": e["late_ns"] / 1e3,
                    }
                )
        finally:
            for p, _ in procs.values():
                p.terminate()
                p.wait(10)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--lead-s", type=float, default=1.0)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    rows: list[dict[str, float]] = []
    for i in range(args.runs):
        r = run(args.lead_s)
        rows += r
        print(
            i,
            " ".join(
                f"{x['station']}: off {x['offset_error_us']:+.1f}us skew {x['start_skew_us']:+.1f}us"
                for x in r
            ),
            flush=True,
        )
    summary = {}
    for key in ("offset_error_us", "start_skew_us", "uncertainty_us", "delay_us"):
        v = np.array([r[key] for r in rows])
        a = np.abs(v)
        summary[key] = {
            "p50_abs": float(np.percentile(a, 50)),
            "p99_abs": float(np.percentile(a, 99)),
            "max_abs": float(a.max()),
            "mean": float(v.mean()),
        }
    for sid in STATIONS:
        v = np.abs([r["offset_error_us"] for r in rows if r["station"] == sid])
        summary[f"offset_error_us_{sid}"] = {
            "p50_abs": float(np.percentile(v, 50)),
            "p99_abs": float(np.percentile(v, 99)),
        }
    print(json.dumps(summary, indent=1))
    if args.out:
        args.out.write_text(
            json.dumps(
                {"host": platform.node(), "runs": args.runs, "summary": summary, "rows": rows}, indent=1
            )
        )


if __name__ == "__main__":
    main()
