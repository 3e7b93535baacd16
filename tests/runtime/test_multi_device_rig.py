"""Per-body-part assignment end to end: a UDP VR controller drives the arm while a glove's pinch drives
the gripper, each speaking its real protocol to its device, through Mosquitto, recorded in one episode."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from telerig.config import load_rig
from telerig.config.schema import EpisodeControlConfig
from telerig.devices.glove.fake import FakeGloveBridge
from telerig.devices.udp_vr.fake import FakeVrSender
from telerig.ir.mcap_log import read_log
from telerig.ir.types import ControllerState, GripperCommand, HandPose, JointCommand
from telerig.runtime.rig import RigRuntime

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def test_vr_controller_drives_the_arm_and_glove_pinch_drives_the_gripper(tmp_path: Path) -> None:
    rig = load_rig("quest_glove")
    vr_port = _free_udp_port()
    with FakeGloveBridge(port=0, rate_hz=120.0) as glove:
        quest_cfg, glove_cfg = rig.devices
        rig = rig.model_copy(
            update={
                "devices": [
                    quest_cfg.model_copy(update={"host": "127.0.0.1", "port": vr_port}),
                    glove_cfg.model_copy(update={"port": glove.port}),
                ],
                "cameras": [],
                # The fake presses a different button every 4 s cycle (x = restart the episode at 4 s):
                # here the buttons only drive the arm and gripper, no session command.
                "episode_control": EpisodeControlConfig(device="quest", buttons={}),
            }
        )
        with FakeVrSender(vr_port, rate_hz=90.0) as quest, RigRuntime(rig, data_root=tmp_path) as runtime:
            quest.start()  # this fake's context manager only owns the socket
            # 6 s: on this 2-core host 4 s gave 26-38 commands (control ticks stalled 200 ms, at
            # c5d7832 as after it), 2.5 s under 50 on a loaded one.
            result = runtime.run_episode(6.0)
    assert result.status == "complete"
    by_stream: dict[str, list[object]] = {}
    for entry in read_log(result.path / "episode.mcap"):
        by_stream.setdefault(entry.topic.split("/", 3)[-1], []).append(entry.sample)
    assert all(isinstance(s, ControllerState) for s in by_stream["quest/right_controller"])
    assert all(isinstance(s, HandPose) for s in by_stream["glove/right_hand"])
    requested = by_stream["arm0/joint_command_requested"]
    # Enough to show the VR drives the arm, not a rate check (benchmarks measure rates): this
    # 2-core host published 42-87 in 6 s, at c5d7832 as after it (control ticks stalled 200 ms).
    assert len(requested) > 30
    assert all(isinstance(s, JointCommand) and s.stamp.source_id.startswith("quest/") for s in requested)
    grips = [s for s in by_stream["arm0/gripper_command_requested"] if isinstance(s, GripperCommand)]
    assert len(grips) > 30
    assert all(s.stamp.source_id.startswith("glove/") for s in grips)
    openings = {round(s.opening, 1) for s in grips}
    assert len(openings) > 2  # the fake glove cycles through open, fist, point and pinch
