"""Offscreen MuJoCo camera: snapshot under the physics lock, render in a child process, at a fixed rate."""

from __future__ import annotations

import logging
import mmap
import os
import pickle
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, suppress
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from types import TracebackType
from typing import Protocol, runtime_checkable

import mujoco
import numpy as np
import numpy.typing as npt

from telerig import priority
from telerig.cameras import _render_worker as worker
from telerig.cameras.delivery import FrameCallback, FrameDelivery
from telerig.errors import ConfigError, DependencyError
from telerig.ir.types import now_ns

__all__ = ["CameraStats", "FrameCallback", "LockProvider", "MujocoCamera", "RenderedScene", "SimulatedRobot"]

_log = logging.getLogger("telerig.cameras.mujoco_camera")

#: Returns a context manager that holds the physics lock and yields ``(model, data)``.
LockProvider = Callable[[], AbstractContextManager[tuple[mujoco.MjModel, mujoco.MjData]]]


@runtime_checkable
class RenderedScene(Protocol):
    """What a scene camera needs of a simulated robot's scene: the geom groups it renders."""

    visual_groups: tuple[int, ...]


@runtime_checkable
class SimulatedRobot(Protocol):
    """A robot whose physics a scene camera renders (the simulated robots of ``telerig.robots.sim``)."""

    @property
    def scene(self) -> RenderedScene: ...

    def locked(self) -> AbstractContextManager[tuple[mujoco.MjModel, mujoco.MjData]]: ...


#: Debian packages that provide each headless MuJoCo GL backend.
_GL_PACKAGES = {"osmesa": "libosmesa6", "egl": "libegl1 libegl-mesa0", "glfw": "libglfw3 (and a display)"}
#: A frame captured later than this fraction of a period after its deadline counts as late.
_LATE_FRACTION = 0.1
#: Snapshots that wait for the render process while it renders another (a camera's frame buffers):
#: a render that overruns by up to this many periods (the render process is descheduled, the host
#: is busy) delays those frames, not their capture. Beyond it the oldest is dropped (``skipped``).
_QUEUED_SNAPSHOTS = 3
_START_TIMEOUT_S = 30.0
#: How long :meth:`MujocoCamera.stop` waits for the frame in progress before killing the render process [s].
_STOP_TIMEOUT_S = 5.0
#: Runs the render process (see :func:`telerig.cameras._render_worker.main`). It exits without the
#: interpreter's teardown (nothing in it to save): at its lowered priority (runtime.priorities) on a
#: loaded 2-core host, those ~50 ms of CPU took over 5 s, and stop() killed it after waiting.
_WORKER_CODE = "import os; from telerig.cameras._render_worker import main; os._exit(main())"


class _RenderProcessError(Exception):
    """The render process exited, or reported an error, while frames were being captured."""


@dataclass(frozen=True, slots=True)
class CameraStats:
    """Counters of one camera since :meth:`MujocoCamera.start`.

    Attributes:
        frames: Frames captured and handed to ``on_frame``.
        late: Frames captured more than a tenth of a period after their deadline.
        skipped: Deadlines passed without a frame (the camera thread woke a period late), and
            snapshots dropped because the render process fell more than ``_QUEUED_SNAPSHOTS``
            frames behind.
        callback_errors: ``on_frame`` calls that raised.
        mean_render_ms: Mean time to render one frame in the render process, forward kinematics
            included [ms].
    """

    frames: int
    late: int
    skipped: int
    callback_errors: int
    mean_render_ms: float


class MujocoCamera:
    """Renders a named MuJoCo camera at ``fps`` in a child process and hands each frame to ``on_frame``.

    Each tick waits for an absolute deadline, then copies the scene's pose state (``time``,
    ``qpos``, mocap poses: a few µs) while holding the physics lock and stamps the capture
    time there. A render process (a fresh interpreter started by :meth:`start`) owns the GL
    context: it runs forward kinematics on the snapshot and renders it into shared memory, so
    neither physics nor a control loop waits for it, and rendering never holds this process's
    GIL (osmesa/llvmpipe holds it in chunks of up to ~5 ms per frame, ~150 ms to create a
    context). The camera thread waits for the frame (without the GIL), copies it out (~0.1 ms
    at 640x480), hands the render process the next snapshot and calls ``on_frame``.

    Like a real camera, capture keeps its clock whatever rendering does: while a frame renders,
    the next deadlines' snapshots are still taken on time and wait (up to ``_QUEUED_SNAPSHOTS``,
    the oldest dropped beyond that), so a slow render delays frames but leaves no hole in their
    capture times. A tick the camera thread itself wakes a period late for is skipped (counted),
    never caught up in a burst.

    The model is copied to the render process at :meth:`start`; later changes to it (colours,
    camera poses) are not seen. If the render process dies, capture stops with a logged error.

    The GL backend is MuJoCo's: set ``MUJOCO_GL`` (``egl`` or ``osmesa`` headless) before
    ``mujoco`` is first imported; the render process inherits it.

    Args:
        name: Camera id from the rig file; the frames' ``camera_id`` and stamp ``source_id``.
        camera: Name of the camera in the MuJoCo model.
        lock_provider: Returns a context manager holding the physics lock and yielding
            ``(model, data)``; held only for the snapshot.
        on_frame: Called on the camera thread with each RGB image, uint8, shape
            (height, width, 3) (a fresh array it may keep) and its :class:`CameraFrame`. Must
            not block. ``frame_index`` counts frames ``on_frame`` accepted (did not return False).
        width: Image width [px].
        height: Image height [px].
        fps: Frame rate [Hz].
        geom_groups: Geom groups to draw (e.g. visual meshes but not collision meshes); all when None.

    The frame's stamp has ``capture_ns`` (common clock, at the snapshot) and ``device_ns``
    (the simulation time of the snapshot, ``data.time`` in [ns]).
    """

    def __init__(
        self,
        name: str,
        camera: str,
        lock_provider: LockProvider,
        *,
        on_frame: FrameCallback,
        width: int = 640,
        height: int = 480,
        fps: float = 30.0,
        geom_groups: Sequence[int] | None = None,
    ) -> None:
        if width <= 0 or height <= 0:
            raise ValueError(f"camera {name!r}: width and height must be positive, got {width}x{height}")
        if not fps > 0:
            raise ValueError(f"camera {name!r}: fps must be positive, got {fps}")
        self.name = name
        self.camera = camera
        self.width = width
        self.height = height
        self.fps = fps
        self._lock_provider = lock_provider
        self._delivery = FrameDelivery(name, on_frame)
        self._period_ns = round(1e9 / fps)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._process: subprocess.Popen[bytes] | None = None
        self._shm: mmap.mmap | None = None
        self._late = 0
        self._skipped = 0
        self._render_ns = 0
        self._geomgroup = (
            None if geom_groups is None else tuple(int(g in geom_groups) for g in range(mujoco.mjNGROUP))
        )

    @property
    def stats(self) -> CameraStats:
        """Counters since :meth:`start`."""
        d = self._delivery
        mean = self._render_ns / d.frames / 1e6 if d.frames else 0.0
        return CameraStats(d.frames, self._late, self._skipped, d.callback_errors, mean)

    def start(self) -> None:
        """Check the camera against the model, start the render process and start capturing. Idempotent.

        Returns once the render process has created its renderer (about a second: it imports
        MuJoCo and creates a GL context).

        Raises:
            ConfigError: The camera does not exist, or the model's offscreen buffer is smaller
                than the image.
            DependencyError: The GL backend (``MUJOCO_GL``) could not be loaded.
            RuntimeError: The camera was stopped (cameras are not restarted), or the render
                process could not be started.
        """
        if self._thread is not None:
            if self._stop.is_set():
                raise RuntimeError(f"camera {self.name!r} was stopped; create a new MujocoCamera")
            return
        with self._lock_provider() as (model, _):
            self._check_model(model)
        # The model is not changed by stepping, so it is copied outside the lock.
        model_pickle = pickle.dumps(model, protocol=pickle.HIGHEST_PROTOCOL)
        layout = worker.StateLayout(model.nq, model.nmocap)
        conn, process, shm = self._spawn(model_pickle)
        self._process, self._shm = process, shm
        self._thread = threading.Thread(
            target=self._run, args=(conn, process, shm, layout), name=f"camera-{self.name}", daemon=True
        )
        self._thread.start()

    def stop(self) -> None:
        """Stop capturing, end the render process and free the shared memory; waits for the frame in progress.

        Idempotent. Called from ``on_frame``, it returns at once and the camera thread cleans up
        after the current frame.
        """
        self._stop.set()
        thread = self._thread
        if thread is None or thread is threading.current_thread():
            return
        thread.join(_STOP_TIMEOUT_S)
        if thread.is_alive():
            _log.warning(
                "%s: render process did not finish its frame in %.0f s; killing it",
                self.name,
                _STOP_TIMEOUT_S,
            )
            if self._process is not None:
                self._process.kill()  # the camera thread sees EOF and cleans up
            thread.join()

    def __enter__(self) -> MujocoCamera:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def _check_model(self, model: mujoco.MjModel) -> None:
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, self.camera) < 0:
            names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(model.ncam)]
            available = ", ".join(n for n in names if n) or "none"
            raise ConfigError(
                f"camera {self.name!r}: model camera {self.camera!r} does not exist. Available: {available}"
            )
        buffer_w, buffer_h = model.vis.global_.offwidth, model.vis.global_.offheight
        if self.width > buffer_w or self.height > buffer_h:
            raise ConfigError(
                f"camera {self.name!r}: {self.width}x{self.height} px is larger than the model's offscreen "
                f'buffer ({buffer_w}x{buffer_h}). Add <visual><global offwidth="{max(self.width, buffer_w)}" '
                f'offheight="{max(self.height, buffer_h)}"/></visual> to the MJCF (or set '
                "model.vis.global_.offwidth/offheight before starting the camera), or lower width/height"
            )

    def _spawn(self, model_pickle: bytes) -> tuple[Connection, subprocess.Popen[bytes], mmap.mmap]:
        """Start the render process and wait for its renderer; raise its start-up error."""
        size = self.height * self.width * 3
        shm_fd = _shared_file(size)
        shm = mmap.mmap(shm_fd, size)
        parent_sock, child_sock = socket.socketpair()
        try:
            # A fresh interpreter, not a fork: this process has threads, GL and network state.
            process = subprocess.Popen(
                [sys.executable, "-c", _WORKER_CODE, str(child_sock.fileno()), str(shm_fd)],
                pass_fds=(child_sock.fileno(), shm_fd),
                stdin=subprocess.DEVNULL,
                env=_worker_env(),
            )
        except BaseException:
            parent_sock.close()
            shm.close()
            raise
        finally:
            child_sock.close()  # so that the render process's death reads as EOF here
            os.close(shm_fd)
        conn = Connection(parent_sock.detach())
        setup = worker.RenderSetup(model_pickle, self.camera, self.width, self.height, self._geomgroup)
        try:
            conn.send(setup)
            reply = conn.recv_bytes() if conn.poll(_START_TIMEOUT_S) else None
        except (EOFError, OSError):
            reply = b""
        if reply is not None and reply[:1] == worker.READY:
            priority.note("render", reply[1:].decode(errors="replace"))
            return conn, process, shm
        exitcode = _end_process(conn, process, timeout_s=1.0)
        shm.close()
        if reply is None:
            raise DependencyError(
                f"camera {self.name!r}: the GL backend MUJOCO_GL={_backend()!r} did not start "
                f"within {_START_TIMEOUT_S:.0f} s"
            )
        message = reply[1:].decode(errors="replace")
        if reply[:1] == worker.GL_ERROR:
            error = RuntimeError(message)
            raise _gl_error(self.name, error) from error
        detail = message if reply[:1] == worker.ERROR else f"it exited with code {exitcode}"
        raise RuntimeError(f"camera {self.name!r}: the render process failed to start: {detail}")

    def _run(
        self, conn: Connection, process: subprocess.Popen[bytes], shm: mmap.mmap, layout: worker.StateLayout
    ) -> None:
        failure: str | None = None
        try:
            self._capture_loop(conn, shm, layout)
        except _RenderProcessError as exc:
            failure = str(exc)
        except Exception:
            _log.exception("%s: capture stopped", self.name)
        finally:
            exitcode = _end_process(conn, process, timeout_s=_STOP_TIMEOUT_S)
            with suppress(BufferError):  # a frame view outlived the loop; the mapping goes with the process
                shm.close()
        if failure is not None and not self._stop.is_set():
            self._stop.set()
            _log.error("%s: %s (exit code %s); capture stopped", self.name, failure, exitcode)

    def _capture_loop(self, conn: Connection, shm: mmap.mmap, layout: worker.StateLayout) -> None:
        image = np.frombuffer(shm, dtype=np.uint8).reshape(self.height, self.width, 3)
        period = self._period_ns
        late_after = int(period * _LATE_FRACTION)
        # Snapshots taken, not yet rendered: (state, capture_ns, sim_ns), oldest first.
        waiting: deque[tuple[npt.NDArray[np.float64], int, int]] = deque()
        rendering: tuple[int, int] | None = None  # (capture_ns, sim_ns) of the frame being rendered
        deadline = time.monotonic_ns()
        while not self._stop.is_set():
            wait_ns = deadline - time.monotonic_ns()
            if wait_ns > 0:
                if rendering is None:
                    self._stop.wait(wait_ns / 1e9)
                elif conn.poll(wait_ns / 1e9):  # waits without the GIL
                    self._render_ns += _receive(conn)
                    frame = image.copy()
                    captured, rendering = rendering, None
                    if waiting:  # render the next one while this one is delivered
                        state, capture_ns, sim_ns = waiting.popleft()
                        _send(conn, state)
                        rendering = (capture_ns, sim_ns)
                    self._delivery.deliver(frame, device_ns=captured[1], capture_ns=captured[0])
                continue
            lateness = -wait_ns
            if lateness >= period:
                missed = lateness // period
                self._skipped += missed
                deadline += missed * period
                lateness -= missed * period
            if lateness > late_after:
                self._late += 1
            state = layout.empty()
            with self._lock_provider() as (_, data):
                capture_ns = now_ns()
                sim_ns = round(data.time * 1e9)
                worker.pack_state(layout, data, state)
            if rendering is None:
                _send(conn, state)
                rendering = (capture_ns, sim_ns)
            else:
                if len(waiting) == _QUEUED_SNAPSHOTS:
                    waiting.popleft()  # the render process fell that far behind: drop the oldest
                    self._skipped += 1
                waiting.append((state, capture_ns, sim_ns))
            deadline += period


def _send(conn: Connection, state: npt.NDArray[np.float64]) -> None:
    """Hand one snapshot to the render process (copied into the socket: ``state`` may be reused)."""
    try:
        conn.send_bytes(state.data)
    except OSError as exc:
        raise _RenderProcessError("render process died") from exc


def _receive(conn: Connection) -> int:
    """The render process's reply to the snapshot sent last: its render time [ns], once the frame
    is in shared memory."""
    try:
        reply = conn.recv_bytes()
    except (EOFError, OSError) as exc:
        raise _RenderProcessError("render process died") from exc
    if reply[:1] != worker.FRAME:
        raise _RenderProcessError(f"render process failed: {reply[1:].decode(errors='replace')}")
    return worker.parse_frame(reply)


def _end_process(conn: Connection, process: subprocess.Popen[bytes], *, timeout_s: float) -> int | None:
    """Close the pipe (the render process exits on EOF), wait, kill it if it lingers; its exit code."""
    conn.close()
    try:
        return process.wait(timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.wait()


def _shared_file(size: int) -> int:
    """Descriptor of ``size`` zero bytes in memory with no name: nothing to unlink, even after a crash."""
    if hasattr(os, "memfd_create"):
        fd = os.memfd_create("telerig-camera")
    else:
        shm_dir = "/dev/shm" if os.path.isdir("/dev/shm") else None
        fd, path = tempfile.mkstemp(prefix="telerig-camera-", dir=shm_dir)
        os.unlink(path)
    os.ftruncate(fd, size)
    return fd


def _worker_env() -> dict[str, str]:
    """This process's environment (``MUJOCO_GL`` and friends) for the render process."""
    env = dict(os.environ)
    # Mesa's llvmpipe renders a 640x480 arm scene as fast on one thread as on two (~24 ms
    # here) but with two it takes the core the control loop needs; read at context creation.
    env.setdefault("LP_NUM_THREADS", "1")
    env[priority.RENDER_ENV] = priority.render_env()
    # The render process imports telerig from where this one did, installed or not.
    root = str(Path(worker.__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH")) if p)
    return env


def _backend() -> str:
    return os.environ.get("MUJOCO_GL", "glfw (MUJOCO_GL unset)")


def _gl_error(name: str, exc: BaseException) -> DependencyError:
    backend = os.environ.get("MUJOCO_GL", "").lower() or "glfw"
    platform = os.environ.get("PYOPENGL_PLATFORM", "").lower()
    if platform and backend in ("egl", "osmesa") and platform != backend:
        fix = f"set PYOPENGL_PLATFORM={backend} (or unset it) to match MUJOCO_GL"
    else:
        package = _GL_PACKAGES.get(backend, _GL_PACKAGES["egl"])
        fix = (
            f"install it with: sudo apt-get install {package}; headless machines need MUJOCO_GL=egl or osmesa"
        )
    return DependencyError(
        f"camera {name!r}: MuJoCo could not create a GL context with MUJOCO_GL={backend}: {fix} ({exc})"
    )
