"""PostgreSQL is a required component of the suite: without it the index tests fail with the fix."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

_ROOT = Path(__file__).resolve().parents[2]
_INDEX_TESTS = _ROOT / "tests" / "store" / "test_index.py"
_PYTEST = (sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir", str(_ROOT))


@pytest.mark.slow
def test_missing_postgresql_fails_the_index_tests_with_the_fix(tmp_path: Path) -> None:
    env = {**os.environ, "TELERIG_PG_BIN": str(tmp_path / "no-postgres")}
    done = subprocess.run(
        [*_PYTEST, "-k", "test_open_creates_the_schema_and_reopens and postgresql", str(_INDEX_TESTS)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=120,
        check=False,
    )
    out = done.stdout + done.stderr
    assert done.returncode == 1, out
    assert "skipped" not in out
    assert "PostgreSQL server binaries (initdb, pg_ctl) not found: run `make sysdeps-test`" in out
