"""Benchmark the episode index (upsert, list, get) on SQLite and PostgreSQL; prints a table, writes JSON."""

from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from telerig.store.episodes import EpisodeManifest, FileEntry
from telerig.store.index import EpisodeIndex

RESULTS = Path(__file__).parent / "results" / "index_db.json"
_T0 = 1_700_000_000_000_000_000
_TASKS = ("pick", "place", "pour", "wipe", "stack")


def _manifests(n: int, tag: str) -> list[EpisodeManifest]:
    return [
        EpisodeManifest(
            id=f"ep-{tag}-{i:06d}",
            rig="demo",
            task=_TASKS[i % len(_TASKS)],
            operator=f"op{i % 20}",
            status="complete" if i % 10 else "incomplete",
            start_ns=_T0 + i * 30_000_000_000,
            end_ns=_T0 + i * 30_000_000_000 + 20_000_000_000,
            duration_s=20.0,
            files=(FileEntry(path="episode.mcap", size=1_000_000 + i, sha256="0" * 64),),
            extra={"robots": ["ur5e"], "session_id": f"s{i // 50}", "rig_fingerprint": "fp"},
        )
        for i in range(n)
    ]


def _timed_ms(fn: Callable[[], object], repeat: int) -> list[float]:
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t) * 1e3)
    return out


def _pct(values: list[float], q: float) -> float:
    return sorted(values)[min(len(values) - 1, int(q * len(values)))]


def bench(url: str, n: int) -> dict[str, float]:
    """Upsert/list timings for ``n`` episodes on a fresh index at ``url``."""
    row: dict[str, float] = {}
    with EpisodeIndex.open(url) as index:
        single = _manifests(n, "a")
        lat = []
        t0 = time.perf_counter()
        for m in single:
            t = time.perf_counter()
            index.upsert_episode(m, location=f"s3://bucket/{m.id}")
            lat.append((time.perf_counter() - t) * 1e3)
        row["upsert_total_s"] = time.perf_counter() - t0
        row["upsert_p50_ms"] = statistics.median(lat)
        row["upsert_p99_ms"] = _pct(lat, 0.99)
        again = _timed_ms(lambda: index.upsert_episode(single[n // 2]), 200)
        row["upsert_unchanged_p50_ms"] = statistics.median(again)
        batch = _manifests(n, "b")
        t0 = time.perf_counter()
        index.upsert_episodes(batch)
        row["batch_upsert_s"] = time.perf_counter() - t0
        total = index.count_episodes()
        row["episodes"] = total
        row["list_recent50_ms"] = statistics.median(
            _timed_ms(lambda: index.list_episodes(order="-start", limit=50), 50)
        )
        row["list_task_op_ms"] = statistics.median(
            _timed_ms(lambda: index.list_episodes(task="pick", operator="op5"), 20)
        )
        row["list_status_since_ms"] = statistics.median(
            _timed_ms(lambda: index.list_episodes(status="incomplete", since_ns=_T0), 20)
        )
        row["list_all_ms"] = statistics.median(_timed_ms(index.list_episodes, 5))
        row["get_ms"] = statistics.median(_timed_ms(lambda: index.get(single[n // 3].id), 200))
    return row


def _postgres_server_class() -> type:
    # The throwaway server lives with the test fixtures; load it from there rather than copy it.
    path = Path(__file__).parents[1] / "tests" / "store" / "conftest.py"
    spec = importlib.util.spec_from_file_location("_telerig_store_conftest", path)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    cls: type = module.PostgresServer
    if module.find_postgres_bin() is None:
        raise SystemExit(
            "PostgreSQL binaries not found; pass --postgres URL or apt-get install postgresql-15"
        )
    return cls


def main() -> None:
    """Run on SQLite and PostgreSQL (a throwaway server with default durability, or ``--postgres URL``)."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("-n", type=int, default=10_000, help="episodes per phase")
    parser.add_argument("--postgres", help="an empty PostgreSQL database URL; default: start one")
    args = parser.parse_args()
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        rows["sqlite"] = bench(tmp, args.n)
    if args.postgres:
        rows["postgresql"] = bench(args.postgres, args.n)
    else:
        server_cls = _postgres_server_class()
        module = sys.modules["_telerig_store_conftest"]
        with server_cls(module.find_postgres_bin()) as server:
            rows["postgresql"] = bench(server.create_database(), args.n)
    keys = list(rows["sqlite"])
    print(f"{'metric':<26}" + "".join(f"{b:>14}" for b in rows))
    for k in keys:
        print(f"{k:<26}" + "".join(f"{rows[b][k]:>14.3f}" for b in rows))
    RESULTS.parent.mkdir(exist_ok=True)
    meta = {"python": platform.python_version(), "machine": platform.machine(), "n": args.n}
    RESULTS.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
