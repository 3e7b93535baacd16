"""Creates the markerless tracker's venv (MediaPipe pins numpy<2 and protobuf<5; telerig cannot)."""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from telerig.errors import DependencyError

__all__ = ["TRACKER_REQUIREMENTS", "ensure_tracker_venv", "main"]

#: Exact versions the tracker is tested with (MediaPipe's models ship inside its wheel).
TRACKER_REQUIREMENTS: tuple[str, ...] = (
    "mediapipe==0.10.21",
    "av==18.1.0",
    "numpy==1.26.4",
    "protobuf==4.25.9",
    "opencv-contrib-python==4.11.0.86",
)


def ensure_tracker_venv(path: Path = Path(".venv-markerless"), python: str | None = None) -> Path:
    """Create ``path`` (if needed) with :data:`TRACKER_REQUIREMENTS`; return its interpreter.

    ``python`` is the base interpreter (3.9 to 3.12, which mediapipe 0.10.21 has wheels for);
    default: the one running telerig.

    Raises:
        DependencyError: If the venv cannot be created or pip fails.
    """
    interpreter = path / "bin" / "python"
    base = python or sys.executable
    try:
        if not interpreter.exists():
            subprocess.run([base, "-m", "venv", str(path)], check=True)
        subprocess.run(
            [
                str(interpreter),
                "-m",
                "pip",
                "install",
                "--disable-pip-version-check",
                "-q",
                *TRACKER_REQUIREMENTS,
            ],
            check=True,
        )
    except (OSError, subprocess.CalledProcessError) as exc:
        raise DependencyError(
            f"could not create the markerless tracker venv {path}: {exc}; "
            f"try `{base} -m venv {path} && {interpreter} -m pip install {' '.join(TRACKER_REQUIREMENTS)}`"
        ) from None
    return interpreter


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m telerig.devices.markerless.install [--venv PATH] [--python PY]``."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--venv", type=Path, default=Path(".venv-markerless"))
    parser.add_argument("--python", default=shutil.which("python3.11") or sys.executable)
    args = parser.parse_args(argv)
    try:
        interpreter = ensure_tracker_venv(args.venv, args.python)
    except DependencyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"markerless tracker ready: {interpreter}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
