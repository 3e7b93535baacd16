"""The stage helpers: provenance round trip and its refusal of damaged files, atomic writes."""

from __future__ import annotations

from pathlib import Path

import pytest

from telerig.errors import ProcessError
from telerig.process.stage import (
    Provenance,
    provenance_key,
    read_provenance,
    settings_hash,
    video_item_id,
    write_atomic,
    write_provenance,
)


def _prov(**over: object) -> Provenance:
    base: dict[str, object] = {
        "stage": "filter", "version": "1", "settings_hash": "s", "source_hash": "h", "upstream": {},
        "item_id": "x", "status": "ok", "outputs": ["kept.mp4"], "metrics": {"kept_fraction": 0.5},
        "started": "2026-01-01T00:00:00Z", "finished": "2026-01-01T00:00:01Z", "host": "h",
    }  # fmt: skip
    base.update(over)
    return Provenance.model_validate(base)


def test_provenance_round_trips_and_key_ignores_times(tmp_path: Path) -> None:
    write_provenance(tmp_path, _prov())
    back = read_provenance(tmp_path)
    assert back == _prov()
    assert provenance_key(_prov()) == provenance_key(_prov(finished="2027-01-01T00:00:00Z", host="o"))
    assert provenance_key(_prov()) != provenance_key(_prov(version="2"))


@pytest.mark.parametrize(
    "content", [b"", b"{", b"\xff\xfe garbage", b"[]", b'{"stage": 1}', b"[" * 100000, b" " * (2 << 20)]
)
def test_damaged_provenance_is_one_line_error(tmp_path: Path, content: bytes) -> None:
    (tmp_path / "provenance.json").write_bytes(content)
    with pytest.raises(ProcessError) as info:
        read_provenance(tmp_path)
    assert "\n" not in str(info.value)
    assert "provenance.json" in str(info.value)


def test_missing_provenance_is_none(tmp_path: Path) -> None:
    assert read_provenance(tmp_path) is None


def test_write_atomic_replaces_and_leaves_no_temp(tmp_path: Path) -> None:
    target = tmp_path / "a.json"
    write_atomic(target, "one")
    write_atomic(target, b"two")
    assert target.read_text() == "two"
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]
    with pytest.raises(ProcessError, match="cannot write"):
        write_atomic(tmp_path / "missing" / "a.json", "x")


def test_settings_hash_and_video_id_are_stable(tmp_path: Path) -> None:
    assert settings_hash({"a": 1, "b": [1, 2]}) == settings_hash({"b": [1, 2], "a": 1})
    assert settings_hash(None) != settings_hash({})
    vid = video_item_id(tmp_path / "v.mp4")
    assert vid.startswith("video-")
    assert len(vid) == 18
    assert vid == video_item_id(tmp_path / "." / "v.mp4")
