"""The RobotDriver contract, run over every registered driver (simulated; real ones with fake peers)."""

from __future__ import annotations

import functools
import itertools
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, ExitStack
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np
import pytest

from telerig.errors import RobotError
from telerig.ir.types import GripperCommand, JointCommand, Stamp, now_ns
from telerig.registry import ROBOTS
from telerig.robots.base import RobotDriver
from telerig.robots.dobot.fake import FakeDobot
from telerig.robots.modbus.fake import FakeDHGripper, FakeInspireHand
from telerig.robots.rosbridge.fake import FakeRosbridge
from telerig.robots.sim.arm import MujocoArm
from telerig.robots.sim.bimanual import BimanualStation, build_bimanual_scene
from telerig.robots.sim.config import MujocoPickPlaceConfig
from telerig.robots.sim.gripper import MujocoGripper, build_gripper_scene
from telerig.robots.sim.hand import MujocoHand, build_hand_scene
from telerig.robots.sim.humanoid import MujocoHumanoid, build_humanoid_scene
from telerig.robots.sim.pick_place import MujocoPickPlace
from telerig.robots.sim.scene import build_arm_scene
from telerig.robots.sim.tiago import build_tiago_scene
from telerig.robots.sim.tiago_driver import MujocoTiago
from telerig.robots.unitree.fake import FakeG1
from telerig.robots.ur.fake import FakeURController
from telerig.safety.supervisor import ResettableDriver

P = TypeVar("P")

#: The ``id`` of every case's rig entry: the name its driver must stamp with.
_ID = "contract"


@dataclass(frozen=True)
class DriverCase:
    """How to make one driver for the contract, and where it legitimately differs from an arm.

    Attributes:
        robot_type: The registered ``type`` (``ROBOTS``) this case covers.
        make: Builds the driver, not connected; starts its fake peer on 127.0.0.1 first, if any.
        advance: Lets time pass so the driver's state follows its commands (steps a simulation, or
            sleeps while a fake peer moves); called as ``advance(driver, seconds)``.
        cleanup: Stops what ``make`` started besides the driver (a fake peer); None when nothing.
        config: The rig's robot entry a stepped simulated driver stands for. Config-built sim
            drivers step in real time on a thread; the contract steps an equivalent driver for
            determinism, and a test checks the config builds the same class, joints and limits.
            None for real drivers, whose ``make`` goes through the config itself.
        has_gripper: False for a robot without any gripper (the G1, a rosbridge arm): then
            ``has_gripper`` must say so and ``send_gripper`` must raise ``RobotError`` naming the
            fix instead of returning the clipped opening.
        unbounded_joints: Joints with no position limit (a mobile base's x, y, yaw): their limits
            must be infinite and ``send`` must pass their targets through unclipped; every other
            joint must have finite limits.
        unlock: What an operator must do on the robot itself before a software reset can re-arm
            it after an e-stop (a UR's protective stop is unlocked on the teach pendant); until
            then ``reset_estop`` must raise ``RobotError`` saying so. None when a software reset
            alone re-arms the robot.
    """

    robot_type: str
    make: Callable[[], RobotDriver]
    advance: Callable[[RobotDriver, float], None]
    cleanup: Callable[[], None] | None = None
    config: dict[str, Any] | None = None
    has_gripper: bool = True
    unbounded_joints: tuple[str, ...] = ()
    unlock: Callable[[], None] | None = None


# -- simulated drivers: stepped, deterministic -----------------------------------------------------


def _step_sim(driver: RobotDriver, seconds: float) -> None:
    assert isinstance(driver, MujocoArm | MujocoGripper)
    with driver.locked() as (model, _):
        steps = round(seconds / model.opt.timestep)
    driver.step(steps)


# Scenes are compiled once per module: drivers never modify the model, each has its own data.
_arm_scene = functools.cache(build_arm_scene)
_bimanual_scene = functools.cache(build_bimanual_scene)
_hand_scene = functools.cache(build_hand_scene)
_tiago_scene = functools.cache(build_tiago_scene)
_humanoid_scene = functools.cache(build_humanoid_scene)


def _bimanual(side: str) -> Callable[[], RobotDriver]:
    def make() -> RobotDriver:
        return BimanualStation(_bimanual_scene("ur5e_robotiq85"), realtime=False).arm(side)

    return make


def _sim(
    robot_type: str,
    make: Callable[[], RobotDriver],
    *,
    has_gripper: bool = True,
    unbounded_joints: tuple[str, ...] = (),
    **config: Any,
) -> DriverCase:
    """A stepped simulated driver standing for the rig entry ``{type: robot_type, **config}``."""
    entry = {"type": robot_type, "id": _ID, **config}
    return DriverCase(
        robot_type, make, _step_sim, config=entry, has_gripper=has_gripper, unbounded_joints=unbounded_joints
    )


# -- real drivers against their fake peers on 127.0.0.1 -------------------------------------------


def _sleep(driver: RobotDriver, seconds: float) -> None:
    time.sleep(seconds)


class _PeerCase(Generic[P]):
    """A real driver built from its rig config, talking to a fake peer that ``make`` starts."""

    def __init__(self, start: Callable[[], AbstractContextManager[P]], config: Callable[[P], dict[str, Any]]):
        self._start = start
        self._config = config
        self._stack = ExitStack()
        self.peer: P | None = None

    def make(self) -> RobotDriver:
        peer = self.peer = self._stack.enter_context(self._start())
        driver = ROBOTS.parse_config(self._config(peer), "robots[0]").build()
        assert isinstance(driver, RobotDriver)
        return driver

    def cleanup(self) -> None:
        self._stack.close()


def _real(
    robot_type: str,
    start: Callable[[], AbstractContextManager[P]],
    config: Callable[[P], dict[str, Any]],
    unlock: Callable[[P], None] | None = None,
    **flags: Any,
) -> DriverCase:
    def entry(peer: P) -> dict[str, Any]:
        return {"type": robot_type, "id": _ID, **config(peer)}

    def unlock_peer() -> None:
        assert unlock is not None
        assert peer_case.peer is not None
        unlock(peer_case.peer)

    peer_case = _PeerCase(start, entry)
    return DriverCase(
        robot_type, peer_case.make, _sleep, peer_case.cleanup, unlock=unlock_peer if unlock else None, **flags
    )


_ROS_JOINTS = ("shoulder", "elbow", "wrist")
# A DDS domain per fake G1 (see tests/robots/unitree/test_unitree.py: sertypes shared in a domain).
_G1_DOMAINS = itertools.count(30)


def _ur(fake: FakeURController) -> dict[str, Any]:
    return {
        "host": "127.0.0.1",
        "rtde_port": fake.rtde_port,
        "script_port": fake.script_port,
        "gripper": "robotiq_urcap",
        "gripper_port": fake.gripper_port,
        "watchdog_s": 0.5,
        "stale_timeout_s": 2.0,
    }


def _dobot(fake: FakeDobot) -> dict[str, Any]:
    return {
        "host": "127.0.0.1",
        "dashboard_port": fake.dashboard_port,
        "motion_port": fake.motion_port,
        "feedback_port": fake.feedback_port,
        "gripper_tool_do": 1,
        "stale_timeout_s": 2.0,
    }


def _rosbridge(fake: FakeRosbridge) -> dict[str, Any]:
    return {
        "url": fake.url,
        "joint_names": _ROS_JOINTS,
        "lower": (-2.0, -2.0, -2.0),
        "upper": (2.0, 2.0, 2.0),
        "velocity": 2.0,
        "acceleration": 10.0,
        "estop_topic": "/telerig/estop",
        "stale_timeout_s": 2.0,
    }


#: Per-request answer timeout of the Modbus drivers here [s]. Their default (0.1 s) suits a device on
#: its own bus; the fake peer is a thread of this loaded test process, which a full suite on two
#: workers once kept from answering a connect within it. Nothing in the contract waits on a timeout.
_MODBUS_TIMEOUT_S = 1.0


def _inspire(fake: FakeInspireHand) -> dict[str, Any]:
    return {"host": "127.0.0.1", "port": fake.port, "stale_after_s": 2.0, "timeout_s": _MODBUS_TIMEOUT_S}


def _dh(fake: FakeDHGripper) -> dict[str, Any]:
    return {
        "transport": "rtu_over_tcp",
        "host": "127.0.0.1",
        "port": fake.port,
        "stale_after_s": 2.0,
        "timeout_s": _MODBUS_TIMEOUT_S,
    }


#: Every driver the contract runs over, keyed by case name; every registered type has at least one.
#: A new driver adds one line: how to make it (from its config, starting its fake peer on
#: 127.0.0.1), how to let time pass, how to stop the peer, and any flag its robot justifies.
DRIVERS: dict[str, DriverCase] = {
    "mujoco_arm/ur5e": _sim("mujoco_arm", lambda: MujocoArm(_arm_scene(), realtime=False)),
    "mujoco_arm/panda": _sim(
        "mujoco_arm", lambda: MujocoArm(_arm_scene("panda"), realtime=False), model="panda"
    ),
    "mujoco_gripper": _sim("mujoco_gripper", lambda: MujocoGripper(build_gripper_scene(), realtime=False)),
    # The arm at the randomized pick-and-place task (issue 16): an arm driver with object poses.
    "mujoco_pick_place": _sim(
        "mujoco_pick_place", lambda: MujocoPickPlace(MujocoPickPlaceConfig(id=_ID).spec(), realtime=False)
    ),
    "mujoco_bimanual_arm/left": _sim("mujoco_bimanual_arm", _bimanual("left"), bench="contract", side="left"),
    "mujoco_bimanual_arm/right": _sim(
        "mujoco_bimanual_arm", _bimanual("right"), bench="contract", side="right"
    ),
    "mujoco_hand/inspire": _sim("mujoco_hand", lambda: MujocoHand(_hand_scene("inspire"), realtime=False)),
    "mujoco_hand/ability_left": _sim(
        "mujoco_hand",
        lambda: MujocoHand(_hand_scene("ability", "left"), realtime=False),
        model="ability",
        handedness="left",
    ),
    "mujoco_tiago": _sim(
        "mujoco_tiago",
        lambda: MujocoTiago(_tiago_scene(), realtime=False),
        unbounded_joints=("base_x", "base_y", "base_yaw"),
    ),
    "mujoco_humanoid": _sim(
        "mujoco_humanoid", lambda: MujocoHumanoid(_humanoid_scene(), realtime=False), has_gripper=False
    ),
    "ur_rtde": _real(
        "ur_rtde",
        lambda: FakeURController(rtde_port=0, script_port=0, gripper_port=0),
        _ur,
        unlock=FakeURController.release,  # the driver's e-stop is a protective stop
    ),
    "dobot": _real(
        "dobot",
        lambda: FakeDobot(dashboard_port=0, motion_port=0, feedback_port=0, clock_offset_ms=-3_600_000),
        _dobot,
    ),
    "rosbridge": _real(
        "rosbridge",
        lambda: FakeRosbridge(_ROS_JOINTS, max_velocity=2.0, clock_offset_ns=86_400 * 10**9),
        _rosbridge,
        has_gripper=False,
    ),
    "unitree_g1": _real(
        "unitree_g1",
        lambda: FakeG1(domain_id=next(_G1_DOMAINS), rate_hz=250),
        lambda fake: {"network_interface": "lo", "domain_id": fake.domain_id, "weight_ramp_s": 0.05},
        has_gripper=False,
    ),
    "inspire_hand": _real("inspire_hand", lambda: FakeInspireHand(full_stroke_s=0.2), _inspire),
    "dh_gripper": _real(
        "dh_gripper", lambda: FakeDHGripper(transport="tcp", full_stroke_s=0.2, init_s=0.05), _dh
    ),
}


_WITH_GRIPPER = sorted(name for name, case in DRIVERS.items() if case.has_gripper)
_WITHOUT_GRIPPER = sorted(name for name, case in DRIVERS.items() if not case.has_gripper)
_REAL = sorted(name for name, case in DRIVERS.items() if case.config is None)


@pytest.fixture(params=sorted(DRIVERS))
def case(request: pytest.FixtureRequest) -> Iterator[DriverCase]:
    case = DRIVERS[request.param]
    try:
        yield case
    finally:
        if case.cleanup is not None:
            case.cleanup()


@pytest.fixture
def driver(case: DriverCase) -> Iterator[RobotDriver]:
    robot = case.make()
    robot.connect()
    try:
        yield robot
    finally:
        robot.close()


def _command(names: tuple[str, ...], positions: np.ndarray) -> JointCommand:
    return JointCommand(Stamp.now("contract", 0), names, positions)


def _bounded(case: DriverCase, driver: RobotDriver) -> np.ndarray:
    """Mask of the joints with position limits."""
    return np.array([n not in case.unbounded_joints for n in driver.joint_names])


def _inside(
    case: DriverCase, driver: RobotDriver, fraction: float, start: np.ndarray | None = None
) -> np.ndarray:
    """Positions ``fraction`` of the way from each joint's lower to its upper limit; unbounded joints
    0.05 from ``start`` (the measured positions when None)."""
    limits = driver.limits
    bounded = _bounded(case, driver)
    out = (driver.read_state().positions if start is None else start) + 0.05
    out[bounded] = limits.lower[bounded] + fraction * (limits.upper[bounded] - limits.lower[bounded])
    return out


# -- the registry is covered ------------------------------------------------------------------------


def test_every_registered_robot_type_has_a_case() -> None:
    covered = {case.robot_type for case in DRIVERS.values()}
    missing = sorted(set(ROBOTS.names()) - covered)
    assert not missing, f"add a DriverCase to DRIVERS for {', '.join(missing)}"


def test_every_case_names_a_registered_type() -> None:
    assert {case.robot_type for case in DRIVERS.values()} <= set(ROBOTS.names())


@pytest.mark.parametrize("name", sorted(n for n, c in DRIVERS.items() if c.config is not None))
def test_stepped_sim_driver_matches_its_config(name: str) -> None:
    case = DRIVERS[name]
    assert case.config is not None
    built = ROBOTS.parse_config(case.config, "robots[0]").build()  # no I/O, no thread until connect()
    stepped = case.make()
    assert type(built) is type(stepped)
    assert built.name == _ID
    assert built.joint_names == stepped.joint_names
    for attr in ("lower", "upper", "velocity", "acceleration"):
        np.testing.assert_array_equal(getattr(built.limits, attr), getattr(stepped.limits, attr))


# -- the contract ----------------------------------------------------------------------------------


def test_driver_implements_the_protocol(driver: RobotDriver) -> None:
    assert isinstance(driver, RobotDriver)


@pytest.mark.parametrize("case", _REAL, indirect=True)
def test_real_driver_is_named_by_its_rig_id(driver: RobotDriver) -> None:
    assert driver.name == _ID


def test_connect_is_idempotent(driver: RobotDriver) -> None:
    before = driver.read_state().positions
    driver.connect()
    np.testing.assert_allclose(driver.read_state().positions, before, atol=1e-6)


def test_close_is_idempotent_and_ends_reads(case: DriverCase) -> None:
    robot = case.make()
    robot.connect()
    robot.close()
    robot.close()
    with pytest.raises(RobotError):
        robot.read_state()
    with pytest.raises(RobotError):
        robot.send(
            _command(robot.joint_names, _inside(case, robot, 0.5, start=np.zeros(len(robot.joint_names))))
        )


def test_read_state_is_stamped_and_shaped(driver: RobotDriver) -> None:
    first, second = driver.read_state(), driver.read_state()
    n = len(driver.joint_names)
    assert first.names == driver.joint_names
    assert first.positions.shape == first.velocities.shape == (n,)
    assert first.efforts.shape in ((n,), (0,))
    assert first.stamp.source_id == driver.name
    # Capture time in the common clock (a device clock mapped, not copied), not in the future.
    assert 0 < now_ns() - first.stamp.capture_ns < 10 * 10**9
    assert second.stamp.seq > first.stamp.seq
    assert np.all(np.isfinite(first.positions))


def test_limits_match_the_joint_names(case: DriverCase, driver: RobotDriver) -> None:
    limits = driver.limits
    bounded = _bounded(case, driver)
    assert limits.names == driver.joint_names
    assert set(case.unbounded_joints) <= set(driver.joint_names)
    assert np.all(np.isfinite(limits.lower[bounded]))
    assert np.all(np.isfinite(limits.upper[bounded]))
    assert np.all(np.isneginf(limits.lower[~bounded]))
    assert np.all(np.isposinf(limits.upper[~bounded]))
    assert np.all(limits.lower < limits.upper)
    assert np.all(limits.velocity > 0)
    assert np.all(limits.acceleration > 0)


def test_send_returns_the_command_sent(case: DriverCase, driver: RobotDriver) -> None:
    target = _inside(case, driver, 0.45)
    before = now_ns()
    applied = driver.send(_command(driver.joint_names, target))
    assert applied.names == driver.joint_names
    np.testing.assert_allclose(applied.positions, target, atol=1e-9)
    assert applied.stamp.source_id == driver.name
    assert before <= applied.stamp.capture_ns <= now_ns()  # stamped when applied, not when asked


def test_send_returns_a_subset_in_the_order_asked(case: DriverCase, driver: RobotDriver) -> None:
    names = driver.joint_names[::-1][:2]
    target = _inside(case, driver, 0.3)[::-1][:2]
    applied = driver.send(_command(names, target))
    assert applied.names == names
    np.testing.assert_allclose(applied.positions, target, atol=1e-9)


def test_send_clips_to_the_limits(case: DriverCase, driver: RobotDriver) -> None:
    limits = driver.limits
    bounded = _bounded(case, driver)
    sign = np.where(np.arange(len(driver.joint_names)) % 2, 1.0, -1.0)
    request = np.where(bounded, sign * 1e3, driver.read_state().positions + sign * 0.05)
    applied = driver.send(_command(driver.joint_names, request))
    expected = np.where(bounded, np.where(sign > 0, limits.upper, limits.lower), request)
    np.testing.assert_allclose(applied.positions, expected, atol=1e-9)


@pytest.mark.parametrize("case", _WITH_GRIPPER, indirect=True)
def test_send_gripper_returns_the_clipped_opening(driver: RobotDriver) -> None:
    applied = driver.send_gripper(GripperCommand(Stamp.now("contract", 0), opening=1.5))
    assert applied.opening == pytest.approx(1.0)
    assert applied.stamp.source_id == driver.name
    applied = driver.send_gripper(GripperCommand(Stamp.now("contract", 1), opening=-0.5))
    assert applied.opening == pytest.approx(0.0)


def test_has_gripper_tells_whether_send_gripper_moves_anything(case: DriverCase, driver: RobotDriver) -> None:
    assert driver.has_gripper is case.has_gripper


@pytest.mark.parametrize("case", _WITHOUT_GRIPPER, indirect=True)
def test_send_gripper_without_a_gripper_is_refused_with_the_fix(driver: RobotDriver) -> None:
    with pytest.raises(
        RobotError, match=rf"^{driver.name}: no gripper .*; remove the gripper from its binding$"
    ):
        driver.send_gripper(GripperCommand(Stamp.now("contract", 0), opening=1.0))


def test_unknown_joint_is_refused(driver: RobotDriver) -> None:
    with pytest.raises(RobotError, match="not found"):
        driver.send(_command(("no_such_joint",), np.zeros(1)))


def test_unknown_joint_among_known_ones_is_refused(driver: RobotDriver) -> None:
    names = (driver.joint_names[0], "no_such_joint")
    with pytest.raises(RobotError, match="no_such_joint"):
        driver.send(_command(names, driver.read_state().positions[:1].repeat(2)))


def test_state_follows_commands(case: DriverCase, driver: RobotDriver) -> None:
    _assert_follows_a_command(case, driver)


def test_reset_estop_rearms_the_robot(case: DriverCase, driver: RobotDriver) -> None:
    # `telerig safety reset` relies on it: every registered driver can be re-armed in software,
    # once the robot's own controls allow it.
    assert isinstance(driver, ResettableDriver)
    driver.estop()
    if case.unlock is not None:
        with pytest.raises(RobotError, match="pendant"):
            driver.reset_estop()
        case.unlock()
    driver.reset_estop()
    _assert_follows_a_command(case, driver)


def _assert_follows_a_command(case: DriverCase, driver: RobotDriver) -> None:
    start = driver.read_state().positions
    limits = driver.limits
    bounded = _bounded(case, driver)
    lower, upper = np.where(bounded, limits.lower, -1.0), np.where(bounded, limits.upper, 1.0)
    toward_middle = np.where(start < (lower + upper) / 2, 1.0, -1.0)
    step = np.where(bounded, np.minimum(0.1, (upper - lower) / 4), 0.1)
    target = start + toward_middle * step
    driver.send(_command(driver.joint_names, target))
    case.advance(driver, 1.0)
    moved = driver.read_state().positions - start
    assert np.all(np.sign(moved) == toward_middle)


def test_estop_latches_and_sends_are_not_applied(case: DriverCase, driver: RobotDriver) -> None:
    driver.estop()
    held = driver.read_state().positions
    limits = driver.limits
    bounded = _bounded(case, driver)
    far = np.where(held - limits.lower > limits.upper - held, limits.lower, limits.upper)
    far = np.where(bounded, far, held + 0.5)
    applied = driver.send(_command(driver.joint_names, far))
    assert np.all(np.abs(applied.positions - far) > 1e-3)  # the held targets, not the request
    assert applied.stamp.source_id == driver.name
    case.advance(driver, 0.5)
    np.testing.assert_allclose(driver.read_state().positions, held, atol=0.02)


@pytest.mark.parametrize("case", _WITH_GRIPPER, indirect=True)
def test_estop_holds_the_gripper(driver: RobotDriver) -> None:
    driver.send_gripper(GripperCommand(Stamp.now("contract", 0), opening=1.0))
    driver.estop()
    applied = driver.send_gripper(GripperCommand(Stamp.now("contract", 1), opening=0.0))
    assert applied.opening > 0.5  # still the open gripper it held, not the close request
    assert applied.stamp.source_id == driver.name
