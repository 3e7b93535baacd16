"""SimDriverLink: the connect / close / step / e-stop latch every simulated driver shares (issue 12)."""

from __future__ import annotations

import mujoco
import pytest

from telerig.errors import RobotError
from telerig.robots.sim.arm import SimDriverLink, SimPhysics

pytestmark = pytest.mark.sim

_XML = """
<mujoco>
  <worldbody>
    <body><joint name="hinge" type="hinge"/><geom type="capsule" size="0.02" fromto="0 0 0 0.2 0 0"/></body>
  </worldbody>
  <actuator><position name="servo" joint="hinge" kp="10"/></actuator>
</mujoco>
"""


def _link(realtime: bool = False) -> SimDriverLink:
    physics = SimPhysics(mujoco.MjModel.from_xml_string(_XML), name="one", realtime=realtime)
    return SimDriverLink(physics, "one")


def test_step_needs_a_connection_and_advances_the_physics() -> None:
    link = _link()
    with pytest.raises(RobotError, match="one: driver is not connected; call connect\\(\\) first"):
        link.step(3)
    link.connect()
    link.connect()  # idempotent
    link.step(3)
    with link.physics.locked() as (model, data):
        assert data.time == pytest.approx(3 * model.opt.timestep)
    link.close()


def test_close_is_idempotent_and_a_closed_link_cannot_connect() -> None:
    link = _link()
    link.connect()
    link.close()
    link.close()
    assert not link.physics.running
    with pytest.raises(RobotError, match="one: driver is closed; create a new one"):
        link.connect()
    with pytest.raises(RobotError, match="one: driver is closed"):
        link.step()


def test_step_in_real_time_is_refused_naming_the_fix() -> None:
    link = _link(realtime=True)
    link.connect()
    try:
        with pytest.raises(RobotError, match="step\\(\\) needs realtime=False"):
            link.step()
    finally:
        link.close()


def test_latch_sets_the_hold_under_the_lock_and_reset_releases_it() -> None:
    link = _link()
    link.connect()
    seen: list[bool] = []

    def hold(data: mujoco.MjData) -> None:
        seen.append(link.physics.lock.locked())
        data.ctrl[0] = 0.25

    link.latch(hold)
    assert link.estopped
    assert seen == [True]
    with link.physics.locked() as (_, data):
        assert data.ctrl[0] == 0.25
    link.reset_estop()
    assert not link.estopped
    link.close()


def test_join_runs_only_when_the_shared_physics_already_runs() -> None:
    first = _link()
    second = SimDriverLink(first.physics, "two")
    joined: list[str] = []
    first.connect(join=lambda data: joined.append("first"))
    second.connect(join=lambda data: joined.append("second"))
    assert joined == ["second"]
    first.close()
    assert first.physics.running  # the second driver still holds it
    second.close()
    assert not first.physics.running
