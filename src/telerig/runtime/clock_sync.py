"""Station → coordinator clock offset and drift from NTP-style exchanges over the bus."""

from __future__ import annotations

import json
import logging
import math
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType

from telerig.bus.base import Bus, Message, Subscription
from telerig.bus.catalogue import CLOCK_PING, CLOCK_PONG
from telerig.bus.jsonpayload import parse_json_object
from telerig.bus.topics import Topic
from telerig.errors import TelerigError, WireError
from telerig.ir.types import now_ns

__all__ = [
    "CLOCK_PING",
    "CLOCK_PONG",
    "Clock",
    "ClockEstimate",
    "ClockSample",
    "ClockSync",
    "ClockSyncClient",
    "ClockSyncServer",
    "offset_clock",
]

log = logging.getLogger(__name__)

#: A clock: returns the current time [ns] (e.g. ``time.time_ns``).
Clock = Callable[[], int]

# The streams (CLOCK_PING, CLOCK_PONG, from the catalogue): station → coordinator requests
# {"seq", "t1"} on telerig/v1/<rig>/<station>/clock_ping, replies {"seq", "t1", "t2", "t3"} on .../clock_pong.


def offset_clock(offset_ns: int, base: Clock = now_ns) -> Clock:
    """A clock reading ``base() + offset_ns`` [ns]: a fake station clock for tests and demos."""

    def clock() -> int:
        return base() + offset_ns

    return clock


@dataclass(frozen=True, slots=True)
class ClockSample:
    """One exchange: ``t1`` station send, ``t2`` coordinator receive, ``t3`` coordinator send, ``t4`` station
    receive [ns]; ``t1``/``t4`` in the station clock, ``t2``/``t3`` in the coordinator clock."""

    t1: int
    t2: int
    t3: int
    t4: int

    @property
    def offset_ns(self) -> int:
        """Coordinator minus station clock [ns], exact if both legs take equally long."""
        return ((self.t2 - self.t1) + (self.t3 - self.t4)) // 2

    @property
    def delay_ns(self) -> int:
        """Round-trip time on the wire, the coordinator's turnaround excluded [ns]; |error| <= delay / 2."""
        return (self.t4 - self.t1) - (self.t3 - self.t2)

    @property
    def local_ns(self) -> int:
        """Midpoint of the exchange in the station clock [ns]."""
        return (self.t1 + self.t4) // 2


@dataclass(frozen=True, slots=True)
class ClockEstimate:
    """A snapshot of :class:`ClockSync`.

    ``coordinator_ns = local_ns + offset_ns + drift_ppm * 1e-6 * (local_ns - reference_local_ns)``.

    Attributes:
        synced: Whether at least one exchange completed (otherwise every number is 0).
        offset_ns: Coordinator minus station clock at ``reference_local_ns`` [ns].
        drift_ppm: Rate of the offset [µs/s = ppm]; 0 until the window spans ``min_drift_span_s``.
        uncertainty_ns: Error bound of ``offset_ns``: half the best round trip plus the rms fit residual [ns].
        delay_ns: Smallest round trip in the window [ns].
        samples: Exchanges in the window.
        reference_local_ns: Station-clock time the offset refers to [ns].
    """

    synced: bool
    offset_ns: int
    drift_ppm: float
    uncertainty_ns: int
    delay_ns: int
    samples: int
    reference_local_ns: int

    def offset_at(self, local_ns: int) -> int:
        """Coordinator minus station clock at station time ``local_ns`` [ns]."""
        return self.offset_ns + round(self.drift_ppm * 1e-6 * (local_ns - self.reference_local_ns))

    def as_dict(self) -> dict[str, int | float | bool]:
        """The estimate as JSON values, for the episode manifest (``extra["clock"]``)."""
        return {
            "synced": self.synced,
            "offset_ns": self.offset_ns,
            "drift_ppm": self.drift_ppm,
            "uncertainty_ns": self.uncertainty_ns,
            "delay_ns": self.delay_ns,
            "samples": self.samples,
            "reference_local_ns": self.reference_local_ns,
        }

    def as_mcap_metadata(self) -> dict[str, str]:
        """The estimate as MCAP metadata (string values), for ``McapLog.add_metadata("clock", ...)``."""
        return {k: json.dumps(v) for k, v in self.as_dict().items()}


_UNSYNCED = ClockEstimate(False, 0, 0.0, 0, 0, 0, 0)


class ClockSync:
    """Filters exchanges into an offset and drift estimate of the coordinator clock.

    The newest ``window`` exchanges (and none older than ``window_s`` before the newest) are kept;
    of those, the ``best`` with the smallest round trip (the least queueing, so the most symmetric)
    are fitted. With at least 3 of them spanning ``min_drift_span_s``, a least-squares line of offset
    against station time gives offset and drift; otherwise the single lowest-delay exchange gives the
    offset and drift is 0. Thread-safe; pure (no clock, no bus).

    Args:
        window: Exchanges kept [count] (>= 1).
        best: Lowest-delay exchanges fitted [count] (1 <= best <= window).
        window_s: Oldest exchange kept, relative to the newest [s] (> 0).
        min_drift_span_s: Station-time span the fitted exchanges need before drift is estimated [s].
    """

    def __init__(
        self, *, window: int = 64, best: int = 16, window_s: float = 120.0, min_drift_span_s: float = 10.0
    ) -> None:
        if window < 1 or not 1 <= best <= window:
            raise ValueError(f"need window >= 1 and 1 <= best <= window, got window={window}, best={best}")
        if window_s <= 0 or min_drift_span_s < 0:
            raise ValueError(
                f"need window_s > 0 and min_drift_span_s >= 0, got {window_s}, {min_drift_span_s}"
            )
        self.window = window
        self.best = best
        self._window_ns = int(window_s * 1e9)
        self._min_span_ns = int(min_drift_span_s * 1e9)
        self._samples: deque[ClockSample] = deque(maxlen=window)
        self._estimate = _UNSYNCED
        self._lock = threading.Lock()
        #: Exchanges rejected: negative delay (a clock stepped during the exchange).
        self.rejected = 0

    def add(self, sample: ClockSample) -> ClockEstimate:
        """Add one exchange and return the new estimate; one with a negative round trip is rejected."""
        with self._lock:
            if sample.delay_ns < 0:
                self.rejected += 1
                return self._estimate
            self._samples.append(sample)
            newest = sample.local_ns
            while self._samples and newest - self._samples[0].local_ns > self._window_ns:
                self._samples.popleft()
            self._estimate = self._fit()
            return self._estimate

    def reset(self) -> None:
        """Forget every exchange (the station clock stepped)."""
        with self._lock:
            self._samples.clear()
            self._estimate = _UNSYNCED

    @property
    def estimate(self) -> ClockEstimate:
        """The current estimate (``synced`` False before the first exchange)."""
        return self._estimate

    @property
    def synced(self) -> bool:
        """Whether at least one exchange completed."""
        return self._estimate.synced

    @property
    def offset_ns(self) -> int:
        """Coordinator minus station clock at the newest exchange [ns]; 0 before the first."""
        e = self._estimate
        return e.offset_at(self._samples[-1].local_ns) if e.synced and self._samples else e.offset_ns

    @property
    def drift_ppm(self) -> float:
        """Rate at which the offset grows [ppm]."""
        return self._estimate.drift_ppm

    @property
    def uncertainty_ns(self) -> int:
        """Error bound of the offset [ns] (see :class:`ClockEstimate`)."""
        return self._estimate.uncertainty_ns

    def to_coordinator(self, local_ns: int) -> int:
        """Station time [ns] → coordinator time [ns].

        Raises:
            TelerigError: No exchange has completed yet; wait with :meth:`ClockSyncClient.wait_synced`.
        """
        e = self._estimate
        if not e.synced:
            raise TelerigError(
                "no clock sync exchange has completed yet; wait with ClockSyncClient.wait_synced"
            )
        return local_ns + e.offset_at(local_ns)

    def to_local(self, coordinator_ns: int) -> int:
        """Coordinator time [ns] → station time [ns] (inverse of :meth:`to_coordinator`)."""
        e = self._estimate
        if not e.synced:
            raise TelerigError(
                "no clock sync exchange has completed yet; wait with ClockSyncClient.wait_synced"
            )
        # offset depends on local time only through drift (ppm): one fixed-point step is exact to < 1 ns.
        local = coordinator_ns - e.offset_ns
        return coordinator_ns - e.offset_at(local)

    def _fit(self) -> ClockEstimate:
        chosen = sorted(self._samples, key=lambda s: s.delay_ns)[: self.best]
        min_delay = chosen[0].delay_ns
        xs = [s.local_ns for s in chosen]
        span = max(xs) - min(xs)
        if len(chosen) >= 3 and span >= max(self._min_span_ns, 1):
            ref = sum(xs) // len(xs)
            dx = [x - ref for x in xs]
            ys = [s.offset_ns for s in chosen]
            y_mean = sum(ys) / len(ys)
            sxx = sum(d * d for d in dx)
            slope = sum(d * (y - y_mean) for d, y in zip(dx, ys, strict=True)) / sxx
            residuals = [y - (y_mean + slope * d) for d, y in zip(dx, ys, strict=True)]
            offset, drift_ppm = round(y_mean), slope * 1e6
        else:
            ref = chosen[0].local_ns
            offset, drift_ppm = chosen[0].offset_ns, 0.0
            residuals = [s.offset_ns - offset for s in chosen[:1]]
        rms = math.sqrt(sum(r * r for r in residuals) / len(residuals))
        return ClockEstimate(
            synced=True,
            offset_ns=offset,
            drift_ppm=drift_ppm,
            uncertainty_ns=min_delay // 2 + round(rms),
            delay_ns=min_delay,
            samples=len(self._samples),
            reference_local_ns=ref,
        )


#: A ping or pong is a handful of integers; anything much larger is not one.
_MAX_EXCHANGE_BYTES = 1024


def _ints(payload: bytes, keys: tuple[str, ...]) -> tuple[int, ...] | None:
    try:
        data = parse_json_object(payload, max_bytes=_MAX_EXCHANGE_BYTES, max_depth=1)
        values = tuple(data[k] for k in keys)
    except (WireError, KeyError):
        return None
    ints = tuple(v for v in values if type(v) is int)
    return ints if len(ints) == len(values) else None


class ClockSyncServer:
    """The coordinator side: answers every station's ``clock_ping`` with ``t2``/``t3`` of its clock.

    Replies run on the bus delivery thread (a few µs each) so the turnaround stays short.

    Args:
        bus: A connected bus.
        rig: Rig name (topic level).
        clock: The coordinator clock [ns]; the rig's common clock by default.
    """

    def __init__(self, bus: Bus, rig: str, *, clock: Clock = now_ns) -> None:
        Topic(rig, "coordinator", CLOCK_PING)  # validates the rig name
        self._bus = bus
        self._rig = rig
        self._clock = clock
        self._sub: Subscription | None = None
        #: Pings answered, and pings dropped as malformed.
        self.answered = 0
        self.malformed = 0

    def start(self) -> ClockSyncServer:
        """Subscribe to the pings of every station. Returns ``self``."""
        if self._sub is None:
            self._sub = self._bus.subscribe(Topic.pattern(self._rig, "+", CLOCK_PING), self._on_ping)
        return self

    def close(self) -> None:
        """Stop answering. Idempotent."""
        if self._sub is not None:
            self._sub.cancel()
            self._sub = None

    def __enter__(self) -> ClockSyncServer:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def _on_ping(self, message: Message) -> None:
        t2 = self._clock()
        values = _ints(message.payload, ("seq", "t1"))
        if values is None:
            self.malformed += 1
            return
        seq, t1 = values
        station = Topic.parse(message.topic).node
        reply = {"seq": seq, "t1": t1, "t2": t2}
        reply["t3"] = self._clock()
        self._bus.publish(str(Topic(self._rig, station, CLOCK_PONG)), json.dumps(reply).encode())
        self.answered += 1


class ClockSyncClient:
    """The station side: pings the coordinator and feeds the answers to a :class:`ClockSync`.

    A thread sends ``burst`` pings ``burst_interval_s`` apart at start (a usable estimate within
    ~0.2 s), then one every ``1 / rate_hz``. An answer is matched to its ping by ``seq`` and ``t1``;
    one arriving later than ``timeout_s`` after its ping is ignored (its delay says nothing useful).

    Args:
        bus: A connected bus.
        rig: Rig name.
        station: Station id (topic node level).
        clock: The station clock [ns]; inject a fake (:func:`offset_clock`) in tests.
        rate_hz: Exchanges per second after the burst (> 0).
        burst: Exchanges at start (>= 1).
        burst_interval_s: Spacing of the burst [s].
        timeout_s: Oldest answer accepted [s].
        sync: The estimator to feed; a default :class:`ClockSync` when ``None``.
    """

    def __init__(
        self,
        bus: Bus,
        rig: str,
        station: str,
        *,
        clock: Clock = now_ns,
        rate_hz: float = 2.0,
        burst: int = 8,
        burst_interval_s: float = 0.02,
        timeout_s: float = 1.0,
        sync: ClockSync | None = None,
    ) -> None:
        if rate_hz <= 0 or burst < 1 or burst_interval_s < 0 or timeout_s <= 0:
            raise ValueError(
                f"need rate_hz > 0, burst >= 1, burst_interval_s >= 0, timeout_s > 0; got "
                f"{rate_hz}, {burst}, {burst_interval_s}, {timeout_s}"
            )
        self._bus = bus
        self._ping_topic = str(Topic(rig, station, CLOCK_PING))
        self._pong_topic = str(Topic(rig, station, CLOCK_PONG))
        self.station = station
        self.clock = clock
        self.rate_hz = rate_hz
        self.burst = burst
        self.burst_interval_s = burst_interval_s
        self._timeout_ns = int(timeout_s * 1e9)
        self.sync = sync if sync is not None else ClockSync()
        self._pending: dict[int, int] = {}  # seq -> t1
        self._lock = threading.Lock()
        self._seq = 0
        self._stop = threading.Event()
        self._synced = threading.Event()
        self._thread: threading.Thread | None = None
        self._sub: Subscription | None = None
        #: Pings sent, answers used, answers ignored (unknown, late or malformed).
        self.sent = 0
        self.received = 0
        self.ignored = 0

    @property
    def estimate(self) -> ClockEstimate:
        """The current estimate."""
        return self.sync.estimate

    def now(self) -> int:
        """The current time in the coordinator clock [ns] (the station clock read and corrected)."""
        return self.sync.to_coordinator(self.clock())

    def record(self) -> dict[str, int | float | bool | str]:
        """The estimate for the manifest and MCAP metadata: station id + :meth:`ClockEstimate.as_dict`."""
        return {"station": self.station, **self.sync.estimate.as_dict(), "exchanges": self.received}

    def start(self) -> ClockSyncClient:
        """Subscribe to answers and start pinging. Returns ``self``."""
        if self._thread is None:
            self._sub = self._bus.subscribe(self._pong_topic, self._on_pong)
            self._thread = threading.Thread(target=self._run, name=f"clock-sync-{self.station}", daemon=True)
            self._thread.start()
        return self

    def wait_synced(self, timeout_s: float | None = None) -> bool:
        """Wait until the first exchange completes; return whether it did within ``timeout_s`` [s]."""
        return self._synced.wait(timeout_s)

    def close(self) -> None:
        """Stop pinging and unsubscribe. Idempotent."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        if self._sub is not None:
            self._sub.cancel()
            self._sub = None

    def __enter__(self) -> ClockSyncClient:
        return self.start()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def ping(self) -> None:
        """Send one exchange now (also done by the thread)."""
        with self._lock:
            self._seq += 1
            seq = self._seq
            t1 = self.clock()
            self._pending[seq] = t1
            # Forget pings that will never be answered in time.
            for old in [s for s, t in self._pending.items() if t1 - t > self._timeout_ns]:
                del self._pending[old]
        self._bus.publish(self._ping_topic, json.dumps({"seq": seq, "t1": t1}).encode())
        self.sent += 1

    def _run(self) -> None:
        for _ in range(self.burst):
            if self._stop.is_set():
                return
            self.ping()
            self._stop.wait(self.burst_interval_s)
        while not self._stop.wait(1.0 / self.rate_hz):
            self.ping()

    def _on_pong(self, message: Message) -> None:
        t4 = self.clock()
        values = _ints(message.payload, ("seq", "t1", "t2", "t3"))
        if values is None:
            self.ignored += 1
            return
        seq, t1, t2, t3 = values
        with self._lock:
            sent = self._pending.pop(seq, None)
        if sent != t1 or t4 - t1 > self._timeout_ns:
            self.ignored += 1
            return
        self.sync.add(ClockSample(t1, t2, t3, t4))
        self.received += 1
        self._synced.set()
