"""Shared fixtures: a real Mosquitto on 127.0.0.1 and connected MQTT clients; every test runs in its
own temp dir and may not touch the user's data root."""

from __future__ import annotations

import atexit
import datetime
import ipaddress
import os
import re
import shutil
import tempfile

# Headless offscreen rendering with Mesa; must be set before MuJoCo is first imported.
os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

import signal
import socket
import sys
import traceback
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus

# The simplified robot meshes' disk cache (telerig.robots.models.visual_meshes): the session's own,
# shared by the processes its tests start and removed at the end; never the user's ~/.cache.
_MESH_CACHE = tempfile.mkdtemp(prefix="telerig-test-cache-")
os.environ["TELERIG_CACHE_DIR"] = _MESH_CACHE
atexit.register(shutil.rmtree, _MESH_CACHE, ignore_errors=True)

# --- isolation from the user's files -----------------------------------------------------------------
# Default data roots are relative (``telerig-data`` in the rig schema, the CLI, calibration profiles)
# and MuJoCo writes MUJOCO_LOG.TXT into the working directory on a warning: every test (and every
# higher-scoped fixture) runs with its working directory in a temp dir. An audit hook records any
# access by absolute path to a ``telerig-data`` outside the temp dirs (the repo's, the user's home's)
# and fails the test that made it.

_REPO = Path(__file__).resolve().parents[1]
FORBIDDEN_DATA_ROOTS = tuple(
    dict.fromkeys(p / "telerig-data" for p in (_REPO, Path.cwd().resolve(), Path.home().resolve()))
)
_PATH_EVENTS = frozenset(
    {"open", "os.mkdir", "os.listdir", "os.scandir", "os.rename", "os.remove", "os.rmdir", "os.chdir",
     "shutil.rmtree", "shutil.copytree", "sqlite3.connect", "os.truncate", "os.utime"}
)  # fmt: skip
#: Forbidden accesses seen since the current test started: (event, path).
data_root_accesses: list[tuple[str, str]] = []


def _forbidden(path: object) -> str | None:
    if isinstance(path, int):
        return None
    try:
        text = os.fsdecode(path)  # type: ignore[arg-type]
    except TypeError:
        return None
    if "telerig-data" not in text or not os.path.isabs(text):
        return None  # relative paths resolve in the test's temp dir
    resolved = os.path.normpath(text)
    for root in FORBIDDEN_DATA_ROOTS:
        if resolved == str(root) or resolved.startswith(str(root) + os.sep):
            return resolved
    return None


def _audit(event: str, args: tuple[Any, ...], _finalizing: Any = sys.is_finalizing) -> None:
    # Hooks stay installed while the interpreter tears down this module's globals (they read None
    # then): nothing to check after the tests have ended.
    if _finalizing() or event not in _PATH_EVENTS or not args:
        return
    for arg in args[:2]:  # rename and copytree: source and destination
        hit = _forbidden(arg)
        if hit is not None:
            data_root_accesses.append((event, hit))
            raise PermissionError(f"tests must not touch the user's data root: {event} {hit}")


sys.addaudithook(_audit)


@pytest.fixture(scope="session", autouse=True)
def _session_cwd(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Session- and module-scoped fixtures run in a temp dir too (they start before ``_test_cwd``)."""
    before = Path.cwd()
    os.chdir(tmp_path_factory.mktemp("cwd"))
    yield
    os.chdir(before)


#: SIGINT as the session found it. A child process inherits an ignored or blocked SIGINT through
#: exec, and Python keeps it ignored: a `telerig run` started by a later test then ignores Ctrl-C
#: (the demo Ctrl-C test failed in full runs, exit 0 with every episode committed, and fails the
#: same way when run alone under a parent that ignores SIGINT).
_SIGINT_AT_START = signal.getsignal(signal.SIGINT)


@pytest.fixture(autouse=True)
def _sigint_kept(request: pytest.FixtureRequest) -> Iterator[None]:
    """Put SIGINT back as the session found it after a test (or its fixtures) changed it, and name
    the test in the run's output (not a failure: the test did its own job)."""
    yield
    changed = signal.getsignal(signal.SIGINT) != _SIGINT_AT_START
    blocked = signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, [])
    if changed or blocked:
        signal.signal(signal.SIGINT, _SIGINT_AT_START)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])
        reporter = request.config.pluginmanager.get_plugin("terminalreporter")
        if reporter is not None:
            reporter.write_line(
                f"{request.node.nodeid} left SIGINT {'blocked' if blocked else 'changed'}; restored"
            )


# --- where a leaked socket was made ---------------------------------------------------------------------
# The suite turns warnings into errors, so a socket that nobody closed fails whichever test is running
# when the collector finalizes it: often long after, when the socket sat in a reference cycle. Python
# then names only the socket's addresses. Each socket made in this process notes the test and the
# code that made it, and one finalized unclosed says so in its warning, which names the leak's owner.

#: id(socket) -> (the test that was running, the stack that made it); gone when the socket is.
_socket_origins: dict[int, tuple[str, traceback.StackSummary]] = {}
_current_test = ["(collection)"]
_PYTEST_CODE = re.compile(r"[/\\](_pytest|pluggy)[/\\]")
_socket_init = socket.socket.__init__


def _noted_socket_init(self: socket.socket, *args: Any, **kwargs: Any) -> None:
    _socket_init(self, *args, **kwargs)
    frames = traceback.walk_stack(sys._getframe(1))
    stack = traceback.StackSummary.extract(frames, limit=16, lookup_lines=False)
    _socket_origins[id(self)] = (_current_test[0], stack)


def _socket_del(self: socket.socket) -> None:
    origin = _socket_origins.pop(id(self), None)
    if self.fileno() == -1:
        return
    what = repr(self)
    self.close()  # one warning, this one: the socket's own finalizer finds it closed
    made = ""
    if origin is not None:
        test, stack = origin
        ours = traceback.StackSummary.from_list([f for f in stack if not _PYTEST_CODE.search(f.filename)])
        made = f", made in {test} at\n" + "".join(ours.format())
    warnings.warn(f"unclosed {what}{made}", ResourceWarning, stacklevel=1)


socket.socket.__init__ = _noted_socket_init  # type: ignore[method-assign]
socket.socket.__del__ = _socket_del  # type: ignore[attr-defined]


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item) -> Iterator[None]:
    _current_test[0] = item.nodeid
    try:
        return (yield)
    finally:
        _current_test[0] = f"(after {item.nodeid})"


@pytest.fixture
def data_root_guard() -> tuple[tuple[Path, ...], list[tuple[str, str]]]:
    """The forbidden data roots and the accesses recorded in this test (a test of the guard clears them)."""
    return FORBIDDEN_DATA_ROOTS, data_root_accesses


@pytest.fixture(autouse=True)
def _test_cwd(tmp_path: Path) -> Iterator[None]:
    """Run each test in its ``tmp_path``; fail it if it touched a forbidden data root."""
    before = Path.cwd()
    os.chdir(tmp_path)
    data_root_accesses.clear()
    yield
    os.chdir(before)
    if data_root_accesses:
        seen = ", ".join(f"{event} {path}" for event, path in data_root_accesses[:3])
        data_root_accesses.clear()
        pytest.fail(f"the test touched the user's data root ({seen}); use tmp_path", pytrace=False)


@pytest.fixture
def broker() -> Iterator[MosquittoBroker]:
    """A fresh Mosquitto per test on a free port (starting one takes ~30 ms)."""
    with MosquittoBroker() as running:
        yield running


@pytest.fixture
def make_bus(broker: MosquittoBroker) -> Iterator[Callable[..., MqttBus]]:
    """Factory of connected :class:`MqttBus` clients of ``broker``, closed at teardown."""
    buses: list[MqttBus] = []

    def make(client_id: str, **options: Any) -> MqttBus:
        bus = MqttBus(broker.url, client_id=client_id, **options).connect()
        buses.append(bus)
        return bus

    yield make
    for bus in buses:
        bus.close()


@pytest.fixture(scope="session")
def tls_pki(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """A CA and a server certificate it signs for 127.0.0.1, as PEM files: ``(ca, cert, key)``."""
    return _write_ca_and_server_cert(tmp_path_factory.mktemp("pki"))


def _write_ca_and_server_cert(folder: Path) -> tuple[Path, Path, Path]:
    """A CA, and a server certificate it signs for 127.0.0.1; returns (ca, cert, key) PEM paths."""
    now = datetime.datetime.now(datetime.UTC)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "telerig test CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")]))
        .issuer_name(ca_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), False
        )
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    ca_path, cert_path, key_path = folder / "ca.pem", folder / "server.pem", folder / "server.key"
    ca_path.write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )
    key_path.chmod(0o600)
    return ca_path, cert_path, key_path


# --- recorded episodes ---------------------------------------------------------------------------------


@pytest.fixture(scope="session")
def demo_recording_unchecked(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data root holding 2 real 4 s episodes of the shipped demo rig (scripted VR operator, simulated
    UR5e, 640x480 camera), recorded once per test session by ``telerig run`` in a subprocess with the
    station's quality gates off (``qa.after_commit: false``): both episodes sit in ``episodes/``
    without a ``qa.json``.

    The one recording of the session: ``demo_recording`` is a checked copy of it (recording the demo
    is the slowest fixture of the suite, 2 x 4 s of real time plus start-up). Read it, never change it
    (copy it with ``shutil.copytree`` first).
    """
    import subprocess

    from telerig.config import shipped_rig_path

    base = tmp_path_factory.mktemp("demo-recording")
    rig = base / "demo-unchecked.yaml"
    rig.write_text(shipped_rig_path("demo").read_text() + "\nqa:\n  after_commit: false\n")
    root = base / "data"
    cmd = [
        sys.executable, "-m", "telerig.cli.main", "run", str(rig),
        "--episodes", "2", "--duration", "4", "--data-root", str(root),
    ]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=240, check=False)
    if done.returncode != 0:
        pytest.fail(f"recording the demo rig failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    return root


@pytest.fixture(scope="session")
def demo_recording(demo_recording_unchecked: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data root holding 2 real episodes of the shipped demo rig (scripted VR operator, simulated
    UR5e, 640x480 camera): a copy of ``demo_recording_unchecked`` checked by ``telerig qa`` with the
    demo rig's gates, as the station checks each episode after its commit (``qa.json``, index rows).

    Shared by the quality-gate, export and episode-CLI tests: read it, never change it (copy it with
    ``shutil.copytree`` first). The gates run on a recording made on a loaded machine, so an episode
    may sit in ``failures/`` (e.g. the camera fell behind): list the episodes with
    ``EpisodeStore(root).list(include_failures=True)``.
    """
    import contextlib
    import io
    import shutil

    from telerig.cli.main import main

    root = Path(shutil.copytree(demo_recording_unchecked, tmp_path_factory.mktemp("demo-checked") / "data"))
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["qa", "--data-root", str(root)])
    if code != 0:
        pytest.fail(
            f"telerig qa on the demo recording failed ({code}):\n"
            f"{out.getvalue()[-2000:]}\n{err.getvalue()[-2000:]}"
        )
    return root
