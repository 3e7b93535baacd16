"""Rig fingerprint: stable over irrelevant changes, differs on cameras, rates, robots; checked per store."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from pydantic import JsonValue

from telerig.config import load_rig
from telerig.config.schema import RigConfig
from telerig.errors import RecordingError
from telerig.store.episodes import EpisodeStore
from telerig.store.fingerprint import (
    MANIFEST_KEY,
    RigFingerprint,
    check_compatible,
    fingerprint,
    rig_fingerprint,
)


def _demo(**changes: Any) -> RigConfig:
    """The shipped demo rig with top-level sections replaced, re-validated."""
    data = load_rig("demo").model_dump(mode="json", serialize_as_any=True)
    for path, value in changes.items():
        node: Any = data
        keys = path.split("__")
        for key in keys[:-1]:
            node = node[int(key)] if isinstance(node, list) else node[key]
        node[keys[-1]] = value
    return RigConfig.model_validate(data)


def _commit(store: EpisodeStore, extra: dict[str, JsonValue]) -> str:
    draft = store.begin(rig="demo", task="pick", operator="alice")
    return draft.commit(extra).id


def test_fingerprint_is_stable_across_loads() -> None:
    assert fingerprint(load_rig("demo")) == fingerprint(load_rig("demo"))
    assert len(fingerprint(load_rig("demo"))) == 16


def test_fingerprint_ignores_task_operator_and_safety() -> None:
    changed = _demo(recording__task="stack", recording__operator="bob", safety__start_ramp_s=1.0)
    assert fingerprint(changed) == fingerprint(load_rig("demo"))


def test_fingerprint_components_name_what_matters() -> None:
    c = rig_fingerprint(load_rig("demo")).components
    assert c["camera scene"] == "640x480@30"
    assert c["robot arm0"] == "mujoco_arm ur5e_robotiq85"
    assert c["robot arm0 control"] == "100 Hz"
    assert c["device vr0"] == "scripted_vr @100 Hz"
    assert c["schema"].startswith("wire v")


@pytest.mark.parametrize(
    ("change", "component"),
    [
        ({"cameras__0__width": 1280, "cameras__0__height": 720}, "camera scene"),
        ({"cameras__0__fps": 15}, "camera scene"),
        ({"devices__0__rate_hz": 50}, "device vr0"),
        ({"robots__0__control_rate_hz": 250}, "robot arm0 control"),
    ],
)
def test_fingerprint_changes_with(change: dict[str, Any], component: str) -> None:
    base, other = rig_fingerprint(load_rig("demo")), rig_fingerprint(_demo(**change))
    assert base.digest != other.digest
    assert [d[0] for d in base.differences(other)] == [component]


def test_json_round_trip() -> None:
    fp = rig_fingerprint(load_rig("demo"))
    assert RigFingerprint.from_json(fp.to_json()) == fp
    assert RigFingerprint.from_json(fp.to_json()).digest == fp.to_json()["digest"]


def test_check_compatible_accepts_an_empty_store_and_matching_episodes(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    check_compatible(store, load_rig("demo"))
    _commit(store, {MANIFEST_KEY: rig_fingerprint(load_rig("demo")).to_json()})
    _commit(store, {})  # recorded before fingerprints: not compared
    check_compatible(store, load_rig("demo"))


def test_check_compatible_names_the_differing_camera_in_one_line(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    stored_id = _commit(store, {MANIFEST_KEY: rig_fingerprint(load_rig("demo")).to_json()})
    wide = _demo(cameras__0__width=1280, cameras__0__height=720)
    with pytest.raises(RecordingError) as info:
        check_compatible(store, wide)
    message = str(info.value)
    assert "\n" not in message
    assert stored_id in message
    assert "camera scene: 640x480@30 vs 1280x720@30" in message


def test_check_compatible_ignores_incomplete_episodes(tmp_path: Path) -> None:
    store = EpisodeStore(tmp_path)
    draft = store.begin(rig="demo", task="pick", operator="alice")
    draft.abandon("test", {MANIFEST_KEY: rig_fingerprint(load_rig("demo")).to_json()})
    check_compatible(store, _demo(cameras__0__fps=15))
