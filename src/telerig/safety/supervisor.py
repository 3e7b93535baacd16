"""Fleet safety supervisor: per-robot fault reactions (halt, e-stop the driver) and the rig's halt policy."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Protocol, TypeVar, runtime_checkable

from telerig.config.safety import POLICIES, FaultPolicy
from telerig.errors import ConfigError
from telerig.ir.types import BaseVelocity, GripperCommand, JointCommand, JointState
from telerig.robots.base import MobileBase, RobotDriver
from telerig.safety.alerts import SafetyAlerts
from telerig.safety.chain import FAULT_CODES, SafetyChain, SafetyOutput
from telerig.safety.filters import SafetyCode, SafetyEvent
from telerig.safety.parts import BaseLimit, GripperLimit

__all__ = ["POLICIES", "FaultPolicy", "ResettableDriver", "RobotSafety", "SafetySupervisor"]

log = logging.getLogger(__name__)

_S = TypeVar("_S")


@runtime_checkable
class ResettableDriver(Protocol):
    """A driver whose latched e-stop can be released in software (e.g. the MuJoCo arm)."""

    def reset_estop(self) -> None: ...


class RobotSafety:
    """One robot under the supervisor: its driver calls go through here so faults are caught.

    The robot's control loop calls, per tick: :meth:`read_state`, then :meth:`step` with the
    retargeted request, then :meth:`send` with the output's command, and :meth:`send_gripper` /
    :meth:`send_base` for the robot's other parts (their own limits, nothing moves while
    e-stopped). A driver that raises (lost connection, controller fault), a missing or invalid
    measured state, or a measured position beyond the joint limits latches the chain's e-stop,
    calls ``driver.estop()`` at once on this thread, and hands the fault to the supervisor's policy.

    Driver calls are serialized by a per-robot lock, so the supervisor may e-stop this robot's
    driver from another robot's thread.
    """

    def __init__(
        self,
        supervisor: SafetySupervisor,
        name: str,
        driver: RobotDriver,
        chain: SafetyChain,
        *,
        gripper: GripperLimit | None = None,
        base: BaseLimit | None = None,
    ) -> None:
        self.name = name
        self.driver = driver
        self.chain = chain
        self.gripper = gripper if gripper is not None else GripperLimit()
        self.base = base if base is not None else BaseLimit()
        self._supervisor = supervisor
        self._lock = threading.RLock()
        self._driver_stopped = False
        self._fault_handled = False

    @property
    def driver_stopped(self) -> bool:
        """Whether ``driver.estop()`` was called since the last reset."""
        return self._driver_stopped

    def read_state(self) -> JointState | None:
        """The driver's measured state, or ``None`` when it raised (a ``driver_fault`` is latched)."""
        try:
            with self._lock:
                return self.driver.read_state()
        except Exception as exc:
            self.fault(f"reading the state of {self.name} failed: {exc}")
            return None

    def sense(self, read: Callable[[], _S], what: str) -> _S | None:
        """One of the driver's other measurements (``read``: e.g. its ``read_gripper``), or ``None``
        when it raised: like a failed :meth:`read_state`, a ``driver_fault`` is latched."""
        try:
            with self._lock:
                return read()
        except Exception as exc:
            self.fault(f"reading the {what} of {self.name} failed: {exc}")
            return None

    def step(
        self, requested: JointCommand | None, *, now_ns: int, measured: JointState | None
    ) -> SafetyOutput:
        """Step the chain (see :meth:`SafetyChain.step`), react to a latched fault, publish alerts."""
        out = self.chain.step(requested, now_ns=now_ns, measured=measured)
        if out.status == "estopped":
            self._stop_driver()
            for event in out.events:
                if event.code in FAULT_CODES:
                    self._on_fault(event)
        alerts = self._supervisor.alerts
        if alerts is not None:
            alerts.update(self.name, out, now_ns)
        return out

    def send(self, command: JointCommand) -> JointCommand | None:
        """Send ``command`` unless e-stopped; ``None`` when not sent (e-stop, or the driver raised)."""
        try:
            with self._lock:
                if self.chain.estopped:
                    return None
                return self.driver.send(command)
        except Exception as exc:
            self.fault(f"sending to {self.name} failed: {exc}")
            return None

    def send_gripper(self, command: GripperCommand) -> GripperCommand | None:
        """Send a gripper command within its limits (:class:`~telerig.safety.parts.GripperLimit`).

        Returns what the driver applied, or ``None`` when nothing was sent: e-stopped (the gripper
        holds), a non-finite command (counted as ``invalid_input`` in the chain's counts), or the
        driver raised (a ``driver_fault`` is latched).
        """
        checked = self.gripper.apply(command)
        if isinstance(checked, SafetyEvent):
            self.chain.note(checked)
            return None
        try:
            with self._lock:
                if self.chain.estopped:
                    return None
                return self.driver.send_gripper(checked)
        except Exception as exc:
            self.fault(f"sending the gripper command to {self.name} failed: {exc}")
            return None

    def send_base(self, command: BaseVelocity, *, now_ns: int) -> BaseVelocity | None:
        """Send a base velocity within its limits (:class:`~telerig.safety.parts.BaseLimit`) at
        ``now_ns`` [ns]; while e-stopped, a stop instead.

        Limited and non-finite commands are counted in the chain's counts (a non-finite one is
        sent as a stop). Returns what the driver applied, or ``None`` when the driver has no base
        or raised (a ``driver_fault`` is latched).
        """
        driver = self.driver
        if not isinstance(driver, MobileBase):
            return None
        try:
            with self._lock:
                if self.chain.estopped and (command.vx, command.vy, command.wz) != (0.0, 0.0, 0.0):
                    command = BaseVelocity(command.stamp, 0.0, 0.0, 0.0)
                limited, event = self.base.apply(command, now_ns)
                if event is not None:
                    self.chain.note(event)
                return driver.send_base(limited)
        except Exception as exc:
            self.fault(f"sending the base command to {self.name} failed: {exc}")
            return None

    def fault(self, reason: str, *, code: SafetyCode = "driver_fault") -> None:
        """Report a hardware fault (any thread): latch the e-stop, stop the driver, apply the policy."""
        action = "check the driver's connection and the robot controller, then reset"
        if self.chain.estop(reason, code=code, suggested_action=action):
            log.error("%s: %s: %s", self.name, code, reason)
        self._stop_driver()
        event = self.chain.estop_event
        if event is not None and event.code in FAULT_CODES:
            self._on_fault(event)

    def halt(
        self, reason: str, *, suggested_action: str = "fix the faulty robot, then reset the rig"
    ) -> None:
        """E-stop this robot for another robot's fault or an operator (any thread): latch the chain
        and stop the driver."""
        self.chain.estop(reason, suggested_action=suggested_action)
        self._stop_driver()

    def reset(self) -> None:
        """Release the chain's e-stop and the driver's, if it can be released in software."""
        with self._lock:
            self.chain.reset()
            if self._driver_stopped and isinstance(self.driver, ResettableDriver):
                self.driver.reset_estop()
            self._driver_stopped = False
            self._fault_handled = False

    def _stop_driver(self) -> None:
        with self._lock:
            if self._driver_stopped:
                return
            self._driver_stopped = True
            try:
                self.driver.estop()
            except Exception:
                log.exception("%s: driver e-stop failed; use the hardware emergency stop", self.name)

    def _on_fault(self, event: SafetyEvent) -> None:
        with self._lock:
            if self._fault_handled:
                return
            self._fault_handled = True
        self._supervisor._apply_policy(self, event)


class SafetySupervisor:
    """Owns the fault reactions of a rig's robots and its policy; thread-safe.

    Each robot's control loop runs on its own thread and talks to its :class:`RobotSafety`
    (from :meth:`add`). On a fault the faulty robot always halts (chain e-stop + ``driver.estop()``
    at once); with ``halt_all`` every other robot is halted too, from the faulting thread, so no
    robot waits for its own next tick.
    """

    def __init__(
        self,
        policy: FaultPolicy = "halt_all",
        *,
        alerts: SafetyAlerts | None = None,
        on_halt_all: Callable[[str, SafetyEvent], None] | None = None,
    ) -> None:
        """Args:
        policy: What a fault on one robot does to the others (see :data:`FaultPolicy`).
        alerts: Where warnings and errors are published; ``None`` to publish nothing.
        on_halt_all: Called with (robot, event) when ``halt_all`` halts the fleet for a fault here,
            to reach robots supervised in other processes (the runtime publishes it on the bus).
        """
        if policy not in POLICIES:
            raise ConfigError(f"safety policy must be one of {', '.join(POLICIES)}, got {policy!r}")
        self.policy: FaultPolicy = policy
        self.alerts = alerts
        self._on_halt_all = on_halt_all
        self._lock = threading.Lock()
        self._robots: dict[str, RobotSafety] = {}
        self._faults: list[tuple[str, SafetyEvent]] = []

    def add(
        self,
        name: str,
        driver: RobotDriver,
        chain: SafetyChain,
        *,
        gripper: GripperLimit | None = None,
        base: BaseLimit | None = None,
    ) -> RobotSafety:
        """Put a robot under supervision; ``ConfigError`` if ``name`` is taken.

        Args:
            name: The robot's id in the rig.
            driver: Its driver, connected by the caller.
            chain: The safety chain of its joints.
            gripper: Limits of its gripper commands; ``None`` for the defaults.
            base: Limits of its base commands; ``None`` for the defaults.
        """
        with self._lock:
            if name in self._robots:
                raise ConfigError(f"robot {name!r} is already supervised; give each robot a unique id")
            robot = self._robots[name] = RobotSafety(self, name, driver, chain, gripper=gripper, base=base)
        return robot

    @property
    def robots(self) -> dict[str, RobotSafety]:
        """The supervised robots, by name (a copy)."""
        with self._lock:
            return dict(self._robots)

    @property
    def faults(self) -> list[tuple[str, SafetyEvent]]:
        """Faults handled since creation: (robot, event), oldest first."""
        with self._lock:
            return list(self._faults)

    def estop_all(self, reason: str) -> None:
        """E-stop every robot now (any thread), e.g. the dashboard's e-stop button."""
        for robot in self.robots.values():
            robot.halt(reason)

    def reset(self, name: str | None = None) -> None:
        """Release the e-stop of robot ``name``, or of every robot when ``None``."""
        robots = self.robots
        if name is not None and name not in robots:
            raise ConfigError(f"robot {name!r} is not supervised. Available: {', '.join(robots)}")
        for robot in robots.values() if name is None else (robots[name],):
            robot.reset()

    def _apply_policy(self, robot: RobotSafety, event: SafetyEvent) -> None:
        with self._lock:
            self._faults.append((robot.name, event))
            others = [r for n, r in self._robots.items() if n != robot.name]
        if self.policy == "pause_affected":
            log.error("%s paused (%s); the other robots keep running", robot.name, event.code)
            return
        log.error("%s faulted (%s): halting every robot", robot.name, event.code)
        for other in others:
            other.halt(f"halted because robot {robot.name!r} faulted ({event.code}): {event.reason}")
        if self._on_halt_all is not None:
            self._on_halt_all(robot.name, event)
