"""A trained policy drives the simulated arm through the same bindings, safety chain and recorder as
an operator (issue 16): a real tiny checkpoint of the real network, inference in its own process,
the scene camera's observation frames over Mosquitto. A slow policy is a missed sample to the
chain: it holds, then its watchdog stops the robot, while the control loop keeps ticking."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from telerig.devices.policy.device import PolicyDevice
from telerig.ir.mcap_log import read_control_sources, read_log
from telerig.ir.types import GripperCommand, JointCommand
from telerig.runtime.rig import RigRuntime
from telerig.store.episodes import EpisodeStore
from telerig.store.qa_file import read_qa

# The shared helpers (and the slow policy's loader, which the spawned inference process imports by
# name: it inherits this sys.path) live beside this file; the suite imports with importlib mode.
if str(Path(__file__).parent) not in sys.path:
    sys.path.insert(0, str(Path(__file__).parent))
from policy_rigs import policy_rig, tiny_checkpoint

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt")


def _sent(mcap: Path, rig: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Recorder times [s], tick numbers (the stamps' seq) and positions of every joint command sent
    to arm0, in order."""
    topic = f"telerig/v1/{rig}/arm0/joint_command_sent"
    entries = list(read_log(mcap, topics=[topic]))
    assert all(isinstance(e.sample, JointCommand) for e in entries)
    t = np.array([e.log_time_ns for e in entries]) / 1e9
    seq = np.array([e.sample.stamp.seq for e in entries])
    q = np.array([e.sample.positions for e in entries])  # type: ignore[union-attr]
    return t, seq, q


def test_a_policy_rolls_out_through_the_safety_chain_and_is_recorded(
    checkpoint: Path, tmp_path: Path
) -> None:
    rig = policy_rig(checkpoint)
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        device = runtime.devices["pi0"].device
        assert isinstance(device, PolicyDevice)
        assert device.info is not None
        # Inference runs in its own process.
        assert device._process is not None
        assert device._process.pid not in (None, os.getpid())
        info = device.info
        limits = runtime.robots["arm0"].limits
        result = runtime.run_episode(3.0)
        stats = dict(device.stats)
        # The rollout goes through the quality gates like any episode (in the QA worker).
        outcome = runtime.storage.qa_outcome(result.episode_id, 180.0)
    assert result.status == "complete"
    assert outcome is not None
    store = EpisodeStore(tmp_path)
    assert read_qa(store.find(result.episode_id).path) is not None
    # Marked in the manifest as a policy episode with the checkpoint's id and hash.
    policy: Any = store.get(result.episode_id).extra["policy"]
    assert isinstance(policy, dict)
    assert policy["episode"] == "rollout"
    mark = policy["devices"]["pi0"]
    assert mark["checkpoint_id"] == info.checkpoint_id
    assert len(info.checkpoint_id) == 12
    assert mark["checkpoint_sha256"].startswith(info.checkpoint_id)
    assert len(mark["checkpoint_sha256"]) == 64
    assert mark["checkpoint"] == str(checkpoint)
    assert mark["stats"]["actions"] == stats["actions"]
    assert policy["control"]["arm0"]["interventions"] == 0
    mcap = store.find(result.episode_id).path / "episode.mcap"
    actions = [e.sample for e in read_log(mcap, topics=["telerig/v1/rollout/pi0/joints"])]
    assert len(actions) >= 5, str(stats)  # ~90 at 30 Hz over 3 s; a loaded 2-core host loses many
    assert all(isinstance(a, JointCommand) and a.names[-1] == "gripper" for a in actions)
    assert stats["actions"] >= len(actions), str(stats)
    assert stats["bad_frames"] == 0
    # Every control tick says the policy drove.
    control = [c for _, c, _ in read_control_sources(mcap, topics=["telerig/v1/rollout/arm0/control_source"])]
    assert len(control) >= 100
    assert {c.stamp.source_id for c in control} == {"arm0"}
    drivers = [(c.source, c.kind) for c in control]
    first = drivers.index(("pi0", "policy"))  # nobody drives before the policy's first action
    assert set(drivers[:first]) <= {(None, "none")}
    assert set(drivers[first:]) == {("pi0", "policy")}
    # The chain's limits hold: no command steps further than the joints' velocity limits allow in
    # the longest tick the chain accounts for (2 control periods at 100 Hz). Only consecutive ticks
    # are compared: a sample the recording lost on a loaded host would make one step span two.
    _, seq, q = _sent(mcap, "rollout")
    assert len(q) >= 100
    consecutive = np.diff(seq) == 1
    assert consecutive.sum() >= 0.9 * len(consecutive)
    step = np.abs(np.diff(q, axis=0))[consecutive].max(axis=0)
    assert np.all(step <= limits.velocity * 0.02 + 1e-9), step
    # The arm went towards the policy's (clipped) target.
    target = np.clip(actions[-1].positions[:6], limits.lower, limits.upper)  # type: ignore[union-attr]
    start, end = np.linalg.norm(q[0] - target), np.linalg.norm(q[-1] - target)
    assert end < start - 0.1, (start, end)  # a few tenths of a radian in 3 s even on a loaded host
    # The gripper followed the policy's gripper entry through the gripper chain.
    grips = [e.sample for e in read_log(mcap, topics=["telerig/v1/rollout/arm0/gripper_command_sent"])]
    assert grips
    assert all(isinstance(g, GripperCommand) and 0.0 <= g.opening <= 1.0 for g in grips)


def test_a_slow_policy_is_a_missed_sample_the_chain_holds_then_stops(
    checkpoint: Path, tmp_path: Path
) -> None:
    rig = policy_rig(checkpoint, loader="policy_rigs:load_slow", name="slowroll")
    with RigRuntime(rig, data_root=tmp_path) as runtime:
        control = runtime.controls["arm0"]
        device = runtime.devices["pi0"].device
        assert isinstance(device, PolicyDevice)
        result = runtime.run_episode(3.5)
        stats, events, ticks = dict(device.stats), dict(control.stats.safety_events), control.stats.ticks
    assert result.status == "complete"
    assert stats["late"] >= 1, stats
    assert events.get("input_stale", 0) >= 1, events
    assert events.get("watchdog_stop", 0) >= 1, events
    # The loop never waited for the policy: it ticked on at the control rate (100 Hz) while the
    # policy was late (a lenient floor for a loaded 2-core host).
    assert ticks >= 150, ticks
    # After the stop the robot holds still: the last 0.5 s of commands do not move.
    t, _, q = _sent(result.path / "episode.mcap", "slowroll")
    tail = q[t >= t[-1] - 0.5]
    assert len(tail) >= 10
    assert np.ptp(tail, axis=0).max() < 1e-9


def test_the_control_process_never_imports_torch() -> None:
    code = (
        "import sys, telerig.runtime.rig, telerig.devices.policy.device, telerig.devices.policy.config, "
        "telerig.retarget.joints.config; assert 'torch' not in sys.modules, 'torch was imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
