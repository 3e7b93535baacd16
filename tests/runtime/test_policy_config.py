"""A policy rig that cannot work is refused before anything moves, with one line saying what to fix:
a damaged checkpoint, a camera without observation frames, an operator who would take over in
absolute mode, two sources of one part at the same priority; and a policy's observation camera
publishes small frames at a bounded rate."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from telerig.bus.memory import InMemoryBus
from telerig.cameras.observation import ObservationPublisher
from telerig.config.schema import RigConfig
from telerig.errors import ConfigError, DeviceError
from telerig.ir.observation import decode_observation
from telerig.runtime.rig import RigRuntime

if str(Path(__file__).parent) not in sys.path:
    sys.path.insert(0, str(Path(__file__).parent))
from policy_rigs import policy_rig, tiny_checkpoint

pytestmark = [pytest.mark.sim, pytest.mark.broker, pytest.mark.slow]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt")


def test_a_damaged_checkpoint_is_refused_in_one_line(tmp_path: Path) -> None:
    damaged = tmp_path / "damaged.pt"
    damaged.write_bytes(b"PK\x03\x04 not a checkpoint" * 10)
    with (
        pytest.raises(DeviceError, match=r"damaged\.pt") as info,
        RigRuntime(policy_rig(damaged), data_root=tmp_path),
    ):
        pass
    assert "\n" not in str(info.value)


def test_a_camera_without_observation_is_refused(checkpoint: Path, tmp_path: Path) -> None:
    rig = policy_rig(checkpoint)
    camera = rig.cameras[0].model_copy(update={"observation": None})
    rig = rig.model_copy(update={"cameras": [camera]})
    with pytest.raises(ConfigError, match="set observation"), RigRuntime(rig, data_root=tmp_path):
        pass


def test_an_absolute_operator_cannot_take_over(checkpoint: Path, tmp_path: Path) -> None:
    raw = policy_rig(checkpoint, operator=True).model_dump(mode="json")
    raw["bindings"][-1]["retargeter"] = {"type": "absolute_pose"}
    with (
        pytest.raises(ConfigError, match="relative mode"),
        RigRuntime(RigConfig.model_validate(raw), data_root=tmp_path),
    ):
        pass


def test_two_sources_of_one_part_at_the_same_priority_are_refused(checkpoint: Path) -> None:
    raw = policy_rig(checkpoint, operator=True).model_dump(mode="json")
    raw["bindings"][-1]["priority"] = 0
    with pytest.raises(ValidationError, match="same priority"):
        RigConfig.model_validate(raw)


def test_observation_frames_are_small_and_rate_bounded() -> None:
    bus = InMemoryBus()
    got: list[bytes] = []
    done = threading.Event()
    bus.subscribe("telerig/v1/r/cam/observation", lambda m: (got.append(m.payload), done.set()))
    publisher = ObservationPublisher(bus, "r", "cam", width=32, height=24, rate_hz=10.0)
    image = np.zeros((480, 640, 3), np.uint8)
    image[:, 320:] = 200  # right half bright: survives the area resize
    taken = 0
    for i in range(60):  # 60 frames at 30 Hz capture time = 2 s: 20 due at 10 Hz
        taken += publisher.offer(image, 1_000_000_000 + i * 33_333_333)
        time.sleep(0.005)
    publisher.close()
    assert 1 <= taken <= 20
    assert publisher.rate_skipped >= 40
    assert len(got) == publisher.published == taken
    frame = decode_observation(got[-1])
    assert frame.image.shape == (24, 32, 3)
    assert frame.image[:, :14].max() < 10
    assert frame.image[:, 18:].min() > 190
