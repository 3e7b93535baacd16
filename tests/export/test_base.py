"""The export run every format shares (refuse other rigs, append) and its atomic metadata write."""

from __future__ import annotations

import json
import os
import shutil
import stat
from pathlib import Path

import pytest

from telerig.errors import ExportError
from telerig.export.base import write_atomic
from telerig.export.run import EpisodeFilter, build_exporter, export
from telerig.store.episodes import EpisodeStore


def test_write_atomic_respects_the_umask(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        write_atomic(tmp_path / "meta.json", "{}")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "meta.json").stat().st_mode) == 0o644
    assert (tmp_path / "meta.json").read_text() == "{}"
    assert [p.name for p in tmp_path.iterdir()] == ["meta.json"]


# --- the export run ------------------------------------------------------------------------------------


@pytest.fixture
def two_rigs(demo_recording: Path, tmp_path: Path) -> tuple[Path, str, str]:
    """A copy of the demo recording whose second episode claims another rig fingerprint."""
    root = tmp_path / "data"
    shutil.copytree(demo_recording, root)
    first, second = (e.id for e in EpisodeStore(root).list(include_failures=True))
    path = EpisodeStore(root).episode_dir(second)
    manifest = json.loads((path / "manifest.json").read_text())
    manifest["extra"]["fingerprint"]["digest"] = "0123456789abcdef"
    (path / "manifest.json").write_text(json.dumps(manifest))
    return root, first, second


def test_episodes_of_another_rig_never_join_a_dataset(
    two_rigs: tuple[Path, str, str], tmp_path: Path
) -> None:
    root, first, second = two_rigs
    out = tmp_path / "dataset"
    selection = EpisodeFilter(ids=(first,), include_failures=True)
    assert export(root, "hdf5", out, selection=selection).added == (first,)
    with pytest.raises(ExportError, match=r"fingerprint is .*another --out directory"):
        export(root, "hdf5", out, selection=EpisodeFilter(ids=(second,), include_failures=True))
    assert build_exporter("hdf5").existing_episodes(out) == {first}


def test_re_running_an_export_appends_only_new_episodes(
    two_rigs: tuple[Path, str, str], tmp_path: Path
) -> None:
    root, first, _ = two_rigs
    out = tmp_path / "dataset"
    selection = EpisodeFilter(ids=(first,), include_failures=True)
    export(root, "hdf5", out, selection=selection)
    again = export(root, "hdf5", out, selection=selection)
    assert (again.added, again.skipped, again.episodes_total) == ((), (first,), 1)


def test_an_unknown_format_names_the_registered_ones() -> None:
    with pytest.raises(ExportError, match="lerobot") as info:
        build_exporter("csv")
    assert "\n" not in str(info.value)
