"""Quality-gate thresholds in the rig file: defaults from issue 13, validation, loading."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from telerig.config import load_rig, shipped_rig_path
from telerig.config.qa import GATES, QaThresholds


def test_defaults_are_the_issue_values() -> None:
    t = QaThresholds()
    assert t.fall_height_fraction == 0.5
    assert t.joint_limit_margin == 0.05
    assert t.max_missing_fraction == 0.02
    assert t.max_gap_ms == 50.0
    assert t.alignment_tolerance_ms is None
    assert t.gates == GATES


def test_rig_file_without_qa_section_gets_defaults() -> None:
    assert load_rig(shipped_rig_path("demo")).qa == QaThresholds()


def test_unknown_gate_is_refused() -> None:
    with pytest.raises(ValidationError, match="gates"):
        QaThresholds.model_validate({"gates": ["fall", "wobble"]})


def test_repeated_gate_is_refused() -> None:
    with pytest.raises(ValidationError, match="listed twice: idle"):
        QaThresholds(gates=("idle", "idle"))


def test_unknown_threshold_is_refused() -> None:
    with pytest.raises(ValidationError, match="drift_deg"):
        QaThresholds.model_validate({"drift_deg": 3})
