"""The ``hand_vector`` retargeter config: registration, validation errors, build."""

from __future__ import annotations

import pytest

from telerig.errors import ConfigError
from telerig.registry import RETARGETERS
from telerig.retarget.hand.config import HandVectorConfig


def _parse(**fields: object) -> HandVectorConfig:
    cfg = RETARGETERS.parse_config({"type": "hand_vector", **fields}, "robots[0].retarget")
    assert isinstance(cfg, HandVectorConfig)
    return cfg


def test_hand_vector_is_registered() -> None:
    assert "hand_vector" in RETARGETERS.names()
    assert _parse().hand == "inspire"


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"hand": "shadow"}, "robots[0].retarget.hand: Input should be 'inspire', 'ability' or 'allegro'"),
        ({"beta": -1}, "robots[0].retarget.beta: Input should be greater than or equal to 0"),
        ({"vectors": [[0, 21]]}, "keypoint indices must be in [0, 20], got [0, 21]"),
        ({"vectors": [[4, 4]]}, "a vector needs two different keypoints"),
        ({"vectors": []}, "need at least one [origin, task] pair"),
        ({"min_confidence": 2}, "min_confidence: Input should be less than or equal to 1"),
        ({"finger_scales": [1, 1]}, "finger_scales[2]: Field required"),
        ({"alpha": 1}, "alpha: unknown field"),
    ],
)
def test_invalid_fields_give_one_line_errors(fields: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=r"^robots\[0\]\.retarget\.") as info:
        _parse(**fields)
    assert message in str(info.value)
    assert "\n" not in str(info.value)


@pytest.mark.sim
def test_a_vector_the_hand_lacks_is_a_config_error() -> None:
    with pytest.raises(
        ConfigError, match=r"hand_vector: allegro_right has no point for keypoint\(s\) \[20\]"
    ):
        _parse(hand="allegro", vectors=[[0, 20]]).build()


@pytest.mark.sim
def test_weights_must_match_the_vectors() -> None:
    with pytest.raises(ConfigError, match="weights must be 1 numbers"):
        _parse(vectors=[[0, 8]], weights=[1.0, 2.0]).build()


@pytest.mark.sim
def test_build_applies_the_fields() -> None:
    r = _parse(hand="ability", handedness="left", scale=1.1, beta=0.01, command="all").build()
    assert r.hand.name == "ability_left"
    assert r.optimizer.beta == 0.01
    assert r.joint_names == r.hand.joint_names
    assert r.alpha[0] == pytest.approx(1.1)
