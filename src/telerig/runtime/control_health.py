"""A control node's live input-to-actuation latency, on its robot's retained ``health`` topic (~2 Hz).

The control loop feeds two :class:`~telerig.runtime.metrics.LatencyWindow` rings (two integer stores
per applied command, nothing else on the tick); a reporting thread of this class computes their
rolling percentiles and publishes one small JSON document every ``period_s``, on the same retained
``health`` stream the device nodes and recorders report on, so the control center reads it with the
rest of the rig's health (``telerig/v1/<rig>/<robot>/health``):

.. code-block:: json

    {"type": "control_latency", "robot": "arm0", "time_ns": 0, "window_s": 2.0, "period_s": 0.5,
     "budget_ms": 20.0, "hold_ms": 100.0,
     "input_to_command": {"count": 200, "p50_ms": 1.1, "p99_ms": 2.4, "max_ms": 3.0},
     "input_to_state": {"count": 199, "p50_ms": 11.0, "p99_ms": 12.9, "max_ms": 13.1}}

* ``input_to_command``: the device sample's capture time (its IR ``Stamp.capture_ns``) to the
  command the driver applied for it (the driver's stamp of what it sent), per applied command
  (safety status ``ok`` or ``limited``): the same value the episode manifest's latency has.
* ``input_to_state``: the same capture time to the first measured joint state the driver stamped
  at or after that command, as the control loop next reads it (so it includes the wait for the next
  tick): where the robot is seen to have taken the command. Counted only for drivers whose state
  stamps move with their measurements.
* ``budget_ms``: the p99 the dashboard shows green; ``hold_ms``: the input age at which the safety
  chain holds the robot (beyond it the operator is no longer in control).
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable

from telerig.bus.base import Bus
from telerig.bus.catalogue import HEALTH
from telerig.bus.topics import Topic, qos_for
from telerig.ir.types import now_ns
from telerig.runtime.metrics import LatencyWindow

__all__ = ["DEFAULT_BUDGET_MS", "REPORT_TYPE", "ControlHealth"]

log = logging.getLogger(__name__)

#: Default input-to-command p99 budget [ms]: a loaded 2-core host keeps p99 under ~15 ms
#: (README, fleet benchmark); past it the operator starts to feel the robot lag.
DEFAULT_BUDGET_MS = 20.0
#: The ``type`` of the document, so a reader tells it from a device's or a recorder's health.
REPORT_TYPE = "control_latency"


class ControlHealth:
    """Rolling input-to-command and input-to-state latency of one robot, published at a bounded rate.

    :meth:`sent` and :meth:`measured` are called by the control thread only (no allocation: integer
    stores); :meth:`start` runs the reporting thread, :meth:`stop` ends it and publishes a last report.

    Args:
        rig: Rig name.
        robot: Robot id (the topic's node).
        bus: Bus to publish on.
        budget_ms: Input-to-command p99 shown green [ms] (> 0).
        hold_ms: Input age at which the safety chain holds [ms] (> 0).
        window_s: Rolling window of the percentiles [s] (> 0).
        period_s: Report period [s] (> 0); 0.5 s is 2 Hz.
        capacity: Ring size of each window.
        clock: Common-clock time [ns] of the report (the control loop stamps values with its tick's).
    """

    def __init__(
        self,
        rig: str,
        robot: str,
        bus: Bus,
        *,
        budget_ms: float = DEFAULT_BUDGET_MS,
        hold_ms: float = 100.0,
        window_s: float = 2.0,
        period_s: float = 0.5,
        capacity: int = 4096,
        clock: Callable[[], int] = now_ns,
    ) -> None:
        for name, value in (("budget_ms", budget_ms), ("hold_ms", hold_ms), ("period_s", period_s)):
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value}")
        self.robot = robot
        self.topic = str(Topic(rig, robot, HEALTH))
        self.budget_ms = float(budget_ms)
        self.hold_ms = float(hold_ms)
        self.period_s = float(period_s)
        self.command = LatencyWindow(window_s, capacity)
        self.state = LatencyWindow(window_s, capacity)
        self._bus = bus
        self._clock = clock
        self._pending_capture_ns = 0  # input of the last applied command not yet seen in a state
        self._pending_sent_ns = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        #: Reports published (the bounded rate is checkable).
        self.published = 0

    # --- control thread --------------------------------------------------------------------------

    def sent(self, capture_ns: int, sent_ns: int, tick_ns: int) -> None:
        """An applied command: its input's capture time, the driver's stamp of it, the tick's time [ns]."""
        self.command.add(sent_ns - capture_ns, tick_ns)
        self._pending_capture_ns = capture_ns
        self._pending_sent_ns = sent_ns

    def measured(self, state_ns: int, tick_ns: int) -> None:
        """A measured state stamped ``state_ns`` [ns]: the first one at or after the pending command
        closes its input-to-state latency."""
        if self._pending_capture_ns and state_ns >= self._pending_sent_ns:
            self.state.add(state_ns - self._pending_capture_ns, tick_ns)
            self._pending_capture_ns = 0

    # --- reporting -------------------------------------------------------------------------------

    def report(self, now: int | None = None) -> dict[str, object]:
        """The current report (what :meth:`publish` sends)."""
        t = self._clock() if now is None else now
        return {
            "type": REPORT_TYPE,
            "robot": self.robot,
            "time_ns": t,
            "window_s": self.command.window_ns / 1e9,
            "period_s": self.period_s,
            "budget_ms": self.budget_ms,
            "hold_ms": self.hold_ms,
            "input_to_command": self.command.summary(t).to_json(),
            "input_to_state": self.state.summary(t).to_json(),
        }

    def publish(self) -> None:
        """Publish the current report on the robot's retained health topic."""
        payload = json.dumps(self.report(), separators=(",", ":")).encode()
        qos, retain = qos_for(HEALTH)
        self._bus.publish(self.topic, payload, qos=qos, retain=retain)
        self.published += 1

    def start(self) -> None:
        """Start the reporting thread; idempotent."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name=f"health-{self.robot}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the reporting thread and publish a last report; idempotent."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stop.set()
        thread.join(timeout=5.0)
        self._publish_quietly()

    def _loop(self) -> None:
        while not self._stop.wait(self.period_s):
            self._publish_quietly()

    def _publish_quietly(self) -> None:
        try:
            self.publish()
        except Exception:
            log.exception("latency report of %s failed", self.robot)
