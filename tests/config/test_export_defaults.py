"""A rig's ``export:`` section: the dataset rate and resampling its episodes export with."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from telerig.config import load_rig
from telerig.config.export import ExportDefaults


def test_a_shipped_rig_exports_with_the_built_in_defaults() -> None:
    assert load_rig("demo").export == ExportDefaults()


def test_the_section_parses_rate_policies_and_normalization() -> None:
    section = {"fps": 15, "resample": {"joint_state": "nearest"}, "normalize": True}
    rig = load_rig("demo").model_validate({**load_rig("demo").model_dump(mode="json"), "export": section})
    assert rig.export == ExportDefaults(fps=15, resample={"joint_state": "nearest"}, normalize=True)


BAD = [
    {"fps": 0},
    {"fps": 10_000},
    {"resample": {"joint_state": "cubic"}},
    {"resample": {"../x": "zoh"}},
    {"speed": 1},
]


@pytest.mark.parametrize("section", BAD)
def test_a_bad_section_is_refused(section: dict[str, object]) -> None:
    with pytest.raises(ValidationError):
        ExportDefaults.model_validate(section)
