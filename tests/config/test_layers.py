"""The rig schema sits low (issue 12): loading a rig file imports no layer above the components."""

from __future__ import annotations

import subprocess
import sys


def _telerig_packages_after(code: str) -> set[str]:
    """The telerig packages (``telerig.<name>``) a fresh interpreter has imported after ``code``."""
    probe = (
        "import sys\n"
        f"{code}\n"
        "print(' '.join(sorted({m.split('.')[1] for m in sys.modules if m.startswith('telerig.')})))\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_the_rig_schema_imports_only_errors_priority_thread_names_ir_and_the_registry() -> None:
    loaded = _telerig_packages_after("import telerig.config")
    assert loaded <= {"config", "errors", "priority", "thread_names", "ir", "registry"}, loaded


def test_loading_every_shipped_rig_imports_no_safety_record_store_or_runtime() -> None:
    # Resolving each component's `type` imports its config module; those must stay on their layer.
    loaded = _telerig_packages_after(
        "from telerig.config import load_rig, shipped_rigs\nfor name in shipped_rigs(): load_rig(name)"
    )
    assert "devices" in loaded
    assert not loaded & {"safety", "record", "store", "runtime", "cli"}, loaded
