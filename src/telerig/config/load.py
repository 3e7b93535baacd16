"""Loading rig files: YAML → validated :class:`RigConfig`, with one-line errors that name the fix."""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from telerig.config.schema import RigConfig
from telerig.errors import ConfigError
from telerig.registry import format_validation_error

__all__ = ["load_rig", "parse_rig", "shipped_rig_path", "shipped_rigs"]


def parse_rig(data: Any, *, source: str = "<rig>") -> RigConfig:
    """Validate an already-parsed mapping; raises :class:`ConfigError` with ``source: field: reason``."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: a rig file must be a mapping with name, devices, robots and bindings")
    try:
        return RigConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{source}: {format_validation_error(exc, model=RigConfig)}") from None


def load_rig(path: str | Path) -> RigConfig:
    """Load a rig by file path, or by the name of a shipped rig (e.g. ``"demo"``)."""
    p = Path(path)
    if not p.exists():
        if p.suffix == "" and str(path) in shipped_rigs():
            p = shipped_rig_path(str(path))
        else:
            raise ConfigError(f"rig file {str(path)!r} not found. Shipped rigs: {', '.join(shipped_rigs())}")
    text = _read_text(p)
    try:
        data = yaml.safe_load(text)
    except yaml.reader.ReaderError as exc:
        # A character YAML refuses (NUL, other control characters): the reader knows only the offset.
        line = text.count("\n", 0, exc.position) + 1
        raise ConfigError(
            f"{p}: line {line}: invalid YAML: unacceptable character #x{exc.character:04x} "
            f"({exc.reason}); remove it"
        ) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{p}:{where}: invalid YAML: {problem}") from None
    return parse_rig(data, source=str(p))


def _read_text(path: Path) -> str:
    """The file's text; a one-line :class:`ConfigError` for a directory, an unreadable or non-UTF-8 file."""
    if path.is_dir():
        raise ConfigError(f"{path}: is a directory; give the path of a rig file (.yaml) inside it")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the rig file: {exc.strerror or exc}") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise ConfigError(
            f"{path}: line {line}: not UTF-8 text (byte 0x{raw[exc.start]:02x}); save the file as UTF-8"
        ) from None


def shipped_rigs() -> list[str]:
    """Names of the example rigs that ship inside the package."""
    root = resources.files("telerig.config") / "rigs"
    return sorted(f.name.removesuffix(".yaml") for f in root.iterdir() if f.name.endswith(".yaml"))


def shipped_rig_path(name: str) -> Path:
    """Path of a shipped rig file."""
    path = Path(str(resources.files("telerig.config") / "rigs" / f"{name}.yaml"))
    if not path.exists():
        raise ConfigError(f"no shipped rig {name!r}. Shipped rigs: {', '.join(shipped_rigs())}")
    return path
