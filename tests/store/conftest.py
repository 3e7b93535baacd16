"""Real servers on 127.0.0.1 for the store tests: PostgreSQL (one per session, a database per test) and
an S3 peer (moto_server, one per session, a bucket per test)."""

from __future__ import annotations

import contextlib
import itertools
import os
import secrets
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from pydantic import SecretStr
from tests.ports import WERKZEUG_RUNNING, free_port, on_a_free_port, start_listening

from telerig.store.remote import RemoteConfig

_PG_VERSIONS = ("15", "16", "17", "14")
_START_TIMEOUT_S = 30


def find_postgres_bin() -> Path | None:
    """Dir with ``initdb`` and ``pg_ctl``: ``$TELERIG_PG_BIN`` when set (and only it), else
    ``/usr/lib/postgresql/<v>/bin`` or PATH."""
    chosen = os.environ.get("TELERIG_PG_BIN")
    if chosen:
        path = Path(chosen)
        return path if (path / "initdb").is_file() and (path / "pg_ctl").is_file() else None
    candidates = [f"/usr/lib/postgresql/{v}/bin" for v in _PG_VERSIONS]
    on_path = shutil.which("pg_ctl")
    candidates.append(str(Path(on_path).parent) if on_path else "")
    for candidate in filter(None, candidates):
        path = Path(candidate)
        if (path / "initdb").is_file() and (path / "pg_ctl").is_file():
            return path
    return None


class PostgresServer:
    """A throwaway PostgreSQL cluster in a temp dir, listening on ``127.0.0.1:<free port>``, trust auth.

    As root the cluster runs as the ``postgres`` user (PostgreSQL refuses to run as root).
    ``settings`` are extra ``-c name=value`` server options (tests turn fsync off).
    """

    def __init__(self, bindir: Path, settings: dict[str, str] | None = None) -> None:
        self._bin = bindir
        self._settings = dict(settings or {})
        self._dir: Path | None = None
        self._port = 0
        self._as: list[str] = []
        self._names = itertools.count()

    @property
    def port(self) -> int:
        """The TCP port on 127.0.0.1."""
        return self._port

    def url(self, database: str = "postgres") -> str:
        """``postgresql://postgres@127.0.0.1:PORT/<database>``."""
        return f"postgresql://postgres@127.0.0.1:{self._port}/{database}"

    def start(self) -> PostgresServer:
        """initdb + pg_ctl start (waits until it accepts connections). Returns ``self``."""
        self._dir = Path(tempfile.mkdtemp(prefix="telerig-pg-"))
        if os.geteuid() == 0:
            import pwd

            user = pwd.getpwnam("postgres")  # KeyError: no postgres user; the fixture fails first
            os.chown(self._dir, user.pw_uid, user.pw_gid)
            self._as = ["runuser", "-u", "postgres", "--"] if shutil.which("runuser") else [
                "setpriv", f"--reuid={user.pw_uid}", f"--regid={user.pw_gid}", "--init-groups", "--"
            ]  # fmt: skip
        data = self._dir / "data"
        self._run(
            "initdb", "-D", str(data), "-A", "trust", "-U", "postgres", "-E", "UTF8", "--locale=C", "-N"
        )
        for attempt in range(3):  # a free port can be taken before postgres binds it
            self._port = free_port()
            options = [f"-p {self._port}", f"-k {self._dir}", "-c listen_addresses=127.0.0.1"]
            options += [f"-c {k}={v}" for k, v in self._settings.items()]
            try:
                self._run(
                    "pg_ctl", "-D", str(data), "-l", str(self._dir / "server.log"), "-w",
                    "-t", str(_START_TIMEOUT_S), "-o", " ".join(options), "start",
                )  # fmt: skip
                return self
            except RuntimeError:
                if attempt == 2:
                    raise
        raise AssertionError("unreachable")  # pragma: no cover

    def create_database(self) -> str:
        """Create an empty database with a fresh name; returns its URL."""
        import psycopg

        name = f"telerig_test_{next(self._names)}"
        with psycopg.connect(
            f"host=127.0.0.1 port={self._port} user=postgres dbname=postgres", autocommit=True
        ) as c:
            c.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def stop(self) -> None:
        """Stop the server (fast shutdown) and remove its directory. Idempotent."""
        if self._dir is None:
            return
        data = self._dir / "data"
        if (data / "postmaster.pid").exists():
            with contextlib.suppress(RuntimeError):
                self._run("pg_ctl", "-D", str(data), "-m", "fast", "-w", "stop")
        shutil.rmtree(self._dir, ignore_errors=True)
        self._dir = None

    def __enter__(self) -> PostgresServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self, program: str, *args: str) -> None:
        done = subprocess.run(
            [*self._as, str(self._bin / program), *args], capture_output=True, text=True, check=False, cwd="/"
        )
        if done.returncode != 0:
            log = self._dir / "server.log" if self._dir else None
            tail = log.read_text(errors="replace")[-2000:] if log and log.exists() else ""
            raise RuntimeError(f"{program} failed ({done.returncode}): {done.stderr.strip()}\n{tail}")


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    """A PostgreSQL server for the whole test session (fsync off: tests, not durability).

    PostgreSQL is a required component of the suite: without it the tests fail with the fix
    (``make sysdeps-test`` installs it), never skip.
    """
    bindir = find_postgres_bin()
    if bindir is None:
        pytest.fail(
            "PostgreSQL server binaries (initdb, pg_ctl) not found: run `make sysdeps-test` "
            "(apt-get install postgresql) or set TELERIG_PG_BIN to their directory",
            pytrace=False,
        )
    try:
        import psycopg  # noqa: F401
    except ImportError:
        pytest.fail("psycopg 3 is not installed: pip install -e '.[dev]' (make test does it)", pytrace=False)
    if os.geteuid() == 0:
        import pwd

        try:
            pwd.getpwnam("postgres")
        except KeyError:
            pytest.fail(
                "running as root and there is no 'postgres' user to run PostgreSQL as (PostgreSQL "
                "refuses root): apt-get install postgresql creates it, or run the tests as a normal user",
                pytrace=False,
            )
    server = PostgresServer(bindir, {"fsync": "off", "synchronous_commit": "off", "full_page_writes": "off"})
    with server:
        yield server


@pytest.fixture
def postgres_url(postgres_server: PostgresServer) -> str:
    """URL of an empty database on :func:`postgres_server`, fresh for each test."""
    return postgres_server.create_database()


# --- S3 (moto_server) -------------------------------------------------------------------------------

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


def start_moto(
    timeout_s: float = 30.0, min_part_size: int = MIN_PART
) -> tuple[subprocess.Popen[bytes], MotoS3, Path]:
    """Start ``moto_server`` on a free port and wait until it listens; returns (process, server, log).

    Args:
        timeout_s: How long to wait for it to listen [s].
        min_part_size: Smallest multipart part it accepts [bytes].
    """
    env = {**os.environ, "S3_UPLOAD_PART_MIN_SIZE": str(min_part_size)}

    def start(port: int) -> tuple[subprocess.Popen[bytes], MotoS3, Path]:
        log = Path(tempfile.mkstemp(prefix="moto-", suffix=".log")[1])
        cmd = [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)]
        try:
            proc = start_listening(cmd, port, log, WERKZEUG_RUNNING, env=env, timeout_s=timeout_s)
        except BaseException:
            log.unlink(missing_ok=True)
            raise
        return proc, MotoS3(f"http://127.0.0.1:{port}"), log

    return on_a_free_port(start)


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
