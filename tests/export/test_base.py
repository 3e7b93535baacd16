"""write_atomic: readers see the old content or the new, never a torn file; files are readable by the lab."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from telerig.export.base import write_atomic


def test_write_atomic_respects_the_umask(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        write_atomic(tmp_path / "meta.json", "{}")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "meta.json").stat().st_mode) == 0o644
    assert (tmp_path / "meta.json").read_text() == "{}"
    assert [p.name for p in tmp_path.iterdir()] == ["meta.json"]
