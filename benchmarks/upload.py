"""Benchmark: verified upload of a 100 MB episode to a local moto S3 server and to a local directory.

Rows: a full upload; a resume after a crash half-way (only the missing parts are sent); a re-run
of a finished upload (verification only). moto is a Python server on the same machine, so the
S3 numbers bound the client's overhead (hashing, journaling, requests), not a real network.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path

from pydantic import SecretStr
from rich.console import Console
from rich.table import Table

from telerig.store.episodes import EpisodeStore
from telerig.store.remote import LocalObjectStore, ObjectStore, RemoteConfig, S3ObjectStore
from telerig.store.upload import EpisodeUploader, UploadEvent, UploadResult

_MB = 1_000_000
#: The episode: one MCAP and three camera videos, 100 MB in all [bytes].
_FILES = {
    "episode.mcap": 40 * _MB,
    "cameras/wrist.mp4": 20 * _MB,
    "cameras/top.mp4": 20 * _MB,
    "cameras/side.mp4": 20 * _MB,
}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start_moto() -> tuple[subprocess.Popen[bytes], str]:
    port = _free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    url = f"http://127.0.0.1:{port}"
    for _ in range(600):
        try:
            with urllib.request.urlopen(f"{url}/moto-api/", timeout=1.0):
                return proc, url
        except (urllib.error.URLError, ConnectionError):
            time.sleep(0.05)
    proc.kill()
    raise RuntimeError("moto_server did not start")


class _CrashError(Exception):
    pass


def _crash_after(nbytes: int) -> Callable[[UploadEvent], None]:
    sent = [0]

    def hook(event: UploadEvent) -> None:
        if event.sent:
            sent[0] += event.nbytes
            if sent[0] >= nbytes:
                raise _CrashError

    return hook


def _episode(root: Path) -> Path:
    draft = EpisodeStore(root).begin(rig="bench", task="upload", operator="bench")
    for rel, size in _FILES.items():
        path = draft.dir / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(os.urandom(size))
    draft.commit()
    return draft.dir


def _row(name: str, r: UploadResult) -> dict[str, float | str | int]:
    return {
        "case": name,
        "seconds": r.seconds,
        "mb_sent": r.bytes_sent / _MB,
        "mb_per_s_sent": r.bytes_sent / _MB / r.seconds if r.seconds > 0 else 0.0,
        "mb_per_s_episode": r.bytes_total / _MB / r.seconds,
        "parts_sent": r.parts_sent,
        "parts_skipped": r.parts_skipped,
    }


def _bench(
    name: str, make_store: Callable[[str], ObjectStore], ep: Path, journal: Path
) -> list[dict[str, float | str | int]]:
    """Full upload into ``full``; crash at 50 MB then resume into ``resume``; re-run of ``full``."""
    rows = [_row(f"{name}: full upload", EpisodeUploader(make_store("full"), journal).upload(ep))]
    crashing = EpisodeUploader(make_store("resume"), journal / "resume", progress=_crash_after(50 * _MB))
    with contextlib.suppress(_CrashError):
        crashing.upload(ep)
    resumed = EpisodeUploader(make_store("resume"), journal / "resume").upload(ep)
    rows.append(_row(f"{name}: resume after crash at 50 MB", resumed))
    rows.append(_row(f"{name}: re-run, verify only", EpisodeUploader(make_store("full"), journal).upload(ep)))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/upload.json"))
    args = parser.parse_args()
    rows: list[dict[str, float | str | int]] = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        ep = _episode(root / "data")
        proc, endpoint = _start_moto()
        try:
            import boto3

            boto3.client(
                "s3",
                endpoint_url=endpoint,
                aws_access_key_id="k",
                aws_secret_access_key="s",
                region_name="us-east-1",
            ).create_bucket(Bucket="bench")

            def s3(prefix: str) -> ObjectStore:
                config = RemoteConfig(
                    url=f"s3://bench/{prefix}",
                    endpoint_url=endpoint,
                    access_key_id="k",
                    secret_access_key=SecretStr("s"),
                    region="us-east-1",
                )
                return S3ObjectStore(config)

            rows += _bench("moto S3", s3, ep, root / "journal-s3")
        finally:
            proc.terminate()
            proc.wait()
        rows += _bench(
            "local dir", lambda p: LocalObjectStore(root / "archive" / p), ep, root / "journal-local"
        )
    table = Table(title=f"Upload of a {sum(_FILES.values()) / _MB:.0f} MB episode (8 MiB parts, verified)")
    for col in ("case", "s", "MB sent", "MB/s sent", "episode MB/s", "parts sent", "parts skipped"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(
            str(r["case"]),
            f"{r['seconds']:.2f}",
            f"{r['mb_sent']:.1f}",
            f"{r['mb_per_s_sent']:.1f}",
            f"{r['mb_per_s_episode']:.1f}",
            str(r["parts_sent"]),
            str(r["parts_skipped"]),
        )
    console = Console(width=120)
    console.print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"benchmark": "upload", "rows": rows}, indent=2))
    console.print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
