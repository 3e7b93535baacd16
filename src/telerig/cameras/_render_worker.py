"""Render process of a MujocoCamera: pose snapshots in, RGB frames out through shared memory."""

from __future__ import annotations

import mmap
import os
import pickle
import signal
import struct
import sys
import time
from contextlib import suppress
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import numpy.typing as npt

from telerig import priority

__all__ = [
    "ERROR",
    "FRAME",
    "GL_ERROR",
    "READY",
    "RenderSetup",
    "StateLayout",
    "main",
    "pack_state",
    "parse_frame",
]

# Replies of the render process: one tag byte, then the payload.
#: Renderer created; the process waits for snapshots. Payload: its CPU priority, UTF-8
#: (:func:`telerig.priority.describe`).
READY = b"R"
#: Frame written to shared memory; payload: render time, int64 little-endian [ns].
FRAME = b"F"
#: Start-up failed before the GL context, or a render failed; payload: UTF-8 message. The process exits.
ERROR = b"E"
#: The GL backend failed (importing MuJoCo, creating the renderer); payload: UTF-8 message. The process exits.
GL_ERROR = b"G"

_NS = struct.Struct("<q")


@dataclass(frozen=True, slots=True)
class RenderSetup:
    """First message to the render process: what to render.

    Attributes:
        model_pickle: The ``MjModel``, pickled.
        camera: Name of the camera in the model.
        width: Image width [px].
        height: Image height [px].
        geomgroup: Per geom group, 1 to draw it; MuJoCo's default when None.
    """

    model_pickle: bytes
    camera: str
    width: int
    height: int
    geomgroup: tuple[int, ...] | None


class StateLayout:
    """Positions of a snapshot's fields in the float64 vector sent to the render process.

    The vector is ``time`` [s], ``qpos`` (nq), ``mocap_pos`` (nmocap x 3, row-major),
    ``mocap_quat`` (nmocap x 4): everything forward kinematics needs to place the bodies.
    """

    def __init__(self, nq: int, nmocap: int) -> None:
        self.nq = nq
        self.nmocap = nmocap
        self.qpos = slice(1, 1 + nq)
        self.mocap_pos = slice(1 + nq, 1 + nq + 3 * nmocap)
        self.mocap_quat = slice(1 + nq + 3 * nmocap, 1 + nq + 7 * nmocap)
        self.size = 1 + nq + 7 * nmocap

    def empty(self) -> npt.NDArray[np.float64]:
        """A snapshot vector to fill, shape (size,)."""
        return np.empty(self.size, dtype=np.float64)


def pack_state(layout: StateLayout, data: Any, out: npt.NDArray[np.float64]) -> None:
    """Copy the pose state of ``data`` (an ``MjData``) into ``out``, shape (layout.size,); a few µs."""
    out[0] = data.time
    out[layout.qpos] = data.qpos
    if layout.nmocap:
        out[layout.mocap_pos] = data.mocap_pos.ravel()
        out[layout.mocap_quat] = data.mocap_quat.ravel()


def parse_frame(reply: bytes) -> int:
    """Render time of a :data:`FRAME` reply [ns]."""
    value: int = _NS.unpack_from(reply, 1)[0]
    return value


def main(argv: list[str] | None = None) -> int:
    """Render process entry point; ``argv`` (default ``sys.argv[1:]``) is ``[CONN_FD, SHM_FD]``.

    ``CONN_FD`` is this process's end of a socket pair to the camera thread, ``SHM_FD`` a
    shared file of height * width * 3 bytes. The first message is a pickled
    :class:`RenderSetup`; the reply is :data:`READY`, :data:`GL_ERROR` or :data:`ERROR`. Then
    each request is a snapshot vector (see :class:`StateLayout`) and each reply :data:`FRAME`,
    sent once the RGB image, uint8 of shape (height, width, 3), is in the shared file. The
    parent closing its end (it stopped the camera, or died) ends the process.
    """
    conn_fd, shm_fd = (int(a) for a in (argv if argv is not None else sys.argv[1:]))
    # Ctrl-C reaches the whole process group; the parent decides when this process ends.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    conn = Connection(conn_fd)
    try:
        setup: RenderSetup = conn.recv()
        shm = mmap.mmap(shm_fd, setup.height * setup.width * 3)
    except (EOFError, OSError):  # the parent is gone
        return 1
    finally:
        os.close(shm_fd)
    try:
        return _render(conn, setup, shm)
    finally:
        with suppress(BufferError):  # a view outlived the loop; the mapping goes with the process
            shm.close()
        conn.close()


def _render(conn: Connection, setup: RenderSetup, shm: mmap.mmap) -> int:
    stage = GL_ERROR
    try:
        import mujoco

        stage = ERROR
        model = pickle.loads(setup.model_pickle)
        data = mujoco.MjData(model)
        option = mujoco.MjvOption()
        if setup.geomgroup is not None:
            option.geomgroup[:] = setup.geomgroup
        stage = GL_ERROR
        renderer = mujoco.Renderer(model, height=setup.height, width=setup.width)
    except Exception as exc:
        _reply(conn, stage + (str(exc) or type(exc).__name__).encode())
        return 1
    try:
        # Now that the renderer and its threads exist (not before: starting lowered took over 30 s
        # on a loaded host): on a busy machine the control loop's threads get a core first and
        # rendering takes what is left (the parent's runtime.priorities).
        applied = priority.enter_render_from_env()
        _serve(conn, model, data, renderer, setup.camera, option, shm, applied)
    except Exception as exc:  # reported to the camera thread, which logs it
        _reply(conn, ERROR + f"{type(exc).__name__}: {exc}".encode())
        return 1
    finally:
        renderer.close()
    return 0


def _serve(
    conn: Connection,
    model: Any,
    data: Any,
    renderer: Any,
    camera: str,
    option: Any,
    shm: mmap.mmap,
    applied: str,
) -> None:
    import mujoco

    image = np.frombuffer(shm, dtype=np.uint8).reshape(renderer.height, renderer.width, 3)
    layout = StateLayout(model.nq, model.nmocap)
    state = layout.empty()
    conn.send_bytes(READY + applied.encode())
    while True:
        try:
            conn.recv_bytes_into(state)
        except EOFError:
            return
        t0 = time.perf_counter_ns()
        data.time = state[0]
        data.qpos[:] = state[layout.qpos]
        if layout.nmocap:
            data.mocap_pos[:] = state[layout.mocap_pos].reshape(-1, 3)
            data.mocap_quat[:] = state[layout.mocap_quat].reshape(-1, 4)
        mujoco.mj_fwdKinematics(model, data)  # body, camera, light, tendon and flex poses
        renderer.update_scene(data, camera=camera, scene_option=option)
        renderer.render(out=image)
        conn.send_bytes(FRAME + _NS.pack(time.perf_counter_ns() - t0))


def _reply(conn: Connection, message: bytes) -> None:
    with suppress(OSError):  # the parent is gone
        conn.send_bytes(message)


if __name__ == "__main__":
    raise SystemExit(main())
