"""The policy's inference process: the only process of a rollout that imports torch.

:class:`InferenceProcess` starts a fresh interpreter (``python -m telerig.devices.policy.worker``,
talking over an inherited socket pair: nothing of the control process is forked into it, its main
module is not re-imported as ``multiprocessing``'s spawn would, and torch never enters the control
process) that loads the checkpoint through a loader (``module:function`` returning an
object with ``spec`` and ``act(state, images)``, by default :func:`telerig.policy.runner.load_policy`)
and answers one request at a time over a pipe. The parent never blocks longer than the deadline
it passes to :meth:`InferenceProcess.request`: an answer that comes later is discarded when it
arrives (the caller counts the tick as missed), so a slow model costs samples, never the loop.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import numpy.typing as npt

from telerig.errors import DeviceError

__all__ = ["DEFAULT_LOADER", "InferenceProcess", "PolicyInfo", "serve"]

#: The loader of telerig's own checkpoints (:mod:`telerig.policy.runner`).
DEFAULT_LOADER = "telerig.policy.runner:load_policy"


@dataclass(frozen=True, slots=True)
class PolicyInfo:
    """What the loaded policy reads and writes (from its runner's ``spec``), in the parent.

    Attributes:
        state_names: State vector entries, in order (joint names, ``gripper``).
        action_names: Action vector entries, in order.
        camera_keys: Cameras it needs, one RGB frame each.
        image_size: (H, W) [px] its network sees.
        fps: Its dataset's rate [Hz].
        chunk_size: Actions per inference.
        checkpoint_id: Short content id recorded with rollout episodes.
        checkpoint_sha256: Full content hash.
        policy_type: ``bc``, ``act_lite`` or a plug-in's name.
    """

    state_names: tuple[str, ...]
    action_names: tuple[str, ...]
    camera_keys: tuple[str, ...]
    image_size: tuple[int, int]
    fps: float
    chunk_size: int
    checkpoint_id: str
    checkpoint_sha256: str
    policy_type: str

    @classmethod
    def of(cls, spec: Any) -> PolicyInfo:
        """From a runner's ``spec`` (duck-typed: any object with these attributes)."""
        return cls(
            tuple(str(n) for n in spec.state_names),
            tuple(str(n) for n in spec.action_names),
            tuple(str(k) for k in spec.camera_keys),
            (int(spec.image_size[0]), int(spec.image_size[1])),
            float(spec.fps),
            int(spec.chunk_size),
            str(spec.checkpoint_id),
            str(spec.checkpoint_sha256),
            str(getattr(spec, "policy_type", "")),
        )


def _load(loader: str) -> Callable[..., Any]:
    module, _, name = loader.partition(":")
    if not module or not name:
        raise ValueError(f"policy loader {loader!r} must be 'module:function'")
    fn = getattr(importlib.import_module(module), name)
    if not callable(fn):
        raise ValueError(f"policy loader {loader!r} is not callable")
    return fn  # type: ignore[no-any-return]


def serve(conn: Connection, loader: str, checkpoint: str, threads: int) -> None:
    """Child main: load the policy, say ``ready`` (or ``error``), then answer ``act`` requests.

    Requests: ``("act", seq, state, images)`` → ``("action", seq, chunk, infer_ns)`` or
    ``("failed", seq, reason)``; ``("stop",)`` ends it, as does a closed pipe.
    """
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    try:
        runner = _load(loader)(checkpoint, threads=threads)
        info = PolicyInfo.of(runner.spec)
    except Exception as exc:
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    conn.send(("ready", info))
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):
            return
        if not isinstance(request, tuple) or not request or request[0] != "act":
            return
        _, seq, state, images = request
        t0 = time.perf_counter_ns()
        try:
            chunk = np.asarray(runner.act(state, images), dtype=np.float64)
        except Exception as exc:
            conn.send(("failed", seq, f"{type(exc).__name__}: {exc}"))
            continue
        conn.send(("action", seq, chunk, time.perf_counter_ns() - t0))


class InferenceProcess:
    """A policy loaded in its own process, asked for action chunks with a deadline.

    Args:
        checkpoint: The checkpoint file.
        loader: ``module:function`` called as ``function(checkpoint, threads=threads)`` in the child.
        threads: torch threads of the child (1: it shares the host with the control loop).
        start_timeout_s: How long loading may take [s].

    Raises:
        DeviceError: the child could not load the policy (its one-line reason), or timed out.
    """

    def __init__(self, checkpoint: str, *, loader: str = DEFAULT_LOADER, threads: int = 1,
                 start_timeout_s: float = 120.0) -> None:  # fmt: skip
        ours, theirs = socket.socketpair()
        env = dict(os.environ)
        # The child imports what this process can (telerig, a loader's module) from the same paths.
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
        env["OMP_NUM_THREADS"] = str(threads)
        self._process = subprocess.Popen(
            [sys.executable, "-m", "telerig.devices.policy.worker", str(theirs.fileno()), loader, checkpoint,
             str(threads)],
            pass_fds=(theirs.fileno(),),
            env=env,
            stdin=subprocess.DEVNULL,
        )  # fmt: skip
        theirs.close()
        parent = self._conn = Connection(ours.detach())
        self._seq = 0
        self._pending: int | None = None
        #: Answers that came after their deadline (discarded), requests the child failed.
        self.late = 0
        self.failed = 0
        self.last_error = ""
        self.infer_ns: list[int] = []
        if not parent.poll(start_timeout_s):
            self.close()
            raise DeviceError(
                f"policy {checkpoint}: the inference process did not load it in {start_timeout_s:g} s"
            )
        try:
            message = parent.recv()
        except (EOFError, OSError):
            self.close()
            raise DeviceError(f"policy {checkpoint}: the inference process exited while loading") from None
        if message[0] != "ready":
            self.close()
            raise DeviceError(f"policy {checkpoint}: {message[1]}")
        self.info: PolicyInfo = message[1]

    @property
    def pid(self) -> int | None:
        return self._process.pid

    @property
    def exitcode(self) -> int | None:
        """The inference process's exit code (negative: killed by that signal); None while it runs."""
        return self._process.poll()

    @property
    def alive(self) -> bool:
        """Whether the inference process still runs."""
        return self._process.poll() is None

    @property
    def busy(self) -> bool:
        """Whether a request is still being answered (after its deadline passed)."""
        self._drain()
        return self._pending is not None

    def _drain(self) -> None:
        """Take answers that arrived after their deadline (discarded)."""
        while self._pending is not None and self._conn.poll(0):
            if self._recv()[1] == self._pending:
                self._pending = None

    def _recv(self) -> tuple[Any, ...]:
        """One answer (``action`` or ``failed``, which is counted)."""
        try:
            answer: tuple[Any, ...] = self._conn.recv()
        except (EOFError, OSError):
            self._pending = None
            raise DeviceError("the policy's inference process died") from None
        if answer[0] == "failed":
            self.failed += 1
            self.last_error = str(answer[2])
        return answer

    def request(
        self, state: npt.NDArray[np.float64], images: Mapping[str, npt.NDArray[np.uint8]], deadline_s: float
    ) -> npt.NDArray[np.float64] | None:
        """The action chunk (chunk, A) for one observation, or None when it is not there by the
        deadline [s from now] (counted in ``late`` when it comes), the policy failed on it, or the
        previous request is still being answered.

        Raises:
            DeviceError: the inference process died.
        """
        if self.busy:
            return None
        self._seq += 1
        seq = self._pending = self._seq
        try:
            self._conn.send(("act", seq, state, dict(images)))
        except (OSError, ValueError):
            raise DeviceError("the policy's inference process died") from None
        end = time.monotonic() + deadline_s
        while True:
            remaining = end - time.monotonic()
            if remaining <= 0 or not self._conn.poll(remaining):
                self.late += 1
                return None
            answer = self._recv()
            if answer[1] != seq:
                continue  # an earlier late answer
            self._pending = None
            if answer[0] == "failed":
                return None
            self.infer_ns.append(int(answer[3]))
            if len(self.infer_ns) > 1000:
                del self.infer_ns[:500]
            return np.asarray(answer[2], dtype=np.float64)

    def close(self) -> None:
        """Stop the child (politely, then by force). Idempotent."""
        with contextlib.suppress(OSError, ValueError):
            self._conn.send(("stop",))
        try:
            self._process.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait(timeout=5.0)
        self._conn.close()


def main(argv: list[str] | None = None) -> None:
    """``python -m telerig.devices.policy.worker FD LOADER CHECKPOINT THREADS`` (started by
    :class:`InferenceProcess`, not by hand)."""
    # Through the module's own name, so what it pickles (PolicyInfo) names telerig's module, not __main__.
    from telerig.devices.policy import worker  # noqa: PLW0406

    fd, loader, checkpoint, threads = (sys.argv[1:] if argv is None else argv)[:4]
    worker.serve(Connection(int(fd)), loader, checkpoint, int(threads))


if __name__ == "__main__":
    main()
