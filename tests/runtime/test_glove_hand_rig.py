"""The shipped glove_hand rig: a data glove (fake bridge, real protocol) drives the simulated Inspire hand."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from telerig.config import load_rig
from telerig.ir.mcap_log import read_log, read_residuals
from telerig.ir.types import HandPose, JointCommand, JointState
from telerig.robots.sim.hand import MujocoHand
from telerig.runtime.rig import RigRuntime

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


def _streams(mcap: Path) -> tuple[dict[str, list[Any]], list[dict[str, Any]]]:
    """IR samples by stream (``<node>/<stream>``) and the residuals of ``hand0`` as
    ``{capture_ns, flagged, <metric>...}``."""
    samples: dict[str, list[Any]] = {}
    for entry in read_log(mcap):
        samples.setdefault(entry.topic.split("/", 3)[-1], []).append(entry.sample)
    residuals = [
        {"capture_ns": r.stamp.capture_ns, "flagged": r.flagged, **r.metrics()}
        for topic, r, _ in read_residuals(mcap)
        if topic.endswith("/hand0/residual")
    ]
    return samples, residuals


def test_glove_drives_the_hand_closed_and_open_smoothly_with_residuals_recorded(tmp_path: Path) -> None:
    rig = load_rig("glove_hand").model_copy(update={"cameras": []})
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        # 4 s: the chain's 1 s start ramp and a loaded host once left the index's sent targets
        # 0.74 rad of their swing at 3 s (the requests swung > 1 rad).
        result = runtime.run_episode(4.0)
        robot = runtime.robots["hand0"]
        assert isinstance(robot, MujocoHand)
        mimic_error = robot.mimic_error()
        flagged_ticks = runtime.controls["hand0"].stats.ik_flagged
    assert result.status == "complete"
    samples, residuals = _streams(result.path / "episode.mcap")
    assert all(isinstance(s, HandPose) for s in samples["glove/right_hand"])
    requested = [c for c in samples["hand0/joint_command_requested"] if isinstance(c, JointCommand)]
    assert len(requested) > 60  # 60 Hz glove for 4 s, with slack for a loaded machine
    assert all(c.stamp.source_id == "glove/right" and c.names == robot.joint_names for c in requested)

    # Fingers follow: the glove closes a fist within the first 1.2 s; the index motor swings > 1 rad
    # in the commands, the measured joint most of that, and the sent targets catch up with the requests.
    index = robot.joint_names.index("joint_r_index_proximal")
    q_req = np.array([c.positions for c in requested])
    sent = [c for c in samples["hand0/joint_command_sent"] if isinstance(c, JointCommand)]
    q_sent = np.array([c.positions for c in sent])
    states = [s for s in samples["hand0/joint_state"] if isinstance(s, JointState)]
    measured = np.array([s.positions for s in states])
    assert np.ptp(q_req[:, index]) > 1.0
    assert np.ptp(q_sent[:, index]) > 1.0
    # The measured joint stops at ~1.10 rad, where the fist's fingers meet (the targets ask ~1.5), and
    # reaches it only as the targets peak: 1.05 rad of swing on a quiet host, 0.84 once under a loaded
    # suite. 0.7 rad is most of the fist.
    assert np.ptp(measured[:, index]) > 0.7
    # The driver stamps what it applied when it applied it: for each request, how close the sends of
    # the next 50 ms came to it (the chain may spread a step over a few ticks).
    t_sent = np.array([c.stamp.capture_ns for c in sent])
    tracked = []
    for c, q in zip(requested, q_req, strict=True):
        window = (t_sent >= c.stamp.capture_ns) & (t_sent <= c.stamp.capture_ns + 50_000_000)
        if window.any():
            tracked.append(float(np.min(np.max(np.abs(q_sent[window] - q), axis=1))))
    assert len(tracked) > 30
    # The chain slows only the fast gesture transitions (and the start ramp); during the held
    # gestures the sent targets reach the requests.
    assert float(np.mean(np.array(tracked) < 0.01)) > 0.2  # the held gestures: ~30 % of the 3 s

    # Residuals: one record per retargeted sample, the mean vector error small.
    # (the recording window may open or close between a tick's request and its residual)
    assert abs(len(residuals) - len(requested)) <= 1
    assert sum(r["flagged"] for r in residuals) <= flagged_ticks
    errors = np.array([r["vector_error_m"] for r in residuals])
    assert float(np.median(errors)) < 0.03
    assert all(r["vectors_valid"] == 6 for r in residuals)

    # Nothing jumps: the chain bounds each sent step by the speed limit times the time since the
    # previous tick, capped at two control periods, however loaded the machine is.
    period = 1.0 / rig.robots[0].control_rate_hz  # type: ignore[attr-defined]
    steps = np.abs(np.diff(q_sent, axis=0))
    assert np.all(steps <= robot.limits.velocity[None, :] * 2 * period + 1e-9)
    assert float(np.max(np.abs(np.diff(measured, axis=0)))) < 0.15  # [rad] between states
    # The linkage held throughout: the mimic joints end on their couplings.
    assert mimic_error < 0.02
