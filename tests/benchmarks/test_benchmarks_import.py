"""Every script in benchmarks/ imports against the installed telerig and its dependencies.

``make bench`` runs them; the suite does not (they take minutes), so an import that a refactor
broke (a renamed module, a dependency swapped for another) went unnoticed until someone ran
them: ``dashboard.py`` still imported ``httpx`` after the project moved to ``httpx2``. One fresh
interpreter imports them all (their module-level code sets environment variables and
``sys.path``), and names each one that fails with its error.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"

_IMPORT_ALL = """
import importlib.util, sys
failed = []
for path in sys.argv[1:]:
    name = path.rsplit("/", 1)[-1][:-3]
    try:
        spec = importlib.util.spec_from_file_location("bench_" + name, path)
        module = sys.modules[spec.name] = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except BaseException as exc:
        failed.append(f"{name}: {type(exc).__name__}: {exc}")
print("\\n".join(failed))
sys.exit(1 if failed else 0)
"""


def test_every_benchmark_script_imports() -> None:
    scripts = sorted(str(p) for p in BENCHMARKS.glob("*.py"))
    assert len(scripts) > 30
    done = subprocess.run(
        [sys.executable, "-c", _IMPORT_ALL, *scripts],
        cwd=BENCHMARKS,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, f"benchmarks that do not import:\n{done.stdout}{done.stderr[-2000:]}"
