"""One registry per extension point: ``type`` name → config model, plus entry points for plug-ins.

A config model knows how to build its component (``config.build(...)``), so the
registry only maps names to config classes. Built-in types register when their
config module is imported; third-party packages register through the entry point
groups ``telerig.devices``, ``telerig.robots``, ``telerig.cameras``,
``telerig.retargeters``, ``telerig.exporters``, ``telerig.hand_detectors`` and ``telerig.segmenters``
(each entry point names a config class).
"""

from __future__ import annotations

import importlib
import importlib.metadata
import pkgutil
import threading
import typing
from pathlib import Path
from typing import Any, Generic, TypeVar

from pydantic import BaseModel, ValidationError

__all__ = [
    "CAMERAS",
    "DEVICES",
    "EXPORTERS",
    "HAND_DETECTORS",
    "PROCESS_STAGES",
    "RETARGETERS",
    "ROBOTS",
    "SEGMENTERS",
    "Registry",
    "StageRegistry",
    "format_validation_error",
]

C = TypeVar("C", bound=BaseModel)


class Registry(Generic[C]):
    """Maps a component ``type`` name to its config class.

    Built-in types are found by importing ``<package>.config`` and the ``config``
    module of every subpackage (one folder per family, its config next to it); a plain module
    (not a package) as ``builtin_package`` is imported itself.
    """

    def __init__(self, kind: str, builtin_package: str, entry_point_group: str) -> None:
        self.kind = kind
        self._package = builtin_package
        self._group = entry_point_group
        self._types: dict[str, type[C]] = {}
        self._loaded = False
        self._lock = threading.Lock()

    def register(self, config_cls: type[C]) -> type[C]:
        """Class decorator: register ``config_cls`` under the default of its ``type`` field."""
        default = config_cls.model_fields["type"].default
        if not isinstance(default, str) or not default:
            raise TypeError(f"{config_cls.__name__} needs a `type: Literal[...] = '<name>'` field")
        existing = self._types.get(default)
        if existing is not None and existing is not config_cls:
            raise ValueError(f"{self.kind} type {default!r} is registered twice ({existing.__name__})")
        self._types[default] = config_cls
        return config_cls

    def names(self) -> list[str]:
        """Sorted registered type names."""
        self._load()
        return sorted(self._types)

    def get(self, name: str) -> type[C]:
        """The config class for ``name``; ``KeyError`` with the valid names otherwise."""
        self._load()
        try:
            return self._types[name]
        except KeyError:
            raise KeyError(f"unknown {self.kind} type {name!r}. Valid: {', '.join(self.names())}") from None

    def parse_config(self, raw: Any, where: str) -> Any:
        """Validate one raw mapping into its registered config; ``ValueError`` with a one-line reason."""
        if isinstance(raw, BaseModel):
            return raw
        if not isinstance(raw, dict):
            raise ValueError(f"{where}: expected a mapping with a 'type' key, got {type(raw).__name__}")
        name = raw.get("type")
        if name is None:
            raise ValueError(f"{where}.type: missing. Valid: {', '.join(self.names())}")
        try:
            cls = self.get(str(name))
        except KeyError as exc:
            raise ValueError(f"{where}.type: {exc.args[0]}") from None
        try:
            return cls.model_validate(raw)
        except ValidationError as exc:
            raise ValueError(format_validation_error(exc, prefix=where, model=cls)) from None

    def _load(self) -> None:
        if self._loaded:
            return
        with self._lock:
            if self._loaded:
                return
            for module in _config_modules(self._package):
                importlib.import_module(module)
            for ep in importlib.metadata.entry_points(group=self._group):
                self.register(ep.load())
            self._loaded = True


def _config_modules(package: str) -> list[str]:
    # Looks at files rather than importing subpackages: a family's __init__ may import heavy
    # optional dependencies that loading a rig file must not need.
    pkg = importlib.import_module(package)
    if not hasattr(pkg, "__path__"):
        return [package]
    modules = []
    for root in pkg.__path__:
        for info in pkgutil.iter_modules([root]):
            if info.name == "config":
                modules.append(f"{package}.config")
            elif info.ispkg and (Path(root) / info.name / "config.py").is_file():
                modules.append(f"{package}.{info.name}.config")
    return sorted(modules)


def format_validation_error(
    exc: ValidationError, prefix: str = "", model: type[BaseModel] | None = None
) -> str:
    """One line for the first error: ``field.path: what is wrong`` (pydantic lists valid choices).

    ``model`` is the class that was validated: an unknown field then lists the valid ones. Without
    it, the registered component configs are searched by the error's title.
    """
    err = exc.errors(include_url=False)[0]
    msg = str(err["msg"])
    if msg.startswith("Value error, "):
        msg = msg.removeprefix("Value error, ")
    parts: list[str] = [prefix] if prefix else []
    for item in err["loc"]:
        if isinstance(item, int):
            if parts:
                parts[-1] += f"[{item}]"
            else:
                parts.append(f"[{item}]")
        else:
            parts.append(str(item))
    loc = ".".join(parts)
    if err["type"] == "extra_forbidden":
        return f"{loc}: unknown field{_valid_fields(exc, model)}"
    # Messages raised by our own validators start with their own field path; join it to ours.
    head = parts[-1].split("[")[0] if parts else ""
    if head and (msg.startswith(head + ".") or msg.startswith(head + "[") or msg.startswith(head + ":")):
        return ".".join([*parts[:-1], msg]) if len(parts) > 1 else msg
    if head and msg.split(":")[0].split(".")[0].split("[")[0] == head:
        return msg
    got = err.get("input")
    suffix = ""
    if err["type"] != "missing" and not isinstance(got, dict | list):
        suffix = f" (got {got!r})"
    return f"{loc}: {msg}{suffix}" if loc else msg


def _valid_fields(exc: ValidationError, model: type[BaseModel] | None) -> str:
    cls = model if model is not None else _model_by_name(exc.title)
    for item in exc.errors(include_url=False)[0]["loc"][:-1]:
        if cls is None or isinstance(item, int):
            continue
        field = cls.model_fields.get(str(item))
        cls = _first_model(field.annotation) if field is not None else None
    return ". Valid fields: " + ", ".join(cls.model_fields) if cls is not None else ""


def _model_by_name(name: str) -> type[BaseModel] | None:
    for registry in (DEVICES, ROBOTS, CAMERAS, RETARGETERS, EXPORTERS, HAND_DETECTORS, SEGMENTERS):
        for cls in registry._types.values():
            if cls.__name__ == name:
                return cls
    return None


def _first_model(annotation: Any) -> type[BaseModel] | None:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _first_model(arg)
        if found is not None:
            return found
    return None


DEVICES: Registry[Any] = Registry("device", "telerig.devices", "telerig.devices")
ROBOTS: Registry[Any] = Registry("robot", "telerig.robots", "telerig.robots")
CAMERAS: Registry[Any] = Registry("camera", "telerig.cameras", "telerig.cameras")
RETARGETERS: Registry[Any] = Registry("retargeter", "telerig.retarget", "telerig.retargeters")
EXPORTERS: Registry[Any] = Registry("exporter", "telerig.export", "telerig.exporters")
#: Hand detectors of the annotation pipeline's frame filter (``process.filter.detector``).
HAND_DETECTORS: Registry[Any] = Registry("hand detector", "telerig.process.hands", "telerig.hand_detectors")
#: Temporal action segmenters of the annotation pipeline (``process.segment.robot`` / ``.video``).
SEGMENTERS: Registry[Any] = Registry("segmenter", "telerig.process.segmenters", "telerig.segmenters")


class StageRegistry:
    """Annotation pipeline stage name → the class that runs it (``module:Class``, built without
    arguments), imported only when a run asks for it; plug-ins add stages through the entry point
    group ``telerig.process_stages`` (each entry point names a stage class).

    Stages are not configs with a ``type`` (their settings live in ``process:``), so this maps names
    to import paths rather than config classes.
    """

    def __init__(self, builtins: dict[str, str], entry_point_group: str) -> None:
        self._paths = dict(builtins)
        self._group = entry_point_group
        self._loaded = False
        self._lock = threading.Lock()

    def names(self) -> list[str]:
        """Every stage name, built-in and plug-in, sorted."""
        self._load()
        return sorted(self._paths)

    def get(self, name: str) -> Any:
        """The stage class of ``name``; ``KeyError`` naming the valid stages otherwise."""
        self._load()
        path = self._paths.get(name)
        if path is None:
            raise KeyError(f"unknown pipeline stage {name!r}. Valid: {', '.join(self.names())}")
        module, _, attr = path.partition(":")
        return getattr(importlib.import_module(module), attr)

    def _load(self) -> None:
        if self._loaded:
            return
        with self._lock:
            if not self._loaded:
                for ep in importlib.metadata.entry_points(group=self._group):
                    self._paths.setdefault(ep.name, ep.value)
                self._loaded = True


#: The annotation pipeline's stages (``telerig process --stages``); the default pipeline runs them
#: in the order of ``telerig.process.stage.STAGE_ORDER``: filter, segment, clips, annotate, layout.
PROCESS_STAGES = StageRegistry(
    {
        "filter": "telerig.process.filter:FilterStage",
        "segment": "telerig.process.segment:SegmentStage",
        "clips": "telerig.process.clips:ClipsStage",
        "annotate": "telerig.process.annotate:AnnotateStage",
        "layout": "telerig.process.layout:LayoutStage",
    },
    "telerig.process_stages",
)
