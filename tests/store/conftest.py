"""A real PostgreSQL on 127.0.0.1 for the store tests: one server per session, a fresh database per test."""

from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

_PG_VERSIONS = ("15", "16", "17", "14")
_START_TIMEOUT_S = 30


def find_postgres_bin() -> Path | None:
    """Dir with ``initdb`` and ``pg_ctl``: ``$TELERIG_PG_BIN``, ``/usr/lib/postgresql/<v>/bin``, PATH."""
    candidates = [os.environ.get("TELERIG_PG_BIN", "")]
    candidates += [f"/usr/lib/postgresql/{v}/bin" for v in _PG_VERSIONS]
    on_path = shutil.which("pg_ctl")
    candidates.append(str(Path(on_path).parent) if on_path else "")
    for candidate in filter(None, candidates):
        path = Path(candidate)
        if (path / "initdb").is_file() and (path / "pg_ctl").is_file():
            return path
    return None


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


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

            user = pwd.getpwnam("postgres")  # KeyError: no postgres user; the fixture skips
            os.chown(self._dir, user.pw_uid, user.pw_gid)
            self._as = ["runuser", "-u", "postgres", "--"] if shutil.which("runuser") else [
                "setpriv", f"--reuid={user.pw_uid}", f"--regid={user.pw_gid}", "--init-groups", "--"
            ]  # fmt: skip
        data = self._dir / "data"
        self._run(
            "initdb", "-D", str(data), "-A", "trust", "-U", "postgres", "-E", "UTF8", "--locale=C", "-N"
        )
        for attempt in range(3):  # a free port can be taken before postgres binds it
            self._port = _free_port()
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
    """A PostgreSQL server for the whole test session (fsync off: tests, not durability)."""
    bindir = find_postgres_bin()
    if bindir is None:
        pytest.skip("PostgreSQL binaries (initdb, pg_ctl) not found; apt-get install postgresql-15")
    try:
        import psycopg  # noqa: F401
    except ImportError:
        pytest.skip("psycopg 3 is not installed; pip install 'psycopg[binary]'")
    if os.geteuid() == 0:
        import pwd

        try:
            pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root and there is no 'postgres' user to run PostgreSQL as")
    server = PostgresServer(bindir, {"fsync": "off", "synchronous_commit": "off", "full_page_writes": "off"})
    with server:
        yield server


@pytest.fixture
def postgres_url(postgres_server: PostgresServer) -> str:
    """URL of an empty database on :func:`postgres_server`, fresh for each test."""
    return postgres_server.create_database()
