"""Dashboard freshness and page load in a real headless Chromium against a running rig (issue 14).

``telerig run`` records the demo rig (its robot, VR device and a 160x120 camera in a robot process
of their own: ``runtime.isolation: processes``) and ``telerig serve --rig`` watches it over TLS, as
a lab runs them; Playwright drives Debian's Chromium (``/usr/bin/chromium``, the issue's flags, a
fresh profile) on the dashboard and measures:

* page load, once the rig records: navigation to the load event, and to the first live data (the
  WebSocket's snapshot rendered: the feed says live and the robot card has its status), the first
  load after the login page and reloads;
* stream stop -> page red: the robot process is stopped (SIGSTOP, a hung device or driver) and the
  time until the VR stream's row turns red on the page (its ``data-light-since``), the device's
  row, and the robot's live latency (red when its control node's 2 Hz reports stop for 1.5 s, or
  earlier when a loaded host already pushed its p99 past the hold time: only timed when it was not
  red before);
* station drop-off -> page red: the station process (``telerig run``: coordinator, recorder,
  clock-sync pings) is stopped and the time until its row turns red.

Each is also timed at the server (``GET /api/rig`` polled every 20 ms with the same login): the
baseline of the same run, so the table shows what the WebSocket and the page add. Targets:
stream stop shown within 1 s, station drop-off within 2 s.

Usage: python benchmarks/dashboard.py [--repeats 5] [--out benchmarks/results/dashboard.json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path
from typing import Any

import httpx2
import numpy as np
import psutil
from rich.console import Console
from rich.table import Table

from telerig.cli.serve import wait_for_url
from telerig.config.load import shipped_rig_path
from telerig.server.accounts import AccountStore

CHROMIUM = "/usr/bin/chromium"
# The flags for this machine (Playwright adds --headless; the profile is a fresh tmp dir).
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
PASSWORD = "dashboard benchmark password"
TARGET_STREAM_S = 1.0
TARGET_STATION_S = 2.0
STEP_MS = 60_000
VR = '#streams tr[data-key*="/vr0/"]'
ROBOT = "#robots li[data-key=arm0]"
STATION = "#stations tr[data-key=station0]"
DEVICE = "#devices tr[data-key=vr0]"


class Lab:
    """A data root with an admin, ``telerig run`` recording the demo rig and ``telerig serve`` on it."""

    def __init__(self, tmp: Path, episode_s: float) -> None:
        self.tmp, self.root = tmp, tmp / "data"
        self.root.mkdir()
        rig_file = tmp / "demo-processes.yaml"
        text = shipped_rig_path("demo").read_text()
        camera = "    width: 640\n    height: 480\n    fps: 30\n"
        if camera not in text:
            raise RuntimeError("the demo rig's camera block changed: update benchmarks/dashboard.py")
        text = text.replace(camera, "    width: 160\n    height: 120\n    fps: 10\n")
        rig_file.write_text(text + "\nruntime:\n  isolation: processes\n")
        with contextlib.closing(AccountStore.open(self.root)) as accounts:
            accounts.add_user("bench", "admin", PASSWORD)
        self._logs = [(tmp / f"{n}.log").open("wb") for n in ("run", "serve")]
        telerig = [sys.executable, "-m", "telerig.cli.main"]
        self.run = subprocess.Popen(
            [*telerig, "run", str(rig_file), "--episodes", "1", "--duration", str(episode_s),
             "--data-root", str(self.root)],
            stdout=self._logs[0], stderr=subprocess.STDOUT,
        )  # fmt: skip
        self.serve = subprocess.Popen(
            [*telerig, "serve", "--rig", str(rig_file), "--data-root", str(self.root),
             "--host", "127.0.0.1", "--port", "0"],
            stdout=self._logs[1], stderr=subprocess.STDOUT,
        )  # fmt: skip
        self.url = wait_for_url(tmp / "serve.log", self.serve)

    def wait(self, page: Any, selector: str, timeout_s: float = 120.0) -> None:
        """Wait for ``selector`` on ``page``, failing at once (with its log) when ``telerig run`` ends."""
        deadline = time.monotonic() + timeout_s
        while True:
            if self.run.poll() is not None:
                raise RuntimeError(f"telerig run exited ({self.run.returncode}):\n{self.log('run')}")
            try:
                page.wait_for_selector(selector, timeout=2_000)
                return
            except Exception:
                if time.monotonic() > deadline:
                    raise

    def log(self, name: str) -> str:
        return (self.tmp / f"{name}.log").read_text(errors="replace")[-3000:]

    def robot_process(self) -> psutil.Process:
        for child in psutil.Process(self.run.pid).children(recursive=True):
            if "telerig.runtime.robot_host" in " ".join(child.cmdline()):
                return child
        raise RuntimeError(f"no robot process under telerig run:\n{self.log('run')}")

    def close(self) -> None:
        with contextlib.suppress(psutil.Error):
            for p in [psutil.Process(self.run.pid), *psutil.Process(self.run.pid).children(recursive=True)]:
                with contextlib.suppress(psutil.Error):
                    p.resume()
        for proc in (self.serve, self.run):
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in (self.serve, self.run):
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for f in self._logs:
            f.close()


class ApiWatch:
    """Polls ``GET /api/rig`` every ``period_s`` with the page's login; :meth:`until` times a condition."""

    def __init__(self, url: str, cookies: dict[str, str], period_s: float = 0.02) -> None:
        self._client = httpx2.Client(base_url=url, cookies=cookies, verify=False, timeout=5.0)
        self._period_s = period_s

    def until(
        self, condition: Callable[[dict[str, Any]], bool], after: float, timeout_s: float
    ) -> float | None:
        """Seconds from ``after`` (``time.time()``) until a snapshot meets ``condition``; None on timeout."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                snap = self._client.get("/api/rig").json()
            except (httpx2.HTTPError, ValueError):
                snap = None
            if snap is not None and condition(snap):
                return time.time() - after
            time.sleep(self._period_s)
        return None

    def close(self) -> None:
        self._client.close()


def _in_thread(fn: Callable[[], float | None]) -> Callable[[], float | None]:
    """Start ``fn`` on a thread now; the returned call waits for its result."""
    out: list[float | None] = [None]
    thread = threading.Thread(target=lambda: out.__setitem__(0, fn()), daemon=True)
    thread.start()

    def join() -> float | None:
        thread.join()
        return out[0]

    return join


#: What a stopped robot process (its device, control node and driver) turns red: (key, selector,
#: the light's dataset attribute).
_ON_ROBOT_STOP = (
    ("page_s", VR, "light"),
    ("device_page_s", DEVICE, "light"),
    ("robot_latency_page_s", ROBOT, "latencyLight"),
)


def _light(page: Any, selector: str, attr: str) -> str | None:
    value: str | None = page.evaluate(
        "([s, a]) => { const n = document.querySelector(s); return n ? n.dataset[a] || null : null; }",
        [selector, attr],
    )
    return value


def _red_since(page: Any, selector: str, attr: str, after_s: float, timeout_s: float = 15.0) -> float | None:
    """Seconds from ``after_s`` until ``selector``'s ``attr`` light turned red (page clock, ms);
    None when it did not within ``timeout_s``."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        handle = page.wait_for_function(
            """([selector, attr, after]) => {
            const node = document.querySelector(selector);
            if (!node || node.dataset[attr] !== "red") return null;
            const since = Number(node.dataset[attr + "Since"]);
            return since >= after ? since : null;
        }""",
            arg=[selector, attr, after_s * 1000],
            timeout=timeout_s * 1000,
        )
    except PlaywrightTimeout:
        return None
    return float(handle.json_value()) / 1000 - after_s


def _stream_red(snap: dict[str, Any]) -> bool:
    """Whether the VR stream is red in a snapshot (as the page colours it: its stall alert counts)."""
    stalled = {a["subject"] for a in snap["active_alerts"] if a["code"] == "stream_stalled"}
    for s in snap["streams"]:
        if "/vr0/" in s["topic"]:
            return s["topic"] in stalled or s["light"] == "red"
    return False


def _station_red(snap: dict[str, Any]) -> bool:
    return bool(snap["stations"][0]["light"] == "red")


@contextlib.contextmanager
def _suspended(process: psutil.Process) -> Iterator[float]:
    t = time.time()
    process.suspend()
    try:
        yield t
    finally:
        process.resume()


def run(repeats: int, shot: Path) -> dict[str, Any]:
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as pw:
        lab = Lab(Path(tmp), episode_s=600.0)
        context = pw.chromium.launch_persistent_context(
            str(Path(tmp) / "profile"),
            executable_path=CHROMIUM,
            headless=True,
            args=CHROMIUM_ARGS,
            ignore_https_errors=True,
            viewport={"width": 1280, "height": 900},
        )
        context.set_default_timeout(STEP_MS)
        try:
            return _measure(lab, context, repeats, shot)
        except BaseException:
            print(f"--- telerig run ---\n{lab.log('run')}\n--- telerig serve ---\n{lab.log('serve')}")
            raise
        finally:
            context.close()
            lab.close()


def _measure(lab: Lab, context: Any, repeats: int, shot: Path) -> dict[str, Any]:
    page = context.new_page()
    page.goto(f"{lab.url}/login")
    page.fill("input[name=user]", "bench")
    page.fill("input[name=password]", PASSWORD)
    page.click("button[type=submit]")
    page.wait_for_url(f"{lab.url}/")

    lab.wait(page, "#session-state[data-state=recording]")  # the rig is up: load its dashboard
    loads = []
    for i in range(repeats + 1):  # the first after the login page, then reloads
        t0 = time.monotonic()
        page.goto(f"{lab.url}/")
        lab.wait(page, "#feed[data-feed=live]")
        lab.wait(page, f"{ROBOT}:not([data-status=unknown])")  # the snapshot's rig state rendered
        live_s = time.monotonic() - t0
        nav = page.evaluate("performance.getEntriesByType('navigation')[0].toJSON()")
        loads.append(
            {
                "first": i == 0,
                "dom_content_loaded_ms": nav["domContentLoadedEventEnd"],
                "load_event_ms": nav["loadEventEnd"],
                "live_data_ms": live_s * 1000,
            }
        )

    cookies = {c["name"]: c["value"] for c in context.cookies()}
    api = ApiWatch(lab.url, cookies)
    robot, station = lab.robot_process(), psutil.Process(lab.run.pid)
    streams, stations = [], []
    try:
        for _ in range(repeats):
            lab.wait(page, f"{VR}:not([data-light=red])")
            # What is not red now (a loaded host may have made it so) can be timed turning red.
            watched = [(k, s, a) for k, s, a in _ON_ROBOT_STOP if _light(page, s, a) not in (None, "red")]
            with _suspended(robot) as t:
                at_api = _in_thread(partial(api.until, _stream_red, t, 10.0))
                shown = {k: _red_since(page, s, a, t) for k, s, a in watched}
                streams.append({"api_s": at_api(), **{k: shown.get(k) for k, _, _ in _ON_ROBOT_STOP}})
            time.sleep(2.0)  # the rig catches up
        for _ in range(repeats):
            lab.wait(page, f"{STATION}:not([data-light=red])")
            with _suspended(station) as t:
                at_api = _in_thread(partial(api.until, _station_red, t, 10.0))
                station_page = _red_since(page, STATION, "light", t)
                stations.append({"page_s": station_page, "api_s": at_api()})
            time.sleep(2.0)
        shot.parent.mkdir(parents=True, exist_ok=True)
        with contextlib.suppress(Exception):
            page.wait_for_selector(f"{VR}:not([data-light=red])", timeout=30_000)
        page.screenshot(path=str(shot), full_page=True)
    finally:
        api.close()
    return {"repeats": repeats, "page_load": loads, "stream_stop": streams, "station_drop": stations}


def _stats(values: list[float | None]) -> dict[str, float | int | None]:
    got = np.array([v for v in values if v is not None], dtype=float)
    if got.size == 0:
        return {"n": 0, "median": None, "max": None, "missed": len(values)}
    return {
        "n": int(got.size),
        "median": float(np.median(got)),
        "max": float(got.max()),
        "missed": len(values) - int(got.size),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="stops of each kind (and page reloads)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/dashboard.json"))
    args = parser.parse_args()
    if not Path(CHROMIUM).exists():
        print(f"Chromium is missing at {CHROMIUM}: run `make sysdeps-test` (apt-get install chromium)")
        return 2
    console = Console(width=140)
    load_before = os.getloadavg()[0]
    console.print(f"recording the demo rig with a dashboard on it ({args.repeats} repeats) ...")
    r = run(args.repeats, args.out.with_suffix(".png"))
    load_after = os.getloadavg()[0]
    summary = {
        "page_load_first_load_event_ms": _stats([x["load_event_ms"] for x in r["page_load"] if x["first"]]),
        "page_load_first_live_data_ms": _stats([x["live_data_ms"] for x in r["page_load"] if x["first"]]),
        "page_reload_load_event_ms": _stats([x["load_event_ms"] for x in r["page_load"] if not x["first"]]),
        "page_reload_live_data_ms": _stats([x["live_data_ms"] for x in r["page_load"] if not x["first"]]),
        "stream_stop_api_s": _stats([x["api_s"] for x in r["stream_stop"]]),
        "stream_stop_page_s": _stats([x["page_s"] for x in r["stream_stop"]]),
        "device_stop_page_s": _stats([x["device_page_s"] for x in r["stream_stop"]]),
        "robot_latency_red_page_s": _stats([x["robot_latency_page_s"] for x in r["stream_stop"]]),
        "station_drop_api_s": _stats([x["api_s"] for x in r["station_drop"]]),
        "station_drop_page_s": _stats([x["page_s"] for x in r["station_drop"]]),
    }
    table = Table(title=f"dashboard in headless Chromium, {os.cpu_count()} cores, load {load_before:.1f}")
    for col in ("what", "n", "median", "max", "target"):
        table.add_column(col, justify="left" if col == "what" else "right")
    targets = {
        "stream_stop_page_s": TARGET_STREAM_S,
        "station_drop_page_s": TARGET_STATION_S,
    }
    for name, s in summary.items():
        unit = "ms" if name.endswith("_ms") else "s"
        digits = 0 if unit == "ms" else 3
        target = targets.get(name)
        verdict = ""
        if target is not None and s["max"] is not None:
            verdict = f"<= {target:g} s " + ("met" if s["max"] <= target and not s["missed"] else "MISSED")
        table.add_row(
            name.removesuffix("_ms").removesuffix("_s").replace("_", " "),
            str(s["n"]),
            "-" if s["median"] is None else f"{s['median']:.{digits}f} {unit}",
            "-" if s["max"] is None else f"{s['max']:.{digits}f} {unit}",
            verdict,
        )
    console.print(table)
    for kind in ("stream_stop", "station_drop"):
        page_s = summary[f"{kind}_page_s"]["median"]
        api_s = summary[f"{kind}_api_s"]["median"]
        if page_s is not None and api_s:
            console.print(f"{kind.replace('_', ' ')}: page / server (GET /api/rig) = {page_s / api_s:.2f}")
    console.print(f"load average (1 min) before {load_before:.2f}, after {load_after:.2f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(
        json.dumps(
            {
                "benchmark": "dashboard",
                "machine": {
                    "cpus": os.cpu_count(),
                    "python": platform.python_version(),
                    "load_avg_1min_before": load_before,
                    "load_avg_1min_after": load_after,
                },
                "argv": sys.argv[1:],
                "targets": {"stream_stop_s": TARGET_STREAM_S, "station_drop_s": TARGET_STATION_S},
                "summary": summary,
                "results": r,
            },
            indent=2,
        )
    )
    console.print(f"wrote {args.out} (and a screenshot beside it)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
