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

The same thread breaks each applied command down into the stages of the operator loop
(:data:`telerig.config.latency.ROBOT_STAGES`: device capture → telerig receive → control node
receive → tick → retargeted → applied → first state after it; one row of seven integer stamps per
command in one more ring) and publishes their rolling p50/p99 against the rig's budgets on the
robot's retained, recorded ``latency`` stream; a stage whose p99 is over its budget raises an alert
(``latency_budget``) on the robot's retained ``alerts`` stream, cleared when it is back under:

.. code-block:: json

    {"type": "latency_stages", "robot": "arm0", "time_ns": 0, "window_s": 2.0, "period_s": 0.5,
     "stages": {"receive": {"count": 199, "p50_ms": 0.1, "p99_ms": 0.3, "max_ms": 0.4,
                            "budget_ms": 10.0, "over": false}, "...": {}},
     "end_to_end": {"count": 199, "p50_ms": 11.0, "p99_ms": 13.0, "max_ms": 14.0,
                    "budget_ms": 50.0, "over": false},
     "out_of_order": 0}

Each row's stages add up to its ``end_to_end`` exactly (consecutive differences of one sample's
stamps); the percentiles of the stages need not add up to the percentile of the sum.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from telerig.bus.base import Bus
from telerig.bus.catalogue import ALERTS, HEALTH, LATENCY
from telerig.bus.topics import Topic, qos_for
from telerig.config.latency import DEFAULT_BUDGETS_MS, ROBOT_STAGES, StageName
from telerig.ir.types import now_ns
from telerig.runtime.metrics import LatencyWindow, WindowSummary

__all__ = ["ALERT_CODE", "DEFAULT_BUDGET_MS", "MIN_COUNT", "REPORT_TYPE", "STAGES_TYPE", "ControlHealth"]

log = logging.getLogger(__name__)

#: Default input-to-command p99 budget [ms]: a loaded 2-core host keeps p99 under ~15 ms
#: (README, fleet benchmark); past it the operator starts to feel the robot lag.
DEFAULT_BUDGET_MS = 20.0
#: The ``type`` of the document, so a reader tells it from a device's or a recorder's health.
REPORT_TYPE = "control_latency"
#: The ``type`` of the per-stage document on ``<robot>/latency``.
STAGES_TYPE = "latency_stages"
#: The ``code`` of a stage's over-budget alert.
ALERT_CODE = "latency_budget"
#: Commands a stage needs in its window before it can be over budget: with fewer, the p99 is the
#: maximum of a handful of values (one late sample at the start of input would raise an alert).
MIN_COUNT = 10
#: What to look at when a stage is over its budget.
_ACTIONS: dict[str, str] = {
    "receive": "check the device's link and tracker (Wi-Fi, USB, the tracker's own buffering)",
    "bus": "check the broker host's load and the network between the stations and the broker",
    "queue": "the control thread waits for the CPU: give the station runtime.priorities or move load off it",
    "retarget": "the retargeter is slow: fewer IK sub-steps or guards, or a faster host",
    "apply": "the safety guards or the driver's link are slow: check the robot's network and guards",
    "state": "the driver reports its state late: check the robot's state rate and link",
    "end_to_end": "see which stage is over its budget",
}


@dataclass(frozen=True, slots=True)
class _Judged:
    window: WindowSummary
    budget_ms: float
    over: bool

    def to_json(self) -> dict[str, object]:
        return {**self.window.to_json(), "budget_ms": self.budget_ms, "over": self.over}


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
        budgets_ms: p99 budget per stage [ms] (the rig's ``latency.budgets_ms``); defaults for
            the stages not given.
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
        budgets_ms: Mapping[StageName, float] | None = None,
    ) -> None:
        for name, value in (("budget_ms", budget_ms), ("hold_ms", hold_ms), ("period_s", period_s)):
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value}")
        self.robot = robot
        self.topic = str(Topic(rig, robot, HEALTH))
        self.stages_topic = str(Topic(rig, robot, LATENCY))
        self.alerts_topic = str(Topic(rig, robot, ALERTS))
        self.budgets_ms: dict[StageName, float] = {**DEFAULT_BUDGETS_MS, **(budgets_ms or {})}
        self.budget_ms = float(budget_ms)
        self.hold_ms = float(hold_ms)
        self.period_s = float(period_s)
        self.command = LatencyWindow(window_s, capacity)
        self.state = LatencyWindow(window_s, capacity)
        #: One row of stamps per applied command whose state was seen (see the module docs).
        self.stages = LatencyWindow(window_s, capacity, stages=ROBOT_STAGES)
        self._bus = bus
        self._clock = clock
        self._pending_capture_ns = 0  # input of the last applied command not yet seen in a state
        self._pending_sent_ns = 0
        self._pending_stamps = (0, 0, 0, 0)  # arrival, received, tick, retargeted of that command
        self._over: tuple[str, ...] | None = None  # stages over budget in the last alerts published
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        #: Reports published (the bounded rate is checkable).
        self.published = 0

    # --- control thread --------------------------------------------------------------------------

    def sent(
        self,
        capture_ns: int,
        sent_ns: int,
        tick_ns: int,
        *,
        arrival_ns: int = 0,
        received_ns: int = 0,
        retargeted_ns: int = 0,
    ) -> None:
        """An applied command: its input's capture time, the driver's stamp of it, the tick's start,
        and where known the input's arrival in telerig, its receipt by this node and the end of its
        retargeting [ns, common clock]. A command without all of them has no stage row."""
        self.command.add(sent_ns - capture_ns, tick_ns)
        self._pending_capture_ns = capture_ns
        self._pending_sent_ns = sent_ns
        self._pending_stamps = (arrival_ns, received_ns, tick_ns, retargeted_ns)

    def measured(self, state_ns: int, tick_ns: int) -> None:
        """A measured state stamped ``state_ns`` [ns]: the first one at or after the pending command
        closes its input-to-state latency."""
        if self._pending_capture_ns and state_ns >= self._pending_sent_ns:
            capture = self._pending_capture_ns
            self.state.add(state_ns - capture, tick_ns)
            self._pending_capture_ns = 0
            arrival, received, tick, retargeted = self._pending_stamps
            if arrival and received and retargeted:
                self.stages.add_stamps(
                    tick_ns, capture, arrival, received, tick, retargeted, self._pending_sent_ns, state_ns
                )

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

    def _judged(self, t: int) -> tuple[dict[str, _Judged], int]:
        """Each stage's (and ``end_to_end``'s) summary at ``t``, its budget and whether it is over,
        and the rows out of order."""
        summary = self.stages.stage_summary(t)
        windows: dict[StageName, WindowSummary] = {s: summary.stages[s] for s in ROBOT_STAGES}
        windows["end_to_end"] = summary.total
        judged: dict[str, _Judged] = {}
        for stage, w in windows.items():
            budget = self.budgets_ms[stage]
            judged[stage] = _Judged(w, budget, w.count >= MIN_COUNT and w.p99_ms > budget)
        return judged, summary.out_of_order

    def stage_report(self, now: int | None = None) -> dict[str, object]:
        """The per-stage report (what :meth:`publish` sends on ``<robot>/latency``)."""
        t = self._clock() if now is None else now
        return self._stage_report(t, *self._judged(t))

    def _stage_report(self, t: int, judged: Mapping[str, _Judged], out_of_order: int) -> dict[str, object]:
        docs = {stage: j.to_json() for stage, j in judged.items()}
        end_to_end = docs.pop("end_to_end")
        return {
            "type": STAGES_TYPE,
            "robot": self.robot,
            "time_ns": t,
            "window_s": self.stages.window_ns / 1e9,
            "period_s": self.period_s,
            "stages": docs,
            "end_to_end": end_to_end,
            "out_of_order": out_of_order,
        }

    def alerts(self, now: int | None = None) -> dict[str, object]:
        """The robot's alerts document: one active ``latency_budget`` alert per stage over budget."""
        t = self._clock() if now is None else now
        return self._alerts(t, self._judged(t)[0])

    def _alerts(self, t: int, judged: Mapping[str, _Judged]) -> dict[str, object]:
        active = [
            {
                "code": ALERT_CODE,
                "severity": "warning",
                "robot": self.robot,
                "stage": stage,
                "time_ns": t,
                "active": True,
                "reason": f"{self.robot} {stage}: p99 {j.window.p99_ms:.1f} ms over its "
                f"{j.budget_ms:g} ms budget ({j.window.count} commands in {self.stages.window_ns / 1e9:g} s)",
                "suggested_action": _ACTIONS[stage],
            }
            for stage, j in judged.items()
            if j.over
        ]
        return {"type": "latency_alerts", "robot": self.robot, "time_ns": t, "active_alerts": active}

    def publish(self) -> None:
        """Publish the current reports: the robot's retained health topic, its per-stage latency
        stream, and its alerts when the set of stages over budget changed (and the first time)."""
        payload = json.dumps(self.report(), separators=(",", ":")).encode()
        qos, retain = qos_for(HEALTH)
        self._bus.publish(self.topic, payload, qos=qos, retain=retain)
        t = self._clock()
        judged, out_of_order = self._judged(t)
        stages = json.dumps(self._stage_report(t, judged, out_of_order), separators=(",", ":")).encode()
        qos, retain = qos_for(LATENCY)
        self._bus.publish(self.stages_topic, stages, qos=qos, retain=retain)
        over = tuple(stage for stage, j in judged.items() if j.over)
        if over != self._over:
            alerts = json.dumps(self._alerts(t, judged)).encode()
            self._bus.publish(self.alerts_topic, alerts, qos=1, retain=True)
            self._over = over
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
