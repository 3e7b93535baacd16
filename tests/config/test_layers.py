"""The rig schema sits low (issue 12): importing it loads only the layers below it, not safety or bus."""

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


def test_the_rig_schema_imports_only_errors_ir_and_the_registry() -> None:
    loaded = _telerig_packages_after("import telerig.config")
    assert loaded <= {"config", "errors", "ir", "registry"}, loaded
