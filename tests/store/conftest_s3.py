"""A real S3 peer for store tests: ``moto_server`` on 127.0.0.1, and a fresh bucket per test.

Test modules import this file by path and re-export ``moto_s3`` and ``s3_config`` (pytest only
collects fixtures from conftest.py and test modules, and tests/store/conftest.py is shared).
"""

from __future__ import annotations

import os
import secrets
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from pydantic import SecretStr

from telerig.store.remote import RemoteConfig

KEY = "testing"
SECRET = "testing"  # moto accepts any credentials
REGION = "us-east-1"
#: Smallest multipart part the test server accepts [bytes] (AWS: 5 MiB); small parts keep tests fast.
MIN_PART = 64 * 1024


@dataclass(frozen=True)
class MotoS3:
    """A running moto S3 server.

    Attributes:
        endpoint_url: ``http://127.0.0.1:<port>``.
    """

    endpoint_url: str

    def client(self) -> Any:
        """A boto3 S3 client of this server (for setup and tampering in tests)."""
        import boto3

        return boto3.client(
            "s3",
            endpoint_url=self.endpoint_url,
            aws_access_key_id=KEY,
            aws_secret_access_key=SECRET,
            region_name=REGION,
        )

    def new_bucket(self) -> str:
        """Create a bucket with a fresh name and return the name."""
        name = f"telerig-{secrets.token_hex(4)}"
        self.client().create_bucket(Bucket=name)
        return name

    def config(self, bucket: str, prefix: str = "robot-data") -> RemoteConfig:
        """A :class:`RemoteConfig` for ``s3://<bucket>/<prefix>`` on this server."""
        return RemoteConfig(
            url=f"s3://{bucket}/{prefix}",
            endpoint_url=self.endpoint_url,
            access_key_id=KEY,
            secret_access_key=SecretStr(SECRET),
            region=REGION,
            min_part_size=MIN_PART,
        )


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_moto(
    timeout_s: float = 30.0, min_part_size: int = MIN_PART
) -> tuple[subprocess.Popen[bytes], MotoS3, Path]:
    """Start ``moto_server`` on a free port and wait until it answers; returns (process, server, log).

    Args:
        timeout_s: How long to wait for it to answer [s].
        min_part_size: Smallest multipart part it accepts [bytes].
    """
    port = _free_port()
    env = {**os.environ, "S3_UPLOAD_PART_MIN_SIZE": str(min_part_size)}
    log = Path(tempfile.mkstemp(prefix="moto-", suffix=".log")[1])
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
        )
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(f"{url}/moto-api/", timeout=1.0):
                break
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            if proc.poll() is not None or time.monotonic() > deadline:
                proc.kill()
                proc.wait()
                raise RuntimeError(f"moto_server did not start on {url}: {log.read_text()[-2000:]}") from None
            time.sleep(0.05)
    return proc, MotoS3(url), log


@pytest.fixture(scope="session")
def moto_s3() -> Iterator[MotoS3]:
    """A moto S3 server for the test session, stopped at the end."""
    proc, server, log = start_moto()
    try:
        yield server
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.unlink(missing_ok=True)


@pytest.fixture
def s3_config(moto_s3: MotoS3) -> RemoteConfig:
    """Config of ``s3://<fresh bucket>/robot-data`` on the moto server."""
    return moto_s3.config(moto_s3.new_bucket())
