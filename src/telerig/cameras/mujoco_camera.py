"""Offscreen camera of a MuJoCo scene: snapshot under the physics lock, render outside it, at a fixed rate."""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from types import TracebackType

import mujoco
import numpy as np
import numpy.typing as npt

from telerig.errors import ConfigError, DependencyError
from telerig.ir.types import CameraFrame, Stamp, now_ns

__all__ = ["CameraStats", "FrameCallback", "LockProvider", "MujocoCamera"]

_log = logging.getLogger("telerig.cameras.mujoco_camera")

#: Returns a context manager that holds the physics lock and yields ``(model, data)``.
LockProvider = Callable[[], AbstractContextManager[tuple[mujoco.MjModel, mujoco.MjData]]]
#: Receives each frame: RGB uint8 image of shape (height, width, 3) and its metadata. Returns False
#: when the frame was not recorded (e.g. the encoder dropped it), so its index is given to the next one.
FrameCallback = Callable[[npt.NDArray[np.uint8], CameraFrame], bool | None]

#: Debian packages that provide each headless MuJoCo GL backend.
_GL_PACKAGES = {"osmesa": "libosmesa6", "egl": "libegl1 libegl-mesa0", "glfw": "libglfw3 (and a display)"}
#: A frame captured later than this fraction of a period after its deadline counts as late.
_LATE_FRACTION = 0.1
_START_TIMEOUT_S = 30.0


@dataclass(frozen=True, slots=True)
class CameraStats:
    """Counters of one camera since :meth:`MujocoCamera.start`.

    Attributes:
        frames: Frames captured and handed to ``on_frame``.
        late: Frames captured more than a tenth of a period after their deadline.
        skipped: Deadlines passed without a frame because rendering overran.
        callback_errors: ``on_frame`` calls that raised.
        mean_render_ms: Mean time to render one frame, outside the lock [ms].
    """

    frames: int
    late: int
    skipped: int
    callback_errors: int
    mean_render_ms: float


class MujocoCamera:
    """Renders a named MuJoCo camera at ``fps`` on its own thread and hands each frame to ``on_frame``.

    Each tick waits for an absolute deadline, then takes a consistent snapshot of the scene
    while holding the physics lock (``update_scene``, about 0.1 ms) and stamps the capture
    time there; rendering happens after the lock is released, so neither physics nor a
    control loop waits for it. Ticks missed because a render overran are skipped (counted),
    never caught up in a burst. The GL context is created on the camera thread, which owns it.

    The GL backend is MuJoCo's: set ``MUJOCO_GL`` (``egl`` or ``osmesa`` headless) before
    ``mujoco`` is first imported.

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
        self._on_frame = on_frame
        self._period_ns = round(1e9 / fps)
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self._start_error: BaseException | None = None
        self._frames = 0
        self._late = 0
        self._skipped = 0
        self._callback_errors = 0
        self._render_ns = 0
        self._scene_option = mujoco.MjvOption()
        if geom_groups is not None:
            for group in range(len(self._scene_option.geomgroup)):
                self._scene_option.geomgroup[group] = int(group in geom_groups)

    @property
    def stats(self) -> CameraStats:
        """Counters since :meth:`start`."""
        mean = self._render_ns / self._frames / 1e6 if self._frames else 0.0
        return CameraStats(self._frames, self._late, self._skipped, self._callback_errors, mean)

    def start(self) -> None:
        """Check the camera against the model, create the renderer and start capturing. Idempotent.

        Raises:
            ConfigError: The camera does not exist, or the model's offscreen buffer is smaller
                than the image.
            DependencyError: The GL backend (``MUJOCO_GL``) could not be loaded.
            RuntimeError: The camera was stopped; cameras are not restarted.
        """
        if self._thread is not None:
            if self._stop.is_set():
                raise RuntimeError(f"camera {self.name!r} was stopped; create a new MujocoCamera")
            return
        with self._lock_provider() as (model, _):
            self._check_model(model)
        self._thread = threading.Thread(
            target=self._run, args=(model,), name=f"camera-{self.name}", daemon=True
        )
        self._thread.start()
        if not self._ready.wait(_START_TIMEOUT_S):
            self.stop()
            raise DependencyError(
                f"camera {self.name!r}: the GL backend MUJOCO_GL={_backend()!r} did not start "
                f"within {_START_TIMEOUT_S:.0f} s"
            )
        if self._start_error is not None:
            self._thread.join()
            raise _gl_error(self.name, self._start_error) from self._start_error

    def stop(self) -> None:
        """Stop capturing and release the renderer; waits for the frame in progress. Idempotent."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()

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

    def _run(self, model: mujoco.MjModel) -> None:
        # Mesa's llvmpipe renders a 640x480 arm scene as fast on one thread as on two (~24 ms
        # here) but with two it takes the core the control loop needs; read at context creation.
        os.environ.setdefault("LP_NUM_THREADS", "1")
        try:
            renderer = mujoco.Renderer(model, height=self.height, width=self.width)
        except Exception as exc:  # any GL loading failure; start() turns it into a DependencyError
            self._start_error = exc
            self._ready.set()
            return
        try:
            self._ready.set()
            self._capture_loop(renderer)
        except Exception:
            _log.exception("%s: capture stopped", self.name)
        finally:
            renderer.close()

    def _capture_loop(self, renderer: mujoco.Renderer) -> None:
        period = self._period_ns
        late_after = int(period * _LATE_FRACTION)
        deadline = time.monotonic_ns()
        index = 0
        while not self._stop.is_set():
            wait_ns = deadline - time.monotonic_ns()
            if wait_ns > 0 and self._stop.wait(wait_ns / 1e9):
                return
            lateness = time.monotonic_ns() - deadline
            if lateness >= period:
                missed = lateness // period
                self._skipped += missed
                deadline += missed * period
                lateness -= missed * period
            if lateness > late_after:
                self._late += 1
            with self._lock_provider() as (_, data):
                capture_ns = now_ns()
                sim_ns = round(data.time * 1e9)
                renderer.update_scene(data, camera=self.camera, scene_option=self._scene_option)
            t0 = time.perf_counter_ns()
            image = renderer.render()
            self._render_ns += time.perf_counter_ns() - t0
            stamp = Stamp(source_id=self.name, seq=index, device_ns=sim_ns, capture_ns=capture_ns)
            meta = CameraFrame(stamp, self.name, index, self.width, self.height)
            self._frames += 1
            try:
                accepted = self._on_frame(image, meta)
            except Exception:
                self._callback_errors += 1
                if self._callback_errors == 1:
                    _log.exception("%s: on_frame failed (later failures are only counted)", self.name)
                accepted = False
            if accepted is not False:
                index += 1
            deadline += period


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
