"""Shared fixture of the benchmark tests: load a script of ``benchmarks/`` as a module.

The scripts are not a package and the suite imports with ``--import-mode=importlib``, so a test reaches
a script's functions through ``load_benchmark("soak")``. Each script is loaded once per process and
registered under its own name in ``sys.modules``: its dataclasses look their module up by name, and a
script that imports another by name (``soak`` imports ``gc_pauses``) then shares the same module.
"""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def _load(name: str) -> ModuleType:
    loaded = sys.modules.get(name)
    if loaded is not None and Path(getattr(loaded, "__file__", "") or "") == BENCHMARKS / f"{name}.py":
        return loaded
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    assert spec is not None, f"no benchmarks/{name}.py"
    assert spec.loader is not None, f"no benchmarks/{name}.py"
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module


@pytest.fixture(scope="session")
def load_benchmark() -> Callable[[str], ModuleType]:
    """``load_benchmark("soak")`` is ``benchmarks/soak.py`` as a module, loaded once."""
    return _load
