"""A device that plays back a recorded stream from an episode MCAP with its original timing."""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
from collections.abc import Iterator
from pathlib import Path

from telerig.devices.base import SampleSink
from telerig.devices.worker import DeviceWorker, PlaybackClock
from telerig.errors import DeviceError, RecordingError, WireError
from telerig.ir.mcap_log import read_log
from telerig.ir.types import Sample

__all__ = ["ReplayDevice"]

_log = logging.getLogger(__name__)


class ReplayDevice:
    """Re-emits the samples of one recorded device stream, paced by their capture times.

    The stream is the samples of ``topic`` and/or ``source_id`` in the MCAP (with neither, the
    file must hold exactly one source). Samples are emitted in capture-time order on the device's
    own thread on an absolute schedule ``t0 + (capture_ns - first capture_ns) / speed``, so
    timing does not drift. Each emitted sample is restamped: ``capture_ns`` = the moment it fell due
    on that schedule (common clock; a late thread's owed samples keep their spacing),
    ``arrival_ns`` = 0; ``source_id``, ``device_ns``, ``seq`` and ``confidence`` are kept from the
    recording. With ``loop``, pass k (from 0) shifts ``seq`` by k x (seq span + 1) and
    ``device_ns`` by k x the cycle length, so both keep increasing.

    :meth:`samples` gives the recorded samples without timing, for tests and tools.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        topic: str | None = None,
        source_id: str | None = None,
        speed: float = 1.0,
        loop: bool = False,
        id: str = "replay",
    ) -> None:
        """Args:
        path: Episode MCAP file (a crashed one without footer works too).
        topic: Only samples recorded on this topic.
        source_id: Only samples with this ``stamp.source_id``.
        speed: Playback speed factor (> 0); 2 plays twice as fast.
        loop: Start over after the last sample, until :meth:`stop`.
        id: Device id.
        """
        if not (math.isfinite(speed) and speed > 0.0):
            raise ValueError(f"speed must be a finite factor > 0, got {speed}")
        self._path = Path(path)
        if not self._path.is_file():
            raise DeviceError(f"replay '{id}': recording {self._path} does not exist")
        self._topic = topic
        self._source_id = source_id
        self._speed = speed
        self._loop = loop
        self._id = id
        self._recorded: tuple[Sample, ...] | None = None
        self._worker = DeviceWorker(id, kind="replay", thread_name=f"telerig-replay-{id}", log=_log)
        #: Samples emitted since :meth:`start` (all passes).
        self.emitted = 0

    @property
    def id(self) -> str:
        """Device id."""
        return self._id

    @property
    def running(self) -> bool:
        """Whether the emitting thread is running (false once a non-looping replay has ended)."""
        return self._worker.running

    def samples(self) -> Iterator[Sample]:
        """The recorded samples of the stream, in replay order, with their recorded stamps, untimed.

        Raises:
            DeviceError: the file cannot be read or holds no matching samples.
        """
        return iter(self._load())

    def start(self, sink: SampleSink) -> None:
        """Load the stream and emit it into ``sink`` from a new thread.

        Raises:
            DeviceError: already running, unreadable file, no matching samples, or ``loop``
                on a stream of zero duration.
        """
        recorded = self._load()
        if self._loop and recorded[-1].stamp.capture_ns == recorded[0].stamp.capture_ns:
            raise DeviceError(f"replay '{self._id}': cannot loop a stream of zero duration")
        with self._worker.starting() as launch:
            self.emitted = 0
            launch(self._run, recorded, sink)

    def stop(self) -> None:
        """Stop emitting and join the thread. Idempotent."""
        self._worker.stop()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until a non-looping replay has emitted everything; ``timeout`` [s]. True when done."""
        return self._worker.wait(timeout)

    def _load(self) -> tuple[Sample, ...]:
        if self._recorded is not None:
            return self._recorded
        topics = None if self._topic is None else [self._topic]
        sources: dict[str, set[str]] = {}
        picked: list[Sample] = []
        try:
            for entry in read_log(self._path, topics=topics):
                sid = entry.sample.stamp.source_id
                sources.setdefault(sid, set()).add(entry.topic)
                if self._source_id is None or sid == self._source_id:
                    picked.append(entry.sample)
        except (RecordingError, WireError) as exc:
            raise DeviceError(f"replay '{self._id}': {exc}") from None
        where = f"{self._path}" + (f" topic {self._topic}" if self._topic else "")
        if not picked:
            available = ", ".join(
                f"{sid} ({', '.join(sorted(tops))})" for sid, tops in sorted(sources.items())
            )
            wanted = f"source_id {self._source_id!r}" if self._source_id else "samples"
            raise DeviceError(
                f"replay '{self._id}': no {wanted} in {where}. Available sources: {available or 'none'}"
            )
        if self._source_id is None and len(sources) > 1:
            raise DeviceError(
                f"replay '{self._id}': {where} holds {len(sources)} sources "
                f"({', '.join(sorted(sources))}); set source_id or topic"
            )
        picked.sort(key=lambda s: s.stamp.capture_ns)  # stable: file order among equal times
        self._recorded = tuple(picked)
        return self._recorded

    def _run(self, recorded: tuple[Sample, ...], sink: SampleSink, stop: threading.Event) -> None:
        first_ns = recorded[0].stamp.capture_ns
        span_ns = recorded[-1].stamp.capture_ns - first_ns
        # One pass lasts the span plus one mean sample period, so the loop seam keeps the rate.
        cycle_ns = span_ns + (span_ns // (len(recorded) - 1) if len(recorded) > 1 else 0)
        seqs = [s.stamp.seq for s in recorded]
        seq_step = max(seqs) - min(seqs) + 1
        clock = PlaybackClock()
        k = 0
        while True:
            for sample in recorded:
                stamp = sample.stamp
                due_ns = clock.wait((k * cycle_ns + stamp.capture_ns - first_ns) / 1e9 / self._speed, stop)
                if due_ns is None:
                    return
                new_stamp = dataclasses.replace(
                    stamp,
                    capture_ns=due_ns,
                    arrival_ns=0,
                    seq=stamp.seq + k * seq_step,
                    device_ns=stamp.device_ns + k * cycle_ns,
                )
                self._worker.deliver(sink, dataclasses.replace(sample, stamp=new_stamp))
                self.emitted += 1
            if not self._loop:
                return
            k += 1
