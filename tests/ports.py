"""Ports for the children the tests start: Mosquitto and PostgreSQL take a port number, not 0.

A port found free here can be bound by another process (a second test worker, a client's ephemeral
port) before the child binds it. :func:`on_a_free_port` therefore starts the child again on another
free port when it exits saying so; a child that fails for any other reason fails the test.
"""

from __future__ import annotations

import socket
import subprocess
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")

ATTEMPTS = 3


class PortTakenError(Exception):
    """The child could not bind its port: another process took it after :func:`free_port`."""


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listened on a moment ago."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def on_a_free_port(start: Callable[[int], T], attempts: int = ATTEMPTS) -> T:
    """``start(port)`` on a free port; on :class:`PortTakenError`, again on another (``attempts`` in all)."""
    for attempt in range(attempts):
        try:
            return start(free_port())
        except PortTakenError:
            if attempt == attempts - 1:
                raise
    raise AssertionError("unreachable")


#: What Mosquitto logs once its listeners are open ("mosquitto version 2.0.11 running").
MOSQUITTO_RUNNING = " running\n"
#: What a Werkzeug server (``moto_server``) prints once it listens (" * Running on http://...").
WERKZEUG_RUNNING = " * Running on "


def start_listening(
    cmd: Sequence[str],
    port: int,
    log: Path,
    ready: str,
    env: Mapping[str, str] | None = None,
    timeout_s: float = 5.0,
) -> subprocess.Popen[bytes]:
    """Start ``cmd`` (its stdout and stderr appended to ``log``) and wait as :func:`wait_listening` does.

    A child that does not listen is killed before the error propagates, so an attempt on a taken
    port leaves nothing behind for :func:`on_a_free_port`'s next one.
    """
    with open(log, "ab") as out:
        proc = subprocess.Popen(list(cmd), stdout=out, stderr=subprocess.STDOUT, env=env)
    try:
        wait_listening(port, proc, log, ready, timeout_s)
    except BaseException:
        proc.kill()
        proc.wait()
        raise
    return proc


def wait_listening(
    port: int, proc: subprocess.Popen[bytes], log: Path, ready: str, timeout_s: float = 5.0
) -> None:
    """Wait until ``proc``'s ``log`` holds ``ready`` (what it logs once it listens) and ``port`` answers.

    The port alone is not enough: a program that took the port first answers at once, while ``proc``
    is still about to fail on it.

    Raises:
        PortTakenError: ``proc`` exited and its ``log`` says the address was in use.
        AssertionError: It exited otherwise (with the log's tail), or did not listen in time.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        text = log.read_text(errors="replace") if log.exists() else ""
        if proc.poll() is not None:
            if "in use" in text:
                raise PortTakenError(f"port {port}: {text.strip().splitlines()[-1]}")
            raise AssertionError(f"{_name(proc)} exited ({proc.returncode}): {text[-2000:]}")
        if ready in text:
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                    return
            except OSError:
                pass
        assert time.monotonic() < deadline, f"{_name(proc)} did not listen on {port} in {timeout_s} s"
        time.sleep(0.02)


def _name(proc: subprocess.Popen[bytes]) -> str:
    """The child's command without its arguments' tail ("python -m moto.server", "mosquitto -c")."""
    args = proc.args if isinstance(proc.args, list) else [proc.args]
    return " ".join(Path(str(a)).name if i == 0 else str(a) for i, a in enumerate(args[:3]))
