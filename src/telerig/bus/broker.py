"""The embedded Mosquitto broker, a child process on 127.0.0.1 with logins, an ACL and a size limit."""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from urllib.parse import quote

from telerig.bus.acl import OWNER, AccessPolicy, Principal, password_file_text, write_private
from telerig.errors import BusError, ConfigError, DependencyError
from telerig.ir.types import now_ns

if sys.platform != "win32":
    import pwd

__all__ = [
    "BROKER_DIR_PREFIX",
    "DEFAULT_MESSAGE_SIZE_LIMIT",
    "MosquittoBroker",
    "find_mosquitto",
    "remove_stale_broker_dirs",
]

log = logging.getLogger(__name__)

#: Prefix of an embedded broker's private directory (config, password hashes, ACL) under the temp dir.
BROKER_DIR_PREFIX = "telerig-mosquitto-"
#: A directory younger than this may belong to a broker still starting [s].
_STALE_AFTER_S = 60.0

#: Where package managers put the binary when it is not on ``PATH`` (Debian, source, Homebrew).
SEARCH_DIRS = ("/usr/sbin", "/usr/local/sbin", "/opt/homebrew/sbin")
HOST = "127.0.0.1"
_INSTALL_HINT = (
    "install Mosquitto: `sudo apt-get install mosquitto` (Debian/Ubuntu), `brew install mosquitto` "
    "(macOS) or run scripts/system-deps.sh"
)
_LOG_TAIL_LINES = 20
#: What Mosquitto (1.6 to 2.x) logs once every listener is open: "mosquitto version 2.0.11 running".
_RUNNING = " running\n"
#: What it logs when its port is taken: "Error: Address already in use".
_IN_USE = "Address already in use"
#: Largest message the embedded broker accepts [bytes]. The largest legitimate message is a camera
#: preview JPEG: at the schema's largest preview (1920x1080, qscale 8) a frame of uniform noise,
#: the worst case for JPEG, encodes to 1 088 165 bytes (measured, PyAV MJPEG); 2 MiB fits it twice.
DEFAULT_MESSAGE_SIZE_LIMIT = 2 * 1024 * 1024
#: A packet this many times the message limit disconnects its sender before the broker buffers it
#: (a memory guard). Below it an oversized message is read and dropped, and its sender stays
#: connected: paho resends an unacknowledged QoS 1 message on every reconnect, so disconnecting
#: for every oversized message would loop forever.
_PACKET_LIMIT_FACTOR = 4


def find_mosquitto(binary: str | os.PathLike[str] | None = None) -> Path:
    """Return the path of the ``mosquitto`` executable.

    Args:
        binary: An explicit path; when given, only it is checked. Otherwise ``PATH``
            is searched, then :data:`SEARCH_DIRS`.

    Raises:
        DependencyError: Not found; the message says how to install it.
    """
    if binary is not None:
        path = Path(binary)
        if path.is_file() and os.access(path, os.X_OK):
            return path
        raise DependencyError(
            f"mosquitto binary {str(path)!r} does not exist or is not executable; {_INSTALL_HINT}"
        )
    found = shutil.which("mosquitto")
    if found is not None:
        return Path(found)
    for folder in SEARCH_DIRS:
        path = Path(folder) / "mosquitto"
        if path.is_file() and os.access(path, os.X_OK):
            return path
    raise DependencyError(
        f"mosquitto not found on PATH or in {', '.join(SEARCH_DIRS)}; {_INSTALL_HINT}, "
        "or pass the URL of an existing broker"
    )


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((HOST, 0))
        port: int = sock.getsockname()[1]
        return port


class MosquittoBroker:
    """A Mosquitto child process listening on ``127.0.0.1``, with its config in a temp dir.

    Anonymous clients are refused: every client logs in as a principal of ``access`` (see
    :mod:`telerig.bus.acl`) and may publish only where the ACL lets it. The password and ACL
    files are written 0600 in a per-run directory (0700) removed by :meth:`stop`. Messages over
    ``message_size_limit`` bytes are dropped by the broker. ``registered`` logins (hashes only:
    registered devices, see :mod:`telerig.bus.registered`) are added to the password file with their
    principal's ACL.

    Nothing happens until :meth:`start`; :meth:`stop` is idempotent and also runs at
    interpreter exit. The broker runs in its own process group so a Ctrl-C in the
    terminal reaches only the parent, which then stops the broker cleanly.

    Example::

        with MosquittoBroker() as broker:
            bus = MqttBus(broker.url, client_id="demo")  # logs in as the owner
    """

    def __init__(
        self,
        port: int = 0,
        *,
        access: AccessPolicy | None = None,
        owner: str | None = None,
        username: str | None = None,
        password: str | None = None,
        message_size_limit: int = DEFAULT_MESSAGE_SIZE_LIMIT,
        certfile: str | os.PathLike[str] | None = None,
        keyfile: str | os.PathLike[str] | None = None,
        max_queued_messages: int = 1000,
        binary: str | os.PathLike[str] | None = None,
        start_timeout_s: float = 5.0,
        registered: Mapping[str, str] | None = None,
    ) -> None:
        """Configure the broker; nothing starts until :meth:`start`.

        Args:
            port: TCP port on 127.0.0.1; ``0`` picks a free one at start.
            access: Who may log in and publish where; ``None``: one principal, ``owner``, with a
                fresh password, allowed everything (or ``username``/``password`` when given).
            owner: The principal whose login :attr:`url` carries; the first of ``access`` by default.
            username: With ``password`` and no ``access``: the one principal's name and password.
            password: Password of ``username``.
            message_size_limit: Largest message payload the broker accepts; larger ones are
                dropped, and a packet over 4 times it disconnects its sender [bytes].
            certfile: PEM server certificate (chain): the listener speaks TLS only (``mqtts://``).
            keyfile: PEM private key of ``certfile``.
            max_queued_messages: Per-client queue bound inside the broker (QoS 1/2 messages
                for a slow or offline client) [messages].
            binary: Path of the ``mosquitto`` executable; ``None`` searches for it.
            start_timeout_s: How long :meth:`start` waits for the port to accept connections [s].
            registered: Extra logins as Mosquitto hashes (``$7$...``) by principal of ``access``
                (registered devices, :mod:`telerig.bus.registered`): they log in with passwords
                this process never knows, with their principal's ACL. :meth:`set_registered`
                changes them while the broker runs.
        """
        if not 0 <= port <= 65535:
            raise ConfigError(f"broker port must be in 0..65535, got {port}")
        if (username is None) != (password is None):
            raise ConfigError("broker username and password must be given together")
        if (certfile is None) != (keyfile is None):
            raise ConfigError("broker certfile and keyfile must be given together")
        if access is not None and username is not None:
            raise ConfigError("give the broker either an access policy or a username and password")
        if max_queued_messages < 1:
            raise ConfigError(f"max_queued_messages must be >= 1, got {max_queued_messages}")
        if message_size_limit < 1024:
            raise ConfigError(f"message_size_limit must be >= 1024 bytes, got {message_size_limit}")
        if access is None:
            access = AccessPolicy.open_to_owner()
            if username is not None and password is not None:
                access = AccessPolicy({username: Principal(username, ("#",), ("#",))}, {username: password})
        self.access = access
        self._owner = owner if owner is not None else next(iter(access.principals), OWNER)
        access.password(self._owner)  # names the valid ones when unknown
        self._check_registered(registered or {})
        self._registered = dict(registered or {})
        if start_timeout_s <= 0:
            raise ConfigError(f"start_timeout_s must be > 0, got {start_timeout_s}")
        self._requested_port = port
        self._port = port
        self._message_size_limit = message_size_limit
        self._tls = None if certfile is None or keyfile is None else (Path(certfile), Path(keyfile))
        self._max_queued = max_queued_messages
        self._binary = binary
        self._start_timeout_s = start_timeout_s
        self._proc: subprocess.Popen[bytes] | None = None
        #: When the broker last started accepting connections (common clock [ns]); 0 before start.
        self.listening_since_ns = 0
        self._dir: Path | None = None
        self._log_start = 0  # the log's size when the running process started [bytes]

    @property
    def port(self) -> int:
        """The TCP port; known after :meth:`start` when constructed with ``port=0``."""
        if self._port == 0:
            raise BusError("the broker has no port yet: call start() first")
        return self._port

    @property
    def url(self) -> str:
        """``mqtt://OWNER:PASSWORD@127.0.0.1:PORT``: the owner's login (keep it out of logs)."""
        return self.url_for(self._owner)

    @property
    def address(self) -> str:
        """``mqtt://127.0.0.1:PORT`` (``mqtts://`` with TLS), without a login (for logs and messages)."""
        return f"{self._scheme}://{HOST}:{self.port}"

    @property
    def _scheme(self) -> str:
        return "mqtt" if self._tls is None else "mqtts"

    @property
    def message_size_limit(self) -> int:
        """Largest message payload the broker accepts [bytes]."""
        return self._message_size_limit

    def url_for(self, principal: str) -> str:
        """``mqtt://PRINCIPAL:PASSWORD@127.0.0.1:PORT`` (``mqtts://`` with TLS).

        Raises:
            ConfigError: ``principal`` is not one of the broker's; the message lists them.
        """
        password = quote(self.access.password(principal), safe="")
        return f"{self._scheme}://{quote(principal, safe='')}:{password}@{HOST}:{self.port}"

    @property
    def pid(self) -> int | None:
        """The broker process's id while it runs."""
        return self._proc.pid if self._proc is not None and self._proc.poll() is None else None

    @property
    def running(self) -> bool:
        """Whether the broker process is alive."""
        return self._proc is not None and self._proc.poll() is None

    @property
    def log_path(self) -> Path | None:
        """The broker's log file, while started."""
        return None if self._dir is None else self._dir / "mosquitto.log"

    def start(self) -> MosquittoBroker:
        """Start the broker and wait until its port accepts connections. Returns ``self``.

        Raises:
            DependencyError: Mosquitto is not installed.
            BusError: The broker exited or did not listen within ``start_timeout_s``;
                the message ends with the tail of its log.
        """
        if self.running:
            return self
        binary = find_mosquitto(self._binary)
        self._dir = Path(tempfile.mkdtemp(prefix=BROKER_DIR_PREFIX))
        atexit.register(self.stop)
        try:
            # A port picked here can be taken before mosquitto binds it; pick again then.
            for attempt in range(3):
                if self._requested_port == 0:
                    self._port = _free_port()
                try:
                    self._spawn(binary)
                    return self
                except BusError:
                    if self._requested_port != 0 or attempt == 2 or _IN_USE not in self._log_since_spawn():
                        raise
        except BaseException:
            self.stop()
            raise
        raise AssertionError("unreachable")  # pragma: no cover

    @property
    def registered(self) -> Mapping[str, str]:
        """The registered logins the broker accepts (hash by principal)."""
        return dict(self._registered)

    def set_registered(self, registered: Mapping[str, str]) -> None:
        """Replace the registered logins; a running broker rereads its files (``SIGHUP``), which also
        disconnects a client whose login is gone.

        Raises:
            ConfigError: A principal is not one of :attr:`access`, or a hash holds ':' or a newline.
        """
        self._check_registered(registered)
        self._registered = dict(registered)
        if self._dir is None:
            return
        self._write_passwd()
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGHUP)

    def _check_registered(self, registered: Mapping[str, str]) -> None:
        for user, digest in registered.items():
            if user not in self.access.principals or user == self._owner:
                raise ConfigError(f"registered login {user!r} is not a principal of the broker's rig")
            if not digest.startswith("$7$") or any(c in digest for c in ":\n\r \t"):
                raise ConfigError(f"registered login {user!r}: not a Mosquitto $7$ hash")

    def _write_passwd(self) -> Path:
        assert self._dir is not None
        own = {u: p for u, p in self.access.passwords.items() if u not in self._registered}
        text = password_file_text(own) + "".join(f"{u}:{h}\n" for u, h in self._registered.items())
        tmp = write_private(self._dir / ".passwd.tmp", text)
        os.replace(tmp, self._dir / "passwd")
        return self._dir / "passwd"

    def restart(self) -> None:
        """Stop the broker process and start it again on the same port (clients reconnect)."""
        if self._dir is None:
            raise BusError("the broker was never started: call start() first")
        self._terminate()
        self._spawn(find_mosquitto(self._binary))

    def stop(self) -> None:
        """Terminate the broker (kill it if it does not exit in 3 s) and remove its temp dir. Idempotent."""
        self._terminate()
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None
        if self._requested_port == 0:
            self._port = 0
        atexit.unregister(self.stop)

    def __enter__(self) -> MosquittoBroker:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def _spawn(self, binary: Path) -> None:
        assert self._dir is not None
        config = self._dir / "mosquitto.conf"
        config.write_text(self._config_text())
        self._log_start = self._log_size()
        log.debug("starting %s on %s:%d", binary, HOST, self._port)
        kwargs: dict[str, object] = {}
        if sys.platform == "win32":  # pragma: no cover
            kwargs["creationflags"] = subprocess.CREATE_NEW_PROCESS_GROUP
        else:
            kwargs["start_new_session"] = True
            if sys.platform.startswith("linux"):
                kwargs["preexec_fn"] = _die_with_parent
        self._proc = subprocess.Popen(
            [str(binary), "-c", str(config)],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            **kwargs,  # type: ignore[call-overload]
        )
        self._wait_listening()

    def _config_text(self) -> str:
        assert self._dir is not None
        lines = [
            f"listener {self._port} {HOST}",
            "set_tcp_nodelay true",
            f"max_queued_messages {self._max_queued}",
            "persistence false",
            f"log_dest file {self._dir / 'mosquitto.log'}",
            "allow_anonymous false",
            f"password_file {self._write_passwd()}",
            f"acl_file {write_private(self._dir / 'acl', self.access.acl_text())}",
            f"message_size_limit {self._message_size_limit}",
            f"max_packet_size {self._message_size_limit * _PACKET_LIMIT_FACTOR}",
        ]
        if self._tls is not None:
            lines += [f"certfile {self._tls[0].resolve()}", f"keyfile {self._tls[1].resolve()}"]
        if sys.platform != "win32":
            # Run as root, mosquitto drops to user "mosquitto", which cannot write our temp dir.
            lines.append(f"user {pwd.getpwuid(os.geteuid()).pw_name}")
        return "\n".join(lines) + "\n"

    def _wait_listening(self) -> None:
        """Wait until the log says the broker runs (it has opened its listener) and the port answers.

        The port alone is not enough: when another program listens there (a port picked free and
        taken since, a system broker on 1883), it answers at once, and Mosquitto exits a moment
        later with "Address already in use".
        """
        assert self._proc is not None
        deadline = time.monotonic() + self._start_timeout_s
        while True:
            if self._proc.poll() is not None:
                code = self._proc.returncode
                self._proc = None
                if _IN_USE in self._log_since_spawn():
                    raise BusError(
                        f"port {self._port} on {HOST} is in use by another program: stop it, or give the "
                        "broker another port (the rig's broker.port; 0 picks a free one)"
                    )
                raise BusError(
                    f"mosquitto exited with code {code} while starting on {HOST}:{self._port}; "
                    f"its log ends with:\n{self._log_tail()}"
                )
            if _RUNNING in self._log_since_spawn():
                try:
                    with socket.create_connection((HOST, self._port), timeout=0.5):
                        self.listening_since_ns = now_ns()
                        return
                except OSError:
                    pass
            if time.monotonic() > deadline:
                self._terminate()
                raise BusError(
                    f"mosquitto did not listen on {HOST}:{self._port} within {self._start_timeout_s} s; "
                    f"its log ends with:\n{self._log_tail()}"
                )
            time.sleep(0.02)

    def _terminate(self) -> None:
        proc, self._proc = self._proc, None
        if proc is None or proc.poll() is not None:
            return
        self._signal(proc, signal.SIGTERM)
        try:
            proc.wait(timeout=3.0)
        except subprocess.TimeoutExpired:
            log.warning("mosquitto (pid %d) did not exit on SIGTERM; killing it", proc.pid)
            self._signal(proc, signal.SIGKILL if hasattr(signal, "SIGKILL") else signal.SIGTERM)
            proc.wait(timeout=3.0)

    @staticmethod
    def _signal(proc: subprocess.Popen[bytes], sig: signal.Signals) -> None:
        # The broker leads its own process group (start_new_session), so signal the group.
        with contextlib.suppress(ProcessLookupError, PermissionError):
            if hasattr(os, "killpg"):
                os.killpg(proc.pid, sig)
            else:  # pragma: no cover
                proc.send_signal(sig)

    def _log_size(self) -> int:
        path = self.log_path
        try:
            return 0 if path is None else path.stat().st_size
        except FileNotFoundError:
            return 0

    def _log_since_spawn(self) -> str:
        """What the running process logged (a restart appends to the same log)."""
        path = self.log_path
        if path is None:
            return ""
        try:
            with open(path, "rb") as f:
                f.seek(self._log_start)
                return f.read().decode(errors="replace")
        except FileNotFoundError:
            return ""

    def _log_tail(self) -> str:
        path = self.log_path
        if path is None or not path.exists():
            return "(no log written)"
        lines = path.read_text(errors="replace").splitlines()
        return "\n".join(lines[-_LOG_TAIL_LINES:]) or "(log is empty)"


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """Linux: SIGTERM the broker when the thread that started it dies, even by kill -9 of telerig."""
    import ctypes

    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGTERM)


def remove_stale_broker_dirs(tmp: Path | None = None, *, older_than_s: float = _STALE_AFTER_S) -> list[Path]:
    """Remove embedded-broker directories left by a station that was killed (``kill -9``): those no
    running process names on its command line (Linux; elsewhere nothing is removed). They hold the
    run's password hashes and ACL. Returns the directories removed."""
    proc = Path("/proc")
    if not proc.is_dir():
        return []
    root = Path(tempfile.gettempdir()) if tmp is None else tmp
    now = time.time()
    candidates = []
    for directory in root.glob(f"{BROKER_DIR_PREFIX}*"):
        try:
            if directory.is_dir() and now - directory.stat().st_mtime > older_than_s:
                candidates.append(directory)
        except OSError:
            continue
    if not candidates:
        return []
    in_use: set[Path] = set()
    for cmdline in proc.glob("[0-9]*/cmdline"):
        try:
            text = cmdline.read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        in_use.update(d for d in candidates if str(d) in text)
    removed = [d for d in candidates if d not in in_use]
    for directory in removed:
        shutil.rmtree(directory, ignore_errors=True)
        log.info("removed %s, left by an embedded broker that is gone", directory)
    return removed
