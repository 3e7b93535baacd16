"""Runtime tests run rigs as ``telerig run`` does: with the process settings of a control process."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from telerig.runtime.process_settings import control_process


@pytest.fixture(scope="session", autouse=True)
def _control_process() -> Iterator[None]:
    """The 1 ms GIL switch interval and the kept C heap the entry points apply (RigRuntime does not).
    Without the frozen heap: the session opens a hundred rigs, whose objects must not outlive them."""
    with control_process(freeze_after_start=False):
        yield
