"""The native VR stream device: receives VrFrame datagrams on a UDP port and emits IR samples."""

from __future__ import annotations

import logging
import socket
import threading

from telerig.devices.base import SampleSink
from telerig.devices.udp_vr.protocol import (
    MAX_DATAGRAM_BYTES,
    SequenceFilter,
    datagram_samples,
    decode_datagram,
)
from telerig.devices.worker import DeviceWorker
from telerig.errors import DeviceError, WireError
from telerig.ir.clock import ClockOffsetEstimator
from telerig.ir.types import Stamp, now_ns

__all__ = ["DEFAULT_PORT", "UdpVrDevice"]

_log = logging.getLogger(__name__)

#: Default UDP port of the native VR stream.
DEFAULT_PORT = 9870
# How often the receive loop wakes up to notice stop() [s].
_POLL_S = 0.05


class UdpVrDevice:
    """Receives the native VR stream (``telerig/v1/vr_stream.proto``) on a UDP socket.

    Emits, per accepted datagram and tracked part: the head ``Pose``, a ``ControllerState`` per
    controller and a ``HandPose`` per hand, all in the operator frame (x forward, y left, z up,
    metres; see :mod:`telerig.devices.udp_vr.protocol`), with source ids ``"<id>/head"``,
    ``"<id>/left"``, ``"<id>/right"``, ``"<id>/left_hand"``, ``"<id>/right_hand"``.

    Stamps: ``device_ns`` is the sender's ``device_time_ns`` (the receive time if it sends 0);
    ``capture_ns = device_ns + offset`` with the offset from
    :class:`~telerig.ir.clock.ClockOffsetEstimator` (the windowed minimum of arrival - device);
    ``arrival_ns`` is the receive time; ``seq`` counts samples per source from 0.

    The socket binds ``host:port`` at :meth:`start`; the default 127.0.0.1 only hears the local
    machine (tests, a fake sender): a lab binds the host's LAN address (or ``0.0.0.0``) so the
    headset on the Wi-Fi can reach it. Bad datagrams never stop the device: they are counted in
    :attr:`stats` by reason (``malformed``, ``oversize``, ``duplicate``, ``reordered``, ``stale``)
    next to ``received``, ``accepted``, ``samples``, ``lost``, ``restart`` and ``sink_error``.
    """

    def __init__(
        self,
        id: str = "vr0",
        *,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        frame_id: str = "operator",
        clock_window_s: float = 6.0,
    ) -> None:
        """Args:
        id: Device id, the prefix of the source ids.
        host: Address to bind; 127.0.0.1 for local senders, the LAN address for a headset.
        port: UDP port to bind, 0 for any free port (read it from :attr:`address` after start).
        frame_id: Frame id the operator-frame samples are labelled with.
        clock_window_s: Window the clock offset minimum is taken over [s] (> 0); 6 s holds about
            512 datagrams at 90 Hz.
        """
        if not 0 <= port <= 65535:
            raise DeviceError(f"port must be in [0, 65535], got {port}")
        self._id = id
        self.host = host
        self.port = port
        self.frame_id = frame_id
        if not clock_window_s > 0:
            raise DeviceError(f"clock_window_s must be > 0, got {clock_window_s}")
        self.clock = ClockOffsetEstimator(max(1, round(clock_window_s * 1e9)))
        self.sequence = SequenceFilter()
        self.stats: dict[str, int] = dict.fromkeys(
            (
                "received",
                "accepted",
                "samples",
                "malformed",
                "oversize",
                "duplicate",
                "reordered",
                "stale",
                "lost",
                "restart",
                "sink_error",
            ),
            0,
        )
        self.last_error = ""
        self._seqs: dict[str, int] = {}
        self._sock: socket.socket | None = None
        self._address: tuple[str, int] | None = None
        self._worker = DeviceWorker(id, kind="udp_vr device", thread_name=f"telerig-udp-vr-{id}", log=_log)

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def address(self) -> tuple[str, int]:
        """The bound ``(host, port)``.

        Raises:
            DeviceError: If the device has not been started.
        """
        if self._address is None:
            raise DeviceError(f"udp_vr device '{self._id}' is not started; call start() first")
        return self._address

    @property
    def running(self) -> bool:
        """Whether the receive thread is running."""
        return self._worker.running

    def start(self, sink: SampleSink) -> None:
        """Bind the socket and deliver samples into ``sink`` from a new thread.

        Raises:
            DeviceError: If already running, or the address cannot be bound.
        """
        with self._worker.starting() as launch:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                sock.bind((self.host, self.port))
            except OSError as exc:
                sock.close()
                raise DeviceError(
                    f"udp_vr device '{self._id}' cannot bind {self.host}:{self.port} ({exc.strerror}); "
                    "pick a free port or an address of this host"
                ) from None
            sock.settimeout(_POLL_S)
            bound = sock.getsockname()
            self._sock, self._address = sock, (str(bound[0]), int(bound[1]))
            launch(self._run, sock, sink)
        _log.info("%s: listening for VR datagrams on udp://%s:%d", self._id, *self._address)

    def stop(self) -> None:
        """Stop receiving, join the thread and close the socket. Idempotent."""
        self._worker.stop()
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def __enter__(self) -> UdpVrDevice:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def handle(self, data: bytes, arrival_ns: int, sink: SampleSink) -> None:
        """Process one received datagram (what the receive thread does; public for replay and tests).

        Args:
            data: The UDP payload.
            arrival_ns: Receive time in the common clock [ns].
            sink: Where the samples go.
        """
        stats = self.stats
        stats["received"] += 1
        if len(data) > MAX_DATAGRAM_BYTES:
            stats["oversize"] += 1
            self._note("oversize", f"datagram over {MAX_DATAGRAM_BYTES} bytes")
            return
        try:
            datagram = decode_datagram(data)
        except WireError as exc:
            stats["malformed"] += 1
            self._note("malformed", str(exc))
            return
        verdict = self.sequence.accept(datagram.stream_id, datagram.seq)
        counts = self.sequence.counts
        stats["lost"] = counts["lost"]
        stats["restart"] = counts["restart"]
        if verdict not in ("accepted", "restart"):
            stats[verdict] += 1
            return
        if verdict == "restart":
            self.clock.reset()
        stats["accepted"] += 1
        device_ns = datagram.device_ns or arrival_ns
        capture_ns = device_ns + self.clock.update(device_ns, arrival_ns)
        seqs = self._seqs
        prefix = self._id

        def stamp(suffix: str, confidence: float) -> Stamp:
            source = f"{prefix}/{suffix}"
            seq = seqs.get(source, 0)
            seqs[source] = seq + 1
            return Stamp(source, seq, device_ns, capture_ns, arrival_ns, confidence)

        worker = self._worker
        for sample in datagram_samples(datagram, stamp, self.frame_id):
            worker.deliver(sink, sample)
        stats["samples"] = worker.samples
        stats["sink_error"] = worker.sink_errors

    def _note(self, reason: str, message: str) -> None:
        self.last_error = message
        if self.stats[reason] == 1:  # log the first of each kind; the counters tell the rest
            _log.warning("%s: dropped a %s datagram: %s", self._id, reason, message)

    def _run(self, sock: socket.socket, sink: SampleSink, stop: threading.Event) -> None:
        bufsize = MAX_DATAGRAM_BYTES + 1  # one more byte, so an oversize datagram shows as such
        while not stop.is_set():
            try:
                data = sock.recv(bufsize)
            except (TimeoutError, ConnectionResetError):  # the latter: ICMP port unreachable on Windows
                continue
            except OSError:
                if stop.is_set():  # closed by stop()
                    return
                _log.exception("%s: receive failed; stopping", self._id)
                return
            self.handle(data, now_ns(), sink)
