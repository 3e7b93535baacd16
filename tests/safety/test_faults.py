"""Fault injection on the simulated UR5e behind the full safety chain: limits hold, it stops in time."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import pytest

from telerig.bus.memory import InMemoryBus
from telerig.ir.types import FloatArray, JointCommand, JointState, Stamp
from telerig.robots.base import JointLimits
from telerig.robots.models.arm import ArmScene, build_arm_kinematics
from telerig.robots.sim.arm import MujocoArm
from telerig.robots.sim.scene import build_arm_scene
from telerig.safety import (
    Box,
    ConfigurationGuard,
    Deadman,
    KinematicsModel,
    RobotSafety,
    SafetyChain,
    SafetyOutput,
    SafetySupervisor,
    SelfCollision,
    WorkspaceBounds,
)
from telerig.safety.commands import SafetyCommandListener, safety_command_topic

MS = 1_000_000
PERIOD_NS = 10 * MS
T0 = 1_000_000_000_000
STOP_TIMEOUT_S = 0.25
FLOOR_Z = 0.15  # workspace box floor above the base [m]


@pytest.fixture(scope="module")
def kinematics_scene() -> ArmScene:
    return build_arm_kinematics()


@pytest.fixture(scope="module")
def sim_scene() -> ArmScene:
    return build_arm_scene(with_cube=False)


@pytest.fixture
def robot(sim_scene: ArmScene) -> Iterator[MujocoArm]:
    with MujocoArm(sim_scene, name="ur5e", realtime=False) as arm:
        yield arm


class FlakyDriver:
    """The sim arm, with a fault injected from a given tick: read_state raises or reports a bad state."""

    def __init__(self, arm: MujocoArm, mode: str, after: int) -> None:
        self.arm, self.mode, self.after = arm, mode, after
        self.reads = 0
        self.estops = 0

    @property
    def name(self) -> str:
        return self.arm.name

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.arm.joint_names

    @property
    def limits(self) -> JointLimits:
        return self.arm.limits

    def read_state(self) -> JointState:
        self.reads += 1
        state = self.arm.read_state()
        if self.reads <= self.after:
            return state
        if self.mode == "disconnect":
            raise ConnectionError("connection reset by peer")
        q = state.positions.copy()
        q[1] = self.arm.limits.upper[1] + 0.2  # beyond the joint limit
        return JointState(state.stamp, state.names, q, state.velocities)

    def send(self, command: JointCommand) -> JointCommand:
        return self.arm.send(command)

    def estop(self) -> None:
        self.estops += 1
        self.arm.estop()

    def reset_estop(self) -> None:
        self.arm.reset_estop()


@dataclass
class Run:
    """Every tick's output and measured state of a closed loop (chain → sim arm → measured)."""

    outputs: list[SafetyOutput] = field(default_factory=list)
    measured: list[FloatArray | None] = field(default_factory=list)
    times: list[int] = field(default_factory=list)

    def commands(self) -> list[FloatArray]:
        return [o.command.positions for o in self.outputs if o.command is not None]

    def codes(self) -> set[str]:
        return {e.code for o in self.outputs for e in o.events}


class Loop:
    """Steps one supervised robot at 100 Hz: read state, step the chain, send, simulate 10 ms."""

    def __init__(self, robot: RobotSafety, sim: MujocoArm) -> None:
        self.robot, self.sim = robot, sim
        self.t = T0
        self.seq = 0
        self.run = Run()

    def request(self, q: FloatArray, *, stamp_ns: int | None = None) -> JointCommand:
        self.seq += 1
        t = self.t if stamp_ns is None else stamp_ns
        return JointCommand(Stamp("retarget", self.seq, t, t), self.sim.joint_names, q)

    def tick(self, q: FloatArray | JointCommand | None) -> SafetyOutput:
        self.t += PERIOD_NS
        measured = self.robot.read_state()
        request = self.request(q) if isinstance(q, np.ndarray) else q
        out = self.robot.step(request, now_ns=self.t, measured=measured)
        if out.command is not None:
            self.robot.send(out.command)
        self.sim.step(5)  # 5 x 2 ms
        self.run.outputs.append(out)
        self.run.measured.append(None if measured is None else measured.positions.copy())
        self.run.times.append(self.t)
        return out

    def follow(self, path: Callable[[int], FloatArray | None], ticks: int) -> Run:
        for k in range(ticks):
            self.tick(path(k))
        return self.run


def chain_for(limits: JointLimits, guard: ConfigurationGuard | None = None, **kw: object) -> SafetyChain:
    return SafetyChain.default(limits, ramp_duration_s=0.5, guard=guard, **kw)  # type: ignore[arg-type]


def supervised(robot: MujocoArm, chain: SafetyChain, driver: object | None = None) -> RobotSafety:
    return SafetySupervisor("pause_affected").add(robot.name, driver or robot, chain)  # type: ignore[arg-type]


def assert_within_limits(run: Run, limits: JointLimits, *, dt: float = PERIOD_NS * 1e-9) -> None:
    """Positions in range; while tracking or holding, speed and acceleration within the limits."""
    tol = 1e-9
    for q in run.commands():
        assert (q >= limits.lower - tol).all()
        assert (q <= limits.upper + tol).all()
    moving = [
        o.command.positions for o in run.outputs if o.status in ("ok", "limited", "holding") and o.command
    ]
    v = np.diff(np.array(moving), axis=0) / dt
    assert (np.abs(v) <= limits.velocity * (1 + 1e-6)).all(), np.abs(v).max(axis=0)
    a = np.diff(v, axis=0) / dt
    assert (np.abs(a) <= limits.acceleration * (1 + 1e-6)).all(), np.abs(a).max(axis=0)


def assert_stopped_by(run: Run, deadline_ns: int) -> None:
    """From ``deadline_ns`` on the chain is stopped (command = measured) or e-stopped (no command)."""
    after = [(o, m) for o, m, t in zip(run.outputs, run.measured, run.times, strict=True) if t >= deadline_ns]
    assert after
    for out, measured in after:
        assert out.status in ("stopped", "estopped")
        if out.status == "stopped":
            assert out.command is not None
            assert measured is not None
            np.testing.assert_allclose(out.command.positions, run.measured[run.outputs.index(out)], atol=0.02)


def sine(home: FloatArray, amplitude: float = 0.3) -> Callable[[int], FloatArray]:
    def path(k: int) -> FloatArray:
        q = home.copy()
        q[0] += amplitude * math.sin(2 * math.pi * 0.5 * k * 0.01)
        return q

    return path


def test_nan_burst_never_reaches_the_robot(robot: MujocoArm) -> None:
    loop = Loop(supervised(robot, chain_for(robot.limits)), robot)
    home, good = robot.scene.home.copy(), sine(robot.scene.home.copy())
    nan = np.full(6, math.nan)
    run = loop.follow(lambda k: nan if 60 <= k < 68 else good(k), 150)
    assert all(np.isfinite(q).all() for q in run.commands())
    assert "invalid_input" in run.codes()
    assert_within_limits(run, robot.limits)
    assert run.outputs[-1].status in ("ok", "limited")  # tracking resumed after the burst
    assert home is not None


def test_frozen_input_stops_within_the_watchdog_time(robot: MujocoArm) -> None:
    loop = Loop(supervised(robot, chain_for(robot.limits)), robot)
    loop.follow(sine(robot.scene.home.copy()), 50)
    frozen = loop.request(robot.scene.home + 0.05)  # the same stamp, repeated every tick
    frozen_at = frozen.stamp.capture_ns
    run = loop.follow(lambda k: None, 0)
    for _ in range(40):
        loop.tick(frozen)
    assert {"input_stale", "watchdog_stop"} <= run.codes()
    assert_within_limits(run, robot.limits)
    assert_stopped_by(run, frozen_at + round(STOP_TIMEOUT_S * 1e9) + PERIOD_NS)


def test_one_radian_jump_is_smoothed_within_velocity_and_acceleration(robot: MujocoArm) -> None:
    loop = Loop(supervised(robot, chain_for(robot.limits)), robot)
    home = robot.scene.home.copy()
    loop.follow(lambda k: home, 60)
    jumped = home.copy()
    jumped[0] += 1.0
    run = loop.follow(lambda k: jumped, 150)
    assert_within_limits(run, robot.limits)
    np.testing.assert_allclose(run.commands()[-1], jumped, atol=1e-6)


@pytest.mark.parametrize("mode", ["disconnect", "limit_violation"])
def test_driver_fault_halts_and_estops_the_driver(robot: MujocoArm, mode: str) -> None:
    driver = FlakyDriver(robot, mode, after=60)
    loop = Loop(supervised(robot, chain_for(robot.limits), driver), robot)
    run = loop.follow(sine(robot.scene.home.copy()), 80)
    faulted = next(i for i, o in enumerate(run.outputs) if o.status == "estopped")
    assert faulted == 60  # the very tick the fault appears
    code = "driver_fault" if mode == "disconnect" else "joint_limit_fault"
    assert run.outputs[faulted].events[0].code == code
    assert all(o.status == "estopped" and o.command is None for o in run.outputs[faulted:])
    assert driver.estops == 1
    assert robot.estopped
    assert_within_limits(Run(run.outputs[:faulted]), robot.limits)


def test_workspace_breach_is_refused_and_the_tool_never_leaves_the_box(
    robot: MujocoArm, kinematics_scene: ArmScene
) -> None:
    s = kinematics_scene
    kin = KinematicsModel(s.model, s.arm_joints, base_body=s.base_body)
    ws = WorkspaceBounds(kin, [s.ee_site], box=Box([-1.0, -1.0, FLOOR_Z], [1.0, 1.0, 1.2], "table"))
    loop = Loop(supervised(robot, chain_for(robot.limits, ConfigurationGuard([ws]))), robot)
    home = robot.scene.home.copy()
    loop.follow(lambda k: home, 60)
    # Lower the tool towards the table: shoulder lift +1 rad reaches z = -0.15 m, through the floor.
    run = loop.follow(lambda k: home + np.array([0, min(k, 100) * 0.01, 0, 0, 0, 0]), 200)
    assert "workspace" in run.codes()
    z = [float(ws.points(q)[0, 2]) for q in run.commands()]
    assert min(z) >= FLOOR_Z
    assert min(z) < FLOOR_Z + 0.05  # it did go close to the floor: the check is what stopped it
    assert_within_limits(run, robot.limits)
    measured_z = [float(ws.points(q)[0, 2]) for q in run.measured if q is not None]
    assert min(measured_z) >= FLOOR_Z - 0.005  # the simulated arm follows within its servo error


def test_self_colliding_request_is_refused(robot: MujocoArm, kinematics_scene: ArmScene) -> None:
    s = kinematics_scene
    kin = KinematicsModel(s.model, s.arm_joints, base_body=s.base_body)
    sc = SelfCollision(kin, allowed=[s.home])
    folded = s.home.copy()
    folded[2] = 3.0
    assert sc.violation(folded) is not None
    loop = Loop(supervised(robot, chain_for(robot.limits, ConfigurationGuard([sc]))), robot)
    home = robot.scene.home.copy()
    loop.follow(lambda k: home, 60)
    run = loop.follow(lambda k: home + (folded - home) * min(k / 120, 1.0), 200)
    assert "self_collision" in run.codes()
    assert all(sc.violation(q) is None for q in run.commands())
    assert_within_limits(run, robot.limits)
    assert run.commands()[-1][2] > 2.3  # folded as far as allowed, not stopped early


def test_deadman_release_holds_then_stops_within_the_watchdog_time(robot: MujocoArm) -> None:
    deadman = Deadman(signal_timeout_s=0.05)
    loop = Loop(supervised(robot, chain_for(robot.limits, deadman=deadman)), robot)
    path = sine(robot.scene.home.copy())
    for k in range(80):
        deadman.update(True, loop.t + PERIOD_NS)
        loop.tick(path(k))
    released_at = loop.t
    deadman.update(False, released_at)
    run = loop.follow(lambda k: path(80 + k), 40)  # requests keep coming; the button is up
    assert "deadman" in run.codes()
    assert run.outputs[80].status == "holding"
    assert_within_limits(run, robot.limits)
    assert_stopped_by(run, released_at + round(STOP_TIMEOUT_S * 1e9) + PERIOD_NS)


@pytest.mark.parametrize("policy", ["halt_all", "pause_affected"])
def test_fault_policy_with_two_robots(sim_scene: ArmScene, policy: str) -> None:
    with (
        MujocoArm(sim_scene, name="left", realtime=False) as left,
        MujocoArm(sim_scene, name="right", realtime=False) as right,
    ):
        supervisor = SafetySupervisor(policy)  # type: ignore[arg-type]
        flaky = FlakyDriver(left, "disconnect", after=50)
        loops = [
            Loop(supervisor.add("left", flaky, chain_for(left.limits)), left),  # type: ignore[arg-type]
            Loop(supervisor.add("right", right, chain_for(right.limits)), right),
        ]
        path = sine(sim_scene.home.copy())
        for k in range(80):
            for loop in loops:
                loop.tick(path(k))
        left_run, right_run = loops[0].run, loops[1].run
        assert left_run.outputs[-1].status == "estopped"
        assert left.estopped
        assert [name for name, _ in supervisor.faults] == ["left"]
        if policy == "halt_all":
            assert right.estopped
            assert right_run.outputs[50].status == "estopped"  # halted in the same tick as the fault
            assert right_run.outputs[-1].status == "estopped"
        else:
            assert not right.estopped
            assert right_run.outputs[-1].status in ("ok", "limited")
            assert_within_limits(right_run, right.limits)
        supervisor.reset()
        assert not left.estopped
        assert not right.estopped


# -- operator commands over the bus (`telerig safety estop|reset`, the dashboard) ------------------


def _command(bus: InMemoryBus, **fields: object) -> None:
    bus.publish(safety_command_topic("rig"), json.dumps(fields).encode(), qos=1)


def test_an_operator_estop_stops_one_robot_and_a_reset_resumes_it_without_a_jump(sim_scene: ArmScene) -> None:
    with (
        MujocoArm(sim_scene, name="left", realtime=False) as left,
        MujocoArm(sim_scene, name="right", realtime=False) as right,
    ):
        bus = InMemoryBus()
        supervisor = SafetySupervisor("halt_all")
        listener = SafetyCommandListener(bus, "rig", supervisor)
        loops = [
            Loop(supervisor.add("left", left, chain_for(left.limits)), left),
            Loop(supervisor.add("right", right, chain_for(right.limits)), right),
        ]
        path = sine(sim_scene.home.copy())
        for k in range(100):
            if k == 60:
                _command(bus, command="estop", robot="left", operator="op7", reason="cable in the way")
            for loop in loops:
                loop.tick(path(k))
        left_run, right_run = loops[0].run, loops[1].run
        assert left_run.outputs[60].status == "estopped"
        assert left.estopped
        estop = left_run.outputs[60].events[0]
        assert estop.reason == "e-stop by op7 (bus): cable in the way"
        assert estop.suggested_action == "telerig safety reset --robot left"
        # An operator's e-stop is not a fault: the rig's halt_all policy leaves the other robot running.
        assert supervisor.faults == []
        assert not right.estopped
        assert right_run.outputs[-1].status in ("ok", "limited")

        held = left.read_state().positions
        _command(bus, command="reset", robot="left")
        assert not left.estopped
        resumed = Run()
        for k in range(100, 250):
            resumed.outputs.append(loops[0].tick(path(k)))
        # Restarted from where it stood, ramped up again: never a jump, tracking at the end.
        first = next(o.command for o in resumed.outputs if o.command is not None)
        np.testing.assert_allclose(first.positions, held, atol=1e-3)
        assert_within_limits(resumed, left.limits)
        assert resumed.outputs[-1].status in ("ok", "limited")
        assert listener.applied == 2


def test_a_reset_after_a_fault_rearms_every_robot_of_the_process(sim_scene: ArmScene) -> None:
    with (
        MujocoArm(sim_scene, name="left", realtime=False) as left,
        MujocoArm(sim_scene, name="right", realtime=False) as right,
    ):
        bus = InMemoryBus()
        supervisor = SafetySupervisor("halt_all")
        SafetyCommandListener(bus, "rig", supervisor)
        flaky = FlakyDriver(left, "disconnect", after=30)
        loops = [
            Loop(supervisor.add("left", flaky, chain_for(left.limits)), left),  # type: ignore[arg-type]
            Loop(supervisor.add("right", right, chain_for(right.limits)), right),
        ]
        path = sine(sim_scene.home.copy())
        for k in range(40):
            for loop in loops:
                loop.tick(path(k))
        assert left.estopped
        assert right.estopped  # halted by the policy
        flaky.after = 10**9  # the connection is back
        _command(bus, command="reset")
        assert not left.estopped
        assert not right.estopped
        for k in range(40, 200):
            for loop in loops:
                loop.tick(path(k))
        assert loops[0].run.outputs[-1].status in ("ok", "limited")
        assert loops[1].run.outputs[-1].status in ("ok", "limited")


def test_a_reset_while_the_fault_persists_latches_it_again(robot: MujocoArm) -> None:
    bus = InMemoryBus()
    supervisor = SafetySupervisor("pause_affected")
    SafetyCommandListener(bus, "rig", supervisor)
    flaky = FlakyDriver(robot, "limit_violation", after=20)
    loop = Loop(supervisor.add("ur5e", flaky, chain_for(robot.limits)), robot)  # type: ignore[arg-type]
    loop.follow(sine(robot.scene.home.copy()), 30)
    _command(bus, command="reset", robot="ur5e")
    out = loop.tick(robot.scene.home.copy())
    assert out.status == "estopped"
    assert out.events[0].code == "joint_limit_fault"
    assert [name for name, _ in supervisor.faults] == ["ur5e", "ur5e"]


def test_malformed_or_foreign_commands_change_nothing(
    robot: MujocoArm, caplog: pytest.LogCaptureFixture
) -> None:
    bus = InMemoryBus()
    supervisor = SafetySupervisor("pause_affected")
    listener = SafetyCommandListener(bus, "rig", supervisor)
    loop = Loop(supervisor.add("ur5e", robot, chain_for(robot.limits)), robot)
    loop.follow(sine(robot.scene.home.copy()), 20)
    bus.publish(safety_command_topic("rig"), b"{not json", qos=1)
    _command(bus, command="reboot")
    _command(bus, command="estop", robot="ur5e", speed=3)
    _command(bus, command="estop", robot="other_process_arm")
    assert listener.rejected == 3
    assert listener.applied == 0
    assert not robot.estopped
    assert loop.tick(robot.scene.home.copy()).status != "estopped"
    assert "dropped a safety command on telerig/v1/rig/safety/command: command:" in caplog.text
