"""The recorded 'robot never jumps' check shared by the rig tests whose commands pass the safety chain.

Between two sent commands a joint moves at most its velocity limit over the chain's longest tick
(two control periods). The one larger step the chain makes on purpose is a watchdog stop on a
starved control loop (a loaded host): it commands the arm to stay *where it was measured*, which can
differ from the last command by the arm's tracking error. So a larger step passes only when that
command is where the arm was measured within 30 ms of it: a jump is a command away from the arm.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from telerig.ir.mcap_log import read_log
from telerig.ir.types import FloatArray, JointCommand, JointState

__all__ = ["assert_no_jump", "assert_steps_bounded"]


def assert_no_jump(
    mcap: Path, robot_topic: str, bound: FloatArray, *, max_stops: int = 3
) -> tuple[float, int]:
    """Check ``<robot_topic>/joint_command_sent`` of ``mcap`` against ``bound`` [rad per step].

    Returns the largest step [rad] and the number of watchdog stops at the measured pose.
    """
    sent: list[tuple[float, FloatArray]] = []
    measured: list[tuple[float, FloatArray]] = []
    for e in read_log(mcap, topics=[f"{robot_topic}/joint_command_sent", f"{robot_topic}/joint_state"]):
        t = e.log_time_ns / 1e9
        if isinstance(e.sample, JointCommand):
            sent.append((t, np.asarray(e.sample.positions)))
        elif isinstance(e.sample, JointState):
            measured.append((t, np.asarray(e.sample.positions)))
    assert len(sent) > 1, f"no commands on {robot_topic}/joint_command_sent"
    return assert_steps_bounded(sent, measured, bound, max_stops=max_stops)


def assert_steps_bounded(
    sent: list[tuple[float, FloatArray]],
    measured: list[tuple[float, FloatArray]],
    bound: FloatArray,
    *,
    max_stops: int = 3,
) -> tuple[float, int]:
    """The check on (time [s], positions) of the sent commands and the measured states, in order.

    Returns the largest step [rad] and the number of watchdog stops at the measured pose.
    """
    q = np.array([s[1] for s in sent])
    steps = np.abs(np.diff(q, axis=0))
    measured_t = np.array([m[0] for m in measured])
    stops = 0
    for i in np.flatnonzero(np.any(steps > bound + 1e-9, axis=1)):
        t, target = sent[i + 1]
        # The stop commands the pose measured that tick; a starved loop (a loaded host) records the
        # states around it sparser, so look up to 0.1 s either side.
        near = np.flatnonzero(np.abs(measured_t - t) <= 0.1)
        gaps = [float(np.abs(target - measured[j][1]).max()) for j in near]
        assert gaps, (i, steps[i], "no measured state near this command")
        assert min(gaps) <= float(np.max(bound)), (i, steps[i], gaps)
        stops += 1
    assert stops <= max_stops, stops
    return float(steps.max()), stops
