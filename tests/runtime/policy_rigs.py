"""Shared by the policy rollout tests: a real tiny checkpoint (written in a child process, so torch
never enters the test's control process), rigs that roll it out, and loaders for the inference
process (a slow policy wraps the real runner)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from telerig.config.schema import RigConfig

UR5E = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
NAMES = (*UR5E, "gripper")


def tiny_checkpoint(path: Path, *, fps: float = 30.0) -> Path:
    """A real, untrained ``bc`` checkpoint of the UR5e + gripper state, camera ``scene`` at 24x32."""
    code = (
        "import sys; from telerig.policy.checkpoint import tiny_for_tests; "
        f"tiny_for_tests(sys.argv[1], state_names={NAMES!r}, camera_keys=('scene',), "
        f"image_size=(24, 32), fps={fps})"
    )
    subprocess.run([sys.executable, "-c", code, str(path)], check=True, timeout=120)
    return path


def policy_rig(
    checkpoint: Path,
    *,
    loader: str | None = None,
    operator: bool = False,
    clutch: tuple[float, float] | None = None,
    rate_hz: float = 30.0,
    deadline_ms: float | None = None,
    name: str = "rollout",
) -> RigConfig:
    """The demo arm driven by a ``policy`` device, its scene camera publishing 32x24 observations;
    with ``operator``, a scripted VR controller bound at a higher priority (relative mode, clutch
    ``a``; its grip is held throughout) that takes over while the clutch is held (from
    ``clutch[0]`` to ``clutch[1]`` s of its 12 s cycle)."""
    policy: dict[str, Any] = {
        "id": "pi0",
        "type": "policy",
        "checkpoint": str(checkpoint),
        "robot": "arm0",
        "rate_hz": rate_hz,
    }
    if loader is not None:
        policy["loader"] = loader
    if deadline_ms is not None:
        policy["deadline_ms"] = deadline_ms
    devices: list[dict[str, Any]] = [policy]
    bindings: list[dict[str, Any]] = [
        {
            "device": "pi0",
            "part": "joints",
            "robot": "arm0",
            "target": "arm",
            "retargeter": {"type": "joint_passthrough"},
        },
        {
            "device": "pi0",
            "part": "joints",
            "robot": "arm0",
            "target": "gripper",
            "retargeter": {"type": "joint_gripper"},
        },
    ]
    if operator:
        devices.append(
            {
                "id": "vr0",
                "type": "scripted_vr",
                "hand": "right",
                "rate_hz": 100,
                "home": [0.4, 0.0, 1.1],
                "pick": [0.41, 0.0, 0.78],
                "place": [0.37, -0.23, 0.78],
                "cycle_s": 12.0,
                # The operator holds the clutch (the takeover button) during this part of the cycle.
                "presses": [{"button": "a", "start_s": clutch[0], "end_s": clutch[1]}] if clutch else [],
            }
        )
        bindings.append(
            {
                "device": "vr0",
                "part": "right_controller",
                "robot": "arm0",
                "target": "arm",
                "priority": 10,
                "retargeter": {"type": "arm_pose", "mode": "relative", "clutch_button": "a"},
            }
        )
    return RigConfig.model_validate(
        {
            "name": name,
            "devices": devices,
            "robots": [
                {"id": "arm0", "type": "mujoco_arm", "model": "ur5e_robotiq85", "control_rate_hz": 100}
            ],
            "cameras": [
                {
                    "id": "scene",
                    "type": "mujoco",
                    "robot": "arm0",
                    "camera": "scene",
                    "width": 160,
                    "height": 120,
                    "fps": 15,
                    "preview": {"enabled": False},
                    "observation": {"width": 32, "height": 24, "rate_hz": 15},
                }
            ],
            "bindings": bindings,
            "safety": {"start_ramp_s": 1.0, "hold_timeout_ms": 100, "watchdog_timeout_ms": 250},
            "recording": {"episode_duration_s": 3.0, "task": "policy rollout", "operator": "policy"},
        }
    )


class _Slow:
    """The real runner, answering in time for its first ``fast`` calls and ``delay_s`` late after."""

    def __init__(self, runner: Any, fast: int, delay_s: float) -> None:
        self.spec = runner.spec
        self._runner = runner
        self._fast = fast
        self._delay_s = delay_s
        self._calls = 0

    def act(self, state: Any, images: Any) -> Any:
        self._calls += 1
        if self._calls > self._fast:
            time.sleep(self._delay_s)
        return self._runner.act(state, images)


def load_slow(checkpoint: str, threads: int = 1) -> _Slow:
    """Loader (``policy_rigs:load_slow``): 8 actions in time (0.27 s at 30 Hz), then each 0.6 s late."""
    from telerig.policy.runner import load_policy

    return _Slow(load_policy(checkpoint, threads=threads), fast=8, delay_s=0.6)
