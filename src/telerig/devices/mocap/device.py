"""Mocap devices: an OptiTrack NatNet client and a BVH file player, each on its own thread."""

from __future__ import annotations

import dataclasses
import logging
import math
import selectors
import socket
import threading
import time
from collections import Counter
from collections.abc import Mapping
from pathlib import Path

from telerig.devices.base import SampleSink
from telerig.devices.mocap._axes import MountTransform
from telerig.devices.mocap.bvh import BvhClip, cmu_renames, detect_scale, parse_bvh
from telerig.devices.mocap.protocol import (
    NAT_FRAMEOFDATA,
    NAT_KEEPALIVE,
    NAT_MODELDEF,
    NAT_REQUEST_MODELDEF,
    NAT_SERVERINFO,
    PORT_COMMAND,
    PORT_DATA,
    FrameNormalizer,
    MocapFrame,
    NatNetVersion,
    encode_connect,
    encode_packet,
    parse_frame,
    parse_model_definitions,
    parse_server_info,
    split_packet,
)
from telerig.devices.worker import DeviceWorker, PlaybackClock
from telerig.errors import DeviceError, WireError
from telerig.ir.clock import ClockOffsetEstimator
from telerig.ir.types import BodySkeleton, Sample, now_ns

__all__ = ["BvhPlayer", "NatNetClient"]

_log = logging.getLogger(__name__)
_RETRY_S = 1.0  # connect / model definition request retry and keep-alive period


class NatNetClient:
    """An OptiTrack Motive (NatNet 3.x/4.x) client: ``Pose`` per rigid body, ``BodySkeleton`` per skeleton.

    Command channel: NAT_CONNECT to ``server:command_port`` (retried each second until the
    NAT_SERVERINFO reply gives the bitstream version and clock frequency), then
    NAT_REQUEST_MODELDEF for names (again whenever a frame names an unknown id or Motive flags
    a changed asset list); in unicast mode a keep-alive each second. Data channel: frames on the
    multicast group (Motive's default ``239.255.42.99:1511``) or, with ``multicast_group=None``,
    unicast to ``local_address:data_port``; frames arriving on the command socket are taken too.

    Stamps: ``device_ns`` = camera mid-exposure in the server clock (high-resolution ticks
    converted with its frequency; Motive's ``timestamp`` when absent); ``capture_ns`` =
    ``device_ns`` + a :class:`~telerig.ir.clock.ClockOffsetEstimator` offset fitted on (transmit
    time, arrival) over 5 s, restarting on a jump over 1 s (a server restart), so the server's own
    latency is not counted twice. Frames before the model definitions arrive are dropped
    (``awaiting_models``) for ``connect_timeout_s``, then streamed under id-based names.
    ``stats`` counts frames, samples and drops per reason, and ``frames_missed``: frames the
    transport lost, from forward jumps of Motive's frame number (a full receive buffer after a
    stall, a lossy network). Both sockets ask for a 1 MiB receive buffer (~7 s of frames at
    120 Hz; the kernel caps it at ``net.core.rmem_max``), since unicast frames may arrive on
    either.
    """

    def __init__(
        self,
        id: str = "mocap0",
        *,
        server: str = "127.0.0.1",
        command_port: int = PORT_COMMAND,
        data_port: int = PORT_DATA,
        multicast_group: str | None = None,
        local_address: str = "0.0.0.0",
        version: str | None = None,
        mount: MountTransform | None = None,
        frame_id: str = "mocap",
        skeleton_coordinates: str = "global",
        max_range_m: float = 100.0,
        connect_timeout_s: float = 2.0,
    ) -> None:
        """Args:
        id: Device id, prefix of the source ids ``"<id>/<rigid body or skeleton name>"``.
        server: Motive host (IPv4).
        command_port: Motive's command port (1510).
        data_port: Data port to listen on (1511; 0 picks a free one, see :attr:`data_address`).
        multicast_group: Group to join for data, or None for unicast data.
        local_address: Interface address to bind (and to join the group on).
        version: Bitstream version, e.g. ``"4.1"``; None takes the server's from NAT_SERVERINFO.
        mount: Motive world -> output frame (default: Y up, +Z forward).
        frame_id: Frame name of the samples.
        skeleton_coordinates: Motive's streaming setting, ``"global"`` or ``"local"``.
        max_range_m: Largest accepted |coordinate| [m].
        connect_timeout_s: How long frames wait for the model definitions [s].
        """
        self._id = id
        self._server = server
        self._command_port = command_port
        self._data_port = data_port
        self._group = multicast_group
        self._local = local_address
        self._fixed_version = NatNetVersion.parse(version) if version is not None else None
        self._connect_timeout_ns = int(connect_timeout_s * 1e9)
        self._normalizer = FrameNormalizer(
            id,
            mount=mount,
            frame_id=frame_id,
            skeleton_coordinates=skeleton_coordinates,
            max_range_m=max_range_m,
        )
        self._lock = threading.Lock()  # guards _stats
        self._worker = DeviceWorker(id, kind="NatNet client", thread_name=f"telerig-natnet-{id}", log=_log)
        self._sockets: list[socket.socket] = []
        self._stats: Counter[str] = Counter()
        self._version: NatNetVersion | None = self._fixed_version
        self._clock_hz = 0
        self._offset = ClockOffsetEstimator(5_000_000_000, reset_ns=1_000_000_000)
        self._want_models = True
        self._last_frame: int | None = None
        #: Set once NAT_SERVERINFO and NAT_MODELDEF have both arrived.
        self.connected = threading.Event()
        self.data_address: tuple[str, int] | None = None

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def stats(self) -> Mapping[str, int]:
        """Counters: ``frames``, ``samples``, ``model_definitions`` and drops per reason (a snapshot)."""
        with self._lock:
            return {**self._stats, "samples": self._worker.samples}

    @property
    def version(self) -> NatNetVersion | None:
        """Bitstream version in use (None until the server answered, unless fixed)."""
        return self._version

    def start(self, sink: SampleSink) -> None:
        """Open the sockets and stream samples into ``sink`` from a new thread.

        Raises:
            DeviceError: already running, or a socket cannot be opened (port in use, bad address).
        """
        with self._worker.starting() as launch:
            try:
                command, data = self._open()
            except OSError as exc:
                raise DeviceError(
                    f"NatNet client '{self._id}': cannot open sockets ({exc}); check local_address "
                    f"{self._local!r}, data_port {self._data_port} and multicast_group {self._group!r}"
                ) from None
            self._sockets = [command, data]
            self.connected.clear()
            launch(self._run, sink, command, data)

    def stop(self) -> None:
        """Stop streaming, join the thread and close the sockets. Idempotent."""
        self._worker.stop()
        for s in self._sockets:
            s.close()
        self._sockets = []

    def _open(self) -> tuple[socket.socket, socket.socket]:
        command = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        data = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            for sock in (command, data):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            command.bind((self._local, 0))
            data.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if self._group is not None:
                data.bind(("", self._data_port))
                mreq = socket.inet_aton(self._group) + socket.inet_aton(self._local)
                data.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
            else:
                data.bind((self._local, self._data_port))
        except OSError:
            command.close()
            data.close()
            raise
        host, port = data.getsockname()[:2]
        self.data_address = (str(host), int(port))
        return command, data

    def _count(self, key: str, n: int = 1) -> None:
        with self._lock:
            self._stats[key] += n

    def _run(
        self, sink: SampleSink, command: socket.socket, data: socket.socket, stop: threading.Event
    ) -> None:
        target = (self._server, self._command_port)
        sel = selectors.DefaultSelector()
        sel.register(command, selectors.EVENT_READ)
        sel.register(data, selectors.EVENT_READ)
        started = time.monotonic_ns()
        last_connect = last_request = last_keepalive = -math.inf
        self._want_models = True
        try:
            while not stop.is_set():
                now = time.monotonic()
                try:
                    if self._clock_hz == 0 and now - last_connect > _RETRY_S:
                        command.sendto(encode_connect(), target)
                        last_connect = now
                    if self._want_models and now - last_request > _RETRY_S:
                        command.sendto(encode_packet(NAT_REQUEST_MODELDEF), target)
                        last_request = now
                    if self._group is None and now - last_keepalive > _RETRY_S:
                        command.sendto(encode_packet(NAT_KEEPALIVE), target)
                        last_keepalive = now
                except OSError as exc:
                    self._count("send_error")
                    _log.debug("%s: send to %s failed: %s", self._id, target, exc)
                for key, _ in sel.select(timeout=0.1):
                    sock = key.fileobj
                    assert isinstance(sock, socket.socket)
                    try:
                        packet = sock.recv(65536)
                    except OSError:
                        self._count("receive_error")
                        continue
                    waiting = time.monotonic_ns() - started < self._connect_timeout_ns
                    for sample in self._handle(packet, now_ns(), waiting):
                        self._worker.deliver(sink, sample)
        finally:
            sel.close()

    def _handle(self, packet: bytes, arrival: int, waiting: bool) -> list[Sample]:
        """Samples of one datagram (none for command replies); never raises on bad input."""
        try:
            message_id, payload = split_packet(packet)
            if message_id == NAT_FRAMEOFDATA:
                return self._frame(payload, arrival, waiting)
            if message_id == NAT_SERVERINFO:
                info = parse_server_info(payload)
                if self._fixed_version is None:
                    self._version = info.version
                self._clock_hz = info.high_res_clock_hz or -1
                self._count("server_info")
            elif message_id == NAT_MODELDEF:
                if self._version is None:
                    self._count("awaiting_server_info")
                    return []
                self._normalizer.set_models(parse_model_definitions(payload, self._version))
                self._want_models = False
                self._count("model_definitions")
            else:
                self._count("other_message")
            if self._clock_hz != 0 and self._normalizer.has_models:
                self.connected.set()
        except WireError as exc:
            self._count("malformed")
            _log.debug("%s: dropped malformed packet: %s", self._id, exc)
        return []

    def _frame(self, payload: memoryview, arrival: int, waiting: bool) -> list[Sample]:
        version = self._version
        if version is None:
            self._count("awaiting_server_info")
            return []
        frame = parse_frame(payload, version)
        self._count("frames")
        last, self._last_frame = self._last_frame, frame.frame_number
        if last is not None and frame.frame_number > last + 1:
            self._count("frames_missed", frame.frame_number - last - 1)
        if frame.tracked_models_changed or self._normalizer.unknown_ids(frame):
            if not self._want_models:
                self._count("models_requested")
            self._want_models = True
        if not self._normalizer.has_models and waiting:
            self._count("awaiting_models")
            return []
        device_ns, sent_ns = self._device_times(frame)
        offset = self._offset.update(sent_ns, arrival)
        samples, drops = self._normalizer.normalize(frame, device_ns, device_ns + offset)
        with self._lock:
            self._stats.update(drops)
        return samples

    def _device_times(self, frame: MocapFrame) -> tuple[int, int]:
        """(mid-exposure, transmit) in the server clock [ns]."""
        hz = self._clock_hz
        if hz > 0 and frame.stamp_camera_mid_exposure > 0:
            mid = frame.stamp_camera_mid_exposure * 1_000_000_000 // hz
            sent = frame.stamp_transmit * 1_000_000_000 // hz if frame.stamp_transmit > 0 else mid
            return mid, max(sent, mid)
        t = round(frame.timestamp * 1e9)
        return t, t


class BvhPlayer:
    """Plays a BVH file as ``BodySkeleton`` samples with the file's frame timing.

    Joint positions [m] and orientations are in ``frame_id`` with the operator axes (x forward,
    y left, z up) through ``mount`` (default: BVH's Y up, +Z forward). ``scale`` converts file
    units to metres; None detects mm / cm / inch / the CMU database's unit / m from the body's
    proportions (see :func:`detect_scale`). With ``normalize_names`` the shoulder, elbow, wrist and hip
    joints, found by the skeleton's structure, take their CMU names (``RightArm``, ``RightForeArm``,
    ``RightHand``, ``RightUpLeg``, ...; see :func:`~telerig.devices.mocap.bvh.cmu_renames`) whatever the
    file calls them, so the humanoid retargeter reads every file the same way.
    Frames are emitted on the device's own thread on an absolute schedule
    ``t0 + k * frame_time / speed``; stamps: source ``"<id>/body"``, ``seq`` increasing,
    ``device_ns`` = file time of the frame (+ one clip length per loop), ``capture_ns`` = the moment
    the frame fell due on that schedule (common clock; a late thread's owed frames keep their spacing).
    """

    def __init__(
        self,
        path: Path | str,
        *,
        id: str = "bvh0",
        speed: float = 1.0,
        loop: bool = False,
        scale: float | None = None,
        up_axis: str = "+y",
        forward_axis: str = "+z",
        yaw_deg: float = 0.0,
        offset: tuple[float, float, float] = (0.0, 0.0, 0.0),
        frame_id: str = "mocap",
        include_end_sites: bool = True,
        normalize_names: bool = True,
    ) -> None:
        """Args:
        path: BVH file.
        id: Device id.
        speed: Playback speed factor (> 0).
        loop: Start over after the last frame, until :meth:`stop`.
        scale: File units to metres, or None to detect.
        up_axis: File axis pointing up.
        forward_axis: File axis the performer faces.
        yaw_deg: Extra yaw about the output z axis [deg].
        offset: Translation added in the output frame [m].
        frame_id: Frame name of the samples.
        include_end_sites: Emit End Sites as joints named ``"<parent>_end"``.
        normalize_names: Name the arm and hip joints found by structure with their CMU names.
        """
        if not (math.isfinite(speed) and speed > 0.0):
            raise DeviceError(f"bvh '{id}': speed must be a finite factor > 0, got {speed}")
        self._path = Path(path)
        if not self._path.is_file():
            raise DeviceError(f"bvh '{id}': file {self._path} does not exist")
        self._id = id
        self._speed = speed
        self._loop = loop
        self._scale = scale
        self._axes = (up_axis, forward_axis, yaw_deg, offset)
        MountTransform(up=up_axis, forward=forward_axis, yaw_deg=yaw_deg, offset=offset)  # validate now
        self._frame_id = frame_id
        self._end_sites = include_end_sites
        self._normalize = normalize_names
        self.source_id = f"{id}/body"
        self._clip: BvhClip | None = None
        self._frames: list[BodySkeleton] | None = None
        self._worker = DeviceWorker(id, kind="bvh", thread_name=f"telerig-bvh-{id}", log=_log)
        #: Samples emitted since :meth:`start` (all passes).
        self.emitted = 0

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def running(self) -> bool:
        """Whether the emitting thread is running."""
        return self._worker.running

    def clip(self) -> BvhClip:
        """The parsed file (parsed once). Raises DeviceError if it is not valid BVH."""
        if self._clip is None:
            try:
                text = self._path.read_text(encoding="utf-8", errors="replace")
                self._clip = parse_bvh(text)
            except (OSError, WireError) as exc:
                raise DeviceError(f"bvh '{self._id}': {self._path}: {exc}") from None
        return self._clip

    def frames(self) -> list[BodySkeleton]:
        """Every frame as a ``BodySkeleton`` with file-time stamps (see :meth:`BvhClip.skeletons`)."""
        if self._frames is None:
            clip = self.clip()
            up, forward, yaw, offset = self._axes
            scale = self._scale if self._scale is not None else detect_scale(clip, up)
            mount = MountTransform(up=up, forward=forward, yaw_deg=yaw, offset=offset, scale=scale)
            rename = cmu_renames(clip, up, forward) if self._normalize else None
            try:
                self._frames = clip.skeletons(
                    self.source_id,
                    mount=mount,
                    frame_id=self._frame_id,
                    include_end_sites=self._end_sites,
                    rename=rename,
                )
            except WireError as exc:
                raise DeviceError(f"bvh '{self._id}': {self._path}: {exc}") from None
        return self._frames

    def start(self, sink: SampleSink) -> None:
        """Load the clip and emit its frames into ``sink`` from a new thread.

        Raises:
            DeviceError: already running, or the file is not valid BVH.
        """
        frames = self.frames()
        with self._worker.starting() as launch:
            self.emitted = 0
            launch(self._run, frames, sink)

    def stop(self) -> None:
        """Stop emitting and join the thread. Idempotent."""
        self._worker.stop()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until a non-looping playback has ended; ``timeout`` [s]. True when done."""
        return self._worker.wait(timeout)

    def _run(self, frames: list[BodySkeleton], sink: SampleSink, stop: threading.Event) -> None:
        clip = self.clip()
        period = clip.frame_time_s / self._speed
        cycle_ns = round(clip.duration_s * 1e9)
        clock = PlaybackClock()
        k = 0  # frames emitted, all passes
        seq = 0
        while True:
            for frame in frames:
                due_ns = clock.wait(k * period, stop)
                if due_ns is None:
                    return
                n_pass = k // len(frames)
                stamp = dataclasses.replace(
                    frame.stamp,
                    seq=seq,
                    device_ns=frame.stamp.device_ns + n_pass * cycle_ns,
                    capture_ns=due_ns,
                )
                self._worker.deliver(sink, dataclasses.replace(frame, stamp=stamp))
                self.emitted += 1
                seq += 1
                k += 1
            if not self._loop:
                return
