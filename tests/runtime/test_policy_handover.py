"""The handover's rules and the joint passthrough, without a rig (fast): who drives when, the
hand-back delay, commands, and the blend-in after a reset."""

from __future__ import annotations

import numpy as np
import pytest

from telerig.errors import ConfigError
from telerig.ir.types import ControllerState, GripperCommand, JointCommand, Stamp
from telerig.retarget.joints.passthrough import JointGripper, JointPassthrough
from telerig.runtime.handover import Handover, Source

MS = 1_000_000


def _controller(t_ns: int, *buttons: str) -> ControllerState:
    stamp = Stamp("vr0/right", t_ns, t_ns, t_ns)
    return ControllerState(stamp, "right", np.zeros(3), np.array([1.0, 0, 0, 0]), "op", frozenset(buttons))


def _action(t_ns: int, q: list[float], names: tuple[str, ...] = ("a", "b", "gripper")) -> JointCommand:
    return JointCommand(Stamp("pi0/joints", t_ns, t_ns, t_ns), names, np.array(q))


def _handover() -> tuple[Handover, Source, Source]:
    policy = Source("pi0", "pi0", "policy", 0)
    operator = Source("vr0", "vr0", "operator", 10, takeover_button="a")
    return Handover([policy, operator], hand_back_s=0.5), policy, operator


def test_the_engaged_operator_takes_over_and_hands_back_after_the_delay() -> None:
    h, policy, operator = _handover()
    assert h.select({}, 1 * MS) == (None, False)  # nobody acted yet
    t = 10 * MS
    assert h.select({"pi0": _action(t, [0, 0, 1])}, t) == (policy, False)
    # The operator streams without its button: the policy keeps driving.
    assert h.select({"pi0": _action(t, [0, 0, 1]), "vr0": _controller(t)}, t + MS)[0] is policy
    # Button down: takeover (an intervention).
    assert h.select({"vr0": _controller(t, "a"), "pi0": _action(t, [0, 0, 1])}, t + 2 * MS) == (
        operator,
        True,
    )
    assert (h.handovers, h.interventions) == (1, 1)
    # Released: control stays 0.5 s (a re-clutch keeps it), then goes back.
    released = t + 100 * MS
    assert (
        h.select({"vr0": _controller(released), "pi0": _action(released, [0, 0, 1])}, released)[0] is operator
    )
    later = released + 400 * MS
    assert h.select({"vr0": _controller(later), "pi0": _action(later, [0, 0, 1])}, later)[0] is operator
    back = released + 600 * MS
    assert h.select({"vr0": _controller(back), "pi0": _action(back, [0, 0, 1])}, back) == (policy, True)
    assert (h.handovers, h.interventions) == (2, 1)
    state = h.state()
    assert state["active"] == "pi0"
    assert state["kind"] == "policy"


def test_a_silent_policy_keeps_the_part_until_someone_engages() -> None:
    h, policy, _ = _handover()
    h.select({"pi0": _action(MS, [0, 0, 1])}, MS)
    # Its samples stop: nobody is engaged, it keeps the part (the chain holds, then stops).
    assert h.select({}, 2000 * MS) == (policy, False)


def test_commands_pin_the_operator_and_hand_back() -> None:
    h, policy, operator = _handover()
    h.select({"pi0": _action(MS, [0, 0, 1])}, MS)
    assert h.command(" OPERATOR\n")
    assert h.select({"pi0": _action(2 * MS, [0, 0, 1])}, 2 * MS) == (operator, True)  # no button needed
    assert h.command("policy")
    assert h.select({"pi0": _action(3 * MS, [0, 0, 1])}, 3 * MS) == (policy, True)
    # After 'policy' the operator's next press still takes over (safety first).
    assert h.select({"vr0": _controller(4 * MS, "a")}, 4 * MS) == (operator, True)
    assert not h.command("auto")  # the press already ended the pin: nothing changes
    for junk in ("", "take over", "operator;policy", "x" * 5000, "\x00"):
        with pytest.raises(ValueError, match="control command"):
            h.command(junk)


def test_sources_of_one_part_need_different_priorities() -> None:
    with pytest.raises(ConfigError, match="different priorities"):
        Handover([Source("a", "a", "policy", 0), Source("b", "b", "operator", 0)])
    with pytest.raises(ConfigError, match="at least one"):
        Handover([])


def test_the_passthrough_maps_by_name_and_blends_in_after_a_reset() -> None:
    p = JointPassthrough("arm0", ("b", "a"), blend_s=0.1)
    q0 = np.array([1.0, 1.0])
    cmd, residual = p(_action(MS, [0.0, 2.0, 0.5]), q0, 0.05)  # half way through the blend
    assert residual is None
    assert cmd is not None
    assert cmd.names == ("b", "a")
    np.testing.assert_allclose(cmd.positions, [1.5, 0.5])
    cmd, _ = p(_action(2 * MS, [0.0, 2.0, 0.5]), q0, 0.05)
    assert cmd is not None
    np.testing.assert_allclose(cmd.positions, [2.0, 0.0])  # blended in
    p.reset()
    cmd, _ = p(_action(3 * MS, [0.0, 2.0, 0.5]), np.array([2.0, 0.0]), 0.05)
    assert cmd is not None
    np.testing.assert_allclose(cmd.positions, [2.0, 0.0])
    # Prefixed names (multi-robot exports) are accepted; missing joints send nothing and are counted.
    cmd, _ = p(_action(4 * MS, [3.0, 4.0], ("arm0.a", "arm0.b")), q0, 0.2)
    assert cmd is not None
    assert p(_action(5 * MS, [3.0], ("a",)), q0, 0.01) == (None, None)
    assert p.mismatched == 1
    with pytest.raises(ValueError, match="blend_s"):
        JointPassthrough("arm0", ("a",), blend_s=float("nan"))


def test_the_gripper_reads_the_gripper_entry_clipped() -> None:
    g = JointGripper()
    assert g(_action(MS, [0, 0, 1.7])) == GripperCommand(_action(MS, [0, 0, 1.7]).stamp, 1.0)
    out = g(_action(MS, [0, 0, -0.3]))
    assert out is not None
    assert out.opening == 0.0
    assert g(_action(MS, [0, 0, float("nan")])) is None
    assert g(_action(MS, [0, 0], ("a", "b"))) is None
    assert g(_controller(MS)) is None
